"""Play a recording (format v1) to live interfaces at its recorded pace, as the sensors
would: the service's tests and its benchmark read the player exactly as they read the robot.

- LiDAR: `/lidar/packets` and `/lidar/telemetry` as UDP datagrams to the data and
  telemetry ports, from a socket bound to `lidar_source` (127.0.0.1 by default: the
  sender address is what the service's `sensor_ip` filter checks).
- GNSS: `/gnss/nmea`, each sentence written as recorded to a pseudo-terminal; the slave
  (`gnss_device`) is the receiver's serial port.
- Wheels: a pseudo-terminal (`wheels_device`) acting as the Jackal MCU. rosserial is a
  dialogue, so the recorded bytes cannot simply be streamed (the host flushes its input
  on open and must ask for topics first): the player answers the host's topic request with
  the TopicInfo frames found in the recording, asks for the time every 2.5 s and stops
  publishing after 11 s without a time reply or on TX stop, as rosserial_client does; the
  recorded user-topic frames (Feedback, Status, ...) go out at their recorded pace while
  the host is configured, the rest are counted as `wheels_unsent`. A recording with
  `/wheels/bridge` instead (the retrofit encoder board) is streamed as recorded.

Pacing: every message is due at `start + (log_time - first_log_time) / speed` on the
monotonic clock, one schedule shared by all streams, so they never drift apart; a stream
that falls behind sends what is due in a burst. Lateness (send time - due time) is counted.
While no program has a pty's slave open, what falls due is skipped and counted (`unheard`):
a USB device's bytes are lost while its port is closed, and a backlog would arrive later
in one burst with wrong timing.

The streamed topics are held in memory (about 1 MB per second of survey, mostly LiDAR).
With `loop`, the recording restarts `LOOP_GAP_S` after its end; sensor clocks then jump
back (GNSS time, LiDAR timestamps, wheel travel), as after a power cycle.

`write_camera_video` turns the `/camera/jpeg` messages into an MJPG video for the
service's `camera.device = <video file>` mode.
"""

from __future__ import annotations

import errno
import logging
import os
import select
import socket
import statistics
import threading
import time
import tty
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from treetraits.damage import integrity_facts
from treetraits.drivers import recording as rec
from treetraits.errors import ParseError, SourceError
from treetraits.firmware_bridge.jackal import rosserial as rs

log = logging.getLogger(__name__)

LOOP_GAP_S = 0.1
# rosserial_client (ros/node_handle.h, SYNC_SECONDS = 5): a time request every 2.5 s while
# configured; no time reply for 11 s and the MCU drops back to unconfigured.
TIME_REQUEST_S = 2.5
SYNC_LOST_S = 11.0
WRITE_TIMEOUT_S = 0.2  # a reader that takes nothing for this long: the rest is dropped
_IDLE_POLL_S = 0.02  # how often a pty without a reader is checked for one
_LATENESS_SAMPLES = 65_536  # median over the newest sends; the max is over all


@dataclass
class StreamCounters:
    """What one stream did. `late_*` over the messages sent, in ms."""

    sent: int = 0
    bytes: int = 0
    unheard: int = 0  # due while nobody had the port open (or unplugged): skipped
    dropped: int = 0  # the reader did not take them within WRITE_TIMEOUT_S, or send failed
    late_max_ms: float = 0.0
    _late: deque[float] = field(default_factory=lambda: deque(maxlen=_LATENESS_SAMPLES))

    def late(self, ms: float) -> None:
        self._late.append(ms)
        self.late_max_ms = max(self.late_max_ms, ms)

    def deliver(self, pty: _Pty, data: bytes, due_ns: int) -> None:
        """Write one message that fell due at `due_ns` (monotonic) and count the outcome."""
        late_ms = (time.monotonic_ns() - due_ns) / 1e6
        if pty.write(data):
            self.sent += 1
            self.bytes += len(data)
            self.late(late_ms)
        else:
            self.dropped += 1

    @property
    def late_median_ms(self) -> float:
        return statistics.median(self._late) if self._late else 0.0


