"""The ego car: a URDF chassis on four raycast wheels in a PyBullet world.

``models/car/car.urdf`` describes the geometry and the masses; this module reads every
dimension it needs from that file (see :func:`read_car_spec`) and adds what a URDF cannot say:
the suspension, the tyres, the drivetrain (torque and power limits, brakes), Ackermann
steering with a rate limit, rolling resistance and aerodynamic drag.

Frames and signs (ROS REP-103, same as the world frame: x east, y north, z up):

* the car's reference point is the centre of its footprint at ground level (the base link
  origin of the URDF), so ``state().z`` is the height of the road under the car at rest;
* yaw 0 points the car along +x (east), yaw grows counter-clockwise;
* roll/pitch/yaw are the URDF/ROS fixed-axis x-y-z angles: pitch > 0 is nose *down*
  (climbing a hill gives a negative pitch), roll > 0 is left side up;
* steer > 0 turns left (yaw increases), speed > 0 is forwards.

Raycast vehicle (as btRaycastVehicle, PhysX vehicles, Unity's WheelCollider). The chassis is
the URDF's base link: a dynamic rigid body with the URDF's mass and inertia (the wheel links'
masses ride along on their joints) and the only link that collides in Bullet, so it still
hits buildings, cars and, when bottoming out, the ground. The wheel links collide with
nothing. Before every ``stepSimulation`` :meth:`EgoVehicle.substep`

1. casts one ray per wheel (one ``rayTestBatch``) from the suspension top, the wheel centre
   raised by the bump travel, down the chassis' -z, skipping the chassis' collision group;
   the hit gives the compression, the road point and its normal. A thin ray sees each
   triangle of a mesh or heightfield exactly, so triangle edges do not throw the car off;
2. computes each wheel's normal load: a spring preloaded so that the car rests with its
   wheels at their URDF positions (unloaded at full droop), a bump stop, anti-roll bars and a
   damper on the chassis' velocity along the normal;
3. computes the tyre forces in the road plane, along the (Ackermann-steered) wheel heading
   and across it: longitudinal from the drive torque (rear wheels, open differential), the
   brakes and rolling resistance; lateral from the slip angle, through a tyre deflection that
   relaxes over ``RELAXATION_LENGTH`` of rolling (so the same spring holds the car sideways at
   standstill) and a brush-model saturation; a braked wheel below ``HOLD_SPEED`` grips like a
   stiff spring anchored where it stopped (static friction: no creep on a slope); the sum is
   limited to the friction circle ``mu Fz`` with a load-sensitive ``mu``;
4. applies the four wheels' forces as one force at the centre of mass and one torque
   (``applyExternalForce`` / ``applyExternalTorque``, world frame), which Bullet clears after
   the step.

The steering and wheel-spin joints only show the wheels (:meth:`EgoVehicle.sync_visuals`
poses them with ``resetJointStatesMultiDof``). Aerodynamic drag ``0.5 rho CdA v^2`` is
Bullet's multibody damping (``m d v (1 + |v|)`` with ``d = rho CdA / 2m``).

Stepping physics: the car must run before every ``stepSimulation``. Either let the car step
the world, ``car.step(n)`` (``n`` substeps of the client's time step; ``car.advance(0.1)``
for one SUMO step), or, in a loop that calls ``stepSimulation`` itself, call
``car.substep()`` right before each one and ``car.sync_visuals()`` before rendering.
:meth:`EgoVehicle.apply_control` only stores the command (pedals, steer, gear).

Physics rate: :func:`configure_physics` (``RECOMMENDED_PHYSICS_HZ`` substeps per second);
models/car/README.md gives the measurements behind it. Any fixed step from 20 Hz up works:
the tyre springs are kept stable at coarse steps.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pybullet as p

from models import car_urdf_path

# --- joint names in the URDF ---------------------------------------------------------------
STEER_JOINTS = ("front_left_steer_joint", "front_right_steer_joint")
WHEEL_JOINTS = (
    "front_left_wheel_joint",
    "front_right_wheel_joint",
    "rear_left_wheel_joint",
    "rear_right_wheel_joint",
)
DRIVEN = (False, False, True, True)  # rear-wheel drive, same order as WHEEL_JOINTS


@dataclass(frozen=True)
class CarSpec:
    """Geometry and masses of a car URDF (base link frame, zero joint angles)."""

    urdf_path: Path
    length: float  # m, bounding box of the body's (base link's) collision geometry along x
    width: float  # m, along y
    height: float  # m, top of the body above the ground the tyres stand on
    ground_z: float  # m, lowest collision point (the tyre bottoms at the design position) in the base frame
    front_overhang: float  # m, front of the body ahead of the front axle
    rear_overhang: float  # m, back of the body behind the rear axle
    wheelbase: float  # m, front axle x - rear axle x
    track: float  # m, distance between the front wheel centres
    front_axle_x: float  # m, in the base frame
    rear_axle_x: float
    mass: float  # kg, all links
    com: tuple[float, float, float]  # m, centre of mass of all links in the base frame
    wheel_radius: float  # m
    wheel_width: float  # m, of the visual tyre cylinder
    wheel_mass: float  # kg, one wheel
    max_steer: float  # rad, road-wheel lock of each steering joint (URDF joint limit)
    steer_rate: float  # rad/s, steering joint velocity limit (URDF joint limit)
    # tyre, from the wheels' <contact> element (PyBullet's URDF extension)
    tyre_friction: float  # tyre-road friction coefficient mu of the raycast tyre model
    tyre_rolling_friction: float  # <contact> values the raycast model does not use (0 if absent)
    tyre_spinning_friction: float
    tyre_stiffness: float
    tyre_damping: float
    # wheel centres (FL, FR, RL, RR) in the base frame at zero joint angles: the suspension
    # design position (where the wheels sit at rest on flat ground)
    wheel_positions: tuple[tuple[float, float, float], ...] = ()

    @property
    def com_height(self) -> float:
        return self.com[2] - self.ground_z


def _floats(text: str | None, default: str) -> np.ndarray:
    return np.array([float(v) for v in (text or default).split()])


def _origin(el: ET.Element | None) -> np.ndarray:
    """4x4 transform of a URDF <origin> element (missing = identity)."""
    xyz = _floats(el.get("xyz") if el is not None else None, "0 0 0")
    r, pch, y = _floats(el.get("rpy") if el is not None else None, "0 0 0")
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(pch), math.sin(pch), math.cos(y), math.sin(y)
    t = np.eye(4)
    # URDF rpy = fixed-axis roll about x, then pitch about y, then yaw about z: R = Rz Ry Rx
    t[:3, :3] = [
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ]
    t[:3, 3] = xyz
    return t


def _geometry_extent(geom: ET.Element, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned bounds (lo, hi) in the base frame of one <geometry> placed at ``t``."""
    shape = geom[0]
    rot, centre = t[:3, :3], t[:3, 3]
    if shape.tag == "box":
        half = _floats(shape.get("size"), "0 0 0") / 2.0
        ext = np.abs(rot) @ half
    elif shape.tag == "cylinder":
        r, h = float(shape.get("radius")), float(shape.get("length")) / 2.0
        axis = rot[:, 2]
        ext = np.abs(axis) * h + r * np.sqrt(np.clip(1.0 - axis**2, 0.0, 1.0))
    elif shape.tag == "sphere":
        ext = np.full(3, float(shape.get("radius")))
    else:  # meshes are not used for collision in the cosim car
        raise ValueError(f"unsupported collision geometry <{shape.tag}> in car URDF")
    return centre - ext, centre + ext


