"""`treetraits replay`: a recording (or a LiDAR capture with an NMEA log) through the
whole pipeline, faster than real time, writing the run's outputs.

Reads messages in the order they were received, feeds them to `SurveyProcessor`, commits
each scan's observations and trees to the store, rewrites `trees.geojson` and `trees.csv`
atomically every `export_every_s` of recorded time (less often where the exports would
take more than `export_max_share` of the wall time) and at the end. Deterministic: the
same input and options give the same outputs.
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from treetraits.damage import integrity_facts
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration, load_calibration
from treetraits.drivers.rosbag.detect import refuse_ros_bag
from treetraits.drivers.velodyne.sources import open_source
from treetraits.errors import SourceError
from treetraits.files import iso_utc
from treetraits.pipeline.fieldmap import load_field_map, parse_geojson
from treetraits.pipeline.trees import (
    HEIGHT_BOUND_LEGEND,
    WIDTH_BOUND_LEGEND,
    Tree,
    height_bounded,
    marked,
    width_bounded,
)
from treetraits.service.config import ServiceConfig
from treetraits.service.outputs import (
    CSV_NAME,
    GEOJSON_NAME,
    REJECTED_NAME,
    STORE_NAME,
    RunWriter,
    next_export_after,
)
from treetraits.service.survey import make_processor, start_facts


@dataclass(frozen=True)
class ReplayOptions:
    """What to replay with. Calibration and field map: these files when given, else the
    recording's own, else the config's `pipeline.calibration` / `pipeline.field_map`."""

    config: ServiceConfig = field(default_factory=ServiceConfig)
    field_map: Path | None = None
    calibration: Path | None = None
    nmea: Path | None = None  # with a pcap input
    # Seconds added to the NMEA log's UTC to put it on the capture's clock (a logger whose
    # clock was off), or "start": its first epoch at the capture's first packet.
    nmea_offset: float | str = 0.0


@dataclass(frozen=True)
class Input:
    messages: Iterator[tuple[str, bytes, int, int]]  # topic, data, log_time, publish_time
    calibration: dict | None
    field_map: bytes | None
    size_bytes: int
    close: Callable[[], None] = lambda: None  # for an input never read (the output refused)
    # What could not be read, once the messages are: `integrity_facts` of a recording.
    integrity: Callable[[], dict] = lambda: integrity_facts()


def open_input(
    path: Path,
    nmea: Path | None = None,
    nmea_offset: float | str = 0.0,
    gnss_latency_s: float = 0.0,
) -> Input:
    """A recording, or a pcap/pcapng/raw LiDAR capture with an optional NMEA text log
    (`nmea_log_messages` places its sentences on the capture's clock)."""
    refuse_ros_bag(path, "a recording or a LiDAR capture")
    if not Path(path).is_file():
        raise SourceError(f"{path}: no such file (expected a recording or a LiDAR capture)")
    with open(path, "rb") as f:
        is_mcap = f.read(8) == b"\x89MCAP0\r\n"
    if is_mcap:
        if nmea is not None:
            raise SourceError("--nmea goes with a LiDAR capture; a recording has its own GNSS")
        recording = rec.read_recording(path)
        field_map = recording.attachments.get(rec.FIELD_MAP_NAME)

        def messages():
            with recording:
                for m in recording:
                    yield m.topic, m.data, m.log_time, m.publish_time

        return Input(
            messages(),
            recording.metadata.calibration if recording.metadata else None,
            field_map.data if field_map else None,
            path.stat().st_size,
            recording.close,
            lambda: integrity_facts(recording),
        )
    if nmea is not None and not Path(nmea).is_file():
        raise SourceError(f"--nmea {nmea}: no such file")

    # Opened here, not when the messages are first read: a capture or a log that cannot
    # be used stops the replay before anything of an earlier run is touched.
    source = open_source(path)
    packets = iter(source)
    first = next(packets, None)
    gnss = iter(())
    if nmea is not None and first is not None:
        try:
            gnss = nmea_log_messages(nmea, first.t_host, nmea_offset, gnss_latency_s)
        except BaseException:
            source.close()
            raise

    def capture_messages():
        try:
            if first is None:
                return
            lidar = (_packet_message(p) for p in itertools.chain([first], packets))
            yield from heapq.merge(lidar, gnss, key=lambda m: m[2])
        finally:
            source.close()

    return Input(
        capture_messages(),
        None,
        None,
        path.stat().st_size,
        source.close,
        lambda: integrity_facts(truncated=source.stats.truncated),
    )


def _packet_message(packet) -> tuple[str, bytes, int, int]:
    topic = rec.LIDAR_PACKETS if packet.is_data else rec.LIDAR_TELEMETRY
    return topic, packet.payload, packet.t_host, packet.t_host


def nmea_log_messages(
    path: Path, capture_start_ns: int, offset: float | str, latency_s: float
) -> Iterator[tuple[str, bytes, int, int]]:
    """An NMEA log's sentences as recorded messages on the capture's clock. A log has no
    receive times, but its sentences carry their UTC: each is stamped with its epoch's UTC
    (`publish_time`; a log without dates takes the capture's) and received `latency_s`
    later (`log_time`), after `offset` seconds are added ("start": the log's first epoch
    at `capture_start_ns`). A log that ends before the capture starts is refused (here,
    not when the messages are read): its fixes would all come before the first scan and
    place none of them."""
    from treetraits.drivers.gnss.sources import open_gnss_source
    from treetraits.drivers.gnss.times import NmeaClock, sentence_time

    def stamped():
        """(sentence, its epoch's UTC or None before the log's first time)."""
        clock = NmeaClock()
        timed = False
        source = open_gnss_source(path)
        try:
            # No receive times: every sentence is "read" at the capture's start, so the
            # clock dates times of day without a date of their own by the capture's date.
            for sentence in source:
                utc = clock.stamp(sentence.raw, capture_start_ns)
                timed = timed or sentence_time(sentence.raw).tod_ns is not None
                yield sentence.raw, utc if timed else None
        finally:
            source.close()

    first = last = None
    for _, utc in stamped():  # a first pass for the log's span: text, quick to read
        if utc is not None:
            first = utc if first is None else first
            last = utc
    if first is None:
        raise SourceError(f"--nmea {path}: no NMEA sentence with a time in it")
    shift = capture_start_ns - first if offset == "start" else int(float(offset) * 1e9)
    if last + shift < capture_start_ns:
        raise SourceError(
            f"--nmea {path}: the log ends ({iso_utc(last + shift)}) before the capture "
            f"starts ({iso_utc(capture_start_ns)}); if the logger's clock was off, give "
            "--nmea-offset SECONDS, or --nmea-offset start to begin both together"
        )
    latency = int(latency_s * 1e9)

    def messages():
        for raw, utc in stamped():
            # Sentences before the log's first time go with its first epoch.
            placed = (first if utc is None else utc) + shift
            yield rec.GNSS_NMEA, raw, placed + latency, placed

    return messages()


@dataclass(frozen=True)
class ReplayReport:
    summary: dict
    trees: list[Tree]  # found
    out_dir: Path
    missing: list[Tree] = field(default_factory=list)  # field-map trees passed, not found
    rejected: list[Tree] = field(default_factory=list)  # objects that are not trees
    # The mapper's final records of every object reported or rejected (`TrackedTree`,
    # with its cues) and the run's UTM grid (None: no fix): `calibrate classify` reads them.
    mapped: list = field(default_factory=list)
    grid: object = None


# The files a replay writes into its output directory (service/outdir.py owns them).
REPLAY_OUTPUTS = (
    STORE_NAME,
    f"{STORE_NAME}-wal",
    f"{STORE_NAME}-shm",
    CSV_NAME,
    GEOJSON_NAME,
    REJECTED_NAME,
)


@dataclass(frozen=True)
class ReplayInputs:
    """A replay's inputs, opened and checked: what `open_replay` returns."""

    source: Input
    calibration: Calibration
    field_map: list
    # Where the field map came from: "--field-map", "attachment", "config" or "none".
    field_map_source: str = "none"


def _attached_text(path: Path, data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise SourceError(
            f"{path} (attached field map): not UTF-8 text ({exc.reason} at byte {exc.start}); "
            "give --field-map FILE to replay with another"
        ) from None


def open_replay(path: Path, options: ReplayOptions) -> ReplayInputs:
    """Open the input and load the calibration and field map, so that every input error
    comes before an output is touched."""
    cfg = options.config
    source = open_input(path, options.nmea, options.nmea_offset, cfg.localization.gnss_latency_s)
    try:
        if options.calibration is not None:
            calibration = load_calibration(options.calibration)
        elif source.calibration:
            calibration = load_calibration(source.calibration)
        elif cfg.pipeline.calibration:
            calibration = load_calibration(Path(cfg.pipeline.calibration))
        else:
            calibration = Calibration()
        if options.field_map is not None:
            field_map, origin = load_field_map(options.field_map), "--field-map"
        elif source.field_map:
            field_map = parse_geojson(
                _attached_text(path, source.field_map), f"{path} (attached field map)"
            )
            origin = "attachment"
        elif cfg.pipeline.field_map:
            field_map, origin = load_field_map(Path(cfg.pipeline.field_map)), "config"
        else:
            field_map, origin = [], "none"
    except BaseException:
        source.close()
        raise
    return ReplayInputs(source, calibration, field_map, origin)


def run_replay(
    path: Path,
    out_dir: Path,
    options: ReplayOptions,
    progress: Callable[[int], None] | None = None,
    inputs: ReplayInputs | None = None,
    stop: Callable[[], str | None] | None = None,
) -> ReplayReport:
    """Process `path` into `out_dir` (traits.sqlite, trees.geojson, trees.csv), replacing
    an earlier replay's store there. `inputs`: from `open_replay`, when the caller opened
    them before preparing `out_dir` (the CLI, which builds the outputs aside).

    `stop`: asked before each message; a reason ("SIGINT") ends the reading there, and the
    replay finishes as the service does on a signal: the scans read so far are completed,
    committed and exported, and the store's `end` fact says `interrupted (SIGINT)`
    (`complete` when the whole input was read)."""
    cfg = options.config
    inputs = inputs or open_replay(path, options)
    source, calibration, field_map = inputs.source, inputs.calibration, inputs.field_map

    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in (STORE_NAME, f"{STORE_NAME}-wal", f"{STORE_NAME}-shm"):
        (out_dir / stale).unlink(missing_ok=True)  # a replay is a run of its own
    processor = make_processor(cfg, calibration)
    summary = {
        **start_facts(cfg, calibration, str(path)),
        # The field map used, and from where: a recording cut before its attachment
        # replays without one, and says so (treetraits/cli/replay.py).
        "field_map": {"source": inputs.field_map_source, "trees": len(field_map)},
    }
    writer = RunWriter(out_dir, processor, field_map, cfg.output, facts=summary)
    next_export = None  # recorded time (ns)
    export_allowed = 0.0  # time.monotonic()
    stopped_by = None
    try:
        for topic, data, log_time, publish_time in source.messages:
            if stop is not None and (stopped_by := stop()):
                break
            outcomes = processor.feed(topic, data, log_time, publish_time)
            for outcome in outcomes:
                writer.commit(outcome)
            # Exports follow recorded time, held to export_max_share of the wall time (a
            # replay runs several times faster than the drive); which scans they fall
            # after changes no output.
            due = next_export is None or log_time >= next_export
            if outcomes and due and time.monotonic() >= export_allowed:
                started = time.monotonic()
                writer.export()
                finished = time.monotonic()
                next_export = log_time + int(cfg.output.export_every_s * 1e9)
                export_allowed = next_export_after(
                    finished, finished - started, 0.0, cfg.output.export_max_share
                )
            if progress:
                progress(len(data))
        for outcome in processor.finish():
            writer.commit(outcome)
        exported = writer.export()
        trees = exported.found
        mapped = writer.seen()
        summary.update(
            scans=writer.scans,
            trees=len(trees),
            matched=sum(t.field_id is not None for t in trees),
            missing=len(exported.missing),
            rejected=dict(sorted(Counter(t.reason for t in exported.rejected).items())),
            **processor.facts(live=False),
            **source.integrity(),
            # As the service says how its run ended (docs/service.md): the exports were
            # rewritten from the store after the last scan, so they hold what it holds.
            end=f"interrupted ({stopped_by})" if stopped_by else "complete",
            exports="level with the store",
        )
        writer.set_facts(summary)
        # Not in the summary (it is printed): the path for `treetraits report`'s map.
        writer.set_facts({"path": writer.path_utm()})
    finally:
        writer.close()
    return ReplayReport(
        summary,
        trees,
        out_dir,
        exported.missing,
        exported.rejected,
        mapped,
        processor.localizer.grid,
    )


def format_table(trees: list[Tree]) -> str:
    """The per-tree table printed at the end of a replay (missing trees: their field id,
    the map's position and `missing`)."""
    header = (
        f"{'tree':>5} {'field id':>8} {'row':>6} {'easting':>12} {'northing':>13} "
        f"{'width m':>7} {'height m':>8} {'NDVI':>5} {'obs':>4}"
    )
    lines = [header, "-" * len(header)]
    for t in trees:
        east = f"{t.easting:12.2f}" if t.easting is not None else f"{'-':>12}"
        north = f"{t.northing:13.2f}" if t.northing is not None else f"{'-':>13}"
        if t.status == "missing":
            traits = f"{'missing':>27}"
        else:
            ndvi = f"{t.ndvi:5.2f}" if t.ndvi is not None else f"{'-':>5}"
            width = marked(t.width_m, width_bounded(t.width_sides_seen))
            height = marked(t.height_m, height_bounded(t.height_top_seen))
            traits = f"{width:>7} {height:>8} {ndvi} {t.observations:4d}"
        lines.append(
            f"{t.tree_id or '-':>5} {t.field_id or '-':>8} {t.row or '-':>6} {east} {north} "
            f"{traits}"
        )
    found = [t for t in trees if t.status != "missing"]
    if any(width_bounded(t.width_sides_seen) for t in found):
        lines.append(WIDTH_BOUND_LEGEND)
    if any(height_bounded(t.height_top_seen) for t in found):
        lines.append(HEIGHT_BOUND_LEGEND)
    return "\n".join(lines)
