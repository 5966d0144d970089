"""A VLP-16-like sweep of a walled yard, taken while the robot drives at 2 m/s and turns at
0.5 rad/s: each point ray-cast from where the LiDAR really was when it fired, and the
robot's poses on that arc."""

from __future__ import annotations

import math

import numpy as np

SPEED, YAW_RATE = 2.0, 0.5  # m/s, rad/s
SWEEP_NS = 100_000_000
FIRINGS = 1800  # 0.2 deg steps
ELEVATIONS = np.radians(np.arange(-15, 16, 2))  # 16 rings
T_HOST_END = 1_700_000_000_123_456_789  # host receive time of the last firing
# The sensor's clock: microseconds past the hour from its own power-on, minutes off the host.
T_DEVICE_END = 3_000_000_000_000 + 417_000
# Walls around the robot's position at the scan's middle: (normal, offset), n . p = c.
WALLS = [((1.0, 0.0), 8.0), ((-1.0, 0.0), 6.0), ((0.0, 1.0), 3.0), ((0.0, -1.0), 3.0)]
T_BASE_LIDAR = np.array(
    [[1.0, 0, 0, 0.25], [0, 1.0, 0, 0.05], [0, 0, 1.0, 0.65], [0, 0, 0, 1.0]]
)  # LiDAR 0.25 m ahead, 5 cm left, 0.65 m up


def base_pose(t_s: np.ndarray) -> np.ndarray:
    """T_world_base (n, 4, 4) on a constant-speed arc; t in seconds from the middle."""
    t_s = np.atleast_1d(t_s)
    yaw = YAW_RATE * t_s
    r = SPEED / YAW_RATE
    out = np.tile(np.eye(4), (len(t_s), 1, 1))
    out[:, 0, 0], out[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    out[:, 1, 0], out[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    out[:, 0, 3], out[:, 1, 3] = r * np.sin(yaw), r * (1 - np.cos(yaw))
    return out


def sweep():
    """(points in the LiDAR frame as measured, offsets from the middle in ns, wall index)."""
    k = np.arange(FIRINGS)
    dt = (k * SWEEP_NS // (FIRINGS - 1)) - SWEEP_NS // 2  # ns from the middle
    azimuth = 2 * math.pi * k / FIRINGS  # clockwise from x, as the VLP-16 counts
    el = np.repeat(ELEVATIONS[None, :], FIRINGS, axis=0).ravel()
    az = np.repeat(azimuth, len(ELEVATIONS))
    dt = np.repeat(dt, len(ELEVATIONS))
    d_lidar = np.stack([np.cos(el) * np.cos(-az), np.cos(el) * np.sin(-az), np.sin(el)], 1)
    world_lidar = base_pose(dt / 1e9) @ T_BASE_LIDAR
    origin = world_lidar[:, :3, 3]
    d_world = np.einsum("nij,nj->ni", world_lidar[:, :3, :3], d_lidar)
    best = np.full(len(az), np.inf)
    wall = np.full(len(az), -1)
    for i, (n, c) in enumerate(WALLS):
        n3 = np.array([*n, 0.0])
        denom = d_world @ n3
        with np.errstate(divide="ignore", invalid="ignore"):
            s = (c - origin @ n3) / denom
        hit = (denom > 1e-9) & (s > 0) & (s < best)
        best[hit], wall[hit] = s[hit], i
    ok = wall >= 0
    return best[ok, None] * d_lidar[ok], dt[ok], wall[ok]


def samples(step_ns=10_000_000):
    times = np.arange(-SWEEP_NS // 2, SWEEP_NS // 2 + 1, step_ns)
    return times, base_pose(times / 1e9)
