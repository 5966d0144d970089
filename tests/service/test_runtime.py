"""The service's parts in process: bounded queues (drop newest), health and the status
line, sd_notify over a real datagram socket, the run directory, and receive threads on
real loopback sockets and pseudo-terminals."""

from __future__ import annotations

import os
import socket
import struct
import threading
import time
from types import SimpleNamespace

import pytest

from tests.helpers.net import free_udp_port
from treetraits.drivers import recording as rec
from treetraits.drivers.velodyne.packet import lidar_publish_time
from treetraits.service.config import GnssConfig, LidarConfig, ServiceConfig
from treetraits.service.health import SensorState, assess, sensor_problem, status_line
from treetraits.service.notify import Notifier, watchdog_period_s
from treetraits.service.runtime import Service, new_run_dir
from treetraits.service.workers import (
    BoundedQueue,
    GnssWorker,
    LidarWorker,
    Message,
)

HOUR_NS = 3600 * 10**9


def message(t: int, topic: str = rec.LIDAR_PACKETS) -> Message:
    return Message(topic, b"x", t, t)


def wait_for(condition, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.02)
    return condition()


# --- queues ------------------------------------------------------------------------------


def test_a_full_queue_drops_the_newest_and_counts_it():
    wake = threading.Event()
    queue = BoundedQueue("lidar", 3, wake)
    assert [queue.put(message(t)) for t in range(5)] == [True, True, True, False, False]
    assert wake.is_set()
    assert (len(queue), queue.accepted, queue.dropped, queue.high_water) == (3, 3, 2, 3)
    assert [queue.pop().log_time for _ in range(3)] == [0, 1, 2]  # the oldest kept, in order
    assert queue.head_time() is None
    assert queue.put(message(9)) and queue.head_time() == 9


def test_the_loop_takes_the_oldest_head_first():
    wake = threading.Event()
    queues = {name: BoundedQueue(name, 10, wake) for name in ("lidar", "gnss", "wheels")}
    for name, times in (("lidar", [5, 6, 30]), ("gnss", [1, 20]), ("wheels", [7])):
        for t in times:
            queues[name].put(message(t))
    service = Service(ServiceConfig())
    service.workers = [SimpleNamespace(queue=q) for q in queues.values()]
    order = []
    while (m := service._next_message()) is not None:
        order.append(m.log_time)
    assert order == [1, 5, 6, 7, 20, 30]


# --- health ------------------------------------------------------------------------------


def test_silent_disconnected_and_ok_sensors():
    ok = SensorState("lidar", 1.0, started=0.0, last_seen=9.5)
    silent = SensorState("gnss", 3.0, started=0.0, last_seen=5.9)
    never = SensorState("camera", 2.0, started=7.0)
    gone = SensorState("wheels", 2.0, 0.0, 9.9, connected=False, detail="reopening /dev/jackal")
    assert sensor_problem(ok, 10.0) == ("ok", None)
    assert sensor_problem(silent, 10.0) == ("silent", "gnss silent 4.1 s")
    assert sensor_problem(never, 10.0) == ("silent", "camera silent 3.0 s, nothing received yet")
    assert sensor_problem(gone, 10.0) == (
        "disconnected",
        "wheels disconnected: reopening /dev/jackal",
    )
    health = assess([ok, silent, never, gone], 10.0, extra=["disk full: /x"])
    assert health.states == {
        "lidar": "ok",
        "gnss": "silent",
        "camera": "silent",
        "wheels": "disconnected",
    }
    line = status_line(health, {"scans": 120, "trees": 6})
    assert line.startswith("DEGRADED gnss silent 4.1 s; camera silent 3.0 s")
    assert line.endswith(
        "disk full: /x | scans=120 trees=6 lidar=ok gnss=silent camera=silent wheels=disconnected"
    )
    assert status_line(assess([ok], 10.0), {"scans": 1}) == "OK scans=1 lidar=ok"


