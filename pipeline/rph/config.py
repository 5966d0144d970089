"""Settings of the RPH baseline: the values `leggedrobotics/tree_detection` ships, and a
declared retune for single VLP-16 scans.

The shipped values are those of `tree_detection_ros/config/tree_detection.yaml` (the node
reads every key from it, so the C++ header defaults never apply). The retune changes only
what a single scan's sparsity forces; each change says why (docs/rph.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from treetraits.errors import ConfigError


@dataclass(frozen=True)
class ElevationMapConfig:
    """`ground_plane_removal/elevation_map` and the grid_map_pcl cell settings."""

    resolution: float = 0.5  # grid_map/resolution, m
    min_points_per_cell: int = 1  # grid_map/min_num_points_per_cell
    # Per-cell Euclidean clustering (cluster_extraction/*); the cell's elevation is the
    # lowest (or highest) mean z of its sub-clusters.
    cell_cluster_tolerance: float = 0.02
    use_max_height_as_cell_elevation: bool = False
    use_median_filter: bool = True
    median_filter_radius: float = 2.0  # m
    median_filter_downsample: int = 1
    # Points kept: h + min <= z <= h + max (h = filtered elevation of the point's cell).
    min_height_above_ground: float = 0.2
    max_height_above_ground: float = 3.5

    def __post_init__(self) -> None:
        _positive(self, "resolution", "cell_cluster_tolerance", "median_filter_radius")
        _at_least_one(self, "min_points_per_cell", "median_filter_downsample")
        if not self.min_height_above_ground < self.max_height_above_ground:
            raise ConfigError(
                "rph.ground: min_height_above_ground must be below max_height_above_ground, "
                f"got {self.min_height_above_ground} and {self.max_height_above_ground}"
            )


@dataclass(frozen=True)
class DetectorConfig:
    """`tree_detection/*` plus the (disabled as shipped) voxel grid of the preprocessor."""

    cluster_tolerance: float = 0.1  # m
    min_points: int = 200  # clusters with fewer points are discarded (PCL size limits)
    max_points: int = 5_000_000
    # |largest principal axis . z| must exceed this (strictly).
    min_eigenvector_alignment: float = 0.7
    min_height: float = 0.8  # m: discard if max z - min z is below
    max_diameter: float = 4.0  # m: discard if the x or the y extent is above
    voxel_size: float | None = None  # m; None = no voxel grid (point_cloud_preprocessing)

    def __post_init__(self) -> None:
        _positive(self, "cluster_tolerance", "max_diameter")
        _at_least_one(self, "min_points")
        if self.max_points < self.min_points:
            raise ConfigError("rph.detector: max_points must be >= min_points")
        if not 0.0 <= self.min_eigenvector_alignment <= 1.0:
            raise ConfigError(
                "rph.detector: min_eigenvector_alignment is |cos| of an angle, in [0, 1], "
                f"got {self.min_eigenvector_alignment}"
            )
        if self.min_height < 0:
            raise ConfigError(f"rph.detector: min_height must be >= 0, got {self.min_height}")
        if self.voxel_size is not None:
            _positive(self, "voxel_size")


@dataclass(frozen=True)
class AssociationConfig:
    """RPH has no tracker: a detection joins the nearest tree (x-y, same frame) within
    `gate_m`, one detection per tree per scan, greedily by distance; else it starts a tree."""

    gate_m: float = 1.5

    def __post_init__(self) -> None:
        _positive(self, "gate_m")


@dataclass(frozen=True)
class RphConfig:
    preset: str = "shipped"
    ground: ElevationMapConfig = field(default_factory=ElevationMapConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    association: AssociationConfig = field(default_factory=AssociationConfig)

    @classmethod
    def shipped(cls) -> RphConfig:
        """tree_detection.yaml as shipped (the defaults of this class)."""
        return cls()

    @classmethod
    def retuned_vlp16(cls) -> RphConfig:
        """The declared single-scan retune (docs/rph.md, "Retuned for single VLP-16 scans").

        - cluster_tolerance 0.1 -> 0.5 m: adjacent VLP-16 rings are 0.035 r apart
          vertically (0.1 m at 3 m, 0.18 m at 5 m) and a crown's visible shell has gaps of
          that order, so at 0.1 m a tree falls apart into per-ring slivers. 0.5 m is still
          less than half the gap between neighbouring crowns (>= 1.2 m in the twin).
        - min_points 200 -> 50: a single scan puts ~100-2000 points on a tree, not the tens
          of thousands of an accumulated map; 50 still rejects leaf-sized specks.
        - min_eigenvector_alignment 0.7 -> 0.0 (the PCA is still computed and reported in
          `Cluster.alignment`, but no longer gates): a citrus crown is wider than tall, and
          a single scan sees only its near half-shell, wider still, so its principal axis
          is horizontal (|e1 . z| ~ 0.01) and the shipped test rejects the tree in all but
          a few oblique views. RPH's test was made for forest trunks with the crowns
          cropped off; the paper reports RPH traits for every tree, so its RPH accepted them.
        Ground removal, min_height, max_diameter and the height band are as shipped.
        """
        return cls(
            preset="vlp16",
            detector=DetectorConfig(
                cluster_tolerance=0.5, min_points=50, min_eigenvector_alignment=0.0
            ),
        )


PRESETS = {"shipped": RphConfig.shipped, "vlp16": RphConfig.retuned_vlp16}


def rph_config(preset: str = "shipped") -> RphConfig:
    """A preset by name: `shipped` (tree_detection.yaml) or `vlp16` (the retune)."""
    try:
        return PRESETS[preset]()
    except KeyError:
        raise ConfigError(f"rph: unknown preset {preset!r}; known: {sorted(PRESETS)}") from None


def _positive(section, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
            raise ConfigError(f"rph.{_label(section)}: {name} must be > 0, got {value!r}")


def _at_least_one(section, *names: str) -> None:
    for name in names:
        value = getattr(section, name)
        if not (isinstance(value, int) and value >= 1):
            raise ConfigError(f"rph.{_label(section)}: {name} must be an integer >= 1")


def _label(section) -> str:
    return {
        "ElevationMapConfig": "ground",
        "DetectorConfig": "detector",
        "AssociationConfig": "association",
    }.get(type(section).__name__, type(section).__name__)


__all__ = [
    "PRESETS",
    "AssociationConfig",
    "DetectorConfig",
    "ElevationMapConfig",
    "RphConfig",
    "rph_config",
]
