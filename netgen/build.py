"""Build a world: OSM + elevation -> SUMO network + chunked 3D layers + world.json.

netconvert is the long pole: the build is arranged so that little is left to do once it
has finished, and what is left runs on both cores. Stages (timed; the report and
``world.json`` carry the figures, ``timings_s``):

1. resolve the place (preset, local OSM file, Overpass bbox); convert the OSM data to the
   XML netconvert reads (``osm``, cached);
2. start netconvert in the background (when there is a world on disk that may be up to
   date, only after checking its build key, which needs the elevation source), and
   meanwhile, on the other core, open the elevation source (``elevation_open``) and do
   everything that does not need the network: sample the terrain grid
   (``terrain_sample``), read buildings and scenery (``features``; from the PBF source
   when there is one), extrude every building on a base of 0 and find where its base
   will be sampled (``buildings_plan``), and generate, test against the buildings and
   drape the scenery (``scenery_plan``; left to step 4 when netconvert is done first),
   and make each chunk's building files but for the heights (``buildings_prepare``: the
   tiles' face text, the GLB's indices and scene, buildings.json but the bases; chunk by
   chunk while netconvert runs, the rest where the chunk is written);
3. read the network while netconvert writes it (``net_read``: netconvert spends about a
   quarter of its time writing, and what the builder needs comes first in the file);
4. then three streams (:class:`_Streams`): this process meshes the roads; a forked
   process builds the carriageway and places the scenery on it (moving poles off it,
   cutting grass along it), levels the terrain under the roads if it is done with that
   before the meshing has found the levelling support (``terrain_level``; the rest of the
   meshing goes on here meanwhile; else this process levels as soon as it has the support,
   as on a city whose scenery takes long to place; it cuts the buildings' passages over the
   roads while the support comes), puts the scenery on the final terrain and writes it,
   then writes the buildings (lifted onto the levelled terrain: positions and bases into
   the prepared files); a second forked process, started once the roads are meshed, writes road
   tiles, piece by piece with this process, by whichever is free.
   The junction planes of the network's nodes (:func:`planes_to_register`) are written to
   ``road_planes.npz``; a build given a register (``heights``: a streamed window gets its
   world's) keeps the planes it holds and adds its own to it once the build is in place;
5. ``world.json`` last: the world is built in a temporary folder and renamed into place, so
   a killed build never leaves a folder that looks complete (forked processes die with
   the build).

Files inside the temporary folder are not fsynced one by one (see :mod:`netgen.meshio`);
``world.json`` is. Each chunk has ``terrain.npy``, one OBJ per tile and class
(``tiles/<a>_<b>/<class>.obj``: asphalt, sidewalk, marking, rail, deck, building; a ``g`` group
per piece), ``roads.json``, ``buildings.glb`` and ``buildings.json``, ``scenery.json``,
``areas.glb`` and ``areas.obj`` (the buildings are in the tiles and the GLB; there is no
merged buildings.obj).

A rebuild with the same inputs finds ``world.json`` with the same build key and returns at
once; netconvert's output is also cached by its inputs (OSM content, options, projection).
"""
from __future__ import annotations

import datetime as _dt
import gc
import json
import math
import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import __version__ as NETGEN_VERSION
from ._atomic import atomic_path, check_writable, folder_lock, remove_stale_temps, write_text
from .config import QUALITY, WorldConfig
from .errors import BuildError, DataError, InputError
from .frame import WorldFrame
from .meshio import COLLIDE_CLASSES, ObjBatch, tile_index, write_collision_mesh, write_file

FORMAT_VERSION = 1
TILE_M = 250.0


class Timer:
    def __init__(self):
        self.t = {}

    @contextmanager
    def stage(self, name):
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.t[name] = round(self.t.get(name, 0.0) + time.perf_counter() - t0, 3)


def _noop(*a, **k):
    pass


# ---------------------------------------------------------------------------------------
# 1. place and elevation
# ---------------------------------------------------------------------------------------
def resolve_place(cfg: WorldConfig):
    """-> (name, centre (lat, lon), osm source dict, preset or None)."""
    from .presets import get_preset

    if cfg.preset:
        p = get_preset(cfg.preset)
        centre = cfg.center or p.center
        return p.name, centre, {"kind": "preset", "file": str(p.osm), "preset": p.name,
                                "date": p.osm_date, "place": p.place}, p
    if cfg.osm:
        from .osm_file import header_bbox, scan

        path = Path(cfg.osm)
        centre = cfg.center
        if centre is None:
            bb = header_bbox(path) or scan(path)["bbox"]
            centre = ((bb[0] + bb[2]) / 2.0, (bb[1] + bb[3]) / 2.0)
        return path.name.split(".")[0], centre, {"kind": "file", "file": str(path.resolve())}, None
    if cfg.bbox:
        s, w, n, e = cfg.bbox
        centre = cfg.center or ((s + n) / 2.0, (w + e) / 2.0)
        return f"bbox_{s:.4f}_{w:.4f}", centre, {"kind": "overpass", "bbox": list(cfg.bbox)}, None
    lat, lon = cfg.center
    return f"at_{lat:.4f}_{lon:.4f}", cfg.center, {"kind": "overpass"}, None


def open_elevation_source(cfg: WorldConfig, preset, bbox):
    """The elevation source the config asks for; never silently flat."""
    from .dem import FlatElevation

    if cfg.flat:
        return FlatElevation(cfg.flat_elevation_m)
    if cfg.dem:
        from .dem import open_dem

        src = open_dem(cfg.dem)
        src.check_covers(*bbox)
        return src
    if cfg.elevation_url:
        from .open_elevation import OpenElevation

        src = OpenElevation.from_config(cfg)
        src.prepare(*bbox)
        return src
    if preset is not None:
        if preset.elevation == "flat":
            return FlatElevation(preset.flat_elevation_m)
        from .dem import open_dem

        src = open_dem([str(Path(preset.osm).parent / preset.elevation)])
        src.check_covers(*bbox)
        return src
    raise InputError("no elevation source: give --dem FILE, --elevation URL or --flat")


def _osm_for(cfg, source, bbox, cache: Path) -> tuple[Path, dict]:
    """The OSM XML netconvert reads, and the source's info (its sha256). From a PBF file,
    only what netconvert reads (:func:`netgen.osm_file.network_xml`: the same network, made
    faster; the buildings and scenery are read from the PBF itself); from XML (a file or
    Overpass), the whole file sorted, which the buildings and scenery are read from too."""
    from .osm_file import network_xml, to_osm_xml

    if source["kind"] in ("preset", "file"):
        if _is_pbf(Path(source["file"])):
            return network_xml(Path(source["file"]), cache)
        return to_osm_xml(Path(source["file"]), cache)
    from .overpass import fetch_osm

    path = fetch_osm(bbox, urls=cfg.overpass_urls, cache_dir=cache, timeout_s=cfg.http_timeout_s,
                     retries=cfg.http_retries)
    source["file"] = str(path)
    source["date"] = _dt.date.today().isoformat()
    try:
        return to_osm_xml(Path(path), cache)
    except DataError as e:
        if "has no map data" in str(e):
            raise DataError(f"no roads in the area {bbox[0]:.5f},{bbox[1]:.5f},{bbox[2]:.5f},{bbox[3]:.5f}: "
                            "Overpass has no map data there (open sea?)") from None
        raise


