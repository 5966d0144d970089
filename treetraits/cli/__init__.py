"""The `treetraits` command line: one entry point, a sub-command per job.

Errors the user can fix (a bad path, a port in use) and what the system refuses (permission,
disk full) print one clear line and exit with a documented code (docs/cli.md); only a bug ends
in a traceback.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading

from treetraits import __version__
from treetraits.errors import (
    EXIT_INTERRUPTED,
    EXIT_IO,
    EXIT_TERMINATED,
    EXIT_USAGE,
    TreetraitsError,
)


def build_parser() -> argparse.ArgumentParser:
    # The commands are imported here, inside main's error boundary: their imports (NumPy,
    # Open3D, OpenCV...) take seconds, and Ctrl-C then must not end in a traceback.
    from treetraits.cli import (
        batch,
        calibrate,
        camera,
        config,
        doctor,
        eval,
        export,
        fuse,
        imports,
        inspect,
        lidar,
        nmea,
        play,
        record,
        replay,
        report,
        run,
        season,
        sim,
    )

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
    inspect.register(commands)
    imports.register(commands)
    export.register(commands)
    run.register(commands)
    record.register(commands)
    config.register(commands)
    play.register(commands)
    doctor.register(commands)
    eval.register(commands)
    batch.register(commands)
    season.register(commands)
    report.register(commands)
    return parser


def main(argv: list[str] | None = None) -> int:
    # The one error boundary of every command: what the user or the system can be told in
    # a line never ends in a traceback (exit codes: docs/cli.md). Only a bug does (exit 1).
    interrupted = threading.Event()
    previous = _watch_interrupt(interrupted)
    try:
        args = build_parser().parse_args(argv)
        return int(args.run(args) or 0)
    except TreetraitsError as exc:
        return _fail(str(exc), exc.exit_code)
    except Terminated:
        return _fail("interrupted (SIGTERM)", EXIT_TERMINATED)
    except KeyboardInterrupt:
        return _fail(INTERRUPTED, EXIT_INTERRUPTED)
    except BrokenPipeError:  # e.g. `treetraits lidar info x | head`
        return 0
    except OSError as exc:
        return _fail(describe_os_error(exc), EXIT_IO)
    except _sqlite_error() as exc:  # evaluated only when an exception gets here
        return _fail(f"SQLite: {exc}", EXIT_IO)
    except RecursionError:
        return _fail("an input is nested too deeply to be read (JSON or TOML?)", EXIT_USAGE)
    except UnicodeDecodeError as exc:
        return _fail(f"an input is not UTF-8 text ({exc.reason} at byte {exc.start})", EXIT_USAGE)
    except Exception:
        # Ctrl-C inside a C extension's import comes out as its ImportError ("initialization
        # failed"): an interruption all the same, not a bug.
        if interrupted.is_set():
            return _fail(INTERRUPTED, EXIT_INTERRUPTED)
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


INTERRUPTED = "interrupted (SIGINT)"


class _NoSqliteError(Exception):
    """Raised by nothing: what `_sqlite_error` names while SQLite is not loaded."""


def _sqlite_error() -> type[Exception]:
    """sqlite3.Error once SQLite is loaded (only then can it have raised one). Importing it
    for the `except` clause alone would cost every start, `--help` included."""
    module = sys.modules.get("sqlite3")
    return module.Error if module is not None else _NoSqliteError


class Terminated(KeyboardInterrupt):
    """SIGTERM (`kill`, a CI runner's timeout, systemd): stopped as Ctrl-C stops a command
    (`sim` discards what it built, the earlier outputs stay), with its own exit code.
    `run`, `record` and `replay` install their own handler: a clean stop with a final
    export (`replay`: cli/stopping.py)."""


def _watch_interrupt(event: threading.Event) -> dict:
    """Make Ctrl-C raise KeyboardInterrupt as Python's own handler does (SIGTERM:
    `Terminated`), and set `event`. Each is left alone when ignored (a background job) or
    handled by someone else, and off the main thread. The handlers to put back."""

    def interrupt(signum, frame):
        event.set()
        raise KeyboardInterrupt

    def terminate(signum, frame):
        event.set()
        raise Terminated

    previous = {}
    with contextlib.suppress(ValueError):  # not the main thread
        if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            previous[signal.SIGINT] = signal.signal(signal.SIGINT, interrupt)
        if signal.getsignal(signal.SIGTERM) == signal.SIG_DFL:
            previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, terminate)
    return previous


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
