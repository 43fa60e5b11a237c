"""SUMO demand (cars, trucks, buses and pedestrians) for a network, made with SUMO's own tools.

Vehicles and persons come from ``<SUMO_HOME>/tools/randomTrips.py`` (run with this interpreter,
``SUMO_HOME`` set): random origin/destination pairs, routed by duarouter (``-r``, which drops
with ``--ignore-errors`` every trip it cannot route), so every kept trip is drivable (or walkable,
for ``--pedestrians``). randomTrips' own ``--validate`` is not used: it routes the trips up to
four times (a validation pass, a resampling pass, then the routes; about 2.5 s each on a 3 x 3 km
city), where one routing pass does. Instead randomTrips samples ``OVERSAMPLE`` times as many trips
as wanted, duarouter routes them once, and a seeded draw keeps the wanted number of the routed
ones (in departure order), so the density does not drop by the share of unroutable pairs
(10-15 % on the city presets). Where fewer than wanted could be routed (on the motorway preset
only about half of the random pedestrian pairs connect), a second round samples what is missing
at the first round's success rate; a shortfall after it is logged. Vehicles reference a
``vTypeDistribution`` (85 % passenger cars 4.5 x 1.8 m, 10 % trucks 10 x 2.5 m, 5 % buses
12 x 2.5 m) that duarouter resolves per vehicle, so each trip is validated for its own class.

Density
-------
``density`` is a preset (``none|light|normal|dense``) or a number: vehicles per km² present at
once. A world built from a preset scales the named ones by the preset's ``traffic_scale``
(``place_density``): Kouvola's neighbourhood takes 0.5, as at 80 vehicles per km² its arterials'
unsignalled junctions lock up in SUMO within minutes. Persons are proportional (``PERSONS_PER_VEHICLE`` persons per vehicle). The departure
period follows from Little's law (present = arrival rate x mean trip duration)::

    A      = W * H / 1e6                       network area in km² (convBoundary of the net)
    d      = DETOUR * 0.5214 * sqrt(W * H)     mean route length in m (0.5214 s is the mean
                                               distance between two random points of a square
                                               of side s; DETOUR = 1.3 for street networks)
    T      = d / v                             expected trip duration in s, v = 5.0 m/s for
                                               vehicles (urban speed including signals), 1.2 m/s
                                               for pedestrians
    N      = density * A                       wanted number present (persons: x 0.5)
    period = T / N                             seconds between departures (randomTrips -p)

On Helsinki (1.01 x 1.67 km, A = 1.69 km²) ``dense`` (200/km²) asks for ~337 vehicles and ~169
persons. The estimate assumes free-flowing traffic; when the network is saturated trips take
longer than T and more vehicles than N are present.

Time span and prefill
---------------------
Trips depart over ``[0, duration]`` (randomTrips ``--end``): the simulation drains after
``duration`` seconds, so pass the length of the run (default one hour). So that the city is
already populated at t = 0 instead of filling up over T seconds, trips are generated over
``[-T, duration]`` and those departing before 0 are started *in progress*: a trip that departed
at -t is cut to begin ``t * v`` metres down its route (at a random point of that edge), departing
at 0; trips that would already have arrived are dropped. Present counts are thus roughly steady
from the first second.

Repeatability and caching
-------------------------
``seed`` is passed to randomTrips (``--seed``) and duarouter (``--duarouter-seed``): the same
(network, density, seed, duration) gives byte-identical route files. Results are cached under
``out_dir/demand-<key>/`` where key hashes the net file's content, density, seed, duration and
this module's generator version; a re-run finds ``demand.json`` there and regenerates nothing.
Files are written to a temp name and moved in place with ``os.replace``; ``demand.json`` is
written last, so a half-written folder is never taken for a cached one.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import random
import re
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

from netgen._atomic import disk_error, disk_full
from netgen.errors import BuildError, InputError

log = logging.getLogger(__name__)

GENERATOR_VERSION = 5
OVERSAMPLE = 1.5       # trips sampled per trip wanted (see the module docstring)

DENSITY_PRESETS = {"none": 0.0, "light": 30.0, "normal": 80.0, "dense": 200.0}  # vehicles / km²
PERSONS_PER_VEHICLE = 0.5
DETOUR = 1.3
MEAN_DIST_FACTOR = 0.5214
VEHICLE_SPEED = 5.0     # m/s, effective urban travel speed including signals and junctions
PEDESTRIAN_SPEED = 1.2  # m/s, effective walking speed including waits at crossings
DEFAULT_DURATION = 3600.0

# id, vClass, probability, length, width, height, max speed (m/s), gui shape
VEHICLE_TYPES = (
    ("car", "passenger", 0.85, 4.5, 1.8, 1.5, 50.0, "passenger"),
    ("truck", "truck", 0.10, 10.0, 2.5, 3.4, 25.0, "truck"),
    ("bus", "bus", 0.05, 12.0, 2.5, 3.1, 25.0, "bus"),
)
VTYPE_DISTRIBUTION = "cosim_mix"
PERSON_TYPE = ("ped", 0.5, 0.6, 1.75)  # id, length (depth), width, height


def sumo_home() -> str:
    """SUMO_HOME of the eclipse-sumo wheel (never a system SUMO)."""
    try:
        import sumo  # the eclipse-sumo wheel
    except ImportError as e:  # pragma: no cover - dependency of the project
        raise BuildError(f"the eclipse-sumo package is not installed ({e})")
    return str(sumo.SUMO_HOME)


def sumo_env() -> dict:
    """Environment for SUMO's binaries and tools: SUMO_HOME and PROJ data of the wheel."""
    home = sumo_home()
    env = dict(os.environ)
    env["SUMO_HOME"] = home
    proj = os.path.join(home, "data", "proj")
    if os.path.isdir(proj):
        env.setdefault("PROJ_DATA", proj)
        env.setdefault("PROJ_LIB", proj)
    return env


