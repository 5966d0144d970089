"""Reads a recording back linearly, so that a file cut by a power failure still yields
every message of every chunk completed before the cut, and a damaged chunk is skipped
(reading resumes at the next good one) and accounted for (`Damage`)."""

from __future__ import annotations

import contextlib
import io
import mmap
import os
import re
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO

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

from treetraits.drivers.jsontext import loads_limited
from treetraits.drivers.recording.format import (
    FORMAT_VERSION,
    MCAP_MAGIC,
    METADATA_NAME,
    READ_VERSIONS,
    RECORD_SIZE_LIMIT,
    SOFTWARE,
    RecordedAttachment,
    RecordedMessage,
    RecordingMetadata,
)
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.errors import SourceError


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
            head = self._file.read(len(MCAP_MAGIC))
            if head != MCAP_MAGIC and not (
                len(head) < len(MCAP_MAGIC) and MCAP_MAGIC.startswith(head)
            ):
                raise SourceError(
                    f"{self.path}: not an MCAP file (expected a treetraits recording, format "
                    f"v{FORMAT_VERSION}: an MCAP file starting with {MCAP_MAGIC!r}; "
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
        refuse_ros_bag(self.path, "a treetraits recording (.mcap)")
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
        offset = len(MCAP_MAGIC)
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
                    if file.read(len(MCAP_MAGIC)) != MCAP_MAGIC and track:
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
                file.seek(-len(MCAP_MAGIC), io.SEEK_END)
                if file.read(len(MCAP_MAGIC)) == MCAP_MAGIC:
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
            file.seek(-len(MCAP_MAGIC), io.SEEK_END)
            if file.read(len(MCAP_MAGIC)) != MCAP_MAGIC:
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
    if size < len(MCAP_MAGIC) * 2 + _FOOTER_RECORD:
        return False
    file.seek(size - len(MCAP_MAGIC) - _FOOTER_RECORD)
    tail = file.read(_FOOTER_RECORD + len(MCAP_MAGIC))
    return tail[:9] == b"\x02" + struct.pack("<Q", 20) and tail[-8:] == MCAP_MAGIC


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
