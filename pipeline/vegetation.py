"""Is it vegetation: cues measured on each cluster of a scan, weighed into one evidence.

No one cue decides. Each is measured at a metric scale that does not depend on the
range or on the LiDAR's angular step or mount, each has a physical reason and a value
on real returns (docs/pipeline.md, "Vegetation evidence"), and each adds a bounded
contribution, so that a cue that misleads on some canopy (a pruned hedge is smoother
than a wild crown; a camera that never saw the object says nothing) cannot veto a
tree on its own:

- `texture_m`: how far a return lies off the midpoint of the returns `texture_step_m`
  either side of it on its ring (median). Leaves are 3-10 cm: returns 5 cm apart fall
  on different leaves at depths centimetres to decimetres apart (real apple canopy
  0.05-0.14 m); a wall, a vehicle's panel, clothes or a post is one smooth surface over
  10 cm and the distance is the range noise (real indoor walls and furniture
  0.004-0.03 m, edges and chairs up to 0.047 m).
- `planar_share`: the share of the cluster's 0.3 m patches whose returns lie within
  the range noise of one plane. Walls, panels, boxes are made of planes; foliage at
  that scale is a volume of leaves (real canopy 0-0.26, real indoor objects 0.09-1.0).
- `ndvi`: the camera's mean NDVI over the object's returns it saw; live leaves reflect
  near-infrared and absorb red (citrus 0.5-0.8), soil, wood, paint, cloth and metal
  do not (< 0.3). The most direct evidence of live foliage, when there is a frame.
- `intensity`: the median return intensity (the VLP-16's calibrated reflectivity).
  Leaves reflect 40-50 % at 905 nm (real canopy's crowns 12-26), black plastic, tyres
  and dark cloth under 10 % (real indoor dark objects 3-11), but a far crown's sparse
  top hit on leaf edges measured 6-8: it weighs nothing by default. It does say how far
  the surface cues can be trusted: a weak echo's range is noisy, and noise looks like
  leaves, so their evidence for foliage counts by `echo_clarity`.

A track adds up its clusters' cues (`EvidenceSum`): each surface cue's contribution is
its mean over the scans that measured it, and NDVI's the mean over every return the
camera saw, so an object the camera saw in a tenth of its scans, or a sliver of it in
each, still has its NDVI counted in full.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from treetraits.pipeline.config import ClassifyConfig
from treetraits.pipeline.medians import median_of_groups

# Triples for the texture: at least this many on a cluster, or it is not measured.
_MIN_TRIPLES = 5
# A patch for the planarity: at least this many returns on each of two rings or more.
# One ring's returns lie in its own fan of beams, which a plane fits whatever they hit:
# a patch is tested only where two rings cross it (real canopy at 5 m: a ring and one
# or two returns of the next made 70 % of its patches "flat").
_MIN_RING_RETURNS = 3
# Patches spread over less than this (second axis, RMS m) are a line (one ring, an
# edge), which any plane fits: left out.
_MIN_PATCH_SPREAD_M = 0.04
# Planar shares of fewer patches than this are not measured.
_MIN_PATCHES = 3
# A cue measured on fewer samples than this weighs in proportion (a median of 5 triples,
# a share of 3 patches are loose: a crown's fragment of 20 returns is not a wall).
FULL_TRIPLES = 30
FULL_PATCHES = 10
# NDVI counts in full once this many of an object's returns have one (a mean over 100
# returns is the object's colour, not a stray pixel's or a projection's edge), in
# proportion below. Not a share of its returns: a crown beside the path is mostly out of
# the camera's view, and the part it sees is as green (the twin's hedgerow: 34 % of its
# crowns' clusters had any NDVI, most of them on under 5 % of their returns).
FULL_NDVI_RETURNS = 100

CUES = ("texture", "planar", "ndvi", "intensity")


@dataclass(frozen=True)
class Cues:
    """What one cluster shows of its surface (NaN: not measured on it)."""

    texture_m: float = math.nan
    texture_triples: int = 0  # the triples its median is of
    planar_share: float = math.nan
    planar_patches: int = 0  # the patches its share is of
    ndvi: float = math.nan  # mean of its returns that have one
    ndvi_share: float = 0.0  # share of its returns with an NDVI
    ndvi_returns: int = 0  # its returns with an NDVI
    intensity: float = math.nan  # median raw intensity (0-255)


@dataclass(frozen=True)
class Evidence:
    """Each cue's contribution (positive: vegetation; 0: not measured) and their sum."""

    texture: float = 0.0
    planar: float = 0.0
    ndvi: float = 0.0
    intensity: float = 0.0
    measured: tuple[str, ...] = ()  # the cues measured (a 0 may be measured or not)

    @property
    def total(self) -> float:
        return self.texture + self.planar + self.ndvi + self.intensity

    @property
    def vegetation(self) -> bool:
        """The cues, weighed together, speak for vegetation: an object nothing could be
        measured on (too few returns, dark echoes) is not shown to be one."""
        return self.total > 0.0

    @property
    def disproved(self) -> bool:
        """The cues, weighed together, speak against vegetation (0: undecided)."""
        return self.total < 0.0

    @property
    def against(self) -> str:
        """The cue that speaks most against vegetation: `ndvi` or a surface cue."""
        return min(CUES, key=lambda cue: getattr(self, cue))


