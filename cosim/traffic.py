"""SUMO traffic as a co-simulation component (libsumo by default, TraCI selectable).

``SumoTraffic`` owns one SUMO run: routing, traffic lights, other cars and pedestrians. The
orchestrating loop calls ``setup()`` once, then per frame ``set_ego_pose(...)``, ``step()`` and
``actors_near(...)``, and ``teardown()`` at the end (MetaDrive-manager / SMARTS-provider style).

Frames and conventions
----------------------
SUMO's network coordinates *are* world metres (netconvert ran with the world's tmerc projection
and ``--offset.disable-normalization``). SUMO reports a vehicle's position at its FRONT bumper
and its heading as degrees, 0 = north, clockwise. The world uses body centres and yaw in
radians, 0 = +x (east), counter-clockwise. The small pure functions below convert between the
two; everything this module returns is in world convention (centre, yaw), and ``set_ego_pose``
takes world centre and yaw.

The ego
-------
``add_ego`` puts a vehicle of the ego's size into SUMO before the first ``moveToXY`` (moving a
vehicle that SUMO does not know fails). Each frame ``set_ego_pose`` calls
``vehicle.moveToXY(keepRoute=2)``: SUMO puts the ego exactly there, maps it onto the nearest lane
(replacing its route when it leaves it) so that SUMO's cars follow / brake for it and pedestrians
see it; its speed mode and lane-change mode are 0 so SUMO never fights the pose, and after each
step its speed is set to the physics speed (``setPreviousSpeed``), not the displacement SUMO
derives. The ego never appears in actor lists or counts.

Actors
------
``actors_near`` reads one context subscription on the ego (vehicles and persons, all variables
in one batch per step) instead of per-actor getters; without an ego a hidden POI is the anchor.

libsumo runs one simulation per process: a second ``setup()`` while another SumoTraffic runs on
libsumo raises SimulationError. SUMO's own errors (missing or corrupt net, bad route file) come
out as one-line SimulationError messages taken from SUMO's error log.
"""
from __future__ import annotations

import contextlib
import dataclasses
import glob
import itertools
import logging
import math
import os
import random
import re
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from netgen.errors import SimulationError

from .component import Component
from .config import LANE_CHANGE_S
from .driving import _onto_segments, _via_lanes, run_steps as _run_steps, undrivable_steps, without_turnarounds

log = logging.getLogger(__name__)

EGO_ID = "ego"
TMP_PREFIX = "cosim-sumo-"      # SUMO's folder for its logs: <tmp>/cosim-sumo-<pid>-*
_STALE_SWEPT = False            # remove_stale_tmp has run in this process
PROBE_ID = "cosim_probe"
VEHICLE_RECOUNT_STEPS = 10   # SUMO's vehicles are counted every this many steps (in between: departed - arrived)
# m: front-bumper anchors vs centre distances (half a bus, 6 m, + half the ego, 2.25 m, + 1 m,
# and a little for the ego's front in SUMO versus its centre asked about: _context_results
# checks). The context's cost in SUMO's step goes with the actors in it (20 m: 10 % more)
CONTEXT_MARGIN = 12.0
TRACI_START_TIMEOUT_S = 120   # seconds a TraCI SUMO has to load its network and open its port
DEFAULT_CONTEXT_RADIUS = 150.0
EGO_JOINT_NUDGE_M = 0.3       # a front bumper in the gap at a lane joint is mapped this far on (_across_joint)
STANDOFF_CHAIN = 2            # release_standoff: standing vehicles between the one taken out and the ego
STANDOFF_CREEP_MPS = 0.5      # standoffs: slower than this stands (the chain to the ego, the car and what it waits for)
EGO_MATCH_RADIUS_M = 15.0      # the ego is mapped onto a lane within this distance, else off the network
PERSON_YIELD_RANGE_M = 15.0    # pedestrians this near the ego are checked (see _persons_yield)
PERSON_YIELD_MARGIN_M = 0.5    # they stop this far outside the ego's footprint
PERSON_YIELD_HORIZON = (0.25, 0.5, 0.75, 1.0)   # s ahead at which their paths are tested
PERSON_DIMS = (0.215, 0.478, 1.719)  # SUMO's default pedestrian type: length, width, height (m)
#: a goal beyond a streamed window's roads whose nearest road there cannot be reached: the
#: nearest one the car reaches within this much further (m), driving towards the goal
BEYOND_SEARCH_M = 300.0
EGO_UNSTICK_M = 0.015       # see _after_step: a long-waiting ego jitters this much in SUMO

_LIBSUMO_OWNER = None   # the SumoTraffic running on libsumo in this process, if any


@contextlib.contextmanager
def _stderr_to(path: str):
    """Redirect the process's stderr (fd 2, where libsumo's C++ code writes) into a file."""
    try:
        sys.stderr.flush()
    except Exception:
        pass
    saved = os.dup(2)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        os.dup2(fd, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(fd)


def _forward_text(path: str) -> None:
    try:
        with open(path, encoding="utf-8", errors="replace") as f:
            text = f.read().strip()
    except OSError:
        return
    for line in text.splitlines():
        if line.strip() and "proj.db" not in line:
            log.info("SUMO: %s", line.strip())


# --- pure conversions -----------------------------------------------------------------------
def sumo_angle_to_yaw(angle_deg):
    """SUMO heading (degrees, 0 = north, clockwise) -> world yaw (radians, 0 = east, CCW),
    wrapped to [-pi, pi). Works on scalars and arrays (a scalar in plain float arithmetic,
    the same operations: SUMO's worker converts one every step)."""
    if isinstance(angle_deg, (float, int)):
        return (math.radians(90.0 - angle_deg) + math.pi) % (2.0 * math.pi) - math.pi
    yaw = np.radians(90.0 - np.asarray(angle_deg, dtype=float))
    yaw = (yaw + np.pi) % (2.0 * np.pi) - np.pi
    return float(yaw) if np.ndim(yaw) == 0 else yaw


def yaw_to_sumo_angle(yaw_rad):
    """World yaw (radians, 0 = east, CCW) -> SUMO heading (degrees in [0, 360), 0 = north, CW)."""
    if isinstance(yaw_rad, (float, int)):
        return (90.0 - math.degrees(yaw_rad)) % 360.0
    a = (90.0 - np.degrees(np.asarray(yaw_rad, dtype=float))) % 360.0
    return float(a) if np.ndim(a) == 0 else a


def _boxes_overlap(a, b, margin: float = 0.0) -> bool:
    """Do two oriented rectangles (x, y, yaw in rad, length, width) overlap, or come within
    ``margin`` of each other? Separating-axis test."""
    ax, ay, ayaw, al, aw = a
    bx, by, byaw, bl, bw = b
    dx, dy = bx - ax, by - ay
    if dx * dx + dy * dy > ((al + bl) * 0.5 + aw + bw + margin) ** 2:
        return False

    def half(yaw, length, width, ux, uy):
        c, s = math.cos(yaw), math.sin(yaw)
        return 0.5 * length * abs(c * ux + s * uy) + 0.5 * width * abs(-s * ux + c * uy)

    for yaw in (ayaw, byaw):
        c, s = math.cos(yaw), math.sin(yaw)
        for ux, uy in ((c, s), (-s, c)):
            if abs(dx * ux + dy * uy) > half(ayaw, al, aw, ux, uy) + half(byaw, bl, bw, ux, uy) + margin:
                return False
    return True


def carried_id(vid: str) -> str:
    """A vehicle's id without the generation a network swap gives the vehicles it carries into
    the new SUMO (``swap_adopt``: "veh973" -> "veh973~1"; "veh973~1" -> "veh973~2")."""
    return vid.split("~", 1)[0]


def _cannot_stop(gap: float, closing: float) -> bool:
    """Whether a vehicle ``gap`` m behind another that appears at once, closing on it at
    ``closing`` m/s, cannot stop before it at a normal deceleration (EGO_INSERT_DECEL, 1 m to
    spare): SUMO inserts its own vehicles only where the follower can brake, and the ego and
    the vehicles carried across a swap appear without that check."""
    return gap < closing * closing / (2 * EGO_INSERT_DECEL) + 1.0


def _polyline_distance(P, x: float, y: float) -> float:
    """Distance from (x, y) to the polyline `P` (n >= 2 points)."""
    _, _, _, ex, ey, _ = _onto_segments(P[:-1], np.diff(P, axis=0), x, y)
    return float(np.sqrt(np.min(ex * ex + ey * ey)))


def front_to_center(x, y, angle_deg, length):
    """SUMO front-bumper position -> body centre: centre = front - heading * length / 2."""
    if isinstance(angle_deg, (float, int)) and isinstance(x, (float, int)) and isinstance(y, (float, int)) \
            and isinstance(length, (float, int)):
        a, half = math.radians(angle_deg), 0.5 * length
        return float(x - math.sin(a) * half), float(y - math.cos(a) * half)
    a = np.radians(np.asarray(angle_deg, dtype=float))
    half = 0.5 * np.asarray(length, dtype=float)
    cx = np.asarray(x, dtype=float) - np.sin(a) * half
    cy = np.asarray(y, dtype=float) - np.cos(a) * half
    if np.ndim(cx) == 0:
        return float(cx), float(cy)
    return cx, cy


def center_to_front(x, y, angle_deg, length):
    """Body centre -> SUMO front-bumper position (inverse of :func:`front_to_center`)."""
    if isinstance(length, (float, int)):
        return front_to_center(x, y, angle_deg, -length)
    return front_to_center(x, y, np.asarray(angle_deg, dtype=float), -np.asarray(length, dtype=float))


# --- snapshot -------------------------------------------------------------------------------
@dataclass
class ActorsSnapshot:
    """Actors near a point, as parallel numpy arrays (world convention: centre, yaw)."""
    time: float
    ids: np.ndarray        # str (object)
    kind: np.ndarray       # str: SUMO vehicle class ("passenger", "truck", "bus", ...) or "person"
    x: np.ndarray          # body centre, m
    y: np.ndarray
    yaw: np.ndarray        # rad, 0 = east, CCW
    length: np.ndarray     # m
    width: np.ndarray
    height: np.ndarray
    speed: np.ndarray      # m/s
    slope: np.ndarray      # degrees, positive uphill (pitch)
    lane: np.ndarray | None = None   # str: SUMO lane id ("" where not known); None: unknown

    def __len__(self) -> int:
        return len(self.ids)

    @property
    def is_person(self) -> np.ndarray:
        return self.kind == "person"

    def within(self, x: float, y: float, radius: float) -> "ActorsSnapshot":
        """The actors whose centre is within ``radius`` of (x, y)."""
        return self.subset(np.hypot(self.x - x, self.y - y) <= radius)

    def subset(self, keep: np.ndarray) -> "ActorsSnapshot":
        """The actors selected by a boolean mask (or index array)."""
        return ActorsSnapshot(self.time, self.ids[keep], self.kind[keep], self.x[keep], self.y[keep],
                              self.yaw[keep], self.length[keep], self.width[keep], self.height[keep],
                              self.speed[keep], self.slope[keep],
                              None if self.lane is None else self.lane[keep])

    def above_ground(self, tunnels) -> "ActorsSnapshot":
        """Without the actors on a lane of a tunnel edge (``tunnels``: edge ids): they drive
        or walk under the ground, where the world has nothing."""
        if not tunnels or self.lane is None or not len(self.ids):
            return self
        keep = np.fromiter((not ln or ln[:ln.rfind("_")] not in tunnels for ln in self.lane.tolist()),
                           dtype=bool, count=len(self.ids))
        return self if keep.all() else self.subset(keep)

    def index(self, actor_id: str) -> int:
        hits = np.nonzero(self.ids == actor_id)[0]
        if len(hits) == 0:
            raise KeyError(actor_id)
        return int(hits[0])

    @classmethod
    def empty(cls, time: float = 0.0) -> "ActorsSnapshot":
        z = np.zeros(0)
        return cls(time, np.zeros(0, dtype=object), np.zeros(0, dtype=object), z, z.copy(),
                   z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), z.copy(), np.zeros(0, dtype=object))


# (TraCI's variable ids, the same in libsumo and traci: the keys of the context's results)
_VAR_SPEED, _VAR_SLOPE, _VAR_POSITION, _VAR_ANGLE, _VAR_TYPE, _VAR_LANE_ID, _VAR_VEHICLE = 0x40, 0x36, 0x42, 0x43, 0x4F, 0x51, 0xC3


@dataclass
class ActorsContext:
    """The actors around the ego as SUMO's context subscription gives them (``res``: id ->
    {variable: value}), with the class and size of their types (``types``: (is a vehicle,
    type id) -> (class, length, width, height)) and speeds to report instead of SUMO's
    (``speeds``). Made where SUMO runs (``SumoTraffic.actors_context``); :meth:`snapshot`
    turns it into the snapshot wherever it is needed."""
    time: float
    res: dict
    types: dict
    speeds: dict | None = None

    def snapshot(self, x: float, y: float, radius: float) -> ActorsSnapshot:
        """The vehicles and walking persons whose body centre is within ``radius`` m of (x, y),
        the ego and persons riding in vehicles left out."""
        types, speeds = self.types, self.speeds
        ids, kind, lanes, rows = [], [], [], []
        for aid, v in self.res.items():
            pos = v.get(_VAR_POSITION)
            if pos is None or aid == EGO_ID:
                continue
            riding = v.get(_VAR_VEHICLE)     # None: a vehicle; "": a person walking
            if riding:
                continue                     # riding: drawn as part of the vehicle
            info = types[(riding is None, v[_VAR_TYPE])]
            ids.append(aid)
            kind.append(info[0])
            lanes.append(v.get(_VAR_LANE_ID, ""))   # (for a person: a sidewalk, walking area or crossing)
            speed = v[_VAR_SPEED] if speeds is None else speeds.get(aid, v[_VAR_SPEED])
            rows.append((pos[0], pos[1], v[_VAR_ANGLE], info[1], info[2], info[3], speed, v.get(_VAR_SLOPE, 0.0)))
        if not rows:
            return ActorsSnapshot.empty(self.time)
        a = np.array(rows, dtype=float).T
        cx, cy = front_to_center(a[0], a[1], a[2], a[3])
        keep = (cx - x) ** 2 + (cy - y) ** 2 <= radius * radius
        ids, kind, lanes = (np.array(v, dtype=object) for v in (ids, kind, lanes))
        if not keep.all():
            a, cx, cy, ids, kind, lanes = a[:, keep], cx[keep], cy[keep], ids[keep], kind[keep], lanes[keep]
        return ActorsSnapshot(self.time, ids, kind, cx, cy, sumo_angle_to_yaw(a[2]), a[3], a[4], a[5], a[6],
                              a[7], lanes)


@dataclass
class TrafficStats:
    """Per-step counts and accumulated totals (never fatal)."""
    steps: int = 0
    vehicles: int = 0          # in the simulation now (ego excluded)
    persons: int = 0           # walking now (departed, not arrived)
    teleports: int = 0         # accumulated teleport starts
    collisions: int = 0        # accumulated distinct collisions (collider, victim)
    max_vehicles: int = 0
    max_persons: int = 0
    swap_dropped: int = 0      # carried persons a swap had to drop (see _drop_stranded_persons)
    swap_lost: int = 0         # actors near the ego at a swap that the new SUMO does not have (these too)
    persons_held: int = 0      # times a pedestrian stopped rather than walk into the ego (_persons_yield)
    released: int = 0          # vehicles taken out after a standoff with the ego (release_standoff)
    _seen_collisions: set = field(default_factory=set, repr=False)


EGO_INSERT_DECEL = 4.5     # m/s², a vehicle behind the ego as it goes into SUMO must stop at this (_clear_ego_footprint)
SWAP_WARM_S = 1.0          # a new SUMO runs this long before actors are carried into it
KEEP_ROUTE_PREFIX = "cosim_keep_"   # the routes of the vehicles carried across a swap
#: how many edges of the ego's route ahead are watched for vehicles SUMO inserts in its way
#: (_drop_inserted_ahead)
INSERT_AHEAD_EDGES = 8
FOLLOWER_LOOK_M = 100.0     # how far behind a carried vehicle its follower is looked for at a swap
#: s of the route graph worked out after each step where SUMO runs in the caller's process
#: (warm_routes; SUMO's worker does it while it waits for a request)
EXTENSION_STEP_BUDGET_S = 0.001
#: pieces of a prepared route extension drawn after each step (prepare_extension; a piece: a
#: destination's route asked of SUMO, or up to SEARCH_PIECE edges of a search, or a turn
#: measured). Counted, not timed: drawn at the same steps in every run, a run repeats exactly (a
#: draw paced by the clock, in the worker's idle time too, changed SUMO's traffic from run to run
#: of the same seed, though every draw gave the same route: 368-409 m driven in 60 s). SUMO's
#: worker does them before it can take the next step: 8 pieces made 13 steps of Helsinki's
#: bench 0.3-2.9 ms longer, 2 pieces 51 steps 0.1-1.8 ms, one piece 101 steps 0.05-1.6 ms
#: (18 ms in all; the draw spans 10 s, within the 480 m between cosim.sim's EXTEND_PREPARE_M
#: and EXTEND_AT_M at up to 48 m/s; a draw not done by then is finished in one frame)
EXTENSION_STEP_PIECES = 1
# the ego's body reaching this far into a neighbouring lane makes that lane's follower (within
# STRADDLE_LOOK_M) keep STRADDLE_GAP_M behind it (_straddle_yield)
STRADDLE_M = 0.3
STRADDLE_AHEAD_S = 1.0     # ... or will reach, going on sideways as it moves now for this long
STRADDLE_LOOK_M = 60.0
STRADDLE_GAP_M = 2.0
SWAP_ROOM_MARGIN_M = 20.0    # the new SUMO's own actors this far beyond the kept ones make room


