"""What a tree is: each cluster of a scan judged tree / not a tree from its shape and
its height above the terrain against a crop profile, and from the evidence of
vegetation on it (`pipeline.vegetation`: surface texture, planarity, NDVI).

Every shape rule names a physical difference between a tree and what else stands in a
grove (`ClassifyConfig` gives each bound and its reason): weeds, cover crop and drip
lines are low; posts, wires, trunks alone and people are thin or slender; buildings and
long walls are wider than any crown. Walls, sheds and vehicles of a crown's shape are
told by their surface and colour, weighed together. One scan can be misleading (a far
tree's top is missed, a crown is seen edge-on), so the mapper keeps the verdicts and the
cues of every scan of a track and decides over all of them (`Votes`).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from treetraits.jit import kernel, kernel_layout, warm_up
from treetraits.pipeline.config import ClassifyConfig
from treetraits.pipeline.medians import median_of_groups
from treetraits.pipeline.vegetation import Cues, Evidence, EvidenceSum

TREE = "tree"
# Reasons a cluster is not a tree, in the order the rules are tried.
LOW = "low"  # weeds, cover crop, drip lines, a curb
TALL = "tall"  # a building, a tall pole or mast
THIN = "thin"  # a post, a trunk without its crown, a wire's end
SLENDER = "slender"  # a standing or walking person, a pole
WIDE = "wide"  # a long wall, a building, a parked row of vehicles
FLOATING = "floating"  # a ceiling, a roof edge, a crown's fragment cut off its tree
SMOOTH = "smooth"  # a wall, a shed, a vehicle: its surface is not foliage's
NOT_GREEN = "not_green"  # the camera sees no vegetation on it
REASONS = (LOW, TALL, FLOATING, THIN, SLENDER, WIDE, SMOOTH, NOT_GREEN)

# Bearings for the horizontal extent (the width): 12 directions, 15 deg apart, miss a
# set's true diameter by at most 1 - cos(7.5 deg) = 0.9 %.
_ANGLES = np.arange(12) * math.pi / 12
_DIRECTIONS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)])
_BEARINGS = np.ascontiguousarray(_DIRECTIONS.T)
# Ring numbers one group may span for the roughness's counting sort by ring (a VLP-16's
# span 16); wider, NumPy's lexsort orders the returns.
_MAX_RINGS = 1024


@dataclass(frozen=True)
class Shape:
    """What the rules read off one cluster (its returns in a frame with z up)."""

    height_m: float  # top above the terrain under the cluster
    base_m: float  # lowest return above the terrain under the cluster
    width_m: float  # largest horizontal extent
    roughness: float  # m, along its rings (see `roughness`; NaN: too few returns)
    ndvi: float  # mean NDVI of its returns that have one (NaN: none)
    ndvi_share: float  # share of its returns with an NDVI
    # Largest horizontal extent of its returns above the understorey (NaN: none there, or
    # not measured): a post or a person standing in a weed clump is as thin there as
    # anywhere, whatever the clump's width at its foot.
    crown_width_m: float = math.nan
    # Its lowest return is on the sensor's lowest ring: what lies under it was out of the
    # LiDAR's view (a LiDAR mounted high, looking down on a crown close by), so nothing
    # says it floats. On a Jackal's 0.4 m mount that beam points down and hits nothing
    # a metre above the ground.
    base_cut: bool = False

    @property
    def aspect(self) -> float:
        return self.width_m / self.height_m if self.height_m > 0 else math.inf


def shape_of(
    points: np.ndarray,
    ring: np.ndarray,
    lidar_xy: np.ndarray,
    ground_z: float,
    ndvi: np.ndarray | None = None,
    rough: float | None = None,
    rings_known: bool = True,
) -> Shape:
    """`points` N x 3 with z up (the frame of `lidar_xy`, the LiDAR's x-y), their rings
    (0 the lowest beam; `rings_known` False for a cloud imported without them, every ring
    0); `ndvi` per point (NaN where unknown) or None; `rough`: their `roughness` when
    known (`roughness_of_groups`)."""
    if len(points) == 0:
        return Shape(0.0, 0.0, 0.0, math.nan, math.nan, 0.0)
    height = float(points[:, 2].max() - ground_z)
    lowest = int(np.argmin(points[:, 2]))
    base = float(points[lowest, 2] - ground_z)
    width = horizontal_extent(points[:, :2])
    mean_ndvi, share, _ = ndvi_seen(ndvi)
    if rough is None:
        rough = roughness(points, ring, lidar_xy)
    base_cut = rings_known and int(ring[lowest]) == 0
    return Shape(height, base, width, rough, mean_ndvi, share, base_cut=base_cut)


def ndvi_seen(ndvi: np.ndarray | None) -> tuple[float, float, int]:
    """The mean NDVI of the returns that have one (NaN: none), their share and count."""
    if ndvi is None or len(ndvi) == 0:
        return math.nan, 0.0, 0
    known = np.isfinite(ndvi)
    # known.mean() sums the flags as float64 (exactly) and divides by the count: the same
    # correctly rounded quotient, without np.mean's machinery.
    seen = int(np.count_nonzero(known))
    return (float(ndvi[known].mean()) if seen else math.nan), seen / len(ndvi), seen


def horizontal_extent(xy: np.ndarray) -> float:
    """The largest extent of x-y points over 12 bearings (their width), 0 for none."""
    if len(xy) == 0:
        return 0.0
    # One row per bearing: reduced along rows, 6x quicker than along columns at 3000 points.
    projected = _BEARINGS @ xy.T
    return float((projected.max(axis=1) - projected.min(axis=1)).max())


def roughness(points: np.ndarray, ring: np.ndarray, lidar_xy: np.ndarray) -> float:
    """Median distance (m) of a return from the midpoint of its two neighbours on the
    same ring (consecutive firings, no gap between them). Along a ring the VLP-16 fires
    every 0.2-0.4 deg (2-4 cm at 5 m): on a wall, a vehicle, a post, a person's clothes
    the three lie on one smooth curve and the distance is the range noise (measured on
    the real indoor captures: 0.004-0.03 m); in foliage consecutive beams hit different
    leaves decimetres apart in depth. NaN with fewer than 5 such triples."""
    return float(roughness_of_groups(points, ring, lidar_xy, np.array([len(points)]))[0])


def roughness_of_groups(
    points: np.ndarray, ring: np.ndarray, lidar_xy: np.ndarray, sizes: np.ndarray
) -> np.ndarray:
    """`roughness` of each group of consecutive returns (`sizes[k]` of them) at once: a
    scan's clusters in one pass, not ~25 NumPy calls each. The groups are kept apart by a
    leading sort key and by no pair or triple spanning two of them; NaN for a group of
    fewer than 3 returns or 5 triples. The bearings and the gaps between them are
    NumPy's (its arctangent and complex exponential are SIMD code a kernel would not
    match to the bit); their order (`_lexsort_groups`) and what follows the gaps
    (`_roughness_after_gaps`) are kernels, to the bit `roughness_of_groups_numpy`'s."""
    if points.dtype != np.float64:  # the kernel's arithmetic is float64's
        return roughness_of_groups_numpy(points, ring, lidar_xy, sizes)
    rings, counts = kernel_layout(ring, np.int64), kernel_layout(sizes, np.int64)
    azimuth = _bearings(points, lidar_xy)
    order = _lexsort_groups(rings, azimuth, counts)
    if order is None:  # rings too far apart to count out
        order = _lexsort(azimuth, ring, sizes)
    # The returns and rings read through `order` in the kernel, not gathered first.
    return _roughness_after_gaps(kernel_layout(points), rings, order, _gaps(azimuth, order), counts)


