"""TreeMapper end to end on the digital twin: VLP-16 packets emulated along a path through
an orchard of known trees, decoded by our batcher, a Survey3N frame rendered per scan,
and exact poses from the path in `odom`. Every tree must be found once, where it stands,
with foliage NDVI; and the edge cases: first tree, one tree, touching crowns, nothing
but ground, an empty scan, no frame, no pose, a heading other than east."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from tests.helpers.twin import drive, grid_drive, mapped, match
from treetraits.drivers.calibration import Calibration
from treetraits.drivers.records import POINT_DTYPE
from treetraits.pipeline.config import MapperConfig, TrackingConfig, TraitsConfig
from treetraits.pipeline.mapper import (
    SIDES_MARGIN_DEG,
    TreeMapper,
    _Centres,
    _Tree,
    row_direction,
    sides_seen,
    trunk_position,
)
from treetraits.pipeline.tracking import Motion
from treetraits.sim.camera import FOLIAGE
from treetraits.sim.orchard import (
    TreeSpec,
    grid_orchard,
)


def assert_each_found_once(trees, truth, reach=None):
    """No strays; every true tree found exactly once (those farther than `reach` m from
    the path's end, never in the crop box, at most once). Counted: what the outputs call
    trees (kind "tree"); a fragment judged a post for a scan is a rejected object."""
    found, stray = match([t for t in trees if t.kind == "tree"], truth)
    assert stray == []
    for t in truth:
        count = len(found[t.tree_id])
        assert count <= 1, t.tree_id
        if reach is None or math.hypot(t.x - reach[0], t.y - reach[1]) < reach[2]:
            assert count == 1, t.tree_id


def ndvi_of(bands) -> float:
    red, _, nir = bands
    return (nir - red) / (nir + red)


# --- the straight drive past the 2 x 3 grid --------------------------------------------


@pytest.mark.parametrize("method", ["paper", "robust"])
def test_every_tree_is_found_once_where_it_stands(method):
    data = grid_drive()
    assert len(data.scans) >= 195  # ~20 s at 10 Hz
    mapper, _ = mapped(method)
    trees = mapper.trees()
    found, stray = match(trees, data.truth)
    assert stray == []
    assert {k: len(v) for k, v in found.items()} == {t.tree_id: 1 for t in data.truth}
    # Position: both methods report the centre of the accumulated crown outline (the
    # paper's looser limit dates from when it reported the Kalman state, the centroid of
    # the visible near face).
    limit = {"paper": 0.8, "robust": 0.6}[method]
    for truth in data.truth:
        tree = found[truth.tree_id][0]
        assert math.hypot(tree.x - truth.x, tree.y - truth.y) < limit, truth.tree_id
        assert tree.frame == "odom" and tree.traits == method
        assert tree.observations > 100
        assert data.poses[0].t <= tree.first_seen < tree.last_seen <= data.poses[-1].t


def test_trees_carry_the_ndvi_of_foliage():
    mapper, results = mapped("paper")
    foliage = ndvi_of(FOLIAGE)
    assert all(r.ndvi == "ok" for r in results)
    found, _ = match(mapper.trees(), grid_drive().truth)
    for truth in grid_drive().truth:
        (tree,) = found[truth.tree_id]
        if truth.x < 7:  # front and middle: seen whole, near
            assert tree.ndvi == pytest.approx(foliage, abs=0.04)
        else:  # back: seen past the middle crowns, its outline mixes in soil and sky
            assert 0.55 < tree.ndvi < foliage
    with_ndvi = [c for r in results for c in r.clusters if np.isfinite(c.ndvi)]
    assert len(with_ndvi) > 300  # the camera sees forward: clusters ahead have NDVI


def test_scan_results_tell_what_happened_to_each_cluster():
    _, results = mapped("paper")
    first = results[0]
    assert first.frame == "odom" and first.ground.fitted
    # The first trees (nothing to compare with); a piece of a crown split off by the
    # clustering starts a tree that the merge folds into its own at once.
    assert {c.outcome for c in first.clusters} <= {"created", "merged"}
    assert all(math.isnan(c.p_max) for c in first.clusters)
    assert first.created == [c.tree_id for c in first.clusters if c.outcome == "created"]
    assert len(first.created) >= 4
    later = results[100]
    assert later.updated and all(c.tree_id is not None for c in later.clusters)
    for c in later.clusters:
        if c.outcome == "updated":
            assert c.p_max > 0.5 and c.entropy < 0.8
        assert c.hull_volume > 0 and c.num_points >= 10
    # Many tree clusters fail the paper's gate (a 7 % change in the count of points is
    # enough) and start a tree that the merge folds back at once (docs): measured 410
    # merged against 560 updated since the understorey is cut off the crowns (a third
    # before), and the understorey's own pieces (low) are merged into their tree.
    outcomes = [c.outcome for r in results for c in r.clusters]
    crowns = [c.outcome for r in results for c in r.clusters if c.cluster.verdict == "tree"]
    assert crowns.count("updated") > 1.2 * crowns.count("merged")
    assert outcomes.count("created") < 20
    known = {t.tree_id for t in mapped("paper")[0].trees()}
    ids = {c.tree_id for r in results for c in r.clusters if c.outcome != "duplicate"}
    assert known <= ids
    for r in results:  # every id a scan reports exists after that scan (merges resolved)
        assert set(r.created) | set(r.updated) >= {c.tree_id for c in r.clusters}
    # Centroids are reported in odom: each lies within a crown of a true tree.
    truth = grid_drive().truth
    for r in results[::20]:
        for c in r.clusters:
            gap = min(math.hypot(c.centroid[0] - t.x, c.centroid[1] - t.y) for t in truth)
            assert gap < 1.6


def test_same_input_same_output():
    data = grid_drive()

    def run():
        mapper = TreeMapper(MapperConfig(), data.calibration)
        for s, f, p in zip(data.scans[:40], data.frames[:40], data.poses[:40], strict=True):
            mapper.process(s, f, p)
        return mapper.trees()

    assert run() == run()


def test_without_a_camera_the_same_trees_without_ndvi():
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(), data.calibration)
    results = [mapper.process(s, None, p) for s, p in zip(data.scans, data.poses, strict=True)]
    assert {r.ndvi for r in results} == {"no_frame"}
    found, stray = match(mapper.trees(), data.truth)
    assert stray == [] and all(len(v) == 1 for v in found.values())
    assert all(t.ndvi is None for t in mapper.trees())
    # A frame given to a mapper whose calibration has no camera is set aside, not fatal.
    blind = TreeMapper(MapperConfig(), Calibration())
    assert blind.process(data.scans[0], data.frames[0], data.poses[0]).ndvi == "no_camera"


@pytest.mark.parametrize("motion", [None, Motion(0.5, 0.0)])
def test_without_poses_trees_are_held_in_the_lidar_frame(motion):
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(), data.calibration)
    for scan in data.scans[:80]:
        result = mapper.process(scan, None, None, motion=motion)
    assert result.frame == "lidar"
    trees = mapper.trees()
    assert all(t.frame == "lidar" for t in trees)
    # Positions are in the last scan's LiDAR frame: put them in odom to compare.
    pose, lidar = data.poses[79], data.calibration.T_base_lidar[:3, 3]
    in_odom = [dataclasses.replace(t, x=t.x + pose.x + lidar[0], y=t.y + pose.y) for t in trees]
    assert_each_found_once(in_odom, data.truth, reach=(pose.x, pose.y, 14.0))
    assert len(in_odom) >= 4


def test_robust_traits_without_poses_follow_the_motion():
    """Without poses the robust traits accumulate where the motion says the first scan's
    LiDAR frame is: with the drive's true motion they match the run with poses."""
    data = grid_drive()
    config = MapperConfig(traits=TraitsConfig(method="robust"))
    with_poses = TreeMapper(config, data.calibration)
    dead_reckoned = TreeMapper(config, data.calibration)
    for scan, pose in zip(data.scans[:80], data.poses[:80], strict=True):
        with_poses.process(scan, None, pose)
        dead_reckoned.process(scan, None, None, motion=Motion(0.5, 0.0))
    pose, lidar = data.poses[79], data.calibration.T_base_lidar[:3, 3]
    for a, b in zip(with_poses.trees(), dead_reckoned.trees(), strict=True):
        assert b.width_m == pytest.approx(a.width_m, rel=0.03)
        assert b.height_m == pytest.approx(a.height_m, abs=0.05)
        assert b.x + pose.x + lidar[0] == pytest.approx(a.x, abs=0.1)
        assert b.y + pose.y == pytest.approx(a.y, abs=0.1)


def test_a_run_keeps_one_frame():
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(), data.calibration)
    mapper.process(data.scans[0], None, data.poses[0])
    with pytest.raises(ValueError, match="odom"):
        mapper.process(data.scans[1], None, dataclasses.replace(data.poses[1], frame="utm"))
    with pytest.raises(ValueError, match="no pose"):
        mapper.process(data.scans[1], None, None)


