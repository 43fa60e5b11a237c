"""The autopilot, and the controller interface a user's own driver plugs into.

The controller interface
------------------------
:class:`cosim.sim.Simulation` calls ``driver.control(state, s_here, actors, dt)`` once per
SUMO step and applies the returned ``(throttle, brake, steer)`` (pedals 0..1, steering -1..1,
+ = left, as a fraction of full lock) to the physics car's wheels. ``state`` is the car's
``cosim.vehicle.VehicleState``, ``s_here`` its arc length on the route's lane path
(``sim.path``), ``actors`` the SUMO actors near it (``cosim.traffic.ActorsSnapshot``).

* :class:`Autopilot` is the default driver (below).
* :class:`CallbackDriver` wraps a plain function ``fn(obs) -> (throttle, brake, steer)``;
  ``obs`` is :meth:`Autopilot.observation` (speed, lateral offset, heading error, lidar, next
  light, lead vehicle, the autopilot's own suggestion, ...).
* ``cosim.env.DrivingEnv`` is the same thing as a Gymnasium-style ``step(action)``.

The autopilot
-------------
Lateral: pure pursuit from the rear axle on the SUMO lane path (``cosim.driving``), aimed
along the rear axle's direction of travel (the tyres' slip angle included).

Longitudinal: a target speed, the minimum of

* the set speed (``cfg.speed_mps``) and, when ``cfg.respect_speed_limit``, SUMO's lane
  speed limit (``lane.getMaxSpeed``), braked for ahead of time;
* the curve speed (2.5 m/s² lateral) of the path ahead, braked for ahead of time;
* adaptive cruise behind the nearest obstacle on the path, fused from three sensors: the
  lidar (``cosim.sensors``: the nearest hit in the path corridor), the mirrored SUMO actors
  projected onto the path (vehicles and pedestrians, with a short prediction of crossing
  ones), and SUMO's leader (``vehicle.getLeader("ego")``, accepted when it is on a lane of the
  path ahead). It keeps ``TIME_GAP_S`` (1.8 s, at least 1.5 s) plus a standstill gap;
* traffic control at each junction the path enters (``LanePath.stops``, state read live
  from ``lane.getLinks``): stop at red and at yellow when it can stop in time; at a stop sign
  (SUMO link state ``s`` or ``w``, or an OpenStreetMap ``highway=stop`` sign from the world's
  scenery next to a minor approach, since netconvert does not import them) stop at the line
  for at least ``STOP_SIGN_HOLD_S`` and go when the junction is clear; at minor links (``m``,
  ``=``, ``g``, blinking ``o``) go only when no vehicle with right of way
  (``lane.getFoes``) would arrive before the ego has crossed, and nothing is on a conflicting
  junction lane (``lane.getInternalFoes``);
* pedestrians: stop before a crossing the path goes over (``LanePath.crossings``) while a
  person on it is near the path, and for a person in the path corridor;
* the car's own sweep: its footprint (grown by ``SWEEP_MARGIN_M``) rolled forward along where
  its steering takes it, which in a turn tighter than the car can follow is not the lane path
  (it cuts the corner). Where the sweep would touch a mirrored actor beside the corridor, the
  car follows the path closely (a short look-ahead, at most ``CLOSE_TRACK_MPS``) if that
  passes it, else stops ``SWEEP_STOP_M`` before the touch and waits (``clearance ...``),
  steering closely while it stops where that comes no nearer (``_sweep_steering``);
* lane changes (gap acceptance): where the path moves over to the next lane along an edge
  (``LanePath.changes``), a vehicle in that lane (or coming into it: a junction lane beside
  the car's, the road before) without room for the car, behind it its safe gap
  (``LC_REACT_S`` at its speed plus braking at ``LC_DECEL`` down to the car's speed), ahead the
  car's own, holds the car in its own lane (``LanePath.set_hold``) until it passes: the car
  drops back behind a vehicle beside or ahead, and stops ``LC_ROOM_M`` before the edge's end
  if no room comes (reason ``lane change``). Once ``LC_COMMIT`` of the way over it goes on. A
  queue (slower than ``LC_SLOW_MPS``) holds it back only with its follower within
  ``LC_SLOW_GAP_M`` of the car: the car merges behind the vehicle beside it;
* the goal: stop at the snapped goal;
* a turn back onto the road's other direction tighter than the car can make (a dead end's
  U-turn, which a route takes where it has no other way on): stop ``ROOM_AHEAD_M`` short of
  it and turn round in moves forward and back inside the carriageway
  (``cosim.turnround.TurnRound``; reason ``turning round``); where the carriageway has no room
  for them, or a step across it, the car stays stopped there (``no room to turn round``). The
  controls then carry the gear: ``Autopilot.reverse`` is True for a move back (the
  simulation reads a driver's ``reverse``; :class:`CallbackDriver`'s function may return it
  as a fourth value, and the observation's ``autopilot_reverse`` suggests it).

A PI speed controller with a force model (``cosim.driving.SpeedController``) turns the target
into throttle and brake. It counts, for benchmarks, stops and near misses
(:class:`DrivingStats`: time-to-collision below ``NEAR_MISS_TTC_S`` or a gap below
``NEAR_MISS_GAP_M`` while moving).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field

import numpy as np

from .driving import (PurePursuit, SpeedController, _drivable_lanes, _resample, curve_speed, junction_of,
                      plan_speed, stop_speed)
from .mirror import LEVEL_M      # (levels more than this apart: a deck and the road under it)
from .sumo_process import NOT_YET
from .traffic import NETWORK_READS, STANDOFF_CREEP_MPS, _boxes_overlap, carried_id
from .turnround import MOVE_SPEED as MOVE_SPEED_TURN
from .vehicle import STEER_RATE, WHEELBASE

log = logging.getLogger("cosim.autopilot")

TIME_GAP_S = 1.8           # kept behind a vehicle ahead (>= 1.5 s)
STANDSTILL_GAP_M = 4.0     # bumper to bumper when stopped behind a vehicle
PERSON_GAP_M = 4.0         # stop this far before a pedestrian in the path
COMFORT_DECEL = 2.0        # m/s2 used to plan stops and slow-downs
YELLOW_DECEL = 3.5         # m/s2: at yellow, stop only if this deceleration suffices
STOP_LINE_MARGIN_M = 2.0   # front bumper this far before the stop line
CROSSING_MARGIN_M = 1.5    # front bumper this far before a crossing's edge
CROSSING_APPROACH_MPS = 2.0  # speed over a crossing where people wait at its ends (from 3 m/s the car,
#   braking once they stepped on 1.5 m before the crossing, reached them: Lauf, dense seed 20)
STOP_SIGN_HOLD_S = 1.2     # full stop at a stop sign at least this long (>= 1 s)
YIELD_GIVE_UP_S = 40.0     # after waiting this long at a yield, go when nothing is < 2 s away
NEAR_MISS_TTC_S = 1.5
NEAR_MISS_GAP_M = 2.0
SENSE_RANGE_M = 80.0       # obstacles on the path are considered up to here
STANDOFF_S = 20.0          # the car and a vehicle in its sweep both standing this long: a standoff
STANDOFF_GAP_M = 5.0       # _standoff: a vehicle on a lane over the path this near is waited for, whatever binds
LEVEL_REACH_M = 40.0       # ... looked at for actors this near (in x and y) where the path is up there
CROSS_LANE_MARGIN_M = 3.5  # a crossing vehicle's road may have a lane nearer than its own
LANE_CONFLICT_MARGIN_M = 0.5  # a junction lane over the path: clear of the two bodies by this
MERGE_BEHIND_M = 1.0       # _lane_conflict: a lane merging in beside the car is left to its vehicle if the car's rear is this far past the join when it gets there
ROLLBACK_MPS = 0.3           # moving backwards this fast while driving forward: brakes (control)
OVER_PATH_M = 3.0            # a junction lane this near the path is looked at closer (_over)
MERGE_WATCH_M = 2.5        # a vehicle in a lane the path changes into is followed from this far beside
HARD_DECEL = 6.0           # m/s2: the car's firm braking (what "can still stop before it" means)
# the car's own sweep (_sweep): its footprint, grown by SWEEP_MARGIN_M on every side, rolled
# forward along where its steering takes it (not the lane path: in a turn tighter than the car
# can follow it cuts the corner) for SWEEP_MIN_M plus what stops it at SWEEP_DECEL, at most
# SWEEP_MAX_M, in steps of SWEEP_STEP_M
SWEEP_MARGIN_M = 0.15
SWEEP_MIN_M = 3.0
SWEEP_MAX_M = 10.0
SWEEP_DECEL = 3.0
SWEEP_STEP_M = 1.0
SWEEP_PREDICT_S = 1.0      # a crossing or oncoming actor moves on along its heading for this long in the roll
SWEEP_PERSON_M = 0.35      # a walking person's box grows by this much more each side in the roll (_sweep)
SWEEP_WALL_M = 0.1         # the car's footprint grows by this much each side against walls in the roll
SWEEP_STILL_MPS = 0.2      # ... one slower than this (standing) does not
SWEEP_STOP_M = 0.5         # stop this far (along the sweep) before the first touch
SWEEP_GATE_M = 0.15        # no roll while the car is this near the lane path ...
SWEEP_GATE_RADIUS_M = 15.0  # ... and the path ahead turns no tighter than this (_sweep)
# where the sweep touches something, the car may still pass by following the lane path more
# closely: pure pursuit with this look-ahead (m), at most CLOSE_TRACK_MPS
CLOSE_TRACK = {"k_ld": 0.3, "k_ld2": 0.0, "ld_min": 2.0}
CLOSE_TRACK_MPS = 2.0
# lane changes (_lane_change): the path moves over to the next lane along an edge; the car
# holds back in its own lane while a vehicle in (or coming into) that lane would not have room
LC_LOOK_S = 1.5            # looked at from this long before the steering's look-ahead meets the blend
LC_ROOM_M = 12.0           # the change is made at the latest this far before the edge's end
LC_REACT_S = 0.8           # a follower in the lane changed into: reaction time in its safe gap ...
LC_DECEL = 4.0             # ... and the deceleration it is asked for at most
LC_MIN_GAP_M = 2.0         # bumper to bumper, at least, before and behind in that lane
LC_BAND_M = 1.8            # a vehicle's centre this near the lane changed into's centreline is in it
LC_BEHIND_M = 100.0        # vehicles looked at this far behind ...
LC_AHEAD_M = 30.0          # ... and this far ahead
LC_COMMIT = 0.35           # this part of the way over (0..1), the car goes on with the change
LC_HOLD_IN_S = 0.6         # the hold comes on over this long ...
LC_HOLD_OUT_S = 2.5        # ... and goes off over this long, or LC_HOLD_OUT_M of the way
LC_HOLD_OUT_M = 12.0       # (the longer: from a standstill the car moves over within 12 m)
LC_SLOW_MPS = 3.0          # a vehicle slower than this (a queue) does not hold the car back
# beside or ahead (the car merges behind it, following it as a leader, and SUMO holds the
# follower it reaches in front of: _straddle_yield); behind, it needs LC_SLOW_GAP_M only
LC_SLOW_GAP_M = 1.0
EXPECT_AHEAD_M = 40.0      # reads are asked ahead (_expect) this far beyond where they are needed
OSM_SIGN_RADIUS_M = 20.0   # an OSM stop sign belongs to an approach whose stop line is this close
YIELD_STATES = set("m=goO")
RED_STATES = set("rRu")
YELLOW_STATES = set("yY")
STOP_STATES = set("sw")
STUCK_S = 4.0              # held still this long against the throttle, nothing to stop for: a move back
STUCK_MPS = 0.05           # ... slower than this
STUCK_THROTTLE = 0.15      # ... with at least this much throttle
STUCK_LOOK_M = 6.0         # the way the path turns: its heading this far ahead against the car's
BACKOFF_MAX = 3            # moves back at most within ...
BACKOFF_SPOT_M = 6.0       # ... this far along the path of one another
STATIC_TOUCH_M = 0.05      # a wall this near a point of the car's outline is one it touches (_static_along)
STATIC_RAY_DZ = (-0.15, 0.35)   # m over the car's centre of the rays along its outline's way (_static_along)


def _normal_lanes(lanes) -> list:
    """``lanes`` (a link's foes) but the junction lanes."""
    return [f for f in lanes if not f.startswith(":")]


@dataclass
class Lead:
    gap: float                 # m, bumper to bumper along the path
    speed: float               # m/s along the path (0 for static obstacles and pedestrians)
    kind: str                  # "vehicle", "person", "static"
    source: str                # "lidar", "actors", "sumo"; "conflict": on a lane over the path (_lane_conflict)
    actor: str = ""
    track_gap: float | None = None     # a vehicle crossing the path: the gap to its track (the
    # gap above is to where the car stops, CROSS_LANE_MARGIN_M before it); a person walking into
    # the corridor from the side: the gap to it; None for others (near misses: _update_stats)


@dataclass
class DrivingStats:
    """What the autopilot saw, for benchmarks (counts are events, not steps)."""
    steps: int = 0
    near_misses: int = 0
    stops: int = 0
    min_ttc_s: float = float("inf")
    min_gap_moving_m: float = float("inf")
    red_light_stops: int = 0
    stop_sign_stops: int = 0
    pedestrian_yields: int = 0
    sweeps: int = 0          # times the car's sweep found something beside the path corridor (_sweep)
    rollbacks: int = 0       # times the car rolled back (ROLLBACK_MPS) against the throttle
    standoffs: int = 0       # vehicles taken out of SUMO after a standoff with the car (_standoff)
    lane_change_waits: int = 0   # lane changes held back for a vehicle in the lane changed into
    turnarounds: int = 0     # turns made in moves forward and back where the route turns back (cosim.turnround)
    no_room_to_turn: int = 0     # ... where the carriageway has no room for them: the car stops there
    backoffs: int = 0        # moves back where the car was held still against the throttle (cosim.turnround.BackOff)
    time_gaps: list = field(default_factory=list, repr=False)   # steady following samples, s
    events: list = field(default_factory=list, repr=False)      # (t, kind, detail)

    def as_dict(self) -> dict:
        tg = np.array(self.time_gaps) if self.time_gaps else np.zeros(0)
        return {"near_misses": self.near_misses, "stops": self.stops, "min_ttc_s": round(self.min_ttc_s, 2),
                "min_gap_moving_m": round(self.min_gap_moving_m, 2), "red_light_stops": self.red_light_stops,
                "stop_sign_stops": self.stop_sign_stops, "pedestrian_yields": self.pedestrian_yields,
                "sweeps": self.sweeps, "rollbacks": self.rollbacks, "standoffs": self.standoffs,
                "lane_change_waits": self.lane_change_waits, "turnarounds": self.turnarounds,
                "no_room_to_turn": self.no_room_to_turn, "backoffs": self.backoffs,
                "time_gap_p5_s": round(float(np.percentile(tg, 5)), 2) if len(tg) else None}


class Autopilot:
    """The default driver (module doc). ``lidar``: use the ray sensor (needs the PyBullet
    world); ``time_gap``: the ACC's time gap (s, at least 1.5)."""

    # pure pursuit's look-ahead: 0.7 s + 0.008 s per m/s of speed, at least 5 m (shorter at
    # urban speeds than the former 0.9 s, which cut curves; as long at motorway speed, where
    # a shorter one oscillates after a sideways jump of the path)
    STEERING = {"k_ld": 0.7, "k_ld2": 0.008, "ld_min": 5.0}

    def __init__(self, sim, lidar: bool = True, time_gap: float = TIME_GAP_S, n_rays: int = 41,
                 lidar_range: float = 70.0):
        from .vehicle import LENGTH, WHEELBASE, WIDTH, min_turn_radius

        if time_gap < 1.5:
            raise ValueError("the time gap must be at least 1.5 s")
        self.sim = sim
        self.length, self.width = LENGTH, WIDTH
        self.front = LENGTH / 2.0
        self.pp = PurePursuit(WHEELBASE, 1.0 / min_turn_radius(), **self.STEERING)
        self.pp_close = PurePursuit(WHEELBASE, 1.0 / min_turn_radius(), **CLOSE_TRACK)
        self.speed = SpeedController()
        self.time_gap = float(time_gap)
        self.lidar = None
        if lidar and getattr(sim, "physics", None) is not None and sim.physics.client is not None:
            from .sensors import Lidar

            self.lidar = Lidar(sim.physics.client, n_rays=n_rays, range_m=lidar_range)
        self.target_speed = 0.0
        self.reason = ""
        self.lead: Lead | None = None
        self.lead_gap = None
        self.sweep: tuple | None = None          # (distance m, actor id, kind) of _sweep's first touch
        self.next_control: dict | None = None    # {"kind", "state", "distance_m"} of the next stop line
        self.scan = None
        self.stats = DrivingStats()
        self.last = (0.0, 0.0, 0.0)
        self._too_steep = False           # rolled back at full throttle on this path: hold (control)
        self._rolling_back = False
        self._path = None
        self._s_goal = None
        self._stop_state: dict = {}
        self._yellow: dict = {}
        self._osm_stops: dict = {}
        self._incoming: dict | None = None
        self._edge_ends: dict | None = None    # edge -> (from, to junction): SumoTraffic.edge_ends
        self._foes: dict = {}
        self._internal_foes: dict = {}
        self._internal_foes_all: dict = {}
        self._ego_min_gap: float | None = None
        self._lane_shapes: dict = {}      # junction lane -> (centreline points, arc lengths)
        self._lane_vias: dict | None = None   # lane -> the junction lanes its links go through
        self._vias_asked: set = set()     # lanes whose junction lanes' shapes were asked ahead
        self._conflict_lanes: dict = {}   # lane -> _conflict_vias (per path)
        self._over_path: dict = {}        # junction lane -> the path's stretch near it, or () (per path)
        self._path_lanes: set = set()     # the lanes of the path
        self._path_bridge = None          # per path point: on a bridge's lane (None: no bridge)
        self._standoff_with = None        # (vehicle, since): the car stands before it for its sweep
        self._standoff_next = 0.0         # a circle not yet closed (_standoff): tried again from then
        self._released: set = set()       # vehicles taken out after a standoff (_standoff)
        self._path_rises = None           # per path point: how high it stands over the terrain (_path_rises_at)
        self._path_edges: set = set()     # the edges of the path
        self._net_generation = getattr(getattr(sim, "traffic", None), "_generation", 0)
        self._hold = 0.0                  # how far the car holds back from a lane change (0..1)
        self._hold_key = None             # ... which one (LaneChange.key: it outlives the path)
        self._hold_blocker = None         # (vehicle, its speed, "behind" / "beside" / "ahead")
        self._near_miss_until = -1.0
        self._sweeping = False
        self._moving = False
        self._prev_target = None
        self._st = None
        self._s_here = 0.0
        self._k = 0
        self._lat = 0.0
        self.reverse = False              # the gear the car's controls are for (a turn's moves back)
        self._turn = None                 # the turn round under way (cosim.turnround.TurnRound)
        self._backoff = None              # the move back under way (cosim.turnround.BackOff)
        self._stuck_s = 0.0               # s the car has been held still against the throttle (_stuck)
        self._backoffs: list = []         # (path, arc length) of each move back: BACKOFF_MAX per spot
        self._uturns: list = []           # the path's stop lines where it turns back tighter than the car can
        self._no_room: set = set()        # (lane, to_lane) where the carriageway has no room to turn round
        self._lane_widths: dict = {}

    # --- the controller interface ------------------------------------------------------
    def control(self, st, s_here: float, actors, dt: float):
        sim = self.sim
        path = sim.path
        gen = getattr(getattr(sim, "traffic", None), "_generation", 0)
        if gen != self._net_generation:         # SUMO moved to another network (world streaming)
            self._net_generation = gen
            self._incoming = self._edge_ends = None
            self._foes, self._internal_foes, self._internal_foes_all = {}, {}, {}
            self._lane_shapes, self._lane_vias, self._vias_asked = {}, None, set()
            self._stop_state.clear()
            self._yellow.clear()
            self._path = None
        if path is not self._path:
            self._new_path(path)
        self._st, self._s_here = st, s_here
        if self._turn is not None:
            return self._turning(st, actors, dt, getattr(sim, "t", 0.0))
        if self._backoff is not None:
            return self._backing_off(st, actors, dt, getattr(sim, "t", 0.0))
        self.reverse = False
        pr = getattr(sim, "ego_projection", None)
        if pr is not None and pr[0] is path and pr[1] == st.x and pr[2] == st.y and pr[3] == s_here:
            self._k, self._lat = pr[4], pr[5]       # the loop's own projection of this state
        else:
            self._k, _, self._lat = path.project(st.x, st.y, path.index_at(s_here))
        actors = self._same_level(actors, path, s_here)
        v = st.speed
        t = getattr(sim, "t", 0.0)
        lane_change = self._lane_change(st, path, s_here, v, actors, dt, t)
        # the car's own sweep: anything it would touch beside the lane path's corridor; where
        # it would, follow the path closely and slowly if that passes, else stop before it
        touch, self.sweep, pp, v_sweep = self._sweep_steering(st, path, s_here, actors)
        if touch is not None and not self._sweeping:
            self.stats.sweeps += 1
            self.stats.events.append((round(getattr(sim, "t", 0.0), 2), "sweep", touch[1] + (
                " (close tracking)" if v_sweep is not None else "")))
        self._sweeping = touch is not None
        steer, _ = pp.steer(path, st.x, st.y, st.yaw, v, s_here, velocity=getattr(st, "velocity", None),
                            yaw_rate=float(getattr(st, "yaw_rate", 0.0)))
        cfg = sim.cfg
        v_set = float(cfg.speed_mps)
        targets = [(v_set, "cruise")]
        # the path ahead: curves and (if asked) the lanes' speed limits
        horizon = max(40.0, v * v / (2 * COMFORT_DECEL) + 30.0)
        v_path, s_bind = plan_speed(path, s_here, v_set, horizon, decel=COMFORT_DECEL,
                                    speed_limit=bool(getattr(cfg, "respect_speed_limit", False)))
        if v_path < v_set - 1e-6:
            i = path.index_at(s_bind)
            limited = getattr(cfg, "respect_speed_limit", False) and path.max_speed[i] < v_set and \
                abs(path.curvature_smooth[i]) < 2.5 / max(path.max_speed[i], 0.1) ** 2
            targets.append((v_path, "speed limit" if limited else "curve"))
        # the goal, or the end of the path
        if sim.goal_xy is not None:
            targets.append((stop_speed(self._s_goal - s_here, COMFORT_DECEL), "goal"))
        else:
            targets.append((stop_speed(path.length - s_here - 3.0, COMFORT_DECEL), "end of path"))
        targets.extend(lane_change)
        # the edge of the built world (the road goes on, the ground does not)
        s_edge = self._world_edge(path, s_here, horizon)
        if s_edge is not None:
            targets.append((stop_speed(s_edge - s_here - self.front - 5.0, COMFORT_DECEL), "edge of the world"))
        self._expect(path, s_here, v, actors)
        # obstacles ahead: adaptive cruise
        self.lead = self._sense(st, s_here, actors, path)
        self.lead_gap = self.lead.gap if self.lead else None
        if self.lead is not None:
            targets.append((self._follow_speed(self.lead, v), "lead " + self.lead.kind))
        # junctions: lights, stop signs, yielding
        targets.extend(self._junctions(path, s_here, v, t))
        # pedestrians on crossings
        targets.extend(self._crossings(path, s_here, v, actors))
        # anything the car's own sweep would touch (above)
        if v_sweep is not None:
            targets.append((v_sweep, "close tracking"))
        if self.sweep is not None:
            targets.append((stop_speed(self.sweep[0] - SWEEP_STOP_M, SWEEP_DECEL), "clearance " + self.sweep[2]))
        # rolling back against the throttle: the road is steeper than the car climbs (a DEM's
        # cliff under a 14 m Monaco street left it at 50 %: the car rolled back at full throttle
        # to 4.2 m/s into the car behind it). On the brakes instead: at full throttle for good
        # on this path (a re-plan tries again), else for the moment (a hill start's sag)
        rolling_back = v < -ROLLBACK_MPS
        if rolling_back and not self._too_steep:
            if not self._rolling_back:
                self.stats.rollbacks += 1
                self.stats.events.append((round(t, 2), "rollback", f"{v:.2f} m/s, pitch {math.degrees(st.pitch):.1f} deg"))
            if self.last[0] >= 0.99:
                self._too_steep = True
                log.warning("the car rolls back at full throttle at t=%.1f s (pitch %.1f deg): too steep "
                            "for it, held on the brakes", t, math.degrees(st.pitch))
        self._rolling_back = rolling_back
        if rolling_back or self._too_steep:
            targets.append((0.0, "too steep" if self._too_steep else "rolling back"))
        # where the path turns back tighter than the car can: stopped short of it, to turn round
        # in moves forward and back (cosim.turnround)
        turn = self._turn_ahead(path, st, s_here, v, targets, t)
        if turn is not None:
            return turn
        v_target, reason = min(targets, key=lambda x: x[0])
        v_target = max(0.0, v_target)
        a_ff = 0.0
        if self._prev_target is not None and reason != "cruise":
            a_ff = max(-3.0, min(0.0, (v_target - self._prev_target) / max(dt, 1e-3)))
        self._prev_target = v_target
        self.target_speed, self.reason = v_target, reason
        throttle, brake = self.speed.control(v_target, v, dt, pitch=self._road_pitch(st), a_ff=a_ff)
        if v_target < 0.05 and v < 0.3:
            throttle, brake = 0.0, 1.0
        self._update_stats(v, t)
        self._standoff(v, t, actors)
        self.last = (throttle, brake, steer)
        if self._stuck(st, path, s_here, v_target, reason, throttle, dt, t):
            return self._backing_off(st, actors, dt, t)
        return throttle, brake, steer

    def _lane_change(self, st, path, s_here: float, v: float, actors, dt: float, t: float) -> list:
        """Gap acceptance. The path moves over to the next lane along an edge (``LaneChange``);
        before the car starts to, and until it is LC_COMMIT of the way over, a vehicle in (or
        coming into) that lane without room for the car (``_lc_blocker``) holds it back in its
        own lane (``LanePath.set_hold``), slowing to drop behind a vehicle beside or ahead, and
        stopping LC_ROOM_M before the edge's end if the room does not come. (Blending over
        regardless, the car moved in beside a faster car: Portland, seed 12, which SUMO counted
        as a collision.) Returns the speed targets it sets."""
        c = None
        if path.changes:
            reach = s_here + self.pp.lookahead(v) + max(v, 2.0) * LC_LOOK_S
            for ch in path.changes:
                if ch.s_end > s_here:
                    c = ch if ch.s0 <= reach else None
                    break
        if c is None or (self._hold_key is not None and self._hold_key != c.key):
            self._hold, self._hold_key, self._hold_blocker = 0.0, None, None
        if c is None:
            path.set_hold(None, 0.0)
            return []
        k = self._k
        raw = self._lat + path.held_lat(k)              # the car's offset from the path itself
        if k >= c.i1:
            progress = 1.0
        elif k < c.i0:
            progress = 0.0
        else:
            j = k - c.i0
            sep = float(c.src_lat[j] - c.tgt_lat[j])
            progress = 1.0 - (raw - float(c.tgt_lat[j])) / sep if abs(sep) > 0.5 else \
                (1.0 if s_here >= c.s1 else 0.0)
        s_dead = c.s_end - LC_ROOM_M
        hold = self._hold
        blocker = None
        if hold > 0.0 or progress < LC_COMMIT:
            if hold > 0.0 and s_here > s_dead + 3.0 and v > 1.0:
                blocker = None        # run past where it had to be made (no stop in time): go
            elif hold > 0.0 or v < LC_SLOW_MPS or \
                    s_here + self.front + v * v / (2.0 * 1.5 * COMFORT_DECEL) < s_dead:
                blocker = self._lc_blocker(c, st, path, s_here, v, actors)
        if blocker is not None:
            if hold == 0.0:
                self.stats.lane_change_waits += 1
                self.stats.events.append((round(t, 2), "lane change wait",
                                          f"{c.from_lane} -> {c.to_lane}: {blocker[2]} {blocker[0]}"))
            hold = min(1.0, hold + dt / LC_HOLD_IN_S)
        else:
            hold = max(0.0, hold - max(v, 1.0) * dt / max(LC_HOLD_OUT_M, max(v, 1.0) * LC_HOLD_OUT_S))
        self._hold, self._hold_key, self._hold_blocker = hold, (c.key if hold > 0.0 else None), blocker
        path.set_hold(c if hold > 0.0 else None, hold)
        self._lat = raw - path.held_lat(k)
        if blocker is None:
            return []
        targets = [(stop_speed(s_dead - s_here - self.front, COMFORT_DECEL), "lane change")]
        if blocker[2] != "behind":          # beside or ahead: drop back behind it
            targets.append((max(0.0, blocker[1] - 2.0), "lane change"))
        return targets

    def _lc_blocker(self, c, st, path, s_here: float, v: float, actors):
        """The vehicle in lane change `c`'s target lane (or coming into it: a junction lane
        beside the car's, the road before) without the room the change needs, as (id, speed,
        "behind" / "beside" / "ahead"), or None. Room: behind the car a follower's safe gap
        (LC_REACT_S at its speed, plus what it must brake at LC_DECEL to come down to the car's
        speed), ahead the car's own, at least LC_MIN_GAP_M. A vehicle slower than LC_SLOW_MPS
        (a queue) needs LC_SLOW_GAP_M behind the car and none ahead, nor beside unless the car
        is as slow: the car merges behind it as before (Lauf, seed 18: held back beside a queue, the car stood inside a
        junction and then for good before the edge's end; SUMO's queues leave no car-sized gap)."""
        if actors is None or not len(actors):
            return None
        dx, dy = actors.x - st.x, actors.y - st.y
        r = LC_BEHIND_M + 10.0
        near = np.flatnonzero((dx * dx + dy * dy < r * r) & (actors.kind != "person"))
        if len(near) == 0:
            return None
        s, off = path.project_many(actors.x[near], actors.y[near], s_here - LC_BEHIND_M, s_here + LC_AHEAD_M)
        ok = np.isfinite(s)
        if not ok.any():
            return None
        near, s, off = near[ok], s[ok], off[ok]
        idx = np.clip(np.searchsorted(path.s, s, side="right") - 1, 0, len(path.s) - 1)
        raw = off + path.held_lat(idx)
        # behind where the path begins (it begins at the car after a start or a re-plan): along
        # the line of its first heading
        before = s <= 1e-6
        if before.any():
            h0 = float(path.heading[0])
            ex = actors.x[near[before]] - path.xy[0, 0]
            ey = actors.y[near[before]] - path.xy[0, 1]
            s[before] = ex * math.cos(h0) + ey * math.sin(h0)
            raw[before] = -ex * math.sin(h0) + ey * math.cos(h0) + path.held_lat(0)
        band = c.tgt_lat[np.clip(idx - c.i0, 0, len(c.tgt_lat) - 1)]
        dyaw = np.angle(np.exp(1j * (actors.yaw[near] - path.heading[idx])))
        inl = (np.abs(raw - band) < LC_BAND_M) & (np.abs(dyaw) < 0.7) & (idx < c.i1 + 5)
        worst = None
        ego_front, ego_rear = s_here + self.front, s_here - self.front
        for j in np.flatnonzero(inl).tolist():
            i = near[j]
            half = 0.5 * float(actors.length[i])
            vf = max(0.0, float(actors.speed[i]) * math.cos(float(dyaw[j])))
            slow = vf < LC_SLOW_MPS
            if s[j] + half < ego_rear:
                gap = ego_rear - (s[j] + half)
                need = LC_SLOW_GAP_M if slow else \
                    max(LC_MIN_GAP_M, vf * LC_REACT_S + (vf * vf - v * v) / (2.0 * LC_DECEL))
                where = "behind"
            elif slow and (v >= LC_SLOW_MPS or s[j] - half > ego_front):
                # (but a queue beside a car in a queue itself holds it: it cannot drop behind.
                # Helsinki, seed 37: the car stood beside a standing car past the edge's
                # deadline, its hold ran out, and on moving off it steered into the lane while
                # the car was still beside it; SUMO counted a collision)
                continue
            elif s[j] - half > ego_front:
                gap = (s[j] - half) - ego_front
                need = max(LC_MIN_GAP_M, v * 0.5 + (v * v - vf * vf) / (2.0 * LC_DECEL))
                where = "ahead"
            else:
                gap, need, where = -1.0, 0.0, "beside"
            if gap < need and (worst is None or gap - need < worst[3]):
                worst = (str(actors.ids[i]), vf, where, gap - need)
        return worst[:3] if worst is not None else None

    def _standoff(self, v: float, t: float, actors) -> None:
        """A standoff: the car stands for its sweep's sake (``clearance``), or for a vehicle on
        a junction lane over its path, before a vehicle that stands too, STANDOFF_S and more,
        and SUMO has that vehicle wait for nothing it can see (no red light or queue ahead of
        it) but the car: it waits for the car (Monaco, seed 17: a car stood inside a junction,
        waiting for the car, which waited for it, until SUMO teleported it 120 s later; seed 1:
        the car waited for a car standing on a lane over its path, which waited behind a car
        SUMO had merge ahead of it, which waited behind the car). That vehicle is taken out of SUMO (``SumoTraffic.release_standoff``:
        SUMO's own remedy for a jam, sooner), once. Also a vehicle the car follows (any other
        lead), standing within STANDOFF_GAP_M, where SUMO has it wait for the car through a
        queue (``circle``: Monaco, seed 7, a junction cluster: the car waited for a vehicle
        standing across its path, which waited for one that stood behind the car, in the
        queue SUMO kept behind it; SUMO teleported one every 120 s, and the car drove 114 m in
        300 s); tried again every second while the circle is not closed."""
        who = self.sweep[1] if self.sweep is not None and self.sweep[2] != "building" and \
            self.reason.startswith("clearance") else None
        circle = False
        if who is None and self.lead is not None and self.lead.gap < STANDOFF_GAP_M and self.lead.actor \
                and self.lead.kind == "vehicle":
            # (waited for on a lane over the path: Monaco, seed 1; also while the binding
            # reason flips to "curve" as the car creeps up to it: the Kouvola motorway's
            # junction cluster 2453037388, where the car crept at 0.2 m/s and the wait began
            # again at each flip, for 95 s, until SUMO teleported a vehicle)
            who, circle = self.lead.actor, self.lead.source != "conflict"
        if who is None or v > STANDOFF_CREEP_MPS:
            self._standoff_with = None
            return
        try:
            k = actors.index(who)
        except (KeyError, ValueError, IndexError):
            k = None
        if k is None or actors.kind[k] == "person" or float(actors.speed[k]) > STANDOFF_CREEP_MPS:
            self._standoff_with = None
            return
        if self._standoff_with is None or carried_id(self._standoff_with[0]) != carried_id(who):
            self._standoff_with, self._standoff_next = (who, t), 0.0
            return
        # (the same vehicle carried over a network swap, "veh973" -> "veh973~1": its wait goes on;
        # it began again, and a Lauf car waited 40 s before a bus in place of 20 s)
        self._standoff_with = (who, self._standoff_with[1])
        if t - self._standoff_with[1] < STANDOFF_S or who in self._released or t < self._standoff_next:
            return
        tr = getattr(self.sim, "traffic", None)
        release = getattr(tr, "release_standoff", None) if tr is not None else None
        if release is None:
            return
        if circle:
            if not release(who, STANDOFF_S, circle=True):
                self._standoff_next = t + 1.0           # (not yet: again in a second)
                return
            self._released.add(who)
        else:
            self._released.add(who)
            if not release(who, STANDOFF_S):
                return
        self.stats.standoffs += 1
        self.stats.events.append((round(t, 2), "standoff", f"{who} taken out after {t - self._standoff_with[1]:.0f} s"))
        log.info("standoff with %s at t=%.1f s: taken out of SUMO", who, t)

    # --- perception ----------------------------------------------------------------------
    def _road_pitch(self, st) -> float:
        """The road's pitch under the car: the chassis pitch minus the suspension's own
        (squat / dive), from the wheels' compressions."""
        veh = getattr(self.sim, "vehicle", None)
        if veh is None:
            return st.pitch
        try:
            c = veh.suspension_compression()
        except Exception:
            return st.pitch
        return st.pitch - math.atan2(0.5 * (c[0] + c[1]) - 0.5 * (c[2] + c[3]), veh.spec.wheelbase)

    def _new_path(self, path):
        self._path = path
        self._too_steep = False
        self._over_path, self._conflict_lanes = {}, {}
        self._path_lanes = {ln for ln, _ in path.lane_of}
        self._s_goal = None
        sim = self.sim
        if sim.goal_xy is not None:
            run = path.last_run(path.edges[-1])
            if run is not None:
                k, s_goal, _ = path.project(sim.goal_xy[0], sim.goal_xy[1], hint=run[0] + 20,
                                            window=run[1] - run[0] + 20)
                self._s_goal = float(s_goal)
            else:
                self._s_goal = path.length
        self._osm_stops = self._match_osm_stop_signs(path)
        world = getattr(sim, "world", None)
        bridges = world.bridge_lanes() if world is not None and hasattr(world, "bridge_lanes") else ()
        on = np.array([ln in bridges for ln, _ in path.lane_of], dtype=bool) if bridges else None
        self._path_bridge = on if on is not None and on.any() else None
        self._path_rises = None
        self._path_edges = {e for _, e in path.lane_of}
        self._uturns = self._turns_back(path)

    # --- turning round (cosim.turnround) -----------------------------------------------------
    def _turns_back(self, path) -> list:
        """The path's stop lines where it turns back onto its road's other direction ("-X" for
        "X", else by its junctions: ``cosim.traffic.reverses``) along a line the car would
        run wide of by more than TURN_DEVIATION_MAX_M (a dead end's U-turn, a U-turn inside a
        junction: SUMO draws them 3-4 m round)."""
        from .driving import TURN_DEVIATION_MAX_M, car_turn_radius, turn_deviation
        from .traffic import opposite_edge, reverses

        out = []
        for u in path.stops:
            if not u.to_lane:
                continue
            edge, to = u.lane.rsplit("_", 1)[0], u.to_lane.rsplit("_", 1)[0]
            if to != opposite_edge(edge):
                try:
                    ends = self._network_ends(self.sim.traffic)
                except Exception:
                    continue
                if not reverses(ends, edge, to):
                    continue
            i0 = path.index_at(u.s - 10.0)
            i1 = path.index_at(u.s + u.internal_length + 10.0)
            if turn_deviation(path.xy[i0:i1 + 1], car_turn_radius()) > TURN_DEVIATION_MAX_M:
                out.append(u)
        return out

    def _lane_width(self, lane: str):
        """A lane's width (m; cached), None while SUMO's worker has not sent it yet."""
        got = self._lane_widths.get(lane)
        if got is None:
            try:
                got = self._lane_read("getWidth", lane)
            except Exception:
                got = 3.2
            if got is NOT_YET:
                return None
            got = self._lane_widths[lane] = float(got)
        return got

    def _turn_ahead(self, path, st, s_here: float, v: float, targets: list, t: float):
        """Where the path turns back ahead (:meth:`_turns_back`): a stop short of it, and once
        the car stands there the turn round begins (its first controls returned); None
        otherwise."""
        u = next((u for u in self._uturns if u.s > s_here - 2.0), None)
        if u is None:
            return None
        from .turnround import ROOM_AHEAD_M

        s_stop = u.s - self.front - ROOM_AHEAD_M
        no_room = (u.lane, u.to_lane) in self._no_room
        targets.append((stop_speed(s_stop - s_here, COMFORT_DECEL), "no room to turn round" if no_room else
                        "turning round"))
        if no_room or s_here < s_stop - 1.5 or abs(v) > 0.2 or min(targets, key=lambda x: x[0])[1] != "turning round":
            return None
        if not self._start_turn(path, u, st):
            return None
        return self._turning(st, None, 0.0, t)

    def _start_turn(self, path, u, st) -> bool:
        """A :class:`cosim.turnround.TurnRound` for the car standing before stop line ``u``, if
        the carriageway has room for it (else the car stays stopped: ``no room to turn
        round``). False while the lanes' shapes or widths are still on their way."""
        from . import vehicle as V
        from .driving import car_turn_radius
        from .turnround import SURFACE_STEP_MAX_M, Carriageway, TurnRound, moves_needed, surface_step

        far = self._lane_shape(u.to_lane)
        w_own, w_far = self._lane_width(u.lane), self._lane_width(u.to_lane)
        if far is None or w_own is None or w_far is None:
            return False
        i0, i1 = path.index_at(u.s - 60.0), path.index_at(u.s)
        C = path.xy[i0:i1 + 1]
        t = getattr(self.sim, "t", 0.0)
        try:
            cw = Carriageway.between(C, w_own, far[0], w_far, near_s=float(path.s[self._k] - path.s[i0]))
        except ValueError:
            cw = None
        half_l, half_w = self.length / 2.0, self.width / 2.0
        rear = V.SPEC.rear_axle_x
        n = moves_needed(cw, st.x, st.y, st.yaw, half_l, half_w, car_turn_radius(), rear) if cw else None
        step = surface_step(cw, st.x, st.y, self._surface_heights) if n is not None else 0.0
        if n is None or step > SURFACE_STEP_MAX_M:
            self._no_room.add((u.lane, u.to_lane))
            self.stats.no_room_to_turn += 1
            self.stats.events.append((round(t, 2), "no room to turn round", u.lane))
            why = (f"a step of {step:.2f} m across its carriageway" if n is not None else
                   f"its carriageway ({(cw.left - cw.right) if cw else 0.0:.1f} m) has no room for the moves")
            log.warning("t=%.1f s: the route turns back at the end of lane %s and the car cannot turn round there (%s): "
                        "it stops", t, u.lane, why)
            return False
        max_steer = math.atan(WHEELBASE / car_turn_radius())
        self._turn = TurnRound(cw, half_l, half_w, car_turn_radius(), rear, max_steer, u.to_lane, u.lane)
        log.info("t=%.1f s: turning round before the end of lane %s into %s (%d moves planned)", t, u.lane,
                 u.to_lane, n)
        return True

    def _surface_heights(self, pts: np.ndarray) -> np.ndarray:
        """The height of the world's static surface at points (n, 2): rays down from 4 m over the
        car to 6 m under it, past the car's chassis; NaN where a ray meets nothing or a mirrored
        actor (or without the physics world)."""
        import pybullet as pb

        sim = self.sim
        phys, veh = getattr(sim, "physics", None), getattr(sim, "vehicle", None)
        out = np.full(len(pts), np.nan)
        if phys is None or phys.client is None or veh is None:
            return out
        z = float(veh.state().z)
        actors = set(sim.mirror.body_actors()) if getattr(sim, "mirror", None) is not None else set()
        for k0 in range(0, len(pts), 4000):
            chunk = pts[k0:k0 + 4000]
            hits = pb.rayTestBatch([(float(x), float(y), z + 4.0) for x, y in chunk],
                                   [(float(x), float(y), z - 6.0) for x, y in chunk], numThreads=1,
                                   collisionFilterMask=veh._ray_mask, physicsClientId=phys.client)
            for k, h in enumerate(hits):
                if h[0] >= 0 and h[0] not in actors:
                    out[k0 + k] = h[3][2]
        return out

    def _turning(self, st, actors, dt: float, t: float):
        """The turn round's controls; once done, the route goes on from the lane turned into
        (``sim.turned_round``); given up, the car stands (``no room to turn round``)."""
        tr = self._turn
        throttle, brake, steer, rev = tr.control(st, dt, actors)
        self.reverse = rev
        self.target_speed = 0.0 if (tr.waiting or tr.phase != "go") else MOVE_SPEED_TURN
        self.reason = "turning round" + (": waiting" if tr.waiting else "")
        if tr.done or tr.failed:
            self._turn = None
            self.reverse = False
            if tr.done:
                self.stats.turnarounds += 1
                self.stats.events.append((round(t, 2), "turned round", f"{tr.move + 1} moves"))
                log.info("t=%.1f s: turned round into %s in %d moves", t, tr.to_lane, tr.move + 1)
                turned = getattr(self.sim, "turned_round", None)
                if turned is not None:
                    turned(tr.from_lane, tr.to_lane)
            else:
                self._no_room.add((tr.from_lane, tr.to_lane))
                self.stats.no_room_to_turn += 1
                log.warning("t=%.1f s: gave up turning round before the end of lane %s after %d moves", t,
                            tr.from_lane, tr.move)
            throttle, brake, steer = 0.0, 1.0, steer
        self.last = (throttle, brake, steer)
        return throttle, brake, steer

    def _stuck(self, st, path, s_here: float, v_target: float, reason: str, throttle: float, dt: float,
               t: float) -> bool:
        """Whether the car, held still for STUCK_S against the throttle with nothing ahead to
        stop for (cruising or slowing for a bend), or stopped before a wall its sweep meets
        (:meth:`_sweep`), starts a move back and round
        (:class:`cosim.turnround.BackOff`, towards the way its path heads STUCK_LOOK_M on): at
        most BACKOFF_MAX times within BACKOFF_SPOT_M of the same spot of its path."""
        pushing = throttle >= STUCK_THROTTLE and v_target > 1.0 and reason in ("cruise", "curve", "speed limit")
        if abs(st.speed) < STUCK_MPS and (pushing or reason == "clearance building"):
            self._stuck_s += dt
        else:
            self._stuck_s = 0.0
        if self._stuck_s < STUCK_S:
            return False
        self._stuck_s = 0.0
        if sum(1 for p, s in self._backoffs if p is path and abs(s - s_here) <= BACKOFF_SPOT_M) >= BACKOFF_MAX:
            return False
        from . import vehicle as V
        from .driving import car_turn_radius
        from .turnround import BackOff

        i = path.index_at(s_here + STUCK_LOOK_M)
        j = min(i + 1, len(path.xy) - 1)
        i = j - 1 if j > 0 else 0
        ahead = math.atan2(path.xy[j, 1] - path.xy[i, 1], path.xy[j, 0] - path.xy[i, 0])
        turn = math.remainder(ahead - st.yaw, 2 * math.pi)
        side = 0 if abs(turn) < math.radians(10.0) else (1 if turn > 0 else -1)
        self._backoffs.append((path, s_here))
        self._backoff = BackOff(side, ahead, self.length / 2.0, self.width / 2.0, car_turn_radius(),
                                V.SPEC.rear_axle_x, math.atan(WHEELBASE / car_turn_radius()))
        self.stats.backoffs += 1
        self.stats.events.append((round(t, 2), "backed off", f"held still {STUCK_S:.0f} s at s={s_here:.1f} m"))
        log.info("t=%.1f s: the car is held still (%s) at %.1f m along its path: it backs off "
                 "(%s) and drives on", t, reason, s_here, {1: "right lock, then left", -1: "left lock, then right",
                                                 0: "straight"}[side])
        return True

    def _backing_off(self, st, actors, dt: float, t: float):
        """The moves' controls (:class:`cosim.turnround.BackOff`); once done, the car drives on
        along its path from where it stands."""
        bo = self._backoff
        throttle, brake, steer, rev = bo.control(st, dt, actors, static_in_way=self._static_in_way)
        self.reverse = rev
        self.target_speed = 0.0 if (bo.waiting or bo.phase != "go") else MOVE_SPEED_TURN
        self.reason = "backing off" + (": waiting" if bo.waiting else "")
        if bo.done:
            self._backoff = None
            self.reverse = False
            self.speed.reset()
            self._prev_target = None
            throttle, brake = 0.0, 1.0
        self.last = (throttle, brake, steer)
        return throttle, brake, steer

    def _static_in_way(self, st, forward: bool, curvature: float, ahead_m: float) -> bool:
        """Whether a building or a piece of scenery stands in the way of the car's footprint
        over the next ``ahead_m`` of a move at ``curvature`` (its rear axle's, 1/m, left
        positive), forward or back (:meth:`_static_along`). False without the physics world."""
        from . import vehicle as V
        from .turnround import arc_pose

        poses = [(st.x, st.y, st.yaw),
                 arc_pose(st.x, st.y, st.yaw, ahead_m if forward else -ahead_m, curvature, V.SPEC.rear_axle_x)]
        return self._static_along(st, poses) is not None

    def _static_along(self, st, poses, grow: float = 0.0):
        """The first of the poses (x, y, yaw) of the car's centre (``poses[0]`` where it is)
        at which its footprint, grown by ``grow`` m, meets a building or a piece of scenery on
        its way from the pose before: rays from the footprint's outline (its corners and the
        middles of its sides, at two heights over the car's centre) to where each point gets,
        all cast at once. Its index, or None (also without the physics world)."""
        import pybullet as pb

        sim = self.sim
        phys, veh = getattr(sim, "physics", None), getattr(sim, "vehicle", None)
        if phys is None or phys.client is None or veh is None or len(poses) < 2:
            return None
        hl, hw = self.length / 2.0 + grow, self.width / 2.0 + grow
        ox = np.array([hl, hl, 0.0, -hl, -hl, -hl, 0.0, hl])
        oy = np.array([0.0, hw, hw, hw, 0.0, -hw, -hw, -hw])
        Q = np.array(poses, dtype=float)
        c, s = np.cos(Q[:, 2])[:, None], np.sin(Q[:, 2])[:, None]
        X, Y = Q[:, :1] + c * ox - s * oy, Q[:, 1:2] + s * ox + c * oy        # (poses, 8)
        z0 = float(getattr(st, "z", veh.state().z))
        starts, ends = [], []
        for dz in STATIC_RAY_DZ:
            z = z0 + dz
            for k in range(1, len(Q)):
                starts += [(a, b, z) for a, b in zip(X[k - 1].tolist(), Y[k - 1].tolist())]
                ends += [(a, b, z) for a, b in zip(X[k].tolist(), Y[k].tolist())]
        hits = pb.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=veh._ray_mask,
                               physicsClientId=phys.client)
        first = None
        n = len(Q) - 1
        for r, ((a, b), h) in enumerate(zip(zip(starts, ends), hits)):
            # (a face met within STATIC_TOUCH_M of the point: the one it touches, moving off it;
            # Bullet turns a face's normal towards the ray, from either side)
            if h[0] < 0 or h[2] * math.dist(a, b) < STATIC_TOUCH_M:
                continue
            k = (r // 8) % n + 1
            if (first is None or k < first) and phys.body_kind(h[0]) in ("building", "scenery"):
                first = k
        return first

    def _same_level(self, actors, path, s_here: float):
        """`actors` without those on another level than the path: a car on a bridge's deck over
        the path, or on the road under a deck the path goes over. An actor's level is how high
        it stands over the terrain (``ActorMirror.raised``: on a deck, else 0); the path's, where
        the actor would meet it (its projection), how high the path's lane is there over the
        terrain (a bridge's lane, else 0); they are other levels more than LEVEL_M apart.
        Actors on the path's roads, persons and vehicles on no known lane are kept. Such a car
        crossing the path is no lead, foe or obstacle (Monaco, seed 13: the car stopped for
        cars passing over it on Boulevard du Larvotto's bridge). The actors as they are where
        no actor stands on a deck and the path has no bridge near."""
        raised = getattr(getattr(self.sim, "mirror", None), "raised", None) or {}
        bridge = self._path_bridge
        n = len(actors)
        lanes = getattr(actors, "lane", None)
        if not n or lanes is None:
            return actors
        s0, s1 = s_here - 20.0, s_here + SENSE_RANGE_M + 40.0
        up = None                   # the path's points ahead on a deck more than LEVEL_M up
        if bridge is not None:
            i0, i1 = path.index_at(s0), path.index_at(s1) + 1
            on = i0 + np.flatnonzero(bridge[i0:i1])
            if len(on):
                up = on[self._path_rises_at(path, on) > LEVEL_M]
                if not len(up):
                    up = None
        if not raised and up is None:
            return actors
        is_raised = np.array([a in raised for a in actors.ids.tolist()], dtype=bool) if raised \
            else np.zeros(n, dtype=bool)
        if up is None:              # only raised actors can be on another level
            cand = np.flatnonzero(is_raised)
        else:                       # ... and those that can meet the path where it is up
            P = path.xy[up]
            lo, hi = P.min(axis=0) - LEVEL_REACH_M, P.max(axis=0) + LEVEL_REACH_M
            near = (actors.x >= lo[0]) & (actors.x <= hi[0]) & (actors.y >= lo[1]) & (actors.y <= hi[1])
            cand = np.flatnonzero(near | is_raised)
        if len(cand):
            # (persons are kept: one on a walking area or crossing on a deck, no bridge's lane,
            # stands on the terrain in this world; so is a vehicle on no known lane)
            edges = self._path_edges
            cand = cand[[bool(ln) and k != "person" and ln.rsplit("_", 1)[0] not in edges
                         for ln, k in zip(lanes[cand].tolist(), actors.kind[cand].tolist())]]
        if not len(cand):
            return actors
        if up is None:              # (the path is on the ground ahead: each one raised is up there)
            s, ok = None, np.ones(len(cand), dtype=bool)
        else:
            s, _ = path.project_many(actors.x[cand], actors.y[cand], s0, s1)
            ok = np.isfinite(s)
        h_actor = np.array([raised.get(a, 0.0) for a in actors.ids[cand].tolist()])
        h_path = np.zeros(len(cand))
        if up is not None:
            idx = np.clip(np.searchsorted(path.s, np.where(ok, s, 0.0), side="right") - 1, 0, len(path.s) - 1)
            at = np.flatnonzero(ok & self._path_bridge[idx])
            h_path[at] = self._path_rises_at(path, idx[at])
        other = cand[ok & (np.abs(h_actor - h_path) > LEVEL_M)]
        if not len(other):
            return actors
        keep = np.ones(n, dtype=bool)
        keep[other] = False
        return actors.subset(keep)

    def _path_rises_at(self, path, idx: np.ndarray) -> np.ndarray:
        """How high the path's points `idx` (on a bridge's lane) stand over the terrain: the
        highest road surface there less the terrain's height (0 where unknown; cached)."""
        rises = self._path_rises
        if rises is None or len(rises) != len(path.xy):
            rises = self._path_rises = np.full(len(path.xy), np.nan)
        new = idx[np.isnan(rises[idx])]
        if len(new):
            # (with the bridge's points up to 200 further on: one call for a stretch of them)
            lo = int(new.max()) + 1
            hi = min(len(rises), lo + 199)
            more = lo + np.flatnonzero(self._path_bridge[lo:hi] & np.isnan(rises[lo:hi]))
            new = np.concatenate((new, more))
            world = self.sim.world
            x, y = path.xy[new, 0], path.xy[new, 1]
            r = world.road_top_z(x, y) - world.ground_z(x, y)
            rises[new] = np.where(np.isfinite(r) & (r > 0.0), r, 0.0)
        return rises[idx]

    def _world_edge(self, path, s_here, horizon):
        """Arc length of the first path point ahead outside the built chunks, or None."""
        world = getattr(self.sim, "world", None)
        if world is None or not getattr(world, "chunks", None):
            return None
        i0, i1 = path.index_at(s_here), path.index_at(s_here + horizon + 10.0) + 1
        cs = float(world.chunk_size)
        ij = np.floor(path.xy[i0:i1] / cs + 0.5).astype(int)
        if not len(ij):
            return None
        keys = world.chunks
        # (the points come in runs in one chunk: the first point of each run is tested)
        starts = [0] + (np.flatnonzero((ij[1:] != ij[:-1]).any(axis=1)) + 1).tolist()
        for k, (ci, cj) in zip(starts, ij[starts].tolist()):
            if (ci, cj) not in keys:
                return float(path.s[i0 + k])
        return None

    def _sense(self, st, s_here, actors, path) -> Lead | None:
        cands = []
        # 1. lidar
        self.scan = None
        if self.lidar is not None:
            from .sensors import corridor_obstacle

            self.scan = scan = self.lidar.scan_vehicle(st)
            hit = corridor_obstacle(scan, path, s_here, front=self.front)
            if hit is not None:
                mirror = getattr(self.sim, "mirror", None)
                aid = mirror.body_actors().get(hit.body) if mirror is not None else None
                if aid is not None and actors is not None and len(actors):
                    try:
                        i = actors.index(aid)
                        kind = "person" if actors.kind[i] == "person" else "vehicle"
                        sp = 0.0 if kind == "person" else max(
                            0.0, float(actors.speed[i]) * math.cos(float(actors.yaw[i]) - path.heading_at(hit.s)))
                    except KeyError:
                        kind, sp = "vehicle", 0.0
                    cands.append(Lead(hit.gap, sp, kind, "lidar", aid))
                elif aid is None:
                    cands.append(Lead(hit.gap, 0.0, "static", "lidar"))
        # 2. the mirrored actors, projected onto the path
        if actors is not None and len(actors):
            lead = self._actors_on_path(actors, st, s_here, path)
            if lead is not None:
                cands.append(lead)
        # 3. SUMO's leader
        lead = self._sumo_leader(s_here, path, actors)
        if lead is not None:
            cands.append(lead)
        if not cands:
            return None
        return min(cands, key=lambda c: c.gap)

    def _sweep_steering(self, st, path, s_here, actors):
        """The car's sweep (_sweep) with its usual steering and, where that touches something,
        with close tracking (``pp_close``). Returns (the first touch with the usual steering,
        the touch to stop before or None, the steering to use, the speed it allows or None).

        Where close tracking passes, or touches a metre and more further on, the car follows
        the path closely at CLOSE_TRACK_MPS at most. Where it touches no nearer than the usual
        steering, the car stops before it and steers closely while it does: steered by the
        longer look-ahead between two steps of close tracking, a car in a tight right turn in
        Lauf ran wide each time it braked, until it touched a bus waiting on the opposite lane
        of the road it turned into (then it pushed against the bus for 18 s)."""
        touch = self._sweep(st, path, s_here, actors, self.pp)
        if touch is None:
            return None, None, self.pp, None
        close = self._sweep(st, path, s_here, actors, self.pp_close)
        if close is None or close[0] > touch[0] + 1.0:
            return touch, close, self.pp_close, CLOSE_TRACK_MPS
        if close[0] >= touch[0]:
            return touch, close, self.pp_close, None
        return touch, touch, self.pp, None

    def _sweep(self, st, path, s_here, actors, pp) -> tuple | None:
        """Where the car's footprint, rolled forward along the way its steering takes it,
        first comes within SWEEP_MARGIN_M of a mirrored actor, or within SWEEP_WALL_M of a
        building or a piece of scenery (:meth:`_static_along`): (distance along the roll, actor
        id or "wall", "vehicle", "person" or "building"), or None.

        The path corridor (_sense) covers what stands on the lane path; in a turn tighter than
        the car's smallest circle, or at a kink of a junction lane, the car cuts the corner by
        half a metre or more, and a vehicle standing at the start of the opposite lane, inside
        the turn, is beside the corridor but in the car's way (Kouvola, seed 3: a car standing
        askew there was brushed at 2.9 m/s). The roll is pure pursuit on a kinematic bicycle
        (the steering moving at its rate limit) from the car's pose, steered by ``pp``. An
        actor the car touches already is left out (braking cannot help; the other checks see
        it). (A wall: Lauf's Förstergasse, where the car met a house at a bend at 0.5-2.9 m/s
        before it backed off: :meth:`_stuck`.)"""
        if st.speed < -0.1:
            return None
        v = max(st.speed, 0.0)
        reach = min(SWEEP_MAX_M, SWEEP_MIN_M + v * v / (2.0 * SWEEP_DECEL))
        # where the car is on the path and the path ahead turns no tighter than
        # SWEEP_GATE_RADIUS_M, the car stays on it (lateral error p95 0.15 m) and the corridor
        # covers its sweep: no roll
        if abs(self._lat) < SWEEP_GATE_M:
            i0, i1 = max(0, self._k - 2), path.index_at(s_here + reach + pp.lookahead(v)) + 1
            if i1 <= i0 or float(np.abs(path.curvature_smooth[i0:i1]).max()) * SWEEP_GATE_RADIUS_M < 1.0:
                return None
        boxes = self._sweep_boxes(st, actors, reach) if actors is not None and len(actors) else []
        # the roll: the car's centre every SWEEP_STEP_M
        c, s = math.cos(st.yaw), math.sin(st.yaw)
        rear = pp.rear
        rx, ry, yaw = st.x - rear * c, st.y - rear * s, st.yaw
        kappa = math.tan(getattr(st, "steer", 0.0)) / WHEELBASE
        kmax = pp.kmax
        v_roll = max(v, 1.0)
        dk = STEER_RATE / WHEELBASE / v_roll * SWEEP_STEP_M     # curvature change per step (small angles)
        s_path = s_here
        poses, dists = [], []
        d = 0.0
        while True:
            poses.append((rx + rear * math.cos(yaw), ry + rear * math.sin(yaw), yaw))
            dists.append(d)
            if d >= reach:
                break
            _, kc = pp.steer(path, poses[-1][0], poses[-1][1], yaw, v_roll, s_path)
            kc = max(-kmax, min(kmax, kc))
            kappa += max(-dk, min(dk, kc - kappa))
            half = yaw + 0.5 * kappa * SWEEP_STEP_M
            rx += SWEEP_STEP_M * math.cos(half)
            ry += SWEEP_STEP_M * math.sin(half)
            yaw += kappa * SWEEP_STEP_M
            s_path += SWEEP_STEP_M
            d += SWEEP_STEP_M
        # a wall on the way (a house at a bend tighter than the lane lets the car take); the
        # pose where the car stands now is left out (one it touches already: braking cannot help)
        wall = self._static_along(st, poses, grow=SWEEP_WALL_M)
        L, W = self.length + 2.0 * SWEEP_MARGIN_M, self.width + 2.0 * SWEEP_MARGIN_M
        for k, ((x, y, h), d) in enumerate(zip(poses, dists)):
            if wall is not None and k >= wall:
                return dists[k - 1], "wall", "building"     # (met on the way from the pose before)
            b = (x, y, h, L, W)
            t_roll = min(d / v_roll, SWEEP_PREDICT_S)
            for i, a, vel in boxes:
                if vel is not None and t_roll > 0.0:
                    a = (a[0] + vel[0] * t_roll, a[1] + vel[1] * t_roll) + a[2:]
                if _boxes_overlap(b, a):
                    kind = "person" if actors.kind[i] == "person" else "vehicle"
                    return d, str(actors.ids[i]), kind
        return None

    def _sweep_boxes(self, st, actors, reach: float) -> list:
        """For :meth:`_sweep`: the boxes of the actors near enough to meet the car's roll, each
        as (actor index, box, velocity or None)."""
        dx, dy = actors.x - st.x, actors.y - st.y
        # (the car's box within `reach` of its centre, the actors' boxes: by half diagonals)
        lim = reach + 0.5 * (math.hypot(self.length, self.width) + np.hypot(actors.length, actors.width)) \
            + SWEEP_MARGIN_M + np.abs(actors.speed) * SWEEP_PREDICT_S
        near = np.nonzero(dx * dx + dy * dy < lim * lim)[0]
        boxes: list = []
        if len(near) == 0:
            return boxes
        here = (st.x, st.y, st.yaw, self.length, self.width)
        c, s = math.cos(st.yaw), math.sin(st.yaw)
        behind = -0.5 * self.length + SWEEP_MARGIN_M + 0.15
        mirror = getattr(self.sim, "mirror", None)
        for i in near.tolist():
            b = (float(actors.x[i]), float(actors.y[i]), float(actors.yaw[i]), float(actors.length[i]),
                 float(actors.width[i]))
            # a bus or a truck in a turn: the bent chain of boxes its body is in PyBullet (its
            # snapshot's straight box cuts the turn's inside; Helsinki, dense, seed 22: a 12 m
            # bus turning past the standing car, its tail outside that box, touched the car as
            # it drove off)
            chain = mirror.chain_boxes(actors.ids[i]) if mirror is not None and b[3] > 7.0 else None
            for b in chain or (b,):
                # wholly behind the car's rear bumper: driving forward leaves it (a car queued 5
                # cm behind, within the margin, held a Monaco car for good: "clearance" at 0 m)
                rel = b[2] - st.yaw
                front = (b[0] - st.x) * c + (b[1] - st.y) * s + \
                    0.5 * (b[3] * abs(math.cos(rel)) + b[4] * abs(math.sin(rel)))
                if front < behind:
                    continue
                if not _boxes_overlap(here, b):
                    # one not going the car's way (crossing, oncoming) moves on along its heading
                    # while the car rolls, for up to SWEEP_PREDICT_S (Monaco, seed 28: a car at
                    # 6.8 m/s angled 24 degrees towards the car's side passed 0.1 m clear of the
                    # roll's margin and touched the car's rear corner 0.2 s later)
                    sp = float(actors.speed[i])
                    moving = sp > 0.5 and abs(math.remainder(b[2] - st.yaw, 2 * math.pi)) > math.pi / 4
                    vel = (sp * math.cos(b[2]), sp * math.sin(b[2])) if moving else None
                    if actors.kind[i] == "person" and sp >= SWEEP_STILL_MPS:
                        # a walking person is kept 0.5 m from, not 0.15 m (Portland, seed 1:
                        # walking back along the car's side as it crept round a right turn, in
                        # and out of the margin, it let the car on each other step, and the car's
                        # corner hit it). One standing is not: at a crossing SUMO's persons wait
                        # for the car, and two standing on a walking area's corner 0.55 m beside
                        # the car's turn held it for good (Helsinki, dense seed 20)
                        b = b[:3] + (b[3] + 2.0 * SWEEP_PERSON_M, b[4] + 2.0 * SWEEP_PERSON_M)
                    boxes.append((i, b, vel))
        return boxes

    def _expect(self, path, s_here, v, actors) -> None:
        """Tell SUMO's worker process (``TrafficProcess.expect``) what this driver will read
        soon, so that those reads do not wait for the SUMO step in flight when they come
        (each such wait cost a frame about one SUMO step): the network answers about the
        path's junctions and the roads of the actors around, the links and the lanes to
        watch at the next stop lines, the crossings ahead. Reaches EXPECT_AHEAD_M beyond
        what the checks below look at, so that the answers are in before they are asked."""
        tr = getattr(self.sim, "traffic", None)
        expect = getattr(tr, "expect", None)
        if expect is None:
            return
        lane_p, edge_p = ("sumo", "lane"), ("sumo", "edge")
        reads = [((name,), ()) for name in NETWORK_READS]
        far = s_here + SENSE_RANGE_M + EXPECT_AHEAD_M
        for lane in path.lanes_between(s_here - 5.0, far):
            if lane.startswith(":"):
                reads.append((lane_p + ("getInternalFoes",), (lane,)))
        lanes = getattr(actors, "lane", None)
        if lanes is not None:
            for ln in set(lanes[actors.kind != "person"].tolist()):
                if ln and not ln.startswith(":"):
                    if self._lane_vias is not None and ln not in self._vias_asked:
                        self._vias_asked.add(ln)
                        reads += [(lane_p + ("getShape",), (w,)) for w in self._lane_vias.get(ln, ())
                                  if w not in self._lane_shapes]
                elif ln and ln not in self._lane_shapes:
                    reads.append((lane_p + ("getShape",), (ln,)))
        front = s_here + self.front
        horizon = max(60.0, v * v / (2 * COMFORT_DECEL) + 30.0) + EXPECT_AHEAD_M
        inc = self._incoming if self._incoming is not None else {}
        answered = getattr(tr, "answered", None)
        for stop in path.stops:
            if stop.s < front - 0.3:
                continue
            if stop.s > front + horizon:
                break
            if answered is not None:
                # the foes at this stop as soon as they are in (not when _junction_clear first
                # reads them), so that their vehicles are asked for from the next step on, before
                # that check reads them (each read not asked ahead waits for the step in flight)
                key = (stop.lane, stop.to_lane)
                if key not in self._foes:
                    got = answered(lane_p + ("getFoes",), key)
                    if got is not NOT_YET:
                        self._foes[key] = _normal_lanes(got)
                if stop.via and stop.via not in self._internal_foes:
                    got = answered(lane_p + ("getInternalFoes",), (stop.via,))
                    if got is not NOT_YET:
                        self._internal_foes[stop.via] = self._vehicle_lanes(got)
            reads.append((lane_p + ("getLinks",), (stop.lane,)))
            reads.append((lane_p + ("getFoes",), (stop.lane, stop.to_lane)))
            if stop.via:
                reads.append((lane_p + ("getInternalFoes",), (stop.via,)))
                for f in self._internal_foes.get(stop.via, ()):
                    reads.append((lane_p + ("getLastStepVehicleIDs",), (f,)))
            for f in self._foes.get((stop.lane, stop.to_lane), ()):
                reads += [(lane_p + ("getLength",), (f,)), (lane_p + ("getLastStepVehicleIDs",), (f,))]
                for q in inc.get(f, ()):
                    reads += [(lane_p + ("getLength",), (q,)), (lane_p + ("getLastStepVehicleIDs",), (q,))]
        for c in path.crossings:
            if c.s + c.width / 2.0 < front:
                continue
            if c.s - c.width / 2.0 > front + max(40.0, v * v / (2 * COMFORT_DECEL) + 20.0) + EXPECT_AHEAD_M:
                break
            reads.append((edge_p + ("getLastStepPersonIDs",), (c.edge,)))
        try:
            expect(reads)
        except Exception as e:      # (a worker that died says so at the next call)
            log.debug("expect: %s", e)

    def _foe_lanes(self, path, s_here) -> set:
        """Junction lanes of other links that cross the path's junction lanes ahead."""
        out = set()
        tr = getattr(self.sim, "traffic", None)
        if tr is None:
            return out
        for lane in path.lanes_between(s_here - 5.0, s_here + SENSE_RANGE_M):
            if not lane.startswith(":"):
                continue
            foes = self._internal_foes_all.get(lane)
            if foes is None:
                try:
                    foes = set(tr.sumo.lane.getInternalFoes(lane))
                except Exception:
                    foes = set()
                self._internal_foes_all[lane] = foes
            out |= foes
        return out

    def _actors_on_path(self, actors, st, s_here, path) -> Lead | None:
        """The nearest actor in the path corridor ahead, or crossing into it in time to meet
        the ego: pedestrians, and vehicles on junction lanes that cross the path's (SUMO's
        ``lane.getInternalFoes``). A crossing actor's position and velocity in the path's
        frame give the interval it occupies the corridor, compared with the interval the ego
        needs to pass its spot at the current speed."""
        dx, dy = actors.x - st.x, actors.y - st.y
        near = np.nonzero(dx * dx + dy * dy < SENSE_RANGE_M ** 2)[0]
        if len(near) == 0:
            return None
        s0, s1 = s_here, min(path.length, s_here + SENSE_RANGE_M)
        s, off = path.project_many(actors.x[near], actors.y[near], s0, s1 + 5.0)
        half_ego = self.width / 2.0 + 0.3
        # where each actor is in the path's frame, for all at once: those beside or behind the
        # ego, or too far to the side, are left out before the loop
        ok = np.isfinite(s) & (s < s1 + 4.0)
        if not ok.any():
            return None
        near, s, off = near[ok], s[ok], off[ok]
        idx = np.minimum(np.maximum(path.s.searchsorted(s, side="right") - 1, 0), len(path.s) - 1)
        dyaw = actors.yaw[near] - path.heading[idx]
        cos_d, sin_d = np.cos(dyaw), np.sin(dyaw)
        c, sn = np.abs(cos_d), np.abs(sin_d)
        L, W = actors.length[near], actors.width[near]
        persons = actors.kind[near] == "person"
        speeds = actors.speed[near]
        ext_lons = 0.5 * L * c + 0.5 * W * sn
        gaps = s - s_here - self.front - ext_lons
        hws = half_ego + 0.5 * W * c + 0.5 * L * sn
        crossings = persons | (c < 0.7)
        # (a crossing actor is watched from as far as it covers in 4 s sideways)
        reaches = np.where(crossings, np.maximum(12.0, 4.0 * np.abs(speeds * sin_d)), 12.0)
        inside_mask = (gaps >= -self.front) & (np.abs(off) <= hws + reaches)
        keep = np.flatnonzero(inside_mask).tolist()
        v_ego = max(st.speed, 0.5)
        foes = None
        tr = getattr(self.sim, "traffic", None)
        lanes = getattr(actors, "lane", None)
        extra = set()
        if tr is not None and lanes is not None:
            # vehicles on (or heading into) a junction lane that runs over the path ahead are
            # timed along that lane wherever they are now, beside or behind the car too (Monaco,
            # seed 6: a car came up from behind on the left, on a road into the next junction,
            # whose lane across the car's road SUMO draws 25 m from the junction: it drove into
            # the car's side)
            cand = np.flatnonzero(~inside_mask & ~persons)
            conf = self._conflict_lanes
            for j, ln in zip(cand.tolist(), lanes[near[cand]].tolist()):
                c = conf.get(ln)
                if c is None:
                    c = self._conflict_vias(path, ln)
                if c:
                    extra.add(j)
            if extra:
                keep = sorted(keep + list(extra))
        best = None
        for j in keep:
            i = near[j]
            person, crossing = bool(persons[j]), bool(crossings[j])
            ext_lon, gap, hw = float(ext_lons[j]), float(gaps[j]), float(hws[j])
            sp = float(speeds[j])
            v_along = sp * float(cos_d[j])
            v_lat = sp * float(sin_d[j])              # + = towards the path's left
            o = float(off[j])
            inside = abs(o) <= hw
            if not person and tr is not None:
                # SUMO's lanes say which vehicles can meet the ego: those on the path's lanes
                # (or beside them on the same edge: lane changes) and those on junction lanes
                # that cross the path's; oncoming and other traffic stays in its lanes
                if foes is None:
                    foes = self._foe_lanes(path, s_here)
                    mine = path.lanes_between(s_here - 5.0, s_here + SENSE_RANGE_M)
                    my_edges = {ln.rsplit("_", 1)[0] for ln in mine}
                    my_junctions = {junction_of(ln) for ln in mine if ln.startswith(":")}
                if lanes is not None:
                    lane = lanes[i] or None     # from the step's context subscription
                else:
                    try:
                        lane = tr.sumo.vehicle.getLaneID(str(actors.ids[i]))
                    except Exception:
                        lane = None
                if lane:
                    on_path = lane in mine or lane.rsplit("_", 1)[0] in my_edges
                    if not on_path and lane not in foes and not person:
                        # a junction lane that SUMO does not make a foe of the path's but that
                        # runs over it (two junctions drawn into each other, a turn drawn across
                        # the end of the road in: Monaco): timed along its own lane, or along
                        # the lane it is on and on into such a junction lane
                        if lane.startswith(":"):
                            hit = None if lane in self._path_lanes else \
                                self._lane_conflict(path, lane, actors, i, s_here, v_ego)
                        else:
                            hit = None
                            vias = self._conflict_lanes.get(lane)
                            for via in vias if vias is not None else self._conflict_vias(path, lane):
                                if via in foes:
                                    continue
                                h = self._lane_conflict(path, via, actors, i, s_here, v_ego, approach=lane)
                                if h is not None and (hit is None or h.gap < hit.gap):
                                    hit = h
                        if hit is not None:
                            if best is None or hit.gap < best.gap:
                                best = hit
                            continue
                    if j in extra:
                        continue        # (kept for the timing above only)
                    if not on_path:
                        if lane in foes:
                            crossing = True
                        elif not crossing:
                            continue    # parallel or oncoming, in its own lanes
                        elif not lane.startswith(":") and self._at_path_junction(tr, lane, my_junctions):
                            # on a road into (or out of) a junction of the path: the junction's
                            # right of way decides (_junctions), not the crossing time (a car
                            # 17 m up a side street stopped the ego inside a Helsinki junction)
                            continue
                        # (else a vehicle crossing the path on a lane SUMO does not make a foe:
                        # a road that SUMO's network takes over or under the path, which this
                        # world, draped on the terrain, has at grade; the timing below decides)
                    elif not inside:
                        # on one of the path's lanes, but beside the corridor: the path is
                        # changing into its lane (blended from the lane it came in on over the
                        # edge). Followed like a leader, so that the car merges behind it, not
                        # into its side (Helsinki, seed 12: a car 0.7 m ahead in the lane
                        # changed into, side-swiped at 6.9 m/s)
                        # (not while the car holds back from that change: _lane_change)
                        if not (lane in mine and not crossing and abs(o) <= hw + MERGE_WATCH_M) or path.hold >= 0.5:
                            continue
                        inside = True
                elif not inside:
                    continue
            if inside and not crossing:
                lead_v = max(0.0, v_along)
            else:
                lead_v = 0.0
                min_vlat = 0.3 if person else 0.5
                towards = o * v_lat < 0
                if abs(v_lat) < min_vlat:
                    if not inside:
                        continue
                    t_in, t_out = 0.0, float("inf")
                elif inside:
                    t_in = 0.0
                    t_out = (hw + abs(o)) / abs(v_lat) if towards else (hw - abs(o)) / abs(v_lat)
                elif towards:
                    t_in = (abs(o) - hw) / abs(v_lat)
                    t_out = (abs(o) + hw) / abs(v_lat)
                else:
                    continue
                if t_in > 4.0:
                    continue
                t_arr = max(gap, 0.0) / v_ego
                # the ego may slow down before it is past (a curve on the way: a motorway ramp
                # crossing a road at grade, where the car slowed from 22 to 12 m/s and met a
                # car it had timed to pass behind): it passes at the lowest speed its path
                # allows up to the far side of the actor's track
                v_slow = min(v_ego, curve_speed(path.max_curvature(s_here, float(s[j]) + self.length)))
                t_pass = (max(gap, 0.0) + self.length + 2.0 * ext_lon) / max(v_slow, 0.5)
                if t_arr > t_out + 1.0 or t_pass < t_in - 0.5:
                    continue                          # it is gone before, or comes after, the ego
            if crossing and not person and not inside:
                # past the point of no return (its track is nearer than the ego can stop in,
                # or already under the car), braking would leave the ego standing in its way:
                # go on (a Helsinki drive braked at 6.6 m/s2 for a gap of 0 m and stopped there)
                if gap < v_ego * v_ego / (2.0 * HARD_DECEL):
                    continue
                track_gap = max(0.0, gap)
                # a vehicle crossing the path: stop before its road, not just before its lane
                # (stopped 4 m before a car in the far lane of a two-lane road, the car's nose
                # was in the near lane, and a truck in it hit the car)
                gap -= CROSS_LANE_MARGIN_M
            else:
                # a person walking in from the side (not in the corridor yet): its track too,
                # for the near-miss count (a Lauf person 4 m beside the path, stepping towards
                # it, counted as a near miss at TTC 0.76 s as if it stood in the lane)
                track_gap = max(0.0, gap) if person and not inside else None
            if best is None or gap < best.gap:
                best = Lead(max(0.0, gap), lead_v, "person" if person else "vehicle", "actors", str(actors.ids[i]),
                            track_gap)
        return best

    def _lane_shape(self, lane: str):
        """A lane's centreline every metre or less, and the arc length at each point (cached);
        None while SUMO's worker has not sent it yet (asked for now, in by the next frame: a
        wait for the step in flight cost a frame 1.6-2.7 ms, 15 times in 120 s of a Helsinki
        drive at about 400 actors, each for a vehicle seen on a new lane)."""
        got = self._lane_shapes.get(lane)
        if got is None:
            try:
                P = self._lane_read("getShape", lane)
                if P is NOT_YET:
                    return None
                P = np.asarray(P, dtype=float)[:, :2]
            except Exception:
                P = np.zeros((0, 2))
            Q = _resample(P, 1.0) if len(P) >= 2 else np.zeros((0, 2))
            if len(Q) >= 2:
                got = (Q, np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(Q, axis=0).T))]))
            else:
                got = (np.zeros((0, 2)), np.zeros(0))
            self._lane_shapes[lane] = got
        return got

    def _lane_read(self, fn: str, lane: str):
        """SUMO's ``lane.<fn>(lane)``, a network answer: from SUMO's worker without waiting for
        the step in flight (NOT_YET until it is in, by the next frame), else in process."""
        tr = self.sim.traffic
        answered = getattr(tr, "answered", None)
        if answered is not None:
            return answered(("sumo", "lane", fn), (lane,))
        return getattr(tr.sumo.lane, fn)(lane)

    def _vias(self, lane: str) -> tuple:
        """The junction lanes that the links of (normal) lane `lane` go through (the whole
        network's, read once per network)."""
        if self._lane_vias is None:
            try:
                self._lane_vias = self.sim.traffic.via_lanes()
            except Exception:
                self._lane_vias = {}
        return self._lane_vias.get(lane, ())

    def _over(self, path, lane: str) -> bool:
        """Does junction lane `lane` come within OVER_PATH_M of the path anywhere (cached per
        path; ``_lane_conflict`` looks closer)? The callers leave out the lanes SUMO makes foes
        of the path's: there SUMO's right of way decides (``_junctions``). In the path's own
        junctions too, a lane SUMO does not make a foe can run over the path (Monaco, dense seed
        22: a car turning left from the opposite road swept across the car's right turn in
        cluster_2104788829_..., SUMO's two links not foes; the car saw it only on the junction
        lane, 7 m away, and it drove into the car standing)."""
        got = self._over_path.get(lane)
        if got is None:
            got = ()
            # (not the path's own lanes: a vehicle headed onto them is on the path behind the
            # car; Lauf, seed 40: one coming up 9 m behind, its junction lane taken for one
            # over the path, braked the car from 4.5 to 1.8 m/s in the junction)
            shape = self._lane_shape(lane) if lane not in self._path_lanes else ((), None)
            if shape is None:
                return None         # (not known yet: asked again next frame)
            P = shape[0]
            if len(P):
                lo, hi = P.min(axis=0) - OVER_PATH_M, P.max(axis=0) + OVER_PATH_M
                box = np.flatnonzero(np.all((path.xy >= lo) & (path.xy <= hi), axis=1))
                if len(box):
                    d2 = ((P[:, None, :] - path.xy[box][None, :, :]) ** 2).sum(axis=2)
                    close = box[d2.min(axis=0) < OVER_PATH_M ** 2]
                    if len(close):      # the path's stretch near it
                        got = (float(path.s[close.min()]), float(path.s[close.max()]))
            self._over_path[lane] = got
        return bool(got)

    def _conflict_vias(self, path, lane) -> tuple:
        """The junction lanes over the path (``_over``) that a vehicle on `lane` is on or heads
        into: `lane` itself, or those its links go through (cached per path)."""
        got = self._conflict_lanes.get(lane)
        if got is None:
            if not lane:
                got = ()
            else:
                vias = (lane,) if lane.startswith(":") else self._vias(lane)
                over = [self._over(path, via) for via in vias]
                got = tuple(via for via, o in zip(vias, over) if o)
                if any(o is None for o in over):
                    return got      # (a shape not in yet: not kept, asked again next frame)
            self._conflict_lanes[lane] = got
        return got

    def _lane_conflict(self, path, lane: str, actors, i: int, s_here: float, v_ego: float,
                       approach: str | None = None) -> Lead | None:
        """The vehicle `i` on junction lane `lane` (or on lane `approach` that leads into it),
        if that lane passes within the two bodies' half widths (+ LANE_CONFLICT_MARGIN_M) of the
        path ahead and the vehicle is there while the car would be: a stop before that
        stretch. Its times in and out come from its distance along its lane(s) and its speed."""
        s1 = s_here + SENSE_RANGE_M
        if approach is not None:
            near = self._over_path.get(lane)      # (where on the path it comes near: _over)
            if not near or near[1] < s_here - self.length - 5.0 or near[0] > s1:
                return None
        shape = self._lane_shape(lane)
        if shape is None:
            return None
        P, arc = shape
        if not len(P):
            return None
        W, L = float(actors.width[i]), float(actors.length[i])
        reach = 0.5 * (self.width + W) + LANE_CONFLICT_MARGIN_M
        if not path.comes_within(lane, P, s_here - 5.0, s1, reach):
            return None         # (the usual answer, from distances kept per lane: see comes_within)
        s, off = path.project_many(P[:, 0], P[:, 1], s_here - 5.0, s1)
        hit = np.isfinite(s) & (np.abs(off) < reach) & (s < s1 - 1.0)
        if not hit.any():
            return None
        a0, a1, p0, p1 = float(arc[hit].min()), float(arc[hit].max()), float(s[hit].min()), float(s[hit].max())
        yaw = float(actors.yaw[i])
        fx = float(actors.x[i]) + 0.5 * L * math.cos(yaw)
        fy = float(actors.y[i]) + 0.5 * L * math.sin(yaw)
        if approach is None:
            pos = float(arc[int(np.argmin((P[:, 0] - fx) ** 2 + (P[:, 1] - fy) ** 2))])
        else:       # on the lane into it: its distance to that lane's end, before the junction lane's start
            shape = self._lane_shape(approach)
            if shape is None or not len(shape[0]):
                return None
            A, arc_a = shape
            pos = float(arc_a[int(np.argmin((A[:, 0] - fx) ** 2 + (A[:, 1] - fy) ** 2))] - arc_a[-1])
        if pos - L > a1:
            return None                                   # its back is past the stretch
        sp = float(actors.speed[i])
        if sp < 0.5:
            if pos < a0:
                return None                               # standing before it
            if self._waits_for_ego(str(actors.ids[i])):
                # SUMO has it wait for the car: the car goes first (its body, if in the way,
                # is the sweep's; Kouvola, seed 1: a U-turn waiting for the car, the car for it)
                return None
            t_in, t_out = 0.0, float("inf")
        else:
            t_in, t_out = max(a0 - pos, 0.0) / sp, (a1 - pos + L) / sp
        gap = p0 - s_here - self.front
        if gap < -self.length:
            return None                                   # the stretch is behind the car
        if gap > 0.0:
            if t_in > 6.0:
                return None
            if gap < v_ego * v_ego / (2.0 * HARD_DECEL) and t_in > 0.0:
                return None           # past the point of no return, and not there yet: go on
            t_arr = gap / v_ego
            t_pass = (gap + self.length + 2.0) / max(v_ego, 0.5)
            if t_arr > t_out + 1.0 or t_pass < t_in - 0.5:
                return None           # gone before the car gets there, or comes after it
        elif (p1 - s_here + 0.5 * self.length + 2.0) / max(v_ego, 0.5) < t_in - 0.5:
            # the car is in the stretch already and out of it before the vehicle comes: go on
            # (stopping there is what would put it in the vehicle's way; a Monaco car braked
            # from 8.2 to 2.5 m/s for one 11 m off to the side at 3.3 m/s)
            return None
        else:
            # the car is in the stretch, and the vehicle's lane joins the path there going the
            # same way: if the car's rear is past the join by the time the vehicle gets to it,
            # the vehicle comes up behind the car, whose stopping would only put it in its way
            # (seed 40, Lauf, Helsinki, Portland: six brakes to a crawl inside junctions for cars
            # 9-18 m behind on a lane merging in)
            i_join, i_last = int(np.argmin(np.where(hit, arc, np.inf))), int(np.argmax(np.where(hit, arc, -np.inf)))
            s_join = float(s[i_join])
            if pos < a0 and float(s[i_last]) > s_join + 1.0 \
                    and s_here - (self.length - self.front) + v_ego * t_in > s_join + MERGE_BEHIND_M:
                return None
        return Lead(max(0.0, gap - LANE_CONFLICT_MARGIN_M), 0.0, "vehicle", "conflict", str(actors.ids[i]))

    def _waits_for_ego(self, vid: str) -> bool:
        """Does SUMO have vehicle `vid` wait for the ego (``SumoTraffic.waits_for_ego``)?"""
        tr = getattr(self.sim, "traffic", None)
        if tr is None:
            return False
        try:
            return bool(tr.waits_for_ego(vid))
        except Exception:
            return False

    def _at_path_junction(self, tr, lane: str, junctions: set) -> bool:
        """Does the edge of `lane` end or start at one of `junctions`?"""
        if not junctions:
            return False
        ends = self._network_ends(tr).get(lane.rsplit("_", 1)[0])
        return ends is not None and (ends[1] in junctions or ends[0] in junctions)

    def _network_ends(self, tr) -> dict:
        """edge -> (from, to junction) of the network (``SumoTraffic.edge_ends``: one call for
        the whole network, asked ahead: _expect; kept until SUMO moves to another network)."""
        if self._edge_ends is None:
            self._edge_ends = tr.edge_ends()
        return self._edge_ends

    def _sumo_leader(self, s_here, path, actors=None) -> Lead | None:
        """SUMO's leader of the ego, if it is on a lane of the path ahead. Its lane and speed
        come from the actors' snapshot where it is in it (a read of a vehicle the loop did
        not ask for before waits for SUMO's step in flight: 66 waits in 3,000 frames)."""
        tr = getattr(self.sim, "traffic", None)
        if tr is None:
            return None
        if not getattr(tr, "_ego_in_sim", False) or getattr(tr, "_ego_off_network", False):
            return None
        try:
            s = tr.sumo
            # only for an ego on a lane (libsumo's getLeader is not safe for a vehicle that
            # moveToXY left off the network)
            if not s.vehicle.getLaneID("ego"):
                return None
            res = s.vehicle.getLeader("ego", SENSE_RANGE_M)
            if not res or not res[0]:
                return None
            lid, dist = res
            if self._ego_min_gap is None:       # (the ego's type's: read once)
                self._ego_min_gap = float(s.vehicle.getMinGap("ego"))
            gap = float(dist) + self._ego_min_gap
            k = None
            if getattr(actors, "lane", None) is not None:
                try:
                    k = actors.index(lid)
                except KeyError:
                    pass
                if k is not None and not actors.lane[k]:
                    k = None
            lane = actors.lane[k] if k is not None else s.vehicle.getLaneID(lid)
            if lane not in path.lanes_between(s_here, s_here + gap + self.front + 15.0):
                return None
            speed = float(actors.speed[k]) if k is not None else float(s.vehicle.getSpeed(lid))
            return Lead(max(0.0, gap), max(0.0, speed), "vehicle", "sumo", lid)
        except Exception:
            return None

    def _follow_speed(self, lead: Lead, v: float) -> float:
        d0 = PERSON_GAP_M if lead.kind == "person" else STANDSTILL_GAP_M
        d_star = d0 + self.time_gap * v
        vl = lead.speed
        v_stop = stop_speed(lead.gap - d0, COMFORT_DECEL)
        if vl <= 0.5:                 # standing (or crossing): stop d0 behind it, and when
            if lead.gap - d0 < 15.0:  # near, do not speed up towards it
                return min(v_stop, max(v, 2.0))
            return v_stop
        # moving: close the gap to the time gap, never faster than what still allows braking
        # to the lead's speed d0 behind it at a comfortable deceleration
        v_follow = vl + 0.4 * (lead.gap - d_star)
        v_safe = math.sqrt(max(0.0, vl * vl + 2.0 * COMFORT_DECEL * (lead.gap - d0)))
        return max(0.0, min(v_follow, max(v_safe, v_stop)))

    # --- junctions -----------------------------------------------------------------------
    def _junctions(self, path, s_here, v, t) -> list:
        out = []
        self.next_control = None
        sumo = self.sim.traffic.sumo if getattr(self.sim, "traffic", None) is not None else None
        if sumo is None:
            return out
        horizon = max(60.0, v * v / (2 * COMFORT_DECEL) + 30.0)
        front = s_here + self.front
        seen = 0
        for stop in path.stops:
            if stop.s < front - 0.3:
                if stop.s < front - 5.0:        # passed: forget (a loop may bring it back)
                    self._stop_state.pop((stop.junction, stop.lane), None)
                continue
            if stop.s > front + horizon or seen >= 3:
                break
            seen += 1
            d = stop.s - front - STOP_LINE_MARGIN_M
            key = (stop.junction, stop.lane)
            try:
                state = stop.state(sumo)
            except Exception:
                state = stop.initial_state
            osm_stop = key in self._osm_stops
            kind = "light" if stop.tls else ("stop sign" if state in STOP_STATES or osm_stop else
                                             ("yield" if state in YIELD_STATES else "priority"))
            if self.next_control is None:
                self.next_control = {"kind": kind, "state": state, "distance_m": round(stop.s - front, 2),
                                     "junction": stop.junction}
            if state in RED_STATES:
                out.append((stop_speed(d, COMFORT_DECEL), "red light"))
                self._yellow.pop(key, None)
                continue
            if state in YELLOW_STATES:
                # decide once, when the light turns yellow: stop if the car can (at most
                # YELLOW_DECEL), else go through; the decision holds while it stays yellow
                decel = self._yellow.get(key)
                if decel is None:
                    need = v * v / (2.0 * max(d, 0.01))
                    decel = self._yellow[key] = (max(COMFORT_DECEL, need) if need <= YELLOW_DECEL
                                                 or d > 0 and v < 1.0 else 0.0)
                if decel > 0.0:
                    out.append((stop_speed(d, decel), "yellow light"))
                continue
            self._yellow.pop(key, None)
            if state in STOP_STATES or (osm_stop and not stop.tls and state not in "GM"):
                v_c = self._stop_sign(stop, key, d, v, t)
                if v_c is not None:
                    out.append((v_c, "stop sign"))
                    break
                continue
            if state in YIELD_STATES:
                v_c = self._yield(stop, key, d, v, t)
                if v_c is not None:
                    out.append((v_c, "yield"))
                    break
        return out

    def _stop_sign(self, stop, key, d, v, t):
        rec = self._stop_state.setdefault(key, {"since": None, "released": False, "t0": t})
        if rec["released"]:
            return None
        if v < 0.15 and d < 3.0:
            if rec["since"] is None:
                rec["since"] = t
                self.stats.stop_sign_stops += 1
                self.stats.events.append((round(t, 2), "stop sign", stop.junction))
        elif v > 0.5:
            rec["since"] = None
        if rec["since"] is not None and t - rec["since"] >= STOP_SIGN_HOLD_S - 1e-6:
            if self._junction_clear(stop, d, v, t - rec["since"]):
                rec["released"] = True
                self.stats.events.append((round(t, 2), "stop sign go", stop.junction))
                return None
        return stop_speed(d, COMFORT_DECEL)

    def _yield(self, stop, key, d, v, t):
        rec = self._stop_state.setdefault(key, {"since": None, "released": False, "t0": t})
        if rec["released"]:
            return None
        if d > max(20.0, v * v / (2 * COMFORT_DECEL) + 8.0):
            return None                                   # not yet: decide when closer
        if d < -0.5 and v > 1.0:
            rec["released"] = True                        # committed
            return None
        waited = 0.0 if rec["since"] is None else t - rec["since"]
        if self._junction_clear(stop, d, v, waited):
            if d < 3.0:
                rec["released"] = True                    # at the line and clear: go, and stay gone
            return None
        if v < 0.2 and rec["since"] is None:
            rec["since"] = t
        return stop_speed(d, COMFORT_DECEL)

    def _incoming_lanes(self) -> dict:
        if self._incoming is None:
            # one call (SUMO may be in a worker process: not one call per lane of the network)
            self._incoming = self.sim.traffic.incoming_lanes()
        return self._incoming

    def _junction_clear(self, stop, d, v, waited: float) -> bool:
        """No vehicle with right of way arrives before the ego has crossed, and nothing is on
        a conflicting lane inside the junction."""
        s = self.sim.traffic.sumo
        # time for the ego to get clear of the conflict area (about the middle of the junction)
        dist = max(d, 0.0) + 0.6 * stop.internal_length + self.length
        if v < 1.0:
            t_need = math.sqrt(2.0 * dist / 1.8) + 1.0
        else:
            t_need = dist / v + 1.0
        t_need = min(t_need, 7.0)
        if waited > YIELD_GIVE_UP_S:
            t_need = 2.0
        key = (stop.lane, stop.to_lane)
        foes = self._foes.get(key)
        if foes is None:
            try:
                foes = _normal_lanes(s.lane.getFoes(stop.lane, stop.to_lane))
            except Exception:
                foes = []
            self._foes[key] = foes
        inc = self._incoming_lanes()
        for f in foes:
            lanes = [(f, 0.0)]
            Lf = s.lane.getLength(f)
            lanes += [(p, Lf) for p in inc.get(f, [])]
            for lane, extra in lanes:
                L = s.lane.getLength(lane)
                for vid in s.lane.getLastStepVehicleIDs(lane):
                    if vid == "ego":
                        continue
                    try:        # (a vehicle listed a moment ago may have left SUMO since)
                        sp = s.vehicle.getSpeed(vid)
                        togo = L - s.vehicle.getLanePosition(vid) + extra
                    except Exception:
                        continue
                    if sp > 0.5 and togo / sp < t_need:
                        return False
        vias = self._internal_foes.get(stop.via)
        if vias is None:
            try:
                vias = self._vehicle_lanes(s.lane.getInternalFoes(stop.via))
            except Exception:
                vias = []
            self._internal_foes[stop.via] = vias
        for lane in vias:
            for vid in s.lane.getLastStepVehicleIDs(lane):
                if vid != "ego":
                    return False
        return True

    @staticmethod
    def _is_ped_lane(lane: str) -> bool:
        core = lane[1:].rsplit("_", 1)[0]
        tail = core.rsplit("_", 1)[-1]
        return tail.startswith("c") or tail.startswith("w")

    @classmethod
    def _vehicle_lanes(cls, lanes) -> list:
        """The junction lanes among ``lanes`` (a link's internal foes) that vehicles use."""
        return [f for f in lanes if not cls._is_ped_lane(f)]

    def _match_osm_stop_signs(self, path) -> dict:
        """Stop lines of the path with an OpenStreetMap stop sign next to them (from the
        world's scenery): the sign is within OSM_SIGN_RADIUS_M of this approach's stop line and
        nearer to it than to any other approach of the junction."""
        world = getattr(self.sim, "world", None)
        tr = getattr(self.sim, "traffic", None)
        if world is None or tr is None or not path.stops:
            return {}
        signs = []
        try:
            for ij in world.chunks:
                signs += [(float(i["x"]), float(i["y"])) for i in world.scenery(ij) if i.get("kind") == "stop_sign"]
        except Exception:
            return {}
        if not signs:
            return {}
        signs = np.array(signs)
        s = tr.sumo
        out = {}
        for stop in path.stops:
            if stop.tls:
                continue
            p = path.point_at(stop.s)
            d = np.hypot(signs[:, 0] - p[0], signs[:, 1] - p[1])
            j = int(np.argmin(d))
            if d[j] > OSM_SIGN_RADIUS_M:
                continue
            mine = d[j]
            try:
                others = [e for e in s.junction.getIncomingEdges(stop.junction)
                          if e != stop.lane.rsplit("_", 1)[0] and not e.startswith(":")]
            except Exception:
                others = []
            nearer = False
            for e in others:
                for lane in _drivable_lanes(s, e):
                    sh = s.lane.getShape(lane)
                    if sh and math.hypot(sh[-1][0] - signs[j, 0], sh[-1][1] - signs[j, 1]) < mine - 0.5:
                        nearer = True
                        break
                if nearer:
                    break
            if not nearer:
                out[(stop.junction, stop.lane)] = (float(signs[j, 0]), float(signs[j, 1]))
        return out

    # --- pedestrians on crossings ---------------------------------------------------------
    def _crossings(self, path, s_here, v, actors=None) -> list:
        out = []
        persons = None
        if actors is not None and len(actors):
            pm = actors.kind == "person"
            if pm.any():
                persons = np.column_stack([actors.x[pm], actors.y[pm]])
        tr = getattr(self.sim, "traffic", None)
        if tr is None:
            return out
        s = tr.sumo
        front = s_here + self.front
        horizon = max(40.0, v * v / (2 * COMFORT_DECEL) + 20.0)
        for c in path.crossings:
            near_edge = c.s - c.width / 2.0
            if c.s + c.width / 2.0 < front:
                continue
            if near_edge > front + horizon:
                break
            if persons is not None and c.shape is not None:
                # people waiting at either end: approach slowly, ready to stop
                ends = np.array([c.shape[0], c.shape[-1]])
                d = np.hypot(persons[:, None, 0] - ends[None, :, 0], persons[:, None, 1] - ends[None, :, 1])
                if (d < 3.5).any():
                    d_c = near_edge - front - CROSSING_MARGIN_M
                    if d_c > -0.5:
                        out.append((math.sqrt(CROSSING_APPROACH_MPS ** 2 + 2 * COMFORT_DECEL * max(d_c, 0.0)),
                                    "pedestrian crossing"))
            try:
                on_it = s.edge.getLastStepPersonIDs(c.edge)
            except Exception:
                continue
            if not on_it:
                continue
            p_here = path.point_at(c.s)
            h = path.heading_at(c.s)
            ch, sh = math.cos(h), math.sin(h)
            block = False
            for pid in on_it:
                try:            # (a person listed a moment ago may have arrived since)
                    px, py = s.person.getPosition(pid)
                    sp = s.person.getSpeed(pid)
                    ang = math.radians(90.0 - s.person.getAngle(pid))
                except Exception:
                    continue
                lat = -(px - p_here[0]) * sh + (py - p_here[1]) * ch      # across our path
                vlat = sp * (-math.cos(ang) * sh + math.sin(ang) * ch)
                # on our side of the path or walking into it within 3 s
                if abs(lat) < self.width / 2.0 + 2.5 or (abs(lat) < 8.0 and lat * vlat < 0
                                                          and abs(lat) - 3.0 * abs(vlat) < self.width / 2.0 + 1.0):
                    block = True
                    break
            if block:
                d = near_edge - front - CROSSING_MARGIN_M
                if d < -0.5:
                    continue          # already on it: the corridor check handles a person ahead
                out.append((stop_speed(d, COMFORT_DECEL), "pedestrian crossing"))
                break
        return out

    # --- bookkeeping ---------------------------------------------------------------------
    def _update_stats(self, v, t):
        st = self.stats
        st.steps += 1
        if v > 2.0:
            self._moving = True
        elif v < 0.2 and self._moving:
            self._moving = False
            st.stops += 1
            r = self.reason
            if r == "red light":
                st.red_light_stops += 1
            elif r == "pedestrian crossing" or r == "lead person":
                st.pedestrian_yields += 1
            st.events.append((round(t, 2), "stop", r))
        lead = self.lead
        if lead is None or v < 1.0:
            return
        closing = v - lead.speed
        if lead.track_gap is None:
            gap = lead.gap
            ttc = gap / closing if closing > 0.3 else float("inf")
        else:       # a vehicle crossing the path: its track's distance (no TTC: it moves across)
            gap, ttc = lead.track_gap, float("inf")
        st.min_ttc_s = min(st.min_ttc_s, ttc)
        st.min_gap_moving_m = min(st.min_gap_moving_m, gap)
        if lead.kind == "vehicle" and lead.speed > 2.0 and abs(closing) < 0.5 and lead.gap < 60:
            st.time_gaps.append(lead.gap / v)
        if ttc < NEAR_MISS_TTC_S or gap < NEAR_MISS_GAP_M:
            if t >= self._near_miss_until:
                st.near_misses += 1
                log.info("near miss at t=%.1f s: %s %s, gap %.1f m, ttc %.2f s, %.1f m/s", t, lead.kind, lead.actor,
                         gap, ttc, v)
                st.events.append((round(t, 2), "near miss", f"{lead.kind} {lead.actor} gap {gap:.1f} m "
                                                            f"ttc {ttc:.2f} s v {v:.1f}"))
            self._near_miss_until = t + 3.0

    # --- what a user's driver sees -----------------------------------------------------------
    def observation(self) -> dict:
        """The autopilot's view after its last :meth:`control` (for user drivers and the env)."""
        st = self._st
        path = self.sim.path
        if st is None:
            return {}
        k = self._k
        he = math.atan2(math.sin(st.yaw - path.heading[k]), math.cos(st.yaw - path.heading[k]))
        nc = self.next_control or {}
        kind, state = nc.get("kind"), nc.get("state", "")
        if kind == "light":
            code = 3 if state in RED_STATES else (2 if state in YELLOW_STATES else 1)
        else:
            code = {"stop sign": 4, "yield": 5}.get(kind, 0)
        return {
            "t": getattr(self.sim, "t", 0.0), "state": st, "speed": st.speed, "set_speed": float(self.sim.cfg.speed_mps),
            "target_speed": self.target_speed, "reason": self.reason,
            "s": self._s_here, "remaining_m": (self._s_goal if self._s_goal is not None else path.length) - self._s_here,
            "lateral_offset": self._lat, "heading_error": he,
            "curvature_ahead": path.max_curvature(self._s_here, self._s_here + 30.0),
            "lidar": None if self.scan is None else self.scan.distance.copy(),
            "lidar_body": None if self.scan is None else self.scan.body.copy(),
            "lead_gap": None if self.lead is None else self.lead.gap,
            "lead_speed": None if self.lead is None else self.lead.speed,
            "lead_kind": None if self.lead is None else self.lead.kind,
            "next_control": nc, "light_code": code,   # 0 none/priority, 1 green, 2 yellow, 3 red, 4 stop, 5 yield
            "autopilot": self.last, "autopilot_reverse": self.reverse,
        }


class CallbackDriver:
    """Drive with your own function: ``fn(obs) -> (throttle, brake, steer)``, or with a fourth,
    ``reverse`` (True: the reverse gear).

    ``obs`` is :meth:`Autopilot.observation` (the autopilot runs alongside as the perception
    and to suggest a command, ``obs["autopilot"]``, but only ``fn``'s command is applied).
    Install it on a set-up simulation: ``sim.driver = CallbackDriver(sim, fn)``."""

    def __init__(self, sim, fn, **autopilot_kw):
        self.sim = sim
        self.fn = fn
        self.autopilot = Autopilot(sim, **autopilot_kw)
        self.speed = self.autopilot.speed
        self.target_speed = float("nan")
        self.last_obs: dict = {}
        self.reverse = False

    def control(self, st, s_here, actors, dt):
        self.autopilot.control(st, s_here, actors, dt)
        self.last_obs = obs = self.autopilot.observation()
        out = list(self.fn(obs))
        throttle, brake, steer = (float(x) for x in out[:3])
        self.reverse = bool(out[3]) if len(out) > 3 else False     # (an optional fourth: reverse gear)
        return (max(0.0, min(1.0, throttle)), max(0.0, min(1.0, brake)), max(-1.0, min(1.0, steer)))
