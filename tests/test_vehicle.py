"""The ego car: its URDF through a real URDF parser, and its driving in real PyBullet.

Every driving test runs PyBullet in DIRECT mode at the recommended physics rate (or at
$COSIM_VEHICLE_TEST_HZ). The basic tests drive on a large static box (flat, or tilted into a
10 % grade); the decisive ones drive on the kinds of ground the real world is made of, built
here: static concave triangle meshes written as OBJ (lane strips resampled every 2.5 m, a
fan-triangulated junction, two meshes meeting with a 1 cm step) and GEOM_HEIGHTFIELD
terrain at 5 m spacing (gentle hills, a 10 % grade). Those run at the recommended rate and
at 100 Hz.
"""
from __future__ import annotations

import math
import os
import shutil
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

yourdfpy = pytest.importorskip("yourdfpy", reason="the URDF tests need the yourdfpy parser (test extra)")

from cosim import vehicle as V  # noqa: E402
from models import car_urdf_path  # noqa: E402

# the recommended rate; COSIM_VEHICLE_TEST_HZ re-runs the suite at the loop's own rate
HZ = int(os.environ.get("COSIM_VEHICLE_TEST_HZ") or V.RECOMMENDED_PHYSICS_HZ)
DT = 1.0 / HZ
GRADE = 0.10  # 10 % incline
KMH100 = 100.0 / 3.6
# the triangle-mesh / heightfield tests run at the test rate and at 50 and 100 Hz
MESH_RATES = sorted({HZ, 50, 100})


# --- worlds ------------------------------------------------------------------------------------
def new_client(hz: int = HZ) -> int:
    cid = p.connect(p.DIRECT)
    p.setGravity(0, 0, -9.81, physicsClientId=cid)
    V.configure_physics(cid, hz=hz)
    return cid


def make_world(grade: float = 0.0, hz: int = HZ) -> int:
    """A DIRECT client with gravity and a 6 km x 400 m asphalt box whose top passes through
    the origin, rising along +x with the given grade."""
    cid = new_client(hz)
    half = (3000.0, 200.0, 1.0)
    pitch = -math.atan(grade)  # about +y: a negative angle lifts +x
    orn = p.getQuaternionFromEuler((0.0, pitch, 0.0))
    rot = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
    centre = -rot @ np.array([0.0, 0.0, half[2]])  # top face through the origin
    shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=cid)
    ground = p.createMultiBody(0, shape, basePosition=centre.tolist(), baseOrientation=orn,
                               physicsClientId=cid)
    V.set_asphalt_friction(cid, ground)
    return cid


def write_obj(path: Path, verts, faces) -> Path:
    with open(path, "w") as f:
        f.writelines("v %.6f %.6f %.6f\n" % tuple(v) for v in verts)
        f.writelines("f %d %d %d\n" % (a + 1, b + 1, c + 1) for a, b, c in faces)
    return path


def lane_strip(x0: float, x1: float, y0: float, y1: float, step: float = 2.5, z: float = 0.0):
    """A lane strip as the world writes it: its two edges resampled every ``step`` m and
    zig-zag triangulated (long thin triangles, every diagonal an internal edge)."""
    xs = np.arange(x0, x1 + 1e-9, step)
    verts = [v for x in xs for v in ((x, y0, z), (x, y1, z))]
    faces = [f for i in range(len(xs) - 1)
             for f in ((2 * i, 2 * i + 2, 2 * i + 1), (2 * i + 1, 2 * i + 2, 2 * i + 3))]
    return verts, faces


def fan(cx: float, cy: float, radius: float, sectors: int, z: float = 0.0):
    """A junction polygon triangulated as a fan from its centre (long triangles meeting at one point)."""
    verts = [(cx, cy, z)] + [(cx + radius * math.cos(a), cy + radius * math.sin(a), z)
                             for a in np.linspace(0.0, 2 * math.pi, sectors, endpoint=False)]
    faces = [(0, 1 + k, 1 + (k + 1) % sectors) for k in range(sectors)]
    return verts, faces


def merge(*parts):
    verts, faces = [], []
    for v, f in parts:
        off = len(verts)
        verts += list(v)
        faces += [(a + off, b + off, c + off) for a, b, c in f]
    return verts, faces


def mesh_body(cid: int, path: Path) -> int:
    """A static concave triangle mesh from an OBJ file, as the world loads its road layers."""
    shape = p.createCollisionShape(p.GEOM_MESH, fileName=str(path), flags=p.GEOM_FORCE_CONCAVE_TRIMESH,
                                   physicsClientId=cid)
    return p.createMultiBody(0, shape, -1, [0, 0, 0], physicsClientId=cid)


def heightfield_body(cid: int, height, x0: float, x1: float, y0: float, y1: float, spacing: float = 5.0) -> int:
    """A GEOM_HEIGHTFIELD terrain sampled every ``spacing`` m, placed as the world places its tiles."""
    xs, ys = np.arange(x0, x1 + 1e-9, spacing), np.arange(y0, y1 + 1e-9, spacing)
    z = height(*np.meshgrid(xs, ys))
    ny, nx = z.shape
    shape = p.createCollisionShape(p.GEOM_HEIGHTFIELD, meshScale=[spacing, spacing, 1.0],
                                   heightfieldData=z.ravel().tolist(), numHeightfieldRows=nx,
                                   numHeightfieldColumns=ny, physicsClientId=cid)
    centre = [xs[0] + (nx - 1) * spacing / 2, ys[0] + (ny - 1) * spacing / 2, (z.min() + z.max()) / 2]
    return p.createMultiBody(0, shape, -1, centre, physicsClientId=cid)


