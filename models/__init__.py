"""Simulation assets (URDF models and meshes) shipped as package data."""
from __future__ import annotations

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent


def car_urdf_path() -> Path:
    """Absolute path of the ego car's URDF (``models/car/car.urdf``)."""
    return MODELS_DIR / "car" / "car.urdf"


def prefab_dir() -> Path:
    """Folder of the scenery prefabs (``models/prefabs``: OBJ meshes and prefabs.json)."""
    return MODELS_DIR / "prefabs"
