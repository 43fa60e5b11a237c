"""Road surfaces from the SUMO network's own lane, junction and crossing shapes.

Positions, widths and connections are exactly SUMO's: each lane is a strip around its SUMO
centreline, each junction its SUMO polygon, each walking area and crossing its SUMO shape.
Heights follow the ground: every edge gets one height profile along its middle lane, sampled
from the natural terrain, and all its lanes take their height from that profile (its other
vehicle lanes where they project onto it, its sidewalks between where their ends project), so
the road is level across its width; the lanes of an edge "-X" take theirs from the profile
of its opposite edge "X" (the same road's other direction) where they project onto it, so the
two directions meet without a step. Before that, the ends of the
edges at each node are put on one plane of at most 7 % grade, the planes' heights solved for
all nodes at once, each edge taking up its ends' moves linearly (:func:`_junction_planes`; the
planes of a register's nodes are kept, so that a streamed window's streets lie where the world
before it had them: ``build_roads(pinned=...)``, :mod:`netgen.build`).
Tunnels (OSM ``tunnel=*``, an edge parameter) are not meshed, nor the junctions where only
tunnels meet (:func:`underground_junctions`). Bridges (``bridge=*``) are decks, straight
between where they meet the ground (:func:`_bridge_decks`), risen over the roads under them
where they can be (:func:`_raise_decks`); their points above the ground hold no terrain up
(:attr:`RoadGeometry.support_hold`). Junctions and walking areas
are triangulated by GEOS's constrained Delaunay triangulation (earcut where a SUMO polygon is
invalid) with a boundary point every ``step`` metres. A junction's and its walking areas'
points blend the heights of the ends of the lanes that meet it (weights 1/d^4: at a lane's end
exactly its height; from all of its junction's lane ends). Crossings are paint (zebra stripes in the marking class), each stripe
corner on the highest surface (lane, junction, walking area) under it. Strips are resampled
every ``step`` metres so the surface follows the terrain between SUMO's (often sparse) points.

Everything is computed on concatenated arrays of all lanes at once (a city has ~10^4 lanes;
per-lane Python would dominate the build).

The carriageway (where vehicles drive: vehicle lanes and junctions) is given as overlapping
polygons, :func:`carriageway_parts`, made on demand from the network alone.

A vehicle lane through a junction whose polygon misses part of it (netconvert's polygon of a
junction on odd geometry can) gets a strip of its own, element ``junction_lane``
(:func:`junction_gaps`). The ground left bare between a lane's square end and a junction
border at an angle to it is meshed with the junction (:func:`_lane_end_gaps`), and a junction
polygon that crosses itself as the polygons of its valid form.

Sidewalk lanes are left out where they lie on another road's vehicle lane or junction
(:func:`_sidewalks_off_other_roads`). A road that overlaps a higher-ranked one without meeting
it at a node (an untagged bridge or tunnel, two carriageways mapped too close) takes that
road's height there, just under it (:func:`_conform_to_higher_roads`).

Mesh classes: ``asphalt`` (vehicle lanes, junctions), ``sidewalk`` (pedestrian-only
lanes and walking areas, 2 cm higher), ``rail`` (train-only tracks) and ``marking`` (lane lines and zebra stripes, visual
only, 1.5 cm above the surface). Each piece keeps its SUMO id and the OSM way ids.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from operator import attrgetter
import types

import mapbox_earcut
import numpy as np
import shapely
from scipy.spatial import cKDTree

SIDEWALK_LIFT = 0.02
MARKING_LIFT = 0.015
MARK_W = 0.12
DASH_ON, DASH_OFF = 3.0, 6.0
#: lanes only trains use are ballast, not asphalt (trams share the street and stay asphalt)
RAIL_CLASSES = frozenset({"rail", "rail_urban", "rail_electric", "rail_fast", "cable_car", "subway"})
_LANE_INDEX = attrgetter("index")
#: spacing of the levelling support points inside junctions (m)
JUNCTION_SUPPORT_STEP = 4.0
#: the steepest grade a junction's plane may have (the edges that meet it take up the rest)
JUNCTION_MAX_GRADE = 0.07
#: an edge's mean grade (end to end) beyond this is a DEM artefact that the planes take out
EDGE_MAX_GRADE = 0.25
#: a junction this share of whose polygon lies inside another's shares its plane (_junction_clusters)
NESTED_JUNCTION_SHARE = 0.9
#: a pinned plane (_junction_planes) is taken by a node whose edge ends' mean is this near it
PIN_MATCH_M = 0.5
OWN_PLANE_REACH_M = 0.5         # _onto_own_plane: an edge's points this near its one plane's junctions lie on it
OWN_PLANE_FADE_M = 5.0          # and further out come back to their own height over this distance
#: passes of a [1 2 1] / 4 filter over each edge's height profile (points about 2.5 m apart;
#: 8 passes: a vertical curve of about 10 m where the ground's grade changes)
PROFILE_SMOOTH_PASSES = 8
#: no road's profile is steeper than this (the DEM's cliffs beside a road become ramps of it;
#: a street this steep is rare, a steeper one a stairway)
MAX_PROFILE_GRADE = 0.25
#: a lane's ends are put on their junction's plane (across the lane's width too), the move
#: fading out over this length (m; at most half the lane)
END_FADE_M = 10.0
#: a road that overlaps a higher-ranked one without a junction takes its height there, fading
#: back to its own over this length (:func:`_conform_to_higher_roads`), and stays this far under it
CONFORM_FADE_M = 15.0
CONFORM_BELOW_M = 0.02
SOFT_STEP_M = 0.15               # (a path drawn into a vehicle lane, this far off its height: left out there)
#: a path drawn into a vehicle lane this far off its height at most takes the lane's height
#: there (build_roads); further off, a footbridge kept on the ground, it is left out there
PATH_CONFORM_MAX_M = 0.5
CONFORM_MAX_M = 1.6             # (further apart than this somewhere: a bridge over a road, both kept)
CONFORM_NODE_CLEAR_M = 15.0    # roads meeting at a node conform only this far beyond its junction
CONFORM_MIN_OVERLAP_M = 1.0     # (of the cross-section inside the other road's lane: a sliver
                                # where two roads' lanes graze near a junction does not count)
#: twin roads (two edges between the same two nodes, not "X" and "-X": a street's one-way
#: halves) conform, on their profiles, wherever a cross-section reaches this far into the
#: other's lane, up to CONFORM_TWIN_NODE_CLEAR_M beyond their nodes' junctions (up to the
#: nodes, they made steps at the junctions)
CONFORM_TWIN_MIN_OVERLAP_M = 0.05
CONFORM_TWIN_NODE_CLEAR_M = 5.0
#: a road that leaves a node beside a higher-ranked one, its lane inside the other's near the
#: node (within CONFORM_NODE_CLEAR_M of its junction), comes down onto it there where it
#: stands at most this much over it, the move fading out along it over FORK_FADE_M
#: (build_roads; Monaco: Rue du Portier, leaving Boulevard du Larvotto at a sharp angle and
#: climbing at 12 %, stood 0.8 m over the boulevard's lane, and a car at 10 m/s stopped dead)
FORK_CONFORM_MAX_M = 2.5
FORK_FADE_M = 25.0
#: a bridge deck's points more than this above the natural ground hold no terrain up (the
#: ground under a bridge stays where it is: a river, a road in a cutting)
DECK_CLEAR_M = 0.5
#: a deck is this far above a vehicle lane that passes under it (a clearance of 4.5 m and the
#: deck), rising to it at DECK_GRADE
DECK_CLEARANCE_M = 5.0
#: a deck that cannot rise to DECK_CLEARANCE_M over the roads under it but to this much less
#: (m) rises as far as it can: 4.1 m under its underside still lets a lorry pass (_raise_decks)
DECK_CLEARANCE_SLACK_M = 0.5
DECK_THICKNESS_M = 0.4          # (its underside, drawn only)
#: a deck this far over a road (m) lets a car pass under it (_lift_viaducts)
DECK_PASSABLE_M = 2.5
#: a deck's lanes that stand at most this far over the lanes of a road they cross (nowhere
#: further: not a bridge over it) come down onto them (build_roads)
DECK_DOWN_MAX_M = 0.5
DECK_GRADE = 0.06
DECK_MAX_GRADE = 0.08
#: a deck put at grade on the junctions it crosses (_decks_onto_junctions) is no steeper than
#: this between them and where it keeps its height (a steep ramp's grade; a short link over a
#: street 1.3 m under it needs 9 %)
DECK_AT_GRADE_MAX_GRADE = 0.12
#: a road stacked under a higher layer's descends from its ends at this grade at most (a car
#: park's ramp), and goes down only where it gets this far under the road over it
#: (:func:`_stack_under_higher_layers`)
STACK_MAX_GRADE = 0.15
STACK_MIN_CLEARANCE_M = 2.5
#: how far a sidewalk may reach into a vehicle lane of another road before that piece of it is
#: left out (m)
SIDEWALK_INTRUSION_M = 0.3


@dataclass
class MeshPart:
    """Many pieces of one class in one vertex/face array; piece k owns faces [fstart[k], fstart[k+1])."""
    kind: str
    vertices: np.ndarray
    faces: np.ndarray
    ids: list                     # SUMO id per piece
    elements: list                # lane | junction | walkingarea | crossing | marking
    osm: list                     # tuple of OSM way ids per piece
    fstart: np.ndarray            # (pieces + 1,)
    centroids: np.ndarray         # (pieces, 2)


@dataclass
class RoadGeometry:
    parts: dict = field(default_factory=dict)      # kind -> list[MeshPart]
    support_pts: np.ndarray = None                 # (n, 3) road surface points for levelling
    support_hw: np.ndarray = None                  # (n,) ground-is-road radius at each point
    support_car: np.ndarray = None                 # (n,) True where cars drive (lanes, junctions)
    support_tris: np.ndarray = None                # (m, 3) the drivable surface's triangles over support_pts
    support_hold: np.ndarray = None                # (n,) False where a bridge's deck is above the ground
    stacked_over: list = field(default_factory=list)   # edges over a road stacked under them (_stack_under_higher_layers)
    planes: dict = field(default_factory=dict)     # node -> (x0, y0, z0, gx, gy): its junction plane
    stats: dict = field(default_factory=dict)
    net: object = None

    @cached_property
    def carriageway_parts(self) -> list:
        """Where vehicles drive, as overlapping polygons (see :func:`carriageway_parts`)."""
        return carriageway_parts(self.net)

    @cached_property
    def carriageway(self):
        """The union of :attr:`carriageway_parts` (about a second on a city: the build's
        scenery uses the parts themselves, :class:`netgen.scenery.PolygonSet`)."""
        parts = [p for p in self.carriageway_parts if p is not None and not p.is_empty]
        return shapely.union_all(parts) if parts else shapely.GeometryCollection()


# ---------------------------------------------------------------------------------------
# vectorised polylines: many polylines as one (N, 2) array plus a group id per point
# ---------------------------------------------------------------------------------------
def _concat(shapes):
    lens = np.array([len(s) for s in shapes], dtype=np.int64)
    P = np.vstack(shapes) if len(shapes) else np.zeros((0, 2))
    gid = np.repeat(np.arange(len(shapes)), lens)
    return P, gid


def resample_many(P, gid, step):
    """Insert points so no segment is longer than `step`; original points kept."""
    same = gid[1:] == gid[:-1]
    seg = P[1:] - P[:-1]
    L = np.hypot(seg[:, 0], seg[:, 1])
    n = np.where(same, np.maximum(1, np.ceil(L / step)).astype(np.int64), 0)
    starts = np.ones(len(P), dtype=bool)
    starts[1:] = ~same
    # each polyline's first point, then for each segment n new points
    counts = np.zeros(len(P), dtype=np.int64)
    counts[starts] += 1
    counts[1:] += n
    total = counts.sum()
    out = np.empty((total, 2))
    ogid = np.empty(total, dtype=np.int64)
    pos = np.cumsum(counts) - counts
    first_idx = np.nonzero(starts)[0]
    out[pos[first_idx]] = P[first_idx]
    ogid[pos[first_idx]] = gid[first_idx]
    seg_idx = np.nonzero(n)[0]
    reps = n[seg_idx]
    k = np.repeat(seg_idx, reps)
    within = np.arange(reps.sum()) - np.repeat(np.cumsum(reps) - reps, reps) + 1
    t = within / np.repeat(reps, reps)
    dst = np.repeat(pos[seg_idx + 1] + (starts[seg_idx + 1].astype(np.int64)), reps) + within - 1
    out[dst] = P[k] + t[:, None] * seg[k]
    ogid[dst] = gid[k]
    return out, ogid


def _arclen(P, gid):
    d = np.zeros(len(P))
    same = gid[1:] == gid[:-1]
    d[1:] = np.where(same, np.hypot(*(P[1:] - P[:-1]).T), 0.0)
    c = np.cumsum(d)
    first = np.ones(len(P), dtype=bool)
    first[1:] = ~same
    base = np.maximum.accumulate(np.where(first, c, 0.0))
    s = c - base
    total = np.zeros(gid.max() + 1 if len(gid) else 0)
    np.maximum.at(total, gid, s)
    return s, total


def _normals_many(P, gid):
    """Unit left normals (mitred at bends, bounded) of many polylines."""
    n = len(P)
    same_next = np.zeros(n, dtype=bool)
    same_next[:-1] = gid[1:] == gid[:-1]
    same_prev = np.zeros(n, dtype=bool)
    same_prev[1:] = same_next[:-1]
    d = np.zeros((n, 2))
    d[:-1] = P[1:] - P[:-1]
    L = np.hypot(d[:, 0], d[:, 1])
    L[L == 0] = 1.0
    d = d / L[:, None]
    d[~same_next] = 0.0                      # segment direction from point i to i+1
    prev = np.zeros((n, 2))
    prev[1:] = d[:-1]
    prev[~same_prev] = 0.0
    t = d + prev
    tl = np.hypot(t[:, 0], t[:, 1])
    tl[tl < 1e-9] = 1.0
    t = t / tl[:, None]
    nrm = np.column_stack([-t[:, 1], t[:, 0]])
    segn = np.column_stack([-d[:, 1], d[:, 0]])
    cos = np.where(same_next & same_prev, np.einsum("ij,ij->i", nrm, segn), 1.0)
    return nrm / np.clip(cos, 0.5, 1.0)[:, None]


def _strips(C, gid, z, halfw, lift=0.0, seg_mask=None, tilt=None):
    """Triangle strips around many centrelines (`tilt`: height gained per metre to the left,
    per point). Returns vertices, faces, face group ids."""
    nrm = _normals_many(C, gid) * halfw[:, None]
    v = np.empty((2 * len(C), 3))
    v[0::2, :2] = C + nrm
    v[1::2, :2] = C - nrm
    dz = 0.0 if tilt is None else tilt * np.hypot(nrm[:, 0], nrm[:, 1])
    v[0::2, 2] = z + lift + dz
    v[1::2, 2] = z + lift - dz
    ok = gid[1:] == gid[:-1]
    if seg_mask is not None:
        ok &= seg_mask
    i = np.nonzero(ok)[0] * 2
    f = np.concatenate([np.column_stack([i, i + 1, i + 2]), np.column_stack([i + 1, i + 3, i + 2])])
    fg = np.concatenate([gid[i // 2], gid[i // 2]])
    order = np.argsort(fg, kind="stable")
    return v, f[order], fg[order]


def _top_surface_z(xy, parts, cell: float = 8.0, lowest: bool = False):
    """Height of the highest triangle of `parts` (MeshParts) over each point of `xy` (n, 2)
    (with `lowest`, of the lowest); NaN where there is none."""
    top = np.full(len(xy), np.inf if lowest else -np.inf)
    if not len(xy):
        return np.full(0, np.nan)
    # only the triangles that can hold a point: with a corner in a cell next to one of a
    # point's, or spanning more than a cell (one that holds a point and spans less has its
    # corners within a cell of it; one whose corners' cells are 2 or more apart spans more).
    # The cells near the points are a grid of flags over the points' extent (a lookup per
    # corner: Helsinki's zebra crossings, 25,000 corners over 180,000 road faces, took 110 ms
    # with sorted cell keys)
    near = _CellGrid(np.floor(xy / cell).astype(np.int64), margin=1)
    near.flags[near.cells[:, None] + near.around()[None, :]] = True
    T = []
    for p in parts:
        if not len(p.faces):
            continue
        ij = np.floor(p.vertices[:, :2] / cell).astype(np.int64)
        vnear = near.flag_at(ij)
        f = p.faces
        keep = vnear[f[:, 0]] | vnear[f[:, 1]] | vnear[f[:, 2]]
        rest = np.flatnonzero(~keep)
        a, b, c = ij[f[rest, 0]], ij[f[rest, 1]], ij[f[rest, 2]]
        span = np.maximum(np.maximum(a, b), c) - np.minimum(np.minimum(a, b), c)
        keep[rest[(span >= 2).any(axis=1)]] = True
        T.append(p.vertices[f[keep]])
    if not T:
        return np.full(len(xy), np.nan)
    T = np.concatenate(T)                                      # (n, 3, 3)
    a, b, c = T[:, 0], T[:, 1], T[:, 2]
    det = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
    ok = np.abs(det) > 1e-9
    T, det = T[ok], det[ok]
    if not len(T):
        return np.full(len(xy), np.nan)
    # candidate (point, triangle) pairs: each triangle listed under the cells of a finer grid
    # its bounding box covers, each point looked up in its cell; then the point in the
    # triangle's bounding box (4 numbers a pair), before the triangle itself (10)
    fine = cell / 2.0
    bmin = np.minimum(np.minimum(T[:, 0, :2], T[:, 1, :2]), T[:, 2, :2])
    bmax = np.maximum(np.maximum(T[:, 0, :2], T[:, 1, :2]), T[:, 2, :2])
    pi, ti = _CellGrid(np.floor(xy / fine).astype(np.int64)).pairs(np.floor(bmin / fine).astype(np.int64),
                                                                    np.floor(bmax / fine).astype(np.int64))
    x, y = xy[pi, 0], xy[pi, 1]
    eps = 1e-6
    inb = (x >= bmin[ti, 0] - eps) & (x <= bmax[ti, 0] + eps) & (y >= bmin[ti, 1] - eps) & (y <= bmax[ti, 1] + eps)
    pi, ti, x, y = pi[inb], ti[inb], x[inb], y[inb]
    Tt = T[ti]
    a, b, c = Tt[:, 0], Tt[:, 1], Tt[:, 2]
    l1 = ((b[:, 1] - c[:, 1]) * (x - c[:, 0]) + (c[:, 0] - b[:, 0]) * (y - c[:, 1])) / det[ti]
    l2 = ((c[:, 1] - a[:, 1]) * (x - c[:, 0]) + (a[:, 0] - c[:, 0]) * (y - c[:, 1])) / det[ti]
    inside = (l1 >= -1e-9) & (l2 >= -1e-9) & (l1 + l2 <= 1.0 + 1e-9)
    z = l1 * a[:, 2] + l2 * b[:, 2] + (1.0 - l1 - l2) * c[:, 2]
    (np.minimum if lowest else np.maximum).at(top, pi[inside], z[inside])
    top[~np.isfinite(top)] = np.nan
    return top


class _CellGrid:
    """Integer cells ``ij`` (n, 2) of some points, on a dense grid over their extent (grown by
    ``margin`` cells): ``flags`` (one per cell, False) for marking cells, and the points per
    cell (``pairs``), found by indexing instead of sorted keys and binary searches."""

    def __init__(self, ij, margin: int = 0):
        self.lo = ij.min(axis=0) - margin
        self.shape = ij.max(axis=0) + margin - self.lo + 1
        self.cells = self.index(ij)
        self._flags = None

    def index(self, ij):
        return (ij[:, 1] - self.lo[1]) * self.shape[0] + (ij[:, 0] - self.lo[0])

    def around(self):
        """The index offsets of a cell's 3 x 3 neighbourhood (margin 1 or more)."""
        d = np.array([-1, 0, 1], dtype=np.int64)
        return (d[:, None] * self.shape[0] + d[None, :]).ravel()

    @property
    def flags(self):
        if self._flags is None:
            self._flags = np.zeros(int(self.shape[0] * self.shape[1]), dtype=bool)
        return self._flags

    def flag_at(self, ij):
        """``flags`` at the cells ``ij`` (False outside the grid)."""
        out = np.zeros(len(ij), dtype=bool)
        r = ij - self.lo
        on = (r[:, 0] >= 0) & (r[:, 0] < self.shape[0]) & (r[:, 1] >= 0) & (r[:, 1] < self.shape[1])
        out[on] = self.flags[r[on, 1] * self.shape[0] + r[on, 0]]
        return out

    def pairs(self, lo, hi):
        """Pairs (point, box), in no set order: the point's cell is one of the cells
        ``lo[b] .. hi[b]`` (both ends included) of box b."""
        lo = np.maximum(lo, self.lo)                  # (cells off the grid hold no point)
        hi = np.minimum(hi, self.lo + self.shape - 1)
        nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
        nc = np.where((nx > 0) & (ny > 0), nx * ny, 0)
        b = np.repeat(np.arange(len(lo)), nc)
        k = np.arange(nc.sum()) - np.repeat(np.cumsum(nc) - nc, nc)
        row, col = np.divmod(k, nx[b])
        cell = self.index(lo)[b] + row * self.shape[0] + col
        count = np.bincount(self.cells, minlength=int(self.shape[0] * self.shape[1]))
        start = np.cumsum(count) - count
        order = np.argsort(self.cells, kind="stable")
        cnt = count[cell]
        at = np.repeat(start[cell], cnt) + np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        return order[at], np.repeat(b, cnt)


_KEY_BIAS = 1 << 30


