"""Driving on real presets: scripted scenarios, asserting on telemetry and SUMO/PyBullet state.

The physics car is driven through its wheels by the autopilot (cosim.autopilot); every check
reads positions, speeds and states back from the simulation (the path geometry, SUMO's
vehicles, persons and lights, the telemetry rows), not from the autopilot's own beliefs.
Scenarios: a GPS goal across junctions (lane keeping, speed holding, arrival), a light forced
red and yellow through libsumo, a lead car (time gap, stopping behind it, lidar), a
pedestrian on a crossing, an OpenStreetMap stop sign (Portland), a steep Monaco street,
the lane speed limit, the Gymnasium-style env and a callback driver.

Worlds are built once per module (chunks=0: 1 km x 1 km); the wall-clock tile-loading budget
is lifted so that runs are reproducible."""
from __future__ import annotations

import json
import logging
import math
import re

import numpy as np
import pytest

from cosim.config import SimConfig
from cosim.sim import Simulation
from netgen.build import build_world
from netgen.config import WorldConfig
from netgen.errors import InputError

from conftest import shared_file

FRONT = 2.25                                   # m from the car's centre to its front bumper
# Central Helsinki (embedded preset): a route across six junctions (five with lights)
HEL_GOAL = (60.172335, 24.948216)
HEL_MID = (60.170763, 24.945623)               # on 17132580#1 (134 m), 125 m before a light
HEL_CROSSING_START = (60.172835, 24.943318)    # 117164342#1, 90 m before an unsignalised crossing
HEL_CROSSING_GOAL = (60.171993, 24.943379)
HEL_OFF_ROAD = (60.174039, 24.945603)          # 137 m from the nearest road for cars
# Portland: an approach with an OpenStreetMap stop sign (node 40639708) onto a minor link
PDX_START, PDX_GOAL = (45.530676, -122.694569), (45.531742, -122.694608)
# Monaco: 4229539 -> 4229537#0/#1: down about -25 %, then up about +19 % (SRTM terrain)
MC_START, MC_GOAL = (43.738822, 7.424690), (43.738369, 7.424390)
# Monaco: from Allée Guillaume Apollinaire (159170444) east to Avenue Princesse Grace (503462465#0)
MC_WEST, MC_PRINCESSE_GRACE = (43.735163, 7.419143), (43.741633, 7.430513)


@pytest.fixture(scope="module")
def helsinki(tmp_path_factory):
    out = tmp_path_factory.mktemp("drv") / "helsinki"
    build_world(WorldConfig(preset="helsinki", chunks=0, out=str(out), cache_dir=str(out.parent / "cache")))
    return str(out)


def shared_world(tmp_path_factory, name: str, osm: str, dem: str, center) -> str:
    """A one-chunk world built from an extract and a DEM of ``../shared/data`` (skipped,
    naming the file, where it is absent)."""
    osm, dem = shared_file(osm), shared_file(dem)
    out = tmp_path_factory.mktemp("drv") / name
    build_world(WorldConfig(osm=str(osm), dem=[str(dem)], center=center, chunks=0, out=str(out),
                            cache_dir=str(out.parent / "cache")))
    return str(out)


@pytest.fixture(scope="module")
def monaco(tmp_path_factory):
    return shared_world(tmp_path_factory, "monaco", "osm/monaco-2022.osm.pbf", "dem/N43E007.hgt", (43.7384, 7.4246))


def _portland_world(tmp_path_factory, name: str, center: tuple) -> str:
    """One chunk of Portland (OSM and NED from ../shared/data) around `center`."""
    return shared_world(tmp_path_factory, name, "osm/portland-central-2015.osm.pbf", "dem/portland-ned.tif", center)


@pytest.fixture(scope="module")
def portland(tmp_path_factory):
    return _portland_world(tmp_path_factory, "portland", (45.5310, -122.6990))


def start_sim(world, **kw) -> Simulation:
    kw.setdefault("traffic", "none")
    kw.setdefault("seed", 1)
    sim = Simulation(SimConfig(world_dir=world, **kw)).setup()
    sim.physics.load_budget_ms = 1e9           # tile loading independent of wall-clock time
    return sim


def drive_logged(world, tmp_path, before=None, **kw):
    """A run of ``start_sim(world, **kw)`` with telemetry: (its summary, the autopilot's stats,
    the telemetry rows). ``before(sim)``, if given, is called after the setup."""
    tel = tmp_path / "t.jsonl"
    sim = start_sim(world, telemetry=str(tel), **kw)
    try:
        if before is not None:
            before(sim)
        summary = sim.run()
        stats = sim.driver.stats
    finally:
        sim.teardown()
    return summary, stats, [json.loads(line) for line in tel.read_text().splitlines()]


def s_of(sim, x, y) -> tuple[float, float]:
    """Arc length and lateral offset of a point on the simulation's lane path."""
    _, s, off = sim.path.project(x, y, sim._path_idx)
    return float(s), float(off)


def ego_front_s(sim) -> float:
    st = sim.vehicle.state()
    return s_of(sim, st.x, st.y)[0] + FRONT


def tls_of_lane(sumo, lane: str) -> str:
    for tid in sumo.trafficlight.getIDList():
        for links in sumo.trafficlight.getControlledLinks(tid):
            if any(link[0] == lane for link in links):
                return tid
    raise AssertionError(f"no traffic light controls {lane}")


def force_tls(sim, tid: str, letter: str):
    n = len(sim.traffic.sumo.trafficlight.getRedYellowGreenState(tid))
    sim.traffic.set_tls_state(tid, letter * n)


def settled_cruise(rows, set_speed, hold_s=3.0, dt=0.1):
    """Indices where the autopilot's target has been the set speed for hold_s and the car had
    reached it (within 0.15 m/s) since: the samples a speed-holding claim is about."""
    out, ok, run = [], False, 0
    for i, r in enumerate(rows):
        if abs(r["target_speed_mps"] - set_speed) > 1e-6:
            ok, run = False, 0
            continue
        run += 1
        if not ok and abs(r["speed_mps"] - set_speed) < 0.15:
            ok = True
        if ok and run * dt >= hold_s:
            out.append(i)
    return out


# --------------------------------------------------------------------------------------------
def test_drives_to_gps_goal_in_lane_across_junctions(helsinki, tmp_path):
    tel = tmp_path / "goal.jsonl"
    sim = start_sim(helsinki, goal=HEL_GOAL, speed_mps=10.0, duration_s=150, telemetry=str(tel))
    try:
        info = dict(sim.snap_info)
        stops = list(sim.path.stops)
        summary = sim.run()
        st = sim.vehicle.state()
        goal_d = math.hypot(st.x - sim.goal_xy[0], st.y - sim.goal_xy[1])
        front = ego_front_s(sim)
        links = [l for stop in stops for l in sim.traffic.sumo.lane.getLinks(stop.lane) if l[0] == stop.to_lane]
    finally:
        sim.teardown()
    assert info["route_length_m"] > 300 and info["eta_s"] > 0 and info["goal_snap_m"] < 10
    assert summary.arrived, summary.line()
    # the route's length is the drive's, from the car to the goal (SUMO's counts its first and
    # last roads whole: 503 m for this drive of 450), and the ETA is at most the set speed
    assert abs(info["route_length_m"] - summary.distance_m) < 0.02 * summary.distance_m + 5.0, \
        (info, summary.distance_m)
    assert info["route_length_m"] / 10.0 <= info["eta_s"] <= sim.t, (info, sim.t)
    assert goal_d < 10.0
    assert sum(1 for stop in stops if stop.s < front) >= 5          # junctions crossed
    assert all(l[6] != "t" for l in links)                           # no U-turn in the lane plan
    rows = [json.loads(l) for l in tel.read_text().splitlines()]
    moving = np.array([abs(r["lateral_offset_m"]) for r in rows if r["speed_mps"] > 2.0])
    assert len(moving) > 200
    assert np.percentile(moving, 99) <= 0.5 and moving.max() < 1.0, (np.percentile(moving, 99), moving.max())
    assert all(r["on_road"] for r in rows)
    assert summary.ego_collisions == 0
    # constant speed on the flat: within 0.3 m/s of the set speed once reached
    held = settled_cruise(rows, 10.0)
    assert len(held) >= 50
    err = np.array([rows[i]["speed_mps"] - 10.0 for i in held])
    assert np.abs(err).max() <= 0.3, np.abs(err).max()


@pytest.fixture(scope="module")
def kouvola(tmp_path_factory):
    out = tmp_path_factory.mktemp("drv") / "kouvola"
    build_world(WorldConfig(preset="kouvola", chunks=0, out=str(out), cache_dir=str(out.parent / "cache")))
    return str(out)


def test_a_start_facing_a_dead_end_turns_round_to_the_goal(kouvola):
    """Kouvola: a start on -369217777#0, which runs 234 m into a cul-de-sac, with the goal
    behind it (on 369217777#1). From that lane the route takes the dead end's U-turn, which
    the car cannot make: it drove 453 m, into a building at the turn (twice), and arrived
    after 68 s. The car now starts on the road's other direction, which leads to the goal."""
    sim = start_sim(kouvola, start=(60.530104, 26.945745), goal=(60.529146, 26.945554), speed_mps=10.0,
                    duration_s=60)
    try:
        # (from the snapped lane SUMO's route turns round, and no route the car can drive
        # without turning leads to the goal: the one planned from there turns round in moves at
        # the dead end, 234 m on; the road's other direction needs no turn)
        fastest = sim.traffic.sumo.simulation.findRoute("-369217777#0", "369217777#1", vType="DEFAULT_VEHTYPE").edges
        assert "-369217777#0" in fastest and "369217777#0" in fastest, fastest
        snapped = sim.traffic.plan_route("-369217777#0_1", 90.0, **sim._plan_kw())["route"]
        assert snapped[:2] == ["-369217777#0", "369217777#0"], snapped
        assert sim.snap_info["start_lane"] == "369217777#0_1" and sim.snap_info.get("start_turned")
        assert "-369217777#0" not in sim.route, sim.route
        summary = sim.run()
    finally:
        sim.teardown()
    assert summary.arrived and summary.ego_collisions == 0 and summary.distance_m < 200, summary.line()
    # and with no goal (a random route), the same start: the road ahead runs into the dead end
    # (before: 403 m in 60 s, two collisions with the building at its end)
    sim = start_sim(kouvola, start=(60.530104, 26.945745), speed_mps=10.0, duration_s=40)
    try:
        assert sim.traffic.runs_into_dead_end("-369217777#0_1") and not sim.traffic.runs_into_dead_end("369217777#0_1")
        assert sim.snap_info["start_lane"] == "369217777#0_1" and sim.snap_info.get("start_turned")
        summary = sim.run()
    finally:
        sim.teardown()
    assert summary.ego_collisions == 0 and summary.distance_m > 250, summary.line()


@pytest.fixture(scope="module")
def lauf_pocket(tmp_path_factory):
    """Lauf, one chunk round Krummleitenweg (way 24446380) and the streets off it: every way
    out of them is closed to cars (tracks, service ways), so a route from there turns back."""
    return shared_world(tmp_path_factory, "lauf", "osm/lauf-2020.osm.pbf", "dem/N49E011.hgt.zip", (49.5003, 11.2640))


def test_the_turn_round_moves_stay_in_the_carriageway():
    """``cosim.turnround`` on a straight two-way road: the car's moves (its kinematics, as
    planned before it starts) turn it round in a few moves on 6.4 m of carriageway (two lanes
    of SUMO's default 3.2 m: nearly every dead end in the five test worlds), in fewer on a
    wider road, and not at all in 5 m; no move takes the footprint over an edge."""
    from cosim import turnround as T
    from cosim.driving import car_turn_radius

    R = car_turn_radius()
    C = np.array([[x, 0.0] for x in range(-60, 1)], dtype=float)
    need = {}
    for width in (5.0, 6.4, 8.0):
        far = np.array([[x, width / 2] for x in range(0, -61, -1)], dtype=float)
        cw = T.Carriageway.between(C, width / 2, far, width / 2, near_s=50.0)
        assert cw.side == 1 and cw.right == pytest.approx(-width / 4) and cw.left == pytest.approx(3 * width / 4)
        x, y, yaw = -FRONT - T.ROOM_AHEAD_M, 0.0, 0.0
        need[width] = T.moves_needed(cw, x, y, yaw, FRONT, 0.9, R, -1.35)
        if need[width] is None:
            continue
        # the moves again, each as far as its room less the stop's, every pose's footprint
        # checked, until the car heads the way back
        done = False
        for move in range(need[width]):
            fwd = move % 2 == 0
            curv = (1.0 if fwd else -1.0) / R
            go = T.room_along(cw, x, y, yaw, fwd, curv, FRONT, 0.9, -1.35) - 2 * T.STOP_ROOM_M
            assert go > 0.1, (width, move)
            for d in np.arange(0.0, go, 0.05):
                pose = T.arc_pose(x, y, yaw, d if fwd else -d, curv, -1.35)
                assert cw.violation(T.footprint(*pose, FRONT, 0.9)) <= 1e-9, (width, move, d)
                if abs(math.degrees(T._wrap(pose[2] - math.pi))) <= T.DONE_DEG:
                    done = True
                    break
            if done:
                break
            x, y, yaw = T.arc_pose(x, y, yaw, go if fwd else -go, curv, -1.35)
        assert done, (width, need[width], math.degrees(yaw))
    assert need[5.0] is None
    assert need[6.4] is not None and need[8.0] is not None and 3 <= need[8.0] < need[6.4] <= 11, need


def test_a_route_that_turns_back_is_driven_as_a_turn_in_moves(lauf_pocket, tmp_path):
    """Lauf: from Krummleitenweg every way on ends in a dead end or at a way closed to cars,
    and the random route turns back on itself where SUMO draws a U-turn 3-4 m round. The car
    drove that loop at full lock 6 m wide of it: off the road for 78 s of 110, into a building
    (at 1.3 m/s), where it stood 77 s. It now stops short of the turn and turns round in moves
    forward and back inside the carriageway (``cosim.turnround``), then drives on."""
    summary, stats, rows = drive_logged(lauf_pocket, tmp_path, start=(49.500266, 11.262326), speed_mps=10.0,
                                        duration_s=110)
    turning = [r for r in rows if r["reason"].startswith("turning round")]
    assert stats.turnarounds >= 1 and stats.no_room_to_turn == 0, stats.as_dict()
    assert summary.turnarounds == stats.turnarounds and "turned round in moves" in summary.line()
    assert summary.ego_collisions == 0 and summary.held_longest_s <= 0.5, summary.line()
    assert all(r["on_road"] for r in rows), [r["t"] for r in rows if not r["on_road"]][:5]
    assert min(r["speed_mps"] for r in turning) < -0.5          # moves back, in reverse
    done = [e for e in stats.events if e[1] == "turned round"]
    t_done = done[0][0]
    before = [r for r in turning if r["t"] < t_done][0]
    after = next(r for r in rows if r["t"] > t_done + 3.0)
    assert abs((after["yaw_deg"] - before["yaw_deg"] + 180.0) % 360.0 - 180.0) > 150.0, (before, after)
    moved_after = sum(math.hypot(b["x"] - a["x"], b["y"] - a["y"]) for a, b in zip(rows, rows[1:]) if a["t"] > t_done)
    assert moved_after > 100.0, moved_after


@pytest.fixture(scope="module")
def lauf_old_town(tmp_path_factory):
    """Lauf, one chunk round Förstergasse (way 142272501), whose lane bends twice at 75-85
    degrees between houses."""
    return shared_world(tmp_path_factory, "lauf-old-town", "osm/lauf-2020.osm.pbf", "dem/N49E011.hgt.zip",
                        (49.5169, 11.2861))


def test_a_car_held_against_a_wall_at_a_tight_bend_backs_off_and_drives_on(lauf_old_town, tmp_path):
    """Lauf, Förstergasse (-142272501#3): after a right bend the lane turns left by 85 degrees,
    and the house on the bend's outside stands 0.24 m beyond the lane's edge. The car at full
    lock met its wall with its front corner and stood against it, throttle on, for the rest of
    the run (28 s of this one's 40; 126 s in a 300 s drive through it). Its sweep now sees the
    wall, and the car stops short of it; held there a few seconds, it backs off at the other
    lock, turns forward at full lock towards the way on, and drives on along its lane to the
    goal, without touching the house."""
    def on_forstergasse(sim):
        assert sim.route[0] == "-142272501#3", sim.route

    summary, stats, rows = drive_logged(lauf_old_town, tmp_path, before=on_forstergasse, start=(49.516877, 11.286610),
                                        goal=(49.516765, 11.285728), speed_mps=10.0, duration_s=40)
    backing = [r for r in rows if r["reason"].startswith("backing off")]
    assert summary.arrived and 1 <= stats.backoffs <= 2, (summary.line(), stats.as_dict())
    assert summary.ego_collisions == 0 and summary.held_longest_s < 10.0, summary.line()
    assert any(r["reason"] == "clearance building" for r in rows)
    assert summary.backoffs == stats.backoffs and "backed off where it was held still" in summary.line()
    assert min(r["speed_mps"] for r in backing) < -0.3          # the move back, in reverse
    # it turned the car towards the way on: the heading when it drove on, against where it stood
    t0, t1 = backing[0]["t"], backing[-1]["t"]
    stood = next(r for r in rows if r["t"] >= t0 - 0.05)
    after = next(r for r in rows if r["t"] > t1)
    assert (after["yaw_deg"] - stood["yaw_deg"]) % 360.0 > 25.0, (stood, after)
    # on its lane but while it turns (then it swings into the street's other lane, 3.2 m left
    # of its own, as a driver does round such a corner: on_road counts 3 m either side)
    assert all(r["on_road"] for r in rows if not t0 <= r["t"] <= t1 + 3.0)
    assert max(abs(r["lateral_offset_m"]) for r in rows) < 4.8


@pytest.fixture(scope="module")
def helsinki_siltavuori(tmp_path_factory):
    """The Helsinki preset, one chunk round Siltavuorenpenger."""
    out = tmp_path_factory.mktemp("drv") / "helsinki-siltavuori"
    build_world(WorldConfig(preset="helsinki", center=(60.1752, 24.9485), chunks=0, out=str(out),
                            cache_dir=str(out.parent / "cache")))
    return str(out)


def test_a_start_on_a_lane_narrower_than_the_car_is_moved_to_one_it_fits_in(helsinki_siltavuori):
    """Helsinki, Siltavuorenpenger (-34918425): its lane for cars is 1.5 m wide (OSM's width),
    and where it passes between two houses the passages cut for it leave 1.70 m; the car (1.8
    m) started there stood before the first house, held by its lidar, for a whole 300 s run.
    Such a lane is now no road for the car, like a tunnel: a start on it snaps to the nearest
    lane it fits in, and routes go round it."""
    from cosim.driving import LANE_MIN_WIDTH_M, is_too_narrow, off_the_world

    sim = start_sim(helsinki_siltavuori, start=(60.175543, 24.950960), speed_mps=10.0, duration_s=60)
    try:
        s = sim.traffic.sumo
        assert s.lane.getWidth("-34918425_1") < LANE_MIN_WIDTH_M and is_too_narrow(s, "-34918425")
        assert off_the_world(s, "-34918425") and not off_the_world(s, sim.path.edges[0])
        narrow = [e for e in sim.path.edges if is_too_narrow(s, e)]
        assert not narrow and sim.path.edges[0] != "-34918425", sim.path.edges[:3]
        summary = sim.run()
    finally:
        sim.teardown()
    assert summary.ego_collisions == 0 and summary.distance_m > 200.0, summary.line()


def test_a_pocket_of_streets_is_left_by_turning_round(kouvola, caplog, tmp_path):
    """Kouvola (the embedded preset): from -74057323#0 every way on ends at a dead end or a turn
    tighter than the car can make, and so does the other direction's. The route turns back at
    the road's end, where SUMO draws a U-turn 3-4 m round: the car turns round there in moves
    forward and back, drives the other way, and leaves by the tight right turn into 74057316#0
    (no U-turn before it: the route takes it all the same, and the car follows it)."""
    caplog.set_level(logging.INFO)
    tel = tmp_path / "t.jsonl"
    sim = start_sim(kouvola, start=(60.532123, 26.944800), speed_mps=10.0, duration_s=80, telemetry=str(tel))
    try:
        assert sim.route == ["-74057323#0", "74057323#0"], sim.route
        assert not sim.traffic.leads_on("-74057323#0_1") and not sim.traffic.leads_on("74057323#0_1")
        summary = sim.run()
        stats = sim.driver.stats
    finally:
        sim.teardown()
    rows = [json.loads(line) for line in tel.read_text().splitlines()]
    assert summary.ego_collisions == 0 and stats.turnarounds == 1 and stats.no_room_to_turn == 0, summary.line()
    assert all(r["on_road"] for r in rows) and min(r["speed_mps"] for r in rows) < -0.5
    assert "turned round into 74057323#0_1" in caplog.text
    assert any(r["lane"] == "74057316#0_1" for r in rows) and summary.distance_m > 300.0, summary.line()


