"""Recording format v1 (`drivers.recording`): real MCAP files in tmp_path, no mocks.

Every check compares what the reader returns with what the test itself wrote, and the
contract's channel table is restated here (not imported) so the writer is held to it.
"""

from __future__ import annotations

import io
import json
import random
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import Writer

import treetraits
from tests.helpers.recordings import chunk_spans
from treetraits.drivers import recording as rec
from treetraits.errors import SourceError

# The contract's table, verbatim.
CONTRACT_ENCODINGS = {
    "/lidar/packets": "velodyne-data",
    "/lidar/telemetry": "velodyne-position",
    "/camera/jpeg": "jpeg",
    "/gnss/nmea": "nmea0183",
    "/wheels/jackal": "rosserial",
    "/wheels/bridge": "treetraits-bridge",
}
T0 = 1_717_000_000_000_000_000  # ns since the epoch, mid 2024
MAGIC = b"\x89MCAP0\r\n"

# (topic, log_time, publish_time as passed or None, expected publish_time, sequence, data)
Written = tuple[str, int, int | None, int, int, bytes]


def _as_tuple(message: rec.RecordedMessage) -> tuple[str, int, int, int, bytes]:
    return (message.topic, message.log_time, message.publish_time, message.sequence, message.data)


def _expected(written: list[Written], topics: set[str] | None = None) -> list[tuple]:
    return [
        (topic, log, publish, seq, data)
        for topic, log, _, publish, seq, data in written
        if topics is None or topic in topics
    ]


def _mixed_messages(rng: random.Random, count: int = 300) -> list[Written]:
    """Messages on all six topics, interleaved, with their expected sequence numbers."""
    makers = {
        "/lidar/packets": lambda: rng.randbytes(1206),
        "/lidar/telemetry": lambda: rng.randbytes(512),
        "/camera/jpeg": lambda: b"\xff\xd8" + rng.randbytes(rng.randrange(1000, 40_000)),
        "/gnss/nmea": lambda: b"$GNGGA,120000.00,4807.038,N,01131.000,E,4,12,0.9,545.4,M*47\r\n",
        "/wheels/jackal": lambda: b"\xff\xfe" + rng.randbytes(rng.randrange(0, 80)),
        "/wheels/bridge": lambda: rng.randbytes(rng.randrange(0, 64)),
    }
    topics = list(makers)
    sequences = dict.fromkeys(topics, 0)
    written: list[Written] = []
    for i in range(count):
        topic = topics[rng.randrange(len(topics))]
        log_time = T0 + i * 1_000_003
        # LiDAR and GNSS carry their own clock; the others fall back to the host time.
        if topic in ("/lidar/packets", "/lidar/telemetry", "/gnss/nmea"):
            publish = log_time - rng.randrange(0, 50_000_000)
            expected_publish = publish
        else:
            publish = None
            expected_publish = log_time
        written.append(
            (topic, log_time, publish, expected_publish, sequences[topic], makers[topic]())
        )
        sequences[topic] += 1
    # Edge cases: an empty payload and one larger than a chunk.
    for topic, data in (("/wheels/bridge", b""), ("/camera/jpeg", rng.randbytes(700_000))):
        log_time = T0 + count * 1_000_003
        written.append((topic, log_time, None, log_time, sequences[topic], data))
        sequences[topic] += 1
        count += 1
    return written


def _write(path: Path, written: list[Written], **options) -> None:
    with rec.RecordingWriter(path, **options) as writer:
        for topic, log_time, publish, _, _, data in written:
            writer.write(topic, data, log_time, publish)


def _read_all(path: Path, topics=None) -> tuple[list[tuple], rec.RecordingReader]:
    reader = rec.read_recording(path, topics)
    messages = [_as_tuple(m) for m in reader]
    return messages, reader


# --- writing and reading back --------------------------------------------------------------


def test_round_trip_all_six_topics(tmp_path):
    written = _mixed_messages(random.Random(1))
    assert {w[0] for w in written} == set(CONTRACT_ENCODINGS)
    path = tmp_path / "run.mcap"
    _write(path, written)

    messages, reader = _read_all(path)

    assert messages == _expected(written)
    assert reader.truncated is False


