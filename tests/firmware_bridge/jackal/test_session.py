"""The live session over a real pseudo-terminal, against a simulated Jackal MCU.

`SimMcu` plays the MCU side of the rosserial recipe on the pty master: on a topic request it
sends a time request and a TopicInfo per publisher and subscriber (with unusual ids, so
nothing can be hard-coded), asks for the time every 0.3 s and, like the firmware (11 s there,
1 s here), stops publishing when no time reply came for a while. While configured it sends
Feedback at 50 Hz with known wheel travel, plus Status, IMU, NMEA, a type the host cannot
know, and some line noise. It records every byte the host writes, parsed by its own parser.

The host side is the real thing: pyserial on `os.ttyname(slave)`, `JackalSession`, and for
teleop a FIFO standing in for /dev/input/js0 carrying `struct js_event` records.
"""

from __future__ import annotations

import contextlib
import itertools
import os
import select
import statistics
import struct
import threading
import time
import tty
from dataclasses import dataclass, field

import pytest

from tests.helpers.rosserial import (
    feedback_bytes,
    imu_bytes,
    ros_frame,
    ros_header,
    sentence_bytes,
    status_bytes,
    topic_info_bytes,
)
from treetraits.drivers.records import WheelSample
from treetraits.errors import SourceError
from treetraits.firmware_bridge.jackal.records import (
    JackalFeedback,
    JackalImu,
    JackalMagnetometer,
    JackalNmea,
    JackalStatus,
    LinkEvent,
    SerialChunk,
)
from treetraits.firmware_bridge.jackal.session import JackalSession
from treetraits.firmware_bridge.jackal.teleop import TeleopConfig

FEEDBACK_MD5 = "3bdabb0ef46338ee5672d1b82220ab49"
STATUS_MD5 = "c851ebcf9a6e20b196bc7894e285b4f6"
IMU_MD5 = "6a62c6daae103f4ff57a132d6f95cec2"
MAG_MD5 = "2f3b0b43eed0c9501de0fa3ff89a45aa"
SENTENCE_MD5 = "9f221efc5f4b3bac7ce4af102b32308b"
DRIVE_MD5 = "601cf097cd47c174590c366c6ddd5fb3"
BOOL_MD5 = "8b94c1b53db61fb6aed406028ad6332a"

# The MCU's topics, with ids of its own choosing.
ID_FEEDBACK, ID_STATUS, ID_IMU, ID_MAG, ID_NMEA, ID_MYSTERY = 137, 101, 142, 119, 150, 171
ID_CMD_DRIVE, ID_WIFI = 163, 102
PUBLISHERS = [
    (ID_FEEDBACK, "feedback", "jackal_msgs/Feedback", FEEDBACK_MD5),
    (ID_STATUS, "status", "jackal_msgs/Status", STATUS_MD5),
    (ID_IMU, "imu/data_raw", "sensor_msgs/Imu", IMU_MD5),
    (ID_MAG, "imu/mag", "sensor_msgs/MagneticField", MAG_MD5),
    (ID_NMEA, "navsat/nmea_sentence", "nmea_msgs/Sentence", SENTENCE_MD5),
    (ID_MYSTERY, "diagnostics/secret", "acme_msgs/Secret", "5" * 32),
]
SUBSCRIBERS = [
    (ID_CMD_DRIVE, "cmd_drive", "jackal_msgs/Drive", DRIVE_MD5),
    (ID_WIFI, "wifi_connected", "std_msgs/Bool", BOOL_MD5),
]
NOISE = b"\x00\x13\xffnoise\xff"  # between frames now and then: no ff fe in it


def travel(k: int) -> tuple[float, float]:
    """Wheel travel in the k-th Feedback: exact in float32."""
    return k * 0.5, -k * 0.25


def split_frames(data: bytes, final: bool = True) -> tuple[list[tuple[int, bytes]], bytes, int]:
    """The test's own strict frame parser: (topic, payload) frames, the bytes that are not
    part of a valid frame (there must be none from the host), and how many bytes it used
    (with `final=False` it stops before a frame that may still be arriving)."""
    frames, junk, i = [], bytearray(), 0
    while i < len(data):
        if data[i : i + 2] == b"\xff\xfe":
            if not final and (
                i + 5 > len(data) or i + 8 + (data[i + 2] | data[i + 3] << 8) > len(data)
            ):
                break
            n = data[i + 2] | data[i + 3] << 8
            if (data[i + 2] + data[i + 3] + data[i + 4]) % 256 == 255 and i + 8 + n <= len(data):
                body = data[i + 5 : i + 8 + n]
                if sum(body) % 256 == 255:
                    frames.append((body[0] | body[1] << 8, bytes(body[2:-1])))
                    i += 8 + n
                    continue
        junk.append(data[i])
        i += 1
    return frames, bytes(junk), i


