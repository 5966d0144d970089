"""One receive thread per sensor, each feeding a bounded queue the processing loop drains.

A receiver never blocks on the loop: `BoundedQueue.put` drops the NEWEST item when the
queue is full and counts it (the items already queued are older and keep their order, so
the loop's view stays contiguous up to the gap). Each worker stamps when it last received
something and whether its device is there, for `health`. Devices that disappear are
reopened with backoff by the drivers (serial, camera) or by the worker itself when the
first open fails; a LiDAR port that cannot be bound is fatal (another program owns it).

Items are `Message`s in the recording's terms (topic, bytes as received, `log_time` =
t_host, `publish_time`), so the loop can hand them to `SurveyProcessor` and the recorder
alike.
"""

from __future__ import annotations

import abc
import contextlib
import ctypes
import logging
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from treetraits.drivers import recording as rec
from treetraits.drivers.camera.replay import VideoFileSource
from treetraits.drivers.camera.settings import CameraSettings
from treetraits.drivers.velodyne.sources import UdpSource
from treetraits.errors import SourceError
from treetraits.service.config import CameraConfig, GnssConfig, LidarConfig, WheelsConfig
from treetraits.service.health import SensorState

log = logging.getLogger("treetraits.service")

READ_TIMEOUT_S = 0.25  # longest a receive blocks before it looks at stop()
# Between two reads of the LiDAR's queued packets (7-8 data packets): as long as the
# loop's own gathering (service/runtime.py GATHER_S), a tenth of a scan. Each wake-up
# costs the thread CPU of its own: one a packet was most of the thread's share of a core,
# one every 10 ms leaves less than half of it (docs/performance.md, "Reading LiDAR
# packets in bursts").
LIDAR_BURST_GAP_S = 0.01
RETRY_FIRST_S = 0.5  # first wait before trying a device that would not open again
RETRY_MAX_S = 5.0
PR_SET_NAME = 15  # prctl(2)


@dataclass(frozen=True, slots=True)
class Message:
    topic: str
    data: bytes
    log_time: int  # t_host, ns since the Unix epoch
    publish_time: int


class BoundedQueue:
    """A single-producer, single-consumer FIFO of at most `capacity` items.

    Lock-free by construction: only the receive thread appends and only the loop pops, and
    CPython's deque append/popleft are atomic, so the length seen by the producer can only
    shrink before its append: the bound holds. `wake` is set after every put.
    """

    def __init__(self, name: str, capacity: int, wake: threading.Event):
        if capacity < 1:
            raise ValueError(f"queue {name}: capacity must be >= 1, got {capacity}")
        self.name = name
        self.capacity = capacity
        self.accepted = 0
        self.dropped = 0
        self.high_water = 0
        self._items: deque[Message] = deque()
        self._wake = wake

    def put(self, message: Message) -> bool:
        """Enqueue; False (and counted) when full: the newest item is the one dropped."""
        size = len(self._items)
        if size >= self.capacity:
            self.dropped += 1
            return False
        self._items.append(message)
        self.accepted += 1
        if size + 1 > self.high_water:
            self.high_water = size + 1
        # set() takes a lock: skip it when already set. Safe because the item is in
        # before the look, and the loop clears the event before it looks at the queues.
        if not self._wake.is_set():
            self._wake.set()
        return True

    def head_time(self) -> int | None:
        """`log_time` of the oldest item, or None when empty."""
        try:
            return self._items[0].log_time
        except IndexError:
            return None

    def pop(self) -> Message:
        return self._items.popleft()

    def __len__(self) -> int:
        return len(self._items)


def name_os_thread(name: str) -> None:
    """Give the calling thread its name in the OS too (`top -H`, /proc/<pid>/task/*/comm),
    so the CPU of each receive thread can be told apart. Linux only; best effort."""
    with contextlib.suppress(Exception):
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_NAME, ctypes.c_char_p(name.encode()[:15]), 0, 0, 0)


