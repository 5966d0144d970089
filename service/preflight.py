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
    # Permission problems found when checking as another user than the service's.
    notes: tuple[str, ...] = ()


def check_start(
    cfg: ServiceConfig, *, process: bool = True, record: bool = False, as_service: bool = True
) -> StartInputs:
    """Every start-up check of `run` (`process`) or `record` that needs no device.
    `record`: a recording will be written into `record.dir` (run --record).
    `as_service`: this process is the one that will write (run); False for `config
    check`, often run by an admin for a service that runs as its own user: a directory
    this user may not write is then a note, not an error (a file in the way still is)."""
    _check_sensors(cfg)
    _check_camera_device(cfg)
    calibration = _calibration(cfg)
    field_map, field_map_bytes = _field_map(cfg)
    notes = []
    for key, wanted, directory in (
        ("output.dir", process, cfg.output.dir),
        ("record.dir", record, cfg.record.dir),
    ):
        if not wanted:
            continue
        problem = _check_writable_dir(key, Path(directory))
        if problem and as_service:
            raise ConfigError(problem)
        if problem:
            notes.append(f"{problem} by this user (the service's user may differ)")
    return StartInputs(calibration, field_map, field_map_bytes, tuple(notes))


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


def _check_writable_dir(key: str, directory: Path) -> str | None:
    """`directory` is one we could write in, or could be made: its nearest existing
    ancestor is a directory. Nothing is created. A file in the way raises; what this
    user may not write or look into is returned as the problem."""
    existing = directory
    try:
        while not existing.exists() and existing.parent != existing:
            existing = existing.parent
        is_dir = existing.is_dir()
    except PermissionError:
        return f"{key}: {existing} cannot be looked into (making {directory})"
    if not is_dir:
        raise ConfigError(f"{key}: {existing} is not a directory (in {directory})")
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"{key}: {existing} is not writable (making {directory})"
    return None
