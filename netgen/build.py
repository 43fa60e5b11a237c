"""Build a world: OSM + elevation -> SUMO network + chunked 3D layers + world.json.

Stages (timed; the report and ``world.json`` carry the figures):

1. resolve the place (preset, local OSM file, Overpass bbox) and the elevation source;
2. start netconvert in the background (the longest step), and meanwhile, on the other core,
   sample the terrain grid and read buildings and scenery from the OSM file;
3. read the network, mesh the roads, level the terrain under them;
4. extrude buildings onto the final terrain, place scenery;
5. write chunk files, then ``world.json`` last: the world is built in a temporary folder and
   renamed into place, so a killed build never leaves a folder that looks complete.

A rebuild with the same inputs finds ``world.json`` with the same build key and returns at
once; netconvert's output is also cached by its inputs (OSM content, options, projection).
"""
from __future__ import annotations

import datetime as _dt
import json
import os
import shutil
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from . import __version__ as NETGEN_VERSION
from ._atomic import atomic_path, check_writable, remove_stale_temps, write_text
from .config import QUALITY, WorldConfig
from .errors import BuildError, DataError, InputError
from .frame import WorldFrame
from .meshio import split_pieces, tile_index, write_obj

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
    from .osm_file import to_osm_xml

    if source["kind"] in ("preset", "file"):
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


def _build_key(cfg: WorldConfig, osm_sha: str, elev_info: dict, centre) -> str:
    stable = {k: v for k, v in elev_info.items() if k not in VOLATILE_INFO}
    extra = {"osm": osm_sha, "elev": json.dumps(stable, sort_keys=True, default=str),
             "centre": [round(centre[0], 7), round(centre[1], 7)], "format": FORMAT_VERSION,
             "code": NETGEN_VERSION}
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


