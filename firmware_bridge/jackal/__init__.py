"""The Clearpath Jackal's MCU over USB serial (`/dev/jackal`), as a rosserial host without ROS.

- `rosserial`: frames, the resyncing `FrameReader`, TopicInfo and the host's few frames;
- `messages`: the ROS 1 layouts (jackal_msgs, sensor_msgs, nmea_msgs, std_msgs) as data;
- `records`: what a session yields besides `WheelSample`;
- `session`: the protocol state machine (`JackalProtocol`), the live `JackalSession` and
  `decode_stream` for recordings;
- `serial_link`: the port; `teleop`: the optional joystick relay (off by default).

See docs/jackal.md.
"""

from treetraits.firmware_bridge.jackal.messages import Drive
from treetraits.firmware_bridge.jackal.records import (
    DriveUnit,
    JackalFeedback,
    JackalImu,
    JackalMagnetometer,
    JackalNmea,
    JackalStatus,
    LinkEvent,
    McuLog,
    SerialChunk,
)
from treetraits.firmware_bridge.jackal.rosserial import Frame, FrameReader, TopicInfo
from treetraits.firmware_bridge.jackal.serial_link import LinkLostError, SerialLink
from treetraits.firmware_bridge.jackal.session import JackalProtocol, JackalSession, decode_stream
from treetraits.firmware_bridge.jackal.teleop import TeleopConfig, TeleopRelay, teleop_drive

__all__ = [
    "Drive",
    "DriveUnit",
    "Frame",
    "FrameReader",
    "JackalFeedback",
    "JackalImu",
    "JackalMagnetometer",
    "JackalNmea",
    "JackalProtocol",
    "JackalSession",
    "JackalStatus",
    "LinkEvent",
    "LinkLostError",
    "McuLog",
    "SerialChunk",
    "SerialLink",
    "TeleopConfig",
    "TeleopRelay",
    "TopicInfo",
    "decode_stream",
    "teleop_drive",
]
