"""The CLI's one error boundary (docs/cli.md, "Exit codes"): what the system refuses, bad
inputs and Ctrl-C each end in one line naming the file and the problem, with a documented
exit code, never a traceback; an earlier run's outputs stay as they were."""

from __future__ import annotations

import contextlib
import csv
import json
import resource
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.helpers.captures import VLP16_DIR
from tests.helpers.paths import REPO
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration
from treetraits.errors import EXIT_INTERRUPTED, EXIT_IO, EXIT_TERMINATED, EXIT_USAGE
from treetraits.service.config import ServiceConfig
from treetraits.service.outputs import OutputError, RunWriter
from treetraits.service.survey import make_processor
from treetraits.sim.run import SurveySettings


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    # Two trees, 3 m driven, camera frames included: a real recording in a few seconds.
    return twin_survey(SurveySettings(columns=2, rows=1, goal=3.0, seed=0))


# 130, or killed by SIGINT (-2 to Popen; a shell shows 130 too): CPython ends itself with
# SIGINT when the interrupt landed in code an extension ran (Open3D's start-up), even if
# main() handled it.
INTERRUPTED_STATUS = (EXIT_INTERRUPTED, -signal.SIGINT)


def _ctrl_c_as_in_a_terminal() -> None:
    """The child starts with SIGINT at its default, as a command typed in a terminal does:
    a suite run as a background job (`make test &`, a CI runner) hands its children
    SIGINT ignored, and the command then rightly leaves Ctrl-C alone."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(argv: list[str]) -> subprocess.Popen:
    """`python -m treetraits ARGV` in a child, its output captured."""
    return subprocess.Popen(
        [sys.executable, "-m", "treetraits", *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_ctrl_c_as_in_a_terminal,
    )


def one_line(capsys) -> str:
    err = capsys.readouterr().err
    assert err.startswith("treetraits: error: ") and err.count("\n") == 1, err
    assert "Traceback" not in err
    return err


def test_an_output_the_system_refuses_is_one_line_exit_6(survey, tmp_path, capsys):
    """Paths that fail even for root: a file where a directory should be, /proc."""
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    rec_path = str(survey.recording)
    cases = [
        (["replay", rec_path, "--out", str(a_file / "out")], str(a_file / "out")),
        (["replay", rec_path, "--out", "/proc/treetraits-test/out"], "/proc/treetraits-test"),
        (["sim", "--goal", "1", "--out", "/proc/treetraits-test.mcap"], "/proc/"),
        (["lidar", "export", rec_path, "--out", str(a_file / "x")], str(a_file / "x")),
        # Through the boundary itself (camera grab reports the OSError as it comes).
        (["camera", "grab", rec_path, "--out", "/proc/treetraits-test"], "/proc/treetraits"),
    ]
    for argv, named in cases:
        capsys.readouterr()
        assert main(argv) == EXIT_IO, argv
        assert named in one_line(capsys), argv


def test_bad_inputs_are_one_line_naming_the_file_exit_2(survey, tmp_path, capsys):
    deep_json = tmp_path / "deep.json"
    deep_json.write_text("[" * 100_000 + "]" * 100_000)
    deep_toml = tmp_path / "deep.toml"
    deep_toml.write_text("a = " + "[" * 5000 + "]" * 5000)
    # A recording whose attached field map is not UTF-8 (a damaged attachment).
    broken = tmp_path / "broken_attachment.mcap"
    with rec.RecordingWriter(broken, calibration={}) as writer:
        writer.attach(rec.FIELD_MAP_NAME, b'{"type": "\xff\xfe', rec.FIELD_MAP_MEDIA_TYPE)
    # One whose attached field map is nested 100 000 deep (the explicit depth limit).
    deep_attached = tmp_path / "deep_attachment.mcap"
    with rec.RecordingWriter(deep_attached, calibration={}) as writer:
        writer.attach(rec.FIELD_MAP_NAME, deep_json.read_bytes(), rec.FIELD_MAP_MEDIA_TYPE)
    replay = ["replay", str(survey.recording), "--out", str(tmp_path / "out")]
    cases = [
        ([*replay, "--calibration", str(tmp_path)], f"{tmp_path}: cannot read the calibration"),
        ([*replay, "--calibration", str(deep_json)], "deep.json: JSON nested 33+ levels deep"),
        ([*replay, "--field-map", str(deep_json)], "deep.json: JSON nested 33+ levels deep"),
        (["replay", str(deep_attached), "--out", str(tmp_path / "out")], "map): JSON nested 33+"),
        ([*replay, "--config", str(deep_toml)], "deep.toml: TOML nested too deeply"),
        (["replay", str(broken), "--out", str(tmp_path / "out")], "attached field map): not UTF-8"),
    ]
    for argv, named in cases:
        capsys.readouterr()
        assert main(argv) == EXIT_USAGE, argv
        assert named in one_line(capsys), argv
    assert not (tmp_path / "out").exists()  # refused before the output was made


def _signal_mid_replay(replay: subprocess.Popen, out: Path, signum: int) -> None:
    """Send `signum` once the replay has committed trees to its staged store (it is then
    inside its loop, with scans still to read: the survey takes seconds to replay)."""
    deadline = time.monotonic() + 120
    while replay.poll() is None:
        assert time.monotonic() < deadline
        stores = list(out.glob(".treetraits.staging-*/traits.sqlite"))
        if stores and _stored_trees(stores[0]):
            break
        time.sleep(0.02)
    replay.send_signal(signum)


def _stored_trees(store: Path) -> int:
    try:
        with contextlib.closing(sqlite3.connect(f"file:{store}?mode=ro", uri=True)) as db:
            return db.execute("SELECT COUNT(*) FROM trees WHERE status = 'found'").fetchone()[0]
    except sqlite3.Error:  # being created
        return 0


def _facts(store: Path) -> dict[str, str]:
    with contextlib.closing(sqlite3.connect(store)) as db:
        assert db.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        return dict(db.execute("SELECT key, value FROM run"))


def assert_csv_is_the_store(run: Path) -> None:
    """Every trees.csv row is a row of the store's trees table and the other way round:
    the same ids, statuses and observation counts, the traits to the CSV's decimals."""
    with contextlib.closing(sqlite3.connect(run / "traits.sqlite")) as db:
        stored = db.execute(
            "SELECT tree_id, status, observations, width_m, height_m, ndvi FROM trees"
        ).fetchall()
    with open(run / "trees.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    key = {"found": lambda r: r["tree_id"], "missing": lambda r: f"missing:{r['field_id']}"}
    in_csv = {key[r["status"]](r): r for r in rows}
    assert len(in_csv) == len(rows) > 0
    assert sorted(in_csv) == sorted(t[0] for t in stored)
    for tree_id, status, observations, width, height, ndvi in stored:
        row = in_csv[tree_id]
        assert row["status"] == status and int(row["observations"]) == observations
        for name, value, decimals in (
            ("width_m", width, 3),
            ("height_m", height, 3),
            ("ndvi", ndvi, 4),
        ):
            if value is None:
                assert row[name] == "", (tree_id, name)
            else:
                assert abs(float(row[name]) - value) <= 0.51 * 10**-decimals, (tree_id, name)


def test_ctrl_c_in_a_replay_keeps_what_was_mapped_marked_interrupted(survey, tmp_path):
    """Issue 14, case 8: SIGINT mid-replay into a new output. The scans read so far are
    finished, committed and exported; the store says the run was interrupted, trees.csv
    holds the store's trees, the exit status is 130 and one line says where it all is."""
    complete = tmp_path / "complete"
    assert main(["replay", str(survey.recording), "--out", str(complete)]) == 0
    out = tmp_path / "out"
    replay = _start(["replay", str(survey.recording), "--out", str(out)])
    _signal_mid_replay(replay, out, signal.SIGINT)
    _, err = replay.communicate(timeout=120)
    assert replay.returncode == EXIT_INTERRUPTED, err
    (line,) = err.strip().splitlines()
    assert line.startswith("treetraits: error: interrupted (SIGINT): the outputs of the ")
    assert f"are in {out}/, marked end = interrupted (SIGINT)" in line
    facts = _facts(out / "traits.sqlite")
    assert facts["end"] == "interrupted (SIGINT)"
    assert facts["exports"] == "level with the store"
    assert 0 < int(facts["scans"]) < int(_facts(complete / "traits.sqlite")["scans"])
    assert f"the {facts['scans']} scans replayed so far" in line
    assert _facts(complete / "traits.sqlite")["end"] == "complete"
    assert_csv_is_the_store(out)
    features = json.loads((out / "trees.geojson").read_text())["features"]
    assert len(features) == len((out / "trees.csv").read_text().splitlines()) - 1
    assert not list(out.glob(".treetraits.staging-*"))
    # What is there is a run's outputs: a replay without --force is refused (exit 4).
    assert main(["replay", str(survey.recording), "--out", str(out)]) == 4


def test_a_store_that_cannot_be_created_is_one_error_naming_it(tmp_path):
    """SQLite refuses a directory where traits.sqlite should be: an OutputError (exit 6)
    naming the file, not a bare sqlite3 error."""
    (tmp_path / "traits.sqlite").mkdir()
    processor = make_processor(ServiceConfig(), Calibration())
    with pytest.raises(OutputError, match=r"traits\.sqlite: store not created") as refused:
        RunWriter(tmp_path, processor)
    assert refused.value.exit_code == EXIT_IO


def _wait_for_library(process: subprocess.Popen, name: str, timeout_s: float = 120) -> None:
    """Until `process` has mapped a shared library whose path holds `name` (it is then
    importing the commands, inside main's error boundary), however loaded the machine."""
    deadline = time.monotonic() + timeout_s
    maps = Path(f"/proc/{process.pid}/maps")
    while name not in maps.read_text():
        assert process.poll() is None and time.monotonic() < deadline
        time.sleep(0.005)


@pytest.mark.parametrize("library", ["numpy", "_sqlite3"])
def test_ctrl_c_during_start_up_is_one_line_exit_130(survey, tmp_path, library):
    """SIGINT while the command's modules are imported: as NumPy is mapped (among the
    first) and as SQLite is (the last before the outputs are touched, ~0.25 s in on an
    idle machine, the output directory at ~0.36 s: a fixed 0.5 s after NumPy fell after
    it). The same one line, never a traceback. (A signal before Python has run any of our
    code, during the interpreter's own start, cannot be caught by it.)"""
    argv = ["replay", str(survey.recording), "--out", str(tmp_path / "out")]
    replay = _start(argv)
    _wait_for_library(replay, library)
    replay.send_signal(signal.SIGINT)
    _, err = replay.communicate(timeout=120)
    assert replay.returncode in INTERRUPTED_STATUS, err
    assert err.strip().splitlines() == ["treetraits: error: interrupted (SIGINT)"]
    assert not list((tmp_path / "out").glob("[!.]*"))


def test_sigterm_in_a_forced_replay_keeps_the_earlier_run_and_the_interrupted_one_aside(
    survey, tmp_path
):
    """`kill` (a CI runner's timeout, a supervisor) mid-replay with --force over an earlier
    run: a partial run never replaces a complete one. The earlier outputs stay byte for
    byte; the interrupted run's are kept in OUT/interrupted-<UTC>/, marked, exit 143."""
    out = tmp_path / "out"
    assert main(["replay", str(survey.recording), "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in out.glob("[!.]*")}
    replay = _start(["replay", str(survey.recording), "--out", str(out), "--force"])
    _signal_mid_replay(replay, out, signal.SIGTERM)
    _, err = replay.communicate(timeout=120)
    assert replay.returncode == EXIT_TERMINATED, err  # 128 + SIGTERM, docs/cli.md
    (aside,) = out.glob("interrupted-*")
    (line,) = err.strip().splitlines()
    assert line.startswith("treetraits: error: interrupted (SIGTERM): the outputs of the ")
    assert f"kept aside in {aside}/ (the earlier run's outputs stay)" in line
    assert {p.name: p.read_bytes() for p in out.glob("[!.]*") if p.is_file()} == before
    assert sorted(p.name for p in aside.iterdir()) == [
        "rejected.geojson",
        "traits.sqlite",
        "trees.csv",
        "trees.geojson",
    ]
    facts = _facts(aside / "traits.sqlite")
    assert facts["end"] == "interrupted (SIGTERM)"
    assert 0 < int(facts["scans"]) < int(_facts(out / "traits.sqlite")["scans"])
    assert_csv_is_the_store(aside)
    assert not list(out.glob(".treetraits.staging-*"))
    # The next forced replay replaces the earlier run and leaves the interrupted one.
    assert main(["replay", str(survey.recording), "--out", str(out), "--force"]) == 0
    assert list(out.glob("interrupted-*")) == [aside]


def test_a_sqlite_error_is_one_line_exit_6(monkeypatch, capsys):
    """The boundary names sqlite3.Error without importing SQLite at every start: a command
    that used SQLite and failed in it still ends in one line, exit 6."""
    import argparse
    import sqlite3

    import treetraits.cli as cli

    def fails(args):
        sqlite3.connect(":memory:").execute("select * from no_such_table")

    parser = argparse.ArgumentParser()
    parser.set_defaults(run=fails)
    monkeypatch.setattr(cli, "build_parser", lambda: parser)
    assert main([]) == EXIT_IO
    assert "SQLite: no such table: no_such_table" in one_line(capsys)


# --- issue 14 ("never lose, mix or hide a result"): a disk full while the store is
# created, a deeply nested calibration through `run`, an output onto its own input, an
# immutable output directory ----------------------------------------------------------

TIMEOUT_S = 300  # a replay's imports and work on a loaded 2-core machine


def _treetraits(argv: list[str], preexec_fn=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "treetraits", *argv],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=TIMEOUT_S,
        preexec_fn=preexec_fn,
    )


def _disk_of_20_kb() -> None:
    """RLIMIT_FSIZE stands in for a full disk: a write past it fails (EFBIG) as a write to
    a full disk does (ENOSPC), with SIGXFSZ ignored."""
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))