class _Schedule:
    """The due times (monotonic ns) of one stream's messages: one clock for all streams."""

    def __init__(self, t0: int, period_ns: int, speed: float, loop: bool):
        self.t0 = t0
        self.period_ns = period_ns
        self.speed = speed
        self.loop = loop
        self.start_ns = 0

    def __call__(self, items: list[tuple[int, bytes]]) -> Iterator[tuple[int, bytes]]:
        k = 0
        while True:
            offset = k * self.period_ns - self.t0
            for log_time, data in items:
                yield self.start_ns + int((log_time + offset) / self.speed), data
            k += 1
            if not self.loop or not items:
                return


def _wait_until(due_ns: int, stop: threading.Event) -> bool:
    """Sleep until `due_ns` (monotonic); False if stopped meanwhile."""
    wait = (due_ns - time.monotonic_ns()) / 1e9
    if wait > 0:
        return not stop.wait(wait)
    return not stop.is_set()


class _Pty:
    """A pseudo-terminal whose master the player drives; the slave is the device path.

    The slave is made raw (bytes pass unchanged) and closed again: a program opens it as it
    would a USB serial port. Closing the master hangs the slave up: its reader gets EOF
    (pyserial: "device reports readiness to read but returned no data"), as on unplug.
    """

    def __init__(self) -> None:
        master, slave = os.openpty()
        try:
            tty.setraw(slave)
            self.device = os.ttyname(slave)
        finally:
            os.close(slave)
        os.set_blocking(master, False)  # a reader that stops must not stall the player
        self._master: int | None = master
        self._lock = threading.Lock()

    @property
    def unplugged(self) -> bool:
        return self._master is None

    def listened(self) -> bool:
        """True while a program has the slave open (no POLLHUP on the master)."""
        master = self._master
        if master is None:
            return False
        poller = select.poll()
        poller.register(master, select.POLLIN)
        try:
            events = poller.poll(0)
        except (OSError, ValueError):
            return False
        return not any(mask & select.POLLHUP for _, mask in events)

    def write(self, data: bytes) -> bool:
        """Write all of `data`; False (the rest dropped) if the reader took nothing for
        WRITE_TIMEOUT_S or the pty was unplugged."""
        with self._lock:
            master = self._master
            if master is None:
                return False
            view = memoryview(data)
            deadline = time.monotonic() + WRITE_TIMEOUT_S
            while view:
                try:
                    n = os.write(master, view)
                except BlockingIOError:
                    n = 0
                except OSError:
                    return False
                view = view[n:]
                if view:
                    remaining = deadline - time.monotonic()
                    if remaining <= 0:
                        return False
                    select.select([], [master], [], min(remaining, 0.01))
            return True

    def read(self, timeout: float) -> bytes | None:
        """What the slave's program wrote (b"" if nothing within `timeout`); None while
        nobody has the slave open or once unplugged (then it waits `timeout` first, so a
        caller's loop does not spin)."""
        master = self._master
        if master is None:
            return None
        try:
            ready, _, _ = select.select([master], [], [], timeout)
            if not ready:
                return b""
            return os.read(master, 4096)
        except BlockingIOError:
            return b""
        except (OSError, ValueError) as exc:
            if isinstance(exc, OSError) and exc.errno not in (errno.EIO, errno.EBADF):
                raise
            time.sleep(max(timeout, _IDLE_POLL_S))  # EIO: no slave open; select() won't wait
            return None

    def close(self) -> None:
        with self._lock:
            master, self._master = self._master, None
        if master is not None:
            os.close(master)


def _raw_stream(
    pty: _Pty,
    items: list[tuple[int, bytes]],
    schedule: _Schedule,
    counters: StreamCounters,
    stop: threading.Event,
) -> None:
    """Write each recorded message to the pty when due (GNSS sentences, bridge bytes)."""
    for due, data in schedule(items):
        if not _wait_until(due, stop):
            return
        if not pty.listened():
            counters.unheard += 1
            continue
        counters.deliver(pty, data, due)


@dataclass
class McuCounters:
    topic_requests: int = 0
    time_requests: int = 0
    time_replies: int = 0
    tx_stops: int = 0
    sync_losses: int = 0  # no time reply for SYNC_LOST_S: stopped publishing


