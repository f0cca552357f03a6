"""Safety maps (docs/method.md section 2; the paper's 4.2.1 with its formulas corrected) and
passability.

With clearance ``R``, horizontal clearance ``R_h`` and ``|q - p|`` the horizontal distance
between cell centres:

- vertical:   ``S(p) = z(p) + R``
- horizontal: ``S(p) = max{ z(q) : |q - p| <= R_h } + R``
- spherical:  ``S(p) = max{ z(q) + sqrt(R^2 - |q - p|^2) : |q - p| <= R }``, the lowest height
  above ``p`` at which a sphere of radius ``R`` touches no terrain grid point: a grey dilation
  with a non-flat spherical structuring element.

The structuring element (the disc ``|q - p| <= R``, or ``R_h``) is clipped at the map edge.
Where it holds a no-data cell the terrain is unknown, so ``S`` is NaN there (and such cells are
not passable, as docs/method.md section 2 requires).

The kernels are exact. The spherical one splits the disc by row offset ``d``: every input row
is dilated once per offset by the 1-D spherical cap of that offset (contiguous loops that the
compiler vectorises), and ``S(i, j)`` is the maximum over ``d`` of those row results, read from a
ring buffer of ``2r + 1`` rows. The horizontal one is the same dilation with a flat disc.
"""

from __future__ import annotations

import functools
import math

import dask.array as da
import numpy as np
import xarray as xr
from llvmlite import ir
from numba.core import types
from numba.core.extending import intrinsic

from ..dem.canonical import check_dem
from ..exceptions import InvalidParameterError
from ..params import MAPS, check_clearance
from ..runtime.jit import njit

# --------------------------------------------------------------------------- structuring element


def disc_widths(radius_m: float, a: float) -> np.ndarray:
    """Half-widths of the disc ``|q - p| <= radius_m`` per row offset, in cells.

    ``widths[d]`` is the largest ``w`` with ``a^2 (d^2 + w^2) <= radius_m^2``; the disc spans row
    offsets ``-r .. r`` with ``r = len(widths) - 1``.
    """
    r = int(math.floor(radius_m / a))
    while (r + 1) * (r + 1) * a * a <= radius_m * radius_m:
        r += 1
    while r > 0 and r * r * a * a > radius_m * radius_m:
        r -= 1
    widths = np.empty(r + 1, dtype=np.int64)
    for d in range(r + 1):
        w = int(math.floor(math.sqrt(max(radius_m * radius_m / (a * a) - d * d, 0.0))))
        while (d * d + (w + 1) * (w + 1)) * a * a <= radius_m * radius_m:
            w += 1
        while w > 0 and (d * d + w * w) * a * a > radius_m * radius_m:
            w -= 1
        widths[d] = w
    return widths


def sphere_heights(radius_m: float, a: float, widths: np.ndarray) -> np.ndarray:
    """``b[d, k] = sqrt(R^2 - a^2 (d^2 + k^2))`` inside the disc, -inf outside."""
    r = widths.size - 1
    b = np.full((r + 1, r + 1), -np.inf)
    for d in range(r + 1):
        k = np.arange(widths[d] + 1)
        b[d, : widths[d] + 1] = np.sqrt(
            np.maximum(radius_m * radius_m - a * a * (d * d + k * k), 0.0)
        )
    return b


# --------------------------------------------------------------------------- kernels


@intrinsic
def _maximum(typingctx, x, y):
    """The larger of two floats (LLVM's ``llvm.maximum`` with the flags ``nnan nsz``: a NaN or
    a zero's sign may give either operand; without them x86 has no such instruction, and a
    maximum took 3 blends and a compare besides its ``vmaxpd``).

    Why not ``if v > dst[j]: dst[j] = v``: the compiler vectorised that (and the equivalent
    ``max`` or select, whose result is the value already stored when the sum is NaN) as a
    store through a mask, ``vmaskmovpd``, one instruction on Intel and microcoded on AMD Zen 3,
    where the spherical map took five times as long; ``maximum`` stores every element (a plain
    store) (CHANGELOG.md, "Measurements"). A NaN
    comes only from a no-data cell and whatever it gives reaches only the cells whose disc
    holds it, which are NaN in the map anyway (``_nodata_near``); every sum ``z + b`` has
    ``b >= +0.0``, so a -0.0 of the DEM is +0.0 by then (see ``_row_dilation``): the map is the
    same bit for bit."""

    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(args[0].type, [args[0].type, args[1].type])
        fn = builder.module.declare_intrinsic("llvm.maximum", [args[0].type], fnty)
        return builder.call(fn, args, fastmath=("nnan", "nsz"))

    return x(x, y), codegen