def test_a_disk_full_while_the_store_is_created_is_one_line_exit_6(survey, tmp_path):
    out = tmp_path / "out"
    result = _treetraits(["replay", str(survey.recording), "--out", str(out)], _disk_of_20_kb)
    assert result.returncode == EXIT_IO, result.stderr
    (line,) = result.stderr.strip().splitlines()
    assert line.startswith("treetraits: error: ") and "traits.sqlite: store not created" in line
    # Nothing half-written is left: no outputs, no staging directory.
    assert [p.name for p in out.iterdir()] == [".treetraits.lock"]


def test_a_deeply_nested_calibration_through_run_is_one_line_exit_2(tmp_path):
    """The issue's RecursionError "also through `run`": now the depth limit's message,
    naming the config key and the file, before any device is opened."""
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    config = tmp_path / "config.toml"
    config.write_text(
        f'[output]\ndir = "{tmp_path / "out"}"\n[pipeline]\ncalibration = "{deep}"\n'
        "[lidar]\nenabled = false\n[camera]\nenabled = false\n[wheels]\nenabled = false\n"
    )
    result = _treetraits(["run", "--config", str(config)])
    assert result.returncode == 2, result.stderr
    (line,) = [x for x in result.stderr.splitlines() if x.startswith("treetraits: error")]
    assert f"pipeline.calibration: {deep}: JSON nested 33+ levels deep" in line
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out").exists()


