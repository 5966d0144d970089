"""The live UDP source over real loopback sockets, fed by replaying a real capture.

A sender thread replays veloview_vlp16_20hz_strongest.pcap (1902 data and 367 position
packets over 2.5 s) to the source's ephemeral ports, paced by the capture's own timestamps.
The scans received must equal the scans decoded from the file, except for the per-point
times, which come from the host clock on receipt.
"""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from tests.helpers.captures import VLP16_DIR, decode_file, reference
from treetraits.drivers.records import Scan
from treetraits.drivers.velodyne.reader import LidarReader
from treetraits.drivers.velodyne.sources import DEFAULT_RCVBUF, LidarPacket, UdpSource, open_source
from treetraits.errors import SourceError

CAPTURE = "veloview_vlp16_20hz_strongest.pcap"
# Everything a point carries that does not depend on the receive time.
CLOCK_FREE_FIELDS = ["x", "y", "z", "azimuth", "intensity", "ring", "return_type", "duplicate"]


@pytest.fixture(scope="module")
def veloview() -> tuple[list[LidarPacket], list[Scan]]:
    """The capture's packets (with their pcap times) and its scans, decoded from the file."""
    source = open_source(VLP16_DIR / CAPTURE)
    packets = list(source)
    source.close()
    raw = reference(CAPTURE)["raw"]
    assert sum(p.is_data for p in packets) == raw["data_packets"] == 1902
    assert sum(not p.is_data for p in packets) == raw["position_packets"] == 367
    scans, _ = decode_file(VLP16_DIR / CAPTURE)
    return packets, scans


def replay(packets, data_port, telemetry_port=None, speed=1.0, sender_ip="127.0.0.1"):
    """Send each payload to its port from `sender_ip`, at `speed` x the recorded rate."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        tx.bind((sender_ip, 0))
        start, first = time.monotonic(), packets[0].t_host
        for packet in packets:
            delay = start + (packet.t_host - first) / 1e9 / speed - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            port = data_port if packet.is_data else telemetry_port
            if port is not None:
                tx.sendto(packet.payload, ("127.0.0.1", port))


def start_replay(*args, **kwargs) -> threading.Thread:
    sender = threading.Thread(target=replay, args=args, kwargs=kwargs, daemon=True)
    sender.start()
    return sender


def assert_same_scans_but_times(received: list[Scan], expected: list[Scan]) -> None:
    assert len(received) == len(expected)
    for i, (got, want) in enumerate(zip(received, expected, strict=True)):
        assert (got.packets, got.lost_packets, got.complete) == (
            want.packets,
            want.lost_packets,
            want.complete,
        ), f"scan {i}"
        assert (got.model, got.return_mode) == (want.model, want.return_mode)
        assert len(got.points) == len(want.points), f"scan {i}"
        for field in CLOCK_FREE_FIELDS:
            np.testing.assert_array_equal(
                got.points[field], want.points[field], err_msg=f"scan {i}, {field}"
            )


def close_when_quiet(source: UdpSource, sender: threading.Thread, quiet_s=0.3) -> None:
    """Once the sender is done and no packet arrived for `quiet_s`, close the source."""
    sender.join()
    seen = -1
    while seen != source.stats.packets + source.stats.malformed + source.stats.foreign:
        seen = source.stats.packets + source.stats.malformed + source.stats.foreign
        time.sleep(quiet_s)
    source.close()


@pytest.mark.slow
def test_real_rate_replay_through_lidar_reader(veloview):
    """Data and position packets at the recorded rate, iterated by `LidarReader` until
    another thread closes the source."""
    packets, expected = veloview
    source = UdpSource(host="127.0.0.1", port=0, telemetry_port=0)
    data_port, telemetry_port = source.ports
    reader = LidarReader(source)
    sender = start_replay(packets, data_port, telemetry_port, speed=1.0)
    closer = threading.Thread(target=close_when_quiet, args=(source, sender), daemon=True)
    closer.start()

    started, wall_start = time.monotonic(), time.time_ns()
    items = list(reader)  # ends when the closer closes the source
    closer.join(timeout=5)
    assert time.monotonic() - started >= 2.4  # really paced: the capture spans 2.52 s

    scans = [item for item in items if isinstance(item, Scan)]
    telemetry = [item for item in items if not isinstance(item, Scan)]
    assert source.stats.data_packets == 1902
    assert source.stats.position_packets == len(telemetry) == 367
    assert source.stats.malformed == source.stats.foreign == 0
    assert source.stats.kernel_drops == 0
    assert reader.batcher.stats.lost == 0
    assert reader.batcher.stats.malformed == reader.stats.telemetry_malformed == 0
    assert_same_scans_but_times(scans, expected)
    # Stamped with the host clock on receipt, not with the capture's 2014 times.
    assert all(wall_start <= scan.t_host <= time.time_ns() for scan in scans)


@pytest.mark.slow
def test_fast_replay_through_read(veloview):
    """Data packets at 4 x the recorded rate (about 3000 packets/s) into `read(timeout)`."""
    packets, expected = veloview
    data = [p for p in packets if p.is_data]
    source = open_source("udp://127.0.0.1:0?telemetry=0")
    assert isinstance(source, UdpSource)
    (data_port,) = source.ports
    reader = LidarReader(source)
    sender = start_replay(data, data_port, speed=4.0)

    received, scans = [], []
    while (packet := source.read(timeout=0.3)) is not None or sender.is_alive():
        if packet is not None:
            received.append(packet.payload)
            if (scan := reader.handle(packet)) is not None:
                scans.append(scan)
    if (last := reader.batcher.flush()) is not None:
        scans.append(last)
    source.close()

    assert received == [p.payload for p in data]
    assert source.stats.data_packets == 1902
    assert source.stats.kernel_drops == 0
    assert reader.batcher.stats.lost == 0
    assert_same_scans_but_times(scans, expected)


def test_sensor_ip_filter(veloview):
    """Linux routes all of 127/8 to loopback: senders bound to 127.0.0.2 and 127.0.0.3."""
    payloads = [p.payload for p in veloview[0][:40]]
    source = open_source("udp://127.0.0.1:0?telemetry=0&sensor=127.0.0.2")
    try:
        (port,) = source.ports
        for sender_ip, batch in (("127.0.0.3", payloads[:25]), ("127.0.0.2", payloads[25:])):
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
                tx.bind((sender_ip, 0))
                for payload in batch:
                    tx.sendto(payload, ("127.0.0.1", port))
        got = []
        while (packet := source.read(timeout=0.5)) is not None:
            got.append(packet.payload)
        assert got == payloads[25:]
        assert source.stats.foreign == 25
        assert source.stats.packets == 15
    finally:
        source.close()


def test_malformed_datagrams_are_counted_never_raised(veloview):
    payload = veloview[0][0].payload
    source = UdpSource(host="127.0.0.1", port=0, telemetry_port=None)
    try:
        (port,) = source.ports
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for length in (1, 1205, 1207, 511, 513, 4000):
                tx.sendto((payload * 4)[:length], ("127.0.0.1", port))
            tx.sendto(payload, ("127.0.0.1", port))
        packet = source.read(timeout=2.0)
        assert packet is not None and packet.payload == payload
        assert source.stats.malformed == 6
        assert source.stats.packets == 1
        assert source.read(timeout=0.1) is None
    finally:
        source.close()


@pytest.mark.realtime
def test_read_times_out_on_a_quiet_socket():
    source = UdpSource(host="127.0.0.1", port=0, telemetry_port=None)
    try:
        started = time.monotonic()
        assert source.read(timeout=0.2) is None
        assert 0.2 <= time.monotonic() - started < 0.6
    finally:
        source.close()


def test_close_from_another_thread_ends_iteration():
    source = UdpSource(host="127.0.0.1", port=0, telemetry_port=None)
    got: list[LidarPacket] = []
    iterating = threading.Thread(target=lambda: got.extend(source), daemon=True)
    iterating.start()
    time.sleep(0.1)
    closed_at = time.monotonic()
    source.close()
    iterating.join(timeout=2.0)
    assert not iterating.is_alive()
    assert time.monotonic() - closed_at < 1.0
    assert got == []
    assert source.read(timeout=1.0) is None  # a closed source returns at once


def test_close_while_another_thread_reads_never_raises():
    """`close()` can land between a reader's closed check and its wait in select."""
    errors: list[BaseException] = []
    for _ in range(30):
        source = UdpSource(host="127.0.0.1", port=0, telemetry_port=None)
        stop = threading.Event()

        def spin(source=source, stop=stop):
            try:
                while not stop.is_set():
                    source.read(timeout=0)
            except Exception as error:
                errors.append(error)

        spinner = threading.Thread(target=spin, daemon=True)
        spinner.start()
        time.sleep(0.005)
        source.close()
        stop.set()
        spinner.join(timeout=2.0)
    assert errors == []


