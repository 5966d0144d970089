"""pipeline/survey.py: when a scan goes through. A scan is processed as soon as its pose
and its camera frame can no longer change (not a fixed wait), and it gets exactly the
pose and frame it would get by waiting: checked against the localizer's final history and
the recording's frames, on a simulated survey."""

from __future__ import annotations

import itertools
import statistics

import numpy as np
import pytest

from tests.helpers.surveys import twin_survey
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import load_calibration
from treetraits.pipeline.projection import scan_mid_time
from treetraits.service.config import ServiceConfig
from treetraits.service.survey import POSE_WAIT_NS, make_processor
from treetraits.sim.gnss import GnssSettings
from treetraits.sim.paths import drive, riding_trajectory, waypoints
from treetraits.sim.run import DEFAULT_CALIBRATION, SurveySettings, make_ground
from treetraits.sim.wheels import JackalMcuEmulator, WheelSettings, imu_truth


@pytest.fixture(scope="module")
def survey(tmp_path_factory):
    # 8 m at 0.5 m/s: about 17 s, well inside the localizer's 30 s history. A dual-antenna
    # receiver (HDT), so the heading is known without the wheels too.
    settings = SurveySettings(goal=8.0, rows=2, seed=2, gnss=GnssSettings(dual_antenna=True))
    return twin_survey(settings)


def messages(survey, without=()):
    with rec.read_recording(survey.recording) as recording:
        calibration = load_calibration(recording.metadata.calibration)
        kept = [
            (m.topic, bytes(m.data), m.log_time, m.publish_time)
            for m in recording
            if m.topic not in without
        ]
    return kept, calibration


def run(survey, without=()):
    """Every outcome with the log_time of the message that let it through."""
    kept, calibration = messages(survey, without)
    processor = make_processor(ServiceConfig(), calibration)
    out = []
    for topic, data, log_time, publish_time in kept:
        out.extend((o, log_time) for o in processor.feed(topic, data, log_time, publish_time))
    return processor, out, kept


def waits_ms(out) -> list[float]:
    """From each scan's last packet to the message that let it through."""
    return [(released - o.scan.t_host) / 1e6 for o, released in out]


def test_a_scan_goes_through_once_settled_with_the_pose_and_frame_waiting_would_give(survey):
    processor, out, kept = run(survey)
    assert len(out) > 120
    waits = waits_ms(out)
    # Wheels at 50 Hz and a 10 fps camera settle a scan's middle about when its last
    # packet is in; a fixed wait held every scan 250 ms past its last packet.
    assert statistics.median(waits) < 80
    assert max(waits) < POSE_WAIT_NS / 1e6
    frame_times = np.array([pt for topic, _, _, pt in kept if topic == rec.CAMERA_JPEG])
    for outcome, _ in out:
        middle = scan_mid_time(outcome.scan)
        final = processor.pose_at(middle)  # with everything in
        assert outcome.pose is not None and final is not None
        assert (outcome.pose.x, outcome.pose.y, outcome.pose.yaw) == (final.x, final.y, final.yaw)
        assert np.array_equal(outcome.pose.covariance, final.covariance)
        nearest = frame_times[np.argmin(np.abs(frame_times - middle))]
        assert outcome.frame.t_capture == nearest


def test_without_a_camera_scans_do_not_wait_for_frames(survey):
    _, out, _ = run(survey, without=(rec.CAMERA_JPEG,))
    assert len(out) > 120 and all(o.frame is None for o, _ in out)
    assert statistics.median(waits_ms(out)) < 80


def test_without_wheels_a_scan_waits_for_the_fixes_at_most_the_bound(survey):
    # Poses then come from the 10 Hz GNSS epochs alone, each known one epoch late.
    processor, out, _ = run(survey, without=(rec.WHEELS_JACKAL, rec.WHEELS_BRIDGE))
    assert len(out) > 120
    waits = waits_ms(out)
    # The bound is on the scan's middle; the last packet is half a rotation (50 ms) later.
    assert max(waits) <= POSE_WAIT_NS / 1e6
    for outcome, _ in out:
        final = processor.pose_at(scan_mid_time(outcome.scan))
        if outcome.pose is not None:
            assert (outcome.pose.x, outcome.pose.y, outcome.pose.yaw) == (
                final.x,
                final.y,
                final.yaw,
            )


