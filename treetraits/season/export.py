"""`treetraits season export`: the season as a long CSV (one line per tree and survey)
and a GeoJSON of the trees with their growth (docs/season.md, "Export")."""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Sequence
from typing import Any, TextIO

from treetraits.files import write_atomically
from treetraits.pipeline.georef import iso_utc, point_geometry
from treetraits.pipeline.linking import growth_per_30_days
from treetraits.season.store import SeasonTree

CSV_NAME = "season.csv"
GEOJSON_NAME = "season.geojson"
EXPORT_OUTPUTS = (CSV_NAME, GEOJSON_NAME)

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
    "easting",
    "northing",
    "lat",
    "lon",
    "width_m",
    "height_m",
    "ndvi",
    "observations",
]


def growth(tree: SeasonTree) -> dict[str, Any]:
    """A tree's change over the season, from its first to its last survey that measured
    it: width and height per 30 days (m), NDVI (last minus first)."""
    found = [v for v in tree.visits if v.status == "found"]
    times = [v.t_start for v in found]
    ndvi = [(v.t_start, v.ndvi) for v in found if v.ndvi is not None]
    last = tree.visits[-1] if tree.visits else None
    return {
        "width_change_m_per_30d": _round(growth_per_30_days(times, [v.width_m for v in found])),
        "height_change_m_per_30d": _round(growth_per_30_days(times, [v.height_m for v in found])),
        "ndvi_change": round(ndvi[-1][1] - ndvi[0][1], 4) if len(ndvi) >= 2 else None,
        "surveys": len(tree.visits),
        "found": len(found),
        "first_date": iso_utc(tree.visits[0].t_start) if tree.visits else None,
        "last_date": iso_utc(last.t_start) if last else None,
        "last_status": last.status if last else None,
        "width_m": _round(found[-1].width_m) if found else None,
        "height_m": _round(found[-1].height_m) if found else None,
        "ndvi": _round(found[-1].ndvi, 4) if found else None,
    }


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
                        t.field_id or "",
                        t.row or "",
                        v.survey_id,
                        iso_utc(v.t_start),
                        v.recording,
                        v.status,
                        v.run_tree_id or "",
                        _text(v.easting, 3),
                        _text(v.northing, 3),
                        _text(v.lat, 8),
                        _text(v.lon, 8),
                        _text(v.width_m, 3),
                        _text(v.height_m, 3),
                        _text(v.ndvi, 4),
                        "" if v.observations is None else v.observations,
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


def _text(value: float | None, decimals: int) -> str:
    return "" if value is None else f"{value:.{decimals}f}"
