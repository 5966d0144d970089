"""Recording format v1: every sensor's raw bytes in one MCAP file, written and read back.

The onboard recorder writes what each sensor sent, exactly as received, so a field day can
be replayed through the same drivers later. The format (frozen, see docs/architecture.md):

- one MCAP file, zstd-compressed chunks;
- one channel per sensor stream, no schema (schema id 0), the `message_encoding` naming the
  wire format (`TOPIC_ENCODINGS`);
- `log_time` = host receive time, `publish_time` = the sensor's own UTC time where it has
  one, else the host time; both in ns since the Unix epoch;
- a metadata record named `treetraits` holding `format_version` ("1"; "1.1" for a
  recording that carries the motion and points channels of `V11_TOPICS`), `software` and
  `calibration` (a JSON object as a string);
- attachments may hold the field map (`field_map.geojson`).

`RecordingWriter` writes such a file; `read_recording` reads one linearly, so a file cut by
a power failure still yields every message of every chunk completed before the cut, and a
damaged chunk is skipped (reading resumes at the next good one) and accounted for.
"""

from __future__ import annotations

import contextlib
import io
import json
import mmap
import operator
import os
import re
import struct
import time
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any

import zstandard
from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

import treetraits
from treetraits.drivers.jsontext import loads_limited
from treetraits.errors import SourceError

FORMAT_VERSION = "1"
# Format 1.1 adds the motion and points channels (`V11_TOPICS`); a writer marks a recording 1.1 only
# when asked to, so a recording without them stays readable by format-1 readers.
FORMAT_VERSION_MOTION = "1.1"
READ_VERSIONS = (FORMAT_VERSION, FORMAT_VERSION_MOTION)
METADATA_NAME = "treetraits"
SOFTWARE = f"treetraits {treetraits.__version__}"

LIDAR_PACKETS = "/lidar/packets"
LIDAR_TELEMETRY = "/lidar/telemetry"
CAMERA_JPEG = "/camera/jpeg"
GNSS_NMEA = "/gnss/nmea"
WHEELS_JACKAL = "/wheels/jackal"
WHEELS_BRIDGE = "/wheels/bridge"
WHEELS_ODOMETRY = "/wheels/odometry"
IMU_DATA = "/imu/data"
LIDAR_POINTS = "/lidar/points"

# Topic -> message_encoding, the only channels a v1 recording is written with.
TOPIC_ENCODINGS: Mapping[str, str] = {
    LIDAR_PACKETS: "velodyne-data",  # one 1206-byte UDP payload from port 2368
    LIDAR_TELEMETRY: "velodyne-position",  # one 512-byte UDP payload from port 8308
    CAMERA_JPEG: "jpeg",
    GNSS_NMEA: "nmea0183",
    WHEELS_JACKAL: "rosserial",
    WHEELS_BRIDGE: "treetraits-bridge",
    # Format 1.1 (drivers/motion.py): a robot's odometry and an IMU given as numbers.
    WHEELS_ODOMETRY: "treetraits-odometry",
    IMU_DATA: "treetraits-imu",
    # Format 1.1 (drivers/points.py): a decoded point cloud, one message per scan.
    LIDAR_POINTS: "treetraits-points",
}
V11_TOPICS = frozenset({WHEELS_ODOMETRY, IMU_DATA, LIDAR_POINTS})

FIELD_MAP_NAME = "field_map.geojson"
FIELD_MAP_MEDIA_TYPE = "application/geo+json"

# Chunks are compressed and written whole, so a power cut loses the chunk in progress:
# 256 KiB is about a second of VLP-16 traffic.
DEFAULT_CHUNK_SIZE = 256 * 1024
# No record of a v1 recording (chunk, attachment), compressed or not, is larger than this;
# a bigger length read from a file is garbage (a torn write) and ends the reading.
RECORD_SIZE_LIMIT = 64 * 1024 * 1024

_MCAP_MAGIC = b"\x89MCAP0\r\n"
_U32 = 1 << 32
_U64 = 1 << 64


class _CorruptRecordError(Exception):
    """A length or size in the file that no valid v1 recording has."""


