"""The service's config file: defaults, validation naming the key, round trip through
`config dump`, and the installed default file."""

from __future__ import annotations

import argparse
from pathlib import Path

import pytest

from tests.helpers.paths import REPO
from treetraits.cli import config as config_cli
from treetraits.errors import ConfigError
from treetraits.pipeline.config import CropConfig
from treetraits.service.config import (
    OutputConfig,
    ServiceConfig,
    dump_config,
    field_help,
    load_config,
    parse_config,
    tomllib,
    with_overrides,
)


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.toml"
    path.write_text(text)
    return path


def test_defaults_are_the_contract():
    cfg = load_config(None)
    assert cfg.output.dir == "/var/lib/treetraits" and cfg.output.export_every_s == 5.0
    assert (cfg.lidar.data_port, cfg.lidar.telemetry_port) == (2368, 8308)
    assert cfg.lidar.rcvbuf_bytes == 8388608 and cfg.lidar.silence_s == 1.0
    assert cfg.wheels.kind == "jackal" and cfg.wheels.port == "/dev/jackal"
    assert cfg.record.enabled is False and cfg.record.chunk_kb == 512
    assert cfg.queues.lidar_packets == 8000 and cfg.queues.camera_frames == 16
    assert cfg.service.status_every_s == 2.0 and cfg.service.log_level == "info"


def test_installed_default_file_holds_every_key_with_its_default():
    path = REPO / "systemd" / "config.toml"
    assert load_config(path) == ServiceConfig()
    document = tomllib.loads(path.read_text())
    for section, content in document.items():
        assert set(content) == set(vars(getattr(ServiceConfig(), section))), section


def test_a_partial_file_keeps_the_other_defaults(tmp_path):
    cfg = load_config(write(tmp_path, "[lidar]\ndata_port = 2400\n[wheels]\nkind = 'bridge'\n"))
    assert cfg.lidar.data_port == 2400 and cfg.lidar.telemetry_port == 8308
    assert cfg.wheels.kind == "bridge" and cfg.gnss == ServiceConfig().gnss


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ("[lidar]\ndata_prot = 2368\n", "lidar.data_prot; did you mean lidar.data_port?"),
        ("[lidr]\n", "unknown section [lidr]; did you mean lidar?"),
        ("[lidar]\ndata_port = 70000\n", "lidar.data_port must be a port in 1..65535"),
        ("[lidar]\ndata_port = '2368'\n", "lidar.data_port must be an integer"),
        ("[lidar]\nenabled = 1\n", "lidar.enabled must be true or false"),
        ("[lidar]\nsensor_ip = '192.168.1.300'\n", "lidar.sensor_ip must be an IPv4 or IPv6"),
        ("[lidar]\nmodel = 'hdl64'\n", "lidar.model unknown LiDAR model"),
        ("[gnss]\nsilence_s = 0\n", "gnss.silence_s must be in [0.01, 3600]"),
        ("[gnss]\nsilence_s = 1e300\n", "gnss.silence_s must be in [0.01, 3600]"),
        ("[gnss]\nbaudrate = 1000000000\n", "gnss.baudrate must be in [50, 4000000]"),
        ("[lidar]\nrcvbuf_bytes = 4294967296\n", "lidar.rcvbuf_bytes must be in [1, 2147483647]"),
        ("[output]\nexport_every_s = 1e12\n", "output.export_every_s must be in [0.01, 3600]"),
        ("[output]\nmatch_gate_m = 5000.0\n", "output.match_gate_m must be in [0.01, 100]"),
        ("[output]\nexport_max_share = 0\n", "output.export_max_share must be in [0.001, 1]"),
        ("[record]\nmax_file_mb = 9999999999\n", "record.max_file_mb must be in [1, 1048576]"),
        ("[gnss]\nsilence_s = nan\n", "gnss.silence_s must be a finite number"),
        ("[wheels]\nkind = 'tractor'\n", "wheels.kind must be one of jackal, bridge"),
        ("[pipeline]\nmethod = 'best'\n", "pipeline.method must be one of paper, rph"),
        ("[queues]\nlidar_packets = 0\n", "queues.lidar_packets must be in [1, 1000000]"),
        ("[queues]\nwheel_chunks = 10000000000\n", "queues.wheel_chunks must be in [1, 1000000]"),
        ("[service]\nlog_level = 'loud'\n", "service.log_level must be one of"),
        ("lidar = 3\n", "lidar must be a [lidar] table"),
    ],
)
def test_a_bad_value_is_named(tmp_path, text, named):
    path = write(tmp_path, text)
    with pytest.raises(ConfigError) as error:
        load_config(path)
    assert named in str(error.value)
    assert str(path) in str(error.value)


