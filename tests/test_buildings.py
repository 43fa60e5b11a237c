"""Buildings from real OSM extracts: footprints, heights, courtyards, terrain, chunks, files.

The reference values are computed independently of netgen: geodesic areas with
pyproj.Geod on lon/lat polygons that pyosmium assembles here, tags read here with pyosmium.
"""
from __future__ import annotations

import json
import math

import numpy as np
import osmium
import pytest
import shapely
import trimesh
from pyproj import Geod
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.polygon import orient

from netgen.buildings import (LEVEL_HEIGHT_M, building_height, default_height, make_buildings,
                              parse_length, write_chunk_buildings)
from netgen.frame import WorldFrame
from netgen.osm_features import extract_features
from netgen.presets import get_preset

from conftest import shared_file

MONACO_CENTRE = (43.7385, 7.4244)   # middle of the built-up core of the Monaco extract


def tilted(x, y):
    return 0.1 * np.asarray(x)


def bumpy(x, y):
    """A deterministic hilly ground: a few metres of relief over tens of metres."""
    x, y = np.asarray(x, float), np.asarray(y, float)
    return (4.0 * np.sin(x / 17.0) * np.cos(y / 23.0) + 2.5 * np.sin((x + 2 * y) / 41.0)
            + 0.03 * x - 0.02 * y + 1.5 * np.cos(x / 7.3 + 0.4) * np.sin(y / 9.1))


def _place(name):
    if name == "monaco":
        return shared_file("osm/monaco-2022.osm.pbf"), MONACO_CENTRE
    p = get_preset(name)
    return p.osm, p.center


_cache: dict = {}


def world(name, ground=tilted, chunk=1000.0, rings=1):
    key = (name, ground.__name__, chunk, rings)
    if key not in _cache:
        path, (lat, lon) = _place(name)
        frame = WorldFrame(lat, lon, chunk)
        feats = _cache.get(("feats", name, chunk)) or extract_features(path, frame)
        _cache[("feats", name, chunk)] = feats
        chunks = [frame.chunk_bounds(i, j) for i, j in frame.ring(rings)]
        res = make_buildings(feats, ground, chunks)
        _cache[key] = (path, frame, feats, chunks, res)
    return _cache[key]


def all_records(res):
    return {r["id"]: (c, r) for c in res for r in c.records}


def reference_buildings(path):
    """{osm id: (lon/lat (Multi)Polygon, tags)} for every building area pyosmium assembles."""
    wkb = osmium.geom.WKBFactory()
    out = {}
    for a in osmium.FileProcessor(str(path)).with_areas().with_filter(osmium.filter.KeyFilter("building")):
        if not a.is_area() or a.tags.get("building") in (None, "no"):
            continue
        ident = ("way/" if a.from_way() else "relation/") + str(a.orig_id())
        out[ident] = (shapely.from_wkb(wkb.create_multipolygon(a)), dict(a.tags))
    return out


def geodesic_area(geom) -> float:
    g = Geod(ellps="WGS84")
    total = 0.0
    for p in shapely.get_parts(geom):
        total += g.geometry_area_perimeter(orient(p, 1.0))[0]
    return total


# --- heights ----------------------------------------------------------------------------------
@pytest.mark.parametrize("text,metres", [
    ("12", 12.0), ("12 m", 12.0), ("12.5m", 12.5), ("12,5", 12.5), ("40'", 40 * 0.3048),
    ("40 ft", 40 * 0.3048), ("40'6\"", 40 * 0.3048 + 6 * 0.0254), ("12;15", 12.0),
    ("tall;15", 15.0), (" 7 metres", 7.0), ("abc", None), ("", None), (None, None),
])
def test_parse_length(text, metres):
    got = parse_length(text)
    if metres is None:
        assert got is None
    else:
        assert got == pytest.approx(metres, abs=1e-9)


