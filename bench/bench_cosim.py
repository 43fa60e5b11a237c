"""Co-simulation benchmark and soak run.

    python bench/bench_cosim.py                      # RTF vs SUMO alone, frame times (120 s each)
    python bench/bench_cosim.py --cpus 1 --mode serial   # the one-core figure
    python bench/bench_cosim.py --soak-minutes 30    # the 30-minute dense drive across chunks

Real-time factors are taken side by side in one run, on the same network, demand and seed:

* SUMO alone: libsumo stepping the scenario, nothing else, in a process of its own; it steps
  in blocks of 50 steps, each just before the co-simulation's same 50 steps (the two
  alternate, so both meet the machine in the same state);
* the full co-simulation: SUMO + PyBullet (ego car, mirrored actors, streamed tiles), headless,
  with SUMO in the same process ("serial") and in its worker process stepping while the
  physics runs ("pipelined", the default on two or more CPUs). Each run builds the window it
  drives into from scratch (``<world>/windows`` is emptied first; ``--keep-windows`` reuses
  an earlier run's), as a drive into a new place would: a window build (netconvert, meshing,
  demand) takes several CPU seconds, which on one core come out of the loop's time;
* frame times twice: those of the run above, between SUMO alone's blocks, and those of a
  second run alone on the machine (the co-simulation's frames ran slower throughout between
  the blocks, not only just after a switch);
* with the pipelined loop on two or more CPUs, a second SUMO alone steps the same blocks on one
  CPU while a pure-Python busy loop runs on another: how much slower SUMO's step gets when the
  second core is busy, as it is in the pipelined loop (the physics runs while SUMO steps), and
  so the ratio that loop could reach at most were the core busy for the whole step.

The goals: co-sim >= 0.7 x SUMO-alone speed with ~400 actors, >= 20x real time; frame time
p99.9 <= 2 x median and no frame over 50 ms caused by tile loading. The soak reports memory
(RSS) every simulated minute, collisions, teleports, windows built and network swaps.
Nothing is asserted: figures are printed.
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import psutil  # noqa: E402

from cosim.config import SimConfig  # noqa: E402
from cosim.demand import generate_demand  # noqa: E402
from cosim.sim import Simulation  # noqa: E402
from netgen.build import build_world  # noqa: E402
from netgen.config import WorldConfig  # noqa: E402


def sumo_alone_cmd(net, routes, seed, lane_change_s=None) -> list:
    """SUMO's command line for the yardstick, SUMO alone (also bench_sumo_gap.py's): the
    co-simulation's own options (``SumoTraffic.setup``) that change what SUMO computes."""
    from cosim.config import LANE_CHANGE_S
    from cosim.traffic import lane_change_args
    from netgen.sumo_net import sumo_binary

    return [sumo_binary("sumo"), "-n", str(net), "-r", ",".join(map(str, routes)), "--step-length", "0.1",
            "--seed", str(seed), "--no-step-log", "--no-warnings", "--collision.action", "warn",
            "--collision.mingap-factor", "0", "--time-to-teleport", "120", "--ignore-route-errors"] + \
        lane_change_args(LANE_CHANGE_S if lane_change_s is None else lane_change_s)


def _alone_main(conn, net, routes, seed, cpu=None, lane_change_s=None):
    """SUMO alone in a process of its own, stepping blocks of steps on request (on CPU
    ``cpu`` only, if given)."""
    import libsumo

    if cpu is not None:
        os.sched_setaffinity(0, {cpu})
    libsumo.start(sumo_alone_cmd(net, routes, seed, lane_change_s))
    try:
        while (n := conn.recv()) is not None:
            steps = np.empty(n)
            t0 = time.perf_counter()
            for i in range(n):
                s0 = time.perf_counter()
                libsumo.simulationStep()
                steps[i] = time.perf_counter() - s0
            wall = time.perf_counter() - t0
            conn.send((wall, steps, libsumo.vehicle.getIDCount() + libsumo.person.getIDCount()))
    finally:
        libsumo.close()


