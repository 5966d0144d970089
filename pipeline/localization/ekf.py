"""The pose filter: an extended Kalman filter on (x, y, yaw) in the UTM grid (filterpy).

Prediction integrates wheel-odometry increments (distance, turn) with noise that grows
with the motion; updates take GNSS antenna positions (with the lever arm to the robot
centre) and headings. Each update is gated by its Mahalanobis distance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from treetraits.pipeline.localization.utm import wrap_angle


@dataclass(frozen=True, slots=True)
class Innovation:
    """What an update saw: its squared Mahalanobis distance and whether it was applied."""

    mahalanobis2: float
    applied: bool


def _wrap_yaw_residual(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    residual = np.subtract(a, b)
    residual[-1] = wrap_angle(float(residual[-1]))
    return residual


def rotate_xy(vector: np.ndarray, yaw: float) -> np.ndarray:
    """A robot-frame (x forward, y left) vector in the grid, at heading `yaw`."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([c * vector[0] - s * vector[1], s * vector[0] + c * vector[1]])


class PoseFilter:
    """x = [x, y, yaw]; all angles ENU (counter-clockwise from east), metres."""

    def __init__(self, x: float, y: float, yaw: float, covariance: np.ndarray):
        from filterpy.kalman import ExtendedKalmanFilter  # heavy: scipy.stats

        self._ekf = ExtendedKalmanFilter(dim_x=3, dim_z=2)
        self._ekf.x = np.array([x, y, wrap_angle(yaw)], dtype=float)
        self._ekf.P = np.array(covariance, dtype=float)

    @property
    def state(self) -> np.ndarray:
        return self._ekf.x.copy()

    @property
    def covariance(self) -> np.ndarray:
        return self._ekf.P.copy()

    def predict(self, distance: float, turn: float, sigma_distance: float, sigma_turn: float):
        """Move by `distance` along the mean heading of a step that turns by `turn`."""
        x, y, yaw = self._ekf.x
        mid = yaw + turn / 2
        c, s = math.cos(mid), math.sin(mid)
        jacobian = np.array([[1.0, 0.0, -distance * s], [0.0, 1.0, distance * c], [0, 0, 1.0]])
        # Odometry noise enters through the increments: Q = G diag(var) G^T.
        g = np.array([[c, -distance * s / 2], [s, distance * c / 2], [0.0, 1.0]])
        q = g @ np.diag([sigma_distance**2, sigma_turn**2]) @ g.T
        self._ekf.x = np.array([x + distance * c, y + distance * s, wrap_angle(yaw + turn)])
        self._ekf.P = jacobian @ self._ekf.P @ jacobian.T + q

    def update_antenna(
        self,
        z: np.ndarray,
        covariance: np.ndarray,
        lever_arm: np.ndarray,
        gate_chi2: float,
        observe_yaw: bool = True,
    ) -> Innovation:
        """A GNSS position of the antenna, which sits at `lever_arm` (x forward, y left,
        metres) from the robot centre.

        With `observe_yaw` False the update moves the position only. While the heading is
        unknown (a wide prior), the linearised position update can swing yaw to a wrong
        solution that later headings are then gated against (a robot that starts by turning
        ends up mapped backwards); the lever arm's unknown direction is added to the noise.
        """
        ox, oy = float(lever_arm[0]), float(lever_arm[1])

        def h(state: np.ndarray) -> np.ndarray:
            c, s = math.cos(state[2]), math.sin(state[2])
            return np.array([state[0] + c * ox - s * oy, state[1] + s * ox + c * oy])

        def jacobian(state: np.ndarray) -> np.ndarray:
            c, s = math.cos(state[2]), math.sin(state[2])
            yaw_column = (-s * ox - c * oy, c * ox - s * oy) if observe_yaw else (0.0, 0.0)
            return np.array([[1.0, 0.0, yaw_column[0]], [0.0, 1.0, yaw_column[1]]])

        if not observe_yaw:
            self._ekf.P[:2, 2] = 0.0
            self._ekf.P[2, :2] = 0.0
            covariance = np.asarray(covariance, float) + np.eye(2) * (ox * ox + oy * oy)
        return self._gated_update(
            np.asarray(z, float), covariance, h, jacobian, np.subtract, gate_chi2
        )

    def update_yaw(self, yaw: float, sigma: float, gate_chi2: float) -> Innovation:
        def h(state: np.ndarray) -> np.ndarray:
            return np.array([state[2]])

        def jacobian(state: np.ndarray) -> np.ndarray:
            return np.array([[0.0, 0.0, 1.0]])

        return self._gated_update(
            np.array([yaw]), np.array([[sigma**2]]), h, jacobian, _wrap_yaw_residual, gate_chi2
        )

    @property
    def yaw_sigma(self) -> float:
        return math.sqrt(max(float(self._ekf.P[2, 2]), 0.0))

    def reset_yaw(self, yaw: float, sigma: float, lever_arm: np.ndarray | None = None) -> None:
        """Take a heading as it is, forgetting the old one and its correlations. With the
        antenna's `lever_arm` (x forward, y left), the robot turns about the antenna, not
        about its centre: the antenna's position is what the fixes measured, and the centre
        was placed from it with the old heading."""
        if lever_arm is not None:
            old, new = float(self._ekf.x[2]), wrap_angle(yaw)
            self._ekf.x[:2] += rotate_xy(lever_arm, old) - rotate_xy(lever_arm, new)
        self._ekf.x[2] = wrap_angle(yaw)
        self._ekf.P[2, :] = 0.0
        self._ekf.P[:, 2] = 0.0
        self._ekf.P[2, 2] = sigma**2

    def reset_position(self, x: float, y: float, covariance_xy: np.ndarray) -> None:
        """Jump to a trusted position, forgetting the correlation with yaw."""
        self._ekf.x[:2] = (x, y)
        self._ekf.P[:2, :] = 0.0
        self._ekf.P[:, :2] = 0.0
        self._ekf.P[:2, :2] = covariance_xy

    def _gated_update(self, z, covariance, h, jacobian, residual, gate_chi2) -> Innovation:
        ekf = self._ekf
        ekf.dim_z = len(z)
        hj = jacobian(ekf.x)
        innovation = residual(z, h(ekf.x))
        s = hj @ ekf.P @ hj.T + covariance
        d2 = float(innovation @ np.linalg.solve(s, innovation))
        if d2 > gate_chi2:
            return Innovation(d2, applied=False)
        ekf.update(z, jacobian, h, R=covariance, residual=residual)
        ekf.x[2] = wrap_angle(float(ekf.x[2]))
        return Innovation(d2, applied=True)
