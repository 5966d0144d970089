"""rosserial framing and the ROS 1 message layouts of the Jackal MCU.

Expected bytes are built independently of the code under test: frames with the two
checksums written out by hand, payloads with `struct` from the public .msg definitions
(tests/helpers/rosserial.py), and md5sums recomputed here from the .msg text with the
ROS 1 algorithm. Then:

- frames and messages decode exactly; the host's frames match literals built from the
  rosserial protocol description;
- bad length and data checksums, garbage between frames, truncated frames and a byte-by-byte
  feed all resync and lose no good frame;
- fuzz (hypothesis): the reader never raises, gives the same frames however the bytes are
  chunked, accounts for every byte; the protocol accounts for every frame.
"""

from __future__ import annotations

import hashlib
import random
import re
import struct

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.helpers.rosserial import (
    feedback_bytes,
    imu_bytes,
    ros_frame,
    ros_string,
    sentence_bytes,
    status_bytes,
    topic_info_bytes,
)
from treetraits.drivers.records import WheelSample
from treetraits.errors import ParseError
from treetraits.firmware_bridge.jackal import messages as m
from treetraits.firmware_bridge.jackal import rosserial as rs
from treetraits.firmware_bridge.jackal.records import (
    JackalFeedback,
    JackalImu,
    JackalNmea,
    JackalStatus,
)
from treetraits.firmware_bridge.jackal.session import JackalProtocol, decode_stream

