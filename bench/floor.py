"""Where the floor of a replay is: of a scan's CPU, the share that is work a compiled
pipeline would still have to do, and the share that is the interpreter, NumPy's call
machinery and the allocator around them.

A child process replays the recording (default: the demo survey, bench/replay.py's) once
to warm up and then `--rounds` times inside `measured_replays`, pinned to one CPU, while
py-spy samples it with native frames (`py-spy record --native -f raw`; at rates much
above 25 Hz its native unwinding falls behind). Only the samples inside
`measured_replays` count, each by the function on top of its stack:

- interpreter and runtimes: a Python frame (bytecode, dataclass constructors, the stages'
  glue), libpython, CPython's C modules (struct), numba's dispatch;
- NumPy's call machinery: argument parsing, type resolution, array and iterator set-up
  and tear-down (`ufunc_generic_fastcall`, `PyArray_NewFromDescr`, `NpyIter_*`, ...);
- libc: malloc, free, memcpy (in good part the arrays those calls make and drop);
- work: NumPy's inner loops, copies, fancy indexing and sorts; the compiled kernels
  (numba's code, which py-spy shows without a name); libjpeg-turbo; SciPy, BLAS, libm;
  zstd; SQLite; file reads, writes and syncs.

Where a frame could go either way it is counted as overhead, so the floor is if anything
set too low and `best_realtime` too high.

`floor_ms_per_scan` is a scan's CPU in a replay nobody samples (this process, after a
warm-up: the median of `--rounds` replays' `time.process_time`; py-spy's pauses would
leave the sampled child's caches colder) times the work's share: what a scan would
cost were every interpreter and NumPy call compiled away and the allocator with them, the
work itself done as today. `best_realtime` is the drive's seconds over that cost for
every scan: what compiling the glue away could give a replay on this machine at most,
unless the work itself is made smaller (fewer points, passes or pixels).

Needs py-spy (`pip install py-spy`, not a dependency of the package) and the right to
read another process's memory (root, or `kernel.yama.ptrace_scope` 0).

    .venv/bin/python bench/floor.py [--recording FILE.mcap] [--rounds 3] [--rate 25]
                                    [--cpu N] [--cache DIR]

Last line, exactly: `work_share=W ms_per_scan=M floor_ms_per_scan=F best_realtime=X
samples=S` (no line breaks).
"""

from __future__ import annotations

import os

for _name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_name, "1")

import argparse  # noqa: E402
import re  # noqa: E402
import shutil  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections import Counter  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from replay import demo_recording, input_once, replay_once  # noqa: E402

MEASURED = "measured_replays"
# The rows, and whether each is work a compiled pipeline would still do.
INTERPRETER = "interpreter and runtimes (CPython, numba's dispatch)"
NUMPY_CALLS = "NumPy's call machinery"
LIBC = "libc (malloc, free, memcpy)"
KERNELS = "work: compiled kernels (numba)"
NUMPY_WORK = "work: NumPy loops, copies, sorts"
JPEG = "work: JPEG decode"
OTHER_WORK = "work: SciPy, BLAS, libm and the rest"
IO_WORK = "work: zstd, SQLite, file I/O"
CATEGORIES = (
    (INTERPRETER, False),
    (NUMPY_CALLS, False),
    (LIBC, False),
    (KERNELS, True),
    (NUMPY_WORK, True),
    (JPEG, True),
    (OTHER_WORK, True),
    (IO_WORK, True),
)
# NumPy's own functions that move or compute data (the rest of its C is call machinery).
_NUMPY_DATA = re.compile(
    r"mapiter|Nonzero|TransferNDim|CopyAsFlat|AssignArray|boolean_subscript|sort|partition"
    r"|_contig|_strided|_aligned|svml|simd|DOUBLE_|FLOAT_|LONG_|BOOL_|INT_|sum_of_products"
    r"|count_boolean|binsearch|copyswap"
)
# C source with line numbers: CPython's own modules and headers (struct, refcounts) and
# Cython's argument parsing; numba's dispatch and runtime (its kernels have no file).
_RUNTIME_C = re.compile(r"\.(c|h|cpp)(\.h)?:\d+\)$|numba/|_dispatcher")
_FILE_IO = {"read", "write", "pread64", "pwrite64", "fsync", "fdatasync", "lseek", "openat"}