def test_ipv6_loopback(veloview):
    payload = veloview[0][0].payload
    source = open_source("udp://[::1]:0?telemetry=0")
    try:
        (port,) = source.ports
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as tx:
            tx.sendto(payload, ("::1", port))
        packet = source.read(timeout=2.0)
        assert packet is not None and packet.payload == payload and packet.is_data
    finally:
        source.close()


def test_effective_rcvbuf_is_within_kernel_limits():
    rmem_default = int(Path("/proc/sys/net/core/rmem_default").read_text())
    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    source = UdpSource(host="127.0.0.1", port=0, telemetry_port=None)
    try:
        granted = source.effective_rcvbuf
    finally:
        source.close()
    assert rmem_default <= granted <= 2 * rmem_max
    # Linux grants twice the request, the request capped at rmem_max.
    assert granted == 2 * min(DEFAULT_RCVBUF, rmem_max)


def test_a_second_reader_on_the_same_port_is_refused():
    """No silent sharing: the second source on a port fails with a clear error."""
    first = UdpSource(host="127.0.0.1", port=0, telemetry_port=None)
    try:
        with pytest.raises(SourceError, match="bound to the port"):
            UdpSource(host="127.0.0.1", port=first.ports[0], telemetry_port=None)
    finally:
        first.close()


def test_a_packet_carries_its_arrival_time_not_the_read_time(veloview):
    """`t_host` is the kernel's receive stamp: a reader that gets round to a packet late
    (a busy process, a burst read) still places it when it arrived."""
    packets, _ = veloview
    source = UdpSource("127.0.0.1", 0, telemetry_port=None)
    try:
        assert source.kernel_timestamps
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            sent = []
            for packet in [p for p in packets if p.is_data][:10]:
                before = time.time_ns()
                tx.sendto(packet.payload, ("127.0.0.1", source.ports[0]))
                sent.append((before, time.time_ns(), packet.payload))
                time.sleep(0.002)
        time.sleep(0.2)
        first = source.read(timeout=1.0)
        read_at = time.time_ns()
        assert source.pending == 9  # the rest of the burst, read in the same wake-up
        received = [first] + [source.read(timeout=1.0) for _ in range(9)]
    finally:
        source.close()
    assert [p.payload for p in received] == [payload for _, _, payload in sent]
    for packet, (before, after, _) in zip(received, sent, strict=True):
        assert before <= packet.t_host <= after  # loopback: stamped within sendto()
    assert read_at - received[-1].t_host > 150_000_000  # read 0.2 s later
