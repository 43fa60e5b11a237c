"""End-to-end world builds on real data: the world.json contract, the network against OSM,
terrain against the DEM, buildings on the terrain, caching, bad input and killed builds."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import osmium
import pytest
from pyproj import Geod, Transformer

from netgen.build import build_world, load_world_json
from netgen.config import WorldConfig
from netgen.roadnet import read_net
from tests.conftest import REPO, shared_file

GEOD = Geod(ellps="WGS84")
CLI = [sys.executable, "-m", "cosim"]
DRIVABLE = {"motorway", "trunk", "primary", "secondary", "tertiary", "unclassified", "residential",
            "motorway_link", "trunk_link", "primary_link", "secondary_link", "tertiary_link", "living_street"}


@pytest.fixture(scope="session")
def helsinki(tmp_path_factory):
    out = tmp_path_factory.mktemp("worlds") / "helsinki"
    cache = tmp_path_factory.mktemp("cache")
    w = build_world(WorldConfig(preset="helsinki", chunks=1, out=str(out), cache_dir=str(cache)))
    return out, w, cache


def _ways(pbf, with_geom=True):
    """OSM highway ways of a file: id -> (highway, [(lon, lat)])."""
    ways = {}
    for o in osmium.FileProcessor(str(pbf)).with_locations().with_filter(osmium.filter.KeyFilter("highway")):
        if o.is_way():
            pts = [(n.lon, n.lat) for n in o.nodes if n.location.valid()]
            ways[o.id] = (o.tags["highway"], pts, o.tags.get("area") == "yes")
    return ways


# ---------------------------------------------------------------------------------------
def test_world_json_contract(helsinki):
    out, w, _ = helsinki
    on_disk = json.loads((out / "world.json").read_text())
    for key in ("center", "chunk_size_m", "chunks", "projection", "net_file", "terrain", "counts",
                "sources", "timings_s"):
        assert key in on_disk, key
    assert set(on_disk["center"]) == {"lat", "lon"}
    assert len(on_disk["chunks"]) == 9
    for c in on_disk["chunks"]:
        assert {"i", "j", "bounds_m", "files"} <= set(c)
        xmin, ymin, xmax, ymax = c["bounds_m"]
        assert xmax - xmin == pytest.approx(1000.0) and ymax - ymin == pytest.approx(1000.0)
        assert (out / c["files"]["terrain"]).exists()
    assert {"road_edges", "junctions", "traffic_lights", "buildings", "buildings_height_from_tags",
            "trees", "street_lamps"} <= set(on_disk["counts"])
    assert on_disk["counts"]["road_edges"] > 500 and on_disk["counts"]["traffic_lights"] > 50
    assert on_disk["counts"]["buildings"] > 300
    assert on_disk["sources"]["osm"]["licence"] == "ODbL 1.0"
    assert on_disk["terrain"]["spacing_m"] <= 10.0
    assert (out / on_disk["net_file"]).exists()


def test_projection_maps_osm_nodes_onto_sumo_junctions(helsinki):
    """world.json's proj string alone (PROJ, no project code) maps an OSM node's lat/lon onto
    the SUMO junction built from it, to the centimetre."""
    out, w, _ = helsinki
    tr = Transformer.from_crs("EPSG:4326", w["projection"]["proj"], always_xy=True)
    net = read_net(out / w["net_file"])
    assert net.location["projParameter"].split() == w["projection"]["proj"].split()
    nodes = {}
    for o in osmium.FileProcessor(str(REPO / "netgen/presets/helsinki-2019.osm.pbf"), osmium.osm.NODE):
        nodes[str(o.id)] = (o.lon, o.lat)
    checked = 0
    for jid, j in net.junctions.items():
        if jid in nodes and j.type in ("priority", "right_before_left", "dead_end"):
            x, y = tr.transform(*nodes[jid])
            ox, oy = w["projection"]["net_offset"]
            assert abs(x + ox - j.x) < 0.01 and abs(y + oy - j.y) < 0.01, jid
            checked += 1
    assert checked > 200


def test_road_lengths_match_geodesic_osm_lengths(helsinki):
    """An OSM way that became edges with no other way merged in: the edges' full geometry
    (junction centre to junction centre) is as long as the way's geodesic length, within 1 %."""
    out, w, _ = helsinki
    net = read_net(out / w["net_file"])
    ways = _ways(REPO / "netgen/presets/helsinki-2019.osm.pbf")
    by_way: dict = {}
    for e in net.normal_edges():
        if e.id.startswith("-") or len(e.orig_ids) != 1 or e.from_node.startswith("cluster") \
                or e.to_node.startswith("cluster"):
            continue
        by_way.setdefault(int(e.orig_ids[0]), []).append(e)
    checked, bad = 0, []
    for wid, edges in by_way.items():
        if wid not in ways:
            continue
        hw, pts, _ = ways[wid]
        if len(pts) < 2:
            continue
        lon, lat = np.array(pts).T
        geo_len = GEOD.line_length(lon, lat)
        if geo_len < 50:
            continue
        # the way's edges must cover it whole: their from/to nodes are the way's end nodes
        net_len = 0.0
        for e in edges:
            shape = e.raw_shape if e.raw_shape is not None else None
            if shape is None:
                fj, tj = net.junctions[e.from_node], net.junctions[e.to_node]
                lane = e.lanes[0].shape
                shape = np.vstack([[fj.x, fj.y], lane, [tj.x, tj.y]])
            net_len += float(np.sum(np.hypot(*np.diff(shape, axis=0).T)))
        ratio = net_len / geo_len
        if 0.5 < ratio < 1.5:      # ways only partly built (cut at the area edge) are skipped
            checked += 1
            if abs(ratio - 1.0) > 0.01:
                bad.append((wid, round(geo_len, 1), round(net_len, 1)))
    assert checked >= 100, checked
    assert not bad, f"{len(bad)} of {checked} ways off by more than 1 %: {bad[:5]}"


