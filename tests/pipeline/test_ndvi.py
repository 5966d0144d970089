"""NDVI from synthetic RGN images of known reflectance, the vegetation mask at its bounds,
and the reflectance fit on a synthetic MAPIR target V2 (marker found, boxes given, through
the CLI)."""

from __future__ import annotations

import json
import subprocess
import sys
from fractions import Fraction

import cv2
import numpy as np
import pytest

from tests.helpers.paths import CITRUSFARM
from treetraits.drivers.calibration import load_calibration
from treetraits.errors import CalibrationError
from treetraits.pipeline.ndvi import (
    MAPIR_TARGET_V2,
    TARGET_V2_MARKER_IN,
    TARGET_V2_PANELS_IN,
    Box,
    PixelNdvi,
    find_target_v2,
    fit_band,
    fit_reflectance,
    ndvi,
    ndvi_image,
    reflectance,
    sample_panels,
    vegetation_mask,
)

CLI = [sys.executable, "-m", "treetraits"]

# Gains and offsets that are exact in binary, so every reflectance and every NDVI below is
# computed exactly (or correctly rounded) and can be compared with ==.
NIR_GAIN = (1 / 128, -1 / 256)  # reflectance (2 v - 1) / 256, clamped at 0
RED_GAIN = (1 / 256, -1 / 256)  # reflectance (v - 1) / 256, clamped at 0


def _exact_reflectance(v: int, gain: tuple[float, float]) -> Fraction:
    return max(Fraction(gain[0]) * v + Fraction(gain[1]), Fraction(0))


def _expected_ndvi(nir_raw: int, red_raw: int) -> float:
    nir, red = _exact_reflectance(nir_raw, NIR_GAIN), _exact_reflectance(red_raw, RED_GAIN)
    if nir + red == 0:
        return float("nan")
    # Rounding the exact ratio to float64 then float32 equals rounding it once to float32.
    return float(np.float32(float((nir - red) / (nir + red))))


# (nir raw, red raw, in the mask?) and why each pixel is there
CASES = [
    (4, 14, False),  # nir 7/256, red 13/256: NDVI exactly -0.3, the open lower bound
    (4, 13, True),  # -5/19, just above -0.3
    (4, 15, False),  # below -0.3
    (4, 1, True),  # red reflectance 0: NDVI exactly 1.0, the closed upper bound
    (4, 0, True),  # red below the offset, clamped to 0: NDVI 1.0
    (0, 14, False),  # nir clamped to 0: NDVI -1
    (0, 1, False),  # nir + red == 0: NaN, never vegetation
    (0, 0, False),  # both clamped: NaN
    (100, 30, True),  # leaf-like: 199/256 vs 29/256 -> 0.7456
    (60, 60, True),  # 119/256 vs 59/256: NDVI 0.34
    (255, 255, True),  # saturated but defined
]


def _case_image(channels: dict[str, int]) -> np.ndarray:
    image = np.zeros((2, len(CASES), 3), dtype=np.uint8)
    image[..., channels["green"]] = 77  # a value that must not matter
    for i, (nir_raw, red_raw, _) in enumerate(CASES):
        image[:, i, channels["nir"]] = nir_raw
        image[:, i, channels["red"]] = red_raw
    return image


@pytest.mark.parametrize(
    "channels",
    [{"red": 2, "green": 1, "nir": 0}, {"red": 0, "green": 2, "nir": 1}],
    ids=["rgn-default", "permuted"],
)
def test_ndvi_and_mask_of_known_reflectances_exactly(channels):
    image = _case_image(channels)
    gains = {"red": RED_GAIN, "nir": NIR_GAIN, "green": (1 / 255, 0.0)}
    frame = ndvi_image(image, channels, gains)
    assert frame.dtype == np.float32 and frame.shape == (2, len(CASES))
    expected = np.array([_expected_ndvi(n, r) for n, r, _ in CASES], dtype=np.float32)
    np.testing.assert_array_equal(frame[0], expected)  # NaN == NaN here
    np.testing.assert_array_equal(frame[1], expected)
    assert np.isnan(frame[0, 6]) and np.isnan(frame[0, 7])
    assert frame[0, 0] == np.float32(-0.3) and frame[0, 3] == 1.0 and frame[0, 5] == -1.0
    np.testing.assert_array_equal(vegetation_mask(frame)[0], [c[2] for c in CASES])


