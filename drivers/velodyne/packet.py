"""Pure decoding of VLP-16 data packets (1206-byte payloads).

A batch of N packets is viewed in place as a structured array (`PACKET_DTYPE`), checked
by NumPy, and turned into points by two compiled passes over its bytes (`treetraits.jit`)
and NumPy's trigonometry: no Python loop per packet or per point. The points depend on
the packets alone. Conventions (ROS `lidar` frame, vertical offset
applied, per-point time) are documented in `docs/lidar.md`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from treetraits.drivers.records import POINT_DTYPE
from treetraits.drivers.velodyne import models as m
from treetraits.jit import kernel, warm_up

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

# Per record j (0..31) of a block: firing sequence j // 16 and laser id j % 16.
_RECORD = np.arange(m.RECORDS_PER_BLOCK)
_LASER_OF_RECORD = _RECORD % m.LASERS
# Firing time of record j after the first firing of its block.
_T_IN_BLOCK_NS = (_RECORD // m.LASERS) * m.SEQUENCE_NS + _LASER_OF_RECORD * m.LASER_SLOT_NS
# A point seen as 7 four-byte words, so that the kernel writes its fields through two
# (points, 7) C-ordered views (float32 and uint32) whatever the number of points (numba
# compiles anew for each array layout, and views of one field are strided or, for one
# point, contiguous). Word 6 holds the four one-byte fields that end a point.
_WORDS = POINT_DTYPE.itemsize // 4
_Z, _AZIMUTH, _T_LOW, _T_HIGH, _TAIL = 2, 3, 4, 5, 6
assert [POINT_DTYPE.fields[f][1] for f in ("z", "azimuth", "t", "intensity", "duplicate")] == [
    4 * _Z,
    4 * _AZIMUTH,
    4 * _T_LOW,
    4 * _TAIL,
    4 * _TAIL + 3,
] and POINT_DTYPE.itemsize == 4 * _WORDS


@dataclass(frozen=True, eq=False)
class _RecordTables:
    """What a record's place in the packet says about its point, whatever the packet
    holds: terms of the block b (0..11) and of the record j (0..31) in it."""

    block_t_offset_ns: np.ndarray  # (12,) int64: the block's first firing after the ToH
    t_in_block_ns: np.ndarray  # (32,) int64: firing time after the block's first firing
    # (4, 32) float32, rows: that time in firing blocks (to interpolate the azimuth), the
    # elevation's cosine and sine, the vertical offset (m)
    laser: np.ndarray
    tail: np.ndarray  # (12, 32) "<u4": ring and return_type in their bytes of the tail word

    def kernel_args(self) -> tuple[np.ndarray, ...]:
        """The tables in `_fill_points`' order (not `astuple`: it deep-copies arrays)."""
        return self.block_t_offset_ns, self.t_in_block_ns, self.laser, self.tail


@lru_cache(maxsize=16)
def _record_tables(dual: bool, last_return: bool, optics: m.LaserModel) -> _RecordTables:
    block = np.arange(m.BLOCKS_PER_PACKET)[:, None]
    # In dual mode blocks (0,1), (2,3)... are one firing: last return, then strongest.
    firing_block = block // 2 if dual else block
    elevation = np.deg2rad(np.asarray(optics.elevation_deg, dtype=np.float64))[_LASER_OF_RECORD]
    if dual:
        return_type = np.where(block % 2 == 1, m.RETURN_TYPE_STRONGEST, m.RETURN_TYPE_LAST)
    else:
        return_type = m.RETURN_TYPE_LAST if last_return else m.RETURN_TYPE_STRONGEST
    ring = optics.ring[_LASER_OF_RECORD].astype(np.uint32)
    tail = (ring << 8) | (np.asarray(return_type, dtype=np.uint32) << 16)
    laser = np.stack(
        [
            _T_IN_BLOCK_NS / m.BLOCK_NS,
            np.cos(elevation),
            np.sin(elevation),
            (np.asarray(optics.vertical_offset_mm) / 1000)[_LASER_OF_RECORD],
        ]
    ).astype(np.float32)
    return _RecordTables(
        block_t_offset_ns=(firing_block[:, 0] * m.BLOCK_NS).astype(np.int64),
        t_in_block_ns=_T_IN_BLOCK_NS.astype(np.int64),
        laser=laser,
        tail=np.broadcast_to(tail, (m.BLOCKS_PER_PACKET, m.RECORDS_PER_BLOCK)).astype(
            "<u4",
            order="C",  # one layout (and one compiled kernel) whatever the mode
        ),
    )


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
    mode = packets["return_mode"]
    mode_ok = (mode >= min(m.RETURN_MODE_NAMES)) & (mode <= max(m.RETURN_MODE_NAMES))
    return flags_ok & azimuth_ok & mode_ok


