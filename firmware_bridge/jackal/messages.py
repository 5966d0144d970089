"""ROS 1 message layouts the Jackal MCU speaks, as data, and one serializer for all of them.

ROS 1 serialization (roscpp_serialization, wiki.ros.org/msg): fields in declaration order,
little-endian, no padding; `bool` one byte; `string` = uint32 byte count + bytes; `T[n]` =
n elements back to back; `T[]` = uint32 count + elements; `time` = uint32 sec + uint32 nsec,
`duration` = int32 sec + int32 nsec; nested messages inlined. rosserial adds no length
prefix (the frame header carries the length).

Each `MessageType` names its fields as the .msg file does, with the md5sum ROS 1 computes
from the definition (tests/firmware_bridge/jackal/test_rosserial.py recomputes each from
the public .msg text). A topic is decoded only when the md5 the MCU announced in its
TopicInfo equals ours: a different md5 means a different layout.

`decode` gives plain values: ints, floats, bools, `bytes` for strings, tuples for arrays,
dicts for nested messages, and int nanoseconds for `time`/`duration`.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from treetraits.errors import ParseError

# ROS 1 primitive -> struct code (little-endian, no padding).
PRIMITIVES: Mapping[str, str] = {
    "bool": "B",
    "int8": "b",
    "uint8": "B",
    "byte": "b",
    "char": "B",
    "int16": "h",
    "uint16": "H",
    "int32": "i",
    "uint32": "I",
    "int64": "q",
    "uint64": "Q",
    "float32": "f",
    "float64": "d",
}
_STRUCTS = {name: struct.Struct("<" + code) for name, code in PRIMITIVES.items()}
_TIME = struct.Struct("<II")
_DURATION = struct.Struct("<ii")
_U32 = struct.Struct("<I")
_NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class MessageType:
    """A ROS 1 message layout: `fields` are (type, name) pairs in declaration order."""

    name: str
    md5: str
    fields: tuple[tuple[str, str], ...]

    def decode(self, payload: bytes) -> dict[str, Any]:
        """The message's values; `ParseError` if the payload is short or too long."""
        try:
            values, offset = _read_message(self, payload, 0)
        except (struct.error, IndexError) as exc:
            raise ParseError(
                f"{self.name}: payload of {len(payload)} bytes ends inside a field ({exc})"
            ) from exc
        if offset != len(payload):
            raise ParseError(
                f"{self.name}: {len(payload) - offset} unexpected bytes after the message "
                f"({len(payload)} bytes, the layout used {offset}); is the definition the same?"
            )
        return values

    def encode(self, values: Mapping[str, Any]) -> bytes:
        """Serialize `values` (the same shapes `decode` returns)."""
        out: list[bytes] = []
        _write_message(self, values, out)
        return b"".join(out)


def _split_array(type_name: str) -> tuple[str, int | None, bool]:
    """'float64[9]' -> ('float64', 9, True); 'string[]' -> ('string', None, True)."""
    if not type_name.endswith("]"):
        return type_name, None, False
    base, _, size = type_name[:-1].partition("[")
    return base, (int(size) if size else None), True


def _read_string(data: bytes, offset: int) -> tuple[bytes, int]:
    (n,) = _U32.unpack_from(data, offset)
    offset += 4
    if offset + n > len(data):
        raise ParseError(f"a string of {n} bytes at offset {offset} runs past the payload")
    return data[offset : offset + n], offset + n


def _read_one(base: str, data: bytes, offset: int) -> tuple[Any, int]:
    st = _STRUCTS.get(base)
    if st is not None:
        (value,) = st.unpack_from(data, offset)
        return (bool(value) if base == "bool" else value), offset + st.size
    if base == "string":
        return _read_string(data, offset)
    if base == "time":
        sec, nsec = _TIME.unpack_from(data, offset)
        return sec * _NS + nsec, offset + _TIME.size
    if base == "duration":
        sec, nsec = _DURATION.unpack_from(data, offset)
        return sec * _NS + nsec, offset + _DURATION.size
    return _read_message(TYPES[base], data, offset)


