"""pipeline/localization/attitude.py: roll and pitch from synthetic IMU streams whose true
attitude is known. The streams are what a body-fixed IMU measures along a given motion:
the gyro reads the body's angular velocity (plus a bias and noise), the accelerometer the
specific force R^T (a + g up) (plus vibration and noise), at 50 Hz like the Jackal MCU."""

from __future__ import annotations

import math

import numpy as np
import pytest

from treetraits.errors import ConfigError
from treetraits.pipeline.localization.attitude import (
    GRAVITY,
    AttitudeFilter,
    cross3,
    rotation_zyx,
)
from treetraits.pipeline.localization.config import LocalizationConfig

RATE_HZ = 50
T0 = 1_700_000_000_000_000_000
BIAS = np.array([0.012, -0.009, 0.006])  # rad/s, a plausible MEMS gyro bias


def _vee(m: np.ndarray) -> np.ndarray:
    return np.array([m[2, 1], m[0, 2], m[1, 0]])


def imu_stream(duration_s, roll, pitch, yaw, speed, seed=0, gyro_noise=0.003,
               accel_noise=0.05, vibration=None):  # fmt: skip
    """(t_ns, gyro, accel, speed, true roll, true pitch) at 50 Hz. roll, pitch, yaw, speed
    are functions of time (s); the robot drives forward along its body x."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / RATE_HZ
    h = 1e-4

    def rot(t):
        return rotation_zyx(roll(t), pitch(t), yaw(t))

    def velocity(t):
        return rot(t) @ np.array([speed(t), 0.0, 0.0])

    out = []
    for k in range(int(duration_s * RATE_HZ)):
        t = k * dt
        r = rot(t)
        omega = _vee(r.T @ (rot(t + h) - rot(t - h)) / (2 * h))
        accel_world = (velocity(t + h) - velocity(t - h)) / (2 * h)
        force = r.T @ (accel_world + np.array([0.0, 0.0, GRAVITY]))
        gyro = omega + BIAS + rng.normal(0, gyro_noise, 3)
        accel = force + rng.normal(0, accel_noise, 3)
        if vibration is not None:
            g_vib, a_vib = vibration(t, rng)
            gyro, accel = gyro + g_vib, accel + a_vib
        out.append((T0 + round(t * 1e9), gyro, accel, speed(t), roll(t), pitch(t)))
    return out


def run(stream, use_speed=True, config=None):
    f = AttitudeFilter(config or LocalizationConfig())
    errors = []
    for t, gyro, accel, speed, roll, pitch in stream:
        if use_speed:
            f.add_speed(t, speed)
        f.add_imu(t, gyro, accel)
        est = f.attitude
        if est is not None:
            errors.append((t, est[0] - roll, est[1] - pitch))
    return f, np.array(errors)


def const(value):
    return lambda t: value


def worst_deg(errors, after_s=0.0, until_s=math.inf):
    t = (errors[:, 0] - T0) / 1e9
    sel = (t >= after_s) & (t <= until_s)
    return math.degrees(np.abs(errors[sel, 1:]).max())


def test_rotation_is_zyx_as_rep103():
    # Pitch up (negative pitch) lifts the nose: body x gets a positive world z.
    assert rotation_zyx(0, -0.1, 0)[2, 0] == pytest.approx(math.sin(0.1))
    # Roll positive lifts the left side: body y gets a positive world z.
    assert rotation_zyx(0.1, 0, 0)[2, 1] == pytest.approx(math.sin(0.1))
    r = rotation_zyx(0.1, 0.2, 0.3)
    rz = rotation_zyx(0, 0, 0.3)
    ry = rotation_zyx(0, 0.2, 0)
    rx = rotation_zyx(0.1, 0, 0)
    np.testing.assert_allclose(r, rz @ ry @ rx, atol=1e-12)


def test_static_tilt_is_found_at_once_and_the_gyro_bias_learned():
    roll, pitch = math.radians(5.0), math.radians(-8.0)
    stream = imu_stream(30, const(roll), const(pitch), const(0.7), const(0.0))
    f, errors = run(stream)
    # The first accelerometer sample sets the attitude; noise is averaged from then on.
    # Until the bias is learned it tilts the estimate by bias x tau (0.012 rad/s: 0.7 deg).
    assert worst_deg(errors) < 0.8  # measured 0.39 deg
    assert worst_deg(errors, after_s=10.0) < 0.2  # measured 0.09 deg
    # At rest the gyro reads its bias: learned within 30 s (6 time constants).
    np.testing.assert_allclose(f.bias, BIAS, atol=0.001)  # measured 0.0004 rad/s
    assert f.stats.rest_samples == len(stream)


def test_a_change_of_slope_is_followed_within_a_second():
    # Driving at 1.5 m/s on the flat, then onto a 10 deg climb (nose up) over 0.5 s,
    # then a 6 deg side slope builds up; the gyro bias is unknown (never at rest).
    def pitch(t):
        return -math.radians(10.0) * min(max((t - 5.0) / 0.5, 0.0), 1.0)

    def roll(t):
        return math.radians(6.0) * min(max((t - 10.0) / 1.0, 0.0), 1.0)

    stream = imu_stream(15, roll, pitch, lambda t: 0.2 * t, const(1.5))
    _, errors = run(stream)
    assert worst_deg(errors, after_s=2.0, until_s=5.0) < 1.3  # measured: 0.66 deg
    # Through the slope change the gyro carries the attitude: no lag of a time constant
    # (a filter on the accelerometer alone would be 10 deg x e^-t/tau behind).
    assert worst_deg(errors, after_s=5.0, until_s=6.5) < 1.3  # measured: 0.66 deg
    assert worst_deg(errors, after_s=10.0, until_s=12.0) < 1.0  # measured: 0.42 deg
    # Meanwhile the bias of the roll and pitch axes is learned in motion.
    assert worst_deg(errors, after_s=12.0) < 0.8  # measured: 0.41 deg


def grove_floor(t, rng):
    """Driving over a grove floor: broadband shaking, a 14 Hz chassis mode, and a bump
    (a root) every 1.7 s that throws 6 m/s^2 up for one sample."""
    gyro = rng.normal(0, 0.05, 3)
    accel = rng.normal(0, 0.8, 3) + np.array([0.0, 0.0, 1.5 * math.sin(2 * math.pi * 14 * t)])
    if int(t * RATE_HZ) % 85 == 0:
        accel[2] += 6.0
    return gyro, accel


def test_driving_vibration_and_a_turn_do_not_tilt_the_estimate():
    # 1.5 m/s in a 0.5 rad/s turn: 0.75 m/s^2 centripetal, which read as gravity would
    # tilt the roll by 4.4 deg; the wheels' speed and the gyro's rate explain it.
    stream = imu_stream(
        20,
        const(math.radians(3.0)),
        const(math.radians(-2.0)),
        lambda t: 0.5 * t,
        const(1.5),
        vibration=grove_floor,
        seed=3,
    )
    f, errors = run(stream)
    t = (errors[:, 0] - T0) / 1e9
    rms = math.degrees(np.sqrt((errors[t > 3.0, 1:] ** 2).mean()))
    assert rms < 1.2  # measured: 0.56 deg (0.56-0.86 over seeds 0-5)
    assert worst_deg(errors, after_s=3.0) < 3.5  # measured: 1.65 deg (1.54-2.47)
    assert f.stats.gated >= 20  # every bump refused, with the worst shaking: 129
    # Without the wheel speed the centripetal acceleration is taken for gravity.
    _, blind = run(stream, use_speed=False)
    t = (blind[:, 0] - T0) / 1e9
    assert math.degrees(np.abs(blind[t > 5.0, 1]).mean()) > 3.0  # measured: 4.3 deg


def test_yaw_rate_is_the_rate_about_the_vertical():
    stream = imu_stream(5, const(0.1), const(0.05), lambda t: 0.4 * t, const(1.0))
    f, _ = run(stream)
    assert f.yaw_rate == pytest.approx(0.4, abs=0.03)


def test_attitude_at_interpolates_between_samples():
    stream = imu_stream(2, const(0.05), const(-0.02), const(0.0), const(0.0))
    f, _ = run(stream)
    t_mid = (stream[10][0] + stream[11][0]) // 2
    roll, pitch = f.attitude_at(t_mid)
    assert roll == pytest.approx(0.05, abs=0.01) and pitch == pytest.approx(-0.02, abs=0.01)
    assert f.attitude_at(stream[0][0] - 1) is None
    assert f.settled_until() == stream[-2][0]


@pytest.mark.parametrize(
    "key, value",
    [
        ("attitude_time_constant_s", 0.0),
        ("attitude_accel_gate_mps2", -1.0),
        ("gyro_bias_time_constant_s", float("nan")),
        ("deskew_step_s", 0.2),
        ("deskew", "yes"),
    ],
)
def test_bad_settings_are_named(key, value):
    with pytest.raises(ConfigError, match=f"localization.{key}"):
        LocalizationConfig(**{key: value})


def test_the_mapper_places_the_base_with_roll_and_pitch():
    from treetraits.pipeline.localization.pose import Pose
    from treetraits.pipeline.mapper import TreeMapper

    pose = Pose(0, 1.0, 2.0, 0.3, np.zeros((3, 3)), "utm", z=0.5, roll=0.1, pitch=-0.2)
    t_map_base = TreeMapper()._map_from_base(pose, None, 0)
    np.testing.assert_allclose(t_map_base[:3, :3], rotation_zyx(0.1, -0.2, 0.3), atol=1e-12)
    np.testing.assert_allclose(t_map_base[:3, 3], (1.0, 2.0, 0.5))
    # A point 1 m up the robot's mast leans with the roll (left side up: mast to the right).
    top = t_map_base @ np.array([0.0, 0.0, 1.0, 1.0])
    assert top[2] == pytest.approx(0.5 + math.cos(0.1) * math.cos(-0.2))
    right = np.array([math.sin(0.3), -math.cos(0.3)])  # the robot's right, in the map
    assert (top[:2] - (1.0, 2.0)) @ right == pytest.approx(math.sin(0.1))


def test_cross3_is_numpys_cross_bit_for_bit():
    rng = np.random.default_rng(7)
    for _ in range(2000):
        scale = 10.0 ** rng.integers(-6, 4)
        a, b = rng.normal(size=3) * scale, rng.normal(size=3)
        assert np.array_equal(cross3(a, b), np.cross(a, b))
