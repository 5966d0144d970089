"""Packets to full-rotation scans: a push object, one data packet in, a scan out when done.

Per packet it reads only the bytes it needs (ToH, last-block azimuth, factory bytes, the
first and last block flags) and keeps the raw payload; the whole scan is checked and
decoded in one call when it closes. It cuts at packet granularity like velodyne_decoder:
a scan ends with, and includes, the first packet whose last-block azimuth has crossed
the cut angle.

Loss, duplicates and reordering are found from the device clock (ToH steps of 1327 us in
single-return mode, 664 us in dual), independent of the transport. Loss counting assumes
the sensor sends the whole 360 deg; a configured FOV shows up as lost packets.
"""

from __future__ import annotations

import struct
from dataclasses import asdict, dataclass, field

import numpy as np

from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.packet import (
    blocks_intact,
    decode_counting_duplicates,
    resolve_hour_one,
    view_packets,
)

_HOUR_US = 3_600_000_000
_HALF_HOUR_US = _HOUR_US // 2
_PACKET_SIZE = m.DATA_PACKET_SIZE
_VLP16 = m.PRODUCT_VLP16
_BLOCK_FLAG = m.BLOCK_FLAG
# The first block's flag; the last block's flag and azimuth (bytes 1100-1103); ToH,
# return mode and product (bytes 1200-1205). The other blocks' flags are checked with
# the whole scan's, when it is decoded (`blocks_intact`): a strided slice of each packet
# here cost a quarter of `push`.
_FIELDS = struct.Struct("<H1098xHH96xIBB")
assert _FIELDS.size == m.DATA_PACKET_SIZE
# Last firing of a single-return packet after its ToH (block 11, 2nd sequence, laser 15).
_LAST_FIRING_SINGLE_NS = m.PACKET_NS_SINGLE - m.SEQUENCE_NS + 15 * m.LASER_SLOT_NS
_RETURN_MODES = frozenset(m.RETURN_MODE_NAMES)
# A ToH step longer than 1.5 packet periods (us) means packets were lost.
_LOSS_STEP_US = {mode: 1.5 * m.packet_period_ns(mode) / 1000 for mode in m.RETURN_MODE_NAMES}


def _firings_in_order(t_packet: np.ndarray) -> bool:
    """True when each single-return packet starts after the last firing of the one
    before: the points' times then never run back and need no clamping."""
    return len(t_packet) < 2 or int((t_packet[1:] - t_packet[:-1]).min()) > _LAST_FIRING_SINGLE_NS


@dataclass
class BatcherStats:
    """What the batcher saw. Every data packet lands in exactly one of: decoded into a
    scan, `malformed`, `unsupported_model`, `duplicates`, `late`."""

    data_packets: int = 0
    malformed: int = 0
    unsupported_model: int = 0
    lost: int = 0  # missing from the device clock sequence
    duplicates: int = 0
    out_of_order: int = 0  # arrived late but put back in place within its scan
    late: int = 0  # arrived after its scan was closed: dropped
    time_jumps: int = 0  # device clock jumped (sensor restart, reconfigured): scan closed
    scans: int = 0
    complete_scans: int = 0
    points: int = 0
    duplicate_returns: int = 0

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


@dataclass(slots=True)
class _ScanInProgress:
    started_at_cut: bool
    return_mode: int
    product: int
    t_host_first: int  # late packets are put back between the first and the last
    t_host_last: int = 0
    payloads: list[bytes] = field(default_factory=list)
    toh: list[int] = field(default_factory=list)  # unwrapped device microseconds
    lost: int = 0
    coverage: int | None = None  # centidegrees swept past the cut angle


