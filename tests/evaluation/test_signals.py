"""`treetraits eval` stopped while its worker processes simulate (issue 14): SIGTERM to the
main process (`kill`, a CI runner's timeout) or SIGINT to the whole process group (Ctrl-C
in a terminal) ends the main process and every worker within seconds, with one line and
the documented exit code (docs/cli.md), never a traceback."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers.paths import REPO
from treetraits.errors import EXIT_INTERRUPTED, EXIT_TERMINATED

STOP_S = 10.0  # "promptly": the workers are killed, not waited for


def _children(pid: int) -> set[int]:
    found: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        text = (task / "children").read_text()
        found |= {int(p) for p in text.split()}
    return found


def _alive(pid: int) -> bool:
    """Running (a zombie waiting for its parent to reap it is not)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.parametrize(
    ("signum", "whole_group", "code"),
    [(signal.SIGTERM, False, EXIT_TERMINATED), (signal.SIGINT, True, EXIT_INTERRUPTED)],
    ids=["sigterm", "ctrl-c"],
)
def test_eval_stops_with_its_workers(tmp_path, signum, whole_group, code):
    argv = ["eval", "--cases", "straight-5x5", "--quick", "--methods", "paper"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "treetraits", *argv, "--jobs", "2", "--out", str(tmp_path)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own group, as a shell gives a command
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        # Until the pool is up (spawned Python processes), then into the simulation
        # (a minute here: its recording is written at the end).
        deadline = time.monotonic() + 180
        workers: set[int] = set()
        while not workers:
            assert proc.poll() is None, proc.communicate()[1]
            assert time.monotonic() < deadline, "no worker started"
            time.sleep(0.05)
            workers = {p for p in _children(proc.pid) if _alive(p)}
        time.sleep(8.0)
        assert not list((tmp_path / "cases").glob("*.sim.json"))  # still simulating
        workers = {p for p in _children(proc.pid) if _alive(p)}
        sent = time.monotonic()
        if whole_group:
            os.killpg(proc.pid, signum)
        else:
            proc.send_signal(signum)
        _, err = proc.communicate(timeout=60)
        took = time.monotonic() - sent
        while any(_alive(p) for p in workers) and time.monotonic() - sent < STOP_S:
            time.sleep(0.05)
        left = [p for p in workers if _alive(p)]
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert took < STOP_S, (took, err)
    assert not left, f"workers still running {STOP_S} s after the signal: {left}"
    assert proc.returncode == code, err
    name = signal.Signals(signum).name
    assert err.strip().splitlines()[-1] == f"treetraits: error: interrupted ({name})", err
    assert "Traceback" not in err


def test_a_pool_stopped_by_an_exception_leaves_no_thread_behind():
    """The pool's manager thread has ended (its wake-up pipe closed) when the exception
    leaves `_stopped_on_exception`: at exit, concurrent.futures writes to that pipe without
    a lock, and a close at the same moment printed an EBADF traceback after the one-line
    error (seen once under load in this file's test above)."""
    import threading
    from concurrent.futures import ProcessPoolExecutor
    from multiprocessing import get_context

    from treetraits.evaluation.run import _stopped_on_exception

    before = set(threading.enumerate())
    pool = ProcessPoolExecutor(max_workers=1, mp_context=get_context("spawn"))
    with pytest.raises(KeyboardInterrupt), _stopped_on_exception(pool):
        running = pool.submit(time.sleep, 60)
        deadline = time.monotonic() + 60
        while not running.running() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert running.running()
        raise KeyboardInterrupt
    assert set(threading.enumerate()) == before