def read_car_spec(urdf_path: str | Path | None = None) -> CarSpec:
    """Read a car's dimensions and masses from its URDF (default: the cosim car)."""
    path = Path(urdf_path) if urdf_path is not None else car_urdf_path()
    root = ET.parse(path).getroot()
    links = {el.get("name"): el for el in root.findall("link")}
    joints = {el.get("name"): el for el in root.findall("joint")}
    child_of = {el.find("child").get("link"): el for el in joints.values()}
    base = next(name for name in links if name not in child_of)

    # link poses in the base frame at zero joint angles
    poses: dict[str, np.ndarray] = {}

    def pose(name: str) -> np.ndarray:
        if name not in poses:
            j = child_of.get(name)
            poses[name] = np.eye(4) if j is None else pose(j.find("parent").get("link")) @ _origin(j.find("origin"))
        return poses[name]

    mass, moment = 0.0, np.zeros(3)
    body_lo, body_hi = np.full(3, np.inf), np.full(3, -np.inf)  # the base link's (body's) collision
    ground = np.inf  # lowest collision point of any link (the tyre bottoms)
    for name, el in links.items():
        t = pose(name)
        inertial = el.find("inertial")
        if inertial is not None:
            m = float(inertial.find("mass").get("value"))
            mass += m
            moment += m * (t @ _origin(inertial.find("origin")))[:3, 3]
        for col in el.findall("collision"):
            a, b = _geometry_extent(col.find("geometry"), t @ _origin(col.find("origin")))
            ground = min(ground, float(a[2]))
            if name == base:
                body_lo, body_hi = np.minimum(body_lo, a), np.maximum(body_hi, b)

    def wheel_link(joint: str) -> str:
        return joints[joint].find("child").get("link")

    centres = {j: pose(wheel_link(j))[:3, 3] for j in WHEEL_JOINTS}
    fl, fr, rl, rr = (centres[j] for j in WHEEL_JOINTS)
    wheel = links[wheel_link(WHEEL_JOINTS[0])]
    tyre = wheel.find("collision/geometry")[0]  # sphere or cylinder of the tyre's radius
    tread = next((v.find("geometry/cylinder") for v in wheel.findall("visual")
                  if v.find("geometry/cylinder") is not None
                  and float(v.find("geometry/cylinder").get("radius")) == float(tyre.get("radius"))), None)
    width = float(tread.get("length")) if tread is not None else float(tyre.get("length", 2 * float(tyre.get("radius"))))
    wheel_inertial = wheel.find("inertial/mass")
    limit = joints[STEER_JOINTS[0]].find("limit")
    contact = links[wheel_link(WHEEL_JOINTS[0])].find("contact")

    def contact_value(tag: str, default: float) -> float:
        el = contact.find(tag) if contact is not None else None
        return float(el.get("value")) if el is not None else default

    front_x, rear_x = (fl[0] + fr[0]) / 2.0, (rl[0] + rr[0]) / 2.0
    return CarSpec(
        urdf_path=path.resolve(),
        length=float(body_hi[0] - body_lo[0]),
        width=float(body_hi[1] - body_lo[1]),
        height=float(body_hi[2] - ground),
        ground_z=float(ground),
        front_overhang=float(body_hi[0] - front_x),
        rear_overhang=float(rear_x - body_lo[0]),
        wheelbase=float(front_x - rear_x),
        track=float(fl[1] - fr[1]),
        front_axle_x=float(front_x),
        rear_axle_x=float(rear_x),
        mass=mass,
        com=tuple(float(v) for v in moment / mass),
        wheel_radius=float(tyre.get("radius")),
        wheel_width=width,
        wheel_mass=float(wheel_inertial.get("value")),
        max_steer=min(abs(float(limit.get("lower"))), abs(float(limit.get("upper")))),
        steer_rate=float(limit.get("velocity")),
        tyre_friction=contact_value("lateral_friction", 1.0),
        tyre_rolling_friction=contact_value("rolling_friction", 0.0),
        tyre_spinning_friction=contact_value("spinning_friction", 0.0),
        tyre_stiffness=contact_value("stiffness", 0.0),
        tyre_damping=contact_value("damping", 0.0),
        wheel_positions=tuple(tuple(float(v) for v in centres[j]) for j in WHEEL_JOINTS),
    )


