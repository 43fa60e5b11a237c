"""The co-simulation: SUMO traffic around a physics car in PyBullet, one loop.

Components share one lifecycle (``setup`` / ``step`` / ``teardown``), as MetaDrive's managers
do, and :class:`Simulation` orchestrates them every SUMO step (0.1 s by default):

1. the ego's physics pose goes into SUMO (``moveToXY``), so SUMO's drivers and pedestrians
   react to it; SUMO advances one step;
2. SUMO's vehicles and persons near the ego are mirrored into PyBullet as kinematic bodies
   (``cosim.mirror``);
3. the driver (autopilot, keyboard or the user's own controller) reads the ego's state, its
   path, the actors and the next traffic light, and sets throttle, brake and steering;
4. physics advances by its substeps (the car is driven through its wheels);
5. the static world streams: tiles within the sensor range plus a margin are loaded, far
   ones unloaded, and the loop checks that the sensor range lies inside the loaded world;
6. a telemetry row is written.

The same class is the Python API (see README) behind ``cosim run``, scenario files and the GUI.
"""
from __future__ import annotations

import contextlib
import copy
import gc
import logging
import math
import random
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from netgen.errors import CosimError, InputError, SimulationError

from .config import SimConfig

log = logging.getLogger("cosim.sim")
#: the driver's-view camera: metres ahead of the car's centre and above the ground (just ahead of
#: the windscreen of models/car, whose cabin ends 1.05 m ahead of the centre, above its 0.95 m bonnet)
DRIVER_CAMERA = (1.1, 1.4)
MAX_CAMERA_PX = 4096     # camera_image: width and height at most this
HELD_THROTTLE = 0.3      # _check_held: the throttle at least this, the car still, no brake
HELD_WARN_S = 10.0       # a stretch this long is said (and the summary line reports the time)


def _number(value, what: str) -> float:
    """``value`` as a float, or a one-line InputError naming ``what``."""
    try:
        return float(value)
    except (TypeError, ValueError):
        raise InputError(f"{what} must be a number, got {value!r}") from None


@dataclass
class EgoState:
    t: float
    x: float
    y: float
    z: float
    yaw: float                 # rad, 0 = east, CCW
    speed: float               # m/s
    lat: float
    lon: float
    alt_m: float
    edge: str | None
    lane: str | None
    lateral_offset_m: float
    on_road: bool
    roll: float = 0.0
    pitch: float = 0.0


@dataclass
class Summary:
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    real_time_factor: float = 0.0
    steps: int = 0
    max_vehicles: int = 0
    max_persons: int = 0
    max_mirrored: int = 0
    tiles_loaded: int = 0
    tiles_unloaded: int = 0
    chunks_visited: int = 0
    sumo_collisions: int = 0
    sumo_teleports: int = 0
    persons_held: int = 0            # pedestrians that stopped rather than walk into the ego
    standoffs_released: int = 0      # vehicles taken out of SUMO after a standoff with the ego
    turnarounds: int = 0             # turns round in moves forward and back (cosim.turnround)
    no_room_to_turn: int = 0         # ... not made: the carriageway had no room (the car stopped there)
    backoffs: int = 0                # moves back and round where the car was held still (cosim.turnround.BackOff)
    ego_collisions: int = 0
    distance_m: float = 0.0
    sensor_range_violations: int = 0
    max_mirror_error_m: float = 0.0
    arrived: bool | None = None
    windows_built: int = 0
    network_swaps: int = 0
    swap_ms_max: float = 0.0
    swap_wait_s: float = 0.0         # wall time a repeatable run waited for late window builds
    swap_actors_lost: int = 0        # actors near the car at a swap that the new network's SUMO could not take
    sumo_restarts: int = 0           # SUMO's worker process crashed and was started again
    lifted_out: int = 0              # the car set on top of a replaced tile's higher ground (_lift_out)
    other_ways: int = 0              # routes taken on from the car's own lane after a lane change never came
    held_s: float = 0.0              # time the car stood still with the throttle on (something held it)
    held_longest_s: float = 0.0      # the longest such stretch
    frame_ms_median: float = 0.0
    frame_ms_p999: float = 0.0
    frame_ms_max: float = 0.0
    notes: list = field(default_factory=list)

    def line(self) -> str:
        arr = "" if self.arrived is None else (" arrived at goal." if self.arrived else " goal NOT reached.")
        return (f"sim {self.sim_time_s:.1f} s in {self.wall_time_s:.1f} s wall (x{self.real_time_factor:.1f} real time); "
                f"{self.distance_m:.0f} m driven; actors up to {self.max_vehicles} vehicles + {self.max_persons} persons "
                f"({self.max_mirrored} mirrored); tiles loaded {self.tiles_loaded} / unloaded {self.tiles_unloaded}; "
                f"collisions: ego {self.ego_collisions}, SUMO {self.sumo_collisions}; teleports {self.sumo_teleports}; "
                f"pedestrians stopped for the ego {self.persons_held}; sensor-range violations {self.sensor_range_violations}; "
                f"windows built {self.windows_built}, SUMO network swaps {self.network_swaps}"
                + (f" (waited {self.swap_wait_s:.1f} s for late builds)" if self.swap_wait_s else "")
                + (f"; actors near the car not carried over the swaps {self.swap_actors_lost}"
                   if self.swap_actors_lost else "")
                + (f"; SUMO restarted after a crash {self.sumo_restarts} time(s)" if self.sumo_restarts else "")
                + (f"; the car set on top of new, higher ground {self.lifted_out} time(s)" if self.lifted_out else "")
                + (f"; another way taken after waiting {LANE_CHANGE_GIVE_UP_S:.0f} s for a lane change "
                   f"{self.other_ways} time(s)" if self.other_ways else "")
                + (f"; vehicles taken out after a standoff with the ego {self.standoffs_released}"
                   if self.standoffs_released else "")
                + (f"; turned round in moves forward and back {self.turnarounds} time(s)" if self.turnarounds else "")
                + (f"; stopped where the route turns back, with no room to turn round, {self.no_room_to_turn} "
                   f"time(s)" if self.no_room_to_turn else "")
                + (f"; backed off where it was held still, {self.backoffs} time(s)" if self.backoffs else "")
                + (f"; the car stood still with the throttle on for {self.held_s:.0f} s (longest {self.held_longest_s:.0f} s)"
                   if self.held_longest_s >= HELD_WARN_S else "")
                + f".{arr}")


LIFT_CHECK_M = 8.0          # a tile replaced within this distance of the car: is the car caught in its ground?
MAX_SUMO_RESTARTS = 5      # a SUMO worker that keeps crashing ends the run
#: the car standing this long for a lane change its route needs (no gap in the lane beside: a
#: jam) takes another way, a route on from the lane it is in (a 30-minute dense Helsinki drive
#: stood 18 minutes for one, in a queue that never let it in)
LANE_CHANGE_GIVE_UP_S = 30.0
EXTEND_AT_M = 120.0        # the route is extended when its path ends this near ahead of the car
EXTEND_PREPARE_M = 600.0   # ... and its extension drawn ahead from this near (prepare_extension:
                           # a piece after each step, over about 100 steps)


