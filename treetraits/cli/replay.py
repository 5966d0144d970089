"""`treetraits replay`: a recording through the whole pipeline, with the run's outputs."""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

from treetraits.cli.stopping import EXIT_BY_SIGNAL, StopOnSignal
from treetraits.damage import add_allow_damaged, format_loss, report_damage
from treetraits.errors import ConfigError
from treetraits.service.outdir import OutputDir


def register(commands: argparse._SubParsersAction) -> None:
    from treetraits.pipeline.methods import METHODS, TRAIT_METHODS

    replay = commands.add_parser(
        "replay",
        help="run a recording through the pipeline and write the tree outputs",
        description=(
            "Decode, localise, fuse, detect, track and estimate every tree of a recording "
            "(or of a LiDAR capture with --nmea), faster than real time, and write OUT/"
            "traits.sqlite, OUT/trees.geojson and OUT/trees.csv. Deterministic: the same "
            "input and options give the same outputs. Ctrl-C (or SIGTERM) stops it with the "
            "outputs of what it read so far, marked interrupted (exit 130/143); over an "
            "earlier run (--force) they go to OUT/interrupted-<UTC time>/ instead."
        ),
    )
    replay.add_argument("input", type=Path, help="a recording (.mcap) or a LiDAR capture")
    replay.add_argument("--out", required=True, type=Path, help="output directory")
    replay.add_argument(
        "--field-map",
        type=Path,
        help="GeoJSON or CSV of the field's trees (default: the recording's)",
    )
    replay.add_argument(
        "--calibration", type=Path, help="calibration v1 JSON (default: the recording's)"
    )
    replay.add_argument(
        "--nmea",
        type=Path,
        help="an NMEA log to go with a LiDAR capture: its sentences are placed on the "
        "capture's clock by their UTC (received localization.gnss_latency_s later)",
    )
    replay.add_argument(
        "--nmea-offset",
        default="0",
        metavar="SECONDS|start",
        help="seconds to add to the NMEA log's times when the logger's clock was off the "
        "capture's, or 'start' to put the log's first epoch at the capture's first packet "
        "(default 0: both clocks on UTC)",
    )
    replay.add_argument(
        "--config",
        type=Path,
        help="config file (TOML, as `treetraits run` takes): the pipeline's settings "
        "([pipeline] method, [detection], [tracking], [traits], [localization], the [output] "
        "gates and export_every_s); default: the built-in defaults. Its calibration and field "
        "map are used when neither the options nor the recording give one",
    )
    replay.add_argument(
        "--method",
        choices=METHODS,
        help="paper (the config's default), rph (the RPH baseline as shipped) or rph-vlp16 "
        "(RPH retuned for single VLP-16 scans); overrides pipeline.method",
    )
    replay.add_argument(
        "--traits",
        choices=TRAIT_METHODS,
        help="paper (keep the maximum, the default) or robust (accumulated); overrides "
        "traits.method",
    )
    replay.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_allow_damaged(replay, "writes the outputs")
    replay.add_argument(
        "--force",
        action="store_true",
        help="replace the outputs of an earlier run in OUT (without it such a run is kept "
        "and the replay refused, exit 4); other files in OUT are never touched",
    )
    replay.set_defaults(run=run)


def _nmea_offset(text: str) -> float | str:
    if text == "start":
        return text
    try:
        seconds = float(text)
    except ValueError:
        seconds = math.nan
    if not math.isfinite(seconds):
        raise ConfigError(f"--nmea-offset is a number of seconds or 'start', got {text!r}")
    return seconds


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from treetraits.files import utc_stamp
    from treetraits.service.config import load_config, with_method
    from treetraits.service.replay import (
        REPLAY_OUTPUTS,
        ReplayOptions,
        format_table,
        open_replay,
        run_replay,
    )

    config = with_method(load_config(args.config), args.method, args.traits)
    options = ReplayOptions(
        config=config,
        field_map=args.field_map,
        calibration=args.calibration,
        nmea=args.nmea,
        nmea_offset=_nmea_offset(args.nmea_offset),
    )
    # Checked before any input is read, and the inputs before the output is touched: a
    # failing replay leaves an earlier run's outputs as they were (docs/cli.md).
    output = OutputDir(
        args.out,
        REPLAY_OUTPUTS,
        force=args.force,
        inputs=(args.input, args.nmea, args.calibration, args.field_map, args.config),
    )
    inputs = open_replay(args.input, options)
    defaulted = inputs.calibration.describe_defaults()
    if defaulted:
        print(f"treetraits: note: {defaulted}", file=sys.stderr)
    start = time.perf_counter()
    try:
        # Progress in bytes of sensor data (a recording is compressed: no total to show).
        # SIGINT/SIGTERM end the reading; what was mapped so far is finished, exported
        # and kept, marked interrupted (a second signal discards it).
        with (
            StopOnSignal() as stop,
            output as staging,
            tqdm(unit="B", unit_scale=True, desc="replay", leave=False, disable=None) as bar,
        ):
            report = run_replay(args.input, staging, options, bar.update, inputs, stop)
            if report.summary["end"] != "complete":
                # Never in place of an earlier complete run (--force): beside it.
                output.keep_aside(f"interrupted-{utc_stamp()}")
    finally:
        inputs.source.close()
    elapsed = time.perf_counter() - start
    summary = dict(report.summary, elapsed_s=round(elapsed, 2))
    summary.pop("calibration", None)
    # A damaged recording is replayed as far as it reads, and says so: its outputs are
    # kept, the exit status tells that data is missing from them.
    status = report_damage(args.input, summary, args.allow_damaged)
    if stop.reason:
        status = EXIT_BY_SIGNAL[stop.reason]
        print(f"treetraits: error: {_interrupted(stop.reason, summary, output)}", file=sys.stderr)
    if args.json:
        print(json.dumps(summary, indent=1))
        return status
    print(format_table(report.trees + report.missing))
    rejected = ", ".join(f"{n} {reason}" for reason, n in summary["rejected"].items())
    print(
        f"\n{summary['trees']} trees ({summary['matched']} on the field map, "
        f"{summary['missing']} missing) from {summary['scans']} scans in {elapsed:.1f} s; "
        f"not trees: {rejected or 'none'}; outputs in {args.out}/"
    )
    if summary["data_loss"]:
        print(f"DATA LOSS: {format_loss(summary)}")
    return status


def _interrupted(reason: str, summary: dict, output: OutputDir) -> str:
    """The one line an interrupted replay ends with: what it kept, and where."""
    if summary["end"] == "complete":  # the signal came after the last message
        return f"interrupted ({reason}) once the replay was complete; outputs in {output.placed}/"
    where = (
        f"kept aside in {output.placed}/ (the earlier run's outputs stay)"
        if output.placed != output.directory
        else f"in {output.placed}/"
    )
    return (
        f"interrupted ({reason}): the outputs of the {summary['scans']} scans replayed so far "
        f"are {where}, marked end = interrupted ({reason})"
    )