def ground_height(cid: int, x: float, y: float) -> float:
    hit = p.rayTestBatch([(x, y, 500.0)], [(x, y, -500.0)], collisionFilterMask=-1 ^ V.CHASSIS_COLLISION_GROUP,
                         physicsClientId=cid)[0]  # the ground under the car, not its roof
    assert hit[0] >= 0, f"no ground at ({x}, {y})"
    return hit[3][2]


def hills(x, y):
    """Gentle hills: up to 1.5 m high, slopes up to ~8 %, sideways too."""
    return 1.0 * np.sin(2 * np.pi * x / 150.0) + 0.5 * np.sin(2 * np.pi * (x + y) / 90.0)


@pytest.fixture
def flat():
    cid = make_world()
    yield cid
    p.disconnect(cid)


@pytest.fixture
def incline():
    cid = make_world(GRADE)
    yield cid
    p.disconnect(cid)


@pytest.fixture
def client_at():
    """new_client(hz) for a test's own rate, disconnected afterwards."""
    made = []

    def make(hz: int) -> int:
        made.append(new_client(hz))
        return made[-1]

    yield make
    for cid in made:
        p.disconnect(cid)


def step(car: V.EgoVehicle, seconds: float, throttle=0.0, brake=0.0, steer=0.0, **kw):
    """Hold a command for ``seconds`` of simulated time."""
    car.apply_control(throttle, brake, steer, **kw)
    car.step(int(round(seconds / car.time_step)))
    return car.state()


def settled_car(cid, position=(0.0, 0.0, 0.0), yaw=0.0, pitch=0.0):
    car = V.EgoVehicle(cid, position=position, yaw=yaw)
    if pitch:
        car.reset(position, yaw, pitch=pitch)
    step(car, 1.0, brake=1.0)
    return car


def upright(s: V.VehicleState, slope_pitch: float = 0.0, limit_deg: float = 5.0) -> bool:
    return abs(math.degrees(s.roll)) < limit_deg and abs(math.degrees(s.pitch - slope_pitch)) < limit_deg


def hold_speed(car: V.EgoVehicle, target: float, steer: float = 0.0, kp=0.4, ki=0.2):
    """A PI speed controller (anti-windup) called once per substep; returns a stepper."""
    integral = 0.0
    hz = round(1.0 / car.time_step)

    def control(steer_now: float = steer) -> V.VehicleState:
        nonlocal integral
        s = car.state()
        err = target - s.speed
        integral = min(max(integral + err / hz, -5.0), 5.0)
        u = kp * err + ki * integral
        car.apply_control(max(u, 0.0), max(-u, 0.0), steer_now)
        car.step(1)
        return s

    return control


# --- the URDF, through a real parser ---------------------------------------------------------
def test_urdf_is_a_valid_tree_with_inertials():
    urdf = yourdfpy.URDF.load(str(car_urdf_path()), load_meshes=False)
    assert urdf.validate(), getattr(urdf, "errors", "invalid URDF")
    robot = urdf.robot
    links = {link.name for link in robot.links}
    children = [j.child for j in robot.joints]
    # a tree: every joint names existing links, every link but one has exactly one parent
    assert all(j.parent in links and j.child in links for j in robot.joints)
    assert len(children) == len(set(children)) == len(links) - 1
    assert urdf.base_link == "base_link" and "base_link" not in children
    for link in robot.links:
        inertial = link.inertial
        assert inertial is not None and inertial.mass > 0, f"{link.name} has no inertial"
        eig = np.linalg.eigvalsh(inertial.inertia)
        assert eig.min() > 0, f"{link.name}: inertia not positive definite"
        a, b, c = sorted(eig)
        assert a + b >= c * (1 - 1e-9), f"{link.name}: principal moments violate the triangle inequality"
    types = {j.name: j.type for j in robot.joints}
    assert sorted(t for t in types.values()) == ["continuous"] * 4 + ["revolute"] * 2
    for name in V.STEER_JOINTS:
        j = urdf.joint_map[name]
        assert j.type == "revolute" and np.allclose(j.axis, [0, 0, 1])
        assert math.degrees(j.limit.upper) == pytest.approx(35.0, abs=1.0)
        assert math.degrees(j.limit.lower) == pytest.approx(-35.0, abs=1.0)
    for name in V.WHEEL_JOINTS:
        assert urdf.joint_map[name].type == "continuous"
        assert np.allclose(urdf.joint_map[name].axis, [0, 1, 0])


