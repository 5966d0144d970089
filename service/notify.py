"""The systemd notify protocol (sd_notify(3)), thin: READY, STATUS, WATCHDOG, STOPPING.

Messages go through `systemd.daemon.notify` (systemd-python) when `NOTIFY_SOCKET` is
set; without it every call is a no-op, so the service runs the same by hand. The watchdog
period comes from `WATCHDOG_USEC` (for this process when `WATCHDOG_PID` names another,
none); the loop pings at half of it, and only when it made progress since the last ping:
a hung pipeline stops the pings and systemd restarts the service.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Mapping

log = logging.getLogger("treetraits.service")

Send = Callable[[str], bool]


def watchdog_period_s(env: Mapping[str, str], pid: int) -> float | None:
    """The watchdog period systemd asked for, in seconds, or None (no watchdog)."""
    usec = env.get("WATCHDOG_USEC", "")
    owner = env.get("WATCHDOG_PID", "")
    if owner and owner.isdigit() and int(owner) != pid:
        return None
    try:
        period = int(usec) / 1e6
    except ValueError:
        return None
    return period if period > 0 else None


def _systemd_send() -> Send | None:
    try:
        from systemd import daemon
    except ImportError:
        log.warning("NOTIFY_SOCKET is set but systemd-python is not installed: no sd_notify")
        return None
    return daemon.notify


class Notifier:
    """sd_notify for the service. `env` is read for NOTIFY_SOCKET and the watchdog (default
    os.environ); systemd-python sends to the process's own $NOTIFY_SOCKET."""

    def __init__(
        self,
        env: Mapping[str, str] | None = None,
        send: Send | None = None,
        clock: Callable[[], float] = time.monotonic,
    ):
        env = os.environ if env is None else env
        self.enabled = bool(env.get("NOTIFY_SOCKET"))
        self._send = send if send is not None else (_systemd_send() if self.enabled else None)
        self.enabled = self.enabled and self._send is not None
        period = watchdog_period_s(env, os.getpid())
        self.watchdog_interval_s = period / 2 if period is not None else None
        self._clock = clock
        self._next_ping = clock()
        self._failed = False
        self.pings = 0

    def _notify(self, message: str) -> None:
        if not self.enabled:
            return
        try:
            self._send(message)
        except OSError as exc:  # a bad socket path: say so once, never stop the service
            if not self._failed:
                log.warning("sd_notify to $NOTIFY_SOCKET failed: %s", exc)
                self._failed = True

    def ready(self, status: str) -> None:
        self._notify(f"READY=1\nSTATUS={status}")

    def status(self, text: str) -> None:
        self._notify(f"STATUS={text}")

    def stopping(self, status: str) -> None:
        self._notify(f"STOPPING=1\nSTATUS={status}")

    def watchdog(self, progressed: bool) -> bool:
        """Ping if a ping is due and the loop made progress; True when it pinged."""
        if self.watchdog_interval_s is None or not progressed:
            return False
        now = self._clock()
        if now < self._next_ping:
            return False
        self._notify("WATCHDOG=1")
        self._next_ping = now + self.watchdog_interval_s
        self.pings += 1
        return True
