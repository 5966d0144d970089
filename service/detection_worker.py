"""A scan's detection beside the mapping of the scans before it (`[pipeline] workers = 2`,
docs/performance.md): on a second thread, or in a second process.

Detection (crop, mixed returns, terrain, NDVI, voxels, clustering, each cluster's
measurements) needs no track: `TreeMapper.detect_scan` reads the mapper's settings and
calibration only. On a thread its compiled kernels release the GIL
(`treetraits.jit.kernel`), so they run beside the caller's reading, batching, de-skewing
and tracking, while its Python and NumPy calls on small arrays wait for the caller's. In
a process (`detection_process`) nothing waits: the scan and its camera frame go to it
pickled, and the detected scan comes back. Scans are handed back in the order they came,
so the mapper sees them as the sequential path would and the outputs are the same bytes.
"""

from __future__ import annotations

import signal
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import Executor, Future, ProcessPoolExecutor, ThreadPoolExecutor
from multiprocessing import get_context
from typing import Any, Generic, TypeVar

from treetraits.drivers.records import Frame, Scan

Context = TypeVar("Context")


class DetectionWorker(Generic[Context]):
    """Detects scans one at a time on its own thread (or `executor`'s one worker);
    `depth` scans at most are waiting (detected or not), each with the caller's `context`
    (what mapping it needs)."""

    def __init__(
        self,
        detect: Callable[[Scan, Frame | None], Any],
        depth: int = 2,
        executor: Executor | None = None,
    ):
        self._detect = detect
        self._pool = executor or ThreadPoolExecutor(
            max_workers=1, thread_name_prefix="treetraits-detect"
        )
        self._waiting: deque[tuple[Future, Context]] = deque()
        self.depth = depth

    @property
    def full(self) -> bool:
        return len(self._waiting) >= self.depth

    def submit(self, scan: Scan, frame: Frame | None, context: Context) -> None:
        self._waiting.append((self._pool.submit(self._detect, scan, frame), context))

    def done(self, wait: bool = False, at_least: int = 0) -> Iterator[tuple[Any, Context]]:
        """The detected scans in the order they came, with their contexts: those done
        (all of them with `wait`; the first `at_least` waited for). A detection's
        exception is raised here, in the caller's thread."""
        taken = 0
        while self._waiting:
            future, context = self._waiting[0]
            if not (wait or taken < at_least or future.done()):
                return
            detected = future.result()
            self._waiting.popleft()
            taken += 1
            yield detected, context

    def close(self) -> None:
        """Stops the worker once the scans waiting are detected (they are dropped)."""
        self._pool.shutdown(wait=True, cancel_futures=True)
        self._waiting.clear()


# The detecting process's own mapper: its settings and calibration, no tracks.
_detector = None


def _start_detector(config, calibration, timing: bool) -> None:
    global _detector
    from treetraits.pipeline.mapper import TreeMapper

    # The caller ends it (`close`, or its own exit closing the pipe): a SIGTERM to the
    # service's whole cgroup (`systemctl stop`) or a Ctrl-C to the terminal's process
    # group must not kill it before the caller has mapped the scans it holds.
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _detector = TreeMapper(config, calibration, timing=timing)


def _detect_in_process(scan: Scan, frame: Frame | None):
    return _detector.detect_scan(scan, frame)


def detection_process(mapper, depth: int = 2) -> DetectionWorker:
    """A `DetectionWorker` whose detection runs in a second process (spawned: Open3D's
    threads and fork do not mix) with a mapper of `mapper`'s settings and calibration."""
    pool = ProcessPoolExecutor(
        max_workers=1,
        mp_context=get_context("spawn"),
        initializer=_start_detector,
        initargs=(mapper.config, mapper.calibration, mapper.timing),
    )
    return DetectionWorker(_detect_in_process, depth, executor=pool)
