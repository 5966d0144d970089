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
    )
    check.add_argument("file", type=Path, help="config file (TOML)")
    check.set_defaults(run=run_check)


def run_dump(args: argparse.Namespace) -> int:
    from treetraits.service.config import dump_config

    print(dump_config(read_config(args.config), comments=not args.bare), end="")
    return 0


def run_check(args: argparse.Namespace) -> int:
    from treetraits.service.config import load_config

    load_config(args.file)
    print(f"{args.file}: ok")
    return 0
