"""Georeferencing and the outputs: UTM round trips, field maps (GeoJSON and CSV, and every
way they can be malformed), matching with a gate, trees mapped in `odom` during an outage,
trees.csv / trees.geojson exactly as the contract says, written atomically."""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import os
from datetime import datetime, timezone

import numpy as np
import pytest

from tests.helpers.contract import CONTRACT_CSV_COLUMNS
from tests.helpers.paths import REPO
from treetraits.drivers.records import Fix, WheelSample
from treetraits.errors import ConfigError
from treetraits.files import iso_utc
from treetraits.pipeline.fieldmap import FieldTree, load_field_map
from treetraits.pipeline.georef import (
    CSV_COLUMNS,
    FieldMapIndex,
    _feature,
    georeference,
    match_nearest,
    write_trees_csv,
    write_trees_geojson,
)
from treetraits.pipeline.localization import LocalizationConfig, Localizer
from treetraits.pipeline.localization.utm import UtmGrid, true_heading_to_grid_yaw
from treetraits.pipeline.mapper import TrackedTree
from treetraits.pipeline.trees import (
    GEOJSON_FIELDS,
    TREE_FIELDS,
    Tree,
    csv_row,
    fields_markdown,
)

GRID = UtmGrid.for_zone(11, north=True)  # a grove near Riverside, California
E0, N0 = 467_000.0, 3_758_000.0
T_SEEN = int(datetime(2026, 11, 22, 10, 15, 30, tzinfo=timezone.utc).timestamp()) * 10**9


def tracked(
    tree_id,
    x,
    y,
    frame="utm",
    width=2.7,
    height=2.6,
    ndvi=0.61,
    seen=T_SEEN,
    top_seen=False,
    sides=1,
):
    return TrackedTree(
        tree_id=tree_id,
        x=x,
        y=y,
        z=1.2,
        frame=frame,
        width_m=width,
        height_m=height,
        ndvi=ndvi,
        observations=12,
        first_seen=seen,
        last_seen=seen + 5_123_456_789,
        traits="paper",
        height_top_seen=top_seen,
        width_sides_seen=sides,
    )


def field_tree(tree_id, easting, northing, row="1"):
    lat, lon = GRID.inverse(easting, northing)
    return FieldTree(tree_id, lat, lon, row)


# ---- UTM ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("lat", "lon", "zone"),
    [(33.9700, -117.3300, "11N"), (-33.8600, 151.2100, "56S"), (0.0001, 0.0001, "31N")],
)
def test_utm_round_trip_through_the_grid(lat, lon, zone):
    grid = UtmGrid.for_position(lat, lon)
    assert grid.name == zone
    easting, northing = grid.forward(lat, lon)
    assert 160_000 < easting < 840_000
    assert grid.inverse(easting, northing) == pytest.approx((lat, lon), abs=1e-9)
    # 1 m east is 1 m east (to the scale factor) after the round trip.
    lat2, lon2 = grid.inverse(easting + 1.0, northing)
    assert grid.forward(lat2, lon2) == pytest.approx((easting + 1.0, northing), abs=1e-6)


# ---- field maps -------------------------------------------------------------------------


def geojson(*features):
    return {"type": "FeatureCollection", "features": list(features)}


def point(tree_id=None, lon=-117.33, lat=33.97, row=None, geometry=None, **extra):
    properties = {} if tree_id is None else {"id": tree_id}
    if row is not None:
        properties["row"] = row
    return {
        "type": "Feature",
        "geometry": geometry or {"type": "Point", "coordinates": [lon, lat]},
        "properties": properties,
        **extra,
    }


def write(tmp_path, name, content):
    path = tmp_path / name
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


def test_geojson_field_map(tmp_path):
    data = geojson(
        point("R1T1", -117.33, 33.97, row="1"),
        point("R1T2", -117.32995, 33.97, row=1),  # an integer row is kept as text
        {**point(None, -117.3299, 33.97001), "id": "R2T1"},  # the feature's own id
        point("R2T2", geometry={"type": "Point", "coordinates": [-117.3298, 33.9701, 312.5]}),
    )
    trees = load_field_map(write(tmp_path, "map.geojson", data))
    assert trees == [
        FieldTree("R1T1", 33.97, -117.33, "1"),
        FieldTree("R1T2", 33.97, -117.32995, "1"),
        FieldTree("R2T1", 33.97001, -117.3299, None),
        FieldTree("R2T2", 33.9701, -117.3298, None),
    ]
    # Recognised by content too (no suffix).
    assert load_field_map(write(tmp_path, "map", data)) == trees


