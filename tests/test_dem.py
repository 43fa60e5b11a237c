"""DEM reader tests on real SRTM tiles and USGS NED GeoTIFFs (../shared/data/dem).

Derived files (a neighbouring tile, a knocked-out void, a PixelIsPoint or projected copy)
are written to tmp_path from the real rasters; nothing from ../shared is copied into the
project.
"""
from __future__ import annotations

import zipfile

import numpy as np
import pytest
import tifffile

from netgen.dem import Elevation, FlatElevation, fill_voids, open_dem
from netgen.errors import CosimError, DataError
from tests.conftest import shared_file

N49 = "dem/N49E011.hgt.zip"
N43 = "dem/N43E007.hgt"
PDX = "dem/portland-ned.tif"
PDX_NODATA = "dem/portland-ned-nodata.tif"

# Portland GeoTIFF grid (from its ModelTiepoint / ModelPixelScale; PixelIsArea)
PDX_W, PDX_N = -122.71, 45.55
PDX_SX, PDX_SY = 9.259259259259062e-05, 9.259259259258513e-05


def raw_hgt(path) -> np.ndarray:
    """The tile's int16 samples, read independently of netgen.dem."""
    if str(path).endswith(".zip"):
        with zipfile.ZipFile(path) as zf:
            data = zf.read([n for n in zf.namelist() if n.endswith(".hgt")][0])
        return np.frombuffer(data, ">i2").reshape(1201, 1201)
    return np.fromfile(path, ">i2").reshape(1201, 1201)


def write_hgt(path, arr: np.ndarray) -> None:
    np.asarray(arr, dtype=">i2").tofile(path)


def one_line(e: BaseException) -> str:
    msg = str(e)
    assert msg and "\n" not in msg
    return msg


def pdx_centre(r, c):
    """(lon, lat) of the centre of pixel (r, c) of the Portland GeoTIFFs."""
    return PDX_W + (np.asarray(c) + 0.5) * PDX_SX, PDX_N - (np.asarray(r) + 0.5) * PDX_SY


def write_geotiff(path, data, tiepoint, scale, geokeys, nodata=None):
    """A GeoTIFF with the given tags (GeoKeyDirectory as a list of (key, value) shorts)."""
    keys = [1, 1, 0, len(geokeys)]
    for k, v in geokeys:
        keys += [k, 0, 1, v]
    tags = [(33550, "d", 3, tuple(scale), False), (33922, "d", 6, tuple(tiepoint), False),
            (34735, "H", len(keys), tuple(keys), False)]
    if nodata is not None:
        tags.append((42113, "s", 0, str(nodata), False))
    tifffile.imwrite(path, data, extratags=tags)


# --------------------------------------------------------------------------------------------
# SRTM HGT
# --------------------------------------------------------------------------------------------

def test_reference_values_n49e011():
    dem = open_dem([shared_file(N49)])
    z = dem.sample([11.574869, 11.558647, 11.57517], [49.968651, 49.958233, 49.949784])
    assert z == pytest.approx([458.6, 329.8, 337.8], abs=0.1)
    info = dem.info()
    assert info["kind"] == "dem" and info["format"] == "srtm-hgt"
    assert info["files"] == ["N49E011.hgt.zip"]
    assert info["datum"] == "EGM96 geoid (SRTM)"
    assert "public domain" in info["licence"]
    assert info["resolution_arcsec"] == [3.0]


def test_sample_at_grid_points_returns_raw_samples():
    """HGT row 0 is the northern edge and the grid includes both edges."""
    path = shared_file(N49)
    raw = raw_hgt(path)
    dem = open_dem([path])
    rng = np.random.default_rng(1)
    r = rng.integers(0, 1201, 500)
    c = rng.integers(0, 1201, 500)
    ok = raw[r, c] != -32768
    z = dem.sample(11 + c / 1200, 50 - r / 1200)
    np.testing.assert_allclose(z[ok], raw[r, c][ok], atol=1e-6)
    # the four corners of the tile, exactly on its edges
    corners = dem.sample([11.0, 12.0, 11.0, 12.0], [50.0, 50.0, 49.0, 49.0])
    np.testing.assert_allclose(corners, [raw[0, 0], raw[0, -1], raw[-1, 0], raw[-1, -1]])
    # half-way between two samples is their mean (bilinear, not nearest)
    mid = dem.sample(11 + 600.5 / 1200, 50 - 300 / 1200)
    assert mid == pytest.approx((float(raw[300, 600]) + float(raw[300, 601])) / 2)