def test_file_follows_the_contract(tmp_path):
    """Read with mcap's own reader: schema-less channels with the contract's encodings,
    zstd chunks, the `treetraits` metadata record, exact times."""
    written = _mixed_messages(random.Random(2), count=120)
    path = tmp_path / "run.mcap"
    _write(path, written, calibration={"lidar": {"yaw_deg": 1.5}})

    with open(path, "rb") as f:
        reader = make_reader(f)
        got = [
            (ch.topic, ch.message_encoding, ch.schema_id, m.log_time, m.publish_time, m.data)
            for _, ch, m in reader.iter_messages(log_time_order=False)
        ]
    assert got == [
        (topic, CONTRACT_ENCODINGS[topic], 0, log, publish, data)
        for topic, log, _, publish, _, data in written
    ]

    with open(path, "rb") as f:
        records = list(StreamReader(f, emit_chunks=True).records)
    chunks = [r for r in records if isinstance(r, Chunk)]
    assert chunks and all(c.compression == "zstd" for c in chunks)
    metadata = [r for r in records if isinstance(r, Metadata) and r.name == "treetraits"]
    assert len(metadata) == 1
    fields = metadata[0].metadata
    assert fields["format_version"] == "1"
    assert fields["software"] == f"treetraits {treetraits.__version__}"
    assert json.loads(fields["calibration"]) == {"lidar": {"yaw_deg": 1.5}}


def test_metadata_calibration_and_field_map(tmp_path):
    calibration = {
        "lidar_to_base": {"xyz": [0.12, 0.0, 0.85], "rpy_deg": [0.0, -1.25, 90.0]},
        "camera": {"model": "Survey3N", "fx": 1234.5},
    }
    field_map = json.dumps({"type": "FeatureCollection", "features": []}).encode()
    path = tmp_path / "run.mcap"
    with rec.RecordingWriter(path, calibration=calibration) as writer:
        writer.attach("field_map.geojson", field_map, "application/geo+json", log_time=T0)
        writer.write("/gnss/nmea", b"$GNRMC*00\r\n", T0 + 1)

    reader = rec.read_recording(path)
    assert reader.metadata == rec.RecordingMetadata(
        "1", f"treetraits {treetraits.__version__}", calibration
    )
    attachment = reader.attachments["field_map.geojson"]
    assert (attachment.data, attachment.media_type, attachment.log_time) == (
        field_map,
        "application/geo+json",
        T0,
    )
    assert [_as_tuple(m) for m in reader] == [("/gnss/nmea", T0 + 1, T0 + 1, 0, b"$GNRMC*00\r\n")]


def test_no_calibration_is_an_empty_object(tmp_path):
    path = tmp_path / "run.mcap"
    with rec.RecordingWriter(path):
        pass
    reader = rec.read_recording(path)
    assert reader.metadata is not None
    assert reader.metadata.calibration == {}
    assert reader.attachments == {}
    assert list(reader) == []
    assert reader.truncated is False


def test_writer_to_a_stream(tmp_path):
    written = _mixed_messages(random.Random(3), count=50)
    buffer = io.BytesIO()
    with rec.RecordingWriter(buffer, chunk_size=4096) as writer:
        for topic, log_time, publish, _, _, data in written:
            writer.write(topic, data, log_time, publish)
    assert not buffer.closed
    path = tmp_path / "from_stream.mcap"
    path.write_bytes(buffer.getvalue())
    assert _read_all(path)[0] == _expected(written)


def test_unknown_topic_is_rejected(tmp_path):
    path = tmp_path / "run.mcap"
    with rec.RecordingWriter(path) as writer:
        writer.write("/lidar/packets", b"\x01" * 1206, T0)
        with pytest.raises(ValueError, match="/weather") as info:
            writer.write("/weather", b"{}", T0 + 1)
        for topic in CONTRACT_ENCODINGS:  # the message names what is allowed
            assert topic in str(info.value)
        writer.write("/lidar/packets", b"\x02" * 1206, T0 + 2)
    messages, reader = _read_all(path)
    assert messages == [
        ("/lidar/packets", T0, T0, 0, b"\x01" * 1206),
        ("/lidar/packets", T0 + 2, T0 + 2, 1, b"\x02" * 1206),
    ]
    assert not reader.truncated


