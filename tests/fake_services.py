"""Real HTTP servers on 127.0.0.1 that stand in for Overpass and open-elevation in tests.

:class:`FakeServices` runs a ``ThreadingHTTPServer`` (port 0, daemon thread) that answers

* Overpass: ``POST <prefix>/api/interpreter`` with the form field ``data=<query>`` (also
  ``GET ?data=``), as the real API takes it. It reads the global bbox (``[bbox:S,W,N,E]``)
  and the tag-filter statements (``way["highway"];``, ``node["natural"="tree"];``,
  ``way["railway"~"^(tram|light_rail)$"];``), and answers OSM XML in Overpass's layout cut
  from a real extract read with pyosmium: the matching nodes in the bbox, the matching ways
  with a node in the bbox, the matching relations with a member in the bbox, then every
  node and way they reference (as ``(._;>;)`` does), sorted by type and id.
* open-elevation: ``POST <prefix>/api/v1/lookup`` with ``{"locations": [...]}`` (also
  ``GET ?locations=lat,lon|lat,lon``), answered from an SRTM ``.hgt`` tile read with numpy
  (bilinear on the 1201 x 1201 grid; -32768 where a corner is a void, as raw SRTM servers
  do; ``null`` outside the tile). More than ``max_batch`` locations gives HTTP 413.

Any path prefix works (``/a/api/interpreter``, ``/b/api/interpreter``), so one server gives
several "endpoints", each with its own request counter and failure script: a list of
actions consumed one per request, after which it answers normally. Actions:

``"ok"``; an int status (``500``, ``502``, ``504``) or ``("status", 429, {"Retry-After": "1"})``;
``("sleep", seconds)`` (then the normal answer, if the client still listens); ``"drop"``
(close without answering); ``"cut"`` (announce the full length, send half, close);
``"html"`` (Overpass's "server too busy" page with HTTP 200); ``"random"`` (random bytes);
``"empty"``; ``"truncated"`` (the first half of the real answer as a complete HTTP 200);
Overpass only: ``"remark"`` (partial XML + ``<remark> runtime error: Query timed out ...``);
open-elevation only: ``"wrong_count"``, ``"null_elevation"``, ``"string_elevation"``,
``"swapped"`` (results in the wrong order), ``"no_results"``.

:func:`closed_port_url` gives a URL on which nothing listens (connection refused).
"""
from __future__ import annotations

import json
import math
import random
import re
import socket
import threading
from collections import defaultdict, deque
from functools import lru_cache
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit
from xml.sax.saxutils import escape

import numpy as np
import osmium

REPO = Path(__file__).resolve().parents[1]
PRESET_OSM = REPO / "netgen" / "presets" / "helsinki-2019.osm.pbf"

OVERPASS_PATH = "/api/interpreter"
ELEVATION_PATH = "/api/v1/lookup"

_BUSY_HTML = b"""<?xml version="1.0" encoding="UTF-8"?>
<!DOCTYPE html PUBLIC "-//W3C//DTD XHTML 1.0 Strict//EN" "http://www.w3.org/TR/xhtml1/DTD/xhtml1-strict.dtd">
<html xmlns="http://www.w3.org/1999/xhtml" xml:lang="en" lang="en">
<head>
  <meta http-equiv="content-type" content="text/html; charset=utf-8" lang="en"/>
  <title>OSM3S Response</title>
</head>
<body>

<p>The data included in this document is from www.openstreetmap.org. The data is made available under ODbL.</p>
<p><strong style="color:#FF0000">Error</strong>: runtime error: open64: 0 Success /osm3s_v0.7.61_osm_base Dispatcher_Client::request_read_and_idx::timeout. The server is probably too busy to handle your request. </p>

</body>
</html>
"""


def closed_port_url(path: str = OVERPASS_PATH) -> str:
    """A URL on 127.0.0.1 where nothing listens (the port was just bound and released)."""
    s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    return f"http://127.0.0.1:{port}{path}"