def test_building_height_sources_and_defaults():
    assert building_height({"building": "yes", "height": "21.5"}) == (21.5, "height")
    assert building_height({"building": "yes", "height": "60 ft"})[0] == pytest.approx(18.288)
    # an unusable height falls back to the levels, then to the default
    assert building_height({"building": "yes", "height": "-3", "building:levels": "4"}) == (12.0, "building:levels")
    assert building_height({"building": "yes", "height": "n/a", "building:levels": "2",
                            "roof:levels": "1"}) == (3 * LEVEL_HEIGHT_M, "building:levels")
    assert building_height({"building": "yes", "building:levels": "5", "roof:height": "2.5"}) == (17.5, "building:levels")
    h, src = building_height({"building": "apartments"})
    assert src == "default" and 12.0 <= h <= 18.0          # 4-6 storeys, not a 3 m shed
    assert building_height({"building": "shed"}) == (3.0, "default")
    assert building_height({"building": "house"})[0] < building_height({"building": "office"})[0]
    # unspecified type: the footprint decides between outbuilding, house and block
    small = building_height({"building": "yes"}, 20.0)[0]
    house = building_height({"building": "yes"}, 150.0)[0]
    block = building_height({"building": "yes"}, 900.0)[0]
    assert small < house < block and small <= 4.0 and block >= 9.0
    assert default_height("yes") == block


# --- footprints -------------------------------------------------------------------------------
def test_helsinki_footprints_match_geodesic_areas():
    path, frame, feats, chunks, res = world("helsinki")
    recs = all_records(res)
    ref = reference_buildings(path)
    assert len(ref) > 400
    compared = 0
    for ident, (ll, tags) in ref.items():
        if ident not in recs:
            continue
        chunk, rec = recs[ident]
        fp = chunk.footprints[ident]
        expected = geodesic_area(ll)
        assert fp.area == pytest.approx(expected, rel=0.01), ident
        assert rec["footprint_area_m2"] == pytest.approx(expected, rel=0.01), ident
        compared += 1
    # every assembled building is there, except a way that duplicates a relation's outline
    missing = set(ref) - set(recs)
    assert len(missing) == feats.stats["building_ways_duplicating_relations"]
    assert all(m.startswith("way/") for m in missing)
    assert compared == len(ref) - len(missing)
    # node buildings are placeholders, door nodes (building=entrance) are not buildings
    placeholders = [r for _, r in recs.values() if r["placeholder"]]
    assert len(placeholders) == len(feats.building_nodes) > 0
    assert all(r["id"].startswith("node/") and r["footprint_area_m2"] >= 9 for r in placeholders)


def test_every_mesh_is_a_closed_solid_of_the_footprint():
    for name in ("helsinki", "kouvola"):
        _, _, feats, _, res = world(name)
        n = 0
        for c in res:
            for rec in c.records:
                m = c.scene.geometry[rec["id"]]
                assert m.is_watertight and m.is_winding_consistent, rec["id"]
                fp = c.footprints[rec["id"]]
                assert m.volume == pytest.approx(fp.area * (rec["height_m"] - rec["min_height_m"]), rel=1e-6)
                n += 1
        assert n == len(feats.buildings) + len(feats.building_nodes)


def _numeric(v):
    try:
        x = float(v)
    except (TypeError, ValueError):
        return None
    return x if math.isfinite(x) and x > 0 else None


@pytest.mark.parametrize("name", ["helsinki", "monaco"])
def test_heights_from_tags_are_exact(name):
    path, frame, feats, chunks, res = world(name)
    recs = all_records(res)
    tags = {f.id: f.tags for f in feats.buildings}
    n_height = n_levels = 0
    for ident, (c, rec) in recs.items():
        t = tags.get(ident)
        if t is None:
            continue
        zmin, zmax = c.scene.geometry[ident].bounds[:, 2]
        h = _numeric(t.get("height"))
        if h is not None:
            assert rec["height_source"] == "height"
            assert zmax - rec["base_z"] == pytest.approx(h, abs=1e-6), ident
            n_height += 1
            if "min_height" not in t and "building:min_level" not in t and t.get("building") != "roof":
                assert zmax - zmin == pytest.approx(h, abs=1e-6), ident
        elif "height" not in t and _numeric(t.get("building:levels")) is not None:
            lv = float(t["building:levels"])
            roof = _numeric(t.get("roof:height"))
            roof = roof if roof is not None else (_numeric(t.get("roof:levels")) or 0.0) * 3.0
            assert rec["height_source"] == "building:levels"
            assert zmax - rec["base_z"] == pytest.approx(3.0 * lv + roof, abs=1e-6), ident
            n_levels += 1
    assert n_height >= 10 and n_levels >= 100


