"""The PyBullet world streamed from a built world: terrain, meshes, pooling."""
from __future__ import annotations

import numpy as np
import pybullet as pb
import pytest

from cosim.physics import COLLIDE, PART_FACES, PhysicsWorld
from cosim.world import World
from netgen.build import build_world
from netgen.config import WorldConfig
from tests.conftest import shared_file


@pytest.fixture(scope="module")
def monaco_world(tmp_path_factory):
    osm = shared_file("osm/monaco-2022.osm.pbf")
    dem = shared_file("dem/N43E007.hgt")
    out = tmp_path_factory.mktemp("phys") / "monaco"
    build_world(WorldConfig(osm=str(osm), dem=[str(dem)], center=(43.7384, 7.4246), chunks=1,
                            terrain_spacing_m=5.0, out=str(out), cache_dir=str(out.parent / "cache")))
    return World(out)


def test_heightfield_matches_the_terrain_grid(monaco_world):
    """Rays that hit a tile's heightfield find the world's ground height (steep Monaco), across
    tile and chunk borders."""
    w = monaco_world
    pw = PhysicsWorld(w).setup()
    try:
        pw.update(480.0, 0.0, 400.0, budget_ms=1e9)       # straddles the chunk border at x = 500
        hf_bodies = {tb.bodies[0] for tb in pw.tiles.values()}
        rng = np.random.default_rng(0)
        pts = rng.uniform([100, -350], [850, 350], (600, 2))
        hits = pb.rayTestBatch([[x, y, 2000] for x, y in pts], [[x, y, -500] for x, y in pts],
                               physicsClientId=pw.client)
        ground = w.ground_z(pts[:, 0], pts[:, 1])
        errs = [abs(h[3][2] - g) for h, g in zip(hits, ground) if h[0] in hf_bodies]
        assert len(errs) > 100
        # World.ground_z follows Bullet's own triangulation of the grid
        assert max(errs) < 0.01, max(errs)
        assert np.ptp(ground) > 30
    finally:
        pw.teardown()


def test_streaming_reuses_shapes(monaco_world):
    """Driving back and forth loads and unloads tiles; collision shapes are pooled, so a revisit
    creates none and the body count returns to the same level."""
    w = monaco_world
    pw = PhysicsWorld(w).setup()
    try:
        route = [(-600, 0), (0, 0), (600, 0), (0, 600), (0, -600)]
        for x, y in route:
            pw.update(x, y, 200.0, budget_ms=1e9)
        hf_after_first, shapes_after_first = pw.hf_shapes_created, len(pw._shape_pool)
        bodies = []
        for _ in range(3):
            for x, y in route:
                pw.update(x, y, 200.0, budget_ms=1e9)
            bodies.append(pw.body_count())
        assert pw.unloads > 20
        assert pw.hf_shapes_created == hf_after_first
        assert len(pw._shape_pool) == shapes_after_first
        assert len(set(bodies)) == 1
        assert pw.covered(0, -600, 150.0)
    finally:
        pw.teardown()


def test_scenery_colliders_are_one_body_per_tile(monaco_world):
    """Every tree, lamp, signal and sign of a loaded tile stops a ray at its collider (where
    prefabs.json puts it), and a tile's scenery is a single body, not one body per item."""
    import json

    from models import prefab_dir

    w = monaco_world
    pw = PhysicsWorld(w).setup()
    try:
        pw.update(0.0, 0.0, 300.0, budget_ms=1e9)
        meta = json.loads((prefab_dir() / "prefabs.json").read_text())["prefabs"]
        items = []
        for key in pw.tiles:
            xmin, ymin, xmax, ymax = w.tile_bounds(key)
            items += [s for s in w.scenery((key[0], key[1])) if xmin <= s["x"] < xmax and ymin <= s["y"] < ymax
                      and s["kind"] in meta]
        assert len(items) > 100
        n_scenery_bodies = sum(1 for tb in pw.tiles.values() for b in tb.bodies if pw.body_kind(b) == "scenery")
        assert n_scenery_bodies <= len(items) / 16 + len(pw.tiles)     # merged, not one body per item
        # a vertical ray down onto each item's collider, from 1 m above its top
        starts, ends, want = [], [], []
        for s in items:
            col = meta[s["kind"]]["collision"]
            cz = s["z"] + col.get("offset", [0, 0, 0])[2]          # the collider's centre height
            top = cz + (col["height"] / 2 if col["type"] == "cylinder" else col["half_extents"][2])
            starts.append([s["x"], s["y"], top + 1.0])
            ends.append([s["x"], s["y"], cz])
            want.append(top)
        hits = pb.rayTestBatch(starts, ends, physicsClientId=pw.client)
        kinds = [pw.body_kind(h[0]) for h in hits]
        hit_scenery = sum(1 for k in kinds if k == "scenery")
        print(f"{hit_scenery}/{len(want)} scenery colliders hit; other hits: "
              f"{sorted(set(k for k in kinds if k != 'scenery'))}")
        assert hit_scenery >= 0.95 * len(want)
        tops = [abs(h[3][2] - t) for h, k, t in zip(hits, kinds, want) if k == "scenery"]
        assert max(tops) < 0.02          # at the collider's top: placed where prefabs.json says
    finally:
        pw.teardown()


