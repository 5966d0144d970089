"""`decode_packets` on batches of any size and from several threads at once, and its
compiled kernels made ready before a scan needs them.

Expected values come from decoding one packet at a time: a packet's points depend on
that packet alone.
"""

from __future__ import annotations

import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR
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


_COMPILE_COUNT = """
import json, sys
from treetraits.drivers.velodyne import packet as p
from treetraits.drivers.velodyne.batcher import ScanBatcher
from treetraits.drivers.velodyne.sources import open_source

def counts():
    return [len(p._count_returns.signatures), len(p._fill_points.signatures)]

p.compile_kernels()
compiled = counts()
decoded = []
for path in sys.argv[1:]:
    source = open_source(path)
    batcher = ScanBatcher()
    scans = [batcher.push(packet.payload, packet.t_host) for packet in source if packet.is_data]
    source.close()
    decoded.append(any(scan is not None and len(scan.points) for scan in scans))
print(json.dumps({"compiled": compiled, "after": counts(), "decoded": decoded}))
"""


def test_compile_kernels_compiles_what_real_scans_use():
    """The service compiles the kernels before READY (`compile_kernels`); decoding real
    captures of both return modes afterwards must not need another compilation (numba
    compiles anew for every new combination of argument types and layouts). In a fresh
    interpreter, as the service starts: in the test process another module may already
    have compiled a signature of its own (seen on two pytest-xdist workers)."""
    paths = [str(VLP16_DIR / name) for name in CAPTURES]
    run = subprocess.run(
        [sys.executable, "-c", _COMPILE_COUNT, *paths],
        capture_output=True,
        text=True,
        timeout=600,
        check=True,
    )
    facts = json.loads(run.stdout.strip().splitlines()[-1])
    assert all(facts["decoded"])
    assert facts["after"] == facts["compiled"]
    assert facts["compiled"] == [1, 1]
