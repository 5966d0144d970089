"""The season store: one SQLite file holding every survey of a season and each tree's
history across them (docs/season.md).

Written by one process only (the `treetraits batch` client): no concurrent writers. The
runs' own trees are kept as they came (`survey_trees`); which tree of one survey is which
tree of another is derived from them (`trees`, `tree_surveys`) by `relink`, rebuilt for a
whole block in date order each time a survey is added or replaced, so the result does not
depend on the order the recordings were processed in.
"""

from __future__ import annotations

import json
import sqlite3
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from treetraits.errors import TreetraitsError
from treetraits.files import iso_utc
from treetraits.pipeline.trees import (
    TREE_FIELD,
    Tree,
    json_value,
    sql_values,
    tree_from_sql,
)

SCHEMA = """
CREATE TABLE IF NOT EXISTS season (key TEXT PRIMARY KEY, value TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS surveys (
    survey_id INTEGER PRIMARY KEY,
    block TEXT NOT NULL,
    recording TEXT NOT NULL,         -- the path the batch was given
    fingerprint TEXT NOT NULL,       -- the recording's content (`recording_fingerprint`)
    t_start INTEGER NOT NULL,        -- the recording's first message, ns since the epoch
    software TEXT NOT NULL,          -- "treetraits X.Y.Z"
    config_key TEXT NOT NULL,        -- sha256 of the pipeline config the run used
    run_dir TEXT NOT NULL,           -- the run's outputs (traits.sqlite, trees.csv...)
    data_loss INTEGER NOT NULL,      -- 1: a damaged or cut recording, read as far as it went
    summary TEXT NOT NULL,           -- the replay's summary, JSON
    processed_at TEXT NOT NULL,
    UNIQUE (block, fingerprint)
);
CREATE TABLE IF NOT EXISTS survey_trees (
    survey_id INTEGER NOT NULL REFERENCES surveys (survey_id) ON DELETE CASCADE,
    run_tree_id TEXT NOT NULL,       -- the tree's id in its run ("" for a missing tree)
    status TEXT NOT NULL,            -- found, or missing (a field-map tree passed, not found)
    field_id TEXT, row TEXT,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL, observations INTEGER NOT NULL,
    height_top_seen INTEGER,         -- 1, 0 (the height is a lower bound), NULL (not known)
    width_sides_seen INTEGER         -- 2, 1 (one side: the width is a lower bound), NULL
);
CREATE INDEX IF NOT EXISTS survey_trees_survey ON survey_trees (survey_id);
CREATE TABLE IF NOT EXISTS trees (
    tree_id TEXT NOT NULL,           -- the field id, else pos-N (linked by position)
    block TEXT NOT NULL,
    field_id TEXT, row TEXT,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,  -- mean of its finds
    PRIMARY KEY (block, tree_id)     -- blocks' field maps may share ids (T1 in each)
);
CREATE TABLE IF NOT EXISTS tree_surveys (
    tree_id TEXT NOT NULL,           -- in the survey's block
    survey_id INTEGER NOT NULL REFERENCES surveys (survey_id) ON DELETE CASCADE,
    status TEXT NOT NULL,            -- found or missing
    run_tree_id TEXT,
    easting REAL, northing REAL, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL, observations INTEGER,
    height_top_seen INTEGER, width_sides_seen INTEGER,  -- as in survey_trees
    PRIMARY KEY (tree_id, survey_id)
);
CREATE TABLE IF NOT EXISTS failures (
    recording TEXT NOT NULL, block TEXT NOT NULL, software TEXT NOT NULL,
    config_key TEXT NOT NULL, error TEXT NOT NULL, at TEXT NOT NULL
);
"""

# 2: `survey_trees` and `tree_surveys` keep how each height and width was measured
# (`height_top_seen`, `width_sides_seen`). A store of version 1 is read with them NULL
# (not known) and upgraded when a batch opens it to write: the columns added, NULL for the
# surveys already there. Version 1 software refuses a version 2 store rather than
# writing rows without the flags.
SCHEMA_VERSION = "2"
READABLE_VERSIONS = ("1", SCHEMA_VERSION)
# The columns version 2 appended, to both tables.
FLAG_COLUMNS = ("height_top_seen", "width_sides_seen")

# The run's tree columns `survey_trees` keeps after `survey_id` (`tree_id` as
# `run_tree_id`), and the ones of a visit (`tree_surveys`, `TreeVisit`), each stored as
# the run's `trees` table stores it (pipeline/trees.py).
SURVEY_TREE_COLUMNS = (
    "tree_id",
    "status",
    "field_id",
    "row",
    "easting",
    "northing",
    "utm_zone",
    "lat",
    "lon",
    "width_m",
    "height_m",
    "ndvi",
    "observations",
    *FLAG_COLUMNS,
)
VISIT_COLUMNS = (
    "easting",
    "northing",
    "lat",
    "lon",
    "width_m",
    "height_m",
    "ndvi",
    "observations",
    *FLAG_COLUMNS,
)
_SURVEY_TREE_FIELDS = tuple(TREE_FIELD[name] for name in SURVEY_TREE_COLUMNS)
_VISIT_FIELDS = tuple(TREE_FIELD[name] for name in VISIT_COLUMNS)