def test_min_height_lifts_the_underside():
    """building:min_level / min_height (Helsinki has parts bridging over streets)."""
    _, _, feats, _, res = world("helsinki")
    tags = {f.id: f.tags for f in feats.buildings}
    tags.update(zip(feats.building_nodes.ids, feats.building_nodes.tags))
    lifted = 0
    for c in res:
        for rec in c.records:
            t = tags.get(rec["id"], {})
            if rec["min_height_m"] > 0:
                zmin = c.scene.geometry[rec["id"]].bounds[0, 2]
                assert zmin == pytest.approx(rec["base_z"] + rec["min_height_m"])
                assert "min_height" in t or "building:min_level" in t or t.get("building") == "roof"
                lifted += 1
    assert lifted >= 1


@pytest.mark.parametrize("name", ["helsinki", "monaco"])
def test_courtyards_are_holes(name):
    _, frame, feats, chunks, res = world(name)
    found = 0
    for c in res:
        for rec in c.records:
            if not rec["id"].startswith("relation/"):
                continue
            fp = c.footprints[rec["id"]]
            polys = [p for p in shapely.get_parts(fp) if p.interiors]
            if not polys:
                continue
            mesh = c.scene.geometry[rec["id"]]
            outer_only = sum(Polygon(p.exterior).area for p in shapely.get_parts(fp))
            assert fp.area < outer_only
            h = rec["height_m"] - rec["min_height_m"]
            assert mesh.volume == pytest.approx(fp.area * h, rel=1e-6)
            assert mesh.volume < outer_only * h - 1.0
            zmid = rec["base_z"] + rec["min_height_m"] + h / 2
            hole = Polygon(polys[0].interiors[0])
            court = hole.representative_point()
            wall = polys[0].representative_point()
            assert not fp.contains(court)
            inside = mesh.contains([[court.x, court.y, zmid], [wall.x, wall.y, zmid]])
            assert not inside[0] and inside[1], rec["id"]
            found += 1
    assert found >= 1


# --- terrain ---------------------------------------------------------------------------------
def test_base_follows_a_tilted_plane_exactly():
    _, _, _, _, res = world("kouvola", tilted)
    for c in res:
        for rec in c.records:
            fp = c.footprints[rec["id"]]
            # the lowest point of 0.1 x over a polygon is at its westernmost vertex
            assert rec["base_z"] == pytest.approx(0.1 * fp.bounds[0] - 0.1, abs=1e-9)


@pytest.mark.parametrize("name", ["helsinki", "kouvola"])
def test_no_base_above_terrain_on_bumpy_ground(name):
    _, _, feats, _, res = world(name, bumpy)
    worst_float, worst_sink = -np.inf, 0.0
    for c in res:
        for rec in c.records:
            fp = c.footprints[rec["id"]]
            x0, y0, x1, y1 = fp.bounds
            gx, gy = np.meshgrid(np.arange(x0, x1 + 0.5, 0.5), np.arange(y0, y1 + 0.5, 0.5))
            gx, gy = gx.ravel(), gy.ravel()
            m = shapely.contains_xy(fp, gx, gy)
            edge = shapely.get_coordinates(shapely.segmentize(fp.boundary, 0.25))
            xs = np.concatenate([gx[m], edge[:, 0]])
            ys = np.concatenate([gy[m], edge[:, 1]])
            lowest = bumpy(xs, ys).min()
            worst_float = max(worst_float, rec["base_z"] - lowest)
            worst_sink = max(worst_sink, lowest - rec["base_z"])
            zmin = c.scene.geometry[rec["id"]].bounds[0, 2]
            assert zmin == pytest.approx(rec["base_z"] + rec["min_height_m"], abs=1e-9)
    assert worst_float < 0.0            # the base is below the ground everywhere
    assert worst_sink < 0.1 + 0.1       # ... but not buried (sink 0.1 m + sampling)


