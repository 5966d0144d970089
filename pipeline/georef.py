"""Mapped trees to the outputs: positions in UTM and WGS84, the matching field-map tree,
and `trees.csv` / `trees.geojson` written atomically (docs/architecture.md, "Outputs").

A mapper's trees live in a world frame: `utm` (after the first fix) or `odom` (mapped
before the first fix, or kept there through a GNSS outage). `odom` trees are moved to
UTM with the 3x3 `utm_from_odom` transform of the localizer when one is available (given
as a matrix, or as a function of the tree's `last_seen` time that returns one or None);
without it they stay unreferenced (empty position) but are still reported.

Matching: each georeferenced tree is compared with every field-map tree in x-y (UTM);
pairs closer than the gate are taken greedily from the closest, each map tree and each
detected tree at most once. A detected tree left without a pair keeps no `field_id`.
The pairs within the gate are found through a k-d tree of the field map (`FieldMapIndex`,
built once per run by the caller that georeferences after every scan).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Callable, Container, Iterable, Sequence
from typing import Any, Protocol, TextIO

import numpy as np

from treetraits.files import write_atomically
from treetraits.pipeline.classify import TREE
from treetraits.pipeline.fieldmap import FieldTree
from treetraits.pipeline.localization.utm import UtmGrid
from treetraits.pipeline.trees import CSV_COLUMNS, Tree, csv_row, geojson_properties

DEFAULT_GATE_M = 1.5
FEATURES_PER_WRITE = 1000  # GeoJSON features joined per write (~0.5 MB of text)

FOUND, MISSING, REJECTED = "found", "missing", "rejected"

UtmFromOdom = np.ndarray | Callable[[int], np.ndarray | None]


class MappedTree(Protocol):
    """What georeferencing reads from a mapper's tree (`pipeline.mapper.TrackedTree`)."""

    tree_id: Any
    x: float  # in `frame`
    y: float
    frame: str
    width_m: float
    height_m: float
    ndvi: float | None
    observations: int
    first_seen: int
    last_seen: int


class FieldMapIndex:
    """A field map's trees placed in the run's UTM grid once, with a k-d tree, so matching
    a few hundred mapped trees after every scan costs a look-up each, not a projection of
    the whole map and every pair's distance (georeference takes one or builds one)."""

    def __init__(self, field_map: Sequence[FieldTree], grid: UtmGrid):
        from scipy.spatial import cKDTree

        self.trees = list(field_map)
        self.grid = grid
        self.xy = np.full((len(self.trees), 2), np.nan)
        if self.trees:
            lat = np.array([f.lat for f in self.trees], dtype=float)
            lon = np.array([f.lon for f in self.trees], dtype=float)
            self.xy = np.column_stack(grid.forward(lat, lon))
        self._kdtree = cKDTree(self.xy) if self.trees else None

    def __len__(self) -> int:
        return len(self.trees)

    def match(self, detected: np.ndarray, gate_m: float) -> list[int | None]:
        """`match_nearest(detected, self.xy, gate_m)`, the same pairs: the k-d tree only
        finds the candidates (with a hair of slack), the gate and the order are
        match_nearest's own arithmetic."""
        detected = np.asarray(detected, dtype=float).reshape(-1, 2)
        placed = np.flatnonzero(np.isfinite(detected).all(axis=1))
        if self._kdtree is None or not len(placed):
            return [None] * len(detected)
        row, j = self._within(detected[placed], gate_m)
        return _greedy(detected, self.xy, placed[row], j, gate_m, len(detected))

    def approach(self, path_xy: np.ndarray, reach_m: float, nearest: np.ndarray) -> None:
        """Lower `nearest` (one distance per map tree, m) to each tree's distance from
        the nearest of `path_xy` (UTM points, NaN rows skipped), for the trees within
        `reach_m` of one: a path taken in piece by piece gives, within reach, the
        distances of the whole path at once, for the cost of the new piece."""
        path_xy = np.asarray(path_xy, dtype=float).reshape(-1, 2)
        path_xy = path_xy[np.isfinite(path_xy).all(axis=1)]
        if self._kdtree is None or not len(path_xy):
            return
        point, tree = self._within(path_xy, reach_m)
        gap = self.xy[tree] - path_xy[point]
        np.minimum.at(nearest, tree, np.sqrt(gap[:, 0] ** 2 + gap[:, 1] ** 2))

    def _within(self, xy: np.ndarray, reach_m: float) -> tuple[np.ndarray, np.ndarray]:
        """The pairs (row of `xy`, map tree) the k-d tree finds within `reach_m`, with a
        hair of slack: the callers' own arithmetic, not the k-d tree's rounding, decides."""
        found = self._kdtree.query_ball_point(xy, reach_m * (1 + 1e-9) + 1e-9)
        row = np.repeat(np.arange(len(xy)), [len(f) for f in found])
        return row, np.fromiter((k for f in found for k in f), dtype=np.intp, count=len(row))