def test_where_the_car_cannot_go_on_or_turn_round_it_stops_and_says_why(monaco, caplog):
    """Monaco, no goal. Boulevard du Larvotto (92627403) is one way and goes on only into its
    tunnel, which the world has not: the route took it, and the car drove in at 9 m/s into
    Avenue d'Ostende's sidewalk, where it stood for good. Up the Impasse de la Fontaine
    (-200502086#0) the route turns back where the street's two directions lie 0.5 m apart:
    the car's first move ran into that step and stood there. Now the first route ends before
    the tunnel, and the turn is not begun over such a step: the car stops, and says why."""
    caplog.set_level(logging.INFO)
    sim = start_sim(monaco, start=(43.737450, 7.425844), speed_mps=10.0, duration_s=30)
    try:
        from cosim.driving import is_tunnel

        assert sim.route == ["92627403"] and is_tunnel(sim.traffic.sumo, "78149827")
        assert sim.traffic.sumo.lane.getLinks("92627403_1")[0][0] == "78149827_1"
        summary = sim.run()
    finally:
        sim.teardown()
    assert summary.ego_collisions == 0 and 30.0 < summary.distance_m < 60.0, summary.line()
    assert "no way on from road 92627403 that the car can drive" in caplog.text
    caplog.clear()
    sim = start_sim(monaco, start=(43.739606, 7.424848), speed_mps=10.0, duration_s=30)
    try:
        assert sim.route == ["-200502086#0", "200502086#0"], sim.route
        summary = sim.run()
        stats = sim.driver.stats
    finally:
        sim.teardown()
    assert summary.ego_collisions == 0 and summary.held_longest_s < 1.0, summary.line()
    assert stats.no_room_to_turn == 1 and stats.turnarounds == 0 and summary.no_room_to_turn == 1
    m = re.search(r"cannot turn round there \(a step of (\d\.\d\d) m across its carriageway\)", caplog.text)
    assert m and float(m.group(1)) > 0.3, caplog.text[-500:]


def test_a_goal_behind_the_car_on_its_own_road_is_reached_round_the_block(helsinki):
    """A goal 40 m behind the start, on the start's own lane: SUMO's route from a road to
    itself is that road alone, and the plan took it ("route 10 m" for a goal 70 m behind the
    car on a Monaco one-way street; the car stood short of it for good). The route now leaves
    the road and comes back to it (no turnaround: the car cannot make a tight one), and the
    goal's distance is measured on the route's last pass along the road. On Helsinki's roads
    of 100-250 m every such plan comes back to its road; on HEL_MID's (134 m) the car drives
    round (2 km: the centre's one-way streets and its lights; 6 minutes) and arrives. A loop
    only by a turn the car cannot make (SUMO's router takes U-turns over a junction's short
    edges; Monaco's Liaison Marquet, and 4 of these loops) is not taken: the goal's next road
    the car reaches, or none."""
    from cosim.driving import undrivable_steps, without_turnarounds

    sim = start_sim(helsinki, start=HEL_MID, speed_mps=10.0)
    try:
        tr = sim.traffic
        S = tr.sumo
        n = 0
        for ln in S.lane.getIDList():
            if ln.startswith(":") or not 100.0 < S.lane.getLength(ln) < 250.0 \
                    or S.lane.getAllowed(ln) and "passenger" not in S.lane.getAllowed(ln):
                continue
            P = np.asarray(S.lane.getShape(ln), dtype=float)[:, :2]
            d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
            gx, gy = (float(np.interp(d[-1] - 60.0, d, P[:, k])) for k in (0, 1))
            plan = tr.plan_route(ln, d[-1] - 20.0, goal_xy=(gx, gy), max_goal_snap_m=5.0)
            # (never by a turn the car cannot make, with no way round it: 4 of these 18 loops)
            assert not plan["route"] or not undrivable_steps(S, without_turnarounds(S, plan["route"])[0]), \
                (ln, plan["route"])
            if plan["goal"]["lane"] != ln or not plan["route"]:
                continue
            edge = ln.rsplit("_", 1)[0]
            assert plan["route"][0] == edge and plan["route"][-1] == edge and len(plan["route"]) > 2, \
                (ln, plan["route"])
            n += 1
        assert n >= 10, n
        lane = sim.snap_info["start_lane"]
        P = np.asarray(S.lane.getShape(lane), dtype=float)[:, :2]
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
        assert d[-1] > 120.0, d[-1]
        pos = 100.0
        sx, sy = (float(np.interp(pos, d, P[:, k])) for k in (0, 1))
        gx, gy = (float(np.interp(pos - 40.0, d, P[:, k])) for k in (0, 1))
        start, goal = (sim.world.frame.to_lonlat(x, y)[::-1] for x, y in ((sx, sy), (gx, gy)))
    finally:
        sim.teardown()
    sim = start_sim(helsinki, start=tuple(map(float, start)), goal=tuple(map(float, goal)), speed_mps=10.0,
                    duration_s=600)
    try:
        edge = lane.rsplit("_", 1)[0]
        assert sim.snap_info["start_lane"].rsplit("_", 1)[0] == edge, sim.snap_info
        assert sim.route[0] == edge and sim.route[-1] == edge and len(sim.route) > 2, sim.route
        planned = sim.snap_info["route_length_m"]
        # the rest of the road, the way round and the road again up to the goal: over 500 m
        assert planned > 500.0, sim.snap_info
        left = sim.route_left()
        assert left is not None and abs(left[0] - planned) < 1.0, (left, planned)
        summary = sim.run()
        st = sim.vehicle.state()
    finally:
        sim.teardown()
    assert summary.arrived and summary.ego_collisions == 0, summary.line()
    assert summary.distance_m > 0.9 * planned, (summary.distance_m, planned)
    assert math.hypot(st.x - gx, st.y - gy) < 15.0


def test_a_goal_beyond_a_window_drives_towards_a_road_the_car_reaches(kouvola):
    """A streamed window's re-plan towards a goal beyond its roads (``beyond_ok``) routes to the
    road nearest the goal; where the car cannot reach that one (a Portland window's was the
    Marquam Bridge's deck, 161 m from the goal: the run ended with "goal unreachable" at the
    swap), to the nearest one it reaches. Kouvola: goals 150 m beyond the network's edge, all
    round, whose nearest road no route from the start reaches."""
    sim = start_sim(kouvola, start=(60.530104, 26.945745), duration_s=1)
    try:
        lane, pos = sim.snap_info["start_lane"], sim.snap_info["start_pos"]
        (x0, y0), (x1, y1) = sim.traffic.sumo.simulation.getNetBoundary()
        cx, cy, r = (x0 + x1) / 2, (y0 + y1) / 2, max(x1 - x0, y1 - y0) / 2
        far = []
        for k in range(48):
            a = 2 * math.pi * k / 48
            # (the boundary's box, then 150 m more along the ray)
            t = min(abs((x1 - cx) / math.cos(a)) if abs(math.cos(a)) > 1e-9 else math.inf,
                    abs((y1 - cy) / math.sin(a)) if abs(math.sin(a)) > 1e-9 else math.inf)
            far.append((cx + (t + 150.0) * math.cos(a), cy + (t + 150.0) * math.sin(a)))
        cut_off = _plans_to_cut_off_roads(sim, lane, pos, far, near=False)
        # goals 10-40 m outside the chunks the network was built for (world.json's extent),
        # their nearest road within the snap distance but its way in cut where the network
        # ends (a Monaco window's re-plan at a swap ended the run with "goal unreachable": the
        # goal 100 m past the window's edge, 19 m from Avenue de la Costa, whose way in was cut)
        x0, y0, x1, y1 = sim.world.meta["extent_m"]
        edge = [[(x0 + f * (x1 - x0), y0 - off), (x1 + off, y0 + f * (y1 - y0)),
                 (x1 - f * (x1 - x0), y1 + off), (x0 - off, y1 - f * (y1 - y0))][side]
                for side in range(4) for f in np.arange(25) / 25.0 for off in (10.0, 25.0, 40.0)]
        near_cut = _plans_to_cut_off_roads(sim, lane, pos, edge, near=True)
    finally:
        sim.teardown()
    assert len(cut_off) >= 3, cut_off
    # (before: none of the 20; now 18, the other two with no road the car reaches within 300 m)
    routed = [(n, g) for n, route, g in cut_off if route]
    assert len(routed) >= 0.5 * len(cut_off), cut_off
    for nearest, g in routed:
        assert g["beyond"] and g["lane"] != nearest and g["dist"] < 150.0 + 300.0 + r, g
    # (before: 3 of the 40; now 25, the others with no road the car reaches within 300 m more)
    assert len(near_cut) >= 10, near_cut
    routed = [(n, g) for n, route, g in near_cut if route]
    assert len(routed) >= 0.5 * len(near_cut), (len(routed), len(near_cut))
    assert all(g["lane"] != nearest for nearest, g in routed)


def _plans_to_cut_off_roads(sim, lane: str, pos: float, goals, near: bool) -> list:
    """``plan_route`` (``beyond_ok``, 50 m snap) from ``pos`` on ``lane`` to each of the goal
    points whose nearest road lies within 50 m (``near``) or further, and which no route from
    the start's road reaches: [(that nearest lane, the route, the plan's goal)]."""
    out = []
    for gx, gy in goals:
        n = sim.traffic.snap_lane(gx, gy)
        if (n[5] <= 50.0) == near and sim.traffic._route_from([lane.rsplit("_", 1)[0]], n[0].rsplit("_", 1)[0]) is None:
            plan = sim.traffic.plan_route(lane, pos, goal_xy=(gx, gy), rng_state=sim._rng.getstate(),
                                          max_goal_snap_m=50.0, beyond_ok=True)
            out.append((n[0], plan["route"], plan["goal"]))
    return out


def test_a_goal_route_has_no_turn_the_car_cannot_make_or_is_a_clear_error(monaco):
    """Monaco has no tunnels in the world, and turns the car cannot make (U-turns at
    junctions, hairpins drawn too tight). SUMO's fastest route to a goal may take one that
    the lane path finds no way round near it: the car ran wide into a building or stood for
    good (six such drives of 300 s in the 3 x 3 km world: none arrived, four collided). The
    car's own router then takes a way without one (Boulevard des Moulins to Rue Suffren
    Reymond: 1,706 m, arrived; SUMO's route: 798 m, not arrived); where there is none, the run
    does not start, and says so."""
    from cosim.driving import undrivable_steps, without_turnarounds

    sim = start_sim(monaco, start=(43.740668, 7.425754), goal=(43.734396, 7.420976), duration_s=1)
    try:
        s = sim.traffic.sumo
        fastest = list(s.simulation.findRoute("165636046#0", "176293207#1", vType="DEFAULT_VEHTYPE").edges)
        assert undrivable_steps(s, without_turnarounds(s, fastest)[0])
        assert sim.path.edges[0] == "165636046#0" and sim.path.edges[-1] == "176293207#1"
        assert not undrivable_steps(s, sim.path.edges)
    finally:
        sim.teardown()
    # Rue Grimaldi from Place de la Source: every way turns round at a junction or
    # goes through a tunnel, from the start and from the road's other direction
    with pytest.raises(InputError, match=r"^goal unreachable: every route from the car's position to its nearest "
                                         r"road for cars, Rue Grimaldi \(lane 8352246#2_2\), 0 m from it, goes through "
                                         r"a tunnel \(the world has none\), a lane narrower than the car or a turn "
                                         r"it cannot make$"):
        start_sim(monaco, start=(43.739958, 7.420797), goal=(43.735837, 7.420057), duration_s=1)


def test_a_start_with_no_drivable_way_on_turns_round(monaco):
    """Monaco: from Avenue de Grande-Bretagne (157719645#0), going north-east, every way on
    passes a tunnel or a turn the car cannot make, though its lanes have links to more than
    one road (so it is no dead end by its links). With no goal the car drove into one
    (``cosim run``, default traffic: 147 m in 60 s, and a collision). It now starts on the
    road's other direction, from which it drives on (``SumoTraffic.leads_on``)."""
    sim = start_sim(monaco, start=(43.741057, 7.427591), speed_mps=10.0, duration_s=60)
    try:
        assert not sim.traffic.runs_into_dead_end("157719645#0_1")
        assert not sim.traffic.leads_on("157719645#0_1") and sim.traffic.leads_on("-157719645#0_1")
        assert sim.snap_info["start_lane"].startswith("-157719645#0_") and sim.snap_info.get("start_turned")
        summary = sim.run()
    finally:
        sim.teardown()
    assert summary.ego_collisions == 0 and summary.distance_m > 250, summary.line()


def test_goal_far_from_roads_is_a_clear_error(helsinki):
    with pytest.raises(InputError, match=r"goal is 1\d\d m from the nearest road"):
        start_sim(helsinki, goal=HEL_OFF_ROAD, duration_s=5)


def test_an_unreachable_goal_names_its_road(helsinki):
    """A goal whose nearest road for cars no route reaches (Helsinki 2019: Töölönlahdenkatu, a
    one-way island entered from Postikuja, itself entered from no road for cars): the error
    names the street and the lane it snapped to."""
    with pytest.raises(InputError) as e:
        start_sim(helsinki, goal=(60.1735, 24.9380), duration_s=5)
    assert str(e.value) == ("goal unreachable: its nearest road for cars, Töölönlahdenkatu (lane 8034129#0_1), "
                            "29 m from it, cannot be reached by road from the car's position")
    # beyond SUMO's network (it said "no road for cars near (30969, -58921) m", in metres)
    with pytest.raises(InputError, match=r"^goal \(60\.40000, 25\.10000\) is 2\d\.\d km from the world's centre, "
                                         r"outside SUMO's network \(x -?\d+\.\.\d+, y -?\d+\.\.\d+ m\)"):
        start_sim(helsinki, goal=(60.4, 25.1), duration_s=5)


def test_a_start_outside_the_built_world_is_a_clear_error(helsinki):
    """SUMO's network reaches beyond the built chunks (netconvert gets the whole extract): a
    start on a road there had no ground under the car (its height NaN, standing for good)."""
    with pytest.raises(InputError, match=r"outside the built world .*x -500\.\.500"):
        start_sim(helsinki, start=(60.167088, 24.951134), duration_s=5)      # 507 m east


def test_the_world_edge_ahead_is_the_first_path_point_outside_the_built_chunks(helsinki):
    """The autopilot slows for the first point of its path ahead that no built chunk holds
    (``_world_edge``, which tests the first point of each run of points in one chunk): the
    same point as testing every point, on the run's path cut into 100 m cells of which
    some count as built, and into none."""
    sim = start_sim(helsinki, speed_mps=10.0, duration_s=5)
    world, path, driver = sim.world, sim.path, sim.driver
    chunks, size = world.chunks, world.chunk_size
    try:
        world.chunk_size = 100.0
        ij = np.floor(path.xy / 100.0 + 0.5).astype(int)
        cells = {tuple(c) for c in ij.tolist()}
        assert len(cells) >= 4 and path.length > 300.0
        found = 0
        for keep in (lambda c: (c[0] + c[1]) % 3 != 0, lambda c: c[0] % 2 == 0, lambda c: True,
                     lambda c: c == (99, 99)):
            world.chunks = {c: {} for c in cells | {(99, 99)} if keep(c)}
            for s_here in np.linspace(0.0, path.length - 1.0, 40):
                for horizon in (20.0, 150.0, 2000.0):
                    i0 = path.index_at(s_here)
                    i1 = path.index_at(s_here + horizon + 10.0) + 1
                    every = next((float(path.s[i]) for i in range(i0, i1) if tuple(ij[i]) not in world.chunks), None)
                    assert driver._world_edge(path, float(s_here), horizon) == every, (keep, s_here, horizon)
                    found += every is not None and every > path.s[i0]
        assert found >= 20          # (edges past the first point ahead, not only at it)
    finally:
        world.chunks, world.chunk_size = chunks, size
        sim.teardown()


def test_the_driver_takes_the_loops_projection_of_the_car_and_it_is_its_own(helsinki):
    """The loop projects the car onto its path once a frame and the autopilot takes that
    projection (``Simulation.ego_projection``): at every frame it is the one the autopilot
    would make itself, and a driver given another state or another s projects for itself."""
    sim = start_sim(helsinki, speed_mps=12.0, duration_s=30)
    try:
        driver, taken, own = sim.driver, [], []
        orig = driver.control

        def control(st, s_here, actors, dt):
            out = orig(st, s_here, actors, dt)
            k, _, lat = sim.path.project(st.x, st.y, sim.path.index_at(s_here))
            taken.append((driver._k, driver._lat))
            own.append((k, lat))
            return out

        driver.control = control
        for _ in range(150):
            sim.step()
        assert len(taken) == 150 and taken == own
        assert len({k for k, _ in taken}) > 20          # the car moved along its path
        # a state the loop did not project: projected anew, not taken
        st = sim.vehicle.state()
        sim.ego_projection = (sim.path, st.x + 1.0, st.y, 0.0, 0, 99.0)
        orig(st, sim.path.project(st.x, st.y, driver._k)[1], sim.last_snapshot, 0.1)
        assert driver._lat != 99.0 and abs(driver._lat) < 3.0
    finally:
        sim.teardown()


def test_stops_at_red_and_at_yellow_when_it_can(helsinki):
    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL, speed_mps=10.0, duration_s=120)
    try:
        s = sim.traffic.sumo
        assert sim.snap_info["start_lane"].startswith("17132580#1_")
        here = ego_front_s(sim)
        lights = [stop for stop in sim.path.stops if stop.tls and stop.s > here + 40]
        red_stop, yellow_stop = lights[0], lights[1]
        red_tls, yellow_tls = tls_of_lane(s, red_stop.lane), tls_of_lane(s, yellow_stop.lane)
        force_tls(sim, red_tls, "r")
        force_tls(sim, yellow_tls, "G")
        fronts, speeds, states = [], [], []
        for _ in range(300):
            sim.step()
            fronts.append(ego_front_s(sim))
            speeds.append(sim.vehicle.state().speed)
            states.append(red_stop.state(s))
        assert set(states) == {"r"}                     # SUMO's state of the ego's link
        assert max(fronts) <= red_stop.s + 0.05         # never past the stop line
        assert red_stop.s - fronts[-1] < 6.0            # stopped close to it
        stopped = [i for i, v in enumerate(speeds) if abs(v) < 0.1]
        assert stopped and len(stopped) * 0.1 >= 10.0   # and stayed there
        force_tls(sim, red_tls, "G")
        for _ in range(100):
            sim.step()
            if ego_front_s(sim) > red_stop.s + 3.0:
                break
        assert ego_front_s(sim) > red_stop.s + 3.0      # green: gone
        # yellow 35 m before the next light at ~10 m/s: it can stop (14 m at 3.5 m/s2), so it does
        for _ in range(400):
            if yellow_stop.s - ego_front_s(sim) <= 35.0:
                break
            sim.step()
        v0 = sim.vehicle.state().speed
        assert v0 > 6.0
        force_tls(sim, yellow_tls, "y")
        fronts = []
        for _ in range(100):
            sim.step()
            fronts.append(ego_front_s(sim))
        assert max(fronts) <= yellow_stop.s + 0.05
        assert abs(sim.vehicle.state().speed) < 0.1
        assert sim.summary.ego_collisions == 0
    finally:
        sim.teardown()


def _lead_gap(sim, vid) -> float:
    """Bumper-to-bumper gap along the path from SUMO's pose of vehicle `vid`."""
    from cosim.traffic import front_to_center

    s = sim.traffic.sumo
    fx, fy = s.vehicle.getPosition(vid)
    ang = s.vehicle.getAngle(vid)
    length = s.vehicle.getLength(vid)
    cx, cy = front_to_center(fx, fy, ang, length)
    s_c, _ = s_of(sim, float(cx), float(cy))
    return s_c - length / 2.0 - ego_front_s(sim)


def test_follows_with_time_gap_then_stops_behind_stopped_car(helsinki):
    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL, speed_mps=12.0, duration_s=120)
    try:
        s = sim.traffic.sumo
        for stop in sim.path.stops:
            if stop.tls:
                force_tls(sim, tls_of_lane(s, stop.lane), "G")
        lane = sim.snap_info["start_lane"]
        s.route.add("lead_route", [e for e in sim.route])
        s.vehicle.add("lead", "lead_route", departLane=lane.rsplit("_", 1)[1],
                      departPos=str(sim.snap_info["start_pos"] + 30.0), departSpeed="5")
        s.vehicle.setSpeed("lead", 5.0)
        gaps, tgaps = [], []
        for _ in range(250):                                   # catch up and follow
            sim.step()
            if "lead" not in s.vehicle.getIDList():
                continue
            v = sim.vehicle.state().speed
            g = _lead_gap(sim, "lead")
            gaps.append(g)
            if v > 3.0 and abs(v - s.vehicle.getSpeed("lead")) < 0.5:
                tgaps.append(g / v)
        assert min(gaps) > 2.0
        assert len(tgaps) >= 30, len(tgaps)
        assert min(tgaps) >= 1.5, min(tgaps)                   # at least 1.5 s behind
        # the lead brakes to a stop: the ego stops behind it
        s.vehicle.setSpeed("lead", 0.0)
        for _ in range(150):
            sim.step()
        assert abs(sim.vehicle.state().speed) < 0.1
        gap = _lead_gap(sim, "lead")
        assert 2.0 <= gap <= 8.0, gap
        # the lidar sees the mirrored car straight ahead, where SUMO has it
        scan = sim.driver.scan
        body = sim.mirror.body_of("lead")
        mid = len(scan.distance) // 2
        assert scan.body[mid] == body
        assert abs(scan.distance[mid] + 0.05 - gap) < 0.5
        assert sim.driver.stats.near_misses == 0
        # it drives off: the ego resumes
        s.vehicle.setSpeed("lead", 8.0)
        for _ in range(120):
            sim.step()
        assert sim.vehicle.state().speed > 3.0
        assert sim.summary.ego_collisions == 0
    finally:
        sim.teardown()