def _plan(mt: MessageType) -> list[tuple]:
    """How to read `mt`: runs of primitive fields (and fixed-size primitive arrays) as one
    struct each, the rest field by field. Built once per type: at 50 Hz Feedback and IMU
    frames, reading field by field was a millisecond a frame of a replay's time."""
    plan: list[tuple] = []
    for type_name, field in mt.fields:
        base, size, is_array = _split_array(type_name)
        code = PRIMITIVES.get(base)
        if code is None or (is_array and size is None):
            plan.append(("field", field, base, size, is_array))
        elif is_array:
            plan.append(("array", field, struct.Struct(f"<{size}{code}"), base == "bool"))
        elif plan and plan[-1][0] == "run":
            _, names, bools, codes = plan.pop()
            plan.append(("run", (*names, field), (*bools, base == "bool"), codes + code))
        else:
            plan.append(("run", (field,), (base == "bool",), code))
    for k, step in enumerate(plan):
        if step[0] == "run":
            plan[k] = (*step[:3], struct.Struct("<" + step[3]))
    return plan


_PLANS: dict[MessageType, list[tuple]] = {}


def _read_message(mt: MessageType, data: bytes, offset: int) -> tuple[dict[str, Any], int]:
    plan = _PLANS.get(mt)
    if plan is None:
        plan = _PLANS[mt] = _plan(mt)
    values: dict[str, Any] = {}
    for step in plan:
        if step[0] == "run":
            _, names, bools, st = step
            read = st.unpack_from(data, offset)
            for name, is_bool, value in zip(names, bools, read, strict=True):
                values[name] = bool(value) if is_bool else value
            offset += st.size
            continue
        if step[0] == "array":
            _, field, st, is_bool = step
            items = st.unpack_from(data, offset)
            values[field] = tuple(bool(v) for v in items) if is_bool else items
            offset += st.size
            continue
        _, field, base, size, is_array = step
        if not is_array:
            values[field], offset = _read_one(base, data, offset)
            continue
        if size is None:
            (size,) = _U32.unpack_from(data, offset)
            offset += 4
            if size > len(data) - offset:  # every element takes at least one byte
                raise ParseError(f"{mt.name}.{field}: {size} elements cannot fit the payload")
        items = []
        for _ in range(size):
            item, offset = _read_one(base, data, offset)
            items.append(item)
        values[field] = tuple(items)
    return values, offset


def _write_one(base: str, value: Any, out: list[bytes]) -> None:
    st = _STRUCTS.get(base)
    if st is not None:
        out.append(st.pack(int(value) if base == "bool" else value))
    elif base == "string":
        raw = value.encode() if isinstance(value, str) else bytes(value)
        out.append(_U32.pack(len(raw)) + raw)
    elif base in ("time", "duration"):
        sec, nsec = divmod(int(value), _NS)
        out.append((_TIME if base == "time" else _DURATION).pack(sec, nsec))
    else:
        _write_message(TYPES[base], value, out)


def _write_message(mt: MessageType, values: Mapping[str, Any], out: list[bytes]) -> None:
    for type_name, field in mt.fields:
        base, size, is_array = _split_array(type_name)
        value = values[field]
        if not is_array:
            _write_one(base, value, out)
            continue
        if size is None:
            out.append(_U32.pack(len(value)))
        elif len(value) != size:
            raise ValueError(f"{mt.name}.{field} needs {size} elements, got {len(value)}")
        for item in value:
            _write_one(base, item, out)


def _type(name: str, md5: str, *fields: str) -> MessageType:
    """A layout from .msg-style lines: 'float32 current'."""
    pairs = tuple(tuple(line.split()) for line in fields)
    assert all(len(p) == 2 for p in pairs), name
    return MessageType(name, md5, pairs)  # type: ignore[arg-type]


