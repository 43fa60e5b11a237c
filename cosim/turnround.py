"""Turning round where the route turns back: a multi-point turn inside the carriageway.

A route the car has no other way on for (a dead end, a pocket of streets whose every way out
is closed to cars: Lauf's Krummleitenweg and the streets off it) turns back on itself, with
a U-turn link SUMO draws as a loop of 3-4 m radius. The car turns no tighter than 4.6 m (its
rear axle at full lock) and ran 6 m wide of that loop, off the road and into what stood there.
A driver turns round in a few moves instead: forward at full lock across the road, back at
the other lock, forward again, until the car faces the other way. :class:`TurnRound` does
that: each move goes, slowing, until the car's footprint would come within
:data:`STOP_ROOM_M` of leaving the carriageway (the approach lane and the lane it turns back
into, as SUMO draws them, less :data:`EDGE_MARGIN_M`) or of the lane's end ahead; it waits
while an actor stands in the way of the move, ends where the car is held still; it is done
when the car heads within :data:`DONE_DEG` of the way back. :func:`moves_needed` runs the same
moves on the car's kinematics first, so that a road too narrow for them (on SUMO's default
6.4 m of carriageway the car needs 9 moves, on 6 m none suffice) is known before the car
starts, and :func:`surface_step` finds a step across the carriageway that the wheels would not
climb.

The frame: ``C``, the approach lane's centreline (the lane path up to the stop line), along
which a point has its arc length ``s`` and its signed offset ``d`` (left positive). The
carriageway lies between ``right`` and ``left`` in ``d``; the turn goes towards the far lane
(``side``: +1 where it lies to the left, as in right-hand traffic).
"""
from __future__ import annotations

import math

import numpy as np

#: m/s of each move forward and back
MOVE_SPEED = 1.2
#: m the footprint keeps inside the carriageway's edges and the lane's end
EDGE_MARGIN_M = 0.2
#: the turn is done when the car heads within this of the way back (deg)
DONE_DEG = 25.0
#: give up after this many moves
MAX_MOVES = 15
#: m of lane the car stops short of the turn's stop line (front bumper), room for the first move
ROOM_AHEAD_M = 4.0
#: deceleration (m/s2) a move ends with
STOP_DECEL = 1.5
#: a move ends this far (m) short of where the footprint would reach an edge
STOP_ROOM_M = 0.1
#: m looked ahead along a move for its room, in steps of
ROOM_LOOK_M = 4.0
ROOM_STEP_M = 0.1
#: a step in the carriageway's surface higher than this (m, between points SURFACE_SPACING_M
#: apart, within SURFACE_REACH_M along it of the car) leaves no room to turn round
SURFACE_STEP_MAX_M = 0.15
SURFACE_SPACING_M = 0.3
SURFACE_REACH_M = 8.0
#: a move held still this long (s) ends there
STALL_S = 2.0
#: an actor within this of the footprint the next move sweeps holds the move (m)
ACTOR_CLEAR_M = 1.0
#: the steering is at its lock within this (rad) before a move starts
STEER_TOL = 0.05


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def footprint(x: float, y: float, yaw: float, half_l: float, half_w: float) -> np.ndarray:
    """The four corners (4, 2) of a box centred at (x, y) heading ``yaw``."""
    c, s = math.cos(yaw), math.sin(yaw)
    a = np.array([half_l, half_l, -half_l, -half_l])
    b = np.array([half_w, -half_w, half_w, -half_w])
    return np.column_stack([x + c * a - s * b, y + s * a + c * b])


def arc_pose(x: float, y: float, yaw: float, dist: float, curvature: float, rear: float) -> tuple:
    """The pose (x, y, yaw) of a car's reference point after its rear axle (``rear`` m along
    the heading from that point, negative behind) travels ``dist`` m (negative: backwards) on a
    circle of ``curvature`` (1/m, left positive)."""
    rx, ry = x + rear * math.cos(yaw), y + rear * math.sin(yaw)
    dth = dist * curvature
    if abs(dth) < 1e-9:
        rx, ry = rx + dist * math.cos(yaw), ry + dist * math.sin(yaw)
    else:
        r = 1.0 / curvature
        rx += r * (math.sin(yaw + dth) - math.sin(yaw))
        ry -= r * (math.cos(yaw + dth) - math.cos(yaw))
    yaw2 = yaw + dth
    return rx - rear * math.cos(yaw2), ry - rear * math.sin(yaw2), yaw2