class Worker(abc.ABC):
    """A receive thread: `open()` (in the caller's thread), `start()`, `stop()`, `join()`.
    Subclasses implement `_open_source`, `_receive` (one bounded wait) and `_close_source`."""

    name = "sensor"

    def __init__(self, queue: BoundedQueue, silence_s: float):
        self.queue = queue
        self.silence_s = silence_s
        self.source = None
        self.started = time.monotonic()
        self.last_seen: float | None = None
        self.items = 0
        self.fatal: str | None = None  # the thread died: named in the status
        self._stop = threading.Event()
        self._retry_at: float | None = None  # when the next open is tried (first open failed)
        self._retry_delay = RETRY_FIRST_S
        self._last_open_error = ""
        self._thread = threading.Thread(target=self._main, name=f"rx-{self.name}", daemon=True)

    # --- lifecycle ---------------------------------------------------------------------

    def open(self, retry: bool = True) -> None:
        """Open the device now. With `retry`, a device that is not there is tried again
        from the thread with backoff; without, its SourceError goes to the caller."""
        self.started = time.monotonic()
        try:
            self.source = self._open_source()
        except SourceError as exc:
            if not retry:
                raise
            self._schedule_retry(exc)

    def start(self) -> None:
        # Silence counts from here, when the device is first read: between open() and
        # start() the service loads its pipeline (1-2 s on a loaded machine), and a
        # sensor is not silent for what nobody was listening to.
        self.started = time.monotonic()
        self._thread.start()

    def stop(self) -> None:
        """Ask the thread to end and close the device (wakes a blocked read)."""
        self._stop.set()
        source, self.source = self.source, None
        if source is not None:
            try:
                self._close_source(source)
            except Exception:  # closing is best effort: the device may be gone
                log.debug("%s: close failed", self.name, exc_info=True)

    def join(self, timeout: float) -> bool:
        if self._thread.is_alive():
            self._thread.join(timeout)
        return not self._thread.is_alive()

    # --- the thread --------------------------------------------------------------------

    def _main(self) -> None:
        name_os_thread(f"rx-{self.name}")
        try:
            while not self._stop.is_set():
                source = self.source
                if source is None:
                    self._try_open()
                    continue
                message = self._receive(source)
                if message is not None:
                    self.emit(message)
        except Exception as exc:  # a driver bug must show in the status, not vanish
            if not self._stop.is_set():
                self.fatal = f"receive thread failed: {type(exc).__name__}: {exc}"
                log.exception("%s: receive thread failed", self.name)

    def emit(self, message: Message) -> None:
        self.last_seen = time.monotonic()
        self.items += 1
        self.queue.put(message)

    def _schedule_retry(self, exc: Exception) -> None:
        text = str(exc)
        if text != self._last_open_error:  # the full hint once, not every retry
            log.warning("%s: %s; retrying with backoff", self.name, text)
            self._last_open_error = text
        self._retry_at = time.monotonic() + self._retry_delay
        self._retry_delay = min(self._retry_delay * 2, RETRY_MAX_S)

    def _try_open(self) -> None:
        wait = 0.0 if self._retry_at is None else self._retry_at - time.monotonic()
        if wait > 0 and self._stop.wait(wait):
            return
        try:
            source = self._open_source()
        except SourceError as exc:
            self._schedule_retry(exc)
            return
        if self._stop.is_set():
            self._close_source(source)
            return
        self.source, self._retry_at, self._retry_delay = source, None, RETRY_FIRST_S
        log.warning("%s: opened", self.name)

    # --- health ------------------------------------------------------------------------

    def state(self) -> SensorState:
        connected, detail = True, ""
        if self.fatal:
            connected, detail = False, self.fatal
        elif self.source is None:
            left = max(0.0, (self._retry_at or time.monotonic()) - time.monotonic())
            connected, detail = False, f"not found, retrying in {left:.0f} s"
        else:
            connected, detail = self._link_state(self.source)
        return SensorState(
            self.name, self.silence_s, self.started, self.last_seen, connected, detail
        )

    def _link_state(self, source) -> tuple[bool, str]:
        return True, ""

    def counters(self) -> dict[str, int]:
        return {"items": self.items, "dropped": self.queue.dropped}

    # --- per sensor --------------------------------------------------------------------

    @abc.abstractmethod
    def _open_source(self):
        """The sensor's source (it reopens itself with backoff where it can)."""

    @abc.abstractmethod
    def _receive(self, source) -> Message | None:
        """The next message, or None after a short timeout."""

    def _close_source(self, source) -> None:
        source.close()


class LidarWorker(Worker):
    """The VLP-16's UDP ports. Does nothing but receive and enqueue."""

    name = "lidar"

    def __init__(self, cfg: LidarConfig, queue: BoundedQueue):
        super().__init__(queue, cfg.silence_s)
        self.cfg = cfg
        self._stats = None

    def _open_source(self) -> UdpSource:
        source = UdpSource(
            host=self.cfg.bind,
            port=self.cfg.data_port,
            telemetry_port=self.cfg.telemetry_port or None,
            sensor_ip=self.cfg.sensor_ip or None,
            rcvbuf=self.cfg.rcvbuf_bytes,
        )
        self._stats = source.stats
        granted = source.effective_rcvbuf
        if granted < self.cfg.rcvbuf_bytes:
            log.warning(
                "lidar: receive buffer %d bytes, asked for %d: raise net.core.rmem_max "
                "(sysctl) or packets may be lost during a long scan",
                granted,
                self.cfg.rcvbuf_bytes,
            )
        return source

    def _receive(self, source: UdpSource) -> Message | None:
        if source.kernel_timestamps and not source.pending:
            # Packets wait in the kernel, each stamped there on arrival, and one wake-up
            # reads them all: not a wake-up (and a take of the GIL from the pipeline) for
            # every one of 754 a second.
            self._stop.wait(LIDAR_BURST_GAP_S)
        packet = source.read(READ_TIMEOUT_S)
        if packet is None:
            return None
        topic = rec.LIDAR_PACKETS if packet.is_data else rec.LIDAR_TELEMETRY
        # publish_time is worked out by the loop, and only for the recorder.
        return Message(topic, packet.payload, packet.t_host, packet.t_host)

    def counters(self) -> dict[str, int]:
        out = super().counters()
        if self._stats is not None:
            out.update(
                foreign=self._stats.foreign,
                malformed=self._stats.malformed,
                kernel_drops=self._stats.kernel_drops,
            )
        return out