def test_csv_field_map(tmp_path):
    text = "\ufeffLat , ID,lon,Row,note\n33.97,R1T1,-117.33,1,big\n\n33.97001,R1T2,-117.32995,,\n"
    trees = load_field_map(write(tmp_path, "map.csv", text))
    assert trees == [
        FieldTree("R1T1", 33.97, -117.33, "1"),
        FieldTree("R1T2", 33.97001, -117.32995, None),
    ]
    plain = load_field_map(write(tmp_path, "plain.csv", "id,lat,lon\nA,-33.86,151.21\n"))
    assert plain == [FieldTree("A", -33.86, 151.21, None)]


BAD_GEOJSON = {
    "not JSON": ("{'type': oops", r"not valid JSON \(line 1"),
    "not a collection": (point("A"), "expected a GeoJSON FeatureCollection, got 'Feature'"),
    "no features list": ({"type": "FeatureCollection"}, "without a 'features' list"),
    "not a feature": (geojson(point("A"), [1, 2]), r"features\[1\]: expected a GeoJSON Feature"),
    "missing id": (geojson(point("A"), point()), r"features\[1\]: field 'id' is missing"),
    "numeric id": (geojson(point(7)), r"features\[0\]: field 'id' must be a string, got 7"),
    "empty id": (geojson(point("  ")), r"features\[0\]: field 'id' is empty"),
    "no geometry": (
        geojson({"type": "Feature", "geometry": None, "properties": {"id": "A"}}),
        r"features\[0\] \(id 'A'\): field 'geometry' is missing",
    ),
    "polygon": (
        geojson(point("A", geometry={"type": "Polygon", "coordinates": [[[0, 0], [1, 0]]]})),
        r"features\[0\] \(id 'A'\): geometry type is 'Polygon'; expected 'Point'",
    ),
    "one coordinate": (
        geojson(point("A", geometry={"type": "Point", "coordinates": [1.0]})),
        r"field 'coordinates' must be \[lon, lat\]",
    ),
    "latitude out of range": (
        geojson(point("A", lon=-117.3, lat=117.3)),
        r"features\[0\] \(id 'A'\): field 'coordinates\[1\] \(lat\)' = 117.3 is outside",
    ),
    "longitude not a number": (
        geojson(point("A", lon=[1], lat=3)),
        r"field 'coordinates\[0\] \(lon\)' must be a number",
    ),
    "NaN": (
        '{"type": "FeatureCollection", "features": [{"type": "Feature", "properties": '
        '{"id": "A"}, "geometry": {"type": "Point", "coordinates": [NaN, 3]}}]}',
        r"'coordinates\[0\] \(lon\)' = nan is outside",
    ),
    "bad row": (geojson(point("A", row=[1])), r"field 'row' must be a string or an integer"),
    "duplicate id": (
        geojson(point("A"), point("B"), point("A")),
        r"features\[2\]: field 'id' 'A' is a duplicate of features\[0\]",
    ),
    "no trees": (geojson(), "holds no trees"),
}


@pytest.mark.parametrize("case", sorted(BAD_GEOJSON))
def test_malformed_geojson_is_refused_naming_file_feature_and_field(tmp_path, case):
    content, message = BAD_GEOJSON[case]
    path = write(tmp_path, "map.geojson", content)
    with pytest.raises(ConfigError, match=message) as error:
        load_field_map(path)
    assert str(error.value).startswith(f"{path}: ")


BAD_CSV = {
    "empty": ("", "empty file; expected a CSV header id,lat,lon"),
    "no lat column": ("id,latitude,lon\nA,1,2\n", "line 1: header has no 'lat' column"),
    "repeated column": ("id,lat,lon,lat\nA,1,2,3\n", r"line 1: column\(s\) \['lat'\] appear twice"),
    "missing id": ("id,lat,lon\nA,1,2\n,3,4\n", "line 3: field 'id' is empty"),
    "lat not a number": ("id,lat,lon\nA,north,2\n", "line 2: field 'lat' is not a number: 'north'"),
    "lat out of range": ("id,lat,lon\nA,91,2\n", "line 2: field 'lat' = '91' is outside"),
    "lon NaN": ("id,lat,lon\nA,1,nan\n", "line 2: field 'lon' = 'nan' is outside"),
    "missing cell": ("id,lat,lon,row\nA,1,2,1\nB,1,2\n", r"line 3: expected 4 fields"),
    "extra cell": ("id,lat,lon\nA,1,2,oops\n", r"line 2: expected 3 fields \(id,lat,lon\), got 4"),
    "duplicate id": (
        "id,lat,lon\nA,1,2\nB,1,2\n\nA,3,4\n",
        "line 5: field 'id' 'A' is a duplicate of line 2",
    ),
    "header only": ("id,lat,lon\n", "holds no trees"),
    "not UTF-8": (b"id,lat,lon\nA\xff,1,2\n", "not UTF-8 text"),
}


