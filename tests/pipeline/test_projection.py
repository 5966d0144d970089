"""The camera model against cv2.projectPoints on the real CitrusFarm calibration, against
hand-computed pixels, the z-buffer on a near wall in front of a far wall, and the choice
of the frame for a scan."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from tests.helpers.paths import CITRUSFARM
from treetraits.drivers.calibration import CameraModel, load_calibration
from treetraits.drivers.records import POINT_DTYPE, Scan
from treetraits.pipeline.projection import (
    OcclusionRule,
    PointStatus,
    max_valid_radius,
    nearest_frame,
    occluded,
    point_ndvi,
    project_points,
    scan_mid_time,
)


def _points_in_front(camera_to_lidar: np.ndarray, n: int, seed: int) -> np.ndarray:
    """Random points in front of the camera (depth 0.3-40 m, up to ~55 deg off axis),
    returned in the LiDAR frame."""
    rng = np.random.default_rng(seed)
    depth = rng.uniform(0.3, 40.0, n)
    camera = np.column_stack(
        [rng.uniform(-1.4, 1.4, n) * depth, rng.uniform(-0.9, 0.9, n) * depth, depth]
    )
    return camera @ camera_to_lidar[:3, :3].T + camera_to_lidar[:3, 3]


def test_citrusfarm_camera_model_matches_cv2_projectpoints():
    calibration = load_calibration(CITRUSFARM)
    camera, extrinsic = calibration.camera, calibration.T_camera_lidar
    points = _points_in_front(np.linalg.inv(extrinsic), 20_000, seed=1)
    ours = project_points(points, camera, extrinsic)

    # The whole chain, cv2 given the extrinsic as rvec/tvec.
    rvec, _ = cv2.Rodrigues(extrinsic[:3, :3])
    theirs, _ = cv2.projectPoints(
        points.reshape(-1, 1, 3), rvec, extrinsic[:3, 3], camera.K, camera.dist
    )
    np.testing.assert_allclose(ours.uv, theirs.reshape(-1, 2), rtol=0, atol=1e-6)
    # The lens model alone (same camera-frame points): agreement to rounding.
    in_camera = points @ extrinsic[:3, :3].T + extrinsic[:3, 3]
    lens, _ = cv2.projectPoints(
        in_camera.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist
    )
    np.testing.assert_allclose(ours.uv, lens.reshape(-1, 2), rtol=0, atol=1e-9)
    np.testing.assert_allclose(ours.depth, in_camera[:, 2], rtol=1e-12)

    # In-image flags agree with cv2's pixels wherever the lens model is monotonic.
    uv = theirs.reshape(-1, 2)
    inside = (
        (np.floor(uv[:, 0] + 0.5) >= 0)
        & (np.floor(uv[:, 0] + 0.5) < camera.width)
        & (np.floor(uv[:, 1] + 0.5) >= 0)
        & (np.floor(uv[:, 1] + 0.5) < camera.height)
    )
    r = np.hypot(in_camera[:, 0], in_camera[:, 1]) / in_camera[:, 2]
    regular = r < max_valid_radius(camera.dist)
    np.testing.assert_array_equal(ours.in_image[regular], inside[regular])
    assert 0.3 < ours.in_image.mean() < 0.8  # the test covers both sides of the border


def test_lens_fold_back_is_not_in_the_image():
    """CitrusFarm's k2 < 0 makes the polynomial fold back: a ray ~65 deg off axis lands on
    the principal point in cv2. It is not in the 85 deg-wide image."""
    calibration = load_calibration(CITRUSFARM)
    camera = calibration.camera
    limit = max_valid_radius(camera.dist)
    assert 1.3 < limit < 1.6
    k1, k2 = camera.dist[:2]
    s = (k1 + np.sqrt(k1 * k1 + 4 * -k2)) / (2 * -k2)  # 1 + k1 s + k2 s^2 = 0
    point = np.array([[np.sqrt(s) * 5.0, 0.0, 5.0]])  # camera frame
    uv, _ = cv2.projectPoints(
        point.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), camera.K, camera.dist
    )
    assert abs(uv[0, 0, 0] - camera.K[0, 2]) < 20  # cv2 puts it mid-image (p2 moves it a bit)
    ours = project_points(point, camera, np.eye(4))
    assert not ours.in_front[0] and not ours.in_image[0]
    result = point_ndvi(point, np.zeros((720, 1280), np.float32), camera, np.eye(4))
    assert result.status[0] == PointStatus.OUTSIDE and np.isnan(result.ndvi[0])


# A simple camera: 640x480, no distortion; lidar (x fwd, y left, z up) -> optical frame.
SIMPLE = CameraModel(640, 480, np.array([[500.0, 0, 320], [0, 400.0, 240], [0, 0, 1]]), np.zeros(5))
T_SIMPLE = np.array([[0, -1, 0, 0.1], [0, 0, -1, -0.2], [1, 0, 0, 0.05], [0, 0, 0, 1]], dtype=float)


def _pixel_index_frame() -> np.ndarray:
    """An NDVI frame whose value tells which pixel was read: (row * 640 + col) / 2**19."""
    rows, cols = np.mgrid[0:480, 0:640]
    return ((rows * 640 + cols) / 2**19).astype(np.float32)


def test_projection_matches_hand_computed_pixels():
    points = np.array(
        [
            [4.0, 1.0, 0.5],  # camera (-0.9, -0.7, 4.05)
            [10.0, -2.0, -1.0],  # camera (2.1, 0.8, 10.05)
            [2.0, 0.0, 0.0],  # camera (0.1, -0.2, 2.05)
            [-3.0, 0.0, 0.0],  # behind
            [1.0, 5.0, 0.0],  # in front, far to the left
        ]
    )
    projection = project_points(points, SIMPLE, T_SIMPLE)
    hand = [
        (500 * -0.9 / 4.05 + 320, 400 * -0.7 / 4.05 + 240),
        (500 * 2.1 / 10.05 + 320, 400 * 0.8 / 10.05 + 240),
        (500 * 0.1 / 2.05 + 320, 400 * -0.2 / 2.05 + 240),
    ]
    np.testing.assert_allclose(projection.uv[:3], hand, rtol=0, atol=1e-9)
    np.testing.assert_allclose(projection.depth, [4.05, 10.05, 2.05, -2.95, 1.05], atol=1e-12)
    assert projection.in_image.tolist() == [True, True, True, False, False]
    assert projection.in_front.tolist() == [True, True, True, False, True]

    result = point_ndvi(points, _pixel_index_frame(), SIMPLE, T_SIMPLE)
    for i, (u, v) in enumerate(hand):  # nearest pixel: round(u), round(v)
        column, row = int(np.floor(u + 0.5)), int(np.floor(v + 0.5))
        assert result.ndvi[i] == np.float32((row * 640 + column) / 2**19)
    assert result.status.tolist() == [0, 0, 0, PointStatus.BEHIND, PointStatus.OUTSIDE]
    assert np.isnan(result.ndvi[3:]).all()
    assert result.counts() == {
        "ok": 3,
        "behind": 1,
        "outside": 1,
        "occluded": 0,
        "no_ndvi": 0,
        "no_frame": 0,
    }


def test_pixel_borders_and_structured_points():
    # u = 500 * x / z + 320 with z = 1: choose x for u = -0.5 (in), -0.51 (out), 639.49 (in),
    # 639.5 (out); camera frame points, identity extrinsic.
    xs = np.array([-320.5, -320.51, 319.49, 319.5]) / 500
    camera_points = np.column_stack([xs, np.zeros(4), np.ones(4)])
    assert project_points(camera_points, SIMPLE, np.eye(4)).in_image.tolist() == [
        True,
        False,
        True,
        False,
    ]
    scan_points = np.zeros(2, dtype=POINT_DTYPE)
    scan_points["x"], scan_points["z"] = [4.0, -4.0], [0.5, 0.5]
    projection = project_points(scan_points, SIMPLE, T_SIMPLE)
    assert projection.in_image.tolist() == [True, False]


def _wall(distance: float, half_width: float, half_height: float) -> np.ndarray:
    """A wall facing the sensor, sampled like a VLP-16: 0.2 deg azimuth x 2 deg elevation."""
    azimuth = np.radians(np.arange(-60, 60, 0.2))
    elevation = np.radians(np.arange(-15, 16, 2.0))
    a, e = np.meshgrid(azimuth, elevation)
    y, z = distance * np.tan(a), distance * np.tan(e) / np.cos(a)
    keep = (np.abs(y) <= half_width) & (np.abs(z) <= half_height)
    return np.column_stack([np.full(keep.sum(), distance), y[keep], z[keep]])


def test_near_wall_hides_the_far_wall_behind_it():
    near = _wall(2.0, 0.4, 0.3)
    far = _wall(5.0, 3.0, 1.2)  # includes the part behind the near wall, as a camera ray sees
    points = np.vstack([near, far])
    frame = np.full((480, 640), 0.5, dtype=np.float32)
    result = point_ndvi(points, frame, SIMPLE, T_SIMPLE)
    near_status, far_status = result.status[: len(near)], result.status[len(near) :]
    assert (near_status == PointStatus.OK).all()  # the near wall keeps every value
    np.testing.assert_array_equal(result.ndvi[: len(near)], 0.5)

    # Which far points are behind the near wall in the camera's own view: compare pixels.
    projection = project_points(points, SIMPLE, T_SIMPLE)
    near_uv, far_uv = projection.uv[: len(near)], projection.uv[len(near) :]
    low, high = near_uv.min(axis=0), near_uv.max(axis=0)
    behind = np.all((far_uv > low) & (far_uv < high), axis=1)
    assert behind.sum() > 500
    assert (far_status[behind] == PointStatus.OCCLUDED).all()
    assert np.isnan(result.ndvi[len(near) :][behind]).all()
    # Far points clear of the near wall by more than the rule's reach (3 blocks) keep values.
    reach = 3 * OcclusionRule().block_px
    clear = np.any((far_uv < low - reach) | (far_uv > high + reach), axis=1)
    clear &= projection.in_image[len(near) :]
    assert clear.sum() > 1000
    assert (far_status[clear] == PointStatus.OK).all()

    # Without the z-buffer the far wall would take the near wall's pixels.
    plain = point_ndvi(points, frame, SIMPLE, T_SIMPLE, OcclusionRule(enabled=False))
    assert (plain.status[len(near) :][behind] == PointStatus.OK).all()


def test_one_slanted_surface_does_not_hide_itself():
    # A wall at 45 deg (depth 2..6 m across the image): depths differ inside each block
    # window by far less than the margin.
    azimuth = np.radians(np.arange(-25, 25, 0.2))
    elevation = np.radians(np.arange(-15, 16, 2.0))
    a, e = np.meshgrid(azimuth, elevation)
    distance = 4.0 / (np.cos(a) + np.sin(a))  # the plane x + y = 4
    points = np.column_stack(
        [
            (distance * np.cos(a)).ravel(),
            (distance * np.sin(a)).ravel(),
            (distance * np.tan(e)).ravel(),
        ]
    )
    projection = project_points(points, SIMPLE, T_SIMPLE)
    assert projection.in_image.sum() > 2000
    assert not occluded(projection, 640, 480, OcclusionRule()).any()


def test_pixel_without_ndvi_is_counted():
    frame = np.full((480, 640), np.nan, dtype=np.float32)
    result = point_ndvi(np.array([[4.0, 0.0, 0.0]]), frame, SIMPLE, T_SIMPLE)
    assert result.status[0] == PointStatus.NO_NDVI and result.counts()["no_ndvi"] == 1
    with pytest.raises(ValueError, match="not the calibrated 640x480"):
        point_ndvi(np.zeros((1, 3)), np.zeros((720, 1280), np.float32), SIMPLE, T_SIMPLE)


def test_nearest_frame_and_the_skew_limit():
    ms = 1_000_000
    times = [1000 * ms, 1033 * ms, 1066 * ms, 1100 * ms]
    assert nearest_frame([], 1000 * ms).reason == "no_frame"
    match = nearest_frame(times, 1070 * ms, 50 * ms)
    assert match.ok and match.index == 2 and match.skew_ns == -4 * ms
    edge = nearest_frame(times, 1150 * ms, 50 * ms)  # exactly at the limit: accepted
    assert edge.index == 3 and edge.skew_ns == -50 * ms
    late = nearest_frame(times, 1151 * ms, 50 * ms)
    assert not late.ok and late.reason == "skew" and late.skew_ns == -51 * ms
    early = nearest_frame(times, 900 * ms, 50 * ms)
    assert early.reason == "skew" and early.skew_ns == 100 * ms
    tie = nearest_frame([10, 30], 20, 50)
    assert tie.index == 0
    # Unsorted input is fine.
    assert nearest_frame([1100 * ms, 1000 * ms], 1010 * ms, 50 * ms).index == 1


def test_scan_middle_is_on_the_host_clock():
    # The device clock of an unsynchronised VLP-16 is far from the host's (here 25 min).
    scan = Scan(
        points=np.zeros(0, dtype=POINT_DTYPE),
        t_start=1_000_000_000_000,
        t_end=1_000_100_000_000,
        t_host=2_500_000_000_000,
        complete=True,
        packets=76,
        lost_packets=0,
        model="VLP-16",
        return_mode="strongest",
    )
    assert scan_mid_time(scan) == 2_500_000_000_000 - 50_000_000