class GnssWorker(Worker):
    """A receiver on a serial port; `SerialSource` reopens it with backoff."""

    name = "gnss"

    def __init__(self, cfg: GnssConfig, queue: BoundedQueue):
        super().__init__(queue, cfg.silence_s)
        self.cfg = cfg

    def _open_source(self):
        from treetraits.drivers.gnss.sources import SerialSource

        return SerialSource(
            self.cfg.port, self.cfg.baudrate, reconnect=True, reopen_min_s=0.25, reopen_max_s=5.0
        )

    def _receive(self, source) -> Message | None:
        sentence = source.read(READ_TIMEOUT_S)
        if sentence is None:
            return None
        return Message(rec.GNSS_NMEA, sentence.raw, sentence.t_host, sentence.t_host)

    def _link_state(self, source) -> tuple[bool, str]:
        if source.connected:
            return True, ""
        return False, f"reopening {self.cfg.port} ({source.stats.open_failures} tries failed)"


class JackalWorker(Worker):
    """The Jackal MCU: `JackalSession` answers its time requests and reopens the port; the
    raw bytes (`SerialChunk`) go on, for the processor and the recorder."""

    name = "wheels"

    def __init__(self, cfg: WheelsConfig, queue: BoundedQueue):
        super().__init__(queue, cfg.silence_s)
        self.cfg = cfg
        self._connected = True

    def _open_source(self):
        from treetraits.firmware_bridge.jackal.session import JackalSession

        session = JackalSession(self.cfg.port, self.cfg.baudrate)
        session.start()
        self._connected = True
        return session

    def _receive(self, session) -> Message | None:
        from treetraits.firmware_bridge.jackal.records import LinkEvent, SerialChunk

        item = session.read(READ_TIMEOUT_S)
        if isinstance(item, SerialChunk):
            return Message(rec.WHEELS_JACKAL, item.data, item.t_host, item.t_host)
        if isinstance(item, LinkEvent) and item.state in ("connected", "disconnected"):
            self._connected = item.state == "connected"
            if not self._connected:
                log.warning("wheels: %s disconnected (%s); reopening", self.cfg.port, item.detail)
        return None  # decoded records: the processor decodes the raw bytes itself

    def _link_state(self, source) -> tuple[bool, str]:
        return (True, "") if self._connected else (False, f"reopening {self.cfg.port}")


class BridgeWorker(Worker):
    """A retrofit encoder board: `SerialLink` yields the bytes as read and reopens the port."""

    name = "wheels"

    def __init__(self, cfg: WheelsConfig, queue: BoundedQueue):
        super().__init__(queue, cfg.silence_s)
        self.cfg = cfg

    def _open_source(self):
        from treetraits.firmware_bridge.retrofit.serial_link import SerialLink

        # wait_for_port: a board plugged in later is picked up by the link itself.
        return SerialLink(self.cfg.port, self.cfg.baudrate, reconnect=True, wait_for_port=True)

    def _receive(self, link) -> Message | None:
        from treetraits.firmware_bridge.retrofit.serial_link import BridgeChunk

        item = link.read(READ_TIMEOUT_S)
        if isinstance(item, BridgeChunk):
            return Message(rec.WHEELS_BRIDGE, item.data, item.t_host, item.t_host)
        return None

    def _link_state(self, link) -> tuple[bool, str]:
        if link.connected:
            return True, ""
        return False, f"reopening {self.cfg.port} ({link.stats.open_failures} tries failed)"