def weigh(cues: Cues, config: ClassifyConfig) -> Evidence:
    """Each cue's bounded contribution (`contributions`), weighted."""
    texture, planar, ndvi, intensity = contributions(cues, config)
    return Evidence(
        texture=config.texture_weight * texture,
        planar=config.planar_weight * planar,
        ndvi=config.ndvi_weight * ndvi,
        intensity=config.intensity_weight * intensity,
        measured=measured(cues),
    )


def measured(cues: Cues) -> tuple[str, ...]:
    """The cues measured on the cluster (NDVI: on any of its returns)."""
    values = {
        "texture": cues.texture_m,
        "planar": cues.planar_share,
        "ndvi": cues.ndvi if cues.ndvi_returns > 0 else math.nan,
        "intensity": cues.intensity,
    }
    return tuple(cue for cue in CUES if math.isfinite(values[cue]))


def contributions(cues: Cues, config: ClassifyConfig) -> tuple[float, float, float, float]:
    """Each cue in [-1, 1] (0 where it is not measured): texture on a log scale, one
    unit per doubling from `texture_pivot_m`; planarity and NDVI linear about their
    pivots; intensity about its pivot over `intensity_scale`. Cues measured on few
    samples count in proportion (`FULL_TRIPLES`, `FULL_PATCHES`, `FULL_NDVI_RETURNS`)."""
    texture = 0.0
    if math.isfinite(cues.texture_m) and cues.texture_m > 0:
        texture = _clip(math.log2(cues.texture_m / config.texture_pivot_m))
        texture *= min(1.0, cues.texture_triples / FULL_TRIPLES)
        if texture > 0:
            texture *= echo_clarity(cues.intensity, config)
    planar = 0.0
    if math.isfinite(cues.planar_share):
        planar = _clip((config.planar_pivot - cues.planar_share) / config.planar_scale)
        planar *= min(1.0, cues.planar_patches / FULL_PATCHES)
        if planar > 0:
            planar *= echo_clarity(cues.intensity, config)
    ndvi = 0.0
    if cues.ndvi_returns > 0 and math.isfinite(cues.ndvi):
        ndvi = _clip((cues.ndvi - config.min_ndvi) / config.ndvi_scale)
        ndvi *= ndvi_confidence(cues.ndvi_returns)
    intensity = 0.0
    if math.isfinite(cues.intensity):
        intensity = _clip((cues.intensity - config.intensity_pivot) / config.intensity_scale)
    return texture, planar, ndvi, intensity


def ndvi_confidence(returns: int) -> float:
    """How far an NDVI mean over `returns` returns counts, 0-1."""
    return min(1.0, returns / FULL_NDVI_RETURNS)


def echo_clarity(intensity: float, config: ClassifyConfig) -> float:
    """How far a surface cue's evidence for foliage counts, 0-1, by the echoes' median
    intensity: a weak echo's range is noisy (real dark objects at intensity 3-11
    measured a texture of 0.02-0.09 m, real walls at 34-71 0.005-0.01 m), and noise
    looks like leaves to both surface cues. 1 where the intensity is unknown."""
    if not math.isfinite(intensity):
        return 1.0
    dark, clear = config.dark_intensity, config.clear_intensity
    return min(1.0, max(0.0, (intensity - dark) / (clear - dark)))


def _clip(value: float) -> float:
    return min(1.0, max(-1.0, value))


