"""End to end: the demo survey replayed through the whole pipeline in one process on one
core (and on two with the detection worker), and the command line's start.

The recording is `make demo`'s (`treetraits sim --grid 5x5 --path straight --seed 0`: the
paper's 2x3 grid driven straight at 0.5 m/s), simulated once by the command line into a
cache directory (`--cache`, default ~/.cache/treetraits/bench), under a name keyed on the
simulator's code and settings (`evaluation.run.cache_key`), so a change to the twin makes
a new one. The process is pinned to one CPU, with one BLAS/OpenMP thread.

Replay: `run_replay` as `treetraits replay` calls it (default config, outputs to a
temporary directory). The first run also pays the imports and is reported apart (cold);
then `--rounds` runs, each followed by the input alone (the same recording's messages
read and its LiDAR packets batched into scans: the part no pipeline change can remove),
interleaved so that the machine's load hits both alike; medians. There is no peer that
replays a survey end to end; `bench/pipeline.py` compares the per-scan pipeline with RPH.

Frames: the recording's first 60 camera frames decoded as the mapper does (half size,
`fusion.MAPPER_REDUCTION`) and at full size, interleaved, per-frame medians: the one step
of the replay with a peer run side by side.

Start: the wall time of `python -m treetraits --help` in a fresh process, `--starts`
times, median; with the bytecode cache (`PYTHONPYCACHEPREFIX` in the cache directory,
written by a first start: what an installed package or any normal Python run has) and,
for reference, without it (`PYTHONDONTWRITEBYTECODE`: every module compiled at each start).

Two cores: each round also replays with the detection worker (`[pipeline] workers = 2`)
on this CPU and the next one allowed (n/a where only one is).

Last line, exactly: `replay_realtime=X replay_realtime_2cores=Y startup_s=S`, X = the
drive's seconds / the median replay's wall seconds (warm, one core), Y the same on two
cores with the worker, S = the median start with the bytecode cache. The warm
replays' CPU time (`time.process_time`) is printed beside the wall time: on a machine
shared with other jobs the wall time includes their turns on the CPU, the CPU time much
less so, which makes it the figure to compare across runs there.

    .venv/bin/python bench/replay.py [--rounds 5] [--starts 9] [--cache DIR] [--cpu N]
"""

from __future__ import annotations

import os

# One thread for NumPy's BLAS and OpenMP: set before NumPy is first imported.
for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
DEMO_SIM = ["--grid", "5x5", "--path", "straight", "--seed", "0"]  # the Makefile's demo


def demo_recording(cache: Path) -> Path:
    """The demo's recording, simulated by the command line unless the cache holds it."""
    from treetraits.evaluation.run import cache_key
    from treetraits.sim.run import SurveySettings

    key = cache_key(SurveySettings(path="straight", width=5.0, length=5.0, seed=0))
    path = cache / f"demo-survey-{key}.mcap"
    if not path.is_file():
        cache.mkdir(parents=True, exist_ok=True)
        temp = path.with_suffix(".tmp.mcap")
        print(f"simulating the demo survey into {path} (once; ~1 min)", file=sys.stderr)
        command = [sys.executable, "-m", "treetraits", "sim", *DEMO_SIM, "--out", str(temp)]
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
        temp.replace(path)
    return path


def replay_once(recording: Path, workers: int = 1) -> tuple[float, float, dict]:
    """Wall seconds and CPU seconds of one replay (`[pipeline] workers`), and its summary."""
    import dataclasses

    from treetraits.service.config import ServiceConfig
    from treetraits.service.replay import ReplayOptions, run_replay

    config = ServiceConfig()
    config = dataclasses.replace(
        config, pipeline=dataclasses.replace(config.pipeline, workers=workers)
    )
    with tempfile.TemporaryDirectory(prefix="bench-replay-") as out:
        start, cpu = time.perf_counter(), time.process_time()
        report = run_replay(recording, Path(out), ReplayOptions(config))
        return time.perf_counter() - start, time.process_time() - cpu, report.summary


def input_once(recording: Path) -> tuple[float, float]:
    """Wall seconds to read the recording and batch its LiDAR packets into scans, and the
    drive's seconds (first to last message)."""
    from treetraits.drivers import recording as rec
    from treetraits.drivers.velodyne.batcher import ScanBatcher
    from treetraits.service.replay import open_input

    start = time.perf_counter()
    batcher = ScanBatcher()
    first = last = None
    for topic, data, log_time, _ in open_input(recording).messages:
        first = log_time if first is None else first
        last = log_time
        if topic == rec.LIDAR_PACKETS:
            batcher.push(data, log_time)
    batcher.flush()
    return time.perf_counter() - start, (last - first) / 1e9


def decode_ms(recording: Path, frames: int = 60, rounds: int = 5) -> dict[int, float]:
    """Median ms to decode one camera frame, at full size and at the mapper's reduction."""
    from treetraits.drivers import recording as rec
    from treetraits.drivers.records import Frame
    from treetraits.pipeline.fusion import MAPPER_REDUCTION

    jpegs = []
    with rec.read_recording(recording, topics=[rec.CAMERA_JPEG]) as reader:
        for message in reader:
            jpegs.append(Frame(message.data, message.log_time, message.publish_time))
            if len(jpegs) == frames:
                break
    times: dict[int, list[float]] = {1: [], MAPPER_REDUCTION: []}
    for _ in range(rounds):
        for frame in jpegs:
            for reduction, values in times.items():
                start = time.perf_counter()
                frame.decode(reduction)
                values.append((time.perf_counter() - start) * 1e3)
    return {reduction: statistics.median(values) for reduction, values in times.items()}


