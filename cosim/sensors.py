"""Forward sensing: a lidar-like fan of rays in the car's frame (PyBullet batch raycasts).

:class:`Lidar` casts ``n_rays`` horizontal rays (in the chassis frame, so they pitch and roll
with the car) over ``±fov/2`` from the middle of the front bumper at ``height`` above the
road, ``range_m`` long, in one ``rayTestBatch``. The ego's own chassis is excluded through
its collision group (``cosim.vehicle.CHASSIS_COLLISION_GROUP``; the wheel links collide with
nothing). A :class:`LidarScan` gives per ray the distance (``range_m`` when nothing was hit),
the body id hit (-1 for none), the hit point, the surface normal, and on demand the height of
a hit above the surface under it (``LidarScan.heights``: a second batch of short vertical rays,
cast only for the rays asked about).

:func:`corridor_obstacle` keeps the hits that lie in the path corridor ahead (within half the
car's width plus a margin of the path's centreline) and are obstacles rather than the road
itself (a ray meets the road where the street rises ahead, or a kerb, or a seam of the road
mesh: such hits have a surface normal close to vertical or stand only centimetres above the
surface under them), and returns the nearest one as a gap along the path from the bumper.
The autopilot maps hit body ids to SUMO actors through ``ActorMirror.active``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as pb

from .vehicle import CHASSIS_COLLISION_GROUP, LENGTH, WIDTH


class LidarScan:
    """One scan (see the module doc). The height of a hit above the surface under it takes a
    second batch of vertical rays: cast on first use, only for the rays asked about
    (:meth:`heights`; ``corridor_obstacle`` asks for the few hits in the corridor). Ask in the
    frame of the scan: the rays are cast into the world as it is when asked."""

    def __init__(self, angles, distance, body, point, normal, origin, range_m, dirs=None, lidar=None):
        self.angles = angles            # rad, in the car frame (0 = straight ahead, + = left)
        self.distance = distance        # m from the origin (range when nothing was hit)
        self.body = body                # body id hit, -1 none
        self.point = point              # (n, 3) world hit points (ray ends for misses)
        self.normal = normal            # (n, 3) world surface normals (0 for misses)
        self.origin = origin            # (3,) the sensor's position
        self.range_m = range_m
        self._dirs, self._lidar = dirs, lidar
        self._height = np.full(len(distance), np.nan)
        self._asked = np.zeros(len(distance), dtype=bool)

    @property
    def hit(self) -> np.ndarray:
        return self.body >= 0

    def nearest(self) -> float:
        return float(self.distance.min()) if len(self.distance) else self.range_m

    def heights(self, idx) -> np.ndarray:
        """Heights (m) of the hits of rays ``idx`` above the surface under them (nan: no hit)."""
        idx = np.asarray(idx, dtype=int)
        new = idx[~self._asked[idx] & (self.body[idx] >= 0)]
        if len(new) and self._lidar is not None:
            new = np.unique(new)
            self._height[new] = self._lidar.heights_under(self.point[new], self._dirs[new])
        self._asked[idx] = True
        return self._height[idx]

    @property
    def height(self) -> np.ndarray:
        """(n,) m of each hit point above the surface under it (nan: no hit)."""
        self.heights(np.arange(len(self.distance)))
        return self._height


class Lidar:
    """A horizontal fan of rays from the front bumper (see the module doc)."""

    def __init__(self, client: int, n_rays: int = 41, fov_deg: float = 70.0, range_m: float = 70.0,
                 height: float = 0.5, mount_x: float | None = None, ignore_mask: int = CHASSIS_COLLISION_GROUP):
        if n_rays < 1:
            raise ValueError("a lidar needs at least one ray")
        self.client = client
        self.n = int(n_rays)
        self.range_m = float(range_m)
        self.height = float(height)
        self.mount_x = LENGTH / 2.0 + 0.05 if mount_x is None else float(mount_x)
        half = math.radians(fov_deg) / 2.0
        self.angles = np.linspace(-half, half, self.n) if self.n > 1 else np.zeros(1)
        self._dirs = np.column_stack([np.cos(self.angles), np.sin(self.angles), np.zeros(self.n)])
        self.mask = -1 ^ int(ignore_mask)

    def scan(self, x: float, y: float, z: float, roll: float, pitch: float, yaw: float) -> LidarScan:
        """Cast the fan from a car whose footprint centre on the ground is (x, y, z) with the
        given attitude (``cosim.vehicle.VehicleState`` fields)."""
        q = pb.getQuaternionFromEuler((roll, pitch, yaw))
        R = np.array(pb.getMatrixFromQuaternion(q)).reshape(3, 3)
        origin = np.array([x, y, z]) + R @ np.array([self.mount_x, 0.0, self.height])
        dirs = self._dirs @ R.T
        ends = origin[None, :] + self.range_m * dirs
        starts = np.repeat(origin[None, :], self.n, axis=0)
        res = pb.rayTestBatch(starts.tolist(), ends.tolist(), numThreads=1, collisionFilterMask=self.mask,
                              physicsClientId=self.client)
        # (the results' columns at once: a list per column cost twice as much)
        body, _, frac, point, normal = zip(*res)
        body = np.array(body, dtype=int)
        point, normal = np.array(point, dtype=float), np.array(normal, dtype=float)
        miss = body < 0
        frac = np.where(miss, 1.0, frac)
        if miss.any():
            point[miss] = ends[miss]
            normal[miss] = 0.0
        return LidarScan(self.angles, frac * self.range_m, body, point, normal, origin, self.range_m, dirs, self)

    def heights_under(self, points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        """Heights of hit ``points`` (rays along ``dirs``) above the surface under them: a
        vertical ray 3 m down from just in front of each (the road ahead rising into the fan is
        not an obstacle; a car is); 3.0 where it meets nothing."""
        top = points - 0.05 * dirs + np.array([0.0, 0.0, 0.05])
        bottom = top - np.array([0.0, 0.0, 3.0])
        down = pb.rayTestBatch(top.tolist(), bottom.tolist(), numThreads=1, collisionFilterMask=self.mask,
                               physicsClientId=self.client)
        return np.array([(p[2] - r[3][2]) if r[0] >= 0 else 3.0 for p, r in zip(points.tolist(), down)])

    def scan_vehicle(self, state) -> LidarScan:
        return self.scan(state.x, state.y, state.z, state.roll, state.pitch, state.yaw)


@dataclass
class CorridorHit:
    gap: float               # m along the path from the ego's front bumper to the hit
    s: float                 # arc length of the hit on the path
    offset: float            # lateral offset of the hit from the path's centreline
    body: int
    ray: int


def corridor_obstacle(scan: LidarScan, path, s_here: float, half_width: float = WIDTH / 2.0 + 0.35,
                      front: float = LENGTH / 2.0, ground_nz: float = 0.7, min_height: float = 0.25,
                      ignore_bodies=None) -> CorridorHit | None:
    """Nearest lidar hit inside the path corridor ahead, as a gap along the path from the
    bumper (``front`` m ahead of the car's centre at ``s_here``), or None.

    A hit counts when it projects onto the path ahead of the bumper, within ``half_width`` of
    the centreline, and is not the road itself: its surface normal is not near vertical (z
    below ``ground_nz``) and it stands at least ``min_height`` above the surface under it (a
    ray meeting a rising street, a kerb or a seam of the road mesh is not an obstacle)."""
    ok = scan.hit & (np.abs(scan.normal[:, 2]) < ground_nz)
    if ignore_bodies:
        ok &= ~np.isin(scan.body, list(ignore_bodies))
    idx = np.nonzero(ok)[0]
    if len(idx) == 0:
        return None
    s, off = path.project_many(scan.point[idx, 0], scan.point[idx, 1], s_here, s_here + scan.range_m + 5.0)
    good = np.isfinite(s) & (np.abs(off) <= half_width) & (s > s_here + front - 0.5)
    # a hit projected onto the end of the searched part is not on the path
    good &= s < min(path.length, s_here + scan.range_m + 5.0) - 0.25
    if not good.any():
        return None
    # (the heights of these few only: each takes a ray cast)
    g = np.flatnonzero(good)
    good[g[scan.heights(idx[g]) < min_height]] = False
    if not good.any():
        return None
    j = int(np.argmin(np.where(good, s, np.inf)))
    return CorridorHit(gap=max(0.0, float(s[j] - s_here - front)), s=float(s[j]), offset=float(off[j]),
                       body=int(scan.body[idx[j]]), ray=int(idx[j]))
