"""The field map: where the orchard's trees stand (docs/architecture.md, "Field map input").

Two formats, told apart by the file name (`.geojson`/`.json`, `.csv`) or else by the
first character:
- GeoJSON: a FeatureCollection of Point features (WGS84 `[lon, lat(, alt)]`), each with a
  string `id` (in `properties`, or the feature's own `id`) and an optional `row`;
- CSV: a header with `id,lat,lon` and optionally `row` (any order, any case; other
  columns are ignored), then one tree per line.

Every problem is a `ConfigError` naming the file, the feature (`features[i]`) or line,
and the field. `row` is kept as the map gives it (as text).
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from treetraits.drivers.jsontext import JsonTooDeepError, loads_limited
from treetraits.errors import ConfigError


@dataclass(frozen=True, slots=True)
class FieldTree:
    id: str
    lat: float
    lon: float
    row: str | None = None


def load_field_map(path: str | os.PathLike) -> list[FieldTree]:
    """The trees of a GeoJSON or CSV field map file, in file order."""
    name = os.fspath(path)
    try:
        text = Path(path).read_bytes().decode("utf-8-sig")
    except FileNotFoundError:
        raise ConfigError(f"{name}: no such field map file") from None
    except IsADirectoryError:
        raise ConfigError(f"{name}: is a directory, expected a field map file") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{name}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    except OSError as exc:
        raise ConfigError(f"{name}: cannot read the field map ({exc.strerror or exc})") from None
    suffix = Path(name).suffix.lower()
    if suffix in (".geojson", ".json") or (suffix != ".csv" and text.lstrip().startswith("{")):
        return parse_geojson(text, name)
    return parse_csv(text, name)


def parse_geojson(text: str, name: str = "field map") -> list[FieldTree]:
    try:
        data = loads_limited(text)
    except JsonTooDeepError as exc:
        raise ConfigError(f"{name}: {exc}: not a field map") from None
    except json.JSONDecodeError as exc:
        raise ConfigError(
            f"{name}: not valid JSON (line {exc.lineno}, column {exc.colno}: {exc.msg})"
        ) from None
    except RecursionError:
        raise ConfigError(f"{name}: JSON nested too deeply to be a field map") from None
    if not isinstance(data, dict) or data.get("type") != "FeatureCollection":
        got = data.get("type") if isinstance(data, dict) else type(data).__name__
        raise ConfigError(f"{name}: expected a GeoJSON FeatureCollection, got {got!r}")
    features = data.get("features")
    if not isinstance(features, list):
        raise ConfigError(f"{name}: FeatureCollection without a 'features' list")
    trees = [_feature(name, i, feature) for i, feature in enumerate(features)]
    return _checked(name, trees, [f"features[{i}]" for i in range(len(trees))])


def parse_csv(text: str, name: str = "field map") -> list[FieldTree]:
    lines = _csv_lines(text, name)
    header = next(lines, None)
    if header is None:
        raise ConfigError(f"{name}: empty file; expected a CSV header id,lat,lon[,row]")
    header_line, cells = header
    columns = [c.strip().lower() for c in cells]
    for column in ("id", "lat", "lon"):
        if column not in columns:
            raise ConfigError(
                f"{name}: line {header_line}: header has no {column!r} column "
                f"(got {','.join(cells)}); expected id,lat,lon[,row]"
            )
    repeated = sorted({c for c in columns if c and columns.count(c) > 1})
    if repeated:
        raise ConfigError(f"{name}: line {header_line}: column(s) {repeated} appear twice")
    where = {
        column: columns.index(column) for column in ("id", "lat", "lon", "row") if column in columns
    }
    trees, places = [], []
    for line, cells in lines:
        if len(cells) < len(columns) or any(c.strip() for c in cells[len(columns) :]):
            raise ConfigError(
                f"{name}: line {line}: expected {len(columns)} fields "
                f"({','.join(columns)}), got {len(cells)}"
            )
        tree_id = cells[where["id"]].strip()
        if not tree_id:
            raise ConfigError(f"{name}: line {line}: field 'id' is empty")
        lat = _coordinate(name, f"line {line}", "lat", cells[where["lat"]], 90.0)
        lon = _coordinate(name, f"line {line}", "lon", cells[where["lon"]], 180.0)
        row = cells[where["row"]].strip() if "row" in where else ""
        trees.append(FieldTree(tree_id, lat, lon, row or None))
        places.append(f"line {line}")
    return _checked(name, trees, places)


def _csv_lines(text: str, name: str) -> Iterator[tuple[int, list[str]]]:
    """(line number, cells) of the non-blank records."""
    reader = csv.reader(io.StringIO(text, newline=""))
    while True:
        start = reader.line_num + 1
        try:
            cells = next(reader)
        except StopIteration:
            return
        except csv.Error as exc:
            raise ConfigError(f"{name}: line {start}: not valid CSV ({exc})") from None
        if any(c.strip() for c in cells):
            yield start, cells


def _feature(name: str, i: int, feature: Any) -> FieldTree:
    where = f"features[{i}]"
    if not isinstance(feature, dict) or feature.get("type") != "Feature":
        raise ConfigError(f"{name}: {where}: expected a GeoJSON Feature object")
    properties = feature.get("properties") or {}
    if not isinstance(properties, dict):
        raise ConfigError(f"{name}: {where}: 'properties' must be an object")
    tree_id = properties.get("id", feature.get("id"))
    if tree_id is None:
        raise ConfigError(f"{name}: {where}: field 'id' is missing (properties.id)")
    if not isinstance(tree_id, str):
        raise ConfigError(
            f"{name}: {where}: field 'id' must be a string, got {tree_id!r} (write \"{tree_id}\")"
        )
    if not tree_id.strip():
        raise ConfigError(f"{name}: {where}: field 'id' is empty")
    where = f"features[{i}] (id {tree_id!r})"
    geometry = feature.get("geometry")
    if not isinstance(geometry, dict):
        raise ConfigError(f"{name}: {where}: field 'geometry' is missing; expected a Point")
    if geometry.get("type") != "Point":
        raise ConfigError(
            f"{name}: {where}: geometry type is {geometry.get('type')!r}; expected 'Point'"
        )
    coordinates = geometry.get("coordinates")
    if not isinstance(coordinates, list) or len(coordinates) not in (2, 3):
        raise ConfigError(
            f"{name}: {where}: field 'coordinates' must be [lon, lat] or [lon, lat, alt], "
            f"got {coordinates!r}"
        )
    lon = _coordinate(name, where, "coordinates[0] (lon)", coordinates[0], 180.0)
    lat = _coordinate(name, where, "coordinates[1] (lat)", coordinates[1], 90.0)
    row = properties.get("row")
    if row is not None and (isinstance(row, bool) or not isinstance(row, str | int)):
        raise ConfigError(f"{name}: {where}: field 'row' must be a string or an integer")
    return FieldTree(tree_id.strip(), lat, lon, None if row is None else str(row))


def _coordinate(name: str, where: str, field: str, value: Any, limit: float) -> float:
    if isinstance(value, str):
        try:
            number = float(value.strip())
        except ValueError:
            raise ConfigError(
                f"{name}: {where}: field {field!r} is not a number: {value!r}"
            ) from None
    elif isinstance(value, int | float) and not isinstance(value, bool):
        number = float(value)
    else:
        raise ConfigError(f"{name}: {where}: field {field!r} must be a number, got {value!r}")
    if not math.isfinite(number) or abs(number) > limit:
        raise ConfigError(
            f"{name}: {where}: field {field!r} = {value!r} is outside [-{limit:g}, {limit:g}] "
            "degrees (WGS84)"
        )
    return number


def _checked(name: str, trees: list[FieldTree], places: list[str]) -> list[FieldTree]:
    if not trees:
        raise ConfigError(f"{name}: the field map holds no trees")
    first: dict[str, str] = {}
    for tree, place in zip(trees, places, strict=True):
        if tree.id in first:
            raise ConfigError(
                f"{name}: {place}: field 'id' {tree.id!r} is a duplicate of {first[tree.id]}"
            )
        first[tree.id] = place
    return trees