def test_heading_north_maps_the_same_trees():
    """The grid turned by 90 deg and driven north (yaw = pi/2): a wrong rotation would
    put every tree on the wrong side of the path."""
    specs = [
        dataclasses.replace(s, x=s.y, y=s.x)
        for s in grid_orchard(2, 3, 5.0, 5.0, np.random.default_rng(1))
    ]
    data = drive(specs, start=(2.5, -9.5), heading=math.pi / 2, speed=0.5, seconds=8.0, seed=5)
    mapper = TreeMapper(MapperConfig(), data.calibration)
    for scan, pose in zip(data.scans, data.poses, strict=True):
        mapper.process(scan, None, pose)
    last = data.poses[-1]
    assert_each_found_once(mapper.trees(), data.truth, reach=(last.x, last.y, 14.0))
    assert len(mapper.trees()) >= 4


# --- the sides a crown was seen from ----------------------------------------------------


@pytest.mark.parametrize("method", ["paper", "robust"])
def test_a_pass_along_one_side_of_each_row_leaves_every_width_one_sided(method):
    """The grid drive runs down the lane between the two rows: each row is seen from
    that lane only, so no crown's far side was in view."""
    trees = [t for t in mapped(method)[0].trees() if t.kind == "tree"]
    assert len(trees) == 6
    assert [t.width_sides_seen for t in trees] == [1] * 6


