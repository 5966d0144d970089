"""rosserial protocol v2 ("Hydro and later") framing, without ROS: pure functions over bytes.

A frame is `ff fe | len u16 | len checksum | topic u16 | payload | data checksum` (all
little-endian, 8 bytes of overhead). The length checksum makes `lenLo + lenHi + chk` end in
0xFF; the data checksum does the same over `topicLo + topicHi + payload + chk`. The payload
is a ROS 1 serialized message with no length prefix of its own.

`FrameReader` is the push decoder: bytes in (any chunking), complete frames out. It hunts
for `ff fe`, checks both checksums and, on any failure, drops a single byte and hunts again
from there, so a real frame hidden behind a false header is still found. Every byte read
ends up counted exactly once: in a frame, skipped, or still pending.

Also here: the reserved topic ids, `TopicInfo` (how the MCU names its topics and their ids
during negotiation), `rosserial_msgs/Log`, and builders for the few frames the host sends
(request topics, time reply, TX stop). See docs/jackal.md.
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass

from treetraits.errors import ParseError

SYNC = b"\xff\xfe"  # sync byte + protocol version 2
PROTOCOL_V1 = 0xFF  # Groovy and earlier: not supported (different header order)
OVERHEAD = 8  # sync, version, length (2), length checksum, topic (2) ... data checksum
HEADER_SIZE = 7

# Reserved topic ids (rosserial_msgs/TopicInfo constants); user topics start at 100.
ID_PUBLISHER = 0  # host -> MCU: "request topics" (empty); MCU -> host: a publisher's TopicInfo
ID_SUBSCRIBER = 1  # MCU -> host: a subscriber's TopicInfo
ID_SERVICE_SERVER = 2
ID_SERVICE_CLIENT = 4  # +0 publisher side, +1 subscriber side
ID_PARAMETER_REQUEST = 6
ID_LOG = 7
ID_TIME = 10  # both ways: MCU time request, host time reply (std_msgs/Time)
ID_TX_STOP = 11  # host -> MCU: the host is going away
FIRST_USER_ID = 100

# rosserial_server reads into a 1023-byte buffer; a longer declared length is almost surely a
# false header, and waiting for its bytes would only delay the frames behind it.
DEFAULT_MAX_PAYLOAD = 1024

_TIME = struct.Struct("<II")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_I32 = struct.Struct("<i")


def _checksum(data: bytes | bytearray | memoryview) -> int:
    """The byte that makes `sum(data) + byte` end in 0xFF."""
    return 255 - (sum(data) & 0xFF)


@dataclass(frozen=True, slots=True)
class Frame:
    """One frame as it came off the wire: its topic id and payload (the serialized message)."""

    topic_id: int
    payload: bytes

    @property
    def raw(self) -> bytes:
        """The frame's exact bytes (checksums are a function of the contents)."""
        return encode_frame(self.topic_id, self.payload)


def encode_frame(topic_id: int, payload: bytes = b"") -> bytes:
    """A complete v2 frame. Write it to the MCU in one call: the client drops a frame that
    is not complete within 20 ms of its first byte."""
    if not 0 <= topic_id <= 0xFFFF:
        raise ValueError(f"topic id must fit in uint16, got {topic_id}")
    if len(payload) > 0xFFFF:
        raise ValueError(f"payload of {len(payload)} bytes does not fit the uint16 length")
    length = _U16.pack(len(payload))
    topic = _U16.pack(topic_id)
    return b"".join(
        (
            SYNC,
            length,
            bytes((_checksum(length),)),
            topic,
            payload,
            bytes((_checksum(topic + payload),)),
        )
    )


