"""Buildings and scenery from an OSM file, in world metres.

One streaming pass of pyosmium (plus the relation pre-pass that its area assembly needs)
over a ``.osm`` / ``.osm.pbf`` / ``.osm.gz`` / ``.osm.bz2`` file collects:

* **buildings**: closed ways and multipolygon relations tagged ``building=*`` (not
  ``building=no``), as shapely (Multi)Polygons with their holes (courtyards), assembled by
  libosmium's area assembler. A closed building way that the assembler rejects (a
  self-intersecting ring) is taken from its node list instead and repaired later with
  ``shapely.make_valid``. A building way that is also the outer ring of a building relation
  is the same building mapped twice: the relation is kept, the way dropped (counted).
  ``building:part=*`` outlines are not used: the outline carries the building's height.
* **building nodes**: ``building=*`` on a node (point + type); ``building=entrance`` and the
  like, which are door nodes on an outline, are not buildings.
* **scenery**: ``natural=tree`` nodes, ``natural=tree_row`` ways (lines), woods
  (``landuse=forest``, ``natural=wood``), ``highway=street_lamp`` / ``traffic_signals`` /
  ``stop`` / ``give_way`` / ``crossing`` nodes, ``amenity=bench`` nodes, water areas
  (``natural=water``, ``water=*``, ``landuse=reservoir``, ``waterway=riverbank``) and grass
  areas (``landuse=grass`` / ``meadow`` / ``village_green``, ``leisure=park``).

For signals, signs and crossings that are nodes of a highway way, the direction of that way
through the node is kept (``road_dir``, radians counter-clockwise from +x, NaN when the node
is on no highway), so that ``direction=forward|backward`` can be turned into a facing.

All coordinates are projected in bulk with :meth:`WorldFrame.to_xy` (one call per layer).
Everything keeps its OSM id as ``"node/1"``, ``"way/2"`` or ``"relation/3"`` (pyosmium's
area ids, 2 x way id and 2 x relation id + 1, are converted back).

A bbox (south, west, north, east, the order of :func:`netgen.frame.parse_bbox`) limits the
output to points inside it and to lines/areas that intersect it; areas are not clipped.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import osmium
import shapely
from shapely.geometry import MultiPolygon, Polygon, box

from .errors import DataError
from .frame import WorldFrame

# --- what is what ----------------------------------------------------------------------------
#: building=* values on nodes that mark a door or a part of an outline, not a building
NOT_BUILDING_NODES = {"entrance", "underpass_entrance", "door", "no", "emergency_exit"}
WOOD = {("landuse", "forest"), ("natural", "wood")}
GRASS = {("landuse", "grass"), ("landuse", "meadow"), ("landuse", "village_green"), ("leisure", "park")}
WATER_TAGS = {("natural", "water"), ("landuse", "reservoir"), ("waterway", "riverbank")}
POINT_KINDS = {  # (key, value) on a node -> layer name
    ("natural", "tree"): "trees",
    ("highway", "street_lamp"): "street_lamps",
    ("highway", "traffic_signals"): "traffic_signals",
    ("highway", "stop"): "stop_signs",
    ("highway", "give_way"): "give_way_signs",
    ("highway", "crossing"): "crossings",
    ("amenity", "bench"): "benches",
}
#: layers whose nodes get the direction of the highway way they sit on
ROAD_NODE_KINDS = ("traffic_signals", "stop_signs", "give_way_signs")
#: highway classes that carry cars (preferred when a node is on several ways)
CAR_HIGHWAYS = {"motorway", "trunk", "primary", "secondary", "tertiary", "unclassified",
                "residential", "living_street", "service", "motorway_link", "trunk_link",
                "primary_link", "secondary_link", "tertiary_link", "road", "busway"}

_NODE_KEYS = ("building", "natural", "highway", "amenity")
_WAY_KEYS = ("building", "natural", "highway")
_AREA_KEYS = ("building", "natural", "landuse", "water", "waterway", "leisure")


@dataclass
class Feature:
    """A line or area feature: OSM id, shapely geometry in world metres, all its tags."""
    id: str
    geometry: object
    tags: dict


@dataclass
class PointSet:
    """Point features of one kind: ids, (N, 2) world x/y, tags and the road direction."""
    kind: str
    ids: list = field(default_factory=list)
    xy: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    tags: list = field(default_factory=list)
    road_dir: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __len__(self) -> int:
        return len(self.ids)


@dataclass
class OSMFeatures:
    frame: WorldFrame
    bbox: tuple | None
    buildings: list = field(default_factory=list)        # Feature, (Multi)Polygon
    building_nodes: PointSet = field(default_factory=lambda: PointSet("building_nodes"))
    trees: PointSet = field(default_factory=lambda: PointSet("trees"))
    tree_rows: list = field(default_factory=list)        # Feature, LineString
    woods: list = field(default_factory=list)            # Feature, (Multi)Polygon
    water: list = field(default_factory=list)
    grass: list = field(default_factory=list)
    street_lamps: PointSet = field(default_factory=lambda: PointSet("street_lamps"))
    traffic_signals: PointSet = field(default_factory=lambda: PointSet("traffic_signals"))
    stop_signs: PointSet = field(default_factory=lambda: PointSet("stop_signs"))
    give_way_signs: PointSet = field(default_factory=lambda: PointSet("give_way_signs"))
    crossings: PointSet = field(default_factory=lambda: PointSet("crossings"))
    benches: PointSet = field(default_factory=lambda: PointSet("benches"))
    stats: dict = field(default_factory=dict)

    def counts(self) -> dict:
        out = {"buildings": len(self.buildings), "tree_rows": len(self.tree_rows),
               "woods": len(self.woods), "water": len(self.water), "grass": len(self.grass)}
        for k in ("building_nodes", "trees", "street_lamps", "traffic_signals", "stop_signs",
                  "give_way_signs", "crossings", "benches"):
            out[k] = len(getattr(self, k))
        return out


def polygonal(geom, min_area: float = 0.0):
    """The polygonal part of a geometry, repaired with make_valid; parts under min_area dropped.

    Returns a Polygon, a MultiPolygon or None. Lines and points that make_valid leaves behind
    (collapsed spikes) are discarded.
    """
    if geom is None or geom.is_empty:
        return None
    if not geom.is_valid:
        geom = shapely.make_valid(geom)
    parts = [g for g in shapely.get_parts(geom)
             if isinstance(g, (Polygon, MultiPolygon))]
    polys = []
    for g in parts:
        polys.extend(shapely.get_parts(g) if isinstance(g, MultiPolygon) else [g])
    polys = [p for p in polys if p.area > min_area and not p.is_empty]
    if not polys:
        return None
    if len(polys) == 1:
        return polys[0]
    return MultiPolygon(polys)


def _area_kinds(tags) -> list[str]:
    kinds = []
    b = tags.get("building")
    if b is not None and b != "no":
        kinds.append("buildings")
    items = {(k, tags.get(k)) for k in ("landuse", "natural", "leisure", "waterway")}
    if items & WOOD:
        kinds.append("woods")
    if items & WATER_TAGS or "water" in tags:
        kinds.append("water")
    if items & GRASS:
        kinds.append("grass")
    return kinds


def extract_features(path, frame: WorldFrame, bbox=None) -> OSMFeatures:
    """Read buildings and scenery from an OSM file (see the module docstring).

    ``bbox`` is (south, west, north, east) in degrees or None for everything in the file.
    Raises :class:`DataError` when the file is missing or cannot be read.
    """
    path = Path(path)
    if not path.is_file():
        raise DataError(f"OSM file not found: {path}")

    nf = osmium.filter.KeyFilter(*_NODE_KEYS)
    nf.enable_for(osmium.osm.NODE)
    wf = osmium.filter.KeyFilter(*_WAY_KEYS)
    wf.enable_for(osmium.osm.WAY)
    af = osmium.filter.KeyFilter(*_AREA_KEYS)
    af.enable_for(osmium.osm.AREA)
    rf = osmium.filter.KeyFilter("building")
    rf.enable_for(osmium.osm.RELATION)
    proc = (osmium.FileProcessor(str(path))
            .with_areas(osmium.filter.KeyFilter(*_AREA_KEYS))
            .with_filter(nf).with_filter(wf).with_filter(af).with_filter(rf))

    wkb = osmium.geom.WKBFactory()
    pts = {k: ([], [], [], []) for k in (*POINT_KINDS.values(), "building_nodes")}  # ids lon lat tags
    wanted = False                               # any node that needs a road direction?
    hw_lines: list[tuple[bool, str]] = []        # (carries cars?, wkb) of highway ways
    areas = {"buildings": [], "woods": [], "water": [], "grass": []}   # (id, wkb, tags)
    closed_bways: dict[int, tuple] = {}          # way id -> (wkb linestring | None, tags)
    area_from_way: set[int] = set()
    rel_outer_ways: dict[int, list[int]] = {}   # building relation id -> its outer ways
    rel_with_area: set[int] = set()
    tree_rows = []
    stats = {"building_ways_incomplete": 0, "building_ways_unclosed": 0, "areas_failed": 0}

    try:
        for o in proc:
            if o.is_node():
                loc = o.location
                if not loc.valid():
                    continue
                tags = o.tags
                for key in ("natural", "highway", "amenity"):
                    layer = POINT_KINDS.get((key, tags.get(key)))
                    if layer:
                        lst = pts[layer]
                        if layer in ROAD_NODE_KINDS:
                            wanted = True
                        lst[0].append(o.id), lst[1].append(loc.lon), lst[2].append(loc.lat)
                        lst[3].append(dict(tags))
                b = tags.get("building")
                if b is not None and b not in NOT_BUILDING_NODES:
                    lst = pts["building_nodes"]
                    lst[0].append(o.id), lst[1].append(loc.lon), lst[2].append(loc.lat)
                    lst[3].append(dict(tags))
            elif o.is_area():
                oid = o.orig_id()
                # an area from a building way comes right after the way, with its tags: the
                # way's copy serves (a tag copy or lookup costs more than the area's geometry)
                way = closed_bways.get(oid) if o.from_way() else None
                kinds = _area_kinds(o.tags if way is None else way[1])
                if not kinds:
                    continue
                try:
                    g = wkb.create_multipolygon(o)
                except RuntimeError:
                    stats["areas_failed"] += 1
                    continue
                ident = f"way/{oid}" if o.from_way() else f"relation/{oid}"
                tags = way[1] if way is not None else dict(o.tags)
                for k in kinds:
                    areas[k].append((ident, g, tags))
                if "buildings" in kinds:
                    (area_from_way if o.from_way() else rel_with_area).add(oid)
            elif o.is_way():
                tags = o.tags
                b = tags.get("building")
                if b is not None and b != "no":
                    if not o.is_closed():
                        stats["building_ways_unclosed"] += 1
                    else:
                        try:
                            closed_bways[o.id] = (wkb.create_linestring(o), dict(tags))
                        except (RuntimeError, osmium.InvalidLocationError):
                            closed_bways[o.id] = (None, dict(tags))
                if tags.get("natural") == "tree_row":
                    try:
                        tree_rows.append((f"way/{o.id}", wkb.create_linestring(o), dict(tags)))
                    except (RuntimeError, osmium.InvalidLocationError):
                        pass
                hw = tags.get("highway")
                if hw is not None and wanted:
                    # matched to the wanted nodes by location after the pass (no per-node Python)
                    try:
                        hw_lines.append((hw in CAR_HIGHWAYS, wkb.create_linestring(o, osmium.geom.ALL)))
                    except (RuntimeError, osmium.InvalidLocationError):
                        pass
            elif o.is_relation():
                if o.tags.get("type") == "multipolygon" and o.tags.get("building", "no") != "no":
                    rel_outer_ways[o.id] = [m.ref for m in o.members
                                            if m.type == "w" and m.role in ("outer", "")]
    except RuntimeError as e:   # libosmium: corrupt or unreadable file
        raise DataError(f"cannot read OSM file {path}: {e}")

    feats = OSMFeatures(frame=frame, bbox=tuple(bbox) if bbox is not None else None)
    bbox_ll = box(bbox[1], bbox[0], bbox[3], bbox[2]) if bbox is not None else None

    # --- buildings: areas, fallback rings of rejected ways, duplicates -----------------------
    # a building way that is an outer ring of a building relation (which became an area) is
    # the same building mapped twice: keep the relation
    dup_ways = {w for r in rel_with_area for w in rel_outer_ways.get(r, ())}
    dup_ways &= set(closed_bways)
    barea = []
    for ident, g, tags in areas["buildings"]:
        if ident.startswith("way/") and int(ident[4:]) in dup_ways:
            continue
        barea.append((ident, g, tags))
    stats["building_ways_duplicating_relations"] = len(dup_ways)
    fallback = 0
    for wid, (line, tags) in closed_bways.items():
        if wid in area_from_way or wid in dup_ways:
            continue
        if line is None:
            stats["building_ways_incomplete"] += 1
            continue
        barea.append((f"way/{wid}", ("ring", line), tags))
        fallback += 1
    stats["building_ways_from_ring"] = fallback
    feats.buildings = _project_areas(barea, frame, bbox_ll)
    feats.woods = _project_areas(areas["woods"], frame, bbox_ll)
    feats.water = _project_areas(areas["water"], frame, bbox_ll)
    feats.grass = _project_areas(areas["grass"], frame, bbox_ll)
    feats.tree_rows = _project_lines(tree_rows, frame, bbox_ll)

    # --- points ---------------------------------------------------------------------------
    for layer, (ids, lon, lat, tags) in pts.items():
        prefix_ids = np.asarray(ids, dtype=np.int64)
        lon = np.asarray(lon, dtype=float)
        lat = np.asarray(lat, dtype=float)
        road_dir = np.full(len(ids), np.nan)
        if layer in ROAD_NODE_KINDS and len(ids) and hw_lines:
            road_dir = _road_directions(lon, lat, hw_lines, frame)
        keep = np.ones(len(ids), bool)
        if bbox is not None:
            s, w, n, e = bbox
            keep = (lon >= w) & (lon <= e) & (lat >= s) & (lat <= n)
        x, y = frame.to_xy(lon[keep], lat[keep])
        ps = PointSet(kind=layer,
                      ids=[f"node/{i}" for i in prefix_ids[keep]],
                      xy=np.column_stack([np.atleast_1d(x), np.atleast_1d(y)]).reshape(-1, 2),
                      tags=[t for t, k in zip(tags, keep) if k],
                      road_dir=road_dir[keep])
        setattr(feats, layer, ps)
    feats.stats = stats
    return feats


def _road_directions(lon, lat, hw_lines, frame: WorldFrame) -> np.ndarray:
    """Direction (radians from +x, world frame) of the highway way through each node, or NaN.

    The nodes are found among the ways' vertices by location (exact to 1e-7 degrees, the
    resolution of OSM coordinates); a way for cars wins over a footway through the same node.
    """
    out = np.full(len(lon), np.nan)
    lines = shapely.from_wkb([w for _, w in hw_lines])
    car = np.array([c for c, _ in hw_lines], dtype=bool)
    pts = shapely.points(lon, lat)
    pi, li = shapely.STRtree(lines).query(pts, predicate="dwithin", distance=1.5e-7)
    best = {}
    for p, l in zip(pi, li):
        if p in best and (best[p][0] or not car[l]):
            continue
        c = shapely.get_coordinates(lines[l])
        d = np.hypot(c[:, 0] - lon[p], c[:, 1] - lat[p])
        k = int(np.argmin(d))
        if d[k] > 1.5e-7:
            continue            # crosses the way between vertices: not one of its nodes
        a, b = c[max(k - 1, 0)], c[min(k + 1, len(c) - 1)]
        best[p] = (bool(car[l]), a, b)
    if best:
        idx = np.fromiter(best, dtype=np.int64)
        ab = np.array([np.concatenate([best[i][1], best[i][2]]) for i in idx])
        x0, y0 = frame.to_xy(ab[:, 0], ab[:, 1])
        x1, y1 = frame.to_xy(ab[:, 2], ab[:, 3])
        out[idx] = np.arctan2(y1 - y0, x1 - x0)
    return out


def _projector(frame: WorldFrame):
    def f(coords):
        x, y = frame.to_xy(coords[:, 0], coords[:, 1])
        return np.column_stack([x, y])
    return f


def _project_areas(items, frame: WorldFrame, bbox_ll) -> list:
    """(id, wkb | ("ring", wkb linestring), tags) -> [Feature] in world metres, bbox-filtered."""
    if not items:
        return []
    geoms = []
    for _, g, _ in items:
        if isinstance(g, tuple):     # a closed way the assembler rejected: take its ring as is
            line = shapely.from_wkb(g[1])
            coords = np.asarray(line.coords)
            geoms.append(Polygon(coords) if len(coords) >= 4 else None)
        else:
            geoms.append(g)
    arr = np.empty(len(geoms), dtype=object)
    wk = [i for i, g in enumerate(geoms) if isinstance(g, str)]
    if wk:
        arr[wk] = shapely.from_wkb([geoms[i] for i in wk])
    for i, g in enumerate(geoms):
        if not isinstance(g, str):
            arr[i] = g
    ok = ~shapely.is_missing(arr) & ~shapely.is_empty(arr)
    if bbox_ll is not None:
        ok &= shapely.intersects(bbox_ll, arr)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return []
    proj = shapely.transform(arr[idx], _projector(frame))
    single = shapely.get_num_geometries(proj) == 1      # libosmium gives MULTIPOLYGONs
    proj[single] = shapely.get_geometry(proj[single], 0)
    return [Feature(items[i][0], g, items[i][2]) for i, g in zip(idx, proj)]


def _project_lines(items, frame: WorldFrame, bbox_ll) -> list:
    if not items:
        return []
    arr = shapely.from_wkb([g for _, g, _ in items])
    ok = np.ones(len(arr), bool)
    if bbox_ll is not None:
        ok = shapely.intersects(bbox_ll, arr)
    idx = np.flatnonzero(ok)
    if not len(idx):
        return []
    proj = shapely.transform(arr[idx], _projector(frame))
    return [Feature(items[i][0], g, items[i][2]) for i, g in zip(idx, proj)]


def bbox_of_frame(frame: WorldFrame, chunks, margin_m: float = 0.0):
    """(south, west, north, east) covering the given chunks plus a margin: a convenience."""
    return frame.bbox_lonlat(frame.extent(chunks), margin_m)


__all__ = ["Feature", "PointSet", "OSMFeatures", "extract_features", "polygonal",
           "bbox_of_frame", "NOT_BUILDING_NODES", "CAR_HIGHWAYS"]
