"""De-skew: every LiDAR point moved from where the sensor was when it fired to where the
sensor was at the scan's reference time (its middle).

A VLP-16 sweep takes 100 ms. At 2 m/s the robot moves 20 cm in it, and turning at
0.5 rad/s it turns 2.9 deg, which moves a point 10 m away by another 50 cm: a straight
wall comes out bent and a trunk smeared. With the robot's pose sampled at a few times
across the sweep (`sample_times`, `sample_poses`: T_world_base, e.g. every 10 ms from the
localizer's history), each point's pose is interpolated linearly between the two samples
around its firing time, and the point is carried through it into the frame at `t_ref`:

    p_ref = T_lidar_base inv(T_world_base(t_ref)) T_world_base(t_i) T_base_lidar p_i

The interpolation blends the neighbouring samples' transforms (the points they give)
rather than their angles: 10 ms apart at 1 rad/s, the blend differs from the exact
rotation by ~1e-5 rad. Points fired outside the sampled span keep the nearest sample's
pose. NumPy rotates the points, a kernel (`treetraits.jit`) moves and blends them.

Clocks: `point_times`, `sample_times` and `t_ref` must share one clock. A `Scan`'s
per-point `t` is on the sensor's clock (VLP-16 microseconds past the hour): use
`scan_point_host_times`, which keeps only its durations and anchors them on `t_host`, as
`scan_mid_time` does.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from treetraits.drivers.records import POINT_DTYPE, Scan, take_points
from treetraits.jit import kernel, warm_up


def scan_point_host_times(scan: Scan, points: np.ndarray | None = None) -> np.ndarray:
    """Each point's firing time on the host clock (int64 ns): the sensor's durations
    anchored on `t_host`, the receive time of the scan's last firing (so the scan's
    middle is `scan_mid_time(scan)`)."""
    pts = scan.points if points is None else points
    return pts["t"].astype(np.int64) + np.int64(scan.t_host - scan.t_end)


def deskew(
    points: np.ndarray,
    point_times: np.ndarray,
    sample_times: np.ndarray,
    sample_poses: np.ndarray,
    t_ref: int,
    T_base_lidar: np.ndarray | None = None,
) -> np.ndarray:
    """`points` (N, 3) in the LiDAR frame, each at its own firing time (`point_times`,
    int64 ns), to the LiDAR frame at `t_ref`. `sample_poses` (M, 4, 4): T_world_base at
    `sample_times` (M >= 1, increasing). `T_base_lidar` (4, 4): the LiDAR's mounting
    (identity when None: the points are in the base frame). Returns (N, 3) float64."""
    xyz = np.asarray(points, dtype=float).reshape(-1, 3)
    times = np.array(sample_times, dtype=np.int64)  # a copy: C-ordered, writable (kernel)
    poses = np.asarray(sample_poses, dtype=float).reshape(-1, 4, 4)
    if len(times) != len(poses) or len(times) == 0:
        raise ValueError("deskew needs one pose per sample time, and at least one")
    if np.any(np.diff(times) <= 0):
        raise ValueError("deskew: sample times must increase")
    if len(times) == 1 or len(xyz) == 0:
        return xyz.copy()
    base_lidar = np.eye(4) if T_base_lidar is None else np.asarray(T_base_lidar, dtype=float)
    lidar_base = np.linalg.inv(base_lidar)

    ref = _blend(poses, times, np.array([t_ref], dtype=np.int64))[0]
    # A_k: the LiDAR frame at sample k, seen from the LiDAR frame at t_ref.
    a = lidar_base @ np.linalg.inv(ref) @ poses @ base_lidar  # (M, 4, 4)

    t = np.clip(np.asarray(point_times, dtype=np.int64), times[0], times[-1])
    order = None
    if np.any(t[1:] < t[:-1]):  # a scan is in firing order; anything else is sorted here
        order = np.argsort(t, kind="stable")
        t, xyz = t[order], xyz[order]
    # Both neighbours' rotations applied to each point by NumPy (BLAS), one interval (a
    # contiguous run of points) at a time: a few 3x3 products over many points beat a
    # 3x3 per point by ~10x. The translations and the blend in one compiled pass.
    edges = np.concatenate(([0], np.searchsorted(t, times[1:-1], side="right"), [len(t)]))
    rotated = np.empty((2, *xyz.shape))
    for j in range(len(times) - 1):
        lo, hi = edges[j], edges[j + 1]
        if lo < hi:
            np.matmul(xyz[lo:hi], a[j, :3, :3].T, out=rotated[0, lo:hi])
            np.matmul(xyz[lo:hi], a[j + 1, :3, :3].T, out=rotated[1, lo:hi])
    out = np.empty(xyz.shape)
    _translate_and_blend(
        rotated,
        np.ascontiguousarray(a[:, :3, 3]),
        t,
        times,
        edges,
        _NO_ORDER if order is None else order,
        out,
    )
    return out


_NO_ORDER = np.empty(0, dtype=np.int64)  # the points are in firing order already


@kernel
def _translate_and_blend(rotated, shifts, t, times, edges, order, out):
    """Per point of interval j (points edges[j]:edges[j + 1], sorted by time `t`): its
    rotations by samples j and j + 1 (`rotated[0]`, `rotated[1]`) moved by their
    `shifts` and blended linearly by its time between the samples, into `out` (at
    `order[k]` for the k-th sorted point, if `order` is not empty), NumPy's steps."""
    for j in range(times.shape[0] - 1):
        span = np.float64(times[j + 1] - times[j])
        for k in range(edges[j], edges[j + 1]):
            w = np.float64(t[k] - times[j]) / span
            into = order[k] if order.shape[0] else k
            for c in range(3):
                p0 = rotated[0, k, c] + shifts[j, c]
                p1 = rotated[1, k, c] + shifts[j + 1, c]
                out[into, c] = p0 + w * (p1 - p0)


