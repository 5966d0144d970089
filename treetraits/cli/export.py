"""`treetraits export foxglove`: a survey as a schema'd MCAP for Foxglove (docs/data.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from treetraits.damage import add_allow_damaged, report_damage


def register(commands: argparse._SubParsersAction) -> None:
    export = commands.add_parser(
        "export",
        help="write a survey in another tool's format (foxglove)",
        description="Write a survey in another tool's format.",
    )
    sub = export.add_subparsers(dest="export_command", metavar="FORMAT", required=True)
    foxglove = sub.add_parser(
        "foxglove",
        help="an MCAP that Foxglove opens as it is: scans, pose, fixes, frames, camera, trees",
        description=(
            "Run a recording (or the recording of a replay's output directory, with that "
            "run's method, traits and calibration) through the pipeline as replay does, and "
            "write what it saw with the published Foxglove protobuf schemas: the decoded "
            "scans (foxglove.PointCloud, /lidar/points), the pose (foxglove.PoseInFrame, "
            "/pose) and path (foxglove.PosesInFrame, /path), the frames map, base_link, "
            "lidar, camera (foxglove.FrameTransform, /tf), the GNSS fixes "
            "(foxglove.LocationFix, /gnss/fix), the camera frames and "
            "their NDVI (foxglove.CompressedImage, /camera/image, /camera/ndvi) and the "
            "trees as cylinders sized by width and height, coloured by NDVI "
            "(foxglove.SceneUpdate, /trees). docs/data.md tells how to look at it."
        ),
    )
    foxglove.add_argument(
        "input", type=Path, metavar="REC.mcap|RUN_DIR", help="a recording, or replay's --out"
    )
    foxglove.add_argument("--out", required=True, type=Path, help="the MCAP to write")
    foxglove.add_argument(
        "--calibration",
        type=Path,
        help="calibration v1 JSON (default: the run's, else the recording's, as replay)",
    )
    foxglove.add_argument(
        "--config",
        type=Path,
        help="config file (TOML) for the pipeline's settings, as replay takes it",
    )
    foxglove.add_argument(
        "--force",
        action="store_true",
        help="replace --out if it exists (without it an existing file is kept and the export "
        "refused, exit 4)",
    )
    add_allow_damaged(foxglove, "writes the view")
    foxglove.add_argument("--json", action="store_true", help="print the summary as JSON")
    foxglove.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from treetraits.extras import require_extra

    require_extra("export", "treetraits export foxglove")
    from tqdm import tqdm

    from treetraits.export.foxglove import export_foxglove
    from treetraits.service.config import load_config

    config = load_config(args.config)
    with tqdm(unit="B", unit_scale=True, desc="export", leave=False, disable=None) as bar:
        report = export_foxglove(
            args.input, args.out, config, args.calibration, args.force, bar.update
        )
    # A damaged recording is exported as far as it reads, and says so (as replay does).
    status = report_damage(args.input, report.integrity, args.allow_damaged, _VIEW_OF_THE_REST)
    if args.json:
        print(json.dumps(report.as_dict(), indent=1))
        return status
    channels = ", ".join(f"{topic} {n}" for topic, n in report.channels.items()) or "nothing"
    print(f"{report.output}: {report.scans} scans, {report.trees} trees; {channels}")
    return status


_VIEW_OF_THE_REST = "the view is of the rest"
