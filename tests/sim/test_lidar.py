"""The VLP-16 emulator through our real decoder: packets at the sensor's rate, points on
the geometry that was ray-cast, motion during the scan, and trees measured by the
traits' definitions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.sim.lidar import LidarSettings, Scene, Vlp16Emulator
from treetraits.sim.orchard import (
    Ground,
    TreeSpec,
    grid_orchard,
    ground_mesh,
    measure_truth,
    tree_mesh,
)

LIDAR_HEIGHT = DEFAULT_T_BASE_LIDAR[2, 3]


def decode(emulator, trajectory, seconds):
    batcher = ScanBatcher()
    scans, times = [], []
    for t_device, payload in emulator.packets(trajectory, 0, int(seconds * 1e9)):
        times.append(t_device)
        scan = batcher.push(payload, t_device + 200_000)
        if scan is not None:
            scans.append(scan)
    return scans, times, batcher.stats


def standing_still(x=0.0, y=0.0, yaw=0.0):
    def trajectory(t):
        return (np.full(t.shape, x), np.full(t.shape, y), np.zeros(t.shape), np.full(t.shape, yaw))

    return trajectory


def test_flat_ground_comes_back_at_the_lidar_height():
    scene = Scene()
    scene.add(*ground_mesh(Ground(), (-60, 60), (-60, 60)), label=0)
    settings = LidarSettings(range_sigma_m=0.0, dropout=0.0)
    scans, times, stats = decode(
        Vlp16Emulator(scene, DEFAULT_T_BASE_LIDAR, settings), standing_still(), 1.0
    )
    assert np.diff(times).tolist() == [m.PACKET_NS_SINGLE] * (len(times) - 1)  # 754 packets/s
    assert stats.malformed == stats.lost == 0
    points = scans[2].points
    # Only the 8 downward beams hit a flat floor; each lands at z = -height (2 mm units).
    assert set(np.unique(points["ring"])) == set(range(8))
    assert np.abs(points["z"] + LIDAR_HEIGHT).max() < 0.01
    ranges = np.hypot(points["x"], points["y"])
    expected = LIDAR_HEIGHT / np.tan(
        -np.deg2rad(np.asarray(m.VLP16.elevation_deg)[np.argsort(m.VLP16.ring)][points["ring"]])
    )
    assert np.abs(ranges - expected).max() < 0.02 * expected.max()
    assert scans[2].complete and 70 <= scans[2].packets <= 77


def test_a_tree_is_seen_where_it_stands_and_measured_by_the_trait_definitions():
    rng = np.random.default_rng(3)
    ground = Ground()
    spec = TreeSpec("T1", "1", 4.0, 1.0, 0.45, 0.08, 1.35, 1.1)
    vertices, triangles = tree_mesh(spec, ground, rng)
    truth = measure_truth(spec, vertices, ground)
    assert truth.height == pytest.approx(0.45 + 2.2, abs=0.08)
    assert truth.width == pytest.approx(2.7, abs=0.12)

    scene = Scene()
    scene.add(*ground_mesh(ground, (-30, 30), (-30, 30)), label=0)
    scene.add(vertices, triangles, label=1)
    scans, _, _ = decode(Vlp16Emulator(scene, DEFAULT_T_BASE_LIDAR, rng=rng), standing_still(), 0.5)
    points = scans[1].points
    tree = points[points["z"] > -LIDAR_HEIGHT + 0.2]
    # The lidar sits 0.04 m ahead of base_link: the tree centre is at (3.96, 1.0).
    centre_distance = np.hypot(tree["x"] - 3.96, tree["y"] - 1.0)
    assert len(tree) > 500
    assert centre_distance.max() < 1.35 + 0.15  # inside the crown (+ noise, leaf size)
    # From 0.44 m, the +15 deg beam meets the crown's near side at about 1.2-1.9 m: the
    # top of a 2.7 m tree 4 m away is out of the sensor's view (the paper's height rule
    # reads the top ring as the robot passes).
    top = tree[np.argmax(tree["z"])]
    assert 1.0 < top["z"] + LIDAR_HEIGHT <= truth.height
    assert top["ring"] == 15
    # The near side of a dense crown is what the beams hit: few points beyond its centre.
    assert np.mean(np.hypot(tree["x"], tree["y"]) > math.hypot(3.96, 1.0)) < 0.25


def test_motion_during_the_scan_is_in_the_points():
    """Driving at 2 m/s towards a wall 10 m ahead, each firing sees the wall from where
    the robot is at that instant: over one 0.1 s scan the wall's x spreads by ~0.2 m."""
    scene = Scene()
    wall = np.array([[10, -30, -5], [10, 30, -5], [10, 30, 10], [10, -30, 10]], dtype=float)
    scene.add(wall, np.array([[0, 1, 2], [0, 2, 3]]), label=1)
    settings = LidarSettings(range_sigma_m=0.0, dropout=0.0)

    def driving(t):
        return t / 1e9 * 2.0, np.zeros(t.shape), np.zeros(t.shape), np.zeros(t.shape)

    def wall_spread(trajectory):
        scans, _, _ = decode(Vlp16Emulator(scene, DEFAULT_T_BASE_LIDAR, settings), trajectory, 0.5)
        p = scans[2].points
        ahead = p[np.abs(p["y"]) < 0.5]  # facing the wall, where x is the distance to it
        return ahead["x"].max() - ahead["x"].min()

    assert wall_spread(standing_still()) < 0.01
    assert wall_spread(driving) == pytest.approx(0.2, abs=0.03)


def test_grid_orchard_sizes_follow_the_paper():
    specs = grid_orchard(2, 3, 5.0, 4.0, np.random.default_rng(0))
    assert [s.tree_id for s in specs] == ["R1T1", "R1T2", "R1T3", "R2T1", "R2T2", "R2T3"]
    assert all(2.6 <= 2 * s.crown_radius <= 2.8 for s in specs)
