"""Calibration v1: the real CitrusFarm calibration (Survey3N + VLP-16 on a Jackal) and
malformed files refused with the field named."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tests.helpers.paths import CITRUSFARM
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR, Calibration, load_calibration
from treetraits.errors import CalibrationError


def test_citrusfarm_calibration_loads_with_its_numbers():
    calibration = load_calibration(CITRUSFARM)
    raw = json.loads(CITRUSFARM.read_text())
    camera = calibration.camera
    assert (camera.width, camera.height) == (1280, 720)
    assert camera.K[0, 0] == raw["camera"]["K"][0] and camera.K[1, 2] == raw["camera"]["K"][5]
    np.testing.assert_array_equal(camera.dist, raw["camera"]["dist"])
    assert camera.channels == {"red": 2, "green": 1, "nir": 0}
    np.testing.assert_array_equal(calibration.T_camera_lidar.ravel(), raw["T_camera_lidar"])
    assert calibration.T_base_lidar[2, 3] == pytest.approx(0.3787)
    assert calibration.T_base_gnss[0, 3] == pytest.approx(-0.18)
    assert calibration.wheels.radius == 0.098 and calibration.wheels.track == 0.37559
    # The LiDAR looks forward, the camera's optical axis (z) too: lidar +x -> camera +z.
    forward = calibration.T_camera_lidar @ np.array([1.0, 0, 0, 0])
    assert forward[2] > 0.99


def test_round_trip_through_json():
    calibration = load_calibration(CITRUSFARM)
    again = load_calibration(calibration.to_json())
    np.testing.assert_array_equal(again.camera.K, calibration.camera.K)
    np.testing.assert_array_equal(again.T_camera_lidar, calibration.T_camera_lidar)
    assert again.reflectance == calibration.reflectance and again.wheels == calibration.wheels


def _citrusfarm() -> dict:
    return json.loads(CITRUSFARM.read_text())


def test_optional_parts_take_their_default_and_say_so():
    raw = _citrusfarm()
    del raw["camera"], raw["T_camera_lidar"]
    calibration = load_calibration(raw)
    assert calibration.camera is None and calibration.T_camera_lidar is None
    assert calibration.reflectance["nir"] == (1 / 255, 0.0)
    assert calibration.defaults == ("camera",)
    assert "no camera (NDVI is left out)" in calibration.describe_defaults()
    # CitrusFarm's file has a camera but no reflectance fit: both bands at v/255, said.
    assert load_calibration(CITRUSFARM).defaults == ("reflectance.red", "reflectance.nir")
    # No calibration anywhere: every default, the Jackal's LiDAR mount among them.
    bare = Calibration()
    np.testing.assert_array_equal(bare.T_base_lidar, DEFAULT_T_BASE_LIDAR)
    assert "0.444 m" in bare.describe_defaults()


@pytest.mark.parametrize(
    ("drop", "named"),
    [
        (("T_base_lidar",), "T_base_lidar missing"),
        (("T_base_gnss",), "T_base_gnss missing"),
        (("wheels",), "wheels missing"),
        (("wheels.radius",), "wheels.radius missing"),
        (("wheels.track", "T_base_lidar"), "T_base_lidar, wheels.track missing"),
    ],
)
def test_a_missing_geometry_key_is_an_error_naming_it(drop, named):
    """The issue's case: without T_base_lidar the Jackal's 0.444 m was taken silently for
    CitrusFarm's 0.379 m mount."""
    raw = _citrusfarm()
    for key in drop:
        section, _, sub = key.partition(".")
        del (raw[section] if sub else raw)[sub or section]
    with pytest.raises(CalibrationError, match=re.escape(named)):
        load_calibration(raw)


def _set(raw: dict, path: str, value) -> dict:
    """`raw` with the value at `path` ("wheels.radius", "T_base_lidar[3]") replaced."""
    key, _, index = path.partition("[")
    section, _, sub = key.partition(".")
    holder = raw[section] if sub else raw
    name = sub or section
    if index:
        holder[name][int(index.rstrip("]"))] = value
    else:
        holder[name] = value
    return raw