@intrinsic
def _bits(typingctx, x):
    """A float32's bits as an int32."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


@intrinsic
def _float(typingctx, x):
    """An int32's bits as a float32."""

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@njit(cache=True)
def _up32(v):
    """The least float32 at or above the float64 ``v`` (NaN and infinities as they are): the
    safety surface is a lowest safe height, so it is rounded up, never below the exact value.
    Rounding up is monotone, so the maximum of rounded values is the rounded maximum. The next
    float32 above a rounded-down ``f`` is one step of its bits away from zero when ``f >= +0``
    and towards zero when ``f < 0`` (``f`` is never -0.0 there: a ``v`` that rounds to -0.0 is
    at most 0); in integers and selects, so that a loop of it vectorises."""
    f = np.float32(v)
    b = _bits(f)
    step = np.int32(1) if b >= 0 else np.int32(-1)
    return _float(b + step) if np.float64(f) < v else f


@njit(cache=True)
def _max_into(dst, src, add):
    """``dst[j] = max(dst[j], src[j] + add)`` (a NaN: see :func:`_maximum`); two distinct
    contiguous views, so it vectorises."""
    for j in range(dst.size):
        dst[j] = _maximum(dst[j], src[j] + add)


@njit(nogil=True, cache=True)
def _nodata_near(z, widths):
    """True where the disc given by ``widths`` around a cell holds a NaN cell; an empty array
    when ``z`` holds no NaN (the usual case: one pass, no memory; the per-row counts of the
    general case are 4 bytes a cell of fresh memory)."""
    rows, cols = z.shape
    r = widths.size - 1
    anynan = False
    for i in range(rows):
        for j in range(cols):
            anynan |= z[i, j] != z[i, j]
        if anynan:
            break
    if not anynan:
        return np.zeros((0, 0), dtype=np.bool_)
    near = np.zeros((rows, cols), dtype=np.bool_)
    count = np.zeros((rows, cols + 1), dtype=np.int32)  # row prefix sums of NaN cells
    for i in range(rows):
        for j in range(cols):
            isnan = z[i, j] != z[i, j]
            count[i, j + 1] = count[i, j] + (1 if isnan else 0)
    for i in range(rows):
        for j in range(cols):
            for d in range(-r, r + 1):
                ii = i + d
                if ii < 0 or ii >= rows:
                    continue
                w = widths[abs(d)]
                lo = max(j - w, 0)
                hi = min(j + w + 1, cols)
                if count[ii, hi] - count[ii, lo] > 0:
                    near[i, j] = True
                    break
    return near


@njit(nogil=True, cache=True)
def _pair_maxima(zr, kmax, m):
    """``m[k, j] = max(zr[j - k], zr[j + k])`` for ``k = 1 .. kmax`` (``kmax < zr.size``): the
    one that exists at the row's ends, -inf where neither does (a NaN: see ``_maximum``). One
    pass over the row's middle, where both exist."""
    cols = zr.size
    for k in range(1, kmax + 1):
        n = cols - k
        mk = m[k]
        for j in range(min(k, n)):
            mk[j] = zr[j + k]  # the left neighbour j - k does not exist
        for j in range(n, k):
            mk[j] = -np.inf  # neither exists (k > cols / 2)
        for j in range(max(n, k), cols):
            mk[j] = zr[j - k]  # the right neighbour j + k does not exist
        _max_pair(mk[k:n], zr[: n - k], zr[2 * k :])


@njit(cache=True)
def _max_of(dst, src):
    """``dst[j] = max(dst[j], src[j])``; two distinct contiguous views, so it vectorises (the
    values are sums ``z + b`` with ``b >= +0.0``, never -0.0: adding +0.0 first, as
    :func:`_max_into` does, would change nothing)."""
    for j in range(dst.size):
        dst[j] = _maximum(dst[j], src[j])


