"""`treetraits fuse`: one scan of a recording drawn over its NDVI frame, to check by eye
that the camera calibration and `T_camera_lidar` put the points where they belong."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING

from treetraits.damage import add_allow_damaged, integrity_facts, report_damage
from treetraits.errors import CalibrationError, ConfigError, SourceError
from treetraits.files import check_output_file

if TYPE_CHECKING:
    import numpy as np

    from treetraits.drivers.calibration import Calibration
    from treetraits.drivers.records import Frame, Scan


def register(commands: argparse._SubParsersAction) -> None:
    fuse = commands.add_parser(
        "fuse",
        help="draw one scan's LiDAR points over its NDVI frame (a calibration check)",
        description=(
            "Take scan K of a recording (0 = the first, partial one, as `lidar export` "
            "numbers them), the camera frame nearest its middle, and write a PNG of the "
            "camera's size: the NDVI frame as a colour map (red -1 .. yellow 0 .. green +1, "
            "grey = no NDVI) with every visible LiDAR point as a dot coloured by its height "
            "above the ground (cyan low .. magenta high). Occluded points are not drawn."
        ),
    )
    fuse.add_argument(
        "input", help="an MCAP recording (format v1) with /lidar/packets and /camera/jpeg"
    )
    fuse.add_argument("--scan", type=int, required=True, metavar="K", help="scan number")
    fuse.add_argument("--out", type=Path, required=True, help="output PNG")
    fuse.add_argument(
        "--calibration",
        type=Path,
        help="calibration v1 JSON (default: the one in the recording's metadata)",
    )
    fuse.add_argument(
        "--max-skew-ms",
        type=float,
        default=50.0,
        help="refuse a frame further than this from the scan's middle (default 50)",
    )
    fuse.add_argument(
        "--background",
        choices=("ndvi", "mask"),
        default="ndvi",
        help="ndvi: NDVI colour map; mask: the paper's binary vegetation frame (white = "
        "NDVI in (-0.3, 1.0])",
    )
    fuse.add_argument("--dot-radius", type=int, default=2, help="dot radius in px (default 2)")
    fuse.add_argument(
        "--height-range",
        metavar="LOW,HIGH",
        help="heights (m) mapped to cyan and magenta (default: 2nd-98th percentile)",
    )
    fuse.add_argument(
        "--no-occlusion", action="store_true", help="draw hidden points too (no z-buffer)"
    )
    fuse.add_argument("--json", action="store_true", help="print the summary as JSON")
    add_allow_damaged(fuse, "draws the picture")
    fuse.set_defaults(run=run_fuse)


def _calibration(args: argparse.Namespace, stored: dict) -> Calibration:
    from treetraits.drivers.calibration import load_calibration

    if args.calibration is not None:
        calibration = load_calibration(args.calibration)
    else:
        if not stored:
            raise CalibrationError(
                f"{args.input}: the recording holds no calibration; give --calibration FILE"
            )
        calibration = load_calibration(stored)
    if calibration.camera is None:
        raise CalibrationError(
            f"{args.calibration or args.input}: the calibration has no camera section; give "
            f"--calibration FILE with camera and T_camera_lidar"
        )
    return calibration


def _scan(path: str, number: int) -> Scan:
    from treetraits.drivers.records import Scan
    from treetraits.drivers.velodyne.reader import LidarReader
    from treetraits.drivers.velodyne.sources import open_source

    reader = LidarReader(open_source(path))
    count = 0
    try:
        for item in reader:
            if isinstance(item, Scan):
                if count == number:
                    return item
                count += 1
    finally:
        reader.close()
    raise ConfigError(
        f"{path}: --scan {number} asked for, the recording has {count} scan(s)"
        + (f" (0..{count - 1})" if count else " (no /lidar/packets?)")
    )


def _frames_near(path: str, t_mid: int, max_skew_ns: int) -> tuple[list[int], list[Frame], dict]:
    """Every frame's capture time, and the frames within the skew limit (bytes kept only
    for those, so a long recording is not held in memory); and what of the recording could
    not be read (the whole file is read: treetraits/damage.py)."""
    from treetraits.drivers import recording
    from treetraits.drivers.records import Frame

    times: list[int] = []
    near: list[Frame] = []
    with recording.read_recording(path, topics=[recording.CAMERA_JPEG]) as reader:
        for message in reader:
            times.append(message.publish_time)
            if abs(message.publish_time - t_mid) <= max_skew_ns:
                near.append(
                    Frame(message.data, message.log_time, message.publish_time, message.sequence)
                )
    return times, near, integrity_facts(reader)


def run_fuse(args: argparse.Namespace) -> int:
    import numpy as np

    from treetraits.drivers import recording
    from treetraits.pipeline.fusion import (
        FusionConfig,
        colorize_mask,
        colorize_ndvi,
        draw_points,
        fuse_scan,
        height_colours,
    )
    from treetraits.pipeline.ndvi import vegetation_mask
    from treetraits.pipeline.projection import (
        OcclusionRule,
        PointStatus,
        nearest_frame,
        scan_mid_time,
    )

    check_output_file(args.out)  # a directory: before the recording is read
    if args.scan < 0:
        raise ConfigError(f"--scan must be >= 0, got {args.scan}")
    if args.dot_radius < 0:
        raise ConfigError(f"--dot-radius must be >= 0, got {args.dot_radius}")
    with recording.read_recording(args.input, topics=[]) as reader:
        stored = reader.metadata.calibration if reader.metadata is not None else {}
    calibration = _calibration(args, stored)
    max_skew_ns = int(args.max_skew_ms * 1e6)
    scan = _scan(args.input, args.scan)
    t_mid = scan_mid_time(scan)
    times, near, damage = _frames_near(args.input, t_mid, max_skew_ns)
    match = nearest_frame(times, t_mid, max_skew_ns)
    if match.reason == "no_frame":
        raise SourceError(f"{args.input}: no {recording.CAMERA_JPEG} frames in the recording")
    if match.reason == "skew":
        raise SourceError(
            f"{args.input}: the frame nearest scan {args.scan} is {match.skew_ns / 1e6:+.1f} ms "
            f"from its middle, beyond --max-skew-ms {args.max_skew_ms:g}"
        )
    occlusion = OcclusionRule(enabled=not args.no_occlusion)
    fused = fuse_scan(scan, near, calibration, FusionConfig(max_skew_ns, occlusion))
    if fused.reason != "ok":
        raise SourceError(f"{args.input}: scan {args.scan}: {fused.detail}")

    assert fused.ndvi_frame is not None and fused.projection is not None
    if args.background == "ndvi":
        background = colorize_ndvi(fused.ndvi_frame)
    else:
        background = colorize_mask(vegetation_mask(fused.ndvi_frame))
    status = fused.points.status
    drawn = (status == PointStatus.OK) | (status == PointStatus.NO_NDVI)
    p = np.column_stack([scan.points["x"], scan.points["y"], scan.points["z"]]).astype(float)
    height = p @ calibration.T_base_lidar[2, :3] + calibration.T_base_lidar[2, 3]
    low, high = _height_range(args.height_range, height[drawn])
    picture = draw_points(
        background,
        fused.projection.pixel[drawn],
        fused.projection.depth[drawn],
        height_colours(height[drawn], low, high),
        args.dot_radius,
    )
    _write_png(args.out, picture)

    values = fused.ndvi[status == PointStatus.OK]
    facts = {
        "input": args.input,
        "scan": args.scan,
        "points": len(scan.points),
        "drawn": int(drawn.sum()),
        **{f"points_{k}": v for k, v in fused.counts().items()},
        "frame_sequence": fused.frame.sequence if fused.frame else None,
        "skew_ms": round(fused.skew_ns / 1e6, 3) if fused.skew_ns is not None else None,
        "image": [int(picture.shape[1]), int(picture.shape[0])],
        "height_range_m": [round(low, 3), round(high, 3)],
        "ndvi_median_points": round(float(np.median(values)), 4) if len(values) else None,
        "vegetation_fraction_points": (
            round(float(vegetation_mask(values).mean()), 4) if len(values) else None
        ),
        "calibration": str(args.calibration) if args.calibration else "recording metadata",
        "out": str(args.out),
    }
    status = report_damage(args.input, damage, args.allow_damaged, "the picture is of the rest")
    if args.json:
        print(json.dumps(facts, indent=1))
    else:
        width = max(len(k) for k in facts)
        print("\n".join(f"{k:<{width}}  {v}" for k, v in facts.items()))
    return status


def _height_range(text: str | None, heights: np.ndarray) -> tuple[float, float]:
    import numpy as np

    if text:
        try:
            low, high = (float(v) for v in text.split(","))
        except ValueError:
            raise ConfigError(f"--height-range {text!r}: expected LOW,HIGH in metres") from None
        if not high > low:
            raise ConfigError(f"--height-range {text!r}: HIGH must exceed LOW")
        return low, high
    if len(heights) == 0:
        return 0.0, 1.0
    low, high = np.percentile(heights, [2, 98])
    return float(low), float(max(high, low + 1e-3))


def _write_png(path: Path, picture: np.ndarray) -> None:
    import cv2

    if path.suffix.lower() != ".png":
        raise ConfigError(f"--out {path}: expected a .png file name")
    if path.parent and not path.parent.exists():
        raise ConfigError(f"--out {path}: directory {path.parent} does not exist")
    if not cv2.imwrite(str(path), picture):
        raise SourceError(f"{path}: could not write the PNG")
