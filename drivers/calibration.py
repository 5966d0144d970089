"""Calibration v1 (docs/architecture.md): camera model, reflectance, extrinsics, wheels.

One JSON object, loaded and checked once; a malformed file, a number that is not finite
or outside its physical range (`LIMITS`), or a missing required field is refused with a
message naming the field. Only the optional parts (`camera`, `reflectance`,
`wheels.ticks_per_rev`) fall back to the defaults below, and `Calibration.defaults` says
which did (docs/calibration.md). Transforms are 4x4 matrices named `T_target_source`:
`p_camera = T_camera_lidar @ p_lidar`; `base` is `base_footprint` (on the ground).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from treetraits.drivers.jsontext import JsonTooDeepError, loads_limited
from treetraits.errors import CalibrationError

BANDS = ("red", "green", "nir")


@dataclass(frozen=True)
class CameraModel:
    """Pinhole + OpenCV radial-tangential distortion (k1, k2, p1, p2, k3)."""

    width: int
    height: int
    K: np.ndarray  # 3x3
    dist: np.ndarray  # 5
    # Index of each band in the decoded (OpenCV BGR-ordered) image.
    channels: dict[str, int] = field(default_factory=lambda: {"red": 2, "green": 1, "nir": 0})


@dataclass(frozen=True)
class WheelGeometry:
    """`radius` (m) turns the Jackal's radians into metres; `track` is the effective track
    of the kinematics (a skid-steer Jackal slips when it turns: 0.37 m x 1.5);
    `ticks_per_rev` converts an encoder board's ticks."""

    radius: float = 0.098
    track: float = 0.555
    ticks_per_rev: float | None = None

    def metres(self, value: float, unit: str) -> float:
        if unit == "rad":
            return value * self.radius
        if unit == "ticks":
            if not self.ticks_per_rev:
                raise CalibrationError(
                    "wheel samples in ticks need calibration wheels.ticks_per_rev"
                )
            return value * 2 * math.pi * self.radius / self.ticks_per_rev
        if unit == "m":
            return value
        raise CalibrationError(f"unknown wheel unit {unit!r}; expected rad, ticks or m")


# Default LiDAR mount when none is given: a VLP-16 on a Jackal's top plate, 0.44 m above
# the ground (CitrusFarm's base_link -> lidar plus the Jackal's 0.0655 m to the ground).
DEFAULT_T_BASE_LIDAR = np.array(
    [[1, 0, 0, 0.04], [0, 1, 0, 0], [0, 0, 1, 0.4442], [0, 0, 0, 1]], dtype=float
)
# Raw 8-bit value to reflectance without a target calibration: v / 255.
DEFAULT_REFLECTANCE = (1.0 / 255.0, 0.0)

# What a calibration file must hold: the robot's own geometry. A default from another
# robot is wrong without a word (the Jackal's 0.444 m LiDAR height on CitrusFarm's
# 0.379 m mount), so it is never taken for these.
REQUIRED = ("T_base_lidar", "T_base_gnss", "wheels")
REQUIRED_WHEELS = ("radius", "track")

# The physical range of every number (closed intervals), and why (docs/calibration.md).
LIMITS: dict[str, tuple[float, float]] = {
    # From a small robot's 5 cm wheel to a tractor's rear tyre (1.9 m across).
    "wheels.radius": (0.01, 2.0),
    # A skid-steer's effective track reaches about 2x its 0.3-2.5 m geometric one.
    "wheels.track": (0.1, 6.0),
    # One count per turn to a 23-bit absolute encoder's 8.4 million (with quadrature).
    "wheels.ticks_per_rev": (1.0, 2.0**23 * 4),
    # Sensors sit on the robot: a tractor with an implement is under 10 m long.
    "translation": (-10.0, 10.0),
    # Image size: the largest machine-vision sensors are about 16k pixels wide.
    "camera.width": (1, 16384),
    "camera.height": (1, 16384),
    # A focal length over 100x the image width is a field of view under 0.6 degrees.
    "camera.focal_per_width": (0.0, 100.0),
    # Radial-tangential coefficients of real lenses are single digits; 100 is no lens.
    "camera.dist": (-100.0, 100.0),
    # Reflectance is 0..1 from an 8-bit value: gain up to 1 (1/255 is the full range).
    "reflectance.gain": (0.0, 1.0),
    "reflectance.offset": (-1.0, 1.0),
}


