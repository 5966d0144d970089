"""Width and height: the paper's rules on shapes with known answers, our robust estimator,
and both against `measure_truth` on the twin drive past the 2 x 3 grid (clean, with
stray returns, with noisy poses)."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from tests.helpers.traits import every_slice_width
from tests.helpers.twin import ghost_returns, grid_drive, mapped, match
from treetraits.pipeline.config import MapperConfig, TraitsConfig
from treetraits.pipeline.mapper import TreeMapper
from treetraits.pipeline.traits import PaperTraits, RobustTraits, caliper, new_traits, slice_width

CONFIG = TraitsConfig()


def ring(radius, z, n=72, centre=(0.0, 0.0)):
    angle = np.arange(n) * 2 * math.pi / n
    return np.column_stack(
        [centre[0] + radius * np.cos(angle), centre[1] + radius * np.sin(angle), np.full(n, z)]
    )


# --- the paper's rules --------------------------------------------------------------------


def test_slice_width_is_the_widest_slice():
    # A "tree": a trunk (r 0.1) under a crown whose widest ring (r 1.3) is mid-height.
    shape = np.vstack(
        [ring(0.1, z) for z in (0.0, 0.2, 0.4)]
        + [ring(r, z) for r, z in ((0.8, 0.6), (1.3, 1.4), (0.9, 2.2), (0.2, 2.6))]
    )
    assert slice_width(shape, 10) == pytest.approx(2.6, rel=1e-3)


def test_slice_width_measures_within_slices_only():
    # The farthest pair of the whole set spans two slices: it is not a slice's width.
    points = np.array([[0.0, 0, 0.0], [0.5, 0, 0.05], [3.0, 0, 10.0], [3.4, 0, 9.95]])
    assert slice_width(points, 10) == pytest.approx(math.hypot(0.5, 0.05))
    # In one slice the pair is 3D: 1.2 apart in x and 0.2 in z.
    assert slice_width(np.array([[0.0, 0, 0.0], [1.2, 0, 0.2]]), 1) == pytest.approx(
        math.hypot(1.2, 0.2)
    )
    assert slice_width(np.zeros((1, 3))) == 0.0


def test_slice_width_skips_only_slices_that_cannot_win():
    """The bounds decide which slices are measured, never the answer: the same width as
    measuring every slice, on crowns of every size, with and without a kept maximum, and
    on sets where slices hold one point or stand on one spot."""
    rng = np.random.default_rng(3)
    for trial in range(200):
        n = int(rng.integers(2, 1500))
        points = rng.normal(size=(n, 3)) * rng.uniform(0.05, 2.0, size=3)
        if trial % 4 == 1:
            points[:, :2] = 0.25  # a column: every slice's extent is nil
        if trial % 4 == 2:
            points[:, 2] = np.round(points[:, 2], 1)  # points on slice edges
        truth = every_slice_width(points, 10, 0.0)
        assert slice_width(points, 10) == truth
        for floor in (0.5 * truth, truth, 1.5 * truth):
            assert slice_width(points, 10, floor) == every_slice_width(points, 10, floor)
        assert slice_width(points, 3) == every_slice_width(points, 3, 0.0)


def test_height_is_registered_when_the_top_ring_changes_and_the_maximum_kept():
    traits = PaperTraits(CONFIG)
    cloud = ring(1.0, 1.0)

    def observe(top_z, top_ring, ground=0.0):
        points = np.vstack([cloud, [[0.0, 0.0, top_z]]])
        rings = np.concatenate([np.full(len(cloud), 3), [top_ring]])
        traits.observe(points, rings, ground)
        return traits.height

    assert observe(2.0, 10) == pytest.approx(2.0)  # first sight registers
    assert observe(2.5, 10) == pytest.approx(2.0)  # same top ring: nothing registered
    assert observe(2.3, 11) == pytest.approx(2.3)  # the ring changed: 2.3 registered
    assert observe(2.1, 12) == pytest.approx(2.3)  # registered, but the maximum stays
    assert observe(2.6, 11, ground=0.2) == pytest.approx(2.4)  # above the local ground
    assert traits.width == pytest.approx(2.0, rel=1e-3)  # the ring r 1.0, the widest


def test_width_is_the_largest_that_two_scans_reached():
    """The paper's maximum over scans, confirmed: a width one scan alone saw (a
    neighbour's crown joined for a scan) does not count; `width_confirm_scans` 1 is the
    paper's plain maximum."""
    traits = PaperTraits(CONFIG)
    traits.observe(ring(1.0, 1.0), np.zeros(72, dtype=np.uint8), 0.0)
    assert traits.width == pytest.approx(2.0, rel=1e-3)  # one scan: the best there is
    for radius in (1.4, 1.2, 2.5):  # 2.5: a 5 m "crown" in one scan
        traits.observe(ring(radius, 1.0), np.zeros(72, dtype=np.uint8), 0.0)
    assert traits.width == pytest.approx(2.8, rel=1e-3)
    other = PaperTraits(CONFIG)
    other.observe(ring(1.5, 3.0), np.zeros(72, dtype=np.uint8), 0.0)
    traits.absorb(other)  # a track of the same tree: its scans count with ours
    assert traits.width == pytest.approx(3.0, rel=1e-3) and traits.height == pytest.approx(3.0)
    plain = PaperTraits(dataclasses.replace(CONFIG, width_confirm_scans=1))
    for radius in (1.0, 1.4, 1.2):
        plain.observe(ring(radius, 1.0), np.zeros(72, dtype=np.uint8), 0.0)
    assert plain.width == pytest.approx(2.8, rel=1e-3)


