"""The SQLite store of record: per-scan transactions, and a kill -9 in the middle of a
scan loses only that scan; the file opens clean."""

from __future__ import annotations

import dataclasses
import math
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

from tests.helpers.paths import REPO
from tests.helpers.store import tree
from treetraits.pipeline.trees import SQL_FIELDS, TREE_FIELD, Tree
from treetraits.service.store import REJECTED_COLUMNS, Observation, TraitStore, trees_table_sql


def test_round_trip(tmp_path):
    with TraitStore(tmp_path / "traits.sqlite") as store:
        store.set_run_facts({"method": "paper", "calibration": {"wheels": {"radius": 0.098}}})
        store.commit_scan(
            [Observation(1, "T1", 1.0, 2.0, 0.0, "utm", 2.7, 2.6, 0.7, 300)], [tree(1)]
        )
        store.commit_scan(
            [Observation(2, "T1", 1.0, 2.1, 0.0, "utm", 2.8, 2.6, 0.7, 310)],
            [tree(1, observations=2), tree(2)],
        )
        assert [t.tree_id for t in store.trees()] == ["T1", "T2"]
        assert store.trees()[0].observations == 2
        assert store.observation_count() == 2
    db = sqlite3.connect(tmp_path / "traits.sqlite")
    assert db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    assert dict(db.execute("SELECT key, value FROM run"))["method"] == "paper"


