"""Per-scan detection: crop, RANSAC ground, the NDVI skirt rule, voxel grid, Euclidean
clustering and the cluster features, on synthetic arrays with known answers and on
VLP-16 twin scans of known trees."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.helpers.scans import first_complete_scan, scan_of
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.drivers.records import POINT_DTYPE
from treetraits.pipeline.clustering import (
    attach,
    connected_labels,
    euclidean_clusters,
    kdtree_clusters,
    nearest_label,
)
from treetraits.pipeline.config import (
    ClassifyConfig,
    ClusterConfig,
    CropConfig,
    DetectionConfig,
    GroundConfig,
)
from treetraits.pipeline.detection import (
    FLAT,
    _narrower,
    crop_mask,
    detect,
    fit_ground,
    hull_area_volume,
    split_ground,
    to_base,
    voxel_grid,
)
from treetraits.sim.clutter import weed_clump
from treetraits.sim.lidar import Scene
from treetraits.sim.orchard import Ground, TreeSpec, ground_mesh, measure_truth, tree_mesh

LIDAR_HEIGHT = DEFAULT_T_BASE_LIDAR[2, 3]


def structured(xyz: np.ndarray, ring=None) -> np.ndarray:
    """POINT_DTYPE points in the lidar frame from base-frame coordinates."""
    out = np.zeros(len(xyz), dtype=POINT_DTYPE)
    lidar = np.asarray(xyz, dtype=float) - DEFAULT_T_BASE_LIDAR[:3, 3]
    out["x"], out["y"], out["z"] = lidar.T
    out["ring"] = 0 if ring is None else ring
    return out


def ground_points(rng, n=6000, extent=12.0, slope=(0.0, 0.0), noise=0.01):
    xy = rng.uniform(-extent, extent, (n, 2))
    z = slope[0] * xy[:, 0] + slope[1] * xy[:, 1] + rng.normal(0, noise, n)
    return np.column_stack([xy, z])


def blob(rng, centre, radius=1.0, n=800):
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    return np.asarray(centre) + direction * radius * rng.uniform(0.8, 1.0, (n, 1))


# --- crop and ground ------------------------------------------------------------------


def test_crop_keeps_the_box_and_drops_the_robot():
    xyz = np.array([[5, 0, 1], [16, 0, 1], [0, -14, 0], [0, 0, 9], [0.3, 0.1, 0.5], [-3, 2, -1]])
    keep = crop_mask(xyz.astype(float), CropConfig(), np.array([0.04, 0.0]))
    assert keep.tolist() == [True, False, True, False, False, True]


@pytest.mark.parametrize("slope", [(0.0, 0.0), (0.05, -0.03)])
def test_ransac_finds_the_ground_plane_under_trees(slope):
    rng = np.random.default_rng(0)
    ground = ground_points(rng, slope=slope)
    trees = np.vstack([blob(rng, (4, 3, 1.6)), blob(rng, (-3, -4, 1.6))])
    plane = fit_ground(np.vstack([ground, trees]), GroundConfig())
    assert plane.fitted
    expected = np.array([-slope[0], -slope[1], 1.0]) / math.hypot(1, *slope)
    assert np.allclose(plane.normal, expected, atol=0.005)
    assert abs(plane.z_at(5.0, 5.0) - (5 * slope[0] + 5 * slope[1])) < 0.02
    # Height above the plane, not z: a point 1 m over the sloped ground reads 1 m.
    assert plane.height(np.array([[8.0, 2.0, 8 * slope[0] + 2 * slope[1] + 1.0]])) == (
        pytest.approx([1.0], abs=0.02)
    )


def test_ground_falls_back_to_the_footprint_without_a_floor():
    rng = np.random.default_rng(1)
    wall = np.column_stack([np.full(3000, 5.0), rng.uniform(-5, 5, 3000), rng.uniform(-2, 3, 3000)])
    assert fit_ground(wall, GroundConfig()) is FLAT
    assert fit_ground(np.zeros((0, 3)), GroundConfig()) is FLAT
    assert FLAT.height(np.array([[1.0, 2.0, 0.7]])) == pytest.approx([0.7])


def test_ransac_is_deterministic_and_agrees_with_open3d():
    rng = np.random.default_rng(2)
    xyz = np.vstack([ground_points(rng, slope=(0.02, 0.01), noise=0.03), blob(rng, (4, 0, 1.5))])
    first, second = fit_ground(xyz, GroundConfig()), fit_ground(xyz, GroundConfig())
    assert np.array_equal(first.normal, second.normal) and first.d == second.d
    other = fit_ground(xyz, GroundConfig(method="open3d"))
    assert np.allclose(other.normal, first.normal, atol=2e-3)
    assert abs(other.d - first.d) < 0.005


def test_ransac_skips_tilted_planes():
    """A wall with more points than the floor: the floor is still the ground."""
    rng = np.random.default_rng(5)
    wall = np.column_stack(
        [np.full(6000, 3.0), rng.uniform(-8, 8, 6000), rng.uniform(-0.45, 0.45, 6000)]
    )
    plane = fit_ground(np.vstack([wall, ground_points(rng, n=2000)]), GroundConfig())
    assert plane.fitted and plane.tilt_deg < 1.0


# --- the NDVI check on ground candidates ------------------------------------------------


def test_skirt_rule_keeps_green_points_in_the_ground_band_only():
    config = GroundConfig()  # clearance 0.15, skirt >= 0.05 m and NDVI >= 0.4
    height = np.array([0.5, 0.10, 0.10, 0.10, 0.02, 0.10])
    ndvi = np.array([0.1, 0.75, 0.15, np.nan, 0.75, 0.40])
    above, skirt = split_ground(height, ndvi, config)
    assert above.tolist() == [True, False, False, False, False, False]
    # Foliage NDVI 0.10 m up: skirt; soil NDVI or no NDVI: ground; 2 cm up: ground.
    assert skirt.tolist() == [False, True, False, False, False, True]
    above, skirt = split_ground(height, None, config)
    assert not skirt.any()


def test_a_skirt_joins_its_tree_but_never_starts_or_bridges_a_cluster():
    rng = np.random.default_rng(3)
    ground = ground_points(rng, n=4000, extent=10)
    crown_a = blob(rng, (4.0, 0.0, 1.2), radius=0.8)  # lowest leaves at ~0.4 m
    crown_b = blob(rng, (4.0, 3.0, 1.2), radius=0.8)  # a 1.4 m gap between the crowns
    # A green skirt under crown A (0.05-0.12 m up, touching its lowest leaves) and a
    # green cover crop strip from A to B, and a lone green patch far from any tree.
    skirt = np.column_stack(
        [rng.uniform(3.6, 4.4, 100), rng.uniform(-0.4, 0.4, 100), rng.uniform(0.06, 0.12, 100)]
    )
    crop = np.column_stack(
        [rng.uniform(3.9, 4.1, 200), rng.uniform(0.3, 2.7, 200), rng.uniform(0.06, 0.12, 200)]
    )
    lone = np.column_stack(
        [rng.uniform(-5, -4, 60), rng.uniform(-5, -4, 60), rng.uniform(0.06, 0.12, 60)]
    )
    xyz = np.vstack([ground, crown_a, crown_b, skirt, crop, lone])
    ndvi = np.concatenate(
        [np.full(len(ground), 0.15), np.full(1600, 0.75), np.full(100 + 200 + 60, 0.7)]
    )
    # On the plane: the counts below are the skirt rule's alone (the terrain takes a cell
    # holding only the 6-12 cm mat, no soil, for ground: a cover crop is terrain).
    config = DetectionConfig(ground=GroundConfig(model="plane"), cluster=ClusterConfig(voxel_m=0.1))
    with_camera = detect(structured(xyz), ndvi, DEFAULT_T_BASE_LIDAR, config)
    without = detect(structured(xyz), None, DEFAULT_T_BASE_LIDAR, config)
    assert len(with_camera.clusters) == len(without.clusters) == 2  # no bridge, no patch
    lowest = sorted(c.points[:, 2].min() for c in with_camera.clusters)
    assert lowest[0] < 0.13  # the skirt (and the crop next to it) joined crown A
    assert min(c.points[:, 2].min() for c in without.clusters) > 0.15
    assert with_camera.counts["skirt"] == 360
    ndvi_means = sorted(c.ndvi for c in with_camera.clusters)
    assert 0.7 <= ndvi_means[0] <= ndvi_means[1] <= 0.75


# --- voxel grid and clustering ----------------------------------------------------------


def test_voxel_grid_gives_the_centroid_of_each_occupied_cell():
    xyz = np.array([[0.01, 0.01, 0.01], [0.09, 0.05, 0.03], [0.15, 0.0, 0.0], [-0.05, 0, 0]])
    voxel_of, centroids = voxel_grid(xyz, 0.1)
    assert len(centroids) == 3
    assert voxel_of[0] == voxel_of[1] != voxel_of[2]
    assert np.allclose(centroids[voxel_of[0]], [0.05, 0.03, 0.02])
    assert np.allclose(centroids[voxel_of[3]], [-0.05, 0, 0])


@pytest.mark.parametrize("method", ["kdtree", "dbscan"])
def test_euclidean_clusters_link_chains_and_split_gaps(method):
    chain = np.column_stack([np.arange(0, 5, 0.45), np.zeros(12), np.zeros(12)])  # 0.45 apart
    apart = chain + np.array([0, 0.55, 0])  # 0.55 from the chain: another cluster at 0.5 m
    far = np.array([[20.0, 0, 0]])
    labels = euclidean_clusters(np.vstack([chain, apart, far]), 0.5, method)
    assert labels.tolist() == [0] * 12 + [1] * 12 + [2]
    assert len(euclidean_clusters(np.zeros((0, 3)), 0.5, method)) == 0


def test_kdtree_and_dbscan_cluster_a_twin_scan_alike(tree_scan):
    xyz = to_base(tree_scan.points, DEFAULT_T_BASE_LIDAR)
    xyz = xyz[xyz[:, 2] > 0.2]
    _, voxels = voxel_grid(xyz, 0.2)
    a = euclidean_clusters(voxels, 0.5, "kdtree")
    b = euclidean_clusters(voxels, 0.5, "dbscan")
    assert np.array_equal(a, b)


def _clouds_for_the_grid(dims: int) -> list[np.ndarray]:
    """Dense blobs (cells joined without a look), sparse scatter (pairs looked at cells
    apart), chains just under and just over 0.25 and 0.5 along the axes and diagonally."""
    rng = np.random.default_rng(7 + dims)
    blobs = np.vstack(
        [rng.normal(c[:dims], 0.08, (300, dims)) for c in ([0, 0, 0], [0.6, 0.1, 0.2], [3, -2, 1])]
    )
    scatter = rng.uniform(-6, 6, (1500, dims))
    steps = np.arange(40)[:, None]
    unit = np.eye(dims)
    diagonal = np.ones(dims) / np.sqrt(dims)
    chains = np.vstack(
        [
            np.full(dims, 10.0) + 2 * k * unit[-1] + steps * step * direction
            for k, (step, direction) in enumerate(
                [
                    (0.249, unit[0]),
                    (0.251, unit[0]),
                    (0.2499, unit[1]),
                    (0.25 - 1e-12, diagonal),
                    (0.25 + 1e-12, diagonal),
                    (0.4999, unit[-1]),
                    (0.5, diagonal),
                    (0.5001, unit[1]),
                ]
            )
        ]
    )
    return [np.vstack([blobs, scatter, chains]), scatter, np.vstack([chains, blobs]), blobs[:5]]


@pytest.mark.parametrize("dims", [2, 3])
def test_the_grid_kernel_clusters_as_the_kdtree(dims):
    """The compiled grid's labels are the k-d tree's pairs' components (what clustering
    computed before), numbered alike, in x-y and in x-y-z."""
    for cloud in _clouds_for_the_grid(dims):
        for tolerance in (0.25, 0.5):
            expected = kdtree_clusters(cloud, tolerance)
            assert np.array_equal(euclidean_clusters(cloud, tolerance), expected)
            # A strided or float32 view is clustered as its float64 copy.
            assert np.array_equal(euclidean_clusters(cloud.T.copy().T, tolerance), expected)


def test_the_grid_kernel_clusters_a_twin_scan_as_the_kdtree(tree_scan):
    xyz = to_base(tree_scan.points, DEFAULT_T_BASE_LIDAR)
    xyz = xyz[xyz[:, 2] > 0.2]
    _, voxels = voxel_grid(xyz, 0.2)
    for cloud, tolerance in ((voxels, 0.5), (xyz[:, :2], 0.25), (xyz[:3000], 0.5)):
        assert np.array_equal(
            euclidean_clusters(cloud, tolerance), kdtree_clusters(cloud, tolerance)
        )


def test_a_grid_too_wide_for_its_keys_is_left_to_the_kdtree():
    cloud = np.array([[0.0, 0, 0], [0.3, 0, 0], [1e9, 1e9, 1e9], [1e9, 1e9, 1e9 + 0.4]])
    assert euclidean_clusters(cloud, 0.5).tolist() == [0, 0, 1, 1]
    assert euclidean_clusters(cloud[[0, 0, 1]], 0.0).tolist() == [0, 0, 1]  # no grid


def test_a_box_short_of_a_width_proves_the_group_narrower():
    """`_narrower` says narrower only where the 12 bearings' width is; groups around
    the width, along either axis, diagonally and as a line, both sides of it."""
    from treetraits.pipeline.classify import horizontal_extent

    rng = np.random.default_rng(5)
    groups = []
    for size in rng.uniform(0.2, 1.0, 300):
        part = rng.uniform(0, size, (int(rng.integers(1, 40)), 2))
        groups.append(part @ np.array([[1, 1], [-1, 1]]) / np.sqrt(2) if size > 0.6 else part)
    groups += [np.array([[0.0, 0.0], [0.5 - 1e-7, 0.0]]), np.array([[0.0, 0.0], [0.3, 0.4]])]
    xy = np.vstack(groups)
    starts = np.cumsum([0] + [len(g) for g in groups[:-1]])
    narrow = _narrower(xy, starts, 0.5)
    widths = np.array([horizontal_extent(g) for g in groups])
    assert (widths[narrow] < 0.5).all()
    assert narrow.any() and not narrow.all()
    assert not narrow[-1] and not narrow[-2]


def test_connected_labels_are_scipys():
    """Our union-find against SciPy's connected_components (what clustering used before):
    a chain linked from its far end (the most rounds of joining), a star, isolated nodes,
    random sparse graphs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    rng = np.random.default_rng(3)
    graphs = [
        (50, np.array([[k, k + 1] for k in range(48, -1, -1)])),
        (30, np.array([[0, k] for k in range(29, 0, -2)])),
        (5, np.zeros((0, 2), dtype=np.int64)),
    ]
    for n in (10, 200, 2000):
        graphs.append((n, np.sort(rng.integers(0, n, size=(n, 2)), axis=1)))
    for n, pairs in graphs:
        graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
        _, expected = connected_components(graph, directed=False)
        assert connected_labels(n, pairs).tolist() == expected.tolist()


