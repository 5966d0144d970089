"""NDVI from a Survey3N RGN image: raw values -> reflectance -> NDVI -> vegetation mask.

Also the pieces of the reflectance calibration (the MAPIR target V2: find its panels, take
their mean raw values, fit `reflectance = gain * raw + offset` per band). Pure functions
over arrays; formulas and defaults are in docs/ndvi_projection.md.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from treetraits.errors import CalibrationError

# The paper's vegetation threshold: NDVI in (-0.3, 1.0] ("chosen in the field").
VEGETATION_LOW = -0.3
VEGETATION_HIGH = 1.0

# Panel reflectances (fractions, panel 1 = brightest) of MAPIR's calibration target V2 as
# MAPIR's own scripts use them for Survey3 filters (camera-scripts @ 179471a, `refvalues`),
# paired by wavelength: green 550 nm, red 660 nm, NIR 850 nm. Another target (T4, a newer
# sheet) is given to `treetraits calibrate reflectance --target FILE` as data.
MAPIR_TARGET_V2: dict[str, tuple[float, ...]] = {
    "green": (0.8689592421, 0.2656248359, 0.1961875592, 0.0195576511),
    "red": (0.8775934407, 0.2661207692, 0.1987265874, 0.0192249327),
    "nir": (0.8653063177, 0.2798126291, 0.2337498097, 0.0193295348),
}

# Target V2 geometry, inches on the sheet, from MAPIR's script: the ArUco marker (4x4_250,
# id 13) is 5.5 in a side; panel centres lie 9.0 in (panels 1, 3) and 10.5 in (panels 2, 4)
# from the marker's TL, TR, BL, BR corners against the marker's top edge direction. In
# marker coordinates (x along TL->TR, y along TL->BL, origin at TL) that is:
TARGET_V2_MARKER_ID = 13
TARGET_V2_MARKER_IN = 5.5
TARGET_V2_PANELS_IN = ((-9.0, 0.0), (-5.0, 0.0), (-9.0, 5.5), (-5.0, 5.5))
TARGET_V2_SAMPLE_IN = 0.75

# A panel is not used for the fit when this fraction of its pixels is clipped at 255 or 0
# (MAPIR drops a saturated first or black last panel; a clipped mean is not linear in light).
CLIPPED_FRACTION = 0.02


def band_reflectance(image: np.ndarray, channel: int, gain: float, offset: float) -> np.ndarray:
    """Reflectance of one band: `max(gain * raw + offset, 0)` as float32.

    Negative values (dark pixels below the fit's intercept) are clamped to 0: a surface
    cannot reflect less than nothing, and an unclamped negative red would push NDVI past 1.
    """
    raw = image[..., channel].astype(np.float32)
    out = raw * np.float32(gain) + np.float32(offset)
    return np.maximum(out, np.float32(0.0), out=out)


def reflectance(
    image: np.ndarray,
    channels: Mapping[str, int],
    gains: Mapping[str, tuple[float, float]],
    bands: Sequence[str] = ("red", "nir"),
) -> dict[str, np.ndarray]:
    """Reflectance per band of a decoded (OpenCV BGR-ordered) image.

    `channels` is the calibration's `camera.channels` (band -> index in the image), `gains`
    its `reflectance` section (band -> (gain, offset)).
    """
    if image.ndim != 3:
        raise ValueError(f"expected an H x W x 3 image, got shape {image.shape}")
    out = {}
    for band in bands:
        if band not in channels:
            raise CalibrationError(f"camera.channels has no {band!r} band")
        gain, offset = gains[band]
        out[band] = band_reflectance(image, channels[band], gain, offset)
    return out


def ndvi(nir: np.ndarray, red: np.ndarray) -> np.ndarray:
    """`(nir - red) / (nir + red)` as float32; NaN where `nir + red == 0` (no light, no
    index)."""
    nir = np.asarray(nir, dtype=np.float32)
    red = np.asarray(red, dtype=np.float32)
    total = nir + red
    out = np.full(np.broadcast(nir, red).shape, np.nan, dtype=np.float32)
    np.divide(nir - red, total, out=out, where=total != 0)
    return out


def ndvi_table(gains: Mapping[str, tuple[float, float]]) -> np.ndarray:
    """NDVI for every (nir raw, red raw) pair of 8-bit values: a 256 x 256 float32 table,
    computed with exactly the float32 operations of `band_reflectance` and `ndvi`.
    Read-only and cached per (gain, offset) pair: a run uses one calibration."""
    return _ndvi_table(tuple(gains["nir"]), tuple(gains["red"]))


@functools.lru_cache(maxsize=8)
def _ndvi_table(nir_gain: tuple[float, float], red_gain: tuple[float, float]) -> np.ndarray:
    raw = np.arange(256, dtype=np.uint8).reshape(1, 256, 1)
    nir = band_reflectance(raw, 0, *nir_gain)[0]
    red = band_reflectance(raw, 0, *red_gain)[0]
    table = ndvi(nir[:, None], red[None, :])
    table.flags.writeable = False  # shared by every caller
    return table


def ndvi_image(
    image: np.ndarray,
    channels: Mapping[str, int],
    gains: Mapping[str, tuple[float, float]],
) -> np.ndarray:
    """The NDVI frame (H x W float32, NaN where undefined) of a decoded BGR image."""
    for band in ("red", "nir"):
        if band not in channels:
            raise CalibrationError(f"camera.channels has no {band!r} band")
    if image.dtype == np.uint8 and image.ndim == 3:
        import cv2

        # 8-bit input: one table look-up per pixel, bit-identical to the formulas and ~4x
        # faster on a 720p frame (contiguous planes first: strided reads are the slow part).
        index = cv2.extractChannel(image, channels["nir"]).astype(np.intp)
        index <<= 8
        index |= cv2.extractChannel(image, channels["red"])
        return ndvi_table(gains).ravel()[index]
    bands = reflectance(image, channels, gains, ("red", "nir"))
    return ndvi(bands["nir"], bands["red"])


class PixelNdvi:
    """The NDVI of a decoded image computed only at the pixels read, for a caller that
    samples a few thousand pixels of a 720p frame (`projection.point_ndvi`): indexing
    `[rows, cols]` gives exactly `ndvi_image(image, ...)[rows, cols]` (the formulas are
    per pixel), without working out the other ~900 000 pixels of the frame.

    `reduction` r > 1: `image` is the frame decoded at 1/r of its size (`Frame.decode`);
    it is still indexed in full-size pixels (`shape` is the full size, `full_shape`), pixel
    (row, col) reading the reduced pixel (row // r, col // r) that covers it."""

    def __init__(
        self,
        image: np.ndarray,
        channels: Mapping[str, int],
        gains: Mapping[str, tuple[float, float]],
        reduction: int = 1,
        full_shape: tuple[int, int] | None = None,
    ):
        if image.ndim != 3:
            raise ValueError(f"expected an H x W x 3 image, got shape {image.shape}")
        for band in ("red", "nir"):
            if band not in channels:
                raise CalibrationError(f"camera.channels has no {band!r} band")
        self.image, self.channels, self.gains = image, channels, gains
        self.reduction = reduction
        self.shape = image.shape[:2] if full_shape is None else tuple(full_shape)
        if tuple(-(-n // reduction) for n in self.shape) != image.shape[:2]:
            raise ValueError(
                f"a {image.shape[1]}x{image.shape[0]} image is not {self.shape[1]}x"
                f"{self.shape[0]} reduced {reduction} times"
            )

    def __getitem__(self, index: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        rows, cols = index
        if self.reduction > 1:
            rows, cols = rows // self.reduction, cols // self.reduction
        if self.image.dtype == np.uint8:
            nir = self.image[rows, cols, self.channels["nir"]].astype(np.intp)
            nir <<= 8
            nir |= self.image[rows, cols, self.channels["red"]]
            return ndvi_table(self.gains).ravel()[nir]
        pixels = self.image[rows, cols][:, None, :]  # K x 1 x 3: a one-column image
        return ndvi_image(pixels, self.channels, self.gains)[:, 0]


def vegetation_mask(
    ndvi_values: np.ndarray, low: float = VEGETATION_LOW, high: float = VEGETATION_HIGH
) -> np.ndarray:
    """True where `low < ndvi <= high` (the paper's (-0.3, 1.0]); NaN is never vegetation.

    The bounds are compared in the array's own precision, so a float32 NDVI equal to
    float32(-0.3) is out and one equal to 1.0 is in.
    """
    values = np.asarray(ndvi_values)
    dtype = values.dtype if values.dtype.kind == "f" else np.dtype(np.float64)
    lo, hi = dtype.type(low), dtype.type(high)
    return (values > lo) & (values <= hi)


# --- reflectance calibration ------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Box:
    """An axis-aligned pixel rectangle: columns x .. x+w-1, rows y .. y+h-1."""

    x: int
    y: int
    w: int
    h: int

    @classmethod
    def parse(cls, text: str) -> Box:
        """`x,y,w,h` in pixels."""
        parts = text.replace(" ", "").split(",")
        try:
            x, y, w, h = (int(p) for p in parts)
        except ValueError:
            raise ValueError(f"box {text!r}: expected x,y,w,h as four integers") from None
        if w <= 0 or h <= 0 or x < 0 or y < 0:
            raise ValueError(f"box {text!r}: x, y must be >= 0 and w, h > 0")
        return cls(x, y, w, h)

    def __str__(self) -> str:
        return f"{self.x},{self.y},{self.w},{self.h}"


@dataclass(frozen=True)
class PanelSample:
    """Mean raw value per band of each panel, and the fraction of its pixels clipped."""

    boxes: tuple[Box, ...]
    mean: dict[str, tuple[float, ...]]
    clipped: dict[str, tuple[float, ...]]


def sample_panels(
    image: np.ndarray, boxes: Sequence[Box], channels: Mapping[str, int]
) -> PanelSample:
    """Mean raw value of every band inside each box (boxes in panel order, brightest first)."""
    height, width = image.shape[:2]
    means: dict[str, list[float]] = {band: [] for band in channels}
    clipped: dict[str, list[float]] = {band: [] for band in channels}
    for box in boxes:
        if box.x + box.w > width or box.y + box.h > height:
            raise CalibrationError(f"panel box {box} reaches outside the {width}x{height} image")
        patch = image[box.y : box.y + box.h, box.x : box.x + box.w]
        for band, channel in channels.items():
            values = patch[..., channel]
            means[band].append(float(values.mean()))
            clipped[band].append(float(np.mean((values >= 255) | (values <= 0))))
    return PanelSample(
        tuple(boxes),
        {b: tuple(v) for b, v in means.items()},
        {b: tuple(v) for b, v in clipped.items()},
    )


@dataclass(frozen=True)
class BandFit:
    """`reflectance = gain * raw + offset` for one band, with the evidence of the fit."""

    band: str
    gain: float
    offset: float
    used: tuple[int, ...]  # panel indices (0 = brightest) the line was fitted on
    raw: tuple[float, ...]  # mean raw value of every panel
    target: tuple[float, ...]  # known reflectance of every panel
    r2: float
    max_residual: float  # largest |fitted - known| reflectance over the used panels
    notes: tuple[str, ...] = field(default=())


def fit_band(
    band: str,
    raw: Sequence[float],
    target: Sequence[float],
    clipped: Sequence[float] | None = None,
) -> BandFit:
    """Least-squares line from panel means to known reflectances (MAPIR's empirical line).

    Clipped panels (saturated or black, `CLIPPED_FRACTION`) are left out; at least two
    must remain, and raw values must fall strictly as reflectance falls, else the photo is
    refused (wrong box order, a shadow on a panel, or exposure unsuited to the target).
    """
    raw_all = np.asarray(raw, dtype=float)
    target_all = np.asarray(target, dtype=float)
    if raw_all.shape != target_all.shape or raw_all.ndim != 1:
        raise CalibrationError(
            f"{band}: {len(raw_all)} panel values for {len(target_all)} known reflectances"
        )
    clipped_all = np.zeros_like(raw_all) if clipped is None else np.asarray(clipped, float)
    notes = []
    keep = clipped_all <= CLIPPED_FRACTION
    for i in np.flatnonzero(~keep):
        notes.append(f"panel {i + 1} left out: {clipped_all[i]:.0%} of its pixels clipped")
    used = np.flatnonzero(keep)
    if len(used) < 2:
        raise CalibrationError(
            f"{band}: only {len(used)} unclipped panel(s); need 2 or more. Lower the exposure "
            f"(panels saturated) or raise it (panels black)"
        )
    order = np.argsort(-target_all[used], kind="stable")
    by_reflectance = raw_all[used][order]
    if not np.all(np.diff(by_reflectance) < 0):
        raise CalibrationError(
            f"{band}: panel means {np.round(raw_all, 1).tolist()} do not fall with the panels' "
            f"reflectance {target_all.tolist()}: give the boxes brightest panel first, and "
            f"check for shadows or glare on the target"
        )
    x, y = raw_all[used], target_all[used]
    gain, offset = np.polyfit(x, y, 1)
    if not gain > 0:
        raise CalibrationError(f"{band}: fitted gain {gain:.3g} is not positive")
    fitted = gain * x + offset
    residual = y - fitted
    total = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - float(np.sum(residual**2)) / total if total > 0 else float("nan")
    if len(used) == 2:
        notes.append("only two panels: the line passes through both, R² says nothing")
    return BandFit(
        band,
        float(gain),
        float(offset),
        tuple(int(i) for i in used),
        tuple(float(v) for v in raw_all),
        tuple(float(v) for v in target_all),
        r2,
        float(np.max(np.abs(residual))),
        tuple(notes),
    )


def fit_reflectance(
    sample: PanelSample, target: Mapping[str, Sequence[float]]
) -> dict[str, BandFit]:
    """`fit_band` for every band that has both panel means and known reflectances."""
    fits = {}
    for band, known in target.items():
        if band not in sample.mean:
            continue
        if len(known) != len(sample.boxes):
            raise CalibrationError(
                f"{band}: the target has {len(known)} panels, {len(sample.boxes)} boxes given"
            )
        fits[band] = fit_band(band, sample.mean[band], known, sample.clipped[band])
    return fits


def find_target_v2(image: np.ndarray) -> tuple[list[Box], np.ndarray]:
    """The four panel sample boxes of a MAPIR target V2, found through its ArUco marker.

    Returns the boxes (panel 1 = brightest first) and the marker's corners (4 x 2 pixels,
    TL TR BR BL). Panel positions come from a homography of the marker's corners, so a
    target photographed at an angle still lands right. Raises CalibrationError when no
    marker id 13 is found.
    """
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250)
    detector = cv2.aruco.ArucoDetector(dictionary, cv2.aruco.DetectorParameters())
    # The marker's ink may not be dark in NIR: try grey first, then each channel alone.
    candidates = [cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)] if image.ndim == 3 else [image]
    if image.ndim == 3:
        candidates += [np.ascontiguousarray(image[..., c]) for c in range(image.shape[2])]
    corners = None
    for gray in candidates:
        found, ids, _ = detector.detectMarkers(gray)
        if ids is not None:
            for marker, marker_id in zip(found, ids.ravel(), strict=True):
                if marker_id == TARGET_V2_MARKER_ID:
                    corners = marker.reshape(4, 2).astype(float)
                    break
        if corners is not None:
            break
    if corners is None:
        raise CalibrationError(
            "no MAPIR target V2 marker (ArUco 4x4_250 id 13) found in the image; give the "
            "panels as --box x,y,w,h (brightest first)"
        )
    side = TARGET_V2_MARKER_IN
    sheet = np.array([[0, 0], [side, 0], [side, side], [0, side]], dtype=np.float32)
    homography = cv2.getPerspectiveTransform(sheet, corners.astype(np.float32))
    height, width = image.shape[:2]
    half = TARGET_V2_SAMPLE_IN / 2
    boxes = []
    for px, py in TARGET_V2_PANELS_IN:
        square = np.array(
            [
                [px - half, py - half],
                [px + half, py - half],
                [px + half, py + half],
                [px - half, py + half],
            ],
            dtype=np.float32,
        )
        pixels = cv2.perspectiveTransform(square[None], homography)[0]
        # The axis-aligned box inside the projected square: only panel pixels are sampled.
        xs, ys = np.sort(pixels[:, 0]), np.sort(pixels[:, 1])
        x0, x1 = int(np.ceil(xs[1])), int(np.floor(xs[2]))
        y0, y1 = int(np.ceil(ys[1])), int(np.floor(ys[2]))
        if x1 <= x0 or y1 <= y0:
            raise CalibrationError("target V2 found but too small in the image to sample")
        if x0 < 0 or y0 < 0 or x1 > width or y1 > height:
            raise CalibrationError(
                "target V2 marker found but its panels fall outside the image: frame the "
                "whole target"
            )
        boxes.append(Box(x0, y0, x1 - x0, y1 - y0))
    return boxes, corners