# What mcap and zstandard raise on a torn or corrupt file (CRC mismatches are ValueErrors,
# short fields struct.errors, bad strings UnicodeDecodeErrors, a field length past any
# index, which mcap hands to read(), OverflowErrors).
_READ_ERRORS = (
    McapError,
    ValueError,
    OverflowError,
    struct.error,
    zstandard.ZstdError,
    _CorruptRecordError,
)


@dataclass(frozen=True, slots=True)
class RecordedMessage:
    """One message of a recording: the sensor's bytes exactly as received.

    `log_time` is the host receive time, `publish_time` the sensor's own UTC time (or the
    host time when the sensor has none), both ns since the Unix epoch; `sequence` counts the
    messages of the topic from 0 in the writer.
    """

    topic: str
    log_time: int
    publish_time: int
    sequence: int
    data: bytes


@dataclass(frozen=True, slots=True)
class RecordingMetadata:
    """The `treetraits` metadata record of a recording, calibration parsed back to a dict."""

    format_version: str
    software: str
    calibration: dict[str, Any]


@dataclass(frozen=True, slots=True)
class RecordedAttachment:
    """An attachment of a recording (e.g. the field map)."""

    name: str
    media_type: str
    log_time: int
    create_time: int
    data: bytes


def _time_ns(value: int, what: str) -> int:
    """An MCAP timestamp: an integer in [0, 2**64)."""
    try:
        value = operator.index(value)
    except TypeError:
        raise TypeError(f"{what} must be an int in ns, got {type(value).__name__}") from None
    if not 0 <= value < _U64:
        raise ValueError(f"{what} must be in [0, 2**64) ns, got {value}")
    return value


