"""`treetraits inspect`'s pure part: pick one scan of a LiDAR input, and turn a scan's
detection into one row per object (cluster) with its cues, their contributions and its
verdict, plus the summary line. No drawing, no printing (`treetraits/cli/inspect.py`)."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from treetraits.errors import ConfigError

if TYPE_CHECKING:
    from treetraits.drivers.records import Scan
    from treetraits.pipeline.detection import Cluster

# An object whose returns span more than this vertically (top minus lowest return), of
# at least TALL_RETURNS returns, is "tall" in the summary: a tree's crown cross-section,
# a wall, a person. Fewer returns give the texture too few triples to weigh in full (a
# far crown's sparse top of 20 dark returns shows nothing either way).
TALL_EXTENT_M = 1.0
TALL_RETURNS = 50
# A tree's shape with no evidence either way in this scan (`Evidence.total` 0: nothing
# measured, or dark echoes): its track decides over its scans.
UNDECIDED = "undecided"


def shown_verdict(cluster: Cluster) -> str:
    """The verdict an operator reads: `undecided` where the shape is a tree's but this
    scan shows no evidence of vegetation (the mapper keeps it as a tree's piece and the
    track decides), else the cluster's own."""
    if cluster.verdict == "tree" and not cluster.evidence.vegetation:
        return UNDECIDED
    return cluster.verdict


@dataclass(frozen=True)
class Picked:
    """The scan picked, its number among the input's full scans and its start in seconds
    from the first scan's start."""

    scan: Scan
    number: int
    t_s: float


def scan_mid_s(scan: Scan) -> float:
    return (scan.t_start + scan.t_end) / 2e9


def pick_scan(scans: Iterable[Scan], number: int | None = None, time_s: float | None = None):
    """The `number`-th full scan (0-based; `complete` scans only), or the full scan whose
    middle is nearest `time_s` seconds after the first scan's start (partial scans
    included in that clock: the input's start). Neither: the first full scan. Raises
    ConfigError naming how many full scans there are when there is no such scan."""
    if number is not None and number < 0:
        raise ConfigError(f"--scan {number}: scans are numbered from 0")
    start = None
    full = -1
    best: Picked | None = None
    for scan in scans:
        if start is None:
            start = scan.t_start / 1e9
        if not scan.complete:
            continue
        full += 1
        t = scan_mid_s(scan) - start
        if time_s is None:
            if full == (number or 0):
                return Picked(scan, full, t)
            continue
        if best is None or abs(t - time_s) < abs(best.t_s - time_s):
            best = Picked(scan, full, t)
        elif t > time_s:
            return best  # the scans come in time order: later ones are farther
    if best is not None:
        return best
    count = full + 1
    if count == 0:
        raise ConfigError("the input holds no full scan (a whole rotation) to inspect")
    raise ConfigError(
        f"--scan {number}: the input holds {count} full scan(s), numbered 0 to {count - 1}"
    )


def _num(value: float, digits: int = 3) -> float | None:
    """A float for JSON: rounded, NaN and infinities as None."""
    value = float(value)
    return round(value, digits) if math.isfinite(value) else None


def object_row(index: int, cluster: Cluster, lidar_xyz: np.ndarray) -> dict[str, Any]:
    """One object's row: where it is, its size, its cues and their contributions, its
    verdict. Lengths in metres in `base` (z up); NaN (not measured) as None."""
    points = np.asarray(cluster.points, dtype=float)
    top, bottom = (float(points[:, 2].max()), float(points[:, 2].min())) if len(points) else (0, 0)
    c = np.asarray(cluster.centroid, dtype=float)
    shape, cues, ev = cluster.shape, cluster.cues, cluster.evidence
    return {
        "id": index,
        "x_m": _num(c[0], 2),
        "y_m": _num(c[1], 2),
        "z_m": _num(c[2], 2),
        "range_m": _num(np.linalg.norm(c - lidar_xyz), 2),
        "returns": len(points),
        "voxels": int(cluster.num_points),
        "height_m": _num(shape.height_m, 2),
        "base_m": _num(shape.base_m, 2),
        "extent_m": _num(top - bottom, 2),
        "width_m": _num(shape.width_m, 2),
        "aspect": _num(shape.aspect, 2),
        "roughness_m": _num(shape.roughness, 4),
        "top": cluster.top_view,
        "verdict": shown_verdict(cluster),
        "vegetation": bool(ev.vegetation),
        "evidence": _num(ev.total),
        "measured": list(ev.measured),
        "texture_m": _num(cues.texture_m, 4),
        "texture_triples": int(cues.texture_triples),
        "texture_e": _num(ev.texture),
        "planar_share": _num(cues.planar_share),
        "planar_patches": int(cues.planar_patches),
        "planar_e": _num(ev.planar),
        "ndvi": _num(cues.ndvi),
        "ndvi_share": _num(cues.ndvi_share),
        "ndvi_e": _num(ev.ndvi),
        "intensity": _num(cues.intensity, 1),
        "intensity_e": _num(ev.intensity),
    }


def object_rows(
    clusters: list[Cluster], T_base_lidar: np.ndarray, tracks: list[Track] | None = None
) -> list[dict[str, Any]]:
    """Each cluster's row; with `tracks` (one per cluster, `track_verdicts`), the track
    it went to and what its scans so far make of it."""
    lidar = np.asarray(T_base_lidar, dtype=float)[:3, 3]
    rows = [object_row(i, c, lidar) for i, c in enumerate(clusters)]
    for row, track in zip(rows, tracks or [], strict=False):
        row["track"] = track.tree_id
        row["track_scans"] = track.scans
        row["track_verdict"] = track.kind
    return rows


