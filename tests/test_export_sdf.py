"""Gazebo export (`cosim export-sdf`): real worlds, checked with the real SDFormat parser.

The checker (tests/sdf_checker) is a small C++ program linked against libsdformat, compiled
here on first use; it loads each file with SDFormat (strict: unknown elements and parser
warnings are errors), resolves model/link/joint poses through SDFormat's frame graph and
mesh URIs the way simulators do (``model://`` on the resource path), and prints what it
understood as JSON. Tests that need it skip, naming the reason, when SDFormat (>= 12, with
headers) is not installed; CI installs it (apt: g++ pkg-config libsdformat-dev sdformat-sdf).

What is compared against the world (read independently here: world.json, terrain .npy grids,
tile OBJs parsed by a few lines below, buildings.glb via trimesh, scenery.json):
every world and model parses with zero errors, every mesh URI resolves inside the export
and loads in trimesh, building poses equal buildings.json and their meshes equal the GLB,
terrain meshes pass through every grid node, road meshes equal the tile OBJs, scenery
poses/scales equal scenery.json, and the car's SDF equals SDFormat's own URDF conversion.
"""
from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from lxml import etree

from netgen.build import build_world
from netgen.config import WorldConfig
from netgen.export_sdf import (CAR_DROP_M, CAR_MODEL, COLOURS, EXPORT_FORMAT, export_sdf, parse_chunks,
                               surface_z, Part)
from netgen.errors import InputError
from conftest import REPO, shared_file


