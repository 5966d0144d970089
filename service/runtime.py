"""The service's main loop: `treetraits run` (map and store) and `treetraits record`.

`Service(cfg).run()`:

1. opens the run directory (`output.dir/runs/<UTC start>/`, `runs/latest` -> it), the
   store, the recorder when recording, and every enabled source (a LiDAR port that cannot
   be bound, or a bad calibration, ends the start with a clear error; a serial device or a
   camera that is not there yet is retried in the background);
2. tells systemd READY=1, then takes messages from the queues oldest first (each queue's
   head, by `log_time`), feeds them to `SurveyProcessor`, commits every processed scan,
   writes them to the recorder, exports every `output.export_every_s`, sends STATUS= every
   `service.status_every_s` and WATCHDOG=1 while the loop goes round;
3. on SIGTERM/SIGINT closes the sources, drains what is queued (at most `DRAIN_S`),
   commits, exports, closes store and recorder, STOPPING=1, and returns 0 (a second
   signal exits at once with 128 + signal number).

A full disk never stops the mapping: a scan the store cannot commit is rolled back and
counted, the status says DEGRADED with the file and the error, and later scans try again
(trees are rewritten whole each time they change, so the store catches up once space is
freed). The recorder is closed at its first write error and stays off for the run. See
docs/service.md.
"""

from __future__ import annotations

import contextlib
import gc
import importlib
import json
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration
from treetraits.drivers.gnss.times import NmeaClock
from treetraits.drivers.velodyne.packet import lidar_publish_time
from treetraits.errors import ConfigError, TreetraitsError
from treetraits.files import utc_stamp
from treetraits.service.config import ServiceConfig, dump_config
from treetraits.service.health import assess, status_line
from treetraits.service.notify import Notifier
from treetraits.service.outputs import OutputError, RunWriter, next_export_after
from treetraits.service.preflight import check_start
from treetraits.service.survey_start import SurveyStart
from treetraits.service.workers import (
    BoundedQueue,
    BridgeWorker,
    CameraWorker,
    GnssWorker,
    JackalWorker,
    LidarWorker,
    Message,
    Worker,
)

log = logging.getLogger("treetraits.service")

DRAIN_S = 3.0  # at shutdown, queued items are processed for at most this long
JOIN_S = 1.0  # then each receive thread gets this long to end
IDLE_WAIT_S = 0.1  # with every queue empty, the loop sleeps at most this long
BATCH = 256  # items between two looks at the clock (exports, status, watchdog)
GATHER_S = 0.01  # once woken from idle, the loop waits this long for more items
# What the pipeline imports where it is used (first scans would wait for them).
PIPELINE_IMPORTS = (
    "cv2",
    "filterpy.kalman",
    "scipy.ndimage",
    "scipy.optimize",
    "scipy.spatial",
    "treetraits.pipeline.fusion",
)
# Where the modules with compiled kernels are looked for (treetraits.jit.kernel_modules).
KERNEL_PACKAGES = ("treetraits.drivers", "treetraits.pipeline")


def load_pipeline() -> None:
    """Import what the pipeline imports where it is used and every module with compiled
    kernels, and compile each kernel or load it from numba's cache (treetraits.jit). The
    service does it before READY; `make install` once as the service's user, to fill the
    unit's cache."""
    from treetraits.jit import compile_all, kernel_modules

    for module in (*PIPELINE_IMPORTS, *kernel_modules(*KERNEL_PACKAGES)):
        importlib.import_module(module)
    compile_all()


@dataclass
class Counters:
    """The loop's own counts, beside the workers'."""

    messages: int = 0
    scans: int = 0
    store_failures: int = 0
    processing_errors: int = 0  # messages the pipeline raised on (logged, then skipped)
    export_failures: int = 0
    recorded: int = 0
    problems: dict[str, str] = field(default_factory=dict)  # "store", "export", ... -> text


