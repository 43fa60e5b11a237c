"""The autopilot: the default driver behind the controller interface.

``control(state, s_here, actors, dt) -> (throttle, brake, steer)``. It follows the lane path
with pure pursuit, holds the set speed with a PI controller on wheel torque, slows for curves
ahead, keeps a time gap behind the vehicle ahead on its path, stops for pedestrians on its
path, and stops at red (and at yellow when it can stop in time) using SUMO's state of the ego's
next traffic-light link.
"""
from __future__ import annotations

import math

import numpy as np

from .driving import PurePursuit, SpeedController, curve_speed

TIME_GAP_S = 1.8          # kept behind a vehicle ahead (>= 1.5 s)
STANDSTILL_GAP_M = 4.0    # bumper to bumper when stopped
COMFORT_DECEL = 2.5       # m/s2 used to plan stops
STOP_LINE_MARGIN_M = 2.0


class Autopilot:
    def __init__(self, sim):
        from .vehicle import LENGTH, WHEELBASE, min_turn_radius

        self.sim = sim
        self.length = LENGTH
        self.pp = PurePursuit(WHEELBASE, 1.0 / min_turn_radius())
        self.speed = SpeedController()
        self.target_speed = 0.0
        self.reason = ""
        self.lead_gap = None

    def control(self, st, s_here: float, actors, dt: float):
        sim = self.sim
        path = sim.path
        v = st.speed
        steer, _ = self.pp.steer(path, st.x, st.y, st.yaw, v, s_here)
        v_set = sim.cfg.speed_mps
        reason = "cruise"
        # curves ahead: the braking distance plus a margin
        horizon = max(20.0, v * v / (2 * COMFORT_DECEL) + 10.0)
        k = path.max_curvature(s_here, s_here + horizon)
        v_curve = curve_speed(k)
        if v_curve < v_set:
            v_set, reason = v_curve, "curve"
        # the end of the path (goal)
        remaining = path.length - s_here
        if sim.goal_xy is not None:
            v_goal = math.sqrt(max(0.0, 2 * COMFORT_DECEL * max(0.0, remaining - 3.0)))
            if v_goal < v_set:
                v_set, reason = v_goal, "goal"
        # lead vehicle / pedestrian on the path ahead
        gap, lead_v, lead_kind = self._lead(actors, st, s_here, path)
        self.lead_gap = gap
        if gap is not None:
            desired = STANDSTILL_GAP_M + TIME_GAP_S * v
            # approach speed that would stop at STANDSTILL_GAP_M with comfortable deceleration
            v_gap = math.sqrt(max(0.0, 2 * COMFORT_DECEL * max(0.0, gap - STANDSTILL_GAP_M)))
            v_follow = min(v_gap, max(0.0, lead_v) + 0.5 * (gap - desired))
            if lead_kind == "person":
                v_follow = min(v_follow, v_gap)
            if v_follow < v_set:
                v_set, reason = max(0.0, v_follow), "lead " + lead_kind
        # traffic light of the next link
        tls = sim.traffic.ego_next_tls() if sim.traffic is not None else None
        if tls is not None:
            _, dist, state = tls
            stop_at = dist - STOP_LINE_MARGIN_M
            can_stop = v * v / (2 * 4.0) <= max(stop_at, 0.0) + 1.0
            if state in "rRu" or (state in "yY" and can_stop):
                v_stop = math.sqrt(max(0.0, 2 * COMFORT_DECEL * max(0.0, stop_at)))
                if v_stop < v_set:
                    v_set, reason = v_stop, "red light" if state in "rRu" else "yellow light"
        self.target_speed = v_set
        self.reason = reason
        throttle, brake = self.speed.control(v_set, v, dt)
        if v_set < 0.3 and v < 0.3:
            throttle, brake = 0.0, 1.0
        return throttle, brake, steer

    def _lead(self, actors, st, s_here, path):
        """Nearest actor whose centre lies on the path ahead (within half a lane plus its own
        half width): gap bumper to bumper, its speed along the path, its kind."""
        if actors is None or len(actors) == 0:
            return None, 0.0, ""
        dx = actors.x - st.x
        dy = actors.y - st.y
        c, s = math.cos(st.yaw), math.sin(st.yaw)
        ahead = dx * c + dy * s
        cand = np.nonzero((ahead > 0) & (ahead < 80.0))[0]
        best = (None, 0.0, "")
        for i in cand:
            k, s_a, off = path.project(float(actors.x[i]), float(actors.y[i]), sim_hint(path, s_here), window=120)
            if s_a <= s_here:
                continue
            half = 1.6 + 0.5 * float(actors.width[i])
            if abs(off) > half:
                continue
            gap = (s_a - s_here) - 0.5 * self.length - 0.5 * float(actors.length[i])
            if best[0] is None or gap < best[0]:
                rel = math.cos(float(actors.yaw[i]) - path.heading[k])
                kind = "person" if actors.kind[i] == "person" else "vehicle"
                best = (max(0.0, gap), float(actors.speed[i]) * rel, kind)
        return best


def sim_hint(path, s_here):
    return int(np.searchsorted(path.s, s_here))
