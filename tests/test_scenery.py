"""Scenery from real OSM extracts: counts against the source, placement, determinism, areas.

The carriageway (``road_area``) that the roads layer gives in a build is made here the
simple way: OSM highway ways for cars buffered by half their width. Source counts and
positions are read here with pyosmium, independently of netgen.
"""
from __future__ import annotations

import json
import math
import sys
from collections import Counter

import numpy as np
import osmium
import pytest
import shapely
import trimesh
from pyproj import Geod

from netgen.buildings import footprint_union
from netgen.frame import WorldFrame
from netgen.osm_features import extract_features
from netgen.presets import get_preset
from netgen.scenery import (AREA_STYLE, MAX_MOVE_M, OFF_ROAD_M, POLE_FOOT_M, PREFAB_KINDS, make_scenery,
                            write_chunk_scenery)

from conftest import REPO, shared_file

MONACO_CENTRE = (43.7385, 7.4244)
HALF_WIDTH = {"motorway": 7.0, "trunk": 6.0, "primary": 5.0, "secondary": 4.5, "tertiary": 4.0,
              "unclassified": 3.0, "residential": 3.0, "living_street": 2.5, "service": 2.0,
              "motorway_link": 3.5, "trunk_link": 3.5, "primary_link": 3.5, "secondary_link": 3.5,
              "tertiary_link": 3.0}
SOURCE_TAGS = {  # scenery source -> (key, value) on OSM nodes
    "tree": ("natural", "tree"), "street_lamp": ("highway", "street_lamp"),
    "traffic_signal": ("highway", "traffic_signals"), "stop_sign": ("highway", "stop"),
    "give_way_sign": ("highway", "give_way"), "bench": ("amenity", "bench"),
}
POLES = ("street_lamp", "traffic_signal", "stop_sign", "give_way_sign")


def flat(x, y):
    return np.zeros_like(np.asarray(x, float))


def bumpy(x, y):
    x, y = np.asarray(x, float), np.asarray(y, float)
    return 3.0 * np.sin(x / 19.0) * np.cos(y / 27.0) + 0.05 * x + 1.0 * np.cos(y / 6.0)


def road_area_from_osm(path, frame):
    """Car carriageways: highway ways for cars (not in tunnels) buffered by half a width."""
    wkb = osmium.geom.WKBFactory()
    lines, half = [], []
    for w in osmium.FileProcessor(str(path)).with_locations().with_filter(osmium.filter.KeyFilter("highway")):
        if not w.is_way():
            continue
        hw = w.tags.get("highway")
        if hw not in HALF_WIDTH or w.tags.get("area") == "yes" or w.tags.get("tunnel", "no") != "no":
            continue
        try:
            lines.append(wkb.create_linestring(w))
        except (RuntimeError, osmium.InvalidLocationError):
            continue                     # cut at the extract's edge
        try:
            half.append(max(float(w.tags.get("lanes")), 1.0) * 3.0 / 2.0)
        except (TypeError, ValueError):
            half.append(HALF_WIDTH[hw])
    g = shapely.from_wkb(lines)
    g = shapely.transform(g, lambda c: np.column_stack(frame.to_xy(c[:, 0], c[:, 1])))
    return shapely.union_all(shapely.buffer(g, np.array(half), quad_segs=4))


def source_nodes(path, frame, extent):
    """{source: {osm id: (x, y, tags)}} of the scenery nodes inside the extent."""
    want = {v: k for k, v in SOURCE_TAGS.items()}
    want[("highway", "crossing")] = "crossing"
    raw = {k: [] for k in (*SOURCE_TAGS, "crossing")}
    for n in osmium.FileProcessor(str(path), osmium.osm.NODE):
        for key in ("natural", "highway", "amenity"):
            src = want.get((key, n.tags.get(key)))
            if src:
                raw[src].append((f"node/{n.id}", n.location.lon, n.location.lat, dict(n.tags)))
    out = {}
    for src, items in raw.items():
        out[src] = {}
        if not items:
            continue
        x, y = frame.to_xy([i[1] for i in items], [i[2] for i in items])
        for (ident, _, _, tags), xx, yy in zip(items, np.atleast_1d(x), np.atleast_1d(y)):
            if extent[0] <= xx < extent[2] and extent[1] <= yy < extent[3]:
                out[src][ident] = (float(xx), float(yy), tags)
    return out


