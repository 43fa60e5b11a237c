"""Terrain: a regular height grid sampled (bilinearly) from the elevation source.

One grid covers the whole world window, so chunks cut from it share their border samples
exactly (seamless). Under roads the grid is levelled to the road surface (a few cm below it)
and blended back into the natural terrain over a short distance, so the car neither falls
through the road nor meets a bump at its edge.

On disk, chunk (i, j) is ``terrain/<i>_<j>.npy``: float32 ``z[row, col]`` at
``x = xmin + col * spacing``, ``y = ymin + row * spacing`` (row 0 is the southern edge), with
(xmin, ymin) the chunk's lower-left corner; both edges are included, so a 1000 m chunk at 5 m
spacing is 201 x 201 samples and neighbours repeat their shared edge.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

ROAD_SINK_M = 0.08       # terrain under a road sits this far below the road surface
INNER_CELLS = 0.75       # nodes this many cells beyond a road's edge are levelled too (flat bilinear surface)
STACK_NEIGHBOURS = 16    # road points looked at per node for a road further down
STACK_STEP_M = 0.5       # ... lower than the nearest road point by more than this
STACK_GRADE = 0.25       # ... plus this grade times their distance (steeper than any street)


def levelling_reach(halfwidth: float, spacing: float) -> float:
    """Distance from a road point beyond which the terrain is the untouched DEM."""
    return halfwidth + INNER_CELLS * spacing + spacing


@dataclass
class TerrainGrid:
    xmin: float
    ymin: float
    spacing: float
    z: np.ndarray            # (ny, nx), row = y index

    @property
    def shape(self):
        return self.z.shape

    @property
    def xmax(self):
        return self.xmin + (self.z.shape[1] - 1) * self.spacing

    @property
    def ymax(self):
        return self.ymin + (self.z.shape[0] - 1) * self.spacing

    def nodes(self):
        ny, nx = self.z.shape
        xs = self.xmin + np.arange(nx) * self.spacing
        ys = self.ymin + np.arange(ny) * self.spacing
        return np.meshgrid(xs, ys)

    def sample(self, x, y) -> np.ndarray:
        """Bilinear height at world x/y (arrays); clamped at the grid's border."""
        return self._bilinear(*self._corners(x, y))

    def _cell(self, x, y):
        """(row, col) of the grid cell under world x/y (arrays; clamped at the grid's border)
        and the position in it, (tx, ty) in [0, 1)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        ny, nx = self.z.shape
        fx = np.minimum(np.maximum((x - self.xmin) / self.spacing, 0.0), nx - 1.000001)  # (np.clip, without its
        fy = np.minimum(np.maximum((y - self.ymin) / self.spacing, 0.0), ny - 1.000001)  # wrapper's 3 us)
        c = np.floor(fx).astype(np.int64)
        r = np.floor(fy).astype(np.int64)
        return r, c, fx - c, fy - r

    def _corners(self, x, y):
        """The heights of the corners of the cell under x/y, (this node, the next column,
        the next row, the next of both), and the position in the cell (tx, ty)."""
        r, c, tx, ty = self._cell(x, y)
        nx = self.z.shape[1]
        zf = self.z.ravel()
        i = r * nx + c
        return zf[i], zf[i + 1], zf[i + nx], zf[i + nx + 1], tx, ty

    @staticmethod
    def _bilinear(z00, zc, zr, z11, tx, ty):
        return z00 * (1 - tx) * (1 - ty) + zc * tx * (1 - ty) + zr * (1 - tx) * ty + z11 * tx * ty

    @staticmethod
    def _triangles(z00, zc, zr, z11, tx, ty):
        return np.where(tx + ty <= 1.0, z00 + (zc - z00) * tx + (zr - z00) * ty,
                        z11 + (zr - z11) * (1.0 - tx) + (zc - z11) * (1.0 - ty))

    __call__ = sample

    def sample_tri(self, x, y) -> np.ndarray:
        """Height on the grid's triangulation as Bullet's heightfield builds it: each cell is
        cut along its anti-diagonal, from (x+1, y) to (x, y+1). Objects placed with this sit
        exactly on the physics terrain (bilinear differs by up to |z00+z11-z01-z10|/4)."""
        return self._triangles(*self._corners(x, y))

    def sample_higher(self, x, y) -> np.ndarray:
        """``max(sample(x, y), sample_tri(x, y))``, the cell found and its corners read once."""
        corners = self._corners(x, y)
        return np.maximum(self._bilinear(*corners), self._triangles(*corners))

    def cut(self, bounds) -> np.ndarray:
        """The sub-grid covering chunk bounds (both edges included)."""
        xmin, ymin, xmax, ymax = bounds
        c0 = int(round((xmin - self.xmin) / self.spacing))
        r0 = int(round((ymin - self.ymin) / self.spacing))
        c1 = int(round((xmax - self.xmin) / self.spacing))
        r1 = int(round((ymax - self.ymin) / self.spacing))
        return self.z[r0:r1 + 1, c0:c1 + 1]


def sample_grid(frame, elevation, extent, spacing: float) -> TerrainGrid:
    """Sample the elevation source on a grid covering `extent` (xmin, ymin, xmax, ymax)."""
    xmin, ymin, xmax, ymax = extent
    nx = int(round((xmax - xmin) / spacing)) + 1
    ny = int(round((ymax - ymin) / spacing)) + 1
    xs = xmin + np.arange(nx) * spacing
    ys = ymin + np.arange(ny) * spacing
    X, Y = np.meshgrid(xs, ys)
    lon, lat = frame.to_lonlat(X.ravel(), Y.ravel())
    z = np.asarray(elevation.sample(lon, lat), dtype=float).reshape(ny, nx)
    return TerrainGrid(xmin=xmin, ymin=ymin, spacing=spacing, z=z)


def _point_cells(grid: TerrainGrid, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(row, column) of the grid cell of each point, points beyond the grid at its border."""
    ny, nx = grid.z.shape
    sp = grid.spacing
    ci = np.clip(np.floor((pts[:, 0] - grid.xmin) / sp), 0, nx - 1).astype(np.int64)
    ri = np.clip(np.floor((pts[:, 1] - grid.ymin) / sp), 0, ny - 1).astype(np.int64)
    return ri, ci


