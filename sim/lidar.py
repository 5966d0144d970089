"""A VLP-16 emulator: ray-casts the orchard firing by firing and writes the UDP payloads
the real sensor would send (1206-byte data packets, 754 per second at 600 rpm).

Every laser fires at its own time (2.304 us slots, 55.296 us sequences), from the pose the
robot has at that instant (motion during the scan is real), in the direction the rotor
points then. Ranges get Gaussian noise and 2 mm quantisation; a fraction of returns drop
out; beyond `max_range` there is no return. The block azimuth written in each packet is
the rotor angle at the block's first firing, rounded to 0.01 deg as the sensor does.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

import numpy as np

from treetraits.drivers.velodyne import models as m
from treetraits.drivers.velodyne.encode import encode_packets

if TYPE_CHECKING:
    import open3d as o3d

# Pose of base_link in the world at times t (ns array): x, y, z, yaw arrays, optionally
# followed by pitch and roll (REP-103, R = Rz(yaw) Ry(pitch) Rx(roll); absent = level).
Trajectory = Callable[[np.ndarray], tuple[np.ndarray, ...]]


@dataclass(frozen=True)
class LidarSettings:
    rpm: float = 600.0
    range_sigma_m: float = 0.02  # VLP-16 datasheet: +-3 cm typical
    dropout: float = 0.01
    max_range_m: float = 100.0
    min_range_m: float = 0.4
    reflectivity_by_label: tuple[int, int] = (8, 45)  # ground, trees
    optics: m.LaserModel = m.VLP16
    # The sensor's GPS input (PPS and $GPRMC from the GNSS receiver): its ToH counts on UTC
    # and its position packets say PPS "locked" with the RMC. Without it (the default, as
    # on a stock Jackal) the ToH counts from power-on and position packets are not sent.
    gps_sync: bool = False
    power_on_s: float = 1234.567  # how long a sensor without GPS input has been running
    enabled: bool = True  # False: the sensor sends nothing (a drive of GNSS and wheels only)


@dataclass(frozen=True)
class Material:
    """What a surface looks like to the sensors: VLP-16 calibrated reflectivity (0-100,
    diffuse targets) and the camera's red, green and NIR reflectance (0-1)."""

    reflectivity: int
    reflectance: tuple[float, float, float]


class Walk(Protocol):
    """A rigid mesh translated over time (`sim.clutter.WalkingPath`): at time t its point
    q is at q + offset(t)."""

    centre: tuple[float, float]  # x, y the motion stays about
    reach: float  # m: the farthest any point of the mesh gets from `centre` (x-y)

    def offset(self, t_s: np.ndarray) -> np.ndarray: ...  # (N, 3)


class Sway(Protocol):
    """A mesh bending about its base in the wind (`sim.orchard.TreeSway`)."""

    base: tuple[float, float, float]
    max_offset: float  # m: the farthest any point of the mesh moves horizontally

    def shear(self, t_s: np.ndarray) -> np.ndarray: ...  # (N, 2) per metre above base