def test_without_poses_the_sides_are_judged_in_the_dead_reckoned_frame():
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(), data.calibration)
    for scan in data.scans[:80]:
        mapper.process(scan, None, None, motion=Motion(0.5, 0.0))
    trees = [t for t in mapper.trees() if t.kind == "tree"]
    assert trees and all(t.width_sides_seen == 1 for t in trees)


def _shifted(drive_data, ns: int):
    """A drive's scans and poses `ns` later on the host clock."""
    scans = [dataclasses.replace(s, t_host=s.t_host + ns) for s in drive_data.scans]
    poses = [dataclasses.replace(p, t=p.t + ns) for p in drive_data.poses]
    return scans, poses


def test_a_row_passed_on_both_sides_has_its_crowns_seen_from_both():
    """One row (y = 0) of two citrus trees: driven east along the lane at y = 2.5, then
    back west along the lane at y = -2.5. After the first lane every crown is seen from
    one side; after the second, from both."""
    specs = grid_orchard(1, 2, 5.0, 5.0, np.random.default_rng(1))
    ahead = dict(speed=1.0, seconds=12.0, seed=2)
    east = drive(specs, start=(-3.5, 2.5), heading=0.0, **ahead)
    west = drive(specs, start=(8.5, -2.5), heading=math.pi, **ahead)
    mapper = TreeMapper(MapperConfig(), east.calibration)
    for scan, pose in zip(east.scans, east.poses, strict=True):
        mapper.process(scan, None, pose)
    first = [t for t in mapper.trees() if t.kind == "tree"]
    assert len(first) == 2 and [t.width_sides_seen for t in first] == [1, 1]
    later = east.scans[-1].t_host + 100_000_000
    for scan, pose in zip(*_shifted(west, later), strict=True):
        mapper.process(scan, None, pose)
    trees = [t for t in mapper.trees() if t.kind == "tree"]
    assert_each_found_once(trees, east.truth)
    assert [t.width_sides_seen for t in trees] == [2, 2]