@dataclass
class EvidenceSum:
    """A track's cues over its scans: per cue, the sum of its raw values and of its
    contributions, and how many scans measured it. NDVI is kept along the track by
    return: its value and its contribution (at full confidence) are means over every
    return the camera saw, and it counts in full once the track has `FULL_NDVI_RETURNS`
    of them, however few each scan saw."""

    sums: dict[str, float] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)

    def add(self, cues: Cues, evidence: Evidence) -> None:
        values = {
            "texture": cues.texture_m,
            "planar": cues.planar_share,
            "ndvi": cues.ndvi,
            "intensity": cues.intensity,
        }
        for cue in evidence.measured:
            weight, contribution = 1, getattr(evidence, cue)
            if cue == "ndvi":  # by return, at full confidence
                weight = cues.ndvi_returns
                contribution /= ndvi_confidence(weight)
            self.sums[cue] = self.sums.get(cue, 0.0) + values[cue] * weight
            self.sums[f"{cue}:e"] = self.sums.get(f"{cue}:e", 0.0) + contribution * weight
            self.counts[cue] = self.counts.get(cue, 0) + weight

    def absorb(self, other: EvidenceSum) -> None:
        for key, value in other.sums.items():
            self.sums[key] = self.sums.get(key, 0.0) + value
        for key, value in other.counts.items():
            self.counts[key] = self.counts.get(key, 0) + value

    def mean(self, cue: str) -> float:
        """The cue's mean value over the scans that measured it (NDVI: over the returns
        that had one; NaN: none)."""
        count = self.counts.get(cue, 0)
        return self.sums[cue] / count if count else math.nan

    def evidence(self) -> Evidence:
        """Each cue's mean contribution over the scans that measured it."""
        means = {}
        for cue in CUES:
            count = self.counts.get(cue, 0)
            means[cue] = self.sums[f"{cue}:e"] / count if count else 0.0
        means["ndvi"] *= ndvi_confidence(self.counts.get("ndvi", 0))
        return Evidence(**means, measured=tuple(c for c in CUES if self.counts.get(c)))


def measure_groups(
    points: np.ndarray,
    ring: np.ndarray,
    firing: np.ndarray,
    lidar_xyz: np.ndarray,
    sizes: np.ndarray,
    config: ClassifyConfig,
) -> list[Cues]:
    """The surface cues (texture, planarity, intensity; NDVI is the caller's) of each
    group of consecutive returns (`sizes[k]` of them): a scan's clusters in one pass.
    `points` N x 3 in any frame with `lidar_xyz` the LiDAR's origin in it; `firing`
    each return's POINT_DTYPE fields `azimuth` (the sensor's rotation angle: the order
    along a ring whatever the mount), `intensity` and `return_type`. The texture reads
    one echo per firing: a dual-return sensor's two echoes of a firing share its azimuth
    and are no neighbours on a surface; its last echoes are one per firing (the
    strongest is dropped where it repeats the last), so they alone are read then."""
    owner = np.repeat(np.arange(len(sizes)), sizes)
    last = firing["return_type"] == 1
    single = last if last.any() else np.ones(len(last), dtype=bool)
    texture, triples = texture_of_groups(
        points[single],
        ring[single],
        firing["azimuth"][single].astype(float),
        lidar_xyz,
        np.bincount(owner[single], minlength=len(sizes)),
        config.texture_step_m,
    )
    planar, patches = planar_share_of_groups(
        points, ring, sizes, config.planar_patch_m, config.planar_noise_m
    )
    level = median_of_groups(firing["intensity"].astype(float), owner, len(sizes))
    return [
        Cues(
            texture_m=float(texture[k]),
            texture_triples=int(triples[k]),
            planar_share=float(planar[k]),
            planar_patches=int(patches[k]),
            intensity=float(level[k]),
        )
        for k in range(len(sizes))
    ]


