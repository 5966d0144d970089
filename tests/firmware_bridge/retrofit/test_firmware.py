"""The reference firmware's portable core, built with the machine's `cc` and run on the host.

The simulator (firmware/host/sim_main.c) runs the same quadrature decoder, framing and
reporting schedule a board runs, fed with a scripted A/B waveform. Its output must be,
byte for byte, what the Python encoder builds from the counts the script implies, and the
Python reader must read it back exactly. Then it streams into a real pseudo-terminal that
the host opens with pyserial through `serial_link`: samples arrive with host times,
closing the pty is a disconnect (no busy loop, samples kept), and a new pty behind the
same path is picked up again.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
import threading
import time
import tty
from pathlib import Path

import pytest

from tests.helpers.paths import REPO
from treetraits.drivers.records import WheelSample
from treetraits.errors import SourceError
from treetraits.firmware_bridge.retrofit import protocol as p
from treetraits.firmware_bridge.retrofit.reader import BridgeDecoder, BridgeReader
from treetraits.firmware_bridge.retrofit.serial_link import (
    LinkEvent,
    RetrofitSource,
    SerialLink,
    open_bridge,
)

FIRMWARE = REPO / "firmware_bridge" / "firmware"
CORE = ["core/quadrature.c", "core/frame.c", "core/bridge.c"]
# As firmware/Makefile, plus undefined-behaviour checks that trap (no runtime library).
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-Wconversion", "-Wshadow"]
CFLAGS += ["-O1", "-fsanitize=undefined", "-fsanitize-undefined-trap-on-error"]

FREESTANDING = ["-std=c99", "-ffreestanding", "-Wall", "-Wextra", "-Werror", "-O2"]

FORWARD = [(0, 0), (1, 0), (1, 1), (0, 1)]  # A leads B
TICK_US = 10_000


@pytest.fixture(scope="module")
def sim(tmp_path_factory) -> Path:
    cc = shutil.which("cc")
    assert cc, "the C compiler `cc` is required (make setup installs gcc)"
    out = tmp_path_factory.mktemp("firmware") / "bridge_sim"
    sources = [str(FIRMWARE / s) for s in [*CORE, "host/sim_main.c"]]
    subprocess.run(
        [cc, *CFLAGS, "-I", str(FIRMWARE / "core"), *sources, "-o", str(out)],
        check=True,
        capture_output=True,
        timeout=120,
    )
    return out


class Waveform:
    """A script of pin levels and the counts it implies, tracked step by step."""

    def __init__(self):
        self.phase = [0, 0]  # index into FORWARD per side
        self.count = [0, 0]
        self.errors = [0, 0]
        self.events: dict[int, None] = {}
        self.lines = ["0 0 0 0 0"]  # initial levels
        self.history = [(0, (0, 0), (0, 0))]  # (t_us, counts, errors) after each line

    def step(self, t_us: int, side: int, kind: str) -> None:
        if kind == "fwd":
            self.phase[side] = (self.phase[side] + 1) % 4
            self.count[side] += 1
        elif kind == "back":
            self.phase[side] = (self.phase[side] - 1) % 4
            self.count[side] -= 1
        else:  # both pins flip at once: illegal, no count
            self.phase[side] = (self.phase[side] + 2) % 4
            self.errors[side] += 1
        la, lb = FORWARD[self.phase[0]]
        ra, rb = FORWARD[self.phase[1]]
        assert t_us >= self.history[-1][0]
        self.lines.append(f"{t_us} {la} {lb} {ra} {rb}")
        self.history.append((t_us, tuple(self.count), tuple(self.errors)))

    def at(self, t_us: int) -> tuple[tuple[int, int], tuple[int, int]]:
        """Counts and errors a frame stamped `t_us` reports: every line at or before it."""
        state = self.history[0]
        for entry in self.history:
            if entry[0] <= t_us:
                state = entry
        return state[1], state[2]

    @property
    def script(self) -> str:
        return "\n".join(["# t_us LA LB RA RB", *self.lines]) + "\n"


def scripted_waveform() -> Waveform:
    """Left: 40 forward, 15 back, an illegal jump at 250 ms, 8 forward. Right: 25 back,
    then 60 forward, then an illegal jump at 1.2 s."""
    steps = []
    steps += [(2_000 + 3_000 * k, 0, "fwd") for k in range(40)]
    steps += [(150_000 + 4_000 * k, 0, "back") for k in range(15)]
    steps += [(250_000, 0, "jump")]
    steps += [(300_000 + 5_000 * k, 0, "fwd") for k in range(8)]
    steps += [(1_000 + 7_000 * k, 1, "back") for k in range(25)]
    steps += [(400_000 + 2_500 * k, 1, "fwd") for k in range(60)]
    steps += [(1_200_000, 1, "jump")]
    wave = Waveform()
    for t_us, side, kind in sorted(steps, key=lambda s: s[0]):
        wave.step(t_us, side, kind)
    return wave


def expected_frames(
    wave: Waveform,
    end_us: int,
    tick_us: int = TICK_US,
    heartbeat_us: int = 1_000_000,
    sign: tuple[int, int] = (1, 1),
    sticky: int = 0,
    boot_id: int = 0,
    config: dict | None = None,
) -> bytes:
    """What the board must send, built with the Python encoder from the waveform's counts."""
    config = config or {"ticks_per_rev": 4096}
    frames, seq, seen_errors = [], 0, (0, 0)
    for t in range(0, end_us + 1, tick_us):
        counts, errors = wave.at(t)
        if t == 0:
            frames.append(p.encode_config_echo(seq, t, **config, boot_id=boot_id))
            seq += 1
        if t % heartbeat_us == 0:
            faults = sticky
            faults |= p.Fault.LEFT_GLITCH if errors[0] != seen_errors[0] else 0
            faults |= p.Fault.RIGHT_GLITCH if errors[1] != seen_errors[1] else 0
            frames.append(p.encode_heartbeat(seq, t, int(faults), boot_id=boot_id))
            seq, seen_errors = seq + 1, errors
        left, right = sign[0] * counts[0], sign[1] * counts[1]
        frames.append(p.encode_ticks(seq, t, left, right, *errors, boot_id=boot_id))
        seq += 1
    return b"".join(frames)


