"""Clusters to trees: one Kalman filter per tree and the paper's probabilistic association
(Algorithm 1, l.10-23).

The state is m = [x, y, z, num_points, mean NDVI] with F = H = Q = I5, R = 0.1 I5 and a
new tree at x = m_k, P = I5. For each cluster k and tree j: the innovation m_k - H x_j,
normalised to a percentage change, its Mahalanobis distance d under S = H P H^T + R,
p = exp(-0.1 d). A cluster may join a tree when p > th_p and the entropy (log base M) of
its normalised probabilities is < th_H (the paper's gate); clusters and trees are then
paired by one global assignment per scan on the cost d over the gated pairs (the paper
takes each cluster's most probable tree, which lets two clusters claim one tree while
another goes without). A gated cluster left without a tree is a piece of a tree that
took another (dropped); an ungated one starts a tree.

Trees live in a "map" frame: the world (odom/utm) when poses are known, where standing
trees do not move; else the LiDAR frame, moved every scan by the robot's motion (the
paper's B v_x). The percentage is always taken in the LiDAR frame, as in the paper.
How each vague point is read is written out in docs/pipeline.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from treetraits.pipeline.config import TrackingConfig

DIM = 5
NDVI = 4  # index of the NDVI component
_BITS = 1 << np.arange(DIM)
# np.eye(DIM), made once: a filter's matrices are copies or products of it (np.eye
# itself costs as much as the rest of starting a track).
_EYE = np.eye(DIM)
_LARGEST = np.finfo(float).max


@dataclass(frozen=True)
class Motion:
    """Forward speed (m/s) and yaw rate (rad/s) of the robot, for the paper's B v_x
    prediction when no pose is known."""

    v_x: float
    omega: float = 0.0


def motion_transform(motion: Motion, dt_s: float, T_base_lidar: np.ndarray) -> np.ndarray:
    """T_new_old of the LiDAR frame after driving `motion` for `dt_s`: a standing tree at
    p (old LiDAR frame) is at T_new_old @ p now. For omega = 0 this is x <- x - B v_x with
    B = [cos(theta) dt, sin(theta) dt] and theta = 0, the robot's heading in its own
    frame; with a turn, the chord of the arc and the rotation."""
    dtheta = motion.omega * dt_s
    step = motion.v_x * dt_s
    c, s = math.cos(dtheta), math.sin(dtheta)
    old_from_new_base = np.eye(4)
    old_from_new_base[:2, :2] = [[c, -s], [s, c]]
    old_from_new_base[:2, 3] = (step * math.cos(dtheta / 2), step * math.sin(dtheta / 2))
    lidar_from_base = np.linalg.inv(T_base_lidar)
    old_from_new = lidar_from_base @ old_from_new_base @ T_base_lidar
    return np.linalg.inv(old_from_new)


def normalised_innovation(
    measured: np.ndarray,
    predicted: np.ndarray,
    measured_sensor: np.ndarray,
    predicted_sensor: np.ndarray,
    config: TrackingConfig,
) -> np.ndarray:
    """The "percentage change" of m_k against H x_j, K x M x 5.

    Each component's difference over the size of the predicted value, |H x_j| (at least
    the component's floor), times `config.percent`. Positions are compared in the LiDAR
    frame (`*_sensor`, K x 3 and M x 3) as in the paper, counts and NDVI as they are.
    """
    floor = np.asarray(config.floor, dtype=float)
    diff = np.empty((len(measured), len(predicted), DIM))
    diff[:, :, :3] = measured_sensor[:, None, :] - predicted_sensor[None, :, :]
    diff[:, :, 3:] = measured[:, None, 3:] - predicted[None, :, 3:]
    scale = np.empty((len(predicted), DIM))
    scale[:, :3] = np.abs(predicted_sensor)
    scale[:, 3:] = np.abs(predicted[:, 3:])
    return config.percent * diff / np.maximum(scale, floor)[None, :, :]


def mahalanobis(innovation: np.ndarray, S: np.ndarray, used: np.ndarray) -> np.ndarray:
    """d = sqrt(i^T S^-1 i) over the `used` components of each (k, j) pair.

    innovation K x M x 5, S M x 5 x 5, used K x M x 5 bool (a component is left out, i.e.
    marginalised, where a cluster or a tree has no NDVI)."""
    if used.all():  # the usual case: every component measured, one batched solve
        solved = np.linalg.solve(S[None, :, :, :], innovation[..., None])[..., 0]
        return np.sqrt(np.einsum("kmi,kmi->km", innovation, solved))
    out = np.empty(innovation.shape[:2])
    # Each pair's mask as one integer (component c is bit c): the distinct masks by a
    # bincount; np.unique over boolean rows cost more than the solves. The same pairs,
    # in the same order, go to each solve (pairs of different masks do not mix).
    codes = used.astype(np.intp) @ _BITS
    for code in np.flatnonzero(np.bincount(codes.ravel())):
        mask = (code & _BITS) != 0
        k, j = np.nonzero(codes == code)
        sub = S[j][:, mask][:, :, mask]
        i = innovation[k, j][:, mask]
        out[k, j] = np.sqrt(np.einsum("ni,ni->n", i, np.linalg.solve(sub, i[..., None])[..., 0]))
    return out


def _nan_to_num(values: np.ndarray) -> np.ndarray:
    """np.nan_to_num of a float64 array (a copy: NaN 0, infinities the largest floats)
    by its own three steps, without its dispatch and finfo look-ups."""
    out = np.array(values, dtype=float)
    np.copyto(out, 0.0, where=np.isnan(out))
    np.copyto(out, _LARGEST, where=out == np.inf)
    np.copyto(out, -_LARGEST, where=out == -np.inf)
    return out


def normalised_entropy(log_p: np.ndarray) -> np.ndarray:
    """H = -sum p^ log_M p^ over each row's normalised probabilities p^ = p / sum p, from
    log p (so that p far below float range still normalises). H = 0 when M = 1."""
    m = log_p.shape[-1]
    if m <= 1:
        return np.zeros(log_p.shape[:-1])
    shifted = log_p - log_p.max(axis=-1, keepdims=True)
    log_hat = shifted - np.log(np.exp(shifted).sum(axis=-1, keepdims=True))
    hat = np.exp(log_hat)
    return -(hat * log_hat).sum(axis=-1) / math.log(m)


@dataclass
class ScanSet:
    """The scans (by index in the run) a tree was seen in: a bit set from the first one.
    A merge takes the union, so a tree never counts more scans than the run has; a tree
    seen over a few hundred scans costs a few dozen bytes."""

    first: int
    bits: int = 1

    def add(self, index: int) -> None:
        if index < self.first:
            self.bits <<= self.first - index
            self.first = index
        self.bits |= 1 << (index - self.first)

    def union(self, other: ScanSet) -> None:
        first = min(self.first, other.first)
        self.bits = (self.bits << (self.first - first)) | (other.bits << (other.first - first))
        self.first = first

    def __len__(self) -> int:
        return bin(self.bits).count("1")


@dataclass
class Track:
    """One tree in memory: its Kalman filter and its bookkeeping."""

    tree_id: int
    kf: object  # filterpy.kalman.KalmanFilter
    has_ndvi: bool
    first_seen: int
    last_seen: int
    scans: ScanSet
    # A post, a person, a vehicle or a wall (its first cluster's verdict, then its
    # votes', kept by the mapper): never merged with a tree by distance.
    standing: bool = False

    @property
    def state(self) -> np.ndarray:
        return self.kf.x[:, 0]

    @property
    def observations(self) -> int:
        """Scans this tree was seen in."""
        return len(self.scans)


@dataclass(frozen=True)
class Decision:
    """What happened to one cluster."""

    tree_id: int  # the tree it updated or created (after merges), or the one it duplicated
    # "updated"; "created"; "merged" (it started a tree that the merge folded into an
    # older one at once); "duplicate" (dropped: its tree took a likelier cluster).
    outcome: str
    p_max: float  # NaN when there was no tree to compare with
    entropy: float


@dataclass
class StepResult:
    decisions: list[Decision]
    candidates: int  # M: trees in view, gated against
    merged: list[tuple[int, int]] = field(default_factory=list)  # (kept, absorbed)


class Tracker:
    def __init__(self, config: TrackingConfig):
        self.config = config
        self.tracks: list[Track] = []
        self._next_id = 1
        self._scan = -1  # index of the current scan in the run
        # Set by the mapper: whether two tracks are known to be two trees (where each
        # stands is known, and far apart), which no drift of their states may merge.
        self.apart: Callable[[Track, Track], bool] | None = None

    def positions(self) -> np.ndarray:
        return np.array([t.state[:3] for t in self.tracks]).reshape(-1, 3)

    def move(self, new_from_old: np.ndarray) -> None:
        """Apply a rigid motion to every tree (the map frame moved: the paper's B v_x)."""
        rotation, translation = new_from_old[:3, :3], new_from_old[:3, 3]
        for track in self.tracks:
            track.kf.x[:3, 0] = rotation @ track.kf.x[:3, 0] + translation
            block = track.kf.P[:3, :3]
            track.kf.P[:3, :3] = rotation @ block @ rotation.T

    def step(
        self,
        measurements: np.ndarray,
        sensor_from_map: np.ndarray,
        in_view: np.ndarray,
        t: int,
        standing: np.ndarray | None = None,
    ) -> StepResult:
        """One scan: `measurements` K x 5 m_k in the map frame (NDVI NaN when unknown),
        `sensor_from_map` the LiDAR frame now, `in_view` one bool per track (who could be
        seen), `standing` one bool per measurement (a post, person, vehicle or wall: a
        tree it starts is `standing`). Returns one Decision per measurement, in order."""
        cfg = self.config
        self._scan += 1
        active = [tr for tr, seen in zip(self.tracks, in_view, strict=True) if seen]
        # Predict the trees that can be seen, once per scan (F = I, Q = q I): standing
        # trees do not move in the map frame; their uncertainty grows.
        for track in active:
            track.kf.predict()
        k, m = len(measurements), len(active)
        p_max = np.full(k, np.nan)
        entropy = np.full(k, np.nan)
        gated = np.zeros((k, m), dtype=bool)
        log_p = np.full((k, m), -np.inf)
        if k and m:
            log_p, entropy = self._gate(measurements, active, sensor_from_map)
            p_max = np.exp(log_p.max(axis=1))
            gated = (np.exp(log_p) > cfg.th_p) & (entropy < cfg.th_h)[:, None]
            if cfg.max_association_m > 0:
                predicted = np.array([tr.state[:2] for tr in active])
                jump = np.hypot(*(measurements[:, None, :2] - predicted[None, :, :]).T).T
                gated &= jump < cfg.max_association_m
        taken = _assign(gated, -log_p)

        decisions: list[Decision | None] = [None] * k
        for index, j in taken:
            track = active[j]
            self._update(track, measurements[index], t)
            decisions[index] = Decision(track.tree_id, "updated", p_max[index], entropy[index])
        # New trees after the loop: clusters of one scan are distinct by construction,
        # so a tree born in this scan is no candidate for its siblings.
        for index in range(k):
            if decisions[index] is not None:
                continue
            if gated[index].any():
                # It looks like a tree in view that took a likelier cluster: a piece of it.
                j = int(np.argmax(np.where(gated[index], log_p[index], -np.inf)))
                tree_id = active[j].tree_id
                decisions[index] = Decision(tree_id, "duplicate", p_max[index], entropy[index])
                continue
            track = self._create(measurements[index], t)
            track.standing = bool(standing[index]) if standing is not None else False
            decisions[index] = Decision(track.tree_id, "created", p_max[index], entropy[index])
        # Decisions name the trees that remain: a tree started here and merged into an
        # older one at once reads "merged" with the older tree's id.
        merged = self._merge(in_view)
        alias = {absorbed: kept for kept, absorbed in merged}
        for index, d in enumerate(decisions):
            if d.tree_id in alias:
                outcome = "merged" if d.outcome == "created" else d.outcome
                decisions[index] = Decision(alias[d.tree_id], outcome, d.p_max, d.entropy)
        return StepResult(decisions, m, merged)

    def _gate(self, measurements, active, sensor_from_map):
        cfg = self.config
        states = np.array([tr.state for tr in active])
        rotation, translation = sensor_from_map[:3, :3], sensor_from_map[:3, 3]
        measured_sensor = measurements[:, :3] @ rotation.T + translation
        predicted_sensor = states[:, :3] @ rotation.T + translation
        innovation = normalised_innovation(
            _nan_to_num(measurements), states, measured_sensor, predicted_sensor, cfg
        )
        used = np.ones(innovation.shape, dtype=bool)
        has_tree_ndvi = np.array([tr.has_ndvi for tr in active])
        used[:, :, NDVI] = np.isfinite(measurements[:, NDVI])[:, None] & has_tree_ndvi[None, :]
        S = np.array([tr.kf.P for tr in active]) + cfg.r * _EYE  # H P H^T + R, H = I
        log_p = -cfg.prob_scale * mahalanobis(innovation, S, used)
        return log_p, normalised_entropy(log_p)

    def _create(self, m: np.ndarray, t: int) -> Track:
        from filterpy.kalman import KalmanFilter

        cfg = self.config
        kf = KalmanFilter(dim_x=DIM, dim_z=DIM)
        has_ndvi = bool(np.isfinite(m[NDVI]))
        kf.x = _nan_to_num(m).reshape(DIM, 1).astype(float)
        kf.P = _EYE * cfg.p0
        kf.F = _EYE.copy()
        kf.H = _EYE.copy()
        kf.Q = _EYE * cfg.q
        kf.R = _EYE * cfg.r
        track = Track(self._next_id, kf, has_ndvi, t, t, ScanSet(self._scan))
        self._next_id += 1
        self.tracks.append(track)
        return track

    def _update(self, track: Track, m: np.ndarray, t: int) -> None:
        cfg = self.config
        measured = np.isfinite(m)
        if measured[NDVI] and not track.has_ndvi:
            # First NDVI for a tree started without one: that component starts now.
            track.kf.x[NDVI, 0] = m[NDVI]
            track.kf.P[NDVI, :] = track.kf.P[:, NDVI] = 0.0
            track.kf.P[NDVI, NDVI] = cfg.p0
            track.has_ndvi = True
            measured[NDVI] = False
        if measured.all():
            track.kf.update(m)
        else:  # a missing component is not measured: H and R keep the measured rows only
            H = _EYE[measured]
            track.kf.update(m[measured].reshape(-1, 1), R=_EYE[: len(H), : len(H)] * cfg.r, H=H)
        track.scans.add(self._scan)
        track.last_seen = t

    def drop(self, tree_ids: set[int]) -> None:
        """Forget these trees (the mapper finalised them: out of range for good)."""
        self.tracks = [tr for tr in self.tracks if tr.tree_id not in tree_ids]

    def fold(self, keep_id: int, drop_id: int) -> None:
        """Tree `drop_id` is tree `keep_id` seen apart (the mapper's outlines say so): one
        tree, as the merge makes it."""
        keep = next(tr for tr in self.tracks if tr.tree_id == keep_id)
        drop = next(tr for tr in self.tracks if tr.tree_id == drop_id)
        _fold(keep, drop)
        self.tracks.remove(drop)

    def _merge(self, in_view: np.ndarray) -> list[tuple[int, int]]:
        """Trees in view closer than merge_distance_m (x-y) are one, unless one stands (a
        post, a person) and the other does not, or they are known `apart`: the older
        (lower id) keeps its id; the two estimates are fused by their covariances and the
        tree keeps the union of their scans."""
        limit = self.config.merge_distance_m
        if limit <= 0 or len(self.tracks) < 2:
            return []
        view = np.ones(len(self.tracks), dtype=bool)  # trees born this scan: in view
        view[: len(in_view)] = in_view
        index = np.flatnonzero(view)
        xy = self.positions()[index, :2]
        gap = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        close = np.argwhere(np.triu(gap < limit, k=1))
        if len(close) == 0:
            return []
        merged, gone = [], set()
        for a, b in close:  # row-major: by the older tree, then the newer
            if a in gone or b in gone:
                continue
            keep, drop = self.tracks[index[a]], self.tracks[index[b]]
            if keep.standing != drop.standing:
                continue  # a person beside a crown is not a piece of it
            if float(np.hypot(*(keep.state[:2] - drop.state[:2]))) >= limit:
                continue  # `keep` took another tree's state above and moved away
            if self.apart is not None and self.apart(keep, drop):
                continue  # two trees whose states drifted together
            _fold(keep, drop)
            merged.append((keep.tree_id, drop.tree_id))
            gone.add(b)
        dropped = {int(index[b]) for b in gone}
        self.tracks = [tr for i, tr in enumerate(self.tracks) if i not in dropped]
        return merged


def _assign(gated: np.ndarray, cost: np.ndarray) -> list[tuple[int, int]]:
    """(cluster, tree) pairs of least total cost, each at most once, over gated pairs only."""
    if not gated.any():
        return []
    from scipy.optimize import linear_sum_assignment

    rows = np.flatnonzero(gated.any(axis=1))
    cols = np.flatnonzero(gated.any(axis=0))
    sub_gated = gated[np.ix_(rows, cols)]
    # Pairs outside the gate cost more than any set of gated pairs could: the solver then
    # takes as many gated pairs as it can, and those it is left with are dropped.
    sub_cost = np.where(sub_gated, cost[np.ix_(rows, cols)], 0.0)
    forbidden = 1.0 + sub_cost.sum() + len(rows)
    sub_cost = np.where(sub_gated, sub_cost, forbidden)
    r, c = linear_sum_assignment(sub_cost)
    return sorted(
        (int(rows[i]), int(cols[j])) for i, j in zip(r, c, strict=True) if sub_gated[i, j]
    )


def _fold(keep: Track, drop: Track) -> None:
    fuse_estimates(keep, drop)
    keep.scans.union(drop.scans)
    keep.first_seen = min(keep.first_seen, drop.first_seen)
    keep.last_seen = max(keep.last_seen, drop.last_seen)


def fuse_estimates(keep: Track, drop: Track) -> None:
    """Two estimates of one tree into `keep`: the covariance-weighted combination of the
    components both have (x = x1 + K (x2 - x1), P = P1 - K P1, K = P1 (P1 + P2)^-1); an
    NDVI only one of them has is taken as it is."""
    x1, p1 = keep.kf.x[:, 0].copy(), keep.kf.P.copy()
    x2, p2 = drop.kf.x[:, 0], drop.kf.P
    # The components both have are the first n (NDVI is the last): slices, not fancy
    # indexing; the block copied to a C-ordered array as the fancy index made it, so the
    # products and the inverse get the same operands (a tracker folds ~10 a scan in a
    # cluttered field).
    both = DIM if keep.has_ndvi and drop.has_ndvi else NDVI
    block = np.ascontiguousarray(p1[:both, :both])
    gain = block @ np.linalg.inv(block + p2[:both, :both])
    x, p = x1.copy(), p1.copy()
    x[:both] = x1[:both] + gain @ (x2[:both] - x1[:both])
    p[:both, :both] = block - gain @ block
    if drop.has_ndvi and not keep.has_ndvi:
        x[NDVI] = x2[NDVI]
        p[NDVI, :] = p[:, NDVI] = 0.0
        p[NDVI, NDVI] = p2[NDVI, NDVI]
        keep.has_ndvi = True
    keep.kf.x = x.reshape(DIM, 1)
    keep.kf.P = (p + p.T) / 2
