"""Download the OSM data of a bbox from the Overpass API, as a cached OSM XML file.

:func:`fetch_osm` returns the path of an ``.osm`` file (OSM XML, elements sorted by type
and id, every referenced node and way included) that netconvert and pyosmium both read.
It asks the configured Overpass servers in order (retries, backoff and failover in
:mod:`netgen._http`) and caches the answer under ``<cache>/overpass/`` keyed by the query
without the server URL or the timeout, so the same bbox is downloaded once.

The query (``S,W,N,E`` is the bbox, ``T`` the server-side timeout in whole seconds)::

    [out:xml][timeout:T][bbox:S,W,N,E];
    (
      way["highway"];
      node["highway"];
      node["crossing"];
      way["railway"~"^(tram|light_rail)$"];
      node["railway"~"^(level_crossing|crossing|tram_level_crossing|tram_stop)$"];
      way["building"];
      relation["building"]["type"="multipolygon"];
      way["building:part"];
      relation["building:part"]["type"="multipolygon"];
      node["natural"="tree"];
      way["natural"];
      relation["natural"]["type"="multipolygon"];
      way["landuse"];
      relation["landuse"]["type"="multipolygon"];
      way["leisure"];
      relation["leisure"]["type"="multipolygon"];
      node["amenity"="bench"];
      node["barrier"];
      way["barrier"];
      way["waterway"];
      relation["type"="restriction"];
    );
    (._;>;);
    out body;

That is: every road, footway and path with the point features on them (signals, stop and
give-way signs, crossings, street lamps, ...), tram tracks, buildings and building parts,
trees, tree rows, woods, water, land use, parks, benches, barriers, waterways, the
multipolygon relations of those areas and the turn restrictions netconvert uses; ``(._;>;)``
adds every node and way they reference, also outside the bbox, so no way is cut.
``out body`` (not ``qt``) keeps the output sorted by id, as OSM files normally are.

An answer is accepted only if it is a complete OSM XML document: an ``<osm>`` root, no
Overpass ``<remark>`` (``runtime error: Query timed out ...``, ``out of memory``, which
Overpass sends with HTTP 200 after a partial result), not an HTML page, and pyosmium
parses it to the end (a truncated document fails). A document with no elements is valid:
the area is empty, and the caller reports that there are no roads.
"""
from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Sequence

import osmium

from ._http import DEFAULT_BACKOFF_BASE_S, DEFAULT_MAX_WAIT_S, Garbage, fetch
from .errors import InputError
from .frame import check_latlon

SERVICE = "Overpass API"
NAMESPACE = "overpass"
MAX_AREA_KM2 = 2500.0   # 50 km x 50 km: past that, use a local extract (--osm)

DEFAULT_URLS = [
    "https://overpass-api.de/api/interpreter",
    "https://overpass.kumi.systems/api/interpreter",
    "https://maps.mail.ru/osm/tools/overpass/api/interpreter",
]

_SELECTION = """(
  way["highway"];
  node["highway"];
  node["crossing"];
  way["railway"~"^(tram|light_rail)$"];
  node["railway"~"^(level_crossing|crossing|tram_level_crossing|tram_stop)$"];
  way["building"];
  relation["building"]["type"="multipolygon"];
  way["building:part"];
  relation["building:part"]["type"="multipolygon"];
  node["natural"="tree"];
  way["natural"];
  relation["natural"]["type"="multipolygon"];
  way["landuse"];
  relation["landuse"]["type"="multipolygon"];
  way["leisure"];
  relation["leisure"]["type"="multipolygon"];
  node["amenity"="bench"];
  node["barrier"];
  way["barrier"];
  way["waterway"];
  relation["type"="restriction"];
);
(._;>;);
out body;"""


def check_bbox(bbox) -> tuple[float, float, float, float]:
    """Validate an (S, W, N, E) bbox for an Overpass query and return it as floats."""
    try:
        s, w, n, e = bbox
    except (TypeError, ValueError):
        raise InputError(f"bbox: expected (S, W, N, E), got {bbox!r}")
    s, w = check_latlon(s, w, "bbox south-west corner")
    n, e = check_latlon(n, e, "bbox north-east corner")
    if not (s < n and w < e):
        raise InputError(f"bbox: need S < N and W < E, got {s},{w},{n},{e}")
    km_lat = (n - s) * 111.32
    km_lon = (e - w) * 111.32 * math.cos(math.radians(0.5 * (s + n)))
    if km_lat * km_lon > MAX_AREA_KM2:
        raise InputError(f"bbox {s},{w},{n},{e} is {km_lat:.0f} x {km_lon:.0f} km: too large for the "
                         f"Overpass API (at most {MAX_AREA_KM2:.0f} km2); use a local extract with --osm")
    return s, w, n, e


