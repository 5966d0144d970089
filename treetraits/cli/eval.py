"""`treetraits eval`: the paper's Table I reproduced on the digital twin, side by side with
the published numbers (docs/evaluation.md)."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from treetraits.errors import ConfigError


def register(commands: argparse._SubParsersAction) -> None:
    from treetraits.evaluation.methods import DEFAULT_METHODS, METHODS
    from treetraits.sim import FOLIAGE_MODELS as MODELS

    ev = commands.add_parser(
        "eval",
        help="reproduce the paper's Table I on the twin",
        description=(
            "Simulate the paper's cases (5 seeds each), replay them with each method, and "
            "print Table I beside the paper's numbers: MAPE per row for width and height, "
            "detections, duplicates, position error, time per scan. Writes OUT/table.md, "
            "OUT/table.csv, OUT/summary.json and OUT/maps/<case>.png; recordings are cached "
            "in OUT/cases/ and reused by a rerun with the same settings and software."
        ),
    )
    ev.add_argument("--out", type=Path, help="output directory (required but with --list)")
    ev.add_argument("--quick", action="store_true", help="one seed per case (= --seeds 1)")
    ev.add_argument("--seeds", type=int, help="seeds per case, K..K+N-1 (default 5)")
    ev.add_argument(
        "--first-seed",
        type=int,
        default=0,
        metavar="K",
        help="the first seed (default 0): report on seeds that settings were not tuned on",
    )
    ev.add_argument("--json", action="store_true", help="print the summary as one JSON object")
    ev.add_argument(
        "--suite",
        choices=("paper", "field"),
        default="paper",
        help="paper: the paper's Table I cases (default); field: a real grove's conditions "
        "(slopes and uneven ground, weeds, posts, people, vehicles, walls, hedgerows, young "
        "and old trees, missing trees, irregular crowns, wind), scored also for false "
        "positives by what they hit and for missing trees",
    )
    ev.add_argument(
        "--cases",
        help="comma list of case names or prefixes of the suite, or 'all' (default: the "
        "suite's default cases; for paper, its simulated cases and the CitrusFarm grove)",
    )
    ev.add_argument(
        "--methods",
        help=f"comma list of {', '.join(METHODS)} (default {','.join(DEFAULT_METHODS)})",
    )
    ev.add_argument(
        "--jobs", type=int, help=f"worker processes (default: the CPUs, {os.cpu_count()})"
    )
    ev.add_argument(
        "--config",
        type=Path,
        help="config file (TOML, as `treetraits run` takes): its [detection], [tracking], "
        "[traits], [localization] and [output] gates are used by every replay (default: "
        "the built-in defaults); each method still sets pipeline.method and traits.method",
    )
    ev.add_argument(
        "--foliage",
        choices=tuple(MODELS),
        metavar="MODEL",
        help=f"grow every case's crowns with this foliage model ({', '.join(MODELS)}; "
        "default: each case's own, scattered in the paper suite, mixed in the field suite)",
    )
    ev.add_argument(
        "--lidar-height",
        type=float,
        metavar="M",
        help="simulate every case with the LiDAR this high above base_link, in metres "
        "(0.2-5; default: the calibration's, a Jackal's 0.38 m): what a tractor's "
        "bonnet (~1.7) or cab (~2.6) mount measures",
    )
    ev.add_argument("--list", action="store_true", help="list the cases and exit")
    ev.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.extras import require_extra

    require_extra("eval", "treetraits eval")
    from treetraits.cli.sim import LIDAR_HEIGHT_M, _within
    from treetraits.evaluation.cases import CASES, select_cases
    from treetraits.evaluation.report import write_report
    from treetraits.evaluation.run import parse_methods, run_evaluation
    from treetraits.service.config import load_config
    from treetraits.service.outdir import output_lock

    if args.list:
        for case in CASES:
            if case.suite != args.suite:
                continue
            print(f"{case.name:22} {'' if case.default else '(not default) '}{case.title}")
        return 0
    if args.out is None:
        raise ConfigError("--out DIR is required: where the tables, maps and cases go")
    if args.quick and args.seeds not in (None, 1):
        raise ConfigError(f"--quick runs one seed; it cannot go with --seeds {args.seeds}")
    seeds = 1 if args.quick else (5 if args.seeds is None else args.seeds)
    if seeds < 1:
        raise ConfigError(f"--seeds must be >= 1, got {seeds}")
    if args.first_seed < 0:
        raise ConfigError(f"--first-seed must be >= 0, got {args.first_seed}")
    if args.jobs is not None and args.jobs < 1:
        raise ConfigError(f"--jobs must be >= 1, got {args.jobs}")
    cases = select_cases(args.cases, suite=args.suite)
    if args.foliage is not None:
        cases = [case.with_foliage(args.foliage) for case in cases]
    if args.lidar_height is not None:
        _within("--lidar-height", args.lidar_height, *LIDAR_HEIGHT_M)
        cases = [case.with_lidar_height(args.lidar_height) for case in cases]
    methods = parse_methods(args.methods)
    config = load_config(args.config)
    # The lock only: a rerun reuses the recordings cached in OUT/cases/ and rewrites the
    # tables, so no --force; two evaluations into one OUT would mix them (docs/cli.md).
    with output_lock(args.out):
        evaluation = run_evaluation(
            cases,
            range(args.first_seed, args.first_seed + seeds),
            methods,
            args.out,
            args.jobs,
            config=config,
        )
        report = write_report(evaluation, args.out)
    if args.json:
        print(json.dumps(report.summary, indent=1))
    else:
        print(report.markdown)
        print(
            f"{len(evaluation.simulated)} recordings, {len(evaluation.replayed)} replays in "
            f"{evaluation.wall_s:.0f} s ({evaluation.jobs} jobs); outputs in {args.out}/"
        )
    return 0