# --- density --------------------------------------------------------------------------------
def parse_density(density) -> float:
    """Preset name or number (vehicles per km²) -> vehicles per km²."""
    if isinstance(density, str):
        key = density.strip().lower()
        if key in DENSITY_PRESETS:
            return DENSITY_PRESETS[key]
        try:
            value = float(key)
        except ValueError:
            raise InputError(f"traffic density {density!r}: expected one of "
                             f"{'|'.join(DENSITY_PRESETS)} or vehicles per km²")
    else:
        value = float(density)
    if not math.isfinite(value) or value < 0 or value > 5000:
        raise InputError(f"traffic density {density!r} is out of range (0..5000 vehicles per km²)")
    return value


def place_density(density, scale: float = 1.0) -> float:
    """The density a world's traffic gets, vehicles per km²: a named one (``light``, ``normal``,
    ``dense``) times the world's ``scale`` (its preset's ``traffic_scale``, in world.json's
    ``traffic``), a number as it is."""
    value = parse_density(density)
    if isinstance(density, str) and density.strip().lower() in DENSITY_PRESETS:
        value *= float(scale)
    return value


def world_traffic_scale(meta: dict) -> float:
    """A world's traffic scale (its world.json ``traffic.scale``; 1 for a world built before
    it), for :func:`place_density`."""
    return float(meta.get("traffic", {}).get("scale", 1.0))


def net_boundary(net_file) -> tuple[float, float, float, float]:
    """convBoundary (xmin, ymin, xmax, ymax) from the net's <location> element."""
    try:
        with open(net_file, "rb") as f:
            head = f.read(1 << 16).decode("utf-8", "replace")
    except OSError as e:
        raise BuildError(f"cannot read SUMO network {net_file}: {e.strerror or e}")
    m = re.search(r'<location[^>]*convBoundary="([^"]+)"', head)
    if not m:
        raise BuildError(f"{net_file} is not a SUMO network (no <location convBoundary>)")
    try:
        xmin, ymin, xmax, ymax = (float(v) for v in m.group(1).split(","))
    except ValueError:
        raise BuildError(f"{net_file}: bad convBoundary {m.group(1)!r}")
    return xmin, ymin, xmax, ymax


MAX_VEHICLES_FACTOR = 1.5


