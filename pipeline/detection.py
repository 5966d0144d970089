"""Per scan: trees as clusters of points (the paper's `compute_clusters`, Algorithm 1 l.3).

Pure functions over arrays; `detect` is the recipe. Everything happens in `base`
(base_footprint: x forward, y left, z up from the ground under the robot), so heights
read directly and the crop box is robot-relative whatever the LiDAR mount.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import NamedTuple

import numpy as np

from treetraits.drivers.records import POINT_DTYPE
from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.classify import (
    Shape,
    horizontal_extent,
    judge,
    ndvi_seen,
    roughness_of_groups,
    shape_of,
)
from treetraits.pipeline.clustering import euclidean_clusters, nearest_label, stable_order
from treetraits.pipeline.config import (
    ClassifyConfig,
    ClusterConfig,
    CropConfig,
    DetectionConfig,
    GroundConfig,
)
from treetraits.pipeline.mixed import mixed_returns
from treetraits.pipeline.stems import StemSearch, stem_of_voxels
from treetraits.pipeline.terrain import TerrainGrid, fit_terrain, lowest_ring_reach
from treetraits.pipeline.understorey import join_understorey
from treetraits.pipeline.vegetation import Cues, Evidence, measure_groups, weigh
from treetraits.pipeline.visibility import BeamsAbove

# Voxel keys: 21 bits per axis (+-1M cells: +-100 km at 0.1 m), packed into one int64.
_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


@dataclass(frozen=True)
class GroundPlane:
    """a x + b y + c z + d = 0 in `base`, (a, b, c) a unit normal with c > 0."""

    normal: np.ndarray
    d: float
    inliers: int
    fitted: bool  # False: RANSAC found no acceptable plane; z = 0 of base_footprint

    def height(self, xyz: np.ndarray) -> np.ndarray:
        """Vertical height of each point above the plane (m)."""
        return (xyz @ self.normal + self.d) / self.normal[2]

    def z_at(self, x, y) -> np.ndarray | float:
        """The plane's z at (x, y): points or arrays of them."""
        a, b, c = self.normal
        z = -(a * np.asarray(x, dtype=float) + b * np.asarray(y, dtype=float) + self.d) / c
        return float(z) if np.ndim(z) == 0 else z

    @property
    def tilt_deg(self) -> float:
        return math.degrees(math.acos(min(1.0, float(self.normal[2]))))


FLAT = GroundPlane(np.array([0.0, 0.0, 1.0]), 0.0, 0, False)

# What a scan's ground is: either model answers `height(xyz)` and `z_at(x, y)`.
GroundModel = GroundPlane | TerrainGrid


@dataclass(frozen=True)
class Cluster:
    """One cluster C_k. `centroid`, `num_points` and `ndvi` are the paper's m_k (centroid
    and count over the voxel grid's points); `hull_area`/`hull_volume` are the paper's
    suggested extra features (3D hull of the voxel points), computed when first read:
    the association does not use them, and qhull on every cluster of every scan would
    be paid for nothing."""

    centroid: np.ndarray  # (3,) base frame
    num_points: int  # voxels
    ndvi: float  # mean NDVI of its returns that have one; NaN if none
    voxels: np.ndarray  # (num_points, 3) voxel centroids, base frame
    points: np.ndarray  # (n, 3) every return of the cluster, base frame
    ring: np.ndarray  # (n,) uint8, ring of each return
    ground_z: float  # ground height under the centroid, base frame
    shape: Shape  # what the tree rules read (`pipeline.classify`)
    verdict: str  # "tree" or the reason it is not one (`classify.REASONS`)
    # (3,) base frame: the direction of the beam above its highest ring at its top's
    # bearing, when that beam passed over all of it (`pipeline.visibility`): its top lies
    # between its highest return and that ray. None: the crown went on above (or no beam
    # is above: the sensor's top ring hit it).
    beam_above: np.ndarray | None = None
    # The sensor's top ring hit it (`BeamsAbove.top_view`): its top was out of view because
    # it reached above the top beam, not because something nearer hid it (`top_view`).
    top_cut: bool = False
    # (3,) base frame: the axis of the one trunk seen under its crown in this scan
    # (`cluster_trunks`); None when none or more than one was seen.
    trunk: np.ndarray | None = None
    # What its surface and colour show (`pipeline.vegetation`) and what that weighs.
    cues: Cues = field(default_factory=Cues)
    evidence: Evidence = field(default_factory=Evidence)

    @property
    def top_seen(self) -> bool:
        """Its top was in view in this scan (see `beam_above`)."""
        return self.beam_above is not None

    @property
    def top_view(self) -> str:
        """Why its top was or was not in view in this scan: "seen"; "cut" (it reached the
        sensor's top beam: too close or too tall); "hidden" (the beam above hit something
        nearer than its far side within its bearings: a neighbour's crown, a branch, or
        the object going on upward)."""
        if self.top_seen:
            return "seen"
        return "cut" if self.top_cut else "hidden"

    @property
    def features(self) -> np.ndarray:
        """m_k = [x, y, z, num_points, mean NDVI] (NDVI may be NaN)."""
        return np.array([*self.centroid, self.num_points, self.ndvi], dtype=float)

    @cached_property
    def hull(self) -> tuple[float, float]:
        return hull_area_volume(self.voxels)

    @property
    def hull_area(self) -> float:
        """Surface area of the 3D convex hull (m^2); 0 for a flat cluster."""
        return self.hull[0]

    @property
    def hull_volume(self) -> float:
        """Volume of the 3D convex hull (m^3)."""
        return self.hull[1]