class Simulation:
    """Build or load a world, start SUMO and PyBullet, drive the ego. See the module doc."""

    def __init__(self, config: SimConfig, progress=None, driver=None):
        # a copy: set_speed and set_goal change this run's settings, not the caller's config
        # (a second Simulation made from it started at the first one's last speed and goal)
        self._init_args = (config, progress, driver)
        self._used = False
        self.cfg = copy.deepcopy(config.validate())
        self.progress = progress or (lambda *a, **k: None)
        self.world = None
        self.demand = None          # the run's cosim.demand.Demand (its plan: the density used)
        self.traffic = None
        self.physics = None
        self.mirror = None
        self.vehicle = None
        self.telemetry = None
        self.driver = driver
        self.path = None
        self.route: list[str] = []
        self._route_sent = None            # the route SUMO has as the ego's (set_ego_route)
        self.t = 0.0
        self.summary = Summary()
        self._frame_ms: list = []
        self.last_tiles_ms = 0.0           # this frame's tile loading and unloading (physics.update)
        self._wall0 = None
        self._path_idx = 0
        self.ego_projection = None      # (path, x, y, s, index, lateral offset) of this frame's car
        self._last_xy = None
        self._rng = random.Random(config.seed)
        self._chunks_seen: set = set()
        self.goal_xy = None
        self.goal_beyond = False        # the route ends where this network does, short of the goal
        self._goal_on_path = None       # (path, goal's arc length on it, time to each point) for route_left
        self.snap_info: dict = {}
        self.manual = None                 # (throttle, brake, steer) when driven by hand
        self.last_control = (0.0, 0.0, 0.0)
        self.last_snapshot = None
        self.collision_log: list = []
        self.keyboard = None               # a cosim.keyboard.KeyboardControl when keys drive
        self.streamer = None
        self._pipelined = False            # SUMO in a worker process (cosim.sumo_process)
        self._restart_notes: list = []
        self._replan_pending = False       # a swap came in a junction: re-plan after it
        # a SUMO network swap over two frames (SUMO in its worker, see swap_traffic): (net,
        # routes, plan) to start at the next frame's start, then (plan, net) to take once the
        # new SUMO has the actors
        self._swap_next = None
        self._swap_adopting = None
        self._swap_hold = 0                # frames left without reloading stale tiles
        self._extend_retry_t = 0.0         # no route extension before this sim time
        self._no_way_on_said = None        # the route end a "no way on" warning was given for
        self._lc_stuck_since = None        # standing for a lane change since (LANE_CHANGE_GIVE_UP_S)
        self._warned_no_visuals = False    # camera_image without visual meshes (said once)
        self._extension_asked = None       # (route, generator state) of the extension prepared
        self._setup_done = False
        self._gc_frozen = False
        self._lost_before_restart = 0      # swap_actors_lost of SUMOs restarted after a crash
        self._held_s = 0.0                 # standing with the throttle on, this stretch (_check_held)
        self._held_said = False

    # ------------------------------------------------------------------------------------
    def setup(self) -> "Simulation":
        from .demand import generate_demand, place_density
        from .mirror import ActorMirror
        from .physics import PhysicsWorld
        from .telemetry import Telemetry
        from .traffic import SumoTraffic
        from .vehicle import RECOMMENDED_PHYSICS_HZ, EgoVehicle, configure_physics

        if self._setup_done:
            raise SimulationError("setup() called twice: tear the simulation down first")
        if self._used:          # set up again after a teardown: a new run (clock, summary, route)
            self.__init__(*self._init_args)
        self._used = True
        cfg = self.cfg
        try:
            self.world = self._load_world()
            density = place_density(cfg.traffic, self.world.traffic_scale)
            self.progress("traffic", 0.0, f"generating traffic demand ({density:g} vehicles/km2)")
            self.demand = demand = generate_demand(self.world.net_file, self.world.path / "traffic",
                                                   density=density, seed=cfg.seed,
                                                   duration=max(cfg.duration_s, 60.0) + 60.0)
            self.progress("sumo", 0.0, "starting SUMO")
            kind = SumoTraffic
            if self.parallel_sumo:
                from .sumo_process import TrafficProcess as kind
            cap = demand.max_vehicles
            self._routes = list(demand.route_files)
            self._traffic_kind = kind
            self._traffic_kw = dict(step_length=cfg.step_length_s, seed=cfg.seed, backend=cfg.backend,
                                    gui=cfg.sumo_gui, lane_change_s=cfg.lane_change_s,
                                    extra_args=["--max-num-vehicles", str(cap)] if cap else ())
            self.traffic = kind(self.world.net_file, self._routes, **self._traffic_kw)
            self.traffic.setup()
            self._expect_network()
            self._pipelined = kind is not SumoTraffic
            self.progress("physics", 0.0, "loading the physics world")
            hz = cfg.physics_hz or RECOMMENDED_PHYSICS_HZ
            self.substeps = max(1, int(round(cfg.step_length_s * hz)))
            self.physics = PhysicsWorld(self.world, gui=cfg.gui, physics_hz=hz,
                                        visuals=cfg.gui or cfg.render).setup()
            configure_physics(self.physics.client, hz)
            x, y, yaw, lane, pos, plan = self._face_the_way(*self._snap_start())
            self.physics.update(x, y, self.keep_radius, budget_ms=1e9)
            z = float(self.world.ground_z(x, y)[0])
            # (the bridges' lanes read now, not in the first frame: the mirror's decks too)
            if lane in self.world.bridge_lanes():
                # (on a bridge: on its deck, not on the ground under it; Portland, a start on the
                # Hawthorne Bridge's lane -282174242#0_0 put the car on the river 8 m below, and
                # it drove into the bank)
                top = float(self.world.road_top_z(np.array([x]), np.array([y]))[0])
                if np.isfinite(top) and top > z + 0.5:
                    z = top
            self.vehicle = EgoVehicle(self.physics.client, position=(x, y, z + 0.05), yaw=yaw)
            self.vehicle.place_on_ground(x, y, yaw, z)      # on the road surface, tilted with it
            self.mirror = ActorMirror(self.physics.client, self.world, visuals=cfg.gui or cfg.render)
            if plan is not None:
                self._apply_plan(plan)              # (planned already, facing the way)
            else:
                self._plan_route(lane, pos)
            self.traffic.add_ego(route_edges=self.route)
            self.traffic.set_ego_pose(x, y, yaw, 0.0)
            self.telemetry = Telemetry(cfg.telemetry).setup()
            from .streaming import WorldStreamer

            self.streamer = WorldStreamer(self).setup()
            if self.driver is None:
                from .autopilot import Autopilot

                self.driver = Autopilot(self)
            self._last_xy = (x, y)
            if cfg.gui:
                from .keyboard import KeyboardControl

                self.keyboard = KeyboardControl()
        except BaseException:
            self.teardown()
            raise
        # what setup made (the world's tables, the network, the route: hundreds of thousands
        # of objects) leaves the garbage collector's sight until teardown: a full collection
        # scanned it all in one frame (16 ms on Helsinki, against a 4 ms frame)
        if not gc.get_freeze_count():
            gc.freeze()
            self._gc_frozen = True
        self._wall0 = time.perf_counter()
        self._setup_done = True
        self.progress("run", 0.0, "running")
        return self

    def _expect_network(self) -> None:
        """A new network (setup, a swap): for random routes, SUMO's side works out their graph
        a little after each step (``SumoTraffic.warm_routes``), so that the draws of the route
        extensions find it done."""
        if self.cfg.goal is None:
            self.traffic.warm_routes()

    @property
    def parallel_sumo(self) -> bool:
        """SUMO runs in a worker process and steps while the physics runs (libsumo only)."""
        from .sumo_process import available_cpus

        p = self.cfg.parallel_sumo
        if p is None:
            p = available_cpus() >= 2
        return bool(p) and self.cfg.backend == "libsumo"

    @property
    def keep_radius(self) -> float:
        return self.cfg.sensor_range_m + self.world.tile_size * 0.75

    def _load_world(self):
        from .world import World

        if self.cfg.world_dir:
            return World(self.cfg.world_dir)
        from netgen.build import build_world

        self.progress("build", 0.0, "building the world")
        w = build_world(self.cfg.world, progress=self.progress)
        return World(w["out"])

    def _snap(self, x: float, y: float, what: str):
        """Nearest lane a car may use: (lane id, position on lane, snapped x, y, yaw, distance)."""
        try:
            return self.traffic.snap_lane(x, y)
        except SimulationError as e:
            raise InputError(f"{what}: {e}") from None

    def _snap_start(self):
        cfg = self.cfg
        if cfg.start:
            x, y = self.world.frame.to_xy(cfg.start[1], cfg.start[0])
        else:
            x, y = 0.0, 0.0
        x, y = float(x), float(y)
        lane, pos, px, py, yaw, dist = self._snap(x, y, "start")
        if dist > cfg.max_snap_m:
            raise InputError(f"start is {dist:.0f} m from the nearest road for cars (more than {cfg.max_snap_m:.0f} m)")
        if not np.isfinite(self.world.ground_z(px, py)[0]):
            # (SUMO's network reaches beyond the built chunks: the car would have no ground)
            raise InputError(f"start ({px:.0f}, {py:.0f}) m is outside the built world (its chunks cover "
                             f"{self._world_extent()}); start inside it or build more --chunks")
        # leave room to accelerate: not in the last metres of a lane
        self.snap_info = {"start_snap_m": round(dist, 2), "start_lane": lane, "start_pos": round(pos, 1)}
        log.info("start snapped %.1f m onto lane %s", dist, lane)
        return px, py, yaw, lane, pos

    def _face_the_way(self, x: float, y: float, yaw: float, lane: str, pos: float):
        """The start, turned round onto the road's other direction where the way on from the
        snapped lane takes a turnaround the car cannot make (a lane into a cul-de-sac: in
        Lauf the car drove into the building at its end) and the other direction's does not:
        with a goal, the route to it; with none, the road ahead, which runs into a dead end
        (read from the lanes' links: a route search here changed what SUMO did next, and the
        default run drove 359 m, not 360), or from which no road the car can drive leads on
        (``SumoTraffic.leads_on``: Monaco's Avenue de Grande-Bretagne, every way on through a
        tunnel or a turn the car cannot make; it drove into one). (x, y, yaw, lane, pos, the
        goal's plan from the lane taken, if made)"""

        from .traffic import opposite_edge, reverses

        ends = None

        def turns_round(route) -> bool:
            nonlocal ends
            if any(b == opposite_edge(a) for a, b in zip(route, route[1:])):
                return True
            if ends is None:
                ends = self.traffic.edge_ends()
            return any(reverses(ends, a, b) for a, b in zip(route, route[1:]))

        start = (x, y, yaw, lane, pos, None)
        try:
            if self.cfg.goal:
                plan = self.traffic.plan_route(lane, pos, **self._plan_kw())
                if not turns_round(plan["route"]) and not plan.get("undrivable"):
                    return start[:5] + (plan,)
                other = self.traffic.opposite_lane_at(lane, x, y)
                if other is None:
                    return start
                first, plan = plan, self.traffic.plan_route(other[0], other[1], **self._plan_kw())
                if not plan["route"] or turns_round(plan["route"]):
                    return start
                why = "the route takes a U-turn" if first["route"] else "no route the car can drive leads on from it"
            else:
                dead = self.traffic.runs_into_dead_end(lane)
                if not dead and self.traffic.leads_on(lane):
                    return start
                other = self.traffic.opposite_lane_at(lane, x, y)
                if other is None or self.traffic.runs_into_dead_end(other[0]) or not self.traffic.leads_on(other[0]):
                    return start
                plan, why = None, "it runs into a dead end" if dead else "no road the car can drive leads on from it"
        except SimulationError:
            return start                        # (_plan_route says what is wrong)
        if not np.isfinite(self.world.ground_z(other[2], other[3])[0]):
            return start
        log.info("start turned round onto lane %s: from lane %s %s", other[0], lane, why)
        self.snap_info.update(start_lane=other[0], start_pos=round(other[1], 1), start_turned=True)
        return other[2], other[3], other[4], other[0], other[1], plan

    def _world_extent(self) -> str:
        b = [c["bounds_m"] for c in self.world.chunks.values()]
        if not b:
            return "nothing"
        return f"x {min(v[0] for v in b):.0f}..{max(v[2] for v in b):.0f}, y {min(v[1] for v in b):.0f}..{max(v[3] for v in b):.0f} m"

    def _plan_route(self, lane: str, pos: float):
        try:
            plan = self.traffic.plan_route(lane, pos, **self._plan_kw())
        except SimulationError as e:
            if "no road for cars" in str(e):      # the goal's
                gx, gy = self._plan_kw()["goal_xy"]
                (x0, y0), (x1, y1) = self.traffic.sumo.simulation.getNetBoundary()
                if not (x0 <= gx <= x1 and y0 <= gy <= y1):
                    lat, lon = self.cfg.goal
                    raise InputError(f"goal ({lat:.5f}, {lon:.5f}) is {math.hypot(gx, gy) / 1000:.1f} km from the "
                                     f"world's centre, outside SUMO's network (x {x0:.0f}..{x1:.0f}, y {y0:.0f}.."
                                     f"{y1:.0f} m): pick a goal inside it, or build the world around the goal") from None
                raise InputError(f"goal: {e}") from None
            raise
        self._apply_plan(plan)

    def _plan_kw(self) -> dict:
        goal = None
        if self.cfg.goal:
            gx, gy = self.world.frame.to_xy(self.cfg.goal[1], self.cfg.goal[0])
            goal = (float(gx), float(gy))
        return dict(goal_xy=goal, rng_state=self._rng.getstate(), max_goal_snap_m=self.cfg.max_snap_m)

    def _apply_plan(self, plan: dict):
        """Take a route planned by ``SumoTraffic.plan_route`` (where SUMO runs)."""
        g = plan["goal"]
        self.goal_beyond = False
        if g is not None:
            beyond = bool(g.get("beyond")) and self.goal_xy is not None
            if g["dist"] > self.cfg.max_snap_m and not beyond:
                raise InputError(self._far_goal(g))
            if not plan["route"]:
                on = f"{g['street']} (lane {g['lane']})" if g.get("street") else f"lane {g['lane']}"
                if plan.get("undrivable"):
                    raise InputError(f"goal unreachable: every route from the car's position to its nearest road "
                                     f"for cars, {on}, {g['dist']:.0f} m from it, goes through a tunnel (the world "
                                     f"has none), a lane narrower than the car or a turn it cannot make")
                raise InputError(f"goal unreachable: its nearest road for cars, {on}, {g['dist']:.0f} m from it, "
                                 f"cannot be reached by road from the car's position")
            self.summary.arrived = False
            if beyond:
                # a re-plan on a network that does not reach the goal (a streamed window around
                # the car, the goal further on): towards the goal as far as this network goes;
                # the goal stays where it was snapped, and the window after this one, built
                # towards it (WorldStreamer), plans the rest. (The run ended with "goal is 220 m
                # from the nearest road for cars" at a swap.)
                self.goal_beyond = True
                log.info("t=%.1f s: the goal is %.0f m beyond this network's roads: driving towards it", self.t,
                         g["dist"])
            else:
                self.goal_xy = (g["x"], g["y"])
                length, eta = self._route_to_goal(plan["path"], g["x"], g["y"])
                self.snap_info.update({"goal_snap_m": round(g["dist"], 2), "route_length_m": round(length, 1),
                                       "eta_s": round(eta, 1)})
        else:
            self.goal_xy = None
            self._rng.setstate(plan["rng_state"])
        self.route = plan["route"]
        self.path = plan["path"]
        self._path_idx = 0

    def _far_goal(self, g: dict) -> str:
        """Why a goal this far from a road cannot be taken: outside the world (a goal beyond the
        built area was "1334 m from the nearest road", though the OSM data has roads there), or
        in it, off the roads."""
        gx, gy = self._plan_kw()["goal_xy"]
        x0, y0, x1, y1 = self.world.loaded_extent()
        if not (x0 <= gx <= x1 and y0 <= gy <= y1):
            lat, lon = self.cfg.goal
            return (f"goal ({lat:.5f}, {lon:.5f}) is outside the world, {math.hypot(gx, gy) / 1000:.1f} km from its "
                    f"centre (x {x0:.0f}..{x1:.0f}, y {y0:.0f}..{y1:.0f} m): pick a goal inside it, or build a "
                    f"larger world (--chunks) or one around the goal")
        return f"goal is {g['dist']:.0f} m from the nearest road for cars"

    def _route_to_goal(self, path, gx: float, gy: float) -> tuple[float, float]:
        """The length of ``path`` from the car (where it starts) to the goal's point, and the
        time to drive it at the set speed, or at the speed limit where that is lower. (SUMO's
        route length counts the first and last roads whole, and its travel time is at the speed
        limits: "route 2143 m, ETA 54 s" for a drive of 1,305 m at 25 m/s on the Kouvola
        motorway.)"""
        run = path.last_run(path.edges[-1])       # (the goal's road: the route ends on it)
        s0 = float(path.s[run[0]]) if run is not None else 0.0
        s_goal = float(path.project_many(np.array([gx]), np.array([gy]), s0, path.length)[0][0])
        if not math.isfinite(s_goal):
            s_goal = path.length
        ds = np.diff(np.minimum(path.s, s_goal))
        v = np.minimum(path.max_speed[:-1], max(float(self.cfg.speed_mps), 0.1))
        cum = np.concatenate([[0.0], np.cumsum(ds / np.maximum(v, 0.1))])
        self._goal_on_path = (path, s_goal, cum)
        return s_goal, float(cum[-1])

    def route_left(self) -> tuple[float, float] | None:
        """(metres, seconds) from the car to the goal along its route, the time as
        ``snap_info['eta_s']`` counts it; None without a goal (or before the route is known)."""
        g = self._goal_on_path
        if g is None or self.goal_xy is None or g[0] is not self.path or self.goal_beyond:
            return None
        path, s_goal, cum = g
        s_here = float(path.s[min(max(self._path_idx, 0), len(path.s) - 1)])
        return max(0.0, s_goal - s_here), max(0.0, float(cum[-1] - np.interp(s_here, path.s, cum)))

    # ------------------------------------------------------------------------------------
    def ego_state(self) -> EgoState:
        st = self.vehicle.state()
        k, s_here, lat_off = self.path.project(st.x, st.y, self._path_idx)
        edge = self.path.lane_of[k][1]
        lane = self.path.driven_lane(k)         # (the lane held to while a lane change waits)
        lon, lat = self.world.frame.to_lonlat(st.x, st.y)
        on_road = abs(lat_off) < 3.0 and st.wheel_contact is not None
        return EgoState(t=self.t, x=st.x, y=st.y, z=st.z, yaw=st.yaw, speed=st.speed, lat=float(lat),
                        lon=float(lon), alt_m=st.z, edge=None if edge.startswith(":") else edge, lane=lane,
                        lateral_offset_m=lat_off, on_road=on_road, roll=st.roll, pitch=st.pitch)

    def _require_setup(self, what: str) -> None:
        if not self._setup_done:
            raise SimulationError(f"call setup() before {what}() (or use the Simulation in a with block)")

    def step(self) -> EgoState:
        if not self._setup_done:
            raise SimulationError("call setup() before step()")
        try:
            return self._step()
        except SimulationError as e:
            # SUMO in its worker process crashed (libsumo can segfault): start it again on
            # the same network and demand, with the ego where it is, and go on (the actors
            # around are new ones). In-process, a crash takes the whole run down.
            if not self._pipelined or "worker process ended unexpectedly" not in str(e) \
                    or self.summary.sumo_restarts >= MAX_SUMO_RESTARTS:
                raise
            log.warning("%s; starting SUMO again", e)
            self._restart_traffic()
            return self._step()

    def _restart_traffic(self):
        st = self.vehicle.state()
        # a swap under way: SUMO starts again on the new network, and the route is planned there
        swap = self._swap_next or self._swap_adopting
        if self._swap_next is not None:
            self._routes = self._swap_next[1]
        self._swap_next = self._swap_adopting = None
        try:
            self._lost_before_restart += self.traffic.stats.swap_lost
            self.traffic.teardown()
        except Exception:
            pass
        self.traffic = self._traffic_kind(self.world.net_file, self._routes, **self._traffic_kw)
        self.traffic.setup()
        self.traffic.add_ego(route_edges=self.route)
        self._route_sent = None
        self.traffic.set_ego_pose(st.x, st.y, st.yaw, max(0.0, st.speed))
        from .traffic import ActorsSnapshot

        self.mirror.update(ActorsSnapshot.empty(self.t))      # SUMO's actors are all new ones
        self.summary.sumo_restarts += 1
        if swap is not None:
            try:
                self.replan()
            except CosimError as e:
                log.info("no route on the new network after SUMO's restart: %s", e)
        self._restart_notes.append(f"SUMO's worker process crashed at t={self.t:.1f} s and was started again")

    def _pose_for_sumo(self, st) -> tuple[float, float, float, float]:
        """The ego's pose for SUMO's next step: the car's at that step's end. SUMO moves its
        drivers to the end of the step it is asked for while the physics takes the car there,
        so the pose the car has now put the ego in SUMO one step behind its traffic (2.5 m at
        25 m/s): SUMO's drivers took their gaps to the car (changing lanes in front of it, at
        junctions) and the driver took SUMO's leader gap that much too long. The car's velocity
        and yaw rate carry it one step on."""
        dt = self.cfg.step_length_s
        vx, vy = st.velocity[0], st.velocity[1]
        return (st.x + vx * dt, st.y + vy * dt, st.yaw + st.yaw_rate * dt, max(0.0, st.speed))

    def _step(self) -> EgoState:
        t0 = time.perf_counter()
        cfg = self.cfg
        st = self.vehicle.state()
        pipelined = self._pipelined
        pose = self._pose_for_sumo(st)
        if not pipelined:
            self.traffic.set_ego_pose(*pose)
            self.traffic.step()
            snap = self.traffic.actors_near(st.x, st.y, cfg.mirror_radius_m)
        else:
            # SUMO's state after the step sent in the previous frame (waits for it, if it is
            # not done yet); then SUMO's next step starts in its worker process and runs
            # while the driver (on this state: lagged_reads) and the physics below run
            snap = None
            if self._swap_adopting is None and self._swap_next is None:
                # (the same requests in the same order, the next step sent first)
                snap = self.traffic.advance(st.x, st.y, cfg.mirror_radius_m, pose)
            if snap is None:
                snap = self.traffic.actors_near(st.x, st.y, cfg.mirror_radius_m)
                if self._swap_adopting is not None:
                    self._swap_note("adopt_wait", t0)
                    self._swap_adopted()
                if self._swap_next is None or not self._swap_start(pose):
                    self.traffic.set_ego_pose(*pose)
                    self.traffic.step()
        snap = snap.above_ground(self.world.tunnels)
        with self.traffic.lagged_reads() if pipelined else contextlib.nullcontext():
            self.t += cfg.step_length_s
            self.last_snapshot = snap
            self.mirror.update(snap, ego=(st.x, st.y, st.yaw, self.vehicle.spec.length, self.vehicle.spec.width, st.z))
            # driving
            k, s_here, lat_off = self.path.project(st.x, st.y, self._path_idx)
            self._path_idx = k
            # (the driver projects the same state onto the same path: it takes this one)
            self.ego_projection = (self.path, st.x, st.y, s_here, k, lat_off)
            if self.keyboard is not None:
                if cfg.gui:
                    from .keyboard import pybullet_keys

                    pybullet_keys(self.physics.client, self.keyboard)
                self.manual = self.keyboard.update(cfg.step_length_s)
            if self.manual is not None:
                throttle, brake, steer = self.manual
            else:
                throttle, brake, steer = self.driver.control(st, s_here, self.mirror.as_placed(snap),
                                                             cfg.step_length_s)
            self.last_control = (throttle, brake, steer)
        if self.manual is None:
            reverse = bool(getattr(self.driver, "reverse", False))
        else:                       # (by hand: the keyboard's gear)
            reverse = bool(getattr(self.keyboard, "reverse", False) and getattr(self.keyboard, "manual", False))
        self.vehicle.apply_control(throttle, brake, steer, reverse=reverse)
        self.vehicle.step(self.substeps)
        self._check_collisions()
        self._check_held(st, throttle, brake)
        # route bookkeeping (not while SUMO swaps networks: the route is planned anew then)
        swapping = self._swap_next is not None or self._swap_adopting is not None
        if self.manual is None and abs(st.speed) < 0.1 and getattr(self.driver, "reason", "") == "lane change":
            if self._lc_stuck_since is None:
                self._lc_stuck_since = self.t
            elif self.t - self._lc_stuck_since >= LANE_CHANGE_GIVE_UP_S and not swapping:
                self._lc_stuck_since = self.t          # (tried again after as long, if no other way)
                self._take_another_way()
        else:
            self._lc_stuck_since = None
        if self.goal_xy is None and not swapping:
            ahead = self.path.length - s_here
            if ahead < EXTEND_AT_M:
                self._extend_route()
            elif ahead < EXTEND_PREPARE_M and self._extension_asked != (id(self.route), self._rng.getstate()):
                self._prepare_extension()
        if self.route is not self._route_sent and not swapping:
            # SUMO's drivers see the ego coming at a junction only along its route there
            self._route_sent = self.route
            try:
                self.traffic.set_ego_route(self.route)
            except CosimError as e:
                log.info("SUMO did not take the ego's route: %s", e)
        if self.goal_xy is not None and math.hypot(st.x - self.goal_xy[0], st.y - self.goal_xy[1]) < 10.0 \
                and abs(st.speed) < 1.0:
            self.summary.arrived = True
        # streaming
        if self._replan_pending and not swapping and not self.path.lane_of[self._path_idx][0].startswith(":"):
            self.replan()                   # after a swap in a junction: now on the lane after it
        # (tiles of chunks a new window replaced are reloaded later, not in the frames that
        # carry the SUMO swap: they are loaded, only older)
        t_tiles = time.perf_counter()
        self.physics.update(st.x, st.y, self.keep_radius, stale=not self._swap_hold,
                            urgent_radius=self.cfg.sensor_range_m + self.world.tile_size * 0.5,
                            critical_radius=self.cfg.sensor_range_m + self.world.tile_size * 0.25,
                            spare=self.traffic.busy if pipelined else None)
        self.last_tiles_ms = (time.perf_counter() - t_tiles) * 1000.0
        if self.physics.replaced_now:
            self._lift_out(st)
        self._swap_hold = max(0, self._swap_hold - 1)
        self.streamer.step(st.x, st.y)
        if not self._covered(st.x, st.y):
            self.summary.sensor_range_violations += 1
        self._chunks_seen.add(self.world.frame.chunk_of(st.x, st.y))
        if self._last_xy is not None:
            self.summary.distance_m += math.hypot(st.x - self._last_xy[0], st.y - self._last_xy[1])
        self._last_xy = (st.x, st.y)
        if cfg.gui:
            import pybullet as pb

            pb.resetDebugVisualizerCamera(12.0, math.degrees(st.yaw) - 90.0, -18.0, [st.x, st.y, st.z + 1.0],
                                          physicsClientId=self.physics.client)
        frame_ms = (time.perf_counter() - t0) * 1000.0
        self._frame_ms.append(frame_ms)
        ego = self.ego_state()
        self._telemetry(ego, snap, frame_ms)
        self.summary.steps += 1
        if cfg.realtime:
            lag = self._wall0 + self.t - time.perf_counter()
            if lag > 0:
                time.sleep(lag)
        return ego

    def _covered(self, x, y) -> bool:
        """B8: every tile within the sensor range is built and loaded."""
        return self.physics.covered(x, y, self.cfg.sensor_range_m)

    def _prepare_extension(self, state=None):
        """Ask SUMO's side to draw the route's extension ahead, a little after each step
        (``SumoTraffic.prepare_extension``): the frame that extends the route then takes the
        answer instead of drawing it (60-130 ms in one frame on Helsinki)."""
        state = state or self._rng.getstate()
        self._extension_asked = (id(self.route), state)
        prepare = getattr(self.traffic, "prepare_extension", None)
        if prepare is None:
            return
        first = self._car_on_route()[3]
        try:
            prepare(self.route, first, state, start_lane=self.path.last_lane, lead_in=self.path.lead_in())
        except CosimError as e:
            log.info("could not prepare the route's extension: %s", e)

    def _car_on_route(self) -> tuple:
        """(the car's state, the lane of the path under it, that lane's edge, the index of
        that edge in the route: the route's last edge where the edge is not in it)."""
        st = self.vehicle.state()
        k, _, _ = self.path.project(st.x, st.y, self._path_idx)
        lane = self.path.lane_of[k][0]
        cur_edge = lane.rsplit("_", 1)[0]
        return st, lane, cur_edge, self.route.index(cur_edge) if cur_edge in self.route else len(self.route) - 1

    def turned_round(self, from_lane: str, to_lane: str) -> None:
        """The driver has turned the car round where the route turns back from ``from_lane``
        into ``to_lane`` (``cosim.turnround``): the route and the lane path go on from the car
        on ``to_lane``."""
        st = self.vehicle.state()
        a, b = from_lane.rsplit("_", 1)[0], to_lane.rsplit("_", 1)[0]
        first = self._car_on_route()[3]
        steps = [j for j in range(len(self.route) - 1) if self.route[j] == a and self.route[j + 1] == b]
        after = [j for j in steps if j >= first - 1]
        j = (after or steps or [None])[0]
        route = self.route[j + 1:] if j is not None else [b]
        pos = self.traffic.lane_pos(to_lane, st.x, st.y)
        try:
            path = self.traffic.lane_path(route, start_lane=to_lane, start_pos=pos)
        except (ValueError, CosimError) as e:
            log.info("no lane path on from %s after turning round (%s): planning a new route", to_lane, e)
            self.replan()
            return
        self.route, self.path = route, path
        self._path_idx = self.path.project(st.x, st.y, 0)[0]

    def _extend_route(self):
        if self.t < self._extend_retry_t:
            return
        last = self.route[-1]
        st, lane, cur_edge, first = self._car_on_route()
        try:
            at, more, state, tail = self.traffic.random_extension_path(self.route, first, self._rng.getstate(),
                                                                       start_lane=self.path.last_lane,
                                                                       lead_in=self.path.lead_in())
            if at < len(self.route) - 1:
                # every way on from the route's end has a turn the car cannot make: the way
                # out from an earlier edge, the path planned again from the car (once out of
                # a junction: tried again in a moment, the same draw)
                if lane.startswith(":"):
                    self._extend_retry_t = self.t + 0.5
                    return
                self._rng.setstate(state)
                route = self.route[first:at] + more
                pos = self.traffic.lane_pos(lane, st.x, st.y)
                self.path = self.traffic.lane_path(route, start_lane=lane, start_pos=pos)
                self.route = route
                self._path_idx = self.path.project(st.x, st.y, 0)[0]
                log.info("route cut back to %s: every way on from %s has a turn the car cannot make",
                         route[at - first], last)
                return
            self._rng.setstate(state)
        except CosimError as e:
            # the route's last edge leads nowhere (a dead end, the network's edge): a new route
            # from where the car is, else the car stops at the path's end; tried again in 10 s
            log.info("could not extend the route from %s (%s): planning a new one from the car", last, e)
            self._extend_retry_t = self.t + 1.0
            try:
                self.replan()
            except CosimError as e2:
                log.info("no new route either: %s", e2)
                self._extend_retry_t = self.t + 10.0
            return
        if len(more) < 2:
            # nothing to drive on to (every draw ended where it began): drawn again in 2 s,
            # not every frame (each draw can take 0.4 s), prepared meanwhile
            if self._no_way_on_said != last:
                self._no_way_on_said = last
                log.warning("t=%.1f s: no way on from road %s that the car can drive (each passes a tunnel, which "
                            "the world has none of, a lane narrower than the car or a turn it cannot make): it "
                            "stops at the end of its route", self.t, last)
            self._extend_retry_t = self.t + 2.0
            self._prepare_extension()
            return
        if cur_edge in self.route:
            i = self.route.index(cur_edge)
            self.route = self.route[i:] + more[1:]
        else:   # inside a junction: continue from the next edge
            self.route = self.route[-1:] + more[1:]
        try:
            s = self.traffic.sumo
            self.path = self.path.extended(s, more, tail=tail)     # keeps the geometry the car is on
            self._path_idx = self.path.project(st.x, st.y, 0, window=len(self.path.xy))[0]
        except (ValueError, CosimError) as e:
            log.info("could not extend the route: %s", e)

    def _lift_out(self, st) -> None:
        """Tiles near the car were replaced from a newer build this frame: if the road under
        the car is now higher than the car (the two builds' heights differ there), the car
        goes on top of it (``EgoVehicle.lift_out``) rather than stay caught in it."""
        near = set(self.world.tiles_within(st.x, st.y, LIFT_CHECK_M))
        if not near.intersection(self.physics.replaced_now):
            return
        rise = self.vehicle.lift_out()
        if rise > 0.0:
            self.summary.lifted_out += 1
            log.warning("t=%.1f s: the ground under the car came up %.2f m with a new tile; the car was "
                        "set on top of it", self.t, rise)

    def _check_held(self, st, throttle: float, brake: float) -> None:
        """Time the car stands still with the throttle on and no brake: something holds it (a
        step in the road, a body it pushes against). Counted for the summary, and said once a
        stretch passes HELD_WARN_S (a Portland car stood 1,071 s against a bridge deck's edge,
        and nothing said so)."""
        if abs(st.speed) < 0.1 and throttle >= HELD_THROTTLE and brake == 0.0:
            self._held_s += self.cfg.step_length_s
            s = self.summary
            s.held_s = round(s.held_s + self.cfg.step_length_s, 3)
            s.held_longest_s = round(max(s.held_longest_s, self._held_s), 3)
            if self._held_s >= HELD_WARN_S and not self._held_said:
                self._held_said = True
                lane = self.path.driven_lane(self._path_idx) if self.path is not None else ""
                log.warning("t=%.1f s: the car has stood still with the throttle at %.0f%% for %.0f s at "
                            "(%.1f, %.1f) on lane %s: something holds it", self.t, throttle * 100.0,
                            self._held_s, st.x, st.y, lane)
        else:
            self._held_s = 0.0
            self._held_said = False

    def _check_collisions(self):
        """Count and log the ego's collisions: a chassis contact with a mirrored actor, or a
        side-on contact (normal within 60 degrees of horizontal) with anything static."""
        import pybullet as pb

        cps = pb.getContactPoints(bodyA=self.vehicle.body_id, physicsClientId=self.physics.client)
        body_actor = self.mirror.body_actors()
        hit = None
        for c in cps:
            other = c[2]
            if other in body_actor:
                hit = ("actor", body_actor[other], c)
                break
            if abs(c[7][2]) < 0.5:
                hit = ("static", self.physics.body_kind(other), c)
        if hit and not getattr(self, "_in_contact", False):
            self.summary.ego_collisions += 1
            st = self.vehicle.state()
            ev = {"t": round(self.t, 2), "with": hit[0], "what": hit[1], "x": round(st.x, 1), "y": round(st.y, 1),
                  "speed_mps": round(st.speed, 2), "normal": [round(v, 2) for v in hit[2][7]]}
            snap = self.last_snapshot
            if hit[0] == "actor" and snap is not None:
                try:
                    j = snap.index(hit[1])
                    dx, dy = float(snap.x[j]) - st.x, float(snap.y[j]) - st.y
                    # where the actor is, seen from the car (0 = dead ahead, 90 = left), its speed
                    ev["actor_bearing_deg"] = round(math.degrees(math.remainder(math.atan2(dy, dx) - st.yaw,
                                                                                math.tau)))
                    ev["actor_speed_mps"] = round(float(snap.speed[j]), 2)
                    ev["actor_kind"] = str(snap.kind[j])
                except KeyError:
                    pass
            self.collision_log.append(ev)
            log.warning("ego collision at t=%.1f s with %s %s (%.1f m/s)", self.t, hit[0], hit[1], st.speed)
        self._in_contact = hit is not None

    def _telemetry(self, ego: EgoState, snap, frame_ms):
        v, p = self.mirror.counts()
        ts = self.traffic.stats_nowait if self._pipelined else self.traffic.stats
        s = self.summary
        s.max_vehicles = max(s.max_vehicles, ts.vehicles)
        s.max_persons = max(s.max_persons, ts.persons)
        s.max_mirrored = max(s.max_mirrored, v + p)
        if self.telemetry is None or self.telemetry.f is None:
            return
        th, br, stv = self.last_control
        self.telemetry.write({
            "t": round(self.t, 3), "lat": round(ego.lat, 7), "lon": round(ego.lon, 7), "alt_m": round(ego.alt_m, 3),
            "x": round(ego.x, 3), "y": round(ego.y, 3), "yaw_deg": round(math.degrees(ego.yaw), 2),
            "speed_mps": round(ego.speed, 3), "edge": ego.edge, "lane": ego.lane,
            "lateral_offset_m": round(ego.lateral_offset_m, 3), "on_road": ego.on_road,
            "vehicles": v, "persons": p, "chunks_loaded": len({(k[0], k[1]) for k in self.physics.tiles}),
            "tiles_loaded": len(self.physics.tiles), "frame_ms": round(frame_ms, 2),
            "throttle": round(th, 3), "brake": round(br, 3), "steer": round(stv, 3),
            "target_speed_mps": round(getattr(self.driver, "target_speed", float("nan")), 2),
            "reason": getattr(self.driver, "reason", None) or None,
            "mode": "manual" if self.manual is not None else "auto",
            "sumo_vehicles": ts.vehicles, "sumo_persons": ts.persons,
        })

    # --- SUMO network swaps ---------------------------------------------------------------
    def swap_traffic(self, net_file, routes, plan: dict | None = None) -> dict:
        """Move SUMO to another network (a new window), carrying the actors around the car.

        In-process, at once. With SUMO in its worker process and started ahead on the new
        network, in the next two frames without a wait: the next frame captures the actors
        (a few ms) and sends them to the new SUMO, which inserts them while that frame's
        physics runs on the old network's last state; the frame after takes the new ids and
        the route (``plan``, made ahead; else planned then). Returns the times taken now (ms)."""
        if self._pipelined and getattr(self.traffic, "preparing", None) is not None:
            self._swap_next = (net_file, list(routes), plan)
            self._swap_hold = 3
            return {}
        t0 = time.perf_counter()
        mapping = self.traffic.swap_network(net_file, routes, keep_radius=self.cfg.mirror_radius_m)
        self._routes = list(routes)          # what SUMO restarts on, should its worker crash
        t1 = time.perf_counter()
        self._swap_taken(mapping, plan, net_file)
        return {"sumo": round((t1 - t0) * 1000.0, 1), "replan": round((time.perf_counter() - t1) * 1000.0, 1)}

    def _swap_start(self, pose) -> bool:
        """The swap's first frame: True if SUMO's insert of the carried actors is also this
        frame's step (the ego at `pose`)."""
        t0 = time.perf_counter()
        net_file, routes, plan = self._swap_next
        self._swap_next = None
        stepped = self.traffic.swap_begin(net_file, routes, keep_radius=self.cfg.mirror_radius_m, ego_pose=pose)
        self._routes = routes
        self._swap_adopting = (plan, net_file)
        self._swap_note("capture", t0)
        return stepped

    def _swap_adopted(self):
        t0 = time.perf_counter()
        (plan, net_file), self._swap_adopting = self._swap_adopting, None
        self._swap_taken(self.traffic.swap_end(), plan, net_file)
        self._swap_note("replan", t0)

    def _swap_taken(self, mapping: dict, plan, net_file):
        """The carried actors keep their bodies under their new ids; the route is taken."""
        self.mirror.rekey(mapping)
        self._expect_network()
        self.replan(plan)
        log.info("SUMO swapped to %s, %d actors kept", Path(net_file).parent.parent.name, len(mapping))

    def _swap_note(self, phase: str, t0: float):
        """The time a swap took in this frame, in its phase (ms, the streamer's record)."""
        phases = self.streamer.swap_phases_ms if self.streamer is not None else None
        if phases:
            phases[-1][phase] = round((time.perf_counter() - t0) * 1000.0, 1)
            self.streamer.swap_ms[-1] = round(sum(phases[-1].values()), 1)

    def replan_args(self) -> tuple | None:
        """Arguments of ``SumoTraffic.replan_from`` for the car where it is: its lanes ahead on
        the path, its pose, its route; None inside a junction (re-plan once past it: the old
        path's geometry holds until then)."""
        st = self.vehicle.state()
        k, _, _ = self.path.project(st.x, st.y, self._path_idx)
        if self.path.lane_of[k][0].startswith(":"):
            return None
        lanes = list(dict.fromkeys(ln for ln, _ in self.path.lane_of[k:]))
        return (lanes, st.x, st.y, st.yaw), dict(route=self.route, beyond_ok=True, **self._plan_kw())

    def _take_another_way(self) -> bool:
        """The car has stood LANE_CHANGE_GIVE_UP_S for a lane change its route needs: a route
        on from the lane it holds to, whose next road that lane leads to itself (to the goal
        the fastest such way, else at random), as a driver takes another street rather than
        wait in a jam for a gap that does not come. False (the route kept) where there is none."""
        st = self.vehicle.state()
        k, _, _ = self.path.project(st.x, st.y, self._path_idx)
        lane = self.path.driven_lane(k)
        if not lane or lane.startswith(":"):
            return False
        try:
            plan = self.traffic.plan_route(lane, 0.0, keep_lane=True, at_xy=(st.x, st.y), beyond_ok=True,
                                           **self._plan_kw())
            lane = plan["lane"]
        except CosimError as e:
            log.info("no other way from %s: %s", lane, e)
            return False
        if not plan["route"] or plan["path"] is None:
            log.info("no other way from %s to the goal", lane)
            return False
        log.info("t=%.1f s: no gap for the lane change in %.0f s: another way from %s (%s)", self.t,
                 LANE_CHANGE_GIVE_UP_S, lane, " ".join(plan["route"][:3]))
        self._apply_plan(plan)
        self._path_idx = self.path.project(st.x, st.y, 0)[0]
        self.summary.other_ways += 1
        return True

    def replan(self, plan: dict | None = None):
        """Plan the route again from where the car is (after a SUMO network swap), from the
        car's own position, so the new path starts under the car; inside a junction, once past
        it. ``plan``: one already made (ahead of the swap, from where the car was a moment
        ago) to take instead."""
        if plan is None:
            args = self.replan_args()
            self._replan_pending = args is None
            if args is None:
                return
            plan = self.traffic.replan_from(*args[0], **args[1])
        self._apply_plan(plan)
        st = self.vehicle.state()
        self._path_idx = self.path.project(st.x, st.y, 0)[0]

    # --- live controls (GUI, keyboard, scripts) -------------------------------------------
    def set_speed(self, mps: float):
        """Change the set speed while driving."""
        from .config import MAX_SPEED_MPS

        v = _number(mps, "speed")
        if not 0 <= v <= MAX_SPEED_MPS:
            raise InputError(f"speed {mps} m/s is out of range (0..{MAX_SPEED_MPS:.0f})")
        self.cfg.speed_mps = v

    def set_goal(self, lat: float | None, lon: float | None = None) -> dict:
        """Route from where the car is now to a GPS coordinate (None: drive on at random).
        Returns the route length and ETA."""
        from netgen.frame import check_latlon

        self._require_setup("set_goal")
        goal = None if lat is None else check_latlon(lat, lon, "goal")
        st = self.vehicle.state()
        k, s_here, _ = self.path.project(st.x, st.y, self._path_idx)
        lane = self.path.lane_of[k][0]
        if lane.startswith(":"):
            # in a junction: plan from the lane it leads into
            lane = self.traffic.sumo.lane.getLinks(lane)[0][0]
            pos = 0.0
        else:
            pos = max(0.0, self.traffic.lane_pos(lane, st.x, st.y))
        # (a goal that cannot be taken leaves the car on its way to the one it had: a second,
        # rejected destination used to drop the first, and the car never arrived)
        old = self.cfg.goal, self.goal_xy, self.goal_beyond
        self.cfg.goal = goal
        self.goal_xy = None
        try:
            self._plan_route(lane, pos)
        except CosimError:
            self.cfg.goal, self.goal_xy, self.goal_beyond = old
            raise
        if goal is None:                # no goal: no route length, ETA or arrival to report
            for key in ("route_length_m", "eta_s", "goal_snap_m"):
                self.snap_info.pop(key, None)
            self._goal_on_path = None
            self.summary.arrived = None
        return {k: self.snap_info.get(k) for k in ("route_length_m", "eta_s", "goal_snap_m")}

    def set_manual(self, control: tuple | None):
        """(throttle, brake, steer) to drive by hand, or None to give control back to the driver."""
        if control is None:
            if self.manual is not None and hasattr(self.driver, "speed"):
                self.driver.speed.reset()
            self.manual = None
        else:
            try:
                t, b, st = (float(v) for v in control)
            except (TypeError, ValueError):
                raise InputError(f"manual control must be (throttle, brake, steer), got {control!r}") from None
            if not all(math.isfinite(v) for v in (t, b, st)):
                # (NaN passed the clamps below as full throttle, brake and lock)
                raise InputError(f"manual control must be finite numbers, got {control!r}")
            self.manual = (max(0.0, min(1.0, t)), max(0.0, min(1.0, b)), max(-1.0, min(1.0, st)))

    def camera_image(self, width: int = 480, height: int = 270, view: str = "chase"):
        """An RGB image (height, width, 3) from PyBullet's camera: 'chase' (behind and above
        the car) or 'driver' (from the windscreen, looking ahead). The world is drawn only when
        its visual meshes are loaded (``SimConfig(render=True)`` or ``gui=True``); a headless
        run loads none (they cost time and memory), and its picture shows the cars alone (a
        warning says so, once)."""
        self._require_setup("camera_image")
        for what, v in (("width", width), ("height", height)):
            # (a negative size aborted the whole process inside PyBullet: std::bad_alloc)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 1 <= v <= MAX_CAMERA_PX:
                raise InputError(f"camera image {what} must be a whole number of pixels from 1 to "
                                 f"{MAX_CAMERA_PX}, got {v!r}")
        if view not in ("chase", "driver"):
            raise InputError(f"camera view must be 'chase' or 'driver', got {view!r}")
        if not self.physics.visuals and not self._warned_no_visuals:
            self._warned_no_visuals = True
            log.warning("camera_image: this simulation loaded no visual meshes, so the picture shows "
                        "no roads, terrain or buildings; set SimConfig(render=True) to draw them")
        st = self.vehicle.state()
        c, s = math.cos(st.yaw), math.sin(st.yaw)
        if view == "driver":
            # from just ahead of the windscreen, above the bonnet, along the car's pitch (a camera
            # inside the cabin, as before, saw the inside of its roof and windscreen)
            fx, fy, fz = c * math.cos(st.pitch), s * math.cos(st.pitch), -math.sin(st.pitch)
            eye = [st.x + DRIVER_CAMERA[0] * fx, st.y + DRIVER_CAMERA[0] * fy,
                   st.z + DRIVER_CAMERA[1] + DRIVER_CAMERA[0] * fz]
            target = [eye[0] + 30 * fx, eye[1] + 30 * fy, eye[2] + 30 * fz - 0.2]
        else:
            eye = [st.x - 12 * c, st.y - 12 * s, st.z + 5.0]
            target = [st.x + 8 * c, st.y + 8 * s, st.z + 1.0]
        self.vehicle.sync_visuals()
        return self.physics.camera_image(eye, target, width, height, fov=70.0, far=self.cfg.sensor_range_m * 2)

    def actors(self) -> dict:
        """The mirrored actors as plain lists: ids, kind, x, y, yaw, length, width, speed."""
        snap = self.last_snapshot
        if snap is None:
            return {"ids": [], "kind": [], "x": [], "y": [], "yaw": [], "length": [], "width": [], "speed": []}
        return {"ids": list(snap.ids), "kind": list(snap.kind), "x": snap.x.tolist(), "y": snap.y.tolist(),
                "yaw": snap.yaw.tolist(), "length": snap.length.tolist(), "width": snap.width.tolist(),
                "speed": snap.speed.tolist()}

    def traffic_lights(self) -> dict:
        """State string of every traffic light (SUMO's letters: r, y, G, g, ...)."""
        self._require_setup("traffic_lights")
        return self.traffic.tls_states()

    # ------------------------------------------------------------------------------------
    def run(self, duration_s: float | None = None, on_step=None) -> Summary:
        duration = self.cfg.duration_s if duration_s is None else duration_s
        n = int(round(duration / self.cfg.step_length_s))
        for i in range(n):
            ego = self.step()
            if on_step:
                on_step(self, ego)
            if self.summary.arrived:
                break
        return self.finish()

    def finish(self) -> Summary:
        if self.telemetry is not None:
            self.telemetry.flush()      # a full disk is the run's error, not a teardown warning
        s = self.summary
        s.sim_time_s = round(self.t, 3)
        s.wall_time_s = round(time.perf_counter() - self._wall0, 3) if self._wall0 is not None else 0.0
        s.real_time_factor = round(s.sim_time_s / s.wall_time_s, 2) if s.wall_time_s > 0 else 0.0
        if self.physics is not None:
            s.tiles_loaded, s.tiles_unloaded = self.physics.loads, self.physics.unloads
        if self.traffic is not None:
            if self._pipelined:
                self.traffic.sync()
            s.sumo_collisions, s.sumo_teleports = self.traffic.stats.collisions, self.traffic.stats.teleports
            s.persons_held = self.traffic.stats.persons_held
            s.standoffs_released = getattr(self.traffic.stats, "released", 0)
            s.swap_actors_lost = self._lost_before_restart + getattr(self.traffic.stats, "swap_lost", 0)
        stats = getattr(self.driver, "stats", None)
        s.turnarounds = getattr(stats, "turnarounds", 0)
        s.no_room_to_turn = getattr(stats, "no_room_to_turn", 0)
        s.backoffs = getattr(stats, "backoffs", 0)
        s.chunks_visited = len(self._chunks_seen)
        if self._frame_ms:
            f = np.array(self._frame_ms)
            s.frame_ms_median = round(float(np.median(f)), 2)
            s.frame_ms_p999 = round(float(np.percentile(f, 99.9)), 2)
            s.frame_ms_max = round(float(f.max()), 2)
        if self.mirror is not None:
            s.max_mirror_error_m = round(self.mirror.max_error_m, 4)
        if self.streamer is not None:
            s.windows_built = len(self.streamer.build_s)
            s.network_swaps = self.streamer.swaps
            s.swap_ms_max = max(self.streamer.swap_ms, default=0.0)
            s.swap_wait_s = round(sum(self.streamer.waited_s), 2)
            s.notes = list(self.streamer.errors)
        s.notes = list(s.notes) + [n for n in self._restart_notes if n not in s.notes]
        return s

    def teardown(self):
        for comp in ("streamer", "telemetry", "physics", "traffic"):
            c = getattr(self, comp, None)
            if c is not None:
                try:
                    c.teardown()
                except Exception as e:  # teardown must not mask the original error
                    log.warning("teardown of %s: %s", comp, e)
                setattr(self, comp, None)
        if self._gc_frozen:
            gc.unfreeze()
            self._gc_frozen = False
        self._setup_done = False

    def __enter__(self):
        return self.setup()

    def __exit__(self, *exc):
        self.teardown()