def georeference(
    trees: Iterable[MappedTree],
    grid: UtmGrid | None,
    field_map: Sequence[FieldTree] | FieldMapIndex = (),
    utm_from_odom: UtmFromOdom | None = None,
    gate_m: float = DEFAULT_GATE_M,
    only: Container[str] | None = None,
) -> list[Tree]:
    """`Tree` records, in the order given. `grid` is the run's UTM zone (the localizer's,
    from the first fix); None when there never was a fix: nothing is referenced then.
    `only`: the records of these tree ids alone (matching still weighs every tree, since
    a tree's field id depends on its neighbours')."""
    trees = list(trees)
    xy = utm_positions(trees, grid, utm_from_odom)
    field_ids: list[FieldTree | None] = [None] * len(trees)
    if grid is not None and len(field_map):
        index = field_map if isinstance(field_map, FieldMapIndex) else None
        if index is None or index.grid is not grid:
            index = FieldMapIndex(field_map if index is None else index.trees, grid)
        for i, j in enumerate(index.match(xy, gate_m)):
            field_ids[i] = None if j is None else index.trees[j]
    keep = [i for i, t in enumerate(trees) if only is None or str(t.tree_id) in only]
    placed = [i for i in keep if np.isfinite(xy[i, 0])]
    lat_lon = {}
    if placed:
        lat, lon = grid.inverse(xy[placed, 0], xy[placed, 1])
        lat_lon = {i: (float(a), float(o)) for i, a, o in zip(placed, lat, lon, strict=True)}
    out = []
    for i in keep:
        tree, (e, n), match = trees[i], xy[i], field_ids[i]
        kind = getattr(tree, "kind", TREE)
        placed_here = i in lat_lon
        lat, lon = lat_lon.get(i, (None, None))
        out.append(
            Tree(
                tree_id=str(tree.tree_id),
                easting=float(e) if placed_here else None,
                northing=float(n) if placed_here else None,
                utm_zone=grid.name if placed_here else None,
                lat=lat,
                lon=lon,
                width_m=float(tree.width_m),
                height_m=float(tree.height_m),
                ndvi=tree.ndvi,
                observations=int(tree.observations),
                first_seen=int(tree.first_seen),
                last_seen=int(tree.last_seen),
                field_id=match.id if match else None,
                row=match.row if match else None,
                status=FOUND if kind == TREE else REJECTED,
                reason=None if kind == TREE else kind,
                height_top_seen=getattr(tree, "height_top_seen", None),
                width_sides_seen=getattr(tree, "width_sides_seen", None),
                **({} if kind == TREE else _cues(tree)),
            )
        )
    return out


def _cues(tree: MappedTree) -> dict[str, float | None]:
    """A rejected object's cues (`pipeline.vegetation`), None where unmeasured."""
    out = {}
    for name in ("evidence", "texture_m", "planar_share", "intensity"):
        value = getattr(tree, name, None)
        out[name] = None if value is None or not math.isfinite(value) else float(value)
    return out


