"""Stores opened by a command that only reads them (treetraits/readonly.py): read-only,
nothing left beside them, a WAL writer's changes read through its -wal, and every SQLite
error naming the file. Real SQLite files; the read-only disk through the CLI, in
tests/cli/test_rules.py."""

from __future__ import annotations

import contextlib
import shutil
import sqlite3
import sys
from pathlib import Path

import pytest

from tests.helpers.readonly import run_read_only
from tests.helpers.season import small_season
from treetraits.errors import EXIT_IO, EXIT_USAGE
from treetraits.readonly import (
    NotAStoreError,
    StoreReadError,
    connect_read_only,
    read_only_uri,
    sqlite_errors,
)


def _rows(path: Path) -> list[tuple]:
    with contextlib.closing(connect_read_only(path)) as db:
        return db.execute("SELECT tree_id FROM trees ORDER BY tree_id").fetchall()


def test_a_closed_store_is_read_immutable_and_nothing_is_left_beside_it(tmp_path):
    store = small_season(tmp_path / "season.sqlite")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["season.sqlite"]
    assert read_only_uri(store).endswith("?mode=ro&immutable=1")
    assert _rows(store) == [("pos-1",), ("pos-2",), ("pos-3",)]
    # mode=ro alone would have made season.sqlite-wal and -shm and left them.
    assert sorted(p.name for p in tmp_path.iterdir()) == ["season.sqlite"]


def test_a_store_being_written_is_read_through_its_wal(tmp_path):
    """A writer holds the store with changes in its -wal (a live run, a batch): read
    without immutable, so the changes are seen; the writer's files stay its own."""
    store = small_season(tmp_path / "season.sqlite")
    with contextlib.closing(sqlite3.connect(store, isolation_level=None)) as writer:
        writer.execute("PRAGMA journal_mode=WAL")
        writer.execute("PRAGMA wal_autocheckpoint=0")  # the change stays in the -wal
        writer.execute("UPDATE trees SET tree_id = 'T9' WHERE tree_id = 'pos-3'")
        assert (tmp_path / "season.sqlite-wal").stat().st_size > 0
        assert read_only_uri(store).endswith("?mode=ro")
        assert _rows(store) == [("T9",), ("pos-1",), ("pos-2",)]


# Run in a process of its own with the store's directory read-only (tests/helpers/
# readonly.py): what it reads, or the error it is refused with.
_READ = """
import contextlib, sys
from treetraits.readonly import connect_read_only, StoreReadError
try:
    with contextlib.closing(connect_read_only(sys.argv[1])) as db:
        print(*(r[0] for r in db.execute("SELECT tree_id FROM trees ORDER BY tree_id")))
except StoreReadError as exc:
    print(f"{type(exc).__name__} {exc.exit_code} {exc}")
"""


def test_changes_that_cannot_be_read_on_a_read_only_disk_are_refused_naming_the_file(tmp_path):
    """A store copied with its -wal of changes but no -shm onto a read-only disk: SQLite
    cannot read the changes there, so the store is refused in one line rather than read
    without them."""
    (tmp_path / "live").mkdir()
    live = small_season(tmp_path / "live" / "season.sqlite")
    copy = tmp_path / "copy"
    copy.mkdir()
    with contextlib.closing(sqlite3.connect(live, isolation_level=None)) as writer:
        writer.execute("PRAGMA journal_mode=WAL")
        writer.execute("PRAGMA wal_autocheckpoint=0")
        writer.execute("UPDATE trees SET tree_id = 'T9' WHERE tree_id = 'pos-3'")
        for name in ("season.sqlite", "season.sqlite-wal"):
            shutil.copy(live.parent / name, copy / name)
    store = copy / "season.sqlite"
    result = run_read_only(copy, [sys.executable, "-c", _READ, str(store)])
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith(f"StoreReadError {EXIT_IO} {store}: "), result.stdout
    assert "holds changes not yet in the store" in result.stdout
    assert sorted(p.name for p in copy.iterdir()) == ["season.sqlite", "season.sqlite-wal"]


def test_a_store_in_a_directory_that_may_not_be_written_reads(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    store = small_season(folder / "season.sqlite")
    result = run_read_only(folder, [sys.executable, "-c", _READ, str(store)])
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["pos-1", "pos-2", "pos-3"]
    assert sorted(p.name for p in folder.iterdir()) == ["season.sqlite"]


def test_sqlite_errors_name_the_file(tmp_path):
    not_sqlite = tmp_path / "notes.sqlite"
    not_sqlite.write_bytes(b"not an SQLite file\n" * 200)
    with pytest.raises(NotAStoreError, match="not a season store") as error:
        connect_read_only(not_sqlite, "a season store")
    assert str(error.value).startswith(f"{not_sqlite}: ") and error.value.exit_code == EXIT_USAGE
    store = small_season(tmp_path / "season.sqlite")
    with contextlib.closing(connect_read_only(store)) as db:
        with pytest.raises(NotAStoreError, match="no such table: nope"), sqlite_errors(store):
            db.execute("SELECT * FROM nope")
        written = "INSERT INTO trees (tree_id, block) VALUES ('x', 'y')"  # read-only: refused
        with (
            pytest.raises(StoreReadError, match=r"season\.sqlite: SQLite: ") as refused,
            sqlite_errors(store),
        ):
            db.execute(written)
        assert refused.value.exit_code == EXIT_IO
    a_directory = tmp_path / "dir.sqlite"
    a_directory.mkdir()
    with pytest.raises(StoreReadError, match=r"dir\.sqlite: SQLite: "):
        connect_read_only(a_directory)
