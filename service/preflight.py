"""The checks a start of the service makes before it touches anything: one function that
`treetraits run` and `record` call at start and `treetraits config check` calls alone, so
the two can never disagree (docs/service.md).

`check_start(cfg)` reads the calibration and the field map, checks the keys that only make
sense together (the LiDAR's two ports, a sensor enabled) and where the outputs will go,
and returns what it read; a problem is a `ConfigError` naming the key. It opens no device
and creates nothing: binding the LiDAR's port is the one check only a real start can make.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from treetraits.drivers.calibration import Calibration, load_calibration
from treetraits.errors import ConfigError, TreetraitsError
from treetraits.service.config import ServiceConfig


@dataclass(frozen=True)
class StartInputs:
    """What a start read from the files the config names."""

    calibration: Calibration
    field_map: list  # FieldTree records; [] without a field map
    field_map_bytes: bytes | None  # the file as it is, for a recording's attachment


def check_start(cfg: ServiceConfig, *, process: bool = True, record: bool = False) -> StartInputs:
    """Every start-up check of `run` (`process`) or `record` that needs no device.
    `record`: a recording will be written into `record.dir` (run --record)."""
    _check_sensors(cfg)
    _check_camera_device(cfg)
    calibration = _calibration(cfg)
    field_map, field_map_bytes = _field_map(cfg)
    if process:
        _check_writable_dir("output.dir", Path(cfg.output.dir))
    if record:
        _check_writable_dir("record.dir", Path(cfg.record.dir))
    return StartInputs(calibration, field_map, field_map_bytes)


def _check_sensors(cfg: ServiceConfig) -> None:
    if not (cfg.lidar.enabled or cfg.camera.enabled or cfg.gnss.enabled or cfg.wheels.enabled):
        raise ConfigError(
            "no sensor enabled: set enabled = true in [lidar], [camera], [gnss] or [wheels]"
        )
    lidar = cfg.lidar
    # One socket per port: the same port twice cannot be bound (and would mix the
    # position packets into the data stream if it could).
    if lidar.enabled and lidar.telemetry_port == lidar.data_port:
        raise ConfigError(
            f"lidar.telemetry_port equals lidar.data_port ({lidar.data_port}): give the "
            "position packets their own port (the VLP-16's is 8308) or 0 to ignore them"
        )


def _check_camera_device(cfg: ServiceConfig) -> None:
    from treetraits.drivers.camera.sources import is_live_uri
    from treetraits.service.workers import is_video_file

    camera = cfg.camera
    if camera.enabled and not is_live_uri(camera.device) and not is_video_file(camera.device):
        raise ConfigError(
            f"camera.device: {camera.device}: no such video file; a camera is auto, "
            "usb:VID:PID, /dev/videoN, /dev/survey3n or a video file"
        )


def _calibration(cfg: ServiceConfig) -> Calibration:
    path = cfg.pipeline.calibration
    if not path:
        return Calibration()  # the documented defaults, said at start (describe_defaults)
    try:
        return load_calibration(Path(path))
    except TreetraitsError as exc:
        raise ConfigError(f"pipeline.calibration: {exc}") from exc


def _field_map(cfg: ServiceConfig) -> tuple[list, bytes | None]:
    from treetraits.pipeline.fieldmap import load_field_map

    path = cfg.pipeline.field_map
    if not path:
        return [], None
    try:
        return load_field_map(Path(path)), Path(path).read_bytes()
    except (TreetraitsError, OSError) as exc:
        raise ConfigError(f"pipeline.field_map: {exc}") from exc


def _check_writable_dir(key: str, directory: Path) -> None:
    """`directory` is one we could write in, or could be made: its nearest existing
    ancestor is a directory we may write to. Nothing is created."""
    existing = directory
    while not existing.exists() and existing.parent != existing:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{key}: {existing} is not a directory (in {directory})")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"{key}: {existing} is not writable (making {directory})")
