"""SUMO's actors mirrored into PyBullet as kinematic bodies of their real size.

Each vehicle or person near the ego becomes a static (mass 0) box of the actor's length,
width and height, moved every SUMO step with ``resetBasePositionAndOrientation``: centre from
SUMO's front bumper (done in ``cosim.traffic``), yaw converted from SUMO's heading, z on the
world's ground and pitch from the ground's slope along the heading. Static bodies, asleep
(``cosim.physics.static_body``), cost the physics step almost nothing (no dynamics, no
notification; static-static pairs are not tested), so the ego
meets real obstacles while the step stays cheap, as SMARTS does with its kinematic traffic.

A long vehicle (a bus, a truck: longer than LONG_M) is a chain of boxes of at most SEGMENT_M
that follow the path its front bumper has taken, the way SUMO moves it: its back follows the
same lane, LENGTH behind the front. One rigid box along SUMO's front-to-back chord cuts the
inside of a bend by about L^2 / 8R (2.3 m for a 12 m bus through a 8 m radius turn): Monaco's
buses swept it over cars waiting at the stop line of the next lane. The chain's front is
SUMO's front bumper; an actor first seen starts from the straight chord.

Bodies are pooled per size class: an actor leaving the radius parks its body far below the
world; a new actor of that size reuses it. No body is ever created twice for the same size,
so memory does not grow with the run (PyBullet does not free shapes on removeBody).
"""
from __future__ import annotations

import math

import numpy as np
import pybullet as pb

from .physics import static_body
from .traffic import _boxes_overlap

PARK_Z = -500.0
LONG_M = 7.0          # vehicles longer than this are chains of boxes
SEGMENT_M = 4.0       # ... of at most this length
TRAIL_STEP_M = 1.0    # the front's path is kept as points this far apart (at least)
LEVEL_M = 4.0         # an actor standing this much higher or lower than the ego is on another level (a deck)
COLOURS = {"person": (0.85, 0.55, 0.20, 1), "bus": (0.9, 0.75, 0.1, 1), "truck": (0.55, 0.55, 0.6, 1),
           "default": (0.25, 0.40, 0.75, 1)}


def _size_key(kind, l, w, h):
    if kind == "person":
        return ("person", 0.5, 0.5, 1.75)
    return (kind if kind in ("bus", "truck") else "car", round(l * 2) / 2, round(w * 4) / 4, round(h * 4) / 4)


def _segments(length: float) -> int:
    """Boxes in the chain of a vehicle this long (1: one box)."""
    return 1 if length <= LONG_M else int(math.ceil(length / SEGMENT_M - 1e-9))


