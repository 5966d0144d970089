"""The MAPIR Survey3N RGN camera: live over UVC (OpenCV's V4L2 backend) and replayed from
a folder of JPEGs, a video file or a recording, all behind `open_camera_source(uri)`.

Frames keep the camera's JPEG bytes and are decoded only when the pipeline asks for one.
See docs/camera.md.
"""

from treetraits.drivers.camera.frames import CameraStats, FrameRing, decode_frame, nearest_index
from treetraits.drivers.camera.live import ControlOutcome, Negotiation, UvcCamera
from treetraits.drivers.camera.replay import (
    FolderWriter,
    ImageFolderSource,
    RecordingSource,
    VideoFileSource,
)
from treetraits.drivers.camera.settings import CameraSettings
from treetraits.drivers.camera.sources import CameraSource, open_camera_source, record_frame

__all__ = [
    "CameraSettings",
    "CameraSource",
    "CameraStats",
    "ControlOutcome",
    "FolderWriter",
    "FrameRing",
    "ImageFolderSource",
    "Negotiation",
    "RecordingSource",
    "UvcCamera",
    "VideoFileSource",
    "decode_frame",
    "nearest_index",
    "open_camera_source",
    "record_frame",
]
