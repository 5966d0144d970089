"""A Survey3N emulator: renders the orchard from the camera's pose by ray-casting every
pixel through the calibrated lens, and encodes the RGN bands as the camera would send
them (an MJPG frame whose BGR channels hold the bands given by calibration `channels`).

Reflectance per surface is chosen so that NDVI is what a citrus grove shows: foliage
~0.75, bare soil ~0.15, the trunk ~0.3, sky (no hit) ~ -0.1; raw 8-bit values are the
inverse of the calibration's reflectance gain/offset, so our NDVI pipeline reads the
intended values back.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from treetraits.drivers.calibration import Calibration
from treetraits.sim.lidar import Scene

# (red, green, nir) reflectance by surface label: 0 ground, -1 sky, >0 trees.
SOIL = (0.20, 0.18, 0.27)  # NDVI 0.15
FOLIAGE = (0.05, 0.12, 0.35)  # NDVI 0.75
SKY = (0.30, 0.30, 0.25)  # NDVI -0.09


@dataclass(frozen=True)
class CameraSettings:
    jpeg_quality: int = 90
    noise_dn: float = 1.5  # sensor noise, 8-bit digital numbers
    # Ray-cast at this fraction of the resolution and scale up (1.0 = every pixel): the
    # cost goes with the pixels cast, so 0.25 casts a sixteenth of them.
    render_scale: float = 1.0


class Survey3Emulator:
    def __init__(
        self,
        scene: Scene,
        calibration: Calibration,
        settings: CameraSettings | None = None,
        rng: np.random.Generator | None = None,
    ):
        if calibration.camera is None or calibration.T_camera_lidar is None:
            raise ValueError(
                "the camera emulator needs a calibration with camera and T_camera_lidar"
            )
        self.scene = scene
        self.calibration = calibration
        self.settings = settings or CameraSettings()
        self.rng = rng or np.random.default_rng(0)
        camera = calibration.camera
        scale = self.settings.render_scale
        self._size = (max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
        # Unit ray of every rendered pixel (its centre, in full-resolution pixel
        # coordinates) in the camera frame, through the lens distortion.
        u, v = np.meshgrid(
            (np.arange(self._size[0]) + 0.5) / scale - 0.5,
            (np.arange(self._size[1]) + 0.5) / scale - 0.5,
        )
        pixels = np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)
        undistorted = _undistort(pixels, camera.K, camera.dist)
        rays = np.column_stack([undistorted, np.ones(len(undistorted))])
        self._rays_camera = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        self._base_from_camera = calibration.T_base_lidar @ np.linalg.inv(
            calibration.T_camera_lidar
        )

    def render(self, world_from_base: np.ndarray, t_ns: int | None = None) -> np.ndarray:
        """The BGR uint8 image the camera sees with base_link at `world_from_base` (4x4),
        at device time `t_ns` (places swaying trees; needed only in wind)."""
        camera = self.calibration.camera
        world_from_camera = world_from_base @ self._base_from_camera
        directions = self._rays_camera @ world_from_camera[:3, :3].T
        origins = np.broadcast_to(world_from_camera[:3, 3], directions.shape)
        _, label = self.scene.cast(np.ascontiguousarray(origins), directions, t_ns)
        reflectance = np.empty((len(label), 3))
        reflectance[label == 0] = SOIL
        reflectance[label > 0] = FOLIAGE
        reflectance[label < 0] = SKY
        index, found = self.scene.material_index(label)
        if found.any():
            own = np.array([mat.reflectance for mat in self.scene.materials.values()])
            reflectance[found] = own[index[found]]
        image = np.zeros((len(label), 3))
        for band, column in (("red", 0), ("green", 1), ("nir", 2)):
            if band not in camera.channels:
                continue
            gain, offset = self.calibration.reflectance[band]
            raw = (reflectance[:, column] - offset) / gain
            image[:, camera.channels[band]] = raw
        image += self.rng.normal(0, self.settings.noise_dn, image.shape)
        image = np.clip(np.round(image), 0, 255).astype(np.uint8)
        image = image.reshape(self._size[1], self._size[0], 3)
        if self._size != (camera.width, camera.height):
            import cv2

            size = (camera.width, camera.height)
            image = cv2.resize(image, size, interpolation=cv2.INTER_NEAREST)
        return image

    def jpeg(self, world_from_base: np.ndarray, t_ns: int | None = None) -> bytes:
        import cv2

        ok, data = cv2.imencode(
            ".jpg",
            self.render(world_from_base, t_ns),
            [cv2.IMWRITE_JPEG_QUALITY, self.settings.jpeg_quality],
        )
        if not ok:
            raise RuntimeError("JPEG encoding failed")
        return data.tobytes()


def _undistort(pixels: np.ndarray, k: np.ndarray, dist: np.ndarray, iterations: int = 30):
    """Normalised image coordinates of distorted pixels (k1 k2 p1 p2 k3), by the usual
    fixed-point iteration (what cv2.undistortPoints does, with more iterations here so the
    far corners converge too)."""
    k1, k2, p1, p2, k3 = dist
    xd = (pixels[:, 0] - k[0, 2]) / k[0, 0]
    yd = (pixels[:, 1] - k[1, 2]) / k[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2**3
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        x = (xd - dx) / radial
        y = (yd - dy) / radial
    return np.column_stack([x, y])
