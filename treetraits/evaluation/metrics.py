"""Scoring one replay against the truth, and aggregating over seeds: pure functions.

Matching: every detection goes to the nearest truth tree within `gate_m` (x-y, UTM).
A truth tree with at least one detection is found; its primary detection is the nearest
one, and any further detection on it is a duplicate. A detection within the gate of no
truth tree is a false positive. Traits and position errors are taken on the primary
detections; a tree not found has no trait error (it counts in `found`, not in MAPE).

Field conditions: a missing tree (truth `kind` "missing": in the field map, not planted)
is a target like the others, but a detection on it is wrong: it counts as a false
positive of kind "missing_tree". Every other false positive is put down to the nearest
non-tree object of the truth's objects file within its footprint + `OBJECT_MARGIN_M`, else
"other". A replay row with `status` "missing" (the replay's own report that a field-map
tree was not seen) is not a detection; it marks that tree as reported missing.
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

# A false positive is put down to an object when its centre is within the object's
# footprint plus this: a cluster's centre sits inside what it hit, and the tracker's
# smoothing and the localisation (~0.3 m on the twin) move it a little.
OBJECT_MARGIN_M = 1.0


@dataclass(frozen=True)
class TruthTree:
    tree_id: str
    row: str
    easting: float
    northing: float
    width_m: float  # NaN for a missing tree
    height_m: float
    kind: str = "tree"  # tree | missing


@dataclass(frozen=True)
class TruthObject:
    """A non-tree object of `<stem>.objects.csv`: a footprint segment of `length_m` through
    (easting, northing) along `heading_deg`, `width_m` across."""

    object_id: str
    kind: str
    easting: float
    northing: float
    length_m: float
    width_m: float
    heading_deg: float

    def distance(self, easting: float, northing: float) -> float:
        """From a point to the footprint's edge (0 inside)."""
        heading = math.radians(self.heading_deg)
        ux, uy = math.cos(heading), math.sin(heading)
        dx, dy = easting - self.easting, northing - self.northing
        along = max(-self.length_m / 2, min(self.length_m / 2, dx * ux + dy * uy))
        gap = math.hypot(dx - along * ux, dy - along * uy)
        return max(0.0, gap - self.width_m / 2)


@dataclass(frozen=True)
class Detection:
    tree_id: str
    easting: float | None  # None: never placed in UTM
    northing: float | None
    width_m: float
    height_m: float
    status: str | None = None  # the replay's `status` column if it has one (found/missing)
    field_id: str | None = None
    # The replay's `height_top_seen` (None: not in its output): False marks a height that
    # is a lower bound, the crown's top not bracketed within 5 % by the LiDAR's beams.
    height_top_seen: bool | None = None
    # The replay's `width_sides_seen` (None: not in its output or not judged): 1 marks a
    # width that is a lower bound, the crown seen from one side of its row only.
    width_sides_seen: int | None = None


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
class MissingScore:
    """One missing tree (in the field map, not planted) in one run."""

    truth: TruthTree
    detections: int  # detections on its position: each one a false positive
    reported_missing: bool | None  # the replay said so (None: its output has no status)


@dataclass(frozen=True)
class RunScore:
    trees: tuple[TreeScore, ...]
    false_positives: tuple[Detection, ...]  # on no truth tree (or never placed)
    missing: tuple[MissingScore, ...] = ()
    false_positive_kinds: tuple[str, ...] = ()  # what each false positive hit, in order

    @property
    def found(self) -> int:
        return sum(t.detection is not None for t in self.trees)

    @property
    def duplicates(self) -> int:
        return sum(t.duplicates for t in self.trees)

    def false_positives_by_kind(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for kind in self.false_positive_kinds:
            out[kind] = out.get(kind, 0) + 1
        return out


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
    # Of the found trees, those whose top the replay says it saw, and the height MAPE
    # over them alone (NaN if none): what the LiDAR's view allowed.
    top_seen: int = 0
    mape_height_top_seen: float = math.nan
    # Of the found trees, those seen from both sides of their row, and the width MAPE
    # over them alone (NaN if none); the others' widths are lower bounds.
    sides_seen: int = 0
    mape_width_sides_seen: float = math.nan
    one_sided: int = 0  # found trees whose width is a lower bound (seen from one side)


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
    detections: Sequence[Detection],
    truths: Sequence[TruthTree],
    gate_m: float = DEFAULT_GATE_M,
    objects: Sequence[TruthObject] = (),
) -> RunScore:
    # Rows the replay marks missing are its report on field-map trees, not detections.
    reports = [d for d in detections if d.status == "missing"]
    detections = [d for d in detections if d.status != "missing"]
    xy = np.array(
        [(np.nan, np.nan) if d.easting is None else (d.easting, d.northing) for d in detections],
        dtype=float,
    ).reshape(-1, 2)
    truth_xy = np.array([(t.easting, t.northing) for t in truths], dtype=float).reshape(-1, 2)
    assigned = nearest_within(xy, truth_xy, gate_m)
    on_tree: dict[int, list[int]] = {}
    false_positives, kinds = [], []
    for i, j in enumerate(assigned):
        if j is None:
            false_positives.append(detections[i])
            kinds.append(_object_kind(detections[i], objects))
        elif truths[j].kind == "missing":
            false_positives.append(detections[i])
            kinds.append("missing_tree")
            on_tree.setdefault(j, []).append(i)
        else:
            on_tree.setdefault(j, []).append(i)
    trees, missing = [], []
    has_status = any(d.status is not None for d in (*detections, *reports))
    for j, truth in enumerate(truths):
        mine = on_tree.get(j, [])
        if truth.kind == "missing":
            reported = None
            if has_status:
                reported = any(
                    r.field_id == truth.tree_id
                    or (
                        r.easting is not None
                        and math.hypot(r.easting - truth.easting, r.northing - truth.northing)
                        <= gate_m
                    )
                    for r in reports
                )
            missing.append(MissingScore(truth, len(mine), reported))
            continue
        primary = min(mine, key=lambda i: (math.dist(xy[i], truth_xy[j]), i)) if mine else None
        trees.append(
            TreeScore(
                truth, None if primary is None else detections[primary], max(0, len(mine) - 1)
            )
        )
    return RunScore(tuple(trees), tuple(false_positives), tuple(missing), tuple(kinds))


