"""Overpass download: query, validation, retries, failover and the on-disk cache.

Every test talks to a real HTTP server on 127.0.0.1 (tests/fake_services.py) that serves
OSM XML cut from the embedded Helsinki preset, with failures scripted per endpoint.
"""
from __future__ import annotations

import logging
import re
import resource
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import osmium
import pytest
import requests

from fake_services import PRESET_OSM, FakeServices, closed_port_url
from netgen._http import Garbage, cache_file
from netgen.errors import BuildError, InputError, ServiceError
from netgen.overpass import cache_key, check_bbox, fetch_osm, overpass_query, validate_osm_xml

BBOX = (60.1680, 24.9400, 60.1720, 24.9470)      # central Helsinki, inside the preset extract
FAST = dict(backoff_base_s=0.01, max_wait_s=0.05)


@pytest.fixture
def fake():
    with FakeServices(osm=PRESET_OSM) as fs:
        yield fs


def read_osm(path):
    """nodes {id: (lat, lon, tags)}, ways {id: (refs, tags)}, relations {id: (members, tags)}."""
    nodes, ways, rels = {}, {}, {}
    for o in osmium.FileProcessor(str(path)):
        tags = {t.k: t.v for t in o.tags}
        if o.is_node():
            nodes[o.id] = (round(o.location.lat, 7), round(o.location.lon, 7), tags)
        elif o.is_way():
            ways[o.id] = ([n.ref for n in o.nodes], tags)
        else:
            rels[o.id] = ([(m.type, m.ref) for m in o.members], tags)
    return nodes, ways, rels


def cache_entries(cache_dir) -> list[Path]:
    d = Path(cache_dir) / "overpass"
    return sorted(d.iterdir()) if d.exists() else []


# --- query ----------------------------------------------------------------------------------
def test_query_asks_for_roads_buildings_and_scenery_in_the_bbox():
    q = overpass_query(BBOX, timeout_s=25)
    assert q.startswith("[out:xml][timeout:25][bbox:60.1680000,24.9400000,60.1720000,24.9470000];")
    for part in ('way["highway"];', 'node["highway"];', 'way["building"];', 'node["natural"="tree"];',
                 'way["railway"~"^(tram|light_rail)$"];', 'way["landuse"];', 'way["leisure"];',
                 'node["amenity"="bench"];', 'relation["landuse"]["type"="multipolygon"];',
                 "(._;>;);", "out body;"):
        assert part in q
    # the cache key is the request without the timeout (and never a server URL)
    assert cache_key(BBOX) == cache_key(tuple(BBOX))
    assert "timeout" not in cache_key(BBOX)
    assert overpass_query(BBOX, 60) != q


@pytest.mark.parametrize("bbox, word", [
    ((95.0, 24.9, 96.0, 25.0), "latitude"),
    ((60.2, 24.9, 60.1, 25.0), "S < N"),
    ((60.1, 190.0, 60.2, 191.0), "longitude"),
    ((40.0, 0.0, 50.0, 10.0), "too large"),
    (("a", 24.9, 60.2, 25.0), "number"),
])
def test_bad_bbox_is_an_input_error(bbox, word, tmp_path):
    with pytest.raises(InputError, match=re.escape(word)):
        fetch_osm(bbox, ["http://127.0.0.1:9/api/interpreter"], tmp_path)
    assert not (tmp_path / "overpass").exists()


