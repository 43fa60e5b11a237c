"""SUMO in a worker process, stepped while the physics runs (the pipelined co-simulation).

libsumo holds Python's GIL for a whole ``simulationStep`` (a thread does not overlap it with
anything), and SUMO's step is the largest single cost of a frame. ``TrafficProcess`` runs a
:class:`cosim.traffic.SumoTraffic` in a spawned worker process and forwards calls to it over
a pipe, with one difference: :meth:`TrafficProcess.step` only *sends* the request and returns,
so SUMO computes its next step on the second core while the main process steps PyBullet, the
car and the sensors. The next call of anything waits for that step to finish first (the pipe
keeps the order), so the loop sees the same sequence of states as with an in-process SUMO;
the only change is that the ego pose SUMO steps with is the one sent before the physics of
the same frame (SUMO sees the car one step, 0.1 s, later than in the serial loop). The loop's
frame begins with :meth:`TrafficProcess.advance`: the next step goes out before the answer to
the last one is read, so the worker, which is the slower of the two, starts SUMO's next step
as soon as it has sent its answer (it waited for this process to wake up, unpickle the
answer and send the next step: about 0.2 ms of each 2 ms frame).

Everything else goes through generic proxies: ``traffic.sumo.vehicle.getLeader("ego", 80)``
is one round trip (about 30-60 us), ``traffic.actors_near(...)`` another. Answers that depend
only on the network (lane shapes, links, junction foes; see ``_STATIC``) are cached in the main
process until the network changes (``swap_network``). A few attributes the loop reads every
frame (``stats``, ``sim_time``, ``_generation``, ...) come back with every answer and are read
locally once the answers in flight are in (``stats_nowait`` does not wait: the loop's
telemetry reads it while SUMO steps).

SUMO errors come back as the same one-line ``SimulationError`` as in-process; a worker that
dies (libsumo can segfault on some inputs) is reported as a one-line error with its exit code.
Log records of the worker (teleports, collisions, warnings) are re-emitted in the main process.
"""
from __future__ import annotations

import collections
import contextlib
import dataclasses
import functools
import inspect
import logging
import math
import os
import pickle
import subprocess
import types
import weakref
from pathlib import Path

from netgen.errors import SimulationError

from .component import Component
from .workers import start_worker, worker_connection

log = logging.getLogger(__name__)

IDLE_WORK_S = 0.0005    # the worker's background work between two polls for a request

# attributes shipped with every answer, read locally
_STATE = ("stats", "sim_time", "running", "_generation", "_ego_in_sim", "_ego_off_network",
          "_ego_added")
# libsumo calls whose answers depend only on the network: cached per network generation
_STATIC = {
    # (not lane.getLinks: its tuples carry the links' current light states)
    ("sumo", "lane", n) for n in ("getShape", "getLength", "getInternalFoes", "getIDList",
                                  "getEdgeID", "getAllowed", "getDisallowed", "getWidth", "getLinkNumber",
                                  "getFoes", "getMaxSpeed")
} | {
    ("sumo", "edge", n) for n in ("getLaneNumber", "getIDList", "getStreetName", "getFromJunction",
                                  "getToJunction", "getParameter")
} | {("incoming_lanes",), ("via_lanes",), ("lane_links",), ("edge_ends",)} | {
    ("sumo", "junction", n) for n in ("getIncomingEdges", "getOutgoingEdges", "getPosition", "getShape",
                                      "getIDList")
} | {
    ("sumo", "trafficlight", n) for n in ("getControlledLinks", "getControlledLanes", "getIDList")
} | {("sumo", "simulation", "getNetBoundary")}


# reads prefetched only for a vehicle on a lane: the caller guards them (libsumo's getLeader
# segfaults for a vehicle that moveToXY left off the network), and a prefetch must not be less
# careful than the caller
_NEEDS_LANE = {("sumo", "vehicle", n) for n in ("getLeader", "getFollower", "getNeighbors", "getNextTLS",
                                                "getBestLanes", "getNextLinks", "getNextStops")}
PREFETCH_KEEP = 3        # steps a read is asked for again after the caller last made it
NOT_YET = object()       # TrafficProcess.answered: not in yet
ACTORS_MARGIN_M = 10.0   # the actors sent with a step cover the radius asked for + this


def _method_kinds() -> dict:
    """(name,) -> "call" for each method of SumoTraffic (what the worker answers to)."""
    from cosim.traffic import SumoTraffic

    return {(n,): "call" for n in dir(SumoTraffic)
            if not n.startswith("__") and inspect.isfunction(getattr(SumoTraffic, n, None))}