class SeasonError(TreetraitsError):
    """A season store that cannot be used (not one, a newer schema), or an unknown tree."""


@dataclass(frozen=True)
class Survey:
    """One processed recording, as the season keeps it."""

    block: str
    recording: str
    fingerprint: str
    t_start: int
    software: str
    config_key: str
    run_dir: str
    data_loss: bool
    summary: dict = field(default_factory=dict)
    survey_id: int | None = None


@dataclass(frozen=True)
class TreeVisit:
    """One tree in one survey."""

    survey_id: int
    t_start: int
    recording: str
    status: str  # found or missing
    run_tree_id: str | None
    easting: float | None
    northing: float | None
    lat: float | None
    lon: float | None
    width_m: float | None
    height_m: float | None
    ndvi: float | None
    observations: int | None
    # How the run measured them (`Tree`'s fields): False / 1 mark a lower bound; None:
    # not known (a survey added before the season kept them, or a missing tree).
    height_top_seen: bool | None = None
    width_sides_seen: int | None = None


@dataclass(frozen=True)
class SeasonTree:
    """One tree of the season with its surveys in date order."""

    tree_id: str
    block: str
    field_id: str | None
    row: str | None
    easting: float | None
    northing: float | None
    utm_zone: str | None
    lat: float | None
    lon: float | None
    visits: list[TreeVisit]