def test_every_drivable_osm_way_is_in_the_network(helsinki):
    out, w, _ = helsinki
    net = read_net(out / w["net_file"])
    represented = set()
    for e in net.normal_edges():
        represented.update(int(x) for x in e.orig_ids)
    ways = _ways(REPO / "netgen/presets/helsinki-2019.osm.pbf")
    drivable = {wid for wid, (hw, pts, area) in ways.items() if hw in DRIVABLE and not area and len(pts) >= 2}
    missing = sorted(drivable - represented)
    assert len(drivable) > 500
    # every drivable way shows up in some edge's origId (geometry.remove may merge it into a
    # neighbour's edge, whose origId then lists both)
    assert not missing, f"{len(missing)} of {len(drivable)} drivable ways missing, e.g. {missing[:10]}"


def test_chunk_terrain_is_seamless_and_levelled_under_roads(helsinki):
    out, w, _ = helsinki
    chunks = {(c["i"], c["j"]): np.load(out / c["files"]["terrain"]) for c in w["chunks"]}
    sp = w["terrain"]["spacing_m"]
    n = int(round(w["chunk_size_m"] / sp)) + 1
    for (i, j), z in chunks.items():
        assert z.shape == (n, n)
        if (i + 1, j) in chunks:
            assert np.array_equal(z[:, -1], chunks[(i + 1, j)][:, 0])
        if (i, j + 1) in chunks:
            assert np.array_equal(z[-1, :], chunks[(i, j + 1)][0, :])


def test_rebuild_reuses_the_world(helsinki):
    out, w, cache = helsinki
    t0 = time.perf_counter()
    again = build_world(WorldConfig(preset="helsinki", chunks=1, out=str(out), cache_dir=str(cache)))
    assert again.get("reused") is True
    assert again["build_key"] == w["build_key"]


# ---------------------------------------------------------------------------------------
def _dem_world(tmp_path, osm, dem, center, spacing=10.0):
    return build_world(WorldConfig(osm=str(osm), dem=[str(dem)], center=center, chunks=0,
                                   terrain_spacing_m=spacing, out=str(tmp_path / "w"),
                                   cache_dir=str(tmp_path / "cache")))


def _check_terrain_against_dem(out: Path, w: dict, dem_path: Path, rng, n=400):
    from netgen.dem import open_dem
    from netgen.frame import WorldFrame

    dem = open_dem([str(dem_path)])
    frame = WorldFrame(w["center"]["lat"], w["center"]["lon"], w["chunk_size_m"])
    lev = 0
    checked = 0
    for c in w["chunks"]:
        z = np.load(out / c["files"]["terrain"]).astype(float)
        xmin, ymin = c["bounds_m"][:2]
        sp = w["terrain"]["spacing_m"]
        rows = rng.integers(0, z.shape[0], n)
        cols = rng.integers(0, z.shape[1], n)
        x = xmin + cols * sp
        y = ymin + rows * sp
        lon, lat = frame.to_lonlat(x, y)
        ref = dem.sample(lon, lat)
        d = np.abs(z[rows, cols] - ref)
        # nodes under or beside roads are levelled to the road; everywhere else the terrain is the DEM
        lev += int(np.sum(d > 0.2))
        checked += n
        assert np.median(d) < 0.05
    assert lev < 0.5 * checked, f"{lev} of {checked} nodes differ from the DEM by > 0.2 m"
    return lev, checked


