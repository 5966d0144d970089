"""Posts, poles and people standing beside or between crowns: found in one scan and cut
out before the crowns are clustered, so they can neither join a crown nor bridge two.

A trellis post 0.5 m from a crown's edge, or a worker standing in the gap between two
trees, is closer to the crowns than the clustering's reach (0.5 m, which must bridge
the ring gaps of a far crown): without this cut the post widens the tree by a metre,
and the person joins two trees into one cluster that no trunk cut can part (the legs
are a trunk-sized blob between the two trunks).

A stem is a smooth vertical column standing clear: a blob of returns in the trunk band
(as a trunk is; or, where a weed clump hides its foot, in a band as deep just above the
understorey, `detection.stem_seed_band`), over which returns stand without a gap, within
a person's half-width of its axis, up to at least `min_stem_height_m` (or the top of the
LiDAR's view), are smooth along the rings (`classify.roughness`: clothes, wood, concrete
and steel are smooth, foliage is not) and have little around them. A tree's trunk passes
the first test and fails the others: above a citrus trunk (0.35-0.6 m, where the skirt
starts) the column holds either nothing (the crown's surface is farther out than a
person's half-width) or foliage (a young tree's crown, its apex), which is rough, and
the crown is around it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.classify import roughness
from treetraits.pipeline.clustering import stable_order
from treetraits.pipeline.config import ClassifyConfig, ClusterConfig
from treetraits.pipeline.medians import median

# The VLP-16's rings are 2 deg apart: on an upright surface at range r they land
# r tan(2 deg) apart in height. A column is continuous while its next return up is no
# farther than this many ring gaps (a dropped return, the body's narrower neck), plus
# the voxel's size.
_RING_GAP_RAD = math.radians(2.0)
_MISSED_RINGS = 1.5


@dataclass(frozen=True)
class Stem:
    """One post, pole or person in a scan (`base`)."""

    centre: np.ndarray  # (2,) x-y of its band blob
    top_m: float  # the column's continuous top above the terrain
    roughness: float  # m, of the column's returns above the trunk band


def find_stems(
    xyz: np.ndarray,
    height: np.ndarray,
    ring: np.ndarray,
    lidar_xyz: np.ndarray,
    blob_centres: np.ndarray,
    band_top: float,
    config: ClusterConfig,
    classify: ClassifyConfig,
) -> list[Stem]:
    """The stems among the blobs (`blob_centres`, K x 2) of a band whose top is
    `band_top` above the terrain (the trunk band, or the seed band above the
    understorey). `xyz` the scan's returns clear of the ground (`base`), `height` above
    the terrain, `ring` each one's; `lidar_xyz` the LiDAR's origin (`base`)."""
    search = StemSearch(xyz, height, ring, lidar_xyz, config)
    return search.find(blob_centres, band_top, classify)


class StemSearch:
    """`find_stems` over one scan's returns for several bands: what depends on the
    returns alone (the top ring's slope, the cells) is worked out once, when first needed."""

    def __init__(
        self,
        xyz: np.ndarray,
        height: np.ndarray,
        ring: np.ndarray,
        lidar_xyz: np.ndarray,
        config: ClusterConfig,
    ):
        self.xyz, self.height, self.ring, self.lidar_xyz = xyz, height, ring, lidar_xyz
        self.config = config

    @cached_property
    def top_slope(self) -> float:
        """The highest ring's elevation (+15 deg on a VLP-16, +10 on a Puck Hi-Res): a
        column near the robot runs out of the field of view before it reaches its top."""
        x, y, z = (float(v) for v in self.lidar_xyz)
        return _top_slope(kernel_layout(self.xyz), x, y, z)

    @cached_property
    def cells(self) -> _Cells:
        return _Cells(self.xyz[:, :2], self.config.stem_clearance_m)

    def find(
        self, blob_centres: np.ndarray, band_top: float, classify: ClassifyConfig
    ) -> list[Stem]:
        """`find_stems` for these blobs and this band."""
        stems: list[Stem] = []
        if len(self.xyz) == 0 or len(blob_centres) == 0:
            return stems
        for centre in blob_centres:
            # Only the returns within the clearance can be in the column or around it:
            # those of the cells around the centre, in their order in the scan.
            mine = self.cells.around(centre)
            found = _stem_at(
                centre,
                self.xyz[mine],
                self.height[mine],
                self.ring[mine],
                self.lidar_xyz,
                self.top_slope,
                band_top,
                self.config,
                classify,
            )
            if found is not None:
                stems.append(found)
        return stems


def _stem_at(
    centre: np.ndarray,
    xyz: np.ndarray,
    height: np.ndarray,
    ring: np.ndarray,
    lidar_xyz: np.ndarray,
    top_slope: float,
    band_top: float,
    config: ClusterConfig,
    classify: ClassifyConfig,
) -> Stem | None:
    """The stem over one blob's centre, or None; `xyz` holds at least every return
    within `stem_clearance_m` of it (x-y)."""
    gap = np.hypot(xyz[:, 0] - centre[0], xyz[:, 1] - centre[1])
    near = gap <= config.stem_radius_m
    above = near & (height > band_top)
    if not above.any():
        return None
    lidar_xy = lidar_xyz[:2]
    reach = float(np.hypot(*(centre - lidar_xy)))
    top = column_top(height[above], band_top, max_gap_m(reach, config.voxel_m))
    # What the sensor can see of a column here: up to its highest ring, less a ring
    # gap (a post's top ring can fall beside it).
    terrain_z = median(xyz[above, 2] - height[above])
    in_view = lidar_xyz[2] - terrain_z + reach * (top_slope - math.tan(_RING_GAP_RAD))
    needed = min(config.min_stem_height_m, in_view)
    # A column cut short by the field of view below a tree's least height proves
    # nothing: a weed, a trunk and a person look alike that low.
    if needed < classify.min_height_m or top < needed:
        return None
    # Judged above the skirts: there a tree's column is foliage, a post's still wood.
    column = above & (height <= top) & (height >= config.stem_judged_from_m)
    # Standing clear: a trunk's column is inside its crown and a weed under a skirt
    # has the crown's side around it, where a post or a person has air.
    around = (gap > config.stem_radius_m) & (gap <= config.stem_clearance_m)
    around &= (height >= config.stem_judged_from_m) & (height <= top)
    if around.sum() > config.max_stem_surround_share * column.sum():
        return None
    rough = roughness(xyz[column], ring[column], lidar_xy)
    # Too few returns along the rings to say (NaN): not cut, a tree keeps its trunk.
    if math.isfinite(rough) and rough < classify.min_roughness_m:
        return Stem(np.asarray(centre, dtype=float), top, rough)
    return None


class _Cells:
    """A scan's returns binned on a coarse x-y grid, to gather those near a spot without
    a pass over all of them per spot (a scan has tens of blobs and ~20k returns)."""

    def __init__(self, xy: np.ndarray, reach: float):
        # Cells a little wider than the reach: a return within it of a spot is in the
        # spot's cell or the next one in each direction, whatever the rounding.
        self.size = reach + 0.05
        # Column by column: NumPy reduces an N x 2 array over its rows several times slower.
        self.origin = np.array([xy[:, 0].min(), xy[:, 1].min()])
        ij = np.floor((xy - self.origin) / self.size).astype(np.int64)
        self.shape = np.array([ij[:, 0].max(), ij[:, 1].max()]) + 1
        cell = ij[:, 0] * self.shape[1] + ij[:, 1]
        self.order = stable_order(cell)
        self.sorted_cells = cell[self.order]

    def around(self, spot: np.ndarray) -> np.ndarray:
        """Indices (increasing) of the returns in the 3 x 3 cells around `spot`: every
        return within `reach` of it, and some farther."""
        return _around(
            float(spot[0]) - float(self.origin[0]),
            float(spot[1]) - float(self.origin[1]),
            self.size,
            int(self.shape[0]),
            int(self.shape[1]),
            self.sorted_cells,
            self.order,
        )


@kernel
def _around(
    dx: float,
    dy: float,
    size: float,
    rows: int,
    cols: int,
    sorted_cells: np.ndarray,
    order: np.ndarray,
) -> np.ndarray:
    """`_Cells.around` of a spot `dx`, `dy` from the grid's origin: each row's run of
    the 3 cells in `sorted_cells`, their returns' indices gathered and sorted."""
    i, j = np.int64(np.floor(dx / size)), np.int64(np.floor(dy / size))
    j_low, j_high = max(j - 1, 0), min(j + 1, cols - 1)
    row_low, row_high = max(i - 1, 0), min(i + 1, rows - 1)
    if j_low > j_high or row_low > row_high:
        return np.zeros(0, dtype=np.int64)
    runs = np.empty((row_high - row_low + 1, 2), dtype=np.int64)
    total = 0
    for r in range(len(runs)):
        row = (row_low + r) * cols
        runs[r, 0] = np.searchsorted(sorted_cells, row + j_low)
        runs[r, 1] = np.searchsorted(sorted_cells, row + j_high + 1)
        total += runs[r, 1] - runs[r, 0]
    found = np.empty(total, dtype=np.int64)
    at = 0
    for r in range(len(runs)):
        for k in range(runs[r, 0], runs[r, 1]):
            found[at] = order[k]
            at += 1
    return np.sort(found)  # distinct indices: any sort gives this order


@kernel
def _top_slope(xyz: np.ndarray, lidar_x: float, lidar_y: float, lidar_z: float) -> float:
    """`StemSearch.top_slope` in one pass: each return's height over its reach (no less
    than 0.1 m) from the LiDAR, the largest; NaN if any is (as np.max gives it)."""
    top = -np.inf
    for k in range(len(xyz)):
        reach = np.hypot(xyz[k, 0] - lidar_x, xyz[k, 1] - lidar_y)
        slope = (xyz[k, 2] - lidar_z) / (0.1 if reach < 0.1 else reach)
        if np.isnan(slope):
            return np.nan
        top = max(top, slope)
    return top


@warm_up
def compile_kernels() -> None:
    """The stem search's kernels compiled for the types a scan gives them."""
    _around(0.5, 0.5, 1.0, 2, 2, np.arange(3), np.arange(3))
    _top_slope(np.ones((2, 3)), 0.0, 0.0, 0.5)


def max_gap_m(reach_m: float, voxel_m: float) -> float:
    """The largest height gap inside one upright column seen from `reach_m`."""
    return _MISSED_RINGS * reach_m * math.tan(_RING_GAP_RAD) + voxel_m


def column_top(heights: np.ndarray, start_m: float, max_gap: float) -> float:
    """Climb from `start_m` through `heights` while no gap exceeds `max_gap`; the last
    height reached (`start_m` when the first return is already too far up)."""
    climbed = np.sort(heights)
    # Sorted, the height reached before each return is the start or the return below it,
    # whichever is higher: the climb's steps all at once, not a Python loop per return.
    reached = np.maximum(np.concatenate(([start_m], climbed[:-1])), start_m)
    too_far = np.flatnonzero(climbed - reached > max_gap)
    if len(too_far):
        return float(reached[too_far[0]])
    return max(start_m, float(climbed[-1])) if len(climbed) else start_m


def stem_of_voxels(
    voxels: np.ndarray, voxel_height: np.ndarray, stems: list[Stem], config: ClusterConfig
) -> np.ndarray:
    """Index of the stem each voxel belongs to (-1: none): within the column's radius
    (plus half a voxel: centroids sit inside their cell) and no higher than its top
    plus a voxel. The nearest stem wins where two columns overlap (a person's legs)."""
    owner = np.full(len(voxels), -1, dtype=np.int64)
    if not stems:
        return owner
    centres = np.stack([s.centre for s in stems])
    tops = np.array([s.top_m for s in stems])
    gaps = np.hypot(
        voxels[:, None, 0] - centres[None, :, 0], voxels[:, None, 1] - centres[None, :, 1]
    )
    inside = (gaps <= config.stem_radius_m + config.voxel_m / 2) & (
        voxel_height[:, None] <= tops[None, :] + config.voxel_m
    )
    gaps = np.where(inside, gaps, np.inf)
    nearest = gaps.argmin(axis=1)
    claimed = np.isfinite(gaps[np.arange(len(voxels)), nearest])
    owner[claimed] = nearest[claimed]
    return owner