@dataclass
class _McuFrames:
    """A `/wheels/jackal` recording split into what the MCU says when asked (TopicInfo) and
    what it publishes on its own (user topics and log messages, with their log_time)."""

    announcements: list[bytes]
    published: list[tuple[int, bytes]]
    skipped: int  # time requests and other reserved frames: the live MCU makes its own


def split_mcu_stream(messages: list[tuple[int, bytes]]) -> _McuFrames:
    """Frames from the recorded chunks (any chunking), each stamped with the log_time of
    the chunk that completed it. TopicInfo answers keep their first order, the newest
    content of each (kind, id) winning."""
    reader = rs.FrameReader()
    announcements: dict[tuple[int, int], bytes] = {}
    published: list[tuple[int, bytes]] = []
    skipped = 0
    for log_time, data in messages:
        for frame in reader.push(data):
            if frame.topic_id in (rs.ID_PUBLISHER, rs.ID_SUBSCRIBER):
                try:
                    info = rs.TopicInfo.decode(frame.payload)
                except ParseError:  # skipped, as the host would skip it
                    skipped += 1
                    continue
                announcements[(frame.topic_id, info.topic_id)] = frame.raw
            elif frame.topic_id >= rs.FIRST_USER_ID or frame.topic_id == rs.ID_LOG:
                published.append((log_time, frame.raw))
            else:
                skipped += 1
    return _McuFrames(list(announcements.values()), published, skipped)


def _jackal_mcu(
    pty: _Pty,
    frames: _McuFrames,
    schedule: _Schedule,
    counters: StreamCounters,
    mcu: McuCounters,
    stop: threading.Event,
    done: threading.Event,
) -> None:
    """The MCU side of rosserial on the pty: answers topic requests, asks for the time,
    publishes the recorded frames when due while configured. Runs until `stop`, answering
    the host after the recording has played out (`done`)."""
    host = rs.FrameReader()
    configured = False
    last_reply = last_request = time.monotonic()
    upcoming = schedule(frames.published)
    nxt = next(upcoming, None)
    if nxt is None:
        done.set()

    while not stop.is_set():
        now = time.monotonic()
        wait = _IDLE_POLL_S * 5
        if nxt is not None:
            wait = min(wait, max(0.0, (nxt[0] / 1e9) - now))
        if configured:
            wait = min(wait, max(0.0, last_request + TIME_REQUEST_S - now))
        data = pty.read(wait if wait > 0 else 0.0)
        if data is None and pty.unplugged:
            return
        now = time.monotonic()
        for frame in host.push(data or b""):
            if frame.topic_id == rs.ID_PUBLISHER and not frame.payload:
                mcu.topic_requests += 1
                # As the client does: a time request first, then every topic it has.
                mcu.time_requests += 1
                pty.write(rs.encode_frame(rs.ID_TIME))
                for announcement in frames.announcements:
                    pty.write(announcement)
                configured = True
                last_reply = last_request = now
            elif frame.topic_id == rs.ID_TIME:
                mcu.time_replies += 1
                last_reply = now
            elif frame.topic_id == rs.ID_TX_STOP:
                mcu.tx_stops += 1
                configured = False
        if configured and now - last_reply > SYNC_LOST_S:
            configured = False
            mcu.sync_losses += 1
        if configured and now - last_request >= TIME_REQUEST_S:
            mcu.time_requests += 1
            pty.write(rs.encode_frame(rs.ID_TIME))
            last_request = now
        now_ns = time.monotonic_ns()
        while nxt is not None and nxt[0] <= now_ns:
            due, frame_bytes = nxt
            if configured and pty.listened():
                counters.deliver(pty, frame_bytes, due)
            else:
                counters.unheard += 1
            nxt = next(upcoming, None)
            if nxt is None:
                done.set()