def startup_times(starts: int, env: dict[str, str]) -> list[float]:
    """Wall seconds of `python -m treetraits --help`, each in a fresh process."""
    command = [sys.executable, "-m", "treetraits", "--help"]
    times = []
    for _ in range(starts):
        start = time.perf_counter()
        subprocess.run(command, check=True, stdout=subprocess.DEVNULL, env=env)
        times.append(time.perf_counter() - start)
    return times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=5, help="warm replays (default 5)")
    parser.add_argument("--starts", type=int, default=9, help="CLI starts timed (default 9)")
    parser.add_argument(
        "--cache", type=Path, default=Path.home() / ".cache" / "treetraits" / "bench"
    )
    parser.add_argument("--cpu", type=int, help="the CPU to pin to (default: the first allowed)")
    args = parser.parse_args()

    allowed = os.sched_getaffinity(0)
    cpu = args.cpu if args.cpu is not None else min(allowed)
    os.sched_setaffinity(0, {cpu})  # children (the starts) inherit it
    recording = demo_recording(args.cache)

    # The start first, while this process has imported nothing of the pipeline.
    cached = dict(os.environ, PYTHONPYCACHEPREFIX=str(args.cache / "pycache"))
    cached.pop("PYTHONDONTWRITEBYTECODE", None)
    startup_times(1, cached)  # writes the bytecode cache
    start_cached = statistics.median(startup_times(args.starts, cached))
    uncached = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    uncached.pop("PYTHONPYCACHEPREFIX", None)
    start_uncached = statistics.median(startup_times(args.starts, uncached))

    cold, _, summary = replay_once(recording)  # pays the imports
    # Two cores: this CPU and the next allowed one, for the replays with the detection
    # worker (threads made after the change inherit it); none where one is allowed.
    others = sorted(set(allowed) - {cpu})
    pair = {cpu, others[0]} if others else None
    replays, cpus, inputs, pairs = [], [], [], []
    for _ in range(args.rounds):
        seconds, cpu_s, again = replay_once(recording)
        assert again["trees"] == summary["trees"] and again["scans"] == summary["scans"]
        replays.append(seconds)
        cpus.append(cpu_s)
        seconds, drive_s = input_once(recording)
        inputs.append(seconds)
        if pair is not None:
            os.sched_setaffinity(0, pair)
            seconds, _, again = replay_once(recording, workers=2)
            os.sched_setaffinity(0, {cpu})
            assert again["trees"] == summary["trees"] and again["scans"] == summary["scans"]
            pairs.append(seconds)
    replay_s, input_s = statistics.median(replays), statistics.median(inputs)
    cpu_s = statistics.median(cpus)
    decode = decode_ms(recording)
    full, (reduction, reduced) = decode[1], max(decode.items())

    print(f"recording: {recording} ({recording.stat().st_size / 1e6:.1f} MB)")
    print(
        f"drive {drive_s:.1f} s, {summary['scans']} scans, {summary['frames']} frames, "
        f"{summary['trees']} trees; CPU {cpu}; {args.rounds} rounds, medians"
    )
    print(f"  replay, cold (imports included)   {cold:7.2f} s  {drive_s / cold:6.1f}x real time")
    print(
        f"  replay, warm                      {replay_s:7.2f} s  {drive_s / replay_s:6.1f}x real "
        f"time  (runs: {', '.join(f'{s:.2f}' for s in replays)})"
    )
    print(
        f"  replay, warm, CPU time            {cpu_s:7.2f} s  {drive_s / cpu_s:6.1f}x real "
        f"time  (the wall time less what the machine's other jobs took; "
        f"load {os.getloadavg()[0]:.1f})"
    )
    two_cores = "n/a"
    if pairs:
        pair_s = statistics.median(pairs)
        two_cores = f"{drive_s / pair_s:.1f}"
        print(
            f"  replay, warm, 2 cores (workers 2) {pair_s:7.2f} s  {two_cores:>6}x real "
            f"time  (CPUs {sorted(pair)}; runs: {', '.join(f'{s:.2f}' for s in pairs)})"
        )
    print(
        f"  input alone (read + batch scans)  {input_s:7.2f} s  {drive_s / input_s:6.1f}x real "
        f"time  ({input_s / replay_s:.0%} of the replay)"
    )
    print(
        f"  a 720p frame decoded: full size {full:.2f} ms, 1/{reduction} size (the mapper's) "
        f"{reduced:.2f} ms: {full / reduced:.2f}x faster"
    )
    print(f"  `treetraits --help`, bytecode cached  {start_cached:.3f} s ({args.starts} starts)")
    print(f"  `treetraits --help`, no bytecode      {start_uncached:.3f} s ({args.starts} starts)")
    print(
        f"replay_realtime={drive_s / replay_s:.1f} replay_realtime_2cores={two_cores} "
        f"startup_s={start_cached:.3f}"
    )


if __name__ == "__main__":
    main()