# --- the robust estimator -------------------------------------------------------------


def crown_scans(rng, scans=6, radius=1.3, centre=(5.0, 2.0, 1.6), n=3000):
    """The near half of a spherical crown as several scans would sample it."""
    out = []
    for _ in range(scans):
        d = rng.normal(size=(n, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[d[:, 1] < 0.2]  # the side facing the robot, and its outline
        out.append(np.asarray(centre) + radius * d)
    return out


def test_robust_measures_the_cells_seen_in_several_scans():
    rng = np.random.default_rng(0)
    traits = RobustTraits(CONFIG)
    for points in crown_scans(rng):
        traits.observe(None, None, 0.0, points, 0.0)
    assert traits.width == pytest.approx(2.6, rel=0.03)
    assert traits.height == pytest.approx(1.6 + 1.3, abs=0.06)
    # The centre of the extents: right along the row, pulled towards the robot across it
    # (only the near half was seen).
    centre = traits.centre()
    assert centre[0] == pytest.approx(5.0, abs=0.1) and 0.7 < centre[1] < 2.0
    # A stray return far out, once: ignored. The same cell hit in three scans: a surface.
    for _ in range(2):
        traits.observe(None, None, 0.0, np.array([[5.0, -1.0, 4.5]]), 0.0)
    assert traits.height == pytest.approx(2.9, abs=0.06)
    traits.observe(None, None, 0.0, np.array([[5.0, -1.0, 4.5]]), 0.0)
    assert traits.height == pytest.approx(4.5, abs=0.06)


def test_robust_cells_are_each_cells_first_return_and_scan_count():
    """The grid kept scan by scan (merged into, the centre asked in between) is, cell for
    cell, the definition: the first return that fell in each cell and the number of
    scans that hit it."""
    rng = np.random.default_rng(4)
    traits = RobustTraits(CONFIG)
    scans = [s + rng.normal(0, 0.02, s.shape) for s in crown_scans(rng)]
    for points in scans:
        traits.observe(None, None, 0.0, points, 0.0)
        traits.centre()
    first: dict[tuple, np.ndarray] = {}
    hits: dict[tuple, int] = {}
    for points in scans:
        keys = [tuple(c) for c in np.floor(points / CONFIG.voxel_m).astype(int)]
        for cell, point in zip(keys, points, strict=True):
            first.setdefault(cell, point)
        for cell in set(keys):
            hits[cell] = hits.get(cell, 0) + 1
    points, counts = traits.cells()
    got = {
        tuple(c): (p, n)
        for c, p, n in zip(
            np.floor(points / CONFIG.voxel_m).astype(int), points, counts, strict=True
        )
    }
    assert got.keys() == first.keys()
    assert all(np.array_equal(got[c][0], first[c]) and got[c][1] == hits[c] for c in first)


def test_robust_height_is_above_the_median_ground():
    rng = np.random.default_rng(1)
    traits = RobustTraits(CONFIG)
    for points, ground in zip(crown_scans(rng), (0.3, 0.3, 0.3, 0.3, 5.0, 0.3), strict=True):
        traits.observe(None, None, 0.0, points + np.array([0, 0, 0.3]), ground)
    assert traits.height == pytest.approx(2.9, abs=0.06)


def test_robust_memory_is_bounded():
    rng = np.random.default_rng(2)
    traits = RobustTraits(dataclasses.replace(CONFIG, max_points=500))
    for points in crown_scans(rng, scans=4):
        traits.observe(None, None, 0.0, points, 0.0)
    points, hits = traits.cells()
    assert len(points) <= 500 and traits.voxel > CONFIG.voxel_m
    assert hits.sum() > 4 * len(points) * 0.5  # the hits were summed, not lost
    assert traits.width == pytest.approx(2.6, rel=0.1)


def test_robust_absorb_sums_the_hits():
    rng = np.random.default_rng(3)
    one, two = RobustTraits(CONFIG), RobustTraits(CONFIG)
    scans = crown_scans(rng, scans=4)
    for points in scans[:2]:
        one.observe(None, None, 0.0, points, 0.0)
    for points in scans[2:]:
        two.observe(None, None, 0.0, points, 0.0)
    assert math.isnan(one.width) or one.width < 2.4  # two scans: few cells seen 3 times
    one.absorb(two)
    assert one.width == pytest.approx(2.6, rel=0.03)


def test_caliper_finds_the_longest_extent():
    corners = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0], [0.0, 3.0]])
    width, centre = caliper(corners, 36)
    assert width == pytest.approx(5.0, rel=0.002)  # the diagonal, to 5 deg bearings
    assert centre == pytest.approx([2.0, 1.5])


