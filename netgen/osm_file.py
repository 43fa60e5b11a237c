"""Local OSM files: .osm, .osm.pbf, .osm.gz, .osm.bz2 (read with pyosmium).

netconvert reads OSM XML only, so other encodings are converted once with pyosmium (fast, in
C++) into the cache, keyed by the file's content hash. The conversion is also the check: an
empty, corrupt or truncated file, or one with no ways at all, is a one-line DataError. It is
one pass over the file, counting ways and relations on the way (a Python callback per node
would cost more than the whole conversion; nodes are counted only to word the "no map data"
error).
"""
from __future__ import annotations

import hashlib
from pathlib import Path

import osmium

from ._atomic import atomic_path
from .errors import DataError

SUFFIXES = (".osm", ".osm.pbf", ".pbf", ".osm.gz", ".osm.bz2", ".xml")


def file_hash(path: Path, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while True:
            b = f.read(chunk)
            if not b:
                break
            h.update(b)
    return h.hexdigest()


def _suffix_ok(path: Path) -> bool:
    name = path.name.lower()
    return any(name.endswith(s) for s in SUFFIXES)


def _check_readable(path: Path) -> None:
    if not path.exists():
        raise DataError(f"OSM file not found: {path}")
    if not _suffix_ok(path):
        raise DataError(f"OSM file {path.name}: unknown format (use .osm, .osm.pbf, .osm.gz or .osm.bz2)")
    if path.stat().st_size == 0:
        raise DataError(f"OSM file {path.name} is empty")


class _WayCounter(osmium.SimpleHandler):
    """Counts ways, highway ways and relations (no node callback: see the module docstring)."""

    def __init__(self):
        super().__init__()
        self.ways = self.highways = self.relations = 0

    def way(self, w):
        self.ways += 1
        if "highway" in w.tags:
            self.highways += 1

    def relation(self, r):
        self.relations += 1


def scan(path: Path) -> dict:
    """Read the whole file once with pyosmium; return counts and the data bbox.

    Raises DataError for a missing, empty, corrupt or truncated file."""
    path = Path(path)
    _check_readable(path)

    class Counter(_WayCounter):
        def __init__(self):
            super().__init__()
            self.nodes = 0
            self.minlon = self.minlat = 1e9
            self.maxlon = self.maxlat = -1e9

        def node(self, n):
            self.nodes += 1
            loc = n.location
            if loc.valid():
                lon, lat = loc.lon, loc.lat
                if lon < self.minlon: self.minlon = lon
                if lon > self.maxlon: self.maxlon = lon
                if lat < self.minlat: self.minlat = lat
                if lat > self.maxlat: self.maxlat = lat

    c = Counter()
    try:
        c.apply_file(str(path))
    except Exception as e:  # osmium raises RuntimeError subclasses for parse errors
        msg = " ".join(str(e).split())[:200]
        raise DataError(f"OSM file {path.name} is corrupt or truncated ({msg})") from None
    if c.nodes == 0 or c.ways == 0:
        raise DataError(f"OSM file {path.name} has no map data ({c.nodes} nodes, {c.ways} ways)")
    return {"nodes": c.nodes, "ways": c.ways, "relations": c.relations, "highway_ways": c.highways,
            "bbox": (c.minlat, c.minlon, c.maxlat, c.maxlon)}


def header_bbox(path: Path):
    """The (south, west, north, east) box from the file header, or None."""
    try:
        r = osmium.io.Reader(str(path), osmium.osm.osm_entity_bits.NOTHING)
        box = r.header().box()
        r.close()
    except Exception:
        return None
    if not box.valid():
        return None
    return (box.bottom_left.lat, box.bottom_left.lon, box.top_right.lat, box.top_right.lon)


def count_xml(path: Path, chunk: int = 1 << 22) -> dict:
    """Ways, relations and highway ways of an OSM XML file written by libosmium, counted in
    its text (a Python callback per way, as :class:`_WayCounter` does, costs twice as much
    as the whole conversion): libosmium writes one element or tag per line, nodes, then
    ways, then relations, and escapes ``<`` inside values, so ``<way `` starts a way,
    ``<relation `` a relation, and a ``<tag k="highway"`` line between the first way and
    the first relation is a way's highway tag (a key appears once per object)."""
    way, rel, hw = b"<way ", b"<relation ", b'<tag k="highway"'
    n_way = n_rel = n_hw = 0
    in_ways = done = False          # reading ways / past the first relation
    rest = b""
    with open(path, "rb") as f:
        while True:
            data = f.read(chunk)
            buf = rest + data
            if data:                # whole lines only; the rest goes with the next chunk
                cut = buf.rfind(b"\n") + 1
                buf, rest = buf[:cut], buf[cut:]
            if not buf:
                if not data:
                    break
                continue
            n_way += buf.count(way)
            n_rel += buf.count(rel)
            if not done:
                lo = 0
                if not in_ways:
                    lo = buf.find(way)
                    in_ways = lo >= 0
                if in_ways:
                    hi = buf.find(rel, lo)
                    done = hi >= 0
                    n_hw += buf.count(hw, lo, hi if done else len(buf))
            if not data:
                break
    return {"ways": n_way, "relations": n_rel, "highway_ways": n_hw}


def to_osm_xml(path: Path, cache_dir: Path) -> tuple[Path, dict]:
    """Check `path` and return (OSM XML file netconvert can read, info with the sha256).

    Every input is rewritten once into the cache as OSM XML sorted by type and id (pyosmium's
    MergeInputReader sorts): netconvert reads only XML, and pyosmium's area assembly needs
    sorted input (extracts edited in JOSM carry negative ids out of order)."""
    import json

    from ._atomic import write_text

    path = Path(path).resolve()
    _check_readable(path)
    digest = file_hash(path)
    out = Path(cache_dir) / "osm" / f"{digest[:24]}.osm"
    marker = Path(cache_dir) / "osm" / f"{digest[:24]}.scan"
    if marker.exists() and out.exists():
        try:
            return out, json.loads(marker.read_text())
        except ValueError:
            pass
    with atomic_path(out) as tmp:
        w = osmium.SimpleWriter(osmium.io.File(str(tmp), "osm"), overwrite=True)
        try:
            r = osmium.MergeInputReader()
            r.add_file(str(path))
            r.apply(w)
        except Exception as e:    # libosmium: a parse error, a truncated block (RuntimeError subclasses)
            msg = " ".join(str(e).split())[:200]
            raise DataError(f"OSM file {path.name} is corrupt or truncated ({msg})") from None
        finally:
            w.close()
        counts = count_xml(tmp)
        if counts["ways"] == 0:
            nodes = scan(path)["nodes"]      # only to word the error
            raise DataError(f"OSM file {path.name} has no map data ({nodes} nodes, 0 ways)")
    info = {**counts, "sha256": digest}
    write_text(marker, json.dumps(info))
    return out, info