def test_hgt_and_zip_agree(tmp_path):
    zpath = shared_file(N49)
    with zipfile.ZipFile(zpath) as zf:
        (tmp_path / "N49E011.hgt").write_bytes(zf.read("N49E011.hgt"))
    a = open_dem([zpath])
    b = open_dem([tmp_path / "N49E011.hgt"])
    rng = np.random.default_rng(2)
    lon, lat = 11 + rng.random(20000), 49 + rng.random(20000)
    np.testing.assert_array_equal(a.sample(lon, lat), b.sample(lon, lat))
    assert a.info()["voids_filled"] == b.info()["voids_filled"] == 20
    assert b.info()["files"] == ["N49E011.hgt"]


def test_mosaic_of_four_tiles_is_seamless(tmp_path):
    """Neighbours derived from the real tile by mirroring it about its east / north edge.

    A tile's first column mirrored is the original's last column, so the east neighbour
    shares the original's edge samples exactly (as real SRTM neighbours do), and the
    mosaic is mirror-symmetric about lon 12 and lat 50: any seam error breaks the symmetry.
    """
    zpath = shared_file(N49)
    raw = raw_hgt(zpath)
    write_hgt(tmp_path / "N49E012.hgt", raw[:, ::-1])
    write_hgt(tmp_path / "N50E011.hgt", raw[::-1, :])
    write_hgt(tmp_path / "N50E012.hgt", raw[::-1, ::-1])
    single = open_dem([zpath])
    mosaic = open_dem([zpath, tmp_path / "N49E012.hgt", tmp_path / "N50E011.hgt", tmp_path / "N50E012.hgt"])
    mosaic.check_covers(49.5, 11.5, 50.5, 12.5)

    rng = np.random.default_rng(3)
    lat = 49 + rng.random(5000)
    d = rng.random(5000) * 0.02
    d[:50] = np.linspace(0, 1 / 1200, 50)  # within the cells touching the seam
    east, west = mosaic.sample(12 + d, lat), mosaic.sample(12 - d, lat)
    np.testing.assert_allclose(east, west, atol=1e-6)
    # on the seam the mosaic equals the original tile's edge
    np.testing.assert_allclose(mosaic.sample(np.full(500, 12.0), lat[:500]),
                               single.sample(np.full(500, 12.0), lat[:500]), atol=1e-9)
    # west of the seam it is the original tile
    np.testing.assert_array_equal(mosaic.sample(12 - d, lat), single.sample(12 - d, lat))

    lon = 11 + rng.random(5000)
    north, south = mosaic.sample(lon, 50 + d), mosaic.sample(lon, 50 - d)
    np.testing.assert_allclose(north, south, atol=1e-6)
    # diagonal neighbour, near the four-tile corner
    np.testing.assert_allclose(mosaic.sample(12 + d[:200], 50 + d[::-1][:200]),
                               mosaic.sample(12 - d[:200], 50 - d[::-1][:200]), atol=1e-6)

    # a profile crossing the seam has no step there: its largest jump between neighbouring
    # points (spacing << one cell) at the seam is no bigger than elsewhere on the profile
    lons = np.linspace(11.95, 12.05, 4001)
    prof = mosaic.sample(lons, np.full(lons.size, 49.4321))
    jumps = np.abs(np.diff(prof))
    seam = np.abs(lons[:-1] - 12) < 2 / 1200
    assert jumps[seam].max() <= jumps.max() + 1e-9
    assert jumps.max() < 5.0  # ~2.5e-5 deg steps: metres of relief per step would be a bug

    # each mirrored tile carries the original's 20 voids; sampling all four reads them all
    mosaic.sample([11.5, 12.5, 11.5, 12.5], [49.5, 49.5, 50.5, 50.5])
    info = mosaic.info()
    assert info["voids_filled"] == 80
    assert sorted(info["rasters_read"]) == ["N49E011.hgt.zip", "N49E012.hgt", "N50E011.hgt", "N50E012.hgt"]


