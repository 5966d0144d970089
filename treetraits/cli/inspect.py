"""`treetraits inspect`: every object of one scan with its cues and verdict, and a picture."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from treetraits.cli.lidar import _INPUT_HELP, _add_decoder_options, _reader
from treetraits.damage import add_allow_damaged, describe_loss, report_damage, source_integrity
from treetraits.errors import ConfigError
from treetraits.files import check_output_file

_COLUMNS_HELP = """\
columns (lengths in metres, base frame: x forward, y left, z up from the ground under
the robot; '-' = not measured):
  id       the object's number in this scan (the picture's labels)
  x m/y m  its centroid (over the voxel grid)
  range    distance from the LiDAR to the centroid (3-D)
  returns  LiDAR returns in the object
  height   its top above the terrain under it (the height rule's value)
  extent   vertical extent: its highest return minus its lowest
  width    its largest horizontal extent
  top      its top in this scan: seen (the beam above passed over all of it: its height
           is bracketed), cut (the sensor's top beam hit it: too close or too tall for
           its top to be in view), hidden (the beam above hit something nearer within
           its bearings: a neighbour's crown, or the object going on upward)
  verdict  tree, or the first rule it fails: low, tall, floating, thin, slender, wide,
           smooth (its surface speaks against foliage), not_green (the camera's NDVI)
  veg      yes when the cues weighed together speak for vegetation (evidence > 0)
  evid     the evidence: the sum of the four contributions below
  texture  median texture along its rings (m, at 5 cm); tex+ its contribution
  planar   share of its 0.3 m patches that are planar; pla+ its contribution
  ndvi     mean NDVI of its returns (none here: inspect runs without the camera); ndv+
  inten    median raw intensity (0-255); int+ its contribution
  track    the track (tree id) the mapper gave it, following every scan up to this one;
  scans    the scans that track was seen in; track is: what the map holds of it now, by
           all those scans (a tree, or why not; unconfirmed: seen in fewer scans than
           output.min_observations, not in the map): one scan's verdict decides nothing
verdict `undecided`: a tree's shape with no evidence either way in this scan (nothing
measured, or dark echoes); its track decides. The summary line counts the objects, those
judged vegetation, of the objects whose vertical extent exceeds 1 m with 50 returns or
more how many are vegetation (their share), and how many of their tracks are trees."""


def register(commands: argparse._SubParsersAction) -> None:
    inspect = commands.add_parser(
        "inspect",
        help="show every object of one scan with its cues and verdict (and a picture)",
        description=(
            "Why the map holds what it holds: run the per-scan detection on one full scan "
            "(a whole rotation) of a recording or a LiDAR capture and print every object "
            "(cluster) with its size, its vegetation cues and what each contributes, and its "
            "verdict; --png draws the scan with the objects coloured by verdict. Without "
            "NDVI: camera frames of a recording are not used (the ndvi cue is not "
            "measured). Dual returns: each echo once, as the pipeline does."
        ),
        epilog=_COLUMNS_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    inspect.add_argument("path", metavar="RECORDING|CAPTURE", help=_INPUT_HELP)
    which = inspect.add_mutually_exclusive_group()
    which.add_argument(
        "--scan",
        type=int,
        metavar="N",
        help="the N-th full scan, from 0 (default: the first full scan); past the last is "
        "an error naming how many there are (exit 2)",
    )
    which.add_argument(
        "--time",
        type=float,
        metavar="T",
        help="the full scan whose middle is nearest T seconds after the start of the "
        "input's first scan (device time)",
    )
    inspect.add_argument(
        "--calibration",
        type=Path,
        help="calibration v1 JSON: its T_base_lidar places the LiDAR (default: the "
        "recording's, else the config's pipeline.calibration, else a level LiDAR 0.44 m up)",
    )
    inspect.add_argument(
        "--config",
        type=Path,
        help="config file (TOML, as `treetraits run` takes): its [detection] settings "
        "(default: the built-in defaults)",
    )
    inspect.add_argument("--json", action="store_true", help="print one JSON object")
    inspect.add_argument(
        "--png",
        type=Path,
        metavar="FILE",
        help="write a 1200x800 picture: top view and side view, returns grey, objects "
        "coloured by verdict (tree green, smooth/not_green red, low brown, thin/slender "
        "orange, floating/tall/wide purple), their ids, a legend and a scale bar",
    )
    inspect.add_argument(
        "--no-tracks",
        action="store_true",
        help="only this scan: do not map the scans before it (their tracks and what the "
        "map holds of each object are then not shown; quicker for a late scan)",
    )
    add_allow_damaged(inspect, "prints the scan")
    _add_decoder_options(inspect)
    inspect.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.drivers.records import Scan
    from treetraits.inspection import (
        format_summary,
        format_table,
        object_rows,
        pick_scan,
        summarise,
        track_verdicts,
    )
    from treetraits.pipeline.detection import detect, to_base
    from treetraits.service.config import load_config
    from treetraits.service.replay import ReplayOptions, open_replay
    from treetraits.service.survey import make_mapper

    if args.time is not None and not args.time == args.time:  # NaN
        raise ConfigError("--time must be a number of seconds")
    if args.png is not None:
        check_output_file(args.png, "--png")  # a directory: before the scans are read
    config = load_config(args.config)
    path = Path(args.path)
    # The calibration as `replay` takes it (--calibration, the recording's, the config's),
    # the input checked on the way; the scans are then read by the LiDAR reader.
    inputs = open_replay(path, ReplayOptions(config=config, calibration=args.calibration))
    inputs.source.close()
    calibration = inputs.calibration
    defaulted = calibration.describe_defaults()
    if defaulted:
        print(f"treetraits: note: {defaulted}", file=sys.stderr)
    T_base_lidar = calibration.T_base_lidar

    reader = _reader(str(path), args)
    try:
        scans = (item for item in reader if isinstance(item, Scan))
        picked = pick_scan(scans, args.scan, args.time)
    except ConfigError as exc:  # past the last scan: of a cut file, say so
        damage = source_integrity(reader.source)
        if not damage["data_loss"]:
            raise
        raise ConfigError(
            f"{exc}, of what could be read: {path}: {describe_loss(damage)}"
        ) from None
    finally:
        reader.close()
    # What was read up to the scan: damage after it does not change what is shown.
    damage = source_integrity(reader.source)
    scan = picked.scan
    points = scan.distinct if scan.points["duplicate"].any() else scan.points
    if args.no_tracks or config.pipeline.method.startswith("rph"):
        clusters, tracks = detect(points, None, T_base_lidar, config.detection).clusters, None
    else:
        # The map as a replay makes it (no poses here: the mapper's own frame) up to this
        # scan: each object's track and what its scans so far make of it.
        reader = _reader(str(path), args)
        try:
            scans = (item for item in reader if isinstance(item, Scan))
            mapper = make_mapper(config, calibration)
            seen = config.output.min_observations
            clusters, tracks = track_verdicts(scans, picked.number, mapper, seen)
        finally:
            reader.close()
    rows = object_rows(clusters, T_base_lidar, tracks)
    summary = summarise(rows)
    facts = {
        "input": str(path),
        "scan": picked.number,
        "t_s": round(picked.t_s, 3),
        "points": len(points),
        "calibration": _calibration_source(args.calibration, calibration.source),
        "ndvi": "none",
        "summary": summary,
        "objects": rows,
    }
    if args.png is not None:
        from treetraits.scan_picture import draw_scan, write_png

        title = f"{path.name} scan {picked.number} (t {picked.t_s:.2f} s)"
        crop = config.detection.crop
        box = (crop.x_m, crop.y_m, crop.z_m)
        image = draw_scan(to_base(points, T_base_lidar), clusters, T_base_lidar, title, box)
        write_png(args.png, image)
        facts["png"] = str(args.png)
    status = report_damage(path, damage, args.allow_damaged, _OF_THE_REST)
    if args.json:
        print(json.dumps(facts, indent=1, allow_nan=False))
        return status
    print(
        f"{path}: full scan {picked.number} at {picked.t_s:.2f} s, {len(points)} returns, "
        f"calibration {facts['calibration']}, no NDVI"
    )
    print(format_table(rows))
    print(format_summary(summary))
    if args.png is not None:
        print(f"picture: {args.png}")
    return status


_OF_THE_REST = "the scans are of the rest"


def _calibration_source(given: Path | None, source: str) -> str:
    """Where T_base_lidar came from: the file given, the config's, the recording's or the
    default mount."""
    if given is not None:
        return str(given)
    if source == "defaults":
        return "default (a level LiDAR 0.44 m up)"
    if source == "calibration":  # loaded from the recording's metadata
        return "the recording's"
    return source
