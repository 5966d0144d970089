"""Where the service logs: the journal under systemd, stderr otherwise.

Under systemd (`JOURNAL_STREAM` or `INVOCATION_ID` in the environment) records go through
systemd-python's `JournalHandler` with `SYSLOG_IDENTIFIER=treetraits`, so `journalctl -u
treetraits` shows them with their priority; a record's `SENSOR` extra becomes a journal
field (`journalctl SENSOR=gnss`). By hand they go to stderr with a time stamp.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Mapping

FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def under_systemd(env: Mapping[str, str]) -> bool:
    return bool(env.get("JOURNAL_STREAM") or env.get("INVOCATION_ID"))


def setup_logging(level: str = "info", env: Mapping[str, str] | None = None) -> logging.Handler:
    """Route every logger (drivers' included) to the journal or stderr; returns the handler."""
    env = os.environ if env is None else env
    handler: logging.Handler | None = None
    if under_systemd(env):
        try:
            from systemd.journal import JournalHandler
        except ImportError:  # stderr still reaches the journal through the unit's stream
            handler = None
        else:
            handler = JournalHandler(SYSLOG_IDENTIFIER="treetraits")
            handler.setFormatter(logging.Formatter("%(name)s: %(message)s"))
    if handler is None:
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter(FORMAT))
    root = logging.getLogger()
    for old in list(root.handlers):
        root.removeHandler(old)
    root.addHandler(handler)
    root.setLevel(level.upper())
    return handler
