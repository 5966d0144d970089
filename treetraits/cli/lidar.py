"""`treetraits lidar info|export|listen`: look at VLP-16 captures and at a live sensor."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from treetraits.damage import add_allow_damaged, report_damage, source_integrity
from treetraits.errors import ConfigError
from treetraits.service.outdir import OutputDir

if TYPE_CHECKING:
    from treetraits.drivers.records import Scan
    from treetraits.drivers.velodyne.reader import LidarReader

_INPUT_HELP = (
    "a libpcap/pcapng capture, an MCAP recording (format v1) or a raw file of 1206-byte "
    "payloads; recognised by content"
)


def register(commands: argparse._SubParsersAction) -> None:
    from treetraits.drivers import DATA_PORT, TELEMETRY_PORT

    lidar = commands.add_parser(
        "lidar",
        help="inspect VLP-16 captures and a live sensor",
        description="Velodyne VLP-16 / Puck LITE / Puck Hi-Res: decode, summarise, export.",
    )
    sub = lidar.add_subparsers(dest="lidar_command", metavar="COMMAND", required=True)

    info = sub.add_parser(
        "info",
        help="summarise a capture: packets, scans, points, model, rpm, losses",
        description=(
            "Decode a capture and summarise it. Scans are cut at packet granularity when "
            "the last block's azimuth crosses --cut-angle. `full_scans` leaves out the "
            "first and last scan of the input (a capture starts and stops anywhere); "
            "`points_*` count distinct returns (a dual-return echo seen by both the last "
            "and the strongest block counts once; `duplicate_returns` counts the repeats)."
        ),
    )
    info.add_argument("path", help=_INPUT_HELP)
    info.add_argument("--json", action="store_true", help="print one JSON object")
    add_allow_damaged(info, "prints the summary")
    _add_decoder_options(info)
    info.set_defaults(run=run_info)

    export = sub.add_parser(
        "export",
        help="write one binary PCD file per scan",
        description=(
            "Write each scan as DIR/scan_NNNNNN.pcd (binary PCD, fields x y z intensity "
            "ring t; t in seconds since the Unix epoch) and an index DIR/scans.csv."
        ),
    )
    export.add_argument("path", help=_INPUT_HELP)
    export.add_argument("--out", required=True, type=Path, help="output directory")
    export.add_argument(
        "--full-only", action="store_true", help="skip the partial first and last scans"
    )
    export.add_argument(
        "--force",
        action="store_true",
        help="replace an earlier export in DIR (its scans.csv and every scan_*.pcd; without "
        "it the export is refused, exit 4)",
    )
    add_allow_damaged(export, "writes the scans")
    _add_decoder_options(export)
    export.set_defaults(run=run_export)

    listen = sub.add_parser(
        "listen",
        help="receive a live sensor and print rates and losses every second",
        description=(
            "Listen for VLP-16 packets on UDP and print, every second, the packet rate, "
            "scan rate, points per scan and every loss counter. Ctrl-C stops."
        ),
    )
    listen.add_argument("--bind", default="0.0.0.0", help="local address (default 0.0.0.0)")
    listen.add_argument("--port", type=int, default=DATA_PORT, help="data port (default 2368)")
    listen.add_argument(
        "--telemetry-port",
        type=int,
        default=TELEMETRY_PORT,
        help="position packet port (default 8308; 0 = do not listen)",
    )
    listen.add_argument("--sensor-ip", help="accept packets from this address only")
    listen.add_argument("--seconds", type=float, help="stop after this many seconds")
    listen.add_argument("--json", action="store_true", help="print the final summary as JSON")
    _add_decoder_options(listen)
    listen.set_defaults(run=run_listen)


def _add_decoder_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--model",
        default="auto",
        help=(
            "auto (read the packet's product byte; 0x21 from early VLP-16 firmware is "
            "told from an HDL-32E by packet timing), vlp16, puck-lite or puck-hires"
        ),
    )
    parser.add_argument(
        "--cut-angle",
        type=float,
        default=0.0,
        metavar="DEG",
        help="sensor azimuth where a scan ends, degrees in [0, 360) (default 0)",
    )


def _reader(uri: str, args: argparse.Namespace) -> LidarReader:
    from treetraits.drivers.velodyne.reader import LidarReader
    from treetraits.drivers.velodyne.sources import open_source

    try:
        return LidarReader(open_source(uri), model=args.model, cut_angle_deg=args.cut_angle)
    except ValueError as exc:
        raise ConfigError(str(exc)) from exc


def _summarise(reader: LidarReader) -> dict:
    from treetraits.drivers.records import Scan
    from treetraits.drivers.velodyne.summary import LidarSummary
    from treetraits.drivers.velodyne.telemetry import Telemetry

    summary = LidarSummary()
    for item in reader:
        if isinstance(item, Scan):
            summary.add_scan(item)
        elif isinstance(item, Telemetry):
            summary.add_telemetry(item)
    return summary.as_dict(reader.counters())


def run_info(args: argparse.Namespace) -> int:
    reader = _reader(args.path, args)
    try:
        facts = _summarise(reader)
    finally:
        reader.close()
    damage = source_integrity(reader.source)
    # `lost` is the packets the batcher missed: the recording's lost time spans apart.
    facts.update(
        damaged_chunks=damage["damaged_chunks"],
        lost_spans=damage["lost"],
        data_loss=damage["data_loss"],
    )
    status = report_damage(args.path, damage, args.allow_damaged, "the summary is of the rest")
    if args.json:
        print(json.dumps(facts, indent=1))
    else:
        print(_format_facts(args.path, facts))
    return status


def _format_facts(title: str, facts: dict) -> str:
    lines = [title]
    width = max(len(k) for k in facts)
    for key, value in facts.items():
        if value in (None, {}, []) or key.startswith("t_"):
            continue
        lines.append(f"  {key:<{width}}  {value}")
    return "\n".join(lines)


# The files an export owns in its directory (service/outdir.py): replaced whole.
EXPORT_OUTPUTS = ("scans.csv", "scan_*.pcd")


def run_export(args: argparse.Namespace) -> int:
    import csv

    from tqdm import tqdm

    from treetraits.drivers.records import Scan

    output = OutputDir(
        args.out, EXPORT_OUTPUTS, force=args.force, inputs=[Path(args.path)], what="an export"
    )
    reader = _reader(args.path, args)
    written = 0
    pending: Scan | None = None  # held back one scan so --full-only can drop the last
    try:
        # Built aside and moved into place at the end: an export into an earlier one
        # leaves no stale scan of it.
        with output as staging, open(staging / "scans.csv", "w", newline="") as index_file:
            index = csv.writer(index_file)
            index.writerow(
                ["file", "scan", "t_start_ns", "t_end_ns", "points", "complete", "lost_packets"]
            )
            scans = (item for item in reader if isinstance(item, Scan))
            for number, scan in enumerate(
                tqdm(scans, unit="scan", desc="export", leave=False, disable=None)
            ):
                if pending is not None:
                    written += _export_one(staging, index, number - 1, pending)
                pending = None if (args.full_only and number == 0) else scan
            if pending is not None and not args.full_only:
                written += _export_one(staging, index, number, pending)
            index_file.flush()
    finally:
        reader.close()
    print(f"wrote {written} scans to {args.out} (index: {args.out / 'scans.csv'})")
    damage = source_integrity(reader.source)
    return report_damage(args.path, damage, args.allow_damaged, "the scans are of the rest")


def _export_one(out: Path, index, number: int, scan: Scan) -> int:
    from treetraits.drivers.velodyne.pcd import write_pcd

    name = f"scan_{number:06d}.pcd"
    write_pcd(out / name, scan.points)
    index.writerow(
        [name, number, scan.t_start, scan.t_end, len(scan.points), scan.complete, scan.lost_packets]
    )
    return 1


def run_listen(args: argparse.Namespace) -> int:
    from treetraits.drivers.records import Scan
    from treetraits.drivers.velodyne.reader import LidarReader
    from treetraits.drivers.velodyne.sources import UdpSource
    from treetraits.drivers.velodyne.summary import LidarSummary
    from treetraits.drivers.velodyne.telemetry import Telemetry

    source = UdpSource(
        host=args.bind,
        port=args.port,
        telemetry_port=args.telemetry_port or None,
        sensor_ip=args.sensor_ip,
    )
    print(
        f"listening on {args.bind}:{args.port}"
        + (f" and :{args.telemetry_port}" if args.telemetry_port else "")
        + f", receive buffer {source.effective_rcvbuf // 1024} KiB",
        file=sys.stderr,
    )
    reader = LidarReader(source, model=args.model, cut_angle_deg=args.cut_angle)
    summary = LidarSummary()
    start = last_report = time.monotonic()
    last_packets = last_scans = 0
    points_last = 0
    try:
        while args.seconds is None or time.monotonic() - start < args.seconds:
            packet = source.read(timeout=0.2)
            item = None if packet is None else reader.handle(packet)
            if isinstance(item, Scan):
                summary.add_scan(item)
                points_last = len(item.distinct)
            elif isinstance(item, Telemetry):
                summary.add_telemetry(item)
            now = time.monotonic()
            if now - last_report >= 1.0:
                counters = reader.counters()
                rate = (counters["packets"] - last_packets) / (now - last_report)
                scans = len(summary.scan_points)
                hz = (scans - last_scans) / (now - last_report)
                print(
                    f"{now - start:6.1f}s  {rate:7.1f} pkt/s  {hz:5.1f} scans/s  "
                    f"{points_last:6d} pts/scan  lost {counters['batcher_lost']}  "
                    f"malformed {counters['malformed'] + counters['batcher_malformed']}  "
                    f"foreign {counters['foreign']}  kernel drops {counters['kernel_drops']}",
                    file=sys.stderr,
                )
                if counters["packets"] == 0 and now - start > 2:
                    print(
                        f"  no packets yet: is the sensor on this network, sending to port "
                        f"{args.port}? A firewall may drop them (ufw allow {args.port}/udp).",
                        file=sys.stderr,
                    )
                last_report, last_packets, last_scans = now, counters["packets"], scans
    except KeyboardInterrupt:
        pass
    finally:
        reader.close()
    last = reader.batcher.flush()  # the scan in progress when listening stopped
    if last is not None:
        summary.add_scan(last)
    facts = summary.as_dict(reader.counters())
    print(json.dumps(facts, indent=1) if args.json else _format_facts("live", facts))
    return 0
