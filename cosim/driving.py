"""The ego's driving: a lane-level path along a SUMO route, and controllers that follow it.

* :class:`LanePath` turns a route (SUMO edges) into one centreline polyline: on each edge the
  lane that connects to the next edge (the rightmost such drivable lane), the junction's
  internal lanes between them (SUMO's own ``via`` lanes, so the path is exactly the lane
  geometry SUMO's vehicles use), and a smooth lateral blend where the route needs a lane
  change. Everything comes from libsumo (``lane.getLinks``, ``lane.getShape``): no second
  parse of the network.
* :class:`PurePursuit` steers towards a look-ahead point on the path.
* :class:`SpeedController` is a PI controller on wheel torque (throttle / brake), with a
  curve speed limit from the path's curvature ahead, so the physics car is driven through its
  wheels, never by setting its pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

CAR = "passenger"


def _lane_allows(sim, lane: str, vclass: str = CAR) -> bool:
    allowed = sim.lane.getAllowed(lane)
    if allowed:
        return vclass in allowed
    return vclass not in sim.lane.getDisallowed(lane)


def _drivable_lanes(sim, edge: str) -> list[str]:
    n = sim.edge.getLaneNumber(edge)
    return [f"{edge}_{k}" for k in range(n) if _lane_allows(sim, f"{edge}_{k}")]


def _resample(P: np.ndarray, step: float) -> np.ndarray:
    if len(P) < 2:
        return P
    d = np.hypot(*np.diff(P, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(d)])
    if s[-1] <= 0:
        return P[:1]
    n = max(2, int(math.ceil(s[-1] / step)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.column_stack([np.interp(t, s, P[:, 0]), np.interp(t, s, P[:, 1])])


@dataclass
class PathPoint:
    s: float
    x: float
    y: float
    lane: str
    edge: str


class LanePath:
    """A drivable centreline along a SUMO route. ``xy`` (n, 2), ``s`` arc length, per point the
    SUMO lane and edge it belongs to."""

    STEP = 1.0

    def __init__(self, sim, edges: list[str], start_lane: str | None = None, start_pos: float = 0.0):
        self.edges = list(edges)
        pts, lanes = [], []
        # which lane to be on at each edge: must connect to the next edge
        plan = []
        for i, e in enumerate(self.edges):
            cands = _drivable_lanes(sim, e)
            if not cands:
                raise ValueError(f"edge {e} has no lane for cars")
            if i + 1 < len(self.edges):
                nxt = self.edges[i + 1]
                ok = []
                for ln in cands:
                    for link in sim.lane.getLinks(ln):
                        to_lane, via = link[0], link[4]
                        if to_lane.rsplit("_", 1)[0] == nxt:
                            ok.append((ln, to_lane, via))
                            break
                if not ok:
                    raise ValueError(f"no lane of {e} connects to {nxt}")
                plan.append(ok[0])          # the rightmost lane with the link
            else:
                plan.append((cands[0], None, None))
        entry = start_lane if start_lane and start_lane.rsplit("_", 1)[0] == self.edges[0] else plan[0][0]
        for i, e in enumerate(self.edges):
            want = plan[i][0]
            shape_in = np.array(sim.lane.getShape(entry))
            shape_want = np.array(sim.lane.getShape(want))
            if entry != want and len(shape_in) >= 2 and len(shape_want) >= 2:
                seg = self._blend(shape_in, shape_want)
            else:
                seg = shape_want
            if i == 0 and start_pos > 0:
                seg = self._cut_from(seg, start_pos)
            seg = _resample(seg, self.STEP)
            pts.append(seg)
            lanes.extend([(want, e)] * len(seg))
            if plan[i][1] is not None:
                # internal (junction) lanes SUMO uses for this link
                via = plan[i][2]
                guard = 0
                while via and via.startswith(":") and guard < 5:
                    vs = _resample(np.array(sim.lane.getShape(via)), self.STEP)
                    pts.append(vs)
                    lanes.extend([(via, via.rsplit("_", 1)[0])] * len(vs))
                    nxt = None
                    for link in sim.lane.getLinks(via):
                        nxt = link[0]
                        break
                    via = nxt if nxt and nxt.startswith(":") else None
                    guard += 1
                entry = plan[i][1]
        P = np.vstack(pts)
        keep = np.ones(len(P), dtype=bool)
        keep[1:] = np.hypot(*np.diff(P, axis=0).T) > 1e-3
        self.xy = P[keep]
        self.lane_of = [lanes[k] for k in np.nonzero(keep)[0]]
        d = np.hypot(*np.diff(self.xy, axis=0).T)
        self.s = np.concatenate([[0.0], np.cumsum(d)])
        self.length = float(self.s[-1])
        h = np.arctan2(*np.diff(self.xy, axis=0).T[::-1])
        self.heading = np.concatenate([h, h[-1:]])
        dh = np.angle(np.exp(1j * np.diff(self.heading)))
        ds = np.maximum(d, 1e-6)
        k = dh / ds
        self.curvature = np.concatenate([k, k[-1:]])

    @staticmethod
    def _cut_from(P, pos):
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
        if pos >= d[-1]:
            return P[-2:]
        k = int(np.searchsorted(d, pos))
        t = (pos - d[k - 1]) / max(d[k] - d[k - 1], 1e-9) if k > 0 else 0.0
        first = P[k - 1] + t * (P[k] - P[k - 1]) if k > 0 else P[0]
        return np.vstack([first, P[k:]])

    @staticmethod
    def _blend(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Move from lane a to lane b along one edge: a smooth (cosine) lateral blend over the
        middle of the edge, at most 60 m long."""
        n = 100
        fa = _resample(a, max(1e-3, np.sum(np.hypot(*np.diff(a, axis=0).T)) / (n - 1)))[:n]
        fb = _resample(b, max(1e-3, np.sum(np.hypot(*np.diff(b, axis=0).T)) / (n - 1)))[:n]
        m = min(len(fa), len(fb))
        fa, fb = fa[:m], fb[:m]
        L = float(np.sum(np.hypot(*np.diff(fb, axis=0).T)))
        t = np.linspace(0, 1, m)
        span = min(0.8, 60.0 / max(L, 1.0))
        t0 = 0.5 - span / 2
        w = np.clip((t - t0) / span, 0, 1)
        w = 0.5 - 0.5 * np.cos(np.pi * w)
        return fa * (1 - w)[:, None] + fb * w[:, None]

    def project(self, x: float, y: float, hint: int = 0, window: int = 400) -> tuple[int, float, float]:
        """Closest path index near `hint`, arc length there, signed lateral offset (left +)."""
        lo = max(0, hint - 20)
        hi = min(len(self.xy), hint + window)
        seg = self.xy[lo:hi]
        d2 = (seg[:, 0] - x) ** 2 + (seg[:, 1] - y) ** 2
        k = lo + int(np.argmin(d2))
        # refine on the segment k..k+1 (or k-1..k)
        best = (k, self.s[k], 0.0)
        bestd = float("inf")
        for a in (k - 1, k):
            if a < 0 or a + 1 >= len(self.xy):
                continue
            p, q = self.xy[a], self.xy[a + 1]
            v = q - p
            L2 = float(v @ v)
            if L2 <= 0:
                continue
            t = max(0.0, min(1.0, float((np.array([x, y]) - p) @ v) / L2))
            c = p + t * v
            dd = math.hypot(x - c[0], y - c[1])
            if dd < bestd:
                side = v[0] * (y - p[1]) - v[1] * (x - p[0])
                bestd = dd
                best = (a, self.s[a] + t * math.sqrt(L2), math.copysign(dd, side))
        return best

    def point_at(self, s: float) -> np.ndarray:
        s = min(max(s, 0.0), self.length)
        return np.array([np.interp(s, self.s, self.xy[:, 0]), np.interp(s, self.s, self.xy[:, 1])])

    def max_curvature(self, s0: float, s1: float) -> float:
        m = (self.s >= s0) & (self.s <= s1)
        if not m.any():
            return 0.0
        # smooth over ~5 m so single-point kinks do not dominate
        k = np.abs(self.curvature[m])
        if len(k) >= 5:
            k = np.convolve(k, np.ones(5) / 5, mode="same")
        return float(k.max())


