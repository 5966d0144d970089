"""RPH's tree detector on one gravity-aligned cloud: ground removal, Euclidean
clustering, then the three per-cluster tests of `TreeDetector::extractValidPointClusters`
(PCA verticality, too low, too wide). Each kept cluster gives its mean and its
axis-aligned extents, as RPH outputs them, plus the traits read from its box:

- height = top of the cluster above the filtered elevation map at the cluster's mean x-y
  (the box alone starts 0.2 m above the ground, the removed band, and under-reads);
- width = the larger horizontal side of the box in the cloud's frame (RPH's dimX/dimY).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from treetraits.pipeline.rph.clustering import euclidean_clusters
from treetraits.pipeline.rph.config import DetectorConfig, RphConfig
from treetraits.pipeline.rph.elevation_map import ElevationMap, remove_ground

# Counters of one detection run, every cluster in exactly one of the last five.
COUNTERS = (
    "points",
    "ground_removed",
    "clusters",
    "too_few_or_many_points",
    "not_vertical",
    "too_low",
    "too_wide",
    "detections",
)


@dataclass(frozen=True)
class Cluster:
    """One kept cluster, in the frame of the cloud it came from."""

    position: np.ndarray  # mean of its points (x, y, z)
    dimensions: np.ndarray  # axis-aligned extents (dimX, dimY, dimZ)
    top_z: float
    ground_z: float  # filtered elevation under `position` (NaN when the map has none)
    points: int
    alignment: float  # |largest principal axis . z|

    @property
    def width_m(self) -> float:
        return float(max(self.dimensions[0], self.dimensions[1]))

    @property
    def height_m(self) -> float:
        if np.isfinite(self.ground_z):
            return float(self.top_z - self.ground_z)
        return float(self.dimensions[2])  # no ground under it: the box is all we have


@dataclass(frozen=True)
class Detection:
    clusters: tuple[Cluster, ...]
    kept: np.ndarray  # mask of the input points that survived ground removal
    elevation_map: ElevationMap | None
    counts: dict[str, int] = field(default_factory=dict)


def principal_alignment(points: np.ndarray) -> float:
    """|z component| of the eigenvector of the largest eigenvalue of the covariance."""
    centred = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(centred.T @ centred)  # ascending eigenvalues
    return float(abs(vectors[2, -1]))


def voxel_downsample(points: np.ndarray, leaf: float) -> np.ndarray:
    """PCL VoxelGrid: the centroid of the points in each leaf (leaves in sorted order)."""
    keys = np.floor(points / leaf).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.ravel()
    sums = np.zeros((len(counts), 3))
    np.add.at(sums, inverse, points)
    return sums / counts[:, None]


def detect(points: np.ndarray, config: RphConfig) -> Detection:
    """Trees in an N x 3 gravity-aligned cloud (metres, z up)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    counts = dict.fromkeys(COUNTERS, 0)
    counts["points"] = len(points)
    kept, grid = remove_ground(points, config.ground)
    counts["ground_removed"] = int(len(points) - kept.sum())
    cloud = points[kept]
    d = config.detector
    if d.voxel_size is not None and len(cloud):
        cloud = voxel_downsample(cloud, d.voxel_size)
    everything = euclidean_clusters(cloud, d.cluster_tolerance)
    counts["clusters"] = len(everything)
    clusters = []
    for indices in everything:
        if not d.min_points <= len(indices) <= d.max_points:
            counts["too_few_or_many_points"] += 1
            continue
        cluster = _evaluate(cloud[indices], grid, d, counts)
        if cluster is not None:
            clusters.append(cluster)
    counts["detections"] = len(clusters)
    return Detection(tuple(clusters), kept, grid, counts)


def _evaluate(
    points: np.ndarray, grid: ElevationMap | None, d: DetectorConfig, counts: dict[str, int]
) -> Cluster | None:
    low, high = points.min(axis=0), points.max(axis=0)
    dimensions = high - low
    alignment = principal_alignment(points)
    # All three tests are evaluated, as in the C++; the first failure is the one counted.
    vertical = alignment > d.min_eigenvector_alignment
    too_low = dimensions[2] < d.min_height
    too_wide = dimensions[0] > d.max_diameter or dimensions[1] > d.max_diameter
    if not vertical:
        counts["not_vertical"] += 1
    elif too_low:
        counts["too_low"] += 1
    elif too_wide:
        counts["too_wide"] += 1
    else:
        mean = points.mean(axis=0)
        ground = float(grid.height_at(mean[:2])[0]) if grid is not None else float("nan")
        return Cluster(mean, dimensions, float(high[2]), ground, len(points), alignment)
    return None