_cache: dict = {}


def place(name):
    if name == "monaco":
        return shared_file("osm/monaco-2022.osm.pbf"), MONACO_CENTRE
    p = get_preset(name)
    return p.osm, p.center


def world(name, ground=flat, density=1.0, seed=0, chunks=None):
    key = (name, ground.__name__, density, seed, tuple(chunks) if chunks else None)
    if key in _cache:
        return _cache[key]
    if ("base", name) not in _cache:
        path, (lat, lon) = place(name)
        frame = WorldFrame(lat, lon, 1000.0)
        feats = extract_features(path, frame)
        _cache[("base", name)] = (path, frame, feats, road_area_from_osm(path, frame), footprint_union(feats))
    path, frame, feats, road, bld = _cache[("base", name)]
    cb = [frame.chunk_bounds(i, j) for i, j in (chunks or frame.ring(1))]
    res = make_scenery(feats, ground, road, bld, cb, density=density, seed=seed)
    _cache[key] = (path, frame, feats, road, bld, cb, res)
    return _cache[key]


def totals(res):
    t = Counter()
    for c in res:
        for what, d in c.stats.items():
            for src, n in d.items():
                t[(what, src)] += n
    return t


def instances(res):
    return [i for c in res for i in c.instances]


# --- counts against the source ------------------------------------------------------------------
@pytest.mark.parametrize("name", ["helsinki", "monaco"])
def test_counts_match_the_source_minus_drops(name):
    path, frame, feats, road, bld, cb, res = world(name)
    ext = (cb[0][0], cb[0][1], cb[-1][2], cb[-1][3])
    src = source_nodes(path, frame, ext)
    t = totals(res)
    inst = instances(res)
    by_src = {s: {i["id"] for i in inst if i["kind"] == s and i["id"].startswith("node/")}
              for s in SOURCE_TAGS}
    checked = 0
    for s in SOURCE_TAGS:
        n_src = len(src[s])
        dropped = t[("dropped_building", s)] + t[("dropped_road", s)]
        assert len(by_src[s]) == t[("placed", s)], s
        assert len(by_src[s]) + dropped == n_src, s
        assert by_src[s] <= set(src[s]), s
        checked += n_src
        if s == "tree" and n_src:
            assert dropped < 0.10 * n_src                       # a few, not many
        if s in POLES and n_src:
            assert dropped <= max(2, 0.02 * n_src), s           # poles are moved, not deleted
    assert checked > 150
    # crossings are records
    assert {c["id"] for r in res for c in r.crossings} == set(src["crossing"])
    assert len(src["crossing"]) > 100


def test_helsinki_has_the_documented_amounts():
    path, frame, feats, road, bld, cb, res = world("helsinki")
    kinds = Counter(i["kind"] for i in instances(res))
    assert kinds["tree"] > 600 and kinds["street_lamp"] > 550 and kinds["traffic_signal"] > 120
    assert kinds["bench"] > 140 and kinds["give_way_sign"] > 10
    assert set(kinds) <= set(PREFAB_KINDS)


# --- placement ------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["helsinki", "monaco"])
def test_nothing_in_buildings_or_on_the_carriageway(name):
    path, frame, feats, road, bld, cb, res = world(name)
    inst = instances(res)
    x = np.array([i["x"] for i in inst])
    y = np.array([i["y"] for i in inst])
    assert not shapely.contains_xy(bld, x, y).any()
    assert not shapely.contains_xy(road, x, y).any()
    # every instance is in the chunk it was put in, standing on the ground
    for c in res:
        x0, y0, x1, y1 = c.bounds
        for i in c.instances:
            assert x0 <= i["x"] < x1 and y0 <= i["y"] < y1
            assert i["z"] == 0.0 and i["scale"] > 0 and 0 <= i["yaw"] < 2 * math.pi


