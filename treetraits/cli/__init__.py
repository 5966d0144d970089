"""The `treetraits` command line: one entry point, a sub-command per job.

Errors the user can fix (a bad path, a port in use) and what the system refuses (permission,
disk full) print one clear line and exit with a documented code (docs/cli.md); only a bug ends
in a traceback.
"""

from __future__ import annotations

import argparse
import sqlite3
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
from treetraits.errors import EXIT_INTERRUPTED, EXIT_IO, EXIT_USAGE, TreetraitsError


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
    # The one error boundary of every command: what the user or the system can be told in
    # a line never ends in a traceback (exit codes: docs/cli.md). Only a bug does (exit 1).
    try:
        return int(args.run(args) or 0)
    except TreetraitsError as exc:
        return _fail(str(exc), exc.exit_code)
    except KeyboardInterrupt:
        return _fail("interrupted; outputs of this run not written", EXIT_INTERRUPTED)
    except BrokenPipeError:  # e.g. `treetraits lidar info x | head`
        return 0
    except OSError as exc:
        return _fail(describe_os_error(exc), EXIT_IO)
    except sqlite3.Error as exc:
        return _fail(f"SQLite: {exc}", EXIT_IO)
    except RecursionError:
        return _fail("an input is nested too deeply to be read (JSON or TOML?)", EXIT_USAGE)
    except UnicodeDecodeError as exc:
        return _fail(f"an input is not UTF-8 text ({exc.reason} at byte {exc.start})", EXIT_USAGE)


def _fail(message: str, code: int) -> int:
    print(f"treetraits: error: {message}", file=sys.stderr)
    return code


def describe_os_error(exc: OSError) -> str:
    """`FILE: what the system said` (both files of a rename)."""
    what = exc.strerror or str(exc)
    if exc.filename is None:
        return what
    if exc.filename2 is not None:
        return f"{exc.filename} -> {exc.filename2}: {what}"
    return f"{exc.filename}: {what}"


if __name__ == "__main__":
    sys.exit(main())