def blocks_intact(packets: np.ndarray) -> np.ndarray:
    """Per packet: all 12 block flags are FF EE and all azimuths in 0..36000 (the part of
    `valid_packets` that the batcher's per-packet check of the header, the first and
    the last block's flags leaves)."""
    blocks = packets["blocks"]
    flag, azimuth = blocks["flag"], blocks["azimuth"]
    if (flag == m.BLOCK_FLAG).all() and azimuth.max(initial=0) <= 36000:  # the usual case
        return np.ones(len(packets), dtype=bool)
    return (flag == m.BLOCK_FLAG).all(axis=1) & (azimuth <= 36000).all(axis=1)


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


_INT64_SAFE = 2**62  # far enough from int64's limits that NumPy's arithmetic cannot wrap


def resolve_hour_one(toh_us: int, t_ref_ns: int) -> int:
    """`resolve_hour` of one ToH, in Python integers: the same result without the cost of
    NumPy calls on one-element arrays (the batcher needs it once per scan)."""
    if not (isinstance(t_ref_ns, int) and -_INT64_SAFE < t_ref_ns < _INT64_SAFE):
        return int(resolve_hour(np.array([toh_us]), np.array([t_ref_ns]))[0])
    t = t_ref_ns // m.HOUR_NS * m.HOUR_NS + toh_us * 1000
    if t - t_ref_ns > m.HOUR_NS // 2:
        return t - m.HOUR_NS
    if t_ref_ns - t > m.HOUR_NS // 2:
        return t + m.HOUR_NS
    return t


def lidar_publish_time(payload: bytes, t_host: int) -> int:
    """The recording's `publish_time` of a LiDAR payload: its microseconds past the hour
    (ToH) with the hour from `t_host` (docs/architecture.md, recording format v1)."""
    if len(payload) == m.DATA_PACKET_SIZE:
        offset = 1200
    elif len(payload) == m.POSITION_PACKET_SIZE:
        offset = 198
    else:
        return t_host
    toh_us = int.from_bytes(payload[offset : offset + 4], "little")
    return resolve_hour_one(toh_us, int(t_host))  # once per packet: no NumPy calls


# The kernels' constants (numba freezes module globals when it compiles).
_BLOCK_BYTES = 100  # flag (2), azimuth (2), 32 records of distance (2) and reflectivity (1)
_DISTANCE_UNIT = np.float32(m.DISTANCE_UNIT_M)
_FULL_TURN = np.float32(36000)  # centidegrees
_TO_RADIANS = np.float32(np.pi / 18000)


@kernel
def _count_returns(raw: np.ndarray) -> int:
    """Records with a return (distance not 0) in (packets, 1206) payload bytes."""
    count = 0
    for k in range(raw.shape[0]):
        for first in range(4, 1200, _BLOCK_BYTES):  # a block's records after its flag, azimuth
            for o in range(first, first + 96, 3):
                if raw[k, o] | raw[k, o + 1]:
                    count += 1
    return count


