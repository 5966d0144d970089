"""The VLP-16's clock on UTC from its position packets (pipeline/localization/lidar_clock.py):
real position packets, the HDL-32E capture's real $GPRMC, and packets built with it."""

from __future__ import annotations

import datetime as dt

import numpy as np

from tests.helpers.captures import VLP16_DIR
from treetraits.drivers.gnss.sentences import checksum
from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.encode import encode_position
from treetraits.drivers.velodyne.sources import open_source
from treetraits.drivers.velodyne.telemetry import PPS_LOCKED, decode_telemetry
from treetraits.pipeline.localization.lidar_clock import (
    OFFSET_WINDOW_NS,
    SYNC_HOLD_NS,
    LidarUtcClock,
)

HOUR_NS = 3_600 * 10**9
# The real sentence in the HDL-32E capture's position packets (2012-12-11 21:46:16 UTC).
REAL_RMC = "$GPRMC,214616,A,3708.3443,N,12139.4299,W,009.7,040.6,111212,013.8,E,D*0E"
RMC_UTC = int(dt.datetime(2012, 12, 11, 21, 46, 16, tzinfo=dt.UTC).timestamp()) * 10**9


def rmc(time: str = "214616", status: str = "A") -> str:
    """The real sentence with its time or status changed (and its checksum redone)."""
    body = f"GPRMC,{time},{status},3708.3443,N,12139.4299,W,009.7,040.6,111212,013.8,E,D"
    return f"${body}*{checksum(body.encode()):02X}"


# A host clock 17.25 s ahead of UTC (no NTP in the field).
HOST_AHEAD = 17_250_000_000


def position_packets(name: str):
    source = open_source(VLP16_DIR / name)
    return [decode_telemetry(p.payload, p.t_host) for p in source if not p.is_data]


