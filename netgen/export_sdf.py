"""Gazebo export: a built world as a folder that Gazebo (gz sim, Ignition, Classic) loads as is.

    cosim export-sdf --world worlds/helsinki --out export/helsinki [--chunks "0,0;1,0"] [--format stl|dae]

Layout of the export (every model is a Gazebo model folder: ``model.config`` + ``model.sdf``,
meshes in its ``meshes/``; every mesh URI is ``model://MODEL/meshes/FILE``)::

    world.sdf                SDF 1.6 world: sun, physics, scene, spherical coordinates, an
                             <include> (model://NAME) of each model below, the ego car
    export.json              manifest: every object (building, scenery object, road tile...)
                             with its model, element, world pose and source (OSM id / file)
    README.md                how to launch it (GZ_SIM_RESOURCE_PATH / GAZEBO_MODEL_PATH=models)
    models/terrain_I_J/      terrain of chunk (I, J): one triangle mesh through every grid node
    models/roads_I_J/        road surfaces: asphalt, sidewalk, rail (collide), marking and deck
                             (bridges' undersides; visual),
                             one element per 250 m tile and layer (``asphalt_A_B``)
    models/areas_I_J/        grass / water areas (visual only)
    models/buildings_I_J/    one element per building, named by its OSM id (``way_123``)
    models/scenery_I_J/      trees, lamps, signal poles, signs, benches: the prefab mesh
                             (model://prefab_KIND/meshes/...) at each object's pose and scale,
                             with the prefab's primitive collision
    models/prefab_KIND/      the scenery prefabs as stand-alone models
    models/cosim_car/        the ego car: model.sdf (converted here) and model.urdf (copied)

Coordinates are the world's (metres, x east, y north, z up = elevation). The per-chunk models
are static, sit at the world origin and hold one link; each object is a visual (+ collision)
whose <pose> is its world pose, with its mesh vertices local to that pose: a building's pose
in the SDF is (centroid x, centroid y, base z) of buildings.json, a scenery object's is
(x, y, z, yaw) of scenery.json, a terrain's / road tile's is its square's centre at z = 0.

Why objects are grouped per chunk rather than one model per building or tree: SDFormat (the
parser in every Gazebo) takes ~45 ms per <include> and ~7 ms per model, but ~1 ms per visual
or collision, so a world of 2000 included models took 180 s to load and the grouped one 5 s.

Meshes: binary STL (one colour each, given by an SDF <material>) or COLLADA 1.4.1 (.dae,
with its materials, face normals, smooth normals on the terrain), written here with numpy;
``--format auto`` (the default) picks STL for quality "low" and DAE for "medium"/"high". The
terrain is a mesh rather than a Gazebo <heightmap>: a heightmap is one square 2^n + 1 image
for the whole world, quantises heights to 8/16 bits and is resampled by each simulator, so
the road meshes (levelled into the terrain to the centimetre) would float or sink; a mesh of
the chunk grid is exact, per chunk, and works with every physics engine.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import re
import shutil
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
import xml.etree.ElementTree as ET
from xml.sax.saxutils import escape

import numpy as np

from .errors import BuildError, CosimError, DataError, InputError
from .meshio import LAYER_COLOURS

EXPORT_FORMAT = "cosim-sdf-export"
EXPORT_FORMAT_VERSION = 1
SDF_VERSION = "1.6"
MESH_FORMATS = ("auto", "stl", "dae")
CAR_MODEL = "cosim_car"
CAR_DROP_M = 0.05          # the car is spawned this far above the road surface

COLOURS = LAYER_COLOURS
ROAD_LAYERS = ("asphalt", "sidewalk", "rail", "marking", "deck")   # tile layers exported as road models
COLLIDE = {"asphalt", "sidewalk", "rail", "building", "terrain"}


class ExportError(BuildError):
    """Writing the export failed."""


# =======================================================================================
# meshes
@dataclass
class Part:
    """A triangle mesh with one material: vertices (n, 3) float64, faces (m, 3) int."""
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    rgba: tuple = (0.7, 0.7, 0.7, 1.0)
    smooth: bool = False         # DAE: per-vertex (smooth) normals instead of face normals

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)

    @property
    def empty(self) -> bool:
        return len(self.faces) == 0

    def moved(self, offset) -> "Part":
        return Part(self.name, self.vertices - np.asarray(offset, dtype=float), self.faces, self.rgba, self.smooth)


def read_obj(path: Path) -> list[Part]:
    """Parts of a Wavefront OBJ, one per ``usemtl`` material (name = material, or 'mesh').

    Handles the world's OBJs (``v x y z`` / ``f a b c``) on a vectorised path and any other
    OBJ (``f a/b/c ...`` polygons, negative indices) on a per-line path. Colours come from
    the ``mtllib`` file's ``Kd`` when there is one."""
    text = Path(path).read_text()
    lines = text.splitlines()
    vl = [ln[2:] for ln in lines if ln.startswith("v ")]
    try:
        V = np.array(" ".join(vl).split(), dtype=np.float64).reshape(-1, 3)
    except ValueError:        # 'v x y z w' or 'v x y z r g b'
        V = np.array([[float(t) for t in ln.split()[:3]] for ln in vl], dtype=np.float64).reshape(-1, 3)
    nv = len(V)
    groups: dict[str, list[str]] = {}
    order: list[str] = []
    cur = "mesh"
    mtl_file = None
    if "usemtl" not in text:                 # the world's OBJs: one material
        groups[cur] = [ln[2:] for ln in lines if ln[:2] == "f "]
        order = [cur] if groups[cur] else []
        mtl = [ln for ln in lines if ln[:7] == "mtllib "]
        mtl_file = mtl[0][7:].strip() if mtl else None
    else:
        for ln in lines:
            if ln.startswith("f "):
                if cur not in groups:
                    groups[cur] = []
                    order.append(cur)
                groups[cur].append(ln[2:])
            elif ln.startswith("usemtl "):
                cur = ln[7:].strip() or "mesh"
            elif ln.startswith("mtllib "):
                mtl_file = ln[7:].strip()
    kd = _read_mtl(Path(path).parent / mtl_file) if mtl_file else {}
    parts = []
    for name in order:
        fl = groups[name]
        joined = " ".join(fl)
        toks = joined.split()
        if "/" not in joined and len(toks) == 3 * len(fl):
            F = np.array(toks, dtype=np.int64).reshape(-1, 3)
        else:
            tri = []
            for ln in fl:
                idx = [int(t.split("/")[0]) for t in ln.split()]
                tri.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
            F = np.array(tri, dtype=np.int64).reshape(-1, 3)
        F = np.where(F < 0, nv + F, F - 1)
        if len(F) and (F.min() < 0 or F.max() >= nv):
            raise DataError(f"{path}: face index out of range (corrupt OBJ)")
        rgba = tuple(kd[name]) + (1.0,) if name in kd else (0.7, 0.7, 0.7, 1.0)
        parts.append(Part(name, V, F, rgba))
    return [compact(p) for p in parts]


def _read_mtl(path: Path) -> dict:
    out, cur = {}, None
    if not path.exists():
        return out
    for ln in path.read_text().splitlines():
        t = ln.split()
        if not t:
            continue
        if t[0] == "newmtl" and len(t) > 1:
            cur = t[1]
        elif t[0] == "Kd" and cur is not None and len(t) >= 4:
            out[cur] = tuple(float(x) for x in t[1:4])
    return out


def compact(p: Part) -> Part:
    """Drop vertices no face uses (OBJ parts share one vertex list)."""
    if p.empty:
        return Part(p.name, np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), p.rgba, p.smooth)
    used, inv = np.unique(p.faces.ravel(), return_inverse=True)
    if len(used) == len(p.vertices):
        return p
    return Part(p.name, p.vertices[used], inv.reshape(-1, 3), p.rgba, p.smooth)


def merge(parts: list[Part], name: str, rgba) -> Part:
    V, F, n = [], [], 0
    for p in parts:
        V.append(p.vertices)
        F.append(p.faces + n)
        n += len(p.vertices)
    return Part(name, np.concatenate(V) if V else np.zeros((0, 3)),
                np.concatenate(F) if F else np.zeros((0, 3), dtype=np.int64), rgba)


