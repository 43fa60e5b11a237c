"""Elevation sources: SRTM ``.hgt`` / ``.hgt.zip`` tiles and geographic GeoTIFFs.

Every source implements :class:`Elevation`: ``sample(lon, lat)`` returns metres
(bilinear interpolation between the raster's sample points), ``check_covers(s, w, n, e)``
raises :class:`~netgen.errors.DataError` naming what is missing, and ``info()`` describes
the source for ``world.json`` and the build report.

:func:`open_dem` opens a list of DEM files as one seamless source:

* SRTM HGT tiles (``.hgt`` or zipped ``.hgt.zip``): 1 x 1 degree, the file name gives the
  south-west corner (``N49E011``), 1201 x 1201 (3 arc-second) or 3601 x 3601 (1 arc-second)
  big-endian int16 samples, first row = northern edge, the grid includes both edges (so
  neighbouring tiles share their edge rows/columns and a mosaic is seamless), -32768 = void.
* GeoTIFF (``.tif``/``.tiff``) in a geographic CRS on a WGS84/GRS80 ellipsoid (EPSG:4326,
  EPSG:4269 NAD83, ETRS89, ...; all within ~2 m of WGS84, far below DEM accuracy), read with
  ``tifffile``: ModelPixelScale + ModelTiepoint (or a non-rotated ModelTransformation),
  the GeoKeyDirectory (model type, raster type, CRS, vertical units) and GDAL_NODATA.
  For PixelIsArea rasters the value of pixel (r, c) is the sample at the pixel's centre and
  the file covers out to the outer pixel edges (queries in the outer half pixel take the
  edge sample's value); for PixelIsPoint rasters pixel (r, c) *is* the sample at the
  tiepoint-derived position and the file covers exactly its sample span.

Rasters are read lazily (on the first sample / coverage check that needs them) and cached.
Voids (HGT -32768, GeoTIFF nodata or NaN) are filled once per raster when it is read, by
harmonic interpolation: void cells solve the discrete Laplace equation with the valid
neighbours as fixed boundary values and zero gradient at the raster's edges. That is smooth,
continuous with the data around it and never over- or undershoots the surrounding values; at
a raster edge it becomes a smooth extrapolation of the nearest valid data. Void regions of up
to ``_DIRECT_MAX`` cells are solved exactly (sparse direct solve); larger ones by a coarse-to-
fine multigrid cascade (exact solve on a coarse grid, bilinear prolongation, Jacobi
relaxation at every finer level), which is close to the exact solution at a fraction of the
cost.
"""
from __future__ import annotations

import math
import re
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .errors import DataError, InputError

__all__ = ["Elevation", "FlatElevation", "DemElevation", "open_dem", "fill_voids"]

HGT_VOID = -32768
_EPS = 1e-9  # degrees (0.1 mm): coverage tolerance for floating-point noise at extents
_DIRECT_MAX = 20000  # void regions up to this many cells are solved exactly
_LICENCE_PD = "public domain (SRTM/USGS NED)"


class Elevation:
    """Interface of every elevation source.

    ``sample(lon, lat)`` takes arrays of degrees and returns metres above the source's datum,
    bilinearly interpolated; ``check_covers(s, w, n, e)`` raises DataError naming what is
    missing when the source does not cover a bbox; ``info()`` describes the source for
    world.json's ``sources`` and the build report (kind, files, voids_filled, ...).
    """

    name = "elevation"
    voids_filled = 0

    def sample(self, lon, lat) -> np.ndarray:
        raise NotImplementedError

    def check_covers(self, south: float, west: float, north: float, east: float) -> None:
        return None

    def info(self) -> dict:
        return {"kind": self.name, "voids_filled": int(self.voids_filled)}


class FlatElevation(Elevation):
    name = "flat"

    def __init__(self, z: float = 0.0):
        self.z = float(z)

    def sample(self, lon, lat) -> np.ndarray:
        return np.full(np.shape(np.asarray(lon, dtype=float)), self.z)

    def info(self) -> dict:
        return {"kind": "flat", "elevation_m": self.z, "voids_filled": 0}


# --------------------------------------------------------------------------------------------
# void filling
# --------------------------------------------------------------------------------------------