def test_urdf_mass_dimensions_and_wheels():
    urdf = yourdfpy.URDF.load(str(car_urdf_path()), load_meshes=False)
    masses = {link.name: link.inertial.mass for link in urdf.robot.links}
    assert sum(masses.values()) == pytest.approx(1500.0, rel=0.10)
    # forward kinematics from the parser: wheel centres
    centre = {j: urdf.get_transform(urdf.joint_map[j].child)[:3, 3] for j in V.WHEEL_JOINTS}
    fl, fr, rl, rr = (centre[j] for j in V.WHEEL_JOINTS)
    assert fl[0] - rl[0] == pytest.approx(2.7, abs=0.1)  # wheelbase
    assert fl[1] - fr[1] == pytest.approx(1.55, abs=0.05)  # track
    for j in V.WHEEL_JOINTS:
        link = urdf.link_map[urdf.joint_map[j].child]
        assert link.inertial.mass == pytest.approx(20.0, rel=0.25)
        geom = link.collisions[0].geometry
        tyre = geom.sphere if geom.sphere is not None else geom.cylinder
        assert tyre.radius == pytest.approx(0.32, abs=0.02)
        assert centre[j][2] == pytest.approx(tyre.radius, abs=1e-6)  # tyre bottom on z = 0
        assert any(v.geometry.cylinder is not None and v.geometry.cylinder.radius == tyre.radius
                   for v in link.visuals)  # drawn as a real tyre
    # the module's constants agree with the parser
    assert V.MASS == pytest.approx(sum(masses.values()))
    assert V.WHEELBASE == pytest.approx(fl[0] - rl[0])
    assert V.TRACK == pytest.approx(fl[1] - fr[1])
    assert np.allclose(V.SPEC.wheel_positions, [centre[j] for j in V.WHEEL_JOINTS])
    assert V.LENGTH == pytest.approx(4.5, abs=0.1)
    assert V.WIDTH == pytest.approx(1.8, abs=0.05)
    assert V.HEIGHT == pytest.approx(1.45, abs=0.1)
    assert V.WHEEL_RADIUS == pytest.approx(0.32, abs=0.02)
    assert 0.4 < V.COM_HEIGHT < 0.6  # low centre of mass
    # static stability factor t / 2h far above the tyres' friction: cannot tip on flat ground
    assert V.TRACK / (2 * V.COM_HEIGHT) > 1.2


def test_constants_come_from_the_urdf(tmp_path):
    """Edit a copy of the URDF: the spec follows it (nothing duplicated by hand)."""
    text = car_urdf_path().read_text()
    text = text.replace('radius="0.32"', 'radius="0.35"').replace('<mass value="1410"/>', '<mass value="1610"/>')
    text = text.replace('xyz="1.35 ', 'xyz="1.45 ')  # front axle 10 cm forward
    copy = tmp_path / "car.urdf"
    copy.write_text(text)
    spec = V.read_car_spec(copy)
    assert spec.wheel_radius == pytest.approx(0.35)
    assert spec.mass == pytest.approx(V.MASS + 200.0)
    assert spec.wheelbase == pytest.approx(V.WHEELBASE + 0.10)
    assert spec.wheel_positions[0] == pytest.approx((1.45, V.TRACK / 2, 0.32))
    assert spec.ground_z == pytest.approx(-0.03)  # bigger tyres on the same axles reach lower
    assert spec.height == pytest.approx(V.HEIGHT + 0.03)
    assert yourdfpy.URDF.load(str(copy), load_meshes=False).validate()


# --- loading and placement -----------------------------------------------------------------
def test_loads_and_settles_on_its_springs(flat):
    car = V.EgoVehicle(flat, position=(5.0, -3.0, 0.0), yaw=0.5)
    n = p.getNumJoints(car.body_id, physicsClientId=flat)
    total = sum(p.getDynamicsInfo(car.body_id, link, physicsClientId=flat)[0] for link in range(-1, n))
    assert total == pytest.approx(V.MASS)
    s = car.state()
    assert s.z == pytest.approx(V.SPAWN_CLEARANCE, abs=1e-6)  # dropped from just above
    assert not any(s.wheel_contact)  # no ray cast yet
    car.step(1)
    assert all(car.state().wheel_contact)  # the drooping wheels reach the ground 3 cm below
    s = step(car, 2.0, brake=1.0)
    assert all(s.wheel_contact)
    assert (s.x, s.y) == pytest.approx((5.0, -3.0), abs=0.02)
    assert s.yaw == pytest.approx(0.5, abs=1e-3)
    # the springs are preloaded for the design ride height: the footprint centre is on the road
    assert abs(s.z) < 0.002
    assert max(map(abs, car.suspension_compression())) < 0.002
    assert upright(s, limit_deg=0.1)
    assert abs(s.speed) < 1e-3
    loads = car.wheel_loads()
    assert sum(loads) == pytest.approx(V.MASS * 9.81, rel=0.002)
    front = (loads[0] + loads[1]) / sum(loads)
    assert front == pytest.approx((V.SPEC.com[0] - V.SPEC.rear_axle_x) / V.WHEELBASE, abs=0.005)
    assert loads[0] == pytest.approx(loads[1], rel=1e-3) and loads[2] == pytest.approx(loads[3], rel=1e-3)
    # the rays carry the car: no Bullet contact between the car and the ground at all
    assert p.getContactPoints(bodyA=car.body_id, physicsClientId=flat) == ()


