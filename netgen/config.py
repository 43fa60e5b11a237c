"""Build configuration: what place, how big, which elevation, where to put it.

One object, :class:`WorldConfig`, is filled from the CLI (``cosim build``), the GUI and the
``[world]`` table of scenario TOML files; :func:`netgen.build.build_world` takes it.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from .errors import InputError
from .frame import check_latlon, parse_bbox, parse_latlon

QUALITY = {
    # terrain grid spacing (m), scenery density factor, road resampling step (m)
    "low": {"terrain_spacing_m": 10.0, "scenery_density": 0.5, "road_step_m": 5.0},
    "medium": {"terrain_spacing_m": 5.0, "scenery_density": 1.0, "road_step_m": 2.5},
    "high": {"terrain_spacing_m": 2.5, "scenery_density": 1.0, "road_step_m": 1.25},
}

MAX_RINGS = 5


def default_cache_dir() -> Path:
    env = os.environ.get("COSIM_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "cosim"


@dataclass
class WorldConfig:
    # --- place: exactly one of preset / osm / bbox (center alone means Overpass around it) ---
    preset: str | None = None
    osm: str | None = None                   # local .osm / .osm.pbf / .osm.gz / .osm.bz2
    bbox: tuple[float, float, float, float] | None = None   # S, W, N, E -> Overpass
    center: tuple[float, float] | None = None                # lat, lon; the world origin
    # --- size ---
    chunks: int = 1                          # rings around the centre chunk (1 -> 3 x 3)
    chunk_size_m: float = 1000.0
    window: tuple[int, int] = (0, 0)         # the chunk the rings are centred on (streaming)
    # --- elevation: exactly one of dem / elevation_url / flat (or the preset's own) ---
    dem: list[str] = field(default_factory=list)
    elevation_url: str | None = None
    flat: bool = False
    flat_elevation_m: float = 0.0
    # --- web services ---
    overpass_urls: list[str] = field(default_factory=lambda: [
        "https://overpass-api.de/api/interpreter",
        "https://overpass.kumi.systems/api/interpreter",
        "https://maps.mail.ru/osm/tools/overpass/api/interpreter",
    ])
    http_timeout_s: float = 60.0
    http_retries: int = 3
    # --- detail ---
    quality: str = "low"
    terrain_spacing_m: float | None = None   # overrides the quality level's spacing
    # --- output ---
    out: str | None = None
    cache_dir: str | None = None
    jobs: int = 2                             # worker processes for the per-chunk layers

    def validate(self) -> "WorldConfig":
        places = [x for x in (self.preset, self.osm, self.bbox) if x]
        if len(places) > 1:
            raise InputError("give only one of --preset, --osm, --bbox")
        if not places and self.center is None:
            raise InputError("no place given: use --preset NAME, --osm FILE, --bbox S,W,N,E or --center LAT,LON")
        if isinstance(self.bbox, str):
            self.bbox = parse_bbox(self.bbox)
        if isinstance(self.center, str):
            self.center = parse_latlon(self.center, "centre")
        if self.center is not None:
            self.center = check_latlon(*self.center, what="centre")
        if self.bbox is not None:
            s, w, n, e = self.bbox
            check_latlon(s, w, "bbox"), check_latlon(n, e, "bbox")
            if not (s < n and w < e):
                raise InputError("bbox: need S < N and W < E")
        if not isinstance(self.chunks, int) or not 0 <= self.chunks <= MAX_RINGS:
            raise InputError(f"chunks must be a whole number from 0 to {MAX_RINGS}, got {self.chunks!r}")
        if self.quality not in QUALITY:
            raise InputError(f"quality must be one of {', '.join(QUALITY)}, got {self.quality!r}")
        sp = self.spacing
        if not 0.5 <= sp <= 10.0:
            raise InputError(f"terrain spacing must be 0.5..10 m, got {sp}")
        if not 0 < float(self.http_timeout_s) <= 3600:
            raise InputError(f"HTTP timeout must be 0..3600 s, got {self.http_timeout_s}")
        if isinstance(self.http_retries, bool) or not isinstance(self.http_retries, int) or not 0 <= self.http_retries <= 20:
            raise InputError(f"HTTP retries must be a whole number from 0 to 20, got {self.http_retries!r}")
        if isinstance(self.jobs, bool) or not isinstance(self.jobs, int) or not 1 <= self.jobs <= 64:
            raise InputError(f"jobs must be a whole number from 1 to 64, got {self.jobs!r}")
        n_elev = sum(bool(x) for x in (self.dem, self.elevation_url, self.flat))
        if n_elev > 1:
            raise InputError("give only one of --dem, --elevation, --flat")
        if self.osm and not Path(self.osm).exists():
            raise InputError(f"OSM file not found: {self.osm}")
        for d in self.dem:
            if not Path(d).exists():
                raise InputError(f"DEM file not found: {d}")
        return self

    @property
    def spacing(self) -> float:
        return float(self.terrain_spacing_m or QUALITY[self.quality]["terrain_spacing_m"])

    @property
    def cache_path(self) -> Path:
        return Path(self.cache_dir) if self.cache_dir else default_cache_dir()

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "WorldConfig":
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise InputError(f"unknown world setting(s): {', '.join(sorted(unknown))}")
        d = dict(d)
        for k in ("bbox", "center", "window"):
            if isinstance(d.get(k), list):
                d[k] = tuple(d[k])
        if isinstance(d.get("dem"), str):
            d["dem"] = [d["dem"]]
        return cls(**d)

    def fingerprint(self, extra: dict | None = None) -> str:
        """A key of everything that changes the built world (not where it is written)."""
        d = self.to_dict()
        for k in ("out", "cache_dir", "jobs", "http_timeout_s", "http_retries", "overpass_urls"):
            d.pop(k, None)
        d.update(extra or {})
        return hashlib.sha256(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:20]
