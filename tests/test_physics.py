"""The PyBullet world streamed from a built world: terrain, meshes, pooling."""
from __future__ import annotations

import numpy as np
import pybullet as pb
import pytest

from cosim.physics import PhysicsWorld
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
