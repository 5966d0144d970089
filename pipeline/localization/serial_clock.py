"""Serial devices' own times on the host clock: the Jackal MCU's header stamps, the retrofit
encoder board's clock, GNSS epochs' UTC.

The service stamps serial bytes when its reader threads read them; on a loaded host they
wait (in the pty, for the thread) and come in backlogs: gaps of 600-730 ms, then a dozen
messages read in the same millisecond (docs/service.md, "Live against replay"). A replay
reads the times the recording holds, so a live run and a replay of the same drive would
see different times. Each device's own time, put on the host clock by the least delay
(`least_delay.LeastDelayOffset`), gives both the time an unloaded host would have read.
"""

from __future__ import annotations

from dataclasses import dataclass

from treetraits.pipeline.localization.least_delay import LeastDelayOffset

# The least delay is taken over this much host time: long enough to hold, through the
# longest backlog measured (0.73 s), many messages that met no queue (the MCU's 50 Hz
# feedback, a receiver's 1-10 Hz epochs), short enough that a crystal 100 ppm off the
# host's clock moves 0.5 ms in it.
SERIAL_WINDOW_NS = 5_000_000_000
# A message read this much later than the least delay says is a device clock that went
# back (an MCU or board reset, a time sync stepping the MCU's clock, the host's stepped
# forward), not a wait: backlogs on a loaded 2-core host reached 0.73 s, and a scan waits
# at most `survey.POSE_WAIT_NS` (1 s) for its pose, so a longer wait would have lost the
# data anyway. The estimate then restarts. (A clock that went forward needs no bound: the
# smaller delay is the new least at once.)
MAX_SERIAL_WAIT_NS = 2_000_000_000


@dataclass
class SerialClock:
    """One device clock: `place` turns a message's stamp and read time into its time on the
    host clock."""

    offset: LeastDelayOffset

    @classmethod
    def new(cls) -> SerialClock:
        return cls(LeastDelayOffset(SERIAL_WINDOW_NS, MAX_SERIAL_WAIT_NS))

    def place(self, t_host: int, stamp_ns: int | None) -> int:
        """`stamp_ns` on the host clock; `t_host` itself for a message without a stamp
        (None, or 0: a ROS header left unset)."""
        if not stamp_ns:
            return t_host
        return self.offset.place(t_host, stamp_ns)
