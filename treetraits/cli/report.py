"""`treetraits report`: one self-contained HTML page of a run or a season (docs/season.md,
"Report")."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    report = commands.add_parser(
        "report",
        help="write one HTML page of a run or a season, to open offline",
        description=(
            "Write one self-contained HTML page (images embedded, nothing fetched) of a run "
            "directory (replay's or batch's outputs) or a season store: the map of the block "
            "with each tree drawn to its width, coloured by height or NDVI and labelled with "
            "its field-map id (the run's id, marked #, where it was not matched), over the "
            "robot's path, missing trees and rejected objects marked, the per-row table, "
            "histograms of width, height and NDVI, the objects rejected and why, and a note "
            "where the run had no GNSS fix; for a season also the growth map and a few "
            "trees' histories against the survey dates."
        ),
    )
    report.add_argument("source", type=Path, metavar="RUN_DIR|SEASON.sqlite")
    report.add_argument("--out", required=True, type=Path, help="the HTML file to write")
    report.add_argument(
        "--colour",
        choices=("height", "ndvi"),
        default="height",
        help="what the map's colours show (default height)",
    )
    report.add_argument("--force", action="store_true", help="replace an existing page")
    report.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.extras import require_extra
    from treetraits.files import check_output_file

    check_output_file(args.out, force=args.force)  # before any work: a directory, a page
    require_extra("season", "treetraits report", ("matplotlib",))
    from treetraits.season.report import load_report_data, write_report
    from treetraits.service.outdir import OutputDir

    data = load_report_data(args.source)  # inputs first: a bad source touches nothing
    output = OutputDir(
        args.out.parent if str(args.out.parent) else Path("."),
        (args.out.name,),
        force=args.force,
        inputs=(args.source,),
        tag=args.out.name,
        what="a report",
        target=args.out,
    )
    with output as staging:
        write_report(staging / args.out.name, data, colour=args.colour)
    print(f"report: {args.out}")
    return 0
