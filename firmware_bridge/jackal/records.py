"""What the Jackal session yields besides `WheelSample`: typed views of the MCU's messages.

Every record carries `t_host` (ns since the Unix epoch, when the bytes that completed it were
read) and the MCU topic it came on; the ones decoded from a message keep its exact payload.
`stamp_ns` is the message header's stamp: the MCU's clock, which the host's time replies keep
set to the host's realtime clock, so it is comparable to `t_host` (but not a substitute).
"""

from __future__ import annotations

from dataclasses import dataclass

Vector = tuple[float, float, float]
Covariance = tuple[float, ...]  # 9 values, row-major 3x3, as ROS sends them


@dataclass(frozen=True, slots=True)
class SerialChunk:
    """Bytes exactly as read from the MCU port, in read order: what `/wheels/jackal` records."""

    t_host: int
    data: bytes


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """The link changed state: "connected" (port open, topics requested), "configured" (every
    required topic announced), "disconnected" (port lost or closed; `detail` says why)."""

    t_host: int
    state: str
    detail: str = ""


@dataclass(frozen=True, slots=True)
class DriveUnit:
    """jackal_msgs/DriveFeedback: one side's motor driver and motor."""

    current: float  # battery -> MOSFET bridge, A
    duty_cycle: float  # bridge duty cycle
    bridge_temperature: float  # deg C
    motor_temperature: float  # deg C
    measured_velocity: float  # wheel, rad/s
    measured_travel: float  # wheel, cumulative rad (a float32 on the MCU)
    driver_fault: bool


@dataclass(frozen=True, slots=True)
class JackalFeedback:
    """jackal_msgs/Feedback (50 Hz): both drive units, board temperatures, control modes.

    `commanded_mode`/`actual_mode` use the Drive modes (0 velocity, 1 PWM, 2 effort,
    -1 none); they differ when the motors are disabled (e-stop) or in over-current.
    """

    t_host: int
    topic: str
    seq: int
    stamp_ns: int
    frame_id: str
    left: DriveUnit
    right: DriveUnit
    pcb_temperature: float  # deg C
    mcu_temperature: float  # deg C
    commanded_mode: int
    actual_mode: int
    payload: bytes

    @property
    def driver_fault(self) -> bool:
        return self.left.driver_fault or self.right.driver_fault


@dataclass(frozen=True, slots=True)
class JackalStatus:
    """jackal_msgs/Status (1 Hz, and at once when the stop loop changes)."""

    t_host: int
    topic: str
    seq: int
    stamp_ns: int
    frame_id: str
    hardware_id: str  # firmware source commit
    mcu_uptime_ns: int
    connection_uptime_ns: int
    drivers_active: bool
    driver_external_stop_present: bool
    driver_external_stop_stopped: bool
    measured_battery: float  # V, averaged over the period
    measured_12v: float  # V
    measured_5v: float  # V
    drive_current: float  # A, averaged
    user_current: float  # A
    computer_current: float  # A
    total_current: float  # A
    total_current_peak: float  # A, highest 1 ms window
    total_power_consumed: float  # Wh since power-on
    payload: bytes


@dataclass(frozen=True, slots=True)
class JackalImu:
    """sensor_msgs/Imu from the MCU (`imu/data_raw`: rates and accelerations, no orientation;
    ROS marks an absent orientation with covariance[0] = -1)."""

    t_host: int
    topic: str
    seq: int
    stamp_ns: int
    frame_id: str
    orientation: tuple[float, float, float, float]  # x, y, z, w
    orientation_covariance: Covariance
    angular_velocity: Vector  # rad/s
    angular_velocity_covariance: Covariance
    linear_acceleration: Vector  # m/s^2
    linear_acceleration_covariance: Covariance
    payload: bytes


@dataclass(frozen=True, slots=True)
class JackalMagnetometer:
    """sensor_msgs/MagneticField (`unit` "T") or, on older firmware, geometry_msgs/Vector3Stamped
    (`unit` "", the scale is not documented)."""

    t_host: int
    topic: str
    seq: int
    stamp_ns: int
    frame_id: str
    field: Vector
    covariance: Covariance | None
    unit: str
    payload: bytes


@dataclass(frozen=True, slots=True)
class JackalNmea:
    """One NMEA sentence the MCU relayed from the stock GPS (nmea_msgs/Sentence or a
    std_msgs/String on an NMEA topic). `raw` is the string's bytes as sent, usually without
    the trailing CR LF; `stamp_ns` is 0 for std_msgs/String (no header)."""

    t_host: int
    topic: str
    stamp_ns: int
    raw: bytes
    payload: bytes

    @property
    def sentence(self) -> str:
        return self.raw.decode("ascii", errors="replace").rstrip("\r\n")


@dataclass(frozen=True, slots=True)
class McuLog:
    """A rosserial_msgs/Log line from the firmware: level 0 debug, 1 info, 2 warn, 3 error,
    4 fatal."""

    t_host: int
    level: int
    level_name: str
    msg: str
