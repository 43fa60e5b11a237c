"""SUMO's actors mirrored into PyBullet as kinematic bodies of their real size.

Each vehicle or person near the ego becomes a static (mass 0) box of the actor's length,
width and height, moved every SUMO step with ``resetBasePositionAndOrientation``: centre from
SUMO's front bumper (done in ``cosim.traffic``), yaw converted from SUMO's heading, z on the
world's ground and pitch from the ground's slope along the heading. Static bodies cost the
physics step almost nothing (no dynamics; static-static pairs are not tested), so the ego
meets real obstacles while the step stays cheap, as SMARTS does with its kinematic traffic.

Bodies are pooled per size class: an actor leaving the radius parks its body far below the
world; a new actor of that size reuses it. No body is ever created twice for the same size,
so memory does not grow with the run (PyBullet does not free shapes on removeBody).
"""
from __future__ import annotations

import math

import numpy as np
import pybullet as pb

PARK_Z = -500.0
COLOURS = {"person": (0.85, 0.55, 0.20, 1), "bus": (0.9, 0.75, 0.1, 1), "truck": (0.55, 0.55, 0.6, 1),
           "default": (0.25, 0.40, 0.75, 1)}


def _size_key(kind, l, w, h):
    if kind == "person":
        return ("person", 0.5, 0.5, 1.75)
    return (kind if kind in ("bus", "truck") else "car", round(l * 2) / 2, round(w * 4) / 4, round(h * 4) / 4)


def _overlap(a, b, margin: float = 0.1) -> bool:
    """Do two oriented rectangles (x, y, yaw, length, width) overlap? Separating-axis test."""
    ax, ay, ayaw, al, aw = a
    bx, by, byaw, bl, bw = b
    dx, dy = bx - ax, by - ay
    if dx * dx + dy * dy > ((al + bl) * 0.5 + aw + bw) ** 2:
        return False
    axes = []
    for yaw in (ayaw, byaw):
        c, s = math.cos(yaw), math.sin(yaw)
        axes.append((c, s))
        axes.append((-s, c))
    for ux, uy in axes:
        def half(yaw, l, w):
            c, s = math.cos(yaw), math.sin(yaw)
            return 0.5 * l * abs(c * ux + s * uy) + 0.5 * w * abs(-s * ux + c * uy)
        if abs(dx * ux + dy * uy) > half(ayaw, al, aw) + half(byaw, bl, bw) + margin:
            return False
    return True