# --- the cosim car, read from models/car/car.urdf ------------------------------------------
SPEC = read_car_spec()
LENGTH = SPEC.length
WIDTH = SPEC.width
HEIGHT = SPEC.height
WHEELBASE = SPEC.wheelbase
TRACK = SPEC.track
MASS = SPEC.mass
WHEEL_RADIUS = SPEC.wheel_radius
COM_HEIGHT = SPEC.com_height
MAX_STEER = SPEC.max_steer  # inner road-wheel lock, rad
STEER_RATE = SPEC.steer_rate  # rad/s at the road wheels


def min_turn_radius(spec: CarSpec = SPEC) -> float:
    """Radius (m) of the rear-axle centre's circle at full lock (inner wheel at its limit)."""
    return spec.wheelbase / math.tan(spec.max_steer) + spec.track / 2.0


# --- drivetrain, brakes, resistances (not expressible in URDF; see models/car/README.md) ---
GRAVITY = 9.81  # m/s^2
MAX_WHEEL_TORQUE = 3000.0  # N m, total at the driven wheels (~250 N m engine x 13.5:1 in 1st x 0.9)
MAX_POWER = 75_000.0  # W at the wheels (~100 hp)
TOP_SPEED = 50.0  # m/s, governed: the drive torque fades to zero over GOVERNOR_BAND below it
REVERSE_SPEED = 8.0  # m/s, governed top speed in reverse
GOVERNOR_BAND = 1.0  # m/s
COAST_TORQUE = 25.0  # N m per driven wheel: engine braking with both pedals released
MAX_BRAKE_TORQUE = 4300.0  # N m, all four wheels (~0.9 g on mu = 1)
BRAKE_FRONT_SHARE = 0.7  # fraction of the brake torque on the front axle
ROLLING_RESISTANCE = 0.012  # Crr: a force Crr * Fz against each loaded wheel's rolling
DRAG_AREA = 0.66  # Cd * A, m^2 (Cd 0.30, frontal area 2.2 m^2)
AIR_DENSITY = 1.225  # kg/m^3

# --- suspension (per corner; see models/car/README.md) ------------------------------------
SUSPENSION_STIFFNESS = 35_000.0  # N/m wheel rate: ~1.5 Hz ride frequency, ~0.1 m static deflection
SUSPENSION_DAMPING = 3_500.0  # N s/m: ~0.5 of critical
SUSPENSION_BUMP_TRAVEL = 0.10  # m the wheel can rise above its design (static) position
# (rebound: the wheel droops below its design position until the spring is unloaded, i.e. by
# its static deflection, ~0.10-0.11 m, so the total travel is ~0.21 m)
BUMP_STOP_STIFFNESS = 350_000.0  # N/m beyond the bump travel
# anti-roll bars (front, rear): N/m of the left-right compression difference, on each wheel of the axle
ANTI_ROLL_STIFFNESS = (20_000.0, 10_000.0)

# --- tyres ----------------------------------------------------------------------------------
CORNERING_STIFFNESS = 17.0  # lateral force per unit load per rad of slip (C_alpha / Fz)
RELAXATION_LENGTH = 0.5  # m rolled for the lateral force to build up (also the standstill tyre spring)
LOW_SPEED_DAMPING = 0.5  # damping ratio of the tyre spring, fading out over LOW_SPEED_DAMPING_SPEED
LOW_SPEED_DAMPING_SPEED = 3.0  # m/s
LOAD_SENSITIVITY = 0.2  # mu falls by this fraction of itself per nominal load (m g / 4) of extra load
HOLD_SPEED = 0.5  # m/s: below it a braked wheel grips the road like a spring (static friction)
HOLD_DAMPING = 0.7  # damping ratio of that spring

_TWO_PI = 2.0 * math.pi
SPAWN_CLEARANCE = 0.03  # m dropped onto the ground when spawned / reset
LIFT_MIN_STEP_M = 0.1   # lift_out: ground this far above the car's footprint puts the car on top of it
LIFT_REACH_M = 1.0      # lift_out: rays from this far above the footprint (under any bridge deck)
# The chassis' collision group: the wheel rays skip it (a ray from inside the body never hits
# the body). The chassis still collides with everything (its mask is all groups).
CHASSIS_COLLISION_GROUP = 1 << 6

RECOMMENDED_PHYSICS_HZ = 100  # substeps per simulated second: the issue asks for 100 Hz or more (see models/car/README.md)
RECOMMENDED_SOLVER_ITERATIONS = 20
# Bullet keeps a contact point until its bodies separate by this much (default 0.02 m). Only
# the chassis touches anything through Bullet contacts now (crashes, bottoming out).
CONTACT_BREAKING_THRESHOLD = 0.001

# legacy (the joint-motor model before the raycast wheels); kept for code that imports them
MAX_JOINT_VELOCITY = 250.0  # rad/s, still set on the body so the visual wheel joints may spin
STEER_MAX_TORQUE = 5000.0
STEER_POSITION_GAIN = 1.0
HOLD_SPIN = HOLD_SPEED / SPEC.wheel_radius  # rad/s
HOLD_POSITION_GAIN = 0.02


def configure_physics(client: int, hz: float = RECOMMENDED_PHYSICS_HZ,
                      solver_iterations: int = RECOMMENDED_SOLVER_ITERATIONS,
                      contact_breaking_threshold: float = CONTACT_BREAKING_THRESHOLD) -> None:
    """Set the fixed time step, solver iterations and contact threshold the car is validated at."""
    p.setPhysicsEngineParameter(fixedTimeStep=1.0 / hz, numSubSteps=0,
                                numSolverIterations=int(solver_iterations),
                                contactBreakingThreshold=contact_breaking_threshold,
                                physicsClientId=client)


def set_asphalt_friction(client: int, body_id: int, link: int = -1) -> None:
    """Give a road/ground body dry-asphalt friction (lateral 1.0, no rolling/spinning).

    The raycast tyres do not use it (their grip is the tyre's own ``mu``); it matters for the
    chassis touching that body (scraping, crashes).
    """
    p.changeDynamics(body_id, link, lateralFriction=1.0, rollingFriction=0.0,
                     spinningFriction=0.0, restitution=0.0, physicsClientId=client)


