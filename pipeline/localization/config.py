"""Settings of the localisation, each with the reason for its default."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from treetraits.drivers.calibration import WheelGeometry
from treetraits.errors import ConfigError

__all__ = ["DEFAULT_SIGMA_PER_HDOP", "LocalizationConfig", "WheelGeometry"]

# Horizontal 1-sigma per unit of HDOP when a receiver sends no GST, by GGA quality.
# Typical receiver accuracies: autonomous ~2.5 m, SBAS/DGPS ~0.7 m, RTK fixed ~2 cm,
# RTK float ~0.3 m. Quality 0 (invalid) and 6 (the receiver's own dead reckoning) are
# never used.
DEFAULT_SIGMA_PER_HDOP = {1: 2.5, 2: 0.7, 3: 2.5, 4: 0.02, 5: 0.3, 9: 1.0}


@dataclass(frozen=True)
class LocalizationConfig:
    # Wheel odometry noise. Variances grow in proportion to the motion (a random walk in
    # distance and angle), so the model does not depend on the wheel sample rate:
    # travel error per sqrt(metre) travelled (slip on grass and soil), heading error per
    # sqrt(radian) turned (a skid steer scrubs when it turns) and per sqrt(metre) travelled
    # (unequal slip of the two sides bends a straight line).
    odom_sigma_per_sqrt_m: float = 0.05
    odom_yaw_sigma_per_sqrt_rad: float = 0.10
    odom_yaw_sigma_per_sqrt_m: float = math.radians(1.0)

    # With a gyro (the Jackal MCU's IMU), the heading between wheel samples follows it.
    # Its noise: angle random walk per sqrt(second) (a MEMS gyro's 0.01 deg/s/sqrt(Hz) is
    # 2e-4; 1e-3 leaves room for the chassis' vibration) and the bias left after the
    # at-rest learning (a MEMS bias wanders by ~0.3 deg/s with temperature; learned at
    # each stop to ~0.005 rad/s).
    gyro_yaw_sigma_per_sqrt_s: float = 1e-3
    gyro_bias_sigma_rad_s: float = 0.005

    sigma_per_hdop: dict[int, float] = field(default_factory=lambda: dict(DEFAULT_SIGMA_PER_HDOP))
    # A GST sigma below this is not believed (multipath under canopy is not in GST).
    min_fix_sigma_m: float = 0.01
    # Mahalanobis gate for fixes: chi-square, 2 dof, p = 0.999.
    fix_gate_chi2: float = 13.8
    # After this many fixes in a row fail the gate, the filter trusts GNSS again (its
    # own estimate has drifted, e.g. after wheel slip) and re-initialises position.
    max_rejected_in_a_row: int = 5

    # True heading (HDT/THS) standard deviation: a dual-antenna baseline of ~1 m.
    heading_sigma_rad: float = math.radians(1.0)
    # Course over ground is used as heading only while moving forward at least this fast
    # and not turning faster than this; its sigma is this many m/s of velocity noise
    # over the speed.
    cog_min_speed_mps: float = 0.3
    cog_max_yaw_rate: float = math.radians(10.0)
    cog_velocity_sigma_mps: float = 0.05
    # The heading counts as known once its sigma is below this. Until then position fixes
    # do not move yaw, and the first heading measurement is taken as it is.
    known_yaw_sigma_rad: float = math.radians(20.0)
    # With no heading source at all: the heading the robot starts with (ENU, radians
    # from east; a stock Jackal has no earth-referenced heading) and how little we trust it.
    initial_yaw_rad: float = 0.0
    initial_yaw_sigma_rad: float = math.pi

    # GNSS time. A fix describes the robot at its epoch's UTC; its sentences arrive later
    # by the receiver's computation and the serial link (a u-blox F9P at 115200 baud:
    # 30-60 ms; at 9600 baud a burst of GGA+RMC+GST takes 0.25 s alone); at 2 m/s, 60 ms
    # is 12 cm along the path. When a fix arrives within this of its UTC the host clock
    # is taken to be on UTC (NTP or PPS) and the fix is placed at its UTC: the delay is
    # then measured, not assumed.
    gnss_clock_tolerance_s: float = 1.0
    # Else (a host clock that is not on UTC) the fix is placed this long before it
    # arrived: a receiver's latency at 115200 baud. Measure yours: `treetraits nmea info`
    # of a recording made with the host on NTP prints it.
    gnss_latency_s: float = 0.05

    # Pose history kept for `pose_at`, seconds.
    history_s: float = 30.0

    # Roll and pitch from the IMU (pipeline/localization/attitude.py, docs/localization.md).

    # Time constant of the complementary filter, seconds: a tilt error of the gyro (its
    # bias, a missed rate) decays with it, and the accelerometer's vibration is averaged
    # over it. 1 s averages ~50 samples of a grove floor's shaking (a 1 m/s^2 vibration
    # leaves ~0.5 deg) and keeps a 0.01 rad/s bias to 0.6 deg, while the gyro itself
    # follows a change of slope as it happens.
    attitude_time_constant_s: float = 1.0
    # An accelerometer sample corrects the attitude only if, once the acceleration the
    # wheels explain is taken out, its magnitude is within this of g (m/s^2): more is a
    # shock (a root or a pothole: 0.5-1 g for a sample or two). The floor's ordinary
    # shaking (~1 m/s^2, zero mean) is averaged by the filter and let through; a
    # horizontal acceleration a changes the magnitude only by a^2/2g, so the gate cannot
    # see one: that is why the acceleration the wheels know of is taken out first.
    attitude_accel_gate_mps2: float = 2.0
    # Gyro bias learning: while the robot stands still the gyro reads its bias alone,
    # averaged over this many seconds (a MEMS bias wanders over minutes with temperature;
    # 5 s of rest average its noise below 0.001 rad/s).
    gyro_bias_time_constant_s: float = 5.0
    # While driving, the bias of the roll and pitch axes is learned from the tilt error
    # the accelerometer keeps correcting, over this many seconds: slow against the filter's
    # 1 s, so a turn the wheels mis-explain for a few seconds teaches it little.
    gyro_bias_motion_time_constant_s: float = 20.0
    # At rest means: the wheels slower than this (m/s) and every gyro axis below this
    # (rad/s; 3 deg/s, above a MEMS gyro's bias, below any real turn). Without wheel data
    # the gyro alone decides.
    rest_speed_mps: float = 0.02
    gyro_rest_rad_s: float = 0.05

    # De-skew each scan with the motion during its sweep: a 100 ms rotation at 2 m/s
    # while turning at 0.5 rad/s smears a wall 10 m away by 20 cm and bends it by 0.5 m.
    deskew: bool = True
    # Poses are sampled across the sweep this often (seconds) and interpolated per point:
    # at 1 rad/s the pose changes by 10 mrad in 10 ms, which a straight line follows to
    # well below a millimetre.
    deskew_step_s: float = 0.01

    def __post_init__(self) -> None:
        positive = (
            "odom_sigma_per_sqrt_m",
            "odom_yaw_sigma_per_sqrt_rad",
            "odom_yaw_sigma_per_sqrt_m",
            "gyro_yaw_sigma_per_sqrt_s",
            "gyro_bias_sigma_rad_s",
            "min_fix_sigma_m",
            "fix_gate_chi2",
            "heading_sigma_rad",
            "cog_velocity_sigma_mps",
            "known_yaw_sigma_rad",
            "initial_yaw_sigma_rad",
            "history_s",
            "gnss_clock_tolerance_s",
            "attitude_time_constant_s",
            "attitude_accel_gate_mps2",
            "gyro_bias_time_constant_s",
            "gyro_bias_motion_time_constant_s",
            "rest_speed_mps",
            "gyro_rest_rad_s",
            "deskew_step_s",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"localization.{name} must be a finite number > 0, got {value}")
        for name in ("cog_min_speed_mps", "cog_max_yaw_rate", "gnss_latency_s"):
            if not getattr(self, name) >= 0:
                raise ConfigError(f"localization.{name} must be >= 0")
        if not isinstance(self.deskew, bool):
            raise ConfigError(f"localization.deskew must be true or false, got {self.deskew!r}")
        if self.deskew_step_s > 0.05:
            raise ConfigError(
                "localization.deskew_step_s must be <= 0.05 (two poses per 100 ms sweep at "
                f"least), got {self.deskew_step_s}"
            )
        if self.max_rejected_in_a_row < 1:
            raise ConfigError("localization.max_rejected_in_a_row must be >= 1")
        for quality, sigma in self.sigma_per_hdop.items():
            if not (isinstance(quality, int) and 0 <= quality <= 9):
                raise ConfigError(
                    f"localization.sigma_per_hdop: keys are GGA qualities 0-9, got {quality!r}"
                )
            if not (math.isfinite(sigma) and sigma > 0):
                raise ConfigError(f"localization.sigma_per_hdop.{quality} must be > 0")
