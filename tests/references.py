"""Independent references the tests of several stages share: the planners' graph built
with scipy, brute-force safety surfaces, reference paths and their lengths, path checks, and
small DEMs with known answers. Nothing here calls the code under test to make a reference."""

from __future__ import annotations

import math

import numpy as np
from conftest import (
    metric_dataarray,
    random_surface,
)
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra as scipy_dijkstra

from pipeline.maps.components import label_components

A = 30.0  # the cell side (m) of the shared DEMs
MOVES = [(0, 1), (1, 1), (1, 0), (1, -1), (0, -1), (-1, -1), (-1, 0), (-1, 1)]


def reference_distances(surface, passable, a, start):
    g = reference_graph(surface, passable, a)
    return scipy_dijkstra(g, indices=start[0] * surface.shape[1] + start[1])


def check_cells(cells, passable, start, goal):
    """Start to goal in 8-neighbour moves over passable cells, no corner cut, no cell twice."""
    assert tuple(cells[0]) == tuple(start) and tuple(cells[-1]) == tuple(goal)
    assert passable[cells[:, 0], cells[:, 1]].all()
    steps = np.diff(cells, axis=0)
    assert np.all(np.abs(steps).max(axis=1) == 1)  # 8-neighbour moves, no jumps, no stays
    for (r, c), (dr, dc) in zip(cells[:-1], steps, strict=True):
        if dr and dc:
            assert passable[r, c + dc] and passable[r + dr, c]  # no corner cutting
    assert len({tuple(x) for x in cells}) == len(cells)  # simple


def cell_metrics(cells, surface, ridge, a):
    """A path's length and ridge length, step by step in Python."""
    length = ridge_len = 0.0
    for (r0, c0), (r1, c1) in zip(cells[:-1], cells[1:], strict=True):
        step = math.sqrt(
            a * a * ((r1 - r0) ** 2 + (c1 - c0) ** 2)
            + (float(surface[r1, c1]) - float(surface[r0, c0])) ** 2
        )
        length += step
        ridge_len += step if ridge[r1, c1] else 0.0
    return length, ridge_len


WALL_ROW, WALL_END = 120, 200  # land wall on row 120 from col 0 to col 199

RING = (175, 232, 150, 232)  # a closed land ring (rows, cols), interior unreachable


def reference_length(surface, passable, a, start, goal):
    """The graph of docs/method.md section 4 built edge by edge, solved by
    scipy.sparse.csgraph.dijkstra."""
    d = reference_distances(surface, passable, a, start)
    return float(d[goal[0] * surface.shape[1] + goal[1]])


def reference_graph(surface, passable, a):
    """The graph of docs/method.md section 4 built edge by edge (8 moves, no corner cutting,
    3-D lengths) as a scipy sparse matrix over row-major cell indices."""
    rows, cols = surface.shape
    src, dst, w = [], [], []
    for r in range(rows):
        for c in range(cols):
            if not passable[r, c]:
                continue
            for dr, dc in MOVES:
                nr, nc = r + dr, c + dc
                if not (0 <= nr < rows and 0 <= nc < cols and passable[nr, nc]):
                    continue
                if dr and dc and not (passable[r, nc] and passable[nr, c]):
                    continue  # no corner cutting
                src.append(r * cols + c)
                dst.append(nr * cols + nc)
                dz = float(surface[nr, nc]) - float(surface[r, c])
                w.append(math.sqrt(a * a * (dr * dr + dc * dc) + dz * dz))
    return coo_matrix((w, (src, dst)), shape=(rows * cols, rows * cols)).tocsr()


def check_path(t, passable, start, goal):
    check_cells(t.cells, passable, start, goal)


def independent_metrics(t, surface, ridge, a):
    return cell_metrics(t.cells, surface, ridge, a)


def optimum(graph, shape, s, g):
    return scipy_dijkstra(graph, directed=False, indices=s[0] * shape[1] + s[1])[
        g[0] * shape[1] + g[1]
    ]


