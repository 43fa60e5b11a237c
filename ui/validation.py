"""The launcher's inputs and states, without Qt.

Two layers of checks turn what the user typed (:class:`FormValues`, all strings) into a
:class:`cosim.config.SimConfig`:

* :func:`check_ranges` — instant, run on every keystroke: numbers parse, each lies in its
  range (latitude -90..90, longitude -180..180, chunks 0..``MAX_RINGS``, speed
  0..``MAX_SPEED_MPS``, traffic a density name or 0..2000 vehicles/km2), files exist.
* :func:`check_reality` — may read files (an OSM extract, a DEM), so the window runs it in a
  worker thread: the start (and destination) lies inside the map data, a road for cars is
  within reach of it, the destination lies inside the world that will be built, the DEM
  covers the world. It returns the final SimConfig, checked by ``SimConfig.validate()``.

:class:`StateMachine` is the seed's model of the launcher: Idle -> Input checked -> Error or
Ready -> Simulation -> Stop -> Idle. Every transition is listed in ``TRANSITIONS``; anything
else raises :class:`InvalidTransition`, so a UI bug shows up as an error, not a silent state.
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path

import numpy as np

from cosim.config import DENSITIES, MAX_SPEED_MPS, SimConfig
from netgen.config import MAX_RINGS, QUALITY, WorldConfig
from netgen.errors import CosimError, InputError

# highway=* values SUMO imports as roads a passenger car may use (the start snaps onto one)
CAR_HIGHWAYS = frozenset({
    "motorway", "motorway_link", "trunk", "trunk_link", "primary", "primary_link", "secondary",
    "secondary_link", "tertiary", "tertiary_link", "unclassified", "residential", "living_street",
    "service", "road"})
MAX_TRAFFIC = 2000.0
# a launcher run lasts until Stop, at most this long in simulated time: traffic demand is
# generated for it when a world is first run (about 20 s for an hour; cached per world after)
RUN_DURATION_S = 3600.0
DEM_SUFFIXES = (".hgt", ".hgt.zip", ".tif", ".tiff")

LABELS = {"preset": "Preset", "lat": "Latitude", "lon": "Longitude", "chunks": "Chunks",
          "speed": "Speed", "quality": "Quality", "traffic": "Traffic", "dest_lat": "Destination latitude",
          "dest_lon": "Destination longitude", "dest": "Destination", "osm": "OSM file", "dem": "DEM file",
          "place": "Place", "start": "Start"}


# --------------------------------------------------------------------------------------
# states
# --------------------------------------------------------------------------------------
class State(Enum):
    IDLE = "Idle"
    CHECKING = "Input checked"      # the seed's "Input checked": checks are running
    ERROR = "Error"
    READY = "Ready"
    SIMULATION = "Simulation"       # building the world, then running
    STOPPING = "Stop"               # SUMO and PyBullet are being shut down


class InvalidTransition(RuntimeError):
    pass


# (state, event) -> next state. Events:
#   edit      an input changed (or the defaults were filled in / a run ended): check them
#   invalid   a check failed: the message says which input and why
#   valid     every check passed
#   start     the user pressed Start
#   stop      the user pressed Stop, or closed the window
#   stopped   the worker tore SUMO and PyBullet down
#   failed    setup or a step raised: the worker tore down, the message is shown
TRANSITIONS = {
    (State.IDLE, "edit"): State.CHECKING,
    (State.CHECKING, "edit"): State.CHECKING,
    (State.CHECKING, "invalid"): State.ERROR,
    (State.CHECKING, "valid"): State.READY,
    (State.ERROR, "edit"): State.CHECKING,
    (State.READY, "edit"): State.CHECKING,
    (State.READY, "start"): State.SIMULATION,
    (State.SIMULATION, "stop"): State.STOPPING,
    (State.SIMULATION, "failed"): State.ERROR,
    (State.SIMULATION, "stopped"): State.IDLE,      # the run ended by itself
    (State.STOPPING, "stopped"): State.IDLE,
    (State.STOPPING, "failed"): State.ERROR,        # a step failed as Stop was pressed: still shown
}


class StateMachine:
    """The launcher's state and its message; listeners get (old, new, message)."""

    def __init__(self):
        self.state = State.IDLE
        self.message = ""
        self.history: list[tuple[State, str, State]] = []
        self._listeners: list = []

    def subscribe(self, fn) -> None:
        self._listeners.append(fn)

    def can(self, event: str) -> bool:
        return (self.state, event) in TRANSITIONS

    def fire(self, event: str, message: str = "") -> State:
        new = TRANSITIONS.get((self.state, event))
        if new is None:
            raise InvalidTransition(f"no transition from {self.state.value} on {event!r}")
        old, self.state = self.state, new
        # Error carries its message; Ready, Idle and Simulation clear it (or carry a note);
        # while checking or stopping the last message stays
        if new in (State.ERROR, State.READY, State.IDLE, State.SIMULATION):
            self.message = message
        self.history.append((old, event, new))
        for fn in list(self._listeners):
            fn(old, new, self.message)
        return new


