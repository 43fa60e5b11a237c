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

from ._atomic import atomic_path, disk_full
from .errors import BuildError, DataError

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


def _corrupt(path: Path, e: Exception) -> DataError:
    """The one-line error for a file libosmium could not read (a parse error, a truncated
    block: RuntimeError subclasses)."""
    msg = " ".join(str(e).split())[:200]
    return DataError(f"OSM file {path.name} is corrupt or truncated ({msg})")


def _conversion_error(path: Path, out: Path, e: Exception) -> Exception:
    """The one-line error for a libosmium failure while converting ``path`` into ``out``:
    the disk's when the write failed (libosmium says "Write failed"), else the file's."""
    text = " ".join(str(e).split())
    if "No space left" in text or disk_full(out.parent):
        return BuildError(f"disk full while writing {out}")
    if "Write failed" in text:
        return BuildError(f"cannot write {out}: {text[:200]}")
    return _corrupt(path, e)


def _give_up(writer) -> None:
    """Close a pyosmium writer after an error, or else never let it be destroyed. A writer
    whose output failed (a full disk) keeps the buffer it could not write, and destroying it
    writes that buffer again; libosmium, in its error state, throws from the destructor and
    the process aborts ("terminate called after throwing an instance of 'osmium::io_error'"),
    after the build had said "disk full while writing ...". Such a writer keeps one more
    reference, so it is never destroyed (its memory stays with the process: a failed build's)."""
    try:
        writer.close()
        return
    except Exception:
        pass
    import ctypes

    ctypes.pythonapi.Py_IncRef(ctypes.py_object(writer))


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
        raise _corrupt(path, e) from None
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


def _cache_entry(path: Path, cache_dir: Path, ext: str, marker_ext: str):
    """(resolved path, its sha256, the cache file and its marker, the marker's info if both
    are there and it reads, else None) for a file converted from `path` into the cache. The
    marker is written after the file is in place, so a file without it is not trusted."""
    import json

    path = Path(path).resolve()
    _check_readable(path)
    digest = file_hash(path)
    out = Path(cache_dir) / "osm" / f"{digest[:24]}{ext}"
    marker = Path(cache_dir) / "osm" / f"{digest[:24]}{marker_ext}"
    info = None
    if marker.exists() and out.exists():
        try:
            info = json.loads(marker.read_text())
        except ValueError:
            pass
    return path, digest, out, marker, info


# ---------------------------------------------------------------------------------------
# ways netconvert must not join (``--geometry.remove``)
# ---------------------------------------------------------------------------------------
#: OSM ``tunnel=*`` values of roads that stay on the ground (through a building, under an
#: avalanche roof): meshed like any road
SURFACE_TUNNEL_VALUES = frozenset({"no", "", "building_passage", "avalanche_protector"})
#: the tags a way kept apart has one of (:func:`_level_way`: a tunnel, another layer)
LEVEL_KEYS = ("tunnel", "layer")


def _level_way(tags) -> bool:
    """A tunnel (not a passage through a building), or a way on another layer that is no
    bridge. (A bridge is left to be joined with its approaches: the world lifts the joined
    edge as one deck, which clears what it spans. Kept apart, a bridge could rise only over
    its own length, or on approaches found again, and Portland's tangles of ramps and bridges
    then came out with new steps.)"""
    if tags.get("tunnel", "no") not in SURFACE_TUNNEL_VALUES:
        return True
    return tags.get("layer", "0") != "0" and tags.get("bridge", "no") == "no"


def _edge_ids(way_id: int, n_nodes: int) -> list:
    """The ids netconvert's OSM importer may give the edges of a way: the way's id, ``#k``
    for its k-th piece where other ways split it, ``-`` in front for the other direction."""
    base = [str(way_id)] + [f"{way_id}#{k}" for k in range(max(n_nodes - 1, 0))]
    return base + ["-" + i for i in base]


def keep_edges_file(osm_xml: Path) -> Path:
    """The list of edges netconvert is to keep whole (``--geometry.remove.keep-edges.input-file``)
    for an OSM file converted into the cache: written beside it, before its marker."""
    return Path(str(osm_xml) + ".keep")


def _write_keep(ways, out: Path) -> int:
    """Write the edge ids of `ways` ((id, node count) of the tunnels and the ways on other
    layers: :func:`_level_way`) to `out`, atomically. netconvert's ``--geometry.remove`` joins
    a way with the ways it continues into one edge that keeps the tags of one of them: a
    tunnel joined with the street it leads into left the street unmeshed (a hole in the road)
    or the tunnel meshed over the ground. The presets' and the shared places' networks had
    2-41 such edges with car lanes (Monaco 37), and 20-78 without."""
    from ._atomic import write_text

    write_text(out, "".join(i + "\n" for wid, n in ways for i in _edge_ids(wid, n)))
    return len(ways)