class SumoAlone:
    """SUMO alone (libsumo stepping the scenario, nothing else), in its own process, run in
    blocks that alternate with the co-simulation's: both meet the same machine, whose speed
    drifts by 20-30 % from minute to minute here (one run after the other did not compare)."""

    def __init__(self, net, routes, seed, busy_neighbour: bool = False, lane_change_s=None):
        import multiprocessing as mp

        ctx = mp.get_context("spawn")
        self.conn, child = ctx.Pipe()
        self.flag = self.spinner = None
        cpu = None
        if busy_neighbour:          # SUMO on one CPU, a busy loop on another during its blocks
            cpu, other = sorted(os.sched_getaffinity(0))[:2]
            self.flag = ctx.Value("i", 0, lock=False)
            self.wake = ctx.Event()
            self.spinner = ctx.Process(target=_spin, args=(self.flag, self.wake, other), daemon=True)
            self.spinner.start()
        self.proc = ctx.Process(target=_alone_main, args=(child, net, routes, seed, cpu, lane_change_s),
                                daemon=True)
        self.proc.start()
        self.wall, self.steps, self.actors = 0.0, [], []

    def run(self, n, measure=True):
        if self.flag is not None:
            self.flag.value = 1
            self.wake.set()
            time.sleep(0.002)       # (the loop spinning before SUMO's first step)
        self.conn.send(n)
        wall, steps, actors = self.conn.recv()
        if self.flag is not None:
            self.wake.clear()       # (before the flag: the loop then blocks, it does not poll)
            self.flag.value = 0
        if measure:
            self.wall += wall
            self.steps.append(steps * 1000.0)
            self.actors.append(actors)

    def close(self):
        self.conn.send(None)
        self.proc.join(30)
        if self.spinner is not None:
            self.flag.value = -1
            self.wake.set()
            self.spinner.join(5)


def _spin(flag, wake, cpu):
    """A pure-Python busy loop on CPU ``cpu`` while ``flag`` is 1, gone at -1: the load the
    pipelined loop's main process puts on the second core while SUMO steps. Between SUMO
    alone's blocks it sleeps on ``wake`` (an event: no polling, which would wake it thousands
    of times a second and take the CPU from the co-simulation's processes in their blocks)."""
    os.sched_setaffinity(0, {cpu})
    while True:
        wake.wait()
        f = flag.value
        if f < 0:
            return
        while flag.value == 1:
            x = 0
            for _ in range(20000):
                x += 1


class Yardsticks:
    """SUMO alone with the other core idle (the yardstick) and, on two or more CPUs, a second
    SUMO alone on one CPU beside a busy loop on another: both step each block of the
    co-simulation's steps just before it."""

    def __init__(self, net, routes, seed, busy_neighbour: bool, lane_change_s=None):
        self.idle = SumoAlone(net, routes, seed, lane_change_s=lane_change_s)
        self.busy = SumoAlone(net, routes, seed, busy_neighbour=True, lane_change_s=lane_change_s) \
            if busy_neighbour else None

    def run(self, n, measure=True):
        self.idle.run(n, measure)
        if self.busy is not None:
            self.busy.run(n, measure)

    def close(self):
        self.idle.close()
        if self.busy is not None:
            self.busy.close()