def run_sim(sim: Path, script: str, *args: str) -> bytes:
    done = subprocess.run(
        [str(sim), *args], input=script.encode(), capture_output=True, timeout=30, check=True
    )
    return done.stdout


# ---------------------------------------------------------------- the core, byte for byte


def test_core_is_freestanding(tmp_path):
    """The core needs no OS and no C library: it builds freestanding and every symbol it
    uses is its own (memcpy/memset allowed, which a freestanding compiler may emit)."""
    objects = []
    for source in CORE:
        obj = tmp_path / (Path(source).stem + ".o")
        subprocess.run(
            ["cc", *FREESTANDING, "-c", "-o", str(obj), str(FIRMWARE / source)],
            check=True,
            capture_output=True,
        )
        objects.append(str(obj))
    listing = subprocess.run(
        ["nm", "--format=posix", *objects], check=True, capture_output=True, text=True
    ).stdout.split("\n")
    symbols = [line.split() for line in listing if line and not line.endswith(":")]
    defined = {s[0] for s in symbols if len(s) > 1 and s[1] in "TtDdBbRr"}
    undefined = {s[0] for s in symbols if len(s) > 1 and s[1] == "U"}
    assert undefined - defined <= {"memcpy", "memset"}


def test_scripted_waveform_frames_are_byte_exact(sim):
    wave = scripted_waveform()
    out = run_sim(sim, wave.script, "--end-us", "2000000")
    assert out == expected_frames(wave, 2_000_000)


def test_scripted_waveform_reads_back_exactly(sim):
    wave = scripted_waveform()
    out = run_sim(sim, wave.script, "--end-us", "2000000")
    decoder = BridgeDecoder()
    items = decoder.push(out, t_host=1)
    decoder.flush()
    samples = [i for i in items if isinstance(i, WheelSample)]
    assert len(samples) == 201
    for k, sample in enumerate(samples):
        counts, _ = wave.at(k * TICK_US)
        assert sample.t_device_us == k * TICK_US
        assert (sample.left, sample.right) == counts
    # The waveform's totals: 40 - 15 + 8 left, -25 + 60 right, one illegal step each.
    assert (samples[-1].left, samples[-1].right) == (33, 35)
    assert decoder.reader.stats.ticks == 201
    heartbeats = [i for i in items if isinstance(i, p.Heartbeat)]
    assert [h.t_device_us for h in heartbeats] == [0, 1_000_000, 2_000_000]
    assert [h.fault_names for h in heartbeats] == [[], ["LEFT_GLITCH"], ["RIGHT_GLITCH"]]
    assert heartbeats[0].board_name == "host-sim" and heartbeats[0].firmware == "1.0.0"
    (config,) = [i for i in items if isinstance(i, p.ConfigEcho)]
    assert (config.ticks_per_rev, config.tick_rate_hz, config.heartbeat_period_ms) == (
        4096,
        100,
        1000,
    )
    stats = decoder.stats.as_dict()
    assert stats["frames"] == 205 and stats["lost"] == 0
    assert all(stats[k] == 0 for k in ("resyncs", "leading", "truncated", "device_restarts"))

    # The illegal steps reach the host in the TICKS error counts too.
    ticks = [m for m in BridgeReader().push(out, 0) if isinstance(m, p.Ticks)]
    assert [(t.left_errors, t.right_errors) for t in ticks[24:26]] == [(0, 0), (1, 0)]  # 250 ms
    assert (ticks[-1].left_errors, ticks[-1].right_errors) == (1, 1)