class RecordingWriter:
    """Writes a recording (format v1) to a path or a binary stream.

    Use it as a context manager, or call `close()`: only a closed recording has its summary
    (indexes, statistics) and is fsynced. A recording left unclosed by a crash is still
    readable up to its last complete chunk.

    A path is created, never overwritten unless `overwrite` is set. A stream must support
    `write()` and `tell()`; it is flushed (and fsynced when it has a file descriptor) but
    not closed. `calibration` must be JSON-serializable; it is stored as a JSON string.

    For live recording, bound what a crash loses (both off by default, which keeps chunks
    in memory until they exceed `chunk_size` and buffers the stream as it likes):
    - `max_chunk_age_s`: a chunk open that long is closed at the next `write()`, so a
      slow stream (GNSS alone) still reaches the disk within about that time;
    - `fsync_every_s`: fsync at most this often, when a chunk is written.
    With either set, every chunk is flushed to the OS as soon as it is written, so a
    kill -9 loses only the open chunk. `flush()` closes the open chunk on demand.
    """

    def __init__(
        self,
        output: str | os.PathLike[str] | IO[bytes],
        *,
        calibration: Mapping[str, Any] | None = None,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        overwrite: bool = False,
        max_chunk_age_s: float | None = None,
        fsync_every_s: float | None = None,
        format_version: str = FORMAT_VERSION,
    ):
        if format_version not in READ_VERSIONS:
            raise ValueError(
                f"format_version must be one of {READ_VERSIONS}, got {format_version!r}"
            )
        self.format_version = format_version
        if chunk_size <= 0:
            raise ValueError(f"chunk_size must be positive, got {chunk_size}")
        for name, value in (("max_chunk_age_s", max_chunk_age_s), ("fsync_every_s", fsync_every_s)):
            if value is not None and not value > 0:
                raise ValueError(f"{name} must be positive seconds or None, got {value}")
        self._max_chunk_age_s = max_chunk_age_s
        self._fsync_every_s = fsync_every_s
        self._streaming = max_chunk_age_s is not None or fsync_every_s is not None
        self._chunk_opened: float | None = None  # monotonic time of the open chunk's first message
        self._last_fsync = time.monotonic()
        calibration_json = json.dumps(
            dict(calibration or {}), sort_keys=True, allow_nan=False, separators=(",", ":")
        )
        self._path: Path | None
        self._file: IO[bytes]
        if isinstance(output, (str, os.PathLike)):
            self._path = Path(output)
            self._file = open(self._path, "wb" if overwrite else "xb")  # noqa: SIM115
        else:
            self._path = None
            self._file = output
        self._channels: dict[str, int] = {}
        self._sequences: dict[str, int] = {}
        self._closed = False
        self._handed_over = 0  # stream position last handed to the OS (streaming mode)
        self._final_size = 0
        try:
            self._writer = Writer(
                self._file, chunk_size=chunk_size, compression=CompressionType.ZSTD
            )
            self._writer.start(profile="", library=f"{SOFTWARE}; {LIBRARY_IDENTIFIER}")
            self._writer.add_metadata(
                METADATA_NAME,
                {
                    "format_version": format_version,
                    "software": SOFTWARE,
                    "calibration": calibration_json,
                },
            )
        except BaseException:
            if self._path is not None:
                self._file.close()
            raise

    @property
    def closed(self) -> bool:
        return self._closed

    def write(
        self, topic: str, data: bytes, log_time: int, publish_time: int | None = None
    ) -> None:
        """Append one message: `data` exactly as received, times in ns since the epoch.

        `publish_time` defaults to `log_time` (for sensors without their own clock).
        Raises ValueError for a topic outside `TOPIC_ENCODINGS`, or of format 1.1 in a
        recording written as format 1.
        """
        if self._closed:
            raise ValueError("write to a closed recording")
        encoding = TOPIC_ENCODINGS.get(topic)
        if encoding is None:
            raise ValueError(
                f"unknown topic {topic!r}: a v1 recording carries only {', '.join(TOPIC_ENCODINGS)}"
            )
        if topic in V11_TOPICS and self.format_version == FORMAT_VERSION:
            raise ValueError(
                f"topic {topic!r} is of format {FORMAT_VERSION_MOTION}: "
                f"write with format_version={FORMAT_VERSION_MOTION!r}"
            )
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"data must be bytes, got {type(data).__name__}")
        log_time = _time_ns(log_time, "log_time")
        publish_time = log_time if publish_time is None else _time_ns(publish_time, "publish_time")
        channel_id = self._channels.get(topic)
        if channel_id is None:
            channel_id = self._writer.register_channel(topic, encoding, schema_id=0)
            self._channels[topic] = channel_id
            self._sequences[topic] = 0
        sequence = self._sequences[topic]
        self._sequences[topic] = (sequence + 1) % _U32  # MCAP sequences are uint32
        self._writer.add_message(
            channel_id,
            log_time=log_time,
            data=bytes(data),
            publish_time=publish_time,
            sequence=sequence,
        )
        if not self._streaming:
            return
        # In chunked mode the writer writes to the stream only when it closes a chunk (or
        # writes an attachment), so a moved position means something to hand to the OS.
        if self._file.tell() != self._handed_over:
            self._chunk_written()
        elif self._chunk_opened is None:
            self._chunk_opened = time.monotonic()
        elif (
            self._max_chunk_age_s is not None
            and time.monotonic() - self._chunk_opened >= self._max_chunk_age_s
        ):
            self._writer.flush()
            self._chunk_written()

    def _chunk_written(self) -> None:
        """A chunk just went to the stream: hand it to the OS, fsync if it is time."""
        self._chunk_opened = None
        self._file.flush()
        self._handed_over = self._file.tell()
        if (
            self._fsync_every_s is not None
            and time.monotonic() - self._last_fsync >= self._fsync_every_s
        ):
            self._fsync()

    def flush(self, *, fsync: bool = False) -> None:
        """Close the open chunk (if it holds messages), write it and everything buffered
        to the OS, and fsync when `fsync` is set. Compression works per chunk, so flushing
        often costs compression ratio."""
        if self._closed:
            raise ValueError("flush of a closed recording")
        self._writer.flush()
        self._chunk_opened = None
        self._handed_over = self._file.tell()
        if fsync:
            self._fsync()

    @property
    def bytes_written(self) -> int:
        """Bytes handed to the output so far (the open chunk, still in memory, excluded);
        after `close()`, the size of the finished recording."""
        if self._closed:
            return self._final_size
        return self._file.tell()

    def abort(self) -> None:
        """Close without writing the open chunk or the summary, e.g. after a write failed
        (disk full): the file stays readable up to its last complete chunk. Errors while
        closing are swallowed, since the file is already known to be broken. Idempotent."""
        if self._closed:
            return
        self._closed = True
        with contextlib.suppress(OSError, ValueError):
            self._final_size = self._file.tell()
        if self._path is not None:
            with contextlib.suppress(OSError, ValueError):
                self._file.close()

    def attach(
        self,
        name: str,
        data: bytes,
        media_type: str,
        *,
        log_time: int | None = None,
        create_time: int = 0,
    ) -> None:
        """Attach a file (e.g. `FIELD_MAP_NAME`, `FIELD_MAP_MEDIA_TYPE`).

        `log_time` defaults to now; `create_time` 0 means unknown.
        """
        if self._closed:
            raise ValueError("attach to a closed recording")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"data must be bytes, got {type(data).__name__}")
        self._writer.add_attachment(
            create_time=_time_ns(create_time, "create_time"),
            log_time=_time_ns(time.time_ns() if log_time is None else log_time, "log_time"),
            name=name,
            media_type=media_type,
            data=bytes(data),
        )

    def close(self) -> None:
        """Write the last chunk and the summary, flush and fsync. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            try:
                self._file.flush()
                self._final_size = self._file.tell()
                self._fsync()
            finally:
                if self._path is not None:
                    self._file.close()

    def _fsync(self) -> None:
        self._last_fsync = time.monotonic()
        if self._path is None:
            # A caller's stream: fsync only when it is a real file.
            with contextlib.suppress(AttributeError, OSError):
                os.fsync(self._file.fileno())
            return
        os.fsync(self._file.fileno())
        # The new directory entry too, so the file itself survives a power cut.
        with contextlib.suppress(OSError):
            fd = os.open(self._path.parent, os.O_RDONLY)
            try:
                os.fsync(fd)
            finally:
                os.close(fd)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class _CappedFile:
    """A binary file that refuses reads longer than `cap` and clamps long reads to what is
    left in the file.

    mcap's readers trust every length inside a record, and `read(n)` allocates n bytes
    before reading: a garbage length in a torn file must not become a MemoryError.
    """

    _CHECK_ABOVE = 1 << 20

    def __init__(self, file: IO[bytes], cap: int):
        self._file = file
        self._cap = cap

    def read(self, size: int | None = -1) -> bytes:
        if size is None or size < 0 or size > self._cap:
            raise _CorruptRecordError(f"read of {size} bytes (limit {self._cap})")
        if size > self._CHECK_ABOVE:
            remaining = os.fstat(self._file.fileno()).st_size - self._file.tell()
            size = max(0, min(size, remaining))
        return self._file.read(size)

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._file.seek(offset, whence)

    def tell(self) -> int:
        return self._file.tell()


def _chunk_records(chunk: Chunk, limit: int) -> list[McapRecord]:
    """The records inside a chunk, its CRC checked; sizes over `limit` are corrupt."""
    if chunk.uncompressed_size > limit:
        raise _CorruptRecordError(f"chunk of {chunk.uncompressed_size} bytes uncompressed")
    if chunk.compression == "zstd":
        content_size = zstandard.get_frame_parameters(chunk.data).content_size
        if content_size != zstandard.CONTENTSIZE_UNKNOWN and content_size > limit:
            raise _CorruptRecordError(f"zstd frame of {content_size} bytes")
    return breakup_chunk(chunk, validate_crc=True)


@dataclass(slots=True)
class Damage:
    """A stretch of a recording that could not be read, and the messages it cost.

    `lost_from_ns`/`lost_to_ns`: the log times the lost messages lie within, as tight as
    the file tells: a skipped chunk's own message times when its header is readable, else
    the last message read before the damage and the first read after it; `lost_to_ns` is
    None when nothing was read after it (the file is cut there)."""

    offset: int  # file offset where the unreadable bytes start
    resumed_at: int | None  # where reading went on; None: nothing readable after it
    chunks: int  # chunk records skipped (a torn record counts as one)
    lost_from_ns: int | None
    lost_to_ns: int | None


class _TornRecordError(Exception):
    """A record that cannot be read where one should start (`offset`)."""

    def __init__(self, offset: int):
        super().__init__(offset)
        self.offset = offset


# Opcodes of the MCAP spec (0x01-0x0F); 0x80-0xFF are private records a reader skips.
# Anything else where a record should start is damage.
_KNOWN_OPCODES = frozenset(range(0x01, 0x10))
_CHUNK_FIXED = 8 + 8 + 8 + 4 + 4 + 8  # a chunk's fields around its compression string
_FOOTER_RECORD = 1 + 8 + 8 + 8 + 4


def _record(opcode: int, body: bytes) -> McapRecord | None:
    """One top-level record parsed from its body, as mcap's StreamReader does it."""
    reader = StreamReader(
        io.BytesIO(bytes([opcode]) + struct.pack("<Q", len(body)) + body),
        skip_magic=True,
        emit_chunks=True,
        record_size_limit=None,
    )
    return next(iter(reader.records), None)


