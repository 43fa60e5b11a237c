"""The world frame: one projection for SUMO, meshes, terrain and the physics world.

The reference coordinate (centre lat/lon) is the origin. The projection is a transverse
Mercator centred on it (scale 1 at the origin, so metres are metres to well under 0.01 % over
a few km). netconvert gets the same proj string with normalisation off, so SUMO's network
coordinates *are* world coordinates (netOffset 0,0); ``world.json`` records both so that any
tool can map lat/lon to x/y with PROJ alone.

Chunks are squares of ``chunk_size_m`` on a grid; chunk (0, 0) is centred on the origin, and
chunk (i, j) spans x in [(i - 1/2) s, (i + 1/2) s], y in [(j - 1/2) s, (j + 1/2) s].
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from pyproj import Transformer

from .errors import InputError


def check_latlon(lat: float, lon: float, what: str = "coordinate") -> tuple[float, float]:
    """Validate a latitude/longitude pair and return it as floats."""
    try:
        lat, lon = float(lat), float(lon)
    except (TypeError, ValueError):
        raise InputError(f"{what}: latitude and longitude must be numbers, got {lat!r}, {lon!r}")
    if not math.isfinite(lat) or not -90.0 <= lat <= 90.0:
        raise InputError(f"{what}: latitude {lat} is out of range (-90..90)")
    if not math.isfinite(lon) or not -180.0 <= lon <= 180.0:
        raise InputError(f"{what}: longitude {lon} is out of range (-180..180)")
    if abs(lat) > 84.0:
        raise InputError(f"{what}: latitude {lat} is too close to a pole for a driving world (|lat| <= 84)")
    return lat, lon


def parse_latlon(text: str, what: str = "coordinate") -> tuple[float, float]:
    """Parse 'LAT,LON' into a validated pair."""
    parts = [p.strip() for p in str(text).replace(";", ",").split(",")]
    if len(parts) != 2:
        raise InputError(f"{what}: expected LAT,LON, got {text!r}")
    return check_latlon(parts[0], parts[1], what)


def parse_bbox(text: str) -> tuple[float, float, float, float]:
    """Parse 'S,W,N,E' (Overpass order) into a validated bbox."""
    parts = [p.strip() for p in str(text).split(",")]
    if len(parts) != 4:
        raise InputError(f"bbox: expected S,W,N,E, got {text!r}")
    try:
        s, w, n, e = (float(p) for p in parts)
    except ValueError:
        raise InputError(f"bbox: S,W,N,E must be numbers, got {text!r}")
    check_latlon(s, w, "bbox south-west corner")
    check_latlon(n, e, "bbox north-east corner")
    if not (s < n and w < e):
        raise InputError(f"bbox: need S < N and W < E, got {text!r}")
    return s, w, n, e


@dataclass(frozen=True)
class WorldFrame:
    center_lat: float
    center_lon: float
    chunk_size_m: float = 1000.0

    def __post_init__(self):
        check_latlon(self.center_lat, self.center_lon, "centre")
        if not 50.0 <= float(self.chunk_size_m) <= 10000.0:
            raise InputError(f"chunk size {self.chunk_size_m} m is out of range (50..10000)")

    # --- projection -------------------------------------------------------------------
    @property
    def proj_string(self) -> str:
        return (f"+proj=tmerc +lat_0={self.center_lat:.7f} +lon_0={self.center_lon:.7f} +k=1 "
                "+x_0=0 +y_0=0 +ellps=WGS84 +datum=WGS84 +units=m +no_defs")

    net_offset = (0.0, 0.0)

    @cached_property
    def _fwd(self) -> Transformer:
        return Transformer.from_crs("EPSG:4326", self.proj_string, always_xy=True)

    @cached_property
    def _inv(self) -> Transformer:
        return Transformer.from_crs(self.proj_string, "EPSG:4326", always_xy=True)

    def to_xy(self, lon, lat):
        """lon/lat (degrees, scalars or arrays) -> world x/y in metres."""
        x, y = self._fwd.transform(np.asarray(lon, dtype=float), np.asarray(lat, dtype=float))
        return x, y

    def to_lonlat(self, x, y):
        lon, lat = self._inv.transform(np.asarray(x, dtype=float), np.asarray(y, dtype=float))
        return lon, lat

    # --- chunks -------------------------------------------------------------------------
    def chunk_bounds(self, i: int, j: int) -> tuple[float, float, float, float]:
        s = float(self.chunk_size_m)
        return ((i - 0.5) * s, (j - 0.5) * s, (i + 0.5) * s, (j + 0.5) * s)

    def chunk_of(self, x: float, y: float) -> tuple[int, int]:
        s = float(self.chunk_size_m)
        return (int(math.floor(x / s + 0.5)), int(math.floor(y / s + 0.5)))

    @staticmethod
    def ring(rings: int, ci: int = 0, cj: int = 0) -> list[tuple[int, int]]:
        """Chunks within `rings` of chunk (ci, cj): rings=1 gives 3 x 3."""
        return [(ci + di, cj + dj) for dj in range(-rings, rings + 1) for di in range(-rings, rings + 1)]

    def extent(self, chunks) -> tuple[float, float, float, float]:
        b = np.array([self.chunk_bounds(i, j) for i, j in chunks])
        return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())

    def bbox_lonlat(self, extent, margin_m: float = 0.0) -> tuple[float, float, float, float]:
        """(south, west, north, east) that covers a metric extent plus a margin."""
        xmin, ymin, xmax, ymax = extent
        xs = np.array([xmin - margin_m, xmax + margin_m, xmax + margin_m, xmin - margin_m,
                       0.5 * (xmin + xmax), 0.5 * (xmin + xmax)])
        ys = np.array([ymin - margin_m, ymin - margin_m, ymax + margin_m, ymax + margin_m,
                       ymin - margin_m, ymax + margin_m])
        lon, lat = self.to_lonlat(xs, ys)
        return float(lat.min()), float(lon.min()), float(lat.max()), float(lon.max())

    def to_json(self) -> dict:
        return {"proj": self.proj_string, "net_offset": list(self.net_offset), "crs": "EPSG:4326 -> proj"}