def test_configuration_is_echoed_and_applied(sim):
    wave = scripted_waveform()
    args = ["--end-us", "1000000", "--rate-hz", "50", "--heartbeat-ms", "500"]
    args += ["--ticks-per-rev", "2048", "--invert-left", "--reset-cause", "watchdog"]
    args += ["--boot-id", "48879"]
    out = run_sim(sim, wave.script, *args)
    config = {"ticks_per_rev": 2048, "tick_rate_hz": 50, "heartbeat_period_ms": 500}
    config["invert_left"] = True
    expected = expected_frames(
        wave,
        1_000_000,
        tick_us=20_000,
        heartbeat_us=500_000,
        sign=(-1, 1),
        sticky=int(p.Fault.WATCHDOG_RESET),
        boot_id=48879,
        config=config,
    )
    assert out == expected
    items = BridgeDecoder().push(out, 0)
    echo = next(i for i in items if isinstance(i, p.ConfigEcho))
    assert echo.invert_left and not echo.invert_right and echo.boot_id == 48879
    assert all("WATCHDOG_RESET" in i.fault_names for i in items if isinstance(i, p.Heartbeat))


def test_a_late_main_loop_latches_loop_overrun(sim):
    wave = scripted_waveform()
    decoder = BridgeDecoder()
    items = decoder.push(run_sim(sim, wave.script, "--end-us", "1000000", "--poll-us", "25000"), 0)
    samples = [i for i in items if isinstance(i, WheelSample)]
    assert [s.t_device_us for s in samples] == list(range(0, 1_000_001, 25_000))
    assert all((s.left, s.right) == wave.at(s.t_device_us)[0] for s in samples)
    heartbeats = [i for i in items if isinstance(i, p.Heartbeat)]
    assert "LOOP_OVERRUN" not in heartbeats[0].fault_names
    assert "LOOP_OVERRUN" in heartbeats[1].fault_names
    assert decoder.stats.lost == 0


def test_int32_wrap_of_the_board_counter_is_invisible_to_the_host(sim):
    """Drive the left count backwards past zero and check the frames carry int32 values
    the host turns back into the plain count (the board's uint32 counter wraps at 0)."""
    wave = Waveform()
    for k in range(6):
        wave.step(1_000 * (k + 1), 0, "back")
    out = run_sim(sim, wave.script, "--end-us", "20000")
    assert out == expected_frames(wave, 20_000)
    samples = [i for i in BridgeDecoder().push(out, 0) if isinstance(i, WheelSample)]
    assert [s.left for s in samples] == [0.0, -6.0, -6.0]


@pytest.mark.parametrize(
    "script", ["0 0 0 0\n", "0 0 0 0 2\n", "5 0 0 0 0\n3 1 0 0 0\n", "x 0 0 0 0\n"]
)
def test_bad_scripts_are_refused_with_a_message(sim, script):
    done = subprocess.run([str(sim)], input=script.encode(), capture_output=True, timeout=10)
    assert done.returncode == 2
    assert b"expected 'T_US LA LB RA RB'" in done.stderr


# ---------------------------------------------------------------- over a real pty


