"""An evaluation's files: OUT/table.md, OUT/table.csv, OUT/maps/<case>.png, and the JSON."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from treetraits.evaluation.metrics import load_truth
from treetraits.evaluation.plot import plot_case
from treetraits.evaluation.results import best_method, score, summarize, to_json
from treetraits.evaluation.run import Evaluation
from treetraits.evaluation.table import markdown, write_csv


@dataclass(frozen=True)
class Report:
    summary: dict  # what --json prints
    markdown: str  # table.md
    maps: tuple[Path, ...]


def write_report(evaluation: Evaluation, out: Path) -> Report:
    out = Path(out)
    results = score(evaluation)
    summaries = summarize(results, evaluation.methods)
    best = best_method(summaries).method
    text = markdown(results, evaluation.methods, summaries, best, evaluation.seeds)
    (out / "table.md").write_text(text)
    write_csv(out / "table.csv", results)
    summary = to_json(evaluation, results)
    (out / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    maps_dir = out / "maps"
    maps_dir.mkdir(exist_ok=True)
    maps = []
    for case in evaluation.cases:
        # The map shows the case's first seed: one run, every method over the same truth.
        sim = next(s for s in evaluation.simulated if s.case == case.name)
        detections = {
            r.method: r.detections
            for r in evaluation.replayed
            if r.case == case.name and r.seed == sim.seed
        }
        path = maps_dir / f"{case.name}.png"
        plot_case(path, case, sim.seed, load_truth(sim.truth_csv), detections)
        maps.append(path)
    return Report(summary, text, tuple(maps))