def _nodes_near(grid: TerrainGrid, pts: np.ndarray, reach: float) -> np.ndarray:
    """Flat indices (ascending) of the grid nodes that may lie within `reach` of one of `pts`:
    every node within reach is among them (a superset, by whole cells: the square of
    +-(reach/spacing + 1) cells around each point's cell; points beyond the grid count at its
    border)."""
    ny, nx = grid.z.shape
    sp = grid.spacing
    if not len(pts) or not np.all(np.isfinite(pts[:, :2])) or not np.isfinite(reach):
        return np.arange(ny * nx)
    ri, ci = _point_cells(grid, pts)
    occ = np.zeros((ny, nx), dtype=np.int32)
    occ[ri, ci] = 1
    k = int(np.ceil(reach / sp)) + 1
    for axis, n in ((1, nx), (0, ny)):      # dilate by k cells along x, then along y
        cs = np.cumsum(occ, axis=axis, dtype=np.int32)
        cs = np.concatenate([np.zeros_like(cs.take([0], axis=axis)), cs], axis=axis)
        i = np.arange(n)
        hi, lo = np.minimum(i + k + 1, n), np.maximum(i - k, 0)
        occ = (cs.take(hi, axis=axis) - cs.take(lo, axis=axis) > 0).astype(np.int32)
    return np.flatnonzero(occ)


