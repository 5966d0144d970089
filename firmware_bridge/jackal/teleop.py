"""Optional teleop relay: a Linux joystick to jackal_msgs/Drive at 50 Hz, off by default.

The service owns the MCU port, so nothing else can drive the robot; this relay is the only
path to motion, and only when enabled. Safety rules, all in the pure `teleop_drive`:

- motion only while the dead-man button is held, and only after a real press seen since the
  joystick was opened (a button already down when the device appears does not count);
- every wheel's ground speed is capped at `speed_limit_mps` (both sides scaled together, so
  the curvature is kept);
- a release, an unplugged joystick (read error or end of file) or a silent one (no event for
  `silence_timeout_s`) is a stop: `DriveGate` sends explicit zero commands for `stop_hold_s`
  and then goes quiet. The firmware's own command timeout is not documented, so the relay
  never relies on it.

Input is the kernel joystick API (`/dev/input/js*`): 8-byte `struct js_event` records,
`u32 time (ms), s16 value, u8 type, u8 number`, in native byte order; type bit 0x80 marks the
synthetic events the driver sends on open to report the initial state. The kernel reports
changes only: a stick held perfectly still with the button down sends nothing, which the
silence rule cannot tell from a frozen link (see docs/jackal.md).
"""

from __future__ import annotations

import errno
import logging
import math
import os
import select
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass

from treetraits.errors import ConfigError
from treetraits.firmware_bridge.jackal.messages import MODE_VELOCITY, STOP, Drive

log = logging.getLogger(__name__)

JS_EVENT = struct.Struct("=IhBB")  # struct js_event, native byte order
JS_EVENT_BUTTON = 0x01
JS_EVENT_AXIS = 0x02
JS_EVENT_INIT = 0x80
AXIS_MAX = 32767


@dataclass(frozen=True, slots=True)
class JsEvent:
    time_ms: int  # the driver's timestamp (ms, arbitrary origin)
    value: int  # axis -32767..32767; button 0/1
    type: int
    number: int

    @property
    def is_init(self) -> bool:
        return bool(self.type & JS_EVENT_INIT)

    @property
    def kind(self) -> int:
        return self.type & ~JS_EVENT_INIT


def parse_js_events(data: bytes) -> tuple[list[JsEvent], bytes]:
    """Whole `js_event` records from `data`, and the bytes of an unfinished one."""
    whole = len(data) - len(data) % JS_EVENT.size
    events = [JsEvent(*fields) for fields in JS_EVENT.iter_unpack(data[:whole])]
    return events, data[whole:]


@dataclass(frozen=True, slots=True)
class TeleopConfig:
    """The relay's settings. Axes and buttons are js numbers (`jstest /dev/input/js0`
    shows them); the defaults fit Logitech F710 / Xbox-style pads (left stick, LB)."""

    device: str = "/dev/input/js0"
    deadman_button: int = 4
    linear_axis: int = 1
    angular_axis: int = 0
    invert_linear: bool = True  # the kernel reports stick-forward as negative
    invert_angular: bool = True  # and stick-left as negative; a left turn is +yaw
    max_linear_mps: float = 0.5  # at full stick
    max_angular_rps: float = 1.0  # at full stick
    speed_limit_mps: float = 0.5  # hard cap on each wheel's ground speed
    deadzone: float = 0.05  # fraction of full stick read as zero
    wheel_radius_m: float = 0.098
    track_m: float = 0.5634  # effective skid-steer track (0.37559 m x 1.5, jackal_control)
    rate_hz: float = 50.0
    silence_timeout_s: float | None = 0.15  # None: trust the link until a read error
    stop_hold_s: float = 0.5  # keep commanding zero this long after a stop, then go quiet
    reopen_s: float = 0.5  # retry opening a missing joystick this often

    def __post_init__(self) -> None:
        positive = {
            "max_linear_mps": self.max_linear_mps,
            "max_angular_rps": self.max_angular_rps,
            "speed_limit_mps": self.speed_limit_mps,
            "wheel_radius_m": self.wheel_radius_m,
            "track_m": self.track_m,
            "rate_hz": self.rate_hz,
            "reopen_s": self.reopen_s,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"teleop.{name} must be a positive number, got {value!r}")
        if not 0.0 <= self.deadzone < 1.0:
            raise ConfigError(f"teleop.deadzone must be in [0, 1), got {self.deadzone!r}")
        if self.silence_timeout_s is not None and not self.silence_timeout_s > 0:
            raise ConfigError(
                f"teleop.silence_timeout_s must be positive or null, got {self.silence_timeout_s!r}"
            )
        if not self.stop_hold_s >= 0:
            raise ConfigError(f"teleop.stop_hold_s must be >= 0, got {self.stop_hold_s!r}")
        for name in ("deadman_button", "linear_axis", "angular_axis"):
            if not 0 <= getattr(self, name) <= 255:
                raise ConfigError(f"teleop.{name} must be a js number 0..255")