# --- chunks and files -------------------------------------------------------------------------
def test_each_building_in_exactly_one_chunk_and_files(tmp_path):
    path, frame, feats, chunks, res = world("helsinki", tilted, chunk=400.0, rings=3)
    seen: dict = {}
    nonempty = 0
    for k, c in enumerate(res):
        x0, y0, x1, y1 = c.bounds
        for rec in c.records:
            assert rec["id"] not in seen, f"{rec['id']} in chunks {seen[rec['id']]} and {k}"
            seen[rec["id"]] = k
            p = c.footprints[rec["id"]].representative_point()
            assert x0 <= p.x < x1 and y0 <= p.y < y1
        if c.records:
            nonempty += 1
            out = tmp_path / f"chunk_{k}"
            files = write_chunk_buildings(c, out)
            assert files == {"glb": "buildings.glb", "obj": "buildings.obj", "json": "buildings.json"}
            scene = trimesh.load(out / files["glb"], force="scene")
            names = set(scene.graph.nodes_geometry)
            assert names == {r["id"] for r in c.records}
            merged = trimesh.load(out / files["obj"], force="mesh", process=False)
            assert len(merged.faces) == len(c.mesh.faces)
            assert merged.bounds == pytest.approx(c.mesh.bounds, abs=1e-3)
            data = json.loads((out / files["json"]).read_text())
            assert [r["id"] for r in data["buildings"]] == [r["id"] for r in c.records]
            assert set(data["buildings"][0]) >= {"id", "kind", "height_m", "height_source", "base_z",
                                                 "footprint_area_m2", "centroid", "levels"}
    assert nonempty >= 4
    assert len(seen) == len(feats.buildings) + len(feats.building_nodes)
    assert res[0].stats["outside_chunks"] == 0
    # a straddling building is in one chunk only, and whole
    cut = [c.footprints[i] for c in res for i in c.footprints
           if not shapely.box(*c.bounds).contains(c.footprints[i])]
    assert cut, "expected buildings across chunk borders at 400 m chunks"


def test_empty_chunk_writes_only_records(tmp_path):
    path, frame, feats, chunks, res = world("kouvola")
    far = make_buildings(feats, tilted, [frame.chunk_bounds(20, 20)])
    assert far[0].records == [] and far[0].mesh is None
    files = write_chunk_buildings(far[0], tmp_path)
    assert files["glb"] is None and files["obj"] is None
    assert json.loads((tmp_path / "buildings.json").read_text())["buildings"] == []


OSM_XML = """<?xml version='1.0' encoding='UTF-8'?>
<osm version="0.6" generator="hand">
 <node id="1" lat="60.170000" lon="24.940000"/>
 <node id="2" lat="60.170300" lon="24.940600"/>
 <node id="3" lat="60.170300" lon="24.940000"/>
 <node id="4" lat="60.170000" lon="24.940600"/>
 <node id="11" lat="60.171000" lon="24.941000"/>
 <node id="12" lat="60.171000" lon="24.941020"/>
 <node id="13" lat="60.171010" lon="24.941020"/>
 <node id="14" lat="60.171010" lon="24.941000"/>
 <node id="21" lat="60.169000" lon="24.939000"><tag k="building" v="house"/></node>
 <node id="22" lat="60.169100" lon="24.939000"><tag k="building" v="entrance"/></node>
 <way id="100"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="4"/><nd ref="1"/>
  <tag k="building" v="yes"/><tag k="building:levels" v="2"/></way>
 <way id="101"><nd ref="11"/><nd ref="12"/><nd ref="13"/><nd ref="14"/><nd ref="11"/>
  <tag k="building" v="shed"/></way>
</osm>
"""


def test_invalid_and_tiny_footprints_from_a_real_osm_file(tmp_path):
    """A self-intersecting (bow-tie) outline is repaired, a 1 m2 sliver dropped and counted."""
    f = tmp_path / "bad.osm"
    f.write_text(OSM_XML)
    frame = WorldFrame(60.17, 24.94)
    feats = extract_features(f, frame)
    assert feats.stats["building_ways_from_ring"] >= 1      # libosmium rejected the bow-tie
    res = make_buildings(feats, tilted, [frame.chunk_bounds(0, 0)])
    recs = {r["id"]: r for r in res[0].records}
    assert "way/100" in recs and "way/101" not in recs and "node/21" in recs and "node/22" not in recs
    assert res[0].stats["slivers_dropped"] == 1 and res[0].stats["repaired"] >= 1
    fp = res[0].footprints["way/100"]
    assert isinstance(fp, MultiPolygon) and fp.is_valid and len(fp.geoms) == 2
    mesh = res[0].scene.geometry["way/100"]
    assert mesh.is_watertight and mesh.volume == pytest.approx(fp.area * 6.0, rel=1e-6)
    # the bow-tie's two triangles: about half of its 33 x 33 m bounding box
    assert fp.area == pytest.approx(0.5 * fp.envelope.area, rel=0.02)
    assert recs["node/21"]["placeholder"] and recs["node/21"]["footprint_area_m2"] == pytest.approx(64.0)