def terrain_part(z: np.ndarray, x0: float, y0: float, spacing: float) -> Part:
    """The chunk grid z[row, col] (x = x0 + col*s, y = y0 + row*s) as a triangle mesh with
    its vertices exactly on the grid nodes; each cell is cut along its (col+1, row) - (col, row+1)
    diagonal."""
    ny, nx = z.shape
    xs = x0 + np.arange(nx) * spacing
    ys = y0 + np.arange(ny) * spacing
    X, Y = np.meshgrid(xs, ys)
    V = np.column_stack([X.ravel(), Y.ravel(), np.asarray(z, dtype=np.float64).ravel()])
    idx = np.arange(ny * nx).reshape(ny, nx)
    a = idx[:-1, :-1].ravel()       # (row, col)
    b = idx[:-1, 1:].ravel()        # (row, col+1)
    c = idx[1:, :-1].ravel()        # (row+1, col)
    d = idx[1:, 1:].ravel()         # (row+1, col+1)
    F = np.concatenate([np.column_stack([a, b, c]), np.column_stack([b, d, c])])
    return Part("terrain", V, F, COLOURS["terrain"], smooth=True)


def face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    u, v = b - a, c - a
    n = np.empty_like(u)
    n[:, 0] = u[:, 1] * v[:, 2] - u[:, 2] * v[:, 1]
    n[:, 1] = u[:, 2] * v[:, 0] - u[:, 0] * v[:, 2]
    n[:, 2] = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]
    ln = np.sqrt((n * n).sum(axis=1))
    ok = ln > 1e-12
    n[ok] /= ln[ok, None]
    n[~ok] = (0.0, 0.0, 1.0)
    return n


def vertex_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])   # area weighted
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], n)
    ln = np.linalg.norm(vn, axis=1, keepdims=True)
    out = np.tile([0.0, 0.0, 1.0], (len(V), 1))
    np.divide(vn, ln, out=out, where=ln > 1e-12)
    return out


