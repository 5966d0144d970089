"""The VLP-16's clock on UTC, and the host clock measured against it.

A VLP-16 with a GNSS receiver wired to its GPS input (PPS and $GPRMC) counts its
microseconds past the hour (ToH) on UTC; its position packets (port 8308) say so with PPS
status "locked" and carry the receiver's last RMC (its date and time name the hour).
Without that input the ToH counts from power-on and says nothing about UTC.

Locked, every packet's ToH is a UTC time, sent within a fraction of a millisecond of it,
so `t_host - UTC` of each packet is the host clock's offset from UTC plus the packet's
transport and read delay. The least of these over a short window is the offset
(`least_delay.LeastDelayOffset`). With it:

- a scan is placed at its last firing's UTC on the host clock instead of when its last
  packet was read (a host busy for 50 ms would move a scan at 1 m/s by 5 cm);
- a GNSS epoch's UTC goes onto the host clock exactly, whether or not the host runs NTP
  (`Localizer.epoch_time`), instead of its arrival less an assumed receiver latency.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from treetraits.drivers.gnss.sentences import RMC, parse_sentence
from treetraits.drivers.gnss.times import utc_ns
from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.models import HOUR_NS
from treetraits.drivers.velodyne.packet import resolve_hour
from treetraits.drivers.velodyne.telemetry import PPS_LOCKED, Telemetry
from treetraits.errors import ParseError
from treetraits.pipeline.localization.least_delay import LeastDelayOffset

# Position packets come tens of times a second; a sensor that has sent no locked one for
# this long has lost its GPS input (or its packets are not reaching us): its ToH may
# drift from UTC from then on, so nothing is placed by it.
SYNC_HOLD_NS = 2_000_000_000
# The offset is the least delay seen over this window: long enough to hold many packets
# that arrived without queueing, short enough that a host clock drifting at 50 ppm moves
# less than half a millisecond in it.
OFFSET_WINDOW_NS = 10_000_000_000
# A locked packet's ToH falls in the second its RMC names or the next (the RMC follows
# the pulse it describes by up to a second); one further off is inconsistent (a stale
# RMC, a ToH not yet on UTC) and is not used.
RMC_SPAN_NS = (-1_000_000_000, 2_000_000_000)


@dataclass
class LidarClockStats:
    telemetry_locked: int = 0  # position packets with PPS locked and a valid RMC
    # position packets that do not put the ToH on UTC (PPS not locked, no valid RMC, or a
    # ToH that disagrees with its RMC)
    telemetry_unlocked: int = 0
    scans_on_utc: int = 0  # scans placed at their UTC on the host clock
    host_minus_utc_ms: float | None = None  # the last offset estimate


class LidarUtcClock:
    """Feed position packets and scans in receive order (module doc)."""

    def __init__(self) -> None:
        self.stats = LidarClockStats()
        self._locked_at: int | None = None  # t_host of the last locked position packet
        self._utc_ref: tuple[int, int] | None = None  # (UTC, t_host) of that packet
        # No restart bound (as before): UTC does not jump; a host clock stepped back is
        # followed at once (a smaller delay), one stepped forward once the window turns over.
        self._offset = LeastDelayOffset(OFFSET_WINDOW_NS)

    def add_telemetry(self, telemetry: Telemetry) -> None:
        """One position packet: when locked with a valid RMC, it names the hour of the ToH
        and is itself a sample of the offset."""
        rmc_utc = _rmc_utc(telemetry.nmea) if telemetry.pps_status == PPS_LOCKED else None
        # The RMC tells the second of the last pulse; the ToH, the packet's own time.
        utc = None if rmc_utc is None else int(resolve_hour([telemetry.toh_us], [rmc_utc])[0])
        if utc is None or not RMC_SPAN_NS[0] <= utc - rmc_utc <= RMC_SPAN_NS[1]:
            self.stats.telemetry_unlocked += 1
            return
        self.stats.telemetry_locked += 1
        self._locked_at = telemetry.t_host
        self._utc_ref = (utc, telemetry.t_host)
        self._add_sample(telemetry.t_host, utc)

    def place(self, scan: Scan) -> Scan:
        """The scan with `t_host` moved to its last firing's UTC on the host clock, when the
        sensor is locked (a sample of the offset too); else as it came."""
        if not self._locked(scan.t_host):
            return scan
        utc_end = self._utc_of(scan.t_end % HOUR_NS, scan.t_host)
        self._add_sample(scan.t_host, utc_end)
        offset = self.host_minus_utc(scan.t_host)
        if offset is None:
            return scan
        self.stats.scans_on_utc += 1
        return replace(scan, t_host=utc_end + offset)

    def host_minus_utc(self, t_host: int) -> int | None:
        """The host clock's offset from UTC (ns) at `t_host`, None when the sensor is not
        locked (or not since SYNC_HOLD_NS)."""
        if not self._locked(t_host):
            return None
        return self._offset.offset

    def _locked(self, t_host: int) -> bool:
        # Either side: position packets may come a little out of order with data packets.
        return self._locked_at is not None and abs(t_host - self._locked_at) <= SYNC_HOLD_NS

    def _utc_of(self, ns_past_hour: int, t_host: int) -> int:
        """The UTC of a time past the hour seen at `t_host`: the hour nearest the last
        locked packet's UTC carried forward by the host clock."""
        utc, then = self._utc_ref  # type: ignore[misc]  # set whenever locked
        return int(resolve_hour([ns_past_hour // 1000], [utc + t_host - then])[0]) + (
            ns_past_hour % 1000
        )

    def _add_sample(self, t_host: int, utc: int) -> None:
        self.stats.host_minus_utc_ms = self._offset.add(t_host, utc) / 1e6


def _rmc_utc(nmea: str | None) -> int | None:
    """The UTC (ns) of a valid RMC with a date, else None."""
    if not nmea:
        return None
    try:
        record = parse_sentence(nmea.encode("ascii"))
    except ParseError:
        return None
    if not isinstance(record, RMC) or record.status != "A":
        return None
    if record.tod_ns is None or record.date is None:
        return None
    return utc_ns(record.tod_ns, record.date)
