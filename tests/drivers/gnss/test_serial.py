"""The live serial source on a real pseudo-terminal: pyserial opens the pty's slave side
while the test writes a real log into the master, paced like a receiver.

Unplugging is closing the master (reads then fail with EIO, as on a vanished USB adapter).
A pty's path cannot come back, so recovery is tested through a symlink, the way a udev
rule's /dev/gnss works: the link is removed, then pointed at a new pty.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
import tty

import pytest

from tests.helpers.paths import FIXTURES
from treetraits.cli import main
from treetraits.drivers.gnss import LogSource, SerialSource, open_gnss_source
from treetraits.errors import SourceError

NMEA_DIR = FIXTURES / "nmea"


class Pty:
    """A pseudo-terminal pair; `path` is the slave's device path (Linux: /dev/pts/N)."""

    def __init__(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: bytes pass as they are
        self.path = os.ttyname(self.slave)

    def wait_until_opened(self, timeout: float = 5.0) -> None:
        """Until the source under test has the slave open too (this process is the only
        other holder). Probing with flock would race with pyserial's exclusive lock."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            holders = 0
            for fd in os.listdir("/proc/self/fd"):
                with contextlib.suppress(OSError):
                    holders += os.readlink(f"/proc/self/fd/{fd}") == self.path
            if holders > 1:
                time.sleep(0.1)  # pyserial flushes its input just after opening
                return
            time.sleep(0.01)
        raise AssertionError("the serial source never opened the pty")

    def write_paced(self, data: bytes, chunk: int = 48, pause: float = 0.001) -> None:
        for start in range(0, len(data), chunk):
            os.write(self.master, data[start : start + chunk])
            time.sleep(pause)

    def unplug(self) -> None:
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):
                os.close(fd)


@pytest.fixture
def pty_pair():
    pair = Pty()
    yield pair
    pair.unplug()


def read_n(source: SerialSource, count: int, timeout: float = 10.0) -> list:
    got = []
    deadline = time.monotonic() + timeout
    while len(got) < count and time.monotonic() < deadline:
        sentence = source.read(timeout=0.2)
        if sentence is not None:
            got.append(sentence)
    return got


def file_sentences(name: str) -> list:
    source = LogSource(NMEA_DIR / name)
    try:
        return list(source)
    finally:
        source.close()


@pytest.mark.parametrize("name", ["gp-320fw-2019-04-07-coldboot.nmea", "isync.nmea"])
def test_serial_yields_the_same_sentences_as_the_file(pty_pair, name):
    """The garbled logs (NULs, glued and cut sentences, a collision) through a real tty."""
    expected = file_sentences(name)
    source = open_gnss_source(pty_pair.path, baud=115200)
    assert isinstance(source, SerialSource) and source.is_live
    try:
        writer = threading.Thread(
            target=pty_pair.write_paced, args=((NMEA_DIR / name).read_bytes(),)
        )
        writer.start()
        got = read_n(source, len(expected))
        writer.join()
        assert [s.raw for s in got] == [s.raw for s in expected]
        assert [s.checksum_ok for s in got] == [s.checksum_ok for s in expected]
        times = [s.t_host for s in got]
        assert times == sorted(times) and len(set(times)) > 10  # many reads, in order
        assert abs(times[0] - time.time_ns()) < 60 * 10**9  # the host's realtime clock
        live = source.counters()
        log = LogSource(NMEA_DIR / name)
        list(log)
        log.close()
        for key in ("valid", "bad_checksum", "truncated", "unterminated", "garbage_bytes"):
            assert live[key] == log.counters()[key], key
        assert live["disconnects"] == 0
    finally:
        source.close()


def test_unplug_backoff_without_busy_loop_and_recovery(tmp_path):
    first = Pty()
    link = tmp_path / "gnss"
    link.symlink_to(first.path)
    source = open_gnss_source(link, baud=38400, reopen_min_s=0.02, reopen_max_s=0.25)
    received: list = []
    stop = threading.Event()

    def reader():
        while not stop.is_set():
            sentence = source.read(timeout=0.05)
            if sentence is not None:
                received.append(sentence)

    thread = threading.Thread(target=reader)
    thread.start()
    second = None
    try:
        lines = (NMEA_DIR / "mt3339.nmea").read_bytes().splitlines(keepends=True)
        first.write_paced(b"".join(lines[:10]))
        deadline = time.monotonic() + 5
        while len(received) < 10 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [s.raw for s in received] == lines[:10]

        # Unplug in the middle of a sentence: the fragment is counted, not returned.
        os.write(first.master, lines[10][:20])
        time.sleep(0.1)
        first.unplug()
        link.unlink()
        deadline = time.monotonic() + 5
        while source.stats.disconnects == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert source.stats.disconnects == 1 and not source.connected

        # The device stays away for a second: the reader sleeps between attempts.
        clock = time.pthread_getcpuclockid(thread.ident)
        cpu_before, attempts_before = time.clock_gettime(clock), source.stats.open_failures
        time.sleep(1.0)
        cpu = time.clock_gettime(clock) - cpu_before
        attempts = source.stats.open_failures - attempts_before
        assert cpu < 0.05, f"reader thread used {cpu:.3f} s of CPU in 1 s while unplugged"
        assert 2 <= attempts <= 15  # backoff from 0.02 s up to 0.25 s
        assert source.splitter.stats.truncated == 1

        # Plugged in again, as a new device behind the same path.
        second = Pty()
        link.symlink_to(second.path)
        second.wait_until_opened()
        assert source.stats.reconnects == 1 and source.connected
        second.write_paced(b"".join(lines[11:20]))
        deadline = time.monotonic() + 5
        while len(received) < 19 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert [s.raw for s in received] == lines[:10] + lines[11:20]
    finally:
        stop.set()
        thread.join(timeout=5)
        source.close()
        first.unplug()
        if second is not None:
            second.unplug()
    assert not thread.is_alive()


def test_close_from_another_thread_ends_iteration(pty_pair):
    source = open_gnss_source(f"serial://{pty_pair.path}?baud=57600")
    assert source.baud == 57600
    done = threading.Event()

    def consume():
        for _ in source:
            pass
        done.set()

    thread = threading.Thread(target=consume)
    thread.start()
    time.sleep(0.2)
    source.close()
    assert done.wait(2.0)
    thread.join()


def test_without_reconnect_iteration_ends_at_unplug(pty_pair):
    source = SerialSource(pty_pair.path, 9600, reconnect=False)
    os.write(pty_pair.master, b"$GPHDT,274.07,T*03\r\n$GPHDT,27")
    assert source.read(timeout=2).raw == b"$GPHDT,274.07,T*03\r\n"
    pty_pair.unplug()  # a hangup: what the kernel still held is gone with the device
    assert list(source) == []  # ends by itself
    assert source.closed and source.stats.disconnects == 1 and source.stats.reconnects == 0
    assert source.splitter.stats.truncated == 1  # the sentence cut by the unplug


def test_open_errors_are_clear(pty_pair, tmp_path):
    with pytest.raises(SourceError, match="no such file or device"):
        open_gnss_source("/dev/ttyNOSUCHDEVICE0")
    with pytest.raises(SourceError, match="unknown option"):
        open_gnss_source(f"serial://{pty_pair.path}?speed=9600")
    with pytest.raises(SourceError, match="baud must be an integer"):
        open_gnss_source(f"serial://{pty_pair.path}?baud=fast")
    with pytest.raises(SourceError, match="cannot open GNSS receiver"):
        open_gnss_source("serial:///dev/ttyNOSUCHDEVICE0")
    holder = open_gnss_source(pty_pair.path)
    try:
        with pytest.raises(SourceError, match="another program"):
            open_gnss_source(pty_pair.path)  # the port is opened exclusively
    finally:
        holder.close()
    with pytest.raises(SourceError, match="not a file nor a character device"):
        open_gnss_source(tmp_path)


def test_cli_info_on_a_live_port(pty_pair, capsys):
    name = "skytraq-PX1172RH_DS.nmea"
    data = (NMEA_DIR / name).read_bytes()

    def receiver():
        pty_pair.wait_until_opened()
        pty_pair.write_paced(data, chunk=256)

    thread = threading.Thread(target=receiver)
    thread.start()
    code = main(["nmea", "info", pty_pair.path, "--json", "--baud", "115200", "--seconds", "1.5"])
    thread.join()
    assert code == 0
    facts = json.loads(capsys.readouterr().out)
    expected = json.loads((NMEA_DIR / "expected_counts.json").read_text())["files"][name]
    assert facts["is_live"] is True and facts["source"].endswith("baud=115200")
    assert facts["valid_by_type"] == expected["valid_by_type"]
    assert facts["ths_with_value"] == 9 and facts["first_fix"]["quality"] == 5
    assert facts["disconnects"] == 0