def _object_kind(detection: Detection, objects: Sequence[TruthObject]) -> str:
    """The kind of the nearest object within its footprint + OBJECT_MARGIN_M, else other."""
    if detection.easting is None or not objects:
        return "other"
    distance, kind = min(
        (o.distance(detection.easting, detection.northing), o.kind) for o in objects
    )
    return kind if distance <= OBJECT_MARGIN_M else "other"


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
        seen = [t for t in hits if t.detection.height_top_seen]
        both = [t for t in hits if t.detection.width_sides_seen == 2]
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
                top_seen=len(seen),
                mape_height_top_seen=_mean([t.height_ape for t in seen]),
                sides_seen=len(both),
                mape_width_sides_seen=_mean([t.width_ape for t in both]),
                one_sided=sum(t.detection.width_sides_seen == 1 for t in hits),
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
    """The simulator's REC.truth.csv (`kind` absent: every row a tree, as written before
    the field conditions)."""
    try:
        with open(path, newline="") as f:
            return [
                TruthTree(
                    r["tree_id"],
                    r["row"],
                    float(r["easting"]),
                    float(r["northing"]),
                    _number(r["width_m"]),
                    _number(r["height_m"]),
                    r.get("kind") or "tree",
                )
                for r in csv.DictReader(f)
            ]
    except FileNotFoundError:
        raise SourceError(f"{path}: no truth CSV beside the recording (re-simulate)") from None
    except (KeyError, ValueError) as exc:
        raise SourceError(f"{path}: not a truth CSV written by treetraits sim ({exc})") from None


def objects_path(truth_csv: Path) -> Path:
    """`<stem>.objects.csv` beside `<stem>.truth.csv`."""
    truth_csv = Path(truth_csv)
    return truth_csv.with_name(truth_csv.name.removesuffix(".truth.csv") + ".objects.csv")


def load_objects(path: Path) -> list[TruthObject]:
    """The simulator's `<stem>.objects.csv`; no file (an older recording): no objects."""
    try:
        with open(path, newline="") as f:
            return [
                TruthObject(
                    r["object_id"],
                    r["kind"],
                    float(r["easting"]),
                    float(r["northing"]),
                    float(r["length_m"]),
                    float(r["width_m"]),
                    float(r["heading_deg"]),
                )
                for r in csv.DictReader(f)
            ]
    except FileNotFoundError:
        return []
    except (KeyError, ValueError) as exc:
        raise SourceError(f"{path}: not an objects CSV written by treetraits sim ({exc})") from None


def _number(text: str) -> float:
    return float(text) if text.strip() else math.nan


def detections_from_trees(trees: Iterable) -> list[Detection]:
    """`drivers.records.Tree` records (a replay's output) as detections; a `status` field
    (found/missing), where the records have one, is kept."""
    return [
        Detection(
            t.tree_id,
            t.easting,
            t.northing,
            math.nan if t.width_m is None else float(t.width_m),
            math.nan if t.height_m is None else float(t.height_m),
            getattr(t, "status", None),
            getattr(t, "field_id", None),
            getattr(t, "height_top_seen", None),
            getattr(t, "width_sides_seen", None),
        )
        for t in trees
    ]