def test_attach_takes_the_nearest_anchor_within_reach():
    anchors = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    labels = attach(np.array([[0.2, 0, 0], [0.9, 0, 0], [5, 0, 0]]), anchors, np.array([4, 7]), 0.5)
    assert labels.tolist() == [4, 7, -1]


def _kdtree_attach(points, anchors, labels, tolerance):
    """`attach` as the k-d tree's bounded query gave it (the reference)."""
    from scipy.spatial import cKDTree

    distance, index = cKDTree(anchors).query(points, distance_upper_bound=tolerance)
    return np.where(np.isfinite(distance), labels[np.minimum(index, len(anchors) - 1)], -1)


def test_attach_and_nearest_label_are_the_kdtrees():
    """The compiled searches against the k-d tree's queries: random clouds in 2-D and
    3-D, points exactly at the tolerance (not within it, as the tree's bound is strict),
    points far outside the anchors' box, and equidistant anchors of two labels (the
    tree's pick, whatever it is)."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(12)
    for dims in (2, 3):
        for _trial in range(20):
            anchors = rng.uniform(-3, 3, (int(rng.integers(1, 400)), dims))
            labels = rng.integers(0, 5, len(anchors))
            points = np.vstack([rng.uniform(-4, 4, (300, dims)), rng.uniform(-50, 50, (5, dims))])
            on_edge = anchors[: min(5, len(anchors))] + 0.5 * np.eye(dims)[0]
            points = np.vstack([points, on_edge, anchors[:3]])
            assert np.array_equal(
                attach(points, anchors, labels, 0.5), _kdtree_attach(points, anchors, labels, 0.5)
            )
            nearest = cKDTree(anchors).query(points[:20])[1]
            assert np.array_equal(nearest_label(points[:20], anchors, labels), labels[nearest])
    anchors = np.array([[-0.25, 0.0], [0.25, 0.0], [3.0, 0.0]])
    for labels in (np.array([1, 2, 3]), np.array([2, 1, 3])):
        middle = np.array([[0.0, 0.0], [2.9, 0.0]])
        tree = _kdtree_attach(middle, anchors, labels, 0.5)
        assert np.array_equal(attach(middle, anchors, labels, 0.5), tree)
        assert np.array_equal(nearest_label(middle, anchors, labels), tree)


def test_hull_area_and_volume_of_a_box():
    corners = np.array([[x, y, z] for x in (0, 2) for y in (0, 1) for z in (0, 3)], float)
    area, volume = hull_area_volume(np.vstack([corners, corners.mean(axis=0)]))
    assert area == pytest.approx(2 * (2 + 6 + 3))
    assert volume == pytest.approx(6.0)
    assert hull_area_volume(corners[:3]) == (0.0, 0.0)
    assert hull_area_volume(np.column_stack([np.arange(5.0), np.zeros(5), np.zeros(5)])) == (0, 0)


# --- whole scans --------------------------------------------------------------------------


def test_empty_and_ground_only_scans_give_no_clusters():
    empty = detect(np.zeros(0, POINT_DTYPE), None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert empty.clusters == [] and empty.counts["points"] == 0
    rng = np.random.default_rng(4)
    flat = detect(structured(ground_points(rng)), None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert flat.clusters == [] and flat.ground.fitted
    assert flat.counts["ground"] == flat.counts["cropped"]


TREE = TreeSpec("T1", "1", 4.0, 2.0, 0.45, 0.08, 1.35, 1.1)
FAR_TREE = TreeSpec("T2", "1", -12.0, -3.0, 0.45, 0.08, 1.35, 1.1)


@pytest.fixture(scope="module")
def tree_scene():
    rng = np.random.default_rng(7)
    ground = Ground()
    scene = Scene()
    scene.add(*ground_mesh(ground, (-30, 30), (-30, 30)), label=0)
    truths = []
    for i, spec in enumerate((TREE, FAR_TREE)):
        vertices, triangles = tree_mesh(spec, ground, rng)
        scene.add(vertices, triangles, label=i + 1)
        truths.append(measure_truth(spec, vertices, ground))

    return first_complete_scan(scene, DEFAULT_T_BASE_LIDAR, rng), truths


@pytest.fixture(scope="module")
def tree_scan(tree_scene):
    return tree_scene[0]


def test_a_near_and_a_far_tree_are_one_cluster_each(tree_scene):
    scan, truths = tree_scene
    detection = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert detection.ground.fitted
    assert len(detection.clusters) == 2
    near, far = sorted(detection.clusters, key=lambda c: np.hypot(*c.centroid[:2]))
    # The visible (near) face: the centroid sits between the tree's centre and the robot.
    for cluster, truth in ((near, truths[0]), (far, truths[1])):
        offset = np.hypot(cluster.centroid[0] - truth.x, cluster.centroid[1] - truth.y)
        assert offset < 1.35
        assert np.hypot(*cluster.centroid[:2]) < np.hypot(truth.x, truth.y)
        assert cluster.ground_z == pytest.approx(0.0, abs=0.02)
        assert cluster.points[:, 2].max() <= truth.height + 0.05
        assert math.isnan(cluster.ndvi)
        assert cluster.hull_volume > 0.1 and cluster.hull_area > 1.0
        assert cluster.features.shape == (5,)
    # 12.4 m away the rings are 0.43 m apart: still one cluster at the 0.5 m tolerance,
    # one per ring (or pieces) at 0.3 m.
    assert len({int(r) for r in far.ring}) >= 4
    split = DetectionConfig(cluster=ClusterConfig(tolerance_m=0.3))
    assert len(detect(scan.points, None, DEFAULT_T_BASE_LIDAR, split).clusters) > 2


def test_stage_times_are_reported_when_asked(tree_scan):
    stage_ms: dict[str, float] = {}
    detect(tree_scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig(), stage_ms)
    assert set(stage_ms) == {
        "crop",
        "mixed",
        "ground",
        "ndvi_check",
        "voxel",
        "stems",
        "cluster",
        "features",
    }
    assert all(v >= 0 for v in stage_ms.values())


def test_ndvi_function_is_asked_only_for_points_clear_of_the_ground(tree_scan):
    asked = []

    def ndvi_of(index):
        asked.append(index)
        return np.full(len(index), 0.7)

    detection = detect(tree_scan.points, ndvi_of, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    assert len(asked) == 1
    heights = tree_scan.points["z"][asked[0]] + LIDAR_HEIGHT
    assert heights.min() >= 0.04 and len(asked[0]) < 0.5 * len(tree_scan.points)
    assert all(c.ndvi == pytest.approx(0.7) for c in detection.clusters)


def test_a_trunk_under_its_crown_is_where_the_tree_stands():
    """Each crown's cluster carries the axis of the one trunk under it: a 16 cm and a
    30 cm trunk, a lobed crown whose returns' centre is decimetres off its trunk, and a
    trunk with a weed clump as narrow beside it (rough foliage, not bark). The axis is
    the returns' mean moved back by pi/4 of the radius: the old trunk's raw mean lies
    ~12 cm in front of it."""
    rng = np.random.default_rng(3)
    specs = {
        "mature": TreeSpec("M", "1", 5.0, -2.5, 0.45, 0.08, 1.35, 1.1),
        "old": TreeSpec("O", "1", 7.0, 4.0, 0.6, 0.15, 2.3, 2.2),
        "lobed": TreeSpec(
            "L", "1", -5.0, 3.0, 0.45, 0.08, 1.35, 1.1,
            lobes=((0.6, 0.3, 0.0, 1.0, 0.8), (0.4, -0.5, 0.1, 0.9, 0.8)),
        ),
    }  # fmt: skip
    meshes = [tree_mesh(spec, Ground(), rng) for spec in specs.values()]
    # Under the mature crown, nearer the robot than its trunk: more returns than the trunk.
    weed = weed_clump(4.8, -1.8, 0.0, 0.23, 0.4, rng)
    scan = scan_of(*meshes, weed)
    clusters = detect(scan.points, None, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    for name, spec in specs.items():
        mine = min(
            clusters, key=lambda c: math.hypot(c.centroid[0] - spec.x, c.centroid[1] - spec.y)
        )
        assert mine.trunk is not None, name
        assert math.hypot(mine.trunk[0] - spec.x, mine.trunk[1] - spec.y) < 0.08, name
    lobed = min(clusters, key=lambda c: math.hypot(c.centroid[0] + 5.0, c.centroid[1] - 3.0))
    assert math.hypot(lobed.centroid[0] + 5.0, lobed.centroid[1] - 3.0) > 0.5
    # Without the smoothness test the weed, as narrow as a trunk and with more returns,
    # is taken for the mature tree's trunk.
    weed_blob = detect(
        scan.points,
        None,
        DEFAULT_T_BASE_LIDAR,
        DetectionConfig(classify=ClassifyConfig(min_roughness_m=1.0)),
    ).clusters
    mature = min(weed_blob, key=lambda c: math.hypot(c.centroid[0] - 5.0, c.centroid[1] + 2.5))
    assert math.hypot(mature.trunk[0] - 4.8, mature.trunk[1] + 1.8) < 0.2