@dataclass(frozen=True)
class DemandPlan:
    """The numbers behind a demand: see the module doc for the formula."""
    area_km2: float
    vehicles_per_km2: float
    vehicles: float           # wanted number present at once
    persons: float
    vehicle_trip_s: float     # expected trip durations T
    person_trip_s: float
    vehicle_period: float     # seconds between departures (inf: none)
    person_period: float


def world_extent(net_file) -> tuple[float, float, float, float] | None:
    """The extent (xmin, ymin, xmax, ymax) of the world whose network ``net_file`` is (its
    ``world.json`` beside the ``net`` folder), or None (a network alone)."""
    try:
        e = json.loads((Path(net_file).absolute().parent.parent / "world.json").read_text())["extent_m"]
        return tuple(float(v) for v in e[:4])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def plan_demand(net_file, density) -> DemandPlan:
    dens = parse_density(density)
    xmin, ymin, xmax, ymax = net_boundary(net_file)
    # the network's area within its world: the network keeps whole the ways that cross the
    # world's border, and a railway running on for kilometres made Lauf's 9 km2 world a
    # network of 13.8 km2 (and 50 % more traffic than its density)
    ext = world_extent(net_file)
    if ext is not None and max(xmin, ext[0]) < min(xmax, ext[2]) and max(ymin, ext[1]) < min(ymax, ext[3]):
        xmin, ymin, xmax, ymax = max(xmin, ext[0]), max(ymin, ext[1]), min(xmax, ext[2]), min(ymax, ext[3])
    w, h = max(xmax - xmin, 1.0), max(ymax - ymin, 1.0)
    area = w * h / 1e6
    dist = DETOUR * MEAN_DIST_FACTOR * math.sqrt(w * h)
    tv, tp = dist / VEHICLE_SPEED, dist / PEDESTRIAN_SPEED
    nv = dens * area
    npers = nv * PERSONS_PER_VEHICLE
    return DemandPlan(area, dens, nv, npers, tv, tp,
                      tv / nv if nv > 0 else math.inf, tp / npers if npers > 0 else math.inf)


# --- result ----------------------------------------------------------------------------------
@dataclass
class Demand:
    """Generated route files (give ``route_files`` to SUMO in this order)."""
    folder: Path
    vehicles_file: Path | None
    persons_file: Path | None
    plan: DemandPlan
    seed: int
    duration: float
    n_vehicles: int = 0
    n_persons: int = 0
    cached: bool = False
    meta: dict = field(default_factory=dict)

    @property
    def route_files(self) -> list[Path]:
        return [p for p in (self.vehicles_file, self.persons_file) if p is not None]

    @property
    def max_vehicles(self) -> int | None:
        """A cap on vehicles running at once (SUMO's --max-num-vehicles): the planned number
        plus half. The departures are planned from free-flow trip times; in a jam trips last
        longer, and without a cap the network fills up until it locks (seen: 1365 vehicles
        for 337 planned on dense Helsinki, the car stuck for 20 minutes)."""
        if not self.plan.vehicles or not math.isfinite(self.plan.vehicles):
            return None
        return int(math.ceil(self.plan.vehicles * MAX_VEHICLES_FACTOR)) + 10