def test_rays_skip_the_chassis(tmp_path, flat):
    """A chassis collision box right across the front wheels' rays (a low crossmember, in a
    copy of the URDF): the rays pass it (collision group), the car rests on the road. Rays
    that hit it would lift the car on its own body."""
    text = car_urdf_path().read_text()
    crossmember = ('<collision name="crossmember"><origin xyz="1.35 0 0.25" rpy="0 0 0"/>'
                   '<geometry><box size="0.1 1.8 0.05"/></geometry></collision>\n    ')
    text = text.replace('<collision name="underbody">', crossmember + '<collision name="underbody">', 1)
    copy = tmp_path / "crossmember.urdf"
    copy.write_text(text)
    car = V.EgoVehicle(flat, urdf_path=copy)
    s = step(car, 2.0, brake=1.0)
    assert all(s.wheel_contact) and abs(s.z) < 0.002 and upright(s, limit_deg=0.1)
    assert sum(car.wheel_loads()) == pytest.approx(V.MASS * 9.81, rel=0.002)
    # the box is there: the ray the wheel casts would hit it without the chassis' group excluded
    start = p.getLinkState(car.body_id, car.steer_joints[0], physicsClientId=flat)[4]
    hit = p.rayTest((start[0], start[1], start[2] + 0.1), (start[0], start[1], -0.5), physicsClientId=flat)[0]
    assert hit[0] == car.body_id and hit[3][2] == pytest.approx(0.275, abs=0.005)


def test_rays_miss_beyond_the_travel(flat):
    """Lifted above the suspension's reach, no ray hits anything and the car falls freely."""
    car = V.EgoVehicle(flat, position=(0.0, 0.0, 0.0))
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, clearance=1.0)
    car.step(1)
    assert car.state().wheel_contact == (False, False, False, False)
    assert car.wheel_loads() == (0.0, 0.0, 0.0, 0.0)
    z0 = car.state().z
    car.step(int(0.2 * HZ) - 1)
    s = car.state()
    assert not any(s.wheel_contact)
    assert s.velocity[2] == pytest.approx(-9.81 * 0.2, rel=0.02)  # free fall: no wheel force
    assert z0 > s.z > 0.6
    # and it lands on its wheels without bouncing off again
    s = step(car, 3.0, brake=1.0)
    assert all(s.wheel_contact) and abs(s.z) < 0.002 and upright(s, limit_deg=0.1)


def test_chassis_still_collides_with_buildings(client_at, tmp_path):
    """The body box is a Bullet collider: driving into a building (a concave mesh wall) stops the car."""
    cid = client_at(HZ)
    road = write_obj(tmp_path / "road.obj", *lane_strip(-20.0, 60.0, -10.0, 10.0))
    mesh_body(cid, road)
    # a closed box building 10 m ahead, as the world meshes buildings (triangles, no volume)
    x0, x1, y0, y1, h = 10.0, 20.0, -8.0, 8.0, 6.0
    corners = [(x, y, z) for z in (0.0, h) for x, y in ((x0, y0), (x1, y0), (x1, y1), (x0, y1))]
    quads = [(0, 1, 2, 3), (4, 5, 6, 7), (0, 1, 5, 4), (1, 2, 6, 5), (2, 3, 7, 6), (3, 0, 4, 7)]
    faces = [t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))]
    mesh_body(cid, write_obj(tmp_path / "building.obj", corners, faces))
    car = V.EgoVehicle(cid)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=8.0, clearance=0.0)
    s = step(car, 4.0, throttle=0.3)
    front = s.x + V.SPEC.front_overhang + V.WHEELBASE / 2
    assert front < x0 + 0.3, f"the car's front got to x = {front:.2f} m, into the wall at {x0}"
    assert abs(s.speed) < 1.0


def test_reset_and_set_pose_velocity(flat):
    car = settled_car(flat)
    step(car, 3.0, throttle=1.0, steer=0.4)
    car.reset((50.0, 20.0, 0.0), math.pi / 2)
    s = car.state()
    assert (s.x, s.y, s.yaw) == pytest.approx((50.0, 20.0, math.pi / 2), abs=1e-6)
    assert s.speed == pytest.approx(0.0, abs=1e-9) and s.steer == pytest.approx(0.0, abs=1e-9)
    car.set_pose_velocity((0.0, 0.0, 0.0), math.pi, speed=12.0, clearance=0.0)
    s = car.state()
    assert s.speed == pytest.approx(12.0, abs=1e-6)
    assert s.velocity[0] == pytest.approx(-12.0, abs=1e-6)  # heading west
    assert car.wheel_spin_rates() == pytest.approx((12.0 / V.WHEEL_RADIUS,) * 4)
    s = step(car, 1.0)  # rolls on at about that speed, wheels spinning with it
    assert 11.0 < s.speed < 12.0 and s.x < -10.0 and all(s.wheel_contact)
    assert car.wheel_spin_rates() == pytest.approx((s.speed / V.WHEEL_RADIUS,) * 4, rel=0.01)


