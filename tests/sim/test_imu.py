"""The Jackal MCU emulator's IMU: imu/data_raw frames in the rosserial stream, announced
in the handshake, decoded by the host's own decoder into JackalImu, reading gravity in the
body frame of the robot's true attitude and its true rates."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from treetraits.drivers.calibration import WheelGeometry
from treetraits.drivers.records import WheelSample
from treetraits.firmware_bridge.jackal import JackalImu
from treetraits.firmware_bridge.jackal.session import JackalProtocol, decode_stream
from treetraits.sim.orchard import Ground
from treetraits.sim.paths import attitude_on, riding_trajectory
from treetraits.sim.wheels import JackalMcuEmulator, WheelSettings, imu_truth

G = 9.80665
WHEELS = WheelGeometry(radius=0.098, track=0.5634)


def record(trajectory, seconds, settings=None, seed=0):
    """The MCU's bytes for `seconds` of `trajectory` at 50 Hz, as (t_host, chunk)."""
    settings = settings or WheelSettings()
    mcu = JackalMcuEmulator(
        WHEELS, settings, np.random.default_rng(seed), np.random.default_rng([seed, 3])
    )
    chunks = [(0, mcu.handshake())]
    for t in np.arange(0, int(seconds * 1e9), int(1e9 / settings.rate_hz)):
        x, y, z, yaw, *_ = (float(v[0]) for v in trajectory(np.array([t])))
        data = mcu.feedback(int(t), x, y, yaw, z)
        if settings.imu:
            data += mcu.imu(int(t), *imu_truth(trajectory, int(t), settings.imu_difference_s))
        chunks.append((int(t) + 2_000_000, data))
    return chunks


def still(ground, yaw):
    return riding_trajectory(np.array([[0.0, 1.0, 2.0, yaw], [100.0, 1.0, 2.0, yaw]]), 0, ground)


def test_a_level_robot_at_rest_reads_plus_g_on_z_and_no_rotation():
    records = list(decode_stream(record(still(Ground(), 0.3), 4.0)))
    imu = [r for r in records if isinstance(r, JackalImu)]
    assert len(imu) == 200  # 50 Hz
    assert all(r.topic == "imu/data_raw" and r.orientation_covariance[0] == -1 for r in imu)
    accel = np.array([r.linear_acceleration for r in imu])
    gyro = np.array([r.angular_velocity for r in imu])
    # Means over 200 samples: the white noise averages to ~0.05/sqrt(200) = 0.004 m/s^2;
    # what is left is the bias (a few hundredths) and no more.
    assert accel.mean(axis=0) == pytest.approx([0.0, 0.0, G], abs=0.1)
    assert np.abs(gyro.mean(axis=0)).max() < 0.01  # bias ~0.002 rad/s
    # Realistic noise: the spread is the MEMS-class figure, not zero and not 10x it.
    assert 0.02 < accel[:, 2].std() < 0.1 and 0.002 < gyro[:, 2].std() < 0.01
    # The wheel samples are still there, one per IMU frame.
    assert sum(isinstance(r, WheelSample) for r in records) == 200


@pytest.mark.parametrize(("slope_x", "slope_y", "yaw"), [(0.12, 0.0, 0.0), (0.1, 0.06, 2.0)])
def test_gravity_in_the_body_frame_follows_the_robots_roll_and_pitch(slope_x, slope_y, yaw):
    ground = Ground(slope_x=slope_x, slope_y=slope_y)
    imu = [
        r
        for r in decode_stream(record(still(ground, yaw), 4.0, seed=1))
        if isinstance(r, JackalImu)
    ]
    accel = np.array([r.linear_acceleration for r in imu]).mean(axis=0)
    _, pitch, roll = (float(v) for v in attitude_on(ground, 1.0, 2.0, yaw))
    # The world's up (what an accelerometer at rest reads, times g) seen from a body
    # pitched by p (positive nose down) and rolled by r (positive left side up).
    up = G * np.array(
        [-math.sin(pitch), math.cos(pitch) * math.sin(roll), math.cos(pitch) * math.cos(roll)]
    )
    assert accel == pytest.approx(up, abs=0.1)
    if slope_x and not slope_y and yaw == 0.0:
        # Nose uphill: the accelerometer's x reads +g sin(atan(slope)).
        assert accel[0] == pytest.approx(G * math.sin(math.atan(slope_x)), abs=0.1)


def test_turning_reads_the_yaw_rate_on_z():
    # Turning on the spot at 0.5 rad/s on level ground.
    poses = np.array([[t, 0.0, 0.0, 0.5 * t] for t in np.arange(0, 10.01, 0.01)])
    trajectory = riding_trajectory(poses, 0, Ground())
    imu = [r for r in decode_stream(record(trajectory, 8.0)) if isinstance(r, JackalImu)]
    gyro = np.array([r.angular_velocity for r in imu[10:-10]])
    assert gyro[:, 2].mean() == pytest.approx(0.5, abs=0.01)
    assert np.abs(gyro[:, :2].mean(axis=0)).max() < 0.01


def test_the_handshake_announces_the_imu_and_the_host_protocol_decodes_it():
    chunks = record(still(Ground(), 0.0), 0.2)
    protocol = JackalProtocol()
    records = []
    for t_host, data in chunks:
        records += protocol.receive(data, t_host, t_host / 1e9)
    assert "imu/data_raw" in protocol.announced
    assert any(isinstance(r, JackalImu) for r in records)
    assert protocol.stats.md5_mismatch == 0 and protocol.stats.unknown_topic == 0


def test_no_imu_for_a_platform_without_one():
    settings = dataclasses.replace(WheelSettings(), imu=False)
    chunks = record(still(Ground(), 0.0), 1.0, settings)
    records = list(decode_stream(chunks))
    assert not any(isinstance(r, JackalImu) for r in records)
    assert sum(isinstance(r, WheelSample) for r in records) == 50