# ---------------------------------------------------------------------------------------
VOLATILE_INFO = {"requests", "cached", "attempts", "url", "urls"}


def _build_key(cfg: WorldConfig, osm_sha: str, elev_info: dict, centre, traffic_scale: float = 1.0) -> str:
    stable = {k: v for k, v in elev_info.items() if k not in VOLATILE_INFO}
    extra = {"osm": osm_sha, "elev": json.dumps(stable, sort_keys=True, default=str),
             "centre": [round(centre[0], 7), round(centre[1], 7)], "format": FORMAT_VERSION,
             "code": NETGEN_VERSION, "traffic_scale": traffic_scale}
    return cfg.fingerprint(extra)


def _dem_files_key(cfg) -> list:
    from .osm_file import file_hash

    return [file_hash(Path(p))[:16] for p in cfg.dem]


def load_world_json(out: Path) -> dict | None:
    p = Path(out) / "world.json"
    if not p.exists():
        return None
    try:
        w = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    # trust it only if every listed file exists
    for c in w.get("chunks", []):
        for f in c.get("files", {}).values():
            for rel in (f if isinstance(f, list) else [f]):
                if rel and not (Path(out) / rel).exists():
                    return None
    if not (Path(out) / w.get("net_file", "-")).exists():
        return None
    return w


def build_world(cfg: WorldConfig, progress=_noop, force: bool = False, heights=None) -> dict:
    """Build (or reuse) the world described by `cfg`; returns the world.json dict.

    ``heights``: a road heights register (``road_planes.npz``, see :func:`read_planes`) to
    build consistently with: its junction planes are kept, and this build's own are added to
    it for the nodes it has not got (a streamed window and the world before it then give the
    same street the same height; without, up to 0.45 m apart on Portland)."""
    from . import sumo_net

    cfg.validate()
    T = Timer()
    t_start = time.perf_counter()
    cache = cfg.cache_path
    name, centre, source, preset = resolve_place(cfg)
    frame = WorldFrame(centre[0], centre[1], cfg.chunk_size_m)
    chunks = frame.ring(cfg.chunks, *cfg.window)
    extent = frame.extent(chunks)
    bbox = frame.bbox_lonlat(extent, margin_m=50.0)
    out = Path(cfg.out) if cfg.out else Path("worlds") / name
    out = out.resolve()
    check_writable(out.parent)
    check_writable(cache)

    # one build of a folder at a time: a second process waits, then finds the first's world
    with folder_lock(out, lambda: progress("osm", 0.0, f"waiting for another build of {out.name}")):
        progress("osm", 0.0, "reading OSM data")
        with T.stage("osm"):
            osm_xml, osm_info = _osm_for(cfg, source, bbox, cache)
        tmp = out.parent / f"{out.name}.tmp-{os.getpid()}"
        # netconvert, cached by its inputs (not the elevation). With no world on disk to reuse,
        # it starts now, before the elevation source is opened (a cold start imports a lot)
        nc_key = cfg.fingerprint({"osm": osm_info["sha256"], "proj": frame.proj_string,
                                  "bbox": [round(b, 6) for b in bbox], "opts": sumo_net.NETCONVERT_VERSION_TAG,
                                  "only": "net"})
        nc = _Netconvert(sumo_net, osm_xml, tmp / NET_FILE, frame.proj_string, bbox,
                         cache / "net" / f"{nc_key}.net.xml", cache / "net" / f"{nc_key}.warnings.json")
        try:
            if force or load_world_json(out) is None:
                _start(nc, tmp, out, progress)
            progress("elevation", 0.0, "opening elevation")
            with T.stage("elevation_open"):
                elevation = open_elevation_source(cfg, preset, bbox)
            elev_info = elevation.info()
            if cfg.dem:
                elev_info = {**elev_info, "hashes": _dem_files_key(cfg)}
            scale = preset.traffic_scale if preset is not None else 1.0
            key = _build_key(cfg, osm_info["sha256"], elev_info, centre, scale)
            if not force and not nc.started:
                old = load_world_json(out)
                if old is not None and old.get("build_key") == key:
                    old["reused"] = True
                    old["out"] = str(out)
                    old["timings_s"] = {"total": round(time.perf_counter() - t_start, 3), "reused": True}
                    progress("done", 1.0, "world is up to date")
                    return old
            if not nc.started:
                _start(nc, tmp, out, progress)
            world = _build_into(tmp, cfg, frame, chunks, extent, bbox, osm_xml, osm_info, source,
                                elevation, elev_info, key, name, nc, T, progress, read_planes(heights))
            world["timings_s"]["total"] = round(time.perf_counter() - t_start, 3)
            world["traffic"] = {"scale": scale, "note": TRAFFIC_NOTE}
            write_text(tmp / "world.json", json.dumps(world, indent=1))
            _swap_into_place(tmp, out)
            if heights is not None:
                merge_planes(heights, read_planes(out / PLANES_FILE))
        except BaseException:
            nc.kill()
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        world["out"] = str(out)
        progress("done", 1.0, f"world written to {out}")
        return world


NET_FILE = "net/world.net.xml"
TRAFFIC_NOTE = ("the named traffic densities (light/normal/dense) are multiplied by scale "
                "(the preset's traffic_scale); a density in vehicles/km2 is taken as it is")
PLANES_FILE = "road_planes.npz"


def planes_to_register(planes: dict, net, extent) -> dict:
    """The junction planes a build registers: all its nodes', those near and beyond the
    extent's edge too, so that a lane of an edge chunk reaching into a window's chunk meets the
    window's roads there (registered only 300 m or more inside the extent, Monaco's window
    (-2, -1) gave 13 % of the lane points it shares with the world other heights, up to 2.2 m,
    and such lanes up to 0.6 m). But not the ends of a bridge's deck that reaches out of the
    extent: a deck's height is set along its whole length (straight between where it meets the
    ground, clear of the roads under it), and beyond the extent the network is cut, so it
    does not have all the roads the deck must clear there (Portland's ramp 48785401, its deck
    350 m on past the world's edge, put its start 2.9 m lower than a build around it; the
    windows kept that, and the deck crossed NW Northrup Street 0.3 m over its lanes)."""
    x0, y0, x1, y1 = extent
    skip = set()
    for e in net.edges.values():
        if e.bridge and e.function == "normal" and e.lanes:
            P = np.vstack([ln.shape[:, :2] for ln in e.lanes])
            if ((P[:, 0] < x0) | (P[:, 0] > x1) | (P[:, 1] < y0) | (P[:, 1] > y1)).any():
                skip.update((e.from_node, e.to_node))
    return {j: p for j, p in planes.items() if j not in skip}


def read_planes(path) -> dict | None:
    """A road heights register: node id -> junction plane (x0, y0, z0, gx, gy), the plane
    z0 + gx (x - x0) + gy (y - y0) that the ends of the node's roads lie on. ``road_planes.npz``
    holds ``ids`` (strings) and ``planes`` (n, 5). None if there is none, or it cannot be read."""
    if path is None or not Path(path).is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as d:
            ids, planes = d["ids"], np.asarray(d["planes"], dtype=float)
    except (OSError, ValueError, KeyError):
        return None
    if planes.ndim != 2 or planes.shape[1] != 5 or len(ids) != len(planes):
        return None
    return {str(j): tuple(p) for j, p in zip(ids.tolist(), planes.tolist())}


