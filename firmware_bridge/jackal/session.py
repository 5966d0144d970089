"""The host side of a rosserial session with the Jackal MCU, without ROS.

`JackalProtocol` is the state machine, free of I/O: bytes and clock readings in, records and
frames to write out. It follows rosserial_server (docs/jackal.md, "Session"):

1. on connect, ask for topics (an empty frame on topic 0);
2. learn every topic id from the MCU's TopicInfo answers (publishers on 0, subscribers on 1);
   ids are never assumed. Ask again every `request_interval_s` until the `required` topics
   have all been announced, and again after `sync_timeout_s` without a time request or a
   TopicInfo (the MCU went quiet: reset, or dropped back to unconfigured);
3. answer every time request (topic 10) at once with the host's realtime clock: the MCU
   stops publishing if it hears no answer for 11 s;
4. decode the MCU's publishers by message type, only when the md5 it announced matches the
   layout we know; everything else is skipped and counted.

It writes nothing else. A Drive frame is built only on request (`drive_frame`), which only
the teleop relay makes, and only for a `cmd_drive` subscriber announced with the Drive md5.

`JackalSession` is the thin live shell: a reader thread on `SerialLink` that reopens the
port with backoff, answers time while the consumer is busy, and queues records for
`read()`/iteration; plus the optional `TeleopRelay`. `decode_stream` replays recorded bytes.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import asdict, dataclass

from treetraits.drivers.records import WheelSample
from treetraits.errors import ParseError, SourceError
from treetraits.firmware_bridge.jackal import messages as m
from treetraits.firmware_bridge.jackal import rosserial as rs
from treetraits.firmware_bridge.jackal.records import (
    DriveUnit,
    JackalFeedback,
    JackalImu,
    JackalMagnetometer,
    JackalNmea,
    JackalStatus,
    LinkEvent,
    McuLog,
    SerialChunk,
)
from treetraits.firmware_bridge.jackal.serial_link import (
    DEFAULT_BAUDRATE,
    DEFAULT_PORT,
    LinkLostError,
    SerialLink,
)
from treetraits.firmware_bridge.jackal.teleop import TeleopConfig, TeleopRelay

log = logging.getLogger(__name__)

DEFAULT_REQUIRED = ("feedback",)
DRIVE_TOPIC = "cmd_drive"
# A jump in measured_travel faster than this (plus a margin) cannot be wheel motion: the
# Jackal tops out near 20 rad/s (2 m/s); a jump means the MCU reset or wrapped its count.
MAX_WHEEL_RAD_S = 50.0
TRAVEL_JUMP_MARGIN_RAD = 5.0

Record = (
    WheelSample
    | JackalFeedback
    | JackalStatus
    | JackalImu
    | JackalMagnetometer
    | JackalNmea
    | McuLog
    | LinkEvent
)
Item = Record | SerialChunk


@dataclass
class SessionStats:
    """What the protocol saw and did. Every good frame lands in exactly one of the frame
    counters (`negotiation` .. `malformed`)."""

    # frames, by what became of them
    negotiation: int = 0  # TopicInfo answers (publishers and subscribers)
    time_requests: int = 0
    logs: int = 0
    decoded: int = 0  # user-topic frames turned into records
    unknown_topic: int = 0  # an id no TopicInfo announced (yet)
    unknown_type: int = 0  # a message type we have no layout for
    md5_mismatch: int = 0  # a known type announced with another md5: layout differs
    ignored: int = 0  # reserved ids we do not serve (services, parameters, ...)
    malformed: int = 0  # payload does not fit the announced layout
    # what was written
    topic_requests: int = 0
    time_replies: int = 0
    drive_frames: int = 0  # Drive frames built for the teleop relay
    drive_refused: int = 0  # no cmd_drive subscriber with the Drive md5 announced
    # derived
    renegotiations: int = 0  # sync_timeout_s without a sign of life: topics requested again
    travel_jumps: int = 0  # measured_travel jumped (MCU reset or wrap): see docs/jackal.md

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _header(values: dict) -> tuple[int, int, str]:
    header = values["header"]
    return header["seq"], header["stamp"], header["frame_id"].decode("utf-8", errors="replace")


def _vector(v: dict) -> tuple[float, float, float]:
    return (v["x"], v["y"], v["z"])


def _drive_unit(v: dict) -> DriveUnit:
    return DriveUnit(
        v["current"],
        v["duty_cycle"],
        v["bridge_temperature"],
        v["motor_temperature"],
        v["measured_velocity"],
        v["measured_travel"],
        v["driver_fault"],
    )


def feedback_record(topic: str, payload: bytes, t_host: int) -> JackalFeedback:
    values = m.FEEDBACK.decode(payload)
    seq, stamp, frame_id = _header(values)
    left, right = (_drive_unit(d) for d in values["drivers"])
    return JackalFeedback(
        t_host,
        topic,
        seq,
        stamp,
        frame_id,
        left,
        right,
        values["pcb_temperature"],
        values["mcu_temperature"],
        values["commanded_mode"],
        values["actual_mode"],
        payload,
    )


def wheel_sample(feedback: JackalFeedback) -> WheelSample:
    """Cumulative wheel travel (rad, as the MCU reports it) and wheel speeds (rad/s)."""
    return WheelSample(
        t_host=feedback.t_host,
        left=feedback.left.measured_travel,
        right=feedback.right.measured_travel,
        unit="rad",
        t_device_us=feedback.stamp_ns // 1000 if feedback.stamp_ns else None,
        left_velocity=feedback.left.measured_velocity,
        right_velocity=feedback.right.measured_velocity,
    )


def status_record(topic: str, payload: bytes, t_host: int) -> JackalStatus:
    v = m.STATUS.decode(payload)
    seq, stamp, frame_id = _header(v)
    return JackalStatus(
        t_host,
        topic,
        seq,
        stamp,
        frame_id,
        v["hardware_id"].decode("utf-8", errors="replace"),
        v["mcu_uptime"],
        v["connection_uptime"],
        v["drivers_active"],
        v["driver_external_stop_present"],
        v["driver_external_stop_stopped"],
        v["measured_battery"],
        v["measured_12v"],
        v["measured_5v"],
        v["drive_current"],
        v["user_current"],
        v["computer_current"],
        v["total_current"],
        v["total_current_peak"],
        v["total_power_consumed"],
        payload,
    )


def imu_record(topic: str, payload: bytes, t_host: int) -> JackalImu:
    v = m.IMU.decode(payload)
    seq, stamp, frame_id = _header(v)
    q = v["orientation"]
    return JackalImu(
        t_host,
        topic,
        seq,
        stamp,
        frame_id,
        (q["x"], q["y"], q["z"], q["w"]),
        v["orientation_covariance"],
        _vector(v["angular_velocity"]),
        v["angular_velocity_covariance"],
        _vector(v["linear_acceleration"]),
        v["linear_acceleration_covariance"],
        payload,
    )


def magnetic_field_record(topic: str, payload: bytes, t_host: int) -> JackalMagnetometer:
    v = m.MAGNETIC_FIELD.decode(payload)
    seq, stamp, frame_id = _header(v)
    field = _vector(v["magnetic_field"])
    cov = v["magnetic_field_covariance"]
    return JackalMagnetometer(t_host, topic, seq, stamp, frame_id, field, cov, "T", payload)


def vector3_stamped_record(topic: str, payload: bytes, t_host: int) -> JackalMagnetometer:
    v = m.VECTOR3_STAMPED.decode(payload)
    seq, stamp, frame_id = _header(v)
    return JackalMagnetometer(
        t_host, topic, seq, stamp, frame_id, _vector(v["vector"]), None, "", payload
    )


def sentence_record(topic: str, payload: bytes, t_host: int) -> JackalNmea:
    v = m.NMEA_SENTENCE.decode(payload)
    return JackalNmea(t_host, topic, v["header"]["stamp"], v["sentence"], payload)


def string_record(topic: str, payload: bytes, t_host: int) -> JackalNmea | None:
    """std_msgs/String carries NMEA only on a topic named for it; other strings are skipped."""
    if "nmea" not in topic.lower():
        return None
    return JackalNmea(t_host, topic, 0, m.STRING.decode(payload)["data"], payload)


# message type -> (layout, record builder). The layout's md5 must match the TopicInfo's.
DECODERS: dict[str, tuple[m.MessageType, Callable[[str, bytes, int], Record | None]]] = {
    m.FEEDBACK.name: (m.FEEDBACK, feedback_record),
    m.STATUS.name: (m.STATUS, status_record),
    m.IMU.name: (m.IMU, imu_record),
    m.MAGNETIC_FIELD.name: (m.MAGNETIC_FIELD, magnetic_field_record),
    m.VECTOR3_STAMPED.name: (m.VECTOR3_STAMPED, vector3_stamped_record),
    m.NMEA_SENTENCE.name: (m.NMEA_SENTENCE, sentence_record),
    m.STRING.name: (m.STRING, string_record),
}


class JackalProtocol:
    """The session state machine (no I/O). Call `connect` when the port opens, `receive` with
    every chunk read, `poll` now and then; write what `take_outgoing` returns, each frame in
    one write. `now` is monotonic seconds; `t_host` realtime ns; `clock_ns` gives the time
    sent in time replies."""

    def __init__(
        self,
        required: Iterable[str] = DEFAULT_REQUIRED,
        request_interval_s: float = 1.0,
        sync_timeout_s: float = 5.0,
        max_payload: int = rs.DEFAULT_MAX_PAYLOAD,
        clock_ns: Callable[[], int] = time.time_ns,
    ):
        self.required = frozenset(name.lstrip("/") for name in required)
        self.request_interval_s = request_interval_s
        self.sync_timeout_s = sync_timeout_s
        self.clock_ns = clock_ns
        self.reader = rs.FrameReader(max_payload)
        self.stats = SessionStats()
        self.publishers: dict[int, rs.TopicInfo] = {}  # the MCU's publishers, by id
        self.subscribers: dict[str, rs.TopicInfo] = {}  # the MCU's subscribers, by name
        self.configured = False
        self._outgoing: list[bytes] = []
        self._last_request = float("-inf")
        self._last_sync = 0.0
        self._warned: set[tuple[str, str]] = set()  # (topic, kind) already logged
        self._last_travel: dict[str, tuple[float, float, int]] = {}

    # --- driving the state machine --------------------------------------------------------

    def connect(self, now: float) -> None:
        """A fresh link: forget partial frames and announced topics, ask for topics."""
        self.reader.reset()
        self.publishers.clear()
        self.subscribers.clear()
        self.configured = False
        self._last_travel.clear()
        self._last_sync = now
        self._request_topics(now)

    def take_outgoing(self) -> list[bytes]:
        out, self._outgoing = self._outgoing, []
        return out

    def poll(self, now: float) -> None:
        """Timers: ask for topics again while required ones are missing, or after silence."""
        if now - self._last_sync >= self.sync_timeout_s:
            self.stats.renegotiations += 1
            self._last_sync = now
            self.configured = False
            self._request_topics(now)
        elif not self.configured and now - self._last_request >= self.request_interval_s:
            self._request_topics(now)

    def receive(self, data: bytes, t_host: int, now: float) -> list[Record]:
        records: list[Record] = []
        for frame in self.reader.push(data):
            self._handle(frame, t_host, now, records)
        if not self.configured and self.required <= self.announced:
            self.configured = True
            records.append(LinkEvent(t_host, "configured", ", ".join(sorted(self.announced))))
        return records

    def drive_frame(self, drive: m.Drive) -> bytes | None:
        """`drive` as a frame on the MCU's cmd_drive id, or None (and counted) if the MCU has
        not announced a cmd_drive subscriber with the Drive md5."""
        info = self.subscribers.get(DRIVE_TOPIC)
        if info is None or info.message_type != m.DRIVE.name or info.md5sum != m.DRIVE.md5:
            self.stats.drive_refused += 1
            return None
        self.stats.drive_frames += 1
        return rs.encode_frame(info.topic_id, drive.encode())

    @property
    def announced(self) -> set[str]:
        """Names of every topic the MCU announced since the last connect."""
        return {i.name for i in self.publishers.values()} | set(self.subscribers)

    # --- internals ------------------------------------------------------------------------

    def _request_topics(self, now: float) -> None:
        self._outgoing.append(rs.REQUEST_TOPICS)
        self._last_request = now
        self.stats.topic_requests += 1

    def _handle(self, frame: rs.Frame, t_host: int, now: float, out: list[Record]) -> None:
        topic_id = frame.topic_id
        if topic_id >= rs.FIRST_USER_ID:
            self._user_frame(frame, t_host, out)
        elif topic_id == rs.ID_TIME:
            self.stats.time_requests += 1
            self._last_sync = now
            self._outgoing.append(rs.time_reply(self.clock_ns()))
            self.stats.time_replies += 1
        elif topic_id in (rs.ID_PUBLISHER, rs.ID_SUBSCRIBER):
            try:
                info = rs.TopicInfo.decode(frame.payload)
            except ParseError as exc:
                self.stats.malformed += 1
                log.warning("jackal: unreadable TopicInfo: %s", exc)
                return
            if info.topic_id < rs.FIRST_USER_ID:
                self.stats.malformed += 1
                log.warning(
                    "jackal: TopicInfo for %r claims reserved id %d", info.name, info.topic_id
                )
                return
            self.stats.negotiation += 1
            self._last_sync = now
            if topic_id == rs.ID_PUBLISHER:
                self.publishers[info.topic_id] = info
            else:
                self.subscribers[info.name] = info
        elif topic_id == rs.ID_LOG:
            try:
                entry = rs.Log.decode(frame.payload)
            except ParseError:
                self.stats.malformed += 1
                return
            self.stats.logs += 1
            out.append(McuLog(t_host, entry.level, entry.level_name, entry.msg))
        else:
            self.stats.ignored += 1

    def _user_frame(self, frame: rs.Frame, t_host: int, out: list[Record]) -> None:
        info = self.publishers.get(frame.topic_id)
        if info is None:
            self.stats.unknown_topic += 1
            return
        decoder = DECODERS.get(info.message_type)
        if decoder is None:
            self.stats.unknown_type += 1
            self._warn_once(info, "type", f"no layout for {info.message_type}: skipped")
            return
        layout, build = decoder
        if info.md5sum != layout.md5:
            self.stats.md5_mismatch += 1
            self._warn_once(
                info,
                "md5",
                f"{info.message_type} announced with md5 {info.md5sum}, we know {layout.md5}: "
                "a different firmware's layout, skipped",
            )
            return
        try:
            record = build(info.name, frame.payload, t_host)
        except ParseError as exc:
            self.stats.malformed += 1
            self._warn_once(info, "malformed", f"{exc} (further ones only counted)")
            return
        if record is None:
            self.stats.unknown_type += 1
            return
        self.stats.decoded += 1
        if isinstance(record, JackalFeedback):
            self._check_travel(record)
            out.append(wheel_sample(record))
        out.append(record)

    def _check_travel(self, fb: JackalFeedback) -> None:
        last = self._last_travel.get(fb.topic)
        travel = (fb.left.measured_travel, fb.right.measured_travel)
        if last is not None:
            dt = max(0, fb.t_host - last[2]) / 1e9
            bound = MAX_WHEEL_RAD_S * dt + TRAVEL_JUMP_MARGIN_RAD
            if abs(travel[0] - last[0]) > bound or abs(travel[1] - last[1]) > bound:
                self.stats.travel_jumps += 1
                log.warning("jackal: wheel travel jumped (%s -> %s): MCU reset?", last[:2], travel)
        self._last_travel[fb.topic] = (*travel, fb.t_host)

    def _warn_once(self, info: rs.TopicInfo, kind: str, message: str) -> None:
        key = (info.name, kind)
        if key not in self._warned:
            self._warned.add(key)
            log.warning("jackal: topic %r (id %d): %s", info.name, info.topic_id, message)


def decode_stream(chunks: Iterable[tuple[int, bytes]]) -> Iterator[Record]:
    """Records from recorded MCU bytes (`/wheels/jackal`: (t_host, data) in read order).
    Topic ids come from the TopicInfo answers in the recording itself; nothing is written."""
    protocol = JackalProtocol()
    for t_host, data in chunks:
        yield from protocol.receive(data, t_host, t_host / 1e9)
        protocol.take_outgoing()


class JackalSession:
    """The live MCU link: `start()`, then iterate (or `read()`) for `SerialChunk`s (the raw
    bytes, for recording) and records, in arrival order; `close()` when done.

    A reader thread owns the port: it answers time requests even while the consumer is busy,
    and reopens a lost port with backoff (`reconnect_s` doubling up to `max_reconnect_s`),
    reporting each change as a `LinkEvent`. If the consumer falls `queue_size` items behind,
    new items are dropped and counted (`queue_overflow`). With `teleop` set the relay runs
    too; without it the session never writes a Drive frame.
    """

    is_live = True

    def __init__(
        self,
        port: str = DEFAULT_PORT,
        baudrate: int = DEFAULT_BAUDRATE,
        *,
        teleop: TeleopConfig | None = None,
        required: Iterable[str] | None = None,
        queue_size: int = 10_000,
        reconnect_s: float = 0.25,
        max_reconnect_s: float = 5.0,
        link: SerialLink | None = None,
        protocol: JackalProtocol | None = None,
    ):
        self.uri = port
        self.link = link if link is not None else SerialLink(port, baudrate)
        if required is None:
            required = (*DEFAULT_REQUIRED, DRIVE_TOPIC) if teleop is not None else DEFAULT_REQUIRED
        self.protocol = protocol if protocol is not None else JackalProtocol(required)
        self.relay = TeleopRelay(teleop, self._send_drive) if teleop is not None else None
        self.reconnect_s = reconnect_s
        self.max_reconnect_s = max_reconnect_s
        self._delay = reconnect_s
        self.queue_overflow = 0
        self._queue: queue.Queue[Item] = queue.Queue(maxsize=queue_size)
        self._lock = threading.Lock()  # the protocol's state; writes go through it
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jackal-mcu", daemon=True)
        self._closed = False

    # --- lifecycle ------------------------------------------------------------------------

    def start(self) -> JackalSession:
        """Open the port (`SourceError` with a hint if it will not) and start the threads."""
        self.link.open()
        self._connected()
        self._thread.start()
        if self.relay is not None:
            self.relay.start()
        return self

    def __enter__(self) -> JackalSession:
        return self.start()

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        """Stop the relay (a last stop goes out if it was driving), stop the reader, tell the
        MCU we are leaving (TX stop) and close the port."""
        if self._closed:
            return
        self._closed = True
        if self.relay is not None:
            self.relay.close()
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        with self._lock:
            if self.link.is_open:
                with contextlib.suppress(LinkLostError):
                    self.link.write(rs.TX_STOP)
            self.link.close()

    # --- consuming ------------------------------------------------------------------------

    def read(self, timeout: float | None = None) -> Item | None:
        """The next item, or None after `timeout` seconds (or once closed and drained)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            remaining = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
            try:
                return self._queue.get(timeout=max(0.0, remaining))
            except queue.Empty:
                if self._closed or (deadline is not None and time.monotonic() >= deadline):
                    return None

    def __iter__(self) -> Iterator[Item]:
        while True:
            item = self.read()
            if item is None:
                return
            yield item

    def counters(self) -> dict[str, int]:
        """Every counter of the link, the framing, the protocol and the relay, flat."""
        merged = {f"link_{k}": v for k, v in self.link.stats.as_dict().items()}
        merged.update({f"frame_{k}": v for k, v in self.protocol.reader.stats.as_dict().items()})
        merged.update(self.protocol.stats.as_dict())
        merged["queue_overflow"] = self.queue_overflow
        if self.relay is not None:
            merged.update({f"teleop_{k}": v for k, v in self.relay.stats.as_dict().items()})
        return merged

    # --- the reader thread ----------------------------------------------------------------

    def _put(self, item: Item) -> None:
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.queue_overflow += 1

    def _connected(self) -> None:
        with self._lock:
            self.protocol.connect(time.monotonic())
            self._flush()
        self._put(LinkEvent(time.time_ns(), "connected", self.link.port))

    def _flush(self) -> None:
        """Write what the protocol queued (caller holds the lock)."""
        for frame in self.protocol.take_outgoing():
            self.link.write(frame)

    def _lost(self, why: str) -> None:
        log.warning("jackal: MCU link lost: %s", why)
        self.link.close()
        self._put(LinkEvent(time.time_ns(), "disconnected", why))

    def _reopen(self) -> bool:
        """Reopen the port, waiting longer after each failure, until it works (True) or the
        session closes (False). The wait resets once frames flow again."""
        last_error = ""
        while not self._stop.wait(self._delay):
            self._delay = min(self._delay * 2, self.max_reconnect_s)
            try:
                self.link.open()
            except SourceError as exc:
                if str(exc) != last_error:
                    log.warning("jackal: %s; retrying", exc)
                    last_error = str(exc)
                continue
            try:
                self._connected()
            except LinkLostError as exc:
                self._lost(str(exc))
                continue
            return True
        return False

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self.link.is_open and not self._reopen():
                return
            try:
                data = self.link.read()
            except LinkLostError as exc:
                if not self._stop.is_set():
                    self._lost(str(exc))
                continue
            t_host = time.time_ns()
            now = time.monotonic()
            lost = None
            with self._lock:
                frames_before = self.protocol.reader.stats.frames
                records = self.protocol.receive(data, t_host, now) if data else []
                if self.protocol.reader.stats.frames > frames_before:
                    self._delay = self.reconnect_s  # the MCU talks: the next loss starts afresh
                self.protocol.poll(now)
                try:
                    self._flush()
                except LinkLostError as exc:
                    lost = str(exc)
            if data:
                self._put(SerialChunk(t_host, data))
            for record in records:
                self._put(record)
            if lost is not None:
                self._lost(lost)

    def _send_drive(self, drive: m.Drive) -> bool:
        """The teleop relay's only way to the MCU."""
        with self._lock:
            frame = self.protocol.drive_frame(drive)
            if frame is None or not self.link.is_open:
                return False
            try:
                return self.link.write(frame)
            except LinkLostError:
                return False
