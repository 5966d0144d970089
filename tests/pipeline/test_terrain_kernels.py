"""The compiled steps of the crop and the terrain (`treetraits.jit` kernels) give the same
bits as the NumPy formulations they replaced, on a ray-cast VLP-16 scan of a sloped,
furrowed grove, and a scan compiles nothing beyond the warm-ups."""

from __future__ import annotations

import functools
import math

import numpy as np
import pytest
from scipy import ndimage

from tests.helpers.kernels import assert_warm_ups_cover
from tests.helpers.terrain import RollingGround, one_scan, rotation
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR
from treetraits.pipeline import detection, terrain
from treetraits.pipeline.config import DetectionConfig
from treetraits.pipeline.detection import crop, crop_mask, detect, to_base
from treetraits.pipeline.terrain import TerrainGrid, fit_terrain


@functools.cache
def scan_points() -> np.ndarray:
    return one_scan(RollingGround()).points


def cropped_xyz() -> np.ndarray:
    config = DetectionConfig()
    xyz = to_base(scan_points(), DEFAULT_T_BASE_LIDAR)
    return xyz[crop_mask(xyz, config.crop, DEFAULT_T_BASE_LIDAR[:2, 3])]


def numpy_lowest_layer(xyz, config, x0, y0, nx, ny) -> np.ndarray:
    """`terrain._lowest_layer` as NumPy computed it before its kernel."""
    c = config.cell_m
    i = np.floor((xyz[:, 0] - x0) / c).astype(np.int64)
    j = np.floor((xyz[:, 1] - y0) / c).astype(np.int64)
    inside = (i >= 0) & (i < nx) & (j >= 0) & (j < ny)
    cell, z = (i * ny + j)[inside], xyz[inside, 2]
    lowest = np.full(nx * ny, np.inf)
    np.minimum.at(lowest, cell, z)
    layer = z <= lowest[cell] + config.lowest_layer_m
    total = np.bincount(cell[layer], weights=z[layer], minlength=nx * ny)
    count = np.bincount(cell[layer], minlength=nx * ny)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.where(count > 0, total / np.maximum(count, 1), np.nan)
    return mean.reshape(nx, ny)


def numpy_z_at(grid: TerrainGrid, x, y) -> np.ndarray:
    """`TerrainGrid.z_at` as NumPy computed it before its kernel."""
    fx = (np.asarray(x, dtype=float) - grid.x0) / grid.cell - 0.5
    fy = (np.asarray(y, dtype=float) - grid.y0) / grid.cell - 0.5
    nx, ny = grid.z.shape
    fx, fy = np.clip(fx, 0.0, nx - 1.0), np.clip(fy, 0.0, ny - 1.0)
    i = np.minimum(fx.astype(np.int64), nx - 2) if nx > 1 else np.zeros_like(fx, np.int64)
    j = np.minimum(fy.astype(np.int64), ny - 2) if ny > 1 else np.zeros_like(fy, np.int64)
    tx, ty = fx - i, fy - j
    i1, j1 = np.minimum(i + 1, nx - 1), np.minimum(j + 1, ny - 1)
    z = grid.z
    return (
        z[i, j] * (1 - tx) * (1 - ty)
        + z[i1, j] * tx * (1 - ty)
        + z[i, j1] * (1 - tx) * ty
        + z[i1, j1] * tx * ty
    )


def numpy_grow(lowest, observed, ground, accepted, config) -> np.ndarray:
    """`terrain._grow` as NumPy and scipy.ndimage computed it before its kernel."""
    c = config.cell_m
    pending = observed & ~accepted
    window = max(3, 2 * round(config.support_radius_m / c) + 1)
    for _ in range(4 * max(lowest.shape)):
        gap, (near_i, near_j) = ndimage.distance_transform_edt(~accepted, return_indices=True)
        gap = gap * c
        step = lowest - ground[near_i, near_j]
        allowance = config.step_tolerance_m + config.max_slope * gap
        take = pending & (gap <= config.max_gap_m) & (np.abs(step) <= allowance)
        lowest_around = ndimage.minimum_filter(np.where(take, lowest, np.inf), size=window)
        take &= lowest <= lowest_around + config.step_tolerance_m
        around = ndimage.uniform_filter(take.astype(float), window, mode="constant")
        support = np.rint(around * window * window) - 1
        take &= (gap <= 2 * c) | (support >= config.min_support_cells)
        if not take.any():
            break
        ground = np.where(take, lowest, ground)
        accepted = accepted | take
        pending &= ~take
    return np.where(accepted, ground, np.nan)