class Frame:
    """Arc length and signed offset (left positive) of points along a polyline ``C``."""

    def __init__(self, C: np.ndarray):
        C = np.asarray(C, dtype=float)[:, :2]
        keep = np.ones(len(C), dtype=bool)
        keep[1:] = np.hypot(*np.diff(C, axis=0).T) > 1e-6
        self.C = C[keep]
        if len(self.C) < 2:
            raise ValueError("a frame needs a polyline of two points or more")
        self.a = self.C[:-1]
        self.u = np.diff(self.C, axis=0)
        self.len = np.hypot(self.u[:, 0], self.u[:, 1])
        self.u = self.u / self.len[:, None]
        self.s0 = np.concatenate([[0.0], np.cumsum(self.len)])[:-1]
        self.length = float(self.s0[-1] + self.len[-1])

    def sd(self, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s, d) of points ``P`` (n, 2): the nearest segment's (its ends extended at the
        polyline's ends)."""
        P = np.asarray(P, dtype=float).reshape(-1, 2)
        rel = P[:, None, :] - self.a[None, :, :]                         # (n, m, 2)
        t = np.einsum("nmk,mk->nm", rel, self.u)
        lo = np.where(np.arange(len(self.a)) == 0, -np.inf, 0.0)         # the first segment reaches back
        hi = np.where(np.arange(len(self.a)) == len(self.a) - 1, np.inf, self.len)
        tc = np.clip(t, lo[None, :], hi[None, :])
        foot = self.a[None, :, :] + tc[..., None] * self.u[None, :, :]
        dist = np.hypot(*(P[:, None, :] - foot).transpose(2, 0, 1))
        j = np.argmin(dist, axis=1)
        k = np.arange(len(P))
        s = self.s0[j] + tc[k, j]
        d = self.u[j, 0] * rel[k, j, 1] - self.u[j, 1] * rel[k, j, 0]
        return s, d

    def xy(self, s: np.ndarray, d: np.ndarray) -> np.ndarray:
        """The points (n, 2) at arc lengths ``s`` and offsets ``d`` (left positive)."""
        s = np.asarray(s, dtype=float)
        j = np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.u) - 1)
        t = s - self.s0[j]
        u = self.u[j]
        return self.a[j] + t[:, None] * u + np.asarray(d, dtype=float)[:, None] * np.column_stack([-u[:, 1], u[:, 0]])

    def heading_at(self, s: float) -> float:
        j = int(np.clip(np.searchsorted(self.s0, s, side="right") - 1, 0, len(self.u) - 1))
        return math.atan2(self.u[j, 1], self.u[j, 0])


class Carriageway:
    """Where the car may turn round: between offsets ``right`` and ``left`` of :class:`Frame`
    ``frame`` (the approach lane's centreline), up to arc length ``s_max`` (the approach lane's
    end); ``side`` +1 where the far lane lies to the left, ``d_far`` that lane's centre."""

    def __init__(self, frame: Frame, right: float, left: float, s_max: float, side: int, d_far: float):
        self.frame, self.right, self.left, self.s_max = frame, right, left, s_max
        self.side, self.d_far = side, d_far

    @classmethod
    def between(cls, C: np.ndarray, own_width: float, far_shape: np.ndarray, far_width: float,
                near_s: float) -> "Carriageway":
        """The approach lane (centreline ``C``, ending at the stop line) and the lane the
        route turns back into (``far_shape``), the latter's offset taken around arc length
        ``near_s`` (where the car turns)."""
        frame = Frame(C)
        F = np.asarray(far_shape, dtype=float)[:, :2]
        s, d = frame.sd(F)
        near = np.abs(s - near_s) <= 15.0
        d_far = float(np.median(d[near] if near.any() else d))
        side = 1 if d_far >= 0 else -1
        lo = min(-own_width / 2.0, d_far - far_width / 2.0)
        hi = max(own_width / 2.0, d_far + far_width / 2.0)
        return cls(frame, lo, hi, frame.length, side, d_far)

    def violation(self, P: np.ndarray) -> float:
        """How far (m) corners ``P`` reach past the carriageway's edges or the lane's end,
        margins included; <= 0 inside."""
        s, d = self.frame.sd(P)
        return float(max(np.max(d - (self.left - EDGE_MARGIN_M)), np.max((self.right + EDGE_MARGIN_M) - d),
                         np.max(s - (self.s_max - EDGE_MARGIN_M))))


