"""SUMO network from OSM with netconvert (from the eclipse-sumo wheel, never a system SUMO).

Options: SUMO's OSM typemaps for cars and pedestrians, guessed sidewalks and crossings,
guessed and joined traffic lights (actuated), guessed ramps, joined junction clusters,
simplified geometry, street names and OSM ids kept (``origId`` params). Heights do not come
from OSM ``ele`` tags (sparse tags give spiky junctions): the network is 2D and the world's
ground model (``netgen.terrain``) gives every z.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from .errors import BuildError, DataError


def sumo_home() -> Path:
    import sumo  # the eclipse-sumo wheel

    return Path(sumo.SUMO_HOME)


def sumo_binary(name: str) -> str:
    p = sumo_home() / "bin" / name
    if not p.exists():
        raise BuildError(f"SUMO binary {name} not found in the eclipse-sumo wheel ({p})")
    return str(p)


def sumo_env() -> dict:
    env = dict(os.environ)
    env["SUMO_HOME"] = str(sumo_home())
    proj = sumo_home() / "data" / "proj"
    if proj.is_dir():
        env.setdefault("PROJ_DATA", str(proj))   # the wheel's proj.db, for netconvert's PROJ
    return env


NETCONVERT_VERSION_TAG = "netconvert-opts-v7"


def netconvert_args(osm_xml: Path, out_net: Path, proj: str, geo_boundary=None, tls_join: bool = False,
                    keep_edges: Path | None = None) -> list[str]:
    """netconvert's command line.

    ``--tls.join`` is off by default: on central Helsinki it merges up to 15 nearby signals
    into one program that serves each approach in turn, with cycles of 646 s, and traffic
    jams (600 s of normal demand: 206 of 558 trips arrive, mean wait 171 s; without it 475
    arrive, mean wait 96 s, longest cycle 225 s; --tls.discard-simple or --tls.join-dist 10
    still give 652 s cycles). ``--junctions.join`` already merges the nodes of one
    intersection, so each intersection keeps a single signal program.

    ``--sidewalks.guess.from-permissions`` makes the guess add sidewalks to edges that allow
    pedestrians (the pedestrian typemap gives every street type its own sidewalk). By speed
    alone (``--sidewalks.guess``'s default rule: 5.8 < speed <= 13.89 m/s) netconvert gave a
    sidewalk to every tram and railway edge of central Helsinki (285 tram, 183 rail): people
    walked along the rails, and where a tram track runs beside a street its sidewalk lay
    0.2-0.5 m from the centre of a car lane, so they walked through the cars.

    The OSM tags ``tunnel``, ``bridge`` and ``layer`` are kept as edge parameters (the world
    does not mesh tunnels). ``highway=raceway`` is left out: Monaco's Grand Prix circuit is
    mapped as a second way over the public streets it borrows, and as its own 2.7 km edge it
    laid a second road surface over them, at other heights, with SUMO traffic on it.

    ``keep_edges``: a file of edge ids ``--geometry.remove`` is to leave whole (the tunnels and
    the ways on other layers that are no bridge: :func:`netgen.osm_file.keep_edges_file`), so
    that an edge is all tunnel or all ground.
    """
    tm = sumo_home() / "data" / "typemap"
    args = [
        sumo_binary("netconvert"),
        "--osm-files", str(osm_xml),
        "--type-files", f"{tm / 'osmNetconvert.typ.xml'},{tm / 'osmNetconvertPedestrians.typ.xml'}",
        "--proj", proj, "--offset.disable-normalization", "true",
        "--sidewalks.guess", "true", "--sidewalks.guess.from-permissions", "true",
        "--crossings.guess", "true",
        "--tls.guess-signals", "true", "--tls.join", "true" if tls_join else "false",
        "--tls.default-type", "actuated",
        "--ramps.guess", "true", "--junctions.join", "true", "--geometry.remove", "true",
        "--roundabouts.guess", "true", "--remove-edges.isolated", "true",
        "--output.street-names", "true", "--output.original-names", "true",
        "--junctions.corner-detail", "5", "--rectangular-lane-cut", "false",
        "--osm.elevation", "false",
        "--osm.all-attributes", "true", "--osm.extra-attributes", "tunnel,bridge,layer",
        "--remove-edges.by-type", "highway.raceway",
        "--no-warnings", "false", "--aggregate-warnings", "5",
        "-o", str(out_net),
    ]
    if keep_edges is not None:
        args[-2:-2] = ["--geometry.remove.keep-edges.input-file", str(keep_edges)]
    if geo_boundary is not None:
        s, w, n, e = geo_boundary
        args += ["--keep-edges.in-geo-boundary", f"{w:.7f},{s:.7f},{e:.7f},{n:.7f}"]
    return args


_NUM = re.compile(r"-?\d+(\.\d+)?")
_QUOTED = re.compile(r"'[^']*'")


def summarize_warnings(stderr: str, top: int = 8) -> dict:
    """Group netconvert's warnings by their message template, largest groups first."""
    groups: Counter = Counter()
    for line in stderr.splitlines():
        line = line.strip()
        if not line.startswith("Warning:"):
            continue
        msg = line[len("Warning:"):].strip()
        m = re.match(r"(\d+) total messages of type: (.*)", msg)
        if m:  # netconvert's own aggregation line: its count includes the shown examples
            groups[m.group(2).strip()] = max(groups[m.group(2).strip()], int(m.group(1)))
            continue
        key = _NUM.sub("%", _QUOTED.sub("'%'", msg))
        groups[key] += 1
    total = sum(groups.values())
    return {"total": total, "kinds": len(groups),
            "top": [{"count": c, "message": k} for k, c in groups.most_common(top)]}


@dataclass
class NetResult:
    net_file: Path
    warnings: dict = field(default_factory=dict)
    seconds: float = 0.0


def start_netconvert(osm_xml: Path, out_net: Path, proj: str, geo_boundary=None, log: Path | None = None):
    """Start netconvert in the background (the caller works on other layers meanwhile)."""
    out_net.parent.mkdir(parents=True, exist_ok=True)
    errf = open(log or (out_net.parent / "netconvert.log"), "w+")
    from .osm_file import keep_edges_file

    keep = keep_edges_file(osm_xml)
    args = netconvert_args(osm_xml, out_net, proj, geo_boundary, keep_edges=keep if keep.exists() else None)
    try:
        proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=errf, env=sumo_env())
    except OSError as e:
        errf.close()
        raise BuildError(f"cannot start netconvert: {e}") from None
    return proc, errf


def finish_netconvert(proc, errf, out_net: Path) -> dict:
    rc = proc.wait()
    errf.seek(0)
    stderr = errf.read()
    errf.close()
    errors = [l.strip()[len("Error:"):].strip() for l in stderr.splitlines() if l.strip().startswith("Error:")]
    if rc != 0 or not out_net.exists():
        joined = " | ".join(errors[:3]) or f"exit code {rc}"
        if any("No nodes loaded" in e or "No edges" in e or "empty" in e.lower() for e in errors):
            raise DataError(f"no roads in the area: netconvert found nothing to build ({joined})")
        raise BuildError(f"netconvert failed: {joined}")
    return summarize_warnings(stderr)


def netconvert_available() -> bool:
    try:
        sumo_binary("netconvert")
        return True
    except BuildError:
        return False


def copy_net(src: Path, dst: Path) -> None:
    dst.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dst)
