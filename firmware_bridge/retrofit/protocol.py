"""Retrofit encoder board protocol v1 (firmware_bridge/PROTOCOL.md): pure functions over bytes.

CRC-32C and COBS, the frame header, the message layouts as data, the message records,
and encoders that build frames byte for byte as the reference firmware does (the tests
hold the two to each other). Nothing here reads a port or keeps state across frames:
that is `reader.BridgeReader`'s job.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum, IntFlag

from treetraits.errors import ParseError

VERSION = 1
DELIMITER = 0x00
HEADER = struct.Struct("<BBHHQ")  # version, type, sequence, boot id, board clock (us since boot)
CRC = struct.Struct("<I")
MIN_FRAME = HEADER.size + CRC.size  # a v1 frame with an empty payload
MAX_FRAME = 254  # header + payload + CRC: one COBS block, so at most 255 bytes encoded
MAX_ENCODED = MAX_FRAME + 1
MAX_PAYLOAD = MAX_FRAME - MIN_FRAME


class MessageType(IntEnum):
    TICKS = 0x01
    HEARTBEAT = 0x02
    CONFIG_ECHO = 0x03


class Fault(IntFlag):
    """HEARTBEAT fault bits. Latched bits tell what happened since the previous heartbeat;
    sticky bits hold for the whole boot."""

    LEFT_GLITCH = 1 << 0  # latched: illegal A/B transition on the left encoder
    RIGHT_GLITCH = 1 << 1  # latched: illegal A/B transition on the right encoder
    TX_OVERFLOW = 1 << 2  # latched: a frame was dropped because the link was full
    LOOP_OVERRUN = 1 << 3  # latched: the board was late by a whole TICKS period
    WATCHDOG_RESET = 1 << 4  # sticky: this boot began with a watchdog reset
    BROWNOUT_RESET = 1 << 5  # sticky: this boot began with a supply brown-out
    CONFIG_DEFAULTS = 1 << 6  # sticky: the stored configuration was invalid; defaults in use


KNOWN_FAULTS = 0x7F

BOARDS = {0: "host-sim", 1: "rp2040"}

CONFIG_INVERT_LEFT = 1 << 0
CONFIG_INVERT_RIGHT = 1 << 1


@dataclass(frozen=True, slots=True)
class Layout:
    """A message's payload as v1 defines it. A later firmware may append fields: a payload
    longer than `body.size` is read for the known fields and the rest ignored."""

    type: MessageType
    body: struct.Struct
    fields: tuple[str, ...]


LAYOUTS: dict[int, Layout] = {
    MessageType.TICKS: Layout(
        MessageType.TICKS,
        struct.Struct("<iiII"),
        ("left", "right", "left_errors", "right_errors"),
    ),
    MessageType.HEARTBEAT: Layout(
        MessageType.HEARTBEAT,
        struct.Struct("<IIBBBB"),
        ("faults", "tx_dropped", "fw_major", "fw_minor", "fw_patch", "board"),
    ),
    MessageType.CONFIG_ECHO: Layout(
        MessageType.CONFIG_ECHO,
        struct.Struct("<IHHB"),
        ("ticks_per_rev", "tick_rate_hz", "heartbeat_period_ms", "flags"),
    ),
}


class FrameError(ParseError):
    """A delimited chunk that is not a frame this reader can use. `reason` is the counter
    it belongs to: bad_cobs, too_short, oversize, bad_crc, unknown_version, unknown_type,
    bad_length."""

    def __init__(self, reason: str, message: str):
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True, slots=True)
class Frame:
    """A v1 frame whose CRC checked: the header and the raw payload."""

    type: int
    seq: int
    boot_id: int
    t_device_us: int
    payload: bytes
    wire: bytes  # the COBS-encoded bytes as received, without delimiters


@dataclass(frozen=True, slots=True)
class Ticks:
    """Cumulative 4x quadrature counts, direction-corrected by the board (positive = the
    wheel's forward travel), as int32 that wrap; illegal A/B transitions as uint32."""

    t_host: int  # ns since the Unix epoch, when the frame's last byte was read
    seq: int
    boot_id: int  # drawn at random when the board boots
    t_device_us: int  # board clock, us since its boot, when the counts were sampled
    left: int
    right: int
    left_errors: int
    right_errors: int
    wire: bytes


@dataclass(frozen=True, slots=True)
class Heartbeat:
    """Once a second: fault bits, frames the board could not send, firmware version."""

    t_host: int
    seq: int
    boot_id: int
    t_device_us: int
    faults: int
    tx_dropped: int
    fw_major: int
    fw_minor: int
    fw_patch: int
    board: int
    wire: bytes

    @property
    def uptime_us(self) -> int:
        return self.t_device_us

    @property
    def firmware(self) -> str:
        return f"{self.fw_major}.{self.fw_minor}.{self.fw_patch}"

    @property
    def board_name(self) -> str:
        return BOARDS.get(self.board, f"unknown-{self.board}")

    @property
    def fault_names(self) -> list[str]:
        """Names of the bits set; bits v1 does not define show as `bit<N>`."""
        names = [f.name for f in Fault if self.faults & f and f.name]
        names += [f"bit{i}" for i in range(32) if self.faults & ~KNOWN_FAULTS & (1 << i)]
        return names


@dataclass(frozen=True, slots=True)
class ConfigEcho:
    """What the board is configured with: at boot, when the host opens the port (where the
    board can see it), and every 10 s."""

    t_host: int
    seq: int
    boot_id: int
    t_device_us: int
    ticks_per_rev: int  # 4x counts per wheel revolution, as calibration wheels.ticks_per_rev
    tick_rate_hz: int
    heartbeat_period_ms: int
    flags: int
    wire: bytes

    @property
    def invert_left(self) -> bool:
        return bool(self.flags & CONFIG_INVERT_LEFT)

    @property
    def invert_right(self) -> bool:
        return bool(self.flags & CONFIG_INVERT_RIGHT)


Message = Ticks | Heartbeat | ConfigEcho
_RECORDS: dict[int, type[Ticks] | type[Heartbeat] | type[ConfigEcho]] = {
    MessageType.TICKS: Ticks,
    MessageType.HEARTBEAT: Heartbeat,
    MessageType.CONFIG_ECHO: ConfigEcho,
}


def _crc32c_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x82F63B78 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC32C_TABLE = _crc32c_table()


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli): reflected poly 0x82F63B78, init and xorout 0xFFFFFFFF.
    crc32c(b"123456789") == 0xE3069283."""
    crc = 0xFFFFFFFF
    table = _CRC32C_TABLE
    for byte in data:
        crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
    return crc ^ 0xFFFFFFFF


def cobs_encode(data: bytes) -> bytes:
    """COBS (Cheshire & Baker 1999), as the firmware does it: data that ends in a full
    254-byte block gets no extra code byte after it."""
    out = bytearray(b"\x01")
    code_at = 0
    last = len(data) - 1
    for i, byte in enumerate(data):
        if byte == 0:
            code_at = len(out)
            out.append(1)
            continue
        out.append(byte)
        out[code_at] += 1
        if out[code_at] == 0xFF and i < last:
            code_at = len(out)
            out.append(1)
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Undo COBS. Also accepts the 0x01 code byte some encoders add after a final full
    block. Raises FrameError."""
    zero = data.find(b"\x00")
    if zero >= 0:
        raise FrameError("bad_cobs", f"COBS: a 0x00 inside a frame at byte {zero}")
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        end = i + code
        if end > n:
            raise FrameError(
                "bad_cobs", f"COBS: code {code} at byte {i} runs past the frame's {n} bytes"
            )
        out += data[i + 1 : end]
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def _int32(value: int) -> int:
    return (value + 0x8000_0000) % 0x1_0000_0000 - 0x8000_0000