HEADER = _type(
    "std_msgs/Header",
    "2176decaecbce78abc3b96ef049fabed",
    "uint32 seq",
    "time stamp",
    "string frame_id",
)
TIME = _type("std_msgs/Time", "cd7166c74c552c311fbcc2fe5a7bc289", "time data")
STRING = _type("std_msgs/String", "992ce8a1687cec8c8bd883ec73ca41d1", "string data")
BOOL = _type("std_msgs/Bool", "8b94c1b53db61fb6aed406028ad6332a", "bool data")
VECTOR3 = _type(
    "geometry_msgs/Vector3",
    "4a842b65f413084dc2b10fb484ea7f17",
    "float64 x",
    "float64 y",
    "float64 z",
)
QUATERNION = _type(
    "geometry_msgs/Quaternion",
    "a779879fadf0160734f906b8c19c7004",
    "float64 x",
    "float64 y",
    "float64 z",
    "float64 w",
)
VECTOR3_STAMPED = _type(
    "geometry_msgs/Vector3Stamped",
    "7b324c7325e683bf02a9b14b01090ec7",
    "std_msgs/Header header",
    "geometry_msgs/Vector3 vector",
)
IMU = _type(
    "sensor_msgs/Imu",
    "6a62c6daae103f4ff57a132d6f95cec2",
    "std_msgs/Header header",
    "geometry_msgs/Quaternion orientation",
    "float64[9] orientation_covariance",
    "geometry_msgs/Vector3 angular_velocity",
    "float64[9] angular_velocity_covariance",
    "geometry_msgs/Vector3 linear_acceleration",
    "float64[9] linear_acceleration_covariance",
)
MAGNETIC_FIELD = _type(
    "sensor_msgs/MagneticField",
    "2f3b0b43eed0c9501de0fa3ff89a45aa",
    "std_msgs/Header header",
    "geometry_msgs/Vector3 magnetic_field",
    "float64[9] magnetic_field_covariance",
)
NMEA_SENTENCE = _type(
    "nmea_msgs/Sentence",
    "9f221efc5f4b3bac7ce4af102b32308b",
    "std_msgs/Header header",
    "string sentence",
)
DRIVE_FEEDBACK = _type(
    "jackal_msgs/DriveFeedback",
    "8dd0b7a3cfa20cfc5c054ddd9763609b",
    "float32 current",  # battery -> bridge, A
    "float32 duty_cycle",
    "float32 bridge_temperature",  # deg C
    "float32 motor_temperature",  # deg C
    "float32 measured_velocity",  # wheel, rad/s
    "float32 measured_travel",  # wheel, cumulative rad
    "bool driver_fault",
)
FEEDBACK = _type(
    "jackal_msgs/Feedback",
    "3bdabb0ef46338ee5672d1b82220ab49",
    "std_msgs/Header header",
    "jackal_msgs/DriveFeedback[2] drivers",  # 0 left, 1 right
    "float32 pcb_temperature",
    "float32 mcu_temperature",
    "int8 commanded_mode",
    "int8 actual_mode",
)
# Constants (not serialized, but part of the md5): MODE_VELOCITY=0 MODE_PWM=1 MODE_EFFORT=2
# MODE_NONE=-1 LEFT=0 RIGHT=1.
DRIVE = _type(
    "jackal_msgs/Drive",
    "601cf097cd47c174590c366c6ddd5fb3",
    "int8 mode",
    "float32[2] drivers",
)
STATUS = _type(
    "jackal_msgs/Status",
    "c851ebcf9a6e20b196bc7894e285b4f6",
    "std_msgs/Header header",
    "string hardware_id",
    "duration mcu_uptime",
    "duration connection_uptime",
    "bool drivers_active",
    "bool driver_external_stop_present",
    "bool driver_external_stop_stopped",
    "float32 measured_battery",
    "float32 measured_12v",
    "float32 measured_5v",
    "float32 drive_current",
    "float32 user_current",
    "float32 computer_current",
    "float32 total_current",
    "float32 total_current_peak",
    "float64 total_power_consumed",
)

TYPES: Mapping[str, MessageType] = {
    mt.name: mt
    for mt in (
        HEADER,
        TIME,
        STRING,
        BOOL,
        VECTOR3,
        QUATERNION,
        VECTOR3_STAMPED,
        IMU,
        MAGNETIC_FIELD,
        NMEA_SENTENCE,
        DRIVE_FEEDBACK,
        FEEDBACK,
        DRIVE,
        STATUS,
    )
}

# jackal_msgs/Drive modes and the size of its payload.
MODE_VELOCITY = 0  # wheel rad/s
MODE_PWM = 1  # fraction of full voltage, -1..1
MODE_EFFORT = 2  # torque, N m
MODE_NONE = -1
DRIVE_SIZE = 9


@dataclass(frozen=True, slots=True)
class Drive:
    """jackal_msgs/Drive: one command for both sides. Positive values drive forward."""

    mode: int
    left: float
    right: float

    def encode(self) -> bytes:
        return DRIVE.encode({"mode": self.mode, "drivers": (self.left, self.right)})

    @classmethod
    def decode(cls, payload: bytes) -> Drive:
        values = DRIVE.decode(payload)
        return cls(values["mode"], *values["drivers"])

    @property
    def is_stop(self) -> bool:
        return self.left == 0.0 and self.right == 0.0


STOP = Drive(MODE_VELOCITY, 0.0, 0.0)
