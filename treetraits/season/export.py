"""`treetraits season export`: the season as a long CSV (one line per tree and survey)
and a GeoJSON of the trees with their growth (docs/season.md, "Export")."""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Sequence
from typing import Any, TextIO

from treetraits.files import iso_utc, write_atomically
from treetraits.pipeline.georef import point_geometry
from treetraits.pipeline.linking import growth_per_30_days
from treetraits.pipeline.trees import csv_cells, json_value, width_bounded
from treetraits.season.store import VISIT_COLUMNS, SeasonTree, TreeVisit

CSV_NAME = "season.csv"
GEOJSON_NAME = "season.geojson"
EXPORT_OUTPUTS = (CSV_NAME, GEOJSON_NAME)

# The season's own columns, then a visit's tree columns, formatted as trees.csv does.
CSV_COLUMNS = [
    "tree_id",
    "block",
    "field_id",
    "row",
    "survey_id",
    "date",
    "recording",
    "status",
    "run_tree_id",
    *VISIT_COLUMNS,
]


def growth(tree: SeasonTree) -> dict[str, Any]:
    """A tree's change over the season, from its first to its last survey that measured
    it: width and height per 30 days (m), NDVI (last minus first).

    The height's change is over the surveys that saw the crown's top (`height_top_seen`
    true) only: a lower bound is where the LiDAR's top beam cut the crown, set by how close
    the robot passed, not by the tree (a tree "shrank" from 2.79 to 2.00 m between two
    drives that way), and a survey from before the season kept the flag may be one. The
    width's change is over every survey that measured it, and `width_change_one_sided`
    says whether its first or last width was seen from one side only (null: not known):
    a lane's view of a crown is the same part of it from drive to drive, so that change
    compares like with like only when both ends were seen the same way."""
    found = [v for v in tree.visits if v.status == "found"]
    times = [v.t_start for v in found]
    topped = [v for v in found if v.height_top_seen is True]
    ndvi = [(v.t_start, v.ndvi) for v in found if v.ndvi is not None]
    last = tree.visits[-1] if tree.visits else None
    width_change = growth_per_30_days(times, [v.width_m for v in found])
    height_change = growth_per_30_days([v.t_start for v in topped], [v.height_m for v in topped])
    return {
        "width_change_m_per_30d": _round(width_change),
        "width_change_one_sided": _one_sided_ends(found) if width_change is not None else None,
        "height_change_m_per_30d": _round(height_change),
        # Found surveys whose height was a lower bound (left out of the change above).
        "height_lower_bounds": sum(v.height_top_seen is False for v in found),
        "ndvi_change": round(ndvi[-1][1] - ndvi[0][1], 4) if len(ndvi) >= 2 else None,
        "surveys": len(tree.visits),
        "found": len(found),
        "first_date": iso_utc(tree.visits[0].t_start) if tree.visits else None,
        "last_date": iso_utc(last.t_start) if last else None,
        "last_status": last.status if last else None,
        # The latest measurement, as trees.geojson writes it.
        "width_m": json_value("width_m", found[-1].width_m) if found else None,
        "height_m": json_value("height_m", found[-1].height_m) if found else None,
        "ndvi": json_value("ndvi", found[-1].ndvi) if found else None,
        "height_top_seen": found[-1].height_top_seen if found else None,
        "width_sides_seen": found[-1].width_sides_seen if found else None,
    }


def _one_sided_ends(found: Sequence[TreeVisit]) -> bool | None:
    """Whether the first or the last measured width was seen from one side only (None
    when neither was and one of them is not known)."""
    measured = [v for v in found if v.width_m is not None]
    ends = [measured[0].width_sides_seen, measured[-1].width_sides_seen]
    if any(width_bounded(sides) for sides in ends):
        return True
    return None if None in ends else False


def write_season_csv(path: str | os.PathLike, trees: Sequence[SeasonTree]) -> None:
    def write(f: TextIO) -> None:
        out = csv.writer(f, lineterminator="\n")
        out.writerow(CSV_COLUMNS)
        for t in trees:
            for v in t.visits:
                out.writerow(
                    [
                        t.tree_id,
                        t.block,
                        *csv_cells(t, ("field_id", "row")),
                        v.survey_id,
                        iso_utc(v.t_start),
                        v.recording,
                        v.status,
                        v.run_tree_id or "",
                        *csv_cells(v, VISIT_COLUMNS),
                    ]
                )

    write_atomically(path, write, permissions=0o644)


def write_season_geojson(path: str | os.PathLike, trees: Sequence[SeasonTree]) -> None:
    """One WGS84 Point per season tree (its mean position; null geometry when it has no
    latitude), its growth as properties."""

    def feature(t: SeasonTree) -> dict:
        geometry = point_geometry(t.lat, t.lon)
        properties = {
            "tree_id": t.tree_id,
            "block": t.block,
            "field_id": t.field_id,
            "row": t.row,
            **growth(t),
        }
        return {"type": "Feature", "geometry": geometry, "properties": properties}

    def write(f: TextIO) -> None:
        json.dump(
            {"type": "FeatureCollection", "features": [feature(t) for t in trees]}, f, indent=1
        )
        f.write("\n")

    write_atomically(path, write, permissions=0o644)


def _round(value: float | None, decimals: int = 3) -> float | None:
    return None if value is None else round(float(value), decimals)