def encode_frame(
    msg_type: int,
    seq: int,
    t_device_us: int,
    payload: bytes,
    *,
    boot_id: int = 0,
    version: int = VERSION,
) -> bytes:
    """One frame as it goes on the wire: 0x00, COBS(header + payload + CRC-32C), 0x00."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes; v1 allows at most {MAX_PAYLOAD}")
    body = HEADER.pack(version, msg_type, seq & 0xFFFF, boot_id, t_device_us) + payload
    return b"\x00" + cobs_encode(body + CRC.pack(crc32c(body))) + b"\x00"


def encode_ticks(
    seq: int,
    t_device_us: int,
    left: int,
    right: int,
    left_errors: int = 0,
    right_errors: int = 0,
    *,
    boot_id: int = 0,
) -> bytes:
    """A TICKS frame; counts wrap to int32 and error counts to uint32 as on the board."""
    body = LAYOUTS[MessageType.TICKS].body.pack(
        _int32(left), _int32(right), left_errors & 0xFFFFFFFF, right_errors & 0xFFFFFFFF
    )
    return encode_frame(MessageType.TICKS, seq, t_device_us, body, boot_id=boot_id)


def encode_heartbeat(
    seq: int,
    t_device_us: int,
    faults: int = 0,
    tx_dropped: int = 0,
    firmware: tuple[int, int, int] = (1, 0, 0),
    board: int = 0,
    *,
    boot_id: int = 0,
) -> bytes:
    body = LAYOUTS[MessageType.HEARTBEAT].body.pack(faults, tx_dropped, *firmware, board)
    return encode_frame(MessageType.HEARTBEAT, seq, t_device_us, body, boot_id=boot_id)


def encode_config_echo(
    seq: int,
    t_device_us: int,
    ticks_per_rev: int,
    tick_rate_hz: int = 100,
    heartbeat_period_ms: int = 1000,
    invert_left: bool = False,
    invert_right: bool = False,
    *,
    boot_id: int = 0,
) -> bytes:
    flags = (CONFIG_INVERT_LEFT if invert_left else 0) | (
        CONFIG_INVERT_RIGHT if invert_right else 0
    )
    body = LAYOUTS[MessageType.CONFIG_ECHO].body.pack(
        ticks_per_rev, tick_rate_hz, heartbeat_period_ms, flags
    )
    return encode_frame(MessageType.CONFIG_ECHO, seq, t_device_us, body, boot_id=boot_id)


def decode_frame(encoded: bytes) -> Frame:
    """The frame in one delimited chunk (the bytes between two 0x00, exclusive).

    Checks, in this order: length, COBS, CRC, version. Raises FrameError naming the
    counter the chunk belongs to.
    """
    if len(encoded) > MAX_ENCODED:
        raise FrameError(
            "oversize",
            f"{len(encoded)} bytes between delimiters; a v1 frame is at most "
            f"{MAX_ENCODED} (bytes lost, or not a treetraits bridge)",
        )
    raw = cobs_decode(encoded)
    if len(raw) < 1 + CRC.size:
        raise FrameError("too_short", f"frame of {len(raw)} bytes is too short to hold a CRC")
    (sent,) = CRC.unpack_from(raw, len(raw) - CRC.size)
    body = raw[: -CRC.size]
    if crc32c(body) != sent:
        raise FrameError("bad_crc", f"CRC-32C mismatch on a {len(raw)}-byte frame")
    if raw[0] != VERSION:
        # The CRC and the version byte's place are fixed across versions; nothing else is.
        raise FrameError(
            "unknown_version",
            f"protocol version {raw[0]}; this host reads version {VERSION}: update treetraits "
            "or flash the board with a matching firmware",
        )
    if len(body) < HEADER.size:
        raise FrameError("too_short", f"v1 frame of {len(raw)} bytes; the minimum is {MIN_FRAME}")
    _, msg_type, seq, boot_id, t_device_us = HEADER.unpack_from(body)
    return Frame(msg_type, seq, boot_id, t_device_us, body[HEADER.size :], bytes(encoded))


def decode_message(frame: Frame, t_host: int) -> Message:
    """The record for a checked frame. Raises FrameError for an unknown type or a payload
    shorter than the type's layout; longer payloads are read for the known fields."""
    layout = LAYOUTS.get(frame.type)
    if layout is None:
        raise FrameError("unknown_type", f"message type 0x{frame.type:02x} is not defined in v1")
    if len(frame.payload) < layout.body.size:
        raise FrameError(
            "bad_length",
            f"{layout.type.name} payload of {len(frame.payload)} bytes; v1 defines "
            f"{layout.body.size}",
        )
    values = dict(zip(layout.fields, layout.body.unpack_from(frame.payload), strict=True))
    return _RECORDS[frame.type](
        t_host=t_host,
        seq=frame.seq,
        boot_id=frame.boot_id,
        t_device_us=frame.t_device_us,
        wire=frame.wire,
        **values,
    )
