"""`treetraits fuse` end to end on a recording built from a real VLP-16 capture plus camera
frames rendered through the real CitrusFarm calibration; and every way a frame can fail
(missing, too far in time, corrupt, wrong size) without a crash."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file
from tests.helpers.paths import FIXTURES
from treetraits.drivers import recording
from treetraits.drivers.calibration import load_calibration
from treetraits.drivers.records import Frame
from treetraits.drivers.velodyne.sources import open_source
from treetraits.errors import ParseError
from treetraits.pipeline.fusion import FusionConfig, colorize_ndvi, fuse_scan
from treetraits.pipeline.ndvi import ndvi_image
from treetraits.pipeline.projection import PointStatus, max_valid_radius, scan_mid_time

CLI = [sys.executable, "-m", "treetraits"]
CAPTURE = VLP16_DIR / "nebula_vlp16_dual_10hz.pcap"  # 4 scans, indoors, 0.5-15 m
CALIBRATION = {
    **json.loads((FIXTURES / "citrusfarm_calib" / "citrusfarm_calibration_v1.json").read_text()),
    "reflectance": {"red": [0.004, -0.02], "nir": [0.0036, -0.01]},
}
FRAME_PERIOD_NS = 33_333_333  # 30 fps
LATENCY_NS = 15_000_000  # capture -> host receive
DOT = 3  # rendered disc radius, px

# Raw (nir, green, red) painted where a point lands: above Z_SPLIT (m, lidar frame; the
# middle of what this indoor scan shows the camera) leaf-like (NDVI ~ +0.67), below it
# bare (NDVI ~ -0.38); the background is grey (NDVI ~ -0.04).
HIGH, LOW, BACKGROUND = (200, 90, 40), (60, 90, 120), (90, 90, 90)
Z_SPLIT = 0.1


def _camera_pixels(points, calibration):
    """Pixels of points through cv2.projectPoints (independent of our model), keeping
    those in front and inside the lens model's range; also their camera depth."""
    camera, extrinsic = calibration.camera, calibration.T_camera_lidar
    xyz = np.column_stack([points["x"], points["y"], points["z"]]).astype(float)
    in_camera = xyz @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    depth = in_camera[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.hypot(in_camera[:, 0], in_camera[:, 1]) / depth
    front = (depth > 0.05) & (r < max_valid_radius(camera.dist))
    uv, _ = cv2.projectPoints(
        in_camera.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist
    )
    pixel = np.nan_to_num(np.floor(uv.reshape(-1, 2) + 0.5), nan=-1, posinf=-1, neginf=-1)
    inside = front & (pixel[:, 0] >= 0) & (pixel[:, 0] < camera.width)
    inside &= (pixel[:, 1] >= 0) & (pixel[:, 1] < camera.height)
    return np.clip(pixel, -1, 1e6).astype(int), depth, inside


def _render(scan, calibration) -> bytes:
    """A 1280x720 RGN JPEG of the scan as the camera would see an NDVI-painted scene."""
    image = np.empty((720, 1280, 3), dtype=np.uint8)
    image[:] = BACKGROUND
    pixel, depth, inside = _camera_pixels(scan.points, calibration)
    for i in np.flatnonzero(inside)[np.argsort(-depth[inside])]:  # far first
        colour = HIGH if scan.points["z"][i] > Z_SPLIT else LOW
        cv2.circle(image, (int(pixel[i, 0]), int(pixel[i, 1])), DOT, colour, -1)
    ok, data = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    return data.tobytes()


def _write_recording(path, frames, calibration=CALIBRATION):
    with recording.RecordingWriter(path, calibration=calibration) as writer:
        source = open_source(CAPTURE)
        for packet in source:
            writer.write(recording.LIDAR_PACKETS, packet.payload, packet.t_host)
        source.close()
        for frame in frames:
            writer.write(recording.CAMERA_JPEG, frame.jpeg, frame.t_host, frame.t_capture)


@pytest.fixture(scope="module")
def scans():
    return decode_file(CAPTURE)[0]


@pytest.fixture(scope="module")
def frames(scans):
    """Frames at 30 fps over the capture, each rendered from the scan nearest in time."""
    calibration = load_calibration(CALIBRATION)
    middles = np.array([scan_mid_time(s) for s in scans])
    start = scans[0].t_host - (scans[0].t_end - scans[0].t_start)
    out, rendered = [], {}
    for sequence in range(13):
        t = start + sequence * FRAME_PERIOD_NS
        nearest = int(np.argmin(np.abs(middles - t)))
        if nearest not in rendered:
            rendered[nearest] = _render(scans[nearest], calibration)
        out.append(Frame(rendered[nearest], t + LATENCY_NS, t, sequence))
    return out


@pytest.fixture(scope="module")
def rec(tmp_path_factory, frames):
    path = tmp_path_factory.mktemp("fuse") / "rec.mcap"
    _write_recording(path, frames)
    return path


def run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([*CLI, *args], capture_output=True, text=True)


def test_fuse_draws_the_scan_on_its_ndvi_frame(rec, scans, frames, tmp_path):
    out = tmp_path / "overlay.png"
    result = run("fuse", str(rec), "--scan", "1", "--out", str(out), "--json")
    assert result.returncode == 0, result.stderr
    facts = json.loads(result.stdout)
    overlay = cv2.imread(str(out), cv2.IMREAD_COLOR)
    assert overlay is not None and overlay.shape == (720, 1280, 3)
    assert facts["image"] == [1280, 720] and facts["calibration"] == "recording metadata"

    # The frame it chose is the one nearest the scan's middle (on the host clock).
    scan = scans[1]
    times = np.array([f.t_capture for f in frames])
    chosen = int(np.argmin(np.abs(times - scan_mid_time(scan))))
    assert facts["frame_sequence"] == frames[chosen].sequence
    assert abs(facts["skew_ms"]) <= FRAME_PERIOD_NS / 2e6

    # Against the plain NDVI picture of that frame, the overlay differs exactly on the
    # dots: every changed pixel is within the dot radius of a projected point (pixels
    # from cv2.projectPoints), and each drawn point's disc has changed.
    calibration = load_calibration(CALIBRATION)
    image = frames[chosen].decode()
    plain = colorize_ndvi(ndvi_image(image, calibration.camera.channels, calibration.reflectance))
    changed = np.any(overlay != plain, axis=2)
    pixel, _, inside = _camera_pixels(scan.points, calibration)
    fused = fuse_scan(scan, [frames[chosen]], calibration)
    drawn = (fused.points.status == PointStatus.OK) | (fused.points.status == PointStatus.NO_NDVI)
    assert drawn.sum() == facts["drawn"] > 1000
    assert not (drawn & ~inside).any()  # we never draw what cv2 puts outside the image
    discs = np.zeros((720, 1280), np.uint8)
    for i in np.flatnonzero(drawn):
        cv2.circle(discs, (int(pixel[i, 0]), int(pixel[i, 1])), 2, 1, -1, cv2.LINE_8)
    np.testing.assert_array_equal(changed, discs.astype(bool))

    # The dots sit on the structure rendered from them: high points read the leaf-like
    # NDVI painted there, low points the bare one (a few cm off the split, discs overlap).
    z = scan.points["z"]
    ok = fused.points.status == PointStatus.OK
    high, low = ok & (z > Z_SPLIT + 0.03), ok & (z < Z_SPLIT - 0.03)
    assert high.sum() > 300 and low.sum() > 300
    assert np.median(fused.ndvi[high]) > 0.5 and np.median(fused.ndvi[low]) < -0.2
    assert facts["points_ok"] == int(ok.sum())


def test_fuse_with_a_calibration_file_and_the_mask_background(rec, tmp_path):
    calibration = tmp_path / "calibration.json"
    calibration.write_text(json.dumps(CALIBRATION))
    out = tmp_path / "mask.png"
    result = run(
        "fuse",
        str(rec),
        "--scan",
        "2",
        "--out",
        str(out),
        "--calibration",
        str(calibration),
        "--background",
        "mask",
    )
    assert result.returncode == 0, result.stderr
    picture = cv2.imread(str(out))
    assert picture.shape == (720, 1280, 3)
    grey = picture[np.all(picture == picture[..., :1], axis=2)]  # not a dot
    assert set(np.unique(grey)) <= {0, 255}  # binary vegetation frame under the dots


def test_fuse_refuses_with_one_clear_line(rec, scans, frames, tmp_path):
    out = str(tmp_path / "x.png")
    beyond = run("fuse", str(rec), "--scan", "9", "--out", out)
    assert beyond.returncode == 2 and "has 4 scan(s) (0..3)" in beyond.stderr

    no_camera = tmp_path / "lidar_only.mcap"
    _write_recording(no_camera, [])
    missing = run("fuse", str(no_camera), "--scan", "1", "--out", out)
    assert missing.returncode == 2 and "no /camera/jpeg frames" in missing.stderr

    late = tmp_path / "late.mcap"
    shifted = [Frame(f.jpeg, f.t_host + 10**9, f.t_capture + 10**9, f.sequence) for f in frames]
    _write_recording(late, shifted)
    skewed = run("fuse", str(late), "--scan", "1", "--out", out, "--max-skew-ms", "40")
    assert skewed.returncode == 2 and "beyond --max-skew-ms 40" in skewed.stderr

    corrupt = tmp_path / "corrupt.mcap"
    broken = [Frame(f.jpeg[: len(f.jpeg) // 3], f.t_host, f.t_capture, f.sequence) for f in frames]
    _write_recording(corrupt, broken)
    bad = run("fuse", str(corrupt), "--scan", "1", "--out", out)
    assert bad.returncode == 2 and "not a decodable JPEG" in bad.stderr

    uncalibrated = tmp_path / "uncalibrated.mcap"
    _write_recording(uncalibrated, frames[:2], calibration={})
    nocal = run("fuse", str(uncalibrated), "--scan", "1", "--out", out)
    assert nocal.returncode == 2 and "--calibration FILE" in nocal.stderr
    for result in (beyond, missing, skewed, bad, nocal):
        assert "Traceback" not in result.stderr
    assert not (tmp_path / "x.png").exists()


def test_fuse_scan_counts_every_frame_problem(scans, frames):
    calibration = load_calibration(CALIBRATION)
    scan = scans[1]
    n = len(scan.points)
    t = scan_mid_time(scan)

    def check(result, reason):
        assert result.reason == reason
        assert np.isnan(result.ndvi).all() and len(result.ndvi) == n
        assert result.counts()["no_frame"] == n

    check(fuse_scan(scan, [], calibration), "no_frame")
    far = Frame(frames[0].jpeg, t + 80_000_000, t + 60_000_000)
    skew = fuse_scan(scan, [far], calibration)
    check(skew, "skew")
    assert skew.skew_ns == 60_000_000 and "limit 50 ms" in skew.detail
    assert fuse_scan(scan, [far], calibration, FusionConfig(max_skew_ns=70_000_000)).reason == "ok"
    check(fuse_scan(scan, [Frame(b"\xff\xd8garbage", t, t)], calibration), "corrupt_jpeg")
    small = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    wrong = fuse_scan(scan, [Frame(small, t, t, 7)], calibration)
    check(wrong, "size_mismatch")
    assert "640x480" in wrong.detail and "1280x720" in wrong.detail
    # The nearest of several is used even when a corrupt one is further away.
    good = fuse_scan(
        scan,
        [Frame(b"junk", t - 40_000_000, t - 40_000_000), Frame(frames[3].jpeg, t + 1, t + 1)],
        calibration,
    )
    assert good.reason == "ok" and good.counts()["ok"] > 1000


def test_a_half_size_decode_keeps_every_status_and_reads_the_covering_pixel(scans, frames):
    """The mapper's way (MAPPER_REDUCTION): the same projection and occlusion, so the same
    status for every point; NDVI from the half-size decode at (row // 2, col // 2)."""
    calibration = load_calibration(CALIBRATION)
    scan = scans[1]
    full = fuse_scan(scan, frames, calibration, keep_ndvi_frame=False)
    half = fuse_scan(scan, frames, calibration, keep_ndvi_frame=False, reduction=2)
    frame = half.frame
    assert half.reason == "ok" and half.counts()["ok"] > 1000
    np.testing.assert_array_equal(half.points.status, full.points.status)
    camera = calibration.camera
    reduced = frame.decode(2)
    assert reduced.shape == (360, 640, 3)
    ok = half.points.status == PointStatus.OK
    pixel = full.projection.pixel[ok]
    expected = ndvi_image(reduced, camera.channels, calibration.reflectance)
    np.testing.assert_array_equal(half.ndvi[ok], expected[pixel[:, 1] // 2, pixel[:, 0] // 2])
    # What the mapper keeps, the mean over the points, moves little: 0.0045 here, where
    # the 7 px dots on a contrasting background put most points near a rim (their pixel
    # mixes in the background); the demo survey's trees moved at most 0.0041.
    assert abs(float(half.ndvi[ok].mean() - full.ndvi[ok].mean())) < 0.01
    small = cv2.imencode(".jpg", np.zeros((480, 640, 3), np.uint8))[1].tobytes()
    t = scan_mid_time(scan)
    wrong = fuse_scan(scan, [Frame(small, t, t)], calibration, keep_ndvi_frame=False, reduction=2)
    assert wrong.reason == "size_mismatch" and "1/2 size" in wrong.detail
    with pytest.raises(ValueError, match="keep_ndvi_frame"):
        fuse_scan(scan, [frame], calibration, reduction=2)


# Chroma subsampling 4:4:4, 4:2:2 and 4:2:0 (OpenCV's flags), and a size no reduction
# divides, as another camera or video mode may send them.
SAMPLINGS = (
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_422,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
)


def test_frames_decode_to_opencvs_pixels_and_damage_as_opencv_takes_it(frames):
    """`Frame.decode` (libjpeg-turbo through simplejpeg) gives `cv2.imdecode`'s pixels at
    every reduction; a frame cut short is refused as imdecode refuses it, one with flipped
    bits decoded as imdecode decodes it."""
    flags = {
        1: cv2.IMREAD_COLOR,
        2: cv2.IMREAD_REDUCED_COLOR_2,
        4: cv2.IMREAD_REDUCED_COLOR_4,
        8: cv2.IMREAD_REDUCED_COLOR_8,
    }
    picture = cv2.imdecode(np.frombuffer(frames[0].jpeg, np.uint8), cv2.IMREAD_COLOR)
    odd = cv2.resize(picture, (1283, 717))
    jpegs = [f.jpeg for f in frames[:4]]
    for sampling in SAMPLINGS:
        params = [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, sampling]
        jpegs.append(cv2.imencode(".jpg", odd, params)[1].tobytes())
    jpegs.append(cv2.imencode(".jpg", cv2.cvtColor(odd, cv2.COLOR_BGR2GRAY))[1].tobytes())
    rng = np.random.default_rng(0)
    flipped = 0
    for jpeg in jpegs:
        damaged = bytearray(jpeg)
        for at in rng.integers(len(jpeg) // 2, len(jpeg) - 2, 4):
            damaged[at] ^= 1 << int(rng.integers(8))
        for reduction, flag in flags.items():
            expected = cv2.imdecode(np.frombuffer(jpeg, np.uint8), flag)
            decoded = Frame(jpeg, 0, 0).decode(reduction)
            assert decoded.dtype == np.uint8 and decoded.shape == expected.shape
            np.testing.assert_array_equal(decoded, expected)
            with pytest.raises(ParseError, match="not a decodable JPEG"):
                Frame(jpeg[: len(jpeg) * 2 // 3], 0, 0).decode(reduction)
            assert cv2.imdecode(np.frombuffer(jpeg[: len(jpeg) * 2 // 3], np.uint8), flag) is None
            expected = cv2.imdecode(np.frombuffer(bytes(damaged), np.uint8), flag)
            if expected is not None:
                flipped += 1
                np.testing.assert_array_equal(
                    Frame(bytes(damaged), 0, 0).decode(reduction), expected
                )
    assert flipped >= 8  # most damaged frames still decode (imdecode's way)
    with pytest.raises(ValueError, match="reduction"):
        frames[0].decode(3)


def test_help():
    for command in (["fuse"], ["calibrate"], ["calibrate", "reflectance"]):
        result = run(*command, "--help")
        assert result.returncode == 0 and result.stdout.startswith("usage: treetraits")
