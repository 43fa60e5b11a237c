"""Embedded presets: one small TOML file per preset in ``netgen/presets/``, plus its OSM file.

Presets are data: drop a new ``NAME.toml`` (and the OSM file it names) into that folder, or
into a folder listed in the ``COSIM_PRESETS`` environment variable, and it shows up in
``cosim presets``.

A preset's fields: ``name``, ``place``, ``environment`` (city block / neighbourhood / freeway),
``description``, ``osm`` (its file, next to the TOML), ``osm_date``, ``center`` [lat, lon],
``elevation`` (``"flat"`` or a DEM file next to the TOML), ``flat_elevation_m``, and
``traffic_scale`` (default 1): the named traffic densities (``light``, ``normal``, ``dense``)
are multiplied by it in the worlds built from the preset, so that ``normal`` means the usual
traffic of that kind of place (a number of vehicles per km² is taken as it is).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from ..errors import InputError

PRESET_DIR = Path(__file__).resolve().parent
DEFAULT_PRESET = "helsinki"


@dataclass(frozen=True)
class Preset:
    name: str
    place: str
    environment: str
    osm: Path
    center: tuple[float, float]
    description: str = ""
    osm_date: str = ""
    elevation: str = "flat"           # "flat", or a DEM file path relative to the preset dir
    flat_elevation_m: float = 0.0
    traffic_scale: float = 1.0        # the named traffic densities (light/normal/dense) x this
    extra: dict = field(default_factory=dict)


def _preset_dirs() -> list[Path]:
    dirs = [PRESET_DIR]
    for p in os.environ.get("COSIM_PRESETS", "").split(os.pathsep):
        if p:
            dirs.append(Path(p))
    return dirs


def _load(path: Path) -> Preset:
    try:
        d = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as e:
        raise InputError(f"preset file {path}: {e}")
    try:
        lat, lon = d["center"]
        known = {"name", "place", "environment", "osm", "center", "description", "osm_date",
                 "elevation", "flat_elevation_m", "traffic_scale"}
        scale = float(d.get("traffic_scale", 1.0))
        if not 0.0 < scale <= 10.0:
            raise ValueError(f"traffic_scale must be in (0, 10], got {scale:g}")
        return Preset(name=d.get("name", path.stem), place=d["place"], environment=d["environment"],
                      osm=(path.parent / d["osm"]).resolve(), center=(float(lat), float(lon)),
                      description=d.get("description", ""), osm_date=str(d.get("osm_date", "")),
                      elevation=d.get("elevation", "flat"),
                      flat_elevation_m=float(d.get("flat_elevation_m", 0.0)), traffic_scale=scale,
                      extra={k: v for k, v in d.items() if k not in known})
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(f"preset file {path} is missing or has a bad field: {e}")


def list_presets() -> list[Preset]:
    seen: dict[str, Preset] = {}
    for d in _preset_dirs():
        for p in sorted(d.glob("*.toml")):
            pr = _load(p)
            seen.setdefault(pr.name, pr)
    return list(seen.values())


def get_preset(name: str) -> Preset:
    for p in list_presets():
        if p.name == name:
            return p
    names = ", ".join(p.name for p in list_presets())
    raise InputError(f"unknown preset {name!r} (known: {names})")
