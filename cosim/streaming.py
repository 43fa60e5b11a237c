"""Keeping the world ahead of the car: windows built in the background, SUMO swapped over.

A *window* is a complete build (``netgen.build``) of the chunks within ``rings`` of one chunk,
in the world's one frame. The run starts in the window around the reference point. When the
car leaves that window's centre chunk, the window centred on the chunk its route reaches
:data:`LOOKAHEAD_S` ahead (one next to the car's, or the car's own) is built in a worker
process (netconvert, layers and traffic demand: Python threads would not help, and a spawned
process shares no libsumo or PyBullet state), into ``<world>/windows/<i>_<j>``.
When it is ready:

* with SUMO in its worker process, SUMO is first started on the new network and demand in a
  second worker (``TrafficProcess.prepare_network``), while the car drives on; the swap
  waits for nothing once it has loaded (in-process SUMO restarts during the swap's frame);
* the world view takes in its chunks (``World.add_window``); the loaded tiles of replaced
  chunks are replaced from the new build over the next frames, within the loading budget
  (``PhysicsWorld.refresh``), so roads cut at the old window's edge become whole;
* SUMO switches to the new network (``swap_network``): the actors near the ego keep their
  positions and speeds and their mirrored bodies (re-keyed to the new SUMO ids), so none
  visibly vanishes, and the new demand's own actors there make room for them;
* the ego's route is planned again on the new network.

A window whose swap comes when the car is no further inside it than inside the current one
waits for the car to drive further in; it is given up (and the window the car needs built
next) where the car is back in the current centre chunk, outside the new window, or near the
current window's edge.

A run is repeatable (``SimConfig.repeatable``, the default): the swap comes
:data:`SWAP_DELAY_S` of simulated time after the build started, or once the car is within
:data:`SWAP_EDGE_M` of the current window's edge if that is sooner, however long the build
took in wall-clock time. A window ready earlier waits; one not ready by then is waited for (a long
frame, logged). Without it the swap comes as soon as the build and SUMO are ready, so that
the same seed can give another run on a busier or slower machine.

With one ring a window reaches at least one chunk beyond the car's chunk, so the car can
drive a whole chunk while the next window is built.
"""
from __future__ import annotations

import logging
import os
import subprocess
import time
from pathlib import Path

from .workers import start_worker, worker_connection

log = logging.getLogger("cosim.streaming")
BUILD_NICENESS = 5     # window builds run at this niceness (netconvert inherits it)
#: in a repeatable run, the swap comes this many simulated seconds after its window's build
#: started, or earlier once the car is within SWAP_EDGE_M of the current window's edge (a
#: window reaches a chunk, 1 km, beyond its centre chunk: at 30 m/s that is 20 s away)
SWAP_DELAY_S = 60.0
SWAP_EDGE_M = 400.0
#: the next window is centred on the chunk of the route this many seconds ahead of the car at
#: its set speed (within LOOKAHEAD_M): a car that crosses a chunk's corner, or starts in a
#: chunk it is leaving, gets the window it drives into, not the one it leaves
LOOKAHEAD_S = 20.0
LOOKAHEAD_M = (100.0, 600.0)


def _build_window(cfg_dict: dict, window: tuple, out: str, traffic, seed: int, duration: float, conn):
    """Worker process: build a window and its demand; send (out, route files) or an error."""
    try:
        from cosim.demand import generate_demand, place_density, world_traffic_scale
        from netgen.build import PLANES_FILE, build_world
        from netgen.config import WorldConfig

        cfg = WorldConfig.from_dict(cfg_dict)
        cfg.window = tuple(window)
        cfg.out = out
        # (the road heights of the world's register: <world>/windows/<i>_<j> -> <world>)
        w = build_world(cfg, heights=Path(out).parent.parent / PLANES_FILE)
        net = Path(w["out"]) / w["net_file"]
        d = generate_demand(net, Path(w["out"]) / "traffic",
                            density=place_density(traffic, world_traffic_scale(w)),
                            seed=seed, duration=duration)
        from .world import write_bridge_lanes
        write_bridge_lanes(net)        # (read here, not in the loop's frame at the swap)
        result = ("ok", w["out"], [str(p) for p in d.route_files])
    except BaseException as e:  # report anything, the loop decides
        result = ("error", f"{type(e).__name__}: {e}", [])
    try:
        conn.send(result)
    except OSError:
        pass        # the loop has ended without this window (a script that left without teardown())
    finally:
        conn.close()


