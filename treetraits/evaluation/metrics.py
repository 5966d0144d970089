"""Scoring one replay against the truth, and aggregating over seeds: pure functions.

Matching: every detection goes to the nearest truth tree within `gate_m` (x-y, UTM).
A truth tree with at least one detection is found; its primary detection is the nearest
one, and any further detection on it is a duplicate. A detection within the gate of no
truth tree is a false positive. Traits and position errors are taken on the primary
detections; a tree not found has no trait error (it counts in `found`, not in MAPE).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from treetraits.errors import SourceError

# A detection is scored against the nearest true tree within the replay's own field-map gate.
from treetraits.pipeline.georef import DEFAULT_GATE_M


@dataclass(frozen=True)
class TruthTree:
    tree_id: str
    row: str
    easting: float
    northing: float
    width_m: float
    height_m: float


@dataclass(frozen=True)
class Detection:
    tree_id: str
    easting: float | None  # None: never placed in UTM
    northing: float | None
    width_m: float
    height_m: float


@dataclass(frozen=True)
class TreeScore:
    """One truth tree in one run."""

    truth: TruthTree
    detection: Detection | None  # the primary one; None = missed
    duplicates: int  # further detections on this tree

    @property
    def width_ape(self) -> float | None:
        return _ape(self.detection.width_m, self.truth.width_m) if self.detection else None

    @property
    def height_ape(self) -> float | None:
        return _ape(self.detection.height_m, self.truth.height_m) if self.detection else None

    @property
    def position_error_m(self) -> float | None:
        if self.detection is None:
            return None
        return math.hypot(
            self.detection.easting - self.truth.easting,
            self.detection.northing - self.truth.northing,
        )


@dataclass(frozen=True)
class RunScore:
    trees: tuple[TreeScore, ...]
    false_positives: tuple[Detection, ...]  # on no truth tree (or never placed)

    @property
    def found(self) -> int:
        return sum(t.detection is not None for t in self.trees)

    @property
    def duplicates(self) -> int:
        return sum(t.duplicates for t in self.trees)


@dataclass(frozen=True)
class RowStats:
    """One row over every run given: Table I's columns."""

    row: str
    trees: int  # truth trees (over runs)
    found: int
    gt_width_m: float  # mean
    width_mean_m: float  # of the primary detections (NaN if none)
    width_sd_m: float
    mape_width: float  # %
    gt_height_m: float
    height_mean_m: float
    height_sd_m: float
    mape_height: float


def _ape(estimate: float, truth: float) -> float:
    return abs(estimate - truth) / truth * 100.0


def nearest_within(points: np.ndarray, targets: np.ndarray, gate_m: float) -> list[int | None]:
    """For each point (NaN = not placed), the index of the nearest target within the gate
    (ties to the lower index), or None. Many points may share a target."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    targets = np.asarray(targets, dtype=float).reshape(-1, 2)
    if not len(points) or not len(targets):
        return [None] * len(points)
    distance = np.hypot(*(points[:, None, :] - targets[None, :, :]).transpose(2, 0, 1))
    distance = np.where(np.isnan(distance), np.inf, distance)
    best = distance.argmin(axis=1)
    return [int(j) if distance[i, j] <= gate_m else None for i, j in enumerate(best.tolist())]


def score_run(
    detections: Sequence[Detection], truths: Sequence[TruthTree], gate_m: float = DEFAULT_GATE_M
) -> RunScore:
    xy = np.array(
        [(np.nan, np.nan) if d.easting is None else (d.easting, d.northing) for d in detections],
        dtype=float,
    ).reshape(-1, 2)
    truth_xy = np.array([(t.easting, t.northing) for t in truths], dtype=float).reshape(-1, 2)
    assigned = nearest_within(xy, truth_xy, gate_m)
    on_tree: dict[int, list[int]] = {}
    false_positives = []
    for i, j in enumerate(assigned):
        if j is None:
            false_positives.append(detections[i])
        else:
            on_tree.setdefault(j, []).append(i)
    trees = []
    for j, truth in enumerate(truths):
        mine = on_tree.get(j, [])
        primary = min(mine, key=lambda i: (math.dist(xy[i], truth_xy[j]), i)) if mine else None
        trees.append(
            TreeScore(
                truth, None if primary is None else detections[primary], max(0, len(mine) - 1)
            )
        )
    return RunScore(tuple(trees), tuple(false_positives))


def row_stats(scores: Iterable[RunScore], rows: Sequence[str]) -> list[RowStats]:
    """Per row (in the order given), over all runs."""
    by_row: dict[str, list[TreeScore]] = {row: [] for row in rows}
    for score in scores:
        for tree in score.trees:
            by_row.setdefault(tree.truth.row, []).append(tree)
    out = []
    for row, trees in by_row.items():
        hits = [t for t in trees if t.detection is not None]
        widths = [t.detection.width_m for t in hits]
        heights = [t.detection.height_m for t in hits]
        out.append(
            RowStats(
                row=row,
                trees=len(trees),
                found=len(hits),
                gt_width_m=_mean([t.truth.width_m for t in trees]),
                width_mean_m=_mean(widths),
                width_sd_m=_sd(widths),
                mape_width=_mean([t.width_ape for t in hits]),
                gt_height_m=_mean([t.truth.height_m for t in trees]),
                height_mean_m=_mean(heights),
                height_sd_m=_sd(heights),
                mape_height=_mean([t.height_ape for t in hits]),
            )
        )
    return out


def position_rmse(scores: Iterable[RunScore]) -> float:
    """RMSE (m) of the primary detections' x-y against the truth (NaN if none found)."""
    errors = [t.position_error_m for s in scores for t in s.trees if t.detection is not None]
    return math.sqrt(sum(e * e for e in errors) / len(errors)) if errors else math.nan


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else math.nan


def _sd(values: Sequence[float]) -> float:
    return float(np.std(values, ddof=1)) if len(values) > 1 else math.nan


# ---- reading the files ------------------------------------------------------------------


def load_truth(path: Path) -> list[TruthTree]:
    """The simulator's REC.truth.csv."""
    try:
        with open(path, newline="") as f:
            return [
                TruthTree(
                    r["tree_id"],
                    r["row"],
                    float(r["easting"]),
                    float(r["northing"]),
                    float(r["width_m"]),
                    float(r["height_m"]),
                )
                for r in csv.DictReader(f)
            ]
    except FileNotFoundError:
        raise SourceError(f"{path}: no truth CSV beside the recording (re-simulate)") from None
    except (KeyError, ValueError) as exc:
        raise SourceError(f"{path}: not a truth CSV written by treetraits sim ({exc})") from None


def detections_from_trees(trees: Iterable) -> list[Detection]:
    """`drivers.records.Tree` records (a replay's output) as detections."""
    return [
        Detection(t.tree_id, t.easting, t.northing, float(t.width_m), float(t.height_m))
        for t in trees
    ]
