"""An evaluation's numbers: per case and method, Table I's rows and the detection counts;
the headline over all cases for the best method."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from treetraits.evaluation.cases import Case, PaperRow
from treetraits.evaluation.metrics import (
    DEFAULT_GATE_M,
    RowStats,
    RunScore,
    load_objects,
    load_truth,
    objects_path,
    position_rmse,
    row_stats,
    score_run,
)
from treetraits.evaluation.run import Evaluation


@dataclass(frozen=True)
class CaseMethodResult:
    case: Case
    method: str
    runs: int
    rows: tuple[RowStats, ...]
    trees_total: int
    trees_found: int
    duplicates: int
    false_positives: int
    position_rmse_m: float
    s_per_scan: float  # replay wall time / scans, mean over runs
    scores: tuple[RunScore, ...]
    # Field conditions: what the false positives hit, and the missing trees (in the field
    # map, not planted): how many, how many detections were made on one (each also a false
    # positive), and how many the replay reported missing (None: no status in its output).
    false_positives_by_kind: dict[str, int] = dataclasses.field(default_factory=dict)
    missing_trees: int = 0
    missing_detected: int = 0
    missing_reported: int | None = None


@dataclass(frozen=True)
class MethodSummary:
    method: str
    worst_row_mape_width: float
    worst_row_mape_height: float
    trees_found: int
    trees_total: int
    duplicates: int
    false_positives: int
    position_rmse_m: float
    s_per_scan: float
    # Heights over the found trees whose top was in view (rows with none left out), and
    # how many found trees that is: the rest have a height that is a lower bound.
    worst_row_mape_height_top_seen: float = math.nan
    heights_top_seen: int = 0
    # Widths over the found trees seen from both sides (rows with none left out), and
    # how many that is: the rest have a width that is a lower bound.
    worst_row_mape_width_sides_seen: float = math.nan
    widths_sides_seen: int = 0


def score(evaluation: Evaluation, gate_m: float = DEFAULT_GATE_M) -> list[CaseMethodResult]:
    truths = {(s.case, s.seed): load_truth(s.truth_csv) for s in evaluation.simulated}
    objects = {
        (s.case, s.seed): load_objects(objects_path(s.truth_csv)) for s in evaluation.simulated
    }
    out = []
    for case in evaluation.cases:
        for method in evaluation.methods:
            runs = [r for r in evaluation.replayed if r.case == case.name and r.method == method]
            scores = tuple(
                score_run(r.detections, truths[(r.case, r.seed)], gate_m, objects[(r.case, r.seed)])
                for r in runs
            )
            by_kind: dict[str, int] = {}
            for s in scores:
                for kind, n in s.false_positives_by_kind().items():
                    by_kind[kind] = by_kind.get(kind, 0) + n
            missing = [m for s in scores for m in s.missing]
            reported = [m.reported_missing for m in missing if m.reported_missing is not None]
            out.append(
                CaseMethodResult(
                    case=case,
                    method=method,
                    runs=len(runs),
                    rows=tuple(row_stats(scores, case.rows)),
                    trees_total=sum(len(s.trees) for s in scores),
                    trees_found=sum(s.found for s in scores),
                    duplicates=sum(s.duplicates for s in scores),
                    false_positives=sum(len(s.false_positives) for s in scores),
                    position_rmse_m=position_rmse(scores),
                    s_per_scan=_mean([r.s_per_scan for r in runs]),
                    scores=scores,
                    false_positives_by_kind=dict(sorted(by_kind.items())),
                    missing_trees=len(missing),
                    missing_detected=sum(m.detections > 0 for m in missing),
                    missing_reported=sum(reported) if reported else None,
                )
            )
    return out


def summarize(results: list[CaseMethodResult], methods: tuple[str, ...]) -> list[MethodSummary]:
    out = []
    for method in methods:
        mine = [r for r in results if r.method == method]
        rows = [row for r in mine for row in r.rows]
        out.append(
            MethodSummary(
                method=method,
                worst_row_mape_width=_worst([row.mape_width for row in rows]),
                worst_row_mape_height=_worst([row.mape_height for row in rows]),
                trees_found=sum(r.trees_found for r in mine),
                trees_total=sum(r.trees_total for r in mine),
                duplicates=sum(r.duplicates for r in mine),
                false_positives=sum(r.false_positives for r in mine),
                position_rmse_m=position_rmse([s for r in mine for s in r.scores]),
                s_per_scan=_mean([r.s_per_scan for r in mine]),
                worst_row_mape_height_top_seen=_worst(
                    [row.mape_height_top_seen for row in rows if row.top_seen]
                ),
                heights_top_seen=sum(row.top_seen for row in rows),
                worst_row_mape_width_sides_seen=_worst(
                    [row.mape_width_sides_seen for row in rows if row.sides_seen]
                ),
                widths_sides_seen=sum(row.sides_seen for row in rows),
            )
        )
    return out


def best_method(summaries: list[MethodSummary]) -> MethodSummary:
    """The lowest worst-row MAPE (the larger of width and height), then the lower sum of
    both, then the order given. A method that lost a row entirely (NaN) ranks last."""

    def key(s: MethodSummary):
        worst = max(s.worst_row_mape_width, s.worst_row_mape_height)
        both = s.worst_row_mape_width + s.worst_row_mape_height
        return (math.isnan(worst), worst if not math.isnan(worst) else 0.0, both)

    return min(summaries, key=key)


def to_json(evaluation: Evaluation, results: list[CaseMethodResult]) -> dict:
    summaries = summarize(results, evaluation.methods)
    best = best_method(summaries)
    return {
        "best_method": best.method,
        "best_method_rule": "lowest worst-row MAPE over width and height, all cases",
        "worst_row_mape_width": _round(best.worst_row_mape_width),
        "worst_row_mape_height": _round(best.worst_row_mape_height),
        "trees_found": best.trees_found,
        "trees_total": best.trees_total,
        "duplicates": best.duplicates,
        "false_positives": best.false_positives,
        "position_rmse_m": _round(best.position_rmse_m, 3),
        "s_per_scan": _round(best.s_per_scan, 4),
        "worst_row_mape_height_top_seen": _round(best.worst_row_mape_height_top_seen),
        "heights_top_seen": best.heights_top_seen,
        "worst_row_mape_width_sides_seen": _round(best.worst_row_mape_width_sides_seen),
        "widths_sides_seen": best.widths_sides_seen,
        "methods": {
            s.method: {
                "worst_row_mape_width": _round(s.worst_row_mape_width),
                "worst_row_mape_height": _round(s.worst_row_mape_height),
                "trees_found": s.trees_found,
                "trees_total": s.trees_total,
                "duplicates": s.duplicates,
                "false_positives": s.false_positives,
                "position_rmse_m": _round(s.position_rmse_m, 3),
                "s_per_scan": _round(s.s_per_scan, 4),
                "worst_row_mape_height_top_seen": _round(s.worst_row_mape_height_top_seen),
                "heights_top_seen": s.heights_top_seen,
                "worst_row_mape_width_sides_seen": _round(s.worst_row_mape_width_sides_seen),
                "widths_sides_seen": s.widths_sides_seen,
            }
            for s in summaries
        },
        "seeds": list(evaluation.seeds),
        "cases": [
            {
                "case": r.case.name,
                "method": r.method,
                "runs": r.runs,
                "trees_found": r.trees_found,
                "trees_total": r.trees_total,
                "duplicates": r.duplicates,
                "false_positives": r.false_positives,
                "position_rmse_m": _round(r.position_rmse_m, 3),
                "s_per_scan": _round(r.s_per_scan, 4),
                "suite": r.case.suite,
                "false_positives_by_kind": r.false_positives_by_kind,
                "missing_trees": r.missing_trees,
                "missing_detected": r.missing_detected,
                "missing_reported_missing": r.missing_reported,
                "rows": [row_json(r.case, row) for row in r.rows],
            }
            for r in results
        ],
        "simulated": [
            {
                "case": s.case,
                "seed": s.seed,
                "driving_s": round(s.driving_s, 1),
                "simulate_s": round(s.simulate_s, 1),
                "cached": s.cached,
            }
            for s in evaluation.simulated
        ],
        "wall_s": round(evaluation.wall_s, 1),
        "jobs": evaluation.jobs,
    }


def row_json(case: Case, row: RowStats) -> dict:
    paper: PaperRow | None = case.paper_row(row.row)
    return {
        "row": row.row,
        "trees": row.trees,
        "found": row.found,
        "gt_width_m": _round(row.gt_width_m, 3),
        "width_mean_m": _round(row.width_mean_m, 3),
        "width_sd_m": _round(row.width_sd_m, 3),
        "mape_width": _round(row.mape_width),
        "gt_height_m": _round(row.gt_height_m, 3),
        "height_mean_m": _round(row.height_mean_m, 3),
        "height_sd_m": _round(row.height_sd_m, 3),
        "mape_height": _round(row.mape_height),
        "top_seen": row.top_seen,
        "mape_height_top_seen": _round(row.mape_height_top_seen),
        "sides_seen": row.sides_seen,
        "mape_width_sides_seen": _round(row.mape_width_sides_seen),
        "one_sided": row.one_sided,
        "paper_mape_width_ours": paper.width_ours if paper else None,
        "paper_mape_width_rph": paper.width_rph if paper else None,
        "paper_mape_height_ours": paper.height_ours if paper else None,
        "paper_mape_height_rph": paper.height_rph if paper else None,
    }


def _worst(values: list[float]) -> float:
    # A row where the method found no tree has no MAPE: that is the worst of all.
    if not values or any(math.isnan(v) for v in values):
        return math.nan
    return max(values)


def _mean(values: list[float]) -> float:
    values = [v for v in values if not math.isnan(v)]
    return sum(values) / len(values) if values else math.nan


def _round(value: float, digits: int = 2) -> float | None:
    return None if value is None or math.isnan(value) else round(value, digits)
