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

GOAL_M = 23.0
PATHS = ("straight", "s", "n")


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
    """A `sim.lidar.Trajectory`: the pose at device times (ns), interpolated."""
    times = poses[:, 0]
    yaw = np.unwrap(poses[:, 3])

    def at(t_ns: np.ndarray):
        t = (np.asarray(t_ns) - t0_ns) / 1e9
        x = np.interp(t, times, poses[:, 1])
        y = np.interp(t, times, poses[:, 2])
        return x, y, np.zeros_like(x), np.interp(t, times, yaw)

    return at
