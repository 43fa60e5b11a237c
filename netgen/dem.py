"""Elevation sources (skeleton; being filled in)."""
from __future__ import annotations

import numpy as np


class Elevation:
    """Interface of every elevation source.

    ``sample(lon, lat)`` takes arrays of degrees and returns metres above the source's datum,
    bilinearly interpolated; ``check_covers(s, w, n, e)`` raises DataError naming what is
    missing when the source does not cover a bbox; ``info()`` describes the source for
    world.json's ``sources`` and the build report (kind, files, voids_filled, ...).
    """

    name = "elevation"
    voids_filled = 0

    def sample(self, lon, lat) -> np.ndarray:
        raise NotImplementedError

    def check_covers(self, south: float, west: float, north: float, east: float) -> None:
        return None

    def info(self) -> dict:
        return {"kind": self.name, "voids_filled": int(self.voids_filled)}


class FlatElevation(Elevation):
    name = "flat"

    def __init__(self, z: float = 0.0):
        self.z = float(z)

    def sample(self, lon, lat) -> np.ndarray:
        return np.full(np.shape(np.asarray(lon, dtype=float)), self.z)

    def info(self) -> dict:
        return {"kind": "flat", "elevation_m": self.z, "voids_filled": 0}