def new_run_dir(root: Path, stamp: str) -> Path:
    """`root/runs/<stamp>` (with -2, -3, ... when a restart falls in the same second) and
    `root/runs/latest` pointing at it, replaced atomically (symlink beside it, rename)."""
    runs = root / "runs"
    runs.mkdir(parents=True, exist_ok=True)
    run = runs / stamp
    n = 1
    while True:
        try:
            run.mkdir()
            break
        except FileExistsError:
            n += 1
            run = runs / f"{stamp}-{n}"
    link = runs / f".latest.{os.getpid()}"
    with contextlib.suppress(FileNotFoundError):
        link.unlink()
    link.symlink_to(run.name)
    os.replace(link, runs / "latest")
    return run


class Service:
    """The onboard service. `process=False` only records (`treetraits record`)."""

    def __init__(
        self,
        cfg: ServiceConfig,
        *,
        process: bool = True,
        record_path: Path | None = None,
        config_path: Path | None = None,
        notifier: Notifier | None = None,
    ):
        self.cfg = cfg
        self.process = process
        self.record_path = record_path
        self.config_path = config_path
        self.notifier = notifier or Notifier()
        self.counters = Counters()
        self.run_dir: Path | None = None
        self.writer: RunWriter | None = None
        self.processor = None
        self.recorder = None
        self.workers: list[Worker] = []
        self._nmea_clock = NmeaClock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._signals = 0
        self._stopped_by: str | None = None  # "SIGTERM", "SIGINT": the signal that stopped it
        self._export_failed = False  # the last export did not go through
        self._shed_reported = 0  # scans_shed as of the last STATUS
        self._unprocessed = 0  # queued items the shutdown's drain limit left
        # A video file played as the camera starts with the first LiDAR packet: a survey
        # played into the service then gets frames where its own were (PacedVideo).
        self._video_playing = False
        self._survey_start = SurveyStart()  # when the survey's first firing was, for it

    # --- start ---------------------------------------------------------------------------

    def _make_workers(self) -> list[Worker]:
        cfg, q = self.cfg, self.cfg.queues
        workers: list[Worker] = []
        if cfg.lidar.enabled:
            workers.append(LidarWorker(cfg.lidar, self._queue("lidar", q.lidar_packets)))
        if cfg.camera.enabled:
            workers.append(CameraWorker(cfg.camera, self._queue("camera", q.camera_frames)))
        if cfg.gnss.enabled:
            workers.append(GnssWorker(cfg.gnss, self._queue("gnss", q.gnss_sentences)))
        if cfg.wheels.enabled:
            kind = JackalWorker if cfg.wheels.kind == "jackal" else BridgeWorker
            workers.append(kind(cfg.wheels, self._queue("wheels", q.wheel_chunks)))
        return workers  # at least one: check_start refuses a config without a sensor

    def _queue(self, name: str, capacity: int) -> BoundedQueue:
        return BoundedQueue(name, capacity, self._wake)

    def _open_recorder(self, calibration: Calibration, field_map: bytes | None) -> None:
        from treetraits.drivers.recording.rotation import RotatingRecorder

        path = self.record_path
        if path is None:
            directory = Path(self.cfg.record.dir)
            directory.mkdir(parents=True, exist_ok=True)
            path = directory / f"{self._stamp}.mcap"
        path.parent.mkdir(parents=True, exist_ok=True)
        self.recorder = RotatingRecorder(
            path,
            max_bytes=self.cfg.record.max_file_mb * 1024 * 1024,
            chunk_bytes=self.cfg.record.chunk_kb * 1024,
            fsync_every_s=self.cfg.record.fsync_every_s,
            calibration=calibration.to_json(),
            field_map=field_map,
        )
        log.info("recording to %s", path)

    def start(self) -> None:
        """Everything up to READY=1. TreetraitsError for what the user must fix.

        The checks `config check` makes come first (`check_start`), then the devices are
        opened; the run directory is made last, so a start that fails makes none and
        leaves `runs/latest` where it was."""
        self._stamp = utc_stamp()
        recording = self.cfg.record.enabled or self.record_path is not None
        inputs = check_start(
            self.cfg,
            process=self.process,
            record=recording and self.record_path is None,
        )
        calibration = inputs.calibration
        if calibration.describe_defaults():
            log.warning("%s", calibration.describe_defaults())
        self.workers = self._make_workers()
        try:
            for worker in self.workers:
                # Only a LiDAR port we cannot bind is fatal: a serial device or a camera
                # may be plugged in later.
                worker.open(retry=not isinstance(worker, LidarWorker))
            if recording:  # refused when its file exists (exit 4): before the run dir
                self._open_recorder(calibration, inputs.field_map_bytes)
            if self.process:
                self._open_run(calibration, inputs.field_map)
        except BaseException:
            for worker in self.workers:
                worker.stop()
            self._close_outputs()
            raise
        # What is in memory now (modules, the field map, the config) lives as long as the
        # run: left out of the collector's full passes, which otherwise walk it each time
        # (docs/performance.md, "The service").
        gc.collect()
        gc.freeze()
        for worker in self.workers:
            worker.start()
        if not self.cfg.lidar.enabled:  # no packet will come to start the video
            self._play_videos()

    def _anchor_videos(self, first_firing_ns: int) -> None:
        for worker in self.workers:
            if isinstance(worker, CameraWorker):
                worker.anchor_video(first_firing_ns)

    def _play_videos(self, start_ns: int | None = None) -> None:
        self._video_playing = True
        for worker in self.workers:
            if isinstance(worker, CameraWorker):
                worker.play_video(start_ns)

    def _open_run(self, calibration: Calibration, field_map: list) -> None:
        from treetraits.service.survey import make_processor, start_facts

        self.processor = make_processor(self.cfg, calibration, self.cfg.lidar.model, live=True)
        # Before READY: the first scans would otherwise wait for the imports (seconds:
        # filterpy's pulls in scipy.stats) and longer for a kernel to compile, a backlog
        # past max_backlog_s.
        load_pipeline()
        if self.cfg.service.max_backlog_s > 0:
            limit_ns = round(self.cfg.service.max_backlog_s * 1e9)
            # Items carry their receive time on the host's clock (`Message.log_time`).
            self.processor.behind = lambda newest: time.time_ns() - newest > limit_ns
        try:
            self.run_dir = new_run_dir(Path(self.cfg.output.dir), self._stamp)
        except OSError as exc:
            raise ConfigError(
                f"output.dir: cannot make a run directory in {self.cfg.output.dir} "
                f"({exc.strerror or exc})"
            ) from exc
        self.writer = RunWriter(
            self.run_dir,
            self.processor,
            field_map,
            self.cfg.output,
            facts={
                **start_facts(self.cfg, calibration, "live"),
                "started": self._stamp,
                "config": dump_config(self.cfg, comments=False),
                # Until the run ends cleanly: a run killed outright stays "running".
                "end": "running",
            },
        )
        log.info("run directory %s", self.run_dir)

    # --- the loop ------------------------------------------------------------------------

    def run(self) -> int:
        """Start, loop until a signal, shut down. The exit status."""
        self.start()
        self._install_signals()
        now = time.monotonic()
        status = self._status(now)
        self.notifier.ready(status)
        log.info("ready: %s", status)
        next_status = now + self.cfg.service.status_every_s
        next_export = now + self.cfg.output.export_every_s
        while not self._stop.is_set():
            handled = self._handle_batch(BATCH)
            now = time.monotonic()
            if self.writer is not None and now >= next_export:
                self._export()
                finished = time.monotonic()
                out = self.cfg.output
                next_export = next_export_after(
                    finished, finished - now, out.export_every_s, out.export_max_share
                )
            if now >= next_status:
                self._report(now)
                next_status = now + self.cfg.service.status_every_s
            # The loop came round: it handled items, or found every queue empty.
            self.notifier.watchdog(progressed=True)
            if not handled:
                self._wake.wait(IDLE_WAIT_S)
                self._wake.clear()
                # Let a few more items in before going round: the LiDAR alone sends 754
                # packets/s, and a wake-up per packet costs more than handling it.
                time.sleep(GATHER_S)
        return self._shutdown()

    def _next_message(self) -> Message | None:
        """The oldest item at the head of any queue (receive order as far as practical)."""
        best, best_time = None, None
        for worker in self.workers:
            t = worker.queue.head_time()
            if t is not None and (best_time is None or t < best_time):
                best, best_time = worker.queue, t
        return best.pop() if best is not None else None

    def _handle_batch(self, limit: int, deadline: float | None = None) -> int:
        handled = 0
        while handled < limit:
            if deadline is not None and time.monotonic() >= deadline:
                break
            message = self._next_message()
            if message is None:
                break
            self._handle(message)
            handled += 1
        return handled

    def _handle(self, m: Message) -> None:
        self.counters.messages += 1
        if m.topic == rec.LIDAR_PACKETS and self._survey_start.add(m.data, m.log_time):
            start = self._survey_start.first_firing_ns
            self._anchor_videos(start)
            if not self._video_playing:
                self._play_videos(start)
        if self.recorder is not None:
            self._record(m)
        if self.processor is not None:
            try:
                outcomes = self.processor.feed(m.topic, m.data, m.log_time, m.publish_time)
            except Exception:  # a pipeline bug: keep the sensors and the store going
                self.counters.processing_errors += 1
                if self.counters.processing_errors <= 3:
                    log.exception("processing a %s message failed; going on", m.topic)
                return
            for outcome in outcomes:
                self._commit(outcome)

    def _record(self, m: Message) -> None:
        publish = m.publish_time
        if m.topic in (rec.LIDAR_PACKETS, rec.LIDAR_TELEMETRY):
            publish = lidar_publish_time(m.data, m.log_time)
        elif m.topic == rec.GNSS_NMEA:
            publish = self._nmea_clock.stamp(m.data, m.log_time)  # the epoch's UTC
        try:
            self.recorder.write(m.topic, m.data, m.log_time, publish)
        except (TreetraitsError, OSError) as exc:
            self._fail_recorder(exc)
            return
        self.counters.recorded += 1

    def _fail_recorder(self, exc: Exception) -> None:
        text = f"recording stopped: {exc}"
        log.error("%s; mapping goes on, the files written so far stay readable", text)
        self.counters.problems["recorder"] = text
        recorder, self.recorder = self.recorder, None
        with contextlib.suppress(Exception):  # the disk that failed may fail the close too
            recorder.close()

    def _commit(self, outcome) -> None:
        if not self._attempt(
            "store",
            lambda: self.writer.commit(outcome),
            "; the scan is rolled back, later scans try again",
        ):
            self.counters.store_failures += 1
            return
        self.counters.scans += 1

    def _export(self) -> None:
        self._export_failed = not self._attempt("export", self.writer.export)
        if self._export_failed:
            self.counters.export_failures += 1

    def end_state(self) -> str:
        """How the run ended, as the store's `end` fact and the summary say it:
        "interrupted (SIGTERM)" after a signal, "stopped" when asked from the code; a run
        killed outright keeps the "running" it started with."""
        return f"interrupted ({self._stopped_by})" if self._stopped_by else "stopped"

    def _attempt(self, kind: str, action, consequence: str = "") -> bool:
        """Run an output step; an OutputError is logged once while it lasts and shown in
        the status (`problems[kind]`) until the step works again."""
        try:
            action()
        except OutputError as exc:
            if kind not in self.counters.problems:
                log.error("%s%s", exc, consequence)
            self.counters.problems[kind] = str(exc)
            return False
        if self.counters.problems.pop(kind, None) is not None:
            log.warning("%s: %s works again", self.writer.out_dir, kind)
        return True

    # --- status ----------------------------------------------------------------------------

    def _numbers(self) -> dict[str, int]:
        """The STATUS counters. The LiDAR's intake and losses always (the packets are
        what must not be lost); other sensors' queue drops, foreign datagrams and errors
        only when there are some, so the line stays readable in `systemctl status`."""
        numbers: dict[str, int] = {}
        if self.writer is not None:
            numbers["scans"] = self.counters.scans
            numbers["trees"] = len(self.writer.reported())
        if self.recorder is not None or "recorder" in self.counters.problems:
            numbers["recorded"] = self.counters.recorded
        for worker in self.workers:
            if isinstance(worker, LidarWorker):
                counts = worker.counters()
                numbers["lidar_packets"] = counts["items"]
                numbers["dropped_lidar"] = counts["dropped"]
                numbers["kernel_drops"] = counts.get("kernel_drops", 0)
                if counts.get("foreign"):
                    numbers["foreign"] = counts["foreign"]
        for worker in self.workers:
            if not isinstance(worker, LidarWorker) and worker.queue.dropped:
                numbers[f"dropped_{worker.queue.name}"] = worker.queue.dropped
        if self.counters.processing_errors:
            numbers["errors"] = self.counters.processing_errors
        if self.processor is not None and self.processor.stats.scans_shed:
            numbers["scans_shed"] = self.processor.stats.scans_shed
        return numbers

    def _status(self, now: float) -> str:
        health = assess((w.state() for w in self.workers), now, self.counters.problems.values())
        return status_line(health, self._numbers())

    def _report(self, now: float) -> None:
        if self.processor is not None:
            shed = self.processor.stats.scans_shed - self._shed_reported
            self._shed_reported += shed
            if shed:
                scans = "scan" if shed == 1 else "scans"
                self.counters.problems["processing"] = (
                    f"behind its sensors: {shed} {scans} not mapped since the last status"
                )
            else:
                self.counters.problems.pop("processing", None)
        line = self._status(now)
        self.notifier.status(line)
        if line.startswith("DEGRADED"):
            log.warning("%s", line)
        else:
            log.info("%s", line)

    # --- stop ------------------------------------------------------------------------------

    def _install_signals(self) -> None:
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._on_signal)

    def _on_signal(self, signum, frame) -> None:
        self._signals += 1
        if self._signals > 1:
            os._exit(128 + signum)  # asked twice: no more flushing
        self._stopped_by = signal.Signals(signum).name
        self._stop.set()
        self._wake.set()

    def _shutdown(self) -> int:
        begun = time.monotonic()
        self.notifier.stopping(self._status(begun))
        log.info("stopping: closing the sources, draining the queues")
        for worker in self.workers:
            worker.stop()
        left = sum(len(w.queue) for w in self.workers)
        self._handle_batch(left, deadline=begun + DRAIN_S)
        unhandled = sum(len(w.queue) for w in self.workers)
        self._unprocessed = unhandled  # said in the run facts and the summary
        if unhandled:
            log.warning("stopping: %d queued items left unprocessed (drain limit)", unhandled)
        if self.processor is not None:
            # The last partial scan and those waiting for poses: normally a few, quick.
            try:
                outcomes = self.processor.finish()
            except Exception:
                log.exception("processing the last scans failed")
                outcomes = []
            for outcome in outcomes:
                self._commit(outcome)
        self._close_outputs()
        for worker in self.workers:
            if not worker.join(JOIN_S):
                log.warning("%s: receive thread still busy at exit", worker.name)
        summary = dict(self._numbers(), messages=self.counters.messages)
        summary["end"] = self.end_state()
        summary["unprocessed_at_stop"] = unhandled
        summary["store_failures"] = self.counters.store_failures
        summary["run_s"] = round(time.monotonic() - begun, 2)
        log.info("stopped: %s", json.dumps(summary))
        return 0

    def _close_outputs(self) -> None:
        if self.writer is not None:
            if self.processor is not None:
                self._export()
                self._set_final_facts()
            try:
                self.writer.close()
            except OutputError as exc:
                log.error("%s", exc)
        if self.recorder is not None:
            try:
                self.recorder.close()
            except (TreetraitsError, OSError) as exc:
                log.error("recording not closed cleanly: %s", exc)
            else:
                log.info("recording closed: %s", ", ".join(map(str, self.recorder.files)))

    def _set_final_facts(self) -> None:
        facts = {
            "scans": self.counters.scans,
            **self.processor.facts(live=True),
            "stopped": utc_stamp(),
            "end": self.end_state(),
            # Items still queued when the drain limit ran out: received, never processed
            # nor recorded (a loop that lagged its sensors, e.g. on a loaded machine).
            "unprocessed_at_stop": self._unprocessed,
            # The exports were rewritten from the store's trees after the last scan, so
            # they hold what it holds; if that failed they lag it, and say so here.
            "exports": "behind the store" if self._export_failed else "level with the store",
        }
        try:
            self.writer.set_facts(facts)
        except OutputError as exc:
            log.error("%s", exc)
