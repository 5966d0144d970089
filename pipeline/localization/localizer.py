"""Wheel samples and GNSS epochs in, the robot's pose in UTM out, at any recent time.

Until the first good fix the robot is only known in `odom` (dead reckoning from where it
started). The first good fix sets the datum: the UTM zone, and the filter's start.
Heading comes from a true heading (HDT/THS) when the receiver has one, else from course
over ground while driving straight forward, else from the configured initial heading.
Fixes that disagree with the prediction beyond the gate are rejected; when GNSS goes
away the pose keeps following the wheels and its uncertainty grows; when it comes back
the first fixes pull the pose back in.

Feed events in time order (the service merges its queues; replay sorts by `t_host`).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from treetraits.drivers.records import Fix, WheelSample
from treetraits.pipeline.localization.config import LocalizationConfig, WheelGeometry
from treetraits.pipeline.localization.ekf import PoseFilter, rotate_xy
from treetraits.pipeline.localization.pose import Pose
from treetraits.pipeline.localization.utm import UtmGrid, true_heading_to_grid_yaw, wrap_angle

# A wheel step implying more than this speed is a counter reset, not motion.
_MAX_WHEEL_SPEED_MPS = 10.0


@dataclass(frozen=True, slots=True)
class FixVerdict:
    used: bool
    reason: str  # "datum", "accepted", "rejected", "reset", or why it was not usable
    mahalanobis2: float | None = None


@dataclass
class LocalizerStats:
    wheel_samples: int = 0
    wheel_resets: int = 0
    fixes: int = 0
    fixes_used: int = 0
    fixes_rejected: int = 0
    fixes_unusable: int = 0
    position_resets: int = 0
    heading_resets: int = 0  # first heading once unknown, or several in a row disagreeing
    headings_used: int = 0
    courses_used: int = 0
    gyro_samples: int = 0
    latency_ms: float | None = None  # arrival of the last fix after its UTC, host on UTC


# Wheel samples older than this (before a fix) mean there is no odometry right now.
WHEELS_GONE_NS = 1_000_000_000
# A gyro silent for this long (ten samples at the Jackal's 50 Hz) is gone: the wheels turn.
GYRO_GONE_NS = 200_000_000


@dataclass
class _Motion:
    """Recent speed and yaw rate from the wheels, to judge course over ground."""

    speed: float = 0.0
    yaw_rate: float = 0.0


@dataclass
class _History:
    times: deque = field(default_factory=deque)
    poses: deque = field(default_factory=deque)


class Localizer:
    def __init__(
        self,
        config: LocalizationConfig | None = None,
        wheels: WheelGeometry | None = None,
        T_base_gnss: np.ndarray | None = None,
    ):
        """`wheels` and `T_base_gnss` (the antenna lever arm, 4x4) are calibration, not
        settings: they come from the robot's calibration file."""
        self.config = config or LocalizationConfig()
        self.wheels = wheels or WheelGeometry()
        self.stats = LocalizerStats()
        self.grid: UtmGrid | None = None
        self._filter: PoseFilter | None = None
        self._odom = np.zeros(3)  # dead-reckoned x, y, yaw in `odom`
        self._last_wheels: WheelSample | None = None
        self._gyro_t: int | None = None
        self._gyro_turn = 0.0  # integrated since the last wheel sample, rad
        self._motion = _Motion()
        self._moved = False  # a wheel step seen: `_motion` is measured
        self._rejected_in_a_row = 0
        self._headings_rejected_in_a_row = 0
        # The variance (m^2) of the last fix used: the least a reported position's can be
        # (`_reported_covariance`).
        self._fix_variance = 0.0
        self._t = 0
        # The host clock's offset from UTC where a UTC source measures it (a PPS-locked
        # VLP-16: `lidar_clock.LidarUtcClock`), else None.
        self.host_minus_utc: int | None = None
        self._odom_history = _History()
        self._utm_history = _History()
        lever_pose = np.eye(4) if T_base_gnss is None else T_base_gnss
        lever = np.asarray(lever_pose, dtype=float).reshape(4, 4)[:3, 3]
        self._lever_arm = lever[:2]

    # ---- inputs ---------------------------------------------------------------------------

    def add_wheels(self, sample: WheelSample) -> None:
        self.stats.wheel_samples += 1
        previous, self._last_wheels = self._last_wheels, sample
        gyro_turn = self._take_gyro_turn(sample.t_host)
        if previous is None:
            self._record(sample.t_host)
            return
        dt = (sample.t_host - previous.t_host) / 1e9
        left = self.wheels.metres(sample.left - previous.left, sample.unit)
        right = self.wheels.metres(sample.right - previous.right, sample.unit)
        if dt <= 0 or max(abs(left), abs(right)) > _MAX_WHEEL_SPEED_MPS * max(dt, 0.02):
            self.stats.wheel_resets += 1  # counter reset or a clock step: no motion known
            return
        distance = (left + right) / 2
        turn = (right - left) / self.wheels.track
        if gyro_turn is not None:
            turn = gyro_turn  # a skid steer's wheels scrub in a turn; the gyro does not
        self._motion = _Motion(speed=distance / dt, yaw_rate=turn / dt)
        self._moved = True

        yaw = self._odom[2] + turn / 2
        self._odom = np.array(
            [
                self._odom[0] + distance * math.cos(yaw),
                self._odom[1] + distance * math.sin(yaw),
                wrap_angle(self._odom[2] + turn),
            ]
        )
        if self._filter is not None:
            c = self.config
            sigma_distance = c.odom_sigma_per_sqrt_m * math.sqrt(abs(distance))
            if gyro_turn is None:
                sigma_turn = math.sqrt(
                    c.odom_yaw_sigma_per_sqrt_rad**2 * abs(turn)
                    + c.odom_yaw_sigma_per_sqrt_m**2 * abs(distance)
                )
            else:
                sigma_turn = math.hypot(
                    c.gyro_yaw_sigma_per_sqrt_s * math.sqrt(dt), c.gyro_bias_sigma_rad_s * dt
                )
            self._filter.predict(distance, turn, sigma_distance, sigma_turn)
        self._record(sample.t_host)

    def add_yaw_rate(self, t: int, rate: float) -> None:
        """The gyro's bias-corrected turn rate about the vertical (rad/s) at `t`: from then
        on the heading between wheel samples follows the gyro, not the wheels' difference."""
        if self._gyro_t is not None and 0 < t - self._gyro_t <= GYRO_GONE_NS:
            self._gyro_turn += rate * (t - self._gyro_t) / 1e9
        self._gyro_t = t if self._gyro_t is None else max(self._gyro_t, t)
        self.stats.gyro_samples += 1

    def _take_gyro_turn(self, t: int) -> float | None:
        """The gyro's turn since the last wheel sample (and start afresh), or None when the
        gyro is silent (no IMU, or a link that dropped it)."""
        turn, self._gyro_turn = self._gyro_turn, 0.0
        if self._gyro_t is None or t - self._gyro_t > GYRO_GONE_NS:
            return None
        return turn

    def add_fix(self, fix: Fix) -> FixVerdict:
        self.stats.fixes += 1
        sigma = self._fix_sigma(fix)
        if fix.lat is None or fix.lon is None or sigma is None:
            self.stats.fixes_unusable += 1
            return FixVerdict(False, "no usable position (quality or fields)")
        if self.grid is None:
            self.grid = UtmGrid.for_position(fix.lat, fix.lon)
        easting, northing = self.grid.forward(fix.lat, fix.lon)
        convergence = self.grid.convergence_rad(fix.lat, fix.lon)
        covariance = np.diag([sigma[0] ** 2, sigma[1] ** 2])
        heading = self._heading_measurement(fix, convergence)
        # The epoch describes the robot at its own time, not when its sentences arrived:
        # carry it forward by the motion the wheels measured since.
        shift, turn = self._motion_since(self.epoch_time(fix))
        easting, northing = easting + shift[0], northing + shift[1]
        if heading is not None:
            heading = (wrap_angle(heading[0] + turn), *heading[1:])

        if self._filter is None:
            verdict = self._start(fix, easting, northing, covariance, heading)
        else:
            verdict = self._update(easting, northing, covariance)
            if heading is not None and verdict.used:
                self._add_heading(*heading)
        if verdict.used:
            self._fix_variance = max(sigma) ** 2
        self._record(fix.t_host)
        return verdict

    # ---- outputs --------------------------------------------------------------------------

    def pose(self) -> Pose | None:
        """The latest pose: in `utm` once there is a datum, else in `odom`."""
        if self._filter is not None:
            x, y, yaw = self._filter.state
            return Pose(self._t, float(x), float(y), float(yaw), self._reported_covariance(), "utm")
        if self._last_wheels is None:
            return None
        x, y, yaw = self._odom
        return Pose(self._t, float(x), float(y), float(yaw), np.zeros((3, 3)), "odom")

    def pose_at(self, t: int, frame: str = "utm") -> Pose | None:
        """The pose at time `t` (ns), interpolated between the poses around it; None
        outside the kept history (`history_s`) or before the datum (for `utm`)."""
        history = self._utm_history if frame == "utm" else self._odom_history
        times = history.times
        if not times or t < times[0] or t > times[-1]:
            return None
        i = bisect.bisect_left(times, t)
        after = history.poses[i]
        if times[i] == t or i == 0:
            return Pose(t, *after[:3], after[3], frame)
        before = history.poses[i - 1]
        w = (t - times[i - 1]) / (times[i] - times[i - 1])
        yaw = wrap_angle(before[2] + w * wrap_angle(after[2] - before[2]))
        x = before[0] + w * (after[0] - before[0])
        y = before[1] + w * (after[1] - before[1])
        return Pose(t, x, y, yaw, after[3] if w >= 0.5 else before[3], frame)

    def utm_from_odom(self, t: int | None = None) -> np.ndarray | None:
        """The 3x3 homogeneous 2-D transform taking `odom` points to `utm` at time `t`
        (default: now), to georeference what was mapped before the datum or through an
        outage. Odometry drifts, so take it at the first time with a `utm` pose after
        the thing was seen (`first_utm_time`)."""
        if t is None:
            utm, odom = self.pose(), self.pose_at(self._t, frame="odom")
        else:
            utm, odom = self.pose_at(t), self.pose_at(t, frame="odom")
        if utm is None or odom is None or utm.frame != "utm":
            return None
        return _se2(utm.x, utm.y, utm.yaw) @ np.linalg.inv(_se2(odom.x, odom.y, odom.yaw))

    def settled_until(self, frame: str = "utm") -> int | None:
        """Poses at times up to this one are final: `pose_at` will give the same answer
        whatever comes in later. The history only grows at its end, but several inputs at
        one instant replace its newest pose (`_append`), so what is final is up to the
        second newest entry. None while the history has fewer than two entries."""
        times = (self._utm_history if frame == "utm" else self._odom_history).times
        return times[-2] if len(times) >= 2 else None

    @property
    def first_utm_time(self) -> int | None:
        """The earliest time still in the history with a pose in `utm`."""
        return self._utm_history.times[0] if self._utm_history.times else None

    # ---- internals ------------------------------------------------------------------------

    def _fix_sigma(self, fix: Fix) -> tuple[float, float] | None:
        """1-sigma (east, north) in metres: GST when sent, else HDOP x a per-quality sigma."""
        per_hdop = self.config.sigma_per_hdop.get(fix.quality)
        if per_hdop is None:
            return None
        floor = self.config.min_fix_sigma_m
        if fix.std_lat_m is not None and fix.std_lon_m is not None:
            return max(fix.std_lon_m, floor), max(fix.std_lat_m, floor)
        hdop = fix.hdop if fix.hdop is not None else 1.0
        sigma = max(per_hdop * hdop, floor)
        return sigma, sigma

    def _heading_measurement(self, fix: Fix, convergence: float):
        """(grid yaw, sigma, kind) from a true heading, or from course over ground while
        driving straight forward; None otherwise."""
        c = self.config
        if fix.heading_deg is not None:
            return (
                true_heading_to_grid_yaw(fix.heading_deg, convergence),
                c.heading_sigma_rad,
                "heading",
            )
        if fix.course_deg is None or fix.speed_mps is None or fix.speed_mps < c.cog_min_speed_mps:
            return None
        sigma = max(c.cog_velocity_sigma_mps / fix.speed_mps, math.radians(0.5))
        wheels = self._last_wheels
        if wheels is None or fix.t_host - wheels.t_host > WHEELS_GONE_NS:
            # No odometry to tell forward from reverse or straight from turning: course over
            # ground alone, trusted less (a wrong one is reset by the ones that follow).
            # Without it a robot without wheel data would never learn its heading.
            return true_heading_to_grid_yaw(fix.course_deg, convergence), 3 * sigma, "course"
        if (
            self._motion.speed >= c.cog_min_speed_mps
            and abs(self._motion.yaw_rate) <= c.cog_max_yaw_rate
        ):
            return true_heading_to_grid_yaw(fix.course_deg, convergence), sigma, "course"
        return None

    def epoch_time(self, fix: Fix) -> int:
        """When, on the host clock, the robot was where the fix says (ns): the epoch's UTC
        moved onto the host clock by `host_minus_utc` when a UTC source measures it, else
        taken as is when the host clock is on UTC (NTP or PPS: the fix arrived within
        `gnss_clock_tolerance_s` of its UTC). Then the arrival delay is the receiver's
        latency, measured (`stats.latency_ms`). Otherwise the arrival less the configured
        `gnss_latency_s`.

        The service and replay (`service.survey`) pass `t_host` as the epoch's UTC plus the
        least arrival delay over a few seconds (`serial_clock`): the host clock's offset
        from UTC plus the receiver's least latency, with the host's read backlogs taken
        out. So the last case is UTC + least offset - `gnss_latency_s`: the same as the
        arrival of an epoch that met no queue, without the jitter of one read in a backlog
        (it is exact when `gnss_latency_s` is the receiver's latency to its first sentence),
        and `latency_ms` is the receiver's least latency."""
        c = self.config
        if fix.utc_ns is not None:
            placed = fix.utc_ns + (self.host_minus_utc or 0)
            delay = fix.t_host - placed
            if 0 <= delay <= c.gnss_clock_tolerance_s * 1e9:
                self.stats.latency_ms = delay / 1e6
                return placed
        return fix.t_host - int(c.gnss_latency_s * 1e9)

    def _motion_since(self, t: int) -> tuple[np.ndarray, float]:
        """How far the antenna moved (grid east, north) and the robot turned from `t` to
        now, by the wheels: odometry is exact over the fraction of a second of a
        receiver's latency, and unlike the filter's history it holds no fix's correction.
        Zero when `t` is not behind the newest input or no longer in the history; no
        displacement before the datum (no grid heading to carry it with: at 2 m/s and
        60 ms, 12 cm, inside the datum's own uncertainty)."""
        then, now = self.pose_at(t, "odom"), self.pose_at(self._t, "odom")
        if then is None or now is None or t >= self._t:
            return np.zeros(2), 0.0
        turn = wrap_angle(now.yaw - then.yaw)
        if self._filter is None:
            return np.zeros(2), turn
        lever = self._lever_arm
        moved = (
            np.array([now.x - then.x, now.y - then.y])
            + rotate_xy(lever, now.yaw)
            - rotate_xy(lever, then.yaw)
        )
        # From odom into the grid: by the filter's heading against odometry's, now.
        return rotate_xy(moved, float(self._filter.state[2]) - now.yaw), turn

    @property
    def speed(self) -> float | None:
        """The forward speed of the latest wheel step (m/s); None before the first step
        (one sample is no speed: a service started on a moving robot must not report a
        standstill, whose jump to the true speed would read as a hard acceleration)."""
        return self._motion.speed if self._moved else None

    @property
    def heading_known(self) -> bool:
        return (
            self._filter is not None and self._filter.yaw_sigma <= self.config.known_yaw_sigma_rad
        )

    def _add_heading(self, yaw: float, sigma: float, kind: str) -> None:
        applied = False
        if not self.heading_known:
            self._filter.reset_yaw(yaw, sigma, self._lever_arm)
            self.stats.heading_resets += 1
            applied = True
        else:
            result = self._filter.update_yaw(yaw, sigma, self.config.fix_gate_chi2)
            if result.applied:
                self._headings_rejected_in_a_row = 0
                applied = True
            else:
                # Several headings in a row disagree with ours: ours is what went wrong.
                self._headings_rejected_in_a_row += 1
                if self._headings_rejected_in_a_row >= self.config.max_rejected_in_a_row:
                    self._filter.reset_yaw(yaw, sigma, self._lever_arm)
                    self._headings_rejected_in_a_row = 0
                    self.stats.heading_resets += 1
                    applied = True
        self.stats.headings_used += int(applied and kind == "heading")
        self.stats.courses_used += int(applied and kind == "course")

    def _start(self, fix, easting, northing, covariance, heading) -> FixVerdict:
        c = self.config
        yaw, yaw_sigma = (
            (heading[0], heading[1]) if heading else (c.initial_yaw_rad, c.initial_yaw_sigma_rad)
        )
        base = np.array([easting, northing]) - rotate_xy(self._lever_arm, yaw)
        p = np.zeros((3, 3))
        p[:2, :2] = covariance
        if heading is None:  # the centre lies anywhere on a circle of the lever's length
            p[:2, :2] += np.eye(2) * float(self._lever_arm @ self._lever_arm)
        p[2, 2] = yaw_sigma**2
        self._filter = PoseFilter(base[0], base[1], yaw, p)
        self.stats.fixes_used += 1
        return FixVerdict(True, "datum")

    def _update(self, easting, northing, covariance) -> FixVerdict:
        c = self.config
        result = self._filter.update_antenna(
            np.array([easting, northing]),
            covariance,
            self._lever_arm,
            c.fix_gate_chi2,
            observe_yaw=self.heading_known,
        )
        if result.applied:
            self._rejected_in_a_row = 0
            self.stats.fixes_used += 1
            return FixVerdict(True, "accepted", result.mahalanobis2)
        self._rejected_in_a_row += 1
        if self._rejected_in_a_row < c.max_rejected_in_a_row:
            self.stats.fixes_rejected += 1
            return FixVerdict(False, "rejected", result.mahalanobis2)
        # Several good fixes in a row disagree with us: our dead reckoning is what drifted.
        yaw = self._filter.state[2]
        base = np.array([easting, northing]) - rotate_xy(self._lever_arm, yaw)
        self._filter.reset_position(base[0], base[1], covariance)
        self._rejected_in_a_row = 0
        self.stats.position_resets += 1
        self.stats.fixes_used += 1
        return FixVerdict(True, "reset", result.mahalanobis2)

    def _record(self, t: int) -> None:
        self._t = max(self._t, t)
        _append(
            self._odom_history,
            self._t,
            (*map(float, self._odom), np.zeros((3, 3))),
            self.config.history_s,
        )
        if self._filter is not None:
            x, y, yaw = self._filter.state
            _append(
                self._utm_history,
                self._t,
                (float(x), float(y), float(yaw), self._reported_covariance()),
                self.config.history_s,
            )

    def _reported_covariance(self) -> np.ndarray:
        """The filter's covariance with the position's variances no less than the last
        used fix's. A receiver's error is not white: a float or DGPS solution's wanders
        for minutes, so fusing ten of its fixes a second brings the position no closer
        than the receiver's own sigma, though the filter, taking them as independent, says
        so (0.05 m under a 0.25 m float on the twin). What the poses place (a tree's
        outline) is then weighed by how well it was placed."""
        covariance = np.array(self._filter.covariance, dtype=float)
        for axis in (0, 1):
            covariance[axis, axis] = max(covariance[axis, axis], self._fix_variance)
        return covariance


def _append(history: _History, t: int, pose: tuple, keep_s: float) -> None:
    if history.times and history.times[-1] == t:
        history.poses[-1] = pose  # several inputs at one instant: keep the last state
        return
    history.times.append(t)
    history.poses.append(pose)
    while history.times and t - history.times[0] > keep_s * 1e9:
        history.times.popleft()
        history.poses.popleft()


def _se2(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, x], [s, c, y], [0.0, 0.0, 1.0]])