@dataclass(frozen=True)
class Track:
    """The track a cluster went to and its verdict over its scans so far."""

    tree_id: int
    scans: int  # the scans it was seen in
    kind: str  # "tree" or the reason it is not one (`pipeline.classify.REASONS`)


# A track seen in fewer scans than the output's `min_observations`: not in the map (yet).
UNCONFIRMED = "unconfirmed"


def track_verdicts(
    scans: Iterable[Scan], number: int, mapper, min_observations: int
) -> tuple[list[Cluster], list[Track]]:
    """Every full scan up to the `number`-th through the mapper (no poses: the mapper's
    own frame), as the map is made: the picked scan's clusters and, for each, its track's
    verdict by the scans so far: what the map would hold of it now (`unconfirmed`: seen
    in fewer than `min_observations` scans, which the outputs leave out)."""
    full = -1
    for scan in scans:
        if not scan.complete:
            continue
        full += 1
        result = mapper.process(scan)
        if full == number:
            trees = {t.tree_id: t for t in mapper.trees()}
            tracks = []
            for found in result.clusters:
                tree = trees.get(found.tree_id)
                seen = tree.observations if tree is not None else 0
                kind = tree.kind if seen >= min_observations else UNCONFIRMED
                tracks.append(Track(found.tree_id, seen, kind))
            return [found.cluster for found in result.clusters], tracks
    raise ConfigError(f"--scan {number}: the input holds {full + 1} full scan(s)")


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """How many objects, how many judged vegetation, and of those spanning more than
    TALL_EXTENT_M vertically with TALL_RETURNS returns or more how many are vegetation
    (share None when there are none)."""
    tall = [
        r for r in rows if (r["extent_m"] or 0.0) > TALL_EXTENT_M and r["returns"] >= TALL_RETURNS
    ]
    tall_vegetation = sum(r["vegetation"] for r in tall)
    verdicts: dict[str, int] = {}
    for r in rows:
        verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
    tracked = {r["track"]: r["track_verdict"] for r in rows if "track" in r}
    return {
        "objects": len(rows),
        "vegetation": sum(r["vegetation"] for r in rows),
        "trees": verdicts.get("tree", 0),
        # The tracks of this scan's objects that are trees by their scans so far (None:
        # tracks not followed, --no-tracks).
        "track_trees": sum(kind == "tree" for kind in tracked.values()) if tracked else None,
        "verdicts": dict(sorted(verdicts.items())),
        "tall_extent_m": TALL_EXTENT_M,
        "tall_returns": TALL_RETURNS,
        "tall": len(tall),
        "tall_vegetation": tall_vegetation,
        "tall_vegetation_share": round(tall_vegetation / len(tall), 3) if tall else None,
    }


# The table's columns: (header, row key, format). Contributions follow their cue.
COLUMNS = (
    ("id", "id", "{:>3}"),
    ("x m", "x_m", "{:>6.2f}"),
    ("y m", "y_m", "{:>6.2f}"),
    ("range", "range_m", "{:>5.1f}"),
    ("returns", "returns", "{:>7}"),
    ("height", "height_m", "{:>6.2f}"),
    ("extent", "extent_m", "{:>6.2f}"),
    ("width", "width_m", "{:>5.2f}"),
    ("top", "top", "{:<6}"),
    ("verdict", "verdict", "{:<9}"),
    ("veg", "vegetation", "{:<3}"),
    ("evid", "evidence", "{:>+5.2f}"),
    ("texture", "texture_m", "{:>7.3f}"),
    ("tex+", "texture_e", "{:>+5.2f}"),
    ("planar", "planar_share", "{:>6.2f}"),
    ("pla+", "planar_e", "{:>+5.2f}"),
    ("ndvi", "ndvi", "{:>5.2f}"),
    ("ndv+", "ndvi_e", "{:>+5.2f}"),
    ("inten", "intensity", "{:>5.0f}"),
    ("int+", "intensity_e", "{:>+5.2f}"),
    ("track", "track", "{:>5}"),
    ("scans", "track_scans", "{:>5}"),
    ("track is", "track_verdict", "{:<9}"),
)


def _cell(fmt: str, value: Any) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    if value is None:
        return "-"  # not measured (NaN)
    return fmt.format(value)


def format_table(rows: list[dict[str, Any]]) -> str:
    """The per-object table (`treetraits inspect` without --json)."""
    cells = [[h for h, _, _ in COLUMNS]]
    for r in rows:
        cells.append([_cell(fmt, r.get(key)) for _, key, fmt in COLUMNS])
    widths = [max(len(row[i]) for row in cells) for i in range(len(COLUMNS))]
    lines = []
    for n, row in enumerate(cells):
        line = " ".join(
            cell.ljust(w) if COLUMNS[i][2].startswith("{:<") else cell.rjust(w)
            for i, (cell, w) in enumerate(zip(row, widths, strict=True))
        )
        lines.append(line.rstrip())
        if n == 0:
            lines.append("-" * len(line))
    return "\n".join(lines)


def format_summary(summary: dict[str, Any]) -> str:
    share = summary["tall_vegetation_share"]
    tall = (
        f"{summary['tall_vegetation']} of {summary['tall']} spanning more than "
        f"{summary['tall_extent_m']:g} m vertically with {summary['tall_returns']} returns "
        f"or more are vegetation ({share:.0%})"
        if share is not None
        else f"none spans more than {summary['tall_extent_m']:g} m vertically"
    )
    verdicts = ", ".join(f"{n} {v}" for v, n in summary["verdicts"].items()) or "none"
    tracks = (
        ""
        if summary["track_trees"] is None
        else f"; {summary['track_trees']} of their tracks are trees by their scans so far"
    )
    return (
        f"{summary['objects']} objects ({verdicts}); {summary['vegetation']} judged "
        f"vegetation; {tall}{tracks}"
    )
