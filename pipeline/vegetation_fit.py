"""Fitting the vegetation evidence (`pipeline.vegetation`) to one orchard: pure statistics.

Given each cue's values on the objects at field-map trees (the trees) and on everything
else the mapper tracked (the others), `propose` says, per cue, how far apart the two
groups lie and where its pivot would sit in the middle of that margin. `treetraits
calibrate classify` collects the values from a recording and prints or writes the result
(docs/pipeline.md, "Calibrating the tree evidence to your orchard").

The margin is taken on the side of the cue that says vegetation: for a cue that is higher
on foliage (texture, NDVI, intensity), the trees' 10th percentile minus the others' 90th;
for the planar share (lower on foliage), the others' 10th minus the trees' 90th. Positive:
the groups are apart, and the pivot goes in the middle (the geometric mean for the texture,
which the evidence weighs on a log scale); zero or negative: they overlap, the cue cannot
tell them apart here and its weight is 0.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from treetraits.pipeline.config import ClassifyConfig

PERCENTILES = (10.0, 50.0, 90.0)


@dataclass(frozen=True)
class Cue:
    """How a cue enters `ClassifyConfig`: the record field it is read from, its pivot and
    weight keys, which side says vegetation, and the weight it gets where it separates."""

    name: str
    field: str  # on the mapper's records (`TrackedTree`)
    pivot_key: str
    weight_key: str
    higher_is_vegetation: bool
    log: bool = False  # weighed on a log scale: the pivot is a geometric mean
    # The weight proposed where the groups are apart: the default's, or (intensity, 0 by
    # default: it misleads on far crowns) this.
    separated_weight: float | None = None

    def weight_when_apart(self) -> float:
        if self.separated_weight is not None:
            return self.separated_weight
        return float(getattr(ClassifyConfig(), self.weight_key))


CUES = (
    Cue("texture", "texture_m", "texture_pivot_m", "texture_weight", True, log=True),
    Cue("planar", "planar_share", "planar_pivot", "planar_weight", False),
    Cue("ndvi", "ndvi", "min_ndvi", "ndvi_weight", True),
    # A surface cue's weight (planar's) where an orchard shows a margin.
    Cue(
        "intensity", "intensity", "intensity_pivot", "intensity_weight", True, separated_weight=0.5
    ),
)


@dataclass(frozen=True)
class Distribution:
    """The finite values' count and 10th, 50th, 90th percentiles (NaN with no value)."""

    count: int
    p10: float = math.nan
    p50: float = math.nan
    p90: float = math.nan


def distribution(values: Iterable[float | None]) -> Distribution:
    finite = np.array(
        [v for v in values if v is not None and math.isfinite(v)], dtype=float
    ).reshape(-1)
    if not len(finite):
        return Distribution(0)
    p10, p50, p90 = (float(x) for x in np.percentile(finite, PERCENTILES))
    return Distribution(len(finite), p10, p50, p90)


def margin_bounds(cue: Cue, trees: Distribution, others: Distribution) -> tuple[float, float]:
    """(others' edge, trees' edge) on the side that says vegetation: the others' 90th and
    the trees' 10th percentile for a cue higher on foliage, the others' 10th and the trees'
    90th for one lower on it."""
    if cue.higher_is_vegetation:
        return others.p90, trees.p10
    return others.p10, trees.p90


def margin(cue: Cue, trees: Distribution, others: Distribution) -> float:
    """The gap between the groups, in the cue's units, positive where they are apart
    (NaN when a group has no value)."""
    other_edge, tree_edge = margin_bounds(cue, trees, others)
    gap = tree_edge - other_edge
    return gap if cue.higher_is_vegetation else -gap


@dataclass(frozen=True)
class Proposal:
    cue: str
    trees: Distribution
    others: Distribution
    margin: float  # cue units; > 0 apart, <= 0 overlapping, NaN not measured on a group
    pivot: float | None  # None: keep the config's (overlapping, or not measured)
    weight: float | None  # None: keep the config's (not measured on both groups)
    pivot_key: str
    weight_key: str
    note: str

    @property
    def section(self) -> dict[str, float]:
        """The config keys this proposal sets."""
        out = {}
        if self.pivot is not None:
            out[self.pivot_key] = self.pivot
        if self.weight is not None:
            out[self.weight_key] = self.weight
        return out


def propose(cue: Cue, trees: Distribution, others: Distribution) -> Proposal:
    """The pivot in the middle of the margin and the weight where the groups are apart;
    weight 0 where they overlap; nothing where a group never measured the cue."""
    gap = margin(cue, trees, others)
    keys = {"pivot_key": cue.pivot_key, "weight_key": cue.weight_key}
    if not trees.count or not others.count:
        empty = "the trees" if not trees.count else "the others"
        note = f"not measured on {empty}: keep the config's"
        return Proposal(cue.name, trees, others, math.nan, None, None, note=note, **keys)
    if not gap > 0:
        return Proposal(
            cue.name, trees, others, gap, None, 0.0, note="overlap: says nothing here", **keys
        )
    low, high = sorted(margin_bounds(cue, trees, others))
    # The texture is weighed on a log scale: its middle is the geometric mean.
    pivot = math.sqrt(low * high) if cue.log and low > 0 else (low + high) / 2
    weight = cue.weight_when_apart()
    return Proposal(cue.name, trees, others, gap, pivot, weight, note="apart", **keys)


def propose_all(
    trees: dict[str, list[float | None]], others: dict[str, list[float | None]]
) -> list[Proposal]:
    """One proposal per cue (`CUES`), from each group's values keyed by the cue's name."""
    return [
        propose(cue, distribution(trees.get(cue.name, ())), distribution(others.get(cue.name, ())))
        for cue in CUES
    ]


def section(proposals: Iterable[Proposal]) -> dict[str, float]:
    """The `[detection.classify]` keys of the proposals, rounded to 4 significant digits."""
    out: dict[str, float] = {}
    for proposal in proposals:
        for key, value in proposal.section.items():
            out[key] = float(f"{value:.4g}")
    return out