def test_reflectance_per_band_uses_gain_offset_and_channels():
    image = np.zeros((1, 3, 3), dtype=np.uint8)
    image[0, :, 0] = [0, 100, 255]  # NIR in channel 0 (BGR default)
    image[0, :, 2] = [10, 20, 30]  # red in channel 2
    calibration = load_calibration(
        {
            **json.loads(CITRUSFARM.read_text()),
            "reflectance": {"red": [0.004, -0.02], "nir": [0.0036, -0.01]},
        }
    )
    bands = reflectance(image, calibration.camera.channels, calibration.reflectance)
    np.testing.assert_allclose(bands["nir"][0], [0.0, 0.35, 0.908], rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(bands["red"][0], [0.02, 0.06, 0.10], rtol=1e-6)
    assert bands["nir"].dtype == np.float32


def test_ndvi_of_plain_arrays_and_mask_bounds():
    values = ndvi(np.array([0.5, 0.0, 0.2]), np.array([0.5, 0.0, 0.0]))
    np.testing.assert_array_equal(values, np.array([0.0, np.nan, 1.0], dtype=np.float32))
    assert vegetation_mask(np.array([0.0, 0.5, 0.9]), low=0.4, high=0.8).tolist() == [
        False,
        True,
        False,
    ]
    # float64 input is compared in float64
    assert vegetation_mask(np.array([-0.3, -0.29999999, 1.0, 1.0000001])).tolist() == [
        False,
        True,
        True,
        False,
    ]


# --- reflectance fit -------------------------------------------------------------------

TRUE_FIT = {"red": (0.0040, -0.020), "green": (0.0042, -0.030), "nir": (0.0036, -0.010)}
CHANNELS = {"red": 2, "green": 1, "nir": 0}
PX_PER_IN = 24.0


def _target_photo(seed: int = 7, noise: float = 2.0, jpeg: bool = True):
    """A 1280x720 photo of a target V2 sheet under a mild perspective, panels painted with
    the raw values that `TRUE_FIT` maps to MAPIR's panel reflectances, plus noise.
    Returns the BGR image and the panel centres in pixels (for the --box path)."""
    # The sheet in its own pixels: marker TL at (12, 2) in, panels left of it.
    sheet_w, sheet_h = int(20 * PX_PER_IN), int(12 * PX_PER_IN)
    sheet = np.full((sheet_h, sheet_w, 3), 235, dtype=np.uint8)
    origin = np.array([12.5, 3.0])  # marker TL on the sheet, inches
    side = int(TARGET_V2_MARKER_IN * PX_PER_IN)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_250)
    marker = cv2.aruco.generateImageMarker(dictionary, 13, side)
    mx, my = (origin * PX_PER_IN).astype(int)
    sheet[my : my + side, mx : mx + side] = np.where(marker[..., None] > 127, 235, 15)
    half = int(1.75 * PX_PER_IN)  # 3.5 in panels
    for i, (px, py) in enumerate(TARGET_V2_PANELS_IN):
        cx, cy = ((origin + np.array([px, py])) * PX_PER_IN).astype(int)
        for band, channel in CHANNELS.items():
            gain, offset = TRUE_FIT[band]
            raw = (MAPIR_TARGET_V2[band][i] - offset) / gain
            sheet[cy - half : cy + half, cx - half : cx + half, channel] = np.uint8(round(raw))
    # Perspective: the sheet's corners to a trapezoid in the photo.
    source = np.float32([[0, 0], [sheet_w, 0], [sheet_w, sheet_h], [0, sheet_h]])
    dest = np.float32([[300, 170], [1010, 200], [990, 560], [320, 600]])
    homography = cv2.getPerspectiveTransform(source, dest)
    photo = np.full((720, 1280, 3), (60, 110, 70), dtype=np.uint8)  # grass-like background
    warped = cv2.warpPerspective(sheet, homography, (1280, 720), flags=cv2.INTER_LINEAR)
    inside = (
        cv2.warpPerspective(
            np.full((sheet_h, sheet_w), 255, np.uint8),
            homography,
            (1280, 720),
            flags=cv2.INTER_NEAREST,
        )
        > 0
    )
    photo[inside] = warped[inside]
    rng = np.random.default_rng(seed)
    noisy = np.round(photo + rng.normal(0, noise, photo.shape))  # round: no -0.5 DN bias
    photo = np.clip(noisy, 0, 255).astype(np.uint8)
    if jpeg:
        _, data = cv2.imencode(".jpg", photo, [cv2.IMWRITE_JPEG_QUALITY, 95])
        photo = cv2.imdecode(data, cv2.IMREAD_COLOR)
    centres = [
        cv2.perspectiveTransform(
            np.float32([[(origin + np.array([px, py])) * PX_PER_IN]]), homography
        )[0, 0]
        for px, py in TARGET_V2_PANELS_IN
    ]
    return photo, centres


