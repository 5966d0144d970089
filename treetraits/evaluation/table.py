"""Table I side by side with the paper's: table.md (also printed) and table.csv."""

from __future__ import annotations

import csv
import math
from pathlib import Path

from treetraits.evaluation.results import CaseMethodResult, MethodSummary, row_json

CSV_COLUMNS = (
    "case",
    "row",
    "method",
    "runs",
    "trees",
    "found",
    "gt_width_m",
    "width_mean_m",
    "width_sd_m",
    "mape_width",
    "gt_height_m",
    "height_mean_m",
    "height_sd_m",
    "mape_height",
    "paper_mape_width_ours",
    "paper_mape_width_rph",
    "paper_mape_height_ours",
    "paper_mape_height_rph",
    "case_trees_found",
    "case_trees_total",
    "case_duplicates",
    "case_false_positives",
    "case_position_rmse_m",
    "case_s_per_scan",
    # Field conditions (appended): "kind:n;kind:n", and the missing trees' figures.
    "case_false_positives_by_kind",
    "case_missing_trees",
    "case_missing_detected",
    "case_missing_reported",
    # Heights (appended): found trees whose top was in view, and the height MAPE over them.
    "top_seen",
    "mape_height_top_seen",
    # Widths (appended): found trees seen from both sides of their row, the width MAPE
    # over them, and the found trees seen from one side only (their widths lower bounds).
    "sides_seen",
    "mape_width_sides_seen",
    "one_sided",
)


def write_csv(path: Path, results: list[CaseMethodResult]) -> None:
    """One line per (case, row, method); the case's detection figures repeated on each."""
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, CSV_COLUMNS, lineterminator="\n")
        writer.writeheader()
        for r in results:
            for row in r.rows:
                cells = row_json(r.case, row)
                cells.pop("row")
                writer.writerow(
                    {
                        "case": r.case.name,
                        "row": row.row,
                        "method": r.method,
                        "runs": r.runs,
                        **{k: "" if v is None else v for k, v in cells.items()},
                        "case_trees_found": r.trees_found,
                        "case_trees_total": r.trees_total,
                        "case_duplicates": r.duplicates,
                        "case_false_positives": r.false_positives,
                        "case_position_rmse_m": _cell(r.position_rmse_m, 3),
                        "case_s_per_scan": _cell(r.s_per_scan, 4),
                        "case_false_positives_by_kind": _kinds(r.false_positives_by_kind),
                        "case_missing_trees": r.missing_trees,
                        "case_missing_detected": r.missing_detected,
                        "case_missing_reported": ""
                        if r.missing_reported is None
                        else r.missing_reported,
                    }
                )


