"""Bytes from a retrofit encoder board to records: push objects, no I/O.

`BridgeReader` splits the byte stream at the 0x00 delimiters, checks each frame and
returns the messages; everything it cannot use is counted, never raised. `TickOdometer`
turns TICKS into `WheelSample`s whose counts run on across int32 wraps and board
restarts. `BridgeDecoder` is the two together: what the live source and a replay of the
`/wheels/bridge` recording topic both use, so both give the same samples.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from treetraits.drivers.records import WheelSample
from treetraits.firmware_bridge.retrofit.protocol import (
    MAX_ENCODED,
    ConfigEcho,
    FrameError,
    Heartbeat,
    Message,
    Ticks,
    decode_frame,
    decode_message,
)

_SEQ_MOD = 1 << 16


@dataclass
class ReaderStats:
    """What the reader saw. Every delimited chunk is a message, or lands in exactly one of
    the rejection counters, or is the `leading` partial frame of a stream."""

    bytes: int = 0
    frames: int = 0  # CRC-checked v1 frames, known type or not
    ticks: int = 0
    heartbeats: int = 0
    configs: int = 0
    bad_cobs: int = 0
    too_short: int = 0
    oversize: int = 0  # no delimiter within a frame's maximum length
    bad_crc: int = 0
    unknown_version: int = 0  # skipped: a newer (or older) protocol version
    unknown_type: int = 0  # skipped: a v1 message type this host does not know
    bad_length: int = 0  # a known type with a payload shorter than its layout
    resyncs: int = 0  # times bytes were thrown away to find the next frame
    discarded_bytes: int = 0
    leading: int = 0  # the partial frame before the first delimiter of a stream
    truncated: int = 0  # a partial frame at the end of a stream or before a reconnect
    lost: int = 0  # frames missing from the sequence numbers
    sequence_jumps: int = 0  # sequence went backwards or jumped by half its range
    device_restarts: int = 0  # a new boot id (or the board clock went back): it rebooted

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


_REJECTIONS = {"bad_cobs", "too_short", "oversize", "bad_crc"}


class BridgeReader:
    """Protocol v1 byte stream in, `Ticks` / `Heartbeat` / `ConfigEcho` out, in order.

    Frames are delimited by 0x00 and carry their own CRC, so after any damage the reader
    is back in step at the next delimiter. A message's `t_host` is that of the `push` that
    delivered its closing delimiter. Lost frames are counted from the sequence numbers;
    a new boot id (or a board clock that goes backwards) is a restart, not a loss.
    """

    def __init__(self) -> None:
        self.stats = ReaderStats()
        self._partial = bytearray()
        self._skipping = False  # inside an oversize run: drop until the next delimiter
        self._at_start = True  # the first chunk of a stream may be the tail of a frame
        self._last: tuple[int, int, int] | None = None  # seq, boot id, board clock

    def push(self, data: bytes, t_host: int) -> list[Message]:
        """Feed bytes as read from the port. Never raises on bad bytes."""
        self.stats.bytes += len(data)
        out: list[Message] = []
        start = 0
        while (end := data.find(b"\x00", start)) >= 0:
            if self._skipping:
                self.stats.discarded_bytes += end - start
                self._skipping = False
            else:
                if self._partial:
                    self._partial += data[start:end]
                    chunk = bytes(self._partial)
                    self._partial.clear()
                else:
                    chunk = data[start:end]
                if chunk:
                    self._chunk(chunk, t_host, out)
            self._at_start = False
            start = end + 1
        rest = len(data) - start
        if self._skipping:
            self.stats.discarded_bytes += rest
        elif rest:
            self._partial += data[start:]
            if len(self._partial) > MAX_ENCODED:
                self.stats.oversize += 1
                self._resync(len(self._partial))
                self._partial.clear()
                self._skipping = True
        return out

    def discontinuity(self) -> None:
        """The byte stream broke (the port was closed and opened again): drop the partial
        frame. The sequence is kept: frames the board sent meanwhile count as lost."""
        if self._partial or self._skipping:
            self.stats.truncated += 1
            self.stats.discarded_bytes += len(self._partial)
        self._partial.clear()
        self._skipping = False
        self._at_start = True

    def flush(self) -> None:
        """End of the stream: a partial frame left over is counted as truncated."""
        self.discontinuity()

    def _resync(self, discarded: int) -> None:
        self.stats.resyncs += 1
        self.stats.discarded_bytes += discarded

    def _chunk(self, chunk: bytes, t_host: int, out: list[Message]) -> None:
        try:
            frame = decode_frame(chunk)
        except FrameError as exc:
            if exc.reason in _REJECTIONS and self._at_start:
                self.stats.leading += 1  # we began reading in the middle of a frame
                self.stats.discarded_bytes += len(chunk)
                return
            setattr(self.stats, exc.reason, getattr(self.stats, exc.reason) + 1)
            if exc.reason in _REJECTIONS:
                self._resync(len(chunk))
            return
        self.stats.frames += 1
        self._sequence(frame.seq, frame.boot_id, frame.t_device_us)
        try:
            message = decode_message(frame, t_host)
        except FrameError as exc:
            setattr(self.stats, exc.reason, getattr(self.stats, exc.reason) + 1)
            return
        if isinstance(message, Ticks):
            self.stats.ticks += 1
        elif isinstance(message, Heartbeat):
            self.stats.heartbeats += 1
        else:
            self.stats.configs += 1
        out.append(message)

    def _sequence(self, seq: int, boot_id: int, t_device_us: int) -> None:
        if self._last is not None:
            last_seq, last_boot, last_t = self._last
            if boot_id != last_boot or t_device_us < last_t:
                self.stats.device_restarts += 1  # a new boot numbers its frames from 0
            else:
                gap = (seq - last_seq - 1) % _SEQ_MOD
                if gap >= _SEQ_MOD // 2:
                    self.stats.sequence_jumps += 1  # repeated or reordered: nothing to count
                else:
                    self.stats.lost += gap
        self._last = (seq, boot_id, t_device_us)


def _delta32(new: int, old: int) -> int:
    """The signed step from `old` to `new` of a counter that wraps as int32."""
    return (new - old + 0x8000_0000) % 0x1_0000_0000 - 0x8000_0000


class TickOdometer:
    """TICKS to `WheelSample`s (unit "ticks") that never wrap or restart.

    The first sample reports the board's own counts; later ones add the signed int32
    step from the previous frame, so a wrap is invisible. When the boot id changes (or the
    board clock goes backwards) the board has rebooted and counts again from zero: its new
    counts are added to the totals so far (travel while it was rebooting is not known).
    """

    def __init__(self) -> None:
        self.restarts = 0
        self._last: Ticks | None = None
        self._left = 0
        self._right = 0

    def sample(self, ticks: Ticks) -> WheelSample:
        last = self._last
        if last is None:
            self._left, self._right = ticks.left, ticks.right
        elif ticks.boot_id != last.boot_id or ticks.t_device_us < last.t_device_us:
            self.restarts += 1
            self._left += ticks.left
            self._right += ticks.right
        else:
            self._left += _delta32(ticks.left, last.left)
            self._right += _delta32(ticks.right, last.right)
        self._last = ticks
        return WheelSample(
            t_host=ticks.t_host,
            left=float(self._left),
            right=float(self._right),
            unit="ticks",
            t_device_us=ticks.t_device_us,
        )


class BridgeDecoder:
    """A `BridgeReader` and a `TickOdometer`: bytes in, `WheelSample`, `Heartbeat` and
    `ConfigEcho` out. `config` holds the last ConfigEcho, `heartbeat` the last Heartbeat."""

    def __init__(self) -> None:
        self.reader = BridgeReader()
        self.odometer = TickOdometer()
        self.config: ConfigEcho | None = None
        self.heartbeat: Heartbeat | None = None

    def push(self, data: bytes, t_host: int) -> list[WheelSample | Heartbeat | ConfigEcho]:
        out: list[WheelSample | Heartbeat | ConfigEcho] = []
        for message in self.reader.push(data, t_host):
            if isinstance(message, Ticks):
                out.append(self.odometer.sample(message))
                continue
            if isinstance(message, Heartbeat):
                self.heartbeat = message
            else:
                self.config = message
            out.append(message)
        return out

    def discontinuity(self) -> None:
        self.reader.discontinuity()

    def flush(self) -> None:
        self.reader.flush()

    @property
    def stats(self) -> ReaderStats:
        return self.reader.stats
