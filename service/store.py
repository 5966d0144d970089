"""The store of record: `traits.sqlite` in WAL mode, committed after every scan, so a power
cut loses at most the scan in flight and the file always opens clean.

Tables:
- `run`: key/value facts about the run (software, calibration, method, start time).
- `trees`: the latest state of every tree (one row per tree, replaced on each update);
  `status` found, or missing for a field-map tree passed and not found (tree_id
  `missing:<field id>`, replaced at each export); `height_top_seen` 1 when some scan's
  beam passed over the crown's top, 0 when its height is a lower bound, NULL unjudged.
- `rejected`: objects seen as often as trees that are not trees, with the reason
  (replaced at each export).
- `observations`: every per-scan observation of a tree or object (append only).
"""

from __future__ import annotations

import contextlib
import json
import sqlite3
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

from treetraits.pipeline.trees import Tree

SCHEMA = """
CREATE TABLE IF NOT EXISTS run (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS trees (
    tree_id TEXT PRIMARY KEY,
    field_id TEXT, row TEXT,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL,  -- NULL until measured
    observations INTEGER NOT NULL, first_seen INTEGER, last_seen INTEGER,
    status TEXT NOT NULL DEFAULT 'found',
    height_top_seen INTEGER  -- 1, 0 (the height is a lower bound), NULL (not judged)
);
CREATE TABLE IF NOT EXISTS rejected (
    tree_id TEXT PRIMARY KEY, reason TEXT NOT NULL,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL,
    observations INTEGER NOT NULL, first_seen INTEGER NOT NULL, last_seen INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS observations (
    scan_t INTEGER NOT NULL, tree_id TEXT NOT NULL,
    x REAL NOT NULL, y REAL NOT NULL, z REAL NOT NULL, frame TEXT NOT NULL,
    width_m REAL, height_m REAL, ndvi REAL, points INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS observations_tree ON observations (tree_id);
"""


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
        """A store written before a column was appended gets it (NULL: not known)."""
        have = {row[1] for row in self._db.execute("PRAGMA table_info(trees)")}
        if "height_top_seen" not in have:
            self._db.execute("ALTER TABLE trees ADD COLUMN height_top_seen INTEGER")

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
                "INSERT INTO rejected VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [(t.tree_id, t.reason or "", *_measured(t)) for t in rejected],
            )

    def _insert_trees(self, trees: Iterable[Tree]) -> None:
        self._db.executemany(
            "INSERT OR REPLACE INTO trees VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
            [
                (
                    t.tree_id or f"missing:{t.field_id}",
                    t.field_id,
                    t.row,
                    *_measured(t),
                    t.status,
                    None if t.height_top_seen is None else int(t.height_top_seen),
                )
                for t in trees
            ],
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
        rows = self._db.execute(
            "SELECT tree_id, easting, northing, utm_zone, lat, lon, width_m, height_m, ndvi, "
            "observations, first_seen, last_seen, field_id, row, status, height_top_seen "
            "FROM trees ORDER BY tree_id"
        ).fetchall()
        return [
            Tree(*row[:-1], height_top_seen=None if row[-1] is None else bool(row[-1]))
            for row in rows
        ]

    def observation_count(self) -> int:
        return self._db.execute("SELECT COUNT(*) FROM observations").fetchone()[0]

    def close(self) -> None:
        self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
        self._db.close()

    def __enter__(self) -> TraitStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _measured(t: Tree) -> tuple:
    """A tree's columns from `easting` to `last_seen`, as the trees and rejected tables
    hold them (an unmeasured trait, NaN, as NULL)."""
    return (
        t.easting,
        t.northing,
        t.utm_zone,
        t.lat,
        t.lon,
        _real(t.width_m),
        _real(t.height_m),
        t.ndvi,
        t.observations,
        t.first_seen,
        t.last_seen,
    )


def _real(value: float | None) -> float | None:
    """NULL for an unmeasured trait (NaN)."""
    return None if value is None or value != value else value