def write_planes(path, planes: dict) -> None:
    ids = sorted(planes)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, ids=np.array(ids, dtype=str),
                     planes=np.array([planes[j] for j in ids], dtype=float).reshape(-1, 5))


def merge_planes(path, new: dict | None) -> None:
    """Add the planes of ``new`` whose nodes ``path``'s register has not got (the first build
    to register a node fixes it)."""
    if not new:
        return
    have = read_planes(path) or {}
    add = {j: p for j, p in new.items() if j not in have}
    if add:
        write_planes(path, {**have, **add})


def _start(nc, tmp: Path, out: Path, progress) -> None:
    """A fresh temporary world folder, and netconvert (or its cached output) into it."""
    remove_stale_temps(out.parent, out.name)
    if tmp.exists():
        shutil.rmtree(tmp)
    (tmp / "net").mkdir(parents=True)
    if not nc.cached:
        progress("netconvert", 0.0, "building the SUMO network (netconvert)")
    nc.start()


def _swap_into_place(tmp: Path, out: Path) -> None:
    old = None
    if out.exists():
        old = out.parent / f"{out.name}.tmp-old-{os.getpid()}"
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


#: the natural ground under the roads reaches this far beyond the world's extent (m)
ROAD_GROUND_MARGIN_M = 400.0
#: the elevation source covers this much beyond the extent (the bbox: 50 m, checked at the start)
COVERED_MARGIN_M = 45.0


def road_ground(natural, elevation, frame, margin: float = ROAD_GROUND_MARGIN_M):
    """The natural ground under the roads: the terrain grid ``natural`` (over the extent)
    grown by ``margin`` on its own lattice, the nodes beyond the extent sampled from the
    elevation source where it covers them, else the grid's border (clamped). A lane whose
    middle is in the world reaches out of it (30 m in Monaco, 300 m in Lauf); a window built
    beyond the edge later samples the same nodes, so both builds give such a lane the same
    heights. (Clamped at the border, a Monaco lane 28 m past the world's west edge followed
    the border column's heights down a slope and ended 5 m under its junction; the window
    built there kept that chunk's lane, and the car ran into the step at 10 m/s.)"""
    from .terrain import TerrainGrid

    sp = natural.spacing
    k = int(math.ceil(margin / sp))
    ny, nx = natural.z.shape
    x0, y0 = natural.xmin - k * sp, natural.ymin - k * sp
    xs, ys = x0 + np.arange(nx + 2 * k) * sp, y0 + np.arange(ny + 2 * k) * sp
    X, Y = np.meshgrid(xs, ys)
    z = np.asarray(natural.sample(X, Y), dtype=float)          # (beyond the extent: clamped)
    z[k:k + ny, k:k + nx] = natural.z
    ex0, ey0 = natural.xmin, natural.ymin
    ex1, ey1 = ex0 + (nx - 1) * sp, ey0 + (ny - 1) * sp
    for pad in (margin, COVERED_MARGIN_M):
        out = (X < ex0) | (X > ex1) | (Y < ey0) | (Y > ey1)
        out &= (X >= ex0 - pad) & (X <= ex1 + pad) & (Y >= ey0 - pad) & (Y <= ey1 + pad)
        lon, lat = frame.to_lonlat(X[out], Y[out])
        try:
            zo = np.asarray(elevation.sample(lon, lat), dtype=float)
        except (DataError, InputError):
            continue            # (not all covered: the nodes of the bbox alone)
        z[out] = np.where(np.isfinite(zo), zo, z[out])
        break
    return TerrainGrid(x0, y0, sp, z)


