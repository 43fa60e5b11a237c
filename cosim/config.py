"""One configuration object for a run, shared by the CLI, the GUI and scenario files.

A scenario file is TOML with four tables, each optional::

    [world]            # netgen.config.WorldConfig fields: preset / osm / bbox / center, chunks,
    preset = "helsinki"  # dem / elevation_url / flat, quality, out, ...
    chunks = 1
    [traffic]
    density = "normal" # none | light | normal | dense | vehicles per km2
    seed = 1
    lane_change_s = 3.0  # SUMO's drivers change lanes over this time (0: within one step)
    [ego]
    start = [60.1700, 24.9420]   # lat, lon; default: the world's centre
    goal = [60.1735, 24.9380]    # lat, lon; default: none (drive on along a random route)
    speed_mps = 11.0
    [run]
    duration_s = 120
    telemetry = "run.jsonl"

Relative paths in a scenario (osm, dem, out, telemetry) are relative to the scenario file.
Each value is checked against its field's type as the file is read (``_typed``): a value of
another type, an unknown setting or table is a one-line InputError naming them.
"""
from __future__ import annotations

import types
import typing
from dataclasses import asdict, dataclass, field
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from netgen.config import WorldConfig
from netgen.errors import InputError
from netgen.frame import check_latlon

DENSITIES = ("none", "light", "normal", "dense")
MAX_SPEED_MPS = 40.0
MAX_SEED = 2**31 - 1
# SUMO's drivers change lanes over this many seconds (--lanechange.duration: a lane's width at
# about 1 m/s sideways, SUMO's own maxSpeedLat); 0 is SUMO's default, a change within one step,
# which a mirrored car makes as a 3 m jump sideways
LANE_CHANGE_S = 3.0


