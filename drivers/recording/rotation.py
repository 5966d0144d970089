"""The onboard raw recorder: recordings v1 rotated by size, safe against a power cut.

`RotatingRecorder` writes `REC.mcap`, then `REC.1.mcap`, `REC.2.mcap`, ... each a complete
recording v1 (header, the `treetraits` metadata with the calibration, the field map
attachment when given), so any one file can be replayed on its own.

What a crash costs: chunks are closed when they pass `chunk_bytes` (about one second of all
sensors) or have been open `fsync_every_s` (so GNSS alone still reaches the disk), and each
chunk is handed to the OS as soon as it is written; fsync runs at most every
`fsync_every_s`, and at every rotation and at close. A kill -9 therefore loses at most the
open chunk (about a second); a power cut at most that plus the last unsynced second. The
truncated last file replays up to the cut (`drivers.recording.read_recording`).

Disk full or an I/O error raises `RecordingError` naming the file; the recorder then stops
(every later `write` raises the same error) and leaves the files already written readable.
"""

from __future__ import annotations

import errno
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from treetraits.drivers.recording import FIELD_MAP_MEDIA_TYPE, FIELD_MAP_NAME, RecordingWriter
from treetraits.errors import OutputExistsError, TreetraitsError


class RecordingError(TreetraitsError):
    """The raw recording cannot go on: disk full, I/O error, or a file already there."""


class RecordingExistsError(RecordingError, OutputExistsError):
    """A recording (or a file of its rotation) is already there: never overwritten, so
    `record` has no --force (exit 4, docs/cli.md)."""


def rotated_path(first_path: Path, index: int) -> Path:
    """The name of the `index`-th file of a rotation: REC.mcap, REC.1.mcap, REC.2.mcap..."""
    if index == 0:
        return first_path
    suffix = first_path.suffix
    stem = first_path.name[: -len(suffix)] if suffix else first_path.name
    return first_path.with_name(f"{stem}.{index}{suffix}")


def _describe(error: OSError) -> str:
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"{error.strerror or error}: the disk is full, free space or record elsewhere"
    if error.errno == errno.EFBIG:
        return f"{error.strerror or error}: the file size limit was reached (ulimit -f)"
    return str(error.strerror or error)


