"""Generate the scenery prefab meshes (``*.obj`` + ``*.mtl``) and ``prefabs.json``.

Run ``python models/prefabs/make_prefabs.py`` to rewrite them beside this script. Conventions
for every prefab: metres, z up, the origin at the centre of its base (where it meets the
ground), its front (sign face, signal lights, lamp arm, the side one sits on a bench from)
towards +x; a scenery instance's ``yaw`` turns +x to its facing. Each is light (well under
500 faces). ``prefabs.json`` gives, for the physics loader, each prefab's file, size and one
collision primitive: a ``cylinder`` (radius, height) for trunks and poles, a ``box``
(half_extents) for the bench, with ``offset`` = the primitive's centre relative to the origin
(PyBullet's shapes are centred), and ``rgba``, the colour of its largest part, for loaders
that take one colour per shape.
"""
from __future__ import annotations

import json
import math
import re
import sys
from pathlib import Path

import numpy as np
import trimesh
from shapely.geometry import Polygon
from trimesh.visual.material import SimpleMaterial

HERE = Path(__file__).resolve().parent
FACE_LIMIT = 500


def _mat(name, rgb):
    return trimesh.visual.TextureVisuals(material=SimpleMaterial(name=name, diffuse=[*rgb, 255]))


def _paint(mesh, name, rgb):
    mesh.visual = _mat(name, rgb)
    return mesh


def _cyl(r, h, z0=0.0, sections=8):
    """Vertical cylinder from z0 to z0 + h."""
    m = trimesh.creation.cylinder(radius=r, height=h, sections=sections)
    m.apply_translation((0, 0, z0 + h / 2 - m.bounds[0][2] - h / 2))
    return m


def _box(ext, centre):
    m = trimesh.creation.box(extents=ext)
    m.apply_translation(centre)
    return m


def _plate(poly_yz: Polygon, thickness: float, x0: float):
    """A flat plate whose outline (in the y/z plane) faces +x, from x = x0 to x0 + thickness."""
    m = trimesh.creation.extrude_polygon(poly_yz, thickness)      # outline in x/y, depth along z
    # (x, y, z) -> (z + x0, x, y): the outline's x becomes y, its y becomes z, depth becomes x
    T = np.array([[0, 0, 1, x0], [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]], dtype=float)
    m.apply_transform(T)
    return m


def _regular(n, r, rot, cy=0.0, cz=0.0):
    a = rot + np.arange(n) * 2 * math.pi / n
    return Polygon(np.column_stack([cy + r * np.cos(a), cz + r * np.sin(a)]))


def tree():
    trunk = _paint(_cyl(0.18, 3.2, sections=8), "bark", (95, 70, 45))
    crown = trimesh.creation.icosphere(subdivisions=1, radius=2.4)
    crown.apply_scale((1.0, 1.0, 1.15))
    crown.apply_translation((0, 0, 8.0 - 2.4 * 1.15))
    _paint(crown, "leaves", (60, 125, 55))
    return [trunk, crown], {"type": "cylinder", "radius": 0.18, "height": 3.2, "offset": [0, 0, 1.6]}


def street_lamp():
    pole = _paint(_cyl(0.08, 8.0, sections=8), "lamp_pole", (90, 95, 100))
    arm = _paint(_box((1.5, 0.08, 0.08), (0.75, 0, 7.9)), "lamp_pole", (90, 95, 100))
    head = _paint(_box((0.6, 0.28, 0.14), (1.35, 0, 7.8)), "lamp_head", (235, 230, 190))
    return [pole, arm, head], {"type": "cylinder", "radius": 0.08, "height": 8.0, "offset": [0, 0, 4.0]}


def traffic_signal():
    pole = _paint(_cyl(0.07, 3.0, sections=8), "signal_pole", (70, 75, 80))
    housing = _paint(_box((0.25, 0.34, 0.95), (0.12, 0, 3.0 + 0.475 - 0.1)), "signal_housing", (30, 30, 30))
    parts = [pole, housing]
    for k, (name, rgb) in enumerate((("red", (220, 30, 30)), ("amber", (240, 170, 20)),
                                     ("green", (30, 200, 70)))):
        lamp = trimesh.creation.cylinder(radius=0.1, height=0.04, sections=10)
        lamp.apply_transform(trimesh.transformations.rotation_matrix(math.pi / 2, (0, 1, 0)))
        lamp.apply_translation((0.25 + 0.02, 0, 3.0 + 0.475 - 0.1 + 0.3 - k * 0.3))
        parts.append(_paint(lamp, f"light_{name}", rgb))
    return parts, {"type": "cylinder", "radius": 0.07, "height": 3.0, "offset": [0, 0, 1.5]}


