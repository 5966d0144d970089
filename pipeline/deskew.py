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
pose. One compiled pass (`treetraits.jit`) moves and blends every point.

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
    times, a = _sample_transforms(sample_times, sample_poses, t_ref, T_base_lidar)
    if len(times) == 1 or len(xyz) == 0:
        return xyz.copy()
    out = np.empty(xyz.shape)
    t = np.asarray(point_times, dtype=np.int64)
    columns = (xyz[:, 0], xyz[:, 1], xyz[:, 2])
    _move_points(*columns, t, np.int64(0), times, a, out[:, 0], out[:, 1], out[:, 2])
    return out


def _sample_transforms(
    sample_times: np.ndarray,
    sample_poses: np.ndarray,
    t_ref: int,
    T_base_lidar: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """The sample times (int64, C-ordered) and A_k (M, 4, 4): the LiDAR frame at sample
    k seen from the LiDAR frame at `t_ref`. ValueError for samples that do not fit."""
    times = np.array(sample_times, dtype=np.int64)  # a copy: C-ordered, writable (kernel)
    poses = np.asarray(sample_poses, dtype=float).reshape(-1, 4, 4)
    if len(times) != len(poses) or len(times) == 0:
        raise ValueError("deskew needs one pose per sample time, and at least one")
    if np.any(np.diff(times) <= 0):
        raise ValueError("deskew: sample times must increase")
    if len(times) == 1:
        return times, np.eye(4)[None]  # one pose: nothing moves
    base_lidar = np.eye(4) if T_base_lidar is None else np.asarray(T_base_lidar, dtype=float)
    lidar_base = np.linalg.inv(base_lidar)
    ref = _blend(poses, times, np.array([t_ref], dtype=np.int64))[0]
    return times, lidar_base @ np.linalg.inv(ref) @ poses @ base_lidar


@kernel
def _move_points(x, y, z, t, offset, times, a, out_x, out_y, out_z):
    """Each point (x, y, z at time t + offset, clipped to the samples' span) through
    A_j and A_j+1 of its interval (times[j] < t <= times[j + 1]; the first interval from
    times[0] on) and blended linearly by its time between them, into out_x, out_y, out_z
    (float64, or float32 rounded to nearest as NumPy casts; they may be x, y, z: a point
    is read before it is written). The rotations are written out as sums, not left to
    BLAS, so every machine gives the same bits; one pass without temporaries, the
    interval found by a walk (a scan comes in firing order)."""
    last = times.shape[0] - 1
    outputs = (out_x, out_y, out_z)
    j = 0
    for i in range(x.shape[0]):
        ti = min(max(np.int64(t[i]) + offset, times[0]), times[last])
        while j > 0 and ti <= times[j]:
            j -= 1
        while j < last - 1 and ti > times[j + 1]:
            j += 1
        w = np.float64(ti - times[j]) / np.float64(times[j + 1] - times[j])
        px, py, pz = np.float64(x[i]), np.float64(y[i]), np.float64(z[i])
        b, c = a[j], a[j + 1]
        for r in range(3):
            p0 = px * b[r, 0] + py * b[r, 1] + pz * b[r, 2] + b[r, 3]
            p1 = px * c[r, 0] + py * c[r, 1] + pz * c[r, 2] + c[r, 3]
            outputs[r][i] = p0 + w * (p1 - p0)


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
    times, a = _sample_transforms(sample_times, sample_poses, t_ref, T_base_lidar)
    if len(times) > 1 and len(points):
        # The float32 fields moved in place by one compiled pass; the times as
        # `scan_point_host_times` gives them.
        fields = (points["x"], points["y"], points["z"])
        offset = np.int64(scan.t_host - scan.t_end)
        _move_points(*fields, points["t"], offset, times, a, *fields)
    return replace(scan, points=points)


@warm_up
def compile_kernels() -> None:
    """The kernels compiled for the types a scan gives them: two points fired between
    two poses a metre apart, out of firing order, as an array and as a scan's fields."""
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, 0, 3] = 1.0
    deskew(np.ones((2, 3)), np.array([7, 3]), np.array([0, 10]), poses, 5, np.eye(4))
    points = np.zeros(2, dtype=POINT_DTYPE)  # a scan's fields: strided views
    points["t"] = [7, 3]
    deskew_scan(Scan(points, 3, 7, 7, True, 0, 0, "VLP-16", "strongest"), [0, 10], poses, 5)