def test_tile_loading_is_paced_by_how_near_the_missing_tiles_are(monaco_world):
    """Tiles ahead come a part per call, only while the caller has time to spare (SUMO still
    stepping in its worker), until one within ``urgent_radius`` is missing (then a part per
    call anyway) or one within ``critical_radius`` (then parts within the time budget)."""
    w = monaco_world
    pw = PhysicsWorld(w).setup()
    try:
        k0 = next(k for k in w.tiles_within(0.0, 0.0, 10.0) if w.is_built(k))
        xmin, ymin, xmax, ymax = w.tile_bounds(k0)
        x, y = xmax - 45.0, (ymin + ymax) / 2      # 45 m from k0's east edge
        k1 = next(k for k in w.tiles_within(xmax + 1.0, y, 0.5) if w.is_built(k))
        assert w.tiles_within(x, y, 30.0) == [k0] and set(w.tiles_within(x, y, 60.0)) == {k0, k1}
        pw.load_tile(k0)
        pw.load_tile(k1)
        kw = dict(unload_radius=2000.0, budget_ms=1000.0, urgent_radius=60.0, critical_radius=30.0)
        r = pw.update(x, y, 400.0, spare=lambda: False, **kw)     # no time to spare: nothing
        assert r["loaded"] == 0 and not pw._loading and r["pending"] > 0
        r = pw.update(x, y, 400.0, spare=lambda: True, **kw)      # time to spare: one part
        assert r["loaded"] == 0 and len(pw._loading) == 1
        (far, job), = pw._loading.items()
        assert len(pw._loading[far][0].kinds) <= 1
        # k1 missing (within the urgent radius): one part a call, time to spare or not
        pw.unload_tile(k1)
        r = pw.update(x, y, 400.0, spare=lambda: False, **kw)
        assert r["loaded"] == 0 and k1 in pw._loading and k1 not in pw.tiles
        assert len(pw._loading[k1][0].kinds) <= 1 and len(pw._loading[far][0].kinds) <= 1
        # k0 missing (within the critical radius): parts within the budget
        pw.unload_tile(k0)
        r = pw.update(x, y, 400.0, spare=lambda: False, **kw)
        assert k0 in pw.tiles and k1 in pw.tiles and r["loaded"] >= 2 and pw.covered(x, y, 60.0)
    finally:
        pw.teardown()