def parse_host_bytes(data: bytes) -> tuple[list[tuple[int, bytes]], bytes]:
    frames, junk, _ = split_frames(data)
    return frames, junk


@dataclass
class HostFrame:
    t: float  # monotonic, when the MCU read it
    topic: int
    payload: bytes


@dataclass
class SimMcu:
    master: int
    reply_timeout_s: float = 1.0
    time_request_s: float = 0.3
    received: bytearray = field(default_factory=bytearray)
    host_frames: list[HostFrame] = field(default_factory=list)
    sent_travel: list[tuple[float, float]] = field(default_factory=list)
    time_offsets_ns: list[int] = field(default_factory=list)
    configured: bool = False
    configurations: int = 0
    unconfigurations: int = 0
    last_feedback_t: float = 0.0

    def __post_init__(self):
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._buf = bytearray()
        self.next_feedback = 0.0
        os.set_blocking(self.master, False)  # a host that does not read must not stall us

    def start(self) -> SimMcu:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._receive(timeout=0.05)  # what the host wrote last (TX stop)

    def _receive(self, timeout: float) -> bool:
        try:
            ready, _, _ = select.select([self.master], [], [], timeout)
            data = os.read(self.master, 4096) if ready else b""
        except (OSError, ValueError):
            return False
        now = time.monotonic()  # after the read: a frame is never stamped before it arrived
        self.received += data
        self._buf += data
        frames, _, used = split_frames(bytes(self._buf), final=False)
        del self._buf[:used]
        for topic, payload in frames:
            self.host_frames.append(HostFrame(now, topic, payload))
            self._handle(topic, payload, now)
        return True

    def drives(self) -> list[tuple[float, int, float, float]]:
        out = []
        for f in self.host_frames:
            if f.topic == ID_CMD_DRIVE:
                mode, left, right = struct.unpack("<b2f", f.payload)
                out.append((f.t, mode, left, right))
        return out

    def _send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self.master, data)

    def _negotiate(self, now: float) -> None:
        self._send(ros_frame(10, bytes(8)))  # time request first, as the client does
        for topic_id, name, msg_type, md5 in PUBLISHERS:
            self._send(ros_frame(0, topic_info_bytes(topic_id, name, msg_type, md5, 512)))
        for topic_id, name, msg_type, md5 in SUBSCRIBERS:
            self._send(ros_frame(1, topic_info_bytes(topic_id, name, msg_type, md5, 512)))
        self.configured = True
        self.configurations += 1
        self.last_reply = now
        self.last_request = now
        self.next_feedback = now

    def _handle(self, topic: int, payload: bytes, now: float) -> None:
        if topic == 0 and not payload:
            self._negotiate(now)
        elif topic == 10 and len(payload) == 8:
            sec, nsec = struct.unpack("<II", payload)
            self.time_offsets_ns.append(sec * 1_000_000_000 + nsec - time.time_ns())
            self.last_reply = now
        elif topic == 11:
            self.configured = False

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            if not self._receive(timeout=0.002):
                return
            now = time.monotonic()
            if not self.configured:
                continue
            if now - self.last_reply > self.reply_timeout_s:
                self.configured = False  # the firmware drops back and stops publishing
                self.unconfigurations += 1
                continue
            if now - self.last_request >= self.time_request_s:
                self._send(ros_frame(10, bytes(8)))
                self.last_request = now
            if now >= self.next_feedback:
                self.next_feedback += 0.02
                k += 1
                left, right = travel(k)
                lf = (1.0, 0.5, 30.0, 28.0, 2.0, left, False)
                rf = (1.0, 0.5, 31.0, 29.0, 2.0, right, k % 50 == 0)
                frame = ros_frame(ID_FEEDBACK, feedback_bytes(seq=k, left=lf, right=rf))
                noise = NOISE if k % 7 == 0 else b""
                self._send(noise + frame)
                self.sent_travel.append((left, right))
                self.last_feedback_t = now
                if k % 10 == 0:
                    self._send(ros_frame(ID_STATUS, status_bytes(seq=k)))
                    self._send(ros_frame(ID_NMEA, sentence_bytes(b"$GPGGA,0*00", seq=k)))
                    self._send(ros_frame(ID_MYSTERY, b"\x01\x02\x03"))
                    mag = ros_header(k, 0, 0, "imu") + struct.pack("<12d", *range(12))
                    self._send(ros_frame(ID_MAG, mag))
                if k % 5 == 0:
                    self._send(ros_frame(ID_IMU, imu_bytes(seq=k)))


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)
    fds = {"master": master, "slave": slave}
    yield fds
    for fd in fds.values():
        with contextlib.suppress(OSError):
            os.close(fd)