def test_monaco_plausible_and_voids_counted():
    path = shared_file(N43)
    raw = raw_hgt(path)
    void = raw == -32768
    assert void.sum() == 4  # independently of netgen.dem
    dem = open_dem([path])
    assert dem.info()["voids_filled"] == 0  # nothing read yet: lazy
    z = float(dem.sample(7.4246, 43.7384))  # Monaco-Ville, the rock above the port
    assert 20.0 < z < 100.0
    assert dem.info()["voids_filled"] == 4
    # filled cells are finite and within their valid neighbourhood's range (no overshoot)
    for r, c in np.argwhere(void):
        filled = float(dem.sample(7 + c / 1200, 44 - r / 1200))
        nb = raw[max(r - 1, 0):r + 2, max(c - 1, 0):c + 2]
        nb = nb[nb != -32768]
        assert np.isfinite(filled)
        assert nb.min() - 1e-6 <= filled <= nb.max() + 1e-6


def test_void_fill_accuracy_on_knocked_out_real_data(tmp_path):
    """Blank out blocks of the real tile, fill them, compare with the real values."""
    path = shared_file(N43)
    raw = raw_hgt(path).copy()
    truth = raw.astype(float)
    blocks = [(200, 820, 10), (150, 100, 40), (100, 300, 180)]  # 100, 1600, 32400 cells (land)
    for r, c, s in blocks:
        assert (raw[r - 1:r + s + 1, c - 1:c + s + 1] != -32768).all()
        raw[r:r + s, c:c + s] = -32768
    write_hgt(tmp_path / "N43E007.hgt", raw)
    dem = open_dem([tmp_path / "N43E007.hgt"])
    dem.check_covers(43.5, 7.2, 43.9, 7.6)
    assert dem.info()["voids_filled"] == 4 + sum(s * s for _, _, s in blocks)
    filled = dem.grids[0].load()
    for r, c, s in blocks:
        blk = (slice(r, r + s), slice(c, c + s))
        ring = truth[r - 1:r + s + 1, c - 1:c + s + 1].copy()
        ring[1:-1, 1:-1] = np.nan
        f, t = filled[blk].astype(float), truth[blk]
        assert np.isfinite(f).all()
        # maximum principle: within the range of the valid cells around the void
        assert np.nanmin(ring) - 1e-3 <= f.min() and f.max() <= np.nanmax(ring) + 1e-3
        # clearly better than filling with the mean of the surrounding valid cells (these are
        # steep Alpine slopes with valleys crossing the blocks, which no boundary-only
        # interpolation reproduces; measured ratios are 0.64..0.74)
        rms = np.sqrt(np.mean((f - t) ** 2))
        rms_mean_fill = np.sqrt(np.mean((np.nanmean(ring) - t) ** 2))
        assert rms < 0.85 * rms_mean_fill, (s, rms, rms_mean_fill)
        # continuous with the data: cells next to the boundary are off by about one
        # neighbour-to-neighbour step of the real terrain (a mean fill is off by 100s of m)
        edge = np.concatenate([f[0] - t[0], f[-1] - t[-1], f[:, 0] - t[:, 0], f[:, -1] - t[:, -1]])
        step = np.abs(np.diff(truth[r - 1:r + s + 1, c - 1:c + s + 1], axis=1)).mean()
        assert np.median(np.abs(edge)) < 1.6 * step, (s, np.median(np.abs(edge)), step)


def test_multigrid_cascade_close_to_exact_harmonic_fill():
    """The large-void path (cascade) against an exact sparse solve of the same problem."""
    raw = raw_hgt(shared_file(N49)).astype(np.float32)
    void = np.zeros(raw.shape, bool)
    void[700:900, 300:520] = True  # 44000 cells: beyond the default direct-solve size
    void |= raw == -32768
    a, b = raw.copy(), raw.copy()
    a[void] = np.nan
    b[void] = np.nan
    assert fill_voids(a, void) == fill_voids(b, void, direct_max=10 ** 6) == void.sum()
    blk = (slice(700, 900), slice(300, 520))
    diff = np.abs(a[blk].astype(float) - b[blk])
    relief = float(raw[blk].max() - raw[blk].min())
    # measured: mean 0.19 m, max 3.3 m (1.3 % of the 253 m relief); without the relaxation
    # sweeps at each level the max is 9.4 m
    assert diff.mean() < 0.5 and diff.max() < 0.02 * relief, (diff.mean(), diff.max(), relief)