def file_sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def cache_key(net_hash: str, density: float, seed: int, duration: float, area_km2: float | None = None) -> str:
    d = {"net": net_hash, "density": round(float(density), 6), "seed": int(seed),
         "duration": round(float(duration), 3), "v": GENERATOR_VERSION}
    if area_km2 is not None:
        d["area_km2"] = round(float(area_km2), 6)
    text = json.dumps(d, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def generate_demand(net_file, out_dir, density="normal", seed: int = 0,
                    duration: float = DEFAULT_DURATION, prefill: bool = True,
                    timeout: float = 900.0) -> Demand:
    """Make (or find in the cache) vehicle and pedestrian route files for ``net_file``.

    Returns a :class:`Demand`; raises :class:`BuildError` (one line) when randomTrips fails,
    no vehicle trip could be routed or the files cannot be written (a full disk), and
    :class:`InputError` for a bad density/duration. The folder's ``demand.json`` is written
    last: a folder without it is never used.
    """
    try:
        return _generate_demand(net_file, out_dir, density, seed, duration, prefill, timeout)
    except OSError as e:
        raise disk_error(Path(out_dir), e) from None


def _generate_demand(net_file, out_dir, density, seed, duration, prefill, timeout) -> Demand:
    net_file = Path(net_file).absolute()     # randomTrips runs in its own working folder
    out_dir = Path(out_dir).absolute()
    if not net_file.is_file():
        raise BuildError(f"SUMO network {net_file} does not exist")
    try:
        duration = float(duration)
    except (TypeError, ValueError):
        raise InputError(f"demand duration {duration!r} is not a number")
    if not math.isfinite(duration) or not 1.0 <= duration <= 7 * 86400:
        raise InputError(f"demand duration {duration} s is out of range (1 s .. 7 days)")
    seed = int(seed)
    plan = plan_demand(net_file, density)
    key = cache_key(file_sha256(net_file), plan.vehicles_per_km2, seed, duration, plan.area_km2)
    folder = Path(out_dir) / f"demand-{key}"
    meta_path = folder / "demand.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
            veh = folder / meta["vehicles_file"] if meta.get("vehicles_file") else None
            per = folder / meta["persons_file"] if meta.get("persons_file") else None
            if all(p is None or p.is_file() for p in (veh, per)):
                log.info("demand: cached %s", folder)
                return Demand(folder, veh, per, plan, seed, duration, meta.get("n_vehicles", 0),
                              meta.get("n_persons", 0), cached=True, meta=meta)
        except (ValueError, KeyError, OSError):
            pass  # a broken cache entry is regenerated
    folder.mkdir(parents=True, exist_ok=True)
    n_veh = n_per = 0
    veh_file = per_file = None
    trips_info: dict = {}
    with tempfile.TemporaryDirectory(prefix="demand-", dir=folder) as tmp:
        tmp = Path(tmp)
        # vehicles and pedestrians are generated in parallel (two randomTrips processes)
        jobs = {}
        # a density so low that not one trip falls in the run is no traffic (as 0): randomTrips
        # found none, and the run stopped with "no routable vehicle trips"
        too_few = _trips_expected(plan.vehicle_period, plan.vehicle_trip_s, duration, prefill) < 1.0
        if plan.vehicles > 0 and too_few:
            log.info("demand: %g vehicles per km2 give less than one trip in %.0f s: no traffic",
                     plan.vehicles_per_km2, duration)
        if plan.vehicles > 0 and not too_few:
            jobs["veh"] = _start_random_trips(net_file, tmp, "veh", plan.vehicle_period,
                                              plan.vehicle_trip_s, duration, seed, prefill,
                                              persons=False)
        if plan.persons > 0 and _trips_expected(plan.person_period, plan.person_trip_s, duration, prefill) >= 1.0:
            jobs["ped"] = _start_random_trips(net_file, tmp, "ped", plan.person_period,
                                              plan.person_trip_s, duration, seed, prefill,
                                              persons=True)
        lengths = _edge_lengths(net_file) if jobs else {}
        results = {}
        for name, job in jobs.items():
            try:
                routes, sampled = _wait_random_trips(job, net_file, timeout)
                results[name] = ([routes], sampled)
            except BuildError as e:
                for other in jobs.values():
                    _kill(other[0])
                if name == "ped" and "valid edges" in str(e).lower():
                    results[name] = None  # a network without sidewalks (a motorway): no pedestrians
                else:
                    raise
        # a network where few random pairs connect (a motorway's footpaths): one more round
        # of sampling for what is missing, at the success rate the first round had
        more = {}
        for name, res in results.items():
            if res is None:
                continue
            (routes,), sampled = res
            routed = _count_tag(routes, "person" if name == "ped" else "vehicle")
            wanted = round(sampled / OVERSAMPLE)
            if 0 < routed < wanted:
                persons = name == "ped"
                fill = plan.person_trip_s if persons else plan.vehicle_trip_s
                span = duration + (fill if prefill else 0.0)
                need = min(20.0 * wanted, 1.25 * (wanted - routed) * sampled / routed)
                log.info("demand: %d of %d sampled %s trips routed: sampling %.0f more", routed, sampled,
                         name, need)
                more[name] = _start_random_trips(net_file, tmp, name + "B", span / need, fill, duration,
                                                 seed + 1, prefill, persons=persons, oversample=1.0)
        for name, job in more.items():
            try:
                results[name][0].append(_wait_random_trips(job, net_file, timeout)[0])
            except BuildError as e:
                log.warning("demand: the second round of %s trips failed: %s", name, e)
        if "veh" in results:
            veh_file = folder / "vehicles.rou.xml"
            n_veh = _finish_routes(*results["veh"], veh_file, lengths,
                                   plan.vehicle_trip_s if prefill else 0.0, VEHICLE_SPEED, seed,
                                   persons=False, info=trips_info.setdefault("vehicles", {}))
            if n_veh == 0:
                raise BuildError(f"no routable vehicle trips on {net_file.name} "
                                 "(randomTrips/duarouter found no connected roads for cars)")
        if "ped" in results:
            per_file = folder / "persons.rou.xml"
            raw = results["ped"]
            n_per = _finish_routes(*raw, per_file, lengths,
                                   plan.person_trip_s if prefill else 0.0, PEDESTRIAN_SPEED,
                                   seed, persons=True, info=trips_info.setdefault("persons", {})) \
                if raw is not None else _write_empty(per_file, True)
            if n_per == 0:
                log.warning("demand: no walkable pedestrian trips on %s (no sidewalks?)",
                            net_file.name)
    meta = {"net": str(net_file), "key": key, "density": plan.vehicles_per_km2, "seed": seed,
            "duration": duration, "prefill": prefill, "area_km2": plan.area_km2,
            "target_vehicles": plan.vehicles, "target_persons": plan.persons,
            "vehicle_period": plan.vehicle_period, "person_period": plan.person_period,
            "vehicles_file": veh_file.name if veh_file else None,
            "persons_file": per_file.name if per_file else None,
            "n_vehicles": n_veh, "n_persons": n_per, "trips": trips_info,
            "generator_version": GENERATOR_VERSION}
    _atomic_write_text(meta_path, json.dumps(meta, indent=1, default=_json_float))
    log.info("demand: %d vehicle trips, %d person trips in %s", n_veh, n_per, folder)
    return Demand(folder, veh_file, per_file, plan, seed, duration, n_veh, n_per, meta=meta)


def _json_float(o):
    return None if isinstance(o, float) and not math.isfinite(o) else str(o)


# --- internals --------------------------------------------------------------------------------
def _vtypes_xml(vehicles: bool = True, persons: bool = True) -> str:
    lines = ["<additional>"]
    if vehicles:
        lines.append(f'    <vTypeDistribution id="{VTYPE_DISTRIBUTION}">')
    for vid, vclass, prob, length, width, height, vmax, shape in VEHICLE_TYPES if vehicles else ():
        lines.append(f'        <vType id="{vid}" vClass="{vclass}" probability="{prob}" '
                     f'length="{length}" width="{width}" height="{height}" maxSpeed="{vmax}" '
                     f'guiShape="{shape}"/>')
    if vehicles:
        lines.append("    </vTypeDistribution>")
    pid, plen, pwid, phei = PERSON_TYPE
    if persons:
        lines.append(f'    <vType id="{pid}" vClass="pedestrian" length="{plen}" width="{pwid}" '
                     f'height="{phei}" guiShape="pedestrian"/>')
    lines.append("</additional>\n")
    return "\n".join(lines)


def _trips_expected(period: float, fill_s: float, duration: float, prefill: bool) -> float:
    """Trips that depart in the run (and in its prefill) at one every ``period`` s."""
    return (duration + (fill_s if prefill else 0.0)) / period if period > 0 else math.inf


def _start_random_trips(net_file: Path, tmp: Path, prefix: str, period: float, fill_s: float,
                        duration: float, seed: int, prefill: bool, persons: bool,
                        oversample: float = OVERSAMPLE):
    """Start randomTrips.py, sampling OVERSAMPLE times the trips of ``period``, routed once by
    duarouter; returns (process, routes file, what, stderr file, trips file)."""
    home = sumo_home()
    script = os.path.join(home, "tools", "randomTrips.py")
    work = tmp / prefix              # own working dir: duarouter writes a file named NUL there
    work.mkdir()
    types = work / "types.add.xml"
    types.write_text(_vtypes_xml())
    trips, routes = work / f"{prefix}.trips.xml", work / f"{prefix}.rou.xml"
    # trips are generated over [0, duration + fill] and shifted by -fill afterwards (prefill)
    end = duration + (fill_s if prefill else 0.0)
    cmd = [sys.executable, script, "-n", str(net_file.resolve()), "-a", str(types),
           "-o", str(trips), "-r", str(routes), "--no-validate", "--seed", str(seed),
           "--duarouter-seed", str(seed), "-b", "0", "-e", f"{end:.2f}", "-p", f"{period / oversample:.4f}",
           "--prefix", prefix, "--error-log", str(work / f"{prefix}.errors.log"),
           "--random-arrivalpos"]
    if persons:
        cmd += ["--pedestrians", "-t", f'type="{PERSON_TYPE[0]}"']
    else:
        cmd += ["-t", f'type="{VTYPE_DISTRIBUTION}" departLane="best" departSpeed="max"']
    log.debug("demand: %s", " ".join(cmd))
    err = open(work / "stderr.txt", "w+")
    try:
        proc = subprocess.Popen(cmd, cwd=work, env=sumo_env(), stdout=subprocess.DEVNULL,
                                stderr=err, text=True)
    except OSError as e:
        err.close()
        raise BuildError(f"cannot run randomTrips.py: {e}")
    return proc, routes, "pedestrians" if persons else "vehicles", err, trips


def _kill(proc) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.wait()


def _wait_random_trips(job, net_file: Path, timeout: float) -> tuple[Path, int]:
    """Wait for randomTrips; returns (routes file, number of trips it sampled)."""
    proc, routes, what, err, trips = job
    try:
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            _kill(proc)
            raise BuildError(f"randomTrips ({what}) for {net_file.name} took longer than "
                             f"{timeout:.0f} s")
        err.seek(0)
        stderr = err.read()
    finally:
        err.close()
    if proc.returncode != 0 or not routes.is_file():
        folder = routes.parents[2]          # demand-<key>/<tmp>/<prefix>/<prefix>.rou.xml
        if disk_full(folder):               # (its stderr file may be empty for the same reason)
            raise BuildError(f"disk full while writing the traffic demand in {folder}")
        msg = _last_error_line(stderr) or f"exit code {proc.returncode}"
        raise BuildError(f"randomTrips ({what}) failed on {net_file.name}: {msg}")
    return routes, _count_tag(trips, "person" if what == "pedestrians" else "trip")


def _last_error_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").splitlines()
             if ln.strip() and "proj.db" not in ln]
    for ln in reversed(lines):
        if "error" in ln.lower():
            return ln
    return lines[-1] if lines else ""