# --------------------------------------------------------------------------------------
# inputs
# --------------------------------------------------------------------------------------
@dataclass
class FormValues:
    """What the user typed, as strings (the widgets' text)."""

    mode: str = "preset"           # "preset" | "coords"
    preset: str = "kouvola"
    lat: str = ""
    lon: str = ""
    chunks: str = "1"
    speed: str = "10"
    quality: str = "low"
    traffic: str = "light"
    dest_lat: str = ""
    dest_lon: str = ""
    osm: str = ""
    dem: str = ""
    flat: bool = False             # flat ground when there is no elevation data
    gui: bool = False
    realtime: bool = True
    seed: int = 0


@dataclass
class FieldError:
    field: str
    message: str

    def text(self) -> str:
        return f"{LABELS.get(self.field, self.field)}: {self.message}"


@dataclass
class Ranged:
    """The parsed values (after check_ranges)."""

    values: FormValues
    start: tuple[float, float] | None = None
    goal: tuple[float, float] | None = None
    chunks: int = 1
    speed: float = 10.0
    traffic: str | float = "light"
    osm: str | None = None
    dem: str | None = None


@dataclass
class CheckResult:
    errors: list[FieldError] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    config: SimConfig | None = None

    @property
    def ok(self) -> bool:
        return not self.errors and self.config is not None

    def message(self) -> str:
        return "\n".join(e.text() for e in self.errors)


def _number(text: str, fld: str, errors: list, lo: float, hi: float, unit: str = "",
            integer: bool = False):
    t = text.strip().replace(",", ".") if fld not in ("lat", "lon", "dest_lat", "dest_lon") else text.strip()
    if not t:
        errors.append(FieldError(fld, "is empty"))
        return None
    try:
        v = float(t)
    except ValueError:
        errors.append(FieldError(fld, f"{text.strip()!r} is not a number"))
        return None
    if not math.isfinite(v):
        errors.append(FieldError(fld, f"{text.strip()!r} is not a finite number"))
        return None
    if integer and v != int(v):
        errors.append(FieldError(fld, f"{text.strip()} is not a whole number"))
        return None
    if not lo <= v <= hi:
        u = unit if unit in ("", "°") else f" {unit}"
        lo_s, hi_s = (f"{lo:g}", f"{hi:g}")
        errors.append(FieldError(fld, f"{t}{u} is out of range ({lo_s}..{hi_s}{u})"))
        return None
    return int(v) if integer else v


def _latlon(lat_t: str, lon_t: str, lat_f: str, lon_f: str, errors: list, what: str):
    from netgen.frame import check_latlon

    n = len(errors)
    lat = _number(lat_t, lat_f, errors, -90.0, 90.0, "°")
    lon = _number(lon_t, lon_f, errors, -180.0, 180.0, "°")
    if len(errors) > n:
        return None
    try:   # the API's own limits (e.g. not within 6 degrees of a pole)
        return check_latlon(lat, lon, what)
    except InputError as e:
        errors.append(FieldError(lat_f, str(e).split(": ", 1)[-1]))
        return None