class Pty:
    """A pseudo-terminal reached through a stable symlink, as udev names a real board."""

    def __init__(self, link: Path):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # binary: no CR/LF translation, no echo
        self.link = link
        tmp = link.with_suffix(".new")
        tmp.unlink(missing_ok=True)
        tmp.symlink_to(os.ttyname(self.slave))
        os.replace(tmp, link)
        self.process: subprocess.Popen | None = None

    def start(self, sim: Path, script: str, *args: str) -> None:
        self.process = subprocess.Popen(
            [str(sim), "--realtime", *args], stdin=subprocess.PIPE, stdout=self.master
        )
        self.process.stdin.write(script.encode())
        self.process.stdin.close()

    def unplug(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.wait(timeout=10)
        for fd in (self.master, self.slave):
            with contextlib.suppress(OSError):  # already closed
                os.close(fd)


def read_until(source, count: int, timeout: float = 10.0) -> list:
    items, deadline = [], time.monotonic() + timeout
    while sum(isinstance(i, WheelSample) for i in items) < count:
        assert time.monotonic() < deadline, f"only {len(items)} items in {timeout} s"
        item = source.read(timeout=0.5)
        if item is not None:
            items.append(item)
    return items


def test_missing_port_is_a_source_error(tmp_path):
    with pytest.raises(SourceError, match="dialout"):
        SerialLink(str(tmp_path / "no-such-board"))
    link = SerialLink(str(tmp_path / "no-such-board"), wait_for_port=True, backoff_s=(0.05, 0.2))
    assert link.read(timeout=0.3) is None and not link.connected
    link.close()


def test_close_from_another_thread_ends_a_blocked_read(tmp_path):
    pty = Pty(tmp_path / "silent-board")
    source = open_bridge(str(pty.link))
    try:
        assert isinstance(source.read(), LinkEvent)  # connected; the board says nothing
        closer = threading.Timer(0.2, source.close)
        closer.start()
        started = time.monotonic()
        assert source.read() is None
        assert time.monotonic() - started < 1.0
        closer.join()
    finally:
        source.close()
        pty.unplug()


def test_samples_over_a_pty_and_the_recording_replays_the_same(sim, tmp_path):
    wave = scripted_waveform()
    pty = Pty(tmp_path / "treetraits-bridge")
    chunks = []
    source = open_bridge(str(pty.link), ticks_per_rev=4096, on_chunk=chunks.append)
    try:
        started = time.time_ns()
        pty.start(sim, wave.script, "--end-us", "400000")
        items = read_until(source, 41)
    finally:
        source.close()
        pty.unplug()
    assert isinstance(items[0], LinkEvent) and items[0].kind == "connected"
    samples = [i for i in items if isinstance(i, WheelSample)]
    assert [s.t_device_us for s in samples] == list(range(0, 400_001, TICK_US))
    assert all((s.left, s.right) == wave.at(s.t_device_us)[0] for s in samples)
    t_host = [s.t_host for s in samples]
    assert t_host == sorted(t_host) and started < t_host[0] <= time.time_ns()
    # Paced at the board's rate: 0.4 s of board time took about as long on the host.
    assert 0.3e9 < t_host[-1] - t_host[0] < 2.0e9
    assert source.counters()["config_mismatches"] == 0
    # The recorded chunks are the bytes the board sent, and replay gives the same samples.
    assert b"".join(c.data for c in chunks) == expected_frames(wave, 400_000)
    replay = BridgeDecoder()
    replayed = [
        i for c in chunks for i in replay.push(c.data, c.t_host) if isinstance(i, WheelSample)
    ]
    assert replayed == samples


def test_unplug_is_a_disconnect_without_busy_loop_then_replug(sim, tmp_path):
    wave = scripted_waveform()
    link_path = tmp_path / "treetraits-bridge"
    first = Pty(link_path)
    link = SerialLink(str(link_path), backoff_s=(0.05, 0.4))
    source = RetrofitSource(link, ticks_per_rev=2048)
    second = None
    try:
        first.start(sim, wave.script, "--end-us", "30000000", "--boot-id", "1")
        before = read_until(source, 20)
        first.unplug()  # mid-stream: the board's side of the pty is gone

        items = []
        deadline = time.monotonic() + 5
        while not any(isinstance(i, LinkEvent) and i.kind == "disconnected" for i in items):
            assert time.monotonic() < deadline, "no disconnect reported"
            item = source.read(timeout=0.5)
            if item is not None:
                items.append(item)
        assert items[-1].port == str(link_path) and items[-1].detail

        # Disconnected: reading waits for the device without spinning.
        cpu, wall = time.process_time(), time.monotonic()
        assert source.read(timeout=1.0) is None
        assert time.monotonic() - wall >= 0.9
        assert time.process_time() - cpu < 0.2
        assert 1 <= link.stats.open_failures <= 6

        # A rebooted board appears behind the same path: picked up, counts run on. It
        # starts sending once the port is open, as a USB board does when DTR rises.
        second = Pty(link_path)
        after = [source.read(timeout=2.0)]
        assert isinstance(after[0], LinkEvent) and after[0].kind == "connected"
        second.start(sim, wave.script, "--end-us", "30000000", "--boot-id", "2")
        after += read_until(source, 5)
    finally:
        source.close()
        first.unplug()
        if second is not None:
            second.unplug()

    kept = [i for i in before + items if isinstance(i, WheelSample)]
    assert len(kept) >= 20
    assert [s.t_device_us for s in kept] == [TICK_US * k for k in range(len(kept))]
    assert all((s.left, s.right) == wave.at(s.t_device_us)[0] for s in kept)
    resumed = [i for i in after if isinstance(i, WheelSample)]
    # The second board counts from zero again; the host adds its counts to the totals.
    offset = (kept[-1].left, kept[-1].right)
    for sample in resumed:
        counts = wave.at(sample.t_device_us)[0]
        assert (sample.left, sample.right) == (offset[0] + counts[0], offset[1] + counts[1])
    counters = source.counters()
    assert counters["link_disconnects"] == 1 and counters["link_connects"] == 2
    assert counters["device_restarts"] == 1 and counters["odometer_restarts"] == 1
    assert counters["config_mismatches"] == 2  # the board says 4096, the calibration 2048
