"""`RphMapper`: the RPH baseline behind the same calls as the paper's `TreeMapper`
(`process(scan, frame=None, pose=None)` per scan, `trees()` for the map so far, the same
`TrackedTree` records), so the replay can switch with `--method rph`.

Per scan: the LiDAR points go to the world frame of the pose (gravity-aligned: the pose
has no roll or pitch), RPH detects clusters there (`detector.detect`), and each detection
joins a tree. RPH itself has no tracker; the association here is the simplest one that
lets its per-cloud boxes be compared with the paper's tracks: the nearest tree in x-y
within `association.gate_m`, one detection per tree per scan, pairs taken greedily by
distance; an unmatched detection starts a tree. A tree's position is the mean of its
detections' centroids; its width and height are the maximum over its detections (the
paper's "keep the maximum"). No NDVI: `ndvi` is None. Pure and deterministic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from treetraits.drivers.calibration import Calibration
from treetraits.drivers.records import Frame, Scan
from treetraits.pipeline.localization.pose import Pose
from treetraits.pipeline.mapper import TrackedTree
from treetraits.pipeline.projection import scan_mid_time
from treetraits.pipeline.rph.config import RphConfig
from treetraits.pipeline.rph.detector import COUNTERS, Cluster, detect

# The frame trees are kept in when scans come without a pose: the robot is taken as
# standing still, its base_footprint as the world.
NO_POSE_FRAME = "base_footprint"
TRAITS = "rph"  # TrackedTree.traits: width/height read from RPH's boxes


@dataclass(frozen=True)
class RphClusterResult:
    """One kept RPH cluster of a scan (world frame) and the tree it joined; the fields
    shared with the paper mapper's `ClusterResult` come first."""

    centroid: np.ndarray  # (3,) mean of the cluster's points, in the world frame
    num_points: int
    ndvi: float  # always NaN: RPH has no NDVI
    tree_id: int
    outcome: str  # "created" or "updated"
    cluster: Cluster  # the box, ground height and PCA alignment

    @property
    def width_m(self) -> float:
        return self.cluster.width_m

    @property
    def height_m(self) -> float:
        return self.cluster.height_m


@dataclass(frozen=True)
class RphScanResult:
    t: int  # the scan's middle, host clock, ns
    frame: str  # world frame of the centroids and the trees
    clusters: list[RphClusterResult]
    created: list[int]
    updated: list[int]
    merged: list[tuple[int, int]] = field(default_factory=list)  # RPH never merges
    ndvi: str = "not_used"
    counts: dict[str, int] = field(default_factory=dict)  # detector.COUNTERS


@dataclass
class _Track:
    tree_id: int
    position_sum: np.ndarray
    width: float
    height: float
    observations: int
    first_seen: int
    last_seen: int

    @property
    def position(self) -> np.ndarray:
        return self.position_sum / self.observations

    def add(self, cluster: Cluster, t: int) -> None:
        self.position_sum = self.position_sum + cluster.position
        self.width = max(self.width, cluster.width_m)
        self.height = max(self.height, cluster.height_m)
        self.observations += 1
        self.first_seen = min(self.first_seen, t)
        self.last_seen = max(self.last_seen, t)