@pytest.mark.parametrize("case", sorted(BAD_CSV))
def test_malformed_csv_is_refused_naming_file_line_and_field(tmp_path, case):
    content, message = BAD_CSV[case]
    path = write(tmp_path, "map.csv", content)
    with pytest.raises(ConfigError, match=message) as error:
        load_field_map(path)
    assert str(error.value).startswith(f"{path}: ")


def test_missing_field_map_file(tmp_path):
    with pytest.raises(ConfigError, match="no such field map file"):
        load_field_map(tmp_path / "nowhere.geojson")


# ---- matching -----------------------------------------------------------------------------


def test_matching_with_a_gate_one_map_tree_to_one_detected_tree():
    field_map = [field_tree("M1", E0, N0, "1"), field_tree("M2", E0 + 6.0, N0, "2")]
    trees = [
        tracked(1, E0 + 0.2, N0),  # 0.2 m off M1: matches
        tracked(2, E0 + 6.0, N0 + 3.0),  # 3 m off M2: outside the 1.5 m gate
        tracked(3, E0 - 0.1, N0 + 0.4),  # also near M1, but farther than tree 1: unmatched
        tracked(4, E0 + 20.0, N0),  # not on the map at all: still reported
    ]
    out = georeference(trees, GRID, field_map)
    assert [(t.tree_id, t.field_id, t.row) for t in out] == [
        ("1", "M1", "1"),
        ("2", None, None),
        ("3", None, None),
        ("4", None, None),
    ]
    assert out[0].easting == E0 + 0.2 and out[0].utm_zone == "11N"
    assert (out[0].lat, out[0].lon) == pytest.approx(GRID.inverse(E0 + 0.2, N0), abs=1e-12)
    # Greedy by distance, not by tree order: the nearer detection wins whatever its id.
    out = georeference([trees[2], trees[0]], GRID, field_map)
    assert [t.field_id for t in out] == [None, "M1"]
    # The gate is inclusive and configurable.
    assert match_nearest([[1.5, 0.0], [0.0, 3.0]], [[0.0, 0.0], [0.0, 0.0]], 1.5) == [0, None]
    assert match_nearest([[1.5, 0.0]], [[0.0, 0.0]], 1.49) == [None]
    assert georeference(trees[1:2], GRID, field_map, gate_m=3.5)[0].field_id == "M2"
    assert match_nearest([[np.nan, np.nan]], [[0.0, 0.0]], 1.5) == [None]


def test_the_field_map_index_pairs_as_the_exhaustive_matching_does():
    # Half-metre lattices make exact distance ties and pairs right on the gate; some
    # detected trees are unplaced (NaN). The k-d tree must find exactly the pairs the
    # all-pairs matching finds, tie-breaks included.
    rng = np.random.default_rng(7)
    matched = 0
    for _ in range(50):
        detected = rng.integers(0, 12, (int(rng.integers(1, 40)), 2)) * 0.5
        detected[rng.random(len(detected)) < 0.1] = np.nan
        mapped = rng.integers(0, 12, (int(rng.integers(1, 40)), 2)) * 0.5
        index = FieldMapIndex(
            [field_tree(f"F{j}", E0 + x, N0 + y) for j, (x, y) in enumerate(mapped)], GRID
        )
        # Detected trees on the map trees' own positions (a UTM round trip moves them by
        # nanometres, which would make the ties ties no more).
        placed = np.where(np.isnan(detected), np.nan, index.xy[0] + detected - mapped[0])
        found = index.match(placed, 1.0)
        assert found == match_nearest(placed, index.xy, 1.0)
        matched += sum(j is not None for j in found)
    assert matched > 200


