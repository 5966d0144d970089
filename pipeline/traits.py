"""Tree width and height, two ways on the same clusters.

`paper` (the paper, Sec. III-C): height by the top-ring rule, width by 10 z-slices and
the farthest pair in each, both "keep the maximum" over scans.

`robust` (ours): each tree's returns accumulated in the world frame over scans on a
bounded voxel grid, counting the scans that hit each cell; width and height are measured
on the cells seen in several scans. A stray return (mixed pixel, dust, a leaf blown out)
moves a maximum for good but is seen once; the accumulated cloud joins the views of
every side the robot passed, where one scan sees only its near half; a piece of a
neighbour's crown is cut off by the mapper (Voronoi cut between tracked objects) before
it is added (and before the paper's width and height are measured). Percentiles were
tried first and cut real crown: the crown outline is sampled thinly (grazing rays), so
its last percent is real (docs/pipeline.md).

The definitions match `sim.orchard.measure_truth`: height = top of the tree above the
ground at the tree, width = the largest horizontal distance between two of its points.
"""

from __future__ import annotations

import math

import numpy as np

from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.config import TraitsConfig

# Bearings for the per-slice upper bound: a set's true diameter D is at most its largest
# extent over K bearings divided by cos(pi / 2K).
_BEARINGS = 16
_ANGLES = np.arange(_BEARINGS) * math.pi / _BEARINGS
_DIRECTIONS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)])
_BOUND = 1.0 / math.cos(math.pi / (2 * _BEARINGS))


def slice_width(points: np.ndarray, slices: int = 10, floor: float = 0.0) -> float:
    """The paper's width of one cluster: cut it into `slices` equal z-slices, take the
    farthest pair of points in each (3D distance), return the largest; or `floor` when
    no slice is wider than that (a kept maximum: such slices are not measured).

    The farthest pair of a slice is found among the vertices of its x-y convex hull (a
    slice is a tenth of the tree: the pair's height difference changes the distance by
    at most slice_height^2 / (2 width), ~1 cm on a citrus crown, and it is included).
    Slices are visited widest bound first and skipped once their bound (the extent over
    16 bearings, scaled up to the worst case, with the slice height) cannot win: once a
    tree's width is known, nine calls in ten measure no slice at all, so the bounds are
    worked out in one compiled pass (`_slice_bounds`)."""
    import cv2

    if len(points) < 2:
        return floor
    bound, filled, index = _slice_bounds(kernel_layout(points), slices, _DIRECTIONS, _BOUND)
    best = floor * floor
    for k in np.argsort(-bound, kind="stable"):
        if bound[k] ** 2 <= best:
            break
        members = points[index == filled[k]]  # in row order, as the hull was always given
        xy = np.ascontiguousarray(members[:, :2], dtype=np.float32)
        vertices = members[cv2.convexHull(xy, returnPoints=False).ravel()]
        gaps = vertices[:, None, :] - vertices[None, :, :]
        best = max(best, float(np.einsum("ijk,ijk->ij", gaps, gaps).max()))
    return math.sqrt(best) if len(filled) else floor