def level_under_roads(grid: TerrainGrid, pts: np.ndarray, halfwidth: np.ndarray,
                      blend_m: float | None = None, clear=True, tris: np.ndarray | None = None,
                      hold: np.ndarray | None = None) -> dict:
    """Level the grid to the road surface.

    `pts` (n, 3) are dense road-surface points (x, y, z) and `halfwidth` (n,) the distance
    from each point within which the ground is the road. Grid nodes within that distance
    (plus half a grid cell, so the bilinear surface is flat across the road) take the road
    height minus ROAD_SINK_M; nodes within `blend_m` beyond that blend linearly back to the
    natural ground. With `clear` (True, or a mask of `pts`: the points where cars drive),
    then :func:`clear_road_points` of those points, and, given `tris` (m, 3: triangles of the
    drivable surface over `pts`), of :func:`surface_check_points` too: the terrain is then
    below the whole surface, not only below its points. ``hold`` (a mask of `pts`) limits the
    points the ground is levelled to (a bridge's deck above the ground holds none up), not
    those it is cleared under.
    """
    if len(pts) == 0:
        return {"levelled_nodes": 0, "blended_nodes": 0, "max_change_m": 0.0}
    all_pts = pts
    if hold is not None:
        hold = np.asarray(hold, dtype=bool)
        pts, halfwidth = pts[hold], halfwidth[hold]
    if len(pts) == 0:          # (nothing to level to: only the clearing)
        z0 = grid.z.ravel().copy()
        out = {"levelled_nodes": 0, "blended_nodes": 0}
    else:
        z0, out = _level_to(grid, pts, halfwidth, blend_m)
    if clear is not False:
        P = all_pts if clear is True else all_pts[np.asarray(clear, dtype=bool)]
        if tris is not None and len(tris):
            P = np.vstack([P, surface_check_points(grid, all_pts, tris)])
        out["lowered_nodes"] = clear_road_points(grid, P)
    out["max_change_m"] = float(np.max(np.abs(grid.z.ravel() - z0))) if grid.z.size else 0.0
    return out