class RphMapper:
    def __init__(self, config: RphConfig | None = None, calibration: Calibration | None = None):
        self.config = config or RphConfig.shipped()
        self.calibration = calibration or Calibration()
        self.frame: str | None = None  # fixed by the first scan, as in TreeMapper
        self.scans = 0
        self.counts = dict.fromkeys(COUNTERS, 0)  # totals over every scan processed
        self._tracks: list[_Track] = []

    def reanchor(self, new_from_old: np.ndarray, frame: str) -> None:
        """Move every tree into another world frame (as `TreeMapper.reanchor`)."""
        rotation, translation = new_from_old[:3, :3], new_from_old[:3, 3]
        for track in self._tracks:
            # The sum of n transformed positions: R sum + n t.
            track.position_sum = rotation @ track.position_sum + track.observations * translation
        self.frame = frame

    def process(
        self,
        scan: Scan,
        frame: Frame | None = None,
        pose: Pose | None = None,
        *,
        motion: object | None = None,
    ) -> RphScanResult:
        """Detect trees in one scan and fold them into the map.

        `frame` (the camera image) and `motion` are accepted for the common interface and
        not used: RPH has no NDVI, and without a pose the robot is taken as standing still.
        `pose`: base_footprint in a world frame at the scan's middle; every scan of a run
        must come with a pose in one frame, or none (as for TreeMapper)."""
        del frame, motion
        t = scan_mid_time(scan)
        world = self._check_frame(pose, t)
        points = scan.distinct  # dual return: each echo once
        lidar = np.column_stack([points["x"], points["y"], points["z"]]).astype(np.float64)
        T_world_lidar = _world_from_base(pose) @ self.calibration.T_base_lidar
        cloud = lidar @ T_world_lidar[:3, :3].T + T_world_lidar[:3, 3]

        detection = detect(cloud, self.config)
        self.scans += 1
        for key, value in detection.counts.items():
            self.counts[key] += value
        results = self._associate(detection.clusters, t)
        return RphScanResult(
            t=t,
            frame=world,
            clusters=results,
            created=[r.tree_id for r in results if r.outcome == "created"],
            updated=[r.tree_id for r in results if r.outcome == "updated"],
            counts=dict(detection.counts),
        )

    def trees(self) -> list[TrackedTree]:
        """Every tree so far, by id."""
        return [
            TrackedTree(
                tree_id=track.tree_id,
                x=float(track.position[0]),
                y=float(track.position[1]),
                z=float(track.position[2]),
                frame=self.frame or NO_POSE_FRAME,
                width_m=float(track.width),
                height_m=float(track.height),
                ndvi=None,
                observations=track.observations,
                first_seen=track.first_seen,
                last_seen=track.last_seen,
                traits=TRAITS,
            )
            for track in self._tracks
        ]

    def _check_frame(self, pose: Pose | None, t: int) -> str:
        world = NO_POSE_FRAME if pose is None else pose.frame
        if self.frame is None:
            self.frame = world
        elif world != self.frame:
            raise ValueError(
                f"scan at {t} has {'no pose' if pose is None else f'a pose in {world!r}'} but "
                f"this mapper holds its trees in {self.frame!r}: give every scan of a run a "
                "pose in one frame, or none (georeferencing happens after mapping)"
            )
        return world

    def _associate(self, clusters: tuple[Cluster, ...], t: int) -> list[RphClusterResult]:
        gate = self.config.association.gate_m
        pairs = []
        for k, cluster in enumerate(clusters):
            for n, track in enumerate(self._tracks):
                d = math.dist(cluster.position[:2], track.position[:2])
                if d <= gate:
                    pairs.append((d, k, n))
        pairs.sort()  # by distance, ties by detection then tree order: deterministic
        owner: dict[int, int] = {}
        taken: set[int] = set()
        for _, k, n in pairs:
            if k not in owner and n not in taken:
                owner[k] = n
                taken.add(n)
        results = []
        for k, cluster in enumerate(clusters):
            if k in owner:
                track, outcome = self._tracks[owner[k]], "updated"
            else:
                track = _Track(len(self._tracks) + 1, np.zeros(3), 0.0, 0.0, 0, t, t)
                self._tracks.append(track)
                outcome = "created"
            track.add(cluster, t)
            results.append(
                RphClusterResult(
                    cluster.position.copy(),
                    cluster.points,
                    math.nan,
                    track.tree_id,
                    outcome,
                    cluster,
                )
            )
        return results


def _world_from_base(pose: Pose | None) -> np.ndarray:
    T = np.eye(4)
    if pose is None:
        return T
    c, s = math.cos(pose.yaw), math.sin(pose.yaw)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = [pose.x, pose.y, pose.z]
    return T
