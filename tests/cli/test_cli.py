"""The `treetraits` command line as a user runs it: help, export, listen, errors."""

from __future__ import annotations

import csv
import json
import socket
import subprocess
import sys
import time

import numpy as np
import open3d as o3d
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file, reference
from tests.helpers.net import free_udp_port
from treetraits.drivers.velodyne.sources import open_source

CLI = [sys.executable, "-m", "treetraits"]


def run(*args: str, **kwargs) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True, **kwargs)


@pytest.mark.parametrize(
    "command",
    [[], ["lidar"], ["lidar", "info"], ["lidar", "export"], ["lidar", "listen"]],
)
def test_every_command_has_help(command):
    result = run(*command, "--help")
    assert result.returncode == 0
    assert result.stdout.startswith("usage: treetraits")
    assert "--help" in result.stdout


def test_bad_input_is_one_clear_line_not_a_traceback(tmp_path):
    missing = run("lidar", "info", str(tmp_path / "nope.pcap"))
    assert missing.returncode == 2
    assert "no such file" in missing.stderr and "Traceback" not in missing.stderr

    text = tmp_path / "notes.txt"
    text.write_text("not a capture\n")
    garbage = run("lidar", "info", str(text))
    assert garbage.returncode == 2 and "not a pcap" in garbage.stderr

    model = run(
        "lidar", "info", str(VLP16_DIR / "lidarutils_vlp16_strongest_0x22.pcap"), "--model", "hdl64"
    )
    assert model.returncode == 2 and "unknown LiDAR model" in model.stderr


def test_export_writes_pcd_files_that_open3d_reads_back(tmp_path):
    name = "nebula_vlp16_dual_10hz.pcap"
    out = tmp_path / "scans"
    result = run("lidar", "export", str(VLP16_DIR / name), "--out", str(out))
    assert result.returncode == 0, result.stderr

    scans, _ = decode_file(VLP16_DIR / name)
    files = sorted(out.glob("scan_*.pcd"))
    assert len(files) == reference(name)["velodyne_decoder"]["cut_angle_0"]["scans_emitted"]
    with open(out / "scans.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["points"]) for r in rows] == [len(s.points) for s in scans]

    cloud = o3d.t.io.read_point_cloud(str(files[1]))
    expected = scans[1].points
    positions = cloud.point.positions.numpy()
    np.testing.assert_array_equal(positions[:, 0], expected["x"])
    np.testing.assert_array_equal(positions[:, 2], expected["z"])
    np.testing.assert_array_equal(cloud.point.ring.numpy().ravel(), expected["ring"])
    np.testing.assert_array_equal(cloud.point.intensity.numpy().ravel(), expected["intensity"])
    np.testing.assert_allclose(cloud.point.t.numpy().ravel(), expected["t"] / 1e9, atol=1e-6)


def test_export_full_only_drops_the_partial_ends(tmp_path):
    name = "einride_vlp16_strongest_1000pkts.bin"
    result = run("lidar", "export", str(VLP16_DIR / name), "--out", str(tmp_path), "--full-only")
    assert result.returncode == 0, result.stderr
    full = reference(name)["velodyne_decoder"]["cut_angle_0"]["full_scans"]
    assert len(list(tmp_path.glob("scan_*.pcd"))) == full


@pytest.mark.slow
def test_listen_reports_what_a_sender_sent():
    name = "lidarutils_vlp16_strongest_0x21_with_position.pcap"
    source = open_source(VLP16_DIR / name)
    packets = list(source)
    source.close()
    data_port, telemetry_port = free_udp_port(), free_udp_port()
    listener = subprocess.Popen(
        [
            *CLI,
            "lidar",
            "listen",
            "--bind",
            "127.0.0.1",
            "--port",
            str(data_port),
            "--telemetry-port",
            str(telemetry_port),
            "--seconds",
            "3",
            "--json",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        # It says so once its sockets are bound (a cold start can take seconds).
        first_line = listener.stderr.readline()
        assert first_line.startswith("listening on"), first_line
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            for packet in packets:
                port = data_port if packet.is_data else telemetry_port
                sender.sendto(packet.payload, ("127.0.0.1", port))
                time.sleep(0.0005)
        out, err = listener.communicate(timeout=15)
        err = first_line + err
    finally:
        listener.kill()
    assert listener.returncode == 0, err
    facts = json.loads(out)
    raw = reference(name)["raw"]
    assert facts["data_packets"] == raw["data_packets"]
    assert facts["position_packets"] == raw["position_packets"]
    assert facts["points_total"] == raw["nonzero_returns_total"]
    assert facts["lost"] == 0 and facts["kernel_drops"] == 0
    assert "pkt/s" in err  # the per-second report goes to stderr