def test_bad_times_and_data_are_rejected(tmp_path):
    with rec.RecordingWriter(tmp_path / "run.mcap") as writer:
        with pytest.raises(ValueError):
            writer.write("/gnss/nmea", b"$", -1)
        with pytest.raises(ValueError):
            writer.write("/gnss/nmea", b"$", T0, 1 << 64)
        with pytest.raises(TypeError):
            writer.write("/gnss/nmea", "$GNGGA", T0)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="closed"):
        writer.write("/gnss/nmea", b"$", T0)


def test_existing_file_is_not_overwritten(tmp_path):
    path = tmp_path / "run.mcap"
    path.write_bytes(b"yesterday")
    with pytest.raises(FileExistsError):
        rec.RecordingWriter(path)
    assert path.read_bytes() == b"yesterday"
    with rec.RecordingWriter(path, overwrite=True) as writer:
        writer.write("/gnss/nmea", b"$", T0)
    assert _read_all(path)[0] == [("/gnss/nmea", T0, T0, 0, b"$")]


def test_topic_filter_skips_other_topics(tmp_path):
    written = _mixed_messages(random.Random(4), count=200)
    path = tmp_path / "run.mcap"
    _write(path, written)
    wanted = {"/lidar/packets", "/gnss/nmea"}

    messages, reader = _read_all(path, topics=sorted(wanted))

    assert messages == _expected(written, wanted)
    assert {m[0] for m in messages} == wanted
    assert not reader.truncated


# --- other writers ---------------------------------------------------------------------


def _raw_recording(path: Path, *, version: str = "1", metadata: str = "front") -> list[tuple]:
    """A recording written with mcap's own writer, with an extra topic the contract does
    not know. `metadata`: "front", "end" (after the messages) or "none"."""
    rng = random.Random(5)
    written = []
    with open(path, "wb") as f:
        writer = Writer(f, chunk_size=2048)
        writer.start()
        fields = {"format_version": version, "software": "other 9", "calibration": "{}"}
        if metadata == "front":
            writer.add_metadata("treetraits", fields)
        lidar = writer.register_channel("/lidar/packets", "velodyne-data", 0)
        weather = writer.register_channel("/weather/station", "json", 0)
        for i in range(60):
            if i % 3 == 0:
                topic, channel, data = "/weather/station", weather, b'{"t": %d}' % i
            else:
                topic, channel, data = "/lidar/packets", lidar, rng.randbytes(1206)
            writer.add_message(channel, T0 + i, data, T0 + i - 7, sequence=100 + i)
            written.append((topic, T0 + i, T0 + i - 7, 100 + i, data))
        if metadata == "end":
            writer.add_metadata("treetraits", fields)
        writer.finish()
    return written


def test_unknown_topic_in_file_is_read_or_skipped(tmp_path):
    path = tmp_path / "raw.mcap"
    written = _raw_recording(path)

    everything, reader = _read_all(path)
    assert everything == written
    assert not reader.truncated
    assert reader.metadata == rec.RecordingMetadata("1", "other 9", {})

    lidar_only, reader = _read_all(path, topics=["/lidar/packets"])
    assert lidar_only == [w for w in written if w[0] == "/lidar/packets"]
    assert not reader.truncated


def test_metadata_after_the_messages_is_found(tmp_path):
    path = tmp_path / "raw.mcap"
    written = _raw_recording(path, metadata="end")
    messages, reader = _read_all(path)
    assert reader.metadata == rec.RecordingMetadata("1", "other 9", {})
    assert messages == written


@pytest.mark.parametrize("metadata", ["none", "front-v2"])
def test_wrong_or_missing_format_version_raises(tmp_path, metadata):
    path = tmp_path / "raw.mcap"
    if metadata == "none":
        _raw_recording(path, metadata="none")
    else:
        _raw_recording(path, version="2")
    with pytest.raises(SourceError, match=r"raw\.mcap"):
        rec.read_recording(path)


@pytest.mark.parametrize(
    "content",
    [
        b"not a recording at all, just text\n" * 10,
        b"\xd4\xc3\xb2\xa1" + bytes(100),
        b"\x89MCAP1\r\n",
    ],
    ids=["text", "pcap", "other-magic"],
)
def test_not_mcap_raises_source_error(tmp_path, content):
    path = tmp_path / "bogus.mcap"
    path.write_bytes(content)
    with pytest.raises(SourceError, match=r"bogus\.mcap.*MCAP"):
        rec.read_recording(path)


