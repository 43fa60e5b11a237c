"""Gazebo export benchmark: `cosim export-sdf` time and size per km² for each preset.

    python bench/bench_export.py [--rings 1] [--repeat 3] [--only helsinki,kouvola] [--formats stl,dae]

For each place (the embedded presets, and Monaco on SRTM at quality medium when
../shared/data is present) it builds a world of (2 * rings + 1)^2 chunks of 1 km once, then
exports it in each mesh format --repeat times and reports the median export time, the
export's size and file count, per km² as well, and how long SDFormat takes to load the
exported world.sdf with all its includes (what Gazebo does at start-up), when the SDFormat
checker of the tests can be built (tests/sdf_checker). Nothing is asserted: this machine
is noisy.
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
SHARED = REPO.parent / "shared" / "data"

from netgen.build import build_world  # noqa: E402
from netgen.config import WorldConfig  # noqa: E402
from netgen.export_sdf import export_sdf  # noqa: E402


def places(rings):
    out = [("helsinki", dict(preset="helsinki")), ("kouvola", dict(preset="kouvola")),
           ("kouvola-motorway", dict(preset="kouvola-motorway"))]
    if (SHARED / "osm/monaco-2022.osm.pbf").exists():
        out.append(("monaco+srtm/medium", dict(osm=str(SHARED / "osm/monaco-2022.osm.pbf"),
                                               dem=[str(SHARED / "dem/N43E007.hgt")], center=(43.7384, 7.4246),
                                               quality="medium")))
    return [(n, dict(kw, chunks=rings)) for n, kw in out]


def checker():
    spec = importlib.util.spec_from_file_location("sdf_checker_build", REPO / "tests/sdf_checker/build.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    try:
        return mod.build_checker()
    except mod.CheckerUnavailable as e:
        print(f"(no SDFormat load times: {e})", file=sys.stderr)
        return None


def sdf_load_s(exe, export: Path):
    t0 = time.perf_counter()
    r = subprocess.run([str(exe), "--path", str(export / "models"), str(export / "world.sdf")],
                       capture_output=True, text=True)
    dt = time.perf_counter() - t0
    errs = len(json.loads(r.stdout)["files"][0]["errors"]) if r.stdout else -1
    return dt, errs


def du(path: Path) -> tuple[int, int]:
    files = [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files), len(files)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rings", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--only", default="")
    ap.add_argument("--formats", default="stl,dae")
    a = ap.parse_args()
    only = {s for s in a.only.split(",") if s}
    exe = checker()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench-export-") as td:
        td = Path(td)
        for name, kw in places(a.rings):
            if only and name.split("/")[0] not in only:
                continue
            wdir = td / "w" / name.replace("/", "_")
            t0 = time.perf_counter()
            w = build_world(WorldConfig(out=str(wdir), cache_dir=str(td / "cache"), **kw))
            tb = time.perf_counter() - t0
            km2 = len(w["chunks"]) * w["chunk_size_m"] ** 2 / 1e6
            c = w["counts"]
            for fmt in a.formats.split(","):
                times, cpus, m = [], [], None
                for k in range(a.repeat):
                    out = td / "x" / f"{name.replace('/', '_')}-{fmt}"
                    shutil.rmtree(out, ignore_errors=True)
                    t0, c0 = time.perf_counter(), time.process_time()
                    m = export_sdf(wdir, out, mesh_format=fmt)
                    times.append(time.perf_counter() - t0)
                    cpus.append(time.process_time() - c0)
                size, nfiles = du(out)
                load, errs = sdf_load_s(exe, out) if exe else (float("nan"), -1)
                t, cpu = statistics.median(times), statistics.median(cpus)
                rows.append((name, fmt, km2, c["buildings"], m["counts"]["scenery"], tb, t, t / km2, size / 1e6,
                             size / 1e6 / km2, nfiles, m["counts"]["models_in_world"], load, errs, cpu))
                print(f"{name:<20} {fmt}: export {t:.2f} s ({t / km2:.2f} s/km², cpu {cpu:.2f} s), "
                      f"{size / 1e6:.1f} MB "
                      f"({size / 1e6 / km2:.2f} MB/km²), {nfiles} files, SDFormat load {load:.1f} s "
                      f"({errs} errors)", file=sys.stderr)
    print(f"\n(2 x {a.rings} + 1)^2 chunks of 1 km; median of {a.repeat} exports; SDFormat = "
          "sdf::Root::Load of world.sdf with every include (the parse Gazebo does at start-up)\n")
    print("| place | format | km² | buildings | scenery | build (s) | export (s) | export CPU (s) | s/km² | MB "
          "| MB/km² | files | models | SDFormat load (s) |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r[0]} | {r[1]} | {r[2]:.0f} | {r[3]} | {r[4]} | {r[5]:.1f} | {r[6]:.2f} | {r[14]:.2f} | "
              f"{r[7]:.2f} | {r[8]:.1f} | {r[9]:.2f} | {r[10]} | {r[11]} | {r[12]:.1f} |")


if __name__ == "__main__":
    main()