def stl_bytes(p: Part) -> bytes:
    """Binary STL of one part (float32, face normals)."""
    V, F = p.vertices, p.faces
    rec = np.zeros(len(F), dtype=[("n", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"] = face_normals(V, F)
    rec["v"] = V[F]
    head = (b"cosim export: metres, z up" + b" " * 80)[:80]
    return head + np.uint32(len(F)).tobytes() + rec.tobytes()


def _fmt(arr: np.ndarray, fmt: str) -> str:
    a = np.asarray(arr).ravel()
    if not len(a):
        return ""
    return ((fmt + " ") * len(a) % tuple(a.tolist()))[:-1]


def dae_text(parts: list[Part], title: str = "") -> str:
    """COLLADA 1.4.1 with one geometry and one phong material per part, metres, Z up."""
    now = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime())
    eff, mat, geo, nodes = [], [], [], []
    for k, p in enumerate(parts):
        if p.empty:
            continue
        nm = escape(_safe(p.name) or f"part{k}")
        r, g, b, a = p.rgba
        amb = f"{r * 0.6:.4f} {g * 0.6:.4f} {b * 0.6:.4f} 1"
        eff.append(f'<effect id="e{k}"><profile_COMMON><technique sid="common"><phong>'
                   f'<emission><color>0 0 0 1</color></emission><ambient><color>{amb}</color></ambient>'
                   f'<diffuse><color>{r:.4f} {g:.4f} {b:.4f} {a:.4f}</color></diffuse>'
                   f'<specular><color>0.05 0.05 0.05 1</color></specular><shininess><float>8</float></shininess>'
                   f'</phong></technique></profile_COMMON></effect>')
        mat.append(f'<material id="m{k}" name="{nm}"><instance_effect url="#e{k}"/></material>')
        V, F = p.vertices, p.faces
        if p.smooth:
            N = vertex_normals(V, F)
            prim = np.repeat(F, 2, axis=1)          # (v, n) pairs with n = v
        else:
            N = face_normals(V, F)
            fi = np.arange(len(F))
            prim = np.column_stack([F[:, 0], fi, F[:, 1], fi, F[:, 2], fi])
        geo.append(
            f'<geometry id="g{k}" name="{nm}"><mesh>'
            f'<source id="g{k}p"><float_array id="g{k}pa" count="{V.size}">{_fmt(V, "%.4f")}</float_array>'
            f'<technique_common><accessor source="#g{k}pa" count="{len(V)}" stride="3">'
            f'<param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>'
            f'</accessor></technique_common></source>'
            f'<source id="g{k}n"><float_array id="g{k}na" count="{N.size}">{_fmt(N, "%.4f")}</float_array>'
            f'<technique_common><accessor source="#g{k}na" count="{len(N)}" stride="3">'
            f'<param name="X" type="float"/><param name="Y" type="float"/><param name="Z" type="float"/>'
            f'</accessor></technique_common></source>'
            f'<vertices id="g{k}v"><input semantic="POSITION" source="#g{k}p"/></vertices>'
            f'<triangles material="s{k}" count="{len(F)}">'
            f'<input semantic="VERTEX" source="#g{k}v" offset="0"/>'
            f'<input semantic="NORMAL" source="#g{k}n" offset="1"/>'
            f'<p>{_fmt(prim, "%d")}</p></triangles></mesh></geometry>')
        nodes.append(f'<node id="n{k}" name="{nm}" type="NODE"><instance_geometry url="#g{k}"><bind_material>'
                     f'<technique_common><instance_material symbol="s{k}" target="#m{k}"/></technique_common>'
                     f'</bind_material></instance_geometry></node>')
    return ('<?xml version="1.0" encoding="utf-8"?>\n'
            '<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">\n'
            f'<asset><contributor><authoring_tool>cosim export-sdf</authoring_tool>'
            f'<comments>{escape(title)}</comments></contributor>'
            f'<created>{now}</created><modified>{now}</modified>'
            '<unit name="meter" meter="1"/><up_axis>Z_UP</up_axis></asset>\n'
            f'<library_effects>{"".join(eff)}</library_effects>\n'
            f'<library_materials>{"".join(mat)}</library_materials>\n'
            f'<library_geometries>\n{(chr(10)).join(geo)}\n</library_geometries>\n'
            f'<library_visual_scenes><visual_scene id="scene" name="scene">{"".join(nodes)}'
            '</visual_scene></library_visual_scenes>\n'
            '<scene><instance_visual_scene url="#scene"/></scene>\n</COLLADA>\n')


# =======================================================================================
# SDF text
def _safe(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(s)).strip("_")


def _pose(p) -> str:
    x, y, z, r, pi, yw = (list(p) + [0.0] * 6)[:6]
    return f"{x:.4f} {y:.4f} {z:.4f} {r:.6f} {pi:.6f} {yw:.6f}"


def _g(v: float) -> str:
    return "%.12g" % v


def _pose_exact(p) -> str:
    return " ".join(_g(v) for v in (list(p) + [0.0] * 6)[:6])


def _rgba(c) -> str:
    return " ".join(f"{v:.3f}" for v in c)


@dataclass
class Elem:
    """One object in a static model's link: a mesh visual (one mesh file) at `pose` (the
    model sits at the world origin, so this is the object's world pose), and its collision:
    the same mesh ("mesh"), an SDF primitive geometry (xml, at `col_pose`), or none."""
    name: str
    pose: tuple
    uri: str
    rgba: tuple | None = None      # SDF <material> colour (STL meshes); None: the mesh's own (DAE)
    scale: float = 1.0
    collision: str | None = None
    col_pose: tuple | None = None

    def sdf(self) -> str:
        sc = f"<scale>{self.scale:.4f} {self.scale:.4f} {self.scale:.4f}</scale>" if self.scale != 1.0 else ""
        geom = f"<geometry><mesh><uri>{escape(self.uri)}</uri>{sc}</mesh></geometry>"
        mat = ""
        if self.rgba is not None:
            c = _rgba(self.rgba)
            mat = (f"<material><ambient>{c}</ambient><diffuse>{c}</diffuse>"
                   "<specular>0.05 0.05 0.05 1</specular></material>")
        out = f'      <visual name="{escape(self.name)}"><pose>{_pose(self.pose)}</pose>{geom}{mat}</visual>\n'
        if self.collision == "mesh":
            out += (f'      <collision name="{escape(self.name)}_collision"><pose>{_pose(self.pose)}</pose>'
                    f'{geom}</collision>\n')
        elif self.collision:
            out += (f'      <collision name="{escape(self.name)}_collision">'
                    f'<pose>{_pose(self.col_pose or self.pose)}</pose>{self.collision}</collision>\n')
        return out


@dataclass
class Placed:
    """A world object in the manifest: which model and element hold it, its pose, its source."""
    kind: str
    model: str
    element: str
    pose: tuple
    source: str = ""
    chunk: tuple | None = None
    scale: float = 1.0


@dataclass
class Writer:
    """Writes model folders under ``root/models``; counts files and bytes (thread safe)."""
    root: Path
    mesh_format: str
    files: int = 0
    bytes: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)
    dirs: set = field(default_factory=set)

    def write(self, path: Path, data) -> None:
        if path.parent not in self.dirs:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.dirs.add(path.parent)
        b = data.encode("utf-8") if isinstance(data, str) else data
        path.write_bytes(b)
        with self.lock:
            self.files += 1
            self.bytes += len(b)

    def model_dir(self, name: str) -> Path:
        return self.root / "models" / name

    def config(self, name: str, description: str) -> None:
        self.write(self.model_dir(name) / "model.config",
                   '<?xml version="1.0"?>\n<model>\n'
                   f'  <name>{escape(name)}</name>\n  <version>1.0</version>\n'
                   f'  <sdf version="{SDF_VERSION}">model.sdf</sdf>\n'
                   '  <author><name>cosim export-sdf</name><email>none@example.invalid</email></author>\n'
                   f'  <description>{escape(description)}</description>\n</model>\n')

    def mesh(self, model: str, stem: str, parts: list[Part], rgba=None) -> tuple[str, tuple | None]:
        """Write one mesh file of `parts` into the model's meshes/ folder. STL merges the parts
        (colour `rgba`, default the first part's, returned for an SDF <material>); DAE keeps
        one material per part. Returns (model:// uri, colour or None)."""
        parts = [p for p in parts if not p.empty]
        if self.mesh_format == "dae":
            fn = f"{stem}.dae"
            self.write(self.model_dir(model) / "meshes" / fn, dae_text(parts, f"{model}/{stem}"))
            return f"model://{model}/meshes/{fn}", None
        p = parts[0] if len(parts) == 1 else merge(parts, stem, rgba or parts[0].rgba)
        fn = f"{stem}.stl"
        self.write(self.model_dir(model) / "meshes" / fn, stl_bytes(p))
        return f"model://{model}/meshes/{fn}", tuple(rgba or p.rgba)

    def static_model(self, name: str, elems: list[Elem], description: str) -> None:
        """model.sdf (static, at the origin, one link holding every element) + model.config."""
        self.write(self.model_dir(name) / "model.sdf",
                   f'<?xml version="1.0"?>\n<sdf version="{SDF_VERSION}">\n  <model name="{escape(name)}">\n'
                   '    <static>true</static>\n    <link name="link">\n' + "".join(e.sdf() for e in elems) +
                   '    </link>\n  </model>\n</sdf>\n')
        self.config(name, description)


def _unique(name: str, used: set) -> str:
    n, k = name, 1
    while n in used:
        k += 1
        n = f"{name}_{k}"
    used.add(n)
    return n


# =======================================================================================
# URDF -> SDF
def _rpy_matrix(r, p, y) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _matrix_rpy(R) -> tuple:
    p = math.asin(max(-1.0, min(1.0, -R[2, 0])))
    if abs(R[2, 0]) < 1 - 1e-9:
        r = math.atan2(R[2, 1], R[2, 2])
        y = math.atan2(R[1, 0], R[0, 0])
    else:                                   # gimbal lock: put it all in yaw
        r = 0.0
        y = math.atan2(-R[0, 1], R[1, 1])
    return r, p, y


def _origin(el) -> np.ndarray:
    T = np.eye(4)
    o = el.find("origin") if el is not None else None
    if o is not None:
        xyz = [float(v) for v in (o.get("xyz") or "0 0 0").split()]
        rpy = [float(v) for v in (o.get("rpy") or "0 0 0").split()]
        T[:3, :3] = _rpy_matrix(*rpy)
        T[:3, 3] = xyz
    return T


def _pose_of(T) -> tuple:
    return tuple(T[:3, 3].tolist()) + _matrix_rpy(T[:3, :3])


def urdf_to_sdf(urdf_text: str, mesh_uri=lambda fn: fn, model_name: str | None = None) -> str:
    """Convert a URDF robot to an SDF model (links, joints, inertials, collisions, visuals,
    materials, contact friction). Link poses are resolved to the model frame; each joint sits
    at its child link's origin with its axis in that (= the URDF joint) frame.
    `mesh_uri` maps a URDF mesh filename to the URI written in the SDF."""
    try:
        robot = ET.fromstring(urdf_text.encode("utf-8") if isinstance(urdf_text, str) else urdf_text)
    except ET.ParseError as e:
        raise DataError(f"the car URDF is not valid XML ({e})")
    if robot.tag != "robot":
        raise DataError("the car URDF has no <robot> root")
    name = model_name or robot.get("name") or "robot"
    colours = {}
    for m in robot.findall("material"):
        c = m.find("color")
        if c is not None and m.get("name"):
            colours[m.get("name")] = [float(v) for v in c.get("rgba").split()]
    links = {ln.get("name"): ln for ln in robot.findall("link")}
    joints = robot.findall("joint")
    child_of = {j.find("child").get("link"): j for j in joints}
    roots = [n for n in links if n not in child_of]
    if len(roots) != 1:
        raise DataError(f"the car URDF must have exactly one root link, found {roots}")
    world_T = {roots[0]: np.eye(4)}
    pending = list(joints)
    while pending:
        rest = []
        for j in pending:
            par, ch = j.find("parent").get("link"), j.find("child").get("link")
            if par in world_T:
                world_T[ch] = world_T[par] @ _origin(j)
            else:
                rest.append(j)
        if len(rest) == len(pending):
            raise DataError("the car URDF's joints do not form a tree")
        pending = rest

    def geometry(g) -> str:
        if g is None or not len(g):
            return ""
        s = g[0]
        if s.tag == "box":
            return f"<geometry><box><size>{s.get('size')}</size></box></geometry>"
        if s.tag == "cylinder":
            return (f"<geometry><cylinder><radius>{s.get('radius')}</radius><length>{s.get('length')}</length>"
                    "</cylinder></geometry>")
        if s.tag == "sphere":
            return f"<geometry><sphere><radius>{s.get('radius')}</radius></sphere></geometry>"
        if s.tag == "mesh":
            sc = f"<scale>{s.get('scale')}</scale>" if s.get("scale") else ""
            return f"<geometry><mesh><uri>{escape(mesh_uri(s.get('filename')))}</uri>{sc}</mesh></geometry>"
        raise DataError(f"the car URDF has an unsupported geometry <{s.tag}>")

    out = [f'<?xml version="1.0"?>\n<sdf version="{SDF_VERSION}">\n  <model name="{escape(name)}">\n'
           f'    <static>false</static>\n    <self_collide>false</self_collide>\n']
    for ln_name, ln in links.items():
        out.append(f'    <link name="{escape(ln_name)}">\n'
                   f'      <pose>{_pose_exact(_pose_of(world_T[ln_name]))}</pose>\n')
        ine = ln.find("inertial")
        if ine is not None:
            m = float(ine.find("mass").get("value"))
            it = ine.find("inertia")
            iv = {k: float(it.get(k, 0.0)) for k in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
            out.append(f'      <inertial>\n        <pose>{_pose_exact(_pose_of(_origin(ine)))}</pose>\n'
                       f'        <mass>{_g(m)}</mass>\n        <inertia>' +
                       "".join(f"<{k}>{_g(v)}</{k}>" for k, v in iv.items()) + "</inertia>\n      </inertial>\n")
        mu = None
        ct = ln.find("contact")
        if ct is not None and ct.find("lateral_friction") is not None:
            mu = float(ct.find("lateral_friction").get("value"))
        used = set()
        for kind in ("visual", "collision"):
            for k, el in enumerate(ln.findall(kind)):
                nm = el.get("name") or f"{kind}_{k}"
                while (kind, nm) in used:
                    nm = f"{nm}_{k}"
                used.add((kind, nm))
                geom = geometry(el.find("geometry"))
                if not geom:
                    continue
                extra = ""
                if kind == "visual":
                    mt = el.find("material")
                    rgba = None
                    if mt is not None:
                        c = mt.find("color")
                        rgba = ([float(v) for v in c.get("rgba").split()] if c is not None
                                else colours.get(mt.get("name")))
                    if rgba:
                        extra = (f"<material><ambient>{_rgba(rgba)}</ambient><diffuse>{_rgba(rgba)}</diffuse>"
                                 "<specular>0.1 0.1 0.1 1</specular></material>")
                elif mu is not None:
                    extra = f"<surface><friction><ode><mu>{_g(mu)}</mu><mu2>{_g(mu)}</mu2></ode></friction></surface>"
                out.append(f'      <{kind} name="{escape(nm)}">\n'
                           f'        <pose>{_pose_exact(_pose_of(_origin(el)))}</pose>\n'
                           f'        {geom}\n' + (f"        {extra}\n" if extra else "") + f"      </{kind}>\n")
        out.append("    </link>\n")
    for j in joints:
        jt = j.get("type")
        par, ch = j.find("parent").get("link"), j.find("child").get("link")
        if jt not in ("revolute", "continuous", "prismatic", "fixed"):
            raise DataError(f"the car URDF joint {j.get('name')!r} has type {jt!r}, which SDF export does not handle")
        sdf_type = "revolute" if jt == "continuous" else jt
        body = (f'    <joint name="{escape(j.get("name"))}" type="{sdf_type}">\n'
                f'      <parent>{escape(par)}</parent>\n      <child>{escape(ch)}</child>\n'
                '      <pose>0 0 0 0 0 0</pose>\n')
        if jt != "fixed":
            ax = j.find("axis")
            xyz = ax.get("xyz") if ax is not None else "1 0 0"
            lim = j.find("limit")
            lo, hi = ("-1e16", "1e16") if jt == "continuous" else (
                (lim.get("lower", "0"), lim.get("upper", "0")) if lim is not None else ("0", "0"))
            lims = f"<lower>{lo}</lower><upper>{hi}</upper>"
            if lim is not None:
                if lim.get("effort") is not None:
                    lims += f"<effort>{lim.get('effort')}</effort>"
                if lim.get("velocity") is not None:
                    lims += f"<velocity>{lim.get('velocity')}</velocity>"
            dyn = j.find("dynamics")
            dyns = ""
            if dyn is not None:
                dyns = (f"<dynamics><damping>{dyn.get('damping', '0')}</damping>"
                        f"<friction>{dyn.get('friction', '0')}</friction></dynamics>")
            body += f"      <axis>\n        <xyz>{xyz}</xyz>\n        <limit>{lims}</limit>{dyns}\n      </axis>\n"
        out.append(body + "    </joint>\n")
    out.append("  </model>\n</sdf>\n")
    return "".join(out)


def export_car(w: Writer, urdf_path: Path) -> dict:
    """models/cosim_car: model.urdf (copied; its mesh files copied into meshes/ and referred
    to by relative paths; ``package://PKG/REST`` is looked up as REST beside the URDF) and
    model.sdf (converted, mesh URIs model://cosim_car/meshes/...)."""
    d = w.model_dir(CAR_MODEL)
    text = urdf_path.read_text()
    try:
        tree = ET.fromstring(text.encode("utf-8"), parser=ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
    except ET.ParseError as e:
        raise DataError(f"the car URDF {urdf_path} is not valid XML ({e})")
    meshes = {}
    for m in tree.iter("mesh"):
        fn = m.get("filename") or ""
        src = fn
        if fn.startswith("package://"):
            src = fn.split("/", 3)[-1]
        elif fn.startswith("file://"):
            src = fn[7:]
        p = (urdf_path.parent / src) if not os.path.isabs(src) else Path(src)
        if not p.exists():
            raise DataError(f"the car URDF refers to a mesh {fn!r} that does not exist")
        key = str(p.resolve())
        if key not in meshes:
            rel = f"meshes/{p.name}"
            if rel in meshes.values():                  # same name, another file
                rel = f"meshes/{len(meshes)}_{p.name}"
            w.write(d / rel, p.read_bytes())
            meshes[key] = rel
        m.set("filename", meshes[key])
    # no meshes: the file as it is, byte for byte; else re-serialised (comments kept)
    urdf_out = text if not meshes else '<?xml version="1.0"?>\n' + ET.tostring(tree, encoding="unicode") + "\n"
    w.write(d / "model.urdf", urdf_out)
    sdf = urdf_to_sdf(urdf_out, mesh_uri=lambda fn: f"model://{CAR_MODEL}/{fn}", model_name=CAR_MODEL)
    w.write(d / "model.sdf", sdf)
    w.config(CAR_MODEL, "cosim ego car (converted from models/car/car.urdf; model.urdf is the original)")
    return {"urdf": f"models/{CAR_MODEL}/model.urdf", "sdf": f"models/{CAR_MODEL}/model.sdf",
            "meshes": sorted(set(meshes.values()))}


# =======================================================================================
# the world
def parse_chunks(text: str) -> list[tuple[int, int]]:
    """'0,0;1,0' (or '0,0 1,0') -> [(0, 0), (1, 0)]."""
    out = []
    for item in re.split(r"[;\s]+", str(text).strip()):
        if not item:
            continue
        m = re.fullmatch(r"\(?\s*(-?\d+)\s*[,_]\s*(-?\d+)\s*\)?", item)
        if not m:
            raise InputError(f"--chunks: expected 'I,J;I,J' (e.g. '0,0;1,0'), got {text!r}")
        ij = (int(m.group(1)), int(m.group(2)))
        if ij not in out:
            out.append(ij)
    if not out:
        raise InputError(f"--chunks: no chunk given in {text!r}")
    return out


_GLB_DTYPES = {5121: np.uint8, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}


def _quat_matrix(q) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def read_glb(path: Path) -> dict:
    """Named nodes of a binary glTF: name -> (vertices (n, 3) float64 in scene coordinates,
    faces (m, 3), rgba of its first primitive's material). Triangle primitives only (what
    the world's GLBs hold); anything else is read through trimesh."""
    import struct

    data = Path(path).read_bytes()
    try:
        magic, _ver, _len = struct.unpack_from("<4sII", data, 0)
        if magic != b"glTF":
            raise ValueError(f"{path} is not a GLB file")
        off, js, blob = 12, None, b""
        while off + 8 <= len(data):
            ln, typ = struct.unpack_from("<II", data, off)
            chunk = data[off + 8:off + 8 + ln]
            if typ == 0x4E4F534A:
                js = json.loads(chunk)
            elif typ == 0x004E4942:
                blob = chunk
            off += 8 + ln
        g = js
        mats = g.get("materials", [])

        def accessor(k):
            a = g["accessors"][k]
            if "sparse" in a or "bufferView" not in a:
                raise NotImplementedError("sparse accessor")
            bv = g["bufferViews"][a["bufferView"]]
            dt = np.dtype(_GLB_DTYPES[a["componentType"]])
            ncomp = {"SCALAR": 1, "VEC3": 3}[a["type"]]
            start = bv.get("byteOffset", 0) + a.get("byteOffset", 0)
            stride = bv.get("byteStride") or dt.itemsize * ncomp
            if stride == dt.itemsize * ncomp:
                arr = np.frombuffer(blob, dtype=dt, count=a["count"] * ncomp, offset=start)
            else:
                raw = np.frombuffer(blob, dtype=np.uint8, count=(a["count"] - 1) * stride + dt.itemsize * ncomp,
                                    offset=start)
                arr = np.lib.stride_tricks.as_strided(raw, (a["count"], dt.itemsize * ncomp), (stride, 1)).copy()
                arr = arr.view(dt)
            return arr.reshape(-1, ncomp) if ncomp > 1 else arr

        out = {}

        def visit(k, parent):
            nd = g["nodes"][k]
            M = np.eye(4)
            if "matrix" in nd:
                M = np.array(nd["matrix"], dtype=float).reshape(4, 4).T
            else:
                if "scale" in nd:
                    M[:3, :3] = np.diag(nd["scale"])
                if "rotation" in nd:
                    M[:3, :3] = _quat_matrix(nd["rotation"]) @ M[:3, :3]
                if "translation" in nd:
                    M[:3, 3] = nd["translation"]
            M = parent @ M
            if "mesh" in nd:
                Vs, Fs, n, rgba = [], [], 0, None
                for pr in g["meshes"][nd["mesh"]]["primitives"]:
                    if pr.get("mode", 4) != 4:
                        raise NotImplementedError("non-triangle primitive")
                    V = accessor(pr["attributes"]["POSITION"]).astype(np.float64)
                    F = (accessor(pr["indices"]).astype(np.int64) if "indices" in pr
                         else np.arange(len(V), dtype=np.int64)).reshape(-1, 3)
                    Vs.append(V)
                    Fs.append(F + n)
                    n += len(V)
                    if rgba is None and "material" in pr:
                        rgba = tuple(mats[pr["material"]].get("pbrMetallicRoughness", {})
                                     .get("baseColorFactor", (0.7, 0.7, 0.7, 1.0)))
                V = np.concatenate(Vs) if Vs else np.zeros((0, 3))
                if not np.array_equal(M, np.eye(4)):
                    V = V @ M[:3, :3].T + M[:3, 3]
                name = nd.get("name") or f"node{k}"
                out[name] = (V, np.concatenate(Fs) if Fs else np.zeros((0, 3), dtype=np.int64), rgba)
            for ch in nd.get("children", []):
                visit(ch, M)

        scenes = g.get("scenes")
        scene = scenes[g.get("scene", 0)] if scenes else {"nodes": range(len(g.get("nodes", [])))}
        for k in scene.get("nodes", []):
            visit(k, np.eye(4))
        return out
    except (NotImplementedError, KeyError, IndexError, TypeError, struct.error):
        return _read_glb_trimesh(path)


def _read_glb_trimesh(path: Path) -> dict:
    import trimesh

    sc = trimesh.load(str(path), force="scene", process=False)
    out = {}
    for node in sc.graph.nodes_geometry:
        T, gname = sc.graph[node]
        gm = sc.geometry[gname]
        V = np.asarray(gm.vertices, dtype=np.float64) @ T[:3, :3].T + T[:3, 3]
        rgba = None
        try:
            c = np.asarray(gm.visual.material.baseColorFactor, dtype=float)
            rgba = tuple((c / 255.0 if c.max() > 1.0 else c).tolist())
        except (AttributeError, TypeError, ValueError):
            pass
        out[node] = (V, np.asarray(gm.faces, dtype=np.int64), rgba)
    return out


def _building_parts(path: Path, wanted: dict) -> dict:
    """Building id -> Part (world coordinates, its glb colour) from a chunk's buildings.glb."""
    out = {}
    for name, (V, F, rgba) in read_glb(path).items():
        if name in wanted:
            out[name] = Part("building", V, F, tuple(rgba) if rgba else COLOURS["building"])
    return out


def _area_parts(path: Path, kinds: dict) -> list[Part]:
    """Areas (grass, water...) of a chunk's areas.glb, merged per kind."""
    by_kind: dict = {}
    for name, (V, F, _rgba) in read_glb(path).items():
        kind = kinds.get(name, "areas")
        by_kind.setdefault(kind, []).append(Part(kind, V, F))
    return [merge(ps, k, COLOURS.get(k, COLOURS["areas"])) for k, ps in sorted(by_kind.items())]


_TAG = re.compile(r"<(edge|lane)\s([^>]*)>")
_ATTR = re.compile(r'([\w:.-]+)="([^"]*)"')


def _lanes_for_spawn(net_file: Path, xy_box) -> list:
    """Passenger-car lanes (of normal, not internal, edges) inside xy_box: (length, shape
    (n, 2) array, id). Scans the SUMO network's <edge>/<lane> tags (a regex over the text is
    ~10x faster than an XML parser for a 10 MB network, and needs nothing else from it)."""
    x0, y0, x1, y1 = xy_box
    out = []
    if not net_file.exists():
        return out
    normal = False
    for m in _TAG.finditer(net_file.read_text(errors="replace")):
        at = dict(_ATTR.findall(m.group(2)))
        if m.group(1) == "edge":
            normal = at.get("function", "normal") == "normal"
            continue
        if not normal:
            continue
        allow, disallow = at.get("allow"), at.get("disallow") or ""
        if (allow is not None and not {"passenger", "all"} & set(allow.split())) or \
                {"passenger", "all"} & set(disallow.split()):
            continue
        try:
            pts = np.array([[float(v) for v in p.split(",")[:2]] for p in at["shape"].split()])
            length = float(at.get("length", 0))
        except (KeyError, ValueError):
            continue
        if len(pts) < 2:
            continue
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        if lo[0] >= x0 and hi[0] <= x1 and lo[1] >= y0 and hi[1] <= y1:
            out.append((length, pts, at.get("id")))
    return out


def surface_z(parts: list[Part], x: float, y: float) -> float | None:
    """Highest z of the given meshes' triangles above (x, y), or None."""
    best = None
    for p in parts:
        if p.empty:
            continue
        T = p.vertices[p.faces]                     # (m, 3, 3)
        a, b, c = T[:, 0], T[:, 1], T[:, 2]
        d = (b[:, 1] - c[:, 1]) * (a[:, 0] - c[:, 0]) + (c[:, 0] - b[:, 0]) * (a[:, 1] - c[:, 1])
        ok = np.abs(d) > 1e-12
        with np.errstate(divide="ignore", invalid="ignore"):
            l1 = ((b[:, 1] - c[:, 1]) * (x - c[:, 0]) + (c[:, 0] - b[:, 0]) * (y - c[:, 1])) / d
            l2 = ((c[:, 1] - a[:, 1]) * (x - c[:, 0]) + (a[:, 0] - c[:, 0]) * (y - c[:, 1])) / d
        l3 = 1 - l1 - l2
        inside = ok & (l1 >= -1e-9) & (l2 >= -1e-9) & (l3 >= -1e-9)
        if inside.any():
            z = (l1 * a[:, 2] + l2 * b[:, 2] + l3 * c[:, 2])[inside].max()
            best = float(z) if best is None else max(best, float(z))
    return best


def _pick_car_pose(world, chunks: list, road_parts: dict) -> tuple | None:
    """A spawn pose on a passenger-car lane near the middle of the exported chunks: the
    middle of the lane (>= 20 m long) nearest to that point, heading along it, on the
    asphalt mesh."""
    bs = np.array([world.chunks[ij]["bounds_m"] for ij in chunks], dtype=float)
    box = (bs[:, 0].min(), bs[:, 1].min(), bs[:, 2].max(), bs[:, 3].max())
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    built = {ij for ij in chunks}
    cands = []
    for length, pts, _lid in _lanes_for_spawn(world.net_file, box):
        if length < 20.0:
            continue
        seg = np.diff(pts, axis=0)
        sl = np.hypot(seg[:, 0], seg[:, 1])
        cum = np.concatenate([[0], np.cumsum(sl)])
        half = cum[-1] / 2
        k = min(len(sl) - 1, int(np.searchsorted(cum, half, side="right") - 1))
        t = (half - cum[k]) / sl[k] if sl[k] > 0 else 0.0
        p = pts[k] + t * seg[k]
        cands.append((math.hypot(p[0] - cx, p[1] - cy), float(p[0]), float(p[1]),
                      math.atan2(seg[k][1], seg[k][0])))
    cands.sort()
    for _d, x, y, yaw in cands[:50]:
        i, j, a, b = world.tile_of(x, y)
        if (i, j) not in built:
            continue
        p = road_parts.get((i, j, a, b))
        z = surface_z([p], x, y) if p is not None else None
        if z is None:
            continue
        # pitch from the road under the axles (pitch > 0 is nose down), when both are on it
        half = 1.35
        zf = surface_z([p], x + half * math.cos(yaw), y + half * math.sin(yaw))
        zb = surface_z([p], x - half * math.cos(yaw), y - half * math.sin(yaw))
        pitch = -math.atan2(zf - zb, 2 * half) if zf is not None and zb is not None else 0.0
        return (x, y, z + CAR_DROP_M, 0.0, pitch, yaw)
    return None


def _resolve_format(fmt: str, quality: str) -> str:
    if fmt not in MESH_FORMATS:
        raise InputError(f"--format must be one of {', '.join(MESH_FORMATS)}, got {fmt!r}")
    if fmt == "auto":
        return "dae" if quality in ("medium", "high") else "stl"
    return fmt


def _prepare_out(out: Path) -> Path:
    """Check `out` can be (re)written; returns a fresh temporary folder beside it."""
    out = Path(out)
    if out.exists():
        if not out.is_dir():
            raise InputError(f"--out {out} is a file, not a folder")
        if any(out.iterdir()):
            try:
                prev = json.loads((out / "export.json").read_text())
            except (OSError, ValueError):
                prev = None
            if not (isinstance(prev, dict) and prev.get("format") == EXPORT_FORMAT):
                raise InputError(f"--out {out} is not empty and holds no earlier cosim SDF export: "
                                 "choose a new or empty folder")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        for p in out.parent.glob(out.name + ".tmp-*"):      # leftovers of a killed export
            shutil.rmtree(p, ignore_errors=True)
        return Path(tempfile.mkdtemp(prefix=out.name + ".tmp-", dir=out.parent))
    except OSError as e:
        raise ExportError(f"cannot write {out}: {e.strerror or e}") from None


def _swap_in(tmp: Path, out: Path) -> None:
    """Put the finished export in place of `out` (an earlier export there is removed only
    once the new one is in place)."""
    old = None
    try:
        if out.exists():
            old = out.parent / f"{out.name}.tmp-old-{os.getpid()}"
            os.replace(out, old)
        os.replace(tmp, out)
        os.chmod(out, 0o755)
    except OSError as e:
        if old is not None and not out.exists():
            try:
                os.replace(old, out)
                old = None
            except OSError:
                pass
        raise ExportError(f"cannot write {out}: {e.strerror or e}") from None
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _prefab_models(w: Writer) -> dict:
    """models/prefab_<kind> for every scenery prefab (models/prefabs); returns kind ->
    (mesh uri, STL colour or None, collision dict)."""
    from models import prefab_dir

    meta = json.loads((prefab_dir() / "prefabs.json").read_text())["prefabs"]
    out = {}
    for kind, m in sorted(meta.items()):
        name = f"prefab_{kind}"
        parts = read_obj(prefab_dir() / m["file"])
        uri, rgba = w.mesh(name, kind, parts, rgba=tuple(m.get("rgba", (0.6, 0.6, 0.6, 1.0))))
        col = m["collision"]
        e = Elem(kind, (0, 0, 0, 0, 0, 0), uri, rgba, collision=_primitive(col, 1.0),
                 col_pose=tuple(col.get("offset", (0, 0, 0))) + (0, 0, 0))
        w.static_model(name, [e], f"scenery prefab '{kind}' (from models/prefabs/{m['file']}), base at the origin")
        out[kind] = (uri, rgba, col)
    return out


def _primitive(col: dict, s: float) -> str:
    if col["type"] == "cylinder":
        return (f"<geometry><cylinder><radius>{col['radius'] * s:.4f}</radius>"
                f"<length>{col['height'] * s:.4f}</length></cylinder></geometry>")
    if col["type"] == "box":
        he = col["half_extents"]
        size = " ".join(f"{2 * h * s:.4f}" for h in he)
        return f"<geometry><box><size>{size}</size></box></geometry>"
    if col["type"] == "sphere":
        return f"<geometry><sphere><radius>{col['radius'] * s:.4f}</radius></sphere></geometry>"
    raise DataError(f"prefabs.json: unknown collision type {col['type']!r}")


def _export_chunk(world, ij, w: Writer, prefabs: dict) -> dict:
    """Write the models of one chunk: terrain_I_J, roads_I_J, areas_I_J, buildings_I_J,
    scenery_I_J (those that are not empty). Returns their names, the placed objects and the
    chunk's asphalt meshes per tile (world coordinates, to put the car on a road)."""
    c = world.chunks[ij]
    f = c["files"]
    i, j = ij
    tag = f"{i}_{j}"
    xmin, ymin, xmax, ymax = c["bounds_m"]
    centre = ((xmin + xmax) / 2, (ymin + ymax) / 2, 0.0)
    models: list = []
    placed: list = []
    asphalt: dict = {}
    zero = (0.0, 0.0, 0.0)

    # -- terrain ------------------------------------------------------------------------
    g = world.grid(ij)
    if g is not None:
        name = f"terrain_{tag}"
        part = terrain_part(g.z, g.xmin, g.ymin, g.spacing).moved(centre)
        uri, rgba = w.mesh(name, "terrain", [part])
        w.static_model(name, [Elem("terrain", centre + zero, uri, rgba, collision="mesh")],
                       f"terrain of chunk {i},{j}: {g.z.shape[1]} x {g.z.shape[0]} grid nodes, {g.spacing} m apart")
        models.append(name)
        placed.append(Placed("terrain", name, "terrain", centre + zero, f["terrain"], ij))

    # -- road surfaces, one element per tile and layer ------------------------------------
    name = f"roads_{tag}"
    elems = []
    for ab, layers in sorted(c.get("tiles", {}).items()):
        a, b = (int(v) for v in ab.split("_"))
        x0, y0, x1, y1 = world.tile_bounds((i, j, a, b))
        tc = ((x0 + x1) / 2, (y0 + y1) / 2, 0.0)
        srcs = []
        for layer in ROAD_LAYERS:
            if layer not in layers:
                continue
            p = merge(read_obj(world.path / layers[layer]), layer, COLOURS[layer])
            if p.empty:
                continue
            if layer == "asphalt":
                asphalt[(i, j, a, b)] = p
            stem = f"{layer}_{ab}"
            uri, rgba = w.mesh(name, stem, [p.moved(tc)])
            elems.append(Elem(stem, tc + zero, uri, rgba, collision="mesh" if layer in COLLIDE else None))
            srcs.append(layers[layer])
        if srcs:
            placed.append(Placed("road_tile", name, ab, tc + zero, ";".join(srcs), ij))
    if elems:
        w.static_model(name, elems, f"road surfaces of chunk {i},{j}: asphalt, sidewalk and rail (collide), "
                                    "markings and bridges' undersides (visual only), one element per "
                                    "250 m tile and layer")
        models.append(name)

    # -- grass / water areas (visual only) ----------------------------------------------
    if f.get("scenery_glb"):
        sj = json.loads((world.path / f["scenery_json"]).read_text()) if f.get("scenery_json") else {}
        kinds = {a.get("node", a.get("id")): a.get("kind", "areas") for a in sj.get("areas", [])}
        name = f"areas_{tag}"
        elems = []
        for p in _area_parts(world.path / f["scenery_glb"], kinds):
            if p.empty:
                continue
            uri, rgba = w.mesh(name, _safe(p.name), [p.moved(centre)])
            elems.append(Elem(_safe(p.name), centre + zero, uri, rgba))
        if elems:
            w.static_model(name, elems, f"grass and water areas of chunk {i},{j} (visual only)")
            models.append(name)
            placed.append(Placed("areas", name, "", centre + zero, f["scenery_glb"], ij))

    # -- buildings: one element per building, at (centroid x, centroid y, base z) ------------
    if f.get("buildings_json"):
        recs = json.loads((world.path / f["buildings_json"]).read_text())["buildings"]
        if recs:
            if not f.get("buildings_glb"):
                raise DataError(f"chunk {i},{j} lists {len(recs)} buildings but has no buildings.glb")
            name = f"buildings_{tag}"
            byid = {r["id"]: r for r in recs}
            parts = _building_parts(world.path / f["buildings_glb"], byid)
            elems, used = [], set()
            for bid, r in byid.items():
                p = parts.get(bid)
                if p is None or p.empty:
                    raise DataError(f"building {bid} of chunk {i},{j} has no mesh in {f['buildings_glb']}")
                pos = (float(r["centroid"][0]), float(r["centroid"][1]), float(r["base_z"]))
                el = _unique(_safe(bid), used)
                uri, rgba = w.mesh(name, el, [p.moved(pos)])
                elems.append(Elem(el, pos + zero, uri, rgba, collision="mesh"))
                placed.append(Placed("building", name, el, pos + zero, bid, ij))
            w.static_model(name, elems, f"{len(elems)} buildings of chunk {i},{j}, one element per building "
                                        "named by its OSM id, posed at (centroid x, centroid y, base z)")
            models.append(name)

    # -- scenery: prefab meshes (model://prefab_<kind>) at the instances' poses and scales --
    inst = [s for s in world.scenery(ij) if s.get("kind") in prefabs]
    if inst:
        name = f"scenery_{tag}"
        elems, used = [], set()
        for s in inst:
            kind = s["kind"]
            uri, rgba, col = prefabs[kind]
            sc = float(s.get("scale", 1.0) or 1.0)
            x, y, z, yaw = float(s["x"]), float(s["y"]), float(s["z"]), float(s.get("yaw", 0.0))
            ox, oy, oz = (v * sc for v in col.get("offset", (0, 0, 0)))
            cp = (x + math.cos(yaw) * ox - math.sin(yaw) * oy, y + math.sin(yaw) * ox + math.cos(yaw) * oy,
                  z + oz, 0.0, 0.0, yaw)
            el = _unique(f"{kind}_{_safe(s.get('id', 'x'))}", used)
            elems.append(Elem(el, (x, y, z, 0.0, 0.0, yaw), uri, rgba, scale=sc,
                              collision=_primitive(col, sc), col_pose=cp))
            placed.append(Placed("scenery:" + kind, name, el, (x, y, z, 0.0, 0.0, yaw), str(s.get("id", "")), ij, sc))
        w.static_model(name, elems, f"{len(elems)} scenery objects of chunk {i},{j} (trees, lamps, signals, "
                                    "signs, benches): prefab meshes with their pose and scale")
        models.append(name)
    return {"models": models, "placed": placed, "asphalt": asphalt}


def export_sdf(world_dir, out_dir, chunks=None, mesh_format: str = "auto", car: bool = True,
               progress=None, workers: int | None = None) -> dict:
    """Export the built world at `world_dir` (all chunks, or the (i, j) pairs in `chunks`) as a
    Gazebo world folder at `out_dir` (replacing an earlier export there). Returns the
    manifest (also written to export.json).

    Raises CosimError subclasses with one-line messages: DataError (no world, corrupt
    files), InputError (unknown chunk, bad format, --out holds something else), ExportError
    (cannot write)."""
    from cosim.world import World

    t_start = time.perf_counter()
    prog = progress or (lambda *a, **k: None)
    world = World(world_dir)
    meta = world.meta
    quality = meta.get("quality", "low")
    fmt = _resolve_format(mesh_format, quality)
    if chunks is None:
        sel = sorted(world.chunks)
    else:
        sel = []
        for ij in chunks:
            ij = (int(ij[0]), int(ij[1]))
            if ij not in world.chunks:
                have = sorted(world.chunks)
                raise InputError(f"chunk {ij[0]},{ij[1]} is not in the world at {world.path} (it has "
                                 f"{len(have)} chunks, i {have[0][0]}..{have[-1][0]}, j "
                                 f"{min(h[1] for h in have)}..{max(h[1] for h in have)})")
            if ij not in sel:
                sel.append(ij)
    out = Path(out_dir)
    wp, op = world.path.resolve(), out.resolve()
    if op == wp or wp in op.parents or op in wp.parents:
        raise InputError(f"--out {out} overlaps the world folder {world.path}; choose a folder outside it")
    tmp = _prepare_out(out)
    w = Writer(tmp, fmt)
    timings: dict = {}
    try:
        t0 = time.perf_counter()
        prog("prefabs", 0.0, "scenery prefabs")
        prefabs = _prefab_models(w)
        prog("chunks", 0.0, f"{len(sel)} chunks")
        results = {}
        nw = max(1, min(workers or (os.cpu_count() or 2), 8, len(sel)))
        with ThreadPoolExecutor(max_workers=nw) as pool:
            futs = {pool.submit(_export_chunk, world, ij, w, prefabs): ij for ij in sel}
            for k, fu in enumerate(futs):
                results[futs[fu]] = fu.result()
                prog("chunks", (k + 1) / len(sel), f"chunk {futs[fu][0]},{futs[fu][1]}")
        timings["chunks"] = time.perf_counter() - t0
        models = [m for ij in sel for m in results[ij]["models"]]
        placed = [p for ij in sel for p in results[ij]["placed"]]

        car_info = None
        if car:
            t0 = time.perf_counter()
            prog("car", 0.0, "ego car")
            from models import car_urdf_path

            car_info = export_car(w, car_urdf_path())
            asphalt = {k: v for ij in sel for k, v in results[ij]["asphalt"].items()}
            pose = _pick_car_pose(world, sel, asphalt)
            car_info["placed_on"] = "lane"
            if pose is None:          # no drivable lane in these chunks: the ground at their middle
                bs = np.array([world.chunks[ij]["bounds_m"] for ij in sel], dtype=float)
                x, y = float(bs[:, [0, 2]].mean()), float(bs[:, [1, 3]].mean())
                pose = (x, y, float(world.ground_z(x, y)[0]) + CAR_DROP_M, 0.0, 0.0, 0.0)
                car_info["placed_on"] = "terrain"
            car_info["pose"] = [round(v, 6) for v in pose]
            placed.append(Placed("car", CAR_MODEL, "ego", pose, "models/car/car.urdf",
                                 world.frame.chunk_of(pose[0], pose[1])))
            timings["car"] = time.perf_counter() - t0

        counts = {"chunks": len(sel), "models_in_world": len(models) + int(car_info is not None),
                  "model_folders": len(models) + len(prefabs) + int(car_info is not None),
                  "terrain": sum(1 for p in placed if p.kind == "terrain"),
                  "road_tiles": sum(1 for p in placed if p.kind == "road_tile"),
                  "areas": sum(1 for p in placed if p.kind == "areas"),
                  "buildings": sum(1 for p in placed if p.kind == "building"),
                  "scenery": sum(1 for p in placed if p.kind.startswith("scenery:")),
                  "prefabs": len(prefabs), "car": int(car_info is not None)}
        manifest = {
            "format": EXPORT_FORMAT, "format_version": EXPORT_FORMAT_VERSION, "sdf_version": SDF_VERSION,
            "generator": "cosim export-sdf",
            "world": {"path": str(wp), "name": meta.get("name"), "build_key": meta.get("build_key"),
                      "quality": quality, "center": meta["center"], "chunk_size_m": world.chunk_size},
            "mesh_format": fmt, "chunks": [list(ij) for ij in sel],
            "area_km2": round(len(sel) * world.chunk_size ** 2 / 1e6, 6),
            "models": models + ([CAR_MODEL] if car_info else []),
            "prefabs": {k: v[0] for k, v in prefabs.items()},
            "counts": counts, "car": car_info,
            "objects": [{"kind": p.kind, "model": p.model, "element": p.element,
                         "pose": [round(v, 6) for v in p.pose], "scale": p.scale, "source": p.source,
                         "chunk": list(p.chunk) if p.chunk else None} for p in placed],
            "sources": meta.get("sources", {}),
        }
        w.write(tmp / "world.sdf", world_sdf(meta, models, car_info))
        w.write(tmp / "README.md", readme_text(manifest))
        timings["total"] = time.perf_counter() - t_start
        manifest["timings_s"] = {k: round(v, 3) for k, v in timings.items()}
        manifest["files"] = w.files + 1
        manifest["size_bytes"] = w.bytes          # every file but export.json itself
        w.write(tmp / "export.json", json.dumps(manifest, indent=1))
        manifest["total_bytes"] = w.bytes
        _swap_in(tmp, out)
    except OSError as e:
        shutil.rmtree(tmp, ignore_errors=True)
        fn = getattr(e, "filename", None)
        if fn and wp in Path(fn).resolve().parents:
            raise DataError(f"cannot read {fn}: {e.strerror or e} (rebuild the world)") from e
        raise ExportError(f"cannot write {out}: {e.strerror or e}") from e
    except (ValueError, KeyError, IndexError, TypeError) as e:
        shutil.rmtree(tmp, ignore_errors=True)
        raise DataError(f"the world at {world.path} has a corrupt or unexpected file "
                        f"({type(e).__name__}: {e}); rebuild it") from e
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    prog("done", 1.0, f"{len(models)} models")
    manifest["out"] = str(out)
    return manifest


def world_sdf(meta: dict, models: list[str], car_info) -> str:
    """world.sdf: sun, physics, scene, spherical coordinates, an <include> per model (all
    static models at the origin) and the ego car at its pose. No <gui> and no <plugin>: each
    simulator then loads its default GUI layout and systems."""
    c = meta["center"]
    name = _safe(meta.get("name") or "cosim_world") or "cosim_world"
    inc = [f'    <include>\n      <uri>model://{m}</uri>\n      <name>{m}</name>\n      <static>true</static>\n'
           '      <pose>0 0 0 0 0 0</pose>\n    </include>\n' for m in models]
    if car_info:
        inc.append(f'    <include>\n      <uri>model://{CAR_MODEL}</uri>\n      <name>ego</name>\n'
                   f'      <pose>{_pose(car_info["pose"])}</pose>\n    </include>\n')
    return (f'<?xml version="1.0"?>\n<!-- cosim export-sdf: world "{escape(str(meta.get("name")))}". '
            'Map data (c) OpenStreetMap contributors, ODbL 1.0. Launch: see README.md. -->\n'
            f'<sdf version="{SDF_VERSION}">\n  <world name="{name}">\n'
            '    <gravity>0 0 -9.81</gravity>\n'
            '    <physics name="1ms" type="ode" default="true">\n      <max_step_size>0.001</max_step_size>\n'
            '      <real_time_factor>1</real_time_factor>\n      <real_time_update_rate>1000</real_time_update_rate>\n'
            '    </physics>\n'
            '    <scene>\n      <ambient>0.45 0.45 0.45 1</ambient>\n      <background>0.70 0.80 0.92 1</background>\n'
            '      <shadows>true</shadows>\n      <grid>false</grid>\n    </scene>\n'
            '    <spherical_coordinates>\n      <surface_model>EARTH_WGS84</surface_model>\n'
            '      <world_frame_orientation>ENU</world_frame_orientation>\n'
            f'      <latitude_deg>{c["lat"]:.8f}</latitude_deg>\n      <longitude_deg>{c["lon"]:.8f}</longitude_deg>\n'
            '      <elevation>0</elevation>\n      <heading_deg>0</heading_deg>\n    </spherical_coordinates>\n'
            '    <light type="directional" name="sun">\n      <cast_shadows>true</cast_shadows>\n'
            '      <pose>0 0 1000 0 0 0</pose>\n      <diffuse>0.85 0.85 0.80 1</diffuse>\n'
            '      <specular>0.20 0.20 0.20 1</specular>\n'
            '      <attenuation>\n        <range>20000</range>\n        <constant>0.9</constant>\n'
            '        <linear>0.0</linear>\n        <quadratic>0.0</quadratic>\n      </attenuation>\n'
            '      <direction>-0.4 0.3 -0.87</direction>\n    </light>\n'
            + "".join(inc) + "  </world>\n</sdf>\n")


def readme_text(m: dict) -> str:
    c = m["counts"]
    osm = m.get("sources", {}).get("osm", {})
    car = m.get("car")
    chunks = " ".join(f"{i},{j}" for i, j in m["chunks"])
    car_line = ("The ego car (`ego`, model `" + CAR_MODEL + "`) stands on a lane at x, y, z, yaw = "
                + ", ".join(f"{v:.2f}" for v in (car["pose"][:3] + [car["pose"][5]])) + " (metres, radians).\n"
                if car else "The ego car was not exported (--no-car).\n")
    return f"""# {m['world']['name']}: a Gazebo world exported by cosim

Exported by `cosim export-sdf` from the cosim world `{m['world']['path']}` (quality
{m['world']['quality']}): {c['chunks']} chunk(s) of {m['world']['chunk_size_m']:.0f} m ({m['area_km2']} km²;
chunks {chunks}) with {c['road_tiles']} road tiles, {c['buildings']} buildings and {c['scenery']}
scenery objects; meshes as {m['mesh_format'].upper()}.

## Launch

Every `model://NAME` URI (in `world.sdf` and in the models' mesh URIs) is a folder in
`models/`: put that folder on the simulator's resource path and open the world from here.

```sh
# Gazebo (gz sim: Garden, Harmonic, Ionic)
export GZ_SIM_RESOURCE_PATH="$PWD/models${{GZ_SIM_RESOURCE_PATH:+:$GZ_SIM_RESOURCE_PATH}}"
gz sim world.sdf

# Ignition Gazebo Fortress
export IGN_GAZEBO_RESOURCE_PATH="$PWD/models${{IGN_GAZEBO_RESOURCE_PATH:+:$IGN_GAZEBO_RESOURCE_PATH}}"
ign gazebo world.sdf

# Gazebo Classic 11
export GAZEBO_MODEL_PATH="$PWD/models${{GAZEBO_MODEL_PATH:+:$GAZEBO_MODEL_PATH}}"
gazebo --verbose world.sdf
```

## What is in it

- `world.sdf`: SDF {m['sdf_version']}: a directional sun, ODE physics at 1 kHz, spherical
  coordinates (the origin is lat/lon {m['world']['center']['lat']:.6f}, {m['world']['center']['lon']:.6f},
  ENU, elevation 0) and an `<include>` of each model below.
- Per chunk I_J (a {m['world']['chunk_size_m']:.0f} m square), static models, all at the world origin, each
  with one link whose visuals and collisions sit at their objects' world poses:
  - `terrain_I_J`: the terrain, a triangle mesh through every node of the chunk's grid;
  - `roads_I_J`: asphalt, sidewalk and rail surfaces (with collision), road markings and
    bridges' undersides (visual only), one element per 250 m tile and layer (`asphalt_A_B`, ...);
  - `areas_I_J`: grass and water areas (visual only);
  - `buildings_I_J`: one element per building, named by its OSM id (`way_123`), at
    (centroid x, centroid y, base z) of the world's `buildings.json`;
  - `scenery_I_J`: trees, street lamps, signal poles, signs and benches: the prefab meshes
    of `models/prefab_<kind>` at each object's pose and scale, with a primitive collision.
- `models/prefab_<kind>`: the scenery prefabs as stand-alone models.
- `models/{CAR_MODEL}`: the ego car as SDF (`model.sdf`, used by the world) and as URDF
  (`model.urdf`, the original). It has no drive plugin: it stands where it is put.
- `export.json`: every object (building, scenery object, road tile, ...) with its model,
  element, world pose and source (OSM id or world file).

Coordinates: metres, x east, y north, z up (elevation), the world's transverse Mercator
frame (`world.json` projection). Poses are x y z roll pitch yaw.

Why objects are grouped per chunk: SDFormat, the parser inside every Gazebo, reads about
20 `<include>`s or 150 models per second but about 1000 visuals or collisions, so a world
with one model per building and tree would take minutes to open.

{car_line}
## Licence

Map data {osm.get('attribution', '© OpenStreetMap contributors')}, {osm.get('licence', 'ODbL 1.0')}
({osm.get('place', '')}). Any public use of this export must credit OpenStreetMap.
"""


# =======================================================================================
# command line
def add_export_parser(subparsers) -> argparse.ArgumentParser:
    """Add ``export-sdf`` to a ``cosim`` sub-parser set (call from cosim/cli.py)."""
    p = subparsers.add_parser(
        "export-sdf", help="export a built world as a Gazebo (SDF) world folder",
        description="Write a folder that Gazebo loads as it is: world.sdf (sun, physics, terrain, roads, "
                    "buildings, scenery, the ego car) and one model folder per model with STL or COLLADA "
                    "meshes. See README.md in the export for how to launch it.")
    p.add_argument("--world", required=True, metavar="DIR", help="a world folder written by `cosim build`")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="export folder (created; an earlier export there is replaced)")
    p.add_argument("--chunks", metavar="I,J;I,J", default=None,
                   help="export only these chunks (default: all). Write --chunks=\"-1,0;0,0\" "
                        "(with '=') when the first index is negative")
    p.add_argument("--format", dest="mesh_format", choices=MESH_FORMATS, default="auto",
                   help="mesh files: stl, dae (COLLADA with materials), or auto: stl for quality low, "
                        "dae for medium/high (default auto)")
    p.add_argument("--no-car", action="store_true", help="do not export or place the ego car")
    p.add_argument("--json", action="store_true", help="print the manifest (export.json) instead of the report")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.add_argument("-v", "--verbose", action="store_true", help="progress lines even when stderr is not a terminal")
    p.set_defaults(func=cmd_export_sdf)
    return p


def cmd_export_sdf(a) -> int:
    import sys

    chunks = parse_chunks(a.chunks) if a.chunks else None
    progress = None
    try:
        from cosim.cli import Progress

        progress = Progress(quiet=a.quiet, verbose=a.verbose)
    except ImportError:
        pass
    m = export_sdf(a.world, a.out, chunks=chunks, mesh_format=a.mesh_format, car=not a.no_car, progress=progress)
    if a.json:
        print(json.dumps(m, indent=1))
        return 0
    c = m["counts"]
    print(f"export     {m['out']}  ({m['mesh_format'].upper()} meshes, SDF {m['sdf_version']})")
    print(f"area       {c['chunks']} chunks, {m['area_km2']} km²")
    print(f"objects    {c['terrain']} terrain chunks, {c['road_tiles']} road tiles, {c['buildings']} buildings, "
          f"{c['scenery']} scenery objects, car {'yes' if c['car'] else 'no'}")
    print(f"models     {c['models_in_world']} in world.sdf, {c['model_folders']} model folders")
    print(f"size       {m['total_bytes'] / 1e6:.1f} MB in {m['files']} files, {m['timings_s']['total']:.2f} s")
    print(f"launch     cd {m['out']} && GZ_SIM_RESOURCE_PATH=$PWD/models gz sim world.sdf   (see README.md)")
    sys.stdout.flush()
    return 0


def main(argv=None) -> int:
    """``python -m netgen.export_sdf ...``: the same command outside cosim's CLI."""
    import sys

    p = argparse.ArgumentParser(prog="python -m netgen.export_sdf")
    sub = p.add_subparsers(dest="cmd")
    add_export_parser(sub)
    a = p.parse_args(["export-sdf"] + list(sys.argv[1:] if argv is None else argv))
    try:
        return a.func(a) or 0
    except CosimError as e:
        if os.environ.get("COSIM_DEBUG"):
            raise
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code


if __name__ == "__main__":
    raise SystemExit(main())
