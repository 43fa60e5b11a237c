"""Scenery: prefab instances (trees, lamps, signals, signs, benches) and draped area layers.

Instances
---------
Each instance is a dict ``{kind, id, x, y, z, yaw, scale}`` (``z`` = ground height, ``yaw`` in
radians counter-clockwise from +x, ``scale`` uniform) plus, where they apply, ``direction``
(the OSM tag, kept for signs and signals) and ``moved_m`` (how far it was moved off the
road). Kinds are the prefabs of ``models/prefabs/prefabs.json``: ``tree``, ``street_lamp``,
``traffic_signal``, ``stop_sign``, ``give_way_sign``, ``bench``. Ids are OSM ids
(``node/123``) or derived ones for generated trees: ``way/123#5`` (5th tree along a tree
row) and ``way/123#ix_iy`` (a wood's tree in cell ix, iy of the world-aligned grid).

* single trees (``natural=tree``); tree rows sampled every 8 m / density along the line;
  woods filled on a jittered grid of one tree per 150 m2 / density, the grid aligned to world
  multiples of its cell and the jitter a hash of (seed, cell), so a tree does not depend on
  which chunks are built together, and overlapping woods do not double up;
* trees and benches inside a building footprint (``building_area``) or on the carriageway
  (``road_area``; their colliders, turned by their yaw, reaching into it) are dropped; street lamps, traffic signals and signs are roadside poles: one
  that is on the carriageway is moved to the nearest point 0.5 m beyond its edge (at most
  ``max_move_m``, else dropped); a pole inside a building is dropped. Everything is counted.
* yaw: trees and benches get a deterministic pseudo-random yaw (a bench within reach of the
  carriageway stands along it, facing it, instead); signs and signals face the
  oncoming traffic when the node's road direction is known (``direction=forward`` -> traffic
  along the way, the face looks back along it; ``backward`` the other way; a number is the
  compass bearing, clockwise from north, the face looks to; right-hand traffic is not
  assumed); otherwise, like street lamps, they face the nearest carriageway. Prefabs have
  their front (sign face, signal lights, lamp arm) towards +x.

Counts per chunk (``stats``) by source (``tree``, ``tree_row``, ``wood``, ``street_lamp``,
``traffic_signal``, ``stop_sign``, ``give_way_sign``, ``bench``): ``placed`` (moved ones
included), ``moved``, ``dropped_building``, ``dropped_road``; a drop is counted in the chunk
where the object was mapped.

Crossings (``highway=crossing`` nodes) are drawn by the roads layer from the SUMO network;
here they are kept as records ``{id, x, y, z, crossing}``.

Areas
-----
Water, grass (and woods' floor) polygons become thin draped meshes: each area is clipped to
the chunk (grass and wood also minus the carriageway), cut by a world-aligned grid of
``area_cell_m`` (10 m; coarser if a chunk would need more than 40 000 cells per area), whole
cells become two triangles and the cut cells are triangulated by earcut (as trimesh does),
and every vertex gets ``ground(x, y)`` plus a small offset (wood 3 cm, grass 5 cm, water
7 cm, so they do not flicker where they overlap). One scene node per area, named by its OSM
id; vertices shared by cells are merged.

Pipeline and speed
------------------
:func:`make_scenery` is three steps, so that a world build can do each as soon as its input
exists: :func:`plan_scenery` needs neither road nor terrain (candidates, the building test,
each area clipped to its chunk and draped cell by cell in x/y); :func:`place_scenery` needs
the carriageway (drops, moves, facing; the cells of grass and woods that the carriageway
touches are draped again, the others kept); :func:`finish_scenery` needs the final terrain
(every z). The carriageway and the buildings are :class:`PolygonSet` s: the polygons
themselves, overlapping, with a spatial index, instead of their union (a city's lane strips
take about a second to union): a point is on the road if it is in a part, and the nearest
point of the road's edge from a pole on it is taken on the union of the few parts around
it, which is the same as on the whole union there.
"""
from __future__ import annotations

import json
import math
import zlib
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import shapely
from mapbox_earcut import triangulate_float64
from shapely.geometry import MultiPolygon, Polygon, box

from .buildings import chunk_index, parse_length
from .errors import BuildError
from .meshio import glb_bytes, write_file, write_obj
from .osm_features import OSMFeatures, polygonal

if TYPE_CHECKING:          # (annotations only: trimesh is imported where it is used)
    import trimesh

TREE_ROW_SPACING_M = 8.0
WOOD_M2_PER_TREE = 150.0
OFF_ROAD_M = 0.5
POLE_FOOT_M = 0.3           # a pole this close to the carriageway is moved off it (OFF_ROAD_M beyond)
BENCH_REACH_M = 0.95        # a bench this close to the carriageway is turned along it (its box's half diagonal)
MAX_MOVE_M = 15.0
AREA_CELL_M = 10.0
MAX_AREA_CELLS = 40000
GRID_CELL_M = 10.0          # smallest cell of PolygonSet's point-test grid
RAY_BLOCK = 8               # ray steps tested at a time when searching around a stuck pole
AREA_STYLE = {  # kind: (RGBA, height above ground in m)
    "wood": ((70, 110, 60, 255), 0.03),
    "grass": ((110, 160, 80, 255), 0.05),
    "water": ((60, 110, 170, 255), 0.07),
}
PREFAB_KINDS = ("tree", "street_lamp", "traffic_signal", "stop_sign", "give_way_sign", "bench")
#: source -> (prefab kind, policy on the road: "drop" or "move")
SOURCES = {
    "tree": ("tree", "drop"), "tree_row": ("tree", "drop"), "wood": ("tree", "drop"),
    "street_lamp": ("street_lamp", "move"), "traffic_signal": ("traffic_signal", "move"),
    "stop_sign": ("stop_sign", "move"), "give_way_sign": ("give_way_sign", "move"),
    "bench": ("bench", "drop"),
}
_M64 = np.uint64(0xFFFFFFFFFFFFFFFF)