def test_all_void_tile_is_an_error(tmp_path):
    write_hgt(tmp_path / "N10E010.hgt", np.full((1201, 1201), -32768))
    dem = open_dem([tmp_path / "N10E010.hgt"])
    with pytest.raises(DataError) as ei:
        dem.sample(10.5, 10.5)
    msg = one_line(ei.value)
    assert "N10E010.hgt" in msg and "no valid elevation" in msg


def test_bbox_inside_a_void_has_no_valid_data(tmp_path):
    raw = raw_hgt(shared_file(N43)).copy()
    raw[100:400, 100:400] = -32768
    write_hgt(tmp_path / "N43E007.hgt", raw)
    dem = open_dem([tmp_path / "N43E007.hgt"])
    # rows 100..399 are lat 44 - r/1200; columns 100..399 lon 7 + c/1200
    with pytest.raises(DataError) as ei:
        dem.check_covers(44 - 350 / 1200, 7 + 150 / 1200, 44 - 150 / 1200, 7 + 350 / 1200)
    assert "no valid elevation data" in one_line(ei.value)
    dem.check_covers(44 - 350 / 1200, 7 + 150 / 1200, 44 - 50 / 1200, 7 + 350 / 1200)  # reaches data


# --------------------------------------------------------------------------------------------
# GeoTIFF
# --------------------------------------------------------------------------------------------

def test_portland_geotiff_pixel_centres_and_orientation():
    path = shared_file(PDX)
    raw = tifffile.imread(path).astype(float)
    dem = open_dem([path])
    info = dem.info()
    assert info["format"] == "geotiff" and info["files"] == ["portland-ned.tif"]
    assert info["datum"] == "NAVD88 (NED)" and info["voids_filled"] == 0

    # PixelIsArea: the value of pixel (r, c) is the sample at the pixel's centre
    rc = np.array([(0, 0), (20, 5), (20, 858), (640, 5), (640, 858), (647, 863), (324, 432), (551, 18)])
    lon, lat = pdx_centre(rc[:, 0], rc[:, 1])
    np.testing.assert_allclose(dem.sample(lon, lat), raw[rc[:, 0], rc[:, 1]], atol=1e-3)
    # half-way between two vertically adjacent pixel centres is their mean; at the corner
    # shared by four pixels, the mean of the four
    lon, lat = pdx_centre(300.5, 400)
    assert float(dem.sample(lon, lat)) == pytest.approx((raw[300, 400] + raw[301, 400]) / 2, abs=1e-3)
    lon, lat = pdx_centre(300.5, 400.5)
    assert float(dem.sample(lon, lat)) == pytest.approx(raw[300:302, 400:402].mean(), abs=1e-3)

    # north/south and east/west orientation against geography: Council Crest
    # (45.4986 N, 122.7078 W, 327 m) is the highest point of the area; the Willamette runs
    # through the middle at a few metres above sea level.
    assert float(dem.sample(-122.7078, 45.4986)) > 315.0
    r, c = np.unravel_index(np.argmax(raw), raw.shape)
    lon, lat = pdx_centre(r, c)
    assert abs(lat - 45.4986) < 0.002 and abs(lon - -122.7078) < 0.002
    # the same column mirrored north-south is low ground (a flipped reader would find it here)
    assert float(dem.sample(-122.7078, 45.49 + 45.55 - 45.4986)) < 60.0
    assert float(dem.sample(-122.6700, 45.5120)) < 15.0  # the river near the Hawthorne Bridge


