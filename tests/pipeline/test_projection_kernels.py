"""The projection's compiled steps (`projection._project`, `_hidden`, `_statuses`) give the
bits of the NumPy formulation they replaced: on the twin drive's scans with its camera,
and on points all around the CitrusFarm camera (behind it, beside it, at zero depth, past
the lens model's fold-back radius, NaN); and a scan compiles nothing beyond the warm-up."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from tests.helpers.kernels import assert_warm_ups_cover
from tests.helpers.paths import CITRUSFARM
from tests.helpers.twin import grid_drive
from treetraits.drivers.calibration import load_calibration
from treetraits.pipeline import projection as projection_module
from treetraits.pipeline.fusion import MAPPER_REDUCTION
from treetraits.pipeline.ndvi import PixelNdvi
from treetraits.pipeline.projection import (
    MIN_DEPTH_M,
    OcclusionRule,
    PointStatus,
    Projection,
    max_valid_radius,
    occluded,
    point_ndvi,
    project_points,
    xyz,
)


def numpy_project(points, camera, T_camera_lidar, min_depth=MIN_DEPTH_M) -> Projection:
    """`project_points` as NumPy computed it before its kernel."""
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
        column = np.floor(u + 0.5)
        row = np.floor(v + 0.5)
        in_image = (
            in_front & (column >= 0) & (column < camera.width) & (row >= 0) & (row < camera.height)
        )
    pixel = np.zeros((len(p), 2), dtype=np.int64)
    pixel[in_image, 0] = column[in_image]
    pixel[in_image, 1] = row[in_image]
    return Projection(uv, depth, in_front, in_image, pixel)


def numpy_occluded(projection, width, height, rule) -> np.ndarray:
    """`occluded` as NumPy computed it before its kernel."""
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
        padded = np.pad(nearest, n, constant_values=np.inf)
        spread = nearest.copy()
        for dr in range(2 * n + 1):
            for dc in range(2 * n + 1):
                np.minimum(spread, padded[dr : dr + rows, dc : dc + cols], out=spread)
        nearest = spread
    front = nearest.ravel()[block]
    hidden[index] = depth > front + rule.margin_m + rule.margin_rel * front
    return hidden


def numpy_point_ndvi(projection, ndvi_frame, camera, rule) -> tuple[np.ndarray, np.ndarray]:
    """`point_ndvi`'s values and statuses as NumPy computed them before the kernels."""
    n = len(projection.depth)
    status = np.full(n, PointStatus.OUTSIDE, dtype=np.uint8)
    status[~projection.in_front] = PointStatus.BEHIND
    status[(projection.depth >= MIN_DEPTH_M) & ~projection.in_front] = PointStatus.OUTSIDE
    values = np.full(n, np.nan, dtype=np.float32)
    visible = projection.in_image & ~numpy_occluded(projection, camera.width, camera.height, rule)
    status[projection.in_image] = PointStatus.OCCLUDED
    cols, rows = projection.pixel[visible, 0], projection.pixel[visible, 1]
    sampled = ndvi_frame[rows, cols].astype(np.float32)
    values[visible] = sampled
    status[visible] = np.where(np.isnan(sampled), PointStatus.NO_NDVI, PointStatus.OK)
    return values, status


def same_projection(got: Projection, want: Projection) -> None:
    for field in dataclasses.fields(Projection):
        a, b = getattr(got, field.name), getattr(want, field.name)
        assert a.dtype == b.dtype and a.shape == b.shape, field.name
        assert a.tobytes() == b.tobytes(), field.name


@functools.cache
def drive_frames() -> tuple:
    """(scan points, NDVI of its frame at the mapper's reduction) for every 8th scan of the
    twin drive, and its calibration."""
    data = grid_drive()
    calibration = data.calibration
    pairs = []
    for scan, frame in list(zip(data.scans, data.frames, strict=True))[::8]:
        camera = calibration.camera
        image = frame.decode(MAPPER_REDUCTION)
        ndvi = PixelNdvi(
            image,
            camera.channels,
            calibration.reflectance,
            MAPPER_REDUCTION,
            (camera.height, camera.width),
        )
        pairs.append((scan.points, ndvi))
    return tuple(pairs), calibration