def _is_done(cw: Carriageway, x: float, y: float, yaw: float) -> bool:
    """The car heads within DONE_DEG of the way back (wherever it stands across the road: the
    lane path takes it over to the far lane from there, turning away from the near edge)."""
    s, _ = cw.frame.sd(np.array([[x, y]]))
    back = cw.frame.heading_at(float(s[0])) + math.pi
    return abs(_wrap(yaw - back)) <= math.radians(DONE_DEG)


def surface_step(cw: Carriageway, x: float, y: float, heights, reach: float = SURFACE_REACH_M,
                 spacing: float = SURFACE_SPACING_M) -> float:
    """The largest height step (m) between neighbouring points of a grid ``spacing`` apart over
    the carriageway within ``reach`` along it of (x, y), its edges kept 0.1 m off; ``heights``
    maps points (n, 2) to the surface's heights there (NaN where unknown: left out). A road whose
    two directions lie at different heights (0.5 m apart on a steep street: Monaco's Impasse
    de la Fontaine) has no room to turn round: the car ran into the step and stood."""
    s0 = float(cw.frame.sd(np.array([[x, y]]))[0][0])
    ss = np.arange(max(0.0, s0 - reach), min(cw.s_max, s0 + reach) + 1e-9, spacing)
    dd = np.arange(cw.right + 0.1, cw.left - 0.1 + 1e-9, spacing)
    if len(ss) < 2 or len(dd) < 2:
        return 0.0
    S, Dd = np.meshgrid(ss, dd, indexing="ij")
    z = np.asarray(heights(cw.frame.xy(S.ravel(), Dd.ravel())), dtype=float).reshape(S.shape)
    steps = [np.abs(np.diff(z, axis=0)), np.abs(np.diff(z, axis=1))]
    return float(max((np.nanmax(a) if np.isfinite(a).any() else 0.0) for a in steps))


def room_along(cw: Carriageway, x: float, y: float, yaw: float, forward: bool, curvature: float,
               half_l: float, half_w: float, rear: float, step: float = ROOM_STEP_M) -> float:
    """How far (m, up to :data:`ROOM_LOOK_M`) a car at pose (x, y, yaw) can move (``forward``
    or back) on a circle of ``curvature`` before its footprint reaches past the carriageway's
    edges, margins included (or reaches further past them, where it is past already)."""
    v0 = cw.violation(footprint(x, y, yaw, half_l, half_w))
    dist = 0.0
    while dist < ROOM_LOOK_M:
        x2, y2, yaw2 = arc_pose(x, y, yaw, step if forward else -step, curvature, rear)
        v1 = cw.violation(footprint(x2, y2, yaw2, half_l, half_w))
        if v1 > 0.0 and v1 > v0:
            return dist
        x, y, yaw, v0 = x2, y2, yaw2, v1
        dist += step
    return dist


def moves_needed(cw: Carriageway, x: float, y: float, yaw: float, half_l: float, half_w: float,
                 radius: float, rear: float, step: float = 0.05) -> int | None:
    """How many moves the car needs to turn round in ``cw`` from pose (x, y, yaw), on its
    kinematics (rear axle on circles of ``radius`` at full lock), each move as far as its room
    (:func:`room_along`) less twice :data:`STOP_ROOM_M` (where the car stops, and as much
    again); None where it cannot."""
    for move in range(MAX_MOVES):
        forward = move % 2 == 0
        curv = cw.side * (1.0 if forward else -1.0) / radius
        go = room_along(cw, x, y, yaw, forward, curv, half_l, half_w, rear) - 2.0 * STOP_ROOM_M
        if go < 0.1:
            return None
        for d in np.arange(step, go + 1e-9, step):
            pose = arc_pose(x, y, yaw, d if forward else -d, curv, rear)
            if _is_done(cw, *pose):
                return move + 1
        x, y, yaw = arc_pose(x, y, yaw, go if forward else -go, curv, rear)
    return None