class WorldStreamer:
    """Component (setup / step / teardown) run by the simulation loop."""

    def __init__(self, sim):
        self.sim = sim
        meta = sim.world.meta
        self.base_cfg = meta.get("config")
        self.center = tuple(meta.get("window", (0, 0)))
        self.built = {self.center}
        self.proc = None
        self.conn = None
        self.job_window = None
        self.job_started = 0.0
        self.repeatable = bool(sim.cfg.repeatable)
        self.due_t = None                 # sim time of the swap in a repeatable run
        self.waited_s: list = []          # wall time waited for a late build at the swap's due time
        self.swaps = 0
        self.swap_ms: list = []
        self.swap_phases_ms: list = []    # per swap: {phase: ms}
        self.ready = None                 # (window, out, routes) built, SUMO loading for it
        self.plan_asked = False           # the car's route asked of the SUMO started ahead
        self._ending: list = []           # build processes that answered, exiting
        self.build_s: list = []
        self.dropped: list = []           # windows built but not swapped to: the car had left them
        self._dropped_at = None           # (the last one, the car's chunk then)
        self.errors: list = []
        self.enabled = self.base_cfg is not None
        if not self.enabled:
            log.info("world.json has no build config: the world will not grow beyond %s", sim.world.path)

    def setup(self):
        return self

    @property
    def building(self):
        return self.job_window

    def step(self, x: float, y: float) -> None:
        if not self.enabled:
            return
        if self._ending:
            self._ending = [p for p in self._ending if p.poll() is None]
        due = self._due(x, y)
        if self.ready is not None:
            if due is False:
                return                          # (SUMO goes on loading in its own process)
            self._settle_ready(x, y, due)
            return
        ij = self.sim.world.frame.chunk_of(x, y)
        if self.proc is None and ij != self.center:
            here, ij = ij, self._target(x, y, ij)
            # (not the window just given up again while the car is in the chunk it was given up in)
            if ij != self.center and ij not in self.built and self._dropped_at != (ij, here):
                self._start(ij)
                due = self._due(x, y)
        if self.proc is not None and (due is True or self.conn.poll() or self.proc.poll() is not None):
            t_wait = time.perf_counter()
            try:
                status, out, routes = self.conn.recv()      # (at the due time: waits for the build)
            except (EOFError, OSError):
                status, out, routes = "error", f"the build process ended with exit code {self.proc.poll()}", []
            if due is True:
                self._note_wait(t_wait, "the window build")
            self._ending.append(self.proc)     # it exits by itself: reaped later, not waited for here
            self.proc = None
            self.conn.close()
            self.conn = None
            self.build_s.append(round(time.perf_counter() - self.job_started, 2))
            window, self.job_window = self.job_window, None
            if status != "ok":
                self.errors.append(out)
                self.built.add(window)          # do not retry in a loop; reported in the summary
                self.due_t = None
                log.warning("could not build the window around chunk %s: %s", window, out)
                return
            net = self._net_of(out)
            if hasattr(self.sim.traffic, "prepare_network"):
                try:
                    self.sim.traffic.prepare_network(net, routes)
                except Exception as e:          # the swap restarts SUMO itself then
                    log.info("could not start SUMO ahead on the next network: %s", e)
            self.ready = (window, out, routes)
            if due is not False:                # (due now: in this frame, whenever the build ended)
                self._settle_ready(x, y, due)

    def _target(self, x: float, y: float, ij: tuple) -> tuple:
        """The chunk to centre the next window on, for a car in chunk ``ij``: the chunk of its
        route :data:`LOOKAHEAD_S` ahead, no further than the chunks around ``ij`` (the car's own
        chunk stays in the window). (Centred on the car's chunk, a car that started in a corner
        of the world's chunk (0, 1), driving away from it down the Kouvola motorway, was swapped
        60 s later into the window around (0, 1), 1.5 km behind it, whose network did not reach
        its goal.)"""
        sim = self.sim
        if getattr(sim, "goal_beyond", False) and sim.goal_xy is not None:
            # (the route ends where this window's network does, short of the goal: towards it)
            gi, gj = sim.world.frame.chunk_of(*sim.goal_xy)
            return (ij[0] + (gi > ij[0]) - (gi < ij[0]), ij[1] + (gj > ij[1]) - (gj < ij[1]))
        path = getattr(sim, "path", None)
        if path is None or not len(path.s):
            return ij
        lo, hi = LOOKAHEAD_M
        ahead = min(max(float(sim.cfg.speed_mps) * LOOKAHEAD_S, lo), hi)
        k = min(max(int(getattr(sim, "_path_idx", 0)), 0), len(path.s) - 1)
        px, py = path.point_at(float(path.s[k]) + ahead)
        ti, tj = sim.world.frame.chunk_of(float(px), float(py))
        return (min(max(ti, ij[0] - 1), ij[0] + 1), min(max(tj, ij[1] - 1), ij[1] + 1))

    def _verdict(self, window: tuple, x: float, y: float) -> str:
        """What to do with the built window around chunk ``window`` now that its swap is due,
        for the car at (x, y): "swap" where it holds the car further from its edge than the
        current window does; else "drop" where the car is back in the current window's centre
        chunk, outside the new window's chunks or near the current window's edge (then the
        window it needs is built next); else "wait" (it drives on into the new window)."""
        here = self._edge_distance(x, y)
        if self._edge_distance(x, y, window) > here:
            return "swap"
        rings = int((self.base_cfg or {}).get("chunks", 1))
        ci, cj = self.sim.world.frame.chunk_of(x, y)
        if (ci, cj) == self.center or max(abs(ci - window[0]), abs(cj - window[1])) > rings \
                or here <= SWAP_EDGE_M:
            return "drop"
        return "wait"

    def _settle_ready(self, x: float, y: float, due) -> None:
        """The ready window, its swap due (or, not repeatable, whenever): swapped to, given up
        or kept waiting, as :meth:`_verdict` says."""
        verdict = self._verdict(self.ready[0], x, y)
        if verdict == "drop":
            self._drop_ready(x, y)
        elif verdict == "swap":
            self._swap_when_ready(block=due is True)

    def _drop_ready(self, x: float, y: float) -> None:
        """Give up a built window that the car has left behind (it stays on disk: a later build
        of it reuses it), and SUMO started ahead on its network."""
        window = self.ready[0]
        self.ready = None
        self.plan_asked = False
        self.due_t = None
        if hasattr(self.sim.traffic, "discard_prepared"):
            self.sim.traffic.discard_prepared()
        self.dropped.append(window)
        self._dropped_at = (window, self.sim.world.frame.chunk_of(x, y))
        log.info("not swapping to the window around chunk %s: the car, now in chunk %s, has left it behind",
                 window, self._dropped_at[1])

    def _due(self, x: float, y: float):
        """In a repeatable run, whether the swap's time has come (True / False; once come, it
        stays so); None when the run is not repeatable or nothing is being built."""
        if not self.repeatable or self.due_t is None:
            return None
        if self.sim.t < self.due_t - 1e-9 and self._edge_distance(x, y) <= SWAP_EDGE_M:
            self.due_t = self.sim.t
        return self.sim.t >= self.due_t - 1e-9

    def _note_wait(self, t0: float, what: str) -> None:
        """Record a wait (since ``t0``, perf_counter) of a repeatable run's swap for ``what``."""
        waited = time.perf_counter() - t0
        if waited > 0.05:
            self.waited_s.append(round(waited, 2))
            log.info("waited %.1f s for %s at the swap's time (a repeatable run)", waited, what)

    def _edge_distance(self, x: float, y: float, window: tuple | None = None) -> float:
        """How far (m) (x, y) is inside the current window's square of chunks (or that of the
        window around chunk ``window``)."""
        rings = int((self.base_cfg or {}).get("chunks", 1))
        frame, (ci, cj) = self.sim.world.frame, (self.center if window is None else window)
        x0, y0, _, _ = frame.chunk_bounds(ci - rings, cj - rings)
        _, _, x1, y1 = frame.chunk_bounds(ci + rings, cj + rings)
        return min(x - x0, x1 - x, y - y0, y1 - y)

    def _swap_when_ready(self, block: bool = False):
        """With SUMO started ahead on the new network: once it has loaded, it plans the car's
        route from where the car is (in the background too; in a junction, once past it), and
        once that is answered the swap takes both. (A SUMO restarted after a crash has lost
        what was prepared: then swap at once, the slow way.) With ``block`` (a repeatable
        run's due time) each of these waits for SUMO instead of trying again next frame, so
        the route is asked in the first frame the car allows and the swap is the frame after."""
        sim, traffic = self.sim, self.sim.traffic
        if getattr(traffic, "preparing", None) is not None:
            t_wait = time.perf_counter()
            if not traffic.prepared_ready(block=block):
                return
            if block:
                self._note_wait(t_wait, "SUMO on the next network")
            if not self.plan_asked:
                args = sim.replan_args()
                if args is None:
                    return
                traffic.prepare_call("plan", "replan_from", *args[0], **args[1])
                self.plan_asked = True
                return
        plan, err = traffic.prepared_result("plan") if self.plan_asked else (None, None)
        if err is not None:
            log.info("planning the route on the next network failed (%s): planned again after the swap", err)
        window, out, routes = self.ready
        self.ready = None
        self.plan_asked = False
        self.due_t = None
        self._swap(window, out, routes, plan)

    @staticmethod
    def _net_of(out) -> Path:
        from .world import World

        return World(out).net_file

    def _start(self, window):
        cfg = self.sim.cfg
        out = str(self.sim.world.path / "windows" / f"{window[0]}_{window[1]}")
        self.proc, self.conn = start_worker("cosim.streaming")
        try:        # a background job: the loop's own processes come first
            os.setpriority(os.PRIO_PROCESS, self.proc.pid, BUILD_NICENESS)
        except (AttributeError, OSError):
            pass
        self.conn.send((self.base_cfg, window, out, cfg.traffic, cfg.seed, max(cfg.duration_s, 60.0) + 60.0))
        self.job_window = window
        self.job_started = time.perf_counter()
        self.due_t = self.sim.t + SWAP_DELAY_S
        log.info("building the window around chunk %s in the background", window)

    def _swap(self, window, out, routes, plan=None):
        sim = self.sim
        t0 = time.perf_counter()
        phases = {}

        def lap(name):
            nonlocal t0
            t = time.perf_counter()
            phases[name] = round((t - t0) * 1000.0, 1)
            t0 = t

        changed = sim.world.add_window(out)
        sim.physics.refresh(changed)
        lap("world")
        phases.update(sim.swap_traffic(sim.world.net_file, routes, plan))
        self.center = window
        self.built.add(window)
        self.swaps += 1
        self.swap_phases_ms.append(phases)
        self.swap_ms.append(round(sum(phases.values()), 1))
        log.info("swapped to the window around chunk %s (%d chunks new, %.0f ms in this frame: %s)",
                 window, len(changed), self.swap_ms[-1], phases)

    def teardown(self):
        for p in self._ending:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
        self._ending = []
        if self.proc is not None:
            self.proc.terminate()           # its output is written atomically: nothing half-built stays valid
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
            self.proc = None
        if self.conn is not None:
            self.conn.close()
            self.conn = None


if __name__ == "__main__":
    _conn = worker_connection()
    try:
        _job = _conn.recv()
    except (EOFError, OSError):
        raise SystemExit(0)         # the loop ended before it asked for a window
    _build_window(*_job, _conn)
