"""The SQLite store of record: per-scan transactions, and a kill -9 in the middle of a
scan loses only that scan; the file opens clean."""

from __future__ import annotations

import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

from tests.helpers.paths import REPO
from tests.helpers.store import tree
from treetraits.service.store import Observation, TraitStore


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