@njit(cache=True)
def _max_pair(dst, x, y):
    """``dst[j] = max(x[j], y[j])``; three distinct contiguous views, so it vectorises."""
    for j in range(dst.size):
        dst[j] = _maximum(x[j], y[j])


@njit(nogil=True, cache=True)
def _row_dilation(zr, m, widths, b, e, t):
    """``t[j] = max_k zr[j + k] + b[e, |k|]`` over ``|k| <= widths[e]`` (clipped to the row),
    from the pair maxima ``m`` (:func:`_pair_maxima`): ``fl(max(x, y) + c) = max(fl(x + c),
    fl(y + c))``, as rounding is monotone, so each offset ``k`` takes one maximum, not two.
    (Of a -0.0 and a +0.0, ``m`` may hold either; ``b`` is >= +0.0 and ``-0.0 + c == +0.0 + c``
    for such ``c``, so that changes no sum.)"""
    cols = zr.size
    bb = b[e, 0]
    for j in range(cols):
        t[j] = zr[j] + bb
    for k in range(1, min(widths[e], cols - 1) + 1):
        _max_into(t, m[k], b[e, k])


@njit(nogil=True, cache=True)
def _dilate(z, widths, b):
    """Exact grey dilation of ``z`` by the structuring function ``b`` on the disc ``widths``.

    ``b[d, k]`` is the height added for row offset ``d`` and column offset ``k`` (the spherical
    cap, or zeros for the flat disc); by row offsets:

    ``S(i, j) = max_d T_|d|(i + d, j)`` with ``T_e(row, j) = max_k z(row, j + k) + b(e, k)``.
    Each input row's ``T_e`` (e = 0..r) is computed once, from the row's pair maxima (one
    maximum per column offset and its mirror, :func:`_row_dilation`, faster than two passes,
    and faster still with the flags of :func:`_maximum`), and
    kept in a ring buffer of 2r + 1 rows. Candidates are summed in float64; storing ``T`` as
    float32 rounds each maximum up once (:func:`_up32`; rounding is monotone, so the max of
    rounded values is the rounded max).
    """
    rows, cols = z.shape
    r = widths.size - 1
    ring = 2 * r + 1
    near = _nodata_near(z, widths)
    tbuf = np.empty((ring, r + 1, cols), dtype=np.float32)
    zr = np.empty(cols, dtype=np.float64)
    kmax = min(r, cols - 1)
    m = np.empty((kmax + 1, cols), dtype=np.float64)
    t = np.empty(cols, dtype=np.float64)
    acc = np.empty(cols, dtype=np.float32)
    out = np.empty((rows, cols), dtype=np.float32)
    for row in range(rows + r):
        if row < rows:
            for j in range(cols):
                zr[j] = z[row, j]
            _pair_maxima(zr, kmax, m)
            slot = row % ring
            for e in range(r + 1):
                _row_dilation(zr, m, widths, b, e, t)
                kept = tbuf[slot, e]
                for j in range(cols):  # rounds each maximum up to float32 once
                    kept[j] = _up32(t[j])
        i = row - r
        if i < 0:
            continue
        # element loops, not slice copies: a slice copy compiles numba's text for a shape
        # mismatch (seconds of a new machine's first compile in each process)
        first = tbuf[i % ring, 0]
        for j in range(cols):
            acc[j] = first[j]
        for d in range(1, r + 1):
            if i - d >= 0:
                _max_of(acc, tbuf[(i - d) % ring, d])
            if i + d < rows:
                _max_of(acc, tbuf[(i + d) % ring, d])
        if near.size == 0:
            for j in range(cols):
                out[i, j] = acc[j]
        else:
            for j in range(cols):
                out[i, j] = np.nan if near[i, j] else acc[j]
    return out


@njit(nogil=True, cache=True)
def _horizontal(z, widths, clearance):
    flat = np.zeros((widths.size, widths.size))
    out = _dilate(z, widths, flat)
    for i in range(out.shape[0]):
        for j in range(out.shape[1]):
            out[i, j] = _up32(np.float64(out[i, j]) + clearance)
    return out


@njit(nogil=True, cache=True)
def _vertical(z, clearance):
    out = np.empty(z.shape, dtype=np.float32)
    for i in range(z.shape[0]):
        for j in range(z.shape[1]):
            out[i, j] = _up32(np.float64(z[i, j]) + clearance)
    return out