def cosim(world, traffic, seconds, seed, warm, speed, parallel, alone: "Yardsticks | None", block=50,
          lane_change_s=None):
    cfg = SimConfig(world_dir=str(world), traffic=traffic, seed=seed, speed_mps=speed, duration_s=warm + seconds,
                    parallel_sumo=parallel)
    if lane_change_s is not None:
        cfg.lane_change_s = lane_change_s
    sim = Simulation(cfg).setup()
    try:
        if alone is not None:
            alone.run(int(warm / 0.1), measure=False)
        for _ in range(int(warm / 0.1)):
            sim.step()
        frames = []
        loads = []
        tiles = []
        building = []
        wall = 0.0
        n = int(seconds / 0.1)
        for b0 in range(0, n, block):
            k = min(block, n - b0)
            if alone is not None:
                alone.run(k)           # the same steps of SUMO alone, just before
            t0 = time.perf_counter()
            for _ in range(k):
                n0 = sim.physics.loads + sim.physics.unloads
                f0 = time.perf_counter()
                sim.step()
                frames.append((time.perf_counter() - f0) * 1000.0)
                st = sim.streamer               # (a window being built in the background meanwhile)
                building.append(st is not None and getattr(st, "proc", None) is not None)
                loads.append(sim.physics.loads + sim.physics.unloads > n0)
                tiles.append(sim.last_tiles_ms)
            wall += time.perf_counter() - t0
        s = sim.finish()
    finally:
        sim.teardown()
    f = np.array(frames)
    ld = np.array(loads)
    cosim.building = np.array(building, dtype=bool)
    return seconds / wall, s, f, ld, np.array(tiles)


