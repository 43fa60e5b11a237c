"""The PyBullet world: static tiles streamed around the car, prefab scenery, gravity.

Tiles (250 m squares of a chunk) are the unit of streaming: each brings a terrain
heightfield cut from its chunk's grid, the merged road, sidewalk and building meshes of the
tile (static concave triangle meshes), lane markings (visual only), and the scenery
instances standing in it (the colliders of its trees, poles, signs and benches merged into one
triangle mesh). A tile is loaded a part at a time (terrain, each mesh class PART_FACES faces at a
time from its binary copy, the scenery in runs of about as many) within a per-frame time
budget (``update``), so that no frame pays for a whole tile: Bullet builds a triangle mesh's
tree at about 1.2 us a face, and a whole class of a city tile took 3-6 ms.

PyBullet does not free a mesh's memory when a body is removed, so shapes are pooled: a
tile's collision and visual shapes are created once per file and reused whenever the tile
comes back, and heightfield shapes are removed with ``removeCollisionShape``. Memory is
therefore bounded by the tiles the car has visited, not by how often it streamed them.

Every static body (tiles, scenery, and the mirror's actors: ``static_body``) is put to sleep
when it is made. PyBullet's step writes a transform-changed notification for every awake
body, static ones included, and Bullet wakes none of them again (moving one with
``resetBasePositionAndOrientation`` does not): in Helsinki's world of 220 bodies that was a
third of the car's substep (``bench/HISTORY.md``, session 38). Rays, contacts with the car and
rendering are the same for a sleeping static body.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pybullet as pb

from models import prefab_dir
from netgen.meshio import COLLIDE_CLASSES, LAYER_COLOURS

COLOURS = LAYER_COLOURS
COLLIDE = set(COLLIDE_CLASSES)
#: a colliding mesh class of a tile is made this many faces at a time, from its binary copy
#: (``<class>.npz``): Bullet builds a triangle mesh's tree at about 1.2 µs a face, and a whole
#: class of a city tile (3,000-5,000 faces) took a frame 3-6 ms over its median of 2. (600 made
#: 0.5-1 ms parts, but three times the bodies, which cost every step and lidar scan: Helsinki's
#: frame median 1.9 -> 2.1 ms, the car's physics 0.42 -> 0.60 ms; 2,000: 0.46 ms. Session 29,
#: at about 400 actors, where the loop waits for SUMO's worker: 1,000 against 2,000, frames over
#: 2 x the median 3 against 11-13 in 1,200, the largest part 3.3-3.7 against 5.1-5.2 ms, the car's
#: physics 0.83 against 0.74 ms, hidden in the wait for the worker: the same frame median)
PART_FACES = 1000
COMPOUND_MAX = 16   # children per createCollisionShapeArray / createVisualShapeArray (PyBullet's limit)
PREFAB_COLOURS = {"tree": (0.20, 0.45, 0.18, 1), "street_lamp": (0.35, 0.36, 0.38, 1),
                  "traffic_signal": (0.15, 0.15, 0.15, 1), "stop_sign": (0.80, 0.10, 0.10, 1),
                  "give_way_sign": (0.95, 0.95, 0.95, 1), "bench": (0.45, 0.30, 0.18, 1)}


UNPACED_MS = 1e6   # a tile-loading budget this large: no pacing (see PhysicsWorld.update)
_SIDES = 12     # a cylinder collider's prism
_DONE = object()  # (a tile's parts are all made)


#: the sky of camera_image, where the camera sees nothing: a pale blue at the bottom of the
#: picture, deeper at its top (PyBullet's own renderers leave it white)
SKY_HORIZON_RGB = (196, 218, 240)
SKY_TOP_RGB = (110, 158, 214)


def compact_order(xy: np.ndarray, run: int) -> np.ndarray:
    """An order of the points ``xy`` (n, 2) whose consecutive runs of ``run`` (the last
    shorter) each cover a compact box: the set is halved across its longer side, at a
    multiple of ``run``, until a box holds one run (k-d cuts with ``argpartition``).

    A tile's mesh classes and scenery come in files in an arbitrary order; cut into parts in
    that order, every part spanned most of the tile, so that the parts' boxes held the car
    and the rays: Bullet tested the chassis against 3.9 scenery and 2 building parts per
    substep (Helsinki, about 400 actors) and each wheel and lidar ray against every part of
    its tile. Parts cut in this
    order have the same sizes, and a point of the tile lies in one part's box of a class,
    or in a few at the seams."""
    n = len(xy)
    if n <= run:
        return np.arange(n)
    out = []
    todo = [np.arange(n)]
    while todo:
        idx = todo.pop()
        if len(idx) <= run:
            out.append(idx)
            continue
        k = -(-len(idx) // run)
        m = (k // 2) * run                   # the first half: whole runs
        pts = xy[idx]
        span = pts.max(axis=0) - pts.min(axis=0)
        side = pts[:, 1] if span[1] > span[0] else pts[:, 0]
        cut = np.argpartition(side, m - 1)
        todo.append(idx[cut[m:]])            # (popped after the first half: runs stay in order)
        todo.append(idx[cut[:m]])
    return np.concatenate(out)


def static_body(client: int, collision: int, visual: int, position, orientation=(0.0, 0.0, 0.0, 1.0)) -> int:
    """A static body (mass 0, maximal coordinates), asleep (see the module doc)."""
    b = pb.createMultiBody(0, collision, visual, list(position), list(orientation), useMaximalCoordinates=True,
                           physicsClientId=client)
    pb.changeDynamics(b, -1, activationState=pb.ACTIVATION_STATE_SLEEP, physicsClientId=client)
    return b


def _colliders_mesh(cols, frames) -> tuple[np.ndarray, np.ndarray]:
    """One triangle mesh (vertices, faces) of primitive colliders: ``cols`` as in
    ``_load_prefabs`` (type, radius, half extents, height, offset), ``frames`` (position,
    yaw quaternion) of each. Cylinders (z axis) become closed prisms of _SIDES sides with a
    centre vertex on each cap, boxes closed boxes turned by their yaw; each item's vertices
    and faces in the items' order (all items of a kind at once: 0.1 ms for a part of 45
    trees, 0.27 ms one item at a time)."""
    a = np.linspace(0.0, 2.0 * np.pi, _SIDES, endpoint=False)
    ring = np.column_stack([np.cos(a), np.sin(a)])
    k = np.arange(_SIDES)
    k1 = (k + 1) % _SIDES
    # cylinder: 0.._SIDES-1 bottom ring, _SIDES..2*_SIDES-1 top ring, 2S bottom centre, 2S+1 top
    cyl_f = np.concatenate([np.column_stack([k, k1, _SIDES + k1]), np.column_stack([k, _SIDES + k1, _SIDES + k]),
                            np.column_stack([np.full(_SIDES, 2 * _SIDES), k1, k]),
                            np.column_stack([np.full(_SIDES, 2 * _SIDES + 1), _SIDES + k, _SIDES + k1])])
    box_v = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], float)
    box_f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                      [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    n = len(cols)
    cyl = np.array([c[0] == pb.GEOM_CYLINDER for c in cols], dtype=bool)
    pos = np.array([p for p, _ in frames], float).reshape(n, 3)
    nv = np.where(cyl, 2 * _SIDES + 2, len(box_v))
    nf = np.where(cyl, len(cyl_f), len(box_f))
    v0 = np.concatenate([[0], np.cumsum(nv)[:-1]]).astype(int)
    f0 = np.concatenate([[0], np.cumsum(nf)[:-1]]).astype(int)
    V = np.empty((int(nv.sum()), 3))
    F = np.empty((int(nf.sum()), 3), dtype=cyl_f.dtype)
    ic = np.flatnonzero(cyl)
    if len(ic):
        r = np.array([cols[i][1] for i in ic], float)[:, None, None]
        h = np.array([cols[i][3] for i in ic], float)[:, None]
        blk = np.zeros((len(ic), 2 * _SIDES + 2, 3))
        blk[:, :_SIDES, :2] = ring[None] * r
        blk[:, _SIDES:2 * _SIDES, :2] = ring[None] * r
        blk[:, :_SIDES, 2] = -h / 2
        blk[:, _SIDES:2 * _SIDES, 2] = h / 2
        blk[:, 2 * _SIDES, 2] = -h[:, 0] / 2
        blk[:, 2 * _SIDES + 1, 2] = h[:, 0] / 2
        V[(v0[ic][:, None] + np.arange(2 * _SIDES + 2)).ravel()] = (blk + pos[ic][:, None, :]).reshape(-1, 3)
        F[(f0[ic][:, None] + np.arange(len(cyl_f))).ravel()] = (cyl_f[None] + v0[ic][:, None, None]).reshape(-1, 3)
    ib = np.flatnonzero(~cyl)
    if len(ib):
        q = np.array([frames[i][1] for i in ib], float)
        yaw = 2.0 * np.arctan2(q[:, 2], q[:, 3])
        cy, sy = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
        v = box_v[None] * np.array([cols[i][2] for i in ib], float)[:, None, :]
        blk = np.stack([v[..., 0] * cy - v[..., 1] * sy, v[..., 0] * sy + v[..., 1] * cy, v[..., 2]], axis=-1)
        V[(v0[ib][:, None] + np.arange(len(box_v))).ravel()] = (blk + pos[ib][:, None, :]).reshape(-1, 3)
        F[(f0[ib][:, None] + np.arange(len(box_f))).ravel()] = (box_f[None] + v0[ib][:, None, None]).reshape(-1, 3)
    return V, F


@dataclass
class TileBodies:
    bodies: list = field(default_factory=list)
    kinds: list = field(default_factory=list)
    hf_shape: int = -1
    load_ms: float = 0.0


class PhysicsWorld:
    """Component with the loop's lifecycle: setup(), step(), teardown()."""

    def __init__(self, world, gui: bool = False, physics_hz: float = 100.0, visuals: bool | None = None,
                 load_budget_ms: float = 8.0):
        self.world = world
        self.gui = gui
        self.physics_hz = physics_hz
        self.visuals = gui if visuals is None else visuals
        self.load_budget_ms = load_budget_ms
        self.client = None
        self.tiles: dict = {}
        self._stale: set = set()          # loaded tiles a newer window replaced (refresh)
        self.replaced_now: list = []      # tiles of which update() replaced parts in its last call
        self._loading: dict = {}          # tile -> (TileBodies, its parts still to make): being loaded
        self._shape_pool: dict = {}       # (file, collide) -> (collision id, visual id)
        self._prefabs: dict = {}
        self._chunk_visuals: dict = {}    # chunk -> (body, refcount)
        self._hf_free: dict = {}          # (nx, ny, spacing) -> [free heightfield shapes]
        self._hf_key_of: dict = {}
        self.hf_shapes_created = 0
        self.loads = 0
        self.unloads = 0
        self.load_times_ms: list = []

    # --- lifecycle ------------------------------------------------------------------------
    def setup(self):
        if self.gui:
            from netgen.errors import SimulationError

            from .display import display_problem

            why = display_problem()       # (PyBullet's window thread ends the process without one)
            if why:
                raise SimulationError(f"PyBullet cannot open its window: {why}; run without --gui")
        self.client = pb.connect(pb.GUI if self.gui else pb.DIRECT)
        if self.client < 0:
            from netgen.errors import SimulationError

            raise SimulationError("PyBullet could not open a window (no display?): run without --gui")
        c = self.client
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        pb.setTimeStep(1.0 / self.physics_hz, physicsClientId=c)
        pb.setPhysicsEngineParameter(numSolverIterations=10, physicsClientId=c)
        if self.gui:
            pb.configureDebugVisualizer(pb.COV_ENABLE_GUI, 0, physicsClientId=c)
            pb.configureDebugVisualizer(pb.COV_ENABLE_SHADOWS, 1, physicsClientId=c)
            # the window's own keys off: W drew the world as wireframe, A its bounding boxes,
            # S, D and the others toggled what it draws; WASD drive the car (cosim.keyboard)
            pb.configureDebugVisualizer(pb.COV_ENABLE_KEYBOARD_SHORTCUTS, 0, physicsClientId=c)
        self._load_prefabs()
        return self

    def step(self, n: int = 1):
        for _ in range(n):
            pb.stepSimulation(physicsClientId=self.client)

    def teardown(self):
        if self.client is not None:
            try:
                pb.disconnect(physicsClientId=self.client)
            except pb.error:
                pass
            self.client = None
        self.tiles.clear()
        self._loading.clear()
        self._shape_pool.clear()
        self._chunk_visuals.clear()

    # --- streaming ------------------------------------------------------------------------
    def update(self, x: float, y: float, keep_radius: float, unload_radius: float | None = None,
               budget_ms: float | None = None, stale: bool = True, urgent_radius: float | None = None,
               critical_radius: float | None = None, spare=None) -> dict:
        """Load tiles within keep_radius, nearest first, a part at a time (the terrain, each
        mesh class, the scenery: see ``_tile_parts``), so that a tile's load is spread over
        frames; a tile counts as loaded (``tiles``, ``covered``) once all its parts are in.
        Unload those beyond unload_radius (hysteresis). With ``stale`` False, stale tiles
        (see ``refresh``) wait. Returns counts of what happened.

        How much a call loads: while a tile within ``critical_radius`` is missing (or
        without the radii), parts until the time budget is spent (at least one part); while
        one within ``urgent_radius`` is, one part; else one part if ``spare()`` says that the
        caller would wait anyway (None: always), as for SUMO stepping in its worker process.
        The tiles ahead thus come in a part per frame, mostly hidden behind that wait, and a
        frame seldom carries several parts (up to 14 ms on Helsinki, where the median frame
        takes 4 ms). A budget of :data:`UNPACED_MS` or more loads all at once, whatever the
        wall clock says (tests that compare runs)."""
        unload_radius = unload_radius or keep_radius + self.world.tile_size
        budget = self.load_budget_ms if budget_ms is None else budget_ms
        # (one list of the tiles around, for all the radii: nearest first)
        near = self.world.tiles_by_distance(x, y, max(keep_radius, unload_radius,
                                                      urgent_radius or 0.0, critical_radius or 0.0))
        built = self.world.is_built
        k2 = keep_radius * keep_radius
        want = [k for d2, k in near if d2 <= k2 and built(k)]

        todo = [k for k in want if k not in self.tiles or (stale and k in self._stale)]

        def missing(r):
            r2 = r * r
            return any(k not in self.tiles for d2, k in near if d2 <= r2 and built(k))

        hurry = go = False
        if todo:        # (the radii looked at only when there is something to load)
            hurry = urgent_radius is None or critical_radius is None or budget >= UNPACED_MS \
                or missing(critical_radius)
            go = hurry or missing(urgent_radius) or spare is None or spare()
        t0 = time.perf_counter()
        loaded = parts = 0
        self.replaced_now = []
        for k in todo if go else ():
            if parts and (not hurry or (time.perf_counter() - t0) * 1000.0 > budget):
                break
            # a tile, a part at a time (terrain, each mesh class, scenery) within the budget; a
            # stale one part for part (see _replace_parts)
            job = self._loading.get(k)
            if job is None:
                job = self._loading[k] = self._start_tile(k)
            if job[2] is not None:
                self.replaced_now.append(k)
            while True:
                done = next(job[1], _DONE) is _DONE
                parts += 1
                if done or not hurry or (time.perf_counter() - t0) * 1000.0 > budget:
                    break
            if done:
                del self._loading[k]
                self._finish_tile(k, job)
                loaded += 1
        u2 = unload_radius * unload_radius
        keep = {k for d2, k in near if d2 <= u2}
        unloaded = 0
        for k in [k for k in self.tiles if k not in keep]:
            self.unload_tile(k)
            unloaded += 1
        for k in [k for k in self._loading if k not in keep]:
            self._drop_loading(k)
        return {"loaded": loaded, "unloaded": unloaded,
                "pending": sum(1 for k in want if k not in self.tiles or k in self._stale)}

    def covered(self, x: float, y: float, r: float) -> bool:
        """True when every tile touching the disc (x, y, r) is built and loaded."""
        return all(k in self.tiles for k in self.world.tiles_within(x, y, r))

    def refresh(self, chunks) -> int:
        """The world took in a new window: the loaded tiles of the chunks it replaced are
        stale. ``update`` replaces them nearest first, a part at a time within its time budget
        like any other load, each new part taking the place of the old one of its kind in the
        same call (``_replace_parts``): the sensors never see a hole. Returns how many tiles
        became stale."""
        chunks = set(chunks)
        for k in [k for k in self._loading if (k[0], k[1]) in chunks]:
            self._drop_loading(k)         # (half made from the old build: begun anew)
        stale = {k for k in self.tiles if (k[0], k[1]) in chunks}
        self._stale |= stale
        for ij in chunks & set(self._chunk_visuals):      # visual only: redrawn from the new build
            body, n = self._chunk_visuals.pop(ij)
            if body is not None:
                pb.removeBody(body, physicsClientId=self.client)
            self._chunk_visual_ref(ij, n)
        return len(stale)

    def load_tile(self, key):
        """Load a tile at once (all its parts); returns its TileBodies."""
        job = self._loading.pop(key, None) or self._start_tile(key)
        for _ in job[1]:
            pass
        return self._finish_tile(key, job)

    def _start_tile(self, key):
        """A tile's loading job: (its TileBodies, the generator of its parts, the stale tile it
        replaces or None)."""
        tb = TileBodies()
        old = self.tiles.get(key) if key in self._stale else None
        if old is None:
            return tb, self._tile_parts(key, tb, PART_FACES), None
        return tb, self._replace_parts(key, tb, old), old

    def _finish_tile(self, key, job):
        tb, _, old = job
        if old is not None:             # what is left of the stale tile (its scenery) goes now
            self._remove_bodies(old)
            if self.visuals:
                self._chunk_visual_ref((key[0], key[1]), -1)
            self._stale.discard(key)
            self.unloads += 1
        self.load_times_ms.append(tb.load_ms)
        self.tiles[key] = tb
        self.loads += 1
        return tb

    def _replace_parts(self, key, tb, old):
        """The new build of a stale tile, a part at a time; each part removes the stale tile's
        part of the same kind in the same call (the terrain for the terrain, a mesh class for
        its class), so that the ground is never missing nor doubled. The stale tile stays in
        ``tiles`` (and ``covered``) until the new one is complete (``_finish_tile``)."""
        made = 0
        for _ in self._tile_parts(key, tb, 0):        # (a class whole: one body for one)
            t0 = time.perf_counter()
            for kind in tb.kinds[made:]:
                self._remove_kind(old, kind)
            made = len(tb.kinds)
            tb.load_ms += (time.perf_counter() - t0) * 1000.0
            yield

    def _remove_kind(self, tb, kind: str) -> None:
        """Remove a tile's bodies of one kind (terrain or a mesh class)."""
        for i, k in enumerate(tb.kinds):
            if k == kind and tb.bodies[i] is not None:
                pb.removeBody(tb.bodies[i], physicsClientId=self.client)
                tb.bodies[i] = None
                if kind == "terrain":
                    self._release_heightfield(tb)

    def _tile_parts(self, key, tb, part_faces: int = PART_FACES):
        """A tile's bodies, one part per iteration (the terrain, each mesh class, the
        scenery), so that ``update`` can spread a tile over frames; ``tb.load_ms`` sums them.
        With ``part_faces``, a colliding class with a binary copy (``<class>.npz``) comes that
        many faces at a time, a body each (0: the class's OBJ, one body)."""
        c = self.client
        t0 = time.perf_counter()
        g = self.world.tile_terrain(key)
        if g is not None:
            sh, base = self._heightfield(g)
            tb.hf_shape = sh
            # (the shape's heights, then the body: a part each, about 0.6 ms each)
            tb.load_ms += (time.perf_counter() - t0) * 1000.0
            yield
            t0 = time.perf_counter()
            ny, nx = g.z.shape
            pos = [g.xmin + (nx - 1) * g.spacing / 2, g.ymin + (ny - 1) * g.spacing / 2, base]
            vis = self._terrain_visual(key, g, pos) if self.visuals else self._invisible()
            b = static_body(c, sh, vis, pos)
            tb.bodies.append(b)
            tb.kinds.append("terrain")
        tb.load_ms += (time.perf_counter() - t0) * 1000.0
        yield
        for kind, f in self.world.tile_files(key).items():
            collide = kind in COLLIDE
            if not collide and not self.visuals:
                continue
            t0 = time.perf_counter()
            npz = f.with_suffix(".npz") if collide and part_faces else None
            if npz is not None and npz.exists():
                for col in self._part_shapes(npz, part_faces):
                    if col is not None:         # (None: the class's file read, a part of its own)
                        b = static_body(c, col, self._unseen(), (0, 0, 0))
                        tb.bodies.append(b)
                        tb.kinds.append(kind)
                    tb.load_ms += (time.perf_counter() - t0) * 1000.0
                    yield
                    t0 = time.perf_counter()
                if not self.visuals:
                    continue
                col, vis = -1, self._shapes(f, kind, False)[1]      # (drawn whole)
            else:
                col, vis = self._shapes(f, kind, collide)
            b = static_body(c, col, vis, (0, 0, 0))
            tb.bodies.append(b)
            tb.kinds.append(kind)
            tb.load_ms += (time.perf_counter() - t0) * 1000.0
            yield
        t0 = time.perf_counter()
        groups = self._scenery_bodies(key, part_faces)
        for n, bodies in enumerate(groups):
            if n:                       # (a part each: the last with the tile's completion)
                tb.load_ms += (time.perf_counter() - t0) * 1000.0
                yield
                t0 = time.perf_counter()
            tb.bodies.extend(bodies)
        if self.visuals:
            self._chunk_visual_ref((key[0], key[1]), +1)
        tb.load_ms += (time.perf_counter() - t0) * 1000.0

    def _drop_loading(self, key) -> None:
        """Remove what a tile still being loaded has made so far (and, when it was replacing
        a stale tile that has already lost parts, that tile too: it is loaded anew)."""
        job = self._loading.pop(key, None)
        if job is None:
            return
        job[1].close()
        self._remove_bodies(job[0])
        old = job[2]
        if old is not None and self.tiles.get(key) is old and any(b is None for b in old.bodies):
            self.unload_tile(key)

    def _remove_bodies(self, tb) -> None:
        """Remove a tile's bodies; its heightfield shape goes back to the pool."""
        for b in tb.bodies:
            if b is not None:
                pb.removeBody(b, physicsClientId=self.client)
        tb.bodies = [None] * len(tb.bodies)
        self._release_heightfield(tb)

    def _release_heightfield(self, tb) -> None:
        """A tile's heightfield shape goes back to the pool (PyBullet never frees a shape)."""
        if tb.hf_shape >= 0:
            self._hf_free.setdefault(self._hf_key_of[tb.hf_shape], []).append(tb.hf_shape)
            tb.hf_shape = -1

    def unload_tile(self, key):
        self._stale.discard(key)
        tb = self.tiles.pop(key, None)
        if tb is None:
            return
        self._remove_bodies(tb)
        if self.visuals:
            self._chunk_visual_ref((key[0], key[1]), -1)
        self.unloads += 1

    # --- shapes -------------------------------------------------------------------------
    def _unseen(self) -> int:
        """The visual shape of a body that only collides (a mesh class's part, the scenery's
        colliders; they are drawn by their own visual bodies): none, except in PyBullet's
        window, which draws a body without one as its collision shape in a colour of its own,
        over the road's own mesh (red and blue roads and fronts that flickered). In DIRECT a
        visual shape would cost 0.5 ms a body, and TinyRenderer draws no mesh that only collides."""
        return self._invisible() if self.gui else -1

    def _invisible(self) -> int:
        """A visual shape nobody sees, for a heightfield body without visuals: given none,
        PyBullet makes the renderer's mesh of the heightfield itself, which took 1.6 of the
        2.0 ms a terrain body cost."""
        vis = self._shape_pool.get("invisible")
        if vis is None:
            vis = self._shape_pool["invisible"] = pb.createVisualShape(
                pb.GEOM_SPHERE, radius=0.001, rgbaColor=[0, 0, 0, 0], physicsClientId=self.client)
        return vis

    def _part_shapes(self, npz: Path, part_faces: int):
        """The collision shapes of a mesh class's binary copy, ``part_faces`` faces each, made
        one per iteration as they are needed (pooled like ``_shapes``: a tile that comes back
        reuses them, and one dropped half made goes on where it stopped). Reading the file
        is an iteration of its own, which yields None: 0.4-0.9 ms, which made the first part
        of a class 2-3.4 ms against 1.3-1.6 for the others (Helsinki, about 400 actors)."""
        made, total = self._shape_pool.setdefault(("parts", str(npz), part_faces), ([], [None]))
        i, V, F = 0, None, None
        while True:
            if i < len(made):
                yield made[i]
                i += 1
                continue
            if total[0] is not None and i >= total[0]:
                return
            if F is None:
                with np.load(npz) as d:
                    V, F = d["v"].astype(np.float64), d["f"]
                # (three times the faces' centroids: only their order counts)
                F = F[compact_order(V[F[:, 0], :2] + V[F[:, 1], :2] + V[F[:, 2], :2], part_faces)]
                total[0] = (len(F) + part_faces - 1) // part_faces
                yield None
            if i >= total[0]:
                return
            Fi = F[i * part_faces:(i + 1) * part_faces]
            used, inv = np.unique(Fi, return_inverse=True)
            made.append(pb.createCollisionShape(pb.GEOM_MESH, vertices=V[used].tolist(),
                                                indices=inv.ravel().tolist(),
                                                flags=pb.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=self.client))
            yield made[i]
            i += 1

    def _shapes(self, f: Path, kind: str, collide: bool):
        key = (str(f), collide, self.visuals)
        got = self._shape_pool.get(key)
        if got is None:
            c = self.client
            col = pb.createCollisionShape(pb.GEOM_MESH, fileName=str(f), flags=pb.GEOM_FORCE_CONCAVE_TRIMESH,
                                          physicsClientId=c) if collide else -1
            vis = pb.createVisualShape(pb.GEOM_MESH, fileName=str(f), rgbaColor=COLOURS.get(kind, (0.7, 0.7, 0.7, 1)),
                                       physicsClientId=c) if self.visuals else -1
            got = (col, vis)
            self._shape_pool[key] = got
        return got

    HF_RANGE = 600.0

    def _terrain_visual(self, key, g, pos):
        """A visual mesh of the tile's grid on Bullet's triangulation (a refilled heightfield
        keeps the visual of its creation data, so terrain is drawn with its own mesh).
        Cached per tile, as PyBullet cannot free visual shapes."""
        pool_key = ("terrain-visual", key, str(self.world.chunks[(key[0], key[1])]["_base"]))
        vis = self._shape_pool.get(pool_key)
        if vis is not None:
            return vis
        ny, nx = g.z.shape
        xs = np.arange(nx) * g.spacing + g.xmin - pos[0]
        ys = np.arange(ny) * g.spacing + g.ymin - pos[1]
        X, Y = np.meshgrid(xs, ys)
        V = np.column_stack([X.ravel(), Y.ravel(), (g.z - pos[2]).ravel()])
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b_, c_, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]   # (r,c) (r,c+1) (r+1,c) (r+1,c+1)
        tri = np.concatenate([np.stack([a, b_, c_], -1).reshape(-1, 3), np.stack([b_, d, c_], -1).reshape(-1, 3)])
        vis = pb.createVisualShape(pb.GEOM_MESH, vertices=V.tolist(), indices=tri.ravel().tolist(),
                                   rgbaColor=COLOURS["terrain"], physicsClientId=self.client)
        self._shape_pool[pool_key] = vis
        return vis

    def _heightfield(self, g):
        """A pooled heightfield shape filled with tile grid `g`; returns (shape, body z).

        PyBullet never frees a collision shape once a body used it, so heightfield shapes
        are reused: a free one of the same size is refilled in place
        (``replaceHeightfieldIndex``). Bullet centres a heightfield on (min+max)/2 of the data
        it was *created* with and keeps that on refill, so every shape is created spanning
        a fixed range of +-HF_RANGE (centre 0) and heights are stored relative to the
        tile's own base, with the body placed at that base.
        """
        ny, nx = g.z.shape
        key = (nx, ny, g.spacing)
        base = float(np.round((g.z.min() + g.z.max()) / 2.0))
        data = (g.z - base).ravel().tolist()
        c = self.client
        free = self._hf_free.get(key)
        if free:
            sh = free.pop()
        else:
            init = np.zeros(nx * ny)
            init[0], init[1] = -self.HF_RANGE, self.HF_RANGE
            sh = pb.createCollisionShape(pb.GEOM_HEIGHTFIELD, meshScale=[g.spacing, g.spacing, 1.0],
                                         heightfieldData=init.tolist(), numHeightfieldRows=nx,
                                         numHeightfieldColumns=ny, physicsClientId=c)
            self._hf_key_of[sh] = key
            self.hf_shapes_created += 1
        pb.createCollisionShape(pb.GEOM_HEIGHTFIELD, meshScale=[g.spacing, g.spacing, 1.0], heightfieldData=data,
                                numHeightfieldRows=nx, numHeightfieldColumns=ny, replaceHeightfieldIndex=sh,
                                physicsClientId=c)
        return sh, base

    def _load_prefabs(self):
        meta = json.loads((prefab_dir() / "prefabs.json").read_text())["prefabs"]
        for kind, m in meta.items():
            col = m["collision"]
            off = col.get("offset", [0, 0, 0])
            if col["type"] == "cylinder":
                cs = (pb.GEOM_CYLINDER, float(col["radius"]), [0.0, 0.0, 0.0], float(col["height"]), list(off))
            else:
                cs = (pb.GEOM_BOX, 0.0, list(col["half_extents"]), 0.0, list(off))
            self._prefabs[kind] = (cs, None, m["file"])

    def _scenery_bodies(self, key, part_faces: int = 0):
        """The tile's scenery (trees, lamps, signals, signs, benches), lists of bodies, one
        list per iteration: the items' colliders (prefabs.json's cylinders and boxes, as
        12-sided prisms and boxes) merged into one triangle mesh, or, with ``part_faces``, into
        one mesh per run of items of about that many faces (a tile of trees took 5 ms a mesh),
        the visual bodies (visuals on) with the last. Bullet's step costs about 0.6 us per body, so one body
        per item (hundreds per tile) cost more than the rest of the world together; and
        PyBullet takes about 0.25 ms per child to create a compound body, so compounds of 16
        primitives cost 20-45 ms per tile, where the mesh takes 1-3 ms (and a pooled one well
        under 1 ms). With visuals on, each kind's meshes are merged into visual-only bodies of
        up to COMPOUND_MAX (PyBullet's limit per shape array)."""
        inst = self.world.scenery((key[0], key[1]))
        if not inst:
            return
        xmin, ymin, xmax, ymax = self.world.tile_bounds(key)
        items = [s for s in inst if xmin <= s["x"] < xmax and ymin <= s["y"] < ymax and s["kind"] in self._prefabs]
        if not items:
            return
        c = self.client
        ox, oy = (xmin + xmax) / 2.0, (ymin + ymax) / 2.0   # bodies' origin: the tile's centre

        def frame(s, off=(0.0, 0.0, 0.0)):
            yaw = float(s.get("yaw", 0.0))
            cy, sy = math.cos(yaw), math.sin(yaw)
            return ([s["x"] - ox + cy * off[0] - sy * off[1], s["y"] - oy + sy * off[0] + cy * off[1], s["z"] + off[2]],
                    [0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])

        # (runs of items by an upper bound of their faces: a prism 44, a box 12)
        per = max(1, part_faces // 44) if part_faces else len(items)
        if len(items) > per:                # (runs of neighbours: see compact_order)
            order = compact_order(np.array([(s["x"], s["y"]) for s in items], float), per)
            items = [items[k] for k in order]
        runs = [items[n:n + per] for n in range(0, len(items), per)]
        for n, run in enumerate(runs):
            cs = self._shape_pool.get(("scenery-mesh", key, per, n))
            if cs is None:
                V, F = _colliders_mesh([self._prefabs[s["kind"]][0] for s in run],
                                       [frame(s, self._prefabs[s["kind"]][0][4]) for s in run])
                cs = pb.createCollisionShape(pb.GEOM_MESH, vertices=V.tolist(), indices=F.ravel().tolist(),
                                             flags=pb.GEOM_FORCE_CONCAVE_TRIMESH, physicsClientId=c)
                self._shape_pool[("scenery-mesh", key, per, n)] = cs
            body = static_body(c, cs, self._unseen(), (ox, oy, 0.0))
            if n < len(runs) - 1:
                yield [body]
        bodies = [body]
        if self.visuals:
            by_kind: dict = {}
            for s in items:
                by_kind.setdefault(s["kind"], []).append(s)
            for kind, group in by_kind.items():
                f = str(prefab_dir() / self._prefabs[kind][2])
                for n0 in range(0, len(group), COMPOUND_MAX):
                    part = group[n0:n0 + COMPOUND_MAX]
                    vs = self._shape_pool.get(("scenery-visual", key, kind, n0))
                    if vs is None:
                        frames = [frame(s) for s in part]
                        vs = pb.createVisualShapeArray(
                            shapeTypes=[pb.GEOM_MESH] * len(part), fileNames=[f] * len(part),
                            meshScales=[[1, 1, 1]] * len(part), visualFramePositions=[fr[0] for fr in frames],
                            visualFrameOrientations=[fr[1] for fr in frames], physicsClientId=c)
                        self._shape_pool[("scenery-visual", key, kind, n0)] = vs
                    b = static_body(c, -1, vs, (ox, oy, 0.0))
                    pb.changeVisualShape(b, -1, rgbaColor=PREFAB_COLOURS.get(kind, (0.6, 0.6, 0.6, 1)),
                                         physicsClientId=c)
                    bodies.append(b)
        yield bodies

    def _chunk_visual_ref(self, ij, delta):
        body, n = self._chunk_visuals.get(ij, (None, 0))
        n += delta
        c = self.client
        if n > 0 and body is None:
            f = self.world.chunks[ij]["files"].get("scenery_obj")
            if f:
                _, vis = self._shapes(self.world.file(ij, f), "areas", False)
                body = static_body(c, -1, vis, (0, 0, 0))
        if n <= 0 and body is not None:
            pb.removeBody(body, physicsClientId=c)
            body = None
        if n <= 0:
            self._chunk_visuals.pop(ij, None)
        else:
            self._chunk_visuals[ij] = (body, n)

    # --- queries --------------------------------------------------------------------------
    def camera_image(self, eye, target, width=640, height=400, fov=60.0, far=600.0, up=(0, 0, 1)):
        """An RGB picture (height, width, 3) from ``eye`` towards ``target``. Where the camera
        sees nothing (PyBullet leaves those pixels white), a sky: :data:`SKY_TOP_RGB` at the
        top of the picture to :data:`SKY_HORIZON_RGB` at its bottom."""
        c = self.client
        view = pb.computeViewMatrix(eye, target, up, physicsClientId=c)
        proj = pb.computeProjectionMatrixFOV(fov, width / height, 0.5, far, physicsClientId=c)
        renderer = pb.ER_BULLET_HARDWARE_OPENGL if self.gui else pb.ER_TINY_RENDERER
        _, _, rgb, depth, seg = pb.getCameraImage(width, height, view, proj, renderer=renderer,
                                                  shadow=0, physicsClientId=c)
        img = np.array(np.reshape(np.asarray(rgb, dtype=np.uint8), (height, width, 4))[:, :, :3])
        sky = np.reshape(np.asarray(seg), (height, width)) < 0
        if sky.any():
            t = np.linspace(0.0, 1.0, height)[:, None]
            rows = np.rint((1.0 - t) * np.array(SKY_TOP_RGB) + t * np.array(SKY_HORIZON_RGB)).astype(np.uint8)
            img[sky] = np.broadcast_to(rows[:, None, :], img.shape)[sky]
        return img

    def body_kind(self, body: int) -> str:
        """What a static body is: terrain, a mesh class of a tile, or scenery."""
        for key, tb in self.tiles.items():
            if body in tb.bodies:
                i = tb.bodies.index(body)
                return tb.kinds[i] if i < len(tb.kinds) else "scenery"
        return "unknown"

    def body_count(self) -> int:
        return pb.getNumBodies(physicsClientId=self.client)
