"""The onboard service (`treetraits run`) under full sensor load on loopback, against the
pipeline's own cost (`treetraits replay` of the same recording) measured in this process.

A simulated survey long enough for the window (cached under out/bench/) is played by
`sim.player.RecordingPlayer` at its recorded pace: VLP-16 packets over UDP from
127.0.0.1 (754 /s), NMEA into a pty, a live Jackal MCU on a second pty; the camera is
the recording's frames as an MJPG video (`camera.device = <file>`, played from the
service's start, so it is not time-aligned with the LiDAR: the load is right, the
pictures are not). The service runs as a subprocess with a NOTIFY_SOCKET we bind; the
player starts on READY=1 and plays for `--seconds` (default 60). With `--busy N` the
service is pinned to one CPU beside N busy loops: a computer too slow for every scan,
where the service sheds scans (`service.max_backlog_s`, docs/service.md). Measured:

- lost packets: the player's count sent (data + telemetry) minus what the service took
  from its sockets (STATUS `lidar_packets`: what the kernel dropped for a full socket
  buffer is in this difference), plus what the service took but its LiDAR queue dropped
  (`dropped_lidar`). The kernel's drops are shown beside, from /proc/net/udp `drops`
  (exact and independent of the service) and from the service's own SO_RXQ_OVFL count;
  a service that does not report `lidar_packets` is charged its drops plus the kernel's;
- CPU: utime + stime of the service (/proc/<pid>/stat) over the window, % of one core;
  and per thread (/proc/<pid>/task/*/stat; the receive threads are named rx-<sensor>);
  a detection process the service started (`--detect-in process`) counted with it, its
  memory too;
- RSS: VmRSS every second; the peak, and the median of the first and last thirds (flat
  means last/first near 1);
- latency from a scan's last packet to its trees committed: `traits.sqlite` is polled
  every `POLL_S` for new observation `scan_t` values (the scan's middle on the host
  clock, committed in the scan's transaction); latency = first seen - (scan_t + half a
  rotation, the median measured on the recording). Only scans that saw a tree are in the
  store; the poll adds 0-POLL_S (half on average).

The peer: `treetraits.service.replay.run_replay` of the same recording in this process after the
live run (nothing else running), its CPU per recorded second. `cpu_vs_replay` = the
service's CPU per live second / the replay's per recorded second: what being live
costs on top of the pipeline (1.0 = nothing).

Last line, exactly: `service_lost=N cpu_pct=C busiest_thread_pct=T rss_peak_mb=M
latency_ms_p50=A latency_ms_p99=B rss_growth=G cpu_vs_replay=R` (no line breaks);
`busiest_thread_pct`: the service's busiest thread's CPU (from /proc/PID/task), % of one
core: what one core of a slower computer must keep up with.

    .venv/bin/python bench/service.py [--seconds 60] [--record] [--recording REC.mcap]
        [--busy N] [--workers 1|2] [--detect-in thread|process]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import signal
import socket
import sqlite3
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from treetraits.drivers import recording as rec  # noqa: E402
from treetraits.drivers.velodyne.batcher import ScanBatcher  # noqa: E402
from treetraits.service.replay import ReplayOptions, run_replay  # noqa: E402
from treetraits.sim.player import RecordingPlayer, write_camera_video  # noqa: E402
from treetraits.sim.run import SurveySettings, simulate_survey  # noqa: E402

CACHE = ROOT / "out" / "bench"
POLL_S = 0.02
READY_TIMEOUT_S = 60.0
STOP_TIMEOUT_S = 30.0
WATCHDOG_S = 10.0
CLK_TCK = os.sysconf("SC_CLK_TCK")
SPEED_M_S = 0.5  # the simulated robot's cruise speed (sim.paths.DriveSettings)


# --- the input ------------------------------------------------------------------------------


def survey_for(seconds: float) -> Path:
    """A simulated straight survey lasting at least `seconds` + 5 s, trees all along it
    (2 columns, a row every 5 m), cached: simulating a minute takes about 40 s."""
    goal = (seconds + 5) * SPEED_M_S + 1.0
    rows = max(3, int(goal // 5.0))
    path = CACHE / f"service_{int(goal)}m_{rows}rows.mcap"
    if not path.exists():
        print(f"simulating a {goal:.0f} m survey into {path} ...", flush=True)
        CACHE.mkdir(parents=True, exist_ok=True)
        partial = path.with_suffix(".partial.mcap")
        result = simulate_survey(partial, SurveySettings(goal=goal, rows=rows, seed=0))
        for suffix in (".truth.csv", ".field_map.geojson"):
            os.replace(partial.with_suffix(suffix), path.with_suffix(suffix))
        os.replace(result.recording, path)
    return path


def span_s(path: Path) -> float:
    """From the recording's first message to its last, by log_time."""
    times = [m.log_time for m in rec.read_recording(path, [rec.LIDAR_PACKETS])]
    return (max(times) - min(times)) / 1e9