@pytest.mark.parametrize("name", ["helsinki", "monaco"])
def test_tree_trunks_and_benches_stay_off_the_carriageway(name):
    """Not only the mapped point: the collider a car could hit (prefabs.json's trunk cylinder,
    the bench's box turned by its yaw) does not reach into the carriageway (a Lauf bench mapped
    at the kerb stood half a metre into a lane and stopped the car for good)."""
    from models import prefab_dir

    path, frame, feats, road, bld, cb, res = world(name)
    cols = {k: v["collision"] for k, v in json.loads((prefab_dir() / "prefabs.json").read_text())["prefabs"].items()}
    shapes = []
    for i in instances(res):
        if i["kind"] not in ("tree", "bench"):
            continue
        col, k = cols[i["kind"]], i["scale"]
        c, s = math.cos(i["yaw"]), math.sin(i["yaw"])
        ox, oy = col["offset"][0] * k, col["offset"][1] * k
        cx, cy = i["x"] + ox * c - oy * s, i["y"] + ox * s + oy * c
        if col["type"] == "box":
            hx, hy = col["half_extents"][0] * k, col["half_extents"][1] * k
            shapes.append(shapely.Polygon([(cx + a * hx * c - b * hy * s, cy + a * hx * s + b * hy * c)
                                           for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]))
        else:
            shapes.append(shapely.Point(cx, cy).buffer(col["radius"] * k, 16))
    assert len(shapes) > 300
    inside = shapely.area(shapely.intersection(np.array(shapes, dtype=object), road))
    # (the check samples a collider's rim and corners: a road's own corner may poke in between)
    assert inside.max() < 0.01, (inside.max(), int((inside > 0.01).sum()))


@pytest.mark.parametrize("name", ["helsinki", "monaco"])
def test_poles_are_moved_just_off_the_carriageway(name):
    path, frame, feats, road, bld, cb, res = world(name)
    ext = (cb[0][0], cb[0][1], cb[-1][2], cb[-1][3])
    src = source_nodes(path, frame, ext)
    edge = road.boundary
    moved = tight = 0
    for i in instances(res):
        if i["kind"] not in POLES:
            continue
        ox, oy, _ = src[i["kind"]][i["id"]]
        d = math.hypot(i["x"] - ox, i["y"] - oy)
        p0, p1 = shapely.Point(ox, oy), shapely.Point(i["x"], i["y"])
        if not road.contains(p0) and road.distance(p0) > POLE_FOOT_M + 0.01:
            assert d == pytest.approx(0.0, abs=2e-3) and "moved_m" not in i   # left where it was
            continue
        if not road.contains(p0) and road.distance(p0) > POLE_FOOT_M - 0.01:
            continue      # at the tolerance: either way
        # on the carriageway, or with its foot (POLE_FOOT_M) on it: moved
        assert road.distance(p1) >= POLE_FOOT_M - 0.05
        moved += 1
        assert i["moved_m"] == pytest.approx(d, abs=2e-3)
        assert 0.0 < road.distance(p1) <= OFF_ROAD_M + 1e-3          # just beyond the edge
        assert d <= MAX_MOVE_M
        if d <= edge.distance(p0) + OFF_ROAD_M + 2e-3:                 # the nearest such point
            tight += 1
    assert moved > 10
    # (the others were squeezed: their nearest way off left them within POLE_FOOT_M of
    # another carriageway, so they took the search around; Monaco's narrow streets: 61 of 71)
    assert tight >= 0.85 * moved
    # most signals stand within ~3 m of their carriageway's edge-side OSM position
    ds = [i["moved_m"] for i in instances(res) if i["kind"] in POLES and "moved_m" in i]
    assert np.median(ds) < 6.0


def test_sign_directions_are_kept_and_face_the_traffic():
    path, frame, feats, road, bld, cb, res = world("monaco")
    by_id = {i["id"]: i for i in instances(res)}
    checked = 0
    for ps in (feats.give_way_signs, feats.stop_signs, feats.traffic_signals):
        for ident, tags, rd in zip(ps.ids, ps.tags, ps.road_dir):
            inst = by_id.get(ident)
            if inst is None or "direction" not in tags:
                continue
            assert inst["direction"] == tags["direction"]
            if tags["direction"] == "forward" and math.isfinite(rd):
                assert inst["yaw"] == pytest.approx((rd + math.pi) % (2 * math.pi), abs=1e-3)
                checked += 1
            elif tags["direction"] == "backward" and math.isfinite(rd):
                assert inst["yaw"] == pytest.approx(rd % (2 * math.pi), abs=1e-3)
                checked += 1
    assert checked >= 5


