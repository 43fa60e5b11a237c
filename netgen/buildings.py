"""Buildings: OSM footprints extruded to solid blocks standing on the terrain.

Height
------
:func:`building_height` takes, in this order:

1. ``height`` (metres; "12", "12 m", "12.5m", "12,5", "40'", "40 ft", "40'6\\"", "12;15" -> the
   first valid value; feet converted), when it is a plausible number (0 < h < 1000 m);
2. ``building:levels`` x 3.0 m, plus the roof: ``roof:height`` if given, else ``roof:levels``
   x 3.0 m (OSM's ``height`` is to the top of the roof, so a block built from levels is
   too);
3. a default, by building type and, for unspecified types, by footprint size.

Why these defaults: the seed's 3 m (10 ft) is one storey, a garden shed; a typical European
urban building is 3-5 storeys, a Nordic suburb is mostly one- or two-storey houses with
sheds, saunas and garages beside them. The type says which, when it is there
(``shed``/``garage``/``kiosk``... 3 m, ``house``/``detached``... 6 m, ``terrace`` 7 m,
halls (``industrial``/``warehouse``/``retail``...) 8 m, ``church`` 12 m, ``apartments``/
``office``/``commercial``/``hotel``/``public``... 15 m = 5 storeys). Most buildings are
``building=yes`` (or ``residential``), and there the footprint is the best cue we have:
under 60 m2 it is an outbuilding (3 m), under 300 m2 a house (6 m), above that a block of
4 storeys (12 m, the middle of the 3-5 storey range). Measured on the Kouvola extract, this
puts its ``yes`` sheds (median 37 m2) at 3 m and its ``residential`` houses (median 170 m2)
at 6 m instead of making the whole suburb either sheds or blocks.

``building=roof`` (a canopy, e.g. over fuel pumps) is a 0.5 m slab at the top of its height
(default 5 m) so that cars can drive under it, unless ``min_height`` says otherwise; likewise
``min_height`` / ``building:min_level`` (x 3 m) lift the underside of any building.

Placement
---------
Each building goes to exactly one chunk: the one holding its footprint's representative
point (``point_on_surface``; chunk intervals are half-open). Its base is the lowest terrain
under the footprint: ``ground`` is sampled at every vertex, along the outline every <= 2 m and
on a 2 m grid inside (coarser for huge footprints, at most ~4000 points), and the base is the
minimum less ``sink_m`` (0.1 m), which hides what a 2 m sampling can miss, so nothing floats.
The solid spans ``base_z + min_height`` .. ``base_z + height``.

Footprints are repaired with ``shapely.make_valid`` (polygonal parts kept); parts and
buildings under 2 m2 are dropped and counted. Buildings mapped as a node get a placeholder
box by type (8 x 8 m house, 3 x 6 m garage...), ``placeholder: true`` in their record.

Over the roads
--------------
Where a footprint overlaps the carriageway of the SUMO network (its vehicle lanes, junctions
and junction lanes: :func:`netgen.roads.carriageway_parts`), the building does not stand on
the road: the part over it (grown by 0.2 m) becomes a passage, its underside at 4.5 m
(``PASSAGE_CLEARANCE_M``, a road's usual clearance) above the highest ground under that part
(on a slope, higher than above the base), or at the building's own ``min_height`` if higher,
the rest standing on the ground as usual; where less than 1 m of the building would be left
above that underside, the part over the road is left out (and so is a building wholly over
the road). Once the roads' surface and the buildings' bases on the final terrain are known,
:func:`raise_passages` lifts an underside standing 0.5 m or more short of 4.5 m over the road
surface under it (a road's profile is not the DEM's ground: it is smoothed over steep terrain,
or a deck over another road). This is what OSM maps as ``tunnel=building_passage`` (a street through a block's
gateway), and it also settles footprints that netconvert's lanes run into (a narrow old-town
street whose guessed lane and sidewalk widths are wider than the space between its mapped
buildings: in Lauf, a wall 0.37 m from a lane's centre stopped the car). The record keeps the
whole footprint's area and base; ``passage_from_m`` gives the underside of the part over the
road (null where that part was left out). :func:`cut_passages` does it, once the network is
known (a world build: right after reading netconvert's output).

Pipeline
--------
:func:`make_buildings` is :func:`plan_buildings` (footprints, heights, chunks, all solids
extruded at once on a base of 0, and the ground sample points of every footprint; no
terrain needed, so a world build does it while netconvert runs) then
:func:`place_buildings` (one vectorised terrain lookup for the bases, every solid lifted by
its base). Meshes stay arrays (:class:`ChunkBuildings`); files are written from them
directly (GLB and OBJ by :mod:`netgen.meshio`, records as compact JSON).
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import shapely
from mapbox_earcut import triangulate_float64
from shapely.geometry import Polygon, box

from .errors import BuildError
from .meshio import GlbTemplate, JsonTemplate, write_file, write_obj
from .osm_features import OSMFeatures, polygonal

if TYPE_CHECKING:          # (annotations only: trimesh is imported where it is used)
    import trimesh

LEVEL_HEIGHT_M = 3.0
MIN_AREA_M2 = 2.0
PASSAGE_CLEARANCE_M = 4.5     # underside of a building's part over a road (see "Over the roads")
PASSAGE_MARGIN_M = 0.2        # the road grown by this, for the cut
PASSAGE_MIN_SOLID_M = 1.0     # an upper part thinner than this is left out
PASSAGE_MIN_AREA_M2 = 0.1     # overlaps smaller than this are left alone
PASSAGE_SLACK_M = 0.5         # raise_passages: a passage this much short of the clearance over the road stays
ROOF_SLAB_M = 0.5
SAMPLE_STEP_M = 2.0
MAX_SAMPLES = 4000

_SMALL = {"shed", "garage", "garages", "carport", "hut", "cabin", "kiosk", "toilets", "sauna",
          "container", "bunker", "allotment_house", "shelter", "greenhouse", "glasshouse",
          "gatehouse", "boathouse", "pavilion", "static_caravan", "service", "hangar_small",
          "bicycle_shed", "outbuilding"}
_HOUSE = {"house", "detached", "semidetached_house", "bungalow", "villa", "farm", "cottage",
          "chalet"}
_HALL = {"industrial", "warehouse", "manufacture", "factory", "hangar", "barn", "stable",
         "cowshed", "farm_auxiliary", "retail", "supermarket", "sports_hall", "storage_tank",
         "transportation", "parking"}
_BLOCK = {"apartments", "commercial", "office", "hotel", "public", "civic", "government",
          "school", "university", "college", "hospital", "dormitory", "block", "train_station",
          "kindergarten", "museum", "courthouse", "fire_station", "townhall", "stadium"}
DEFAULT_HEIGHT_BY_TYPE = {
    **{k: 3.0 for k in _SMALL}, **{k: 6.0 for k in _HOUSE}, "terrace": 7.0,
    **{k: 8.0 for k in _HALL}, **{k: 15.0 for k in _BLOCK}, "kindergarten": 4.0,
    "church": 12.0, "chapel": 6.0, "mosque": 12.0, "temple": 10.0, "synagogue": 12.0,
    "cathedral": 25.0, "tower": 20.0, "roof": 5.0,
}
#: unspecified types ("yes", "residential", anything unknown): by footprint area (m2)
DEFAULT_HEIGHT_BY_AREA = ((60.0, 3.0), (300.0, 6.0), (math.inf, 12.0))
DEFAULT_HEIGHT_M = 12.0    # unspecified type, footprint unknown
#: placeholder footprint (width, depth) in metres for buildings mapped as a node
NODE_FOOTPRINT = {"house": (8, 8), "detached": (8, 8), "semidetached_house": (12, 8),
                  "garage": (3, 6), "shed": (3, 3), "kiosk": (3, 3), "hut": (4, 4),
                  "cabin": (5, 5), "toilets": (3, 3), "roof": (6, 6), "sauna": (4, 4)}
NODE_FOOTPRINT_DEFAULT = (10, 10)

COLOURS = {  # RGBA by building type group, for the GLB
    "small": (170, 150, 130, 255), "house": (225, 205, 170, 255), "hall": (185, 185, 190, 255),
    "block": (210, 200, 185, 255), "church": (230, 225, 210, 255), "roof": (120, 120, 125, 255),
    "other": (200, 195, 188, 255),
}

_LEN_RE = re.compile(
    r"""^\s*(?P<num>[+-]?\d+(?:[.,]\d+)?|[+-]?[.,]\d+)\s*
        (?P<unit>m|meters?|metres?|ft|feet|foot|'|’|′)?\s*
        (?:(?P<inch>\d+(?:\.\d+)?)\s*(?:"|”|″|in|inch|inches))?\s*$""",
    re.IGNORECASE | re.VERBOSE)


def parse_length(value) -> float | None:
    """A length tag in metres ("12", "12 m", "12.5m", "40'", "40 ft", "40'6\\"", "12;15"), or None.

    With several values separated by ';' the first valid one is taken. Feet (and inches)
    are converted; a comma decimal separator ("12,5") is accepted.
    """
    if value is None:
        return None
    for part in str(value).split(";"):
        m = _LEN_RE.match(part)
        if not m:
            continue
        num = float(m.group("num").replace(",", "."))
        unit = (m.group("unit") or "m").lower()
        if unit in ("ft", "feet", "foot", "'", "’", "′"):
            num = num * 0.3048 + (float(m.group("inch")) * 0.0254 if m.group("inch") else 0.0)
        elif m.group("inch"):
            continue            # "12 m 6 in" is not a thing
        if math.isfinite(num):
            return num
    return None


def parse_levels(value) -> float | None:
    """building:levels-like tag -> a number of storeys (first valid of "a;b"), or None."""
    if value is None:
        return None
    for part in str(value).split(";"):
        try:
            v = float(part.strip().replace(",", "."))
        except ValueError:
            continue
        if math.isfinite(v) and 0.0 <= v < 200.0:
            return v
    return None


def _group(kind: str) -> str:
    if kind in _SMALL:
        return "small"
    if kind in _HOUSE or kind == "terrace":
        return "house"
    if kind in _HALL:
        return "hall"
    if kind in _BLOCK:
        return "block"
    if kind in ("church", "chapel", "cathedral", "mosque", "temple", "synagogue"):
        return "church"
    if kind == "roof":
        return "roof"
    return "other"


def default_height(kind: str | None, footprint_area_m2: float | None = None) -> float:
    """The documented default height for a building type (see the module docstring)."""
    if kind in DEFAULT_HEIGHT_BY_TYPE:
        return DEFAULT_HEIGHT_BY_TYPE[kind]
    if footprint_area_m2 is None:
        return DEFAULT_HEIGHT_M
    for limit, h in DEFAULT_HEIGHT_BY_AREA:
        if footprint_area_m2 < limit:
            return h
    return DEFAULT_HEIGHT_M


def building_height(tags, footprint_area_m2: float | None = None) -> tuple[float, str]:
    """(height in metres, source) with source "height", "building:levels" or "default"."""
    h = parse_length(tags.get("height"))
    if h is not None and 0.0 < h < 1000.0:
        return h, "height"
    lv = parse_levels(tags.get("building:levels"))
    if lv is not None and lv > 0:
        roof = parse_length(tags.get("roof:height"))
        if roof is None or not 0.0 <= roof < 100.0:
            rl = parse_levels(tags.get("roof:levels"))
            roof = (rl or 0.0) * LEVEL_HEIGHT_M
        return lv * LEVEL_HEIGHT_M + roof, "building:levels"
    return default_height(tags.get("building"), footprint_area_m2), "default"


def building_min_height(tags, height: float) -> float:
    """Height of the underside above the base: min_height, building:min_level x 3 m, a roof
    slab, else 0. Always below ``height`` (an inconsistent min_height is ignored)."""
    mh = parse_length(tags.get("min_height"))
    if mh is None:
        ml = parse_levels(tags.get("building:min_level"))
        mh = ml * LEVEL_HEIGHT_M if ml is not None else None
    if mh is None and tags.get("building") == "roof":
        mh = height - ROOF_SLAB_M
    if mh is None or not 0.0 <= mh < height - 0.1:
        return 0.0
    return float(mh)


# ------------------------------------------------------------------------------------------
@dataclass
class ChunkBuildings:
    """One chunk's buildings: the records, the footprints, counts, and the meshes as arrays.

    Building k (``records[k]``) owns ``vertices[vstart[k]:vstart[k+1]]`` and
    ``faces[fstart[k]:fstart[k+1]]`` (face indices into ``vertices``); ``material[k]``
    is its colour group (a key of :data:`COLOURS`). ``scene`` (one trimesh node per
    building, named by OSM id) and ``mesh`` (all merged, None without buildings) are made
    from the arrays when asked for; the build writes the arrays directly."""
    bounds: tuple
    records: list = field(default_factory=list)
    footprints: dict = field(default_factory=dict)    # id -> shapely geometry (world m)
    stats: dict = field(default_factory=dict)
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int64))
    vstart: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    fstart: np.ndarray = field(default_factory=lambda: np.zeros(1, np.int64))
    material: list = field(default_factory=list)

    def piece(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Vertices and (local) faces of building k."""
        v0, v1, f0, f1 = self.vstart[k], self.vstart[k + 1], self.fstart[k], self.fstart[k + 1]
        return self.vertices[v0:v1], self.faces[f0:f1] - v0

    @cached_property
    def scene(self) -> "trimesh.Scene":
        import trimesh

        scene = trimesh.Scene()
        mats = _materials()
        for k, rec in enumerate(self.records):
            v, f = self.piece(k)
            mesh = trimesh.Trimesh(v, f, process=False,
                                   visual=trimesh.visual.TextureVisuals(material=mats[self.material[k]]))
            scene.add_geometry(mesh, node_name=rec["id"], geom_name=rec["id"])
        return scene

    @cached_property
    def mesh(self) -> "trimesh.Trimesh | None":
        import trimesh

        if not self.records:
            return None
        return trimesh.Trimesh(self.vertices, self.faces, process=False)


def _materials() -> dict:
    from trimesh.visual.material import PBRMaterial

    return {k: PBRMaterial(name=f"building_{k}", baseColorFactor=list(c), metallicFactor=0.0,
                           roughnessFactor=0.9) for k, c in COLOURS.items()}


def underground(tags) -> bool:
    """A building below the ground (``location=underground``, or a negative ``layer``: an
    underground station, a car park under a square). Not built: extruded from the ground up,
    Monaco's underground railway station (``layer=-2``, 150 m long) stood 12 m tall across the
    streets above it, and the car drove onto its roof."""
    if str(tags.get("location", "")).strip().lower() in ("underground", "underwater"):
        return True
    layer = str(tags.get("layer", "")).strip()
    try:
        return int(float(layer)) < 0 if layer else False
    except ValueError:
        return False


def _footprints(features: OSMFeatures):
    """[(id, geometry, tags, placeholder)] with repaired geometry (underground buildings left
    out), and drop counts."""
    out, stats = [], {"slivers_dropped": 0, "parts_dropped": 0, "repaired": 0, "placeholders": 0,
                      "underground": 0}
    for f in features.buildings:
        g = f.geometry
        if underground(f.tags):
            stats["underground"] += 1
            continue
        if isinstance(g, Polygon) and g.area >= MIN_AREA_M2 and g.is_valid:   # the usual case
            out.append((f.id, g, f.tags, False))
            continue
        if not g.is_valid:
            stats["repaired"] += 1
        full = polygonal(g)
        kept = polygonal(g, MIN_AREA_M2)
        if kept is None:
            stats["slivers_dropped"] += 1
            continue
        stats["parts_dropped"] += len(shapely.get_parts(full)) - len(shapely.get_parts(kept))
        out.append((f.id, kept, f.tags, False))
    bn = features.building_nodes
    for i, ident in enumerate(bn.ids):
        if underground(bn.tags[i]):
            stats["underground"] += 1
            continue
        kind = bn.tags[i].get("building", "yes")
        w, d = NODE_FOOTPRINT.get(kind, NODE_FOOTPRINT_DEFAULT)
        x, y = bn.xy[i]
        out.append((ident, box(x - w / 2, y - d / 2, x + w / 2, y + d / 2), bn.tags[i], True))
        stats["placeholders"] += 1
    return out, stats


def footprint_parts(features: OSMFeatures) -> list:
    """Every building footprint (repaired; node placeholders included), as a list."""
    return [g for _, g, _, _ in _footprints(features)[0]]


def footprint_union(features: OSMFeatures):
    """Union of all building footprints (repaired; node placeholders included): the
    ``building_area`` that scenery keeps trees and benches out of. (A build hands scenery
    the footprints themselves, :func:`footprint_parts`: a point test needs no union.)"""
    parts = footprint_parts(features)
    if not parts:
        return Polygon()
    return shapely.union_all(parts)


def _base_samples(geoms) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the ground is sampled under each footprint (vertices, outline every <= 2 m, a
    2 m inner grid): (x, y, footprint index), all footprints at once."""
    n = len(geoms)
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0, np.int64)
    areas = shapely.area(geoms)
    step = np.maximum(SAMPLE_STEP_M, np.sqrt(areas / MAX_SAMPLES))
    outline = shapely.segmentize(geoms, step)
    xy, idx = shapely.get_coordinates(outline, return_index=True)
    # an inner grid per footprint, all footprints at once
    b = shapely.bounds(geoms)
    nx = np.maximum(np.floor((b[:, 2] - b[:, 0]) / step), 0).astype(np.int64) + 1
    ny = np.maximum(np.floor((b[:, 3] - b[:, 1]) / step), 0).astype(np.int64) + 1
    cnt = nx * ny
    gid = np.repeat(np.arange(n), cnt)
    k = np.arange(int(cnt.sum())) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    # centre the grid in the bounding box
    ox = b[:, 0] + 0.5 * ((b[:, 2] - b[:, 0]) - (nx - 1) * step)
    oy = b[:, 1] + 0.5 * ((b[:, 3] - b[:, 1]) - (ny - 1) * step)
    gx = ox[gid] + (k % nx[gid]) * step[gid]
    gy = oy[gid] + (k // nx[gid]) * step[gid]
    shapely.prepare(geoms)
    inside = shapely.contains_xy(geoms[gid], gx, gy)
    return (np.concatenate([xy[:, 0], gx[inside]]), np.concatenate([xy[:, 1], gy[inside]]),
            np.concatenate([idx, gid[inside]]))


def _base_heights(n: int, x, y, owner, ground, sink_m: float) -> np.ndarray:
    """Lowest ground under each of n footprints (samples from :func:`_base_samples`), less sink_m."""
    if n == 0:
        return np.zeros(0)
    z = np.asarray(ground(x, y), dtype=float).reshape(-1)
    if z.shape != x.shape or not np.all(np.isfinite(z)):
        raise BuildError("ground() returned no height for some building footprints")
    base = np.full(n, np.inf)
    np.minimum.at(base, owner, z)
    return base - sink_m


def extrude_footprints(geoms, z0, z1):
    """Extrude many footprints at once: solids from z0[i] to z1[i] over footprint geoms[i].

    Returns ``(vertices (V, 3), faces (F, 3), vstart (n+1,), fstart (n+1,))``: footprint i owns
    vertices ``vstart[i]:vstart[i+1]`` and faces ``fstart[i]:fstart[i+1]`` (global indices).
    Roof and floor are each polygon triangulated by earcut (mapbox-earcut, trimesh's polygon
    engine, which adds no vertices, so holes are kept as they are); the walls join each ring
    edge's floor and roof vertices, so every solid is watertight and outward-facing by
    construction (rings re-oriented: exterior counter-clockwise, holes clockwise). A polygon
    whose exterior has fewer than 3 distinct points contributes nothing.
    """
    geoms = np.asarray(geoms, dtype=object)
    nb = len(geoms)
    z0 = np.broadcast_to(np.asarray(z0, dtype=float), (nb,))
    z1 = np.broadcast_to(np.asarray(z1, dtype=float), (nb,))
    polys, bld = shapely.get_parts(geoms, return_index=True)
    rings, poly_of_ring = shapely.get_rings(polys, return_index=True)
    xy, ring_of = shapely.get_coordinates(rings, return_index=True)
    if not len(xy):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(nb + 1, np.int64), np.zeros(nb + 1, np.int64)
    nr = len(rings)
    # drop each ring's closing point and repeated consecutive points
    first = np.r_[True, ring_of[1:] != ring_of[:-1]]
    last = np.r_[ring_of[1:] != ring_of[:-1], True]
    keep = ~last
    same_prev = np.r_[False, np.all(xy[1:] == xy[:-1], axis=1)] & ~first
    keep &= ~same_prev
    xy, ring_of = xy[keep], ring_of[keep]
    cnt = np.bincount(ring_of, minlength=nr)
    rstart = np.cumsum(cnt) - cnt
    # ring orientation (shoelace), reverse where needed
    nxt = np.arange(len(xy)) + 1
    rend = rstart + cnt
    ok_ring = cnt >= 3
    nxt[rend[ok_ring] - 1] = rstart[ok_ring]
    nxt = np.minimum(nxt, len(xy) - 1)
    cross = xy[:, 0] * xy[nxt, 1] - xy[nxt, 0] * xy[:, 1]
    area2 = np.bincount(ring_of, weights=cross, minlength=nr)
    is_ext = np.r_[True, poly_of_ring[1:] != poly_of_ring[:-1]]
    flip = (area2 > 0) != is_ext
    pos = np.arange(len(xy)) - rstart[ring_of]
    src = np.where(flip[ring_of], rstart[ring_of] + cnt[ring_of] - 1 - pos, np.arange(len(xy)))
    xy = xy[src]
    # drop degenerate rings, and polygons whose exterior is degenerate
    poly_ok = np.ones(len(polys), bool)
    poly_ok[poly_of_ring[is_ext & ~ok_ring]] = False
    rk = ok_ring & poly_ok[poly_of_ring]
    ptk = rk[ring_of]
    xy, ring_of = xy[ptk], ring_of[ptk]
    cnt = np.where(rk, cnt, 0)
    rstart = np.cumsum(cnt) - cnt
    # per polygon: its points are contiguous (rings of a polygon are contiguous)
    npoly = len(polys)
    pcnt = np.bincount(poly_of_ring, weights=cnt, minlength=npoly).astype(np.int64)
    pstart = np.cumsum(pcnt) - pcnt            # into xy
    vbase = 2 * pstart                          # floor at vbase + i, roof at vbase + n + i
    # walls, all at once
    gi = np.arange(len(xy))
    p_of_pt = poly_of_ring[ring_of]
    gj = gi + 1
    re_ = rstart + cnt
    gj[re_[rk] - 1] = rstart[rk]
    li, lj = gi - pstart[p_of_pt], gj - pstart[p_of_pt]
    vb, n_p = vbase[p_of_pt], pcnt[p_of_pt]
    walls = np.concatenate([np.column_stack([vb + li, vb + lj, vb + n_p + lj]),
                            np.column_stack([vb + li, vb + n_p + lj, vb + n_p + li])])
    wall_poly = np.concatenate([p_of_pt, p_of_pt])
    # roofs and floors: earcut per polygon
    tris, tri_poly = [], []
    # each polygon's kept rings (rings of a polygon are contiguous): their ends, from 0
    kept = np.flatnonzero(rk)
    ring_end = (rstart + cnt)[kept]
    r0 = np.searchsorted(poly_of_ring[kept], np.arange(npoly), side="left")
    r1 = np.searchsorted(poly_of_ring[kept], np.arange(npoly), side="right")
    for p in np.flatnonzero(pcnt >= 3).tolist():
        a, n = pstart[p], pcnt[p]
        t = triangulate_float64(xy[a:a + n], (ring_end[r0[p]:r1[p]] - a).astype(np.uint32))
        if len(t):
            tris.append(t.reshape(-1, 3).astype(np.int64) + a)
            tri_poly.append(p)
    if tris:
        t = np.concatenate(tris)
        tp = np.repeat(np.array(tri_poly, dtype=np.int64), [len(x) for x in tris])
        e1, e2 = xy[t[:, 1]] - xy[t[:, 0]], xy[t[:, 2]] - xy[t[:, 0]]
        up = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) >= 0
        t = np.where(up[:, None], t, t[:, ::-1])
        loc = t - pstart[tp][:, None]
        vb_t, n_t = vbase[tp][:, None], pcnt[tp][:, None]
        floor = (vb_t + loc)[:, ::-1]
        roof = vb_t + n_t + loc
    else:
        floor = roof = np.zeros((0, 3), np.int64)
        tp = np.zeros(0, np.int64)
    faces = np.concatenate([floor, roof, walls])
    fpoly = np.concatenate([tp, tp, wall_poly])
    order = np.argsort(fpoly, kind="stable")
    faces, fpoly = faces[order], fpoly[order]
    # vertices: per polygon floor block then roof block
    V = np.empty((2 * len(xy), 3))
    zb0, zb1 = z0[bld], z1[bld]
    fl = vbase[p_of_pt] + (gi - pstart[p_of_pt])
    V[fl, :2] = xy
    V[fl, 2] = zb0[p_of_pt]
    V[fl + pcnt[p_of_pt], :2] = xy
    V[fl + pcnt[p_of_pt], 2] = zb1[p_of_pt]
    # per footprint ranges
    vcount = np.bincount(bld, weights=2 * pcnt, minlength=nb).astype(np.int64)
    fcount = np.bincount(bld[fpoly], minlength=nb) if len(fpoly) else np.zeros(nb, np.int64)
    vstart = np.r_[0, np.cumsum(vcount)]
    fstart = np.r_[0, np.cumsum(fcount)]
    return V, faces, vstart, fstart


