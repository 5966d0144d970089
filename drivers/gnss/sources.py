"""Where NMEA comes from: a serial port (live), a text log, or a recording (replay).

`open_gnss_source(uri)` picks the source; all of them yield framed `Sentence`s (good and
bad checksums, see `stream.SentenceSplitter`) with `t_host`, and share `is_live`, `uri`,
`counters()` and `close()`:

- `SerialSource`: `/dev/ttyUSB0`, any character device or a symlink to one (`/dev/gnss`
  from a udev rule), or `serial:///dev/ttyUSB0?baud=115200`. `t_host` is read the moment a
  read returns. When the device disappears (USB unplugged, cable cut) the source counts a
  disconnect and tries to reopen the same path with exponential backoff, sleeping between
  tries: never a busy loop.
- `LogSource`: a plain NMEA text log (gpsd, u-center, `cat /dev/ttyUSB0 > log`), binary
  interleaving and all. A log has no receive times: `t_host` is the time the bytes were read.
- `RecordingSource`: the `/gnss/nmea` channel of an MCAP recording (format v1); each message
  is one sentence as received and `t_host` is its `log_time`, so replay gives the same
  times as the live run.
"""

from __future__ import annotations

import contextlib
import os
import stat
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol
from urllib.parse import parse_qs, urlsplit

from treetraits.drivers import DEFAULT_BAUD
from treetraits.drivers.gnss.sentences import Sentence
from treetraits.drivers.gnss.stream import SentenceSplitter
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.errors import SourceError

_READ_TIMEOUT_S = 0.1  # longest a serial read blocks, so close() and deadlines are seen
_LOG_CHUNK = 64 * 1024
_MCAP_MAGIC = b"\x89MCAP0\r\n"


@dataclass
class SourceStats:
    """What a source read, before splitting (the splitter counts the rest)."""

    reads: int = 0  # reads that returned bytes (serial, log) or messages (recording)
    bytes: int = 0
    disconnects: int = 0  # serial: the device went away (read error, unplugged)
    reconnects: int = 0  # serial: reopened after a disconnect
    open_failures: int = 0  # serial: reopen attempts that failed (device still missing)
    recording_truncated: bool = False  # recording: the file ends early or is corrupt

    def as_dict(self) -> dict[str, int | bool]:
        return asdict(self)


class GnssSource(Protocol):
    """What every GNSS source offers."""

    uri: str
    is_live: bool
    stats: SourceStats
    splitter: SentenceSplitter

    def __iter__(self) -> Iterator[Sentence]: ...

    def counters(self) -> dict[str, int | bool]: ...

    def close(self) -> None: ...


class _SplittingSource:
    """Shared by the sources: the splitter and the flat counters."""

    uri: str
    is_live: bool

    def __init__(self, uri: str, max_length: int | None = None):
        self.uri = uri
        self.stats = SourceStats()
        self.splitter = SentenceSplitter() if max_length is None else SentenceSplitter(max_length)

    def counters(self) -> dict[str, int | bool]:
        """Every counter of the source and its splitter in one flat dict; the splitter's
        byte count is the source's, so it appears once, as `bytes`."""
        merged: dict[str, int | bool] = dict(self.stats.as_dict())
        merged.update({k: v for k, v in self.splitter.stats.as_dict().items() if k != "bytes"})
        return merged


class LogSource(_SplittingSource):
    """A text log read front to back (see the module docstring)."""

    is_live = False

    def __init__(self, path: str | os.PathLike[str], max_length: int | None = None):
        super().__init__(os.fspath(path), max_length)
        try:
            self._file = open(path, "rb")  # noqa: SIM115 - closed by close()
        except OSError as exc:
            raise SourceError(f"{path}: cannot open ({exc.strerror or exc})") from exc

    def __iter__(self) -> Iterator[Sentence]:
        while chunk := self._file.read(_LOG_CHUNK):
            self.stats.reads += 1
            self.stats.bytes += len(chunk)
            yield from self.splitter.push(chunk, time.time_ns())
        yield from self.splitter.flush()

    def close(self) -> None:
        self._file.close()


