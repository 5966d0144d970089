"""Roll and pitch of `base_link` from the IMU's gyro and accelerometer (no magnetometer).

A complementary filter on the direction of "up" seen from the robot (`AttitudeFilter`):

- the gyro carries the attitude from one sample to the next (it follows a change of
  slope as it happens, and is deaf to vibration and to the robot's own acceleration, but
  its bias makes it drift without bound);
- the accelerometer measures the specific force f = a - g: at rest or at constant
  velocity, minus gravity, i.e. "up" with magnitude g, which pins roll and pitch down for
  good but is buried in vibration and tilted by every acceleration. The acceleration the
  wheels know of (forward speed changes and the centripetal v * yaw rate of a turn) is
  taken out first; a sample whose magnitude is still more than `attitude_accel_gate_mps2`
  from g is a shock or a hard acceleration and corrects nothing;
- each accepted sample pulls the gyro's estimate towards the accelerometer's with the
  weight dt / (tau + dt): errors of the gyro decay with the time constant tau, noise of
  the accelerometer is averaged over about tau. This is a first-order complementary
  filter rather than a Kalman filter because its one parameter has a physical meaning
  that can be checked (how long a tilt error lives) and because the noise densities a
  Kalman filter needs are not published for the Jackal's IMU;
- the gyro bias is learned while the robot stands still (wheels at rest, or without
  wheels a gyro reading below `gyro_rest_rad_s`): the gyro then reads its bias alone,
  averaged with the time constant `gyro_bias_time_constant_s`; while moving, slowly
  (`gyro_bias_motion_time_constant_s`), from the tilt error the accelerometer keeps
  correcting (the integral term of a Mahony filter), for the roll and pitch axes only.

The IMU's frame is taken to be `base_link` (the Jackal's MCU IMU sits on the main board,
axes aligned with the chassis, x forward, y left, z up: REP-103). A tilted or rotated
mounting would need a calibration `T_base_imu`, which the calibration format does not
have yet.

Angles follow REP-103: roll about x (forward), pitch about y (left), yaw about z (up),
R = Rz(yaw) Ry(pitch) Rx(roll). Pure and deterministic: samples in, angles out.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from treetraits.pipeline.localization.config import LocalizationConfig

GRAVITY = 9.80665  # m/s^2, standard gravity
# A gap between IMU samples longer than this is an outage: the gyro is not integrated
# across it (the next accelerometer sample is taken as it is).
_MAX_GAP_NS = 500_000_000


def rotation_zyx(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (REP-103): body (x forward, y left, z up) to world."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`np.cross` of two 3-vectors, the same products and differences: np.cross's generic
    broadcasting costs ~15x more on one pair, and the filter takes two per IMU sample."""
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def roll_pitch_from_up(up: np.ndarray) -> tuple[float, float]:
    """Roll and pitch from the world's up direction seen in the body frame.

    With R = Rz Ry Rx, up in the body is R^T (0, 0, 1) = (-sin p, sin r cos p, cos r cos p).
    """
    roll = math.atan2(up[1], up[2])
    pitch = math.atan2(-up[0], math.hypot(up[1], up[2]))
    return roll, pitch


@dataclass
class AttitudeStats:
    samples: int = 0
    corrections: int = 0  # accelerometer samples that corrected the attitude
    gated: int = 0  # accelerometer samples refused by the magnitude gate
    rest_samples: int = 0  # samples that taught the gyro bias
    gaps: int = 0  # outages longer than _MAX_GAP_NS


