"""When a survey played into the service began, on the host clock: the first LiDAR
packet's first firing, by the least delay of the packets that follow.

A video played as the camera (`workers.PacedVideo`) stands in for a camera that ran with
the survey: its frame k was captured k frame periods after the survey's first firing. The
first packet's read time is a poor anchor on a loaded host (read 2-3 ms late, it moved
every frame 2-3 ms: enough, for scans whose middle falls halfway between two frames, to
take the other one). Each packet's ToH (device microseconds past the hour, its first
firing) says how long after the first firing it was sent; the least `read - sent` over the
first seconds is the delay of a packet that met no queue, and the first firing is the first
ToH plus it.
"""

from __future__ import annotations

from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.packet import view_packets
from treetraits.pipeline.localization.least_delay import LeastDelayOffset

# Packets over this much of the survey's start give the least delay: at ~750 packets a
# second, thousands, most of them read without queueing; the estimate is fixed after it,
# so the frames' stamps do not move during the run.
ANCHOR_SPAN_NS = 5_000_000_000
_HOUR_US = m.HOUR_NS // 1000


class SurveyStart:
    """Feed LiDAR data packets with their read times; `first_firing_ns` is the estimate
    (None before the first packet)."""

    def __init__(self) -> None:
        self.first_firing_ns: int | None = None
        self._first: tuple[int, int] | None = None  # (ToH us, read time) of the first packet
        # Device time: ns since the first packet's first firing.
        self._offset = LeastDelayOffset(ANCHOR_SPAN_NS)

    def add(self, packet: bytes, t_host: int) -> bool:
        """One packet; True when the estimate changed (False past the span, or for a packet
        that is not a data packet)."""
        if len(packet) != m.DATA_PACKET_SIZE:
            return False
        fields = view_packets(packet)[0]
        toh_us = int(fields["toh"])  # microseconds past the hour of its first firing
        if self._first is None:
            self._first = (toh_us, t_host)
        elif t_host - self._first[1] > ANCHOR_SPAN_NS:
            return False
        # Sent after its last firing: its ToH (its first firing; past the first packet's,
        # across the hour) plus a packet period.
        since_first_ns = ((toh_us - self._first[0]) % _HOUR_US) * 1000
        sent = since_first_ns + m.packet_period_ns(int(fields["return_mode"]))
        estimate = self._offset.add(t_host, sent)
        changed, self.first_firing_ns = estimate != self.first_firing_ns, estimate
        return changed
