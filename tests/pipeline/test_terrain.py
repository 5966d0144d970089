"""The terrain model on ground shaped as groves are: a VLP-16 scan ray-cast by the twin's
emulator over a sloped, undulating height field with trees on it, from a robot standing
level and from a robot pitched and rolled by the slope it stands on."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.terrain import TREES, RollingGround, high_mount, one_scan, rotation
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline.classify import FLOATING
from treetraits.pipeline.config import DetectionConfig, TerrainConfig
from treetraits.pipeline.detection import crop_mask, detect, to_base
from treetraits.pipeline.terrain import (
    SEED_PAST_LOWEST_RING_M,
    TerrainGrid,
    _gaussian,
    _gaussian_weights,
    fit_terrain,
    lowest_ring_reach,
    seed_radius,
)


def ground_truth_in_base(ground, tilt: np.ndarray, x: float, y: float) -> float:
    """The ground height under (x, y) of the robot's tilted base frame."""
    z = 0.0
    for _ in range(20):  # p_world = tilt @ p_base; solve z_world(p) = ground(x_w, y_w)
        world = tilt @ np.array([x, y, z])
        z += float(ground.height(world[0], world[1])) - world[2]
    return z


@pytest.mark.parametrize("pitched", [False, True], ids=["level-lidar", "pitched-robot"])
def test_terrain_follows_slope_and_furrows(pitched):
    ground = RollingGround()
    tilt = np.eye(3)
    if pitched:  # the robot's attitude on this slope: nose up, left side up
        tilt = rotation(math.atan(ground.across), -math.atan(ground.along))
    scan = one_scan(ground, tilt if pitched else None)
    config = DetectionConfig()
    xyz = to_base(scan.points, DEFAULT_T_BASE_LIDAR)
    xyz = xyz[crop_mask(xyz, config.crop, DEFAULT_T_BASE_LIDAR[:2, 3])]
    terrain = fit_terrain(xyz, config.terrain, config.crop.x_m, config.crop.y_m)

    # Every cell taken for ground lies on the true ground: what the model says under the
    # returns it kept matches the surface to within the range noise and the cell's tilt.
    centres = [
        (terrain.x0 + (i + 0.5) * terrain.cell, terrain.y0 + (j + 0.5) * terrain.cell)
        for i, j in np.argwhere(terrain.ground)
    ]
    errors = np.array(
        [terrain.z_at(x, y) - ground_truth_in_base(ground, tilt, x, y) for x, y in centres]
    )
    assert len(errors) > 150
    # Measured: RMS 4.6 cm (level LiDAR) and 3.8 cm (pitched robot); the worst cells,
    # 0.24-0.28 m, hold a trunk's foot and no soil.
    assert np.sqrt(np.mean(errors**2)) < 0.09
    assert np.abs(errors).max() < 0.5

    # Under each trunk the terrain is the ground, not the skirt: the tree's height
    # rests on it. Measured: within 0.15 m on both robots (a trunk's foot).
    for spec in TREES:
        x, y = spec.x, spec.y
        if pitched:
            x, y, _ = np.linalg.solve(tilt, np.array([spec.x, spec.y, ground.height(x, y)]))
        truth = ground_truth_in_base(ground, tilt, x, y)
        assert terrain.z_at(x, y) == pytest.approx(truth, abs=0.3), spec.tree_id


@pytest.mark.parametrize("pitched", [False, True], ids=["level-lidar", "pitched-robot"])
def test_each_tree_is_one_cluster_and_no_ground_clusters(pitched):
    ground = RollingGround()
    tilt = rotation(math.atan(ground.across), -math.atan(ground.along)) if pitched else None
    scan = one_scan(ground, tilt)
    detection = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    tall = [c for c in detection.clusters if c.points[:, 2].max() - c.ground_z > 0.5]
    # One cluster per tree, 1.2-2.8 m tall (crowns of 2.3-2.8 m, seen by one scan);
    # measured: no other cluster on the pitched robot, and on the level LiDAR two slivers
    # of upslope ground 11 m out, 0.3-0.4 m tall (the classifier's height rule's job).
    assert len(tall) == len(TREES)
    for spec in TREES:
        near = [c for c in tall if math.hypot(c.centroid[0] - spec.x, c.centroid[1] - spec.y) < 2]
        assert len(near) == 1, spec.tree_id
    if pitched:
        assert len(detection.clusters) == len(TREES)

    # The ground under each tree's cluster: measured within 0.15 m.
    frame = tilt if pitched else np.eye(3)

    def ground_errors(clusters):
        return [
            abs(c.ground_z - ground_truth_in_base(ground, frame, *c.centroid[:2])) for c in clusters
        ]

    assert max(ground_errors(tall)) < 0.3


@pytest.mark.parametrize("mount_m", [1.7, 2.6], ids=["bonnet-1.7m", "cab-2.6m"])
def test_a_lidar_mounted_high_seeds_the_ground_on_the_ground(mount_m):
    """A LiDAR on a tractor, 1.7 m up (its bonnet) or 2.6 m (its cab), over level,
    furrowed ground: its lowest beam meets the ground 6.3 or 9.7 m out, beyond the
    Jackal's 6 m seed disc, where only the near crowns' skirts were (before, the ground
    was seeded on them, 1 m up). The ground is seeded on the ground: under each trunk the
    terrain is the ground, and each tree is one cluster on it, the near crowns, whose
    bases the lowest beam cuts (nothing under them in view), not judged floating.
    (Level: inside the disc no beam reaches, the ground is filled from around it, which
    on the 15 % slope puts the foot of a tree 6 m downhill 1.1-1.7 m high: docs.)"""
    ground = RollingGround(along=0.0, across=0.0)
    mount = high_mount(mount_m)
    scan = one_scan(ground, mount_height_m=mount_m)
    detection = detect(scan.points, None, mount, DetectionConfig())
    tall = [c for c in detection.clusters if c.points[:, 2].max() - c.ground_z > 0.5]
    for spec in TREES:
        truth = float(ground.height(spec.x, spec.y))
        assert detection.ground.z_at(spec.x, spec.y) == pytest.approx(truth, abs=0.3)
        near = [c for c in tall if math.hypot(c.centroid[0] - spec.x, c.centroid[1] - spec.y) < 2]
        assert len(near) == 1, spec.tree_id
        assert near[0].verdict != FLOATING, spec.tree_id


