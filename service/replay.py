"""`treetraits replay`: a recording (or a LiDAR capture with an NMEA log) through the
whole pipeline, faster than real time, writing the run's outputs.

Reads messages in the order they were received, feeds them to `SurveyProcessor`, commits
each scan's observations and trees to the store, rewrites `trees.geojson` and `trees.csv`
atomically every `export_every_s` of recorded time and at the end. Deterministic: the same
input and options give the same outputs.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from treetraits import __version__
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration, load_calibration
from treetraits.drivers.records import Tree
from treetraits.drivers.velodyne.sources import open_source
from treetraits.errors import SourceError
from treetraits.pipeline.fieldmap import load_field_map, parse_geojson
from treetraits.service.config import ServiceConfig
from treetraits.service.outputs import STORE_NAME, RunWriter
from treetraits.service.survey import SurveyProcessor


@dataclass(frozen=True)
class ReplayOptions:
    """What to replay with. Calibration and field map: these files when given, else the
    recording's own, else the config's `pipeline.calibration` / `pipeline.field_map`."""

    config: ServiceConfig = field(default_factory=ServiceConfig)
    field_map: Path | None = None
    calibration: Path | None = None
    nmea: Path | None = None  # with a pcap input


@dataclass(frozen=True)
class Input:
    messages: Iterator[tuple[str, bytes, int, int]]  # topic, data, log_time, publish_time
    calibration: dict | None
    field_map: bytes | None
    size_bytes: int


def open_input(path: Path, nmea: Path | None = None) -> Input:
    """A recording, or a pcap/pcapng/raw LiDAR capture with an optional NMEA text log."""
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
        )

    def capture_messages():
        source = open_source(path)
        lidar = (
            (rec.LIDAR_PACKETS if p.is_data else rec.LIDAR_TELEMETRY, p.payload, p.t_host, p.t_host)
            for p in source
        )
        yield from _merge(lidar, _nmea_lines(nmea) if nmea else iter(()))
        source.close()

    return Input(capture_messages(), None, None, path.stat().st_size)


def _nmea_lines(path: Path):
    """An NMEA log has no receive times: sentences keep their order and are stamped from the
    LiDAR stream's clock by the merge (the log is taken to cover the same drive)."""
    from treetraits.drivers.gnss.sources import open_gnss_source

    source = open_gnss_source(path)
    for sentence in source:
        yield rec.GNSS_NMEA, sentence.raw, sentence.t_host, sentence.t_host
    source.close()


def _merge(first, second):
    import heapq

    return heapq.merge(first, second, key=lambda m: m[2])


def make_mapper(config: ServiceConfig, calibration: Calibration):
    """The mapper of `pipeline.method`, with the config's settings."""
    method = config.pipeline.method
    if method.startswith("rph"):
        from treetraits.pipeline.rph import RphMapper, rph_config

        preset = "vlp16" if method == "rph-vlp16" else "shipped"
        return RphMapper(rph_config(preset), calibration=calibration)
    from treetraits.pipeline.mapper import TreeMapper

    return TreeMapper(config.mapper(), calibration)


def make_processor(config: ServiceConfig, calibration: Calibration, lidar_model: str = "auto"):
    """The processing core shared by replay and the live service."""
    return SurveyProcessor(
        make_mapper(config, calibration), calibration, config.localization, lidar_model
    )


@dataclass(frozen=True)
class ReplayReport:
    summary: dict
    trees: list[Tree]  # found
    out_dir: Path
    missing: list[Tree] = field(default_factory=list)  # field-map trees passed, not found
    rejected: list[Tree] = field(default_factory=list)  # objects that are not trees


def run_replay(
    path: Path, out_dir: Path, options: ReplayOptions, progress: Callable[[int], None] | None = None
) -> ReplayReport:
    """Process `path` into `out_dir` (traits.sqlite, trees.geojson, trees.csv)."""
    cfg = options.config
    source = open_input(path, options.nmea)
    if options.calibration is not None:
        calibration = load_calibration(options.calibration)
    elif source.calibration:
        calibration = load_calibration(source.calibration)
    elif cfg.pipeline.calibration:
        calibration = load_calibration(Path(cfg.pipeline.calibration))
    else:
        calibration = Calibration()
    if options.field_map is not None:
        field_map = load_field_map(options.field_map)
    elif source.field_map:
        field_map = parse_geojson(source.field_map.decode(), f"{path} (attached field map)")
    elif cfg.pipeline.field_map:
        field_map = load_field_map(Path(cfg.pipeline.field_map))
    else:
        field_map = []

    out_dir.mkdir(parents=True, exist_ok=True)
    for stale in (STORE_NAME, f"{STORE_NAME}-wal", f"{STORE_NAME}-shm"):
        (out_dir / stale).unlink(missing_ok=True)  # a replay is a run of its own
    processor = make_processor(cfg, calibration)
    summary = {
        "software": f"treetraits {__version__}",
        "input": str(path),
        "method": cfg.pipeline.method,
        "traits": cfg.traits.method,
        "calibration": calibration.to_json(),
    }
    writer = RunWriter(out_dir, processor, field_map, cfg.output, facts=summary)
    next_export = None
    try:
        for topic, data, log_time, publish_time in source.messages:
            outcomes = processor.feed(topic, data, log_time, publish_time)
            for outcome in outcomes:
                writer.commit(outcome)
            # Exports follow recorded time, so a replay is deterministic.
            if outcomes and (next_export is None or log_time >= next_export):
                writer.export()
                next_export = log_time + int(cfg.output.export_every_s * 1e9)
            if progress:
                progress(len(data))
        for outcome in processor.finish():
            writer.commit(outcome)
        exported = writer.export()
        trees = exported.found
        summary.update(
            scans=writer.scans,
            trees=len(trees),
            matched=sum(t.field_id is not None for t in trees),
            missing=len(exported.missing),
            rejected=dict(sorted(Counter(t.reason for t in exported.rejected).items())),
            world_frame=processor.world_frame,
            utm_zone=processor.localizer.grid.name if processor.localizer.grid else None,
            scans_without_pose=processor.stats.scans_without_pose,
            scans_without_heading=processor.stats.scans_without_heading,
            fixes=processor.stats.fixes,
            frames=processor.stats.frames,
        )
        writer.set_facts(summary)
    finally:
        writer.close()
    return ReplayReport(summary, trees, out_dir, exported.missing, exported.rejected)


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
            traits = f"{t.width_m:7.2f} {t.height_m:8.2f} {ndvi} {t.observations:4d}"
        lines.append(
            f"{t.tree_id or '-':>5} {t.field_id or '-':>8} {t.row or '-':>6} {east} {north} "
            f"{traits}"
        )
    return "\n".join(lines)
