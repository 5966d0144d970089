"""The output rules every writing command keeps (`replay`, `sim`, `lidar export`; `eval`
takes the lock only): docs/cli.md, "Output directories".

- The caller checks its inputs and options before entering `OutputDir`: a bad input stops
  the run before the output is touched.
- One run at a time per output: a lock file in the output's directory, taken with
  `fcntl.flock` without waiting; a second run fails at once (`OutputBusyError`).
- The files a command owns (a fixed set of names and patterns, `owned`) are written into a
  staging directory beside them (same file system, so moving is a rename) and moved into
  place when the run succeeds; a failing or interrupted run leaves the earlier outputs as
  they were.
- A run that stops early but has outputs worth keeping (an interrupted replay: what was
  mapped so far, marked interrupted) calls `keep_aside(name)`: its outputs go into place
  when the directory holds no earlier run's, else into `directory/name/` beside the
  earlier run, which stays as it was (a partial run never replaces a complete one).
- An earlier run's outputs are replaced only with `force` (else `OutputExistsError`);
  replacing removes every owned file of the earlier run that the new run did not write (an
  export's stale .pcd files). Files the command does not own (the input recording beside
  the outputs, notes) are never touched, and an input that is one of the outputs is refused.

A command whose output is one file (`report`, `export foxglove`, `import`, `inspect --png`...)
checks it with `treetraits.files.check_output_file` before any work.
"""

from __future__ import annotations

import contextlib
import fcntl
import fnmatch
import os
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from types import TracebackType

from treetraits.errors import FileAccessError, OutputBusyError, OutputExistsError
from treetraits.files import OutputPathError, fsync_directory

LOCK_NAME = ".treetraits.lock"


class OutputDirError(OutputPathError):
    """An output that cannot be used as given (a file in place of the directory, an input
    among the outputs); what the system refuses is a `FileAccessError` (exit 6)."""


@contextlib.contextmanager
def output_lock(directory: Path, lock_name: str = LOCK_NAME) -> Iterator[Path]:
    """Hold `directory/lock_name` (created with the directory) for one run; fail fast when
    another run holds it. The lock file stays: removing it would let a third run lock a new
    file while the second still holds the old one."""
    directory = Path(directory)
    _make_directory(directory)
    path = directory / lock_name
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
    except OSError as exc:
        raise FileAccessError(f"{path}: cannot create the lock file ({_text(exc)})") from exc
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(fd)
            raise OutputBusyError(
                f"{directory}: another run is writing there{holder}; wait for it to end or "
                "choose another output"
            ) from None
        # Who holds it, for the message a second run prints (advisory only).
        with contextlib.suppress(OSError):
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield path
    finally:
        os.close(fd)  # releases the lock


def _read_holder(fd: int) -> str:
    with contextlib.suppress(OSError, ValueError):
        pid = int(os.pread(fd, 32, 0).decode().strip())
        return f" (process {pid})"
    return ""


