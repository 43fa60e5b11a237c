"""The ``cosim`` command line: build worlds, list presets, run and export them.

Every user error prints ``error: <one line>`` and exits with status 2; nothing prints a
traceback unless ``COSIM_DEBUG=1`` is set.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

from netgen.errors import CosimError


class Progress:
    """Progress on stderr: a bar redrawn in place on a terminal, one line per stage otherwise."""

    def __init__(self, stream=sys.stderr, quiet=False, verbose=False):
        self.stream = stream
        self.tty = stream.isatty()
        # off a terminal (scripts, CI) progress is silent unless asked for, so that stderr
        # holds only errors
        self.quiet = quiet or not (self.tty or verbose)
        self.last = None
        self.t0 = time.perf_counter()

    def __call__(self, stage: str, frac: float, msg: str = ""):
        if self.quiet:
            return
        el = time.perf_counter() - self.t0
        if self.tty:
            n = int(20 * max(0.0, min(1.0, frac)))
            self.stream.write(f"\r[{'#' * n}{'.' * (20 - n)}] {el:6.1f}s {stage:<10} {msg[:50]:<50}")
            if stage == "done":
                self.stream.write("\n")
            self.stream.flush()
        elif stage != self.last:
            self.stream.write(f"[{el:6.1f}s] {stage}: {msg}\n")
            self.stream.flush()
        self.last = stage


# ---------------------------------------------------------------------------------------
def add_place_args(p: argparse.ArgumentParser, build_only: bool = True):
    g = p.add_argument_group("place (one of)")
    g.add_argument("--preset", help="embedded preset name (see `cosim presets`)")
    g.add_argument("--osm", metavar="FILE", help="local OSM file: .osm, .osm.pbf, .osm.gz, .osm.bz2")
    g.add_argument("--bbox", metavar="S,W,N,E", help="fetch this area from the Overpass API")
    g.add_argument("--center", metavar="LAT,LON",
                   help="world origin (default: the preset's centre, the file's or bbox's middle); "
                        "alone, fetches the area around it from Overpass")
    s = p.add_argument_group("size and detail")
    s.add_argument("--chunks", type=int, default=None, metavar="N",
                   help="rings of chunks around the centre chunk: 1 -> 3x3 (default 1)")
    s.add_argument("--chunk-size", type=float, default=None, metavar="M", help="chunk edge in metres (default 1000)")
    s.add_argument("--quality", choices=["low", "medium", "high"], default=None,
                   help="terrain spacing 10/5/2.5 m, scenery density, road mesh detail (default low)")
    s.add_argument("--terrain-spacing", type=float, default=None, metavar="M", help="override the terrain grid spacing")
    e = p.add_argument_group("elevation (one of; presets bring their own)")
    e.add_argument("--dem", nargs="+", metavar="FILE", help="DEM files: SRTM .hgt/.hgt.zip tiles or GeoTIFF")
    e.add_argument("--elevation", metavar="URL", help="open-elevation API lookup URL (POST /api/v1/lookup)")
    e.add_argument("--flat", nargs="?", const=0.0, type=float, metavar="Z",
                   help="no elevation data: a flat world at height Z (default 0)")
    w = p.add_argument_group("web services and files")
    w.add_argument("--overpass-url", action="append", metavar="URL",
                   help="Overpass API endpoint; repeat to give fallbacks, tried in order")
    w.add_argument("--timeout", type=float, default=None, help="HTTP timeout in seconds (default 60)")
    w.add_argument("--cache-dir", metavar="DIR", help="cache folder (default $COSIM_CACHE or ~/.cache/cosim)")
    w.add_argument("--out", metavar="DIR", help="output folder (default worlds/<name>)")


def world_config_from_args(a, base=None):
    from netgen.config import WorldConfig
    from netgen.frame import parse_bbox, parse_latlon

    cfg = base or WorldConfig()
    if a.preset or a.osm or a.bbox:
        cfg.preset, cfg.osm, cfg.bbox = a.preset, a.osm, None
        if a.bbox:
            cfg.bbox = parse_bbox(a.bbox)
    if a.center:
        cfg.center = parse_latlon(a.center, "--center")
    if a.chunks is not None:
        cfg.chunks = a.chunks
    if a.chunk_size is not None:
        cfg.chunk_size_m = a.chunk_size
    if a.quality:
        cfg.quality = a.quality
    if a.terrain_spacing is not None:
        cfg.terrain_spacing_m = a.terrain_spacing
    if a.dem:
        cfg.dem = list(a.dem)
    if a.elevation:
        cfg.elevation_url = a.elevation
    if a.flat is not None:
        cfg.flat, cfg.flat_elevation_m = True, float(a.flat)
    if a.overpass_url:
        cfg.overpass_urls = list(a.overpass_url)
    if a.timeout is not None:
        cfg.http_timeout_s = a.timeout
    if a.cache_dir:
        cfg.cache_dir = a.cache_dir
    if a.out:
        cfg.out = a.out
    if not (cfg.preset or cfg.osm or cfg.bbox or cfg.center):
        from netgen.presets import DEFAULT_PRESET

        cfg.preset = DEFAULT_PRESET
    return cfg.validate()


def print_build_report(w: dict, stream=sys.stdout):
    c = w["counts"]
    t = w.get("timings_s", {})
    print(f"world      {w.get('out', '')}", file=stream)
    print(f"place      {w['name']}  centre {w['center']['lat']:.6f},{w['center']['lon']:.6f}  "
          f"{len(w['chunks'])} chunks of {w['chunk_size_m']:.0f} m", file=stream)
    if w.get("reused"):
        print(f"status     up to date (reused in {t.get('total', 0):.2f} s)", file=stream)
    print(f"network    {c['road_edges']} road edges ({c['road_length_km']} km), {c['junctions']} junctions, "
          f"{c['traffic_lights']} traffic lights, {c['crossings']} crossings, {c['footpath_edges']} footpaths", file=stream)
    print(f"buildings  {c['buildings']} ({c['buildings_height_from_tags']} heights from tags, "
          f"{c.get('buildings_height_from_levels', 0)} from levels)", file=stream)
    print(f"scenery    {c['trees']} trees, {c['street_lamps']} street lamps, {c['traffic_signal_poles']} signal poles, "
          f"{c['stop_signs']} stop / {c['give_way_signs']} give-way signs, {c['benches']} benches", file=stream)
    tr = w["terrain"]
    ev = w["sources"]["elevation"]
    print(f"terrain    {tr['spacing_m']} m grid, z {tr['z_range_m'][0]}..{tr['z_range_m'][1]} m from "
          f"{ev.get('kind')} {', '.join(ev.get('files', []))}; voids filled: {ev.get('voids_filled', 0)}", file=stream)
    nw = w.get("netconvert_warnings", {})
    if nw.get("total"):
        top = "; ".join(f"{x['count']}x {x['message'][:60]}" for x in nw.get("top", [])[:3])
        print(f"netconvert {nw['total']} warnings of {nw['kinds']} kinds: {top}", file=stream)
    if not w.get("reused"):
        stages = ", ".join(f"{k} {v:.2f}" for k, v in t.items() if k != "total")
        print(f"timings    total {t.get('total', 0):.2f} s ({stages})", file=stream)


# ---------------------------------------------------------------------------------------
def cmd_presets(a):
    from netgen.presets import DEFAULT_PRESET, list_presets

    ps = list_presets()
    if a.json:
        print(json.dumps([{"name": p.name, "place": p.place, "environment": p.environment,
                           "center": list(p.center), "osm": p.osm.name, "elevation": p.elevation} for p in ps], indent=1))
        return 0
    print(f"{'name':<18} {'environment':<14} {'centre':<22} place")
    for p in ps:
        star = "*" if p.name == DEFAULT_PRESET else " "
        print(f"{p.name + star:<18} {p.environment:<14} {p.center[0]:.4f},{p.center[1]:.4f}{'':<5} {p.place}")
    print("(* default; OSM data © OpenStreetMap contributors, ODbL)")
    return 0


def cmd_build(a):
    from netgen.build import build_world

    cfg = world_config_from_args(a)
    w = build_world(cfg, progress=Progress(quiet=a.quiet, verbose=a.verbose), force=a.force)
    if a.json:
        print(json.dumps(w, indent=1))
    else:
        print_build_report(w)
    return 0


def make_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="cosim", description="Turn any place on Earth into a drivable, "
                                "traffic-filled simulation (OpenStreetMap + elevation -> SUMO + PyBullet).")
    sub = p.add_subparsers(dest="cmd", metavar="COMMAND")
    sp = sub.add_parser("presets", help="list the embedded presets", description="List the embedded presets.")
    sp.add_argument("--json", action="store_true")
    sp.set_defaults(func=cmd_presets)
    b = sub.add_parser("build", help="build a world (SUMO network + 3D chunks) from OSM and elevation",
                       description="Build a world folder (world.json, SUMO network, terrain, road, building and "
                                   "scenery meshes per chunk). With no place given, builds the default preset.")
    add_place_args(b)
    b.add_argument("--force", action="store_true", help="rebuild even if the output is up to date")
    b.add_argument("--json", action="store_true", help="print world.json instead of the report")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    b.add_argument("-v", "--verbose", action="store_true", help="progress lines even when stderr is not a terminal")
    b.set_defaults(func=cmd_build)
    return p


def main(argv=None) -> int:
    import logging

    p = make_parser()
    a = p.parse_args(argv)
    verbose = getattr(a, "verbose", False)
    # retries and warnings are for a person watching; scripts get only the final error line
    logging.basicConfig(level=logging.INFO if verbose else (logging.WARNING if sys.stderr.isatty() else logging.ERROR),
                        format="%(levelname)s: %(message)s")
    if not getattr(a, "func", None):
        p.print_help()
        return 0
    try:
        return a.func(a) or 0
    except CosimError as e:
        if os.environ.get("COSIM_DEBUG"):
            raise
        print(f"\nerror: {e}" if sys.stderr.isatty() else f"error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