def test_step_equals_substep_then_stepsimulation():
    """A loop that steps the world itself (substep() before each stepSimulation) drives the
    car exactly as step() does."""
    runs = []
    for own_loop in (False, True):
        cid = make_world()
        try:
            car = V.EgoVehicle(cid)
            car.apply_control(0.8, 0.0, 0.3)
            for _ in range(3):
                if own_loop:
                    for _ in range(HZ):
                        car.substep()
                        p.stepSimulation(physicsClientId=cid)
                    car.sync_visuals()
                else:
                    car.step(HZ)
            s = car.state()
            joints = [j[0] for j in p.getJointStates(car.body_id, car.steer_joints + car.wheel_joints,
                                                     physicsClientId=cid)]
            runs.append((s.x, s.y, s.z, s.yaw, s.speed, *joints))
        finally:
            p.disconnect(cid)
    assert runs[0] == pytest.approx(runs[1], abs=1e-9)
    assert runs[0][4] > 5.0 and runs[0][3] > 0.5  # it did drive and turn
    # the visual joints show the Ackermann angles
    assert runs[0][5:7] == pytest.approx(V.ackermann_angles(0.3), abs=1e-9)


def test_advance_runs_whole_physics_steps(flat):
    car = V.EgoVehicle(flat)
    assert car.time_step == pytest.approx(1.0 / HZ)
    assert car.advance(0.1) == round(0.1 * HZ)
    with pytest.raises(ValueError):
        car.advance(0.5 / HZ)


# --- longitudinal performance ---------------------------------------------------------------
def test_full_throttle_acceleration_and_top_speed(flat):
    car = settled_car(flat)
    t, t100, t30 = 0.0, None, None
    while t < 60.0:
        s = step(car, DT, throttle=1.0)
        t += DT
        if t100 is None and s.speed >= KMH100:
            t100 = t
        if t30 is None and s.speed >= 30.0:
            t30 = t
        assert upright(s)
    assert t100 is not None and 6.0 <= t100 <= 16.0, f"0-100 km/h in {t100} s"
    assert t30 is not None and t30 <= 60.0
    assert 30.0 <= s.speed <= V.TOP_SPEED + 0.5  # bounded by the governor / power
    assert abs(s.y) < 0.001 * s.x and abs(s.yaw) < 0.01  # drives straight (< 1 m per km)


def test_braking_from_20_mps(flat):
    car = settled_car(flat)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=20.0, clearance=0.0)
    s0 = step(car, 0.2)  # let the tyres load up
    x0, v0 = s0.x, s0.speed
    assert v0 > 19.5
    t, s = 0.0, s0
    while s.speed > 0.05 and t < 10.0:
        s = step(car, DT, brake=1.0)
        t += DT
        assert upright(s)
    distance = s.x - x0
    assert 20.0 <= distance <= 40.0, f"stopped in {distance:.1f} m"
    decel_g = v0 ** 2 / (2 * distance) / 9.81
    assert 0.7 <= decel_g <= 1.05
    s1 = step(car, 2.0, brake=1.0)  # and stays stopped (the tyres spring back by a centimetre at most)
    assert abs(s1.speed) < 0.01 and abs(s1.x - s.x) < 0.02


def test_coasting_slows_by_drag_and_rolling_resistance(flat):
    car = settled_car(flat)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=30.0, clearance=0.0)
    s = step(car, 10.0)
    # drag 0.5 rho CdA v^2 (~360 N at 30 m/s) + Crr m g (~180 N) + engine braking: 0.3-0.6 m/s^2
    assert 24.0 < s.speed < 27.5


def test_reverse_gear(flat):
    car = settled_car(flat)
    s = step(car, 5.0, throttle=0.5, reverse=True)
    assert -V.REVERSE_SPEED - 0.2 < s.speed < -2.0
    assert s.x < -5.0
    s = step(car, 10.0, throttle=1.0, reverse=True)
    assert s.speed == pytest.approx(-V.REVERSE_SPEED, abs=0.6)  # governed


# --- lateral behaviour -----------------------------------------------------------------------
@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_steer_sign_turns_the_right_way(flat, sign):
    car = settled_car(flat)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=8.0, clearance=0.0)
    s = step(car, 2.0, throttle=0.1, steer=0.5 * sign)
    assert sign * s.yaw_rate > 0.2  # steer > 0: left, counter-clockwise
    assert sign * s.yaw > 0.3
    assert sign * s.y > 1.0
    assert sign * s.steer > 0
    assert sign * s.roll > 0  # the body leans out of the turn (left turn: left side up)


def test_steady_turn_at_10_mps_stays_upright(flat):
    car = settled_car(flat)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=10.0, clearance=0.0)
    steer = 0.3  # 0.63 g
    control = hold_speed(car, 10.0, steer, kp=0.3, ki=0.1)
    radii, worst = [], 0.0
    for k in range(int(15 * HZ)):
        s = control()
        if k > 5 * HZ:
            worst = max(worst, abs(s.roll), abs(s.pitch))
            radii.append(s.speed / s.yaw_rate)
            assert all(s.wheel_contact)
    assert math.degrees(worst) < 5.0
    assert s.speed == pytest.approx(10.0, abs=0.3)
    # the rear-axle centre follows the Ackermann circle R = R_min / steer widened by the tyres'
    # slip (a little understeer at 0.63 g); speed / yaw_rate is that radius
    geometric = V.min_turn_radius() / steer
    assert 1.0 <= np.mean(radii) / geometric <= 1.08
    assert np.std(radii) < 0.01 * np.mean(radii)