def stop_sign():
    pole = _paint(_cyl(0.035, 2.6, sections=8), "sign_pole", (150, 150, 155))
    r = 0.375 / math.cos(math.pi / 8)          # 750 mm across the flats
    plate = _paint(_plate(_regular(8, r, math.pi / 8, cz=2.2), 0.02, 0.04), "stop_red", (200, 20, 25))
    inner = _paint(_plate(_regular(8, r * 0.9, math.pi / 8, cz=2.2), 0.005, 0.06), "sign_white", (245, 245, 245))
    inner2 = _paint(_plate(_regular(8, r * 0.82, math.pi / 8, cz=2.2), 0.005, 0.065), "stop_red", (200, 20, 25))
    return [pole, plate, inner, inner2], {"type": "cylinder", "radius": 0.035, "height": 2.6,
                                          "offset": [0, 0, 1.3]}


def give_way_sign():
    pole = _paint(_cyl(0.035, 2.5, sections=8), "sign_pole", (150, 150, 155))
    side = 0.9
    rr = side / math.sqrt(3)                   # circumradius of the triangle
    outer = _regular(3, rr, -math.pi / 2, cz=2.1)           # point down
    plate = _paint(_plate(outer, 0.02, 0.04), "giveway_red", (200, 20, 25))
    inner = _paint(_plate(_regular(3, rr * 0.62, -math.pi / 2, cz=2.1 + 0.0), 0.005, 0.06),
                   "sign_white", (245, 245, 245))
    return [pole, plate, inner], {"type": "cylinder", "radius": 0.035, "height": 2.5,
                                  "offset": [0, 0, 1.25]}


def bench():
    wood, metal = ("bench_wood", (150, 105, 60)), ("bench_metal", (60, 60, 65))
    seat = _paint(_box((0.45, 1.8, 0.05), (0.0, 0, 0.45)), *wood)
    back = _paint(_box((0.05, 1.8, 0.4), (-0.22, 0, 0.75)), *wood)
    legs = [_paint(_box((0.5, 0.06, 0.45), (-0.02, y, 0.225)), *metal) for y in (-0.8, 0.8)]
    posts = [_paint(_box((0.05, 0.06, 0.45), (-0.22, y, 0.7)), *metal) for y in (-0.8, 0.8)]
    return [seat, back, *legs, *posts], {"type": "box", "half_extents": [0.25, 0.9, 0.475],
                                         "offset": [-0.02, 0, 0.475]}


PREFABS = {
    "tree": tree, "street_lamp": street_lamp, "traffic_signal": traffic_signal,
    "stop_sign": stop_sign, "give_way_sign": give_way_sign, "bench": bench,
}


def build(out_dir: Path = HERE) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    index = {"version": 1, "units": "m", "up": "+z", "front": "+x", "origin": "base centre",
             "prefabs": {}}
    for name, fn in PREFABS.items():
        parts, collision = fn()
        scene = trimesh.Scene()
        for k, p in enumerate(parts):
            scene.add_geometry(p, node_name=f"{name}_{k}", geom_name=f"{name}_{k}")
        faces = sum(len(p.faces) for p in parts)
        if faces >= FACE_LIMIT:
            raise SystemExit(f"{name}: {faces} faces, over the {FACE_LIMIT} limit")
        obj, files = trimesh.exchange.obj.export_obj(scene, include_normals=True, return_texture=True,
                                                     mtl_name=f"{name}.mtl", header=None, digits=5)
        # a coordinate that rounds to zero is written "0.00000", never "-0.00000": its sign
        # comes from the last bits of the arithmetic, which differ between numpy/trimesh
        # versions, and the files are compared byte for byte with a fresh build
        obj = re.sub(r"(?<![\w.])-(0\.0+)(?![\w.])", r"\1", obj)
        (out_dir / f"{name}.obj").write_text(obj)
        for fname, data in files.items():
            (out_dir / fname).write_bytes(data)
        lo, hi = scene.bounds
        main = max(parts, key=lambda p: p.area)          # its colour, for single-colour loaders
        rgba = [round(float(c) / 255.0, 3) for c in main.visual.material.main_color]
        index["prefabs"][name] = {
            "file": f"{name}.obj", "mtl": f"{name}.mtl", "faces": int(faces), "rgba": rgba,
            "size_m": [round(float(v), 3) for v in hi - lo],
            "bounds": [[round(float(v), 3) for v in lo], [round(float(v), 3) for v in hi]],
            "collision": collision,
        }
    (out_dir / "prefabs.json").write_text(json.dumps(index, indent=1) + "\n")
    return index


if __name__ == "__main__":
    idx = build(Path(sys.argv[1]) if len(sys.argv) > 1 else HERE)
    for k, v in idx["prefabs"].items():
        print(f"{k:15s} {v['faces']:4d} faces  size {v['size_m']}")
