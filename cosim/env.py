"""A Gymnasium-style environment around :class:`cosim.sim.Simulation`.

``DrivingEnv(config)`` drives the physics car with your actions, one SUMO step (0.1 s by
default) per ``step``::

    from cosim.config import SimConfig
    from cosim.env import DrivingEnv
    from netgen.config import WorldConfig

    env = DrivingEnv(SimConfig(world=WorldConfig(preset="helsinki", chunks=0), traffic="light",
                               goal=(60.1716, 24.9452), speed_mps=10.0, duration_s=120))
    obs, info = env.reset(seed=1)
    done = False
    while not done:
        action = info["autopilot_action"]          # or your policy: [throttle, brake, steer]
        obs, reward, terminated, truncated, info = env.step(action)
        done = terminated or truncated
    env.close()

``DrivingEnv(config, render_mode="rgb_array")`` loads the world's visual meshes (as
``SimConfig(render=True)``), and ``render()`` returns PyBullet's chase-camera picture
(270 x 480 x 3, uint8).

Gymnasium is *not* a dependency: the class follows its API (``reset(seed=None, options=None)
-> (obs, info)``, ``step(action) -> (obs, reward, terminated, truncated, info)``, ``close()``)
and, when ``gymnasium`` is importable, subclasses ``gymnasium.Env`` with matching
``action_space`` (``Box([0, 0, -1], [1, 1, 1])``) and ``observation_space`` (a ``Dict``).

Action
    ``[throttle, brake, steer]``: pedals 0..1, steering -1..1 (+ = left, a fraction of full
    lock; ``cosim.vehicle``), applied to the wheels for one step.

Observation (a dict of small numpy arrays, all float32 except ``light``)
    ``speed`` (m/s), ``set_speed`` (m/s), ``lateral_offset`` (m from the lane path's
    centreline, + = left), ``heading_error`` (rad, car yaw minus path heading),
    ``curvature_ahead`` (1/m, the largest over the next 30 m), ``lidar`` (``n_rays``
    distances in m from the front bumper, ``±35°``, ``lidar_range`` when nothing is hit),
    ``light`` (int: 0 none / priority road, 1 green, 2 yellow, 3 red, 4 stop sign, 5 yield),
    ``light_distance`` (m from the bumper to that stop line, 1000 when none),
    ``lead_gap`` / ``lead_speed`` (m and m/s of the nearest obstacle on the path as the
    autopilot's perception fuses it; gap ``lidar_range``, speed 0 when none).

Reward (per step; weights in ``DrivingEnv.REWARD``)
    ``+ progress``: metres gained along the route divided by the set speed's metres per step
    (1.0 per step at the set speed); ``- lateral``: 0.5 (offset / 1 m)²; ``- speeding``: 0.5
    per m/s above the set speed; ``- red_light``: 5 for crossing a stop line at red;
    ``- collision``: 20 (and the episode ends); ``- off_road``: 10 (the car more than 3 m
    from its lane path: the episode ends); ``+ arrived``: 10 at the goal (the episode ends).

Episodes
    ``terminated``: arrived, collision or off road. ``truncated``: ``max_steps`` (default
    ``config.duration_s / step``). ``reset(seed=N)`` starts the simulation afresh with that
    seed: the same seed gives the same episode, step for step, for the same actions (as
    Gymnasium's ``check_env`` asks). ``reset()`` without a seed puts the car back at the start
    in the running simulation (fast: SUMO's traffic goes on from where it was). ``info``
    carries ``autopilot_action`` (what the autopilot would do now: for imitation or as a
    baseline), the ego state, the step's reward terms and the simulation's summary at the end.
"""
from __future__ import annotations

import copy
import math

import numpy as np

from .autopilot import Autopilot
from .config import MAX_SEED

try:  # Gymnasium is optional: follow its API, subclass it when present
    import gymnasium as _gym
    from gymnasium import spaces as _spaces

    _Base = _gym.Env
except Exception:  # pragma: no cover - depends on the environment
    _gym = None
    _spaces = None
    _Base = object

LIGHT_CODES = {"none": 0, "green": 1, "yellow": 2, "red": 3, "stop": 4, "yield": 5}


class _ActionDriver:
    """The simulation's driver inside the env: runs the autopilot (perception, and its
    suggestion) and applies the env's action."""

    def __init__(self, autopilot: Autopilot):
        self.autopilot = autopilot
        self.action = (0.0, 1.0, 0.0)
        self.speed = autopilot.speed
        self.target_speed = float("nan")

    def control(self, st, s_here, actors, dt):
        self.autopilot.control(st, s_here, actors, dt)
        return self.action