@dataclass(frozen=True)
class Detection:
    clusters: list[Cluster]
    ground: GroundModel
    # How many points went where: input, cropped (kept by the box), ground, skirt
    # (ground candidates kept as foliage), voxels, clustered voxels, clusters dropped.
    counts: dict[str, int] = field(default_factory=dict)


def to_base(points: np.ndarray, T_base_lidar: np.ndarray) -> np.ndarray:
    """N x 3 float64 in `base` from a POINT_DTYPE array in `lidar`."""
    xyz = np.empty((len(points), 3))
    xyz[:, 0], xyz[:, 1], xyz[:, 2] = points["x"], points["y"], points["z"]
    if np.array_equal(T_base_lidar[:3, :3], np.eye(3)):  # the usual level mount
        xyz += T_base_lidar[:3, 3]
        return xyz
    return xyz @ T_base_lidar[:3, :3].T + T_base_lidar[:3, 3]


def lowest_ring_elevation(points: np.ndarray) -> float | None:
    """The elevation (rad, in `lidar`) of the sensor's lowest beam: the median over the
    returns of ring 0 (rings are numbered by elevation from the lowest; the caller knows
    the scan's rings are numbered). None when that beam returned nothing (two of the
    indoor captures: the floor within the sensor's minimum range)."""
    lowest = points["ring"] == 0
    if not lowest.any():
        return None
    x, y, z = points["x"][lowest], points["y"][lowest], points["z"][lowest]
    return float(np.median(np.arctan2(z, np.hypot(x, y))))


def crop_mask(xyz: np.ndarray, config: CropConfig, lidar_xy: np.ndarray) -> np.ndarray:
    """Inside the box and not on the robot (horizontal distance from the LiDAR)."""
    x, y, z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    keep = (x >= config.x_m[0]) & (x <= config.x_m[1])
    keep &= (y >= config.y_m[0]) & (y <= config.y_m[1])
    keep &= (z >= config.z_m[0]) & (z <= config.z_m[1])
    near = (x - lidar_xy[0]) ** 2 + (y - lidar_xy[1]) ** 2 < config.min_range_m**2
    return keep & ~near