def _blend(poses: np.ndarray, times: np.ndarray, at: np.ndarray) -> np.ndarray:
    """T_world_base at the times `at`, blended linearly between the samples around them
    (re-orthonormalised: a blend of rotations is not quite one)."""
    t = np.clip(at, times[0], times[-1])
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    w = ((t - times[k]) / (times[k + 1] - times[k]).astype(float))[:, None, None]
    out = (1 - w) * poses[k] + w * poses[k + 1]
    u, _, vt = np.linalg.svd(out[:, :3, :3])
    out[:, :3, :3] = u @ vt
    return out


def deskew_scan(
    scan: Scan,
    sample_times: np.ndarray,
    sample_poses: np.ndarray,
    t_ref: int,
    T_base_lidar: np.ndarray | None = None,
) -> Scan:
    """The scan with every point de-skewed to `t_ref` (host clock); other fields kept."""
    points = take_points(scan.points, slice(None))
    # The fields read (into float64, as `deskew` works) and written back in one compiled
    # pass each, where NumPy took one per field; the times as `scan_point_host_times`.
    xyz, times = _read_points(
        points["x"], points["y"], points["z"], points["t"], np.int64(scan.t_host - scan.t_end)
    )
    moved = deskew(xyz, times, sample_times, sample_poses, t_ref, T_base_lidar)
    _write_points(moved, points["x"], points["y"], points["z"])
    return replace(scan, points=points)


@kernel
def _read_points(x, y, z, t, offset):
    """(N x 3 float64 of the fields x, y, z; t + offset as int64), NumPy's conversions."""
    xyz = np.empty((x.shape[0], 3))
    times = np.empty(x.shape[0], dtype=np.int64)
    for i in range(x.shape[0]):
        xyz[i, 0], xyz[i, 1], xyz[i, 2] = x[i], y[i], z[i]
        times[i] = np.int64(t[i]) + offset
    return xyz, times


@kernel
def _write_points(moved, x, y, z):
    """The columns of `moved` into the float32 fields (rounded to nearest, as NumPy)."""
    for i in range(moved.shape[0]):
        x[i], y[i], z[i] = moved[i, 0], moved[i, 1], moved[i, 2]


@warm_up
def compile_kernels() -> None:
    """The kernels compiled for the types a scan gives them: two points fired between
    two poses a metre apart, out of firing order; a scan's fields read and written."""
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, 0, 3] = 1.0
    deskew(np.ones((2, 3)), np.array([7, 3]), np.array([0, 10]), poses, 5, np.eye(4))
    points = np.zeros(2, dtype=POINT_DTYPE)  # a scan's fields: strided views
    xyz, _ = _read_points(points["x"], points["y"], points["z"], points["t"], np.int64(5))
    _write_points(xyz, points["x"], points["y"], points["z"])
