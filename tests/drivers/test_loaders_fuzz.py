"""Property tests: the loaders of the files a user hands a command (calibration, field
map, service config, a recording's metadata and attachment) give a typed error or a
result, never anything else (issue 14: 0 tracebacks).

Inputs: arbitrary JSON documents; the real CitrusFarm calibration with any one value
replaced by an arbitrary JSON value; valid files with bytes flipped, inserted or cut;
documents nested up to thousands of levels deep (the explicit depth limit,
`drivers/jsontext.py`).
"""

from __future__ import annotations

import contextlib
import json
import math
import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tests.helpers.fuzz import cuts, edits, mutate
from tests.helpers.paths import CITRUSFARM, REPO
from treetraits.drivers.calibration import Calibration, load_calibration
from treetraits.drivers.jsontext import MAX_DEPTH, JsonTooDeepError, json_depth, loads_limited
from treetraits.errors import CalibrationError, ConfigError, SourceError
from treetraits.pipeline.fieldmap import FieldTree, load_field_map, parse_geojson
from treetraits.service.config import ServiceConfig, load_config

CONFIG = REPO / "systemd" / "config.toml"
FIELD_MAP_GEOJSON = json.dumps(
    {
        "type": "FeatureCollection",
        "features": [
            {
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [-80.11 - i * 1e-5, 26.37]},
                "properties": {"id": f"T{i}", "row": "1"},
            }
            for i in range(3)
        ],
    }
)
FIELD_MAP_CSV = "id,lat,lon,row\nT0,26.37,-80.11,1\nT1,26.37,-80.11001,1\n"

CONFIG_KEYS = [
    "dir",
    "data_port",
    "telemetry_port",
    "silence_s",
    "baudrate",
    "lidar_packets",
    "max_file_mb",
    "export_every_s",
    "calibration",
    "method",
    "y",
]
FUZZ = settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
_WORK = tempfile.TemporaryDirectory(prefix="treetraits-loaders-fuzz-")
WORK = Path(_WORK.name)

CALIBRATION_KEYS = [
    "camera",
    "reflectance",
    "T_camera_lidar",
    "T_base_lidar",
    "T_base_gnss",
    "wheels",
    "width",
    "height",
    "K",
    "dist",
    "channels",
    "red",
    "green",
    "nir",
    "radius",
    "track",
    "ticks_per_rev",
    "type",
    "features",
    "geometry",
    "coordinates",
    "properties",
    "id",
    "row",
    "Feature",
    "FeatureCollection",
]
scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=8)
    | st.sampled_from(CALIBRATION_KEYS)
)
json_values = st.recursive(
    scalars,
    lambda children: (
        st.lists(children, max_size=17)
        | st.dictionaries(st.sampled_from(CALIBRATION_KEYS) | st.text(max_size=6), children)
    ),
    max_leaves=40,
)


def _write(name: str, data: str | bytes) -> Path:
    path = WORK / name
    if isinstance(data, str):
        data = data.encode("utf-8", "surrogatepass")
    path.write_bytes(data)
    return path


def _calibration_ok(source) -> None:
    try:
        result = load_calibration(source)
    except CalibrationError:
        return
    assert isinstance(result, Calibration)
    # What is accepted is finite: the ranges hold.
    assert math.isfinite(result.wheels.radius) and 0.01 <= result.wheels.radius <= 2.0
    assert abs(result.T_base_lidar[:3, 3]).max() <= 10


def _field_map_ok(path: Path) -> None:
    try:
        trees = load_field_map(path)
    except ConfigError:
        return
    assert all(isinstance(t, FieldTree) for t in trees)


def _config_ok(path: Path) -> None:
    try:
        cfg = load_config(path)
    except ConfigError:
        return
    assert isinstance(cfg, ServiceConfig)


@FUZZ
@given(json_values)
def test_any_json_document_as_calibration(value):
    _calibration_ok(_write("any.json", json.dumps(value)))
    if isinstance(value, dict):
        _calibration_ok(value)  # as a recording's metadata hands it over


def _paths(value, prefix=()):
    """Every (path) into a JSON document."""
    yield prefix
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            yield from _paths(item, (*prefix, i))


CITRUSFARM_PATHS = [p for p in _paths(json.loads(CITRUSFARM.read_text())) if p]


@FUZZ
@given(st.sampled_from(CITRUSFARM_PATHS), json_values, st.booleans())
def test_the_real_calibration_with_one_value_replaced(path, value, delete):
    """Deep inside the checks: a channel index that is a list, a K entry that is text, a
    wheel radius of 1e30, a missing dist."""
    raw = json.loads(CITRUSFARM.read_text())
    holder = raw
    for key in path[:-1]:
        holder = holder[key]
    if delete and isinstance(holder, dict):
        del holder[path[-1]]
    else:
        holder[path[-1]] = value
    _calibration_ok(raw)
    _calibration_ok(_write("replaced.json", json.dumps(raw)))


@FUZZ
@given(edits, cuts)
def test_a_damaged_calibration_file(change, cut):
    _calibration_ok(_write("damaged.json", mutate(CITRUSFARM.read_bytes(), change, cut)))


@FUZZ
@given(json_values)
def test_any_json_document_as_field_map(value):
    _field_map_ok(_write("any.geojson", json.dumps(value)))
    with contextlib.suppress(ConfigError):  # a recording's attachment
        parse_geojson(json.dumps(value), "attached field map")