def test_ackermann_geometry_inner_wheel_steers_more(flat):
    for steer in (0.2, 0.6, 1.0):
        left, right = V.ackermann_angles(steer)
        assert left > right > 0  # left turn: left wheel inside
        radius = V.min_turn_radius() / steer
        assert math.tan(left) == pytest.approx(V.WHEELBASE / (radius - V.TRACK / 2))
        assert math.tan(right) == pytest.approx(V.WHEELBASE / (radius + V.TRACK / 2))
        assert V.ackermann_angles(-steer) == pytest.approx((-right, -left))
    assert V.ackermann_angles(1.0)[0] == pytest.approx(V.MAX_STEER)
    # on the car, and on its visual steering joints
    car = settled_car(flat)
    step(car, 2.0, steer=0.6, brake=1.0)
    left, right = car.wheel_steer_angles()
    assert (left, right) == pytest.approx(V.ackermann_angles(0.6), abs=1e-9)
    joints = [j[0] for j in p.getJointStates(car.body_id, car.steer_joints, physicsClientId=flat)]
    assert joints == pytest.approx([left, right], abs=1e-9)
    assert left > right > 0
    step(car, 3.0, steer=-0.6, brake=1.0)
    left, right = car.wheel_steer_angles()
    assert right < left < 0 and abs(right) > abs(left)


def test_steering_rate_is_limited(flat):
    car = settled_car(flat)
    target = V.ackermann_angles(1.0)[0]
    step(car, 0.2, steer=1.0, brake=1.0)
    left = car.wheel_steer_angles()[0]
    assert left == pytest.approx(V.STEER_RATE * 0.2, abs=1e-9)  # still on its way, at the rate limit
    step(car, 1.5, steer=1.0, brake=1.0)
    assert car.wheel_steer_angles()[0] == pytest.approx(target, abs=1e-9)  # arrived, at the lock


# --- grades ----------------------------------------------------------------------------------
def test_pi_speed_controller_holds_10_mps_up_a_10_percent_grade(incline):
    slope = -math.atan(GRADE)  # nose up is a negative pitch
    car = settled_car(incline, pitch=slope)
    assert car.state().pitch == pytest.approx(slope, abs=0.01)
    control, errors = hold_speed(car, 10.0), []
    for k in range(int(40 * HZ)):
        s = control()
        assert upright(s, slope_pitch=slope)
        if k >= 20 * HZ:
            errors.append(10.0 - s.speed)
    assert max(abs(e) for e in errors) <= 0.3, f"speed error up to {max(map(abs, errors)):.2f} m/s"
    assert s.z > 25.0  # it really climbed: ~300 m along a 10 % grade
    assert s.pitch == pytest.approx(slope, abs=math.radians(1.0))


def test_brake_holds_the_car_on_a_10_percent_grade(incline):
    slope = -math.atan(GRADE)
    car = V.EgoVehicle(incline)
    car.reset((0.0, 0.0, 0.0), 0.0, pitch=slope)
    s0 = step(car, 1.0, brake=1.0)
    s1 = step(car, 10.0, brake=1.0)
    moved = math.dist((s0.x, s0.y, s0.z), (s1.x, s1.y, s1.z))
    assert moved < 0.05, f"crept {moved:.3f} m"
    # and without the brake it does roll back down (the test could fail)
    s2 = step(car, 3.0)
    assert s2.speed < -0.5 and s2.x < s1.x - 1.0


def test_full_throttle_climbs_a_40_percent_grade_from_a_standstill():
    """First gear's torque at the wheels (about 3000 N m) takes the car up a 40 % street from
    a standstill; with 1500 N m it stalled at about 30 % and rolled back (a Monaco street on a
    DEM cliff, 50 %)."""
    grade = 0.40
    cid = make_world(grade)
    try:
        slope = -math.atan(grade)
        car = settled_car(cid, pitch=slope)
        s0 = car.state()
        s1 = step(car, 3.0, throttle=1.0)
        assert s1.speed > 1.0 and s1.x > s0.x + 2.0, f"{s1.speed:.2f} m/s after 3 s, {s1.x - s0.x:.2f} m"
        assert upright(s1, slope_pitch=slope, limit_deg=6.0)
    finally:
        p.disconnect(cid)


def test_result_does_not_depend_on_the_physics_rate():
    """0-100 km/h at the test rate agrees with 4x finer steps within 4 %."""
    times = []
    for hz in (HZ, 4 * HZ):
        cid = make_world(hz=hz)
        try:
            car = V.EgoVehicle(cid)
            car.step(hz)
            t = 0.0
            car.apply_control(1.0, 0.0, 0.0)
            while car.state().speed < KMH100 and t < 30.0:
                car.step(1)
                t += 1.0 / hz
            times.append(t)
        finally:
            p.disconnect(cid)
    assert times[0] == pytest.approx(times[1], rel=0.04)


def test_urdf_copy_loads_in_pybullet(tmp_path, flat):
    """A user-supplied URDF path works (here an identical copy outside the package)."""
    copy = tmp_path / "mycar.urdf"
    shutil.copy(car_urdf_path(), copy)
    car = V.EgoVehicle(flat, urdf_path=copy, position=(0.0, 10.0, 0.0))
    assert car.spec.urdf_path == copy.resolve()
    s = step(car, 1.0, brake=1.0)
    assert all(s.wheel_contact) and s.y == pytest.approx(10.0, abs=0.02)