def _edge_lengths(net_file: Path) -> dict[str, float]:
    """Non-internal edge id -> length (of its first lane)."""
    lengths: dict[str, float] = {}
    for _, el in ET.iterparse(str(net_file), events=("end",)):
        if el.tag == "edge":
            eid = el.get("id", "")
            if not eid.startswith(":"):
                lane = el.find("lane")
                if lane is not None:
                    lengths[eid] = float(lane.get("length", "0"))
            el.clear()
        elif el.tag in ("junction", "connection", "tlLogic", "roundabout"):
            el.clear()
    return lengths


def _write_empty(path: Path, persons: bool) -> int:
    _atomic_write_text(path, f"<routes>\n{_vtypes_body(persons)}</routes>\n")
    return 0


def _vtypes_body(persons: bool) -> str:
    """The vehicle types (vehicle file) or the pedestrian type (person file), each defined once."""
    xml = _vtypes_xml(vehicles=not persons, persons=persons)
    return xml.split("\n", 1)[1].rsplit("</additional>", 1)[0]


def _count_tag(xml: Path, tag: str) -> int:
    """How many ``tag`` elements a trips or routes file holds."""
    return sum(1 for _, el in ET.iterparse(str(xml)) if el.tag == tag)


def _finish_routes(raws: list, sampled: int, out: Path, lengths: dict[str, float], fill_s: float,
                   speed: float, seed: int, persons: bool, info: dict | None = None) -> int:
    """Keep the wanted share of the routed trips (``sampled / OVERSAMPLE`` of them, a seeded
    draw in departure order); shift departures by -fill_s; cut trips departing before 0 to
    start in progress.

    Writes ``out`` atomically and returns the number of trips kept; ``info`` gets the counts
    (sampled in the first round, wanted, routed in all rounds).
    """
    rng = random.Random(seed * 7919 + (1 if persons else 0))
    tag = "person" if persons else "vehicle"
    routed = [el for raw in raws for el in ET.parse(raw).getroot() if el.tag == tag]  # (our vTypes go on top)
    routed.sort(key=lambda el: float(el.get("depart", "0")))    # (stable: rounds merged in time)
    wanted = round(sampled / OVERSAMPLE)
    if info is not None:
        info.update(sampled=sampled, wanted=wanted, routed=len(routed), rounds=len(raws))
    if len(routed) > wanted:
        keep = set(rng.sample(range(len(routed)), wanted))
        routed = [el for k, el in enumerate(routed) if k in keep]
    elif len(routed) < wanted:
        log.warning("demand: only %d %s trips could be routed (%d wanted)", len(routed), tag, wanted)
    kept = []
    for el in routed:
        depart = float(el.get("depart", "0")) - fill_s
        if depart < 0:
            if not _start_in_progress(el, -depart * speed, lengths, rng, persons):
                continue
            depart = 0.0
        el.set("depart", f"{depart:.2f}")
        kept.append(el)
    parts = ['<?xml version="1.0" encoding="UTF-8"?>\n',
             "<!-- generated by cosim.demand with SUMO randomTrips.py, routed by duarouter -->\n",
             "<routes>\n", _vtypes_body(persons)]
    for el in kept:
        ET.indent(el, space="    ", level=1)
        parts.append("    " + ET.tostring(el, encoding="unicode").rstrip() + "\n")
    parts.append("</routes>\n")
    _atomic_write_text(out, "".join(parts))
    return len(kept)


