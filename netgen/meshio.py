"""Mesh files of the world: Wavefront OBJ, one file per layer and tile, and binary glTF (GLB).

Each OBJ file holds many pieces (a lane, a junction, a building) as OBJ groups (``g`` lines)
named by their ids (``edge/-117164342#1``, ``junction/314765499``, ``way/4227351``), so every
face traces back to SUMO and OSM in any tool that opens OBJ. PyBullet loads these files as
static concave collision meshes (tinyobjloader), and trimesh, Blender or MeshLab read them
as they are. Vertices are in world metres, z up, written with millimetre precision.

A chunk (1000 m) is split into tiles (250 m by default) so that the physics world streams
small, merged meshes: a piece belongs to the tile that holds its centroid.

Speed: a world is tens of MB of mesh text, so the text is made by numpy, not by Python's
string formatting: numbers become rows of ASCII digits in a fixed-width byte matrix whose
padding is masked out (:func:`_ascii_lines`); the result is the same text as
``"v %.3f %.3f %.3f"`` / ``"f %d %d %d"`` (except that a coordinate which rounds to zero is
written ``0.000``, never ``-0.000``). GLB files (one named node per building or area, for
viewers) are assembled the same way, straight from vertex and face arrays
(:func:`glb_bytes`), instead of through thousands of trimesh objects.

Files inside a world being built are written with :func:`write_file`: a temporary name and a
rename, so a killed build never leaves a half-written file under its final name, but no
fsync per file (the world folder is itself renamed into place only when complete).
"""
from __future__ import annotations

import json
import os
import struct
from pathlib import Path

import numpy as np

from ._atomic import disk_error


# layer colours (RGBA), shared by the PyBullet view and the Gazebo export so both look alike
LAYER_COLOURS = {
    "asphalt": (0.23, 0.23, 0.25, 1.0),
    "sidewalk": (0.62, 0.61, 0.58, 1.0),
    "marking": (0.95, 0.95, 0.92, 1.0),
    "building": (0.80, 0.74, 0.64, 1.0),
    "terrain": (0.42, 0.55, 0.33, 1.0),
    "grass": (0.36, 0.62, 0.30, 1.0),
    "water": (0.25, 0.45, 0.70, 1.0),
    "areas": (0.36, 0.62, 0.30, 1.0),
    "rail": (0.45, 0.40, 0.36, 1.0),
    "deck": (0.55, 0.55, 0.53, 1.0),
}


# ---------------------------------------------------------------------------------------
# vectorised text
# ---------------------------------------------------------------------------------------
#: "000" .. "999" as ASCII: numbers are written three digits at a time, one table per digit
_TRIPLES = [np.array([ord(f"{i:03d}"[d]) for i in range(1000)], dtype=np.uint8) for d in range(3)]


