"""Time the OSM feature extraction, building meshing and scenery layers on real extracts.

    .venv/bin/python bench/bench_layers.py [--repeat N] [--rings R] [--chunk M]

Helsinki and Kouvola (the embedded presets) always, Monaco when ../shared/data has it.
Prints wall-clock times (the best of N runs) and counts; asserts nothing. The carriageway
that the roads layer gives a real build is approximated here by buffering the OSM highway
ways for cars; the ground is the preset's flat level, or a synthetic hilly function for
Monaco (its DEM reader lives elsewhere), so that base heights are sampled for real.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np
import osmium
import shapely

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from netgen.buildings import footprint_union, make_buildings, write_chunk_buildings  # noqa: E402
from netgen.frame import WorldFrame  # noqa: E402
from netgen.osm_features import extract_features  # noqa: E402
from netgen.presets import get_preset  # noqa: E402
from netgen.scenery import make_scenery, write_chunk_scenery  # noqa: E402

SHARED = Path(os.environ.get("COSIM_SHARED_DATA", REPO.parent / "shared" / "data"))
HALF_WIDTH = {"motorway": 7.0, "trunk": 6.0, "primary": 5.0, "secondary": 4.5, "tertiary": 4.0,
              "unclassified": 3.0, "residential": 3.0, "living_street": 2.5, "service": 2.0,
              "motorway_link": 3.5, "trunk_link": 3.5, "primary_link": 3.5,
              "secondary_link": 3.5, "tertiary_link": 3.0}


def road_area(path, frame):
    wkb = osmium.geom.WKBFactory()
    lines, half = [], []
    for w in osmium.FileProcessor(str(path)).with_locations().with_filter(osmium.filter.KeyFilter("highway")):
        hw = w.tags.get("highway") if w.is_way() else None
        if hw not in HALF_WIDTH or w.tags.get("tunnel", "no") != "no":
            continue
        try:
            lines.append(wkb.create_linestring(w))
        except (RuntimeError, osmium.InvalidLocationError):
            continue
        half.append(HALF_WIDTH[hw])
    g = shapely.transform(shapely.from_wkb(lines), lambda c: np.column_stack(frame.to_xy(c[:, 0], c[:, 1])))
    return shapely.union_all(shapely.buffer(g, np.array(half), quad_segs=4))


def best(fn, repeat):
    out, times = None, []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return out, min(times)


def places():
    for name in ("helsinki", "kouvola"):
        p = get_preset(name)
        z = p.flat_elevation_m
        yield name, p.osm, p.center, (lambda x, y, z=z: np.full(np.shape(x), z)), "flat"
    monaco = SHARED / "osm" / "monaco-2022.osm.pbf"
    if monaco.exists():
        def hills(x, y):
            x, y = np.asarray(x, float), np.asarray(y, float)
            return 60 + 0.08 * y + 6 * np.sin(x / 35.0) * np.cos(y / 50.0)
        yield "monaco", monaco, (43.7385, 7.4244), hills, "synthetic hills"
    else:
        print(f"(monaco skipped: {monaco} is absent)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rings", type=int, default=1)
    ap.add_argument("--chunk", type=float, default=1000.0)
    a = ap.parse_args(argv)
    print(f"{'place':9s} {'extract':>8s} {'buildings':>10s} {'write b.':>9s} {'scenery':>8s} "
          f"{'write s.':>9s}   counts")
    for name, path, (lat, lon), ground, gname in places():
        frame = WorldFrame(lat, lon, a.chunk)
        frame.to_xy(lon, lat)                       # build the PROJ transformer outside the timing
        chunks = [frame.chunk_bounds(i, j) for i, j in frame.ring(a.rings)]
        feats, t_ex = best(lambda: extract_features(path, frame), a.repeat)
        res_b, t_b = best(lambda: make_buildings(feats, ground, chunks), a.repeat)
        road, bld = road_area(path, frame), footprint_union(feats)
        res_s, t_s = best(lambda: make_scenery(feats, ground, road, bld, chunks), a.repeat)
        with tempfile.TemporaryDirectory() as tmp:
            t = time.perf_counter()
            for k, c in enumerate(res_b):
                write_chunk_buildings(c, Path(tmp) / f"c{k}")
            t_wb = time.perf_counter() - t
            t = time.perf_counter()
            for k, c in enumerate(res_s):
                write_chunk_scenery(c, Path(tmp) / f"c{k}")
            t_ws = time.perf_counter() - t
        nb = sum(len(c.records) for c in res_b)
        faces = sum(len(c.mesh.faces) for c in res_b if c.mesh is not None)
        kinds = Counter(i["kind"] for c in res_s for i in c.instances)
        moved = sum(v for c in res_s for v in c.stats["moved"].values())
        dropped = sum(v for c in res_s for w in ("dropped_building", "dropped_road")
                      for v in c.stats[w].values())
        areas = sum(len(c.area_records) for c in res_s)
        afaces = sum(r["faces"] for c in res_s for r in c.area_records)
        print(f"{name:9s} {t_ex:7.3f}s {t_b:9.3f}s {t_wb:8.3f}s {t_s:7.3f}s {t_ws:8.3f}s   "
              f"{nb} buildings ({faces} faces), "
              + ", ".join(f"{v} {k}" for k, v in sorted(kinds.items()))
              + f"; {moved} moved, {dropped} dropped; {areas} areas ({afaces} faces); "
              f"{len(chunks)} chunks, ground {gname}")
        src = Counter(r["height_source"] for c in res_b for r in c.records)
        print(f"{'':9s} heights: " + ", ".join(f"{v} from {k}" for k, v in src.most_common()))


if __name__ == "__main__":
    main()