@dataclass
class SimConfig:
    world: WorldConfig = field(default_factory=WorldConfig)
    world_dir: str | None = None          # run an already built world (skips the build)
    # traffic
    traffic: str | float = "normal"
    seed: int = 0
    backend: str = "libsumo"              # or "traci" (needed for sumo-gui)
    # libsumo in a worker process, stepping while the physics runs (None: when >= 2 CPUs)
    parallel_sumo: bool | None = None
    sumo_gui: bool = False
    lane_change_s: float = LANE_CHANGE_S   # 0: SUMO's instant lane changes
    # ego
    start: tuple[float, float] | None = None
    goal: tuple[float, float] | None = None
    speed_mps: float = 10.0
    respect_speed_limit: bool = False
    max_snap_m: float = 50.0
    # run
    duration_s: float = 60.0
    step_length_s: float = 0.1
    physics_hz: float | None = None       # default: the vehicle model's recommended rate
    sensor_range_m: float = 100.0         # lidar / camera distance (the loaded world must cover it)
    # SUMO actors within this radius are mirrored in PyBullet: the sensor range and 20 m more
    # (two actors closing head-on at 30 m/s each take more than three SUMO steps to cross it)
    mirror_radius_m: float = 120.0
    telemetry: str | None = None
    gui: bool = False                     # PyBullet's 3D window
    render: bool = False                  # load visual meshes for camera images (the Qt GUI)
    realtime: bool = False                # pace the loop to wall-clock time (GUI use)
    # the same seed, world and SUMO mode repeat the run step for step: a window swap comes a
    # fixed simulated time after its build started (waiting for a late build) instead of as
    # soon as the build is ready (cosim.streaming)
    repeatable: bool = True
    name: str = ""

    def validate(self) -> "SimConfig":
        if self.world_dir is None:
            self.world.validate()
        if isinstance(self.traffic, str) and self.traffic not in DENSITIES:
            try:
                self.traffic = float(self.traffic)
            except ValueError:
                raise InputError(f"traffic must be one of {', '.join(DENSITIES)} or vehicles per km2, got {self.traffic!r}")
        if not isinstance(self.traffic, str) and not 0 <= float(self.traffic) <= 2000:
            raise InputError(f"traffic density {self.traffic} vehicles/km2 is out of range (0..2000)")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or not 0 <= self.seed <= MAX_SEED:
            # (SUMO's tools take a 32-bit seed: a larger one failed deep in randomTrips)
            raise InputError(f"seed must be a whole number from 0 to {MAX_SEED}, got {self.seed!r}")
        if not 0 <= float(self.speed_mps) <= MAX_SPEED_MPS:
            raise InputError(f"speed {self.speed_mps} m/s is out of range (0..{MAX_SPEED_MPS:.0f})")
        if not 0 < float(self.duration_s) <= 24 * 3600:
            raise InputError(f"duration {self.duration_s} s is out of range (0..86400]")
        for k in ("start", "goal"):
            v = getattr(self, k)
            if v is not None:
                setattr(self, k, check_latlon(*v, what=k))
        if self.backend not in ("libsumo", "traci"):
            raise InputError("backend must be libsumo or traci")
        if self.sumo_gui and self.backend != "traci":
            self.backend = "traci"
        if not 0.01 <= float(self.step_length_s) <= 1.0:
            # (SUMO takes 0.001..10 s, but the ego's pose goes into SUMO once a step: a step
            # of seconds lets SUMO's drivers see the car jump)
            raise InputError(f"step length {self.step_length_s} s is out of range (0.01..1)")
        if float(self.duration_s) < float(self.step_length_s) - 1e-9:
            # (a 0.05 s run made no step and printed a summary of zeros)
            raise InputError(f"duration {self.duration_s} s is shorter than one step ({self.step_length_s} s)")
        if self.physics_hz is not None and not 50 <= float(self.physics_hz) <= 1000:
            # (the car's tyre model is validated from 100 Hz: models/car/README.md)
            raise InputError(f"physics rate {self.physics_hz} Hz is out of range (50..1000)")
        if not 0 < float(self.max_snap_m) <= 1000:
            raise InputError(f"max snap distance {self.max_snap_m} m is out of range (0..1000]")
        if not isinstance(self.name, str):
            raise InputError(f"name must be a string, got {self.name!r}")
        if not 0 <= float(self.lane_change_s) <= 20:
            raise InputError(f"lane change duration {self.lane_change_s} s is out of range (0..20)")
        if 0 < float(self.lane_change_s) < float(self.step_length_s):
            raise InputError(f"lane change duration {self.lane_change_s} s is shorter than one step "
                             f"({self.step_length_s} s): give 0 for SUMO's instant lane changes")
        if not 10 <= self.sensor_range_m <= 1000:
            raise InputError("sensor range must be 10..1000 m")
        if not self.sensor_range_m <= self.mirror_radius_m <= 2000:
            raise InputError(f"mirror radius must be at least the sensor range ({self.sensor_range_m:g} m) "
                             f"and at most 2000 m, got {self.mirror_radius_m:g} m")
        return self

    # --- scenario files ------------------------------------------------------------------
    @classmethod
    def from_toml(cls, path: str | Path) -> "SimConfig":
        path = Path(path)
        try:
            d = tomllib.loads(path.read_text(encoding="utf-8"))
        except FileNotFoundError:
            raise InputError(f"scenario file not found: {path}")
        except UnicodeDecodeError:
            raise InputError(f"scenario {path.name}: not a TOML file (not UTF-8 text)")
        except (OSError, tomllib.TOMLDecodeError) as e:
            raise InputError(f"scenario {path.name}: {e}")
        base = path.parent
        unknown = set(d) - {"world", "traffic", "ego", "run", "name"}
        if unknown:
            raise InputError(f"scenario {path.name}: unknown table(s) {', '.join(sorted(unknown))}")
        for table in ("world", "traffic", "ego", "run"):
            if not isinstance(d.get(table, {}), dict):
                raise InputError(f"scenario {path.name}: [{table}] must be a table")
        w = dict(d.get("world", {}))
        world_hints = typing.get_type_hints(WorldConfig)
        for k, v in w.items():
            if k in world_hints and not (k in ("bbox", "center") and isinstance(v, str)) \
                    and not (k == "dem" and isinstance(v, str)):
                w[k] = _typed(path.name, "world", k, v, world_hints[k])
        for k in ("osm", "out"):
            if isinstance(w.get(k), str):
                w[k] = str((base / w[k]).resolve())
        if "dem" in w:
            dems = [w["dem"]] if isinstance(w["dem"], str) else w["dem"]
            w["dem"] = [str((base / p).resolve()) for p in dems]
        world_dir = w.pop("dir", None)
        if world_dir is not None:
            world_dir = _typed(path.name, "world", "dir", world_dir, str)
        name = d.get("name", path.stem)
        if not isinstance(name, str):
            raise InputError(f"scenario {path.name}: name must be a string, got {name!r}")
        cfg = cls(world=WorldConfig.from_dict(w), name=name)
        if world_dir:
            cfg.world_dir = str((base / world_dir).resolve())
        t = d.get("traffic", {})
        e = d.get("ego", {})
        r = d.get("run", {})
        mapping = {"density": "traffic", "seed": "seed", "backend": "backend", "sumo_gui": "sumo_gui",
                   "parallel_sumo": "parallel_sumo", "lane_change_s": "lane_change_s",
                   "start": "start", "goal": "goal", "speed_mps": "speed_mps",
                   "respect_speed_limit": "respect_speed_limit", "max_snap_m": "max_snap_m",
                   "duration_s": "duration_s", "step_length_s": "step_length_s", "physics_hz": "physics_hz",
                   "sensor_range_m": "sensor_range_m", "mirror_radius_m": "mirror_radius_m",
                   "telemetry": "telemetry", "gui": "gui", "realtime": "realtime", "render": "render",
                   "repeatable": "repeatable"}
        hints = typing.get_type_hints(cls)
        for table, tname in ((t, "traffic"), (e, "ego"), (r, "run")):
            for k, v in table.items():
                if k not in mapping:
                    raise InputError(f"scenario {path.name}: unknown setting [{tname}] {k}")
                v = _typed(path.name, tname, k, v, hints[mapping[k]])
                if k == "telemetry" and v:
                    v = str((base / v).resolve())
                setattr(cfg, mapping[k], v)
        return cfg.validate()

    def to_dict(self) -> dict:
        return asdict(self)