def test_a_status_is_always_one_line():
    health = assess([SensorState("gnss", 1.0, 0.0, connected=False, detail="a\nb")], 5.0)
    assert "\n" not in status_line(health, {})


# --- sd_notify ---------------------------------------------------------------------------


@pytest.fixture
def notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(2.0)
    yield path, sock
    sock.close()


def test_notifier_sends_ready_status_watchdog_and_stopping(notify_socket, monkeypatch):
    path, sock = notify_socket
    now = [100.0]
    monkeypatch.setenv("NOTIFY_SOCKET", str(path))  # systemd-python reads the process's
    monkeypatch.setenv("WATCHDOG_USEC", "4000000")
    notifier = Notifier(clock=lambda: now[0])
    assert notifier.watchdog_interval_s == 2.0  # half the period systemd asked for
    notifier.ready("OK scans=0")
    assert sock.recv(4096) == b"READY=1\nSTATUS=OK scans=0"
    assert notifier.watchdog(progressed=True)
    assert sock.recv(4096) == b"WATCHDOG=1"
    now[0] += 1.0
    assert not notifier.watchdog(progressed=True)  # not due yet
    now[0] += 1.5
    assert not notifier.watchdog(progressed=False)  # due, but the loop made no progress
    assert notifier.watchdog(progressed=True)
    assert sock.recv(4096) == b"WATCHDOG=1"
    notifier.status("DEGRADED gnss silent 4.1 s")
    assert sock.recv(4096) == b"STATUS=DEGRADED gnss silent 4.1 s"
    notifier.stopping("OK")
    assert sock.recv(4096) == b"STOPPING=1\nSTATUS=OK"
    assert notifier.pings == 2


def test_notifier_without_systemd_is_silent_and_a_bad_socket_is_not_fatal(tmp_path, monkeypatch):
    monkeypatch.delenv("NOTIFY_SOCKET", raising=False)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    quiet = Notifier()
    assert not quiet.enabled and quiet.watchdog_interval_s is None
    quiet.ready("OK")
    assert not quiet.watchdog(progressed=True)
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "nobody"))
    broken = Notifier()
    assert broken.enabled
    broken.ready("OK")  # ConnectionRefused / FileNotFound: logged once, not raised
    broken.status("OK")


def test_watchdog_period_only_for_this_process():
    assert watchdog_period_s({"WATCHDOG_USEC": "10000000"}, 42) == 10.0
    assert watchdog_period_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "42"}, 42) == 10.0
    assert watchdog_period_s({"WATCHDOG_USEC": "10000000", "WATCHDOG_PID": "7"}, 42) is None
    assert watchdog_period_s({"WATCHDOG_USEC": "soon"}, 42) is None
    assert watchdog_period_s({}, 42) is None


# --- run directory -----------------------------------------------------------------------


def test_each_start_gets_a_run_directory_and_latest_follows(tmp_path):
    first = new_run_dir(tmp_path, "20261123T161800Z")
    assert first == tmp_path / "runs" / "20261123T161800Z" and first.is_dir()
    assert (tmp_path / "runs" / "latest").resolve() == first
    again = new_run_dir(tmp_path, "20261123T161800Z")  # a restart within the same second
    assert again.name == "20261123T161800Z-2"
    assert os.readlink(tmp_path / "runs" / "latest") == "20261123T161800Z-2"
    assert sorted(p.name for p in (tmp_path / "runs").iterdir()) == [
        "20261123T161800Z",
        "20261123T161800Z-2",
        "latest",
    ]


# --- receive threads on real interfaces --------------------------------------------------


def data_packet(toh_us: int) -> bytes:
    return bytes(1200) + struct.pack("<I", toh_us) + b"\x37\x22"


def test_lidar_publish_time_takes_the_hour_from_the_host_clock():
    hour = 490_000 * HOUR_NS
    t_host = hour + 10 * 10**9
    assert lidar_publish_time(data_packet(9_990_000), t_host) == hour + 9_990_000_000
    # ToH just before the hour, received just after it: the previous hour.
    assert lidar_publish_time(data_packet(3_599_999_000), hour + 5_000_000) == hour - 1_000_000
    assert lidar_publish_time(b"short", t_host) == t_host


