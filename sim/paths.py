"""Robot paths through the twin's orchard, driven like the paper's Jackal: v = 0.5 m/s,
turning no faster than w = 1 rad/s, following waypoints with pure pursuit.

Layout (the paper's 2x3 grid): trees in three rows across the direction of travel (front,
middle, back, `length` apart along +x, the front row `length` ahead of the start) and two
columns at y = +-width/2. The goal is 23 m ahead of the start, as in the paper.

- straight: down the centre lane to the goal.
- s: a serpentine through three lanes (left outside, centre, right outside), turning at
  the headlands: every tree is passed close by on both sides.
- n: the three lanes all driven towards the goal, returning along the outside between
  them: longer straight legs, the shape of an N. (The paper shows both paths only in a
  figure; this is our reading of them.)
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from treetraits.sim import PATHS

GOAL_M = 23.0


@dataclass(frozen=True)
class DriveSettings:
    speed: float = 0.5  # m/s
    max_yaw_rate: float = 1.0  # rad/s
    lookahead: float = 1.0  # m, pure pursuit
    rate_hz: float = 100.0


def waypoints(path: str, width: float, length: float, goal: float = GOAL_M) -> np.ndarray:
    """The path's corner points (N x 2), starting at the origin facing +x."""
    if path not in PATHS:
        raise ValueError(f"unknown path {path!r}; expected one of {', '.join(PATHS)}")
    lanes = [width, 0.0, -width]  # left outside, centre, right outside
    end = goal
    if path == "straight":
        return np.array([[0.0, 0.0], [end, 0.0]])
    if path == "s":
        points = [[0.0, 0.0]]
        points += [
            [1.0, lanes[0]],
            [end, lanes[0]],
            [end + 2.0, lanes[0] / 2],
            [end, lanes[1]],
            [1.0, lanes[1]],
            [-1.0, lanes[2] / 2],
            [1.0, lanes[2]],
            [end, lanes[2]],
        ]
        return np.array(points)
    # n: up each lane, back around the outside (behind the start) to the next lane.
    points = [
        [0.0, 0.0],
        [1.0, lanes[0]],
        [end, lanes[0]],
        [end + 2.0, lanes[0] + 2.0],
        [-3.0, lanes[0] + 2.0],
        [-3.0, lanes[1]],
        [end, lanes[1]],
        [end + 2.0, lanes[2] - 2.0],
        [-3.0, lanes[2] - 2.0],
        [-1.0, lanes[2]],
        [end, lanes[2]],
    ]
    return np.array(points)


def drive(points: np.ndarray, settings: DriveSettings | None = None) -> np.ndarray:
    """Poses (t s, x, y, yaw) at `rate_hz` along the waypoints by pure pursuit; the robot
    starts at the first point facing the second."""
    s = settings or DriveSettings()
    dense = _densify(points, 0.05)
    x, y = dense[0]
    yaw = math.atan2(dense[1][1] - y, dense[1][0] - x)
    dt = 1.0 / s.rate_hz
    poses = [(0.0, x, y, yaw)]
    target = 0
    t = 0.0
    while True:
        # Farthest point within the lookahead along the path, never going back.
        while (
            target < len(dense) - 1
            and math.hypot(dense[target][0] - x, dense[target][1] - y) < s.lookahead
        ):
            target += 1
        tx, ty = dense[target]
        if target == len(dense) - 1 and math.hypot(tx - x, ty - y) < s.speed * dt * 2:
            break
        alpha = math.atan2(ty - y, tx - x) - yaw
        alpha = (alpha + math.pi) % (2 * math.pi) - math.pi
        curvature = 2 * math.sin(alpha) / max(math.hypot(tx - x, ty - y), 1e-6)
        yaw_rate = max(-s.max_yaw_rate, min(s.max_yaw_rate, s.speed * curvature))
        # Turn on the spot-ish (slowly) when the target is behind: a skid steer can.
        speed = s.speed if abs(alpha) < math.pi / 2 else 0.1
        mid = yaw + yaw_rate * dt / 2
        x, y = x + speed * dt * math.cos(mid), y + speed * dt * math.sin(mid)
        yaw = yaw + yaw_rate * dt
        t += dt
        poses.append((t, x, y, yaw))
        if t > 3600:
            raise RuntimeError("the path follower did not reach the goal in an hour")
    return np.array(poses)


