"""Elevation from an open-elevation server (``POST /api/v1/lookup``).

The API takes ``{"locations": [{"latitude": .., "longitude": ..}, ...]}`` and answers
``{"results": [{"latitude": .., "longitude": .., "elevation": ..}, ...]}`` in request order.
Public servers cap the size and rate of requests, so :class:`OpenElevation` does not ask
for every point the builder needs: :meth:`OpenElevation.prepare` fetches a regular lattice
over a bbox (aligned on a global grid of ``spacing_arcsec`` arc-seconds in latitude, and a
whole multiple of it in longitude chosen so cells are about square), in batches of
``batch_size`` points, each batch cached on disk by its list of points (not by server URL);
:meth:`OpenElevation.sample` then interpolates bilinearly on that lattice (numpy, vectorised).

Answers are checked: a wrong number of results, a missing, null, non-numeric or non-finite
elevation, or coordinates that do not match the request are garbage (retried, then
:class:`ServiceError`). Elevations below -1000 m or above 9000 m are no-data markers of the
server's DEM (SRTM voids are -32768): they are filled from neighbouring lattice points and
counted in ``info()["voids_filled"]``.
"""
from __future__ import annotations

import json
import math
import os
from typing import Sequence

import numpy as np

from ._http import DEFAULT_BACKOFF_BASE_S, DEFAULT_MAX_WAIT_S, Garbage, fetch
from .dem import Elevation
from .errors import DataError, InputError
from .frame import check_latlon

SERVICE = "open-elevation"
NAMESPACE = "open-elevation"
DEFAULT_URL = "https://api.open-elevation.com/api/v1/lookup"
VOID_BELOW_M = -1000.0
VOID_ABOVE_M = 9000.0
_COORD_TOL_DEG = 1e-6     # about 0.1 m; one lattice step is 1 arc-second = 2.8e-4 deg
_EDGE_TOL_DEG = 1e-9


def _number(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _result_coords(r: dict):
    if "latitude" in r or "longitude" in r:
        return r.get("latitude"), r.get("longitude")
    loc = r.get("location")
    if isinstance(loc, dict):
        return loc.get("lat"), loc.get("lng", loc.get("lon"))
    return None


def parse_answer(body: bytes, locations: Sequence[tuple[float, float]]) -> np.ndarray:
    """Elevations (metres) of an answer to ``locations`` [(lat, lon), ...]; Garbage if wrong."""
    try:
        d = json.loads(body)
    except (ValueError, UnicodeDecodeError):
        raise Garbage(f"not JSON (starts with {bytes(body[:40])!r})")
    results = d.get("results") if isinstance(d, dict) else None
    if not isinstance(results, list):
        raise Garbage("JSON without a 'results' list")
    if len(results) != len(locations):
        raise Garbage(f"{len(results)} results for {len(locations)} locations")
    z = np.empty(len(results))
    for k, (r, (lat, lon)) in enumerate(zip(results, locations)):
        if not isinstance(r, dict):
            raise Garbage(f"result {k} is not an object")
        v = _number(r.get("elevation"))
        if v is None:
            raise Garbage(f"result {k} has no numeric elevation ({r.get('elevation')!r})")
        c = _result_coords(r)
        if c is not None:
            rlat, rlon = (_number(x) for x in c)
            if rlat is None or rlon is None or abs(rlat - lat) > _COORD_TOL_DEG or abs(rlon - lon) > _COORD_TOL_DEG:
                raise Garbage(f"result {k} is for {c[0]!r},{c[1]!r}, not the requested {lat},{lon}")
        z[k] = v
    return z


def _fill_voids(z: np.ndarray) -> int:
    """Fill non-finite cells in place from the mean of their valid 4-neighbours, repeatedly."""
    bad = ~np.isfinite(z)
    n = int(bad.sum())
    if n == 0:
        return 0
    if n == z.size:
        raise DataError(f"{SERVICE}: the server has no elevation data for any point of the area")
    while bad.any():
        p = np.pad(np.where(bad, 0.0, z), 1)
        v = np.pad((~bad).astype(float), 1)
        s = p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:]
        c = v[:-2, 1:-1] + v[2:, 1:-1] + v[1:-1, :-2] + v[1:-1, 2:]
        fill = bad & (c > 0)
        z[fill] = s[fill] / c[fill]
        bad &= ~fill
    return n