def _frame_at(data: bytes | mmap.mmap, offset: int, size: int, limit: int) -> bool:
    """Whether a whole, well-formed chunk, metadata or attachment frame starts at
    `offset` (a chunk's content unchecked): after damage, reading resumes at the next one.
    Each field's length must add up to the record's, which bytes in the middle of
    compressed data do not do by chance."""
    if offset + 9 > size:
        return False
    opcode = data[offset]
    (length,) = struct.unpack_from("<Q", data, offset + 1)
    body, end = offset + 9, offset + 9 + length
    if length > limit or end > size:
        return False
    try:
        if opcode == 0x06:  # chunk
            if length < _CHUNK_FIXED:
                return False
            (uncompressed,) = struct.unpack_from("<Q", data, body + 16)
            (n,) = struct.unpack_from("<I", data, body + 28)
            if n not in (0, 3, 4) or uncompressed > limit:
                return False
            if bytes(data[body + 32 : body + 32 + n]) not in (b"", b"lz4", b"zstd"):
                return False
            (records,) = struct.unpack_from("<Q", data, body + 32 + n)
            return records == length - _CHUNK_FIXED - n
        if opcode == 0x0C:  # metadata: name, then a map of string pairs
            (n,) = struct.unpack_from("<I", data, body)
            (m,) = struct.unpack_from("<I", data, body + 4 + n)
            return 4 + n + 4 + m == length
        if opcode == 0x09:  # attachment: times, name, media type, data, crc
            (n,) = struct.unpack_from("<I", data, body + 16)
            (k,) = struct.unpack_from("<I", data, body + 20 + n)
            (d,) = struct.unpack_from("<Q", data, body + 24 + n + k)
            return 16 + 4 + n + 4 + k + 8 + d + 4 == length
    except struct.error:
        return False
    return False


