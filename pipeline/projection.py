"""LiDAR points into the camera image: the camera model of calibration v1, a z-buffer for
occlusion, per-point NDVI, and the choice of the camera frame for a scan.

Frames as in docs/architecture.md: `p_camera = T_camera_lidar @ p_lidar`, camera = OpenCV
optical (z forward, x right, y down); the lens is OpenCV's radial-tangential model
(k1 k2 p1 p2 k3), so `project_points` gives what `cv2.projectPoints` gives. Pure functions
over arrays and records; the rules are written out in docs/ndvi_projection.md.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from treetraits.drivers.calibration import CameraModel
from treetraits.drivers.records import Scan
from treetraits.jit import kernel, warm_up
from treetraits.pipeline.ndvi import PixelNdvi

# Points nearer than this to the lens plane are "behind": the model is meaningless there
# and the VLP-16 reports nothing closer than ~0.4 m anyway.
MIN_DEPTH_M = 0.05


class PointStatus(enum.IntEnum):
    """Why a point has (or has not) an NDVI value."""

    OK = 0
    BEHIND = 1  # behind the camera (or closer than MIN_DEPTH_M to the lens plane)
    OUTSIDE = 2  # in front but projects outside the image (or beyond the lens model's range)
    OCCLUDED = 3  # its pixel shows a nearer surface (z-buffer rule)
    NO_NDVI = 4  # its pixel has no NDVI (nir + red == 0)
    NO_FRAME = 5  # no usable camera frame for this scan (see FusedScan.reason)


def xyz(points: np.ndarray) -> np.ndarray:
    """N x 3 float64 coordinates from a POINT_DTYPE array or any N x 3 array."""
    if points.dtype.names:
        # Straight into float64 (one conversion, not a float32 stack first).
        out = np.empty((len(points), 3))
        out[:, 0], out[:, 1], out[:, 2] = points["x"], points["y"], points["z"]
        return out
    array = np.asarray(points, dtype=np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"expected N x 3 points, got shape {array.shape}")
    return array


def max_valid_radius(dist: Sequence[float]) -> float:
    """The normalised radius up to which the radial distortion still grows with the angle.

    Past it the polynomial folds back and a point far outside the field of view would land
    inside the image; such points are OUTSIDE. inf when the model never folds.
    """
    return _max_valid_radius(tuple(float(k) for k in dist))


@functools.lru_cache(maxsize=16)
def _max_valid_radius(dist: tuple[float, ...]) -> float:
    # Once per camera, not per scan: the lens does not change, and np.roots (an
    # eigenvalue solve) is dear next to the rest of a scan's projection.
    k1, k2, _, _, k3 = (list(dist) + [0.0] * 5)[:5]
    # d/dr of r (1 + k1 r^2 + k2 r^4 + k3 r^6), in s = r^2: 1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3
    roots = np.roots(np.trim_zeros([7 * k3, 5 * k2, 3 * k1, 1.0], "f"))
    real = [r.real for r in roots if abs(r.imag) < 1e-12 and r.real > 0]
    return float(np.sqrt(min(real))) if real else float("inf")


@dataclass(frozen=True)
class Projection:
    """Where each point lands. `uv` is computed for every point (as cv2.projectPoints
    would), but only `in_image` points have a meaningful `pixel` (column, row)."""

    uv: np.ndarray  # N x 2 float64, pixels (OpenCV: pixel centres at integers)
    depth: np.ndarray  # N float64, metres along the optical axis (camera z)
    in_front: np.ndarray  # N bool: depth >= MIN_DEPTH_M and within the lens model's range
    in_image: np.ndarray  # N bool: in front and on a pixel of the image
    pixel: np.ndarray  # N x 2 int64: (column, row) = round(u), round(v); valid where in_image


def project_points(
    points: np.ndarray,
    camera: CameraModel,
    T_camera_lidar: np.ndarray,
    min_depth: float = MIN_DEPTH_M,
) -> Projection:
    """Project LiDAR-frame points through `T_camera_lidar`, K and the distortion."""
    # The rotation by NumPy (BLAS), the rest in one compiled pass.
    rotated = xyz(points) @ T_camera_lidar[:3, :3].T
    limit = max_valid_radius(camera.dist)
    uv, depth, in_front, in_image, pixel = _project(
        rotated,
        np.array(T_camera_lidar[:3, 3], dtype=np.float64),
        np.array(camera.dist, dtype=np.float64),
        np.array(camera.K, dtype=np.float64),
        float(min_depth),
        float(limit * limit) if np.isfinite(limit) else -1.0,
        int(camera.width),
        int(camera.height),
    )
    return Projection(uv, depth, in_front, in_image, pixel)


@kernel
def _project(rotated, shift, dist, K, min_depth, limit2, width, height):
    """The NumPy steps of the projection, point by point: `rotated` (N x 3, the points
    rotated into the camera frame) moved by `shift`, divided by the depth, distorted,
    through K, and tested against the lens model's radius (`limit2`, squared; < 0: none)
    and the image."""
    n = rotated.shape[0]
    uv = np.empty((n, 2))
    depth = np.empty(n)
    in_front = np.empty(n, dtype=np.bool_)
    in_image = np.empty(n, dtype=np.bool_)
    pixel = np.zeros((n, 2), dtype=np.int64)
    k1, k2, p1, p2, k3 = dist[0], dist[1], dist[2], dist[3], dist[4]
    for i in range(n):
        px = rotated[i, 0] + shift[0]
        py = rotated[i, 1] + shift[1]
        d = rotated[i, 2] + shift[2]
        depth[i] = d
        # np.divide: the hardware's quotient, as NumPy's (`/` raises on a zero divisor).
        x = np.divide(px, d)
        y = np.divide(py, d)
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
        v = K[1, 1] * yd + K[1, 2]
        uv[i, 0], uv[i, 1] = u, v
        front = d >= min_depth
        if limit2 >= 0.0:
            front = front and r2 < limit2
        in_front[i] = front
        column, row = np.floor(u + 0.5), np.floor(v + 0.5)
        inside = front and column >= 0 and column < width and row >= 0 and row < height
        in_image[i] = inside
        if inside:
            pixel[i, 0], pixel[i, 1] = np.int64(column), np.int64(row)
    return uv, depth, in_front, in_image, pixel


@dataclass(frozen=True)
class OcclusionRule:
    """The z-buffer: the image is cut into `block_px` square blocks; each block keeps the
    nearest depth of the points landing in it; a point is OCCLUDED when its depth exceeds
    the nearest depth found in its own block or the `neighbours` blocks around it by more
    than `margin_m + margin_rel * nearest`.

    Why blocks and neighbours: LiDAR points are sparse in the image (VLP-16 rings ~25 px
    apart at 720p, ~2.5 px along a ring), so a surface does not cover every pixel it
    hides; a far point seen through the parallax between the two sensors lands *between*
    the near surface's points. Why a margin: points on one surface (a canopy, a slanted
    wall) differ in depth within a block and must not hide each other.
    """

    block_px: int = 8
    neighbours: int = 1
    margin_m: float = 0.3
    margin_rel: float = 0.1
    enabled: bool = True


def occluded(projection: Projection, width: int, height: int, rule: OcclusionRule) -> np.ndarray:
    """N bool: in-image points hidden behind a nearer surface under `rule`."""
    hidden = np.zeros(len(projection.depth), dtype=bool)
    if not rule.enabled or not projection.in_image.any():
        return hidden
    b = rule.block_px
    return _hidden(
        projection.in_image,
        projection.pixel,
        projection.depth,
        b,
        -(-height // b),
        -(-width // b),
        rule.neighbours,
        float(rule.margin_m),
        float(rule.margin_rel),
    )


@kernel
def _hidden(in_image, pixel, depth, b, rows, cols, n, margin_m, margin_rel):
    """`occluded`'s z-buffer in two passes: each block's nearest depth, then each point
    against the nearest of the blocks around its own (the grid's edge as +inf padding)."""
    nearest = np.full((rows, cols), np.inf)
    for i in range(depth.shape[0]):
        if in_image[i]:
            r, c = pixel[i, 1] // b, pixel[i, 0] // b
            nearest[r, c] = min(nearest[r, c], depth[i])
    hidden = np.zeros(depth.shape[0], dtype=np.bool_)
    for i in range(depth.shape[0]):
        if in_image[i]:
            r, c = pixel[i, 1] // b, pixel[i, 0] // b
            front = np.inf
            for rr in range(max(r - n, 0), min(r + n + 1, rows)):
                for cc in range(max(c - n, 0), min(c + n + 1, cols)):
                    front = min(front, nearest[rr, cc])
            hidden[i] = depth[i] > front + margin_m + margin_rel * front
    return hidden


@dataclass(frozen=True)
class PointNdvi:
    """NDVI per point (NaN unless status is OK) and the reason for each NaN."""

    ndvi: np.ndarray  # N float32
    status: np.ndarray  # N uint8, PointStatus values

    def counts(self) -> dict[str, int]:
        """Points per status, by lower-case name (every status listed)."""
        found = np.bincount(self.status, minlength=len(PointStatus))
        return {s.name.lower(): int(found[s]) for s in PointStatus}


def point_ndvi(
    points: np.ndarray,
    ndvi_frame: np.ndarray | PixelNdvi,
    camera: CameraModel,
    T_camera_lidar: np.ndarray,
    rule: OcclusionRule | None = None,
    projection: Projection | None = None,
) -> PointNdvi:
    """Each point takes the NDVI of the pixel it lands on; NaN (with a status) when it is
    behind the camera, outside the image, occluded, or its pixel has no NDVI.
    `ndvi_frame`: the H x W NDVI frame, or a `PixelNdvi` that works out only the pixels
    read."""
    if ndvi_frame.shape[:2] != (camera.height, camera.width):
        raise ValueError(
            f"NDVI frame {ndvi_frame.shape[1]}x{ndvi_frame.shape[0]} is not the calibrated "
            f"{camera.width}x{camera.height}"
        )
    if projection is None:
        projection = project_points(points, camera, T_camera_lidar)
    rule = OcclusionRule() if rule is None else rule
    n = len(projection.depth)
    hidden = occluded(projection, camera.width, camera.height, rule)
    status, visible = _statuses(projection.depth, projection.in_front, projection.in_image, hidden)
    values = np.full(n, np.nan, dtype=np.float32)
    cols, rows = projection.pixel[visible, 0], projection.pixel[visible, 1]
    sampled = ndvi_frame[rows, cols].astype(np.float32)
    values[visible] = sampled
    status[visible] = np.where(np.isnan(sampled), PointStatus.NO_NDVI, PointStatus.OK)
    return PointNdvi(values, status)


@kernel
def _statuses(depth, in_front, in_image, hidden):
    """Each point's status short of its NDVI (BEHIND, OUTSIDE, or OCCLUDED for every
    in-image point) and whether it is visible (in the image and not hidden)."""
    status = np.empty(depth.shape[0], dtype=np.uint8)
    visible = np.empty(depth.shape[0], dtype=np.bool_)
    for i in range(depth.shape[0]):
        if in_image[i]:
            status[i] = _OCCLUDED
        elif in_front[i] or depth[i] >= MIN_DEPTH_M:
            # In front but beyond the lens model's fold-back radius: OUTSIDE, not BEHIND.
            status[i] = _OUTSIDE
        else:
            status[i] = _BEHIND
        visible[i] = in_image[i] and not hidden[i]
    return status, visible


_OCCLUDED, _OUTSIDE, _BEHIND = (
    np.uint8(PointStatus.OCCLUDED),
    np.uint8(PointStatus.OUTSIDE),
    np.uint8(PointStatus.BEHIND),
)


@warm_up
def compile_kernels() -> None:
    """The projection's kernels compiled for a scan's types: two points, one in a
    640 x 480 image, one at zero depth."""
    camera = CameraModel(
        640,
        480,
        np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]]),
        np.array([-0.1, 0.01, 0.001, 0.001, 0.0]),
        {"red": 2, "nir": 0},
    )
    points = np.array([[0.1, 0.2, 5.0], [1.0, 0.0, 0.0]])
    projection = project_points(points, camera, np.eye(4))
    hidden = occluded(projection, camera.width, camera.height, OcclusionRule())
    _statuses(projection.depth, projection.in_front, projection.in_image, hidden)


