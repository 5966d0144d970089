"""`treetraits lidar info` and the decoder against each real capture's reference facts.

The facts (`*.reference.json`) were read from the bytes and from velodyne_decoder 3.0.0
when the fixtures were collected; nothing here is computed by the code under test.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.helpers.captures import VLP16_CAPTURES, VLP16_DIR, decode_file, reference
from treetraits.cli import main
from treetraits.drivers.velodyne import models as m


def lidar_info(path, capsys) -> dict:
    assert main(["lidar", "info", str(path), "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.parametrize("name", VLP16_CAPTURES)
def test_lidar_info_agrees_with_reference(name, capsys):
    ref = reference(name)
    raw, cut0 = ref["raw"], ref["velodyne_decoder"]["cut_angle_0"]
    info = lidar_info(VLP16_DIR / name, capsys)

    assert info["data_packets"] == raw["data_packets"]
    assert info["position_packets"] == raw["position_packets"]
    assert info["malformed"] == 0
    assert info["lost"] == 0
    assert info["scans"] == cut0["scans_emitted"]
    assert info["full_scans"] == cut0["full_scans"]
    assert info["points_per_full_scan_median"] == cut0["points_per_full_scan_median"]
    assert info["points_total"] == cut0["total_points_all_scans"]
    assert info["points_total"] + info["duplicate_returns"] == raw["nonzero_returns_total"]
    assert info["rings_present"] == cut0["all_points_stats"]["rings_present"]
    mode_byte = int(next(iter(raw["factory_bytes"])).split("/")[0], 16)
    assert info["return_mode"] == m.RETURN_MODE_NAMES[mode_byte]
    assert info["model"] == "VLP-16"  # 0x21 (early firmware) included: told apart by timing
    assert info["rpm"] == pytest.approx(raw["rpm_estimate"], abs=0.5)
    # duration_s runs from the first to the last firing: the ToH span plus the last
    # packet's own firing time (at most one packet period).
    period_s = m.packet_period_ns(mode_byte) / 1e9
    assert raw["toh_span_s"] <= info["duration_s"] <= raw["toh_span_s"] + period_s


@pytest.mark.parametrize("name", VLP16_CAPTURES)
def test_point_counts_per_scan_and_return_types(name):
    cut0 = reference(name)["velodyne_decoder"]["cut_angle_0"]
    scans, _ = decode_file(VLP16_DIR / name)
    assert [len(s.distinct) for s in scans] == cut0["points_per_scan_all"]

    points = np.concatenate([s.points for s in scans])
    distinct = points[points["duplicate"] == 0]
    # velodyne_decoder: 1 strongest, 2 last, 3 both (one echo seen by both blocks).
    counts = {int(k): v for k, v in cut0["all_points_stats"]["return_type_counts"].items()}
    if scans[0].return_mode == "dual":
        assert int(points["duplicate"].sum()) == counts[3]
        assert int((distinct["return_type"] == m.RETURN_TYPE_LAST).sum()) == counts[2] + counts[3]
        assert int((distinct["return_type"] == m.RETURN_TYPE_STRONGEST).sum()) == counts[1]
    else:
        assert not points["duplicate"].any()
        assert int((points["return_type"] == m.RETURN_TYPE_STRONGEST).sum()) == counts[1]
    intensity_range = [int(distinct["intensity"].min()), int(distinct["intensity"].max())]
    assert intensity_range == cut0["all_points_stats"]["intensity_range"]


def _last_packet_time(scan) -> int:
    """Device time of the scan's last packet (velodyne_decoder's scan stamp)."""
    last_firing = (
        m.packet_period_ns(m.RETURN_DUAL if scan.return_mode == "dual" else m.RETURN_STRONGEST)
        - m.SEQUENCE_NS
        + 15 * m.LASER_SLOT_NS
    )
    return scan.t_end - last_firing


@pytest.mark.parametrize("name", VLP16_CAPTURES)
def test_golden_points(name):
    """The first 4 and last 2 points of the first full scan (or, in a capture shorter
    than two rotations, of the first scan) as velodyne_decoder gave them."""
    cut0 = reference(name)["velodyne_decoder"]["cut_angle_0"]
    scans, _ = decode_file(VLP16_DIR / name)
    scan = scans[1] if cut0["golden_points_source"] == "first full scan" else scans[0]
    first_full = scan.distinct
    t_rel = (first_full["t"] - _last_packet_time(scan)) / 1e9
    golden = cut0["golden_first_points"] + cut0["golden_last_points"]
    for point in golden:
        # Match by firing (time, ring): order within a dual-return firing is the peer's own.
        same_firing = (first_full["ring"] == point["ring"]) & (
            np.abs(t_rel - point["time"]) <= 1e-5 + 1e-9
        )
        candidates = first_full[same_firing]
        assert len(candidates) >= 1, point
        error = np.max(
            np.abs(
                np.stack(
                    [
                        candidates["x"] - point["x"],
                        candidates["y"] - point["y"],
                        candidates["z"] - point["z"],
                    ]
                )
            ),
            axis=0,
        )
        best = candidates[np.argmin(error)]
        assert error.min() <= 0.005, (point, best)
        assert best["intensity"] == point["intensity"]


def test_console_script_prints_json_for_a_capture():
    name = "lidarutils_vlp16_strongest_0x21_with_position.pcap"
    result = subprocess.run(
        [sys.executable, "-m", "treetraits", "lidar", "info", str(VLP16_DIR / name), "--json"],
        capture_output=True,
        text=True,
        check=True,
    )
    info = json.loads(result.stdout)
    assert info["data_packets"] == 84 and info["position_packets"] == 16
    assert info["pps_status"] == {"absent": 16}


def test_hdl32e_capture_is_refused_not_decoded_as_vlp16(capsys):
    """Byte 0x21 with HDL-32E timing (553 us) must not become plausible-looking garbage."""
    info = lidar_info(VLP16_DIR / "secondary" / "hdl32e_monterey_gprmc_short.pcap", capsys)
    facts = json.loads(
        (VLP16_DIR / "secondary" / "hdl32e_monterey_gprmc_short.pcap.reference.json").read_text()
    )
    assert info["scans"] == 0
    assert info["unsupported_model"] == facts["data_packets"]
    assert info["position_packets"] == facts["position_packets"]
    sentence = facts["position_nmea_distinct"][0].strip()
    assert info["nmea_sentences"] == {sentence: facts["position_packets"]}