# ---------------------------------------------------------------------------------------
def _build_into(tmp: Path, cfg, frame, chunks, extent, bbox, osm_xml, osm_info, source,
                elevation, elev_info, key, name, nc, T: Timer, progress, pinned=None) -> dict:
    q = QUALITY[cfg.quality]
    spacing = cfg.spacing
    bounds = [frame.chunk_bounds(i, j) for i, j in chunks]
    net_rel = NET_FILE
    gc_frozen = gc_was_on = False
    try:
        # -- meanwhile (netconvert has the other core): all that needs no network ---------
        from .buildings import plan_buildings           # (imported once netconvert runs)
        from .roads import _road_lanes as road_lanes, build_roads, carriageway_parts, junction_gaps
        from .scenery import plan_scenery
        from .terrain import TerrainGrid, sample_grid
        import scipy.sparse.linalg  # noqa: F401  (the junction planes' solver, 12 ms to import)

        progress("terrain", 0.0, "sampling terrain")
        with T.stage("terrain_sample"):
            grid = sample_grid(frame, elevation, extent, spacing)
            natural = TerrainGrid(grid.xmin, grid.ymin, grid.spacing, grid.z.copy())
            roads_ground = road_ground(natural, elevation, frame)
        progress("features", 0.0, "reading buildings and scenery")
        with T.stage("features"):
            feats = _read_features(source, osm_xml, frame, bbox, cfg.cache_path)
        progress("buildings", 0.0, "extruding buildings")
        with T.stage("buildings_plan"):
            bplan = plan_buildings(feats, bounds)
        progress("scenery", 0.0, "placing scenery")

        def scenery_plan():
            return plan_scenery(feats, bplan.all_footprints, bounds, density=q["scenery_density"], seed=0)

        splan = None
        if nc.running():            # else the scenery process plans it, beside the roads
            with T.stage("scenery_plan"):
                splan = scenery_plan()
        for i, j in chunks:
            (tmp / "chunks" / f"{i}_{j}").mkdir(parents=True)
        buildings = _Buildings(chunks, bounds, bplan, grid)
        with T.stage("buildings_prepare"):      # the files but the heights, chunk by chunk
            for k in range(len(chunks)):        # while netconvert runs (else where written)
                if not nc.running():
                    break
                buildings.prepare(k, tmp)
        streams = _Streams(_parallel(), grid, q["road_step_m"])
        # -- the network, read while netconvert writes it --------------------------------
        progress("roads", 0.0, "meshing roads")
        gc_frozen = _gc_freeze()        # (again before the forks)
        # no collections from here to the end, in this process and in the forked ones: the
        # young objects of the meshing and the writing are freed by their counts, and the
        # collector's passes over them cost Helsinki's critical path 17 ms (re-enabled below)
        gc_was_on = gc.isenabled()
        gc.disable()
        with T.stage("net_read"):
            net = nc.read_net()
        counts = net.counts()
        if counts["road_edges"] == 0:
            raise DataError(f"no drivable road in the area (bbox {bbox[0]:.5f},{bbox[1]:.5f},{bbox[2]:.5f},{bbox[3]:.5f})")

        # -- after the network: three streams on the two cores (see _Streams) -----------
        with T.stage("roads"):      # the lanes by edge, used by both streams: made once, before the fork
            road_lanes(net)
            junction_gaps(net)
        # the buildings' passages under them (no building stands on a road: buildings.py) are
        # cut where the buildings are written: with a second process, cosim-layers alone (from
        # the network, beside the roads: 0.12 s of Helsinki's build that came before the fork)
        in_layers = streams.parallel
        if not in_layers:
            with T.stage("buildings_passages"):
                buildings.cut_passages(carriageway_parts(net), natural.sample)
        if gc_frozen:
            gc.freeze()
        with streams:
            streams.fork("cosim-layers", lambda: _layers(tmp, chunks, net, splan or scenery_plan, grid,
                                                         buildings, streams, natural.sample))
            with T.stage("roads"):  # the levelling support: levelled here or in cosim-layers
                roads = build_roads(net, roads_ground.sample, q["road_step_m"],
                                    on_support=lambda pts, hw, car, tris, hold: streams.level(
                                        pts, hw, car, tris, hold, T),
                                    pinned=pinned, surfaces=streams.surfaces)
            write_planes(tmp / PLANES_FILE, planes_to_register(roads.planes, net, extent))
            T.t["roads"] = round(T.t["roads"] - T.t.get("terrain_level", 0.0), 3)
            with T.stage("road_tiles_plan"):
                road_tiles = _RoadTiles(chunks, bounds, roads, TILE_M)
            streams.fork("cosim-tiles", lambda: road_tiles.write_claimed(tmp, streams))
            progress("write", 0.0, "writing chunks")
            with T.stage("write"):
                tiles = road_tiles.write_claimed(tmp, streams)          # what nobody has taken
                with T.stage("terrain_wait"):
                    streams.wait_terrain()
                entries = _write_terrain(tmp, chunks, bounds, grid)
                bfiles = {} if in_layers else buildings.write_claimed(tmp, streams)
            # netconvert writes the rest of its file (connections) meanwhile: only now check
            # that it succeeded (and cache its output)
            with T.stage("netconvert_wait"):
                warnings = nc.finish(T)
            with T.stage("streams_wait"):
                lout, t2 = streams.results(
                    lambda: _layers(tmp, chunks, net, splan or scenery_plan, grid, buildings, streams,
                                    natural.sample),
                    lambda: [])
    finally:
        nc.kill()       # only if still running: an error above
        if gc_frozen:
            gc.unfreeze()
        if gc_was_on:
            gc.enable()
    T.t.update(lout["timings"])
    lev = streams.lev if streams.lev is not None else lout["levelling"]
    bfiles.update(lout["buildings"])
    for k, t in tiles + t2:
        entries[k]["tiles"].update(t)
    for k, (e, se) in enumerate(zip(entries, lout["chunks"])):
        cdir = f"chunks/{e['i']}_{e['j']}"
        be = bfiles[k]
        for t, f in be["tiles"].items():
            e["tiles"].setdefault(t, {}).update(f)
        e["tiles"] = {t: dict(sorted(e["tiles"][t].items())) for t in sorted(e["tiles"])}
        e["files"] = {"terrain": e["files"]["terrain"],
                      "tiles": sorted(v for t in e["tiles"].values() for v in t.values()),
                      "roads_index": f"{cdir}/roads.json", **be["files"], **se["files"]}
        e["counts"] = {"buildings": be["buildings"], "scenery": se["scenery"]}
    progress("write", 1.0, "chunks written")
    # -- counts and report ---------------------------------------------------------------
    fc = feats.counts()
    nb, n_tag, n_lev, n_pass = lout["building_counts"]
    scen_counts = lout["kinds"]
    zs = grid.z
    world = {
        "format": "cosim-world", "format_version": FORMAT_VERSION, "generator": f"cosim netgen {NETGEN_VERSION}",
        "name": name, "build_key": key,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "center": {"lat": frame.center_lat, "lon": frame.center_lon},
        "chunk_size_m": frame.chunk_size_m, "tile_size_m": TILE_M, "rings": cfg.chunks,
        "extent_m": list(extent), "bbox_lonlat": {"south": bbox[0], "west": bbox[1], "north": bbox[2], "east": bbox[3]},
        "projection": {"proj": frame.proj_string, "net_offset": list(frame.net_offset),
                       "note": "x, y = proj(lon, lat) + net_offset; SUMO's network uses the same (see net_file <location>)"},
        "net_file": net_rel,
        "road_planes": {"file": PLANES_FILE, "pinned": roads.stats.get("planes_pinned", 0),
                        "note": "junction planes (ids; planes: x0, y0, z0, gx, gy) of the network's "
                                "nodes but the ends of a bridge's deck that reaches out of the extent; "
                                "in the world a streamed window starts from, also those its windows "
                                "added"},
        "tunnels": sorted(e.id for e in net.edges.values() if e.function == "normal" and e.tunnel),
        "stacked_over_lanes": sorted(ln.id for e in roads.stacked_over for ln in net.edges[e].lanes),
        "terrain": {"format": "npy-float32-grid", "spacing_m": spacing,
                    "layout": "chunks[].files.terrain: z[row, col] at x = bounds_m[0] + col*spacing_m, y = bounds_m[1] + row*spacing_m; row 0 = south; both edges included (shared with neighbours)",
                    "origin_m": [grid.xmin, grid.ymin], "shape": list(grid.z.shape),
                    "z_range_m": [round(float(zs.min()), 2), round(float(zs.max()), 2)],
                    "datum": elev_info.get("datum", "elevation source's vertical datum"),
                    "road_levelling": lev},
        "chunks": entries,
        "counts": {**counts, "buildings": nb, "buildings_height_from_tags": n_tag,
                   "buildings_height_from_levels": n_lev, "building_passages": n_pass,
                   "trees": scen_counts.get("tree", 0), "street_lamps": scen_counts.get("street_lamp", 0),
                   "traffic_signal_poles": scen_counts.get("traffic_signal", 0),
                   "stop_signs": scen_counts.get("stop_sign", 0), "give_way_signs": scen_counts.get("give_way_sign", 0),
                   "benches": scen_counts.get("bench", 0),
                   "osm_features": fc, "road_faces": roads.stats["faces"],
                   "road_gaps_filled": roads.stats.get("lane_end_gaps_filled", 0),
                   "road_points_on_junction_planes": roads.stats.get("own_plane_points", 0)},
        "sources": {
            "osm": {**{k: v for k, v in source.items()}, "sha256": osm_info["sha256"],
                    "licence": "ODbL 1.0", "attribution": "© OpenStreetMap contributors"},
            "elevation": elev_info,
        },
        "netconvert_warnings": warnings,
        "quality": cfg.quality,
        "window": list(cfg.window),
        "config": {k: v for k, v in cfg.to_dict().items() if k not in ("out", "window")},
        "timings_s": dict(T.t),
    }
    return world


def _is_pbf(f: Path) -> bool:
    return f.name.lower().endswith(".pbf") and f.is_file()


def _read_features(source: dict, osm_xml: Path, frame, bbox, cache: Path):
    """Buildings and scenery, read from the OSM source itself when it is PBF (read twice as
    fast as XML), else, or when the PBF is not in the id order pyosmium's area assembly
    needs (an edited extract), from the whole source converted to sorted XML."""
    from .osm_features import extract_features
    from .osm_file import to_osm_xml

    f = Path(source.get("file") or osm_xml)
    if source["kind"] in ("preset", "file") and _is_pbf(f):
        try:
            return extract_features(f, frame, bbox)
        except DataError:       # "Way IDs out of order": the XML conversion is sorted
            osm_xml, _ = to_osm_xml(f, cache)
    return extract_features(osm_xml, frame, bbox)


