"""`decode_packets` on batches of any size and from several threads at once.

The decoder keeps work memory per thread and reuses it up to a size; larger
batches get their own. Expected values come from decoding one packet at a time: a
packet's points depend on that packet alone.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from tests.conftest import VLP16_DIR
from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne import packet as p
from treetraits.drivers.velodyne.sources import open_source

CAPTURES = ["einride_vlp16_strongest_1000pkts.bin", "nebula_vlp16_dual_10hz.pcap"]


def real_packets(name: str) -> tuple[np.ndarray, np.ndarray]:
    source = open_source(VLP16_DIR / name)
    payloads = [packet.payload for packet in source if packet.is_data]
    source.close()
    packets = p.view_packets(b"".join(payloads))
    # Device time only, from an arbitrary hour.
    t_packet = 1_700_000_000_000_000_000 + packets["toh"].astype(np.int64) * 1000
    return packets, t_packet


def one_at_a_time(packets: np.ndarray, t_packet: np.ndarray) -> bytes:
    parts = [
        p.decode_packets(packets[i : i + 1], t_packet[i : i + 1], m.VLP16)
        for i in range(len(packets))
    ]
    return np.concatenate(parts).tobytes()


@pytest.mark.parametrize("name", CAPTURES)
def test_batches_of_any_size_decode_as_their_packets(name):
    packets, t_packet = real_packets(name)
    # The whole capture, then smaller batches reusing the memory it left.
    for count in (len(packets), 300, 7):
        decoded = p.decode_packets(packets[:count], t_packet[:count], m.VLP16)
        assert decoded.dtype == p.POINT_DTYPE
        assert decoded.tobytes() == one_at_a_time(packets[:count], t_packet[:count])


def test_work_memory_is_kept_up_to_its_cap_only():
    int64 = np.dtype(np.int64)
    small, smaller = p._work("test", 1000, int64), p._work("test", 10, int64)
    assert np.shares_memory(small, smaller)  # the same thread memory, reused
    assert smaller.dtype == int64 and len(smaller) == 10
    assert not np.shares_memory(small, p._work("other", 10, int64))  # one buffer a name
    beyond = p._work("test", p._SCRATCH_MAX_BYTES // 8 + 1, int64)
    assert not np.shares_memory(beyond, p._work("test", 10, int64))


def test_threads_decoding_at_once_get_their_own_points():
    batches = [real_packets(name) for name in CAPTURES]
    expected = [p.decode_packets(k[:200], t[:200], m.VLP16).tobytes() for k, t in batches]

    def decode(job: int) -> bytes:
        packets, t_packet = batches[job % 2]
        return p.decode_packets(packets[:200], t_packet[:200], m.VLP16).tobytes()

    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(decode, range(40)))
    assert results == [expected[job % 2] for job in range(40)]


@pytest.mark.parametrize("name", CAPTURES)
def test_duplicates_are_counted_as_flagged(name):
    packets, t_packet = real_packets(name)
    points, duplicates = p.decode_counting_duplicates(packets, t_packet, m.VLP16)
    assert points.tobytes() == p.decode_packets(packets, t_packet, m.VLP16).tobytes()
    assert duplicates == np.count_nonzero(points["duplicate"])
    assert (duplicates > 0) == (packets["return_mode"][0] == m.RETURN_DUAL)
