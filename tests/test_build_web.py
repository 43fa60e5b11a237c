"""`cosim build` against web services: a real HTTP server on 127.0.0.1 standing in for
Overpass (data cut from real extracts) and open-elevation (answers from a real SRTM tile)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from netgen.build import build_world
from netgen.config import WorldConfig
from tests.conftest import shared_file
from tests.fake_services import FakeServices, closed_port_url

CLI = [sys.executable, "-m", "cosim"]


def _cli(args, cwd, cache):
    env = dict(os.environ, COSIM_CACHE=str(cache))
    return subprocess.run(CLI + args, cwd=cwd, capture_output=True, text=True, timeout=600, env=env)


def test_bbox_build_from_overpass_then_offline_from_cache(tmp_path):
    with FakeServices() as fs:
        url = fs.overpass_url()
        cfg = WorldConfig(bbox=(60.166, 24.936, 60.174, 24.948), chunks=0, flat=True, flat_elevation_m=5,
                          overpass_urls=[url], out=str(tmp_path / "w"), cache_dir=str(tmp_path / "c"))
        w = build_world(cfg)
        assert fs.count(url) == 1
        assert w["counts"]["road_edges"] > 100 and w["counts"]["buildings"] > 20
        assert w["sources"]["osm"]["kind"] == "overpass"
    # the server is gone: a rebuild (even forced) needs no network
    cfg2 = WorldConfig(bbox=(60.166, 24.936, 60.174, 24.948), chunks=0, flat=True, flat_elevation_m=5,
                       overpass_urls=[closed_port_url()], out=str(tmp_path / "w2"), cache_dir=str(tmp_path / "c"))
    w2 = build_world(cfg2, force=True)
    assert w2["counts"]["road_edges"] == w["counts"]["road_edges"]


def test_open_elevation_build(tmp_path):
    hgt = shared_file("dem/N43E007.hgt")
    osm = shared_file("osm/monaco-2022.osm.pbf")
    with FakeServices(osm=osm, hgt=hgt, max_batch=100) as fs:
        cfg = WorldConfig(osm=str(osm), center=(43.7384, 7.4246), chunks=0, elevation_url=fs.elevation_url(),
                          out=str(tmp_path / "w"), cache_dir=str(tmp_path / "c"))
        w = build_world(cfg)
        assert w["sources"]["elevation"]["kind"] == "open-elevation"
        assert fs.count(fs.elevation_url()) > 1                   # batched
        assert w["terrain"]["z_range_m"][1] - w["terrain"]["z_range_m"][0] > 50


def test_sea_bbox_has_no_roads(tmp_path):
    # a bbox in the Gulf of Finland, south of the Helsinki extract: Overpass answers no data
    with FakeServices() as fs:
        r = _cli(["build", "--bbox", "60.100,24.900,60.105,24.910", "--flat", "--chunks", "0",
                  "--overpass-url", fs.overpass_url(), "--out", "w"], tmp_path, tmp_path / "c")
    assert r.returncode == 2, r.stderr
    assert r.stderr.startswith("error: ") and "no" in r.stderr and "road" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "w" / "world.json").exists()


@pytest.mark.parametrize("failure", [503, "html", "remark", "random"])
def test_overpass_down_or_garbage_is_one_line(tmp_path, failure):
    with FakeServices() as fs:
        url = fs.overpass_url()
        fs.script(url, [failure] * 10)
        r = subprocess.run(CLI + ["build", "--bbox", "60.166,24.936,60.174,24.948", "--flat", "--chunks", "0",
                                  "--overpass-url", url, "--timeout", "5", "--out", "w"],
                           cwd=tmp_path, capture_output=True, text=True, timeout=300,
                           env=dict(os.environ, COSIM_CACHE=str(tmp_path / "c")))
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: Overpass"), r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "w" / "world.json").exists()
