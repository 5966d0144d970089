"""The compiled steps of the clusters' features (`treetraits.jit` kernels) give the same
bits as the NumPy formulations they replaced: the roughness along the rings and the
beam-above test, on the groups and clusters a ray-cast VLP-16 scan of trees, a person, a
post and a wall gives them, and on edge cases of the arithmetic (NaN, the +-pi seam)."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest

from tests.helpers.kernels import assert_warm_ups_cover
from tests.helpers.scans import scan_of
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline import classify, detection, visibility
from treetraits.pipeline.classify import roughness_of_groups, roughness_of_groups_numpy
from treetraits.pipeline.config import DetectionConfig
from treetraits.pipeline.visibility import BeamsAbove
from treetraits.sim.clutter import box, cylinder, person
from treetraits.sim.orchard import Ground, TreeSpec, tree_mesh

TREES = (
    TreeSpec("A", "1", 4.0, -3.0, 0.45, 0.08, 1.35, 1.2),
    TreeSpec("B", "1", 12.0, 3.0, 0.45, 0.08, 1.35, 1.2),
    TreeSpec("C", "1", -4.0, 2.0, 0.3, 0.04, 0.5, 0.45),
    TreeSpec("D", "1", -9.0, -4.5, 0.45, 0.08, 1.75, 1.3),
)


@functools.cache
def scan_points() -> np.ndarray:
    rng = np.random.default_rng(7)
    meshes = [tree_mesh(spec, Ground(), rng) for spec in TREES]
    meshes += [person(5.0, 1.5, 0.0), cylinder(3.0, 4.0, 0.0, 2.0, 0.05)]
    meshes.append(box(-6.0, 5.0, 0.0, 2.5, 6.0, 0.2))
    return scan_of(*meshes).points


@functools.cache
def detected_calls() -> tuple[list[tuple], list[tuple]]:
    """The arguments `detect` gives the roughness and the beam-above test on the scan."""
    rough_calls, top_calls = [], []
    saved, original = detection.roughness_of_groups, BeamsAbove.top_view

    def rough(*args):
        rough_calls.append(args)
        return saved(*args)

    def top_view(self, members, window, reach):
        top_calls.append((self, members, window, reach))
        return original(self, members, window, reach)

    detection.roughness_of_groups, BeamsAbove.top_view = rough, top_view
    try:
        detection.detect(scan_points(), None, DEFAULT_T_BASE_LIDAR, DetectionConfig())
    finally:
        detection.roughness_of_groups, BeamsAbove.top_view = saved, original
    return rough_calls, top_calls


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and np.array_equal(a.view(np.int64), b.view(np.int64))


def test_roughness_kernel_is_numpys_to_the_bit_on_a_scan():
    rough_calls, _ = detected_calls()
    assert len(rough_calls) >= 2  # the trunks' bark, the clusters' features
    found = [roughness_of_groups(*args) for args in rough_calls]
    for args, values in zip(rough_calls, found, strict=True):
        assert args[0].dtype == np.float64 and args[1].dtype == np.uint8  # the kernel's
        assert same_bits(values, roughness_of_groups_numpy(*args))
    every = np.concatenate(found)
    assert np.isfinite(every).sum() >= 6 and np.isnan(every).any()
    assert every[np.isfinite(every)].min() < 0.05 < every[np.isfinite(every)].max()


def test_roughness_kernel_is_numpys_to_the_bit_at_the_edges():
    """Empty and tiny groups, even and odd counts, repeated bearings, a NaN return (its
    group's median is NaN), rings given as int64."""
    xyz, rings, lidar_xy, _ = detected_calls()[0][-1]
    rng = np.random.default_rng(3)
    points = xyz.copy()
    points[5] = np.nan
    points[40:60] = points[40]  # one bearing repeated
    sizes = np.array([0, 1, 2, 3, 30, 31, 0])
    sizes = np.append(sizes, len(points) - sizes.sum())
    for ring in (rings, rings.astype(np.int64), rng.integers(0, 2, len(rings))):
        found = roughness_of_groups(points, ring, lidar_xy, sizes)
        assert same_bits(found, roughness_of_groups_numpy(points, ring, lidar_xy, sizes))
    assert np.isnan(found[:4]).all()  # too few returns


@pytest.mark.parametrize("data", ["scan", "spread"])
def test_each_distance_off_the_middle_is_numpys_norm(data):
    """Every triple, each distance alone (the medians see a few of them): the scan's
    returns, and returns spread over four orders of magnitude, where a sum of the
    squares in another order differs in the last bit."""
    xyz = np.ascontiguousarray(detected_calls()[0][-1][0])
    if data == "spread":
        rng = np.random.default_rng(5)
        xyz = rng.normal(size=(5000, 3)) * rng.uniform(1e-3, 10, (5000, 1))
    d = xyz[1:-1] - (xyz[:-2] + xyz[2:]) / 2
    want = np.linalg.norm(d, axis=1)
    order = np.arange(len(xyz))
    got = np.array([classify._off_middle(xyz, order, i) for i in range(1, len(xyz) - 1)])
    assert len(got) > 1000 and same_bits(got, want)
    if data == "spread":  # the data tells the orders apart
        other = np.sqrt(d[:, 0] * d[:, 0] + (d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]))
        assert not same_bits(other, want)


