"""Workers that keep the window responsive: each is a QObject moved to its own QThread.

:class:`SimWorker` owns the :class:`cosim.sim.Simulation`: it is created, set up (the world
build, SUMO, PyBullet), stepped and torn down in the worker thread only, and everything the
window shows comes back through Qt signals (queued across the threads). The window talks to
it through signals as well (start, speed, destination, keys), except :meth:`SimWorker.request_stop`,
which only sets a thread-safe flag: a world build in progress checks it at its next progress
report and unwinds (the build writes atomically, so nothing half-written stays behind), and
the step loop checks it before every step. Either way ``Simulation.teardown()`` runs in the
worker thread and then ``stopped`` (or ``failed``) is emitted, exactly once per start.

:class:`CheckWorker` runs :func:`ui.validation.check_reality` (it may read an OSM file).
"""
from __future__ import annotations

import logging
import threading
import time
from collections import deque

import numpy as np
from PyQt5.QtCore import QObject, QThread, QTimer, pyqtSignal, pyqtSlot
from PyQt5.QtGui import QImage

from netgen.errors import CosimError

from . import validation

log = logging.getLogger("cosim.ui")

# stages as Simulation.setup / build_world report them, in order (for one overall progress bar)
STAGES = ["build", "osm", "elevation", "netconvert", "terrain", "features", "buildings", "scenery", "roads",
          "write", "done", "traffic", "sumo", "physics", "run"]


class WorkerThread(QThread):
    """A QThread whose event loop runs inside one Python call.

    pyproj >= 3.7 keeps its PROJ context in thread-local storage that is only safe while the
    thread holds a Python thread state; a plain QThread gets a fresh one for every slot call
    and pyproj then crashes (pyproj issue #1509). Running ``exec_()`` from a Python ``run()``
    keeps one thread state for the thread's whole life."""

    def run(self):
        self.exec_()


class Cancelled(Exception):
    """Raised from the progress callback to unwind a build or setup the user stopped."""


class _LogForward(logging.Handler):
    def __init__(self, signal):
        super().__init__(level=logging.WARNING)
        self.signal = signal

    def emit(self, record):
        try:
            self.signal.emit(" ".join(record.getMessage().split())[:200])
        except Exception:
            pass


