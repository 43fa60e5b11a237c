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

from netgen.errors import CosimError, InputError


#: where each stage of a world build starts and ends on the progress bar (its share of a typical
#: build's time; "roads" holds the wait for netconvert and the road meshing)
BUILD_STAGES = {"osm": (0.0, 0.08), "netconvert": (0.08, 0.08), "elevation": (0.08, 0.1),
                "terrain": (0.1, 0.12), "features": (0.12, 0.2), "buildings": (0.2, 0.23),
                "scenery": (0.23, 0.26), "roads": (0.26, 0.9), "write": (0.9, 1.0), "done": (1.0, 1.0)}


class Progress:
    """Progress on stderr: a bar redrawn in place on a terminal, one line per stage otherwise.
    A world build's stages fill the bar in turn (:data:`BUILD_STAGES`); other stages show their
    own fraction."""

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
            if stage in BUILD_STAGES:
                lo, hi = BUILD_STAGES[stage]
                frac = lo + (hi - lo) * max(0.0, min(1.0, frac))
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
    road_chunks = sum(1 for ch in w["chunks"]
                      if any(str(f).endswith("/asphalt.obj") for f in ch.get("files", {}).get("tiles", [])))
    if road_chunks < len(w["chunks"]):
        print(f"coverage   roads in {road_chunks} of {len(w['chunks'])} chunks: the OSM data covers only part "
              "of this world (nothing to drive on in the others)", file=stream)
    if w.get("reused"):
        print(f"status     up to date (reused in {t.get('total', 0):.2f} s)", file=stream)
    print(f"network    {c['road_edges']} road edges ({c['road_length_km']} km), {c['junctions']} junctions, "
          f"{c['traffic_lights']} traffic lights, {c['crossings']} crossings, {c['footpath_edges']} footpaths", file=stream)
    print(f"buildings  {c['buildings']} ({c['buildings_height_from_tags']} heights from tags, "
          f"{c.get('buildings_height_from_levels', 0)} from levels; {c.get('building_passages', 0)} "
          "over a road: passages)", file=stream)
    print(f"scenery    {c['trees']} trees, {c['street_lamps']} street lamps, {c['traffic_signal_poles']} signal poles, "
          f"{c['stop_signs']} stop / {c['give_way_signs']} give-way signs, {c['benches']} benches", file=stream)
    tr = w["terrain"]
    ev = w["sources"]["elevation"]
    source = " ".join(x for x in (str(ev.get("kind")), ", ".join(ev.get("files", []))) if x)
    print(f"terrain    {tr['spacing_m']} m grid, z {tr['z_range_m'][0]}..{tr['z_range_m'][1]} m from "
          f"{source}; voids filled: {ev.get('voids_filled', 0)}", file=stream)
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


def sim_config_from_args(a):
    from .config import SimConfig

    if a.scenario:
        cfg = SimConfig.from_toml(a.scenario)
        if a.preset or a.osm or a.bbox or a.center or a.world:
            world_config_from_args(a, base=cfg.world)
    else:
        cfg = SimConfig()
        if not a.world:
            cfg.world = world_config_from_args(a)
    if a.world:
        # (they were ignored: `--world W --center LAT,LON` started at the world's centre)
        given = [f"--{k.replace('_', '-')}" for k in ("preset", "osm", "bbox", "center", "chunks", "chunk_size",
                                                      "quality", "terrain_spacing", "dem", "elevation", "flat",
                                                      "overpass_url", "timeout", "out")
                 if getattr(a, k, None) is not None]
        if given:
            hint = " (to start elsewhere in it: --start LAT,LON)" if "--center" in given else ""
            raise InputError(f"--world runs a world as it was built: {', '.join(given)} cannot change it{hint}; "
                             "to build another, give the place instead of --world")
        cfg.world_dir = a.world
    for k_arg, k_cfg in (("duration", "duration_s"), ("speed", "speed_mps"), ("traffic", "traffic"),
                         ("seed", "seed"), ("telemetry", "telemetry"), ("sensor_range", "sensor_range_m"),
                         ("backend", "backend"), ("parallel_sumo", "parallel_sumo"),
                         ("lane_change", "lane_change_s")):
        v = getattr(a, k_arg)
        if v is not None:
            setattr(cfg, k_cfg, v)
    if a.start:
        from netgen.frame import parse_latlon

        cfg.start = parse_latlon(a.start, "--start")
    if a.to:
        from netgen.frame import parse_latlon

        cfg.goal = parse_latlon(a.to, "--to")
    if a.gui:
        cfg.gui = True
        cfg.realtime = True
    if a.sumo_gui:
        cfg.sumo_gui = True
    if a.respect_speed_limit:
        cfg.respect_speed_limit = True
    if getattr(a, "swap_when_ready", False):
        cfg.repeatable = False
    return cfg.validate()


def cmd_run(a):
    from .sim import Simulation

    cfg = sim_config_from_args(a)
    prog = Progress(quiet=a.quiet, verbose=a.verbose)
    sim = Simulation(cfg, progress=prog)
    tty = sys.stderr.isatty()
    last = [0.0]

    def on_step(s, ego):
        if a.quiet or s.t - last[0] < (1.0 if tty else 10.0):
            return
        last[0] = s.t
        v, p = s.mirror.counts()
        line = (f"t={s.t:6.1f}s  {ego.speed:5.1f} m/s  lat {ego.lat:.6f} lon {ego.lon:.6f}  "
                f"{v:3d} vehicles {p:3d} persons near  tiles {len(s.physics.tiles):3d}  {s.driver.reason if hasattr(s.driver, 'reason') else ''}")
        if tty:
            sys.stderr.write("\r" + line[:150].ljust(150))
        elif a.verbose:
            sys.stderr.write(line + "\n")
        sys.stderr.flush()

    try:
        sim.setup()
        info = sim.snap_info
        start = (f"start snapped {info.get('start_snap_m')} m onto lane {info.get('start_lane')}"
                 + (f"; route {info['route_length_m']:.0f} m, ETA {info['eta_s']:.0f} s" if 'route_length_m' in info else ""))
        if not a.json:
            print(start)
        elif not a.quiet:           # (with --json, standard output holds the summary alone)
            print(start, file=sys.stderr)
        summary = sim.run(on_step=on_step)
    finally:
        sim.teardown()
        if tty and not a.quiet:
            sys.stderr.write("\n")
    if a.json:
        import dataclasses

        print(json.dumps(dataclasses.asdict(summary), indent=1))
    else:
        print("summary: " + summary.line())
    return 0


