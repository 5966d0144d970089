"""The motion channels of recording format v1.1: a robot's own odometry and an IMU that
arrive as numbers (a ROS `nav_msgs/Odometry` and `sensor_msgs/Imu`, `rosbag_import`),
not as the bytes of a link treetraits reads itself (docs/recording.md).

- `/wheels/odometry` (`treetraits-odometry`): float64 little-endian forward speed (m/s,
  along base_link's x) and yaw rate (rad/s, about its z), the twist the robot's controller
  reported. `OdometryIntegrator` turns a stream of them into cumulative left/right wheel
  travel in metres (`WheelSample`, unit "m"), so the localiser reads them as it reads the
  Jackal's wheels.
- `/imu/data` (`treetraits-imu`): float64 little-endian angular velocity x y z (rad/s) and
  linear acceleration x y z (m/s^2) in the IMU's frame, which is taken as base_link (as the
  Jackal MCU's IMU is).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from treetraits.drivers.records import WheelSample
from treetraits.errors import ParseError

_ODOMETRY = struct.Struct("<2d")
_IMU = struct.Struct("<6d")
# A gap longer than this between two odometry messages is not integrated (the robot's
# controller stopped, or the bag has a hole): no travel is invented across it.
MAX_ODOMETRY_GAP_NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class ImuSample:
    t_host: int
    angular_velocity: tuple[float, float, float]  # rad/s
    linear_acceleration: tuple[float, float, float]  # m/s^2


def encode_odometry(speed_mps: float, yaw_rate: float) -> bytes:
    return _ODOMETRY.pack(speed_mps, yaw_rate)


def decode_odometry(data: bytes) -> tuple[float, float]:
    if len(data) != _ODOMETRY.size:
        raise ParseError(f"odometry message of {len(data)} bytes, expected {_ODOMETRY.size}")
    return _ODOMETRY.unpack(data)


def encode_imu(angular_velocity, linear_acceleration) -> bytes:
    return _IMU.pack(*angular_velocity, *linear_acceleration)


def decode_imu(data: bytes, t_host: int) -> ImuSample:
    if len(data) != _IMU.size:
        raise ParseError(f"IMU message of {len(data)} bytes, expected {_IMU.size}")
    values = _IMU.unpack(data)
    return ImuSample(t_host, values[:3], values[3:])


class OdometryIntegrator:
    """Twist samples to cumulative wheel travel. A sample's speeds hold over the interval
    that ends at it (a diff-drive controller reports the last interval's wheel motion), so
    the travel from t[k-1] to t[k] is v[k] x dt; each side moves v -/+ w x track / 2, which
    the localiser turns back into v x dt and w x dt with the same track."""

    def __init__(self, track_m: float):
        self.track = track_m
        self._t: int | None = None
        self._left = 0.0
        self._right = 0.0

    def push(self, data: bytes, t_host: int) -> WheelSample:
        speed, yaw_rate = decode_odometry(data)
        if self._t is not None and 0 < t_host - self._t <= MAX_ODOMETRY_GAP_NS:
            dt = (t_host - self._t) / 1e9
            self._left += (speed - yaw_rate * self.track / 2) * dt
            self._right += (speed + yaw_rate * self.track / 2) * dt
        self._t = t_host if self._t is None else max(self._t, t_host)
        return WheelSample(t_host, self._left, self._right, "m")
