"""Pure, vectorised decoding of VLP-16 data packets (1206-byte payloads).

A batch of N packets is viewed in place as a structured array (`PACKET_DTYPE`), checked,
and turned into points with one pass of NumPy per field: no Python loop per packet or
per point. Conventions (ROS `lidar` frame, vertical offset applied, per-point time) are
documented in `docs/lidar.md`.
"""

from __future__ import annotations

import numpy as np

from drivers.records import POINT_DTYPE
from drivers.velodyne import models as m

BLOCK_DTYPE = np.dtype(
    [
        ("flag", "<u2"),
        ("azimuth", "<u2"),
        ("records", [("distance", "<u2"), ("reflectivity", "u1")], (m.RECORDS_PER_BLOCK,)),
    ]
)
PACKET_DTYPE = np.dtype(
    [
        ("blocks", BLOCK_DTYPE, (m.BLOCKS_PER_PACKET,)),
        ("toh", "<u4"),
        ("return_mode", "u1"),
        ("product", "u1"),
    ]
)
assert PACKET_DTYPE.itemsize == m.DATA_PACKET_SIZE

_RECORDS_PER_PACKET = m.BLOCKS_PER_PACKET * m.RECORDS_PER_BLOCK

# Per record j (0..31) of a block: firing sequence j // 16 and laser id j % 16.
_RECORD = np.arange(m.RECORDS_PER_BLOCK)
_LASER_OF_RECORD = _RECORD % m.LASERS
# Firing time of record j after the first firing of its block.
_T_IN_BLOCK_NS = (_RECORD // m.LASERS) * m.SEQUENCE_NS + _LASER_OF_RECORD * m.LASER_SLOT_NS
# The same as a fraction of the block, to interpolate the azimuth between blocks.
_FRACTION_OF_BLOCK = (_T_IN_BLOCK_NS / m.BLOCK_NS).astype(np.float32)


def view_packets(buffer: bytes | bytearray | memoryview | np.ndarray) -> np.ndarray:
    """View back-to-back 1206-byte payloads as a structured array, without copying."""
    return np.frombuffer(buffer, dtype=PACKET_DTYPE)


def valid_packets(packets: np.ndarray) -> np.ndarray:
    """Per packet: all 12 block flags are FF EE, azimuths in 0..36000 and a known
    return-mode byte. Packets failing any of these are malformed. (36000 is not in the
    manual, but 2014 VLP-16 firmware sends it for 0 at the wrap; it decodes as 0.)"""
    blocks = packets["blocks"]
    flags_ok = (blocks["flag"] == m.BLOCK_FLAG).all(axis=1)
    azimuth_ok = (blocks["azimuth"] <= 36000).all(axis=1)
    mode_ok = np.isin(packets["return_mode"], list(m.RETURN_MODE_NAMES))
    return flags_ok & azimuth_ok & mode_ok


def resolve_hour(toh_us: np.ndarray, t_ref_ns: np.ndarray) -> np.ndarray:
    """Absolute device time (ns since the epoch) of each packet's ToH.

    The packet counts microseconds past the hour; the hour comes from a reference clock
    (the host receive time). A result more than 30 min from the reference belongs to the
    neighbouring hour, so it is moved by one hour.
    """
    t_ref_ns = np.asarray(t_ref_ns, dtype=np.int64)
    hour_start = (t_ref_ns // m.HOUR_NS) * m.HOUR_NS
    t = hour_start + np.asarray(toh_us, dtype=np.int64) * 1000
    half_hour = m.HOUR_NS // 2
    t = np.where(t - t_ref_ns > half_hour, t - m.HOUR_NS, t)
    return np.where(t_ref_ns - t > half_hour, t + m.HOUR_NS, t)


def _rotation_rate(firing_azimuth: np.ndarray) -> np.ndarray:
    """Per packet: rotation in centidegrees per firing block, from the first to the last
    firing block of the packet (unwrapped across 0). One rate per packet averages out
    the 0.01 deg quantisation of each block's azimuth."""
    sweep = (firing_azimuth[:, -1] - firing_azimuth[:, 0]) % 36000
    return (sweep / (firing_azimuth.shape[1] - 1)).astype(np.float32)


def decode_packets(
    packets: np.ndarray, t_packet_ns: np.ndarray, optics: m.LaserModel
) -> np.ndarray:
    """Decode valid data packets of one return mode into points (`POINT_DTYPE`).

    `packets` is a `PACKET_DTYPE` array (see `view_packets`), already checked with
    `valid_packets`; `t_packet_ns` is each packet's absolute ToH (see `resolve_hour`).
    Records with distance 0 (no return) are skipped. Points come in packet, block,
    firing sequence, laser order.
    """
    n = len(packets)
    if n == 0:
        return np.empty(0, dtype=POINT_DTYPE)
    mode = int(packets["return_mode"][0])
    dual = mode == m.RETURN_DUAL
    # In dual mode blocks (0,1), (2,3)... are one firing: last return, then strongest.
    blocks_per_firing = 2 if dual else 1

    blocks = packets["blocks"]
    distance = blocks["records"]["distance"].reshape(-1)
    idx = np.flatnonzero(distance)
    block_idx = idx // m.RECORDS_PER_BLOCK  # global block index
    record = idx % m.RECORDS_PER_BLOCK
    laser = record % m.LASERS
    packet_idx = block_idx // m.BLOCKS_PER_PACKET
    block_in_packet = block_idx % m.BLOCKS_PER_PACKET
    firing_block_in_packet = block_in_packet // blocks_per_firing

    firing_azimuth = blocks["azimuth"][:, ::blocks_per_firing].astype(np.int32)
    rate = _rotation_rate(firing_azimuth)
    firing_block = packet_idx * (m.BLOCKS_PER_PACKET // blocks_per_firing) + firing_block_in_packet
    centideg = (
        firing_azimuth.reshape(-1)[firing_block] + rate[packet_idx] * _FRACTION_OF_BLOCK[record]
    )
    azimuth = np.deg2rad(np.fmod(centideg, 36000.0, dtype=np.float32) / np.float32(100.0))

    elevation = np.deg2rad(np.asarray(optics.elevation_deg, dtype=np.float64))
    cos_el = np.cos(elevation).astype(np.float32)[laser]
    sin_el = np.sin(elevation).astype(np.float32)[laser]
    offset = (np.asarray(optics.vertical_offset_mm, dtype=np.float32) / 1000)[laser]
    rng = distance[idx].astype(np.float32) * np.float32(m.DISTANCE_UNIT_M)
    horizontal = rng * cos_el

    out = np.empty(idx.size, dtype=POINT_DTYPE)
    out["x"] = horizontal * np.cos(azimuth)
    out["y"] = -horizontal * np.sin(azimuth)
    out["z"] = rng * sin_el + offset
    out["azimuth"] = azimuth
    out["t"] = (
        np.asarray(t_packet_ns, dtype=np.int64)[packet_idx]
        + firing_block_in_packet * m.BLOCK_NS
        + _T_IN_BLOCK_NS[record]
    )
    out["intensity"] = blocks["records"]["reflectivity"].reshape(-1)[idx]
    out["ring"] = optics.ring[laser]
    if dual:
        strongest = (block_in_packet & 1).astype(bool)
        out["return_type"] = np.where(strongest, m.RETURN_TYPE_STRONGEST, m.RETURN_TYPE_LAST)
        # The partner record in the even (last-return) block sits one block earlier.
        partner = np.where(strongest, idx - m.RECORDS_PER_BLOCK, idx)
        out["duplicate"] = strongest & (distance[partner] == distance[idx])
    else:
        last = mode == m.RETURN_LAST
        out["return_type"] = m.RETURN_TYPE_LAST if last else m.RETURN_TYPE_STRONGEST
        out["duplicate"] = 0
    return out