def test_portland_nodata_voids_filled_near_truth():
    full_path, nd_path = shared_file(PDX), shared_file(PDX_NODATA)
    full = tifffile.imread(full_path).astype(float)
    nd = tifffile.imread(nd_path)
    void = nd == -999999
    n_void = int(void.sum())
    assert n_void > 0
    dem = open_dem([nd_path])
    ref = open_dem([full_path])
    dem.check_covers(45.49, -122.71, 45.55, -122.63)
    info = dem.info()
    assert info["voids_filled"] == n_void

    rows, cols = np.nonzero(void)
    lon, lat = pdx_centre(rows, cols)
    z = dem.sample(lon, lat)
    assert np.isfinite(z).all() and z.min() > -50 and z.max() < 400
    # rows of data that are not void stay exactly as they were
    ok_rows = np.nonzero(~void.any(axis=1))[0]
    lon, lat = pdx_centre(ok_rows[1:, None], np.arange(0, 864, 7)[None, :])
    np.testing.assert_allclose(dem.sample(lon, lat), ref.sample(lon, lat), atol=1e-9)

    # next to the boundary of the nodata area the filled values are close to the real ones
    dist = _distance_to_valid(void)
    for d_max, med_tol in ((1, 1.0), (3, 2.0)):
        m = void & (dist <= d_max)
        err = np.abs(dem.sample(*pdx_centre(*np.nonzero(m))) - full[m])
        assert np.median(err) < med_tol, (d_max, np.median(err))
        assert np.percentile(err, 95) < 4 * med_tol, (d_max, np.percentile(err, 95))


def _distance_to_valid(void: np.ndarray) -> np.ndarray:
    from scipy import ndimage
    return ndimage.distance_transform_cdt(void, metric="taxicab")


def test_pixel_is_point_geotiff_same_georeferencing(tmp_path):
    """The Portland raster re-tagged as PixelIsPoint with the tiepoint moved to the centre
    of pixel (0, 0) describes the same samples: values must agree; its coverage is half a
    pixel smaller on each side."""
    src = shared_file(PDX)
    data = tifffile.imread(src)
    tie = (0, 0, 0, PDX_W + PDX_SX / 2, PDX_N - PDX_SY / 2, 0)
    keys = [(1024, 2), (1025, 2), (2048, 4269), (2054, 9102)]
    write_geotiff(tmp_path / "pdx-point.tif", data, tie, (PDX_SX, PDX_SY, 0), keys)
    area, point = open_dem([src]), open_dem([tmp_path / "pdx-point.tif"])
    rng = np.random.default_rng(5)
    lon = PDX_W + PDX_SX + rng.random(20000) * (0.08 - 2 * PDX_SX)
    lat = PDX_N - PDX_SY - rng.random(20000) * (0.06 - 2 * PDX_SY)
    np.testing.assert_allclose(point.sample(lon, lat), area.sample(lon, lat), atol=1e-4)
    area.check_covers(45.49, -122.71, 45.55, -122.63)
    with pytest.raises(DataError):
        point.check_covers(45.49, -122.71, 45.55, -122.63)
    point.check_covers(45.49 + PDX_SY / 2, -122.71 + PDX_SX / 2, 45.55 - PDX_SY / 2, -122.63 - PDX_SX / 2)
    assert point.info()["datum"] == "NAVD88 (NED)"


def test_south_up_geotiff(tmp_path):
    """The raster stored upside down (first row = southern edge, negative y pixel size)."""
    src = shared_file(PDX)
    data = tifffile.imread(src)
    keys = [(1024, 2), (1025, 1), (2048, 4269)]
    write_geotiff(tmp_path / "south-up.tif", data[::-1], (0, 0, 0, PDX_W, 45.49, 0),
                  (PDX_SX, -PDX_SY, 0), keys)
    flipped, ref = open_dem([tmp_path / "south-up.tif"]), open_dem([src])
    rng = np.random.default_rng(8)
    lon = -122.709 + rng.random(20000) * 0.078
    lat = 45.491 + rng.random(20000) * 0.058
    np.testing.assert_allclose(flipped.sample(lon, lat), ref.sample(lon, lat), atol=1e-3)
    flipped.check_covers(45.49, -122.71, 45.55, -122.63)


def test_geotiff_wgs84_tagged_and_feet(tmp_path):
    """The same raster tagged EPSG:4326 with vertical unit feet: heights are converted."""
    data = tifffile.imread(shared_file(PDX))
    tie = (0, 0, 0, PDX_W, PDX_N, 0)
    keys = [(1024, 2), (1025, 1), (2048, 4326), (4099, 9002)]
    write_geotiff(tmp_path / "pdx-ft.tif", data, tie, (PDX_SX, PDX_SY, 0), keys)
    ft, m = open_dem([tmp_path / "pdx-ft.tif"]), open_dem([shared_file(PDX)])
    pts = ([-122.70, -122.66, -122.64], [45.50, 45.52, 45.54])
    np.testing.assert_allclose(ft.sample(*pts), m.sample(*pts) * 0.3048, rtol=1e-6)
    assert "unknown" in ft.info()["datum"]  # no vertical datum key and not NED's NAD83