def test_lowest_layer_is_numpys_bit_for_bit():
    config = DetectionConfig().terrain
    xyz = cropped_xyz()
    assert len(xyz) > 10_000
    # The crop box's grid, and one smaller than the points' extent (points fall outside).
    for x0, y0, nx, ny in ((-15.0, -15.0, 60, 60), (-4.2, -3.1, 13, 17)):
        got = terrain._lowest_layer(xyz, config, x0, y0, nx, ny)
        want = numpy_lowest_layer(xyz, config, x0, y0, nx, ny)
        assert np.isfinite(want).sum() > 100
        assert got.tobytes() == want.tobytes()


def test_z_at_and_height_are_numpys_bit_for_bit():
    config = DetectionConfig()
    xyz = cropped_xyz()
    grid = fit_terrain(xyz, config.terrain, config.crop.x_m, config.crop.y_m)
    assert np.ptp(grid.z) > 1.0  # a slope: the interpolation has something to do
    want = xyz[:, 2] - numpy_z_at(grid, xyz[:, 0], xyz[:, 1])
    assert grid.height(xyz).tobytes() == want.tobytes()
    # Beyond the grid (clamped), on its edges and cell centres, a 2-D array, a scalar.
    rng = np.random.default_rng(3)
    xy = np.concatenate([rng.uniform(-20, 20, (500, 2)), [[-15, -15], [15, 15], [0.25, -0.25]]])
    assert grid.z_at(xy[:, 0], xy[:, 1]).tobytes() == numpy_z_at(grid, *xy.T).tobytes()
    square = xy[:500].reshape(25, 20, 2)
    got = grid.z_at(square[..., 0], square[..., 1])
    assert got.shape == (25, 20)
    assert got.tobytes() == numpy_z_at(grid, square[..., 0], square[..., 1]).tobytes()
    value = grid.z_at(3.3, -7.1)
    assert isinstance(value, float) and value == float(numpy_z_at(grid, 3.3, -7.1))


@pytest.mark.parametrize("seeds_m", [2.0, 4.0, 0.0])
def test_grow_is_numpys_bit_for_bit(seeds_m):
    """Grown from the cells within `seeds_m` of the robot: few seeds (many rounds, gaps
    crossed in patches), more, none."""
    config = DetectionConfig()
    terrain_config = config.terrain
    nx = ny = 60
    lowest = numpy_lowest_layer(cropped_xyz(), terrain_config, -15.0, -15.0, nx, ny)
    observed = np.isfinite(lowest)
    centres = -15.0 + (np.arange(nx) + 0.5) * terrain_config.cell_m
    seeds = observed & (np.hypot(centres[:, None], centres[None, :]) <= seeds_m)
    ground = np.where(seeds, lowest, np.nan)
    want = numpy_grow(lowest, observed, ground, seeds, terrain_config)
    got = terrain._grow(lowest, observed, ground.copy(), seeds.copy(), terrain_config)
    assert got.tobytes() == want.tobytes()
    assert np.isfinite(want).sum() > (400 if seeds_m else -1)


def numpy_median3(ground: np.ndarray) -> np.ndarray:
    """`terrain._median3` as NumPy computed it before its kernel."""
    padded = np.pad(ground, 1, constant_values=np.nan)
    i, j = np.nonzero(np.isfinite(ground))
    stack = np.stack([padded[i + di, j + dj] for di in range(3) for dj in range(3)], axis=-1)
    ordered = np.sort(stack, axis=-1)
    middle = (np.isfinite(stack).sum(axis=-1) - 1) // 2
    out = np.full(ground.shape, np.nan)
    out[i, j] = np.take_along_axis(ordered, middle[:, None], axis=-1)[:, 0]
    return out


def test_median3_is_numpys_bit_for_bit():
    config = DetectionConfig()
    xyz = cropped_xyz()
    lowest = numpy_lowest_layer(xyz, config.terrain, -15.0, -15.0, 60, 60)
    ground = np.where(fit_terrain(xyz, config.terrain, config.crop.x_m, config.crop.y_m).ground,
                      lowest, np.nan)  # fmt: skip
    assert terrain._median3(ground).tobytes() == numpy_median3(ground).tobytes()
    # Infinities sort but do not count, as np.sort and isfinite have it; a grid a row high.
    some = np.argwhere(np.isfinite(ground))[::50]
    ground[some[:, 0], some[:, 1]] = np.inf
    ground[0, :5] = -np.inf
    assert terrain._median3(ground).tobytes() == numpy_median3(ground).tobytes()
    row = ground[20:21, :]
    assert terrain._median3(row).tobytes() == numpy_median3(row).tobytes()