def test_compressed_osm_xml_reads_the_same(tmp_path):
    import bz2
    import gzip
    plain = tmp_path / "a.osm"
    plain.write_text(OSM_XML)
    (tmp_path / "a.osm.gz").write_bytes(gzip.compress(OSM_XML.encode()))
    (tmp_path / "a.osm.bz2").write_bytes(bz2.compress(OSM_XML.encode()))
    frame = WorldFrame(60.17, 24.94)
    ref = extract_features(plain, frame)
    for name in ("a.osm.gz", "a.osm.bz2"):
        f = extract_features(tmp_path / name, frame)
        assert [b.id for b in f.buildings] == [b.id for b in ref.buildings]
        assert all(a.geometry.equals(b.geometry) for a, b in zip(f.buildings, ref.buildings))
        assert f.building_nodes.ids == ref.building_nodes.ids == ["node/21"]


def test_bbox_limits_the_features():
    path, frame, feats, chunks, res = world("helsinki")
    bbox = frame.bbox_lonlat((-150.0, -150.0, 150.0, 150.0))
    small = extract_features(path, frame, bbox)
    s, w, n, e = bbox
    area = shapely.box(*frame.extent([(0, 0)]))
    assert 0 < len(small.buildings) < len(feats.buildings)
    assert 0 < len(small.trees) < len(feats.trees)
    # points inside the bbox only; every area touches it; none that touches it is missing
    lon, lat = frame.to_lonlat(small.trees.xy[:, 0], small.trees.xy[:, 1])
    assert ((lon >= w - 1e-9) & (lon <= e + 1e-9) & (lat >= s - 1e-9) & (lat <= n + 1e-9)).all()
    bb = shapely.box(-150.0, -150.0, 150.0, 150.0)
    assert {b.id for b in small.buildings} >= {b.id for b in feats.buildings if b.geometry.intersects(bb)}
    assert area.contains(bb)


def test_unreadable_osm_files_are_data_errors(tmp_path):
    from netgen.errors import DataError
    frame = WorldFrame(60.17, 24.94)
    bad = tmp_path / "bad.osm.pbf"
    bad.write_bytes(b"this is not a protobuf file")
    with pytest.raises(DataError):
        extract_features(bad, frame)
    with pytest.raises(DataError):
        extract_features(tmp_path / "missing.osm", frame)


def test_underground_buildings_are_not_built():
    """Buildings below the ground (a negative layer, location=underground) are left out:
    Monaco's underground railway station (way 156780354, building=railway, layer=-2, 150 m
    long under the streets of the Sainte-Dévote ravine) was extruded 12 m up from the lowest
    ground under it, across the streets above, and the car drove onto its roof."""
    from netgen.buildings import underground

    assert underground({"building": "yes", "layer": "-1"})
    assert underground({"building": "parking", "location": "underground"})
    assert not underground({"building": "yes", "layer": "1"})
    assert not underground({"building": "yes", "layer": "garbage"})
    assert not underground({"building": "yes"})
    path, frame, feats, chunks, res = world("monaco")
    tagged = {b.id for b in feats.buildings if underground(b.tags)}
    assert "way/156780354" in tagged                      # it is in the data
    built = all_records(res)
    assert not tagged & set(built) and len(built) > 1000
    assert res[0].stats["underground"] >= len(tagged) >= 1            # counted in the report


