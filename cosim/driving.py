"""The ego's driving: a lane-level path along a SUMO route, and controllers that follow it.

* :class:`LanePath` turns a route (SUMO edges) into one centreline polyline: on each edge the
  lane that connects to the next edge (the rightmost such drivable lane), the junction's
  internal lanes between them (SUMO's own ``via`` lanes, so the path is exactly the lane
  geometry SUMO's vehicles use), and a smooth lateral blend where the route needs a lane
  change. Everything comes from libsumo (``lane.getLinks``, ``lane.getShape``): no second
  parse of the network. Along the way it records what a driver needs ahead:

  - ``stops``: one :class:`StopLine` per junction the path crosses: the arc length of the stop
    line (where SUMO's approach lane ends), the approach lane, the link's target and ``via``
    lanes, and whether a traffic light controls it. The link's *current* state (SUMO's
    letters: ``r``/``y``/``G``/``g`` of a light, ``M`` major, ``m`` minor, ``=`` right before
    left, ``s`` stop sign, ``w`` all-way stop) is read live with :meth:`StopLine.state`;
  - ``crossings``: one :class:`CrossingOnPath` per pedestrian crossing whose internal lane
    conflicts with the path's junction lanes (``lane.getInternalFoes``), with the arc length
    where the path meets the crossing's centreline;
  - ``max_speed``: SUMO's speed limit of the lane at every path point.

* :class:`PurePursuit` steers the rear axle towards a look-ahead point on the path (the
  steering command of ``cosim.vehicle`` is a rear-axle path curvature, so the geometry is
  exact for the raycast car).
* :class:`SpeedController` turns a target speed into throttle / brake through a longitudinal
  force model of the car (mass, grade from the chassis pitch, rolling resistance, drag, the
  drivetrain's torque and power limits, the brakes) plus a PI correction, so the physics car is
  driven through its wheels, never by setting its pose, and holds its speed on steep grades.
* :func:`curve_speed` and :func:`stop_speed` give the speed limits a planner takes the minimum
  of (:func:`plan_speed` applies them along the path ahead with a comfortable deceleration).
"""
from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

CAR = "passenger"
TLS_STATES = set("rRyYgGuoO")          # letters a traffic light gives a link
CROSSING_RE = re.compile(r"^:(.+)_c\d+_\d+$")


def _lane_allows(sim, lane: str, vclass: str = CAR) -> bool:
    allowed = sim.lane.getAllowed(lane)
    if allowed:
        return vclass in allowed
    return vclass not in sim.lane.getDisallowed(lane)


def _links(sim, lane: str) -> tuple:
    """``lane.getLinks(lane)``, for the network's shape: through SUMO's worker process
    (``cosim.sumo_process``) from one table of every lane's links, kept per network (a route
    search reads the links of hundreds of lanes, and each call across the pipe waits for the
    step in flight: 2.2 s for one route extension on the default run). The lights' states in
    it may be old: a light's state is read with ``lane.getLinks`` itself."""
    table = getattr(sim, "network_links", None)
    if table is not None:
        try:
            return table()[lane]
        except KeyError:
            pass
    return sim.lane.getLinks(lane)


def _drivable_lanes(sim, edge: str) -> list[str]:
    n = sim.edge.getLaneNumber(edge)
    return [f"{edge}_{k}" for k in range(n) if _lane_allows(sim, f"{edge}_{k}")]


def _resample(P: np.ndarray, step: float) -> np.ndarray:
    if len(P) < 2:
        return P
    d = np.hypot(*np.diff(P, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(d)])
    if s[-1] <= 0:
        return P[:1]
    n = max(2, int(math.ceil(s[-1] / step)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, P[:, 0]), np.interp(t, s, P[:, 1])])


BACKSTEP_MAX_M = 2.0    # a point this near behind the one before is a kink where lanes join
#: points up to this far behind the one before are dropped too where the chain comes forward
#: again past it within that distance (a zig-zag through junctions that overlap)
BACKSTEP_FAR_M = 5.0


def _forward_points(P: np.ndarray, *, runs: bool = True) -> np.ndarray:
    """Which points of a chain of lane shapes to keep: not a repeat of the point before, and
    not a little behind it. Where SUMO joins lanes at a very short edge, one lane can begin
    behind the end of the one before (central Helsinki: 0.86 m back at junction 266377992): a
    path through that point doubles back on itself, and a point projected onto it past the
    kink reads as far off the path. Only points within BACKSTEP_MAX_M are dropped: a turn of
    more than 90 degrees at a point (Helsinki's junction 1319789487: south-west into a 0.2 m
    edge, then north) left every later point "behind", and the path jumped 585 m straight
    through the city to the first point ahead again.

    Points further behind, up to BACKSTEP_FAR_M, are dropped only where the chain comes
    forward again (ahead of the last point kept) with every point between within that
    distance: a zig-zag, not a turn. Mikonkatu in Helsinki has three signal nodes within 6 m
    whose junctions overlap; each 0.2 m edge begins 2.2 m behind the end of the one before,
    and the step through them read as a turn the car could not make (19.8 m wide at full
    lock): every route on from Mikonkatu was refused, and the default run stood there. The
    chain comes forward where it crosses the line through the last point kept, across the way
    to it, within BACKSTEP_FAR_M of that point; the first point ahead may lie further on (a
    turn's check takes lanes as SUMO draws them, not resampled: Monaco's Avenue Princesse
    Grace at junction 21918939 steps 2.3 m back, then on along one 14 m segment, and read as
    a straight turn 20 m wider than the car's lock; the only way by the streets from the
    west of Monaco to the east was refused, and the route went through Tunnel de la Colle,
    which the world does not have).

    ``runs`` False: the rule point by point, without taking runs of forward steps whole (the
    same points: the tests' reference)."""
    n = len(P)
    keep = np.ones(n, dtype=bool)
    if n < 2:
        return keep
    # where the point before and the one before it were both kept (most of a path), point i
    # is kept when it steps forward: those runs are taken whole (a path of 1,000 points took
    # 5 ms point by point, in the step that drew the car's next route)
    D = np.diff(P, axis=0)
    dd = np.einsum("ij,ij->i", D, D)
    forward = np.empty(n, dtype=bool)
    forward[0] = True
    forward[1] = dd[0] > 1e-6
    forward[2:] = (dd[1:] > 1e-6) & (np.einsum("ij,ij->i", D[1:], D[:-1]) > 0.0)
    not_forward = np.flatnonzero(~forward)
    last, prev = 0, None
    i = 1
    while i < n:
        if runs and last == i - 1 and prev == (i - 2 if i >= 2 else None):
            k = int(np.searchsorted(not_forward, i))
            j = int(not_forward[k]) if k < len(not_forward) else n
            if j > i:               # i .. j-1 kept
                prev, last, i = j - 2, j - 1, j
                continue
        d = P[i] - P[last]
        dd_i = d @ d
        if dd_i <= 1e-6:
            keep[i] = False
            i += 1
            continue
        if prev is not None:
            u = P[last] - P[prev]
            if d @ u <= 0.0:
                if dd_i < BACKSTEP_MAX_M ** 2:
                    keep[i] = False
                    i += 1
                    continue
                # a zig-zag: back, then forward past the last point kept, all near it (where
                # the chain crosses back over the line through that point across its way: the
                # point after may be far on, the end of a lane's one long segment)
                j = i
                while j < n and (P[j] - P[last]) @ (P[j] - P[last]) < BACKSTEP_FAR_M ** 2 \
                        and (P[j] - P[last]) @ u <= 0.0:
                    j += 1
                if j < n and j > i:
                    b = (P[j] - P[last]) @ u
                    if b > 0.0:
                        a = (P[j - 1] - P[last]) @ u
                        x = P[j - 1] + (P[j] - P[j - 1]) * (-a / (b - a)) - P[last]
                        if x @ x < BACKSTEP_FAR_M ** 2:
                            keep[i:j] = False
                            i = j
                            continue
        prev, last = last, i
        i += 1
    return keep


#: a step between two points of a lane path this long or longer, sideways, is a jump: a lane
#: change forced on an edge too short to blend it on (Helsinki, edge 30605639#1 of 0.2 m: 3.1 m
#: to the right from the lane a junction leads onto to the only lane linked onward; blended on
#: the edge, the path stepped 3 m sideways within 3 m, and the car, at full lock, ran 1.6 m off
#: it through the junction after it; SUMO logged the ego colliding with a truck there)
JUMP_MIN_M = 1.5
#: ... eased over this much of the path after it (a cosine from the line before to the new lane)
JUMP_EASE_M = 15.0
#: a lane change on an edge shorter than this is not blended on it (a 3 m step sideways within
#: a few metres): the path stays on the lane it came in on to the edge's end, and the step to
#: the lane changed into is eased over the path after it (_ease_jumps)
BLEND_MIN_M = 8.0


def _ease_jumps(P: np.ndarray) -> np.ndarray:
    """The chain of lane shapes ``P`` with each sideways jump (:data:`JUMP_MIN_M`) eased: the
    points after it start on the line before it and reach their own lane within
    :data:`JUMP_EASE_M` (its forward part stays). A step back (lanes joined at a very short
    edge, a zig-zag) is left to :func:`_forward_points`."""
    if len(P) < 3:
        return P
    d = np.diff(P, axis=0)
    jumps = np.flatnonzero(np.hypot(d[:, 0], d[:, 1]) >= JUMP_MIN_M)
    if not len(jumps):
        return P
    P = P.copy()
    for k in jumps.tolist():
        u = P[k] - P[max(0, k - 3)]
        nu = math.hypot(u[0], u[1])
        if nu < 1e-6:
            continue
        u = u / nu
        J = P[k + 1] - P[k]
        along = float(J @ u)
        side = J - along * u
        if along < 0.0 or math.hypot(side[0], side[1]) < JUMP_MIN_M:
            continue
        seg = np.hypot(*np.diff(P[k + 1:], axis=0).T)
        dist = np.concatenate([[0.0], np.cumsum(seg)])
        m = int(np.searchsorted(dist, JUMP_EASE_M))
        w = 0.5 - 0.5 * np.cos(np.pi * dist[:m] / JUMP_EASE_M)
        P[k + 1:k + 1 + m] -= side * (1.0 - w)[:, None]
    return P


