"""open-elevation client: lattice, batching, cache, bilinear sampling and bad answers.

The server is a real HTTP server on 127.0.0.1 (tests/fake_services.py) answering from the
SRTM tile ../shared/data/dem/N43E007.hgt (Monaco); reference values are computed here with
numpy straight from that file.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from conftest import shared_file
from fake_services import FakeServices, closed_port_url
from netgen.errors import DataError, InputError, ServiceError
from netgen.open_elevation import OpenElevation

HGT = "dem/N43E007.hgt"
BBOX = (43.7300, 7.4150, 43.7350, 7.4200)     # Monaco: S, W, N, E
FAST = dict(backoff_base_s=0.01, max_wait_s=0.05)


@pytest.fixture
def hgt():
    return shared_file(HGT)


@pytest.fixture
def fake(hgt):
    with FakeServices(osm=None, hgt=hgt, max_batch=100) as fs:
        yield fs


def hgt_bilinear(path, lat, lon):
    """Reference: bilinear on the 1201 x 1201 SRTM grid (first row north, both edges included)."""
    z = np.fromfile(path, dtype=">i2").reshape(1201, 1201).astype(float)
    y = (44.0 - np.asarray(lat, dtype=float)) * 1200.0
    x = (np.asarray(lon, dtype=float) - 7.0) * 1200.0
    r, c = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = y - r, x - c
    assert (z[r, c] > -1000).all() and (z[r + 1, c + 1] > -1000).all(), "reference hit a void"
    return (z[r, c] * (1 - fy) * (1 - fx) + z[r, c + 1] * (1 - fy) * fx
            + z[r + 1, c] * fy * (1 - fx) + z[r + 1, c + 1] * fy * fx)


def cache_files(tmp_path):
    d = tmp_path / "open-elevation"
    return sorted(d.iterdir()) if d.exists() else []


def make(fake, tmp_path, **kw):
    kw = {"cache_dir": tmp_path, "retries": 0, **FAST, **kw}
    return OpenElevation(kw.pop("url", fake.elevation_url()), **kw)


@pytest.mark.parametrize("batch", [37, 100])
def test_lattice_is_fetched_in_batches_with_the_dem_values(fake, tmp_path, hgt, batch):
    oe = make(fake, tmp_path, batch_size=batch).prepare(*BBOX)
    s, w, n, e = BBOX
    lats, lons = oe.lats, oe.lons
    # a 1 arc-second lattice on the global grid that covers the bbox
    assert lats[0] <= s and lats[-1] >= n and lons[0] <= w and lons[-1] >= e
    assert np.allclose(lats * 3600, np.round(lats * 3600), atol=1e-3)
    assert np.allclose(np.diff(lats), 1 / 3600, atol=1e-6) and np.allclose(np.diff(lons), 1 / 3600, atol=1e-6)
    npts = lats.size * lons.size
    assert npts > 300
    assert fake.count() == math.ceil(npts / batch)
    sent = [json.loads(b)["locations"] for b in fake.bodies]
    assert all(len(x) <= batch for x in sent) and sum(len(x) for x in sent) == npts
    info = oe.info()
    assert info["kind"] == "open-elevation" and info["url"] == fake.elevation_url()
    assert (info["points"], info["requests"], info["cached"], info["voids_filled"]) == (
        npts, math.ceil(npts / batch), 0, 0)
    # the values are the DEM's, at the lattice points, in the right places
    glat, glon = np.meshgrid(lats, lons, indexing="ij")
    ref = hgt_bilinear(hgt, glat, glon)
    assert np.allclose(oe.grid, ref, atol=1e-6)
    assert np.allclose(oe.sample(glon, glat), ref, atol=1e-6)
    assert 0 < ref.min() and ref.max() < 300 and ref.std() > 5    # Monaco: steep, above the sea


def test_sample_interpolates_bilinearly_between_lattice_points(fake, tmp_path, hgt):
    oe = make(fake, tmp_path).prepare(*BBOX)
    lats, lons, g = oe.lats, oe.lons, oe.grid
    # the centre of a cell is the mean of its corners
    i, j = 5, 7
    c = oe.sample((lons[j] + lons[j + 1]) / 2, (lats[i] + lats[i + 1]) / 2)
    assert c.shape == ()
    assert c == pytest.approx(g[i:i + 2, j:j + 2].mean(), abs=1e-6)
    # anywhere: what an independent bilinear interpolator says; shape follows the input
    rng = np.random.default_rng(3)
    lat = rng.uniform(BBOX[0], BBOX[2], size=(20, 30))
    lon = rng.uniform(BBOX[1], BBOX[3], size=(20, 30))
    z = oe.sample(lon, lat)
    assert z.shape == (20, 30)
    ref = RegularGridInterpolator((lats, lons), g, method="linear")(np.stack([lat, lon], axis=-1))
    assert np.allclose(z, ref, atol=1e-6)
    # and it stays close to the DEM itself (1" lattice on a 3" DEM: bilinear of bilinear)
    assert np.abs(z - hgt_bilinear(hgt, lat, lon)).max() < 5.0


def test_second_prepare_comes_from_the_cache(fake, tmp_path):
    first = make(fake, tmp_path).prepare(*BBOX)
    n = fake.count()
    assert len(cache_files(tmp_path)) == n
    # a new client, another server URL: the batches are keyed by their points, not the URL
    again = make(fake, tmp_path, url=fake.elevation_url("other")).prepare(*BBOX)
    assert fake.count() == n
    assert again.info()["cached"] == n and again.info()["requests"] == 0
    assert np.array_equal(again.grid, first.grid)


def test_a_damaged_cached_batch_is_fetched_again(fake, tmp_path):
    first = make(fake, tmp_path).prepare(*BBOX)
    n = fake.count()
    victim = cache_files(tmp_path)[1]
    good = victim.read_bytes()
    victim.write_bytes(good[: len(good) // 2])
    again = make(fake, tmp_path).prepare(*BBOX)
    assert fake.count() == n + 1
    assert (again.info()["requests"], again.info()["cached"]) == (1, n - 1)
    assert victim.read_bytes() == good
    assert np.array_equal(again.grid, first.grid)


def test_batch_over_the_server_limit_is_a_service_error(fake, tmp_path):
    with pytest.raises(ServiceError, match="HTTP 413") as ei:
        make(fake, tmp_path, batch_size=150, retries=3).prepare(*BBOX)
    assert "\n" not in str(ei.value) and str(ei.value).startswith("open-elevation")
    assert fake.count() == 1        # the same request would get the same answer: not retried
    assert cache_files(tmp_path) == []


@pytest.mark.parametrize("action, says", [
    ("wrong_count", "99 results for 100 locations"),
    ("null_elevation", "no numeric elevation (None)"),
    ("string_elevation", "no numeric elevation ('n/a')"),
    ("swapped", "not the requested"),
    ("no_results", "without a 'results' list"),
    ("html", "not JSON"),
    ("random", "not JSON"),
    ("truncated", "not JSON"),
    ("empty", "not JSON"),
])
def test_bad_answers_are_retried_then_a_service_error(fake, tmp_path, action, says):
    url = fake.elevation_url()
    fake.script(url, [action, action])
    with pytest.raises(ServiceError) as ei:
        make(fake, tmp_path, retries=1).prepare(*BBOX)
    msg = str(ei.value)
    assert "\n" not in msg and msg.startswith("open-elevation failed after 2 attempts")
    assert "answered garbage" in msg and says in msg and url in msg
    assert fake.count() == 2
    assert cache_files(tmp_path) == []
    # once bad, then good: the client recovers and caches only good answers
    fake.reset_counts()
    fake.script(url, [action])
    oe = make(fake, tmp_path, retries=1).prepare(*BBOX)
    batches = math.ceil(oe.grid.size / 100)
    assert fake.count() == batches + 1
    assert len(cache_files(tmp_path)) == batches


def test_server_errors_and_timeouts_are_retried(fake, tmp_path):
    url = fake.elevation_url()
    fake.script(url, [("status", 503, {"Retry-After": "0"}), ("sleep", 2), 502])
    oe = make(fake, tmp_path, retries=3, timeout_s=0.5).prepare(*BBOX)
    batches = math.ceil(oe.grid.size / 100)
    assert fake.count() == batches + 3
    assert oe.info()["attempts"] == batches + 3


def test_failover_to_the_second_server(fake, tmp_path, hgt):
    down, b = closed_port_url("/api/v1/lookup"), fake.elevation_url("b")
    oe = make(fake, tmp_path, url=[down, b], retries=2).prepare(*BBOX)
    assert fake.count(b) == math.ceil(oe.grid.size / 100)
    glat, glon = np.meshgrid(oe.lats, oe.lons, indexing="ij")
    assert np.allclose(oe.grid, hgt_bilinear(hgt, glat, glon), atol=1e-6)


def test_no_server_is_a_one_line_service_error(tmp_path):
    down = closed_port_url("/api/v1/lookup")
    with pytest.raises(ServiceError) as ei:
        OpenElevation(down, cache_dir=tmp_path, retries=1, **FAST).prepare(*BBOX)
    msg = str(ei.value)
    assert msg == f"open-elevation failed after 2 attempts: connection refused (tried {down})"


def test_outside_the_prepared_area_is_a_data_error(fake, tmp_path):
    oe = make(fake, tmp_path)
    with pytest.raises(DataError, match="prepare"):
        oe.sample(7.416, 43.731)
    oe.prepare(*BBOX)
    oe.check_covers(43.731, 7.416, 43.734, 7.419)
    with pytest.raises(DataError, match="outside the fetched area"):
        oe.check_covers(43.731, 7.416, 43.740, 7.419)
    with pytest.raises(DataError, match="1 point"):
        oe.sample([7.416, 7.416], [43.731, 43.760])
    assert np.isfinite(oe.sample([7.416, 7.4195], [43.731, 43.7349])).all()


def test_check_covers_fetches_on_first_use(fake, tmp_path):
    oe = make(fake, tmp_path)
    assert fake.count() == 0
    oe.check_covers(*BBOX)
    assert fake.count() > 0 and oe.info()["points"] == oe.grid.size


def test_voids_in_the_servers_dem_are_filled(fake, tmp_path, hgt):
    # N43E007 has voids (-32768) at row 405, columns 251..253: lat 43.6625, lon 7.209..7.211
    oe = make(fake, tmp_path).prepare(43.6610, 7.2070, 43.6640, 7.2130)
    info = oe.info()
    assert info["voids_filled"] > 0
    assert np.isfinite(oe.grid).all()
    lo, hi = info["elevation_range_m"]
    assert -100 < lo and hi < 1000


@pytest.mark.parametrize("kw", [{"spacing_arcsec": 0}, {"batch_size": 0}, {"spacing_arcsec": "x"}])
def test_bad_settings_are_input_errors(kw, tmp_path):
    with pytest.raises(InputError):
        OpenElevation("http://127.0.0.1:9/api/v1/lookup", cache_dir=tmp_path, **kw)