def _cell_pairs(lo, hi, qkey):
    """Pairs (q, b), in no set order: query q's cell (key ``qkey[q]``, :func:`_keys`) is one of
    the cells ``lo[b] .. hi[b]`` (integer cell ranges, both ends included) of box b. (The
    smaller side, the queries or the boxes' cells, is the one sorted.)"""
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    nc = nx * ny
    b = np.repeat(np.arange(len(lo)), nc)
    k = np.arange(nc.sum()) - np.repeat(np.cumsum(nc) - nc, nc)
    ckey = _keys(np.column_stack([lo[b, 0] + k % nx[b], lo[b, 1] + k // nx[b]]))
    if len(qkey) < len(ckey):       # each box cell looked up among the sorted queries
        order = np.argsort(qkey)
        sq = qkey[order]
        first, last = np.searchsorted(sq, ckey, "left"), np.searchsorted(sq, ckey, "right")
        cnt = last - first
        at = np.repeat(first, cnt) + np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
        return order[at], np.repeat(b, cnt)
    order = np.argsort(ckey, kind="stable")
    ckey, b = ckey[order], b[order]
    first, last = np.searchsorted(ckey, qkey, "left"), np.searchsorted(ckey, qkey, "right")
    cnt = last - first
    q = np.repeat(np.arange(len(qkey)), cnt)
    return q, b[np.repeat(first, cnt) + np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)]


def _keys(ij):
    """One int64 per (i, j) cell (|i|, |j| < 2^30)."""
    return ((ij[:, 0] + _KEY_BIAS) << 32) + (ij[:, 1] + _KEY_BIAS)


def _part(kind, v, f, fg, n_groups, ids, elements, osm, centroids):
    counts = np.bincount(fg, minlength=n_groups) if len(fg) else np.zeros(n_groups, dtype=np.int64)
    fstart = np.concatenate([[0], np.cumsum(counts)])
    return MeshPart(kind, v, f.astype(np.int64), list(ids), list(elements), list(osm), fstart, centroids)


# ---------------------------------------------------------------------------------------
def _road_lanes(net):
    """Normal edges with lanes; their lanes (>= 2 shape points) in index order, the edge of
    each lane, and per edge (edge number, shape of its middle lane). Kept on the network
    (read-only): the build makes it once, before the processes that use it are forked."""
    cached = getattr(net, "_road_lanes_cache", None)
    if cached is not None:
        return cached
    edges = [e for e in net.edges.values() if e.function == "normal" and e.lanes and not getattr(e, "tunnel", False)]
    lanes, lane_edge, refs = [], [], []
    for ei, e in enumerate(edges):
        ls = [l for l in e.lanes if len(l.shape) >= 2]
        if not ls:
            continue
        if len(ls) > 1:
            ls.sort(key=_LANE_INDEX)
        refs.append((ei, ls[len(ls) // 2].shape))
        for l in ls:
            lanes.append(l)
            lane_edge.append(ei)
    out = (edges, lanes, np.array(lane_edge, dtype=np.int64), refs)
    try:
        net._road_lanes_cache = out
    except AttributeError:      # a network object that takes no attributes: not kept
        pass
    return out


def underground_junctions(net) -> frozenset:
    """Junctions whose roads are all tunnels (OSM ``tunnel=*``): not on the surface, so
    neither they, their walking areas, crossings and turns, nor their tunnels are meshed
    (a tunnel drawn over the ground ran across Monaco's streets at their height, and a
    street's junction levelled beside it left the tunnel's edge standing 1 m proud of it).
    Kept on the network."""
    cached = getattr(net, "_underground_cache", None)
    if cached is not None:
        return cached
    surface, under = set(), set()
    for e in net.edges.values():
        if e.function != "normal":
            continue
        (under if getattr(e, "tunnel", False) else surface).update((e.from_node, e.to_node))
    out = frozenset(under - surface)
    try:
        net._underground_cache = out
    except AttributeError:
        pass
    return out


def _repaired(polys):
    """Invalid polygons (netconvert's junction and walking area shapes, a lane's strip round a
    tight bend, can cross themselves) as the area they enclose: GEOS's "structure" repair, a
    superset of the default "linework" one, which leaves a region the ring winds round twice
    out (Monaco: 220 m2 more of its junctions covered) and takes 8 times as long."""
    return shapely.make_valid(polys, method="structure", keep_collapsed=False)


def _repaired_polygons(rings) -> np.ndarray:
    """Polygons of ``rings`` (open, (n, 2) each), the invalid ones repaired (:func:`_repaired`)."""
    if not len(rings):
        return np.empty(0, dtype=object)
    R, g = _concat(rings)
    polys = shapely.polygons(shapely.linearrings(R, indices=g))
    bad = ~shapely.is_valid(polys)
    polys[bad] = _repaired(polys[bad])
    return polys


def _near_polygons(pts, polys, reach) -> tuple:
    """Pairs (point number, polygon number) of the shapely points ``pts`` and ``polys`` within
    ``reach[point]`` of each other."""
    qi, ji = shapely.STRtree(polys).query(pts, predicate="dwithin", distance=float(np.max(reach)) if len(reach) else 0.0)
    ok = shapely.distance(pts[qi], polys[ji]) <= reach[qi]
    return qi[ok], ji[ok]


def _open_ring(shape):
    """A polygon shape without its closing point, or None with fewer than 3 points left."""
    ring = shape
    if ring[0, 0] == ring[-1, 0] and ring[0, 1] == ring[-1, 1]:
        ring = ring[:-1]
    return ring if len(ring) >= 3 else None


def _internal_lanes(net):
    """The vehicle lanes inside junctions (internal edges ``:J_k``): (the junction id of
    each, the lanes). Kept on the network like :func:`_road_lanes`; empty when the network
    was read without them."""
    cached = getattr(net, "_internal_lanes_cache", None)
    if cached is not None:
        return cached
    jids, lanes = [], []
    under = underground_junctions(net)
    for e in net.edges.values():
        if e.function != "internal":
            continue
        j = e.id[1:e.id.rfind("_")]
        if j in under:
            continue
        for ln in e.lanes:
            if ln.drivable and ln.shape is not None and len(ln.shape) >= 2:
                jids.append(j)
                lanes.append(ln)
    out = (jids, lanes)
    try:
        net._internal_lanes_cache = out
    except AttributeError:
        pass
    return out


def _lane_strips(lanes, mitre_limit: float = 2.0, inset: float = 0.0):
    """Shapely strips of lanes: the centreline buffered by half the width (less `inset`), flat
    ends."""
    if not len(lanes):
        return np.empty(0, dtype=object)
    P, g = _concat([ln.shape[:, :2] for ln in lanes])
    return shapely.buffer(shapely.linestrings(P, indices=g), np.array([ln.width for ln in lanes]) / 2.0 - inset,
                          cap_style="flat", join_style="mitre", mitre_limit=mitre_limit)


def _polygon_rings(geom, min_area: float = 0.5) -> list:
    """The exterior rings (n, 2) of the polygons of `geom` larger than `min_area` m2."""
    return [np.asarray(g.exterior.coords)[:, :2] for g in shapely.get_parts(geom)
            if isinstance(g, shapely.Polygon) and g.area > min_area]


#: a vehicle lane inside a junction is "off" the junction's polygon where this much of its
#: middle (m, away from its ends) lies more than 0.3 m outside it
JUNCTION_GAP_M = 1.0
#: a corner of such a lane's strip on a road's vehicle lane, at most this far from its height
#: (m), takes that lane's height (build_roads)
GAP_ONTO_LANE_MAX_M = 0.8


def junction_gaps(net) -> tuple[list, list]:
    """The vehicle lanes inside junctions whose middle leaves their junction's polygon:
    (their junction ids, the lanes); kept on the network.

    netconvert's polygon of a junction on odd geometry can miss most of a turn: on a steep
    Monaco hairpin (junction 7265762803) the turning lane ran over bare ground, and across a
    walking area that the same polygon error put over the carriageway, 0.3 m above it; the
    car ran onto it and stuck. Such lanes get a surface of their own (the walking areas of
    their junction give way to it); the others are covered by their junction."""
    cached = getattr(net, "_junction_gaps_cache", None)
    if cached is not None:
        return cached
    out = _junction_gaps(net)
    try:
        net._junction_gaps_cache = out
    except AttributeError:
        pass
    return out


def _junction_gaps(net) -> tuple[list, list]:
    jids, lanes = _internal_lanes(net)
    if not lanes:
        return [], []
    ring_of, rings = {}, []
    for j in sorted(set(jids)):
        jn = net.junctions.get(j)
        r = _open_ring(jn.shape[:, :2]) if jn is not None and jn.shape is not None and len(jn.shape) >= 3 else None
        if r is not None:
            ring_of[j] = len(rings)
            rings.append(r)
    if not rings:
        return [], []
    jpoly = _repaired_polygons(rings)
    shapely.prepare(jpoly)
    # the middles, a point every half metre, without the first and last metre (where lanes
    # meet); a point is off when more than 0.3 m outside the polygon
    sel = [k for k, j in enumerate(jids) if j in ring_of and lanes[k].length > 2.0]
    if not sel:
        return [], []
    P, g = _concat([lanes[k].shape[:, :2] for k in sel])
    D, dg = resample_many(P, g, 0.5)
    ds, tot = _arclen(D, dg)
    mid = (ds > 1.0) & (ds < tot[dg] - 1.0)
    D, dg = D[mid], dg[mid]
    owner = np.array([ring_of[jids[k]] for k in sel])[dg]
    out = np.flatnonzero(~shapely.contains_xy(jpoly[owner], D[:, 0], D[:, 1]))
    out = out[shapely.distance(jpoly[owner[out]], shapely.points(D[out])) > 0.3]
    if len(out):    # ... and not on another junction or a vehicle lane (netconvert's junctions overlap)
        pts = shapely.points(D[out])
        on = shapely.STRtree(jpoly).query(pts, predicate="intersects")[0]
        _, rlanes, _, _ = _road_lanes(net)
        drive = [ln for ln in rlanes if ln.drivable]
        if drive:
            LP, lg = _concat([ln.shape[:, :2] for ln in drive])
            lines = shapely.linestrings(LP, indices=lg)
            hw = np.array([ln.width for ln in drive]) / 2.0
            pi, li = shapely.STRtree(lines).query(pts, predicate="dwithin", distance=float(hw.max()))
            near = shapely.distance(pts[pi], lines[li]) <= hw[li]
            on = np.concatenate([on, pi[near]])
        out = np.delete(out, np.unique(on))
    n_out = 0.5 * np.bincount(dg[out], minlength=len(sel))
    off = [sel[i] for i in np.flatnonzero(n_out >= JUNCTION_GAP_M)]
    return [jids[k] for k in off], [lanes[k] for k in off]


#: a lane's end is extended this far at most (m) towards its junction's border (_lane_end_gaps)
END_GAP_REACH_M = 2.0
#: the lanes' strips within this far of their ends (m) make the carriageway around a junction
END_STRIP_REACH_M = 4.0


def _lane_end_gaps(edges, lane_edge, C, cg, cs, ctot, nrm, drive, jrings) -> tuple[list, np.ndarray]:
    """Bare ground in front of vehicle lanes' ends at junctions: ([(junction id, open ring (n,
    2))], the rows of the lane points near the ends there). A lane's strip ends square to its
    first (last) segment, and netconvert's junction border can run at an angle to it: between
    the two a triangle of the lane's width was left bare, a notch at the road's edge or, with
    the lane beside leaning the other way, a hole (Monaco, junction 273245248: 0.56 m2 in a
    lane's way, over ground 2 m below the road; the car's wheel caught its far edge). Only
    junctions with a lane end corner more than 5 cm off their polygon are looked at. There,
    each lane's end is extended END_GAP_REACH_M across its width towards the junction; what
    of that neither the polygon nor a lane's strip near its end covers (slivers under 10 cm
    left out), and touches both the lane's end and the polygon, is the gap."""
    none = ([], np.zeros(0, dtype=np.int64))
    if not len(cg) or not jrings:
        return none
    first = np.r_[0, np.nonzero(cg[1:] != cg[:-1])[0] + 1]
    last = np.r_[first[1:] - 1, len(cg) - 1]
    # lane ends at junctions with a polygon: the junction, the end's row, the next row in
    ej, ea, en = [], [], []
    for a, b in zip(first[drive[cg[first]]], last[drive[cg[first]]]):
        if b <= a:
            continue
        e = edges[lane_edge[cg[a]]]
        if e.from_node in jrings:
            ej.append(e.from_node), ea.append(a), en.append(a + 1)
        if e.to_node in jrings:
            ej.append(e.to_node), ea.append(b), en.append(b - 1)
    if not ej:
        return none
    ea, en = np.array(ea), np.array(en)
    jids, jnum = np.unique(np.array(ej), return_inverse=True)
    jarr = _repaired_polygons([jrings[j] for j in jids])
    off = np.maximum(shapely.distance(jarr[jnum], shapely.points(C[ea] + nrm[ea])),
                     shapely.distance(jarr[jnum], shapely.points(C[ea] - nrm[ea])))
    cand = np.zeros(len(jids), dtype=bool)
    cand[jnum[off > 0.05]] = True
    sel = np.flatnonzero(cand[jnum])
    if not len(sel):
        return none
    ea, en, jnum = ea[sel], en[sel], jnum[sel]
    n = len(sel)
    # the strips near the ends: the points within END_STRIP_REACH_M of the end and the first
    # beyond it, each strip a ring of its left side out and its right side back
    at_start = en > ea
    near_s = np.bincount(cg, weights=cs <= END_STRIP_REACH_M, minlength=cg[-1] + 1).astype(np.int64)
    near_e = np.bincount(cg, weights=ctot[cg] - cs <= END_STRIP_REACH_M, minlength=cg[-1] + 1).astype(np.int64)
    size = (last - first + 1)[np.searchsorted(first, ea, "right") - 1]
    cnt = np.minimum(np.where(at_start, near_s[cg[ea]], near_e[cg[ea]]) + 1, size)
    lo = np.where(at_start, ea, ea - cnt + 1)
    tot = int(cnt.sum())
    grp = np.repeat(np.arange(n), cnt)
    within = np.arange(tot) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    rows = lo[grp] + within
    back = lo[grp] + cnt[grp] - 1 - within
    ring = np.empty((2 * tot, 2))
    base = np.repeat(2 * (np.cumsum(cnt) - cnt), cnt)
    ring[base + within] = C[rows] + nrm[rows]
    ring[base + cnt[grp] + within] = C[back] - nrm[back]
    strips = shapely.polygons(shapely.linearrings(ring, indices=np.repeat(np.arange(n), 2 * cnt)))
    bad = ~shapely.is_valid(strips)
    strips[bad] = _repaired(strips[bad])
    strip_j = jnum.copy()
    # the aprons in front of the ends, across the lane's width
    u = C[ea] - C[en]
    u *= (END_GAP_REACH_M / np.maximum(np.hypot(u[:, 0], u[:, 1]), 1e-9))[:, None]
    L, R = C[ea] + nrm[ea], C[ea] - nrm[ea]
    apron = shapely.polygons(np.stack([L, R, R + u, L + u], axis=1))
    edge = shapely.linestrings(np.stack([L, R], axis=1))
    shapely.prepare(jarr)
    out_of = ~shapely.covers(jarr[jnum], apron)          # (an apron on its junction has no gap)
    apron, edge, jnum, ea = apron[out_of], edge[out_of], jnum[out_of], ea[out_of]
    J = jarr[jnum]
    # each apron less its junction and, round by round, the strips of its junction's lanes
    # that reach into it
    G = shapely.difference(apron, J)
    ai, si = shapely.STRtree(strips).query(apron, predicate="intersects")
    keep_pair = jnum[ai] == strip_j[si]
    ai, si = ai[keep_pair], si[keep_pair]
    order = np.argsort(ai, kind="stable")
    ai, si = ai[order], si[order]
    rnd = np.arange(len(ai)) - np.searchsorted(ai, ai)           # (the pair's rank for its apron)
    for r in range(int(rnd.max()) + 1 if len(rnd) else 0):
        on = rnd == r
        G[ai[on]] = shapely.difference(G[ai[on]], strips[si[on]])
    # (slivers under 10 cm, as between two strips that nearly meet, are no gap)
    G = shapely.buffer(shapely.buffer(G, -0.05, join_style="mitre"), 0.05, join_style="mitre")
    parts, owner = shapely.get_parts(G, return_index=True)
    if not len(parts):
        return none
    ok = (shapely.get_type_id(parts) == 3) & (shapely.area(parts) > 0.01)
    ok &= (shapely.distance(parts, edge[owner]) < 0.02) & (shapely.distance(parts, J[owner]) < 0.02)
    parts, owner = parts[ok], owner[ok]
    out = [(str(jids[jnum[m]]), np.asarray(pg.exterior.coords)[:-1, :2]) for pg, m in zip(parts, owner)]
    return out, np.unique(rows)


def _interior_points(shapes, step: float) -> np.ndarray:
    """Points of a square lattice (``step``, offset by half a step from each shape's bounding
    box) inside polygon shapes, all shapes together (k, 2)."""
    rings = [r for r in (_open_ring(np.asarray(sh)[:, :2]) for sh in shapes) if r is not None]
    if not rings:
        return np.zeros((0, 2))
    R, g = _concat(rings)
    starts = np.r_[0, np.cumsum(np.bincount(g))[:-1]]
    lo = np.column_stack([np.minimum.reduceat(R[:, 0], starts), np.minimum.reduceat(R[:, 1], starts)])
    hi = np.column_stack([np.maximum.reduceat(R[:, 0], starts), np.maximum.reduceat(R[:, 1], starts)])
    cnt = np.maximum(np.ceil((hi - lo) / step - 0.5), 0).astype(np.int64)     # lattice columns, rows
    n = cnt[:, 0] * cnt[:, 1]
    owner = np.repeat(np.arange(len(rings)), n)
    local = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
    X = lo[owner, 0] + (local % np.maximum(cnt[owner, 0], 1) + 0.5) * step
    Y = lo[owner, 1] + (local // np.maximum(cnt[owner, 0], 1) + 0.5) * step
    polys = shapely.polygons(shapely.linearrings(R, indices=g))
    shapely.prepare(polys)
    inside = shapely.contains_xy(polys[owner], X, Y)
    return np.column_stack([X[inside], Y[inside]])


def _dense_triangulated(shapes, step: float):
    """Polygon shapes as open rings with a point at least every `step` metres (their own
    points kept), triangulated: GEOS's constrained Delaunay triangulation where the ring is a
    valid polygon, else earcut. Returns the points (n, 2), the shape of each point, the
    triangles (m, 3: rows of the points, counter-clockwise) and the shape of each triangle;
    shapes with fewer than 3 points have neither. (The points along a junction's long side
    take their heights from the lane ends that touch it, not from its far corners; Delaunay
    triangles are well shaped, where earcut's long fans made a sloping junction fold between
    corners of different heights.)"""
    idx, rings = [], []
    for k, sh in enumerate(shapes):
        r = _open_ring(sh)
        if r is not None:
            idx.append(k)
            rings.append(r[:, :2])
    if not idx:
        return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int64)
    idx = np.array(idx)
    P0, g0 = _concat(rings)
    lens = np.bincount(g0, minlength=len(idx))
    ends = np.cumsum(lens)
    Pc = np.insert(P0, ends, P0[ends - lens], axis=0)          # each ring closed
    gc = np.insert(g0, ends, np.arange(len(idx)))
    D, dg = resample_many(Pc, gc, step)
    dlen = np.bincount(dg, minlength=len(idx))
    keep_pt = np.ones(len(D), dtype=bool)
    keep_pt[np.cumsum(dlen) - 1] = False                       # the open rings
    P, g = D[keep_pt], dg[keep_pt]
    start = np.cumsum(dlen - 1) - (dlen - 1)
    done = np.zeros(len(idx), dtype=bool)
    F, FG = [np.zeros((0, 3), np.int64)], [np.zeros(0, np.int64)]
    polys = shapely.polygons(shapely.linearrings(D, indices=dg))
    valid = np.nonzero(shapely.is_valid(polys))[0]
    if len(valid):
        C, owner = shapely.get_coordinates(shapely.constrained_delaunay_triangles(polys[valid]),
                                           return_index=True)
        C = C.reshape(-1, 4, 2)[:, :3].reshape(-1, 2)       # (each triangle a closed ring)
        owner = valid[owner.reshape(-1, 4)[:, :3].ravel()]
        # the triangles' corners are the ring's points, exactly: found by sorting keys (x
        # shifted by the polygon's number, y), each checked
        key = (P[:, 0] + g * 1e6) + 1j * P[:, 1]
        ck = (C[:, 0] + owner * 1e6) + 1j * C[:, 1]
        order = np.argsort(key)
        vid = order[np.minimum(np.searchsorted(key[order], ck), len(P) - 1)]
        bad = np.zeros(len(idx), dtype=bool)
        bad[owner[key[vid] != ck]] = True
        owner = owner[::3]
        vid = vid.reshape(-1, 3)
        a, b, c = P[vid[:, 0]], P[vid[:, 1]], P[vid[:, 2]]
        cw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) < 0
        vid[cw] = vid[cw][:, ::-1]
        ok = ~bad[owner]
        F.append(vid[ok])
        FG.append(owner[ok])
        done[np.unique(owner[ok])] = True
    n1 = np.zeros(1, dtype=np.uint32)
    for n in np.nonzero(~done)[0]:
        n1[0] = dlen[n] - 1
        t = mapbox_earcut.triangulate_float64(np.ascontiguousarray(P[start[n]:start[n] + dlen[n] - 1]), n1)
        F.append(t.reshape(-1, 3).astype(np.int64) + start[n])
        FG.append(np.full(len(t) // 3, n, dtype=np.int64))
    F, FG = np.concatenate(F), np.concatenate(FG)
    order = np.argsort(FG, kind="stable")
    return P, idx[g], F[order], idx[FG[order]]


def carriageway_parts(net) -> list:
    """Where vehicles drive: each vehicle lane's strip (its SUMO shape buffered by half its
    width, flat ends), each junction polygon (repaired where invalid) and the strips of the
    vehicle lanes inside junctions (their turns). They
    overlap; the union is not formed (scenery tests points against the parts). Kept on the
    network, as :func:`_road_lanes` (a build's buildings and scenery both use them)."""
    cached = getattr(net, "_carriageway_cache", None)
    if cached is not None:
        return list(cached)
    _, lanes, _, _ = _road_lanes(net)
    drive = [l for l in lanes if l.drivable]
    out = list(_lane_strips(drive, mitre_limit=5.0))       # (GEOS's default mitre limit)
    under = underground_junctions(net)
    rings = [r for r in (_open_ring(j.shape) for j in net.junctions.values()
                         if j.type != "internal" and len(j.shape) >= 3 and j.id not in under) if r is not None]
    if rings:
        JP, jg = _concat(rings)         # linearrings() closes each ring
        jp = shapely.polygons(shapely.linearrings(JP, indices=jg))
        bad = ~shapely.is_valid(jp)
        jp[bad] = _repaired(jp[bad])
        out += list(jp)
    # the vehicle lanes inside junctions too, whole: a junction's polygon can miss part of a
    # turn (:func:`junction_gaps`), and is often narrower than its turns' lanes (Monaco: a
    # building's wall stood 0.37 m outside a junction's polygon, inside a turn's lane, 1.2 m
    # from its middle; the car's lidar saw it in its way and the car stood for good)
    _, inner = _internal_lanes(net)
    out += list(_lane_strips(inner))
    try:
        net._carriageway_cache = tuple(out)
    except AttributeError:      # a network object that takes no attributes: not kept
        pass
    return out


def _deck_clearance(RP, idx, own_e, hw, under_e, higher, lane_edge, onto_profile, core_tree) -> np.ndarray:
    """For :func:`_raise_decks`: for the deck's profile points ``idx`` (of edges ``own_e``,
    half widths ``hw``), the height the deck must reach there: :data:`DECK_CLEARANCE_M` over
    the highest vehicle lane within ``hw`` of it of an edge in ``under_e`` (a mask of edges),
    but near a node where that edge meets the deck's (:data:`CONFORM_NODE_CLEAR_M` beyond its
    junction); NaN where none. (Junctions under a deck too: no better in Portland, worse in
    Lauf, where decks then stayed down.)"""
    need = np.full(len(idx), np.nan)
    veh, cores, fn, tn, nxy, nrad = higher[0], higher[1], higher[3], higher[4], higher[6], higher[7]
    if not len(idx) or not len(veh):
        return need
    pts = shapely.points(RP[idx])
    qi, li = core_tree.query(pts, predicate="dwithin", distance=float(hw.max()))
    B, A = lane_edge[veh[li]], own_e[qi]
    ok = under_e[B]
    Q = RP[idx[qi]]
    for a in (fn[A], tn[A]):            # (a road that meets the deck: not near where it does)
        shared = (a == fn[B]) | (a == tn[B])
        d = np.hypot(Q[:, 0] - nxy[a, 0], Q[:, 1] - nxy[a, 1])
        ok &= ~shared | (d > nrad[a] + CONFORM_NODE_CLEAR_M)        # (NaN: never far)
    qi, li = qi[ok], li[ok]
    ok = shapely.distance(pts[qi], cores[li]) <= hw[qi]
    qi, li = qi[ok], li[ok]
    top = np.full(len(idx), -np.inf)
    if len(qi):
        zu = onto_profile(RP[idx[qi]], veh[li], lane_edge[veh[li]]) + DECK_CLEARANCE_M
        fin = np.isfinite(zu)
        np.maximum.at(top, qi[fin], zu[fin])
    return np.where(np.isfinite(top), top, np.nan)


def _bridge_decks(edges, ref_e, rg, rs, rtot, rz, deck, nodes=None) -> None:
    """Bridges (OSM ``bridge=*``; ``deck``: the mask of the profiles that are one) as decks
    (``rz`` in place).

    A profile sampled from the ground took a bridge down into what it spans: Portland's
    bridges over the Willamette and the I-405 cutting dipped up to 20 m, and a car on an
    overpass ran into the motorway's surface at the bottom of the dip. A deck runs straight
    between its nodes; the nodes where it meets the ground (abutments: a road that is no
    bridge meets it there, a drivable one where the deck is drivable, so that steps down from
    a bridge are not abutments; or the bridge ends there) keep their height, those along the
    bridge (a ramp joining it, a bridge mapped in pieces) take the length-weighted mean of their
    neighbours' along it (solved for all at once). Where a road passes under it, it rises
    later (:func:`_raise_decks`). ``nodes``: :func:`_deck_nodes` (else worked out here)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = len(ref_e)
    if not deck.any():
        return
    num, fn, tn, abut, on = nodes if nodes is not None else _deck_nodes(edges, ref_e, deck)
    m = len(num)
    ground = _node_heights(fn, tn, rg, rz, m)
    h = ground.copy()
    if on.any():
        # each unknown node: sum over its deck profiles of w (h - h_other) = 0, w = 1 / length
        # (a tiny pull to its ground: a bridge that meets the ground nowhere stays on it)
        w = 1.0 / np.maximum(rtot[:n][deck], 1.0)
        a, b = fn[deck], tn[deck]
        idx = -np.ones(m, dtype=np.int64)
        idx[on] = np.arange(int(on.sum()))
        rows, cols, vals = [], [], []
        rhs = np.zeros(int(on.sum()))
        for p, q in ((a, b), (b, a)):
            sel = on[p] & (p != q)
            rows += [idx[p[sel]]]
            cols += [idx[p[sel]]]
            vals += [w[sel]]
            known = sel & ~on[q]
            np.add.at(rhs, idx[p[known]], w[known] * ground[q[known]])
            unk = sel & on[q]
            rows += [idx[p[unk]]]
            cols += [idx[q[unk]]]
            vals += [-w[unk]]
        eps = 1e-6 * float(np.max(w))
        k = int(on.sum())
        rows.append(np.arange(k))
        cols.append(np.arange(k))
        vals.append(np.full(k, eps))
        rhs += eps * ground[on]
        A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(k, k))
        h[on] = spsolve(A.tocsc(), rhs)
    u = rs / np.maximum(rtot[rg], 1e-9)
    pd = deck[rg]
    z0, z1 = h[fn][rg], h[tn][rg]
    rz[pd] = (z0 + u * (z1 - z0))[pd]


def _deck_nodes(edges, ref_e, deck) -> tuple:
    """The nodes of the profiles (``ref_e``: their edges; ``deck``: which are a bridge's
    deck): their numbers (node id -> number), each profile's from and to node, and which
    nodes are a bridge's abutment (a road that is no bridge meets it there, a drivable one
    where the deck is drivable, so that steps down from a bridge are not abutments; or the
    bridge ends there) and which lie along a bridge (every other node a deck meets)."""
    num: dict = {}
    fn = np.array([num.setdefault(edges[int(e)].from_node, len(num)) for e in ref_e], dtype=np.int64)
    tn = np.array([num.setdefault(edges[int(e)].to_node, len(num)) for e in ref_e], dtype=np.int64)
    m = len(num)
    drv = np.array([edges[int(e)].drivable for e in ref_e], dtype=bool)
    ends = np.concatenate([fn, tn])
    at = lambda mask: np.bincount(ends, np.tile(mask, 2).astype(float), m) > 0      # noqa: E731
    # (a bridge's end where nothing else meets it: one neighbour along decks, "X" and "-X" one)
    nb = np.unique(np.column_stack([np.r_[fn[deck], tn[deck]], np.r_[tn[deck], fn[deck]]]), axis=0)
    degree = np.bincount(nb[:, 0], minlength=m)
    abut = at(~deck & drv) | (~at(deck & drv) & at(~deck)) | (degree == 1)
    on = at(deck) & ~abut
    return num, fn, tn, abut, on


def _node_heights(fn, tn, rg, rz, m) -> np.ndarray:
    """Each of ``m`` nodes' mean height of the ends of the profiles (``rg``, ``rz``; from and
    to nodes ``fn``, ``tn``) there."""
    first = np.r_[0, np.nonzero(rg[1:] != rg[:-1])[0] + 1]
    last = np.r_[first[1:] - 1, len(rg) - 1]
    ends = np.concatenate([fn, tn])
    return np.bincount(ends, rz[np.concatenate([first, last])], m) / np.maximum(np.bincount(ends, minlength=m), 1)


#: a node along a bridge is lifted at most this many times (_lift_viaducts)
VIADUCT_LIFT_ROUNDS = 4


def _lift_viaducts(edges, ref_e, rg, rs, rtot, rz, deck, planes, clearance, keep=frozenset(), nodes=None) -> int:
    """The nodes along bridges (:func:`_deck_nodes`) lifted where a deck that ends there must
    reach ``clearance(points)`` (the heights over the roads and junctions under its profile
    points, :func:`_deck_clearance`, NaN where none; and how far over them the deck comes down
    onto them later) higher than :data:`DECK_MAX_GRADE` from its
    ends allows, for :func:`_raise_decks`: the nearer of its ends that lies along a bridge
    rises just enough, but no higher than that grade allows from the abutments along the
    decks (a shortest path); every profile ending there follows linearly along its length,
    and the node's plane (``planes``) with it (``rz``, ``planes`` in place). A node along a
    bridge lay where the mean of its neighbours and the junction planes put it: Portland's
    viaducts east of the Morrison Bridge stayed near the ground between abutments on both
    sides of I-5, so their decks could not rise over it: one crossed the freeway at grade,
    another 1.3 m over it, and cars ran into both. Nodes in ``keep`` stay (a deck's end on
    another node's junction: lifted, Portland's 34089106#0 began 0.9 m over the junction of
    the street beside its node). Returns how many nodes rose."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import dijkstra

    num, fn, tn, abut, on = nodes if nodes is not None else _deck_nodes(edges, ref_e, deck)
    m = len(num)
    on = on & ~np.isin(np.arange(m), [num[j] for j in keep if j in num])
    if not on.any():
        return 0
    h = _node_heights(fn, tn, rg, rz, m)
    src = np.flatnonzero(abut & np.isfinite(h) & (np.bincount(np.r_[fn[deck], tn[deck]], minlength=m) > 0))
    if not len(src):
        return 0
    dk = np.flatnonzero(deck)
    a, b, length = fn[dk], tn[dk], rtot[dk]
    # the highest each node may stand: from the abutments along the decks at DECK_MAX_GRADE
    # (a source joined to each abutment by the rise from the lowest one)
    base = float(np.min(h[src]))
    w = np.maximum(np.r_[length, length, (h[src] - base) / DECK_MAX_GRADE], 1e-9)
    rows, cols = np.r_[a, b, np.full(len(src), m)], np.r_[b, a, src]
    # (one entry per pair of nodes, the shortest: a sparse matrix sums duplicates, and a
    # street's two directions are two decks between the same nodes)
    o = np.lexsort((w, cols, rows))
    rows, cols, w = rows[o], cols[o], w[o]
    one = np.r_[True, (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])]
    graph = sp.csr_matrix((w[one], (rows[one], cols[one])), shape=(m + 1, m + 1))
    top = base + DECK_MAX_GRADE * dijkstra(graph, indices=m)[:m]
    prof = np.full(len(ref_e), -1, dtype=np.int64)
    prof[dk] = np.arange(len(dk))
    pts = np.flatnonzero(deck[rg])
    u = rs / np.maximum(rtot[rg], 1e-9)
    h0 = h.copy()
    for _ in range(VIADUCT_LIFT_ROUNDS):
        need, down = clearance(pts)
        sel = np.isfinite(need)
        if not sel.any():
            break
        p, nd, down = pts[sel], need[sel], down[sel]
        k = prof[rg[p]]
        sa, sb = rs[p], length[k] - rs[p]
        cap = np.minimum(h[a[k]] + DECK_MAX_GRADE * sa, h[b[k]] + DECK_MAX_GRADE * sb)
        short = nd > cap + 1e-6       # (lifted to the full clearance where it can)
        if not short.any():
            break
        use_a = short & on[a[k]] & ((sa <= sb) | ~on[b[k]])          # (the nearer end along a bridge)
        use_b = short & ~use_a & on[b[k]]
        lift = h.copy()
        np.maximum.at(lift, a[k][use_a], (nd - DECK_MAX_GRADE * sa)[use_a])
        np.maximum.at(lift, b[k][use_b], (nd - DECK_MAX_GRADE * sb)[use_b])
        new = np.where(on, np.maximum(h, np.minimum(lift, top)), h)
        # (not where a deck that cannot clear a road would rise to stand in a car's way over
        # it: higher than it comes down onto it from, lower than DECK_PASSABLE_M; Portland's
        # ramp 30260391, at grade with the street it crosses 10 m from its foot, rose to 1.2 m
        # over it)
        f = sa / np.maximum(length[k], 1e-9)
        road = nd - DECK_CLEARANCE_M

        def in_way(z):
            return (z > road + down) & (z < road + DECK_PASSABLE_M)

        was = in_way(h[a[k]] * (1.0 - f) + h[b[k]] * f)
        for _ in range(len(dk)):
            cap2 = np.minimum(new[a[k]] + DECK_MAX_GRADE * sa, new[b[k]] + DECK_MAX_GRADE * sb)
            worse = (nd > cap2 + DECK_CLEARANCE_SLACK_M) & in_way(new[a[k]] * (1.0 - f) + new[b[k]] * f) & ~was
            if not worse.any():
                break
            back = np.unique(np.r_[a[k][worse], b[k][worse]])
            new[back] = h[back]
        if not np.any(new > h + 1e-3):
            break
        d = new - h
        rz += d[fn][rg] * (1.0 - u) + d[tn][rg] * u        # (every profile that ends there)
        h = new
    rose = np.flatnonzero(h > h0 + 1e-3)
    for node, k in num.items():
        if h[k] > h0[k] + 1e-3 and node in planes:
            x0, y0, z0, gx, gy = planes[node]
            planes[node] = (x0, y0, z0 + float(h[k] - h0[k]), gx, gy)
    return len(rose)


def _deck_ends_on_other_junctions(edges, ref_e, RP, rg, deck, edge_hw, jids, jpolys) -> set:
    """The nodes where a deck's profile (``deck``) ends within its half width (``edge_hw``)
    of the polygon (``jpolys``) of another node's junction (``jids``)."""
    first = np.r_[0, np.nonzero(rg[1:] != rg[:-1])[0] + 1]
    last = np.r_[first[1:] - 1, len(rg) - 1]
    ends = np.r_[first, last]
    node = np.array([edges[int(e)].from_node for e in ref_e] + [edges[int(e)].to_node for e in ref_e], dtype=object)
    sel = np.flatnonzero(deck[rg[ends]])
    ends, node = ends[sel], node[sel]
    if not len(ends) or not len(jids):
        return set()
    qi, ji = _near_polygons(shapely.points(RP[ends]), jpolys, edge_hw[ref_e[rg[ends]]])
    return {node[q] for q, j in zip(qi.tolist(), ji.tolist()) if jids[j] != node[q]}


def _raise_decks(edges, ref_e, rg, rs, rz, deck, edge_deck, clearance, junction_clearance=None) -> None:
    """Lowest OSM layer first, where a road passes under a deck (:func:`_bridge_decks`;
    ``clearance(points, their edges, under-edge mask)``: the heights needed there,
    :func:`_deck_clearance`; a deck of a lower layer counts as a road), the deck rises to clear
    it at :data:`DECK_GRADE` (``rz`` in place) where it can: its ends stay, and from them it
    rises at :data:`DECK_MAX_GRADE` at most (a short bridge over a road stays at its ends'
    height, and the road under it crosses it there, conformed to it as an untagged bridge is:
    reaching the clearance would take approaches OSM does not tag as the bridge). After the
    junction planes, so that the roads under it have their heights. ``deck``: per profile,
    ``edge_deck``: per edge.

    ``junction_clearance(points, their edges)``: the heights needed over the junctions under
    them (:func:`_deck_junction_clearance`). A deck that rises over a road rises over those
    too where it can (else as before, over the roads alone): left at its line there, and so
    neither over a junction by a car's height nor at grade with it, Monaco's Boulevard du
    Larvotto (503783368, risen over a road 40 m on) ran 1.35 m over Rond-Point du Portier's
    junction 1736937871, and a car on the junction drove into its edge."""
    pd = deck[rg]
    layer_e = np.array([e.layer for e in edges], dtype=np.int64)
    layer = layer_e[ref_e]

    def envelope(i, nc, sc):
        """The deck's heights ``rz[i]`` risen to needs ``nc`` at ``sc``; None if it cannot."""
        # (from its ends, which stay, at DECK_MAX_GRADE at most: where a deck cannot rise
        # enough over every road under it, it stays, and they cross at its height, conformed)
        cap = np.minimum(rz[i[0]] + DECK_MAX_GRADE * rs[i], rz[i[-1]] + DECK_MAX_GRADE * (rs[i[-1]] - rs[i]))
        if np.any(nc > np.interp(sc, rs[i], cap) + DECK_CLEARANCE_SLACK_M):
            return None         # (partly raised, it would stand lower than a car over a road)
        env = np.max(nc[None, :] - DECK_GRADE * np.abs(rs[i][:, None] - sc[None, :]), axis=1)
        # (no dips between the points that need it: over a road running under it at a
        # slant, sampled every few metres, the cones alone left waves, 0.29 m deep on
        # Kouvola's motorway bridge 39653008#1; one threw a car at 19 m/s off a bridge)
        o = np.argsort(sc)
        inside = (rs[i] >= sc[o[0]]) & (rs[i] <= sc[o[-1]])
        env[inside] = np.maximum(env[inside], np.interp(rs[i][inside], sc[o], nc[o]))
        return np.maximum(rz[i], np.minimum(env, cap))

    for L in np.unique(layer[deck]):
        idx = np.flatnonzero(pd & (layer[rg] == L))
        need = clearance(idx, ref_e[rg[idx]], ~edge_deck | (layer_e < L))
        jneed = np.full(len(idx), np.nan)
        if junction_clearance is not None:
            jneed = junction_clearance(idx, ref_e[rg[idx]])
        for g in np.unique(rg[idx[np.isfinite(need) | np.isfinite(jneed)]]):
            i = np.arange(np.searchsorted(rg, g), np.searchsorted(rg, g, side="right"))     # (its points)
            mine = rg[idx] == g
            z = None
            if np.isfinite(jneed[mine]).any():
                both = np.fmax(need, jneed)
                c = mine & np.isfinite(both)
                z = envelope(i, both[c], rs[idx[c]])
            if z is None and np.isfinite(need[mine]).any():
                c = mine & np.isfinite(need)
                z = envelope(i, need[c], rs[idx[c]])
            if z is not None:
                rz[i] = z


def _deck_junction_clearance(RP, idx, own_e, hw, rz, planes, jids, jpolys, edges, deck_nodes,
                             min_gap: float = 0.3) -> np.ndarray:
    """For :func:`_raise_decks`: for the deck's profile points ``idx`` (of edges ``own_e``,
    half widths ``hw`` per point), the height the deck must reach over the junctions under
    them: :data:`DECK_CLEARANCE_M` over the junction's plane (``planes``) where the point's
    cross-section reaches into its polygon (``jpolys``, of nodes ``jids``), the deck stands
    more than ``min_gap`` over it (at grade nearer, :func:`_decks_onto_junctions`) and less
    than the clearance. Not the junctions of the deck's own nodes, nor of any node a deck meets
    (``deck_nodes``: a bridge's own junctions along it). NaN where none."""
    need = np.full(len(idx), np.nan)
    if not len(idx) or not len(jids):
        return need
    qi, ji = _near_polygons(shapely.points(RP[idx]), jpolys, hw)
    if not len(qi):
        return need
    nodes = [jids[j] for j in ji.tolist()]
    ok = np.array([j not in deck_nodes and j not in (edges[int(e)].from_node, edges[int(e)].to_node)
                   for j, e in zip(nodes, own_e[qi].tolist())], dtype=bool)
    qi, ji = qi[ok], ji[ok]
    if not len(qi):
        return need
    P = np.array([planes[jids[j]] for j in ji.tolist()])
    Q = RP[idx[qi]]
    zj = P[:, 2] + P[:, 3] * (Q[:, 0] - P[:, 0]) + P[:, 4] * (Q[:, 1] - P[:, 1])
    gap = rz[idx[qi]] - zj
    ok = (gap > min_gap) & (gap < DECK_CLEARANCE_M)
    top = np.full(len(idx), -np.inf)
    np.maximum.at(top, qi[ok], zj[ok] + DECK_CLEARANCE_M)
    return np.where(np.isfinite(top), top, np.nan)


def _stack_under_higher_layers(edges, lanes, lane_edge, higher, ref_e, group_of, opposite_profile,
                               RP, rg, rs, rz, vehicle_edge, onto_profile, step, jrings, edge_hw) -> list:
    """Roads stacked in OSM's layers, neither of them a bridge (``rz`` in place; bridges rise
    over what they cross, :func:`_raise_decks`): where a vehicle lane lies under a vehicle
    lane of a road of a higher layer (its cross-section :data:`CONFORM_MIN_OVERLAP_M` or
    more inside it, away from the nodes they share: :func:`_higher_overlaps`), its road's
    profile goes :data:`DECK_CLEARANCE_M` under that road's, the descent widening at
    :data:`DECK_GRADE` along it. Its ends stay, and so do its points on the junctions of other
    nodes (``jrings``: a junction left over a lowered road stood in a car's way); from them it
    descends at :data:`STACK_MAX_GRADE` at most; where that leaves less than
    :data:`STACK_MIN_CLEARANCE_M` under the other road, it stays as it was (conformed to it,
    :func:`_conform_to_higher_roads`).
    The lanes of "-X" follow the profile of "X" (:func:`_share_opposite_profiles`), so the
    two directions go down together; the levelling takes the ground down to the lower road
    (``level_under_roads``: the lowest road within reach).

    Monaco's Liaison Marquet winds down through the Stade Louis II as two ways, layers -1 and
    -2, whose lanes overlap for about 80 m: both on the ground's height, 0.3-0.5 m apart, a
    car's wheels on one side climbed the other's edge and it rolled over.
    Returns the ids of the edges whose lanes now stand over a road stacked under them (and
    their opposites): the mirror puts the vehicles on them on their surface, as on a deck."""
    veh, core_box, deck, opp = higher[0], higher[5], higher[8], higher[9]
    layer_e = np.array([e.layer for e in edges], dtype=np.int64)
    flat = ~deck & vehicle_edge
    if not len(veh) or np.unique(layer_e[flat]).size < 2:
        return []
    # (candidates: vehicle lanes whose strip's box meets a higher layer's vehicle lane's box)
    ve = lane_edge[veh]
    lv = layer_e[ve]
    lo = np.flatnonzero(flat[ve] & (lv < lv[flat[ve]].max()))
    up = np.flatnonzero(flat[ve] & (lv > lv[flat[ve]].min()))
    qi, ui = shapely.STRtree(shapely.box(*core_box[up].T)).query(shapely.box(*core_box[lo].T), predicate="intersects")
    sel = lv[up[ui]] > lv[lo[qi]]
    cand = np.unique(veh[lo[qi[sel]]])
    if not len(cand):
        return []
    LP, lg = _concat([lanes[k].shape[:, :2] for k in cand])
    C, cg = resample_many(LP, lg, step)
    own = lane_edge[cand[cg]]
    hw = np.array([lanes[k].width for k in cand])[cg] / 2.0
    pi, li, B = _higher_overlaps(lane_edge, higher, C, cg, own, hw)
    keep = (layer_e[B] > layer_e[own[pi]]) & ~deck[B]
    pi, li, B = pi[keep], li[keep], B[keep]
    if not len(pi):
        return []
    need = onto_profile(C[pi], veh[li], B) - DECK_CLEARANCE_M
    # the profile each point takes its height from: its edge's, or for "-X" that of "X"
    a = own[pi]
    target = np.where(opposite_profile[a] >= 0, opposite_profile[a], group_of[a])
    at, _ = _onto_profiles(RP, rg, rs, C[pi], target)
    fin = np.isfinite(need) & np.isfinite(at) & (target >= 0)
    need, at, target, B = need[fin], at[fin], target[fin], B[fin]
    over: set = set()
    jtree = jids = None
    for g in np.unique(target):
        i = np.arange(np.searchsorted(rg, g), np.searchsorted(rg, g, side="right"))
        c = target == g
        nc, sc = need[c], at[c]
        ei = int(ref_e[g])
        e = edges[ei]
        fixed = np.zeros(len(i), dtype=bool)
        fixed[[0, -1]] = True
        if jtree is None:
            jids = list(jrings)
            jtree = shapely.STRtree([shapely.Polygon(jrings[j]) for j in jids])
        near, jn = jtree.query(shapely.points(RP[i]), predicate="dwithin", distance=float(edge_hw[ei]))
        fixed[near[[jids[k] not in (e.from_node, e.to_node) for k in jn.tolist()]]] = True
        f = np.flatnonzero(fixed)
        floor = np.max(rz[i[f]][None, :] - STACK_MAX_GRADE * np.abs(rs[i][:, None] - rs[i[f]][None, :]), axis=1)
        short = np.interp(sc, rs[i], floor) - nc
        if np.any(short > DECK_CLEARANCE_M - STACK_MIN_CLEARANCE_M):
            continue
        env = np.min(nc[None, :] + DECK_GRADE * np.abs(rs[i][:, None] - sc[None, :]), axis=1)
        o = np.argsort(sc)
        inside = (rs[i] >= sc[o[0]]) & (rs[i] <= sc[o[-1]])
        env[inside] = np.minimum(env[inside], np.interp(rs[i][inside], sc[o], nc[o]))
        rz[i] = np.minimum(rz[i], np.maximum(env, floor))
        for b in np.unique(B[c]).tolist():
            over.add(edges[b].id)
            if opp[b] >= 0:
                over.add(edges[int(opp[b])].id)
    return sorted(over)


def _decks_onto_junctions(edges, ref_e, RP, rg, rs, rz, deck, hw, planes, junctions, skip=None,
                          fixed=None) -> dict:
    """A deck (:func:`_bridge_decks`) that lies over a junction of other roads, within a car's
    height of its plane (:data:`CONFORM_MAX_M`) wherever they overlap, is at grade there: its
    profile points whose cross-section (``hw`` either side, per profile) reaches
    :data:`CONFORM_MIN_OVERLAP_M` into the polygon of a junction of another node go onto that
    junction's plane, and the points between them and the profile's ends (which stay) move
    linearly between their moves (``rz`` in place). A deck further apart from a junction
    somewhere (risen over it, or a bridge over a valley) stays there, as do the profiles
    ``skip`` marks (those :func:`_raise_decks` raised: a deck that clears a road is left as it
    is). The points ``fixed`` marks (a mask: those that lie on or under a higher-ranked road,
    :func:`_conform_to_higher_roads`, or over a road they clear) keep their height, as the ends
    do and the points over a junction further than that below. ``junctions``: id -> polygon
    ring; ``planes``: node -> plane.

    Conforming makes a road under a deck that cannot rise take the deck's height, but a
    junction's surface is its plane: Portland's Morrison Bridge (5520143, bridge=yes, layer 1)
    starts 10 m east of SE Martin Luther King Blvd and runs over its junction 256196698,
    straight at 12.3-12.4 m, where the junction's plane falls at 7 % to 11.0 m: the deck's lane
    lay across MLK's lanes up to 1.27 m over the junction, and a car on MLK stood against its
    edge (0.25 m) for the rest of a 1,800 s run. Returns per moved profile (number) the
    junctions it was put on."""
    out: dict = {}
    if not planes or not junctions or not deck.any():
        return out
    pd = deck[rg] if skip is None else (deck & ~skip)[rg]
    pd[np.r_[0, np.nonzero(rg[1:] != rg[:-1])[0] + 1]] = False        # (its ends stay)
    pd[np.r_[np.nonzero(rg[1:] != rg[:-1])[0], len(rg) - 1]] = False
    idx = np.flatnonzero(pd)
    jid = [j for j in junctions if j in planes and len(junctions[j]) >= 3]
    if not len(idx) or not jid:
        return out
    R, rgi = _concat([np.asarray(junctions[j], dtype=float)[:, :2] for j in jid])
    polys = shapely.polygons(shapely.linearrings(R, indices=rgi))
    g = rg[idx]
    reach = np.maximum(hw[g] - CONFORM_MIN_OVERLAP_M, 0.0)
    qi, ji = _near_polygons(shapely.points(RP[idx]), polys, reach)
    if not len(qi):
        return out
    # (not the deck's own nodes: its ends are on their planes already)
    own = np.array([jid[j] in (edges[int(ref_e[g[q]])].from_node, edges[int(ref_e[g[q]])].to_node)
                    for q, j in zip(qi.tolist(), ji.tolist())], dtype=bool)
    qi, ji = qi[~own], ji[~own]
    if not len(qi):
        return out
    P = np.array([planes[jid[j]] for j in ji.tolist()])
    Q = RP[idx[qi]]
    dz = P[:, 2] + P[:, 3] * (Q[:, 0] - P[:, 0]) + P[:, 4] * (Q[:, 1] - P[:, 1]) - rz[idx[qi]]
    # (a deck and a junction further apart than a car is tall somewhere: a bridge over it; one
    # within a centimetre of it everywhere: on it already)
    pair = g[qi] * len(jid) + ji
    _, inv = np.unique(pair, return_inverse=True)
    apart = np.zeros(inv.max() + 1)
    np.maximum.at(apart, inv, np.abs(dz))
    keep = (apart[inv] <= CONFORM_MAX_M) & (apart[inv] > 0.01)
    # (and over a junction it clears, it keeps its height: coming down between the junctions it
    # meets, the Morrison Bridge's deck went from 1.6-1.8 m over SE 2nd Avenue's to 0.9-1.2 m)
    clear = np.zeros(len(rz), dtype=bool)
    clear[idx[qi[apart[inv] > CONFORM_MAX_M]]] = True
    fixed = clear if fixed is None else fixed | clear
    qi, ji, dz = qi[keep], ji[keep], dz[keep]
    if not len(qi):
        return out
    # between those points and the deck's ends and fixed points (which stay), the moves
    # linearly: the deck runs straight between where it meets the ground and the roads it
    # crosses at grade (faded back to its line over 15-20 m from each junction, the Morrison
    # Bridge went up 0.8 m and down again between two junctions of the street under it, 30 m
    # apart). Where that would make the deck steeper than DECK_AT_GRADE_MAX_GRADE (or than it
    # was) between two points, the junction next to the steepest such place is left out for
    # this deck, its points stay, and the rest is tried again (the Eastbank Freeway's off-ramp
    # edge would have dropped 1 m in its first metre onto a street's junction 15 m from its
    # node: the step stays, as before).
    pq = idx[qi]
    for q in np.unique(g[qi]).tolist():
        a, b = np.searchsorted(rg, q), np.searchsorted(rg, q, side="right")
        mine = g[qi] == q
        p_, j_, d_ = pq[mine], ji[mine], dz[mine]
        stay = np.unique(np.r_[a, a + np.flatnonzero(fixed[a:b]), b - 1])
        free = ~np.isin(p_, stay)
        p_, j_, d_ = p_[free], j_[free], d_[free]
        ds = np.maximum(np.diff(rs[a:b]), 1e-6)
        limit = np.maximum(np.abs(np.diff(rz[a:b])) / ds, DECK_AT_GRADE_MAX_GRADE) + 1e-6
        while len(p_):
            # (a point over two junctions: the smaller move; junctions that touch share one plane)
            o = np.lexsort((np.abs(d_), p_))
            first = np.r_[True, p_[o][1:] != p_[o][:-1]]
            pp, dd = p_[o][first], d_[o][first]
            kn = np.r_[stay, pp]
            o = np.argsort(kn, kind="stable")
            move = np.interp(rs[a:b], rs[kn[o]], np.r_[np.zeros(len(stay)), dd][o])
            steep = np.abs(np.diff(rz[a:b] + move)) / ds > limit
            if not steep.any():
                rz[a:b] += move
                out[q] = {jid[j] for j in np.unique(j_).tolist()}
                break
            k = a + int(np.argmax(np.where(steep, np.abs(np.diff(move)), -1.0)))
            near = np.argmin(np.minimum(np.abs(p_ - k), np.abs(p_ - k - 1)))
            keep = j_ != j_[near]
            # (over the junction left out, the deck keeps its height: straight past it, it
            # came down to 1.0-1.4 m over two of Portland's junctions that it was 0.5-0.6 m over)
            stay = np.unique(np.r_[stay, p_[~keep]])
            keep &= ~np.isin(p_, stay)
            p_, j_, d_ = p_[keep], j_[keep], d_[keep]
    return out


def _junction_planes(edges, ref_e, RP, rg, rs, rtot, rz, half_width=None, junctions=None,
                     max_grade: float = JUNCTION_MAX_GRADE, grade_weight: float = 40.0, tie_weight: float = 3.0,
                     ridge: float = 0.5, planes_out: dict | None = None,
                     max_edge_grade: float = EDGE_MAX_GRADE, deck=None, pinned: dict | None = None) -> tuple:
    """Make the ends of the edges that meet at a node lie on one plane (``rz`` in place).

    Each edge's profile is sampled from the ground, so the roads at a junction on a hillside
    ended at the heights of their own patches of ground: metres apart in height a few metres
    apart in plan on a steep Monaco hairpin, and the junction's surface, blended between those
    ends, folded (6 % of Monaco's junction area was steeper than 70 %; a car's chassis caught on
    a fold and stopped).

    Per node, a plane: its tilt fitted to its edge ends' ground heights (least squares,
    slightly damped so that two ends give a line, not a tilt across it) and capped at
    ``max_grade``; its height chosen for all nodes at once (sparse least squares) to keep the
    ends near their ground (1 m of move costs 1) and the grade each edge takes up small (a
    change of an edge's mean grade by 0.1 costs as much as 4 m: ``grade_weight``; but a mean
    grade steeper than ``max_edge_grade`` is asked to come down to it), and two
    different roads that overlap in plan (``half_width`` per profile: the edge's half width)
    at one height where they overlap (``tie_weight`` per profile point), as are a junction
    (``junctions``: id -> polygon ring; its surface is close to its plane) and another
    junction or another node's road that overlaps it (but for a bridge's deck, ``deck`` per
    profile, and what it passes over). Each end moves onto
    its plane and each edge's profile takes its two moves linearly along its length. (Moving
    the ends onto planes set by their own node alone made the short edges between two
    junctions take the difference, Monaco's lanes steeper than 70 % grew 3.4 times; without
    the ties, a street beside a parallel one ended 1 m below it, and the car caught its edge.)
    ``pinned``: node -> plane (x0, y0, z0, gx, gy), as ``planes_out`` gives them: those nodes
    keep that plane (where their edge ends' mean lies within PIN_MATCH_M of x0, y0: the same
    node) and the others are solved around them. The solve couples every node to every other
    through the grades and ties, so two builds of overlapping areas (a streamed window and the
    world it replaces) gave the same street heights up to 0.45 m apart (Portland: the car's
    tile, replaced under it at a swap, trapped it); a window pins the planes the builds before
    it gave (:mod:`netgen.build`, ``road_planes.npz``).
    Returns (how many ends moved by more than 1 cm, how many of ``pinned``'s nodes kept their
    plane)."""
    import scipy.sparse as sp
    from scipy.sparse.linalg import spsolve

    n = len(ref_e)
    if n == 0:
        return 0, 0
    first = np.r_[0, np.nonzero(rg[1:] != rg[:-1])[0] + 1]
    last = np.r_[first[1:] - 1, len(rg) - 1]
    # junctions that overlap share one plane (a cluster no wider than cluster_m)
    rep = _junction_clusters(junctions) if junctions else {}
    num: dict = {}                 # group -> plane number
    ids: dict = {}                 # node -> plane number

    def plane_of(j):
        k = ids.get(j)
        if k is None:
            k = ids[j] = num.setdefault(rep.get(j, j), len(num))
        return k

    node = np.array([plane_of(edges[int(e)].from_node) for e in ref_e]
                    + [plane_of(edges[int(e)].to_node) for e in ref_e], dtype=np.int64)
    m = len(num)
    end = np.concatenate([first, last])
    X, Y, Z = RP[end, 0], RP[end, 1], rz[end]
    cnt = np.bincount(node, minlength=m).astype(float)
    mx, my, mz = (np.bincount(node, V, m) / cnt for V in (X, Y, Z))
    dx, dy, dz = X - mx[node], Y - my[node], Z - mz[node]
    sxx, syy, sxy = (np.bincount(node, A * B, m) for A, B in ((dx, dx), (dy, dy), (dx, dy)))
    sxz, syz = np.bincount(node, dx * dz, m), np.bincount(node, dy * dz, m)
    a, d = sxx + ridge, syy + ridge
    det = a * d - sxy * sxy
    gx = (d * sxz - sxy * syz) / det
    gy = (a * syz - sxy * sxz) / det
    g = np.hypot(gx, gy)
    scale = np.where(g > max_grade, max_grade / np.maximum(g, 1e-12), 1.0)
    gx, gy = gx * scale, gy * scale
    fixed = np.full(m, np.nan)          # c of a pinned plane
    if pinned:
        for j, k in ids.items():
            p = pinned.get(j)
            if p is None or np.isfinite(fixed[k]) or math.hypot(p[0] - mx[k], p[1] - my[k]) > PIN_MATCH_M:
                continue
            gx[k], gy[k] = p[3], p[4]
            fixed[k] = p[2] + p[3] * (mx[k] - p[0]) + p[4] * (my[k] - p[1]) - mz[k]
    # r: each end's height above its node's plane through the mean; the unknown c shifts a
    # node's plane, and an end moves by c[node] - r
    r = dz - gx[node] * dx - gy[node] * dy
    # each end's move is spread linearly along its edge
    L = np.maximum(rtot[:n], 1.0)
    w = grade_weight / L
    k0, k1 = node[:n], node[n:]
    u = rs / np.maximum(rtot[rg], 1e-9)
    rows = [np.arange(2 * n), 2 * n + np.arange(n), 2 * n + np.arange(n)]
    cols = [node, k1, k0]
    # (an edge's mean grade is kept, but for the part beyond max_edge_grade: a DEM's cliff
    # between two junctions 7 m apart gave a Monaco street a 46 % step down, where a car's
    # chassis struck the road at the bottom)
    G = (Z[n:] - Z[:n]) / L
    # (the road between two nodes is as long as the shortest of the edges that join them: a
    # street's other direction, between the same two junctions, can be half as long)
    pair = np.minimum(k0, k1) * m + np.maximum(k0, k1)
    _, inv = np.unique(pair, return_inverse=True)
    shortest = np.full(inv.max() + 1, np.inf)
    np.minimum.at(shortest, inv, L)
    cap = max_edge_grade * shortest[inv] / L
    vals = [np.ones(2 * n), w, -w]
    rhs = [r, w * (r[n:] - r[:n]) + w * L * (np.clip(G, -cap, cap) - G)]
    nr = 3 * n
    if half_width is not None and tie_weight > 0 and len(RP) > 1:
        from scipy.spatial import cKDTree

        # (every other profile point, 5 m apart; centres up to 8 m apart: two 3-lane roads)
        sub = np.arange(0, len(RP), 2)
        pairs = cKDTree(RP[sub]).query_pairs(min(8.0, float(2.0 * np.max(half_width))), output_type="ndarray")
        i, j = sub[pairs[:, 0]], sub[pairs[:, 1]]
        ga, gb = rg[i], rg[j]
        dist = np.hypot(*(RP[i] - RP[j]).T)
        ok = (ga != gb) & (dist < half_width[ga] + half_width[gb] - 0.5)
        if deck is not None:
            ok &= deck[ga] == deck[gb]
        i, j, ga, gb = i[ok], j[ok], ga[ok], gb[ok]
        if len(i):
            t = len(i)
            ui, uj = u[i], u[j]
            rows.append(np.repeat(nr + np.arange(t), 4))
            cols.append(np.column_stack([node[ga], node[n + ga], node[gb], node[n + gb]]).ravel())
            vals.append(tie_weight * np.column_stack([1.0 - ui, ui, -(1.0 - uj), -uj]).ravel())
            rhs.append(tie_weight * (rz[j] - rz[i] + (1.0 - ui) * r[ga] + ui * r[n + ga]
                                     - (1.0 - uj) * r[gb] - uj * r[n + gb]))
            nr += t
    if junctions:
        nr = _junction_ties(junctions, ids, node, n, RP, rg, u, r, rz, mx, my, mz, gx, gy, tie_weight,
                            nr, rows, cols, vals, rhs, deck=deck)
    A = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(nr, m))
    b = np.concatenate(rhs)
    fx = np.isfinite(fixed)
    if fx.any():            # the pinned planes' columns go to the right-hand side
        c = fixed.copy()
        free = np.flatnonzero(~fx)
        if len(free):
            Af = A[:, free]
            bf = b - A[:, np.flatnonzero(fx)] @ fixed[fx]
            c[free] = np.atleast_1d(spsolve((Af.T @ Af).tocsc(), Af.T @ bf))
    else:
        c = spsolve((A.T @ A).tocsc(), A.T @ b)
    dz_end = c[node] - r
    rz += (1.0 - u) * dz_end[:n][rg] + u * dz_end[n:][rg]
    if planes_out is not None:
        # node -> (x0, y0, z0, gx, gy): its plane z0 + gx (x - x0) + gy (y - y0), on which its
        # edges' ends now lie
        for j, k in ids.items():
            planes_out[j] = (float(mx[k]), float(my[k]), float(mz[k] + c[k]), float(gx[k]), float(gy[k]))
    n_pinned = sum(1 for j, k in ids.items() if fx[k] and j in pinned) if pinned else 0
    return int(np.sum(np.abs(dz_end) > 0.01)), n_pinned


def _onto_own_plane(edges, lane_edge, C, cg, cz, tilt, unit_left, planes, junctions,
                    reach: float = OWN_PLANE_REACH_M, fade: float = OWN_PLANE_FADE_M) -> int:
    """A lane whose two ends lie on one plane (its edge joins two junctions drawn into each
    other, which share one plane, or loops back to its node) runs inside that junction
    surface: its points within ``reach`` of the polygons of the junctions on that plane go
    onto it, with the plane's slope across the lane, and those further out fade back to their
    own height over ``fade`` m (``cz`` and ``tilt`` in place). (A lane takes its height from its
    edge's profile, and netconvert can draw a lane far longer than its edge: Monaco's
    `161880706_2`, a 5.9 m edge between two such junctions, is drawn 20 m across them, the
    edge's profile 0.14 m long; it stood 0.4 m over their surface, a kerb that stopped a car
    dead at 7.9 m/s.) Returns how many points moved more than 1 cm."""
    if not len(C) or not planes or not junctions:
        return 0
    by_plane: dict = {}
    for k in np.unique(cg).tolist():
        e = edges[lane_edge[k]]
        pl = planes.get(e.from_node)
        if pl is not None and pl == planes.get(e.to_node):
            by_plane.setdefault(pl, []).append(k)
    if not by_plane:
        return 0
    members: dict = {}
    for j, pl in planes.items():
        if pl in by_plane and j in junctions and len(junctions[j]) >= 3:
            members.setdefault(pl, []).append(j)
    return _lanes_onto_planes(C, cg, cz, tilt, unit_left, by_plane, members, junctions, reach, fade)


def _lanes_onto_planes(C, cg, cz, tilt, unit_left, by_plane: dict, members: dict, junctions: dict,
                       reach: float = OWN_PLANE_REACH_M, fade: float = OWN_PLANE_FADE_M, hold=None) -> int:
    """For :func:`_onto_own_plane` and :func:`_deck_lanes_onto_junctions`: per plane (x0, y0,
    z0, gx, gy), the points of the lanes ``by_plane[plane]`` within ``reach`` of the polygons
    of the junctions ``members[plane]`` go onto it, with its slope across the lane, and those
    further out fade back to their own height over ``fade`` m (``cz``, ``tilt`` in place);
    ``hold`` (per point, 0..1): how much of its own height and slope a point keeps all the same.
    Returns how many points moved more than 1 cm."""
    jids = list(dict.fromkeys(j for js in members.values() for j in js))
    if not jids:
        return 0
    R, rgi = _concat([np.asarray(junctions[j], dtype=float)[:, :2] for j in jids])
    poly = dict(zip(jids, shapely.polygons(shapely.linearrings(R, indices=rgi))))
    moved = 0
    for pl, ks in by_plane.items():
        js = members.get(pl)
        if not js:
            continue
        ks = np.array(ks)
        lo, hi = np.searchsorted(cg, ks, "left"), np.searchsorted(cg, ks, "right")
        pts = np.concatenate([np.arange(a, b) for a, b in zip(lo, hi)])
        P = shapely.points(C[pts])
        d = shapely.distance(np.array([poly[j] for j in js])[:, None], P[None, :]).min(axis=0)
        w = np.clip((d - reach) / fade, 0.0, 1.0)
        if hold is not None:
            w = w + hold[pts] * (1.0 - w)
        x0, y0, z0, gx, gy = pl
        zp = z0 + gx * (C[pts, 0] - x0) + gy * (C[pts, 1] - y0)
        new = zp + w * (cz[pts] - zp)
        moved += int(np.sum(np.abs(new - cz[pts]) > 0.01))
        cz[pts] = new
        across = gx * unit_left[pts, 0] + gy * unit_left[pts, 1]
        tilt[pts] = across + w * (tilt[pts] - across)
    return moved


def _deck_lanes_onto_junctions(lane_edge, C, cg, cz, cs, ctot, tilt, unit_left, planes, junctions,
                               at_grade: dict, opp, reach: float = OWN_PLANE_REACH_M, fade: float = OWN_PLANE_FADE_M) -> int:
    """The lanes of the decks :func:`_decks_onto_junctions` put on junctions' planes (``at_grade``:
    edge number -> junction ids; the lanes of its opposite edge "-X" too, ``opp`` (per edge,
    :func:`_higher_roads`), which share its profile), lane by lane: their points within ``reach`` of those junctions' polygons lie on
    the plane across their width too (the profile is one lane's; a lane beside it, level
    across, stood off a plane tilted across the deck by the grade times its distance from
    it), fading back over ``fade`` m (:func:`_lanes_onto_planes`); but a lane's ends stay on
    their own nodes' planes (:func:`_ends_on_planes`), the move fading in over the same
    :data:`END_FADE_M` (West Burnside's deck ended 0.3 m under the Burnside Bridge's, where
    Naito Parkway's junction reached its end, and a car drove into the step). Returns how many
    points moved more than 1 cm."""
    if not at_grade or not len(C):
        return 0
    jset: dict = {}
    for e, js in at_grade.items():
        for k in (e, int(opp[e])):
            if k >= 0:
                jset.setdefault(k, set()).update(js)
    by_plane: dict = {}
    members: dict = {}
    for k in np.unique(cg).tolist():
        for j in sorted(jset.get(int(lane_edge[k]), ())):    # (not a set's order: PYTHONHASHSEED)
            pl = planes.get(j)
            if pl is None or j not in junctions or len(junctions[j]) < 3:
                continue
            by_plane.setdefault(pl, set()).add(k)
            members.setdefault(pl, set()).add(j)
    by_plane = {pl: sorted(ks) for pl, ks in by_plane.items()}
    members = {pl: sorted(js) for pl, js in members.items()}
    end_fade = np.maximum(np.minimum(END_FADE_M, 0.5 * ctot[cg]), 1e-6)
    hold = np.clip(1.0 - np.minimum(cs, ctot[cg] - cs) / end_fade, 0.0, 1.0)
    return _lanes_onto_planes(C, cg, cz, tilt, unit_left, by_plane, members, junctions, reach, fade, hold=hold)


def _junction_clusters(junctions: dict, reach: float = 0.3, cluster_m: float = 40.0) -> dict:
    """Junctions whose polygons touch (within ``reach``), grouped while a group's bounding box
    stays within ``cluster_m`` (a chain of them along a steep street is not made one plane):
    junction id -> the id standing for its group. (Two junctions side by side, each on its own
    plane, met at a 0.25 m step on a Monaco hillside, which a turning car caught.)"""
    jid = list(junctions)
    if len(jid) < 2:
        return {}
    R, rgi = _concat([junctions[j] for j in jid])
    polys = shapely.polygons(shapely.linearrings(R, indices=rgi))
    lo = np.column_stack([np.minimum.reduceat(R[:, 0], np.r_[0, np.cumsum(np.bincount(rgi))[:-1]]),
                          np.minimum.reduceat(R[:, 1], np.r_[0, np.cumsum(np.bincount(rgi))[:-1]])])
    hi = np.column_stack([np.maximum.reduceat(R[:, 0], np.r_[0, np.cumsum(np.bincount(rgi))[:-1]]),
                          np.maximum.reduceat(R[:, 1], np.r_[0, np.cumsum(np.bincount(rgi))[:-1]])])
    a_, b_ = shapely.STRtree(polys).query(polys, predicate="dwithin", distance=reach)
    sel = a_ < b_
    a_, b_ = a_[sel], b_[sel]
    parent = list(range(len(jid)))
    box = [[lo[i, 0], lo[i, 1], hi[i, 0], hi[i, 1]] for i in range(len(jid))]

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    def nested(a, b) -> bool:
        # a junction mostly inside another's polygon lies on its plane, however wide the other
        # (Lauf: 2189534308, 80 m2, inside cluster_251795596_..., 60 x 43 m, on a plane of its
        # own 0.1 m over it, where a car turning in caught its edge and stood)
        pa, pb = shapely.make_valid(polys[a]), shapely.make_valid(polys[b])
        small = min(pa.area, pb.area)
        return small > 0.0 and shapely.intersection(pa, pb).area >= NESTED_JUNCTION_SHARE * small

    for a, b in zip(a_.tolist(), b_.tolist()):
        ra, rb = find(a), find(b)
        if ra == rb:
            continue
        u = [min(box[ra][0], box[rb][0]), min(box[ra][1], box[rb][1]),
             max(box[ra][2], box[rb][2]), max(box[ra][3], box[rb][3])]
        if max(u[2] - u[0], u[3] - u[1]) > cluster_m and not nested(a, b):
            continue
        parent[rb] = ra
        box[ra] = u
    return {jid[i]: jid[find(i)] for i in range(len(jid)) if find(i) != i or parent[i] != i}


def _junction_ties(junctions, ids, node, n, RP, rg, u, r, rz, mx, my, mz, gx, gy, weight, nr,
                   rows, cols, vals, rhs, reach: float = 0.5, deck=None) -> int:
    """Rows for :func:`_junction_planes` (appended to rows/cols/vals/rhs; returns the new row
    count) that put a junction's plane at the height of what overlaps it: another junction
    (at each polygon's corners within ``reach`` of the other; two junctions side by side on a
    hillside met at a 0.25 m step, which a turning car caught) and the profile points (every
    other one) of roads of other nodes inside it (not of a bridge's deck: ``deck`` per
    profile). Junctions whose polygon is invalid are left out."""
    jid = [j for j in junctions if j in ids]
    if not jid:
        return nr
    R, rgi = _concat([junctions[j] for j in jid])
    polys = shapely.polygons(shapely.linearrings(R, indices=rgi))
    ok = shapely.is_valid(polys)
    k = np.array([ids[j] for j in jid])

    def plane0(kk, x, y):          # a node's plane before its shift c
        return mz[kk] + gx[kk] * (x - mx[kk]) + gy[kk] * (y - my[kk])

    valid = np.flatnonzero(ok)
    polys, k = polys[valid], k[valid]
    remap = -np.ones(len(ok), dtype=np.int64)
    remap[valid] = np.arange(len(valid))
    vsel = remap[rgi] >= 0
    V, vj = R[vsel], remap[rgi[vsel]]
    # corners of each junction near another junction (the polygons queried against a tree of
    # the points: a few thousand queries, not tens of thousands)
    # (pairs by bounding box first, those of one cluster dropped, then the distance: most pairs
    # are a polygon and its own corners)
    box = shapely.bounds(polys) + np.array([-reach, -reach, reach, reach])
    pts = shapely.points(V)
    pj, vi = shapely.STRtree(pts).query(shapely.box(*box.T))
    keep = k[vj[vi]] != k[pj]                  # (junctions of one cluster share their plane)
    vi, pj = vi[keep], pj[keep]
    keep = shapely.dwithin(pts[vi], polys[pj], reach)
    vi, pj = vi[keep], pj[keep]
    if len(vi):
        t = len(vi)
        ka, kb = k[vj[vi]], k[pj]
        X, Y = V[vi, 0], V[vi, 1]
        rows += [nr + np.arange(t), nr + np.arange(t)]
        cols += [ka, kb]
        vals += [np.full(t, weight), np.full(t, -weight)]
        rhs.append(weight * (plane0(kb, X, Y) - plane0(ka, X, Y)))
        nr += t
    # profile points of roads inside a junction they do not end at
    sub = np.arange(0, len(RP), 2)
    ji, pi = shapely.STRtree(shapely.points(RP[sub])).query(polys, predicate="contains")
    if len(pi):
        pi = sub[pi]
        g = rg[pi]
        kj = k[ji]
        ka0, ka1 = node[g], node[n + g]
        ok = (ka0 != kj) & (ka1 != kj)
        if deck is not None:
            ok &= ~deck[g]
        pi, g, kj, ka0, ka1 = pi[ok], g[ok], kj[ok], ka0[ok], ka1[ok]
        t = len(pi)
        if t:
            uu = u[pi]
            rows.append(np.repeat(nr + np.arange(t), 3))
            cols.append(np.column_stack([ka0, ka1, kj]).ravel())
            vals.append(weight * np.column_stack([1.0 - uu, uu, -np.ones(t)]).ravel())
            rhs.append(weight * (plane0(kj, RP[pi, 0], RP[pi, 1]) - rz[pi] + (1.0 - uu) * r[g] + uu * r[n + g]))
            nr += t
    return nr


def _opposite_profiles(edges, ref_e) -> np.ndarray:
    """Per edge, the profile group (of ``ref_e``) of its opposite edge "X" for an edge "-X"
    that has a profile, whose lanes take their heights from it
    (:func:`_share_opposite_profiles`); -1 for the others."""
    group_of = {int(e): g for g, e in enumerate(ref_e)}         # edge number -> profile group
    number_of = {e.id: i for i, e in enumerate(edges)}
    target = np.full(len(edges), -1, dtype=np.int64)
    for i, e in enumerate(edges):
        if i not in group_of or not e.id.startswith("-"):
            continue
        j = number_of.get(e.id[1:])
        if j is not None and j in group_of:
            target[i] = group_of[j]
    return target


def _share_opposite_profiles(edges, lane_edge, ref_e, RP, rg, rz, C, cg, cz, max_d: float = 8.0,
                             target=None) -> int:
    """Heights ``cz`` (in place) of the lane points of every edge "-X" whose opposite edge "X"
    has a profile: that profile's height where the point projects onto it (an edge none of
    whose points comes within ``max_d`` of it keeps its own). Returns how many points
    changed. (Taking the middle lanes' heights by projection too, not only the others',
    changed the steep Monaco street's profile so that the speed test went over its 0.3 m/s:
    left for later.) ``target``: :func:`_opposite_profiles`, if made already."""
    if target is None:
        target = _opposite_profiles(edges, ref_e)
    tg = target[lane_edge[cg]]
    sel = np.nonzero(tg >= 0)[0]
    if not len(sel) or not len(RP):
        return 0
    best_z, best_d = _onto_profiles(RP, rg, rz, C[sel], tg[sel])
    # (per edge: all its lanes where the nearest lies within max_d, or none; lane by lane, a
    # Lauf street's inner lane at 6.4 m took the other direction's profile and the lane beside
    # it at 9.6 m its own, and they met at steps of up to 0.57 m)
    ed = lane_edge[cg[sel]]
    near = np.full(len(edges), np.inf)
    np.minimum.at(near, ed, best_d)
    use = np.isfinite(best_z) & (near[ed] <= max_d)
    cz[sel[use]] = best_z[use]
    return int(use.sum())


def _onto_profiles(RP, rg, rz, pts, groups):
    """Height of profile `groups[i]` (of the profiles RP, rg, rz) where point `pts[i]`
    projects onto it, and the distance to it (NaN, inf where none of the profile's points is
    among the 16 nearest). (Given the profiles' fractions of their length as `rz`, the
    fraction there.)"""
    n = len(RP)
    if not len(pts) or not n:
        return np.full(len(pts), np.nan), np.full(len(pts), np.inf)
    sub = np.flatnonzero(np.isin(rg, np.unique(groups)))    # (the tree over those profiles only)
    if not len(sub):
        return np.full(len(pts), np.nan), np.full(len(pts), np.inf)
    k = min(16, len(sub))
    _, idx = cKDTree(RP[sub]).query(pts, k=k, workers=-1)
    idx = sub[idx.reshape(len(pts), k)]
    same = rg[idx] == groups[:, None]
    has = same.any(axis=1)
    j = idx[np.arange(len(pts)), np.argmax(same, axis=1)]
    best_z = np.full(len(pts), np.nan)
    best_d = np.full(len(pts), np.inf)
    for a_off in (-1, 0):           # the segments (j-1, j) and (j, j+1) of the same profile
        a, b = j + a_off, j + a_off + 1
        ok = has & (a >= 0) & (b < n)
        a, b = np.clip(a, 0, n - 1), np.clip(b, 0, n - 1)
        ok &= (rg[a] == rg[j]) & (rg[b] == rg[j])
        v = RP[b] - RP[a]
        L2 = np.maximum((v * v).sum(axis=1), 1e-12)
        t = np.clip(((pts - RP[a]) * v).sum(axis=1) / L2, 0.0, 1.0)
        dist = np.hypot(*(RP[a] + t[:, None] * v - pts).T)
        better = ok & (dist < best_d)
        best_d = np.where(better, dist, best_d)
        best_z = np.where(better, rz[a] + t * (rz[b] - rz[a]), best_z)
    return best_z, best_d


def _higher_roads(edges, lanes, lane_edge, junctions):
    """For :func:`_conform_to_higher_roads`: the vehicle lanes (numbers, their strips less
    :data:`SIDEWALK_INTRUSION_M` along each side), each edge's rank (OSM layer, a bridge being
    1; netconvert's priority, vehicle lanes, width, then the id), its nodes' numbers, and
    the nodes' positions and radii (their junction shape's farthest point; NaN and 0 for a
    node without a junction), which edges are a bridge's deck (:func:`_deck_clearance`), and
    each edge's opposite ("X" and "-X"; -1: none)."""
    ne = len(edges)
    veh = np.array([k for k, ln in enumerate(lanes) if ln.drivable and not (ln.allowed and ln.allowed <= RAIL_CLASSES)],
                   dtype=np.int64)
    nveh = np.bincount(lane_edge[veh], minlength=ne)
    width = np.bincount(lane_edge, np.array([ln.width for ln in lanes]), minlength=ne)
    nv, wr = nveh.tolist(), np.round(width, 2).tolist()     # (numpy's rounding, as before: plain numbers as keys)
    order = sorted(range(ne), key=lambda i: (edges[i].layer, edges[i].priority, nv[i], wr[i], edges[i].id))
    rank = np.empty(ne, dtype=np.int64)
    rank[order] = np.arange(ne)
    cores = _lane_strips([lanes[k] for k in veh], inset=SIDEWALK_INTRUSION_M)
    shapely.prepare(cores)
    node_no: dict = {}
    fn = np.array([node_no.setdefault(e.from_node, len(node_no)) for e in edges], dtype=np.int64)
    tn = np.array([node_no.setdefault(e.to_node, len(node_no)) for e in edges], dtype=np.int64)
    nxy = np.full((len(node_no), 2), np.nan)
    nrad = np.zeros(len(node_no))
    for nid, k in node_no.items():
        j = junctions.get(nid)
        if j is not None:
            nxy[k] = (j.x, j.y)
            if j.shape is not None and len(j.shape):
                nrad[k] = float(np.max(np.hypot(j.shape[:, 0] - j.x, j.shape[:, 1] - j.y)))
    deck = np.array([bool(getattr(e, "bridge", False)) for e in edges], dtype=bool)
    num = {e.id: k for k, e in enumerate(edges)}
    opp = np.array([num.get(e.id[1:] if e.id.startswith("-") else "-" + e.id, -1) for e in edges], dtype=np.int64)
    return veh, cores, rank, fn, tn, shapely.bounds(cores), nxy, nrad, deck, opp


def _box_pairs(bmin, bmax, boxes, cell: float = 25.0):
    """Pairs (i, j) of boxes ``(bmin[i], bmax[i])`` (many, small) and ``boxes[j]`` (xmin,
    ymin, xmax, ymax) that overlap: each small box hashed to the grid cell of its centre, each
    big one to every cell it covers grown by the largest small half size, then the boxes
    compared (numpy: tens of thousands of shapely boxes and an STRtree query cost more)."""
    if not len(bmin) or not len(boxes):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    grow = float(np.max(bmax - bmin)) / 2.0
    cen = _keys(np.floor((bmin + bmax) / 2.0 / cell).astype(np.int64))
    i, j = _cell_pairs(np.floor((boxes[:, :2] - grow) / cell).astype(np.int64),
                       np.floor((boxes[:, 2:] + grow) / cell).astype(np.int64), cen)
    ok = (bmin[i, 0] <= boxes[j, 2]) & (bmax[i, 0] >= boxes[j, 0]) & (bmin[i, 1] <= boxes[j, 3]) & \
         (bmax[i, 1] >= boxes[j, 1])
    return i[ok], j[ok]


def _higher_overlaps(lane_edge, higher, P, g, own_edge, halfw, only=None, twins: bool = False,
                     any_rank: bool = False, top: bool = True, min_overlap: float = CONFORM_MIN_OVERLAP_M,
                     near_nodes: bool = False):
    """For :func:`_conform_to_higher_roads`: the points (numbers) whose cross-section runs far
    enough inside a vehicle lane of a higher-ranked road that their road does not meet at a
    node, with that lane (number among the vehicle lanes) and its edge: the highest-ranked
    one per point. With ``twins``, twin roads (:data:`CONFORM_TWIN_MIN_OVERLAP_M`) count too;
    with ``any_rank``, the roads of any rank but the point's own, and without ``top`` every such
    (point, lane, road), not only the highest-ranked road's per point (:func:`_top_overlaps`);
    ``min_overlap``: how far (m) a cross-section runs inside the lane to count. With
    ``near_nodes``, only the points near a node their road and the other meet at (where they
    are otherwise left out), of roads that are neither twins nor each other's opposite."""
    veh, cores, rank, fn, tn, core_box, nxy, nrad, _, opp = higher
    none = np.zeros(0, np.int64)
    sel = np.arange(len(P)) if only is None else np.flatnonzero(only)
    if not len(sel):
        return none, none, none
    nrm = _normals_many(P, g)[sel] * halfw[sel, None]
    lo, hi = P[sel] - nrm, P[sel] + nrm
    # (pairs by bounding box, then the cheap tests, then the geometry)
    qi, vi = _box_pairs(np.minimum(lo, hi), np.maximum(lo, hi), core_box)
    A, B = own_edge[sel[qi]], lane_edge[veh[vi]]
    # roads that meet at a node: only away from it (its junction's reach and
    # CONFORM_NODE_CLEAR_M more), where two one-way streets between the same two nodes run
    # over each other (Lauf: 0.1-0.2 m apart in height at a bend, a step the car ran into)
    ok = B != A if any_rank else rank[B] > rank[A]
    Q = P[sel[qi]]
    # (a street's two directions share one profile already: no twins)
    twin = (((fn[A] == fn[B]) & (tn[A] == tn[B])) | ((fn[A] == tn[B]) & (tn[A] == fn[B]))) & twins & (opp[A] != B)
    near = np.zeros(len(qi), dtype=bool)
    for a in (fn[A], tn[A]):
        shared = (a == fn[B]) | (a == tn[B])
        d = np.hypot(Q[:, 0] - nxy[a, 0], Q[:, 1] - nxy[a, 1])
        near |= shared & ~(d > nrad[a] + np.where(twin, CONFORM_TWIN_NODE_CLEAR_M, CONFORM_NODE_CLEAR_M))  # (NaN: never far)
    ok &= (near & ~twin & (opp[A] != B)) if near_nodes else ~near
    qi, vi, B, twin = qi[ok], vi[ok], B[ok], twin[ok]
    if not len(qi):
        return none, none, none
    sections = shapely.linestrings(np.stack([lo[qi], hi[qi]], axis=1))
    ok = shapely.intersects(cores[vi], sections)            # (prepared: fast)
    qi, vi, B, twin, sections = qi[ok], vi[ok], B[ok], twin[ok], sections[ok]
    ok = shapely.length(shapely.intersection(sections, cores[vi])) >= np.where(
        twin, CONFORM_TWIN_MIN_OVERLAP_M, min_overlap)
    pi, vi, B, twin = sel[qi[ok]], vi[ok], B[ok], twin[ok]
    if not len(pi) or not top:
        return pi, vi, B
    # per point, the highest-ranked road; a twin only where no other road is (a Monaco service
    # road taken up to its twin stood 0.23 m through a street it runs under)
    return _top_overlaps(pi, vi, B, rank[B] + np.where(twin, 0, len(rank)))


def _top_overlaps(pi, vi, B, key):
    """Of (point, lane, road) triples, each point's one with the highest ``key``."""
    if not len(pi):
        return pi, vi, B
    o = np.lexsort((key, pi))
    pi, vi, B = pi[o], vi[o], B[o]
    last = np.r_[pi[1:] != pi[:-1], True]
    return pi[last], vi[last], B[last]


def _conform_to_higher_roads(edges, lanes, lane_edge, higher, P, g, s, z, own_edge, halfw, onto,
                             lower_only: bool = False, only=None, fade: float = CONFORM_FADE_M,
                             cache: dict | None = None, twins: bool = False, max_apart: float = CONFORM_MAX_M,
                             raise_only: bool = False, pointwise: bool = False, hold=None) -> int:
    """Heights ``z`` (in place) of the points `P` (lines `g`, arc length `s`) of roads that
    overlap a higher-ranked road without meeting it at a node (or far from the node where they
    meet: :data:`CONFORM_NODE_CLEAR_M`): where a point's cross-section
    (``halfw`` either side) runs for :data:`CONFORM_MIN_OVERLAP_M` or more inside a vehicle
    lane of such a road (:func:`_higher_roads`), it takes that road's height, 2 cm under it
    (``onto(points, lane numbers, edge numbers)``); the move fades out along the line over
    ``fade`` metres either side. With ``lower_only``, points only move down; ``only`` (a
    mask) limits the points looked at (not the fade); ``cache`` (a dict) keeps which points
    overlap which roads for another call on the same points; ``twins`` (the edges' profiles,
    before the junction planes) conforms twin roads too (:data:`CONFORM_TWIN_MIN_OVERLAP_M`,
    up to their nodes). Two roads that are more than ``max_apart`` (:data:`CONFORM_MAX_M`) apart in height anywhere they
    overlap are a bridge and the road under it: neither moves (with ``raise_only`` or
    ``pointwise``, only the points that far apart stay). ``hold`` (per point, 0..1): the share
    of its move each point takes (a lane's ends, 0, stay on their junctions' planes).

    Roads that cross without a junction are a bridge or tunnel that OSM does not tag (a
    service road in Monaco's old railway tunnel under Boulevard Princesse Charlotte), or a
    bridge the world keeps on the ground; and a street's two carriageways mapped closer than
    their lanes' widths overlap. Each edge's profile follows its own patch of ground, so on a
    hillside one stood through the other: the tunnel's road 0.3 m proud of the boulevard's
    lane, which a car drove into; the two carriageways of Avenue Princesse Grace 1.4 m apart
    where they overlap. Returns how many points moved."""
    veh = higher[0]
    if not len(P) or not len(veh):
        return 0
    if cache is not None and "pairs" in cache:
        pi, vi, B = cache["pairs"]
    else:
        pi, vi, B = _higher_overlaps(lane_edge, higher, P, g, own_edge, halfw, only, twins)
        if cache is not None:
            cache["pairs"] = (pi, vi, B)
    if not len(pi):
        return 0
    tz = onto(P[pi], veh[vi], B)
    fin = np.isfinite(tz)
    pi, B, tz = pi[fin], B[fin], tz[fin] - CONFORM_BELOW_M
    # two roads further apart in height than a car is tall are a bridge and the road under it
    # (a car on the lower one passes under the other): both stay
    pair = own_edge[pi] * len(edges) + B
    _, inv = np.unique(pair, return_inverse=True)
    apart = np.zeros(inv.max() + 1 if len(inv) else 0)
    np.maximum.at(apart, inv, np.abs(tz - z[pi]))
    # (with raise_only, point by point: where a bridge comes down to its end beside a road
    # it crosses, or a road climbs beside one)
    keep = (np.abs(tz - z[pi]) if raise_only or pointwise else apart[inv]) <= max_apart
    pi, tz = pi[keep], tz[keep]
    n = len(P)
    delta = np.zeros(n)             # (the move, not the height, fades: the road keeps its grade)
    delta[pi] = tz - z[pi]
    if lower_only:
        delta = np.minimum(delta, 0.0)
    if raise_only:
        delta = np.maximum(delta, 0.0)
    on = np.zeros(n, dtype=bool)
    on[pi[delta[pi] != 0.0]] = True
    if not on.any():
        return 0
    # each point: the nearest moved point of its own line, along it
    idx = np.arange(n)
    prev = np.maximum.accumulate(np.where(on, idx, -1))
    nxt = np.minimum.accumulate(np.where(on, idx, n)[::-1])[::-1]
    pv, nx = np.clip(prev, 0, n - 1), np.clip(nxt, 0, n - 1)
    dprev = np.where((prev >= 0) & (g[pv] == g), s - s[pv], np.inf)
    dnext = np.where((nxt < n) & (g[nx] == g), s[nx] - s, np.inf)
    near = np.where(dprev <= dnext, pv, nx)
    w = np.clip(1.0 - np.minimum(dprev, dnext) / fade, 0.0, 1.0)
    moved = w > 0.0
    z[moved] += w[moved] * delta[near[moved]] * (1.0 if hold is None else hold[moved])
    return int(moved.sum())


def surface_meshes(net, step: float) -> dict:
    """The junctions' and walking areas' polygons and their triangulations in the plane
    (constrained Delaunay, points every `step` m inside), which need nothing but the network:
    ``polys``, ``pkind`` ("asphalt" or "sidewalk"), ``pid`` (junction or walking area id),
    ``pel`` (element), and ``tri``: kind -> (the polygons' indices, :func:`_dense_triangulated`'s
    V, vg, F, fg). :func:`build_roads` makes them, or takes them made in another process (the
    build's second process makes them while this one fits the roads' heights)."""
    gap_j, gap_lanes = junction_gaps(net)
    cuts = {}
    if gap_lanes:
        for j, strip in zip(gap_j, _lane_strips(gap_lanes)):
            cuts.setdefault(j, []).append(strip)
        cuts = {j: shapely.union_all(v) for j, v in cuts.items()}
    polys, pkind, pid, pel = [], [], [], []
    under = underground_junctions(net)
    # walking areas that a lane's strip cuts: the part of each the strips leave (all at once:
    # most are valid polygons, and GEOS's repair is slow even on those)
    wa_cut, wa_ids, wa_rings, wa_cuts = {}, [], [], []
    for e in net.edges.values():
        if e.function == "walkingarea" and e.lanes and len(e.lanes[0].shape) >= 3:
            cut = cuts.get(e.id[1:e.id.rfind("_w")])
            r = _open_ring(e.lanes[0].shape[:, :2]) if cut is not None else None
            if r is not None:
                wa_ids.append(e.id); wa_rings.append(r); wa_cuts.append(cut)
    if wa_ids:
        R_, rg_ = _concat(wa_rings)
        wa = shapely.polygons(shapely.linearrings(R_, indices=rg_))
        bad_ = ~shapely.is_valid(wa)
        wa[bad_] = _repaired(wa[bad_])
        wcut = np.array(wa_cuts, dtype=object)
        hit = np.flatnonzero(shapely.area(shapely.intersection(wa, wcut)) > 0.5)
        for k, g in zip(hit, shapely.difference(wa[hit], wcut[hit])):
            wa_cut[wa_ids[k]] = _polygon_rings(g)
    for j in net.junctions.values():
        if j.type != "internal" and len(j.shape) >= 3 and j.id not in under:
            polys.append(j.shape); pkind.append("asphalt"); pid.append(j.id); pel.append("junction")
    for e in net.edges.values():
        if e.function == "walkingarea" and under and e.id[1:e.id.rfind("_w")] in under:
            continue
        if e.function == "walkingarea" and e.lanes and len(e.lanes[0].shape) >= 3:
            for shp in wa_cut.get(e.id, (e.lanes[0].shape,)):
                polys.append(shp); pkind.append("sidewalk"); pid.append(e.id); pel.append("walkingarea")
    # netconvert's polygon of a junction can cross itself (Monaco: 177 of its 2,272), and
    # earcut then covered part of it (215 m2 of Monaco's junctions were bare ground; a road
    # crossing cluster_25193390_6444966511 ran over a hole): such a junction is meshed as the
    # polygons of its valid form
    jk = [k for k in range(len(polys)) if pkind[k] == "asphalt"]
    rings = [_open_ring(np.asarray(polys[k])[:, :2]) for k in jk]
    has = [i for i, r in enumerate(rings) if r is not None]
    if has:
        R_, rg_ = _concat([rings[i] for i in has])
        jp_ = shapely.polygons(shapely.linearrings(R_, indices=rg_))
        bad_ = np.flatnonzero(~shapely.is_valid(jp_))
        if len(bad_):
            vparts, vof = shapely.get_parts(_repaired(jp_[bad_]), return_index=True)
            keep_ = (shapely.get_type_id(vparts) == 3) & (shapely.area(vparts) > 0.05)
            fixed: dict = {}
            for g, b in zip(vparts[keep_], vof[keep_]):
                fixed.setdefault(jk[has[bad_[b]]], []).append(np.asarray(g.exterior.coords)[:, :2])
            for k in sorted((jk[has[b]] for b in bad_), reverse=True):
                f = fixed.get(k, [])
                polys[k:k + 1] = f
                pkind[k:k + 1] = [pkind[k]] * len(f)
                pid[k:k + 1] = [pid[k]] * len(f)
                pel[k:k + 1] = [pel[k]] * len(f)

    tri = {}
    for kind in ("asphalt", "sidewalk"):
        cand = [k for k in range(len(polys)) if pkind[k] == kind]
        tri[kind] = (cand,) + tuple(_dense_triangulated([polys[k] for k in cand], step))
    return {"polys": polys, "pkind": pkind, "pid": pid, "pel": pel, "tri": tri}


def build_roads(net, ground, step: float = 2.5, on_support=None, pinned: dict | None = None,
                surfaces=None) -> RoadGeometry:
    """Meshes for every SUMO edge, junction, walking area and crossing of `net`.

    `ground(x, y)` is the natural terrain height (vectorised). `on_support(pts, hw, car, tris,
    hold)`, if given, is called with the levelling support (:attr:`RoadGeometry.support_pts`,
    ``support_hw``, ``support_car``, ``support_tris``, ``support_hold``) as soon as it is complete, before the rest of the meshing (lane strips,
    markings, walking areas, crossings), so that the terrain can be levelled meanwhile.
    ``pinned``: planes of nodes to keep (:func:`_junction_planes`); the planes of all nodes
    are in :attr:`RoadGeometry.planes`. ``surfaces``: a function that returns
    :func:`surface_meshes` for this `step` made elsewhere (or None: made here)."""
    geo = RoadGeometry(net=net)
    edges, lanes, lane_edge, refs = _road_lanes(net)

    # 1. height profile per edge along its middle lane
    ref_e = np.array([r[0] for r in refs], dtype=np.int64)
    RP, rg = _concat([r[1] for r in refs])
    RP, rg = resample_many(RP, rg, step)
    rs, rtot = _arclen(RP, rg)
    rkey = 2.0 * ref_e[rg] + rs / np.maximum(rtot[rg], 1e-9)
    rz = _smooth_profiles(np.asarray(ground(RP[:, 0], RP[:, 1]), dtype=float), rg, PROFILE_SMOOTH_PASSES)
    rz = _limit_grade(rz, rs, rg, MAX_PROFILE_GRADE)
    edge_hw = np.zeros(len(edges))
    np.add.at(edge_hw, lane_edge, 0.5 * np.array([ln.width for ln in lanes]))
    under = underground_junctions(net)
    jrings = {j.id: r for j in net.junctions.values()
              if j.type != "internal" and j.id not in under and j.shape is not None and len(j.shape) >= 3
              for r in (_open_ring(j.shape[:, :2]),) if r is not None}
    # roads that overlap a higher-ranked road without a junction take its height there: before
    # the planes are fitted (so that the nodes near the overlap follow) and again after
    higher = _higher_roads(edges, lanes, lane_edge, net.junctions)
    core_tree = shapely.STRtree(higher[1])          # (their vehicle lanes' strips, for the passes below)
    group_of = np.full(len(edges), -1, dtype=np.int64)
    group_of[ref_e] = np.arange(len(ref_e))

    def onto_profile(pts, lane_no, edge_no):        # (the other road's profile, where it projects)
        gB = group_of[edge_no]
        z, _ = _onto_profiles(RP, rg, rz, pts, gB)
        return np.where(gB >= 0, z, np.nan)

    # bridges' decks: straight between where they meet the ground, and clear of the roads under them
    edge_deck = higher[8]
    deck = edge_deck[ref_e]                                     # (per profile: a bridge's deck)
    deck_graph = _deck_nodes(edges, ref_e, deck) if deck.any() else None
    _bridge_decks(edges, ref_e, rg, rs, rtot, rz, deck, nodes=deck_graph)

    # (roads with vehicle lanes: a footway's lanes on a road are left out, as sidewalks are)
    vehicle_edge = np.bincount(lane_edge[higher[0]], minlength=len(edges)) > 0
    overlaps: dict = {}
    conform = lambda: _conform_to_higher_roads(edges, lanes, lane_edge, higher, RP, rg, rs, rz,   # noqa: E731
                                               ref_e[rg], edge_hw[ref_e[rg]], onto_profile,
                                               only=vehicle_edge[ref_e[rg]], cache=overlaps, twins=True)
    conform()
    planes: dict = {}
    ends_moved, n_pinned = _junction_planes(edges, ref_e, RP, rg, rs, rtot, rz, half_width=edge_hw[ref_e],
                                            junctions=jrings, planes_out=planes, deck=deck, pinned=pinned)
    geo.planes = planes

    conformed = conform()
    # and a road that leaves a node beside a higher-ranked one, inside its lane near the node,
    # comes down onto it there (FORK_CONFORM_MAX_M; after the planes: before them, the moves
    # changed the nodes' planes and left steps between lanes and junctions in Lauf)
    forks = _higher_overlaps(lane_edge, higher, RP, rg, ref_e[rg], edge_hw[ref_e[rg]], only=vehicle_edge[ref_e[rg]],
                             near_nodes=True)
    if len(forks[0]):
        conformed += _conform_to_higher_roads(edges, lanes, lane_edge, higher, RP, rg, rs, rz, ref_e[rg],
                                              edge_hw[ref_e[rg]], onto_profile, lower_only=True, pointwise=True,
                                              max_apart=FORK_CONFORM_MAX_M, fade=FORK_FADE_M,
                                              cache={"pairs": forks})
    # roads stacked in OSM's layers, neither a bridge: the lower goes under the higher
    opposite_profile = _opposite_profiles(edges, ref_e)
    stacked = _stack_under_higher_layers(edges, lanes, lane_edge, higher, ref_e, group_of, opposite_profile,
                                         RP, rg, rs, rz, vehicle_edge, onto_profile, step, jrings, edge_hw)
    geo.stacked_over = stacked
    at_grade: dict = {}
    if deck.any():
        deck_nodes = {n for e, d in zip(edges, edge_deck) if d for n in (e.from_node, e.to_node)}
        # (the junctions near a deck's profile: those it may pass over)
        jids = [j for j in jrings if j in planes]
        cen = np.array([jrings[j].mean(axis=0) for j in jids]).reshape(-1, 2)
        rad = np.array([np.max(np.hypot(*(jrings[j] - c).T)) for j, c in zip(jids, cen)])
        near, _ = cKDTree(RP[deck[rg]]).query(cen, k=1, workers=-1) if len(jids) else (np.zeros(0), None)
        jids = [j for j, d, r in zip(jids, near, rad) if d <= r + float(edge_hw.max()) + 5.0]
        jpolys = _repaired_polygons([jrings[j] for j in jids])
        # (the roads under the decks, and the junctions at grade with them too: a deck's node
        # lifted for one road did not take another deck of it up over a junction it crossed at
        # grade, to stand 1.5-1.9 m over it)
        def lift_need(idx):
            own_e = ref_e[rg[idx]]
            road = _deck_clearance(RP, idx, own_e, edge_hw[own_e], ~edge_deck, higher, lane_edge, onto_profile,
                                   core_tree)
            junction = _deck_junction_clearance(RP, idx, own_e, edge_hw[own_e], rz, planes, jids, jpolys, edges,
                                                deck_nodes, min_gap=-CONFORM_MAX_M)
            # (and how far over it a deck comes down onto it later: _decks_onto_junctions, the
            # deck's lanes onto a road's)
            return np.fmax(road, junction), np.where(junction >= np.nan_to_num(road, nan=-np.inf), CONFORM_MAX_M,
                                                     DECK_DOWN_MAX_M)

        if deck_graph[4].any():                 # (nodes along a bridge)
            _lift_viaducts(edges, ref_e, rg, rs, rtot, rz, deck, planes, lift_need,
                           keep=_deck_ends_on_other_junctions(edges, ref_e, RP, rg, deck, edge_hw, jids, jpolys),
                           nodes=deck_graph)
        before = rz.copy()
        _raise_decks(edges, ref_e, rg, rs, rz, deck, edge_deck, lambda idx, own_e, under_e: _deck_clearance(
            RP, idx, own_e, edge_hw[own_e], under_e, higher, lane_edge, onto_profile, core_tree),
            lambda idx, own_e: _deck_junction_clearance(RP, idx, own_e, edge_hw[own_e], rz, planes, jids, jpolys,
                                                        edges, deck_nodes))
        # a deck that stayed down over a junction of other roads is at grade there: on its
        # plane, and the roads conformed under it follow it
        raised = np.bincount(rg, np.abs(rz - before) > 1e-9, len(ref_e)) > 0
        # (a deck keeps its height where it lies on or under a higher road, and where it
        # clears a road under it by more than a car's height)
        fixed = np.zeros(len(rz), dtype=bool)
        if "pairs" in overlaps:
            pi, _, B = overlaps["pairs"]
            fixed[pi] = True
            gB = group_of[B]
            over = (gB >= 0) & deck[np.maximum(gB, 0)]
            at, _ = _onto_profiles(RP, rg, np.arange(len(rz), dtype=float), RP[pi[over]], gB[over])
            zd, _ = _onto_profiles(RP, rg, rz, RP[pi[over]], gB[over])
            with np.errstate(invalid="ignore"):
                at = at[np.isfinite(at) & (zd - rz[pi[over]] > CONFORM_MAX_M)]
            fixed[np.floor(at).astype(np.int64)] = True
            fixed[np.ceil(at).astype(np.int64)] = True
        # (decks with vehicle lanes, over junctions where a road with vehicle lanes meets: a
        # footbridge's or a path's piece off a carriageway's height is left out there, as
        # sidewalks are, _sidewalks_off_other_roads)
        car_nodes = {n for e, v in zip(edges, vehicle_edge) if v for n in (e.from_node, e.to_node)}
        at_grade = _decks_onto_junctions(edges, ref_e, RP, rg, rs, rz, deck, edge_hw[ref_e], planes,
                                         {j: r for j, r in jrings.items() if j in car_nodes},
                                         skip=raised | ~vehicle_edge[ref_e], fixed=fixed)
        if at_grade and "pairs" in overlaps:
            pi, vi, B = overlaps["pairs"]
            sel = np.isin(B, ref_e[list(at_grade)])
            conformed += _conform_to_higher_roads(edges, lanes, lane_edge, higher, RP, rg, rs, rz, ref_e[rg],
                                                  edge_hw[ref_e[rg]], onto_profile,
                                                  cache={"pairs": (pi[sel], vi[sel], B[sel])})

    # 2. lane centrelines, resampled, with heights from their edge's profile
    LP, lg = _concat([l.shape for l in lanes])
    C, cg = resample_many(LP, lg, step)
    cs, ctot = _arclen(C, cg)
    frac = cs / np.maximum(ctot[cg], 1e-9)
    # the other lanes of an edge take its profile's height where each point projects onto it,
    # not at the same fraction of their own length: on a bend the inner lane is shorter, and at
    # an angled junction border the lanes' ends are staggered (Monaco: seams between two lanes
    # of one edge stepping over 0.1 m 3.85 -> 0.71 %); sidewalks, and a point that finds no
    # profile, between where their ends project
    ref_shape = {int(ei): id(shp) for ei, shp in refs}
    other = np.flatnonzero([id(ln.shape) != ref_shape.get(int(e), 0) for ln, e in zip(lanes, lane_edge)])
    if len(other):
        lfirst = np.r_[0, np.nonzero(cg[1:] != cg[:-1])[0] + 1]
        llast = np.r_[lfirst[1:] - 1, len(cg) - 1]
        grp_of = np.full(len(edges), -1, dtype=np.int64)
        grp_of[ref_e] = np.arange(len(ref_e))
        og = grp_of[lane_edge[other]]
        other, og = other[og >= 0], og[og >= 0]
        at, d = _onto_profiles(RP, rg, rs / np.maximum(rtot[rg], 1e-9),
                               np.vstack([C[lfirst[other]], C[llast[other]]]), np.concatenate([og, og]))
        f0, f1 = at[:len(other)], at[len(other):]
        ok = np.isfinite(f0) & np.isfinite(f1) & (d[:len(other)] <= 8.0) & (d[len(other):] <= 8.0)
        lf0, lf1 = np.zeros(len(lanes)), np.ones(len(lanes))
        lf0[other[ok]], lf1[other[ok]] = f0[ok], f1[ok]
        frac = lf0[cg] + (lf1 - lf0)[cg] * frac
    key = 2.0 * lane_edge[cg] + frac
    cz = np.interp(key, rkey, rz)
    car_other = other[[lanes[k].drivable for k in other]] if len(other) else other
    if len(car_other):        # (vehicle lanes: sidewalks keep the mapping by their ends)
        po = np.flatnonzero(np.isin(cg, car_other))
        zo, do = _onto_profiles(RP, rg, rz, C[po], grp_of[lane_edge[cg[po]]])
        okp = np.isfinite(zo) & (do <= 8.0)
        cz[po[okp]] = zo[okp]
    # the two directions of one road ("X" and "-X", side by side) share the profile of "X",
    # where each lane point of "-X" projects onto it: each levelled across its own width on a
    # hillside, they met at a step of the cross slope times a lane width (0.43 m on a Monaco
    # street, which a car's chassis stopped on)
    _share_opposite_profiles(edges, lane_edge, ref_e, RP, rg, rz, C, cg, cz, target=opposite_profile)
    width = np.array([l.width for l in lanes])
    hw = width[cg] / 2.0
    nrm = _normals_many(C, cg) * hw[:, None]
    # each lane's ends onto its nodes' planes, across its width too: cz moves, and the lane
    # tilts across (tilt: height gained per metre to the left) near its ends
    unit_left = nrm / hw[:, None]
    tilt = _ends_on_planes(edges, lanes, lane_edge, C, cg, cz, cs, ctot, unit_left, planes)
    own_plane = _onto_own_plane(edges, lane_edge, C, cg, cz, tilt, unit_left, planes, jrings)
    at_grade_points = _deck_lanes_onto_junctions(lane_edge, C, cg, cz, cs, ctot, tilt, unit_left, planes, jrings,
                                                 {int(ref_e[g]): js for g, js in at_grade.items()}, higher[9])
    side = np.array([l.pedestrian_only for l in lanes])
    rail = np.array([bool(l.allowed) and l.allowed <= RAIL_CLASSES for l in lanes])
    drive = np.array([l.drivable for l in lanes])
    # and where a lane's end (on its node's plane) or a turn still stands through a
    # higher-ranked road, it goes under it (a dead-end service road ending on a Monaco bridge
    # stood 0.3 m through it)
    # (the three passes below take their pairs of overlapping roads from one search)
    on_deck = edge_deck[lane_edge[cg]] & ~rail[cg]
    own = lane_edge[cg]
    ai, av, aB = _higher_overlaps(lane_edge, higher, C, cg, own, hw, only=drive[cg] | on_deck, any_rank=True, top=False)
    rank = higher[2]

    def pairs(mask, rk):
        return {"pairs": _top_overlaps(ai[mask], av[mask], aB[mask], rk[aB[mask]])}

    def onto_lanes(pts, lane_no, edge_no):      # (the other road's lane, where each point projects)
        return _onto_profiles(C, cg, cz, pts, lane_no)[0]

    conformed += _conform_to_higher_roads(edges, lanes, lane_edge, higher, C, cg, cs, cz, own, hw, onto_lanes,
                                          lower_only=True, only=drive[cg],
                                          cache=pairs(drive[cg][ai] & (rank[aB] > rank[own[ai]]), rank))
    end_fade = np.maximum(np.minimum(END_FADE_M, 0.5 * ctot[cg]), 1e-6)
    end_hold = np.clip(np.minimum(cs, ctot[cg] - cs) / end_fade, 0.0, 1.0)
    if on_deck.any():
        # and a deck's lane that stands over a road it crosses by DECK_DOWN_MAX_M at most (at
        # grade: it could not rise over it) comes down onto that road's lanes there, the move
        # fading along the deck; the road under it ranks lower and only goes down, so its lanes
        # keep their junctions' planes (Portland's Burnside Bridge, layer 3, crossed Naito
        # Parkway 0.17 m over its lanes, and a car on Naito stopped dead against its edge). The
        # deck's lane ends stay on their junctions' planes: the move fades out over the last
        # END_FADE_M of each lane (moved ends folded the junctions' surfaces blended from them).
        at_grade_rank = np.where(edge_deck, -1, higher[2])
        conformed += _conform_to_higher_roads(edges, lanes, lane_edge, higher[:2] + (at_grade_rank,) + higher[3:],
                                              C, cg, cs, cz, own, hw,
                                              lambda *a: onto_lanes(*a) + CONFORM_BELOW_M,   # (onto it: it went
                                              lower_only=True, only=on_deck,                 # under the deck already)
                                              max_apart=DECK_DOWN_MAX_M, hold=end_hold,
                                              cache=pairs(on_deck[ai] & (at_grade_rank[aB] > at_grade_rank[own[ai]]),
                                                          at_grade_rank))
    # and a vehicle lane that another road's lanes still stand over by DECK_DOWN_MAX_M at most
    # where they cross (neither can move otherwise: a road the other ranks over only goes
    # down, and a bridge joined with its approaches into one edge ranks with the other as a
    # deck: Portland's SW Jefferson Street and SW Sheridan Street stood 0.26 and 0.43 m under
    # I-405's lanes, and cars stopped dead against their edges) comes up onto them, point by
    # point, the move fading along it and not at its ends
    conformed += _conform_to_higher_roads(edges, lanes, lane_edge, higher, C, cg, cs, cz, own, hw,
                                          lambda *a: onto_lanes(*a) + CONFORM_BELOW_M, only=drive[cg],
                                          max_apart=DECK_DOWN_MAX_M, raise_only=True, hold=end_hold,
                                          cache=pairs(drive[cg][ai] & (higher[9][own[ai]] != aB), rank))
    # paths, footways and cycleways drawn into another road's vehicle lane within
    # PATH_CONFORM_MAX_M of its height take its height there, 2 cm under it, the move fading
    # along them and not at their ends (Lauf: a path drawn into Daschstraße's lane stood 0.2 m
    # over it, and a car at 10 m/s stopped dead against its edge); a piece still off it by
    # over SOFT_STEP_M is left out (_sidewalks_off_other_roads, below)
    soft = ~drive & ~rail
    path = soft & ~side
    if path.any():
        reach = _higher_overlaps(lane_edge, higher, C, cg, own, hw, only=path[cg], min_overlap=0.0)
        conformed += _conform_to_higher_roads(edges, lanes, lane_edge, higher, C, cg, cs, cz, own, hw, onto_lanes,
                                              max_apart=PATH_CONFORM_MAX_M, pointwise=True, hold=end_hold,
                                              cache={"pairs": reach})
    # the pieces of sidewalks, footways, paths and cycleways (lanes no car uses) that lie on
    # another road's carriageway are left out, and do not hold the ground up either (a
    # footbridge over Avenue du Port, kept on the ground, stood 0.7-1.5 m above the road
    # under it: a slab in a car's way)
    seg_keep, pt_keep = _sidewalks_off_other_roads(C, cg, cz, nrm, side, soft, drive, lanes, lane_edge, edges,
                                                   jrings, higher[:2])
    # support points for levelling and for junction heights: centrelines and lane corners
    Ck, czk, hwk, nk = C[pt_keep], cz[pt_keep], hw[pt_keep], nrm[pt_keep]
    tk = tilt[pt_keep] * np.hypot(nk[:, 0], nk[:, 1])
    corners = np.vstack([np.column_stack([Ck + nk, czk + tk]), np.column_stack([Ck - nk, czk - tk])])
    sup = [np.column_stack([Ck, czk]), corners]
    sup_hw = [hwk, np.zeros(len(corners))]
    car_k = ~(side | rail)[cg[pt_keep]]
    sup_car = [car_k, np.concatenate([car_k, car_k])]
    # (a bridge's deck, its junctions along it: held up by no terrain where above the ground)
    dk = edge_deck[lane_edge[cg[pt_keep]]]
    sup_deck = [dk, np.concatenate([dk, dk])]
    touch: dict = {}
    for e, d in zip(edges, edge_deck):
        for j in (e.from_node, e.to_node):
            touch[j] = touch.get(j, True) and bool(d)
    deck_junctions = {j for j, d in touch.items() if d}
    # the drivable surface's triangles over the support points (the lanes' strips as
    # `_strips` makes them, the junctions' and gap lanes' meshes below): the terrain is cleared
    # under the whole surface, not only under its points
    nk_ = len(Ck)
    kept = np.flatnonzero(pt_keep)
    i = np.flatnonzero((kept[1:] == kept[:-1] + 1) & (cg[kept[1:]] == cg[kept[:-1]]) & car_k[:-1])
    L0, R0 = nk_ + i, 2 * nk_ + i
    sup_tris = [np.column_stack([L0, R0, L0 + 1]), np.column_stack([R0, R0 + 1, L0 + 1])]
    tree = cKDTree(np.vstack(sup)[:, :2], balanced_tree=False, compact_nodes=False)   # (3x faster to build)
    supz = np.concatenate([czk, czk + tk, czk - tk])

    def zfun(xy):
        _, i = tree.query(xy, k=1, workers=-1)     # threads: a core may be idle
        return supz[i]

    # A junction's points take their heights from the ends of the lanes that meet there,
    # weighted by 1/d^4: at a lane's end exactly its height, in between a smooth blend (1/d^2
    # left steps of 0.1 m at twice as many lane ends). (The nearest lane of any road took one
    # from a road passing by: a tunnel under a Monaco junction, a parallel street up the
    # hill; the nearest lane end alone changed in steps along the boundary, and the junction
    # folded between them.)
    first = np.r_[0, np.nonzero(cg[1:] != cg[:-1])[0] + 1]
    last = np.r_[first[1:] - 1, len(cg) - 1]
    node_num: dict = {}
    end_node = np.array([node_num.setdefault(edges[lane_edge[cg[i]]].from_node, len(node_num)) for i in first]
                        + [node_num.setdefault(edges[lane_edge[cg[i]]].to_node, len(node_num)) for i in last],
                        dtype=np.int64)
    ends = np.concatenate([first, last])
    EP = np.vstack([C[ends], C[ends] + nrm[ends], C[ends] - nrm[ends]])   # (centres and corners)
    te = tilt[ends] * hw[ends]
    EZ = np.concatenate([cz[ends], cz[ends] + te, cz[ends] - te])
    EN = np.tile(end_node, 3)

    e_order = np.argsort(EN, kind="stable")
    e_count = np.bincount(EN, minlength=len(node_num) + 1)
    e_start = np.r_[0, np.cumsum(e_count)[:-1]]

    # each lane end's height less its node's plane there (0 where the node has no plane): a
    # blend of heights on a tilted plane is not the plane (two junctions on one plane met at
    # steps of 0.3 m), so the ends' heights off the plane are blended and the plane added
    node_plane = np.full((len(node_num) + 1, 5), np.nan)
    for j, r in node_num.items():
        if j in planes:
            node_plane[r] = planes[j]
    pe = node_plane[EN]
    EZ_off = EZ - np.where(np.isfinite(pe[:, 0]), pe[:, 2] + pe[:, 3] * (EP[:, 0] - pe[:, 0])
                           + pe[:, 4] * (EP[:, 1] - pe[:, 1]), 0.0)

    EPx_n, EPy_n, EZ_n = EP[e_order, 0], EP[e_order, 1], EZ_off[e_order]     # (the ends in node order)

    def zfun_at(xy, junction_ids, of):
        """Heights for points of junctions: point i is of junction `junction_ids[of[i]]`,
        blended from all the lane ends of its junction. (From those among the 16 lane ends
        nearest to it, a point of a long junction with many sidewalks could find none of its
        own, and took the height of any road nearby.)"""
        node = np.array([node_num.get(j, -1) for j in junction_ids] + [-1], dtype=np.int64)[of]
        has = node >= 0
        nn = np.maximum(node, 0)
        cnt = np.where(has, e_count[nn], 0)
        pt = np.repeat(np.arange(len(xy)), cnt)
        # (point, end) pairs: the ends of a point's junction are a run of the ends in node
        # order; the arrays made in place, a million pairs and more on a city
        k = np.arange(len(pt)) + np.repeat(e_start[nn] - (np.cumsum(cnt) - cnt), cnt)
        dx = np.repeat(xy[:, 0], cnt)
        dx -= EPx_n[k]
        dy = np.repeat(xy[:, 1], cnt)
        dy -= EPy_n[k]
        d2 = dx * dx
        d2 += dy * dy
        d2 += 1e-6
        w = np.multiply(d2, d2, out=dx)
        np.divide(1.0, w, out=w)
        wsum = np.bincount(pt, w, minlength=len(xy))
        z = np.bincount(pt, np.multiply(w, EZ_n[k], out=dy), minlength=len(xy)) / np.maximum(wsum, 1e-300)
        PL = np.array([planes.get(j, (np.nan,) * 5) for j in junction_ids] + [(np.nan,) * 5])[of]
        on = np.isfinite(PL[:, 0])
        z += np.where(on, PL[:, 2] + PL[:, 3] * (xy[:, 0] - PL[:, 0]) + PL[:, 4] * (xy[:, 1] - PL[:, 1]), 0.0)
        none = wsum == 0.0
        if none.any():
            z[none] = zfun(xy[none])
        return z

    # 3. junctions, walking areas: polygons (constrained Delaunay) with heights from the lane
    # ends; the junctions first (they complete the levelling support)
    # (a junction's vehicle lanes that leave its polygon get strips of their own, and its
    # walking areas give way to them: see junction_gaps)
    gap_j, gap_lanes = junction_gaps(net)
    sm = surfaces() if surfaces is not None else None
    if sm is None:
        sm = surface_meshes(net, step)
    polys, pid, pel, tri = sm["polys"], sm["pid"], sm["pel"], sm["tri"]
    crossings = [e for e in net.edges.values()
                 if e.function == "crossing" and e.lanes and len(e.lanes[0].shape) >= 2
                 and not (under and e.id[1:e.id.rfind("_c")] in under)]

    # the nodes only paths meet (no vehicle lane): their junctions' and walking areas' pieces
    # on a carriageway's lanes are left out, and the rest meets the lanes at their height
    car_node = {n for e, v in zip(edges, vehicle_edge) if v for n in (e.from_node, e.to_node)}
    foot_nodes = {n for e in edges for n in (e.from_node, e.to_node)} - car_node

    def polygon_part(kind):
        cand, V2, vg, F, fg = tri[kind]
        keep_c = np.unique(fg)                      # (shapes with triangles)
        if not len(keep_c):
            return None
        keep = [cand[c] for c in keep_c]
        remap = -np.ones(len(cand), dtype=np.int64)
        remap[keep_c] = np.arange(len(keep_c))
        FG = remap[fg]
        # (a walking area ":J_w0" lies around junction J, and overlaps its lanes' ends too)
        owner = [pid[k] if kind == "asphalt" else pid[k][1:pid[k].rfind("_w")] for k in keep]
        Z = zfun_at(V2, owner, remap[vg])           # (points of shapes left out: -1, unused)
        foot = np.array([o in foot_nodes for o in owner], dtype=bool)
        if foot.any():
            # (the pieces of a path's junction on a carriageway's lanes: left out, as its
            # sidewalks are; the rest meets the lanes at their height)
            on = _faces_on_vehicle_lanes(V2, F, foot[FG], core_tree)
            F, FG = F[~on], FG[~on]
            _onto_vehicle_lanes(V2, Z, foot[remap[vg]] & (remap[vg] >= 0), higher[0], core_tree, C, cg, cz)
        if kind == "sidewalk":
            Z += SIDEWALK_LIFT
        V = np.column_stack([V2, Z])
        PP, pg = _concat([polys[k][:, :2] for k in keep])     # as given (closing point too)
        cnt = np.bincount(pg, minlength=len(keep))
        cen = np.column_stack([np.bincount(pg, PP[:, 0], len(keep)), np.bincount(pg, PP[:, 1], len(keep))])
        cen /= cnt[:, None]
        part = _part(kind, V, F, FG, len(keep), [pid[k] for k in keep],
                     [pel[k] for k in keep], [()] * len(keep), cen)
        if kind == "asphalt":
            # junction interiors as levelling support: points on a lattice inside each polygon
            # at the height of its own surface (its centroid at the height of the nearest lane,
            # levelled across the whole polygon, left a tilted Monaco junction 0.3 m under the
            # ground on its low side; a car drove into the next lane's edge there)
            on_deck = np.array([pid[k] in deck_junctions for k in keep], dtype=bool)
            for d in (False, True):
                Q = _interior_points([polys[k] for k, dd in zip(keep, on_deck) if dd == d], JUNCTION_SUPPORT_STEP)
                if len(Q):
                    qz = _top_surface_z(Q, [part])
                    ok = np.isfinite(qz)
                    sup.append(np.column_stack([Q[ok], qz[ok]]))
                    sup_hw.append(np.full(int(ok.sum()), 0.5 * JUNCTION_SUPPORT_STEP))
                    sup_car.append(np.ones(int(ok.sum()), dtype=bool))
                    sup_deck.append(np.full(int(ok.sum()), d))
            sup_tris.append(F + sum(map(len, sup)))      # (V's first index in the support)
            sup.append(V)
            sup_hw.append(np.zeros(len(V)))
            sup_car.append(np.ones(len(V), dtype=bool))
            sup_deck.append((remap[vg] >= 0) & on_deck[np.maximum(remap[vg], 0)])
        return part

    junction_part = polygon_part("asphalt")
    gap_part = None
    if gap_lanes:
        # heights: on the junction's own surface where they overlap it (no step between the
        # two), else from the junction's lane ends like its points
        GP, gg = _concat([ln.shape[:, :2] for ln in gap_lanes])
        G, gg = resample_many(GP, gg, step)
        ghw = np.array([ln.width for ln in gap_lanes])[gg] / 2.0
        v, f, fg = _strips(G, gg, np.zeros(len(G)), ghw)
        vz = _top_surface_z(v[:, :2], [junction_part]) if junction_part is not None else np.full(len(v), np.nan)
        miss = ~np.isfinite(vz)
        if miss.any():
            vz[miss] = zfun_at(v[miss, :2], gap_j, np.repeat(gg, 2)[miss])
            # (and where they lie on a road's vehicle lane, that lane's height: a turn cut
            # across the last metres of a steep Monaco street's lane (161882802_2) from the
            # junction's lane ends stood 0.65 m over it, and a car on the street ran into it.
            # Not a lane further apart: a corner lifted 1.46 m onto one (182700005_1, at 21 %
            # into its junction) made a spike on the turn)
            _onto_vehicle_lanes(v[:, :2], vz, miss, higher[0], core_tree, C, cg, cz, max_apart=GAP_ONTO_LANE_MAX_M)
        v[:, 2] = vz
        gz = 0.5 * (vz[0::2] + vz[1::2])
        n = len(gap_lanes)
        gcen = np.column_stack([np.bincount(gg, G[:, 0], n), np.bincount(gg, G[:, 1], n)])
        gcen /= np.maximum(np.bincount(gg, minlength=n), 1)[:, None]
        gap_part = _part("asphalt", v, f, fg, n, [ln.id for ln in gap_lanes], ["junction_lane"] * n,
                         [()] * n, gcen)
        sup.append(np.column_stack([G, gz]))
        sup_hw.append(ghw)
        sup_car.append(np.ones(len(G), dtype=bool))
        sup_deck.append(np.zeros(len(G), dtype=bool))
        sup_tris.append(f + sum(map(len, sup)))
        sup.append(v)
        sup_hw.append(np.zeros(len(v)))
        sup_car.append(np.ones(len(v), dtype=bool))
        sup_deck.append(np.zeros(len(v), dtype=bool))
    # bare ground where lanes meet a junction at an angle to its border (_lane_end_gaps): filled,
    # each corner at the height of the surface just outside it (the junction, or a lane's
    # strip as step 4 makes it), with no point inside
    hole_part = None
    holes, near = _lane_end_gaps(edges, lane_edge, C, cg, cs, ctot, nrm, drive, jrings)
    if holes:
        HP, hg, HF, hfg = _dense_triangulated([h[1] for h in holes], 1e9)
        remap = -np.ones(len(lanes), dtype=np.int64)
        ln_near = np.unique(cg[near])
        remap[ln_near] = np.arange(len(ln_near))
        sv, sf, sfg = _strips(C[near], remap[cg[near]], cz[near], hw[near], tilt=tilt[near],
                              seg_mask=(cg[near][1:] == cg[near][:-1]) & (near[1:] == near[:-1] + 1))
        strips_near = _part("asphalt", sv, sf, sfg, len(ln_near), [""] * len(ln_near), ["lane"] * len(ln_near),
                            [()] * len(ln_near), np.zeros((len(ln_near), 2)))
        # (each corner on the lowest surface 3 cm around it: where a steep lane's strip stands
        # over its junction, the junction, which the car comes from; at a corner between two
        # lanes' strips, the lower one)
        mid = np.column_stack([np.bincount(hg, HP[:, 0]), np.bincount(hg, HP[:, 1])]) / np.bincount(hg)[:, None]
        ang = np.arange(8) * (np.pi / 4)
        ring8 = 0.03 * np.column_stack([np.cos(ang), np.sin(ang)])
        probe = (HP[:, None, :] + ring8[None, :, :]).reshape(-1, 2)
        around = [strips_near]
        if junction_part is not None:         # (the junctions with gaps only)
            with_gap = {h[0] for h in holes}
            k_ = np.array([k for k, i in enumerate(junction_part.ids) if i in with_gap], dtype=np.int64)
            if len(k_):
                fs = np.concatenate([np.arange(junction_part.fstart[k], junction_part.fstart[k + 1]) for k in k_])
                around.append(types.SimpleNamespace(vertices=junction_part.vertices, faces=junction_part.faces[fs]))
        pz = _top_surface_z(probe, around, lowest=True).reshape(len(HP), 8)
        with np.errstate(all="ignore"):
            hz = np.where(np.isfinite(pz).any(axis=1), np.nanmin(np.where(np.isfinite(pz), pz, np.inf), axis=1), np.nan)
        miss = ~np.isfinite(hz)
        if miss.any():
            hz[miss] = zfun_at(HP[miss], [h[0] for h in holes], hg[miss])
        n = len(holes)
        hole_part = _part("asphalt", np.column_stack([HP, hz]), HF, hfg, n, [h[0] for h in holes],
                          ["junction"] * n, [()] * n, mid)
        sup_tris.append(HF + sum(map(len, sup)))
        sup.append(np.column_stack([HP, hz]))
        sup_hw.append(np.zeros(len(HP)))
        sup_car.append(np.ones(len(HP), dtype=bool))
        sup_deck.append(np.zeros(len(HP), dtype=bool))
    geo.support_pts = np.vstack(sup)
    geo.support_hw = np.concatenate(sup_hw)
    geo.support_car = np.concatenate(sup_car)
    geo.support_tris = np.vstack(sup_tris).astype(np.int64)
    # (a deck's points above the ground hold no terrain up; the terrain is still cleared under them)
    sdeck = np.concatenate(sup_deck)
    geo.support_hold = np.ones(len(sdeck), dtype=bool)
    if sdeck.any():
        P = geo.support_pts[sdeck]
        geo.support_hold[sdeck] = P[:, 2] - np.asarray(ground(P[:, 0], P[:, 1]), dtype=float) <= DECK_CLEAR_M
    if on_support is not None:
        on_support(geo.support_pts, geo.support_hw, geo.support_car, geo.support_tris, geo.support_hold)

    # 4. lanes as strips
    ids = [lanes[k].id for k in range(len(lanes))]
    osm = [edges[lane_edge[k]].orig_ids for k in range(len(lanes))]
    cent = np.zeros((len(lanes), 2))
    np.add.at(cent, cg, C)
    cent /= np.maximum(np.bincount(cg, minlength=len(lanes)), 1)[:, None]
    parts = {"asphalt": [], "sidewalk": [], "marking": [], "rail": []}
    for kind, mask, lift in (("asphalt", ~side & ~rail, 0.0), ("sidewalk", side, SIDEWALK_LIFT),
                             ("rail", rail, 0.0)):
        sel = np.nonzero(mask)[0]
        if not len(sel):
            continue
        remap = -np.ones(len(lanes), dtype=np.int64)
        remap[sel] = np.arange(len(sel))
        pm = mask[cg]
        at = np.nonzero(pm)[0]
        v, f, fg = _strips(C[pm], remap[cg[pm]], cz[pm], hw[pm], lift,
                           seg_mask=seg_keep[at[:-1]] if kind != "rail" else None, tilt=tilt[pm])
        parts[kind].append(_part(kind, v, f, fg, len(sel), [ids[k] for k in sel], ["lane"] * len(sel),
                                 [osm[k] for k in sel], cent[sel]))
    # the underside of bridges' decks, DECK_THICKNESS_M under their lanes where they stand
    # above the ground (class "deck", drawn only: PyBullet's renderer draws a face from its
    # front alone, and a camera on the road under a bridge saw nothing over it)
    dmask = edge_deck[lane_edge] & ~rail
    if dmask.any():
        sel = np.nonzero(dmask)[0]
        remap = -np.ones(len(lanes), dtype=np.int64)
        remap[sel] = np.arange(len(sel))
        pm = dmask[cg]
        at = np.nonzero(pm)[0]
        high = cz[at] - np.asarray(ground(C[at, 0], C[at, 1]), dtype=float) > DECK_CLEAR_M + DECK_THICKNESS_M
        v, f, fg = _strips(C[pm], remap[cg[pm]], cz[pm] - DECK_THICKNESS_M, hw[pm], 0.0,
                           seg_mask=seg_keep[at[:-1]] & high[:-1] & high[1:], tilt=tilt[pm])
        has = np.unique(fg)                 # (the lanes with an underside at all)
        if len(has):
            back = -np.ones(len(sel), dtype=np.int64)
            back[has] = np.arange(len(has))
            sel = sel[has]
            parts["deck"] = [_part("deck", v, f[:, ::-1], back[fg], len(sel), [ids[k] for k in sel],
                                   ["deck"] * len(sel), [osm[k] for k in sel], cent[sel])]

    # 5. lane markings on vehicle lanes: dashed between lanes of one edge, solid at the edges
    _markings(parts, edges, lanes, lane_edge, drive, C, cg, cz, cs, hw, tilt)

    # 6. the polygons in their classes (after the lanes), walking areas, crossings
    if junction_part is not None:
        parts["asphalt"].append(junction_part)
    if gap_part is not None:
        parts["asphalt"].append(gap_part)
    if hole_part is not None:
        parts["asphalt"].append(hole_part)
    walk_part = polygon_part("sidewalk")
    if walk_part is not None:
        parts["sidewalk"].append(walk_part)
    if crossings:
        # zebra crossings are paint, not a surface: the car drives on the junction and lane
        # ends under them (a crossing strip of its own, level along the road, stood 0.3 m proud
        # of a sloping Monaco junction and stopped the car). Stripes of 0.5 m every metre along
        # the walking direction, 90 % of the width, each corner on the highest surface under it
        XP, xg = _concat([e.lanes[0].shape for e in crossings])
        xw = np.array([e.lanes[0].width for e in crossings])
        Z2, z2g = resample_many(XP, xg, 0.5)
        zs, _ = _arclen(Z2, z2g)
        seg_on = (np.floor((zs[:-1] + zs[1:]) / 2.0 / 0.5) % 2 == 0) & (zs[1:] > zs[:-1])
        v, f, fg = _strips(Z2, z2g, np.zeros(len(Z2)), 0.45 * xw[z2g], seg_mask=seg_on)
        top = _top_surface_z(v[:, :2], parts["asphalt"] + parts["sidewalk"])
        miss = ~np.isfinite(top)
        if miss.any():
            top[miss] = zfun(v[miss, :2])
        v[:, 2] = top + MARKING_LIFT
        xcent = np.zeros((len(crossings), 2))
        np.add.at(xcent, z2g, Z2)
        xcent /= np.bincount(z2g, minlength=len(crossings))[:, None]
        parts["marking"].append(_part("marking", v, f, fg, len(crossings), [e.id for e in crossings],
                                      ["zebra"] * len(crossings), [()] * len(crossings), xcent))
    geo.parts = {k: v for k, v in parts.items() if v}
    geo.stats = {"lanes_meshed": len(lanes), "planes_pinned": n_pinned, "own_plane_points": own_plane,
                 "junctions_meshed": len(junction_part.ids) if junction_part is not None else 0,
                 "walkingareas_meshed": len({i for i, e in zip(pid, pel) if e == "walkingarea"}),  # (cut: pieces)
                 "junction_lanes_meshed": len(gap_lanes),
                 "lane_end_gaps_filled": len(holes),
                 "crossings_meshed": len(crossings),
                 "junction_ends_moved": ends_moved,
                 "points_conformed": conformed,
                 "deck_profiles_at_grade": len(at_grade), "deck_lane_points_at_grade": at_grade_points,
                 "faces": int(sum(len(p.faces) for ps in geo.parts.values() for p in ps))}
    return geo


def _smooth_profiles(z, gid, passes: int) -> np.ndarray:
    """Each profile (points of one `gid`) smoothed by `passes` of a [1 2 1] / 4 filter, its end
    points kept. The DEM's bilinear surface changes grade at its cells' edges (Monaco: from
    -12 % to -29 % within a metre, where a car at 8 m/s ran 0.4 m/s over its set speed);
    a road's grade changes over a vertical curve."""
    if passes <= 0 or len(z) < 3:
        return z
    inner = np.zeros(len(z), dtype=bool)
    inner[1:-1] = (gid[1:-1] == gid[:-2]) & (gid[1:-1] == gid[2:])
    i = np.nonzero(inner)[0]
    z = z.copy()
    for _ in range(passes):
        z[i] = 0.25 * z[i - 1] + 0.5 * z[i] + 0.25 * z[i + 1]
    return z


def _limit_grade(z, s, gid, grade: float) -> np.ndarray:
    """Each profile (points of one `gid`, arc length `s`) made no steeper than `grade`: the
    mean of its upper and lower `grade`-Lipschitz envelopes (the largest such function under
    it and the smallest over it), which is itself no steeper than `grade` and is the profile
    itself wherever it is nowhere steeper. A cliff of the DEM beside a road becomes a ramp of
    that grade centred on it (Monaco's Avenue Pasteur ran along the edge of an SRTM cliff,
    12.6 m down over 40 m, with faces of 100 % grade in the lane).

    Each envelope is two running extrema along the profiles (forward and backward), the
    profiles kept apart by an offset per profile that no value of another crosses."""
    if len(z) < 2:
        return z
    g = np.r_[0, np.cumsum(gid[1:] != gid[:-1])].astype(float)      # profile number, 0, 1, ...
    big = 4.0 * (float(np.abs(z).max()) + grade * float(np.abs(s).max()) + 1.0)
    a, b = z - grade * s, z + grade * s
    # upper: min over s' of z(s') + grade |s - s'|; lower: max of z(s') - grade |s - s'|
    up = np.minimum(np.minimum.accumulate(a - g * big) + g * big + grade * s,
                    np.minimum.accumulate((b + g * big)[::-1])[::-1] - g * big - grade * s)
    lo = np.maximum(np.maximum.accumulate(b + g * big) - g * big - grade * s,
                    np.maximum.accumulate((a - g * big)[::-1])[::-1] + g * big + grade * s)
    return 0.5 * (up + lo)


def _ends_on_planes(edges, lanes, lane_edge, C, cg, cz, cs, ctot, unit_left, planes) -> np.ndarray:
    """Put each lane's two ends on the planes of the nodes it joins (``cz`` in place), and
    return the lanes' tilt across their width (height per metre to the left, per point).

    The edge's profile puts its middle lane's ends on the planes; another lane of the edge
    ends elsewhere along the junction's edge and a lane width to the side, where the plane
    lies higher or lower (a lane of the opposite direction takes its profile from the other
    edge). Its end's move, and the plane's slope across it, fade out linearly over
    :data:`END_FADE_M` (at most half the lane). (Blended over a junction, the lane ends'
    offsets from its plane met within half a metre: 0.18 m over 0.4 m at a Monaco
    junction, where a car's bumper caught the fold.)"""
    tilt = np.zeros(len(C))
    if not len(C) or not planes:
        return tilt
    first = np.r_[0, np.nonzero(cg[1:] != cg[:-1])[0] + 1]
    last = np.r_[first[1:] - 1, len(cg) - 1]
    lane_no = cg[first]
    nan5 = (np.nan,) * 5
    L = np.array([planes.get(edges[lane_edge[k]].from_node, nan5) for k in lane_no] +
                 [planes.get(edges[lane_edge[k]].to_node, nan5) for k in lane_no])
    at = np.concatenate([first, last])
    ok = np.isfinite(L[:, 0])
    on = L[:, 2] + L[:, 3] * (C[at, 0] - L[:, 0]) + L[:, 4] * (C[at, 1] - L[:, 1])
    move = np.where(ok, on - cz[at], 0.0)
    across = np.where(ok, L[:, 3] * unit_left[at, 0] + L[:, 4] * unit_left[at, 1], 0.0)
    n = len(first)
    g = np.repeat(np.arange(n), last - first + 1)          # (lane number per point)
    fade = np.maximum(np.minimum(END_FADE_M, 0.5 * ctot[lane_no]), 1e-6)[g]
    f0 = np.clip(1.0 - cs / fade, 0.0, 1.0)
    f1 = np.clip(1.0 - (ctot[lane_no][g] - cs) / fade, 0.0, 1.0)
    cz += f0 * move[:n][g] + f1 * move[n:][g]
    tilt += f0 * across[:n][g] + f1 * across[n:][g]
    return tilt


def _sidewalks_off_other_roads(C, cg, cz, nrm, side, soft, drive, lanes, lane_edge, edges, jrings, strips):
    """Which pieces of the sidewalks to mesh: (per segment i -> i+1 of the resampled lane
    centrelines `C`, per point) masks, False for a sidewalk's segment that reaches more than
    :data:`SIDEWALK_INTRUSION_M` into a vehicle lane of another edge, or into a junction
    (`jrings`: id -> ring) other than the two its edge joins, and for its points whose
    segments are all left out.

    netconvert guesses a sidewalk on each side of a road from its permissions, also where the
    road's two directions are mapped as two ways a few metres apart: the sidewalk between them
    then lies on the other carriageway (Monaco, Helsinki: a few thousand m2 each). On a
    hillside the two carriageways are at different heights, and such a sidewalk stood 1.4 m
    above the other one's lane, a wall that a car drove into.

    The other lanes no car uses (`soft`, which holds the sidewalks `side` too: footways,
    paths, cycleways; heights `cz`) lose such a
    segment only where it is more than :data:`SOFT_STEP_M` above or below the vehicle lane
    it reaches into: a footbridge over Avenue du Port, kept on the ground, stood 0.7-1.5 m
    above the road under it, a slab in a car's way (a path level with the road is left: on
    flat Helsinki, paths and cycleways drawn into a carriageway cover 19,000 m²)."""
    n = len(C)
    seg_keep = np.ones(max(n - 1, 0), dtype=bool)
    pt_keep = np.ones(n, dtype=bool)
    # the vehicle lanes wide enough to reach into, with their strips less SIDEWALK_INTRUSION_M
    # (`strips`: _higher_roads' numbers and strips of every vehicle lane, ascending)
    hveh, hcores = strips
    wide = drive[hveh] & (np.array([lanes[k].width for k in hveh]) / 2.0 > SIDEWALK_INTRUSION_M + 0.05)
    veh, cores = hveh[wide], hcores[wide]
    if n < 2 or not soft.any() or not len(veh):
        return seg_keep, pt_keep
    seg = np.nonzero((cg[1:] == cg[:-1]) & soft[cg[:-1]])[0]
    if not len(seg):
        return seg_keep, pt_keep
    ca, cb, na, nb = C[seg], C[seg + 1], nrm[seg], nrm[seg + 1]
    quads = _ring_polygons(np.stack([ca + na, cb + nb, cb - nb, ca - na, ca + na], axis=1))
    shapely.prepare(cores)
    qi, vi = shapely.STRtree(cores).query(quads)    # (by bounding box; a road's own lanes first
    other = lane_edge[cg[seg[qi]]] != lane_edge[veh[vi]]    # out, then the geometry)
    qi, vi = qi[other], vi[other]
    hit = shapely.intersects(cores[vi], quads[qi])
    qi, vi = qi[hit], vi[hit]
    path = ~side[cg[seg[qi]]]       # a path, cycleway, ...: only where it stands off the vehicle lane
    if path.any():
        # (off the lane's height at either end or the middle: a segment 0.14 m over a Lauf
        # lane at its middle stood 0.2 m over it at its end, where a car ran into its edge)
        a, b, vl = seg[qi[path]], seg[qi[path]] + 1, veh[vi[path]]
        off = np.zeros(len(a))          # (fmax: a point that projects onto no lane counts 0)
        for pts, zs in ((C[a], cz[a]), (C[b], cz[b]), (0.5 * (C[a] + C[b]), 0.5 * (cz[a] + cz[b]))):
            off = np.fmax(off, np.abs(zs - _onto_profiles(C, cg, cz, pts, vl)[0]))
        keep_hit = np.ones(len(qi), dtype=bool)
        keep_hit[np.flatnonzero(path)] = off > SOFT_STEP_M
        qi = qi[keep_hit]
    seg_keep[seg[qi]] = False
    if jrings and side.any():
        sm = side[cg[seg]]                  # (into a junction: the sidewalks only, as before)
        seg, quads = seg[sm], quads[sm]
        jids = list(jrings)
        JP, jg = _concat([jrings[j] for j in jids])
        jp = shapely.polygons(shapely.linearrings(JP, indices=jg))
        bad = ~shapely.is_valid(jp)
        jp[bad] = _repaired(jp[bad])
        # pairs by the junctions' own bounding boxes (those of their cores lie inside), the
        # own junctions' dropped, then the cores of the junctions left (a negative buffer
        # of every junction took a sixth of the time)
        qi, ji = shapely.STRtree(jp).query(quads)
        if len(qi):
            num: dict = {j: k for k, j in enumerate(jids)}
            fn = np.array([num.get(e.from_node, -1) for e in edges], dtype=np.int64)
            tn = np.array([num.get(e.to_node, -1) for e in edges], dtype=np.int64)
            ei = lane_edge[cg[seg[qi]]]
            own = (fn[ei] == ji) | (tn[ei] == ji)
            qi, ji = qi[~own], ji[~own]
            cand = np.unique(ji)
            jcores = np.full(len(jp), None, dtype=object)
            jcores[cand] = shapely.buffer(jp[cand], -SIDEWALK_INTRUSION_M)
            shapely.prepare(jcores[cand])
            hit = shapely.intersects(jcores[ji], quads[qi])
            seg_keep[seg[qi[hit]]] = False
    # a point goes with its segments: kept if one of them is
    prev_ok = np.zeros(n, dtype=bool)
    next_ok = np.zeros(n, dtype=bool)
    same = cg[1:] == cg[:-1]
    next_ok[:-1] = same & seg_keep
    prev_ok[1:] = same & seg_keep
    alone = np.ones(n, dtype=bool)          # (a lane of one point has no segment to lose)
    alone[:-1] &= ~same
    alone[1:] &= ~same
    pt_keep = next_ok | prev_ok | alone | ~soft[cg]
    return seg_keep, pt_keep


def _onto_vehicle_lanes(xy, z, sel, veh, core_tree, C, cg, cz, max_apart: float = CONFORM_MAX_M) -> int:
    """Heights ``z`` (in place) of the points ``xy[sel]`` (of the junctions and walking areas
    of nodes only paths meet; of the strips of turns that leave their junction) that lie on a
    vehicle lane ``veh[k]`` (within
    :data:`SIDEWALK_INTRUSION_M` of its strip in ``core_tree``, :func:`_higher_roads`', which is
    that much narrower either side) and within ``max_apart``
    (:data:`CONFORM_MAX_M`) of its height: that lane's height where they project onto its
    centreline (``C``, ``cg``, ``cz``). A footway's dead end mapped on a Monaco street (node 8258594205) took its height
    from the footways' ends, and its junction and walking area stood 0.13-0.27 m over the
    street's two lanes: a car at 8 m/s ran into the edge and stood. Their triangles on the
    lanes are left out (:func:`_faces_on_vehicle_lanes`, as a path's lanes are:
    :func:`_sidewalks_off_other_roads`); these are the points of the rest. Returns how many
    points moved."""
    idx = np.flatnonzero(sel)
    if not len(idx) or not len(veh):
        return 0
    pi, li = core_tree.query(shapely.points(xy[idx]), predicate="dwithin", distance=SIDEWALK_INTRUSION_M)
    if not len(pi):
        return 0
    pi, first = np.unique(pi, return_index=True)         # (one lane per point)
    li = li[first]
    zl, _ = _onto_profiles(C, cg, cz, xy[idx[pi]], veh[li])
    ok = np.isfinite(zl) & (np.abs(zl - z[idx[pi]]) <= max_apart)
    z[idx[pi[ok]]] = zl[ok]
    return int(ok.sum())


def _faces_on_vehicle_lanes(xy, F, sel, core_tree) -> np.ndarray:
    """Which of the triangles ``F`` (of points ``xy``; only those where ``sel``) have their
    centre on a vehicle lane (its strip less :data:`SIDEWALK_INTRUSION_M` either side, in
    ``core_tree``: :func:`_higher_roads`')."""
    out = np.zeros(len(F), dtype=bool)
    idx = np.flatnonzero(sel)
    if not len(idx):
        return out
    cen = xy[F[idx]].mean(axis=1)
    hit, _ = core_tree.query(shapely.points(cen), predicate="within")
    out[idx[hit]] = True
    return out


def _ring_polygons(rings: np.ndarray):
    """Shapely polygons of closed rings (n, k, 2), all of k points: the same polygons as
    ``shapely.polygons(rings)`` (closed: 5x faster than open ones), in half the time
    (``from_ragged_array``: 25 against 49 ms for 42,000 quads)."""
    n, k = rings.shape[:2]
    return shapely.from_ragged_array(shapely.GeometryType.POLYGON, np.ascontiguousarray(rings).reshape(-1, 2),
                                     (np.arange(0, n * k + 1, k), np.arange(n + 1)))


def _markings(parts, edges, lanes, lane_edge, drive, C, cg, cz, cs, hw, tilt=None):
    """Lane lines on vehicle lanes: dashed between two vehicle lanes of one edge, solid at the
    right edge of the first and the left edge of the last vehicle lane."""
    dl = np.nonzero(drive)[0]
    if not len(dl):
        return
    # per edge: rank of each vehicle lane among the edge's vehicle lanes
    e_of = lane_edge[dl]
    first = np.ones(len(dl), dtype=bool)
    first[1:] = e_of[1:] != e_of[:-1]
    last = np.ones(len(dl), dtype=bool)
    last[:-1] = e_of[1:] != e_of[:-1]
    is_first = np.zeros(len(lanes), dtype=bool); is_first[dl[first]] = True
    is_last = np.zeros(len(lanes), dtype=bool); is_last[dl[last]] = True
    pm = drive[cg]
    P, g, z, s, h = C[pm], cg[pm], cz[pm], cs[pm], hw[pm]
    nrm = _normals_many(P, g)
    k = (tilt[pm] if tilt is not None else np.zeros(len(P))) * np.hypot(nrm[:, 0], nrm[:, 1])
    lines = []   # (points, gid, heights, seg_mask)
    # solid right edge of the first vehicle lane
    m = is_first[g]
    lines.append((P[m] - nrm[m] * (h[m] - MARK_W)[:, None], g[m], z[m] - k[m] * (h[m] - MARK_W), None))
    # left edge of each vehicle lane: dashed if another vehicle lane follows, else solid
    lw = h - np.where(is_last[g], MARK_W, 0.0)
    left = P + nrm * lw[:, None]
    mid = 0.5 * (s[1:] + s[:-1])
    dashed_on = (mid % (DASH_ON + DASH_OFF)) < DASH_ON
    m_last = is_last[g]
    seg_solid = m_last[1:] & m_last[:-1]
    seg_dash = (~m_last[1:]) & (~m_last[:-1]) & dashed_on
    lines.append((left, g, z + k * lw, seg_solid | seg_dash))
    vs, fs, fgs, off = [], [], [], 0
    for pts, gg, zz, mask in lines:
        if mask is None:
            v, f, fg = _strips(pts, gg, zz, np.full(len(pts), MARK_W / 2.0), MARKING_LIFT)
        else:
            v, f, fg = _strips(pts, gg, zz, np.full(len(pts), MARK_W / 2.0), MARKING_LIFT, seg_mask=mask)
        vs.append(v); fs.append(f + off); fgs.append(fg); off += len(v)
    V = np.vstack(vs); F = np.vstack(fs); FG = np.concatenate(fgs)
    order = np.argsort(FG, kind="stable")
    F, FG = F[order], FG[order]
    used = np.unique(FG)
    remap = -np.ones(len(lanes), dtype=np.int64); remap[used] = np.arange(len(used))
    cen = np.zeros((len(lanes), 2)); np.add.at(cen, cg, C)
    cen /= np.maximum(np.bincount(cg, minlength=len(lanes)), 1)[:, None]
    parts["marking"].append(_part("marking", V, F, remap[FG], len(used),
                                  [edges[lane_edge[k]].id for k in used], ["marking"] * len(used),
                                  [edges[lane_edge[k]].orig_ids for k in used], cen[used]))