def _painted_line(band: str) -> tuple[float, float]:
    """The least-squares line through the integer values actually painted (by hand: the
    paint is rounded to whole DN, which moves the line by up to ~0.002 in reflectance)."""
    gain, offset = TRUE_FIT[band]
    y = np.array(MAPIR_TARGET_V2[band])
    x = np.round((y - offset) / gain)
    slope = np.mean((x - x.mean()) * (y - y.mean())) / np.mean((x - x.mean()) ** 2)
    return slope, y.mean() - slope * x.mean()


def _assert_recovered(fits):
    for band, (gain, offset) in TRUE_FIT.items():
        fit = fits[band]
        assert fit.gain == pytest.approx(gain, rel=0.01), band
        assert fit.offset == pytest.approx(offset, abs=0.004), band
        # Noise (2-3 DN) and JPEG move the line by well under 1 DN from the painted one.
        painted_gain, painted_offset = _painted_line(band)
        assert fit.gain == pytest.approx(painted_gain, rel=0.003), band
        assert fit.offset == pytest.approx(painted_offset, abs=0.0025), band
        assert fit.r2 > 0.9999 and fit.used == (0, 1, 2, 3)


def test_fit_recovers_gain_offset_with_the_marker_found_automatically():
    photo, centres = _target_photo()
    boxes, _ = find_target_v2(photo)
    assert len(boxes) == 4
    for box, centre in zip(boxes, centres, strict=True):  # each box on its panel
        assert abs(box.x + box.w / 2 - centre[0]) < 3 and abs(box.y + box.h / 2 - centre[1]) < 3
        assert box.w >= 10 and box.h >= 10
    _assert_recovered(fit_reflectance(sample_panels(photo, boxes, CHANNELS), MAPIR_TARGET_V2))
    # Upside down: the panels follow the marker's own corner order, not the image's.
    upside_down = np.ascontiguousarray(photo[::-1, ::-1])
    turned, _ = find_target_v2(upside_down)
    for box, centre in zip(turned, centres, strict=True):
        assert abs(box.x + box.w / 2 - (1279 - centre[0])) < 3
        assert abs(box.y + box.h / 2 - (719 - centre[1])) < 3


def test_fit_recovers_gain_offset_from_given_boxes():
    photo, centres = _target_photo(seed=11, noise=3.0)
    boxes = [Box(int(cx) - 12, int(cy) - 12, 24, 24) for cx, cy in centres]
    _assert_recovered(fit_reflectance(sample_panels(photo, boxes, CHANNELS), MAPIR_TARGET_V2))


def test_fit_refuses_bad_photos_and_drops_clipped_panels():
    target = MAPIR_TARGET_V2["red"]
    with pytest.raises(CalibrationError, match="brightest panel first"):
        fit_band("red", [60.0, 230.0, 50.0, 10.0], target)  # boxes out of order
    with pytest.raises(CalibrationError, match="only 1 unclipped"):
        fit_band("red", [255.0, 255.0, 255.0, 10.0], target, clipped=[1, 1, 0.5, 0])
    raw = [(r + 0.02) / 0.004 for r in target]
    fit = fit_band("red", [255.0, *raw[1:]], target, clipped=[0.9, 0, 0, 0])
    assert fit.used == (1, 2, 3) and "panel 1 left out" in fit.notes[0]
    assert fit.gain == pytest.approx(0.004) and fit.offset == pytest.approx(-0.02)
    with pytest.raises(CalibrationError, match="no MAPIR target V2 marker"):
        find_target_v2(np.full((200, 300, 3), 128, np.uint8))