def test_the_seed_disc_reaches_past_where_the_lowest_beam_meets_the_ground():
    """The VLP-16's -15 deg beam from 0.44 m (the Jackal) lands 1.7 m out: the configured
    6 m disc stands. From 2.6 m it lands 9.7 m out, and the disc reaches 2 m past it. A
    mount pitched down 10 deg lands nearest ahead (5.6 m) and farthest behind (30 m):
    the median over the bearings, about where it lands to the sides, counts. One tilted
    up 20 deg never brings that beam down ahead; behind and to the sides it does."""
    low = math.radians(-15.0)
    config = TerrainConfig()
    jackal = lowest_ring_reach(low, DEFAULT_T_BASE_LIDAR)
    height = DEFAULT_T_BASE_LIDAR[2, 3]
    # (the LiDAR 4 cm ahead of the footprint: 4 cm nearer ahead, farther behind)
    assert jackal == pytest.approx(height / math.tan(math.radians(15)), abs=0.05)
    assert seed_radius(config, jackal) == config.seed_radius_m
    cab = lowest_ring_reach(low, high_mount(2.6))
    cab_disc = 2.6 / math.tan(math.radians(15)) + SEED_PAST_LOWEST_RING_M
    assert seed_radius(config, cab) == pytest.approx(cab_disc, abs=0.05)
    pitched = high_mount(2.6)
    pitched[:3, :3] = rotation(0.0, math.radians(10))  # nose down: the beams ahead fall
    sideways = 2.6 / math.tan(math.radians(15))
    assert lowest_ring_reach(low, pitched) == pytest.approx(sideways, rel=0.15)
    up = high_mount(2.6)
    up[:3, :3] = rotation(0.0, math.radians(-20))
    assert lowest_ring_reach(low, up) == pytest.approx(sideways, rel=0.15)
    assert lowest_ring_reach(low, high_mount(0.0)) is None
    assert seed_radius(config, None) == config.seed_radius_m


def test_flat_ground_without_returns_near_the_robot_is_the_footprint():
    """No return at all (a blind scan): the terrain is the footprint's plane, z = 0."""
    terrain = fit_terrain(np.zeros((0, 3)), TerrainConfig(), (-15, 15), (-15, 15))
    assert terrain.z_at(3.0, -7.0) == 0.0 and terrain.ground_cells == 0


def test_a_lone_low_return_across_a_gap_is_not_ground():
    """A post's foot 10 m out, hit by a level ring with no ground around it, is not taken
    for ground: the ground there is the ground around the robot carried out."""
    rng = np.random.default_rng(3)
    angle = rng.uniform(0, 2 * math.pi, 4000)
    radius = rng.choice([1.5, 1.7, 2.1, 2.5, 3.3, 4.6], 4000)
    near = np.column_stack([radius * np.cos(angle), radius * np.sin(angle), np.zeros(4000)])
    post = np.column_stack([np.full(30, 10.0), np.full(30, 0.0), np.linspace(0.3, 1.5, 30)])
    terrain = fit_terrain(np.vstack([near, post]), TerrainConfig(), (-15, 15), (-15, 15))
    assert terrain.z_at(10.0, 0.0) == pytest.approx(0.0, abs=0.02)


@pytest.mark.parametrize("shape", [(60, 60), (7, 3), (1, 5), (5, 1), (1, 1)])
def test_one_points_ground_is_the_arrays_to_the_bit(shape):
    """`z_at` of one point at a time against the same points as an array, at random
    spots and on cell centres, inside the grid and clamped outside it."""
    rng = np.random.default_rng(1)
    ones = np.ones(shape, dtype=bool)
    grid = TerrainGrid(-15.0, -15.0, 0.5, rng.normal(0, 1, shape), ones, ones)
    x, y = rng.uniform(-20, 20, 2000), rng.uniform(-20, 20, 2000)
    x[:50] = -14.75 + 0.5 * np.arange(50)
    each = np.array([grid.z_at(a, b) for a, b in zip(x, y, strict=True)])
    assert isinstance(grid.z_at(x[0], y[0]), float)
    assert np.array_equal(each.view(np.int64), grid.z_at(x, y).view(np.int64))


def test_the_fills_gaussian_is_scipys_to_the_bit():
    """`_gaussian` with cached weights against scipy.ndimage.gaussian_filter, at the fill's
    widths and past the grid's size, on sparse ground as the fill sees it."""
    from scipy import ndimage

    rng = np.random.default_rng(2)
    for shape in [(60, 60), (7, 3), (1, 1)]:
        known = rng.random(shape) < 0.3
        values = np.where(known, rng.normal(0, 0.3, shape), 0.0)
        for sigma in (2.0, 4.0, 8.0, 64.0, 0.7):
            want = ndimage.gaussian_filter(values, sigma, mode="constant", truncate=3.0)
            got = _gaussian(values, _gaussian_weights(sigma, 3.0))
            assert np.array_equal(got.view(np.int64), want.view(np.int64))
