"""A light, fast read of a SUMO ``.net.xml`` for meshing and analysis.

``sumolib.net.readNet`` builds a full object graph and takes seconds on a city network; the
world builder needs only shapes, widths, permissions and ids, so it reads the same XML with
the standard library's streaming parser (``xml.etree.ElementTree.iterparse``), keeps shapes as
numpy arrays, and uses sumolib's own vehicle-class rules for allow/disallow.
"""
from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from sumolib.net.lane import get_allowed

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


def read_net(path: str | Path) -> RoadNet:
    edges: dict = {}
    junctions: dict = {}
    tls: list = []
    location: dict = {}
    cur_edge: Edge | None = None
    cur_lane_el = None
    lane_params: dict = {}
    for ev, el in ET.iterparse(str(path), events=("start", "end")):
        tag = el.tag
        if ev == "start":
            if tag == "edge":
                a = el.attrib
                cur_edge = Edge(id=a["id"], function=a.get("function", "normal"),
                                from_node=a.get("from"), to_node=a.get("to"), name=a.get("name", ""),
                                type=a.get("type", ""), orig_ids=(),
                                raw_shape=parse_shape(a.get("shape")) if "shape" in a else None)
            elif tag == "lane":
                cur_lane_el = el
                lane_params = {}
            continue
        # end events
        if tag == "param" and cur_lane_el is not None:
            lane_params[el.attrib.get("key")] = el.attrib.get("value")
        elif tag == "lane" and cur_edge is not None:
            a = el.attrib
            allowed = frozenset(get_allowed(a.get("allow"), a.get("disallow")))
            cur_edge.lanes.append(Lane(id=a["id"], index=int(a.get("index", 0)),
                                       width=float(a.get("width", 3.2)), speed=float(a.get("speed", 13.89)),
                                       length=float(a.get("length", 0.0)), allowed=allowed,
                                       shape=parse_shape(a.get("shape"))))
            if "origId" in lane_params and not cur_edge.orig_ids:
                cur_edge.orig_ids = tuple(lane_params["origId"].split())
            cur_lane_el = None
        elif tag == "edge" and cur_edge is not None:
            edges[cur_edge.id] = cur_edge
            cur_edge = None
            el.clear()
        elif tag == "junction":
            a = el.attrib
            junctions[a["id"]] = Junction(id=a["id"], type=a.get("type", ""), x=float(a.get("x", 0)),
                                          y=float(a.get("y", 0)), shape=parse_shape(a.get("shape")))
            el.clear()
        elif tag == "tlLogic":
            if el.attrib["id"] not in tls:
                tls.append(el.attrib["id"])
            el.clear()
        elif tag == "location":
            location = dict(el.attrib)
        elif tag in ("connection", "request", "roundabout"):
            el.clear()
    return RoadNet(edges=edges, junctions=junctions, tls_ids=tls, location=location)
