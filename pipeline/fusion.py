"""One scan with one camera frame: pick the frame, decode it, NDVI, per-point NDVI.

Never raises for bad data: a missing frame, a frame too far in time, a corrupt JPEG or a
frame of the wrong size gives every point NaN with status NO_FRAME and the reason in
`FusedScan.reason`, for the caller to count. Also the overlay picture of the paper's
Fig. 2b (NDVI frame + LiDAR points coloured by height), as pure array functions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from treetraits.drivers.calibration import Calibration
from treetraits.drivers.records import Frame, Scan
from treetraits.errors import CalibrationError, ParseError
from treetraits.pipeline.ndvi import PixelNdvi, ndvi_image
from treetraits.pipeline.projection import (
    DEFAULT_MAX_SKEW_NS,
    OcclusionRule,
    PointNdvi,
    PointStatus,
    Projection,
    nearest_frame,
    point_ndvi,
    project_points,
    scan_mid_time,
)

# The mapper decodes its frames at half size: a tree's NDVI is the mean over its points,
# and the points resolve no finer detail. At the Survey3N's 720p (fx ~704 px) a VLP-16's
# firings 0.2 deg apart land 2.5 px apart along a ring at the image centre, more towards
# its edges (demo survey: median 3.2 px, 6 % of neighbours nearer than 2 px) and its rings
# 2 deg (~25 px) apart, so at half size each point still reads a pixel of its own, now the
# mean of the 2 x 2 it covered (at a quarter, most neighbours along a ring would share
# one). Measured on the demo survey: every tree's NDVI within 0.0041 of the full-size
# decode (widths, heights, positions and observations unchanged), and the decode, a large
# part of a scan's cost, is cheaper (docs/performance.md). Projection and occlusion stay
# at full size.
MAPPER_REDUCTION = 2

# Frame-level reasons, each counted by the caller.
FRAME_REASONS = ("ok", "no_frame", "skew", "corrupt_jpeg", "size_mismatch")


@dataclass(frozen=True)
class FusionConfig:
    max_skew_ns: int = DEFAULT_MAX_SKEW_NS
    occlusion: OcclusionRule = field(default_factory=OcclusionRule)


@dataclass(frozen=True)
class FusedScan:
    """Per-point NDVI of one scan and how it was obtained."""

    points: PointNdvi
    reason: str  # one of FRAME_REASONS
    detail: str  # a sentence for a log line
    frame: Frame | None  # the frame used (or the refused one, for corrupt/size_mismatch)
    skew_ns: int | None  # frame time - scan middle, None without frames
    ndvi_frame: np.ndarray | None = None
    projection: Projection | None = None

    @property
    def ndvi(self) -> np.ndarray:
        return self.points.ndvi

    def counts(self) -> dict[str, int]:
        return self.points.counts()


def _no_frame(n: int, reason: str, detail: str, frame=None, skew=None) -> FusedScan:
    status = np.full(n, PointStatus.NO_FRAME, dtype=np.uint8)
    points = PointNdvi(np.full(n, np.nan, dtype=np.float32), status)
    return FusedScan(points, reason, detail, frame, skew)


def fuse_scan(
    scan: Scan,
    frames: Sequence[Frame],
    calibration: Calibration,
    config: FusionConfig | None = None,
    *,
    keep_ndvi_frame: bool = True,
    reduction: int = 1,
) -> FusedScan:
    """NDVI for every point of `scan` from the frame nearest its middle (by `t_capture`).

    `keep_ndvi_frame=False`: NDVI is worked out only at the pixels the points land on and
    `FusedScan.ndvi_frame` is None; the per-point values are the same (the mapper's way:
    it needs no picture). With it, `reduction` 2 (or 4, 8) decodes the JPEG at half (a
    quarter, an eighth) of its size: the points are projected and tested for occlusion
    at full size as before, and each takes the NDVI of the reduced pixel that covers its
    pixel (see MAPPER_REDUCTION). Raises CalibrationError only for a calibration without
    a camera; data problems come back as a `reason`.
    """
    if reduction != 1 and keep_ndvi_frame:
        raise ValueError("a reduced decode gives no full NDVI frame: keep_ndvi_frame=False")
    config = FusionConfig() if config is None else config
    camera, extrinsic = calibration.camera, calibration.T_camera_lidar
    if camera is None or extrinsic is None:
        raise CalibrationError(
            f"{calibration.source}: NDVI fusion needs camera and T_camera_lidar in the calibration"
        )
    n = len(scan.points)
    t_mid = scan_mid_time(scan)
    match = nearest_frame([f.t_capture for f in frames], t_mid, config.max_skew_ns)
    if match.index is None:
        if match.reason == "no_frame":
            return _no_frame(n, "no_frame", "no camera frame")
        return _no_frame(
            n,
            "skew",
            f"nearest frame {match.skew_ns / 1e6:+.1f} ms from the scan middle "
            f"(limit {config.max_skew_ns / 1e6:.0f} ms)",
            skew=match.skew_ns,
        )
    frame = frames[match.index]
    try:
        image = frame.decode(reduction)
    except ParseError as exc:
        return _no_frame(n, "corrupt_jpeg", str(exc), frame, match.skew_ns)
    # Reduced, a frame of another video mode still shows (other sizes differ by far more
    # than the rounding of ceil(size / reduction)).
    expected = (-(-camera.height // reduction), -(-camera.width // reduction))
    if image.shape[:2] != expected:
        return _no_frame(
            n,
            "size_mismatch",
            f"frame {frame.sequence} is {image.shape[1]}x{image.shape[0]}"
            + (f" decoded at 1/{reduction} size" if reduction > 1 else "")
            + f", the calibration is for {camera.width}x{camera.height} (intrinsics are per "
            "video mode)",
            frame,
            match.skew_ns,
        )
    if keep_ndvi_frame:
        ndvi_frame = ndvi_image(image, camera.channels, calibration.reflectance)
    else:
        ndvi_frame = PixelNdvi(
            image,
            camera.channels,
            calibration.reflectance,
            reduction,
            (camera.height, camera.width),
        )
    projection = project_points(scan.points, camera, extrinsic)
    points = point_ndvi(
        scan.points, ndvi_frame, camera, extrinsic, config.occlusion, projection=projection
    )
    return FusedScan(
        points,
        "ok",
        f"frame {frame.sequence} at {match.skew_ns / 1e6:+.1f} ms",
        frame,
        match.skew_ns,
        ndvi_frame if keep_ndvi_frame else None,
        projection,
    )


# --- the overlay picture ------------------------------------------------------------------

# NDVI -1 .. +1 as ColorBrewer RdYlGn (5 classes), BGR: red = bare/dead, green = vegetation.
_RDYLGN_BGR = np.array(
    [[28, 25, 215], [97, 174, 253], [191, 255, 255], [106, 217, 166], [65, 150, 26]], float
)
NDVI_LUT = (
    np.stack(
        [np.interp(np.linspace(0, 4, 256), np.arange(5), _RDYLGN_BGR[:, c]) for c in range(3)], 1
    )
    .round()
    .astype(np.uint8)
)
NAN_BGR = (64, 64, 64)  # no NDVI: dark grey
# The table with NaN's grey as its 257th entry: one gather colours a frame, where masking
# the NaN pixels out and back in took four passes over it (4x slower at 1280 x 960).
_NDVI_LUT_NAN = np.vstack([NDVI_LUT, np.array(NAN_BGR, dtype=np.uint8)])


def colorize_ndvi(ndvi_frame: np.ndarray) -> np.ndarray:
    """BGR uint8 picture of an NDVI frame: RdYlGn over [-1, 1], NaN or infinite grey."""
    index = np.clip(ndvi_frame, -1.0, 1.0)
    index += 1.0
    index *= 127.5
    np.rint(index, out=index)
    index[~np.isfinite(ndvi_frame)] = len(NDVI_LUT)
    return np.take(_NDVI_LUT_NAN, index.astype(np.uint16), axis=0)


def colorize_mask(mask: np.ndarray) -> np.ndarray:
    """The paper's binary NDVI frame: vegetation white, the rest black."""
    out = np.zeros((*mask.shape, 3), dtype=np.uint8)
    out[mask] = 255
    return out


def height_colours(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """M x 3 BGR uint8 for heights: OpenCV's COOL map (cyan low .. magenta high).

    Its blue channel is always 255 and green + red = 255, so a dot's colour is never one
    of the backgrounds' (RdYlGn's blue stays <= 191; grey, black, white): no dot vanishes.
    """
    import cv2

    span = high - low if high > low else 1.0
    index = np.clip((values - low) / span * 255.0, 0, 255).round().astype(np.uint8)
    return cv2.applyColorMap(index.reshape(-1, 1), cv2.COLORMAP_COOL).reshape(-1, 3)


def draw_points(
    background: np.ndarray,
    pixel: np.ndarray,
    depth: np.ndarray,
    colours: np.ndarray,
    radius: int = 2,
) -> np.ndarray:
    """A copy of `background` with a filled dot per point, far points first so the
    nearest is on top."""
    import cv2

    out = background.copy()
    for i in np.argsort(-depth, kind="stable"):
        colour = tuple(int(c) for c in colours[i])
        cv2.circle(out, (int(pixel[i, 0]), int(pixel[i, 1])), radius, colour, -1, cv2.LINE_8)
    return out