def test_trait_method_is_chosen_by_config():
    assert isinstance(new_traits(TraitsConfig(method="paper")), PaperTraits)
    assert isinstance(new_traits(TraitsConfig(method="robust")), RobustTraits)


# --- on the twin, against measure_truth -----------------------------------------------------


def errors(mapper: TreeMapper) -> dict[str, tuple[float, float]]:
    """Signed width and height error (%) of each true tree's match (the one with the
    most observations: stray returns make a few one-scan trees)."""
    truth = grid_drive().truth
    found, _ = match(mapper.trees(), truth)
    out = {}
    for t in truth:
        tree = max(found[t.tree_id], key=lambda tree: tree.observations)
        out[t.tree_id] = (
            100 * (tree.width_m - t.width) / t.width,
            100 * (tree.height_m - t.height) / t.height,
        )
    return out


def passed(tree_id: str) -> bool:
    """Front and middle trees (x = 0 and 5): seen near and whole. The back ones (x = 10)
    only from 9.5-15 m, mostly hidden behind the middle ones."""
    return not tree_id.endswith("T3")


@pytest.mark.parametrize("method", ["paper", "robust"])
def test_traits_within_tolerance_of_the_truth(method):
    """Tolerances: front/middle width and height within 5 %; back trees width within 30 %
    (occluded: both methods see only the part that sticks out) and height within 10 %;
    over all six, MAPE at most the paper's worst simulated case (12.1 % / 14.7 %).
    Measured and reported in docs/pipeline.md."""
    mapper, _ = mapped(method)
    err = errors(mapper)
    for tree_id, (width, height) in err.items():
        if passed(tree_id):
            assert abs(width) < 5 and abs(height) < 5, (tree_id, width, height)
        else:
            assert abs(width) < 30 and abs(height) < 10, (tree_id, width, height)
        assert height < 2  # the top is only ever seen from below
    assert np.mean([abs(w) for w, _ in err.values()]) < 12.1
    assert np.mean([abs(h) for _, h in err.values()]) < 14.7