def junction_of(internal_lane: str) -> str:
    """Junction id of an internal lane ``:J_k_i`` (junction ids may contain underscores)."""
    return internal_lane[1:].rsplit("_", 2)[0]


def _segment_intersection(p, q, a, b):
    """Parameter t along p->q where it crosses a->b (both as segments), or None."""
    r = q - p
    s = b - a
    den = r[0] * s[1] - r[1] * s[0]
    if abs(den) < 1e-12:
        return None
    w = a - p
    t = (w[0] * s[1] - w[1] * s[0]) / den
    u = (w[0] * r[1] - w[1] * r[0]) / den
    if -1e-9 <= t <= 1 + 1e-9 and -1e-9 <= u <= 1 + 1e-9:
        return t
    return None


def _first_crossing(path: np.ndarray, shape: np.ndarray):
    """(a, t) of the first segment path[a] -> path[a+1] (then the first segment of ``shape``)
    that crosses ``shape``, t along that path segment, or None: ``_segment_intersection`` over
    all pairs in that order, in one numpy pass."""
    p, r = path[:-1, None, :], (path[1:] - path[:-1])[:, None, :]
    a, s = shape[None, :-1, :], (shape[1:] - shape[:-1])[None, :, :]
    den = r[..., 0] * s[..., 1] - r[..., 1] * s[..., 0]
    w = a - p
    ok = np.abs(den) >= 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * s[..., 1] - w[..., 1] * s[..., 0]) / den
        u = (w[..., 0] * r[..., 1] - w[..., 1] * r[..., 0]) / den
    hit = ok & (t >= -1e-9) & (t <= 1 + 1e-9) & (u >= -1e-9) & (u <= 1 + 1e-9)
    rows = np.flatnonzero(hit.any(axis=1))
    if not len(rows):
        return None
    ia = int(rows[0])
    ib = int(np.argmax(hit[ia]))
    return ia, float(t[ia, ib])


#: the most a car at full lock would leave a turn's centreline (m) for the turn to be driven;
#: beyond it the car's body leaves a 3.2 m lane by more than half a metre
TURN_DEVIATION_MAX_M = 0.9
_TURN_CACHE: dict = {}


def car_turn_radius() -> float:
    """Radius (m) of the circle the car's rear axle drives at full lock."""
    from .vehicle import min_turn_radius

    return float(min_turn_radius())


def turn_deviation(P: np.ndarray, radius: float, lookahead: float = 5.0, step: float = 0.5) -> float:
    """How far (m) the middle of a car's footprint leaves the polyline ``P`` when it follows it
    by pure pursuit (look-ahead ``lookahead``, the autopilot's at low speed) turning no
    tighter than its rear axle's ``radius``: a kinematic run along the polyline, ``step``
    metres a step. 0 where the polyline never turns tighter than the car can (checked first,
    without the run). For the ego car, a 90-degree junction turn of 2.6 m (SUMO's tightest)
    gives about 0.6 m; a Monaco hairpin drawn at 3 m, 1.5 m."""
    from .vehicle import WHEELBASE

    P = np.asarray(P, dtype=float)[:, :2]
    P = P[_forward_points(P)]            # (as the path is built: no doubling back at tiny edges)
    if len(P) < 3:
        return 0.0
    Q = _resample(P, step)
    n = len(Q)
    if n < 3:
        return 0.0
    h = np.unwrap(np.arctan2(np.diff(Q[:, 1]), np.diff(Q[:, 0])))
    w = max(1, int(round(2.0 / step)))   # heading change over +-2 m
    if len(h) <= 2 * w or np.max(np.abs(h[2 * w:] - h[:-2 * w])) / (2 * w * step) <= 1.0 / radius:
        return 0.0
    k_max = 1.0 / radius
    qx, qy = Q[:, 0].tolist(), Q[:, 1].tolist()      # (plain floats: a step is a few numbers)
    x, y, yaw = qx[0], qy[0], float(h[0])
    i = 0
    ahead = int(round(lookahead / step))
    half_wb = WHEELBASE / 2.0
    worst = 0.0
    cos, sin, atan2, hypot = math.cos, math.sin, math.atan2, math.hypot
    for _ in range(n + 20):
        best = None
        for j in range(max(0, i - 2), min(n, i + 6)):
            d2 = (qx[j] - x) ** 2 + (qy[j] - y) ** 2
            if best is None or d2 < best:
                best, i_new = d2, j
        i = i_new
        if i + ahead >= n - 1:
            break
        tx, ty = qx[i + ahead] - x, qy[i + ahead] - y
        k = 2.0 * sin(atan2(ty, tx) - yaw) / max(hypot(tx, ty), 1e-6)
        yaw += max(-k_max, min(k_max, k)) * step
        x += step * cos(yaw)
        y += step * sin(yaw)
        cx, cy = x + half_wb * cos(yaw), y + half_wb * sin(yaw)
        near = min((qx[j] - cx) ** 2 + (qy[j] - cy) ** 2 for j in range(max(0, i - 2), min(n, i + 8)))
        worst = max(worst, near)
    return math.sqrt(worst)


def _via_lanes(sim, via) -> list:
    """A link's junction lanes in order: ``via`` and those after it. A junction with an
    internal junction splits a link in two (Kouvola, ``:36156596_6_0`` then ``_17_0``); the
    next is the first link's own junction lane, not the lane it leads to (taking that, a lane
    path left out a 14 m turn, the car drove its 2 m chord, and SUMO put the ego on the
    oncoming junction lane beside, where a waiting car ran into it)."""
    out, guard = [], 0
    while via and via.startswith(":") and guard < 5:
        out.append(via)
        links = _links(sim, via)
        via = (links[0][4] or links[0][0]) if links else None
        guard += 1
    return out


