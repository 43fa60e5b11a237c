"""SUMO alone, stepping with idle time between its steps: what the co-simulation's own work
between two SUMO steps costs SUMO on this machine, with nothing else running.

    python bench/bench_sumo_gap.py [--preset helsinki] [--traffic dense] [--warm 60] [--rounds 6]

libsumo steps the same scenario as ``bench_cosim.py`` (the preset's world and its demand) in
this process. After the warm-up, blocks of 25 steps alternate between gaps of 0, 0.3, 1, 2.5,
5 and 10 ms after each step (the gap a busy-wait of the CPU, or a sleep; nothing else runs,
and the busy-wait touches next to no memory). The median step time per gap, and its ratio to
the steps with no gap, are printed. Nothing is asserted.

The co-simulation spends 2.5-3 ms of its own between two SUMO steps (the driver, the physics
and the mirror), and SUMO alone (``bench_cosim.py``'s yardstick) steps back to back; a
difference here is SUMO's step getting slower from idle time alone (caches that other work
on the host evicts meanwhile), which no change of the co-simulation's code removes.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from bench_cosim import sumo_alone_cmd  # noqa: E402
from cosim.demand import generate_demand  # noqa: E402
from netgen.build import build_world  # noqa: E402
from netgen.config import WorldConfig  # noqa: E402

GAPS_MS = (0.0, 0.3, 1.0, 2.5, 5.0, 10.0)
BLOCK = 25


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="helsinki")
    ap.add_argument("--traffic", default="dense")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--warm", type=float, default=60.0)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "worlds"))
    a = ap.parse_args(argv)
    import libsumo

    w = build_world(WorldConfig(preset=a.preset, chunks=1, out=str(Path(a.out) / a.preset)))
    world = Path(w["out"])
    n_steps = int(a.warm / 0.1) + a.rounds * len(GAPS_MS) * BLOCK * 2
    d = generate_demand(world / w["net_file"], world / "traffic", density=a.traffic, seed=a.seed,
                        duration=n_steps * 0.1 + 60.0)
    libsumo.start(sumo_alone_cmd(world / w["net_file"], d.route_files, a.seed))
    try:
        for _ in range(int(a.warm / 0.1)):
            libsumo.simulationStep()
        kinds = [(g, "busy") for g in GAPS_MS] + [(g, "sleep") for g in GAPS_MS if g > 0]
        steps = {k: [] for k in kinds}
        for _ in range(a.rounds):
            for k in kinds:
                gap = k[0] / 1000.0
                for _ in range(BLOCK):
                    t0 = time.perf_counter()
                    libsumo.simulationStep()
                    steps[k].append(time.perf_counter() - t0)
                    if k[1] == "sleep":
                        time.sleep(gap)
                    else:
                        t1 = time.perf_counter()
                        while time.perf_counter() - t1 < gap:
                            pass
        actors = libsumo.vehicle.getIDCount() + libsumo.person.getIDCount()
    finally:
        libsumo.close()
    base = float(np.median(steps[(0.0, "busy")])) * 1000.0
    print(f"== {a.preset}, traffic {a.traffic}, seed {a.seed}: SUMO alone (libsumo), {actors} actors at the end; "
          f"blocks of {BLOCK} steps, {a.rounds} rounds, gaps alternating")
    for k in kinds:
        v = np.array(steps[k]) * 1000.0
        print(f"   gap {k[0]:5.1f} ms ({k[1]:5s}): step median {np.median(v):5.2f} ms, mean {v.mean():5.2f} ms, "
              f"x{np.median(v) / base:4.2f} the steps with no gap")


if __name__ == "__main__":
    main()