# ---------------------------------------------------------------------------------------
# netconvert
# ---------------------------------------------------------------------------------------
class _Netconvert:
    """netconvert in the background (:meth:`start`), its output cached by its inputs.

    The network is read while netconvert is still writing it (see
    :func:`netgen.roadnet.read_net_while_written`); :meth:`finish` then checks that it
    succeeded and caches its output. With a cached network nothing runs."""

    def __init__(self, sumo_net, osm_xml, net_file, proj, bbox, cache: Path, warn: Path):
        self.sumo_net, self.osm_xml, self.net_file, self.proj, self.bbox = sumo_net, osm_xml, net_file, proj, bbox
        self.cache, self.warn = cache, warn
        self.cached = cache.exists() and warn.exists()
        self.proc = self.errf = None
        self.started = False
        self.t_end = None

    def start(self) -> None:
        self.started = True
        if self.cached:
            shutil.copyfile(self.cache, self.net_file)
            return
        self.t0 = time.perf_counter()
        self.proc, self.errf = self.sumo_net.start_netconvert(
            self.osm_xml, self.net_file, self.proj, self.bbox, log=self.net_file.parent / "netconvert.log")
        # its exit time, for its timing: a thread waits for it (the build's own checks come
        # when the build is free, up to a second later)
        import threading

        def watch(proc=self.proc):
            proc.wait()
            self.t_end = self.t_end or time.perf_counter()

        threading.Thread(target=watch, daemon=True, name="netconvert-watch").start()

    def read_net(self):
        """The network without its internal junctions (nothing meshes them); its internal
        lanes are kept (the vehicle ones are part of their junction's surface)."""
        from .roadnet import read_net, read_net_while_written

        if self.proc is None:
            return read_net(self.net_file, internal_junctions=False)
        try:
            return read_net_while_written(self.net_file, self.proc, internal_junctions=False)
        except Exception:           # netconvert failed (or wrote garbage): finish() says why
            self.finish()
            return read_net(self.net_file, internal_junctions=False)

    def finish(self, T: Timer | None = None) -> dict:
        """netconvert's grouped warnings; raises DataError/BuildError if it failed."""
        if self.proc is None:
            if T is not None:
                T.t["netconvert"] = 0.0
            return json.loads(self.warn.read_text())
        proc, self.proc = self.proc, None
        warnings = self.sumo_net.finish_netconvert(proc, self.errf, self.net_file)
        if T is not None:       # its run time, to its exit
            T.t["netconvert"] = round((self.t_end or time.perf_counter()) - self.t0, 3)
        with atomic_path(self.cache) as p:
            shutil.copyfile(self.net_file, p)
        write_text(self.warn, json.dumps(warnings))
        return warnings

    def running(self) -> bool:
        """Still running? (Its exit time is noted by the thread that waits for it.)"""
        return self.proc is not None and self.proc.poll() is None

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait()
            self.errf.close()
            self.proc = None


# ---------------------------------------------------------------------------------------
# the scenery stream
# ---------------------------------------------------------------------------------------
def _parallel() -> bool:
    """More processes help when there is a second core and processes can be forked (and
    this is not a daemonic multiprocessing worker, which may not have children)."""
    import multiprocessing as mp

    try:
        ncpu = len(os.sched_getaffinity(0))
    except AttributeError:          # not Linux
        ncpu = os.cpu_count() or 1
    return ncpu >= 2 and "fork" in mp.get_all_start_methods() and not mp.current_process().daemon


def _gc_freeze() -> bool:
    """Move every object made so far (the network, features, plans: millions) out of the
    garbage collector's sight until :func:`gc.unfreeze`: without this, each full collection
    after the network is read scans them all, in this process and in each forked one (where
    it also copies the pages it touches), about 0.2 s each on a city. Nothing is frozen if
    the caller froze objects itself (returns whether this froze)."""
    if gc.get_freeze_count():
        return False
    gc.freeze()
    return True


