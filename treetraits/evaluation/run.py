"""Simulate every (case, seed) once, replay each recording with every method, and score.

Simulating is the slow part (about real time on this machine), so recordings are cached
in OUT/cases/: the file name carries a key over the survey settings, the software version
and the simulator's own source and data, and a `.sim.json` marker written last says the
recording is complete. Work runs in a process pool (spawned: Open3D's threads and fork do
not mix); a recording's replays are queued as soon as it exists, longest cases first.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import sys
import time
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

from tqdm import tqdm

import treetraits.sim as sim_package
from treetraits import __version__
from treetraits.errors import ConfigError
from treetraits.evaluation.cases import Case
from treetraits.evaluation.methods import DEFAULT_METHODS, METHODS
from treetraits.evaluation.metrics import Detection, detections_from_trees
from treetraits.files import write_atomically
from treetraits.service.config import ServiceConfig, with_method
from treetraits.sim.run import SurveySettings


@dataclass(frozen=True)
class Simulated:
    case: str
    seed: int
    recording: Path
    truth_csv: Path
    driving_s: float  # simulated time
    simulate_s: float  # wall time it took (when it was made, if cached)
    cached: bool


@dataclass(frozen=True)
class Replayed:
    case: str
    seed: int
    method: str
    detections: tuple[Detection, ...]
    scans: int
    replay_s: float  # wall time of run_replay

    @property
    def s_per_scan(self) -> float:
        return self.replay_s / self.scans if self.scans else float("nan")


@dataclass(frozen=True)
class Evaluation:
    cases: tuple[Case, ...]
    seeds: tuple[int, ...]
    methods: tuple[str, ...]
    simulated: tuple[Simulated, ...]
    replayed: tuple[Replayed, ...]
    wall_s: float
    jobs: int


def parse_methods(spec: str | None) -> tuple[str, ...]:
    if spec is None:
        return DEFAULT_METHODS
    names = tuple(dict.fromkeys(w.strip() for w in spec.split(",") if w.strip()))
    unknown = [n for n in names if n not in METHODS]
    if unknown or not names:
        raise ConfigError(
            f"--methods: unknown {', '.join(map(repr, unknown)) or 'empty list'}; "
            f"choose from {', '.join(METHODS)}"
        )
    return names


# What a recording is made of: the simulator's modules and its bundled data (not every
# file under sim/: another tool living there must not invalidate the cache).
SIMULATOR_FILES = (
    "run.py",
    "orchard.py",
    "foliage.py",
    "paths.py",
    "lidar.py",
    "camera.py",
    "gnss.py",
    "wheels.py",
    "clutter.py",
)


def cache_key(settings: SurveySettings) -> str:
    """Over the settings, the version, and the simulator's code and data: a change in any
    makes a new recording rather than reusing a stale one."""
    digest = hashlib.sha256()
    digest.update(json.dumps(dataclasses.asdict(settings), sort_keys=True, default=str).encode())
    digest.update(__version__.encode())
    sim_dir = Path(sim_package.__file__).resolve().parent
    files = [sim_dir / name for name in SIMULATOR_FILES] + sorted(sim_dir.glob("data/*"))
    for path in files:
        digest.update(path.name.encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def recording_path(cases_dir: Path, case: Case, seed: int) -> Path:
    return cases_dir / f"{case.name}-seed{seed}-{cache_key(case.settings(seed))}.mcap"


def simulate(case: Case, seed: int, cases_dir: Path) -> Simulated:
    """The recording of (case, seed), simulated unless the cache holds it."""
    from treetraits.sim.run import simulate_survey

    path = recording_path(cases_dir, case, seed)
    marker = path.with_suffix(".sim.json")
    truth = path.with_suffix(".truth.csv")
    if marker.is_file() and path.is_file() and truth.is_file():
        facts = json.loads(marker.read_text())
        return Simulated(
            case.name, seed, path, truth, facts["driving_s"], facts["simulate_s"], True
        )
    start = time.perf_counter()
    result = simulate_survey(path, case.settings(seed))
    elapsed = time.perf_counter() - start
    facts = {
        "case": case.name,
        "seed": seed,
        "driving_s": result.duration_s,
        "simulate_s": round(elapsed, 2),
        "software": f"treetraits {__version__}",
        "settings": dataclasses.asdict(case.settings(seed)),
    }
    text = json.dumps(facts, indent=1, default=str)
    # Last, and whole or not at all: its presence means the recording is whole.
    write_atomically(marker, lambda f: f.write(text))
    return Simulated(case.name, seed, path, truth, result.duration_s, elapsed, False)


def replay(sim: Simulated, method: str, runs_dir: Path, config: ServiceConfig) -> Replayed:
    """Replay one recording with `method` over `config` (the eval's --config)."""
    from treetraits.service.replay import ReplayOptions, run_replay

    m = METHODS[method]
    out_dir = runs_dir / sim.case / f"seed{sim.seed}" / method
    start = time.perf_counter()
    config = with_method(config, m.replay_method, m.traits)
    report = run_replay(sim.recording, out_dir, ReplayOptions(config=config))
    elapsed = time.perf_counter() - start
    return Replayed(
        sim.case,
        sim.seed,
        method,
        tuple(detections_from_trees(report.trees + report.missing)),
        int(report.summary.get("scans", 0)),
        elapsed,
    )


def _expected_cost(case: Case) -> float:
    """Rough driving length (m), to start the longest cases first."""
    s = case.survey
    lanes = {"straight": 1, "s": 3, "n": 5}.get(s.path, 1)
    return lanes * s.goal * (1.0 + 0.5 * (s.wind.speed_mps > 0))


WORKER_STOP_S = 3.0  # a worker that ignores SIGTERM this long is killed


@contextlib.contextmanager
def _stopped_on_exception(pool: ProcessPoolExecutor) -> Iterator[ProcessPoolExecutor]:
    """The pool, shut down as usual at the end; on an exception (SIGTERM, Ctrl-C, a task
    that failed) its workers are terminated at once instead of being waited for, with
    their queued tasks cancelled: a simulation runs for minutes, and `kill` must stop
    the evaluation within seconds."""
    try:
        yield pool
    except BaseException:
        workers = list((getattr(pool, "_processes", None) or {}).values())
        manager = getattr(pool, "_executor_manager_thread", None)  # shutdown forgets it
        pool.shutdown(wait=False, cancel_futures=True)
        for worker in workers:
            with contextlib.suppress(OSError):
                worker.terminate()
        deadline = time.monotonic() + WORKER_STOP_S
        for worker in workers:
            worker.join(max(0.0, deadline - time.monotonic()))
            if worker.is_alive():
                worker.kill()
                worker.join()
        # The pool's manager thread, finding its workers gone, closes its wake-up pipe; at
        # exit concurrent.futures writes to that pipe without a lock (CPython 3.11), and a
        # close at the same moment printed an EBADF traceback after our last line.
        if manager is not None:
            manager.join(WORKER_STOP_S)
        raise
    pool.shutdown(wait=True)


def run_evaluation(
    cases: Sequence[Case],
    seeds: Sequence[int],
    methods: Sequence[str],
    out: Path,
    jobs: int | None = None,
    progress: bool = True,
    config: ServiceConfig | None = None,
) -> Evaluation:
    """Simulate (or reuse) and replay everything with `config`'s pipeline settings (None:
    the defaults); the results in memory (no files but the recordings and the replays'
    own outputs)."""
    config = config or ServiceConfig()
    if not cases:
        raise ConfigError("no case to evaluate")
    jobs = max(1, jobs or os.cpu_count() or 1)
    out = Path(out)
    cases_dir, runs_dir = out / "cases", out / "runs"
    cases_dir.mkdir(parents=True, exist_ok=True)
    by_name = {c.name: c for c in cases}
    order = sorted(((c, s) for c in cases for s in seeds), key=lambda p: -_expected_cost(p[0]))
    simulated: list[Simulated] = []
    replayed: list[Replayed] = []
    start = time.perf_counter()
    total = len(order) * (1 + len(methods))
    with (
        tqdm(total=total, desc="eval", unit="job", file=sys.stderr, disable=not progress) as bar,
        _stopped_on_exception(
            ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn"))
        ) as pool,
    ):
        # Own queue, at most `jobs` tasks in the pool: a recording's replays go before
        # the next simulation, so results (and failures) come early.
        sims_todo = list(order)
        replays_todo: list[tuple[Simulated, str]] = []
        pending: dict[Future, str] = {}
        while sims_todo or replays_todo or pending:
            while len(pending) < jobs and (replays_todo or sims_todo):
                if replays_todo:
                    sim, method = replays_todo.pop(0)
                    pending[pool.submit(replay, sim, method, runs_dir, config)] = "replay"
                else:
                    case, seed = sims_todo.pop(0)
                    pending[pool.submit(simulate, case, seed, cases_dir)] = "sim"
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                kind = pending.pop(future)
                result = future.result()
                bar.update(1)
                if kind == "sim":
                    simulated.append(result)
                    how = "cached" if result.cached else f"{result.simulate_s:.0f} s"
                    bar.set_postfix_str(f"simulated {result.case} seed {result.seed} ({how})")
                    replays_todo += [(result, method) for method in methods]
                else:
                    replayed.append(result)
                    bar.set_postfix_str(
                        f"replayed {result.case} seed {result.seed} {result.method}"
                    )
    key = {c.name: i for i, c in enumerate(cases)}
    simulated.sort(key=lambda s: (key[s.case], s.seed))
    replayed.sort(key=lambda r: (key[r.case], r.seed, list(methods).index(r.method)))
    return Evaluation(
        tuple(by_name[c.name] for c in cases),
        tuple(seeds),
        tuple(methods),
        tuple(simulated),
        tuple(replayed),
        time.perf_counter() - start,
        jobs,
    )