@dataclass(slots=True)
class VehicleState:
    """Kinematic state of the car's reference point (footprint centre at ground level)."""

    x: float
    y: float
    z: float
    roll: float
    pitch: float
    yaw: float  # rad, 0 = +x (east), counter-clockwise positive
    speed: float  # m/s along the heading, negative when reversing
    velocity: tuple[float, float, float]  # m/s, world frame, of the reference point
    yaw_rate: float  # rad/s, counter-clockwise positive
    steer: float  # rad, effective (bicycle-model) road-wheel angle, left positive
    wheel_contact: tuple[bool, bool, bool, bool]  # FL, FR, RL, RR: the wheel's ray hit in the last substep


def ackermann_angles(steer: float, spec: CarSpec = SPEC) -> tuple[float, float]:
    """Road-wheel angles (left, right) in rad for a normalised steer in [-1, 1].

    ``steer`` is the path curvature as a fraction of the tightest one: the rear-axle centre
    follows a circle of radius ``R = min_turn_radius / |steer|``; the inner wheel steers to
    ``atan(L / (R - t/2))`` and the outer one to ``atan(L / (R + t/2))``.
    """
    s = max(-1.0, min(1.0, float(steer)))
    if s == 0.0:
        return 0.0, 0.0
    radius = min_turn_radius(spec) / abs(s)
    half = spec.track / 2.0
    inner = math.atan(spec.wheelbase / (radius - half))
    outer = math.atan(spec.wheelbase / (radius + half))
    return (inner, outer) if s > 0 else (-outer, -inner)


def _effective_steer(left: float, right: float, spec: CarSpec) -> float:
    """Bicycle-model angle whose curvature is the mean of the two wheels' curvatures."""
    half = spec.track / 2.0
    kappa = 0.0
    for delta, side in ((left, 1.0), (right, -1.0)):
        t = math.tan(delta)
        kappa += t / (spec.wheelbase + side * half * t)  # 1/R of the rear-axle centre
    return math.atan(spec.wheelbase * kappa / 2.0)


def time_step(client: int) -> float:
    """The client's fixed physics time step (s): one ``stepSimulation`` advances this much."""
    return float(p.getPhysicsEngineParameters(physicsClientId=client)["fixedTimeStep"])