def check_ranges(v: FormValues) -> tuple[Ranged, list[FieldError]]:
    """Instant checks of every field against its range. Returns the parsed values and errors."""
    from netgen.osm_file import SUFFIXES as OSM_SUFFIXES
    from netgen.presets import list_presets

    errors: list[FieldError] = []
    r = Ranged(values=v)
    if v.mode == "preset":
        names = [p.name for p in list_presets()]
        if v.preset not in names:
            errors.append(FieldError("preset", f"unknown preset {v.preset!r} (known: {', '.join(names)})"))
    elif v.mode == "coords":
        if v.lat.strip() or v.lon.strip() or not v.osm.strip():
            r.start = _latlon(v.lat, v.lon, "lat", "lon", errors, "start")
    else:
        errors.append(FieldError("place", f"unknown place mode {v.mode!r}"))
    c = _number(v.chunks, "chunks", errors, 0, MAX_RINGS, integer=True)
    if c is not None:
        r.chunks = c
    s = _number(v.speed, "speed", errors, 0.0, MAX_SPEED_MPS, "m/s")
    if s is not None:
        r.speed = s
    if v.quality not in QUALITY:
        errors.append(FieldError("quality", f"{v.quality!r} is not one of {', '.join(QUALITY)}"))
    t = v.traffic.strip().lower()
    if t in DENSITIES:
        r.traffic = t
    else:
        try:
            tv = float(t) if t else None
        except ValueError:
            tv = None
        if tv is None or not math.isfinite(tv):
            errors.append(FieldError("traffic", f"{v.traffic.strip()!r} is neither one of {', '.join(DENSITIES)} "
                                                f"nor a number of vehicles/km² (0..{MAX_TRAFFIC:g})"))
        else:
            tv = _number(t, "traffic", errors, 0.0, MAX_TRAFFIC, "vehicles/km²")
            if tv is not None:
                r.traffic = tv
    if v.dest_lat.strip() or v.dest_lon.strip():
        r.goal = _latlon(v.dest_lat, v.dest_lon, "dest_lat", "dest_lon", errors, "destination")
    if v.mode == "coords" and v.osm.strip():
        p = Path(v.osm.strip()).expanduser()
        if not p.is_file():
            errors.append(FieldError("osm", f"{p} does not exist"))
        elif not any(p.name.lower().endswith(x) for x in OSM_SUFFIXES):
            errors.append(FieldError("osm", f"{p.name}: unknown format (use .osm, .osm.pbf, .osm.gz or .osm.bz2)"))
        else:
            r.osm = str(p.resolve())
    if v.dem.strip():
        p = Path(v.dem.strip()).expanduser()
        if not p.is_file():
            errors.append(FieldError("dem", f"{p} does not exist"))
        elif not any(p.name.lower().endswith(x) for x in DEM_SUFFIXES):
            errors.append(FieldError("dem", f"{p.name}: unknown format (use .hgt, .hgt.zip, .tif or .tiff)"))
        else:
            r.dem = str(p.resolve())
    return r, errors


# --------------------------------------------------------------------------------------
# roads near a point (from the OSM file, read once and cached)
# --------------------------------------------------------------------------------------
class RoadIndex:
    """The car roads of one OSM file as segments, for "is there a road near this point"."""

    def __init__(self, path: str | Path):
        import osmium

        from netgen.errors import DataError
        from netgen.osm_file import header_bbox

        self.path = Path(path)
        segs = []
        lat_min = lon_min = math.inf
        lat_max = lon_max = -math.inf
        try:
            fp = osmium.FileProcessor(str(self.path), osmium.osm.NODE | osmium.osm.WAY).with_locations()
            for o in fp:
                if not o.is_way() or o.tags.get("highway") not in CAR_HIGHWAYS:
                    continue
                pts = [(nd.lon, nd.lat) for nd in o.nodes if nd.location.valid()]
                if len(pts) >= 2:
                    a = np.asarray(pts, dtype=float)
                    segs.append(np.hstack([a[:-1], a[1:]]))
                    lon_min, lat_min = min(lon_min, a[:, 0].min()), min(lat_min, a[:, 1].min())
                    lon_max, lat_max = max(lon_max, a[:, 0].max()), max(lat_max, a[:, 1].max())
        except Exception as e:  # libosmium's parse errors
            raise DataError(f"{self.path.name} is corrupt or truncated ({' '.join(str(e).split())[:120]})") from None
        self.segments = np.vstack(segs) if segs else np.zeros((0, 4))   # lon0, lat0, lon1, lat1
        hb = header_bbox(self.path)
        if hb is None and segs:
            hb = (lat_min, lon_min, lat_max, lon_max)
        self.bbox = hb            # (south, west, north, east) of the map data, or None

    def contains(self, lat: float, lon: float) -> bool:
        if self.bbox is None:
            return False
        s, w, n, e = self.bbox
        return s <= lat <= n and w <= lon <= e

    def bbox_text(self) -> str:
        s, w, n, e = self.bbox
        return f"{s:.4f}..{n:.4f} N, {w:.4f}..{e:.4f} E"

    def nearest_road_m(self, lat: float, lon: float) -> float:
        """Distance (m) from the point to the nearest car road (inf if there is none)."""
        if not len(self.segments):
            return math.inf
        kx = 111_320.0 * math.cos(math.radians(lat))     # local equirectangular metres
        ky = 110_540.0
        p0 = np.stack([(self.segments[:, 0] - lon) * kx, (self.segments[:, 1] - lat) * ky], axis=1)
        p1 = np.stack([(self.segments[:, 2] - lon) * kx, (self.segments[:, 3] - lat) * ky], axis=1)
        d = p1 - p0
        L2 = np.maximum((d * d).sum(axis=1), 1e-12)
        t = np.clip(-(p0 * d).sum(axis=1) / L2, 0.0, 1.0)
        q = p0 + t[:, None] * d
        return float(np.sqrt((q * q).sum(axis=1)).min())