def _is_read(path) -> bool:
    """A call that only reads SUMO's state (safe to answer from the step's prefetch)."""
    name = path[-1]
    return name.startswith(("get", "is", "has")) or name in ("actors_context", "tls_states", "ego_state",
                                                               "ego_next_tls")


_WORKERS: "weakref.WeakSet[TrafficProcess]" = weakref.WeakSet()


def live_workers() -> list[int]:
    """Process ids of the SUMO worker processes this process runs now."""
    procs = []
    for t in list(_WORKERS):
        procs.append(t._proc)
        procs.append((t._next or {}).get("proc"))
        procs.extend(p for p, _ in t._retired)
    return [p.pid for p in procs if p is not None and p.poll() is None]


def available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


# --- the worker -----------------------------------------------------------------------------
class _LogForward(logging.Handler):
    def __init__(self):
        super().__init__()
        self.records: list = []

    def emit(self, record):
        try:
            self.records.append((record.name, record.levelno, record.getMessage()))
        except Exception:
            pass


def _plain_types() -> frozenset:
    from cosim.traffic import ActorsContext, ActorsSnapshot

    return frozenset({str, int, float, bool, type(None), bytes, ActorsSnapshot, ActorsContext})


_PLAIN: frozenset = frozenset()


def _portable(value, depth: int = 0):
    """``value`` if it pickles, else the same shape with SWIG objects (libsumo's TraCIStage,
    TraCICollision, ...) turned into namespaces of their public data attributes."""
    if type(value) in _PLAIN:       # (pickled once, by the send: not twice)
        return value
    try:
        pickle.dumps(value)
        return value
    except Exception:
        pass
    if depth > 4:
        return repr(value)
    if isinstance(value, (list, tuple)):
        return type(value)(_portable(v, depth + 1) for v in value)
    if isinstance(value, dict):
        return {k: _portable(v, depth + 1) for k, v in value.items()}
    ns = types.SimpleNamespace()
    for k in dir(value):
        if k.startswith("_"):
            continue
        try:
            v = getattr(value, k)
        except Exception:
            continue
        if callable(v):
            continue
        setattr(ns, k, _portable(v, depth + 1))
    return ns


def _portable_error(e: BaseException) -> BaseException:
    if isinstance(e, SimulationError):
        return e
    try:
        pickle.loads(pickle.dumps(e))
        return e
    except Exception:
        return SimulationError(f"{type(e).__name__}: {e}")


@functools.lru_cache(maxsize=None)
def _stats_fields() -> tuple:
    """The public fields of ``TrafficStats``, in order: what ``_state`` sends of the stats."""
    from cosim.traffic import TrafficStats

    return tuple(f.name for f in dataclasses.fields(TrafficStats) if not f.name.startswith("_"))


def _state(t) -> dict:
    """What comes back with every answer (:data:`_STATE`). The stats go as a tuple of their
    public fields (persons_held, swap_dropped too), a ``TrafficStats`` again on arrival (3.8 us
    in the caller): a copy of the dataclass and its pickle take 5 us, the tuple and its pickle
    2 us (timed alone; SUMO's worker, the loop's slower side, made and pickled the whole state in
    28 us a step)."""
    out = {}
    for k in _STATE:
        try:
            v = getattr(t, k)
        except Exception:
            continue
        if k == "stats":
            v = tuple([getattr(v, f) for f in _stats_fields()])
        out[k] = v
    return out


def _stats_from(values: tuple):
    from cosim.traffic import TrafficStats

    return TrafficStats(**dict(zip(_stats_fields(), values)))


def _on_lane(t, args) -> bool:
    try:
        return bool(args) and bool(t.sumo.vehicle.getLaneID(args[0]))
    except Exception:
        return False


def _attr(obj, path):
    """obj.a.b.c for path ("a", "b", "c")."""
    for name in path:
        obj = getattr(obj, name)
    return obj


def _kinds_under(root, path: tuple) -> dict:
    """path + (name,) -> "obj" for each module or class under `root` (libsumo's domains), and
    path + (name, fn) -> "call" for each of their functions: what a "get" request would
    answer for them, all at once."""
    out = {}
    for name in dir(root):
        obj = getattr(root, name, None) if not name.startswith("_") else None
        if not (inspect.ismodule(obj) or inspect.isclass(obj)):
            continue
        out[path + (name,)] = "obj"
        for fn in dir(obj):
            f = getattr(obj, fn, None) if not fn.startswith("_") else None
            if f is not None and callable(f) and not (inspect.ismodule(f) or inspect.isclass(f)):
                out[path + (name, fn)] = "call"
    return out


def _freeze_garbage_free() -> None:
    """Collect the cycles among the young objects, then freeze all objects (gc.freeze): later
    collections leave them alone. (The cycles among older ones wait for a full collection
    that, this way, is short.)"""
    import gc

    gc.collect(1)
    gc.freeze()


