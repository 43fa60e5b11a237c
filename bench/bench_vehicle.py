"""Ego car benchmark: cost per substep, driving figures, and the physics-rate sweep.

Run: ``.venv/bin/python bench/bench_vehicle.py`` (about a minute). Prints only; no asserts.
Wall times are the best of several repeats (the machine is shared), in microseconds.

The grounds are the kinds the world is built of: a flat asphalt box (reference), static
concave triangle meshes written as OBJ (two 3.5 m lane strips resampled every 2.5 m, a
fan-triangulated junction, a road/junction/road with 1 cm steps, a 7.5 cm speed hump, a
building), and GEOM_HEIGHTFIELD terrain at 5 m spacing (gentle hills, a 10 % grade).
"""
from __future__ import annotations

import math
import tempfile
import time
from pathlib import Path

import numpy as np
import pybullet as p

from cosim import vehicle as V

KMH100 = 100.0 / 3.6
TMP = Path(tempfile.mkdtemp(prefix="bench_vehicle_"))


# --- grounds ---------------------------------------------------------------------------------
def client(hz: int = V.RECOMMENDED_PHYSICS_HZ, iterations: int = V.RECOMMENDED_SOLVER_ITERATIONS) -> int:
    cid = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    V.configure_physics(cid, hz, iterations)
    return cid


def box_ground(cid: int) -> None:
    g = p.createMultiBody(0, p.createCollisionShape(p.GEOM_BOX, halfExtents=[3000, 3000, 1], physicsClientId=cid),
                          basePosition=[0, 0, -1], physicsClientId=cid)
    V.set_asphalt_friction(cid, g)


def obj_body(cid: int, name: str, verts, faces) -> int:
    path = TMP / f"{name}.obj"
    if not path.exists():
        with open(path, "w") as f:
            f.writelines("v %.6f %.6f %.6f\n" % tuple(v) for v in verts)
            f.writelines("f %d %d %d\n" % (a + 1, b + 1, c + 1) for a, b, c in faces)
    shape = p.createCollisionShape(p.GEOM_MESH, fileName=str(path), flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                   physicsClientId=cid)
    return p.createMultiBody(0, shape, -1, [0, 0, 0], physicsClientId=cid)


def strip(x0, x1, y0, y1, step=2.5, z=lambda x: 0.0):
    xs = np.arange(x0, x1 + 1e-9, step)
    verts = [v for x in xs for v in ((x, y0, z(x)), (x, y1, z(x)))]
    faces = [f for i in range(len(xs) - 1) for f in ((2 * i, 2 * i + 2, 2 * i + 1), (2 * i + 1, 2 * i + 2, 2 * i + 3))]
    return verts, faces


def merge(*parts):
    verts, faces = [], []
    for v, f in parts:
        off = len(verts)
        verts += list(v)
        faces += [(a + off, b + off, c + off) for a, b, c in f]
    return verts, faces


def lanes(cid: int) -> None:
    """Four 3.5 m lane strips (a 14 m carriageway along +x), each resampled every 2.5 m."""
    obj_body(cid, "lanes", *merge(*(strip(-50, 2500, y, y + 3.5) for y in (-7.0, -3.5, 0.0, 3.5))))


def junction_fan(cid: int) -> None:
    sectors, radius, cy = 24, 45.0, 20.0
    verts = [(0.0, cy, 0.0)] + [(radius * math.cos(a), cy + radius * math.sin(a), 0.0)
                                for a in np.linspace(0, 2 * math.pi, sectors, endpoint=False)]
    obj_body(cid, "fan", verts, [(0, 1 + k, 1 + (k + 1) % sectors) for k in range(sectors)])


def seams(cid: int) -> None:
    obj_body(cid, "road_in", *merge(strip(-150, 0, -3.5, 0.0), strip(-150, 0, 0.0, 3.5)))
    obj_body(cid, "junction", *strip(0.0, 20.0, -8.0, 8.0, 20.0 / 7, z=lambda x: 0.01))
    obj_body(cid, "road_out", *merge(strip(20, 150, -3.5, 0.0), strip(20, 150, 0.0, 3.5)))


def hump(cid: int) -> None:
    """A 7.5 cm high, 3.7 m long round-top speed hump at x = 0..3.7, resampled every 0.25 m."""
    def z(x):
        return 0.075 * math.sin(math.pi * x / 3.7) ** 2 if 0.0 < x < 3.7 else 0.0
    obj_body(cid, "hump", *strip(-100.0, 100.0, -4.0, 4.0, 0.25, z))


