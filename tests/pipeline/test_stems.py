"""Posts and people cut out before clustering (`pipeline.stems`): each object ray-cast by
the twin's VLP-16 emulator and decoded by our own decoder, seen from a robot at the
origin; a row of trees 2.5 m to its left."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.scans import scan_of
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.config import ClusterConfig, DetectionConfig
from treetraits.pipeline.detection import detect
from treetraits.pipeline.stems import StemSearch, _Cells, column_top, max_gap_m
from treetraits.sim.clutter import box, cylinder, person, tube, weed_clump
from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh

ROW_Y = 2.5
NO_STEMS = DetectionConfig(cluster=ClusterConfig(min_stem_height_m=0))


def crown(x: float, radius: float = 1.4, seed: int = 4):
    spec = TreeSpec("A", "1", x, ROW_Y, 0.45, 0.08, radius, 1.35)
    return tree_mesh(spec, Ground(), np.random.default_rng(seed))


def near(clusters, x, reach=1.0):
    return [c for c in clusters if math.hypot(c.centroid[0] - x, c.centroid[1] - ROW_Y) < reach]


def test_a_person_beside_a_crown_is_cut_out_and_the_crown_keeps_its_width():
    """A worker 0.3 m from the crown's edge (a 2.8 m crown at x = -2, the person at
    x = -0.3, beside the robot): without the cut they are one cluster 3 m wide."""
    scan = scan_of(crown(-2.0), person(-0.3, ROW_Y, 0.0))
    joined = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, NO_STEMS)
    assert max(c.shape.width_m for c in near(joined.clusters, -2.0, 1.5)) > 2.95
    cut = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert cut.counts["stems"] >= 1
    tree = [c for c in near(cut.clusters, -2.0, 1.5) if c.verdict == TREE]
    assert len(tree) == 1 and tree[0].shape.width_m < 2.85
    worker = near(cut.clusters, -0.3, 0.4)
    assert worker and all(c.verdict != TREE for c in worker)
    assert all(c.shape.width_m < 0.6 for c in worker)


@pytest.mark.parametrize("x", [-5.0, -3.0, 0.0, 3.0])
def test_posts_and_people_between_trees_stand_apart(x):
    """Trees at x and x + 4, a person in the gap, end posts 0.6 m off each crown: every
    post and person is a cluster of its own, never a tree, and each crown is one tree."""
    scan = scan_of(
        crown(x),
        crown(x + 4.0),
        person(x + 2.0, ROW_Y, 0.0),
        cylinder(x - 2.0, ROW_Y, 0.0, 2.0, 0.05),
        cylinder(x + 6.0, ROW_Y, 0.0, 1.8, 0.05),
    )
    clusters = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    for centre in (x, x + 4.0):
        trees = [c for c in near(clusters, centre, 1.4) if c.verdict == TREE]
        assert len(trees) == 1, (centre, [(c.centroid, c.verdict) for c in clusters])
        assert trees[0].shape.width_m < 3.0
    for thing in (x + 2.0, x - 2.0, x + 6.0):
        assert all(c.verdict != TREE for c in near(clusters, thing, 0.3)), thing


@pytest.mark.parametrize("x", [0.0, 3.0])
@pytest.mark.parametrize("weed_at", [(0.0, 0.0), (0.25, 0.1), (-0.3, 0.0)])
def test_a_post_standing_in_a_weed_clump_is_cut_out_all_the_same(x, weed_at):
    """An end post 0.6 m off a 2.8 m crown, a 0.4 m weed clump around its foot (where the
    mower cannot reach) and a trellis wire at 1 m from it through the crown: the clump
    makes the foot no trunk-sized blob, so the post is seeded above the understorey.
    Measured without that seed: the post joined the crown, 3.2-3.5 m wide. The post's
    foot and the clump stay one cluster, judged on what stands above the understorey (a
    smooth post): with its weeds' cues it was a 0.61 x 1.3 m tree (texture 0.049 m)."""
    rng = np.random.default_rng(1)
    post = (x - 2.0, ROW_Y)
    scan = scan_of(
        crown(x),
        box(*post, 0.0, 1.8, 0.1, 0.1),
        tube(np.array([[x - 2.0, ROW_Y, 1.0], [x + 6.0, ROW_Y, 1.0]]), 0.002, sides=4),
        weed_clump(post[0] + weed_at[0], post[1] + weed_at[1], 0.0, 0.3, 0.4, rng),
    )
    detection = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert detection.counts["stems"] >= 1
    trees = [c for c in near(detection.clusters, x, 1.4) if c.verdict == TREE]
    assert len(trees) == 1 and trees[0].shape.width_m < 3.05
    assert all(c.verdict != TREE for c in near(detection.clusters, post[0], 0.4))