class RecordingSource(_SplittingSource):
    """The `/gnss/nmea` messages of a recording; other topics are skipped. Each message is
    split on its own (it holds one sentence as received), t_host = its log_time."""

    is_live = False

    def __init__(self, path: str | os.PathLike[str], max_length: int | None = None):
        from treetraits.drivers import recording

        super().__init__(os.fspath(path), max_length)
        self._recording = recording.read_recording(path, topics=[recording.GNSS_NMEA])

    def __iter__(self) -> Iterator[Sentence]:
        for message in self._recording:
            self.stats.reads += 1
            self.stats.bytes += len(message.data)
            yield from self.splitter.push(bytes(message.data), message.log_time)
            yield from self.splitter.flush()
        # A chunk skipped as damaged is reported as a cut is: data was lost.
        self.stats.recording_truncated = self._recording.truncated or self._recording.lost_data

    @property
    def recording(self):
        """The recording's reader: what of it could not be read (treetraits/damage.py)."""
        return self._recording

    def close(self) -> None:
        self._recording.close()


class SerialSource(_SplittingSource):
    """A receiver on a serial port (see the module docstring).

    `read(timeout)` returns the next sentence or None when `timeout` seconds pass without
    one; iteration blocks until `close()` (callable from another thread). After a
    disconnect the port is reopened with backoff from `reopen_min_s` doubling to
    `reopen_max_s`; `reconnect=False` ends iteration instead. The port is opened
    exclusively: a second reader of the same device fails with a clear error.
    """

    is_live = True

    def __init__(
        self,
        device: str | os.PathLike[str],
        baud: int = DEFAULT_BAUD,
        *,
        reconnect: bool = True,
        reopen_min_s: float = 0.1,
        reopen_max_s: float = 2.0,
        max_length: int | None = None,
    ):
        try:
            import serial
        except ImportError as exc:  # pragma: no cover - a dependency of the package
            raise SourceError("reading a serial port needs pyserial: pip install pyserial") from exc
        self._serial = serial
        self.device = os.fspath(device)
        super().__init__(f"serial://{self.device}?baud={baud}", max_length)
        if baud <= 0:
            raise SourceError(f"baud rate must be positive, got {baud}")
        self.baud = baud
        self.reconnect = reconnect
        self.reopen_min_s = reopen_min_s
        self.reopen_max_s = reopen_max_s
        self.connected = False
        self._closed = False
        self._wake = threading.Event()  # set by close(): ends a backoff sleep at once
        self._queue: deque[Sentence] = deque()
        self._backoff = reopen_min_s
        self._next_attempt = 0.0
        self._port = self._open()

    @property
    def closed(self) -> bool:
        """True after close(), or after a disconnect when not reconnecting."""
        return self._closed

    def _open(self):
        try:
            port = self._serial.Serial(
                self.device, self.baud, timeout=_READ_TIMEOUT_S, exclusive=True
            )
        except (self._serial.SerialException, OSError, ValueError) as exc:
            raise SourceError(
                f"cannot open GNSS receiver {self.device} at {self.baud} baud: {exc}; is it "
                "plugged in (ls -l /dev/serial/by-id), is another program (gpsd, a second "
                "treetraits) reading it, and may this user read it (group dialout)?"
            ) from exc
        self.connected = True
        return port

    def read(self, timeout: float | None = None) -> Sentence | None:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            if self._queue:  # complete sentences go out even after close or unplug
                return self._queue.popleft()
            if self._closed:
                return None
            if self._port is None:
                if not self._reopen(deadline):
                    return None  # closed, out of time, or not reconnecting
                continue
            self._read_port()
            if deadline is not None and time.monotonic() >= deadline and not self._queue:
                return None

    def _read_port(self) -> None:
        try:
            data = self._port.read(1)  # blocks up to _READ_TIMEOUT_S for the first byte
            t_host = time.time_ns()  # when the bytes arrived, before reading the rest
            if data:
                waiting = self._port.in_waiting
                if waiting:
                    data += self._port.read(waiting)
        except (self._serial.SerialException, OSError, TypeError, AttributeError):
            # TypeError/AttributeError: pyserial's fd vanished under a concurrent close().
            if not self._closed:
                self._disconnected()
            return
        if data:
            self.stats.reads += 1
            self.stats.bytes += len(data)
            self._queue.extend(self.splitter.push(data, t_host))

    def _disconnected(self) -> None:
        self.stats.disconnects += 1
        self.connected = False
        self._queue.extend(self.splitter.flush())  # a sentence cut by the unplug: truncated
        with contextlib.suppress(Exception):
            self._port.close()
        self._port = None
        self._backoff = self.reopen_min_s
        self._next_attempt = time.monotonic() + self._backoff

    def _reopen(self, deadline: float | None) -> bool:
        """Sleep until the next attempt is due (or the deadline, or close()), then try to
        open the device again. True once it is open; False to return to the caller."""
        if not self.reconnect:
            self._closed = True
            return False
        while not self._closed:
            now = time.monotonic()
            if now >= self._next_attempt:
                try:
                    self._port = self._open()
                except SourceError:
                    self.stats.open_failures += 1
                    self._backoff = min(self._backoff * 2, self.reopen_max_s)
                    self._next_attempt = now + self._backoff
                else:
                    self.stats.reconnects += 1
                    return True
            if deadline is not None and now >= deadline:
                return False
            wait = self._next_attempt - now
            if deadline is not None:
                wait = min(wait, deadline - now)
            if self._wake.wait(max(wait, 0.0)):
                return False  # closed
        return False

    def __iter__(self) -> Iterator[Sentence]:
        while (sentence := self.read()) is not None:
            yield sentence

    def close(self) -> None:
        self._closed = True
        self._wake.set()
        port, self._port = self._port, None
        if port is not None:
            with contextlib.suppress(Exception):
                port.close()