@kernel
def _slice_bounds(
    points: np.ndarray, slices: int, directions: np.ndarray, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For `slice_width`: each point's slice (`slices` equal z-slices, the top one
    closed), the slices of two points or more in increasing order and a bound on each
    one's width: the largest extent over `directions`' bearings times `scale`, with the
    slice height. A slice's extent also takes in the lone points of the slices up to the
    next one measured: the bound can only grow, it stays a bound."""
    n, bearings = points.shape[0], directions.shape[1]
    low = high = points[0, 2]
    for i in range(1, n):
        low = min(low, points[i, 2])
        high = max(high, points[i, 2])
    span = max(high - low, 1e-9)
    step = slices / span
    index = np.empty(n, dtype=np.int64)
    counts = np.zeros(slices, dtype=np.int64)
    top = np.full((slices, bearings), -np.inf)
    bottom = np.full((slices, bearings), np.inf)
    for i in range(n):
        # Clamped both ways: a NaN height (none reaches here) must not index outside.
        k = max(min(np.int64((points[i, 2] - low) * step), slices - 1), 0)
        index[i] = k
        counts[k] += 1
        for b in range(bearings):
            along = points[i, 0] * directions[0, b] + points[i, 1] * directions[1, b]
            top[k, b] = max(top[k, b], along)
            bottom[k, b] = min(bottom[k, b], along)
    filled = np.flatnonzero(counts >= 2)
    bound = np.empty(len(filled))
    height_sq = (span / slices) ** 2
    for f in range(len(filled)):
        last = filled[f + 1] if f + 1 < len(filled) else slices
        extent = 0.0
        for b in range(bearings):
            high_b, low_b = top[filled[f], b], bottom[filled[f], b]
            for k in range(filled[f] + 1, last):
                high_b = max(high_b, top[k, b])
                low_b = min(low_b, bottom[k, b])
            extent = max(extent, high_b - low_b)
        bound[f] = np.sqrt((extent * scale) ** 2 + height_sq)
    return bound, filled, index


class PaperTraits:
    """Per tree: the top ring so far, and the largest height and width registered.

    The position is not one of the paper's traits: the paper reports the Kalman state, the
    centroid of the returns, which lies on the side the robot sees (half a crown radius,
    0.7 m on the twin, from the trunk when passed on one side). The centre reported here
    is the accumulated outline's, as the robust traits measure it."""

    method = "paper"

    def __init__(self, config: TraitsConfig):
        self.config = config
        self.top_ring: int | None = None
        self.height = float("nan")
        # The largest per-scan widths, at most `width_confirm_scans`, largest first.
        self._widths: list[float] = []
        self._outline = RobustTraits(config)

    @property
    def width(self) -> float:
        """The largest width that `width_confirm_scans` scans reached (with fewer scans
        measured, the smallest of them: the best there is); NaN before any."""
        return self._widths[-1] if self._widths else float("nan")

    def observe(
        self,
        points_base,
        ring,
        ground_z_base,
        points_world=None,
        ground_world=None,
        pose_sigma: float | None = None,
    ):
        """One cluster of this tree (points in `base`, ground height under it in `base`;
        and in the world frame for the outline, when the mapper has a steady pose, whose
        position sigma is `pose_sigma`)."""
        if len(points_base) == 0:
            return
        self._outline.observe(
            points_base, ring, ground_z_base, points_world, ground_world, pose_sigma
        )
        # Height: when the ring of the topmost return changes (and on the first sight),
        # register the top's height above the ground; keep the largest.
        top = int(np.argmax(points_base[:, 2]))
        if self.top_ring is None or int(ring[top]) != self.top_ring:
            self.top_ring = int(ring[top])
            self.height = _max(self.height, float(points_base[top, 2] - ground_z_base))
        # Width: the widest slice of this cluster; keep the largest few over scans (slices
        # that cannot enter them are not measured).
        full = len(self._widths) >= self.config.width_confirm_scans
        floor = self._widths[-1] if full else 0.0
        width = slice_width(points_base, self.config.slices, floor)
        if width > floor or not full:
            self._keep_widths([width])

    def absorb(self, other: PaperTraits) -> None:
        """Another track of the same tree merged into this one."""
        self.height = _max(self.height, other.height)
        self._keep_widths(other._widths)
        self._outline.absorb(other._outline)

    def _keep_widths(self, widths: list[float]) -> None:
        kept = sorted(self._widths + widths, reverse=True)
        self._widths = kept[: self.config.width_confirm_scans]

    def centre(self) -> np.ndarray | None:
        return self._outline.centre()


def _max(a: float, b: float) -> float:
    return b if math.isnan(a) else max(a, b)