def missions(ok, k, seed, min_cells=1):
    """k random missions within one component, at least ``min_cells`` apart."""
    comp, _ = label_components(ok)
    rng = np.random.default_rng(seed)
    cells = np.argwhere(ok)
    out = []
    if min_cells > 1:  # far apart: draw candidate pairs in batches
        while len(out) < k:
            i = rng.integers(len(cells), size=(4096, 2))
            a, b = cells[i[:, 0]], cells[i[:, 1]]
            keep = (comp[a[:, 0], a[:, 1]] == comp[b[:, 0], b[:, 1]]) & (
                np.hypot(*(a - b).T) >= min_cells
            )
            out += [
                (tuple(map(int, x)), tuple(map(int, y)))
                for x, y in zip(a[keep], b[keep], strict=True)
            ]
        return out[:k]
    while len(out) < k:
        s, g = (tuple(int(v) for v in cells[i]) for i in rng.integers(len(cells), size=2))
        if comp[s] == comp[g] and math.dist(s, g) >= min_cells:
            out.append((s, g))
    return out


def wall_with_gap_dem(n=200, gap=(12, 20)):
    """Flat deep seabed, a land wall across row n / 2 with one gap far from the straight line
    between the test's start and goal, and a closed land ring (an unreachable lagoon)."""
    z = random_surface((n, n), seed=7) * 0.05 - 2500.0
    z[n // 2 - 1 : n // 2 + 2, :] = 20.0
    z[n // 2 - 1 : n // 2 + 2, gap[0] : gap[1]] = -2500.0
    z[20:60, 40:43] = z[20:60, 77:80] = z[20:23, 40:80] = z[57:60, 40:80] = 20.0
    return metric_dataarray(z.astype(np.float32), a=A).chunk(64)


def wall_dem():
    z = random_surface((240, 240), seed=3) * 0.1 - 2500.0  # gentle relief
    z[WALL_ROW - 1 : WALL_ROW + 2, :WALL_END] = 20.0
    r0, r1, c0, c1 = RING
    z[r0:r1, c0 : c0 + 2] = z[r0:r1, c1 - 2 : c1] = 20.0
    z[r0 : r0 + 2, c0:c1] = z[r1 - 2 : r1, c0:c1] = 20.0
    return metric_dataarray(z.astype(np.float32), a=A).chunk(64)


MISSION = dict(start=(20, 20), goal=(225, 30))


SMALL = dict(rho=4, section_size=24, margin=6)


def rounded_up(ref64):
    """The least float32 at or above each float64 value (NaN as it is): numpy's nextafter
    where the value rounded to nearest lies below it."""
    ref64 = np.asarray(ref64, dtype=np.float64)
    with np.errstate(over="ignore", invalid="ignore"):
        out = ref64.astype(np.float32)
        below = out.astype(np.float64) < ref64
    out[below] = np.nextafter(out[below], np.float32(np.inf))
    return out


def assert_correctly_rounded(got, ref64):
    """``got`` (float32) is the float64 reference rounded up once (a lowest safe height is
    never below the exact one): exact, and so within one float32 ulp (<= 4.9e-4 m at depths of
    4-8 km; the stored maps are float32)."""
    np.testing.assert_array_equal(got, rounded_up(ref64))


def brute_force(z, a, method, R, Rh=None):
    """Direct transcription of docs/method.md section 2, in float64, NaN if the disc holds
    no-data."""
    Rh = R if Rh is None else Rh
    rows, cols = z.shape
    radius = R if method == "spherical" else Rh
    r = int(math.floor(radius / a)) + 1
    out = np.empty((rows, cols))
    for i in range(rows):
        for j in range(cols):
            if method == "vertical":
                out[i, j] = float(z[i, j]) + R
                continue
            best, nodata = -np.inf, False
            for di in range(-r, r + 1):
                for dj in range(-r, r + 1):
                    ii, jj = i + di, j + dj
                    d2 = a * a * (di * di + dj * dj)
                    if not (0 <= ii < rows and 0 <= jj < cols) or d2 > radius * radius:
                        continue
                    v = float(z[ii, jj])
                    if np.isnan(v):
                        nodata = True
                        continue
                    c = v + math.sqrt(R * R - d2) if method == "spherical" else v
                    best = max(best, c)
            out[i, j] = np.nan if nodata else (best if method == "spherical" else best + R)
    return out


def scipy_reference(z, a, R):
    """grey_dilation with the spherical non-flat element, clipped at the edge (cval -inf)."""
    r = int(math.floor(R / a))
    off = np.arange(-r, r + 1)
    d2 = a * a * (off[:, None] ** 2 + off[None, :] ** 2)
    footprint = d2 <= R * R
    structure = np.where(footprint, np.sqrt(np.maximum(R * R - d2, 0.0)), 0.0)
    return ndimage.grey_dilation(
        np.asarray(z, np.float64),
        footprint=footprint,
        structure=structure,
        mode="constant",
        cval=-np.inf,
    )


def assert_upper_envelope(dem, z, x, y, crs=None, *, points=20000):
    """The planning seabed against the source grid ``z`` on axes ``x`` (lon or x) by ``y``
    (``crs``: the source's; None, the DEM's own): independently of the warp, by pyproj and
    scipy. (1) No node lies below the source's bilinear value there. (2) The DEM's own
    bilinear surface lies on or above the source's at random points between its nodes (the
    promise). (3) No node is higher than the highest source point within the square of
    half-side one cell around it, one source cell grown (it is no coarser than it must be).
    (4) The raise recorded (mean, greatest) is the one measured. Returns the raise."""
    import pytest
    from pyproj import CRS, Transformer
    from scipy.interpolate import RegularGridInterpolator
    from scipy.spatial import cKDTree

    a = float(dem.attrs["cell_size"])
    v = dem.values.astype(np.float64)
    dx, dy = dem.x.values, dem.y.values
    to_src = None
    if crs is not None:
        to_src = Transformer.from_crs(CRS.from_wkt(dem.attrs["crs_wkt"]), crs, always_xy=True)
    order = np.argsort(y)
    src = RegularGridInterpolator((y[order], x), z[order].astype(np.float64))

    def source_at(px, py):
        sx, sy = to_src.transform(px, py) if to_src is not None else (px, py)
        sx, sy = np.asarray(sx), np.asarray(sy)
        inside = (sx >= x.min()) & (sx <= x.max()) & (sy >= y.min()) & (sy <= y.max())
        out = np.full(sx.shape, np.nan)
        out[inside] = src(np.stack([sy[inside], sx[inside]], axis=-1))
        return out

    xx, yy = np.meshgrid(dx, dy)
    ref = source_at(xx, yy)
    ok = np.isfinite(ref) & np.isfinite(v)
    assert ok.mean() > 0.5
    assert np.all(v[ok] >= ref[ok] - 1e-3), (v[ok] - ref[ok]).min()  # (1)
    rng = np.random.default_rng(0)
    px = rng.uniform(dx.min(), dx.max(), points)
    py = rng.uniform(dy.min(), dy.max(), points)
    mine = RegularGridInterpolator((dy[::-1], dx), v[::-1])(np.stack([py, px], axis=-1))
    theirs = source_at(px, py)
    both = np.isfinite(mine) & np.isfinite(theirs)
    assert both.mean() > 0.5
    assert np.all(mine[both] >= theirs[both] - 1e-3), (mine[both] - theirs[both]).min()  # (2)
    # (3): the source points in map coordinates, the highest within the grown square
    gx, gy = np.meshgrid(x, y)
    if to_src is not None:
        back = Transformer.from_crs(crs, CRS.from_wkt(dem.attrs["crs_wkt"]), always_xy=True)
        gx, gy = back.transform(gx, gy)
    cell = 1.01 * np.hypot(*(np.ptp(np.asarray(g)[:2, :2]) for g in (gx, gy)))
    tree = cKDTree(np.column_stack([np.ravel(gx), np.ravel(gy)]))
    near = tree.query_ball_point(np.column_stack([xx[ok], yy[ok]]), a * np.sqrt(2) + cell)
    zs = z.astype(np.float64).ravel()
    top = np.array([zs[i].max() for i in near])
    assert np.all(v[ok] <= top + 0.05), (v[ok] - top).max()  # (a file's float32 grid)
    raised = v[ok] - ref[ok]
    if "seabed_raise_mean_m" in dem.attrs:  # (4), where the bilinear value is defined
        assert dem.attrs["seabed_raise_max_m"] >= raised.max() - 1e-2
        assert dem.attrs["seabed_raise_mean_m"] == pytest.approx(raised.mean(), rel=0.05, abs=0.05)
    return raised


def densify(xyz: np.ndarray, step: float) -> np.ndarray:
    """The polyline ``xyz`` with points at most ``step`` apart (horizontally) on each leg."""
    out = [xyz[:1]]
    for p, q in zip(xyz[:-1], xyz[1:], strict=True):
        n = max(1, int(math.ceil(math.hypot(*(q - p)[:2]) / step)))
        t = (np.arange(1, n + 1) / n)[:, None]
        out.append(p + t * (q - p))
    return np.concatenate(out)
