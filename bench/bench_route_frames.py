"""Frame times around route extensions: the drive's worst frames, and the frames that extend the
route, for this checkout and, side by side, another one (an earlier commit's worktree).

    .venv/bin/python bench/bench_route_frames.py [--presets helsinki,kouvola] [--seeds 0,3] [--duration 300]
    .venv/bin/python bench/bench_route_frames.py --compare /tmp/old-worktree      # A/B, alternating

Each drive is ``cosim run``'s (random routes extended as the car nears the path's end, SUMO
in its worker process), headless, in a process of its own with the given checkout first on
``sys.path``; the worlds are the presets' default ones (built once, by this checkout, into
--workdir: both checkouts must read the same world format). Printed per drive: distance,
real-time factor, frame median / p99 / p99.9 / max, p99.9 as a multiple of the median, and the
frames in which the route changed (an extension, a re-plan, a network swap): how many, their
median and max. Runs alternate between the checkouts, so both meet the machine in the
same state. Nothing is asserted.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

DRIVE = r"""
import json, sys, time
sys.path.insert(0, {repo!r})
import numpy as np
from cosim.config import SimConfig
from cosim.sim import Simulation
cfg = SimConfig(world_dir={world!r}, traffic={traffic!r}, seed={seed}, duration_s={duration})
sim = Simulation(cfg).setup()
frames, ext = [], []
route = sim.route
for _ in range(int({duration} / cfg.step_length_s)):
    t0 = time.perf_counter()
    sim.step()
    frames.append((time.perf_counter() - t0) * 1000.0)
    if sim.route is not route:
        ext.append(len(frames) - 1)
        route = sim.route
s = sim.finish()
sim.teardown()
print(json.dumps(dict(km=s.distance_m / 1000.0, rtf=s.real_time_factor, frames=frames, ext=ext)))
"""


def drive(repo: Path, world: Path, seed: int, duration: float, traffic: str) -> dict:
    code = DRIVE.format(repo=str(repo), world=str(world), seed=seed, duration=duration, traffic=traffic)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(repo))
    if out.returncode != 0:
        raise SystemExit(f"drive failed ({repo}, seed {seed}): {out.stderr.strip().splitlines()[-1:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def stats(r: dict) -> str:
    import numpy as np

    f = np.array(r["frames"])
    med = float(np.median(f))
    e = f[r["ext"]] if r["ext"] else np.zeros(0)
    ext = f"{len(e)} route changes, median {np.median(e):.1f} ms, max {e.max():.1f} ms" if len(e) else "no route change"
    return (f"{r['km']:.2f} km, x{r['rtf']:.1f}; frames median {med:.2f}, p99 {np.percentile(f, 99):.2f}, "
            f"p99.9 {np.percentile(f, 99.9):.2f} ({np.percentile(f, 99.9) / med:.2f} x median), max {f.max():.1f} ms; "
            f"{ext}; frames over 20 ms: {int((f > 20).sum())}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--presets", default="helsinki,kouvola")
    ap.add_argument("--seeds", default="0,3")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--traffic", default="normal")
    ap.add_argument("--compare", metavar="DIR", help="another checkout, run alternating with this one")
    ap.add_argument("--workdir", default=str(Path(tempfile.gettempdir()) / "cosim-bench-route-frames"))
    a = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from netgen.build import build_world
    from netgen.config import WorldConfig

    work = Path(a.workdir)
    repos = [("this", REPO)] + ([("compare", Path(a.compare).resolve())] if a.compare else [])
    for preset in a.presets.split(","):
        world = work / preset
        build_world(WorldConfig(preset=preset, out=str(world), cache_dir=str(work / "cache")))
        for seed in (int(s) for s in a.seeds.split(",")):
            print(f"== {preset}, seed {seed}, {a.duration:.0f} s, traffic {a.traffic}")
            for name, repo in repos:
                print(f"   {name:8s}: {stats(drive(repo, world, seed, a.duration, a.traffic))}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