def test_a_robot_already_moving_on_a_slope_gets_its_pitch_from_the_first_samples():
    """The service may start (or restart) while the robot drives. Its first wheel sample
    is no speed: taken for a standstill, the jump to 0.5 m/s read as a 4 m/s^2 forward
    acceleration, subtracted from the accelerometer, tilted the first scans' pitch by 10
    degrees on an 8 % slope (and a ground strip ahead became an object). The twin's MCU
    bytes (wheels and IMU at 50 Hz, moving from the first sample) through the processor:
    the pitch is within 1 degree of the ground's from the first estimate on."""
    settings = SurveySettings(slope=0.08, goal=6.0, seed=4)
    ground = make_ground(settings)
    poses = drive(waypoints(settings.path, settings.width, settings.length, settings.goal))
    t0 = 1_778_000_000_000_000_000
    pose_at = riding_trajectory(poses, t0, ground)
    calibration = load_calibration(DEFAULT_CALIBRATION)
    mcu = JackalMcuEmulator(
        calibration.wheels, WheelSettings(), np.random.default_rng(1), np.random.default_rng(2)
    )
    processor = make_processor(ServiceConfig(), calibration)
    processor.feed(rec.WHEELS_JACKAL, mcu.handshake(), t0, t0)
    errors = []
    for t in range(t0, t0 + 3_000_000_000, 20_000_000):
        x, y, z, yaw, pitch, _roll = (float(v[0]) for v in pose_at(np.array([t])))
        omega, force = imu_truth(pose_at, t, WheelSettings().imu_difference_s)
        data = mcu.feedback(t, x, y, yaw, z) + mcu.imu(t, omega, force)
        processor.feed(rec.WHEELS_JACKAL, data, t + 2_000_000, t + 2_000_000)
        if (attitude := processor.attitude.attitude) is not None:
            errors.append(abs(attitude[1] - pitch))
    assert len(errors) > 140
    assert np.degrees(max(errors)) < 1.0


def backlogged(kept, topics, gaps, hold_ns=600_000_000):
    """The messages as a loaded host reads them: those of `topics` logged in each gap
    (start, offset from the first message) held and all read at its end, stamped in the
    same instant, as the service's reader threads stamped them (docs/service.md)."""
    t0 = kept[0][2]
    out = []
    for topic, data, log_time, publish_time in kept:
        for start in gaps:
            if topic in topics and t0 + start <= log_time < t0 + start + hold_ns:
                log_time = t0 + start + hold_ns
        out.append((topic, data, log_time, publish_time))
    return sorted(out, key=lambda m: m[2])  # stable: each stream keeps its order


def test_wheels_and_gnss_read_in_backlogs_give_the_poses_read_on_time(survey):
    """The MCU's bytes and the receiver's sentences held 600 ms twice, then read in a
    burst (what a loaded host did to the live run): each wheel sample and IMU sample is
    timed by its header stamp, each GNSS epoch by its UTC, and the fixes wait for the
    wheels, so every scan gets the pose it gets when they come on time."""
    kept, calibration = messages(survey)
    late = backlogged(kept, (rec.WHEELS_JACKAL, rec.GNSS_NMEA), gaps=(4_000_000_000, 9_000_000_000))
    wheel_times = [m[2] for m in late if m[0] == rec.WHEELS_JACKAL]
    assert max(b - a for a, b in itertools.pairwise(wheel_times)) >= 590_000_000

    def poses(messages):
        processor = make_processor(ServiceConfig(), calibration)
        out = []
        for message in messages:
            out.extend(processor.feed(*message))
        out.extend(processor.finish())
        assert processor.stats.scans_without_pose == 0
        return {o.scan.t_host: (o.pose.x, o.pose.y, o.pose.yaw, o.pose.pitch) for o in out}

    on_time, backlog = poses(kept), poses(late)
    assert len(on_time) > 120
    assert backlog == on_time