def _serve(conn):
    """Worker main loop: one SumoTraffic, requests answered in order."""
    import faulthandler

    from cosim.traffic import SumoTraffic

    global _PLAIN
    _PLAIN = _plain_types()
    faulthandler.enable()      # a crash inside libsumo names the call on stderr
    args, kwargs, log_level = conn.recv()

    fwd = _LogForward()
    root = logging.getLogger("cosim")
    root.addHandler(fwd)
    root.setLevel(log_level)
    root.propagate = False
    t = SumoTraffic(*args, **kwargs)
    t.work_when_idle = True
    # what lives as long as the worker (SUMO's tables, the network's answers, later the route
    # graph) is moved out of the collector's reach, so that a full collection does not walk it
    # in the middle of a frame (one took 11 ms at t = 100 s of the default run)
    _freeze_garbage_free()
    graph_work = True
    while True:
        try:
            # the route graph worked out while no request waits: in the time the main process
            # runs its frame, half a millisecond at a time (a route's extension is drawn once
            # a step is answered: SumoTraffic.work_after_step, below)
            while not conn.poll():
                if not t.background_work(IDLE_WORK_S):
                    if graph_work:          # the graph is complete: out of reach too
                        _freeze_garbage_free()
                    graph_work = False
                    break
                graph_work = True
            op, path, a, kw = conn.recv()
        except (EOFError, OSError, KeyboardInterrupt):
            break
        if op == "exit":
            break
        status, value = "ok", None
        try:
            if op == "step":
                if a:                          # the ego's pose, sent with the step
                    t.set_ego_pose(*a, **kw)
                t.step()
                status, value = "step", {}
                fns: dict = {}                 # (each function looked up once a step: 16 lanes' reads)
                for key in path:               # reads the caller will make: answered now
                    if key[0] in _NEEDS_LANE and not _on_lane(t, key[1]):
                        continue   # libsumo can crash on these for a vehicle off the network
                    try:
                        fn = fns.get(key[0])
                        if fn is None:
                            fn = fns[key[0]] = _attr(t, key[0])
                        value[key] = ("ok", _portable(fn(*key[1])))
                    except BaseException as e:  # noqa: BLE001
                        value[key] = ("err", _portable_error(e))
            elif op == "kinds":                # what the caller's proxies are (TrafficProcess.setup)
                value = _kinds_under(_attr(t, path), path)
            elif op == "batch":                # reads asked ahead (TrafficProcess.expect)
                value = []
                for key_path, key_args in path:
                    try:
                        value.append(("ok", _portable(_attr(t, key_path)(*key_args))))
                    except BaseException as e:  # noqa: BLE001
                        value.append(("err", _portable_error(e)))
            else:
                obj = _attr(t, path)
                if op == "call":
                    value = _portable(obj(*a, **kw))
                elif inspect.ismodule(obj) or inspect.isclass(obj):
                    status = "obj"
                elif callable(obj):
                    status = "call"
                else:
                    value = _portable(obj)
        except BaseException as e:  # noqa: BLE001 - everything goes back to the caller
            status, value = "err", _portable_error(e)
        records, fwd.records = fwd.records, []
        try:
            conn.send((status, value, _state(t), records))
        except (EOFError, OSError, BrokenPipeError):
            break
        if op == "step" and status == "step":     # (after the answer: the caller goes on meanwhile)
            t.work_after_step()
    try:
        t.teardown()
    except Exception:
        pass
    conn.close()


# --- the main-process side ------------------------------------------------------------------
def _ask_exit(proc, conn) -> None:
    """Ask a worker to close SUMO and end (without waiting). Closing a big simulation takes
    CPU for a while: at the lowest priority, so that the loop and the new SUMO come first."""
    try:
        if proc.poll() is None:
            try:
                os.setpriority(os.PRIO_PROCESS, proc.pid, 19)
            except (AttributeError, OSError):
                pass
            conn.send(("exit", (), (), {}))
    except Exception:
        pass


def _reap(proc, conn, wait: bool) -> bool:
    """Collect a worker that was asked to end; True once it has."""
    if wait:
        try:
            proc.wait(10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5.0)
    elif proc.poll() is None:
        return False
    try:
        conn.close()
    except Exception:
        pass
    _remove_tmp_of(proc)
    return True


def _remove_tmp_of(proc) -> None:
    """A worker that has ended: its SUMO folder goes too (killed, it left it behind)."""
    from cosim.traffic import SumoTraffic

    SumoTraffic.remove_tmp_of(proc.pid)