@dataclass
class ChunkScenery:
    """One chunk's scenery: instances, crossing records, area records, counts, and the area
    meshes as arrays (area k owns ``area_vertices[area_vstart[k]:area_vstart[k+1]]`` and
    ``area_faces[area_fstart[k]:area_fstart[k+1]]``, indices into ``area_vertices``).
    ``areas`` (one trimesh node per area) and ``areas_mesh`` (all merged) are made from the
    arrays when asked for; the build writes the arrays directly."""
    bounds: tuple
    instances: list = field(default_factory=list)
    crossings: list = field(default_factory=list)
    area_records: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)
    area_vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    area_faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    area_vstart: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    area_fstart: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))

    @cached_property
    def areas(self) -> "trimesh.Scene":
        import trimesh

        scene = trimesh.Scene()
        mats = _area_materials()
        for k, rec in enumerate(self.area_records):
            v0, v1 = self.area_vstart[k], self.area_vstart[k + 1]
            f = self.area_faces[self.area_fstart[k]:self.area_fstart[k + 1]] - v0
            mesh = trimesh.Trimesh(self.area_vertices[v0:v1], f, process=False,
                                   visual=trimesh.visual.TextureVisuals(material=mats[rec["kind"]]))
            scene.add_geometry(mesh, node_name=rec["node"], geom_name=rec["node"])
        return scene

    @property
    def areas_mesh(self) -> "trimesh.Trimesh | None":
        import trimesh

        if not self.area_records:
            return None
        return trimesh.Trimesh(self.area_vertices, self.area_faces, process=False)


def _area_materials() -> dict:
    from trimesh.visual.material import PBRMaterial

    return {k: PBRMaterial(name=f"area_{k}", baseColorFactor=list(c), metallicFactor=0.0,
                           roughnessFactor=1.0) for k, (c, _) in AREA_STYLE.items()}


