"""`treetraits batch`: many recordings replayed in parallel on Dask distributed, their
trees gathered into the season store (docs/season.md).

One task per recording, each the replay of `service/replay.py` into its own run directory
(built aside and moved into place as `treetraits replay` does). The tasks return the run's
trees; only the client writes the season store, so SQLite never has two writers. A task
that fails is reported and the others go on. A recording already in the season, processed
by the same software with the same config (`config_key`), is skipped unless forced.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from datetime import datetime, timezone
from pathlib import Path

from treetraits import __version__
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.errors import SourceError, TreetraitsError
from treetraits.pipeline.trees import Tree
from treetraits.service.config import ServiceConfig

SOFTWARE = f"treetraits {__version__}"
# Bytes read from each end of a recording for its fingerprint: enough to tell two drives
# apart (the first chunk holds the start time and the first sensor data) without reading
# gigabytes on the client.
FINGERPRINT_SPAN = 1 << 20


def config_key(config: ServiceConfig) -> str:
    """sha256 of the config as `config dump` writes it without comments: equal configs,
    whatever file they came from, give one key."""
    from treetraits.service.config import dump_config

    return hashlib.sha256(dump_config(config, comments=False).encode()).hexdigest()


def recording_fingerprint(path: Path) -> str:
    """sha256 over a recording's size and its first and last MiB: the same bytes under
    another name or on another machine give the same fingerprint."""
    path = Path(path)
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        digest.update(str(size).encode())
        digest.update(f.read(FINGERPRINT_SPAN))
        if size > FINGERPRINT_SPAN:
            f.seek(max(FINGERPRINT_SPAN, size - FINGERPRINT_SPAN))
            digest.update(f.read(FINGERPRINT_SPAN))
    return digest.hexdigest()


@dataclass(frozen=True)
class TaskResult:
    """What a worker sends back: the run's summary and trees, or the error."""

    recording: str
    run_dir: str
    ok: bool
    error: str | None = None
    t_start: int | None = None
    summary: dict = field(default_factory=dict)
    trees: list[dict] = field(default_factory=list)  # found and missing, as Tree fields


def replay_task(recording: str, run_dir: str, config: ServiceConfig) -> TaskResult:
    """One recording through `treetraits replay`'s path into `run_dir` (replacing an
    earlier run there). Runs on a Dask worker: a bad input comes back as an error result
    (the message the CLI would print), not as an exception."""
    from treetraits.service.outdir import OutputDir
    from treetraits.service.replay import REPLAY_OUTPUTS, ReplayOptions, open_replay, run_replay

    path = Path(recording)
    try:
        options = ReplayOptions(config=config)
        output = OutputDir(Path(run_dir), REPLAY_OUTPUTS, force=True, inputs=(path,))
        t_start = first_log_time(path)
        inputs = open_replay(path, options)
        try:
            with output as staging:
                report = run_replay(path, staging, options, None, inputs)
        finally:
            inputs.source.close()
    except (TreetraitsError, OSError) as exc:
        return TaskResult(recording, run_dir, False, _describe(exc))
    summary = dict(report.summary)
    summary.pop("calibration", None)
    return TaskResult(
        recording,
        run_dir,
        True,
        None,
        t_start,
        summary,
        [asdict(t) for t in report.trees + report.missing],
    )


def first_log_time(path: Path) -> int:
    """The recording's first message's receive time (ns): when the survey was driven."""
    from treetraits.errors import SourceError
    from treetraits.service.replay import open_input

    source = open_input(path)
    try:
        for _, _, log_time, _ in source.messages:
            return int(log_time)
    finally:
        source.close()
    raise SourceError(f"{path}: no messages (an empty recording is no survey)")


def _describe(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.filename is not None:
        return f"{exc.filename}: {exc.strerror or exc}"
    return str(exc) or type(exc).__name__


@dataclass(frozen=True)
class BatchItem:
    recording: Path
    fingerprint: str
    run_dir: Path


@dataclass
class BatchOutcome:
    """What the batch did, recording by recording (paths as given)."""

    processed: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    damaged: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)  # recording -> error

    def as_json(self) -> dict:
        return {
            "processed": self.processed,
            "skipped": self.skipped,
            "damaged": self.damaged,
            "failed": self.failed,
        }


def plan(
    recordings: Sequence[Path],
    season,
    block: str,
    key: str,
    runs_dir: Path,
    force: bool,
    outcome: BatchOutcome,
) -> list[BatchItem]:
    """The recordings to process: each checked (a missing file fails here, and the others
    go on), and skipped when the season has it from this software and config."""
    items: list[BatchItem] = []
    seen: set[str] = set()
    for path in recordings:
        try:
            refuse_ros_bag(path, "a recording")  # a bag: the import to run first
            fingerprint = recording_fingerprint(path)
        except SourceError as exc:
            outcome.failed[str(path)] = str(exc)
            continue
        except OSError as exc:
            outcome.failed[str(path)] = _describe(exc)
            continue
        if fingerprint in seen:  # the same recording twice on the command line
            outcome.skipped.append(str(path))
            continue
        seen.add(fingerprint)
        if not force and season.processed(block, fingerprint, SOFTWARE, key):
            outcome.skipped.append(str(path))
            continue
        run_dir = runs_dir / f"{Path(path).stem}-{fingerprint[:10]}"
        items.append(BatchItem(Path(path), fingerprint, run_dir))
    return items


def run_batch(
    items: Sequence[BatchItem],
    client,
    config: ServiceConfig,
    on_result: Callable[[BatchItem, TaskResult | None, str | None], None],
) -> None:
    """Submit one task per item to the Dask `client` and hand each result to `on_result`
    as it completes (in the client's thread: the only writer of the season). A task that
    raised (a bug, a worker that died) comes as (item, None, error)."""
    from distributed import as_completed

    futures = {}
    for item in items:
        future = client.submit(
            replay_task,
            str(item.recording.resolve()),
            str(item.run_dir.resolve()),
            config,
            key=f"replay-{item.fingerprint[:16]}-{item.run_dir.name}",
            pure=False,
            retries=0,
        )
        futures[future] = item
    for future in as_completed(futures):
        item = futures.pop(future)
        if future.status == "finished":
            on_result(item, future.result(), None)
        else:
            exc = future.exception()
            on_result(item, None, f"{type(exc).__name__}: {exc}")
        future.release()


def trees_of(result: TaskResult) -> list[Tree]:
    return [Tree(**t) for t in result.trees]


def now_iso() -> str:
    return datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