def test_a_loop_behind_its_sensors_sheds_whole_scans_and_keeps_the_poses(survey):
    """Live, `behind` (the service's clock against the newest message) says the loop is
    too far behind to map: the scans ready then are counted and not mapped, and the
    others get the pose and frame of a run that maps every scan (the localizer still
    takes every message)."""
    _, full, kept = run(survey)
    processor = make_processor(ServiceConfig(), messages(survey)[1])
    # Behind during every other second of the survey, by the newest message's time.
    t0 = kept[0][2]
    processor.behind = lambda newest: (newest - t0) // 1_000_000_000 % 2 == 1
    mapped = []
    for message in kept:
        mapped.extend(processor.feed(*message))
    assert len(full) > 120
    assert processor.stats.scans_shed > 40 and len(mapped) > 40
    assert processor.stats.scans_shed + len(mapped) == len(full)
    assert processor.stats.scans == len(mapped)  # only they reached the mapper
    everything = {o.scan.t_host: (o.pose, o.frame.t_capture) for o, _ in full}
    for outcome in mapped:
        pose, frame_time = everything[outcome.scan.t_host]
        assert (outcome.pose.x, outcome.pose.y, outcome.pose.yaw) == (pose.x, pose.y, pose.yaw)
        assert outcome.frame.t_capture == frame_time


def test_a_scan_before_the_first_fix_is_as_uncertain_as_the_datum(survey):
    """Carried into utm at the datum, a pose seen before the first fix has the datum's
    covariance, not the zero of odometry: a scan a few ms before the first fix was
    mapped with a heading still unknown (the live run's first scan, T2 7 % wider), where
    one a few ms after it was left out."""
    processor, _, _ = run(survey)
    first = processor.localizer.first_utm_time
    start = processor.localizer.pose_at(first - 50_000_000, "odom")
    assert start is not None
    before = processor.pose_at(start.t)
    datum = processor.localizer.pose_at(first)
    assert before.frame == "utm"
    assert np.array_equal(before.covariance, datum.covariance)
    assert datum.covariance[0, 0] > 0


def test_encoder_board_ticks_read_in_a_backlog_are_timed_by_the_board_clock():
    """The retrofit encoder board stamps each TICKS frame with its own clock (us since its
    boot): 600 ms of frames held and read at once give the odometry they give on time."""
    from dataclasses import replace

    from treetraits.firmware_bridge.retrofit.protocol import encode_ticks

    calibration = load_calibration(DEFAULT_CALIBRATION)
    calibration = replace(calibration, wheels=replace(calibration.wheels, ticks_per_rev=4096))
    t0, boot_us = 1_778_000_000_000_000_000, 42_000_000
    frames = []  # (read on time, bytes): 50 Hz, a left-hand arc
    for k in range(250):
        data = encode_ticks(k, boot_us + k * 20_000, left=20 * k, right=26 * k)
        frames.append((t0 + k * 20_000_000 + 1_500_000, data))
    held = (t0 + 2_000_000_000, t0 + 2_600_000_000)

    def odometry(late: bool):
        processor = make_processor(ServiceConfig(), calibration)
        for read, data in frames:
            if late and held[0] <= read < held[1]:
                read = held[1]
            processor.feed(rec.WHEELS_BRIDGE, data, read, read)
        return [
            processor.localizer.pose_at(t, "odom")
            for t in range(t0 + 100_000_000, t0 + 4_900_000_000, 10_000_000)
        ]

    on_time, backlog = odometry(False), odometry(True)
    assert on_time[-1].x > 0.5  # it moved
    assert [(p.x, p.y, p.yaw) for p in backlog] == [(p.x, p.y, p.yaw) for p in on_time]