def _check_range(name: str, key: str, value: float, limit: str | None = None) -> None:
    low, high = LIMITS[limit or key]
    if not (math.isfinite(value) and low <= value <= high):
        raise CalibrationError(
            f"{name}: {key} must be in [{low:g}, {high:g}] ({_UNITS.get(limit or key, '')}), "
            f"got {value!r}"
        )


_UNITS = {
    "wheels.radius": "m",
    "wheels.track": "m",
    "wheels.ticks_per_rev": "counts per wheel turn",
    "translation": "m",
    "camera.width": "px",
    "camera.height": "px",
    "camera.focal_per_width": "focal length / image width",
    "camera.dist": "distortion coefficient",
    "reflectance.gain": "per 8-bit count",
    "reflectance.offset": "reflectance",
}


@dataclass(frozen=True)
class Calibration:
    camera: CameraModel | None = None
    # band -> (gain, offset): reflectance = gain * raw + offset
    reflectance: dict[str, tuple[float, float]] = field(
        default_factory=lambda: {b: DEFAULT_REFLECTANCE for b in BANDS}
    )
    T_camera_lidar: np.ndarray | None = None
    T_base_lidar: np.ndarray = field(default_factory=lambda: DEFAULT_T_BASE_LIDAR.copy())
    T_base_gnss: np.ndarray = field(default_factory=lambda: np.eye(4))
    wheels: WheelGeometry = field(default_factory=WheelGeometry)
    source: str = "defaults"
    # The IMU whose sensor_msgs/Imu a bag carries, in base_link (`treetraits import` turns
    # its axes into base_link's); None: not given (the import then asks the bag's frames).
    T_base_imu: np.ndarray | None = None
    # The parts the source did not give, which took their documented default ("camera":
    # no NDVI; "reflectance.nir": 1/255...): said aloud by the commands. A bare
    # `Calibration()` (no calibration anywhere) is all defaults.
    defaults: tuple[str, ...] = ("T_base_lidar", "T_base_gnss", "wheels", "camera")

    def describe_defaults(self) -> str | None:
        """One line naming what was not calibrated, or None when everything was given."""
        if not self.defaults:
            return None
        what = {
            "camera": "no camera (NDVI is left out)",
            "T_base_lidar": "the LiDAR on a Jackal's top plate (0.444 m up)",
            "T_base_gnss": "the GNSS antenna at base_footprint",
            "wheels": "a Jackal's wheels (radius 0.098 m, track 0.555 m)",
        }
        parts = [what.get(key, f"{key} = the default (v/255)") for key in self.defaults]
        return f"calibration {self.source}: documented defaults taken: " + "; ".join(parts)

    def to_json(self) -> dict[str, Any]:
        """The calibration v1 object (as stored in a recording's metadata)."""
        out: dict[str, Any] = {}
        if self.camera is not None:
            out["camera"] = {
                "width": self.camera.width,
                "height": self.camera.height,
                "K": self.camera.K.ravel().tolist(),
                "dist": self.camera.dist.tolist(),
                "channels": dict(self.camera.channels),
            }
        out["reflectance"] = {band: list(v) for band, v in self.reflectance.items()}
        if self.T_camera_lidar is not None:
            out["T_camera_lidar"] = self.T_camera_lidar.ravel().tolist()
        out["T_base_lidar"] = self.T_base_lidar.ravel().tolist()
        out["T_base_gnss"] = self.T_base_gnss.ravel().tolist()
        if self.T_base_imu is not None:
            out["T_base_imu"] = self.T_base_imu.ravel().tolist()
        wheels: dict[str, float] = {"radius": self.wheels.radius, "track": self.wheels.track}
        if self.wheels.ticks_per_rev:
            wheels["ticks_per_rev"] = self.wheels.ticks_per_rev
        out["wheels"] = wheels
        return out


