"""Calibration v1: the real CitrusFarm calibration (Survey3N + VLP-16 on a Jackal) and
malformed files refused with the field named."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from tests.conftest import FIXTURES
from treetraits.drivers.calibration import DEFAULT_T_BASE_LIDAR, load_calibration
from treetraits.errors import CalibrationError

CITRUSFARM = FIXTURES / "citrusfarm_calib" / "citrusfarm_calibration_v1.json"


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


def test_defaults_when_parts_are_missing():
    calibration = load_calibration({})
    assert calibration.camera is None and calibration.T_camera_lidar is None
    np.testing.assert_array_equal(calibration.T_base_lidar, DEFAULT_T_BASE_LIDAR)
    assert calibration.reflectance["nir"] == (1 / 255, 0.0)


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
        ({"lens": {}}, "unknown field(s) ['lens']"),
    ],
)
def test_malformed_fields_are_named(change, message):
    with pytest.raises(CalibrationError, match=re.escape(message)):
        load_calibration(change)


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
