"""A Jackal MCU emulator: the bytes the robot's microcontroller sends over `/dev/jackal`
once the host has asked for its topics: TopicInfo for its publishers, time requests every
few seconds, jackal_msgs/Feedback at 50 Hz with each wheel's cumulative travel (rad),
which slips on the ground by a few percent, and sensor_msgs/Imu on `imu/data_raw` at
50 Hz (body rates and specific force, no orientation), as the real MCU publishes them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from treetraits.drivers.calibration import WheelGeometry
from treetraits.firmware_bridge.jackal import messages as m
from treetraits.firmware_bridge.jackal import rosserial as rs

FEEDBACK_TOPIC_ID = 137  # the MCU's choice; the host learns it from TopicInfo
IMU_TOPIC_ID = 138
IMU_TOPIC = "imu/data_raw"
IMU_FRAME_ID = "imu_link"  # the Jackal URDF's IMU frame (the real MCU's is unconfirmed)
GRAVITY_MPS2 = 9.80665  # standard gravity; a level robot at rest reads +g on z


@dataclass(frozen=True)
class WheelSettings:
    rate_hz: float = 50.0
    slip_left: float = 0.02  # wheels turn this much more than the ground moves
    slip_right: float = 0.015
    noise_rad: float = 0.002
    # The MCU's IMU (imu/data_raw, at rate_hz with the Feedback, as the Jackal's firmware
    # publishes both at 50 Hz); False for a platform without one (a retrofit tractor).
    imu: bool = True
    # A MEMS IMU of the Jackal's class (consumer/industrial 6-axis parts): gyro white noise
    # ~0.005 rad/s per 50 Hz sample (0.3 deg/s, a noise density of ~0.01 deg/s/sqrt(Hz)
    # over a ~25 Hz bandwidth) and a turn-on bias of ~0.002 rad/s (0.1 deg/s) per axis;
    # accelerometer white noise ~0.05 m/s^2 (5 mg) and a bias of ~0.02 m/s^2 (2 mg) per
    # axis after factory calibration. Biases are drawn once per run.
    gyro_noise_rps: float = 0.005
    gyro_bias_rps: float = 0.002
    accel_noise_mps2: float = 0.05
    accel_bias_mps2: float = 0.02
    # Half-width (s) of the central differences that give rates and accelerations from
    # the true pose: 0.04 s, i.e. what an IMU's ~25 Hz digital low-pass filter passes.
    imu_difference_s: float = 0.04


def imu_truth(trajectory, t_ns: int, h_s: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """The true body angular velocity (rad/s) and specific force (m/s^2, gravity included:
    +g on z when level at rest) at t_ns, by central differences over +-h_s of the 6-DoF
    `trajectory` (x, y, z, yaw, pitch, roll at ns times; pitch and roll absent = level)."""
    from treetraits.sim.lidar import rotation_matrices

    h = int(h_s * 1e9)
    t = np.array([t_ns - h, t_ns, t_ns + h], dtype=np.int64)
    pose = trajectory(t)
    position = np.column_stack(pose[:3])
    rotation = rotation_matrices(*pose[3:6]) if len(pose) >= 6 else rotation_matrices(pose[3])
    # Angular velocity in the body frame: R(t-h)^T R(t+h) = exp([w] 2h).
    delta = rotation[0].T @ rotation[2]
    angle = math.acos(max(-1.0, min(1.0, (np.trace(delta) - 1) / 2)))
    skew = delta - delta.T
    axis = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
    scale = angle / (2 * math.sin(angle)) if angle > 1e-9 else 0.5
    omega = axis * scale / (2 * h_s)
    acceleration = (position[2] - 2 * position[1] + position[0]) / h_s**2
    specific_force = rotation[1].T @ (acceleration + np.array([0.0, 0.0, GRAVITY_MPS2]))
    return omega, specific_force


class JackalMcuEmulator:
    def __init__(
        self,
        wheels: WheelGeometry,
        settings: WheelSettings | None = None,
        rng: np.random.Generator | None = None,
        imu_rng: np.random.Generator | None = None,
    ):
        self.wheels = wheels
        self.settings = settings or WheelSettings()
        self.rng = rng or np.random.default_rng(0)
        # The IMU's noise has a generator of its own: the wheels' draws (and everything
        # sharing `rng`) are the same with the IMU on or off.
        self.imu_rng = imu_rng or np.random.default_rng([0, 3])
        s = self.settings
        self._gyro_bias = self.imu_rng.normal(0, s.gyro_bias_rps, 3)
        self._accel_bias = self.imu_rng.normal(0, s.accel_bias_mps2, 3)
        self._imu_seq = 0
        self._left = self._right = 0.0
        self._last: tuple[float, float, float] | None = None
        self._last_z: float | None = None

    def handshake(self) -> bytes:
        """What the MCU answers to the host's topic request."""
        info = rs.TopicInfo(FEEDBACK_TOPIC_ID, "feedback", m.FEEDBACK.name, m.FEEDBACK.md5, 512)
        out = rs.encode_frame(rs.ID_PUBLISHER, info.encode())
        if self.settings.imu:
            imu = rs.TopicInfo(IMU_TOPIC_ID, IMU_TOPIC, m.IMU.name, m.IMU.md5, 512)
            out += rs.encode_frame(rs.ID_PUBLISHER, imu.encode())
        return out + rs.encode_frame(rs.ID_TIME)

    def imu(self, t_ns: int, angular_velocity, specific_force) -> bytes:
        """One imu/data_raw frame: the true body rates (rad/s) and specific force (m/s^2)
        with the run's biases and white noise; no orientation (covariance[0] = -1)."""
        s = self.settings
        gyro = np.asarray(angular_velocity) + self._gyro_bias
        gyro = gyro + self.imu_rng.normal(0, s.gyro_noise_rps, 3)
        accel = np.asarray(specific_force) + self._accel_bias
        accel = accel + self.imu_rng.normal(0, s.accel_noise_mps2, 3)
        gyro_var, accel_var = s.gyro_noise_rps**2, s.accel_noise_mps2**2
        payload = m.IMU.encode(
            {
                "header": {"seq": self._imu_seq, "stamp": t_ns, "frame_id": IMU_FRAME_ID},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 0.0},
                "orientation_covariance": [-1.0] + [0.0] * 8,
                "angular_velocity": dict(zip("xyz", map(float, gyro), strict=True)),
                "angular_velocity_covariance": [gyro_var, 0, 0, 0, gyro_var, 0, 0, 0, gyro_var],
                "linear_acceleration": dict(zip("xyz", map(float, accel), strict=True)),
                "linear_acceleration_covariance": [
                    accel_var, 0, 0, 0, accel_var, 0, 0, 0, accel_var
                ],
            }
        )  # fmt: skip
        self._imu_seq += 1
        return rs.encode_frame(IMU_TOPIC_ID, payload)

    def feedback(self, t_ns: int, x: float, y: float, yaw: float, z: float | None = None) -> bytes:
        """One Feedback frame for the robot at (x, y, yaw) at time t_ns; with `z` (on
        uneven ground) the wheels roll the 3-D distance."""
        if self._last is not None:
            lx, ly, lyaw = self._last
            if z is None or self._last_z is None:
                distance = math.hypot(x - lx, y - ly)
            else:
                distance = math.hypot(x - lx, y - ly, z - self._last_z)
            if math.cos(math.atan2(y - ly, x - lx) - lyaw) < 0:
                distance = -distance  # reversing
            turn = (yaw - lyaw + math.pi) % (2 * math.pi) - math.pi
            track = self.wheels.track
            s = self.settings
            self._left += (distance - turn * track / 2) * (1 + s.slip_left) / self.wheels.radius
            self._right += (distance + turn * track / 2) * (1 + s.slip_right) / self.wheels.radius
            self._left += self.rng.normal(0, s.noise_rad)
            self._right += self.rng.normal(0, s.noise_rad)
        self._last = (x, y, yaw)
        self._last_z = z
        drivers = [
            {
                "current": 1.0,
                "duty_cycle": 0.2,
                "bridge_temperature": 35.0,
                "motor_temperature": 40.0,
                "measured_velocity": 0.0,
                "measured_travel": travel,
                "driver_fault": False,
            }
            for travel in (self._left, self._right)
        ]
        payload = m.FEEDBACK.encode(
            {
                "header": {"seq": 0, "stamp": t_ns, "frame_id": ""},
                "drivers": drivers,
                "pcb_temperature": 38.0,
                "mcu_temperature": 45.0,
                "commanded_mode": 0,
                "actual_mode": 0,
            }
        )
        return rs.encode_frame(FEEDBACK_TOPIC_ID, payload)
