"""`treetraits record`: the raw sensor streams to a recording, nothing else."""

from __future__ import annotations

import argparse
from pathlib import Path

from treetraits.cli.run import add_config_option, read_config


def register(commands: argparse._SubParsersAction) -> None:
    record = commands.add_parser(
        "record",
        help="record the live sensors' raw streams (recording format v1)",
        description=(
            "Read the sensors enabled in the config and write what each sends, exactly as "
            "received, to OUT (MCAP, recording format v1), rotating to OUT.1.mcap, "
            "OUT.2.mcap, ... past record.max_file_mb. Chunks are small (record.chunk_kb) so "
            "a power cut loses about a second; a cut file still replays up to the cut. "
            "Stops cleanly on SIGTERM or Ctrl-C."
        ),
    )
    add_config_option(record)
    record.add_argument("--out", required=True, type=Path, help="recording to write (.mcap)")
    record.set_defaults(run=run_record)


def run_record(args: argparse.Namespace) -> int:
    from treetraits.files import check_output_file
    from treetraits.service.logs import setup_logging

    # A directory is refused before any device is opened; an existing recording is the
    # recorder's to refuse (never overwritten, exit 4).
    check_output_file(args.out)
    from treetraits.service.runtime import Service

    cfg = read_config(args.config)
    setup_logging(cfg.service.log_level)
    return Service(cfg, process=False, record_path=args.out, config_path=args.config).run()