def build_world(cfg: WorldConfig, progress=_noop, force: bool = False) -> dict:
    """Build (or reuse) the world described by `cfg`; returns the world.json dict."""
    cfg.validate()
    T = Timer()
    t_start = time.perf_counter()
    cache = cfg.cache_path
    name, centre, source, preset = resolve_place(cfg)
    frame = WorldFrame(centre[0], centre[1], cfg.chunk_size_m)
    chunks = frame.ring(cfg.chunks)
    extent = frame.extent(chunks)
    bbox = frame.bbox_lonlat(extent, margin_m=50.0)
    out = Path(cfg.out) if cfg.out else Path("worlds") / name
    out = out.resolve()
    check_writable(out.parent)
    check_writable(cache)

    progress("osm", 0.0, "reading OSM data")
    with T.stage("osm"):
        osm_xml, osm_info = _osm_for(cfg, source, bbox, cache)
    progress("elevation", 0.0, "opening elevation")
    with T.stage("elevation_open"):
        elevation = open_elevation_source(cfg, preset, bbox)
    elev_info = elevation.info()
    if cfg.dem:
        elev_info = {**elev_info, "hashes": _dem_files_key(cfg)}
    key = _build_key(cfg, osm_info["sha256"], elev_info, centre)
    if not force:
        old = load_world_json(out)
        if old is not None and old.get("build_key") == key:
            old["reused"] = True
            old["timings_s"] = {"total": round(time.perf_counter() - t_start, 3), "reused": True}
            progress("done", 1.0, "world is up to date")
            return old

    remove_stale_temps(out.parent)
    tmp = out.parent / f"{out.name}.tmp-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        world = _build_into(tmp, cfg, frame, chunks, extent, bbox, osm_xml, osm_info, source,
                            elevation, elev_info, key, name, T, progress)
        world["timings_s"]["total"] = round(time.perf_counter() - t_start, 3)
        write_text(tmp / "world.json", json.dumps(world, indent=1))
        _swap_into_place(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    world["out"] = str(out)
    progress("done", 1.0, f"world written to {out}")
    return world


def _swap_into_place(tmp: Path, out: Path) -> None:
    old = None
    if out.exists():
        old = out.parent / f"{out.name}.tmp-old-{os.getpid()}"
        os.replace(out, old)
    os.replace(tmp, out)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


# ---------------------------------------------------------------------------------------
def _build_into(tmp: Path, cfg, frame, chunks, extent, bbox, osm_xml, osm_info, source,
                elevation, elev_info, key, name, T: Timer, progress) -> dict:
    from . import sumo_net
    from .roadnet import read_net
    from .roads import build_roads
    from .terrain import level_under_roads, sample_grid

    q = QUALITY[cfg.quality]
    spacing = cfg.spacing
    (tmp / "net").mkdir()
    net_rel = "net/world.net.xml"
    net_file = tmp / net_rel
    # -- netconvert, cached by its inputs ----------------------------------------------
    nc_key = cfg.fingerprint({"osm": osm_info["sha256"], "proj": frame.proj_string,
                              "bbox": [round(b, 6) for b in bbox], "opts": sumo_net.NETCONVERT_VERSION_TAG,
                              "only": "net"})
    nc_cache = cfg.cache_path / "net" / f"{nc_key}.net.xml"
    nc_warn = cfg.cache_path / "net" / f"{nc_key}.warnings.json"
    proc = errf = None
    if nc_cache.exists() and nc_warn.exists():
        shutil.copyfile(nc_cache, net_file)
    else:
        progress("netconvert", 0.0, "building the SUMO network (netconvert)")
        t_nc = time.perf_counter()
        proc, errf = sumo_net.start_netconvert(osm_xml, net_file, frame.proj_string, bbox,
                                               log=tmp / "net" / "netconvert.log")
    # -- meanwhile: terrain and OSM features -------------------------------------------
    progress("terrain", 0.0, "sampling terrain")
    with T.stage("terrain_sample"):
        grid = sample_grid(frame, elevation, extent, spacing)
        raw = grid.z.copy()
    progress("features", 0.0, "reading buildings and scenery")
    with T.stage("features"):
        from .osm_features import extract_features

        feats = extract_features(osm_xml, frame, bbox)
    # -- network -----------------------------------------------------------------------
    with T.stage("netconvert_wait"):
        if proc is not None:
            warnings = sumo_net.finish_netconvert(proc, errf, net_file)
            T.t["netconvert"] = round(time.perf_counter() - t_nc, 3)
            with atomic_path(nc_cache) as p:
                shutil.copyfile(net_file, p)
            write_text(nc_warn, json.dumps(warnings))
        else:
            warnings = json.loads(nc_warn.read_text())
            T.t["netconvert"] = 0.0
    progress("roads", 0.0, "meshing roads")
    with T.stage("net_read"):
        net = read_net(net_file)
    counts = net.counts()
    if counts["road_edges"] == 0:
        raise DataError(f"no drivable road in the area (bbox {bbox[0]:.5f},{bbox[1]:.5f},{bbox[2]:.5f},{bbox[3]:.5f})")
    from .terrain import TerrainGrid

    natural = TerrainGrid(grid.xmin, grid.ymin, grid.spacing, raw)
    with T.stage("roads"):
        roads = build_roads(net, natural.sample, q["road_step_m"])
    with T.stage("terrain_level"):
        lev = level_under_roads(grid, roads.support_pts, roads.support_hw)
    # -- buildings and scenery on the final terrain --------------------------------------
    bounds = [frame.chunk_bounds(i, j) for i, j in chunks]
    progress("buildings", 0.0, "extruding buildings")
    with T.stage("buildings"):
        from .buildings import footprint_union, make_buildings

        bres = make_buildings(feats, grid.sample, bounds)
    progress("scenery", 0.0, "placing scenery")
    with T.stage("scenery"):
        from .scenery import make_scenery

        sres = make_scenery(feats, grid.sample, roads.carriageway, footprint_union(feats), bounds,
                            density=q["scenery_density"], seed=0)
    # -- write chunks --------------------------------------------------------------------
    progress("write", 0.0, "writing chunks")
    chunk_entries = []
    with T.stage("write"):
        for k, (i, j) in enumerate(chunks):
            chunk_entries.append(_write_chunk(tmp, i, j, bounds[k], grid, roads, bres[k], sres[k], TILE_M))
            progress("write", (k + 1) / len(chunks), f"chunk {i},{j}")
    # -- counts and report ---------------------------------------------------------------
    fc = feats.counts()
    nb = sum(len(r.records) for r in bres)
    n_tag = sum(1 for r in bres for rec in r.records if rec["height_source"] == "height")
    n_lev = sum(1 for r in bres for rec in r.records if rec["height_source"] == "building:levels")
    scen_counts: dict = {}
    for r in sres:
        for inst in r.instances:
            scen_counts[inst["kind"]] = scen_counts.get(inst["kind"], 0) + 1
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
        "terrain": {"format": "npy-float32-grid", "spacing_m": spacing,
                    "layout": "chunks[].files.terrain: z[row, col] at x = bounds_m[0] + col*spacing_m, y = bounds_m[1] + row*spacing_m; row 0 = south; both edges included (shared with neighbours)",
                    "origin_m": [grid.xmin, grid.ymin], "shape": list(grid.z.shape),
                    "z_range_m": [round(float(zs.min()), 2), round(float(zs.max()), 2)],
                    "datum": elev_info.get("datum", "elevation source's vertical datum"),
                    "road_levelling": lev},
        "chunks": chunk_entries,
        "counts": {**counts, "buildings": nb, "buildings_height_from_tags": n_tag,
                   "buildings_height_from_levels": n_lev,
                   "trees": scen_counts.get("tree", 0), "street_lamps": scen_counts.get("street_lamp", 0),
                   "traffic_signal_poles": scen_counts.get("traffic_signal", 0),
                   "stop_signs": scen_counts.get("stop_sign", 0), "give_way_signs": scen_counts.get("give_way_sign", 0),
                   "benches": scen_counts.get("bench", 0),
                   "osm_features": fc, "road_faces": roads.stats["faces"]},
        "sources": {
            "osm": {**{k: v for k, v in source.items()}, "sha256": osm_info["sha256"],
                    "licence": "ODbL 1.0", "attribution": "© OpenStreetMap contributors"},
            "elevation": elev_info,
        },
        "netconvert_warnings": warnings,
        "quality": cfg.quality,
        "timings_s": dict(T.t),
    }
    return world