def _link_deviation(sim, lane: str, link, lead_m: float = 10.0) -> float:
    """:func:`turn_deviation` of a link: the last ``lead_m`` metres of ``lane``, the link's
    junction lane and the first ``lead_m`` metres of its target (cached by the shapes' ends:
    another network's lane of the same id is measured again)."""
    sa, sb = sim.lane.getShape(lane), sim.lane.getShape(link[0])
    vias = _via_lanes(sim, link[4])
    sv = [sim.lane.getShape(x) for x in vias]
    mid = [p for shp in sv for p in shp]
    # (the key from SUMO's tuples as they come: numpy only for a turn not measured yet)
    key = (lane, link[0], tuple(vias), tuple(sa[-1][:2]), tuple(sb[0][:2]), len(mid),
           tuple(mid[len(mid) // 2][:2]) if mid else ())

    def polyline():
        a = np.array(sa, dtype=float)[:, :2]
        b = np.array(sb, dtype=float)[:, :2]
        v = np.array(mid, dtype=float)[:, :2] if mid else np.zeros((0, 2))
        return np.vstack([_tail(a, lead_m), v, _tail(b[::-1], lead_m)[::-1]])

    return _cached_deviation(key, polyline)


def _cached_deviation(key, polyline) -> float:
    """:func:`turn_deviation` of ``polyline()`` at the car's turning radius, cached by ``key``."""
    out = _TURN_CACHE.get(key)
    if out is None:
        out = turn_deviation(polyline(), car_turn_radius())
        if len(_TURN_CACHE) > 100_000:
            _TURN_CACHE.clear()
        _TURN_CACHE[key] = out
    return out


def _tail(P: np.ndarray, length: float) -> np.ndarray:
    """The last ``length`` metres of a polyline, cut inside a segment where it is longer (a
    lane of one 380 m segment made a turn's run 380 m long: 7 ms instead of 0.2)."""
    if len(P) < 2:
        return P
    d = np.hypot(*np.diff(P, axis=0).T)
    back = np.concatenate([[0.0], np.cumsum(d[::-1])])      # distance from the end, per point (reversed)
    k = int(np.searchsorted(back, length))
    if k >= len(P):
        return P
    out = P[len(P) - 1 - k:].copy()
    over = back[k] - length                                  # how far the first point lies beyond
    seg = d[len(P) - 1 - k]
    if over > 1e-9 and seg > 0.0:
        out[0] = P[len(P) - 1 - k] + (P[len(P) - k] - P[len(P) - 1 - k]) * (over / seg)
    return out


def _unturnable(sim, lane: str, link) -> bool:
    """A link the car cannot drive: a turnaround, or a turn tighter than its full lock by
    more than :data:`TURN_DEVIATION_MAX_M`."""
    if link[6] == "t":
        return True
    try:
        return _link_deviation(sim, lane, link) > TURN_DEVIATION_MAX_M
    except Exception:
        return False


#: an edge shorter than this between two junctions is checked with the turns on both sides
#: of it as one: netconvert joins close junctions by edges of 0.2 m, and two turns that each
#: pass on their own can make a hairpin together (Monaco: 0.6 m and 0 m alone, 2.5 m chained)
CHAIN_EDGE_M = 10.0


def _short(sim, edge: str) -> bool:
    lanes = _drivable_lanes(sim, edge)
    return bool(lanes) and float(sim.lane.getLength(lanes[0])) < CHAIN_EDGE_M


def _chain_deviation(sim, lane: str, link1, link2, lead_m: float = 10.0) -> float:
    """:func:`turn_deviation` through two links in a row: the last ``lead_m`` metres of
    ``lane``, ``link1``'s junction lane, its (short) target lane, ``link2``'s junction lane
    and the first ``lead_m`` metres of its target (cached like :func:`_link_deviation`)."""
    def shape(ln):
        return np.array(sim.lane.getShape(ln), dtype=float)[:, :2] if ln else np.zeros((0, 2))

    def via_shape(via):
        """A link's junction lanes, all of them (a junction may split a link in two)."""
        parts = [shape(x) for x in _via_lanes(sim, via)]
        return np.vstack(parts) if parts else np.zeros((0, 2))

    sa, smid, sb = sim.lane.getShape(lane), sim.lane.getShape(link1[0]), sim.lane.getShape(link2[0])
    key = ("chain", lane, link1[0], link1[4], link2[0], link2[4], tuple(sa[-1][:2]), tuple(smid[0][:2]),
           tuple(sb[0][:2]))

    def polyline():
        a, mid, b = (np.array(x, dtype=float)[:, :2] for x in (sa, smid, sb))
        v1, v2 = via_shape(link1[4]), via_shape(link2[4])
        return np.vstack([_tail(a, lead_m), v1, mid, v2, _tail(b[::-1], lead_m)[::-1]])

    return _cached_deviation(key, polyline)


def _chain_unturnable(sim, edge: str, short: str, nxt: str) -> bool:
    """Does every way of the route's steps edge -> short -> nxt (``short`` a short edge between
    two junctions) run wider than :data:`TURN_DEVIATION_MAX_M` at full lock, the two turns
    taken as one?"""
    found = other = False
    for ln in _drivable_lanes(sim, edge):
        for l1 in _links(sim, ln):
            if l1[0].rsplit("_", 1)[0] != short or not _lane_allows(sim, l1[0]):
                continue
            for l2 in _links(sim, l1[0]):
                if l2[0].rsplit("_", 1)[0] != nxt or not _lane_allows(sim, l2[0]):
                    continue
                try:
                    bad = _chain_deviation(sim, ln, l1, l2) > TURN_DEVIATION_MAX_M
                except Exception:
                    bad = False
                if bad:
                    found = True
                else:
                    other = True
    return found and not other


def is_tunnel(sim, edge: str) -> bool:
    """Is ``edge`` in a tunnel (the OSM tag, kept by netconvert as the edge's parameter)? The
    world has no tunnels: their roads are not meshed."""
    from netgen.roadnet import SURFACE_TUNNEL_VALUES

    try:
        return sim.edge.getParameter(edge, "tunnel") not in SURFACE_TUNNEL_VALUES
    except Exception:
        return False


#: m: a lane for cars narrower than this is one the car does not fit in (1.8 m wide). OSM's
#: ``width`` gives a few (Helsinki's Siltavuorenpenger 1.5 m, Lauf's and Monaco's 1.6 m), and
#: the passages cut through buildings for them are as narrow: a car started there stood at the
#: first one for good
LANE_MIN_WIDTH_M = 2.0
_NARROW_CACHE: dict = {}


def is_too_narrow(sim, edge: str) -> bool:
    """Is every lane of ``edge`` that cars may use narrower than :data:`LANE_MIN_WIDTH_M`?
    (Kept per network.)"""
    key, out = _kept(_NARROW_CACHE, sim, edge)
    if out is None:
        try:
            lanes = _drivable_lanes(sim, edge)
            out = bool(lanes) and all(float(sim.lane.getWidth(ln)) < LANE_MIN_WIDTH_M for ln in lanes)
        except Exception:
            out = False
        if key is not None:
            _keep(_NARROW_CACHE, key, out)
    return out


def _kept(cache: dict, sim, *parts) -> tuple:
    """(the key (network, *parts) of a cache kept per network, what it holds under it or None);
    (None, None) where the network cannot be told."""
    try:
        key = (_net_key(sim),) + parts
    except Exception:
        return None, None
    return key, cache.get(key)


def _keep(cache: dict, key, value) -> None:
    """``cache[key] = value``, the cache emptied first once it holds 200,000 entries (the
    caches kept per network: :func:`note_network`)."""
    if len(cache) > 200_000:
        cache.clear()
    cache[key] = value


def off_the_world(sim, edge: str) -> bool:
    """Is ``edge`` a road the car cannot drive in the world: a tunnel (:func:`is_tunnel`) or
    too narrow for it (:func:`is_too_narrow`)?"""
    return is_tunnel(sim, edge) or is_too_narrow(sim, edge)


_TURNAROUND_CACHE: dict = {}
#: steps worked out (not found in _TURNAROUND_CACHE) so far: the route checks yield every
#: TURN_PIECE of them (an 80-edge route checked on new streets took 8 ms in one piece)
_TURN_WORK = [0]
TURN_PIECE = 4


def _turnaround(sim, edge: str, nxt: str, after: str | None = None) -> bool:
    """Does the route's step edge -> nxt only have links the car cannot drive (turnarounds,
    turns far tighter than its full lock: :func:`_unturnable`), or enter a road off the world (a
    tunnel, a lane narrower than the car: :func:`off_the_world`)? With
    ``after`` (the edge after ``nxt``) and ``nxt`` shorter than :data:`CHAIN_EDGE_M`, also
    when the two turns around ``nxt`` taken as one cannot be driven (:func:`_chain_unturnable`).
    Kept per network (a random route's draws check the same steps again and again)."""
    key, out = _kept(_TURNAROUND_CACHE, sim, edge, nxt, after)
    if key is None:
        return _turnaround_uncached(sim, edge, nxt, after)
    if out is None:
        _TURN_WORK[0] += 1
        out = _turnaround_uncached(sim, edge, nxt, after)
        _keep(_TURNAROUND_CACHE, key, out)
    return out


def _turnaround_uncached(sim, edge: str, nxt: str, after: str | None) -> bool:
    if off_the_world(sim, nxt) and not off_the_world(sim, edge):
        return True
    found = other = False
    for ln in _drivable_lanes(sim, edge):
        for link in _links(sim, ln):
            if link[0].rsplit("_", 1)[0] == nxt:
                if _unturnable(sim, ln, link):
                    found = True
                else:
                    other = True
    if found and not other:
        return True
    return after is not None and _short(sim, nxt) and _chain_unturnable(sim, edge, nxt, after)


#: the searches below yield after this many edges expanded (their ``*_steps`` generators: SUMO's
#: worker draws routes between requests, and a step that comes waits for the piece in hand)
SEARCH_PIECE = 50


def route_without_turnarounds(sim, src: str, dst: str, max_edges: int = 20000) -> list[str] | None:
    """Shortest route by road from edge ``src`` to edge ``dst`` (both included) that uses no
    link the car cannot drive (a turnaround, a turn far tighter than its full lock:
    :func:`_unturnable`) and no tunnel (:func:`is_tunnel`; Dijkstra over lane links, expanded
    lazily), or None."""
    return run_steps(_route_steps(sim, src, dst, max_edges))


def _route_steps(sim, src: str, dst: str, max_edges: int = 20000):
    """:func:`route_without_turnarounds`, yielding every :data:`SEARCH_PIECE` edges."""
    import heapq

    succ: dict = {}
    dist = {src: 0.0}
    prev = {}
    heap = [(0.0, src)]
    seen = 0
    while heap:
        d, e = heapq.heappop(heap)
        if d > dist.get(e, float("inf")):
            continue
        if e == dst:
            break
        seen += 1
        if seen > max_edges:
            break
        if seen % SEARCH_PIECE == 0:
            yield
        nx = succ.get(e)
        if nx is None:
            nx = succ[e] = yield from _drivable_nexts_steps_kept(sim, e, dst)
        for ne, w, via in nx:
            nd = d + w
            if nd < dist.get(ne, float("inf")):
                dist[ne] = nd
                prev[ne] = (e, via)
                heapq.heappush(heap, (nd, ne))
    if dst not in prev:
        return None
    out = [dst]
    while out[-1] != src:
        e, via = prev[out[-1]]
        if via is not None:
            out.append(via)
        out.append(e)
        if len(out) > max_edges:
            return None
    return out[::-1]


#: (network, edge) -> (``_drivable_nexts`` without a destination, the edges it looked at)
_NEXTS_CACHE: dict = {}


_NET_FILES: dict = {}


def note_network(sim, net_file) -> None:
    """``sim`` has just loaded the network ``net_file``: what the caches kept per network
    (:func:`_net_key`, its boundary) hold for another network of the same boundary is dropped.
    Two networks of one place can share it: a test's own netconvert run of the Helsinki
    preset and the preset's world, whose tunnels are kept apart; a route drawn on the world
    in the same process then took the other network's steps from Alvar Aallon katu, found
    none, and the start was refused."""
    try:
        key = _net_key(sim)
        st = os.stat(net_file)
        ident = (str(Path(net_file).resolve()), st.st_size, st.st_mtime_ns)
    except Exception:
        return
    if _NET_FILES.get(key, ident) != ident:
        for cache in (_TURNAROUND_CACHE, _NEXTS_CACHE, _NARROW_CACHE):
            for k in [k for k in cache if k[0] == key]:
                del cache[k]
    _NET_FILES[key] = ident


def _net_key(sim) -> tuple:
    """Which network ``sim`` has loaded, for caches of its shape: its boundary (a network
    answer, kept by SUMO's worker proxy too; well under a microsecond in libsumo, where the
    lane count takes a millisecond)."""
    return tuple(map(tuple, sim.simulation.getNetBoundary()))


def _drivable_nexts(sim, e: str, dst: str | None = None) -> list:
    """[(next edge, metres, short edge passed on the way or None)] the car can drive from edge
    ``e`` (no turnaround, no turn it cannot make, no tunnel but ``dst``): through a short edge
    (:data:`CHAIN_EDGE_M`) at once to the edges after it, the two turns checked as one.

    Kept per network: the random route draws search the same streets again and again (a draw
    from Mikonkatu, Helsinki: 377 searches over 8,560 edges, 1.4 s). ``dst`` changes the answer
    only where it is one of the edges looked at."""
    return run_steps(_drivable_nexts_steps_kept(sim, e, dst))


def _drivable_nexts_steps_kept(sim, e: str, dst: str | None = None):
    """:func:`_drivable_nexts` as a generator: at once where kept, else yielding after each
    turn it measures (a search piece over streets not worked out before took 4.5 ms in SUMO's
    worker, in one step of a Helsinki drive; see :func:`route_graph_steps`)."""
    key, hit = _kept(_NEXTS_CACHE, sim, e)
    if hit is None:
        hit = yield from _drivable_nexts_steps(sim, e, None)
        if key is not None:
            _keep(_NEXTS_CACHE, key, hit)
    out, seen = hit
    if dst is not None and dst in seen:
        out = (yield from _drivable_nexts_steps(sim, e, dst))[0]
    return out


def route_graph_steps(sim, edges):
    """Work out :func:`_drivable_nexts` of ``edges`` (kept per network, as the searches keep
    them), a turn at a time: a generator that yields after each turn it measures, so that a
    caller can spread the work over frames (``cosim.traffic.SumoTraffic.warm_routes``; one
    edge into a big junction measures 20 turns or more, 10 ms)."""
    net = _net_key(sim)
    for e in edges:
        if (net, e) in _NEXTS_CACHE:
            continue
        try:
            hit = yield from _drivable_nexts_steps(sim, e, None)
        except Exception:      # (an edge SUMO does not know: the search says so itself)
            continue
        _keep(_NEXTS_CACHE, (net, e), hit)


def run_steps(gen):
    """Run a generator to its end; its return value."""
    while True:
        try:
            next(gen)
        except StopIteration as e:
            return e.value


def _drivable_nexts_uncached(sim, e: str, dst: str | None) -> tuple[list, set]:
    """:func:`_drivable_nexts`, and the edges it looked at."""
    return run_steps(_drivable_nexts_steps(sim, e, dst))


def _drivable_nexts_steps(sim, e: str, dst: str | None):
    """:func:`_drivable_nexts_uncached`, yielding after each turn measured."""
    best = {}
    seen = set()
    for ln in _drivable_lanes(sim, e):
        for link in _links(sim, ln):
            if not _lane_allows(sim, link[0]):
                continue
            ne = link[0].rsplit("_", 1)[0]
            seen.add(ne)
            if ne in best:
                continue
            bad = _unturnable(sim, ln, link)
            yield
            if bad or (ne != dst and off_the_world(sim, ne)):
                continue
            w = float(sim.lane.getLength(link[0])) + float(link[7] or 0.0)
            if ne == dst or not _short(sim, ne):
                best[ne] = (w, None)
                continue
            for l2 in _links(sim, link[0]):
                nne = l2[0].rsplit("_", 1)[0]
                seen.add(nne)
                if (nne in best and best[nne][0] <= w) or not _lane_allows(sim, l2[0]) or \
                        _unturnable(sim, link[0], l2) or (nne != dst and off_the_world(sim, nne)):
                    continue
                try:
                    chain = _chain_deviation(sim, ln, link, l2)
                except Exception:
                    chain = 0.0
                yield
                if chain > TURN_DEVIATION_MAX_M:
                    continue
                best[nne] = (w + float(sim.lane.getLength(l2[0])) + float(l2[7] or 0.0), ne)
    return [(ne, w, via) for ne, (w, via) in best.items()], seen


def escapes(sim, edge: str, reach_m: float = 1000.0, max_edges: int = 3000) -> bool:
    """Can the car drive ``reach_m`` metres on from the end of ``edge`` without a step it
    cannot drive (:func:`_drivable_nexts`)? False at the head of a one-way street whose every
    way out has a turn tighter than the car can make (or a tunnel): a route ending there leaves
    the car nowhere to go but through it."""
    return run_steps(escapes_steps(sim, edge, reach_m, max_edges))


def escapes_steps(sim, edge: str, reach_m: float = 1000.0, max_edges: int = 3000):
    """:func:`escapes`, yielding every :data:`SEARCH_PIECE` edges."""
    import heapq

    dist = {edge: 0.0}
    heap = [(0.0, edge)]
    seen = 0
    while heap:
        d, e = heapq.heappop(heap)
        if d >= reach_m:
            return True
        if d > dist.get(e, float("inf")):
            continue
        seen += 1
        if seen > max_edges:
            return True
        if seen % SEARCH_PIECE == 0:
            yield
        try:
            nx = yield from _drivable_nexts_steps_kept(sim, e)
        except Exception:
            continue
        for ne, w, _via in nx:
            nd = d + w
            if nd < dist.get(ne, float("inf")):
                dist[ne] = nd
                heapq.heappush(heap, (nd, ne))
    return False


def without_turnarounds(sim, edges: list[str]) -> tuple[list[str], list]:
    """The route with every step the car cannot turn (a U-turn inside a junction, far tighter
    than the car's 4.6 m turning radius; a turn a car at full lock would run wide of by more
    than :data:`TURN_DEVIATION_MAX_M`, such as a hairpin drawn too tight; a way into a tunnel,
    which the world does not have) replaced by the shortest detour without one (around a
    block), where there is one.
    Returns (edges, detours made as (from edge, to edge, edges added))."""
    return run_steps(without_turnarounds_steps(sim, edges))


def without_turnarounds_steps(sim, edges: list[str]):
    """:func:`without_turnarounds`, yielding in its searches (:data:`SEARCH_PIECE`)."""
    out = [edges[0]] if edges else []
    detours = []
    whole_tried = False
    i = 1
    mark = _TURN_WORK[0]
    while i < len(edges):
        if _TURN_WORK[0] - mark >= TURN_PIECE:
            mark = _TURN_WORK[0]
            yield
        cur, nxt = out[-1], edges[i]
        after = edges[i + 1] if i + 1 < len(edges) else None
        try:
            uturn = _turnaround(sim, cur, nxt)
            chain = not uturn and _turnaround(sim, cur, nxt, after)
        except Exception:
            uturn = chain = False
        if uturn or chain:
            # (into a tunnel: around the whole tunnel, to the first edge after it; two turns
            # around a short edge: rejoining after it)
            j = i + 1 if chain else i
            while j < len(edges) - 1 and off_the_world(sim, edges[j]):
                j += 1
            tunnel = j > i or off_the_world(sim, nxt)
            found = yield from _detour_steps(sim, out, edges, i, j, tunnel=tunnel)
            if found is not None:
                back, jj, alt = found
                start = out[len(out) - 1 - back]
                del out[len(out) - back:]
                out.extend(alt[1:])
                detours.append((start, edges[jj], len(alt) - 2))
                i = jj + 1
                continue
            if tunnel and edges[-1] != cur:
                # no way round near it (the tunnel rejoins the streets only further on, or runs
                # on in pieces: since netgen 0.1.26 a tunnel is its own edges): the whole rest
                # of the route by the car's own router, where it has one
                alt = yield from _route_steps(sim, cur, edges[-1])
                if alt and len(alt) >= 2 and not (yield from undrivable_steps_steps(sim, alt)):
                    out.extend(alt[1:])
                    detours.append((cur, edges[-1], len(alt) - 2))
                    break
                if not whole_tried and out[0] != cur:
                    # none from there (a one-way street on into the tunnel): the whole route
                    # from its first edge, where the car's router has a way (Monaco: SUMO's
                    # route from Avenue d'Ostende took Boulevard Louis II into its tunnel, whose
                    # way in leads only into it; the streets' way turns off at Rond-Point
                    # Sainte-Dévote, before)
                    whole_tried = True
                    alt = yield from _route_steps(sim, out[0], edges[-1])
                    if alt and len(alt) >= 2 and not (yield from undrivable_steps_steps(sim, alt)):
                        del out[1:]
                        out.extend(alt[1:])
                        detours[:] = [(alt[0], edges[-1], len(alt) - 2)]
                        break
        out.append(nxt)
        i += 1
    return out, detours


def undrivable_steps(sim, edges: list[str]) -> list:
    """The steps (edge, next edge) of a route the car cannot drive (see :func:`_turnaround`)."""
    return run_steps(undrivable_steps_steps(sim, edges))


def undrivable_steps_steps(sim, edges: list[str]):
    """:func:`undrivable_steps`, yielding every :data:`TURN_PIECE` steps worked out."""
    out = []
    mark = _TURN_WORK[0]
    for k, (a, b) in enumerate(zip(edges, edges[1:])):
        if _TURN_WORK[0] - mark >= TURN_PIECE:
            mark = _TURN_WORK[0]
            yield
        try:
            if _turnaround(sim, a, b, edges[k + 2] if k + 2 < len(edges) else None):
                out.append((a, b))
        except Exception:
            pass
    return out


def _detour_steps(sim, out: list, edges: list, i: int, j: int, tunnel: bool, back_max: int = 4,
                  ahead_max: int = 4, max_search: int = 400):
    """A way around the step ``out[-1] -> edges[i]`` (or the tunnel ``edges[i:j]``): from the
    route's last edge, else from up to ``back_max`` edges before it (a one-way street may
    have no other exit), to ``edges[j]``, else up to ``ahead_max`` edges further on. Returns
    (edges of ``out`` given up, index of the edge rejoined, the detour's edges) or None.
    Each search expands at most ``max_search`` edges (a block, not the city). A detour with a
    step the car cannot drive is no way around (the search avoids single links, not two turns
    around a short edge: Helsinki's way around the hairpin at junction 1319789487 came back
    to the same hairpin after 1.4 km). A generator that yields in its searches
    (:data:`SEARCH_PIECE`); its value is the answer."""
    for back in range(min(back_max, len(out) - 1) + 1):
        src = out[len(out) - 1 - back]
        for jj in range(j, min(len(edges), j + ahead_max + 1)):
            alt = yield from _route_steps(sim, src, edges[jj], max_edges=max_search)
            if jj == j and not tunnel and back == 0:
                if alt and len(alt) > 2 and not (yield from undrivable_steps_steps(sim, alt)):
                    return back, jj, alt
                continue
            if alt and len(alt) >= 2 and not (back == 0 and jj == i and len(alt) == 2) \
                    and not (yield from undrivable_steps_steps(sim, alt)):
                return back, jj, alt
    return None


@dataclass
class PathPoint:
    s: float
    x: float
    y: float
    lane: str
    edge: str


@dataclass
class StopLine:
    """Where the path enters a junction: the end of SUMO's approach lane."""
    s: float                  # arc length of the stop line on the path
    lane: str                 # approach lane (ends at the stop line)
    to_lane: str              # lane after the junction
    via: str                  # first internal lane of the link
    junction: str
    tls: bool                 # a traffic light controls the link (when the path was built)
    initial_state: str
    internal_length: float = 0.0   # m of junction lanes until the next normal lane

    def link(self, sim):
        """SUMO's link tuple of this connection now (state letters change with the light)."""
        for link in sim.lane.getLinks(self.lane):
            if link[0] == self.to_lane and (not self.via or link[4] == self.via):
                return link
        return None

    def state(self, sim) -> str:
        link = self.link(sim)
        return link[5] if link else self.initial_state


@dataclass
class CrossingOnPath:
    """A pedestrian crossing the path goes over."""
    s: float                  # arc length where the path meets the crossing's centreline
    edge: str                 # SUMO crossing edge (``:J_c0``)
    lane: str
    width: float
    junction: str
    shape: np.ndarray = field(repr=False, default=None)


@dataclass
class LaneChange:
    """Where the path moves over from one lane to the next along an edge (``LanePath._blend``).

    ``i0``..``i1`` (exclusive) are the path's points on that edge; per point, ``shift`` is the
    vector from the path to the lane the car comes in on (zero before the blend begins, the
    whole lane offset after it ends), ``src_lat`` and ``tgt_lat`` the signed lateral offsets
    (left +) of that lane and of the lane changed into, from the path. ``s0`` and ``s1`` are
    where the blend begins and ends, ``s_end`` where the edge ends (its stop line)."""
    edge: str
    from_lane: str
    to_lane: str
    i0: int
    i1: int
    s0: float
    s1: float
    s_end: float
    shift: np.ndarray = field(repr=False, default=None)
    src_lat: np.ndarray = field(repr=False, default=None)
    tgt_lat: np.ndarray = field(repr=False, default=None)

    @property
    def key(self) -> tuple:
        return (self.edge, self.from_lane, self.to_lane)


def _onto_segments(P, V, x, y):
    """Points (x, y; arrays broadcast against the segments) projected onto segments from `P`
    along `V` (m, 2): (t in [0, 1], the point less the segment's start dx, dy, the point
    less its projection ex, ey, the segments' squared lengths)."""
    L2 = np.maximum(V[:, 0] * V[:, 0] + V[:, 1] * V[:, 1], 1e-12)
    dx, dy = x - P[:, 0], y - P[:, 1]
    t = np.minimum(np.maximum((dx * V[:, 0] + dy * V[:, 1]) / L2, 0.0), 1.0)   # (np.clip's wrapper: 3 us more)
    return t, dx, dy, dx - t * V[:, 0], dy - t * V[:, 1], L2


#: edges (or junction lanes) of a path built in one piece (LanePath.build_steps)
BUILD_PIECE = 3
#: points of a path before its last edge that its continuation is built after (LanePath.lead_in)
LEAD_IN_POINTS = 3


class LanePath:
    """A drivable centreline along a SUMO route. ``xy`` (n, 2), ``s`` arc length, per point the
    SUMO lane and edge it belongs to; ``stops``, ``crossings`` and ``max_speed`` (module doc)."""

    STEP = 1.0

    def __init__(self, sim, edges: list[str], start_lane: str | None = None, start_pos: float = 0.0,
                 lead_in=None):
        for _ in self.build_steps(sim, edges, start_lane, start_pos, lead_in):
            pass

    def build_steps(self, sim, edges: list[str], start_lane: str | None = None, start_pos: float = 0.0,
                    lead_in=None):
        """The construction (``__init__``) as a generator that yields every
        :data:`BUILD_PIECE` edges or junction lanes, so that SUMO's worker can build a path in
        pieces between steps (``SumoTraffic.random_extension_path``: an 800 m path in one
        piece took 10-15 ms in one step). ``lead_in``: the last points before the path (of the
        path it continues, :meth:`extended`), so that a step back right at its start is
        dropped as within a path (:func:`_forward_points`)."""
        self.edges, self.detours = without_turnarounds(sim, list(edges))
        self._stay_in_start_lane(sim, start_lane, start_pos)
        pts, lanes = [], []
        # which lane to be on at each edge: one with a link to the next edge, chosen by a
        # backward pass that minimises lane changes, cheaper on long edges (a change on a
        # 0.2 m edge would be a sideways jump)
        n_e = len(self.edges)
        links = []                 # per edge: {lane: [(to_lane, via, state), ...]} towards the next edge
        lanes_e = []
        lengths = []
        for i, e in enumerate(self.edges):
            if i and i % BUILD_PIECE == 0:
                yield
            cands = _drivable_lanes(sim, e)
            if not cands:
                raise ValueError(f"edge {e} has no lane for cars")
            lanes_e.append(cands)
            lengths.append(float(sim.lane.getLength(cands[0])))
            if i + 1 < n_e:
                nxt = self.edges[i + 1]
                lk = {}
                for ln in cands:
                    for link in _links(sim, ln):
                        if link[0].rsplit("_", 1)[0] == nxt and _lane_allows(sim, link[0]):
                            lk.setdefault(ln, []).append((link[0], link[4], link[5]))
                if not lk:
                    raise ValueError(f"no lane of {e} connects to {nxt}")
                links.append(lk)
            else:
                links.append({ln: [(None, None, None)] for ln in cands})

        def idx(lane):
            return int(lane.rsplit("_", 1)[1])

        def change_cost(a, b, length):
            return abs(idx(a) - idx(b)) * (1.0 + 60.0 / max(length, 1.0))

        INF = float("inf")
        cost = [dict() for _ in range(n_e)]      # cost[i][lane]: from being on `lane` (with its link) to the end
        best_link = [dict() for _ in range(n_e)]
        for i in range(n_e - 1, -1, -1):
            for ln, lk in links[i].items():
                if i == n_e - 1:
                    cost[i][ln], best_link[i][ln] = 0.0, lk[0]
                    continue
                bc, bl = INF, lk[0]
                for target in lk:
                    c = self._enter_cost(target[0], cost[i + 1], lengths[i + 1], change_cost)
                    if c < bc:
                        bc, bl = c, target
                cost[i][ln], best_link[i][ln] = bc, bl

        def choose(i, entry_lane):
            """Lane to be on at edge i arriving on entry_lane: fewest (weighted) changes to the end."""
            best, bc = None, INF
            for ln in links[i]:
                c = (change_cost(entry_lane, ln, lengths[i]) if entry_lane else 0.0) + cost[i][ln]
                if c < bc - 1e-9 or (abs(c - bc) <= 1e-9 and best is not None and idx(ln) < idx(best)):
                    best, bc = ln, c
            return best

        entry = start_lane if start_lane and start_lane.rsplit("_", 1)[0] == self.edges[0] else None
        if entry is None:
            entry = choose(0, None)
        plan = []
        change_specs = []          # (edge, from lane, to lane, their shapes) of each lane change
        stop_marks = []            # (point index in the unfiltered list, plan entry, internal length)
        n_pts = 0
        yield
        for i, e in enumerate(self.edges):
            if i and i % BUILD_PIECE == 0:
                yield
            want = choose(i, entry)
            to_lane, via, st = best_link[i][want]
            plan.append((want, to_lane, via, st))
            shape_in = np.array(sim.lane.getShape(entry))
            shape_want = np.array(sim.lane.getShape(want))
            if i == 0 and start_pos > 0:
                shape_in = self._cut_from(shape_in, start_pos)
                shape_want = self._cut_from(shape_want, start_pos)
            if entry != want and len(shape_in) >= 2 and len(shape_want) >= 2:
                # (on an edge too short to blend on, the lane in, and the step to the lane
                # changed into eased over the path after it: _ease_jumps)
                short = float(np.sum(np.hypot(*np.diff(shape_want, axis=0).T))) < BLEND_MIN_M
                seg = shape_in if short and i + 1 < n_e else self._blend(shape_in, shape_want)
                change_specs.append((e, entry, want, shape_in, shape_want))
            else:
                seg = shape_want
            seg = _resample(seg, self.STEP)
            last_start = n_pts
            pts.append(seg)
            lanes.extend([(want, e)] * len(seg))
            n_pts += len(seg)
            if plan[i][1] is not None:
                end_index = n_pts - 1
                # internal (junction) lanes SUMO uses for this link
                internal = 0.0
                for via in _via_lanes(sim, plan[i][2]):
                    vs = _resample(np.array(sim.lane.getShape(via)), self.STEP)
                    internal += float(sim.lane.getLength(via))
                    pts.append(vs)
                    lanes.extend([(via, via.rsplit("_", 1)[0])] * len(vs))
                    n_pts += len(vs)
                stop_marks.append((end_index, plan[i], internal))
                entry = plan[i][1]
        yield
        P = _ease_jumps(np.vstack(pts))
        if lead_in is not None and len(lead_in):
            # (a continuation: its start knows where the path came from. Without, a zig-zag
            # through overlapping junctions right at the join stayed in the path, 2.2 m back,
            # and the car, at Helsinki's junction 142054948, read 1.8 m off it)
            L = np.asarray(lead_in, dtype=float).reshape(-1, 2)
            keep = _forward_points(np.vstack([L, P]))[len(L):]
            if not keep.any():
                keep[0] = True
        else:
            keep = _forward_points(P)
        new_index = np.maximum(np.cumsum(keep) - 1, 0)     # (a point dropped at the start: the first kept)
        self._set_geometry(P[keep], [lanes[k] for k in np.nonzero(keep)[0]], sim)
        yield
        self._set_changes(change_specs)
        # stop lines and crossings
        self.stops: list[StopLine] = []
        for at, (ln, to_lane, via, st), internal in stop_marks:
            j = int(new_index[at])
            jun = junction_of(via) if via else ""
            self.stops.append(StopLine(s=float(self.s[j]), lane=ln, to_lane=to_lane, via=via or "", junction=jun,
                                       tls=(st or "") in TLS_STATES, initial_state=st or "", internal_length=internal))
        yield
        self.crossings: list[CrossingOnPath] = yield from self._find_crossings(sim)
        self.last_lane = plan[-1][0]                       # the lane the path ends on
        self.last_edge_start = int(new_index[last_start])  # index where the last edge begins

    def _set_geometry(self, xy: np.ndarray, lane_of: list, sim, limits: dict | None = None):
        self._seg_d2 = {}               # comes_within's distances, per key
        keep = np.ones(len(xy), dtype=bool)
        keep[1:] = np.hypot(*np.diff(xy, axis=0).T) > 1e-3
        self.xy = xy[keep]
        self.lane_of = [lane_of[k] for k in np.nonzero(keep)[0]]
        # runs of points on one lane (lanes_between looks them up instead of every point)
        starts = [k for k in range(len(self.lane_of)) if k == 0 or self.lane_of[k][0] != self.lane_of[k - 1][0]]
        self._run_starts = np.array(starts, dtype=int)
        self._run_lanes = [self.lane_of[k][0] for k in starts]
        d = np.hypot(*np.diff(self.xy, axis=0).T)
        self.s = np.concatenate([[0.0], np.cumsum(d)])
        self.length = float(self.s[-1])
        h = np.arctan2(*np.diff(self.xy, axis=0).T[::-1])
        self.heading = np.concatenate([h, h[-1:]]) if len(h) else np.zeros(len(self.xy))
        dh = np.angle(np.exp(1j * np.diff(self.heading)))
        ds = np.maximum(d, 1e-6)
        k = dh / ds
        self.curvature = np.concatenate([k, k[-1:]]) if len(k) else np.zeros(len(self.xy))
        self.curvature_smooth = self._smooth_curvature()
        # speed limits of the lanes
        limits = dict(limits or {})
        for lane, _ in set(self.lane_of):
            if lane in limits:
                continue
            try:
                limits[lane] = float(sim.lane.getMaxSpeed(lane))
            except Exception:
                limits[lane] = 50.0
        self._limits = limits
        self.max_speed = np.array([limits[lane] for lane, _ in self.lane_of])
        return keep

    def lead_in(self) -> tuple:
        """The points before the path's last edge that a continuation (:meth:`extended`) is
        built after: ``lead_in`` of its tail, as plain tuples (sent to SUMO's worker, part of
        a prepared extension's key)."""
        i1 = self.last_edge_start
        return tuple((float(x), float(y)) for x, y in self.xy[max(0, i1 - LEAD_IN_POINTS):i1])

    def extended(self, sim, edges: list[str], keep_m: float = 300.0, tail: "LanePath | None" = None) -> "LanePath":
        """This path continued along ``edges`` (``edges[0]`` is this path's last edge): the
        geometry before the last edge is kept as it is (the car is on it, perhaps halfway
        through a lane change), up to ``keep_m`` metres of it; the last edge is re-planned for
        the continuation. Arc lengths start again from 0 at the first kept point. ``tail``:
        ``LanePath(sim, edges, start_lane=self.last_lane)`` built already (where SUMO runs:
        ``SumoTraffic.random_extension_path``)."""
        if not edges or edges[0] != self.edges[-1]:
            raise ValueError("an extension must start on the path's last edge")
        from dataclasses import replace

        if tail is None or list(tail.edges[:1]) != [edges[0]]:
            tail = LanePath(sim, edges, start_lane=self.last_lane, lead_in=self.lead_in())
        i1 = self.last_edge_start
        i0 = int(np.searchsorted(self.s, self.s[i1] - keep_m)) if i1 > 0 else 0
        i0 = min(i0, i1)
        cut = float(self.s[i0])
        new = object.__new__(LanePath)
        kept_edges = []
        for _, e in self.lane_of[i0:i1]:
            if not e.startswith(":") and (not kept_edges or kept_edges[-1] != e):
                kept_edges.append(e)
        new.edges = kept_edges + tail.edges
        xy = np.vstack([self.xy[i0:i1], tail.xy])
        new._set_geometry(xy, self.lane_of[i0:i1] + tail.lane_of, sim, limits={**self._limits, **tail._limits})
        s_join = float(new.s[i1 - i0]) if i1 - i0 < len(new.s) else new.length
        new.stops = [replace(st, s=st.s - cut) for st in self.stops if cut - 1e-6 <= st.s < self.s[i1] - 1e-6] + \
            [replace(st, s=st.s + s_join) for st in tail.stops]
        new.crossings = [replace(c, s=c.s - cut) for c in self.crossings if cut - 1e-6 <= c.s < self.s[i1] - 1e-6]
        new.crossings += [replace(c, s=c.s + s_join) for c in tail.crossings
                          if all(c.lane != o.lane or abs(c.s + s_join - o.s) > 5.0 for o in new.crossings)]
        new.last_lane = tail.last_lane
        new.last_edge_start = (i1 - i0) + tail.last_edge_start
        # the lane changes of the kept part (the last edge's is planned again with the tail)
        kept = [c for c in self.changes if c.i0 < i1 and c.i1 > i0]
        specs = [sp for sp in self._change_specs if any(sp[:3] == c.key for c in kept)]
        new._set_changes(specs + list(tail._change_specs))
        return new

    # --- lane changes, and holding back from one ------------------------------------------
    # The path blends from lane to lane over the middle of an edge. The driver may hold back
    # (``set_hold``): it then follows the lane it came in on, ``hold`` (0..1) of the way back
    # from the path to it, until the lane changed into has room (``Autopilot._lane_change``).
    # ``aim_at`` (the steering's look-ahead point), ``project`` and ``project_many`` (their
    # lateral offsets: the corridor, the lidar's, the telemetry's) follow the line driven.
    changes: tuple = ()
    _change_specs: tuple = ()
    hold = 0.0
    _held = None                   # the LaneChange held back from
    _project_memo = None           # project()'s last question and answer
    HOLD_TAIL = 30                 # points past the edge's end the held shift still applies

    def _set_changes(self, specs) -> None:
        """The :class:`LaneChange` of each (edge, from lane, to lane, from shape, to shape),
        found in order on the path's points of that edge (labelled with the lane changed into)."""
        self._change_specs = tuple(specs)
        self.changes = []
        self.hold, self._held = 0.0, None
        runs = list(self._run_starts) + [len(self.xy)]
        cursor = 0
        for edge, a, b, shape_a, shape_b in specs:
            for r in range(cursor, len(self._run_lanes)):
                k0, k1 = int(runs[r]), int(runs[r + 1])
                if self._run_lanes[r] == b and self.lane_of[k0][1] == edge:
                    cursor = r + 1
                    break
            else:
                continue
            pts = self.xy[k0:k1]
            if len(pts) < 2:
                continue
            h = self.heading[k0:k1]
            nx, ny = -np.sin(h), np.cos(h)

            def onto(shape):
                P = np.asarray(shape, dtype=float)[:-1, :2]
                V = np.asarray(shape, dtype=float)[1:, :2] - P
                t, _, _, ex, ey, _ = _onto_segments(P, V, pts[:, 0:1], pts[:, 1:2])
                j = np.argmin(ex * ex + ey * ey, axis=1)
                r_ = np.arange(len(pts))
                return np.stack([-ex[r_, j], -ey[r_, j]], axis=1)      # from the point to the lane

            to_a, to_b = onto(shape_a), onto(shape_b)
            src_lat = to_a[:, 0] * nx + to_a[:, 1] * ny
            tgt_lat = to_b[:, 0] * nx + to_b[:, 1] * ny
            moved = np.flatnonzero(np.abs(src_lat) > 0.05)
            arrived = np.flatnonzero(np.abs(tgt_lat) < 0.05)
            s0 = float(self.s[k0 + moved[0]]) if len(moved) else float(self.s[k1 - 1])
            after = arrived[arrived >= (moved[0] if len(moved) else 0)]
            s1 = float(self.s[k0 + after[0]]) if len(after) else float(self.s[k1 - 1])
            self.changes.append(LaneChange(edge, a, b, k0, k1, s0, s1, float(self.s[k1 - 1]), to_a, src_lat, tgt_lat))

    def set_hold(self, change: LaneChange | None, hold: float) -> None:
        """Hold back ``hold`` (0..1) of the way to the lane ``change`` comes from (module doc)."""
        if change is None or hold <= 0.0:
            self.hold, self._held = 0.0, None
        else:
            self.hold, self._held = min(1.0, float(hold)), change

    def held_lat(self, idx):
        """The held line's lateral offset from the path (left +) at point index (or indices) idx."""
        c = self._held
        if c is None:
            return np.zeros(np.shape(idx)) if np.ndim(idx) else 0.0
        j = np.asarray(idx) - c.i0
        inside = (j >= 0) & (j < len(c.src_lat) + self.HOLD_TAIL)
        val = self.hold * c.src_lat[np.clip(j, 0, len(c.src_lat) - 1)] * inside
        return val if np.ndim(idx) else float(val)

    def aim_at(self, s: float) -> np.ndarray:
        """The point the car steers for at arc length s: the path's, or the held line's."""
        p = self.point_at(s)
        c = self._held
        if c is not None:
            j = self.index_at(s) - c.i0
            if 0 <= j < len(c.src_lat) + self.HOLD_TAIL:
                p = p + self.hold * c.shift[min(j, len(c.shift) - 1)]
        return p

    def driven_lane(self, k: int) -> str:
        """The lane the car drives on at point k: the path's, or the lane held to."""
        c = self._held
        if c is not None and self.hold >= 0.5 and c.i0 <= k < c.i1 + self.HOLD_TAIL \
                and self.lane_of[k][0] == c.to_lane:
            return c.from_lane
        return self.lane_of[k][0]

    def _stay_in_start_lane(self, sim, start_lane, start_pos, min_change_m: float = 40.0):
        """A route that needs another lane than the car's within a few metres (a start or a
        re-plan at a stop line, in a turning lane) would be a sideways jump: follow one of the
        start lane's own links instead and route from there to the same destination."""
        edges = self.edges
        if not start_lane or len(edges) < 2 or start_lane.rsplit("_", 1)[0] != edges[0]:
            return
        try:
            links = _links(sim, start_lane)
            remaining = float(sim.lane.getLength(start_lane)) - float(start_pos)
        except Exception:
            return
        if remaining >= min_change_m or any(l[0].rsplit("_", 1)[0] == edges[1] for l in links):
            return
        order = {"s": 0, "r": 1, "l": 2, "R": 1, "L": 2}
        for link in sorted(links, key=lambda l: order.get(l[6], 3)):
            if link[6] == "t" or not _lane_allows(sim, link[0]):
                continue
            first = link[0].rsplit("_", 1)[0]
            alt = [first] if first == edges[-1] else route_without_turnarounds(sim, first, edges[-1])
            if alt:
                self.detours.append((edges[0], edges[1], len(alt)))
                self.edges = [edges[0]] + alt
                return

    @staticmethod
    def _enter_cost(lane, cost_next: dict, length: float, change_cost) -> float:
        """Cost of arriving on `lane` of the next edge: changes to its best lane, plus that
        lane's cost onwards."""
        if not cost_next:
            return 0.0
        return min(change_cost(lane, ln, length) + c for ln, c in cost_next.items())

    def _smooth_curvature(self, half: float = 3.0) -> np.ndarray:
        """Curvature from the heading change over +-half metres (robust to kinks between
        SUMO's lane pieces)."""
        n = len(self.xy)
        if n < 3:
            return np.zeros(n)
        lo = np.searchsorted(self.s, self.s - half)
        hi = np.minimum(np.searchsorted(self.s, self.s + half, side="right") - 1, n - 1)
        lo = np.minimum(lo, n - 2)
        hi = np.maximum(hi, lo + 1)
        # heading unwrapped along the path
        hu = np.unwrap(self.heading)
        return (hu[hi] - hu[lo]) / np.maximum(self.s[hi] - self.s[lo], 1e-6)

    def _find_crossings(self, sim):
        """The crossings the path goes over (a generator, as ``build_steps``: its value)."""
        out = []
        span: dict = {}            # junction lane -> (first, last) index of its path points
        for i, (lane, _) in enumerate(self.lane_of):
            if lane.startswith(":"):
                span[lane] = (span[lane][0], i) if lane in span else (i, i)
        for n, (lane, (i0, i1)) in enumerate(span.items()):
            if n and n % BUILD_PIECE == 0:
                yield
            try:
                foes = sim.lane.getInternalFoes(lane)
            except Exception:
                continue
            for foe in foes:
                m = CROSSING_RE.match(foe)
                if not m or any(c.lane == foe for c in out):
                    continue
                shape = np.array(sim.lane.getShape(foe))
                if len(shape) < 2:
                    continue
                # where the path meets the crossing (search around this junction lane)
                a0 = max(0, i0 - 25)
                a1 = min(len(self.xy) - 1, i1 + 25)
                hit = _first_crossing(self.xy[a0:a1 + 1], shape) if a1 > a0 else None
                if hit is None:
                    continue
                a = a0 + hit[0]
                s_hit = float(self.s[a] + hit[1] * (self.s[a + 1] - self.s[a]))
                out.append(CrossingOnPath(s=s_hit, edge=foe.rsplit("_", 1)[0], lane=foe,
                                          width=float(sim.lane.getWidth(foe)), junction=m.group(1), shape=shape))
        out.sort(key=lambda c: c.s)
        return out

    @staticmethod
    def _cut_from(P, pos):
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
        if pos >= d[-1]:
            return P[-2:]
        k = int(np.searchsorted(d, pos))
        t = (pos - d[k - 1]) / max(d[k] - d[k - 1], 1e-9) if k > 0 else 0.0
        first = P[k - 1] + t * (P[k] - P[k - 1]) if k > 0 else P[0]
        return np.vstack([first, P[k:]])

    @staticmethod
    def _blend(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Move from lane a to lane b along one edge: a smooth (cosine) lateral blend over the
        middle of the edge, at most 60 m long."""
        n = 100
        fa = _resample(a, max(1e-3, np.sum(np.hypot(*np.diff(a, axis=0).T)) / (n - 1)))[:n]
        fb = _resample(b, max(1e-3, np.sum(np.hypot(*np.diff(b, axis=0).T)) / (n - 1)))[:n]
        m = min(len(fa), len(fb))
        fa, fb = fa[:m], fb[:m]
        L = float(np.sum(np.hypot(*np.diff(fb, axis=0).T)))
        t = np.linspace(0, 1, m)
        span = min(0.8, 60.0 / max(L, 1.0))
        t0 = 0.5 - span / 2
        w = np.clip((t - t0) / span, 0, 1)
        w = 0.5 - 0.5 * np.cos(np.pi * w)
        return fa * (1 - w)[:, None] + fb * w[:, None]

    def project(self, x: float, y: float, hint: int = 0, window: int = 400) -> tuple[int, float, float]:
        """Closest path index near `hint`, arc length there, signed lateral offset (left +).

        The last answer is kept: the loop projects the car's state at the end of a frame and
        again, unchanged, at the start of the next."""
        memo = self._project_memo
        if memo is not None and memo[0] == x and memo[1] == y and memo[2] == hint and memo[3] == window \
                and memo[4] is self.xy and memo[5] is self._held and memo[6] == self.hold:
            return memo[7]
        out = self._project(x, y, hint, window)
        self._project_memo = (x, y, hint, window, self.xy, self._held, self.hold, out)
        return out

    def _project(self, x: float, y: float, hint: int, window: int) -> tuple[int, float, float]:
        lo = max(0, hint - 20)
        hi = min(len(self.xy), hint + window)
        if hi - lo < 2:
            return (lo, float(self.s[lo]), math.hypot(x - self.xy[lo, 0], y - self.xy[lo, 1]))
        P = self.xy[lo:hi - 1]
        V = self.xy[lo + 1:hi] - P
        t, dx, dy, ex, ey, L2 = _onto_segments(P, V, x, y)
        d2 = ex * ex + ey * ey                  # to each segment (not its first point: the
        # points of a pass can lie 2 m from the car beside a segment of it, where another
        # pass has a point 0.7 m away; a Kouvola route passing a junction twice jumped 325 m)
        # where the path passes the point more than once (a loop, a junction crossed twice),
        # take the pass nearest the hint, then descend to its local minimum
        dmin = math.sqrt(float(d2.min()))
        cand = np.nonzero(d2 <= (dmin + 1.5) ** 2)[0]
        j = int(cand[np.argmin(np.abs(cand + lo - hint))])
        while j + 1 < len(d2) and d2[j + 1] < d2[j]:
            j += 1
        while j > 0 and d2[j - 1] < d2[j]:
            j -= 1
        a = lo + j
        side = V[j, 0] * dy[j] - V[j, 1] * dx[j]
        off = math.copysign(math.sqrt(float(d2[j])), side)
        if self._held is not None:
            off -= self.held_lat(a)
        return (a, float(self.s[a] + t[j] * math.sqrt(float(L2[j]))), off)

    def last_run(self, edge: str) -> tuple[int, int] | None:
        """The points (i0, i1) of the path's last pass along ``edge`` (the goal's road: a route
        that comes back to the road it starts on passes it twice), or None."""
        k = len(self.lane_of) - 1
        while k >= 0 and self.lane_of[k][1] != edge:
            k -= 1
        if k < 0:
            return None
        i1 = k + 1
        while k > 0 and self.lane_of[k - 1][1] == edge:
            k -= 1
        return k, i1

    def _part(self, s0: float, s1: float) -> tuple[int, int]:
        """The points i0 .. i1 - 1 whose segments cover arc lengths s0 to s1 (project_many's,
        comes_within's)."""
        return (max(0, int(self.s.searchsorted(s0)) - 1),
                min(len(self.xy), int(self.s.searchsorted(s1, side="right")) + 1))

    def project_many(self, x: np.ndarray, y: np.ndarray, s0: float, s1: float) -> tuple[np.ndarray, np.ndarray]:
        """Arc length and signed lateral offset (left +) of many points, each projected onto the
        part of the path between arc lengths s0 and s1 (vectorised). Points that project onto
        that part's ends get the end's s (and their true distance as offset)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        i0, i1 = self._part(s0, s1)
        if len(x) == 0 or i1 - i0 < 2:
            return np.full(len(x), np.nan), np.full(len(x), np.inf)
        P = self.xy[i0:i1 - 1]
        V = self.xy[i0 + 1:i1] - P
        t, dx, dy, cx, cy, L2 = _onto_segments(P, V, x[:, None], y[:, None])
        d2 = cx ** 2 + cy ** 2
        j = d2.argmin(axis=1)
        r = np.arange(len(x))
        side = V[j, 0] * dy[r, j] - V[j, 1] * dx[r, j]
        off = np.sqrt(d2[r, j]) * np.where(side >= 0, 1.0, -1.0)
        s = self.s[i0 + j] + t[r, j] * np.sqrt(L2[j])
        if self._held is not None:
            off = off - self.held_lat(i0 + j)
        return s, off

    def comes_within(self, key, P: np.ndarray, s0: float, s1: float, reach: float) -> bool:
        """Does any of the points ``P`` (n, 2) come within ``reach`` of the part of the path
        between arc lengths s0 and s1? Exactly when ``project_many`` would give one of them an
        offset under ``reach`` (outside a held lane change: see ``held_lat``). The points'
        nearest distance to each segment of the whole path is computed once per ``key`` and
        points array, so that a lane checked frame after frame costs a slice. While
        a lane change is held back, True (offsets are then from the held line)."""
        if self._held is not None:
            return True
        got = self._seg_d2.get(key)
        if got is not None and got[0] is P:
            d2 = got[1]
        else:
            A = self.xy[:-1]
            Pf = np.asarray(P, dtype=float)
            _, _, _, cx, cy, _ = _onto_segments(A, self.xy[1:] - A, Pf[:, 0][:, None], Pf[:, 1][:, None])
            d2 = (cx ** 2 + cy ** 2).min(axis=0) if len(Pf) else np.full(len(A), np.inf)
            self._seg_d2[key] = (P, d2)       # (for these very points: another array is measured anew)
        i0, i1 = self._part(s0, s1)
        if i1 - i0 < 2:
            return False
        return bool(math.sqrt(float(d2[i0:i1 - 1].min())) < reach)

    def index_at(self, s: float) -> int:
        return min(max(int(self.s.searchsorted(s, side="right")) - 1, 0), len(self.s) - 1)

    def point_at(self, s: float) -> np.ndarray:
        s = min(max(s, 0.0), self.length)
        return np.array([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])])

    def heading_at(self, s: float) -> float:
        return float(self.heading[self.index_at(s)])

    def lanes_between(self, s0: float, s1: float) -> set:
        """The lanes of the path's points from arc length s0 to s1."""
        i0, i1 = self.index_at(s0), self.index_at(s1)
        if i1 < i0:
            return set()
        r0, r1 = (self._run_starts.searchsorted((i0, i1), side="right") - 1).tolist()
        return set(self._run_lanes[r0:r1 + 1])

    def max_curvature(self, s0: float, s1: float) -> float:
        m = (self.s >= s0) & (self.s <= s1)
        if not m.any():
            return 0.0
        return float(np.abs(self.curvature_smooth[m]).max())


class PurePursuit:
    """Steering towards a look-ahead point: curvature = 2 sin(alpha) / Ld, from the rear axle.

    ``cosim.vehicle``'s steering command is the rear-axle path curvature as a fraction of the
    tightest one, so the command is ``kappa / kappa_max``. The look-ahead grows with speed
    (``k_ld`` s plus ``k_ld2`` s per m/s) between ``ld_min`` and ``ld_max``.

    Given the car's ``velocity`` and ``yaw_rate``, the angle to the look-ahead point is taken
    from the rear axle's direction of travel rather than from the heading: in a curve the
    rear tyres' slip angle (``a_lat / (CORNERING_STIFFNESS g)``, 0.02 rad at 3 m/s2) turns
    it outwards, and steering by the heading alone held a 50 m curve 0.15 m wide at 12 m/s.
    ``tau`` (s, default 0) aims from the pose the car reaches in that time instead."""

    def __init__(self, wheelbase: float, max_curvature: float, k_ld: float = 0.9, ld_min: float = 4.0,
                 ld_max: float = 25.0, rear_axle: float | None = None, tau: float = 0.0, k_ld2: float = 0.0):
        self.wheelbase = wheelbase
        self.tau = tau
        self.k_ld2 = k_ld2
        self.kmax = max_curvature
        self.k_ld, self.ld_min, self.ld_max = k_ld, ld_min, ld_max
        self.rear = wheelbase / 2.0 if rear_axle is None else rear_axle   # centre -> rear axle

    def lookahead(self, speed: float) -> float:
        """The look-ahead distance (m) at ``speed``."""
        return min(self.ld_max, max(self.ld_min, self.k_ld * abs(speed) + self.k_ld2 * speed * speed))

    def steer(self, path: LanePath, x, y, yaw, speed, s_here, velocity=None, yaw_rate: float = 0.0,
              tau: float | None = None) -> tuple[float, float]:
        c, s = math.cos(yaw), math.sin(yaw)
        rx, ry = x - self.rear * c, y - self.rear * s
        heading = yaw
        ld = self.lookahead(speed)
        # the look-ahead point: ld from the rear axle, measured along the path from its projection
        s_rear = s_here - self.rear
        if velocity is not None and speed > 1.0:
            # the rear axle moves along its velocity, which the tyres' slip angle turns
            # outwards from the heading in a curve (0.02 rad at 3 m/s2)
            rvx, rvy = velocity[0] + yaw_rate * self.rear * s, velocity[1] - yaw_rate * self.rear * c
            if math.hypot(rvx, rvy) > 1.0:
                course = math.atan2(rvy, rvx)
                if abs(math.remainder(course - yaw, 2 * math.pi)) < 0.2:
                    heading = course
            # where the car will be when this command takes effect: the steering turns at a
            # limited rate, so aim from the pose tau seconds on, at the present curvature
            tau = self.tau if tau is None else tau
            if tau > 0.0:
                ds = speed * tau
                dpsi = ds * yaw_rate / speed
                rx += ds * math.cos(heading + 0.5 * dpsi)
                ry += ds * math.sin(heading + 0.5 * dpsi)
                heading += dpsi
                s_rear += ds
        tx, ty = path.aim_at(s_rear + ld)
        dist = math.hypot(tx - rx, ty - ry)
        if dist < 1e-3:
            return 0.0, 0.0
        alpha = math.atan2(ty - ry, tx - rx) - heading
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        kappa = 2.0 * math.sin(alpha) / dist
        return max(-1.0, min(1.0, kappa / self.kmax)), kappa


class SpeedController:
    """Target speed -> (throttle, brake) through the car's longitudinal force model plus PI.

    The wanted acceleration ``a = a_ff + kp e + ki integral(e)`` (clipped to ``a_min..a_max``)
    becomes a wheel force ``F = m a + m g sin(grade) + Crr m g cos(grade) + drag``; a positive
    force is throttle (the fraction of the drivetrain's torque / power limit at this speed), a
    negative one brake (the fraction of the brakes' force). The grade comes from the chassis'
    pitch; the integral absorbs what the model misses (suspension pitch, tyre losses, bumps).
    """

    def __init__(self, kp: float = 1.5, ki: float = 0.5, a_max: float = 2.0, a_min: float = -7.0,
                 i_max: float = 1.0, i_band: float = 0.7, a_up: float = 1.8):
        from . import vehicle as V

        self.kp, self.ki, self.a_max, self.a_min, self.i_max = kp, ki, a_max, a_min, i_max
        self.i_band = i_band
        self.mass = V.MASS
        self.g = V.GRAVITY
        self.crr = V.ROLLING_RESISTANCE
        self.drag = 0.5 * V.AIR_DENSITY * V.DRAG_AREA
        self.r = V.WHEEL_RADIUS
        self.t_max = V.MAX_WHEEL_TORQUE
        self.p_max = V.MAX_POWER
        self.brake_force = V.MAX_BRAKE_TORQUE / V.WHEEL_RADIUS
        self.i = 0.0
        self.last_accel = 0.0
        self.v_ref = None
        self.a_up = a_up

    def reset(self):
        self.i = 0.0
        self.v_ref = None

    def drive_force_max(self, v: float) -> float:
        return min(self.t_max, self.p_max * self.r / max(abs(v), 1e-3)) / self.r

    def force_to_pedals(self, F: float, v: float) -> tuple[float, float]:
        if F >= 0.0:
            return min(1.0, max(1e-4, F / self.drive_force_max(v))), 0.0
        return 0.0, min(1.0, -F / self.brake_force)

    def control(self, v_target: float, v: float, dt: float, pitch: float = 0.0,
                a_ff: float = 0.0) -> tuple[float, float]:
        """Pedals for one step. ``pitch`` is the road's pitch under the car (rad, > 0 nose
        down); ``a_ff`` a planned deceleration (<= 0) to follow, if any."""
        if v_target <= 0.05 and v < 0.5:
            self.i = 0.0
            self.v_ref = None
            self.last_accel = 0.0
            return 0.0, 1.0
        # a reference speed that ramps up at a_up (the controller tracks it without overshoot)
        # and follows the planner's target straight down
        if self.v_ref is None or abs(self.v_ref - v) > 1.5:
            self.v_ref = v
        steady = False
        if v_target > self.v_ref:
            # ramp at a_up, easing off over the last a_up * 0.5 s of it
            a_ref = self.a_up * min(1.0, (v_target - self.v_ref) / (self.a_up * 0.5))
            self.v_ref = min(v_target, self.v_ref + a_ref * dt)
        else:
            steady = a_ff == 0.0 and self.v_ref - v_target < 0.05
            self.v_ref = v_target
            a_ref = min(0.0, a_ff)
        e = self.v_ref - v
        a = a_ref + self.kp * e + self.i
        a_clip = min(self.a_max, max(self.a_min, a))
        # integrate only on a steady reference, near it and when not saturated (no wind-up in
        # transients: the model's feed-forward carries those)
        if steady and abs(e) < self.i_band and (a == a_clip or (a > a_clip and e < 0) or (a < a_clip and e > 0)):
            self.i = max(-self.i_max, min(self.i_max, self.i + self.ki * e * dt))
        self.last_accel = a_clip
        grade = -pitch                     # pitch > 0 is nose down (cosim.vehicle convention)
        m, g = self.mass, self.g
        F = m * a_clip + m * g * math.sin(grade) + self.crr * m * g * math.cos(grade) \
            + self.drag * v * (1.0 + abs(v)) * (1.0 if v >= 0 else -1.0)
        if a_clip < 0 and v < 0.3 and F < 0:
            return 0.0, min(1.0, max(0.3, -F / self.brake_force))
        return self.force_to_pedals(F, v)


def curve_speed(kappa: float, a_lat: float = 2.5) -> float:
    """Highest speed for a curvature at a comfortable lateral acceleration."""
    return math.sqrt(a_lat / max(abs(kappa), 1e-6))


def stop_speed(d: float, decel: float = 2.5, tail: float = 0.8) -> float:
    """Speed from which the car stops in ``d`` metres at ``decel``, tapering linearly
    (``tail`` m/s per m) over the last metres so the stop is gentle and precise."""
    if d <= 0.15:
        return 0.0
    return min(math.sqrt(2.0 * decel * d), tail * d + 0.2)


def plan_speed(path: LanePath, s_here: float, v_cap: float, horizon: float, decel: float = 2.0,
               a_lat: float = 2.5, speed_limit: bool = False) -> tuple[float, float]:
    """Highest speed now such that, braking at ``decel``, the car meets every point's limit
    ahead (curvature, and the lane's speed limit when ``speed_limit``) within ``horizon`` m.
    Returns (speed, arc length of the binding point)."""
    i0 = path.index_at(s_here - 1.0)
    i1 = path.index_at(s_here + horizon) + 1
    k = np.abs(path.curvature_smooth[i0:i1])
    v_allow = np.sqrt(a_lat / np.maximum(k, 1e-6))
    v_allow = np.minimum(v_allow, v_cap)
    if speed_limit:
        v_allow = np.minimum(v_allow, path.max_speed[i0:i1])
    d = np.maximum(path.s[i0:i1] - s_here, 0.0)
    v = np.sqrt(v_allow ** 2 + 2.0 * decel * d)
    j = int(np.argmin(v))
    return float(v[j]), float(path.s[i0 + j])