def heightfield(cid: int, fn, x0, x1, y0, y1, spacing=5.0) -> None:
    xs, ys = np.arange(x0, x1 + 1e-9, spacing), np.arange(y0, y1 + 1e-9, spacing)
    z = fn(*np.meshgrid(xs, ys))
    ny, nx = z.shape
    shape = p.createCollisionShape(p.GEOM_HEIGHTFIELD, meshScale=[spacing, spacing, 1.0], heightfieldData=z.ravel().tolist(),
                                   numHeightfieldRows=nx, numHeightfieldColumns=ny, physicsClientId=cid)
    p.createMultiBody(0, shape, -1, [xs[0] + (nx - 1) * spacing / 2, ys[0] + (ny - 1) * spacing / 2,
                                     (z.min() + z.max()) / 2], physicsClientId=cid)


def hills(x, y):
    return 1.0 * np.sin(2 * np.pi * x / 150.0) + 0.5 * np.sin(2 * np.pi * (x + y) / 90.0)


def building(cid: int, x0=10.0, x1=20.0, y0=-8.0, y1=8.0, h=6.0) -> None:
    corners = [(x, y, z) for z in (0.0, h) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    quads = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    obj_body(cid, "building", corners, [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])


def ground_z(cid: int, x: float, y: float) -> float:
    hit = p.rayTestBatch([(x, y, 500.0)], [(x, y, -500.0)], collisionFilterMask=-1 ^ V.CHASSIS_COLLISION_GROUP,
                         physicsClientId=cid)[0]
    return hit[3][2]


# --- helpers ---------------------------------------------------------------------------------
def best_of(fn, n: int, repeats: int = 7) -> float:
    """Best wall time per call, microseconds."""
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        times.append((time.perf_counter() - t0) / n)
    return min(times) * 1e6


class Speed:
    """PI speed controller (+ optional lane keeping on y = lane_y), one call per substep."""

    def __init__(self, car: V.EgoVehicle, target: float, lane_y: float | None = None):
        self.car, self.target, self.lane_y, self.integral = car, target, lane_y, 0.0

    def __call__(self, steer: float = 0.0) -> V.VehicleState:
        s = self.car.state()
        err = self.target - s.speed
        self.integral = min(max(self.integral + err * self.car.time_step, -5.0), 5.0)
        u = 0.4 * err + 0.2 * self.integral
        if self.lane_y is not None:  # gentle lane keeping (gains for up to 30 m/s)
            steer += -0.01 * (s.y - self.lane_y) - 0.15 * s.yaw
        self.car.apply_control(max(u, 0.0), max(-u, 0.0), steer)
        self.car.step(1)
        return s


# --- costs -----------------------------------------------------------------------------------
def step_costs() -> None:
    hz = V.RECOMMENDED_PHYSICS_HZ
    print(f"cost per substep at {hz} Hz ({round(0.1 * hz)} substeps per 0.1 s SUMO step), car at 10 m/s in a turn")
    grounds = (("flat box", box_ground, 0.0), ("lane-strip mesh", lanes, -1.75),
               ("heightfield hills", lambda c: heightfield(c, hills, -100, 1100, -60, 60), 10.0))
    for label, build, y0 in grounds:
        cid = client()
        build(cid)
        car = V.EgoVehicle(cid, position=(0.0, y0, ground_z(cid, 0.0, y0)))
        car.set_pose_velocity((0.0, y0, ground_z(cid, 0.0, y0)), 0.0, speed=10.0, clearance=0.0)
        car.apply_control(0.1, 0.0, 0.05)
        car.step(hz)

        def both():
            car.substep()
            p.stepSimulation(physicsClientId=cid)

        total = best_of(both, 200)
        physics = best_of(lambda: p.stepSimulation(physicsClientId=cid), 200)
        per_sumo = best_of(lambda: car.step(round(0.1 * hz)), 40)
        state = best_of(car.state, 500)
        visuals = best_of(car.sync_visuals, 500)
        empty = client()
        build(empty)
        bare = best_of(lambda: p.stepSimulation(physicsClientId=empty), 200)
        p.disconnect(empty)
        print(f"  {label:18s} vehicle model (substep) {total - physics:6.1f} us; stepSimulation {physics:6.1f} us "
              f"(world without the car {bare:5.1f} us); step({round(0.1 * hz)}) {per_sumo:7.1f} us per SUMO step; "
              f"state() {state:4.1f} us; sync_visuals() {visuals:4.1f} us")
        p.disconnect(cid)


# --- figures ---------------------------------------------------------------------------------
def drive_figures() -> None:
    hz = V.RECOMMENDED_PHYSICS_HZ
    dt = 1.0 / hz
    cid = client()
    box_ground(cid)
    car = V.EgoVehicle(cid)
    car.apply_control(0.0, 1.0, 0.0)
    car.step(hz)
    loads = car.wheel_loads()
    print(f"at rest: z {car.state().z * 1000:+.2f} mm, wheel loads FL/FR/RL/RR {'/'.join(f'{f:.0f}' for f in loads)} N "
          f"({100 * (loads[0] + loads[1]) / sum(loads):.1f} % front)")
    t, marks, s = 0.0, {}, car.state()
    car.apply_control(1.0, 0.0, 0.0)
    squat = 0.0
    while t < 60.0:
        car.step(1)
        t += dt
        s = car.state()
        squat = min(squat, s.pitch)
        for v in (KMH100, 30.0, 40.0):
            if v not in marks and s.speed >= v:
                marks[v] = t
    print("performance (flat dry asphalt):")
    print(f"  0-100 km/h {marks.get(KMH100, float('nan')):.2f} s; 0-30 m/s {marks.get(30.0, float('nan')):.2f} s; "
          f"0-40 m/s {marks.get(40.0, float('nan')):.2f} s; speed after 60 s {s.speed:.2f} m/s "
          f"(governed top speed {V.TOP_SPEED:.0f} m/s); squat {math.degrees(-squat):.2f} deg")
    for v0 in (20.0, KMH100):
        car.reset((0.0, 0.0, 0.0), 0.0)
        car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=v0, clearance=0.0)
        car.apply_control(0.0, 0.0, 0.0)
        car.step(hz // 5)
        s0 = car.state()
        s, t, dive = s0, 0.0, 0.0
        car.apply_control(0.0, 1.0, 0.0)
        while s.speed > 0.05 and t < 20.0:
            car.step(1)
            t += dt
            s = car.state()
            dive = max(dive, s.pitch)
        d = s.x - s0.x
        car.step(2 * hz)
        back = car.state().x - s.x
        print(f"  full braking from {s0.speed:5.2f} m/s: {d:5.2f} m in {t:.2f} s (mean {s0.speed ** 2 / (2 * d) / 9.81:.2f} g), "
              f"dive {math.degrees(dive):.2f} deg, rock-back after the stop {100 * back:+.1f} cm")
    car.reset((0.0, 0.0, 0.0), 0.0)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=30.0, clearance=0.0)
    car.apply_control(0.0, 0.0, 0.0)
    car.step(10 * hz)
    print(f"  coasting 10 s from 30 m/s: {car.state().speed:.2f} m/s (drag, rolling resistance, engine braking)")
    print("steady turns at 10 m/s (PI speed control), geometric radius R_min / steer:")
    for steer in (0.1, 0.2, 0.3, 0.4, 0.5):
        car.reset((0.0, 0.0, 0.0), 0.0)
        car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=10.0, clearance=0.0)
        ctl, radii, rolls = Speed(car, 10.0), [], []
        for k in range(15 * hz):
            s = ctl(steer)
            if k > 8 * hz:
                radii.append(s.speed / s.yaw_rate)
                rolls.append(s.roll)
        r0 = V.min_turn_radius() / steer
        r = float(np.mean(radii))
        print(f"  steer {steer:.1f}: R {r:6.2f} m vs {r0:6.2f} m ({100 * (r / r0 - 1):+5.1f} %), "
              f"{100.0 / r / 9.81:.2f} g, roll {math.degrees(np.mean(rolls)):.2f} deg, R jitter {100 * np.std(radii) / r:.2f} %")
    print("step steer at speed (coasting, 4 s): peak body sideslip")
    for v0, steer in ((20.0, 0.5), (30.0, 0.1), (30.0, 0.3)):
        car.reset((0.0, 0.0, 0.0), 0.0)
        car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=v0, clearance=0.0)
        car.apply_control(0.0, 0.0, steer)
        beta = 0.0
        for _ in range(4 * hz):
            car.step(1)
            s = car.state()
            vx = math.cos(s.yaw) * s.velocity[0] + math.sin(s.yaw) * s.velocity[1]
            vy = -math.sin(s.yaw) * s.velocity[0] + math.cos(s.yaw) * s.velocity[1]
            beta = max(beta, abs(math.atan2(vy, vx)))
        print(f"  {v0:.0f} m/s, steer {steer}: {math.degrees(beta):.1f} deg, {s.speed:.1f} m/s after 4 s, "
              f"yaw rate {s.yaw_rate:.2f} rad/s")
    p.disconnect(cid)