def _bearings(points: np.ndarray, lidar_xy: np.ndarray) -> np.ndarray:
    """Each return's bearing (rad) from the LiDAR."""
    return np.arctan2(points[:, 1] - lidar_xy[1], points[:, 0] - lidar_xy[0])


def _lexsort(azimuth: np.ndarray, ring: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """The returns by group, ring and bearing (stable: each group's own lexsort)."""
    return np.lexsort((azimuth, ring, np.repeat(np.arange(len(sizes)), sizes)))


def _gaps(azimuth: np.ndarray, order: np.ndarray) -> np.ndarray:
    """The bearing gap (rad, wrapped) after each return in `order`."""
    return np.abs(np.angle(np.exp(1j * np.diff(azimuth[order]))))


def roughness_of_groups_numpy(
    points: np.ndarray, ring: np.ndarray, lidar_xy: np.ndarray, sizes: np.ndarray
) -> np.ndarray:
    """`roughness_of_groups` in NumPy calls: for points other than float64, and the
    formulation the kernel is held to (tests)."""
    groups = len(sizes)
    azimuth = _bearings(points, lidar_xy)
    order = _lexsort(azimuth, ring, sizes)
    gap = _gaps(azimuth, order)
    owner = np.repeat(np.arange(groups), sizes)
    p, r, owner = points[order], ring[order], owner[order]
    same = (r[1:] == r[:-1]) & (owner[1:] == owner[:-1])
    step = median_of_groups(gap[same], owner[1:][same], groups)
    adjacent = same & (gap <= 2.5 * step[owner[1:]])  # NaN steps: no pair, never same
    triple = adjacent[:-1] & adjacent[1:]
    middle = (p[:-2] + p[2:]) / 2
    spread = np.linalg.norm(p[1:-1] - middle, axis=1)[triple]
    found = median_of_groups(spread, owner[1:-1][triple], groups)
    enough = (np.bincount(owner[1:-1][triple], minlength=groups) >= 5) & (sizes >= 3)
    return np.where(enough, found, math.nan)


@kernel
def _lexsort_groups(ring: np.ndarray, azimuth: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """`np.lexsort((azimuth, ring, owner))` of groups of consecutive returns (`sizes`):
    each group's returns counted out by ring, then each ring's sorted by bearing. None
    when a group's rings span more than `_MAX_RINGS` values (then NumPy sorts)."""
    order = np.empty(len(ring), dtype=np.int64)
    end = 0
    for group in range(len(sizes)):
        start, end = end, end + sizes[group]
        if end == start:
            continue
        low, high = ring[start], ring[start]
        for i in range(start, end):
            low, high = min(low, ring[i]), max(high, ring[i])
        if high - low >= _MAX_RINGS:
            return None
        first = np.zeros(high - low + 2, dtype=np.int64)  # each ring's start in the group
        for i in range(start, end):
            first[ring[i] - low + 1] += 1
        for r in range(1, len(first)):
            first[r] += first[r - 1]
        at = first + start
        for i in range(start, end):  # in index order: each ring's returns stay in it
            order[at[ring[i] - low]] = i
            at[ring[i] - low] += 1
        for r in range(high - low + 1):
            _sort_by_bearing(order, azimuth, start + first[r], start + first[r + 1])
    return order


@kernel
def _sort_by_bearing(order: np.ndarray, azimuth: np.ndarray, lo: int, hi: int) -> None:
    """Sort order[lo:hi] by bearing, equal bearings by index: the one order a stable sort
    gives. Insertion sort: linear on a ring's returns in firing order (bearings nearly
    monotonic; a mostly falling run is turned around first); returns in no order (a
    recording from another driver) go to a merge sort once the moves pass a few per
    return, before the insertion sort turns quadratic."""
    falling = 0
    for i in range(lo + 1, hi):
        falling += 1 if _before(order[i], order[i - 1], azimuth) else 0
        falling -= 1 if _before(order[i - 1], order[i], azimuth) else 0
    if falling > 0:  # turned around in place
        for i in range((hi - lo) // 2):
            order[lo + i], order[hi - 1 - i] = order[hi - 1 - i], order[lo + i]
    moves_left = 8 * (hi - lo) + 64
    for i in range(lo + 1, hi):
        this, j = order[i], i - 1
        while j >= lo and _before(this, order[j], azimuth):
            order[j + 1] = order[j]
            j -= 1
            moves_left -= 1
        order[j + 1] = this
        if moves_left < 0:
            segment = np.sort(order[lo:hi])  # index order: a stable sort keeps ties so
            order[lo:hi] = segment[np.argsort(azimuth[segment], kind="mergesort")]
            return


@kernel
def _before(a: int, b: int, azimuth: np.ndarray) -> bool:
    """Return a sorts before return b: a smaller bearing in NumPy's order (NaN last,
    -0.0 equal to 0.0), or an equal one and a smaller index."""
    x, y = azimuth[a], azimuth[b]
    if x < y or (y != y and x == x):
        return True
    if y < x or (x != x and y == y):
        return False
    return a < b


@kernel
def _roughness_after_gaps(
    points: np.ndarray, ring: np.ndarray, order: np.ndarray, gap: np.ndarray, sizes: np.ndarray
) -> np.ndarray:
    """`roughness_of_groups_numpy` from the returns, their rings, their `order` (by group,
    ring and bearing: the groups stay where they were) and the `gap` after each one in
    it: the same pairs, triples, distances and medians, one group after the other."""
    found = np.full(len(sizes), np.nan)
    values = np.empty(max(len(order), 1))
    end = 0
    for group in range(len(sizes)):
        start, end = end, end + sizes[group]
        # The median step between returns of one ring (pair i: returns i and i + 1).
        count = 0
        for i in range(start, end - 1):
            if ring[order[i + 1]] == ring[order[i]]:
                values[count] = gap[i]
                count += 1
        limit = 2.5 * _kernel_median(values[:count])
        # The spread of each triple of adjacent returns (i - 1, i, i + 1).
        count = 0
        for i in range(start + 1, end - 1):
            if _adjacent(ring, order, gap, i - 1, limit) and _adjacent(ring, order, gap, i, limit):
                values[count] = _off_middle(points, order, i)
                count += 1
        if count >= 5 and sizes[group] >= 3:
            found[group] = _kernel_median(values[:count])
    return found


@kernel
def _adjacent(ring: np.ndarray, order: np.ndarray, gap: np.ndarray, i: int, limit: float) -> bool:
    """Returns i and i + 1 in `order` consecutive firings: one ring, a gap within the
    limit (never with a NaN limit)."""
    return ring[order[i + 1]] == ring[order[i]] and gap[i] <= limit


@kernel
def _off_middle(points: np.ndarray, order: np.ndarray, i: int) -> float:
    """Distance of return i in `order` from the midpoint of returns i - 1 and i + 1,
    summed as `np.linalg.norm(..., axis=1)` sums the squares of a row."""
    this, before, after = order[i], order[i - 1], order[i + 1]
    total = 0.0
    for axis in range(3):
        d = points[this, axis] - (points[before, axis] + points[after, axis]) / 2
        total = total + d * d if axis else d * d
    return math.sqrt(total)


@kernel
def _kernel_median(values: np.ndarray) -> float:
    """`median` of a 1-D float array: the same middle values by one partition (linear,
    where a sort is not), NaN when any value is."""
    n = len(values)
    if n == 0:
        return math.nan
    for value in values:
        if math.isnan(value):
            return math.nan
    half = n // 2
    part = np.partition(values, half)
    return part[half] if n % 2 else (part[:half].max() + part[half]) / 2


def judge(shape: Shape, config: ClassifyConfig, evidence: Evidence | None = None) -> str:
    """TREE, or the first rule the shape fails (one of REASONS); then, with `evidence`
    (`pipeline.vegetation`), `not_green` or `smooth` where it speaks against
    vegetation, by the cue that speaks most against it. Undecided evidence (nothing
    measured, or for and against in balance) leaves a scan's verdict to the shape: the
    track decides over all its scans (`Votes`)."""
    if shape.height_m < config.min_height_m:
        return LOW
    if shape.height_m > config.max_height_m:
        return TALL
    if shape.base_m > config.max_base_m and not shape.base_cut:
        return FLOATING
    if shape.width_m < config.min_width_m or shape.crown_width_m < config.min_width_m:
        return THIN  # (a NaN crown width, nothing above the understorey, compares False)
    if shape.aspect < config.min_aspect:
        return SLENDER
    if shape.width_m > config.max_width_m:
        return WIDE
    if evidence is not None and evidence.disproved:
        return not_vegetation(evidence)
    return TREE


def not_vegetation(evidence: Evidence) -> str:
    """The reason an object the evidence speaks against is not a tree."""
    return NOT_GREEN if evidence.against == "ndvi" else SMOOTH


# Verdicts of a tree's shape that the vegetation evidence turned down: the track's
# evidence, over all its scans, decides those (`Votes.kind`).
EVIDENCE_REASONS = (SMOOTH, NOT_GREEN)


@dataclass
class Votes:
    """The verdicts of every cluster of one track (a scan may give a track several
    pieces) and their vegetation evidence.

    Its shape is a tree's when its tree-shaped verdicts (`tree`, and `smooth` or
    `not_green`, which are tree-shaped objects whose scan spoke against vegetation) are
    at least `min_share` of the verdicts that judge what the object is and at least
    `min_share_all` of all of them; else it is the reason given most often. A tree's
    shape is a tree when the track's evidence speaks for vegetation (each surface cue's
    mean over the scans that measured it, NDVI's over every return the camera saw:
    `vegetation.EvidenceSum`): one scan's evidence, or one cue's, decides nothing alone.

    `low` and `floating` judge a piece, not the object: a crown cut by the crop box or
    hidden in part is a floating top or a low skirt in some scans, and on a path that
    passes a tree from several sides such pieces were half of its verdicts (the twin's
    grove). A weed or a post taken for a tree in a few scans stays far below the floor."""

    counts: Counter = field(default_factory=Counter)
    evidence: EvidenceSum = field(default_factory=EvidenceSum)

    def add(self, verdict: str, cues: Cues | None = None, evidence: Evidence | None = None) -> None:
        self.counts[verdict] += 1
        if cues is not None and evidence is not None and verdict not in (LOW, FLOATING):
            # A piece (a skirt, a crown's top) is not the object: its surface is not weighed.
            self.evidence.add(cues, evidence)

    def absorb(self, other: Votes) -> None:
        self.counts.update(other.counts)
        self.evidence.absorb(other.evidence)

    def kind(self, min_share: float, min_share_all: float) -> str:
        total = sum(self.counts.values())
        if total == 0:
            return TREE
        shaped = self.counts[TREE] + sum(self.counts[r] for r in EVIDENCE_REASONS)
        judging = total - self.counts[LOW] - self.counts[FLOATING]
        if shaped >= min_share * judging and shaped >= min_share_all * total:
            evidence = self.evidence.evidence()
            return TREE if evidence.vegetation else not_vegetation(evidence)
        # Not a tree's shape: some verdict other than the tree-shaped ones outweighs them.
        reasons = [(n, r) for r, n in self.counts.items() if r not in (TREE, *EVIDENCE_REASONS)]
        return max(reasons, key=lambda item: (item[0], -REASONS.index(item[1])))[1]


@warm_up
def compile_kernels() -> None:
    """The roughness kernel compiled for the types a scan gives it: two groups of float64
    returns on uint8 rings (the ring arrays of `points`)."""
    azimuth = np.linspace(-0.2, 0.2, 12)
    xyz = np.column_stack([5 * np.cos(azimuth), 5 * np.sin(azimuth), np.ones(12)])
    roughness_of_groups(xyz, np.zeros(12, dtype=np.uint8), np.zeros(2), np.array([7, 5]))
    # The helpers too, as clustering's: a caller loaded from the cache compiles none.
    index = np.arange(12)
    _adjacent(np.zeros(12, dtype=np.int64), index, np.zeros(11), 0, 0.5)
    _off_middle(xyz, index, 1)
    _kernel_median(np.zeros(3))
    _sort_by_bearing(index, azimuth, 0, 12)
    _before(0, 1, azimuth)