def test_gaussian_is_scipys_with_signed_zeros_and_past_the_grid():
    """Negative zeros (kept or lost by the pairs beyond the edges, as scipy's sums do),
    widths far wider than the grid, and some cells only."""
    values = np.zeros((9, 7))
    values[4, 3], values[0, 0], values[8, 6], values[2, 5] = -0.0, -1.5, 2.0, -0.0
    for sigma in (0.4, 1.0, 3.0, 40.0):
        want = ndimage.gaussian_filter(values, sigma, mode="constant", truncate=3.0)
        got = terrain._gaussian(values, terrain._gaussian_weights(sigma, 3.0))
        assert got.tobytes() == want.tobytes()
    # Only some cells wanted (the fill's missing ones): those are scipy's, the rest NaN.
    wanted = np.zeros(values.shape, dtype=bool)
    wanted[4, :3], wanted[7, 6], wanted[0, 0] = True, True, True
    for sigma in (1.0, 40.0):
        want = ndimage.gaussian_filter(values, sigma, mode="constant", truncate=3.0)
        got = terrain._gaussian(values, terrain._gaussian_weights(sigma, 3.0), wanted)
        assert got[wanted].tobytes() == want[wanted].tobytes()
        assert np.isnan(got[~wanted]).all()
    negative = np.full((5, 4), -0.0)
    want = ndimage.gaussian_filter(negative, 9.0, mode="constant", truncate=3.0)
    assert terrain._gaussian(negative, terrain._gaussian_weights(9.0, 3.0)).tobytes() == (
        want.tobytes()
    )


@pytest.mark.parametrize("shape", [(1, 5), (4, 1), (1, 1)])
def test_z_at_on_a_grid_one_cell_wide(shape):
    grid = TerrainGrid(-1.0, -2.0, 0.5, np.arange(np.prod(shape), dtype=float).reshape(shape),
                       np.ones(shape, bool), np.ones(shape, bool))  # fmt: skip
    x, y = np.meshgrid(np.linspace(-2, 2, 9), np.linspace(-3, 1, 9))
    assert grid.z_at(x, y).tobytes() == numpy_z_at(grid, x, y).tobytes()


@pytest.mark.parametrize("tilted", [False, True], ids=["level-mount", "tilted-mount"])
def test_crop_is_to_base_and_crop_mask(tilted):
    points = scan_points()
    mount = DEFAULT_T_BASE_LIDAR.copy()
    if tilted:
        mount[:3, :3] = rotation(0.05, -math.atan(0.15))
    config = DetectionConfig().crop
    xyz = to_base(points, mount)
    keep = np.flatnonzero(crop_mask(xyz, config, mount[:2, 3]))
    assert 0 < len(keep) < len(points)  # the box and the robot drop some
    got_xyz, got_keep = crop(points, mount, config)
    assert got_keep.dtype == keep.dtype and got_keep.tobytes() == keep.tobytes()
    assert got_xyz.tobytes() == np.take(xyz, keep, axis=0).tobytes()
    # Points given as a read-only, strided selection: the same, without compiling anew.
    every_other = points[::2]
    every_other.flags.writeable = False
    xyz = to_base(every_other, mount)
    keep = np.flatnonzero(crop_mask(xyz, config, mount[:2, 3]))
    got_xyz, got_keep = crop(every_other, mount, config)
    assert got_keep.tobytes() == keep.tobytes()
    assert got_xyz.tobytes() == np.take(xyz, keep, axis=0).tobytes()
    assert len(detection._crop_level.signatures) == 1


def test_a_scan_compiles_nothing_beyond_the_warm_ups():
    kernels = (
        terrain._bilinear,
        terrain._lowest_layer_mean,
        terrain._grow_once,
        detection._crop_level,
    )
    assert_warm_ups_cover(
        kernels,
        (terrain.compile_kernels, detection.compile_kernels),
        lambda: detect(scan_points(), None, DEFAULT_T_BASE_LIDAR, DetectionConfig()),
    )
