"""pipeline/deskew.py: a VLP-16-like sweep of a walled yard, taken while the robot drives
at 2 m/s and turns at 0.5 rad/s. Each point is ray-cast from where the LiDAR really was
when it fired, so the raw scan is smeared; de-skewed with poses sampled every 10 ms it
lies on the walls as seen from the LiDAR at the scan's middle."""

from __future__ import annotations

import time

import numpy as np
import pytest

from tests.helpers.deskew import (
    SWEEP_NS,
    T_BASE_LIDAR,
    T_DEVICE_END,
    T_HOST_END,
    WALLS,
    base_pose,
    samples,
    sweep,
)
from treetraits.drivers.records import POINT_DTYPE, Scan, row_items, take_points
from treetraits.pipeline.deskew import (
    compile_kernels,
    deskew,
    deskew_scan,
    scan_point_host_times,
)
from treetraits.pipeline.localization.attitude import rotation_zyx
from treetraits.pipeline.projection import scan_mid_time


def wall_distances(points_lidar: np.ndarray, wall: np.ndarray) -> np.ndarray:
    """Distance of each point (in the LiDAR frame at the middle) from its true wall."""
    world = points_lidar @ (base_pose(np.zeros(1))[0] @ T_BASE_LIDAR)[:3, :3].T
    world += (base_pose(np.zeros(1))[0] @ T_BASE_LIDAR)[:3, 3]
    normals = np.array([[*WALLS[i][0], 0.0] for i in wall])
    offsets = np.array([WALLS[i][1] for i in wall])
    return np.abs((world * normals).sum(1) - offsets)


def straightness(points_lidar: np.ndarray, wall: np.ndarray, index: int) -> float:
    """Largest distance of a wall's points from their own best-fit vertical plane."""
    xy = points_lidar[wall == index, :2]
    centred = xy - xy.mean(0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    return float(np.abs(centred @ vt[1]).max())


def test_a_wall_comes_out_straight_after_deskew_and_smeared_before():
    points, dt, wall = sweep()
    assert len(points) > 25_000
    times, poses = samples()
    compile_kernels()  # as the service does before READY: the timing is of a scan's call
    start = time.perf_counter()
    fixed = deskew(points, dt, times, poses, 0, T_BASE_LIDAR)
    elapsed_ms = (time.perf_counter() - start) * 1e3

    before, after = wall_distances(points, wall), wall_distances(fixed, wall)
    # Raw: 10 cm of travel each side of the middle and 1.4 deg of turn: tens of cm off.
    assert before.max() > 0.1  # measured: 0.18 m
    assert after.max() < 0.001  # measured: 0.025 mm (the 10 ms blend of rotations)
    for index in range(len(WALLS)):
        assert straightness(fixed, wall, index) < 0.001  # measured: < 0.02 mm
    # The wall the sweep starts and ends on (ahead: the cut) is torn apart before.
    assert straightness(points, wall, 0) > 0.06  # measured: 0.13 m
    assert elapsed_ms < 50  # measured: 2.5 ms for 28.8k points (a loaded 2-core box)
    # Points in any order give the same answer (a scan is in firing order; this is not).
    perm = np.random.default_rng(0).permutation(len(dt))
    shuffled = deskew(points[perm], dt[perm], times, poses, 0, T_BASE_LIDAR)
    np.testing.assert_array_equal(shuffled, fixed[perm])


def test_deskew_scan_uses_durations_of_the_sensor_clock_only():
    points, dt, wall = sweep()
    cloud = np.zeros(len(points), dtype=POINT_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = points.T
    cloud["t"] = T_DEVICE_END - SWEEP_NS // 2 + dt  # the sensor's own, unsynchronised clock
    scan = Scan(
        cloud,
        int(cloud["t"].min()),
        int(cloud["t"].max()),
        T_HOST_END,
        True,
        76,
        0,
        "VLP-16",
        "strongest",
    )
    middle = scan_mid_time(scan)
    host = scan_point_host_times(scan)
    assert host.max() == T_HOST_END and abs(int(np.median(host)) - middle) < 2_000_000
    times, poses = samples()
    fixed = deskew_scan(scan, middle + times, poses, middle, T_BASE_LIDAR)
    xyz = np.stack([fixed.points["x"], fixed.points["y"], fixed.points["z"]], 1)
    assert wall_distances(xyz, wall).max() < 0.003  # float32 points
    assert np.array_equal(fixed.points["t"], scan.points["t"]) and fixed.t_host == scan.t_host


def test_still_robot_and_single_pose_leave_points_alone():
    points, dt, _ = sweep()
    still = np.tile(np.eye(4), (3, 1, 1))
    out = deskew(points, dt, np.array([-50, 0, 50]) * 1_000_000, still, 0, T_BASE_LIDAR)
    np.testing.assert_allclose(out, points, atol=1e-12)
    one = deskew(points, dt, np.array([0]), still[:1], 0)
    np.testing.assert_array_equal(one, points)
    with pytest.raises(ValueError):
        deskew(points, dt, np.array([5, 1]), still[:2], 0)


def test_roll_and_pitch_changes_during_the_sweep_are_taken_out():
    # Rocking over a root: pitch from +2 to -2 deg in 100 ms (0.7 rad/s), robot still.
    points = np.array([[10.0, 0.0, 0.0]] * 11)
    dt = np.linspace(-SWEEP_NS // 2, SWEEP_NS // 2, 11).astype(np.int64)
    pitch = np.radians(2.0) - np.radians(4.0) * (dt + SWEEP_NS // 2) / SWEEP_NS
    poses = np.array([np.eye(4) for _ in dt])
    for pose, p in zip(poses, pitch, strict=True):
        pose[:3, :3] = rotation_zyx(0.0, p, 0.0)
    out = deskew(points, dt, dt, poses, 0)
    # A point 10 m ahead fired at pitch p sits at z = -10 sin(p) in the middle's frame.
    np.testing.assert_allclose(out[:, 2], -10 * np.sin(pitch), atol=2e-3)
    assert np.ptp(out[:, 2]) > 0.6


def test_take_points_is_indexing_as_a_copy():
    rng = np.random.default_rng(3)
    points = np.zeros(500, dtype=POINT_DTYPE)
    for name in POINT_DTYPE.names:
        points[name] = rng.integers(0, 200, len(points))
    points["x"] += rng.normal(size=len(points)).astype(np.float32)
    mask = rng.random(len(points)) < 0.4
    order = rng.permutation(len(points))[:300]
    for index in (mask, order, slice(None), slice(10, 400, 3)):
        taken = take_points(points, index)
        assert taken.dtype == POINT_DTYPE
        assert taken.tobytes() == points[index].tobytes()
        assert not np.shares_memory(taken, points)


def test_row_items_copies_rows_of_a_grid_under_a_mask():
    rng = np.random.default_rng(4)
    grid = rng.normal(size=(200, 3))
    mask = rng.random(200) < 0.5
    out = np.zeros((int(mask.sum()), 3))
    row_items(out)[:] = row_items(grid)[mask]
    assert np.array_equal(out, grid[mask])
    keys = np.arange(10)
    assert row_items(keys) is keys  # plain 1-D items are copied natively already