class Scene:
    """Triangle meshes in the world frame with a label per mesh (0 = ground). A label may
    have a `Material` (`materials`); without one, 0 looks like soil and the rest like
    foliage.

    A mesh added with a `walk` is translated by `walk.offset(t)` at time t: each ray is
    moved back by that offset and cast against the mesh's own scene, as for a sway.

    A mesh added with a `sway` moves: at time t its point q is at
    q + shear(t) * (q_z - base_z) (horizontal). A shear maps straight lines to straight
    lines, so each ray is moved into the mesh's rest frame instead and cast there, against
    a scene of its own; the ray parameter (the distance) is the same in both frames."""

    def __init__(self) -> None:
        import open3d as o3d  # heavy (pulls plotly and dash): only where meshes are cast

        self._scene = o3d.t.geometry.RaycastingScene()
        self._labels: list[int] = []
        # (own scene, label, sway or walk, x-y centre, reach: horizontal radius about the
        # centre it can occupy)
        self._moving: list[
            tuple[o3d.t.geometry.RaycastingScene, int, Sway | Walk, tuple[float, float], float]
        ] = []
        self.materials: dict[int, Material] = {}

    def add(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        label: int,
        sway: Sway | None = None,
        walk: Walk | None = None,
        material: Material | None = None,
    ) -> None:
        import open3d as o3d

        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor(np.asarray(vertices, dtype=np.float32))
        mesh.triangle.indices = o3d.core.Tensor(np.asarray(triangles, dtype=np.int32))
        if material is not None:
            self.materials[label] = material
        if sway is not None or walk is not None:
            own = o3d.t.geometry.RaycastingScene()
            own.add_triangles(mesh)
            if sway is not None:
                centre = (float(sway.base[0]), float(sway.base[1]))
                spread = np.hypot(*(np.asarray(vertices)[:, :2] - centre).T).max()
                reach = float(spread) + sway.max_offset + 0.05
                self._moving.append((own, label, sway, centre, reach))
            else:
                self._moving.append((own, label, walk, walk.centre, walk.reach + 0.05))
            return
        geometry_id = self._scene.add_triangles(mesh)
        assert geometry_id == len(self._labels)
        self._labels.append(label)

    def material_index(self, label: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For each label, its index in `materials` (in insertion order) and whether it has
        one."""
        if not self.materials:
            return np.zeros(label.shape, dtype=np.int64), np.zeros(label.shape, dtype=bool)
        keys = np.fromiter(self.materials, dtype=np.int64)
        order = np.argsort(keys)
        position = np.clip(np.searchsorted(keys[order], label), 0, len(keys) - 1)
        index = order[position]
        return index, keys[index] == label

    @property
    def moving(self) -> bool:
        return bool(self._moving)

    def cast(self, origins: np.ndarray, directions: np.ndarray, t_ns=None):
        """Distance along each unit ray (inf for a miss) and the label hit (-1 for none).
        `t_ns` (one time or one per ray, ns) places the swaying meshes; required if any."""
        import open3d as o3d

        rays = np.hstack([origins, directions]).astype(np.float32)
        hits = self._scene.cast_rays(o3d.core.Tensor(rays))
        distance = hits["t_hit"].numpy()
        geometry = hits["geometry_ids"].numpy().astype(np.int64)
        labels = np.asarray([*self._labels, -1])
        hit = np.isfinite(distance)
        label = np.where(hit, labels[np.where(hit, geometry, -1)], -1)
        if not self._moving:
            return distance, label
        if t_ns is None:
            raise ValueError("a scene with swaying meshes needs the rays' times (t_ns)")
        t_s = np.broadcast_to(np.asarray(t_ns, dtype=np.float64) / 1e9, (len(origins),))
        origins = np.asarray(origins, dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        for own, mesh_label, motion, centre, reach in self._moving:
            # Only the rays passing within reach of the mesh's axis (in x-y) can hit it.
            axis = np.asarray(centre) - origins[:, :2]
            flat = directions[:, :2]
            along = np.clip(
                (axis * flat).sum(axis=1) / np.maximum((flat * flat).sum(axis=1), 1e-12), 0, None
            )
            near = np.hypot(*(flat * along[:, None] - axis).T) < reach
            if not near.any():
                continue
            o, d = origins[near], directions[near]
            if hasattr(motion, "shear"):
                shear = motion.shear(t_s[near])  # (n, 2)
                o[:, :2] -= shear * (o[:, 2:3] - motion.base[2])
                d[:, :2] -= shear * d[:, 2:3]
            else:
                o -= motion.offset(t_s[near])
            rays = np.hstack([o, d]).astype(np.float32)
            t_hit = own.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
            closer = t_hit < distance[near]
            index = np.flatnonzero(near)[closer]
            distance[index] = t_hit[closer]
            label[index] = mesh_label
        return distance, label


class Vlp16Emulator:
    def __init__(
        self,
        scene: Scene,
        T_base_lidar: np.ndarray,
        settings: LidarSettings | None = None,
        rng: np.random.Generator | None = None,
    ):
        self.scene = scene
        self.T_base_lidar = np.asarray(T_base_lidar, dtype=float)
        self.settings = settings or LidarSettings()
        self.rng = rng or np.random.default_rng(0)
        optics = self.settings.optics
        laser = np.arange(m.RECORDS_PER_BLOCK) % m.LASERS
        self._elevation = np.deg2rad(np.asarray(optics.elevation_deg))[laser]
        self._vertical_offset = (np.asarray(optics.vertical_offset_mm) / 1000)[laser]
        sequence = np.arange(m.RECORDS_PER_BLOCK) // m.LASERS
        self._t_in_block = sequence * m.SEQUENCE_NS + laser * m.LASER_SLOT_NS

    def packets(
        self, trajectory: Trajectory, t_start: int, t_end: int, packets_per_batch: int = 76
    ) -> Iterator[tuple[int, bytes]]:
        """(UTC of the packet's first firing, payload) from t_start to t_end (ns). The
        payload's ToH is on the sensor's own clock (`device_time`). The caller stamps host
        receive times (e.g. + a small latency)."""
        period = m.PACKET_NS_SINGLE
        count = int((t_end - t_start) // period)
        for first in range(0, count, packets_per_batch):
            n = min(packets_per_batch, count - first)
            t_packet = t_start + (first + np.arange(n, dtype=np.int64)) * period
            payload = self._batch(trajectory, t_packet, self.device_time(t_packet, t_start))
            for i in range(n):
                yield (
                    int(t_packet[i]),
                    payload[i * m.DATA_PACKET_SIZE : (i + 1) * m.DATA_PACKET_SIZE],
                )

    def device_time(self, t: np.ndarray, t_start: int) -> np.ndarray:
        """The sensor's own clock (ns; its ToH is this past the hour) at UTC `t`: UTC when
        its GPS input is locked, else the time since power-on."""
        if self.settings.gps_sync:
            return t
        return t - t_start + round(self.settings.power_on_s * 1e9)

    def _rotor_angle(self, t: np.ndarray) -> np.ndarray:
        """Rotor azimuth (radians, clockwise from lidar +x) at device time t (ns)."""
        turns_per_ns = self.settings.rpm / 60.0 / 1e9
        return 2 * math.pi * ((t * turns_per_ns) % 1.0)

    def _batch(self, trajectory: Trajectory, t_packet: np.ndarray, t_device: np.ndarray) -> bytes:
        s = self.settings
        block_start = t_packet[:, None] + np.arange(m.BLOCKS_PER_PACKET) * m.BLOCK_NS  # (P,12)
        t_fire = block_start[:, :, None] + self._t_in_block  # (P, 12, 32)
        azimuth = self._rotor_angle(t_fire)
        elevation = np.broadcast_to(self._elevation, t_fire.shape)
        # Beam in the lidar frame (x forward, y left, z up; azimuth clockwise from x).
        direction = np.stack(
            [
                np.cos(elevation) * np.cos(azimuth),
                -np.cos(elevation) * np.sin(azimuth),
                np.sin(elevation),
            ],
            axis=-1,
        ).reshape(-1, 3)
        origin = np.zeros_like(direction)
        origin[:, 2] = np.broadcast_to(self._vertical_offset, t_fire.shape).reshape(-1)

        world_from_base = _poses(*trajectory(t_fire.reshape(-1)))  # (N, 4, 4)
        world_from_lidar = world_from_base @ self.T_base_lidar
        rotation, translation = world_from_lidar[:, :3, :3], world_from_lidar[:, :3, 3]
        origins = np.einsum("nij,nj->ni", rotation, origin) + translation
        directions = np.einsum("nij,nj->ni", rotation, direction)
        distance, label = self.scene.cast(origins, directions, t_fire.reshape(-1))

        distance = distance + self.rng.normal(0, s.range_sigma_m, distance.shape)
        keep = (
            np.isfinite(distance)
            & (distance >= s.min_range_m)
            & (distance <= s.max_range_m)
            & (self.rng.random(distance.shape) >= s.dropout)
        )
        units = np.where(keep, np.round(distance / m.DISTANCE_UNIT_M), 0).astype(np.uint16)
        ground, tree = s.reflectivity_by_label
        base = np.where(label == 0, ground, tree)
        index, found = self.scene.material_index(label)
        if found.any():
            own = np.array([mat.reflectivity for mat in self.scene.materials.values()])
            base = np.where(found, own[index], base)
        reflectivity = base + self.rng.integers(-3, 4, label.shape)
        reflectivity = np.where(keep, np.clip(reflectivity, 0, 100), 0).astype(np.uint8)

        block_azimuth = np.round(np.degrees(self._rotor_angle(block_start)) * 100).astype(int)
        return encode_packets(
            block_azimuth % 36000,
            units.reshape(t_fire.shape),
            reflectivity.reshape(t_fire.shape),
            (t_device // 1000) % (m.HOUR_NS // 1000),
        )


def _poses(x, y, z, yaw, pitch=None, roll=None) -> np.ndarray:
    """world_from_base (N, 4, 4) of R = Rz(yaw) Ry(pitch) Rx(roll) and (x, y, z)."""
    x = np.atleast_1d(np.asarray(x, dtype=float))
    out = np.zeros((len(x), 4, 4))
    out[:, 3, 3] = 1.0
    out[:, :3, :3] = rotation_matrices(yaw, pitch, roll, len(x))
    out[:, 0, 3], out[:, 1, 3], out[:, 2, 3] = x, y, z
    return out


def rotation_matrices(yaw, pitch=None, roll=None, n: int | None = None) -> np.ndarray:
    """(N, 3, 3) rotations Rz(yaw) Ry(pitch) Rx(roll); pitch and roll None = level."""
    yaw = np.atleast_1d(np.asarray(yaw, dtype=float))
    n = len(yaw) if n is None else n
    yaw = np.broadcast_to(yaw, (n,))
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.zeros((n, 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = c, -s, s, c
    out[:, 2, 2] = 1.0
    if pitch is None and roll is None:
        return out  # exactly the level rotation (the paper's flat twin)
    p = np.broadcast_to(np.asarray(0.0 if pitch is None else pitch, dtype=float), (n,))
    r = np.broadcast_to(np.asarray(0.0 if roll is None else roll, dtype=float), (n,))
    cp, sp, cr, sr = np.cos(p), np.sin(p), np.cos(r), np.sin(r)
    ry = np.zeros((n, 3, 3))
    ry[:, 0, 0], ry[:, 0, 2], ry[:, 1, 1], ry[:, 2, 0], ry[:, 2, 2] = cp, sp, 1, -sp, cp
    rx = np.zeros((n, 3, 3))
    rx[:, 0, 0], rx[:, 1, 1], rx[:, 1, 2], rx[:, 2, 1], rx[:, 2, 2] = 1, cr, -sr, sr, cr
    return out @ ry @ rx