def _serial_source(uri: str, baud: int | None, **options) -> SerialSource:
    parts = urlsplit(uri)
    query = {k: v[-1] for k, v in parse_qs(parts.query).items()}
    unknown = set(query) - {"baud"}
    if unknown:
        raise SourceError(f"{uri}: unknown option(s) {sorted(unknown)}; known: ['baud']")
    if baud is None:
        try:
            baud = int(query.get("baud", DEFAULT_BAUD))
        except ValueError as exc:
            raise SourceError(f"{uri}: baud must be an integer ({exc})") from exc
    device = (parts.netloc + parts.path) or ""
    if not device:
        raise SourceError(f"{uri}: no device; expected serial:///dev/ttyUSB0?baud=115200")
    return SerialSource(device, baud, **options)


def open_gnss_source(
    uri: str | os.PathLike[str], *, baud: int | None = None, **options
) -> GnssSource:
    """Open a GNSS source by URI (see the module docstring).

    - `serial:///dev/ttyUSB0?baud=115200`, or the path of a character device (a symlink to
      one included): a live receiver; `baud` overrides the URI's (default 9600);
    - a file starting with the MCAP magic: a recording (format v1);
    - any other file: a text log.

    `options` go to the source (`max_length`; for serial also `reconnect`,
    `reopen_min_s`, `reopen_max_s`). Raises SourceError when nothing can be opened.
    """
    text = os.fspath(uri)
    if text.startswith("serial://"):
        return _serial_source(text, baud, **options)
    path = Path(text)
    refuse_ros_bag(path, "an NMEA log or a recording")
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        hint = "is the receiver plugged in?" if text.startswith("/dev/") else "check the path"
        raise SourceError(
            f"{text}: no such file or device ({exc.strerror}); expected an NMEA text log, an "
            f"MCAP recording or a serial device; {hint}"
        ) from exc
    if stat.S_ISCHR(mode):
        return SerialSource(path, DEFAULT_BAUD if baud is None else baud, **options)
    if not stat.S_ISREG(mode):
        raise SourceError(
            f"{text}: not a file nor a character device; expected an NMEA text log, an MCAP "
            "recording or a serial device"
        )
    with open(path, "rb") as f:
        head = f.read(len(_MCAP_MAGIC))
    serial_only = {"reconnect", "reopen_min_s", "reopen_max_s"} & set(options)
    if serial_only:
        raise SourceError(f"{text}: {sorted(serial_only)} apply to serial devices only")
    if head == _MCAP_MAGIC:
        return RecordingSource(path, **options)
    return LogSource(path, **options)
