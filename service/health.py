"""Per-sensor health and the one-line status: pure functions of what the workers saw.

A sensor is `ok` while items arrive, `silent` when nothing came for longer than its
`silence_s` (counted from the start when nothing ever came), `disconnected` while its
device is gone and being reopened. Any problem (a sensor's, or the service's own, e.g. a
full disk) makes the status DEGRADED and is named in it. Sensors disabled in the config
have no state and are not reported.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class SensorState:
    """What one receive thread knows about its sensor (times on the monotonic clock)."""

    name: str  # lidar | camera | gnss | wheels
    silence_s: float
    started: float  # when the service began listening
    last_seen: float | None = None  # when the last item arrived; None: nothing yet
    connected: bool = True
    detail: str = ""  # why disconnected / what is being done about it, one phrase


@dataclass(frozen=True, slots=True)
class Health:
    states: dict[str, str]  # sensor -> ok | silent | disconnected, in the given order
    problems: list[str]  # one phrase each, e.g. "gnss silent 4.1 s"

    @property
    def ok(self) -> bool:
        return not self.problems


def sensor_problem(state: SensorState, now: float) -> tuple[str, str | None]:
    """(`ok` | `silent` | `disconnected`, the phrase naming the problem or None)."""
    if not state.connected:
        phrase = f"{state.name} disconnected"
        return "disconnected", f"{phrase}: {state.detail}" if state.detail else phrase
    since = now - (state.last_seen if state.last_seen is not None else state.started)
    if since > state.silence_s:
        never = "" if state.last_seen is not None else ", nothing received yet"
        return "silent", f"{state.name} silent {since:.1f} s{never}"
    return "ok", None


def assess(states: Iterable[SensorState], now: float, extra: Iterable[str] = ()) -> Health:
    """Every sensor's state and every problem; `extra` adds the service's own (disk full)."""
    labels: dict[str, str] = {}
    problems: list[str] = []
    for state in states:
        label, problem = sensor_problem(state, now)
        labels[state.name] = label
        if problem:
            problems.append(problem)
    problems.extend(extra)
    return Health(labels, problems)


def status_line(health: Health, counters: Mapping[str, int]) -> str:
    """The STATUS= text: `OK scans=120 trees=6 lidar=ok ...` or `DEGRADED gnss silent
    4.1 s; ... | scans=120 ...`. Always one line (systemd shows it as given)."""
    numbers = " ".join(f"{k}={v}" for k, v in counters.items())
    sensors = " ".join(f"{k}={v}" for k, v in health.states.items())
    tail = " ".join(part for part in (numbers, sensors) if part)
    problems = "; ".join(health.problems)
    line = f"OK {tail}" if health.ok else f"DEGRADED {problems} | {tail}"
    return " ".join(line.split())  # no newline may reach the notify socket
