"""A device's clock put onto the host clock by the least delay of its messages.

A message stamped `stamp` by a device (a VLP-16's UTC, an MCU's header stamp, a GNSS
epoch's UTC) and read by the host at `t_host` gives `t_host - stamp`: the offset between
the two clocks plus the message's transport and read delay. Delays only add, so the
least of these over a window is the offset plus the least delay (a message that met no
queue); the window, seconds long, lets the estimate follow a clock that drifts or is
stepped. `stamp + offset` is then when the message would have been read on an unloaded
host: a backlog (bytes that waited 600 ms in a pty, then a dozen read in the same
millisecond) no longer bends the times.

A device clock can also jump: an MCU that resets counts from its boot again, a time sync
steps its clock, the host's clock is stepped. A jump forward (or the host's backward)
makes `t_host - stamp` smaller: the window's minimum follows at once (every larger sample
is dropped). A jump backward (or the host's forward) makes it larger, which looks like a
long delay; the estimate restarts when a sample exceeds it by more than `max_delay_ns`,
the longest a message can plausibly have waited on the host.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field


@dataclass
class LeastDelayOffset:
    """The least `t_host - stamp` over the last `window_ns` of host time (module doc)."""

    window_ns: int
    # A sample this much above the estimate is a clock that jumped, not a delay: restart.
    # None: never (a source whose clock cannot jump backward).
    max_delay_ns: int | None = None
    restarts: int = 0  # estimates restarted by a jump
    # (t_host, t_host - stamp), the second increasing: the front is the window's least.
    _samples: deque[tuple[int, int]] = field(default_factory=deque, repr=False)

    def add(self, t_host: int, stamp: int) -> int:
        """One message; returns the offset estimate with it (ns, host minus device)."""
        delay = t_host - stamp
        while self._samples and self._samples[0][0] < t_host - self.window_ns:
            self._samples.popleft()
        if (
            self.max_delay_ns is not None
            and self._samples
            and delay - self._samples[0][1] > self.max_delay_ns
        ):
            self._samples.clear()
            self.restarts += 1
        while self._samples and self._samples[-1][1] >= delay:
            self._samples.pop()
        self._samples.append((t_host, delay))
        return self._samples[0][1]

    def place(self, t_host: int, stamp: int) -> int:
        """The message's time on the host clock: `stamp` plus the offset estimate with it
        (never later than `t_host`)."""
        return stamp + self.add(t_host, stamp)

    @property
    def offset(self) -> int | None:
        """The current estimate (ns), None before the first sample."""
        return self._samples[0][1] if self._samples else None