def _udp_stream(
    sock: socket.socket,
    items: list[tuple[int, tuple[int, bytes]]],
    schedule: _Schedule,
    counters: dict[int, StreamCounters],
    host: str,
    stop: threading.Event,
) -> None:
    """Send each datagram when due; items carry (port, payload), counted per port."""
    for due, (port, payload) in schedule(items):  # type: ignore[arg-type,misc]
        if not _wait_until(due, stop):
            return
        c = counters[port]
        late_ms = (time.monotonic_ns() - due) / 1e6
        try:
            sock.sendto(payload, (host, port))
        except OSError:
            c.dropped += 1
            continue
        c.sent += 1
        c.bytes += len(payload)
        c.late(late_ms)


class RecordingPlayer:
    """Streams a recording to a UDP port pair and two pseudo-terminals at its recorded pace.

    `data_port` / `telemetry_port` None: that LiDAR topic is not sent. `gnss_pty` /
    `wheels_pty` False: no pty (`gnss_device` / `wheels_device` None). Raises
    `SourceError` for a recording that cannot be read, or whose Jackal bytes carry no
    TopicInfo (a live host could never learn the topic ids).
    """

    def __init__(
        self,
        recording_path: str | os.PathLike[str],
        lidar_host: str = "127.0.0.1",
        data_port: int | None = 2368,
        telemetry_port: int | None = 8308,
        gnss_pty: bool = True,
        wheels_pty: bool = True,
        speed: float = 1.0,
        loop: bool = False,
        *,
        lidar_source: str = "127.0.0.1",
    ):
        if not speed > 0:
            raise ValueError(f"speed must be positive, got {speed}")
        self.path = Path(recording_path)
        self.speed = speed
        self.loop = loop
        self.lidar_host = lidar_host
        self.data_port = data_port
        self.telemetry_port = telemetry_port
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._done: list[threading.Event] = []
        self._closed = False
        self._started = False

        lidar: list[tuple[int, tuple[int, bytes]]] = []
        gnss: list[tuple[int, bytes]] = []
        jackal: list[tuple[int, bytes]] = []
        bridge: list[tuple[int, bytes]] = []
        ports = {rec.LIDAR_PACKETS: data_port, rec.LIDAR_TELEMETRY: telemetry_port}
        reader = rec.read_recording(self.path)
        for m in reader:
            if m.topic in ports:
                port = ports[m.topic]
                if port is not None:
                    lidar.append((m.log_time, (port, m.data)))
            elif m.topic == rec.GNSS_NMEA and gnss_pty:
                gnss.append((m.log_time, m.data))
            elif m.topic == rec.WHEELS_JACKAL and wheels_pty:
                jackal.append((m.log_time, m.data))
            elif m.topic == rec.WHEELS_BRIDGE and wheels_pty:
                bridge.append((m.log_time, m.data))
        self.truncated = reader.truncated or reader.lost_data  # cut, or a chunk skipped
        self.integrity = integrity_facts(reader)  # what was lost, for the command's line
        # A recording's messages are in log_time order per chunk, not across: sort stably.
        for items in (lidar, gnss, jackal, bridge):
            items.sort(key=lambda item: item[0])
        self.mcu_frames: _McuFrames | None = None
        if jackal:
            self.mcu_frames = split_mcu_stream(jackal)
            if self.mcu_frames.published and not self.mcu_frames.announcements:
                raise SourceError(
                    f"{self.path}: /wheels/jackal holds no TopicInfo frames, so a live host "
                    "could not learn the MCU's topic ids; record from the MCU's first answer "
                    "(`treetraits record` does)"
                )
        wheel_items = self.mcu_frames.published if self.mcu_frames else bridge
        times = [items[0][0] for items in (lidar, gnss, wheel_items) if items]
        ends = [items[-1][0] for items in (lidar, gnss, wheel_items) if items]
        t0 = min(times) if times else 0
        self.duration_s = (max(ends) - t0) / 1e9 if ends else 0.0
        period = max(ends) - t0 + int(LOOP_GAP_S * 1e9) if ends else 0
        self._schedule = _Schedule(t0, period, speed, loop)
        self._lidar = lidar
        self._gnss_items = gnss
        self._bridge = bridge

        self.lidar = StreamCounters()
        self.telemetry = StreamCounters()
        self.gnss = StreamCounters()
        self.wheels = StreamCounters()
        self.mcu = McuCounters()
        self._sock: socket.socket | None = None
        self._gnss_pty: _Pty | None = None
        self._wheels_pty: _Pty | None = None
        try:
            if lidar:
                family = socket.AF_INET6 if ":" in lidar_source else socket.AF_INET
                self._sock = socket.socket(family, socket.SOCK_DGRAM)
                # A burst after a stall must not fail with ENOBUFS: room for ~3000 packets.
                self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
                self._sock.bind((lidar_source, 0))
            self._gnss_pty = _Pty() if gnss_pty else None
            self._wheels_pty = _Pty() if wheels_pty else None
        except BaseException:
            self.close()
            raise

    @property
    def gnss_device(self) -> str | None:
        return self._gnss_pty.device if self._gnss_pty else None

    @property
    def wheels_device(self) -> str | None:
        return self._wheels_pty.device if self._wheels_pty else None

    @property
    def lidar_sender(self) -> tuple[str, int] | None:
        """The (address, port) the datagrams come from."""
        return self._sock.getsockname()[:2] if self._sock else None

    def start(self) -> RecordingPlayer:
        """Start playing: the first message is due now."""
        if self._started:
            raise RuntimeError("a RecordingPlayer plays once; make a new one")
        self._started = True
        self._schedule.start_ns = time.monotonic_ns()
        stop, schedule = self._stop, self._schedule
        if self._sock is not None:
            by_port = {self.data_port: self.lidar, self.telemetry_port: self.telemetry}
            args = (self._sock, self._lidar, schedule, by_port, self.lidar_host, stop)
            self._spawn("lidar", _udp_stream, args, self._done_event())
        if self._gnss_pty is not None and self._gnss_items:
            args = (self._gnss_pty, self._gnss_items, schedule, self.gnss, stop)
            self._spawn("gnss", _raw_stream, args, self._done_event())
        if self._wheels_pty is not None and self.mcu_frames is not None:
            # The MCU keeps answering the host after its last frame: `done` is set then.
            done = self._done_event()
            args = (self._wheels_pty, self.mcu_frames, schedule, self.wheels, self.mcu)
            self._spawn("wheels", _jackal_mcu, (*args, stop, done), None, done)
        elif self._wheels_pty is not None and self._bridge:
            args = (self._wheels_pty, self._bridge, schedule, self.wheels, stop)
            self._spawn("wheels", _raw_stream, args, self._done_event())
        return self

    def _done_event(self) -> threading.Event:
        done = threading.Event()
        self._done.append(done)
        return done

    def _spawn(
        self,
        name: str,
        target: Callable[..., None],
        args: tuple,
        done_on_return: threading.Event | None,
        done_on_error: threading.Event | None = None,
    ) -> None:
        def run() -> None:
            try:
                target(*args)
            except Exception:
                log.exception("player: the %s stream failed", name)
                if done_on_error is not None:
                    done_on_error.set()  # wait() must not hang on a dead stream
            finally:
                if done_on_return is not None:
                    done_on_return.set()

        thread = threading.Thread(target=run, name=f"player-{name}", daemon=True)
        self._threads.append(thread)
        thread.start()

    def wait(self, timeout: float | None = None) -> bool:
        """True once every stream has played out (never with `loop`)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        for done in self._done:
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not done.wait(remaining):
                return False
        return True

    def close_gnss(self) -> None:
        """Unplug the GNSS receiver: close the pty master (its reader sees the hang-up);
        sentences due afterwards count as `gnss_unheard`."""
        if self._gnss_pty is not None:
            self._gnss_pty.close()

    def stop(self) -> None:
        """Stop sending (the MCU falls silent too) but keep the ptys open: the readers see
        silence, not an unplug. Idempotent; `close()` still closes everything."""
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=2.0)

    def close(self) -> None:
        """Stop every stream and close the sockets and ptys. Idempotent."""
        if self._closed:
            return
        self._closed = True
        self.stop()
        for pty in (self._gnss_pty, self._wheels_pty):
            if pty is not None:
                pty.close()
        if self._sock is not None:
            self._sock.close()

    def __enter__(self) -> RecordingPlayer:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    @property
    def elapsed_s(self) -> float:
        if not self._started:
            return 0.0
        return (time.monotonic_ns() - self._schedule.start_ns) / 1e9

    @property
    def counters(self) -> dict[str, float | int]:
        """Flat: `<stream>_<counter>` for the streams lidar (data packets), telemetry, gnss
        and wheels (frames published), plus the MCU dialogue (`mcu_*`), `loops` (passes
        begun after the first, with `loop`) and `elapsed_s`."""
        out: dict[str, float | int] = {}
        streams = {
            "lidar": self.lidar,
            "telemetry": self.telemetry,
            "gnss": self.gnss,
            "wheels": self.wheels,
        }
        for name, c in streams.items():
            out[f"{name}_sent"] = c.sent
            out[f"{name}_bytes"] = c.bytes
            out[f"{name}_unheard"] = c.unheard
            out[f"{name}_dropped"] = c.dropped
            out[f"{name}_late_max_ms"] = round(c.late_max_ms, 3)
            out[f"{name}_late_median_ms"] = round(c.late_median_ms, 3)
        for key, value in vars(self.mcu).items():
            out[f"mcu_{key}"] = value
        out["loops"] = self.loops
        out["elapsed_s"] = round(self.elapsed_s, 3)
        return out

    @property
    def loops(self) -> int:
        if not self._started or not self.loop or self._schedule.period_ns <= 0:
            return 0
        elapsed = (time.monotonic_ns() - self._schedule.start_ns) * self.speed
        return int(elapsed // self._schedule.period_ns)


def write_camera_video(
    recording_path: str | os.PathLike[str], out_path: str | os.PathLike[str]
) -> Path:
    """The recording's `/camera/jpeg` messages as an MJPG AVI at their mean frame rate.

    The JPEG bytes are kept verbatim (OpenCV's FFmpeg writer in raw mode): a reader of the
    video gets the recorded images bit for bit. If this OpenCV cannot write raw packets,
    the frames are decoded and re-encoded (logged as a warning). `SourceError` when the
    recording has no camera frame or OpenCV cannot write `out_path`.
    """
    import cv2
    import numpy as np

    path = Path(recording_path)
    out = Path(out_path)
    frames = [(m.log_time, m.data) for m in rec.read_recording(path, [rec.CAMERA_JPEG])]
    if not frames:
        raise SourceError(f"{path}: no {rec.CAMERA_JPEG} messages, so no camera video to write")
    frames.sort(key=lambda f: f[0])
    span_s = (frames[-1][0] - frames[0][0]) / 1e9
    fps = (len(frames) - 1) / span_s if len(frames) > 1 and span_s > 0 else 1.0
    first = cv2.imdecode(np.frombuffer(frames[0][1], np.uint8), cv2.IMREAD_COLOR)
    if first is None:
        raise SourceError(f"{path}: the first {rec.CAMERA_JPEG} message is not a readable JPEG")
    size = (first.shape[1], first.shape[0])
    fourcc = cv2.VideoWriter_fourcc(*"MJPG")
    out.parent.mkdir(parents=True, exist_ok=True)
    writer = cv2.VideoWriter(
        str(out), cv2.CAP_FFMPEG, fourcc, fps, size, [cv2.VIDEOWRITER_PROP_RAW_VIDEO, 1]
    )
    raw = writer.isOpened()
    if not raw:
        log.warning("OpenCV cannot write raw MJPG packets here: re-encoding the frames")
        writer = cv2.VideoWriter(str(out), fourcc, fps, size)
        if not writer.isOpened():
            raise SourceError(f"{out}: OpenCV cannot write an MJPG video there")
    try:
        for _, jpeg in frames:
            if raw:
                writer.write(np.frombuffer(jpeg, np.uint8).reshape(1, -1))
                continue
            image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            if image is not None:
                if (image.shape[1], image.shape[0]) != size:
                    image = cv2.resize(image, size)
                writer.write(image)
    finally:
        writer.release()
    return out
