"""The output rules of `replay`, `sim`, `lidar export` and `eval` (docs/cli.md, "Output
directories"), through the real CLI on a small twin recording: a failing run touches
nothing, an earlier run is replaced only with --force, one run at a time per output."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.captures import VLP16_DIR
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.errors import EXIT_OUTPUT_BUSY, EXIT_OUTPUT_EXISTS, EXIT_USAGE
from treetraits.service.outdir import OutputDir
from treetraits.sim.run import SurveySettings

CAPTURE = VLP16_DIR / "lidarutils_vlp16_strongest_0x22.pcap"
REPLAY_FILES = ("traits.sqlite", "trees.csv", "trees.geojson", "rejected.geojson")


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    # Two trees, 3 m driven: a real recording in a few seconds.
    return twin_survey(SurveySettings(columns=2, rows=1, goal=3.0, seed=0))


@pytest.fixture(scope="module")
def replayed(survey, tmp_path_factory) -> Path:
    """A directory holding one replay's outputs (copied by the tests that change it)."""
    out = tmp_path_factory.mktemp("replayed") / "run"
    assert main(["replay", str(survey.recording), "--out", str(out)]) == 0
    return out


def snapshot(directory: Path) -> dict[str, bytes]:
    """Every visible file's bytes (the lock file and staging directories left out)."""
    return {
        p.name: p.read_bytes()
        for p in sorted(directory.iterdir())
        if p.is_file() and not p.name.startswith(".")
    }


def copy_run(source: Path, tmp_path: Path) -> Path:
    out = tmp_path / "run"
    out.mkdir()
    for name, data in snapshot(source).items():
        (out / name).write_bytes(data)
    return out


def test_a_failing_replay_leaves_the_earlier_run_as_it_was(survey, replayed, tmp_path, capsys):
    out = copy_run(replayed, tmp_path)
    before = snapshot(out)
    assert set(REPLAY_FILES) <= set(before)
    empty = tmp_path / "empty.pcap"
    empty.write_bytes(b"")
    capture = CAPTURE
    failing = [
        # An empty capture, a typo in --nmea, the run's own store as the input: each with
        # --force, which must not matter when the input is bad.
        ["replay", str(empty), "--out", str(out), "--force"],
        [
            "replay",
            str(capture),
            "--nmea",
            str(tmp_path / "tpyo.nmea"),
            "--out",
            str(out),
            "--force",
        ],
        ["replay", str(out / "traits.sqlite"), "--out", str(out), "--force"],
    ]
    for argv in failing:
        capsys.readouterr()
        assert main(argv) == EXIT_USAGE, argv
        err = capsys.readouterr().err
        assert err.startswith("treetraits: error: ") and err.count("\n") == 1, err
        assert snapshot(out) == before, argv
        if "traits.sqlite" in argv[1]:
            assert "is one of the outputs this run writes" in err
    assert not list(out.glob(".treetraits.staging-*"))


def test_an_earlier_run_is_replaced_only_with_force(survey, replayed, tmp_path, capsys):
    out = copy_run(replayed, tmp_path)
    (out / "notes.txt").write_text("the grower's notes")
    stale_wal = out / "traits.sqlite-wal"
    stale_wal.write_bytes(b"a WAL of an earlier run")
    before = snapshot(out)

    assert main(["replay", str(survey.recording), "--out", str(out)]) == EXIT_OUTPUT_EXISTS
    err = capsys.readouterr().err
    assert "--force" in err and err.count("\n") == 1
    assert snapshot(out) == before

    (out / "trees.csv").write_text("not the replay's")
    assert main(["replay", str(survey.recording), "--out", str(out), "--force"]) == 0
    after = snapshot(out)
    assert after["notes.txt"] == b"the grower's notes"  # not owned by replay: kept
    assert not stale_wal.exists()  # owned, not written by the new run: removed
    assert after["trees.csv"] == before["trees.csv"]  # the replay's, deterministic
    assert {n for n in after if n != "notes.txt"} == set(REPLAY_FILES)


def test_the_demo_reruns_with_its_recording_inside_the_output(tmp_path):
    """`make demo`: sim into OUT/survey.mcap, replay it into OUT, twice, with --force."""
    out = tmp_path / "demo"
    recording = out / "survey.mcap"
    sim = ["sim", "--grid", "5x5", "--layout", "2x1", "--goal", "3", "--out", str(recording)]
    for _ in range(2):
        assert main([*sim, "--force"]) == 0
        assert main(["replay", str(recording), "--out", str(out), "--force"]) == 0
        assert recording.is_file() and (out / "trees.csv").is_file()
    names = set(snapshot(out))
    assert names == {
        "survey.mcap",
        "survey.truth.csv",
        "survey.objects.csv",
        "survey.field_map.geojson",
        *REPLAY_FILES,
    }


HOLD_LOCK = """
import sys, time
from pathlib import Path
from treetraits.service.outdir import output_lock
with output_lock(Path(sys.argv[1]), sys.argv[2]):
    print("locked", flush=True)
    sys.stdin.read()
"""