def test_cli_fits_and_writes_the_reflectance_section(tmp_path):
    photo, centres = _target_photo()
    image = tmp_path / "target.png"
    cv2.imwrite(str(image), photo)
    calibration = tmp_path / "calibration.json"
    calibration.write_text(CITRUSFARM.read_text())
    show = tmp_path / "panels.png"
    result = subprocess.run(
        [
            *CLI,
            "calibrate",
            "reflectance",
            str(image),
            "--write",
            str(calibration),
            "--show",
            str(show),
            "--json",
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["panels"].startswith("target V2 marker")
    loaded = load_calibration(calibration)
    for band, (gain, offset) in TRUE_FIT.items():
        assert loaded.reflectance[band][0] == pytest.approx(gain, rel=0.01)
        assert loaded.reflectance[band][1] == pytest.approx(offset, abs=0.004)
    # The other sections are kept as they were.
    original = load_calibration(CITRUSFARM)
    np.testing.assert_array_equal(loaded.T_camera_lidar, original.T_camera_lidar)
    np.testing.assert_array_equal(loaded.camera.K, original.camera.K)
    assert cv2.imread(str(show)).shape == photo.shape

    boxes = [f"{int(cx) - 12},{int(cy) - 12},24,24" for cx, cy in centres]
    given = subprocess.run(
        [
            *CLI,
            "calibrate",
            "reflectance",
            str(image),
            *[arg for b in boxes for arg in ("--box", b)],
        ],
        capture_output=True,
        text=True,
    )
    assert given.returncode == 0, given.stderr
    assert '"reflectance"' in given.stdout.splitlines()[-1]
    wrong = subprocess.run(
        [
            *CLI,
            "calibrate",
            "reflectance",
            str(image),
            "--box",
            boxes[1],
            "--box",
            boxes[0],
            "--box",
            boxes[2],
            "--box",
            boxes[3],
        ],
        capture_output=True,
        text=True,
    )
    assert wrong.returncode == 2 and "brightest panel first" in wrong.stderr
    assert "Traceback" not in wrong.stderr


def test_ndvi_image_table_is_bit_identical_to_the_formulas():
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (64, 80, 3), dtype=np.uint8)
    gains = {"red": (0.004, -0.02), "nir": (0.0036, -0.01), "green": (1 / 255, 0.0)}
    bands = reflectance(image, CHANNELS, gains)
    np.testing.assert_array_equal(
        ndvi_image(image, CHANNELS, gains), ndvi(bands["nir"], bands["red"])
    )
    # Non-8-bit input takes the formulas directly.
    as_float = ndvi_image(image.astype(np.float32), CHANNELS, gains)
    np.testing.assert_array_equal(as_float, ndvi(bands["nir"], bands["red"]))


def test_pixel_ndvi_reads_what_the_whole_frame_holds_at_those_pixels():
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (72, 128, 3), dtype=np.uint8)
    image[5, 7] = 0  # nir + red == 0: NaN in both
    gains = {"red": (0.004, -0.02), "nir": (0.0036, -0.01)}
    rows = np.r_[5, rng.integers(0, 72, 500)]
    cols = np.r_[7, rng.integers(0, 128, 500)]
    for picture in (image, image.astype(np.float32)):
        whole = ndvi_image(picture, CHANNELS, gains)
        sampled = PixelNdvi(picture, CHANNELS, gains)
        assert sampled.shape == whole.shape
        np.testing.assert_array_equal(sampled[rows, cols], whole[rows, cols])
        assert np.isnan(sampled[rows[:1], cols[:1]]).all()
    with pytest.raises(CalibrationError, match="nir"):
        PixelNdvi(image, {"red": 2}, gains)


def test_pixel_ndvi_of_a_reduced_image_reads_the_pixel_covering_each_full_size_one():
    rng = np.random.default_rng(2)
    reduced = rng.integers(0, 256, (36, 64, 3), dtype=np.uint8)  # 127x71 at half size
    gains = {"red": (0.004, -0.02), "nir": (0.0036, -0.01)}
    sampled = PixelNdvi(reduced, CHANNELS, gains, reduction=2, full_shape=(71, 127))
    assert sampled.shape == (71, 127)  # indexed in full-size pixels, as the calibration
    rows, cols = rng.integers(0, 71, 500), rng.integers(0, 127, 500)
    whole = ndvi_image(reduced, CHANNELS, gains)
    np.testing.assert_array_equal(sampled[rows, cols], whole[rows // 2, cols // 2])
    with pytest.raises(ValueError, match="reduced 2 times"):
        PixelNdvi(reduced, CHANNELS, gains, reduction=2, full_shape=(72, 140))