# --- the decisive ones: triangle meshes and heightfields, as the world is built -------------
@pytest.mark.parametrize("hz", MESH_RATES)
def test_30_mps_on_lane_strip_meshes(client_at, tmp_path, hz):
    """Two 3.5 m lane strips resampled every 2.5 m (a concave triangle mesh): at 30 m/s all
    four wheels keep contact, the body neither rolls nor bounces."""
    cid = client_at(hz)
    road = merge(lane_strip(-50.0, 1000.0, -3.5, 0.0), lane_strip(-50.0, 1000.0, 0.0, 3.5))
    mesh_body(cid, write_obj(tmp_path / "lanes.obj", *road))
    car = V.EgoVehicle(cid, position=(0.0, -1.75, 0.0))
    step(car, 1.0, brake=1.0)
    car.set_pose_velocity((0.0, -1.75, 0.0), 0.0, speed=30.0, clearance=0.0)
    control = hold_speed(car, 30.0)
    contact, vz, roll, s = [], [], [], car.state()
    for _ in range(int(20 * hz)):
        s = control(-0.01 * (s.y + 1.75) - 0.15 * s.yaw)  # keep the right lane
        contact.append(all(car.state().wheel_contact))
        vz.append(s.velocity[2])
        roll.append(abs(s.roll))
    assert np.mean(contact) >= 0.99, f"all wheels down in {100 * np.mean(contact):.1f} % of substeps"
    assert math.degrees(max(roll)) < 3.0
    assert np.std(vz) < 0.05, f"vertical velocity std {np.std(vz):.3f} m/s"
    assert s.x > 550.0 and s.speed == pytest.approx(30.0, abs=0.3)
    assert abs(s.z) < 0.01  # riding at its design height on the mesh
    assert abs(s.y + 1.75) < 0.5


@pytest.mark.parametrize("hz", MESH_RATES)
def test_30_mps_over_heightfield_hills(client_at, hz):
    """GEOM_HEIGHTFIELD at 5 m spacing with gentle hills (sideways slopes too): contact in
    >= 99 % of substeps at 30 m/s, upright, riding at the terrain's height."""
    cid = client_at(hz)
    heightfield_body(cid, hills, -100.0, 1100.0, -60.0, 60.0)
    z0 = ground_height(cid, 0.0, 10.0)
    car = V.EgoVehicle(cid, position=(0.0, 10.0, z0))
    step(car, 1.0, brake=1.0)
    car.set_pose_velocity((0.0, 10.0, car.state().z), 0.0, speed=30.0, clearance=0.0)
    control = hold_speed(car, 30.0, kp=0.6)
    contact, worst, height_error, s = [], 0.0, [], car.state()
    for k in range(int(25 * hz)):
        s = control(-0.01 * (s.y - 10.0) - 0.15 * s.yaw)
        contact.append(all(car.state().wheel_contact))
        worst = max(worst, abs(s.roll))
        if k % 10 == 0:
            height_error.append(s.z - ground_height(cid, s.x, s.y))
    assert np.mean(contact) >= 0.99, f"all wheels down in {100 * np.mean(contact):.1f} % of substeps"
    assert math.degrees(worst) < 5.0
    assert s.x > 700.0 and s.speed == pytest.approx(30.0, abs=1.0)
    # the footprint centre follows the terrain (sagging in the dips, floating over the crests)
    assert max(map(abs, height_error)) < 0.08
    assert np.ptp([ground_height(cid, x, 10.0) for x in range(0, 700, 10)]) > 2.0  # it was hilly


@pytest.mark.parametrize("hz", MESH_RATES)
def test_20_m_radius_turn_on_a_fan_triangulated_junction(client_at, tmp_path, hz):
    """A 20 m circle at 10 m/s (0.5 g) on a junction polygon fanned into 24 long triangles:
    every lap crosses 48 internal edges; the radius holds within 5 % of the Ackermann one."""
    cid = client_at(hz)
    mesh_body(cid, write_obj(tmp_path / "junction.obj", *fan(0.0, 20.0, 45.0, 24)))
    car = V.EgoVehicle(cid)
    car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=10.0, clearance=0.0)
    steer = V.min_turn_radius() / 20.0
    control = hold_speed(car, 10.0, steer)
    radii, contact, worst, path = [], [], 0.0, []
    for k in range(int(30 * hz)):
        s = control()
        contact.append(all(car.state().wheel_contact))
        if k > 5 * hz:
            radii.append(s.speed / s.yaw_rate)
            worst = max(worst, abs(s.roll))
            path.append((s.x, s.y))
    assert np.mean(contact) >= 0.99
    assert np.mean(radii) == pytest.approx(20.0, rel=0.05)
    assert np.std(radii) < 0.01 * np.mean(radii)
    assert math.degrees(worst) < 3.0
    # the path is one circle (not a spiral, no wobble): least-squares circle, residuals < 5 cm
    xy = np.array(path)
    d, e, f = np.linalg.lstsq(np.c_[xy, np.ones(len(xy))], -(xy ** 2).sum(1), rcond=None)[0]
    centre = np.array([-d / 2, -e / 2])
    radius = math.sqrt(centre @ centre - f)
    assert np.abs(np.hypot(*(xy - centre).T) - radius).max() < 0.05
    assert radius == pytest.approx(math.hypot(np.mean(radii), V.WHEELBASE / 2), rel=0.01)  # mid-wheelbase