# --- deterministic hashing -------------------------------------------------------------------
def _mix(h: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on a uint64 array."""
    with np.errstate(over="ignore"):
        h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return h ^ (h >> np.uint64(31))


def _u01(seed: int, salt: int, *keys) -> np.ndarray:
    """Uniform [0, 1) per element, a pure function of (seed, salt, keys)."""
    keys = [np.asarray(k).astype(np.int64).view(np.uint64) if np.asarray(k).dtype.kind == "i"
            else np.asarray(k, dtype=np.uint64) for k in keys]
    shape = np.broadcast_shapes(*[k.shape for k in keys]) if keys else ()
    with np.errstate(over="ignore"):
        h = np.full(shape, np.uint64((seed * 0x9E3779B97F4A7C15 + salt) & 0xFFFFFFFFFFFFFFFF))
        for k in keys:
            h = _mix(h ^ k + np.uint64(0x9E3779B97F4A7C15))
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 9007199254740992.0)


def _id_keys(ids) -> np.ndarray:
    return np.array([zlib.crc32(i.encode()) for i in ids], dtype=np.uint64)


# --- candidates -----------------------------------------------------------------------------
class _Cands:
    def __init__(self):
        self.src, self.ids, self.x, self.y, self.yaw, self.scale, self.extra = [], [], [], [], [], [], []

    def add(self, src, ids, xy, yaw, scale, extra=None):
        n = len(ids)
        if not n:
            return
        self.src += [src] * n
        self.ids += list(ids)
        self.x.append(np.asarray(xy)[:, 0])
        self.y.append(np.asarray(xy)[:, 1])
        self.yaw.append(np.broadcast_to(np.asarray(yaw, float), (n,)))
        self.scale.append(np.broadcast_to(np.asarray(scale, float), (n,)))
        self.extra += list(extra) if extra is not None else [None] * n

    def arrays(self):
        cat = (lambda a: np.concatenate(a) if a else np.zeros(0))
        return (np.array(self.src, dtype=object), self.ids, cat(self.x), cat(self.y),
                cat(self.yaw), cat(self.scale), self.extra)


def _tree_scale(tags, u) -> float:
    h = parse_length(tags.get("height")) if tags else None
    if h is not None and 1.0 <= h <= 60.0:
        return float(np.clip(h / 8.0, 0.25, 4.0))     # the prefab tree is 8 m tall
    return 0.8 + 0.4 * float(u)


def _facing(tags, road_dir: float) -> float | None:
    """Yaw the front of a sign/signal looks to, from its direction tag and road direction."""
    d = (tags or {}).get("direction") or (tags or {}).get("traffic_signals:direction")
    if d is not None:
        d = str(d).strip().lower()
        try:
            bearing = float(d)
            return math.radians(90.0 - bearing)
        except ValueError:
            pass
        if math.isfinite(road_dir):
            if d == "forward":
                return road_dir + math.pi
            if d == "backward":
                return road_dir
    if math.isfinite(road_dir):
        return road_dir + math.pi
    return None


def _wood_points(woods, extent, density: float, seed: int):
    """Jittered-grid tree positions in woods within extent: (ids, xy)."""
    if not woods or density <= 0:
        return [], np.zeros((0, 2))
    cell = math.sqrt(WOOD_M2_PER_TREE / density)
    ext = box(*extent)
    seen = set()
    ids, xs, ys = [], [], []
    for w in woods:
        g = polygonal(w.geometry)
        if g is None:
            continue
        g = g.intersection(ext)
        if g.is_empty:
            continue
        x0, y0, x1, y1 = g.bounds
        ix = np.arange(math.floor(x0 / cell), math.floor(x1 / cell) + 1)
        iy = np.arange(math.floor(y0 / cell), math.floor(y1 / cell) + 1)
        IX, IY = np.meshgrid(ix, iy)
        IX, IY = IX.ravel(), IY.ravel()
        px = (IX + 0.1 + 0.8 * _u01(seed, 11, IX, IY)) * cell
        py = (IY + 0.1 + 0.8 * _u01(seed, 12, IX, IY)) * cell
        shapely.prepare(g)
        inside = shapely.contains_xy(g, px, py)
        for a, b, x, y in zip(IX[inside], IY[inside], px[inside], py[inside]):
            if (a, b) in seen:
                continue
            seen.add((a, b))
            ids.append(f"{w.id}#{a}_{b}")
            xs.append(x)
            ys.append(y)
    return ids, np.column_stack([xs, ys]) if ids else np.zeros((0, 2))


def _row_points(rows, density: float):
    ids, pts = [], []
    if density <= 0:
        return ids, np.zeros((0, 2))
    step = TREE_ROW_SPACING_M / density
    for r in rows:
        L = r.geometry.length
        n = max(int(L // step) + 1, 1)
        d = (L - (n - 1) * step) / 2.0 + np.arange(n) * step       # centred along the line
        p = shapely.get_coordinates(shapely.line_interpolate_point(r.geometry, d))
        ids += [f"{r.id}#{k}" for k in range(n)]
        pts.append(p)
    return ids, (np.vstack(pts) if pts else np.zeros((0, 2)))


class PolygonSet:
    """Polygons that stand for their union, without computing it (a city's carriageway is
    thousands of overlapping lane strips; their union costs about a second).

    Point tests go through an STRtree of the parts (a point is in the union if it is in a
    part). Where a pole must be moved off the road, the nearest point of the union's
    boundary is needed: it is found on the union of the few parts around the point only
    (:meth:`nearest_edge`), which is exact there. ``PolygonSet.of`` takes a shapely
    geometry (a union made elsewhere), a list of polygons, or None."""

    def __init__(self, geoms=(), disjoint: bool = False):
        parts = shapely.get_parts(np.asarray(list(geoms), dtype=object)) if len(geoms) else np.zeros(0, object)
        if len(parts):      # polygons only: lines and points left by make_valid cover nothing
            parts = parts[(shapely.get_type_id(parts) == 3) & ~shapely.is_empty(parts)]
        shapely.prepare(parts)
        self.parts = parts
        self.disjoint = disjoint         # the parts of one (multi)polygon: no union needed
        self.tree = shapely.STRtree(parts) if len(parts) else None
        self._edges: dict = {}
        self._grid = None

    def _cells(self):
        """A uniform grid over the parts' bounding boxes (cell -> parts, as CSR arrays): point
        tests find their candidate parts with array arithmetic, without making a shapely
        point per test point (which costs more than the test)."""
        if self._grid is None:
            b = shapely.bounds(self.parts)
            size = max(GRID_CELL_M, 0.25 * float(np.median(np.maximum(b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]))))
            x0, y0 = b[:, 0].min(), b[:, 1].min()
            i0 = np.floor((b[:, 0] - x0) / size).astype(np.int64)
            j0 = np.floor((b[:, 1] - y0) / size).astype(np.int64)
            i1 = np.floor((b[:, 2] - x0) / size).astype(np.int64)
            j1 = np.floor((b[:, 3] - y0) / size).astype(np.int64)
            ni = int(i1.max()) + 1
            nx, ny = i1 - i0 + 1, j1 - j0 + 1
            cnt = nx * ny
            part = np.repeat(np.arange(len(b)), cnt)
            k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            cell = (np.repeat(j0, cnt) + k // np.repeat(nx, cnt)) * ni + np.repeat(i0, cnt) + k % np.repeat(nx, cnt)
            order = np.argsort(cell, kind="stable")
            ncell = ni * (int(j1.max()) + 1)
            start = np.zeros(ncell + 1, np.int64)
            np.cumsum(np.bincount(cell, minlength=ncell), out=start[1:])
            self._grid = (x0, y0, size, ni, ncell, start, part[order], b)
        return self._grid

    def covers_xy(self, x, y) -> np.ndarray:
        """Points inside or on the boundary of the union."""
        x, y = np.asarray(x, float).ravel(), np.asarray(y, float).ravel()
        out = np.zeros(len(x), bool)
        if self.tree is None or not len(x):
            return out
        x0, y0, size, ni, ncell, start, cell_parts, b = self._cells()
        i = np.floor((x - x0) / size).astype(np.int64)
        j = np.floor((y - y0) / size).astype(np.int64)
        ok = (i >= 0) & (i < ni) & (j >= 0) & (j * ni + i < ncell)
        pts = np.flatnonzero(ok)
        c = j[pts] * ni + i[pts]
        n = start[c + 1] - start[c]
        pi = np.repeat(pts, n)
        gi = cell_parts[np.repeat(start[c] - (np.cumsum(n) - n), n) + np.arange(int(n.sum()))]
        inbox = (x[pi] >= b[gi, 0]) & (x[pi] <= b[gi, 2]) & (y[pi] >= b[gi, 1]) & (y[pi] <= b[gi, 3])
        pi, gi = pi[inbox], gi[inbox]
        hit = shapely.intersects_xy(self.parts[gi], x[pi], y[pi])     # prepared parts
        out[pi[hit]] = True
        return out

    @classmethod
    def of(cls, area) -> "PolygonSet":
        if isinstance(area, PolygonSet):
            return area
        if area is None:
            return cls()
        if isinstance(area, (list, tuple, np.ndarray)):
            return cls(area)
        return cls([] if area.is_empty else [area], disjoint=isinstance(area, (Polygon, MultiPolygon)))

    def __len__(self) -> int:
        return len(self.parts)

    def clipped(self, xmin, ymin, xmax, ymax) -> "PolygonSet":
        if not len(self):
            return self
        b = shapely.bounds(self.parts)
        cross = np.flatnonzero((b[:, 0] < xmin) | (b[:, 1] < ymin) | (b[:, 2] > xmax) | (b[:, 3] > ymax))
        if not len(cross):
            return self
        parts = self.parts.copy()       # only the parts that cross the rectangle are cut
        parts[cross] = shapely.clip_by_rect(parts[cross], xmin, ymin, xmax, ymax)
        return PolygonSet(parts, self.disjoint)

    def union_within(self, geom):
        """The union within `geom`'s bounding box (+ 1 m) of the parts that intersect `geom`
        (None if there is none): all a difference with `geom` needs."""
        if self.tree is None:
            return None
        idx = self.tree.query(geom, predicate="intersects")
        if not len(idx):
            return None
        x0, y0, x1, y1 = geom.bounds
        parts = shapely.clip_by_rect(self.parts[idx], x0 - 1.0, y0 - 1.0, x1 + 1.0, y1 + 1.0)
        if self.disjoint:
            parts = shapely.get_parts(parts)
            return shapely.MultiPolygon(list(parts[shapely.get_type_id(parts) == 3]))
        return shapely.union_all(parts)

    def _local_edge(self, x: float, y: float, r: float):
        """Boundary of the union of the parts within a box of half-size r around (x, y), and
        whether those are all the parts."""
        idx = self.tree.query(shapely.box(x - r, y - r, x + r, y + r))
        if self.disjoint:       # the boundary of the part that holds the point
            idx = idx[shapely.intersects_xy(self.parts[idx], x, y)][:1]
        key = tuple(sorted(idx.tolist()))
        g = self._edges.get(key)
        if g is None:
            g = shapely.boundary(shapely.union_all(self.parts[idx]) if len(idx) > 1 else self.parts[idx[0]])
            self._edges[key] = g
        return g, self.disjoint or len(idx) == len(self.parts)

    def nearest_edge(self, x, y) -> np.ndarray:
        """(n, 2): for a point outside the union its nearest point of the union, for one
        inside the nearest point of the union's boundary (NaN without parts)."""
        x, y = np.asarray(x, float), np.asarray(y, float)
        q = np.full((len(x), 2), np.nan)
        if self.tree is None or not len(x):
            return q
        inside = self.covers_xy(x, y)
        out = np.flatnonzero(~inside)
        if len(out):
            pts = shapely.points(x[out], y[out])
            pi, gi = self.tree.query_nearest(pts, all_matches=False)
            c = shapely.get_coordinates(shapely.shortest_line(self.parts[gi], pts[pi]))
            q[out[pi]] = c.reshape(-1, 2, 2)[:, 0, :]
        for i in np.flatnonzero(inside):
            # the union of the parts within r is the union itself within r of the point:
            # a boundary point nearer than r is the true nearest one; else look further
            r = 4.0
            while True:
                edge, everything = self._local_edge(x[i], y[i], r)
                p = shapely.Point(x[i], y[i])
                c = shapely.get_coordinates(shapely.shortest_line(edge, p))
                if len(c) and (everything or math.hypot(c[0, 0] - x[i], c[0, 1] - y[i]) < r):
                    q[i] = c[0]
                    break
                if everything:
                    break
                r *= 2.0
        return q


def _near(road: PolygonSet, x, y, r: float) -> np.ndarray:
    """Points within about ``r`` of the union: the point or one of 8 around it at ``r`` in it."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    out = road.covers_xy(x, y)
    for a in np.arange(8) * (np.pi / 4):
        out |= road.covers_xy(x + r * np.cos(a), y + r * np.sin(a))
    return out


def _collider_on(road: PolygonSet, kinds, x, y, yaw, scale) -> np.ndarray:
    """Whether each prefab's collider (``prefabs.json``: a cylinder by its rim, a box by its
    corners and edge midpoints, scaled, turned by ``yaw``) reaches into the union."""
    from models import prefab_dir

    cols = {k: v["collision"] for k, v in json.loads((prefab_dir() / "prefabs.json").read_text())["prefabs"].items()}
    x, y, yaw, scale = (np.asarray(a, float) for a in (x, y, yaw, scale))
    kinds = np.asarray(kinds, dtype=object)
    out = np.zeros(len(x), dtype=bool)
    for kind in set(kinds.tolist()):
        sel = np.flatnonzero(kinds == kind)
        col = cols[kind]
        ox, oy = float(col.get("offset", (0, 0, 0))[0]), float(col.get("offset", (0, 0, 0))[1])
        if col["type"] == "box":
            hx, hy = float(col["half_extents"][0]), float(col["half_extents"][1])
            pts = [(ox + a * hx, oy + b * hy) for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b]
        else:
            r = float(col["radius"])
            pts = [(ox + r * math.cos(a), oy + r * math.sin(a)) for a in np.arange(8) * (math.pi / 4)]
        c, sn, k = np.cos(yaw[sel]), np.sin(yaw[sel]), scale[sel]
        for px, py in pts:
            out[sel] |= road.covers_xy(x[sel] + k * (px * c - py * sn), y[sel] + k * (px * sn + py * c))
    return out


def _radial_exit(x, y, road: PolygonSet, bld: PolygonSet, max_move_m: float, ndir: int = 32,
                 step: float = 0.25):
    """For each point, the nearest point 0.5 m beyond the first exit from the road along one of
    ``ndir`` rays that is off the road and out of buildings (NaN where there is none)."""
    ang = np.arange(ndir) * (2 * math.pi / ndir)
    dist = np.arange(step, max_move_m - OFF_ROAD_M + 1e-9, step)
    rx, ry = np.full(len(x), np.nan), np.full(len(x), np.nan)
    # the ray samples, tested a few steps at a time for all rays still on the road:
    # first[i, a] is the first step of ray a from point i that is off the road
    cos, sin = np.cos(ang), np.sin(ang)
    first = np.full((len(x), ndir), len(dist))
    onroad = np.ones((len(x), ndir), bool)
    for k0 in range(0, len(dist), RAY_BLOCK):
        ri, ra = np.nonzero(onroad)
        if not len(ri):
            break
        dk = dist[None, k0:k0 + RAY_BLOCK]
        X = x[ri, None] + cos[ra, None] * dk
        Y = y[ri, None] + sin[ra, None] * dk
        off = ~road.covers_xy(X.ravel(), Y.ravel()).reshape(X.shape)
        hit = off.any(axis=1)
        first[ri[hit], ra[hit]] = k0 + off[hit].argmax(axis=1)
        onroad[ri[hit], ra[hit]] = False
    has = first < len(dist)
    d_exit = np.where(has, dist[np.minimum(first, len(dist) - 1)], np.inf) + OFF_ROAD_M   # (n, ndir)
    order = np.argsort(d_exit, axis=1)          # per row, as a point-by-point argsort
    # candidates in order of their exit distance, round r trying every point's r-th one:
    # the first that is off the road and out of buildings wins (as one point at a time would)
    pending = np.arange(len(x))
    for r in range(ndir):
        a = order[pending, r]
        d = d_exit[pending, a]
        go = np.isfinite(d) & (d <= max_move_m)       # sorted: past the limit, nothing follows
        pending, a, d = pending[go], a[go], d[go]
        if not len(pending):
            break
        cx, cy = x[pending] + np.cos(ang[a]) * d, y[pending] + np.sin(ang[a]) * d
        # the ray steps are coarse: pull back to 0.5 m from the nearest edge
        q = road.nearest_edge(cx, cy)
        L = np.hypot(cx - q[:, 0], cy - q[:, 1])
        pull = L > OFF_ROAD_M
        f = np.where(pull, OFF_ROAD_M / np.where(pull, L, 1.0), 1.0)
        cx = np.where(pull, q[:, 0] + (cx - q[:, 0]) * f, cx)
        cy = np.where(pull, q[:, 1] + (cy - q[:, 1]) * f, cy)
        ok = ~_near(road, cx, cy, POLE_FOOT_M) & ~bld.covers_xy(cx, cy)
        rx[pending[ok]], ry[pending[ok]] = cx[ok], cy[ok]
        pending = pending[~ok]
    return rx, ry


# --- plan (no road, no terrain), place (the road), finish (the terrain) -----------------------
@dataclass
class SceneryPlan:
    """Scenery before the road is known (see :func:`plan_scenery`)."""
    chunk_bounds: list
    extent: tuple
    max_move_m: float
    area_cell_m: float
    bld: PolygonSet
    src: np.ndarray                 # candidates in the chunks: source, ids, position, yaw, ...
    ids: list
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    scale: np.ndarray
    extra: list
    in_bld: np.ndarray
    crossings: list                 # (chunk, id, x, y, crossing tag)
    areas: list                     # per chunk: [(kind, area id, clipped polygon, _Drape or None)]


@dataclass
class PlacedScenery:
    """Scenery placed in x/y, off roads and buildings (see :func:`place_scenery`)."""
    plan: SceneryPlan
    status: np.ndarray
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    moved: np.ndarray
    areas: list                     # per chunk: [(kind, area id, polygon, (V2, F))]


def plan_scenery(features: OSMFeatures, building_area, chunk_bounds_list, density: float = 1.0,
                 seed: int = 0, max_move_m: float = MAX_MOVE_M, area_cell_m: float = AREA_CELL_M,
                 drape_areas: bool = True) -> SceneryPlan:
    """Everything that needs neither the road nor the terrain: candidates (mapped and
    generated), which are in buildings, crossings, and each chunk's area polygons, draped
    in 2D already when `drape_areas` (:func:`place_scenery` redoes the cells the road
    cuts, or everything when they were not draped here)."""
    chunk_bounds_list = [tuple(map(float, b)) for b in chunk_bounds_list]
    cb = np.array(chunk_bounds_list).reshape(-1, 4)
    extent = (cb[:, 0].min(), cb[:, 1].min(), cb[:, 2].max(), cb[:, 3].max()) if len(cb) else (0, 0, 0, 0)
    bld = PolygonSet.of(building_area)

    C = _Cands()
    if chunk_bounds_list:
        t = features.trees
        if len(t):
            k = _id_keys(t.ids)
            C.add("tree", t.ids, t.xy, 2 * math.pi * _u01(seed, 1, k),
                  [_tree_scale(tg, u) for tg, u in zip(t.tags, _u01(seed, 2, k))])
        ids, xy = _row_points(features.tree_rows, density)
        if ids:
            k = _id_keys(ids)
            C.add("tree_row", ids, xy, 2 * math.pi * _u01(seed, 1, k), 0.8 + 0.4 * _u01(seed, 2, k))
        ids, xy = _wood_points(features.woods, extent, density, seed)
        if ids:
            k = _id_keys(ids)
            C.add("wood", ids, xy, 2 * math.pi * _u01(seed, 1, k), 0.7 + 0.6 * _u01(seed, 2, k))
        for src, ps in (("street_lamp", features.street_lamps), ("traffic_signal", features.traffic_signals),
                        ("stop_sign", features.stop_signs), ("give_way_sign", features.give_way_signs)):
            if len(ps):
                yaw = [(_facing(tg, rd) if src != "street_lamp" else None)
                       for tg, rd in zip(ps.tags, ps.road_dir)]
                yaw = np.array([np.nan if v is None else v for v in yaw], dtype=float)
                extra = [({"direction": tg["direction"]} if src != "street_lamp" and "direction" in tg
                          else None) for tg in ps.tags]
                C.add(src, ps.ids, ps.xy, yaw, 1.0, extra)
        b = features.benches
        if len(b):
            C.add("bench", b.ids, b.xy, 2 * math.pi * _u01(seed, 1, _id_keys(b.ids)), 1.0)
    src, ids, x, y, yaw, scale, extra = C.arrays()
    ins = chunk_index(x, y, chunk_bounds_list) >= 0
    src, x, y, yaw, scale = src[ins], x[ins], y[ins], yaw[ins], scale[ins]
    ids = [i for i, k in zip(ids, ins) if k]
    extra = [e for e, k in zip(extra, ins) if k]

    crossings = []
    cr = features.crossings
    if len(cr) and chunk_bounds_list:
        ck = chunk_index(cr.xy[:, 0], cr.xy[:, 1], chunk_bounds_list)
        for i in np.flatnonzero(ck >= 0):
            crossings.append((int(ck[i]), cr.ids[i], float(cr.xy[i, 0]), float(cr.xy[i, 1]),
                              cr.tags[i].get("crossing")))

    areas = [_chunk_area_polygons(b, features, area_cell_m if drape_areas else None)
             for b in chunk_bounds_list]
    return SceneryPlan(chunk_bounds=chunk_bounds_list, extent=extent, max_move_m=max_move_m,
                       area_cell_m=area_cell_m, bld=bld, src=src, ids=ids, x=x, y=y, yaw=yaw,
                       scale=scale, extra=extra, in_bld=bld.covers_xy(x, y), crossings=crossings,
                       areas=areas)


def place_scenery(plan: SceneryPlan, road_area) -> PlacedScenery:
    """Drop trees and benches on the road, move poles off it, face poles to it, and cut the
    grass and wood areas along it (in x/y; the terrain comes in :func:`finish_scenery`)."""
    max_move_m = plan.max_move_m
    road = PolygonSet.of(road_area)
    e = plan.extent
    m = 2 * max_move_m
    road = road.clipped(e[0] - m, e[1] - m, e[2] + m, e[3] + m)
    bld = plan.bld
    x, y, yaw = plan.x.copy(), plan.y.copy(), plan.yaw.copy()
    n = len(x)
    move_policy = np.array([SOURCES[s][1] == "move" for s in plan.src], dtype=bool)
    status = np.array(["placed"] * n, dtype=object)
    in_bld = plan.in_bld
    status[in_bld] = "dropped_building"
    on_road = road.covers_xy(x, y) & ~in_bld
    # a tree or a bench whose collider reaches the carriageway is on it too (a Lauf bench mapped
    # at the kerb, turned by its yaw, stood half a metre into a lane and stopped the car there);
    # a bench that could reach it stands along it first, facing it, as benches at a kerb do
    drop = ~move_policy & ~in_bld & ~on_road
    bench = np.flatnonzero(drop & (plan.src == "bench"))
    if len(bench) and len(road):
        near = _near(road, x[bench], y[bench], BENCH_REACH_M * float(np.max(plan.scale[bench])))
        b = bench[near]
        if len(b):
            q = road.nearest_edge(x[b], y[b])
            good = np.isfinite(q[:, 0])
            yaw[b[good]] = np.mod(np.arctan2(q[good, 1] - y[b[good]], q[good, 0] - x[b[good]]), 2 * math.pi)
    if drop.any():
        on_road[drop] = _collider_on(road, [SOURCES[s][0] for s in plan.src[drop]], x[drop], y[drop],
                                     yaw[drop], plan.scale[drop])
    # a pole whose foot reaches the carriageway is on it too (OSM puts traffic signals on the
    # road's own node: at a lane's end the point sits on the edge of both the lane strip and
    # the junction, where the point test can fall either way, and the pole stood in the lane)
    on_road |= _near(road, x, y, POLE_FOOT_M) & move_policy & ~in_bld
    status[on_road & ~move_policy] = "dropped_road"
    tomove = np.flatnonzero(on_road & move_policy)
    moved = np.zeros(n)
    if len(tomove):
        px, py = x[tomove].copy(), y[tomove].copy()
        todo = np.ones(len(tomove), bool)
        for _ in range(4):           # a push can land on another carriageway: push again
            if not todo.any():
                break
            sel = np.flatnonzero(todo)
            q = road.nearest_edge(px[sel], py[sel])
            d = q - np.column_stack([px[sel], py[sel]])
            L = np.hypot(d[:, 0], d[:, 1])
            u = np.where(L[:, None] > 1e-9, d / np.maximum(L, 1e-9)[:, None], [1.0, 0.0])
            px[sel] = q[:, 0] + OFF_ROAD_M * u[:, 0]
            py[sel] = q[:, 1] + OFF_ROAD_M * u[:, 1]
            todo[sel] = _near(road, px[sel], py[sel], POLE_FOOT_M)
        dist = np.hypot(px - x[tomove], py - y[tomove])
        bad = todo | (dist > max_move_m) | bld.covers_xy(px, py)
        if bad.any():   # squeezed between carriageways or against a wall: search around
            rx, ry = _radial_exit(x[tomove[bad]], y[tomove[bad]], road, bld, max_move_m)
            found = np.isfinite(rx)
            bi = np.flatnonzero(bad)[found]
            px[bi], py[bi] = rx[found], ry[found]
            bad[bi] = False
            dist = np.hypot(px - x[tomove], py - y[tomove])
        status[tomove[bad]] = "dropped_road"
        good = tomove[~bad]
        x[good], y[good] = px[~bad], py[~bad]
        moved[good] = dist[~bad]
        status[good] = "moved"
    keep = (status == "placed") | (status == "moved")

    # yaw for poles: face the nearest carriageway when nothing better is known
    face = np.flatnonzero(keep & np.isnan(yaw))
    yaw[face] = 0.0
    if len(face) and len(road):
        q = road.nearest_edge(x[face], y[face])
        ok = np.isfinite(q[:, 0])
        yaw[face[ok]] = np.arctan2(q[ok, 1] - y[face[ok]], q[ok, 0] - x[face[ok]])
    yaw = np.mod(yaw, 2 * math.pi)

    # areas: grass and wood minus the carriageway (water stays)
    areas = []
    for bounds, chunk_areas in zip(plan.chunk_bounds, plan.areas):
        out = []
        for kind, ident, g, drape in chunk_areas:
            if kind != "water" and len(road):
                cut = road.union_within(g)
                if cut is not None:
                    g = polygonal(g.difference(cut))
                    if g is not None and drape is not None:
                        drape = drape.recut(g, cut)     # only the cells the road touches
            if g is None or g.area < 1.0:
                continue
            mesh2d = drape.mesh() if drape is not None else _drape_parts(g, plan.area_cell_m)
            out.append((kind, ident, g, mesh2d))
        areas.append(out)
    return PlacedScenery(plan=plan, status=status, x=x, y=y, yaw=yaw, moved=moved, areas=areas)


def finish_scenery(placed: PlacedScenery, ground) -> list[ChunkScenery]:
    """Heights from `ground` (the final terrain), and everything sorted into chunks."""
    plan = placed.plan
    results = [ChunkScenery(bounds=b) for b in plan.chunk_bounds]
    status, x, y, yaw, src = placed.status, placed.x, placed.y, placed.yaw, plan.src
    keep = (status == "placed") | (status == "moved")
    z = np.zeros(len(x))
    if keep.any():
        z[keep] = np.asarray(ground(x[keep], y[keep]), dtype=float).reshape(-1)
        if not np.all(np.isfinite(z[keep])):
            raise BuildError("ground() returned no height for some scenery objects")
    ch_final = chunk_index(x, y, plan.chunk_bounds)
    ch_orig = chunk_index(plan.x, plan.y, plan.chunk_bounds)
    for r in results:
        r.stats = {s: {k: 0 for k in SOURCES} for s in ("placed", "moved", "dropped_building",
                                                        "dropped_road")}
    for i in range(len(x)):
        st = status[i]
        if st in ("placed", "moved"):
            k = int(ch_final[i])
            if k < 0:            # pushed out of the world: count where it came from
                results[int(ch_orig[i])].stats["dropped_road"][src[i]] += 1
                continue
            inst = {"kind": SOURCES[src[i]][0], "id": plan.ids[i], "x": float(x[i]), "y": float(y[i]),
                    "z": float(z[i]), "yaw": float(yaw[i]), "scale": round(float(plan.scale[i]), 3)}
            if plan.extra[i]:
                inst.update(plan.extra[i])
            if st == "moved":
                inst["moved_m"] = float(placed.moved[i])
                results[k].stats["moved"][src[i]] += 1
            results[k].stats["placed"][src[i]] += 1
            results[k].instances.append(inst)
        else:
            results[int(ch_orig[i])].stats[st][src[i]] += 1

    if plan.crossings:
        cz = np.asarray(ground(np.array([c[2] for c in plan.crossings]),
                               np.array([c[3] for c in plan.crossings])), dtype=float).reshape(-1)
        for (k, ident, cx, cy, tag), zz in zip(plan.crossings, cz):
            results[k].crossings.append({"id": ident, "x": round(cx, 3), "y": round(cy, 3),
                                         "z": round(float(zz), 3), "crossing": tag})

    for r, chunk_areas in zip(results, placed.areas):
        _finish_areas(r, chunk_areas, ground)
    return results


def make_scenery(features: OSMFeatures, ground, road_area, building_area, chunk_bounds_list,
                 density: float = 1.0, seed: int = 0, max_move_m: float = MAX_MOVE_M,
                 area_cell_m: float = AREA_CELL_M) -> list[ChunkScenery]:
    """Place the scenery of ``features`` in the chunks (see the module docstring).

    ``ground(x, y) -> z`` (vectorised); ``road_area`` and ``building_area`` are shapely
    geometries in world metres, :class:`PolygonSet` s or None; ``chunk_bounds_list`` a list
    of (xmin, ymin, xmax, ymax). Returns one :class:`ChunkScenery` per chunk, in order.
    (:func:`plan_scenery`, :func:`place_scenery`, :func:`finish_scenery` in one go.)
    """
    plan = plan_scenery(features, building_area, chunk_bounds_list, density, seed, max_move_m,
                        area_cell_m)
    return finish_scenery(place_scenery(plan, road_area), ground)


# --- areas --------------------------------------------------------------------------------------
def _chunk_area_polygons(bounds, features: OSMFeatures, cell: float | None) -> list:
    """[(kind, area id, polygon clipped to the chunk, its _Drape or None)] of one chunk."""
    x0, y0, x1, y1 = bounds
    cbox = box(x0, y0, x1, y1)
    out = []
    for kind, layer in (("wood", features.woods), ("grass", features.grass), ("water", features.water)):
        if not layer:
            continue
        hit = shapely.intersects(np.array([a.geometry for a in layer], dtype=object), cbox)
        for a in (layer[i] for i in np.flatnonzero(hit)):
            g = polygonal(a.geometry)
            if g is None:
                continue
            g = polygonal(shapely.clip_by_rect(g, x0, y0, x1, y1))
            if g is None:
                continue
            drape = _Drape.of(g, cell) if cell is not None and g.area >= 1.0 else None
            out.append((kind, a.id, g, drape))
    return out


def _finish_areas(r: ChunkScenery, chunk_areas: list, ground) -> None:
    """Lift each area's 2D mesh onto the ground, merge its duplicate vertices, record it."""
    names = set()
    vs, fs, vstart, fstart, nv, nf = [], [], [0], [0], 0, 0
    for kind, ident, g, (V2, F) in chunk_areas:
        if not len(F):
            continue
        # one vertex per distinct position (cells share corners; earcut pieces repeat their
        # first point), as trimesh's merge_vertices would
        key = np.rint(V2 * 1e8).astype(np.int64)
        _, first, inv = np.unique(key.view([("x", np.int64), ("y", np.int64)]).ravel(),
                                  return_index=True, return_inverse=True)
        V2, F = V2[first], inv.reshape(-1)[F]
        z = np.asarray(ground(V2[:, 0], V2[:, 1]), dtype=float).reshape(-1) + AREA_STYLE[kind][1]
        if not np.all(np.isfinite(z)):
            raise BuildError("ground() returned no height under an area layer")
        vs.append(np.column_stack([V2, z]))
        fs.append(F + nv)
        nv += len(V2)
        nf += len(F)
        vstart.append(nv)
        fstart.append(nf)
        name = ident if ident not in names else f"{ident}#{kind}"
        names.add(name)
        r.area_records.append({"id": ident, "node": name, "kind": kind,
                               "area_m2": round(float(g.area), 1), "faces": int(len(F))})
    if vs:
        r.area_vertices = np.vstack(vs)
        r.area_faces = np.vstack(fs)
        r.area_vstart = np.array(vstart, dtype=np.int64)
        r.area_fstart = np.array(fstart, dtype=np.int64)