# --------------------------------------------------------------------------- public API


def _vertical_block(block, clearance):
    return _vertical(block, clearance)


def _horizontal_block(block, widths, clearance):
    return _horizontal(block, widths, clearance)


def _dilate_block(block, widths, b):
    return _dilate(block, widths, b)


def _check_memory(dem: xr.DataArray, radius_m: float, a: float) -> None:
    """Refuse, before any compute, a structuring element too large for this machine: the
    kernel holds a block with its halo (float32, in and out, plus a ring buffer of rows) and
    the element's table (float64)."""
    import psutil

    r = int(radius_m // a)
    z = dem.data
    block = z.chunksize if isinstance(z, da.Array) else z.shape
    side = [min(n, c + 2 * r) for n, c in zip(dem.shape, block, strict=True)]
    need = 16 * side[0] * side[1] + 8 * (r + 1) ** 2
    have = psutil.virtual_memory().total
    if need > have // 2:
        raise InvalidParameterError(
            f"the safety map needs about {need / 2**30:.1f} GiB per task (a structuring element "
            f"of {r} cells: a clearance of {radius_m:g} m over cells of {a:g} m), more than half "
            f"of this machine's {have / 2**30:.1f} GiB; resample the DEM to larger cells "
            "(resolution), lower the clearance or use smaller chunks"
        )


def _map_overlap(z: da.Array, kernel, depth: int, meta) -> da.Array:
    """``kernel`` over ``z`` with a halo of ``depth`` cells, for any map size and chunking, in
    ``z``'s own chunks: an axis no longer than the halo is taken whole (it needs none), and
    chunks that map_overlap had to merge (thinner than the halo) are split back, so that the
    result writes to a store chunked like its input."""
    chunks = z.chunks
    halo = {ax: (0 if depth >= z.shape[ax] else depth) for ax in (0, 1)}
    whole = {ax: -1 for ax in (0, 1) if halo[ax] == 0 and depth > 0}
    if whole:
        z = z.rechunk(whole)
    if halo[0] == halo[1] == 0:
        data = z.map_blocks(kernel, dtype=np.float32, meta=meta)
    else:
        data = z.map_overlap(kernel, depth=halo, boundary="none", dtype=np.float32, meta=meta)
    return data if data.chunks == chunks else data.rechunk(chunks)


def block_kernel(method: str, clearance: float, horizontal_clearance: float, a: float):
    """``(kernel, depth)``: the safety surface of a block with a halo of ``depth`` cells (none
    at the map's edges) is ``kernel(haloed block)`` trimmed by the halo; arguments checked as
    :func:`safety_map` checks them."""
    # module-level functions bound with partial: a task pickles them by reference, so a
    # worker reuses its compiled kernels (a closure would carry the numba dispatcher by value,
    # and every new client would make the workers compile it again)
    if method == "vertical":
        return functools.partial(_vertical_block, clearance=clearance), 0
    if method == "horizontal":
        widths = disc_widths(horizontal_clearance, a)
        return (
            functools.partial(_horizontal_block, widths=widths, clearance=clearance),
            widths.size - 1,
        )
    widths = disc_widths(clearance, a)
    b = sphere_heights(clearance, a, widths)
    return functools.partial(_dilate_block, widths=widths, b=b), widths.size - 1


def safety_map(
    dem: xr.DataArray,
    method: str = MAPS.method.default,
    clearance: float = MAPS.clearance.default,
    horizontal_clearance: float | None = None,
) -> xr.DataArray:
    """The safety surface: the lowest height at which the vehicle keeps its clearance.

    Parameters
    ----------
    dem : xarray.DataArray
        Canonical elevation (see :func:`pipeline.open_dem`), numpy- or dask-backed.
    method : {"spherical", "horizontal", "vertical"}
        Clearance measured in 3-D (a sphere), horizontally (a disc) or vertically.
    clearance : float
        ``R`` in metres.
    horizontal_clearance : float, optional
        ``R_h`` for the horizontal method; defaults to ``clearance``.

    Returns
    -------
    xarray.DataArray
        ``safety`` (float32 metres), same coords as ``dem``; lazy for dask input. NaN where the
        structuring element holds no-data.

    Examples
    --------
    >>> dem = pipeline.synthetic_dem((500, 500), cell_size=30.0, chunks=256)  # doctest: +SKIP
    >>> S = safety_map(dem, "spherical", clearance=300.0)                     # doctest: +SKIP
    >>> bool((S >= dem + 300 - 1e-3).all())                                   # doctest: +SKIP
    True
    """
    a = check_dem(dem, floating=True)
    method = MAPS.method.check(method)
    clearance = check_clearance(clearance, a)
    if horizontal_clearance is None:
        horizontal_clearance = clearance
    horizontal_clearance = check_clearance(
        horizontal_clearance, a, "`horizontal_clearance`", MAPS.horizontal_clearance
    )
    if method != "vertical":
        radius = horizontal_clearance if method == "horizontal" else clearance
        _check_memory(dem, radius, a)

    kernel, depth = block_kernel(method, clearance, horizontal_clearance, a)
    z = dem.data
    if isinstance(z, da.Array):
        z = z.astype(np.float32)
        meta = np.empty((0, 0), dtype=np.float32)
        data = _map_overlap(z, kernel, depth, meta)
    else:
        data = kernel(np.ascontiguousarray(z, dtype=np.float32))
    attrs = {
        "long_name": f"{method} safety surface",
        "units": "m",
        "method": method,
        "clearance_m": clearance,
        "cell_size": a,
        "element_radius_cells": int(depth),
    }
    if method == "horizontal":
        attrs["horizontal_clearance_m"] = horizontal_clearance
    for key in ("crs_wkt",):
        if key in dem.attrs:
            attrs[key] = dem.attrs[key]
    return xr.DataArray(data, dims=dem.dims, coords=dem.coords, name="safety", attrs=attrs)


def passable(
    dem: xr.DataArray,
    safety: xr.DataArray,
    sea_level: float = MAPS.sea_level.default,
    surface_clearance: float | None = None,
) -> xr.DataArray:
    """Cells the vehicle may occupy (docs/method.md section 2).

    A cell is passable when its elevation is known and below ``sea_level`` (not land), no
    no-data cell lies within the safety map's structuring element (``safety`` is finite), and
    the safety surface leaves the vehicle submerged: ``S <= sea_level - surface_clearance``
    (``surface_clearance`` defaults to the safety map's clearance ``R``).

    Examples
    --------
    >>> ok = passable(dem, safety_map(dem))  # doctest: +SKIP
    """
    check_dem(dem, floating=True)
    if not isinstance(safety, xr.DataArray) or safety.shape != dem.shape:
        got = safety.shape if isinstance(safety, xr.DataArray) else type(safety).__name__
        raise InvalidParameterError(
            f"`safety` must be a DataArray of the DEM's shape "
            f"{dem.shape}, got {got}; build it with safety_map(dem)"
        )
    sea_level = MAPS.sea_level.check(sea_level)
    if surface_clearance is None:
        surface_clearance = float(safety.attrs.get("clearance_m", 0.0))
    surface_clearance = MAPS.surface_clearance.check(surface_clearance)
    return xr.DataArray(
        passable_cells(dem.data, safety.data, sea_level, surface_clearance),
        dims=dem.dims,
        coords=dem.coords,
        name="passable",
        attrs={
            "long_name": "passable cells",
            "sea_level_m": float(sea_level),
            "surface_clearance_m": surface_clearance,
            "safety_method": safety.attrs.get("method", "unknown"),
            "clearance_m": safety.attrs.get("clearance_m", float("nan")),
        },
    )


def passable_cells(z, s, sea_level: float, surface_clearance: float):
    """:func:`passable` on the arrays (numpy or dask) of elevation ``z`` and safety ``s``. The
    surface limit as the greatest float32 at or below it: ``s <= top`` exactly."""
    limit = float32_toward(sea_level - surface_clearance, -np.inf)
    return (z == z) & (z < sea_level) & (s == s) & (s <= limit)


def float32_toward(v: float, to: float) -> np.float32:
    """The float32 nearest ``v`` on the side of ``to`` (``+inf``: the least at or above it,
    ``-inf``: the greatest at or below it)."""
    f = np.float32(v)
    if (to > 0 and np.float64(f) < v) or (to < 0 and np.float64(f) > v):
        f = np.nextafter(f, np.float32(to))
    return f