def _harmonic_direct(z: np.ndarray, unknown: np.ndarray) -> None:
    """Solve the discrete Laplace equation for the ``unknown`` cells of ``z`` in place.

    Each unknown cell equals the mean of its 4-neighbours that lie inside the array (so the
    array's edges are zero-gradient). Every 4-connected component of ``unknown`` must touch
    at least one known cell (else the system is singular).
    """
    from scipy import sparse
    from scipy.sparse.linalg import spsolve

    nr, nc = z.shape
    vr, vc = np.nonzero(unknown)
    n = vr.size
    if n == 0:
        return
    flat = vr.astype(np.int64) * nc + vc  # sorted (row-major order from nonzero)
    deg = np.zeros(n)
    b = np.zeros(n)
    rows, cols = [], []
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        rr, cc = vr + dr, vc + dc
        inside = (rr >= 0) & (rr < nr) & (cc >= 0) & (cc < nc)
        deg += inside
        k = np.nonzero(inside)[0]
        rr, cc = rr[k], cc[k]
        nbu = unknown[rr, cc]
        ku = k[nbu]
        j = np.searchsorted(flat, rr[nbu].astype(np.int64) * nc + cc[nbu])
        rows.append(ku)
        cols.append(j)
        kk = k[~nbu]
        np.add.at(b, kk, z[rr[~nbu], cc[~nbu]])
    rows.append(np.arange(n))
    cols.append(np.arange(n))
    vals = np.concatenate([-np.ones(sum(r.size for r in rows[:-1])), deg])
    a = sparse.csc_matrix((vals, (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    z[vr, vc] = spsolve(a, b, permc_spec="MMD_AT_PLUS_A")


def _avg4(z: np.ndarray) -> np.ndarray:
    p = np.pad(z, 1, mode="edge")
    return 0.25 * (p[:-2, 1:-1] + p[2:, 1:-1] + p[1:-1, :-2] + p[1:-1, 2:])


def _upsample_linear(zc: np.ndarray, shape: tuple[int, int], fr: int, fc: int) -> np.ndarray:
    """Bilinear prolongation of a coarse grid (block factors fr, fc) to ``shape``."""

    def axis_weights(n_fine, n_coarse, f):
        x = (np.arange(n_fine) + 0.5) / f - 0.5
        x = np.clip(x, 0, n_coarse - 1)
        i0 = np.minimum(x.astype(np.intp), max(n_coarse - 2, 0))
        i1 = np.minimum(i0 + 1, n_coarse - 1)
        return i0, i1, x - i0

    r0, r1, wr = axis_weights(shape[0], zc.shape[0], fr)
    c0, c1, wc = axis_weights(shape[1], zc.shape[1], fc)
    zr = zc[r0] * (1 - wr)[:, None] + zc[r1] * wr[:, None]
    return zr[:, c0] * (1 - wc) + zr[:, c1] * wc


def _cascade(z: np.ndarray, known: np.ndarray, direct_max: int, sweeps: int = 8) -> np.ndarray:
    """Approximate harmonic fill of ~known cells: coarse exact solve, then refine."""
    unknown = ~known
    nu = int(unknown.sum())
    if nu == 0:
        return z
    nr, nc = z.shape
    if nu <= direct_max or (nr <= 2 and nc <= 2):
        z = z.copy()
        _harmonic_direct(z, unknown)
        return z
    fr, fc = (2 if nr > 2 else 1), (2 if nc > 2 else 1)
    pr, pc = (-nr) % fr, (-nc) % fc
    zz = np.pad(np.where(known, z, 0.0), ((0, pr), (0, pc)))
    kk = np.pad(known, ((0, pr), (0, pc))).astype(np.float64)
    shp = ((nr + pr) // fr, fr, (nc + pc) // fc, fc)
    s = zz.reshape(shp).sum(axis=(1, 3))
    w = kk.reshape(shp).sum(axis=(1, 3))
    kc = w > 0  # a coarse cell is known when any of its fine cells is
    zc = _cascade(np.where(kc, s / np.maximum(w, 1.0), 0.0), kc, direct_max, sweeps)
    out = np.where(known, z, _upsample_linear(zc, z.shape, fr, fc))
    for _ in range(sweeps):
        out = np.where(known, out, _avg4(out))
    return out


def fill_voids(z: np.ndarray, void: np.ndarray, direct_max: int = _DIRECT_MAX) -> int:
    """Fill the ``void`` cells of the 2-D array ``z`` in place by harmonic interpolation.

    Returns the number of cells filled. Raises ValueError when every cell is void.
    Regions (4-connected) of up to ``direct_max`` cells are solved exactly, larger ones by
    the multigrid cascade (see the module docstring).
    """
    from scipy import ndimage

    n_void = int(np.count_nonzero(void))
    if n_void == 0:
        return 0
    if n_void == void.size:
        raise ValueError("every sample is void")
    labels, nlab = ndimage.label(void)
    sizes = np.bincount(labels.ravel(), minlength=nlab + 1)
    small = sizes <= direct_max
    small[0] = False
    small_cells = small[labels]
    if small_cells.any():
        # one block-diagonal sparse system for all small regions (their 4-neighbours are all
        # valid cells, or the raster's edge)
        _harmonic_direct(z, small_cells)
    big = np.nonzero(~small)[0]
    big = big[big > 0]
    if big.size:
        objs = ndimage.find_objects(labels)
        for k in big:
            sr, sc = objs[k - 1]
            sl = (slice(max(sr.start - 1, 0), min(sr.stop + 1, z.shape[0])),
                  slice(max(sc.start - 1, 0), min(sc.stop + 1, z.shape[1])))
            region = labels[sl] == k
            known = ~region
            crop = z[sl].astype(np.float64)
            other = void[sl] & ~small_cells[sl] & ~region  # other big regions: provisional
            if other.any():
                valid = ~void[sl] | small_cells[sl]
                idx = ndimage.distance_transform_edt(~valid, return_distances=False,
                                                     return_indices=True)
                crop[other] = crop[idx[0][other], idx[1][other]]
            crop = _cascade(crop, known, direct_max)
            z[sl][region] = crop[region]
    return n_void


# --------------------------------------------------------------------------------------------
# rasters
# --------------------------------------------------------------------------------------------

def _fmt_deg(x: float) -> str:
    return f"{x:.6f}".rstrip("0").rstrip(".") if abs(x - round(x)) > 1e-12 else str(int(round(x)))


class _Grid:
    """One georeferenced raster of point samples on a regular lon/lat grid (north-up).

    Sample (r, c) lies at lat = lat0 - r * dlat, lon = lon0 + c * dlon. The raster covers
    [south, north] x [west, east] (for PixelIsArea GeoTIFFs half a pixel beyond the samples;
    queries there take the edge sample's value).
    """

    fmt = ""

    def __init__(self, path: Path, label: str, nrows: int, ncols: int, lat0: float, lon0: float,
                 dlat: float, dlon: float, south: float, west: float, north: float, east: float):
        self.path, self.label = path, label
        self.nrows, self.ncols = nrows, ncols
        self.lat0, self.lon0, self.dlat, self.dlon = lat0, lon0, dlat, dlon
        self.south, self.west, self.north, self.east = south, west, north, east
        # the span of the sample points themselves (inside the extent)
        self.s_south, self.s_north = lat0 - (nrows - 1) * dlat, lat0
        self.s_west, self.s_east = lon0, lon0 + (ncols - 1) * dlon
        self._z: np.ndarray | None = None
        self._void: np.ndarray | None = None
        self.voids: int | None = None  # known once loaded
        self.load_seconds = 0.0
        self.fill_seconds = 0.0

    # --- subclasses provide the raw samples (float array, NaN = void) ---
    def _read(self) -> np.ndarray:
        raise NotImplementedError

    @property
    def loaded(self) -> bool:
        return self._z is not None

    def extent_text(self) -> str:
        return (f"lat {_fmt_deg(self.south)}..{_fmt_deg(self.north)}, "
                f"lon {_fmt_deg(self.west)}..{_fmt_deg(self.east)}")

    def load(self) -> np.ndarray:
        if self._z is not None:
            return self._z
        t0 = time.perf_counter()
        z = self._read()
        if z.shape != (self.nrows, self.ncols):
            raise DataError(f"{self.label}: raster is {z.shape[0]} x {z.shape[1]}, "
                            f"expected {self.nrows} x {self.ncols}")
        void = ~np.isfinite(z)
        t1 = time.perf_counter()
        try:
            n = fill_voids(z, void)
        except ValueError:
            raise DataError(f"{self.label}: no valid elevation data at all "
                            f"(all {z.size} samples are voids/nodata)") from None
        self.fill_seconds = time.perf_counter() - t1
        self.load_seconds = t1 - t0
        self.voids = n
        self._void = void if n else None
        self._z = z
        return z

    def contains(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        return ((lat >= self.south - _EPS) & (lat <= self.north + _EPS)
                & (lon >= self.west - _EPS) & (lon <= self.east + _EPS))

    def contains_samples(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        return ((lat >= self.s_south - _EPS) & (lat <= self.s_north + _EPS)
                & (lon >= self.s_west - _EPS) & (lon <= self.s_east + _EPS))

    def contains_box(self, s: float, w: float, n: float, e: float, samples: bool = False) -> bool:
        if samples:
            return (s >= self.s_south - _EPS and n <= self.s_north + _EPS
                    and w >= self.s_west - _EPS and e <= self.s_east + _EPS)
        return (s >= self.south - _EPS and n <= self.north + _EPS
                and w >= self.west - _EPS and e <= self.east + _EPS)

    def intersects_box(self, s: float, w: float, n: float, e: float) -> bool:
        return (s <= self.north + _EPS and n >= self.south - _EPS
                and w <= self.east + _EPS and e >= self.west - _EPS)

    def sample(self, lon: np.ndarray, lat: np.ndarray) -> np.ndarray:
        """Bilinear interpolation at points known to lie inside the raster's extent."""
        z = self.load()
        nr, nc = z.shape
        # fractional row / column of every point (in-place arithmetic: this is the hot loop)
        r = lat - self.lat0
        r *= -1.0 / self.dlat
        c = lon - self.lon0
        c *= 1.0 / self.dlon
        # clamp to the grid (points in the outer half pixel of a PixelIsArea raster, and
        # float noise at edges); stopping a hair short of the last row/column keeps the
        # cell index <= n - 2 without a further pass (weight error 1e-9 of a cell)
        np.clip(r, 0.0, nr - 1 - 1e-9, out=r)
        np.clip(c, 0.0, nc - 1 - 1e-9, out=c)
        r0 = r.astype(np.intp)
        c0 = c.astype(np.intp)
        r -= r0
        c -= c0
        i = r0
        i *= nc
        i += c0
        flat = z.ravel()
        v00 = np.take(flat, i)
        i += 1
        v01 = np.take(flat, i)
        i += nc
        v11 = np.take(flat, i)
        i -= 1
        v10 = np.take(flat, i)
        v01 -= v00
        v11 -= v10
        top = v01 * c
        top += v00
        bot = v11 * c
        bot += v10
        bot -= top
        bot *= r
        bot += top
        return bot

    def index_window(self, s: float, w: float, n: float, e: float) -> tuple[slice, slice]:
        """Rows/columns of the samples that the bbox's interpolation uses."""
        r_lo = math.floor((self.lat0 - min(n, self.north)) / self.dlat + 1e-9)
        r_hi = math.ceil((self.lat0 - max(s, self.south)) / self.dlat - 1e-9)
        c_lo = math.floor((max(w, self.west) - self.lon0) / self.dlon + 1e-9)
        c_hi = math.ceil((min(e, self.east) - self.lon0) / self.dlon - 1e-9)
        r_lo, c_lo = max(r_lo, 0), max(c_lo, 0)
        r_hi, c_hi = min(max(r_hi, r_lo), self.nrows - 1), min(max(c_hi, c_lo), self.ncols - 1)
        return slice(r_lo, r_hi + 1), slice(c_lo, c_hi + 1)

    def valid_count(self, s: float, w: float, n: float, e: float) -> tuple[int, int]:
        """(valid samples, all samples) among those used inside the bbox."""
        self.load()
        rs, cs = self.index_window(s, w, n, e)
        total = (rs.stop - rs.start) * (cs.stop - cs.start)
        if self._void is None:
            return total, total
        return total - int(np.count_nonzero(self._void[rs, cs])), total


_HGT_NAME = re.compile(r"^([NS])(\d{1,2})([EW])(\d{1,3})", re.IGNORECASE)
_HGT_SIZES = {1201: 3.0, 3601: 1.0}  # samples per side -> arc-seconds


def _parse_hgt_name(name: str) -> tuple[int, int] | None:
    m = _HGT_NAME.match(Path(name).name)
    if not m:
        return None
    lat = int(m.group(2)) * (1 if m.group(1).upper() == "N" else -1)
    lon = int(m.group(4)) * (1 if m.group(3).upper() == "E" else -1)
    if not (-90 <= lat < 90 and -180 <= lon < 180):
        return None
    return lat, lon


def hgt_tile_name(lat: int, lon: int) -> str:
    """SRTM tile file name of the 1 x 1 degree tile whose south-west corner is (lat, lon)."""
    return f"{'N' if lat >= 0 else 'S'}{abs(lat):02d}{'E' if lon >= 0 else 'W'}{abs(lon):03d}.hgt"


class _HgtTile(_Grid):
    fmt = "srtm-hgt"

    def __init__(self, path: Path, label: str, lat: int, lon: int, n: int,
                 member: str | None = None):
        step = 1.0 / (n - 1)
        super().__init__(path, label, n, n, lat + 1.0, float(lon), step, step,
                         float(lat), float(lon), lat + 1.0, lon + 1.0)
        self.tile = (lat, lon)
        self.member = member
        self.arcsec = _HGT_SIZES[n]

    def _read(self) -> np.ndarray:
        n = self.nrows
        try:
            if self.member is None:
                raw = np.fromfile(self.path, dtype=">i2")
            else:
                with zipfile.ZipFile(self.path) as zf:
                    raw = np.frombuffer(zf.read(self.member), dtype=">i2")
        except (OSError, zipfile.BadZipFile, zlib.error, EOFError, RuntimeError) as e:
            raise DataError(f"{self.label}: cannot read SRTM tile: {e}") from None
        if raw.size != n * n:
            raise DataError(f"{self.label}: SRTM tile has {raw.size} samples, expected {n} x {n}")
        raw = raw.reshape(n, n)
        void = raw == HGT_VOID
        valid = raw[~void]
        if valid.size and (valid.min() < -1500 or valid.max() > 9000):
            raise DataError(f"{self.label}: implausible elevations {int(valid.min())}..{int(valid.max())} m "
                            "(not a big-endian SRTM .hgt tile?)")
        z = raw.astype(np.float32)
        z[void] = np.nan
        return z


def _open_hgt(path: Path) -> list[_HgtTile]:
    base = path.name
    if base.lower().endswith(".zip"):
        try:
            with zipfile.ZipFile(path) as zf:
                members = [i for i in zf.infolist()
                           if not i.is_dir() and i.filename.lower().endswith(".hgt")]
        except (OSError, zipfile.BadZipFile, zlib.error, EOFError) as e:
            raise DataError(f"{base}: not a readable zip file ({e})") from None
        if not members:
            raise DataError(f"{base}: zip file contains no .hgt tile")
        tiles = []
        for info in members:
            ll = _parse_hgt_name(info.filename)
            if ll is None and len(members) == 1:
                ll = _parse_hgt_name(base)
            if ll is None:
                raise DataError(f"{base}: cannot tell the tile's corner from the name "
                                f"{info.filename!r} (expected e.g. N49E011.hgt)")
            n = _hgt_side(info.file_size, f"{base}:{info.filename}")
            label = base if len(members) == 1 else f"{base}:{Path(info.filename).name}"
            tiles.append(_HgtTile(path, label, ll[0], ll[1], n, member=info.filename))
        return tiles
    ll = _parse_hgt_name(base)
    if ll is None:
        raise DataError(f"{base}: cannot tell the tile's corner from the file name "
                        "(expected e.g. N49E011.hgt)")
    n = _hgt_side(path.stat().st_size, base)
    return [_HgtTile(path, base, ll[0], ll[1], n)]


def _hgt_side(nbytes: int, label: str) -> int:
    for n in _HGT_SIZES:
        if nbytes == 2 * n * n:
            return n
    raise DataError(f"{label}: {nbytes} bytes is not an SRTM tile size "
                    f"(1201 x 1201 or 3601 x 3601 int16 = {2 * 1201 ** 2} or {2 * 3601 ** 2} bytes)")


# --- GeoTIFF -----------------------------------------------------------------------------------

_GEOKEY_NAMES = {1024: "GTModelType", 1025: "GTRasterType", 2048: "GeographicType",
                 2054: "GeogAngularUnits", 2057: "GeogSemiMajorAxis", 2059: "GeogInvFlattening",
                 3072: "ProjectedCSType", 4096: "VerticalCSType", 4099: "VerticalUnits"}
_VERTICAL_UNITS = {9001: 1.0, 9002: 0.3048, 9003: 1200.0 / 3937.0}
_VERTICAL_DATUMS = {5703: "NAVD88", 5773: "EGM96 geoid", 3855: "EGM2008 geoid", 5714: "mean sea level",
                    5783: "DHHN92", 7837: "DHHN2016", 5701: "ODN", 5717: "N60", 3900: "N2000",
                    5720: "NAP"}
_NED_NAD83 = {4269, 4617, 4759, 6318}


def _geokeys(page) -> dict:
    """GeoKeyDirectory as {name: value}, resolving double/ascii parameter references."""
    tags = page.tags
    gkd = tags.get(34735)
    if gkd is None:
        return {}
    d = [int(v) for v in gkd.value]
    doubles = tags.get(34736)
    ascii_ = tags.get(34737)
    out = {}
    for i in range(4, 4 + 4 * d[3], 4):
        key, loc, count, off = d[i:i + 4]
        if loc == 0:
            val = off
        elif loc == 34736 and doubles is not None:
            vals = doubles.value
            val = vals[off] if count == 1 else tuple(vals[off:off + count])
        elif loc == 34737 and ascii_ is not None:
            val = str(ascii_.value)[off:off + count].rstrip("|")
        else:
            val = None
        out[_GEOKEY_NAMES.get(key, key)] = val
    return out


def _wgs84_like_geographic(code) -> bool:
    """True if EPSG `code` is a geographic CRS on the WGS84/GRS80 ellipsoid."""
    try:
        from pyproj import CRS
        crs = CRS.from_epsg(int(code))
        ell = crs.ellipsoid
        return bool(crs.is_geographic and ell is not None and abs(ell.semi_major_metre - 6378137.0) < 1.0
                    and abs(ell.inverse_flattening - 298.257) < 0.01)
    except Exception:
        return False


class _GeoTiff(_Grid):
    fmt = "geotiff"

    def __init__(self, path: Path, label: str, page_shape, geo: dict, nodata, z_scale: float,
                 datum: str, licence: str, flip_rows: bool, flip_cols: bool, grid_args: tuple):
        super().__init__(path, label, *page_shape, *grid_args)
        self.geo, self.nodata, self.z_scale = geo, nodata, z_scale
        self.datum, self.licence = datum, licence
        self.flip_rows, self.flip_cols = flip_rows, flip_cols
        self.arcsec = round(abs(self.dlon) * 3600.0, 4)

    def _read(self) -> np.ndarray:
        import tifffile
        try:
            with tifffile.TiffFile(self.path) as tif:
                a = tif.pages[0].asarray()
        except Exception as e:  # tifffile raises many types for broken/unsupported data
            raise DataError(f"{self.label}: cannot decode GeoTIFF raster data: "
                            f"{type(e).__name__}: {e}") from None
        if a.ndim != 2:
            a = np.squeeze(a)
        if a.ndim != 2:
            raise DataError(f"{self.label}: expected a single-band raster, got shape {a.shape}")
        z = a.astype(np.float64 if a.dtype.itemsize > 4 else np.float32)
        if self.nodata is not None:
            nd = self.nodata
            if math.isnan(nd):
                pass  # NaN samples are voids anyway
            elif np.issubdtype(a.dtype, np.integer):
                info = np.iinfo(a.dtype)
                if nd == int(nd) and info.min <= nd <= info.max:
                    z[a == int(nd)] = np.nan
            else:
                z[a == np.asarray(nd, dtype=a.dtype)] = np.nan
        if self.z_scale != 1.0:
            z *= self.z_scale
        if self.flip_rows:
            z = z[::-1]
        if self.flip_cols:
            z = z[:, ::-1]
        return np.ascontiguousarray(z)


def _open_geotiff(path: Path) -> _GeoTiff:
    import tifffile

    base = path.name
    try:
        with tifffile.TiffFile(path) as tif:
            if not tif.pages:
                raise DataError(f"{base}: TIFF file has no images")
            page = tif.pages[0]
            tags = page.tags
            shape = page.shape
            spp = page.samplesperpixel
            geo = _geokeys(page)
            scale = tags.get(33550)
            tie = tags.get(33922)
            trans = tags.get(34264)
            nodata_tag = tags.get(42113)
            scale = tuple(float(v) for v in scale.value) if scale is not None else None
            tie = tuple(float(v) for v in tie.value) if tie is not None else None
            trans = tuple(float(v) for v in trans.value) if trans is not None else None
            nodata_txt = str(nodata_tag.value).strip().strip("\x00") if nodata_tag is not None else None
            size = path.stat().st_size
            offs = [int(v) for v in (page.dataoffsets or ())]
            cnts = [int(v) for v in (page.databytecounts or ())]
            if any(o + c > size for o, c in zip(offs, cnts)):
                raise DataError(f"{base}: GeoTIFF is truncated (image data runs past the end of the file)")
    except DataError:
        raise
    except Exception as e:
        raise DataError(f"{base}: not a readable GeoTIFF ({type(e).__name__}: {e})") from None

    if spp != 1:
        raise DataError(f"{base}: GeoTIFF has {spp} bands per pixel; expected a single elevation band")
    dims = [d for d in shape if d != 1]
    if len(dims) != 2:
        raise DataError(f"{base}: expected a 2-D elevation raster, got shape {tuple(shape)}")
    nrows, ncols = dims
    if nrows < 2 or ncols < 2:
        raise DataError(f"{base}: raster of {nrows} x {ncols} pixels is too small to interpolate")
    if not geo:
        raise DataError(f"{base}: TIFF has no GeoTIFF georeferencing (GeoKeyDirectory tag missing)")
    model = geo.get("GTModelType")
    if model == 1 or "ProjectedCSType" in geo:
        code = geo.get("ProjectedCSType")
        raise DataError(f"{base}: GeoTIFF is in a projected CRS"
                        f"{f' (EPSG:{code})' if code and code != 32767 else ''}; cosim needs geographic "
                        "lon/lat degrees (EPSG:4326 or EPSG:4269), e.g. gdalwarp -t_srs EPSG:4326")
    if model not in (2, None):
        raise DataError(f"{base}: unsupported GeoTIFF model type {model} (need geographic lon/lat)")
    units = geo.get("GeogAngularUnits")
    if units not in (None, 9102, 9122):
        raise DataError(f"{base}: GeoTIFF angular unit EPSG:{units} is not degrees")
    gcs = geo.get("GeographicType")
    if gcs not in (None, 32767):
        if not _wgs84_like_geographic(gcs):
            raise DataError(f"{base}: geographic CRS EPSG:{gcs} is not on the WGS84/GRS80 ellipsoid; "
                            "reproject to EPSG:4326")
    else:
        a_ = geo.get("GeogSemiMajorAxis")
        invf = geo.get("GeogInvFlattening")
        if a_ is not None and (abs(float(a_) - 6378137.0) > 1.0
                               or (invf is not None and abs(float(invf) - 298.257) > 0.01)):
            raise DataError(f"{base}: user-defined geographic CRS is not on the WGS84/GRS80 ellipsoid; "
                            "reproject to EPSG:4326")
    raster_type = geo.get("GTRasterType", 1)
    if raster_type not in (1, 2):
        raise DataError(f"{base}: unknown GeoTIFF raster type {raster_type}")
    is_point = raster_type == 2

    # raster (i = column, j = row) -> lon = x0 + i * sx, lat = y0 - j * sy
    if scale is not None and tie is not None and len(tie) >= 6:
        if len(tie) > 6:
            raise DataError(f"{base}: GeoTIFF with several tiepoints (warped grid) is not supported")
        sx, sy = scale[0], scale[1]
        x0 = tie[3] - tie[0] * sx
        y0 = tie[4] + tie[1] * sy
    elif trans is not None and len(trans) == 16:
        a, b, _, d, e, f = trans[0], trans[1], trans[2], trans[3], trans[4], trans[5]
        h = trans[7]
        if abs(b) > 1e-12 or abs(e) > 1e-12:
            raise DataError(f"{base}: rotated GeoTIFF grids are not supported")
        sx, sy, x0, y0 = a, -f, d, h
    else:
        raise DataError(f"{base}: GeoTIFF lacks ModelPixelScale + ModelTiepoint (or ModelTransformation)")
    if not all(math.isfinite(v) for v in (sx, sy, x0, y0)) or sx == 0 or sy == 0:
        raise DataError(f"{base}: GeoTIFF has a degenerate pixel size ({sx}, {sy})")
    half = 0.0 if is_point else 0.5
    # sample positions of pixel (r, c) in the file's row/column order
    lon_c0 = x0 + half * sx
    lat_r0 = y0 - half * sy
    flip_rows, flip_cols = sy < 0, sx < 0
    dlon, dlat = abs(sx), abs(sy)
    lon_first = lon_c0 if not flip_cols else lon_c0 + (ncols - 1) * sx
    lat_first = lat_r0 if not flip_rows else lat_r0 - (nrows - 1) * sy
    west, east = lon_first, lon_first + (ncols - 1) * dlon
    north, south = lat_first, lat_first - (nrows - 1) * dlat
    if not is_point:
        west, east, north, south = west - dlon / 2, east + dlon / 2, north + dlat / 2, south - dlat / 2
    if not (-180.0 - 1e-6 <= west and east <= 360.0 + 1e-6 and -90.0 - 1e-6 <= south and north <= 90.0 + 1e-6):
        raise DataError(f"{base}: GeoTIFF extent lat {south:.4f}..{north:.4f}, lon {west:.4f}..{east:.4f} "
                        "is not in degrees (projected CRS mislabelled as geographic?)")

    nodata = None
    if nodata_txt:
        try:
            nodata = float(nodata_txt)
        except ValueError:
            raise DataError(f"{base}: unreadable GDAL_NODATA value {nodata_txt!r}") from None
    vunits = geo.get("VerticalUnits")
    if vunits is not None and vunits not in _VERTICAL_UNITS:
        raise DataError(f"{base}: unsupported vertical unit EPSG:{vunits} (need metres or feet)")
    z_scale = _VERTICAL_UNITS.get(vunits, 1.0)
    vcs = geo.get("VerticalCSType")
    if vcs in _VERTICAL_DATUMS:
        datum = _VERTICAL_DATUMS[vcs]
    elif vcs not in (None, 32767):
        datum = f"EPSG:{vcs}"
    elif gcs in _NED_NAD83:
        datum = "NAVD88 (NED)"  # USGS NED is NAD83 lon/lat with NAVD88 heights
    else:
        datum = "unknown (the GeoTIFF names no vertical datum)"
    licence = _LICENCE_PD if gcs in _NED_NAD83 else "unknown (user-supplied GeoTIFF; see its source)"
    return _GeoTiff(path, base, (nrows, ncols), geo, nodata, z_scale, datum, licence, flip_rows, flip_cols,
                    (lat_first, lon_first, dlat, dlon, south, west, north, east))


# --------------------------------------------------------------------------------------------
# the composite source
# --------------------------------------------------------------------------------------------

class DemElevation(Elevation):
    """Elevation from one or more DEM rasters (a seamless mosaic of SRTM tiles, or GeoTIFFs).

    Where rasters overlap, the first one listed wins (preferring a raster whose sample points
    surround the query, so GeoTIFFs that overlap by one pixel mosaic seamlessly; HGT tiles
    share their edge samples and always do). Use :func:`open_dem` to create one.
    """

    name = "dem"

    def __init__(self, grids: list[_Grid], files: list[str]):
        if not grids:
            raise DataError("no DEM rasters given")
        self.grids = list(grids)
        self.files = list(files)
        self.format = grids[0].fmt
        self._tiles = {g.tile: g for g in grids if isinstance(g, _HgtTile)}

    # --- info ---
    @property
    def voids_filled(self) -> int:  # filled cells in the rasters read so far
        return int(sum(g.voids or 0 for g in self.grids))

    @property
    def fill_seconds(self) -> float:
        return float(sum(g.fill_seconds for g in self.grids))

    def info(self) -> dict:
        if self.format == "srtm-hgt":
            datum, licence = "EGM96 geoid (SRTM)", _LICENCE_PD
        else:
            datums = sorted({g.datum for g in self.grids})
            licences = sorted({g.licence for g in self.grids})
            datum = datums[0] if len(datums) == 1 else "mixed: " + "; ".join(datums)
            licence = licences[0] if len(licences) == 1 else "; ".join(licences)
        return {
            "kind": "dem",
            "format": self.format,
            "files": list(self.files),
            "voids_filled": self.voids_filled,
            "rasters_read": [g.label for g in self.grids if g.loaded],
            "resolution_arcsec": sorted({float(g.arcsec) for g in self.grids}),
            "void_fill": "harmonic interpolation (Laplace equation; zero gradient at raster edges)",
            "datum": datum,
            "licence": licence,
        }

    # --- coverage ---
    def _missing_tiles(self, s: float, w: float, n: float, e: float) -> list[tuple[int, int]]:
        lats = range(math.floor(s + _EPS), max(math.ceil(n - _EPS), math.floor(s + _EPS) + 1))
        lons = range(math.floor(w + _EPS), max(math.ceil(e - _EPS), math.floor(w + _EPS) + 1))
        return [(la, lo) for la in lats for lo in lons if (la, lo) not in self._tiles]

    @staticmethod
    def _tiles_text(missing: list[tuple[int, int]], limit: int = 8) -> str:
        parts = [f"{hgt_tile_name(la, lo)} (lat {la}..{la + 1}, lon {lo}..{lo + 1})"
                 for la, lo in missing[:limit]]
        more = f" and {len(missing) - limit} more" if len(missing) > limit else ""
        return ("missing tile " if len(missing) == 1 else "missing tiles ") + ", ".join(parts) + more

    def _extents_text(self) -> str:
        return "; ".join(f"{g.label} covers {g.extent_text()}" for g in self.grids)

    def _uncovered_box(self, s: float, w: float, n: float, e: float) -> bool:
        """True if some part of the bbox lies outside the union of the rasters' extents."""
        xs = sorted({w, e} | {x for g in self.grids for x in (g.west, g.east) if w < x < e})
        ys = sorted({s, n} | {y for g in self.grids for y in (g.south, g.north) if s < y < n})
        xs = xs if len(xs) > 1 else [w, w]
        ys = ys if len(ys) > 1 else [s, s]
        for i in range(len(xs) - 1):
            cx = 0.5 * (xs[i] + xs[i + 1])
            for j in range(len(ys) - 1):
                cy = 0.5 * (ys[j] + ys[j + 1])
                # test the elementary cell's centre and (for degenerate boxes) its corners
                pts = [(cx, cy), (xs[i], ys[j]), (xs[i + 1], ys[j + 1]), (xs[i], ys[j + 1]), (xs[i + 1], ys[j])]
                for x, y in pts:
                    if not any(g.west - _EPS <= x <= g.east + _EPS and g.south - _EPS <= y <= g.north + _EPS
                               for g in self.grids):
                        return True
        return False

    def check_covers(self, south: float, west: float, north: float, east: float) -> None:
        s, w, n, e = (float(v) for v in (south, west, north, east))
        if not all(math.isfinite(v) for v in (s, w, n, e)) or s > n or w > e:
            raise InputError(f"DEM coverage check: bad bbox S,W,N,E = {south},{west},{north},{east}")
        box = f"lat {_fmt_deg(s)}..{_fmt_deg(n)}, lon {_fmt_deg(w)}..{_fmt_deg(e)}"
        if self.format == "srtm-hgt":
            missing = self._missing_tiles(s, w, n, e)
            if missing:
                raise DataError(f"DEM does not cover the area: {self._tiles_text(missing)} "
                                f"[requested {box}]")
        elif self._uncovered_box(s, w, n, e):
            raise DataError(f"DEM does not cover the area: requested {box}, but {self._extents_text()}")
        valid = total = 0
        for g in self.grids:
            if g.intersects_box(s, w, n, e):
                v, t = g.valid_count(s, w, n, e)
                valid, total = valid + v, total + t
        if valid == 0:
            names = ", ".join(g.label for g in self.grids if g.intersects_box(s, w, n, e))
            raise DataError(f"DEM has no valid elevation data in the area ({box}): all {total} samples "
                            f"of {names} there are voids/nodata")

    # --- sampling ---
    def sample(self, lon, lat) -> np.ndarray:
        lon = np.asarray(lon, dtype=np.float64)
        lat = np.asarray(lat, dtype=np.float64)
        shape = np.broadcast_shapes(lon.shape, lat.shape)
        lon = np.broadcast_to(lon, shape).ravel()
        lat = np.broadcast_to(lat, shape).ravel()
        if lon.size == 0:
            return np.empty(shape)
        s, n, w, e = lat.min(), lat.max(), lon.min(), lon.max()
        if np.isfinite([s, n, w, e]).all():
            # fast path: one raster holds every point (inside its sample span, or anywhere in
            # its extent when it is the only raster)
            for g in self.grids:
                if g.contains_box(s, w, n, e, samples=True) or (
                        len(self.grids) == 1 and g.contains_box(s, w, n, e)):
                    return g.sample(lon, lat).reshape(shape)
        out = np.empty(lon.size)
        todo = np.isfinite(lon) & np.isfinite(lat)
        bad = int(lon.size - np.count_nonzero(todo))
        if bad:
            raise DataError(f"DEM sample: {bad} of {lon.size} points have non-finite coordinates")
        # a point is taken from the first raster whose sample span holds it (true bilinear
        # interpolation); only points in no span (the outer half pixel of a PixelIsArea
        # GeoTIFF) take the edge value of a raster whose extent holds them
        for inside in (_Grid.contains_samples, _Grid.contains):
            for g in self.grids:
                if not g.intersects_box(s, w, n, e):
                    continue
                m = todo & inside(g, lon, lat)
                if m.any():
                    out[m] = g.sample(lon[m], lat[m])
                    todo &= ~m
                    if not todo.any():
                        return out.reshape(shape)
        k = np.nonzero(todo)[0]
        ex = f"e.g. lat {lat[k[0]]:.6f}, lon {lon[k[0]]:.6f}"
        if self.format == "srtm-hgt":
            keys = np.unique(np.stack([np.floor(lat[k]), np.floor(lon[k])], axis=1), axis=0)
            missing = [(int(a), int(b)) for a, b in keys]
            raise DataError(f"DEM does not cover {k.size} of {lon.size} sampled points ({ex}): "
                            f"{self._tiles_text(missing)}")
        raise DataError(f"DEM does not cover {k.size} of {lon.size} sampled points ({ex}): "
                        f"{self._extents_text()}")


def open_dem(paths) -> DemElevation:
    """Open DEM files (SRTM ``.hgt``/``.hgt.zip`` tiles, or geographic GeoTIFFs) as one source.

    Only headers are read here; raster data is read (and its voids filled) on first use.
    Raises DataError (one line, naming the file) for missing, unreadable, corrupt or
    unsupported files, duplicate tiles, or a list mixing HGT tiles with GeoTIFFs.
    """
    if isinstance(paths, (str, Path)):
        paths = [paths]
    paths = [Path(p) for p in paths]
    if not paths:
        raise DataError("no DEM files given")
    grids: list[_Grid] = []
    kinds = set()
    for p in paths:
        low = p.name.lower()
        if not p.exists():
            raise DataError(f"DEM file not found: {p}")
        if not p.is_file():
            raise DataError(f"DEM path is not a file: {p}")
        if low.endswith(".hgt") or low.endswith(".hgt.zip"):
            grids.extend(_open_hgt(p))
            kinds.add("srtm-hgt")
        elif low.endswith(".tif") or low.endswith(".tiff"):
            grids.append(_open_geotiff(p))
            kinds.add("geotiff")
        else:
            raise DataError(f"{p.name}: unknown DEM format (expected .hgt, .hgt.zip, .tif or .tiff)")
    if len(kinds) > 1:
        raise DataError("cannot mix SRTM .hgt tiles and GeoTIFFs in one DEM (their vertical datums differ: "
                        "EGM96 vs the GeoTIFF's); give one kind: "
                        + ", ".join(p.name for p in paths))
    seen: dict[tuple[int, int], str] = {}
    for g in grids:
        if isinstance(g, _HgtTile):
            if g.tile in seen:
                raise DataError(f"SRTM tile {hgt_tile_name(*g.tile)[:-4]} given twice ({seen[g.tile]}, {g.label})")
            seen[g.tile] = g.label
    return DemElevation(grids, [p.name for p in paths])
