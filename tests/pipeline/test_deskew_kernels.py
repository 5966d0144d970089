"""De-skew's compiled pass (`deskew._move_points`) gives the bits of its NumPy formulation
(the rotations as sums of products, as the kernel writes them), and within rounding what
NumPy's matrix products (BLAS) gave before it, on the walled yard's sweep taken while
driving and turning."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.deskew import SWEEP_NS, T_BASE_LIDAR, T_DEVICE_END, T_HOST_END, samples, sweep
from treetraits.drivers.records import POINT_DTYPE, Scan, take_points
from treetraits.pipeline import deskew as deskew_module
from treetraits.pipeline.deskew import _blend, deskew, deskew_scan, scan_point_host_times
from treetraits.pipeline.projection import scan_mid_time


def numpy_deskew(points, point_times, sample_times, sample_poses, t_ref, T_base_lidar, rotate):
    """`deskew` in NumPy (valid arguments, M >= 2): each interval's points rotated by
    `rotate(p, R)`, moved and blended."""
    xyz = np.asarray(points, dtype=float).reshape(-1, 3)
    times = np.asarray(sample_times, dtype=np.int64)
    poses = np.asarray(sample_poses, dtype=float).reshape(-1, 4, 4)
    lidar_base = np.linalg.inv(T_base_lidar)
    ref = _blend(poses, times, np.array([t_ref], dtype=np.int64))[0]
    a = lidar_base @ np.linalg.inv(ref) @ poses @ T_base_lidar
    t = np.clip(np.asarray(point_times, dtype=np.int64), times[0], times[-1])
    order = None
    if np.any(t[1:] < t[:-1]):
        order = np.argsort(t, kind="stable")
        t, xyz = t[order], xyz[order]
    edges = np.concatenate(([0], np.searchsorted(t, times[1:-1], side="right"), [len(t)]))
    out = np.empty_like(xyz)
    for j in range(len(times) - 1):
        lo, hi = edges[j], edges[j + 1]
        if lo == hi:
            continue
        p = xyz[lo:hi]
        w = ((t[lo:hi] - times[j]) / float(times[j + 1] - times[j]))[:, None]
        p0 = rotate(p, a[j, :3, :3]) + a[j, :3, 3]
        p1 = rotate(p, a[j + 1, :3, :3]) + a[j + 1, :3, 3]
        out[lo:hi] = p0 + w * (p1 - p0)
    if order is not None:
        unsorted = np.empty_like(out)
        unsorted[order] = out
        out = unsorted
    return out


def by_sums(p, r):
    """p @ r.T as the kernel sums it: ((x r0 + y r1) + z r2), no fused multiply-add."""
    return p[:, :1] * r[:, 0] + p[:, 1:2] * r[:, 1] + p[:, 2:] * r[:, 2]


def by_blas(p, r):
    """p @ r.T as BLAS computes it (its own order, fused multiply-adds where it has them)."""
    return p @ r.T


@pytest.mark.parametrize("arrangement", ["firing-order", "shuffled", "sparse-samples"])
def test_deskew_is_numpys_bit_for_bit(arrangement):
    points, dt, _ = sweep()
    times, poses = samples()
    if arrangement == "shuffled":  # sorted, blended and put back in place
        shuffle = np.random.default_rng(5).permutation(len(points))
        points, dt = points[shuffle], dt[shuffle]
    if arrangement == "sparse-samples":  # intervals without points; points past the ends
        keep = [0, 1, 2, 6, 7, len(times) - 3]
        times, poses = times[keep], poses[keep]
    args = (points, dt, times, poses, 1_000_000, T_BASE_LIDAR)
    want = numpy_deskew(*args, by_sums)
    got = deskew(*args)
    assert np.abs(got - points).max() > 0.1  # the robot moved: there was work to do
    assert got.tobytes() == want.tobytes()
    # Within rounding of the matrix products' result: the points are 3-40 m out.
    assert np.abs(got - numpy_deskew(*args, by_blas)).max() < 1e-13
    # A scan compiles nothing beyond the warm-up (an array's and a scan's fields' types).
    deskew_module.compile_kernels()
    assert len(deskew_module._move_points.signatures) == 2


def numpy_deskew_scan(scan, sample_times, sample_poses, t_ref, T_base_lidar):
    """`deskew_scan` as NumPy reads the fields into an array for `deskew` and writes them."""
    points = take_points(scan.points, slice(None))
    xyz = np.empty((len(points), 3))
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = points["x"], points["y"], points["z"]
    moved = deskew(
        xyz, scan_point_host_times(scan), sample_times, sample_poses, t_ref, T_base_lidar
    )
    points["x"], points["y"], points["z"] = moved[:, 0], moved[:, 1], moved[:, 2]
    return points


@pytest.mark.parametrize("arrangement", ["firing-order", "shuffled", "one-sample"])
def test_deskew_scan_reads_and_writes_the_fields_as_numpy(arrangement):
    """The walled yard's sweep as a scan on the sensor's clock (float32 fields, int64
    times): every field of every record the same bytes as NumPy gave."""
    points, dt, _ = sweep()
    cloud = np.zeros(len(points), dtype=POINT_DTYPE)
    cloud["x"], cloud["y"], cloud["z"] = points.T
    cloud["t"] = T_DEVICE_END - SWEEP_NS // 2 + dt
    cloud["intensity"] = np.arange(len(cloud)) % 251
    cloud["ring"] = np.arange(len(cloud)) % 16
    if arrangement == "shuffled":
        cloud = cloud[np.random.default_rng(7).permutation(len(cloud))]
    t_start, t_end = int(cloud["t"].min()), int(cloud["t"].max())
    scan = Scan(cloud, t_start, t_end, T_HOST_END, True, 76, 0, "VLP-16", "strongest")
    middle = scan_mid_time(scan)
    times, poses = samples()
    if arrangement == "one-sample":
        times, poses = times[:1], poses[:1]
    want = numpy_deskew_scan(scan, middle + times, poses, middle, T_BASE_LIDAR)
    got = deskew_scan(scan, middle + times, poses, middle, T_BASE_LIDAR)
    assert got.points.dtype == want.dtype and got.points.tobytes() == want.tobytes()
    moved = np.abs(got.points["x"] - scan.points["x"]).max()
    assert moved > 0.05 if arrangement != "one-sample" else moved == 0
    assert scan.points.tobytes() == cloud.tobytes()  # the scan given is left as it was
    deskew_module.compile_kernels()
    assert len(deskew_module._move_points.signatures) == 2
