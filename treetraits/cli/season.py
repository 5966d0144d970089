"""`treetraits season`: the trees of a season store and their history (docs/season.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    season = commands.add_parser(
        "season",
        help="list, show and export the trees of a season store",
        description=(
            "Read a season store that `treetraits batch` wrote: every tree with its surveys "
            "(trees), one tree's history (tree ID), or the season as a long CSV and a "
            "GeoJSON with each tree's growth (export)."
        ),
    )
    sub = season.add_subparsers(dest="season_command", metavar="SUBCOMMAND", required=True)
    trees = sub.add_parser(
        "trees",
        help="every tree with its surveys and traits over time",
        description="Every tree of the season with its surveys by date: found (width, "
        'height, NDVI) or missing. --json: {"trees": [{"id": ..., "surveys": '
        '[{"date": ..., "width_m": ...}]}]} (docs/season.md).',
    )
    tree = sub.add_parser(
        "tree",
        help="one tree's history",
        description="One tree's surveys by date (its field id, or pos-N for a tree "
        "linked by position).",
    )
    tree.add_argument("tree_id", metavar="ID", help="the tree's season id (field id or pos-N)")
    export = sub.add_parser(
        "export",
        help="write DIR/season.csv (one line per tree and survey) and DIR/season.geojson "
        "(per-tree growth)",
    )
    export.add_argument("--out", required=True, type=Path, help="output directory")
    export.add_argument("--force", action="store_true", help="replace an earlier export in DIR")
    for command in (trees, tree, export):
        command.add_argument("--season", required=True, type=Path, help="season store (SQLite)")
    for command in (trees, tree):
        command.add_argument("--json", action="store_true", help="print as JSON")
    season.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.readonly import sqlite_errors
    from treetraits.season.store import SeasonError, SeasonStore, season_trees_json

    # Read-only (treetraits/readonly.py); an SQLite error names the store.
    with SeasonStore(args.season, create=False) as season, sqlite_errors(args.season):
        if args.season_command == "export":
            return _export(args, season)
        trees = season.trees(args.tree_id if args.season_command == "tree" else None)
    if args.season_command == "tree" and not trees:
        raise SeasonError(f"{args.season}: no tree {args.tree_id!r} (`season trees` lists them)")
    if args.json:
        document = season_trees_json(trees)
        # `tree ID`: that tree's object; an id in several blocks (their maps' T1): all of them.
        single = args.season_command == "tree" and len(trees) == 1
        print(json.dumps(document["trees"][0] if single else document, indent=1))
        return 0
    print(format_history(trees))
    return 0


def _export(args: argparse.Namespace, season) -> int:
    from treetraits.season.export import (
        CSV_NAME,
        EXPORT_OUTPUTS,
        GEOJSON_NAME,
        write_season_csv,
        write_season_geojson,
    )
    from treetraits.service.outdir import OutputDir

    output = OutputDir(
        args.out, EXPORT_OUTPUTS, force=args.force, inputs=(args.season,), what="an earlier export"
    )
    trees = season.trees()
    with output as staging:
        write_season_csv(staging / CSV_NAME, trees)
        write_season_geojson(staging / GEOJSON_NAME, trees)
    print(f"{len(trees)} trees: {args.out / CSV_NAME}, {args.out / GEOJSON_NAME}")
    return 0


def format_history(trees) -> str:
    """One block of lines per tree: its surveys by date with the traits measured, a
    lower bound marked `>` (as `replay`'s table), and what the marks mean."""
    from treetraits.files import iso_utc
    from treetraits.pipeline.trees import (
        HEIGHT_BOUND_LEGEND,
        WIDTH_BOUND_LEGEND,
        height_bounded,
        marked,
        width_bounded,
    )

    lines = []
    for t in trees:
        where = f"{t.lat:.7f}, {t.lon:.7f}" if t.lat is not None else "no position"
        lines.append(f"{t.tree_id}  block {t.block}  row {t.row or '-'}  ({where})")
        for v in t.visits:
            traits = (
                "missing"
                if v.status == "missing"
                else f"width {marked(v.width_m, width_bounded(v.width_sides_seen))} m  "
                f"height {marked(v.height_m, height_bounded(v.height_top_seen))} m  "
                f"NDVI {marked(v.ndvi, False)}"
            )
            lines.append(f"  {iso_utc(v.t_start)[:16]}  survey {v.survey_id}  {traits}")
    if not lines:
        return "no trees in this season"
    found = [v for t in trees for v in t.visits if v.status == "found"]
    if any(width_bounded(v.width_sides_seen) for v in found):
        lines.append(WIDTH_BOUND_LEGEND)
    if any(height_bounded(v.height_top_seen) for v in found):
        lines.append(HEIGHT_BOUND_LEGEND)
    if any(v.height_top_seen is None or v.width_sides_seen is None for v in found):
        lines.append(UNKNOWN_FLAGS)
    return "\n".join(lines)


# Surveys without the flags (added by a treetraits that kept none, or RPH's): unmarked.
UNKNOWN_FLAGS = (
    "some surveys do not say how their traits were measured (added before the season kept "
    "it, or by RPH): not known whether they are lower bounds (`batch --force` processes "
    "their recordings again)"
)
