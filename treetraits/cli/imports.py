"""`treetraits import`: ROS 1 / ROS 2 bags to a recording v1 (docs/import.md)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from treetraits.drivers.rosbag.topics import (
    CITRUSFARM_GNSS_QUALITY,
    CITRUSFARM_T_BASE_IMU,
    CITRUSFARM_TOPICS,
    KIND_TYPES,
    KINDS,
    NOT_IMPORTED_YET,
    parse_topics,
)
from treetraits.errors import ConfigError

if TYPE_CHECKING:
    from treetraits.drivers.rosbag.convert import ImportOptions, ImportReport

PRESETS = ("citrusfarm",)


def _kinds_help() -> str:
    known = "; ".join(f"{kind}: {', '.join(types)}" for kind, types in KIND_TYPES.items())
    later = ", ".join(f"{kind} ({t})" for t, kind in NOT_IMPORTED_YET.items())
    return f"{known}. Accepted but not imported yet: {later}" if later else known


def register(commands: argparse._SubParsersAction) -> None:
    parser = commands.add_parser(
        "import",
        help="convert ROS 1 / ROS 2 bags into a recording v1 that replay reads",
        description=(
            "Read ROS 1 bags (.bag) and ROS 2 bags (a directory with metadata.yaml, sqlite3 "
            "or mcap storage) without ROS, and write the sensors' bytes as a treetraits "
            "recording (format v1): VelodyneScan packets byte for byte, NMEA sentences, "
            "NavSatFix as GGA/RMC/GST, images as JPEG, and PointCloud2, Odometry and Imu "
            "(which make it format 1.1; the IMU turned into base_link). Several bags (a "
            "data set split by sensor) are merged by time. Topics of other types, and "
            "asked-for topics the bags lack, are listed in the summary; a damaged bag "
            "stops the import with an error and no recording. docs/import.md gives every rule."
        ),
    )
    parser.add_argument(
        "bags", nargs="+", type=Path, metavar="BAG", help="a .bag file or a ROS 2 bag directory"
    )
    parser.add_argument("--out", required=True, type=Path, help="the recording to write (.mcap)")
    parser.add_argument(
        "--topics",
        nargs="+",
        default=[],
        metavar="KIND=TOPIC",
        help="import only these topics, each as a kind (e.g. lidar=/velodyne_packets "
        f"gnss=/fix camera=/cam/image_raw). Kinds: {_kinds_help()}. Default: every topic "
        "of a known type (the first one of each kind); with --preset, the preset's topics, "
        "which these replace kind by kind",
    )
    parser.add_argument(
        "--calibration",
        type=Path,
        help="calibration v1 JSON stored in the recording's metadata (replay uses it); "
        "default: the preset's, else none",
    )
    parser.add_argument(
        "--preset",
        choices=PRESETS,
        help="citrusfarm: the CitrusFarm data set's topics ("
        + ", ".join(f"{k}={v}" for k, v in CITRUSFARM_TOPICS.items())
        + "), its calibration (the one the simulator uses, plus the MicroStrain IMU's "
        "mounting as T_base_imu when the calibration has none) and GGA quality "
        f"{CITRUSFARM_GNSS_QUALITY} (RTK fixed) for its NavSatFix",
    )
    parser.add_argument(
        "--gnss-quality",
        type=int,
        choices=range(10),
        metavar="0-9",
        help="GGA quality for every NavSatFix with a fix (4 RTK fixed, 5 RTK float, 2 DGPS, "
        "1 autonomous). Default: from NavSatStatus (FIX 1, SBAS 2, GBAS 4 when the "
        "covariance's horizontal sigma is at most 5 cm, else 5); NO_FIX is always 0",
    )
    parser.add_argument(
        "--jpeg-quality",
        type=int,
        default=90,
        metavar="1-100",
        help="JPEG quality for raw images (default 90); compressed JPEGs are copied as they are",
    )
    parser.add_argument(
        "--force",
        "--overwrite",  # the option's first name, kept for the scripts that use it
        dest="force",
        action="store_true",
        help="replace --out if it exists (without it an existing file is kept and the import "
        "refused, exit 4); --overwrite is the same",
    )
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.set_defaults(run=run)


def options_from_args(args: argparse.Namespace) -> ImportOptions:
    """The import's options: the preset's, then what the user gave."""
    from treetraits.drivers.calibration import load_calibration
    from treetraits.drivers.rosbag.convert import ImportOptions
    from treetraits.sim.run import DEFAULT_CALIBRATION

    topics: dict[str, str] | None = None
    calibration_path = args.calibration
    quality = args.gnss_quality
    if args.preset == "citrusfarm":
        topics = dict(CITRUSFARM_TOPICS)
        calibration_path = calibration_path or DEFAULT_CALIBRATION
        quality = CITRUSFARM_GNSS_QUALITY if quality is None else quality
    if args.topics:
        topics = {**(topics or {}), **parse_topics(args.topics)}
    if not 1 <= args.jpeg_quality <= 100:
        raise ConfigError(f"--jpeg-quality must be 1-100, got {args.jpeg_quality}")
    calibration = None
    if calibration_path is not None:
        load_calibration(calibration_path)  # refuse a malformed file before any work
        calibration = json.loads(Path(calibration_path).read_text())
    if args.preset == "citrusfarm" and "T_base_imu" not in (calibration or {}):
        # The MicroStrain's mounting, unless the calibration given says otherwise.
        calibration = {**(calibration or {}), "T_base_imu": list(CITRUSFARM_T_BASE_IMU)}
    return ImportOptions(
        topics=topics,
        gnss_quality=quality,
        calibration=calibration,
        jpeg_quality=args.jpeg_quality,
        force=args.force,
    )


def run(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from treetraits.drivers.rosbag.convert import import_bags
    from treetraits.files import check_output_file

    check_output_file(args.out, force=args.force)  # before the bags and the calibration
    options = options_from_args(args)
    with tqdm(unit="msg", desc="import", leave=False, disable=None) as bar:

        def progress(done: int, total: int) -> None:
            bar.total = total
            bar.update(done - bar.n)

        report = import_bags(args.bags, args.out, options, progress=progress)
    if args.json:
        print(json.dumps(report.as_dict(), indent=1))
    else:
        print(format_report(report))
    return 0


def format_report(report: ImportReport) -> str:
    """The human summary: each topic's fate, then what the recording holds."""
    lines = [f"{report.output}: from {', '.join(report.bags)}"]
    width = max((len(t.topic) for t in report.topics), default=5)
    for t in report.topics:
        done = f" -> {t.written} messages" if t.status == "imported" else ""
        skipped = ""
        if t.skip_reasons:  # messages skipped, and points dropped from clouds
            reasons = ", ".join(f"{n} {why}" for why, n in t.skip_reasons.items())
            skipped = f" ({t.skipped} skipped: {reasons})"
        kind = f"[{t.kind}] " if t.kind else ""
        msgtype = t.msgtype or "not in the bags"
        lines.append(
            f"  {t.topic:<{width}}  {msgtype} x{t.messages}  {kind}{t.status}{done}{skipped}"
        )
    channels = ", ".join(f"{topic} {n}" for topic, n in report.channels.items()) or "nothing"
    lines.append(f"  recording: {channels}")
    if report.first_log_time is not None and report.last_log_time is not None:
        span = (report.last_log_time - report.first_log_time) / 1e9
        lines.append(f"  span: {span:.3f} s of log_time")
    for frame, source in report.imu_frames.items():
        lines.append(f"  IMU {frame} to base_link: {source}")
    if report.out_of_order:
        lines.append(f"  warning: {report.out_of_order} messages written out of log_time order")
    if not report.channels:
        lines.append(f"  hint: no topic was imported; kinds: {', '.join(KINDS)} (see --help)")
    return "\n".join(lines)
