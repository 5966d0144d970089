"""The RPH baseline (leggedrobotics/tree_detection, Jelavic et al.): elevation-map ground
removal, Euclidean clustering, a PCA verticality test and extent limits, reimplemented
without ROS/PCL, with the shipped parameters and a declared single-scan retune
(docs/rph.md). `RphMapper` offers the paper mapper's `process`/`trees` calls and returns
its `TrackedTree` records.
"""

from treetraits.pipeline.rph.config import (
    AssociationConfig,
    DetectorConfig,
    ElevationMapConfig,
    RphConfig,
    rph_config,
)
from treetraits.pipeline.rph.detector import Cluster, Detection, detect
from treetraits.pipeline.rph.elevation_map import ElevationMap, build_elevation_map, remove_ground
from treetraits.pipeline.rph.mapper import RphClusterResult, RphMapper, RphScanResult

__all__ = [
    "AssociationConfig",
    "Cluster",
    "Detection",
    "DetectorConfig",
    "ElevationMap",
    "ElevationMapConfig",
    "RphClusterResult",
    "RphConfig",
    "RphMapper",
    "RphScanResult",
    "build_elevation_map",
    "detect",
    "remove_ground",
    "rph_config",
]