class _Moves:
    """What :class:`TurnRound` and :class:`BackOff` share: a move begins once the car stands
    braked with its wheels at the move's lock (:meth:`_ready`), and counts how far it has gone
    and how long it has been held still (:meth:`_advance`)."""

    def _ready(self, st, steer: float) -> bool:
        """The wheels at ``steer``'s lock (1.7 s from lock to lock) and the car still: the move
        starts (phase ``go``)."""
        if abs(st.steer - steer * self.max_steer) <= STEER_TOL and abs(float(st.speed)) < 0.1:
            self.phase, self.moved, self.last_xy, self.stalled_s = "go", 0.0, (st.x, st.y), 0.0
            self.speed.reset()
            return True
        return False

    def _advance(self, st, dt: float) -> None:
        """The move's distance so far, and how long the car has been held where it stands (a
        step in the road's surface the wheels do not climb at this speed, an actor waited for):
        the move ends after STALL_S of it."""
        step = math.hypot(st.x - self.last_xy[0], st.y - self.last_xy[1])
        self.moved += step
        self.last_xy = (st.x, st.y)
        self.stalled_s = self.stalled_s + dt if step < 0.002 else 0.0


class TurnRound(_Moves):
    """The moves (module doc) from the car standing in carriageway ``cw``: :meth:`control`
    gives the pedals, steering and gear each frame until ``done`` (or ``failed``)."""

    def __init__(self, cw: Carriageway, half_l: float, half_w: float, radius: float, rear: float,
                 max_steer: float, to_lane: str, from_lane: str):
        from .driving import SpeedController

        self.cw = cw
        self.half_l, self.half_w, self.radius, self.rear = half_l, half_w, radius, rear
        self.max_steer = max_steer            # effective road-wheel angle at full lock (rad)
        self.to_lane, self.from_lane = to_lane, from_lane
        self.speed = SpeedController()
        self.move = 0
        self.phase = "steer"                  # steer (wheels to the lock, braked) / go / stop
        self.moved = 0.0
        self.last_xy = None
        self.done = self.failed = False
        self.finishing = False                # heading the way back: braking to a stop, then done
        self.stalled_s = 0.0                  # s the car has stood still in this move
        self.waiting = False

    def _forward(self) -> bool:
        return self.move % 2 == 0

    def _steer_cmd(self) -> float:
        return float(self.cw.side) * (1.0 if self._forward() else -1.0)

    def room(self, x: float, y: float, yaw: float) -> float:
        """How far (m) this move can go on at full lock from pose (x, y, yaw) before the car's
        footprint reaches an edge of the carriageway (or further past it), up to ROOM_LOOK_M."""
        return room_along(self.cw, x, y, yaw, self._forward(), self._steer_cmd() / self.radius,
                          self.half_l, self.half_w, self.rear)

    def _blocked(self, st, actors, ahead_m: float) -> bool:
        """An actor within ACTOR_CLEAR_M of the footprint along the next ``ahead_m`` of the move."""
        if actors is None or not len(actors):
            return False
        fwd = self._forward()
        curv = self._steer_cmd() / self.radius
        pts = []
        for dist in np.linspace(0.0, ahead_m, 4):
            x, y, yaw = arc_pose(st.x, st.y, st.yaw, dist if fwd else -dist, curv, self.rear)
            pts.append(footprint(x, y, yaw, self.half_l, self.half_w))
        P = np.vstack(pts)
        ax, ay = np.asarray(actors.x, dtype=float), np.asarray(actors.y, dtype=float)
        r = np.maximum(np.asarray(actors.length, dtype=float), np.asarray(actors.width, dtype=float)) / 2.0
        cx, cy = st.x, st.y
        near = np.hypot(ax - cx, ay - cy) < 2 * self.half_l + ahead_m + r + 3.0
        if not near.any():
            return False
        d = np.min(np.hypot(ax[near, None] - P[None, :, 0], ay[near, None] - P[None, :, 1]), axis=1)
        return bool(np.any(d < r[near] + ACTOR_CLEAR_M))

    def control(self, st, dt: float, actors=None) -> tuple[float, float, float, bool]:
        """(throttle, brake, steer, reverse) for this frame."""
        fwd = self._forward()
        steer, rev = self._steer_cmd(), not fwd
        self.waiting = False
        v = float(st.speed)
        if self.phase == "steer":
            self._ready(st, steer)
            return 0.0, 1.0, steer, rev
        if self.phase == "go":
            self._advance(st, dt)
            if self.stalled_s >= STALL_S:
                self.phase = "stop"
                return 0.0, 1.0, steer, rev
            if _is_done(self.cw, st.x, st.y, st.yaw):
                self.phase, self.finishing = "stop", True
                return 0.0, 1.0, steer, rev
            speed = abs(v)
            room = self.room(st.x, st.y, st.yaw)
            if room <= STOP_ROOM_M or self.moved > 4.0 * self.radius:
                self.phase = "stop"
            elif self._blocked(st, actors, speed * speed / (2.0 * STOP_DECEL) + 1.0):
                self.waiting = True
                return 0.0, 1.0, steer, rev
            else:
                # slowing so as to stop STOP_ROOM_M short of the edge
                target = min(MOVE_SPEED, math.sqrt(2.0 * STOP_DECEL * 0.5 * max(room - STOP_ROOM_M, 0.0)))
                pitch = float(getattr(st, "pitch", 0.0))
                th, br = self.speed.control(max(target, 0.3), speed, dt, pitch=pitch if fwd else -pitch)
                return th, br, steer, rev
        # stop: braked to a standstill, then the next move
        if abs(v) < 0.05:
            if self.finishing:
                self.done = True
            elif self.moved < 0.1:
                self.failed = True          # a move that cannot start: no room left
            else:
                self.move += 1
                self.phase = "steer"
                if self.move >= MAX_MOVES:
                    self.failed = True
        return 0.0, 1.0, steer, rev


