"""The store of record: `traits.sqlite` in WAL mode, committed after every scan, so a power
cut loses at most the scan in flight and the file always opens clean.

Tables:
- `run`: key/value facts about the run (software, calibration, method, start time).
- `trees`: the latest state of every tree (one row per tree, replaced on each update),
  its columns made from `Tree`'s table (pipeline/trees.py); `status` found, or missing
  for a field-map tree passed and not found (tree_id `missing:<field id>`, replaced at
  each export); `height_top_seen` 1 when the height is measured (the crown's top
  bracketed within 5 % by a beam that passed over it), 0 when it is a lower bound, NULL
  unjudged; `width_sides_seen` 2 when the crown was seen from both sides, 1 when from one
  side only (its width a lower bound), NULL unjudged. A store written before a column
  was appended gets it, NULL.
- `rejected`: objects seen as often as trees that are not trees, with the reason
  (replaced at each export).
- `observations`: every per-scan observation of a tree or object (append only).
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

from treetraits.pipeline.trees import (
    SQL_FIELDS,
    TREE_FIELD,
    Tree,
    TreeField,
    sql_values,
    tree_from_sql,
)

# `rejected`'s columns (its text below), each stored as the `trees` column of that name
# is; `reason` is NOT NULL there: every rejected object has one.
REJECTED_COLUMNS = (
    "tree_id",
    "reason",
    "easting",
    "northing",
    "utm_zone",
    "lat",
    "lon",
    "width_m",
    "height_m",
    "ndvi",
    "observations",
    "first_seen",
    "last_seen",
    "evidence",
    "texture_m",
    "planar_share",
    "intensity",
)
# The cues appended to `rejected` (a store written before them gets them, NULL).
_REJECTED_APPENDED = ("evidence", "texture_m", "planar_share", "intensity")


def trees_table_sql(fields: Sequence[TreeField] = SQL_FIELDS) -> str:
    """The `trees` table's CREATE TABLE text, made from the fields' SQL definitions: the
    columns of one `sql_line` on one line, its `sql_note` as the line's comment."""
    lines: list[list[TreeField]] = []
    for f in fields:
        if lines and f.sql_line is not None and lines[-1][-1].sql_line == f.sql_line:
            lines[-1].append(f)
        else:
            lines.append([f])
    text = []
    for k, line in enumerate(lines):
        columns = ", ".join(f"{f.name} {f.sql_definition}" for f in line)
        comma = "," if k < len(lines) - 1 else ""
        notes = "; ".join(f.sql_note for f in line if f.sql_note)
        text.append(f"    {columns}{comma}" + (f"  -- {notes}" if notes else ""))
    return "CREATE TABLE IF NOT EXISTS trees (\n" + "\n".join(text) + "\n);\n"


SCHEMA = (
    """
CREATE TABLE IF NOT EXISTS run (key TEXT PRIMARY KEY, value TEXT NOT NULL);
"""
    + trees_table_sql()
    + """CREATE TABLE IF NOT EXISTS rejected (
    tree_id TEXT PRIMARY KEY, reason TEXT NOT NULL,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL,
    observations INTEGER NOT NULL, first_seen INTEGER NOT NULL, last_seen INTEGER NOT NULL,
    evidence REAL, texture_m REAL, planar_share REAL, intensity REAL  -- its vegetation cues
);
CREATE TABLE IF NOT EXISTS observations (
    scan_t INTEGER NOT NULL, tree_id TEXT NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL, frame TEXT NOT NULL,
    width_m REAL, height_m REAL, ndvi REAL, points INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS observations_tree ON observations (tree_id);
"""
)


@dataclass(frozen=True, slots=True)
class Observation:
    """One tree seen in one scan (a cluster associated with it)."""

    scan_t: int
    tree_id: str
    x: float
    y: float
    z: float
    frame: str
    width_m: float | None
    height_m: float | None
    ndvi: float | None
    points: int