_FRAME_OPCODES = re.compile(rb"[\x06\x09\x0c]")


class RecordingReader:
    """Reads a recording (format v1) linearly, in file order.

    Iterating yields `RecordedMessage`s of the wanted `topics` (all topics, known or not,
    when None). The file is read once, front to back: a file cut short (a power cut)
    yields every message of every intact chunk before the cut, with `truncated` set; a
    damaged chunk is skipped and reading resumes at the next good one (`_guarded`). What
    could not be read is in `damage`, `damaged_chunks` and `lost_data` once iteration has
    ended. Iterate once; the file closes when iteration ends.

    `metadata` is read when the reader is made; it is None only when the file ends before
    its metadata record. `attachments` (name -> `RecordedAttachment`, the last one of a
    name wins) are read on first use, from the summary's index when the file is complete.

    Raises `SourceError` for a missing file, a file that is not MCAP, or a recording whose
    `format_version` is not "1" (or that has no `treetraits` metadata at all).
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        topics: Iterable[str] | None = None,
        *,
        record_size_limit: int = RECORD_SIZE_LIMIT,
    ):
        self.path = Path(path)
        if isinstance(topics, str):
            topics = [topics]
        self.topics: frozenset[str] | None = None if topics is None else frozenset(topics)
        self.truncated = False
        # What could not be read, in file order (a cut at the end included).
        self.damage: list[Damage] = []
        self.orphan_messages = 0  # messages whose channel record was lost with a damaged chunk
        self._offset = 0  # of the record last read
        self._data_end = False  # the data section read to its end
        self._last_time: int | None = None  # log_time of the last message read, any topic
        self.metadata: RecordingMetadata | None = None
        self._limit = record_size_limit
        self._attachments: dict[str, RecordedAttachment] | None = None
        self._iterated = False
        self._closed = False
        self._pending: list[McapRecord] = []
        self._summary_channels: dict[int, Channel] | None = None
        self._file = self._open()
        try:
            head = self._file.read(len(_MCAP_MAGIC))
            if head != _MCAP_MAGIC and not (
                len(head) < len(_MCAP_MAGIC) and _MCAP_MAGIC.startswith(head)
            ):
                raise SourceError(
                    f"{self.path}: not an MCAP file (expected a treetraits recording, format "
                    f"v{FORMAT_VERSION}: an MCAP file starting with {_MCAP_MAGIC!r}; "
                    f"found {head!r})"
                )
            self._file.seek(0)
            self._records = self._guarded(self._file)
            metadata = self._read_front()
            if metadata is None and not self.truncated:
                metadata = self._side_records()[0]
            if metadata is not None:
                self.metadata = self._parse_metadata(metadata)
            elif not self.truncated:
                raise SourceError(
                    f"{self.path}: MCAP file without a {METADATA_NAME!r} metadata record "
                    f"(expected a treetraits recording, format v{FORMAT_VERSION})"
                )
        except BaseException:
            self.close()
            raise

    def _open(self) -> IO[bytes]:
        try:
            return open(self.path, "rb")
        except OSError as error:
            raise SourceError(
                f"{self.path}: cannot open ({error.strerror or error}); expected a treetraits "
                f"recording (.mcap)"
            ) from error

    def _guarded(self, file: IO[bytes], track: bool = True) -> Iterator[McapRecord]:
        """The file's top-level records in file order (chunks not opened). A record that
        cannot be read is damage: reading resumes at the next well-formed chunk (metadata,
        attachment) frame after it. When none follows, reading ends: `truncated` is set
        unless the file ends with its footer. Also set when the file ends without its
        footer, or its footer without the closing magic. With `track`, damage is noted in
        `damage` and the offset of each record yielded in `_offset`."""
        size = os.fstat(file.fileno()).st_size
        offset = len(_MCAP_MAGIC)
        while offset < size:
            try:
                record, end = self._record_at(file, offset, size)
            except _TornRecordError as torn:
                if self._closed:  # a read from a file closed under us
                    return
                if track and self._data_end:  # in the summary: no message lost
                    self.truncated = not _ends_with_footer(file, size)
                    return
                resume = _next_frame(file, torn.offset + 1, size, self._limit)
                complete = resume is not None or _ends_with_footer(file, size)
                if track:
                    self._damaged(torn.offset, resume, 1 if complete else 0)
                    if not complete:
                        self.truncated = True
                if resume is None:
                    return
                offset = resume
                continue
            if record is not None:
                if track:
                    self._offset = offset
                    self._data_end = self._data_end or isinstance(record, DataEnd)
                yield record
                if isinstance(record, Footer):
                    file.seek(end)
                    if file.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC and track:
                        self.truncated = True
                    return
            offset = end
        if track:  # the file ends without its footer: cut
            self.truncated = True
            if not self._data_end:
                self._damaged(size, None, 0)

    def _record_at(self, file: IO[bytes], offset: int, size: int) -> tuple[McapRecord | None, int]:
        """The record at `offset` (None for a private record, skipped) and where the next
        starts; `_TornRecordError` when no readable record is there."""
        file.seek(offset)
        head = file.read(9)
        if len(head) < 9:
            raise _TornRecordError(offset)
        opcode, length = struct.unpack("<BQ", head)
        if opcode not in _KNOWN_OPCODES and opcode < 0x80:
            raise _TornRecordError(offset)
        end = offset + 9 + length
        if length > self._limit or end > size:
            raise _TornRecordError(offset)
        body = file.read(length)
        if opcode >= 0x80:
            return None, end
        try:
            return _record(opcode, body), end
        except _READ_ERRORS:
            raise _TornRecordError(offset) from None

    def _damaged(
        self, offset: int, resumed_at: int | None, chunks: int, chunk: Chunk | None = None
    ) -> None:
        """Note damage at `offset`, merged with the damage just before it when reading
        resumed right there."""
        last = self.damage[-1] if self.damage else None
        if chunk is not None:
            lost = (chunk.message_start_time, chunk.message_end_time)
        else:
            lost = (self._last_time, None)
        if last is not None and last.resumed_at == offset:
            last.resumed_at = resumed_at
            last.chunks += chunks
            if chunk is not None and last.lost_to_ns is not None:
                last.lost_to_ns = max(last.lost_to_ns, chunk.message_end_time)
            elif chunk is None:
                last.lost_to_ns = None
            return
        self.damage.append(Damage(offset, resumed_at, chunks, *lost))

    def _read_front(self) -> Metadata | None:
        """Read the records before the first chunk, where the writer puts the metadata,
        keeping them for iteration. The `treetraits` metadata, or None if not there."""
        first = True
        for record in self._records:
            if first and not isinstance(record, Header):
                self.truncated = True  # the magic is right but no header follows: corrupt
                self._records = iter(())
                return None
            first = False
            if isinstance(record, Metadata) and record.name == METADATA_NAME:
                return record
            self._pending.append(record)
            if isinstance(record, (Chunk, Message, DataEnd, Footer)):
                return None
        return None

    def _parse_metadata(self, record: Metadata) -> RecordingMetadata:
        fields = record.metadata
        version = fields.get("format_version")
        if version not in READ_VERSIONS:
            raise SourceError(
                f"{self.path}: recording format_version {version!r}, this software "
                f"({SOFTWARE}) reads formats {' and '.join(map(repr, READ_VERSIONS))} only"
            )
        try:
            calibration = loads_limited(fields.get("calibration") or "{}")
        except ValueError as error:  # not JSON, or nested deeper than any calibration
            raise SourceError(
                f"{self.path}: calibration in the {METADATA_NAME!r} metadata is not JSON ({error})"
            ) from error
        if not isinstance(calibration, dict):
            raise SourceError(
                f"{self.path}: calibration in the {METADATA_NAME!r} metadata is a JSON "
                f"{type(calibration).__name__}, expected an object"
            )
        return RecordingMetadata(version, fields.get("software", ""), calibration)

    def __iter__(self) -> Iterator[RecordedMessage]:
        if self._iterated:
            raise RuntimeError(f"{self.path}: a RecordingReader can be iterated only once")
        self._iterated = True
        return self._messages()

    def _messages(self) -> Iterator[RecordedMessage]:
        channels: dict[int, Channel] = {}
        try:
            pending, self._pending = self._pending, []
            for record in _chain(pending, self._records):
                if isinstance(record, Chunk):
                    try:
                        inner = _chunk_records(record, self._limit)
                    except _READ_ERRORS:
                        # Its frame is whole, so the next record is where it says.
                        end = self._offset + 9 + _chunk_length(record)
                        self._damaged(self._offset, end, 1, record)
                        continue
                else:
                    inner = [record]
                for item in inner:
                    if isinstance(item, Channel):
                        channels[item.id] = item
                    elif isinstance(item, Message):
                        channel = channels.get(item.channel_id) or self._summary_channel(
                            item.channel_id, channels
                        )
                        if channel is None:  # its channel was in a damaged chunk
                            self.orphan_messages += 1
                            continue
                        self._read_time(item.log_time)
                        if self.topics is None or channel.topic in self.topics:
                            yield RecordedMessage(
                                channel.topic,
                                item.log_time,
                                item.publish_time,
                                item.sequence,
                                item.data,
                            )
        finally:
            self._file.close()

    def _read_time(self, log_time: int) -> None:
        """A message was read: it bounds the damage before it."""
        self._last_time = log_time
        last = self.damage[-1] if self.damage else None
        if last is not None and last.lost_to_ns is None and last.resumed_at is not None:
            last.lost_to_ns = log_time

    def _summary_channel(self, channel_id: int, channels: dict[int, Channel]) -> Channel | None:
        """A channel whose record was lost with a damaged chunk, from the summary (a
        complete file repeats every channel there)."""
        if self._summary_channels is None:
            self._summary_channels = {}
            with contextlib.suppress(*_READ_ERRORS, OSError), self._open() as file:
                file.seek(-len(_MCAP_MAGIC), io.SEEK_END)
                if file.read(len(_MCAP_MAGIC)) == _MCAP_MAGIC:
                    file.seek(0)
                    reader = SeekingReader(
                        _CappedFile(file, self._limit),  # type: ignore[arg-type]
                        record_size_limit=self._limit,
                    )
                    summary = reader.get_summary()
                    if summary is not None:
                        self._summary_channels = dict(summary.channels)
        channel = self._summary_channels.get(channel_id)
        if channel is not None:
            channels[channel_id] = channel
        return channel

    @property
    def damaged_chunks(self) -> int:
        """Chunks skipped as unreadable (a cut at the end is `truncated`, not counted)."""
        return sum(d.chunks for d in self.damage)

    @property
    def lost_data(self) -> bool:
        """Whether messages may have been lost: damage, a cut before the end of the data,
        or messages whose channel was lost. Known once iteration has ended."""
        return bool(self.damage) or self.orphan_messages > 0

    @property
    def attachments(self) -> dict[str, RecordedAttachment]:
        """The attachments by name (read on first use)."""
        if self._attachments is None:
            self._side_records()
        assert self._attachments is not None
        return self._attachments

    def _side_records(self) -> tuple[Metadata | None, dict[str, RecordedAttachment]]:
        """The `treetraits` metadata and the attachments, wherever they are in the file:
        through the summary's indexes when the file is complete, else by a linear scan
        that skips chunks without opening them."""
        with self._open() as file:
            found = self._indexed_side_records(file)
            if found is None:
                file.seek(0)
                found = [
                    r
                    for r in self._guarded(file, track=False)
                    if isinstance(r, (Metadata, Attachment))
                ]
        metadata = next(
            (r for r in found if isinstance(r, Metadata) and r.name == METADATA_NAME), None
        )
        self._attachments = {
            r.name: RecordedAttachment(r.name, r.media_type, r.log_time, r.create_time, r.data)
            for r in found
            if isinstance(r, Attachment)
        }
        return metadata, self._attachments

    def _indexed_side_records(self, file: IO[bytes]) -> list[Metadata | Attachment] | None:
        """Metadata and attachments through the summary's indexes, or None when the file
        has no complete, consistent summary (truncated, or written without indexes)."""
        try:
            file.seek(-len(_MCAP_MAGIC), io.SEEK_END)
            if file.read(len(_MCAP_MAGIC)) != _MCAP_MAGIC:
                return None
            file.seek(0)
            reader = SeekingReader(
                _CappedFile(file, self._limit),  # type: ignore[arg-type]
                record_size_limit=self._limit,
            )
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return None
            stats = summary.statistics
            if (
                len(summary.metadata_indexes) != stats.metadata_count
                or len(summary.attachment_indexes) != stats.attachment_count
            ):
                return None
            return [*reader.iter_metadata(), *reader.iter_attachments()]
        except (*_READ_ERRORS, OSError):
            return None

    def close(self) -> None:
        """Close the file (iteration then ends). Idempotent."""
        self._closed = True
        file = getattr(self, "_file", None)
        if file is not None:
            file.close()

    def __enter__(self) -> RecordingReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _chunk_length(chunk: Chunk) -> int:
    """The body length of a chunk record as written."""
    return _CHUNK_FIXED + len(chunk.compression.encode()) + len(chunk.data)


def _next_frame(file: IO[bytes], start: int, size: int, limit: int) -> int | None:
    """The offset of the next well-formed chunk, metadata or attachment frame at or after
    `start`, or None."""
    if start >= size:
        return None
    with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as data:
        for match in _FRAME_OPCODES.finditer(data, start):
            if _frame_at(data, match.start(), size, limit):
                return match.start()
    return None


def _ends_with_footer(file: IO[bytes], size: int) -> bool:
    """Whether the file ends with a footer record and the closing magic (complete)."""
    if size < len(_MCAP_MAGIC) * 2 + _FOOTER_RECORD:
        return False
    file.seek(size - len(_MCAP_MAGIC) - _FOOTER_RECORD)
    tail = file.read(_FOOTER_RECORD + len(_MCAP_MAGIC))
    return tail[:9] == b"\x02" + struct.pack("<Q", 20) and tail[-8:] == _MCAP_MAGIC


def _chain(first: list[McapRecord], rest: Iterator[McapRecord]) -> Iterator[McapRecord]:
    yield from first
    yield from rest


def read_recording(
    path: str | os.PathLike[str],
    topics: Iterable[str] | None = None,
    *,
    record_size_limit: int = RECORD_SIZE_LIMIT,
) -> RecordingReader:
    """Open a recording for reading; see `RecordingReader`."""
    return RecordingReader(path, topics, record_size_limit=record_size_limit)
