"""Mesh files of the world: Wavefront OBJ, one file per layer and tile.

Each file holds many pieces (a lane, a junction, a building) as OBJ groups (``g`` lines)
named by their ids (``edge/-117164342#1``, ``junction/314765499``, ``way/4227351``), so every
face traces back to SUMO and OSM in any tool that opens OBJ. PyBullet loads these files as
static concave collision meshes (tinyobjloader), and trimesh, Blender or MeshLab read them
as they are. Vertices are in world metres, z up, written with millimetre precision.

A chunk (1000 m) is split into tiles (250 m by default) so that the physics world streams
small, merged meshes: a piece belongs to the tile that holds its centroid.
"""
from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from ._atomic import atomic_path


def _lines(fmt: str, arr: np.ndarray) -> str:
    """All rows of `arr` formatted with `fmt` (one line each) in one C-level % operation."""
    if len(arr) == 0:
        return ""
    return (fmt * len(arr)) % tuple(arr.ravel().tolist())


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, groups=None, mtl: str | None = None,
              material: str | None = None) -> None:
    """Write one OBJ. `groups` is a list of (name, face_start, face_end) over `faces`."""
    parts = ["# cosim world mesh: world metres, z up\n"]
    if mtl:
        parts.append(f"mtllib {mtl}\n")
    if material:
        parts.append(f"usemtl {material}\n")
    parts.append(_lines("v %.3f %.3f %.3f\n", np.round(np.asarray(vertices, dtype=float), 3)))
    f1 = np.asarray(faces, dtype=np.int64) + 1
    if not groups:
        parts.append(_lines("f %d %d %d\n", f1))
    else:
        flines = _lines("f %d %d %d\n", f1).splitlines(keepends=True)
        for name, a, b in groups:
            if b > a:
                parts.append(f"g {name}\n")
                parts.append("".join(flines[a:b]))
    with atomic_path(path) as tmp:
        Path(tmp).write_text("".join(parts))


def read_obj_groups(path: Path) -> dict:
    """Group name -> number of faces (for tests and tools)."""
    out, cur = {}, None
    with open(path) as f:
        for line in f:
            if line.startswith("g "):
                cur = line[2:].strip()
                out.setdefault(cur, 0)
            elif line.startswith("f ") and cur is not None:
                out[cur] += 1
    return out


def tile_index(xy: np.ndarray, bounds, tile: float) -> np.ndarray:
    """(n,) tile numbers a*nt+b for points inside chunk bounds (clamped at the border)."""
    xmin, ymin, xmax, ymax = bounds
    nt = max(1, int(round((xmax - xmin) / tile)))
    a = np.clip(((xy[:, 0] - xmin) / tile).astype(int), 0, nt - 1)
    b = np.clip(((xy[:, 1] - ymin) / tile).astype(int), 0, nt - 1)
    return a * nt + b, nt


def split_pieces(vertices, faces, fstart, piece_mask):
    """Sub-mesh of the pieces selected by `piece_mask` (bool per piece), compacted.

    Returns vertices, faces and per-kept-piece (face_start, face_end) in the new face array."""
    sel = np.nonzero(piece_mask)[0]
    if not len(sel):
        return None
    counts = fstart[sel + 1] - fstart[sel]
    idx = np.concatenate([np.arange(fstart[k], fstart[k + 1]) for k in sel]) if len(sel) else np.zeros(0, int)
    F = faces[idx]
    used, inv = np.unique(F.ravel(), return_inverse=True)
    V = vertices[used]
    F = inv.reshape(-1, 3)
    ends = np.cumsum(counts)
    return V, F, sel, ends - counts, ends
