"""`treetraits run`: the onboard service (docs/service.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from treetraits.service import DEFAULT_CONFIG_PATH

if TYPE_CHECKING:
    from treetraits.service.config import ServiceConfig


def register(commands: argparse._SubParsersAction) -> None:
    run = commands.add_parser(
        "run",
        help="the onboard service: live sensors in, tree traits out",
        description=(
            "Read the LiDAR, camera, GNSS receiver and wheel odometry live, map every tree "
            "and write OUTPUT_DIR/runs/<UTC start>/traits.sqlite (committed per scan), "
            "trees.geojson and trees.csv (rewritten atomically). Meant to run under "
            "systemd (Type=notify, watchdog); stops cleanly on SIGTERM. See docs/service.md."
        ),
    )
    add_config_option(run)
    run.add_argument(
        "--record",
        action="store_true",
        help="also record the raw sensor streams (record.dir in the config)",
    )
    run.add_argument("--out-dir", type=Path, help="output directory (overrides output.dir)")
    run.set_defaults(run=run_service)


def add_config_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        help=f"config file (TOML; default {DEFAULT_CONFIG_PATH}, or the built-in defaults "
        "when it does not exist)",
    )


def read_config(path: Path | None) -> ServiceConfig:
    """The config the user named, else the installed one, else the defaults."""
    from treetraits.service.config import load_config

    if path is None and DEFAULT_CONFIG_PATH.is_file():
        path = DEFAULT_CONFIG_PATH
    return load_config(path)


def run_service(args: argparse.Namespace) -> int:
    import logging

    from treetraits.service.config import with_overrides
    from treetraits.service.logs import setup_logging
    from treetraits.service.runtime import Service

    cfg = read_config(args.config)
    if args.record:
        cfg = with_overrides(cfg, record={"enabled": True})
    if args.out_dir is not None:
        cfg = with_overrides(cfg, output={"dir": str(args.out_dir.resolve())})
    setup_logging(cfg.service.log_level)
    if args.config is None:
        logging.getLogger("treetraits.service").info(
            "no --config: using %s",
            DEFAULT_CONFIG_PATH if DEFAULT_CONFIG_PATH.is_file() else "the built-in defaults",
        )
    return Service(cfg, config_path=args.config).run()