@dataclass(frozen=True, slots=True)
class JoystickState:
    """What the relay knows about the joystick at one moment (a snapshot)."""

    axes: tuple[int, ...] = ()
    buttons: tuple[int, ...] = ()
    connected: bool = False
    armed: bool = False  # the dead-man went down by a real press since the device opened
    last_event: float | None = None  # monotonic s when the last event was read

    def axis(self, number: int) -> int:
        return self.axes[number] if number < len(self.axes) else 0

    def button(self, number: int) -> bool:
        return number < len(self.buttons) and self.buttons[number] != 0


def _stick(value: int, deadzone: float, invert: bool) -> float:
    x = max(-1.0, min(1.0, value / AXIS_MAX))
    if abs(x) <= deadzone:
        return 0.0
    x = math.copysign((abs(x) - deadzone) / (1.0 - deadzone), x)
    return -x if invert else x


def engaged(now: float, joy: JoystickState, config: TeleopConfig) -> bool:
    """True while motion is allowed: connected, armed, dead-man held, events fresh."""
    if not (joy.connected and joy.armed and joy.button(config.deadman_button)):
        return False
    if config.silence_timeout_s is None:
        return True
    return joy.last_event is not None and now - joy.last_event <= config.silence_timeout_s


def teleop_drive(now: float, joy: JoystickState, config: TeleopConfig) -> Drive | None:
    """The command for this tick: a velocity Drive (wheel rad/s) while engaged, else None
    (stop). Pure: the same inputs always give the same command."""
    if not engaged(now, joy, config):
        return None
    v = _stick(joy.axis(config.linear_axis), config.deadzone, config.invert_linear)
    w = _stick(joy.axis(config.angular_axis), config.deadzone, config.invert_angular)
    v *= config.max_linear_mps
    w *= config.max_angular_rps
    half_track = config.track_m / 2
    left = (v - w * half_track) / config.wheel_radius_m
    right = (v + w * half_track) / config.wheel_radius_m
    limit = config.speed_limit_mps / config.wheel_radius_m
    peak = max(abs(left), abs(right))
    if peak > limit:
        scale = limit / peak
        left, right = left * scale, right * scale
    return Drive(MODE_VELOCITY, left + 0.0, right + 0.0)  # + 0.0: no negative zeros


class DriveGate:
    """Decides what goes on the wire each tick: the command while engaged, explicit stops for
    `stop_hold_s` after it ends, then nothing (so an idle relay never talks to the MCU)."""

    def __init__(self, stop_hold_s: float):
        self.stop_hold_s = stop_hold_s
        self._last_engaged: float | None = None

    def tick(self, now: float, command: Drive | None) -> Drive | None:
        if command is not None:
            self._last_engaged = now
            return command
        if self._last_engaged is not None and now - self._last_engaged <= self.stop_hold_s:
            return STOP
        self._last_engaged = None
        return None

    @property
    def active(self) -> bool:
        """True while it has commands or stops to send."""
        return self._last_engaged is not None


class JoystickTracker:
    """Push object: js events in, `JoystickState` out."""

    def __init__(self, deadman_button: int):
        self.deadman_button = deadman_button
        self._axes: list[int] = []
        self._buttons: list[int] = []
        self._connected = False
        self._armed = False
        self._last_event: float | None = None

    def connect(self, now: float) -> None:
        self._axes.clear()
        self._buttons.clear()
        self._connected = True
        self._armed = False
        self._last_event = now

    def disconnect(self) -> None:
        self._connected = False
        self._armed = False

    def push(self, event: JsEvent, now: float) -> None:
        if event.kind not in (JS_EVENT_BUTTON, JS_EVENT_AXIS):
            return
        table = self._buttons if event.kind == JS_EVENT_BUTTON else self._axes
        if event.number >= len(table):
            table.extend([0] * (event.number + 1 - len(table)))
        table[event.number] = event.value
        self._last_event = now
        if event.kind == JS_EVENT_BUTTON and event.number == self.deadman_button:
            # Only a real press arms: a button already held when the device opens does not.
            self._armed = bool(event.value) and not event.is_init

    @property
    def state(self) -> JoystickState:
        return JoystickState(
            tuple(self._axes), tuple(self._buttons), self._connected, self._armed, self._last_event
        )


