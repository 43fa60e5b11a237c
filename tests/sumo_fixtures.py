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


def sumo_home() -> str:
    import sumo
    return str(sumo.SUMO_HOME)


def proj_string(lat: float, lon: float) -> str:
    return (f"+proj=tmerc +lat_0={lat:.7f} +lon_0={lon:.7f} +k=1 +x_0=0 +y_0=0 "
            "+ellps=WGS84 +datum=WGS84 +units=m +no_defs")


def netconvert_options(lat: float, lon: float) -> list[str]:
    home = sumo_home()
    typ = os.path.join(home, "data", "typemap")
    return ["--type-files", f"{typ}/osmNetconvert.typ.xml,{typ}/osmNetconvertPedestrians.typ.xml",
            "--sidewalks.guess", "--crossings.guess", "--tls.guess-signals", "--tls.join",
            "--ramps.guess", "--junctions.join", "--geometry.remove", "--output.street-names",
            "--output.original-names", "--tls.default-type", "actuated",
            "--proj", proj_string(lat, lon), "--offset.disable-normalization",
            "--no-warnings"]


def pbf_to_osm(pbf: Path, out: Path) -> Path:
    import osmium
    tmp = out.with_name(out.name + ".part.osm")
    h = osmium.SimpleWriter(str(tmp), overwrite=True)
    osmium.apply(str(pbf), h)
    h.close()
    os.replace(tmp, out)
    return out


def build_net(pbf: Path, lat: float, lon: float, out_dir: Path, name: str = "net",
              extra: tuple[str, ...] = (), osm: Path | None = None) -> Path:
    """netconvert ``pbf`` into ``out_dir/<name>.net.xml`` (world-metre coordinates)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if osm is None:
        osm = out_dir / (Path(pbf).name.split(".")[0] + ".osm")
        if not osm.exists():
            pbf_to_osm(Path(pbf), osm)
    net = out_dir / f"{name}.net.xml"
    tmp = out_dir / f"{name}.part.net.xml"
    home = sumo_home()
    env = dict(os.environ, SUMO_HOME=home, PROJ_DATA=os.path.join(home, "data", "proj"))
    cmd = [os.path.join(home, "bin", "netconvert"), "--osm-files", str(osm), "-o", str(tmp),
           *netconvert_options(lat, lon), *extra]
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise RuntimeError(f"netconvert failed: {proc.stderr.strip()[-2000:]}")
    os.replace(tmp, net)
    return net


def build_helsinki(out_dir: Path, name: str = "helsinki", extra: tuple[str, ...] = ()) -> Path:
    return build_net(HELSINKI_PBF, *HELSINKI_CENTER, out_dir, name=name, extra=extra)