def test_two_geotiffs_side_by_side(tmp_path):
    """West and east halves of the real raster, overlapping by one column, as a mosaic."""
    src = shared_file(PDX)
    data = tifffile.imread(src)
    keys = [(1024, 2), (1025, 1), (2048, 4269)]
    write_geotiff(tmp_path / "w.tif", data[:, :433], (0, 0, 0, PDX_W, PDX_N, 0), (PDX_SX, PDX_SY, 0), keys)
    write_geotiff(tmp_path / "e.tif", data[:, 432:], (0, 0, 0, PDX_W + 432 * PDX_SX, PDX_N, 0),
                  (PDX_SX, PDX_SY, 0), keys)
    both, ref = open_dem([tmp_path / "w.tif", tmp_path / "e.tif"]), open_dem([src])
    both.check_covers(45.49, -122.71, 45.55, -122.63)
    rng = np.random.default_rng(6)
    lon = -122.70 + rng.random(20000) * 0.06
    lat = 45.50 + rng.random(20000) * 0.04
    np.testing.assert_allclose(both.sample(lon, lat), ref.sample(lon, lat), atol=1e-4)
    assert both.info()["files"] == ["w.tif", "e.tif"]


# --------------------------------------------------------------------------------------------
# errors
# --------------------------------------------------------------------------------------------

def test_missing_tiles_named():
    dem = open_dem([shared_file(N49)])
    with pytest.raises(DataError) as ei:
        dem.check_covers(60.1, 24.9, 60.2, 25.1)
    msg = one_line(ei.value)
    assert "missing tiles N60E024.hgt (lat 60..61, lon 24..25)" in msg
    assert "N60E025.hgt (lat 60..61, lon 25..26)" in msg
    # partly covered: only the missing neighbour is named
    with pytest.raises(DataError) as ei:
        dem.check_covers(49.9, 11.9, 50.1, 12.1)
    msg = one_line(ei.value)
    assert "N50E011.hgt" in msg and "N49E012.hgt" in msg and "N50E012.hgt" in msg
    assert "N49E011" not in msg.split("[")[0].replace("missing tiles", "")
    dem.check_covers(49.0, 11.0, 50.0, 12.0)  # exactly the tile


def test_sample_outside_coverage_raises():
    dem = open_dem([shared_file(N49)])
    with pytest.raises(DataError) as ei:
        dem.sample([11.5, 24.95], [49.5, 60.17])
    msg = one_line(ei.value)
    assert "N60E024.hgt" in msg and "1 of 2" in msg
    with pytest.raises(DataError):
        dem.sample(11.5, 50.0001)
    with pytest.raises(DataError):
        dem.sample([11.5, np.nan], [49.5, 49.5])
    assert dem.sample(np.zeros((0,)), np.zeros((0,))).shape == (0,)
    z = dem.sample(np.full((3, 4), 11.5), np.full((3, 4), 49.5))
    assert z.shape == (3, 4) and np.isfinite(z).all()


def test_geotiff_not_covering():
    dem = open_dem([shared_file(PDX)])
    with pytest.raises(DataError) as ei:
        dem.check_covers(45.50, -122.80, 45.52, -122.70)
    msg = one_line(ei.value)
    assert "portland-ned.tif covers lat 45.49..45.55, lon -122.71..-122.63" in msg
    assert "lon -122.8..-122.7" in msg
    with pytest.raises(DataError) as ei:
        dem.sample(-122.75, 45.51)
    assert "portland-ned.tif" in one_line(ei.value)


def test_geotiff_nodata_bbox_without_valid_data():
    dem = open_dem([shared_file(PDX_NODATA)])
    nd = tifffile.imread(shared_file(PDX_NODATA))
    void_rows = np.nonzero((nd == -999999).all(axis=1))[0]
    assert void_rows.size > 10
    # a bbox well inside the rows that are entirely nodata
    lat_hi = PDX_N - (void_rows[0] + 2) * PDX_SY
    lat_lo = PDX_N - (void_rows[-1] - 3) * PDX_SY
    with pytest.raises(DataError) as ei:
        dem.check_covers(lat_lo, -122.70, lat_hi, -122.64)
    msg = one_line(ei.value)
    assert "no valid elevation data" in msg and "portland-ned-nodata.tif" in msg