def _start_in_progress(el, travelled: float, lengths, rng, persons: bool) -> bool:
    """Move the start of a trip ``travelled`` metres down its route; False if it has ended."""
    holder = el.find("walk") if persons else el.find("route")
    if holder is None or not holder.get("edges"):
        return False
    edges = holder.get("edges").split()
    acc = 0.0
    for i, e in enumerate(edges):
        le = lengths.get(e, 0.0)
        if acc + le > travelled:
            if i == len(edges) - 1 and persons is False and le < 1.0:
                return False
            rest = edges[i:]
            holder.set("edges", " ".join(rest))
            # a random point of the edge where the trip is now (not exactly at travelled, so
            # that departures do not all line up at the start of edges)
            pos = rng.uniform(0.0, max(le - 0.5, 0.0))
            if len(rest) == 1:
                arr = holder.get("arrivalPos") if persons else el.get("arrivalPos")
                try:
                    if arr is not None and float(arr) <= pos + 1.0:
                        return False
                except ValueError:
                    pass
            el.set("departPos", f"{pos:.2f}")
            return True
        acc += le
    return False


def _atomic_write_text(path: Path, text: str) -> None:
    path = Path(path)
    tmp = path.with_name(f"{path.name}.tmp-{os.getpid()}")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    except OSError as e:
        try:
            tmp.unlink()
        except OSError:
            pass
        raise BuildError(f"cannot write {path}: {e.strerror or e}")


def main(argv=None) -> int:
    import argparse
    ap = argparse.ArgumentParser(description="Generate SUMO demand for a network")
    ap.add_argument("net")
    ap.add_argument("out_dir")
    ap.add_argument("--density", default="normal")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--duration", type=float, default=DEFAULT_DURATION)
    a = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    from netgen.errors import CosimError
    try:
        d = generate_demand(a.net, a.out_dir, a.density, a.seed, a.duration)
    except CosimError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code
    print(json.dumps(d.meta, indent=1, default=_json_float))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