class _Remote:
    """A proxy for an object (module, class) inside the worker: attribute access and calls."""
    __slots__ = ("_tp", "_path")

    def __init__(self, tp, path):
        self._tp = tp
        self._path = path

    def __getattr__(self, name):
        return self._tp._resolve(self._path + (name,))

    def __call__(self, *args, **kwargs):
        return self._tp._call(self._path, args, kwargs)

    def __repr__(self):
        return f"<remote {'.'.join(self._path)} in SUMO's worker process>"

    def network_links(self) -> dict:
        """lane -> its links, every lane of the network, read in one call and kept until the
        network changes (``SumoTraffic.lane_links``): a route search reads hundreds of lanes'
        links, and each ``lane.getLinks`` across the pipe waits for the step in flight."""
        return self._tp._call(("lane_links",), (), {})


class TrafficProcess(Component):
    """A ``SumoTraffic`` (same constructor, same methods) in a worker process; ``step()`` is
    asynchronous: it returns at once and SUMO steps while the caller works."""

    def __init__(self, net_file, route_files=(), **kwargs):
        if isinstance(route_files, (str, os.PathLike)):
            route_files = [route_files]
        self.net_file = Path(net_file)
        self.route_files = [Path(p) for p in route_files]
        self.backend = kwargs.get("backend", "libsumo")
        self._args = (str(self.net_file), [str(p) for p in self.route_files])
        self._kwargs = dict(kwargs)
        self._proc = None
        self._conn = None
        self._inflight: collections.deque = collections.deque()   # a tag per request in flight
        self._adopted = None     # swap_begin's answer (old id -> new id), for swap_end
        self._state: dict = {"running": False, "_generation": 0}
        self._kinds: dict = {}
        self._cache: dict = {}
        self._cache_gen = None
        self._asked: set = set()   # network reads asked ahead (expect), not answered yet
        self._asked_at: dict = {}  # answered()'s reads -> the step count when asked
        # reads answered with the step (path, args) -> (status, value), and the reads to ask
        # for: every read the caller made in one of the last PREFETCH_KEEP steps
        self._prefetched: dict = {}
        self._prefetch_keys: dict = {}
        self._steps = 0
        self._lagged = False       # lagged_reads(): reads answered from the last step's prefetch
        self._actors_req = None    # (x, y, radius) of the actors query sent with the step
        self._actors_radius = None
        self._last_pose = None
        self._pending_pose = None  # set_ego_pose's call, sent with the next step (or before any other request)
        self.calls = 0           # requests sent (for benchmarks)
        self.waits = 0           # answers waited for
        self._next: dict | None = None   # SUMO started ahead on the next network (prepare_network)
        self._retired: list = []         # workers of earlier networks, closing down

    # --- lifecycle ----------------------------------------------------------------------
    def setup(self) -> None:
        if self._proc is not None:
            raise SimulationError("TrafficProcess.setup(): this simulation is already running")
        level = logging.getLogger("cosim").getEffectiveLevel()
        try:
            self._proc, self._conn = start_worker("cosim.sumo_process")
        except OSError as e:
            raise SimulationError(f"cannot start SUMO's worker process: {e}") from None
        _WORKERS.add(self)
        try:
            self._conn.send((self._args, self._kwargs, level))
            self._call(("setup",), (), {})
            # SumoTraffic's methods, libsumo's domains and their functions known at once: the
            # first use of one in a frame asked the worker what it was, and waited for the step
            # in flight (1.5 ms)
            self._post(("kinds", ("sumo",), (), {}))
            self._kinds.update(self.sync()[1])
            self._kinds.update(_method_kinds())
        except BaseException:
            self.teardown()
            raise

    def teardown(self) -> None:
        self.discard_prepared()
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        self._inflight.clear()
        self._pending_pose = None
        self._adopted = None
        if proc is not None:
            _ask_exit(proc, conn)
            self._retired.append((proc, conn))
        for proc, conn in self._retired:
            _reap(proc, conn, wait=True)
        self._retired = []
        self._state["running"] = False

    def __del__(self):
        try:
            self.teardown()
        except Exception:
            pass

    # --- transport ----------------------------------------------------------------------
    def _recv(self):
        try:
            status, value, state, records = self._conn.recv()
        except (EOFError, OSError):
            code = None
            if self._proc is not None:
                try:
                    code = self._proc.wait(2.0)
                except subprocess.TimeoutExpired:
                    self._proc.kill()
                    self._proc.wait(5.0)
                _remove_tmp_of(self._proc)
            self._proc = None
            self._inflight.clear()
            raise SimulationError(f"SUMO's worker process ended unexpectedly (exit code {code}); "
                                  "SUMO crashed on this network or scenario") from None
        tag = self._inflight.popleft() if self._inflight else None
        if "stats" in state:
            state["stats"] = _stats_from(state["stats"])
        self._state.update(state)
        for name, level, msg in records:
            logging.getLogger(name).log(level, "%s", msg)
        if status == "err":
            raise value
        if tag == "adopt":
            self._adopted = value
        elif isinstance(tag, tuple) and tag[0] == "expect":
            self._static_cache_fresh()
            for key, (st, v) in zip(tag[1], value):
                self._asked.discard(key)
                if st == "ok":
                    self._cache[key + ((),)] = v
        if status == "step":
            self._prefetched = value
        return status, value

    def busy(self) -> bool:
        """A request sent (the step) is not answered yet: the worker is still at it."""
        return bool(self._inflight) and self._conn is not None and not self._conn.poll()

    def sync(self):
        """Wait for every request in flight (a step, a pose) to be answered; raise the first
        error among them. Returns the last answer (status, value)."""
        out = None
        self._flush_pose()
        if self._inflight:
            self.waits += 1
        while self._inflight:
            out = self._recv()
        return out

    def _post(self, msg, tag: str | None = None) -> None:
        """Send a request without waiting for its answer."""
        if msg[0] != "step":
            self._flush_pose()
        if self._conn is None:
            raise SimulationError("SUMO is not running: call setup() first")
        self.calls += 1
        try:
            self._conn.send(msg)
        except (EOFError, OSError, BrokenPipeError):
            self._inflight.clear()
            self._recv()   # raises the worker's death as a SimulationError
        self._inflight.append(tag)

    def _flush_pose(self) -> None:
        """Send a pose that waits for the next step now (another request comes first)."""
        if self._pending_pose is not None:
            pose, self._pending_pose = self._pending_pose, None
            self._post(("call", ("set_ego_pose",)) + pose)

    def _static_cache_fresh(self) -> None:
        """The cache of network answers, emptied when the network changed."""
        gen = self._state.get("_generation")
        if gen != self._cache_gen:
            self._cache.clear()
            self._asked.clear()
            self._asked_at.clear()
            self._cache_gen = gen

    def expect(self, reads) -> None:
        """Reads (path, args) the caller will make soon, asked ahead without waiting, so that
        the call itself does not wait for the step in flight: network answers (``_STATIC``)
        not cached yet go to the worker in one batch, answered after the step and cached;
        other reads are asked for with the next step (as if the caller had made them)."""
        if self._conn is None:
            return
        self._static_cache_fresh()
        batch = []
        for path, args in reads:
            key = (path, tuple(args))
            if path in _STATIC:
                if key + ((),) not in self._cache and key not in self._asked:
                    batch.append(key)
                    self._asked.add(key)
                    self._asked_at[key] = self._steps
            elif _is_read(path):
                self._prefetch_keys[key] = self._steps
        if batch:
            self._post(("batch", tuple(batch), (), {}), tag=("expect", tuple(batch)))

    def answered(self, path: tuple, args: tuple):
        """A network answer (``_STATIC``) without waiting: the cached value, or
        :data:`NOT_YET` when it is not in yet: then it is asked for (:meth:`expect`) and in by
        the next frame. An answer asked for in this frame is NOT_YET even if it came early,
        so that a run repeats exactly whatever the timing. (A read that must not wait for the
        step in flight, where a frame later is soon enough: a vehicle seen on a new lane.)"""
        key = (path, tuple(args))
        self._static_cache_fresh()
        got = self._cache.get(key + ((),), NOT_YET)
        if got is NOT_YET or self._asked_at.get(key, -1) >= self._steps:
            if got is NOT_YET and key not in self._asked_at:     # (asked once: an error stays NOT_YET)
                self.expect([key])
            return NOT_YET
        return got

    def prepare_extension(self, route, first: int, rng_state, **kwargs) -> None:
        """``SumoTraffic.prepare_extension`` in the worker, sent without waiting for its answer
        (it only starts the draw: the worker draws on between requests)."""
        self._post_call("prepare_extension", (list(route), int(first), rng_state), kwargs)

    def warm_routes(self, on: bool = True) -> None:
        """``SumoTraffic.warm_routes`` in the worker, sent without waiting for its answer."""
        self._post_call("warm_routes", (bool(on),), {})

    def _post_call(self, name: str, args: tuple, kwargs: dict) -> None:
        """Send ``SumoTraffic.<name>(*args, **kwargs)`` without waiting for its answer (read,
        and discarded, with the next answers; ``advance`` lets it through)."""
        if self._conn is not None:
            self._post(("call", (name,), args, kwargs), tag="posted")

    def _call(self, path, args, kwargs):
        static = path in _STATIC
        if static:
            self._static_cache_fresh()
            key = (path, args, tuple(sorted(kwargs.items())))
            try:
                return self._cache[key]
            except KeyError:
                pass
            except TypeError:      # unhashable arguments
                static = False
            if static and not kwargs and (path, args) in self._asked:
                self.sync()        # asked ahead (expect): answered with the batch in flight
                try:
                    return self._cache[key]
                except KeyError:
                    pass
        elif _is_read(path) and not kwargs:
            key = (path, args)
            if not self._lagged:        # lagged: first the state the step in flight started from
                self.sync()
            hit = self._prefetch_hit(key)
            if hit is None and self._lagged:
                self.sync()
                hit = self._prefetch_hit(key)
            if hit is not None:
                if hit[0] == "err":
                    raise hit[1]
                return hit[1]
        else:
            self._prefetched = {}  # SUMO's state may change: the answers are stale
        self._post(("call", path, args, kwargs))
        value = self.sync()[1]
        if static:
            self._cache[key] = value
        return value

    def _prefetch_hit(self, key):
        """The answer to this read shipped with the last step received, or None; the read
        is asked for again with the next steps."""
        try:
            self._prefetch_keys[key] = self._steps
            return self._prefetched.get(key)
        except TypeError:      # unhashable arguments
            return None

    def _resolve(self, path):
        kind = self._kinds.get(path)
        if kind is None:
            self._post(("get", path, (), {}))
            status, value = self.sync()
            if status == "ok":
                return value
            kind = self._kinds[path] = status
        return _Remote(self, path)

    # --- the loop's calls ---------------------------------------------------------------
    def step(self) -> None:
        """Start one SUMO step in the worker and return; the next call waits for it.

        The step's answer brings the reads the caller made after recent steps (the ego's
        leader, its lane, the persons on a crossing, ...) and the actors around the pose last
        sent, so the next frame usually waits once, for the step itself."""
        self._steps += 1
        if self._retired:
            self._retired = [(p, c) for p, c in self._retired if not _reap(p, c, wait=False)]
        keys = [k for k, last in self._prefetch_keys.items() if self._steps - last <= PREFETCH_KEEP]
        self._prefetch_keys = {k: self._prefetch_keys[k] for k in keys}
        self._actors_req = None
        if self._last_pose is not None and self._actors_radius is not None:
            self._actors_req = (self._last_pose[0], self._last_pose[1], self._actors_radius + ACTORS_MARGIN_M)
            keys.append((("actors_context",), self._actors_req))
        pose, self._pending_pose = self._pending_pose or ((), {}), None
        self._post(("step", tuple(keys)) + pose, tag="step")

    def advance(self, x: float, y: float, radius: float, pose: tuple):
        """``actors_near(x, y, radius)``, then ``set_ego_pose(*pose)`` and ``step()``, in
        that effect, but the step is sent first: the worker goes on to SUMO's next step as
        soon as it has sent the last one, without waiting for this process to wake up, read
        and unpickle that answer and send the next request. The worker gets the same requests
        in the same order, so the states are the same. Returns None, and sends nothing, when
        the actors sent with the last step cannot answer (then the caller takes the usual
        order)."""
        req = self._actors_req
        if req is None or self._conn is None or self._pending_pose is not None \
                or math.hypot(x - req[0], y - req[1]) + radius > req[2]:
            return None
        key = (("actors_context",), req)
        tags = list(self._inflight)
        pending = "step" in tags and all(t in ("step", "posted") or (isinstance(t, tuple) and t[0] == "expect")
                                         for t in tags)
        if not (pending or (not tags and key in self._prefetched)):
            return None
        self._actors_radius = float(radius)
        self.set_ego_pose(*pose)
        self.step()
        while len(self._inflight) > 1:      # all but the step just sent
            self._recv()
        hit = self._prefetched.get(key)
        if hit is None:                     # (the worker answers every key it is sent)
            raise SimulationError("SUMO's worker sent no actors with its step")
        if hit[0] == "err":
            raise hit[1]
        return hit[1].snapshot(x, y, radius)

    # --- the next network, started ahead --------------------------------------------------
    def prepare_network(self, new_net, new_routes=()) -> None:
        """Start SUMO on another network in a second worker process, in the background, so that
        ``swap_network`` to it does not wait for SUMO to load (a second or more on a city's
        network and demand). ``prepared_ready()`` tells when it has loaded."""
        self.discard_prepared()
        if isinstance(new_routes, (str, os.PathLike)):
            new_routes = [new_routes]
        args = (str(Path(new_net)), [str(Path(p)) for p in new_routes])
        level = logging.getLogger("cosim").getEffectiveLevel()
        try:
            proc, conn = start_worker("cosim.sumo_process")
        except OSError as e:
            raise SimulationError(f"cannot start SUMO's worker process: {e}") from None
        nxt = dict(proc=proc, conn=conn, args=args, tags=[], error=None, results={}, errors={})
        self._next = nxt
        try:
            conn.send((args, self._kwargs, level))
        except (EOFError, OSError, BrokenPipeError):
            nxt["error"] = SimulationError("SUMO's worker process for the next network ended at once")
            return
        # load, swap_adopt's first second (SumoTraffic.warm_up) and the network's links and
        # junctions that the autopilot reads at once (warm_network), taken ahead
        self.prepare_call(None, "setup")
        self.prepare_call(None, "warm_up")
        self.prepare_call(None, "warm_network")

    def prepare_call(self, tag: str | None, name: str, *args, **kwargs) -> None:
        """Ask the SUMO started by ``prepare_network`` for ``name(*args, **kwargs)`` (a method
        of SumoTraffic) in the background, before the swap: the route from where the car will
        be, for instance. ``prepared_ready()`` turns True when it is answered; with a tag the
        answer (or error) is ``prepared_result(tag)``, untagged an error makes the prepared SUMO
        unusable."""
        nxt = self._next
        if nxt is None or nxt["error"] is not None:
            return
        try:
            nxt["conn"].send(("call", (name,), args, kwargs))
            nxt["tags"].append(tag)
        except (EOFError, OSError, BrokenPipeError):
            nxt["error"] = SimulationError("SUMO's worker process for the next network ended unexpectedly")
            nxt["tags"] = []

    def prepared_result(self, tag: str):
        """(value, error) of a tagged ``prepare_call``; (None, None) if there is none."""
        nxt = self._next or {}
        return nxt.get("results", {}).get(tag), nxt.get("errors", {}).get(tag)

    @property
    def preparing(self):
        """The (net, routes) SUMO is being started on ahead of a swap, or None."""
        return None if self._next is None else self._next["args"]

    def prepared_ready(self, block: bool = False) -> bool:
        """True once the SUMO started by ``prepare_network`` has loaded (or failed: the swap
        then raises its error). Does not wait unless ``block``."""
        nxt = self._next
        if nxt is None:
            return False
        while nxt["tags"] and (block or nxt["conn"].poll()):
            try:
                status, value, _state, records = nxt["conn"].recv()
            except (EOFError, OSError):
                code = nxt["proc"].poll()
                nxt["error"] = SimulationError(
                    f"SUMO's worker process for the next network ended unexpectedly (exit code {code})")
                nxt["tags"] = []
                break
            tag = nxt["tags"].pop(0)
            for name, level, msg in records:
                logging.getLogger(name).log(level, "%s", msg)
            if tag is not None:
                nxt["errors" if status == "err" else "results"][tag] = value
            elif status == "err" and nxt["error"] is None:
                nxt["error"] = value
        return not nxt["tags"]

    def discard_prepared(self) -> None:
        nxt, self._next = self._next, None
        if nxt is not None:
            _ask_exit(nxt["proc"], nxt["conn"])
            self._retired.append((nxt["proc"], nxt["conn"]))

    def swap_network(self, new_net, new_routes=(), keep_radius: float = 100.0, center=None) -> dict:
        """As ``SumoTraffic.swap_network``. With the same network and routes prepared
        (``prepare_network``), the actors are captured here, the worker switched to the
        prepared one and the actors inserted there: no wait for SUMO to load. Otherwise the
        worker restarts SUMO itself."""
        self.swap_begin(new_net, new_routes, keep_radius, center)
        return self.swap_end()

    def swap_begin(self, new_net, new_routes=(), keep_radius: float = 100.0, center=None,
                   ego_pose: tuple | None = None) -> bool:
        """The swap without waiting for its second half: the actors are captured from this
        SUMO (a few ms), the prepared SUMO takes over, and it inserts them while the caller
        goes on (``swap_adopt``). Steps and calls sent after
        this run after it; ``swap_end()`` gives its answer. Until then, reads under
        ``lagged_reads`` are still answered from the last step of the old network (the frame
        that started it drives on that state). With ``ego_pose`` (x, y, yaw, speed) the insert
        is also the next step, the ego posed there (``SumoTraffic.swap_adopt(advance=True)``):
        the caller sends no step of its own then. Without a prepared SUMO it swaps the slow way,
        here and now (then the caller steps as usual). Returns True if the swap took the step."""
        if isinstance(new_routes, (str, os.PathLike)):
            new_routes = [new_routes]
        args = (str(Path(new_net)), [str(Path(p)) for p in new_routes])
        self._adopted = None
        nxt = self._next
        if nxt is None or nxt["args"] != args:
            self.discard_prepared()
            self._adopted = self._call(("swap_network",), (new_net, list(new_routes)),
                                       dict(keep_radius=keep_radius, center=center))
            self._switched(args)
            return False
        self.prepared_ready(block=True)
        self._next = None
        if nxt["error"] is not None:
            _ask_exit(nxt["proc"], nxt["conn"])
            self._retired.append((nxt["proc"], nxt["conn"]))
            raise nxt["error"]
        last_step = self._prefetched      # (the capture below clears it)
        carry = self._call(("swap_capture",), (keep_radius, center), {})
        old = (self._proc, self._conn)
        self._proc, self._conn = nxt["proc"], nxt["conn"]
        _ask_exit(*old)
        self._retired.append(old)
        self._switched(args)
        self._prefetched = last_step
        kw = {} if ego_pose is None else dict(advance=True, ego_pose=tuple(ego_pose))
        if ego_pose is not None:
            self._last_pose = (float(ego_pose[0]), float(ego_pose[1]))
            self._steps += 1
        self._post(("call", ("swap_adopt",), (carry,), kw), tag="adopt")
        # the new network's links and junctions that the autopilot reads at once, sent after
        # the adopt (the worker has them read: warm_network), cached here when they come
        from .traffic import NETWORK_READS

        keys = tuple(((name,), ()) for name in NETWORK_READS)
        self._post(("batch", keys, (), {}), tag=("expect", keys))
        return ego_pose is not None

    def swap_end(self) -> dict:
        """Old id -> new id of the actors that ``swap_begin`` carried over (waits for them)."""
        if self._adopted is None:
            self.sync()
        mapping, self._adopted = self._adopted, None
        return mapping if mapping is not None else {}

    def _switched(self, args) -> None:
        """The worker now runs SUMO on another network: nothing read before holds (what
        kind of attribute each path names does: the same SumoTraffic runs there)."""
        self._args = args
        self.net_file = Path(args[0])
        self.route_files = [Path(p) for p in args[1]]
        self._prefetched = {}
        self._actors_req = None

    @contextlib.contextmanager
    def lagged_reads(self):
        """Inside: reads the caller made after recent steps, and the attributes shipped with
        every answer, come from the last step received, without waiting for a step in flight.
        The loop posts SUMO's next step, then runs its driver on the state that step started
        from while SUMO computes. Other calls still wait (and see the newer state)."""
        self._lagged = True
        try:
            yield self
        finally:
            self._lagged = False

    def set_ego_pose(self, x, y, *args, **kwargs) -> None:
        """Sent with the next step, or before any other request, whichever comes first
        (one message less a frame); its errors come with the next answer."""
        self._last_pose = (float(x), float(y))
        # (SUMO moves the ego in its next step: reads until then see the state before, as
        # in-process; so the prefetched answers stay valid)
        self._flush_pose()
        self._pending_pose = ((x, y) + args, kwargs)

    def actors_near(self, x: float, y: float, radius: float):
        """As SumoTraffic.actors_near; served from the actors sent with the step when they
        cover the circle asked for."""
        self._actors_radius = float(radius)
        req = self._actors_req
        if req is not None:
            self.sync()
            hit = self._prefetched.get((("actors_context",), req))
            if hit is not None and hit[0] == "ok" and math.hypot(x - req[0], y - req[1]) + radius <= req[2]:
                return hit[1].snapshot(x, y, radius)
        return self._call(("actors_context",), (x, y, radius), {}).snapshot(x, y, radius)

    def tls_states(self):
        return self._call(("tls_states",), (), {})

    @property
    def stats_nowait(self):
        """``stats`` without waiting for a step in flight (as of the last answer)."""
        return self._state["stats"]

    @property
    def sumo(self):
        if self._conn is None:
            raise SimulationError("SUMO is not running: call setup() first")
        return _Remote(self, ("sumo",))

    def __getattr__(self, name):
        if name.startswith("__") or name in ("_proc", "_conn", "_state", "_kinds", "_next", "_retired"):
            raise AttributeError(name)
        state = self.__dict__.get("_state", {})
        if name in _STATE:
            if self.__dict__.get("_conn") is not None and not self.__dict__.get("_lagged"):
                self.sync()
            if name in state:
                return state[name]
            raise AttributeError(name)
        if self.__dict__.get("_conn") is None:
            raise AttributeError(f"{name} (SUMO's worker process is not running)")
        return self._resolve((name,))


if __name__ == "__main__":
    if os.environ.get("COSIM_WORKER_PROFILE"):      # a cProfile dump of the worker, for benchmarks
        import cProfile

        cProfile.run("_serve(worker_connection())", os.environ["COSIM_WORKER_PROFILE"])
    else:
        _serve(worker_connection())