def collect(session: JackalSession, seconds: float) -> list:
    items, deadline = [], time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        item = session.read(timeout=left)
        if item is not None:
            items.append(item)
    return items


def wait_for(predicate, timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not predicate():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.01)


def test_the_sim_mcu_stops_publishing_when_time_goes_unanswered(pty_pair):
    """The simulated MCU behaves like the firmware: without time replies, feedback stops.
    (So the session test below, where feedback keeps flowing, shows the host answers.)"""
    sim = SimMcu(pty_pair["master"]).start()
    try:
        slave = pty_pair["slave"]
        os.write(slave, ros_frame(0, b""))  # request topics, then never answer the time
        heard = bytearray()
        start = time.monotonic()
        while time.monotonic() - start < 1.6:
            if select.select([slave], [], [], 0.05)[0]:
                heard += os.read(slave, 4096)
        frames, _, _ = split_frames(bytes(heard))
        assert sim.configurations == 1 and sim.unconfigurations == 1
        assert sum(t == 0 for t, _ in frames) == len(PUBLISHERS)  # TopicInfo answers
        assert frames[0] == (10, bytes(8))  # the time request comes first
        assert 40 <= sum(t == ID_FEEDBACK for t, _ in frames) <= 60  # ~1 s at 50 Hz, then none
        assert time.monotonic() - sim.last_feedback_t > 0.4
    finally:
        sim.stop()


def test_session_learns_ids_answers_time_and_yields_wheel_travel(pty_pair):
    sim = SimMcu(pty_pair["master"]).start()
    session = JackalSession(os.ttyname(pty_pair["slave"]), required=("feedback", "status"))
    try:
        session.start()
        items = collect(session, 2.6)  # > 2x the simulated 1 s reply timeout
    finally:
        session.close()
        sim.stop()
    items += list(session)  # what was still queued when it closed

    # Ids were learned from the MCU's TopicInfo answers.
    protocol = session.protocol
    assert {i: info.name for i, info in protocol.publishers.items()} == {
        p[0]: p[1] for p in PUBLISHERS
    }
    assert protocol.subscribers["cmd_drive"].topic_id == ID_CMD_DRIVE
    events = [(e.state, e.detail) for e in items if isinstance(e, LinkEvent)]
    assert events[0][0] == "connected" and events[1][0] == "configured"

    # Time was answered, with the host's realtime clock, so the MCU never gave up.
    assert sim.configurations == 1 and sim.unconfigurations == 0
    assert protocol.stats.time_replies == protocol.stats.time_requests >= 8
    assert len(sim.time_offsets_ns) == protocol.stats.time_replies
    assert max(abs(off) for off in sim.time_offsets_ns) < 50_000_000

    # Wheel travel is exactly what the MCU sent, every sample, in order.
    samples = [s for s in items if isinstance(s, WheelSample)]
    assert [(s.left, s.right) for s in samples] == sim.sent_travel[: len(samples)]
    assert len(samples) >= len(sim.sent_travel) - 5 and len(samples) > 100
    assert all(s.unit == "rad" and s.left_velocity == 2.0 for s in samples)
    t_hosts = [s.t_host for s in samples]
    assert t_hosts == sorted(t_hosts) and abs(t_hosts[-1] - time.time_ns()) < 2e9
    feedback = [f for f in items if isinstance(f, JackalFeedback)]
    assert len(feedback) == len(samples)
    assert sum(f.driver_fault for f in feedback) == len(samples) // 50
    assert feedback[0].right.bridge_temperature == 31.0 and feedback[0].pcb_temperature == 38.5

    # The other topics decode; the unknown type is skipped and counted.
    assert any(isinstance(r, JackalStatus) and r.hardware_id == "c0ffee1" for r in items)
    assert any(isinstance(r, JackalImu) for r in items)
    assert any(isinstance(r, JackalNmea) and r.sentence == "$GPGGA,0*00" for r in items)
    mags = [r for r in items if isinstance(r, JackalMagnetometer)]
    assert mags and mags[0].field == (0.0, 1.0, 2.0) and mags[0].unit == "T"
    counters = session.counters()
    assert counters["unknown_type"] >= 1 and counters["md5_mismatch"] == 0
    assert counters["frame_skipped_bytes"] >= len(NOISE) * 10  # the noise, resynced past

    # Raw bytes for recording: every byte read, in order.
    raw = b"".join(c.data for c in items if isinstance(c, SerialChunk))
    assert counters["link_bytes_read"] == len(raw) == counters["frame_bytes"]

    # Every byte the host wrote is a frame: topic requests, time replies, a TX stop.
    frames, junk = parse_host_bytes(bytes(sim.received))
    assert junk == b""
    assert {t for t, _ in frames} <= {0, 10, 11}
    assert all(len(p) == 0 for t, p in frames if t in (0, 11))
    assert all(len(p) == 8 for t, p in frames if t == 10)
    assert frames[0] == (0, b"") and frames[-1] == (11, b"")
    assert not sim.drives()


