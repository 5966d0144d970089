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
        return np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float64)
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
    # Once per camera, not per scan: np.roots costs ~0.3 ms.
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
    p = xyz(points) @ T_camera_lidar[:3, :3].T + T_camera_lidar[:3, 3]
    depth = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = p[:, 0] / depth
        y = p[:, 1] / depth
    k1, k2, p1, p2, k3 = camera.dist
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    K = camera.K
    u = K[0, 0] * xd + K[0, 1] * yd + K[0, 2]
    v = K[1, 1] * yd + K[1, 2]
    uv = np.column_stack([u, v])

    in_front = depth >= min_depth
    limit = max_valid_radius(camera.dist)
    if np.isfinite(limit):
        in_front &= r2 < limit * limit
    with np.errstate(invalid="ignore"):
        # Pixel centres sit at integer coordinates: pixel (c, r) covers [c-0.5, c+0.5).
        column = np.floor(u + 0.5)
        row = np.floor(v + 0.5)
        in_image = (
            in_front & (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height)
        )
    pixel = np.zeros((len(p), 2), dtype=np.int64)
    pixel[in_image, 0] = column[in_image]
    pixel[in_image, 1] = row[in_image]
    return Projection(uv, depth, in_front, in_image, pixel)


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
    rows, cols = -(-height // b), -(-width // b)
    index = np.flatnonzero(projection.in_image)
    col, row = projection.pixel[index, 0] // b, projection.pixel[index, 1] // b
    block = row * cols + col
    depth = projection.depth[index]
    nearest = np.full(rows * cols, np.inf)
    np.minimum.at(nearest, block, depth)
    nearest = nearest.reshape(rows, cols)
    n = rule.neighbours
    if n > 0:
        # Minimum over the (2n+1)^2 blocks around each block (a min filter on the grid).
        padded = np.pad(nearest, n, constant_values=np.inf)
        spread = nearest.copy()
        for dr in range(2 * n + 1):
            for dc in range(2 * n + 1):
                np.minimum(spread, padded[dr : dr + rows, dc : dc + cols], out=spread)
        nearest = spread
    front = nearest.ravel()[block]
    hidden[index] = depth > front + rule.margin_m + rule.margin_rel * front
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
    status = np.full(n, PointStatus.OUTSIDE, dtype=np.uint8)
    status[~projection.in_front] = PointStatus.BEHIND
    # In front but beyond the lens model's fold-back radius: OUTSIDE, not BEHIND.
    status[(projection.depth >= MIN_DEPTH_M) & ~projection.in_front] = PointStatus.OUTSIDE
    values = np.full(n, np.nan, dtype=np.float32)
    visible = projection.in_image & ~occluded(projection, camera.width, camera.height, rule)
    status[projection.in_image] = PointStatus.OCCLUDED
    cols, rows = projection.pixel[visible, 0], projection.pixel[visible, 1]
    sampled = ndvi_frame[rows, cols].astype(np.float32)
    values[visible] = sampled
    status[visible] = np.where(np.isnan(sampled), PointStatus.NO_NDVI, PointStatus.OK)
    return PointNdvi(values, status)


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
