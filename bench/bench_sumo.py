"""SUMO-alone benchmark: stepping speed (real-time factor) on the Helsinki preset with dense
traffic, libsumo vs TraCI, and the cost of actors_near (context subscription) vs per-actor
getters. Prints figures and ratios side by side; asserts nothing.

    .venv/bin/python bench/bench_sumo.py [--warmup 60] [--steps 300] [--radius 100]

The network and demand are built once into --workdir (default: a folder in the temp dir) and
reused by later runs.
"""
from __future__ import annotations

import argparse
import logging
import math
import os
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from cosim.demand import generate_demand  # noqa: E402
from cosim.traffic import SumoTraffic, front_to_center, sumo_angle_to_yaw  # noqa: E402
from sumo_fixtures import build_helsinki  # noqa: E402


def busy_pose(t: SumoTraffic):
    """Centre and yaw of a spot on the lane of the vehicle with most neighbours."""
    s = t.sumo
    ids = [v for v in s.vehicle.getIDList() if v != "ego"]
    pos = {v: s.vehicle.getPosition(v) for v in ids}
    sample = ids[:: max(1, len(ids) // 60)]
    best = max(sample, key=lambda v: sum(math.hypot(p[0] - pos[v][0], p[1] - pos[v][1]) < 100
                                         for p in pos.values()))
    lane = s.vehicle.getLaneID(best)
    edge, idx = lane.rsplit("_", 1)
    p = min(3.0, s.lane.getLength(lane) / 2)
    x, y = s.simulation.convert2D(edge, p, int(idx))
    x2, y2 = s.simulation.convert2D(edge, p + 0.5, int(idx))
    angle = math.degrees(math.atan2(x2 - x, y2 - y))
    cx, cy = front_to_center(x, y, angle, 4.5)
    return edge, cx, cy, sumo_angle_to_yaw(angle)


def run_backend(backend, net, routes, args):
    t = SumoTraffic(net, routes, step_length=args.step, seed=1, backend=backend)
    t.setup()
    try:
        t0 = time.perf_counter()
        while t.sim_time < args.warmup - 1e-9:
            t.step()
        warm_wall = time.perf_counter() - t0
        edge, cx, cy, yaw = busy_pose(t)
        t.add_ego([edge])
        t.set_ego_pose(cx, cy, yaw, 0.0)
        t.step()
        t.actors_near(cx, cy, args.radius)      # subscribe once

        # 1) plain stepping with the ego held in place (subscription active, not read)
        n_actors = 0
        t0 = time.perf_counter()
        for _ in range(args.steps):
            t.set_ego_pose(cx, cy, yaw, 0.0)
            t.step()
            n_actors += t.stats.vehicles + t.stats.persons
        step_wall = time.perf_counter() - t0
        # 2) actors_near through the context subscription, once per step
        q_sub, near = 0.0, 0
        for _ in range(args.steps):
            t.set_ego_pose(cx, cy, yaw, 0.0)
            t.step()
            q0 = time.perf_counter()
            snap = t.actors_near(cx, cy, args.radius)
            q_sub += time.perf_counter() - q0
            near += len(snap)
        # 3) the same with per-actor getters
        q_get = 0.0
        for _ in range(args.steps):
            t.set_ego_pose(cx, cy, yaw, 0.0)
            t.step()
            q0 = time.perf_counter()
            t.actors_near_getters(cx, cy, args.radius)
            q_get += time.perf_counter() - q0
        sim_s = args.steps * args.step
        return dict(backend=backend, warmup_wall=warm_wall, rtf=sim_s / step_wall,
                    ms_step=1000 * step_wall / args.steps, actors=n_actors / args.steps,
                    vehicles=t.stats.vehicles, persons=t.stats.persons,
                    near=near / args.steps, ms_sub=1000 * q_sub / args.steps,
                    ms_get=1000 * q_get / args.steps, teleports=t.stats.teleports,
                    collisions=t.stats.collisions)
    finally:
        t.teardown()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workdir", default=os.path.join(tempfile.gettempdir(), "cosim-bench-sumo"))
    ap.add_argument("--density", default="dense")
    ap.add_argument("--warmup", type=float, default=60.0, help="simulated seconds before measuring")
    ap.add_argument("--steps", type=int, default=300, help="steps per measurement")
    ap.add_argument("--step", type=float, default=0.1, help="SUMO step length, s")
    ap.add_argument("--radius", type=float, default=100.0, help="actors_near radius, m")
    ap.add_argument("--backends", default="libsumo,traci")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    work = Path(args.workdir)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    net = work / "helsinki.net.xml"
    if not net.exists():
        build_helsinki(work)
    net_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    duration = args.warmup + 3 * args.steps * args.step + 60
    dem = generate_demand(net, work / "demand", args.density, seed=1, duration=duration)
    dem_s = time.perf_counter() - t0
    print(f"network: {net} ({net_s:.1f} s{' (cached)' if net_s < 0.5 else ''})")
    print(f"demand:  {args.density}: {dem.n_vehicles} vehicle trips, {dem.n_persons} person trips, "
          f"target present {dem.plan.vehicles:.0f} vehicles + {dem.plan.persons:.0f} persons "
          f"({dem_s:.1f} s{', cached' if dem.cached else ''})")
    print(f"warm-up {args.warmup:.0f} s simulated, then {args.steps} steps of {args.step} s per "
          f"measurement; actors_near radius {args.radius:.0f} m\n")
    rows = [run_backend(b.strip(), net, dem.route_files, args) for b in args.backends.split(",")]
    cols = [("actors present (mean, veh+pers)", "actors", "{:.0f}"), ("  vehicles at end", "vehicles", "{}"),
            ("  persons at end", "persons", "{}"), ("ms per step", "ms_step", "{:.2f}"),
            ("real-time factor", "rtf", "{:.1f}x"), ("actors within radius", "near", "{:.0f}"),
            ("actors_near, subscription (ms)", "ms_sub", "{:.3f}"),
            ("actors_near, getters (ms)", "ms_get", "{:.3f}"),
            ("teleports / collisions", None, None), ("warm-up wall (s)", "warmup_wall", "{:.1f}")]
    print(f"{'':32s}" + "".join(f"{r['backend']:>14s}" for r in rows)
          + ("      ratio" if len(rows) == 2 else ""))
    for label, key, fmt in cols:
        if key is None:
            vals = [f"{r['teleports']}/{r['collisions']}" for r in rows]
            print(f"{label:32s}" + "".join(f"{v:>14s}" for v in vals))
            continue
        vals = [r[key] for r in rows]
        line = f"{label:32s}" + "".join(f"{fmt.format(v):>14s}" for v in vals)
        if len(rows) == 2 and key in ("ms_step", "rtf", "ms_sub", "ms_get") and min(vals) > 0:
            line += f"   {max(vals) / min(vals):7.1f}x"
        print(line)
    print()
    for r in rows:
        if r["ms_sub"] > 0:
            print(f"{r['backend']}: getters cost {r['ms_get'] / r['ms_sub']:.1f}x the subscription "
                  f"read per frame; a frame (step + actors_near) is {r['ms_step'] + r['ms_sub']:.2f} ms "
                  f"with the subscription vs {r['ms_step'] + r['ms_get']:.2f} ms with getters")
    if len(rows) == 2:
        a, b = rows
        print(f"{b['backend']} steps {b['ms_step'] / a['ms_step']:.2f}x the time of {a['backend']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