def _check_buildings_on_ground(out: Path, w: dict):
    from netgen.terrain import TerrainGrid

    n = 0
    for c in w["chunks"]:
        z = np.load(out / c["files"]["terrain"]).astype(float)
        g = TerrainGrid(c["bounds_m"][0], c["bounds_m"][1], w["terrain"]["spacing_m"], z)
        bj = c["files"].get("buildings_json")
        if not bj:
            continue
        for b in json.loads((out / bj).read_text())["buildings"]:
            cx, cy = b["centroid"]
            if c["bounds_m"][0] <= cx <= c["bounds_m"][2] and c["bounds_m"][1] <= cy <= c["bounds_m"][3]:
                assert b["base_z"] <= float(g.sample(cx, cy)) + 1e-3, b["id"]
                n += 1
    return n


def test_monaco_with_srtm(tmp_path):
    osm = shared_file("osm/monaco-2022.osm.pbf")
    dem = shared_file("dem/N43E007.hgt")
    w = _dem_world(tmp_path, osm, dem, (43.7384, 7.4246))
    out = tmp_path / "w"
    assert w["sources"]["elevation"]["kind"] == "dem"
    assert w["terrain"]["z_range_m"][1] - w["terrain"]["z_range_m"][0] > 50   # steep Monaco
    _check_terrain_against_dem(out, w, dem, np.random.default_rng(1))
    assert _check_buildings_on_ground(out, w) > 100


def test_lauf_with_zipped_srtm(tmp_path):
    osm = shared_file("osm/lauf-2020.osm.pbf")
    dem = shared_file("dem/N49E011.hgt.zip")
    w = _dem_world(tmp_path, osm, dem, (49.5105, 11.2780))
    _check_terrain_against_dem(tmp_path / "w", w, dem, np.random.default_rng(2))
    assert 300 < w["terrain"]["z_range_m"][0] < 430


def test_portland_with_geotiff_and_voids(tmp_path):
    osm = shared_file("osm/portland-central-2015.osm.pbf")
    dem = shared_file("dem/portland-ned.tif")
    w = _dem_world(tmp_path / "a", osm, dem, (45.5152, -122.6784))
    _check_terrain_against_dem(tmp_path / "a" / "w", w, dem, np.random.default_rng(3))
    nodata = shared_file("dem/portland-ned-nodata.tif")
    w2 = build_world(WorldConfig(osm=str(osm), dem=[str(nodata)], center=(45.5152, -122.6784), chunks=0,
                                 terrain_spacing_m=10.0, out=str(tmp_path / "b"), cache_dir=str(tmp_path / "cache")))
    assert w2["sources"]["elevation"]["voids_filled"] > 0
    z = np.load(tmp_path / "b" / w2["chunks"][0]["files"]["terrain"])
    assert np.isfinite(z).all()


# ---------------------------------------------------------------------------------------
def _cli(args, cwd, env_extra=None, timeout=300):
    env = dict(os.environ, **(env_extra or {}))
    env.pop("COSIM_DEBUG", None)
    return subprocess.run(CLI + args, cwd=cwd, capture_output=True, text=True, timeout=timeout, env=env)


@pytest.mark.parametrize("args, words", [
    (["build", "--center", "95,10", "--flat"], "latitude 95.0 is out of range"),
    (["build", "--center", "10,200", "--flat"], "longitude 200.0 is out of range"),
    (["build", "--preset", "nowhere"], "unknown preset"),
    (["build", "--preset", "helsinki", "--chunks", "99"], "chunks must be"),
    (["build", "--osm", "missing.osm.pbf", "--flat"], "OSM file not found"),
])
def test_bad_input_is_one_line_and_nonzero(tmp_path, args, words):
    r = _cli(args, tmp_path)
    assert r.returncode == 2
    err = r.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and words in err[0], r.stderr
    assert "Traceback" not in r.stderr