def _ascii_lines(prefix: bytes, values: np.ndarray, decimals: int) -> tuple[bytes, np.ndarray]:
    """Lines ``prefix v0 v1 ...\n`` for the rows of `values` (n, k), numbers written like
    ``%.3f`` (decimals=3) or ``%d`` (decimals=0).

    Returns the text and the (n + 1,) byte offsets of the line starts (and the end). The
    lines are laid out as a fixed-width byte matrix, built column by column (transposed, so
    every write is contiguous): sign, integer digits in groups of three, decimals; the unused
    sign and leading zeros are NUL bytes, deleted from the whole text at once (no digit,
    sign or separator is NUL; ``bytes.translate`` is several times faster than a numpy mask)."""
    if decimals not in (0, 3):
        raise ValueError("decimals must be 0 or 3")
    if 0 in prefix:
        raise ValueError("prefix must not contain NUL bytes")
    values = np.asarray(values)
    n, k = values.shape
    if n == 0:
        return b"", np.zeros(1, dtype=np.int64)
    if decimals:
        m = np.rint(np.asarray(values, dtype=float) * 1000.0).astype(np.int64)
    else:
        m = values.astype(np.int64)
    neg = (m < 0).T                                  # transposed from here on: row j = column j
    ip = np.abs(m).T
    if ip.max() < 2 ** 31:
        ip = ip.astype(np.int32)                     # faster digit arithmetic
    else:
        ip = np.ascontiguousarray(ip)
    if decimals:
        ip, fp = np.divmod(ip, 1000)
    nd = np.ones(ip.shape, dtype=np.int32)           # integer digits
    p = 10
    while p < 10 ** 18:
        more = ip >= p
        if not more.any():
            break
        nd += more
        p *= 10
    ng = -(-int(nd.max()) // 3)                      # groups of three digits
    signed = neg.any(axis=1)                         # columns that need a sign position
    width = len(prefix) + int(signed.sum()) + k * (3 * ng + (4 if decimals else 0)) + (k - 1) + 1
    # bytes per line: the full width less the unused sign positions and leading zeros
    lengths = np.full(n, width, dtype=np.int64)
    for j in range(k):
        lengths -= 3 * ng - nd[j]
        if signed[j]:
            lengths -= ~neg[j]
    C = np.empty((width, n), dtype=np.uint8)         # transposed: C[c] is text column c
    for c, byte in enumerate(prefix):
        C[c] = byte
    pos = len(prefix)
    for j in range(k):
        if j:
            C[pos] = 32                              # " "
            pos += 1
        if signed[j]:
            np.multiply(neg[j], 45, out=C[pos], casting="unsafe")   # "-" for negative numbers, else NUL
            pos += 1
        q = ip[j]
        for g in range(ng - 1, -1, -1):
            if g:
                q, r = np.divmod(q, 1000)
            else:
                r = q                                # < 1000: ng groups hold every number
            for d in range(3):                       # (take into the row: no temporary)
                _TRIPLES[d].take(r, out=C[pos + 3 * g + d], mode="clip")
        for d in range(3 * ng - 1):                  # leading zeros (the last digit always stays)
            row = C[pos + d]
            np.multiply(row, nd[j] >= 3 * ng - d, out=row, casting="unsafe")
        pos += 3 * ng
        if decimals:
            C[pos] = 46                              # "."
            for d in range(3):
                _TRIPLES[d].take(fp[j], out=C[pos + 1 + d], mode="clip")
            pos += 4
    C[pos] = 10                                      # newline
    offsets = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    return C.T.tobytes().translate(None, b"\0"), offsets


def obj_bytes(vertices: np.ndarray, faces: np.ndarray, groups=None, mtl: str | None = None,
              material: str | None = None) -> bytes:
    """One OBJ as bytes. `groups` is a list of (name, face_start, face_end) over `faces`."""
    parts = [b"# cosim world mesh: world metres, z up\n"]
    if mtl:
        parts.append(f"mtllib {mtl}\n".encode())
    if material:
        parts.append(f"usemtl {material}\n".encode())
    parts.append(_ascii_lines(b"v ", np.asarray(vertices, dtype=float).reshape(-1, 3), 3)[0])
    ftext, foff = _ascii_lines(b"f ", np.asarray(faces, dtype=np.int64).reshape(-1, 3) + 1, 0)
    if not groups:
        parts.append(ftext)
    else:
        for name, a, b in groups:
            if b > a:
                parts.append(f"g {name}\n".encode())
                parts.append(ftext[foff[a]:foff[b]])
    return b"".join(parts)


def write_obj(path: Path, vertices: np.ndarray, faces: np.ndarray, groups=None, mtl: str | None = None,
              material: str | None = None) -> None:
    """Write one OBJ. `groups` is a list of (name, face_start, face_end) over `faces`."""
    write_file(path, obj_bytes(vertices, faces, groups, mtl, material))


def obj_face_texts(items) -> list[bytes]:
    """The part of each OBJ after its vertices (faces, with a ``g`` line per group) for a
    list of (faces, groups) over 0-based vertex numbers, in one numpy pass: the same bytes
    as :func:`obj_bytes` writes there. A world build makes the buildings' face text before
    their heights are known (faces do not depend on them)."""
    if not items:
        return []
    ftext, foff = _ascii_lines(b"f ", np.vstack([np.asarray(f, dtype=np.int64).reshape(-1, 3) + 1
                                                  for f, _ in items]), 0)
    out, f0 = [], 0
    for f, groups in items:
        nf = len(f)
        if not groups:
            out.append(ftext[foff[f0]:foff[f0 + nf]])
        else:
            out.append(b"".join(part for name, a, b in groups if b > a
                                for part in (f"g {name}\n".encode(), ftext[foff[f0 + a]:foff[f0 + b]])))
        f0 += nf
    return out


class ObjBatch:
    """Many OBJ files (a world's tiles) made together: the numbers of all of them are turned
    into text in two numpy passes (vertices, faces), then each file is cut out of that text,
    so hundreds of small files cost no more than one big one. The text is the same as
    :func:`obj_bytes` gives file by file. A file's face text may come ready-made
    (:meth:`add_prepared`, from :func:`obj_face_texts`)."""

    HEADER = b"# cosim world mesh: world metres, z up\n"

    def __init__(self):
        self.files = []
        self._dirs = set()

    def add(self, path, vertices: np.ndarray, faces: np.ndarray, groups=None) -> None:
        self.files.append((os.fspath(path), np.asarray(vertices, dtype=float).reshape(-1, 3),
                           np.asarray(faces, dtype=np.int64).reshape(-1, 3), groups))

    def add_prepared(self, path, vertices: np.ndarray, face_text: bytes) -> None:
        """A file whose face text (everything after the vertices) is already made."""
        self.files.append((os.fspath(path), np.asarray(vertices, dtype=float).reshape(-1, 3),
                           bytes(face_text), None))

    def write(self) -> None:
        if not self.files:
            return
        vtext, voff = _ascii_lines(b"v ", np.vstack([v for _, v, _, _ in self.files]), 3)
        made = iter(obj_face_texts([(f, g) for _, _, f, g in self.files if not isinstance(f, bytes)]))
        v0 = 0
        for path, v, f, groups in self.files:
            ftext = f if isinstance(f, bytes) else next(made)
            folder = os.path.dirname(path)
            if folder not in self._dirs:
                os.makedirs(folder, exist_ok=True)
                self._dirs.add(folder)
            write_file(path, b"".join((self.HEADER, vtext[voff[v0]:voff[v0 + len(v)]], ftext)))
            v0 += len(v)
        self.files = []


#: the tile classes that collide in the physics world; each has, beside its OBJ, the same
#: triangles in binary (:func:`write_collision_mesh`), which the physics loader cuts into small
#: parts without parsing text
COLLIDE_CLASSES = ("asphalt", "sidewalk", "rail", "building")


def write_collision_mesh(obj_path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """``<class>.npz`` beside a tile's ``<class>.obj``: ``v`` (n, 3) float32 world metres and
    ``f`` (m, 3) int32, the OBJ's faces in its order (0-based)."""
    import io

    buf = io.BytesIO()
    np.savez(buf, v=np.asarray(vertices, dtype=np.float32).reshape(-1, 3),
             f=np.asarray(faces, dtype=np.int32).reshape(-1, 3))
    write_file(os.fspath(obj_path)[:-4] + ".npz", buf.getvalue())


def write_file(path: Path, data: bytes) -> None:
    """Write `data` under a temporary name and rename it into place (no fsync; see above).

    An OS error (disk full, permission) is a one-line BuildError."""
    path = os.fspath(path)                  # (strings: a world has hundreds of files)
    tmp = f"{path}.tmp-{os.getpid()}"
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        try:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
        finally:
            os.close(fd)
        os.replace(tmp, path)
    except OSError as e:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise disk_error(path, e) from None


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


# ---------------------------------------------------------------------------------------
# binary glTF
# ---------------------------------------------------------------------------------------
def glb_bytes(names, vertices: np.ndarray, faces: np.ndarray, vstart, fstart, material_of,
              materials: list[dict]) -> bytes:
    """A GLB scene with one node (and mesh) per piece, named by `names`.

    Piece k owns ``vertices[vstart[k]:vstart[k+1]]`` and ``faces[fstart[k]:fstart[k+1]]``
    (face indices global, i.e. into `vertices`); ``material_of[k]`` indexes `materials`,
    dicts ``{"name", "rgba" (0-255), "roughness", "metallic"}``. Pieces without faces are
    left out. Positions are float32 and indices uint32, as in any glTF viewer's input.
    (:class:`GlbTemplate` then :meth:`GlbTemplate.render`.)"""
    V = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    return GlbTemplate(names, faces, vstart, fstart, material_of, materials, len(V)).render(V)


def _json_float(x: float) -> str:
    return repr(x) if np.isfinite(x) else json.dumps(x)


class JsonTemplate:
    """``json.dumps(doc)`` of a document with holes whose values come later: `make_doc`
    gets n placeholder strings and returns the document with them where the values go;
    :meth:`render` fills in the values' JSON text. Most of a large document (a chunk's
    buildings, a GLB's nodes) can so be written before its heights are known."""

    def __init__(self, make_doc, n: int, **dumps_kw):
        import re
        import secrets

        tok = secrets.token_hex(8)
        text = json.dumps(make_doc([f"@{tok}:{i}@" for i in range(n)]), **dumps_kw)
        parts = re.split(f'"@{tok}:(\\d+)@"', text)
        self.segments = parts[0::2]
        self.order = [int(i) for i in parts[1::2]]
        if sorted(self.order) != list(range(n)):
            raise ValueError("JsonTemplate: every placeholder must appear exactly once")

    def render(self, values: list) -> str:
        """`values`: the JSON text of each hole, in placeholder order."""
        out = [self.segments[0]]
        for i, seg in zip(self.order, self.segments[1:]):
            out.append(values[i])
            out.append(seg)
        return "".join(out)


class GlbTemplate:
    """Everything of :func:`glb_bytes` that does not depend on the vertex positions (the
    indices, the scene, the JSON), made once; :meth:`render` adds positions and bounds."""

    def __init__(self, names, faces, vstart, fstart, material_of, materials: list[dict], n_vertices: int):
        vstart = np.asarray(vstart, dtype=np.int64)
        fstart = np.asarray(fstart, dtype=np.int64)
        F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
        nf = fstart[1:] - fstart[:-1]
        nv = vstart[1:] - vstart[:-1]
        keep = np.flatnonzero((nf > 0) & (nv > 0))
        self.n_vertices, self.vstart, self.keep = int(n_vertices), vstart, keep
        # indices local to each piece, uint32; all indices first, then all positions
        local = (F - np.repeat(vstart[:-1], nf)[:, None]).astype(np.uint32)
        self.ibytes = local.tobytes()
        ilen = len(self.ibytes)
        self.pad = (-ilen) % 4
        plen = self.n_vertices * 12
        blob_len = ilen + self.pad + plen
        blob_len += (-blob_len) % 4
        used = sorted({int(material_of[k]) for k in keep})
        mat_index = {m: i for i, m in enumerate(used)}
        mats = []
        for m in used:
            d = materials[m]
            mats.append({"name": d["name"], "doubleSided": False, "pbrMetallicRoughness": {
                "baseColorFactor": [c / 255.0 for c in d["rgba"]],
                "metallicFactor": d.get("metallic", 0.0), "roughnessFactor": d.get("roughness", 1.0)}})

        def doc(holes):
            accessors, meshes, nodes = [], [], []
            for r, k in enumerate(keep.tolist()):
                accessors.append({"bufferView": 0, "byteOffset": int(fstart[k]) * 12, "componentType": 5125,
                                  "count": int(nf[k]) * 3, "type": "SCALAR"})
                accessors.append({"bufferView": 1, "byteOffset": int(vstart[k]) * 12, "componentType": 5126,
                                  "count": int(nv[k]), "type": "VEC3",
                                  "min": holes[2 * r], "max": holes[2 * r + 1]})
                meshes.append({"name": names[k], "primitives": [{
                    "attributes": {"POSITION": 2 * r + 1}, "indices": 2 * r, "mode": 4,
                    "material": mat_index[int(material_of[k])]}]})
                nodes.append({"name": names[k], "mesh": r})
            gltf = {"asset": {"version": "2.0", "generator": "cosim netgen"}, "scene": 0,
                    "scenes": [{"nodes": list(range(len(nodes)))}], "nodes": nodes, "meshes": meshes,
                    "accessors": accessors, "materials": mats,
                    "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": ilen, "target": 34963},
                                    {"buffer": 0, "byteOffset": ilen + self.pad, "byteLength": plen,
                                     "target": 34962, "byteStride": 12}],
                    "buffers": [{"byteLength": blob_len}]}
            if not nodes:
                gltf = {k: v for k, v in gltf.items() if k not in ("bufferViews", "buffers", "accessors")}
            return gltf

        self.json = JsonTemplate(doc, 2 * len(keep), separators=(",", ":"))

    def render(self, vertices: np.ndarray) -> bytes:
        V = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
        if len(V) != self.n_vertices:
            raise ValueError(f"GlbTemplate: {len(V)} vertices, made for {self.n_vertices}")
        keep, vstart = self.keep, self.vstart
        bounds = []
        if len(keep):     # per-piece bounds: reduce over [start, end) pairs, every other result
            Vp = np.vstack([V, V[:1]])
            idx = np.column_stack([vstart[keep], vstart[keep + 1]]).ravel()
            vmin = np.minimum.reduceat(Vp, idx, axis=0)[::2]
            vmax = np.maximum.reduceat(Vp, idx, axis=0)[::2]
            mm = np.empty((2 * len(keep), 3), dtype=np.float32)
            mm[0::2], mm[1::2] = vmin, vmax
            if np.all(np.isfinite(mm)):
                bounds = [f"[{a!r},{b!r},{c!r}]" for a, b, c in mm.tolist()]
            else:
                bounds = ["[" + ",".join(_json_float(x) for x in row) + "]" for row in mm.tolist()]
        js = self.json.render(bounds).encode()
        js += b" " * ((-len(js)) % 4)
        chunks = struct.pack("<II", len(js), 0x4E4F534A) + js
        if len(keep):
            blob = self.ibytes + b"\0" * self.pad + V.tobytes()
            blob += b"\0" * ((-len(blob)) % 4)
            chunks += struct.pack("<II", len(blob), 0x004E4942) + blob
        return struct.pack("<4sII", b"glTF", 2, 12 + len(chunks)) + chunks


# ---------------------------------------------------------------------------------------
# tiles
# ---------------------------------------------------------------------------------------
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