class SeasonStore:
    """The season file. `with SeasonStore(path) as season: ...`; every change is one
    transaction."""

    def __init__(self, path: str | Path, *, create: bool = True):
        from treetraits.readonly import connect_read_only, sqlite_errors

        self.path = Path(path)
        if not create and not self.path.is_file():
            raise SeasonError(f"{self.path}: no such season store (batch writes one)")
        # A reader (`create=False`: season, report) never writes: opened read-only, on a
        # read-only disk too, and leaving no -wal/-shm (treetraits/readonly.py). WAL lets
        # it read while a batch is writing.
        with sqlite_errors(self.path, "a season store"):
            self._db = (
                sqlite3.connect(self.path, isolation_level=None, timeout=30)
                if create
                else connect_read_only(self.path, "a season store")
            )
        try:
            # Locked, unreadable: the system's words, naming the file (exit 6).
            with sqlite_errors(self.path, "a season store"):
                if create:
                    self._db.execute("PRAGMA foreign_keys=ON")
                    self._db.execute("PRAGMA journal_mode=WAL")
                    self._db.executescript(SCHEMA)
                    self._db.execute(
                        "INSERT OR IGNORE INTO season VALUES ('schema_version', ?)",
                        (SCHEMA_VERSION,),
                    )
                self._check()
                if create:
                    self._upgrade()
                self._flags = {t: self._columns(t) & set(FLAG_COLUMNS) for t in _FLAGGED}
        except BaseException:
            self._db.close()
            raise

    def _check(self) -> None:
        tables = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master")}
        if not {"season", "surveys", "trees", "tree_surveys"} <= tables:
            raise SeasonError(f"{self.path}: not a season store (no surveys or trees tables)")
        version = self._db.execute(
            "SELECT value FROM season WHERE key = 'schema_version'"
        ).fetchone()
        if version is None or version[0] not in READABLE_VERSIONS:
            raise SeasonError(
                f"{self.path}: season schema {version and version[0]!r}, this treetraits "
                f"reads {' and '.join(map(repr, READABLE_VERSIONS))}"
            )

    def _columns(self, table: str) -> set[str]:
        return {row[1] for row in self._db.execute(f"PRAGMA table_info({table})")}

    def _upgrade(self) -> None:
        """A version 1 store made version 2 (the writer only): the flag columns appended,
        NULL (not known) for the surveys it holds."""
        lacking = [
            (table, name)
            for table in _FLAGGED
            for name in FLAG_COLUMNS
            if name not in self._columns(table)
        ]
        version = self._db.execute("SELECT value FROM season WHERE key = 'schema_version'")
        if not lacking and version.fetchone()[0] == SCHEMA_VERSION:
            return
        with self._transaction():
            for table, name in lacking:
                definition = TREE_FIELD[name].sql_definition
                self._db.execute(f"ALTER TABLE {table} ADD COLUMN {name} {definition}")
            self._db.execute(
                "UPDATE season SET value = ? WHERE key = 'schema_version'", (SCHEMA_VERSION,)
            )

    # --- writing (the batch client) -----------------------------------------------------

    def processed(self, block: str, fingerprint: str, software: str, config_key: str) -> bool:
        """Whether this recording is in the season, processed by this software and config."""
        row = self._db.execute(
            "SELECT 1 FROM surveys WHERE block = ? AND fingerprint = ? AND software = ? "
            "AND config_key = ?",
            (block, fingerprint, software, config_key),
        ).fetchone()
        return row is not None

    def add_survey(self, survey: Survey, trees: Iterable[Tree], processed_at: str) -> int:
        """Add a survey and its run's trees (found and missing), replacing an earlier
        processing of the same recording in the same block. Returns its id; call `relink`
        for its block afterwards."""
        with self._transaction():
            self._db.execute(
                "DELETE FROM surveys WHERE block = ? AND fingerprint = ?",
                (survey.block, survey.fingerprint),
            )
            cursor = self._db.execute(
                "INSERT INTO surveys (block, recording, fingerprint, t_start, software, "
                "config_key, run_dir, data_loss, summary, processed_at) "
                "VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                (
                    survey.block,
                    survey.recording,
                    survey.fingerprint,
                    survey.t_start,
                    survey.software,
                    survey.config_key,
                    survey.run_dir,
                    int(survey.data_loss),
                    json.dumps(survey.summary),
                    processed_at,
                ),
            )
            survey_id = int(cursor.lastrowid)
            self._db.executemany(
                f"INSERT INTO survey_trees ({_SURVEY_TREES_NAMES}) "
                f"VALUES (?, {_marks(SURVEY_TREE_COLUMNS)})",
                [
                    (survey_id, *sql_values(t, _SURVEY_TREE_FIELDS))
                    for t in trees
                    if t.status in ("found", "missing")
                ],
            )
        return survey_id

    def add_failure(
        self, recording: str, block: str, software: str, config_key: str, error: str, at: str
    ) -> None:
        with self._transaction():
            self._db.execute(
                "INSERT INTO failures VALUES (?, ?, ?, ?, ?, ?)",
                (recording, block, software, config_key, error, at),
            )

    def relink(self, block: str, gate_m: float) -> None:
        """Rebuild the block's season trees and their links from its surveys' trees, in
        date order (pipeline/linking.py; docs/season.md)."""
        from treetraits.pipeline.linking import link_surveys

        surveys = self._db.execute(
            "SELECT survey_id FROM surveys WHERE block = ? ORDER BY t_start, survey_id",
            (block,),
        ).fetchall()
        per_survey = [(sid, self._survey_trees(sid)) for (sid,) in surveys]
        linked = link_surveys(per_survey, gate_m)
        with self._transaction():
            self._db.execute("DELETE FROM trees WHERE block = ?", (block,))
            self._db.execute(
                "DELETE FROM tree_surveys WHERE survey_id IN "
                "(SELECT survey_id FROM surveys WHERE block = ?)",
                (block,),
            )
            for tree in linked:
                self._db.execute(
                    "INSERT INTO trees VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                    (tree.tree_id, block, tree.field_id, tree.row, *tree.position()),
                )
                self._db.executemany(
                    f"INSERT INTO tree_surveys ({_TREE_SURVEYS_NAMES}) "
                    f"VALUES (?, ?, ?, ?, {_marks(VISIT_COLUMNS)})",
                    [
                        (
                            tree.tree_id,
                            survey_id,
                            status,
                            t.tree_id or None,
                            *sql_values(t, _VISIT_FIELDS),
                        )
                        for survey_id, status, t in tree.visits
                    ],
                )

    def _survey_trees(self, survey_id: int) -> list[Tree]:
        """A survey's run trees as they came, without what the season does not keep
        (times, the rejected objects' cues); flags a version 1 store lacks are None."""
        columns = ", ".join(
            "run_tree_id" if c == "tree_id" else self._flag_or_null("survey_trees", c)
            for c in SURVEY_TREE_COLUMNS
        )
        rows = self._db.execute(
            f"SELECT {columns} FROM survey_trees WHERE survey_id = ? ORDER BY rowid",
            (survey_id,),
        ).fetchall()
        return [tree_from_sql(dict(zip(SURVEY_TREE_COLUMNS, r, strict=True))) for r in rows]

    # --- reading ------------------------------------------------------------------------

    def blocks(self) -> list[str]:
        return [r[0] for r in self._db.execute("SELECT DISTINCT block FROM surveys ORDER BY 1")]

    def surveys(self) -> list[Survey]:
        rows = self._db.execute(
            "SELECT block, recording, fingerprint, t_start, software, config_key, run_dir, "
            "data_loss, summary, survey_id FROM surveys ORDER BY t_start, survey_id"
        ).fetchall()
        return [
            Survey(r[0], r[1], r[2], r[3], r[4], r[5], r[6], bool(r[7]), json.loads(r[8]), r[9])
            for r in rows
        ]

    def failures(self) -> list[dict]:
        rows = self._db.execute(
            "SELECT recording, block, software, config_key, error, at FROM failures"
        ).fetchall()
        keys = ("recording", "block", "software", "config_key", "error", "at")
        return [dict(zip(keys, r, strict=True)) for r in rows]

    def trees(self, tree_id: str | None = None) -> list[SeasonTree]:
        """Every season tree (or those with `tree_id`, one per block that has it) with its
        surveys in date order."""
        where, params = ("WHERE t.tree_id = ?", (tree_id,)) if tree_id is not None else ("", ())
        trees = self._db.execute(
            "SELECT tree_id, block, field_id, row, easting, northing, utm_zone, lat, lon "
            f"FROM trees t {where} ORDER BY block, tree_id",
            params,
        ).fetchall()
        visits: dict[tuple[str, str], list[TreeVisit]] = {(t[1], t[0]): [] for t in trees}
        rows = self._db.execute(
            "SELECT s.block, v.tree_id, v.survey_id, s.t_start, s.recording, v.status, "
            f"v.run_tree_id, {', '.join(self._visit_column(c) for c in VISIT_COLUMNS)} "
            "FROM tree_surveys v JOIN surveys s USING (survey_id) "
            f"{where.replace('t.', 'v.')} ORDER BY s.t_start, v.survey_id",
            params,
        ).fetchall()
        for r in rows:
            visits[(r[0], r[1])].append(_visit(r[2:]))
        return [SeasonTree(*t, visits=visits[(t[1], t[0])]) for t in trees]

    def _flag_or_null(self, table: str, column: str) -> str:
        """The column's name, or NULL for a flag a version 1 store read as it is lacks."""
        return "NULL" if column in FLAG_COLUMNS and column not in self._flags[table] else column

    def _visit_column(self, column: str) -> str:
        name = self._flag_or_null("tree_surveys", column)
        return name if name == "NULL" else f"v.{name}"

    # --- plumbing -----------------------------------------------------------------------

    def _transaction(self):
        return _Transaction(self._db)

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> SeasonStore:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class _Transaction:
    def __init__(self, db: sqlite3.Connection):
        self.db = db

    def __enter__(self) -> None:
        self.db.execute("BEGIN IMMEDIATE")

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.db.execute("COMMIT")
        elif self.db.in_transaction:
            self.db.execute("ROLLBACK")