def utm_positions(
    trees: Sequence[MappedTree], grid: UtmGrid | None, utm_from_odom: UtmFromOdom | None = None
) -> np.ndarray:
    """(N, 2) easting, northing of mapped trees (or path points), NaN where one cannot be
    placed (no fix yet, no pose): georeference's positions, without its records."""
    xy = np.full((len(trees), 2), np.nan)
    for i, tree in enumerate(trees):
        position = _utm_xy(tree, grid, utm_from_odom)
        if position is not None:
            xy[i] = position
    return xy


def missing_trees(
    field_map: FieldMapIndex, found: Iterable[Tree], passed: np.ndarray, reach_m: float
) -> list[Tree]:
    """Field-map trees no found tree is matched to, that the robot came within `reach_m`
    of (`passed`: each map tree's nearest approach, m, in `field_map` order)."""
    matched = {t.field_id for t in found if t.field_id is not None}
    out = []
    for k in np.flatnonzero(np.asarray(passed) <= reach_m):  # in field-map order
        mapped = field_map.trees[k]
        if mapped.id in matched:
            continue
        easting, northing = field_map.xy[k]
        out.append(
            Tree(
                tree_id="",
                easting=float(easting),
                northing=float(northing),
                utm_zone=field_map.grid.name,
                lat=float(mapped.lat),
                lon=float(mapped.lon),
                width_m=math.nan,
                height_m=math.nan,
                ndvi=None,
                observations=0,
                first_seen=None,
                last_seen=None,
                field_id=mapped.id,
                row=mapped.row,
                status=MISSING,
            )
        )
    return out


def match_nearest(detected: np.ndarray, mapped: np.ndarray, gate_m: float) -> list[int | None]:
    """For each detected x-y (NaN = not placed), the index of its map tree or None:
    pairs within `gate_m`, taken greedily by distance (ties by detected, then map index),
    each side used at most once."""
    detected = np.asarray(detected, dtype=float).reshape(-1, 2)
    mapped = np.asarray(mapped, dtype=float).reshape(-1, 2)
    if not len(detected) or not len(mapped):
        return [None] * len(detected)
    i, j = np.indices((len(detected), len(mapped))).reshape(2, -1)
    return _greedy(detected, mapped, i, j, gate_m, len(detected))


def _greedy(detected, mapped, i, j, gate_m: float, n: int) -> list[int | None]:
    """The greedy pairing over candidate pairs (i, j), each pair's distance as hypot."""
    result: list[int | None] = [None] * n
    distance = np.hypot(detected[i, 0] - mapped[j, 0], detected[i, 1] - mapped[j, 1])
    near = distance <= gate_m  # NaN compares False: unplaced trees never match
    i, j, distance = i[near], j[near], distance[near]
    order = np.lexsort((j, i, distance))
    used = set()
    for k in order:
        if result[i[k]] is None and j[k] not in used:
            result[i[k]] = int(j[k])
            used.add(j[k])
    return result


def _utm_xy(tree: MappedTree, grid: UtmGrid | None, utm_from_odom) -> np.ndarray | None:
    p = np.array([tree.x, tree.y], dtype=float)
    if tree.frame == "utm":
        if grid is None:
            raise ValueError(f"tree {tree.tree_id} is in utm but no UTM grid was given")
        return p
    if tree.frame != "odom" or grid is None or utm_from_odom is None:
        return None  # e.g. base_footprint (no pose), or no transform yet
    T = utm_from_odom(tree.last_seen) if callable(utm_from_odom) else utm_from_odom
    if T is None:
        return None
    T = np.asarray(T, dtype=float)
    if T.shape != (3, 3):
        raise ValueError(f"utm_from_odom must be a 3x3 2-D transform, got shape {T.shape}")
    return (T @ [p[0], p[1], 1.0])[:2]