def test_sides_seen_counts_a_side_only_beyond_the_margin():
    """Views as (x, y, heading) around a tree at the origin, a row along x: a lane's
    pass is one side; a view on the row's own line, or within the margin of it, is on
    neither; one well off it on the far side makes two."""
    lane = [(x, 2.5, 0.0) for x in np.arange(-14.0, 14.5, 0.5)]
    assert sides_seen((0.0, 0.0), np.array(lane)) == 1
    assert sides_seen((0.0, 0.0), np.empty((0, 3))) == 1
    on_line = [(5.0, 0.0, 0.0)]  # the headland, looking down the row
    assert sides_seen((0.0, 0.0), np.array(lane + on_line)) == 1
    inside = math.tan(math.radians(SIDES_MARGIN_DEG - 1)) * 5.0
    outside = math.tan(math.radians(SIDES_MARGIN_DEG + 1)) * 5.0
    assert sides_seen((0.0, 0.0), np.array([*lane, (5.0, -inside, 0.0)])) == 1
    assert sides_seen((0.0, 0.0), np.array([*lane, (5.0, -outside, 0.0)])) == 2
    # Driving the lanes either way is one row: the other lane driven back, west.
    back = [(x, -2.5, math.pi) for x in np.arange(14.0, -14.5, -0.5)]
    assert sides_seen((0.0, 0.0), np.array(lane + back)) == 2
    assert row_direction(np.array([0.0, math.pi])) == pytest.approx(0.0, abs=1e-12)
    # The same views turned with the block (rows at 112 deg): the same answer.
    turn = math.radians(112.0)
    c, s = math.cos(turn), math.sin(turn)
    turned = [(c * x - s * y, s * x + c * y, h + turn) for x, y, h in lane + back]
    assert sides_seen((0.0, 0.0), np.array(turned)) == 2
    assert sides_seen((0.0, 0.0), np.array(turned[: len(lane)])) == 1


# --- edge cases -------------------------------------------------------------------------


def test_one_tree_is_one_tree_from_the_first_scan():
    spec = TreeSpec("T1", "1", 5.0, 2.5, 0.45, 0.08, 1.35, 1.1)
    data = drive([spec], start=(0.0, 0.0), heading=0.0, speed=0.0, seconds=1.0, seed=3)
    mapper = TreeMapper(MapperConfig(), data.calibration)
    results = [mapper.process(s, None, p) for s, p in zip(data.scans, data.poses, strict=True)]
    assert [c.outcome for c in results[0].clusters] == ["created"]
    assert all([c.outcome for c in r.clusters] == ["updated"] for r in results[1:])
    (tree,) = mapper.trees()
    assert tree.tree_id == 1 and tree.observations == len(data.scans) >= 8
    assert math.hypot(tree.x - 5.0, tree.y - 2.5) < 1.35


