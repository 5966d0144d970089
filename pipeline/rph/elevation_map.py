"""Ground removal by an elevation map, as `ground_plane_removal`'s
ElevationMapGroundPlaneRemover builds it with grid_map_pcl.

1. A grid over the cloud's x-y bounding box, centred on it, `resolution` cells
   (round(extent / resolution) of them per axis, at least one).
2. Per cell: Euclidean sub-clusters of its points (tolerance `cell_cluster_tolerance`);
   the cell's elevation is the lowest sub-cluster mean z (the highest if so configured);
   a cell with too few points is NaN.
3. Median filter: each cell becomes the upper median of the finite elevations in a disk
   of `median_filter_radius` around it (cell centres within the radius; the centre cell
   counted twice, as the original appends it once more).
4. A point is kept when h + min_height_above_ground <= z <= h + max_height_above_ground,
   h being its cell's filtered elevation; with h NaN it is kept.

Deviations from the C++ (all at degenerate inputs): neighbours outside the map clamp to
the border cells [0, size - 1] (the original clamps to `size`, one past the end, the
likely cause of tree_detection#6); a disk with no finite cell gives NaN (the original
reads an empty vector); points beyond a rounded-down map edge belong to the border cell;
the disk's offsets are taken around each cell, not from a spiral around the map frame's
origin (identical when the origin is a cell centre inside the map).
The cloud must be gravity-aligned (z up).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from treetraits.pipeline.rph.clustering import component_labels
from treetraits.pipeline.rph.config import ElevationMapConfig


@dataclass(frozen=True)
class ElevationMap:
    origin: np.ndarray  # x, y of the grid's min corner
    resolution: float
    raw: np.ndarray  # (nx, ny) per-cell elevation before filtering, NaN = no data
    elevation: np.ndarray  # (nx, ny) after the median filter (or = raw)

    def cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cell indices of x-y positions; outside the map, the nearest border cell."""
        nx, ny = self.raw.shape
        index = np.floor((np.asarray(xy, dtype=np.float64) - self.origin) / self.resolution)
        i = np.clip(index[:, 0], 0, nx - 1).astype(np.int64)
        j = np.clip(index[:, 1], 0, ny - 1).astype(np.int64)
        return i, j

    def height_at(self, xy: np.ndarray) -> np.ndarray:
        """Filtered elevation under each x-y position (NaN where the map has none)."""
        i, j = self.cells(np.atleast_2d(xy))
        return self.elevation[i, j]


def build_elevation_map(points: np.ndarray, config: ElevationMapConfig) -> ElevationMap:
    """The (filtered) elevation map of an N x 3 gravity-aligned cloud (N >= 1)."""
    points = np.asarray(points, dtype=np.float64)
    low, high = points[:, :2].min(axis=0), points[:, :2].max(axis=0)
    size = np.maximum(np.round((high - low) / config.resolution), 1).astype(np.int64)
    origin = (low + high) / 2 - size * config.resolution / 2
    raw = np.full((int(size[0]), int(size[1])), np.nan)
    grid = ElevationMap(origin, config.resolution, raw, raw)
    i, j = grid.cells(points[:, :2])
    _cell_elevations(points, i, j, raw, config)
    elevation = median_filter(raw, config) if config.use_median_filter else raw
    return ElevationMap(origin, config.resolution, raw, elevation)


def remove_ground(
    points: np.ndarray, config: ElevationMapConfig
) -> tuple[np.ndarray, ElevationMap | None]:
    """Mask of the points kept (above the ground band's floor, below its ceiling)."""
    points = np.asarray(points, dtype=np.float64)
    if len(points) == 0:
        return np.zeros(0, dtype=bool), None
    grid = build_elevation_map(points, config)
    h = grid.height_at(points[:, :2])
    z = points[:, 2]
    # Written as the C++ skip test so that NaN (no elevation) keeps the point.
    skip = (z < h + config.min_height_above_ground) | (z > h + config.max_height_above_ground)
    return ~skip, grid


def _cell_elevations(points, i, j, raw: np.ndarray, config: ElevationMapConfig) -> None:
    nx, ny = raw.shape
    cell = i * ny + j
    counts = np.bincount(cell, minlength=nx * ny)
    usable = counts[cell] >= config.min_points_per_cell
    points, i, j, cell = points[usable], i[usable], j[usable], cell[usable]
    if len(points) == 0:
        return
    # Cluster every cell at once: shift each cell's points by twice the tolerance per cell
    # index, so no two points of different cells are within the tolerance.
    gap = 2.0 * config.cell_cluster_tolerance
    shifted = points.copy()
    shifted[:, 0] += i * gap
    shifted[:, 1] += j * gap
    labels = component_labels(shifted, config.cell_cluster_tolerance)
    count = np.bincount(labels)
    mean_z = np.bincount(labels, weights=points[:, 2]) / count
    cluster_cell = np.zeros(len(count), dtype=np.int64)
    cluster_cell[labels] = cell
    flat = np.full(nx * ny, np.inf if not config.use_max_height_as_cell_elevation else -np.inf)
    if config.use_max_height_as_cell_elevation:
        np.maximum.at(flat, cluster_cell, mean_z)
    else:
        np.minimum.at(flat, cluster_cell, mean_z)
    flat[~np.isfinite(flat)] = np.nan
    raw[:] = flat.reshape(nx, ny)


def disk_offsets(config: ElevationMapConfig) -> np.ndarray:
    """(di, dj) of the cells whose centres lie within the filter radius, in the order a
    ring-by-ring spiral visits them, downsampled past the first 9 as the original does,
    then the centre once more."""
    reach = int(np.floor(config.median_filter_radius / config.resolution))
    di, dj = np.meshgrid(np.arange(-reach, reach + 1), np.arange(-reach, reach + 1), indexing="ij")
    di, dj = di.ravel(), dj.ravel()
    inside = (di * di + dj * dj) * config.resolution**2 <= config.median_filter_radius**2 + 1e-12
    di, dj = di[inside], dj[inside]
    order = np.lexsort((np.arctan2(dj, di), np.maximum(np.abs(di), np.abs(dj))))
    offsets = np.column_stack([di[order], dj[order]])
    k = config.median_filter_downsample
    index = np.arange(len(offsets))
    offsets = offsets[(index <= 8) | (index % k == 0)]
    return np.vstack([offsets, [[0, 0]]])


def median_filter(raw: np.ndarray, config: ElevationMapConfig) -> np.ndarray:
    nx, ny = raw.shape
    ii, jj = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    stack = np.stack(
        [
            raw[np.clip(ii + di, 0, nx - 1), np.clip(jj + dj, 0, ny - 1)]
            for di, dj in disk_offsets(config)
        ]
    )
    stack.sort(axis=0)  # NaN sorts last
    finite = np.isfinite(stack).sum(axis=0)
    upper = np.take_along_axis(stack, (finite // 2)[None], axis=0)[0]  # upper median
    return np.where(finite > 0, upper, np.nan)