def soak(world, minutes, seed, speed, telemetry=None, lane_change_s=None):
    cfg = SimConfig(world_dir=str(world), traffic="dense", seed=seed, speed_mps=speed, duration_s=minutes * 60.0,
                    telemetry=telemetry)
    if lane_change_s is not None:
        cfg.lane_change_s = lane_change_s
    sim = Simulation(cfg).setup()
    proc = psutil.Process()
    try:
        t0 = time.perf_counter()
        frames, swap_frames, build_frames, tiles = [], [], [], []
        swap_tail = 0           # a swap spans three frames (see Simulation.swap_traffic)
        for minute in range(int(minutes)):
            for _ in range(600):
                n_swaps, n_windows = sim.streamer.swaps, len(sim.streamer.build_s)
                f0 = time.perf_counter()
                sim.step()
                frames.append((time.perf_counter() - f0) * 1000.0)
                tiles.append(sim.last_tiles_ms)
                if sim.streamer.swaps != n_swaps:
                    swap_frames.append([round(frames[-1], 1)])
                    swap_tail = 2
                elif swap_tail:
                    swap_frames[-1].append(round(frames[-1], 1))
                    swap_tail -= 1
                elif len(sim.streamer.build_s) != n_windows:
                    build_frames.append(round(frames[-1], 1))
            rss = proc.memory_info().rss / 1e6
            worker = getattr(sim.traffic, "_proc", None)
            wrss = psutil.Process(worker.pid).memory_info().rss / 1e6 if worker is not None else 0.0
            st = sim.vehicle.state()
            print(f"  minute {minute + 1:3d}: rss {rss:7.1f} MB (SUMO worker {wrss:6.1f} MB)  chunk {sim.world.frame.chunk_of(st.x, st.y)}  "
                  f"{sim.summary.distance_m / 1000:5.2f} km  tiles loaded {sim.physics.loads} unloaded {sim.physics.unloads}  "
                  f"windows {sim.streamer.swaps}  heightfield shapes {sim.physics.hf_shapes_created}  "
                  f"mesh shapes {len(sim.physics._shape_pool)}  mirror bodies {sim.mirror.created}  "
                  f"ego collisions {sim.summary.ego_collisions}  wall {time.perf_counter() - t0:6.0f} s", flush=True)
        s = sim.finish()
        print("  summary:", s.line())
        print("  swaps (ms):", sim.streamer.swap_ms, " window builds (s):", sim.streamer.build_s,
              " waited for late builds (s):", sim.streamer.waited_s,
              " errors:", sim.streamer.errors)
        print("  swap phases (ms):", sim.streamer.swap_phases_ms)
        f = np.array(frames)
        med = float(np.median(f))
        print(f"  frames: median {med:.1f} ms, p99 {np.percentile(f, 99):.1f}, p99.9 {np.percentile(f, 99.9):.1f} "
              f"({np.percentile(f, 99.9) / med:.2f} x median), max {f.max():.1f}; over 50 ms: {int((f > 50).sum())} "
              f"of {len(f)}; swap frames (the frame it starts in and the two after) {swap_frames} ms; frames that took in a built window {build_frames} ms; "
              f"SUMO restarts {sim.summary.sumo_restarts}")
        tl = np.array(tiles)
        print(f"  tile loading and unloading per frame: max {tl.max():.1f} ms, p99.9 {np.percentile(tl, 99.9):.1f} ms; "
              f"frames over 50 ms: {int((f > 50).sum())}, of which with over 25 ms of loading: {int(((f > 50) & (tl > 25)).sum())}")
        print("  collisions:", sim.collision_log[:10])
    finally:
        sim.teardown()


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--preset", default="helsinki")
    ap.add_argument("--traffic", default="dense")
    ap.add_argument("--seconds", type=float, default=120.0)
    ap.add_argument("--warm", type=float, default=60.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--speed", type=float, default=12.0)
    ap.add_argument("--soak-minutes", type=float, default=0.0)
    ap.add_argument("--telemetry", help="the soak's telemetry (JSONL) goes here")
    ap.add_argument("--mode", choices=["both", "serial", "pipelined"], default="both",
                    help="SUMO in-process (serial) and/or in a worker process stepping beside the physics")
    ap.add_argument("--out", default=str(REPO / "bench" / "results" / "worlds"))
    ap.add_argument("--keep-windows", action="store_true",
                    help="reuse windows built by an earlier run (by default each run builds its own)")
    ap.add_argument("--cpus", type=int, default=0,
                    help="pin this run (and SUMO's worker) to this many CPUs, e.g. 1 for the one-core figure")
    ap.add_argument("--lane-change", type=float, help="SUMO's lane change duration, s, in both the co-simulation "
                    "and SUMO alone (default: SimConfig's)")
    a = ap.parse_args(argv)
    if a.cpus:
        os.sched_setaffinity(0, set(sorted(os.sched_getaffinity(0))[:a.cpus]))
        print(f"pinned to CPU(s) {sorted(os.sched_getaffinity(0))}")
    out = Path(a.out) / a.preset
    w = build_world(WorldConfig(preset=a.preset, chunks=1, out=str(out)))
    world = Path(w["out"])
    if a.soak_minutes:
        print(f"== soak: {a.soak_minutes:.0f} min, {a.preset}, dense traffic, {a.speed} m/s")
        soak(world, a.soak_minutes, a.seed, a.speed, a.telemetry, a.lane_change)
        return
    d = generate_demand(world / w["net_file"], world / "traffic", density=a.traffic, seed=a.seed,
                        duration=a.warm + a.seconds + 60.0)
    print(f"== {a.preset}, traffic {a.traffic}, seed {a.seed}: {a.warm:.0f} s warm-up, {a.seconds:.0f} s measured")
    print("   (SUMO alone steps in its own process, in blocks of 50 steps that alternate with the co-simulation's)")
    modes = [("serial", False), ("pipelined", True)] if a.mode == "both" else [(a.mode, a.mode == "pipelined")]
    for name, parallel in modes:
        if not a.keep_windows:      # each run builds the window it drives into, as a new place would
            shutil.rmtree(world / "windows", ignore_errors=True)
        sticks = Yardsticks(world / w["net_file"], d.route_files, a.seed,
                            busy_neighbour=parallel and len(os.sched_getaffinity(0)) >= 2,
                            lane_change_s=a.lane_change)
        try:
            rtf_co, s, f, ld, tl = cosim(world, a.traffic, a.seconds, a.seed, a.warm, a.speed, parallel, sticks,
                                         lane_change_s=a.lane_change)
        finally:
            sticks.close()
        alone = sticks.idle
        rtf_sumo = a.seconds / alone.wall
        steps = np.concatenate(alone.steps)
        print(f"   SUMO alone      : x{rtf_sumo:6.1f} real time, {statistics.mean(alone.actors):.0f} actors in the simulation; "
              f"step ms: median {np.median(steps):.2f}, p99.9 {np.percentile(steps, 99.9):.2f} "
              f"({np.percentile(steps, 99.9) / np.median(steps):.2f} x median), max {steps.max():.2f}")
        if sticks.busy is not None:
            busy = np.concatenate(sticks.busy.steps)
            slow = np.median(busy) / np.median(steps)
            print(f"   SUMO alone beside a busy core (a Python loop on the other CPU): x{a.seconds / sticks.busy.wall:6.1f} "
                  f"real time; step ms: median {np.median(busy):.2f}, {slow:.2f} x the idle core's. The pipelined "
                  f"loop's physics keeps that core busy while SUMO steps: were it busy for the whole step, the "
                  f"ratio could reach at most {1 / slow:.2f}")
        print(f"   co-sim {name:9s}: x{rtf_co:6.1f} real time, {s.max_vehicles} vehicles + {s.max_persons} persons, "
              f"{s.max_mirrored} mirrored at most  (load average {os.getloadavg()[0]:.2f})")
        print(f"      ratio co-sim / SUMO alone: {rtf_co / rtf_sumo:.2f}  (goal >= 0.7; and >= 20x real time)")
        print(f"      frame ms: median {np.median(f):.2f}, p99 {np.percentile(f, 99):.2f}, p99.9 "
              f"{np.percentile(f, 99.9):.2f} ({np.percentile(f, 99.9) / np.median(f):.2f} x median; goal <= 2), "
              f"max {f.max():.2f}")
        # the frames of a run alone on the machine: between SUMO alone's blocks (which make the
        # ratio fair) the co-simulation's frames run slower throughout, not only after a switch
        _, _, f1, ld1, _ = cosim(world, a.traffic, a.seconds, a.seed, a.warm, a.speed, parallel, None,
                                 lane_change_s=a.lane_change)
        print(f"      frame ms, the co-simulation alone on the machine (a second run, no SUMO-alone blocks): "
              f"median {np.median(f1):.2f}, p99 {np.percentile(f1, 99):.2f}, p99.9 {np.percentile(f1, 99.9):.2f} "
              f"({np.percentile(f1, 99.9) / np.median(f1):.2f} x median; goal <= 2), max {f1.max():.2f}; "
              f"frames with tile loads {ld1.sum()}, their max {f1[ld1].max() if ld1.any() else 0:.2f} ms")
        b1 = cosim.building
        if b1.any() and (~b1).any():
            print(f"        of which {b1.sum()} while the next window was being built in the background: median "
                  f"{np.median(f1[b1]):.2f}, p99 {np.percentile(f1[b1], 99):.2f}; the other {(~b1).sum()}: p99 "
                  f"{np.percentile(f1[~b1], 99):.2f}, p99.9 {np.percentile(f1[~b1], 99.9):.2f} "
                  f"({np.percentile(f1[~b1], 99.9) / np.median(f1[~b1]):.2f} x median)")
        if ld.any():
            worst = int(np.argmax(np.where(ld, f, -1.0)))
            print(f"      frames with tile loads: {ld.sum()}, their max {f[ld].max():.2f} ms (goal <= 50), of which "
                  f"loading and unloading {tl[worst]:.2f} ms; without loads p99.9 {np.percentile(f[~ld], 99.9):.2f} ms")
            print(f"      tile loading and unloading per frame: max {tl.max():.2f} ms, p99 of frames with loads "
                  f"{np.percentile(tl[ld], 99):.2f} ms; frames with loads minus their loading: max "
                  f"{(f[ld] - tl[ld]).max():.2f} ms")
        print(f"      {s.line()}")

if __name__ == "__main__":
    main()