def add_gui_args(p) -> None:
    """The launcher's options (``cosim gui`` and ``python -m ui.app``)."""
    p.add_argument("--preset", help="preset selected at start")
    p.add_argument("--worlds", metavar="DIR",
                   help="where built worlds are kept (default: $COSIM_CACHE/worlds or ~/.cache/cosim/worlds)")
    p.add_argument("--no-realtime", action="store_true", help="run as fast as possible, not at wall-clock pace")


def cmd_gui(a):
    from ui.app import launch

    return launch(preset=a.preset, worlds=a.worlds, realtime=not a.no_realtime)


class _Parser(argparse.ArgumentParser):
    """argparse, whose mistakes are one line (as every other bad input's), not its usage block."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def make_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="cosim", description="Turn any place on Earth into a drivable, "
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

    from netgen.export_sdf import add_export_parser

    add_export_parser(sub)

    gp = sub.add_parser("gui", help="the desktop launcher (PyQt5) with a live view of the simulation",
                        description="Open the PyQt5 launcher: pick a place, check the inputs, build and drive. "
                                    "Needs a display (QT_QPA_PLATFORM=offscreen runs it without one).")
    add_gui_args(gp)
    gp.set_defaults(func=cmd_gui)

    r = sub.add_parser("run", help="run the co-simulation (headless by default)",
                       description="Build (or reuse) a world and drive the physics car through SUMO traffic. "
                                   "With no place given, runs the default preset.")
    r.add_argument("scenario", nargs="?", help="scenario TOML file (see scenarios/)")
    r.add_argument("--world", metavar="DIR", help="an already built world folder, run as it was built (the place "
                   "and build options are then an error; --start LAT,LON starts elsewhere in it)")
    add_place_args(r)
    g = r.add_argument_group("run")
    g.add_argument("--duration", type=float, metavar="S", help="simulated seconds (default 60)")
    g.add_argument("--speed", type=float, metavar="MPS", help="the ego's set speed in m/s (default 10)")
    g.add_argument("--traffic", metavar="DENSITY", help="none | light | normal | dense | vehicles per km2 of the network "
                   "within the world (the names scaled by the preset's traffic_scale: Kouvola's 0.5)")
    g.add_argument("--seed", type=int, help="random seed, 0..2147483647: the same seed (world, --duration and "
                   "--parallel-sumo) repeats the run")
    g.add_argument("--lane-change", type=float, metavar="S", help="SUMO's drivers change lanes over S seconds "
                   "(default 3; 0: SUMO's default, within one step)")
    g.add_argument("--swap-when-ready", action="store_true",
                   help="swap to the next window as soon as it is built, not at a fixed simulated time "
                        "after its build started (never waits for a build; the run is not repeatable)")
    g.add_argument("--start", metavar="LAT,LON",
                   help="start here (snapped to the nearest lane; on a two-way road, the direction that reaches --to "
                        "without a U-turn, or with no --to the one that does not run into a dead end or a turn the "
                        "car cannot make); default: the centre")
    g.add_argument("--to", metavar="LAT,LON",
                   help="drive to this GPS coordinate by road (by a route with no tunnel and no turn the car "
                        "cannot make: the world has no tunnels; where there is none, the run does not start)")
    g.add_argument("--respect-speed-limit", action="store_true", help="never exceed the lane's speed limit")
    g.add_argument("--sensor-range", type=float, metavar="M", help="lidar/camera range the world must cover (default 100)")
    g.add_argument("--telemetry", metavar="FILE.jsonl", help="write one JSON row per SUMO step")
    g.add_argument("--gui", action="store_true", help="PyBullet's 3D window with a chase camera (needs a display)")
    g.add_argument("--sumo-gui", action="store_true", help="run SUMO in sumo-gui (TraCI backend; needs a display)")
    g.add_argument("--backend", choices=["libsumo", "traci"], help="SUMO API (default libsumo)")
    g.add_argument("--parallel-sumo", action=argparse.BooleanOptionalAction, default=None,
                   help="run libsumo in a worker process that steps while the physics runs "
                        "(default: on with 2 or more CPUs)")
    g.add_argument("--json", action="store_true", help="print the summary as JSON")
    g.add_argument("-q", "--quiet", action="store_true")
    g.add_argument("-v", "--verbose", action="store_true")
    r.set_defaults(func=cmd_run, force=False)
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
        rc = a.func(a) or 0
        sys.stdout.flush()          # (a closed pipe shows here, not at the interpreter's exit)
        return rc
    except CosimError as e:
        if os.environ.get("COSIM_DEBUG"):
            raise
        print(f"\nerror: {e}" if sys.stderr.isatty() else f"error: {e}", file=sys.stderr)
        return e.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:     # the reader went away (`cosim presets | head -1`): stop quietly
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())       # (no second error when Python flushes stdout)
        return 141


if __name__ == "__main__":
    sys.exit(main())