class RotatingRecorder:
    """Writes raw sensor messages to a rotating set of recordings v1 (see the module doc).

    `max_bytes`: rotate once a file has grown past this (at a chunk boundary, so a file
    ends up at most about one chunk plus its summary larger). `calibration` is stored in
    every file; `field_map` (GeoJSON bytes) is attached to every file.
    Call `write` from one thread only.
    """

    def __init__(
        self,
        first_path: Path,
        *,
        max_bytes: int,
        chunk_bytes: int,
        fsync_every_s: float,
        calibration: Mapping[str, Any] | None = None,
        field_map: bytes | None = None,
    ):
        if max_bytes <= 0 or chunk_bytes <= 0:
            raise ValueError(
                f"max_bytes and chunk_bytes must be positive, got {max_bytes}, {chunk_bytes}"
            )
        if not fsync_every_s > 0:
            raise ValueError(f"fsync_every_s must be positive, got {fsync_every_s}")
        self._first = Path(first_path)
        self._max_bytes = max_bytes
        self._chunk_bytes = chunk_bytes
        self._fsync_every_s = fsync_every_s
        self._calibration = dict(calibration or {})
        self._field_map = field_map
        self._files: list[Path] = []
        self._finished_bytes = 0  # sizes of the files already rotated away
        self._failure: RecordingError | None = None
        self._closed = False
        self._refuse_existing()
        self._writer: RecordingWriter | None = None
        self._writer = self._open(self._first)

    def _refuse_existing(self) -> None:
        """Never overwrite a recording, nor mix with the rotation of an earlier one."""
        first = self._first
        if first.exists():
            raise RecordingExistsError(f"{first}: already exists; record to a new name")
        suffix = re.escape(first.suffix)
        stem = re.escape(first.name[: -len(first.suffix)] if first.suffix else first.name)
        pattern = re.compile(rf"{stem}\.\d+{suffix}")
        parent = first.parent
        try:
            names = os.listdir(parent)
        except FileNotFoundError:
            raise RecordingError(
                f"{first}: directory {parent} does not exist; create it first"
            ) from None
        except OSError as error:
            raise RecordingError(f"{parent}: cannot list ({_describe(error)})") from error
        clash = sorted(n for n in names if pattern.fullmatch(n))
        if clash:
            raise RecordingExistsError(
                f"{first}: {parent / clash[0]} of an earlier recording is there; record to a "
                "new name"
            )

    def _open(self, path: Path) -> RecordingWriter:
        try:
            writer = RecordingWriter(
                path,
                calibration=self._calibration,
                chunk_size=self._chunk_bytes,
                max_chunk_age_s=self._fsync_every_s,
                fsync_every_s=self._fsync_every_s,
            )
        except FileExistsError:
            raise RecordingExistsError(f"{path}: already exists; record to a new name") from None
        except OSError as error:
            raise self._fail(path, error, None) from error
        self._files.append(path)
        try:
            if self._field_map is not None:
                writer.attach(FIELD_MAP_NAME, self._field_map, FIELD_MAP_MEDIA_TYPE)
            # Header, metadata and directory entry on disk before the first message.
            writer.flush(fsync=True)
        except OSError as error:
            raise self._fail(path, error, writer) from error
        return writer

    def _fail(self, path: Path, error: OSError, writer: RecordingWriter | None) -> RecordingError:
        if writer is not None:
            writer.abort()
        self._writer = None
        self._failure = RecordingError(f"recording stopped: {path}: {_describe(error)}")
        return self._failure

    @property
    def files(self) -> list[Path]:
        """The files written so far, in order (the last one possibly still open)."""
        return list(self._files)

    @property
    def bytes_written(self) -> int:
        """Bytes handed to the OS over all files (the open chunk excluded)."""
        current = self._writer.bytes_written if self._writer is not None else 0
        return self._finished_bytes + current

    def write(self, topic: str, data: bytes, log_time: int, publish_time: int) -> None:
        """Append one message (see `RecordingWriter.write`); rotate when the file is full.

        Raises `RecordingError` when the disk is full or failing, and for every call after.
        """
        writer = self._live_writer()
        path = self._files[-1]
        try:
            writer.write(topic, data, log_time, publish_time)
            if writer.bytes_written >= self._max_bytes:
                self._rotate(writer)
        except OSError as error:
            raise self._fail(path, error, writer) from error

    def flush(self) -> None:
        """Close the open chunk and fsync now (e.g. when the sensors fell silent, so what
        came last is on disk without waiting for the next message)."""
        writer = self._live_writer()
        try:
            writer.flush(fsync=True)
        except OSError as error:
            raise self._fail(self._files[-1], error, writer) from error

    def _live_writer(self) -> RecordingWriter:
        if self._failure is not None:
            raise self._failure
        if self._closed or self._writer is None:
            raise RecordingError(f"{self._first}: the recorder is closed")
        return self._writer

    def _rotate(self, writer: RecordingWriter) -> None:
        writer.close()  # summary, fsync of the file and its directory
        self._finished_bytes += writer.bytes_written
        self._writer = None
        self._writer = self._open(rotated_path(self._first, len(self._files)))

    def close(self) -> None:
        """Finish the current file (last chunk, summary, fsync). Idempotent; after a
        failure it only releases the file."""
        if self._closed:
            return
        self._closed = True
        writer, self._writer = self._writer, None
        if writer is None:
            return
        try:
            writer.close()
            self._finished_bytes += writer.bytes_written
        except OSError as error:
            writer.abort()
            self._failure = RecordingError(
                f"recording stopped: {self._files[-1]}: {_describe(error)}"
            )
            raise self._failure from error

    def __enter__(self) -> RotatingRecorder:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()
