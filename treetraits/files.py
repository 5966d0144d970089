"""Files every layer writes the same way: replaced atomically, and named by a UTC stamp.

`write_atomically` writes into a temp file beside the target (`.NAME.XXXXXXXX.tmp`),
flushes and fsyncs it, renames it over the target and fsyncs the directory: a reader,
a crash or a power cut finds the old file or the new one, never a part. Any failure
(while writing, at fsync, at the rename) removes the temp file and leaves the old file
as it was.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, Literal, TextIO, overload

from treetraits.errors import OutputExistsError, TreetraitsError

if TYPE_CHECKING:
    from datetime import datetime

# "\n" written as it is: the bytes are the same on every platform.
_TEXT: dict[str, Any] = {"mode": "w", "encoding": "utf-8", "newline": ""}


@overload
def write_atomically(
    path: str | os.PathLike,
    write: Callable[[TextIO], object],
    *,
    binary: Literal[False] = False,
    permissions: int | None = None,
) -> None: ...


@overload
def write_atomically(
    path: str | os.PathLike,
    write: Callable[[IO[bytes]], object],
    *,
    binary: Literal[True],
    permissions: int | None = None,
) -> None: ...


def write_atomically(
    path: str | os.PathLike,
    write: Callable[[IO[Any]], object],
    *,
    binary: bool = False,
    permissions: int | None = None,
) -> None:
    """Replace `path` by what `write(file)` writes, atomically (the module's docstring).

    Text is UTF-8 with "\\n" written as it is (no newline translation). `permissions`:
    the new file's mode, set exactly; None: what `open()` would create (0o666 less the
    umask)."""
    target = Path(path)
    temp, fd = _create_beside(target)
    kind: dict[str, Any] = {"mode": "wb"} if binary else _TEXT
    try:
        with open(fd, **kind) as file:
            if permissions is not None:
                os.fchmod(file.fileno(), permissions)
            write(file)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temp, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temp)
        raise
    fsync_directory(target.parent)  # the rename is durable only once it is on disk too


def fsync_directory(directory: str | os.PathLike) -> None:
    """fsync a directory, so that the entries made or renamed in it survive a power cut;
    not every filesystem lets a directory be fsynced, and there it is skipped."""
    with contextlib.suppress(OSError):
        fd = os.open(directory, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _create_beside(target: Path) -> tuple[Path, int]:
    """A new temp file in `target`'s directory (the rename must not cross filesystems),
    hidden and named after it; created with mode 0o666 so that the umask applies as it
    does to `open()` (tempfile.mkstemp would make it 0600)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0)
    while True:
        temp = target.with_name(f".{target.name}.{os.urandom(4).hex()}.tmp")
        try:
            return temp, os.open(temp, flags, 0o666)
        except FileExistsError:  # another writer's temp file of the same name: draw again
            continue


class OutputPathError(TreetraitsError):
    """An output path that cannot be used as given: a directory where a file is wanted (or
    a file where a directory is: `service.outdir.OutputDirError`); exit 2."""


def check_output_file(
    path: str | os.PathLike, option: str = "--out", *, force: bool | None = None
) -> None:
    """A command's one-file output (a page, a view, a recording, a picture), checked before
    any work (docs/cli.md): a directory there is refused with or without --force (exit 2;
    it would fail only once the work is done); an existing file without `force` is an
    earlier output (exit 4). `force=None`: the command has no --force and refuses an
    existing file its own way (`record`: a recording is never overwritten)."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(
            f"{path}: is a directory; {option} takes the file to write (e.g. {path / 'NAME'})"
        )
    if force is False and path.exists():
        raise OutputExistsError(
            f"{path}: exists; give --force to replace it, or choose another {option}"
        )


def iso_utc(ns: int | None) -> str:
    """ISO 8601 UTC with milliseconds, e.g. 2026-11-22T10:15:30.123Z ("" for None): how
    every output and message writes a time of ns since the Unix epoch."""
    from datetime import datetime, timezone  # imported when used: the CLI starts without it

    if ns is None:
        return ""
    seconds, rest = divmod(int(ns), 1_000_000_000)
    moment = datetime.fromtimestamp(seconds, tz=timezone.utc)
    return f"{moment:%Y-%m-%dT%H:%M:%S}.{rest // 1_000_000:03d}Z"


def utc_stamp(moment: datetime | None = None) -> str:
    """20261123T161800Z (now, unless `moment` is given): sortable, safe in a file name; a
    run directory, a recording and a run kept aside are named by it."""
    from datetime import datetime, timezone  # imported when used: the CLI starts without it

    moment = moment or datetime.now(timezone.utc)
    return moment.strftime("%Y%m%dT%H%M%SZ")
