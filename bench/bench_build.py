"""World-build benchmark: per-stage timings, and the full build against netconvert alone.

    python bench/bench_build.py [--rings 1] [--repeat 2] [--only helsinki,monaco]

For each place (the embedded presets, and Monaco with SRTM when ../shared/data is present)
and a world of (2 * rings + 1)^2 chunks of 1 km, it times, side by side in one run:

* netconvert alone on the same OSM input, bbox and options (the goal's yardstick), the
  whole file as XML; and, for comparison, netconvert alone on the build's network extract
  of a PBF file (the ways, relations and nodes it reads: ``network_xml``), which gives
  the same network faster;
* a full build from scratch (fresh cache: OSM conversion, netconvert, all layers, writing);
* a cached rebuild (same inputs, world already on disk).

Figures are medians over --repeat runs; ratios are full build / netconvert alone (goal <= 1.3)
and the cached rebuild time (goal <= 2 s); each run's own ratio is printed too (on a busy
machine the smallest is the least disturbed). Nothing is asserted: this machine is noisy. The
load average is printed with each place: the build keeps both cores busy after netconvert,
so other work on the machine slows it more than it slows netconvert alone. CPU seconds are
printed too (netconvert alone, and the whole build: this process, netconvert and the forked
writers): with one core taken by other work, netconvert alone still gets the other core,
while in the build it shares it with the build's own work, so the build's CPU time decides.
"""
from __future__ import annotations

import argparse
import os
import resource
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

from netgen import sumo_net  # noqa: E402
from netgen.build import build_world, resolve_place  # noqa: E402
from netgen.config import WorldConfig  # noqa: E402
from netgen.frame import WorldFrame  # noqa: E402
from netgen.osm_file import keep_edges_file, network_xml, to_osm_xml  # noqa: E402


def places(rings):
    out = [("helsinki", dict(preset="helsinki")), ("kouvola", dict(preset="kouvola")),
           ("kouvola-motorway", dict(preset="kouvola-motorway"))]
    if (SHARED / "osm/monaco-2022.osm.pbf").exists():
        out.append(("monaco+srtm", dict(osm=str(SHARED / "osm/monaco-2022.osm.pbf"), dem=[str(SHARED / "dem/N43E007.hgt")],
                                        center=(43.7384, 7.4246))))
    if (SHARED / "osm/lauf-2020.osm.pbf").exists():
        out.append(("lauf+srtm", dict(osm=str(SHARED / "osm/lauf-2020.osm.pbf"), dem=[str(SHARED / "dem/N49E011.hgt.zip")],
                                      center=(49.5105, 11.2780))))
    return [(n, dict(kw, chunks=rings)) for n, kw in out]