def decode_frame(data: bytes) -> Frame:
    """Exactly one complete frame, or `ParseError` saying what is wrong with it."""
    if len(data) < OVERHEAD:
        raise ParseError(f"a rosserial frame is at least {OVERHEAD} bytes, got {len(data)}")
    if data[:2] != SYNC:
        hint = " (protocol v1, pre-Hydro firmware?)" if data[:2] == b"\xff\xff" else ""
        raise ParseError(f"expected sync ff fe, got {data[:2].hex(' ')}{hint}")
    if (data[2] + data[3] + data[4]) & 0xFF != 0xFF:
        raise ParseError(
            f"bad length checksum {data[4]:#04x} for length bytes {data[2:4].hex(' ')}"
        )
    length = data[2] | data[3] << 8
    if len(data) != length + OVERHEAD:
        raise ParseError(
            f"header says {length} payload bytes ({length + OVERHEAD} in all), got {len(data)}"
        )
    if sum(data[5:]) & 0xFF != 0xFF:
        raise ParseError(f"bad data checksum {data[-1]:#04x} on topic {data[5] | data[6] << 8}")
    return Frame(data[5] | data[6] << 8, bytes(data[HEADER_SIZE:-1]))


@dataclass
class FrameStats:
    """What the frame reader saw. `bytes` = `framed_bytes` + `skipped_bytes` + pending."""

    bytes: int = 0  # fed in
    frames: int = 0  # good frames out
    framed_bytes: int = 0  # bytes inside good frames, overhead included
    skipped_bytes: int = 0  # outside any good frame: noise, broken frames, resync
    bad_length_checksum: int = 0
    bad_data_checksum: int = 0
    oversize: int = 0  # a header declaring more than `max_payload` bytes

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class FrameReader:
    """Push decoder: `push(bytes)` returns the frames completed by those bytes.

    Never raises on bad input; every rejected candidate is counted in `stats` and the
    hunt for `ff fe` restarts one byte after its first sync byte.
    """

    def __init__(self, max_payload: int = DEFAULT_MAX_PAYLOAD):
        if not 0 <= max_payload <= 0xFFFF:
            raise ValueError(f"max_payload must be in [0, 65535], got {max_payload}")
        self.max_payload = max_payload
        self.stats = FrameStats()
        self._buf = bytearray()

    @property
    def pending(self) -> int:
        """Bytes held back: a frame still arriving, or a trailing 0xFF that may start one."""
        return len(self._buf)

    def reset(self) -> None:
        """Forget a partial frame (after reconnecting): its bytes count as skipped."""
        self.stats.skipped_bytes += len(self._buf)
        self._buf.clear()

    def push(self, data: bytes) -> list[Frame]:
        stats = self.stats
        stats.bytes += len(data)
        buf = self._buf
        buf += data
        frames: list[Frame] = []
        pos = 0
        end = len(buf)
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                keep = pos < end and buf[end - 1] == 0xFF  # may be the first half of a sync
                stop = end - 1 if keep else end
                stats.skipped_bytes += stop - pos
                pos = stop
                break
            stats.skipped_bytes += start - pos
            pos = start
            if end - pos < 5:
                break  # the length and its checksum are not here yet
            if (buf[pos + 2] + buf[pos + 3] + buf[pos + 4]) & 0xFF != 0xFF:
                stats.bad_length_checksum += 1
                stats.skipped_bytes += 1
                pos += 1
                continue
            length = buf[pos + 2] | buf[pos + 3] << 8
            if length > self.max_payload:
                stats.oversize += 1
                stats.skipped_bytes += 1
                pos += 1
                continue
            total = length + OVERHEAD
            if end - pos < total:
                break  # wait for the rest
            if sum(memoryview(buf)[pos + 5 : pos + total]) & 0xFF != 0xFF:
                stats.bad_data_checksum += 1
                stats.skipped_bytes += 1
                pos += 1
                continue
            topic = buf[pos + 5] | buf[pos + 6] << 8
            frames.append(Frame(topic, bytes(buf[pos + HEADER_SIZE : pos + total - 1])))
            stats.frames += 1
            stats.framed_bytes += total
            pos += total
        del buf[:pos]
        return frames


# --- rosserial_msgs: the negotiation and log messages --------------------------------------

TOPIC_INFO_MD5 = "0ad51f88fc44892f8c10684077646005"
LOG_MD5 = "11abd731c25933261cd6183bd12d6295"
LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")  # rosserial_msgs/Log ROSDEBUG..FATAL


