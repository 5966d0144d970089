"""A command that stops cleanly on SIGINT/SIGTERM: the first signal only asks it to stop
(it ends its loop, finishes and writes its outputs), a second stops it at once as the CLI
boundary does (`treetraits.cli.main`: KeyboardInterrupt, exit 130 / 143)."""

from __future__ import annotations

import signal

from treetraits.errors import EXIT_INTERRUPTED, EXIT_TERMINATED

EXIT_BY_SIGNAL = {"SIGINT": EXIT_INTERRUPTED, "SIGTERM": EXIT_TERMINATED}


class StopOnSignal:
    """Context manager: while inside, SIGINT and SIGTERM set `reason` ("SIGINT",
    "SIGTERM"); call the instance to read it (a `stop` callable for loops). A signal the
    process ignores (a background job's SIGINT) stays ignored. Main thread only."""

    def __init__(self) -> None:
        self.reason: str | None = None
        self._previous: dict[int, object] = {}

    def __call__(self) -> str | None:
        return self.reason

    def __enter__(self) -> StopOnSignal:
        for signum in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(signum) is signal.SIG_IGN:
                continue
            self._previous[signum] = signal.signal(signum, self._on_signal)
        return self

    def _on_signal(self, signum: int, frame) -> None:
        if self.reason is None:
            self.reason = signal.Signals(signum).name
            return
        # Asked twice: no more finishing; the boundary's own handler (or Python's).
        previous = self._previous.get(signum)
        if callable(previous):
            previous(signum, frame)
        raise KeyboardInterrupt

    def __exit__(self, *exc_info: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()