class PurePursuit:
    """Steering towards a look-ahead point: curvature = 2 sin(alpha) / Ld."""

    def __init__(self, wheelbase: float, max_curvature: float, k_ld: float = 0.6, ld_min: float = 4.0,
                 ld_max: float = 20.0):
        self.wheelbase = wheelbase
        self.kmax = max_curvature
        self.k_ld, self.ld_min, self.ld_max = k_ld, ld_min, ld_max

    def steer(self, path: LanePath, x, y, yaw, speed, s_here) -> tuple[float, float]:
        ld = min(self.ld_max, max(self.ld_min, self.k_ld * abs(speed)))
        tx, ty = path.point_at(s_here + ld)
        alpha = math.atan2(ty - y, tx - x) - yaw
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        kappa = 2.0 * math.sin(alpha) / ld
        return max(-1.0, min(1.0, kappa / self.kmax)), kappa


class SpeedController:
    """PI speed control to throttle/brake, with a feed-forward for slopes via the integral."""

    def __init__(self, kp: float = 0.35, ki: float = 0.08, kb: float = 0.25, i_max: float = 0.6):
        self.kp, self.ki, self.kb, self.i_max = kp, ki, kb, i_max
        self.i = 0.0

    def reset(self):
        self.i = 0.0

    def control(self, v_target: float, v: float, dt: float) -> tuple[float, float]:
        e = v_target - v
        if v_target <= 0.05 and v < 0.5:
            self.i = 0.0
            return 0.0, 1.0
        self.i = max(-self.i_max, min(self.i_max, self.i + self.ki * e * dt))
        u = self.kp * e + self.i
        if u >= 0:
            return min(1.0, u), 0.0
        # coast for small negative errors, brake harder when far above target
        brake = min(1.0, max(0.0, -u - 0.05) * self.kb / 0.25)
        return 0.0, brake


def curve_speed(kappa: float, a_lat: float = 2.5) -> float:
    """Highest speed for a curvature at a comfortable lateral acceleration."""
    return math.sqrt(a_lat / max(abs(kappa), 1e-6))
