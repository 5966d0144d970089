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
    from treetraits.pipeline.detection import Cluster, Detection

# An object whose returns span more than this vertically (top minus lowest return) is
# "tall" in the summary: a tree's crown cross-section, a wall, a person.
TALL_EXTENT_M = 1.0


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
        "verdict": cluster.verdict,
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


def object_rows(detection: Detection, T_base_lidar: np.ndarray) -> list[dict[str, Any]]:
    lidar = np.asarray(T_base_lidar, dtype=float)[:3, 3]
    return [object_row(i, c, lidar) for i, c in enumerate(detection.clusters)]


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """How many objects, how many judged vegetation, and of those spanning more than
    TALL_EXTENT_M vertically how many are vegetation (share None when there are none)."""
    tall = [r for r in rows if (r["extent_m"] or 0.0) > TALL_EXTENT_M]
    tall_vegetation = sum(r["vegetation"] for r in tall)
    verdicts: dict[str, int] = {}
    for r in rows:
        verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
    return {
        "objects": len(rows),
        "vegetation": sum(r["vegetation"] for r in rows),
        "trees": verdicts.get("tree", 0),
        "verdicts": dict(sorted(verdicts.items())),
        "tall_extent_m": TALL_EXTENT_M,
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
        cells.append([_cell(fmt, r[key]) for _, key, fmt in COLUMNS])
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
        f"{summary['tall_extent_m']:g} m vertically are vegetation ({share:.0%})"
        if share is not None
        else f"none spans more than {summary['tall_extent_m']:g} m vertically"
    )
    verdicts = ", ".join(f"{n} {v}" for v, n in summary["verdicts"].items()) or "none"
    return (
        f"{summary['objects']} objects ({verdicts}); {summary['vegetation']} judged "
        f"vegetation; {tall}"
    )