def _marks(columns: Sequence) -> str:
    return ", ".join("?" * len(columns))


# The tables that hold the flags, and the columns the writes name (a version 1 store
# upgraded has the flags last, as a new one: named all the same).
_FLAGGED = ("survey_trees", "tree_surveys")
_SURVEY_TREES_NAMES = ", ".join(
    ["survey_id", *("run_tree_id" if c == "tree_id" else c for c in SURVEY_TREE_COLUMNS)]
)
_TREE_SURVEYS_NAMES = ", ".join(["tree_id", "survey_id", "status", "run_tree_id", *VISIT_COLUMNS])


def _visit(values: Sequence) -> TreeVisit:
    """A visit from its row (survey_id ... run_tree_id, then VISIT_COLUMNS): the flags as
    the run's fields hold them (a FLAG's 0 / 1 as False / True), NULL as None."""
    head, tail = values[: -len(VISIT_COLUMNS)], values[-len(VISIT_COLUMNS) :]
    cells = [
        TREE_FIELD[name].format.from_sql(value)
        if name in FLAG_COLUMNS and value is not None
        else value
        for name, value in zip(VISIT_COLUMNS, tail, strict=True)
    ]
    return TreeVisit(*head, *cells)


def season_trees_json(trees: Sequence[SeasonTree]) -> dict:
    """`season trees --json`: {"trees": [{"id": ..., "surveys": [{"date": ..., ...}]}]}."""

    def visit(v: TreeVisit) -> dict:
        return {
            "date": iso_utc(v.t_start),
            "survey": v.survey_id,
            "recording": v.recording,
            "status": v.status,
            "width_m": json_value("width_m", v.width_m),
            "height_m": json_value("height_m", v.height_m),
            "ndvi": json_value("ndvi", v.ndvi),
            "lat": json_value("lat", v.lat),
            "lon": json_value("lon", v.lon),
            "run_tree_id": v.run_tree_id,
            # How they were measured (null: not known): false / 1 mark a lower bound.
            "height_top_seen": v.height_top_seen,
            "width_sides_seen": v.width_sides_seen,
        }

    return {
        "trees": [
            {
                "id": t.tree_id,
                "block": t.block,
                "field_id": t.field_id,
                "row": t.row,
                "lat": json_value("lat", t.lat),
                "lon": json_value("lon", t.lon),
                "surveys": [visit(v) for v in t.visits],
            }
            for t in trees
        ]
    }