def markdown(
    results: list[CaseMethodResult],
    methods: tuple[str, ...],
    summaries: list[MethodSummary],
    best: str,
    seeds: tuple[int, ...],
) -> str:
    """Two tables: traits per row (ours per method, then the paper's), then detections."""
    lines = [
        f"# Table I on the twin ({len(seeds)} seed(s) per case: {', '.join(map(str, seeds))})",
        "",
        "MAPE (%) per tree row; `paper`/`RPH` (published) are Table I's numbers for the "
        "same setup. Widths and heights in m: ground truth mean, then the best method's "
        "mean +- sd over trees and runs.",
        "",
    ]
    by_key = {(r.case.name, r.method): r for r in results}
    cases = list(dict.fromkeys(r.case.name for r in results))
    for trait in ("width", "height"):
        header = (
            ["case", "row", f"GT {trait}", f"{best} {trait}"]
            + [f"{m}" for m in methods]
            + ["paper (published)", "RPH (published)"]
        )
        lines += [f"## {trait.capitalize()} MAPE (%)", "", _md_row(header)]
        lines.append(_md_row(["---"] * len(header)))
        for name in cases:
            first = by_key[(name, methods[0])]
            for i, row in enumerate(first.rows):
                best_row = by_key[(name, best)].rows[i]
                paper = first.case.paper_row(row.row)
                cells = [
                    name,
                    row.row,
                    _cell(getattr(row, f"gt_{trait}_m"), 2),
                    _pm(getattr(best_row, f"{trait}_mean_m"), getattr(best_row, f"{trait}_sd_m")),
                ]
                cells += [
                    _cell(getattr(by_key[(name, m)].rows[i], f"mape_{trait}"), 2) for m in methods
                ]
                cells += [
                    _cell(getattr(paper, f"{trait}_ours"), 2) if paper else "-",
                    _cell(getattr(paper, f"{trait}_rph"), 2) if paper else "-",
                ]
                lines.append(_md_row(cells))
        lines.append("")
    header = ["case", "method", "found / trees", "duplicates", "false pos.", "RMSE m", "s/scan",
              "heights measured", "widths one-sided"]  # fmt: skip
    lines += ["## Detections, position and time", "", _md_row(header)]
    lines.append(_md_row(["---"] * len(header)))
    for r in results:
        lines.append(
            _md_row(
                [
                    r.case.name,
                    r.method,
                    f"{r.trees_found} / {r.trees_total}",
                    str(r.duplicates),
                    str(r.false_positives),
                    _cell(r.position_rmse_m, 3),
                    _cell(r.s_per_scan, 4),
                    f"{sum(row.top_seen for row in r.rows)} / {r.trees_found}",
                    f"{sum(row.one_sided for row in r.rows)} / {r.trees_found}",
                ]
            )
        )
    if any(r.case.suite != "paper" or r.missing_trees for r in results):
        header = ["case", "method", "false pos. by what they hit", "missing trees",
                  "detected on a missing tree", "reported missing"]  # fmt: skip
        lines += ["", "## Field conditions", "", _md_row(header), _md_row(["---"] * 6)]
        for r in results:
            lines.append(
                _md_row(
                    [
                        r.case.name,
                        r.method,
                        _kinds(r.false_positives_by_kind) or "-",
                        str(r.missing_trees),
                        str(r.missing_detected),
                        "-" if r.missing_reported is None else str(r.missing_reported),
                    ]
                )
            )
    lines += ["", "## Over all cases", ""]
    header = [
        "method",
        "worst row W %",
        "worst row H %",
        "worst row H % (top seen)",
        "tops seen / found",
        "worst row W % (both sides)",
        "both sides / found",
        "found / trees",
        "dup.",
        "false pos.",
        "RMSE m",
        "s/scan",
    ]
    lines += [_md_row(header), _md_row(["---"] * len(header))]
    for s in summaries:
        lines.append(
            _md_row(
                [
                    s.method + (" (best)" if s.method == best else ""),
                    _cell(s.worst_row_mape_width, 2),
                    _cell(s.worst_row_mape_height, 2),
                    _cell(s.worst_row_mape_height_top_seen, 2),
                    f"{s.heights_top_seen} / {s.trees_found}",
                    _cell(s.worst_row_mape_width_sides_seen, 2),
                    f"{s.widths_sides_seen} / {s.trees_found}",
                    f"{s.trees_found} / {s.trees_total}",
                    str(s.duplicates),
                    str(s.false_positives),
                    _cell(s.position_rmse_m, 3),
                    _cell(s.s_per_scan, 4),
                ]
            )
        )
    lines += [
        "",
        "Paper, worst simulated rows: width 12.14 %, height 14.71 % (its method); "
        "0.22 s per detection on the Xavier (RPH 0.53 s).",
        "top seen: found trees whose height is measured to 5 % (the crown's top bracketed by "
        "the beams that passed over it); the others' heights are lower bounds "
        "(docs/pipeline.md, 'Heights the LiDAR cannot see'). both sides: found trees seen "
        "from both sides of their row; the others' widths are lower bounds ('Widths seen "
        "from one side').",
        "s/scan here: wall time of the whole replay (decode, localisation, NDVI, fusion, "
        "detection, tracking, traits, store) divided by the scans, on this machine.",
        "",
    ]
    return "\n".join(lines)


def _kinds(by_kind: dict[str, int]) -> str:
    return ";".join(f"{kind}:{n}" for kind, n in by_kind.items())


def _md_row(cells: list[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def _cell(value: float | None, digits: int) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    return f"{value:.{digits}f}"


def _pm(mean: float, sd: float) -> str:
    if math.isnan(mean):
        return "-"
    return f"{mean:.2f} +- {sd:.2f}" if not math.isnan(sd) else f"{mean:.2f}"