def _make_directory(directory: Path) -> None:
    if directory.exists() and not directory.is_dir():
        raise OutputDirError(f"{directory}: exists and is not a directory; give a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FileAccessError(f"{directory}: cannot create the directory ({_text(exc)})") from exc


def _text(exc: OSError) -> str:
    return exc.strerror or str(exc)


class OutputDir:
    """One run's outputs into `directory`, as the module says. Use as a context manager:
    entering locks, checks and makes the staging directory (returned); leaving without an
    exception moves the staged outputs into place, leaving with one discards them.

    `owned`: the names (fnmatch patterns) of the files the command writes into `directory`.
    `inputs`: the run's input files, refused when they are among the outputs; `what` and
    `target` name the earlier run and the output in messages. `tag` names
    the lock (`.<tag>.lock`) and the staging directories (`.<tag>.staging-*`): per directory
    for a directory of outputs, per recording for `sim`, whose outputs share a directory
    with other recordings'.

    The constructor only looks (nothing is created), so a caller can check the output with
    its other options before reading any input."""

    def __init__(
        self,
        directory: Path,
        owned: Sequence[str],
        *,
        force: bool = False,
        inputs: Iterable[Path | None] = (),
        tag: str = "treetraits",
        what: str = "an earlier run",
        target: Path | None = None,
    ):
        self.directory = Path(directory)
        self.owned = tuple(owned)
        self.force = force
        self.tag = tag
        self.what = what
        self.target = self.directory if target is None else Path(target)  # for messages
        self.staging: Path | None = None
        self._aside: str | None = None  # `keep_aside`'s name
        self.placed: Path | None = None  # where the outputs went, once they were moved
        self._lock: contextlib.AbstractContextManager | None = None
        if self.directory.exists() and not self.directory.is_dir():
            raise OutputDirError(
                f"{self.directory}: exists and is not a directory; give a directory"
            )
        for path in inputs:
            if path is not None and self._is_output(Path(path)):
                raise OutputDirError(
                    f"{path}: is one of the outputs this run writes in {self.directory}; "
                    "write the outputs elsewhere"
                )
        self._refuse_existing()

    def _is_output(self, path: Path) -> bool:
        try:
            same_dir = path.resolve().parent == self.directory.resolve()
        except OSError:
            return False
        return same_dir and self._owns(path.name)

    def _owns(self, name: str) -> bool:
        return any(fnmatch.fnmatchcase(name, pattern) for pattern in self.owned)

    def existing(self) -> list[str]:
        """The owned files already in the directory, sorted."""
        try:
            names = os.listdir(self.directory)
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise FileAccessError(f"{self.directory}: cannot list ({_text(exc)})") from exc
        return sorted(n for n in names if self._owns(n) and not n.startswith(f".{self.tag}."))

    def _refuse_existing(self) -> None:
        if self.force:
            return
        found = self.existing()
        if found:
            shown = ", ".join(found[:3]) + (", ..." if len(found) > 3 else "")
            raise OutputExistsError(
                f"{self.target}: the outputs of {self.what} are there ({shown}); give "
                "--force to replace them, or choose another output"
            )

    def __enter__(self) -> Path:
        import tempfile  # here: the command line's parsers import this module

        self._lock = output_lock(self.directory, f".{self.tag}.lock")
        self._lock.__enter__()
        try:
            self._refuse_existing()  # again, under the lock: a run may have ended since
            self._remove_stale_staging()
            try:
                self.staging = Path(
                    tempfile.mkdtemp(prefix=f".{self.tag}.staging-", dir=self.directory)
                )
            except OSError as exc:
                raise FileAccessError(
                    f"{self.directory}: cannot create a staging directory ({_text(exc)})"
                ) from exc
        except BaseException:
            self._release()
            raise
        return self.staging

    def _remove_stale_staging(self) -> None:
        """Staging directories of runs killed before they ended (we hold the lock: nobody
        else is using them)."""
        import shutil

        for entry in self.directory.glob(f".{self.tag}.staging-*"):
            shutil.rmtree(entry, ignore_errors=True)

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        try:
            if exc_type is None:
                self._commit()
        finally:
            if self.staging is not None:
                import shutil

                shutil.rmtree(self.staging, ignore_errors=True)
            self._release()

    def keep_aside(self, name: str) -> None:
        """On a clean exit, put the outputs into place only if no earlier run's are there;
        else move the staging directory to `directory/name` (a rename: same directory) and
        leave the earlier run untouched. For a run that stopped early (`replay` on SIGINT
        or SIGTERM). `name` is not an owned pattern, so later runs never touch it."""
        self._aside = name

    def _commit(self) -> None:
        assert self.staging is not None
        if self._aside is not None and self.existing():
            aside = self.directory / self._aside
            n = 1
            while aside.exists():  # two interrupted runs in one second
                n += 1
                aside = self.directory / f"{self._aside}-{n}"
            try:
                # mkdtemp made it private (0700); as the directory would be made.
                umask = os.umask(0)
                os.umask(umask)
                os.chmod(self.staging, 0o777 & ~umask)
                os.rename(self.staging, aside)
            except OSError as exc:
                raise FileAccessError(f"{aside}: outputs not moved aside ({_text(exc)})") from exc
            self.staging = None  # moved: nothing to remove
            fsync_directory(self.directory)
            self.placed = aside
            return
        self._replace()
        self.placed = self.directory

    def _replace(self) -> None:
        """Remove the earlier run's owned files the new run did not write, then rename the
        new ones into place, and make the renames durable."""
        assert self.staging is not None
        new = sorted(n for n in os.listdir(self.staging) if self._owns(n))
        try:
            for name in self.existing():
                if name not in new:
                    (self.directory / name).unlink(missing_ok=True)
            for name in new:
                os.replace(self.staging / name, self.directory / name)
        except OSError as exc:
            raise FileAccessError(
                f"{self.directory}: outputs not moved into place ({_text(exc)})"
            ) from exc
        fsync_directory(self.directory)

    def _release(self) -> None:
        if self._lock is not None:
            lock, self._lock = self._lock, None
            lock.__exit__(None, None, None)