class ScanBatcher:
    """Turns a stream of VLP-16 data payloads into `Scan`s.

    `model`: "auto" (read byte 1205; 0x21 is taken for a VLP-16 only when the packet
    timing says 16 lasers) or a name from `models.MODELS_BY_NAME` to override the byte.
    `cut_angle_deg`: sensor azimuth where one scan ends and the next begins.
    `max_gap_s`: a device-clock step longer than this (or backwards further than this)
    is a time jump, not packet loss; a scan is also closed after this much device time.
    """

    def __init__(self, model: str = "auto", cut_angle_deg: float = 0.0, max_gap_s: float = 1.0):
        if not 0.0 <= cut_angle_deg < 360.0:
            raise ValueError(f"cut angle must be in [0, 360) degrees, got {cut_angle_deg}")
        self._forced_model = m.model_by_name(model)
        self._cut = round(cut_angle_deg * 100) % 36000
        self._max_gap_us = int(max_gap_s * 1e6)
        self._scan: _ScanInProgress | None = None
        self._next_starts_at_cut = False
        self._byte21_is_vlp16: bool | None = None  # settled by packet timing
        self._last_toh: int | None = None  # unwrapped device microseconds
        self.stats = BatcherStats()

    def push(self, payload: bytes, t_host: int) -> Scan | None:
        """Add one 1206-byte data payload received at `t_host` (ns since the epoch).
        Returns the scan this packet completed, if any. Never raises on bad bytes."""
        stats = self.stats
        stats.data_packets += 1
        if len(payload) != _PACKET_SIZE:
            stats.malformed += 1
            return None
        first_flag, last_flag, azimuth, toh_raw, mode, product = _FIELDS.unpack_from(payload)
        if (
            first_flag != _BLOCK_FLAG
            or last_flag != _BLOCK_FLAG
            or mode not in _RETURN_MODES
            or azimuth > 36000
            or toh_raw >= _HOUR_US
        ):
            stats.malformed += 1
            return None
        if product != _VLP16 and not self._supported(product, toh_raw):
            stats.unsupported_model += 1
            return None

        last_toh = self._last_toh
        max_gap = self._max_gap_us
        closed: Scan | None = None
        scan = self._scan
        if scan is not None and (mode != scan.return_mode or product != scan.product):
            closed = self._close(complete=False)  # the sensor was reconfigured
        missing = 0
        if last_toh is None:
            toh = toh_raw
        else:
            # ToH wraps every hour; keep it increasing: the hour nearest the last.
            step = (toh_raw - last_toh) % _HOUR_US
            if step > _HALF_HOUR_US:
                step -= _HOUR_US
            toh = last_toh + step
            if step == 0:
                stats.duplicates += 1
                return closed
            if step < 0 and step >= -max_gap:
                self._insert_late(payload, toh)
                return closed
            if abs(step) > max_gap:
                stats.time_jumps += 1
                closed = self._close(complete=False) or closed
            elif step > _LOSS_STEP_US[mode]:
                missing = round(step * 1000 / m.packet_period_ns(mode)) - 1
        scan = self._scan
        if scan is not None and toh - scan.toh[0] > max_gap:
            closed = self._close(complete=False) or closed  # no cut in sight: not spinning
            scan = None
        if scan is None:
            scan = self._scan = _ScanInProgress(self._next_starts_at_cut, mode, product, t_host)
            self._next_starts_at_cut = False
        if missing:
            scan.lost += missing
            stats.lost += missing
        self._last_toh = toh
        scan.payloads.append(payload)
        scan.toh.append(toh)
        scan.t_host_last = t_host

        coverage = (azimuth - self._cut) % 36000
        previous = scan.coverage
        scan.coverage = coverage
        if previous is not None and previous > 18000 and coverage < previous:
            done = self._close(complete=scan.started_at_cut)
            self._next_starts_at_cut = True
            return done
        return closed

    def flush(self) -> Scan | None:
        """Close the scan in progress (end of stream): it is partial."""
        return self._close(complete=False)

    def _supported(self, product: int, toh_raw: int) -> bool:
        if self._forced_model is not None or product in m.MODEL_BY_PRODUCT:
            return True
        if product != m.PRODUCT_HDL32E:
            return False
        if self._byte21_is_vlp16 is None:
            scan = self._scan
            if scan is None or scan.product != m.PRODUCT_HDL32E or not scan.toh:
                return True  # undecided: keep it until the next packet shows the timing
            step = (toh_raw - scan.toh[-1]) % _HOUR_US
            if m.looks_like_vlp16_timing(step):
                self._byte21_is_vlp16 = True
            elif not m.looks_like_hdl32e_timing(step):
                return True  # repeated, reordered or after a loss: says nothing yet, keep it
            else:
                self._byte21_is_vlp16 = False
                # An HDL-32E after all: what was kept on trust is not ours to decode.
                self.stats.unsupported_model += len(scan.payloads)
                self._scan = None
                self._last_toh = None
        return self._byte21_is_vlp16

    def _insert_late(self, payload: bytes, toh: int) -> None:
        """Put a packet that arrived after a newer one back in place, if its scan is open."""
        scan = self._scan
        if scan is None or toh < scan.toh[0]:
            self.stats.late += 1  # its scan was already closed
            return
        at = int(np.searchsorted(scan.toh, toh))
        if at < len(scan.toh) and scan.toh[at] == toh:
            self.stats.duplicates += 1
            return
        scan.payloads.insert(at, payload)
        scan.toh.insert(at, toh)
        self.stats.out_of_order += 1
        if scan.lost > 0:  # it was counted missing when the gap was seen
            scan.lost -= 1
            self.stats.lost -= 1

    def _optics(self, product: int) -> m.LaserModel:
        if self._forced_model is not None:
            return self._forced_model
        return m.MODEL_BY_PRODUCT.get(product, m.VLP16)

    def _close(self, complete: bool) -> Scan | None:
        scan, self._scan = self._scan, None
        if scan is None:
            return None
        if (
            scan.product == m.PRODUCT_HDL32E
            and self._forced_model is None
            and not self._byte21_is_vlp16
        ):
            self.stats.unsupported_model += len(scan.payloads)  # 0x21 timing never settled
            return None
        packets = view_packets(b"".join(scan.payloads))
        ok = blocks_intact(packets)  # the rest was checked in `push`
        malformed = len(ok) - int(np.count_nonzero(ok))
        if malformed == len(ok):
            self.stats.malformed += malformed
            return None
        # The hour comes from the host clock once per scan; within the scan the device
        # clock alone orders the packets, so a host clock step cannot bend a scan's times.
        t_first = resolve_hour_one(scan.toh[0] % _HOUR_US, scan.t_host_first)
        t_packet = np.asarray(scan.toh, dtype=np.int64)
        t_packet -= scan.toh[0]
        t_packet *= 1000
        t_packet += t_first
        if malformed:  # rare: skip the costly structured copy otherwise
            self.stats.malformed += malformed
            packets, t_packet = packets[ok], t_packet[ok]
        optics = self._optics(scan.product)
        points, duplicates = decode_counting_duplicates(packets, t_packet, optics)
        mode_name = m.RETURN_MODE_NAMES[scan.return_mode]
        dual = scan.return_mode == m.RETURN_DUAL
        if not dual and len(points) and not _firings_in_order(t_packet):
            # A packet stamped less than a packet period after the one before (a corrupt
            # timestamp: a VLP-16 sends one every 1.33 ms) would start its firings before
            # the last ones ended; the scan's times are held from running back.
            np.maximum.accumulate(points["t"], out=points["t"])
        self.stats.scans += 1
        self.stats.complete_scans += int(complete)
        self.stats.points += len(points) - duplicates
        self.stats.duplicate_returns += duplicates
        last_firing = m.packet_period_ns(scan.return_mode) - m.SEQUENCE_NS + 15 * m.LASER_SLOT_NS
        return Scan(
            points=points,
            t_start=int(t_packet[0]),
            t_end=int(t_packet[-1]) + last_firing,
            t_host=scan.t_host_last,
            complete=complete,
            packets=len(packets),
            lost_packets=scan.lost,
            model=optics.name,
            return_mode=mode_name,
        )
