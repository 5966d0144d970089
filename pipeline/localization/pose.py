"""The robot's pose: what localisation makes and the mapper, the outputs and the exports read."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class Pose:
    """x, y (, z), yaw (, roll, pitch) of `base_link` in `frame` at `t` (ns since the epoch).

    yaw: radians, counter-clockwise from the frame's x axis (east in `utm`). roll and pitch
    (radians, REP-103): roll about the robot's x (forward; positive = left side up), pitch
    about its y (left; positive = nose down), applied as R = Rz(yaw) Ry(pitch) Rx(roll);
    0 where no IMU gives them. `covariance` is the 3x3 covariance of (x, y, yaw).
    """

    t: int
    x: float
    y: float
    yaw: float
    covariance: np.ndarray
    frame: str
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