# --- which frame goes with a scan --------------------------------------------------------

# A scan takes the frame nearest its middle if it is no further away than this: half the
# LiDAR's 100 ms period, so at 1 m/s the camera has moved at most 5 cm.
DEFAULT_MAX_SKEW_NS = 50_000_000


def scan_mid_time(scan: Scan) -> int:
    """The middle of a scan on the host clock (ns since the epoch).

    Anchored on `t_host` (receive time of the scan's last packet), not on the device's
    `t_start`/`t_end`: an unsynchronised VLP-16 counts its microseconds from power-on, so
    its absolute time can be off by minutes, while its durations are right. Camera
    `t_capture` is on the host clock too. Network latency (< 1 ms) is ignored.
    """
    return scan.t_host - (scan.t_end - scan.t_start) // 2


@dataclass(frozen=True, slots=True)
class FrameMatch:
    """The frame chosen for a time: `index` into the list, None when none is usable."""

    index: int | None
    skew_ns: int | None  # frame time - wanted time of the nearest frame (None: no frames)
    reason: str  # "ok", "no_frame" (empty list) or "skew" (nearest beyond the limit)

    @property
    def ok(self) -> bool:
        return self.index is not None


def nearest_frame(
    frame_times: Sequence[int] | np.ndarray, t: int, max_skew_ns: int = DEFAULT_MAX_SKEW_NS
) -> FrameMatch:
    """The frame whose time is nearest `t`, refused beyond `max_skew_ns` (ties: the first
    in the list)."""
    times = np.asarray(frame_times, dtype=np.int64)
    if times.size == 0:
        return FrameMatch(None, None, "no_frame")
    skews = times - np.int64(t)
    best = int(np.argmin(np.abs(skews)))
    skew = int(skews[best])
    if abs(skew) > max_skew_ns:
        return FrameMatch(None, skew, "skew")
    return FrameMatch(best, skew, "ok")