def test_tiles_load_a_part_at_a_time_within_the_budget(monaco_world):
    """With a budget smaller than a tile, ``update`` makes one part of a tile per call (the
    terrain's heights, then its body; each mesh class's file read, then PART_FACES faces at a
    time; the scenery); a tile counts as loaded,
    and ``covered``, only once all its parts are in, and it ends with the same bodies as a tile
    loaded at once."""
    w = monaco_world
    whole = PhysicsWorld(w).setup()
    part = PhysicsWorld(w).setup()
    try:
        key = next(k for k in w.tiles_within(0.0, 0.0, 10.0) if w.is_built(k))
        xmin, ymin, xmax, ymax = w.tile_bounds(key)
        kx, ky = (xmin + xmax) / 2, (ymin + ymax) / 2          # (a disc inside that one tile)
        kinds_whole = whole.load_tile(key).kinds
        n_parts = 3 + sum(1 + -(-len(np.load(f.with_suffix(".npz"))["f"]) // PART_FACES)
                          for kind, f in w.tile_files(key).items() if kind in COLLIDE)
        assert n_parts > 3 + sum(1 for kind in w.tile_files(key) if kind in COLLIDE)     # (some class in parts)
        calls = 0
        while key not in part.tiles:
            r = part.update(kx, ky, 10.0, budget_ms=0.0)    # one part per call
            calls += 1
            if key not in part.tiles:
                assert r["loaded"] == 0 and not part.covered(kx, ky, 5.0)
            assert calls <= 50
        assert calls >= n_parts - 1 and part.covered(kx, ky, 5.0)
        tb = part.tiles[key]
        assert tb.kinds == kinds_whole and len(tb.bodies) == len(whole.tiles[key].bodies)
        # a stale tile (its chunk rebuilt: ``refresh``) is replaced a class at a time, each new
        # class whole taking the place of the old one in the same call: never a hole, never
        # doubled
        assert part.refresh([(key[0], key[1])]) == 1
        old, calls = part.tiles[key], 0
        while part.tiles[key] is old:
            part.update(kx, ky, 10.0, budget_ms=0.0)
            calls += 1
            assert part.replaced_now == [key]          # (what the loop checks the car against)
            assert key in part.tiles and part.covered(kx, ky, 5.0)
            job = part._loading.get(key)
            if job is not None:
                for kind in set(old.kinds):
                    live_old = any(b is not None for b, k in zip(old.bodies, old.kinds) if k == kind)
                    assert live_old != (kind in job[0].kinds), kind
            assert calls <= 50
        assert not part._stale and not part._loading
        part.update(kx, ky, 10.0, budget_ms=0.0)
        assert part.replaced_now == []
        new = part.tiles[key]
        assert set(new.kinds) == set(kinds_whole) and all(b is None for b in old.bodies)
        assert all(b is not None for b in new.bodies)
        # what stands on the tile still stands on the ground
        hit = pb.rayTest([kx, ky, 1000.0], [kx, ky, -1000.0], physicsClientId=part.client)[0]
        assert hit[0] in new.bodies
        # a tile that leaves the window half made leaves no body behind
        other = next(k for k in w.tiles_within(0.0, 0.0, 600.0) if w.is_built(k) and k not in part.tiles)
        xmin, ymin, xmax, ymax = w.tile_bounds(other)
        cx, cy = (xmin + xmax) / 2, (ymin + ymax) / 2
        n0 = pb.getNumBodies(physicsClientId=part.client)
        part.update(cx, cy, 1.0, unload_radius=2000.0, budget_ms=0.0)    # its terrain's heights
        hf = part._loading[other][0].hf_shape
        assert hf >= 0 and pb.getNumBodies(physicsClientId=part.client) == n0
        part.update(cx, cy, 1.0, unload_radius=2000.0, budget_ms=0.0)    # its terrain's body
        assert other in part._loading and pb.getNumBodies(physicsClientId=part.client) > n0
        part.update(5000.0, 5000.0, 1.0, unload_radius=10.0, budget_ms=0.0)
        assert not part._loading and not part.tiles and pb.getNumBodies(physicsClientId=part.client) == 0
        assert any(hf in free for free in part._hf_free.values())          # (its shape back in the pool)
    finally:
        whole.teardown()
        part.teardown()


def test_tiles_by_distance_are_the_tiles_each_radius_touches(monaco_world):
    """The tiles around a point, nearest first, for one radius and filtered for smaller ones
    (as ``update`` does for its radii), are the tiles whose squares the discs touch."""
    w = monaco_world
    rng = np.random.default_rng(3)
    t = w.tile_size
    for x, y in rng.uniform(-1400.0, 1400.0, (40, 2)):
        near = w.tiles_by_distance(x, y, 700.0)
        assert [d for d, _ in near] == sorted(d for d, _ in near)
        for r in (50.0, 230.0, 475.0, 700.0):
            got = [k for d2, k in near if d2 <= r * r]
            assert got == w.tiles_within(x, y, r)
            brute = set()
            for gx in range(-12, 12):
                for gy in range(-12, 12):
                    x0, y0 = gx * t - w.chunk_size / 2, gy * t - w.chunk_size / 2
                    dx = max(x0 - x, 0.0, x - (x0 + t))
                    dy = max(y0 - y, 0.0, y - (y0 + t))
                    if dx * dx + dy * dy <= r * r:
                        i, a = divmod(gx, w.nt)
                        j, b = divmod(gy, w.nt)
                        brute.add((i, j, a, b))
            assert set(got) == brute and len(got) == len(brute)


def test_a_class_in_parts_is_the_same_surface_as_its_obj(monaco_world):
    """Each colliding tile class has a binary copy (``<class>.npz``: the OBJ's vertices and
    faces); loaded PART_FACES faces at a time, a body each, it is the surface the OBJ makes
    (rays straight down over the tiles around the centre hit the same heights)."""
    import trimesh

    from cosim.physics import TileBodies

    w = monaco_world
    keys = [k for k in w.tiles_within(0.0, 0.0, 300.0) if w.is_built(k)]
    n_files = 0
    for k in keys:
        for kind, f in w.tile_files(k).items():
            if kind in COLLIDE:
                d = np.load(f.with_suffix(".npz"))
                m = trimesh.load(f, force="mesh", process=False)
                assert d["f"].shape == m.faces.shape and np.array_equal(d["f"], m.faces)
                assert np.abs(d["v"] - m.vertices).max() < 2e-3
                n_files += 1
    assert n_files >= 10
    worlds = []
    for part_faces in (PART_FACES, 0):
        pw = PhysicsWorld(w).setup()
        for k in keys:
            tb = TileBodies()
            for _ in pw._tile_parts(k, tb, part_faces):
                pass
            pw.tiles[k] = tb
        worlds.append(pw)
    try:
        parts, whole = worlds
        assert sum(len(t.bodies) for t in parts.tiles.values()) > sum(len(t.bodies) for t in whole.tiles.values())
        rng = np.random.default_rng(0)
        P = rng.uniform(-280.0, 280.0, (2000, 2))

        def heights(pw):
            hits = pb.rayTestBatch([[x, y, 2000.0] for x, y in P], [[x, y, -500.0] for x, y in P],
                                   physicsClientId=pw.client)
            return np.array([h[3][2] if h[0] >= 0 else np.nan for h in hits])

        a, b = heights(parts), heights(whole)
        assert np.array_equal(np.isnan(a), np.isnan(b)) and np.nanmax(np.abs(a - b)) < 2e-3
    finally:
        for pw in worlds:
            pw.teardown()


def test_a_classs_parts_are_neighbourhoods_of_the_tile(monaco_world):
    """A mesh class cut into parts comes as parts that each cover a piece of the tile, not
    the whole of it (``compact_order``): the boxes of a class's part bodies add up to about
    the box of the class (in the files' own order they add up to nearly twice it, and the
    car's chassis and every ray were tested against each part). The same for the scenery's
    runs of colliders."""
    from cosim.physics import TileBodies, compact_order

    rng = np.random.default_rng(5)
    xy = rng.uniform(0.0, 250.0, (2345, 2))
    order = compact_order(xy, 500)
    assert sorted(order) == list(range(len(xy)))
    runs = [xy[order[i:i + 500]] for i in range(0, len(xy), 500)]
    assert [len(r) for r in runs] == [500, 500, 500, 500, 345]
    area = sum(float(np.prod(r.max(axis=0) - r.min(axis=0))) for r in runs)
    assert area < 1.1 * 250.0 * 250.0           # (in the given order: about 5 x the square)

    w = monaco_world
    pw = PhysicsWorld(w).setup()
    try:
        checked = scenery = 0
        for k in [k for k in w.tiles_within(0.0, 0.0, 400.0) if w.is_built(k)]:
            tb = TileBodies()
            for _ in pw._tile_parts(k, tb, PART_FACES):
                pass
            by_kind = {}
            for i, b in enumerate(tb.bodies):
                kind = tb.kinds[i] if i < len(tb.kinds) else "scenery"
                lo, hi = pb.getAABB(b, -1, physicsClientId=pw.client)
                by_kind.setdefault(kind, []).append((lo[:2], hi[:2]))
            for kind, boxes in by_kind.items():
                if kind == "terrain" or len(boxes) < 2:
                    continue
                lo = np.min([b[0] for b in boxes], axis=0)
                hi = np.max([b[1] for b in boxes], axis=0)
                parts = sum(float(np.prod(np.subtract(b[1], b[0]))) for b in boxes)
                assert parts <= 1.3 * float(np.prod(hi - lo)), (k, kind, parts / float(np.prod(hi - lo)))
                checked += 1
                scenery += kind == "scenery"
        assert checked >= 5 and scenery >= 1
    finally:
        pw.teardown()


def test_static_bodies_are_asleep_and_still_met_where_they_are_moved():
    """Static bodies are made asleep (``static_body``: PyBullet's step writes a notification
    for every awake body). A sleeping body that the mirror moves must still be where rays,
    the car's collisions and the camera find it, at once and after steps."""
    import ast
    from pathlib import Path

    from cosim.physics import static_body

    c = pb.connect(pb.DIRECT)
    try:
        cs = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[1, 1, 1], physicsClientId=c)
        vs = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[1, 1, 1], rgbaColor=[1, 0, 0, 1], physicsClientId=c)
        b = static_body(c, cs, vs, (0.0, 0.0, 0.0))
        ball = pb.createMultiBody(1.0, pb.createCollisionShape(pb.GEOM_SPHERE, radius=0.5, physicsClientId=c),
                                  -1, [6.0, 0.0, 3.0], physicsClientId=c)
        pb.setGravity(0, 0, -9.81, physicsClientId=c)
        view = pb.computeViewMatrix([0, -15, 3], [0, 0, 0], [0, 0, 1])
        proj = pb.computeProjectionMatrixFOV(60, 1, 0.1, 100)

        def red_columns():
            rgb = np.reshape(pb.getCameraImage(100, 100, view, proj, physicsClientId=c)[2], (100, 100, 4))
            cols = np.flatnonzero(((rgb[:, :, 0] > 200) & (rgb[:, :, 1] < 50)).any(axis=0))
            return float(cols.mean())

        def ray_hits(x):
            return pb.rayTest([x, -5, 0], [x, 5, 0], physicsClientId=c)[0][0] == b

        before = red_columns()
        for _ in range(5):
            pb.stepSimulation(physicsClientId=c)
        pb.resetBasePositionAndOrientation(b, [6.0, 0.0, 0.0], [0, 0, 0, 1], physicsClientId=c)
        assert ray_hits(6.0) and not ray_hits(0.0)          # at once: the broadphase moved it
        for _ in range(400):
            pb.stepSimulation(physicsClientId=c)
        assert ray_hits(6.0) and not ray_hits(0.0)
        assert red_columns() > before + 15                  # drawn where it is now
        # the falling ball lands on it (a sleeping static body still collides)
        assert 1.3 < pb.getBasePositionAndOrientation(ball, physicsClientId=c)[0][2] < 1.6
    finally:
        pb.disconnect(c)
    # every body the co-simulation makes without mass is made by static_body
    for f in sorted((Path(__file__).resolve().parents[1] / "cosim").glob("*.py")):
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "createMultiBody":
                assert f.name == "physics.py" and node.args and getattr(node.args[0], "value", None) == 0, \
                    f"{f.name}:{node.lineno}"
    src = (Path(__file__).resolve().parents[1] / "cosim" / "physics.py").read_text()
    assert src.count("createMultiBody(") == 1 and "def static_body" in src


