"""One output tree and the table of its fields: the record georeferencing makes and every
output writes.

Each field of `Tree` is declared with `column(...)`: its place among the outputs' columns,
its `Format` (the trees.csv cell, the GeoJSON value, the SQLite type and value), where it
appears (trees.csv, a trees.geojson property, the store's `trees` table) and a one-line
doc. `TREE_FIELDS` holds them in column order; trees.csv, trees.geojson, the store's
`trees` table and the season's tree columns are all made from it, and docs/georef.md's
table is checked against it (tests/pipeline/test_georef.py). A new output column is one more field
here, with the next position.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from operator import attrgetter
from typing import Any

from treetraits.files import iso_utc

# ---- formats: one kind of value in each output ------------------------------------------


def _same(value: Any) -> Any:
    return value


def _text(value: Any) -> str:
    return "" if value is None else str(value)


def _iso_or_null(ns: int | None) -> str | None:
    return iso_utc(ns) or None


def _flag(value: bool | None) -> str:
    return "" if value is None else str(bool(value)).lower()


def _real(value: float | None) -> float | None:
    """NULL for an unmeasured value (NaN)."""
    return None if value is None or value != value else float(value)


def _bit(value: bool | None) -> int | None:
    return None if value is None else int(value)


def _bool(value: int | None) -> bool | None:
    return None if value is None else bool(value)


@dataclass(frozen=True, slots=True)
class Format:
    """How one kind of value is written: its trees.csv cell, its GeoJSON value, its SQLite
    type and the value stored there and read back. `null`: what a NULL reads back as in
    a field that cannot be None (NaN for an unmeasured trait)."""

    csv: Callable[[Any], str]
    json: Callable[[Any], Any]
    sql_type: str
    to_sql: Callable[[Any], Any] = _same
    from_sql: Callable[[Any], Any] = _same
    null: Any = None


def decimals(places: int) -> Format:
    """A float with `places` decimals; empty (null, NULL) when None or not finite."""

    def fixed(value: float | None) -> str:
        if value is None or not math.isfinite(value):
            return ""
        return f"{value:.{places}f}"

    def rounded(value: float | None) -> float | None:
        if value is None or not math.isfinite(value):
            return None
        return round(float(value), places)

    return Format(csv=fixed, json=rounded, sql_type="REAL", to_sql=_real, null=math.nan)


TEXT = Format(csv=_text, json=_same, sql_type="TEXT")
COUNT = Format(csv=_text, json=_same, sql_type="INTEGER")
# ns since the Unix epoch; ISO 8601 UTC with milliseconds in trees.csv and GeoJSON.
TIME = Format(csv=iso_utc, json=_iso_or_null, sql_type="INTEGER")
# true / false / empty in trees.csv, a JSON boolean, 1 / 0 / NULL in SQLite.
FLAG = Format(csv=_flag, json=_same, sql_type="INTEGER", to_sql=_bit, from_sql=_bool)
METRES = decimals(3)  # a millimetre
DEGREES = decimals(8)  # WGS84, ~1 mm
INDEX = decimals(4)  # NDVI
SCORE = decimals(3)  # vegetation evidence, shares


# ---- lower bounds: how the outputs that print traits mark them ------------------------

LOWER_BOUND = ">"  # before a value that is a lower bound: `>2.55`
HEIGHT_BOUND_LEGEND = (
    "height >: a lower bound, the crown's top never bracketed within 5 % by the LiDAR's "
    "beams (height_top_seen false)"
)
WIDTH_BOUND_LEGEND = (
    "width >: a lower bound, the crown seen from one side only, its far side hidden "
    "(width_sides_seen 1)"
)


def height_bounded(height_top_seen: bool | None) -> bool:
    """The height is a lower bound (False: not measured to 5 %; None: not judged)."""
    return height_top_seen is False


def width_bounded(width_sides_seen: int | None) -> bool:
    """The width is a lower bound (1: one side seen; None: not judged)."""
    return width_sides_seen == 1


def marked(value: float | None, bound: bool) -> str:
    """A trait as the printed tables show it: 2 decimals, `>` before a lower bound; `-`
    when not measured (None or NaN)."""
    if value is None or not math.isfinite(value):
        return "-"
    return f"{LOWER_BOUND if bound else ''}{value:.2f}"


# ---- the table -------------------------------------------------------------------------

_KEY = "treetraits.tree_field"  # the dataclass field metadata key


@dataclass(frozen=True, slots=True)
class TreeField:
    """One field of `Tree` and how the outputs write it.

    `position`: its place in trees.csv, trees.geojson and the store's `trees` table (a
    field absent from one is skipped there). `csv`: a trees.csv column. `geojson`: its
    trees.geojson property name, None for none (lat and lon are the geometry);
    `geojson_optional`: the property only when the value is not None. `sql`: the
    constraints after the SQLite type in the `trees` table, None when not in it;
    `sql_line`: consecutive columns with the same label share a line of the CREATE TABLE
    text and `sql_note` ends that line as a comment (the text stays the one stores on
    disk hold). `name`, `annotation`, `nullable` and `default` are filled in from the
    dataclass field (as is `geojson`, "" in `column()`'s record, with the name)."""

    position: int
    format: Format
    doc: str
    csv: bool = True
    geojson: str | None = ""
    geojson_optional: bool = False
    sql: str | None = ""
    sql_line: str | None = None
    sql_note: str = ""
    name: str = ""
    annotation: str = ""
    nullable: bool = False
    default: Any = None

    @property
    def sql_definition(self) -> str:
        """The column's definition after its name, e.g. `TEXT NOT NULL DEFAULT 'found'`."""
        return f"{self.format.sql_type} {self.sql or ''}".strip()

    def from_sql(self, value: Any) -> Any:
        """A stored value back as the field holds it (NULL: None, or NaN for a trait)."""
        if value is None:
            return None if self.nullable else self.format.null
        return self.format.from_sql(value)


def column(
    position: int,
    format: Format,
    doc: str,
    *,
    default: Any = dataclasses.MISSING,
    csv: bool = True,
    geojson: bool | str = True,
    geojson_optional: bool = False,
    sql: str | None = "",
    sql_line: str | None = None,
    sql_note: str = "",
) -> Any:
    """A `Tree` field that is an output column (see `TreeField`). `geojson`: True for a
    property named as the field, a text for another name, False for none."""
    spec = TreeField(
        position,
        format,
        doc,
        csv=csv,
        geojson=None if geojson is False else ("" if geojson is True else geojson),
        geojson_optional=geojson_optional,
        sql=sql,
        sql_line=sql_line,
        sql_note=sql_note,
    )
    return dataclasses.field(default=default, metadata={_KEY: spec})


@dataclass(frozen=True, slots=True)
class Tree:
    """One mapped tree, as written to the outputs; its fields are the output columns.

    Position in the UTM zone of the run (`utm_zone` like `11N`) and in WGS84; None while
    the tree is only known in `odom` (seen before the first GNSS fix or in an outage).
    Times are ns since the Unix epoch.

    `status`: "found" (detected), "missing" (a field-map tree the robot passed within
    sensing range and did not find: its position is the map's, `tree_id` is empty, its
    traits NaN, no times) or "rejected" (an object seen as often as a tree that is not
    one: `reason` says why, see `pipeline.classify.REASONS`).

    `height_top_seen`: whether the height is measured: the crown's top bracketed within
    `traits.top_tolerance` (5 %) of it, between the height and the lowest of the beams
    that passed over it (`pipeline.mapper`); False: `height_m` is a lower bound (the crown
    went on above the top beam, or no beam came down close enough onto its top); None
    where nobody judged it (a missing tree, the baselines). `width_sides_seen`: 2 when the
    LiDAR saw the crown from both sides, 1 when from one side only (its far side hidden:
    `width_m` is a lower bound), None where nobody judged it (`pipeline.mapper.sides_seen`).

    The fields are declared in the constructor's positional order; each one's `position`
    is its place among the columns (field_id and row are the second and third there).
    """

    tree_id: str = column(
        0,
        TEXT,
        "the mapper's id, as text; empty for a missing tree (the store keys it "
        "`missing:<field id>`)",
        sql="PRIMARY KEY",
    )
    easting: float | None = column(
        3, METRES, "UTM metres, 3 decimals; empty when not georeferenced", sql_line="position"
    )
    northing: float | None = column(
        4, METRES, "UTM metres, 3 decimals; empty when not georeferenced", sql_line="position"
    )
    utm_zone: str | None = column(
        5, TEXT, "the run's UTM zone, like `11N`; empty when not georeferenced", sql_line="position"
    )
    lat: float | None = column(
        6,
        DEGREES,
        "WGS84 degrees, 8 decimals (~1 mm); empty when not georeferenced; in trees.geojson "
        "the Point's coordinates",
        geojson=False,
        sql_line="position",
    )
    lon: float | None = column(
        7,
        DEGREES,
        "WGS84 degrees, 8 decimals (~1 mm); empty when not georeferenced; in trees.geojson "
        "the Point's coordinates",
        geojson=False,
        sql_line="position",
    )
    width_m: float = column(
        8,
        METRES,
        "width, metres, 3 decimals; empty when unmeasured; a lower bound where "
        "`width_sides_seen` is 1",
        sql_line="traits",
    )
    height_m: float = column(
        9,
        METRES,
        "height, metres, 3 decimals; empty when unmeasured; a lower bound where "
        "`height_top_seen` is false",
        sql_line="traits",
    )
    ndvi: float | None = column(
        10,
        INDEX,
        "4 decimals; empty when unknown (RPH, no camera)",
        sql_line="traits",
        sql_note="NULL until measured",
    )
    observations: int = column(
        11, COUNT, "the scans the tree was seen in, an integer", sql="NOT NULL", sql_line="seen"
    )
    first_seen: int | None = column(
        12,
        TIME,
        "ISO 8601 UTC, milliseconds: `2026-11-22T10:15:30.123Z` (ns since the epoch in "
        "the store); empty for a missing tree",
        sql_line="seen",
    )
    last_seen: int | None = column(
        13, TIME, "as `first_seen`: the last scan that saw the tree", sql_line="seen"
    )
    field_id: str | None = column(
        1,
        TEXT,
        "the matched field-map tree's id; empty when unmatched",
        default=None,
        sql_line="match",
    )
    row: str | None = column(
        2,
        TEXT,
        "the matched field-map tree's row; empty when unmatched",
        default=None,
        sql_line="match",
    )
    status: str = column(
        14,
        TEXT,
        "`found`, or `missing` (a field-map tree passed and not found: the map's position, "
        "empty traits and times); `rejected` in rejected.geojson",
        default="found",
        sql="NOT NULL DEFAULT 'found'",
    )
    reason: str | None = column(
        17,
        TEXT,
        "why a rejected object is not a tree (`pipeline.classify.REASONS`): a property of "
        "rejected.geojson's features only, kept in the store's `rejected` table",
        default=None,
        csv=False,
        geojson_optional=True,
        sql=None,
    )
    height_top_seen: bool | None = column(
        15,
        FLAG,
        "`true`: the height is measured, the crown's top bracketed within 5 % by a beam "
        "that passed over it; `false`: `height_m` is a lower bound (the top above the "
        "LiDAR's top beam, or never bracketed that closely); empty when not judged (a "
        'missing tree; docs/pipeline.md, "Heights the LiDAR cannot see")',
        default=None,
        sql_note="1, 0 (the height is a lower bound), NULL (not judged)",
    )
    width_sides_seen: int | None = column(
        16,
        COUNT,
        "`2`: the crown was seen from both sides of its row (the LiDAR stood on each side of "
        "the row's line through the tree); `1`: from one side only, its far side hidden, "
        "`width_m` is a lower bound; empty when not judged (a missing tree, the RPH baseline; "
        'docs/pipeline.md, "Widths seen from one side")',
        default=None,
        sql_note="2 (both sides), 1 (one side: the width is a lower bound), NULL (not judged)",
    )
    # A rejected object's cues (`pipeline.vegetation`), each its mean over the track's
    # scans: how close it came to being a tree. rejected.geojson and the store only.
    evidence: float | None = column(
        18,
        SCORE,
        "a rejected object's vegetation evidence, the sum of its cues' weighted "
        "contributions (negative: against vegetation; docs/pipeline.md); empty when no "
        "cue was measured",
        default=None,
        csv=False,
        geojson_optional=True,
        sql=None,
    )
    texture_m: float | None = column(
        19,
        METRES,
        "a rejected object's surface texture (m): off-midpoint distance of returns 5 cm "
        "apart along a ring, mean over its scans; empty when unmeasured",
        default=None,
        csv=False,
        geojson_optional=True,
        sql=None,
    )
    planar_share: float | None = column(
        20,
        SCORE,
        "a rejected object's share of 0.3 m patches flat within the range noise, mean over "
        "its scans; empty when unmeasured",
        default=None,
        csv=False,
        geojson_optional=True,
        sql=None,
    )
    intensity: float | None = column(
        21,
        SCORE,
        "a rejected object's median LiDAR intensity (0-255), mean over its scans; empty "
        "when unmeasured",
        default=None,
        csv=False,
        geojson_optional=True,
        sql=None,
    )


def _table() -> tuple[TreeField, ...]:
    """`Tree`'s fields as `TreeField`s in column order; every field must be a column and
    the positions 0, 1, 2, ... without a gap."""
    hints = typing.get_type_hints(Tree)
    out = []
    for f in dataclasses.fields(Tree):
        spec = f.metadata.get(_KEY)
        if spec is None:
            raise TypeError(f"Tree.{f.name} is not declared with column()")
        out.append(
            dataclasses.replace(
                spec,
                name=f.name,
                annotation=str(f.type),
                nullable=type(None) in typing.get_args(hints[f.name]),
                geojson=f.name if spec.geojson == "" else spec.geojson,
                default=None if f.default is dataclasses.MISSING else f.default,
            )
        )
    out.sort(key=lambda spec: spec.position)
    if [spec.position for spec in out] != list(range(len(out))):
        raise TypeError(f"Tree's column positions are not 0..{len(out) - 1}")
    return tuple(out)


TREE_FIELDS = _table()
TREE_FIELD: dict[str, TreeField] = {f.name: f for f in TREE_FIELDS}
CSV_FIELDS = tuple(f for f in TREE_FIELDS if f.csv)
CSV_COLUMNS = tuple(f.name for f in CSV_FIELDS)
GEOJSON_FIELDS = tuple(f for f in TREE_FIELDS if f.geojson is not None)
SQL_FIELDS = tuple(f for f in TREE_FIELDS if f.sql is not None)

# Read once per record, formatted cell by cell: the writers' inner loops.
_CSV_VALUES = attrgetter(*CSV_COLUMNS)
_CSV_FORMATS = tuple(f.format.csv for f in CSV_FIELDS)
_GEOJSON = tuple((f.name, f.geojson, f.format.json, f.geojson_optional) for f in GEOJSON_FIELDS)


def csv_row(tree: Tree) -> list[str]:
    """One trees.csv line's cells, in CSV_COLUMNS order."""
    return [text(value) for text, value in zip(_CSV_FORMATS, _CSV_VALUES(tree), strict=True)]


def csv_cells(record: Any, names: Iterable[str]) -> list[str]:
    """The trees.csv cells of the named columns, read from any record that has them as
    attributes (the season's visits)."""
    return [TREE_FIELD[name].format.csv(getattr(record, name)) for name in names]


def json_value(name: str, value: Any) -> Any:
    """`value` as the GeoJSON outputs write column `name` (rounded, null when empty)."""
    return TREE_FIELD[name].format.json(value)


def geojson_properties(tree: Tree) -> dict[str, Any]:
    """A tree's trees.geojson properties, in column order."""
    properties = {}
    for name, key, to_json, optional in _GEOJSON:
        value = getattr(tree, name)
        if not (optional and value is None):
            properties[key] = to_json(value)
    return properties


def sql_values(tree: Tree, fields: Iterable[TreeField] = SQL_FIELDS) -> tuple:
    """A tree's values as its SQLite columns (`fields`: the store's `trees` table's)."""
    return tuple(f.format.to_sql(getattr(tree, f.name)) for f in fields)


def tree_from_sql(values: Mapping[str, Any]) -> Tree:
    """A `Tree` from stored values by field name; a field not among them takes its default,
    else None (not kept there, e.g. the season's times)."""
    return Tree(
        **{
            f.name: f.from_sql(values[f.name]) if f.name in values else f.default
            for f in TREE_FIELDS
        }
    )


def fields_markdown() -> str:
    """The fields as docs/georef.md's table (tests/pipeline/test_georef.py keeps the page equal to
    it)."""
    lines = [
        "| column | type | trees.csv | trees.geojson | traits.sqlite `trees` | format |",
        "|---|---|---|---|---|---|",
    ]
    for f in TREE_FIELDS:
        csv = str(CSV_COLUMNS.index(f.name) + 1) if f.csv else "-"
        geojson = f"`{f.geojson}`" if f.geojson else "-"
        if f.geojson_optional:
            geojson += " when set"
        sql = f"`{f.sql_definition}`" if f.sql is not None else "-"
        annotation = f.annotation.replace("|", "\\|")
        lines.append(f"| `{f.name}` | `{annotation}` | {csv} | {geojson} | {sql} | {f.doc} |")
    return "\n".join(lines) + "\n"