def _walker_across(sim, crossing) -> str:
    """A SUMO person that walks onto `crossing` from the far side (left of the ego's path);
    the caller slows it down once it is on. (A person at the kerb of a crossing without
    priority waits for any car coming, so the caller holds the ego back until then.)"""
    s = sim.traffic.sumo
    shape = np.array(s.lane.getShape(crossing.lane))
    k = sim.path.index_at(crossing.s)
    lat0 = sim.path.project(*shape[0], k)[2]
    lat1 = sim.path.project(*shape[-1], k)[2]
    far, near = (shape[0], shape[-1]) if lat0 > lat1 else (shape[-1], shape[0])

    def sidewalk_at(end):
        """The sidewalk lane of the crossing's junction that ends nearest this end of the
        crossing, and the position on it by the junction (a person cannot start on a crossing)."""
        best = None
        for e in set(s.junction.getIncomingEdges(crossing.junction)) | set(s.junction.getOutgoingEdges(crossing.junction)):
            lane = f"{e}_0"
            if e.startswith(":") or "pedestrian" not in s.lane.getAllowed(lane):
                continue
            sh = np.array(s.lane.getShape(lane))
            into = s.edge.getToJunction(e) == crossing.junction
            d = float(np.hypot(*(sh[-1 if into else 0] - end)))
            if best is None or d < best[0]:
                length = s.lane.getLength(lane)
                best = (d, e, max(length - 0.5, length / 2) if into else min(0.5, length / 2))
        assert best and best[0] < 10.0, f"no sidewalk by {crossing.lane}"
        return best[1], best[2]

    a, b = sidewalk_at(far), sidewalk_at(near)
    s.person.add("walker", a[0], a[1])
    s.person.appendWalkingStage("walker", [a[0], b[0]], b[1])
    s.person.setSpeed("walker", 1.5)
    return "walker"


def test_yields_to_pedestrian_on_crossing(helsinki):
    sim = start_sim(helsinki, start=HEL_CROSSING_START, goal=HEL_CROSSING_GOAL, speed_mps=10.0, duration_s=90)
    try:
        s = sim.traffic.sumo
        crossing = sim.path.crossings[0]
        assert crossing.junction not in s.trafficlight.getIDList()    # no light: right of way
        pid = _walker_across(sim, crossing)
        sim.set_speed(0.0)                      # until the walker is on the crossing
        near_edge = crossing.s - crossing.width / 2.0
        k = sim.path.index_at(crossing.s)
        waited, slowed = 0, False
        while sim.t < 80 and not sim.summary.arrived:
            sim.step()
            front = ego_front_s(sim)
            v = sim.vehicle.state().speed
            if pid in s.person.getIDList() and s.person.getRoadID(pid) == crossing.edge:
                if not slowed:               # on the crossing: 6 m at 0.3 m/s; the car comes
                    s.person.setSpeed(pid, 0.3)
                    sim.set_speed(10.0)
                    slowed = True
                px, py = s.person.getPosition(pid)
                lat = sim.path.project(px, py, k)[2]
                if lat > -3.0:                 # on the crossing, not yet past the ego's lane
                    assert front <= near_edge + 0.05, (front, near_edge)
                    if abs(v) < 0.1:
                        waited += 1
        assert slowed                          # the walker got onto the crossing
        assert waited >= 30                    # it stopped and waited (> 3 s)
        assert sim.summary.arrived             # and went on when the way was clear
        assert sim.summary.ego_collisions == 0
    finally:
        sim.teardown()


def test_full_stop_at_osm_stop_sign(portland):
    sim = start_sim(portland, start=PDX_START, goal=PDX_GOAL, speed_mps=10.0, duration_s=60)
    try:
        stop = sim.path.stops[0]
        line = np.array(sim.traffic.sumo.lane.getShape(stop.lane)[-1])
        signs = [(i["x"], i["y"]) for ij in sim.world.chunks for i in sim.world.scenery(ij) if i["kind"] == "stop_sign"]
        assert min(math.hypot(x - line[0], y - line[1]) for x, y in signs) < 10.0   # a real sign there
        assert stop.state(sim.traffic.sumo) in "m="                                 # SUMO: minor link
        still, fronts = [], []
        while sim.t < 55 and not sim.summary.arrived:
            sim.step()
            front = ego_front_s(sim)
            fronts.append(front)
            if abs(sim.vehicle.state().speed) < 0.05 and stop.s - 10.0 < front < stop.s:
                still.append((sim.t, front))
        assert still, "no full stop"
        assert 0.0 <= stop.s - still[0][1] <= 3.5                  # at the line
        assert still[-1][0] - still[0][0] >= 1.0 - 1e-6            # for at least 1 s
        assert max(fronts) > stop.s + 10 and sim.summary.arrived   # then on across the junction
        assert sim.summary.ego_collisions == 0
    finally:
        sim.teardown()


def test_holds_speed_on_steep_monaco_street(monaco, tmp_path):
    tel = tmp_path / "monaco.jsonl"
    sim = start_sim(monaco, start=MC_START, goal=MC_GOAL, speed_mps=8.0, duration_s=80, telemetry=str(tel))
    try:
        # placed on the sloping street, tilted with it (placed level, its rear started inside
        # the road, it reared up and a collision was logged at t = 0.3 s)
        st = sim.vehicle.state()
        grade = float(sim.world.slope_pitch(st.x, st.y, st.yaw)[0])     # the ground's, nose up > 0
        assert abs(st.pitch) > 0.05 and st.pitch * grade < 0, (st.pitch, grade)   # (pitch > 0: nose down)
        summary = sim.run()
    finally:
        sim.teardown()
    assert summary.arrived, summary.line()
    assert summary.ego_collisions == 0, sim.collision_log
    rows = [json.loads(l) for l in tel.read_text().splitlines()]
    xyz = np.array([(r["x"], r["y"], r["alt_m"]) for r in rows])
    # the grade from the car's own track: height gained over distance driven in +-1 s
    grade = np.full(len(rows), np.nan)
    for i in range(10, len(rows) - 10):
        d = np.hypot(*(xyz[i + 10, :2] - xyz[i - 10, :2]))
        if d > 4.0:
            grade[i] = (xyz[i + 10, 2] - xyz[i - 10, 2]) / d
    held = settled_cruise(rows, 8.0)
    up = [i for i in held if grade[i] >= 0.10]
    down = [i for i in held if grade[i] <= -0.10]
    assert np.nanmax(grade) >= 0.15 and np.nanmin(grade) <= -0.15
    assert len(up) >= 40 and len(down) >= 10, (len(up), len(down))
    err = np.array([rows[i]["speed_mps"] - 8.0 for i in up + down])
    assert np.abs(err).max() <= 0.3, np.abs(err).max()


def test_respects_lane_speed_limit_when_asked(helsinki):
    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL, speed_mps=20.0, respect_speed_limit=True,
                    duration_s=60)
    try:
        s = sim.traffic.sumo
        for stop in sim.path.stops:
            if stop.tls:
                force_tls(sim, tls_of_lane(s, stop.lane), "G")
        over, top = [], 0.0
        limits = set()
        for _ in range(400):
            ego = sim.step()
            if ego.lane:
                limit = s.lane.getMaxSpeed(ego.lane)
                limits.add(round(limit, 2))
                over.append(ego.speed - limit)
                top = max(top, ego.speed)
            if sim.summary.arrived:
                break
    finally:
        sim.teardown()
    assert max(over) <= 0.3, max(over)
    assert top >= min(limits) - 0.5 and top < 20.0 - 3.0


def test_env_step_api_and_callback_driver(helsinki):
    from cosim.autopilot import CallbackDriver
    from cosim.env import DrivingEnv

    env = DrivingEnv(SimConfig(world_dir=helsinki, traffic="none", start=HEL_MID, goal=HEL_GOAL, speed_mps=10.0,
                               duration_s=60))
    try:
        obs, info = env.reset(seed=1)
        env.sim.physics.load_budget_ms = 1e9
        assert obs["lidar"].shape == (41,) and obs["speed"].shape == (1,) and 0 <= obs["light"] <= 5
        total = 0.0
        for _ in range(80):
            obs, reward, terminated, truncated, info = env.step(info["autopilot_action"])
            total += reward
            assert not terminated
        assert obs["speed"][0] > 5.0 and total > 30.0           # progress pays
        assert abs(obs["lateral_offset"][0]) < 0.5
        for _ in range(40):
            obs, reward, terminated, truncated, info = env.step([0.0, 1.0, 0.0])
        assert abs(obs["speed"][0]) < 0.2 and reward < 0.1       # braking: no progress, no reward
        obs, info = env.reset()                                  # no seed: back at the start
        assert abs(obs["speed"][0]) < 0.1 and abs(obs["lateral_offset"][0]) < 0.3
        with pytest.raises(ValueError):
            env.step([1.0, 0.0])
        env.reset(seed=2**40 + 5)                    # any int, as Gymnasium allows: SUMO's 32-bit seed 5
        assert env.sim.cfg.seed == 5
    finally:
        env.close()

    calls = []

    def my_driver(obs):                     # a user's own controller: P on speed, lane and heading
        calls.append(obs["speed"])
        throttle = max(0.0, min(1.0, 0.3 * (8.0 - obs["speed"])))
        brake = 0.0 if throttle > 0 else min(1.0, 0.2 * (obs["speed"] - 8.0))
        steer = -0.5 * obs["lateral_offset"] - 1.2 * obs["heading_error"]
        return throttle, brake, steer

    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL, duration_s=30)
    try:
        sim.driver = CallbackDriver(sim, my_driver)
        x0 = sim.vehicle.state()
        lats = [abs(sim.step().lateral_offset_m) for _ in range(100)]
        x1 = sim.vehicle.state()
    finally:
        sim.teardown()
    assert len(calls) == 100
    assert math.hypot(x1.x - x0.x, x1.y - x0.y) > 40.0 and max(lats) < 1.0
    # a fourth value selects the reverse gear: the car backs up along its heading
    sim = start_sim(helsinki, start=HEL_MID, duration_s=30)
    try:
        sim.driver = CallbackDriver(sim, lambda obs: (0.3, 0.0, 0.0, True))
        x0 = sim.vehicle.state()
        speeds = [sim.step().speed for _ in range(30)]
        x1 = sim.vehicle.state()
    finally:
        sim.teardown()
    back = (x1.x - x0.x) * math.cos(x0.yaw) + (x1.y - x0.y) * math.sin(x0.yaw)
    assert min(speeds) < -1.0 and back < -1.0, (min(speeds), back)


def test_live_controls_refuse_bad_input_and_a_refused_goal_keeps_the_current_one(helsinki):
    """A script's mistakes are one-line InputErrors that change nothing:
    - a destination that cannot be taken (off the roads, outside the world) leaves the car
      on its way to the one it had (it used to drop it: the car never arrived);
    - ``set_goal(None)`` drops the goal and its figures (it returned the old route's length and
      ETA, and the summary still said "goal NOT reached");
    - camera sizes below one pixel (a negative one aborted the process inside PyBullet), an
      unknown view, manual controls that are not three finite numbers (NaN drove as full
      throttle, brake and lock), a set speed that is not a number.
    Before setup, the live calls say to call setup()."""
    from netgen.errors import InputError, SimulationError

    cfg = SimConfig(world_dir=helsinki, traffic="none", seed=1, start=HEL_MID, goal=HEL_GOAL, speed_mps=10.0,
                    duration_s=60)
    idle = Simulation(cfg)
    for call in (lambda: idle.set_goal(*HEL_GOAL), idle.traffic_lights, lambda: idle.camera_image(64, 48)):
        with pytest.raises(SimulationError, match=r"call setup\(\) before"):
            call()
    sim = Simulation(cfg).setup()
    sim.physics.load_budget_ms = 1e9
    try:
        for _ in range(10):
            sim.step()
        goal, left = sim.goal_xy, sim.route_left()
        assert goal is not None and left is not None
        for bad in ((60.1740, 24.9456), (60.30, 25.20)):        # 137 m from any road; 15 km away
            with pytest.raises(InputError, match="goal"):
                sim.set_goal(*bad)
            assert sim.goal_xy == goal and sim.cfg.goal == HEL_GOAL and sim.route_left() is not None
        with pytest.raises(InputError, match="latitude"):
            sim.set_goal(95.0, 24.9)
        assert sim.goal_xy == goal
        # a goal beyond the built world says so (it said "goal is 1334 m from the nearest road"
        # where SUMO's network reached on beyond the world)
        with pytest.raises(InputError, match=r"^goal \(60\.30000, 25\.20000\) is .*outside"):
            sim.set_goal(60.30, 25.20)
        (x0, y0, x1, y1), ((nx0, ny0), (nx1, ny1)) = sim.world.loaded_extent(), sim.traffic.sumo.simulation.getNetBoundary()
        # (a corner of SUMO's network beyond the world, away from its roads)
        corners = [(cx, cy) for cx in (nx0 + 5, nx1 - 5) for cy in (ny0 + 5, ny1 - 5)
                   if not (x0 <= cx <= x1 and y0 <= cy <= y1) and sim.traffic.snap_lane(cx, cy)[5] > 60.0]
        assert corners, "no corner of the network outside the world and away from its roads"
        lon, lat = sim.world.frame.to_lonlat(*corners[0])
        with pytest.raises(InputError, match=r"is outside the world, 0\.\d km from its centre .*--chunks"):
            sim.set_goal(float(lat), float(lon))
        assert sim.goal_xy == goal
        for w, h in ((-5, 10), (0, 0), (64, 10**6), (64.5, 48)):
            with pytest.raises(InputError, match="camera image (width|height) must be a whole number of pixels"):
                sim.camera_image(w, h)
        with pytest.raises(InputError, match="camera view must be 'chase' or 'driver'"):
            sim.camera_image(64, 48, view="bogus")
        for control in ((float("nan"),) * 3, (0.3, 0.1), ("a", 0, 0), None.__class__):
            with pytest.raises(InputError, match="manual control must be"):
                sim.set_manual(control)
        assert sim.manual is None
        with pytest.raises(InputError, match="speed must be a number, got 'x'"):
            sim.set_speed("x")
        info = sim.set_goal(None)
        assert info == {"route_length_m": None, "eta_s": None, "goal_snap_m": None}
        assert sim.goal_xy is None and sim.route_left() is None and sim.summary.arrived is None
        for _ in range(20):
            sim.step()
        assert "goal" not in sim.finish().line()
    finally:
        sim.teardown()


def test_a_goal_on_a_road_the_car_cannot_reach_takes_the_nearest_one_it_can(helsinki):
    """Where the OSM extract ends, a road entering the area has no road before it: a goal
    on it was "goal unreachable" though a road the car reaches ran beside it. The goal now
    takes the nearest road within the snap distance that the car can reach."""
    from cosim.driving import _lane_allows, is_tunnel

    sim = start_sim(helsinki, start=HEL_MID, duration_s=60)
    try:
        s = sim.traffic.sumo
        lanes = [ln for ln in s.lane.getIDList() if not ln.startswith(":")]
        entered = {link[0].rsplit("_", 1)[0] for ln in s.lane.getIDList() for link in s.lane.getLinks(ln)}
        sources = sorted({ln.rsplit("_", 1)[0] for ln in lanes} - entered)
        tried = 0
        for e in sources:
            lane = next((f"{e}_{i}" for i in range(s.edge.getLaneNumber(e)) if _lane_allows(s, f"{e}_{i}", "passenger")),
                        None)
            if lane is None or s.lane.getLength(lane) < 10 or is_tunnel(s, e):
                continue
            P = np.array(s.lane.getShape(lane))
            x, y = P[len(P) // 2] if len(P) > 2 else P.mean(axis=0)
            if sim.traffic.snap_lane(float(x), float(y))[0].rsplit("_", 1)[0] != e:
                continue                    # (another road is nearer: not the case)
            near = [ln for d, ln in sim.traffic._lanes_near(float(x), float(y), 40.0) if ln.rsplit("_", 1)[0] != e]
            if not near:
                continue
            tried += 1
            lon, lat = sim.world.frame.to_lonlat(float(x), float(y))
            info = sim.set_goal(float(lat), float(lon))
            assert 0 < info["goal_snap_m"] <= 50.0 and sim.route and sim.route[-1] != e, (e, info)
            assert sim.goal_xy is not None
            if tried >= 3:
                break
        assert tried >= 1, "no road entering the extract with a reachable road beside it"
    finally:
        sim.teardown()


def test_a_car_held_still_with_the_throttle_on_is_reported(helsinki, caplog):
    """A car that stands with the throttle on and no brake is held by something (a Portland
    car stood 1,071 s against a bridge deck's edge, the summary silent): said once in the log
    after 10 s, and the summary line gives the time. Here a wall of PyBullet's in front of it."""
    import pybullet as pb

    sim = start_sim(helsinki, start=HEL_MID, duration_s=60)
    try:
        for _ in range(5):
            sim.step()
        st = sim.vehicle.state()
        c, sn = math.cos(st.yaw), math.sin(st.yaw)
        cid = sim.physics.client
        wall = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=[0.5, 3.0, 2.0], physicsClientId=cid)
        pb.createMultiBody(0, wall, basePosition=[st.x + 4.0 * c, st.y + 4.0 * sn, st.z + 1.5],
                           baseOrientation=pb.getQuaternionFromEuler((0, 0, st.yaw)), physicsClientId=cid)
        sim.set_manual((0.8, 0.0, 0.0))
        with caplog.at_level(logging.WARNING, logger="cosim"):
            for _ in range(160):
                sim.step()
        said = [r.getMessage() for r in caplog.records if "stood still with the throttle" in r.getMessage()]
        summary = sim.finish()
    finally:
        sim.teardown()
    assert len(said) == 1 and "something holds it" in said[0], said
    assert summary.held_longest_s >= 10.0 and summary.held_s >= summary.held_longest_s
    assert "the car stood still with the throttle on for" in summary.line()


def test_a_simulation_leaves_its_config_alone_and_sets_up_afresh_after_a_teardown(helsinki):
    """``set_speed`` and ``set_goal`` change the run, not the caller's SimConfig (a second
    Simulation made from it started at the first one's last speed and goal); ``setup()`` after
    ``teardown()`` is a new run: its clock and summary start from zero (they went on from the
    first run's, and the summary added both runs up)."""
    cfg = SimConfig(world_dir=helsinki, traffic="none", seed=1, start=HEL_MID, goal=HEL_GOAL, speed_mps=10.0,
                    duration_s=60)
    sim = Simulation(cfg).setup()
    try:
        for _ in range(30):
            sim.step()
        sim.set_speed(3.0)
        sim.set_goal(None)
        assert (cfg.speed_mps, cfg.goal) == (10.0, HEL_GOAL)
        first = sim.finish()
        assert first.distance_m > 5.0
    finally:
        sim.teardown()
    sim.setup()
    try:
        assert sim.t == 0.0 and sim.summary.distance_m == 0.0 and sim.cfg.speed_mps == 10.0 and sim.goal_xy is not None
        for _ in range(10):
            sim.step()
        again = sim.finish()
        assert again.sim_time_s == pytest.approx(1.0) and again.distance_m < first.distance_m
        with pytest.raises(Exception, match="setup\\(\\) called twice"):
            sim.setup()
    finally:
        sim.teardown()


def test_env_same_seed_gives_the_same_episode(helsinki):
    """``reset(seed=N)`` twice, then the same actions: the same observations and infos step
    for step, with traffic (Gymnasium's ``check_env`` checks this). A seed equal to the running
    one used to put the car back into the running simulation, whose traffic and lights had gone
    on: the second episode differed from its first step. ``reset()`` without a seed still does
    that (fast)."""
    from cosim.env import DrivingEnv

    env = DrivingEnv(SimConfig(world_dir=helsinki, traffic="light", start=HEL_MID, goal=HEL_GOAL, speed_mps=10.0,
                               duration_s=60))
    runs = []
    try:
        for _ in range(2):
            obs, info = env.reset(seed=3)
            sim_before = env.sim
            seen = [(obs, env.sim.traffic.stats.vehicles, info["t"])]
            for k in range(60):
                obs, reward, terminated, truncated, info = env.step(info["autopilot_action"] if k % 3 else [0.6, 0.0, 0.05])
                seen.append((obs, env.sim.traffic.stats.vehicles, info["t"]))
            runs.append(seen)
        assert max(r[1] for r in runs[0]) > 0           # (there was traffic to differ)
        for (o1, v1, t1), (o2, v2, t2) in zip(*runs):
            assert (v1, t1) == (v2, t2)
            for key in o1:
                np.testing.assert_array_equal(o1[key], o2[key], err_msg=key)
        obs, info = env.reset()                         # no seed: the running simulation, car at the start
        assert env.sim is sim_before and info["t"] > runs[1][-1][2]
        assert abs(obs["speed"][0]) < 0.1
    finally:
        env.close()