@dataclass
class _Kept:
    """State of one actor carried across swap_network."""
    old_id: str
    person: bool
    type_id: str
    type_params: dict
    x: float              # SUMO front position
    y: float
    angle: float          # SUMO degrees
    speed: float
    edge: str
    lane: int
    lane_pos: float
    edges: list
    arrival_pos: float | None = None
    lane_id: str = ""
    lane_length: float = -1.0    # of lane_id: the same lane in the next network has the same length


#: SumoTraffic's readings of a whole network that the autopilot makes at once on a new one
#: (each cached per network, ``_net_key``): read ahead of a swap (``warm_network``) and sent to
#: the main process right after it (``TrafficProcess.swap_begin``), asked ahead every frame
#: (``Autopilot._expect``)
NETWORK_READS = ("incoming_lanes", "via_lanes", "edge_ends")


def _plan(lane: str, pos: float, rng_state) -> dict:
    """A route plan (``SumoTraffic.plan_route``) before its route, path and goal are known."""
    return dict(lane=lane, pos=float(pos), goal=None, rng_state=rng_state)


def opposite_edge(edge: str) -> str:
    """The id of an OSM road's edge in the other direction: "X" and "-X"."""
    return edge[1:] if edge.startswith("-") else "-" + edge


def reverses(ends: dict, edge: str, other: str) -> bool:
    """Is ``other`` ``edge``'s road in the other direction? "-X" for "X", or, where the network
    has no "-X", an edge between the same two junctions the other way (``ends``: edge -> (from,
    to junction), ``SumoTraffic.edge_ends``): OSM can draw a street's two directions as two ways
    on one line (Helsinki's Mikonkatu, 199191048#1 and -199191047#0, whose dead end's U-turn
    the car did not turn round at: "goal unreachable")."""
    opp = opposite_edge(edge)
    if other == opp:
        return True
    if opp in ends:
        return False
    a, b = ends.get(edge), ends.get(other)
    return a is not None and b is not None and other != edge and b == (a[1], a[0])


def lane_change_args(seconds: float) -> list:
    """SUMO's options for lane changes over ``seconds`` (0: SUMO's default, within one step);
    also the benchmarks' SUMO alone."""
    return ["--lanechange.duration", f"{seconds:g}"] if seconds > 0 else []


# --- the component --------------------------------------------------------------------------
def _plain_points(points) -> tuple:
    """Points as a tuple of (x, y) float tuples (hashable: part of a prepared extension's key)."""
    return tuple((float(p[0]), float(p[1])) for p in points)