class RobustTraits:
    """Per tree: its returns in the world frame on a `voxel_m` grid, each cell with the
    first return that fell in it and the number of scans that hit it; and the ground
    height under the tree from every scan (the median is used).

    Only cells hit in at least `min_hits` scans count: a leaf surface is hit again and
    again as the robot passes, a stray return (a mixed pixel at a crown edge, dust, a
    leaf blown out for a moment) once. Width is then the largest horizontal extent of
    the counted cells, height the top one above the ground. Memory is bounded: past
    `max_points` cells the grid coarsens (cell x 2, hits summed).

    Cells are only as well placed as the poses that placed them: returns placed under an
    RTK float solution sit its error (decimetres) off those placed once it is fixed, and
    an outline holding both is that much wider, its centre between. So when a scan comes
    with a pose sigma under half the worst one the outline was placed with (and that worst
    more than a cell), a finer outline starts beside it, fed only such scans; once it has
    half as many counted cells as the outline, it replaces it (`_finer`). A tree not seen
    long enough after the pose got better keeps the outline it has."""

    method = "robust"

    def __init__(self, config: TraitsConfig):
        self.config = config
        self.voxel = config.voxel_m
        self._keys = np.zeros(0, dtype=np.int64)
        self._hits = np.zeros(0, dtype=np.int64)
        self._points = np.zeros((0, 3))
        self._pending: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending_count = 0
        self._ground: list[float] = []
        self._cache: tuple[float, float, np.ndarray] | None = None
        # The centre alone is asked every scan (the outline merge): the x-y extent of the
        # counted cells (hit in min_hits scans) is kept as cells reach min_hits (a cell's
        # return never changes and its hits only grow), and found again after coarsening.
        self._seen_count = 0
        self._seen_lo = np.full(2, np.inf)
        self._seen_hi = np.full(2, -np.inf)
        # The largest pose sigma (m) the cells were placed with, and the finer outline
        # placed only under poses better than half of it (class doc).
        self._placed_sigma = 0.0
        self._finer: RobustTraits | None = None
        # The top of the outlines a finer one replaced (world z): a pose's error is
        # horizontal, so the heights they saw stand (the top was seen from afar, often
        # before the pose got better).
        self._replaced_top = -np.inf

    def observe(
        self,
        points_base,
        ring,
        ground_z_base,
        points_world=None,
        ground_world=None,
        pose_sigma: float | None = None,
    ):
        """One cluster of this tree: its returns in the world frame (already cut to this
        tree where a neighbour is near), the ground height under it (world z) and the
        position sigma of the pose that placed them (None: not known)."""
        if points_world is None or len(points_world) == 0:
            return
        if ground_world is not None and math.isfinite(ground_world):
            self._ground.append(float(ground_world))
            if len(self._ground) > 400:  # a bounded, recent sample of the ground
                self._ground = self._ground[-200:]
        self._cache = None
        if pose_sigma is not None and self._refine(
            points_base, ring, ground_z_base, points_world, ground_world, pose_sigma
        ):
            return  # the finer outline, this scan in it, is the outline now
        # One hit per cell per scan: the cells in key order, each with its first return.
        keys, first = _scan_cells(kernel_layout(points_world), float(self.voxel))
        self._pending.append((keys, first))
        self._pending_count += len(keys)
        # Fold pending cells in once they outnumber the grid: amortised O(n log n).
        if self._pending_count > max(len(self._keys), 5000):
            self._consolidate()

    def _refine(self, points_base, ring, ground_z_base, points_world, ground_world, sigma) -> bool:
        """Feed, start or adopt the finer outline for a scan placed with `sigma`; True when
        the finer outline, with this scan, replaced this one."""
        better = self._placed_sigma > self.config.voxel_m and sigma < self._placed_sigma / 2
        if better:
            if self._finer is None:
                self._finer = RobustTraits(self.config)
            self._finer.observe(points_base, ring, ground_z_base, points_world, ground_world, sigma)
            self._consolidate()
            self._finer._consolidate()
            if 2 * self._finer._seen_count >= max(self._seen_count, 2):
                self._adopt(self._finer)
                return True
        self._placed_sigma = max(self._placed_sigma, sigma)
        return False

    def _adopt(self, finer: RobustTraits) -> None:
        """The finer outline's cells replace these; the ground and the top stay (this
        outline saw the same scans since the finer one started, and those before)."""
        seen = self._seen()
        if len(seen):
            self._replaced_top = max(self._replaced_top, float(seen[:, 2].max()))
        for name in (
            "voxel", "_keys", "_hits", "_points", "_pending", "_pending_count",
            "_seen_count", "_seen_lo", "_seen_hi", "_placed_sigma", "_finer",
        ):  # fmt: skip
            setattr(self, name, getattr(finer, name))
        self._cache = None

    def absorb(self, other: RobustTraits) -> None:
        """Another track of the same tree merged into this one (a finer outline either had
        starts again with the next well placed scan)."""
        self._placed_sigma = max(self._placed_sigma, other._placed_sigma)
        self._replaced_top = max(self._replaced_top, other._replaced_top)
        self._finer = None
        other._consolidate()
        points, hits = other.cells()
        keys = _voxel_keys(points, self.voxel)
        # Its cells with their hits: the same cell in both sums its scans.
        self._pending.append((np.repeat(keys, hits), np.repeat(points, hits, axis=0)))
        self._pending_count += int(hits.sum())
        self._ground.extend(other._ground)
        self._cache = None
        self._consolidate()

    def cells(self) -> tuple[np.ndarray, np.ndarray]:
        """(first return of each cell, scans that hit it)."""
        self._consolidate()
        return self._points, self._hits

    def _consolidate(self) -> None:
        if not self._pending:
            return
        # The pending cells among themselves first (a scan's few hundred), then merged into
        # the sorted grid: a cell already there keeps its first return and adds the hits,
        # a new one is inserted in key order. The same cells, returns and hits as one
        # np.unique over the grid and the pending cells together, without sorting the
        # whole grid again at every scan (the outline's centre is asked every scan).
        keys, points, hits = _pending_cells(self._pending, self._pending_count)
        self._pending, self._pending_count = [], 0
        # One pass of a sorted merge (a kernel): what searchsorted, np.insert and the
        # masks of the cells reaching min_hits took a dozen NumPy calls for.
        keys, points, hits, reached = _merged_cells(
            kernel_layout(self._keys, np.int64),
            kernel_layout(self._points),
            kernel_layout(self._hits, np.int64),
            kernel_layout(keys, np.int64),
            kernel_layout(points),
            kernel_layout(hits, np.int64),
            self.config.min_hits,
        )
        need = self.config.min_hits
        coarsened = len(keys) > self.config.max_points
        while len(keys) > self.config.max_points:
            self.voxel *= 2.0
            keys, points, hits = _unique_cells(_voxel_keys(points, self.voxel), points, hits)
        self._keys, self._hits, self._points = keys, hits, points
        if coarsened:  # other cells, other returns: the extent found again
            self._seen_count, self._seen_lo, self._seen_hi = (
                0,
                np.full(2, np.inf),
                np.full(2, -np.inf),
            )
            reached = points.compress(hits >= need, axis=0)
        if len(reached):
            self._seen_count += len(reached)
            self._seen_lo = np.minimum(self._seen_lo, reached[:, :2].min(axis=0))
            self._seen_hi = np.maximum(self._seen_hi, reached[:, :2].max(axis=0))

    def _seen(self) -> np.ndarray:
        """The cells hit in at least `min_hits` scans (their first returns)."""
        points, hits = self.cells()
        return points.compress(hits >= self.config.min_hits, axis=0)

    def _measure(self) -> tuple[float, float, np.ndarray]:
        if self._cache is None:
            seen = self._seen()
            if len(seen) < 2:
                self._cache = (float("nan"), float("nan"), np.full(2, np.nan))
            else:
                ground = float(np.median(self._ground)) if self._ground else 0.0
                height = float(max(seen[:, 2].max(), self._replaced_top) - ground)
                width, centre = caliper(seen[:, :2], self.config.directions)
                self._cache = (width, height, centre)
        return self._cache

    @property
    def width(self) -> float:
        return self._measure()[0]

    @property
    def height(self) -> float:
        return self._measure()[1]

    def centre(self) -> np.ndarray | None:
        self._consolidate()
        if self._seen_count < 2:
            return None
        # caliper's centre: the same minima and maxima of the same cells, the same sum
        return (self._seen_lo + self._seen_hi) / 2


