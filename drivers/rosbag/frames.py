"""The mounting rotation of a bag's IMU: which way its axes point in base_link.

A `sensor_msgs/Imu` gives rates and accelerations in its `header.frame_id`; the localiser
wants them in base_link (x forward, y left, z up). The rotation comes, in this order, from
the calibration's `T_base_imu`, from the bag's static transforms (`/tf_static`, chained
from base_link to the IMU's frame through any frames between), else none (the IMU's frame
is taken as base_link, as the Jackal MCU's IMU is). Only the rotation is applied: the lever
arm's centripetal and tangential accelerations (< 0.05 m/s^2 at 0.3 m and 0.4 rad/s) are
left in, as for the Jackal's own IMU. docs/import.md, "IMU mounting".
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable

import numpy as np

BASE_FRAME = "base_link"


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The rotation matrix of a (normalised here) quaternion."""
    q = np.array([x, y, z, w], dtype=float)
    norm = np.linalg.norm(q)
    if not np.isfinite(norm) or norm == 0:
        raise ValueError("quaternion of zero length")
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _name(frame: str) -> str:
    return frame.strip().lstrip("/")


class StaticFrames:
    """Static transforms (parent, child, R_parent_child) and the rotation between any two
    frames they connect."""

    def __init__(self, transforms: Iterable[tuple[str, str, np.ndarray]] = ()):
        self._edges: dict[str, list[tuple[str, np.ndarray]]] = {}
        for parent, child, rotation in transforms:
            self.add(parent, child, rotation)

    def add(self, parent: str, child: str, rotation: np.ndarray) -> None:
        parent, child = _name(parent), _name(child)
        self._edges.setdefault(parent, []).append((child, rotation))
        self._edges.setdefault(child, []).append((parent, rotation.T))

    def rotation(self, target: str, source: str) -> tuple[np.ndarray, list[str]] | None:
        """R_target_source (a vector in `source` to `target`) and the frames it passes,
        or None when no chain of transforms links them."""
        target, source = _name(target), _name(source)
        if target == source:
            return np.eye(3), [target]
        seen = {target: (np.eye(3), [target])}
        queue = deque([target])
        while queue:
            frame = queue.popleft()
            R, path = seen[frame]
            for child, step in self._edges.get(frame, ()):
                if child in seen:
                    continue
                seen[child] = (R @ step, [*path, child])
                if child == source:
                    return seen[child]
                queue.append(child)
        return None


def rotate(rotation: np.ndarray, vector: tuple[float, float, float]) -> tuple[float, ...]:
    return tuple(float(v) for v in rotation @ np.asarray(vector, dtype=float))