def test_touching_crowns_are_cut_at_their_trunks_and_crowns_apart_are_two():
    """Two crowns that touch (2.7 m apart, the width of each) are one Euclidean cluster;
    the cut at the trunks (`detection.split_at_trunks`) makes them two trees again, each
    about as wide as it is. A gap wider than the tolerance gives two clusters anyway.
    Seen from 4 m beside the pair."""
    for gap in (0.0, 0.8):
        specs = [
            TreeSpec("A", "1", -1.35 - gap / 2, 0.0, 0.45, 0.08, 1.35, 1.1),
            TreeSpec("B", "1", 1.35 + gap / 2, 0.0, 0.45, 0.08, 1.35, 1.1),
        ]
        data = drive(specs, start=(0.0, 4.0), heading=0.0, speed=0.0, seconds=1.0, seed=9)
        mapper = TreeMapper(MapperConfig(), data.calibration)
        for scan, pose in zip(data.scans, data.poses, strict=True):
            mapper.process(scan, None, pose)
        trees = mapper.trees()
        found, stray = match(trees, data.truth)
        assert stray == [] and all(len(v) == 1 for v in found.values()), gap
        for truth in data.truth:
            # Touching: each piece ends where the other tree's begins (the Voronoi cut
            # between the trunks), so a crown's overlap with its neighbour is lost.
            tolerance = 0.06 if gap else 0.15
            assert found[truth.tree_id][0].width_m == pytest.approx(truth.width, rel=tolerance)


def test_an_empty_scan_and_a_ground_only_scan_change_nothing():
    data = grid_drive()
    mapper = TreeMapper(MapperConfig(), data.calibration)
    mapper.process(data.scans[0], data.frames[0], data.poses[0])
    before = mapper.trees()
    empty = dataclasses.replace(data.scans[1], points=np.zeros(0, POINT_DTYPE))
    result = mapper.process(empty, data.frames[1], data.poses[1])
    assert result.clusters == [] and result.counts["points"] == 0
    points = data.scans[2].points
    ground_only = dataclasses.replace(data.scans[2], points=points[points["z"] < -0.25])
    result = mapper.process(ground_only, data.frames[2], data.poses[2])
    assert result.clusters == [] and result.counts["cropped"] > 1000
    # All ground, but for a few green-looking points under crowns: skirt candidates that
    # touch no cluster and are dropped.
    assert result.counts["ground"] + result.counts["skirt"] == result.counts["cropped"]
    assert mapper.trees() == before


def test_a_mapper_without_scans_has_no_trees():
    assert TreeMapper().trees() == []


def test_scans_taken_while_turning_fast_add_nothing_to_the_outline():
    """The same scans and positions, but poses whose heading swings by 0.1 rad from one
    scan to the next (1 rad/s, the paper's turn rate; above traits.max_yaw_rate): the
    robust outline takes none of them but the first (no yaw rate yet), too few for a cell
    to count (no width), while with the true, steady headings every tree gets one.
    Tracking is not touched: the trees are found either way."""
    data = grid_drive()
    config = MapperConfig(traits=TraitsConfig(method="robust"))
    steady, turning = TreeMapper(config, data.calibration), TreeMapper(config, data.calibration)
    for k, (scan, pose) in enumerate(zip(data.scans[:40], data.poses[:40], strict=True)):
        steady.process(scan, None, pose)
        swung = dataclasses.replace(pose, yaw=pose.yaw + (0.05 if k % 2 else -0.05))
        turning.process(scan, None, swung)
    # Trees, not the understorey's objects: with headings swinging, a low piece under a
    # crown can land a scan away from its tree and stand alone (it is listed, `low`).
    steady_trees = [t for t in steady.trees() if t.kind == "tree"]
    turning_trees = [t for t in turning.trees() if t.kind == "tree"]
    assert len(steady_trees) >= 2 and len(turning_trees) == len(steady_trees)
    assert all(math.isfinite(t.width_m) for t in steady_trees)
    assert all(math.isnan(t.width_m) for t in turning_trees)