class _Cursor:
    """Reads ROS 1 primitives from a payload, raising `ParseError` when it runs short."""

    __slots__ = ("data", "offset", "what")

    def __init__(self, data: bytes, what: str):
        self.data = data
        self.offset = 0
        self.what = what

    def take(self, n: int) -> bytes:
        if self.offset + n > len(self.data):
            raise ParseError(
                f"{self.what}: needs {self.offset + n} bytes, payload has {len(self.data)}"
            )
        chunk = self.data[self.offset : self.offset + n]
        self.offset += n
        return chunk

    def unpack(self, st: struct.Struct) -> tuple:
        return st.unpack(self.take(st.size))

    def string(self) -> str:
        (n,) = self.unpack(_U32)
        return self.take(n).decode("utf-8", errors="replace")

    def done(self) -> None:
        if self.offset != len(self.data):
            raise ParseError(
                f"{self.what}: {len(self.data) - self.offset} unexpected bytes after the message"
            )


def _string(text: str) -> bytes:
    data = text.encode()
    return _U32.pack(len(data)) + data


@dataclass(frozen=True, slots=True)
class TopicInfo:
    """rosserial_msgs/TopicInfo: what the MCU says about one of its topics during negotiation.
    Sent on `ID_PUBLISHER` for the MCU's publishers and `ID_SUBSCRIBER` for its subscribers."""

    topic_id: int
    topic_name: str
    message_type: str
    md5sum: str
    buffer_size: int

    @classmethod
    def decode(cls, payload: bytes) -> TopicInfo:
        cur = _Cursor(payload, "TopicInfo")
        (topic_id,) = cur.unpack(_U16)
        name, message_type, md5sum = cur.string(), cur.string(), cur.string()
        (buffer_size,) = cur.unpack(_I32)
        cur.done()
        return cls(topic_id, name, message_type, md5sum, buffer_size)

    def encode(self) -> bytes:
        return b"".join(
            (
                _U16.pack(self.topic_id),
                _string(self.topic_name),
                _string(self.message_type),
                _string(self.md5sum),
                _I32.pack(self.buffer_size),
            )
        )

    @property
    def name(self) -> str:
        """The topic name without a leading slash (firmware may send either form)."""
        return self.topic_name.lstrip("/")


@dataclass(frozen=True, slots=True)
class Log:
    """rosserial_msgs/Log: a message the firmware logged (level 0 debug .. 4 fatal)."""

    level: int
    msg: str

    @classmethod
    def decode(cls, payload: bytes) -> Log:
        cur = _Cursor(payload, "Log")
        (level,) = cur.take(1)
        msg = cur.string()
        cur.done()
        return cls(level, msg)

    @property
    def level_name(self) -> str:
        return LOG_LEVELS[self.level] if self.level < len(LOG_LEVELS) else str(self.level)


# --- the frames the host sends --------------------------------------------------------------

REQUEST_TOPICS = encode_frame(ID_PUBLISHER)  # ff fe 00 00 ff 00 00 ff
TX_STOP = encode_frame(ID_TX_STOP)  # ff fe 00 00 ff 0b 00 f4


def encode_time(t_ns: int) -> bytes:
    """std_msgs/Time (uint32 sec, uint32 nsec) for a time in ns since the Unix epoch."""
    sec, nsec = divmod(t_ns, 1_000_000_000)
    return _TIME.pack(sec & 0xFFFFFFFF, nsec)


def decode_time(payload: bytes) -> int:
    """std_msgs/Time payload -> ns since the Unix epoch."""
    if len(payload) != _TIME.size:
        raise ParseError(f"std_msgs/Time is {_TIME.size} bytes, got {len(payload)}")
    sec, nsec = _TIME.unpack(payload)
    return sec * 1_000_000_000 + nsec


def time_reply(t_ns: int) -> bytes:
    """The answer to the MCU's time request: the host clock on `ID_TIME`."""
    return encode_frame(ID_TIME, encode_time(t_ns))
