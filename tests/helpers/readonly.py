"""A command run with a directory it may not write: how a grower's read-only USB stick or
a store shared read-only looks to it."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers.paths import REPO

TIMEOUT_S = 300  # a command's imports and work on a loaded 2-core machine


def run_with_read_only(directory: Path, argv: list[str]) -> subprocess.CompletedProcess:
    """`python -m treetraits ARGV` with `directory` read-only for it (`run_read_only`)."""
    return run_read_only(directory, [sys.executable, "-m", "treetraits", *argv])


def run_read_only(directory: Path, command: list[str]) -> subprocess.CompletedProcess:
    """`command` with `directory` read-only for it. Not root: the directory's write bits
    are taken away (and given back). Root writes whatever the mode says, so there the
    directory is a read-only bind mount in a mount namespace of the command's own
    (`unshare`), a real read-only file system that nothing else sees; skipped where the
    machine refuses that."""
    if os.geteuid() != 0:
        mode = directory.stat().st_mode
        directory.chmod(0o555)
        try:
            return _run(command)
        finally:
            directory.chmod(mode)
    mount = (
        'mount --bind "$0" "$0" && mount -o remount,bind,ro "$0" && '
        'if touch "$0/.probe" 2>/dev/null; then echo "still writable" >&2; exit 99; fi; '
        'exec "$@"'
    )
    result = _run(["unshare", "--mount", "sh", "-c", mount, str(directory), *command])
    if result.returncode == 99 or "unshare:" in result.stderr or "mount:" in result.stderr:
        pytest.skip(f"no read-only bind mount here: {result.stderr.strip()}")
    return result


def _run(command: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S)