def _densify(points: np.ndarray, step: float) -> np.ndarray:
    out = [points[0]]
    for a, b in itertools.pairwise(points):
        n = max(1, math.ceil(np.linalg.norm(b - a) / step))
        out.extend(a + (b - a) * (i / n) for i in range(1, n + 1))
    return np.array(out)


def trajectory_function(poses: np.ndarray, t0_ns: int):
    """A `sim.lidar.Trajectory`: the pose at device times (ns), interpolated (x, y, z = 0,
    yaw; level). `riding_trajectory` puts it on the ground."""
    times = poses[:, 0]
    track = np.column_stack([poses[:, 1], poses[:, 2], np.unwrap(poses[:, 3])])
    # Outside the drive the robot keeps its first and last velocities: it is already
    # driving when the recording starts (as its wheels report from their first step),
    # so the IMU's differences across the start read no acceleration that never was.
    first = (track[1] - track[0]) / (times[1] - times[0])
    last = (track[-1] - track[-2]) / (times[-1] - times[-2])

    def at(t_ns: np.ndarray):
        t = (np.asarray(t_ns) - t0_ns) / 1e9
        x, y, yaw = (np.interp(t, times, track[:, k]) for k in range(3))
        before, after = np.minimum(t - times[0], 0.0), np.maximum(t - times[-1], 0.0)
        x = x + before * first[0] + after * last[0]
        y = y + before * first[1] + after * last[1]
        yaw = yaw + before * first[2] + after * last[2]
        return x, y, np.zeros_like(x), yaw

    return at


# The Jackal's wheel contact points (Clearpath Jackal: wheelbase 0.262 m, track 0.376 m):
# the robot rests on the ground under these four points.
JACKAL_WHEELBASE_M = 0.262
JACKAL_TRACK_M = 0.376


def attitude_on(ground, x, y, yaw, wheelbase=JACKAL_WHEELBASE_M, track=JACKAL_TRACK_M):
    """(z, pitch, roll) of a robot at (x, y, yaw) resting on `ground` (anything with a
    vectorised `height(x, y)`): the plane through the ground under its four wheels (least
    squares; their mean height is z, the base_footprint on that plane). REP-103 angles:
    pitch about the body's y (positive = nose down), roll about its x (positive = left side
    up), applied as R = Rz(yaw) Ry(pitch) Rx(roll)."""
    x, y, yaw = (np.asarray(v, dtype=float) for v in (x, y, yaw))
    c, s = np.cos(yaw), np.sin(yaw)
    h = {}
    for fx, fy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):  # front/rear, left/right
        dx, dy = fx * wheelbase / 2, fy * track / 2
        h[fx, fy] = ground.height(x + c * dx - s * dy, y + s * dx + c * dy)
    z = (h[1, 1] + h[1, -1] + h[-1, 1] + h[-1, -1]) / 4
    # The plane's gradient in the heading-aligned frame (forward, left).
    g_forward = (h[1, 1] + h[1, -1] - h[-1, 1] - h[-1, -1]) / (2 * wheelbase)
    g_left = (h[1, 1] + h[-1, 1] - h[1, -1] - h[-1, -1]) / (2 * track)
    # The body's z axis is the plane's normal (-g_forward, -g_left, 1) / n; with
    # R = Ry(pitch) Rx(roll) that axis is (sin p cos r, -sin r, cos p cos r).
    norm = np.sqrt(1 + g_forward**2 + g_left**2)
    pitch = -np.arctan(g_forward)
    roll = np.arcsin(np.clip(g_left / norm, -1, 1))
    return z, pitch, roll


def riding_trajectory(poses: np.ndarray, t0_ns: int, ground):
    """A full 6-DoF `sim.lidar.Trajectory` (x, y, z, yaw, pitch, roll): the planar drive
    with the robot resting on `ground` (`attitude_on`)."""
    planar = trajectory_function(poses, t0_ns)

    def at(t_ns: np.ndarray):
        x, y, _, yaw = planar(t_ns)
        z, pitch, roll = attitude_on(ground, x, y, yaw)
        return x, y, z, yaw, pitch, roll

    return at