def caliper(xy: np.ndarray, directions: int) -> tuple[float, np.ndarray]:
    """Largest horizontal extent of the points over `directions` bearings in [0, pi), and
    the centre of their extents along x and y."""
    angles = np.arange(directions) * math.pi / directions
    projected = xy @ np.stack([np.cos(angles), np.sin(angles)])
    extents = projected.max(axis=0) - projected.min(axis=0)
    return float(extents.max()), (xy.min(axis=0) + xy.max(axis=0)) / 2


def _pending_cells(pending: list[tuple[np.ndarray, np.ndarray]], count: int):
    """The pending cells as `_unique_cells` makes them. One scan's cells alone (the usual
    case: the outline's centre is asked every scan) are distinct and in key order
    already, so np.unique would return them as they are, each with one hit."""
    if len(pending) == 1 and _increasing(pending[0][0]):
        keys, points = pending[0]
        return keys, points, np.ones(count, dtype=np.int64)
    return _unique_cells(
        np.concatenate([k for k, _ in pending]),
        np.vstack([p for _, p in pending]),
        np.ones(count, dtype=np.int64),
    )


def _increasing(keys: np.ndarray) -> bool:
    return len(keys) < 2 or bool((keys[1:] > keys[:-1]).all())


def _unique_cells(keys: np.ndarray, points: np.ndarray, hits: np.ndarray):
    """Cells in key order: each key's first point in arrival order (deterministic) and
    its hits summed."""
    unique, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    hits = np.bincount(inverse.ravel(), weights=hits).astype(np.int64)
    return unique, points.take(first, axis=0), hits


