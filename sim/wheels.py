"""A Jackal MCU emulator: the bytes the robot's microcontroller sends over `/dev/jackal`
once the host has asked for its topics: TopicInfo for its publishers, time requests every
few seconds, and jackal_msgs/Feedback at 50 Hz with each wheel's cumulative travel (rad),
which slips on the ground by a few percent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from treetraits.drivers.calibration import WheelGeometry
from treetraits.firmware_bridge.jackal import messages as m
from treetraits.firmware_bridge.jackal import rosserial as rs

FEEDBACK_TOPIC_ID = 137  # the MCU's choice; the host learns it from TopicInfo


@dataclass(frozen=True)
class WheelSettings:
    rate_hz: float = 50.0
    slip_left: float = 0.02  # wheels turn this much more than the ground moves
    slip_right: float = 0.015
    noise_rad: float = 0.002


class JackalMcuEmulator:
    def __init__(
        self,
        wheels: WheelGeometry,
        settings: WheelSettings | None = None,
        rng: np.random.Generator | None = None,
    ):
        self.wheels = wheels
        self.settings = settings or WheelSettings()
        self.rng = rng or np.random.default_rng(0)
        self._left = self._right = 0.0
        self._last: tuple[float, float, float] | None = None

    def handshake(self) -> bytes:
        """What the MCU answers to the host's topic request."""
        info = rs.TopicInfo(FEEDBACK_TOPIC_ID, "feedback", m.FEEDBACK.name, m.FEEDBACK.md5, 512)
        return rs.encode_frame(rs.ID_PUBLISHER, info.encode()) + rs.encode_frame(rs.ID_TIME)

    def feedback(self, t_ns: int, x: float, y: float, yaw: float) -> bytes:
        """One Feedback frame for the robot at (x, y, yaw) at time t_ns."""
        if self._last is not None:
            lx, ly, lyaw = self._last
            distance = math.hypot(x - lx, y - ly)
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