FUZZ = settings(
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

# --- md5sums from the public .msg text (ROS 1 algorithm, genmsg compute_md5_text) -------------

MSG_TEXT = {
    "std_msgs/Header": "uint32 seq\ntime stamp\nstring frame_id",
    "std_msgs/Time": "time data",
    "std_msgs/String": "string data",
    "std_msgs/Bool": "bool data",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Vector3Stamped": "Header header\nVector3 vector",
    "sensor_msgs/Imu": """Header header
geometry_msgs/Quaternion orientation
float64[9] orientation_covariance # Row major about x, y, z axes
geometry_msgs/Vector3 angular_velocity
float64[9] angular_velocity_covariance # Row major about x, y, z axes
geometry_msgs/Vector3 linear_acceleration
float64[9] linear_acceleration_covariance # Row major x, y z""",
    "sensor_msgs/MagneticField": """Header header
geometry_msgs/Vector3 magnetic_field
float64[9] magnetic_field_covariance""",
    "nmea_msgs/Sentence": "# A message representing a single NMEA0183 sentence.\n"
    "Header header\nstring sentence",
    "jackal_msgs/DriveFeedback": """# Current flowing from battery into the MOSFET bridge.
float32 current
# Instantaneous duty cycle of MOSFET bridge.
float32 duty_cycle
# Temperatures measured in the MOSFET bridge and on the motor casing, in deg C.
float32 bridge_temperature
float32 motor_temperature
# Encoder data
float32 measured_velocity   # rad/s
float32 measured_travel     # rad
# True if the underlying driver chip reports a fault condition.
bool driver_fault""",
    "jackal_msgs/Feedback": """Header header
DriveFeedback[2] drivers
# Temperatures
float32 pcb_temperature
float32 mcu_temperature
int8 commanded_mode
int8 actual_mode""",
    "jackal_msgs/Drive": """# Command units dependent on the value of this field
int8 MODE_VELOCITY=0   # velocity command (rad/s of wheels)
int8 MODE_PWM=1        # proportion of full voltage command [-1.0..1.0]
int8 MODE_EFFORT=2     # torque command (Nm)
int8 MODE_NONE=-1      # no control, commanded values ignored.
int8 mode
# Units as above, +ve direction propels chassis forward.
int8 LEFT=0
int8 RIGHT=1
float32[2] drivers""",
    "jackal_msgs/Status": """Header header
# Commit of firmware source.
string hardware_id
duration mcu_uptime
duration connection_uptime
bool drivers_active
bool driver_external_stop_present
bool driver_external_stop_stopped
float32 measured_battery
float32 measured_12v
float32 measured_5v
float32 drive_current
float32 user_current
float32 computer_current
float32 total_current
float32 total_current_peak
float64 total_power_consumed""",
    "rosserial_msgs/TopicInfo": """# special topic_ids
uint16 ID_PUBLISHER=0
uint16 ID_SUBSCRIBER=1
uint16 ID_SERVICE_SERVER=2
uint16 ID_SERVICE_CLIENT=4
uint16 ID_PARAMETER_REQUEST=6
uint16 ID_LOG=7
uint16 ID_TIME=10
uint16 ID_TX_STOP=11
# The endpoint ID for this topic
uint16 topic_id
string topic_name
string message_type
# MD5 checksum for this message type
string md5sum
# size of the buffer message must fit in
int32 buffer_size""",
    "rosserial_msgs/Log": """uint8 ROSDEBUG=0
uint8 INFO=1
uint8 WARN=2
uint8 ERROR=3
uint8 FATAL=4
uint8 level
string msg""",
}
BUILTINS = {
    "bool", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
    "float32", "float64", "string", "time", "duration", "byte", "char",
}  # fmt: skip


def ros1_md5(name: str) -> str:
    package = name.split("/")[0]
    constants, fields = [], []
    for line in MSG_TEXT[name].splitlines():
        line = line.split("#")[0].strip()
        if not line:
            continue
        type_name, rest = line.split(None, 1)
        if "=" in rest:
            const, value = rest.split("=", 1)
            constants.append(f"{type_name} {const.strip()}={value.strip()}")
            continue
        base = re.sub(r"\[.*\]$", "", type_name)
        if base in BUILTINS:
            fields.append(f"{type_name} {rest.strip()}")
        else:
            full = "std_msgs/Header" if base == "Header" else base
            full = full if "/" in full else f"{package}/{full}"
            fields.append(f"{ros1_md5(full)} {rest.strip()}")
    return hashlib.md5("\n".join(constants + fields).encode()).hexdigest()


@pytest.mark.parametrize("name", sorted(m.TYPES))
def test_layout_md5_matches_the_public_definition(name):
    assert m.TYPES[name].md5 == ros1_md5(name)


def test_rosserial_md5s_and_the_notes_values():
    assert ros1_md5("rosserial_msgs/TopicInfo") == rs.TOPIC_INFO_MD5
    assert ros1_md5("rosserial_msgs/Log") == rs.LOG_MD5
    notes = {  # md5sums of the published jackal_msgs definitions
        "jackal_msgs/Feedback": "3bdabb0ef46338ee5672d1b82220ab49",
        "jackal_msgs/DriveFeedback": "8dd0b7a3cfa20cfc5c054ddd9763609b",
        "jackal_msgs/Drive": "601cf097cd47c174590c366c6ddd5fb3",
        "jackal_msgs/Status": "c851ebcf9a6e20b196bc7894e285b4f6",
        "sensor_msgs/Imu": "6a62c6daae103f4ff57a132d6f95cec2",
        "nmea_msgs/Sentence": "9f221efc5f4b3bac7ce4af102b32308b",
        "std_msgs/Bool": "8b94c1b53db61fb6aed406028ad6332a",
        "std_msgs/Time": "cd7166c74c552c311fbcc2fe5a7bc289",
    }
    for name, md5 in notes.items():
        assert ros1_md5(name) == md5 == m.TYPES[name].md5


# --- frames ----------------------------------------------------------------------------------


def test_host_frames_match_the_literals_in_the_notes():
    assert bytes.fromhex("ff fe 00 00 ff 00 00 ff") == rs.REQUEST_TOPICS
    assert bytes.fromhex("ff fe 00 00 ff 0b 00 f4") == rs.TX_STOP
    drive = rs.encode_frame(100, m.Drive(m.MODE_VELOCITY, 2.0, 2.0).encode())
    assert drive == bytes.fromhex("ff fe 09 00 f6 64 00 00 00 00 00 40 00 00 00 40 1b")
    assert ros_frame(100, struct.pack("<b2f", 0, 2.0, 2.0)) == drive


def test_time_reply_is_the_host_clock_as_std_msgs_time():
    t_ns = 1_700_000_123_456_789_012
    expected = ros_frame(10, struct.pack("<II", 1_700_000_123, 456_789_012))
    assert rs.time_reply(t_ns) == expected
    assert rs.decode_time(expected[7:-1]) == t_ns


@pytest.mark.parametrize("payload", [b"", b"\x00", b"\xff\xfe\xff\xfe", bytes(range(256)) * 3])
@pytest.mark.parametrize("topic", [0, 10, 101, 137, 0x1234, 0xFFFF])
def test_frames_round_trip_against_the_independent_encoder(topic, payload):
    raw = ros_frame(topic, payload)
    assert rs.encode_frame(topic, payload) == raw
    assert rs.decode_frame(raw) == rs.Frame(topic, payload)
    reader = rs.FrameReader(max_payload=1024)
    assert reader.push(raw) == [rs.Frame(topic, payload)]
    assert reader.stats.frames == 1 and reader.stats.skipped_bytes == 0 and reader.pending == 0


def test_decode_frame_names_what_is_wrong():
    good = ros_frame(137, b"abc")
    with pytest.raises(ParseError, match="sync"):
        rs.decode_frame(b"\xff\xff" + good[2:])
    with pytest.raises(ParseError, match="length checksum"):
        rs.decode_frame(good[:4] + bytes([good[4] ^ 1]) + good[5:])
    with pytest.raises(ParseError, match="data checksum"):
        rs.decode_frame(good[:-1] + bytes([good[-1] ^ 1]))
    with pytest.raises(ParseError, match="payload bytes"):
        rs.decode_frame(good + b"\x00")
    with pytest.raises(ParseError, match="at least"):
        rs.decode_frame(good[:5])


def test_checksum_errors_drop_only_the_bad_frame():
    a, b, c = ros_frame(101, b"first"), ros_frame(137, b"second"), ros_frame(142, b"third")
    bad_len = b[:4] + bytes([b[4] ^ 0x10]) + b[5:]
    bad_data = b[:9] + bytes([b[9] ^ 0x01]) + b[10:]
    reader = rs.FrameReader()
    frames = reader.push(a + bad_len + c + a + bad_data + c)
    assert [f.payload for f in frames] == [b"first", b"third", b"first", b"third"]
    assert reader.stats.bad_length_checksum == 1
    assert reader.stats.bad_data_checksum == 1
    assert reader.stats.skipped_bytes == 2 * len(b)


def test_garbage_between_frames_is_skipped_and_counted():
    frames = [ros_frame(100 + i, bytes([i]) * i) for i in range(10)]
    garbage = [b"", b"\x00", b"\xff", b"\xfe\xff", b"hello\xff\xff", b"\xff\xfe\x01"]
    stream = b"".join(g + f for g, f in zip(garbage * 2, frames, strict=False))
    reader = rs.FrameReader()
    got = reader.push(stream)
    assert [f.topic_id for f in got] == [100 + i for i in range(10)]
    assert reader.stats.skipped_bytes == len(stream) - sum(map(len, frames))


def test_truncated_frame_then_good_frames():
    good = ros_frame(137, feedback_bytes())
    for cut in (1, 2, 4, 5, 7, 20, len(good) - 1):
        reader = rs.FrameReader()
        got = reader.push(good[:cut] + good + good)
        assert [f.payload for f in got] == [feedback_bytes()] * 2, cut
        assert reader.stats.skipped_bytes == cut
        assert reader.pending == 0


def test_a_false_header_does_not_hide_the_frame_behind_it():
    good = ros_frame(137, b"payload")
    false_header = bytes([0xFF, 0xFE, 0x40, 0x00, 0xBF])  # valid length checksum, 64 bytes
    reader = rs.FrameReader()
    got = reader.push(false_header + good + bytes(100))
    assert got == [rs.Frame(137, b"payload")]
    assert reader.stats.bad_data_checksum == 1


def test_oversize_headers_are_rejected_at_once():
    reader = rs.FrameReader(max_payload=100)
    big = bytes([0xFF, 0xFE, 0x00, 0x10, 0xEF])  # 4096 bytes declared
    assert reader.push(big + ros_frame(101, b"x")) == [rs.Frame(101, b"x")]
    assert reader.stats.oversize == 1


def test_byte_by_byte_feed_gives_the_same_frames():
    rng = random.Random(4)
    stream = b"".join(
        rng.randbytes(rng.randrange(0, 6)).replace(b"\xff", b"\x00")
        + ros_frame(100 + i, rng.randbytes(i * 3))
        for i in range(30)
    )
    whole = rs.FrameReader()
    expected = whole.push(stream)
    reader = rs.FrameReader()
    got = [f for i in range(len(stream)) for f in reader.push(stream[i : i + 1])]
    assert got == expected and len(got) == 30
    assert reader.stats == whole.stats


# --- messages --------------------------------------------------------------------------------


def test_topic_info_decodes_and_encodes_like_the_definition():
    raw = topic_info_bytes(137, "feedback", "jackal_msgs/Feedback", m.FEEDBACK.md5, 512)
    info = rs.TopicInfo.decode(raw)
    assert info == rs.TopicInfo(137, "feedback", "jackal_msgs/Feedback", m.FEEDBACK.md5, 512)
    assert info.encode() == raw
    assert rs.TopicInfo.decode(topic_info_bytes(101, "/status", "t", "m")).name == "status"
    with pytest.raises(ParseError):
        rs.TopicInfo.decode(raw[:-1])
    with pytest.raises(ParseError):
        rs.TopicInfo.decode(raw + b"\x00")


def test_feedback_decodes_exactly():
    payload = feedback_bytes(frame_id="base_link")
    assert len(feedback_bytes()) == 76  # 76 bytes with an empty frame_id (the message layout)
    values = m.FEEDBACK.decode(payload)
    assert values["header"] == {
        "seq": 7,
        "stamp": 1_700_000_000_250_000_000,
        "frame_id": b"base_link",
    }
    left, right = values["drivers"]
    assert left == {
        "current": 1.5,
        "duty_cycle": 0.25,
        "bridge_temperature": 31.5,
        "motor_temperature": 29.0,
        "measured_velocity": 2.5,
        "measured_travel": 123.25,
        "driver_fault": False,
    }
    assert right["measured_travel"] == -45.5 and right["driver_fault"] is True
    assert values["pcb_temperature"] == 38.5 and values["mcu_temperature"] == 41.0
    assert (values["commanded_mode"], values["actual_mode"]) == (0, -1)
    assert m.FEEDBACK.encode(values) == payload
    with pytest.raises(ParseError):
        m.FEEDBACK.decode(payload[:-1])
    with pytest.raises(ParseError):
        m.FEEDBACK.decode(payload + b"\x00")


def test_drive_encodes_like_the_definition():
    drive = m.Drive(m.MODE_VELOCITY, 1.25, -3.5)
    assert drive.encode() == struct.pack("<b2f", 0, 1.25, -3.5)
    assert len(drive.encode()) == m.DRIVE_SIZE
    assert m.Drive.decode(drive.encode()) == drive


def announce(protocol: JackalProtocol, *infos: tuple) -> None:
    stream = b"".join(ros_frame(kind, topic_info_bytes(*info)) for kind, *info in infos)
    protocol.receive(stream, 0, 0.0)


STANDARD_TOPICS = (
    (0, 137, "feedback", "jackal_msgs/Feedback", m.FEEDBACK.md5),
    (0, 101, "status", "jackal_msgs/Status", m.STATUS.md5),
    (0, 142, "imu/data_raw", "sensor_msgs/Imu", m.IMU.md5),
    (0, 150, "navsat/nmea_sentence", "nmea_msgs/Sentence", m.NMEA_SENTENCE.md5),
    (0, 151, "nmea_text", "std_msgs/String", m.STRING.md5),
    (0, 170, "mystery", "acme_msgs/Secret", "0" * 32),
    (0, 171, "old_feedback", "jackal_msgs/Feedback", "f" * 32),
    (1, 163, "cmd_drive", "jackal_msgs/Drive", m.DRIVE.md5),
)


def test_protocol_decodes_each_topic_by_its_announced_type():
    protocol = JackalProtocol()
    announce(protocol, *STANDARD_TOPICS)
    stream = b"".join(
        [
            ros_frame(137, feedback_bytes()),
            ros_frame(101, status_bytes()),
            ros_frame(142, imu_bytes()),
            ros_frame(150, sentence_bytes(b"$GPGGA,1*00")),
            ros_frame(151, ros_string(b"$GPRMC,2*00\r\n")),
            ros_frame(170, b"whatever"),
            ros_frame(171, feedback_bytes()),
            ros_frame(199, b"unannounced"),
            ros_frame(7, b"\x02" + ros_string("motor warm")),
            ros_frame(10, bytes(8)),
        ]
    )
    records = protocol.receive(stream, 42, 1.0)
    kinds = [type(r).__name__ for r in records]
    assert kinds == [
        "WheelSample", "JackalFeedback", "JackalStatus", "JackalImu", "JackalNmea",
        "JackalNmea", "McuLog",
    ]  # fmt: skip
    sample, feedback, status, imu, nmea, text, log = records
    assert sample == WheelSample(
        t_host=42,
        left=123.25,
        right=-45.5,
        unit="rad",
        t_device_us=1_700_000_000_250_000,
        left_velocity=2.5,
        right_velocity=-2.0,
    )
    assert isinstance(feedback, JackalFeedback) and feedback.driver_fault
    assert feedback.right.bridge_temperature == 32.0 and feedback.actual_mode == -1
    assert isinstance(status, JackalStatus)
    assert status.hardware_id == "c0ffee1" and status.mcu_uptime_ns == 3600_000_000_500
    assert status.measured_battery == 26.5 and status.total_power_consumed == 12.125
    assert isinstance(imu, JackalImu) and imu.linear_acceleration == (0.1, 0.2, 9.80665)
    assert isinstance(nmea, JackalNmea) and nmea.sentence == "$GPGGA,1*00"
    assert text.sentence == "$GPRMC,2*00" and text.stamp_ns == 0
    assert (log.level_name, log.msg) == ("warn", "motor warm")
    s = protocol.stats
    assert (s.decoded, s.unknown_type, s.md5_mismatch, s.unknown_topic) == (5, 1, 1, 1)
    assert (s.logs, s.time_requests, s.time_replies, s.negotiation) == (1, 1, 1, 8)
    assert protocol.subscribers["cmd_drive"].topic_id == 163


def test_drive_is_refused_until_the_mcu_announces_cmd_drive_with_the_right_md5():
    protocol = JackalProtocol()
    assert protocol.drive_frame(m.STOP) is None
    announce(protocol, (1, 163, "cmd_drive", "jackal_msgs/Drive", "0" * 32))
    assert protocol.drive_frame(m.STOP) is None
    announce(protocol, (1, 163, "cmd_drive", "jackal_msgs/Drive", m.DRIVE.md5))
    assert protocol.drive_frame(m.STOP) == ros_frame(163, struct.pack("<b2f", 0, 0.0, 0.0))
    assert protocol.stats.drive_refused == 2


def test_topics_are_requested_again_until_the_required_ones_arrive():
    protocol = JackalProtocol(required=("feedback", "cmd_drive"), request_interval_s=1.0)
    protocol.connect(0.0)
    assert protocol.take_outgoing() == [bytes.fromhex("ff fe 00 00 ff 00 00 ff")]
    protocol.poll(0.5)
    assert protocol.take_outgoing() == []
    protocol.poll(1.0)
    assert protocol.take_outgoing() == [bytes.fromhex("ff fe 00 00 ff 00 00 ff")]
    announce(protocol, *STANDARD_TOPICS)
    assert protocol.configured
    protocol.poll(2.5)
    assert protocol.take_outgoing() == []


def test_a_silent_mcu_is_asked_for_topics_again():
    protocol = JackalProtocol(sync_timeout_s=5.0)
    protocol.connect(0.0)
    protocol.receive(ros_frame(0, topic_info_bytes(*STANDARD_TOPICS[0][1:])), 0, 0.1)
    records = protocol.receive(ros_frame(10, bytes(8)), 0, 3.0)  # a time request: alive
    assert protocol.configured and records == []
    protocol.take_outgoing()
    protocol.poll(7.9)
    assert protocol.take_outgoing() == []
    protocol.poll(8.0)  # 5 s since the last time request
    assert protocol.take_outgoing() == [bytes.fromhex("ff fe 00 00 ff 00 00 ff")]
    assert protocol.stats.renegotiations == 1 and not protocol.configured


def test_a_travel_jump_is_counted():
    protocol = JackalProtocol()
    announce(protocol, *STANDARD_TOPICS)
    left = (1.0, 0.5, 30.0, 28.0, 2.0, 5000.0, False)
    protocol.receive(ros_frame(137, feedback_bytes()), 0, 0.0)
    protocol.receive(ros_frame(137, feedback_bytes()), 20_000_000, 0.02)
    assert protocol.stats.travel_jumps == 0
    protocol.receive(ros_frame(137, feedback_bytes(left=left)), 40_000_000, 0.04)
    assert protocol.stats.travel_jumps == 1


def test_decode_stream_replays_recorded_bytes():
    stream = b"".join(ros_frame(k, topic_info_bytes(*i)) for k, *i in STANDARD_TOPICS)
    stream += ros_frame(137, feedback_bytes()) * 3
    chunks = [(1000 + i, stream[i : i + 13]) for i in range(0, len(stream), 13)]
    samples = [r for r in decode_stream(chunks) if isinstance(r, WheelSample)]
    assert [(s.left, s.right) for s in samples] == [(123.25, -45.5)] * 3


# --- fuzz ------------------------------------------------------------------------------------

frames_strategy = st.lists(
    st.tuples(st.integers(0, 0xFFFF), st.binary(max_size=40)).map(lambda tp: ros_frame(*tp)),
    max_size=8,
)


@FUZZ
@given(
    pieces=st.lists(st.one_of(st.binary(max_size=30), frames_strategy.map(b"".join)), max_size=12),
    cuts=st.lists(st.integers(0, 400), max_size=10),
    max_payload=st.sampled_from([0, 16, 1024]),
)
def test_fuzz_reader_never_raises_and_accounts_for_every_byte(pieces, cuts, max_payload):
    stream = b"".join(pieces)
    whole = rs.FrameReader(max_payload)
    expected = whole.push(stream)
    reader = rs.FrameReader(max_payload)
    got = []
    start = 0
    for cut in [*sorted(c for c in cuts if c <= len(stream)), len(stream)]:
        got += reader.push(stream[start:cut])
        start = max(start, cut)
    assert got == expected  # chunking never changes the result
    s = reader.stats
    assert s == whole.stats
    assert s.bytes == len(stream) == s.framed_bytes + s.skipped_bytes + reader.pending
    assert s.frames == len(got)
    assert reader.pending <= max(max_payload + rs.OVERHEAD - 1, 1)


@FUZZ
@given(
    frames=st.lists(st.tuples(st.integers(0, 0xFFFF), st.binary(max_size=60)), max_size=10),
    noise=st.lists(st.binary(max_size=20).map(lambda b: b.replace(b"\xff", b"\x7f")), max_size=11),
)
def test_fuzz_frames_survive_noise_without_sync_bytes(frames, noise):
    """Noise with no 0xFF byte cannot start a false frame: every frame comes through."""
    stream = b"".join(
        (noise[i] if i < len(noise) else b"") + ros_frame(*f) for i, f in enumerate(frames)
    )
    reader = rs.FrameReader()
    got = [f for i in range(0, len(stream), 7) for f in reader.push(stream[i : i + 7])]
    assert got == [rs.Frame(t, p) for t, p in frames]


@FUZZ
@given(
    payloads=st.lists(
        st.tuples(st.sampled_from([0, 1, 2, 6, 7, 10, 11, 101, 137, 142, 150, 151, 170, 199]),
                  st.binary(max_size=120)),
        max_size=15,
    ),
    garbage=st.binary(max_size=200),
)  # fmt: skip
def test_fuzz_protocol_never_raises_and_accounts_for_every_frame(payloads, garbage):
    protocol = JackalProtocol()
    announce(protocol, *STANDARD_TOPICS)
    before = protocol.reader.stats.frames
    stream = garbage + b"".join(ros_frame(t, p) for t, p in payloads)
    protocol.receive(stream, 0, 0.0)
    s = protocol.stats
    counted = (
        s.negotiation + s.time_requests + s.logs + s.decoded + s.unknown_topic
        + s.unknown_type + s.md5_mismatch + s.ignored + s.malformed
    )  # fmt: skip
    assert counted - len(STANDARD_TOPICS) == protocol.reader.stats.frames - before
    assert s.time_replies == s.time_requests


@FUZZ
@given(st.sampled_from(sorted(m.TYPES)), st.binary(max_size=400))
def test_fuzz_layouts_raise_only_parse_error(name, payload):
    try:
        values = m.TYPES[name].decode(payload)
    except ParseError:
        return
    assert isinstance(values, dict)