class EgoVehicle:
    """The ego car in a PyBullet client: a rigid chassis on four raycast wheels.

    ``position`` is the point on the ground under the car's footprint centre; the car is
    dropped from ``SPAWN_CLEARANCE`` above it. Drive it with :meth:`apply_control` (it only
    stores the command) and advance physics with :meth:`step` (``n`` substeps of the client's
    time step: wheel forces, then ``stepSimulation``, each substep). A loop that steps the
    world itself calls :meth:`substep` right before every ``stepSimulation`` instead, and
    :meth:`sync_visuals` before rendering. :meth:`state` reads the car back.
    """

    def __init__(self, client: int, urdf_path: str | Path | None = None,
                 position: tuple[float, float, float] = (0.0, 0.0, 0.0), yaw: float = 0.0):
        self.client = cid = int(client)
        self.spec = sp = SPEC if urdf_path is None else read_car_spec(urdf_path)
        self.body_id = body = p.loadURDF(str(sp.urdf_path), basePosition=list(position),
                                         flags=p.URDF_USE_INERTIA_FROM_FILE | p.URDF_USE_IMPLICIT_CYLINDER,
                                         physicsClientId=cid)
        n = p.getNumJoints(body, physicsClientId=cid)
        index = {p.getJointInfo(body, j, physicsClientId=cid)[1].decode(): j for j in range(n)}
        self.steer_joints = [index[name] for name in STEER_JOINTS]
        self.wheel_joints = [index[name] for name in WHEEL_JOINTS]  # link index == joint index
        self._visual_joints = self.steer_joints + self.wheel_joints
        info = p.getDynamicsInfo(body, -1, physicsClientId=cid)
        # base inertial frame (what Bullet calls the base position) in the base link frame
        self._com_local = tuple(float(v) for v in info[3])
        if max(abs(v) for v in p.getEulerFromQuaternion(info[4])) > 1e-9:
            raise ValueError(f"{sp.urdf_path}: the base link's <inertial> origin must not be rotated")

        # Only the chassis touches the world through Bullet: the wheel links collide with
        # nothing (the rays carry the car), and the rays skip the chassis' collision group.
        for j in range(n):
            p.setCollisionFilterGroupMask(body, j, 0, 0, physicsClientId=cid)
        p.setCollisionFilterGroupMask(body, -1, CHASSIS_COLLISION_GROUP, -1, physicsClientId=cid)
        self._ray_mask = -1 ^ CHASSIS_COLLISION_GROUP
        # aerodynamic drag as Bullet's multibody damping: m d v (1 + |v|) with d = rho CdA / 2m
        p.changeDynamics(body, -1, linearDamping=0.5 * AIR_DENSITY * DRAG_AREA / sp.mass,
                         angularDamping=0.0, maxJointVelocity=MAX_JOINT_VELOCITY, physicsClientId=cid)
        # release Bullet's default joint motors: the joints only show the wheels' steer and spin
        p.setJointMotorControlArray(body, list(range(n)), p.VELOCITY_CONTROL,
                                    targetVelocities=[0.0] * n, forces=[0.0] * n, physicsClientId=cid)

        # --- suspension geometry (base inertial frame) and static loads ---------------------
        r = sp.wheel_radius
        com = sp.com  # of the whole car: what the four springs carry
        front_share = (com[0] - sp.rear_axle_x) / sp.wheelbase
        left_share = 0.5 + com[1] / sp.track
        share = (front_share * left_share, front_share * (1.0 - left_share),
                 (1.0 - front_share) * left_share, (1.0 - front_share) * (1.0 - left_share))
        # spring force at the design position (N): the car rests with its wheels exactly there
        self._preload = tuple(s * sp.mass * GRAVITY for s in share)
        # the wheel droops until its spring is unloaded (its static deflection)
        self._droop = tuple(f / SUSPENSION_STIFFNESS for f in self._preload)
        cx, cy, cz = self._com_local
        # ray origins: the wheel centres raised by the bump travel, relative to the base inertial frame
        self._mount = tuple((x - cx, y - cy, z + SUSPENSION_BUMP_TRAVEL - cz)
                            for x, y, z in sp.wheel_positions)
        self._ray_len = tuple(SUSPENSION_BUMP_TRAVEL + d + r for d in self._droop)
        self._full = (SUSPENSION_BUMP_TRAVEL + r,) * 4  # compression = full - hit distance
        self._bar_front, self._bar_rear = ANTI_ROLL_STIFFNESS
        half = MAX_BRAKE_TORQUE / 2.0
        self._brake_force = (half * BRAKE_FRONT_SHARE / r,) * 2 + (half * (1.0 - BRAKE_FRONT_SHARE) / r,) * 2  # N
        self._coast_force = (0.0, 0.0, COAST_TORQUE / r, COAST_TORQUE / r)
        self._radius = r
        self._mu = sp.tyre_friction
        self._inv_nominal_load = 4.0 / (sp.mass * GRAVITY)
        self._spring_per_load = CORNERING_STIFFNESS / RELAXATION_LENGTH  # standstill tyre spring, N/m per N
        # critical damping of that spring on the wheel's share of the mass, N s/m per N of load
        critical = 2.0 * math.sqrt(CORNERING_STIFFNESS / (RELAXATION_LENGTH * GRAVITY))
        self._low_damping = LOW_SPEED_DAMPING * critical
        self._hold_damping = HOLD_DAMPING * critical
        self._steer_rate = sp.steer_rate
        self._r_min = min_turn_radius(sp)
        self._wheelbase, self._half_track = sp.wheelbase, sp.track / 2.0
        self._dt = time_step(cid)
        self._set_steer_angles(0.0, 0.0)
        self._spin_angle = [0.0] * 4
        self.throttle = self.brake = self.steer = 0.0
        self.reverse = False
        self._goal = (0.0, 0.0)
        self.reset(position, yaw)

    # --- placement ---------------------------------------------------------------------------
    def reset(self, position: tuple[float, float, float], yaw: float = 0.0, *,
              pitch: float = 0.0, roll: float = 0.0) -> None:
        """Teleport the car at rest, wheels straight, pedals released, onto ``position``."""
        self.apply_control(0.0, 0.0, 0.0)
        self.set_pose_velocity(position, yaw, speed=0.0, pitch=pitch, roll=roll, steer_angles=(0.0, 0.0))

    def place_on_ground(self, x: float, y: float, yaw: float, z_hint: float, reach: float = 3.0) -> tuple:
        """Put the car at rest on the surface under x/y (heading ``yaw``), tilted to it.

        One ray per wheel and one at the centre, from ``reach`` above ``z_hint`` (the ground
        model's height there) to ``reach`` below, skipping the car itself; a plane fitted to
        the hits gives the height under the footprint centre, the pitch and the roll. (Placed
        level on a 9 % Monaco street, the rear of the body started 0.15 m inside the road and
        the car reared up.) Returns (z, pitch, roll); with fewer than three hits, (z_hint, 0,
        0) and the car level."""
        fit = self._ground_plane(x, y, yaw, z_hint + reach, z_hint - reach)
        z, pitch, roll = fit if fit is not None else (z_hint, 0.0, 0.0)
        self.reset((x, y, z), yaw, pitch=pitch, roll=roll)
        return z, pitch, roll

    def lift_out(self, min_step: float = LIFT_MIN_STEP_M, reach: float = LIFT_REACH_M) -> float:
        """Put the car back on top of the ground when the ground under it came up: a newer
        build's tile replaced the one it drove on, and its road there is higher (Portland,
        seed 35: 0.36 m, the body inside the new asphalt and pressed down onto the terrain, the
        car stood for the rest of the run). One ray per wheel and one at the centre, from
        ``reach`` above the car's footprint down to below it; when the plane fitted to the hits
        is more than ``min_step`` above the footprint, the car is set onto it with its speed,
        yaw rate and steering. Returns the rise (m; 0 when the car stays where it is)."""
        st = self.state()
        fit = self._ground_plane(st.x, st.y, st.yaw, st.z + reach, st.z - reach)
        if fit is None:
            return 0.0
        z, pitch, roll = fit
        rise = z - st.z
        if rise <= min_step:
            return 0.0
        self.set_pose_velocity((st.x, st.y, z), st.yaw, speed=st.speed, yaw_rate=st.yaw_rate,
                               pitch=pitch, roll=roll)
        return rise

    def _ground_plane(self, x: float, y: float, yaw: float, z_top: float, z_bottom: float) -> tuple | None:
        """The surface under the car's footprint at x/y (heading ``yaw``): one ray per wheel
        and one at the centre, from ``z_top`` down to ``z_bottom``, skipping the car itself; a
        plane fitted to the hits gives (z under the footprint centre, pitch, roll). None with
        fewer than three hits."""
        c, s = math.cos(yaw), math.sin(yaw)
        uv = [(wx, wy) for wx, wy, _ in self.spec.wheel_positions] + [(0.0, 0.0)]
        starts, ends = [], []
        for u, v in uv:
            px, py = x + c * u - s * v, y + s * u + c * v
            starts.append((px, py, z_top))
            ends.append((px, py, z_bottom))
        hits = p.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=self._ray_mask,
                              physicsClientId=self.client)
        rows = [(1.0, u, v, h[3][2]) for (u, v), h in zip(uv, hits) if h[0] >= 0]
        if len(rows) < 3:
            return None
        A = np.array([r[:3] for r in rows])
        z, b, cc = np.linalg.lstsq(A, np.array([r[3] for r in rows]), rcond=None)[0]
        # (pitch > 0 is nose down, roll > 0 left side up: see the module doc)
        return float(z), -math.atan(float(b)), math.atan(float(cc))

    def set_pose_velocity(self, position: tuple[float, float, float], yaw: float, speed: float = 0.0,
                          yaw_rate: float = 0.0, *, pitch: float = 0.0, roll: float = 0.0,
                          clearance: float = SPAWN_CLEARANCE,
                          steer_angles: tuple[float, float] | None = None) -> None:
        """Teleport the car with a forward ``speed`` (m/s) and ``yaw_rate`` (rad/s).

        ``position`` is the ground point under the footprint centre; the car is placed
        ``clearance`` above it with its wheels at their design (resting) positions. The wheels
        get the matching rolling spin and relaxed tyres; the steering keeps its angles unless
        ``steer_angles`` (left, right, rad) is given. ``wheel_contact`` reads all False until
        the next substep casts the rays.
        """
        cid = self.client
        orn = p.getQuaternionFromEuler((roll, pitch, yaw))
        rot = np.array(p.getMatrixFromQuaternion(orn)).reshape(3, 3)
        ref = np.array(position, dtype=float) + (0.0, 0.0, clearance)
        com_offset = rot @ np.array(self._com_local)
        omega = np.array([0.0, 0.0, yaw_rate])
        p.resetBasePositionAndOrientation(self.body_id, (ref + com_offset).tolist(), orn, physicsClientId=cid)
        v = speed * rot[:, 0] + np.cross(omega, com_offset)
        p.resetBaseVelocity(self.body_id, v.tolist(), omega.tolist(), physicsClientId=cid)
        if steer_angles is not None:
            self._set_steer_angles(float(steer_angles[0]), float(steer_angles[1]))
        self._lateral = [0.0] * 4  # tyre lateral deflection, m
        self._anchor = [0.0] * 4  # braked tyre's longitudinal deflection, m
        self._spin = [speed / self._radius] * 4  # rad/s, rolling without slip (visual)
        self._load = [0.0] * 4
        self._compression = [0.0] * 4
        self._contact = (False, False, False, False)
        self.sync_visuals()

    # --- control -----------------------------------------------------------------------------
    def apply_control(self, throttle: float, brake: float, steer: float, reverse: bool = False) -> None:
        """Set the pedals (0..1) and the steering (-1..1, > 0 = left); ``reverse`` selects R.

        The command holds until the next call; the brake overrides the throttle. Nothing is
        sent to Bullet here: the wheel forces follow from it in every substep.
        """
        throttle = 0.0 if throttle <= 0.0 else (1.0 if throttle >= 1.0 else float(throttle))
        brake = 0.0 if brake <= 0.0 else (1.0 if brake >= 1.0 else float(brake))
        steer = -1.0 if steer <= -1.0 else (1.0 if steer >= 1.0 else float(steer))
        self.throttle, self.brake, self.steer, self.reverse = throttle, brake, steer, bool(reverse)
        if steer == 0.0:
            self._goal = (0.0, 0.0)
        else:
            radius = self._r_min / abs(steer)  # ackermann_angles(), inlined for speed
            inner = math.atan(self._wheelbase / (radius - self._half_track))
            outer = math.atan(self._wheelbase / (radius + self._half_track))
            self._goal = (inner, outer) if steer > 0.0 else (-outer, -inner)

    # --- physics -------------------------------------------------------------------------------
    def step(self, n_substeps: int = 1) -> None:
        """Advance the world by ``n_substeps`` physics steps of the client's time step.

        Each substep casts the wheel rays, applies the suspension and tyre forces and calls
        ``stepSimulation`` once; the wheel joints are posed for rendering at the end. The time
        step is read from the client at every call (``configure_physics`` or ``setTimeStep``).
        At 100 Hz one SUMO step of 0.1 s is ``step(10)``.
        """
        cid = self.client
        self._dt = time_step(cid)
        for _ in range(int(n_substeps)):
            self.substep()
            p.stepSimulation(physicsClientId=cid)
        self.sync_visuals()

    def advance(self, duration: float) -> int:
        """Advance by ``duration`` seconds (a whole number of time steps); returns the substeps."""
        self._dt = time_step(self.client)
        n = round(duration / self._dt)
        if n < 1 or abs(n * self._dt - duration) > 1e-6 * max(1.0, duration):
            raise ValueError(f"{duration} s is not a whole number of {self._dt} s physics steps")
        self.step(n)
        return n

    def substep(self, dt: float | None = None) -> None:
        """Apply the wheel forces for the next ``stepSimulation`` (whose step is ``dt``).

        Bullet clears external forces after every ``stepSimulation``, so this must run before
        each one. ``dt`` defaults to the time step read at construction or at the last
        :meth:`step` / :meth:`advance`. Costs one ``getBasePositionAndOrientation``, one
        ``getBaseVelocity``, one ``rayTestBatch`` and one force plus one torque; the four wheels
        are plain float arithmetic (faster than numpy on arrays of four).
        """
        h = self._dt if dt is None else float(dt)
        cid, body = self.client, self.body_id
        sqrt = math.sqrt

        # steering: both road wheels move toward their Ackermann goal at the rate limit, arriving together
        (left, right), (goal_l, goal_r) = self._steer_angles, self._goal
        if left != goal_l or right != goal_r:
            dl, dr = goal_l - left, goal_r - right
            longest = max(abs(dl), abs(dr))
            reach = self._steer_rate * h
            if longest <= reach:
                left, right = goal_l, goal_r
            else:
                left, right = left + dl * reach / longest, right + dr * reach / longest
            self._set_steer_angles(left, right)

        (px, py, pz), orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        (lx, ly, lz), (wx, wy, wz) = p.getBaseVelocity(body, physicsClientId=cid)
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = p.getMatrixFromQuaternion(orn)
        # one ray per wheel from the suspension top along the chassis' -z, skipping the chassis
        starts, ends, arms = [], [], []
        for (mx, my, mz), length in zip(self._mount, self._ray_len):
            ax, ay, az = r00 * mx + r01 * my + r02 * mz, r10 * mx + r11 * my + r12 * mz, r20 * mx + r21 * my + r22 * mz
            arms.append((ax, ay, az))
            starts.append((px + ax, py + ay, pz + az))
            ends.append((px + ax - length * r02, py + ay - length * r12, pz + az - length * r22))
        hits = p.rayTestBatch(starts, ends, numThreads=1, collisionFilterMask=self._ray_mask, physicsClientId=cid)

        # suspension compression (m above the design position; -droop when the ray misses)
        comp = [full - (hit[2] if hit[0] >= 0 else 1.0) * length
                for hit, full, length in zip(hits, self._full, self._ray_len)]
        bar_f, bar_r = self._bar_front * (comp[0] - comp[1]), self._bar_rear * (comp[2] - comp[3])
        bars = (bar_f, -bar_f, bar_r, -bar_r)

        # per wheel: normal load, ground frame (forward u, side s, normal n), contact point velocity
        wheels = []
        for i in range(4):
            hit = hits[i]
            if hit[0] < 0:
                wheels.append(None)
                continue
            c = comp[i]
            d = hit[2] * self._ray_len[i]
            ax, ay, az = arms[i]  # the contact point relative to the centre of mass
            ax, ay, az = ax - d * r02, ay - d * r12, az - d * r22
            nx, ny, nz = hit[4]
            vx, vy, vz = lx + wy * az - wz * ay, ly + wz * ax - wx * az, lz + wx * ay - wy * ax
            spring = self._preload[i] + SUSPENSION_STIFFNESS * c + bars[i]
            if c > SUSPENSION_BUMP_TRAVEL:
                spring += BUMP_STOP_STIFFNESS * (c - SUSPENSION_BUMP_TRAVEL)
            load = spring - SUSPENSION_DAMPING * (vx * nx + vy * ny + vz * nz)
            if load < 0.0:
                load = 0.0
            cs, sn = self._heading[i]  # the wheel's heading in the chassis, projected onto the road
            ux, uy, uz = cs * r00 + sn * r01, cs * r10 + sn * r11, cs * r20 + sn * r21
            k = ux * nx + uy * ny + uz * nz
            ux, uy, uz = ux - k * nx, uy - k * ny, uz - k * nz
            k = 1.0 / max(sqrt(ux * ux + uy * uy + uz * uz), 1e-9)
            ux, uy, uz = ux * k, uy * k, uz * k
            sx, sy, sz = ny * uz - nz * uy, nz * ux - nx * uz, nx * uy - ny * ux  # n x u: to the left
            wheels.append((load, ax, ay, az, nx, ny, nz, ux, uy, uz, sx, sy, sz,
                           vx * ux + vy * uy + vz * uz, vx * sx + vy * sy + vz * sz))

        # drive: the throttle's torque, split equally between the rear wheels (open differential)
        throttle, brake = self.throttle, self.brake
        r = self._radius
        drive = 0.0
        if throttle > 0.0 and brake == 0.0:
            rear = [w[13] for w in wheels[2:] if w is not None]
            v_drive = sum(rear) / len(rear) if rear else 0.0
            sign = -1.0 if self.reverse else 1.0
            top = REVERSE_SPEED if self.reverse else TOP_SPEED
            governor = min(max((top - sign * v_drive) / GOVERNOR_BAND, 0.0), 1.0)
            torque = throttle * governor * min(MAX_WHEEL_TORQUE, MAX_POWER * r / max(abs(v_drive), 1e-3))
            drive = sign * torque / (2.0 * r)

        mu, sigma = self._mu, RELAXATION_LENGTH
        lateral, anchor, spin, loads = self._lateral, self._anchor, self._spin, self._load
        # the tyre springs/dampers act on the wheel's share of the mass (load / g) through explicit
        # forces: keep them stable at coarse steps (c h / m <= 0.6, k h^2 / m <= 0.5)
        damping_cap = 0.6 / (GRAVITY * h)  # N s/m per N of load
        spring_cap = 0.5 / (GRAVITY * h * h)  # N/m per N of load
        if sigma * spring_cap < CORNERING_STIFFNESS:  # the rolling tyre's spring too (below ~28 Hz)
            sigma = CORNERING_STIFFNESS / spring_cap
        contact = []
        force_x = force_y = force_z = torque_x = torque_y = torque_z = 0.0
        for i in range(4):
            w = wheels[i]
            if w is None:
                lateral[i] = anchor[i] = loads[i] = 0.0
                contact.append(False)
                continue
            contact.append(True)
            load, ax, ay, az, nx, ny, nz, ux, uy, uz, sx, sy, sz, vx, vy = w
            loads[i] = load
            spin[i] = vx / r
            avx = abs(vx)
            # grip falls with load (tyre load sensitivity): the more loaded axle saturates first
            mu_i = mu * (1.0 - LOAD_SENSITIVITY * (load * self._inv_nominal_load - 1.0))
            if mu_i < 0.5 * mu:
                mu_i = 0.5 * mu
            # lateral: the tyre deflection y relaxes over sigma of rolling (exact exponential
            # update of dy/dt = vy - |vx| y / sigma); the slip y / sigma gives a brush-model force
            a = avx * h / sigma
            if a > 1e-9:
                decay = math.exp(-a)
                y = lateral[i] * decay + vy * (1.0 - decay) * sigma / avx
            else:
                y = lateral[i] + vy * h
            slide = 3.0 * mu_i / CORNERING_STIFFNESS  # tan(slip angle) of full sliding
            slip = y / sigma
            slip = slide if slip > slide else (-slide if slip < -slide else slip)
            lateral[i] = slip * sigma
            x = abs(slip) * CORNERING_STIFFNESS / mu_i
            f_side = mu_i * load * (x - x * x / 3.0 + x * x * x / 27.0)
            if slip > 0.0:
                f_side = -f_side
            if avx < LOW_SPEED_DAMPING_SPEED:  # damp the standstill tyre spring
                f_side -= min(self._low_damping, damping_cap) * load * (1.0 - avx / LOW_SPEED_DAMPING_SPEED) * vy
            # longitudinal: brakes and rolling resistance oppose the rolling without reversing it
            resist = self._brake_force[i] * brake + ROLLING_RESISTANCE * load
            if brake > 0.0 and avx < HOLD_SPEED:
                # static friction: a stiff tyre spring anchored where the braked wheel stopped,
                # sliding when the brake cannot hold it
                k = min(self._spring_per_load, spring_cap) * load
                bound = resist / k if k > 0.0 else 0.0
                e = anchor[i] + vx * h
                e = bound if e > bound else (-bound if e < -bound else e)
                anchor[i] = e
                f_fwd = -k * e - min(self._hold_damping, damping_cap) * load * vx
                f_fwd = resist if f_fwd > resist else (-resist if f_fwd < -resist else f_fwd)
            else:
                anchor[i] = 0.0
                if brake == 0.0 and throttle == 0.0:
                    resist += self._coast_force[i]
                stop = 0.5 * load * avx / (GRAVITY * h)  # half of what stops the wheel's share in one step
                f_fwd = drive if i >= 2 else 0.0
                f_fwd -= (resist if resist < stop else stop) * (1.0 if vx > 0.0 else -1.0)
            # friction circle
            limit = mu_i * load
            mag = f_fwd * f_fwd + f_side * f_side
            if mag > limit * limit:
                k = limit / sqrt(mag)
                f_fwd *= k
                f_side *= k
            # the wheel's force at its contact point, summed into a force and a torque about the CoM
            ex = load * nx + f_fwd * ux + f_side * sx
            ey = load * ny + f_fwd * uy + f_side * sy
            ez = load * nz + f_fwd * uz + f_side * sz
            force_x += ex
            force_y += ey
            force_z += ez
            torque_x += ay * ez - az * ey
            torque_y += az * ex - ax * ez
            torque_z += ax * ey - ay * ex
        if contact[0] or contact[1] or contact[2] or contact[3]:
            # a force at the CoM (Bullet adds (point - CoM) x force, zero here) and the torque
            p.applyExternalForce(body, -1, (force_x, force_y, force_z), (px, py, pz), p.WORLD_FRAME,
                                 physicsClientId=cid)
            p.applyExternalTorque(body, -1, (torque_x, torque_y, torque_z), p.WORLD_FRAME, physicsClientId=cid)
        self._contact = tuple(contact)
        self._compression = comp
        angle = self._spin_angle
        for i in range(4):  # wheels in the air keep spinning as they were
            angle[i] = (angle[i] + spin[i] * h) % _TWO_PI

    def _set_steer_angles(self, left: float, right: float) -> None:
        self._steer_angles = (left, right)
        self._heading = ((math.cos(left), math.sin(left)), (math.cos(right), math.sin(right)), (1.0, 0.0), (1.0, 0.0))

    def sync_visuals(self) -> None:
        """Pose the steering and wheel-spin joints (for rendering; no effect on the dynamics)."""
        left, right = self._steer_angles
        a = self._spin_angle
        p.resetJointStatesMultiDof(self.body_id, self._visual_joints,
                                   [[left], [right], [a[0]], [a[1]], [a[2]], [a[3]]],
                                   targetVelocities=[[0.0]] * 6, physicsClientId=self.client)

    @property
    def time_step(self) -> float:
        """The physics step (s) the wheel model integrates over: read from the client at
        construction and at every :meth:`step` / :meth:`advance`."""
        return self._dt

    # --- sensing -----------------------------------------------------------------------------
    def state(self) -> VehicleState:
        cid, body = self.client, self.body_id
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=cid)
        lin, ang = p.getBaseVelocity(body, physicsClientId=cid)
        m = p.getMatrixFromQuaternion(orn)  # row-major 3x3
        cx, cy, cz = self._com_local
        off = (m[0] * cx + m[1] * cy + m[2] * cz,  # R @ com_local
               m[3] * cx + m[4] * cy + m[5] * cz,
               m[6] * cx + m[7] * cy + m[8] * cz)
        # velocity of the reference point = v_com - omega x off
        vel = (lin[0] - (ang[1] * off[2] - ang[2] * off[1]),
               lin[1] - (ang[2] * off[0] - ang[0] * off[2]),
               lin[2] - (ang[0] * off[1] - ang[1] * off[0]))
        roll, pitch, yaw = p.getEulerFromQuaternion(orn)
        left, right = self._steer_angles
        return VehicleState(
            x=pos[0] - off[0], y=pos[1] - off[1], z=pos[2] - off[2],
            roll=roll, pitch=pitch, yaw=yaw,
            speed=vel[0] * m[0] + vel[1] * m[3] + vel[2] * m[6],  # along the body x axis
            velocity=vel, yaw_rate=ang[2],
            steer=_effective_steer(left, right, self.spec),
            wheel_contact=self._contact,
        )

    def wheel_steer_angles(self) -> tuple[float, float]:
        """Road-wheel angles (left, right), rad, left positive."""
        return self._steer_angles

    def wheel_spin_rates(self) -> tuple[float, float, float, float]:
        """Wheel spin rates (FL, FR, RL, RR), rad/s, positive rolling forwards (rolling without slip)."""
        return tuple(float(v) for v in self._spin)

    def wheel_loads(self) -> tuple[float, float, float, float]:
        """Normal forces (FL, FR, RL, RR) the suspension applied in the last substep, N."""
        return tuple(float(v) for v in self._load)

    def suspension_compression(self) -> tuple[float, float, float, float]:
        """Wheel travel above the design (resting) position in the last substep, m (< 0: drooping)."""
        return tuple(float(v) for v in self._compression)

    def remove(self) -> None:
        p.removeBody(self.body_id, physicsClientId=self.client)