# --- success path ---------------------------------------------------------------------------
def test_fetch_returns_osm_xml_with_the_bbox_content(fake, tmp_path):
    path = fetch_osm(BBOX, [fake.overpass_url()], tmp_path, timeout_s=10, retries=0, **FAST)
    assert path.suffix == ".osm" and path.parent == tmp_path / "overpass"
    assert fake.count() == 1
    # the request was an Overpass form POST carrying our query
    assert fake.bodies[0].startswith(b"data=")
    assert b"bbox%3A60.1680000%2C24.9400000" in fake.bodies[0]

    nodes, ways, rels = read_osm(path)
    src_nodes, src_ways, _ = read_osm(PRESET_OSM)
    s, w, n, e = BBOX
    inside = {i for i, (la, lo, _) in src_nodes.items() if s <= la <= n and w <= lo <= e}
    src_ways = {i: (set(refs), t) for i, (refs, t) in src_ways.items()}
    expected_roads = {i for i, (refs, t) in src_ways.items() if "highway" in t and inside & refs}
    expected_buildings = {i for i, (refs, t) in src_ways.items() if "building" in t and inside & refs}
    got_roads = {i for i, (_, t) in ways.items() if "highway" in t}
    assert len(expected_roads) > 50
    assert expected_roads <= got_roads
    # the only other roads are members of the relations in the answer (turn restrictions)
    members = {ref for mem, _ in rels.values() for typ, ref in mem if typ == "w"}
    assert got_roads - expected_roads <= members
    assert any(t.get("type") == "restriction" for _, t in rels.values())
    assert expected_buildings and expected_buildings <= set(ways)
    # every referenced node is there, at the source's position (no way is cut at the bbox edge)
    for wid in got_roads:
        for ref in ways[wid][0]:
            if ref in src_nodes:
                assert nodes[ref][:2] == src_nodes[ref][:2]
    outside_ref = [r for wid in got_roads for r in ways[wid][0] if r in src_nodes and r not in inside]
    assert outside_ref, "roads crossing the bbox edge keep their outside nodes"
    signals = {i for i in inside if src_nodes[i][2].get("highway") == "traffic_signals"}
    trees = {i for i in inside if src_nodes[i][2].get("natural") == "tree"}
    assert signals and signals <= set(nodes)
    assert trees and trees <= set(nodes)
    # a road entirely outside the bbox is not there
    far = [i for i, (refs, t) in src_ways.items() if "highway" in t and not inside & refs and i not in members]
    assert far and not set(far[:50]) & set(ways)