def locked_packet(utc: int, delay: int, nmea: str | None = None):
    """The position packet a locked sensor sends at `utc`, read `delay` ns later, with the
    RMC of that second (the real one's fields) unless `nmea` is given."""
    second = dt.datetime.fromtimestamp(utc // 10**9, dt.UTC)
    nmea = nmea or rmc(time=f"{second:%H%M%S}")
    payload = encode_position((utc % HOUR_NS) // 1000, PPS_LOCKED, nmea)
    return decode_telemetry(payload, utc + HOST_AHEAD + delay)


def scan_ending_at(utc_last_firing: int, delay: int) -> Scan:
    """A scan whose last firing was at `utc_last_firing`, its last packet read `delay` ns
    later; its device times carry the hour of the host clock, as the batcher builds them."""
    t_host = utc_last_firing + HOST_AHEAD + delay
    hour = t_host - t_host % HOUR_NS
    t_end = hour + utc_last_firing % HOUR_NS
    return Scan(np.zeros(0), t_end - 100_000_000, t_end, t_host, True, 76, 0, "VLP-16", "strongest")


def test_real_position_packets_without_pps_put_nothing_on_utc():
    """Every real position packet we hold: the VLP-16s' are zero but the ToH, the
    HDL-32E's carries a real RMC but PPS absent. None may set the clock."""
    packets = position_packets("lidarutils_vlp16_strongest_0x21_with_position.pcap")
    packets += position_packets("veloview_vlp16_20hz_strongest.pcap")
    hdl = position_packets("secondary/hdl32e_monterey_gprmc_short.pcap")
    assert len(packets) == 16 + 367 and len(hdl) == 9
    assert {p.nmea for p in hdl} == {REAL_RMC} and {p.pps for p in hdl} == {"absent"}
    clock = LidarUtcClock()
    for telemetry in packets + hdl:
        clock.add_telemetry(telemetry)
    last = hdl[-1].t_host
    assert clock.stats.telemetry_unlocked == len(packets) + 9
    assert clock.host_minus_utc(last) is None
    scan = scan_ending_at(RMC_UTC, 300_000)
    assert clock.place(scan) is scan


def test_the_real_rmc_with_pps_locked_names_the_hour_and_the_offset():
    assert rmc() == REAL_RMC
    clock = LidarUtcClock()
    utc = RMC_UTC + 400_000_000  # 0.4 s after the pulse the RMC describes
    clock.add_telemetry(locked_packet(utc, 350_000))
    assert clock.stats.telemetry_locked == 1
    assert clock.host_minus_utc(utc + HOST_AHEAD) == HOST_AHEAD + 350_000
    # A scan whose last packet waited 40 ms in a busy host's socket goes back to its UTC.
    scan = scan_ending_at(utc + 90_000_000, 40_000_000)
    placed = clock.place(scan)
    assert placed.t_host == utc + 90_000_000 + HOST_AHEAD + 350_000
    assert (placed.t_start, placed.t_end) == (scan.t_start, scan.t_end)
    assert clock.stats.scans_on_utc == 1


def test_a_toh_just_past_the_hour_belongs_to_the_next_hour():
    """The RMC says 21:59:59; the packet is 0.3 s past 22:00 (its ToH near 0)."""
    nmea = rmc(time="215959")
    utc = RMC_UTC + (13 * 60 + 44) * 10**9 + 300_000_000  # 22:00:00.3
    clock = LidarUtcClock()
    clock.add_telemetry(locked_packet(utc, 500_000, nmea))
    assert clock.stats.telemetry_locked == 1
    assert clock.host_minus_utc(utc + HOST_AHEAD) == HOST_AHEAD + 500_000


def test_the_offset_is_the_least_delay_and_follows_a_stepped_host_clock():
    rng = np.random.default_rng(4)
    clock = LidarUtcClock()
    utc = RMC_UTC + 100_000_000
    delays = (300_000 + rng.exponential(3_000_000, 200)).astype(np.int64)
    for k, delay in enumerate(delays):  # 200 packets over 4 s
        clock.add_telemetry(locked_packet(utc + k * 20_000_000, int(delay)))
    now = utc + 199 * 20_000_000 + HOST_AHEAD
    assert clock.host_minus_utc(now) == HOST_AHEAD + delays.min()
    # The host clock is stepped 2 s back (NTP came up): after a window it is followed.
    step = -2_000_000_000
    start = utc + 200 * 20_000_000
    for k in range(0, OFFSET_WINDOW_NS // 20_000_000 + 2):
        clock.add_telemetry(locked_packet(start + k * 20_000_000, step + 400_000))
    assert clock.host_minus_utc(start + k * 20_000_000 + HOST_AHEAD + step) == (
        HOST_AHEAD + step + 400_000
    )


def test_pps_lost_or_a_void_rmc_stops_the_clock():
    clock = LidarUtcClock()
    utc = RMC_UTC + 200_000_000
    clock.add_telemetry(locked_packet(utc, 300_000))
    assert clock.host_minus_utc(utc + HOST_AHEAD + SYNC_HOLD_NS) is not None
    assert clock.host_minus_utc(utc + HOST_AHEAD + SYNC_HOLD_NS + 400_000) is None
    # Locked but the receiver says its fix is void: the RMC's time is not to be trusted.
    void = rmc(status="V")
    clock = LidarUtcClock()
    clock.add_telemetry(locked_packet(utc, 300_000, void))
    assert clock.stats.telemetry_unlocked == 1
    assert clock.host_minus_utc(utc + HOST_AHEAD) is None
    # A stale RMC: the packet's ToH is 5 s past the second it names.
    clock.add_telemetry(locked_packet(RMC_UTC + 5_000_000_000, 300_000, REAL_RMC))
    assert clock.stats.telemetry_unlocked == 2
    # PPS synchronizing (1) with a valid RMC: not yet on UTC.
    payload = encode_position((utc % HOUR_NS) // 1000, 1, REAL_RMC)
    clock.add_telemetry(decode_telemetry(payload, utc + HOST_AHEAD))
    assert clock.host_minus_utc(utc + HOST_AHEAD) is None