def lexsort(azimuth: np.ndarray, ring: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    return np.lexsort((azimuth, ring, np.repeat(np.arange(len(sizes)), sizes)))


def test_the_order_by_group_ring_and_bearing_is_lexsorts_on_a_scan():
    rough_calls, _ = detected_calls()
    for xyz, ring, lidar_xy, sizes in rough_calls:
        azimuth = classify._bearings(xyz, lidar_xy)
        got = classify._lexsort_groups(ring.astype(np.int64), azimuth, sizes.astype(np.int64))
        assert np.array_equal(got, lexsort(azimuth, ring, sizes))


@pytest.mark.parametrize("bearings", ["rising", "falling", "shuffled"])
def test_the_order_is_lexsorts_with_ties_nan_and_signed_zeros(bearings):
    """Equal bearings keep their index order, NaN sorts last, -0.0 ties with 0.0, in
    runs that rise (turned around first when they fall) or have no order."""
    rng = np.random.default_rng(6)
    for _ in range(300):
        sizes = rng.integers(0, 60, rng.integers(1, 6))
        n = int(sizes.sum())
        azimuth = np.round(rng.uniform(-3, 3, n), rng.integers(0, 3))  # many ties
        if bearings != "shuffled":
            azimuth = np.sort(azimuth)[:: 1 if bearings == "rising" else -1].copy()
        azimuth[rng.integers(0, max(n, 1), 3)[: n and 3]] = np.nan
        azimuth[rng.integers(0, max(n, 1), 2)[: n and 2]] = -0.0
        azimuth[rng.integers(0, max(n, 1), 2)[: n and 2]] = 0.0
        ring = rng.integers(0, 16, n)
        got = classify._lexsort_groups(ring, azimuth, sizes)
        assert np.array_equal(got, lexsort(azimuth, ring, sizes))


def test_returns_in_no_order_are_merge_sorted_as_lexsort_sorts_them():
    """A ring of 20,000 returns shuffled (a recording from another driver): the
    insertion sort gives up after a few moves a return and a merge sort takes over."""
    rng = np.random.default_rng(7)
    azimuth = np.round(rng.uniform(-3, 3, 20_000), 2)  # ties
    azimuth[rng.integers(0, 20_000, 5)] = np.nan
    azimuth[rng.integers(0, 20_000, 5)] = -0.0
    ring = np.zeros(20_000, dtype=np.int64)
    sizes = np.array([20_000], dtype=np.int64)
    got = classify._lexsort_groups(ring, azimuth, sizes)
    assert np.array_equal(got, lexsort(azimuth, ring, sizes))


def test_rings_too_far_apart_are_left_to_numpys_lexsort():
    xyz, ring, lidar_xy, sizes = detected_calls()[0][-1]
    far = ring.astype(np.int64) * 1000  # 0 to 15000: no counting sort
    azimuth = classify._bearings(xyz, lidar_xy)
    assert classify._lexsort_groups(far, azimuth, sizes.astype(np.int64)) is None
    found = roughness_of_groups(xyz, far, lidar_xy, sizes)
    assert same_bits(found, roughness_of_groups_numpy(xyz, far, lidar_xy, sizes))
    assert same_bits(found, roughness_of_groups(xyz, ring, lidar_xy, sizes))


def test_a_median_of_an_even_count_and_a_nan_as_numpy_gives_them():
    rng = np.random.default_rng(0)
    for n in (1, 2, 5, 6, 101, 1000):
        values = np.round(rng.uniform(0, 1, n), 2)  # many equal values, as the gaps are
        assert classify._kernel_median(values) == np.median(values)
        values[n // 2] = np.nan
        assert math.isnan(classify._kernel_median(values))


def test_top_seen_kernels_are_numpys_on_a_scan():
    _, top_calls = detected_calls()
    assert len(top_calls) >= 6
    answers = []
    for beams, members, _, _ in top_calls:
        for window in (0.0, math.radians(1.0), 0.2):
            for reach in (0.0, 0.5, 3.0):
                seen = beams.top_seen(members, window, reach)
                assert seen is beams.top_seen_numpy(members, window, reach)
                answers.append(seen)
    assert any(answers) and not all(answers)


def test_top_seen_kernels_across_the_seam_and_with_nan():
    """Members on either side of +-pi, and a NaN height and range, as NumPy's argmax,
    min and max take them."""
    rng = np.random.default_rng(1)
    points = scan_points().copy()
    points["x"] = -np.abs(points["x"])  # everything behind: bearings near +-pi
    beams = BeamsAbove(points)
    seam = np.flatnonzero((np.abs(points["y"]) < 1.0) & (points["ring"] < 12))
    answers = []
    for _ in range(200):
        members = rng.choice(seam, size=rng.integers(1, 40), replace=False)
        for window in (0.0, 0.05):
            seen = beams.top_seen(members, window, 0.5)
            assert seen is beams.top_seen_numpy(members, window, 0.5)
            answers.append(seen)
    assert any(answers) and not all(answers)
    points["z"][seam[:3]] = np.nan
    beams = BeamsAbove(points)
    for members in (seam[:10], seam[2:12], seam[5:15]):
        assert beams.top_seen(members, 0.05, 0.5) is beams.top_seen_numpy(members, 0.05, 0.5)


def numpy_beams(points: np.ndarray) -> tuple:
    """`BeamsAbove`'s arrays as NumPy computed them before its kernel."""
    ring = points["ring"].astype(np.int64)
    x, y, z = (points[axis].astype(float) for axis in "xyz")
    bearing = np.arctan2(y, x)
    order = np.argsort(points["ring"], kind="stable")
    top_ring = max(visibility.TOP_RING, int(ring.max()) if len(ring) else 0)
    span = np.sqrt(x * x + y * y + z * z)
    starts = np.searchsorted(ring[order], np.arange(top_ring + 2))
    return bearing[order], span[order], starts, (x, y, z, bearing, span, ring), top_ring


@pytest.mark.parametrize("rings", ["scan", "more", "none"])
def test_beams_by_ring_are_numpys_to_the_bit(rings):
    """The scan's returns; its rings shuffled up to 31 (a 32-beam cloud); no returns."""
    points = scan_points().copy()
    if rings == "more":
        points["ring"] = np.random.default_rng(2).integers(0, 32, len(points))
    elif rings == "none":
        points = points[:0]
    beams, (bearing, span, starts, by_point, top_ring) = BeamsAbove(points), numpy_beams(points)
    assert beams.top_ring == top_ring == (31 if rings == "more" else 15)
    assert same_bits(beams._bearing, bearing) and same_bits(beams._range, span)
    assert beams._starts.dtype == starts.dtype and np.array_equal(beams._starts, starts)
    for got, want in zip(beams._by_point, by_point, strict=True):
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()


@pytest.mark.parametrize("angle", [-7.0, -math.pi, -1e-17, 0.0, 1e-17, math.pi, 3.5, 7.0])
def test_one_angle_wrapped_as_numpy_wraps_it(angle):
    wrapped = visibility._wrap(np.array([angle, np.nextafter(angle, 9.0)]))
    for value, expected in zip((angle, np.nextafter(angle, 9.0)), wrapped, strict=True):
        assert np.float64(visibility._wrap_one(value)).view(np.int64) == expected.view(np.int64)


def test_a_scan_compiles_nothing_beyond_the_warm_ups():
    kernels = (
        classify._roughness_after_gaps,
        classify._lexsort_groups,
        classify._sort_by_bearing,
        classify._before,
        classify._adjacent,
        classify._off_middle,
        classify._kernel_median,
        visibility._by_ring,
        visibility._top_and_ring,
        visibility._passed_over,
        visibility._wrap_one,
    )
    assert_warm_ups_cover(
        kernels,
        (classify.compile_kernels, visibility.compile_kernels),
        lambda: detection.detect(scan_points(), None, DEFAULT_T_BASE_LIDAR, DetectionConfig()),
    )


def test_a_clusters_ndvi_and_share_are_numpys_means():
    """The NDVI of a cluster is the mean of its returns' finite values and the share is
    np.isfinite(...).mean(), to the bit, with NaN for some returns and whole clusters."""
    points = scan_points()
    rng = np.random.default_rng(9)
    ndvi = rng.uniform(-0.2, 0.9, len(points))
    ndvi[rng.uniform(size=len(points)) < 0.3] = np.nan
    ndvi[points["x"] < -5.0] = np.nan  # clusters there have none
    xyz = detection.to_base(points, DEFAULT_T_BASE_LIDAR)
    of_point = {row.tobytes(): value for row, value in zip(xyz, ndvi, strict=True)}
    clusters = detection.detect(points, ndvi, DEFAULT_T_BASE_LIDAR, DetectionConfig()).clusters
    kinds = set()
    for cluster in clusters:
        values = np.array([of_point[row.tobytes()] for row in cluster.points])
        known = np.isfinite(values)
        want = float(values[known].mean()) if known.any() else math.nan
        assert np.float64(cluster.ndvi).tobytes() == np.float64(want).tobytes()
        assert cluster.shape.ndvi_share == float(known.mean())
        kinds.add((known.all(), known.any()))
    assert {(False, True), (False, False)} <= kinds