class DrivingEnv(_Base):
    """Gymnasium-style environment (module doc)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    REWARD = {"progress": 1.0, "lateral": 0.5, "speeding": 0.5, "red_light": 5.0, "collision": 20.0,
              "off_road": 10.0, "arrived": 10.0}

    def __init__(self, config, max_steps: int | None = None, n_rays: int = 41, lidar_range: float = 70.0,
                 render_mode: str | None = None):
        self.base_config = config
        self.n_rays = int(n_rays)
        self.lidar_range = float(lidar_range)
        self.render_mode = render_mode
        self.max_steps = max_steps
        self.sim = None
        self._seed = None
        self._steps = 0
        self._s_prev = 0.0
        self._collisions = 0
        self._stop_passed: set = set()
        if _spaces is not None:
            f = np.float32
            self.action_space = _spaces.Box(low=np.array([0, 0, -1], f), high=np.array([1, 1, 1], f), dtype=f)
            box = lambda lo, hi, n=1: _spaces.Box(low=lo, high=hi, shape=(n,), dtype=f)  # noqa: E731
            self.observation_space = _spaces.Dict({
                "speed": box(-10.0, 60.0), "set_speed": box(0.0, 60.0), "lateral_offset": box(-50.0, 50.0),
                "heading_error": box(-math.pi, math.pi), "curvature_ahead": box(0.0, 10.0),
                "lidar": box(0.0, self.lidar_range, self.n_rays), "light": _spaces.Discrete(6),
                "light_distance": box(0.0, 1000.0), "lead_gap": box(0.0, 1000.0), "lead_speed": box(0.0, 60.0),
            })
        else:
            self.action_space = None
            self.observation_space = None

    # --- the Gymnasium API ---------------------------------------------------------------
    def reset(self, seed: int | None = None, options: dict | None = None):
        from .sim import Simulation

        if _Base is not object:
            try:
                super().reset(seed=seed)
            except TypeError:
                pass
        # a seed restarts the simulation, so that the same seed gives the same episode (as
        # Gymnasium's API asks, and its check_env tests); without one, the car is put back
        # at the start of the running simulation (fast: SUMO's traffic goes on)
        if self.sim is not None and seed is None and self._soft_reset():
            pass
        else:
            self.close()
            cfg = copy.deepcopy(self.base_config)
            if seed is not None:
                cfg.seed = int(seed) % (MAX_SEED + 1)     # (any int, as Gymnasium allows; SUMO's is 32-bit)
            if self.render_mode == "rgb_array":
                cfg.render = True       # (a headless world has no visual meshes: render() drew none)
            self._seed = cfg.seed
            sim = Simulation(cfg)
            sim.setup()
            self.sim = sim
            self._install_driver()
        self._steps = 0
        self._collisions = self.sim.summary.ego_collisions
        self._stop_passed = set()
        st = self.sim.vehicle.state()
        self._s_prev = self.sim.path.project(st.x, st.y, self.sim._path_idx)[1]
        # one standing step so that perception (lidar, lights, lead) is filled in
        self._driver.action = (0.0, 1.0, 0.0)
        ego = self.sim.step()
        self._s_prev = self.sim.path.project(ego.x, ego.y, self.sim._path_idx)[1]
        return self._observe(ego), self._info(ego, {})

    def step(self, action):
        if self.sim is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=float).reshape(-1)
        if a.shape[0] != 3 or not np.all(np.isfinite(a)):
            raise ValueError("action must be [throttle, brake, steer] (3 finite numbers)")
        self._driver.action = (float(np.clip(a[0], 0, 1)), float(np.clip(a[1], 0, 1)), float(np.clip(a[2], -1, 1)))
        sim = self.sim
        s_before = self._s_prev
        stops_ahead = self._stops_with_state()
        ego = sim.step()
        self._steps += 1
        k, s_now, lat = sim.path.project(ego.x, ego.y, sim._path_idx)
        if sim.path is not getattr(self, "_path_seen", None):   # the route was extended
            self._path_seen = sim.path
            s_before = s_now - max(0.0, ego.speed) * sim.cfg.step_length_s
        progress = s_now - s_before
        self._s_prev = s_now
        W = self.REWARD
        dt = sim.cfg.step_length_s
        v_set = max(float(sim.cfg.speed_mps), 0.1)
        terms = {"progress": W["progress"] * progress / (v_set * dt),
                 "lateral": -W["lateral"] * (lat / 1.0) ** 2,
                 "speeding": -W["speeding"] * max(0.0, ego.speed - v_set)}
        # crossing a stop line at red
        front_before, front_now = s_before + self._front, s_now + self._front
        for key, s_line, state in stops_ahead:
            if state in "rRu" and front_before <= s_line < front_now and key not in self._stop_passed:
                self._stop_passed.add(key)
                terms["red_light"] = -W["red_light"]
        terminated = False
        if sim.summary.ego_collisions > self._collisions:
            self._collisions = sim.summary.ego_collisions
            terms["collision"] = -W["collision"]
            terminated = True
        if abs(lat) > 3.0:
            terms["off_road"] = -W["off_road"]
            terminated = True
        if sim.summary.arrived:
            terms["arrived"] = W["arrived"]
            terminated = True
        reward = float(sum(terms.values()))
        limit = self.max_steps or int(round(sim.cfg.duration_s / dt))
        truncated = not terminated and self._steps >= limit
        info = self._info(ego, terms)
        if terminated or truncated:
            info["summary"] = sim.finish()
        return self._observe(ego), reward, terminated, truncated, info

    def render(self):
        """The chase camera's RGB picture (with ``render_mode="rgb_array"``: the world drawn)."""
        if self.sim is None:
            return None
        return self.sim.camera_image(480, 270)

    def close(self):
        if self.sim is not None:
            self.sim.teardown()
            self.sim = None

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass

    # --- internals -------------------------------------------------------------------------
    def _install_driver(self):
        ap = Autopilot(self.sim, n_rays=self.n_rays, lidar_range=self.lidar_range)
        self._driver = _ActionDriver(ap)
        self.sim.driver = self._driver
        self._front = ap.front
        self._path_seen = self.sim.path

    def _soft_reset(self) -> bool:
        """Put the car back at the start of the running simulation (False: cannot)."""
        sim = self.sim
        try:
            x, y, yaw, lane, pos = sim._snap_start()
            z = float(sim.world.ground_z(x, y)[0])
            sim.physics.update(x, y, sim.keep_radius, budget_ms=1e9)
            sim.vehicle.place_on_ground(x, y, yaw, z)
            sim.goal_xy = None
            sim._plan_route(lane, pos)
            sim.traffic.set_ego_pose(x, y, yaw, 0.0)
            sim._last_xy = (x, y)
            sim.manual = None
        except Exception:
            return False
        self._install_driver()
        return True

    def _stops_with_state(self):
        sim = self.sim
        out = []
        st = sim.vehicle.state()
        s_here = sim.path.project(st.x, st.y, sim._path_idx)[1]
        for stop in sim.path.stops:
            if s_here - 5.0 < stop.s < s_here + 30.0:
                try:
                    state = stop.state(sim.traffic.sumo)
                except Exception:
                    state = stop.initial_state
                out.append(((stop.junction, stop.lane), stop.s, state))
        return out

    def _observe(self, ego) -> dict:
        sim = self.sim
        ap = self._driver.autopilot
        path = sim.path
        st = sim.vehicle.state()
        k, s_here, lat = path.project(st.x, st.y, sim._path_idx)
        he = math.atan2(math.sin(st.yaw - path.heading[k]), math.cos(st.yaw - path.heading[k]))
        if ap.lidar is not None:
            scan = ap.lidar.scan_vehicle(st)
            lidar = scan.distance
        else:
            lidar = np.full(self.n_rays, self.lidar_range)
        light, light_d = LIGHT_CODES["none"], 1000.0
        front = s_here + ap.front
        for stop in path.stops:
            if stop.s < front - 0.3:
                continue
            if stop.s > front + 200.0:
                break
            try:
                state = stop.state(sim.traffic.sumo)
            except Exception:
                state = stop.initial_state
            if stop.tls:
                light = LIGHT_CODES["red"] if state in "rRu" else (LIGHT_CODES["yellow"] if state in "yY"
                                                                  else LIGHT_CODES["green"])
            elif state in "sw" or (stop.junction, stop.lane) in ap._osm_stops:
                light = LIGHT_CODES["stop"]
            elif state in "m=oO":
                light = LIGHT_CODES["yield"]
            else:
                continue
            light_d = float(stop.s - front)
            break
        lead = ap.lead
        f = np.float32
        return {
            "speed": np.array([st.speed], f), "set_speed": np.array([sim.cfg.speed_mps], f),
            "lateral_offset": np.array([lat], f), "heading_error": np.array([he], f),
            "curvature_ahead": np.array([path.max_curvature(s_here, s_here + 30.0)], f),
            "lidar": np.asarray(lidar, dtype=f), "light": int(light),
            "light_distance": np.array([min(max(light_d, 0.0), 1000.0)], f),
            "lead_gap": np.array([min(lead.gap, 1000.0) if lead else self.lidar_range], f),
            "lead_speed": np.array([lead.speed if lead else 0.0], f),
        }

    def _info(self, ego, terms) -> dict:
        ap = self._driver.autopilot
        return {"autopilot_action": np.array(ap.last, dtype=np.float32), "reason": ap.reason,
                "target_speed": ap.target_speed, "ego": ego, "reward_terms": dict(terms),
                "t": self.sim.t, "snap": dict(self.sim.snap_info)}