def test_missing_file_raises_source_error(tmp_path):
    with pytest.raises(SourceError, match=r"absent\.mcap"):
        rec.read_recording(tmp_path / "absent.mcap")


# --- power cuts and damage ----------------------------------------------------------------

PACKET = 1206
CHUNK_SIZE = 32 * 1024
PER_CHUNK = CHUNK_SIZE // PACKET + 1  # a chunk is closed once it exceeds chunk_size


@pytest.fixture(scope="module")
def long_recording(tmp_path_factory) -> tuple[Path, list[Written]]:
    """~2 MB of random (incompressible) 1206-byte packets in small chunks, plus the field
    map attached before them."""
    rng = random.Random(6)
    written: list[Written] = []
    for i in range(1700):
        topic = "/lidar/telemetry" if i % 50 == 49 else "/lidar/packets"
        seq = sum(1 for w in written if w[0] == topic)
        data = rng.randbytes(PACKET if topic == "/lidar/packets" else 512)
        written.append(
            (topic, T0 + i * 1_327_000, T0 + i * 1_327_000 - 11, T0 + i * 1_327_000 - 11, seq, data)
        )
    path = tmp_path_factory.mktemp("long") / "long.mcap"
    with rec.RecordingWriter(path, chunk_size=CHUNK_SIZE, calibration={"k": 1}) as writer:
        writer.attach("field_map.geojson", b'{"type": "FeatureCollection"}', "application/geo+json")
        for topic, log_time, publish, _, _, data in written:
            writer.write(topic, data, log_time, publish)
    assert path.stat().st_size > 2_000_000
    return path, written


def _damaged(source: Path, tmp_path: Path, cut: int, tail: bytes = b"") -> Path:
    path = tmp_path / f"cut_{cut}.mcap"
    path.write_bytes(source.read_bytes()[:cut] + tail)
    return path


@pytest.mark.parametrize("fraction", [0.6, 0.9, 0.999])
@pytest.mark.parametrize(
    "tail", [b"", bytes(4096), b"\xff" * 4096], ids=["cut", "zero-filled", "erased-flash"]
)
def test_power_cut_keeps_the_readable_prefix(long_recording, tmp_path, fraction, tail):
    source, written = long_recording
    size = source.stat().st_size
    cut = int(size * fraction)
    path = _damaged(source, tmp_path, cut, tail)

    messages, reader = _read_all(path)

    expected = _expected(written)
    # An exact prefix: every message returned is the one written at that position.
    assert messages == expected[: len(messages)]
    # All but at most the chunk in progress: a message takes at least size/len(written)
    # bytes of the file on average (the summary included), so at least this many fit.
    fit = cut * len(written) // size
    assert len(messages) >= min(fit, len(written)) - PER_CHUNK - 2
    assert len(messages) <= cut // 512  # the packets are incompressible
    assert reader.truncated is True
    # The metadata at the front and the field map survive.
    assert reader.metadata is not None and reader.metadata.calibration == {"k": 1}
    assert reader.attachments["field_map.geojson"].data == b'{"type": "FeatureCollection"}'


def test_cut_in_the_trailing_magic_keeps_every_message(long_recording, tmp_path):
    source, written = long_recording
    path = _damaged(source, tmp_path, source.stat().st_size - 3)
    messages, reader = _read_all(path)
    assert messages == _expected(written)
    assert reader.truncated is True


def test_complete_file_is_not_truncated(long_recording):
    source, written = long_recording
    messages, reader = _read_all(source, topics=["/lidar/telemetry"])
    assert messages == _expected(written, {"/lidar/telemetry"})
    assert reader.truncated is False


@pytest.mark.parametrize("cut", [0, 3, 8, 12, 40])
def test_cut_in_the_header_yields_nothing(long_recording, tmp_path, cut):
    source, _ = long_recording
    path = _damaged(source, tmp_path, cut)
    reader = rec.read_recording(path)
    assert list(reader) == []
    assert reader.truncated is True
    assert reader.metadata is None
    assert reader.attachments == {}


