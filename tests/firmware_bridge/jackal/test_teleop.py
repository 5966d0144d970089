"""The teleop relay's pure parts: js_event parsing, the joystick state, the command function
and the gate that turns a stop into explicit zero commands, then silence.

js_event records are packed here with `struct` from the kernel's definition
(linux/joystick.h: __u32 time, __s16 value, __u8 type, __u8 number).
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from treetraits.errors import ConfigError
from treetraits.firmware_bridge.jackal.messages import MODE_VELOCITY, STOP, Drive
from treetraits.firmware_bridge.jackal.teleop import (
    DriveGate,
    JoystickState,
    JoystickTracker,
    JsEvent,
    TeleopConfig,
    parse_js_events,
    teleop_drive,
)

BUTTON, AXIS, INIT = 0x01, 0x02, 0x80
CONFIG = TeleopConfig()  # deadman 4, linear axis 1, angular axis 0, limit 0.5 m/s


def js(time_ms: int, value: int, kind: int, number: int) -> bytes:
    return struct.pack("=IhBB", time_ms, value, kind, number)


def held(linear: int = 0, angular: int = 0, last_event: float = 10.0) -> JoystickState:
    axes = [0] * 6
    axes[CONFIG.angular_axis], axes[CONFIG.linear_axis] = angular, linear
    buttons = [0] * 8
    buttons[CONFIG.deadman_button] = 1
    return JoystickState(tuple(axes), tuple(buttons), True, True, last_event)


def test_js_events_parse_and_keep_a_partial_record():
    data = js(1000, -32767, AXIS, 1) + js(1001, 1, BUTTON | INIT, 4) + js(5, 0, BUTTON, 0)[:3]
    events, rest = parse_js_events(data)
    assert events == [JsEvent(1000, -32767, AXIS, 1), JsEvent(1001, 1, BUTTON | INIT, 4)]
    assert events[1].is_init and events[1].kind == BUTTON and not events[0].is_init
    assert rest == js(5, 0, BUTTON, 0)[:3]


def test_only_a_real_press_arms_the_deadman():
    tracker = JoystickTracker(deadman_button=4)
    tracker.connect(0.0)
    tracker.push(JsEvent(0, 1, BUTTON | INIT, 4), 0.0)  # held down when plugged in
    assert tracker.state.button(4) and not tracker.state.armed
    tracker.push(JsEvent(1, 0, BUTTON, 4), 0.1)
    tracker.push(JsEvent(2, 1, BUTTON, 4), 0.2)
    assert tracker.state.armed and tracker.state.last_event == 0.2
    tracker.push(JsEvent(3, 0, BUTTON, 4), 0.3)
    assert not tracker.state.armed
    tracker.push(JsEvent(4, 1, BUTTON, 4), 0.4)
    tracker.disconnect()
    assert not tracker.state.armed and not tracker.state.connected


def test_full_stick_forward_is_clamped_to_the_speed_limit():
    drive = teleop_drive(10.0, held(linear=-32767), CONFIG)
    limit = CONFIG.speed_limit_mps / CONFIG.wheel_radius_m
    assert drive == Drive(MODE_VELOCITY, pytest.approx(limit), pytest.approx(limit))
    assert drive.left > 0  # stick forward reads negative; forward is positive


def test_stick_left_turns_left_and_spin_in_place_is_limited_too():
    drive = teleop_drive(10.0, held(angular=-32767), CONFIG)  # stick left
    assert drive.right > 0 > drive.left  # counter-clockwise seen from above
    limit = CONFIG.speed_limit_mps / CONFIG.wheel_radius_m
    assert max(abs(drive.left), abs(drive.right)) <= limit * (1 + 1e-12)


def test_half_stick_is_below_the_limit_and_linear():
    config = TeleopConfig(max_linear_mps=0.4, speed_limit_mps=1.0, deadzone=0.0)
    drive = teleop_drive(10.0, held(linear=-16384), config)
    assert drive.left == drive.right == pytest.approx(0.2 / config.wheel_radius_m, rel=1e-4)


def test_deadzone_reads_as_zero():
    drive = teleop_drive(10.0, held(linear=1000, angular=-1500), CONFIG)  # < 5 % of full
    assert drive == Drive(MODE_VELOCITY, 0.0, 0.0)


@pytest.mark.parametrize(
    "state",
    [
        JoystickState(),  # never connected
        JoystickState((0, -32767), (0, 0, 0, 0, 1), True, False, 10.0),  # not armed
        JoystickState((0, -32767), (0, 0, 0, 0, 0), True, True, 10.0),  # released
        JoystickState((0, -32767), (0, 0, 0, 0, 1), False, True, 10.0),  # unplugged
        held(linear=-32767, last_event=10.0 - 0.151),  # silent longer than 0.15 s
    ],
)
def test_no_command_unless_engaged(state):
    assert teleop_drive(10.0, state, CONFIG) is None


def test_silence_timeout_can_be_disabled():
    config = TeleopConfig(silence_timeout_s=None)
    assert teleop_drive(1000.0, held(linear=-32767, last_event=0.0), config) is not None


def test_gate_sends_stops_for_a_while_then_nothing():
    gate = DriveGate(stop_hold_s=0.5)
    assert gate.tick(0.0, None) is None  # never engaged: silent
    go = Drive(MODE_VELOCITY, 1.0, 1.0)
    assert gate.tick(1.0, go) == go
    assert gate.tick(1.02, None) == STOP
    assert gate.tick(1.5, None) == STOP
    assert gate.tick(1.52, None) is None and not gate.active


def test_config_is_validated():
    with pytest.raises(ConfigError, match="speed_limit_mps"):
        TeleopConfig(speed_limit_mps=0.0)
    with pytest.raises(ConfigError, match="deadzone"):
        TeleopConfig(deadzone=1.0)
    with pytest.raises(ConfigError, match="silence_timeout_s"):
        TeleopConfig(silence_timeout_s=0.0)


@settings(max_examples=300, deadline=None)
@given(
    linear=st.integers(-32768, 32767),
    angular=st.integers(-32768, 32767),
    limit=st.floats(0.05, 3.0),
    max_linear=st.floats(0.05, 5.0),
    max_angular=st.floats(0.05, 10.0),
)
def test_no_wheel_ever_exceeds_the_limit(linear, angular, limit, max_linear, max_angular):
    config = TeleopConfig(
        speed_limit_mps=limit, max_linear_mps=max_linear, max_angular_rps=max_angular
    )
    drive = teleop_drive(10.0, held(linear, angular), config)
    bound = limit / config.wheel_radius_m * (1 + 1e-9)
    assert abs(drive.left) <= bound and abs(drive.right) <= bound