def _typed(file: str, table: str, key: str, value, hint):
    """``value`` of a scenario's ``[table] key`` checked against its field's type ``hint`` (and
    converted: an int where a float goes, a list where a tuple goes); a value of another
    type is a one-line InputError naming the file, the setting and what it must be."""
    ok, out = _fits(value, hint)
    if not ok:
        raise InputError(f"scenario {file}: [{table}] {key} must be {_describe(hint)}, got {value!r}")
    return out


def _fits(value, hint) -> tuple[bool, object]:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        for a in args:
            ok, out = _fits(value, a)
            if ok:
                return True, out
        return False, None
    if hint is type(None):
        return value is None, None
    if hint is bool:
        return isinstance(value, bool), value
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool), value
    if hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        return ok, float(value) if ok else None
    if hint is str:
        return isinstance(value, str), value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            return False, None
        items = args if origin is tuple else (args[0],) * len(value) if args else (object,) * len(value)
        if len(items) != len(value):
            return False, None
        out = []
        for v, a in zip(value, items):
            ok, o = _fits(v, a) if a is not object else (True, v)
            if not ok:
                return False, None
            out.append(o)
        return True, tuple(out) if origin is tuple else out
    return True, value


def _describe(hint) -> str:
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a) for a in args if a is not type(None))
    if origin is tuple:
        return f"a list of {len(args)} {'numbers' if all(a in (int, float) for a in args) else 'values'}"
    if origin is list:
        return "a list"
    return {bool: "true or false", int: "a whole number", float: "a number", str: "a string"}.get(hint, str(hint))
