"""The Jackal MCU's IMU, end to end over a real pseudo-terminal: a simulated MCU announces
`feedback` and `imu/data_raw` (sensor_msgs/Imu, encoded with the host's own IMU layout and
framed as rosserial does), answers like the firmware and publishes both at 50 Hz while the
robot stands on a known tilt; `JackalSession` reads the pty, and the bytes it recorded go
through `SurveyProcessor` as a replay would feed them. The pose comes out with the tilt."""

from __future__ import annotations

import contextlib
import math
import os
import select
import threading
import time
import tty

import numpy as np
import pytest

from tests.helpers.rosserial import feedback_bytes, ros_frame, topic_info_bytes
from treetraits.drivers import recording as rec
from treetraits.drivers.calibration import Calibration
from treetraits.firmware_bridge.jackal.messages import FEEDBACK, IMU
from treetraits.firmware_bridge.jackal.records import JackalImu, SerialChunk
from treetraits.firmware_bridge.jackal.session import JackalSession
from treetraits.pipeline.localization.attitude import GRAVITY
from treetraits.service.survey import SurveyProcessor

ID_FEEDBACK, ID_IMU = 131, 144  # the MCU's choice, learned from its TopicInfo
ROLL, PITCH = math.radians(4.0), math.radians(-6.0)  # left side up, nose up
GYRO_BIAS = (0.004, -0.003, 0.002)  # rad/s


def imu_payload(seq: int, rng: np.random.Generator) -> bytes:
    """What the MCU's imu/data_raw carries standing still on the tilt: the gyro's bias and
    gravity's specific force in base_link, a little noise, no orientation."""
    up = (
        -math.sin(PITCH),
        math.sin(ROLL) * math.cos(PITCH),
        math.cos(ROLL) * math.cos(PITCH),
    )
    gyro = np.add(GYRO_BIAS, rng.normal(0, 0.002, 3))
    accel = np.multiply(up, GRAVITY) + rng.normal(0, 0.03, 3)
    stamp = time.time_ns()
    return IMU.encode(
        {
            "header": {"seq": seq, "stamp": stamp, "frame_id": "base_link"},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            "orientation_covariance": (-1.0, *([0.0] * 8)),
            "angular_velocity": dict(zip("xyz", map(float, gyro), strict=True)),
            "angular_velocity_covariance": (0.0,) * 9,
            "linear_acceleration": dict(zip("xyz", map(float, accel), strict=True)),
            "linear_acceleration_covariance": (0.0,) * 9,
        }
    )


class ImuMcu:
    """The MCU side: TopicInfo answers on a topic request, time replies expected, then
    Feedback (wheels still) and IMU at 50 Hz."""

    def __init__(self, master: int):
        self.master = master
        self.sent_imu = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._rng = np.random.default_rng(7)
        os.set_blocking(master, False)

    def start(self) -> ImuMcu:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)

    def _send(self, data: bytes) -> None:
        with contextlib.suppress(OSError):
            os.write(self.master, data)

    def _run(self) -> None:
        configured, k, next_t, buf = False, 0, 0.0, b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.002)
            if ready:
                try:
                    buf += os.read(self.master, 4096)
                except OSError:
                    return
                if not configured and b"\xff\xfe\x00\x00\xff\x00\x00\xff" in buf:
                    self._send(ros_frame(10, bytes(8)))  # a time request first
                    for topic_id, name, mt in (
                        (ID_FEEDBACK, "feedback", FEEDBACK),
                        (ID_IMU, "imu/data_raw", IMU),
                    ):
                        info = topic_info_bytes(topic_id, name, mt.name, mt.md5, 512)
                        self._send(ros_frame(0, info))
                    configured, next_t, buf = True, time.monotonic(), b""
            if configured and time.monotonic() >= next_t:
                next_t += 0.02
                k += 1
                still = (1.0, 0.0, 30.0, 28.0, 0.0, 12.5, False)
                self._send(ros_frame(ID_FEEDBACK, feedback_bytes(seq=k, left=still, right=still)))
                self._send(ros_frame(ID_IMU, imu_payload(k, self._rng)))
                self.sent_imu += 1


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)
    yield master, slave
    for fd in (master, slave):
        with contextlib.suppress(OSError):
            os.close(fd)


def test_imu_over_a_pty_gives_the_pose_its_roll_and_pitch(pty_pair):
    master, slave = pty_pair
    mcu = ImuMcu(master).start()
    session = JackalSession(os.ttyname(slave), required=("feedback", "imu/data_raw"))
    items = []
    try:
        session.start()
        deadline = time.monotonic() + 2.5
        while (left := deadline - time.monotonic()) > 0:
            item = session.read(timeout=left)
            if item is not None:
                items.append(item)
    finally:
        session.close()
        mcu.stop()
    items += list(session)

    imus = [r for r in items if isinstance(r, JackalImu)]
    assert len(imus) >= 0.8 * mcu.sent_imu and len(imus) > 80  # ~2.4 s at 50 Hz
    assert session.counters()["md5_mismatch"] == 0
    assert imus[0].frame_id == "base_link" and imus[0].orientation_covariance[0] == -1.0

    # The recorded bytes, replayed through the survey processor.
    processor = SurveyProcessor(None, Calibration())
    for chunk in (c for c in items if isinstance(c, SerialChunk)):
        processor.feed(rec.WHEELS_JACKAL, chunk.data, chunk.t_host, chunk.t_host)
    processor.finish()  # no LiDAR, no GNSS: the run's frame is odom
    assert processor.stats.imu_samples == len(imus)
    assert processor.world_frame == "odom"

    t_last = imus[-1].t_host
    for t in (imus[5].t_host, (imus[10].t_host + t_last) // 2, t_last - 10_000_000):
        pose = processor.pose_at(t)
        assert pose is not None and pose.frame == "odom"
        assert pose.roll == pytest.approx(ROLL, abs=math.radians(0.3))  # measured <= 0.14 deg
        assert pose.pitch == pytest.approx(PITCH, abs=math.radians(0.3))
    # Standing still, the gyro's bias is being learned (5 s time constant: part of it).
    bias = processor.attitude.bias
    assert np.all(np.sign(bias) == np.sign(GYRO_BIAS))
    assert processor.attitude.stats.rest_samples > 0.9 * len(imus)