def prism_arrays(geom, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """One footprint extruded from z0 to z1: (vertices, faces) with local indices."""
    V, F, vs, fs = extrude_footprints([geom], [z0], [z1])
    if not len(F):
        raise ValueError("footprint has no ring with 3 distinct points")
    return V, F


def chunk_index(px, py, chunk_bounds_list) -> np.ndarray:
    """Index into chunk_bounds_list of the chunk holding each point (half-open), or -1."""
    out = np.full(len(px), -1)
    for k, (x0, y0, x1, y1) in enumerate(chunk_bounds_list):
        m = (out < 0) & (px >= x0) & (px < x1) & (py >= y0) & (py < y1)
        out[m] = k
    return out


def cut_passages(plan: "BuildingPlan", road_parts, ground=None, clearance: float = PASSAGE_CLEARANCE_M,
                 margin: float = PASSAGE_MARGIN_M) -> np.ndarray:
    """Lift the parts of planned buildings that stand on the roads (module doc, "Over the
    roads"): ``road_parts`` are polygons where vehicles drive (they may overlap). With
    ``ground(x, y)`` (the natural terrain, vectorised) the clearance is over the highest ground
    under the part over the road, not over the building's base (a passage on a slope). The
    plan's solids, ranges and records are changed in place; returns the indices of the
    buildings changed."""
    parts = [g for g in road_parts if g is not None and not g.is_empty]
    n = len(plan.ids)
    if not parts or not n:
        return np.zeros(0, np.int64)
    low_ground = base_heights(plan, ground, sink_m=0.0) if ground is not None else None
    parts = np.array(parts, dtype=object)
    fps = np.empty(n, dtype=object)
    fps[:] = plan.footprints
    bi, pi = shapely.STRtree(parts).query(fps, predicate="intersects")
    order = np.argsort(bi, kind="stable")
    bi, pi = bi[order], pi[order]
    cuts, geoms, z0s, z1s, owner = [], [], [], [], []
    over_piece, over_floating = {}, {}
    ub, ustart = np.unique(bi, return_index=True)
    for b, lo, hi in zip(ub.tolist(), ustart.tolist(), np.r_[ustart[1:], len(bi)].tolist()):
        rec = plan.records[b]
        low, high = rec["min_height_m"], rec["height_m"]
        if plan.failed[b]:
            continue
        road = shapely.union_all(parts[pi[lo:hi]])
        if margin > 0:
            road = road.buffer(margin, quad_segs=2)
        fp = fps[b]
        over = polygonal(shapely.intersection(fp, road), PASSAGE_MIN_AREA_M2)
        if over is None:
            continue
        if low >= clearance:
            # nothing of it stands lower than a passage here; over a road that climbs under it
            # (a Lauf roof 4.5 m over its lowest ground stood 1.5 m over a road's higher end),
            # raise_passages lifts it whole
            over_floating[b] = (over, float(low))
            continue
        rest = polygonal(shapely.difference(fp, road), PASSAGE_MIN_AREA_M2)
        rise = 0.0
        if low_ground is not None:          # the ground under the road part above the base's
            q = shapely.get_coordinates(over)
            rise = max(0.0, float(np.max(ground(q[:, 0], q[:, 1]))) - float(low_ground[b]))
        top = max(low, clearance + rise)
        upper = high - top >= PASSAGE_MIN_SOLID_M
        pieces = ([(rest, low, high)] if rest is not None else []) + ([(over, top, high)] if upper else [])
        cuts.append(b)
        if not pieces:
            # (wholly over the road and lower than a passage: left out, as the part over the
            # road of any building is; kept whole, Helsinki's 3 m underpass entrance, way
            # 317502062, stood across a turn's lane)
            rec["passage_from_m"] = None
            continue
        for g, a, z in pieces:
            geoms.append(g)
            z0s.append(a)
            z1s.append(z)
            owner.append(b)
        rec["passage_from_m"] = round(float(top), 2) if upper else None
        if upper:
            over_piece[b] = (over, float(top), len(geoms) - 1)
    for b, (over, low) in over_floating.items():       # (its vertices all stay as they are)
        plan.passages[b] = (over, low, int(plan.vstart[b + 1] - plan.vstart[b]))
    if not cuts:
        return np.zeros(0, np.int64)
    if geoms:
        V2, F2, vs2, fs2 = extrude_footprints(geoms, z0s, z1s)
    else:
        V2, F2, vs2, fs2 = np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(1, np.int64), np.zeros(1, np.int64)
    owner = np.array(owner, dtype=np.int64)
    # each cut building's pieces are consecutive: its new range is its first piece's start to
    # its last piece's end; one left out has none
    new = {b: (0, 0, 0, 0) for b in cuts}
    if len(owner):
        first = np.r_[0, np.flatnonzero(owner[1:] != owner[:-1]) + 1]
        last = np.r_[first[1:], len(owner)]
        new.update({b: (vs2[a], vs2[z], fs2[a], fs2[z]) for b, a, z in zip(owner[first].tolist(), first, last)})
    Vb, Fb, vcount, fcount = [], [], np.diff(plan.vstart).copy(), np.diff(plan.fstart).copy()
    for b, (va, vz, fa, fz) in new.items():
        vcount[b], fcount[b] = vz - va, fz - fa
    vstart = np.r_[0, np.cumsum(vcount)]
    fstart = np.r_[0, np.cumsum(fcount)]
    # the arrays again, in runs of untouched buildings and the cut ones between them
    prev = 0
    for b in sorted(new) + [n]:
        if b > prev:                        # buildings prev..b-1 untouched: shifted as a block
            Vb.append(plan.vertices[plan.vstart[prev]:plan.vstart[b]])
            Fb.append(plan.faces[plan.fstart[prev]:plan.fstart[b]] + (vstart[prev] - plan.vstart[prev]))
        if b < n:
            va, vz, fa, fz = new[b]
            Vb.append(V2[va:vz])
            Fb.append(F2[fa:fz] + (vstart[b] - va))
        prev = b + 1
    plan.vertices = np.concatenate(Vb) if Vb else np.zeros((0, 3))
    plan.faces = np.concatenate(Fb).astype(np.int64) if Fb else np.zeros((0, 3), np.int64)
    plan.vstart, plan.fstart = vstart, fstart
    plan.failed = fstart[1:] == fstart[:-1]
    for b, (over, top, g) in over_piece.items():
        plan.passages[b] = (over, top, int(vs2[g + 1] - vs2[g]))
    return np.array(sorted(new), dtype=np.int64)


def raise_passages(plan: "BuildingPlan", base: np.ndarray, road_pts, clearance: float = PASSAGE_CLEARANCE_M) -> np.ndarray:
    """Once the roads' surface and the buildings' bases on the final terrain are known: every
    passage (:func:`cut_passages`) whose underside stands less than ``clearance`` less
    PASSAGE_SLACK_M over the road surface points under it (``road_pts`` (n, 3), where cars
    drive) is raised to ``clearance`` over them,
    keeping at least PASSAGE_MIN_SOLID_M of solid (above the building's roof if need be).
    The cut measures the clearance over the natural ground, and a road stands higher where
    its profile is smoothed over a steep or coarse DEM, or on a deck over another road: in
    Monaco the Espace Saint Antoine's passage was 1.2 m under Liaison Marquet's upper way
    (its base on the ground levelled down to the lower way, 5 m under), and a car stood before
    it for good. Changes the plan's vertices and records in place; returns the buildings
    raised."""
    if not plan.passages or road_pts is None or not len(road_pts):
        return np.zeros(0, np.int64)
    road_pts = np.asarray(road_pts, dtype=float)
    order = np.argsort(road_pts[:, 0], kind="stable")
    X, Y, Z = road_pts[order, 0], road_pts[order, 1], road_pts[order, 2]
    raised = []
    for b in sorted(plan.passages):
        over, top, nv = plan.passages[b]
        # (the road points in its box, then in it (the road grown by PASSAGE_MARGIN_M, cut by
        # the footprint): a tree of a city's road points cost 100 ms)
        x0, y0, x1, y1 = over.bounds
        i0, i1 = np.searchsorted(X, [x0, x1])
        k = i0 + np.flatnonzero((Y[i0:i1] >= y0) & (Y[i0:i1] <= y1))
        if not len(k):
            continue
        k = k[shapely.contains_xy(over, X[k], Y[k])]
        if not len(k):
            continue
        need = float(Z[k].max()) + clearance - float(base[b])
        if need <= top + PASSAGE_SLACK_M:
            continue
        rec = plan.records[b]
        v1 = int(plan.vstart[b + 1])
        piece = plan.vertices[v1 - nv:v1]           # (a prism: its floor's vertices, its roof's)
        z0, z1 = float(piece[:, 2].min()), float(piece[:, 2].max())
        bottom = piece[:, 2] <= z0 + 1e-6
        piece[~bottom, 2] = max(z1, need + PASSAGE_MIN_SOLID_M)
        piece[bottom, 2] = need
        plan.passages[b] = (plan.passages[b][0], need, nv)
        rec["passage_from_m"] = round(need, 2)
        raised.append(b)
    return np.array(raised, dtype=np.int64)


@dataclass
class BuildingPlan:
    """Everything about the buildings that does not need the terrain (see :func:`plan_buildings`).

    Arrays are over the kept buildings (those in a chunk), in record order: the solids
    extruded from z = min_height to z = height above a base of 0, and the ground samples
    that will give each its base."""
    chunk_bounds: list
    stats: dict
    outside: int
    all_footprints: list               # every footprint, in chunks or not (scenery keeps out)
    ids: list
    chunk: np.ndarray
    footprints: list
    records: list                      # without base_z
    material: list
    vertices: np.ndarray
    faces: np.ndarray
    vstart: np.ndarray
    fstart: np.ndarray
    failed: np.ndarray                 # bool: nothing left to extrude (degenerate rings)
    sample_x: np.ndarray
    sample_y: np.ndarray
    sample_owner: np.ndarray
    # cut_passages: building -> (its part over the road, that part's underside over the base,
    # its number of vertices: the building's last), for raise_passages
    passages: dict = field(default_factory=dict)


def plan_buildings(features: OSMFeatures, chunk_bounds_list) -> BuildingPlan:
    """Footprints, heights, chunks and solids (on a base of 0) of every building.

    The terrain is not needed: the build does this while netconvert runs, and
    :func:`place_buildings` then lifts each solid onto the final (road-levelled) terrain."""
    chunk_bounds_list = [tuple(map(float, b)) for b in chunk_bounds_list]
    fps, stats = _footprints(features)
    geoms = np.array([g for _, g, _, _ in fps], dtype=object)
    if len(fps):
        rp = shapely.get_coordinates(shapely.point_on_surface(geoms))
        chunk = chunk_index(rp[:, 0], rp[:, 1], chunk_bounds_list)
    else:
        chunk = np.zeros(0, np.int64)
    sel = np.flatnonzero(chunk >= 0)
    areas = shapely.area(geoms[sel]) if len(sel) else np.zeros(0)
    cent = shapely.get_coordinates(shapely.centroid(geoms[sel])) if len(sel) else np.zeros((0, 2))
    hs = [building_height(fps[i][2], float(a)) for i, a in zip(sel, areas)]
    mhs = np.array([building_min_height(fps[i][2], h) for i, (h, _) in zip(sel, hs)])
    hv = np.array([h for h, _ in hs])
    V, F, vstart, fstart = extrude_footprints(geoms[sel], mhs, hv)
    sx, sy, owner = _base_samples(geoms[sel])
    records, material = [], []
    for n, i in enumerate(sel):
        ident, g, tags, placeholder = fps[i]
        kind = tags.get("building", "yes")
        (h, src), mh = hs[n], mhs[n]
        material.append(_group(kind))
        records.append({
            "id": ident, "kind": kind, "height_m": float(h), "height_source": src,
            "base_z": None, "min_height_m": float(mh),
            "footprint_area_m2": round(float(areas[n]), 2),
            "centroid": [round(float(cent[n, 0]), 2), round(float(cent[n, 1]), 2)],
            "levels": parse_levels(tags.get("building:levels")),
            "name": tags.get("name"), "placeholder": bool(placeholder),
        })
    return BuildingPlan(chunk_bounds=chunk_bounds_list, stats=stats, outside=int((chunk < 0).sum()),
                        all_footprints=[g for _, g, _, _ in fps],
                        ids=[fps[i][0] for i in sel], chunk=chunk[sel],
                        footprints=[fps[i][1] for i in sel], records=records, material=material,
                        vertices=V, faces=F, vstart=vstart, fstart=fstart,
                        failed=(fstart[1:] == fstart[:-1]), sample_x=sx, sample_y=sy, sample_owner=owner)


@dataclass
class ChunkLayout:
    """One chunk's buildings without their heights (what :func:`place_buildings` and the
    world build's prepared writers share): plan indices (``mine``), the chunk's vertices as
    plan vertex numbers (``vidx``), its faces over them, ranges, colour groups, stats."""
    bounds: tuple
    mine: np.ndarray
    vidx: np.ndarray
    faces: np.ndarray
    vstart: np.ndarray
    fstart: np.ndarray
    material: list
    stats: dict


def chunk_layouts(plan: BuildingPlan) -> list[ChunkLayout]:
    """Per chunk, in ``plan.chunk_bounds`` order: which planned solids it holds and how."""
    out = []
    for k, bounds in enumerate(plan.chunk_bounds):
        stats = {"buildings": 0}
        mine = np.flatnonzero(plan.chunk == k)
        failed = mine[plan.failed[mine]]
        if len(failed):             # nothing left of a degenerate ring: count it
            stats["extrude_failed"] = len(failed)
        mine = mine[~plan.failed[mine]]
        vidx = np.zeros(0, np.int64)
        faces = np.zeros((0, 3), np.int64)
        vstart = fstart = np.zeros(1, np.int64)
        if len(mine):
            vs, ve = plan.vstart[mine], plan.vstart[mine + 1]
            fs, fe = plan.fstart[mine], plan.fstart[mine + 1]
            vcnt, fcnt = ve - vs, fe - fs
            vidx = np.repeat(vs - np.cumsum(vcnt) + vcnt, vcnt) + np.arange(vcnt.sum())
            fidx = np.repeat(fs - np.cumsum(fcnt) + fcnt, fcnt) + np.arange(fcnt.sum())
            # faces: global vertex numbers -> numbers in this chunk's vertex array
            shift = np.repeat(np.cumsum(vcnt) - vcnt - vs, fcnt)
            faces = plan.faces[fidx] + shift[:, None]
            vstart = np.r_[0, np.cumsum(vcnt)]
            fstart = np.r_[0, np.cumsum(fcnt)]
        stats["buildings"] = len(mine)
        stats["passages"] = sum(1 for i in mine.tolist() if "passage_from_m" in plan.records[i])
        # global drop counts are reported with every chunk (they happen before assignment)
        stats.update(plan.stats)
        stats["outside_chunks"] = plan.outside
        out.append(ChunkLayout(bounds, mine, vidx, faces, vstart, fstart,
                               [plan.material[i] for i in mine], stats))
    return out


def base_heights(plan: BuildingPlan, ground, sink_m: float = 0.1) -> np.ndarray:
    """Each planned building's base: the lowest ground under its footprint less sink_m."""
    return _base_heights(len(plan.ids), plan.sample_x, plan.sample_y, plan.sample_owner, ground, sink_m)


def lifted_vertices(plan: BuildingPlan, base: np.ndarray) -> np.ndarray:
    """Every planned vertex lifted by its building's base."""
    V = plan.vertices.copy()
    V[:, 2] += np.repeat(base, np.diff(plan.vstart))
    return V


def place_buildings(plan: BuildingPlan, ground, sink_m: float = 0.1) -> list[ChunkBuildings]:
    """Put the planned solids on the ground: base = lowest ground under the footprint less
    sink_m, every vertex lifted by its building's base; one :class:`ChunkBuildings` per chunk."""
    base = base_heights(plan, ground, sink_m)
    V = lifted_vertices(plan, base)
    results = []
    for lay in chunk_layouts(plan):
        r = ChunkBuildings(bounds=lay.bounds, stats=lay.stats)
        if len(lay.mine):
            r.vertices = V[lay.vidx]
            r.faces = lay.faces
            r.vstart, r.fstart = lay.vstart, lay.fstart
            r.material = lay.material
            for i in lay.mine:
                r.footprints[plan.ids[i]] = plan.footprints[i]
                r.records.append({**plan.records[i], "base_z": float(base[i])})
        results.append(r)
    return results


def make_buildings(features: OSMFeatures, ground, chunk_bounds_list, sink_m: float = 0.1
                   ) -> list[ChunkBuildings]:
    """Extrude every building onto the terrain and sort them into chunks.

    ``ground(x_array, y_array) -> z_array`` is the terrain height (vectorised);
    ``chunk_bounds_list`` a list of (xmin, ymin, xmax, ymax). Returns one
    :class:`ChunkBuildings` per chunk, in the same order. Buildings whose representative
    point is in no chunk are left out. (:func:`plan_buildings` then :func:`place_buildings`.)
    """
    return place_buildings(plan_buildings(features, chunk_bounds_list), ground, sink_m)


def write_chunk_buildings(result: ChunkBuildings, out_dir, obj: bool = True) -> dict:
    """Write buildings.glb (named nodes), buildings.obj (merged; only if `obj`) and
    buildings.json (records).

    Returns {"glb": ..., "obj": ..., "json": ...} with file names relative to ``out_dir``;
    a chunk without buildings writes only the JSON (an empty list) and maps glb/obj to None.
    Files are written under a temporary name and renamed; a write error is a
    :class:`BuildError`. (A world build leaves out buildings.obj: its tiles already hold
    every building as a named OBJ group; it writes the same GLB and JSON from templates
    made before the terrain is final, :func:`glb_template` and :func:`json_template`.)
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = {"glb": None, "obj": None, "json": "buildings.json"}
    if result.records:
        write_file(out / "buildings.glb", glb_template(
            [r["id"] for r in result.records], result.faces, result.vstart, result.fstart,
            result.material, len(result.vertices)).render(result.vertices))
        files["glb"] = "buildings.glb"
        if obj:
            write_obj(out / "buildings.obj", result.vertices, result.faces)
            files["obj"] = "buildings.obj"
    write_file(out / "buildings.json", json.dumps(
        {"bounds": list(result.bounds), "buildings": result.records,
         "stats": _jsonable(result.stats)}).encode())
    return files


def glb_template(ids, faces, vstart, fstart, material, n_vertices: int):
    """buildings.glb but its positions (:class:`netgen.meshio.GlbTemplate`)."""
    groups = list(COLOURS)
    return GlbTemplate(ids, faces, vstart, fstart, [groups.index(m) for m in material],
                       [{"name": f"building_{k}", "rgba": c, "roughness": 0.9, "metallic": 0.0}
                        for k, c in COLOURS.items()], n_vertices)


def json_template(bounds, records, stats) -> JsonTemplate:
    """buildings.json of `records` (without their ``base_z``) but the bases: render it
    with the JSON text of each record's base (the same text as :func:`write_chunk_buildings`)."""
    return JsonTemplate(lambda holes: {"bounds": list(bounds),
                                       "buildings": [{**r, "base_z": h} for r, h in zip(records, holes)],
                                       "stats": _jsonable(stats)}, len(records))


def _jsonable(d: dict) -> dict:
    return {k: (v if isinstance(v, (int, float, str, list, type(None))) else str(v)) for k, v in d.items()}


__all__ = ["building_height", "building_min_height", "default_height", "parse_length",
           "parse_levels", "make_buildings", "plan_buildings", "place_buildings", "BuildingPlan",
           "write_chunk_buildings", "footprint_union", "footprint_parts",
           "ChunkBuildings", "chunk_index", "extrude_footprints", "cut_passages", "LEVEL_HEIGHT_M",
           "MIN_AREA_M2", "PASSAGE_CLEARANCE_M"]