def lidar_worker(capacity: int, sensor_ip: str = "") -> LidarWorker:
    cfg = LidarConfig(
        bind="127.0.0.1", data_port=free_udp_port(), telemetry_port=0, sensor_ip=sensor_ip
    )
    worker = LidarWorker(cfg, BoundedQueue("lidar", capacity, threading.Event()))
    worker.open(retry=False)
    worker.start()
    return worker


def test_a_packet_flood_stays_within_the_queue_bound():
    worker = lidar_worker(capacity=50)
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            for i in range(400):
                sender.sendto(data_packet(i), ("127.0.0.1", worker.cfg.data_port))
                if i % 50 == 49:
                    time.sleep(0.01)  # let the receiver keep up with the kernel buffer
        assert wait_for(lambda: worker.queue.accepted + worker.queue.dropped >= 400 - 50)
        assert len(worker.queue) == 50 and worker.queue.high_water == 50
        assert worker.queue.dropped > 0
        # What was kept is the oldest, in order: the newest were dropped.
        kept = [worker.queue.pop().data[1200:1204] for _ in range(50)]
        assert kept == [struct.pack("<I", i) for i in range(50)]
        assert worker.state().connected and worker.last_seen is not None
    finally:
        worker.stop()
        worker.join(2.0)


def test_packets_from_another_host_are_dropped_and_counted():
    worker = lidar_worker(capacity=100, sensor_ip="127.0.0.2")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sender:
            sender.bind(("127.0.0.1", 0))  # not the sensor
            for i in range(30):
                sender.sendto(data_packet(i), ("127.0.0.1", worker.cfg.data_port))
        assert wait_for(lambda: worker.counters()["foreign"] == 30)
        assert len(worker.queue) == 0 and worker.items == 0 and worker.last_seen is None
    finally:
        worker.stop()
        worker.join(2.0)


def test_gnss_on_a_pty_then_the_pty_closed_is_reported_disconnected():
    master, slave = os.openpty()
    device = os.ttyname(slave)
    worker = GnssWorker(
        GnssConfig(port=device, baudrate=115200, silence_s=5.0),
        BoundedQueue("gnss", 10, threading.Event()),
    )
    worker.open()
    worker.start()
    try:
        sentence = b"$GPGGA,161800.00,3357.71,N,11721.42,W,4,12,0.8,300.0,M,-32.0,M,,*4B\r\n"
        os.write(master, sentence)
        assert wait_for(lambda: len(worker.queue) == 1)
        got = worker.queue.pop()
        assert (got.topic, got.data) == (rec.GNSS_NMEA, sentence)
        assert abs(got.log_time - time.time_ns()) < 5 * 10**9
        assert worker.state().connected
        os.close(slave)
        os.close(master)  # the receiver goes away: reads fail, the node vanishes
        assert wait_for(lambda: not worker.state().connected)
        assert worker.state().detail.startswith(f"reopening {device}")
    finally:
        worker.stop()
        worker.join(2.0)


def test_silence_counts_from_when_the_device_is_first_read():
    # The service opens its devices, then loads the pipeline (1-2 s on a loaded machine),
    # then starts reading: a sensor is not silent for that time (READY said DEGRADED).
    cfg = LidarConfig(bind="127.0.0.1", data_port=free_udp_port(), telemetry_port=0, silence_s=0.3)
    worker = LidarWorker(cfg, BoundedQueue("lidar", 10, threading.Event()))
    worker.open(retry=False)
    try:
        time.sleep(0.5)  # longer than silence_s between open and start
        worker.start()
        assert sensor_problem(worker.state(), time.monotonic()) == ("ok", None)
        time.sleep(0.5)  # and silent once nothing came for silence_s of reading
        assert sensor_problem(worker.state(), time.monotonic())[0] == "silent"
    finally:
        worker.stop()
        worker.join(2.0)