def test_unplug_is_reported_and_does_not_spin(pty_pair):
    sim = SimMcu(pty_pair["master"]).start()
    session = JackalSession(os.ttyname(pty_pair["slave"]), reconnect_s=0.1, max_reconnect_s=0.4)
    try:
        session.start()
        wait_for(lambda: session.protocol.configured, 2.0, "configuration")
        sim.stop()
        os.close(pty_pair.pop("master"))  # the cable is pulled
        os.close(pty_pair.pop("slave"))
        deadline, lost = time.monotonic() + 2.0, None
        while lost is None and time.monotonic() < deadline:
            item = session.read(timeout=0.1)
            if isinstance(item, LinkEvent) and item.state == "disconnected":
                lost = item
        assert lost is not None, "the unplug was not reported"
        cpu, wall = time.process_time(), time.monotonic()
        collect(session, 1.5)
        cpu_share = (time.process_time() - cpu) / (time.monotonic() - wall)
        assert cpu_share < 0.2, f"{cpu_share:.0%} of a CPU while the MCU is gone: busy loop?"
        stats = session.link.stats
        assert stats.losses == 1 and stats.open_failures <= 8
    finally:
        t0 = time.monotonic()
        session.close()
        assert time.monotonic() - t0 < 2.5


def test_a_missing_port_fails_with_a_hint(tmp_path):
    session = JackalSession(str(tmp_path / "jackal"))
    with pytest.raises(SourceError, match=r"no such device.*plugged in"):
        session.start()
    session.close()


def test_a_second_owner_is_refused(pty_pair):
    first = JackalSession(os.ttyname(pty_pair["slave"])).start()
    try:
        with pytest.raises(SourceError, match="Only one process can own"):
            JackalSession(os.ttyname(pty_pair["slave"])).start()
    finally:
        first.close()


# --- teleop ----------------------------------------------------------------------------------

JS = struct.Struct("=IhBB")
BUTTON, AXIS, INIT = 0x01, 0x02, 0x80
DEADMAN, LINEAR = 4, 1


class FakeJoystick:
    """A FIFO with `struct js_event` records, opened read-write so the relay never sees end
    of file until `unplug()`."""

    def __init__(self, path):
        os.mkfifo(path)
        self.path = str(path)
        self.fd: int | None = os.open(path, os.O_RDWR)
        self.t0 = time.monotonic()
        self.last_write = 0.0

    def event(self, kind: int, number: int, value: int) -> None:
        assert self.fd is not None
        ms = int((time.monotonic() - self.t0) * 1000) & 0xFFFFFFFF
        os.write(self.fd, JS.pack(ms, value, kind, number))
        self.last_write = time.monotonic()

    def plug_in(self) -> None:
        for n in range(8):
            self.event(BUTTON | INIT, n, 0)
        for n in range(6):
            self.event(AXIS | INIT, n, 0)

    def hold(self, seconds: float, value: int = -32767) -> None:
        """Keep the stick alive (small wiggles every 40 ms), as a hand does."""
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.event(AXIS, LINEAR, value)
            value = value + 1 if value < -32000 else value - 1
            time.sleep(0.04)

    def unplug(self) -> None:
        assert self.fd is not None
        os.close(self.fd)
        self.fd = None
        self.last_write = time.monotonic()