def test_corrupt_files(tmp_path):
    rng = np.random.default_rng(7)
    garbage = rng.integers(0, 256, 5000, dtype=np.uint8).tobytes()
    for name in ("N49E011.hgt", "N49E011.hgt.zip", "dem.tif", "dem.tiff"):
        p = tmp_path / name
        p.write_bytes(garbage)
        with pytest.raises(DataError) as ei:
            open_dem([p])
        assert name in one_line(ei.value)
    # right size for a tile, but noise: caught when the tile is read
    p = tmp_path / "N10E010.hgt"
    p.write_bytes(rng.integers(0, 256, 2 * 1201 * 1201, dtype=np.uint8).tobytes())
    dem = open_dem([p])
    with pytest.raises(DataError) as ei:
        dem.sample(10.5, 10.5)
    assert "N10E010.hgt" in one_line(ei.value)
    # a real GeoTIFF cut short
    src = shared_file(PDX).read_bytes()
    p = tmp_path / "cut.tif"
    p.write_bytes(src[: len(src) // 2])
    with pytest.raises(DataError) as ei:
        dem = open_dem([p])
        dem.sample(-122.67, 45.52)
    assert "cut.tif" in one_line(ei.value)
    # a plain TIFF without georeferencing
    p = tmp_path / "plain.tif"
    tifffile.imwrite(p, np.zeros((10, 10), np.float32))
    with pytest.raises(DataError) as ei:
        open_dem([p])
    assert "plain.tif" in one_line(ei.value)


def test_projected_geotiff_rejected(tmp_path):
    data = tifffile.imread(shared_file(PDX))
    # UTM zone 10N (EPSG:32610), 10 m pixels at Portland's position
    keys = [(1024, 1), (1025, 1), (3072, 32610)]
    write_geotiff(tmp_path / "utm.tif", data, (0, 0, 0, 522000.0, 5044000.0, 0), (10.0, 10.0, 0), keys)
    with pytest.raises(DataError) as ei:
        open_dem([tmp_path / "utm.tif"])
    msg = one_line(ei.value)
    assert "utm.tif" in msg and "projected" in msg and "EPSG:32610" in msg


def test_other_open_errors(tmp_path):
    with pytest.raises(DataError):
        open_dem([])
    with pytest.raises(DataError) as ei:
        open_dem([tmp_path / "N00E000.hgt"])
    assert "not found" in one_line(ei.value)
    p = tmp_path / "dem.xyz"
    p.write_bytes(b"1 2 3\n")
    with pytest.raises(DataError) as ei:
        open_dem([p])
    assert "dem.xyz" in one_line(ei.value)
    p = tmp_path / "tile.hgt"  # no corner in the name
    p.write_bytes(b"\0" * (2 * 1201 * 1201))
    with pytest.raises(DataError) as ei:
        open_dem([p])
    assert "tile.hgt" in one_line(ei.value)
    # the same tile twice, and HGT mixed with GeoTIFF
    zpath = shared_file(N49)
    with zipfile.ZipFile(zpath) as zf:
        (tmp_path / "N49E011.hgt").write_bytes(zf.read("N49E011.hgt"))
    with pytest.raises(DataError) as ei:
        open_dem([zpath, tmp_path / "N49E011.hgt"])
    assert "twice" in one_line(ei.value)
    with pytest.raises(DataError) as ei:
        open_dem([zpath, shared_file(PDX)])
    assert "mix" in one_line(ei.value)
    assert issubclass(DataError, CosimError)


def test_interface_and_flat():
    flat = FlatElevation(12.5)
    assert isinstance(flat, Elevation)
    np.testing.assert_array_equal(flat.sample([1.0, 2.0], [3.0, 4.0]), [12.5, 12.5])
    assert flat.info()["voids_filled"] == 0
    dem = open_dem([shared_file(N43)])
    assert isinstance(dem, Elevation)
    assert {"kind", "files", "voids_filled", "format", "datum", "licence"} <= set(dem.info())
