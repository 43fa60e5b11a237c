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
  (``road_area``) are dropped; street lamps, traffic signals and signs are roadside poles: one
  that is on the carriageway is moved to the nearest point 0.5 m beyond its edge (at most
  ``max_move_m``, else dropped); a pole inside a building is dropped. Everything is counted.
* yaw: trees and benches get a deterministic pseudo-random yaw; signs and signals face the
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
cells become two triangles and the cut cells are triangulated by earcut (trimesh), and every
vertex gets ``ground(x, y)`` plus a small offset (wood 3 cm, grass 5 cm, water 7 cm, so they
do not flicker where they overlap). One scene node per area, named by its OSM id.
"""
from __future__ import annotations

import json
import math
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import shapely
import trimesh
from shapely.geometry import Polygon, box
from trimesh.visual.material import PBRMaterial

from ._atomic import atomic_path, write_text
from .errors import BuildError
from .buildings import chunk_index, parse_length
from .osm_features import OSMFeatures, polygonal

TREE_ROW_SPACING_M = 8.0
WOOD_M2_PER_TREE = 150.0
OFF_ROAD_M = 0.5
MAX_MOVE_M = 15.0
AREA_CELL_M = 10.0
MAX_AREA_CELLS = 40000
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
    bounds: tuple
    instances: list = field(default_factory=list)
    crossings: list = field(default_factory=list)
    areas: trimesh.Scene = field(default_factory=trimesh.Scene)
    area_records: list = field(default_factory=list)
    stats: dict = field(default_factory=dict)

    @property
    def areas_mesh(self) -> trimesh.Trimesh | None:
        geoms = list(self.areas.geometry.values())
        if not geoms:
            return None
        vs, fs, o = [], [], 0
        for g in geoms:
            vs.append(g.vertices)
            fs.append(g.faces + o)
            o += len(g.vertices)
        return trimesh.Trimesh(np.vstack(vs), np.vstack(fs), process=False)


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


class _Edges:
    """Nearest points on the boundary of the carriageway polygons."""

    def __init__(self, road):
        self.parts = np.asarray(shapely.get_parts(road))
        self.boundaries = shapely.boundary(self.parts)
        self.tree = shapely.STRtree(self.parts)

    def nearest(self, x, y) -> np.ndarray:
        pts = shapely.points(x, y)
        pi, gi = self.tree.query_nearest(pts, all_matches=False)
        q = np.full((len(x), 2), np.nan)
        if len(pi):
            c = shapely.get_coordinates(shapely.shortest_line(self.boundaries[gi], pts[pi]))
            q[pi] = c.reshape(-1, 2, 2)[:, 0, :]
        return q


def _radial_exit(x, y, road, bld, edges, max_move_m: float, ndir: int = 32, step: float = 0.25):
    """For each point, the nearest point 0.5 m beyond the first exit from the road along one of
    ``ndir`` rays that is off the road and out of buildings (NaN where there is none)."""
    ang = np.arange(ndir) * (2 * math.pi / ndir)
    dist = np.arange(step, max_move_m - OFF_ROAD_M + 1e-9, step)
    rx, ry = np.full(len(x), np.nan), np.full(len(x), np.nan)
    for i in range(len(x)):
        X = x[i] + np.cos(ang)[:, None] * dist[None, :]
        Y = y[i] + np.sin(ang)[:, None] * dist[None, :]
        out = ~_in(road, X.ravel(), Y.ravel()).reshape(X.shape)
        has = out.any(axis=1)
        if not has.any():
            continue
        first = np.where(has, out.argmax(axis=1), len(dist))
        d_exit = np.where(has, dist[np.minimum(first, len(dist) - 1)], np.inf) + OFF_ROAD_M
        for a in np.argsort(d_exit):
            if not np.isfinite(d_exit[a]) or d_exit[a] > max_move_m:
                break
            cx, cy = x[i] + math.cos(ang[a]) * d_exit[a], y[i] + math.sin(ang[a]) * d_exit[a]
            # the ray steps are coarse: pull back to 0.5 m from the nearest edge
            q = edges.nearest(np.array([cx]), np.array([cy]))[0]
            L = math.hypot(cx - q[0], cy - q[1])
            if L > OFF_ROAD_M:
                cx, cy = q[0] + (cx - q[0]) * OFF_ROAD_M / L, q[1] + (cy - q[1]) * OFF_ROAD_M / L
            if not _in(road, np.array([cx]), np.array([cy]))[0] and \
                    not _in(bld, np.array([cx]), np.array([cy]))[0]:
                rx[i], ry[i] = cx, cy
                break
    return rx, ry


def _in(geom, x, y) -> np.ndarray:
    """Points inside or on the boundary of geom (prepared)."""
    if geom is None or geom.is_empty or not len(x):
        return np.zeros(len(x), bool)
    return shapely.intersects_xy(geom, x, y)


def make_scenery(features: OSMFeatures, ground, road_area, building_area, chunk_bounds_list,
                 density: float = 1.0, seed: int = 0, max_move_m: float = MAX_MOVE_M,
                 area_cell_m: float = AREA_CELL_M) -> list[ChunkScenery]:
    """Place the scenery of ``features`` in the chunks (see the module docstring).

    ``ground(x, y) -> z`` (vectorised); ``road_area`` and ``building_area`` are shapely
    geometries in world metres (or None); ``chunk_bounds_list`` a list of
    (xmin, ymin, xmax, ymax). Returns one :class:`ChunkScenery` per chunk, in order.
    """
    chunk_bounds_list = [tuple(map(float, b)) for b in chunk_bounds_list]
    results = [ChunkScenery(bounds=b) for b in chunk_bounds_list]
    if not chunk_bounds_list:
        return results
    cb = np.array(chunk_bounds_list)
    extent = (cb[:, 0].min(), cb[:, 1].min(), cb[:, 2].max(), cb[:, 3].max())
    road = road_area if road_area is not None and not road_area.is_empty else None
    if road is not None:
        road = shapely.clip_by_rect(road, extent[0] - 2 * max_move_m, extent[1] - 2 * max_move_m,
                                    extent[2] + 2 * max_move_m, extent[3] + 2 * max_move_m)
        road = None if road.is_empty else road
    bld = building_area if building_area is not None and not building_area.is_empty else None
    for g in (road, bld):
        if g is not None:
            shapely.prepare(g)

    # --- candidates -----------------------------------------------------------------------
    C = _Cands()
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

    # --- in the chunks at all ---------------------------------------------------------------
    ins = chunk_index(x, y, chunk_bounds_list) >= 0
    src, x, y, yaw, scale = src[ins], x[ins], y[ins], yaw[ins], scale[ins]
    ids = [i for i, k in zip(ids, ins) if k]
    extra = [e for e, k in zip(extra, ins) if k]
    ox, oy = x.copy(), y.copy()
    n = len(x)
    move_policy = np.array([SOURCES[s][1] == "move" for s in src], dtype=bool)
    status = np.array(["placed"] * n, dtype=object)

    in_bld = _in(bld, x, y)
    status[in_bld] = "dropped_building"
    on_road = _in(road, x, y) & ~in_bld
    status[on_road & ~move_policy] = "dropped_road"
    tomove = np.flatnonzero(on_road & move_policy)
    moved = np.zeros(n)
    edges = _Edges(road) if road is not None else None
    if len(tomove) and road is not None:
        px, py = x[tomove].copy(), y[tomove].copy()
        todo = np.ones(len(tomove), bool)
        for _ in range(4):           # a push can land on another carriageway: push again
            if not todo.any():
                break
            sel = np.flatnonzero(todo)
            q = edges.nearest(px[sel], py[sel])
            d = q - np.column_stack([px[sel], py[sel]])
            L = np.hypot(d[:, 0], d[:, 1])
            u = np.where(L[:, None] > 1e-9, d / np.maximum(L, 1e-9)[:, None], [1.0, 0.0])
            px[sel] = q[:, 0] + OFF_ROAD_M * u[:, 0]
            py[sel] = q[:, 1] + OFF_ROAD_M * u[:, 1]
            todo[sel] = _in(road, px[sel], py[sel])
        dist = np.hypot(px - x[tomove], py - y[tomove])
        bad = todo | (dist > max_move_m) | _in(bld, px, py)
        if bad.any():   # squeezed between carriageways or against a wall: search around
            rx, ry = _radial_exit(x[tomove[bad]], y[tomove[bad]], road, bld, edges, max_move_m)
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

    # --- yaw for poles: face the nearest carriageway when nothing better is known ----------
    face = np.flatnonzero(keep & np.isnan(yaw))
    yaw[face] = 0.0
    if len(face) and road is not None:
        q = edges.nearest(x[face], y[face])
        ok = np.isfinite(q[:, 0])
        yaw[face[ok]] = np.arctan2(q[ok, 1] - y[face[ok]], q[ok, 0] - x[face[ok]])
    yaw = np.mod(yaw, 2 * math.pi)

    z = np.zeros(n)
    if keep.any():
        z[keep] = np.asarray(ground(x[keep], y[keep]), dtype=float).reshape(-1)
        if not np.all(np.isfinite(z[keep])):
            raise BuildError("ground() returned no height for some scenery objects")

    # --- sort into chunks ----------------------------------------------------------------------
    ch_final = chunk_index(x, y, chunk_bounds_list)
    ch_orig = chunk_index(ox, oy, chunk_bounds_list)
    for r in results:
        r.stats = {s: {k: 0 for k in SOURCES} for s in ("placed", "moved", "dropped_building",
                                                        "dropped_road")}
    for i in range(n):
        st = status[i]
        if st in ("placed", "moved"):
            k = int(ch_final[i])
            if k < 0:            # pushed out of the world: count where it came from
                results[int(ch_orig[i])].stats["dropped_road"][src[i]] += 1
                continue
            inst = {"kind": SOURCES[src[i]][0], "id": ids[i], "x": float(x[i]), "y": float(y[i]),
                    "z": float(z[i]), "yaw": float(yaw[i]), "scale": round(float(scale[i]), 3)}
            if extra[i]:
                inst.update(extra[i])
            if st == "moved":
                inst["moved_m"] = float(moved[i])
                results[k].stats["moved"][src[i]] += 1
            results[k].stats["placed"][src[i]] += 1
            results[k].instances.append(inst)
        else:
            results[int(ch_orig[i])].stats[st][src[i]] += 1

    # --- crossings (records) -------------------------------------------------------------------
    cr = features.crossings
    if len(cr):
        cx, cy = cr.xy[:, 0], cr.xy[:, 1]
        ck = chunk_index(cx, cy, chunk_bounds_list)
        sel = np.flatnonzero(ck >= 0)
        cz = np.asarray(ground(cx[sel], cy[sel]), dtype=float).reshape(-1) if len(sel) else []
        for i, zz in zip(sel, cz):
            results[int(ck[i])].crossings.append({
                "id": cr.ids[i], "x": round(float(cx[i]), 3), "y": round(float(cy[i]), 3),
                "z": round(float(zz), 3), "crossing": cr.tags[i].get("crossing")})

    # --- areas -------------------------------------------------------------------------------
    materials = {k: PBRMaterial(name=f"area_{k}", baseColorFactor=list(c), metallicFactor=0.0,
                                roughnessFactor=1.0) for k, (c, _) in AREA_STYLE.items()}
    for k, r in enumerate(results):
        _chunk_areas(r, features, ground, road, materials, area_cell_m)
    return results


def drape(poly, ground, cell: float, z_offset: float = 0.0):
    """Triangulate a polygon on a world-aligned grid and lift it onto the ground.

    Returns (vertices (V, 3), faces (F, 3)) facing up. Whole cells are two triangles each,
    cells cut by the outline are triangulated by earcut (trimesh.creation.triangulate_polygon).
    """
    x0, y0, x1, y1 = poly.bounds
    ncell = (math.floor(x1 / cell) - math.floor(x0 / cell) + 1) * (math.floor(y1 / cell) - math.floor(y0 / cell) + 1)
    if ncell > MAX_AREA_CELLS:
        cell = cell * math.ceil(math.sqrt(ncell / MAX_AREA_CELLS))
    ix = np.arange(math.floor(x0 / cell), math.floor(x1 / cell) + 1)
    iy = np.arange(math.floor(y0 / cell), math.floor(y1 / cell) + 1)
    IX, IY = np.meshgrid(ix, iy)
    IX, IY = IX.ravel() * cell, IY.ravel() * cell
    cells = shapely.box(IX, IY, IX + cell, IY + cell)
    shapely.prepare(poly)
    hit = shapely.intersects(poly, cells)
    full = hit & shapely.covers(poly, cells)
    part = hit & ~full
    vs, fs, off = [], [], 0
    fx, fy = IX[full], IY[full]
    if len(fx):
        c = np.stack([np.column_stack([fx, fy]), np.column_stack([fx + cell, fy]),
                      np.column_stack([fx + cell, fy + cell]), np.column_stack([fx, fy + cell])], axis=1)
        m = len(fx)
        vs.append(c.reshape(-1, 2))
        base = np.arange(m)[:, None] * 4
        fs.append(np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]))
        off = 4 * m
    if part.any():
        pieces = shapely.intersection(poly, cells[part])
        for piece in pieces:
            for p in shapely.get_parts(piece):
                if not isinstance(p, Polygon) or p.area < 1e-6:
                    continue
                v2, f2 = trimesh.creation.triangulate_polygon(p, engine="earcut")
                if len(f2) == 0:
                    continue
                vs.append(np.asarray(v2)[:, :2])
                fs.append(np.asarray(f2, dtype=np.int64) + off)
                off += len(v2)
    if not vs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    V2 = np.vstack(vs)
    F = np.vstack(fs)
    e1, e2 = V2[F[:, 1]] - V2[F[:, 0]], V2[F[:, 2]] - V2[F[:, 0]]
    down = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0
    F[down] = F[down][:, ::-1]
    z = np.asarray(ground(V2[:, 0], V2[:, 1]), dtype=float).reshape(-1) + z_offset
    if not np.all(np.isfinite(z)):
        raise BuildError("ground() returned no height under an area layer")
    return np.column_stack([V2, z]), F


def _chunk_areas(r: ChunkScenery, features: OSMFeatures, ground, road, materials, cell):
    x0, y0, x1, y1 = r.bounds
    cbox = box(x0, y0, x1, y1)
    road_c = None
    if road is not None:
        road_c = shapely.clip_by_rect(road, x0 - 1, y0 - 1, x1 + 1, y1 + 1)
        road_c = None if road_c.is_empty else road_c
    names = set()
    for kind, layer in (("wood", features.woods), ("grass", features.grass), ("water", features.water)):
        colour, dz = AREA_STYLE[kind]
        for a in layer:
            if not a.geometry.intersects(cbox):
                continue
            g = polygonal(a.geometry)
            if g is None:
                continue
            g = polygonal(shapely.clip_by_rect(g, x0, y0, x1, y1))
            if g is not None and road_c is not None and kind != "water":
                g = polygonal(g.difference(road_c))
            if g is None or g.area < 1.0:
                continue
            vs, fs, off = [], [], 0
            for p in shapely.get_parts(g):
                v, f = drape(p, ground, cell, dz)
                if len(f):
                    vs.append(v)
                    fs.append(f + off)
                    off += len(v)
            if not vs:
                continue
            mesh = trimesh.Trimesh(np.vstack(vs), np.vstack(fs), process=True,
                                   visual=trimesh.visual.TextureVisuals(material=materials[kind]))
            name = a.id if a.id not in names else f"{a.id}#{kind}"
            names.add(name)
            r.areas.add_geometry(mesh, node_name=name, geom_name=name)
            r.area_records.append({"id": a.id, "node": name, "kind": kind,
                                   "area_m2": round(float(g.area), 1), "faces": int(len(mesh.faces))})


def write_chunk_scenery(result: ChunkScenery, out_dir) -> dict:
    """Write scenery.json (instances, crossings, area records, counts), areas.glb and areas.obj.

    Returns {"json": ..., "glb": ..., "obj": ...} relative to ``out_dir`` (glb/obj None when
    the chunk has no areas). Files are written atomically; a write error is a BuildError.
    """
    out = Path(out_dir)
    files = {"json": "scenery.json", "glb": None, "obj": None}
    if result.area_records:
        with atomic_path(out / "areas.glb") as tmp:
            result.areas.export(tmp, file_type="glb")
        with atomic_path(out / "areas.obj") as tmp:
            result.areas_mesh.export(tmp, file_type="obj", include_normals=False, include_color=False,
                                     include_texture=False)
        files["glb"], files["obj"] = "areas.glb", "areas.obj"
    write_text(out / "scenery.json", json.dumps({
        "bounds": list(result.bounds), "instances": result.instances,
        "crossings": result.crossings, "areas": result.area_records, "stats": result.stats,
    }, indent=1))
    return files


__all__ = ["make_scenery", "write_chunk_scenery", "drape", "ChunkScenery", "PREFAB_KINDS", "SOURCES"]