class PacedVideo:
    """A video file played as a camera: frames at the file's frame rate, each stamped with
    the host clock when it is handed over (t_host) and when it fell due (t_capture: the
    same unless the reader fell behind). For tests and demos, where
    a survey is played into the service: the video starts with `play()`, which the service
    calls at its first LiDAR packet with the time of that packet's first firing, so frame k
    comes k frame periods after the survey's first scan began, as the survey's own frames
    did, not k periods after the service started (nor after the loop got to the packet:
    10 ms later on a loaded host, which moved every frame 10 ms later than the survey's).
    Its stamp (t_capture) is k periods after `anchor_ns`, the first firing as the least
    delay of the survey's first packets puts it (`survey_start`), when the service set it."""

    is_live = True

    def __init__(self, path: Path):
        self.uri = str(path)
        self._source = VideoFileSource(path)
        self._period = 1.0 / self._source.fps if self._source.fps > 0 else 0.1
        self._frames = iter(self._source)
        self._next = time.monotonic()
        self._wake = threading.Event()
        self._playing = threading.Event()
        self.ended = False
        self._handed = 0  # frames handed over
        # The survey's first firing on the host clock (`survey_start`), set by the service
        # as its packets come: frame k is stamped captured k periods after it.
        self.anchor_ns: int | None = None

    def play(self, start_ns: int | None = None) -> None:
        """Start handing frames over, the first due at `start_ns` (host clock, ns; now when
        None or later than now). Idempotent."""
        if not self._playing.is_set():
            now = time.monotonic()
            late_s = 0.0 if start_ns is None else max(0, time.time_ns() - start_ns) / 1e9
            self._next = now - late_s
            self._playing.set()

    def read(self, timeout: float) -> tuple[bytes, int, int] | None:
        """(JPEG, t_host, t_capture): handed over at t_host, "captured" when it was due."""
        if not self._playing.is_set():
            self._playing.wait(timeout)
            return None
        if self.ended:
            self._wake.wait(timeout)
            return None
        wait = self._next - time.monotonic()
        if wait > timeout:
            self._wake.wait(timeout)
            return None
        if wait > 0 and self._wake.wait(wait):
            return None  # closed
        frame = next(self._frames, None)
        if frame is None:
            self.ended = True
            log.warning("camera: end of the video file %s: no more frames", self.uri)
            return None
        # Frame k is captured k periods after the start, as a camera's would be: a reader
        # that fell behind (decoding, a loaded machine) hands the backlog over at once,
        # each stamped when it was due, so the frames stay on the survey's timeline.
        due, self._next = self._next, self._next + self._period
        now = time.time_ns()
        k, self._handed = self._handed, self._handed + 1
        if (anchor := self.anchor_ns) is not None:
            return frame.jpeg, now, min(now, anchor + round(k * self._period * 1e9))
        return frame.jpeg, now, now - max(0, round((time.monotonic() - due) * 1e9))

    def close(self) -> None:
        self._wake.set()
        self._source.close()


def is_video_file(device: str) -> bool:
    from treetraits.drivers.camera.sources import is_live_uri

    return not is_live_uri(device) and Path(device).is_file()


class CameraWorker(Worker):
    """The Survey3N through `UvcCamera` (reopened with backoff by its own grab thread),
    or a video file played at its frame rate."""

    name = "camera"

    def __init__(self, cfg: CameraConfig, queue: BoundedQueue):
        super().__init__(queue, cfg.silence_s)
        self.cfg = cfg
        self._play = False  # play_video was called

    def _open_source(self):
        if is_video_file(self.cfg.device):
            video = PacedVideo(Path(self.cfg.device))
            if self._play:  # reopened after the survey began
                video.play()
            return video
        from treetraits.drivers.camera.live import UvcCamera

        return UvcCamera(self.cfg.device, CameraSettings(wait_for_device=True))

    def anchor_video(self, first_firing_ns: int) -> None:
        """Stamp a video file's frames from the survey's first firing (`PacedVideo`)."""
        if isinstance(self.source, PacedVideo):
            self.source.anchor_ns = first_firing_ns

    def play_video(self, start_ns: int | None = None) -> None:
        """Start a video file played as the camera (`PacedVideo.play`); nothing for a
        real camera."""
        self._play = True
        if isinstance(self.source, PacedVideo):
            self.source.play(start_ns)

    def _receive(self, source) -> Message | None:
        if isinstance(source, PacedVideo):
            got = source.read(READ_TIMEOUT_S)
            if got is None:
                return None
            jpeg, t_host, t_capture = got
            return Message(rec.CAMERA_JPEG, jpeg, t_host, t_capture)
        frame = source.next_frame(timeout=READ_TIMEOUT_S)
        if frame is None:
            return None
        return Message(rec.CAMERA_JPEG, frame.jpeg, frame.t_host, frame.t_capture)

    def _link_state(self, source) -> tuple[bool, str]:
        if isinstance(source, PacedVideo) or source.state == "streaming":
            return True, ""
        return False, f"reopening {self.cfg.device}"
