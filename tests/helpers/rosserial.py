"""An independent encoder of the Jackal MCU's rosserial traffic: the rosserial protocol v2
frame layout written out, with the two checksums as the rosserial wiki states them, and
payloads packed with `struct` from the public .msg definitions."""

from __future__ import annotations

import struct


def ros_frame(topic: int, payload: bytes) -> bytes:
    """A protocol v2 frame, checksums computed as the rosserial wiki states them."""
    n = len(payload)
    len_lo, len_hi = n & 0xFF, n >> 8
    length_checksum = 255 - ((len_lo + len_hi) % 256)
    t_lo, t_hi = topic & 0xFF, topic >> 8
    data_checksum = 255 - ((t_lo + t_hi + sum(payload)) % 256)
    head = bytes([0xFF, 0xFE, len_lo, len_hi, length_checksum, t_lo, t_hi])
    return head + payload + bytes([data_checksum])


def ros_string(text: str | bytes) -> bytes:
    raw = text.encode() if isinstance(text, str) else text
    return struct.pack("<I", len(raw)) + raw


def ros_header(seq: int, sec: int, nsec: int, frame_id: str = "") -> bytes:
    return struct.pack("<III", seq, sec, nsec) + ros_string(frame_id)


def drive_feedback_bytes(current, duty, bridge_t, motor_t, velocity, travel, fault) -> bytes:
    return struct.pack("<6f?", current, duty, bridge_t, motor_t, velocity, travel, fault)


def feedback_bytes(
    seq=7,
    sec=1_700_000_000,
    nsec=250_000_000,
    frame_id="",
    left=(1.5, 0.25, 31.5, 29.0, 2.5, 123.25, False),
    right=(1.25, -0.125, 32.0, 30.5, -2.0, -45.5, True),
    pcb=38.5,
    mcu=41.0,
    commanded=0,
    actual=-1,
) -> bytes:
    return (
        ros_header(seq, sec, nsec, frame_id)
        + drive_feedback_bytes(*left)
        + drive_feedback_bytes(*right)
        + struct.pack("<ffbb", pcb, mcu, commanded, actual)
    )


def status_bytes(hardware_id="c0ffee1", seq=3) -> bytes:
    return (
        ros_header(seq, 1_700_000_001, 5, "base_link")
        + ros_string(hardware_id)
        + struct.pack("<ii", 3600, 500)  # mcu_uptime
        + struct.pack("<ii", 60, 0)  # connection_uptime
        + struct.pack("<???", True, False, False)
        + struct.pack("<8f", 26.5, 12.25, 5.0, 3.5, 0.75, 1.5, 5.75, 9.5)
        + struct.pack("<d", 12.125)
    )


def imu_bytes(seq=11) -> bytes:
    return (
        ros_header(seq, 1_700_000_002, 0, "imu_link")
        + struct.pack("<4d", 0.0, 0.0, 0.0, 1.0)
        + struct.pack("<9d", -1.0, *([0.0] * 8))
        + struct.pack("<3d", 0.01, -0.02, 0.5)
        + struct.pack("<9d", *([0.001] * 9))
        + struct.pack("<3d", 0.1, 0.2, 9.80665)
        + struct.pack("<9d", *([0.01] * 9))
    )


def sentence_bytes(sentence: bytes, seq=1) -> bytes:
    return ros_header(seq, 1_700_000_003, 0, "navsat") + ros_string(sentence)


def topic_info_bytes(topic_id, name, msg_type, md5, buffer_size=512) -> bytes:
    return (
        struct.pack("<H", topic_id)
        + ros_string(name)
        + ros_string(msg_type)
        + ros_string(md5)
        + struct.pack("<i", buffer_size)
    )