def _die_with_parent() -> None:
    """Linux: have the kernel kill this process when its parent dies (a killed build leaves
    no worker writing into a folder that the next build removes)."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class _Streams:
    """The work after netconvert, on both cores: forked processes and what they share.

    Three streams: this process meshes the roads and writes the terrain; a child forked
    right after the network is read (``cosim-layers``) makes the junctions' surfaces for
    this process, builds the carriageway, cuts the buildings' passages, places the
    scenery, levels the terrain (the roads' levelling support comes through a pipe as soon
    as the meshing has it if cosim-layers is waiting for it, :meth:`claim_level`; else
    this process levels then, :meth:`level`) and writes the scenery and the buildings; a
    child forked once the roads are meshed (``cosim-tiles``) writes road tiles. Forked
    children inherit everything they need and return small dicts through a pipe. The
    levelled heights go to the other processes through shared memory (allocated before
    the forks) once they are final (:meth:`wait_terrain`). Road tiles (by chunk and tile
    column) are taken one unit at a time by whoever is free of this process and
    cosim-tiles (:meth:`next_index`). Without a second core (or without fork) nothing is
    forked and this process does it all, in order (the passages before the roads).

    An error in a child comes back as the error of the build; leaving the ``with`` block
    early kills the children, and the kernel kills them if this process is killed."""

    def __init__(self, parallel: bool, grid, road_step: float = 2.5):
        self.parallel = parallel
        self.grid = grid
        self.road_step = road_step
        self._surf_sender = None
        self.children = []
        self.lev = None             # the levelling's figures, where it ran
        self.road_pts = None        # the road surface where cars drive (the buildings' passages)
        self._in_child = self._have_terrain = False
        if parallel:
            import multiprocessing as mp

            self.ctx = mp.get_context("fork")
            self._z = self.ctx.RawArray("d", grid.z.size)
            self._ready = self.ctx.Event()
            self._claims = self.ctx.Array("i", 3)     # next road-tile unit, building chunk; leveller
            self._sup_r, self._sup_w = self.ctx.Pipe(duplex=False)     # the levelling support
            self._surf_r, self._surf_w = self.ctx.Pipe(duplex=False)   # the roads' surfaces
        else:
            self._claims = [0, 0, 0]

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        for proc, _ in self.children:
            if proc.is_alive():
                proc.kill()
            proc.join()
        return False

    # -- forking ---------------------------------------------------------------------------
    def fork(self, name: str, fn) -> None:
        """Run fn() in a forked child (nothing happens without parallelism)."""
        if not self.parallel:
            return
        res_r, res_w = self.ctx.Pipe(duplex=False)
        proc = self.ctx.Process(target=self._child_main, args=(fn, res_w), daemon=True, name=name)
        proc.start()
        res_w.close()
        self.children.append((proc, res_r))

    def _child_main(self, fn, res_w) -> None:
        _die_with_parent()
        self._in_child = True
        try:
            out = ("ok", fn())
        except BaseException as e:      # reported to the parent, which raises it
            if not isinstance(e, (BuildError, DataError, InputError)):
                e = BuildError(f"{type(e).__name__} in a build process: {e}")
            out = ("error", e)
        res_w.send(out)
        res_w.close()

    def results(self, *serial) -> list:
        """The children's results in the order they were forked; without children, the
        `serial` functions are called here instead."""
        if not self.parallel:
            return [fn() for fn in serial]
        out = []
        for proc, res_r in self.children:
            try:
                status, value = res_r.recv()
            except EOFError:
                proc.join()
                raise BuildError(f"build process {proc.name} died (exit code {proc.exitcode})") from None
            proc.join()
            if status == "error":
                raise value
            out.append(value)
        return out

    # -- sharing -----------------------------------------------------------------------------
    def level(self, pts, hw, car, tris, hold, T: Timer) -> None:
        """The roads' levelling support is known. If cosim-layers is already waiting for it
        (it claimed the levelling, :meth:`claim_level`), send it there and go on meshing;
        else level here, now (as without children), so that cosim-layers, busy with the
        scenery, finds the terrain ready."""
        self.road_pts = pts[car]
        if self.parallel and self.next_index("level"):
            self._sup_w.send((pts, hw, car, tris, hold))
            return
        if self.parallel:       # (cosim-layers writes the buildings: it needs the road surface)
            self._sup_w.send((self.road_pts,))
        self._level(pts, hw, car, tris, hold, T)

    def _level(self, pts, hw, car, tris, hold, T: Timer) -> None:
        from .terrain import level_under_roads

        with T.stage("terrain_level"):
            self.lev = level_under_roads(self.grid, pts, hw, clear=car, tris=tris, hold=hold)
        if self.parallel:       # hand the heights to the others (shared memory, allocated before the forks)
            np.frombuffer(self._z, dtype=np.float64)[:] = self.grid.z.ravel()
            self._ready.set()
        self._have_terrain = True

    def receive_support(self) -> None:
        """In cosim-layers, first thing: a thread takes the support in as soon as it is sent
        (the sender would otherwise block on the full pipe)."""
        import threading

        if self.parallel and self._in_child:
            self._support = []
            self._receiver = threading.Thread(target=lambda: self._support.append(self._sup_r.recv()),
                                              daemon=True)
            self._receiver.start()

    def send_surfaces(self, net) -> None:
        """In cosim-layers, first thing: the junctions' and walking areas' polygons and their
        triangulations (``roads.surface_meshes``: only the network needed), for this process's
        roads (:meth:`surfaces`), which reaches them after fitting the roads' heights. Sent by a
        thread, so that cosim-layers goes on to the scenery meanwhile."""
        import pickle
        import threading

        from .roads import surface_meshes

        if not (self.parallel and self._in_child):
            return
        sm = surface_meshes(net, self.road_step)
        # the thousands of polygons as one array and their lengths (pickled one by one, 5,000
        # small arrays took 13 ms here and as long again to unpickle in the roads' process)
        lens = np.array([len(p) for p in sm["polys"]], dtype=np.int64)
        flat = np.concatenate(sm["polys"]) if len(lens) else np.zeros((0, 2))
        data = pickle.dumps(dict(sm, polys=(flat, lens)), protocol=pickle.HIGHEST_PROTOCOL)
        self._surf_sender = threading.Thread(target=self._surf_w.send_bytes, args=(data,), daemon=True)
        self._surf_sender.start()

    def surfaces_sent(self) -> None:
        """In cosim-layers, before it ends: the surfaces are through the pipe."""
        if self._surf_sender is not None:
            self._surf_sender.join()

    def surfaces(self):
        """In this process: cosim-layers' ``roads.surface_meshes`` (waits for them), or None
        without it (the roads make them themselves)."""
        import pickle

        if not self.parallel or self._in_child or not self.children:
            return None
        proc, res_r = self.children[0]
        while not self._surf_r.poll(0.02):
            if not proc.is_alive():
                self._raise_from(proc, res_r)
        sm = pickle.loads(self._surf_r.recv_bytes())
        flat, lens = sm["polys"]
        ends = np.cumsum(lens).tolist()
        sm["polys"] = [flat[a:b] for a, b in zip([0] + ends[:-1], ends)]     # (views: read only)
        return sm

    def claim_level(self) -> bool:
        """In cosim-layers, once it has nothing else to do before the terrain but what can
        wait for the support (the buildings' passages): claim the levelling unless the roads'
        process already levels (it does when it has the support first). Whichever process is
        free first levels; True if this one does (:meth:`level_claimed`)."""
        return self.parallel and self._in_child and not self._have_terrain and not self.next_index("level")

    def level_claimed(self, T: Timer) -> None:
        """After :meth:`claim_level`: wait for the support and level."""
        with T.stage("terrain_support_wait"):
            self._receiver.join()
        if not self._support:
            raise BuildError("the roads' levelling support never came")
        self._level(*self._support[-1], T)

    def road_points(self) -> np.ndarray:
        """The road surface points where cars drive, (n, 3): in cosim-layers, from the support
        the roads' process sent (all of it if this process levels, else these points)."""
        if self.parallel and self._in_child:
            self._receiver.join()
            if not self._support:
                raise BuildError("the roads' surface never came")
            m = self._support[-1]
            return m[0][m[2]] if len(m) == 5 else m[0]
        return self.road_pts

    def wait_terrain(self) -> None:
        """Block until the levelled heights are in (then self.grid has them). In this
        process, an error of cosim-layers (which levels) is raised instead."""
        if not self.parallel or self._have_terrain:
            return
        if self._in_child:
            self._ready.wait()
        else:
            while not self._ready.wait(0.02):       # (cosim-layers may be levelling)
                proc, res_r = self.children[0]
                if not proc.is_alive() and not self._ready.is_set():
                    self._raise_from(proc, res_r)
        self.grid.z = np.frombuffer(self._z, dtype=np.float64).reshape(self.grid.z.shape)
        self._have_terrain = True

    @staticmethod
    def _raise_from(proc, res_r):
        """A child that ended: raise its error (or that it died)."""
        try:
            status, value = res_r.recv()
        except EOFError:
            proc.join()
            raise BuildError(f"build process {proc.name} died (exit code {proc.exitcode})") from None
        if status == "error":
            raise value
        raise BuildError(f"build process {proc.name} ended before its work was done")

    def next_index(self, what: str) -> int:
        """The next unit of `what` ("roads" or "buildings"; "level": who levels) to write:
        0, 1, 2, ... across all processes, so that each unit is written once, by whoever
        was free."""
        c = ("roads", "buildings", "level").index(what)
        if not self.parallel:
            k = self._claims[c]
            self._claims[c] += 1
            return k
        with self._claims.get_lock():
            k = self._claims[c]
            self._claims[c] += 1
            return k


def _layers(tmp: Path, chunks, net, splan, grid, buildings, streams: _Streams, ground) -> dict:
    """The carriageway, the scenery placed on it and on the final terrain, written; then the
    building chunks (with a second process, all of them, their passages cut here first: see
    _build_into; else those that nobody has taken yet). Returns file names, counts, timings.
    `splan` is the scenery plan, or the function that makes it; `ground` the natural
    terrain's heights (vectorised)."""
    from .roads import carriageway_parts
    from .scenery import PolygonSet, finish_scenery, place_scenery, write_chunk_scenery

    T = Timer()
    streams.receive_support()
    with T.stage("surfaces"):       # (for the roads' process, which needs them in a while)
        streams.send_surfaces(net)
    if callable(splan):
        with T.stage("scenery_plan"):
            splan = splan()
    with T.stage("carriageway"):
        parts = carriageway_parts(net)
        road = PolygonSet(parts)
    with T.stage("scenery_place"):
        placed = place_scenery(splan, road)
    # the levelling claimed (if the roads' support is not in yet: else the roads' process
    # levels), the passages cut while the support comes, then levelled here
    mine = streams.claim_level()
    if streams.parallel:
        with T.stage("buildings_passages"):
            buildings.cut_passages(parts, ground)
    if mine:
        streams.level_claimed(T)
    with T.stage("scenery_terrain_wait"):
        streams.wait_terrain()
    with T.stage("scenery_finish"):
        sres = finish_scenery(placed, grid.sample)
    chunks_out, kinds = [], {}
    with T.stage("scenery_write"):
        for (i, j), r in zip(chunks, sres):
            cdir = f"chunks/{i}_{j}"
            sf = write_chunk_scenery(r, tmp / cdir)
            chunks_out.append({"files": {f"scenery_{k}": f"{cdir}/{v}" for k, v in sf.items() if v},
                               "scenery": len(r.instances)})
            for inst in r.instances:
                kinds[inst["kind"]] = kinds.get(inst["kind"], 0) + 1
    with T.stage("buildings_in_layers"):
        bfiles = buildings.write_claimed(tmp, streams) if streams.parallel else {}
    streams.surfaces_sent()
    return {"chunks": chunks_out, "kinds": kinds, "buildings": bfiles, "timings": dict(T.t),
            "levelling": streams.lev, "building_counts": buildings.counts()}


# ---------------------------------------------------------------------------------------
# writing
# ---------------------------------------------------------------------------------------
def _write_terrain(tmp: Path, chunks, bounds, grid) -> list:
    """Each chunk's terrain.npy; returns the chunk entries of world.json, to be completed."""
    entries = []
    for (i, j), b in zip(chunks, bounds):
        cdir = f"chunks/{i}_{j}"
        np.save(tmp / cdir / "terrain.npy", grid.cut(b).astype(np.float32))
        entries.append({"i": i, "j": j, "bounds_m": list(b), "files": {"terrain": f"{cdir}/terrain.npy"},
                        "tiles": {}, "counts": {}})
    return entries


class _Buildings:
    """The planned buildings, lifted onto the final terrain and written chunk by chunk
    (:meth:`write_claimed`; by cosim-layers where there is a second core): per chunk one OBJ per tile (a group
    per building, in the tile of its centroid), buildings.glb and buildings.json.

    What does not depend on the terrain (the tiles' face text, the GLB's indices and scene,
    buildings.json but the bases) is made by :meth:`prepare`, while netconvert runs when it
    does; once the terrain is final only the positions and bases are left to write."""

    def __init__(self, chunks, bounds, bplan, grid):
        self.chunks, self.bounds, self.bplan, self.grid = chunks, bounds, bplan, grid
        self.layouts = None
        self.prepared = {}
        self.base = self.V = self.road_pts = None

    def counts(self) -> tuple:
        """(buildings, heights from tags, heights from levels, over a road) over all chunks."""
        recs = [r for r, bad in zip(self.bplan.records, self.bplan.failed) if not bad]
        return (len(recs), sum(1 for r in recs if r["height_source"] == "height"),
                sum(1 for r in recs if r["height_source"] == "building:levels"),
                sum(1 for r in recs if "passage_from_m" in r))

    def cut_passages(self, road_parts, ground=None) -> int:
        """The buildings' parts over the roads lifted or left out (:func:`netgen.buildings.cut_passages`),
        before the forks. The chunks prepared with a changed building are prepared again; the
        others' prepared files still hold (each chunk numbers its own vertices)."""
        from .buildings import chunk_layouts, cut_passages

        cut = cut_passages(self.bplan, road_parts, ground)
        if len(cut):
            if self.layouts is not None:
                self.layouts = chunk_layouts(self.bplan)
            for k in set(self.bplan.chunk[cut].tolist()):
                self.prepared.pop(k, None)
        return len(cut)

    def prepare(self, k: int, tmp: Path | None = None) -> None:
        """Chunk k's files but the heights (once); with `tmp`, make their tile folders."""
        from .buildings import chunk_layouts, glb_template, json_template
        from .meshio import obj_face_texts

        if k in self.prepared:
            return
        if self.layouts is None:
            self.layouts = chunk_layouts(self.bplan)
        lay = self.layouts[k]
        recs = [self.bplan.records[i] for i in lay.mine]
        tiles, glb = [], None
        if recs:
            t, nt = tile_index(np.array([rec["centroid"] for rec in recs]), self.bounds[k], TILE_M)
            vnum = np.arange(len(lay.vidx))         # gathered vertex numbers, not positions
            items = []
            for tt in np.unique(t):
                ks = np.flatnonzero(t == tt)
                vi, F, groups = _gather(vnum, lay.faces, lay.vstart, lay.fstart, ks, [recs[n]["id"] for n in ks])
                tiles.append((f"{int(tt) // nt}_{int(tt) % nt}", vi))
                items.append((F, groups))
            tiles = [(name, vi, text, F) for (name, vi), text, (F, _) in zip(tiles, obj_face_texts(items), items)]
            if tmp is not None:
                i, j = self.chunks[k]
                for name, _, _, _ in tiles:
                    (tmp / "chunks" / f"{i}_{j}" / "tiles" / name).mkdir(parents=True, exist_ok=True)
            glb = glb_template([r["id"] for r in recs], lay.faces, lay.vstart, lay.fstart, lay.material,
                               len(lay.vidx))
        self.prepared[k] = (tiles, glb, json_template(lay.bounds, recs, lay.stats))

    def lift(self) -> None:
        """Every building's base on the final terrain, and its vertices lifted by it (once)."""
        from .buildings import base_heights, lifted_vertices, raise_passages

        if self.V is not None:
            return
        self.base = base_heights(self.bplan, self.grid.sample)
        # (passages lower than a road's clearance over the road surface: raised, and their
        # chunks' files, prepared with the old underside, prepared again)
        raised = raise_passages(self.bplan, self.base, self.road_pts)
        for k in set(self.bplan.chunk[raised].tolist()):
            self.prepared.pop(k, None)
        self.V = lifted_vertices(self.bplan, self.base)

    def write_chunk(self, tmp: Path, k: int) -> dict:
        self.lift()
        self.prepare(k)
        tiles_p, glb, jt = self.prepared[k]
        lay = self.layouts[k]
        i, j = self.chunks[k]
        cdir = f"chunks/{i}_{j}"
        tiles, files = {}, {}
        if len(lay.mine):
            V = self.V[lay.vidx]
            batch = ObjBatch()
            for name, vi, text, F in tiles_p:
                rel = f"{cdir}/tiles/{name}/building.obj"
                batch.add_prepared(f"{tmp}/{rel}", V[vi], text)
                tiles[name] = {"building": rel}
            batch.write()
            for name, vi, _, F in tiles_p:          # (after the OBJs: their folders exist)
                write_collision_mesh(f"{tmp}/{cdir}/tiles/{name}/building.obj", V[vi], F)
            # buildings.obj would repeat the building tiles: the world has the tiles and the GLB
            write_file(tmp / cdir / "buildings.glb", glb.render(V))
            files["buildings_glb"] = f"{cdir}/buildings.glb"
        base = self.base[lay.mine].tolist()
        write_file(tmp / cdir / "buildings.json", jt.render([repr(b) for b in base]).encode())
        files["buildings_json"] = f"{cdir}/buildings.json"
        return {"files": files, "tiles": tiles, "buildings": len(lay.mine)}

    def write_claimed(self, tmp: Path, streams: _Streams) -> dict:
        """Write building chunks as long as there are chunks nobody has taken: {chunk: ...}.
        (In a child, waits for the levelled terrain first.)"""
        out = {}
        while True:
            k = streams.next_index("buildings")
            if k >= len(self.chunks):
                return out
            if self.V is None:
                streams.wait_terrain()
                self.road_pts = streams.road_points()
            out[k] = self.write_chunk(tmp, k)


def _gather(V, F, vstart, fstart, ks, names):
    """The pieces ks (each owning its own vertex and face ranges) as one mesh with groups."""
    vcnt = vstart[ks + 1] - vstart[ks]
    fcnt = fstart[ks + 1] - fstart[ks]
    vnew = np.cumsum(vcnt) - vcnt
    fnew = np.cumsum(fcnt) - fcnt
    vidx = np.repeat(vstart[ks] - vnew, vcnt) + np.arange(vcnt.sum())
    fidx = np.repeat(fstart[ks] - fnew, fcnt) + np.arange(fcnt.sum())
    Fo = F[fidx] + np.repeat(vnew - vstart[ks], fcnt)[:, None]
    groups = [(n, int(a), int(a + c)) for n, a, c in zip(names, fnew, fcnt)]
    return V[vidx], Fo, groups


class _RoadTiles:
    """The road pieces sorted into per-tile OBJ files of their class (a piece goes to the tile
    holding its centroid) and each chunk's roads.json index; written a chunk's tile column
    at a time by whichever process is free (:meth:`write_claimed`)."""

    def __init__(self, chunks, bounds, roads, tile: float):
        self.chunks, self.bounds = chunks, bounds
        self.nt = [tile_index(np.zeros((0, 2)), b, tile)[1] for b in bounds]     # tiles per side
        # per chunk, in order (class, part, tile, piece): (a, b, kind, part, pieces, V, F, face counts)
        self.items = [[] for _ in chunks]
        for kind, parts in roads.parts.items():
            for part in parts:
                self._sort_part(kind, part, tile)

    def _sort_part(self, kind, part, tile) -> None:
        from .buildings import chunk_index

        c = part.centroids
        ch = chunk_index(c[:, 0], c[:, 1], self.bounds)
        tt = np.full(len(c), -1)
        nts = {}
        for k in np.unique(ch[ch >= 0]):
            sel = ch == k
            tt[sel], nts[k] = tile_index(c[sel], self.bounds[k], tile)
        ok = np.flatnonzero(ch >= 0)
        if not len(ok):
            return
        # pieces in (chunk, tile, piece) order; each run of one (chunk, tile) is one item
        order = ok[np.lexsort((ok, tt[ok], ch[ok]))]
        grp = ch[order] * 1_000_000 + tt[order]
        starts = np.r_[0, np.flatnonzero(grp[1:] != grp[:-1]) + 1]
        ends = np.r_[starts[1:], len(order)]
        # every item's faces, its used vertices renumbered from 0 (one np.unique for all)
        fcnt = part.fstart[order + 1] - part.fstart[order]
        fidx = np.repeat(part.fstart[order] - (np.cumsum(fcnt) - fcnt), fcnt) + np.arange(fcnt.sum())
        fg = np.repeat(np.repeat(np.arange(len(starts)), ends - starts), fcnt)
        nv = len(part.vertices)
        uniq, inv = np.unique((fg[:, None] * nv + part.faces[fidx]).ravel(), return_inverse=True)
        vfirst = np.searchsorted(uniq // nv, np.arange(len(starts)))
        inv = inv.reshape(-1, 3) - vfirst[fg][:, None]
        V = part.vertices[uniq % nv]
        ffirst = np.r_[0, np.cumsum(np.add.reduceat(fcnt, starts))]
        vbound = np.r_[vfirst, len(uniq)]
        for g, (s0, s1) in enumerate(zip(starts, ends)):
            k = int(ch[order[s0]])
            t = int(tt[order[s0]])
            self.items[k].append((t // nts[k], t % nts[k], kind, part, order[s0:s1],
                                  V[vbound[g]:vbound[g + 1]], inv[ffirst[g]:ffirst[g + 1]], fcnt[s0:s1]))

    def tasks(self) -> list:
        """The units of writing: (chunk, tile column a) pairs, the busy chunks of a city
        being too big to leave to one process; roads.json goes with column 0."""
        return [(k, a) for k in range(len(self.chunks)) for a in range(self.nt[k])]

    def write_task(self, tmp: Path, k: int, col: int) -> dict:
        """Chunk k's road tiles of tile column `col` (and with column 0 its roads.json);
        returns {tile: {class: file}}."""
        i, j = self.chunks[k]
        cdir = f"chunks/{i}_{j}"
        files: dict = {}                # (a, b, kind) -> [(V, F, part, pieces, face counts)]
        for a, b, kind, part, pieces, V, F, pf in self.items[k]:
            if a == col:
                files.setdefault((a, b, kind), []).append((V, F, part, pieces, pf))
        batch = ObjBatch()
        tiles: dict = {}
        binary = []
        for (a, b, kind), items in sorted(files.items()):
            V, F, groups, off, foff = [], [], [], 0, 0
            for v, f, part, pieces, pf in items:
                V.append(v)
                F.append(f + off)
                end = (np.cumsum(pf) + foff).tolist()       # each piece's faces, in the file
                els, ids = part.elements, part.ids
                groups.extend((f"{els[p]}/{ids[p]}", e - n, e) for p, n, e in zip(pieces.tolist(), pf.tolist(), end))
                off += len(v)
                foff += len(f)
            rel = f"{cdir}/tiles/{a}_{b}/{kind}.obj"
            V, F = np.vstack(V), np.vstack(F)
            batch.add(f"{tmp}/{rel}", V, F, groups)
            if kind in COLLIDE_CLASSES:
                binary.append((f"{tmp}/{rel}", V, F))
            tiles.setdefault(f"{a}_{b}", {})[kind] = rel
        batch.write()
        for path, V, F in binary:               # (after the OBJs: their folders exist)
            write_collision_mesh(path, V, F)
        if col == 0:
            index = [{"id": part.ids[p], "element": part.elements[p], "class": kind,
                      "osm": [f"way/{w}" for w in part.osm[p]], "tile": f"{a}_{b}"}
                     for a, b, kind, part, pieces, _, _, _ in self.items[k] for p in pieces.tolist()]
            write_file(tmp / cdir / "roads.json",
                       json.dumps({"bounds": list(self.bounds[k]), "pieces": index}).encode())
        return tiles

    def write_claimed(self, tmp: Path, streams: _Streams) -> list:
        """Write tasks as long as there are tasks nobody has taken: [(chunk, tiles)]."""
        out = []
        tasks = self.tasks()
        while True:
            n = streams.next_index("roads")
            if n >= len(tasks):
                return out
            k, col = tasks[n]
            out.append((k, self.write_task(tmp, k, col)))