def test_env_rgb_array_render_draws_the_world_and_a_headless_camera_says_it_cannot(helsinki, caplog):
    """``DrivingEnv(render_mode="rgb_array")`` loads the world's visual meshes, so that
    ``render()`` shows the road and the ground; a headless simulation loads none, and its
    camera image (the cars alone on the background) comes with a warning. The env's render
    was the empty background with the car in it."""
    from cosim.env import DrivingEnv

    def background_share(img) -> float:            # the sky camera_image draws where it sees nothing
        return float(np.mean(sky_mask(img)[img.shape[0] // 2:]))

    env = DrivingEnv(SimConfig(world_dir=helsinki, traffic="none", start=HEL_MID, speed_mps=10.0, duration_s=20),
                     render_mode="rgb_array")
    try:
        env.reset(seed=1)
        img = env.render()
    finally:
        env.close()
    assert img.shape == (270, 480, 3) and background_share(img) < 0.2
    sim = start_sim(helsinki, start=HEL_MID, duration_s=20)
    try:
        sim.step()
        with caplog.at_level(logging.WARNING, logger="cosim"):
            bare = sim.camera_image(480, 270)
            sim.camera_image(480, 270)
    finally:
        sim.teardown()
    assert background_share(bare) > 0.8
    said = [r for r in caplog.records if "no visual meshes" in r.getMessage()]
    assert len(said) == 1 and "render=True" in said[0].getMessage()


def sky_mask(img) -> np.ndarray:
    """Pixels of camera_image's sky (cosim.physics SKY_TOP_RGB .. SKY_HORIZON_RGB: blue, light)."""
    a = np.asarray(img)[..., :3].astype(int)
    return (a[..., 2] >= 200) & (a[..., 2] - a[..., 0] >= 30)


def test_the_drivers_view_looks_out_over_the_bonnet(helsinki):
    """``camera_image(view="driver")`` sees the road ahead over the bonnet: the car's paint only
    in the lowest part of the picture. The camera sat inside the cabin and saw the inside of
    the roof's edge across the picture and the windscreen's box over half of it."""
    sim = start_sim(helsinki, start=HEL_MID, speed_mps=8.0, duration_s=20, render=True)
    try:
        for _ in range(20):
            sim.step()
        img = np.asarray(sim.camera_image(480, 270, view="driver")).astype(int)
    finally:
        sim.teardown()
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    paint = (b > 140) & (r < 70) & (g < 120)          # models/car's paint, rgba 0.10 0.30 0.70
    rows = np.nonzero(paint.any(axis=1))[0]
    assert len(rows) and rows.min() > 0.7 * img.shape[0] and paint.mean() < 0.25, (rows.min(), paint.mean())
    sky = sky_mask(img)
    assert not ((b > r + 40) & ~sky)[: img.shape[0] // 2].any()     # nothing of the car (its roof's edge) up there
    assert sky[: img.shape[0] // 3].mean() > 0.05      # some sky in the upper third
    # the sky: PyBullet left it white; a gradient from the top of the picture to its bottom
    from cosim.physics import SKY_TOP_RGB
    top = img[0][sky[0]]
    assert len(top) and np.all(np.abs(top - np.array(SKY_TOP_RGB)) <= 1), top[:3]
    assert not (img.min(axis=2) > 250).any()          # (no white left)


def _arc_path(radius: float, angle_deg: float):
    """A LanePath (geometry only) along x: 60 m straight, a left arc, 60 m straight on."""
    from cosim.driving import LanePath

    pts = [(x, 0.0) for x in np.arange(-60.0, 0.0, 0.5)]
    for a in np.arange(0.0, math.radians(angle_deg), 0.5 / radius):
        pts.append((radius * math.sin(a), radius * (1.0 - math.cos(a))))
    h = math.radians(angle_deg)
    end = (radius * math.sin(h), radius * (1.0 - math.cos(h)))
    pts += [(end[0] + d * math.cos(h), end[1] + d * math.sin(h)) for d in np.arange(0.0, 60.0, 0.5)]
    path = object.__new__(LanePath)
    path._set_geometry(np.array(pts), [("a_0", "a")] * len(pts), None, limits={"a_0": 50.0})
    return path


def test_projection_stays_on_its_pass_where_the_path_comes_back_near_it():
    """A route that passes a place twice (Kouvola, seed 2: a junction crossed again 325 m
    later): the car near the first pass projects onto it, even where the second pass has a
    point nearer than any point of the first (sparse points beside the car). It jumped 325 m
    ahead, and the car turned towards the later pass and ran 8 m off the road."""
    from cosim.driving import LanePath

    first = [(x, 0.0) for x in np.arange(0.0, 100.1, 5.0)]                 # points 5 m apart
    loop = [(100.0 + 20 * math.sin(a), 20.0 - 20 * math.cos(a)) for a in np.linspace(0.1, math.pi, 30)]
    back = [(x, 40.0) for x in np.arange(95.0, 60.0, -1.0)]
    down = [(52.5, y) for y in np.arange(35.0, -30.0, -0.5)]                # passes (52.5, 0.5)
    pts = np.array(first + loop + back + down)
    path = object.__new__(LanePath)
    path._set_geometry(pts, [("a_0", "a")] * len(pts), None, limits={"a_0": 50.0})
    hint = 10                                                              # the point (50, 0)
    k, s, lat = path.project(52.5, 0.1, hint)
    assert k == 10 and abs(s - 52.5) < 1e-6 and abs(lat - 0.1) < 1e-6      # on the first pass
    # and where the car has reached the second pass, it is found there
    k2, s2, lat2 = path.project(52.4, -5.0, len(first) + len(loop) + len(back) + 70)
    assert s2 > 150.0 and abs(abs(lat2) - 0.1) < 1e-6


@pytest.mark.parametrize("radius,angle,speed,limit", [(50.0, 120.0, 12.0, 0.15), (100.0, 60.0, 25.0, 0.2)])
def test_autopilot_steering_holds_a_curve_on_the_physics_car(radius, angle, speed, limit):
    """The autopilot's steering (slip-aware pure pursuit) on the raycast car in PyBullet, on
    flat ground, through a curve at urban and motorway speed: the car's centre stays within
    `limit` of the centreline. The tyres' slip angle turns the rear axle's velocity outwards
    (0.02 rad at 3 m/s2); steering by the heading alone held these curves 0.25 / 0.29 m wide."""
    import pybullet as pb

    from cosim import vehicle as V
    from cosim.driving import PurePursuit, SpeedController, plan_speed

    path = _arc_path(radius, angle)
    cid = pb.connect(pb.DIRECT)
    try:
        pb.setGravity(0, 0, -9.81, physicsClientId=cid)
        V.configure_physics(cid)
        box = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=(500, 500, 1), physicsClientId=cid)
        V.set_asphalt_friction(cid, pb.createMultiBody(0, box, basePosition=(0, 0, -1), physicsClientId=cid))
        car = V.EgoVehicle(cid)
        car.set_pose_velocity((-30.0, 0.0, 0.0), 0.0, speed=speed)
        from cosim.autopilot import Autopilot

        pp = PurePursuit(V.WHEELBASE, 1.0 / V.min_turn_radius(), **Autopilot.STEERING)
        sc = SpeedController()
        k, offs, turned = 0, [], 0.0
        for _ in range(600):
            st = car.state()
            k, s_here, off = path.project(st.x, st.y, k)
            if s_here > path.length - 20.0:
                break
            steer, _ = pp.steer(path, st.x, st.y, st.yaw, st.speed, s_here, velocity=st.velocity,
                                yaw_rate=st.yaw_rate)
            v_t = min(speed, plan_speed(path, s_here, speed, 80.0)[0])
            car.apply_control(*sc.control(v_t, st.speed, 0.1), steer)
            car.advance(0.1)
            offs.append(abs(off))
            turned = st.yaw
    finally:
        pb.disconnect(cid)
    assert s_here > path.length - 21.0                       # drove the whole curve
    assert abs(math.remainder(turned - math.radians(angle), 2 * math.pi)) < 0.05
    assert max(offs) < limit, max(offs)


def test_a_car_coming_to_the_same_junction_is_left_to_its_right_of_way(helsinki):
    """A vehicle crossing the path is timed against the car (a road taken over or under the
    path, which this world has at grade) unless it is on a road into or out of a junction
    the path crosses: there the junction's right of way decides (a car 17 m up a side street
    stopped the ego inside a Helsinki junction, braking hard at a gap of 0 m). And a crossing
    vehicle whose track is nearer than the car can stop in does not stop it there."""
    import types

    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL)
    try:
        s = sim.traffic.sumo
        ap, path = sim.driver, sim.path
        st = sim.vehicle.state()
        s_car = s_of(sim, st.x, st.y)[0]
        # the first junction ahead, and a road into it that the path does not take
        k = next(k for k in range(len(path.s)) if path.s[k] > s_car and path.lane_of[k][0].startswith(":"))
        lane_in = path.lane_of[k][0]
        junction = lane_in[1:lane_in.rfind("_", 0, lane_in.rfind("_"))]
        side = next(e for e in s.junction.getIncomingEdges(junction)
                    if not e.startswith(":") and e not in path.edges)
        elsewhere = next(e for e in s.edge.getIDList() if not e.startswith(":")
                         and junction not in (s.edge.getFromJunction(e), s.edge.getToJunction(e))
                         and e not in path.edges)
        s_e = float(path.s[k]) - 10.0               # the car 10 m before the junction at 5 m/s
        ex, ey = path.point_at(s_e)
        car = types.SimpleNamespace(x=float(ex), y=float(ey), speed=5.0)

        def crossing_car(ahead: float, lane: str):
            """A car 10 m to the left of the path, driving at 8 m/s straight at it, crossing
            `ahead` m beyond the ego's front bumper."""
            s_c = s_e + ap.front + 0.9 + ahead
            h = path.heading_at(s_c)
            px, py = path.point_at(s_c)
            x, y = px - 10.0 * math.sin(h), py + 10.0 * math.cos(h)
            one = lambda v: np.array([v])                       # noqa: E731
            snap = ActorsSnapshot(0.0, np.array(["x1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(h - math.pi / 2), one(4.5), one(1.8), one(1.5), one(8.0),
                                  one(0.0), np.array([lane], dtype=object))
            return ap._actors_on_path(snap, car, s_e, path)

        lead = crossing_car(5.0, f"{elsewhere}_0")             # a road not at the path's junctions
        assert lead is not None and lead.actor == "x1" and lead.gap < 5.0
        assert crossing_car(5.0, f"{side}_0") is None           # a road into the junction
        assert crossing_car(0.5, f"{elsewhere}_0") is None      # nearer than 5 m/s stops in (2.1 m)
    finally:
        sim.teardown()


def test_a_long_vehicle_is_mirrored_as_a_chain_along_its_path(helsinki):
    """A 12 m bus through a 90-degree turn of 9 m radius, fed to the mirror as SUMO states
    it (front-to-back chord, centre on it): mirrored as one box along the chord, its middle
    would cut the bend by L^2/8R = 2 m; as a chain of 4 m boxes along its front's path, no box
    centre is more than 0.3 m off the bend, the chain's front is SUMO's front bumper, every
    box maps to the bus, and the boxes go back to the pool when it leaves."""
    import pybullet as pb

    from cosim.mirror import _segments
    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        m = sim.mirror
        st = sim.vehicle.state()
        R, L = 9.0, 12.0
        ox, oy = st.x + 40.0, st.y + 40.0         # the turn's centre, away from the car
        # the front's path: straight east along y = oy - R, then a left turn around (ox, oy)
        def front(u):
            if u < 0.0:
                return ox + u, oy - R, 0.0
            a = min(u / R, math.pi / 2)
            x, y = ox + R * math.sin(a), oy - R * math.cos(a)
            if u > R * math.pi / 2:
                x, y = ox + R, oy + (u - R * math.pi / 2)
            return x, y, a
        def off_path(x, y):
            if x <= ox:
                return abs(y - (oy - R))
            if y >= oy:
                return abs(x - (ox + R))
            return abs(math.hypot(x - ox, y - oy) - R)
        one = lambda v: np.array([v])                       # noqa: E731
        worst_box, worst_chord, worst_err = 0.0, 0.0, 0.0
        for u in np.arange(-20.0, 25.0, 1.2):             # 12 m/s, 0.1 s steps
            fx, fy, _ = front(u)
            bx, by, _ = front(u - L)                      # SUMO's back: L along the path
            yaw = math.atan2(fy - by, fx - bx)
            cx, cy = fx - 0.5 * L * math.cos(yaw), fy - 0.5 * L * math.sin(yaw)
            snap = ActorsSnapshot(0.0, np.array(["bus1"], dtype=object), np.array(["bus"], dtype=object),
                                  one(cx), one(cy), one(yaw), one(L), one(2.5), one(3.4), one(12.0), one(0.0),
                                  np.array(["x_0"], dtype=object))
            m.update(snap)
            worst_err = max(worst_err, m.pose_error(snap))
            if u < L:
                continue                                   # (the chain starts from the chord)
            bodies = [m.active["bus1"][0]] + [b for b, _ in m.chains["bus1"]]
            assert len(bodies) == _segments(L) == 3
            for b in bodies:
                (x, y, _), _ = pb.getBasePositionAndOrientation(b, physicsClientId=sim.physics.client)
                worst_box = max(worst_box, off_path(x, y))
            worst_chord = max(worst_chord, off_path(cx, cy))
            assert all(m.body_actors()[b] == "bus1" for b in bodies)
        assert worst_chord > 1.5, worst_chord
        assert worst_box < 0.3, worst_box
        assert worst_err < 0.05, worst_err
        parked = len(m.pool.get(m.active["bus1"][1], []))
        m.update(ActorsSnapshot.empty(1.0))
        assert "bus1" not in m.active and "bus1" not in m.chains
        assert sum(len(v) for v in m.pool.values()) >= parked + 3
    finally:
        sim.teardown()


def test_a_path_keeps_its_points_after_a_sharp_turn(helsinki):
    """A chain of lane shapes drops a point a little behind the one before (lanes joined at a
    very short edge), but not everything after a turn of more than 90 degrees: at Helsinki's
    junction 1319789487 the route turns south-west into a 0.2 m edge, then north; every later
    point was "behind", and the path ran 585 m straight through the city to the next point
    ahead (the car circled in the junction and hit a pedestrian). The lane path through it
    follows its lanes."""
    from cosim.driving import LanePath, _forward_points

    # a kink of 0.5 m back is dropped; a 135-degree turn keeps what follows it
    P = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [1.5, 0.0], [2.5, 0.0], [3.5, 0.0]])
    assert _forward_points(P).tolist() == [True, True, True, False, True, True]
    turn = np.array([[0.0, 0.0], [-1.0, -1.0], [-2.0, -2.0], [-2.0, -1.0], [-2.0, 0.0], [-2.0, 5.0]])
    assert _forward_points(turn)[3:].sum() >= 2
    sim = start_sim(helsinki, start=HEL_MID)
    try:
        s = sim.traffic.sumo
        path = LanePath(s, ["157428789#2", "117164338#0", "199190672"])
        gaps = np.hypot(*np.diff(path.xy, axis=0).T)
        assert gaps.max() < 20.0, gaps.max()
        assert any(ln.startswith("199190672_") for ln, _ in path.lane_of)
        assert 100.0 < path.length < 130.0, path.length      # (0.2 + 2.8 + 0.2 + 14.6 + 95.2 m)
    finally:
        sim.teardown()


def test_forward_points_taken_in_runs_keep_what_the_point_by_point_rule_keeps():
    """``_forward_points`` takes runs of forward steps whole (a 1,000-point path took 5 ms
    point by point): on random chains with repeats, small and large steps back, zig-zags and
    turns it keeps the same points as the rule applied point by point."""
    from cosim.driving import _forward_points

    rng = np.random.default_rng(7)
    differ = 0
    for _ in range(5000):
        n = int(rng.integers(2, 60))
        steps = rng.normal(size=(n, 2)) * rng.choice([0.01, 0.5, 2.0, 6.0]) + rng.choice([0.0, 1.0]) * np.array([1.0, 0.0])
        steps[rng.random(n) < 0.1] = 0.0
        P = np.cumsum(steps, axis=0)
        differ += int((_forward_points(P) != _forward_points(P, runs=False)).any())
    assert differ == 0
    # and a path's worth of forward points with a few kinks, as the lane paths have
    P = np.cumsum(np.column_stack([np.full(1000, 1.0), np.sin(np.arange(1000) / 30.0)]), axis=0)
    P[[100, 400, 401, 700]] -= [[1.5, 0.0], [0.4, 0.0], [0.2, 0.0], [0.0, 0.0]]
    P[701] = P[700]
    assert (_forward_points(P) == _forward_points(P, runs=False)).all()
    assert not _forward_points(P)[[100, 701]].any()


def test_a_lane_path_built_in_pieces_is_the_path_built_at_once(helsinki):
    """SUMO's worker builds a route extension's lane path a few edges at a time between steps
    (``LanePath.build_steps``: at once, an 800 m path took 10-15 ms in one step): the pieces
    give the same path as ``LanePath(...)``, and a long route comes in many pieces."""
    import random

    from cosim.driving import BUILD_PIECE, LanePath

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        s = sim.traffic.sumo
        edges = sim.traffic._car_edges()
        route = []
        for k in range(20):                 # (a long one: a few start edges lead nowhere far)
            route, _ = sim.traffic.random_route(edges[(37 * k) % len(edges)], random.Random(k).getstate(), 800.0)
            if len(route) > 4 * BUILD_PIECE:
                break
        assert len(route) > 4 * BUILD_PIECE, route
        whole = LanePath(s, route)
        stepwise = object.__new__(LanePath)
        pieces = sum(1 for _ in stepwise.build_steps(s, route)) + 1
        assert pieces >= 2 * len(route) // BUILD_PIECE, pieces
        assert np.array_equal(whole.xy, stepwise.xy) and whole.lane_of == stepwise.lane_of
        assert [st.s for st in whole.stops] == [st.s for st in stepwise.stops]
        assert [c.lane for c in whole.crossings] == [c.lane for c in stepwise.crossings]
        assert whole.last_lane == stepwise.last_lane and whole.edges == stepwise.edges
    finally:
        sim.teardown()


def test_a_lane_change_forced_on_a_short_edge_is_eased_over_the_junction_after_it(helsinki):
    """Helsinki's edge 30605639#1 is 0.2 m long, and only its lane 1 leads on through junction
    142054910, 3.1 m to the right of the lane the junction before leads onto. Blended on the
    edge, the path stepped 3 m sideways within 3 m, and the car, at full lock, ran 1.6 m off it
    (SUMO logged it colliding with a truck there). The path now stays on the lane it came in
    on to the edge's end and eases onto the lane over the 15 m after it: no step sideways of
    more than half a metre a metre, and on the junction's lane by its end."""
    from cosim.driving import JUMP_EASE_M, LanePath

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        s = sim.traffic.sumo
        p = LanePath(s, ["127810493#3", "30605639#1", "17000556"])
        d = np.diff(p.xy, axis=0)
        step = np.hypot(d[:, 0], d[:, 1])
        assert step.max() < 1.2, step.max()
        turn = np.abs(np.angle(np.exp(1j * np.diff(np.arctan2(d[:, 1], d[:, 0])))))
        i0 = next(i for i, (ln, _) in enumerate(p.lane_of) if ln.startswith("30605639#1_"))
        # (from the short edge on; SUMO's own junction lane before it bends 35 degrees at a point)
        assert np.degrees(turn[i0 - 1:].max()) < 25.0, np.degrees(turn[i0 - 1:].max())   # (blended: 72)
        jl = np.array(s.lane.getShape(":142054910_0_0"))
        k = [i for i, (ln, _) in enumerate(p.lane_of) if ln == ":142054910_0_0"]
        ends = p.xy[k[-1]]
        assert np.hypot(*(ends - jl[-1])) < 0.3
        eased = p.s[k] - p.s[k[0]] >= JUMP_EASE_M
        # on the junction's lane once eased (its line: a straight segment)
        u = (jl[-1] - jl[0]) / np.hypot(*(jl[-1] - jl[0]))
        off = (p.xy[k] - jl[0]) @ np.array([-u[1], u[0]])
        assert np.abs(off[eased]).max() < 0.05 and np.abs(off[~eased]).max() > 2.0
    finally:
        sim.teardown()


def test_a_route_continued_after_overlapping_junctions_does_not_step_back(helsinki):
    """A path's continuation is built after the last points of the path it continues
    (``LanePath.lead_in``): at Helsinki's junction 142054948 the next edge, 0.2 m long, begins
    2.2 m behind the end of the junction's lane. Continued from there without them, the
    continuation kept that step back (dropped within a path, :func:`_forward_points`), and the
    car read 1.8 m off its path. The continuation, built here or by SUMO's worker, goes on
    forward."""
    import random

    from cosim.driving import LanePath, _forward_points

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        s = sim.traffic.sumo
        head = LanePath(s, ["127810490#1", "127810493#1", "127810493#2"])
        more = ["127810493#2", "127810493#3"]
        alone = LanePath(s, more, start_lane=head.last_lane)
        assert not _forward_points(np.vstack([head.xy[:head.last_edge_start], alone.xy])).all()
        new = head.extended(s, more)
        assert _forward_points(new.xy).all()
        back = np.einsum("ij,ij->i", np.diff(new.xy, axis=0)[1:], np.diff(new.xy, axis=0)[:-1])
        assert back.min() > 0.0
        # the tail SUMO's side builds with the same lead-in is the same path
        tr = sim.traffic
        for seed in range(10):          # (a draw that gives a path: some end where they begin)
            at, got, _, tail = tr.random_extension_path(["127810490#1", "127810493#1", "127810493#2"], 0,
                                                       random.Random(seed).getstate(), start_lane=head.last_lane,
                                                       lead_in=head.lead_in())
            if tail is not None:
                break
        assert at == 2 and tail is not None and got[0] == "127810493#2", (at, got)
        mine = LanePath(s, got, start_lane=head.last_lane, lead_in=head.lead_in())
        assert np.array_equal(mine.xy, tail.xy) and mine.lane_of == tail.lane_of
    finally:
        sim.teardown()


def test_a_zigzag_through_overlapping_junctions_is_no_turn(helsinki):
    """Mikonkatu, Helsinki: three signal nodes within 6 m, whose junctions overlap; each 0.2 m
    edge begins 2.2 m behind the end of the one before. The chain of lane shapes zig-zags
    back and forth, and read as a turn 19.8 m wider than the car's full lock: every route on
    from Mikonkatu was refused, and the default run stood at the end of its path from 40 s.
    A zig-zag that comes forward again within 5 m is dropped; a real sharp turn keeps its
    points (test_a_path_keeps_its_points_after_a_sharp_turn)."""
    import random

    from cosim.driving import TURN_DEVIATION_MAX_M, _forward_points, _turnaround, car_turn_radius, turn_deviation

    zig = np.array([[0.0, -10.0], [0.0, 0.0], [0.0, 0.2], [0.1, -2.0], [0.1, -1.8], [0.0, 2.6], [0.0, 12.0]])
    assert _forward_points(zig).tolist() == [True, True, True, False, False, True, True]
    assert turn_deviation(zig, car_turn_radius()) <= TURN_DEVIATION_MAX_M
    # back 4 m and never forward again (a U-turn): kept
    back = np.array([[0.0, 0.0], [0.0, 5.0], [1.0, 2.0], [2.0, 0.0], [3.0, -6.0]])
    assert _forward_points(back).all()
    sim = start_sim(helsinki, start=HEL_MID)
    try:
        s = sim.traffic.sumo
        assert not _turnaround(s, "127810493#1", "127810493#2", "127810493#3")
        at, more, _ = sim.traffic.random_extension(["127810490#1"], 0, random.Random(0).getstate())
        assert at == 0 and more[0] == "127810490#1" and len(more) > 5, more
    finally:
        sim.teardown()


def test_a_zigzag_ending_in_a_long_segment_is_no_turn(monaco):
    """Monaco, Avenue Princesse Grace at junction 21918939: netconvert left edge 161733902
    0.2 m long and 2.3 m beyond the junction after it, so the link onward steps 2.3 m back,
    then goes on along the next lane's one 14 m segment. The zig-zag rule wanted a point
    ahead within 5 m and found none (a turn's check takes the lanes' points as SUMO draws
    them), and the straight link read as a turn 20 m wider than the car's full lock. It is
    the one way by the streets from the west of Monaco to the east: routes kept SUMO's way
    through the tunnels, which the world does not have (``cosim run`` from 43.73234,7.41781
    to 43.74797,7.43496: the car drove into Tunnel de la Colle's portal and stood before a
    bench on the ground above it, "lead static", 99 m in 600 s). The chain that crosses back
    over the line through the last point kept, within 5 m of it, ends the zig-zag there. Here
    SUMO's route crosses Monaco through nine tunnel edges; the car's goes by the streets and
    arrives (before: 150 m driven in 400 s). A route into a tunnel whose way in leads only
    into it is routed again from its start where there is no way round from the tunnel's
    mouth."""
    from cosim.driving import (TURN_DEVIATION_MAX_M, _forward_points, _link_deviation, car_turn_radius, is_tunnel,
                               turn_deviation, undrivable_steps, without_turnarounds)

    # the lanes as SUMO draws them: 0.2 m, back 2.3 m, then one segment of 10 m on
    zig = np.array([[0.0, -10.0], [0.0, 0.0], [0.0, 0.2], [-0.24, -2.06], [0.63, 7.76]])
    assert _forward_points(zig).tolist() == [True, True, True, False, True]
    assert _forward_points(zig, runs=False).tolist() == [True, True, True, False, True]
    assert turn_deviation(zig, car_turn_radius()) <= TURN_DEVIATION_MAX_M
    # back, then away to the side, never ahead of the point before: a turn, kept
    side = np.array([[0.0, -10.0], [0.0, 0.0], [0.0, -3.0], [8.0, -3.0], [20.0, -3.0]])
    assert _forward_points(side).all()
    sim = start_sim(monaco, start=MC_WEST, goal=MC_PRINCESSE_GRACE, duration_s=400)
    try:
        s = sim.traffic.sumo
        link = [lk for lk in s.lane.getLinks("161733902_1") if lk[0] == "503462465#0_1"][0]
        assert _link_deviation(s, "161733902_1", link) <= TURN_DEVIATION_MAX_M
        assert undrivable_steps(s, ["353889282", "161733902", "503462465#0"]) == []
        route = list(s.simulation.findRoute("159170444", "503462465#0", vType="DEFAULT_VEHTYPE").edges)
        assert len([e for e in route if is_tunnel(s, e)]) >= 5
        assert not [e for e in sim.path.edges if is_tunnel(s, e)] and "161733902" in sim.path.edges
        # from Avenue d'Ostende SUMO takes Boulevard Louis II's tunnel, whose way in leads only
        # into it: the whole route by the car's router (the way round turns off before)
        route = list(s.simulation.findRoute("4227272", "503462465#0", vType="DEFAULT_VEHTYPE").edges)
        assert "4230891#0" in route
        fixed, _ = without_turnarounds(s, route)
        assert fixed[0] == route[0] and fixed[-1] == route[-1] and not [e for e in fixed if is_tunnel(s, e)]
        tunnels = sim.world.tunnels
        while sim.t < 400.0 and not sim.summary.arrived:
            ego = sim.step()
            assert ego.edge not in tunnels, (sim.t, ego.edge)
        assert sim.summary.arrived, (sim.t, sim.summary.distance_m)
    finally:
        sim.teardown()


def _arc_polyline(r: float, deg: float, lead: float = 10.0) -> np.ndarray:
    th = np.radians(np.linspace(0.0, deg, 60))
    arc = np.column_stack([r * np.sin(th), r * (1.0 - np.cos(th))])
    h = np.radians(deg)
    pre = np.column_stack([np.linspace(-lead, 0.0, 10), np.zeros(10)])
    post = arc[-1] + np.outer(np.linspace(0.0, lead, 10), [np.cos(h), np.sin(h)])
    return np.vstack([pre, arc[1:], post[1:]])


def test_turn_deviation_tells_the_turns_the_car_can_make():
    """How far the car at full lock runs wide of a turn: nothing on a wide curve, about
    0.6 m on SUMO's tightest 90-degree junction turns (driven: within the lane), over a
    metre and a half on a hairpin drawn at 2.9 m (Monaco's 1699777425: the car ran into a wall)."""
    from cosim.driving import TURN_DEVIATION_MAX_M, car_turn_radius, turn_deviation

    R = car_turn_radius()
    assert turn_deviation(_arc_polyline(10.0, 180.0), R) == 0.0
    assert turn_deviation(_arc_polyline(6.0, 90.0), R) == 0.0
    right = turn_deviation(_arc_polyline(2.6, 90.0), R)
    assert 0.3 < right < TURN_DEVIATION_MAX_M
    hairpin = turn_deviation(_arc_polyline(2.9, 155.0), R)
    assert hairpin > 1.5
    assert turn_deviation(_arc_polyline(3.5, 155.0), R) < hairpin   # a wider hairpin: less


def test_routes_go_around_tunnels_and_turns_the_car_cannot_make(monaco):
    """Monaco: its tunnels are not in the world, and Avenue de la Costa's hairpin at junction
    1699777425 is drawn tighter than the car can turn. The step through the hairpin is found
    undrivable, random routes from the start avoid it and every tunnel, and a route into a
    tunnel is replaced by a way around it."""
    from cosim.driving import (TURN_DEVIATION_MAX_M, _lane_allows, _link_deviation, is_tunnel, undrivable_steps,
                               without_turnarounds)

    sim = start_sim(monaco)
    try:
        s = sim.traffic.sumo
        tunnels = sim.world.tunnels
        assert len(tunnels) > 20 and all(is_tunnel(s, e) for e in list(tunnels)[:20])
        link = [lk for lk in s.lane.getLinks("176477340#2_1") if lk[0] == "200502322#0_1"][0]
        assert _link_deviation(s, "176477340#2_1", link) > TURN_DEVIATION_MAX_M
        assert undrivable_steps(s, ["176477340#2", "200502322#0"]) == [("176477340#2", "200502322#0")]
        import random
        for seed in range(6):
            route, _ = sim.traffic.random_route("4229537#0", random.Random(seed).getstate(), min_len=400.0)
            assert not [e for e in route if e in tunnels]
            assert not undrivable_steps(s, without_turnarounds(s, route)[0])
        # up the one-way street to the hairpin, every way leads through it: a route all the same
        route, _ = sim.traffic.random_route("176477340#0", random.Random(0).getstate(), min_len=400.0)
        assert undrivable_steps(s, route)[0] == ("176477340#2", "200502322#0")
        # two turns around a 0.2 m edge that each pass alone make a hairpin together: east
        # along 699218006#1, round a traffic island 9 m across, west along 503475642#0 (the
        # car at full lock would run 1.6 m wide; in the bench's world the same at junctions
        # 1079751575 / 1079751658 took it 2.7 m off its lane)
        from cosim.driving import _chain_deviation, _short, route_without_turnarounds

        l1 = [lk for lk in s.lane.getLinks("699218006#1_1") if lk[0] == "-161775593#0_1"][0]
        l2 = [lk for lk in s.lane.getLinks("-161775593#0_1") if lk[0] == "503475642#0_1"][0]
        assert _short(s, "-161775593#0") and not _short(s, "699218006#1")
        assert _link_deviation(s, "699218006#1_1", l1) <= TURN_DEVIATION_MAX_M
        assert _link_deviation(s, "-161775593#0_1", l2) <= TURN_DEVIATION_MAX_M
        assert _chain_deviation(s, "699218006#1_1", l1, l2) > 1.2
        chain = ["699218006#1", "-161775593#0", "503475642#0", "503475642#1"]
        assert undrivable_steps(s, chain) == [("699218006#1", "-161775593#0")]
        assert undrivable_steps(s, chain[:2]) == []           # (the step alone passes)
        way = route_without_turnarounds(s, "699218006#1", "503475642#1")
        assert way is None or "-161775593#0" not in way
        # SUMO's routes through a tunnel: still connected, same ends; without a tunnel where
        # the car's own router finds a way around (in Monaco the tunnels are mostly the only way)
        from cosim.driving import _drivable_lanes, route_without_turnarounds

        def nexts(e):
            return {lk[0].rsplit("_", 1)[0] for k in range(s.edge.getLaneNumber(e)) for lk in s.lane.getLinks(f"{e}_{k}")}

        surface = sorted(e for e in s.edge.getIDList() if not e.startswith(":") and e not in tunnels
                         and _drivable_lanes(s, e))
        rng = random.Random(3)
        tried = 0
        for _ in range(400):
            try:
                route = list(s.simulation.findRoute(rng.choice(surface), rng.choice(surface), vType="DEFAULT_VEHTYPE").edges)
            except Exception:       # (SUMO's error when there is no route)
                continue
            if not any(e in tunnels for e in route):
                continue
            tried += 1
            fixed, detours = without_turnarounds(s, route)
            assert fixed[0] == route[0] and fixed[-1] == route[-1]
            assert all(b in nexts(a) for a, b in zip(fixed, fixed[1:]))      # connected
            if any(e in tunnels for e in fixed):
                assert route_without_turnarounds(s, route[0], route[-1]) is None or \
                    any(e in tunnels for e in route_without_turnarounds(s, route[0], route[-1]))
            if tried >= 8:
                break
        assert tried >= 5
        # a start on a tunnel's lane snaps to the nearest lane on the surface
        tl = next(f"{e}_0" for e in sorted(tunnels) if _drivable_lanes(s, e) and s.lane.getLength(f"{e}_0") > 30)
        P = np.array(s.lane.getShape(tl))
        lane, _, px, py, _, dist = sim.traffic.snap_lane(*P[len(P) // 2])
        assert lane.rsplit("_", 1)[0] not in tunnels and dist > 0.0
        # and where SUMO's nearest lane is a junction's that leads into a tunnel (a start
        # there went on into the tunnel, and the car drove on bare terrain into a sidewalk)
        into = []
        for jl in s.lane.getIDList():
            links = s.lane.getLinks(jl) if jl.startswith(":") else ()
            if links and links[0][0].rsplit("_", 1)[0] in tunnels and _lane_allows(s, jl, "passenger"):
                Q = np.array(s.lane.getShape(jl))
                at = Q[len(Q) // 2] if len(Q) > 2 else Q.mean(axis=0)
                if s.simulation.convertRoad(float(at[0]), float(at[1]), False, "passenger")[0].startswith(":"):
                    into.append(at)
        assert into
        for at in into:
            lane, *_ = sim.traffic.snap_lane(float(at[0]), float(at[1]))
            assert lane.rsplit("_", 1)[0] not in tunnels and not lane.startswith(":"), (at, lane)
    finally:
        sim.teardown()


def _first_sharp_turn(sim) -> tuple[float, float]:
    """The first sharp turn of the car's path ahead (the heading changes by more than 60
    degrees within 15 m): its side (+1 left, -1 right: where its inside is) and the arc length
    of its apex (where the heading turns fastest)."""
    path = sim.path
    st = sim.vehicle.state()
    s_car = s_of(sim, st.x, st.y)[0]
    s0 = next(float(u) for u in np.arange(s_car + 10.0, path.length - 20.0, 0.5)
              if abs(math.remainder(path.heading_at(u + 15.0) - path.heading_at(u), 2 * math.pi))
              > math.radians(60))
    turn = math.remainder(path.heading_at(s0 + 15.0) - path.heading_at(s0), 2 * math.pi)
    s_apex = max(np.arange(s0, s0 + 15.0, 0.5), key=lambda u: abs(math.remainder(
        path.heading_at(u + 2.5) - path.heading_at(u - 2.5), 2 * math.pi)))
    return (1.0 if turn > 0 else -1.0), float(s_apex)


def test_a_car_standing_inside_a_turn_beside_the_corridor_stops_the_car_before_its_sweep_touches_it(helsinki):
    """In a turn tighter than the car follows, pure pursuit cuts the corner: a vehicle
    standing inside the turn, in a lane of its own beside the path, is in the car's way though
    a car exactly on the path would pass it (Kouvola, seed 3: the car brushed a queued car's
    corner at 2.9 m/s). The corridor check does not see it; the car's sweep (its footprint
    rolled along where its steering takes it) does; moved 2 m further from the path, not."""
    import types

    from cosim.autopilot import SWEEP_MARGIN_M
    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID, goal=(60.170763, 24.948623))     # a right turn 420 m on
    try:
        ap, path = sim.driver, sim.path
        side, s_apex = _first_sharp_turn(sim)
        s_e = float(s_apex) - 7.0                        # the car 7 m before the apex at 3 m/s
        ex, ey = path.point_at(s_e)
        car = types.SimpleNamespace(x=float(ex), y=float(ey), yaw=path.heading_at(s_e), speed=3.0, steer=0.0)
        one = lambda v: np.array([v])                    # noqa: E731

        def standing(offset: float):
            h = path.heading_at(float(s_apex))
            px, py = path.point_at(float(s_apex))
            x, y = px - side * offset * math.sin(h), py + side * offset * math.cos(h)
            return ActorsSnapshot(0.0, np.array(["q1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(h), one(4.5), one(1.8), one(1.5), one(0.0), one(0.0),
                                  np.array(["x_0"], dtype=object))

        # offsets of the standing car's centre from the path where a car exactly on the path
        # would pass it with more than the sweep's margin: the nearest the sweep touches
        found = None
        for offset in np.arange(ap.width / 2.0 + 0.9 + SWEEP_MARGIN_M + 0.05, 4.01, 0.05):
            snap = standing(float(offset))
            assert ap._actors_on_path(snap, car, s_e, path) is None       # not in the corridor
            hit = ap._sweep(car, path, s_e, snap, ap.pp)
            if hit is None:
                break
            found = (float(offset), hit)
        assert found is not None, "the sweep does not reach beyond a car exactly on the path"
        offset, (dist, actor, kind) = found
        assert actor == "q1" and kind == "vehicle" and 0.0 <= dist <= 7.0 + 4.5
        assert ap._sweep(car, path, s_e, standing(offset + 2.0), ap.pp) is None
    finally:
        sim.teardown()


def _longest_car_lane(sumo) -> str:
    """The longest lane outside junctions that passenger cars may use."""
    return max((ln for ln in sumo.lane.getIDList() if not ln.startswith(":")
                and "passenger" in (sumo.lane.getAllowed(ln) or ("passenger",))), key=sumo.lane.getLength)


def _one_actor(vid: str, x: float = 0.0, y: float = 0.0, yaw: float = 0.0, speed: float = 0.0,
               kind: str = "passenger", lane: str = "x_0"):
    """A snapshot of one 4.5 x 1.8 m actor, as the mirror's snapshots give it."""
    from cosim.traffic import ActorsSnapshot

    one = lambda v: np.array([v])                        # noqa: E731
    return ActorsSnapshot(0.0, np.array([vid], dtype=object), np.array([kind], dtype=object), one(x), one(y),
                          one(yaw), one(4.5), one(1.8), one(1.5), one(speed), one(0.0),
                          np.array([lane], dtype=object))


def test_a_standoff_with_a_vehicle_in_the_sweep_ends_with_it_taken_out_of_sumo(helsinki):
    """The car stands for its sweep's sake before a vehicle that stands too (Monaco, seed 17:
    inside a junction each waited for the other until SUMO teleported the vehicle 120 s
    later): after STANDOFF_S the autopilot has SUMO take that vehicle out, once; not while
    either moves, not for a person."""
    from cosim.autopilot import STANDOFF_S
    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        ap, tr = sim.driver, sim.traffic
        s = tr.sumo
        lane = _longest_car_lane(s)
        edge = lane.rsplit("_", 1)[0]
        s.route.add("r_stand", [edge])
        for vid, pos in (("stander2", "60"), ("stander", "20")):
            s.vehicle.add(vid, "r_stand", typeID="DEFAULT_VEHTYPE", depart="now", departPos=pos,
                          departSpeed="0", departLane=lane.rsplit("_", 1)[1])
        for _ in range(int(STANDOFF_S / 0.1) + 20):      # they stand, in SUMO, a little longer
            for vid in ("stander", "stander2"):
                s.vehicle.setSpeed(vid, 0.0)
            tr.step()
        assert {"stander", "stander2"} <= set(s.vehicle.getIDList())
        x, y = s.vehicle.getPosition("stander")
        one = lambda v: np.array([v])                    # noqa: E731

        def snap(kind="passenger", speed=0.0, vid="stander"):
            return ActorsSnapshot(0.0, np.array([vid], dtype=object), np.array([kind], dtype=object),
                                  one(x), one(y), one(0.0), one(4.5), one(1.8), one(1.5), one(speed), one(0.0),
                                  np.array([lane], dtype=object))

        ap.sweep, ap.reason = (0.0, "stander", "vehicle"), "clearance vehicle"
        t = 0.0
        while t < 2.0 * STANDOFF_S:                      # it moves every 10 s: no standoff
            ap._standoff(0.0, t, snap(speed=1.0) if t % 10.0 == 0.0 else snap())
            t += 0.5
        assert ap.stats.standoffs == 0
        while t < 4.0 * STANDOFF_S:                      # a person: none
            ap._standoff(0.0, t, snap(kind="person"))
            t += 0.5
        ap._standoff(0.5, t, snap())                     # (the car rolling: none)
        assert ap.stats.standoffs == 0 and "stander" in s.vehicle.getIDList()
        t0 = t
        while t < t0 + STANDOFF_S - 0.5:                 # standing, both: not yet
            ap._standoff(0.0, t, snap())
            t += 0.5
        assert ap.stats.standoffs == 0 and "stander" in s.vehicle.getIDList()
        for _ in range(4):
            ap._standoff(0.0, t, snap())
            t += 0.5
        assert ap.stats.standoffs == 1
        assert [e for e in ap.stats.events if e[1] == "standoff"][0][2].startswith("stander")
        tr.step()
        assert "stander" not in s.vehicle.getIDList() and tr.stats.released == 1
        # the car waiting for a vehicle standing on a lane over its path (Monaco, seed 1: a
        # circle of waits through SUMO's merge): the same; not for a lead on its own lanes
        from cosim.autopilot import Lead

        ap.sweep, ap.reason = None, "lead vehicle"
        for source, n in (("actors", 1), ("conflict", 2)):
            ap.lead, t0 = Lead(4.0, 0.0, "vehicle", source, "stander2"), t
            while t < t0 + STANDOFF_S + 2.0:
                ap._standoff(0.0, t, snap(vid="stander2"))
                t += 0.5
            assert ap.stats.standoffs == n, source
        tr.step()
        assert "stander2" not in s.vehicle.getIDList() and tr.stats.released == 2
    finally:
        sim.teardown()


def test_a_standoff_goes_on_when_a_network_swap_renames_the_vehicle(helsinki):
    """A network swap carries the vehicles near the car into the new SUMO under a new id
    ("veh973" -> "veh973~1") with SUMO's waiting time at 0. The standoff's wait went on from 0
    too: a Lauf car waited 40 s before a bus that waited for it, in place of 20 s. Now the
    autopilot's wait goes on across the new id, and SUMO's check takes a carried vehicle that
    has stood all the while since it came in: here it comes in 10 s into the standoff and is
    taken out at STANDOFF_S, not 10 s later."""
    from cosim.autopilot import STANDOFF_S

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        ap, tr = sim.driver, sim.traffic
        s = tr.sumo
        lane = _longest_car_lane(s)
        s.route.add("r_carried", [lane.rsplit("_", 1)[0]])

        t, taken = 0.0, None
        while t < STANDOFF_S + 12.0 and taken is None:
            if abs(t - 10.0) < 1e-6:                     # the swap: the vehicle comes in anew
                s.vehicle.add("swapped~1", "r_carried", typeID="DEFAULT_VEHTYPE", depart="now", departPos="30",
                              departSpeed="0", departLane=lane.rsplit("_", 1)[1])
            vid = "swapped" if t < 10.0 else "swapped~1"
            if t > 10.0:
                s.vehicle.setSpeed(vid, 0.0)
            ap.sweep, ap.reason = (0.0, vid, "vehicle"), "clearance vehicle"
            ap._standoff(0.0, t, _one_actor(vid, lane=lane))
            if ap.stats.standoffs:
                taken = t
            tr.step()
            t = round(t + 0.1, 1)
        assert taken is not None and taken < STANDOFF_S + 1.5, taken
        assert [e for e in ap.stats.events if e[1] == "standoff"][0][2].startswith("swapped~1 taken out after 2")
        tr.step()
        assert "swapped~1" not in s.vehicle.getIDList()
    finally:
        sim.teardown()


def test_a_circle_of_waits_through_a_queue_behind_the_car_ends_with_the_lead_taken_out(helsinki):
    """The car follows a vehicle that stands before it (its lidar's lead), and SUMO has that
    vehicle wait for one that stands in the queue behind the car (Monaco, seed 7: in a
    junction cluster, a vehicle standing across the car's path waited for the queue SUMO kept
    behind the car; SUMO teleported one every 120 s, and the car drove 114 m in 300 s). After
    STANDOFF_S the lead is taken out, once SUMO's chain of leaders from it reaches the car;
    not while the queue stands too far behind the car (the circle is not closed), then it is."""
    from cosim.autopilot import STANDOFF_S, Lead
    from cosim.traffic import EGO_ID

    sim = start_sim(helsinki, start=HEL_MID, speed_mps=10.0)
    try:
        for _ in range(60):                              # the car 40 m or so into its road
            sim.step()
        ap, tr = sim.driver, sim.traffic
        s = tr.sumo
        lane, pos = s.vehicle.getLaneID(EGO_ID), s.vehicle.getLanePosition(EGO_ID)
        assert not lane.startswith(":") and pos > 36.0, (lane, pos)
        edge = lane.rsplit("_", 1)[0]
        s.route.add("r_queue", [edge] + list(sim.route[sim.route.index(edge) + 1:][:2]))
        for vid, back in (("queued", 22.0), ("circler", 32.0)):
            s.vehicle.add(vid, "r_queue", typeID="DEFAULT_VEHTYPE", depart="now", departPos=f"{pos - back:.1f}",
                          departSpeed="0", departLane=lane.rsplit("_", 1)[1])
        tr.step()                                        # (in)
        assert {"queued", "circler"} <= set(s.vehicle.getIDList())

        ap.sweep, ap.reason = None, "lead vehicle"
        ap.lead = Lead(4.0, 0.0, "vehicle", "lidar", "circler")
        t = 0.0

        def stand(seconds):
            nonlocal t
            end = t + seconds
            while t < end:
                for vid in (EGO_ID, "queued") + (("circler",) if ap.stats.standoffs == 0 else ()):
                    s.vehicle.setSpeed(vid, 0.0)
                tr.step()
                ap._standoff(0.0, t, _one_actor("circler", lane=lane))
                t += 0.1

        # the queue 17.5 m behind the car: SUMO's chain of leaders (10 m) does not reach it
        stand(STANDOFF_S + 3.0)
        assert ap.stats.standoffs == 0 and "circler" in s.vehicle.getIDList()
        assert not tr.waits_for_ego("circler")
        # the queue up behind the car: the chain circler -> queued -> the car, and the lead,
        # standing longer than STANDOFF_S, is taken out within a second or two
        s.vehicle.moveTo("queued", lane, pos - 8.0)
        s.vehicle.moveTo("circler", lane, pos - 16.0)
        tr.step()
        assert tr.waits_for_ego("circler")
        stand(2.5)
        assert ap.stats.standoffs == 1
        assert [e for e in ap.stats.events if e[1] == "standoff"][0][2].startswith("circler")
        tr.step()
        assert "circler" not in s.vehicle.getIDList() and "queued" in s.vehicle.getIDList()
    finally:
        sim.teardown()


def test_a_car_already_on_a_crossing_junction_lane_goes_on_when_it_clears_it_in_time(helsinki):
    """A junction lane that runs over the path (two junctions drawn into each other) is a
    stretch the car stops before while a vehicle on it would meet the car there. When the car
    is in the stretch already, it stops only if the vehicle comes before the car is out of it
    (a Monaco car braked from 8.2 to 2.5 m/s inside such a stretch for a car 11 m off to the
    side at 3.3 m/s); a vehicle standing in the stretch still stops it."""
    from cosim.driving import _resample
    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL)
    try:
        ap, path = sim.driver, sim.path
        st = sim.vehicle.state()
        s_e = s_of(sim, st.x, st.y)[0] + 20.0
        s_c = s_e + 1.0                              # the lane crosses the path under the car's bonnet
        h = path.heading_at(s_c)
        cx, cy = path.point_at(s_c)
        nx, ny = -math.sin(h), math.cos(h)           # the lane runs from the path's left across it
        P = _resample(np.array([[cx + 40.0 * nx, cy + 40.0 * ny], [cx - 40.0 * nx, cy - 40.0 * ny]]), 1.0)
        arc = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
        lane = ":x_0_0"
        ap._lane_shapes[lane] = (P, arc)
        one = lambda v: np.array([v])                # noqa: E731

        def vehicle(before: float, speed: float):
            """A car on the lane, its front `before` m before the path's centreline."""
            fx, fy = cx + before * nx, cy + before * ny
            x, y = fx - 2.25 * (-nx), fy - 2.25 * (-ny)          # its centre, 2.25 m behind its front
            return ActorsSnapshot(0.0, np.array(["c1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(math.atan2(-ny, -nx)), one(4.5), one(1.8), one(1.5),
                                  one(speed), one(0.0), np.array([lane], dtype=object))

        # far up the lane at 3 m/s: the car at 8 m/s is out of the stretch long before it comes
        assert ap._lane_conflict(path, lane, vehicle(25.0, 3.0), 0, s_e, 8.0) is None
        # about to enter the stretch: the car stops (in the stretch: gap 0)
        lead = ap._lane_conflict(path, lane, vehicle(3.0, 6.0), 0, s_e, 8.0)
        assert lead is not None and lead.actor == "c1" and lead.gap == 0.0
        # standing on the path
        assert ap._lane_conflict(path, lane, vehicle(-1.0, 0.0), 0, s_e, 8.0) is not None
        # but not where SUMO has it wait for the car (Kouvola, seed 1: a U-turn waited for the
        # car, the car for it; its body, if in the way, is the sweep's)
        ap._waits_for_ego = lambda vid: vid == "c1"     # (SUMO's side: test_traffic)
        assert ap._lane_conflict(path, lane, vehicle(-1.0, 0.0), 0, s_e, 8.0) is None
        del ap._waits_for_ego
        # the car itself slow: the same far vehicle comes before it is out
        assert ap._lane_conflict(path, lane, vehicle(25.0, 3.0), 0, s_e, 0.5) is not None

        # a lane that comes in from behind on the left and joins the path beside the car, then
        # runs on along it: a vehicle on it behind the car comes up behind it (Lauf, seed 40:
        # the car braked from 4.5 to 1.8 m/s in a junction for one 9 m behind at 3.7 m/s)
        h_e = path.heading_at(s_e)
        e = np.array(path.point_at(s_e), dtype=float)
        t_, n_ = np.array([math.cos(h_e), math.sin(h_e)]), np.array([-math.sin(h_e), math.cos(h_e)])
        P = _resample(np.array([e - 8.0 * t_ + 8.0 * n_, e + 1.0 * t_, e + 30.0 * t_]), 1.0)
        merge = ":m_0_0"
        ap._lane_shapes[merge] = (P, np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))]))
        d = (P[1] - P[0]) / np.hypot(*(P[1] - P[0]))

        def merging(back: float, speed: float):
            """A car on that lane, its front `back` m along the lane from where it begins."""
            i = int(round(back))
            d_ = (P[i + 1] - P[i]) / np.hypot(*(P[i + 1] - P[i]))
            x, y = P[i] - 2.25 * d_
            return ActorsSnapshot(0.0, np.array(["m1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(math.atan2(d_[1], d_[0])), one(4.5), one(1.8), one(1.5),
                                  one(speed), one(0.0), np.array([merge], dtype=object))

        assert d @ t_ > 0.5                            # (it runs the path's way)
        assert ap._lane_conflict(path, merge, merging(3.0, 3.7), 0, s_e, 4.5) is None
        # the car creeping: the vehicle would get to the join with the car still beside it
        assert ap._lane_conflict(path, merge, merging(3.0, 3.7), 0, s_e, 0.3) is not None
        # standing on the lane ahead of the car, past the join: in the car's way
        assert ap._lane_conflict(path, merge, merging(30.0, 0.0), 0, s_e, 4.5) is not None
    finally:
        sim.teardown()


def test_a_car_heading_into_a_junction_lane_over_the_path_is_timed_from_beside_the_car(helsinki):
    """A junction lane that runs over the path (junctions drawn into each other) is watched
    for the vehicles on the lanes that lead into it too, wherever they are: beside the car or
    behind it (Monaco, seed 6: a car came up on the left on a road into the next junction,
    whose lane across the car's road starts 25 m from that junction, and drove into the car's
    side; the corridor check had left it out as beside the car). Standing, or on a lane that
    does not lead there, it does not stop the car."""
    import types

    from cosim.driving import _resample, junction_of
    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL)
    try:
        ap, path = sim.driver, sim.path
        st = sim.vehicle.state()
        s_e = s_of(sim, st.x, st.y)[0] + 20.0
        s_c = s_e + 15.0                                 # the junction lane crosses the path here
        h = path.heading_at(s_c)
        c = np.array(path.point_at(s_c), dtype=float)
        t, n = np.array([math.cos(h), math.sin(h)]), np.array([-math.sin(h), math.cos(h)])

        def line(a, b):
            P = _resample(np.array([c + a[0] * t + a[1] * n, c + b[0] * t + b[1] * n]), 1.0)
            return P, np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])

        approach, via = "appr_0", ":x_0_0"
        ap._lane_shapes[approach] = line((-45.0, 8.0), (-6.0, 8.0))     # a road on the left, along the path
        ap._lane_shapes[via] = line((-6.0, 8.0), (2.0, -6.0))           # its junction lane, across the path
        ap._lane_vias = {approach: (via,), "other_0": ()}
        if ap._path is not path:
            ap._new_path(path)
        ex, ey = path.point_at(s_e)
        car = types.SimpleNamespace(x=float(ex), y=float(ey), yaw=path.heading_at(s_e), speed=6.0, steer=0.0)
        one = lambda v: np.array([v])                    # noqa: E731

        def vehicle(along: float, speed: float, lane: str = approach):
            """A car on the road on the left, its centre `along` m from the car's (+ = ahead)."""
            x, y = c + (-15.0 + along) * t + 8.0 * n
            return ActorsSnapshot(0.0, np.array(["c1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(h), one(4.5), one(1.8), one(1.5), one(speed), one(0.0),
                                  np.array([lane], dtype=object))

        assert ap._over(path, via) and ap._conflict_vias(path, approach) == (via,)
        # the same lane in a junction the path goes through is watched too (Monaco, dense seed
        # 22: a left turn from the opposite road swept across the car's right turn, SUMO's two
        # links not foes); one SUMO makes a foe of the path's is left to the right of way (below)
        own = next(junction_of(ln) for ln, _ in path.lane_of if ln.startswith(":"))
        ap._lane_shapes[f":{own}_99_0"] = ap._lane_shapes[via]
        assert ap._over(path, f":{own}_99_0")
        # but not the path's own junction lanes: a vehicle headed onto them comes along the
        # path behind the car (Lauf, seed 40: one 9 m behind braked the car in the junction)
        mine = next(ln for ln, _ in path.lane_of if ln.startswith(":"))
        assert not ap._over(path, mine)
        # beside the car at 8 m/s: it comes to the lane over the path when the car does
        lead = ap._actors_on_path(vehicle(0.0, 8.0), car, s_e, path)
        assert lead is not None and lead.actor == "c1"
        assert 0.0 < lead.gap < 15.0 - ap.front          # a stop before the stretch
        # 10 m behind the car, as fast: still in time to meet it there
        assert ap._actors_on_path(vehicle(-10.0, 8.0), car, s_e, path) is not None
        # standing at the end of its road, or on a road that does not lead there: no stop
        assert ap._actors_on_path(vehicle(0.0, 0.0), car, s_e, path) is None
        assert ap._actors_on_path(vehicle(0.0, 8.0, "other_0"), car, s_e, path) is None
        # far behind: gone through long after the car
        assert ap._actors_on_path(vehicle(-40.0, 4.0), car, s_e, path) is None
        # a junction lane SUMO makes a foe of the path's: the junction's right of way decides
        ap._foe_lanes = lambda path_, s_: {via}
        assert ap._actors_on_path(vehicle(0.0, 8.0), car, s_e, path) is None
    finally:
        sim.teardown()


def test_the_car_brakes_when_it_rolls_back_and_holds_where_it_cannot_climb(helsinki):
    """Rolling backwards while it drives forward, the car brakes instead of rolling on into
    what is behind it (Monaco, seed 10: a 14 m street at 50 %, a DEM cliff, the car rolled back
    at full throttle to 4.2 m/s into a car behind). At full throttle that is a road too steep
    for it: it stays on the brakes on this path ("too steep"); a rollback at part throttle (a
    hill start's sag) brakes only while it lasts."""
    import dataclasses

    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL)
    try:
        for _ in range(20):
            sim.step()
        ap = sim.driver
        st = sim.vehicle.state()
        s_here = s_of(sim, st.x, st.y)[0]
        actors = sim.last_snapshot
        back = dataclasses.replace(st, speed=-0.6)
        # part throttle: brakes while rolling back, drives on after
        ap.last = (0.4, 0.0, 0.0)
        throttle, brake, _ = ap.control(back, s_here, actors, 0.1)
        assert (throttle, brake) == (0.0, 1.0) and ap.reason == "rolling back"
        throttle, brake, _ = ap.control(dataclasses.replace(st, speed=0.0), s_here, actors, 0.1)
        assert throttle > 0.0 and brake == 0.0 and ap.reason != "rolling back"
        # full throttle: too steep, held on the brakes, also once it stands
        ap.last = (1.0, 0.0, 0.0)
        throttle, brake, _ = ap.control(back, s_here, actors, 0.1)
        assert (throttle, brake) == (0.0, 1.0) and ap.reason == "too steep"
        throttle, brake, _ = ap.control(dataclasses.replace(st, speed=0.0), s_here, actors, 0.1)
        assert (throttle, brake) == (0.0, 1.0) and ap.reason == "too steep"
        assert ap.stats.rollbacks == 2
        # a new path (a re-plan) tries again
        sim.replan()
        sim.step()
        assert ap.reason != "too steep"
    finally:
        sim.teardown()


def test_the_sweep_leaves_out_a_car_queued_just_behind(helsinki):
    """The car's sweep looks where the car goes: a car queued within the sweep's margin behind
    its rear bumper is not in its way (Monaco, dense seed 3: a car standing 5 cm behind held
    the car for good, "clearance vehicle" at 0 m, nine re-plans); the same car as close in
    front is."""
    import types

    from cosim.autopilot import SWEEP_MARGIN_M
    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID, goal=HEL_GOAL)
    try:
        ap, path = sim.driver, sim.path
        st = sim.vehicle.state()
        s_e = s_of(sim, st.x, st.y)[0] + 10.0
        ex, ey = path.point_at(s_e)
        h = path.heading_at(s_e)
        car = types.SimpleNamespace(x=float(ex), y=float(ey), yaw=h, speed=0.0, steer=0.0)
        ap._lat, ap._k = 0.5, path.index_at(s_e)         # off the path: the sweep rolls
        one = lambda v: np.array([v])                    # noqa: E731

        def queued(along: float):
            """A 4.5 m car on the path, its centre `along` m from the car's (+ = ahead)."""
            x, y = ex + along * math.cos(h), ey + along * math.sin(h)
            return ActorsSnapshot(0.0, np.array(["q1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(h), one(4.5), one(1.8), one(1.5), one(0.0), one(0.0),
                                  np.array(["x_0"], dtype=object))

        gap = 0.5 * SWEEP_MARGIN_M                        # bumper to bumper, within the margin
        assert ap._sweep(car, path, s_e, queued(-(ap.length / 2 + 2.25 + gap)), ap.pp) is None
        hit = ap._sweep(car, path, s_e, queued(ap.length / 2 + 2.25 + gap), ap.pp)
        assert hit is not None and hit[1] == "q1" and hit[0] == 0.0
    finally:
        sim.teardown()


def _highest_deck_point(sim, lane: str):
    """The point of `lane` (every 2 m) where the road surface stands highest over the terrain:
    (x, y, rise, the lane's shape, its arc lengths, the sample's arc length)."""
    P = np.array(sim.traffic.sumo.lane.getShape(lane))[:, :2]
    d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
    ss = np.arange(0.0, d[-1], 2.0)
    X, Y = np.interp(ss, d, P[:, 0]), np.interp(ss, d, P[:, 1])
    rise = sim.world.road_top_z(X, Y) - sim.world.ground_z(X, Y)
    k = int(np.nanargmax(rise))
    return float(X[k]), float(Y[k]), float(rise[k]), P, d, float(ss[k])


def test_a_car_on_a_bridge_is_mirrored_on_its_deck_not_on_the_ground(monaco):
    """A vehicle on a bridge's lane (OSM bridge=*) stands on the deck, not on the terrain under
    it (Monaco, seed 13: a car on Boulevard du Larvotto's bridge, mirrored 5 m down on the
    terrain, drove through the car standing on the avenue beneath); the same spot on another
    lane stays on the ground."""
    import pybullet as pb

    from cosim.traffic import ActorsSnapshot

    sim = start_sim(monaco)
    try:
        lane = "503783368_0"
        assert lane in sim.world.bridge_lanes()
        x, y, rise, P, d, sk = _highest_deck_point(sim, lane)
        assert rise > 3.0                         # the deck stands over the ground here
        h = float(np.arctan2(*(P[min(len(P) - 1, int(np.searchsorted(d, sk)))] - P[max(0, int(np.searchsorted(d, sk)) - 1)])[::-1]))
        one = lambda v: np.array([v])             # noqa: E731
        ground = float(sim.world.ground_z([x], [y])[0])

        def mirrored(on_lane):
            snap = ActorsSnapshot(0.0, np.array(["b1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(x), one(y), one(h), one(4.5), one(1.8), one(1.5), one(10.0), one(0.0),
                                  np.array([on_lane], dtype=object))
            sim.mirror.update(snap)
            return pb.getBasePositionAndOrientation(sim.mirror.body_of("b1"), physicsClientId=sim.physics.client)[0][2]

        assert mirrored(lane) > ground + 3.0
        assert mirrored("25103769#2_1") < ground + 2.0
        # a person on a footbridge's lane (SUMO gives persons' lanes too) stands on its deck
        foot = "-93137606_0"
        assert foot in sim.world.bridge_lanes()
        fx, fy, _, _, _, _ = _highest_deck_point(sim, foot)
        walker = ActorsSnapshot(0.0, np.array(["p1"], dtype=object), np.array(["person"], dtype=object),
                                one(fx), one(fy), one(0.0), one(0.5), one(0.5), one(1.75), one(1.2),
                                one(0.0), np.array([foot], dtype=object))
        sim.mirror.update(walker)
        z_p = pb.getBasePositionAndOrientation(sim.mirror.body_of("p1"), physicsClientId=sim.physics.client)[0][2]
        assert z_p > float(sim.world.ground_z([fx], [fy])[0]) + 3.0
        assert sim.mirror.raised["p1"] > 3.0
    finally:
        sim.teardown()


def test_a_car_that_starts_on_a_bridge_starts_on_its_deck(monaco):
    """The car starting on a bridge's lane stands on the deck, not on the ground under it
    (Portland: a start on the Hawthorne Bridge's lane -282174242#0_0 put the car on the river
    8 m below, and it drove along the water into the bank)."""
    sim = start_sim(monaco)
    try:
        lane = "503783368_0"
        P = np.array(sim.traffic.sumo.lane.getShape(lane))[:, :2]
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
        ss = np.arange(0.0, d[-1], 2.0)
        X, Y = np.interp(ss, d, P[:, 0]), np.interp(ss, d, P[:, 1])
        rise = sim.world.road_top_z(X, Y) - sim.world.ground_z(X, Y)
        # (a point high over the ground where the start snaps onto the deck's lane)
        k = next(k for k in np.argsort(-np.nan_to_num(rise)).tolist() if sim.traffic.snap_lane(X[k], Y[k])[0] == lane)
        assert rise[k] > 3.0
        lon, lat = sim.world.frame.to_lonlat(X[k], Y[k])
    finally:
        sim.teardown()
    sim = start_sim(monaco, start=(float(lat), float(lon)), duration_s=2.0)
    try:
        st = sim.vehicle.state()
        ground = float(sim.world.ground_z([st.x], [st.y])[0])
        assert st.z > ground + 2.5, (st.z, ground)
        sim.run()
        assert sim.vehicle.state().z > ground + 2.5
    finally:
        sim.teardown()


@pytest.fixture(scope="module")
def portland_decks(tmp_path_factory):
    """Portland by I-405's ramps (the bench's centre): junctions on decks."""
    return _portland_world(tmp_path_factory, "portland-decks", (45.5152, -122.6784))


def test_a_car_on_a_junction_on_a_deck_is_mirrored_on_the_deck(portland_decks, tmp_path):
    """A junction every road of which is a bridge (a ramp joining a deck) lies on the deck: its
    junction lanes are bridge lanes, and a car on one stands on the deck (Portland: 102 such
    junction lanes 3-19 m over the terrain, where the mirror put cars on the ground), pitched
    as the deck is. A ``bridges.json`` of an older version beside a network is not trusted."""
    import json
    import shutil

    import pybullet as pb

    from cosim.driving import junction_of
    from cosim.traffic import ActorsSnapshot
    from cosim.world import BRIDGE_LANES_VERSION, World, write_bridge_lanes
    from netgen.roadnet import read_net

    sim = start_sim(portland_decks)
    try:
        lanes = sim.world.bridge_lanes()
        lane = ":40641464_0_0"
        assert lane in lanes
        net = read_net(sim.world.net_file)
        meeting = [e for e in net.normal_edges() if "40641464" in (e.from_node, e.to_node)]
        assert len(meeting) >= 2 and all(e.bridge for e in meeting)
        on_ground = {j for e in net.normal_edges() if not e.bridge for j in (e.from_node, e.to_node)}
        assert not any(ln.startswith(":") and junction_of(ln) in on_ground for ln in lanes)
        x, y, rise, P, d, sk = _highest_deck_point(sim, lane)
        assert rise > 3.0
        k = max(1, int(np.searchsorted(d, sk)))
        h = float(np.arctan2(*(P[min(k, len(P) - 1)] - P[k - 1])[::-1]))
        one = lambda v: np.array([v])             # noqa: E731
        sim.mirror.update(ActorsSnapshot(0.0, np.array(["j1"], dtype=object), np.array(["passenger"], dtype=object),
                                         one(x), one(y), one(h), one(4.5), one(1.8), one(1.5), one(5.0), one(0.0),
                                         np.array([lane], dtype=object)))
        pos, q = pb.getBasePositionAndOrientation(sim.mirror.body_of("j1"), physicsClientId=sim.physics.client)
        assert pos[2] > float(sim.world.ground_z([x], [y])[0]) + 3.0
        # pitched as the deck (a junction's plane), not as the hillside under it
        terrain = math.degrees(float(sim.world.slope_pitch(np.array([x]), np.array([y]), np.array([h]))[0]))
        assert abs(terrain) > 10.0 and abs(math.degrees(pb.getEulerFromQuaternion(q)[1])) < 5.0, terrain
        # the side file a window's build writes: this version's is read, an older one is not
        net_copy = tmp_path / "world.net.xml"
        shutil.copy(sim.world.net_file, net_copy)
        bare = World.__new__(World)
        bare.net_file = net_copy
        side = tmp_path / "world.net.xml.bridges.json"
        side.write_text(json.dumps(sorted(ln for ln in lanes if not ln.startswith(":"))))   # version 1
        assert bare.bridge_lanes() == lanes
        write_bridge_lanes(net_copy)
        assert json.loads(side.read_text())["version"] == BRIDGE_LANES_VERSION
        side.write_text(json.dumps({"version": BRIDGE_LANES_VERSION, "lanes": ["x_0"]}))
        fresh = World.__new__(World)
        fresh.net_file = net_copy
        assert fresh.bridge_lanes() == frozenset({"x_0"})
    finally:
        sim.teardown()


def test_a_car_on_another_level_is_no_obstacle(monaco):
    """A car on a bridge's deck crossing over the path, or on the road under a deck the path
    goes over, is on another level: no lead (Monaco, seed 13: the car stopped for a car on
    Boulevard du Larvotto's bridge passing over Avenue Princesse Grace); the same car at
    grade, or on the same deck, is one. The mirror does not hold a car on the deck over the
    ego (held only where it would overlap the ego at its height)."""
    import pybullet as pb

    from cosim.driving import LanePath
    from cosim.traffic import ActorsSnapshot
    from cosim.vehicle import VehicleState

    sim = start_sim(monaco)
    try:
        s, ap = sim.traffic.sumo, sim.driver
        deck = "503783368_0"
        D = np.array(s.lane.getShape(deck))[:, :2]
        dd = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(D, axis=0).T))])
        # where the avenue's turn through junction 273246212 passes under the deck
        via = np.array(s.lane.getShape(":273246212_1_0"))[:, :2]
        k = int(np.argmin(((D[:, None, :] - via[None, :, :]) ** 2).sum(axis=2).min(axis=1)))

        def on_deck(back):              # a point of the deck lane `back` m before its vertex k
            a = max(0.0, dd[k] - back)
            p = np.array([np.interp(a, dd, D[:, 0]), np.interp(a, dd, D[:, 1])])
            q = np.array([np.interp(a + 1, dd, D[:, 0]), np.interp(a + 1, dd, D[:, 1])])
            return p, float(np.arctan2(*(q - p)[::-1]))

        def snap_of(p, h, lane, speed=16.0):
            one = lambda v: np.array([v])         # noqa: E731
            return ActorsSnapshot(0.0, np.array(["b1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(p[0]), one(p[1]), one(h), one(4.5), one(1.8), one(1.5), one(speed),
                                  one(0.0), np.array([lane], dtype=object))

        def state(path, s_ego, z=0.0, v=8.0):
            (x, y), h = path.point_at(s_ego), path.heading_at(s_ego)
            return VehicleState(float(x), float(y), z, 0.0, 0.0, h, v, (v * np.cos(h), v * np.sin(h), 0.0),
                                0.0, 0.0, (True,) * 4)

        # 1. the path on the ground, under the deck; a car on the deck, up to 20 m before it
        # crosses over the path, is timed as a crossing car unless its level is known
        under = LanePath(s, ["25103769#2", "353889280"])
        sim.path = under
        ap._new_path(under)
        _, s_x, _ = under.project(*on_deck(0)[0], 0)
        st = state(under, max(0.0, s_x - 12.0))
        for back in (5.0, 20.0):
            p, h = on_deck(back)
            up = snap_of(p, h, deck)
            sim.mirror.update(up)
            assert sim.mirror.raised["b1"] > 4.0        # on the deck, over the terrain
            assert ap._actors_on_path(up, st, st_s(under, st), under) is not None   # (the level unknown)
            assert len(ap._same_level(up, under, st_s(under, st))) == 0
            ground = snap_of(p, h, "25103769#2_1")
            sim.mirror.update(ground)
            assert not sim.mirror.raised
            assert len(ap._same_level(ground, under, st_s(under, st))) == 1
        # the mirror holds a car at the ego's height where it would overlap the ego, not one on
        # the deck over it
        p, h = on_deck(0)
        ego_at = (float(p[0]), float(p[1]), h + 1.2, 4.5, 1.8)
        ground_z = float(sim.world.ground_z([p[0]], [p[1]])[0])
        sim.mirror.update(snap_of(p - 8.0 * np.array([np.cos(h), np.sin(h)]), h, deck))
        sim.mirror.update(snap_of(p, h, deck), ego=ego_at + (ground_z,))
        assert "b1" not in sim.mirror.held_at
        z_deck = pb.getBasePositionAndOrientation(sim.mirror.body_of("b1"), physicsClientId=sim.physics.client)[0][2]
        assert z_deck > ground_z + 3.0
        sim.mirror.update(snap_of(p - 8.0 * np.array([np.cos(h), np.sin(h)]), h, deck))
        sim.mirror.update(snap_of(p, h, deck), ego=ego_at + (z_deck - 0.75,))
        assert "b1" in sim.mirror.held_at
        # (a car on the ground beside an ego on a road 2.5 m over the terrain, a deck's ramp, is
        # held: Monaco, seed 13, a truck was not and went through the car)
        sim.mirror.update(snap_of(p - 8.0 * np.array([np.cos(h), np.sin(h)]), h, "25103769#2_1"))
        sim.mirror.update(snap_of(p, h, "25103769#2_1"), ego=ego_at + (ground_z + 2.5,))
        assert "b1" in sim.mirror.held_at

        # 2. the path on the deck: a car on the avenue's turn under it is on another level, a car
        # ahead on the deck is the lead
        over = LanePath(s, ["503783368"])
        sim.path = over
        ap._new_path(over)
        assert ap._path_bridge is not None
        s_over = over.project(*on_deck(0)[0], 0)[1]
        st = state(over, s_over - 25.0)
        vx = via[len(via) // 2]
        vh = float(np.arctan2(*(via[len(via) // 2 + 1] - vx)[::-1]))
        below = snap_of(vx, vh, ":273246212_1_0", speed=0.0)
        sim.mirror.update(below)
        assert not sim.mirror.raised
        assert len(ap._same_level(below, over, s_over - 25.0)) == 0
        person = snap_of(vx, vh, "", speed=1.2)         # (a person's level is not known: kept)
        person.kind[0] = "person"
        assert len(ap._same_level(person, over, s_over - 25.0)) == 1
        p, h = on_deck(0)
        ahead = snap_of(p, h, deck, speed=0.0)
        sim.mirror.update(ahead)
        assert len(ap._same_level(ahead, over, s_over - 25.0)) == 1
        lead = ap._actors_on_path(ahead, st, s_over - 25.0, over)
        assert lead is not None and lead.actor == "b1"
    finally:
        sim.teardown()


def st_s(path, st) -> float:
    return float(path.project(st.x, st.y, 0)[1])


# Helsinki: 74307860#1 (93 m; car lanes _1 and _2) on to 4243035#0: the path changes from
# lane _1 to _2 along the edge (LanePath._blend)
HEL_LC_EDGE, HEL_LC_NEXT = "74307860#1", "4243035#0"


def _lc_start_goal(sim):
    """(lat, lon) 5 m into HEL_LC_EDGE's lane _1, and 30 m into HEL_LC_NEXT."""
    s = sim.traffic.sumo

    def at(lane, pos):
        P = np.asarray(s.lane.getShape(lane), dtype=float)[:, :2]
        d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
        x, y = np.interp(pos, d, P[:, 0]), np.interp(pos, d, P[:, 1])
        lon, lat = sim.world.frame.to_lonlat(x, y)
        return (float(lat), float(lon))

    return at(HEL_LC_EDGE + "_1", 5.0), at(HEL_LC_NEXT + "_0", 30.0)


def _lc_sim(world) -> Simulation:
    """A simulation on Helsinki from 5 m into HEL_LC_EDGE's lane _1 to HEL_LC_NEXT, at 8 m/s."""
    probe = start_sim(world, start=HEL_MID)
    try:
        start, goal = _lc_start_goal(probe)
    finally:
        probe.teardown()
    return start_sim(world, start=start, goal=goal, speed_mps=8.0)


def test_a_car_that_stands_too_long_for_a_lane_change_takes_another_way(helsinki):
    """A car that stands LANE_CHANGE_GIVE_UP_S for a lane change its route needs (a queue in
    the lane beside that never lets it in: a 30-minute dense Helsinki drive stood 18 minutes
    so) takes another way: a route on from the lane it is in, whose next road that lane leads
    to itself. Here the route from HEL_LC_EDGE's lane _1 to HEL_LC_NEXT needs lane _2; a driver
    that stands for that lane change (as the autopilot does with no gap) gets, after the wait
    and not before, a route to the same goal on from lane _1's own link, with no lane change
    on HEL_LC_EDGE; without a goal, a random route on from that link."""
    import random

    from cosim.sim import LANE_CHANGE_GIVE_UP_S

    class Standing:       # the autopilot's state while no gap comes
        reason, target_speed = "lane change", 0.0

        def control(self, st, s_here, actors, dt):
            return 0.0, 1.0, 0.0

    probe = start_sim(helsinki, start=HEL_MID)
    try:
        start, goal = _lc_start_goal(probe)
    finally:
        probe.teardown()
    sim = Simulation(SimConfig(world_dir=helsinki, traffic="none", seed=1, start=start, goal=goal, speed_mps=8.0),
                     driver=Standing()).setup()
    try:
        tr, s = sim.traffic, sim.traffic.sumo
        lane1 = HEL_LC_EDGE + "_1"
        own = {ln[0].rsplit("_", 1)[0] for ln in s.lane.getLinks(lane1)}
        assert sim.route[:2] == [HEL_LC_EDGE, HEL_LC_NEXT] and HEL_LC_NEXT not in own
        assert [c for c in sim.path.changes if c.edge == HEL_LC_EDGE]
        for _ in range(int(LANE_CHANGE_GIVE_UP_S / 0.1) - 5):
            sim.step()
        assert sim.summary.other_ways == 0 and sim.route[1] == HEL_LC_NEXT, "gave up too early"
        for _ in range(10):
            sim.step()
        assert sim.summary.other_ways == 1
        route = sim.route
        assert route[0] == HEL_LC_EDGE and route[1] in own and route[-1] == HEL_LC_NEXT
        assert not [c for c in sim.path.changes if c.edge == HEL_LC_EDGE]
        st = sim.vehicle.state()
        assert abs(sim.path.project(st.x, st.y, 0)[2]) < 0.5        # the new path starts under the car
        # the fastest such way: no other of lane _1's links gives a faster route to the goal
        t_new = s.simulation.findRoute(route[1], HEL_LC_NEXT, vType="DEFAULT_VEHTYPE").travelTime
        for e in own:
            r = s.simulation.findRoute(e, HEL_LC_NEXT, vType="DEFAULT_VEHTYPE")
            assert not r.edges or r.travelTime >= t_new - 1e-6
        # without a goal: at random, on from one of lane _1's links (from the lane nearest the
        # point given, whatever lane is named)
        x, y = s.lane.getShape(lane1)[1][:2]
        plan = tr.plan_route(HEL_LC_EDGE + "_2", 0.0, keep_lane=True, at_xy=(x, y),
                             rng_state=random.Random(5).getstate())
        assert plan["lane"] == lane1 and plan["route"][0] == HEL_LC_EDGE and plan["route"][1] in own
        assert len(plan["route"]) > 2 and not [c for c in plan["path"].changes if c.edge == HEL_LC_EDGE]
    finally:
        sim.teardown()


def test_a_replan_in_a_lane_change_starts_on_the_lane_under_the_car(helsinki):
    """Along a lane change the path names the lane it changes into; a re-plan after a network
    swap started the new path on that lane while the car was still on the lane it came from,
    a lane's width beside it (Helsinki, seed 37: the car drove 3 m sideways through a standing
    queue). ``replan_from`` starts on the lane of the same edge under the car when that is
    nearer, so the new path begins under the car; on the target lane itself it stays there."""
    sim = _lc_sim(helsinki)
    try:
        tr, path = sim.traffic, sim.path
        s = tr.sumo
        c = [c for c in path.changes if c.edge == HEL_LC_EDGE][0]
        kw = sim.replan_args()[1]

        def on(lane, pos):
            P = np.asarray(s.lane.getShape(lane), dtype=float)[:, :2]
            d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(P, axis=0).T))])
            x, y = float(np.interp(pos, d, P[:, 0])), float(np.interp(pos, d, P[:, 1]))
            k = min(int(np.searchsorted(d, pos)), len(P) - 1)
            yaw = math.atan2(*(P[k] - P[k - 1])[::-1])
            return x, y, yaw

        pos = 0.5 * (s.lane.getLength(c.from_lane))
        lanes = [ln for ln, _ in path.lane_of[path.index_at(c.s0):]]
        lanes = list(dict.fromkeys(lanes))
        assert lanes[0] == c.to_lane            # the path's name for the lane along the change
        for lane in (c.from_lane, c.to_lane):
            x, y, yaw = on(lane, pos)
            new = tr.replan_from(lanes, x, y, yaw, **kw)["path"]
            assert float(np.hypot(new.xy[0, 0] - x, new.xy[0, 1] - y)) < 0.3
            moves = [(ch.from_lane, ch.to_lane) for ch in new.changes if ch.edge == HEL_LC_EDGE]
            assert moves == ([(c.from_lane, c.to_lane)] if lane == c.from_lane else [])
    finally:
        sim.teardown()


def test_a_lane_change_holds_back_for_a_car_in_the_lane_changed_into(helsinki):
    """Gap acceptance (Autopilot._lane_change): the path moves over to the next lane along an
    edge; a vehicle in that lane without room for the car holds it in its own lane (the held
    line: LanePath.set_hold), and the car moves over once the vehicle has passed. (Blending
    over regardless, the car moved in beside a faster car: Portland, seed 12.) Checked on the
    geometry (the held line is the lane the car came in on), on the rule (a follower coming
    up fast, one beside, one far behind, one in the car's own lane, a standing queue) and in
    the loop with SUMO: a car in the target lane catching up from behind passes first, and
    SUMO counts no collision."""
    import types

    from cosim.traffic import ActorsSnapshot

    sim = _lc_sim(helsinki)
    try:
        ap, path, tr = sim.driver, sim.path, sim.traffic
        s = tr.sumo
        changes = [c for c in path.changes if c.edge == HEL_LC_EDGE]
        assert len(changes) == 1, [c.key for c in path.changes]
        c = changes[0]
        assert (c.from_lane, c.to_lane) == (HEL_LC_EDGE + "_1", HEL_LC_EDGE + "_2")
        assert c.s0 < c.s1 < c.s_end
        # the geometry: before the blend the path is the lane come in on, after it the target
        # lane; the two a lane's width apart
        assert abs(c.src_lat[0]) < 0.05 and abs(c.tgt_lat[-1]) < 0.05
        width = float(s.lane.getWidth(c.to_lane))
        assert abs(abs(c.src_lat[-1]) - width) < 0.5
        src = np.asarray(s.lane.getShape(c.from_lane), dtype=float)[:, :2]

        def to_src(p):
            P, V = src[:-1], np.diff(src, axis=0)
            t = np.clip(((p - P) * V).sum(axis=1) / (V * V).sum(axis=1), 0, 1)
            return float(np.min(np.hypot(*(P + t[:, None] * V - p).T)))

        s_mid = 0.5 * (c.s0 + c.s1)
        assert to_src(path.aim_at(s_mid)) > 0.8          # the path: halfway over
        path.set_hold(c, 1.0)
        assert to_src(path.aim_at(s_mid)) < 0.1          # held: on the lane come in on
        px, py = path.aim_at(s_mid)
        assert abs(path.project(px, py, path.index_at(s_mid))[2]) < 0.1
        assert path.driven_lane(path.index_at(s_mid)) == c.from_lane
        path.set_hold(None, 0.0)
        assert path.driven_lane(path.index_at(s_mid)) == c.to_lane

        # the rule, with vehicles placed in the lanes (the car 10 m before the blend at 8 m/s)
        s_car = c.s0 - 10.0
        x0, y0 = path.point_at(s_car)
        h = path.heading_at(s_car)
        car = types.SimpleNamespace(x=float(x0), y=float(y0), yaw=h, speed=8.0)
        k = path.index_at(s_car)
        j = k - c.i0
        tgt_off = float(c.tgt_lat[max(j, 0)])

        def snap(*vehicles):
            n = len(vehicles)
            xs, ys, sp = [], [], []
            for ds, off, v in vehicles:
                px, py = path.point_at(s_car + ds)
                hh = path.heading_at(s_car + ds)
                if s_car + ds < 0.0:                 # behind the path's start: on along its line
                    px, py = px + (s_car + ds) * math.cos(hh), py + (s_car + ds) * math.sin(hh)
                xs.append(px - off * math.sin(hh))
                ys.append(py + off * math.cos(hh))
                sp.append(v)
            ones = np.ones(n)
            return ActorsSnapshot(0.0, np.array([f"v{i}" for i in range(n)], dtype=object),
                                  np.array(["passenger"] * n, dtype=object), np.array(xs), np.array(ys),
                                  np.full(n, h), 4.5 * ones, 1.8 * ones, 1.5 * ones, np.array(sp), 0.0 * ones,
                                  np.array([c.to_lane] * n, dtype=object))

        blk = ap._lc_blocker(c, car, path, s_car, 8.0, snap((-12.0, tgt_off, 12.0)))
        assert blk is not None and blk[0] == "v0" and blk[2] == "behind"         # coming up fast
        assert ap._lc_blocker(c, car, path, s_car, 8.0, snap((-60.0, tgt_off, 12.0))) is None   # far
        assert ap._lc_blocker(c, car, path, s_car, 8.0, snap((-12.0, tgt_off, 6.0))) is None    # slower
        assert ap._lc_blocker(c, car, path, s_car, 8.0, snap((1.0, tgt_off, 8.0)))[2] == "beside"
        assert ap._lc_blocker(c, car, path, s_car, 8.0, snap((-12.0, 0.0, 12.0))) is None      # own lane
        assert ap._lc_blocker(c, car, path, s_car, 8.0, snap((6.0, tgt_off, 4.0)))[2] == "ahead"
        # a queue (slower than LC_SLOW_MPS): ahead no hold (the car merges behind it), nor beside
        # a car at speed (it drops behind); beside a car in the queue itself it holds (the car
        # cannot drop behind: Helsinki, seed 37, it steered into a standing car beside it);
        # behind it needs 1 m
        still = types.SimpleNamespace(x=float(x0), y=float(y0), yaw=h, speed=0.0)
        assert ap._lc_blocker(c, still, path, s_car, 0.0, snap((6.0, tgt_off, 1.0))) is None
        assert ap._lc_blocker(c, car, path, s_car, 8.0, snap((0.0, tgt_off, 0.0))) is None
        blk = ap._lc_blocker(c, still, path, s_car, 0.0, snap((6.0, tgt_off, 1.0), (0.0, tgt_off, 0.0)))
        assert blk is not None and blk[0] == "v1" and blk[2] == "beside"
        assert ap._lc_blocker(c, still, path, s_car, 0.0, snap((-6.0, tgt_off, 1.0))) is None    # 1.5 m
        assert ap._lc_blocker(c, still, path, s_car, 0.0, snap((-4.9, tgt_off, 1.0)))[2] == "behind"   # 0.4 m

        # the loop: a SUMO car in lane _2 comes up from behind faster than the car
        ego_lane, sumo_lane_of_ego, order = None, [], []
        added = False
        s.route.add("r_lc", [HEL_LC_EDGE, HEL_LC_NEXT])
        for _ in range(400):
            ego = sim.step()
            if not added and ego.edge == HEL_LC_EDGE and s.vehicle.getLanePosition("ego") > 20.0:
                s.vehicle.add("chaser", "r_lc", typeID="DEFAULT_VEHTYPE", depart="now", departPos="0",
                              departSpeed="10", departLane="2")
                s.vehicle.setMaxSpeed("chaser", 10.0)
                added = True
            if added and "chaser" in s.vehicle.getIDList() and s.vehicle.getRoadID("ego") == HEL_LC_EDGE:
                ego_lane = s.vehicle.getLaneID("ego")
                ahead = s.vehicle.getRoadID("chaser") != HEL_LC_EDGE or \
                    s.vehicle.getLanePosition("chaser") - 5.0 > s.vehicle.getLanePosition("ego")
                sumo_lane_of_ego.append(ego_lane)
                order.append((ego_lane, ahead))
            if ego.edge == HEL_LC_NEXT:
                break
        assert added and c.to_lane in sumo_lane_of_ego, "the car never changed lanes"
        first = next(i for i, (ln, _) in enumerate(order) if ln == c.to_lane)
        assert order[first][1], "the car moved over before the chaser had passed it"
        assert ap.stats.lane_change_waits >= 1
        assert tr.stats.collisions == 0 and not sim.collision_log
    finally:
        sim.teardown()


def test_the_car_steers_closely_while_it_stops_for_its_sweep(helsinki):
    """Where the sweep touches a vehicle with the usual steering and close tracking touches it
    no nearer (no way past), the car stops before it and steers closely while it does (Lauf:
    steered by the usual, longer look-ahead whenever it braked for the sweep, the car ran wide
    in a tight right turn and touched a bus waiting on the opposite lane of the road it turned
    into, then pushed against it for 18 s). A vehicle standing across the turn's apex, at
    offsets from the turn's inside to its outside: where close tracking passes, the car tracks
    closely at CLOSE_TRACK_MPS; where it touches no nearer, the car stops before the close
    touch with the close steering, which turns tighter than the usual one."""
    import types

    from cosim.autopilot import CLOSE_TRACK_MPS

    sim = start_sim(helsinki, start=HEL_MID, goal=(60.170763, 24.948623))     # a right turn 420 m on
    try:
        ap, path = sim.driver, sim.path
        side, s_apex = _first_sharp_turn(sim)
        s_e = s_apex - 4.0
        # the car 0.5 m outside the path (it runs wide), heading along it: the sweep rolls
        px, py = path.point_at(s_e)
        he = path.heading_at(s_e)
        ex, ey = px + side * 0.5 * math.sin(he), py - side * 0.5 * math.cos(he)
        car = types.SimpleNamespace(x=float(ex), y=float(ey), yaw=he, speed=3.0, steer=0.0)

        def standing(offset: float):
            h = path.heading_at(s_apex)
            px, py = path.point_at(s_apex)
            x, y = px - side * offset * math.sin(h), py + side * offset * math.cos(h)
            return _one_actor("q1", x, y, h + math.pi / 2)

        ap._k, _, ap._lat = path.project(car.x, car.y, path.index_at(s_e))
        assert abs(abs(ap._lat) - 0.5) < 0.05
        stops = tracks = 0
        for offset in np.arange(-6.0, 6.01, 0.25):       # + = towards the turn's inside
            snap = standing(float(offset))
            touch, stop_at, pp, v_max = ap._sweep_steering(car, path, s_e, snap)
            if touch is None:
                assert (stop_at, pp, v_max) == (None, ap.pp, None)
                continue
            close = ap._sweep(car, path, s_e, snap, ap.pp_close)
            if close is None or close[0] > touch[0] + 1.0:
                tracks += 1
                assert pp is ap.pp_close and v_max == CLOSE_TRACK_MPS and stop_at == close
            elif close[0] >= touch[0]:
                stops += 1
                assert pp is ap.pp_close and v_max is None and stop_at == close, (offset, touch, close)
                k_close = ap.pp_close.steer(path, car.x, car.y, car.yaw, car.speed, s_e)[1]
                k_usual = ap.pp.steer(path, car.x, car.y, car.yaw, car.speed, s_e)[1]
                assert side * k_close > side * k_usual          # tighter into the turn
            else:
                assert pp is ap.pp and v_max is None and stop_at == touch
        assert stops >= 1, "no offset where close tracking touches no nearer"
    finally:
        sim.teardown()


def test_the_sweep_sees_a_turning_bus_where_its_body_bends(helsinki):
    """A bus or a truck is mirrored as a chain of boxes along the path its front took; in a
    turn its tail lies inside the straight box of its snapshot's heading. The car's sweep
    takes the chain (Helsinki, dense, seed 22: a 12 m bus turning past the standing car, its
    tail outside that straight box, touched the car as the car drove off). A bus mirrored along
    a 90-degree left turn of 8 m radius: the car just below the chain's tail, heading into it,
    is stopped by the sweep; with the straight box alone (no chain known for it), not."""
    import types

    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        ap, path, mirror = sim.driver, sim.path, sim.mirror
        st = sim.vehicle.state()
        s_e = s_of(sim, st.x, st.y)[0] + 20.0
        ex, ey = path.point_at(s_e)
        h = path.heading_at(s_e)
        # the bus's frame: it comes along +x, turns left about (0, R) to head +y; the car there
        # at (1.5, -5.25), heading +y, its front 3 m before the chain's tail
        R, L = 8.0, 12.0
        car_local = np.array([1.5, -5.25])
        rot = h - math.pi / 2.0
        cr, sr = math.cos(rot), math.sin(rot)

        def world(p):
            d = np.asarray(p, dtype=float) - car_local
            return float(ex + cr * d[0] - sr * d[1]), float(ey + sr * d[0] + cr * d[1])

        fronts = [((u, 0.0), 0.0) for u in np.arange(-L, 0.0, 0.5)]
        fronts += [((R * math.sin(a), R - R * math.cos(a)), a) for a in np.linspace(0.0, math.pi / 2.0, 30)]
        ego = (float(ex), float(ey), h, 4.5, 1.8, float(st.z))

        def snap(front, heading, name="bus1"):
            fx, fy = world(front)
            yaw = heading + rot
            one = lambda v: np.array([v])                 # noqa: E731
            return ActorsSnapshot(0.0, np.array([name], dtype=object), np.array(["bus"], dtype=object),
                                  one(fx - 0.5 * L * math.cos(yaw)), one(fy - 0.5 * L * math.sin(yaw)), one(yaw),
                                  one(L), one(2.5), one(3.0), one(0.0), one(0.0), np.array(["x_0"], dtype=object))

        # (its speed 0 in the snapshots: the chain comes from its front's path; a moving
        # bus's boxes move on in the roll, _sweep's prediction)
        for front, heading in fronts:
            last = snap(front, heading)
            mirror.update(last, ego=ego)
        chain = mirror.chain_boxes("bus1")
        assert chain is not None and len(chain) >= 3
        assert abs(math.remainder(chain[-1][2] - chain[0][2], 2 * math.pi)) > math.radians(45)   # bent
        car = types.SimpleNamespace(x=float(ex), y=float(ey), yaw=h, speed=2.0, steer=0.0)
        ap._k, _, ap._lat = path.project(ex, ey, path.index_at(s_e))
        ap._lat = 1.0                                    # (off the path: the sweep rolls)
        touch = ap._sweep(car, path, s_e, last, ap.pp)
        assert touch is not None and touch[1] == "bus1", touch
        straight = snap(*fronts[-1], name="bus2")        # the same bus, no chain known
        assert mirror.chain_boxes("bus2") is None
        assert ap._sweep(car, path, s_e, straight, ap.pp) is None
    finally:
        sim.teardown()


def test_a_route_with_a_turn_the_car_cannot_make_is_driven_only_up_to_where_it_can_go_on(monaco):
    """When every long route drawn has a step the car cannot drive (Monaco, seed 25: a one-way
    street down to a hairpin of 3.1 m radius; the car ran 2.4 m wide into a building), the
    route is cut before that step, back to the last edge from which the car can drive on
    (``SumoTraffic._drivable_head``); the car draws again at its end. On Monaco's network: a
    route SUMO finds through such a step, with no way around it."""
    from cosim.driving import escapes, undrivable_steps, without_turnarounds

    sim = start_sim(monaco)
    try:
        tr = sim.traffic
        s = tr.sumo
        incoming = tr.incoming_lanes()
        found = None
        for a in (e for e in s.edge.getIDList() if not e.startswith(":")):
            for ln in range(s.edge.getLaneNumber(a)):
                for link in s.lane.getLinks(f"{a}_{ln}"):
                    b = link[0].rsplit("_", 1)[0]
                    if b.startswith(":") or not undrivable_steps(s, [a, b]):
                        continue
                    # three edges back up the road into it
                    src, lane = a, f"{a}_{ln}"
                    for _ in range(3):
                        ups = [u for u in incoming.get(lane, ()) if not u.startswith(":")]
                        if not ups:
                            break
                        lane = ups[0]
                        src = lane.rsplit("_", 1)[0]
                    if src == a:
                        continue
                    try:
                        route = list(s.simulation.findRoute(src, b, vType="DEFAULT_VEHTYPE").edges)
                    except Exception:
                        continue                # (a road cars may not start on)
                    fixed = without_turnarounds(s, route)[0]
                    if len(route) >= 3 and (a, b) in undrivable_steps(s, fixed):
                        found = (a, b, route, fixed)
                        break
                if found:
                    break
            if found:
                break
        assert found is not None, "no step the car cannot drive without a way around in Monaco"
        a, b, route, fixed = found
        head = tr._drivable_head(route)
        assert head == fixed[:len(head)] and len(head) < len(fixed)
        assert (a, b) not in list(zip(head, head[1:])) and not undrivable_steps(s, head)
        assert len(head) == 1 or escapes(s, head[-1])
    finally:
        sim.teardown()


def _rolling_car(sim, speed: float):
    """The driver, its path, and the car as the sweep sees it 20 m on along the path, off the
    path (so that the sweep rolls): (driver, path, s, x, y, heading, car)."""
    import types

    ap, path = sim.driver, sim.path
    st = sim.vehicle.state()
    s_e = s_of(sim, st.x, st.y)[0] + 20.0
    ex, ey = path.point_at(s_e)
    h = path.heading_at(s_e)
    car = types.SimpleNamespace(x=float(ex), y=float(ey), yaw=h, speed=speed, steer=0.0)
    ap._k, _, ap._lat = path.project(ex, ey, path.index_at(s_e))
    ap._lat = 1.0
    return ap, path, s_e, ex, ey, h, car


def test_the_sweep_lets_a_crossing_car_move_on_while_the_car_rolls(helsinki):
    """A crossing or oncoming actor moves on along its heading in the car's roll, for up to
    SWEEP_PREDICT_S (Monaco, seed 28: a car angled towards the car's side at 6.8 m/s was clear
    of the roll's margin, and touched the car's rear corner 0.2 s later). A car 4 m ahead and
    4 m to the left, crossing to the right at 5 m/s: in the roll's way; standing there, or
    driving the car's way, not."""

    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        ap, path, s_e, ex, ey, h, car = _rolling_car(sim, 2.0)
        cx = ex + 4.0 * math.cos(h) - 4.0 * math.sin(h)
        cy = ey + 4.0 * math.sin(h) + 4.0 * math.cos(h)

        def snap(yaw, speed):
            one = lambda v: np.array([v])                 # noqa: E731
            return ActorsSnapshot(0.0, np.array(["x1"], dtype=object), np.array(["passenger"], dtype=object),
                                  one(cx), one(cy), one(yaw), one(4.5), one(1.8), one(1.5), one(speed), one(0.0),
                                  np.array(["x_0"], dtype=object))

        crossing = ap._sweep(car, path, s_e, snap(h - math.pi / 2, 5.0), ap.pp)
        assert crossing is not None and crossing[1] == "x1" and crossing[0] > 0.0
        assert ap._sweep(car, path, s_e, snap(h - math.pi / 2, 0.0), ap.pp) is None
        assert ap._sweep(car, path, s_e, snap(h, 5.0), ap.pp) is None
    finally:
        sim.teardown()


def test_the_sweep_keeps_a_person_half_a_metre_clear(helsinki):
    """A person is kept 0.5 m clear in the car's roll, a vehicle 0.15 m (Portland, seed 1: a
    person walking back along the car's side as it crept round a right turn went in and out of
    the 0.15 m margin step by step, the car went on every other step, and its corner hit the
    person). A person walking 0.3 m beside the car's path ahead stops the roll; a car there,
    the person 0.7 m off, or standing there, does not (Helsinki, dense seed 20: two persons
    standing on a walking area's corner, waiting for the car to clear their crossing, 0.55 m
    beside its turn, held it for good)."""

    from cosim.traffic import ActorsSnapshot

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        ap, path, s_e, ex, ey, h, car = _rolling_car(sim, 1.0)

        def snap(kind, gap, w, speed=1.0):
            side = -(0.5 * ap.width + gap + 0.5 * w)     # to the right, 3.5 m ahead, walking the car's way
            one = lambda v: np.array([v])                 # noqa: E731
            return ActorsSnapshot(0.0, np.array(["a1"], dtype=object), np.array([kind], dtype=object),
                                  one(ex + 3.5 * math.cos(h) - side * math.sin(h)),
                                  one(ey + 3.5 * math.sin(h) + side * math.cos(h)), one(h), one(0.5), one(w),
                                  one(1.7), one(speed), one(0.0), np.array(["x_0"], dtype=object))

        person = ap._sweep(car, path, s_e, snap("person", 0.3, 0.5), ap.pp)
        assert person is not None and person[1] == "a1" and person[2] == "person"
        assert ap._sweep(car, path, s_e, snap("person", 0.7, 0.5), ap.pp) is None
        assert ap._sweep(car, path, s_e, snap("person", 0.3, 0.5, speed=0.0), ap.pp) is None
        assert ap._sweep(car, path, s_e, snap("person", 0.1, 0.5, speed=0.0), ap.pp) is not None
        assert ap._sweep(car, path, s_e, snap("passenger", 0.3, 0.5), ap.pp) is None
    finally:
        sim.teardown()


def test_a_lane_path_follows_both_halves_of_a_link_a_junction_splits(helsinki):
    """A junction with an internal junction splits a left turn in two junction lanes (Kouvola:
    ``:36156596_6_0``, 2.6 m, then ``_17_0``, 14.3 m). The path took the lane the first one
    leads to instead of its junction lane, left the 14 m turn out and drove its chord, 2 m
    inside it; SUMO put the ego on the oncoming junction lane beside, and a car waiting there
    ran into it (Kouvola motorway, seed 31). On Helsinki's network, the paths through such
    links run along both halves."""
    from cosim.driving import LanePath, _lane_allows

    sim = start_sim(helsinki, start=HEL_MID)
    try:
        s = sim.traffic.sumo
        found = 0
        for lane in s.lane.getIDList():
            if lane.startswith(":") or found >= 5:
                continue
            for link in s.lane.getLinks(lane):
                first = link[4]
                nxt = s.lane.getLinks(first) if first else ()
                second = nxt[0][4] if nxt else ""
                if not second or not _lane_allows(s, lane) or not _lane_allows(s, link[0]):
                    continue
                edges = [lane.rsplit("_", 1)[0], link[0].rsplit("_", 1)[0]]
                try:
                    path = LanePath(s, edges)
                except Exception:
                    continue
                on = {ln for ln, _ in path.lane_of}
                if first not in on:            # (the path took another lane of the edge)
                    continue
                assert second in on, (edges, first, second)
                # and no point of the turn lies more than 0.3 m off the two halves
                halves = np.vstack([np.array(s.lane.getShape(v))[:, :2] for v in (first, second)])
                k = [i for i, (ln, _) in enumerate(path.lane_of) if ln in (first, second)]
                d = [min(np.hypot(*(halves[j] + t * (halves[j + 1] - halves[j]) - path.xy[i]))
                         for j in range(len(halves) - 1) for t in np.linspace(0.0, 1.0, 11)) for i in k]
                assert max(d) < 0.3, (edges, max(d))
                found += 1
                break
        assert found >= 3
    finally:
        sim.teardown()


def test_a_car_at_the_crossing_approach_speed_stops_before_the_crossing():
    """Where people wait at a crossing's end the car comes up at CROSSING_APPROACH_MPS; if they
    step on as its front bumper is CROSSING_MARGIN_M before the crossing, the speed controller
    (a SUMO step later) stops it before the crossing's edge. From 3 m/s it took 2.05 m (Lauf,
    dense seed 20: two persons started across from the kerb beside the car, which stopped with
    its bumper on one of them)."""
    from cosim.autopilot import CROSSING_APPROACH_MPS, CROSSING_MARGIN_M
    from cosim.driving import SpeedController

    def stopping_distance(v0: float) -> float:
        sc, v, dt = SpeedController(), v0, 0.01
        for _ in range(100):                    # cruising at v0
            sc.control(v0, v, dt)
        x = v * 0.1                             # seen a step later
        for _ in range(1000):
            if v <= 0.01:
                break
            throttle, brake = sc.control(0.0, v, dt)
            a = (throttle * sc.drive_force_max(v) - brake * sc.brake_force) / sc.mass
            v = max(0.0, v + a * dt)
            x += v * dt
        return x

    assert stopping_distance(CROSSING_APPROACH_MPS) < CROSSING_MARGIN_M - 0.1
    assert stopping_distance(3.0) > CROSSING_MARGIN_M          # the old approach speed did not