@pytest.mark.parametrize(
    ("path", "value", "message"),
    [
        ("wheels.radius", float("inf"), "wheels.radius must be in [0.01, 2] (m), got inf"),
        ("wheels.radius", 1e400, "wheels.radius must be in [0.01, 2]"),
        ("wheels.radius", 5.0, "wheels.radius must be in [0.01, 2]"),
        ("wheels.track", float("inf"), "wheels.track must be in [0.1, 6] (m)"),
        ("wheels.track", 0.001, "wheels.track must be in [0.1, 6]"),
        ("wheels.ticks_per_rev", 0.5, "wheels.ticks_per_rev must be in [1, "),
        ("T_base_lidar[3]", 1e300, "T_base_lidar translation x must be in [-10, 10] (m)"),
        ("T_base_gnss[11]", -50.0, "T_base_gnss translation z must be in [-10, 10]"),
        ("T_camera_lidar[7]", 1e30, "T_camera_lidar translation y must be in [-10, 10]"),
        ("camera.width", 10**30, "camera.width must be in [1, 16384] (px)"),
        ("camera.height", 100000, "camera.height must be in [1, 16384] (px)"),
        ("camera.width", True, "camera.width/height must be positive integers"),
        ("camera.K[0]", 1e9, "camera.K fx / camera.width must be in [0, 100]"),
        ("camera.K[2]", 5000.0, "principal point (5000, 376.057) px must lie in the 1280x720"),
        ("camera.dist[0]", 1e6, "camera.dist[0] must be in [-100, 100]"),
    ],
)
def test_absurd_numbers_are_refused_naming_the_key_and_range(path, value, message):
    """Non-finite and physically absurd values (issue 14, case 6): refused with the key
    and its allowed range, through the file as a user would write it."""
    raw = _set(_citrusfarm(), path, value)
    with pytest.raises(CalibrationError, match=re.escape(message)):
        load_calibration(raw)


def test_absurd_numbers_in_a_file_exit_2_with_one_line(tmp_path, capsys):
    """`Infinity` and `1e400` as JSON spells them, through a command's error boundary."""
    from treetraits.cli import main

    text = CITRUSFARM.read_text().replace('"radius": 0.098', '"radius": Infinity')
    assert "Infinity" in text
    bad = tmp_path / "calibration.json"
    bad.write_text(text)
    status = main(
        ["sim", "--goal", "1", "--calibration", str(bad), "--out", str(tmp_path / "s.mcap")]
    )
    err = capsys.readouterr().err
    assert status == 2
    assert err.startswith("treetraits: error: ") and err.count("\n") == 1, err
    assert "wheels.radius must be in [0.01, 2] (m), got inf" in err
    assert not (tmp_path / "s.mcap").exists()
    bad.write_text(CITRUSFARM.read_text().replace('"track": 0.37559', '"track": 1e400'))
    status = main(
        ["sim", "--goal", "1", "--calibration", str(bad), "--out", str(tmp_path / "s.mcap")]
    )
    assert status == 2 and "wheels.track must be in [0.1, 6]" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"T_base_lidar": [1, 0, 0]}, "T_base_lidar must be a list of 16 numbers"),
        ({"T_base_gnss": [2, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]}, "not a rotation"),
        ({"T_base_gnss": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 1, 1]}, "last row"),
        ({"wheels": {"radius": -1}}, "wheels.radius must be a positive number"),
        ({"wheels": {"diameter": 0.2}}, "unknown field"),
        ({"reflectance": {"blue": [1, 0]}}, "reflectance.blue"),
        ({"reflectance": {"nir": [0, 0.1]}}, "gain must be positive"),
        ({"reflectance": {"nir": [2.0, 0.1]}}, "reflectance.nir gain must be in [0, 1]"),
        ({"lens": {}}, "unknown field(s) ['lens']"),
    ],
)
def test_malformed_fields_are_named(change, message):
    with pytest.raises(CalibrationError, match=re.escape(message)):
        load_calibration({**_citrusfarm(), **change})


def test_malformed_camera_is_named(tmp_path):
    raw = json.loads(CITRUSFARM.read_text())
    raw["camera"]["K"][8] = 2.0
    with pytest.raises(CalibrationError, match=r"camera\.K"):
        load_calibration(raw)
    raw = json.loads(CITRUSFARM.read_text())
    raw["camera"]["channels"] = {"red": 0, "green": 1, "nir": 0}
    with pytest.raises(CalibrationError, match="same index"):
        load_calibration(raw)
    raw = json.loads(CITRUSFARM.read_text())
    del raw["T_camera_lidar"]
    with pytest.raises(CalibrationError, match="without T_camera_lidar"):
        load_calibration(raw)
    broken = tmp_path / "calib.json"
    broken.write_text("{ not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(broken)
    with pytest.raises(CalibrationError, match="no such calibration file"):
        load_calibration(tmp_path / "missing.json")
