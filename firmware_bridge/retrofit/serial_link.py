"""The retrofit encoder board on a serial port (USB CDC or a UART adapter), via pyserial.

Two thin shells around the pure decoder:

- `SerialLink` reads the port and yields the bytes exactly as read (`BridgeChunk`, with
  `t_host`): what the recording stores on `/wheels/bridge`. When the device goes away
  (unplugged, board reset, pty closed) it yields a `LinkEvent("disconnected")`, closes the
  port and tries to open it again with an exponential backoff, waiting on an event between
  tries (no busy loop); a successful open yields `LinkEvent("connected")`.
- `RetrofitSource` feeds those bytes to a `BridgeDecoder` and yields `WheelSample`s
  (unit "ticks"), `Heartbeat`s, `ConfigEcho`s and the `LinkEvent`s, in order. An
  `on_chunk` callback sees every chunk first, for recording.

A host never writes to the board in protocol v1.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass

from treetraits.drivers.records import WheelSample
from treetraits.errors import SourceError
from treetraits.firmware_bridge.retrofit.protocol import ConfigEcho, Heartbeat
from treetraits.firmware_bridge.retrofit.reader import BridgeDecoder

DEFAULT_BAUDRATE = 115200  # a USB CDC board ignores it; never 1200 (resets a Pico to BOOTSEL)
DEFAULT_POLL_S = 0.1  # longest a read blocks before it looks at close() and deadlines
DEFAULT_BACKOFF_S = (0.1, 2.0)  # first and longest wait between tries to reopen
_MAX_CHUNK = 4096

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BridgeChunk:
    """Bytes as one read returned them: a chunk may hold part of a frame, or several."""

    data: bytes
    t_host: int  # ns since the Unix epoch, right after the read returned


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """The port came up ("connected") or went away ("disconnected")."""

    t_host: int
    kind: str
    port: str
    detail: str = ""


@dataclass
class LinkStats:
    bytes: int = 0
    chunks: int = 0
    connects: int = 0
    disconnects: int = 0
    open_failures: int = 0  # tries to reopen that failed (the device is still away)

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def _serial_module():
    try:
        import serial
    except ImportError as exc:  # pragma: no cover - a dependency of the project
        raise SourceError("reading a serial port needs pyserial: pip install pyserial") from exc
    return serial


class SerialLink:
    """A serial port read in chunks, reopened when the device comes back.

    `wait_for_port`: if the port cannot be opened at once, keep trying (the board may be
    plugged in later) instead of raising `SourceError`. `reconnect`: after a disconnect,
    reopen with backoff; without it iteration ends at the first disconnect.
    `close()` may be called from another thread: it ends a blocked `read` within
    `poll_s`, usually at once.
    """

    is_live = True

    def __init__(
        self,
        port: str,
        baudrate: int = DEFAULT_BAUDRATE,
        *,
        reconnect: bool = True,
        wait_for_port: bool = False,
        backoff_s: tuple[float, float] = DEFAULT_BACKOFF_S,
        poll_s: float = DEFAULT_POLL_S,
    ):
        if baudrate == 1200:
            raise SourceError("baud rate 1200 would reset a USB CDC Pico into BOOTSEL; use 115200")
        self.port = port
        self.uri = port
        self.baudrate = baudrate
        self.reconnect = reconnect
        self.stats = LinkStats()
        self._serial_mod = _serial_module()
        self._first_backoff, self._max_backoff = backoff_s
        self._backoff = self._first_backoff
        self._poll_s = poll_s
        self._serial = None
        self._closed = False
        self._ended = False  # disconnected with reconnect=False
        self._wake = threading.Event()
        self._next_try = 0.0  # monotonic time of the next open attempt
        self._pending: deque[LinkEvent] = deque()
        try:
            self._open()
        except SourceError:
            if not wait_for_port:
                raise
            self.stats.open_failures += 1
            self._schedule_retry()

    @property
    def connected(self) -> bool:
        return self._serial is not None

    @property
    def finished(self) -> bool:
        """Closed, or disconnected without `reconnect`: `read` returns None from now on."""
        return self._closed or self._ended

    def _open(self) -> None:
        serial = self._serial_mod
        try:
            port = serial.Serial(self.port, self.baudrate, timeout=self._poll_s, exclusive=True)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise SourceError(
                f"cannot open the encoder board's serial port {self.port}: {exc}; is the board "
                "plugged in and the path right (ls /dev/serial/by-id/), is the user in the "
                "'dialout' group, and is no other program reading the port?"
            ) from exc
        self._serial = port
        self._backoff = self._first_backoff
        self.stats.connects += 1
        self._pending.append(LinkEvent(time.time_ns(), "connected", self.port))
        log.info("encoder board connected on %s", self.port)

    def _schedule_retry(self) -> None:
        self._next_try = time.monotonic() + self._backoff
        self._backoff = min(self._backoff * 2, self._max_backoff)

    def _disconnected(self, reason: str) -> LinkEvent:
        port, self._serial = self._serial, None
        with contextlib.suppress(Exception):  # the device is gone: closing is best effort
            port.close()
        self.stats.disconnects += 1
        if self.reconnect:
            self._schedule_retry()
        else:
            self._ended = True
        log.warning("encoder board on %s disconnected: %s", self.port, reason)
        return LinkEvent(time.time_ns(), "disconnected", self.port, reason)

    def read(self, timeout: float | None = None) -> BridgeChunk | LinkEvent | None:
        """The next chunk or link event; None when `timeout` seconds pass without one, or
        when the link is closed (or ended without `reconnect`)."""
        deadline = None if timeout is None else time.monotonic() + timeout
        serial = self._serial_mod
        while not self._closed:
            if self._pending:
                return self._pending.popleft()
            if self._ended:
                return None
            now = time.monotonic()
            if deadline is not None and now >= deadline:
                return None
            if self._serial is None:
                wait = self._next_try - now
                if deadline is not None:
                    wait = min(wait, deadline - now)
                if wait > 0:
                    self._wake.wait(wait)  # set only by close()
                    continue
                try:
                    self._open()
                except SourceError:
                    self.stats.open_failures += 1
                    self._schedule_retry()
                continue
            try:
                data = self._serial.read(1)  # blocks up to poll_s
                if data:
                    waiting = self._serial.in_waiting
                    if waiting:
                        data += self._serial.read(min(waiting, _MAX_CHUNK))
            except (serial.SerialException, OSError, TypeError, ValueError) as exc:
                if self._closed:
                    return None
                return self._disconnected(str(exc))
            if data:
                self.stats.chunks += 1
                self.stats.bytes += len(data)
                return BridgeChunk(data, time.time_ns())
        return None

    def __iter__(self) -> Iterator[BridgeChunk | LinkEvent]:
        while (item := self.read()) is not None:
            yield item

    def close(self) -> None:
        self._closed = True
        self._wake.set()
        port = self._serial
        if port is not None:
            with contextlib.suppress(Exception):  # closing is best effort
                port.cancel_read()
                port.close()


class RetrofitSource:
    """An encoder board: `WheelSample`, `Heartbeat`, `ConfigEcho` and `LinkEvent` out.

    `ticks_per_rev`: the calibration's `wheels.ticks_per_rev`; a board that echoes another
    value is counted in `config_mismatches` and logged, since its samples would convert to
    the wrong distance. `on_chunk(chunk)` sees every chunk as read, before decoding.
    """

    is_live = True

    def __init__(
        self,
        link: SerialLink,
        *,
        ticks_per_rev: float | None = None,
        on_chunk: Callable[[BridgeChunk], None] | None = None,
    ):
        self.link = link
        self.uri = link.uri
        self.decoder = BridgeDecoder()
        self.ticks_per_rev = ticks_per_rev
        self.on_chunk = on_chunk
        self.config_mismatches = 0
        self._queue: deque[WheelSample | Heartbeat | ConfigEcho | LinkEvent] = deque()

    def read(
        self, timeout: float | None = None
    ) -> WheelSample | Heartbeat | ConfigEcho | LinkEvent | None:
        """The next item; None when `timeout` seconds pass without one or the link ends."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._queue:
            left = None if deadline is None else max(0.0, deadline - time.monotonic())
            got = self.link.read(left)
            if got is None:
                if self.link.finished:
                    self.decoder.flush()
                return None
            if isinstance(got, LinkEvent):
                if got.kind == "disconnected":
                    self.decoder.discontinuity()  # the next bytes start a new stream
                self._queue.append(got)
                break
            if self.on_chunk is not None:
                self.on_chunk(got)
            for item in self.decoder.push(got.data, got.t_host):
                if isinstance(item, ConfigEcho):
                    self._check_config(item)
                self._queue.append(item)
        return self._queue.popleft()

    def _check_config(self, config: ConfigEcho) -> None:
        if self.ticks_per_rev is None or config.ticks_per_rev == self.ticks_per_rev:
            return
        if self.config_mismatches == 0:
            log.warning(
                "encoder board on %s reports %d ticks per revolution but the calibration "
                "says wheels.ticks_per_rev = %s: distances will be wrong; fix one of them",
                self.uri,
                config.ticks_per_rev,
                self.ticks_per_rev,
            )
        self.config_mismatches += 1

    def __iter__(self) -> Iterator[WheelSample | Heartbeat | ConfigEcho | LinkEvent]:
        while (item := self.read()) is not None:
            yield item

    def counters(self) -> dict[str, int]:
        """The link's and the decoder's counters in one flat dict."""
        merged = {f"link_{k}": v for k, v in self.link.stats.as_dict().items()}
        merged.update(self.decoder.stats.as_dict())
        merged["odometer_restarts"] = self.decoder.odometer.restarts
        merged["config_mismatches"] = self.config_mismatches
        return merged

    def close(self) -> None:
        self.link.close()


def open_bridge(
    port: str,
    baudrate: int = DEFAULT_BAUDRATE,
    *,
    ticks_per_rev: float | None = None,
    on_chunk: Callable[[BridgeChunk], None] | None = None,
    **link_options,
) -> RetrofitSource:
    """Open an encoder board on `port` (e.g. /dev/serial/by-id/usb-Raspberry_Pi_Pico_...)."""
    link = SerialLink(port, baudrate, **link_options)
    return RetrofitSource(link, ticks_per_rev=ticks_per_rev, on_chunk=on_chunk)
