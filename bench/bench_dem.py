"""Benchmark of the DEM readers (netgen.dem): open, read + void fill, bilinear sampling.

    .venv/bin/python bench/bench_dem.py [--points N] [--repeat K]

Reads the real rasters in ../shared/data/dem (or $COSIM_SHARED_DATA/dem). Prints figures
only (no pass/fail): wall-clock times depend on the machine and its load; each sampling
figure is the median of K runs.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from netgen.dem import fill_voids, open_dem  # noqa: E402

SHARED = Path(os.environ.get("COSIM_SHARED_DATA", REPO.parent / "shared" / "data"))


def ms(t: float) -> str:
    return f"{t * 1000:8.1f} ms"


def bench_file(path: Path, n: int, repeat: int, world_km: float = 5.0) -> None:
    t0 = time.perf_counter()
    dem = open_dem([path])
    t_open = time.perf_counter() - t0
    g = dem.grids[0]
    t0 = time.perf_counter()
    g.load()  # read + decode + void fill, once
    t_load = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    # (a) uniformly random over the whole raster: worst case for memory locality
    lon_a = g.west + rng.random(n) * (g.east - g.west)
    lat_a = g.south + rng.random(n) * (g.north - g.south)
    # (b) a regular grid over a world-sized square (what terrain building samples)
    side = int(round(np.sqrt(n)))
    dlat = world_km / 111.32
    dlon = dlat / np.cos(np.radians(0.5 * (g.south + g.north)))
    dlat, dlon = min(dlat, 0.9 * (g.north - g.south)), min(dlon, 0.9 * (g.east - g.west))
    lat0 = 0.5 * (g.south + g.north) - dlat / 2
    lon0 = 0.5 * (g.west + g.east) - dlon / 2
    lon_b, lat_b = np.meshgrid(lon0 + np.linspace(0, dlon, side), lat0 + np.linspace(0, dlat, side))
    lon_b, lat_b = lon_b.ravel(), lat_b.ravel()
    res = {}
    for name, lon, lat in (("random", lon_a, lat_a), ("grid", lon_b, lat_b)):
        times = []
        for _ in range(repeat):
            t0 = time.perf_counter()
            z = dem.sample(lon, lat)
            times.append(time.perf_counter() - t0)
        assert np.isfinite(z).all()
        res[name] = (statistics.median(times), lon.size)
    print(f"{path.name:28s} open {ms(t_open)}  read+fill {ms(t_load)} (fill {ms(g.fill_seconds).strip()},"
          f" {g.voids} voids)")
    for name, (t, k) in res.items():
        what = "random over raster" if name == "random" else f"{side}x{side} grid over {world_km:g} km"
        print(f"{'':28s} sample {k:>9,d} pts ({what:26s}) {ms(t)}   "
              f"open+read+sample {ms(t_open + t_load + t).strip()}")


def bench_fill(tile: Path) -> None:
    """Void-fill cost on the real tile with blocks of it blanked out (exact vs cascade)."""
    with zipfile.ZipFile(tile) if tile.suffix == ".zip" else open(os.devnull) as zf:
        data = zf.read(zf.namelist()[0]) if tile.suffix == ".zip" else tile.read_bytes()
    raw = np.frombuffer(data, ">i2").reshape(1201, 1201).astype(np.float32)
    base_void = raw == -32768
    print(f"void fill on {tile.name} with a square blanked out (exact = sparse direct solve):")
    for side in (10, 60, 141, 250, 400):
        void = base_void.copy()
        void[300:300 + side, 300:300 + side] = True
        z = raw.copy()
        z[void] = np.nan
        t0 = time.perf_counter()
        n = fill_voids(z, void)
        t = time.perf_counter() - t0
        path = "exact" if side * side <= 20000 else "cascade"
        line = f"  {n:>7,d} cells ({path:7s}) {ms(t)}"
        if path == "cascade" and side <= 250:
            z2 = raw.copy()
            z2[void] = np.nan
            t0 = time.perf_counter()
            fill_voids(z2, void, direct_max=10 ** 7)
            t2 = time.perf_counter() - t0
            d = np.abs(z.astype(float) - z2)[void]
            line += f"   exact solve {ms(t2).strip()}; cascade - exact: mean {d.mean():.2f} m, max {d.max():.2f} m"
        print(line)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--repeat", type=int, default=5)
    a = ap.parse_args(argv)
    dem_dir = SHARED / "dem"
    if not dem_dir.is_dir():
        print(f"skipped: needs {dem_dir} (../shared/data beside the checkout)")
        return 0
    print(f"netgen.dem benchmark: {a.points:,} points, median of {a.repeat} runs; cpus={os.cpu_count()}, "
          f"load average {', '.join(f'{x:.2f}' for x in os.getloadavg())}")
    # netgen.dem imports these lazily; pay their one-time import cost up front so that the
    # per-file figures below are the readers' own
    t0 = time.perf_counter()
    import pyproj  # noqa: F401
    import scipy.ndimage  # noqa: F401
    import scipy.sparse.linalg  # noqa: F401
    import tifffile  # noqa: F401
    from pyproj import CRS
    CRS.from_epsg(4269)
    print(f"one-time imports (scipy.ndimage, scipy.sparse.linalg, tifffile, pyproj): "
          f"{ms(time.perf_counter() - t0).strip()}")
    with tempfile.TemporaryDirectory() as tmp:
        # the zipped N49E011 tile unzipped into a temp dir, for plain-.hgt vs .hgt.zip figures
        zpath = dem_dir / "N49E011.hgt.zip"
        hgt = Path(tmp) / "N49E011.hgt"
        with zipfile.ZipFile(zpath) as zf:
            hgt.write_bytes(zf.read("N49E011.hgt"))
        for p in (hgt, zpath, dem_dir / "N43E007.hgt", dem_dir / "portland-ned.tif",
                  dem_dir / "portland-ned-nodata.tif"):
            if p.exists():
                bench_file(p, a.points, a.repeat)
            else:
                print(f"{p.name}: absent, skipped")
    bench_fill(zpath)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
