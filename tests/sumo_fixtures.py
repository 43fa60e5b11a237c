"""Build a SUMO network from an embedded OSM preset, the way the world builder does.

Kept apart from the tests so that the world builder's real network can replace it later: tests
only need ``build_net(pbf, lat, lon, out_dir) -> Path``. The netconvert options mirror the
world builder's (same tmerc projection at the reference point, normalisation off, so SUMO x/y
are world metres).
"""
from __future__ import annotations

import os
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
HELSINKI_PBF = REPO / "netgen" / "presets" / "helsinki-2019.osm.pbf"
HELSINKI_CENTER = (60.1700, 24.9420)


def build_net(pbf: Path, lat: float, lon: float, out_dir: Path, name: str = "net",
              extra: tuple[str, ...] = (), osm: Path | None = None) -> Path:
    """netconvert ``pbf`` into ``out_dir/<name>.net.xml`` with the world builder's own options
    (netgen.sumo_net.netconvert_args: tmerc at the reference point, world-metre coordinates)."""
    from netgen import sumo_net
    from netgen.frame import WorldFrame
    from netgen.osm_file import to_osm_xml

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if osm is None:
        osm, _ = to_osm_xml(Path(pbf), out_dir / "cache")
    net = out_dir / f"{name}.net.xml"
    tmp = out_dir / f"{name}.part.net.xml"
    args = sumo_net.netconvert_args(osm, tmp, WorldFrame(lat, lon).proj_string) + list(extra)
    proc = subprocess.run(args, capture_output=True, text=True, env=sumo_net.sumo_env())
    if proc.returncode != 0:
        raise RuntimeError(f"netconvert failed: {proc.stderr.strip()[-2000:]}")
    os.replace(tmp, net)
    return net


def build_helsinki(out_dir: Path, name: str = "helsinki", extra: tuple[str, ...] = ()) -> Path:
    return build_net(HELSINKI_PBF, *HELSINKI_CENTER, out_dir, name=name, extra=extra)