@dataclass
class _Drape:
    """A (multi)polygon triangulated on the world-aligned grid, kept cell by cell: whole
    cells (their lower-left corners ``fx, fy``) and the pieces of cut cells (lower-left
    corner, 2D vertices, faces), so that a cut (the carriageway) can redo just the cells
    it touches (:meth:`recut`)."""
    cell: float
    scaled: bool                            # coarser than asked (a huge area)
    fx: np.ndarray
    fy: np.ndarray
    px: np.ndarray
    py: np.ndarray
    pieces: list                            # [(V2, F)] per cut-cell piece

    @classmethod
    def of(cls, g, cell: float) -> "_Drape | None":
        """Every part of g on the grid, or None if a part is too big for `cell` (then
        :func:`_drape_parts` grids each part on its own coarser grid)."""
        ds = [_drape_cells(p, cell) for p in shapely.get_parts(g)]
        if any(d.scaled for d in ds):
            return None
        if not ds:
            return cls(cell, False, np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0), [])
        return cls(cell, False, np.concatenate([d.fx for d in ds]), np.concatenate([d.fy for d in ds]),
                   np.concatenate([d.px for d in ds]), np.concatenate([d.py for d in ds]),
                   [pc for d in ds for pc in d.pieces])

    def recut(self, g2, cut) -> "_Drape":
        """The drape of g2 = this polygon minus `cut`: cells that `cut` touches are made again
        from g2, the others are kept."""
        c = self.cell
        ox = np.concatenate([self.fx, self.px])
        oy = np.concatenate([self.fy, self.py])
        x0, y0, x1, y1 = cut.bounds
        near = np.flatnonzero((ox + c >= x0) & (ox <= x1) & (oy + c >= y0) & (oy <= y1))
        shapely.prepare(cut)
        hit = np.zeros(len(ox), bool)
        hit[near] = shapely.intersects(cut, shapely.box(ox[near], oy[near], ox[near] + c, oy[near] + c))
        nf = len(self.fx)
        keep_f, keep_p = ~hit[:nf], ~hit[nf:]
        # the touched cells, once each
        u = np.unique(ox[hit] + 1j * oy[hit])
        hx, hy = u.real, u.imag
        redo = _cells_of(g2, hx, hy, c)
        return _Drape(c, False, np.concatenate([self.fx[keep_f], redo.fx]),
                      np.concatenate([self.fy[keep_f], redo.fy]),
                      np.concatenate([self.px[keep_p], redo.px]), np.concatenate([self.py[keep_p], redo.py]),
                      [pc for pc, k in zip(self.pieces, keep_p) if k] + redo.pieces)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (V, 2), faces (F, 3)) facing up."""
        vs, fs, off = [], [], 0
        c = self.cell
        fx, fy = self.fx, self.fy
        if len(fx):
            q = np.stack([np.column_stack([fx, fy]), np.column_stack([fx + c, fy]),
                          np.column_stack([fx + c, fy + c]), np.column_stack([fx, fy + c])], axis=1)
            vs.append(q.reshape(-1, 2))
            base = np.arange(len(fx))[:, None] * 4
            fs.append(np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]))
            off = 4 * len(fx)
        for v, f in self.pieces:
            vs.append(v)
            fs.append(f + off)
            off += len(v)
        if not vs:
            return np.zeros((0, 2)), np.zeros((0, 3), np.int64)
        V2 = np.vstack(vs)
        F = np.vstack(fs)
        e1, e2 = V2[F[:, 1]] - V2[F[:, 0]], V2[F[:, 2]] - V2[F[:, 0]]
        down = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0
        F[down] = F[down][:, ::-1]
        return V2, F


def _drape_cells(poly, cell: float) -> _Drape:
    """One polygon on the grid (see drape_2d)."""
    x0, y0, x1, y1 = poly.bounds
    ncell = (math.floor(x1 / cell) - math.floor(x0 / cell) + 1) * (math.floor(y1 / cell) - math.floor(y0 / cell) + 1)
    scaled = ncell > MAX_AREA_CELLS
    if scaled:
        cell = cell * math.ceil(math.sqrt(ncell / MAX_AREA_CELLS))
    ix = np.arange(math.floor(x0 / cell), math.floor(x1 / cell) + 1)
    iy = np.arange(math.floor(y0 / cell), math.floor(y1 / cell) + 1)
    IX, IY = np.meshgrid(ix, iy)
    d = _cells_of(poly, IX.ravel() * cell, IY.ravel() * cell, cell)
    d.scaled = scaled
    return d


def _cells_of(poly, cx, cy, cell: float) -> _Drape:
    """The given cells (lower-left corners) of `poly`: whole ones, and the pieces of the cut
    ones triangulated by earcut (as trimesh.creation.triangulate_polygon does: each piece's
    rings with their closing points; all pieces' rings gathered in one go)."""
    cells = shapely.box(cx, cy, cx + cell, cy + cell)
    shapely.prepare(poly)
    hit = shapely.intersects(poly, cells)
    full = hit & shapely.covers(poly, cells)
    part = np.flatnonzero(hit & ~full)
    px, py, pieces = [], [], []
    if len(part):
        got = shapely.intersection(poly, cells[part])
        pcs, owner = shapely.get_parts(got, return_index=True)
        ok = (shapely.get_type_id(pcs) == 3)
        ok[ok] = shapely.area(pcs[ok]) >= 1e-6
        pcs, owner = pcs[ok], owner[ok]
        if len(pcs):
            rings, ring_poly = shapely.get_rings(pcs, return_index=True)
            xy = shapely.get_coordinates(rings)
            nco = shapely.get_num_coordinates(rings)
            rend = np.cumsum(nco)
            rstart = rend - nco
            first = np.searchsorted(ring_poly, np.arange(len(pcs)), side="left")
            last = np.searchsorted(ring_poly, np.arange(len(pcs)), side="right")
            for k in range(len(pcs)):
                a, b = rstart[first[k]], rend[last[k] - 1]
                tri = triangulate_float64(xy[a:b], (rend[first[k]:last[k]] - a).astype(np.uint32))
                if len(tri) == 0:
                    continue
                c = part[owner[k]]
                px.append(cx[c])
                py.append(cy[c])
                pieces.append((xy[a:b], tri.reshape(-1, 3).astype(np.int64)))
    return _Drape(cell, False, cx[full], cy[full], np.array(px, float), np.array(py, float), pieces)


def _drape_parts(g, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """2D mesh (V2, F) of every part of a (multi)polygon on the world-aligned grid."""
    vs, fs, off = [], [], 0
    for p in shapely.get_parts(g):
        v, f = drape_2d(p, cell)
        if len(f):
            vs.append(v)
            fs.append(f + off)
            off += len(v)
    if not vs:
        return np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    return np.vstack(vs), np.vstack(fs)


def drape_2d(poly, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate a polygon on a world-aligned grid: (vertices (V, 2), faces (F, 3)) facing up.

    Whole cells are two triangles each, cells cut by the outline are triangulated by earcut
    (as trimesh.creation.triangulate_polygon does). A polygon that would need more than
    MAX_AREA_CELLS cells gets coarser cells."""
    return _drape_cells(poly, cell).mesh()


def drape(poly, ground, cell: float, z_offset: float = 0.0):
    """Triangulate a polygon on a world-aligned grid and lift it onto the ground.

    Returns (vertices (V, 3), faces (F, 3)) facing up (:func:`drape_2d`, then ``ground``)."""
    V2, F = drape_2d(poly, cell)
    if not len(F):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    z = np.asarray(ground(V2[:, 0], V2[:, 1]), dtype=float).reshape(-1) + z_offset
    if not np.all(np.isfinite(z)):
        raise BuildError("ground() returned no height under an area layer")
    return np.column_stack([V2, z]), F


def write_chunk_scenery(result: ChunkScenery, out_dir) -> dict:
    """Write scenery.json (instances, crossings, area records, counts), areas.glb and areas.obj.

    Returns {"json": ..., "glb": ..., "obj": ...} relative to ``out_dir`` (glb/obj None when
    the chunk has no areas). Files are written under a temporary name and renamed; a write
    error is a BuildError.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"json": "scenery.json", "glb": None, "obj": None}
    if result.area_records:
        kinds = list(AREA_STYLE)
        write_file(out / "areas.glb", glb_bytes(
            [r["node"] for r in result.area_records], result.area_vertices, result.area_faces,
            result.area_vstart, result.area_fstart, [kinds.index(r["kind"]) for r in result.area_records],
            [{"name": f"area_{k}", "rgba": c, "roughness": 1.0, "metallic": 0.0}
             for k, (c, _) in AREA_STYLE.items()]))
        write_obj(out / "areas.obj", result.area_vertices, result.area_faces)
        files["glb"], files["obj"] = "areas.glb", "areas.obj"
    write_file(out / "scenery.json", json.dumps({
        "bounds": list(result.bounds), "instances": result.instances,
        "crossings": result.crossings, "areas": result.area_records, "stats": result.stats,
    }).encode())
    return files


__all__ = ["make_scenery", "plan_scenery", "place_scenery", "finish_scenery", "PolygonSet",
           "write_chunk_scenery", "drape", "drape_2d", "ChunkScenery", "PREFAB_KINDS", "SOURCES"]