@dataclass
class TeleopStats:
    events: int = 0
    opens: int = 0
    disconnects: int = 0
    ticks: int = 0
    commands_sent: int = 0  # Drive frames written while engaged
    stops_sent: int = 0  # explicit zero commands after disengaging
    send_failures: int = 0  # no cmd_drive topic known yet, or the MCU port is down

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


class TeleopRelay:
    """The thin thread: reads the joystick and, at `rate_hz`, hands `send` the command.

    `send(drive) -> bool` writes one Drive to the MCU (False if it could not). One thread
    does both jobs, blocking in `select` until the next event or the next tick.
    """

    def __init__(
        self,
        config: TeleopConfig,
        send: Callable[[Drive], bool],
        clock: Callable[[], float] = time.monotonic,
    ):
        self.config = config
        self.stats = TeleopStats()
        self._send = send
        self._clock = clock
        self._tracker = JoystickTracker(config.deadman_button)
        self._gate = DriveGate(config.stop_hold_s)
        self._fd: int | None = None
        self._partial = b""
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="jackal-teleop", daemon=True)

    @property
    def joystick(self) -> JoystickState:
        return self._tracker.state

    def start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        """Stop the thread; if the robot was being driven, send one last stop first."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        if self._gate.active:
            self._tracker.disconnect()
            if self._send(STOP):
                self.stats.stops_sent += 1
        self._close_device()

    def _open_device(self, now: float) -> None:
        try:
            self._fd = os.open(self.config.device, os.O_RDONLY | os.O_NONBLOCK)
        except OSError as exc:
            log.debug("joystick %s not available: %s", self.config.device, exc)
            return
        self._partial = b""
        self._tracker.connect(now)
        self.stats.opens += 1
        log.info("teleop: joystick %s opened", self.config.device)

    def _close_device(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def _lost(self, why: str) -> None:
        log.warning("teleop: joystick %s lost (%s): stopping", self.config.device, why)
        self._close_device()
        self._tracker.disconnect()
        self.stats.disconnects += 1

    def _read_events(self, now: float) -> None:
        assert self._fd is not None
        try:
            data = os.read(self._fd, 64 * JS_EVENT.size)
        except BlockingIOError:
            return
        except OSError as exc:
            self._lost(errno.errorcode.get(exc.errno or 0, str(exc)))
            return
        if not data:
            self._lost("end of file")
            return
        events, self._partial = parse_js_events(self._partial + data)
        for event in events:
            self._tracker.push(event, now)
        self.stats.events += len(events)

    def tick(self, now: float) -> Drive | None:
        """One control step: what to send now (None: nothing). Sends it through `send`."""
        self.stats.ticks += 1
        command = teleop_drive(now, self._tracker.state, self.config)
        out = self._gate.tick(now, command)
        if out is None:
            return None
        if not self._send(out):
            self.stats.send_failures += 1
        elif command is None:
            self.stats.stops_sent += 1
        else:
            self.stats.commands_sent += 1
        return out

    def _run(self) -> None:
        period = 1.0 / self.config.rate_hz
        next_tick = self._clock()
        next_open = next_tick
        while not self._stop.is_set():
            now = self._clock()
            if self._fd is None and now >= next_open:
                self._open_device(now)
                next_open = now + self.config.reopen_s
            if now >= next_tick:
                self.tick(now)
                next_tick += period
                if next_tick < now:  # fell behind (suspended?): do not burst to catch up
                    next_tick = now + period
            wait = max(0.0, next_tick - self._clock())
            if self._fd is None:
                self._stop.wait(min(wait, max(0.0, next_open - self._clock())))
                continue
            try:
                ready, _, _ = select.select([self._fd], [], [], wait)
            except (OSError, ValueError) as exc:
                self._lost(str(exc))
                continue
            if ready:
                self._read_events(self._clock())