@FUZZ
@given(st.sampled_from(["map.geojson", "map.csv", "map.txt"]), edits, cuts)
def test_a_damaged_field_map_file(name, change, cut):
    original = FIELD_MAP_CSV if name == "map.csv" else FIELD_MAP_GEOJSON
    _field_map_ok(_write(name, mutate(original.encode(), change, cut)))


@FUZZ
@given(edits, cuts)
def test_a_damaged_config_file(change, cut):
    _config_ok(_write("config.toml", mutate(CONFIG.read_bytes(), change, cut)))


@FUZZ
@given(
    st.dictionaries(
        st.sampled_from(["output", "lidar", "gnss", "queues", "record", "pipeline", "x"]),
        st.dictionaries(
            st.sampled_from(CONFIG_KEYS),
            scalars.filter(lambda v: v is not None),
        ),
    )
)
def test_any_config_values(document):
    """Values of any type and size in known keys: a ConfigError naming the key, or a config."""
    lines = []
    for section, keys in document.items():
        lines.append(f"[{section}]")
        for key, value in keys.items():
            lines.append(f"{key} = {_toml(value)}")
    _config_ok(_write("values.toml", "\n".join(lines) + "\n"))


def _toml(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return (
            "nan"
            if math.isnan(value)
            else ("inf" if value > 0 else "-inf")
            if math.isinf(value)
            else repr(value)
        )
    if isinstance(value, int):
        return str(value)
    return json.dumps(value)


@pytest.mark.parametrize("depth", [MAX_DEPTH + 1, 999, 1001, 100_000])
@pytest.mark.parametrize("bracket", ["[", '{"a":'])
def test_deep_nesting_is_refused_by_the_explicit_limit(depth, bracket):
    """Below, at and past Python's recursion limit: always the loader's own error, naming
    the file and the limit, never a RecursionError."""
    close = "]" if bracket == "[" else "}"
    text = bracket * depth + "1" + close * depth
    path = _write("deep.json", text)
    with pytest.raises(CalibrationError, match=rf"deep\.json: JSON nested {MAX_DEPTH + 1}\+"):
        load_calibration(path)
    geojson = _write("deep.geojson", '{"type": "FeatureCollection", "features": ' + text + "}")
    with pytest.raises(ConfigError, match=r"deep\.geojson: JSON nested .* not a field map"):
        load_field_map(geojson)
    with pytest.raises(JsonTooDeepError):
        loads_limited(text)


def test_the_depth_limit_counts_brackets_outside_strings_only():
    assert json_depth('{"a": "[[[[{{{{", "b": [[1]]}') == 3
    assert json_depth('["\\"[[[["]') == 1
    # Our formats nest 5 levels at most: far inside the limit.
    assert json_depth(FIELD_MAP_GEOJSON) == 5 <= MAX_DEPTH
    assert json_depth(CITRUSFARM.read_text()) <= 3


def test_a_recording_whose_metadata_calibration_is_nested_too_deeply(tmp_path):
    """Our writers never store such metadata: it is built with the MCAP library itself."""
    from mcap.writer import Writer

    from treetraits.drivers import recording as rec

    deep = "[" * 5000 + "]" * 5000
    path = tmp_path / "deep.mcap"
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library="test")
        writer.add_metadata(
            rec.METADATA_NAME, {"format_version": "1", "software": "test", "calibration": deep}
        )
        writer.finish()
    refused = r"calibration in the 'treetraits' metadata is not JSON"
    with pytest.raises(SourceError, match=refused), rec.read_recording(path):
        pass


def _small_recording() -> bytes:
    """A recording with every kind of record a reader meets: metadata (the CitrusFarm
    calibration), messages in a few chunks, the field map attached."""
    from treetraits.drivers import recording as rec

    path = WORK / "small-source.mcap"
    path.unlink(missing_ok=True)
    calibration = json.loads(CITRUSFARM.read_text())
    with rec.RecordingWriter(path, calibration=calibration, chunk_size=2000) as writer:
        for i in range(60):
            writer.write(rec.GNSS_NMEA, b"$GPGGA,%06d*00\r\n" % i, 10**18 + i, 10**18 + i)
        writer.attach(rec.FIELD_MAP_NAME, FIELD_MAP_GEOJSON.encode(), rec.FIELD_MAP_MEDIA_TYPE)
    return path.read_bytes()


SMALL_RECORDING = _small_recording()


@FUZZ
@given(edits, cuts)
# Found by this test: 128 written over the top byte of the attachment's data length
# (2^63 + ...), which mcap hands to read(): an OverflowError, not counted as damage.
@example(change=[(20168, 0, 128)], cut=None)
def test_a_damaged_recording_reads_or_is_refused(change, cut):
    """A recording's metadata, attachments and messages, read back from damaged bytes:
    read as far as they go (the damage counted), or a SourceError; nothing else."""
    from treetraits.drivers import recording as rec

    path = _write("damaged.mcap", mutate(SMALL_RECORDING, change, cut))
    try:
        with rec.read_recording(path) as recording:
            messages = list(recording)
            recording.attachments  # noqa: B018 - reading them is the test
            assert len(messages) <= 60
            if not change and cut is None:
                assert len(messages) == 60 and not recording.lost_data
    except SourceError:
        pass