def half_rotation_ns(path: Path) -> int:
    """The median of (t_end - t_start) / 2 over the recording's complete scans: how far a
    scan's last packet comes after its middle (the mapper's `t`)."""
    batcher = ScanBatcher()
    halves = []
    for m in rec.read_recording(path, [rec.LIDAR_PACKETS]):
        scan = batcher.push(m.data, m.log_time)
        if scan is not None and scan.complete:
            halves.append((scan.t_end - scan.t_start) // 2)
    return int(statistics.median(halves))


# --- what we watch ------------------------------------------------------------------------


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def family(pid: int) -> list[int]:
    """The process and its descendants (/proc/<pid>/task/*/children): a detection worker
    in a second process (`[pipeline] detect_in = "process"`) is the service's work."""
    out, todo = [], [pid]
    while todo:
        parent = todo.pop()
        out.append(parent)
        for children in Path(f"/proc/{parent}/task").glob("*/children"):
            with contextlib.suppress(OSError, ValueError):
                todo += [int(child) for child in children.read_text().split()]
    return out


def stat_cpu_seconds(stat: str) -> float:
    """utime + stime from a /proc stat line (fields 14 and 15 of proc(5)), in seconds."""
    fields = stat[stat.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / CLK_TCK


def cpu_seconds(pid: int) -> float:
    """utime + stime of a process and its descendants, all their threads, in seconds."""
    total = 0.0
    for member in family(pid):
        with contextlib.suppress(OSError, ValueError, IndexError):
            total += stat_cpu_seconds(Path(f"/proc/{member}/stat").read_text())
    return total


def thread_cpu_seconds(pid: int) -> dict[str, float]:
    """utime + stime per thread of a process and its descendants, keyed by `tid name`
    (the name is the OS thread name, /proc/<pid>/task/<tid>/comm: the service names its
    receive threads)."""
    out = {}
    for member in family(pid):
        tasks = []
        with contextlib.suppress(OSError):
            tasks = list(Path(f"/proc/{member}/task").iterdir())
        for task in tasks:
            with contextlib.suppress(OSError, ValueError, IndexError):
                stat = (task / "stat").read_text()
                name = stat[stat.index("(") + 1 : stat.rindex(")")]
                out[f"{task.name} {name}"] = stat_cpu_seconds(stat)
    return out


def rss_mb(pid: int) -> float | None:
    """VmRSS of a process and its descendants, MB (None once it is gone)."""
    total, found = 0.0, False
    for member in family(pid):
        with contextlib.suppress(OSError):
            for line in Path(f"/proc/{member}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    total += int(line.split()[1]) / 1024
                    found = True
    return total if found else None


def udp_drops(port: int) -> int | None:
    """The kernel's drop counter of the UDP socket(s) bound to `port` (/proc/net/udp)."""
    total, found = 0, False
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        with contextlib.suppress(OSError):
            for line in Path(table).read_text().splitlines()[1:]:
                parts = line.split()
                if int(parts[1].rsplit(":", 1)[1], 16) == port:
                    total += int(parts[-1])
                    found = True
    return total if found else None


class Notifications:
    """The NOTIFY_SOCKET the service's sd_notify writes to: READY, STATUS lines, ..."""

    def __init__(self, path: Path):
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(str(path))
        self.sock.settimeout(0.1)
        self.ready = False
        self.statuses: list[tuple[float, str]] = []
        self.watchdogs = 0

    def drain(self, timeout: float = 0.0) -> None:
        self.sock.settimeout(timeout if timeout > 0 else 0.001)
        while True:
            try:
                data = self.sock.recv(65536)
            except (TimeoutError, BlockingIOError):
                return
            for line in data.decode(errors="replace").splitlines():
                key, _, value = line.partition("=")
                if key == "READY" and value == "1":
                    self.ready = True
                elif key == "STATUS":
                    self.statuses.append((time.monotonic(), value))
                elif key == "WATCHDOG":
                    self.watchdogs += 1
            self.sock.settimeout(0.001)

    def close(self) -> None:
        self.sock.close()


STATUS_NUMBER = re.compile(r"([A-Za-z_][\w.]*)=(-?\d+(?:\.\d+)?)")


def status_counters(status: str) -> dict[str, float]:
    """The `name=number` pairs of a STATUS line."""
    return {k: float(v) for k, v in STATUS_NUMBER.findall(status)}


class CommitWatcher(threading.Thread):
    """Polls the run's traits.sqlite for new scans; remembers when each was first seen."""

    def __init__(self, out_dir: Path):
        super().__init__(name="commit-watcher", daemon=True)
        self.out_dir = out_dir
        self.seen: dict[int, int] = {}  # scan_t -> time.time_ns() when first seen
        self.stop = threading.Event()
        self.errors: list[str] = []

    def _store(self) -> Path | None:
        latest = self.out_dir / "runs" / "latest" / "traits.sqlite"
        if latest.exists():
            return latest
        found = sorted(self.out_dir.glob("runs/*/traits.sqlite"))
        return found[-1] if found else None

    def run(self) -> None:
        db = None
        newest = -1
        while not self.stop.wait(POLL_S):
            if db is None:
                path = self._store()
                if path is None:
                    continue
                db = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=0.5)
            try:
                rows = db.execute(
                    "SELECT DISTINCT scan_t FROM observations WHERE scan_t > ?", (newest,)
                ).fetchall()
            except sqlite3.Error as exc:  # not created yet, or busy: try again
                if str(exc) not in self.errors:
                    self.errors.append(str(exc))
                continue
            now = time.time_ns()
            for (scan_t,) in rows:
                self.seen.setdefault(scan_t, now)
                newest = max(newest, scan_t)
        if db is not None:
            db.close()


# --- one live run -----------------------------------------------------------------------


@dataclass
class LiveRun:
    seconds: float
    sent: int = 0
    received: float | None = None  # by the service's own count, if it reports one
    service_drops: float | None = None
    kernel_drops: int | None = None
    cpu_s: float = 0.0
    rss: list[float] = field(default_factory=list)
    latencies_ms: list[float] = field(default_factory=list)
    statuses: list[str] = field(default_factory=list)
    player: dict = field(default_factory=dict)
    exit_code: int | None = None
    watchdogs: int = 0
    log_tail: str = ""
    recorded_bytes: int = 0
    bench_cpu_s: float = 0.0  # this process (the player, the pollers) over the window
    thread_cpu_s: dict[str, float] = field(default_factory=dict)  # per service thread
    scans: int = 0  # committed, by the last STATUS
    scans_shed: int = 0  # not mapped: the loop was behind its sensors (service.max_backlog_s)


def write_config(path: Path, values: dict[str, dict]) -> None:
    lines = []
    for section, keys in values.items():
        lines.append(f"[{section}]")
        for key, value in keys.items():
            lines.append(f"{key} = {json.dumps(value)}")  # TOML takes JSON strings/numbers
        lines.append("")
    path.write_text("\n".join(lines))


def busy_loops(count: int, cpu: int) -> list[subprocess.Popen]:
    """`count` processes spinning on `cpu`: the service pinned there gets about 1/(count+1)
    of it, a computer slower than this one."""
    return [
        subprocess.Popen(
            [sys.executable, "-c", "while True: pass"],
            preexec_fn=lambda: os.sched_setaffinity(0, {cpu}),
        )
        for _ in range(count)
    ]


def live_run(
    recording: Path,
    seconds: float,
    record: bool,
    work: Path,
    busy: int = 0,
    workers: int = 0,
    detect_in: str = "",
) -> LiveRun:
    work.mkdir(parents=True)
    video = write_camera_video(recording, work / "camera.avi")
    calibration = rec.read_recording(recording).metadata
    calibration_path = work / "calibration.json"
    calibration_path.write_text(json.dumps(calibration.calibration if calibration else {}))
    field_map = recording.with_suffix(".field_map.geojson")
    data_port, telemetry_port = free_udp_port(), free_udp_port()
    player = RecordingPlayer(recording, data_port=data_port, telemetry_port=telemetry_port)
    out_dir = work / "out"
    config = work / "config.toml"
    write_config(
        config,
        {
            "output": {"dir": str(out_dir), "export_every_s": 5.0},
            "pipeline": {
                "calibration": str(calibration_path),
                "field_map": str(field_map) if field_map.exists() else "",
                **({"workers": workers} if workers else {}),
                **({"detect_in": detect_in} if detect_in else {}),
            },
            "lidar": {
                "bind": "127.0.0.1",
                "data_port": data_port,
                "telemetry_port": telemetry_port,
                "sensor_ip": "127.0.0.1",
            },
            "camera": {"device": str(video)},
            "gnss": {"port": player.gnss_device},
            "wheels": {"kind": "jackal", "port": player.wheels_device},
            "record": {"enabled": record, "dir": str(work / "recordings")},
            "service": {"status_every_s": 1.0},
        },
    )
    notify = Notifications(work / "notify.sock")
    # A watchdog as the unit sets one (WatchdogSec=): the loop must ping every 5 s.
    env = dict(
        os.environ,
        NOTIFY_SOCKET=str(notify.path),
        WATCHDOG_USEC=str(int(WATCHDOG_S * 1e6)),
        PYTHONUNBUFFERED="1",
    )
    log_path = work / "service.log"
    command = [*SERVICE_COMMAND, "run", "--config", str(config)]
    if record:
        command.append("--record")
    result = LiveRun(seconds)
    watcher = CommitWatcher(out_dir)
    cpu = min(os.sched_getaffinity(0))
    pin = (lambda: os.sched_setaffinity(0, {cpu})) if busy else None
    with open(log_path, "wb") as log:
        service = subprocess.Popen(
            command, cwd=ROOT, env=env, stdout=log, stderr=log, preexec_fn=pin
        )
    spinners = busy_loops(busy, cpu)
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while not notify.ready:
            notify.drain(0.1)
            if service.poll() is not None or time.monotonic() > deadline:
                tail = log_path.read_text(errors="replace")[-3000:]
                raise SystemExit(
                    f"the service did not report READY=1 (exit code {service.poll()}):\n{tail}"
                )
        watcher.start()
        cpu_start = cpu_seconds(service.pid)
        threads_start = thread_cpu_seconds(service.pid)
        started = time.monotonic()
        bench_cpu = time.process_time()
        player.start()
        next_sample = started
        while time.monotonic() - started < seconds:
            notify.drain(max(0.0, next_sample - time.monotonic()))
            if time.monotonic() >= next_sample:
                if (value := rss_mb(service.pid)) is not None:
                    result.rss.append(value)
                next_sample += 1.0
            if service.poll() is not None:
                break
        window = time.monotonic() - started
        result.seconds = window
        if service.poll() is None:
            result.cpu_s = cpu_seconds(service.pid) - cpu_start
            threads_end = thread_cpu_seconds(service.pid)
            result.thread_cpu_s = {k: v - threads_start.get(k, 0.0) for k, v in threads_end.items()}
            result.kernel_drops = udp_drops(data_port)
        player.stop()  # stop sending, ptys left open: the service sees silence, not unplugs
        result.player = player.counters
        result.sent = result.player["lidar_sent"] + result.player["telemetry_sent"]
        result.bench_cpu_s = time.process_time() - bench_cpu
        time.sleep(1.5)  # the service drains its queue and commits the last scans
        notify.drain(0.2)
        if service.poll() is None:
            service.send_signal(signal.SIGTERM)
        try:
            result.exit_code = service.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            service.kill()
            result.exit_code = service.wait()
        notify.drain(0.2)
    finally:
        for spinner in spinners:
            spinner.kill()
            spinner.wait()
        watcher.stop.set()
        player.close()
        if service.poll() is None:
            service.kill()
            service.wait()
        notify.close()
    watcher.join(timeout=2)
    result.statuses = [s for _, s in notify.statuses]
    result.watchdogs = notify.watchdogs
    result.log_tail = log_path.read_text(errors="replace")[-2000:]
    half = half_rotation_ns(recording)
    result.latencies_ms = [(seen - (t + half)) / 1e6 for t, seen in watcher.seen.items()]
    last = status_counters(result.statuses[-1]) if result.statuses else {}
    result.received = last.get(RECEIVED_KEY)
    result.service_drops = next((last[k] for k in DROPPED_KEYS if k in last), None)
    result.scans, result.scans_shed = int(last.get("scans", 0)), int(last.get("scans_shed", 0))
    if KERNEL_DROPS_KEY in last:  # the service's own view of the kernel's drops
        result.kernel_drops = max(result.kernel_drops or 0, int(last[KERNEL_DROPS_KEY]))
    if record:
        result.recorded_bytes = sum(p.stat().st_size for p in (work / "recordings").rglob("*"))
    return result


# STATUS keys: LiDAR datagrams taken from the sockets, LiDAR packets dropped from the
# full queue (`dropped`: all queues, as services before lidar_packets reported it), and
# the kernel's drops the service saw (SO_RXQ_OVFL).
RECEIVED_KEY = "lidar_packets"
DROPPED_KEYS = ("dropped_lidar", "dropped")
KERNEL_DROPS_KEY = "kernel_drops"

SERVICE_COMMAND = [sys.executable, "-m", "treetraits"]


# --- the peer ----------------------------------------------------------------------------


def replay_cost(recording: Path, work: Path) -> tuple[float, float, int]:
    """CPU seconds and wall seconds of `run_replay` on the recording, and its scans."""
    cpu = time.process_time()
    wall = time.perf_counter()
    report = run_replay(recording, work / "replay", ReplayOptions())
    return time.process_time() - cpu, time.perf_counter() - wall, int(report.summary["scans"])


# --- the report --------------------------------------------------------------------------


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    if not ordered:
        return float("nan")
    return ordered[min(len(ordered) - 1, max(0, round(q / 100 * (len(ordered) - 1))))]


def report(run: LiveRun, label: str, replay_cpu_per_s: float) -> dict[str, float]:
    p = run.player
    cpu_pct = 100 * run.cpu_s / run.seconds if run.seconds else float("nan")
    third = max(1, len(run.rss) // 3)
    first, last = run.rss[:third], run.rss[-third:]
    growth = statistics.median(last) / statistics.median(first) if run.rss else float("nan")
    peak = max(run.rss) if run.rss else float("nan")
    lost = None
    if run.received is not None:
        lost = run.sent - run.received + (run.service_drops or 0)
    elif run.service_drops is not None:
        lost = run.service_drops + (run.kernel_drops or 0)
    print(f"== {label}: {run.seconds:.1f} s under load, service exit code {run.exit_code}")
    print(
        f"  player: {p['lidar_sent']} packets ({p['lidar_sent'] / run.seconds:.0f} /s), "
        f"{p['telemetry_sent']} telemetry, {p['gnss_sent']} NMEA, {p['wheels_sent']} MCU "
        f"frames ({p['wheels_unheard']} unheard); lateness median "
        f"{p['lidar_late_median_ms']:.2f} ms, max {p['lidar_late_max_ms']:.1f} ms"
    )
    print(
        f"  packets: sent {run.sent}, service took in "
        f"{'?' if run.received is None else int(run.received)}, service dropped "
        f"{'?' if run.service_drops is None else int(run.service_drops)}, kernel drops "
        f"{'?' if run.kernel_drops is None else run.kernel_drops}"
    )
    vs = (run.cpu_s / run.seconds) / replay_cpu_per_s if replay_cpu_per_s else float("nan")
    print(
        f"  CPU: {run.cpu_s:.1f} s in {run.seconds:.1f} s = {cpu_pct:.1f} % of one core "
        f"(goal <= 25 %); replay of the same data: {100 * replay_cpu_per_s:.1f} % -> "
        f"live/replay {vs:.2f}"
    )
    if run.thread_cpu_s:
        busiest = sorted(run.thread_cpu_s.items(), key=lambda kv: -kv[1])[:6]
        print(
            "  CPU by thread (% of one core): "
            + ", ".join(f"{k} {100 * v / run.seconds:.1f}" for k, v in busiest)
        )
    if run.rss:
        print(
            f"  RSS: peak {peak:.0f} MB (goal <= 400), median first third "
            f"{statistics.median(first):.0f} MB, last third {statistics.median(last):.0f} MB "
            f"(x{growth:.2f}), {len(run.rss)} samples"
        )
    print(f"  scans: committed {run.scans}, shed {run.scans_shed} (the loop behind its sensors)")
    lat = run.latencies_ms
    if lat:
        print(
            f"  latency last packet -> committed: median {statistics.median(lat):.0f} ms, "
            f"p99 {percentile(lat, 99):.0f} ms, max {max(lat):.0f} ms over {len(lat)} scans "
            f"with trees (polled every {POLL_S * 1e3:.0f} ms)"
        )
    else:
        print("  latency: no scan committed with trees (nothing to measure)")
    last_status = run.statuses[-1] if run.statuses else "-"
    print(
        f"  watchdog pings {run.watchdogs} (WATCHDOG_USEC {WATCHDOG_S:.0f} s); the bench "
        f"process (player, pollers) used {100 * run.bench_cpu_s / run.seconds:.1f} % of a core"
    )
    print(f"  last STATUS: {last_status}")
    if run.recorded_bytes:
        mb = run.recorded_bytes / 1e6
        print(f"  recorded {mb:.1f} MB ({mb / run.seconds:.2f} MB/s)")
    if run.exit_code not in (0, None):
        print(f"  service log tail:\n{run.log_tail}")
    busiest_pct = float("nan")
    if run.thread_cpu_s and run.seconds:
        busiest_pct = 100 * max(run.thread_cpu_s.values()) / run.seconds
    return {
        "lost": float("nan") if lost is None else lost,
        "cpu_pct": cpu_pct,
        "busiest_thread_pct": busiest_pct,
        "rss_peak_mb": peak,
        "rss_growth": growth,
        "p50": statistics.median(lat) if lat else float("nan"),
        "p99": percentile(lat, 99),
        "vs": vs,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=60.0, help="load window (default 60)")
    parser.add_argument("--record", action="store_true", help="also a run with --record")
    parser.add_argument("--recording", type=Path, help="play this instead of a simulated survey")
    parser.add_argument("--keep", action="store_true", help="keep the work directory")
    parser.add_argument(
        "--busy",
        type=int,
        default=0,
        help="pin the service to one CPU with this many busy loops: a slower computer (2: "
        "about a third of a core, where a Xavier core 3x slower than this one would need "
        "~135 %% of one for the same load)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=0,
        help="the service's [pipeline] workers (1 or 2; default: the config's default)",
    )
    parser.add_argument(
        "--detect-in",
        choices=("thread", "process"),
        default="",
        help="where the service's detection worker runs ([pipeline] detect_in; default: "
        "the config's, a thread in the service); a process's CPU and memory are counted "
        "with the service's",
    )
    args = parser.parse_args()
    recording = args.recording or survey_for(args.seconds)
    duration = span_s(recording)
    if duration < args.seconds:
        print(
            f"note: {recording} lasts {duration:.1f} s, less than the {args.seconds:.0f} s window"
        )
    work = Path(tempfile.mkdtemp(prefix="treetraits-bench-service-"))
    try:

        def run(record: bool, name: str) -> LiveRun:
            return live_run(
                recording,
                args.seconds,
                record,
                work / name,
                args.busy,
                args.workers,
                args.detect_in,
            )

        runs = [("live", run(False, "live"))]
        if args.record:
            runs.append(("live --record", run(True, "record")))
        replay_cpu, replay_wall, scans = replay_cost(recording, work)
        per_s = replay_cpu / duration
        print(
            f"recording {recording.name}: {duration:.1f} s; replay (the peer): {replay_cpu:.1f} "
            f"CPU-s, {replay_wall:.1f} s wall ({duration / replay_wall:.1f}x real time), "
            f"{scans} scans"
        )
        figures = [report(run, label, per_s) for label, run in runs]
    finally:
        if args.keep:
            print(f"work directory kept: {work}")
        else:
            import shutil

            shutil.rmtree(work, ignore_errors=True)
    f = figures[0]
    print(
        f"service_lost={f['lost']:.0f} cpu_pct={f['cpu_pct']:.1f} "
        f"busiest_thread_pct={f['busiest_thread_pct']:.1f} rss_peak_mb={f['rss_peak_mb']:.0f} "
        f"latency_ms_p50={f['p50']:.0f} latency_ms_p99={f['p99']:.0f} "
        f"rss_growth={f['rss_growth']:.2f} cpu_vs_replay={f['vs']:.2f}"
    )


if __name__ == "__main__":
    main()