def _bbox_text(bbox) -> str:
    return ",".join(f"{v:.7f}" for v in bbox)


def overpass_query(bbox, timeout_s: float = 60.0) -> str:
    """The Overpass QL query for a bbox (see the module docstring)."""
    s, w, n, e = check_bbox(bbox)
    t = max(1, int(math.ceil(float(timeout_s))))
    return f"[out:xml][timeout:{t}][bbox:{_bbox_text((s, w, n, e))}];\n{_SELECTION}\n"


def cache_key(bbox) -> str:
    """The cache key of a bbox's answer: the query without the timeout (nor any server URL)."""
    return f"overpass-osm-xml v1 [bbox:{_bbox_text(check_bbox(bbox))}];\n{_SELECTION}\n"


_HEAD_OSM = re.compile(rb"^\s*(?:<\?xml[^>]*\?>\s*)?(?:<!--.*?-->\s*)*<osm[\s>]", re.S)
_REMARK = re.compile(rb"<remark[^>]*>(.*?)(?:</remark>|$)", re.S)


def _text_of_html(body: bytes) -> str:
    """The message of an HTML error page (Overpass puts it after <strong>Error</strong>:)."""
    text = body[:16000].decode("utf-8", "replace")
    m = re.search(r"(?is)<strong[^>]*>\s*Error\s*</strong>\s*:?(.*?)(?:</p>|$)", text)
    if not m:
        m = re.search(r"(?is)<body[^>]*>(.*)", text)
    text = re.sub(r"(?is)<(script|style)\b.*?</\1>", " ", m.group(1) if m else text)
    text = " ".join(re.sub(r"<[^>]*>", " ", text).split())
    return (text[:117] + "...") if len(text) > 120 else (text or "no message")


class _Parse(osmium.SimpleHandler):
    """Parses the whole document (libosmium does the work; one trivial callback)."""

    def relation(self, r):  # noqa: D401 - present so that pyosmium reads the data
        pass


def validate_osm_xml(body: bytes) -> None:
    """Raise :class:`Garbage` unless ``body`` is a complete OSM XML document without errors."""
    if not body or not body.strip():
        raise Garbage("an empty answer")
    head = body[:4096].lstrip()
    low = head[:1024].lower()
    if b"<!doctype html" in low or b"<html" in low:
        raise Garbage(f"an HTML page instead of OSM XML: {_text_of_html(body)}")
    if head.startswith(b"{") or head.startswith(b"["):
        try:
            remark = json.loads(body).get("remark")
        except (ValueError, AttributeError):
            remark = None
        raise Garbage(f"Overpass remark: {' '.join(str(remark).split())}" if remark
                      else "JSON instead of OSM XML")
    if not _HEAD_OSM.match(head):
        raise Garbage(f"not OSM XML (starts with {head[:40]!r})")
    m = _REMARK.search(body)
    if m:
        remark = " ".join(m.group(1).decode("utf-8", "replace").split())
        raise Garbage(f"Overpass remark: {remark or 'empty remark'}")
    try:
        _Parse().apply_buffer(body, "osm")
    except Exception as e:  # pyosmium raises RuntimeError on XML errors; be broad about it
        raise Garbage(f"incomplete or invalid OSM XML ({e})")


def fetch_osm(bbox, urls: Sequence[str] | None = None, cache_dir: str | os.PathLike | None = None,
              timeout_s: float = 60.0, retries: int = 3, *,
              backoff_base_s: float = DEFAULT_BACKOFF_BASE_S,
              max_wait_s: float = DEFAULT_MAX_WAIT_S) -> Path:
    """Path of a cached ``.osm`` file with the OSM data of ``bbox = (S, W, N, E)``.

    Raises InputError for a bad bbox, ServiceError when no server gave a valid answer,
    BuildError when the cache cannot be written.
    """
    bbox = check_bbox(bbox)
    if cache_dir is None:
        from .config import default_cache_dir
        cache_dir = default_cache_dir()
    query = overpass_query(bbox, timeout_s)
    got = fetch(SERVICE, list(urls) if urls else DEFAULT_URLS, key=cache_key(bbox),
                cache_dir=cache_dir, namespace=NAMESPACE, suffix=".osm",
                method="POST", data={"data": query}, validate=validate_osm_xml,
                timeout_s=timeout_s, retries=retries,
                backoff_base_s=backoff_base_s, max_wait_s=max_wait_s)
    return got.path


def fetch_osm_for(cfg, bbox) -> Path:
    """:func:`fetch_osm` with the web-service settings of a :class:`netgen.config.WorldConfig`."""
    return fetch_osm(bbox, cfg.overpass_urls, cfg.cache_path, cfg.http_timeout_s, cfg.http_retries)