def test_not_toml_and_missing_file_are_clear(tmp_path):
    with pytest.raises(ConfigError, match=r"not valid TOML.*line 1"):
        load_config(write(tmp_path, "[lidar\n"))
    with pytest.raises(ConfigError, match="no such config file"):
        load_config(tmp_path / "absent.toml")


def test_relative_paths_are_taken_from_the_config_directory(tmp_path):
    (tmp_path / "cam.avi").write_bytes(b"")
    cfg = load_config(
        write(
            tmp_path,
            "[output]\ndir = 'out'\n[pipeline]\ncalibration = 'cal/c.json'\n"
            "[camera]\ndevice = 'cam.avi'\n[record]\ndir = '/abs/rec'\n",
        )
    )
    assert cfg.output.dir == str(tmp_path / "out")
    assert cfg.pipeline.calibration == str(tmp_path / "cal" / "c.json")
    assert cfg.camera.device == str(tmp_path / "cam.avi")
    assert cfg.record.dir == "/abs/rec"
    assert cfg.pipeline.field_map == ""  # "" stays "none", not the directory


def test_dump_reads_back_to_an_equal_config(tmp_path):
    cfg = with_overrides(
        ServiceConfig(),
        lidar={"sensor_ip": "192.168.1.201", "telemetry_port": 0},
        camera={"device": "usb:1e10:4000"},
        output={"dir": '/srv/odd "dir"\\x', "export_every_s": 0.5},
        record={"enabled": True},
    )
    for comments in (True, False):
        text = dump_config(cfg, comments=comments)
        assert parse_config(tomllib.loads(text), base=tmp_path) == cfg


def test_a_key_s_help_is_its_own_or_its_comment_s_first_sentence():
    """One answer for `config dump`: a service key's `_key` help, else the first sentence
    of the comment above the field (cut at 110 characters), else none."""
    output = field_help(OutputConfig)
    assert output["min_observations"] == "a tree seen in fewer scans is not reported"
    assert output["export_max_share"].startswith("exports take at most this share")
    crop = field_help(CropConfig)
    assert crop["z_m"].startswith("From below any ground a 10 % slope puts within the box")
    assert crop["x_m"].endswith("...") and len(crop["x_m"]) == 110
    assert "y_m" not in crop  # its reason is x_m's
    dumped = dump_config(ServiceConfig())
    assert f"# {output['missing_range_m']}\n" in dumped and f"# {crop['z_m']}\n" in dumped


def cli(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="treetraits")
    config_cli.register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args.run(args)


def test_config_dump_and_check_commands(tmp_path, capsys):
    path = write(tmp_path, "[gnss]\nport = '/dev/ttyUSB3'\n")
    assert cli(["config", "dump", "--config", str(path)]) == 0
    printed = capsys.readouterr().out
    assert load_config(write(tmp_path, printed)).gnss.port == "/dev/ttyUSB3"
    assert 'port = "/dev/ttyUSB3"' in printed and "[queues]" in printed
    # check also sees that output.dir can be written (as run's start does).
    path = write(tmp_path, f"[gnss]\nport = '/dev/ttyUSB3'\n[output]\ndir = '{tmp_path}'\n")
    assert cli(["config", "check", str(path)]) == 0
    assert capsys.readouterr().out.splitlines()[0] == f"{path}: ok"
    with pytest.raises(ConfigError, match=r"gnss\.baudrate must be in \[50, 4000000\]"):
        cli(["config", "check", str(write(tmp_path, "[gnss]\nbaudrate = -1\n"))])