def test_a_tree_stands_where_most_of_its_trunk_sightings_agree():
    """`trunk_position`: the sightings that agree within `trunk_agree_m` of the best
    supported place, when they are enough, a majority, a share of the tree's scans, and
    under its crown; a weed clump or a neighbour's trunk taken for the trunk now and then
    does not move the tree."""
    config = TraitsConfig()  # 3 sightings, 0.25 m, 5 % of the scans, half the width
    rng = np.random.default_rng(1)
    trunk = np.array([10.0, -4.0])

    def seen(place, n):
        return [tuple(np.array(place) + rng.normal(0, 0.03, 2)) for _ in range(n)]

    sightings = seen(trunk, 20)
    weed = seen((10.6, -3.7), 8)
    found = trunk_position(sightings + weed, config, scans=100)
    assert np.hypot(*(found - trunk)) < 0.03
    assert np.hypot(*(found - trunk)) < np.hypot(*(np.mean(sightings + weed, axis=0) - trunk))
    assert trunk_position(sightings[:2], config) is None  # too few: the outline stands in
    # No majority: as many sightings elsewhere as at the best place.
    assert trunk_position(sightings[:8] + weed, config) is None
    # A place sighted in 20 of 1000 scans (2 %) is a clump glimpsed now and then.
    assert trunk_position(sightings, config, scans=1000) is None
    assert trunk_position(sightings, dataclasses.replace(config, trunk_min_scans=0)) is None
    # A weed clump past the crown's edge (1.5 m from a centre 0.1 m off the trunk, the
    # crown 2.8 m wide), seen more often than the trunk, is no trunk.
    edge = seen((11.5, -4.2), 30)
    crown = trunk + np.array([0.1, 0.0])
    assert np.hypot(*(trunk_position(sightings + edge, config) - (11.5, -4.2))) < 0.03
    assert trunk_position(sightings + edge, config, 100, crown, 2.8) is None
    # Hundreds of sightings (a tree seen for minutes): the same place.
    many = seen(trunk, 600)
    assert np.hypot(*(trunk_position(many, config, 1000, crown, 2.8) - trunk)) < 0.01


def test_a_thin_object_on_a_trunk_does_not_take_the_trunk_from_its_tree():
    """The twin's irregular orchard (seed 2): a crown lobed away from its trunk has its
    centre 0.6 m off the trunk, and the trunk seen once apart from the crown made a thin
    object on it. In the cut (`_Centres`) that object takes the crown's returns nearer to
    it, but not the trunk sightings: they stay the tree's (the tree stood 0.63 m off its
    trunk when the thin object took all 181). A neighbour tree's trunk stays refused."""
    tracks = [
        SimpleNamespace(tree_id=1, state=np.array([14.4, 2.4, 1.5])),  # the lobed crown
        SimpleNamespace(tree_id=2, state=np.array([9.9, 2.4, 1.5])),  # its neighbour
        SimpleNamespace(tree_id=3, state=np.array([15.0, 2.5, 0.5])),  # the trunk alone
    ]
    centres = _Centres(tracks, np.eye(4), claiming={1, 2, 3}, thin={3})
    trunk = np.array([15.04, 2.50])
    assert centres.trunk_is(trunk, 1)
    assert not centres.nearest_is(trunk[None], 1)[0]  # its returns: the thin object's side
    assert not centres.trunk_is(np.array([10.0, 2.45]), 1)  # the neighbour's trunk
    # Not thin (a person standing there): the cut holds for the trunk too.
    person = _Centres(tracks, np.eye(4), claiming={1, 2, 3}, thin=set())
    assert not person.trunk_is(trunk, 1)


def test_an_object_seen_in_fewer_scans_than_claim_min_scans_claims_nothing():
    """A track takes its side in the cut once seen in `tracking.claim_min_scans` scans:
    after one scan of the grid, nothing claims; after three, the trees do."""
    data = grid_drive()
    for claim, scans, claiming in ((3, 1, False), (3, 3, True), (1, 1, True)):
        config = MapperConfig(tracking=TrackingConfig(claim_min_scans=claim))
        mapper = TreeMapper(config, data.calibration)
        for scan, pose in zip(data.scans[:scans], data.poses[:scans], strict=True):
            mapper.process(scan, None, pose)
        trees = {t.tree_id for t in mapper.trees() if t.kind == "tree"}
        assert trees, (claim, scans)
        assert (trees <= mapper._claiming()) == claiming, (claim, scans)
        assert bool(trees & mapper._claiming()) == claiming, (claim, scans)