class SimWorker(QObject):
    # to the window (queued: it lives in the GUI thread); the window reaches the worker's
    # slots through its own signals
    progress = pyqtSignal(str, float, str, float)     # stage, fraction, message, overall 0..1
    started = pyqtSignal(object)                      # dict: map layers, chunks, route, snap info
    frame = pyqtSignal(object)                        # dict: ego, actors, route, tiles, camera, status
    warning = pyqtSignal(str)
    goal_result = pyqtSignal(object)                  # dict (route_length_m, eta_s, route) or {"error": msg}
    speed_result = pyqtSignal(object)                 # {"speed_mps": v} or {"error": msg}
    stopped = pyqtSignal(str)                         # the summary line
    failed = pyqtSignal(str)                          # a one-line error

    FRAME_EVERY_S = 0.05        # ego, actors, map: at most 20 per second
    CAMERA_EVERY_S = 0.15       # the camera image: at most ~7 per second, less when it is slow

    def __init__(self):
        super().__init__()
        self.sim = None
        self._stop = threading.Event()
        self.idle = threading.Event()         # set while no simulation exists (thread-safe)
        self.idle.set()
        self._timer = None
        self._kb = None
        self.camera_size = (480, 270)
        self.camera_view = "chase"
        self.camera_on = True
        self._reset()

    def _reset(self):
        self._last_frame = self._last_cam = 0.0
        self._last_path = None
        self._last_tiles = None
        self._rtf = deque(maxlen=40)
        self._running = False
        self._n_collisions = 0
        self._n_violations = 0
        self._nc_running = False
        self._world_version = 0
        self._overall = 0.0
        self._cam_every = self.CAMERA_EVERY_S
        self._log_handler = None

    # --- thread-safe, called from the window's thread ------------------------------------
    def arm(self):
        """Called by the window just before it sends `start`: a stop requested from now on,
        even before the worker has picked the start up, cancels that run."""
        self._stop.clear()
        self.idle.clear()

    def request_stop(self):
        self._stop.set()

    # --- slots (run in the worker thread) -----------------------------------------------
    @pyqtSlot(object)
    def start(self, cfg):
        from cosim.sim import Simulation

        self.idle.clear()
        self._reset()
        self._log_handler = _LogForward(self.warning)
        for name in ("cosim", "netgen"):
            logging.getLogger(name).addHandler(self._log_handler)
        try:
            self._check_stop()
            if cfg.world_dir is None:
                cfg = self._build(cfg)
            self.sim = Simulation(cfg, progress=self._progress)
            self._check_stop()
            self.sim.setup()
            self._check_stop()
            self._attach_keyboard()
            self._running = True
            self.started.emit(self._started_info())
        except Cancelled:
            self._finish(stopped=True)
            return
        except CosimError as e:
            self._finish(error=str(e))
            return
        except Exception as e:  # an unexpected bug: still tear down, still tell the window
            log.exception("simulation setup failed")
            self._finish(error=f"{type(e).__name__}: {e}")
            return
        self._timer = QTimer(self)
        self._timer.setInterval(0)
        self._timer.timeout.connect(self._tick)
        self._timer.start()

    @pyqtSlot(float)
    def set_speed(self, mps):
        if not self._running:
            return
        try:
            self.sim.set_speed(mps)
            self.speed_result.emit({"speed_mps": float(mps)})
        except CosimError as e:
            self.speed_result.emit({"error": str(e)})

    @pyqtSlot(object)
    def set_goal(self, latlon):
        if not self._running:
            return
        try:
            if latlon is None:
                info = self.sim.set_goal(None)
            else:
                info = self.sim.set_goal(*latlon)
            info = dict(info)
            info["route"] = np.array(self.sim.path.xy, dtype=float)
            info["goal_xy"] = self.sim.goal_xy
            self._last_path = self.sim.path
            self.goal_result.emit(info)
        except CosimError as e:
            self.goal_result.emit({"error": str(e)})
        except Exception as e:   # e.g. a lane without links inside a junction
            self.goal_result.emit({"error": f"could not route there: {e}"})

    @pyqtSlot(str)
    def key_press(self, key):
        if self._kb is not None:
            self._kb.press(key)

    @pyqtSlot(str)
    def key_release(self, key):
        if self._kb is not None:
            self._kb.release(key)

    @pyqtSlot(str)
    def set_camera_view(self, view):
        self.camera_view = view
        self._last_cam = 0.0

    # --- internals ------------------------------------------------------------------------
    def _check_stop(self):
        if self._stop.is_set():
            raise Cancelled()

    def _progress(self, stage, frac, msg=""):
        # a stop request unwinds the build or setup here, except while netconvert may run in
        # the background (from its "netconvert" report until "roads"; builds that start it
        # and wait for it later kill it themselves on an error): an exception then could leave
        # that child process running
        if stage == "netconvert":
            self._nc_running = True
        elif stage == "roads":
            self._nc_running = False
        if not self._nc_running:
            self._check_stop()
        try:
            k = STAGES.index(stage)
            # one bar for the whole start-up, never moving back
            overall = (k + max(0.0, min(1.0, float(frac)))) / len(STAGES)
            self._overall = overall = max(self._overall, overall)
        except ValueError:
            overall = -1.0
        self.progress.emit(stage, float(frac), msg, overall)

    def _build(self, cfg):
        """Build (or reuse) the world with the same API call Simulation.setup makes, then run
        it as a built world (world_dir)."""
        import copy
        from pathlib import Path

        from netgen.build import build_world

        self._progress("build", 0.0, "building the world")
        w = build_world(cfg.world, progress=self._progress)
        cfg = copy.copy(cfg)
        # a reused world's dict has no "out": it is where the config asked for it
        cfg.world_dir = w.get("out") or str(Path(cfg.world.out or Path("worlds") / w["name"]).resolve())
        return cfg

    def _attach_keyboard(self):
        try:
            from cosim.keyboard import KeyboardControl
        except ImportError:      # keyboard driving unavailable in this version of cosim
            self._kb = None
            return
        self._kb = KeyboardControl()
        if hasattr(self.sim, "keyboard"):
            # the simulation polls it every step (and feeds PyBullet's window keys into it)
            self.sim.keyboard = self._kb

    def _world_layers(self) -> dict:
        w = self.sim.world
        return {"layers": w.map_layers(), "chunks": {k: tuple(v["bounds_m"]) for k, v in w.chunks.items()}}

    def _started_info(self) -> dict:
        sim = self.sim
        w = sim.world
        self._world_version = getattr(w, "version", 0)
        info = self._world_layers()
        info.update({"tile_size": w.tile_size, "center": (w.frame.center_lat, w.frame.center_lon),
                     "route": np.array(sim.path.xy, dtype=float), "goal_xy": sim.goal_xy,
                     "snap": dict(sim.snap_info), "world": str(w.path), "speed_mps": sim.cfg.speed_mps})
        self._last_path = sim.path
        return info

    def _tick(self):
        sim = self.sim
        if sim is None:
            return
        if self._stop.is_set():
            self._finish(stopped=True)
            return
        try:
            if self._kb is not None and not hasattr(sim, "keyboard"):
                sim.set_manual(self._kb.update(sim.cfg.step_length_s))
            t0 = time.perf_counter()
            end = sim.cfg.duration_s - 1e-6             # the traffic demand ends there
            ego = sim.step()
            # batch a few steps per tick when running faster than real time (fewer events)
            while not sim.cfg.realtime and time.perf_counter() - t0 < 0.02 and not self._stop.is_set() \
                    and sim.t < end:
                ego = sim.step()
            self._rtf.append((time.perf_counter(), sim.t))
            if sim.t >= end:
                self.frame.emit(self._frame(ego, time.perf_counter()))
                self._finish(stopped=True)
                return
            now = time.perf_counter()
            if now - self._last_frame >= self.FRAME_EVERY_S:
                self._last_frame = now
                self.frame.emit(self._frame(ego, now))
        except CosimError as e:
            self._finish(error=str(e))
        except Exception as e:
            log.exception("simulation step failed")
            self._finish(error=f"{type(e).__name__}: {e}")

    def _frame(self, ego, now) -> dict:
        from dataclasses import asdict

        sim = self.sim
        f = {"ego": asdict(ego), "actors": sim.actors(), "control": tuple(sim.last_control),
             "manual": sim.manual is not None, "speed_mps": sim.cfg.speed_mps,
             "arrived": sim.summary.arrived, "t": sim.t, "route_left": sim.route_left()}
        if sim.path is not self._last_path:
            self._last_path = sim.path
            f["route"] = np.array(sim.path.xy, dtype=float)
            f["goal_xy"] = sim.goal_xy
        tiles = frozenset(sim.physics.tiles)
        if tiles != self._last_tiles:
            new = tiles - (self._last_tiles or frozenset())
            self._last_tiles = tiles
            f["tiles"] = {k: sim.world.tile_bounds(k) for k in tiles}
            if new:
                f["tiles_new"] = sorted(new)
        if self.camera_on and now - self._last_cam >= self._cam_every:
            w, h = self.camera_size
            rgb = np.ascontiguousarray(sim.camera_image(w, h, view=self.camera_view))
            f["camera"] = QImage(rgb.data, w, h, 3 * w, QImage.Format_RGB888).copy()
            self._last_cam = time.perf_counter()
            # PyBullet's software renderer takes 50..250 ms a picture: keep it to a quarter
            # of the time, so that the simulation keeps its pace
            self._cam_every = max(self.CAMERA_EVERY_S, 3.0 * (self._last_cam - now))
        # real-time factor over the last few seconds
        rtf = 0.0
        if len(self._rtf) >= 2:
            (w0, s0), (w1, s1) = self._rtf[0], self._rtf[-1]
            rtf = (s1 - s0) / max(w1 - w0, 1e-6)
        warn = ""
        s = sim.summary
        if len(sim.collision_log) > self._n_collisions:
            self._n_collisions = len(sim.collision_log)
            ev = sim.collision_log[-1]
            warn = f"collision with {ev['with']} {ev['what']} at {ev['speed_mps']:.1f} m/s"
        elif s.sensor_range_violations > self._n_violations:
            self._n_violations = s.sensor_range_violations
            warn = "the sensor range reaches beyond the loaded world"
        elif not ego.on_road:
            warn = "the car is off the road"
        # the world grows while the car drives (cosim.streaming): new chunks, a new network
        version = getattr(sim.world, "version", 0)
        if version != self._world_version:
            self._world_version = version
            f["world"] = self._world_layers()
        streamer = getattr(sim, "streamer", None)
        f["building"] = getattr(streamer, "building", None) if streamer is not None else None
        f["chunk"] = sim.world.frame.chunk_of(ego.x, ego.y)
        f["rtf"] = rtf
        f["warning"] = warn
        f["tiles_loaded"] = len(tiles)
        return f

    def _finish(self, stopped: bool = False, error: str | None = None):
        if self._timer is not None:
            self._timer.stop()
            self._timer.deleteLater()
            self._timer = None
        line = ""
        sim, self.sim = self.sim, None
        if sim is not None:
            try:
                if self._running:
                    line = sim.finish().line()
            except Exception as e:
                log.warning("summary: %s", e)
            sim.teardown()
        if self._log_handler is not None:
            for name in ("cosim", "netgen"):
                logging.getLogger(name).removeHandler(self._log_handler)
            self._log_handler = None
        self._kb = None
        self._running = False
        self.idle.set()
        if error is not None:
            self.failed.emit(error)
        else:
            self.stopped.emit(line or "stopped before the simulation ran")


class CheckWorker(QObject):
    """Runs the checks against reality off the window's thread; results carry the request's
    generation so the window drops answers to inputs that have changed since."""

    done = pyqtSignal(int, object)            # generation, CheckResult

    def __init__(self, out_root=None):
        super().__init__()
        self.out_root = out_root

    @pyqtSlot(int, object)
    def check(self, gen, ranged):
        try:
            res = validation.check_reality(ranged, self.out_root)
        except CosimError as e:
            res = validation.CheckResult(errors=[validation.FieldError("place", str(e))])
        except Exception as e:   # never leave the window waiting in "Input checked"
            log.exception("input check failed")
            res = validation.CheckResult(errors=[validation.FieldError("place", f"{type(e).__name__}: {e}")])
        self.done.emit(gen, res)