def motion(drives, start: float, end: float):
    return [d for d in drives if start <= d[0] <= end and (d[2] != 0.0 or d[3] != 0.0)]


@pytest.mark.realtime
def test_teleop_relay_drives_only_with_the_deadman_and_stops_in_time(pty_pair, tmp_path):
    joystick = FakeJoystick(tmp_path / "js0")
    config = TeleopConfig(
        device=joystick.path,
        max_linear_mps=1.0,
        speed_limit_mps=0.4,
        silence_timeout_s=0.15,
        reopen_s=0.05,
    )
    limit = config.speed_limit_mps / config.wheel_radius_m
    sim = SimMcu(pty_pair["master"]).start()
    session = JackalSession(os.ttyname(pty_pair["slave"]), teleop=config)
    marks: dict[str, float] = {}
    try:
        joystick.plug_in()
        session.start()
        wait_for(lambda: session.protocol.configured, 2.0, "configuration")
        wait_for(lambda: session.relay.joystick.connected, 1.0, "the joystick")

        marks["no_deadman"] = time.monotonic()
        joystick.hold(0.4)  # full stick forward, dead-man not held
        marks["press"] = time.monotonic()
        joystick.event(BUTTON, DEADMAN, 1)
        joystick.hold(1.0)
        joystick.event(BUTTON, DEADMAN, 0)
        marks["release"] = joystick.last_write
        joystick.hold(0.6)  # stick still pushed after release: must not move

        marks["repress1"] = time.monotonic()
        joystick.event(BUTTON, DEADMAN, 1)
        joystick.hold(0.3)
        marks["silent"] = joystick.last_write  # the hand is still on the button; no events
        time.sleep(0.6)

        marks["repress2"] = time.monotonic()
        joystick.event(BUTTON, DEADMAN, 1)
        joystick.hold(0.3)
        joystick.unplug()
        marks["unplug"] = joystick.last_write
        time.sleep(0.6)
        marks["end"] = time.monotonic()
        relay_stats = session.relay.stats
    finally:
        session.close()
        sim.stop()

    drives = sim.drives()
    assert all(mode == 0 for _, mode, _, _ in drives)  # velocity mode, wheel rad/s
    assert all(abs(left) <= limit * (1 + 1e-6) and abs(right) <= limit * (1 + 1e-6)
               for _, _, left, right in drives)  # fmt: skip

    # Without the dead-man: no motion at all.
    assert not motion(drives, marks["no_deadman"], marks["press"])

    # Dead-man held: ~50 Hz, clamped to the speed limit (full stick asks for 1 m/s).
    held = motion(drives, marks["press"] + 0.1, marks["release"])
    rate = (len(held) - 1) / (held[-1][0] - held[0][0])
    assert 40 <= rate <= 60, rate
    assert 0.015 <= statistics.median(b[0] - a[0] for a, b in itertools.pairwise(held)) <= 0.025
    assert all(left == right == pytest.approx(limit, rel=1e-6) for _, _, left, right in held)

    # Release, silence, unplug: motion stops within 0.2 s, and explicit stops follow.
    for mark, until in (("release", "repress1"), ("silent", "repress2"), ("unplug", "end")):
        moving = motion(drives, marks[mark] - 0.1, marks[until])
        assert moving, f"not moving just before {mark}"
        assert moving[-1][0] - marks[mark] <= 0.2, (mark, moving[-1][0] - marks[mark])
        stops = [d for d in drives if marks[mark] <= d[0] <= marks[mark] + 0.4 and d[2] == 0.0]
        assert stops, f"no explicit stop after {mark}"
        assert all(d[2] == d[3] == 0.0 for d in drives if marks[mark] + 0.2 < d[0] < marks[until])
    assert relay_stats.disconnects >= 1
