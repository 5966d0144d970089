"""`treetraits doctor`: can this machine run the onboard service? Each problem with its fix."""

from __future__ import annotations

import argparse
import json
import textwrap
from pathlib import Path


def register(commands: argparse._SubParsersAction) -> None:
    doctor = commands.add_parser(
        "doctor",
        help="check ports, devices, groups, the LiDAR port and limits for the service",
        description=(
            "Check what the onboard service needs: the config loads; the GNSS and wheel "
            "serial ports exist, are accessible and not held by another program; "
            "ModemManager; the USB devices and V4L2 nodes (and which one the camera setting "
            "picks); that UDP data arrives on the LiDAR port (or who holds it); "
            "net.core.rmem_max against lidar.rcvbuf_bytes; group membership; the firewall; "
            "free disk space. Each problem comes with its fix. Exit status 0 when nothing "
            "failed (warnings allowed), 1 otherwise."
        ),
    )
    doctor.add_argument(
        "--config",
        type=Path,
        metavar="FILE",
        help="service config (default /etc/treetraits/config.toml, else built-in defaults)",
    )
    doctor.add_argument("--json", action="store_true", help="print a JSON list of checks")
    doctor.add_argument(
        "--udp-seconds",
        type=float,
        default=2.0,
        metavar="S",
        help="how long to listen on the LiDAR port (default 2)",
    )
    doctor.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    import shutil

    from treetraits.service.doctor import Status, run_checks

    mark = {Status.OK: "ok", Status.WARN: "WARN", Status.FAIL: "FAIL"}
    checks = run_checks(args.config, udp_seconds=args.udp_seconds)
    if args.json:
        print(json.dumps([c.as_dict() for c in checks], indent=2))
    else:
        width = max(len(c.name) for c in checks)
        columns = max(60, shutil.get_terminal_size((100, 20)).columns)
        indent = " " * (width + 8)
        for check in checks:
            head = f"{mark[check.status]:<5} {check.name:<{width}}  "
            print(
                textwrap.fill(check.detail, columns, initial_indent=head, subsequent_indent=indent)
            )
            if check.fix:
                print(
                    textwrap.fill(
                        check.fix,
                        columns,
                        initial_indent=indent + "fix: ",
                        subsequent_indent=indent + "     ",
                    )
                )
        failed = sum(c.status is Status.FAIL for c in checks)
        warned = sum(c.status is Status.WARN for c in checks)
        print(f"{len(checks)} checks: {failed} failed, {warned} warnings")
    return 1 if any(c.status is Status.FAIL for c in checks) else 0