def _cpu() -> float:
    """CPU seconds of this process and of its children that have been waited for."""
    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def netconvert_alone(cfg: WorldConfig, cache: Path, out: Path, extract: bool = False) -> tuple[float, float]:
    """(wall, CPU) seconds of netconvert alone on the whole OSM file (as XML: netconvert
    reads nothing else), or with `extract`, on the build's network extract of it
    (``network_xml``, made beforehand and not timed)."""
    name, centre, source, preset = resolve_place(cfg)
    frame = WorldFrame(centre[0], centre[1], cfg.chunk_size_m)
    bbox = frame.bbox_lonlat(frame.extent(frame.ring(cfg.chunks)), margin_m=50.0)
    osm_xml, _ = (network_xml if extract else to_osm_xml)(Path(source["file"]), cache)
    args = sumo_net.netconvert_args(osm_xml, out, frame.proj_string, bbox,
                                    keep_edges=keep_edges_file(osm_xml))      # the build's options
    t0, c0 = time.perf_counter(), _cpu()
    subprocess.run(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=sumo_net.sumo_env(), check=True)
    return time.perf_counter() - t0, _cpu() - c0


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--rings", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--only", default="")
    ap.add_argument("--quality", default="low")
    a = ap.parse_args(argv)
    only = set(filter(None, a.only.split(",")))
    rows = []
    for name, kw in places(a.rings):
        if only and name not in only:
            continue
        nc, full, cached, stages, nc_cpu, full_cpu, nc_part = [], [], [], [], [], [], []
        for r in range(a.repeat):
            tmp = Path(tempfile.mkdtemp(prefix="bench-build-"))
            try:
                cfg = WorldConfig(**kw, quality=a.quality, out=str(tmp / "w"), cache_dir=str(tmp / "cache"))
                # OSM conversion is cached first so both sides read the same XML
                t_nc, c_nc = netconvert_alone(cfg, tmp / "cache", tmp / "alone.net.xml")
                nc.append(t_nc)
                nc_cpu.append(c_nc)
                nc_part.append(netconvert_alone(cfg, tmp / "cache", tmp / "part.net.xml", extract=True)[0])
                shutil.rmtree(tmp / "cache" / "osm", ignore_errors=True)
                t0, c0 = time.perf_counter(), _cpu()
                w = build_world(cfg)
                full.append(time.perf_counter() - t0)
                full_cpu.append(_cpu() - c0)    # this process, netconvert and the forked writers
                stages.append(w["timings_s"])
                t0 = time.perf_counter()
                w2 = build_world(WorldConfig(**kw, quality=a.quality, out=str(tmp / "w"), cache_dir=str(tmp / "cache")))
                cached.append(time.perf_counter() - t0)
                assert w2.get("reused")
                size = sum(f.stat().st_size for f in (tmp / "w").rglob("*") if f.is_file())
            finally:
                shutil.rmtree(tmp, ignore_errors=True)
        m_nc, m_full, m_cached = statistics.median(nc), statistics.median(full), statistics.median(cached)
        st = {k: round(statistics.median(s.get(k, 0.0) for s in stages), 2) for k in stages[-1] if k != "total"}
        rows.append((name, m_nc, m_full, m_cached, size, w["counts"]))
        load = " ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "?"
        print(f"\n== {name}: {len(w['chunks'])} chunks, {w['counts']['road_edges']} road edges, "
              f"{w['counts']['buildings']} buildings, world {size / 1e6:.1f} MB (load average {load})")
        print(f"   netconvert alone {m_nc:6.2f} s | full build {m_full:6.2f} s | ratio {m_full / m_nc:4.2f} "
              f"(goal <= 1.3) | cached rebuild {m_cached:5.2f} s (goal <= 2)")
        m_part = statistics.median(nc_part)
        print(f"   netconvert alone on the build's network extract {m_part:6.2f} s ({m_part / m_nc:.2f} of the whole file's); "
              f"full build / that {m_full / m_part:4.2f}")
        if len(nc) > 1:     # each run's own pair: the least disturbed one is the best guess on a busy machine
            print("   ratio per run (build / netconvert alone just before it): "
                  + " ".join(f"{b / a:.2f}" for a, b in zip(nc, full)) + f" (min {min(b / a for a, b in zip(nc, full)):.2f})")
        m_ncc, m_fc = statistics.median(nc_cpu), statistics.median(full_cpu)
        print(f"   CPU: netconvert alone {m_ncc:5.2f} s ({m_ncc / m_nc:.0%} of a core) | full build {m_fc:5.2f} s "
              f"(netconvert {min(m_ncc / m_fc, 1.0):.0%} of it)")
        print("   stages (s): " + ", ".join(f"{k} {v}" for k, v in st.items()))
        # netconvert starts once the OSM input is ready: the rest is what the build adds
        print(f"   critical path: OSM input {st.get('osm', 0):.2f} s, netconvert in the build {st.get('netconvert', 0):.2f} s "
              f"(to its exit), after it {m_full - st.get('osm', 0) - st.get('netconvert', 0):.2f} s")
        sys.stdout.flush()
    print("\nsummary: place, netconvert s, build s, ratio, cached s")
    for name, a1, b1, c1, size, _ in rows:
        print(f"  {name:<18} {a1:6.2f} {b1:6.2f} {b1 / a1:5.2f} {c1:5.2f}")


if __name__ == "__main__":
    main()