#: m a car held still against something backs off before it drives on (:class:`BackOff`)
BACKOFF_M = 2.5
#: m the move back and round keeps off an actor's box
BACKOFF_CLEAR_M = 0.5
#: m the move forward at full lock after it goes at most ...
BACKOFF_FORWARD_M = 6.0
#: ... ending where the car heads within this of the way on (deg)
BACKOFF_DONE_DEG = 15.0


def _corners_near(P: np.ndarray, x: float, y: float, yaw: float, half_l: float, half_w: float, d: float) -> bool:
    """Whether any of the points ``P`` (n, 2) lies within ``d`` of the box centred at (x, y)
    heading ``yaw`` (or in it)."""
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = P[:, 0] - x, P[:, 1] - y
    u, w = np.abs(dx * c + dy * s) - half_l, np.abs(-dx * s + dy * c) - half_w
    return bool(np.min(np.hypot(np.maximum(u, 0.0), np.maximum(w, 0.0))) < d)


class BackOff(_Moves):
    """Two moves from where the car is held still against something it drives into (a wall it
    takes a bend too wide for, a step it does not climb): back at full lock against the way the
    path turns (``side``: +1 where it turns left, 0 straight on), then forward at full lock the
    way it turns, until the car heads within :data:`BACKOFF_DONE_DEG` of the way on
    (``way_on``, rad): a driver's move back and round at a tight corner. Each move goes at
    :data:`MOVE_SPEED`, the one back up to :data:`BACKOFF_M`, the one forward up to
    :data:`BACKOFF_FORWARD_M`; either ends sooner where the car is held still
    (:data:`STALL_S`, an actor in its way waited for as long) or before a wall. The car stands
    braked while its wheels turn to each move's lock. Straight on (``side`` 0) there is only
    the move back. :meth:`control` gives the pedals, steering and gear each frame until
    ``done``.

    (Lauf, Förstergasse: an 85-degree bend in a 3.2 m lane with a house 0.24 m outside the
    lane's edge; the car at full lock met its wall with its front corner at 2.9 m/s and stood
    against it, throttle on, for the rest of the run. Backed off and driven on by its lane
    path's steering, it turned the wrong way first, towards the bend's vertex, and met the
    wall again.)"""

    def __init__(self, side: int, way_on: float, half_l: float, half_w: float, radius: float, rear: float,
                 max_steer: float, distance: float = BACKOFF_M):
        from .driving import SpeedController

        self.side, self.way_on = int(side), float(way_on)
        self.half_l, self.half_w, self.radius, self.rear = half_l, half_w, radius, rear
        self.max_steer, self.distance = max_steer, distance
        self.speed = SpeedController()
        self.move = 0                       # 0: back, 1: forward
        self.phase = "steer"                # steer (braked, wheels to the lock) / go / stop
        self.moved = 0.0
        self.last_xy = None
        self.stalled_s = 0.0
        self.waiting = False
        self.done = False

    def steer_cmd(self) -> float:
        return float(self.side) * (-1.0 if self.move == 0 else 1.0)

    def blocked(self, st, actors, ahead_m: float) -> bool:
        """An actor's box within BACKOFF_CLEAR_M of the footprint along the next ``ahead_m`` of
        the move (boxes, not circles: the car queued behind stands 2 m off the bumper, which a
        circle round it of half its length closes)."""
        if actors is None or not len(actors):
            return False
        curv = self.steer_cmd() / self.radius
        sign = -1.0 if self.move == 0 else 1.0
        poses = [arc_pose(st.x, st.y, st.yaw, sign * d, curv, self.rear) for d in np.linspace(0.0, ahead_m, 4)]
        P = np.vstack([footprint(x, y, h, self.half_l, self.half_w) for x, y, h in poses])
        ax, ay = np.asarray(actors.x, dtype=float), np.asarray(actors.y, dtype=float)
        al, aw = np.asarray(actors.length, dtype=float), np.asarray(actors.width, dtype=float)
        near = np.flatnonzero(np.hypot(ax - st.x, ay - st.y) < 2 * self.half_l + ahead_m + np.maximum(al, aw) + 3.0)
        for i in near.tolist():
            # the footprints' corners near the actor's box, or its corners near a footprint
            # (each box's distance to the other's corners: the gap between them)
            box = (ax[i], ay[i], float(actors.yaw[i]), al[i] / 2.0, aw[i] / 2.0)
            if _corners_near(P, *box, BACKOFF_CLEAR_M):
                return True
            A = footprint(*box)
            if any(_corners_near(A, x, y, h, self.half_l, self.half_w, BACKOFF_CLEAR_M) for x, y, h in poses):
                return True
        return False

    def _faces_way_on(self, yaw: float) -> bool:
        return abs(_wrap(yaw - self.way_on)) <= math.radians(BACKOFF_DONE_DEG)

    def control(self, st, dt: float, actors=None, static_in_way=None) -> tuple[float, float, float, bool]:
        """(throttle, brake, steer, reverse) for this frame. ``static_in_way(st, forward,
        curvature, metres)``, if given, says whether something that does not move (a wall)
        stands within that many metres of the footprint's way: the move ends there."""
        steer = self.steer_cmd()
        rev = self.move == 0
        v = float(st.speed)
        self.waiting = False
        if self.phase == "steer":
            if self._ready(st, steer) and self.move == 1 and (self.side == 0 or self._faces_way_on(st.yaw)):
                self.done = True
            return 0.0, 1.0, steer, rev
        if self.phase == "go":
            self._advance(st, dt)
            left = (self.distance if rev else BACKOFF_FORWARD_M) - self.moved
            speed = abs(v)
            look = min(left, speed * speed / (2.0 * STOP_DECEL) + 0.2)
            if left <= 0.05 or self.stalled_s >= STALL_S or (not rev and self._faces_way_on(st.yaw)) or \
                    (static_in_way is not None and static_in_way(st, not rev, steer / self.radius, look + 0.1)):
                self.phase = "stop"
            elif self.blocked(st, actors, look):
                self.waiting = True          # (held still: it ends after STALL_S)
                return 0.0, 1.0, steer, rev
            else:
                target = min(MOVE_SPEED, math.sqrt(2.0 * STOP_DECEL * max(left, 0.0)))
                pitch = float(getattr(st, "pitch", 0.0))
                th, br = self.speed.control(max(target, 0.3), speed, dt, pitch=-pitch if rev else pitch)
                return th, br, steer, rev
        # stop: braked to a standstill, then the next move (or done)
        if abs(v) < 0.05:
            if self.move == 0:
                self.move, self.phase = 1, "steer"
            else:
                self.done = True
        return 0.0, 1.0, steer, rev