# --- data -------------------------------------------------------------------------------------
class OsmData:
    """An OSM extract in memory: nodes (id -> lat, lon, tags), ways, relations."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.nodes: dict[int, tuple[float, float, dict]] = {}
        self.ways: dict[int, tuple[list[int], dict]] = {}
        self.relations: dict[int, tuple[list[tuple[str, int, str]], dict]] = {}
        for o in osmium.FileProcessor(str(path)):
            tags = {t.k: t.v for t in o.tags}
            if o.is_node():
                if o.location.valid():
                    self.nodes[o.id] = (o.location.lat, o.location.lon, tags)
            elif o.is_way():
                self.ways[o.id] = ([n.ref for n in o.nodes], tags)
            elif o.is_relation():
                self.relations[o.id] = ([(m.type, m.ref, m.role) for m in o.members], tags)
        ids = np.fromiter(self.nodes.keys(), dtype=np.int64, count=len(self.nodes))
        self._ids = ids
        self._lat = np.array([self.nodes[i][0] for i in ids.tolist()])
        self._lon = np.array([self.nodes[i][1] for i in ids.tolist()])

    def nodes_in(self, s, w, n, e) -> set[int]:
        m = (self._lat >= s) & (self._lat <= n) & (self._lon >= w) & (self._lon <= e)
        return set(self._ids[m].tolist())

    def select(self, bbox, statements):
        """(node ids, way ids, relation ids) of an Overpass-like query, recursed down.

        ``statements`` is [(type, [(key, op, value), ...]), ...] with op None (key present),
        "=" or "~" (regex), as parsed by :func:`parse_statements`.
        """
        def match(tags, filters):
            for k, op, v in filters:
                if k not in tags or (op == "=" and tags[k] != v) or (op == "~" and not re.search(v, tags[k])):
                    return False
            return True

        def wanted(typ, tags):
            return any(t in (typ, "nwr") and match(tags, f) for t, f in statements)

        inside = self.nodes_in(*bbox)
        nodes = {i for i in inside if wanted("node", self.nodes[i][2])}
        ways_in = {wid for wid, (nds, _) in self.ways.items() if not inside.isdisjoint(nds)}
        ways = {wid for wid in ways_in if wanted("way", self.ways[wid][1])}
        rels = set()
        for rid, (members, tags) in self.relations.items():
            if not wanted("relation", tags):
                continue
            if any((t == "n" and ref in inside) or (t == "w" and ref in ways_in) for t, ref, _ in members):
                rels.add(rid)
        for rid in rels:  # (._;>;): members of relations, then nodes of ways
            for t, ref, _ in self.relations[rid][0]:
                if t == "w" and ref in self.ways:
                    ways.add(ref)
                elif t == "n" and ref in self.nodes:
                    nodes.add(ref)
        for wid in ways:
            nodes.update(r for r in self.ways[wid][0] if r in self.nodes)
        return nodes, ways, rels

    def to_xml(self, nodes, ways, rels) -> list[bytes]:
        """Overpass-style OSM XML, one bytes item per element (for cutting it up)."""
        def tags(d):
            return "".join(f'    <tag k="{escape(k, _Q)}" v="{escape(v, _Q)}"/>\n' for k, v in d.items())

        out = []
        for i in sorted(nodes):
            lat, lon, t = self.nodes[i]
            head = f'  <node id="{i}" lat="{lat:.7f}" lon="{lon:.7f}"'
            out.append((head + (f">\n{tags(t)}  </node>\n" if t else "/>\n")).encode())
        for i in sorted(ways):
            nds, t = self.ways[i]
            body = "".join(f'    <nd ref="{r}"/>\n' for r in nds)
            out.append(f'  <way id="{i}">\n{body}{tags(t)}  </way>\n'.encode())
        names = {"n": "node", "w": "way", "r": "relation"}
        for i in sorted(rels):
            members, t = self.relations[i]
            body = "".join(f'    <member type="{names[m]}" ref="{r}" role="{escape(role, _Q)}"/>\n'
                           for m, r, role in members)
            out.append(f'  <relation id="{i}">\n{body}{tags(t)}  </relation>\n'.encode())
        return out


_Q = {'"': "&quot;"}
XML_HEAD = (b'<?xml version="1.0" encoding="UTF-8"?>\n'
            b'<osm version="0.6" generator="Overpass API 0.7.61.5 4133829e (fake)">\n'
            b'<note>The data included in this document is from www.openstreetmap.org. '
            b'The data is made available under ODbL.</note>\n'
            b'<meta osm_base="2019-01-01T00:00:00Z"/>\n\n')
XML_TAIL = b"\n</osm>\n"


@lru_cache(maxsize=4)
def load_osm(path: str) -> OsmData:
    return OsmData(Path(path))


class Hgt:
    """An SRTM .hgt tile (N43E007.hgt: lat 43..44, lon 7..8), bilinear, read with numpy only."""

    VOID = -32768

    def __init__(self, path: Path):
        path = Path(path)
        m = re.match(r"([NS])(\d\d)([EW])(\d\d\d)", path.name.upper())
        if not m:
            raise ValueError(f"not an SRTM tile name: {path.name}")
        self.lat0 = int(m.group(2)) * (1 if m.group(1) == "N" else -1)
        self.lon0 = int(m.group(4)) * (1 if m.group(3) == "E" else -1)
        raw = np.fromfile(path, dtype=">i2")
        size = int(round(math.sqrt(raw.size)))
        self.z = raw.reshape(size, size).astype(np.int32)   # first row = northern edge
        self.n = size - 1

    def value(self, lat: float, lon: float) -> float | None:
        r = (self.lat0 + 1 - lat) * self.n
        c = (lon - self.lon0) * self.n
        if not (0 <= r <= self.n and 0 <= c <= self.n):
            return None
        r0, c0 = min(int(r), self.n - 1), min(int(c), self.n - 1)
        u, v = r - r0, c - c0
        q = self.z[r0:r0 + 2, c0:c0 + 2]
        if (q == self.VOID).any():
            return float(self.VOID)
        return float((1 - u) * (1 - v) * q[0, 0] + (1 - u) * v * q[0, 1]
                     + u * (1 - v) * q[1, 0] + u * v * q[1, 1])


# --- server -----------------------------------------------------------------------------------
class FakeServices:
    """The fake Overpass + open-elevation server; use as a context manager (see module doc)."""

    def __init__(self, osm: str | Path | None = PRESET_OSM, hgt: str | Path | None = None, max_batch: int = 100):
        self.osm_path = str(osm) if osm else None
        self.hgt = Hgt(hgt) if hgt else None
        self.max_batch = int(max_batch)
        self._lock = threading.Lock()
        self._scripts: dict[str, deque] = defaultdict(deque)
        self._counts: dict[str, int] = defaultdict(int)
        self.log: list[tuple[str, str]] = []        # (path, action) per request
        self.bodies: list[bytes] = []               # request bodies, in order
        self._stop = threading.Event()
        self._server: ThreadingHTTPServer | None = None
        self._thread: threading.Thread | None = None

    # lifecycle
    def start(self) -> "FakeServices":
        if self.osm_path:
            load_osm(self.osm_path)   # load before serving, so the first request is not slow
        handler = type("Handler", (_Handler,), {"fake": self})
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), handler)
        self._server.daemon_threads = True
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05},
                                        daemon=True, name="fake-services")
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
            self._server = None

    def __enter__(self) -> "FakeServices":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    # endpoints
    @property
    def base(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}"

    def overpass_url(self, name: str = "main") -> str:
        return f"{self.base}/{name}{OVERPASS_PATH}"

    def elevation_url(self, name: str = "main") -> str:
        return f"{self.base}/{name}{ELEVATION_PATH}"

    @staticmethod
    def _path(url_or_path: str) -> str:
        return urlsplit(url_or_path).path if "://" in url_or_path else url_or_path

    def script(self, url: str, actions) -> None:
        """Queue failure actions for an endpoint (consumed one per request)."""
        with self._lock:
            self._scripts[self._path(url)].extend(actions)

    def count(self, url: str | None = None) -> int:
        """Requests received by one endpoint (all endpoints when None)."""
        with self._lock:
            if url is None:
                return sum(self._counts.values())
            return self._counts.get(self._path(url), 0)

    def reset_counts(self) -> None:
        with self._lock:
            self._counts.clear()
            self.log.clear()
            self.bodies.clear()

    def _next_action(self, path: str, body: bytes):
        with self._lock:
            self._counts[path] += 1
            q = self._scripts.get(path)
            action = q.popleft() if q else "ok"
            self.log.append((path, str(action)))
            self.bodies.append(body)
            return action


class _Handler(BaseHTTPRequestHandler):
    fake: FakeServices
    protocol_version = "HTTP/1.0"
    server_version = "FakeOverpass/0.7.61"

    def log_message(self, format, *args):  # keep test output quiet
        pass

    def do_GET(self):
        self._handle(b"")

    def do_POST(self):
        n = int(self.headers.get("Content-Length") or 0)
        self._handle(self.rfile.read(n) if n else b"")

    # --- plumbing
    def _send(self, status: int, body: bytes, ctype: str = "text/plain", headers: dict | None = None,
              length: int | None = None) -> None:
        try:
            self.send_response(status)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body) if length is None else length))
            for k, v in (headers or {}).items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(body)
            self.wfile.flush()
        except OSError:  # the client gave up (timeout test): nothing to do
            pass

    def _handle(self, body: bytes) -> None:
        split = urlsplit(self.path)
        path = split.path
        if path.endswith(OVERPASS_PATH):
            answer = self._overpass
        elif path.endswith(ELEVATION_PATH):
            answer = self._elevation
        else:
            self._send(404, b"not found")
            return
        action = self.fake._next_action(path, body)
        if isinstance(action, tuple) and action[0] == "sleep":
            if self.fake._stop.wait(float(action[1])):
                return
            action = "ok"
        if isinstance(action, int) or (isinstance(action, tuple) and action[0] == "status"):
            code = action if isinstance(action, int) else action[1]
            hdrs = {} if isinstance(action, int) else (action[2] if len(action) > 2 else {})
            msg = self.responses.get(code, ("Error",))[0]
            self._send(code, f"<html><body><h1>{code} {msg}</h1></body></html>".encode(), "text/html", hdrs)
            return
        if action == "drop":
            self.close_connection = True
            return
        if action == "html":
            self._send(200, _BUSY_HTML, "text/html; charset=utf-8")
            return
        if action == "random":
            self._send(200, random.Random(7).randbytes(3000), "application/octet-stream")
            return
        if action == "empty":
            self._send(200, b"", "application/osm3s+xml")
            return
        try:
            status, data, ctype = answer(split.query, body, action)
        except Exception as e:  # a bug in the fake: show it as a 500 with the message
            self._send(500, f"fake server error: {e!r}".encode())
            return
        if action == "truncated" and status == 200:
            data = data[: len(data) // 2]
        if action == "cut" and status == 200:
            self._send(status, data[: len(data) // 2], ctype, length=len(data))
            self.close_connection = True
            return
        self._send(status, data, ctype)

    # --- Overpass
    def _overpass(self, query_string: str, body: bytes, action):
        form = parse_qs(body.decode("utf-8", "replace")) if body else parse_qs(query_string)
        query = (form.get("data") or [""])[0]
        if not query:
            return 400, _overpass_error("line 1: parse error: No input found"), "text/html"
        m = re.search(r"\[bbox:\s*([-\d.]+)\s*,\s*([-\d.]+)\s*,\s*([-\d.]+)\s*,\s*([-\d.]+)\s*\]", query)
        if not m:
            return 400, _overpass_error("this fake needs a global [bbox:S,W,N,E]"), "text/html"
        if re.search(r"\[out:(?!xml)", query):
            return 400, _overpass_error("this fake answers only [out:xml]"), "text/html"
        bbox = tuple(float(x) for x in m.groups())
        if not self.fake.osm_path:
            return 503, _overpass_error("no OSM data loaded"), "text/html"
        data = load_osm(self.fake.osm_path)
        elems = data.to_xml(*data.select(bbox, parse_statements(query)))
        if action == "remark":
            part = b"".join(elems[: len(elems) // 3])
            remark = (b'<remark> runtime error: Query timed out in "recurse" at line 26 after 2 seconds. '
                      b"</remark>\n")
            return 200, XML_HEAD + part + remark + XML_TAIL, "application/osm3s+xml"
        return 200, XML_HEAD + b"".join(elems) + XML_TAIL, "application/osm3s+xml"

    # --- open-elevation
    def _elevation(self, query_string: str, body: bytes, action):
        def err(code, msg):
            return code, json.dumps({"error": msg}).encode(), "application/json"

        try:
            if body:
                locs = json.loads(body)["locations"]
                pts = [(float(p["latitude"]), float(p["longitude"])) for p in locs]
            else:
                text = (parse_qs(query_string).get("locations") or [""])[0]
                pts = [tuple(float(x) for x in p.split(",")) for p in text.split("|") if p]
        except (ValueError, KeyError, TypeError):
            return err(400, "Invalid JSON.")
        if len(pts) > self.fake.max_batch:
            return err(413, f"Too many locations: {len(pts)} > {self.fake.max_batch}")
        if self.fake.hgt is None:
            return err(503, "no DEM loaded")
        results = [{"latitude": la, "longitude": lo, "elevation": self.fake.hgt.value(la, lo)} for la, lo in pts]
        if action == "wrong_count":
            results = results[:-1]
        elif action == "null_elevation":
            results[len(results) // 2]["elevation"] = None
        elif action == "string_elevation":
            results[0]["elevation"] = "n/a"
        elif action == "swapped" and len(results) > 1:
            results[0], results[-1] = results[-1], results[0]
        elif action == "no_results":
            return 200, json.dumps({"error": None}).encode(), "application/json"
        return 200, json.dumps({"results": results}).encode(), "application/json"


_STATEMENT = re.compile(r"\b(node|way|relation|nwr)((?:\s*\[\s*\"[^\"]+\"\s*(?:[=~]\s*\"[^\"]*\"\s*)?\])+)\s*;")
_FILTER = re.compile(r"\[\s*\"([^\"]+)\"\s*(?:([=~])\s*\"([^\"]*)\"\s*)?\]")


def parse_statements(query: str) -> list[tuple[str, list[tuple[str, str | None, str | None]]]]:
    """The tag-filter statements of an Overpass QL query: ``way["railway"~"^tram$"];`` ->
    ("way", [("railway", "~", "^tram$")]). Other syntax (areas, around, ids) is ignored."""
    return [(typ, [(k, op or None, v if op else None) for k, op, v in _FILTER.findall(filters)])
            for typ, filters in _STATEMENT.findall(query)]


def _overpass_error(msg: str) -> bytes:
    return _BUSY_HTML.replace(
        b"runtime error: open64: 0 Success /osm3s_v0.7.61_osm_base Dispatcher_Client::request_read_and_idx::timeout. "
        b"The server is probably too busy to handle your request.", msg.encode())