def test_netconvert_reads_the_downloaded_file(fake, tmp_path):
    exe = Path(sys.executable).with_name("netconvert")
    exe = str(exe) if exe.exists() else shutil.which("netconvert")
    if not exe:
        pytest.skip("netconvert (eclipse-sumo) is not installed")
    path = fetch_osm(BBOX, [fake.overpass_url()], tmp_path / "cache", timeout_s=10, retries=0, **FAST)
    out = tmp_path / "t.net.xml"
    r = subprocess.run([exe, "--osm-files", str(path), "-o", str(out), "--no-warnings"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert out.read_text().count("<edge ") > 50


def test_empty_area_is_a_valid_answer(fake, tmp_path):
    path = fetch_osm((60.100, 24.800, 60.101, 24.801), [fake.overpass_url()], tmp_path, retries=0, **FAST)
    assert read_osm(path) == ({}, {}, {})
    assert b"<osm" in path.read_bytes()


def test_fake_overpass_answers_get_too(fake):
    q = overpass_query(BBOX, 10)
    r_get = requests.get(fake.overpass_url(), params={"data": q}, timeout=10)
    r_post = requests.post(fake.overpass_url(), data={"data": q}, timeout=10)
    assert r_get.status_code == r_post.status_code == 200
    assert r_get.content == r_post.content
    validate_osm_xml(r_get.content)


# --- cache ----------------------------------------------------------------------------------
def test_second_fetch_comes_from_the_cache(fake, tmp_path):
    p1 = fetch_osm(BBOX, [fake.overpass_url("a")], tmp_path, timeout_s=10, retries=0, **FAST)
    body = p1.read_bytes()
    # another timeout, another server: same request, so the cached answer is reused
    p2 = fetch_osm(BBOX, [fake.overpass_url("b")], tmp_path, timeout_s=30, retries=0, **FAST)
    assert p2 == p1 and p2.read_bytes() == body
    assert fake.count(fake.overpass_url("a")) == 1
    assert fake.count(fake.overpass_url("b")) == 0
    assert p1 == cache_file(tmp_path, "overpass", cache_key(BBOX), ".osm")
    # a different bbox is a different entry
    fetch_osm((60.1690, 24.9400, 60.1720, 24.9470), [fake.overpass_url("b")], tmp_path, retries=0, **FAST)
    assert fake.count(fake.overpass_url("b")) == 1
    assert len(cache_entries(tmp_path)) == 2


@pytest.mark.parametrize("damage", ["half", "html", "empty"])
def test_damaged_cache_file_is_not_trusted(fake, tmp_path, damage):
    good = fetch_osm(BBOX, [fake.overpass_url()], tmp_path / "ref", retries=0, **FAST).read_bytes()
    path = cache_file(tmp_path / "c", "overpass", cache_key(BBOX), ".osm")
    path.parent.mkdir(parents=True)
    # what a build killed while writing without the atomic rename would have left
    path.write_bytes({"half": good[: len(good) // 2], "html": b"<html><body>oops</body></html>",
                      "empty": b""}[damage])
    fake.reset_counts()
    got = fetch_osm(BBOX, [fake.overpass_url()], tmp_path / "c", retries=0, **FAST)
    assert got == path
    assert fake.count() == 1
    assert path.read_bytes() == good


def test_cache_write_failure_is_a_one_line_build_error(fake, tmp_path):
    # a file-size limit makes the cache write fail the way a full disk does (EFBIG vs ENOSPC)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    old = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (20000, hard))
    try:
        with pytest.raises(BuildError) as ei:
            fetch_osm(BBOX, [fake.overpass_url()], tmp_path, retries=0, **FAST)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, old)
    msg = str(ei.value)
    assert "\n" not in msg and "cannot write cache file" in msg and "File too large" in msg
    assert cache_entries(tmp_path) == []    # neither the entry nor a temp file is left


# --- retries and failover -------------------------------------------------------------------
def test_failover_when_the_first_server_is_down(fake, tmp_path, caplog):
    down = closed_port_url()
    caplog.set_level(logging.WARNING, logger="netgen.http")
    path = fetch_osm(BBOX, [down, fake.overpass_url("b")], tmp_path, retries=2, **FAST)
    assert read_osm(path)[1]
    assert fake.count(fake.overpass_url("b")) == 1
    assert any("connection refused" in r.getMessage() and down in r.getMessage() for r in caplog.records)


def test_failover_when_the_first_server_keeps_failing(fake, tmp_path):
    a, b = fake.overpass_url("a"), fake.overpass_url("b")
    fake.script(a, [500, 502, 504])
    fetch_osm(BBOX, [a, b], tmp_path, retries=2, **FAST)
    assert fake.count(a) == 3            # 1 + 2 retries
    assert fake.count(b) == 1


def test_retry_after_429_is_honoured_then_success(fake, tmp_path, caplog):
    url = fake.overpass_url()
    fake.script(url, [("status", 429, {"Retry-After": "1"})])
    caplog.set_level(logging.WARNING, logger="netgen.http")
    fetch_osm(BBOX, [url], tmp_path, retries=2, backoff_base_s=0.01, max_wait_s=5)
    assert fake.count(url) == 2
    waits = [r.args[-1] for r in caplog.records if "retry" in r.msg]
    assert waits == [1.0]                 # the server's Retry-After, not the 0.01 s backoff


def test_retry_after_is_capped(fake, tmp_path, caplog):
    url = fake.overpass_url()
    fake.script(url, [("status", 503, {"Retry-After": "3600"}), ("status", 429, {"Retry-After": "3600"})])
    caplog.set_level(logging.WARNING, logger="netgen.http")
    fetch_osm(BBOX, [url], tmp_path, retries=2, backoff_base_s=0.01, max_wait_s=0.2)
    assert fake.count(url) == 3
    assert [r.args[-1] for r in caplog.records if "retry" in r.msg] == [0.2, 0.2]


def test_timeout_is_retried(fake, tmp_path):
    url = fake.overpass_url()
    fake.script(url, [("sleep", 3)])
    path = fetch_osm(BBOX, [url], tmp_path, timeout_s=0.5, retries=1, **FAST)
    assert fake.count(url) == 2 and read_osm(path)[1]


def test_timeouts_everywhere_give_a_service_error(fake, tmp_path):
    url = fake.overpass_url()
    fake.script(url, [("sleep", 3)] * 2)
    with pytest.raises(ServiceError, match=r"timed out after 0\.4 s"):
        fetch_osm(BBOX, [url], tmp_path, timeout_s=0.4, retries=1, **FAST)
    assert fake.count(url) == 2
    assert cache_entries(tmp_path) == []


@pytest.mark.parametrize("action, says", [
    ("remark", "Overpass remark: runtime error: Query timed out"),
    ("html", "an HTML page instead of OSM XML: runtime error: open64"),
    ("random", "answered garbage: not OSM XML"),
    ("truncated", "incomplete or invalid OSM XML"),
    ("empty", "an empty answer"),
    ("cut", "connection broken"),
    ("drop", "connection broken"),
])
def test_garbage_is_rejected_and_not_cached(fake, tmp_path, action, says):
    url = fake.overpass_url()
    fake.script(url, [action])
    with pytest.raises(ServiceError) as ei:
        fetch_osm(BBOX, [url], tmp_path, retries=0, **FAST)
    assert says in str(ei.value)
    assert cache_entries(tmp_path) == []
    # the same garbage once, then a good answer: retried, and only the good answer cached
    fake.script(url, [action])
    path = fetch_osm(BBOX, [url], tmp_path, retries=1, **FAST)
    assert fake.count(url) == 3
    assert cache_entries(tmp_path) == [path]
    validate_osm_xml(path.read_bytes())


def test_all_servers_failing_is_one_line_naming_the_service(fake, tmp_path):
    down, a = closed_port_url(), fake.overpass_url("a")
    fake.script(a, [500] * 10)
    with pytest.raises(ServiceError) as ei:
        fetch_osm(BBOX, [down, a], tmp_path, retries=1, **FAST)
    msg = str(ei.value)
    assert "\n" not in msg
    assert msg.startswith("Overpass API failed")
    assert "HTTP 500 Internal Server Error" in msg and "connection refused" in msg
    assert down in msg and a in msg
    assert fake.count(a) == 2
    assert cache_entries(tmp_path) == []


def test_other_4xx_is_not_retried_on_the_same_server(fake, tmp_path):
    a, b = fake.overpass_url("a"), fake.overpass_url("b")
    fake.script(a, [400])
    fetch_osm(BBOX, [a, b], tmp_path, retries=3, **FAST)
    assert fake.count(a) == 1 and fake.count(b) == 1


# --- validation without HTTP ----------------------------------------------------------------
@pytest.mark.parametrize("body", [
    b'{"version": 0.6, "elements": [], "remark": "runtime error: Query timed out"}',
    b'<?xml version="1.0"?><osm version="0.6"><node id="1" lat="1" lon="2"/>'
    b'<remark> runtime remark: Timeout </remark></osm>',
    b'<?xml version="1.0"?><osm version="0.6"><node id="1" lat="1" lon="2"/>',
    b'<?xml version="1.0"?><gpx version="1.1"></gpx>',
])
def test_validator_rejects(body):
    with pytest.raises(Garbage):
        validate_osm_xml(body)


def test_validator_accepts_empty_osm():
    validate_osm_xml(b'<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="x">\n</osm>\n')
    assert check_bbox(["60.1", "24.9", "60.2", "25"]) == (60.1, 24.9, 60.2, 25.0)