def test_garbage_length_after_the_header_is_not_a_memory_error(long_recording, tmp_path):
    """A record claiming 2**64-1 bytes right after the header is not allocated: it is
    damage, skipped to the next good record, and every message behind it is read."""
    source, written = long_recording
    data = source.read_bytes()
    with open(source, "rb") as f:
        records = StreamReader(f, emit_chunks=True).records
        next(records)  # the header
        header_end = f.tell()
    assert data[:8] == MAGIC
    path = tmp_path / "garbage.mcap"
    path.write_bytes(data[:header_end] + b"\x06" + b"\xff" * 8 + data[header_end:])
    messages, reader = _read_all(path)
    assert messages == _expected(written)
    assert reader.truncated is False and reader.metadata.calibration == {"k": 1}
    assert [(d.offset, d.resumed_at) for d in reader.damage] == [(header_end, header_end + 9)]
    assert reader.lost_data  # it cannot know that nothing was in the garbage


def test_corrupt_chunk_is_skipped_and_reading_goes_on(long_recording, tmp_path):
    """One flipped byte inside the compressed data of a chunk halfway: that chunk's
    messages are lost, every other chunk's are read, and the damage says which times."""
    source, written = long_recording
    data = bytearray(source.read_bytes())
    chunks = chunk_spans(source)
    start, end, chunk = chunks[len(chunks) // 2]
    data[end - 100] ^= 0x55  # inside the data of the middle chunk
    path = tmp_path / "flipped.mcap"
    path.write_bytes(bytes(data))

    messages, reader = _read_all(path)

    lost = range(chunk.message_start_time, chunk.message_end_time + 1)
    expected = [m for m in _expected(written) if m[1] not in lost]
    assert messages == expected and len(expected) < len(written) - PER_CHUNK + 2
    assert reader.damaged_chunks == 1 and reader.truncated is False and reader.lost_data
    (damage,) = reader.damage
    assert (damage.offset, damage.resumed_at) == (start, end)
    assert (damage.lost_from_ns, damage.lost_to_ns) == (lost[0], lost[-1])


def test_zeroed_chunk_frame_is_skipped_to_the_next_chunk(long_recording, tmp_path):
    """64 zero bytes over the start of a middle chunk (its opcode, length and times): the
    reader finds the next chunk by its frame and reads on to the end."""
    source, written = long_recording
    data = bytearray(source.read_bytes())
    chunks = chunk_spans(source)
    middle = len(chunks) // 2
    start, _, chunk = chunks[middle]
    data[start : start + 64] = bytes(64)
    path = tmp_path / "zeroed.mcap"
    path.write_bytes(bytes(data))

    messages, reader = _read_all(path)

    lost = range(chunk.message_start_time, chunk.message_end_time + 1)
    assert messages == [m for m in _expected(written) if m[1] not in lost]
    assert reader.damaged_chunks == 1 and reader.truncated is False
    (damage,) = reader.damage
    assert (damage.offset, damage.resumed_at) == (start, chunks[middle + 1][0])
    # Its header unreadable, the loss lies between the messages read around it.
    assert damage.lost_from_ns == chunks[middle - 1][2].message_end_time
    assert damage.lost_to_ns == chunks[middle + 1][2].message_start_time


def test_format_1_1_carries_the_motion_channels_and_format_1_refuses_them(tmp_path):
    from treetraits.drivers.recording.motion import decode_imu, encode_imu, encode_odometry

    odometry, imu = encode_odometry(0.5, -0.1), encode_imu((0.0, 0.01, -0.1), (0.2, 0.0, 9.81))
    with (
        rec.RecordingWriter(tmp_path / "v1.mcap") as writer,
        pytest.raises(ValueError, match=r"format 1\.1"),
    ):
        writer.write(rec.WHEELS_ODOMETRY, odometry, T0)
    assert rec.read_recording(tmp_path / "v1.mcap").metadata.format_version == "1"

    with rec.RecordingWriter(tmp_path / "v11.mcap", format_version="1.1") as writer:
        writer.write(rec.WHEELS_ODOMETRY, odometry, T0, T0 - 5)
        writer.write(rec.IMU_DATA, imu, T0 + 1)
    reader = rec.read_recording(tmp_path / "v11.mcap")
    assert reader.metadata.format_version == "1.1"
    messages = list(reader)
    assert [(m.topic, m.data, m.publish_time) for m in messages] == [
        (rec.WHEELS_ODOMETRY, odometry, T0 - 5),
        (rec.IMU_DATA, imu, T0 + 1),
    ]
    assert decode_imu(messages[1].data, T0).linear_acceleration == (0.2, 0.0, 9.81)