# --- buildings over the roads -------------------------------------------------------------------
def test_the_part_over_a_road_becomes_a_passage():
    """A road strip laid across real footprints: each building's part over it (grown by the
    margin) starts at the clearance, or goes where too little would be left above; the rest
    still stands on the ground; every other building is untouched; solids stay closed."""
    from netgen.buildings import (PASSAGE_CLEARANCE_M, PASSAGE_MARGIN_M, cut_passages, place_buildings,
                                  plan_buildings)

    path, frame, feats, chunks, _ = world("helsinki")
    ref = plan_buildings(feats, chunks)
    plan = plan_buildings(feats, chunks)
    # a 6 m wide straight road through the middle of the largest footprint
    big = int(np.argmax([g.area for g in plan.footprints]))
    c = plan.footprints[big].centroid
    road = shapely.LineString([(c.x - 400, c.y), (c.x + 400, c.y)]).buffer(3.0, cap_style="flat")
    cut = cut_passages(plan, [road])
    crossed = [i for i, g in enumerate(plan.footprints)
               if shapely.intersection(g, road.buffer(PASSAGE_MARGIN_M)).area >= 0.1 and not ref.failed[i]]
    assert big in cut and set(cut.tolist()) <= set(crossed) and len(cut) >= 3
    grown = road.buffer(PASSAGE_MARGIN_M)
    res = place_buildings(plan, lambda x, y: np.zeros(np.shape(x)))
    recs = {r["id"]: (ch, r) for ch in res for r in ch.records}
    lifted = dropped = 0
    for i in cut.tolist():
        ch, rec = recs[plan.ids[i]]
        m = ch.scene.geometry[rec["id"]]
        assert m.is_watertight and m.is_winding_consistent, rec["id"]
        fp = plan.footprints[i]
        over, rest = fp.intersection(grown), fp.difference(grown)
        top = rec["passage_from_m"]
        if top is None:                         # too low to keep a part above the road
            assert rec["height_m"] - max(rec["min_height_m"], PASSAGE_CLEARANCE_M) < 1.0
            assert m.volume == pytest.approx(rest.area * (rec["height_m"] - rec["min_height_m"]), rel=1e-3)
            dropped += 1
        else:
            assert top == pytest.approx(max(rec["min_height_m"], PASSAGE_CLEARANCE_M))
            assert m.volume == pytest.approx(rest.area * (rec["height_m"] - rec["min_height_m"])
                                             + over.area * (rec["height_m"] - top), rel=1e-3)
            lifted += 1
        # nothing of it lower than the passage's underside stands on the road
        tri = m.triangles_center
        on_road = shapely.contains_xy(road.buffer(-0.01), tri[:, 0], tri[:, 1])
        assert (tri[on_road, 2] >= rec["base_z"] + PASSAGE_CLEARANCE_M - 1e-6).all()
        assert rec["footprint_area_m2"] == pytest.approx(fp.area, abs=0.01)   # the whole footprint
    assert lifted >= 1
    # the others: the same solids as without the road
    for i in range(len(plan.ids)):
        if i in set(cut.tolist()):
            continue
        a = ref.vertices[ref.vstart[i]:ref.vstart[i + 1]]
        b = plan.vertices[plan.vstart[i]:plan.vstart[i + 1]]
        assert np.array_equal(a, b)
        fa = ref.faces[ref.fstart[i]:ref.fstart[i + 1]] - ref.vstart[i]
        fb = plan.faces[plan.fstart[i]:plan.fstart[i + 1]] - plan.vstart[i]
        assert np.array_equal(fa, fb)
    assert "passage_from_m" not in ref.records[big]


def test_passage_clearance_is_over_the_ground_under_it():
    """On a slope the passage's underside is the clearance above the highest ground under the
    part over the road, not above the building's base (its lowest ground)."""
    from netgen.buildings import PASSAGE_CLEARANCE_M, cut_passages, plan_buildings

    _, _, feats, chunks, _ = world("helsinki")
    plan = plan_buildings(feats, chunks)
    big = int(np.argmax([g.area for g in plan.footprints]))
    fp = plan.footprints[big]
    c = fp.centroid
    road = shapely.LineString([(c.x, c.y - 400), (c.x, c.y + 400)]).buffer(2.0, cap_style="flat")
    cut_passages(plan, [road], ground=tilted)           # 10 % up to the east
    rec = plan.records[big]
    over = fp.intersection(road.buffer(0.2))
    rise = 0.1 * shapely.get_coordinates(over)[:, 0].max() - 0.1 * shapely.get_coordinates(fp)[:, 0].min()
    assert rise > 1.0
    if rec["height_m"] - (PASSAGE_CLEARANCE_M + rise) >= 1.0:
        assert rec["passage_from_m"] == pytest.approx(PASSAGE_CLEARANCE_M + rise, abs=0.05)
    else:
        assert rec["passage_from_m"] is None
