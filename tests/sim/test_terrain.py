"""The twin's terrain: a height field under the trees, a robot that rides on it (pitch and
roll from the ground under its four wheels), and the VLP-16 cast from that 6-DoF pose."""

from __future__ import annotations

import math

import numpy as np
import pytest

from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.sim.lidar import LidarSettings, Scene, Vlp16Emulator, _poses
from treetraits.sim.orchard import Ground, ground_mesh
from treetraits.sim.paths import attitude_on, riding_trajectory


def standing(ground, x=0.0, y=0.0, yaw=0.0):
    """A robot standing still on `ground` (poses t, x, y, yaw for 10 s)."""
    poses = np.array([[0.0, x, y, yaw], [10.0, x, y, yaw]])
    return riding_trajectory(poses, 0, ground)


@pytest.mark.parametrize("slope", [0.06, 0.15, -0.1])
def test_pitch_on_a_slope_is_the_slope_angle(slope):
    # Nose uphill: REP-103 pitch is positive nose down, so climbing is -atan(slope).
    z, pitch, roll = attitude_on(Ground(slope_x=slope), 3.0, 1.0, 0.0)
    assert float(pitch) == pytest.approx(-math.atan(slope), abs=1e-9)
    assert float(roll) == pytest.approx(0.0, abs=1e-9)
    assert float(z) == pytest.approx(slope * 3.0, abs=1e-9)
    # Turned to face across the slope, the same ground rolls the robot instead: facing +y
    # (yaw 90 deg), uphill (+x) is on its right, so the left side is down (negative roll).
    _, pitch, roll = attitude_on(Ground(slope_x=slope), 3.0, 1.0, math.pi / 2)
    assert float(pitch) == pytest.approx(0.0, abs=1e-9)
    assert float(roll) == pytest.approx(-math.atan(slope), abs=1e-9)


def test_furrows_under_one_track_roll_the_robot():
    # A furrow profile across the rows, the robot straddling a furrow's flank: its left
    # wheels sit higher than its right ones by the profile's difference over its track.
    ground = Ground(furrow_m=0.1, furrow_spacing_m=1.0)
    y = 0.25  # mid-flank of the cosine
    track = 0.376
    left, right = ground.height(0.0, y + track / 2), ground.height(0.0, y - track / 2)
    _, _, roll = attitude_on(ground, 0.0, y, 0.0)
    assert float(roll) == pytest.approx(math.atan((left - right) / track), abs=1e-9)
    assert float(left - right) < -0.1  # a real tilt: ~8 deg here


def test_uneven_ground_is_a_height_field_mesh_on_the_analytic_surface():
    ground = Ground(slope_x=0.1, slope_y=0.05, undulation_m=0.08, furrow_m=0.05)
    vertices, triangles = ground_mesh(ground, (-5, 5), (-4, 4))
    assert len(triangles) > 1000  # not the plane's two triangles
    assert np.abs(vertices[:, 2] - ground.height(vertices[:, 0], vertices[:, 1])).max() < 1e-5
    # Undulation and furrows are bounded by their amplitudes about the plane.
    rest = vertices[:, 2] - (0.1 * vertices[:, 0] + 0.05 * vertices[:, 1])
    assert np.abs(rest).max() <= 0.08 + 0.05 + 1e-6
    assert ground_mesh(Ground(slope_x=0.1), (-5, 5), (-4, 4))[1].shape == (2, 3)


def test_a_scan_from_the_pitched_robot_lands_on_the_ground_plane():
    # A 15 % slope along x and 8 % across: plane z = 0.15 x + 0.08 y. The robot stands on
    # it facing -30 deg; every decoded return, put in the world with the robot's pose (its
    # pitch and roll included), must lie on that plane.
    ground = Ground(slope_x=0.15, slope_y=0.08)
    scene = Scene()
    scene.add(*ground_mesh(ground, (-60, 60), (-60, 60)), label=0)
    settings = LidarSettings(range_sigma_m=0.0, dropout=0.0)
    trajectory = standing(ground, 2.0, -1.0, math.radians(-30))
    batcher = ScanBatcher()
    scans = []
    emulator = Vlp16Emulator(scene, DEFAULT_T_BASE_LIDAR, settings)
    for t_device, payload in emulator.packets(trajectory, 0, int(0.35e9)):
        scan = batcher.push(payload, t_device + 200_000)
        if scan is not None:
            scans.append(scan)
    points = scans[1].points
    lidar = np.column_stack([points["x"], points["y"], points["z"], np.ones(len(points))])
    pose = trajectory(np.array([0]))
    assert abs(float(pose[4][0])) > 0.05 and abs(float(pose[5][0])) > 0.02  # really tilted
    world = (_poses(*pose)[0] @ DEFAULT_T_BASE_LIDAR @ lidar.T).T
    off_plane = world[:, 2] - ground.height(world[:, 0], world[:, 1])
    assert len(points) > 5000
    assert np.abs(off_plane).max() < 0.01  # 2 mm range units, float32 points
    # Without the tilt (the old level pose) the same returns would miss the plane.
    level = (_poses(*pose[:4])[0] @ DEFAULT_T_BASE_LIDAR @ lidar.T).T
    assert np.abs(level[:, 2] - ground.height(level[:, 0], level[:, 1])).max() > 0.5