@pytest.mark.parametrize("hz", MESH_RATES)
def test_1_cm_seam_between_meshes_at_20_mps(client_at, tmp_path, hz):
    """A road mesh, a junction mesh 1 cm higher (resampled differently), and a road mesh again:
    at 20 m/s the wheels keep contact over both steps and the body barely notices."""
    cid = client_at(hz)
    mesh_body(cid, write_obj(tmp_path / "road_in.obj", *merge(lane_strip(-150.0, 0.0, -3.5, 0.0),
                                                               lane_strip(-150.0, 0.0, 0.0, 3.5))))
    mesh_body(cid, write_obj(tmp_path / "junction.obj", *lane_strip(0.0, 20.0, -8.0, 8.0, step=20.0 / 7, z=0.01)))
    mesh_body(cid, write_obj(tmp_path / "road_out.obj", *merge(lane_strip(20.0, 150.0, -3.5, 0.0),
                                                                lane_strip(20.0, 150.0, 0.0, 3.5))))
    car = V.EgoVehicle(cid, position=(-60.0, -1.75, 0.0))
    car.set_pose_velocity((-60.0, -1.75, 0.0), 0.0, speed=20.0, clearance=0.0)
    control = hold_speed(car, 20.0)
    contact, vz, pitch, heights = [], [], [], []
    for _ in range(int(5 * hz)):
        s = control()
        contact.append(all(car.state().wheel_contact))
        vz.append(abs(s.velocity[2]))
        pitch.append(abs(s.pitch))
        if 5.0 < s.x < 15.0:
            heights.append(s.z)
    assert all(contact), f"lost contact in {contact.count(False)} substeps"
    assert s.x > 35.0  # crossed both seams
    assert max(vz) < 0.1 and math.degrees(max(pitch)) < 0.5
    assert np.mean(heights) == pytest.approx(0.01, abs=0.003)  # rode up onto the junction


@pytest.mark.parametrize("hz", MESH_RATES)
def test_10_percent_heightfield_grade_pi_and_parking(client_at, hz):
    """GEOM_HEIGHTFIELD rising 10 %: a PI controller holds 10 m/s within +-0.3 m/s, and
    parked with the brake the car creeps < 5 cm in 10 s."""
    cid = client_at(hz)
    heightfield_body(cid, lambda x, y: GRADE * x, -50.0, 500.0, -30.0, 30.0)
    slope = -math.atan(GRADE)
    car = V.EgoVehicle(cid)
    car.reset((0.0, 0.0, 0.0), 0.0, pitch=slope)
    s0 = step(car, 1.0, brake=1.0)
    s1 = step(car, 10.0, brake=1.0)
    assert all(s1.wheel_contact)
    assert math.dist((s0.x, s0.y, s0.z), (s1.x, s1.y, s1.z)) < 0.05
    control, errors = hold_speed(car, 10.0), []
    for k in range(int(35 * hz)):
        s = control()
        assert upright(s, slope_pitch=slope)
        if k >= 15 * hz:
            errors.append(10.0 - s.speed)
    assert max(map(abs, errors)) <= 0.3, f"speed error up to {max(map(abs, errors)):.2f} m/s"
    assert s.z == pytest.approx(GRADE * s.x, abs=0.05) and s.z > 25.0


def test_lift_out_puts_the_car_on_top_of_new_higher_ground(client_at, tmp_path):
    """A tile replaced under a moving car by a newer build whose road is higher there (Portland
    seed 35: 0.36 m): the car's body is inside the new road. ``lift_out`` sets it on top, with
    its speed; without it the car is caught. A step under ``LIFT_MIN_STEP_M`` is left alone."""
    def caught_in(rise: float, lift: bool):
        cid = client_at(HZ)
        mesh_body(cid, write_obj(tmp_path / "old.obj", *lane_strip(-30.0, 300.0, -6.0, 6.0)))
        car = V.EgoVehicle(cid)
        car.set_pose_velocity((0.0, 0.0, 0.0), 0.0, speed=8.0, clearance=0.0)
        s0 = step(car, 0.5, throttle=0.3)
        mesh_body(cid, write_obj(tmp_path / f"new{rise}.obj", *lane_strip(-30.0, 300.0, -6.0, 6.0, z=rise)))
        lifted = car.lift_out() if lift else 0.0
        s = step(car, 3.0, throttle=0.3)
        return s0, lifted, s

    s0, lifted, s = caught_in(0.36, lift=True)
    assert lifted == pytest.approx(0.36 - s0.z, abs=0.03)
    assert s.x > s0.x + 20.0 and s.speed > 6.0, f"the lifted car went {s.x - s0.x:.1f} m at {s.speed:.1f} m/s"
    assert s.z == pytest.approx(0.36, abs=0.05) and all(s.wheel_contact) and upright(s)
    # without: Bullet pushes the body out of the road it is caught in, and that stops the car
    s0n, _, sn = caught_in(0.36, lift=False)
    assert sn.x - s0n.x < 0.5 * (s.x - s0.x), f"without lift_out the car went {sn.x - s0n.x:.1f} m"
    # a small step: the wheels take it, lift_out does nothing
    s0, lifted, s = caught_in(0.05, lift=True)
    assert lifted == 0.0 and s.x > s0.x + 20.0