def test_tree_rows_are_sampled_every_8_m():
    path, frame, feats, road, bld, cb, res = world("helsinki", density=1.0)
    geod = Geod(ellps="WGS84")
    wkb = osmium.geom.WKBFactory()
    rows = {}
    for w in osmium.FileProcessor(str(path)).with_locations().with_filter(osmium.filter.TagFilter(("natural", "tree_row"))):
        if w.is_way():
            try:
                rows[f"way/{w.id}"] = shapely.from_wkb(wkb.create_linestring(w))
            except (RuntimeError, osmium.InvalidLocationError):
                pass
    assert len(rows) >= 5
    placed = Counter(i["id"].split("#")[0] for i in instances(res) if "#" in i["id"] and i["id"].startswith("way/"))
    t = totals(res)
    total_expected = 0
    for ident, line in rows.items():
        L = geod.geometry_length(line)
        total_expected += int(L // 8.0) + 1
        assert placed[ident] <= int(L // 8.0) + 2
    dropped = t[("dropped_road", "tree_row")] + t[("dropped_building", "tree_row")]
    assert abs(sum(placed[i] for i in rows) + dropped - total_expected) <= len(rows)
    # neighbours along a row are 8 m apart
    pts = sorted(((int(i["id"].split("#")[1]), i["x"], i["y"]) for i in instances(res)
                  if i["id"].startswith(next(iter(rows)) + "#")))
    gaps = [math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in zip(pts, pts[1:]) if b[0] == a[0] + 1]
    assert gaps and max(gaps) <= 8.0 + 1e-3


# --- determinism, density, chunks -------------------------------------------------------------
def test_deterministic_with_a_seed():
    path, frame, feats, road, bld, cb, a = world("monaco", seed=7)
    b = make_scenery(feats, flat, road, bld, cb, seed=7)       # a second, independent run
    assert [c.instances for c in a] == [c.instances for c in b]
    c0 = world("monaco", seed=0)[-1]
    ia, i0 = instances(a), instances(c0)
    woods_a = {i["id"]: (i["x"], i["y"]) for i in ia if "_" in i["id"].split("#")[-1]}
    woods_0 = {i["id"]: (i["x"], i["y"]) for i in i0 if "_" in i["id"].split("#")[-1]}
    assert woods_a and woods_0 and woods_a != woods_0          # the seed moves wood trees
    nodes_a = {i["id"]: (i["x"], i["y"]) for i in ia if i["id"].startswith("node/")}
    nodes_0 = {i["id"]: (i["x"], i["y"]) for i in i0 if i["id"].startswith("node/")}
    assert nodes_a == nodes_0                                    # ... but not mapped ones


def test_woods_density_and_independence_of_the_chunk_set():
    full = world("kouvola", density=1.0)
    half = world("kouvola", density=0.5)
    feats = full[2]
    wood_area = sum(w.geometry.intersection(shapely.box(full[5][0][0], full[5][0][1], full[5][-1][2], full[5][-1][3])).area
                    for w in feats.woods)
    n1 = sum(1 for i in instances(full[-1]) if i["kind"] == "tree")
    n05 = sum(1 for i in instances(half[-1]) if i["kind"] == "tree")
    assert wood_area > 10000
    assert 0.7 * wood_area / 150.0 <= n1 <= 1.1 * wood_area / 150.0     # one per ~150 m2
    assert 0.4 <= n05 / n1 <= 0.6
    # the same trees when a chunk is built alone
    frame = full[1]
    by_chunk = {i["id"]: i for i in instances(full[-1])}
    for ij in [(0, 0), (1, 0), (0, 1)]:
        alone = make_scenery(feats, flat, full[3], full[4], [frame.chunk_bounds(*ij)], density=1.0)
        for i in alone[0].instances:
            assert by_chunk[i["id"]] == i


def test_chunk_sets_with_gaps_give_the_union_of_single_chunks():
    path, frame, feats, road, bld, cb, res = world("helsinki", chunks=[(0, 0), (1, 1)])
    assert len(res) == 2
    singles = [make_scenery(feats, flat, road, bld, [frame.chunk_bounds(*ij)])[0] for ij in [(0, 0), (1, 1)]]
    for together, alone in zip(res, singles):
        assert together.instances == alone.instances
        assert together.stats == alone.stats
    assert sum(len(c.instances) for c in res) > 500


# --- areas and files ----------------------------------------------------------------------------
def test_area_layers_are_draped_and_written(tmp_path):
    path, frame, feats, road, bld, cb, res = world("helsinki", ground=bumpy)
    n_areas = 0
    for k, c in enumerate(res):
        if not c.area_records:
            continue
        for rec in c.area_records:
            m = c.areas.geometry[rec["node"]]
            off = AREA_STYLE[rec["kind"]][1]
            assert np.allclose(m.vertices[:, 2] - bumpy(m.vertices[:, 0], m.vertices[:, 1]), off, atol=1e-9)
            assert (m.face_normals[:, 2] > 0).all()
            flat2d = m.area_faces * np.abs(m.face_normals[:, 2])     # projected on x/y
            assert flat2d.sum() == pytest.approx(rec["area_m2"], rel=0.01, abs=0.5)
            x0, y0, x1, y1 = c.bounds
            assert (m.vertices[:, 0] >= x0 - 1e-6).all() and (m.vertices[:, 0] <= x1 + 1e-6).all()
            n_areas += 1
        out = tmp_path / f"c{k}"
        files = write_chunk_scenery(c, out)
        assert files == {"json": "scenery.json", "glb": "areas.glb", "obj": "areas.obj"}
        scene = trimesh.load(out / "areas.glb", force="scene")
        assert set(scene.graph.nodes_geometry) == {r["node"] for r in c.area_records}
        data = json.loads((out / "scenery.json").read_text())
        assert data["instances"] == c.instances and data["crossings"] == c.crossings
        merged = trimesh.load(out / "areas.obj", force="mesh", process=False)
        assert len(merged.faces) == sum(len(g.faces) for g in c.areas.geometry.values())
    kinds = Counter(r["kind"] for c in res for r in c.area_records)
    assert n_areas > 50 and kinds["grass"] > 50 and kinds["water"] >= 1
    # grass is cut off the carriageway; water is not
    for c in res:
        for rec in c.area_records:
            if rec["kind"] == "grass":
                m = c.areas.geometry[rec["node"]]
                cen = m.triangles_center
                assert not shapely.contains_xy(road, cen[:, 0], cen[:, 1]).any()


# --- prefabs ------------------------------------------------------------------------------------
def test_prefabs_are_light_grounded_and_in_sync_with_their_generator(tmp_path):
    d = REPO / "models" / "prefabs"
    index = json.loads((d / "prefabs.json").read_text())
    assert set(index["prefabs"]) == set(PREFAB_KINDS)
    for kind, p in index["prefabs"].items():
        m = trimesh.load(d / p["file"], force="mesh")
        assert len(m.faces) == p["faces"] < 500
        lo, hi = m.bounds
        assert lo[2] == pytest.approx(0.0, abs=1e-4)                 # stands on its base
        assert abs(lo[0] + hi[0]) < 2.0 and abs(lo[1] + hi[1]) < 0.2    # about the origin
        assert (d / p["mtl"]).exists()
        col = p["collision"]
        assert col["type"] in ("cylinder", "box")
    assert 7.0 <= index["prefabs"]["tree"]["size_m"][2] <= 9.0
    assert 7.0 <= index["prefabs"]["street_lamp"]["size_m"][2] <= 9.0
    sys.path.insert(0, str(d))
    try:
        import make_prefabs
    finally:
        sys.path.remove(str(d))
    fresh = make_prefabs.build(tmp_path)
    assert fresh == index
    for p in index["prefabs"].values():
        assert (tmp_path / p["file"]).read_text() == (d / p["file"]).read_text()