def test_lidar_export_onto_its_own_input_is_refused_and_keeps_it(tmp_path, capsys):
    """`lidar export X.pcap --out X.pcap` was a traceback; now one line (exit 2), and the
    capture is untouched."""
    capture = tmp_path / "X.pcap"
    capture.write_bytes((VLP16_DIR / "lidarutils_vlp16_strongest_0x22.pcap").read_bytes())
    before = capture.read_bytes()
    assert main(["lidar", "export", str(capture), "--out", str(capture)]) == 2
    err = capsys.readouterr().err
    assert err == f"treetraits: error: {capture}: exists and is not a directory; give a directory\n"
    assert capture.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["X.pcap"]


def test_an_immutable_output_directory_is_one_line_exit_6(survey, tmp_path, capsys):
    """`chattr +i`: refused even for root (where a read-only mode is not). Needs
    CAP_LINUX_IMMUTABLE, which a container may not grant: then nothing can be tested."""
    out = tmp_path / "immutable"
    out.mkdir()
    made = subprocess.run(["chattr", "+i", str(out)], capture_output=True, text=True)
    if made.returncode != 0:
        pytest.skip(f"chattr +i refused here: {made.stderr.strip()}")
    try:
        for target in (out, out / "sub"):
            capsys.readouterr()
            assert main(["replay", str(survey.recording), "--out", str(target)]) == EXIT_IO
            err = capsys.readouterr().err
            assert err.startswith(f"treetraits: error: {out}") and err.count("\n") == 1, err
            assert "Operation not permitted" in err
        assert list(out.iterdir()) == []
    finally:
        subprocess.run(["chattr", "-i", str(out)], check=True)