_INDEX: dict = {}
_INDEX_LOCK = threading.Lock()


def road_index(path: str | Path) -> RoadIndex:
    """RoadIndex of a file, cached by path, size and modification time."""
    p = Path(path).resolve()
    st = p.stat()
    key = (str(p), st.st_size, st.st_mtime_ns)
    with _INDEX_LOCK:
        idx = _INDEX.get(key)
    if idx is None:
        idx = RoadIndex(p)
        with _INDEX_LOCK:
            _INDEX[key] = idx
    return idx


def preset_containing(lat: float, lon: float):
    """The embedded preset whose OSM extract holds the point (the nearest centre if several
    share an extract), or None."""
    from netgen.osm_file import header_bbox
    from netgen.presets import list_presets

    hits = []
    for p in list_presets():
        bb = header_bbox(p.osm)
        if bb and bb[0] <= lat <= bb[2] and bb[1] <= lon <= bb[3]:
            hits.append((math.hypot(p.center[0] - lat, (p.center[1] - lon) * math.cos(math.radians(lat))), p.name, p))
    return min(hits)[2] if hits else None


# --------------------------------------------------------------------------------------
# the slower checks against reality
# --------------------------------------------------------------------------------------
def world_out_dir(world: WorldConfig, root: str | Path) -> Path:
    """Where the launcher builds a world: one folder per place and settings, so going back
    to earlier settings reuses the world instead of rebuilding it."""
    from netgen.build import resolve_place

    name = resolve_place(world)[0]
    return Path(root) / f"{name}-{world.fingerprint()[:10]}"


def make_config(r: Ranged, out_root: str | Path | None, place: dict) -> SimConfig:
    """SimConfig from the checked values; `place` holds the WorldConfig place fields."""
    v = r.values
    world = WorldConfig(chunks=r.chunks, quality=v.quality, **place)
    if r.dem:
        world.dem = [r.dem]
    elif v.flat:
        world.flat = True
    if out_root is not None:
        world.out = str(world_out_dir(world, out_root))
    return SimConfig(world=world, traffic=r.traffic, seed=v.seed, start=r.start, goal=r.goal,
                     speed_mps=r.speed, duration_s=RUN_DURATION_S, gui=v.gui, render=True,
                     realtime=v.realtime, name="gui")