@kernel
def _fill_points(raw, t_packet, dual, block_t_offset, t_in_block, laser, tail, floats, words,
                 horizontal, azimuth):  # fmt: skip
    """One pass over the records of (packets, 1206) payload bytes, in packet, block,
    record order, skipping distance 0: each point's time, z, azimuth (radians) and tail
    word into its fields (`floats` and `words`: the points as (points, 7) words), its
    horizontal range and azimuth again into the contiguous `horizontal` and `azimuth`
    for the trigonometry NumPy does after. The arithmetic is in float32, as
    the fields are. Returns how many points are flagged duplicate."""
    firings = 6 if dual else 12  # firing blocks a packet: in dual, pairs of blocks
    last = 10 if dual else 11  # the last firing block's first block
    fraction, cos_elevation, sin_elevation, z_offset = laser[0], laser[1], laser[2], laser[3]
    point = 0
    duplicates = 0
    for k in range(raw.shape[0]):
        first_azimuth = np.int32(raw[k, 2]) | (np.int32(raw[k, 3]) << 8)
        last_azimuth = np.int32(raw[k, _BLOCK_BYTES * last + 2]) | (
            np.int32(raw[k, _BLOCK_BYTES * last + 3]) << 8
        )
        # Centidegrees per firing block, from the first to the last (unwrapped across 0).
        rate = np.float32(((last_azimuth - first_azimuth) % 36000) / (firings - 1))
        for b in range(12):
            offset = _BLOCK_BYTES * b
            block_azimuth = np.float32(
                np.int32(raw[k, offset + 2]) | (np.int32(raw[k, offset + 3]) << 8)
            )
            t_block = t_packet[k] + block_t_offset[b]
            strongest_of_pair = dual and b % 2 == 1
            for j in range(32):
                o = offset + 4 + 3 * j
                distance = np.int32(raw[k, o]) | (np.int32(raw[k, o + 1]) << 8)
                if distance == 0:
                    continue
                word = tail[b, j] | np.uint32(raw[k, o + 2])
                if strongest_of_pair:
                    # A single echo is reported by both blocks of the pair: flag the repeat.
                    paired = np.int32(raw[k, o - _BLOCK_BYTES]) | (
                        np.int32(raw[k, o - _BLOCK_BYTES + 1]) << 8
                    )
                    if distance == paired:
                        word |= np.uint32(1 << 24)
                        duplicates += 1
                words[point, _TAIL] = word
                t = t_block + t_in_block[j]
                words[point, _T_LOW] = np.uint32(t & 0xFFFFFFFF)  # little-endian int64
                words[point, _T_HIGH] = np.uint32((t >> 32) & 0xFFFFFFFF)
                rng = np.float32(distance) * _DISTANCE_UNIT
                horizontal[point] = rng * cos_elevation[j]
                floats[point, _Z] = rng * sin_elevation[j] + z_offset[j]
                centidegrees = rate * fraction[j] + block_azimuth
                if centidegrees >= _FULL_TURN:
                    centidegrees -= _FULL_TURN
                radians = centidegrees * _TO_RADIANS
                floats[point, _AZIMUTH] = radians
                azimuth[point] = radians
                point += 1
    return duplicates


def decode_packets(
    packets: np.ndarray, t_packet_ns: np.ndarray, optics: m.LaserModel
) -> np.ndarray:
    """Decode valid data packets of one return mode into points (`POINT_DTYPE`).

    `packets` is a `PACKET_DTYPE` array (see `view_packets`), already checked with
    `valid_packets`; `t_packet_ns` is each packet's absolute ToH (see `resolve_hour`).
    Records with distance 0 (no return) are skipped. Points come in packet, block,
    firing sequence, laser order.
    """
    return decode_counting_duplicates(packets, t_packet_ns, optics)[0]


def decode_counting_duplicates(
    packets: np.ndarray, t_packet_ns: np.ndarray, optics: m.LaserModel
) -> tuple[np.ndarray, int]:
    """`decode_packets`, and how many of the points are flagged `duplicate`.

    Two compiled passes over the payload bytes: one counts the records with a return, the
    other writes each point's fields but x and y in place. The azimuth's cosine and
    sine are NumPy's, on the contiguous azimuths the second pass leaves.
    """
    if len(packets) == 0:
        return np.empty(0, dtype=POINT_DTYPE), 0
    mode = int(packets["return_mode"][0])
    dual = mode == m.RETURN_DUAL
    raw = np.ascontiguousarray(packets).view(np.uint8).reshape(len(packets), m.DATA_PACKET_SIZE)
    count = _count_returns(raw)
    points = np.empty(count, dtype=POINT_DTYPE)
    if count == 0:  # (empty fields would also be typed, and compiled for, anew)
        return points, 0
    horizontal = np.empty(count, dtype=np.float32)
    azimuth = np.empty(count, dtype=np.float32)
    duplicates = _fill_points(
        raw,
        np.ascontiguousarray(t_packet_ns, dtype=np.int64),
        dual,
        *_record_tables(dual, mode == m.RETURN_LAST, optics).kernel_args(),
        points.view(np.float32).reshape(count, _WORDS),
        points.view(np.uint32).reshape(count, _WORDS),
        horizontal,
        azimuth,
    )
    trig = np.cos(azimuth)
    np.multiply(horizontal, trig, out=points["x"])
    np.multiply(np.negative(horizontal, out=horizontal), np.sin(azimuth, out=trig), out=points["y"])
    return points, int(duplicates)


@warm_up
def compile_kernels() -> None:
    """The decoding kernels compiled for the argument types a scan gives them
    (read-only packet bytes, as received), by decoding two packets of returns."""
    packets = np.zeros(2, dtype=PACKET_DTYPE)
    packets["blocks"]["flag"] = m.BLOCK_FLAG
    packets["blocks"]["records"]["distance"] = 1
    packets["return_mode"] = m.RETURN_STRONGEST
    decode_packets(view_packets(packets.tobytes()), np.zeros(2, dtype=np.int64), m.VLP16)
