"""Pure, vectorised decoding of VLP-16 data packets (1206-byte payloads).

A batch of N packets is viewed in place as a structured array (`PACKET_DTYPE`), checked,
and turned into points by NumPy, each field written once: no Python loop per packet or
per point. The points depend on the packets alone; each thread keeps its work memory
from one call to the next (`_work`). Conventions (ROS `lidar` frame, vertical offset
applied, per-point time) are documented in `docs/lidar.md`.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from treetraits.drivers.records import POINT_DTYPE
from treetraits.drivers.velodyne import models as m

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
# A record's index in a scan's (packet, block, record) order: the low 5 bits are j.
_RECORD_BITS = m.RECORDS_PER_BLOCK - 1
_RECORD_SHIFT = _RECORD_BITS.bit_length()  # index >> 5: the block, counted over the batch
assert m.RECORDS_PER_BLOCK & _RECORD_BITS == 0
# The four one-byte fields that end a point (intensity, ring, return_type, duplicate),
# seen as one little-endian word: one strided write per point instead of four.
_TAIL_VIEW = np.dtype({"names": ["tail"], "formats": ["<u4"], "offsets": [24], "itemsize": 28})
assert [POINT_DTYPE.fields[f][1] for f in ("intensity", "ring", "return_type", "duplicate")] == [
    24,
    25,
    26,
    27,
] and POINT_DTYPE.itemsize == _TAIL_VIEW.itemsize
# What a point takes from its block and from its record j, each gathered in one `take` of
# 16-byte items (a gather costs about the same for 4- or 16-byte items).
_BLOCK_TERMS = np.dtype([("azimuth", "<f4"), ("rate", "<f4"), ("t_ns", "<i8")])
_LASER_TERMS = np.dtype(
    [("fraction", "<f4"), ("cos_elevation", "<f4"), ("sin_elevation", "<f4"), ("z_m", "<f4")]
)
# A structured `take` is several times slower than one of plain items of the same size.
_ITEM16 = np.dtype("V16")
assert _BLOCK_TERMS.itemsize == _LASER_TERMS.itemsize == _ITEM16.itemsize


@dataclass(frozen=True, eq=False)
class _RecordTables:
    """What a record's place in the packet says about its point, whatever the packet
    holds: terms of the record j alone, looked up per point, and of the block, which
    broadcast over a batch of packets."""

    block_t_offset_ns: np.ndarray  # (12,): the block's first firing after the packet's ToH
    t_in_block_ns: np.ndarray  # (32,) int64: firing time after the block's first firing
    # (32,) `_LASER_TERMS`: that time in firing blocks (to interpolate the azimuth), the
    # elevation's cosine and sine, the vertical offset
    laser: np.ndarray
    laser_items: np.ndarray  # `laser` seen as plain 16-byte items, to gather
    tail: np.ndarray  # (12, 32) "<u4": ring and return_type in their bytes of the tail word


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
    laser = np.empty(m.RECORDS_PER_BLOCK, dtype=_LASER_TERMS)
    laser["fraction"] = _T_IN_BLOCK_NS / m.BLOCK_NS
    laser["cos_elevation"] = np.cos(elevation)
    laser["sin_elevation"] = np.sin(elevation)
    laser["z_m"] = (np.asarray(optics.vertical_offset_mm) / 1000)[_LASER_OF_RECORD]
    return _RecordTables(
        block_t_offset_ns=(firing_block[:, 0] * m.BLOCK_NS).astype(np.int64),
        t_in_block_ns=_T_IN_BLOCK_NS.astype(np.int64),
        laser=laser,
        laser_items=laser.view(_ITEM16),
        tail=np.broadcast_to(tail, (m.BLOCKS_PER_PACKET, m.RECORDS_PER_BLOCK)).astype("<u4"),
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


def azimuths_in_range(packets: np.ndarray) -> np.ndarray:
    """Per packet: all 12 block azimuths in 0..36000 (the part of `valid_packets` that a
    per-packet check of the flags and return mode leaves)."""
    azimuth = packets["blocks"]["azimuth"]
    if azimuth.max(initial=0) <= 36000:  # the usual case, in one reduction
        return np.ones(len(packets), dtype=bool)
    return (azimuth <= 36000).all(axis=1)


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
    return int(resolve_hour(np.array([toh_us]), np.array([t_host]))[0])


def _rotation_rate(azimuth: np.ndarray, dual: bool) -> np.ndarray:
    """Per packet: rotation in centidegrees per firing block, from the azimuth of its
    first to that of its last firing block (unwrapped across 0). One rate per packet
    averages out the 0.01 deg quantisation of each block's azimuth."""
    firings = m.BLOCKS_PER_PACKET // 2 if dual else m.BLOCKS_PER_PACKET
    last = m.BLOCKS_PER_PACKET - (2 if dual else 1)  # in dual return: block 10
    sweep = (azimuth[:, last].astype(np.int32) - azimuth[:, 0]) % 36000
    return (sweep / (firings - 1)).astype(np.float32)


