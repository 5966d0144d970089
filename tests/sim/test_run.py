"""A simulated survey end to end: every channel of the recording decodes through the real
drivers, and the pose fused from its GNSS and wheel bytes follows the true path."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest

from tests.helpers.paths import FIXTURES
from tests.helpers.surveys import twin_survey
from treetraits.cli import main
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import load_calibration
from treetraits.drivers.gnss.epochs import EpochAssembler
from treetraits.drivers.gnss.sentences import decode
from treetraits.drivers.gnss.sources import open_gnss_source
from treetraits.drivers.gnss.summary import summarise
from treetraits.drivers.records import Scan, WheelSample
from treetraits.drivers.velodyne.reader import LidarReader
from treetraits.drivers.velodyne.sources import open_source
from treetraits.firmware_bridge.jackal.session import decode_stream
from treetraits.pipeline.localization import LocalizationConfig, Localizer
from treetraits.service.config import ServiceConfig
from treetraits.service.replay import open_input
from treetraits.service.survey import make_processor
from treetraits.sim.gnss import GnssSettings
from treetraits.sim.lidar import LidarSettings
from treetraits.sim.paths import drive, waypoints
from treetraits.sim.run import (
    DEFAULT_CALIBRATION,
    LATENCY_NS,
    START_UTC,
    SurveySettings,
    placement,
)

SETTINGS = SurveySettings(
    path="straight", goal=8.0, seed=5, gnss=dataclasses.replace(GnssSettings(), dual_antenna=True)
)


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    return twin_survey(SETTINGS)


def test_every_channel_is_there_at_its_rate(survey):
    seconds = survey.duration_s
    assert seconds == pytest.approx(16.0, abs=0.5)
    assert survey.counts[rec.LIDAR_PACKETS] == pytest.approx(754 * seconds, rel=0.01)
    assert survey.counts[rec.CAMERA_JPEG] == pytest.approx(10 * seconds, abs=1)
    assert survey.counts[rec.WHEELS_JACKAL] == pytest.approx(50 * seconds, abs=2)
    # GGA + RMC + GST + HDT at 10 Hz.
    assert survey.counts[rec.GNSS_NMEA] == pytest.approx(40 * seconds, abs=4)


def test_lidar_decodes_without_loss_at_10_hz(survey):
    reader = LidarReader(open_source(survey.recording))
    scans = [s for s in reader if isinstance(s, Scan)]
    assert reader.batcher.stats.lost == 0 and reader.batcher.stats.malformed == 0
    assert len(scans) == pytest.approx(10 * survey.duration_s, abs=2)
    assert all(s.model == "VLP-16" for s in scans)


def test_truth_and_field_map_beside_the_recording(survey):
    with open(survey.truth_csv) as f:
        rows = list(csv.DictReader(f))
    assert [r["row"] for r in rows] == ["front", "middle", "back"] * 2
    assert all(2.5 < float(r["width_m"]) < 3.0 and 2.4 < float(r["height_m"]) < 3.0 for r in rows)
    field_map = json.loads(survey.field_map.read_text())
    assert [f["properties"]["id"] for f in field_map["features"]] == [r["tree_id"] for r in rows]
    with rec.read_recording(survey.recording) as recording:
        assert recording.metadata.format_version == "1"
        assert "camera" in recording.metadata.calibration
        assert json.loads(recording.attachments[rec.FIELD_MAP_NAME].data) == field_map


def fused_pose_errors(survey, settings: SurveySettings) -> list[float]:
    """The recording's GNSS and wheel bytes through the real decoders and the localiser:
    the distance of the fused pose from the true path, every 0.5 s from 2 s on."""
    source = open_gnss_source(survey.recording)
    assembler = EpochAssembler()
    fixes = []
    for sentence in source:
        record = decode(sentence)
        if record is not None and (fix := assembler.push(record)) is not None:
            fixes.append(fix)
    if (fix := assembler.flush()) is not None:
        fixes.append(fix)
    with rec.read_recording(survey.recording, topics=[rec.WHEELS_JACKAL]) as recording:
        chunks = [(m.log_time, m.data) for m in recording]
    wheels = [r for r in decode_stream(chunks) if isinstance(r, WheelSample)]
    assert len(wheels) == pytest.approx(50 * survey.duration_s, abs=2)
    assert all(f.quality == 4 for f in fixes)
    assert all((f.heading_deg is not None) == settings.gnss.dual_antenna for f in fixes)

    with rec.read_recording(survey.recording, topics=[]) as recording:
        calibration = recording.metadata.calibration
    t_base_gnss = np.asarray(calibration["T_base_gnss"]).reshape(4, 4)
    localizer = Localizer(LocalizationConfig(history_s=1e4), T_base_gnss=t_base_gnss)
    events = sorted([*fixes, *wheels], key=lambda e: e.t_host)
    for event in events:
        if isinstance(event, WheelSample):
            localizer.add_wheels(event)
        else:
            localizer.add_fix(event)
    truth = drive(waypoints(settings.path, settings.width, settings.length, settings.goal))
    place = placement(settings)
    t0 = wheels[0].t_host - 2_000_000  # the wheels' latency in the twin
    errors = []
    for t, x, y, _yaw in truth[200::50]:
        pose = localizer.pose_at(t0 + int(t * 1e9))
        if pose is not None:
            easting, northing = place.utm(x, y)
            errors.append(math.hypot(pose.x - easting, pose.y - northing))
    return errors


def test_gnss_and_wheels_fuse_back_onto_the_true_path(survey):
    errors = fused_pose_errors(survey, SETTINGS)
    assert len(errors) > 20
    assert max(errors) < 0.1  # RTK (2 cm) with the lever arm removed


@pytest.mark.parametrize(
    "path, field_heading_deg, antenna, dual_antenna",
    [
        ("straight", 112.0, (1.0, 0.5, 0.6), True),
        ("s", 112.0, (-1.0, -0.8, 0.6), True),  # the S path starts with a turn
        ("s", -150.0, (0.0, 0.0, 0.6), False),
        ("straight", 35.0, (-0.6, 1.0, 0.4), False),
    ],
)
def test_a_turned_field_and_any_lever_arm_leave_no_offset(
    tmp_path, path, field_heading_deg, antenna, dual_antenna
):
    """A block planted at any bearing, the antenna anywhere on the robot, a start straight
    or turning, with or without a true heading: the pose follows the true path. (An error
    in the lever arm's sign, the grid convergence or the heading convention shows here as
    an offset that a field aligned with east hides.)"""
    settings = SurveySettings(
        path=path,
        goal=7.0,
        seed=7,
        field_heading_deg=field_heading_deg,
        antenna=antenna,
        gnss=dataclasses.replace(GnssSettings(), dual_antenna=dual_antenna),
        # The pose is the GNSS's and the wheels': a drive without LiDAR and camera.
        lidar=dataclasses.replace(LidarSettings(), enabled=False),
        camera_rate_hz=0.0,
    )
    survey = twin_survey(settings)
    assert not survey.counts.get(rec.LIDAR_PACKETS) and not survey.counts.get(rec.CAMERA_JPEG)
    errors = fused_pose_errors(survey, settings)
    assert len(errors) >= 20
    # Measured: medians 2-3 cm, at most 5 cm, with and without a true heading (without
    # one, course over ground sets it in the first metres).
    assert np.median(errors) < 0.05
    assert max(errors) < 0.1


def test_the_command_line_writes_a_survey(tmp_path, capsys):
    out = tmp_path / "cli.mcap"
    assert (
        main(
            [
                "sim",
                "--grid",
                "4x4",
                "--goal",
                "2",
                "--gnss",
                "float",
                "--outage",
                "0.5:1.0",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert out.exists() and out.with_suffix(".truth.csv").exists()
    assert "wrote" in capsys.readouterr().out
    assert main(["sim", "--grid", "4", "--out", str(out)]) == 2


def test_the_lidar_raised_in_the_recordings_calibration(tmp_path, capsys):
    """`--lidar-height`: the recording's calibration carries the LiDAR that high above
    base_link, the rest of the mount as the calibration has it; out of 0.2-5 m refused."""
    out = tmp_path / "high.mcap"
    argv = ["sim", "--goal", "1", "--lidar-height", "2.6", "--out", str(out)]
    assert main(argv) == 0
    with rec.read_recording(out, topics=[]) as recording:
        written = recording.metadata.calibration
    mount = np.asarray(written["T_base_lidar"]).reshape(4, 4)
    default = load_calibration(DEFAULT_CALIBRATION)
    assert mount[2, 3] == 2.6
    assert np.array_equal(mount[:2], default.T_base_lidar[:2])
    assert np.array_equal(mount[3], default.T_base_lidar[3])
    camera = np.asarray(written["T_camera_lidar"]).reshape(4, 4)
    assert np.array_equal(camera, default.T_camera_lidar)
    capsys.readouterr()
    assert main(["sim", "--lidar-height", "7", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "--lidar-height must be a finite number in [0.2, 5]" in capsys.readouterr().err


def test_nmea_info_measures_the_receivers_latency_in_a_recording(survey):
    """The twin's receiver sends each epoch 60 ms after its UTC (LATENCY_NS); a recording
    keeps the receive times, so `nmea info` measures it. A log file read now has none."""
    facts = summarise(open_gnss_source(survey.recording))
    assert facts["latency_ms"] == pytest.approx(LATENCY_NS["gnss"] / 1e6, abs=1.0)
    log = FIXTURES / "nmea" / "ublox-zed-f9p-nmea.nmea"
    assert summarise(open_gnss_source(log))["latency_ms"] is None


def test_a_gps_locked_lidar_puts_the_fixes_on_a_host_clock_off_utc(tmp_path):
    """A robot whose host clock is 20 s off UTC (no NTP in the field) and a VLP-16 with the
    receiver on its GPS input: the position packets measure the host clock's offset, so
    every fix lands at its epoch on the host clock (the receiver's 60 ms latency measured,
    not assumed) and the poses follow the true path at host times. The same bytes without
    the position packets fall back on the configured latency."""
    host_ahead_s = 20.0
    settings = SurveySettings(
        goal=7.0,
        seed=3,
        host_clock_offset_s=host_ahead_s,
        lidar=dataclasses.replace(LidarSettings(), gps_sync=True),
    )
    survey = twin_survey(settings)
    assert survey.counts[rec.LIDAR_TELEMETRY] == pytest.approx(
        survey.counts[rec.LIDAR_PACKETS] / 14, abs=1
    )

    def processed(with_telemetry: bool):
        source = open_input(survey.recording, None, 0.0, 0.05)
        processor = make_processor(ServiceConfig(), load_calibration(source.calibration))
        for topic, data, log_time, publish_time in source.messages:
            if with_telemetry or topic != rec.LIDAR_TELEMETRY:
                processor.feed(topic, data, log_time, publish_time)
        processor.finish()
        return processor

    locked = processed(with_telemetry=True)
    clock = locked.lidar_clock.stats
    assert clock.telemetry_unlocked == 0 and clock.telemetry_locked > 100
    assert clock.scans_on_utc == locked.stats.scans + locked.stats.scans_skipped
    # The offset is the host's 20 s plus the LiDAR's 0.3 ms transport.
    assert clock.host_minus_utc_ms == pytest.approx(host_ahead_s * 1e3, abs=0.5)
    assert locked.localizer.stats.latency_ms == pytest.approx(LATENCY_NS["gnss"] / 1e6, abs=0.5)
    place = placement(settings)
    truth = drive(waypoints(settings.path, settings.width, settings.length, settings.goal))
    t0_host = START_UTC.timestamp() * 1e9 + host_ahead_s * 1e9
    errors = []
    for t, x, y, _yaw in truth[200::50]:
        pose = locked.localizer.pose_at(int(t0_host + t * 1e9))
        if pose is not None:
            errors.append(math.hypot(pose.x - place.utm(x, y)[0], pose.y - place.utm(x, y)[1]))
    assert len(errors) > 15 and max(errors) < 0.05

    unlocked = processed(with_telemetry=False)
    assert unlocked.lidar_clock.stats.scans_on_utc == 0
    assert unlocked.localizer.stats.latency_ms is None  # 20 s off: the host is not on UTC