def load_calibration(source: str | os.PathLike | Mapping[str, Any]) -> Calibration:
    """Read calibration v1 from a JSON file or an already parsed object."""
    name = "calibration"
    if isinstance(source, Mapping):
        data = source
    else:
        name = os.fspath(source)
        try:
            data = loads_limited(Path(source).read_text())
        except FileNotFoundError:
            raise CalibrationError(f"{name}: no such calibration file") from None
        except JsonTooDeepError as exc:
            raise CalibrationError(f"{name}: {exc}: not a calibration") from None
        except (json.JSONDecodeError, UnicodeDecodeError) as exc:
            raise CalibrationError(f"{name}: not valid JSON ({exc})") from exc
        except RecursionError:  # not with the depth limit; kept as the last guard
            raise CalibrationError(f"{name}: JSON nested too deeply to be a calibration") from None
        except OSError as exc:
            raise CalibrationError(
                f"{name}: cannot read the calibration file ({exc.strerror or exc})"
            ) from None
    if not isinstance(data, Mapping):
        raise CalibrationError(f"{name}: expected a JSON object at the top level")
    known = {
        "camera", "reflectance", "T_camera_lidar", "T_base_lidar", "T_base_gnss", "T_base_imu",
        "wheels",
    }  # fmt: skip
    unknown = sorted(set(data) - known)
    if unknown:
        raise CalibrationError(f"{name}: unknown field(s) {unknown}; known: {sorted(known)}")

    camera = _camera(name, data["camera"]) if "camera" in data else None
    t_camera_lidar = _transform(name, data, "T_camera_lidar", None)
    if camera is not None and t_camera_lidar is None:
        raise CalibrationError(f"{name}: camera given without T_camera_lidar")
    reflectance = _reflectance(name, data.get("reflectance", {}))
    wheels = _wheels(name, data.get("wheels", {}))
    missing = [key for key in REQUIRED if key not in data]
    missing += [
        f"wheels.{k}" for k in REQUIRED_WHEELS if "wheels" in data and k not in data["wheels"]
    ]
    if missing:
        raise CalibrationError(
            f"{name}: {', '.join(missing)} missing: the robot's own geometry has no default "
            "(docs/calibration.md)"
        )
    defaults = [] if camera is not None else ["camera"]
    if camera is not None:
        given = data.get("reflectance", {})
        defaults += [f"reflectance.{b}" for b in ("red", "nir") if b not in given]
    return Calibration(
        camera=camera,
        reflectance=reflectance,
        T_camera_lidar=t_camera_lidar,
        T_base_lidar=_transform(name, data, "T_base_lidar", DEFAULT_T_BASE_LIDAR),
        T_base_gnss=_transform(name, data, "T_base_gnss", np.eye(4)),
        wheels=wheels,
        T_base_imu=_transform(name, data, "T_base_imu", None),
        source=name,
        defaults=tuple(defaults),
    )


def _numbers(name: str, where: str, value: Any, count: int) -> np.ndarray:
    if (
        not isinstance(value, list)
        or len(value) != count
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise CalibrationError(f"{name}: {where} must be a list of {count} numbers, got {value!r}")
    array = np.asarray(value, dtype=float)
    if not np.isfinite(array).all():
        raise CalibrationError(f"{name}: {where} holds a non-finite number")
    return array


def _transform(name: str, data: Mapping, key: str, default: np.ndarray | None):
    if key not in data:
        return None if default is None else default.copy()
    matrix = _numbers(name, key, data[key], 16).reshape(4, 4)
    rotation = matrix[:3, :3]
    if not np.allclose(matrix[3], [0, 0, 0, 1]):
        raise CalibrationError(f"{name}: {key} last row must be 0 0 0 1")
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4) or np.linalg.det(rotation) < 0:
        raise CalibrationError(f"{name}: {key} rotation part is not a rotation (row-major 4x4?)")
    for axis, value in zip("xyz", matrix[:3, 3], strict=True):
        _check_range(name, f"{key} translation {axis}", float(value), "translation")
    return matrix


