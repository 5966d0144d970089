"""`treetraits camera info|grab`: look at the Survey3N, live or replayed, and save frames."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

from treetraits.damage import add_allow_damaged, report_damage, source_integrity
from treetraits.errors import ConfigError, ParseError

_SOURCE_HELP = (
    "auto (default: the first V4L2 camera named MAPIR/Survey), usb:VID:PID, /dev/videoN, "
    "/dev/v4l/by-id/..., /dev/survey3n; or a folder of JPEGs with timestamps.csv, a video "
    "file (.mp4/.avi/.mkv/.mov) or a recording (.mcap)"
)


def register(commands: argparse._SubParsersAction) -> None:
    camera = commands.add_parser(
        "camera",
        help="inspect the Survey3N camera (live or replayed) and save frames",
        description=(
            "MAPIR Survey3N over UVC: find it, negotiate MJPG 1280x720 at 30 fps, lock "
            "exposure and white balance, measure the frame rate; or read frames back from a "
            "folder, a video file or a recording."
        ),
    )
    sub = camera.add_subparsers(dest="camera_command", metavar="COMMAND", required=True)

    info = sub.add_parser(
        "info",
        help="modes, controls, negotiated mode and measured frame rate",
        description=(
            "Live: list the device's formats, sizes and rates and its controls, open it with "
            "the settings below, report what it granted and what happened to each locked "
            "control, and measure the frame rate from capture times for --seconds. "
            "Replay: count frames and measure rate, size and gaps from their times. "
            "Nothing is decoded but the first frame (for its size) unless --decode-all."
        ),
    )
    info.add_argument("source", nargs="?", default="auto", help=_SOURCE_HELP)
    info.add_argument(
        "--seconds", type=float, default=3.0, help="live: how long to measure (default 3)"
    )
    info.add_argument(
        "--decode-all", action="store_true", help="decode every frame to count corrupt ones"
    )
    info.add_argument("--json", action="store_true", help="print one JSON object")
    add_allow_damaged(info, "prints the facts")
    _add_settings_options(info)
    info.set_defaults(run=run_info)

    grab = sub.add_parser(
        "grab",
        help="save frames as JPEG files plus timestamps.csv",
        description=(
            "Write frames as DIR/frame_NNNNNN.jpg, the JPEG bytes exactly as the source holds "
            "them (never decoded), and DIR/timestamps.csv with file,t_capture_ns,t_host_ns: "
            "the folder layout `treetraits camera info DIR` and replay read back."
        ),
    )
    grab.add_argument("source", nargs="?", default="auto", help=_SOURCE_HELP)
    grab.add_argument("--out", required=True, type=Path, help="output folder (new or empty)")
    grab.add_argument(
        "-n",
        "--count",
        type=int,
        help="frames to save (default: 10 from a camera, all from a replay)",
    )
    grab.add_argument("--seconds", type=float, help="stop after this many seconds (live)")
    grab.add_argument(
        "--every", type=int, default=1, metavar="K", help="save every K-th frame (default 1)"
    )
    add_allow_damaged(grab, "writes the frames")
    _add_settings_options(grab)
    grab.set_defaults(run=run_grab)


def _add_settings_options(parser: argparse.ArgumentParser) -> None:
    live = parser.add_argument_group("live camera")
    live.add_argument("--width", type=int, default=1280, help="frame width (default 1280)")
    live.add_argument("--height", type=int, default=720, help="frame height (default 720)")
    live.add_argument("--fps", type=float, default=30.0, help="frame rate (default 30)")
    live.add_argument(
        "--exposure", type=int, help="exposure_time_absolute, 100 us units (default: keep)"
    )
    live.add_argument("--gain", type=int, help="gain, device units (default: keep)")
    live.add_argument("--wb-temperature", type=int, help="white balance, kelvin (default: keep)")
    live.add_argument(
        "--no-lock",
        action="store_true",
        help="leave auto exposure and auto white balance as the camera has them",
    )
    live.add_argument(
        "--strict", action="store_true", help="fail when the device gives another mode"
    )
    video = parser.add_argument_group("video file")
    video.add_argument(
        "--video-start",
        default="0",
        metavar="TIME",
        help="time of the video's first frame: ns since the Unix epoch or ISO 8601 (default 0)",
    )


def _settings(args: argparse.Namespace):
    from treetraits.drivers.camera import CameraSettings

    return CameraSettings(
        width=args.width,
        height=args.height,
        fps=args.fps,
        exposure=args.exposure,
        gain=args.gain,
        wb_temperature=args.wb_temperature,
        lock=not args.no_lock,
        strict_mode=args.strict,
    )


def _start_ns(text: str) -> int:
    if text.strip().lstrip("-").isdigit():
        return int(text)
    try:
        from datetime import datetime

        moment = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise ConfigError(
            f"--video-start {text!r}: expected ns since the Unix epoch or an ISO 8601 time "
            "such as 2026-05-01T10:00:00Z"
        ) from None
    if moment.tzinfo is None:
        raise ConfigError(f"--video-start {text!r}: give a time zone (e.g. Z for UTC)")
    return round(moment.timestamp() * 1e6) * 1000


def _open(args: argparse.Namespace):
    from treetraits.drivers.camera import open_camera_source

    return open_camera_source(
        args.source, _settings(args), video_start_ns=_start_ns(args.video_start)
    )


def _damage(source) -> dict | None:
    """What of a replayed input could not be read, as far as it was read
    (treetraits/damage.py); None for a live camera, which is no recording."""
    return None if source.is_live else source_integrity(source)


def run_info(args: argparse.Namespace) -> int:
    source = _open(args)
    try:
        facts = _live_facts(source, args) if source.is_live else _replay_facts(source, args)
    finally:
        source.close()
    status = 0
    if (damage := _damage(source)) is not None:
        # As `lidar info`: the recording's lost time spans, beside the counters.
        facts.update(
            damaged_chunks=damage["damaged_chunks"],
            lost_spans=damage["lost"],
            data_loss=damage["data_loss"],
        )
        status = report_damage(args.source, damage, args.allow_damaged, "the facts are of the rest")
    print(json.dumps(facts, indent=1) if args.json else _format_facts(facts))
    return status


def _measure(frames) -> dict:
    """Rate, gaps, latency and size from a list of frames (no decoding)."""
    import statistics

    from treetraits.drivers.camera.frames import interval_summary

    times = [f.t_capture for f in frames]
    facts: dict = {"frames": len(frames), **interval_summary(times)}
    if frames:
        facts["jpeg_bytes_mean"] = round(statistics.fmean(len(f.jpeg) for f in frames))
        latencies = [(f.t_host - f.t_capture) / 1e6 for f in frames]
        facts["latency_ms_median"] = statistics.median(latencies)
        facts["duration_s"] = (max(times) - min(times)) / 1e9
    return facts


def _first_size(source, frames) -> dict:
    for frame in frames:
        try:
            image = source.decode(frame)
        except ParseError:
            continue
        return {"width": image.shape[1], "height": image.shape[0]}
    return {}


def _live_facts(source, args: argparse.Namespace) -> dict:
    from treetraits.drivers.camera import v4l2

    facts: dict = {"source": source.uri, "kind": "live", "device": source.device}
    try:
        capability = v4l2.query_capability(source.device)
        facts["card"] = capability.card
        facts["bus"] = capability.bus_info
        facts["driver"] = f"{capability.driver} {capability.version}"
        facts["modes"] = [m.as_dict() for m in v4l2.list_modes(source.device)]
        facts["controls"] = [c.as_dict() for c in v4l2.list_controls(source.device)]
    except OSError as exc:
        facts["v4l2"] = f"cannot enumerate {source.device}: {exc.strerror or exc}"
    facts["negotiation"] = source.negotiation.as_dict() if source.negotiation else None
    facts["locked"] = [c.as_dict() for c in source.controls]
    facts["jpeg"] = source.jpeg_path
    frames = []
    cpu_start = source.cpu_time_s()
    deadline = time.monotonic() + args.seconds
    while (remaining := deadline - time.monotonic()) > 0:
        frame = source.next_frame(timeout=remaining)
        if frame is not None:
            frames.append(frame)
    facts["measured"] = _measure(frames)
    facts["measured"]["grab_cpu_percent"] = round(
        100 * (source.cpu_time_s() - cpu_start) / args.seconds, 1
    )
    facts["measured"].update(_first_size(source, frames[:1]))
    facts["state"] = source.state
    facts["counters"] = source.stats.as_dict()
    return facts


def _replay_facts(source, args: argparse.Namespace) -> dict:
    facts: dict = {"source": source.uri, "kind": source.kind}
    if source.kind == "video":
        facts["codec"] = source.codec
        facts["jpeg"] = "verbatim" if source.passthrough else "reencoded"
    frames = list(source)
    facts["measured"] = _measure(frames)
    facts["measured"].update(_first_size(source, frames))
    if frames:
        facts["t_first_ns"] = min(f.t_capture for f in frames)
        facts["t_last_ns"] = max(f.t_capture for f in frames)
    if args.decode_all:
        for frame in frames[1:]:
            with contextlib.suppress(ParseError):
                source.decode(frame)
    facts["counters"] = source.stats.as_dict()
    return facts


def _format_facts(facts: dict) -> str:
    lines = [f"{facts['source']} ({facts['kind']})"]
    for key, value in facts.items():
        if key in ("source", "kind") or value in (None, [], {}):
            continue
        if key == "modes":
            lines.append("  modes")
            lines += [
                f"    {m['fourcc']:<4} {m['size']:>9}  {', '.join(f'{f:g}' for f in m['fps'])} fps"
                for m in value
            ]
        elif key == "controls":
            lines.append("  controls")
            lines += [
                f"    {c['name']:<32} {c['value']!s:>6}  [{c['min']}..{c['max']}, "
                f"default {c['default']}]" + (" inactive" if c.get("inactive") else "")
                for c in value
            ]
        elif key == "locked":
            lines.append("  locked")
            lines += [
                f"    {c['name']:<26} {c['status']:<11} asked {c['requested']}, "
                f"was {c['before']}, now {c['after']}"
                for c in value
            ]
        elif isinstance(value, dict):
            lines.append(f"  {key}")
            shown = {k: v for k, v in value.items() if v not in (None, 0, False, [], {})}
            width = max((len(k) for k in shown), default=0)
            lines += [f"    {k:<{width}}  {_short(v)}" for k, v in shown.items()]
        else:
            lines.append(f"  {key}  {value}")
    return "\n".join(lines)


def _short(value) -> str:
    if isinstance(value, float):
        return f"{value:.3f}".rstrip("0").rstrip(".")
    if isinstance(value, list):
        return "; ".join(str(v) for v in value)
    return str(value)


def _frames(source, deadline: float | None):
    """A replay's frames, or a camera's until the deadline (waiting in short slices, so a
    camera that stopped sending still ends at the deadline)."""
    if not source.is_live:
        yield from source
        return
    while deadline is None or (remaining := deadline - time.monotonic()) > 0:
        frame = source.next_frame(timeout=0.5 if deadline is None else min(0.5, remaining))
        if frame is not None:
            yield frame


def run_grab(args: argparse.Namespace) -> int:
    from treetraits.drivers.camera import FolderWriter

    if args.every < 1:
        raise ConfigError(f"--every must be at least 1, got {args.every}")
    if args.count is not None and args.count < 1:
        raise ConfigError(f"--count must be at least 1, got {args.count}")
    source = _open(args)
    count = args.count if args.count is not None else (10 if source.is_live else None)
    deadline = None if args.seconds is None else time.monotonic() + args.seconds
    try:
        with FolderWriter(args.out) as writer:
            for index, frame in enumerate(_frames(source, deadline)):
                if index % args.every == 0:
                    writer.write(frame)
                if count is not None and writer.count >= count:
                    break
            written = writer.count
    finally:
        source.close()
    counters = {k: v for k, v in source.stats.as_dict().items() if v and k not in ("frames",)}
    print(f"wrote {written} frames to {args.out} (timestamps.csv); counters: {counters}")
    if source.is_live and written == 0:
        print("no frames arrived: see `treetraits camera info` for the device", file=sys.stderr)
    if (damage := _damage(source)) is None:
        return 0
    return report_damage(args.source, damage, args.allow_damaged, "the frames are of the rest")