class TraitStore:
    def __init__(self, path: str | Path):
        self.path = Path(path)
        # autocommit off: one transaction per scan, committed by `commit_scan`.
        self._db = sqlite3.connect(self.path, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")  # WAL + NORMAL: durable at checkpoints
        self._db.executescript(SCHEMA)
        self._add_missing_columns()

    def _add_missing_columns(self) -> None:
        """A store written before a column was appended gets it (NULL: not known; so an
        appended column allows NULL or has a default, as SQLite requires)."""
        have = {row[1] for row in self._db.execute("PRAGMA table_info(trees)")}
        for f in SQL_FIELDS:
            if f.name not in have:
                self._db.execute(f"ALTER TABLE trees ADD COLUMN {f.name} {f.sql_definition}")
        have = {row[1] for row in self._db.execute("PRAGMA table_info(rejected)")}
        for name in _REJECTED_APPENDED:
            if name not in have:
                self._db.execute(f"ALTER TABLE rejected ADD COLUMN {name} REAL")

    def set_run_facts(self, facts: dict) -> None:
        self._db.execute("BEGIN")
        for key, value in facts.items():
            text = value if isinstance(value, str) else json.dumps(value)
            self._db.execute("INSERT OR REPLACE INTO run VALUES (?, ?)", (key, text))
        self._db.execute("COMMIT")

    def commit_scan(self, observations: Iterable[Observation], trees: Iterable[Tree]) -> None:
        """Everything one scan changed, in one transaction."""
        with self._transaction():
            self._db.executemany(
                "INSERT INTO observations VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [
                    (
                        o.scan_t,
                        o.tree_id,
                        o.x,
                        o.y,
                        o.z,
                        o.frame,
                        o.width_m,
                        o.height_m,
                        o.ndvi,
                        o.points,
                    )
                    for o in observations
                ],
            )
            self._insert_trees(trees)

    def replace_unmatched(self, missing: Iterable[Tree], rejected: Iterable[Tree]) -> None:
        """The run's missing field-map trees and rejected objects as they stand now, in
        one transaction (each export recomputes both)."""
        with self._transaction():
            self._db.execute("DELETE FROM trees WHERE status = 'missing'")
            self._insert_trees(missing)
            self._db.execute("DELETE FROM rejected")
            self._db.executemany(
                f"INSERT INTO rejected VALUES ({_marks(REJECTED_COLUMNS)})",
                [sql_values(t, _REJECTED_FIELDS) for t in rejected],
            )

    def _insert_trees(self, trees: Iterable[Tree]) -> None:
        self._db.executemany(
            f"INSERT OR REPLACE INTO trees ({_TREES_COLUMNS}) VALUES ({_marks(SQL_FIELDS)})",
            [sql_values(_keyed(t)) for t in trees],
        )

    @contextlib.contextmanager
    def _transaction(self):
        """BEGIN ... COMMIT, rolled back if anything in between fails."""
        self._db.execute("BEGIN")
        try:
            yield
        except BaseException:
            self._db.execute("ROLLBACK")
            raise
        self._db.execute("COMMIT")

    def rollback(self) -> None:
        """End a transaction left open by a failed write (SQLite may leave one open after
        SQLITE_FULL or SQLITE_IOERR on COMMIT, and the next BEGIN would then fail for
        good). Nothing open: nothing to do. A ROLLBACK that fails means SQLite already
        rolled back by itself, so its error is not raised."""
        if self._db.in_transaction:
            with contextlib.suppress(sqlite3.Error):
                self._db.execute("ROLLBACK")

    def trees(self) -> list[Tree]:
        rows = self._db.execute(f"SELECT {_TREES_COLUMNS} FROM trees ORDER BY tree_id")
        names = [f.name for f in SQL_FIELDS]
        return [tree_from_sql(dict(zip(names, row, strict=True))) for row in rows]

    def observation_count(self) -> int:
        return self._db.execute("SELECT COUNT(*) FROM observations").fetchone()[0]

    def close(self) -> None:
        self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self._db.close()

    def __enter__(self) -> TraitStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


_TREES_COLUMNS = ", ".join(f.name for f in SQL_FIELDS)
_REJECTED_FIELDS = tuple(TREE_FIELD[name] for name in REJECTED_COLUMNS)


def _marks(columns: Sequence) -> str:
    return ", ".join("?" * len(columns))


def _keyed(tree: Tree) -> Tree:
    """A missing tree has no id of its own: the table keys it by its field id."""
    return tree if tree.tree_id else replace(tree, tree_id=f"missing:{tree.field_id}")