def hold_lock(directory: Path, name: str = ".treetraits.lock") -> subprocess.Popen:
    """Another process holding the output's lock until its stdin closes."""
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_LOCK, str(directory), name],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert holder.stdout.readline().strip() == "locked"
    return holder


def test_a_second_run_into_a_busy_output_fails_fast(survey, replayed, tmp_path, capsys):
    out = copy_run(replayed, tmp_path)
    before = snapshot(out)
    holder = hold_lock(out)
    try:
        assert (
            main(["replay", str(survey.recording), "--out", str(out), "--force"])
            == EXIT_OUTPUT_BUSY
        )
        err = capsys.readouterr().err
        assert f"another run is writing there (process {holder.pid})" in err
        assert snapshot(out) == before
        # eval takes the same lock (and only the lock: its cache in OUT/cases/ is reused).
        argv = ["eval", "--out", str(out), "--quick", "--cases", "straight-5x5"]
        assert main(argv) == EXIT_OUTPUT_BUSY
    finally:
        holder.communicate("")
    # Released when the holder ends.
    assert main(["replay", str(survey.recording), "--out", str(out), "--force"]) == 0


def test_sim_never_overwrites_a_recording_without_force(tmp_path, capsys):
    field = tmp_path / "field.mcap"
    field.write_bytes(b"a day in the field")
    argv = ["sim", "--grid", "5x5", "--layout", "2x1", "--goal", "3", "--out", str(field)]
    assert main(argv) == EXIT_OUTPUT_EXISTS
    assert "--force" in capsys.readouterr().err
    assert field.read_bytes() == b"a day in the field"
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "field.mcap"
    ]
    # A bad option is refused before the output is looked at.
    assert main([*argv, "--force", "--goal", "-1"]) == EXIT_USAGE
    assert field.read_bytes() == b"a day in the field"
    assert main([*argv, "--force"]) == 0
    assert field.read_bytes().startswith(b"\x89MCAP0\r\n")
    assert main(["sim", "--out", str(tmp_path)]) == EXIT_USAGE  # a directory


def test_lidar_export_replaces_an_earlier_export_whole(tmp_path, capsys):
    capture = str(CAPTURE)
    out = tmp_path / "export"
    assert main(["lidar", "export", capture, "--out", str(out)]) == 0
    first = snapshot(out)
    assert main(["lidar", "export", capture, "--out", str(out), "--full-only"]) == (
        EXIT_OUTPUT_EXISTS
    )
    assert snapshot(out) == first
    assert main(["lidar", "export", capture, "--out", str(out), "--full-only", "--force"]) == 0
    index = (out / "scans.csv").read_text().splitlines()[1:]
    listed = {row.split(",")[0] for row in index}
    pcds = {p.name for p in out.glob("*.pcd")}
    assert pcds == listed and len(pcds) == len(first) - 1 - 2  # no stale scan left
    capsys.readouterr()
    # Into the capture itself: one line, and the capture is untouched.
    data = Path(capture).read_bytes()
    assert main(["lidar", "export", capture, "--out", capture]) == EXIT_USAGE
    assert "is not a directory" in capsys.readouterr().err
    assert Path(capture).read_bytes() == data


def test_a_run_that_fails_midway_discards_its_staged_outputs(tmp_path):
    out = tmp_path / "out"
    with OutputDir(out, ("a.txt", "b.txt")) as staging:
        (staging / "a.txt").write_text("first")
    with pytest.raises(RuntimeError), OutputDir(out, ("a.txt", "b.txt"), force=True) as staging:
        (staging / "a.txt").write_text("second")
        (staging / "b.txt").write_text("second")
        raise RuntimeError("the run broke")
    assert snapshot(out) == {"a.txt": b"first"}
    assert sorted(p.name for p in out.iterdir()) == [".treetraits.lock", "a.txt"]


def test_a_run_kept_aside_goes_in_place_only_where_no_earlier_run_is(tmp_path):
    """`keep_aside` (an interrupted replay): into place in an empty output; beside an
    earlier run, in its own directory (readable as a directory made by the run would be),
    the earlier run untouched; a second one in the same second gets `-2`."""
    out = tmp_path / "out"
    with OutputDir(out, ("a.txt",)) as staging:
        (staging / "a.txt").write_text("partial")
    assert snapshot(out) == {"a.txt": b"partial"}
    for expected in ("interrupted-x", "interrupted-x-2"):
        output = OutputDir(out, ("a.txt",), force=True)
        with output as staging:
            (staging / "a.txt").write_text(expected)
            output.keep_aside("interrupted-x")
        assert output.placed == out / expected
        assert (out / expected / "a.txt").read_text() == expected
        assert (out / expected).stat().st_mode & 0o755 == 0o755
        assert snapshot(out) == {"a.txt": b"partial"}
    output = OutputDir(out / "empty", ("a.txt",))
    with output as staging:
        (staging / "a.txt").write_text("alone")
        output.keep_aside("interrupted-y")
    assert output.placed == out / "empty" and (out / "empty" / "a.txt").read_text() == "alone"
    assert not list(out.glob(".treetraits.staging-*"))