class _Scratch(threading.local):
    """A thread's work memory, kept from one decode to the next: a buffer per name.
    A scan's temporaries are large (a dual-return scan's grids hold 58,000 records);
    fresh ones are faulted in page by page, and freed after every scan they often go
    back to the system to be faulted in again (bench/decode.py, dual return: about 56
    page faults a scan before every temporary had its buffer)."""

    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}


_SCRATCH = _Scratch()  # threads decode at once; calls within one never overlap
# A thread keeps buffers of at most this many bytes each (an int64 per record of 512
# packets, about 1.6 MB; a 5 Hz dual-return scan has 302 packets); larger get their own.
_SCRATCH_MAX_BYTES = 8 * 512 * m.BLOCKS_PER_PACKET * m.RECORDS_PER_BLOCK
_BOOL, _UINT16, _INT64, _FLOAT32 = (np.dtype(t) for t in (bool, np.uint16, np.int64, np.float32))
_WORD = np.dtype("<u4")


def _work(name: str, count: int, dtype: np.dtype) -> np.ndarray:
    """`count` uninitialised items of `dtype` from the thread's buffer `name` when they
    fit under its cap. Called a dozen times a scan: one dict look-up and a slice."""
    memory = _SCRATCH.buffers.get(name)
    if memory is None or memory.dtype is not dtype or len(memory) < count:
        if count * dtype.itemsize > _SCRATCH_MAX_BYTES:
            return np.empty(count, dtype=dtype)
        spare = count // 4  # scans differ by a packet or two
        memory = np.empty(min(count + spare, _SCRATCH_MAX_BYTES // dtype.itemsize), dtype)
        _SCRATCH.buffers[name] = memory
    return memory[:count]


def _block_terms(
    packets: np.ndarray, t_packet_ns: np.ndarray, dual: bool, tables: _RecordTables
) -> np.ndarray:
    """(packets x 12,) `_BLOCK_TERMS` as plain 16-byte items: each block's azimuth
    (centidegrees), its packet's rotation rate and the block's first firing time."""
    azimuth = packets["blocks"]["azimuth"]
    items = _work("block_terms", azimuth.size, _ITEM16)
    terms = items.view(_BLOCK_TERMS).reshape(azimuth.shape)
    terms["azimuth"] = azimuth  # uint16 to float32 is exact
    terms["rate"] = _rotation_rate(azimuth, dual)[:, None]
    t_packet = np.asarray(t_packet_ns, dtype=np.int64)[:, None]
    np.add(t_packet, tables.block_t_offset_ns, out=terms["t_ns"])
    return items


def _tail_grid(
    records: np.ndarray, distance: np.ndarray, dual: bool, tables: _RecordTables
) -> np.ndarray:
    """Tail words, flat, one per record: reflectivity, ring, return type and the
    duplicate flag. `distance` is the (packets, 12, 32) grid."""
    words = _work("tail", distance.size, _WORD)
    grid = words.reshape(distance.shape)
    grid[...] = tables.tail
    tail_bytes = words.view(np.uint8).reshape(*distance.shape, 4)
    tail_bytes[..., 0] = records["reflectivity"]
    if dual:
        # A single echo is reported by both blocks of the pair: flag the repeat.
        np.equal(distance[:, 1::2], distance[:, 0::2], out=tail_bytes[:, 1::2, :, 3].view(bool))
    return words


def _gather(name: str, items: np.ndarray, index: np.ndarray) -> np.ndarray:
    """`items[index]` (`items` flat) into the thread's buffer `name`."""
    out = _work(name, len(index), items.dtype)
    np.take(items, index, out=out, mode="clip")  # indices in range: no checking copy
    return out


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
    """`decode_packets`, and how many of the points are flagged `duplicate` (counted on
    the decoder's own contiguous copy: the points' flags are 28 bytes apart).

    The records with a return are found first; each point then gathers what it needs
    from its block and its record j (two 16-byte gathers) and from the distance and
    tail grids, and each field is written once into the output. The temporaries live
    in the thread's work memory.
    """
    if len(packets) == 0:
        return np.empty(0, dtype=POINT_DTYPE), 0
    mode = int(packets["return_mode"][0])
    dual = mode == m.RETURN_DUAL
    tables = _record_tables(dual, mode == m.RETURN_LAST, optics)
    records = packets["blocks"]["records"]
    distances = _work("distance", records.size, _UINT16)
    distance = distances.reshape(records.shape)
    np.copyto(distance, records["distance"])
    # A bool mask first: flatnonzero on the uint16 distances directly is 4x slower.
    has_return = _work("mask", distance.size, _BOOL).reshape(distance.shape)
    np.not_equal(distance, 0, out=has_return)
    index = np.flatnonzero(has_return)
    count = len(index)
    points = np.empty(count, dtype=POINT_DTYPE)

    where = _work("where", count, _INT64)
    block_terms = _block_terms(packets, t_packet_ns, dual, tables)
    block_of_point = np.right_shift(index, _RECORD_SHIFT, out=where)
    block = _gather("block", block_terms, block_of_point).view(_BLOCK_TERMS)
    record = np.bitwise_and(index, _RECORD_BITS, out=where)
    laser = _gather("laser", tables.laser_items, record).view(_LASER_TERMS)
    t = _gather("t", tables.t_in_block_ns, record)
    np.add(block["t_ns"], t, out=points["t"])
    tail = _gather("tail_point", _tail_grid(records, distance, dual, tables), index)
    points.view(_TAIL_VIEW)["tail"] = tail
    duplicates = 0
    if dual:  # only dual return repeats an echo; the flag is the word's top byte
        flagged = np.greater_equal(tail, 1 << 24, out=_work("flagged", count, _BOOL))
        duplicates = int(np.count_nonzero(flagged))

    rng = _work("range", count, _FLOAT32)
    np.multiply(_gather("distance_point", distances, index), np.float32(m.DISTANCE_UNIT_M), out=rng)
    horizontal = np.multiply(rng, laser["cos_elevation"], out=_work("horizontal", count, _FLOAT32))
    z = np.multiply(rng, laser["sin_elevation"], out=rng)
    np.add(z, laser["z_m"], out=points["z"])

    centideg = np.multiply(block["rate"], laser["fraction"], out=_work("azimuth", count, _FLOAT32))
    np.add(centideg, block["azimuth"], out=centideg)
    np.subtract(centideg, 36000, out=centideg, where=centideg >= 36000)
    azimuth = np.multiply(centideg, np.float32(np.pi / 18000), out=centideg)
    points["azimuth"] = azimuth
    trig = _work("trig", count, _FLOAT32)
    np.multiply(horizontal, np.cos(azimuth, out=trig), out=points["x"])
    np.multiply(np.negative(horizontal, out=horizontal), np.sin(azimuth, out=trig), out=points["y"])
    return points, duplicates