def test_kill_9_mid_scan_loses_only_that_scan(tmp_path):
    path = tmp_path / "traits.sqlite"
    writer = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from tests.helpers.store import tree
        from treetraits.service.store import Observation, TraitStore
        store = TraitStore({str(path)!r})
        for scan in range(1, 1_000_000):
            observations = [Observation(scan, f"T{{i}}", 0, 0, 0, "utm", 2.7, 2.6, 0.7, 100)
                            for i in range(50)]
            store.commit_scan(observations, [tree(i, scan) for i in range(50)])
            print(scan, flush=True)
    """)
    process = subprocess.Popen([sys.executable, "-c", writer], stdout=subprocess.PIPE, text=True)
    committed = 0
    deadline = time.monotonic() + 20
    while committed < 40 and time.monotonic() < deadline:
        committed = int(process.stdout.readline())
    process.send_signal(signal.SIGKILL)
    process.wait()
    # The writer runs ahead of this reader: the scans it reported before the kill are all
    # the lines in the pipe, not only those read so far.
    committed = max([committed, *map(int, process.stdout.read().split())])
    assert committed >= 40

    db = sqlite3.connect(path)
    assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    scans = db.execute("SELECT COUNT(DISTINCT scan_t) FROM observations").fetchone()[0]
    # Every scan reported committed is there; at most the one in flight beyond it.
    assert committed <= scans <= committed + 1
    # Trees and observations agree: no half-written scan.
    assert db.execute("SELECT COUNT(*) FROM observations").fetchone()[0] == 50 * scans
    assert db.execute("SELECT MAX(observations) FROM trees").fetchone()[0] == scans


def test_rollback_ends_a_transaction_a_failed_commit_left_open(tmp_path):
    with TraitStore(tmp_path / "traits.sqlite") as store:
        store.rollback()  # nothing open: nothing to do
        store.commit_scan([Observation(1, "T1", 1.0, 2.0, 0.0, "utm", 2.7, 2.6, 0.7, 9)], [tree(1)])
        # What SQLite can leave after a COMMIT that failed (SQLITE_BUSY, some SQLITE_FULL
        # paths): the scan's writes in a transaction still open. No public call makes that
        # state on demand, so it is made here on the connection.
        store._db.execute("BEGIN")
        store._db.execute(
            "INSERT INTO trees (tree_id, observations, first_seen, last_seen) "
            "VALUES ('T9', 1, 0, 0)"
        )
        try:
            store.commit_scan([], [tree(2)])
        except sqlite3.OperationalError as exc:
            assert "within a transaction" in str(exc)
        else:
            raise AssertionError("a BEGIN inside an open transaction should have failed")
        store.rollback()
        store.commit_scan([], [tree(2)])  # the store takes scans again
        assert [t.tree_id for t in store.trees()] == ["T1", "T2"]  # the half scan is gone


def test_a_commit_failing_on_a_full_disk_leaves_the_store_usable(tmp_path):
    # A child process with a file size limit (SIGXFSZ ignored, so writes past it fail with
    # EFBIG, as they would with ENOSPC on a full disk).
    script = textwrap.dedent(
        """
        import os, resource, signal, sqlite3, sys
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        from treetraits.service.store import Observation, TraitStore
        from tests.helpers.store import tree
        path = sys.argv[1]
        store = TraitStore(path)
        store.commit_scan([Observation(1, "T1", 1.0, 2.0, 0.0, "utm", 2.7, 2.6, 0.7, 9)], [tree(1)])
        limit = os.path.getsize(path + "-wal") + 8192
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.RLIM_INFINITY))
        row = (2.0, 0.0, "utm", 2.7, 2.6, 0.7, 9)
        many = [Observation(2, f"T{i}", 1.0, *row) for i in range(5000)]
        try:
            store.commit_scan(many, [tree(2)])
            print("committed")
        except sqlite3.Error as exc:
            print("failed", exc)
        store.rollback()
        resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY,) * 2)
        store.commit_scan(many[:1], [tree(3)])
        print("observations", store.observation_count())
        store.close()
        """
    )
    done = subprocess.run(
        [sys.executable, "-c", script, str(tmp_path / "traits.sqlite")],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
    )
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert lines[0].startswith("failed") and lines[1] == "observations 2"  # no half scan


# The trees table's text as the stores on disk hold it; a new column is a line after these.
STORED_TREES_TABLE = """CREATE TABLE IF NOT EXISTS trees (
    tree_id TEXT PRIMARY KEY,
    field_id TEXT, row TEXT,
    easting REAL, northing REAL, utm_zone TEXT, lat REAL, lon REAL,
    width_m REAL, height_m REAL, ndvi REAL,  -- NULL until measured
    observations INTEGER NOT NULL, first_seen INTEGER, last_seen INTEGER,
    status TEXT NOT NULL DEFAULT 'found',
    height_top_seen INTEGER  -- 1, 0 (the height is a lower bound), NULL (not judged)
"""


def test_the_trees_table_is_made_from_the_fields_table(tmp_path):
    def unended(line: str) -> str:  # the line without the comma an appended column adds
        return line.replace(",  --", "  --").rstrip(",")

    stored = STORED_TREES_TABLE.splitlines()
    made = trees_table_sql().splitlines()
    assert [unended(line) for line in made[: len(stored)]] == [unended(x) for x in stored]
    with TraitStore(tmp_path / "traits.sqlite") as store:
        trees = list(store._db.execute("PRAGMA table_info(trees)"))
        rejected = list(store._db.execute("PRAGMA table_info(rejected)"))
    assert [(c[1], c[2]) for c in trees] == [(f.name, f.format.sql_type) for f in SQL_FIELDS]
    assert [(c[1], c[2]) for c in rejected] == [
        (name, TREE_FIELD[name].format.sql_type) for name in REJECTED_COLUMNS
    ]


def test_trees_read_back_as_they_were_written(tmp_path):
    found = dataclasses.replace(tree(1), field_id="F1", row="r1", height_top_seen=False)
    missing = Tree(
        "", 1.0, 2.0, "11N", 33.9, -117.3, math.nan, math.nan, None, 0, None, None, "F2", "r1",
        "missing",
    )  # fmt: skip
    cues = {"evidence": -0.75, "texture_m": 0.011, "planar_share": None, "intensity": 40.5}
    rejected = dataclasses.replace(tree(3), status="rejected", reason="post", **cues)
    with TraitStore(tmp_path / "traits.sqlite") as store:
        store.commit_scan([], [found])
        store.replace_unmatched([missing], [rejected])
        back = store.trees()
        stored = store._db.execute("SELECT * FROM rejected").fetchall()
        top_seen = store._db.execute("SELECT height_top_seen FROM trees").fetchall()
    assert back[0] == found
    # The missing tree keyed by its field id, its unmeasured traits NaN again (as text:
    # NaN is not equal to itself).
    assert repr(back[1]) == repr(dataclasses.replace(missing, tree_id="missing:F2"))
    assert stored == [("T3", "post", 467003.0, 3758000.0, "11N", 33.96, -117.35, 2.7, 2.6,
                       0.75, 1, 1000, 2001, -0.75, 0.011, None, 40.5)]  # fmt: skip
    assert top_seen == [(0,), (None,)]  # a flag as 0 / 1, unjudged NULL


def test_a_store_from_before_a_column_gets_it(tmp_path):
    path = tmp_path / "traits.sqlite"
    old = sqlite3.connect(path)
    old.execute(
        "CREATE TABLE trees (tree_id TEXT PRIMARY KEY, field_id TEXT, row TEXT, easting REAL, "
        "northing REAL, utm_zone TEXT, lat REAL, lon REAL, width_m REAL, height_m REAL, "
        "ndvi REAL, observations INTEGER NOT NULL, first_seen INTEGER, last_seen INTEGER, "
        "status TEXT NOT NULL DEFAULT 'found')"
    )
    old.execute("INSERT INTO trees (tree_id, observations) VALUES ('T0', 3)")
    old.commit()
    old.close()
    with TraitStore(path) as store:
        store.commit_scan([], [tree(1)])
        assert [(t.tree_id, t.height_top_seen) for t in store.trees()] == [
            ("T0", None),
            ("T1", None),
        ]


def test_a_store_from_before_the_width_flag_gets_it(tmp_path):
    """A run's store written with the height flag and no width flag: opened, it gains
    `width_sides_seen`, NULL (not judged) for the trees already there, and keeps the flag
    of the trees written after."""
    path = tmp_path / "traits.sqlite"
    old = sqlite3.connect(path)
    old.executescript(STORED_TREES_TABLE + ");")
    old.execute("INSERT INTO trees (tree_id, observations, height_top_seen) VALUES ('T0', 3, 0)")
    old.commit()
    old.close()
    with TraitStore(path) as store:
        store.commit_scan([], [dataclasses.replace(tree(1), width_sides_seen=1)])
        back = [(t.tree_id, t.height_top_seen, t.width_sides_seen) for t in store.trees()]
        stored = store._db.execute("SELECT width_sides_seen FROM trees ORDER BY tree_id")
        assert stored.fetchall() == [(None,), (1,)]
    assert back == [("T0", False, None), ("T1", None, 1)]


def test_a_rejected_table_from_before_the_cues_gets_them(tmp_path):
    """A store whose `rejected` table predates the vegetation cues: opened, it gains
    them (NULL for the objects already there) and takes new objects with their cues."""
    path = tmp_path / "traits.sqlite"
    old = sqlite3.connect(path)
    old.execute(
        "CREATE TABLE rejected (tree_id TEXT PRIMARY KEY, reason TEXT NOT NULL, easting REAL, "
        "northing REAL, utm_zone TEXT, lat REAL, lon REAL, width_m REAL, height_m REAL, "
        "ndvi REAL, observations INTEGER NOT NULL, first_seen INTEGER NOT NULL, "
        "last_seen INTEGER NOT NULL)"
    )
    old.execute(
        "INSERT INTO rejected VALUES ('T9', 'smooth', 1, 2, '11N', 3, 4, 1, 2, 0.1, 5, 6, 7)"
    )
    old.commit()
    old.close()
    with TraitStore(path) as store:
        columns = [row[1] for row in store._db.execute("PRAGMA table_info(rejected)")]
        assert columns[-4:] == ["evidence", "texture_m", "planar_share", "intensity"]
        assert store._db.execute("SELECT evidence FROM rejected").fetchall() == [(None,)]
        rejected = dataclasses.replace(tree(3), status="rejected", reason="smooth", evidence=-1.0)
        store.replace_unmatched([], [rejected])
        assert store._db.execute("SELECT tree_id, evidence FROM rejected").fetchall() == [
            ("T3", -1.0)
        ]
