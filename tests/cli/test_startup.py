"""The command line starts without loading the heavy libraries: `--help` of the program and
of every command imports no open3d, SciPy, filterpy, OpenCV, pyproj, MCAP, numba or NumPy (they
are imported by the code that uses them). Behaviour, not timing: bench/replay.py times it.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

from treetraits.cli import build_parser

HEAVY = (
    "open3d", "scipy", "filterpy", "cv2", "pyproj", "mcap", "numpy", "matplotlib", "dask",
    "distributed", "numba",
)  # fmt: skip


def imported_modules(*args: str) -> set[str]:
    """Every module `python -X importtime -m treetraits ARGS` imported (a fresh process)."""
    result = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "treetraits", *args],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.startswith("usage: treetraits")
    return {
        line.rsplit("|", 1)[1].strip()
        for line in result.stderr.splitlines()
        if line.startswith("import time:") and "|" in line
    }


def commands() -> list[str]:
    parser = build_parser()
    (sub,) = (a for a in parser._actions if a.dest == "command")
    return sorted(sub.choices)


def test_the_listing_reads_every_command():
    assert {"lidar", "sim", "replay", "run", "eval", "doctor"} <= set(commands())


@pytest.mark.parametrize("command", [[], *([c] for c in commands()), ["lidar", "listen"]])
def test_help_loads_no_heavy_library(command):
    modules = imported_modules(*command, "--help")
    assert "treetraits.cli" in modules  # the importtime listing was read
    loaded = sorted({m.split(".")[0] for m in modules} & set(HEAVY))
    assert loaded == [], f"`treetraits {' '.join(command)} --help` imported {loaded}"


# Standard-library and own modules that cost a start several milliseconds each (inspect
# through dataclasses, logging, sqlite3's shared library, tempfile with shutil and random,
# statistics with fractions and decimal; the config schema's hundred dataclasses): loaded
# by the commands that use them, never by the parser.
SLOW = (
    "sqlite3", "tempfile", "statistics", "logging", "inspect", "dataclasses", "csv",
    "datetime", "treetraits.pipeline.config",
)  # fmt: skip


def test_help_loads_no_slow_module():
    modules = imported_modules("--help")
    assert "treetraits.cli" in modules
    loaded = sorted(set(SLOW) & modules)
    assert loaded == [], f"`treetraits --help` imported {loaded}"