def to_osm_xml(path: Path, cache_dir: Path) -> tuple[Path, dict]:
    """Check `path` and return (OSM XML file netconvert can read, info with the sha256).

    Every input is rewritten once into the cache as OSM XML sorted by type and id (pyosmium's
    MergeInputReader sorts): netconvert reads only XML, and pyosmium's area assembly needs
    sorted input (extracts edited in JOSM carry negative ids out of order)."""
    import json

    from ._atomic import write_text

    path, digest, out, marker, info = _cache_entry(path, cache_dir, ".osm", ".scan3")
    if info is not None and keep_edges_file(out).exists():
        return out, info
    with atomic_path(out) as tmp:
        try:
            w = osmium.SimpleWriter(osmium.io.File(str(tmp), "osm"), overwrite=True)
            try:
                r = osmium.MergeInputReader()
                r.add_file(str(path))
                r.apply(w)
                w.close()           # (writes what is buffered: a full disk may show here)
            except BaseException:
                _give_up(w)
                raise
        except Exception as e:    # libosmium: a parse error, a truncated block (RuntimeError subclasses)
            raise _conversion_error(path, out, e) from None
        counts = count_xml(tmp)
        if counts["ways"] == 0:
            nodes = scan(path)["nodes"]      # only to word the error
            raise DataError(f"OSM file {path.name} has no map data ({nodes} nodes, 0 ways)")
        keep = [(w.id, len(w.nodes)) for w in osmium.FileProcessor(osmium.io.File(str(tmp), "osm"), osmium.osm.WAY)
                .with_filter(osmium.filter.KeyFilter(*LEVEL_KEYS)) if _level_way(w.tags)]
    counts["level_ways"] = _write_keep(keep, keep_edges_file(out))
    info = {**counts, "sha256": digest}
    write_text(marker, json.dumps(info))
    return out, info


# ---------------------------------------------------------------------------------------
# what netconvert reads
# ---------------------------------------------------------------------------------------
#: the keys that make netconvert's OSM importer take a way in (a road, rail or waterway by
#: its type; ``public_transport`` for platforms). A way without any of them is never part
#: of the network, but its nodes still count: see :func:`network_xml`.
NETWORK_WAY_KEYS = ("highway", "railway", "waterway", "cycleway", "busway", "route", "sidewalk",
                    "highspeed", "usage", "public_transport")
#: the relations netconvert reads: turn restrictions, and routes (a bus route gives buses
#: their permission on the lanes it takes)
NETWORK_RELATION_TYPES = ("restriction", "route")


def network_xml(path: Path, cache_dir: Path) -> tuple[Path, dict]:
    """Check the PBF file `path` and return (OSM XML with only what netconvert reads, info
    with the sha256), written once into the cache.

    netconvert parses its input three times (nodes, ways, relations); on a city extract most
    of it is buildings, land use and their nodes, which it reads and drops. This keeps the
    ways with one of :data:`NETWORK_WAY_KEYS`, the relations of
    :data:`NETWORK_RELATION_TYPES` with their members among those ways (and their node
    members), and the nodes these use, tags and all. netconvert's network from it is the same
    file as from the whole extract, after the header (checked on the presets, Monaco, Lauf and
    Portland), made in 0.66-0.87 of the time. (netconvert splits a way where another way it
    takes in uses its node, and those are the ways kept here: a key such as ``waterway``
    counts even though no typemap of ours builds it. Dropping the route relations, or their
    members' nodes, changed the buses' permissions on some Monaco lanes.)

    Read with pyosmium in three passes over the PBF (ways and relations, nodes, ways again),
    the filtering in C++ but for the node test. An empty, corrupt or truncated file, or one
    with no ways at all, is a one-line DataError, as in :func:`to_osm_xml`."""
    import json

    from ._atomic import write_text

    path, digest, out, marker, info = _cache_entry(path, cache_dir, ".network.osm", ".network3.json")
    if info is not None and keep_edges_file(out).exists():
        return out, info
    with atomic_path(out) as tmp:
        try:
            counts = _write_network(path, tmp)
        except DataError:
            raise
        except Exception as e:    # libosmium: a parse error, a truncated block, a failed write
            raise _conversion_error(path, out, e) from None
        if counts["network_ways"] == 0:
            scan(path)          # no map data at all: its error; else netconvert says "no roads"
    counts["level_ways"] = _write_keep(counts.pop("level"), keep_edges_file(out))
    info = {**counts, "sha256": digest}
    write_text(marker, json.dumps(info))
    return out, info


def _write_network(src: Path, out: Path) -> dict:
    """Three passes: the ways and relations kept (their ids, the nodes they use), then the
    nodes written, then the ways (netconvert wants the nodes first: it stops reading nodes
    at the first way), then the relations."""
    src = str(src)
    ways = osmium.filter.KeyFilter(*NETWORK_WAY_KEYS).enable_for(osmium.osm.WAY)
    types = osmium.filter.TagFilter(*(("type", t) for t in NETWORK_RELATION_TYPES)).enable_for(osmium.osm.RELATION)
    way_ids, node_ids, rels, level = set(), set(), [], []
    for o in osmium.FileProcessor(src, osmium.osm.WAY | osmium.osm.RELATION).with_filter(ways).with_filter(types):
        if o.is_way():
            way_ids.add(o.id)
            node_ids.update(n.ref for n in o.nodes)
            if _level_way(o.tags):
                level.append((o.id, len(o.nodes)))
        else:               # (after the ways: an OSM file has nodes, then ways, then relations)
            members = [(m.type, m.ref, m.role) for m in o.members
                       if (m.ref in way_ids if m.type == "w" else m.type == "n")]
            node_ids.update(ref for t, ref, _ in members if t == "n")
            rels.append(o.replace(members=members, tags=dict(o.tags)))  # (a copy: the buffer goes)
    writer = osmium.SimpleWriter(osmium.io.File(str(out), "osm"), overwrite=True)
    try:
        for n in osmium.FileProcessor(src, osmium.osm.NODE):
            if n.id in node_ids:
                writer.add_node(n)
        osmium.apply(src, osmium.filter.EntityFilter(osmium.osm.WAY), ways, writer)
        for r in rels:
            writer.add_relation(r)
        writer.close()
    except BaseException:
        _give_up(writer)
        raise
    return {"network_ways": len(way_ids), "network_nodes": len(node_ids), "network_relations": len(rels),
            "level": level}
