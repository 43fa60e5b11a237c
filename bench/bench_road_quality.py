"""Road surface quality of built worlds: what a car's wheels and chassis meet.

For each world folder given (built by ``cosim build``), from its tile meshes and terrain:

* steep surface: area of asphalt and sidewalk faces steeper than 40 % and 70 %, per element
  (``lane``, ``junction``, ``junction_lane``, ``walkingarea``); and the junctions'
  area-weighted grade at the 90th / 99th percentile (a fold between road ends of different
  heights shows as a steep face);
* steps between roads: 5 m cells where faces of two different roads (not the two directions
  of one street) lie within 0.8 m of each other in plan and more than 0.15 / 0.3 / 0.6 m
  apart in height, up to 4 m (further apart: a bridge's deck over a road, counted apart as
  deck cells); the same, apart, where one of the two is a junction's face (a junction beside
  a lane, two junctions that overlap);
* sidewalk over a lane: 5 m cells where a sidewalk's face lies within 1 m in plan of a vehicle
  lane's face and 0.3-4 m above it (a slab the car's body drives into);
* grade along the lanes: for each lane a passenger car may use (tunnels left out), the road's
  surface followed along its centreline every 0.5 m with PyBullet's rays (each from 1.5 m above
  the last hit: a deck or a roof above is not taken), and the steepest rise over 2 m; the lanes
  whose steepest 2 m are over 20 / 30 / 40 / 60 %, and the steepest ones (a step where a lane
  meets a junction's plane shows here; Monaco's Rond-Point du Portier stalled the car);
* terrain above the road: the area of asphalt (lanes, junctions; sampled at 8 random points
  per m2, on the physics heightfield's triangles) under the terrain by more than 0 / 5 / 15 /
  30 / 100 cm (the terrain is levelled 8 cm under the road; above it, the car drives on the
  terrain).

    .venv/bin/python bench/bench_road_quality.py WORLD [WORLD ...]

Prints one block per world and the figures side by side.
"""
from __future__ import annotations

import argparse
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cosim.world import World  # noqa: E402


SAMPLES_PER_M2 = 8.0
CLEARANCE_M = 4.0       # two surfaces further apart than this: a bridge's deck over a road


def _groups(world: World, kind: str):
    for c in world.chunks.values():
        for tile in c.get("tiles", {}).values():
            if kind in tile:
                scene = trimesh.load(c["_base"] / tile[kind], group_material=False, split_groups=True,
                                     process=False, force="scene")
                yield from scene.geometry.items()


def _road_of(name: str) -> str:
    """The street of a lane piece: its edge without the direction sign."""
    e = name.split("/", 1)[-1].rsplit("_", 1)[0]
    return e[1:] if e.startswith("-") else e


def _area_samples(g, rng, per_m2: float = SAMPLES_PER_M2) -> np.ndarray:
    """Random points on a mesh's faces, `per_m2` per square metre on average."""
    T = g.triangles
    fi = np.repeat(np.arange(len(T)), rng.poisson(g.area_faces * per_m2))
    u, v = rng.random(len(fi)), rng.random(len(fi))
    flip = u + v > 1.0
    u[flip], v[flip] = 1.0 - u[flip], 1.0 - v[flip]
    A = T[fi, 0]
    return A + u[:, None] * (T[fi, 1] - A) + v[:, None] * (T[fi, 2] - A)


