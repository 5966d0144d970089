"""The retrofit encoder board (tractors): protocol v1 (PROTOCOL.md beside this package's
parent), a push decoder, and the serial link. The reference firmware is in
`firmware_bridge/firmware/`.

    from treetraits.firmware_bridge.retrofit import open_bridge
    for item in open_bridge("/dev/serial/by-id/usb-Raspberry_Pi_Pico_E660...-if00"):
        ...  # WheelSample (unit "ticks"), Heartbeat, ConfigEcho, LinkEvent
"""

from treetraits.firmware_bridge.retrofit.protocol import (
    VERSION,
    ConfigEcho,
    Fault,
    FrameError,
    Heartbeat,
    MessageType,
    Ticks,
)
from treetraits.firmware_bridge.retrofit.reader import (
    BridgeDecoder,
    BridgeReader,
    ReaderStats,
    TickOdometer,
)
from treetraits.firmware_bridge.retrofit.serial_link import (
    BridgeChunk,
    LinkEvent,
    RetrofitSource,
    SerialLink,
    open_bridge,
)

__all__ = [
    "VERSION",
    "BridgeChunk",
    "BridgeDecoder",
    "BridgeReader",
    "ConfigEcho",
    "Fault",
    "FrameError",
    "Heartbeat",
    "LinkEvent",
    "MessageType",
    "ReaderStats",
    "RetrofitSource",
    "SerialLink",
    "TickOdometer",
    "Ticks",
    "open_bridge",
]