@pytest.mark.parametrize(
    "spec",
    [
        TreeSpec("Y", "1", 4.0, 2.0, 0.3, 0.04, 0.5, 0.45),  # young: 1.2 m, a 1 m crown
        TreeSpec("M", "1", 1.0, 2.5, 0.45, 0.08, 1.35, 1.1),  # mature, beside the robot
        TreeSpec("O", "1", 7.0, 4.0, 0.6, 0.15, 2.3, 2.2),  # old: 5 m tall, 4.6 m wide
    ],
)
@pytest.mark.parametrize("weeds", [False, True])
def test_a_tree_has_no_stem(spec, weeds):
    """Trunks are blobs in the band like posts, but with a crown around their column;
    with a weed clump at the trunk, the seed above the understorey is inside the skirt."""
    rng = np.random.default_rng(3)
    meshes = [tree_mesh(spec, Ground(), rng)]
    if weeds:
        meshes.append(weed_clump(spec.x + 0.1, spec.y, 0.0, 0.35, 0.5, rng))
    scan = scan_of(*meshes)
    detection = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert detection.counts["stems"] == 0


def test_column_top_climbs_until_a_gap():
    heights = np.array([0.4, 0.55, 0.7, 1.0, 1.2, 2.0])
    assert column_top(heights, 0.32, 0.35) == pytest.approx(1.2)
    assert column_top(heights, 0.32, 0.9) == pytest.approx(2.0)
    assert column_top(np.array([1.0]), 0.32, 0.3) == pytest.approx(0.32)
    # One ring gap at 10 m is 0.35 m: a column there may miss one and a half.
    assert max_gap_m(10.0, 0.2) == pytest.approx(1.5 * 10 * math.tan(math.radians(2)) + 0.2)


def _around_by_numpy(cells: _Cells, spot: np.ndarray) -> np.ndarray:
    """`_Cells.around` as NumPy computed it before the kernel (the reference)."""
    i, j = np.floor((np.asarray(spot) - cells.origin) / cells.size).astype(np.int64)
    j_low, j_high = max(j - 1, 0), min(j + 1, cells.shape[1] - 1)
    parts = []
    for row in range(max(i - 1, 0), min(i + 1, cells.shape[0] - 1) + 1):
        if j_low <= j_high:
            lo, hi = np.searchsorted(
                cells.sorted_cells,
                (row * cells.shape[1] + j_low, row * cells.shape[1] + j_high + 1),
            )
            parts.append(cells.order[lo:hi])
    return np.sort(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)


def test_the_stem_search_kernels_are_numpys_to_the_bit():
    """The returns around a spot and the top ring's slope, compiled, against the NumPy
    formulation they replace: spots inside, on the edges of and far outside the grid,
    returns right above and beside the LiDAR (reach under 0.1 m)."""
    rng = np.random.default_rng(21)
    xyz = np.vstack([rng.uniform([-15, -10, -0.5], [25, 10, 5], (20000, 3)), [[0, 0, 2.0]]])
    lidar_xyz = np.array([0.05, -0.02, 0.7])
    search = StemSearch(xyz, xyz[:, 2], np.zeros(len(xyz), np.uint8), lidar_xyz, ClusterConfig())
    reach_all = np.hypot(xyz[:, 0] - lidar_xyz[0], xyz[:, 1] - lidar_xyz[1])
    expected = np.max((xyz[:, 2] - lidar_xyz[2]) / np.maximum(reach_all, 0.1))
    assert np.float64(search.top_slope).tobytes() == expected.tobytes()
    spots = np.vstack([rng.uniform([-17, -12], [27, 12], (500, 2)), [[-15, -10], [25, 10]]])
    for spot in np.vstack([spots, [[-100, 0], [0, 100], [1e6, -1e6]]]):
        assert np.array_equal(search.cells.around(spot), _around_by_numpy(search.cells, spot))