def _load_checker_builder():
    import importlib.util

    spec = importlib.util.spec_from_file_location("sdf_checker_build", REPO / "tests" / "sdf_checker" / "build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_cb = _load_checker_builder()
CheckerUnavailable, build_checker, find_sdformat = _cb.CheckerUnavailable, _cb.build_checker, _cb.find_sdformat

MODULE = [sys.executable, "-m", "netgen.export_sdf"]


# ---------------------------------------------------------------------------------------
# fixtures
@pytest.fixture(scope="session")
def checker():
    try:
        return build_checker()
    except CheckerUnavailable as e:
        pytest.skip(f"SDFormat checker unavailable: {e}")


def run_checker(exe, files, models_dir=None, lenient=False) -> dict:
    args = [str(exe)] + (["--path", str(models_dir)] if models_dir else []) + (["--lenient"] if lenient else [])
    r = subprocess.run(args + [str(f) for f in files], capture_output=True, text=True, timeout=600)
    assert r.returncode in (0, 1), r.stderr
    return json.loads(r.stdout)


@pytest.fixture(scope="session")
def helsinki(tmp_path_factory):
    """The helsinki preset, 3 x 3 chunks, quality low (STL by default)."""
    out = tmp_path_factory.mktemp("worlds") / "helsinki"
    build_world(WorldConfig(preset="helsinki", chunks=1, out=str(out), cache_dir=str(tmp_path_factory.mktemp("c"))))
    return out


@pytest.fixture(scope="session")
def helsinki_export(helsinki, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "helsinki-sdf"
    m = export_sdf(helsinki, out)
    return out, m


@pytest.fixture(scope="session")
def monaco(tmp_path_factory):
    """Monaco on SRTM (steep: ~200 m of relief in a chunk), one chunk, quality medium (DAE)."""
    osm = shared_file("osm/monaco-2022.osm.pbf")
    dem = shared_file("dem/N43E007.hgt")
    out = tmp_path_factory.mktemp("worlds") / "monaco"
    build_world(WorldConfig(osm=str(osm), dem=[str(dem)], center=(43.7384, 7.4246), chunks=0, quality="medium",
                            out=str(out), cache_dir=str(tmp_path_factory.mktemp("c"))))
    return out


@pytest.fixture(scope="session")
def monaco_export(monaco, tmp_path_factory):
    out = tmp_path_factory.mktemp("export") / "monaco-sdf"
    return out, export_sdf(monaco, out)


@pytest.fixture(scope="session")
def helsinki_checked(helsinki_export, checker):
    out, _ = helsinki_export
    return run_checker(checker, [out / "world.sdf"], out / "models")["files"][0]


@pytest.fixture(scope="session")
def monaco_checked(monaco_export, checker):
    out, _ = monaco_export
    return run_checker(checker, [out / "world.sdf"], out / "models")["files"][0]


# ---------------------------------------------------------------------------------------
# helpers: poses, the world's own files
def rpy_matrix(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def T(pose):
    m = np.eye(4)
    m[:3, :3] = rpy_matrix(*pose[3:6])
    m[:3, 3] = pose[:3]
    return m


def world_T(model, link, elem):
    """World transform of a visual/collision from the checker's (SDFormat-resolved) poses."""
    return T(model["pose"]) @ T(link["pose"]) @ T(elem["pose"])


def yaw_of(M):
    return math.atan2(M[1, 0], M[0, 0])


def ang_diff(a, b):
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def world_json(world: Path) -> dict:
    return json.loads((world / "world.json").read_text())


def obj_triangles(path: Path) -> np.ndarray:
    """(n, 3, 3) triangles of a world OBJ in file order (v / f lines; polygons fanned)."""
    V, tris = [], []
    for ln in Path(path).read_text().splitlines():
        if ln.startswith("v "):
            V.append([float(t) for t in ln.split()[1:4]])
        elif ln.startswith("f "):
            idx = [int(t.split("/")[0]) for t in ln.split()[1:]]
            idx = [i - 1 if i > 0 else len(V) + i for i in idx]
            tris.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
    V = np.array(V)
    return V[np.array(tris)] if tris else np.zeros((0, 3, 3))


def mesh_triangles(path: Path) -> np.ndarray:
    """(n, 3, 3) triangles of an exported STL or DAE as trimesh loads it (file order)."""
    m = trimesh.load(str(path), process=False)
    if isinstance(m, trimesh.Scene):
        tris = [g.vertices[g.faces] for g in m.dump()] if hasattr(m, "dump") else \
               [g.vertices[g.faces] for g in m.geometry.values()]
        return np.concatenate(tris)
    return np.asarray(m.vertices)[np.asarray(m.faces)]


def uri_file(export: Path, uri: str) -> Path:
    assert uri.startswith("model://"), uri
    return export / "models" / uri[len("model://"):]


def sdf_models(export: Path) -> dict:
    """model name -> {element name: {pose, uri, scale, collision}} read from model.sdf with lxml
    (for the geometry comparisons, which do not need SDFormat)."""
    out = {}
    for f in sorted((export / "models").glob("*/model.sdf")):
        root = etree.parse(str(f)).getroot()
        m = root.find("model")
        els = {}
        for v in m.iter("visual"):
            uri = v.find("geometry/mesh/uri")
            sc = v.find("geometry/mesh/scale")
            pose = v.find("pose")
            els[v.get("name")] = {"pose": [float(x) for x in pose.text.split()] if pose is not None else [0] * 6,
                                  "uri": uri.text if uri is not None else None,
                                  "scale": float(sc.text.split()[0]) if sc is not None else 1.0}
        for c in m.iter("collision"):
            base = c.get("name").removesuffix("_collision")
            pose = c.find("pose")
            if base in els:
                cp = [float(x) for x in pose.text.split()] if pose is not None else [0.0] * 6
                els[base]["collision"] = {"pose": cp, "geometry": c.find("geometry")[0].tag}
        out[m.get("name")] = els
    return out


def checked_model(checked, name):
    ms = [m for m in checked["worlds"][0]["models"] if m["name"] == name]
    assert len(ms) == 1, name
    return ms[0]


# ---------------------------------------------------------------------------------------
def test_checker_skips_with_a_reason_without_sdformat(monkeypatch):
    """The skip path: with pkg-config seeing no libraries, the checker says what to install."""
    monkeypatch.setenv("PKG_CONFIG_LIBDIR", "/nonexistent")
    monkeypatch.setenv("PKG_CONFIG_PATH", "/nonexistent")
    with pytest.raises(CheckerUnavailable, match="libsdformat-dev"):
        find_sdformat()


def test_world_and_every_model_parse_with_zero_errors(helsinki, helsinki_export, helsinki_checked, checker):
    out, m = helsinki_export
    wj = world_json(helsinki)
    f = helsinki_checked
    assert f["errors"] == [] and f["pose_errors"] == [], f["errors"][:5]
    assert f["version"] >= "1.6" and etree.parse(str(out / "world.sdf")).getroot().get("version") == "1.6"
    w = f["worlds"][0]
    # sun, physics, geo-reference
    suns = [l for l in w["lights"] if l["directional"]]
    assert len(suns) == 1 and suns[0]["direction"][2] < 0 and suns[0]["cast_shadows"]
    assert len(w["physics"]) == 1 and w["physics"][0]["default"] and 0 < w["physics"][0]["max_step_size"] <= 0.01
    assert w["gravity"][2] == pytest.approx(-9.81)
    assert w["spherical"]["lat"] == pytest.approx(wj["center"]["lat"]) and \
        w["spherical"]["lon"] == pytest.approx(wj["center"]["lon"])
    # the whole window: every chunk has its terrain, and roads/buildings/scenery where it has them
    names = {x["name"] for x in w["models"]}
    assert names == (set(m["models"]) - {CAR_MODEL}) | {"ego"} and CAR_MODEL in m["models"]
    for c in wj["chunks"]:
        tag = f"{c['i']}_{c['j']}"
        assert f"terrain_{tag}" in names
        assert (f"roads_{tag}" in names) == bool(c["tiles"])
        assert (f"buildings_{tag}" in names) == (c["counts"]["buildings"] > 0)
        assert (f"scenery_{tag}" in names) == (c["counts"]["scenery"] > 0)
    for x in w["models"]:
        assert x["static"] == (x["name"] != "ego")
    # every model folder: model.config naming an SDF file that parses with zero errors
    folders = sorted((out / "models").iterdir())
    assert {p.name for p in folders} == set(m["models"]) | {f"prefab_{k}" for k in m["prefabs"]}
    for d in folders:
        cfg = etree.parse(str(d / "model.config")).getroot()
        assert cfg.tag == "model" and cfg.findtext("name") == d.name
        assert (d / cfg.findtext("sdf")).is_file() and cfg.find("sdf").get("version") == "1.6"
    res = run_checker(checker, [d / "model.sdf" for d in folders], out / "models")
    bad = [(x["file"], x["errors"] + x["pose_errors"]) for x in res["files"] if x["errors"] or x["pose_errors"]]
    assert bad == []
    assert all(x["model"] is not None for x in res["files"])
    # launch instructions
    readme = (out / "README.md").read_text()
    for words in ("GZ_SIM_RESOURCE_PATH", "GAZEBO_MODEL_PATH", "gz sim world.sdf", "gazebo --verbose world.sdf",
                  "OpenStreetMap"):
        assert words in readme
    assert json.loads((out / "export.json").read_text())["format"] == EXPORT_FORMAT


def _all_mesh_geoms(checked_file):
    models = checked_file["worlds"][0]["models"] if checked_file["worlds"] else [checked_file["model"]]
    for mo in models:
        for ln in mo["links"]:
            for kind in ("visuals", "collisions"):
                for e in ln[kind]:
                    if e["geometry"]["type"] == "mesh":
                        yield mo, ln, kind, e


def test_every_mesh_uri_resolves_to_a_file_trimesh_loads(helsinki_export, helsinki_checked):
    out, m = helsinki_export
    files = {}
    for mo, ln, kind, e in _all_mesh_geoms(helsinki_checked):
        g = e["geometry"]
        assert g["uri"].startswith("model://"), g["uri"]          # portable: no absolute paths
        assert g["resolved"], f"SDFormat could not resolve {g['uri']}"
        p = Path(g["resolved"]).resolve()
        assert p == uri_file(out, g["uri"]).resolve() and (out / "models") in p.parents
        files[p] = g["uri"]
    # and the prefab models' own meshes
    for k, uri in m["prefabs"].items():
        files[uri_file(out, uri).resolve()] = uri
    on_disk = {p.resolve() for p in (out / "models").rglob("meshes/*")}
    assert on_disk == set(files), "mesh files that no model uses, or used files that are missing"
    for p in sorted(files):
        mesh = trimesh.load(str(p))
        n = sum(len(g.faces) for g in mesh.geometry.values()) if isinstance(mesh, trimesh.Scene) else len(mesh.faces)
        assert n > 0, p
    assert sum(1 for p in files if p.suffix == ".stl") == len(files)        # quality low -> STL


def test_building_poses_and_meshes_equal_the_world(helsinki, helsinki_export, helsinki_checked):
    out, m = helsinki_export
    wj = world_json(helsinki)
    n = 0
    for c in wj["chunks"]:
        recs = json.loads((helsinki / c["files"]["buildings_json"]).read_text())["buildings"]
        if not recs:
            continue
        mo = checked_model(helsinki_checked, f"buildings_{c['i']}_{c['j']}")
        ln = mo["links"][0]
        vis = {v["name"]: v for v in ln["visuals"]}
        col = {v["name"]: v for v in ln["collisions"]}
        assert len(vis) == len(recs) == len(col)
        glb = trimesh.load(str(helsinki / c["files"]["buildings_glb"]), force="scene", process=False)
        for r in recs:
            name = r["id"].replace("/", "_")
            v = vis[name]
            M = world_T(mo, ln, v)
            # the pose SDFormat resolves is the building's position in the world
            assert M[:3, 3] == pytest.approx([r["centroid"][0], r["centroid"][1], r["base_z"]], abs=1e-3)
            assert np.allclose(M[:3, :3], np.eye(3))
            assert world_T(mo, ln, col[name + "_collision"]) == pytest.approx(M)
            # and the mesh, placed there, is the world's building mesh
            tri = mesh_triangles(Path(v["geometry"]["resolved"]))
            tw = tri @ M[:3, :3].T + M[:3, 3]
            Tn, gname = glb.graph[r["id"]]
            g = glb.geometry[gname]
            src = (np.asarray(g.vertices) @ Tn[:3, :3].T + Tn[:3, 3])[np.asarray(g.faces)]
            assert tw.shape == src.shape and np.abs(tw - src).max() < 2e-3, r["id"]
            # the building stands on its base: its lowest vertex is at base_z - a little at most
            assert tw[..., 2].min() >= r["base_z"] - 0.5
            n += 1
    assert n == wj["counts"]["buildings"] == m["counts"]["buildings"]


def test_terrain_meshes_pass_through_every_grid_node(monaco, monaco_export, monaco_checked):
    """Steep Monaco terrain (DAE): each chunk's mesh has exactly the grid's nodes, at its heights,
    and covers the chunk."""
    out, m = monaco_export
    wj = world_json(monaco)
    s = wj["terrain"]["spacing_m"]
    for c in wj["chunks"]:
        z = np.load(monaco / c["files"]["terrain"]).astype(float)
        ny, nx = z.shape
        mo = checked_model(monaco_checked, f"terrain_{c['i']}_{c['j']}")
        ln = mo["links"][0]
        assert [x["name"] for x in ln["collisions"]] == ["terrain_collision"]
        v = ln["visuals"][0]
        M = world_T(mo, ln, v)
        tri = mesh_triangles(Path(v["geometry"]["resolved"]))
        assert len(tri) == 2 * (nx - 1) * (ny - 1)
        P = tri.reshape(-1, 3) @ M[:3, :3].T + M[:3, 3]
        col = (P[:, 0] - c["bounds_m"][0]) / s
        row = (P[:, 1] - c["bounds_m"][1]) / s
        assert np.abs(col - np.rint(col)).max() < 1e-4 and np.abs(row - np.rint(row)).max() < 1e-4
        ci, ri = np.rint(col).astype(int), np.rint(row).astype(int)
        assert np.abs(P[:, 2] - z[ri, ci]).max() < 1e-3
        assert len(set(zip(ri.tolist(), ci.tolist()))) == nx * ny
        a = tri[:, 1, :2] - tri[:, 0, :2]
        b = tri[:, 2, :2] - tri[:, 0, :2]
        area = 0.5 * np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]).sum()
        xmin, ymin, xmax, ymax = c["bounds_m"]
        assert area == pytest.approx((xmax - xmin) * (ymax - ymin), rel=1e-6)
        assert z.max() - z.min() > 50               # really steep: the test compares heights
    assert m["mesh_format"] == "dae"


def test_road_meshes_equal_the_tile_objs(helsinki, helsinki_export):
    out, _ = helsinki_export
    wj = world_json(helsinki)
    els = sdf_models(out)
    n = 0
    for c in wj["chunks"]:
        for ab, layers in c["tiles"].items():
            for layer, rel in layers.items():
                if layer == "building":                    # buildings come from buildings.glb
                    continue
                src = obj_triangles(helsinki / rel)
                e = els[f"roads_{c['i']}_{c['j']}"][f"{layer}_{ab}"]
                M = T(e["pose"])
                tri = mesh_triangles(uri_file(out, e["uri"]))
                assert tri.shape == src.shape
                assert np.abs(tri @ M[:3, :3].T + M[:3, 3] - src).max() < 2e-3, rel
                # drivable surfaces collide, paint does not
                assert ("collision" in e) == (layer in ("asphalt", "sidewalk", "rail"))
                n += 1
    assert n > 50


def test_scenery_poses_scales_and_collisions_equal_the_world(helsinki, helsinki_export, helsinki_checked):
    out, m = helsinki_export
    wj = world_json(helsinki)
    prefabs = json.loads((REPO / "models/prefabs/prefabs.json").read_text())["prefabs"]
    n = 0
    for c in wj["chunks"]:
        inst = json.loads((helsinki / c["files"]["scenery_json"]).read_text())["instances"]
        inst = [s for s in inst if s["kind"] in prefabs]
        if not inst:
            continue
        mo = checked_model(helsinki_checked, f"scenery_{c['i']}_{c['j']}")
        ln = mo["links"][0]
        assert len(ln["visuals"]) == len(ln["collisions"]) == len(inst)
        # elements are in scenery.json order
        for s, v, col in zip(inst, ln["visuals"], ln["collisions"]):
            assert v["name"].startswith(s["kind"] + "_") and col["name"] == v["name"] + "_collision"
            M = world_T(mo, ln, v)
            assert M[:3, 3] == pytest.approx([s["x"], s["y"], s["z"]], abs=1e-3)
            assert ang_diff(yaw_of(M), s["yaw"]) < 1e-5
            assert v["geometry"]["scale"] == pytest.approx([s["scale"]] * 3, abs=1e-4)
            assert v["geometry"]["uri"] == m["prefabs"][s["kind"]]
            pc = prefabs[s["kind"]]["collision"]
            Mc = world_T(mo, ln, col)
            off = np.array(pc["offset"]) * s["scale"]
            assert Mc[:3, 3] == pytest.approx(M[:3, :3] @ off + M[:3, 3], abs=1e-3)
            g = col["geometry"]
            if pc["type"] == "cylinder":
                assert g["radius"] == pytest.approx(pc["radius"] * s["scale"], abs=1e-3)
                assert g["length"] == pytest.approx(pc["height"] * s["scale"], abs=1e-3)
            else:
                assert g["size"] == pytest.approx([2 * h * s["scale"] for h in pc["half_extents"]], abs=1e-3)
            n += 1
    assert n == m["counts"]["scenery"] > 1000
    # the prefab meshes are the prefabs of models/prefabs (the same bounds)
    for kind, uri in m["prefabs"].items():
        mesh = trimesh.load(str(uri_file(out, uri)))
        assert mesh.bounds == pytest.approx(np.array(prefabs[kind]["bounds"]), abs=2e-3), kind


def test_car_sdf_matches_sdformats_own_urdf_conversion(helsinki_export, checker):
    out, m = helsinki_export
    d = out / "models" / CAR_MODEL
    res = run_checker(checker, [d / "model.urdf"], lenient=True)["files"][0]
    assert res["errors"] == [], res["errors"]
    mine = run_checker(checker, [d / "model.sdf"], out / "models")["files"][0]
    assert mine["errors"] == [] and mine["pose_errors"] == []
    ref, got = res["model"], mine["model"]
    assert len(got["links"]) == len(ref["links"]) == 7 and len(got["joints"]) == len(ref["joints"]) == 6
    rl = {x["name"]: x for x in ref["links"]}
    urdf = etree.parse(str(d / "model.urdf")).getroot()
    named = {mt.get("name"): [float(v) for v in mt.find("color").get("rgba").split()]
             for mt in urdf.findall("material")}
    urdf_colours = {ln.get("name"): [named[v.find("material").get("name")] for v in ln.findall("visual")]
                    for ln in urdf.findall("link")}
    for ln in got["links"]:
        r = rl[ln["name"]]
        assert T(ln["pose"]) == pytest.approx(T(r["pose"]), abs=1e-9), ln["name"]
        assert ln["mass"] == pytest.approx(r["mass"]) and ln["inertia_diag"] == pytest.approx(r["inertia_diag"])
        assert T(ln["inertial_pose"]) == pytest.approx(T(r["inertial_pose"]), abs=1e-9)
        for kind in ("visuals", "collisions"):
            # SDFormat's URDF reader renames elements: compare geometry and pose, in order
            assert len(ln[kind]) == len(r[kind]), (ln["name"], kind)
            for a, b in zip(ln[kind], r[kind]):
                assert a["geometry"] == b["geometry"]
                assert T(a["pose"]) == pytest.approx(T(b["pose"]), abs=1e-9)
        # colours: the URDF's material rgba (SDFormat's own URDF reader brightens them)
        for a, b in zip(ln["visuals"], urdf_colours[ln["name"]]):
            assert a["diffuse"] == pytest.approx(b, abs=1e-6)
    rj = {x["name"]: x for x in ref["joints"]}
    for j in got["joints"]:
        r = rj[j["name"]]
        for k in ("type", "parent", "child", "lower", "upper", "effort", "velocity"):
            assert j[k] == pytest.approx(r[k]) if isinstance(r[k], float) else j[k] == r[k], (j["name"], k)
        assert j["axis_model"] == pytest.approx(r["axis_model"], abs=1e-9)
        assert T(j["pose"]) == pytest.approx(T(r["pose"]), abs=1e-9)
    # the URDF copy is the original robot (no meshes to relocate in today's car)
    src = etree.parse(str(REPO / "models/car/car.urdf")).getroot()
    cp = etree.parse(str(d / "model.urdf")).getroot()
    assert [x.get("name") for x in cp.iter("link")] == [x.get("name") for x in src.iter("link")]
    assert [x.get("name") for x in cp.iter("joint")] == [x.get("name") for x in src.iter("joint")]


def test_car_stands_on_a_lane_in_the_world(helsinki, helsinki_export, helsinki_checked):
    out, m = helsinki_export
    ego = checked_model(helsinki_checked, "ego")
    assert not ego["static"] and len(ego["links"]) == 7
    x, y, z = ego["pose"][:3]
    assert m["car"]["placed_on"] == "lane"
    # on the asphalt of its tile (read from the world's OBJ), CAR_DROP_M above it
    from cosim.world import World

    w = World(helsinki)
    key = w.tile_of(x, y)
    tri = obj_triangles(w.tile_files(key)["asphalt"])
    zs = surface_z([Part("a", tri.reshape(-1, 3), np.arange(len(tri) * 3).reshape(-1, 3))], x, y)
    assert zs is not None and z == pytest.approx(zs + CAR_DROP_M, abs=1e-3)
    # heading along a passenger lane of the SUMO network through that point
    net = etree.parse(str(helsinki / world_json(helsinki)["net_file"]))
    best = 1e9
    for ln in net.iter("lane"):
        if ln.getparent().get("function") or "passenger" in (ln.get("disallow") or "").split():
            continue
        pts = np.array([[float(v) for v in p.split(",")[:2]] for p in ln.get("shape").split()])
        for a, b in zip(pts[:-1], pts[1:]):
            ab = b - a
            t = np.clip(np.dot([x, y] - a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
            dist = np.linalg.norm(a + t * ab - [x, y])
            if dist < 0.01:
                best = min(best, ang_diff(math.atan2(ab[1], ab[0]), ego["pose"][5]))
    assert best < 1e-3


def test_chosen_chunks(helsinki, tmp_path, checker):
    out = tmp_path / "two"
    m = export_sdf(helsinki, out, chunks=parse_chunks("0,0;1,0"))
    assert m["chunks"] == [[0, 0], [1, 0]] and m["area_km2"] == 2.0
    res = run_checker(checker, [out / "world.sdf"], out / "models")["files"][0]
    assert res["errors"] == [] and res["pose_errors"] == []
    names = {x["name"] for x in res["worlds"][0]["models"]}
    assert {"terrain_0_0", "terrain_1_0", "buildings_0_0", "buildings_1_0", "ego"} <= names
    assert not any(n.endswith(("_-1_-1", "_0_1", "_-1_0", "_0_-1")) for n in names)
    wj = world_json(helsinki)
    nb = sum(c["counts"]["buildings"] for c in wj["chunks"] if (c["i"], c["j"]) in ((0, 0), (1, 0)))
    assert m["counts"]["buildings"] == nb
    assert {tuple(o["chunk"]) for o in m["objects"]} == {(0, 0), (1, 0)}
    x, y = m["car"]["pose"][:2]
    assert -500 <= x <= 1500 and -500 <= y <= 500
    # exporting again over it replaces it (a different selection, nothing left behind)
    m2 = export_sdf(helsinki, out, chunks=[(1, 0)], car=False)
    assert sorted(p.name for p in (out / "models").iterdir()) == \
        sorted(m2["models"] + [f"prefab_{k}" for k in m2["prefabs"]]) and CAR_MODEL not in m2["models"]
    assert "ego" not in (out / "world.sdf").read_text() and m2["car"] is None
    assert not list(tmp_path.glob("two.tmp-*"))


def test_dae_export_has_materials(monaco, monaco_export, monaco_checked):
    out, m = monaco_export
    assert monaco_checked["errors"] == [] and monaco_checked["pose_errors"] == []
    uris = [e["geometry"]["uri"] for _, _, _, e in _all_mesh_geoms(monaco_checked)]
    assert uris and all(u.endswith(".dae") for u in uris)
    for _, _, kind, e in _all_mesh_geoms(monaco_checked):
        assert Path(e["geometry"]["resolved"]).is_file()
        if kind == "visuals":
            assert "diffuse" not in e            # the colour is the DAE's own material
    # road colours from the DAE materials, as trimesh/pycollada reads them
    road = next(u for u in uris if "/asphalt_" in u)
    sc = trimesh.load(str(uri_file(out, road)))
    g = next(iter(sc.geometry.values()))
    rgba = np.asarray(g.visual.material.baseColorFactor, dtype=float)
    rgba = rgba / 255.0 if rgba.max() > 1 else rgba
    assert rgba[:3] == pytest.approx(COLOURS["asphalt"][:3], abs=0.01)
    # a multi-material prefab keeps its materials (tree: bark and leaves)
    tree = trimesh.load(str(uri_file(out, m["prefabs"]["tree"])))
    cols = {tuple(np.round(np.asarray(g.visual.material.baseColorFactor, float)[:3] /
                           (255.0 if np.asarray(g.visual.material.baseColorFactor).max() > 1 else 1.0), 2))
            for g in tree.geometry.values()}
    assert len(cols) == 2
    # buildings: every building of the chunk, posed at its base on the steep ground
    c = world_json(monaco)["chunks"][0]
    recs = json.loads((monaco / c["files"]["buildings_json"]).read_text())["buildings"]
    mo = checked_model(monaco_checked, "buildings_0_0")
    ln = mo["links"][0]
    vis = {v["name"]: v for v in ln["visuals"]}
    assert len(vis) == len(recs) > 100
    zs = []
    for r in recs:
        M = world_T(mo, ln, vis[r["id"].replace("/", "_")])
        assert M[:3, 3] == pytest.approx([r["centroid"][0], r["centroid"][1], r["base_z"]], abs=1e-3)
        zs.append(M[2, 3])
    assert max(zs) - min(zs) > 30
    # the car on a sloping road is pitched with it (nose down when the road falls ahead)
    ego = checked_model(monaco_checked, "ego")
    assert m["car"]["placed_on"] == "lane" and abs(ego["pose"][4]) < 0.3


# ---------------------------------------------------------------------------------------
def _module(args, cwd):
    env = dict(os.environ)
    env.pop("COSIM_DEBUG", None)
    return subprocess.run(MODULE + args, cwd=cwd, capture_output=True, text=True, timeout=300, env=env)


def test_command_line_report_and_errors(helsinki, tmp_path):
    r = _module(["--world", str(helsinki), "--out", "x", "--chunks", "0,0", "--no-car", "-q"], tmp_path)
    assert r.returncode == 0, r.stderr
    assert "launch" in r.stdout and "1 chunks" in r.stdout and r.stderr == ""
    assert (tmp_path / "x" / "world.sdf").is_file()
    (tmp_path / "junk").mkdir()
    (tmp_path / "junk" / "keep.txt").write_text("mine")
    (tmp_path / "afile").write_text("")
    for args, words in (
        (["--world", str(tmp_path / "nowhere"), "--out", "y"], "no world at"),
        (["--world", str(helsinki), "--out", "y", "--chunks", "7,7"], "chunk 7,7 is not in the world"),
        (["--world", str(helsinki), "--out", "y", "--chunks=-1,x"], "--chunks: expected"),
        (["--world", str(helsinki), "--out", "/proc/cosim-export"], "cannot write /proc/cosim-export"),
        (["--world", str(helsinki), "--out", "junk"], "is not empty"),
        (["--world", str(helsinki), "--out", "afile"], "is a file"),
        (["--world", str(helsinki), "--out", str(helsinki / "inside")], "overlaps the world folder"),
    ):
        r = _module(args, tmp_path)
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ") and words in lines[0], \
            (args, r.stderr)
        assert "Traceback" not in r.stderr
    assert (tmp_path / "junk" / "keep.txt").read_text() == "mine"
    assert not (tmp_path / "y").exists() and not list(tmp_path.glob("*.tmp-*"))


def test_parse_chunks():
    assert parse_chunks("0,0;1,0") == [(0, 0), (1, 0)]
    assert parse_chunks(" -1,0 ; 0,-1;0,-1 ") == [(-1, 0), (0, -1)]
    assert parse_chunks("-1_0 2,3") == [(-1, 0), (2, 3)]
    for bad in ("", ";", "1", "a,b", "1,2,3"):
        with pytest.raises(InputError):
            parse_chunks(bad)


def test_damaged_world_is_a_one_line_data_error(helsinki, tmp_path):
    import shutil

    from netgen.errors import DataError

    w = tmp_path / "w"
    shutil.copytree(helsinki, w)
    (w / "chunks/0_0/terrain.npy").unlink()
    with pytest.raises(DataError, match=r"cannot read .*terrain\.npy") as e:
        export_sdf(w, tmp_path / "x1", chunks=[(0, 0)])
    assert "\n" not in str(e.value)
    shutil.copy(helsinki / "chunks/0_0/terrain.npy", w / "chunks/0_0/terrain.npy")
    bj = w / "chunks/0_0/buildings.json"
    good = bj.read_text()
    bj.write_text(good[: len(good) // 2])                     # truncated
    with pytest.raises(DataError, match="corrupt or unexpected") as e:
        export_sdf(w, tmp_path / "x2", chunks=[(0, 0)])
    assert "\n" not in str(e.value)
    bj.write_text('{"buildings": [{"id": "way/1", "centroid": [0, 0], "base_z": 0}]}')   # not in the GLB
    with pytest.raises(DataError, match="building way/1 of chunk 0,0 has no mesh"):
        export_sdf(w, tmp_path / "x2", chunks=[(0, 0)])
    assert not (tmp_path / "x1").exists() and not (tmp_path / "x2").exists()
    assert not list(tmp_path.glob("x*.tmp-*"))


def test_car_export_relocates_urdf_meshes(tmp_path, checker):
    """A car URDF with mesh files (relative and package://): they are copied into the model
    and both the URDF copy and the SDF refer to the copies."""
    from netgen.export_sdf import Writer, export_car

    src = tmp_path / "pkg" / "car"
    (src / "meshes").mkdir(parents=True)
    trimesh.creation.box(extents=(4, 2, 1)).export(src / "meshes" / "body.stl")
    trimesh.creation.cylinder(radius=0.3, height=0.2).export(tmp_path / "pkg" / "wheel.stl")
    urdf = src / "car.urdf"
    urdf.write_text("""<?xml version="1.0"?>
<robot name="meshcar">
  <link name="base"><inertial><mass value="1000"/><inertia ixx="100" ixy="0" ixz="0" iyy="400" iyz="0" izz="450"/>
    </inertial>
    <visual><origin xyz="0 0 0.7" rpy="0 0 0.1"/><geometry><mesh filename="meshes/body.stl"/></geometry></visual>
    <collision><origin xyz="0 0 0.7"/><geometry><mesh filename="meshes/body.stl" scale="1 1 1"/></geometry></collision>
  </link>
  <link name="wheel"><inertial><mass value="20"/><inertia ixx="1" ixy="0" ixz="0" iyy="1" iyz="0" izz="1"/></inertial>
    <visual><geometry><mesh filename="package://pkg/wheel.stl"/></geometry></visual></link>
  <joint name="spin" type="continuous"><parent link="base"/><child link="wheel"/>
    <origin xyz="1.3 0.8 0.3" rpy="1.5707963267948966 0 0"/><axis xyz="0 0 1"/></joint>
</robot>
""")
    # package://PKG/REST is looked up as REST beside the URDF (no ROS package path here)
    (src / "wheel.stl").write_bytes((tmp_path / "pkg" / "wheel.stl").read_bytes())
    w = Writer(tmp_path / "out", "stl")
    info = export_car(w, urdf)
    d = tmp_path / "out" / "models" / CAR_MODEL
    cp = etree.parse(str(d / "model.urdf")).getroot()
    files = [m.get("filename") for m in cp.iter("mesh")]
    assert files == ["meshes/body.stl", "meshes/body.stl", "meshes/wheel.stl"]
    assert all((d / f).is_file() for f in files) and info["meshes"] == ["meshes/body.stl", "meshes/wheel.stl"]
    res = run_checker(checker, [d / "model.sdf"], tmp_path / "out" / "models")["files"][0]
    assert res["errors"] == [] and res["pose_errors"] == []
    uris = [v["geometry"]["uri"] for ln in res["model"]["links"] for v in ln["visuals"] + ln["collisions"]]
    assert uris == [f"model://{CAR_MODEL}/meshes/body.stl"] * 2 + [f"model://{CAR_MODEL}/meshes/wheel.stl"]
    ref = run_checker(checker, [d / "model.urdf"], lenient=True)["files"][0]
    assert ref["errors"] == []
    wheel = {ln["name"]: ln for ln in res["model"]["links"]}["wheel"]
    rwheel = {ln["name"]: ln for ln in ref["model"]["links"]}["wheel"]
    assert T(wheel["pose"]) == pytest.approx(T(rwheel["pose"]), abs=1e-9)
    j = res["model"]["joints"][0]
    assert j["axis_model"] == pytest.approx(ref["model"]["joints"][0]["axis_model"], abs=1e-9)
    assert j["axis_model"] == pytest.approx([0, -1, 0], abs=1e-9)      # z turned by roll +90 deg
