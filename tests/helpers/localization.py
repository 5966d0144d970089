"""Known trajectories and what the sensors report along them: the truth in the UTM grid of
a grove near Riverside, California (zone 11N), turned into wheel rotation in radians, GNSS
fixes in WGS84 for the antenna and true (not grid) headings."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

from treetraits.drivers.records import Fix, WheelSample
from treetraits.pipeline.localization import WheelGeometry
from treetraits.pipeline.localization.utm import UtmGrid, wrap_angle

ORIGIN = (467_000.0, 3_758_000.0)  # easting, northing in 11N
GRID = UtmGrid.for_zone(11, north=True)
WHEELS = WheelGeometry(radius=0.098, track=0.555)
WHEEL_HZ, GNSS_HZ = 50, 5


def drive(segments, v=0.5, start_yaw_deg=30.0):
    """Truth poses at WHEEL_HZ: segments of (seconds, yaw rate rad/s[, speed]), speed v
    unless the segment gives its own (0: standing)."""
    x, y, yaw, t = ORIGIN[0], ORIGIN[1], math.radians(start_yaw_deg), 0.0
    poses = [(t, x, y, yaw)]
    for seconds, yaw_rate, *speed in segments:
        speed = speed[0] if speed else v
        for _ in range(int(seconds * WHEEL_HZ)):
            dt = 1.0 / WHEEL_HZ
            mid = yaw + yaw_rate * dt / 2
            x, y, yaw, t = (
                x + speed * dt * math.cos(mid),
                y + speed * dt * math.sin(mid),
                yaw + yaw_rate * dt,
                t + dt,
            )
            poses.append((t, x, y, yaw))
    return poses


@dataclass(frozen=True)
class YawRate:
    t_host: int
    rate: float


def sensors(
    poses,
    rng,
    *,
    slip=0.02,
    gnss_sigma=0.02,
    heading_sigma_deg=None,
    lever=(0.0, 0.0),
    outage=None,
    outliers=None,
    scrub=1.0,
    gyro=None,
):
    """Wheel samples and fixes for the truth. `slip`: wheels over-read travel by this
    fraction on the left and 3/4 of it on the right (a common radius error plus a
    differential that bends dead reckoning);
    `outage`: (start_s, end_s) without GNSS; `outliers`: {fix index: metres of error};
    `scrub`: the wheels turn this much more than the track explains (a skid steer's
    effective track is wider than its real one); `gyro`: (noise rad/s, bias rad/s) of a
    yaw rate sample beside each wheel sample."""
    events = []
    left = right = 0.0
    scale_left, scale_right = 1 + slip, 1 + 0.75 * slip
    for (_, x0, y0, yaw0), (t1, x1, y1, yaw1) in itertools.pairwise(poses):
        distance = math.hypot(x1 - x0, y1 - y0)
        turn = wrap_angle(yaw1 - yaw0)
        left += (distance - scrub * turn * WHEELS.track / 2) * scale_left / WHEELS.radius
        right += (distance + scrub * turn * WHEELS.track / 2) * scale_right / WHEELS.radius
        left += rng.normal(0, 0.002)
        right += rng.normal(0, 0.002)
        events.append(WheelSample(int(t1 * 1e9), left, right, "rad"))
        if gyro is not None:
            rate = turn * WHEEL_HZ + gyro[1] + rng.normal(0, gyro[0])
            events.append(YawRate(int(t1 * 1e9) + 1, rate))
    step = WHEEL_HZ // GNSS_HZ
    for n, (t, x, y, yaw) in enumerate(poses[::step]):
        before = poses[max(n * step - 1, 0)]
        speed = math.hypot(x - before[1], y - before[2]) * WHEEL_HZ
        if outage and outage[0] <= t < outage[1]:
            continue
        ax = x + math.cos(yaw) * lever[0] - math.sin(yaw) * lever[1]
        ay = y + math.sin(yaw) * lever[0] + math.cos(yaw) * lever[1]
        ax += rng.normal(0, gnss_sigma) + (outliers or {}).get(n, 0.0)
        ay += rng.normal(0, gnss_sigma)
        lat, lon = GRID.inverse(ax, ay)
        convergence = GRID.convergence_rad(lat, lon)
        true_yaw = yaw - convergence
        course = (90.0 - math.degrees(true_yaw)) % 360.0
        heading = None
        if heading_sigma_deg is not None:
            heading = (course + rng.normal(0, heading_sigma_deg)) % 360.0
        events.append(
            Fix(
                int(t * 1e9) + 1,
                None,
                lat,
                lon,
                10.0,
                -30.0,
                4,
                14,
                0.8,
                std_lat_m=gnss_sigma,
                std_lon_m=gnss_sigma,
                heading_deg=heading,
                course_deg=(course + rng.normal(0, 2.0)) % 360.0,
                speed_mps=speed,
            )
        )
    events.sort(key=lambda e: e.t_host)
    return events


PATH = [(30, 0.0), (10, 0.15), (20, 0.0), (10, -0.15), (20, 0.0)]  # straight, turns: 90 s