def _write_chunk(tmp: Path, i, j, bounds, grid, roads, bres, sres, tile) -> dict:
    from .buildings import write_chunk_buildings
    from .scenery import write_chunk_scenery

    cdir = f"chunks/{i}_{j}"
    d = tmp / cdir
    d.mkdir(parents=True)
    files = {}
    np.save(d / "terrain.npy", grid.cut(bounds).astype(np.float32))
    files["terrain"] = f"{cdir}/terrain.npy"
    # roads: per tile, per class, pieces as OBJ groups
    tiles: dict = {}
    index = []
    xmin, ymin, xmax, ymax = bounds
    for kind, parts in roads.parts.items():
        for part in parts:
            c = part.centroids
            inside = (c[:, 0] >= xmin) & (c[:, 0] < xmax) & (c[:, 1] >= ymin) & (c[:, 1] < ymax)
            if not inside.any():
                continue
            t, nt = tile_index(c, bounds, tile)
            for tt in np.unique(t[inside]):
                sel = inside & (t == tt)
                sub = split_pieces(part.vertices, part.faces, part.fstart, sel)
                if sub is None:
                    continue
                V, F, ks, a, b = sub
                tiles.setdefault((int(tt) // nt, int(tt) % nt, kind), []).append(
                    (V, F, [(f"{part.elements[k]}/{part.ids[k]}", aa, bb) for k, aa, bb in zip(ks, a, b)]))
                for k in ks:
                    index.append({"id": part.ids[k], "element": part.elements[k], "class": kind,
                                  "osm": [f"way/{w}" for w in part.osm[k]], "tile": f"{int(tt) // nt}_{int(tt) % nt}"})
    # buildings into the same tiles
    if bres.records:
        for rec in bres.records:
            g = bres.scene.geometry.get(rec["id"])
            if g is None:
                continue
            t, nt = tile_index(np.array([rec["centroid"]]), bounds, tile)
            tiles.setdefault((int(t[0]) // nt, int(t[0]) % nt, "building"), []).append(
                (np.asarray(g.vertices), np.asarray(g.faces), [(rec["id"], 0, len(g.faces))]))
    tile_files: dict = {}
    for (a, b, kind), items in sorted(tiles.items()):
        V, F, groups, off, foff = [], [], [], 0, 0
        for v, f, gs in items:
            V.append(v)
            F.append(f + off)
            groups.extend((n, s + foff, e + foff) for n, s, e in gs)
            off += len(v)
            foff += len(f)
        rel = f"{cdir}/tiles/{a}_{b}/{kind}.obj"
        write_obj(tmp / rel, np.vstack(V), np.vstack(F), groups)
        tile_files.setdefault(f"{a}_{b}", {})[kind] = rel
    files["tiles"] = sorted(set(v for t in tile_files.values() for v in t.values()))
    write_text(d / "roads.json", json.dumps({"bounds": list(bounds), "pieces": index}))
    files["roads_index"] = f"{cdir}/roads.json"
    bf = write_chunk_buildings(bres, d)
    for k, v in bf.items():
        if v:
            files[f"buildings_{k}"] = f"{cdir}/{v}"
    sf = write_chunk_scenery(sres, d)
    for k, v in sf.items():
        if v:
            files[f"scenery_{k}"] = f"{cdir}/{v}"
    return {"i": i, "j": j, "bounds_m": list(bounds), "files": files,
            "tiles": {k: v for k, v in sorted(tile_files.items())},
            "counts": {"buildings": len(bres.records), "scenery": len(sres.instances)}}