@pytest.mark.parametrize("method", ["paper", "robust"])
def test_a_height_called_measured_is_within_5_percent_of_the_truth(method):
    """`height_top_seen`: the front trees' tops came under the beams of the approach from
    9.5 m, and each ray that passed over them bounds them from above: called measured
    (1.5-2.6 % low, measured). The others (seen from beside, or from behind the middle
    trees) were never bracketed within 5 %: lower bounds, among them the one 6.9 % low."""
    mapper, _ = mapped(method)
    truth = {t.tree_id: t for t in grid_drive().truth}
    found, _ = match(mapper.trees(), list(truth.values()))
    measured = set()
    for tree_id, trees in found.items():
        tree = max(trees, key=lambda tree: tree.observations)
        if tree.height_top_seen:
            measured.add(tree_id)
            assert abs(tree.height_m / truth[tree_id].height - 1) <= 0.05, tree_id
    assert measured >= {"R1T1", "R2T1"}


@functools.cache
def ghost_run(method: str) -> TreeMapper:
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(traits=TraitsConfig(method=method)), data.calibration)
    for scan, pose in zip(ghost_returns(data.scans, 0.02), data.poses, strict=True):
        mapper.process(scan, None, pose)
    return mapper


def test_robust_shrugs_off_stray_returns_that_the_maximum_keeps():
    paper, robust = errors(ghost_run("paper")), errors(ghost_run("robust"))
    near = [tree_id for tree_id in paper if passed(tree_id)]
    for tree_id in near:
        assert abs(robust[tree_id][0]) < 5, (tree_id, robust[tree_id])
    assert max(paper[t][0] for t in near) > 5  # the paper's maximum took a stray
    assert np.mean([abs(robust[t][0]) for t in near]) < np.mean([abs(paper[t][0]) for t in near])


def test_robust_with_rtk_grade_pose_noise():
    """2 cm and 0.2 deg white noise on every pose (an RTK fix with its heading): the
    accumulated cloud smears by about that much, the widths stay within 5 %."""
    data = grid_drive()
    rng = np.random.default_rng(4)
    mapper = TreeMapper(MapperConfig(traits=TraitsConfig(method="robust")), data.calibration)
    for scan, pose in zip(data.scans, data.poses, strict=True):
        noisy = dataclasses.replace(
            pose,
            x=pose.x + rng.normal(0, 0.02),
            y=pose.y + rng.normal(0, 0.02),
            yaw=pose.yaw + rng.normal(0, math.radians(0.2)),
        )
        mapper.process(scan, None, noisy)
    for tree_id, (width, height) in errors(mapper).items():
        if passed(tree_id):
            assert abs(width) < 5 and abs(height) < 5, (tree_id, width, height)


def test_an_outline_placed_under_a_better_pose_replaces_the_one_placed_under_float():
    """A crown seen for 6 scans under an RTK float pose (sigma 0.25 m) that put it 0.5 m
    east, then 6 under a fixed one (0.02 m): the outline of both is 0.5 m wider and centred
    between; the finer outline started with the first fixed scan replaces it once it has
    half its counted cells. The height seen under float stands (the error is horizontal)."""
    rng = np.random.default_rng(3)
    # Seen from afar under float, the top (3.4 m here); close by under fixed, not.
    top = np.array([[5.5, 2.0, 3.4]])
    float_scans = [np.vstack([p + np.array([0.5, 0.0, 0.0]), top]) for p in crown_scans(rng)]
    fixed_scans = crown_scans(rng)

    def outline(sigmas: tuple[float | None, float | None]) -> RobustTraits:
        traits = RobustTraits(CONFIG)
        for scans, sigma in zip((float_scans, fixed_scans), sigmas, strict=True):
            for points in scans:
                traits.observe(None, None, 0.0, points, 0.0, sigma)
        return traits

    mixed = outline((None, None))  # no pose sigma known: every cell counts
    assert mixed.width == pytest.approx(3.1, rel=0.03)
    assert mixed.centre()[0] == pytest.approx(5.25, abs=0.1)
    finer = outline((0.25, 0.02))
    assert finer.width == pytest.approx(2.6, rel=0.03)
    assert finer.centre()[0] == pytest.approx(5.0, abs=0.1)
    assert finer.height == pytest.approx(mixed.height, abs=1e-9)
    assert finer.height == pytest.approx(3.4, abs=0.06)
    # Poses a cell or better throughout (RTK fixed, 2-5 cm): nothing to replace.
    fixed_only = outline((0.05, 0.02))
    assert fixed_only.width == pytest.approx(mixed.width, abs=1e-9)
