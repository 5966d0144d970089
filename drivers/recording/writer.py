"""Writes a recording (the format: `format.py`, docs/recording.md): what each sensor sent,
exactly as received, in zstd chunks that a power cut loses at most one of."""

from __future__ import annotations

import contextlib
import json
import operator
import os
import time
from collections.abc import Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from treetraits.drivers.recording.format import (
    DEFAULT_CHUNK_SIZE,
    FORMAT_VERSION,
    FORMAT_VERSION_MOTION,
    METADATA_NAME,
    READ_VERSIONS,
    SOFTWARE,
    TOPIC_ENCODINGS,
    U32,
    U64,
    V11_TOPICS,
)
from treetraits.files import fsync_directory


def _time_ns(value: int, what: str) -> int:
    """An MCAP timestamp: an integer in [0, 2**64)."""
    try:
        value = operator.index(value)
    except TypeError:
        raise TypeError(f"{what} must be an int in ns, got {type(value).__name__}") from None
    if not 0 <= value < U64:
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
        self._sequences[topic] = (sequence + 1) % U32  # MCAP sequences are uint32
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
        fsync_directory(self._path.parent)

    def __enter__(self) -> RecordingWriter:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