# ---- outputs --------------------------------------------------------------------------


class RenderCache:
    """Each record's text from the previous write, by the record itself (`Tree` is frozen):
    a writer that gets the same records again (a survey's finalised trees, export after
    export) formats only the new ones. Holds the records of the last write only.

    The very same record object is found by its id (it is held here, so the id is not
    reused); only the others are looked up by value, whose hash runs over all ~20 fields,
    for every tree at every export."""

    def __init__(self) -> None:
        self._by_object: dict[int, tuple[Tree, str]] = {}
        self._by_value: dict[Tree, str] = {}

    def texts(self, trees: Iterable[Tree], render: Callable[[Tree], str]) -> list[str]:
        old_objects, old_values = self._by_object, self._by_value
        objects: dict[int, tuple[Tree, str]] = {}
        values: dict[Tree, str] = {}
        out = []
        for tree in trees:
            held = old_objects.get(id(tree))
            if held is not None and held[0] is tree:
                text = held[1]
            else:
                text = old_values.get(tree)
                if text is None:
                    text = render(tree)
                values[tree] = text  # a new object: by value too (re-made equal next time)
            objects[id(tree)] = (tree, text)
            out.append(text)
        self._by_object, self._by_value = objects, values
        return out


def write_trees_csv(
    path: str | os.PathLike, trees: Iterable[Tree], cache: RenderCache | None = None
) -> None:
    """trees.csv with exactly CSV_COLUMNS (the table's, pipeline/trees.py), written
    atomically (temp file, fsync, rename).
    `cache`: the lines of records written before are reused."""
    lines = (cache or RenderCache()).texts(trees, _csv_line)

    def write(f: TextIO) -> None:
        csv.writer(f, lineterminator="\n").writerow(CSV_COLUMNS)
        f.writelines(lines)

    write_atomically(path, write, permissions=0o644)


def _csv_line(tree: Tree) -> str:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerow(csv_row(tree))
    return out.getvalue()


def write_trees_geojson(
    path: str | os.PathLike, trees: Iterable[Tree], cache: RenderCache | None = None
) -> None:
    """trees.geojson: a FeatureCollection of WGS84 Points (null geometry for a tree not
    yet georeferenced), the columns' values as properties (`geojson_properties`: `reason`
    only for rejected objects, rejected.geojson is written by this too); written
    atomically. The text is
    `json.dump(collection, indent=1)`'s, byte for byte, each feature formatted once
    (`cache`: the features of records written before are reused)."""
    features = (cache or RenderCache()).texts(trees, _feature_text)

    def write(f: TextIO) -> None:
        f.write('{\n "type": "FeatureCollection",\n "features": [')
        if features:
            # Joined a slice at a time: one text of every feature (26 MB at 50,000 trees)
            # would be made, copied and encoded whole, ~100 MB at the peak of an export.
            f.write("\n")
            for start in range(0, len(features), FEATURES_PER_WRITE):
                f.write(",\n" if start else "")
                f.write(",\n".join(features[start : start + FEATURES_PER_WRITE]))
            f.write("\n ")
        f.write("]\n}\n")

    write_atomically(path, write, permissions=0o644)


def _feature_text(tree: Tree) -> str:
    """One feature as json.dump(indent=1) writes it two levels deep (in "features")."""
    text = json.dumps(_feature(tree), indent=1)
    return "\n".join("  " + line for line in text.split("\n"))


def point_geometry(lat: float | None, lon: float | None) -> dict[str, Any] | None:
    """A GeoJSON Point in WGS84 (8 decimals: ~1 mm), or None (null geometry) without one."""
    if lat is None or lon is None:
        return None
    return {"type": "Point", "coordinates": [round(lon, 8), round(lat, 8)]}


def _feature(tree: Tree) -> dict[str, Any]:
    return {
        "type": "Feature",
        "geometry": point_geometry(tree.lat, tree.lon),
        "properties": geojson_properties(tree),
    }
