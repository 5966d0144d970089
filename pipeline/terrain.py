"""The terrain under one scan: an elevation grid grown outwards from the robot.

Why this filter. A grove floor is not a plane: it slopes (up to 15 % along a row, 8 %
across), undulates, has furrows and raised beds. One plane per scan leaves ground a
few decimetres above it at range, and that ground clusters into false trees. Filters
that follow the terrain come in two families: morphological (progressive morphological
filter, PMF) and cloth simulation (CSF). Both judge a cell against a window as wide as
the largest object, and a citrus crown is 3-5 m wide: over such a window a 15 % slope
rises as much as a low skirt hangs (0.4-0.7 m), so slope and skirt cannot be told
apart. What tells them apart is the *local* step: real ground changes height gradually
from cell to cell, a crown's skirt rises out of the ground by its full height at its
edge. So the grid is grown outwards from the ground next to the robot (the lowest
surface with some extent within a few metres: the robot stands on it), accepting a cell
only when its lowest returns continue the ground already accepted next to it within a
slope limit. Everything the growth cannot reach is filled from the ground around it, the way
a crown's ground is the ground around its trunk.

Pure functions on arrays; `fit_terrain` is the recipe. Frame: whatever frame the points
are in (`base` for detection), with z up and the robot's footprint at the origin.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.config import TerrainConfig


@dataclass(frozen=True)
class TerrainGrid:
    """Ground height on a regular grid: cell (i, j) covers x in [x0 + i c, x0 + (i+1) c),
    y likewise; `z` holds the ground height at each cell's centre."""

    x0: float
    y0: float
    cell: float
    z: np.ndarray  # (nx, ny) float64, ground height at cell centres, no NaN
    ground: np.ndarray  # (nx, ny) bool: cells whose own lowest returns are ground
    observed: np.ndarray  # (nx, ny) bool: cells with any return

    fitted = True  # a terrain is always available (the footprint at worst)

    def z_at(self, x, y) -> np.ndarray | float:
        """Ground height at (x, y), bilinear between cell centres (clamped at the edge)."""
        x, y = np.broadcast_arrays(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        out = np.empty(x.shape)
        _bilinear(
            kernel_layout(self.z).ravel(),
            self.z.shape[0],
            self.z.shape[1],
            float(self.x0),
            float(self.y0),
            float(self.cell),
            kernel_layout(x).ravel(),
            kernel_layout(y).ravel(),
            out.reshape(-1),
        )
        return float(out) if out.ndim == 0 else out

    def height(self, xyz: np.ndarray) -> np.ndarray:
        """Height of each point above the terrain under it (m)."""
        return xyz[:, 2] - self.z_at(xyz[:, 0], xyz[:, 1])

    @property
    def ground_cells(self) -> int:
        return int(self.ground.sum())


@kernel
def _bilinear(z, nx, ny, x0, y0, cell, x, y, out):
    """`out[k]`: the (nx, ny) grid `z` (flat) at (x[k], y[k]), bilinear between the cell
    centres and clamped at the edge, with NumPy's steps: the same products in the same
    order. A NaN coordinate gives NaN."""
    for k in range(x.shape[0]):
        fx = (x[k] - x0) / cell - 0.5
        fy = (y[k] - y0) / cell - 0.5
        if np.isnan(fx) or np.isnan(fy):
            out[k] = np.nan
            continue
        # np.clip's max then min (a -0.0 stays as NumPy leaves it)
        fx = fx if fx > 0.0 else 0.0
        fx = fx if fx < nx - 1.0 else nx - 1.0
        fy = fy if fy > 0.0 else 0.0
        fy = fy if fy < ny - 1.0 else ny - 1.0
        i = min(np.int64(fx), nx - 2) if nx > 1 else 0
        j = min(np.int64(fy), ny - 2) if ny > 1 else 0
        tx, ty = fx - i, fy - j
        i1, j1 = min(i + 1, nx - 1), min(j + 1, ny - 1)
        sx, sy = 1 - tx, 1 - ty
        row, row1 = i * ny, i1 * ny
        out[k] = (
            z[row + j] * sx * sy
            + z[row1 + j] * tx * sy
            + z[row + j1] * sx * ty
            + z[row1 + j1] * tx * ty
        )


def fit_terrain(
    xyz: np.ndarray,
    config: TerrainConfig,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    lowest_ring_reach_m: float | None = None,
) -> TerrainGrid:
    """The terrain of one scan's points (N x 3, footprint at the origin, z up) over the
    box x_range x y_range. `lowest_ring_reach_m`: how far from the footprint the LiDAR's
    lowest beam meets level ground (`lowest_ring_reach`), which widens the seed disc for
    a LiDAR mounted high (`seed_radius`); None: `seed_radius_m` as configured."""
    c = config.cell_m
    x0, y0 = x_range[0], y_range[0]
    nx = max(1, math.ceil((x_range[1] - x0) / c))
    ny = max(1, math.ceil((y_range[1] - y0) / c))
    lowest = _lowest_layer(xyz, config, x0, y0, nx, ny)
    observed = np.isfinite(lowest)
    centres_x = x0 + (np.arange(nx) + 0.5) * c
    centres_y = y0 + (np.arange(ny) + 0.5) * c
    distance = np.hypot(centres_x[:, None], centres_y[None, :])

    # Seeds: near the robot, the lowest surface with some extent is the ground (the
    # footprint alone would trust the calibrated mount height; a wrong one, or a robot
    # standing in a furrow, would then seed the ground in mid-air).
    seeds = _seeds(lowest, observed, distance <= seed_radius(config, lowest_ring_reach_m), config)
    ground = _grow(lowest, observed, np.where(seeds, lowest, np.nan), seeds, config)
    ground = _median3(ground)
    accepted = np.isfinite(ground)
    filled = _fill(ground, accepted, c, config.fill_sigma_m)
    return TerrainGrid(x0, y0, c, filled, accepted & observed, observed)


# How far past the lowest beam's landing the seed disc reaches: the next beam up lands
# there too (a VLP-16's -13 deg beam: 1.6 m further out at 2.6 m up, 1 m at 1.6 m up),
# so the disc holds two rings' arcs of ground.
SEED_PAST_LOWEST_RING_M = 2.0


def seed_radius(config: TerrainConfig, lowest_ring_reach_m: float | None) -> float:
    """The radius of the disc the ground is seeded in: `seed_radius_m` (sized for a
    Jackal, whose rings below the horizon land at 1.5-4.6 m), widened for a LiDAR
    mounted higher, whose lowest ring lands farther out: at 1.7 m up a VLP-16's -15 deg
    beam meets level ground 6.3 m away and the disc would hold no ground at all, only
    crowns' skirts, and the ground would be seeded on them, in mid-air."""
    if lowest_ring_reach_m is None:
        return config.seed_radius_m
    return max(config.seed_radius_m, lowest_ring_reach_m + SEED_PAST_LOWEST_RING_M)


def lowest_ring_reach(
    lowest_elevation_rad: float, T_base_lidar: np.ndarray, azimuths: int = 72
) -> float | None:
    """How far from the footprint (horizontally, `base`) a beam at `lowest_elevation_rad`
    in the LiDAR's frame meets the level ground z = 0: the median over `azimuths`
    bearings around the sensor, so that a disc this wide holds at least half of that
    ring's arc (a tilted mount's lowest ring is no circle: pitched down, it lands near
    ahead and far behind; tilted up, ahead it may never come down, counted as infinitely
    far). None where it comes down at fewer than half the bearings, or the LiDAR is not
    above the ground."""
    T = np.asarray(T_base_lidar, dtype=float)
    height = T[2, 3]
    if not height > 0:
        return None
    a = np.linspace(0.0, 2 * np.pi, azimuths, endpoint=False)
    c = math.cos(lowest_elevation_rad)
    rise = np.full(azimuths, math.sin(lowest_elevation_rad))
    down = T[:3, :3] @ np.stack([c * np.cos(a), c * np.sin(a), rise])
    falling = down[2] < -1e-6
    reach = np.full(azimuths, np.inf)
    along = height / -down[2, falling]
    reach[falling] = np.hypot(
        T[0, 3] + along * down[0, falling], T[1, 3] + along * down[1, falling]
    )
    middle = float(np.median(reach))
    return middle if math.isfinite(middle) else None


def _seeds(lowest, observed, near, config: TerrainConfig) -> np.ndarray:
    """Observed cells in the seed disc (`near`, bool) whose lowest layer is within the
    step tolerance of the low tenth of those cells' heights (robust to a few returns from
    below the ground: multipath off a puddle). None near the robot: no seed."""
    near = observed & near
    if near.sum() < config.min_support_cells:
        return np.zeros_like(observed)
    floor = float(np.percentile(lowest[near], 10))
    return near & (lowest <= floor + config.step_tolerance_m)


def _lowest_layer(xyz, config: TerrainConfig, x0, y0, nx, ny) -> np.ndarray:
    """Per cell, the mean height of the returns within `lowest_layer_m` of the cell's
    lowest (the minimum alone sits ~2 sigma of range noise low); NaN where no return."""
    mean = np.empty(nx * ny)
    _lowest_layer_mean(
        kernel_layout(xyz), float(x0), float(y0), float(config.cell_m), nx, ny,
        float(config.lowest_layer_m), mean,
    )  # fmt: skip
    return mean.reshape(nx, ny)


@kernel
def _lowest_layer_mean(xyz, x0, y0, cell, nx, ny, layer_m, mean):
    """`_lowest_layer` into `mean` (nx * ny): each point's cell, the cells' minimum, then
    the layer's sums in point order (as np.bincount adds its weights)."""
    n = xyz.shape[0]
    cell_of = np.full(n, -1, dtype=np.int64)  # -1: outside the grid
    lowest = np.full(nx * ny, np.inf)
    for k in range(n):
        fi = np.floor((xyz[k, 0] - x0) / cell)
        fj = np.floor((xyz[k, 1] - y0) / cell)
        if fi >= 0 and fi < nx and fj >= 0 and fj < ny:  # False for NaN, as NumPy's
            c = np.int64(fi) * ny + np.int64(fj)
            cell_of[k] = c
            z = xyz[k, 2]
            if np.isnan(z) or z < lowest[c]:  # np.minimum: NaN wins
                lowest[c] = z
    total = np.zeros(nx * ny)
    count = np.zeros(nx * ny, dtype=np.int64)
    for k in range(n):
        c = cell_of[k]
        if c >= 0 and xyz[k, 2] <= lowest[c] + layer_m:
            total[c] += xyz[k, 2]
            count[c] += 1
    for c in range(nx * ny):
        mean[c] = total[c] / count[c] if count[c] > 0 else np.nan


def _grow(lowest, observed, ground, accepted, config: TerrainConfig) -> np.ndarray:
    """Accept observed cells outwards from the accepted ones. A cell is ground when its
    lowest layer continues the nearest accepted ground within the slope limit over the
    distance between them; among neighbouring candidates the lowest go first, so a
    skirt is judged against the ground beside it, not against ground beyond a gap."""
    from scipy import ndimage

    if not accepted.any():  # nothing to grow from: no cell is taken
        return np.full(lowest.shape, np.nan)
    c = config.cell_m
    lowest = kernel_layout(lowest)
    ground = np.array(ground, dtype=np.float64, order="C")  # grown in place, as are:
    accepted = np.array(accepted, dtype=bool, order="C")
    pending = observed & ~accepted
    window = max(3, 2 * round(config.support_radius_m / c) + 1)
    gap = np.empty(lowest.shape)
    candidate = np.empty(lowest.shape, dtype=bool)
    for _ in range(4 * max(lowest.shape)):
        # The nearest accepted cell of every cell (scipy's choice among equally near ones).
        nearest = ndimage.distance_transform_edt(
            ~accepted, return_distances=False, return_indices=True
        )
        grew = _grow_once(
            lowest, ground, accepted, pending, nearest, gap, candidate, float(c),
            float(config.step_tolerance_m), float(config.max_slope), float(config.max_gap_m),
            int(config.min_support_cells), window // 2,
        )  # fmt: skip
        if not grew:
            break
    return np.where(accepted, ground, np.nan)


@kernel
def _grow_once(lowest, ground, accepted, pending, nearest, gap, candidate, cell, tolerance,
               max_slope, max_gap, min_support, radius):  # fmt: skip
    """One round of `_grow` over the (nx, ny) grid: the pending cells that continue their
    nearest accepted ground (`nearest`: its indices, as scipy's distance transform gives
    them) are taken, lowest first and in patches across gaps, into `ground`, `accepted`
    and `pending` (in place). Returns whether any was. `gap`, `candidate`: scratch."""
    nx, ny = lowest.shape
    for i in range(nx):
        for j in range(ny):
            candidate[i, j] = False
            if pending[i, j]:
                ni, nj = nearest[0, i, j], nearest[1, i, j]
                di, dj = np.float64(ni - i), np.float64(nj - j)
                gap[i, j] = np.sqrt(di * di + dj * dj) * cell  # distance_transform_edt's
                step = lowest[i, j] - ground[ni, nj]
                allowance = tolerance + max_slope * gap[i, j]
                candidate[i, j] = gap[i, j] <= max_gap and abs(step) <= allowance
    # The lowest first: a candidate more than the tolerance above the lowest candidate
    # within the window waits until that one is ground and it can be compared (a skirt's
    # ring waits for the trunk's foot inside it).
    lowest_first = np.zeros((nx, ny), dtype=np.bool_)
    for i in range(nx):
        for j in range(ny):
            if candidate[i, j]:
                least = np.inf
                for a in range(max(0, i - radius), min(nx, i + radius + 1)):
                    for b in range(max(0, j - radius), min(ny, j + radius + 1)):
                        if candidate[a, b] and lowest[a, b] < least:
                            least = lowest[a, b]
                lowest_first[i, j] = lowest[i, j] <= least + tolerance
    # Across a gap in the rings' coverage, ground comes as a patch (a ring's arc): a lone
    # low cell out there is a trunk or a post seen by a level ring.
    grew = False
    for i in range(nx):
        for j in range(ny):
            if not lowest_first[i, j]:
                continue
            if gap[i, j] > 2 * cell:
                others = -1  # the cell itself is in its window
                for a in range(max(0, i - radius), min(nx, i + radius + 1)):
                    for b in range(max(0, j - radius), min(ny, j + radius + 1)):
                        others += lowest_first[a, b]
                if others < min_support:
                    continue
            ground[i, j] = lowest[i, j]
            accepted[i, j] = True
            pending[i, j] = False
            grew = True
    return grew


def _median3(ground: np.ndarray) -> np.ndarray:
    """Each ground cell as the median of the ground cells in its 3 x 3 neighbourhood: a
    trunk's or a post's foot in a cell without soil returns sits a few cm up; a median
    drops such a one-cell bump and keeps slopes and furrows (NaN: not ground)."""
    out = np.empty(ground.shape)
    _median3_cells(kernel_layout(ground), out)
    return out


@kernel
def _median3_cells(ground, out):
    """`_median3` into `out`: per finite cell, its neighbourhood's values but NaN sorted
    (insertion: nine at most) and the lower median of the finite ones taken, as NumPy's
    sort (NaN last) and take did it."""
    nx, ny = ground.shape
    ordered = np.empty(9)
    for i in range(nx):
        for j in range(ny):
            out[i, j] = np.nan
            if not np.isfinite(ground[i, j]):
                continue
            size = 0
            finite = 0
            for a in range(max(0, i - 1), min(nx, i + 2)):
                for b in range(max(0, j - 1), min(ny, j + 2)):
                    value = ground[a, b]
                    if np.isnan(value):
                        continue
                    finite += np.isfinite(value)
                    k = size
                    while k > 0 and ordered[k - 1] > value:
                        ordered[k] = ordered[k - 1]
                        k -= 1
                    ordered[k] = value
                    size += 1
            out[i, j] = ordered[(finite - 1) // 2]


@functools.lru_cache(maxsize=32)
def _gaussian_weights(sigma: float, truncate: float) -> np.ndarray:
    """The weights scipy.ndimage.gaussian_filter1d correlates with, read off its response
    to an impulse (each output one weight times one plus zeros: the weights exactly),
    once per width: the fill's widths are the same every scan."""
    from scipy import ndimage

    radius = int(truncate * float(sigma) + 0.5)
    impulse = np.zeros(2 * radius + 1)
    impulse[radius] = 1.0
    weights = ndimage.gaussian_filter1d(impulse, sigma, mode="constant", truncate=truncate)
    weights = weights[::-1].copy()
    assert np.array_equal(weights, weights[::-1])  # `_correlate_twice` sums pairs
    weights.flags.writeable = False
    return weights


def _gaussian(
    values: np.ndarray, weights: np.ndarray, wanted: np.ndarray | None = None
) -> np.ndarray:
    """scipy.ndimage.gaussian_filter(values, sigma, mode="constant") with `weights` from
    `_gaussian_weights`: its two correlations, along the first axis and then along the
    second, compiled (`_correlate_twice`). Only at the `wanted` cells (all when None):
    NaN elsewhere."""
    values = kernel_layout(values)
    if wanted is None:
        wanted = np.ones(values.shape, dtype=bool)
    out = np.full(values.shape, np.nan)
    _correlate_twice(values, weights, np.ascontiguousarray(wanted), np.empty(values.shape), out)
    return out


@kernel
def _correlate_twice(values, weights, wanted, along, out):
    """`values` correlated with the symmetric `weights` along axis 0 (into `along`, the
    rows with a wanted cell), then along axis 1 (into `out`, the wanted cells), zeros
    beyond the edges, each sum as scipy's correlate1d makes it: the centre's product,
    then each pair at equal distance summed and weighted, the farthest first. Pairs
    wholly beyond the grid add +0.0, and once is as many times: they are skipped but
    one. The lines are padded with zeros: no bounds to check in the loops over pairs."""
    nx, ny = values.shape
    r = weights.shape[0] // 2
    reach = min(r, nx - 1)
    padded = np.zeros((nx + 2 * reach, ny))
    padded[reach : reach + nx] = values
    for i in range(nx):
        if not wanted[i].any():
            continue
        row = along[i]
        for j in range(ny):
            row[j] = values[i, j] * weights[r]
        if r > reach:
            row += 0.0
        for k in range(reach, 0, -1):
            low, high, weight = padded[reach + i - k], padded[reach + i + k], weights[r - k]
            for j in range(ny):
                row[j] += (low[j] + high[j]) * weight
    reach = min(r, ny - 1)
    line = np.zeros(ny + 2 * reach)
    for i in range(nx):
        if not wanted[i].any():
            continue
        line[reach : reach + ny] = along[i]
        for j in range(ny):
            if not wanted[i, j]:
                continue
            total = along[i, j] * weights[r]
            if r > reach:
                total += 0.0
            for k in range(reach, 0, -1):
                total += (line[reach + j - k] + line[reach + j + k]) * weights[r - k]
            out[i, j] = total


def _fill(ground: np.ndarray, accepted: np.ndarray, cell: float, sigma_m: float) -> np.ndarray:
    """Ground under objects and in shadows: a Gaussian-weighted mean of the accepted
    ground around (normalised convolution), widening until every cell has some."""

    known = accepted & np.isfinite(ground)
    values = np.where(known, ground, 0.0)
    out = np.where(known, ground, np.nan)
    sigma = sigma_m / cell
    while np.isnan(out).any():
        weights = _gaussian_weights(sigma, 3.0)
        missing = np.isnan(out)  # the only cells whose means are wanted
        total = _gaussian(values, weights, missing)
        weight = _gaussian(known.astype(float), weights, missing)
        fill = missing & (weight > 1e-6)
        out[fill] = total[fill] / weight[fill]
        if sigma > max(ground.shape):
            out[np.isnan(out)] = 0.0  # nothing known at all: the footprint's plane
        sigma *= 2
    return out


@warm_up
def compile_kernels() -> None:
    """The terrain's kernels compiled for the types a scan gives them, by fitting a
    terrain to made-up points (one a cell of a 2 x 2 m box, a strip beside it empty: it is
    filled) and reading heights off it."""
    centres = np.arange(-0.75, 1.0, 0.5)
    x, y = np.meshgrid(centres, centres)
    xyz = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, -0.4)])
    fit_terrain(xyz, TerrainConfig(), (-1.0, 1.5), (-1.0, 1.0)).height(xyz)
