"""A light, fast read of a SUMO ``.net.xml`` for meshing and analysis.

``sumolib.net.readNet`` builds a full object graph and takes seconds on a city network; the
world builder needs only shapes, widths, permissions and ids, so it reads the same XML with a
streaming parser (lxml's ``iterparse``, in C, with a tag filter; the standard library's
ElementTree where lxml is missing), keeps shapes as numpy arrays, and uses sumolib's own
vehicle-class rules for allow/disallow.

Speed (a city network is ~10 MB of XML, read while the rest of the build waits):

* only ``edge``, ``junction``, ``tlLogic`` and ``location`` elements are handled, and parsing
  stops at the first ``connection`` (netconvert writes connections, roundabouts and nothing
  else the builder needs after the junctions);
* shapes (``"x,y x,y ..."``) are collected as strings and parsed a few thousand at a time
  in one numpy call, as the file is read;
* permissions are resolved once per distinct (allow, disallow) pair;
* :func:`read_net_while_written` reads netconvert's output while netconvert is still writing
  it (writing a city network takes netconvert a quarter of its run, and what the builder
  needs is in the first three quarters of the file).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np
from sumolib.net.lane import get_allowed

from .osm_file import SURFACE_TUNNEL_VALUES

try:
    from lxml import etree as _etree
    _LXML = True

    def _children(el, tag):
        return el.iterchildren(tag)
except ImportError:  # pragma: no cover - lxml is a dependency; ElementTree is the fallback
    import xml.etree.ElementTree as _etree
    _LXML = False

    def _children(el, tag):
        return el.iterfind(tag)

CAR_CLASSES = {"passenger", "private", "taxi", "bus", "truck", "delivery", "emergency", "evehicle"}


def parse_shape(s: str | None) -> np.ndarray:
    if not s:
        return np.zeros((0, 2))
    pts = [p.split(",") for p in s.split()]
    return np.array([[float(p[0]), float(p[1])] for p in pts], dtype=float)


@dataclass
class Lane:
    id: str
    index: int
    width: float
    speed: float
    length: float
    allowed: frozenset
    shape: np.ndarray

    @property
    def drivable(self) -> bool:
        return bool(self.allowed & CAR_CLASSES)

    @property
    def pedestrian_only(self) -> bool:
        return self.allowed == frozenset({"pedestrian"})


@dataclass
class Edge:
    id: str
    function: str                  # "normal", "internal", "crossing", "walkingarea"
    from_node: str | None
    to_node: str | None
    name: str
    type: str
    orig_ids: tuple                # OSM way ids
    lanes: list = field(default_factory=list)
    raw_shape: np.ndarray | None = None     # from-node .. to-node geometry (unclipped)
    tunnel: bool = False           # OSM tunnel=* (yes, culvert, ...): under the ground, not on it
    priority: int = 0              # netconvert's edge priority (from the road type)
    layer: int = 0                 # OSM layer=* (a bridge without one: 1)
    bridge: bool = False           # OSM bridge=* (not "no"): a deck, not on the ground


    @property
    def drivable(self) -> bool:
        return any(l.drivable for l in self.lanes)


@dataclass
class Junction:
    id: str
    type: str
    x: float
    y: float
    shape: np.ndarray


@dataclass
class RoadNet:
    edges: dict
    junctions: dict
    tls_ids: list
    location: dict

    def normal_edges(self):
        return [e for e in self.edges.values() if e.function == "normal"]

    def drivable_edges(self):
        return [e for e in self.edges.values() if e.function == "normal" and e.drivable]

    def counts(self) -> dict:
        normal = self.normal_edges()
        return {
            "road_edges": sum(1 for e in normal if e.drivable),
            "footpath_edges": sum(1 for e in normal if not e.drivable),
            "lanes": sum(len(e.lanes) for e in normal),
            "junctions": sum(1 for j in self.junctions.values() if j.type != "internal"),
            "traffic_lights": len(self.tls_ids),
            "crossings": sum(1 for e in self.edges.values() if e.function == "crossing"),
            "walkingareas": sum(1 for e in self.edges.values() if e.function == "walkingarea"),
            "road_length_km": round(sum(max((l.length for l in e.lanes), default=0.0)
                                        for e in normal if e.drivable) / 1000.0, 3),
        }


@lru_cache(maxsize=None)
def _int(s: str | None, default=0):
    """An integer attribute (OSM's ``layer`` may be ``1;2`` or ``-0.5``: the first number,
    truncated); `default` where there is none."""
    try:
        return int(float(str(s).split(";")[0]))
    except (TypeError, ValueError):
        return default


@lru_cache(maxsize=None)
def _allowed(allow: str | None, disallow: str | None) -> frozenset:
    """The vehicle classes a lane's allow / disallow attributes let on it (sumolib's rules),
    worked out once per distinct pair (a city network has a few dozen among 30,000 lanes)."""
    return frozenset(get_allowed(allow, disallow))


def _parse_shapes(strings: list) -> list:
    """Many SUMO shape strings ("x,y x,y ...", may be empty) -> list of (n, 2) arrays."""
    counts = np.array([s.count(" ") + 1 if s else 0 for s in strings], dtype=np.int64)
    text = " ".join(s for s in strings if s).replace(",", " ")
    flat = np.fromstring(text, dtype=float, sep=" ") if text else np.zeros(0)     # (C: 1.5x text.split())
    if len(flat) != 2 * counts.sum():   # an odd shape (3D points, stray spaces): one by one
        return [parse_shape(s) for s in strings]
    pts = flat.reshape(-1, 2)
    ends = np.cumsum(counts).tolist()
    return [pts[a:b] for a, b in zip([0] + ends[:-1], ends)]


class _GrowingFile:
    """A file another process is still writing: read() waits for more bytes until that
    process has exited (then the rest, then end of file)."""

    def __init__(self, path: Path, proc, poll_s: float = 0.005):
        self.path, self.proc, self.poll_s = Path(path), proc, poll_s
        self.f = None
        self.writer_done = False

    def read(self, n: int = -1) -> bytes:
        n = n if n and n > 0 else 1 << 16
        while True:
            if self.f is None:
                if self.path.exists():
                    self.f = open(self.path, "rb")
                elif self.proc.poll() is not None:
                    return b""
                else:
                    time.sleep(self.poll_s)
                    continue
            data = self.f.read(n)
            if data or self.writer_done:
                return data
            if self.proc.poll() is not None:
                self.writer_done = True     # read what is left once more, then end of file
            else:
                time.sleep(self.poll_s)

    def close(self) -> None:
        if self.f is not None:
            self.f.close()


def read_net_while_written(path: str | Path, proc, internal: bool = True,
                           internal_junctions: bool | None = None) -> RoadNet:
    """:func:`read_net` of the file that the running process `proc` (netconvert) is writing.

    Returns as soon as the parts the builder reads are in (the first ``connection``), which
    is usually before netconvert has exited: the caller must still check that it succeeded
    (a parse error here, e.g. netconvert failed before or while writing, comes up as the
    parser's exception)."""
    f = _GrowingFile(path, proc)
    try:
        return _read(f, internal, internal_junctions)
    finally:
        f.close()


def read_net(path: str | Path, internal: bool = True, internal_junctions: bool | None = None) -> RoadNet:
    """The network in `path`; ``internal=False`` leaves out internal edges and junctions (the
    connections inside junctions), ``internal_junctions=False`` only the internal junctions
    (the world builder reads the internal lanes, where vehicles drive across a junction, but
    not the junctions inside junctions)."""
    with open(path, "rb") as f:
        return _read(f, internal, internal_junctions)


#: shapes are parsed in batches while the file is read (the last batch is all that is left
#: to parse when the reading ends, which is when netconvert has written the junctions)
SHAPE_BATCH = 2000


def _read(f, internal: bool, internal_junctions: bool | None = None) -> RoadNet:
    if internal_junctions is None:
        internal_junctions = internal
    edges: dict = {}
    junctions: dict = {}
    tls: list = []
    location: dict = {}
    shape_str: list = []        # shape strings not parsed yet, parsed SHAPE_BATCH at a time
    shape_dst: list = []        # (object, attribute) that gets each parsed shape

    def parse_pending():
        for (obj, attr), shp in zip(shape_dst, _parse_shapes(shape_str)):
            setattr(obj, attr, shp)
        shape_str.clear()
        shape_dst.clear()

    wanted = ("edge", "junction", "tlLogic", "location", "connection")
    it = _etree.iterparse(f, events=("end",), tag=wanted) if _LXML else _etree.iterparse(f, events=("end",))
    for _, el in it:
        tag = el.tag
        if tag == "edge":
            get = el.get
            if not internal and get("function") == "internal":
                el.clear()
                continue
            # (positional: a dataclass called with keywords took twice as long)
            e = Edge(get("id"), get("function", "normal"), get("from"), get("to"), get("name", ""),
                     get("type", ""), (), [], None, False, _int(get("priority")))
            shape = get("shape")
            if shape is not None:
                shape_str.append(shape)
                shape_dst.append((e, "raw_shape"))
            for ln in _children(el, "lane"):
                get = ln.get
                lane = Lane(get("id"), int(get("index", 0)), float(get("width", 3.2)),
                            float(get("speed", 13.89)), float(get("length", 0.0)),
                            _allowed(get("allow"), get("disallow")), None)
                shape_str.append(get("shape") or "")
                shape_dst.append((lane, "shape"))
                e.lanes.append(lane)
                if not e.orig_ids:
                    for prm in _children(ln, "param"):
                        if prm.get("key") == "origId":
                            e.orig_ids = tuple(prm.get("value", "").split())
                            break
            layer = bridge = None
            for prm in _children(el, "param"):
                key = prm.get("key")
                if key == "tunnel":
                    e.tunnel = prm.get("value", "no") not in SURFACE_TUNNEL_VALUES
                elif key == "layer":
                    layer = _int(prm.get("value"), None)
                elif key == "bridge":
                    bridge = prm.get("value", "no") != "no"
            e.layer = layer if layer is not None else (1 if bridge else 0)
            e.bridge = bool(bridge)
            edges[e.id] = e
        elif tag == "junction":
            get = el.get
            if not internal_junctions and get("type") == "internal":
                el.clear()
                continue
            j = Junction(get("id"), get("type", ""), float(get("x", 0)), float(get("y", 0)), None)
            shape_str.append(get("shape") or "")
            shape_dst.append((j, "shape"))
            junctions[j.id] = j
        elif tag == "tlLogic":
            if el.get("id") not in tls:
                tls.append(el.get("id"))
        elif tag == "location":
            location = dict(el.attrib)
        elif tag == "connection":
            break                   # nothing the builder reads comes after the junctions
        else:
            continue                # ElementTree: every element comes through; keep children
        el.clear()
        if len(shape_str) >= SHAPE_BATCH:
            parse_pending()
    parse_pending()
    return RoadNet(edges=edges, junctions=junctions, tls_ids=tls, location=location)
