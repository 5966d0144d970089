"""Pose fusion on known trajectories: wheels with slip and noise, GNSS with noise, outages,
outliers, a lever arm, with or without a true heading. Error bounds are stated per test.

The truth is simulated here in the UTM grid of a grove near Riverside, California (zone 11N),
and turned into what the sensors would report: wheel rotation in radians, GNSS fixes in
WGS84 for the antenna, true (not grid) headings.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tests.helpers.localization import GRID, ORIGIN, PATH, WHEELS, YawRate, drive, sensors
from treetraits.drivers.records import Fix, WheelSample
from treetraits.pipeline.localization import LocalizationConfig, Localizer
from treetraits.pipeline.localization.utm import UtmGrid, true_heading_to_grid_yaw, wrap_angle


def run(events, config=None, T_base_gnss=None):
    # Keep the whole drive in the pose history, so every truth pose can be checked.
    config = dataclasses.replace(config or LocalizationConfig(), history_s=1e4)
    localizer = Localizer(config, WHEELS, T_base_gnss)
    verdicts = {}
    for event in events:
        if isinstance(event, WheelSample):
            localizer.add_wheels(event)
        elif isinstance(event, YawRate):
            localizer.add_yaw_rate(event.t_host, event.rate)
        else:
            verdicts[event.t_host] = localizer.add_fix(event)
    return localizer, verdicts


def errors(localizer, poses, after_s=0.0):
    """Position and heading errors of `pose_at` against the truth, from `after_s` on."""
    position, heading = [], []
    for t, x, y, yaw in poses:
        if t < after_s:
            continue
        pose = localizer.pose_at(int(t * 1e9))
        if pose is None:
            continue
        position.append(math.hypot(pose.x - x, pose.y - y))
        heading.append(abs(wrap_angle(pose.yaw - yaw)))
    return np.array(position), np.degrees(np.array(heading))


def test_utm_grid_and_convergence_sign():
    grid = UtmGrid.for_zone(33, north=True)
    # At 45N 16E (east of zone 33's meridian) true north is 0.707 deg counter-clockwise
    # of grid north (published value for this point).
    assert math.degrees(grid.convergence_rad(45.0, 16.0)) == pytest.approx(0.7071, abs=1e-3)
    # So a receiver facing true north there faces 0.707 deg counter-clockwise of grid
    # north: ENU grid yaw 90.707 deg.
    yaw = true_heading_to_grid_yaw(0.0, grid.convergence_rad(45.0, 16.0))
    assert math.degrees(yaw) == pytest.approx(90.7071, abs=1e-3)
    assert UtmGrid.for_position(33.97, -117.32).name == "11N"
    assert UtmGrid.for_position(-33.9, 151.2).name == "56S"
    lat, lon = GRID.inverse(*GRID.forward(33.97, -117.32))
    assert (lat, lon) == pytest.approx((33.97, -117.32), abs=1e-9)
    # Heading 0 (true north) with no convergence is ENU yaw +90 deg; east is 0.
    assert true_heading_to_grid_yaw(0.0, 0.0) == pytest.approx(math.pi / 2)
    assert true_heading_to_grid_yaw(90.0, 0.0) == pytest.approx(0.0)


def test_rtk_with_true_heading_tracks_to_centimetres():
    """RTK fixed (2 cm) at 5 Hz, HDT at 0.5 deg, 2 % wheel slip: position error stays
    under 5 cm RMS and 10 cm worst; heading under 1.5 deg."""
    rng = np.random.default_rng(1)
    poses = drive(PATH)
    localizer, _ = run(sensors(poses, rng, heading_sigma_deg=0.5))
    position, heading = errors(localizer, poses, after_s=2.0)
    assert math.sqrt(np.mean(position**2)) < 0.05
    assert position.max() < 0.10
    assert heading.max() < 1.5
    assert localizer.stats.fixes_rejected == 0
    assert localizer.grid.name == "11N"


def test_heading_from_course_over_ground_without_a_true_heading():
    """A stock Jackal: no HDT. Starting 30 deg off with no prior (initial heading east,
    sigma pi), course over ground while driving straight fixes the heading within 3 deg
    after the first 10 s, and position stays under 10 cm."""
    rng = np.random.default_rng(2)
    poses = drive(PATH)
    localizer, _ = run(sensors(poses, rng))
    position, heading = errors(localizer, poses, after_s=10.0)
    assert heading.max() < 3.0
    assert position.max() < 0.10
    assert localizer.stats.courses_used > 50


def test_lever_arm_is_removed():
    """The antenna 0.4 m ahead and 0.2 m left of the centre: the pose is the centre's,
    within the same bounds; ignoring the lever arm would be off by 0.45 m."""
    rng = np.random.default_rng(3)
    poses = drive(PATH)
    lever = (0.4, 0.2)
    t_base_gnss = np.eye(4)
    t_base_gnss[:2, 3] = lever
    localizer, _ = run(
        sensors(poses, rng, heading_sigma_deg=0.5, lever=lever), T_base_gnss=t_base_gnss
    )
    position, _ = errors(localizer, poses, after_s=1.0)
    assert position.max() < 0.10
    naive, _ = run(sensors(poses, np.random.default_rng(3), heading_sigma_deg=0.5, lever=lever))
    assert errors(naive, poses, after_s=1.0)[0].mean() > 0.3


@pytest.mark.parametrize("lever", [(-1.0, -0.6), (1.0, 0.5), (0.0, 1.0)])
def test_the_first_heading_turns_the_robot_about_its_antenna(lever):
    """No true heading and no prior: the datum places the centre from the antenna with a
    guessed heading (east), 150 deg off the truth here. When course over ground gives the
    heading, the centre must swing about the antenna at once: with a 1 m lever arm the
    centre was otherwise 2 m off until five fixes in a row had been rejected, and the
    scans of that half second mapped a phantom tree beside a real one."""
    rng = np.random.default_rng(5)
    poses = drive([(2, 0.0, 0.0), (20, 0.0)], start_yaw_deg=150.0)  # from a standstill
    t_base_gnss = np.eye(4)
    t_base_gnss[:2, 3] = lever
    localizer, _ = run(sensors(poses, rng, lever=lever), T_base_gnss=t_base_gnss)
    position, heading = errors(localizer, poses, after_s=2.5)
    # Measured: under 5 cm from half a second after setting off, for every lever arm.
    assert position.max() < 0.1 and heading.max() < 3.0
    assert localizer.stats.position_resets == 0


def test_the_gyro_holds_the_heading_through_a_headland_turn_without_gnss():
    """A stock Jackal: no true heading, and a skid steer whose wheels turn 40 % more than
    its track explains in a turn. The GNSS is lost for the 10 s around a U-turn. From the
    wheels alone the turn reads 252 deg instead of 180 and the heading comes out of it
    75 deg off (the position 2.6 m off by the end of the outage); with the gyro (0.01 rad/s
    noise, a 0.003 rad/s bias left: 1.7 deg over the outage) it stays within 4 deg of the
    truth and the position within 0.3 m."""
    poses = drive([(20, 0.0), (2, 0.0), (2 * math.pi, 0.5), (2, 0.0), (20, 0.0)])
    outage = (20.0, 30.3)

    def worst(gyro):
        rng = np.random.default_rng(6)
        events = sensors(poses, rng, outage=outage, scrub=1.4, gyro=gyro)
        localizer, _ = run(events)
        inside = [p for p in poses if outage[0] <= p[0] <= outage[1] + 2.0]
        position, heading = errors(localizer, inside)
        return position.max(), heading.max(), localizer

    position, heading, localizer = worst(gyro=(0.01, 0.003))
    assert localizer.stats.gyro_samples == localizer.stats.wheel_samples
    # Measured: 0.09 m and 3.0 deg (the heading from course over ground before the outage
    # plus the bias).
    assert heading < 4.0 and position < 0.3
    position, heading, _ = worst(gyro=None)
    assert heading > 30 and position > 1.0


def test_outage_dead_reckons_within_its_own_uncertainty_and_reconverges():
    """20 s without GNSS (10 m of travel, with a turn, 4 % slip): the error at the end of
    the outage is under 1.5 m and within 3 sigma of the filter's own covariance. When
    fixes return, no correction overshoots (each moves the pose by no more than its gap to
    the fix plus 3 fix sigmas) and the pose is back under 10 cm within 1 s."""
    rng = np.random.default_rng(4)
    poses = drive(PATH)
    outage = (35.0, 55.0)
    events = sensors(poses, rng, heading_sigma_deg=0.5, slip=0.04, outage=outage)
    localizer = Localizer(LocalizationConfig(history_s=1e4), WHEELS)
    corrections = []
    for event in events:
        if isinstance(event, WheelSample):
            localizer.add_wheels(event)
            continue
        before = localizer.pose()
        verdict = localizer.add_fix(event)
        if event.t_host > outage[1] * 1e9 and len(corrections) < 10 and verdict.used:
            after = localizer.pose()
            fix = np.array(GRID.forward(event.lat, event.lon))
            gap = math.hypot(*(fix - (before.x, before.y)))
            step = math.hypot(after.x - before.x, after.y - before.y)
            corrections.append((step, gap))

    end = int((outage[1] - 0.01) * 1e9)
    pose = localizer.pose_at(end)
    truth = min(poses, key=lambda p: abs(p[0] - outage[1] + 0.01))
    error = math.hypot(pose.x - truth[1], pose.y - truth[2])
    sigma = math.sqrt(max(np.linalg.eigvalsh(pose.covariance[:2, :2])))
    assert 0.0 < error < 1.5  # 15 % of the 10 m driven blind
    assert error < 3 * sigma
    assert corrections[0][1] > 0.2  # the first fix back really was far from the pose
    assert all(step <= gap + 3 * 0.02 for step, gap in corrections)
    position, _ = errors(localizer, poses, after_s=outage[1] + 1.0)
    assert position.max() < 0.10


def test_an_outlier_fix_is_rejected_and_a_persistent_shift_is_accepted():
    rng = np.random.default_rng(5)
    poses = drive(PATH)
    outlier_index = 100  # 20 s in
    events = sensors(poses, rng, heading_sigma_deg=0.5, outliers={outlier_index: 5.0})
    localizer, verdicts = run(events)
    outlier = list(verdicts.values())[outlier_index]
    assert outlier.reason == "rejected" and outlier.mahalanobis2 > 1000
    # A good fix falls outside a p = 0.999 gate about once in 1000: allow a couple.
    assert localizer.stats.fixes_rejected <= 3
    position, _ = errors(localizer, poses, after_s=1.0)
    assert position.max() < 0.10  # the 5 m outlier never reached the pose

    # Every fix from 40 s on 3 m east (a datum change, or slip that odometry missed):
    # after max_rejected_in_a_row rejections the filter follows GNSS again.
    shifted = {n: 3.0 for n in range(200, 450)}
    localizer, verdicts = run(
        sensors(drive(PATH), np.random.default_rng(6), heading_sigma_deg=0.5, outliers=shifted)
    )
    reasons = [v.reason for v in verdicts.values()]
    assert reasons.count("reset") >= 1
    first_reset = reasons.index("reset")
    assert reasons[first_reset - 4 : first_reset] == ["rejected"] * 4


def test_unusable_fixes_are_counted_not_used():
    localizer = Localizer(LocalizationConfig(), WHEELS)
    for quality in (0, 6):
        verdict = localizer.add_fix(Fix(1, None, 33.97, -117.32, 10.0, None, quality, 5, 1.0))
        assert not verdict.used
    assert localizer.add_fix(Fix(2, None, None, None, None, None, 1, 0, None)).used is False
    assert localizer.stats.fixes_unusable == 3
    assert localizer.pose() is None and localizer.grid is None


def test_before_the_datum_the_pose_is_odometry_and_pose_at_interpolates():
    localizer = Localizer(LocalizationConfig(), WHEELS)
    travel = 1.0 / WHEELS.radius  # one metre of wheel rotation, in radians
    localizer.add_wheels(WheelSample(0, 0.0, 0.0, "rad"))
    localizer.add_wheels(WheelSample(2_000_000_000, travel, travel, "rad"))
    pose = localizer.pose()
    assert pose.frame == "odom" and (pose.x, pose.y, pose.yaw) == pytest.approx((1.0, 0.0, 0.0))
    middle = localizer.pose_at(1_000_000_000, frame="odom")
    assert (middle.x, middle.y) == pytest.approx((0.5, 0.0))
    assert localizer.pose_at(3_000_000_000, frame="odom") is None
    assert localizer.pose_at(1_000_000_000) is None  # no utm before the datum

    # A wheel counter that restarts from zero is not a 1 m jump backwards.
    localizer.add_wheels(WheelSample(2_020_000_000, 0.0, 0.0, "rad"))
    assert localizer.stats.wheel_resets == 1
    assert localizer.pose().x == pytest.approx(1.0)


def test_utm_from_odom_georeferences_what_was_seen_before_the_datum():
    """A tree mapped in `odom` before the first fix lands at its true UTM position once
    the datum and heading are known (within the pose error)."""
    rng = np.random.default_rng(7)
    poses = drive(PATH)
    events = sensors(poses, rng, heading_sigma_deg=0.5, outage=(0.0, 10.0))
    localizer, _ = run(events)
    # The robot started at ORIGIN facing 30 deg: a tree 3 m ahead-left of the start.
    tree_odom = np.array([3.0, 1.0, 1.0])
    start_yaw = math.radians(30.0)
    truth = (
        ORIGIN[0] + 3.0 * math.cos(start_yaw) - 1.0 * math.sin(start_yaw),
        ORIGIN[1] + 3.0 * math.sin(start_yaw) + 1.0 * math.cos(start_yaw),
    )
    first = localizer.first_utm_time
    assert first is not None and abs(first - 10e9) < 0.3e9
    placed = localizer.utm_from_odom(first) @ tree_odom
    # Odometry drift over the 5 m before the datum enters the transform (2 % slip).
    assert math.hypot(placed[0] - truth[0], placed[1] - truth[1]) < 0.3
    # Taken at the end of the drive instead, 80 s of drift would put it metres off.
    late = localizer.utm_from_odom() @ tree_odom
    assert math.hypot(late[0] - truth[0], late[1] - truth[1]) > 1.0


@pytest.mark.parametrize("seed", range(4))
def test_a_robot_that_starts_by_turning_gets_its_heading_from_the_first_straight_leg(seed):
    """No true heading, no prior (east, sigma pi), the antenna 0.18 m behind the centre
    (the CitrusFarm rig), and the drive begins with a turn at 1 rad/s, as the S and N paths
    do. Position fixes during the turn must not settle the heading on a wrong answer that
    course over ground is then gated against (that once mapped a whole N-path survey
    backwards). From 5 s into the first straight leg the heading is within 3 deg."""
    rng = np.random.default_rng(seed)
    poses = drive([(2.5, 1.0), (20, 0.0)])
    lever = (-0.18, 0.0)
    t_base_gnss = np.eye(4)
    t_base_gnss[:2, 3] = lever
    localizer, _ = run(sensors(poses, rng, lever=lever), T_base_gnss=t_base_gnss)
    position, heading = errors(localizer, poses, after_s=7.5)
    assert heading.max() < 3.0
    assert position.max() < 0.10


def test_without_wheel_data_course_over_ground_still_gives_the_heading():
    """The wheel link is down (no WheelSample at all): course over ground is the only
    heading there is, so it is used unchecked (trusted less). Driving straight, the
    heading is found (within 3 deg after 5 s); with no heading a run in utm maps nothing."""
    rng = np.random.default_rng(4)
    poses = drive([(30, 0.0)])
    fixes = [e for e in sensors(poses, rng) if isinstance(e, Fix)]
    localizer, _ = run(fixes)
    assert localizer.heading_known
    _, heading = errors(localizer, poses, after_s=5.0)
    assert len(heading) > 100 and heading.max() < 3.0


def test_a_position_is_reported_no_better_than_the_fixes_it_rests_on():
    """Fixes of sigma 0.25 m (an RTK float solution) five a second: the filter, taking them
    as independent, narrows its position to a few centimetres, but a receiver's error
    wanders for minutes and averaging its fixes cannot beat its own sigma: the reported
    pose's position sigma is at least the last fix's. Heading and RTK fixed unchanged."""
    poses = drive([(30, 0.0)])
    for gnss_sigma in (0.25, 0.02):
        localizer, _ = run(sensors(poses, np.random.default_rng(5), gnss_sigma=gnss_sigma))
        filtered = np.sqrt(np.linalg.eigvalsh(localizer._filter.covariance[:2, :2]).max())
        pose = localizer.pose()
        reported = np.sqrt(np.linalg.eigvalsh(pose.covariance[:2, :2]).max())
        # At least the fix's sigma on each axis (the x-y correlation kept: a little more).
        assert gnss_sigma <= reported <= 1.1 * max(gnss_sigma, filtered)
        assert min(pose.covariance[0, 0], pose.covariance[1, 1]) >= gnss_sigma**2
        assert pose.covariance[2, 2] == pytest.approx(localizer._filter.covariance[2, 2])
        if gnss_sigma == 0.25:
            assert filtered < 0.1  # what the filter alone would say