class AttitudeFilter:
    """Complementary filter for roll and pitch; feed samples in time order.

    `add_imu(t, gyro, accel)`: t in ns (host clock, like every t_host), gyro in rad/s and
    accel (specific force, gravity included: about +9.81 on z when level) in m/s^2, both
    in base_link. `add_speed(t, speed)`: the forward speed from the wheels (m/s), to take
    the robot's own acceleration out of the accelerometer and to know when it is at rest.
    """

    def __init__(self, config: LocalizationConfig | None = None):
        self.config = config or LocalizationConfig()
        self.stats = AttitudeStats()
        self.bias = np.zeros(3)  # gyro bias, rad/s
        self._up: np.ndarray | None = None  # world up in base_link, unit vector
        self._t: int | None = None
        self._speed: float | None = None
        self._speed_t: int | None = None
        self._forward_accel = 0.0
        self._yaw_rate: float | None = None
        self._times: deque[int] = deque()
        self._angles: deque[tuple[float, float]] = deque()

    # ---- inputs ---------------------------------------------------------------------------

    def add_speed(self, t: int, speed: float) -> None:
        """The wheels' forward speed at `t`; its change is the forward acceleration
        (low-passed over 0.1 s: wheel speeds from 50 Hz travel differences are noisy)."""
        if self._speed is not None and self._speed_t is not None and t > self._speed_t:
            dt = (t - self._speed_t) / 1e9
            raw = (speed - self._speed) / dt
            w = dt / (0.1 + dt)
            self._forward_accel += w * (raw - self._forward_accel)
        self._speed, self._speed_t = speed, t

    def add_imu(self, t: int, gyro, accel) -> None:
        c = self.config
        gyro = np.asarray(gyro, dtype=float)
        accel = np.asarray(accel, dtype=float)
        self.stats.samples += 1
        previous, self._t = self._t, t if self._t is None else max(self._t, t)
        dt = 0.0 if previous is None else max(t - previous, 0) / 1e9
        if dt * 1e9 > _MAX_GAP_NS:
            self.stats.gaps += 1
            dt = 0.0

        if self._at_rest(gyro, accel):
            self.stats.rest_samples += 1
            w = dt / (c.gyro_bias_time_constant_s + dt) if dt > 0 else 0.0
            self.bias += w * (gyro - self.bias)
        rate = gyro - self.bias
        if self._up is not None:
            self._yaw_rate = float(rate @ self._up)

        if self._up is not None and dt > 0:
            # The world stands still, the body turns by rate: up, seen from the body,
            # turns the other way (first order over one 20 ms step is exact to 1e-7 rad).
            self._up = self._up - cross3(rate, self._up) * dt
            self._up /= np.linalg.norm(self._up)

        gravity = self._gravity(accel, rate)
        if gravity is not None:
            measured = gravity / np.linalg.norm(gravity)
            if self._up is None:
                self._up = measured  # the first one is taken as it is
            else:
                if dt > 0:
                    # In motion the bias shows as a tilt error the accelerometer keeps
                    # pulling back (a Mahony-style integral term): a rate error d held
                    # for tau leaves an error of d tau, so this learns d with the time
                    # constant gyro_bias_motion_time_constant_s. Only its part across
                    # up is seen; the bias about the vertical is learned at rest.
                    k = 1.0 / (c.gyro_bias_motion_time_constant_s * c.attitude_time_constant_s)
                    self.bias -= k * cross3(measured, self._up) * dt
                w = dt / (c.attitude_time_constant_s + dt)
                self._up = self._up + w * (measured - self._up)
                self._up /= np.linalg.norm(self._up)
            self.stats.corrections += 1
        if self._up is not None:
            self._append(self._t, roll_pitch_from_up(self._up))

    # ---- outputs --------------------------------------------------------------------------

    @property
    def attitude(self) -> tuple[float, float] | None:
        """The latest (roll, pitch), radians; None before the first accepted sample."""
        return roll_pitch_from_up(self._up) if self._up is not None else None

    def attitude_at(self, t: int) -> tuple[float, float] | None:
        """(roll, pitch) at `t`, interpolated between the samples around it; None outside
        the kept history (`history_s`)."""
        times = self._times
        if not times or t < times[0] or t > times[-1]:
            return None
        i = bisect.bisect_left(times, t)
        if times[i] == t or i == 0:
            return self._angles[i]
        w = (t - times[i - 1]) / (times[i] - times[i - 1])
        (r0, p0), (r1, p1) = self._angles[i - 1], self._angles[i]
        return r0 + w * (r1 - r0), p0 + w * (p1 - p0)

    def settled_until(self) -> int | None:
        """Attitudes at times up to this one are final (as `Localizer.settled_until`)."""
        return self._times[-2] if len(self._times) >= 2 else None

    @property
    def yaw_rate(self) -> float | None:
        """The latest bias-corrected turn rate about the world's vertical (rad/s): the
        gyro's rate projected on up (the localiser's heading follows it)."""
        return self._yaw_rate

    # ---- internals ------------------------------------------------------------------------

    def _at_rest(self, gyro: np.ndarray, accel: np.ndarray) -> bool:
        c = self.config
        if abs(np.linalg.norm(accel) - GRAVITY) > c.attitude_accel_gate_mps2:
            return False
        if self._speed is not None:
            return abs(self._speed) <= c.rest_speed_mps and bool(
                np.all(np.abs(gyro) <= c.gyro_rest_rad_s)
            )
        return bool(np.all(np.abs(gyro) <= c.gyro_rest_rad_s))

    def _gravity(self, accel: np.ndarray, rate: np.ndarray) -> np.ndarray | None:
        """The accelerometer with the acceleration the wheels explain taken out: minus
        gravity's direction ("up"), or None when the rest is no longer about g long."""
        motion = np.zeros(3)
        if self._speed is not None:
            # Forward acceleration along x, centripetal v * yaw rate along y (a turn to the
            # left, positive yaw rate, pushes the robot's path to the left: +y).
            motion[0] = self._forward_accel
            motion[1] = self._speed * rate[2]
        gravity = accel - motion
        if abs(np.linalg.norm(gravity) - GRAVITY) > self.config.attitude_accel_gate_mps2:
            self.stats.gated += 1
            return None
        return gravity

    def _append(self, t: int, angles: tuple[float, float]) -> None:
        if self._times and self._times[-1] == t:
            self._angles[-1] = angles
            return
        self._times.append(t)
        self._angles.append(angles)
        keep = self.config.history_s * 1e9
        while self._times and t - self._times[0] > keep:
            self._times.popleft()
            self._angles.popleft()