@pytest.mark.parametrize(
    ("ray_top_m", "foot_m", "measured"),
    [
        (2.80, 0.00, True),  # the top bracketed to 3.7 %, the foot on the lowest ground
        (2.70, 0.10, True),  # 3.7 % at the foot alone
        (2.80, 0.10, False),  # each end within 5 %, together 7.4 %: short by up to that
        (2.74, 0.05, True),  # 1.5 % and 1.9 %: 3.3 % together
        (2.90, 0.00, False),  # the top's gap alone is 7.4 %
    ],
)
def test_a_height_is_measured_when_its_two_ends_together_are_within_5_percent(
    ray_top_m, foot_m, measured
):
    """A 2.7 m tree standing at the origin on ground at z = 0 (the lowest seen under it),
    its highest return at 2.70 m + foot. Two scans' level rays passed over its top at
    `ray_top_m`: the true top lies between the highest return and those rays. The height
    measured from the foot is short by the top's gap plus the foot's rise above the
    ground, and is measured when both together are within 5 % of it."""
    tree = _Tree(traits=None)
    tree.raise_top(np.array([0.0, 0.0, 2.70 + foot_m]))
    tree.add_tops(
        np.array([[6.0, 0.0, ray_top_m + foot_m, 0.0], [6.5, 0.0, ray_top_m + foot_m, 0.0]])
    )
    tree.add_grounds(np.zeros(20))
    assert tree.height_measured(np.zeros(2), 2.70, 0.05) is measured


@pytest.mark.parametrize(
    ("top_x_m", "measured"),
    [
        (0.0, True),  # a regular crown's apex over the trunk: the rays 6 cm above it, 2.2 %
        (0.6, False),  # a lobe's, 0.6 m beyond: the rays 0.22 m above it there, 8 %
    ],
)
def test_a_tops_bound_is_taken_where_the_tree_stands_and_at_its_highest_return(top_x_m, measured):
    """A 2.7 m tree at the origin on level ground; two scans 9 m before it, the LiDAR
    0.44 m up, its beam above the top rising 0.258 m a metre: over the trunk at 2.76 m,
    over a point 0.6 m beyond at 2.92 m. Its highest return, 2.70 m, at the trunk or on
    a lobe 0.6 m beyond it: there an apex up to the rays' height there can hide, and its
    height is not known to 5 %."""
    tree = _Tree(traits=None)
    tree.raise_top(np.array([top_x_m, 0.0, 2.70]))
    rise = (2.76 - 0.44) / 9.0
    tree.add_tops(np.array([[-9.0, 0.0, 0.44, rise], [-9.0, 0.0, 0.44, rise]]))
    tree.add_grounds(np.zeros(20))
    assert tree.height_measured(np.zeros(2), 2.70, 0.05) is measured


def test_a_tops_bound_is_one_two_scans_agree_on():
    """The same tree with rays from two scans: one passing 2 cm over its highest return
    (through a gap at the apex, say), one 0.3 m over it. The bound is the second, 11 %:
    not measured; one scan's ray alone proves nothing; a second scan's ray as low as the
    first makes it measured."""
    low, high = [6.0, 0.0, 2.72, 0.0], [6.5, 0.0, 3.00, 0.0]
    for rows, measured in (([low], False), ([low, high], False), ([low, high, low], True)):
        tree = _Tree(traits=None)
        tree.raise_top(np.array([0.0, 0.0, 2.70]))
        tree.add_tops(np.array(rows))
        tree.add_grounds(np.zeros(20))
        assert tree.height_measured(np.zeros(2), 2.70, 0.05) is measured, rows
