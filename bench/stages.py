"""Where a replay's time goes: the demo survey (bench/replay.py's recording) replayed once
in one process on one core, each stage's CPU time (`time.process_time`, so a machine
shared with other jobs moves the figures less than wall time would) summed over the run
and divided by the scans mapped.

No profiler: cProfile's per-call overhead inflates the stages made of many small Python
calls (MCAP records, rosserial frames, packets) several times over and misleads. Instead
the stages' entry points are wrapped with a CPU clock (class attributes replaced for the
run; nothing in the pipeline changes), and the mapper's own stage timer (`StageClock`,
wall clock) is read with the CPU clock. Stages nest: a nested row is part of the row
above it. "the rest" is the whole run's CPU time less the top-level rows: reading the
recording, GNSS and wheel decoding, the scan's bookkeeping.

The imports are paid before the clock starts (a warm run, as bench/replay.py's).

    .venv/bin/python bench/stages.py [--cache DIR] [--cpu N] [--traits paper|robust]
                                     [--recording FILE.mcap]

`--recording` breaks down another recording instead (a field drive with many trees in
view, where the per-tree stages weigh more than on the demo's six trees).
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from replay import demo_recording  # noqa: E402

# (row, owner module, owner attribute or None for a module function, name, depth)
WRAPPED = (
    ("LiDAR packets to scans (decode, batch)", "treetraits.drivers.velodyne.batcher",
     "ScanBatcher", "push", 0),
    ("Jackal MCU bytes (rosserial)", "treetraits.firmware_bridge.jackal.session",
     "JackalProtocol", "receive", 0),
    ("IMU attitude filter", "treetraits.pipeline.localization.attitude", "AttitudeFilter",
     "add_imu", 0),
    ("localiser: GNSS fixes", "treetraits.pipeline.localization.localizer", "Localizer",
     "add_fix", 0),
    ("localiser: wheels", "treetraits.pipeline.localization.localizer", "Localizer",
     "add_wheels", 0),
    ("de-skew", "treetraits.service.survey", "SurveyProcessor", "_deskewed", 0),
    ("mapper (TreeMapper.process)", "treetraits.pipeline.mapper", "TreeMapper", "process", 0),
    ("NDVI of points (fuse_scan)", "treetraits.pipeline.mapper", "_NdviOf", "__call__", 2),
    ("JPEG decode (half size)", "treetraits.drivers.records", "Frame", "decode", 3),
    ("mapping (_map)", "treetraits.pipeline.mapper", "TreeMapper", "_map", 1),
    ("outline merge", "treetraits.pipeline.mapper", "TreeMapper", "_merge_outlines", 2),
    ("store commit (RunWriter.commit)", "treetraits.service.outputs", "RunWriter", "commit", 0),
    ("exports (RunWriter.export)", "treetraits.service.outputs", "RunWriter", "export", 0),
)  # fmt: skip

# The mapper's StageClock laps (detection, then _map's), shown under their parent.
DETECT_LAPS = (
    "crop",
    "mixed",
    "ground",
    "ndvi",
    "ndvi_check",
    "voxel",
    "stems",
    "cluster",
    "features",
)
MAP_LAPS = ("tracking", "traits")


def run(recording: Path, traits: str) -> tuple[dict[str, float], dict[str, float], float, int]:
    import importlib

    from treetraits.pipeline import detection
    from treetraits.service.config import ServiceConfig, with_method
    from treetraits.service.replay import ReplayOptions, run_replay

    spent: dict[str, float] = {}
    laps: dict[str, float] = {}

    def clocked(row, function):
        def wrapper(*args, **kwargs):
            start = time.process_time()
            try:
                return function(*args, **kwargs)
            finally:
                spent[row] = spent.get(row, 0.0) + time.process_time() - start

        return wrapper

    saved = []
    for row, module, owner, name, _ in WRAPPED:
        target = getattr(importlib.import_module(module), owner)
        saved.append((target, name, getattr(target, name)))
        setattr(target, name, clocked(row, getattr(target, name)))
    # The stage timer read with the CPU clock; timing switched on for every mapper.
    saved.append((detection, "time", detection.time))
    detection.time = types.SimpleNamespace(perf_counter=time.process_time)
    mapper_cls = importlib.import_module("treetraits.pipeline.mapper").TreeMapper
    process = mapper_cls.process

    def timed_process(self, *args, **kwargs):
        self.timing = True
        result = process(self, *args, **kwargs)
        for name, ms in result.stage_ms.items():
            laps[name] = laps.get(name, 0.0) + ms / 1e3
        return result

    mapper_cls.process = timed_process
    try:
        config = with_method(ServiceConfig(), traits=traits)
        with tempfile.TemporaryDirectory(prefix="bench-stages-") as out:
            run_replay(recording, Path(out), ReplayOptions(config=config))  # warm up
        spent.clear()
        laps.clear()
        with tempfile.TemporaryDirectory(prefix="bench-stages-") as out:
            start = time.process_time()
            report = run_replay(recording, Path(out), ReplayOptions(config=config))
            total = time.process_time() - start
    finally:
        mapper_cls.process = process
        for target, name, original in reversed(saved):
            setattr(target, name, original)
    return spent, laps, total, int(report.summary["scans"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--cache", type=Path, default=Path.home() / ".cache" / "treetraits" / "bench"
    )
    parser.add_argument("--cpu", type=int, help="the CPU to pin to (default: the first allowed)")
    parser.add_argument("--traits", choices=("paper", "robust"), default="paper")
    parser.add_argument(
        "--recording", type=Path, help="a recording to break down (default: the demo survey)"
    )
    args = parser.parse_args()
    cpu = args.cpu if args.cpu is not None else min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    recording = args.recording or demo_recording(args.cache)
    if not recording.is_file():
        parser.error(f"{recording}: no such recording")
    spent, laps, total, scans = run(recording, args.traits)

    def line(row: str, seconds: float, depth: int) -> None:
        label = "  " * depth + row
        print(f"| {label} | {seconds / scans * 1e3:.2f} | {seconds / total:.0%} |")

    name = "demo survey" if args.recording is None else recording.name
    print(f"{name}, {scans} scans, CPU {cpu}, traits {args.traits}: {total:.2f} s of CPU")
    print("| stage | CPU ms per scan | share |")
    print("|---|---|---|")
    top = 0.0
    for row, _, _, _, depth in WRAPPED:
        seconds = spent.get(row, 0.0)
        top += seconds if depth == 0 else 0.0
        line(row, seconds, depth)
        if row.startswith("mapper"):
            line("detection (detect)", sum(laps.get(n, 0.0) for n in DETECT_LAPS), 1)
            for name in DETECT_LAPS:
                line(f"detect: {name}", laps.get(name, 0.0), 2)
        if row.startswith("mapping"):
            for name in MAP_LAPS:
                line(f"_map: {name}", laps.get(name, 0.0), 2)
    line("the rest (reading the recording, GNSS, bookkeeping)", total - top, 0)
    print(f"stages_cpu_s={total:.2f} scans={scans} ms_per_scan={total / scans * 1e3:.1f}")


if __name__ == "__main__":
    main()