def crop(
    points: np.ndarray, T_base_lidar: np.ndarray, config: CropConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The returns `crop_mask` keeps, in `base` (K x 3 float64, as `to_base` gives them),
    and their indices in `points`. For the usual level mount one compiled pass over the
    points does it (`to_base` and `crop_mask` are a dozen NumPy passes)."""
    if points.dtype != POINT_DTYPE or not np.array_equal(T_base_lidar[:3, :3], np.eye(3)):
        xyz = to_base(points, T_base_lidar)
        keep = np.flatnonzero(crop_mask(xyz, config, T_base_lidar[:2, 3]))
        return np.take(xyz, keep, axis=0), keep
    offset = np.asarray(T_base_lidar, dtype=float)[:3, 3]
    xyz = np.empty((len(points), 3))
    keep = np.empty(len(points), dtype=np.int64)
    count = _crop_level(
        _point_words(points), *offset,
        *(float(v) for v in (*config.x_m, *config.y_m, *config.z_m, *T_base_lidar[:2, 3])),
        float(config.min_range_m**2), xyz, keep,
    )  # fmt: skip
    return xyz[:count], keep[:count]


_WORDS = POINT_DTYPE.itemsize // 4  # a point as 4-byte words: x, y, z first (float32)
assert [POINT_DTYPE.fields[f][1] for f in ("x", "y", "z")] == [0, 4, 8]


def _point_words(points: np.ndarray) -> np.ndarray:
    """POINT_DTYPE points as a writable C-ordered (points, 7) float32 view (copied when
    they are not so): the one layout `_crop_level` is compiled for."""
    points = kernel_layout(points, points.dtype)
    return points.view(np.float32).reshape(len(points), _WORDS)


@kernel
def _crop_level(words, dx, dy, dz, x_lo, x_hi, y_lo, y_hi, z_lo, z_hi, lidar_x, lidar_y,
                min_range_sq, xyz, keep):  # fmt: skip
    """`to_base` for a level mount (the float32 fields in float64, plus the offset) and
    `crop_mask`, with their comparisons, into `xyz` and `keep` (each point kept, its
    index); returns how many were kept."""
    count = 0
    for k in range(words.shape[0]):
        x = np.float64(words[k, 0]) + dx
        y = np.float64(words[k, 1]) + dy
        z = np.float64(words[k, 2]) + dz
        if not (x >= x_lo and x <= x_hi and y >= y_lo and y <= y_hi and z >= z_lo and z <= z_hi):
            continue
        from_x, from_y = x - lidar_x, y - lidar_y
        if from_x * from_x + from_y * from_y < min_range_sq:  # on the robot
            continue
        xyz[count, 0], xyz[count, 1], xyz[count, 2] = x, y, z
        keep[count] = k
        count += 1
    return count


@warm_up
def compile_kernels() -> None:
    """The crop's kernel compiled for the types a scan gives it, on two made-up points."""
    points = np.zeros(2, dtype=POINT_DTYPE)
    points["x"] = 3.0, 0.0
    crop(points, np.eye(4), CropConfig())


def fit_ground(xyz: np.ndarray, config: GroundConfig) -> GroundPlane:
    """RANSAC plane through the points near the footprint plane, refitted by least
    squares on its inliers; FLAT when no acceptable plane is found."""
    index = np.flatnonzero(np.abs(xyz[:, 2]) < config.candidate_window_m)
    if len(index) < max(3, config.min_inliers):
        return FLAT
    if len(index) > config.max_points:
        index = index[np.linspace(0, len(index) - 1, config.max_points).astype(np.int64)]
    candidates = xyz[index]
    if config.method == "open3d":
        normal, d = _open3d_plane(candidates, config)
    else:
        normal, d = _ransac_plane(candidates, config)
    if normal is None:
        return FLAT
    # Least squares on the inliers: the plane no longer depends on which three points
    # RANSAC happened to draw.
    inliers = candidates[np.abs(candidates @ normal + d) < config.distance_m]
    if len(inliers) < config.min_inliers:
        return FLAT
    centre = inliers.mean(axis=0)
    normal = np.linalg.svd(inliers - centre, full_matrices=False)[2][2]
    if normal[2] < 0:
        normal = -normal
    plane = GroundPlane(normal, float(-normal @ centre), len(inliers), True)
    return plane if plane.tilt_deg <= config.max_tilt_deg else FLAT


def _ransac_plane(points: np.ndarray, config: GroundConfig):
    """Seeded RANSAC: `iterations` three-point planes, those tilted more than the
    limit skipped (the ground, not a wall or a crown's flank), most inliers wins."""
    rng = np.random.default_rng(config.seed)
    sample = points[rng.integers(0, len(points), (config.iterations, 3))]
    points = points.astype(np.float32)  # counting inliers at mm precision: float32 is plenty
    normal = np.cross(sample[:, 1] - sample[:, 0], sample[:, 2] - sample[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal = normal / np.where(length > 0, length, 1.0)[:, None]
    upright = np.abs(normal[:, 2]) >= math.cos(math.radians(config.max_tilt_deg))
    upright &= length > 0
    if not upright.any():
        return None, 0.0
    normal = normal[upright]
    d = -(normal * sample[upright, 0]).sum(axis=1)
    distance = points @ normal.T.astype(np.float32)
    distance += d.astype(np.float32)
    inliers = (np.abs(distance) < config.distance_m).sum(axis=0)
    best = int(np.argmax(inliers))  # ties: the first drawn
    return normal[best], float(d[best])


def _open3d_plane(points: np.ndarray, config: GroundConfig):
    """open3d's segment_plane. Its worker threads share one RNG, so the plane can differ
    between two runs of the same scan (seen: 0.8 mm in a tree height): not the default."""
    import open3d as o3d

    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.utility.random.seed(config.seed)
    model, _ = cloud.segment_plane(config.distance_m, 3, config.iterations)
    normal = np.asarray(model[:3], dtype=float)
    length = float(np.linalg.norm(normal))
    if not length > 0:
        return None, 0.0
    return normal / length, float(model[3]) / length


def split_ground(
    height: np.ndarray, ndvi: np.ndarray | None, config: GroundConfig
) -> tuple[np.ndarray, np.ndarray]:
    """(above, skirt): points clear of the ground band, and ground-band points that the
    NDVI check keeps as foliage. Everything else is ground."""
    above = height >= config.clearance_m
    if ndvi is None:
        return above, np.zeros_like(above)
    with np.errstate(invalid="ignore"):
        green = ndvi >= config.skirt_min_ndvi  # NaN: never
    skirt = ~above & (height >= config.skirt_min_height_m) & green
    return above, skirt


def voxel_grid(xyz: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """(voxel of each point, voxel centroids): the PCL VoxelGrid (centroid per occupied
    leaf), leaves on a fixed grid anchored at the frame origin, voxels in key order."""
    cells = np.floor(xyz / size).astype(np.int64) + _KEY_OFFSET
    keys = (cells[:, 0] << (2 * _KEY_BITS)) | (cells[:, 1] << _KEY_BITS) | cells[:, 2]
    _, inverse = np.unique(keys, return_inverse=True)
    inverse = inverse.ravel()
    count = np.bincount(inverse)
    centroids = np.column_stack(
        [np.bincount(inverse, weights=xyz[:, axis]) / count for axis in range(3)]
    )
    return inverse, centroids


def hull_area_volume(xyz: np.ndarray) -> tuple[float, float]:
    """Surface area and volume of the 3D convex hull; (0, 0) when it is degenerate."""
    if len(xyz) < 4:
        return 0.0, 0.0
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(xyz)
    except (QhullError, ValueError):  # flat or collinear: no volume
        return 0.0, 0.0
    return float(hull.area), float(hull.volume)


NdviSource = np.ndarray | Callable[[np.ndarray], np.ndarray] | None


def detect(
    points: np.ndarray,
    ndvi: NdviSource,
    T_base_lidar: np.ndarray,
    config: DetectionConfig,
    stage_ms: dict[str, float] | None = None,
) -> Detection:
    """Clusters of one scan. `points` POINT_DTYPE in `lidar`. `ndvi`: None without a
    camera; an array, one value per point (NaN where unknown); or a function from point
    indices to their NDVI, called once for the points that can need it (those clear of
    the ground by at least the skirt height), so only they are projected.
    `stage_ms`, if given, receives each stage's time in ms."""
    clock = StageClock(stage_ms)
    counts = {"points": len(points)}
    # Robot-relative box: the far field is too sparse to cluster and the robot is not a tree.
    xyz, keep = crop(points, T_base_lidar, config.crop)
    counts["cropped"] = len(xyz)
    clock.lap("crop")
    # A return between an object's edge and what stands behind it links the two
    # (`pipeline.mixed`): read along the whole rings, left out of what the box kept.
    mixed = mixed_returns(points, config.cluster.tolerance_m, config.cluster.mixed_offset_m)
    clean = ~mixed[keep]
    counts["mixed"] = int(len(keep) - clean.sum())
    if counts["mixed"]:
        xyz, keep = xyz[clean], keep[clean]
    ring = points["ring"][keep]
    source = keep  # each kept return's index in `points`
    clock.lap("mixed")

    # Height above the ground under each point, not z, tells ground from tree: the
    # terrain follows slopes, furrows and beds (`pipeline.terrain`).
    # A cloud imported without rings has every return on ring 0: nothing is known of
    # its beams, neither where the lowest meets the ground nor which return it made.
    rings_known = bool(points["ring"].any())
    elevation = lowest_ring_elevation(points) if rings_known else None
    reach = None if elevation is None else lowest_ring_reach(elevation, T_base_lidar)
    ground = ground_model(xyz, config, reach)
    height = ground.height(xyz)
    clock.lap("ground")

    # The image check: low points that look like foliage are a skirt, not soil.
    values = None
    if ndvi is not None:
        values = np.full(len(xyz), np.nan)
        if callable(ndvi):
            need = np.flatnonzero(height >= config.ground.skirt_min_height_m)
            if len(need):
                values[need] = ndvi(keep[need])
            clock.lap("ndvi")
        else:
            values[:] = np.asarray(ndvi, dtype=float)[keep]
    ndvi = values
    above, skirt = split_ground(height, ndvi, config.ground)
    kept = above | skirt
    counts["ground"] = int(len(xyz) - kept.sum())
    counts["skirt"] = int(skirt.sum())
    xyz, ring, above, height = xyz[kept], ring[kept], above[kept], height[kept]
    source = source[kept]
    ndvi = None if ndvi is None else ndvi[kept]
    clock.lap("ndvi_check")

    # Voxel grid: even out the VLP-16's 10:1 along-ring oversampling before clustering.
    voxel_of, voxels = voxel_grid(xyz, config.cluster.voxel_m)
    core = np.zeros(len(voxels), dtype=bool)
    core[voxel_of[above]] = True  # a voxel with any point clear of the ground band
    counts["voxels"] = len(voxels)
    clock.lap("voxel")

    # Posts and people are cut out first, each its own cluster (`pipeline.stems`).
    lidar_xy = T_base_lidar[:2, 3]
    voxel_height = ground.height(voxels)
    blobs = _band_blobs(xyz, height, ring, config.cluster, lidar_xy)
    stem_of, is_stem = _stems(
        xyz, height, ring, T_base_lidar[:3, 3], blobs, voxels, voxel_height, config
    )
    counts["stems"] = int(stem_of.max(initial=-1) + 1)
    clock.lap("stems")

    # Crowns: Euclidean clustering of the voxels that reach above the understorey. What
    # lies lower (trunks, skirts, weeds, drip lines) joins the crown it touches and
    # never links two (`pipeline.understorey`).
    top = np.full(len(voxels), -np.inf)
    np.maximum.at(top, voxel_of, height)
    free = stem_of < 0
    crown = core & free & (top >= config.cluster.bridge_min_height_m)
    labels = np.full(len(voxels), -1, dtype=np.int64)
    crown_index = np.flatnonzero(crown)
    labels[crown_index] = euclidean_clusters(
        voxels[crown_index], config.cluster.tolerance_m, config.cluster.method
    )
    under = free & ~crown
    labels[under] = join_understorey(
        voxels, labels, under, core, config.cluster.tolerance_m, int(labels.max(initial=-1)) + 1
    )
    trunk_blobs = [blob for blob, stem in zip(blobs, is_stem, strict=True) if not stem]
    labels, counts["split"] = split_at_trunks(labels, voxels, crown, trunk_blobs, config.cluster)
    trunks = cluster_trunks(
        labels, voxels, crown, trunk_blobs, config.cluster, config.classify, lidar_xy
    )
    stemmed = stem_of >= 0
    labels[stemmed] = labels.max(initial=-1) + 1 + stem_of[stemmed]
    clusters_kept = _size_filter(labels, config.cluster)
    counts["clusters_dropped"] = int(labels.max(initial=-1) + 1 - len(clusters_kept))
    clock.lap("cluster")

    beams = BeamsAbove(points)
    window = math.radians(config.cluster.top_window_deg)

    def top_view(members: np.ndarray) -> tuple[np.ndarray | None, bool]:
        """The beam above the cluster's top, in `base`, when it passed over it all (else
        None), and whether the sensor's top ring hit it (`BeamsAbove.top_view`)."""
        beam, cut = beams.top_view(source[members], window, config.cluster.tolerance_m)
        return (None if beam is None else T_base_lidar[:3, :3] @ beam), cut

    clusters = _features(
        clusters_kept,
        labels,
        voxel_of,
        voxels,
        xyz,
        ring,
        ndvi,
        ground,
        T_base_lidar[:3, 3],
        config.classify,
        top_view,
        trunks,
        points[["azimuth", "intensity", "return_type"]],  # a view: nothing copied
        source,
        height >= config.cluster.bridge_min_height_m,
        rings_known,
    )
    counts["clustered_voxels"] = sum(c.num_points for c in clusters)
    clock.lap("features")
    return Detection(clusters, ground, counts)


def ground_model(
    xyz: np.ndarray, config: DetectionConfig, lowest_ring_reach_m: float | None = None
) -> GroundModel:
    """The configured ground of one scan's cropped points (`base`); `lowest_ring_reach_m`
    as `fit_terrain` takes it (where the lowest beam meets level ground)."""
    if config.ground.model == "plane":
        return fit_ground(xyz, config.ground)
    return fit_terrain(xyz, config.terrain, config.crop.x_m, config.crop.y_m, lowest_ring_reach_m)


def split_at_trunks(
    labels: np.ndarray,
    voxels: np.ndarray,
    crown: np.ndarray,
    trunk_blobs: list[BandBlob],
    config: ClusterConfig,
) -> tuple[np.ndarray, int]:
    """Crowns that touch (a hedgerow) make one cluster along the row: such a cluster is
    cut into one per trunk, each voxel to the nearest trunk (x-y). Trunks: the trunk
    band's blobs (`_band_blobs`, stems left out) whose nearest crown voxel (x-y, `crown`
    marks them) is the cluster's (`_blobs_under`): a trunk stands under its own crown,
    which need not reach down to it. Only clusters at least two tree spacings long are
    looked at (a single crown, even an old one, has one trunk). Returns the new voxel
    labels and how many clusters were cut."""
    clustered = np.flatnonzero(labels >= 0)
    if len(clustered) == 0:
        return labels, 0
    order = clustered[stable_order(labels[clustered])]
    starts = np.flatnonzero(np.diff(labels[order], prepend=-2))
    ends = np.append(starts[1:], len(order))
    reach = 2 * config.min_tree_spacing_m
    wide = ~_narrower(voxels[order, :2], starts, reach)
    long = [
        order[start:end]
        for start, end in zip(starts[wide], ends[wide], strict=True)
        if horizontal_extent(voxels[order[start:end], :2]) >= reach
    ]
    if not long:
        return labels, 0
    under = _blobs_under(labels, voxels, crown, trunk_blobs)
    next_label = int(labels.max(initial=-1)) + 1
    cut = 0
    for cells in long:
        mine = [trunk_blobs[k] for k in np.flatnonzero(under == labels[cells[0]])]
        trunks = np.array([blob.centre for blob in _trunks(mine, config)]).reshape(-1, 2)
        if len(trunks) < 2:
            continue
        gaps = voxels[cells, None, :2] - trunks[None]
        nearest = (gaps**2).sum(axis=2).argmin(axis=1)
        labels[cells] = np.where(nearest == 0, labels[cells], next_label + nearest - 1)
        next_label += len(trunks) - 1
        cut += 1
    return labels, cut


def _narrower(xy: np.ndarray, starts: np.ndarray, width: float) -> np.ndarray:
    """Which groups (`xy[starts[k]:starts[k + 1]]`, each non-empty, the last to the end)
    are narrower than `width` (`horizontal_extent`) for sure: no width exceeds the
    bounding box's diagonal, and a box a micrometre short of it (far beyond rounding)
    proves it without the 12 bearings."""
    span = np.maximum.reduceat(xy, starts, axis=0) - np.minimum.reduceat(xy, starts, axis=0)
    return (span**2).sum(axis=1) < (width - 1e-6) ** 2


def cluster_trunks(
    labels: np.ndarray,
    voxels: np.ndarray,
    crown: np.ndarray,
    trunk_blobs: list[BandBlob],
    config: ClusterConfig,
    classify: ClassifyConfig,
    lidar_xy: np.ndarray,
) -> dict[int, np.ndarray]:
    """The trunk axis (`BandBlob.axis`, base) of each cluster label under whose crown
    exactly one trunk stands in this scan: where a tree is, for the field map, is its
    trunk, not its crown's centre (a lobed or one-sided crown's centre lies decimetres
    off it). A trunk here is a band blob that is smooth along the rings (bark, under
    `classify.min_roughness_m`; a weed clump as narrow is foliage, rough; too few
    returns to tell: not counted), a tree spacing from any other (`_trunks`). Two or
    more: a neighbour's trunk beside it, and no telling which is the tree's."""
    under = _blobs_under(labels, voxels, crown, trunk_blobs)
    bark = _is_bark([trunk_blobs[k] for k in np.flatnonzero(under >= 0)], lidar_xy, classify)
    bark_of = dict(zip(np.flatnonzero(under >= 0).tolist(), bark, strict=True))
    found = {}
    for label in np.unique(under[under >= 0]):
        mine = [trunk_blobs[k] for k in np.flatnonzero(under == label) if bark_of[k]]
        kept = _trunks(mine, config)
        if len(kept) == 1:
            found[int(label)] = kept[0].axis
    return found


def _is_bark(blobs: list[BandBlob], lidar_xy: np.ndarray, classify: ClassifyConfig) -> list[bool]:
    """Which blobs are smooth along the rings (`classify.roughness`), as bark is; NaN
    (too few returns to tell) is not. All in one pass (`roughness_of_groups`)."""
    if not blobs:
        return []
    rough = roughness_of_groups(
        np.concatenate([blob.xyz for blob in blobs]),
        np.concatenate([blob.ring for blob in blobs]),
        lidar_xy,
        np.array([len(blob.xyz) for blob in blobs]),
    )
    return [bool(r < classify.min_roughness_m) for r in rough]  # NaN: never


def _blobs_under(
    labels: np.ndarray, voxels: np.ndarray, crown: np.ndarray, blobs: list[BandBlob]
) -> np.ndarray:
    """The cluster label of each blob's nearest crown voxel (x-y), -1 with no crown."""
    crown_index = np.flatnonzero(crown & (labels >= 0))
    if not blobs or len(crown_index) == 0:
        return np.full(len(blobs), -1, dtype=np.int64)
    centres = np.array([blob.centre for blob in blobs])
    return nearest_label(centres, voxels[crown_index, :2], labels[crown_index])


def _stems(
    xyz, height, ring, lidar_xyz, blobs, voxels, voxel_height, config: DetectionConfig
) -> tuple[np.ndarray, list[bool]]:
    """The stem (`pipeline.stems`) each voxel belongs to (-1 for none), and which of the
    band's blobs are stems."""
    cluster = config.cluster
    if cluster.min_stem_height_m <= 0:
        return np.full(len(voxels), -1, dtype=np.int64), [False] * len(blobs)
    centres = np.array([blob.centre for blob in blobs]).reshape(-1, 2)
    band_top = cluster.trunk_band_m[1]
    # One search for both bands: what depends on the scan's returns is worked out once.
    search = StemSearch(xyz, height, ring, lidar_xyz, cluster)
    stems = search.find(centres, band_top, config.classify)
    is_stem = [any(np.array_equal(c, stem.centre) for stem in stems) for c in centres]
    # A post or a person whose foot stands in a weed clump (where the mower cannot reach)
    # is no blob in the trunk band: seed it again just above the understorey.
    upper = _band_blobs(xyz, height, ring, cluster, lidar_xyz[:2], stem_seed_band(cluster))
    found = np.array([stem.centre for stem in stems]).reshape(-1, 2)
    seeds = [
        blob.centre
        for blob in upper
        if not (np.hypot(*(found - blob.centre).T) <= cluster.stem_radius_m).any()
    ]
    if seeds:
        seed_top = stem_seed_band(cluster)[1]
        stems += search.find(np.array(seeds), seed_top, config.classify)
    return stem_of_voxels(voxels, voxel_height, stems, cluster), is_stem


def stem_seed_band(config: ClusterConfig) -> tuple[float, float]:
    """Where a stem hidden in the understorey at its foot is seeded: the trunk band's
    depth, from the understorey's top (`bridge_min_height_m`) up."""
    low, high = config.trunk_band_m
    return config.bridge_min_height_m, config.bridge_min_height_m + (high - low)


class BandBlob(NamedTuple):
    """Returns of a trunk, a post or a leg in a band above the terrain."""

    returns: int
    centre: np.ndarray  # (2,) x-y mean of the returns, base
    # (3,) base: the axis under the returns, taking the blob for a round stem seen from
    # the LiDAR. Returns cover the near half of a cylinder of radius r evenly across the
    # line of sight, so their mean lies pi/4 r in front of the axis; r is half the
    # blob's width across the line of sight. z: the returns' mean height.
    axis: np.ndarray
    xyz: np.ndarray  # its returns (base), for `_is_bark`
    ring: np.ndarray


def _band_blobs(
    xyz: np.ndarray,
    height: np.ndarray,
    ring: np.ndarray,
    config: ClusterConfig,
    lidar_xy: np.ndarray,
    band: tuple[float, float] | None = None,
) -> list[BandBlob]:
    """Blobs of the trunk band's returns (or `band`'s: heights above the terrain) (x-y)
    0.25 m apart at most, no wider than `max_trunk_width_m`. Trunks, posts and legs."""
    low, high = band or config.trunk_band_m
    in_band = (height >= low) & (height <= high)
    band_xyz, band_ring = xyz[in_band], ring[in_band]
    if len(band_xyz) < config.min_trunk_points:
        return []
    xy = band_xyz[:, :2]
    # Clustered in x-y alone: the same pairs as with z = 0, one dimension less to search.
    found = []
    for mine in _groups(euclidean_clusters(xy, 0.25)):
        if len(mine) < config.min_trunk_points:
            continue
        part = xy[mine]
        if horizontal_extent(part) > config.max_trunk_width_m:
            continue  # a skirt hanging into the band, a weed: not a trunk
        returns = band_xyz[mine]
        centre = part.mean(axis=0)
        axis = _axis(part, centre, float(returns[:, 2].mean()), lidar_xy)
        found.append(BandBlob(len(part), centre, axis, returns, band_ring[mine]))
    return found


def _groups(labels: np.ndarray) -> list[np.ndarray]:
    """Indices of each label's members, labels in increasing order, members in index
    order (as `labels == b` would give them): one stable sort, not a mask per label."""
    order = stable_order(labels)
    starts = np.flatnonzero(np.diff(labels[order])) + 1
    return np.split(order, starts) if len(order) else []


def _axis(xy: np.ndarray, centre: np.ndarray, z: float, lidar_xy: np.ndarray) -> np.ndarray:
    """`BandBlob.axis` of returns `xy` whose mean is `centre`."""
    ray = centre - lidar_xy
    reach = float(np.hypot(*ray))
    if reach == 0.0:
        return np.array([*centre, z])
    ray /= reach
    across = xy @ np.array([-ray[1], ray[0]])
    radius = float(across.max() - across.min()) / 2
    return np.array([*(centre + ray * (math.pi / 4) * radius), z])


def _trunks(blobs: list[BandBlob], config: ClusterConfig) -> list[BandBlob]:
    """Trunks among band blobs: each at least `min_tree_spacing_m` from one with more
    returns."""
    found = sorted(blobs, key=lambda blob: -blob.returns)
    # The best seen first: a blob of a few returns within a tree spacing of it gives way.
    kept: list[BandBlob] = []
    for blob in found:
        if all(np.hypot(*(blob.centre - k.centre)) >= config.min_tree_spacing_m for k in kept):
            kept.append(blob)
    return kept


def _size_filter(labels: np.ndarray, config: ClusterConfig) -> np.ndarray:
    """Cluster labels whose voxel count is within the limits, in label order."""
    sizes = np.bincount(labels[labels >= 0], minlength=labels.max(initial=-1) + 1)
    return np.flatnonzero((sizes >= config.min_points) & (sizes <= config.max_points))


def _features(
    kept,
    labels,
    voxel_of,
    voxels,
    xyz,
    ring,
    ndvi,
    ground,
    lidar_xyz,
    classify: ClassifyConfig,
    top_view: Callable[[np.ndarray], tuple[np.ndarray | None, bool]],
    trunks: dict[int, np.ndarray],
    firing: np.ndarray,
    source: np.ndarray,
    crown_part: np.ndarray,
    rings_known: bool,
) -> list[Cluster]:
    """Each kept cluster's shape, cues and verdict. `firing`: the scan's returns' sensor
    azimuth, intensity and return type (`vegetation.measure_groups`), `source` each
    kept return's index among them (only the clusters' are gathered). `crown_part`: the
    returns above the understorey, on which the cues are measured: weeds at a post's
    foot are vegetation, and a post standing in them is no crown (a tree's foliage is
    its crown's, above where the understorey ends). `rings_known`: the scan's rings
    number its beams, so a cluster's base on ring 0 is cut by the view
    (`Shape.base_cut`)."""
    lidar_xy = lidar_xyz[:2]
    point_label = labels[voxel_of]
    order = stable_order(point_label)
    bounds = np.searchsorted(point_label[order], np.stack([kept, kept + 1]))
    voxel_order = stable_order(labels)
    voxel_bounds = np.searchsorted(labels[voxel_order], np.stack([kept, kept + 1]))
    # Every cluster's returns gathered once, one slice each: the roughness of all of them
    # in one pass (`roughness_of_groups`), then each one's points and rings.
    members_of = [order[bounds[0, k] : bounds[1, k]] for k in range(len(kept))]
    every = np.concatenate(members_of) if members_of else np.zeros(0, dtype=np.int64)
    all_points, all_rings = xyz[every], ring[every]
    sizes = bounds[1] - bounds[0]
    rough = roughness_of_groups(all_points, all_rings, lidar_xy, sizes)
    upper = crown_part[every]
    owner = np.repeat(np.arange(len(kept)), sizes)
    surface = measure_groups(
        all_points[upper],
        all_rings[upper],
        firing[source[every[upper]]],
        lidar_xyz,
        np.bincount(owner[upper], minlength=len(kept)),
        classify,
    )
    ends = np.cumsum(sizes)
    cells_of = [
        voxels[voxel_order[voxel_bounds[0, k] : voxel_bounds[1, k]]] for k in range(len(kept))
    ]
    centroids = np.array([cells.mean(axis=0) for cells in cells_of]).reshape(-1, 3)
    # The ground under every cluster's centroid in one call: each call has a fixed cost.
    ground_zs = np.atleast_1d(ground.z_at(centroids[:, 0], centroids[:, 1]))
    clusters = []
    for k, members in enumerate(members_of):
        cells, centroid = cells_of[k], centroids[k]
        values = None if ndvi is None else ndvi[members]
        ground_z = float(ground_zs[k])
        points = all_points[ends[k] - sizes[k] : ends[k]]
        rings = all_rings[ends[k] - sizes[k] : ends[k]]
        shape = shape_of(points, rings, lidar_xy, ground_z, values, float(rough[k]), rings_known)
        mine = upper[ends[k] - sizes[k] : ends[k]]
        if mine.any():
            shape = replace(shape, crown_width_m=horizontal_extent(points[mine, :2]))
        crown_ndvi, crown_seen, seen_returns = ndvi_seen(None if values is None else values[mine])
        cues = replace(
            surface[k], ndvi=crown_ndvi, ndvi_share=crown_seen, ndvi_returns=seen_returns
        )
        evidence = weigh(cues, classify)
        beam, cut = top_view(members)
        clusters.append(
            Cluster(
                centroid=centroid,
                num_points=len(cells),
                ndvi=shape.ndvi,  # the mean of the finite values, NaN for none
                voxels=cells,
                points=points,
                ring=rings,
                ground_z=ground_z,
                shape=shape,
                verdict=judge(shape, classify, evidence),
                cues=cues,
                evidence=evidence,
                beam_above=beam,
                top_cut=cut,
                trunk=trunks.get(int(kept[k])),
            )
        )
    return clusters


class StageClock:
    """Stage timer for the benchmark; does nothing without a dict to fill."""

    def __init__(self, out: dict[str, float] | None):
        self.out = out
        self.last = time.perf_counter() if out is not None else 0.0

    def lap(self, name: str) -> None:
        if self.out is not None:
            now = time.perf_counter()
            self.out[name] = self.out.get(name, 0.0) + (now - self.last) * 1e3
            self.last = now