def test_a_path_taken_in_piece_by_piece_passes_the_trees_the_whole_path_passes():
    """The field map's nearest approach, brought up to date one piece of path at a time
    (what each export adds), within reach is the nearest approach of the whole path
    (a k-d tree over all of it, as the exports worked it out before); unplaced points
    (NaN) count for nothing."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(3)
    mapped = rng.uniform(0, 60, (400, 2))
    index = FieldMapIndex(
        [field_tree(f"F{j}", E0 + x, N0 + y) for j, (x, y) in enumerate(mapped)], GRID
    )
    path = index.xy[0] + np.cumsum(rng.normal(0.0, 1.0, (300, 2)), axis=0)
    path[rng.random(len(path)) < 0.05] = np.nan
    nearest = np.full(len(index), np.inf)
    for piece in np.array_split(path, [1, 40, 41, 200]):
        index.approach(piece, 6.0, nearest)
    placed = path[np.isfinite(path).all(axis=1)]
    whole, _ = cKDTree(placed).query(index.xy)
    within = whole <= 6.0
    assert 50 < within.sum() < len(index)  # some passed, some not
    np.testing.assert_allclose(nearest[within], whole[within], rtol=0, atol=1e-9)
    assert np.isinf(nearest[~within]).all()


def test_records_of_some_trees_only_are_those_of_the_whole_map():
    trees = [tracked(i, E0 + 0.6 * (i % 5), N0 + 0.4 * i) for i in range(12)]
    field_map = [field_tree(f"F{j}", E0 + 0.5 * j, N0 + 0.4 * j) for j in range(12)]
    whole = georeference(trees, GRID, field_map)
    some = georeference(trees, GRID, FieldMapIndex(field_map, GRID), only={"2", "7", "11"})
    assert some == [t for t in whole if t.tree_id in ("2", "7", "11")]
    assert sum(t.field_id is not None for t in whole) >= 6  # neighbours compete for maps


def test_an_outage_tree_in_odom_is_georeferenced_through_a_known_transform():
    yaw = math.radians(30.0)
    T_utm_odom = np.array(
        [[math.cos(yaw), -math.sin(yaw), E0], [math.sin(yaw), math.cos(yaw), N0], [0, 0, 1]]
    )
    odom_tree = tracked(7, 4.0, 1.0, frame="odom")
    expected = (E0 + 4.0 * math.cos(yaw) - math.sin(yaw), N0 + 4.0 * math.sin(yaw) + math.cos(yaw))
    field_map = [field_tree("M7", *expected, row="3")]

    (tree,) = georeference([odom_tree], GRID, field_map, utm_from_odom=T_utm_odom)
    assert (tree.easting, tree.northing) == pytest.approx(expected, abs=1e-9)
    assert (tree.field_id, tree.row, tree.utm_zone) == ("M7", "3", "11N")
    # As a function of the tree's last sighting (the localizer's transform after it).
    asked = []

    def transform_at(t):
        asked.append(t)
        return T_utm_odom

    (tree,) = georeference([odom_tree], GRID, field_map, utm_from_odom=transform_at)
    assert asked == [odom_tree.last_seen] and tree.field_id == "M7"
    # No transform yet (or none at all): reported, unplaced, unmatched.
    for transform in (None, lambda t: None):
        (tree,) = georeference([odom_tree], GRID, field_map, utm_from_odom=transform)
        assert (tree.easting, tree.lat, tree.utm_zone, tree.field_id) == (None, None, None, None)
        assert tree.width_m == 2.7 and tree.observations == 12


def test_odom_trees_through_the_localizers_transform():
    """Wheels only for 4 s (odom), then RTK fixes with a true heading: the localizer's
    utm_from_odom at its first utm time puts an odom tree where the fix says."""
    localizer = Localizer(LocalizationConfig())
    speed, t = 0.5, 0
    for k in range(201):  # 4 s at 50 Hz, straight ahead in odom
        t = k * 20_000_000
        travel = speed * t / 1e9 / 0.098
        localizer.add_wheels(WheelSample(T_SEEN + t, travel, travel, "rad"))
    heading = 60.0  # true heading, degrees clockwise from north
    lat, lon = GRID.inverse(E0, N0)
    fix = Fix(T_SEEN + t, T_SEEN + t, lat, lon, 300.0, -33.0, 4, 14, 0.7, heading_deg=heading)
    assert localizer.add_fix(fix).reason == "datum"
    T = localizer.utm_from_odom(localizer.first_utm_time)
    # A tree seen 3 m ahead and 2 m left of the robot's odom position at the fix.
    odom_tree = tracked(1, 2.0 + 3.0, 2.0, frame="odom", seen=T_SEEN)
    (tree,) = georeference([odom_tree], localizer.grid, utm_from_odom=T)
    grid_yaw = true_heading_to_grid_yaw(heading, GRID.convergence_rad(lat, lon))
    ahead = np.array([math.cos(grid_yaw), math.sin(grid_yaw)])
    left = np.array([-math.sin(grid_yaw), math.cos(grid_yaw)])
    expected = np.array([E0, N0]) + 3.0 * ahead + 2.0 * left
    assert (tree.easting, tree.northing) == pytest.approx(tuple(expected), abs=1e-6)
    assert tree.utm_zone == "11N"


def test_trees_in_utm_need_the_grid_and_unposed_trees_stay_unplaced():
    with pytest.raises(ValueError, match="no UTM grid"):
        georeference([tracked(1, E0, N0)], None)
    (tree,) = georeference([tracked(1, 0.5, 0.2, frame="base_footprint")], GRID)
    assert tree.easting is None and tree.field_id is None


# ---- outputs ------------------------------------------------------------------------------


def output_trees():
    field_map = [field_tree("M1", E0, N0, "north-1")]
    trees = [
        tracked(
            1,
            E0 + 0.25,
            N0 - 0.1,
            width=2.71234,
            height=2.60049,
            ndvi=0.612345,
            top_seen=True,
            sides=2,
        ),
        tracked(2, E0 + 10.0, N0, ndvi=None),  # off the map
        tracked(3, 1.0, 2.0, frame="odom"),  # in an outage, no transform yet
    ]
    return georeference(trees, GRID, field_map)


def test_iso_times_are_utc_with_milliseconds():
    assert iso_utc(T_SEEN + 123_456_789) == "2026-11-22T10:15:30.123Z"
    assert iso_utc(0) == "1970-01-01T00:00:00.000Z"


def test_trees_csv_columns_and_values_exactly(tmp_path):
    trees = output_trees()
    path = tmp_path / "trees.csv"
    write_trees_csv(path, trees)
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    assert rows[0][: len(CONTRACT_CSV_COLUMNS)] == CONTRACT_CSV_COLUMNS
    assert tuple(rows[0]) == CSV_COLUMNS
    lat, lon = GRID.inverse(E0 + 0.25, N0 - 0.1)
    first = "2026-11-22T10:15:30.000Z"
    last = "2026-11-22T10:15:35.123Z"  # + 5.123456789 s, milliseconds truncated
    assert rows[1] == [
        "1",
        "M1",
        "north-1",
        f"{E0 + 0.25:.3f}",
        f"{N0 - 0.1:.3f}",
        "11N",
        f"{lat:.8f}",
        f"{lon:.8f}",
        "2.712",
        "2.600",
        "0.6123",
        "12",
        first,
        last,
        "found",
        "true",
        "2",
    ]
    lat, lon = GRID.inverse(E0 + 10.0, N0)
    assert rows[2] == [
        "2",
        "",
        "",
        "467010.000",
        "3758000.000",
        "11N",
        f"{lat:.8f}",
        f"{lon:.8f}",
        "2.700",
        "2.600",
        "",
        "12",
        first,
        last,
        "found",
        "false",
        "1",
    ]
    assert rows[3] == [
        "3",
        "",
        "",
        "",
        "",
        "",
        "",
        "",
        "2.700",
        "2.600",
        "0.6100",
        "12",
        first,
        last,
        "found",
        "false",
        "1",
    ]
    assert len(rows) == 4
    assert oct(os.stat(path).st_mode & 0o777) == "0o644"


def test_trees_geojson(tmp_path):
    path = tmp_path / "trees.geojson"
    write_trees_geojson(path, output_trees())
    data = json.loads(path.read_text())
    assert data["type"] == "FeatureCollection" and len(data["features"]) == 3
    first, off_map, unplaced = data["features"]
    lat, lon = GRID.inverse(E0 + 0.25, N0 - 0.1)
    assert first["geometry"]["type"] == "Point"
    assert first["geometry"]["coordinates"] == pytest.approx([lon, lat], abs=1e-8)
    assert first["properties"] == {
        "tree_id": "1",
        "field_id": "M1",
        "row": "north-1",
        "easting": E0 + 0.25,
        "northing": N0 - 0.1,
        "utm_zone": "11N",
        "width_m": 2.712,
        "height_m": 2.6,
        "ndvi": 0.6123,
        "observations": 12,
        "first_seen": "2026-11-22T10:15:30.000Z",
        "last_seen": "2026-11-22T10:15:35.123Z",
        "status": "found",
        "height_top_seen": True,
        "width_sides_seen": 2,
    }
    assert off_map["properties"]["field_id"] is None and off_map["properties"]["ndvi"] is None
    assert off_map["properties"]["height_top_seen"] is False
    assert off_map["properties"]["width_sides_seen"] == 1
    assert unplaced["geometry"] is None and unplaced["properties"]["easting"] is None


@pytest.mark.parametrize("writer", [write_trees_csv, write_trees_geojson])
def test_atomic_write_keeps_the_old_file_whole_when_writing_fails(tmp_path, monkeypatch, writer):
    path = tmp_path / "out"
    writer(path, output_trees())
    before = path.read_bytes()

    def trees_then_failure():
        yield output_trees()[0]
        raise OSError("No space left on device")  # the temp write fails midway

    with pytest.raises(OSError, match="No space left"):
        writer(path, trees_then_failure())
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["out"]  # the temp file is gone

    def failing_fsync(fd):
        raise OSError("I/O error")

    def failing_replace(source, target):
        raise OSError("Read-only file system")

    for name, failure, message in [
        ("fsync", failing_fsync, "I/O error"),  # written, not yet on disk
        ("replace", failing_replace, "Read-only"),  # written and synced, rename refused
    ]:
        with monkeypatch.context() as patch:
            patch.setattr(os, name, failure)
            with pytest.raises(OSError, match=message):
                writer(path, output_trees()[:1])
        assert path.read_bytes() == before and os.listdir(tmp_path) == ["out"]
    writer(path, output_trees()[:1])  # and a good write replaces it
    assert path.read_bytes() != before and os.listdir(tmp_path) == ["out"]


def test_tree_records_are_the_contract_dataclass():
    tree = output_trees()[0]
    assert isinstance(tree, Tree)
    assert (tree.tree_id, tree.field_id, tree.observations) == ("1", "M1", 12)


def test_every_field_of_tree_is_a_column_of_the_table():
    assert {f.name for f in TREE_FIELDS} == {f.name for f in dataclasses.fields(Tree)}
    assert [f.position for f in TREE_FIELDS] == list(range(len(TREE_FIELDS)))
    assert CSV_COLUMNS[: len(CONTRACT_CSV_COLUMNS)] == tuple(CONTRACT_CSV_COLUMNS)
    assert "reason" not in CSV_COLUMNS  # rejected.geojson's alone


def test_geojson_properties_follow_the_table():
    found, _, _ = output_trees()
    cues = {"evidence": -0.8, "texture_m": 0.012, "planar_share": 0.7, "intensity": 41.0}
    rejected = dataclasses.replace(found, status="rejected", reason="post", **cues)
    keys = [f.geojson for f in GEOJSON_FIELDS]
    # A found tree has no reason and no cues (not set): rejected.geojson's alone.
    optional = ["reason", *cues]
    assert list(_feature(found)["properties"]) == [k for k in keys if k not in optional]
    assert list(_feature(rejected)["properties"]) == keys
    assert _feature(rejected)["properties"]["reason"] == "post"
    assert {k: _feature(rejected)["properties"][k] for k in cues} == cues
    # The same values as trees.csv, as JSON: the cells of the columns both hold.
    cells = dict(zip(CSV_COLUMNS, csv_row(found), strict=True))
    properties = _feature(found)["properties"]
    assert cells["width_m"] == f"{properties['width_m']:.3f}"
    assert cells["first_seen"] == properties["first_seen"]
    assert cells["height_top_seen"] == "true" and properties["height_top_seen"] is True
    assert cells["width_sides_seen"] == "2" and properties["width_sides_seen"] == 2


def test_the_docs_field_table_is_the_code_table():
    """docs/georef.md's table of the output fields is `fields_markdown()`, so the docs cannot
    drift from pipeline/trees.py; on a change, paste the printed table into the page."""
    page = (REPO / "docs" / "georef.md").read_text()
    start = "<!-- fields: generated by treetraits.pipeline.trees.fields_markdown(); "
    table = page.split(start, 1)[1].split("\n", 1)[1].split("<!-- end of fields -->", 1)[0]
    assert table == fields_markdown(), f"docs/georef.md's table should be:\n{fields_markdown()}"