class SumoTraffic(Component):
    """One SUMO run: setup() / step() / teardown(), ego injection, actors, traffic lights."""

    def __init__(self, net_file, route_files: Sequence = (), step_length: float = 0.1,
                 seed: int = 0, backend: str = "libsumo", gui: bool = False,
                 extra_args: Iterable[str] = (), time_to_teleport: float = 120.0,
                 warnings: bool = False, persons_yield: bool = True,
                 lane_change_s: float = LANE_CHANGE_S):
        if backend not in ("libsumo", "traci"):
            raise SimulationError(f"unknown SUMO backend {backend!r} (use libsumo or traci)")
        if gui and backend != "traci":
            raise SimulationError("sumo-gui needs backend='traci' (libsumo cannot drive a GUI)")
        if not (0.001 <= float(step_length) <= 10.0):
            raise SimulationError(f"SUMO step length {step_length} s is out of range (0.001..10)")
        if not (0.0 <= float(lane_change_s) <= 20.0):
            raise SimulationError(f"lane change duration {lane_change_s} s is out of range (0..20)")
        self.net_file = Path(net_file)
        self._extents: dict = {}            # net file -> its world's extent_m (_in_window)
        if isinstance(route_files, (str, os.PathLike)):
            route_files = [route_files]
        self.route_files = [Path(p) for p in route_files]
        self.step_length = float(step_length)
        self.lane_change_s = float(lane_change_s)
        self.seed = int(seed)
        self.backend = backend
        self.gui = bool(gui)
        self.extra_args = [str(a) for a in extra_args]
        self.time_to_teleport = float(time_to_teleport)
        self.warnings = bool(warnings)
        self.persons_yield = bool(persons_yield)
        self.stats = TrafficStats()
        self._sim = None           # libsumo module or a traci Connection
        self._label = None
        self._tmpdir: str | None = None
        self._time_offset = 0.0
        self._generation = 0
        self._loads = 0            # SUMO started on a network (setup): what network caches are of
        self._extension = None     # a route extension drawn a little after each step (prepare_extension)
        self._warm = None          # the route graph worked out a little after each step (warm_routes)
        # SUMO's worker process: the route graph in background_work only, and work_after_step
        # called by the worker once it has answered a step
        self.work_when_idle = False
        self._reset_run_state()
        self._ego_spec: dict | None = None

    # --- lifecycle ----------------------------------------------------------------------
    def _reset_run_state(self):
        self._ego_in_sim = False
        self._ego_clear_due = False
        self._ego_added = False
        self._ego_pending_speed: float | None = None
        self._ego_off_network = False
        self._ego_unstick = False
        self._unstick_sign = 1.0
        self._ego_route: tuple = ()         # (set_ego_route) the edges the ego will drive
        self._ego_route_road = ""           # the road the route was last checked on
        self._ego_route_i = 0               # and where on the route that was
        self._ctx_anchor: str | None = None
        self._ctx_radius = DEFAULT_CONTEXT_RADIUS
        self._probe_xy: tuple | None = None
        self._probe_radius: float | None = None
        self._tls_ids: list[str] = []
        self._tls_fresh: dict[str, str] = {}
        self._lane_tls: dict[str, tuple[str, int]] = {}
        self._exc: tuple = (Exception,)
        self._dims_cache: dict[str, tuple[float, float, float]] = {}
        self._vclass_cache: dict[str, tuple[str, float, float, float]] = {}
        self._held: dict[str, float] = {}  # pedestrians stopped for the ego: id -> their own pace
        self._straddle_held: set = set()    # vehicles kept behind an ego that straddles their lane
        self._straddle_lat: tuple = ("", 0.0)   # the ego's lane and lateral position at the last step
        self._lane_ends: dict = {}               # lane -> its last segment and its next lanes' first (_across_joint)
        self._lane_widths: dict = {}
        self._ego_ctx_res: dict | None = None  # this step's context results (_ego_context)
        self._moved_persons: dict = {}     # persons a swap placed by moveToXY: id -> (x, y, speed)
        self._ego_pose: tuple | None = None  # the centre and yaw last given to set_ego_pose

    @property
    def running(self) -> bool:
        return self._sim is not None

    def setup(self) -> None:
        """Start SUMO on the net and route files. Raises SimulationError (one line)."""
        global _LIBSUMO_OWNER, _STALE_SWEPT
        if self._sim is not None:
            raise SimulationError("SumoTraffic.setup(): this simulation is already running")
        self._preflight()
        if self.gui:
            from .display import display_problem

            why = display_problem()
            if why:
                raise SimulationError(f"sumo-gui cannot open its window: {why}; run without --sumo-gui")
        from cosim.demand import sumo_env, sumo_home
        home = sumo_home()
        env = sumo_env()
        for k in ("SUMO_HOME", "PROJ_DATA", "PROJ_LIB"):
            if k in env:
                os.environ.setdefault(k, env[k])
        if not _STALE_SWEPT:            # (once a process: the folders of runs killed outright)
            _STALE_SWEPT = True
            self.remove_stale_tmp()
        self._tmpdir = tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{os.getpid()}-")   # (see remove_tmp_of)
        err_log = os.path.join(self._tmpdir, "sumo-errors.log")
        binary = os.path.join(home, "bin", "sumo-gui" if self.gui else "sumo")
        cmd = [binary, "-n", str(self.net_file)]
        if self.route_files:
            cmd += ["-r", ",".join(str(p) for p in self.route_files)]
        cmd += ["--step-length", f"{self.step_length:g}", "--seed", str(self.seed),
                "--collision.action", "warn", "--collision.mingap-factor", "0",
                "--time-to-teleport", f"{self.time_to_teleport:g}",
                "--no-step-log", "--ignore-route-errors", "--pedestrian.model", "striping",
                "--error-log", err_log, "--duration-log.disable"]
        cmd += lane_change_args(self.lane_change_s)
        if not self.warnings:
            cmd += ["--no-warnings"]
        if self.gui:
            cmd += ["--start", "--quit-on-end"]
        cmd += self.extra_args
        self._reset_run_state()
        self._loads += 1
        if self.backend == "libsumo":
            import libsumo
            if _LIBSUMO_OWNER is not None or libsumo.simulation.isLoaded():
                self._cleanup_tmp()
                raise SimulationError("libsumo already runs a simulation in this process (one per "
                                      "process): tear the other one down first, or use "
                                      "backend='traci'")
            captured = os.path.join(self._tmpdir, "sumo-stderr.txt")
            try:
                # libsumo prints load errors to the process's stderr (not to --error-log)
                with _stderr_to(captured):
                    libsumo.start(cmd)
            except Exception as e:
                msg = self._sumo_error(e, err_log, captured)
                try:
                    libsumo.close()
                except Exception:
                    pass
                self._cleanup_tmp()
                raise SimulationError(f"SUMO could not start on {self.net_file.name}: {msg}") from None
            self._sim = libsumo
            _LIBSUMO_OWNER = self
            _forward_text(captured)
            self._exc = (libsumo.TraCIException,) + ((libsumo.FatalTraCIError,)
                                                      if hasattr(libsumo, "FatalTraCIError") else ())
        else:
            import traci
            self._label = f"cosim-{id(self):x}-{self._generation}"
            captured = os.path.join(self._tmpdir, "sumo-stderr.txt")
            try:
                self._sim = self._start_traci(cmd, captured)
            except Exception as e:
                msg = self._sumo_error(e, err_log, captured)
                self._cleanup_tmp()
                raise SimulationError(f"SUMO could not start on {self.net_file.name}: {msg}") from None
            self._exc = (traci.exceptions.TraCIException, traci.exceptions.FatalTraCIError)
        self._err_log = err_log
        try:
            self._after_start()
        except self._exc as e:
            self.teardown()
            raise SimulationError(f"SUMO setup failed: {self._sumo_error(e, err_log)}") from None

    def _start_traci(self, cmd: list, captured: str):
        """Start SUMO (or sumo-gui) as a TraCI server and connect to it. ``traci.start`` starts
        SUMO again on another port whenever it ends before the connection, 100 times, printing
        as it goes: a sumo-gui without a display took minutes to fail. Here a SUMO that ends
        stops the start at once (its stderr, in ``captured``, names why); only a port taken
        between choosing and binding it is tried again. Waits up to TRACI_START_TIMEOUT_S
        for SUMO to load."""
        import contextlib
        import io
        import subprocess

        import traci
        from sumolib.miscutils import getFreeSocketPort

        for attempt in range(3):
            port = getFreeSocketPort()
            with open(captured, "wb") as err:
                proc = subprocess.Popen(cmd + ["--remote-port", str(port)], stdout=subprocess.DEVNULL,
                                        stderr=err)
            try:
                with contextlib.redirect_stdout(io.StringIO()):   # (traci prints each retry)
                    traci.init(port, numRetries=TRACI_START_TIMEOUT_S, label=self._label, proc=proc,
                               doSwitch=False)
                return traci.getConnection(self._label)
            except BaseException:
                if proc.poll() is None:
                    proc.kill()
                proc.wait()
                try:
                    with open(captured, encoding="utf-8", errors="replace") as f:
                        text = f.read().lower()
                except OSError:
                    text = ""
                if attempt < 2 and ("port" in text or "bind" in text or "address" in text):
                    continue
                raise

    def teardown(self) -> None:
        """Close SUMO (idempotent)."""
        global _LIBSUMO_OWNER
        sim, self._sim = self._sim, None
        if sim is not None:
            try:
                sim.close()
            except Exception as e:  # already closed / SUMO died: nothing left to close
                log.debug("SUMO close: %s", e)
            if self.backend == "libsumo" and _LIBSUMO_OWNER is self:
                _LIBSUMO_OWNER = None
        self._cleanup_tmp()
        self._reset_run_state()

    def __del__(self):
        try:
            if self._sim is not None:
                self.teardown()
        except Exception:
            pass

    @staticmethod
    def remove_tmp_of(pid: int) -> None:
        """Remove the folders of a process that ran a SumoTraffic and has ended: a worker that
        was killed, or crashed, never removed its own."""
        for d in glob.glob(os.path.join(tempfile.gettempdir(), f"{TMP_PREFIX}{int(pid)}-*")):
            shutil.rmtree(d, ignore_errors=True)

    @staticmethod
    def remove_stale_tmp() -> int:
        """Remove the folders of processes that ran a SumoTraffic and are gone (a run killed
        outright, SIGKILL or SIGTERM, leaves its folder); returns how many. A folder whose
        process id is alive, whatever runs under it now, is left alone."""
        from netgen._atomic import process_alive

        n = 0
        for d in glob.glob(os.path.join(tempfile.gettempdir(), f"{TMP_PREFIX}*-*")):
            pid = os.path.basename(d)[len(TMP_PREFIX):].split("-", 1)[0]
            if pid.isdigit() and not process_alive(int(pid)):
                shutil.rmtree(d, ignore_errors=True)
                n += 1
        return n

    def _cleanup_tmp(self):
        if self._tmpdir:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None

    def _preflight(self):
        """Catch what libsumo would crash or throw a bare 'Process Error' on."""
        net = self.net_file
        if not net.is_file():
            raise SimulationError(f"SUMO network {net} does not exist")
        try:
            with open(net, "rb") as f:
                head = f.read(1 << 16)
        except OSError as e:
            raise SimulationError(f"cannot read SUMO network {net}: {e.strerror or e}")
        text = head.decode("utf-8", "replace")
        body = re.sub(r"<!--.*?-->", "", text, flags=re.S)
        m = re.search(r"<([A-Za-z_][\w.-]*)(\s[^>]*)?>", re.sub(r"<\?.*?\?>", "", body, flags=re.S))
        if not m or m.group(1) != "net" or "version=" not in (m.group(2) or ""):
            raise SimulationError(f"{net} is not a SUMO network (no <net version=...> root element)")
        for r in self.route_files:
            if not r.is_file():
                raise SimulationError(f"SUMO route file {r} does not exist")

    def _sumo_error(self, exc, err_log, *more_logs) -> str:
        """First 'Error:' line of SUMO's error log, else the exception text, on one line."""
        lines = []
        for path in (err_log, *more_logs):
            try:
                with open(path, encoding="utf-8", errors="replace") as f:
                    lines += [ln.strip() for ln in f if ln.strip()]
            except OSError:
                pass
        errs = [ln for ln in lines if ln.startswith("Error:")]
        if errs:
            msg = errs[0][len("Error:"):].strip()
            # SUMO adds the location on following lines ("In file ...", "At line/column ...")
            i = lines.index(errs[0])
            extra = [ln for ln in lines[i + 1:i + 3] if ln.startswith(("In file", "At line"))]
            msg = " ".join([msg] + extra)
        else:
            msg = str(exc) or type(exc).__name__
            # what a SUMO that ended said on stderr without "Error:" (sumo-gui: "FXApp::openDisplay:
            # unable to open display :0.0")
            said = [ln for ln in lines if "proj.db" not in ln and not ln.startswith("Warning:")]
            if said:
                msg = f"{msg} ({said[-1]})"
        return " ".join(msg.split())

    def _after_start(self):
        from .driving import note_network

        s = self._sim
        tc = self._tc
        note_network(s, self.net_file)
        # (no subscription to the lights' states: SUMO would assemble all of them every step,
        # 0.3-0.6 ms of a step on central Helsinki's 235; tls_states reads them when asked)
        self._tls_ids = list(s.trafficlight.getIDList())
        for tid in self._tls_ids:
            for i, links in enumerate(s.trafficlight.getControlledLinks(tid)):
                for link in links:
                    if link and link[0] not in self._lane_tls:
                        self._lane_tls[link[0]] = (tid, i)
        s.simulation.subscribe([tc.VAR_TELEPORT_STARTING_VEHICLES_NUMBER,
                                tc.VAR_COLLIDING_VEHICLES_NUMBER,
                                tc.VAR_DEPARTED_PERSONS_NUMBER, tc.VAR_ARRIVED_PERSONS_NUMBER,
                                tc.VAR_DEPARTED_VEHICLES_IDS, tc.VAR_ARRIVED_VEHICLES_IDS])
        self.stats.vehicles = 0
        self.stats.persons = 0

    @property
    def _tc(self):
        if self.backend == "libsumo":
            import libsumo
            return libsumo.constants
        import traci.constants
        return traci.constants

    def _require(self):
        if self._sim is None:
            raise SimulationError("SUMO is not running: call SumoTraffic.setup() first")
        return self._sim

    # --- time ---------------------------------------------------------------------------
    @property
    def sim_time(self) -> float:
        """Simulation time in s (continuous across swap_network)."""
        if self._sim is None:
            return self._time_offset
        return self._time_offset + self._sim.simulation.getTime()

    @property
    def sumo(self):
        """The raw libsumo module / traci connection (for tests and debugging)."""
        return self._require()

    def step(self) -> None:
        """Advance SUMO by one step (step_length seconds)."""
        s = self._require()
        try:
            s.simulation.step()
        except self._exc as e:
            raise SimulationError(f"SUMO step failed at t={self.sim_time:.1f} s: "
                                  f"{self._sumo_error(e, self._err_log)}") from None
        self._after_step()
        if not self.work_when_idle:
            self.work_after_step()

    def work_after_step(self) -> None:
        """What is drawn after each step: :data:`EXTENSION_STEP_PIECES` of a prepared route
        extension, else (in the caller's process) a little of the route graph. SUMO's worker
        calls it once it has answered the step (``work_when_idle``), so that the caller's frame
        goes on meanwhile; before its answer, the last pieces of an extension made some steps
        3-5 ms longer than SUMO's own. Either way, the same pieces come between the same two
        steps in every run."""
        if self._extension is not None and self._extension["result"] is None:
            self._work_on_extension(EXTENSION_STEP_PIECES)
        elif not self.work_when_idle:
            self.background_work(EXTENSION_STEP_BUDGET_S)

    def background_work(self, budget_s: float) -> bool:
        """The route graph (``warm_routes``) worked out on for ``budget_s`` seconds; whether any
        is left. SUMO's worker process calls it while it waits for the next request
        (``work_when_idle``): after each step it made every frame of the first 100 s of a
        Kouvola drive 1 ms longer. (The graph's answers are the same however it is paced; a
        prepared extension is drawn after the steps, :data:`EXTENSION_STEP_PIECES`.)"""
        if self._warm is not None:
            self._warm_up_routes(budget_s)
        return self._warm is not None

    def _after_step(self):
        s, tc, st = self._sim, self._tc, self.stats
        st.steps += 1
        self._tls_fresh.clear()
        self._ego_ctx_res = None
        r = s.simulation.getSubscriptionResults()
        departed = r.get(tc.VAR_DEPARTED_VEHICLES_IDS, ())
        arrived = r.get(tc.VAR_ARRIVED_VEHICLES_IDS, ())
        if self._ego_added:
            if EGO_ID in departed:
                self._ego_in_sim = True
                self._clear_ego_footprint()
                if self._ctx_anchor != EGO_ID:
                    self._subscribe_context(EGO_ID, self._ctx_radius)
            if EGO_ID in arrived:  # should not happen (remote controlled); re-add next pose
                log.warning("SUMO removed the ego vehicle at t=%.1f s; re-adding it", self.sim_time)
                self._ego_in_sim = False
                self._ctx_anchor = None
                self._readd_ego()
        if departed and self._ego_in_sim and self._ego_route:
            self._drop_inserted_ahead(departed)
        if self._ego_in_sim and self._ego_pending_speed is not None:
            try:
                s.vehicle.setPreviousSpeed(EGO_ID, self._ego_pending_speed)
                # SUMO teleports (and at a route's end removes) a vehicle that stood still for
                # time-to-teleport, the remote-controlled ego too, and its drivers then do not
                # see it for a moment: an ego waiting that long is moved back and forth by
                # EGO_UNSTICK_M in SUMO only (set_ego_pose), which resets SUMO's waiting time
                self._ego_unstick = s.vehicle.getWaitingTime(EGO_ID) > 0.5 * self.time_to_teleport
            except self._exc:
                pass
        if self._ego_route and self._ego_in_sim:
            self._keep_ego_route()
        if self.persons_yield and (self._ego_in_sim or self._held):
            self._persons_yield()
        if self._ego_in_sim or self._straddle_held:
            self._straddle_yield()
        n_tele = int(r.get(tc.VAR_TELEPORT_STARTING_VEHICLES_NUMBER, 0))
        if n_tele:
            st.teleports += n_tele
            log.info("SUMO: %d vehicle(s) teleported at t=%.1f s (total %d)", n_tele,
                     self.sim_time, st.teleports)
        if r.get(tc.VAR_COLLIDING_VEHICLES_NUMBER, 0):
            for c in s.simulation.getCollisions():
                key = (c.collider, c.victim)
                if key not in st._seen_collisions:
                    st._seen_collisions.add(key)
                    st.collisions += 1
                    log.info("SUMO collision at t=%.1f s: %s (%s) hit %s (%s), %s", self.sim_time,
                             c.collider, c.colliderType, c.victim, c.victimType, c.type)
        st.persons += int(r.get(tc.VAR_DEPARTED_PERSONS_NUMBER, 0)) - int(
            r.get(tc.VAR_ARRIVED_PERSONS_NUMBER, 0))
        if st.steps % VEHICLE_RECOUNT_STEPS == 0:   # (a count costs 45 us on a city: SUMO lists them)
            st.vehicles = s.vehicle.getIDCount() - (1 if self._ego_in_sim else 0)
        else:               # (between the counts: those that departed less those that arrived)
            st.vehicles += sum(v != EGO_ID for v in departed) - sum(v != EGO_ID for v in arrived)
        st.max_vehicles = max(st.max_vehicles, st.vehicles)
        st.max_persons = max(st.max_persons, st.persons)

    def waits_for_ego(self, vid: str, chain: int = STANDOFF_CHAIN) -> bool:
        """Does SUMO have vehicle `vid` wait for the ego: the ego its leader within 10 m, or
        at the head of a queue of up to `chain` standing vehicles ahead of it, each within 10 m
        of the next?"""
        s = self._require()
        try:
            lead, hops = s.vehicle.getLeader(vid, 10.0), 0
            while lead and lead[0] and lead[1] < 10.0:
                if lead[0] == EGO_ID:
                    return True
                # (a vehicle that creeps up behind the ego is as good as standing: SUMO had one
                # at 0.13 m/s, 0.13 m behind the standing ego, for a minute)
                if hops >= chain or s.vehicle.getSpeed(lead[0]) >= STANDOFF_CREEP_MPS:
                    return False
                hops += 1
                lead = s.vehicle.getLeader(lead[0], 10.0)
        except self._exc:
            return False
        return False

    def release_standoff(self, vid: str, waited_s: float, circle: bool = False) -> bool:
        """Take vehicle `vid` out of SUMO if it has stood `waited_s` (less a second) for no
        reason SUMO shows: no red or yellow light within 30 m ahead of it, no standing vehicle
        within 10 m ahead but the ego or one that stands behind the ego (up to STANDOFF_CHAIN
        of them, each within 10 m of the next), no stop of its own. The autopilot asks this after a
        standoff (the car waits for it, it waits for the car; SUMO would teleport it after
        ``time_to_teleport``). One carried over a network swap (:func:`carried_id`) has stood all
        the while since it came into this SUMO. With ``circle``, only where SUMO has it wait for the ego
        (:meth:`waits_for_ego`: a vehicle the ego follows, not one beside its path). Returns
        whether it was taken out."""
        s = self._require()
        tc = self._tc
        try:
            if vid == EGO_ID or vid not in s.vehicle.getIDList():
                return False
            if circle and not self.waits_for_ego(vid):
                return False
            wait = s.vehicle.getWaitingTime(vid)
            if wait < waited_s - 1.0 and (carried_id(vid) == vid
                                          or wait < s.simulation.getTime() - s.vehicle.getDeparture(vid) - 1.0):
                return False            # (one carried over a swap: standing all the while since)
            if s.vehicle.isStopped(vid):
                return False
            tls = s.vehicle.getNextTLS(vid)
            if tls and tls[0][2] < 30.0 and tls[0][3] in "rRyYu":
                return False
            # (a standing vehicle ahead of it is a queue, unless the queue ends at the ego: a
            # circle with the car)
            lead = s.vehicle.getLeader(vid, 10.0)
            if lead and lead[0] and lead[0] != EGO_ID and lead[1] < 10.0 \
                    and s.vehicle.getSpeed(lead[0]) < STANDOFF_CREEP_MPS and not self.waits_for_ego(vid):
                return False
            s.vehicle.remove(vid, tc.REMOVE_VAPORIZED)
        except self._exc:
            return False
        self.stats.released += 1
        log.info("SUMO: %s taken out at t=%.1f s after a standoff with the ego (it stood %.0f s)",
                 vid, self.sim_time, waited_s)
        return True

    def _persons_yield(self) -> None:
        """Pedestrians do not walk into the ego: one whose path would take it into the ego's
        footprint (plus PERSON_YIELD_MARGIN_M) within PERSON_YIELD_HORIZON stops where it is
        (``person.setSpeed(0)``) and walks on at its own speed once its path is clear.

        SUMO's pedestrians see vehicles only where they cross a road; elsewhere nothing keeps
        them out of a car that SUMO itself does not move (where a guessed sidewalk overlapped a
        car lane in Helsinki, one walked through the standing ego). A person already touching
        the ego is left to walk out. Uses the ego's context
        subscription (the persons near it come with every step). A person ahead of the car's
        front is never stopped: there the car waits for the person (the autopilot yields to
        people in its path), and stopping both would leave them waiting for each other."""
        s, tc = self._sim, self._tc
        res = {}
        if self._ego_in_sim and self._ctx_anchor == EGO_ID:
            try:
                res = self._ego_context()
            except self._exc:
                res = {}
        hold: set[str] = set()
        if res and self._ego_pose is not None:
            spec = self._ego_spec
            cx, cy, yaw = self._ego_pose
            c, sn = math.cos(yaw), math.sin(yaw)
            hl = spec["length"] / 2 + PERSON_YIELD_MARGIN_M
            hw = spec["width"] / 2 + PERSON_YIELD_MARGIN_M
            r2 = PERSON_YIELD_RANGE_M ** 2
            VEH, POS, SPEED, ANGLE = tc.VAR_VEHICLE, tc.VAR_POSITION, tc.VAR_SPEED, tc.VAR_ANGLE
            for pid, v in res.items():
                if VEH not in v or v[VEH] or POS not in v:
                    continue                         # a vehicle, or a person riding in one
                dx, dy = v[POS][0] - cx, v[POS][1] - cy
                if dx * dx + dy * dy > r2:
                    continue
                # a stopped person: at its own pace; one that stands by itself goes nowhere
                sp = self._held.get(pid, v[SPEED])
                if sp < 0.05:
                    continue
                a = sumo_angle_to_yaw(v[ANGLE])
                vx, vy = sp * math.cos(a), sp * math.sin(a)
                lon, lat = dx * c + dy * sn, -dx * sn + dy * c
                if abs(lon) <= hl and abs(lat) <= hw:
                    continue                         # already touching: let it walk out
                if lon > spec["length"] / 2:
                    continue                         # ahead of the car: the car waits for it
                vlon, vlat = vx * c + vy * sn, -vx * sn + vy * c
                if any(abs(lon + vlon * t) <= hl and abs(lat + vlat * t) <= hw
                       for t in PERSON_YIELD_HORIZON):
                    hold.add(pid)
        held = {}
        for pid in hold:
            if pid in self._held:
                held[pid] = self._held[pid]
                continue
            try:
                pace = s.person.getMaxSpeed(pid)     # its own pace (or one set through TraCI)
                s.person.setSpeed(pid, 0.0)
            except self._exc:
                continue
            held[pid] = pace
            self.stats.persons_held += 1
            log.debug("person %s stops for the ego at t=%.1f s", pid, self.sim_time)
        for pid in self._held.keys() - held.keys():
            try:
                s.person.setSpeed(pid, self._held[pid])     # on at its own pace
            except self._exc:
                pass                                 # arrived or gone
        self._held = held

    def _straddle_yield(self) -> None:
        """SUMO's drivers see the ego only in the lane SUMO maps it to (without the sublane
        model). While the ego's body reaches STRADDLE_M or more into a neighbouring lane, or
        will within STRADDLE_AHEAD_S at its sideways speed (its lane path blends from one lane
        to the next over an edge, or from a junction lane), the follower in that lane
        keeps STRADDLE_GAP_M behind it (``setSpeed`` down to what stops it there at
        EGO_INSERT_DECEL, released after): else, once ``moveToXY`` maps the ego over into that
        lane mid-blend, it lands on a car beside it (Lauf, seeds 4 and 5: SUMO counted the car
        coming up behind as a collision)."""
        s = self._sim
        held: set = set()
        lane = ""
        if self._ego_in_sim and not self._ego_off_network:
            try:
                lane = self._ego_lane()
                if lane:
                    lat = s.vehicle.getLateralLanePosition(EGO_ID)
            except self._exc:
                lane = ""
        if lane:
            w = self._lane_widths.get(lane)
            if w is None:
                w = self._lane_widths[lane] = float(s.lane.getWidth(lane))
            half = self._ego_spec["width"] / 2.0
            # where the body will be: the ego blending over into the next lane moves sideways at
            # about 1 m/s (Portland, seed 12: blending from a junction lane into the lane beside
            # it, the follower coming up there at 4 m/s faster was held only 0.3 s before it hit)
            prev_lane, prev_lat = self._straddle_lat
            v_lat = (lat - prev_lat) / self.step_length if prev_lane == lane else 0.0
            ahead = lat + v_lat * STRADDLE_AHEAD_S
            sides = []
            if max(lat, ahead) + half > w / 2.0 + STRADDLE_M:
                sides.append(s.vehicle.getLeftFollowers)
            if min(lat, ahead) - half < -w / 2.0 - STRADDLE_M:
                sides.append(s.vehicle.getRightFollowers)
            v_ego = self._ego_pending_speed or 0.0
            for followers in sides:
                try:
                    found = followers(EGO_ID)
                except self._exc:
                    continue
                for fid, gap in found:
                    if not fid or gap > STRADDLE_LOOK_M:
                        continue
                    room = gap - STRADDLE_GAP_M
                    v_ok = math.sqrt(v_ego * v_ego + 2.0 * EGO_INSERT_DECEL * room) if room > 0.0 \
                        else max(0.0, v_ego - 2.0)         # beside it: fall back
                    try:
                        if fid in self._straddle_held or s.vehicle.getSpeed(fid) > v_ok:
                            s.vehicle.setSpeed(fid, v_ok)
                            held.add(fid)
                    except self._exc:
                        pass
        for fid in self._straddle_held - held:
            try:
                s.vehicle.setSpeed(fid, -1)          # its own driving again
            except self._exc:
                pass                                 # arrived or gone
        self._straddle_held = held
        self._straddle_lat = (lane, lat if lane else 0.0)

    # --- ego ----------------------------------------------------------------------------
    def add_ego(self, route_edges: Sequence[str] | None = None, from_edge: str | None = None,
                to_edge: str | None = None, length: float = 4.5, width: float = 1.8,
                height: float = 1.5, vclass: str = "passenger", max_speed: float = 70.0) -> None:
        """Add the ego vehicle to SUMO (before any set_ego_pose).

        The route is ``route_edges``, or SUMO's fastest route ``from_edge`` -> ``to_edge``, or any
        edge the ego may use (the first set_ego_pose relocates it anyway).
        """
        s = self._require()
        if self._ego_added:
            raise SimulationError("the ego vehicle was already added")
        self._ego_spec = dict(length=float(length), width=float(width), height=float(height),
                              vclass=vclass, max_speed=float(max_speed))
        if route_edges:
            edges = [str(e) for e in route_edges]
        elif from_edge and to_edge:
            try:
                edges = list(s.simulation.findRoute(from_edge, to_edge, vType="DEFAULT_VEHTYPE").edges)
            except self._exc as e:
                raise SimulationError(f"no route for the ego from {from_edge} to {to_edge}: {e}") from None
            if not edges:
                raise SimulationError(f"no route for the ego from {from_edge} to {to_edge}")
        elif from_edge:
            edges = [from_edge]
        else:
            edges = [self._any_edge_for(vclass)]
        self._ego_spec["edges"] = edges
        self._readd_ego()

    def _any_edge_for(self, vclass: str) -> str:
        s = self._sim
        for e in s.edge.getIDList():
            if e.startswith(":"):
                continue
            lane = f"{e}_0"
            try:
                if vclass in s.lane.getAllowed(lane) or (not s.lane.getAllowed(lane) and
                                                         vclass not in s.lane.getDisallowed(lane)):
                    return e
            except self._exc:
                continue
        raise SimulationError(f"the network has no edge a {vclass} may use for the ego")

    def _ensure_type(self, type_id: str, params: dict, person: bool = False):
        s = self._sim
        if type_id in s.vehicletype.getIDList():
            return
        s.vehicletype.copy("DEFAULT_PEDTYPE" if person else "DEFAULT_VEHTYPE", type_id)
        if "vclass" in params:
            s.vehicletype.setVehicleClass(type_id, params["vclass"])
        for key, fn in (("length", s.vehicletype.setLength), ("width", s.vehicletype.setWidth),
                        ("height", s.vehicletype.setHeight), ("max_speed", s.vehicletype.setMaxSpeed),
                        ("accel", s.vehicletype.setAccel), ("decel", s.vehicletype.setDecel),
                        ("min_gap", s.vehicletype.setMinGap)):
            if params.get(key) is not None:
                fn(type_id, float(params[key]))

    def _readd_ego(self):
        s, spec = self._sim, self._ego_spec
        type_id = "cosim_ego"
        try:
            self._ensure_type(type_id, spec)
            rid = f"cosim_ego_route_{self._generation}_{self.stats.steps}"
            s.route.add(rid, spec["edges"])
            s.vehicle.add(EGO_ID, rid, typeID=type_id, depart="now", departLane="best")
            s.vehicle.setSpeedMode(EGO_ID, 0)
            s.vehicle.setLaneChangeMode(EGO_ID, 0)
        except self._exc as e:
            raise SimulationError(f"cannot add the ego vehicle to SUMO: {e}") from None
        self._ego_added = True
        self._ego_clear_due = True      # (set_ego_pose clears its place once, _after_step again)

    def set_ego_pose(self, x: float, y: float, yaw: float, speed: float = 0.0,
                     edge_hint: str | None = None, lane_hint: int | None = None) -> bool:
        """Place the ego: world body centre (m) and yaw (rad, 0 = east, CCW), speed in m/s.

        Takes effect in the next step(). A pose off SUMO's roads is accepted (the ego then has
        no lane and SUMO's drivers ignore it until it is back on a road: ``ego_state()['lane']``
        is ''); returns False only when SUMO rejects the pose.
        """
        s = self._require()
        if not self._ego_added:
            raise SimulationError("add_ego() must come before set_ego_pose()")
        angle = yaw_to_sumo_angle(yaw)
        self._ego_pose = (float(x), float(y), float(yaw))   # the car's body, for _persons_yield
        if self._ego_unstick:
            self._unstick_sign = -self._unstick_sign
            x += self._unstick_sign * EGO_UNSTICK_M * math.cos(yaw)
            y += self._unstick_sign * EGO_UNSTICK_M * math.sin(yaw)
        fx, fy = center_to_front(x, y, angle, self._ego_spec["length"])
        fx, fy = self._across_joint(fx, fy, yaw)
        if self._ego_clear_due:
            self._ego_clear_due = False
            self._clear_ego_footprint()
        try:
            # matchThreshold: lanes are searched within this radius only (SUMO's default of
            # 100 m made this call cost 0.2-1.2 ms in a dense city; 15 m: 0.05 ms)
            s.vehicle.moveToXY(EGO_ID, edge_hint or "", -1 if lane_hint is None else int(lane_hint),
                               fx, fy, angle, keepRoute=2, matchThreshold=EGO_MATCH_RADIUS_M)
        except self._exc as e:
            if not self._ego_off_network:
                log.info("SUMO cannot map the ego at (%.1f, %.1f): %s", x, y, e)
            self._ego_off_network = True
            return False
        self._ego_off_network = False
        self._ego_pending_speed = max(0.0, float(speed))
        return True

    def _across_joint(self, fx: float, fy: float, yaw: float) -> tuple[float, float]:
        """Where a lane ends and the next begins at an angle, ``moveToXY`` finds no lane for a
        point just past the end on the outer side of the bend (its perpendicular foot lies
        beyond the one lane's end and before the other's start), and SUMO takes the ego off the
        network for that step (Helsinki, seed 18: for that step a car changed into the ego's
        lane 0.8 m behind it, into the ego's tail when it came back; 0.2 m past the end, 0.23 m
        to the side). A front bumper past the end of the lane the ego was on, within 2 m of it,
        is mapped EGO_JOINT_NUDGE_M further on, in the next lane."""
        lane = self._straddle_lat[0]
        if not lane:
            return fx, fy
        ends = self._lane_ends.get(lane)
        if ends is None:
            ends = self._lane_ends[lane] = self._joint_segments(lane)
        if not ends:
            return fx, fy
        (ax, ay), (bx, by) = ends[0]
        ux, uy = bx - ax, by - ay
        L = math.hypot(ux, uy)
        if L < 1e-6 or ((fx - ax) * ux + (fy - ay) * uy) / L <= L or math.hypot(fx - bx, fy - by) > 2.0:
            return fx, fy
        # only in the wedge: where the point's foot is on a next lane, SUMO maps it there, and a
        # point nudged further on along a heading still across the next lane can map onto the
        # lane beside it, the other way (Kouvola motorway, seed 28: the ego turning onto a road
        # 1.8 m wide of its lane went onto the oncoming lane, and the truck on it hit it)
        for (qx, qy), (rx, ry) in ends[1:]:
            vx, vy = rx - qx, ry - qy
            if (fx - qx) * vx + (fy - qy) * vy >= 0.0:
                return fx, fy
        return fx + EGO_JOINT_NUDGE_M * math.cos(yaw), fy + EGO_JOINT_NUDGE_M * math.sin(yaw)

    def _joint_segments(self, lane: str) -> tuple:
        """A lane's last segment, then the first segment of each lane a vehicle goes on to from
        it (the junction lane of each link, or the lane after it); () where the shape is short."""
        s = self._sim
        try:
            P = s.lane.getShape(lane)
            links = s.lane.getLinks(lane)
        except self._exc:
            return ()
        if len(P) < 2:
            return ()
        out = [(tuple(P[-2][:2]), tuple(P[-1][:2]))]
        for ln in links:
            nxt = ln[4] or ln[0]
            try:
                Q = s.lane.getShape(nxt)
            except self._exc:
                continue
            if len(Q) >= 2:
                out.append((tuple(Q[0][:2]), tuple(Q[1][:2])))
        return tuple(out)

    def set_ego_route(self, edges) -> None:
        """The edges the ego will drive (its planned path). Kept as its route in SUMO from the
        edge it is on (:meth:`_keep_ego_route`): moved by ``moveToXY``, the ego's route is
        otherwise the one edge it is on, and SUMO's drivers do not see it coming at a junction
        (SUMO registers a vehicle's approach to the links of its route only; on the Kouvola
        motorway a car turning left across the ego's path did not wait for it and ran into
        it on the junction)."""
        self._ego_route = tuple(e for e in edges if e and not e.startswith(":"))
        self._ego_route_road = ""
        self._ego_route_i = 0
        if self._ego_in_sim:
            self._keep_ego_route()

    def _keep_ego_route(self) -> None:
        """After a step: once the ego is on a new edge of its planned route, SUMO's route for
        it is the rest of the planned one (moveToXY with keepRoute=2 keeps a route while the
        ego stays on it, and replaces it with the edge it is on when it leaves it)."""
        s = self._sim
        try:
            lane = self._ego_lane()
        except self._exc:
            return
        road = lane.rsplit("_", 1)[0]
        if road == self._ego_route_road or not road or road.startswith(":"):
            return
        self._ego_route_road = road
        r = self._ego_route
        i = next((k for k in range(self._ego_route_i, len(r)) if r[k] == road), None)   # (a route may
        if i is None:                                                                   # pass an edge twice)
            i = next((k for k in range(len(r)) if r[k] == road), None)
        if i is None:
            return
        self._ego_route_i = i
        rest = list(r[i:])
        try:
            if list(s.vehicle.getRoute(EGO_ID)[s.vehicle.getRouteIndex(EGO_ID):]) != rest:
                s.vehicle.setRoute(EGO_ID, rest)
        except self._exc as e:
            log.debug("ego route %s... not taken: %s", rest[:3], e)

    def ego_state(self) -> dict | None:
        """The ego as SUMO sees it (centre, yaw, speed, road, lane), or None if not in SUMO."""
        if not self._ego_in_sim:
            return None
        s = self._sim
        fx, fy = s.vehicle.getPosition(EGO_ID)
        angle = s.vehicle.getAngle(EGO_ID)
        cx, cy = front_to_center(fx, fy, angle, self._ego_spec["length"])
        return dict(x=cx, y=cy, front=(fx, fy), yaw=sumo_angle_to_yaw(angle), angle=angle,
                    speed=s.vehicle.getSpeed(EGO_ID), edge=s.vehicle.getRoadID(EGO_ID),
                    lane=s.vehicle.getLaneID(EGO_ID))

    # --- actors -------------------------------------------------------------------------
    def _vehicle_vars(self):
        tc = self._tc
        # (a vehicle's class and size are its type's: read once per type, _vtype_info; a
        # vehicle whose size is changed alone gets a type of its own in SUMO)
        return [tc.VAR_POSITION, tc.VAR_ANGLE, tc.VAR_SPEED, tc.VAR_TYPE, tc.VAR_SLOPE, tc.VAR_LANE_ID]

    def _person_vars(self):
        tc = self._tc
        # VAR_VEHICLE (the vehicle a person rides in) marks person entries: both context
        # domains' results arrive in one dict keyed by object id. Sizes come from the person's
        # type (libsumo files a person context's VAR_LENGTH under the type id, not the person)
        return [tc.VAR_POSITION, tc.VAR_ANGLE, tc.VAR_SPEED, tc.VAR_VEHICLE, tc.VAR_TYPE,
                tc.VAR_SLOPE, tc.VAR_LANE_ID]

    def _vtype_info(self, type_id: str, vehicle: str) -> tuple[str, float, float, float]:
        """(vehicle class, length, width, height) of a vehicle type, cached; the vehicle's own
        when SUMO's type lookup does not know its type."""
        info = self._vclass_cache.get(type_id)
        if info is None:
            try:
                vt = self._sim.vehicletype
                info = (vt.getVehicleClass(type_id), vt.getLength(type_id), vt.getWidth(type_id),
                        vt.getHeight(type_id))
            except self._exc:
                ve = self._sim.vehicle
                return (ve.getVehicleClass(vehicle), ve.getLength(vehicle), ve.getWidth(vehicle),
                        ve.getHeight(vehicle))
            self._vclass_cache[type_id] = info
        return info

    def _type_dims(self, type_id: str, person: str | None = None) -> tuple[float, float, float]:
        """(length, width, height) of a vehicle type; for a person whose type SUMO does not
        list (the copy it makes when a person's speed is set, e.g. ``ped@ped280~1@ped280~2``
        after a network swap), the person's own, or SUMO's default pedestrian size when SUMO
        does not know the person either (a 30-minute run met one carried by a swap)."""
        dims = self._dims_cache.get(type_id)
        if dims is None:
            try:
                vt = self._sim.vehicletype
                dims = (vt.getLength(type_id), vt.getWidth(type_id), vt.getHeight(type_id))
            except self._exc:
                if person is None:
                    raise
                try:
                    pe = self._sim.person
                    return pe.getLength(person), pe.getWidth(person), pe.getHeight(person)
                except self._exc:       # (listed by the context, unknown to the person API)
                    return PERSON_DIMS
            self._dims_cache[type_id] = dims
        return dims

    def _domain(self, anchor: str):
        return self._sim.vehicle if anchor == EGO_ID else self._sim.poi

    def _subscribe_context(self, anchor: str, radius: float):
        tc = self._tc
        dom = self._domain(anchor)
        if self._ctx_anchor and self._ctx_anchor != anchor:
            self._unsubscribe_context()
        if self._probe_radius is not None:   # the ego takes over from the probe
            r, self._probe_radius = self._probe_radius, None
            try:
                self._sim.poi.unsubscribeContext(PROBE_ID, tc.CMD_GET_VEHICLE_VARIABLE, r)
                self._sim.poi.unsubscribeContext(PROBE_ID, tc.CMD_GET_PERSON_VARIABLE, r)
            except self._exc:
                pass
        dom.subscribeContext(anchor, tc.CMD_GET_VEHICLE_VARIABLE, radius, self._vehicle_vars())
        dom.subscribeContext(anchor, tc.CMD_GET_PERSON_VARIABLE, radius, self._person_vars())
        self._ctx_anchor, self._ctx_radius = anchor, radius
        self._ego_ctx_res = None

    def _ego_context(self) -> dict:
        """The ego's context subscription results, read from SUMO once a step (a read of
        150 actors costs 0.4 ms) and shared by _persons_yield and actors_near."""
        if self._ego_ctx_res is None:
            self._ego_ctx_res = self._sim.vehicle.getContextSubscriptionResults(EGO_ID) or {}
        return self._ego_ctx_res

    def _ego_lane(self) -> str:
        """The ego's lane after this step ('' off the network): from its own entry in the
        context subscription it anchors (no call), else asked."""
        if self._ctx_anchor == EGO_ID:
            e = self._ego_context().get(EGO_ID)
            if e is not None and self._tc.VAR_LANE_ID in e:
                return e[self._tc.VAR_LANE_ID]
        return self._sim.vehicle.getLaneID(EGO_ID)

    def _unsubscribe_context(self):
        tc = self._tc
        old = self._ctx_anchor
        self._ctx_anchor = None
        if old is None:
            return
        try:
            dom = self._domain(old)
            dom.unsubscribeContext(old, tc.CMD_GET_VEHICLE_VARIABLE, self._ctx_radius)
            dom.unsubscribeContext(old, tc.CMD_GET_PERSON_VARIABLE, self._ctx_radius)
        except self._exc:
            pass

    def _context_results(self, x: float, y: float, radius: float) -> dict:
        s, tc = self._sim, self._tc
        if self._ego_in_sim:
            if self._ctx_anchor != EGO_ID or radius + CONTEXT_MARGIN > self._ctx_radius:
                self._subscribe_context(EGO_ID, max(radius + CONTEXT_MARGIN, self._ctx_radius))
            res = self._ego_context()
            e = res.get(EGO_ID)
            if e is None:
                return res
            # complete if every actor whose centre is within radius of (x, y) has its front
            # within the subscription range of the ego's front (actors are at most 2 * 6 m long)
            d = math.hypot(e[tc.VAR_POSITION][0] - x, e[tc.VAR_POSITION][1] - y)
            if d + radius + 7.0 <= self._ctx_radius:
                return res
            if d <= 2 * CONTEXT_MARGIN:   # widen the ego's range; results come back at once
                self._subscribe_context(EGO_ID, d + radius + CONTEXT_MARGIN)
                return self._ego_context()
        # a query without an ego (or far from it): a hidden POI at (x, y) is the anchor;
        # subscribing returns results for the current state at once
        if PROBE_ID not in s.poi.getIDList():
            s.poi.add(PROBE_ID, x, y, (0, 0, 0, 0), "cosim_probe")
        if self._probe_xy != (x, y):
            s.poi.setPosition(PROBE_ID, x, y)
            self._probe_xy = (x, y)
        r = radius + CONTEXT_MARGIN
        s.poi.subscribeContext(PROBE_ID, tc.CMD_GET_VEHICLE_VARIABLE, r, self._vehicle_vars())
        s.poi.subscribeContext(PROBE_ID, tc.CMD_GET_PERSON_VARIABLE, r, self._person_vars())
        self._probe_radius = r
        return s.poi.getContextSubscriptionResults(PROBE_ID) or {}

    def actors_near(self, x: float, y: float, radius: float) -> ActorsSnapshot:
        """Vehicles and walking persons whose body centre is within ``radius`` m of (x, y).

        Uses the context subscription on the ego (one batched query per step); the ego itself
        and persons riding in vehicles are excluded.
        """
        return self.actors_context(x, y, radius).snapshot(x, y, radius)

    def actors_context(self, x: float, y: float, radius: float) -> "ActorsContext":
        """SUMO's side of :meth:`actors_near`: the context subscription's results as libsumo
        gives them, with the class and size of each type among them. SUMO's worker process
        sends this with each step and the caller makes the snapshot (``ActorsContext.snapshot``):
        the worker's own work bounds the loop at about 400 actors, the caller's less so."""
        self._require()
        tc = self._tc
        try:
            res = self._context_results(float(x), float(y), float(radius))
        except self._exc as e:
            raise SimulationError(f"SUMO actor query failed: {e}") from None
        VEH, TYPE = tc.VAR_VEHICLE, tc.VAR_TYPE
        infos = {}          # (is a vehicle, type id) -> (class, length, width, height)
        for aid, v in res.items():
            key = (VEH not in v, v.get(TYPE))
            if key not in infos and key[1] is not None:
                infos[key] = self._vtype_info(key[1], aid) if key[0] else \
                    ("person",) + tuple(self._type_dims(key[1], aid))
        speeds = None
        moved = self._moved_persons
        if moved:
            # (SUMO's speed of a person just carried across a network swap is that of its
            # insertion jump until it walks on: see _insert_kept)
            P = tc.VAR_POSITION
            speeds = {}
            for aid, m in list(moved.items()):
                pos = res.get(aid, {}).get(P)
                if pos is None:
                    continue
                if math.hypot(pos[0] - m[0], pos[1] - m[1]) < 0.05:
                    speeds[aid] = m[2]
                else:
                    del moved[aid]
        return ActorsContext(self.sim_time, res, infos, speeds)

    def warm_network(self) -> None:
        """Read what the autopilot asks of a new network at once (every lane's links, the
        lanes into each lane, the junction lanes of each, every edge's junctions), in a SUMO
        started ahead of a swap (``TrafficProcess.prepare_network``): asked after the swap,
        the reading made its third frame 136-144 ms long (a 30-minute Helsinki soak). Cached
        per SUMO load (``_net_key``), they hold through the swap's adopt."""
        for name in NETWORK_READS:
            getattr(self, name)()

    def warm_up(self) -> None:
        """Run a SUMO just started on a network up to ``SWAP_WARM_S``, paying now what its first
        second costs anyway: SUMO builds its lane lookup (convertRoad, moveToXY) and its
        intermodal router (for persons) on first use, 0.1-0.3 s each on a city network, and the
        driving module loads (in a fresh worker process). ``swap_adopt`` calls it; a SUMO
        started ahead of a swap (``TrafficProcess.prepare_network``) runs it in the background."""
        from . import driving  # noqa: F401

        s = self._require()
        if s.simulation.getTime() >= SWAP_WARM_S - 1e-9:
            return
        edges = sorted(e for e in self._edge_set() if not e.startswith(":"))
        if edges:
            x, y = s.lane.getShape(f"{edges[0]}_0")[0]
            try:
                s.simulation.convertRoad(x, y, False, "passenger")
                s.simulation.findIntermodalRoute(edges[0], edges[-1], modes="")
            except self._exc:
                pass
        while s.simulation.getTime() < SWAP_WARM_S - 1e-9:
            self.step()

    # --- route planning for the ego (runs where SUMO runs: in its worker, one round trip) ---
    def snap_lane(self, x: float, y: float, vclass: str = "passenger"):
        """The nearest lane a ``vclass`` may use (inside a junction: the lane it leads into):
        (lane id, position on lane, snapped x, y, lane heading in rad, distance)."""
        s = self._require()
        try:
            edge, pos, idx = s.simulation.convertRoad(x, y, False, vclass)
        except self._exc as e:
            raise SimulationError(f"no road for cars near ({x:.0f}, {y:.0f}) m: {e}") from None
        lane = f"{edge}_{idx}"
        from .driving import off_the_world

        guard = 0
        while lane.startswith(":") and guard < 5:
            links = s.lane.getLinks(lane)
            if not links:
                break
            lane, pos, guard = links[0][0], 0.0, guard + 1
        # (the tunnel checked on the lane a junction's lane leads into: a Monaco start snapped
        # onto a junction lane went on into a tunnel, and the car drove on bare terrain)
        if off_the_world(s, lane.rsplit("_", 1)[0]):
            # the world has no tunnels (nor room for the car in a lane narrower than it): the
            # nearest lane on the surface it fits in instead
            nearest = self._lanes_near(x, y, math.inf, vclass, most=1)
            if nearest:
                lane = nearest[0][1]
                pos = self.lane_pos(lane, x, y)
        return self._lane_point(lane, pos, x, y)

    def runs_into_dead_end(self, lane: str, reach: float = 400.0) -> bool:
        """Whether the road ahead of ``lane`` has no way on but a turnaround within ``reach``
        m: its edge and, while there is one only, the edge that follows have no link (by
        their car lanes, but a turnaround) to more than one road, and the last to none. (The
        lanes' links only: no route search, which would change what SUMO does next.)"""
        from .driving import _drivable_lanes, _links

        s = self._require()
        edge, run, seen = lane.rsplit("_", 1)[0], 0.0, set()
        while run <= reach and edge not in seen:
            seen.add(edge)
            try:
                mine = _drivable_lanes(s, edge)
            except self._exc:
                return False
            on = {ln[0].rsplit("_", 1)[0] for m in mine for ln in _links(s, m)
                  if len(ln) < 7 or str(ln[6]).lower() != "t"}
            if not on:
                return True
            if len(on) > 1:
                return False
            run += float(s.lane.getLength(f"{edge}_0"))
            edge = on.pop()
        return False

    def leads_on(self, lane: str) -> bool:
        """Whether the car can drive on a kilometre from the end of ``lane``'s road without a
        step it cannot drive (a tunnel, a turn far tighter than its full lock:
        :func:`cosim.driving.escapes`, over the lanes' links, no route search)."""
        from .driving import escapes

        try:
            return escapes(self._require(), lane.rsplit("_", 1)[0])
        except self._exc:
            return True

    def opposite_lane_at(self, lane: str, x: float, y: float):
        """The car lane of ``lane``'s road in the other direction (:func:`opposite_edge`)
        nearest to (x, y), as :meth:`snap_lane` answers; None on a one-way road."""
        from .driving import _drivable_lanes

        s = self._require()
        edge = lane.rsplit("_", 1)[0]
        if edge.startswith(":"):
            return None
        try:
            lanes = _drivable_lanes(s, self.reverse_edge(edge))
        except self._exc:
            return None
        if not lanes:
            return None
        best = min(lanes, key=lambda ln: _polyline_distance(np.asarray(s.lane.getShape(ln), dtype=float)[:, :2], x, y))
        return self._lane_point(best, self.lane_pos(best, x, y), x, y)

    def _lane_point(self, lane: str, pos: float, x: float, y: float) -> tuple:
        """:meth:`snap_lane`'s answer for ``lane`` at ``pos`` (clamped to the lane), asked
        from (x, y)."""
        shape = np.array(self._sim.lane.getShape(lane), dtype=float)
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(shape, axis=0).T))])
        pos = min(max(pos, 0.0), d[-1])
        k = min(max(int(np.searchsorted(d, pos)), 1), len(shape) - 1)
        t = (pos - d[k - 1]) / max(d[k] - d[k - 1], 1e-9)
        px, py = shape[k - 1] + t * (shape[k] - shape[k - 1])
        yaw = math.atan2(shape[k, 1] - shape[k - 1, 1], shape[k, 0] - shape[k - 1, 0])
        return lane, float(pos), float(px), float(py), yaw, math.hypot(px - x, py - y)

    def _goal_at(self, snapped: tuple) -> dict:
        """A goal's answer in ``plan_route`` from a point on a lane (:meth:`_lane_point`'s
        tuple): lane, position, point, distance and street name."""
        lane, pos, x, y, _, dist = snapped
        try:
            street = self._sim.edge.getStreetName(lane.rsplit("_", 1)[0])
        except self._exc:
            street = ""
        return dict(lane=lane, pos=pos, x=x, y=y, dist=dist, street=street)

    def _next_edges(self, edge: str) -> tuple[list[str], list[str]]:
        """The roads the lanes of ``edge`` lead to: (not by a turnaround, by one). A route
        takes a turnaround only where no other way goes (the car cannot make a tight one)."""
        s = self._sim
        ahead, back = {}, {}
        try:
            for i in range(s.edge.getLaneNumber(edge)):
                for ln in s.lane.getLinks(f"{edge}_{i}"):
                    turn = len(ln) >= 7 and str(ln[6]).lower() == "t"
                    (back if turn else ahead)[ln[0].rsplit("_", 1)[0]] = True
        except self._exc:
            return [], []
        return list(ahead), [e for e in back if e not in ahead]

    def _route_from(self, firsts, to_edge: str, head=None):
        """SUMO's fastest route from one of the edges ``firsts`` to ``to_edge``, or None. With
        ``head`` (the edges before), the fastest of those with the fewest steps the car cannot
        drive (:func:`cosim.driving.undrivable_steps`: SUMO's router takes U-turns over a
        junction's 0.2 m edges; a Monaco route back round to the start's road took two)."""
        best, key = None, None
        for first in firsts:
            try:
                r = self._sim.simulation.findRoute(first, to_edge, vType="DEFAULT_VEHTYPE")
            except self._exc:
                continue
            if not r.edges:
                continue
            k = (0 if head is None else len(undrivable_steps(self._sim, list(head) + list(r.edges))), r.travelTime)
            if best is None or k < key:
                best, key = r, k
        return best

    def _drivable_route(self, firsts, head, lanes):
        """The car's own route (:func:`cosim.driving.route_without_turnarounds`: no turn it
        cannot make, no tunnel) from one of the edges ``firsts`` (after ``head``) to the road of
        the first of ``lanes`` it reaches: (route, that lane), or None."""
        from .driving import route_without_turnarounds

        seen = set()
        for ln in lanes:
            dst = ln.rsplit("_", 1)[0]
            if dst in seen:
                continue
            seen.add(dst)
            for first in firsts:
                r = route_without_turnarounds(self._sim, first, dst) if first != dst else [dst]
                if r:
                    return list(head) + r, ln
        return None

    def _lanes_near(self, x: float, y: float, radius: float, vclass: str = "passenger", most: int = 12) -> list:
        """(distance, lane) of the lanes on the surface a ``vclass`` may use within ``radius``
        of (x, y), nearest first, one lane an edge, at most ``most``."""
        from .driving import _lane_allows, off_the_world

        s = self._sim
        found = {}
        for ln in s.lane.getIDList():
            if ln.startswith(":"):
                continue
            P = np.asarray(s.lane.getShape(ln), dtype=float)
            if len(P) < 2 or (P[:, 0].min() - radius > x or P[:, 0].max() + radius < x
                              or P[:, 1].min() - radius > y or P[:, 1].max() + radius < y):
                continue
            d = _polyline_distance(P, x, y)
            edge = ln.rsplit("_", 1)[0]
            if d <= radius and d < found.get(edge, (math.inf,))[0] and _lane_allows(s, ln, vclass) \
                    and not off_the_world(s, edge):
                found[edge] = (d, ln)
        return sorted(found.values())[:most]

    def _in_window(self, x: float, y: float) -> bool:
        """Whether (x, y) lies in the square of chunks this network's world was built for
        (:func:`cosim.demand.world_extent`); True where there is none."""
        from .demand import world_extent

        key = str(self.net_file)
        if key not in self._extents:
            self._extents[key] = world_extent(self.net_file)
        e = self._extents[key]
        return e is None or (e[0] <= x <= e[2] and e[1] <= y <= e[3])

    def lane_pos(self, lane: str, x: float, y: float) -> float:
        """Position along ``lane`` of the point of it nearest to (x, y)."""
        shape = np.array(self._require().lane.getShape(lane), dtype=float)
        p, v = shape[:-1], np.diff(shape, axis=0)
        L2 = np.maximum(np.einsum("ij,ij->i", v, v), 1e-18)
        t = np.clip(np.einsum("ij,ij->i", np.array([x, y]) - p, v) / L2, 0.0, 1.0)
        dd = np.hypot(*(p + t[:, None] * v - (x, y)).T)
        a = int(np.argmin(dd))
        return float(np.concatenate([[0.0], np.cumsum(np.sqrt(L2))])[a] + t[a] * math.sqrt(L2[a]))

    def random_extension_path(self, route, first: int, rng_state, start_lane: str, min_len: float = 800.0,
                              back_max: int = 6, lead_in: tuple = ()):
        """:meth:`random_extension`, and where it drives on from the route's last edge, the
        lane path of the extension from ``start_lane`` (``cosim.driving.LanePath``, as
        ``LanePath.extended`` builds it), else None: (k, edges, generator state, path). Built
        here, where the draw just read the same lanes (in the main process, one extension's
        path read 57 turns again across the pipe: 45 ms)."""
        kw = dict(min_len=min_len, back_max=back_max, start_lane=start_lane)
        if lead_in:
            kw["lead_in"] = _plain_points(lead_in)
        return self._extension_answer(route, first, rng_state, kw)

    def random_extension(self, route, first: int, rng_state, min_len: float = 800.0, back_max: int = 6):
        """How to drive on at the end of ``route`` (the car on ``route[first]``): (index ``k``
        into ``route``, a random route from ``route[k]``, the generator's state). ``k`` is the
        last edge, unless every way on from there has a turn the car cannot make (the route
        ends in a one-way street down to a hairpin): then the latest of the ``back_max`` edges
        before it, back to the car's, from which a way without one leaves.

        Drawn ahead by :meth:`prepare_extension` where it was asked for with the same route,
        generator state and lengths (finished here if it is not done yet); the answer is the
        same either way."""
        return self._extension_answer(route, first, rng_state, dict(min_len=min_len, back_max=back_max))[:3]

    def _extension_answer(self, route, first: int, rng_state, kw: dict):
        job, self._extension = self._extension, None
        if job is not None and job["key"] == (tuple(route), rng_state, tuple(sorted(kw.items()))):
            if job["result"] is None:
                self._work_on_extension(None, job)
            status, value = job["result"]
            if status == "err":
                raise value
            if value[0] >= first or value[0] == len(route) - 1:
                return value
            # (drawn back to an edge the car has passed since: drawn again from here)
        return _run_steps(self._extension_steps(route, first, rng_state, **kw))

    def prepare_extension(self, route, first: int, rng_state, min_len: float = 800.0, back_max: int = 6,
                          start_lane: str | None = None, lead_in: tuple = ()) -> None:
        """Start drawing ``random_extension(route, first, rng_state, ...)`` (with
        ``start_lane``, ``random_extension_path``) in the background: :data:`EXTENSION_STEP_PIECES`
        of it after each step. A route extension drawn all at once took 60-130 ms in one frame
        (40 or more random routes, each checked for the turns the car cannot make), against a
        frame of 3-4 ms."""
        kw = dict(min_len=min_len, back_max=back_max)
        if start_lane is not None:
            kw["start_lane"] = start_lane
        if lead_in:
            kw["lead_in"] = _plain_points(lead_in)
        self._extension = {"key": (tuple(route), rng_state, tuple(sorted(kw.items()))), "result": None,
                           "steps": self._extension_steps(route, first, rng_state, **kw)}

    def warm_routes(self, on: bool = True) -> None:
        """Work out the route graph's steps (``cosim.driving._drivable_nexts``: the turns the
        car can make from each edge a car may use), :data:`EXTENSION_STEP_BUDGET_S` after each
        step (in SUMO's worker process: while it waits for a request, ``background_work``),
        so that a route drawn later finds them done: a draw on streets not searched before
        took up to 100 ms in one step (Helsinki: about 0.3 s in all). The answers are the
        same, warmed or not."""
        self._warm = self._warm_steps() if on else None

    def _warm_steps(self):
        from .driving import route_graph_steps

        yield                          # (the car edges listed in the next step: 15 ms on Helsinki)
        yield from route_graph_steps(self._require(), list(self._car_edges()))

    def _warm_up_routes(self, budget_s: float) -> None:
        end = time.perf_counter() + budget_s
        try:
            while time.perf_counter() < end:
                next(self._warm)
        except StopIteration:
            self._warm = None

    def extension_ready(self) -> bool:
        """A prepared extension has been drawn (for tests and benchmarks)."""
        return self._extension is not None and self._extension["result"] is not None

    def _work_on_extension(self, pieces: int | None, job=None) -> None:
        """Draw the prepared extension on, for ``pieces`` pieces (None: to the end)."""
        job = job or self._extension
        if job is None or job["result"] is not None:
            return
        try:
            for _ in itertools.count() if pieces is None else range(pieces):
                next(job["steps"])
        except StopIteration as e:
            job["result"] = ("ok", e.value)
        except Exception as e:      # (raised where the answer is asked for: _extension_answer)
            job["result"] = ("err", e)

    def _extension_steps(self, route, first: int, rng_state, min_len: float, back_max: int,
                         start_lane: str | None = None, lead_in: tuple = ()):
        """:meth:`random_extension` (with ``start_lane``, :meth:`random_extension_path`), a
        random route drawn at a time (a generator: its value is the answer)."""
        rng = random.Random()
        rng.setstate(rng_state)
        n = len(route)
        more, clean = yield from self._draw_route_steps(route[-1], rng, min_len)
        if not clean:
            for k in range(n - 2, max(first, n - 1 - back_max) - 1, -1):
                try:
                    alt, ok = yield from self._draw_route_steps(route[k], rng, min_len)
                except SimulationError:
                    continue
                if ok:
                    return (k, alt, rng.getstate()) + ((None,) if start_lane is not None else ())
        if start_lane is None:
            return n - 1, more, rng.getstate()
        tail = None
        if len(more) >= 2:
            yield
            try:
                tail = yield from self._lane_path_steps(more, start_lane, lead_in)
            except self._exc + (ValueError,):
                tail = None          # (the main process builds it, and says why)
        return n - 1, more, rng.getstate(), tail

    def random_route(self, edge: str, rng_state, min_len: float = 800.0):
        """A route from ``edge`` of at least ``min_len`` m to an edge drawn at random, through no
        tunnel and no turn the car cannot make, to an edge the car can drive on from
        (``cosim.driving.escapes``); else the longest such route of the 40 tries
        (shorter: the car draws again at its end); else the first long one found, with such a
        turn (every way from here has one: a one-way street down a hairpin); else the longest
        route of the tries: (edges, the random generator's state after the draws)."""
        rng = random.Random()
        rng.setstate(rng_state)
        route, _clean = self._draw_route(edge, rng, min_len)
        return route, rng.getstate()

    def _draw_route(self, edge: str, rng: random.Random, min_len: float) -> tuple[list, bool]:
        """``random_route``'s draw with ``rng``: (edges, whether it has no tunnel and no turn
        the car cannot make)."""
        return _run_steps(self._draw_route_steps(edge, rng, min_len))

    def _draw_route_steps(self, edge: str, rng: random.Random, min_len: float):
        """:meth:`_draw_route`, a destination at a time (a generator: its value is the answer)."""
        from .driving import escapes_steps, off_the_world, undrivable_steps_steps, without_turnarounds_steps

        s = self._require()
        key = self._net_key()
        if getattr(self, "_every_key", None) != key:
            self._every = [e for e in s.edge.getIDList() if not e.startswith(":")]
            self._every_key = key
        every = self._every
        best, fallback = [edge], None
        clean, clean_len = None, 0.0
        for k in range(80):
            # (40 draws among all edges; if none of them gave a route, 40 among the edges a car
            # can use: most edges are footways, rails and the like, with no route to them)
            if k >= 40 and (clean is not None or fallback is not None or len(best) >= 2):
                break
            if k:
                yield
            to = rng.choice(every if k < 40 else self._car_edges())
            try:
                r = s.simulation.findRoute(edge, to, vType="DEFAULT_VEHTYPE")
            except self._exc:
                continue
            if not r.edges:
                continue
            # through a tunnel (the world has none) or a turn the car cannot make (a hairpin
            # drawn tighter than its full lock) with no way around: another destination
            # or ending where every way on has one (the head of a one-way street down to a
            # hairpin: the route drawn after this one could only go through it)
            # (a clean route is returned with its detours made here, where libsumo answers
            # in-process: the car's lane path would look for them again across the pipe, 1.9 s
            # for one extension of the default run)
            fixed = list(r.edges)
            bad = len(fixed) >= 2 and any(off_the_world(s, e) for e in fixed)
            if len(fixed) >= 2 and not bad:
                fixed = (yield from without_turnarounds_steps(s, fixed))[0]
                bad = bool((yield from undrivable_steps_steps(s, fixed))) or not (yield from escapes_steps(s, fixed[-1]))
            if r.length >= min_len:
                if bad:
                    fallback = fallback or list(r.edges)
                    continue
                return fixed, True
            if len(r.edges) > len(best):
                best = list(r.edges)
            if not bad and len(fixed) >= 2 and r.length > clean_len:
                clean, clean_len = fixed, float(r.length)
        if clean is not None:
            return clean, True
        if fallback is not None:
            # every long route drawn has a step the car cannot drive: drive it only up to the
            # last edge before that step from which the car can still go on (Monaco, seed 25: a
            # route drawn down a one-way street to a hairpin of 3.1 m radius; the car ran 2.4 m
            # wide into a building). At the end the car draws again (random_extension). Where
            # it cannot go on from anywhere on the way (up the one-way street already), it has
            # no other way than that step: the route all the same
            cut = yield from self._drivable_head_steps(fallback)
            if (yield from escapes_steps(s, cut[-1])):
                return cut, False
            # nor from anywhere on the way (a pocket of streets, or a one-way street, whose ways
            # out all pass a tunnel or such a turn): up to that step and back where the road has
            # a U-turn there (the car turns round in moves: cosim.turnround); else, before a
            # tunnel, up to it, where the car stops (Monaco's Boulevard du Larvotto, one way, goes
            # on only into its tunnel, which the world has not: the car drove in at 9 m/s into
            # Avenue d'Ostende's sidewalk); before a turn, through it all the same (the car
            # follows it closely and slowly where its sweep would touch something)
            head, back, tunnel = yield from self._turned_back_steps(fallback)
            return (back or (head if tunnel else fallback)), False
        if len(best) < 2:
            # no draw reached another road (a street of a few edges whose ends are dead ends, or
            # lead only onto ways closed to cars: Lauf's Steyrer Straße, 23904724): along it to
            # its end and back, where it has a U-turn there (the car turns round in moves:
            # cosim.turnround)
            back = self._along_and_back(edge)
            if back is None:
                raise SimulationError(f"no route for the ego from edge {edge}")
            return back, False
        return best, False

    def _car_edges(self) -> list:
        """The network's edges with a lane a car may use (where ``_draw_route`` draws again when
        40 draws among all edges gave no route: seven in eight edges are footways, rails and the
        like with no route to them, and on a Helsinki network with its bridges kept apart all 40
        draws of seed 1 missed)."""
        cached = getattr(self, "_car_edges_cache", None)
        if cached is None:
            s = self._require()
            cached = []
            for e in s.edge.getIDList():
                if e.startswith(":"):
                    continue
                for i in range(s.edge.getLaneNumber(e)):
                    allowed = s.lane.getAllowed(f"{e}_{i}")
                    if "passenger" in allowed or (not allowed and "passenger" not in s.lane.getDisallowed(f"{e}_{i}")):
                        cached.append(e)
                        break
            self._car_edges_cache = cached
        return cached

    def _drivable_head(self, route: list) -> list:
        """``route`` (around what it can go around: ``without_turnarounds``) up to its first
        step the car cannot drive or tunnel, and back from there to the last edge from which
        the car can drive on (``escapes``: not into a one-way street down to that step)."""
        return _run_steps(self._drivable_head_steps(route))

    def _drivable_head_steps(self, route: list):
        """:meth:`_drivable_head` as a generator (yielding in its searches: its value is the
        answer; in one piece it took up to 9.5 ms in the step that drew the car's next route)."""
        from .driving import escapes_steps

        s = self._require()
        fixed, end = yield from self._head_steps(route)
        while end > 1 and not (yield from escapes_steps(s, fixed[end - 1])):
            end -= 1
        return fixed[:end]

    def _head_steps(self, route: list):
        """(``route`` around what it can go around (``without_turnarounds``), the index of its
        first step the car cannot drive or tunnel): a generator, yielding in its searches,
        whose value is the answer."""
        from .driving import off_the_world, undrivable_steps_steps, without_turnarounds_steps

        s = self._require()
        fixed = (yield from without_turnarounds_steps(s, list(route)))[0]
        bad = yield from undrivable_steps_steps(s, fixed)
        end = len(fixed)
        if bad:
            end = next(k for k in range(len(fixed) - 1) if (fixed[k], fixed[k + 1]) == bad[0]) + 1
        tun = next((k for k in range(1, end) if off_the_world(s, fixed[k])), None)
        if tun is not None:
            end = tun
        return fixed, end

    def _has_uturn(self, edge: str) -> bool:
        """Does a lane of ``edge`` for cars link to its road's other direction (a U-turn)?"""
        from .driving import _drivable_lanes, _lane_allows, _links

        s = self._require()
        opp = self.reverse_edge(edge)
        try:
            return any(link[0].rsplit("_", 1)[0] == opp and _lane_allows(s, link[0])
                       for ln in _drivable_lanes(s, edge) for link in _links(s, ln))
        except self._exc:
            return False

    def _along_and_back(self, edge: str, max_edges: int = 50) -> list | None:
        """From ``edge`` on along the road (each edge's first step the car can drive,
        ``cosim.driving._drivable_nexts``, to an edge not yet on the way and not back onto the
        road's other direction): round to an edge on the way again where it loops, else to where
        it goes on no further and back by the last U-turn on the way (Lauf's Steyrer Straße,
        23904724), or with none there, up to where it goes on no further; None where the way has
        none for cars."""
        from .driving import _drivable_nexts

        s = self._require()
        route = [edge]
        try:
            while len(route) < max_edges:
                here = route[-1]
                nexts = [(ne, via) for ne, _w, via in _drivable_nexts(s, here) if ne != self.reverse_edge(here)]
                ne, via = next(((ne, via) for ne, via in nexts if ne not in route), (None, None))
                if ne is None:
                    if nexts:                   # (it loops: round to the edge on the way again)
                        ne, via = nexts[0]
                        return route + ([via] if via else []) + [ne]
                    break
                route += ([via] if via else []) + [ne]
        except self._exc:
            return None
        # back along the way to the last edge with a U-turn (Steyrer Straße's 23904724#2: the
        # way on from 23904459#1 is a turn the car cannot make, and it has no U-turn); with
        # none, the way up to where it goes on no further, where the car stops (Helsinki's
        # Alvar Aallon katu, -224479207#1: its every way on passes a tunnel, and no random
        # draw of seed 0 reached another road: "no route for the ego")
        k = next((k for k in range(len(route) - 1, -1, -1) if self._has_uturn(route[k])), None)
        if k is None:
            return route if len(route) >= 2 else None
        return route[:k + 1] + [self.reverse_edge(route[k])]

    def _turned_back_steps(self, route: list):
        """(``route`` up to its first step the car cannot drive or tunnel, that and then back
        onto its last edge's other direction by its U-turn or None where the edge has no U-turn
        there for cars, whether that step enters a tunnel): a generator, yielding in its
        searches, whose value is the answer."""
        from .driving import off_the_world

        fixed, end = yield from self._head_steps(route)
        head = fixed[:end]
        tunnel = end < len(fixed) and off_the_world(self._require(), fixed[end])
        return head, (head + [self.reverse_edge(head[-1])] if self._has_uturn(head[-1]) else None), tunnel

    def plan_route(self, lane: str, pos: float, goal_xy=None, rng_state=None, max_goal_snap_m: float = 1e9,
                   min_len: float = 800.0, keep_lane: bool = False, at_xy=None, beyond_ok: bool = False) -> dict:
        """The ego's route from ``pos`` on ``lane``, and its ``LanePath``: to the lane nearest to
        ``goal_xy`` (SUMO's router), else a random route (``random_route``). ``goal`` in the
        answer: snapped lane, point and distance; ``route`` is empty and ``path`` None when the
        goal is too far from a road or cannot be reached. With ``keep_lane``, the route's next
        road is one that ``lane`` itself leads to (no lane change on this road): the fastest
        such way to the goal, else a random route on from one of them; with ``at_xy`` too, from
        the lane of ``lane``'s road nearest to that point (the lane the car is in) and its
        position there. With ``beyond_ok``, a goal further than ``max_goal_snap_m`` from this
        network's roads (a streamed window that does not reach it) is routed to its nearest road
        here, and the answer's goal says ``beyond``."""
        s = self._require()
        edge = lane.rsplit("_", 1)[0]
        firsts = [edge]
        if keep_lane:
            try:
                if at_xy is not None:
                    x, y = float(at_xy[0]), float(at_xy[1])
                    ids = [f"{edge}_{i}" for i in range(s.edge.getLaneNumber(edge))]
                    lane = min(ids, key=lambda ln: _polyline_distance(
                        np.asarray(s.lane.getShape(ln), dtype=float)[:, :2], x, y))
                    pos = max(0.0, self.lane_pos(lane, x, y))
                links = s.lane.getLinks(lane)
            except self._exc as e:
                raise SimulationError(f"SUMO has no lane {lane}: {e}") from None
            # (not a turnaround: too tight for the car to take from a standstill in a queue)
            firsts = list(dict.fromkeys(ln[0].rsplit("_", 1)[0] for ln in links
                                        if len(ln) < 7 or str(ln[6]).lower() != "t"))
            if not firsts:
                raise SimulationError(f"lane {lane} leads nowhere")
        head = [edge] if keep_lane else []
        out = _plan(lane, pos, rng_state)
        if goal_xy is not None:
            gx, gy = float(goal_xy[0]), float(goal_xy[1])
            out["goal"] = self._goal_at(self.snap_lane(gx, gy))
            glane, gdist = out["goal"]["lane"], out["goal"]["dist"]
            if gdist > max_goal_snap_m:
                if not beyond_ok:
                    return dict(out, route=[], path=None)
                out["goal"]["beyond"] = True
            gedge = glane.rsplit("_", 1)[0]
            turns = ()
            loop = not keep_lane and gedge == edge and self.lane_pos(glane, gx, gy) < pos
            if loop:
                # the goal behind the car on its own road: round the block back to it (SUMO's
                # route from a road to itself is that road alone: a Monaco start and goal on
                # one way gave "route 10 m", and the car stood short of a goal 70 m behind it)
                (firsts, turns), head = self._next_edges(edge), [edge]

            def route_to(to_edge):
                if not loop:
                    return self._route_from(firsts, to_edge)
                r = self._route_from(firsts, to_edge, head) or self._route_from(turns, to_edge, head)
                if r is not None and undrivable_steps(s, without_turnarounds(s, head + list(r.edges))[0]):
                    # (only by a turn the car cannot make, with no way round it: Monaco's Liaison
                    # Marquet, a passage into the stadium, left by U-turns over 0.2 m edges; the
                    # car ran 5 m wide of the first into a sign)
                    return None
                return r

            best = route_to(gedge)
            beyond = bool(out["goal"].get("beyond"))
            if best is None and beyond_ok and not beyond and not self._in_window(gx, gy):
                # a goal outside the chunks this network was built for (a streamed window), near
                # a road of the window's that its cut left without a way in: as for a goal beyond
                # it (a Monaco goal 100 m past a window's edge snapped to Avenue de la Costa, 19 m
                # off, whose way in was cut: "goal unreachable" at the swap)
                beyond = True
            radius = max_goal_snap_m if not beyond else gdist + BEYOND_SEARCH_M

            def goal_on(ln):                # (another road near the goal, the one taken)
                out["goal"] = self._goal_at(self._lane_point(ln, self.lane_pos(ln, gx, gy), gx, gy))
                if beyond and out["goal"]["dist"] > max_goal_snap_m:
                    out["goal"]["beyond"] = True

            if best is None and (gdist <= max_goal_snap_m or beyond):
                # the nearest road does not lead there (cut off where the OSM extract ends, say:
                # "goal unreachable" though a road the car reaches lay 50 m off): the nearest
                # one within the snap distance that it does reach; for a goal beyond this
                # network (a streamed window), the nearest one it reaches within BEYOND_SEARCH_M
                # more (the nearest road of a Portland window was the Marquam Bridge's deck,
                # 161 m from the goal and not reachable: the run ended at the swap)
                for d, ln in self._lanes_near(gx, gy, radius):
                    if ln.rsplit("_", 1)[0] == glane.rsplit("_", 1)[0]:
                        continue
                    best = route_to(ln.rsplit("_", 1)[0])
                    if best is not None:
                        goal_on(ln)
                        break
            if best is None:
                return dict(out, route=[], path=None)
            route = head + list(best.edges)
            path = self.lane_path(route, start_lane=lane, start_pos=pos)
            if not loop and undrivable_steps(s, path.edges):
                # SUMO's fastest route takes a turn the car cannot make (a U-turn at a junction)
                # or a tunnel (the world has none), with no way round near it: the car's own
                # router, to the goal's road or another near it. (A Monaco start heading west
                # towards the city's end, its goal to the east: the route turned at a junction,
                # and the car ran 6 m wide into a building; no road the car can drive leads
                # back from there.)
                lanes = [out["goal"]["lane"]] + [ln for _, ln in self._lanes_near(gx, gy, radius)]
                alt = self._drivable_route(firsts, head, lanes)
                if alt is None:
                    # none: SUMO's route up to its first step the car cannot drive and back by
                    # the U-turn there, which the car makes in moves (cosim.turnround), then
                    # the car's own route (Helsinki: from Mikonkatu, 17058783#1, the only way to
                    # a goal on Lönnrotinkatu turns round at the street's north end: "goal
                    # unreachable")
                    _, turned, _ = _run_steps(self._turned_back_steps(route))
                    if turned is not None:
                        alt = self._drivable_route([turned[-1]], turned[:-1], lanes)
                if alt is not None:
                    route, ln = alt
                    if ln != out["goal"]["lane"]:
                        goal_on(ln)
                    path = self.lane_path(route, start_lane=lane, start_pos=pos)
                elif not beyond_ok:
                    return dict(out, route=[], path=None, undrivable=True)
            return dict(out, route=route, path=path)
        else:
            first = firsts[0]
            if len(firsts) > 1:
                rng = random.Random()
                rng.setstate(rng_state)
                first = rng.choice(firsts)
                rng_state = rng.getstate()
            more, out["rng_state"] = self.random_route(first, rng_state, min_len)
            route = head + list(more)
        return dict(out, route=route, path=self.lane_path(route, start_lane=lane, start_pos=pos))

    def replan_from(self, lanes, x: float, y: float, yaw: float, route=(), **kw) -> dict:
        """``plan_route`` from the car at (x, y, yaw) on this network (after a swap): from its
        position on ``lanes[0]`` (the lane it is on in the old path) if this network has that
        lane, or on the lane of the same edge under the car if that is nearer by half a metre
        (mid-way through a lane change); else from the lane under it if that runs its way; else from the start of the
        next of ``lanes`` this network has; else from the nearest lane. Without a goal, the rest
        of the old ``route`` (from the start lane's edge on) is kept where this network has all
        of it: the car keeps its lanes (a new route may want another lane at once, a lane
        change in a queue)."""
        s = self._require()
        known = self._id_set("lane")
        try:
            snapped = self.snap_lane(x, y)
        except SimulationError:
            snapped = None
        # the lane under the car, if it runs the car's way: (lane, position, distance)
        under = None
        if snapped is not None and abs(math.remainder(snapped[4] - yaw, math.tau)) < math.pi / 4:
            under = (snapped[0], snapped[1], snapped[5])
        start = None
        if lanes and lanes[0] in known:
            start = (lanes[0], self.lane_pos(lanes[0], x, y))
            # along a lane change the old path names the lane it changes into, and the car may
            # still be on the one it came from (Helsinki, seed 37: a swap on a 16 m edge; the new
            # path began on the next lane, 3 m beside the car, which drove over to it through a
            # standing queue): the lane under the car, if it is one of the same edge
            if under is not None and under[0] != lanes[0] and not lanes[0].startswith(":") \
                    and under[0].rsplit("_", 1)[0] == lanes[0].rsplit("_", 1)[0] \
                    and under[2] < _polyline_distance(np.asarray(s.lane.getShape(lanes[0]), dtype=float), x, y) - 0.5:
                start = under[:2]
        elif under is not None and under[2] < 2.0:
            start = under[:2]
        if start is None:
            nxt = next((ln for ln in lanes[1:] if ln in known and not ln.startswith(":")), None)
            start = (nxt, 0.0) if nxt else (snapped or self.snap_lane(x, y))[:2]
        edge = start[0].rsplit("_", 1)[0]
        route = list(route)
        if kw.get("goal_xy") is None and edge in route:
            rest = route[route.index(edge):]
            if len(rest) >= 2 and all(e in self._edge_set() for e in rest):
                try:
                    return dict(_plan(start[0], start[1], kw.get("rng_state")), route=rest,
                                path=self.lane_path(rest, start_lane=start[0], start_pos=start[1]))
                except (ValueError, SimulationError):
                    pass
        return self.plan_route(start[0], start[1], **kw)

    def _lane_path_steps(self, edges: Sequence[str], start_lane: str | None, lead_in: tuple = ()):
        """:meth:`lane_path` built in pieces (a generator: its value is the path)."""
        from .driving import LanePath

        path = object.__new__(LanePath)
        yield from path.build_steps(self._require(), list(edges), start_lane=start_lane, lead_in=lead_in or None)
        return path

    def lane_path(self, edges: Sequence[str], start_lane: str | None = None, start_pos: float = 0.0):
        """``cosim.driving.LanePath`` along ``edges`` on this SUMO's network. Built where SUMO
        runs: in SUMO's worker process it reads hundreds of lane shapes and links, which would
        otherwise each be a round trip (a re-plan after a network swap took 165 ms that way)."""
        from .driving import LanePath

        return LanePath(self._require(), list(edges), start_lane=start_lane, start_pos=start_pos)

    def actors_near_getters(self, x: float, y: float, radius: float) -> ActorsSnapshot:
        """Same result as :meth:`actors_near` with per-actor getter calls (reference/benchmark)."""
        s = self._require()
        rows = []
        for vid in s.vehicle.getIDList():
            if vid == EGO_ID:
                continue
            px, py = s.vehicle.getPosition(vid)
            if math.hypot(px - x, py - y) > radius + CONTEXT_MARGIN:
                continue
            rows.append((vid, s.vehicle.getVehicleClass(vid), px, py, s.vehicle.getAngle(vid),
                         s.vehicle.getLength(vid), s.vehicle.getWidth(vid), s.vehicle.getHeight(vid),
                         s.vehicle.getSpeed(vid), s.vehicle.getSlope(vid)))
        for pid in s.person.getIDList():
            px, py = s.person.getPosition(pid)
            if math.hypot(px - x, py - y) > radius + CONTEXT_MARGIN or s.person.getVehicle(pid):
                continue
            rows.append((pid, "person", px, py, s.person.getAngle(pid), s.person.getLength(pid),
                         s.person.getWidth(pid), s.person.getHeight(pid), s.person.getSpeed(pid),
                         s.person.getSlope(pid)))
        if not rows:
            return ActorsSnapshot.empty(self.sim_time)
        ids = np.array([r[0] for r in rows], dtype=object)
        kind = np.array([r[1] for r in rows], dtype=object)
        a = np.array([r[2:] for r in rows], dtype=float).T
        cx, cy = front_to_center(a[0], a[1], a[2], a[3])
        keep = np.hypot(cx - x, cy - y) <= radius
        return ActorsSnapshot(self.sim_time, ids[keep], kind[keep], cx[keep], cy[keep],
                              sumo_angle_to_yaw(a[2])[keep], a[3][keep], a[4][keep], a[5][keep],
                              a[6][keep], a[7][keep])

    # --- network ------------------------------------------------------------------------
    def incoming_lanes(self) -> dict[str, list[str]]:
        """lane -> the normal lanes with a link into it (one call: cached per network)."""
        self._read_links()
        return self._incoming

    def _net_key(self) -> tuple:
        """What a cached reading of the network is of: this SUMO load of this network file
        (a swap's adopt, on a SUMO started ahead on the new network, keeps it)."""
        return self._loads, str(self.net_file)

    def edge_ends(self) -> dict[str, tuple[str, str]]:
        """edge -> (its from-junction, its to-junction), every normal edge of the network (one
        call: cached per network). The autopilot asks whether an actor's road meets a junction
        of its path; asked edge by edge, a road first seen in a frame waited for SUMO's step in
        flight (2 ms) where SUMO runs in its worker process."""
        key = self._net_key()
        if getattr(self, "_edge_ends_key", None) != key:
            s = self._require()
            fr, to = s.edge.getFromJunction, s.edge.getToJunction
            self._edge_ends = {e: (fr(e), to(e)) for e in s.edge.getIDList() if not e.startswith(":")}
            self._edge_ends_key = key
        return self._edge_ends

    def reverse_edge(self, edge: str) -> str:
        """``edge``'s road in the other direction (:func:`reverses`: "-X", else an edge between
        the same two junctions the other way; read when first asked, kept per network), else
        :func:`opposite_edge`'s name (an edge the network does not have)."""
        key = self._net_key()
        if getattr(self, "_reverse_key", None) != key:
            self._reverse, self._reverse_key = {}, key
        got = self._reverse.get(edge)
        if got is None:
            ends = self.edge_ends()
            got = opposite_edge(edge)
            if got not in ends and edge in ends:
                try:            # (the candidates: the edges out of its to-junction)
                    outs = self._require().junction.getOutgoingEdges(ends[edge][1])
                except self._exc:
                    outs = ()
                got = min((e for e in outs if reverses(ends, edge, e)), default=got)
            self._reverse[edge] = got
        return got

    def via_lanes(self) -> dict[str, tuple]:
        """normal lane -> the junction lanes its links go through, both halves of a link a
        junction splits (one call: cached per network)."""
        self._read_links()
        return self._vias

    def lane_links(self) -> dict[str, tuple]:
        """lane -> ``lane.getLinks(lane)``, every lane of the network, junction lanes too (one
        call: cached per network). For the network's shape (route searches): the lights'
        states in it are those of the moment it was read."""
        key = self._net_key()
        if getattr(self, "_links_key", None) != key:
            s = self._require()
            self._links = {lane: tuple(s.lane.getLinks(lane)) for lane in s.lane.getIDList()}
            self._links_key = key
        return self._links

    def _read_links(self) -> None:
        key = self._net_key()
        if getattr(self, "_incoming_key", None) != key:
            s = self._require()
            inc: dict = {}
            vias: dict = {}
            for lane, links in self.lane_links().items():
                if lane.startswith(":"):
                    continue
                for link in links:
                    inc.setdefault(link[0], []).append(lane)
                vias[lane] = tuple(sorted({v for k in links if k[4] for v in _via_lanes(s, k[4])}))
            self._incoming, self._vias, self._incoming_key = inc, vias, key

    # --- traffic lights -----------------------------------------------------------------
    def tls_states(self) -> dict[str, str]:
        """tls id -> SUMO state string ('rGyy...', one char per controlled link)."""
        s = self._require()
        get = s.trafficlight.getRedYellowGreenState
        try:
            out = {tid: get(tid) for tid in self._tls_ids}
        except self._exc as e:
            raise SimulationError(f"SUMO traffic-light query failed: {e}") from None
        out.update(self._tls_fresh)
        return out

    def set_tls_state(self, tls_id: str, state: str) -> None:
        """Force a traffic light's state (it stays until the program is set again)."""
        s = self._require()
        try:
            s.trafficlight.setRedYellowGreenState(tls_id, state)
        except self._exc as e:
            raise SimulationError(f"cannot set traffic light {tls_id}: {e}") from None
        self._tls_fresh[tls_id] = state

    def ego_next_tls(self) -> tuple[str, float, str] | None:
        """(tls id, distance in m from the ego's front to the stop line, state char) or None."""
        s = self._require()
        if not self._ego_in_sim:
            return None
        try:
            nxt = s.vehicle.getNextTLS(EGO_ID)
            if nxt:
                tid, idx, dist, state = nxt[0]
                return tid, float(dist), self._tls_fresh.get(tid, "")[idx:idx + 1] or state
            # the ego's route may end on this edge (moveToXY replaced it): use the lane's link
            lane = s.vehicle.getLaneID(EGO_ID)
            hit = self._lane_tls.get(lane)
            if not hit:
                return None
            tid, idx = hit
            dist = s.lane.getLength(lane) - s.vehicle.getLanePosition(EGO_ID)
            state = self.tls_states().get(tid) or s.trafficlight.getRedYellowGreenState(tid)
            return tid, float(dist), state[idx]
        except self._exc:
            return None

    # --- network swap -------------------------------------------------------------------
    def swap_network(self, new_net, new_routes: Sequence = (), keep_radius: float = 100.0,
                     center: tuple[float, float] | None = None) -> dict[str, str]:
        """Restart SUMO on another network, carrying the actors near the ego across.

        Vehicles and walking persons whose centre is within ``keep_radius`` of the ego (or of
        ``center``) are re-inserted at the same position, heading and speed, with the rest of
        their route where the new network has it. Simulation time continues: after the swap
        ``sim_time`` is the time before it and the kept actors stand where they stood. Kept
        actors get new SUMO ids (``<id>~<n>``) so they cannot clash with the new demand; the
        return value maps old id -> new id (for the mirror to re-key its bodies).

        It is ``swap_capture`` on this SUMO, a restart on the new network, then ``swap_adopt``
        (``cosim.sumo_process.TrafficProcess`` starts the new SUMO in a second process ahead
        of time and does the same two halves, without the restart in between).
        """
        carry = self.swap_capture(keep_radius, center)
        self.teardown()
        self._car_edges_cache = None
        self._extension = None
        self._warm = None
        self.net_file = Path(new_net)
        if isinstance(new_routes, (str, os.PathLike)):
            new_routes = [new_routes]
        self.route_files = [Path(p) for p in new_routes]
        self._generation += 1
        self.setup()
        return self.swap_adopt(carry)

    def swap_capture(self, keep_radius: float = 100.0, center: tuple[float, float] | None = None) -> dict:
        """The first half of a swap: what goes across to the next SUMO (picklable): the actors
        within ``keep_radius`` of the ego (or ``center``), the ego, the clock and the counters."""
        self._require()
        ego = self.ego_state() if self._ego_in_sim else None
        if center is None:
            if ego is None:
                raise SimulationError("swap_network needs the ego in SUMO or an explicit center")
            center = (ego["x"], ego["y"])
        cx, cy = float(center[0]), float(center[1])
        try:
            kept = self._capture(cx, cy, float(keep_radius))
        except self._exc as e:
            raise SimulationError(f"cannot read SUMO state for the swap: {e}") from None
        return dict(kept=kept, ego=ego, center=(cx, cy), keep_radius=float(keep_radius),
                    ego_spec=dict(self._ego_spec) if self._ego_added else None,
                    ego_speed=self._ego_pending_speed, t_before=self.sim_time, stats=self.stats,
                    generation=self._generation)

    def swap_adopt(self, carry: dict, advance: bool = False, ego_pose: tuple | None = None) -> dict[str, str]:
        """The second half of a swap, on a SUMO just started on the new network: its own
        demand's actors around the ego make room (after one step, which inserts the demand's
        trips in progress), the carried actors and the ego are inserted where they were, and
        the clock continues. Returns old id -> new id of the actors carried over.

        With ``advance``, it is also the loop's next step, in one SUMO step instead of two
        hidden ones and a step: vehicles go in where their speed takes them in that step,
        the ego where ``ego_pose`` (x, y, yaw, speed) says, and the clock reads one step after
        the capture (persons go in where they were, a step of walking behind: 0.1-0.15 m)."""
        if advance:
            return self._adopt_advanced(carry, ego_pose)
        s = self._require()
        kept, ego, ego_spec = carry["kept"], carry["ego"], carry["ego_spec"]
        ego_speed = carry["ego_speed"]
        mapping = self._adopt_insert(carry, kept, None)
        # Two steps settle the carried actors; the clock is shifted so that sim_time after them
        # equals the time before the swap. Step 1 inserts everything at the captured positions.
        # Step 2 holds vehicles there (their speed is then set explicitly) and lets persons walk
        # on by themselves (SUMO derives a moved person's speed from the distance it was moved,
        # which is meaningless for the insertion jump), so persons end up at most one step of
        # walking (~0.15 m) ahead.
        self._time_offset = carry["t_before"] - s.simulation.getTime() - 2 * self.step_length
        self.step()
        self._drop_stranded_persons(mapping)
        for k in kept:
            nid = mapping.get(k.old_id)
            if nid is None:
                continue
            try:
                if not k.person:
                    s.vehicle.moveToXY(nid, "", k.lane, k.x, k.y, k.angle, keepRoute=2,
                                       matchThreshold=EGO_MATCH_RADIUS_M)
            except self._exc as e:
                log.debug("swap: %s: %s", nid, e)
        if ego_spec is not None and ego is not None:
            self.set_ego_pose(ego["x"], ego["y"], ego["yaw"], ego_speed or ego["speed"])
        self.step()
        self.stats.steps -= 2
        self._set_carried_speeds(kept, mapping)
        self._clear_behind_carried(kept, mapping)
        self.stats.swap_lost += len(kept) - len(mapping)
        log.info("swap_network: %s, kept %d of %d actors within %.0f m", self.net_file.name,
                 len(mapping), len(kept), carry["keep_radius"])
        return mapping

    def _drop_stranded_persons(self, mapping: dict) -> None:
        """After the step that applied the carried persons' moveToXY: a person SUMO mapped onto
        a crossing or walking area off its route gets a walk that ends on a junction's edge
        (of internal edges only, or ending on a walking area: SUMO replaces the walk with the
        edges around the lane it matched), and SUMO 1.28 crashes (a segfault) when that walk ends, some steps later
        (Helsinki: 2.3 s after a swap, a person on a crossing with the walk ('30471533',
        ':cluster_409705483_409705484_w0')). Such a person is removed at once,
        dropped from ``mapping`` and counted in ``stats.swap_dropped``: one pedestrian gone beats
        the traffic gone."""
        if not mapping:
            return
        s = self._sim
        persons = set(s.person.getIDList())
        for old, nid in list(mapping.items()):
            if nid not in persons:
                continue
            try:
                edges = s.person.getStage(nid).edges
                if not edges or not edges[-1].startswith(":"):     # (ends on a junction's edge)
                    continue
                road = s.person.getRoadID(nid)
                s.person.remove(nid)
            except self._exc:
                continue
            del mapping[old]
            self.stats.swap_dropped += 1
            log.info("swap: %s dropped: SUMO matched it onto %s with a walk ending on a junction's edge: %s",
                     old, road, tuple(edges))

    def _set_carried_speeds(self, kept: list, mapping: dict) -> None:
        """After the swap's last step: the carried vehicles' speeds as captured (the step
        derived them from their insertion); the context subscription's results, older than
        that, are asked for again."""
        s = self._sim
        for k in kept:
            nid = mapping.get(k.old_id)
            if nid is None or k.person:
                continue
            try:
                s.vehicle.setPreviousSpeed(nid, k.speed)
            except self._exc:
                pass
        if self._ctx_anchor is not None:
            self._subscribe_context(self._ctx_anchor, self._ctx_radius)

    def _clear_behind_carried(self, kept: list, mapping: dict) -> int:
        """After the step that put the carried vehicles in: remove this SUMO's own vehicles
        coming up behind one of them in its lane too fast to stop before it at a normal
        deceleration (EGO_INSERT_DECEL, as for the ego: the carried vehicles appear at once,
        where SUMO inserts its own only where the follower can brake; on the Kouvola motorway
        one beyond the room made braked at 7 m/s² and still hit a carried car 0.8 s after the
        swap). Returns how many were removed."""
        s = self._sim
        carried = set(mapping.values())
        n = 0
        for k in kept:
            nid = mapping.get(k.old_id)
            if nid is None or k.person:
                continue
            try:
                fid, gap = s.vehicle.getFollower(nid, FOLLOWER_LOOK_M)
                if not fid or fid in carried or fid == EGO_ID:
                    continue
                v = s.vehicle.getSpeed(fid)
            except self._exc + (ValueError,):
                continue
            if _cannot_stop(gap, max(0.0, v - k.speed)):
                try:
                    s.vehicle.remove(fid)
                    n += 1
                    log.info("SUMO's %s came up behind the carried %s at %.1f m/s, %.1f m away, at the swap: "
                             "removed", fid, nid, v, gap)
                except self._exc:
                    pass
        return n

    def _adopt_insert(self, carry: dict, kept: list, pose) -> dict[str, str]:
        """What both kinds of ``swap_adopt`` do first: the new demand's vehicles around the
        ego make room (after SUMO's first second, which inserts the demand's trips in
        progress), the actors `kept` go in, and the ego at `pose` (x, y, yaw, speed; None:
        where it was captured). Returns old id -> new id."""
        self._generation = max(self._generation, int(carry["generation"]) + 1)
        self.warm_up()
        cx, cy = carry["center"]
        self._make_room(cx, cy, carry["keep_radius"] + SWAP_ROOM_MARGIN_M)
        self.stats = carry["stats"]
        mapping: dict[str, str] = {}
        for k in kept:
            new_id = f"{carried_id(k.old_id)}~{self._generation}"
            try:
                if self._insert_kept(k, new_id):
                    mapping[k.old_id] = new_id
            except self._exc as e:
                log.info("swap: could not carry %s over: %s", k.old_id, e)
        ego, ego_spec = carry["ego"], carry["ego_spec"]
        if ego_spec is not None:
            self._ego_spec = ego_spec
            if ego is not None:
                self._ego_spec["edges"] = [ego["edge"]] if ego["edge"] in self._edge_set() \
                    else [self._any_edge_for(ego_spec["vclass"])]
            self._readd_ego()
            if pose is None and ego is not None:
                pose = (ego["x"], ego["y"], ego["yaw"], carry["ego_speed"] or ego["speed"])
            if pose is not None:
                self.set_ego_pose(*pose)
        return mapping

    def _adopt_advanced(self, carry: dict, ego_pose) -> dict[str, str]:
        s = self._require()
        dt = self.step_length
        ahead = []          # each vehicle where its speed takes it in the step
        for k in carry["kept"]:
            if not k.person and k.speed > 0.0:
                a = math.radians(k.angle)
                k = dataclasses.replace(k, x=k.x + k.speed * dt * math.sin(a), y=k.y + k.speed * dt * math.cos(a),
                                        lane_pos=k.lane_pos + k.speed * dt)
                if k.lane_length >= 0 and k.lane_pos > k.lane_length:
                    k = dataclasses.replace(k, lane_id="", lane_length=-1.0)   # (past its lane's end)
            ahead.append(k)
        mapping = self._adopt_insert(carry, ahead, ego_pose)
        # one step: it inserts everything and is the loop's step; the clock reads one step
        # after the capture
        self._time_offset = carry["t_before"] - s.simulation.getTime()
        self.step()
        self._drop_stranded_persons(mapping)
        self._set_carried_speeds(ahead, mapping)
        self._clear_behind_carried(ahead, mapping)
        self.stats.swap_lost += len(ahead) - len(mapping)
        log.info("swap_network: %s, kept %d of %d actors within %.0f m (in the loop's step)", self.net_file.name,
                 len(mapping), len(ahead), carry["keep_radius"])
        return mapping

    def _make_room(self, cx: float, cy: float, radius: float) -> int:
        """Remove this SUMO's own vehicles within ``radius`` of (cx, cy), and those waiting to
        be inserted on a road that passes there: the vehicles carried over from the previous
        SUMO stand there. (Persons may overlap; and removing walking persons made libsumo
        crash in a later step.)"""
        s = self._sim
        n = 0
        try:
            snap = self.actors_near_getters(cx, cy, radius)
        except self._exc:
            return 0
        for aid, kind in zip(snap.ids, snap.kind):
            if kind == "person":
                continue
            try:
                s.vehicle.remove(aid)
                n += 1
            except self._exc:
                pass
        # and the vehicles waiting to be inserted there: the demand's trips in progress that
        # found no room during the warm-up go in during the next steps, where the carried
        # vehicles then stand (Kouvola motorway: 77-92 were waiting, and one inserted on a
        # carried car's lane ran into it; SUMO counted a collision at every such swap)
        try:
            pending = s.simulation.getPendingVehicles()
        except self._exc:
            pending = ()
        for vid in pending:
            try:
                first = s.vehicle.getRoute(vid)[0]
                if self._edge_near(first, cx, cy, radius):
                    s.vehicle.remove(vid)
                    n += 1
            except self._exc + (IndexError,):
                pass
        return n

    def _drop_inserted_ahead(self, departed) -> int:
        """Take out again, in the step that inserted them, the vehicles of SUMO's demand that
        went in on the ego's route ahead (its next INSERT_AHEAD_EDGES edges) too close for the
        ego to stop before them at a normal deceleration (:func:`_cannot_stop`). SUMO inserts
        a vehicle only where its own followers can brake for it, and the ego, moved by
        ``moveToXY``, is not one of them: in Helsinki a car that had waited 349 s to go in was
        put at a standstill on the ego's route two short edges on, 10 m ahead of the car at
        8.6 m/s, which ran into it. Vehicles carried across a swap (routes KEEP_ROUTE_PREFIX*)
        stay. Returns how many were taken out."""
        v_ego = self._ego_pending_speed or 0.0
        if v_ego < 1.0 or self._ego_pose is None:
            return 0
        s = self._sim
        i = self._ego_route_i
        ahead = set(self._ego_route[i:i + INSERT_AHEAD_EDGES])
        x, y, yaw = self._ego_pose
        c, sn = math.cos(yaw), math.sin(yaw)
        half = self._ego_spec["length"] / 2.0
        n = 0
        for vid in departed:
            if vid == EGO_ID:
                continue
            try:
                if s.vehicle.getRoadID(vid) not in ahead or s.vehicle.getRouteID(vid).startswith(KEEP_ROUTE_PREFIX):
                    continue
                fx, fy = s.vehicle.getPosition(vid)         # (its front)
                length, v = s.vehicle.getLength(vid), s.vehicle.getSpeed(vid)
            except self._exc:
                continue
            dx, dy = fx - x, fy - y
            if dx * c + dy * sn <= half:                    # (its front not ahead of the ego's)
                continue
            gap = max(0.0, math.hypot(dx, dy) - length - half)    # its rear to the ego's front
            if not _cannot_stop(gap, max(0.0, v_ego - v)):
                continue
            try:
                s.vehicle.remove(vid)
                n += 1
                log.info("SUMO's %s went in %.1f m ahead of the ego at %.1f m/s, on its route, at t=%.1f s: "
                         "taken out", vid, gap, v_ego, self.sim_time)
            except self._exc:
                pass
        return n

    def _clear_ego_footprint(self) -> int:
        """While the ego goes into SUMO (at the start, after a restart or a swap): remove the
        vehicles that stand where the ego's body is placed, before its insertion and those
        SUMO inserted in the same step (the demand's trips in progress go in at t = 0; in
        Helsinki one stood where the car starts, and SUMO counted a collision), and those
        coming up behind it in its lane too fast to stop before it at a normal deceleration
        (EGO_INSERT_DECEL; SUMO inserts its own vehicles only where the follower can brake,
        and the ego appears at once: in Lauf one ran into it 0.6 s after the start). Returns
        how many were removed."""
        if self._ego_pose is None:
            return 0
        s = self._sim
        x, y, yaw = self._ego_pose
        ego = (x, y, yaw, self._ego_spec["length"], self._ego_spec["width"])
        try:
            snap = self.actors_near_getters(x, y, ego[3] + 30.0)      # (no car is 30 m long)
        except self._exc:
            return 0
        n = 0
        c, sn = math.cos(yaw), math.sin(yaw)
        for k, (vid, kind) in enumerate(zip(snap.ids, snap.kind)):
            if kind == "person":
                continue
            why = None
            if _boxes_overlap(ego, (snap.x[k], snap.y[k], snap.yaw[k], snap.length[k], snap.width[k])):
                why = "stood where the ego went in"
            else:
                dx, dy = snap.x[k] - x, snap.y[k] - y
                lon, lat = dx * c + dy * sn, -dx * sn + dy * c
                gap = -lon - ego[3] / 2 - snap.length[k] / 2          # its front to the ego's rear
                v = float(snap.speed[k])
                closing = max(0.0, v - (self._ego_pending_speed or 0.0))    # (at a swap the ego moves)
                if (gap >= 0.0 and _cannot_stop(gap, closing)
                        and abs(lat) < (ego[4] + snap.width[k]) / 2 and math.cos(snap.yaw[k] - yaw) > 0.5):
                    why = f"came up behind the ego at {v:.1f} m/s, {gap:.1f} m away, as it went in"
            if why is None:
                continue
            try:
                s.vehicle.remove(vid)
                n += 1
                log.info("SUMO's %s %s at t=%.1f s: removed", vid, why, self.sim_time)
            except self._exc:
                pass
        return n

    def _edge_near(self, edge: str, x: float, y: float, radius: float) -> bool:
        """Whether some lane of ``edge`` passes within ``radius`` of (x, y)."""
        s = self._sim
        return any(_polyline_distance(np.asarray(s.lane.getShape(f"{edge}_{k}"), dtype=float), x, y) <= radius
                   for k in range(s.edge.getLaneNumber(edge)))      # (a lane's shape has 2 points or more)

    def _capture(self, cx: float, cy: float, radius: float) -> list[_Kept]:
        s = self._sim
        snap = self.actors_near_getters(cx, cy, radius)
        kept = []
        for aid, kind in zip(snap.ids, snap.kind):
            person = kind == "person"
            if person:
                p = s.person
                # (a person whose speed was set has a type of its own, "<type>@<person>",
                # which SUMO's vehicle-type lookup does not know: the kept person gets the
                # type it was made from)
                tid = p.getTypeID(aid).split("@")[0]
                edge = p.getRoadID(aid)
                edges = list(p.getEdges(aid))
                edges = edges[self._person_walk_index(aid, edge, edges):]
                try:
                    stage = p.getStage(aid)
                    arrival = float(stage.arrivalPos)
                except Exception:
                    arrival = None
                kept.append(_Kept(aid, True, tid, dict(
                    length=p.getLength(aid), width=p.getWidth(aid), height=p.getHeight(aid),
                    vclass="pedestrian", max_speed=s.vehicletype.getMaxSpeed(tid)),
                    *p.getPosition(aid), p.getAngle(aid), p.getSpeed(aid), edge, 0,
                    p.getLanePosition(aid), edges, arrival, *self._lane_and_length(p.getLaneID(aid))))
            else:
                v = s.vehicle
                tid = v.getTypeID(aid)
                route = list(v.getRoute(aid))
                idx = max(0, v.getRouteIndex(aid))
                kept.append(_Kept(aid, False, tid, dict(
                    length=v.getLength(aid), width=v.getWidth(aid), height=v.getHeight(aid),
                    vclass=v.getVehicleClass(aid), max_speed=s.vehicletype.getMaxSpeed(tid),
                    accel=v.getAccel(aid), decel=v.getDecel(aid), min_gap=v.getMinGap(aid)),
                    *v.getPosition(aid), v.getAngle(aid), v.getSpeed(aid), v.getRoadID(aid),
                    v.getLaneIndex(aid), v.getLanePosition(aid), route[idx:],
                    v.getArrivalPos(aid) if hasattr(v, "getArrivalPos") else None,
                    *self._lane_and_length(v.getLaneID(aid))))
        return kept

    def _lane_and_length(self, lane_id: str) -> tuple[str, float]:
        try:
            return lane_id, float(self._sim.lane.getLength(lane_id)) if lane_id else -1.0
        except self._exc:
            return "", -1.0

    def _same_lane(self, k: _Kept) -> bool:
        """The actor's lane exists in this network with the same length (so the same geometry:
        windows are cut from one OSM source), and the lane position carries over as it is."""
        if not k.lane_id or k.lane_id.startswith(":") or k.edge not in self._edge_set():
            return False
        try:
            return abs(self._sim.lane.getLength(k.lane_id) - k.lane_length) < 0.05
        except self._exc:
            return False

    def _person_walk_index(self, pid: str, road: str, edges: list) -> int:
        """Index in the walk's edges of the edge the person is on or walks onto next."""
        if road in edges:
            return edges.index(road)
        s = self._sim
        nxt = s.person.getNextEdge(pid) if road.startswith(":") else ""
        if nxt in edges:
            return edges.index(nxt)
        # on a walking area / crossing of junction J: the next edge is the first one that
        # starts at J after one that ends there
        junction = (nxt or road)[1:].rsplit("_", 1)[0] if (nxt or road).startswith(":") else ""
        if junction:
            ends = {e: (s.edge.getFromJunction(e), s.edge.getToJunction(e)) for e in edges}
            for j in range(1, len(edges)):
                if junction in ends[edges[j - 1]] and junction in ends[edges[j]]:
                    return j
        return 0

    def _insert_kept(self, k: _Kept, new_id: str) -> bool:
        s = self._sim
        edges_known = self._edge_set()
        self._ensure_type(k.type_id, k.type_params, person=k.person)
        vclass = "pedestrian" if k.person else k.type_params.get("vclass", "passenger")
        edges = [e for e in k.edges if e in edges_known]
        # where to insert it (moveToXY then puts it exactly where it was): on its lane, if the
        # new network has that lane unchanged; inside a junction or on an edge that changed,
        # on the first edge of the rest of its route; else where SUMO's map matching puts it
        # (convertRoad: 10-50 ms a call on a city network)
        same = self._same_lane(k)
        if same:
            road, pos, lane = k.edge, k.lane_pos, k.lane
        elif edges and (k.edge.startswith(":") or k.edge == edges[0]):
            road, pos, lane = edges[0], 0.0, -1
        else:
            try:
                road, pos, lane = s.simulation.convertRoad(k.x, k.y, False, vclass)
            except self._exc:
                road, pos, lane = "", 0.0, -1
            if road.startswith(":"):
                road, pos, lane = (edges[0] if edges else ""), 0.0, -1
        if not road:
            return False
        if not edges or edges[0] != road:
            if edges and road in edges:
                edges = edges[edges.index(road):]
            elif edges:
                try:
                    r = (s.simulation.findIntermodalRoute(road, edges[-1], modes="")
                         if k.person else s.simulation.findRoute(road, edges[-1], vType=k.type_id))
                    found = [e for st in r for e in st.edges] if k.person else list(r.edges)
                except self._exc:
                    found = []
                edges = found or [road]
            else:
                edges = [road]
        if k.person:
            s.person.add(new_id, edges[0], max(0.0, float(pos)), depart=-3, typeID=k.type_id)
            if k.speed > 0.5:   # walking: keep the pace (a new person draws a new speed factor)
                s.person.setSpeed(new_id, k.speed)
            arr = k.arrival_pos if (k.arrival_pos is not None and edges[-1] == (k.edges or [None])[-1]) else -1
            s.person.appendWalkingStage(new_id, edges, arr if arr is not None else -1)
            if not same:
                s.person.moveToXY(new_id, edges[0], k.x, k.y, k.angle, keepRoute=2,
                                  matchThreshold=EGO_MATCH_RADIUS_M)
                # SUMO derives the person's speed from that jump (metres in one step: 28.8 m/s
                # for one moved onto a walking area) and reports it for as long as the person
                # stands there: until it moves, actors_near reports the speed it had
                self._moved_persons[new_id] = (k.x, k.y, k.speed)
        else:
            rid = f"{KEEP_ROUTE_PREFIX}{new_id}"
            s.route.add(rid, edges)
            s.vehicle.add(new_id, rid, typeID=k.type_id, depart="now",
                          departLane=str(lane) if lane >= 0 else "best",
                          departPos=f"{max(0.0, pos):.2f}", departSpeed=f"{max(0.0, k.speed):.2f}")
            s.vehicle.moveToXY(new_id, edges[0], lane, k.x, k.y, k.angle, keepRoute=2,
                               matchThreshold=EGO_MATCH_RADIUS_M)
        return True

    def _id_set(self, domain: str) -> set:
        """The ids of this network's edges or lanes (``domain``), read once per network."""
        cache = self.__dict__.get("_id_sets")
        if cache is None or cache["net"] != str(self.net_file):     # (only this network's)
            cache = self._id_sets = {"net": str(self.net_file)}
        if domain not in cache:
            cache[domain] = set(getattr(self._sim, domain).getIDList())
        return cache[domain]

    def _edge_set(self) -> set:
        return self._id_set("edge")
