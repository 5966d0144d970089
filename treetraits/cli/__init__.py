"""The `treetraits` command line: one entry point, a sub-command per job.

Errors the user can fix (a bad path, a port in use) print one clear line and exit with the
error's code (2 for a bad input or option; the table is in docs/cli.md); they never end in a
traceback.
"""

from __future__ import annotations

import argparse
import sys

from treetraits import __version__
from treetraits.cli import (
    calibrate,
    camera,
    config,
    doctor,
    eval,
    fuse,
    lidar,
    nmea,
    play,
    record,
    replay,
    run,
    sim,
)
from treetraits.errors import EXIT_INTERRUPTED, TreetraitsError


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="treetraits",
        description=(
            "Onboard orchard tree mapper: reads a Velodyne VLP-16, a MAPIR Survey3N, GNSS "
            "and wheel odometry without ROS, and writes each tree's width, height and NDVI."
        ),
    )
    parser.add_argument("--version", action="version", version=f"treetraits {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    lidar.register(commands)
    nmea.register(commands)
    camera.register(commands)
    calibrate.register(commands)
    fuse.register(commands)
    sim.register(commands)
    replay.register(commands)
    run.register(commands)
    record.register(commands)
    config.register(commands)
    play.register(commands)
    doctor.register(commands)
    eval.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except TreetraitsError as exc:
        print(f"treetraits: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # e.g. `treetraits lidar info x | head`
        return 0


if __name__ == "__main__":
    sys.exit(main())