def _level_to(grid: TerrainGrid, pts: np.ndarray, halfwidth: np.ndarray, blend_m: float | None):
    """The levelling of :func:`level_under_roads` (not the clearing): the grid's heights
    before, and the counts."""
    sp = grid.spacing
    blend_m = sp if blend_m is None else blend_m
    tree = cKDTree(pts[:, :2])
    reach = float(halfwidth.max()) + INNER_CELLS * sp + blend_m
    # only the nodes that may have a road point within reach are looked up (the others would
    # find none): a node is a candidate if a road point lies in its square of +-reach
    cand = _nodes_near(grid, pts, reach)
    ny, nx = grid.z.shape
    q = np.column_stack([grid.xmin + (cand % nx) * sp, grid.ymin + (cand // nx) * sp])
    k = min(STACK_NEIGHBOURS, len(pts))
    d, idx = tree.query(q, k=k, distance_upper_bound=reach, workers=-1)     # threads: a core may be idle
    d, idx = d.reshape(len(q), k), idx.reshape(len(q), k)
    hit = np.isfinite(d[:, 0])
    z = grid.z.ravel().copy()
    z0 = z.copy()
    hi = cand[hit]
    di, ii = d[hit, 0], idx[hit, 0]
    # a road below the nearest one, within its own reach of the node, by more than any road
    # grade explains between the two points (a street further down a hillside, not the same
    # street's slope): the node takes the lowest such road, so the terrain between the two
    # does not rise through the lower one. Looked for among the STACK_NEIGHBOURS nearest road
    # points only at the nodes with a road point lower by STACK_STEP_M or more within reach
    # (the lowest point of the cells around, _lowest_near: elsewhere none of them is below)
    if float(np.ptp(pts[:, 2])) < STACK_STEP_M:
        stack = np.zeros(0, dtype=np.int64)      # (no road point is that much lower than another)
    else:
        stack = np.flatnonzero(_lowest_near(grid, pts, reach)[hi] < pts[ii, 2] - STACK_STEP_M)
    inner = halfwidth[ii] + INNER_CELLS * sp
    road_z = pts[ii, 2] - ROAD_SINK_M
    if len(stack):
        i0 = ii[stack]
        d, idx = d[hit][stack], idx[hit][stack]
        ok = np.isfinite(d)
        jj = np.where(ok, idx, 0)
        zj = np.where(ok & (d <= halfwidth[jj] + INNER_CELLS * sp), pts[jj, 2], np.inf)
        gap = np.hypot(pts[jj, 0] - pts[i0, 0][:, None], pts[jj, 1] - pts[i0, 1][:, None])
        below = zj < pts[i0, 2][:, None] - STACK_STEP_M - STACK_GRADE * gap
        lower = np.where(below, zj, np.inf).min(axis=1)
        road_z[stack] = np.where(np.isfinite(lower), lower - ROAD_SINK_M, road_z[stack])
    w = np.clip(1.0 - (di - inner) / blend_m, 0.0, 1.0)     # 1 on the road, 0 beyond the blend
    z[hi] = w * road_z + (1.0 - w) * z0[hi]
    grid.z = z.reshape(grid.z.shape)
    return z0, {"levelled_nodes": int(np.sum(w >= 1.0)), "blended_nodes": int(np.sum((w > 0) & (w < 1)))}


def _lowest_near(grid: TerrainGrid, pts: np.ndarray, reach: float) -> np.ndarray:
    """Per grid node (flat), a height at or below that of every point of `pts` within `reach`
    of it: the lowest point of the cells in the square of +-(reach/spacing + 1) cells around
    it (+inf where there is none; points beyond the grid count at its border)."""
    ny, nx = grid.z.shape
    sp = grid.spacing
    ri, ci = _point_cells(grid, pts)
    low = np.full(ny * nx, np.inf)
    np.minimum.at(low, ri * nx + ci, pts[:, 2])
    low = low.reshape(ny, nx)
    k = int(np.ceil(reach / sp)) + 1
    for axis in (0, 1):             # the square's minimum: along y, then along x
        a, out = low, low.copy()
        n = a.shape[axis]
        for s in range(1, min(k, n - 1) + 1):
            lo, hi = [slice(None)] * 2, [slice(None)] * 2
            lo[axis], hi[axis] = slice(None, n - s), slice(s, None)
            np.minimum(out[tuple(hi)], a[tuple(lo)], out=out[tuple(hi)])
            np.minimum(out[tuple(lo)], a[tuple(hi)], out=out[tuple(lo)])
        low = out
    return low.ravel()


def _ranks(counts: np.ndarray) -> np.ndarray:
    """0, 1, ..., c - 1 for each count c, concatenated (the rank of each item of a
    ``np.repeat(..., counts)`` within its group)."""
    return np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)


def surface_check_points(grid: TerrainGrid, pts: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Points (k, 3) of the triangulated surface (`pts` (n, 3) indexed by `tris` (m, 3)) where
    the terrain, less the surface, can be highest: Bullet's heightfield is planar on each
    half cell, so the difference is planar on each piece of the overlay of the two
    triangulations, and its maximum over the surface lies at a corner of a piece. Those
    corners are the surface's vertices (`pts` themselves, not repeated here), where its edges
    cross the grid's lines and cells' anti-diagonals, and the grid's nodes inside its
    triangles. (Only the vertices were cleared: a ridge of the 10 m grid between two of them
    stood 0.19 m above a Monaco lane, and the car lost 0.6 m/s on it.)"""
    sp = grid.spacing
    g = (pts[:, :2] - (grid.xmin, grid.ymin)) / sp                    # grid units
    # (an edge shared by two triangles comes twice: finding the pairs costs more than the
    # points it would save)
    a = tris.ravel()
    b = tris[:, [1, 2, 0]].ravel()
    out = []
    for u in (g[:, 0], g[:, 1], g[:, 0] + g[:, 1]):                  # x lines, y lines, anti-diagonals
        ua, ub = u[a], u[b]
        lo, hi = np.minimum(ua, ub), np.maximum(ua, ub)
        k0 = np.floor(lo) + 1.0
        n = np.maximum(np.floor(hi) - k0 + 1.0, 0).astype(np.int64)   # integers in (lo, hi]
        sel = np.flatnonzero(n)
        if not len(sel):
            continue
        rep = np.repeat(sel, n[sel])
        k = np.repeat(k0[sel], n[sel]) + _ranks(n[sel])
        u0 = ua[rep]
        t = (k - u0) / (ub[rep] - u0)
        pa = pts[a[rep]]
        out.append(pa + t[:, None] * (pts[b[rep]] - pa))
    # grid nodes inside triangles, at the triangle's height
    X, Y = g[:, 0][tris], g[:, 1][tris]
    c0 = np.ceil(np.minimum(np.minimum(X[:, 0], X[:, 1]), X[:, 2]))
    c1 = np.floor(np.maximum(np.maximum(X[:, 0], X[:, 1]), X[:, 2]))
    r0 = np.ceil(np.minimum(np.minimum(Y[:, 0], Y[:, 1]), Y[:, 2]))
    r1 = np.floor(np.maximum(np.maximum(Y[:, 0], Y[:, 1]), Y[:, 2]))
    nc, nr = np.maximum(c1 - c0 + 1, 0).astype(np.int64), np.maximum(r1 - r0 + 1, 0).astype(np.int64)
    cnt = nc * nr
    sel = np.flatnonzero(cnt)
    if len(sel):
        ti = np.repeat(sel, cnt[sel])
        j = _ranks(cnt[sel])
        cx = c0[ti] + j % nc[ti]
        cy = r0[ti] + j // nc[ti]
        A, B, C = g[tris[ti, 0]], g[tris[ti, 1]], g[tris[ti, 2]]
        d = (B[:, 0] - A[:, 0]) * (C[:, 1] - A[:, 1]) - (C[:, 0] - A[:, 0]) * (B[:, 1] - A[:, 1])
        ok = np.abs(d) > 1e-12
        dd = np.where(ok, d, 1.0)
        l1 = ((cx - A[:, 0]) * (C[:, 1] - A[:, 1]) - (C[:, 0] - A[:, 0]) * (cy - A[:, 1])) / dd
        l2 = ((B[:, 0] - A[:, 0]) * (cy - A[:, 1]) - (cx - A[:, 0]) * (B[:, 1] - A[:, 1])) / dd
        eps = 1e-9
        inside = ok & (l1 >= -eps) & (l2 >= -eps) & (l1 + l2 <= 1 + eps)
        if inside.any():
            tz = pts[tris[ti[inside]], 2]
            z = tz[:, 0] + l1[inside] * (tz[:, 1] - tz[:, 0]) + l2[inside] * (tz[:, 2] - tz[:, 0])
            out.append(np.column_stack([grid.xmin + cx[inside] * sp, grid.ymin + cy[inside] * sp, z]))
    return np.vstack(out) if out else np.zeros((0, 3))


def clear_road_points(grid: TerrainGrid, pts: np.ndarray) -> int:
    """Lower the grid where its surface (bilinear, and the triangles Bullet's heightfield
    makes of it) lies above a road point `pts` (n, 3) less ROAD_SINK_M: the four nodes of that
    point's cell go down by the excess (a node by the largest its cells' points ask). One pass
    clears every point: each point's nodes drop by at least its excess, and no node rises.
    (Nodes take the height of their nearest road point: on a 10 m grid beside a Monaco
    junction the surface between them rose 0.9 m above a lane, and the car drove up onto
    it.) Returns how many nodes were lowered."""
    inside = (pts[:, 0] >= grid.xmin) & (pts[:, 0] <= grid.xmax) & (pts[:, 1] >= grid.ymin) & (pts[:, 1] <= grid.ymax)
    pts = pts[inside]           # (beyond the grid its border stands for the ground: not lowered)
    if not len(pts):
        return 0
    lim = pts[:, 2] - ROAD_SINK_M
    ex = grid.sample_higher(pts[:, 0], pts[:, 1]) - lim
    bad = np.nonzero(ex > 1e-6)[0]
    if not len(bad):
        return 0
    ny, nx = grid.z.shape
    sp = grid.spacing
    c = np.floor(np.clip((pts[bad, 0] - grid.xmin) / sp, 0.0, nx - 1.000001)).astype(np.int64)
    r = np.floor(np.clip((pts[bad, 1] - grid.ymin) / sp, 0.0, ny - 1.000001)).astype(np.int64)
    drop = np.zeros(ny * nx)
    for dr, dc in ((0, 0), (0, 1), (1, 0), (1, 1)):
        np.maximum.at(drop, (r + dr) * nx + c + dc, ex[bad])
    grid.z = (grid.z.ravel() - drop).reshape(ny, nx)
    return int(np.count_nonzero(drop))