def _voxel_keys(xyz: np.ndarray, size: float) -> np.ndarray:
    scaled = xyz / size
    np.floor(scaled, out=scaled)  # in place, as the addition below: no temporaries
    cells = scaled.astype(np.int64)
    cells += 1 << 20
    return (cells[:, 0] << 42) | (cells[:, 1] << 21) | cells[:, 2]


@kernel
def _scan_cells(xyz: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """np.unique(_voxel_keys(xyz, size), return_index=True) and the rows it picks: the
    distinct cell keys in increasing order, each with the first of `xyz`'s rows in it.
    The keys by `_voxel_keys`' steps; a stable sort keeps each key's first row first."""
    n = xyz.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        key = np.int64(0)
        for c in range(3):
            cell = np.int64(np.floor(xyz[i, c] / size)) + np.int64(1 << 20)
            key |= cell << np.int64(21 * (2 - c))
        keys[i] = key
    order = np.argsort(keys, kind="mergesort")
    distinct = 0
    for k in range(n):
        if k == 0 or keys[order[k]] != keys[order[k - 1]]:
            order[distinct] = order[k]
            distinct += 1
    unique = np.empty(distinct, dtype=np.int64)
    rows = np.empty((distinct, 3))
    for k in range(distinct):
        unique[k] = keys[order[k]]
        rows[k] = xyz[order[k]]
    return unique, rows


@kernel
def _merged_cells(grid_keys, grid_points, grid_hits, keys, points, hits, need):
    """A grid of cells (keys increasing) and new cells (keys increasing, distinct) merged
    in key order: a key in both keeps the grid's return and sums the hits, a new key is
    inserted. Also the returns of the cells this brings to `need` hits: the grid's that
    cross it (grid order), then the new ones at it (their order)."""
    size = grid_keys.shape[0] + keys.shape[0]
    out_keys = np.empty(size, dtype=np.int64)
    out_hits = np.empty(size, dtype=np.int64)
    out_points = np.empty((size, 3))
    crossed = np.empty(keys.shape[0], dtype=np.int64)  # rows of the grid
    fresh = np.empty(keys.shape[0], dtype=np.int64)  # rows of the new cells
    n_crossed = n_fresh = 0
    g = o = 0
    for k in range(keys.shape[0]):
        while g < grid_keys.shape[0] and grid_keys[g] < keys[k]:
            out_keys[o], out_hits[o], out_points[o] = grid_keys[g], grid_hits[g], grid_points[g]
            g += 1
            o += 1
        if g < grid_keys.shape[0] and grid_keys[g] == keys[k]:
            after = grid_hits[g] + hits[k]
            if grid_hits[g] < need and after >= need:
                crossed[n_crossed] = g
                n_crossed += 1
            out_keys[o], out_hits[o], out_points[o] = grid_keys[g], after, grid_points[g]
            g += 1
        else:
            if hits[k] >= need:
                fresh[n_fresh] = k
                n_fresh += 1
            out_keys[o], out_hits[o], out_points[o] = keys[k], hits[k], points[k]
        o += 1
    while g < grid_keys.shape[0]:
        out_keys[o], out_hits[o], out_points[o] = grid_keys[g], grid_hits[g], grid_points[g]
        g += 1
        o += 1
    reached = np.empty((n_crossed + n_fresh, 3))
    for r in range(n_crossed):
        reached[r] = grid_points[crossed[r]]
    for r in range(n_fresh):
        reached[n_crossed + r] = points[fresh[r]]
    # Copies: the grid is kept, the rows of the keys both had are not.
    return out_keys[:o].copy(), out_points[:o].copy(), out_hits[:o].copy(), reached


@warm_up
def compile_kernels() -> None:
    """The traits' kernels compiled for what a scan gives them: a cluster's returns
    (float64 rows), and the cells merged into the outline's grid."""
    xyz = np.array([[0.1, 0.2, 0.3], [0.15, 0.2, 0.3], [1.0, -1.0, 2.0]])
    keys, points = _scan_cells(xyz, 0.1)
    _slice_bounds(xyz, 10, _DIRECTIONS, _BOUND)
    _merged_cells(
        keys[:1],
        points[:1],
        np.ones(1, dtype=np.int64),
        keys,
        points,
        np.ones(len(keys), dtype=np.int64),
        2,
    )


def new_traits(config: TraitsConfig) -> PaperTraits | RobustTraits:
    return PaperTraits(config) if config.method == "paper" else RobustTraits(config)