def rate_sweep() -> None:
    """The stability/accuracy sweep behind RECOMMENDED_PHYSICS_HZ."""
    print("physics-rate sweep (meshes and heightfields as the world builds them):")
    print("  A: lane-strip mesh, 30 m/s, +-0.03 steer slalom: all-wheels-down %, max roll, vertical velocity std")
    print("  B: heightfield hills, 30 m/s: all-wheels-down % (after the first second), max |z - terrain|")
    print("  C: 20 m circle on a fan junction at 10 m/s: radius, path residual")
    print("  D: 1 cm seams at 20 m/s: substeps with a wheel up, peak |vz|")
    print("  E: 7.5 cm speed hump at 30 km/h: peak vertical acceleration of the body, peak compression")
    print("  F: 0-100 km/h, braking from 20 m/s, parked on the 10 % heightfield grade: creep in 10 s")
    print("  G: head-on into a building mesh at 20 m/s: the front's penetration of the wall")
    rows = []
    for hz in (400, 200, 100, 50, 30, 20):
        r = {"hz": hz}
        # A
        cid = client(hz)
        lanes(cid)
        car = V.EgoVehicle(cid, position=(0.0, -1.75, 0.0))
        car.set_pose_velocity((0.0, -1.75, 0.0), 0.0, speed=30.0, clearance=0.0)
        ctl, down, roll, vz = Speed(car, 30.0, -1.75), [], 0.0, []
        for k in range(15 * hz):
            t = k / hz
            s = ctl(0.03 * math.sin(math.pi * t) if t > 3 else 0.0)
            down.append(all(car.state().wheel_contact))
            if k > hz:
                roll = max(roll, abs(s.roll))
                vz.append(s.velocity[2])
        r["A"] = (100 * np.mean(down), math.degrees(roll), np.std(vz))
        p.disconnect(cid)
        # B
        cid = client(hz)
        heightfield(cid, hills, -100, 1100, -60, 60)
        z0 = ground_z(cid, 0.0, 10.0)
        car = V.EgoVehicle(cid, position=(0.0, 10.0, z0))
        car.set_pose_velocity((0.0, 10.0, z0), 0.0, speed=30.0, clearance=0.0)
        ctl, down, err = Speed(car, 30.0, 10.0), [], 0.0
        for k in range(25 * hz):
            s = ctl()
            if k >= hz:  # spawned level on a slope, one wheel starts beyond its droop
                down.append(all(car.state().wheel_contact))
            if k % max(1, hz // 10) == 0 and k > hz:
                err = max(err, abs(s.z - ground_z(cid, s.x, s.y)))
        r["B"] = (100 * np.mean(down), err)
        p.disconnect(cid)
        # C
        cid = client(hz)
        junction_fan(cid)
        car = V.EgoVehicle(cid)
        car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=10.0, clearance=0.0)
        ctl, radii, path = Speed(car, 10.0), [], []
        for k in range(25 * hz):
            s = ctl(V.min_turn_radius() / 20.0)
            if k > 5 * hz:
                radii.append(s.speed / s.yaw_rate)
                path.append((s.x, s.y))
        xy = np.array(path)
        d, e, f = np.linalg.lstsq(np.c_[xy, np.ones(len(xy))], -(xy ** 2).sum(1), rcond=None)[0]
        c = np.array([-d / 2, -e / 2])
        r["C"] = (float(np.mean(radii)), np.abs(np.hypot(*(xy - c).T) - math.sqrt(c @ c - f)).max())
        p.disconnect(cid)
        # D
        cid = client(hz)
        seams(cid)
        car = V.EgoVehicle(cid, position=(-60.0, -1.75, 0.0))
        car.set_pose_velocity((-60.0, -1.75, 0.0), 0.0, speed=20.0, clearance=0.0)
        ctl, up, peak = Speed(car, 20.0, -1.75), 0, 0.0
        for _ in range(5 * hz):
            s = ctl()
            up += not all(car.state().wheel_contact)
            peak = max(peak, abs(s.velocity[2]))
        r["D"] = (up, peak)
        p.disconnect(cid)
        # E
        cid = client(hz)
        hump(cid)
        car = V.EgoVehicle(cid, position=(-30.0, 0.0, 0.0))
        car.set_pose_velocity((-30.0, 0.0, 0.0), 0.0, speed=30 / 3.6, clearance=0.0)
        ctl, acc, comp, last = Speed(car, 30 / 3.6), 0.0, 0.0, None
        for _ in range(6 * hz):
            s = ctl()
            if last is not None:
                acc = max(acc, abs(s.velocity[2] - last) * hz)
            last = s.velocity[2]
            comp = max(comp, max(car.suspension_compression()))
        r["E"] = (acc, comp)
        p.disconnect(cid)
        # F
        cid = client(hz)
        box_ground(cid)
        car = V.EgoVehicle(cid)
        car.step(hz // 2)
        car.apply_control(1.0, 0.0, 0.0)
        k = 0
        while car.state().speed < KMH100 and k < 30 * hz:
            car.step(1)
            k += 1
        t100 = k / hz
        car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=20.0, clearance=0.0)
        car.apply_control(0.0, 0.0, 0.0)
        car.step(hz // 5)
        s0 = s = car.state()
        car.apply_control(0.0, 1.0, 0.0)
        while s.speed > 0.05:
            car.step(1)
            s = car.state()
        p.disconnect(cid)
        cid = client(hz)
        heightfield(cid, lambda x, y: 0.1 * x, -50, 200, -30, 30)
        car = V.EgoVehicle(cid)
        car.reset((0.0, 0.0, 0.0), 0.0, pitch=-math.atan(0.1))
        car.apply_control(0.0, 1.0, 0.0)
        car.step(hz)
        a = car.state()
        car.step(10 * hz)
        b = car.state()
        r["F"] = (t100, s.x - s0.x, math.dist((a.x, a.y, a.z), (b.x, b.y, b.z)))
        p.disconnect(cid)
        # G
        cid = client(hz)
        lanes(cid)
        building(cid, x0=30.0, x1=40.0)
        car = V.EgoVehicle(cid, position=(0.0, -1.75, 0.0))
        car.set_pose_velocity((0.0, -1.75, 0.0), 0.0, speed=20.0, clearance=0.0)
        car.apply_control(0.0, 0.0, 0.0)
        deepest = -1e9
        for _ in range(3 * hz):
            car.step(1)
            s = car.state()
            deepest = max(deepest, s.x + V.SPEC.front_overhang + V.WHEELBASE / 2 - 30.0)
        r["G"] = deepest
        p.disconnect(cid)
        rows.append(r)
    print(f"  {'Hz':>4} | {'A down%':>7} {'roll':>6} {'vz std':>7} | {'B down%':>7} {'dz':>6} | {'C R':>6} {'resid':>6} "
          f"| {'D up':>4} {'vz':>5} | {'E acc':>6} {'comp':>5} | {'0-100':>6} {'brake':>6} {'creep':>7} | {'G wall':>6}")
    for r in rows:
        a, b, c, d, e, f = r["A"], r["B"], r["C"], r["D"], r["E"], r["F"]
        print(f"  {r['hz']:>4} | {a[0]:>7.2f} {a[1]:>5.2f}d {a[2]:>7.4f} | {b[0]:>7.2f} {b[1]:>6.3f} | {c[0]:>6.2f} "
              f"{c[1]:>6.3f} | {d[0]:>4d} {d[1]:>5.3f} | {e[0]:>6.2f} {e[1]:>5.3f} | {f[0]:>6.2f} {f[1]:>6.2f} "
              f"{f[2] * 1000:>5.1f}mm | {r['G']:>+6.2f}")


def main() -> None:
    print(f"ego car: {V.LENGTH:.2f} x {V.WIDTH:.2f} x {V.HEIGHT:.2f} m, {V.MASS:.0f} kg, wheelbase "
          f"{V.WHEELBASE:.2f} m, track {V.TRACK:.2f} m, wheel radius {V.WHEEL_RADIUS:.2f} m, "
          f"CoM height {V.COM_HEIGHT:.3f} m, min turn radius {V.min_turn_radius():.2f} m")
    step_costs()
    drive_figures()
    rate_sweep()


if __name__ == "__main__":
    main()
