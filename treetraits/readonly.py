"""Stores read by a command that only reads them (`report`, `season`, `export foxglove` of
a run directory): opened read-only, leaving nothing behind, on a read-only disk too
(docs/cli.md, "Inputs are only read").

A store of ours is in WAL mode. SQLite opened `mode=ro` still makes the `-wal` and `-shm`
files beside it (and leaves them), and cannot open the store at all where it may not make
them (a read-only disk, a directory without write permission). `immutable=1` reads the
file alone, with no side file and no lock, but misses what a `-wal` holds. So:

- no `-wal` beside the store (no writer has it open: a WAL writer keeps its `-wal` until it
  closes), or an empty one: `immutable=1`, the file is the whole store;
- a `-wal` with changes in a directory we may write, or with its `-shm` (a live run, a batch
  writing the season): `mode=ro`, through the writer's `-wal` and `-shm`;
- a `-wal` with changes, no `-shm` and a directory we may not write: SQLite cannot read
  the changes there; refused in one line saying so, not read without them.

Every SQLite error is raised naming the file (`StoreReadError`, exit 6; a file that is no
SQLite database: `NotAStoreError`, exit 2).
"""

from __future__ import annotations

import contextlib
import os
import sqlite3
from collections.abc import Iterator
from pathlib import Path

from treetraits.errors import FileAccessError, SourceError


class StoreReadError(FileAccessError):
    """SQLite could not read a store (unreadable, locked, an I/O error): the file named."""


class NotAStoreError(SourceError):
    """A file that is not an SQLite database (or not the store expected)."""


def read_only_uri(path: Path) -> str:
    """The URI to open `path` read-only with, by the module's rules."""
    uri = f"{path.resolve().as_uri()}?mode=ro"
    wal = path.with_name(path.name + "-wal")
    try:
        has_changes = wal.stat().st_size > 0
    except FileNotFoundError:
        has_changes = False
    if not has_changes:
        return uri + "&immutable=1"
    shm = path.with_name(path.name + "-shm")
    if not shm.exists() and not os.access(path.parent, os.W_OK):
        raise StoreReadError(
            f"{path}: its {wal.name} holds changes not yet in the store and its directory is "
            f"read-only (SQLite needs a {shm.name} there to read them); copy the store with "
            f"its {wal.name} to a writable place and read that"
        )
    return uri


def connect_read_only(path: str | os.PathLike, what: str = "an SQLite store") -> sqlite3.Connection:
    """`path` opened read-only (the module's rules), its header read: a file that is no
    SQLite database is a `NotAStoreError` naming `what` was expected."""
    path = Path(path)
    with sqlite_errors(path):
        db = sqlite3.connect(read_only_uri(path), uri=True, timeout=30)
    try:
        with sqlite_errors(path, what):
            db.execute("SELECT name FROM sqlite_master").fetchall()
    except BaseException:
        db.close()
        raise
    return db


@contextlib.contextmanager
def sqlite_errors(path: Path, what: str = "an SQLite store") -> Iterator[None]:
    """SQLite's errors inside, raised naming `path`: what the system refused (unable to
    open, locked, I/O) as a `StoreReadError`, a file that is no database as a
    `NotAStoreError`."""
    try:
        yield
    except sqlite3.OperationalError as exc:
        if str(exc).startswith(_NOT_OURS):  # a database, but without our tables
            raise NotAStoreError(f"{path}: not {what} ({exc})") from None
        raise StoreReadError(f"{path}: SQLite: {exc}") from None
    except sqlite3.DatabaseError as exc:  # "file is not a database", malformed
        raise NotAStoreError(f"{path}: not {what} ({exc})") from None


_NOT_OURS = ("no such table", "no such column")