def texture_of_groups(
    points: np.ndarray,
    ring: np.ndarray,
    azimuth: np.ndarray,
    lidar_xyz: np.ndarray,
    sizes: np.ndarray,
    step_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """`Cues.texture_m` of each group and the triples it is the median of: along each ring (returns
    ordered by the sensor's azimuth), each return's distance from the midpoint of the returns n
    firings either side, n the firings that span `step_m` at its range (the group's median
    firing step); triples across a gap in the ring (a missed return, another object between) are
    left out. NaN for fewer than `_MIN_TRIPLES` triples."""
    groups = len(sizes)
    out, triples = np.full(groups, math.nan), np.zeros(groups, dtype=np.int64)
    if len(points) < 3:
        return out, triples
    owner = np.repeat(np.arange(groups), sizes)
    # Azimuths about each group's first: a group across the sensor's 0/2 pi seam stays
    # in order (a cluster spans far less than half a turn).
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    turn = 2 * math.pi
    az = (azimuth - azimuth[first[owner]] + math.pi) % turn - math.pi
    order = np.lexsort((az, ring, owner))
    p, a, r, o = points[order], az[order], ring[order], owner[order]
    run = np.concatenate([[0], np.cumsum((r[1:] != r[:-1]) | (o[1:] != o[:-1]))])
    same = run[1:] == run[:-1]
    steps = np.diff(a)
    moving = same & (steps > 0)  # a dual echo or a repeated azimuth is no firing step
    step = median_of_groups(steps[moving], o[1:][moving], groups)
    reach = np.linalg.norm(p - lidar_xyz, axis=1)
    firing = step[o]
    with np.errstate(invalid="ignore", divide="ignore"):
        n = np.where(firing > 0, np.rint(step_m / (reach * firing)), 0)
    n = np.clip(np.nan_to_num(n, nan=0.0), 1, 64).astype(np.int64)
    index = np.arange(len(p))
    before, after = index - n, index + n
    ok = (before >= 0) & (after < len(p)) & np.isfinite(firing)
    before, after = np.clip(before, 0, len(p) - 1), np.clip(after, 0, len(p) - 1)
    ok &= (run[before] == run) & (run[after] == run)
    # No gap: the two neighbours are as many firings apart as expected, give or take half.
    ok &= (a[after] - a[before]) <= 1.5 * 2 * n * firing
    if not ok.any():
        return out, triples
    off = np.linalg.norm(p - (p[before] + p[after]) / 2, axis=1)[ok]
    counted = np.bincount(o[ok], minlength=groups)
    enough = counted >= _MIN_TRIPLES
    found = median_of_groups(off, o[ok], groups)
    return np.where(enough, found, math.nan), np.where(enough, counted, 0)


def planar_share_of_groups(
    points: np.ndarray, ring: np.ndarray, sizes: np.ndarray, patch_m: float, noise_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """`Cues.planar_share` of each group and the patches it is a share of: its returns
    binned in cubes of `patch_m`; of the cubes with at least `_MIN_RING_RETURNS` returns
    on each of two rings or more, spread over a surface (not a line), the share whose
    returns' RMS distance from their best-fit plane is under `noise_m`. NaN for fewer
    than `_MIN_PATCHES` such cubes."""
    groups = len(sizes)
    out, patches = np.full(groups, math.nan), np.zeros(groups, dtype=np.int64)
    if len(points) == 0:
        return out, patches
    owner = np.repeat(np.arange(groups), sizes)
    cells = np.floor(points / patch_m).astype(np.int64)
    cells -= cells.min(axis=0)
    span = cells.max(axis=0) + 1
    key = ((owner * span[0] + cells[:, 0]) * span[1] + cells[:, 1]) * span[2] + cells[:, 2]
    keys, cell_of, count = np.unique(key, return_inverse=True, return_counts=True)
    cell_of = cell_of.ravel()
    # Rings per cell with enough returns on them: (cell, ring) pairs counted.
    pairs, on_ring = np.unique(cell_of * 256 + ring.astype(np.int64), return_counts=True)
    rings = np.bincount(pairs[on_ring >= _MIN_RING_RETURNS] // 256, minlength=len(keys))
    centre = (
        np.stack(
            [
                np.bincount(cell_of, weights=points[:, axis], minlength=len(keys))
                for axis in range(3)
            ],
            axis=1,
        )
        / count[:, None]
    )
    d = points - centre[cell_of]
    cov = np.empty((len(keys), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = (
                np.bincount(cell_of, weights=d[:, i] * d[:, j], minlength=len(keys)) / count
            )
    usable = rings >= 2
    if not usable.any():
        return out, patches
    eigen = np.linalg.eigvalsh(cov[usable])  # ascending
    spread = np.sqrt(np.clip(eigen, 0.0, None))
    surface = spread[:, 1] >= _MIN_PATCH_SPREAD_M
    flat = spread[:, 0] < noise_m
    cell_owner = owner[np.unique(cell_of, return_index=True)[1]][usable]
    patches = np.bincount(cell_owner[surface], minlength=groups)
    planar = np.bincount(cell_owner[surface & flat], minlength=groups)
    enough = patches >= _MIN_PATCHES
    out[enough] = planar[enough] / patches[enough]
    return out, np.where(enough, patches, 0)
