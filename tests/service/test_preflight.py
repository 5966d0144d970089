"""`config check` and the start of `treetraits run` make the same checks (one function,
`service/preflight.py`), and a start that fails makes no run directory and leaves
`runs/latest` alone (issue 14, cases 7 and 8)."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.net import free_udp_port
from tests.helpers.paths import CITRUSFARM, REPO
from treetraits.cli import main

START_S = 120  # imports on a loaded 2-core machine


def write_config(folder: Path, *, lidar: str = "", pipeline: str = "", camera: str = "") -> Path:
    """Only the LiDAR on loopback (the one device a start opens for good), outputs in
    `folder/out`. The telemetry port stays closed: a fixed port would clash between tests
    running side by side."""
    default_lidar = f"data_port = {free_udp_port()}\ntelemetry_port = 0"
    text = (
        f'[output]\ndir = "{folder / "out"}"\n'
        f"[pipeline]\n{pipeline}\n"
        f'[lidar]\nbind = "127.0.0.1"\n{lidar or default_lidar}\n'
        f"[camera]\nenabled = {'true' if camera else 'false'}\n{camera}\n"
        "[gnss]\nenabled = false\n[wheels]\nenabled = false\n"
    )
    path = folder / "config.toml"
    path.write_text(text)
    return path


def calibration_without(folder: Path, key: str) -> Path:
    raw = json.loads(CITRUSFARM.read_text())
    del raw[key]
    path = folder / "calibration.json"
    path.write_text(json.dumps(raw))
    return path


def run_service(config: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "treetraits", "run", "--config", str(config)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=START_S,
    )


def error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.startswith("treetraits: error: ")]
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    return lines[0]


# Each a config `run` refuses at start; `config check` used to call all of them ok.
REFUSED = {
    "equal ports": (
        {"lidar": "data_port = 2368\ntelemetry_port = 2368"},
        "lidar.telemetry_port equals lidar.data_port (2368)",
    ),
    "no calibration file": (
        {"pipeline": 'calibration = "{folder}/nope.json"'},
        "pipeline.calibration: {folder}/nope.json: no such calibration file",
    ),
    "calibration without T_base_lidar": (
        {"pipeline": 'calibration = "{calibration}"'},
        "T_base_lidar missing",
    ),
    "no field map file": (
        {"pipeline": 'field_map = "{folder}/nope.geojson"'},
        "pipeline.field_map: ",
    ),
    "a field map that is not one": (
        {"pipeline": 'field_map = "{calibration}"'},
        "pipeline.field_map: ",
    ),
    "no video file": (
        {"camera": 'device = "{folder}/nope.avi"'},
        "camera.device: {folder}/nope.avi: no such video file",
    ),
    "output.dir under a file": (
        {"pipeline": ""},
        "output.dir: {folder}/out is not a directory",
    ),
}


def _refused_config(tmp_path: Path, case: str) -> tuple[Path, str]:
    sections, message = REFUSED[case]
    calibration = calibration_without(tmp_path, "T_base_lidar")
    fill = {"folder": tmp_path, "calibration": calibration}
    config = write_config(tmp_path, **{k: v.format(**fill) for k, v in sections.items()})
    if case == "output.dir under a file":
        (tmp_path / "out").write_text("a file where the output directory should be")
    return config, message.format(**fill)


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_config_check_refuses_what_run_refuses(tmp_path, capsys, case):
    config, message = _refused_config(tmp_path, case)
    assert main(["config", "check", str(config)]) == 2
    line = error_line(capsys.readouterr().err)
    assert message in line
    assert not (tmp_path / "out" / "runs").exists()


@pytest.mark.parametrize("case", ["equal ports", "calibration without T_base_lidar"])
def test_run_refuses_it_with_the_same_line_and_makes_no_run_directory(tmp_path, capsys, case):
    config, message = _refused_config(tmp_path, case)
    assert main(["config", "check", str(config)]) == 2
    checked = error_line(capsys.readouterr().err)
    assert message in checked
    result = run_service(config)
    assert result.returncode == 2
    assert error_line(result.stderr) == checked
    assert not (tmp_path / "out").exists()


def test_config_check_says_ok_to_a_config_run_starts_with(tmp_path, capsys):
    raw = json.loads(CITRUSFARM.read_text())
    del raw["camera"], raw["T_camera_lidar"]
    (tmp_path / "calibration.json").write_text(json.dumps(raw))
    config = write_config(tmp_path, pipeline=f'calibration = "{tmp_path / "calibration.json"}"')
    assert main(["config", "check", str(config)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == f"{config}: ok"
    # The default it will take is said, not silent.
    assert "no camera (NDVI is left out)" in out[1]
    assert not (tmp_path / "out").exists()  # a check creates nothing


def test_a_start_that_fails_makes_no_run_directory_and_keeps_latest(tmp_path):
    """The LiDAR's port is taken by another program: the one check only a start can make.
    The earlier run stays `runs/latest`; no new run directory appears."""
    runs = tmp_path / "out" / "runs"
    (runs / "20260101T000000Z").mkdir(parents=True)
    (runs / "latest").symlink_to("20260101T000000Z")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        config = write_config(tmp_path, lidar=f"data_port = {port}\ntelemetry_port = 0")
        result = run_service(config)
    assert result.returncode == 2
    assert f"cannot listen on UDP 127.0.0.1:{port}" in error_line(result.stderr)
    assert sorted(p.name for p in runs.iterdir()) == ["20260101T000000Z", "latest"]
    assert (runs / "latest").readlink() == Path("20260101T000000Z")


def test_a_directory_this_user_may_not_write_is_a_note_for_check_an_error_for_run(
    tmp_path, monkeypatch
):
    """`config check` run by an admin for a service with its own user: the OS's answer
    to "may I write here" is for the admin. Root may write anywhere, so that answer is
    stood in for (the one mock: another user cannot exist on every test machine)."""
    from treetraits.errors import ConfigError
    from treetraits.service import preflight
    from treetraits.service.config import load_config

    config = load_config(write_config(tmp_path))
    monkeypatch.setattr(preflight.os, "access", lambda path, mode: False)
    checked = preflight.check_start(config, as_service=False)
    assert checked.notes == (
        f"output.dir: {tmp_path} is not writable (making {tmp_path / 'out'}) by this user "
        "(the service's user may differ)",
    )
    with pytest.raises(ConfigError, match=rf"output\.dir: {tmp_path} is not writable"):
        preflight.check_start(config)