def measure(path: str) -> dict:
    world = World(path)
    steep = defaultdict(lambda: [0.0, 0.0, 0.0])
    jgrade, jarea = [], []
    C, Z, R = [], [], []
    SW, LN = [], []
    above = []
    rng = np.random.default_rng(0)
    for kind in ("asphalt", "sidewalk"):
        for name, g in _groups(world, kind):
            n = g.face_normals
            grade = np.hypot(n[:, 0], n[:, 1]) / np.maximum(np.abs(n[:, 2]), 1e-9)
            area = g.area_faces
            el = f"{kind}/{name.split('/', 1)[0]}"
            steep[el][0] += float(area.sum())
            steep[el][1] += float(area[grade > 0.4].sum())
            steep[el][2] += float(area[grade > 0.7].sum())
            if kind != "asphalt":
                if name.startswith("lane/"):
                    SW.append(g.triangles_center)
                continue
            P = g.triangles_center
            if name.startswith("junction/"):
                jgrade.append(grade)
                jarea.append(area)
            if name.startswith("lane/"):
                LN.append(P)
                C.append(P[:, :2])
                Z.append(P[:, 2])
                R += [_road_of(name)] * len(P)
            elif name.startswith("junction/"):
                C.append(P[:, :2])
                Z.append(P[:, 2])
                R += [name] * len(P)
            S = _area_samples(g, rng)
            d = world.ground_z(S[:, 0], S[:, 1]) - S[:, 2]
            above.append(d[np.isfinite(d)])
    out = {"steep": {k: v for k, v in sorted(steep.items())}}
    if jgrade:
        g, a = np.concatenate(jgrade), np.concatenate(jarea)
        o = np.argsort(g)
        cum = np.cumsum(a[o]) / a.sum()
        out["junction_grade_p90_p99"] = [float(x) for x in g[o][np.searchsorted(cum, [0.9, 0.99])]]
    if C:
        C, Z, R = np.vstack(C), np.concatenate(Z), np.array(R)
        pairs = cKDTree(C).query_pairs(0.8, output_type="ndarray")
        pairs = pairs[R[pairs[:, 0]] != R[pairs[:, 1]]]
        dz = np.abs(Z[pairs[:, 0]] - Z[pairs[:, 1]])
        out["deck_cells"] = len({(int(x // 5), int(y // 5)) for x, y in C[pairs[dz > CLEARANCE_M, 0]]})
        dz = np.where(dz > CLEARANCE_M, 0.0, dz)        # (a bridge's deck over a road: no step)
        junc = np.char.startswith(R.astype(str), "junction/")
        lanes = ~junc[pairs[:, 0]] & ~junc[pairs[:, 1]]
        out["step_cells"] = {th: len({(int(x // 5), int(y // 5)) for x, y in C[pairs[lanes & (dz > th), 0]]})
                             for th in (0.15, 0.3, 0.6)}
        out["junction_step_cells"] = {th: len({(int(x // 5), int(y // 5)) for x, y in C[pairs[~lanes & (dz > th), 0]]})
                                      for th in (0.15, 0.3, 0.6)}
    if SW and LN:
        S, L = np.vstack(SW), np.vstack(LN)
        near = cKDTree(S[:, :2]).query_ball_point(L[:, :2], 1.0)
        hits = [(x, y) for (x, y, z), nb in zip(L, near) if nb and np.any((S[nb, 2] - z > 0.3) & (S[nb, 2] - z < 4.0))]
        out["sidewalk_over_lane_cells"] = len({(int(x // 5), int(y // 5)) for x, y in hits})
    if above:
        d = np.concatenate(above)
        out["terrain_above"] = {th: float(np.sum(d > th)) / SAMPLES_PER_M2 for th in (0.0, 0.05, 0.15, 0.3, 1.0)}
    return out


GRADE_STEP_M = 0.5
GRADE_SPAN_M = 2.0


def lane_grades(path: str) -> dict:
    """Lane id -> (the steepest rise over GRADE_SPAN_M along its centreline, x, y there)."""
    import json

    import pybullet as p
    import sumolib

    from cosim.physics import PhysicsWorld

    world = World(path)
    meta = json.loads((Path(path) / "world.json").read_text())
    x0, y0, x1, y1 = meta["extent_m"]
    pw = PhysicsWorld(world, visuals=False).setup()
    try:
        pw.update((x0 + x1) / 2, (y0 + y1) / 2, keep_radius=float(np.hypot(x1 - x0, y1 - y0)), budget_ms=1e9)
        cid = pw.client
        net = sumolib.net.readNet(str(Path(path) / meta["net_file"]), withInternal=True)
        tunnels = set(meta.get("tunnels", []))
        k = int(round(GRADE_SPAN_M / GRADE_STEP_M))
        out = {}
        for e in net.getEdges(withInternal=True):
            if e.getID() in tunnels:
                continue
            for ln in e.getLanes():
                if not ln.allows("passenger"):
                    continue
                shp = np.array(ln.getShape())[:, :2]
                s = np.r_[0.0, np.cumsum(np.hypot(*np.diff(shp, axis=0).T))]
                if s[-1] < GRADE_SPAN_M:
                    continue
                ss = np.arange(0.0, s[-1], GRADE_STEP_M)
                x, y = np.interp(ss, s, shp[:, 0]), np.interp(ss, s, shp[:, 1])
                zc = float(np.nan_to_num(world.ground_z(x[:1], y[:1])[0]))
                h = p.rayTest((x[0], y[0], zc + 3.0), (x[0], y[0], zc - 10.0), physicsClientId=cid)[0]
                zc = h[3][2] if h[0] >= 0 else zc
                z = np.full(len(x), np.nan)
                for i, (a, b) in enumerate(zip(x, y)):
                    h = p.rayTest((a, b, zc + 1.5), (a, b, zc - 3.0), physicsClientId=cid)[0]
                    if h[0] >= 0:
                        zc = z[i] = h[3][2]
                g = np.abs(z[k:] - z[:-k]) / GRADE_SPAN_M
                if len(g) and np.isfinite(g).any():
                    i = int(np.nanargmax(g))
                    out[ln.getID()] = (float(g[i]), float(x[i + k // 2]), float(y[i + k // 2]))
        return out
    finally:
        pw.teardown()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("worlds", nargs="+")
    a = ap.parse_args(argv)
    rows = []
    for w in a.worlds:
        r = measure(w)
        rows.append((w, r))
        print(f"== {w}")
        for el, (tot, s40, s70) in r["steep"].items():
            print(f"   {el:22s} area {tot:9.0f} m2 | steeper than 40 %: {s40:8.1f} m2 | than 70 %: {s70:8.1f} m2")
        if "junction_grade_p90_p99" in r:
            p90, p99 = r["junction_grade_p90_p99"]
            print(f"   junction grade, area-weighted: p90 {p90:.3f}, p99 {p99:.3f}")
        if "step_cells" in r:
            print("   5 m cells with a step between two roads: " +
                  ", ".join(f"> {th} m: {n}" for th, n in r["step_cells"].items()))
            print("   5 m cells with a step at a junction (junction beside a lane or another junction): " +
                  ", ".join(f"> {th} m: {n}" for th, n in r["junction_step_cells"].items()))
            print(f"   5 m cells with a deck over a road (surfaces > {CLEARANCE_M:g} m apart): {r['deck_cells']}")
        if "sidewalk_over_lane_cells" in r:
            print(f"   5 m cells with a sidewalk 0.3-4 m above a vehicle lane: {r['sidewalk_over_lane_cells']}")
        grades = lane_grades(w)
        v = np.array([g[0] for g in grades.values()])
        r["lanes_steeper"] = {t: int((v > t).sum()) for t in (0.2, 0.3, 0.4, 0.6)}
        print(f"   grade along the lanes over {GRADE_SPAN_M:g} m, of {len(v)} lanes: " +
              ", ".join(f"> {t * 100:.0f} %: {n}" for t, n in r["lanes_steeper"].items()))
        worst = sorted(grades.items(), key=lambda kv: -kv[1][0])[:5]
        print("   steepest: " + "; ".join(f"{lid} {g * 100:.0f} % at ({x:.0f}, {y:.0f})" for lid, (g, x, y) in worst))
        if "terrain_above" in r:
            print("   asphalt under the terrain by more than: " +
                  ", ".join(f"{th} m: {v:.1f} m2" for th, v in r["terrain_above"].items()))
    if len(rows) > 1:
        print("\nside by side: world | steep > 70 % (m2) | step cells > 0.6 m | sidewalk-over-lane cells | "
              "asphalt under the terrain by > 0.05 m (m2) | lanes with 2 m over 40 %")
        for w, r in rows:
            s70 = sum(v[2] for v in r["steep"].values())
            print(f"  {w} | {s70:.0f} | {r.get('step_cells', {}).get(0.6)} | {r.get('sidewalk_over_lane_cells')} | "
                  f"{r.get('terrain_above', {}).get(0.05, float('nan')):.1f} | {r['lanes_steeper'][0.4]}")


if __name__ == "__main__":
    main()