def test_bodies_that_only_collide_are_drawn_as_nothing_in_pybullets_window(monaco_world):
    """PyBullet's window draws a body without a visual shape as its collision shape, in a
    colour of its own: the road's parts were drawn red and blue over the road's own mesh. In
    the window they get an invisible shape; headless none is made for them (a visual shape
    would cost 0.5 ms a body). The window's choice is tested here without a display (``gui`` set after a
    DIRECT setup). The car's link is drawn in its last visual's colour there: the paint."""
    import xml.etree.ElementTree as ET

    from models import car_urdf_path

    for gui in (False, True):
        pw = PhysicsWorld(monaco_world, visuals=False).setup()
        pw.gui = gui
        try:
            pw.update(0.0, 0.0, 150.0, budget_ms=1e9)
            parts = [b for tb in pw.tiles.values() for b, k in zip(tb.bodies, tb.kinds) if k in COLLIDE]
            scenery = [b for tb in pw.tiles.values() for b in tb.bodies[len(tb.kinds):]]   # (their colliders)
            assert len(parts) > 20 and scenery
            for b in parts + scenery:
                shapes = pb.getVisualShapeData(b, physicsClientId=pw.client)
                if gui:
                    assert len(shapes) == 1 and shapes[0][2] == pb.GEOM_SPHERE and shapes[0][7][3] == 0.0
                else:                   # (PyBullet's own stand-in, made from the collision shape)
                    assert all(d[2] != pb.GEOM_SPHERE for d in shapes)
        finally:
            pw.teardown()
    base = ET.parse(car_urdf_path()).getroot().find("link[@name='base_link']")
    assert base.findall("visual")[-1].find("material").get("name") == "paint"
