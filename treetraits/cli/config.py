"""`treetraits config dump|check`: the service's effective config, and checking a file."""

from __future__ import annotations

import argparse
from pathlib import Path

from treetraits.cli.run import add_config_option, read_config


def register(commands: argparse._SubParsersAction) -> None:
    config = commands.add_parser(
        "config",
        help="print the service's effective config, or check a config file",
        description="The service's configuration (TOML); docs/service.md lists every key.",
    )
    actions = config.add_subparsers(dest="action", metavar="ACTION", required=True)
    dump = actions.add_parser(
        "dump",
        help="print the effective config (every key, defaults filled in) as TOML",
        description=(
            "Print the config the service would run with: the file's keys, the defaults for "
            "the rest, relative paths made absolute. The output is itself a valid config."
        ),
    )
    add_config_option(dump)
    dump.add_argument("--bare", action="store_true", help="without the comments")
    dump.set_defaults(run=run_dump)
    check = actions.add_parser(
        "check",
        help="check a config file; exit 0 when valid, 2 with the bad key named otherwise",
        description=(
            "Make every start-up check of `treetraits run` that needs no device, without "
            "starting anything: the keys and their ranges, the LiDAR's two ports, a sensor "
            "enabled, the camera's video file, the calibration and field-map files, and "
            "that output.dir (and record.dir when recording) can be written. Only binding "
            "the LiDAR's port is left to the start. Exit 0 when run would start, 2 with "
            "the key named otherwise."
        ),
    )
    check.add_argument("file", type=Path, help="config file (TOML)")
    check.set_defaults(run=run_check)


def run_dump(args: argparse.Namespace) -> int:
    from treetraits.service.config import dump_config

    print(dump_config(read_config(args.config), comments=not args.bare), end="")
    return 0


def run_check(args: argparse.Namespace) -> int:
    from treetraits.service.config import load_config
    from treetraits.service.preflight import check_start

    cfg = load_config(args.file)
    # The very checks `run` makes at start (service/preflight.py), not a twin of them.
    inputs = check_start(cfg, process=True, record=cfg.record.enabled, as_service=False)
    print(f"{args.file}: ok")
    defaulted = inputs.calibration.describe_defaults()
    for note in ([defaulted] if defaulted else []) + list(inputs.notes):
        print(f"note: {note}")
    return 0