def _along_trail(trail: list, dists) -> list:
    """Points at arc distances `dists` (ascending) back from the trail's newest point (its last),
    going on straight beyond its oldest."""
    out = []
    k = len(trail) - 1
    px, py = trail[k]
    done = 0.0                     # arc length from the front to (px, py)
    for d in dists:
        while True:
            if k == 0:             # beyond the oldest point: straight on, along the last piece
                if len(trail) >= 2:
                    qx, qy = trail[0]
                    rx, ry = trail[1]
                    n = math.hypot(qx - rx, qy - ry) or 1.0
                    out.append((qx + (qx - rx) / n * (d - done), qy + (qy - ry) / n * (d - done)))
                else:
                    out.append((px, py))
                break
            qx, qy = trail[k - 1]
            seg = math.hypot(qx - px, qy - py)
            if done + seg >= d:
                t = (d - done) / seg if seg > 0 else 0.0
                out.append((px + (qx - px) * t, py + (qy - py) * t))
                break
            done += seg
            k -= 1
            px, py = qx, qy
    return out


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
        self.held_at: dict = {}     # actor id -> (x, y): where an actor held this frame stands
        self.raised: dict = {}      # actor id -> m: an actor on a bridge's deck, this high over the terrain
        self.max_error_m = 0.0
        self._keys: dict = {}       # actor id -> size key
        self._last: dict = {}       # body -> last position set (a body standing still is not moved)
        self.chains: dict = {}      # long vehicle id -> [(body, key)] of its boxes behind the first
        self._trails: dict = {}     # long vehicle id -> its front bumper's recent path [(x, y)], newest last
        self._chain_last: dict = {}  # long vehicle id -> (its front bumper, its boxes) last computed

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
        return static_body(c, cs_vs[0], cs_vs[1], (0, 0, PARK_Z))

    def update(self, snap, ego=None) -> dict:
        """Mirror a traffic snapshot (cosim.traffic.ActorsSnapshot). Returns counts.

        `ego` = (x, y, yaw, length, width[, z]): an actor whose new pose would overlap the
        ego's footprint is held where it was (a kinematic body must never teleport into the
        physics car: SUMO does not always see the ego, e.g. while it crosses a junction);
        given the ego's ground z, not one on another level (a bridge's deck over it, or the
        road under the deck it drives on). ``raised`` records the actors placed on a deck."""
        c = self.client
        n = len(snap)
        seen = set()
        held = 0
        self.held_at = {}
        raised = self.raised = {}
        ids_ = snap.ids
        ego_z = ego[5] if ego is not None and len(ego) > 5 else None
        if n:
            x, y, yaw = snap.x, snap.y, snap.yaw
            kinds = snap.kind
            # long vehicles' chains of boxes: their ground looked up with the others' (one call)
            long_ = np.flatnonzero((snap.length > LONG_M) & (kinds != "person")).tolist()
            boxes, where = self._chain_boxes(snap, long_) if long_ else ([], [])
            slope = np.radians(snap.slope)
            if boxes:
                B = np.array(boxes)
                X, Y, YAW = (np.concatenate((a, B[:, j])) for j, a in enumerate((x, y, yaw)))
                slope = np.concatenate((slope, slope[where]))
            else:
                X, Y, YAW = x, y, yaw
            z, pitch = self.world.ground_z_and_pitch(X, Y, YAW)
            z = np.where(np.isfinite(z), z, 0.0)
            lanes = getattr(snap, "lane", None)
            deck = None                 # indices (into X, Y) of the actors and boxes put on a deck
            if lanes is not None:
                # on a bridge: on its deck, not on the terrain under it (Monaco, seed 13: a car
                # on Boulevard du Larvotto's bridge, mirrored 5 m down, drove through the car
                # standing on the avenue beneath)
                bridges = self.world.bridge_lanes()
                if bridges:
                    actor_of = np.concatenate((np.arange(n), np.asarray(where, dtype=int))) if boxes else np.arange(n)
                    on = np.flatnonzero([lanes[a] in bridges for a in actor_of.tolist()])
                    if len(on):
                        top = self.world.road_top_z(X[on], Y[on])
                        up = np.isfinite(top) & (top > z[on] + 0.5)
                        for a, dz in zip(on[up].tolist(), (top[up] - z[on[up]]).tolist()):
                            if a < n:
                                raised[ids_[a]] = dz
                        z[on[up]] = top[up]
                        deck = on[up]
            pitch = np.where(np.isfinite(pitch), pitch, slope)
            if deck is not None and len(deck):
                # (on a deck: pitched as the deck is, 2.5 m ahead and behind, not as the
                # terrain under it: a car on a Portland ramp's deck stood 22 degrees nose up)
                cd, sd = 2.5 * np.cos(YAW[deck]), 2.5 * np.sin(YAW[deck])
                zfb = self.world.road_top_z(np.concatenate((X[deck] + cd, X[deck] - cd)),
                                            np.concatenate((Y[deck] + sd, Y[deck] - sd)), r=2.0)
                p_deck = np.arctan2(zfb[:len(deck)] - zfb[len(deck):], 5.0)
                pitch[deck] = np.where(np.isfinite(p_deck), p_deck, 0.0)
            # quaternions of (roll 0, pitch -p, yaw) for all actors (and boxes) at once
            hy, hp = YAW * 0.5, -pitch * 0.5
            cy, sy, cp2, sp2 = np.cos(hy), np.sin(hy), np.cos(hp), np.sin(hp)
            quat = np.column_stack([-sp2 * sy, sp2 * cy, cp2 * sy, cp2 * cy]).tolist()
            cosp = np.cos(pitch)
            chain_at: dict = {}
            if boxes:
                zl, cl = z[n:].tolist(), cosp[n:].tolist()
                for i, k in enumerate(where):
                    chain_at.setdefault(k, []).append(boxes[i] + (zl[i], cl[i], quat[n + i]))
            if ego is not None:
                for k, bx in chain_at.items():
                    if any(_boxes_overlap(ego[:5], b[:5], margin=0.1) and (ego_z is None or abs(b[5] - ego_z) < LEVEL_M)
                           for b in bx):
                        chain_at[k] = None          # held where it was
            z, cosp = z[:n], cosp[:n]
            # size keys (box sizes rounded so that bodies can be pooled), computed once per actor
            keys = self._keys
            # only actors near the ego can overlap it (cheap distance test first)
            if ego is not None:
                reach = (ego[3] + ego[4]) * 0.5 + 0.5 * (snap.length + snap.width) + 0.5
                near = ((x - ego[0]) ** 2 + (y - ego[1]) ** 2 <= reach * reach).tolist()
            else:
                near = [False] * n
            xs, ys, zs, yaws, cps = x.tolist(), y.tolist(), z.tolist(), yaw.tolist(), cosp.tolist()
            ids = snap.ids.tolist()
            for k in range(n):
                aid = ids[k]
                key = keys.get(aid)
                if key is None:
                    kind = "person" if kinds[k] == "person" else str(kinds[k])
                    key = keys[aid] = _size_key(kind, snap.length[k], snap.width[k], snap.height[k])
                    if k in chain_at:          # (the size of one box of its chain)
                        L = float(snap.length[k])
                        key = keys[aid] = (key[0], round(L / _segments(L), 2), key[2], key[3])
                cur = self.active.get(aid)
                if cur is None or cur[1] != key:
                    if cur is not None:
                        self._park(cur)
                    cur = (self._body(key), key)
                    self.active[aid] = cur
                seen.add(aid)
                if k in chain_at:
                    held += self._place_chain(aid, cur, key, chain_at[k])
                    continue
                if near[k] and _boxes_overlap(ego[:5], (xs[k], ys[k], yaws[k], key[1], key[2]), margin=0.1) \
                        and (ego_z is None or abs(zs[k] - ego_z) < LEVEL_M):
                    held += 1
                    last = self._last.get(cur[0])
                    if last is not None:
                        self.held_at[aid] = (last[0], last[1])
                    continue
                pos = (xs[k], ys[k], zs[k] + key[3] * 0.5 * cps[k])
                if self._last.get(cur[0]) == pos:      # standing still: nothing to move
                    continue
                self._last[cur[0]] = pos
                pb.resetBasePositionAndOrientation(cur[0], pos, quat[k], physicsClientId=c)
        gone = [a for a in self.active if a not in seen]
        for a in gone:
            self._park(self.active.pop(a))
            self._keys.pop(a, None)
            for cur in self.chains.pop(a, []):
                self._park(cur)
            self._trails.pop(a, None)
            self._chain_last.pop(a, None)
        self.held += held
        return {"mirrored": len(self.active), "left": len(gone), "held": held}

    def as_placed(self, snap):
        """`snap` (the snapshot just mirrored) with each actor held outside the ego (see
        :meth:`update`) where its body stands, not moving: what the car has in its way. (A
        Helsinki pedestrian, walking on a guessed walking area that overlaps a car lane, went
        through the standing car in SUMO; its body stood at the car's front bumper until it
        came out behind, and the car, seeing SUMO's pedestrian beside it, drove off into the
        body.)"""
        if not self.held_at:
            return snap
        idx = [k for k, a in enumerate(snap.ids.tolist()) if a in self.held_at]
        if not idx:
            return snap
        out = snap.subset(np.ones(len(snap), dtype=bool))      # (a copy of the arrays)
        for k in idx:
            out.x[k], out.y[k] = self.held_at[snap.ids[k]]
            out.speed[k] = 0.0
        return out

    def _chain_boxes(self, snap, long_) -> tuple:
        """For the long vehicles (indices `long_`): their boxes (x, y, yaw, length, width),
        front first, from each one's trail (updated here), and the vehicle's index for each."""
        boxes, where = [], []
        for k in long_:
            aid = snap.ids[k]
            L, yaw = float(snap.length[k]), float(snap.yaw[k])
            c, s_ = math.cos(yaw), math.sin(yaw)
            fx, fy = float(snap.x[k]) + 0.5 * L * c, float(snap.y[k]) + 0.5 * L * s_
            last = self._chain_last.get(aid)
            if last is not None and last[0] == (fx, fy):     # standing: the same boxes
                boxes += last[1]
                where += [k] * len(last[1])
                continue
            trail = self._trails.get(aid)
            if trail is None:          # first seen: the straight chord behind the front
                trail = self._trails[aid] = [(fx - L * c, fy - L * s_), (fx, fy)]
            else:
                lx, ly = trail[-1]
                px, py = trail[-2]
                if math.hypot(fx - lx, fy - ly) > 3.0 * L:    # a jump (teleported): start anew
                    trail[:] = [(fx - L * c, fy - L * s_), (fx, fy)]
                elif len(trail) > 2 and math.hypot(fx - px, fy - py) < TRAIL_STEP_M:
                    trail[-1] = (fx, fy)       # (near the point before: the newest moves on)
                else:
                    trail.append((fx, fy))
            n = _segments(L)
            seg = L / n
            pts = _along_trail(trail, [i * seg for i in range(n + 1)])
            # drop what lies beyond the tail (keep one point past it)
            tot, keep = 0.0, len(trail) - 1
            while keep > 0 and tot < L + 1.0:
                tot += math.hypot(trail[keep][0] - trail[keep - 1][0], trail[keep][1] - trail[keep - 1][1])
                keep -= 1
            if keep > 0:
                del trail[:keep]
            mine = []
            for i in range(n):
                # (the box's front on the path: the first one's is SUMO's front bumper)
                (ax, ay), (bx, by) = pts[i], pts[i + 1]
                yb = math.atan2(ay - by, ax - bx)
                mine.append((ax - 0.5 * seg * math.cos(yb), ay - 0.5 * seg * math.sin(yb), yb, seg,
                             float(snap.width[k])))
            self._chain_last[aid] = ((fx, fy), mine)
            boxes += mine
            where += [k] * n
        return boxes, where

    def _place_chain(self, aid, cur, key, boxes) -> int:
        """Move a long vehicle's boxes (`cur`: its first, already its own); 1 if held."""
        if boxes is None:
            return 1
        chain = self.chains.setdefault(aid, [])
        while len(chain) < len(boxes) - 1:
            chain.append((self._body(key), key))
        while len(chain) > len(boxes) - 1:
            self._park(chain.pop())
        c = self.client
        for (body, _), (x, y, _yaw, _l, _w, z, cosp, quat) in zip([cur] + chain, boxes):
            pos = (x, y, z + key[3] * 0.5 * cosp)
            if self._last.get(body) == pos:
                continue
            self._last[body] = pos
            pb.resetBasePositionAndOrientation(body, pos, quat, physicsClientId=c)
        return 0

    def chain_boxes(self, aid) -> list | None:
        """A long vehicle's boxes (x, y, yaw, length, width), front first, as last mirrored: in
        a turn its body is this bent chain, not the straight box of its snapshot; None for
        another actor."""
        got = self._chain_last.get(aid)
        return got[1] if got is not None else None

    def body_actors(self) -> dict:
        """Body id -> actor id, for every mirrored body (a long vehicle's boxes all map to it)."""
        out = {b: a for a, (b, _) in self.active.items()}
        for a, chain in self.chains.items():
            for b, _ in chain:
                out[b] = a
        return out

    def _park(self, cur):
        body, key = cur
        self._last.pop(body, None)
        pb.resetBasePositionAndOrientation(body, [0, 0, PARK_Z - 10 * len(self.pool.get(key, []))], [0, 0, 0, 1],
                                           physicsClientId=self.client)
        self.pool.setdefault(key, []).append(body)

    def pose_error(self, snap) -> float:
        """Largest distance between a mirrored body and SUMO's centre for the same actor (m);
        for a long vehicle, between its chain's front and SUMO's front bumper."""
        worst = 0.0
        for k in range(len(snap)):
            aid = snap.ids[k]
            cur = self.active.get(aid)
            if cur is None:
                continue
            (x, y, _), q = pb.getBasePositionAndOrientation(cur[0], physicsClientId=self.client)
            if aid in self._chain_last:
                yaw = pb.getEulerFromQuaternion(q)[2]
                half = 0.5 * cur[1][1]
                L = float(snap.length[k])
                x, y = x + half * math.cos(yaw), y + half * math.sin(yaw)
                fx = snap.x[k] + 0.5 * L * math.cos(snap.yaw[k])
                fy = snap.y[k] + 0.5 * L * math.sin(snap.yaw[k])
                worst = max(worst, math.hypot(x - fx, y - fy))
                continue
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
            for d in (self.chains, self._trails, self._chain_last):
                if old in d:
                    d[new] = d.pop(old)

    def body_of(self, actor_id):
        cur = self.active.get(actor_id)
        return cur[0] if cur else None

    def counts(self):
        persons = sum(1 for _, (b, k) in self.active.items() if k[0] == "person")
        return len(self.active) - persons, persons
