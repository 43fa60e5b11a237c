"""Read-only view of a built world folder (``world.json`` and its chunk files).

Knows the frame (lat/lon <-> x/y), the tiles of every chunk, and the ground height anywhere
in the world (bilinear on the chunk terrain grids, the same surface the physics heightfield
and the road meshes were made from), so mirrored actors can be placed on it.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from netgen.errors import DataError
from netgen.frame import WorldFrame
from netgen.terrain import TerrainGrid

from .demand import world_traffic_scale


class World:
    stacked_over: frozenset = frozenset()       # (see __init__)

    def __init__(self, path: str | Path):
        self.path = Path(path).absolute()
        wj = self.path / "world.json"
        if not wj.exists():
            raise DataError(f"no world at {self.path} (world.json missing): build one with `cosim build`")
        try:
            self.meta = json.loads(wj.read_text())
        except ValueError as e:
            raise DataError(f"{wj} is not valid JSON ({e})")
        m = self.meta
        self.frame = WorldFrame(m["center"]["lat"], m["center"]["lon"], m["chunk_size_m"])
        self.chunk_size = float(m["chunk_size_m"])
        self.tile_size = float(m.get("tile_size_m", self.chunk_size))
        self.spacing = float(m["terrain"]["spacing_m"])
        self.chunks = {(c["i"], c["j"]): dict(c, _base=self.path, _window=tuple(m.get("window", (0, 0))))
                       for c in m["chunks"]}
        self.net_file = self.path / m["net_file"]
        #: SUMO edges in tunnels: not meshed (worlds built before netgen 0.1.9 list none)
        self.tunnels = frozenset(m.get("tunnels", ()))
        #: lanes over a road stacked under them (OSM layers, no bridge: netgen's
        #: _stack_under_higher_layers): vehicles on them are put on their surface, as on a deck
        self.stacked_over = frozenset(m.get("stacked_over_lanes", ()))
        self.traffic_scale = world_traffic_scale(m)        # (cosim.demand.place_density)
        self.windows = [self.path]
        self._grids: dict = {}
        self._scenery: dict = {}
        self.nt = max(1, int(round(self.chunk_size / self.tile_size)))
        self.version = 0                    # bumped when a window adds or replaces chunks

    def add_window(self, path) -> list:
        """Take in another build of the same frame (a window of chunks around another chunk).

        A chunk is taken from the window in which it lies most interior (its roads were cut
        at that window's edge the least). Returns the chunks that were added or replaced."""
        other = World(path)
        if other.meta["projection"]["proj"].split() != self.meta["projection"]["proj"].split():
            raise DataError(f"window {path} uses another projection than {self.path}")
        changed = []
        wi = tuple(other.meta.get("window", (0, 0)))
        for ij, c in other.chunks.items():
            cur = self.chunks.get(ij)
            d_new = max(abs(ij[0] - wi[0]), abs(ij[1] - wi[1]))
            d_cur = max(abs(ij[0] - cur["_window"][0]), abs(ij[1] - cur["_window"][1])) if cur else 1 << 30
            if d_new < d_cur:
                self.chunks[ij] = c
                self._grids.pop(ij, None)
                self._scenery.pop(ij, None)
                changed.append(ij)
        self.net_file = other.net_file
        self.tunnels = self.tunnels | other.tunnels
        self.stacked_over = self.stacked_over | other.stacked_over
        self.windows.append(other.path)
        self.meta["extent_m"] = list(self._union_extent())
        self.version += 1
        return changed

    def _union_extent(self):
        b = np.array([c["bounds_m"] for c in self.chunks.values()])
        return float(b[:, 0].min()), float(b[:, 1].min()), float(b[:, 2].max()), float(b[:, 3].max())

    def file(self, ij, rel) -> Path:
        return self.chunks[ij]["_base"] / rel

    # --- terrain ------------------------------------------------------------------------
    def grid(self, ij) -> TerrainGrid | None:
        g = self._grids.get(ij)
        if g is None and ij in self.chunks:
            c = self.chunks[ij]
            z = np.load(c["_base"] / c["files"]["terrain"]).astype(np.float64)
            g = TerrainGrid(c["bounds_m"][0], c["bounds_m"][1], self.spacing, z)
            self._grids[ij] = g
        return g

    def ground_z(self, x, y) -> np.ndarray:
        """Ground height at world x/y (arrays), on the same triangles as the physics
        heightfield; NaN outside the built world."""
        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        s = self.chunk_size
        ci = np.floor(x / s + 0.5).astype(int)
        cj = np.floor(y / s + 0.5).astype(int)
        if len(x) and ci.min() == ci.max() and cj.min() == cj.max():    # all in one chunk (the usual case)
            g = self.grid((int(ci[0]), int(cj[0])))
            return g.sample_tri(x, y) if g is not None else np.full(x.shape, np.nan)
        out = np.full(x.shape, np.nan)
        for ij in set(zip(ci.tolist(), cj.tolist())):
            g = self.grid(ij)
            if g is None:
                continue
            m = (ci == ij[0]) & (cj == ij[1])
            out[m] = g.sample_tri(x[m], y[m])
        return out

    def bridge_lanes(self) -> frozenset:
        """The lanes of the network's bridges (OSM ``bridge=*``: decks, not on the ground):
        from ``<net>.bridges.json`` beside the network if a window's build wrote it (this
        version's), else read from the network (0.25 s: the simulation's setup asks first);
        and the lanes that stand over a road stacked under them (:attr:`stacked_over`)."""
        got = getattr(self, "_bridge_lanes", None)
        if got is None or got[0] != self.net_file:
            side = Path(str(self.net_file) + ".bridges.json")
            lanes = None
            if side.exists():
                try:
                    doc = json.loads(side.read_text())
                except ValueError:
                    doc = None
                if isinstance(doc, dict) and doc.get("version") == BRIDGE_LANES_VERSION:
                    lanes = frozenset(doc.get("lanes", ()))
            if lanes is None:
                lanes = _read_bridge_lanes(self.net_file)
            got = self._bridge_lanes = (self.net_file, lanes | self.stacked_over)
        return got[1]

    def road_top_z(self, x, y, r: float = 3.0) -> np.ndarray:
        """The highest road surface (asphalt mesh vertex) within ``r`` of each x/y, NaN where
        none: a bridge's deck where it passes over another road (the terrain is under both)."""
        from scipy.spatial import cKDTree

        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        out = np.full(x.shape, np.nan)
        trees = self.__dict__.setdefault("_asphalt_trees", {})
        by_tile: dict = {}
        for k, (xk, yk) in enumerate(zip(x.tolist(), y.tolist())):
            by_tile.setdefault(self.tile_of(xk, yk), []).append(k)
        for key, ks in by_tile.items():
            got = trees.get(key)
            if got is None:
                f = self.tile_files(key).get("asphalt")
                v = np.zeros((0, 3))
                if f is not None and f.with_suffix(".npz").exists():
                    v = np.load(f.with_suffix(".npz"))["v"].astype(float)
                got = trees[key] = (cKDTree(v[:, :2]) if len(v) else None, v[:, 2])
            tree, z = got
            if tree is not None:
                for k, near in zip(ks, tree.query_ball_point(np.column_stack((x[ks], y[ks])), r)):
                    if near:
                        out[k] = float(z[near].max())
        return out

    def ground_z_and_pitch(self, x, y, yaw, d: float = 1.5) -> tuple:
        """``ground_z(x, y)`` and ``slope_pitch(x, y, yaw, d)`` in one lookup of the terrain
        (the mirror asks both for every actor, every frame)."""
        x = np.atleast_1d(np.asarray(x, dtype=float))
        y = np.atleast_1d(np.asarray(y, dtype=float))
        c, s = np.cos(yaw) * d, np.sin(yaw) * d
        n = len(x)
        z = self.ground_z(np.concatenate((x, x + c, x - c)), np.concatenate((y, y + s, y - s)))
        return z[:n], np.arctan2(z[n:2 * n] - z[2 * n:], 2 * d)

    def slope_pitch(self, x, y, yaw, d: float = 1.5) -> np.ndarray:
        """Pitch (rad, nose up positive) of a body at x/y heading yaw, from the ground."""
        return self.ground_z_and_pitch(x, y, yaw, d)[1]

    # --- tiles --------------------------------------------------------------------------
    def tile_bounds(self, key):
        i, j, a, b = key
        xmin, ymin = self.chunks[(i, j)]["bounds_m"][:2] if (i, j) in self.chunks else \
            self.frame.chunk_bounds(i, j)[:2]
        return (xmin + a * self.tile_size, ymin + b * self.tile_size,
                xmin + (a + 1) * self.tile_size, ymin + (b + 1) * self.tile_size)

    def tile_of(self, x: float, y: float):
        i, j = self.frame.chunk_of(x, y)
        xmin, ymin, _, _ = self.frame.chunk_bounds(i, j)
        a = min(self.nt - 1, max(0, int((x - xmin) // self.tile_size)))
        b = min(self.nt - 1, max(0, int((y - ymin) // self.tile_size)))
        return (i, j, a, b)

    def tiles_within(self, x: float, y: float, r: float) -> list:
        """Tile keys (i, j, a, b) whose square intersects the disc (x, y, r), nearest first;
        tiles of chunks that are not built are included (the caller decides what to do)."""
        return [k for _, k in self.tiles_by_distance(x, y, r)]

    def tiles_by_distance(self, x: float, y: float, r: float) -> list:
        """(squared distance, key) of the tiles within r of (x, y), nearest first: a caller
        with several radii filters this list of the largest (``tiles_within`` of a smaller
        radius is the filtered list, in the same order). Called several times a frame: the
        squared distances of a row and a column are shared by its tiles."""
        t = self.tile_size
        h = self.chunk_size / 2
        nt = self.nt
        gx0 = math.floor((x - r + h) / t)
        gx1 = math.floor((x + r + h) / t)
        gy0 = math.floor((y - r + h) / t)
        gy1 = math.floor((y + r + h) / t)
        rows = []
        for gy in range(gy0, gy1 + 1):
            ymin = gy * t - h
            dy = max(ymin - y, 0.0, y - (ymin + t))
            j, b = divmod(gy, nt)
            rows.append((dy * dy, j, b))
        r2 = r * r
        out = []
        for gx in range(gx0, gx1 + 1):
            xmin = gx * t - h
            dx = max(xmin - x, 0.0, x - (xmin + t))
            dx2 = dx * dx
            if dx2 > r2:
                continue
            i, a = divmod(gx, nt)
            for dy2, j, b in rows:
                d2 = dx2 + dy2
                if d2 <= r2:
                    out.append((d2, (i, j, a, b)))
        out.sort()
        return out

    def is_built(self, key) -> bool:
        return (key[0], key[1]) in self.chunks

    def tile_files(self, key) -> dict:
        c = self.chunks.get((key[0], key[1]))
        if not c:
            return {}
        return {k: c["_base"] / v for k, v in c.get("tiles", {}).get(f"{key[2]}_{key[3]}", {}).items()}

    def tile_terrain(self, key) -> TerrainGrid | None:
        g = self.grid((key[0], key[1]))
        if g is None:
            return None
        n = int(round(self.tile_size / self.spacing))
        a, b = key[2], key[3]
        z = g.z[b * n:(b + 1) * n + 1, a * n:(a + 1) * n + 1]
        return TerrainGrid(g.xmin + a * self.tile_size, g.ymin + b * self.tile_size, self.spacing, z)

    def scenery(self, ij) -> list:
        s = self._scenery.get(ij)
        if s is None:
            c = self.chunks.get(ij)
            f = c["files"].get("scenery_json") if c else None
            s = json.loads((c["_base"] / f).read_text())["instances"] if f else []
            self._scenery[ij] = s
        return s

    def map_layers(self) -> dict:
        """2D layers for a top-down map, in world metres: lanes for cars and footpaths as
        (n, 2) polylines, building footprints as (n, 2) rings, chunk bounds."""
        from netgen.roadnet import read_net

        net = read_net(self.net_file)
        roads, paths = [], []
        for e in net.normal_edges():
            for l in e.lanes:
                if len(l.shape) >= 2:
                    (roads if l.drivable else paths).append(l.shape)
        buildings = []
        for c in self.chunks.values():
            f = c["files"].get("buildings_json")
            if not f:
                continue
            for b in json.loads((c["_base"] / f).read_text()).get("buildings", []):
                ring = b.get("footprint")
                if ring:
                    buildings.append(np.asarray(ring, dtype=float))
        return {"roads": roads, "paths": paths, "buildings": buildings,
                        "chunks": [c["bounds_m"] for c in self.chunks.values()]}

    def loaded_extent(self):
        return tuple(self.meta["extent_m"])


#: ``<net>.bridges.json``'s version: 2 adds the lanes of junctions on a deck (an older file is
#: not trusted: the network is read again)
BRIDGE_LANES_VERSION = 2


def _read_bridge_lanes(net_file) -> frozenset:
    """The lanes of bridge edges, and of the junctions on a deck: every road that meets such a
    junction is a bridge (Portland: 145 junctions on I-405's decks and ramps; a vehicle on one
    of their 369 junction lanes was mirrored on the terrain, metres under the deck)."""
    from netgen.roadnet import read_net

    net = read_net(net_file)
    on_deck: dict = {}              # junction -> every road meeting it is a bridge
    lanes = set()
    for e in net.normal_edges():
        bridge = bool(getattr(e, "bridge", False))
        if bridge:
            lanes.update(ln.id for ln in e.lanes)
        for j in (e.from_node, e.to_node):
            if j:
                on_deck[j] = on_deck.get(j, True) and bridge
    for e in net.edges.values():
        if e.function != "normal" and on_deck.get(e.id[1:].rsplit("_", 1)[0]):
            lanes.update(ln.id for ln in e.lanes)
    return frozenset(lanes)


def write_bridge_lanes(net_file) -> None:
    """``<net>.bridges.json``: the bridge lanes of a network, for ``World.bridge_lanes``."""
    from netgen._atomic import write_text

    write_text(Path(str(net_file) + ".bridges.json"),
               json.dumps({"version": BRIDGE_LANES_VERSION, "lanes": sorted(_read_bridge_lanes(net_file))}))

