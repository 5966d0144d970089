"""Cases of issue 14 ("never lose, mix or hide a result") not covered by the tests of the
part they touch: a disk full while the store is created, a deeply nested calibration
through `run`, and a recording written by the live recorder (`run --record`) read back
cut short. (The others: test_outdir, test_replay_damage, test_cli_errors,
test_calibration, test_sim_clutter, test_service_start, test_service_process,
test_loaders_fuzz.)"""

from __future__ import annotations

import json
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.conftest import VLP16_DIR
from treetraits.cli import main
from treetraits.drivers import recording as rec
from treetraits.drivers.recording.rotation import RotatingRecorder
from treetraits.errors import EXIT_DATA_LOSS, EXIT_IO
from treetraits.sim.run import SurveySettings, simulate_survey

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 300  # a replay's imports and work on a loaded 2-core machine


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    out = tmp_path_factory.mktemp("issue14") / "survey.mcap"
    return simulate_survey(out, SurveySettings(columns=2, rows=1, goal=3.0, seed=0))


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


def test_a_live_recording_cut_short_replays_with_data_loss_and_its_field_map(
    survey, tmp_path, capsys
):
    """`run --record` writes through `RotatingRecorder`, which attaches the field map at
    the start of each file: cut at 60 %, the file replays with exit 3 ("completed with
    data loss"), says it is cut, and still matches its trees to the map."""
    live = tmp_path / "live.mcap"
    with rec.read_recording(survey.recording) as source:
        calibration = source.metadata.calibration
        recorder = RotatingRecorder(
            live,
            max_bytes=1 << 30,
            chunk_bytes=256 * 1024,
            fsync_every_s=1.0,
            calibration=calibration,
            field_map=survey.field_map.read_bytes(),
        )
        with recorder:
            for m in source:
                recorder.write(m.topic, m.data, m.log_time, m.publish_time)
    data = live.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])

    capsys.readouterr()
    status = main(["replay", str(cut), "--out", str(tmp_path / "out"), "--json"])
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    assert status == EXIT_DATA_LOSS
    assert summary["truncated"] is True and summary["data_loss"] is True
    assert summary["field_map"]["source"] == "attachment" and summary["matched"] >= 1
    assert "the file is cut short" in captured.err and "no field map" not in captured.err


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
