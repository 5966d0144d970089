"""The one processing API: scans (with a camera frame and a pose when there are) in,
mapped trees out. The replay and the service both call `TreeMapper.process`.

Deterministic: the same scans, frames and poses give the same trees. Works without a
camera (NDVI left out of the association) and without GNSS (poses in `odom`, georeferenced
later), and without any pose (trees held in the LiDAR frame, moved by the robot's motion
if one is given, else standing still).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from treetraits.drivers.calibration import Calibration
from treetraits.drivers.records import Frame, Scan, take_points
from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.classify import FLOATING, LOW, SMOOTH, THIN, TREE, Votes
from treetraits.pipeline.config import MapperConfig, TraitsConfig
from treetraits.pipeline.detection import Cluster, Detection, GroundModel, StageClock, detect
from treetraits.pipeline.localization.attitude import rotation_zyx
from treetraits.pipeline.localization.pose import Pose
from treetraits.pipeline.localization.utm import wrap_angle
from treetraits.pipeline.projection import scan_mid_time
from treetraits.pipeline.tracking import Motion, Track, Tracker, motion_transform
from treetraits.pipeline.traits import PaperTraits, RobustTraits, new_traits

LIDAR_FRAME = "lidar"


@dataclass(frozen=True)
class ClusterResult:
    """One cluster of the scan and what the tracker made of it."""

    centroid: np.ndarray  # (3,) in the mapper's frame
    num_points: int
    ndvi: float  # NaN without NDVI
    tree_id: int  # after merges: the tree that holds this cluster now
    outcome: str  # "updated", "created", "merged" or "duplicate" (tracking.Decision)
    p_max: float  # NaN when there was no tree to compare with
    entropy: float
    cluster: Cluster  # the detection (base frame): its returns, rings, ground, hull

    @property
    def hull_area(self) -> float:
        return self.cluster.hull_area

    @property
    def hull_volume(self) -> float:
        return self.cluster.hull_volume


@dataclass(frozen=True)
class ScanResult:
    t: int  # the scan's middle, host clock, ns
    frame: str  # the frame of the centroids and the trees: "odom", "utm" or "lidar"
    clusters: list[ClusterResult]
    created: list[int]  # trees started by this scan (and still there)
    updated: list[int]  # trees updated by this scan, or that absorbed another
    merged: list[tuple[int, int]]  # (kept, absorbed) tree ids
    ndvi: str  # "ok", "no_frame" (none given), "no_camera", or fuse_scan's reason
    ground: GroundModel  # the scan's ground (base frame)
    counts: dict[str, int] = field(default_factory=dict)
    stage_ms: dict[str, float] = field(default_factory=dict)
    # Trees finalised by this scan (out of `tracking.retire_m`): their records no longer
    # change, and the mapper keeps only those (`TreeMapper.trees`).
    retired: list[int] = field(default_factory=list)


@dataclass(frozen=True)
class TrackedTree:
    tree_id: int
    x: float
    y: float
    z: float  # centroid height in the frame
    frame: str
    width_m: float
    height_m: float
    ndvi: float | None  # mean over its returns that had NDVI
    observations: int
    first_seen: int  # ns, host clock
    last_seen: int
    traits: str  # "paper" or "robust"
    # "tree", or why it is not one (`pipeline.classify.REASONS`), by its scans' majority
    kind: str = "tree"
    # Its height is measured: a beam that passed over its top (`pipeline.visibility`)
    # brackets the top within `traits.top_tolerance` of it (`_Tree.height_measured`); else its
    # height is a lower bound.
    height_top_seen: bool = False
    # 2: the LiDAR saw the crown from both sides (`sides_seen`); 1: from one side only, so
    # its far side was hidden and the width is a lower bound; None: not judged (RPH).
    width_sides_seen: int | None = None
    # Its cues over its scans (`vegetation.EvidenceSum`): each one's mean (NaN: never
    # measured) and the evidence they weigh (None: no cue measured).
    evidence: float | None = None
    texture_m: float = math.nan
    planar_share: float = math.nan
    intensity: float = math.nan


_MAX_TRUNK_SIGHTINGS = 512
# A ray over a crown's top may pass this far below its highest return and still have
# passed over it: the VLP-16's range noise (+-3 cm) and a scan's pose error.
_RAY_NOISE_M = 0.05
# Where the LiDAR stood when it measured a tree (`_Tree.views`): a new place is kept once
# it is this far from the last one kept. A robot standing still adds nothing, and a quarter
# metre turns the bearing from a tree 2.5 m off the lane by 6 deg at most: the span of the
# bearings, all `sides_seen` asks, is kept to that.
_VIEW_SPACING_M = 0.25
_MAX_VIEWS = 512


@dataclass
class _Tree:
    traits: PaperTraits | RobustTraits
    votes: Votes = field(default_factory=Votes)
    ndvi_sum: float = 0.0
    ndvi_count: int = 0
    # One row per scan that had its top in view (the traits frame): the LiDAR's x, y, z
    # and the rise per metre of the beam above its top (`height_measured`).
    tops: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    # The highest of its own returns in any scan (the traits frame's z): its top is
    # at least that high; and its x-y, where the crown's apex most likely is.
    top_z: float = -math.inf
    top_xy: np.ndarray = field(default_factory=lambda: np.full(2, np.nan))
    # The ground's z under its clusters, one per scan (the traits frame; at most
    # `_MAX_TRUNK_SIGHTINGS`): where its height's foot can be (`height_measured`).
    grounds: np.ndarray = field(default_factory=lambda: np.empty(0))
    # x-y of the trunk axis under its crown, one per scan that saw exactly one (the traits
    # frame, as the outline), N x 2: where the tree stands (`trunk_position`).
    trunks: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    # x, y and heading of the LiDAR at the scans that measured it (the traits frame): the
    # sides its crown was seen from (`sides_seen`).
    views: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    # The record `TreeMapper._tracked` made of it last, with the key it built from the
    # track and the map; None once the tree changed (a cluster, a vote, an absorbed track).
    record: tuple[tuple, TrackedTree] | None = field(default=None, repr=False)
    # Its kind by its votes (`TreeMapper._kind`, asked for every tree every scan), kept
    # until it changes.
    kind_by_votes: str | None = field(default=None, repr=False)

    def changed(self) -> None:
        """A cluster, a vote or an absorbed track is changing it: what was kept goes."""
        self.record = self.kind_by_votes = None

    def add_trunks(self, xy: np.ndarray) -> None:
        """Sightings (N x 2) added; at most `_MAX_TRUNK_SIGHTINGS` are kept."""
        self.trunks = np.concatenate([self.trunks, np.reshape(xy, (-1, 2))])
        while len(self.trunks) >= _MAX_TRUNK_SIGHTINGS:
            # Every other one kept: the places' shares of the sightings stay as they were,
            # and `trunk_position`'s cost stays bounded for a tree seen for minutes.
            self.trunks = self.trunks[::2]

    def add_tops(self, tops: np.ndarray) -> None:
        self.tops = _thinned(self.tops, tops)  # a scan's ray lies close to the next

    def add_grounds(self, z: np.ndarray) -> None:
        self.grounds = np.concatenate([self.grounds, np.ravel(z)])
        if len(self.grounds) >= _MAX_TRUNK_SIGHTINGS:  # every other: the spread stays
            self.grounds = self.grounds[::2]

    def raise_top(self, point: np.ndarray) -> None:
        """A return of its own (x, y, z in the traits frame): its top if the highest yet."""
        if point[2] > self.top_z:
            self.top_z, self.top_xy = float(point[2]), np.array(point[:2], dtype=float)

    def height_measured(self, centre: np.ndarray, height: float, tolerance: float) -> bool:
        """Its `height` known within `tolerance` of it (the traits frame), both ends
        together: its top lies between its highest return (`top_z`) and the rays that
        passed over it; its foot, the ground the height was measured from (`top_z` less
        the height), lies above the lowest ground seen under it (10th percentile of
        `grounds`) by what a height taken from the top of the weeds under a crown is short
        by. The two gaps add up: the height is short by the top's, and by the foot's (each
        alone within 5 %, a broadleaf crown's height came out 6.6 % short).

        The top's bound is one that two scans agree on: the second lowest ray over it. A
        single scan's beam may have passed through a gap in the foliage at the apex, or
        over a crown whose apex it could not see (the part behind its highest return), and
        proves nothing alone: a lobed crown measured from one scan came out 6.5 % short.
        A ray rises with its distance from the LiDAR, so it bounds the crown by a
        different height at each place: the apex is where the tree stands (`centre`, x-y)
        on a regular crown, and off it on a lobed one, where its highest return is
        (`top_xy`); the top's gap is the larger of the two places'."""
        if not len(self.tops) or not len(self.grounds) or not height > 0:
            return False

        def rays_at(place: np.ndarray) -> np.ndarray:
            reach = np.hypot(self.tops[:, 0] - place[0], self.tops[:, 1] - place[1])
            return self.tops[:, 2] + reach * self.tops[:, 3]

        # A ray below its highest return where the tree stands passed over a piece of the
        # crown, the rest of it hidden in that scan or cut off the cluster: it bounds nothing.
        at_centre = rays_at(centre)
        valid = at_centre >= self.top_z - _RAY_NOISE_M
        if np.count_nonzero(valid) < 2:
            return False
        top_gap = 0.0  # a ray within the noise below the highest return: 0
        for rays in (at_centre, rays_at(self.top_xy)):
            second_lowest = np.partition(rays[valid], 1)[1]
            top_gap = max(top_gap, float(second_lowest) - self.top_z)
        foot_gap = max(0.0, self.top_z - height - float(np.percentile(self.grounds, 10)))
        return top_gap + foot_gap <= tolerance * height

    def add_view(self, view: np.ndarray) -> None:
        """The LiDAR's x, y and heading at a scan that measured the tree, unless it stood
        within `_VIEW_SPACING_M` of the last one kept; at most `_MAX_VIEWS` are kept."""
        if len(self.views) and np.hypot(*(self.views[-1, :2] - view[:2])) < _VIEW_SPACING_M:
            return
        self.add_views(view)

    def add_views(self, views: np.ndarray) -> None:
        self.views = _thinned(self.views, views)  # the places along the path stay


def _thinned(kept: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """`rows` appended to `kept` (rows of its width); past `_MAX_VIEWS` rows, every other
    one kept."""
    out = np.concatenate([kept, np.reshape(rows, (-1, kept.shape[1]))])
    return out[::2] if len(out) > _MAX_VIEWS else out


# Verdicts whose tracks take no side in the Voronoi cut (`_Centres`).
UNCLAIMING = (LOW, FLOATING)
# Verdicts of things that are not standing objects (posts, people, vehicles, walls):
# trees, the understorey, crown fragments, and a tree's shape whose surface alone spoke
# against it in one scan (`smooth`: the track decides over its scans, and a dense crown
# the camera sees in some scans only flips between `smooth` and `tree`); the tracker
# merges these with trees. `not_green` stands: the camera saw it and it is no plant (a
# person walking past a crown, merged into it, moved that tree 1.4 m on the twin).
NOT_STANDING = (TREE, *UNCLAIMING, SMOOTH)


class TreeMapper:
    def __init__(
        self,
        config: MapperConfig | None = None,
        calibration: Calibration | None = None,
        *,
        timing: bool = False,
    ):
        self.config = config or MapperConfig()
        self.calibration = calibration or Calibration()
        self.timing = timing
        self.T_base_lidar = np.asarray(self.calibration.T_base_lidar, dtype=float)
        self.T_lidar_base = np.linalg.inv(self.T_base_lidar)
        self.tracker = Tracker(self.config.tracking)
        self.tracker.apart = self._known_apart
        self.frame: str | None = None  # fixed by the first scan
        self._trees: dict[int, _Tree] = {}
        # Finalised trees: their record as it was, and the traits frame it was made in
        # (a later move of the map carries it along; see `trees`).
        self._retired: dict[int, tuple[TrackedTree, np.ndarray]] = {}
        self._last_t: int | None = None
        self._last_pose: Pose | None = None  # for the yaw rate (the outline skips fast turns)
        # The frame the robust traits accumulate in, from the map frame: the world itself
        # when poses are known; without poses the map is the moving LiDAR frame, so the
        # returns are held where the motion says the first scan's LiDAR frame is now.
        self._traits_from_map = np.eye(4)

    def reanchor(self, new_from_old: np.ndarray, frame: str) -> None:
        """Move the whole map into another world frame (`new_from_old`, 4x4 rigid): a run
        mapped in `odom` until its first fix is carried into `utm`, trees and accumulated
        returns alike, and goes on there."""
        self.tracker.move(new_from_old)
        self._traits_from_map = self._traits_from_map @ np.linalg.inv(new_from_old)
        self.frame = frame
        self._last_pose = None

    def process(
        self,
        scan: Scan,
        frame: Frame | None = None,
        pose: Pose | None = None,
        *,
        motion: Motion | None = None,
    ) -> ScanResult:
        """Detect, associate and measure the trees of one scan. `pose`: base_footprint in
        a world frame at the scan's middle; all scans of a run must use the same frame
        (or none). `motion`: used only without poses, for the paper's B v_x prediction."""
        return self.map_detected(self.detect_scan(scan, frame), pose, motion=motion)

    def detect_scan(self, scan: Scan, frame: Frame | None = None) -> DetectedScan:
        """The half of `process` that needs no track: the scan's clusters with their
        measurements and cues (`detect`), NDVI from `frame`. It reads the mapper's
        settings and calibration only, so it may run on another thread while this one
        maps the scan before (`service.survey`'s detection worker)."""
        stage_ms: dict[str, float] | None = {} if self.timing else None
        # Dual returns: each echo once (a single-return scan has no duplicates to drop).
        points = scan.distinct if scan.points["duplicate"].any() else scan.points
        ndvi_reason, ndvi_of = self._ndvi(scan, points, frame)
        detection = detect(points, ndvi_of, self.T_base_lidar, self.config.detection, stage_ms)
        if ndvi_of is not None:
            ndvi_reason = ndvi_of.reason
        return DetectedScan(detection, scan_mid_time(scan), ndvi_reason, stage_ms)

    def map_detected(
        self, detected: DetectedScan, pose: Pose | None = None, *, motion: Motion | None = None
    ) -> ScanResult:
        """The half of `process` that tracks and measures: scans mapped in their order."""
        map_from_base = self._map_from_base(pose, motion, detected.t)
        return self._map(
            detected.detection,
            detected.t,
            map_from_base,
            pose,
            motion,
            detected.ndvi_reason,
            detected.stage_ms,
        )

    def process_detection(
        self, detection: Detection, t: int, pose: Pose, ndvi: str = "no_frame"
    ) -> ScanResult:
        """The mapping half of `process` for clusters detected elsewhere (scan middle `t`,
        `pose` as for `process`): what `bench/scale.py` grows a survey with, where
        detecting a synthetic orchard's points would only time the detection again."""
        stage_ms: dict[str, float] | None = {} if self.timing else None
        map_from_base = self._map_from_base(pose, None, t)
        return self._map(detection, t, map_from_base, pose, None, ndvi, stage_ms)

    def _map(
        self,
        detection: Detection,
        t: int,
        map_from_base: np.ndarray,
        pose: Pose | None,
        motion: Motion | None,
        ndvi_reason: str,
        stage_ms: dict[str, float] | None,
    ) -> ScanResult:
        # m_k in the map frame; the gate compares positions in the LiDAR frame.
        clock = StageClock(stage_ms)
        measurements = self._measurements(detection.clusters, map_from_base)
        base_from_map = np.linalg.inv(map_from_base)
        in_view = self._in_view(base_from_map)
        view_ids = {
            tr.tree_id for tr, seen in zip(self.tracker.tracks, in_view, strict=True) if seen
        }
        standing = np.array([c.verdict not in NOT_STANDING for c in detection.clusters])
        step = self.tracker.step(
            measurements, self.T_lidar_base @ base_from_map, in_view, t, standing
        )
        clock.lap("tracking")

        # Traits: each cluster to the tree it went to; then trees merged this scan.
        traits_from_base = self._traits_from_map @ map_from_base
        # Where the LiDAR stands this scan and the robot's heading, in the traits frame (the
        # world with poses, the dead-reckoned frame without): where each tree it measures
        # is seen from (`sides_seen`).
        lidar = traits_from_base[:2, :3] @ self.T_base_lidar[:3, 3] + traits_from_base[:2, 3]
        heading = math.atan2(traits_from_base[1, 0], traits_from_base[0, 0])
        view = np.array([lidar[0], lidar[1], heading])
        centres = _Centres(
            self.tracker.tracks,
            self._traits_from_map,
            self._claiming(),
            {tree_id for tree_id, tree in self._trees.items() if self._kind(tree) == THIN},
        )
        # World points for the outline: not while turning fast; and for the paper's traits
        # (which use the outline for the centre only) not without a pose or a motion, where
        # the cells could not follow the robot and the Kalman state is the better centre.
        steady = self._steady(pose)
        placeable = pose is not None or motion is not None
        pose_sigma = _position_sigma(pose)
        for cluster, decision in zip(detection.clusters, step.decisions, strict=True):
            if decision.outcome == "duplicate":
                continue
            tree = self._changing(decision.tree_id)
            tree.votes.add(cluster.verdict, cluster.cues, cluster.evidence)
            if cluster.verdict == LOW:
                # The understorey (weeds, a drip line's span, a skirt alone) adds nothing
                # to a tree: lower than any tree, it can give it no height, only a
                # drip line's length as its width or a weed's NDVI.
                continue
            outline = steady and (placeable or isinstance(tree.traits, RobustTraits))
            self._observe(
                tree,
                cluster,
                traits_from_base,
                decision.tree_id,
                centres,
                outline,
                pose_sigma,
                view,
            )
        for kept, absorbed in step.merged:
            self._absorb(kept, absorbed)
        self._mark_standing({d.tree_id for d in step.decisions})
        merged = step.merged + self._merge_outlines(step.decisions, view_ids)
        alias = dict((absorbed, kept) for kept, absorbed in merged)
        decisions = [
            replace(d, tree_id=_resolve(alias, d.tree_id)) if d.tree_id in alias else d
            for d in step.decisions
        ]
        retired = self._retire(map_from_base)
        clock.lap("traits")

        results = [
            ClusterResult(
                m[:3].copy(),
                c.num_points,
                c.ndvi,
                d.tree_id,
                d.outcome,
                float(d.p_max),
                float(d.entropy),
                c,
            )
            for c, m, d in zip(detection.clusters, measurements, decisions, strict=True)
        ]
        created = [d.tree_id for d in decisions if d.outcome == "created"]
        updated = [d.tree_id for d in decisions if d.outcome in ("updated", "merged")]
        return ScanResult(
            t=t,
            frame=self.frame,
            clusters=results,
            created=created,
            updated=list(dict.fromkeys(updated + [kept for kept, _ in merged])),
            merged=merged,
            ndvi=ndvi_reason,
            ground=detection.ground,
            counts={**detection.counts, "candidates": step.candidates},
            stage_ms=stage_ms or {},
            retired=retired,
        )

    def trees(self, ids: set[int] | None = None, *, retired: bool = True) -> list[TrackedTree]:
        """Every tree, by id, with the configured trait method's values: those in memory
        and (`retired`) those finalised. `ids`: only these."""
        back = np.linalg.inv(self._traits_from_map)
        out = [
            self._tracked(track, back)
            for track in self.tracker.tracks
            if ids is None or track.tree_id in ids
        ]
        if retired:  # `ids` looked up, not scanned for: the finalised trees are many
            wanted = self._retired if ids is None else (i for i in ids if i in self._retired)
            for tree_id in wanted:
                tree, traits_from_map = self._retired[tree_id]
                out.append(self._moved(tree, traits_from_map, back))
        return sorted(out, key=lambda tree: tree.tree_id)

    def _tracked(self, track, back: np.ndarray) -> TrackedTree:
        """The tree's record; the one made before while neither the tree (`_Tree.record`)
        nor its track's estimate, scans and times, nor the map's frame changed since: the
        store asks for every tree in memory after every scan, most of them not seen in it."""
        tree = self._trees[track.tree_id]
        made_of = (
            track.state[:3].tobytes(),
            track.observations,
            track.first_seen,
            track.last_seen,
            self.frame,
            self._traits_from_map.tobytes(),
        )
        if tree.record is not None and tree.record[0] == made_of:
            return tree.record[1]
        record = self._record(track, tree, back)
        tree.record = (made_of, record)
        return record

    def _record(self, track, tree: _Tree, back: np.ndarray) -> TrackedTree:
        position = track.state[:3]
        centre = tree.traits.centre()
        trunk = self._trunk(track, tree)
        if trunk is not None:
            centre = trunk
        if centre is None:  # where the track is, in the traits frame (as the views)
            rotation, shift = self._traits_from_map[:2, :3], self._traits_from_map[:2, 3]
            here = rotation @ position + shift
        else:
            here = centre
        sides = sides_seen(here, tree.views)
        height = float(tree.traits.height)
        top_measured = tree.height_measured(here, height, self.config.traits.top_tolerance)
        x, y = position[0], position[1]
        if centre is not None:  # traits frame -> the mapper's frame
            x, y = back[:2, :2] @ centre + back[:2, 3]
        ndvi = tree.ndvi_sum / tree.ndvi_count if tree.ndvi_count else None
        cues = tree.votes.evidence
        evidence = cues.evidence()
        return TrackedTree(
            tree_id=track.tree_id,
            x=float(x),
            y=float(y),
            z=float(position[2]),
            frame=self.frame or LIDAR_FRAME,
            width_m=float(tree.traits.width),
            height_m=float(tree.traits.height),
            ndvi=ndvi,
            observations=track.observations,
            first_seen=track.first_seen,
            last_seen=track.last_seen,
            traits=tree.traits.method,
            kind=self._kind(tree),
            height_top_seen=top_measured,
            width_sides_seen=sides,
            evidence=evidence.total if evidence.measured else None,
            texture_m=cues.mean("texture"),
            planar_share=cues.mean("planar"),
            intensity=cues.mean("intensity"),
        )

    def _moved(self, tree: TrackedTree, traits_from_map: np.ndarray, back: np.ndarray):
        """A finalised tree in the mapper's frame now: as it was, unless the map moved
        since (no poses, or odom carried into utm)."""
        if traits_from_map is self._traits_from_map and tree.frame == (self.frame or LIDAR_FRAME):
            return tree
        now_from_then = back @ traits_from_map
        x, y, z = now_from_then[:3, :3] @ (tree.x, tree.y, tree.z) + now_from_then[:3, 3]
        return replace(tree, x=float(x), y=float(y), z=float(z), frame=self.frame or LIDAR_FRAME)

    def _retire(self, map_from_base: np.ndarray) -> list[int]:
        """Finalise the trees farther than `tracking.retire_m` from the robot: out of view
        for good (the config checks the distance against the view's reach), so nothing of
        this run changes them any more; memory and a scan's cost then follow the trees
        around the robot, not the survey's size."""
        limit = self.config.tracking.retire_m
        if limit <= 0 or not self.tracker.tracks:
            return []
        xy = self.tracker.positions()[:, :2]
        far = np.hypot(*(xy - map_from_base[:2, 3]).T) > limit
        if not far.any():
            return []
        back = np.linalg.inv(self._traits_from_map)
        gone = [tr for tr, out in zip(self.tracker.tracks, far, strict=True) if out]
        for track in gone:
            self._retired[track.tree_id] = (self._tracked(track, back), self._traits_from_map)
            del self._trees[track.tree_id]
        ids = {tr.tree_id for tr in gone}
        self.tracker.drop(ids)
        return sorted(ids)

    # --- steps -------------------------------------------------------------------------

    def _map_from_base(self, pose: Pose | None, motion: Motion | None, t: int) -> np.ndarray:
        """T_map_base for this scan; fixes the run's frame on the first scan."""
        frame = LIDAR_FRAME if pose is None else pose.frame
        if self.frame is None:
            self.frame = frame
        elif frame != self.frame:
            raise ValueError(
                f"scan at {t} has {'no pose' if pose is None else f'a pose in {frame!r}'} but "
                f"this mapper holds its trees in {self.frame!r}: give every scan of a run a "
                f"pose in one frame, or none (georeferencing happens after mapping)"
            )
        if pose is not None:
            self._last_t = t
            out = np.eye(4)
            out[:3, :3] = rotation_zyx(pose.roll, pose.pitch, pose.yaw)
            out[:3, 3] = (pose.x, pose.y, pose.z)
            return out
        # No pose: the map is the LiDAR frame of this scan; move the trees by the motion.
        if motion is not None and self._last_t is not None:
            dt = (t - self._last_t) / 1e9
            new_from_old = motion_transform(motion, dt, self.T_base_lidar)
            self.tracker.move(new_from_old)
            self._traits_from_map = self._traits_from_map @ np.linalg.inv(new_from_old)
        self._last_t = t
        return self.T_lidar_base.copy()

    def _ndvi(self, scan: Scan, points: np.ndarray, frame: Frame | None):
        if frame is None:
            return "no_frame", None
        cal = self.calibration
        if cal.camera is None or cal.T_camera_lidar is None:
            return "no_camera", None
        return "ok", _NdviOf(scan, points, frame, cal)

    def _measurements(self, clusters: list[Cluster], map_from_base: np.ndarray) -> np.ndarray:
        out = np.empty((len(clusters), 5))
        for row, cluster in zip(out, clusters, strict=True):
            row[:3] = map_from_base[:3, :3] @ cluster.centroid + map_from_base[:3, 3]
            row[3] = cluster.num_points
            row[4] = cluster.ndvi
        return out

    def _in_view(self, base_from_map: np.ndarray) -> np.ndarray:
        """Trees whose centre lies in the crop box grown by the view margin."""
        if not self.tracker.tracks:
            return np.zeros(0, dtype=bool)
        crop, margin = self.config.detection.crop, self.config.tracking.view_margin_m
        xy = (self.tracker.positions() @ base_from_map[:3, :3].T + base_from_map[:3, 3])[:, :2]
        return (
            (xy[:, 0] >= crop.x_m[0] - margin)
            & (xy[:, 0] <= crop.x_m[1] + margin)
            & (xy[:, 1] >= crop.y_m[0] - margin)
            & (xy[:, 1] <= crop.y_m[1] + margin)
        )

    def _steady(self, pose: Pose | None) -> bool:
        """Not turning faster than traits.max_yaw_rate since the previous scan's pose."""
        last, self._last_pose = self._last_pose, pose
        if pose is None or last is None or pose.t <= last.t:
            return True
        yaw_rate = abs(wrap_angle(pose.yaw - last.yaw)) / ((pose.t - last.t) / 1e9)
        return yaw_rate <= self.config.traits.max_yaw_rate

    def _observe(
        self,
        tree: _Tree,
        cluster: Cluster,
        traits_from_base,
        tree_id,
        centres,
        outline: bool,
        pose_sigma: float | None,
        view: np.ndarray,
    ) -> None:
        # A cluster that took in a piece of a neighbour's crown (touching crowns whose
        # trunk was hidden for a few scans) gives it back before anything is measured.
        world = cluster.points @ traits_from_base[:3, :3].T
        world += traits_from_base[:3, 3]  # in place: the same sums, no second array
        own = centres.nearest_is(world[:, :2], tree_id)
        points, ring, world = _kept(own, cluster.points, cluster.ring, world)
        # The ground under the cluster, carried into the world with the full attitude.
        foot = np.array([cluster.centroid[0], cluster.centroid[1], cluster.ground_z])
        ground_here = float(traits_from_base[2, :3] @ foot + traits_from_base[2, 3])
        if len(points):  # returns of its own were measured from here
            tree.add_view(view)
            tree.raise_top(world[int(np.argmax(world[:, 2]))])
            tree.add_grounds(np.array([ground_here]))
        world_points = ground_world = None
        if outline:  # both methods keep the outline in the world frame (its centre)
            world_points, ground_world = world, ground_here
            if cluster.trunk is not None:
                trunk = traits_from_base[:2, :3] @ cluster.trunk + traits_from_base[:2, 3]
                if centres.trunk_is(trunk, tree_id):  # not a neighbour's
                    tree.add_trunks(trunk)
        tree.traits.observe(points, ring, cluster.ground_z, world_points, ground_world, pose_sigma)
        # The cluster's top in view counts for this tree if that top is its own.
        if cluster.top_seen and own[int(np.argmax(cluster.points[:, 2]))]:
            tree.add_tops(self._top_ray(cluster, traits_from_base))
        if np.isfinite(cluster.ndvi):
            tree.ndvi_sum += cluster.ndvi * len(cluster.points)
            tree.ndvi_count += len(cluster.points)

    def _top_ray(self, cluster: Cluster, traits_from_base: np.ndarray) -> np.ndarray:
        """`_Tree.tops`' row of a cluster whose top was in view: where the LiDAR stood and
        the rise per metre of the beam above the top, in the traits frame (z up)."""
        rotation, shift = traits_from_base[:3, :3], traits_from_base[:3, 3]
        lidar = rotation @ self.T_base_lidar[:3, 3] + shift
        beam = rotation @ cluster.beam_above
        rise = beam[2] / max(math.hypot(beam[0], beam[1]), 1e-9)
        return np.array([lidar[0], lidar[1], lidar[2], rise])

    def _merge_outlines(self, decisions, view_ids: set[int]) -> list[tuple[int, int]]:
        """Trees whose accumulated outlines share a centre (closer than the tracker's
        merge_distance_m) are one tree seen as two, unless their trunks are known apart
        (`_known_apart`: a hedgerow's touching crowns pull their outlines' centres
        together, 1.47 m apart for trunks 2.75 m apart): a crown wider than the association
        gate, seen from both lanes, has its returns' centroids (the Kalman states) a crown
        apart on either side, while each side's outline is centred on the trunk. The older
        tree keeps its id, as in the tracker's merge. A tree with no outline yet (no cell
        hit in `min_hits` scans: a sparse piece of a crown's far side, seen through it in
        a few scans far apart) is where its track is, as it is reported; not the
        understorey's (never outlined): a weed under a crown is no part of the tree."""
        limit = self.config.tracking.merge_distance_m
        touched = {d.tree_id for d in decisions if d.outcome != "duplicate"}
        if limit <= 0 or not touched:
            return []
        # Candidates: the trees this scan touched and those in view before it (a tree out
        # of view is not beside a touched one): the cost stays with the trees around.
        rotation, shift = self._traits_from_map[:2, :3], self._traits_from_map[:2, 3]
        tracks = {track.tree_id: track for track in self.tracker.tracks}
        centres = {}
        for tree_id, tree in self._trees.items():
            if (tree_id in view_ids or tree_id in touched) and tree_id in tracks:
                if (centre := tree.traits.centre()) is not None:
                    centres[tree_id] = centre
                elif self._kind(tree) not in UNCLAIMING:
                    centres[tree_id] = rotation @ tracks[tree_id].state[:3] + shift
        merged = []
        placed = None  # (ids, N x 2 centres) in the dict's order, made when first needed
        for tree_id in sorted(touched):
            own = centres.get(tree_id)
            if own is None:
                continue
            if placed is None:
                placed = list(centres), np.array(list(centres.values())).reshape(-1, 2)
            # Every centre's distance in one hypot (the same values as one at a time).
            ids, xy = placed
            close = np.hypot(xy[:, 0] - own[0], xy[:, 1] - own[1]) < limit
            near = [
                other
                for other in (ids[i] for i in np.flatnonzero(close))
                if other != tree_id
                and tracks[other].standing == tracks[tree_id].standing
                and not self._known_apart(tracks[other], tracks[tree_id])
            ]
            if not near:
                continue
            keep, drop = min(tree_id, near[0]), max(tree_id, near[0])
            self.tracker.fold(keep, drop)
            self._absorb(keep, drop)
            centres.pop(drop)
            if (centre := self._trees[keep].traits.centre()) is not None:
                centres[keep] = centre
            placed = None  # the centres changed
            merged.append((keep, drop))
        return merged

    def _known_apart(self, keep: Track, drop: Track) -> bool:
        """Two tracks are two trees when each one's trunk is known (`trunk_position`) and
        the two stand `merge_distance_m` apart or more. A track's state follows the
        returns' centroid, which moves with the part of a crown in view: along a hedgerow,
        whose touching crowns join in the scans before their trunks cut them, a tree's
        state drifted 1.3 m towards the next, 2.75 m away, and the tracker's merge took
        that tree. Trunks only: a crown fragment's outline centre says where the piece
        seen lies, not where a tree stands (a clumped hedgerow's fragment 1.7 m off its
        crown, kept apart by its outline, became a tree)."""
        trunks = []
        for track in (keep, drop):
            tree = self._trees.get(track.tree_id)
            trunk = None if tree is None else self._trunk(track, tree)
            if trunk is None:
                return False
            trunks.append(trunk)
        gap = trunks[0] - trunks[1]
        return math.hypot(gap[0], gap[1]) >= self.config.tracking.merge_distance_m

    def _trunk(self, track: Track, tree: _Tree) -> np.ndarray | None:
        """Where the track's tree stands by its trunk (traits frame; `trunk_position`
        with its outline as the reach), or None: what `_record` reports when known."""
        return trunk_position(
            tree.trunks,
            self.config.traits,
            track.observations,
            tree.traits.centre(),
            tree.traits.width,
        )

    def _claiming(self) -> set[int]:
        """The tracks that take their side in the Voronoi cut: seen in
        `tracking.claim_min_scans` scans, and not the understorey's or a fragment's."""
        seen = {
            track.tree_id
            for track in self.tracker.tracks
            if track.observations >= self.config.tracking.claim_min_scans
        }
        return {
            tree_id
            for tree_id, tree in self._trees.items()
            if tree_id in seen and self._kind(tree) not in UNCLAIMING
        }

    def _mark_standing(self, tree_ids: set[int]) -> None:
        """Each touched track stands (a post, a person...) as its votes now say: a tree's
        track born of a cluster that looked like a post for one scan joins it again."""
        for track in self.tracker.tracks:
            if track.tree_id in tree_ids and track.tree_id in self._trees:
                track.standing = self._kind(self._trees[track.tree_id]) not in NOT_STANDING

    def _kind(self, tree: _Tree) -> str:
        """ "tree", or why not, by the majority of its scans' verdicts."""
        if tree.kind_by_votes is None:
            classify = self.config.detection.classify
            tree.kind_by_votes = tree.votes.kind(
                classify.min_tree_share, classify.min_tree_share_all
            )
        return tree.kind_by_votes

    def _changing(self, tree_id: int) -> _Tree:
        """The tree of this id (a new one if there is none), about to be changed."""
        tree = self._trees.get(tree_id)
        if tree is None:  # not setdefault: it would build a tree's traits at every call
            tree = self._trees[tree_id] = _Tree(new_traits(self.config.traits))
        tree.changed()
        return tree

    def _absorb(self, kept: int, absorbed: int) -> None:
        gone = self._trees.pop(absorbed, None)
        if gone is None:
            return
        tree = self._changing(kept)
        tree.traits.absorb(gone.traits)
        tree.votes.absorb(gone.votes)
        tree.ndvi_sum += gone.ndvi_sum
        tree.ndvi_count += gone.ndvi_count
        tree.add_tops(gone.tops)
        tree.raise_top(np.array([*gone.top_xy, gone.top_z]))
        tree.add_grounds(gone.grounds)
        tree.add_trunks(gone.trunks)
        tree.add_views(gone.views)


# Both sides of a crown in view (`sides_seen`). A crown's width across its row is whole
# only when the LiDAR faced both of its sides: from one lane it faces the near side, and
# the far half of the crown, across the row, stands behind the near half (a citrus canopy
# lets few beams through), so what is measured across the row is what stands out towards
# that lane. The row's direction is the robot's own: it drives along the rows, so the mean
# of its headings (as an axis: a lane driven either way is the same row) over the scans
# that measured the tree. The LiDAR stood on a side of the row's line through the tree's
# centre when its bearing from the centre is at least SIDES_MARGIN_DEG off that line; both
# sides, when it did so on each. The margin: the centre is an estimate, and a crown seen
# from one side with no trunk sighted has its outline's centre pulled toward that side, by
# up to a quarter of its width (0.7 m for a 2.8 m crown). A LiDAR on the row's own line
# (at the headland, looking down the row: it faces the crown's end, neither side) then
# reads as on the far side by atan(0.7 / range), 8 deg at 5 m; 10 deg keeps such a view
# from counting, while a lane beside the row (2.5 m off its line in a 5 m grid) puts the
# LiDAR beyond 10 deg everywhere within 14 m of the tree along it.
SIDES_MARGIN_DEG = 10.0


def row_direction(headings: np.ndarray) -> float:
    """The axis the robot drove along (rad): the mean of `headings` as axes (each angle
    doubled, averaged as a unit vector, halved), so driving a lane either way counts the
    same; 0 when they cancel out (a robot circling the tree, seen from every side)."""
    doubled = 2 * np.asarray(headings, dtype=float)
    return 0.5 * math.atan2(float(np.sin(doubled).sum()), float(np.cos(doubled).sum()))


def sides_seen(centre: np.ndarray, views: np.ndarray, margin_deg: float = SIDES_MARGIN_DEG) -> int:
    """2 when the LiDAR's places `views` (N x 3: x, y and the robot's heading, rad; the
    frame of `centre`, a tree's x-y) lie on both sides of the row's line through the
    centre (`row_direction` of the headings), each at least `margin_deg` off that line as
    seen from the centre; else 1 (one side, or no place at all)."""
    views = np.reshape(views, (-1, 3))
    if not len(views):
        return 1
    offsets = views[:, :2] - np.asarray(centre, dtype=float)[:2]
    across = np.sin(np.arctan2(offsets[:, 1], offsets[:, 0]) - row_direction(views[:, 2]))
    least = math.sin(math.radians(margin_deg))  # sin: off the line on that side by >= margin
    return 2 if (across >= least).any() and (across <= -least).any() else 1


def trunk_position(
    trunks: np.ndarray | list[tuple[float, float]],
    config: TraitsConfig,
    scans: int = 0,
    crown_centre: np.ndarray | None = None,
    crown_width: float = float("nan"),
) -> np.ndarray | None:
    """Where a tree stands: the mean of the trunk sightings (x-y, one per scan) that lie
    within `trunk_agree_m` of the best supported place, when those are at least
    `trunk_min_scans`, more than half of all its sightings and at least
    `trunk_min_share` of the `scans` that observed the tree; else None (the crown
    outline's centre stands in). A trunk is one place seen again scan after scan, while
    a weed clump or a neighbour's trunk taken for it is seen now and then, elsewhere.
    With the crown's outline (`crown_centre`, `crown_width`), that place must also lie
    under the crown: within `trunk_reach_share` of the width from its centre."""
    if config.trunk_min_scans <= 0 or len(trunks) < config.trunk_min_scans:
        return None
    xy = np.asarray(trunks, dtype=float).reshape(-1, 2)
    candidates = _crowded_places(xy, config.trunk_agree_m)
    gaps = candidates[:, None, :] - xy[None, :, :]
    close = np.hypot(gaps[..., 0], gaps[..., 1]) <= config.trunk_agree_m
    support = close.sum(axis=1)
    best = int(np.argmax(support))
    agreeing = int(support[best])
    if agreeing < max(config.trunk_min_scans, config.trunk_min_share * scans):
        return None
    if 2 * agreeing <= len(xy):
        return None
    # np.mean's own steps (one sum, one division) without its checks: the same bytes.
    position = np.add.reduce(xy[close[best]], axis=0) / agreeing
    outlined = crown_centre is not None and np.isfinite(crown_width)
    if outlined and np.hypot(*(position - crown_centre)) > config.trunk_reach_share * crown_width:
        return None
    return position


def _crowded_places(xy: np.ndarray, cell: float, places: int = 8) -> np.ndarray:
    """The mean sighting of each of the `places` grid cells (of size `cell`) holding the
    most sightings: where the best supported place can be, found in O(n log n) (a tree
    seen for minutes has hundreds of sightings, and the mapper asks every scan)."""
    return _cell_means(kernel_layout(xy), float(cell), places)


@kernel
def _cell_means(xy: np.ndarray, cell: float, places: int) -> np.ndarray:
    """`_crowded_places` compiled, NumPy's steps: the cells (floor, int64, one key per
    cell, |cell| < 2^31) grouped in key order, the `places` fullest by a stable sort
    (ties: the lower key), each one's sightings summed in their order from 0.0 (as
    np.bincount's weights) and divided by their count."""
    n = xy.shape[0]
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        column, row = np.floor(xy[i, 0] / cell), np.floor(xy[i, 1] / cell)
        keys[i] = (np.int64(column) << 32) + np.int64(row)
    order = np.argsort(keys)  # the groups only: the same in any sort
    group = np.empty(n, dtype=np.int64)
    groups = 0
    for k in range(n):
        if k > 0 and keys[order[k]] != keys[order[k - 1]]:
            groups += 1
        group[order[k]] = groups
    groups = groups + 1 if n else 0
    counts = np.zeros(groups, dtype=np.int64)
    sums = np.zeros((groups, 2))
    for i in range(n):
        counts[group[i]] += 1
        sums[group[i], 0] += xy[i, 0]
        sums[group[i], 1] += xy[i, 1]
    top = np.argsort(-counts, kind="mergesort")[:places]
    out = np.empty((top.shape[0], 2))
    for r in range(top.shape[0]):
        out[r, 0] = sums[top[r], 0] / np.float64(counts[top[r]])
        out[r, 1] = sums[top[r], 1] / np.float64(counts[top[r]])
    return out


def _position_sigma(pose: Pose | None) -> float | None:
    """The pose's position sigma (m, the larger axis of its x-y covariance); None without a
    pose or in `odom`, where the covariance says nothing of where the world frame is."""
    if pose is None or pose.frame != "utm":
        return None
    block = np.asarray(pose.covariance, dtype=float)[:2, :2]
    return float(np.sqrt(max(np.linalg.eigvalsh(block).max(), 0.0)))


def _kept(own: np.ndarray, *arrays: np.ndarray) -> list[np.ndarray]:
    """The rows of each array where `own` holds (the arrays themselves, C-contiguous as
    a selection would be, when it holds everywhere: the usual cluster with no neighbour's
    piece). `compress` copies rows as blocks; a boolean index copies them value by value
    (3x the time on a cluster's returns)."""
    if own.all():
        return [np.ascontiguousarray(array) for array in arrays]
    return [array.compress(own, axis=0) for array in arrays]


def _resolve(alias: dict[int, int], tree_id: int) -> int:
    while tree_id in alias:
        tree_id = alias[tree_id]
    return tree_id


class _Centres:
    """The tracked trees' x-y centres in the traits frame (their Kalman states), as
    arrays: the Voronoi cut compares a cluster with its neighbours at array speed."""

    def __init__(self, tracks, traits_from_map: np.ndarray, claiming: set[int], thin: set[int]):
        self.ids = np.array([tr.tree_id for tr in tracks], dtype=np.int64)
        self.rows: dict[int, int] = {}  # each id's first row
        for row, tree_id in enumerate(self.ids.tolist()):
            self.rows.setdefault(tree_id, row)
        # Which tracks take their side of the cut: trees, posts, people, walls. The
        # understorey's (a weed, a drip line's span under a crown) and a crown fragment's
        # are no claim on the foliage above or around them.
        self.claims = np.array([tr.tree_id in claiming for tr in tracks], dtype=bool)
        self.thin = np.array([tr.tree_id in thin for tr in tracks], dtype=bool)
        states = np.array([tr.state[:3] for tr in tracks]).reshape(-1, 3)
        # Row by row as `R @ p + t` for each tree, so the values are those of one at a time.
        self.xy = np.array(
            [traits_from_map[:2, :3] @ p + traits_from_map[:2, 3] for p in states]
        ).reshape(-1, 2)

    def nearest_is(self, xy: np.ndarray, tree_id: int) -> np.ndarray:
        """Points nearer (x-y) to this tree's centre than to any other claiming object's:
        a cluster that took in a piece of a neighbour's crown, a post or a person gives it
        back (a Voronoi cut), so it widens neither this tree's traits nor its outline."""
        return self._nearest_is(xy, tree_id, self.claims)

    def trunk_is(self, xy: np.ndarray, tree_id: int) -> bool:
        """A trunk sighting (x-y) is this tree's, not a neighbour's: nearer to this tree's
        centre than to any other claiming object's but a thin one's. A thin object where a
        tree's trunk is seen is that trunk seen alone, apart from its crown (a crown
        leaning or lobed away from its trunk: its centre is off the trunk, while the
        trunk-alone object's centre is on it, and it would take every later sighting);
        a post beside a trunk, taken for it now and then, is outvoted in
        `trunk_position`."""
        return bool(self._nearest_is(xy[None], tree_id, self.claims & ~self.thin)[0])

    def _nearest_is(self, xy: np.ndarray, tree_id: int, claims: np.ndarray) -> np.ndarray:
        own = self.xy[self.rows[tree_id]]
        # The points' squared distances to this centre and its reach in one compiled pass;
        # the centres (a few) by NumPy.
        points = kernel_layout(xy)
        own_d2, reach = _own_distances(points, own[0], own[1])
        gap = self.xy - own
        near = claims & (self.ids != tree_id) & (np.hypot(gap[:, 0], gap[:, 1]) < 2 * reach)
        if not near.any():
            return np.ones(len(xy), dtype=bool)
        return _nearer(points, own_d2, kernel_layout(self.xy[near]))


@kernel
def _own_distances(xy: np.ndarray, x0: float, y0: float) -> tuple[np.ndarray, float]:
    """Squared x-y distances to (x0, y0) as dx * dx + dy * dy, and the square root of the
    largest (NaN if one is NaN, as NumPy's max; 0 without points)."""
    n = xy.shape[0]
    d2 = np.empty(n)
    top, nan = -np.inf, False
    for i in range(n):
        dx, dy = xy[i, 0] - x0, xy[i, 1] - y0
        d2[i] = dx * dx + dy * dy
        if d2[i] != d2[i]:
            nan = True
        elif d2[i] > top:
            top = d2[i]
    if n == 0:
        return d2, 0.0
    return d2, np.nan if nan else np.sqrt(top)


@kernel
def _nearer(xy: np.ndarray, own_d2: np.ndarray, others: np.ndarray) -> np.ndarray:
    """Per point: `own_d2` <= its least squared distance to `others` (False where a NaN
    is involved, as NumPy's min and <= give)."""
    out = np.empty(xy.shape[0], dtype=np.bool_)
    for i in range(xy.shape[0]):
        least, nan = np.inf, False
        for j in range(others.shape[0]):
            dx, dy = xy[i, 0] - others[j, 0], xy[i, 1] - others[j, 1]
            d2 = dx * dx + dy * dy
            if d2 != d2:
                nan = True
            elif d2 < least:
                least = d2
        out[i] = not nan and own_d2[i] <= least
    return out


@warm_up
def compile_kernels() -> None:
    """The Voronoi cut's and the trunk's kernels compiled for x-y points (float64, C
    order): a cluster's, a tree's trunk sightings."""
    xy = np.array([[0.0, 1.0], [2.0, 0.5]])
    own_d2, _ = _own_distances(xy, 0.0, 0.0)
    _nearer(xy, own_d2, np.array([[1.0, 1.0]]))
    _cell_means(xy, 0.3, 8)


class DetectedScan(NamedTuple):
    """One scan detected (`TreeMapper.detect_scan`), waiting to be mapped."""

    detection: Detection
    t: int  # the scan's middle (host clock, ns)
    ndvi_reason: str
    stage_ms: dict[str, float] | None


class _NdviOf:
    """Per-point NDVI on demand: `detect` asks only for the points that need it (those
    above the plane), so only they are projected. Remembers fuse_scan's reason."""

    def __init__(self, scan: Scan, points: np.ndarray, frame: Frame, calibration: Calibration):
        self.scan, self.points, self.frame, self.calibration = scan, points, frame, calibration
        self.reason = "ok"

    def __call__(self, index: np.ndarray) -> np.ndarray:
        from treetraits.pipeline.fusion import MAPPER_REDUCTION, fuse_scan

        sub = replace(self.scan, points=take_points(self.points, index))
        fused = fuse_scan(
            sub, [self.frame], self.calibration, keep_ndvi_frame=False, reduction=MAPPER_REDUCTION
        )
        self.reason = fused.reason
        return np.asarray(fused.ndvi, dtype=float)