class ActorMirror:
    def __init__(self, client: int, world, visuals: bool = False):
        self.client = client
        self.world = world
        self.visuals = visuals
        self.active: dict = {}      # actor id -> (body, key)
        self.pool: dict = {}        # key -> [free bodies]
        self.shapes: dict = {}      # key -> (collision, visual)
        self.created = 0
        self.held = 0
        self.max_error_m = 0.0
        self._keys: dict = {}       # actor id -> size key
        self._last: dict = {}       # body -> last position set (a body standing still is not moved)

    def _body(self, key):
        free = self.pool.get(key)
        if free:
            return free.pop()
        cs_vs = self.shapes.get(key)
        c = self.client
        if cs_vs is None:
            _, l, w, h = key
            he = [l / 2, w / 2, h / 2]
            cs = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=he, physicsClientId=c)
            vs = -1
            if self.visuals:
                col = COLOURS.get(key[0], COLOURS["default"])
                vs = pb.createVisualShape(pb.GEOM_BOX, halfExtents=he, rgbaColor=col, physicsClientId=c)
            cs_vs = (cs, vs)
            self.shapes[key] = cs_vs
        self.created += 1
        return pb.createMultiBody(0, cs_vs[0], cs_vs[1], [0, 0, PARK_Z], useMaximalCoordinates=True,
                                 physicsClientId=c)

    def update(self, snap, ego=None) -> dict:
        """Mirror a traffic snapshot (cosim.traffic.ActorsSnapshot). Returns counts.

        `ego` = (x, y, yaw, length, width): an actor whose new pose would overlap the ego's
        footprint is held where it was (a kinematic body must never teleport into the
        physics car: SUMO does not always see the ego, e.g. while it crosses a junction)."""
        c = self.client
        n = len(snap)
        seen = set()
        held = 0
        if n:
            x, y, yaw = snap.x, snap.y, snap.yaw
            z = self.world.ground_z(x, y)
            z = np.where(np.isfinite(z), z, 0.0)
            pitch = self.world.slope_pitch(x, y, yaw)
            pitch = np.where(np.isfinite(pitch), pitch, np.radians(snap.slope))
            # size keys (box sizes rounded so that bodies can be pooled), computed once per actor
            keys = self._keys
            # quaternions of (roll 0, pitch -p, yaw) for all actors at once
            hy, hp = yaw * 0.5, -pitch * 0.5
            cy, sy, cp2, sp2 = np.cos(hy), np.sin(hy), np.cos(hp), np.sin(hp)
            quat = np.column_stack([-sp2 * sy, sp2 * cy, cp2 * sy, cp2 * cy]).tolist()
            cosp = np.cos(pitch)
            # only actors near the ego can overlap it (cheap distance test first)
            if ego is not None:
                reach = (ego[3] + ego[4]) * 0.5 + 0.5 * (snap.length + snap.width) + 0.5
                near = ((x - ego[0]) ** 2 + (y - ego[1]) ** 2 <= reach * reach).tolist()
            else:
                near = [False] * n
            xs, ys, zs, yaws = x.tolist(), y.tolist(), z.tolist(), yaw.tolist()
            ids, kinds = snap.ids, snap.kind
            for k in range(n):
                aid = ids[k]
                key = keys.get(aid)
                if key is None:
                    kind = "person" if kinds[k] == "person" else str(kinds[k])
                    key = keys[aid] = _size_key(kind, snap.length[k], snap.width[k], snap.height[k])
                cur = self.active.get(aid)
                if cur is None or cur[1] != key:
                    if cur is not None:
                        self._park(cur)
                    cur = (self._body(key), key)
                    self.active[aid] = cur
                seen.add(aid)
                if near[k] and _overlap(ego, (xs[k], ys[k], yaws[k], key[1], key[2])):
                    held += 1
                    continue
                pos = (xs[k], ys[k], zs[k] + key[3] * 0.5 * cosp[k])
                if self._last.get(cur[0]) == pos:      # standing still: nothing to move
                    continue
                self._last[cur[0]] = pos
                pb.resetBasePositionAndOrientation(cur[0], pos, quat[k], physicsClientId=c)
        gone = [a for a in self.active if a not in seen]
        for a in gone:
            self._park(self.active.pop(a))
            self._keys.pop(a, None)
        self.held += held
        return {"mirrored": len(self.active), "left": len(gone), "held": held}

    def _park(self, cur):
        body, key = cur
        self._last.pop(body, None)
        pb.resetBasePositionAndOrientation(body, [0, 0, PARK_Z - 10 * len(self.pool.get(key, []))], [0, 0, 0, 1],
                                           physicsClientId=self.client)
        self.pool.setdefault(key, []).append(body)

    def pose_error(self, snap) -> float:
        """Largest distance between a mirrored body and SUMO's centre for the same actor (m)."""
        worst = 0.0
        for k in range(len(snap)):
            cur = self.active.get(snap.ids[k])
            if cur is None:
                continue
            (x, y, _), _ = pb.getBasePositionAndOrientation(cur[0], physicsClientId=self.client)
            worst = max(worst, math.hypot(x - snap.x[k], y - snap.y[k]))
        self.max_error_m = max(self.max_error_m, worst)
        return worst

    def rekey(self, mapping: dict) -> None:
        """Actors carried across a SUMO network swap get new ids: keep their bodies."""
        for old, new in mapping.items():
            if old in self.active:
                self.active[new] = self.active.pop(old)
            if old in self._keys:
                self._keys[new] = self._keys.pop(old)

    def body_of(self, actor_id):
        cur = self.active.get(actor_id)
        return cur[0] if cur else None

    def counts(self):
        persons = sum(1 for _, (b, k) in self.active.items() if k[0] == "person")
        return len(self.active) - persons, persons