class OpenElevation(Elevation):
    """An open-elevation server as an :class:`~netgen.dem.Elevation` source (see module doc)."""

    name = "open-elevation"

    def __init__(self, url: str | Sequence[str] | None = None, *, spacing_arcsec: float = 1.0,
                 batch_size: int = 100, cache_dir: str | os.PathLike | None = None,
                 timeout_s: float = 60.0, retries: int = 3,
                 backoff_base_s: float = DEFAULT_BACKOFF_BASE_S, max_wait_s: float = DEFAULT_MAX_WAIT_S,
                 max_points: int = 250_000):
        if url is None:
            self.urls = [DEFAULT_URL]
        elif isinstance(url, str):
            self.urls = [url]
        else:
            self.urls = [u for u in url if u] or [DEFAULT_URL]
        try:
            spacing_arcsec = float(spacing_arcsec)
            batch_size = int(batch_size)
        except (TypeError, ValueError):
            raise InputError("open-elevation: spacing and batch size must be numbers")
        if not 0.1 <= spacing_arcsec <= 60.0:
            raise InputError(f"open-elevation: lattice spacing must be 0.1..60 arc-seconds, got {spacing_arcsec}")
        if batch_size < 1:
            raise InputError(f"open-elevation: batch size must be at least 1, got {batch_size}")
        if cache_dir is None:
            from .config import default_cache_dir
            cache_dir = default_cache_dir()
        self.spacing_arcsec = spacing_arcsec
        self.batch_size = batch_size
        self.cache_dir = cache_dir
        self.timeout_s = float(timeout_s)
        self.retries = int(retries)
        self.backoff_base_s = float(backoff_base_s)
        self.max_wait_s = float(max_wait_s)
        self.max_points = int(max_points)
        self.voids_filled = 0
        self.requests = 0        # batches fetched from a server
        self.attempts = 0        # HTTP attempts, retries included
        self.cached = 0          # batches read from the cache
        self.bbox: tuple[float, float, float, float] | None = None
        self.lats: np.ndarray | None = None    # lattice rows, south to north
        self.lons: np.ndarray | None = None    # lattice columns, west to east
        self.grid: np.ndarray | None = None    # elevations, shape (len(lats), len(lons))

    @classmethod
    def from_config(cls, cfg, **kw) -> "OpenElevation":
        """From a :class:`netgen.config.WorldConfig` (elevation_url, cache and HTTP settings)."""
        return cls(cfg.elevation_url, cache_dir=cfg.cache_path, timeout_s=cfg.http_timeout_s,
                   retries=cfg.http_retries, **kw)

    # --- lattice -------------------------------------------------------------------------
    def _steps(self, lat_c: float) -> tuple[float, float]:
        dlat = self.spacing_arcsec / 3600.0
        return dlat, dlat * max(1, round(1.0 / math.cos(math.radians(lat_c))))

    @staticmethod
    def _axis(lo: float, hi: float, step: float) -> np.ndarray:
        i0 = math.floor(lo / step + 1e-6)
        i1 = math.ceil(hi / step - 1e-6)
        i1 = max(i1, i0 + 1)
        return np.round(np.arange(i0, i1 + 1) * step, 7)

    def prepare(self, south: float, west: float, north: float, east: float) -> "OpenElevation":
        """Fetch (or read from the cache) the lattice covering the bbox; returns self."""
        south, west = check_latlon(south, west, "elevation bbox south-west corner")
        north, east = check_latlon(north, east, "elevation bbox north-east corner")
        if not (south < north and west < east):
            raise InputError(f"elevation bbox: need S < N and W < E, got {south},{west},{north},{east}")
        dlat, dlon = self._steps(0.5 * (south + north))
        lats, lons = self._axis(south, north, dlat), self._axis(west, east, dlon)
        npts = lats.size * lons.size
        if npts > self.max_points:
            raise InputError(f"{SERVICE}: the area needs {npts} lattice points at {self.spacing_arcsec:g}\" "
                             f"spacing (at most {self.max_points}); use a DEM file or a coarser spacing")
        glat, glon = np.meshgrid(lats, lons, indexing="ij")
        pts = list(zip(glat.ravel().tolist(), glon.ravel().tolist()))
        z = np.empty(npts)
        requests = attempts = cached = 0
        for b in range(0, npts, self.batch_size):
            locs = pts[b:b + self.batch_size]
            key = "open-elevation v1\n" + "\n".join(f"{la:.7f},{lo:.7f}" for la, lo in locs)
            got = fetch(SERVICE, self.urls, key=key, cache_dir=self.cache_dir, namespace=NAMESPACE,
                        suffix=".json", method="POST",
                        json_body={"locations": [{"latitude": la, "longitude": lo} for la, lo in locs]},
                        headers={"Accept": "application/json"},
                        validate=lambda body, locs=locs: parse_answer(body, locs),
                        timeout_s=self.timeout_s, retries=self.retries,
                        backoff_base_s=self.backoff_base_s, max_wait_s=self.max_wait_s)
            z[b:b + len(locs)] = parse_answer(got.body, locs)
            cached += got.from_cache
            requests += not got.from_cache
            attempts += got.attempts
        z[(z < VOID_BELOW_M) | (z > VOID_ABOVE_M)] = np.nan
        grid = z.reshape(lats.size, lons.size)
        voids = _fill_voids(grid)
        self.bbox = (south, west, north, east)
        self.lats, self.lons, self.grid = lats, lons, grid
        self.voids_filled = voids
        self.requests, self.attempts, self.cached = requests, attempts, cached
        return self

    # --- Elevation interface ---------------------------------------------------------------
    def _extent(self) -> tuple[float, float, float, float]:
        return float(self.lats[0]), float(self.lons[0]), float(self.lats[-1]), float(self.lons[-1])

    def check_covers(self, south: float, west: float, north: float, east: float) -> None:
        """Prepare the bbox on first use; afterwards DataError if it is outside the lattice."""
        if self.grid is None:
            self.prepare(south, west, north, east)
            return
        s, w, n, e = self._extent()
        t = _EDGE_TOL_DEG
        if south < s - t or west < w - t or north > n + t or east > e + t:
            raise DataError(f"{SERVICE}: bbox {south},{west},{north},{east} is outside the fetched area "
                            f"{s},{w},{n},{e}")

    def sample(self, lon, lat) -> np.ndarray:
        if self.grid is None:
            raise DataError(f"{SERVICE}: no area fetched yet (prepare the bbox first)")
        lon, lat = np.broadcast_arrays(np.asarray(lon, dtype=float), np.asarray(lat, dtype=float))
        s, w, n, e = self._extent()
        t = _EDGE_TOL_DEG
        out = ~((lat >= s - t) & (lat <= n + t) & (lon >= w - t) & (lon <= e + t))
        if out.any():
            k = np.flatnonzero(out.ravel())[0]
            raise DataError(f"{SERVICE}: {int(out.sum())} point(s) outside the fetched area {s},{w},{n},{e}, "
                            f"e.g. lat {lat.ravel()[k]:.6f}, lon {lon.ravel()[k]:.6f}")
        lats, lons, g = self.lats, self.lons, self.grid
        # the lattice coordinates are rounded to 1e-7 degrees: locate cells on the real axes
        i0 = np.clip(np.searchsorted(lats, lat, side="right") - 1, 0, lats.size - 2)
        j0 = np.clip(np.searchsorted(lons, lon, side="right") - 1, 0, lons.size - 2)
        u = np.clip((lat - lats[i0]) / (lats[i0 + 1] - lats[i0]), 0.0, 1.0)
        v = np.clip((lon - lons[j0]) / (lons[j0 + 1] - lons[j0]), 0.0, 1.0)
        return ((1 - u) * (1 - v) * g[i0, j0] + (1 - u) * v * g[i0, j0 + 1]
                + u * (1 - v) * g[i0 + 1, j0] + u * v * g[i0 + 1, j0 + 1])

    def info(self) -> dict:
        d = {"kind": "open-elevation", "url": self.urls[0], "urls": list(self.urls),
             "points": 0 if self.grid is None else int(self.grid.size),
             "requests": int(self.requests), "attempts": int(self.attempts), "cached": int(self.cached),
             "batch_size": self.batch_size, "spacing_arcsec": self.spacing_arcsec,
             "voids_filled": int(self.voids_filled)}
        if self.grid is not None:
            d["bbox"] = list(self.bbox)
            d["lattice"] = {"rows": int(self.lats.size), "cols": int(self.lons.size),
                            "dlat_deg": float(self.lats[1] - self.lats[0]),
                            "dlon_deg": float(self.lons[1] - self.lons[0])}
            d["elevation_range_m"] = [float(np.nanmin(self.grid)), float(np.nanmax(self.grid))]
        return d