def _camera(name: str, value: Any) -> CameraModel:
    if not isinstance(value, Mapping):
        raise CalibrationError(f"{name}: camera must be an object")
    for key in ("width", "height", "K", "dist"):
        if key not in value:
            raise CalibrationError(f"{name}: camera.{key} is missing")
    width, height = value["width"], value["height"]
    if not (
        isinstance(width, int)
        and isinstance(height, int)
        and not isinstance(width, bool)
        and not isinstance(height, bool)
        and width > 0
        and height > 0
    ):
        raise CalibrationError(f"{name}: camera.width/height must be positive integers")
    _check_range(name, "camera.width", width)
    _check_range(name, "camera.height", height)
    k = _numbers(name, "camera.K", value["K"], 9).reshape(3, 3)
    if k[0, 0] <= 0 or k[1, 1] <= 0 or not np.allclose(k[2], [0, 0, 1]):
        raise CalibrationError(f"{name}: camera.K must be [fx,0,cx, 0,fy,cy, 0,0,1] with fx,fy > 0")
    for key, focal in (("camera.K fx", k[0, 0]), ("camera.K fy", k[1, 1])):
        _check_range(name, f"{key} / camera.width", float(focal / width), "camera.focal_per_width")
    # The principal point is where the optical axis meets the sensor: inside the image.
    if not (0 <= k[0, 2] <= width and 0 <= k[1, 2] <= height):
        raise CalibrationError(
            f"{name}: camera.K principal point ({k[0, 2]:g}, {k[1, 2]:g}) px must lie in the "
            f"{width}x{height} image"
        )
    dist = value["dist"]
    dist = _numbers(name, "camera.dist", dist, len(dist) if isinstance(dist, list) else 5)
    if len(dist) not in (4, 5):
        raise CalibrationError(f"{name}: camera.dist must hold 4 or 5 numbers (k1 k2 p1 p2 [k3])")
    for i, coefficient in enumerate(dist):
        _check_range(name, f"camera.dist[{i}]", float(coefficient), "camera.dist")
    dist = np.pad(dist, (0, 5 - len(dist)))
    channels = value.get("channels", {"red": 2, "green": 1, "nir": 0})
    if not isinstance(channels, Mapping):
        raise CalibrationError(f"{name}: camera.channels must be an object, e.g. {{'red': 2}}")
    channels = dict(channels)
    unknown = sorted(map(str, set(channels) - set(BANDS)))
    if unknown:
        raise CalibrationError(f"{name}: camera.channels: unknown band(s) {unknown}")
    for band in ("red", "nir"):
        if band not in channels:
            raise CalibrationError(f"{name}: camera.channels.{band} must be 0, 1 or 2")
    for band, index in channels.items():
        if isinstance(index, bool) or index not in (0, 1, 2):
            raise CalibrationError(f"{name}: camera.channels.{band} must be 0, 1 or 2")
    if len({channels[b] for b in channels}) != len(channels):
        raise CalibrationError(f"{name}: camera.channels gives two bands the same index")
    return CameraModel(width, height, k, dist, channels)


def _reflectance(name: str, value: Any) -> dict[str, tuple[float, float]]:
    if not isinstance(value, Mapping):
        raise CalibrationError(f"{name}: reflectance must be an object")
    out = {b: DEFAULT_REFLECTANCE for b in BANDS}
    for band, pair in value.items():
        if band not in BANDS:
            raise CalibrationError(f"{name}: reflectance.{band}: unknown band; known: {BANDS}")
        gain, offset = _numbers(name, f"reflectance.{band}", pair, 2)
        if gain <= 0:
            raise CalibrationError(f"{name}: reflectance.{band} gain must be positive")
        _check_range(name, f"reflectance.{band} gain", float(gain), "reflectance.gain")
        _check_range(name, f"reflectance.{band} offset", float(offset), "reflectance.offset")
        out[band] = (float(gain), float(offset))
    return out


def _wheels(name: str, value: Any) -> WheelGeometry:
    if not isinstance(value, Mapping):
        raise CalibrationError(f"{name}: wheels must be an object")
    defaults = WheelGeometry()
    numbers = {}
    for key in ("radius", "track", "ticks_per_rev"):
        if key in value:
            v = value[key]
            if not isinstance(v, int | float) or isinstance(v, bool) or not v > 0:
                raise CalibrationError(f"{name}: wheels.{key} must be a positive number")
            _check_range(name, f"wheels.{key}", float(v))
            numbers[key] = float(v)
    unknown = sorted(set(value) - {"radius", "track", "ticks_per_rev"})
    if unknown:
        raise CalibrationError(f"{name}: wheels: unknown field(s) {unknown}")
    return WheelGeometry(
        radius=numbers.get("radius", defaults.radius),
        track=numbers.get("track", defaults.track),
        ticks_per_rev=numbers.get("ticks_per_rev"),
    )