def test_corrupt_and_empty_osm_files(tmp_path):
    src = (REPO / "netgen/presets/kouvola.osm.pbf").read_bytes()
    (tmp_path / "cut.osm.pbf").write_bytes(src[: len(src) // 2])
    (tmp_path / "empty.osm").write_bytes(b"")
    (tmp_path / "junk.osm").write_text("<osm version='0.6'><node id='1' lat='1' lon='1'/><way id=")
    for f, words in (("cut.osm.pbf", "corrupt or truncated"), ("empty.osm", "is empty"),
                     ("junk.osm", "corrupt or truncated")):
        r = _cli(["build", "--osm", f, "--flat", "--out", "w"], tmp_path,
                 {"COSIM_CACHE": str(tmp_path / "c")})
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip().startswith("error: ") and words in r.stderr and "Traceback" not in r.stderr
        assert not (tmp_path / "w" / "world.json").exists()


def test_dem_that_does_not_cover_the_area(tmp_path):
    dem = shared_file("dem/N43E007.hgt")
    r = _cli(["build", "--preset", "helsinki", "--dem", str(dem), "--out", "w"], tmp_path,
             {"COSIM_CACHE": str(tmp_path / "c")})
    assert r.returncode == 2 and "N60E024" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_area_without_roads_is_a_clear_error(tmp_path):
    # a real OSM file of one building far from any road
    (tmp_path / "hut.osm").write_text(
        "<?xml version='1.0'?><osm version='0.6'>"
        "<node id='1' version='1' lat='60.0' lon='25.0'/><node id='2' version='1' lat='60.0' lon='25.0002'/>"
        "<node id='3' version='1' lat='60.0001' lon='25.0002'/>"
        "<way id='10' version='1'><nd ref='1'/><nd ref='2'/><nd ref='3'/><nd ref='1'/><tag k='building' v='hut'/></way>"
        "</osm>")
    r = _cli(["build", "--osm", "hut.osm", "--flat", "--out", "w"], tmp_path, {"COSIM_CACHE": str(tmp_path / "c")})
    assert r.returncode == 2 and "no" in r.stderr and "road" in r.stderr, r.stderr
    assert not (tmp_path / "w" / "world.json").exists()


def test_unwritable_output_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if os.access(ro, os.W_OK):
            pytest.skip("running as a user who can write anywhere (root): permission cannot be denied")
        r = _cli(["build", "--preset", "kouvola", "--out", str(ro / "w")], tmp_path)
        assert r.returncode == 2 and "cannot write" in r.stderr, r.stderr
    finally:
        ro.chmod(0o700)


def test_read_only_filesystem_output(tmp_path):
    """Root ignores permissions, but /proc is read-only for everyone."""
    r = _cli(["build", "--preset", "kouvola", "--out", "/proc/cosim-world"], tmp_path,
             {"COSIM_CACHE": str(tmp_path / "c")})
    assert r.returncode == 2 and r.stderr.startswith("error: cannot write"), r.stderr


def test_killed_build_leaves_nothing_trusted(tmp_path):
    env = dict(os.environ, COSIM_CACHE=str(tmp_path / "c"))
    p = subprocess.Popen(CLI + ["build", "--preset", "helsinki", "--out", "w", "-q"], cwd=tmp_path, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    # kill it mid-way: once netconvert is running
    deadline = time.time() + 60
    while time.time() < deadline and not list((tmp_path).glob("w.tmp-*/net/netconvert.log")):
        time.sleep(0.05)
    time.sleep(0.5)
    p.send_signal(signal.SIGKILL)
    p.wait()
    assert not (tmp_path / "w" / "world.json").exists()
    assert load_world_json(tmp_path / "w") is None
    # the net cache never holds a half-written network under its final name
    for f in (tmp_path / "c" / "net").glob("*.net.xml") if (tmp_path / "c" / "net").exists() else []:
        assert f.read_text().rstrip().endswith("</net>")
    # and the next build works and trusts nothing from the killed one
    r = _cli(["build", "--preset", "helsinki", "--out", "w", "-q"], tmp_path, {"COSIM_CACHE": str(tmp_path / "c")})
    assert r.returncode == 0, r.stderr
    assert load_world_json(tmp_path / "w") is not None
    assert not list(tmp_path.glob("w.tmp-*"))