def category(leaf: str) -> str:
    """The row of CATEGORIES a sample whose top frame is `leaf` (py-spy's raw text,
    `function (file:line)`) counts in. Where a frame could go either way it goes to the
    overheads: that makes the floor lower, the best replay faster than it would be."""
    name, _, where = leaf.partition(" (")
    python = ".py" in where or where.startswith("<") or "libpython" in where
    if python or _RUNTIME_C.search(where):
        return INTERPRETER
    if "jpeg" in leaf.lower():
        return JPEG
    if where.startswith("?"):  # code with no file: numba's compiled kernels
        return KERNELS
    if "_multiarray_umath" in where or "/numpy/" in where:
        return NUMPY_WORK if _NUMPY_DATA.search(name) else NUMPY_CALLS
    if "libc.so" in where or "ld-linux" in where:
        return IO_WORK if name in _FILE_IO else LIBC
    if "zstd" in leaf.lower() or "sqlite" in leaf.lower():
        return IO_WORK
    return OTHER_WORK


def shares(raw: Path) -> tuple[Counter, int]:
    """Samples per category among those inside MEASURED, and their count."""
    counts: Counter = Counter()
    for line in raw.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        if not stack or not n.isdigit():
            continue
        frames = stack.split(";")
        if any(MEASURED in frame for frame in frames):
            counts[category(frames[-1])] += int(n)
    return counts, sum(counts.values())


def measured_replays(recording: Path, rounds: int) -> None:
    """`rounds` replays: the frames py-spy's samples are kept in."""
    for _ in range(rounds):
        replay_once(recording)


def unsampled_cost(recording: Path, rounds: int) -> tuple[float, int, float]:
    """CPU seconds of a warm replay (median of `rounds`), its scans, the drive's seconds."""
    replay_once(recording)  # pays the imports and compiles the kernels
    runs = [replay_once(recording) for _ in range(rounds)]
    _, drive_s = input_once(recording)
    return statistics.median(cpu for _, cpu, _ in runs), int(runs[0][2]["scans"]), drive_s


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--recording", type=Path, help="default: the demo survey")
    parser.add_argument("--rounds", type=int, default=3, help="measured replays (default 3)")
    parser.add_argument("--rate", type=int, default=25, help="py-spy samples a second")
    parser.add_argument("--cpu", type=int, help="the CPU to pin to (default: the first allowed)")
    parser.add_argument(
        "--cache", type=Path, default=Path.home() / ".cache" / "treetraits" / "bench"
    )
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    recording = args.recording or demo_recording(args.cache)
    if not recording.is_file():
        parser.error(f"{recording}: no such recording")
    if args.child:
        replay_once(recording)  # pays the imports and compiles the kernels
        measured_replays(recording, args.rounds)
        return
    spy = shutil.which("py-spy") or str(Path(sys.executable).with_name("py-spy"))
    if not Path(spy).is_file():
        parser.error("py-spy not found: pip install py-spy")
    cpu = args.cpu if args.cpu is not None else min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})  # the child and py-spy inherit it
    with tempfile.TemporaryDirectory(prefix="bench-floor-") as work:
        raw = Path(work) / "samples.raw"
        command = [
            spy, "record", "--native", "-r", str(args.rate), "-f", "raw", "-o", str(raw),
            "--", sys.executable, __file__, "--recording", str(recording),
            "--rounds", str(args.rounds), "--child",
        ]  # fmt: skip
        start = time.perf_counter()
        done = subprocess.run(command, capture_output=True, text=True)
        if done.returncode != 0 or not raw.is_file():
            sys.exit(f"py-spy or the replay failed ({done.returncode}):\n{done.stderr[-2000:]}")
        counts, samples = shares(raw)
        sampled_s = time.perf_counter() - start
    if samples == 0:
        sys.exit("no sample inside the measured replays: py-spy saw nothing")
    cpu_s, scans, drive_s = unsampled_cost(recording, args.rounds)
    work_share = sum(counts[row] for row, is_work in CATEGORIES if is_work) / samples
    ms_per_scan = cpu_s / scans * 1e3
    floor_ms = ms_per_scan * work_share
    best = drive_s / (floor_ms / 1e3 * scans)
    print(
        f"{recording.name}: {drive_s:.1f} s, {scans} scans; CPU {cpu}; {samples} samples at "
        f"{args.rate} Hz in {args.rounds} sampled replays ({sampled_s:.0f} s), then "
        f"{args.rounds} unsampled: {cpu_s:.2f} s of CPU a replay (median); "
        f"load {os.getloadavg()[0]:.1f}"
    )
    print("| share of the samples | % |")
    print("|---|---|")
    for row, _ in CATEGORIES:
        print(f"| {row} | {100 * counts[row] / samples:.1f} |")
    print(f"| **work, all of it** | **{100 * work_share:.1f}** |")
    print(
        f"work_share={work_share:.3f} ms_per_scan={ms_per_scan:.1f} "
        f"floor_ms_per_scan={floor_ms:.1f} best_realtime={best:.1f} samples={samples}"
    )


if __name__ == "__main__":
    main()