def awkward_points(n: int = 20_000, seed: int = 3) -> np.ndarray:
    """Points all around the origin of the LiDAR frame, some on the camera's lens plane
    (zero depth, exactly), some NaN."""
    rng = np.random.default_rng(seed)
    points = rng.normal(0.0, 8.0, (n, 3))
    points[::997] = np.nan
    return points


def test_twin_drive_projections_and_ndvi_are_numpy_s():
    pairs, calibration = drive_frames()
    camera, extrinsic = calibration.camera, calibration.T_camera_lidar
    rules = (OcclusionRule(), OcclusionRule(block_px=5, neighbours=2), OcclusionRule(neighbours=0))
    visible = 0
    for points, ndvi in pairs:
        got = project_points(points, camera, extrinsic)
        want = numpy_project(points, camera, extrinsic)
        same_projection(got, want)
        for rule in rules:
            hidden = occluded(got, camera.width, camera.height, rule)
            assert (
                hidden.tobytes()
                == numpy_occluded(want, camera.width, camera.height, rule).tobytes()
            )
            result = point_ndvi(points, ndvi, camera, extrinsic, rule, projection=got)
            values, status = numpy_point_ndvi(want, ndvi, camera, rule)
            assert result.ndvi.tobytes() == values.tobytes()
            assert result.status.tobytes() == status.tobytes()
        visible += int((result.status == PointStatus.OK).sum())
        assert (result.status == PointStatus.OCCLUDED).any()
    assert visible > 1000  # the camera saw the trees


@pytest.mark.parametrize("limit", ["lens", "none"])
def test_points_all_around_the_camera_project_as_numpy_s(limit):
    calibration = load_calibration(CITRUSFARM)
    camera, extrinsic = calibration.camera, calibration.T_camera_lidar
    if limit == "none":
        camera = dataclasses.replace(camera, dist=np.zeros(5))
    assert np.isfinite(max_valid_radius(camera.dist)) == (limit == "lens")
    points = awkward_points()
    # Points on the lens plane: depth 0 (most exactly, after the round trip): 0/0, x/0.
    on_plane = np.array([[0.0, 0.0, 0.0], [1.5, -2.0, 0.0], [-1.5, 0.0, 0.0], [0.0, 2.0, 0.0]])
    points[1:5] = on_plane @ np.linalg.inv(extrinsic)[:3, :3].T + np.linalg.inv(extrinsic)[:3, 3]
    got = project_points(points, camera, extrinsic)
    with np.errstate(all="ignore"):  # inf and NaN through the lens model
        want = numpy_project(points, camera, extrinsic)
    same_projection(got, want)
    assert (want.depth == 0).sum() >= 2 and np.isnan(want.uv).sum() > 40
    statuses = np.bincount(
        numpy_point_ndvi(want, np.zeros((camera.height, camera.width)), camera, OcclusionRule())[1],
        minlength=6,
    )
    assert (statuses[[PointStatus.OK, PointStatus.BEHIND, PointStatus.OUTSIDE]] > 0).all()
    frame = np.random.default_rng(1).uniform(-1, 1, (camera.height, camera.width))
    frame[::7] = np.nan
    for rule in (OcclusionRule(), OcclusionRule(enabled=False)):
        result = point_ndvi(points, frame, camera, extrinsic, rule, projection=got)
        values, status = numpy_point_ndvi(want, frame, camera, rule)
        assert result.ndvi.tobytes() == values.tobytes()
        assert result.status.tobytes() == status.tobytes()


def test_a_scan_compiles_nothing_beyond_the_warm_up():
    kernels = (
        projection_module._project,
        projection_module._hidden,
        projection_module._statuses,
    )
    pairs, calibration = drive_frames()
    points, ndvi = pairs[0]
    assert_warm_ups_cover(
        kernels,
        (projection_module.compile_kernels,),
        lambda: point_ndvi(points, ndvi, calibration.camera, calibration.T_camera_lidar),
    )