def check_reality(r: Ranged, out_root: str | Path | None = None, max_snap_m: float | None = None) -> CheckResult:
    """Is there a road near the start (and the destination), inside the map data and the
    world that will be built? Reads the OSM file (cached) and the DEM header."""
    from netgen.build import resolve_place
    from netgen.frame import WorldFrame
    from netgen.presets import get_preset

    v = r.values
    res = CheckResult()
    snap = SimConfig.max_snap_m if max_snap_m is None else max_snap_m
    # 1. the place and its map data
    index = None
    data_name = ""
    try:
        if v.mode == "preset":
            p = get_preset(v.preset)
            place = {"preset": p.name}
            index, data_name = road_index(p.osm), f"the {p.name} preset"
            check_point = p.center
            what = "preset"
        elif r.osm:
            place = {"osm": r.osm, "center": r.start}
            index, data_name = road_index(r.osm), Path(r.osm).name
            check_point, what = r.start, "lat"
        else:
            p = preset_containing(*r.start)
            if p is not None:
                place = {"preset": p.name, "center": r.start}
                index, data_name = road_index(p.osm), f"the {p.name} preset"
                res.notes.append(f"map data: the {p.name} preset's extract")
            else:
                place = {"center": r.start}
                res.notes.append("map data: fetched from OpenStreetMap (Overpass) at Start; roads are checked then")
            check_point, what = r.start, "lat"
    except CosimError as e:
        res.errors.append(FieldError("osm" if r.osm else "preset", str(e)))
        return res
    try:
        cfg = make_config(r, out_root, place)
    except CosimError as e:
        res.errors.append(FieldError("place", str(e)))
        return res
    # 2. the start: inside the data, near a road
    if index is not None and check_point is not None:
        lat, lon = check_point
        if index.bbox is not None and not index.contains(lat, lon):
            res.errors.append(FieldError(what, f"{lat:.5f}, {lon:.5f} is outside the map data of {data_name} "
                                               f"({index.bbox_text()})"))
        else:
            d = index.nearest_road_m(lat, lon)
            if d > snap:
                near = "there is no road for cars in the data" if not math.isfinite(d) else \
                    f"the nearest is {d:.0f} m away"
                res.errors.append(FieldError(what, f"no road for cars within {snap:.0f} m of "
                                                   f"{lat:.5f}, {lon:.5f} ({near})"))
    # 3. the destination: inside the world that will be built, near a road
    try:
        name, centre, _, _ = resolve_place(cfg.world)
    except CosimError as e:
        res.errors.append(FieldError("osm" if r.osm else "place", str(e)))
        return res
    frame = WorldFrame(centre[0], centre[1], cfg.world.chunk_size_m)
    extent = frame.extent(frame.ring(cfg.world.chunks))
    if r.goal is not None:
        glat, glon = r.goal
        x, y = (float(a) for a in frame.to_xy(glon, glat))
        xmin, ymin, xmax, ymax = extent
        if not (xmin <= x <= xmax and ymin <= y <= ymax):
            res.errors.append(FieldError(
                "dest", f"{glat:.5f}, {glon:.5f} is outside the world to be built ({math.hypot(x, y) / 1000:.1f} km "
                        f"from its centre; {cfg.world.chunks} ring(s) of chunks reach {xmax / 1000:.1f} km): "
                        f"raise Chunks or pick a nearer point"))
        elif index is not None:
            if index.bbox is not None and not index.contains(glat, glon):
                res.errors.append(FieldError("dest", f"{glat:.5f}, {glon:.5f} is outside the map data of "
                                                     f"{data_name} ({index.bbox_text()})"))
            else:
                d = index.nearest_road_m(glat, glon)
                if d > snap:
                    res.errors.append(FieldError("dest", f"no road for cars within {snap:.0f} m of {glat:.5f}, "
                                                         f"{glon:.5f} (the nearest is {d:.0f} m away)"))
    # 4. elevation: a DEM must cover the whole world; without one, a preset or flat ground
    bbox = frame.bbox_lonlat(extent, margin_m=50.0)
    if r.dem:
        try:
            from netgen.dem import open_dem

            open_dem([r.dem]).check_covers(*bbox)
        except CosimError as e:
            res.errors.append(FieldError("dem", str(e)))
    elif not cfg.world.preset and not v.flat:
        res.errors.append(FieldError("dem", "no elevation data for this place: choose a DEM file "
                                            "(SRTM .hgt or GeoTIFF) or tick 'Flat ground'"))
    # 5. the API's own validation, last
    if not res.errors:
        try:
            res.config = cfg.validate()
        except CosimError as e:
            res.errors.append(FieldError("place", str(e)))
    return res


def check_all(v: FormValues, out_root=None) -> CheckResult:
    """Both layers in one call (scripts and tests)."""
    r, errors = check_ranges(v)
    if errors:
        return CheckResult(errors=errors)
    return check_reality(r, out_root)
