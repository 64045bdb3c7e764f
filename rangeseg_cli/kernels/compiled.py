"""Compiled (numba) kernels of Sec. V-1, V-2 and V-4 of Al-Hujazi & Sood (1990).

The fast paths of :func:`rangeseg_cli.stages.edges.detect_edges` (edge stage) and of
:func:`rangeseg_cli.stages.grow.fit_models` and :func:`rangeseg_cli.stages.grow.grow_pass`
(region growing). The numpy functions in :mod:`rangeseg_cli.stages.edges` and
:mod:`rangeseg_cli.stages.grow` are the reference: these kernels give bit-for-bit the
same AR values, moment sums and residuals, and hence exactly the same edge
maps, fits and labels, because every value is made of the same float64
operations in the same order (no fastmath, so no reassociation and no fused
multiply-add; per-region sums accumulate in raster order, as ``np.bincount``
does over ``np.nonzero``'s pixels).

Notes
-----
Edge stage. One pass of Sec. V (step 1, 2a or 2b) is one sweep down the image rows:

1. For each row and each of the four directions of Fig. 8, the reach of the
   adaptive mask along +d and -d (consecutive usable pixels, at most half the
   mask; Fig. 9), cut to the shorter side for ``"symmetric"`` truncation.
2. AR_d = |sum_k w_k z(p + k d) / sum_k w_k - z(p)| over the kept taps (eq. 3),
   summed as the reference does: centre tap, then +1, -1, +2, -2, ...
3. The AR rows of the last ``2 radius + 1`` rows are kept in a ring buffer;
   once row ``q + radius`` is done, row ``q`` gets the threshold and
   local-maximum test along each direction (ties within ``1e-9 (1 + AR)``
   count as maxima, as in :func:`rangeseg_cli.stages.edges.local_maximum`).

Passes 2a and 2b share one sweep (:func:`roof_passes`): 2b follows a few rows
behind 2a and takes over its AR rows, recomputing each direction's AR only in
the span of columns whose masks along that direction reach a 2a roof edge
(elsewhere the masks, and so the AR, are the same in both passes).

Memory beyond the inputs: one padded copy of the heights and two of the usable
mask, and a few row buffers; no per-direction image temporaries.

The per-row helpers of the passes (``_reach_row``, ``_ar_row``, ``_max_row`` and
the others compiled with :data:`_NO_REFCOUNTS`) only read and write arrays they are given,
through views, and allocate nothing, so they are compiled without numba's
reference counts (its ``_nrt`` target option): the atomic increments and
decrements of their row views took about 8 % of the edge stage at 128x128.

Region growing (Sec. V-4). :func:`run_moments` gathers, per label, the
pixel count, the centre and scale of the conditioning frame and the 15
moments ``sum u^a v^b`` (a + b <= 4) and 6 right-hand sides ``sum phi_i z`` of
the quadric's normal equations in three sweeps over the image (centre, then
spread, then moments), without any per-pixel temporaries;
:func:`run_sse` sums the squared residuals of solved fits in one more
sweep; :func:`grow_pass` is one simultaneous growing pass (8-neighbourhood
test and residual test fused).

Compile time. The first run after installing compiles every kernel it calls
(:mod:`rangeseg_cli.kernels.cache` has the figures), so the kernels are written
to compile little: each is compiled for one signature (callers pass
:data:`_ZERO`, an int64, where a literal ``0`` would have numba compile the
callee once more for the type ``Literal[int](0)``; the call sites cast arrays to
C-contiguous, writeable float64 or int32); helpers called from one place are
inlined into it (``inline="always"``: no compilation of their own); and loops
stand where slice assignment, ``np.full``, ``.max()`` or array arithmetic
would compile numba's generic implementations.

Importing this module imports numba and needs it; :mod:`rangeseg_cli.stages.edges`
imports it lazily and only when numba is installed.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numba import njit

from .cache import compile_ahead_when_cold
from .parallel import map_bands, row_bands

#: ``stages.grow.RCOND``: the conditioning bound of the region fits (a test checks it).
_RCOND = 1e-10

#: Options of the helpers that allocate nothing and only use views of the arrays they
#: are given: no reference counts (numba's ``_nrt`` target option; see the Notes).
_NO_REFCOUNTS: dict[str, Any] = {"_nrt": False}

#: 0 for the counters and offsets that kernels pass to other kernels: an int64 like
#: their other values, where a literal 0 would have the callee compiled once more (see
#: the Notes).
_ZERO: int = np.int64(0)  # type: ignore[assignment]

#: Row and column steps of the four directions of Fig. 8 (as ``edges.DIRECTIONS``).
_DY = np.array([0, 1, 1, 1], dtype=np.int64)
_DX = np.array([1, 0, 1, -1], dtype=np.int64)


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _reach_row(okp: np.ndarray, row: int, pad: int, dy: int, dx: int, half: int, c0: int,
               c1: int, run: np.ndarray, reach: np.ndarray) -> None:  # pragma: no cover
    """Consecutive usable pixels from each pixel (row, c0..c1-1) along (dy, dx), at most ``half``.

    Fig. 9: the adaptive mask stops before the first excluded pixel.
    ``okp`` is the usable mask padded by ``pad`` >= ``half`` with False;
    ``run`` and ``reach`` are row buffers (reach written at c0..c1-1).
    """
    n = c1 - c0
    run, reach = run[c0:c1], reach[c0:c1]  # loops from 0 vectorise
    for c in range(n):
        run[c] = 1
        reach[c] = 0
    for k in range(1, half + 1):
        src = okp[row + pad + k * dy, pad + k * dx + c0: pad + k * dx + c1]
        for c in range(n):
            run[c] &= src[c]
            reach[c] += run[c]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _den_table(w: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Sum of kept weights for each (reach +d, reach -d), added in the reference's order.

    The reference adds ``keep * w_k`` for every k (adding 0.0 where a tap is
    cut), so the sum depends only on the two reaches.
    """
    half = w.shape[0] // 2
    table = np.empty((half + 1, half + 1))
    for rp in range(half + 1):
        for rm in range(half + 1):
            den = w[half]
            for k in range(1, half + 1):
                den += (1.0 if rp >= k else 0.0) * w[half + k]
                den += (1.0 if rm >= k else 0.0) * w[half - k]
            table[rp, rm] = den
    return table


@njit(cache=True, nogil=True, error_model="numpy", **_NO_REFCOUNTS)
def _ar_row(zp: np.ndarray, okp: np.ndarray, row: int, pad: int, dy: int, dx: int,
            w: np.ndarray, den_table: np.ndarray, symmetric: bool, c0: int, c1: int,
            work: np.ndarray, num: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover
    """AR along (dy, dx) at (row, c0..c1-1) with the adaptive mask (eq. 3, Fig. 9).

    ``work`` holds four uint8 row buffers (run, reach +d, run, reach -d); ``num``
    a float64 row buffer; ``out`` receives the AR row's columns c0..c1-1 (0 at
    excluded pixels). Each pixel's value does not depend on the column range.
    """
    half = w.shape[0] // 2
    _reach_row(okp, row, pad, dy, dx, half, c0, c1, work[0], work[1])
    _reach_row(okp, row, pad, -dy, -dx, half, c0, c1, work[2], work[3])
    n = c1 - c0  # views from c0, so that the loops start at 0 and vectorise
    rp, rm, acc, res = work[1, c0:c1], work[3, c0:c1], num[c0:c1], out[c0:c1]
    if symmetric:
        for c in range(n):
            m = min(rp[c], rm[c])
            rp[c] = m
            rm[c] = m
    ok0 = okp[row + pad, pad + c0: pad + c1]
    z0 = zp[row + pad, pad + c0: pad + c1]
    for c in range(n):
        acc[c] = w[half] * (z0[c] if ok0[c] else 0.0)
    for k in range(1, half + 1):
        wp, wm = w[half + k], w[half - k]
        kk = np.uint8(k)
        zplus = zp[row + pad + k * dy, pad + k * dx + c0: pad + k * dx + c1]
        zminus = zp[row + pad - k * dy, pad - k * dx + c0: pad - k * dx + c1]
        for c in range(n):
            xp, xm = zplus[c], zminus[c]
            acc[c] += (xp if rp[c] >= kk else 0.0) * wp
            acc[c] += (xm if rm[c] >= kk else 0.0) * wm
    den = res  # the AR is written last: first hold the mask sums there
    for c in range(n):
        den[c] = den_table[rp[c], rm[c]]
    for c in range(n):
        x = z0[c]
        zc = x if ok0[c] else 0.0
        ar = abs(acc[c] / den[c] - zc)
        res[c] = ar if ok0[c] else 0.0


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _is_local_max(ring: np.ndarray, q: int, c: int, dy: int, dx: int, radius: int,
                  height: int, level: float) -> bool:  # pragma: no cover - compiled
    """Whether ``level`` is >= every AR within +-``radius`` of (q, c) along (dy, dx)."""
    nring = ring.shape[0]
    width = ring.shape[1]
    for k in range(1, radius + 1):
        for s in (1, -1):
            r, cc = q + s * k * dy, c + s * k * dx
            if 0 <= r < height and 0 <= cc < width and not level >= ring[r % nring, cc]:
                return False
    return True


@njit(cache=True, nogil=True, error_model="numpy", **_NO_REFCOUNTS)
def _max_row(ring: np.ndarray, q: int, dy: int, dx: int, radius: int, height: int,
             threshold: float, ok_row: np.ndarray, cand: np.ndarray, found_row: np.ndarray
             ) -> None:  # pragma: no cover - compiled
    """Mark pixels of row ``q`` whose AR is >= ``threshold`` and a maximum along (dy, dx).

    ``cand`` is a uint8 buffer of at least the row length, rounded up to 8 and
    zero beyond it: the candidates are flagged in one vectorised loop and then
    found eight at a time.
    """
    ar_row = ring[q % ring.shape[0]]
    width = ar_row.shape[0]
    for c in range(width):
        cand[c] = ok_row[c] & (ar_row[c] >= threshold)
    words = cand.view(np.uint64)
    for i in range(words.shape[0]):
        if words[i] == 0:
            continue
        for c in range(8 * i, min(8 * i + 8, width)):
            if cand[c]:
                # Ties within rounding error count as maxima (edges.local_maximum).
                ar = ar_row[c]
                level = ar + 1e-9 * (1.0 + ar)
                if _is_local_max(ring, q, c, dy, dx, radius, height, level):
                    found_row[c] = True


@njit(cache=True, nogil=True, error_model="numpy")
def edges_pass(zp: np.ndarray, okp: np.ndarray, pad: int, w: np.ndarray, threshold: float,
               radius: int, symmetric: bool) -> np.ndarray:  # pragma: no cover - compiled
    """One pass of Sec. V: AR in the four directions, threshold and local maximum, fused.

    Parameters
    ----------
    zp
        float64 (H + 2 pad, W + 2 pad) heights padded by ``pad``.
    okp
        bool, same shape: usable pixels (valid and not excluded), False in the padding.
    pad
        Padding width, >= ``len(w) // 2`` and >= ``radius``.
    w
        Odd-length normalised 1-D Gaussian.
    threshold
        Minimum AR of an edge.
    radius
        AR must be the maximum within +-``radius`` pixels along the direction.
    symmetric
        Cut both sides of the mask at the shorter reach (docs/REPRODUCTION.md,
        "Where the paper is vague").

    Returns
    -------
    numpy.ndarray
        bool (H, W): edges of this pass, never at an unusable pixel.
    """
    height, width = zp.shape[0] - 2 * pad, zp.shape[1] - 2 * pad
    nring = 2 * radius + 1
    ring = np.zeros((4, nring, width))
    work = np.empty((4, width), dtype=np.uint8)
    num = np.empty(width)
    cand = np.zeros(8 * ((width + 7) // 8), dtype=np.uint8)
    den_table = _den_table(w)
    found = np.zeros((height, width), dtype=np.bool_)
    for r in range(height + radius):
        if r < height:
            for d in range(4):
                _ar_row(zp, okp, r, pad, _DY[d], _DX[d], w, den_table, symmetric, _ZERO,
                        width, work, num, ring[d, r % nring])
        q = r - radius
        if q >= 0:
            ok_row = okp[q + pad, pad: pad + width]
            for d in range(4):
                _max_row(ring[d], q, _DY[d], _DX[d], radius, height, threshold, ok_row, cand,
                         found[q])
    return found


@njit(cache=True, nogil=True, error_model="numpy")
def absolute_residuals(zp: np.ndarray, okp: np.ndarray, pad: int, w: np.ndarray,
                       symmetric: bool) -> np.ndarray:  # pragma: no cover - compiled
    """AR of eq. 3 in the four directions of Fig. 8, as a (4, H, W) float64 array.

    For tests and inspection (the passes never hold these images); arguments as
    in :func:`edges_pass`.
    """
    height, width = zp.shape[0] - 2 * pad, zp.shape[1] - 2 * pad
    out = np.zeros((4, height, width))
    work = np.empty((4, width), dtype=np.uint8)
    num = np.empty(width)
    den_table = _den_table(w)
    for r in range(height):
        for d in range(4):
            _ar_row(zp, okp, r, pad, _DY[d], _DX[d], w, den_table, symmetric, _ZERO, width,
                    work, num, out[d, r])
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _ar_rows(zp: np.ndarray, okp: np.ndarray, row: int, pad: int, w: np.ndarray,
             den_table: np.ndarray, symmetric: bool, c0: int, c1: int, work: np.ndarray,
             num: np.ndarray, ring: np.ndarray) -> None:  # pragma: no cover - compiled
    """AR of (row, c0..c1-1) in the four directions into ``ring[d, row % depth]``."""
    depth = ring.shape[1]
    for d in range(4):
        _ar_row(zp, okp, row, pad, _DY[d], _DX[d], w, den_table, symmetric, c0, c1, work, num,
                ring[d, row % depth])


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _max_rows(ring: np.ndarray, q: int, radius: int, height: int, threshold: float,
              ok_row: np.ndarray, cand: np.ndarray, found_row: np.ndarray
              ) -> None:  # pragma: no cover - compiled
    """Edges of row ``q`` in any of the four directions (threshold and local maximum)."""
    for d in range(4):
        _max_row(ring[d], q, _DY[d], _DX[d], radius, height, threshold, ok_row, cand,
                 found_row)


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _exclude_row(found_row: np.ndarray, ok_row: np.ndarray, q: int, half: int,
                 lo: np.ndarray, hi: np.ndarray) -> None:  # pragma: no cover - compiled
    """Make the edges of row ``q`` unusable; widen the spans whose AR they change.

    An edge at (q, c) changes the AR along direction d (Fig. 8) of the pixels
    (q, c) - k d, k = -``half``..``half`` (its own, now excluded, and those
    whose mask reaches it, Fig. 9): columns ``lo[d, r]..hi[d, r]`` of row r
    hold every such pixel of that row.
    """
    height, width = lo.shape[1], found_row.shape[0]
    count = 0
    for c in range(width):
        count += found_row[c]
    if count == 0:
        return
    for c in range(width):
        if not found_row[c]:
            continue
        ok_row[c] = False
        for d in range(4):
            dy, dx = _DY[d], _DX[d]
            for k in range(-half, half + 1):
                r, cc = q - k * dy, c - k * dx
                if 0 <= r < height and 0 <= cc < width:
                    lo[d, r] = min(lo[d, r], cc)
                    hi[d, r] = max(hi[d, r], cc)


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _second_pass_row(zp: np.ndarray, okp: np.ndarray, row: int, pad: int, w: np.ndarray,
                     den_table: np.ndarray, symmetric: bool, lo: np.ndarray, hi: np.ndarray,
                     work: np.ndarray, num: np.ndarray, ring: np.ndarray
                     ) -> None:  # pragma: no cover - compiled
    """Turn pass 2a's AR of ``row`` in ``ring`` into pass 2b's, in place.

    The mask of a pixel (Fig. 9) reaches ``half`` pixels along each direction,
    so its AR along a direction changes only where an edge newly excluded by
    2a lies on that line within ``half`` pixels: only the columns
    ``lo[d, row]..hi[d, row]`` of direction d (:func:`_exclude_row`) are
    recomputed, each pixel's AR being independent of the columns computed
    with it.
    """
    depth = ring.shape[1]
    for d in range(4):
        if lo[d, row] <= hi[d, row]:
            _ar_row(zp, okp, row, pad, _DY[d], _DX[d], w, den_table, symmetric, lo[d, row],
                    hi[d, row] + 1, work, num, ring[d, row % depth])


@njit(cache=True, nogil=True, error_model="numpy")
def roof_passes(zp: np.ndarray, okp: np.ndarray, pad: int, w: np.ndarray, threshold_a: float,
                threshold_b: float, radius: int, symmetric: bool
                ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Passes 2a and 2b of Sec. V-2 in one sweep down the rows.

    Pass 2a is :func:`edges_pass`. Pass 2b, which excludes the roof edges of
    2a as well, follows ``lag`` rows behind: once the 2a edges within reach of
    its masks are known and 2a no longer needs the row's AR, which it then
    updates in place near those edges only (:func:`_second_pass_row`). The
    maps are those of two separate passes. Arguments as for
    :func:`edges_pass` (``okp``: step edges already excluded).

    Returns
    -------
    roof_a, roof_b
        bool (H, W) edges of passes 2a and 2b.
    """
    height, width = zp.shape[0] - 2 * pad, zp.shape[1] - 2 * pad
    lag = max(w.shape[0] // 2, radius + 1)
    ring = np.zeros((4, 3 * radius + lag + 1, width))
    work = np.empty((4, width), dtype=np.uint8)
    num = np.empty(width)
    cand = np.zeros(8 * ((width + 7) // 8), dtype=np.uint8)
    den_table = _den_table(w)
    okp_b = okp.copy()
    lo = np.empty((4, height), dtype=np.int64)  # columns of 2b's AR to recompute
    hi = np.empty((4, height), dtype=np.int64)
    for d in range(4):
        for q in range(height):
            lo[d, q], hi[d, q] = width, -1
    roof_a = np.zeros((height, width), dtype=np.bool_)
    roof_b = np.zeros((height, width), dtype=np.bool_)
    for r in range(height + 2 * radius + lag):
        if r < height:
            _ar_rows(zp, okp, r, pad, w, den_table, symmetric, _ZERO, width, work, num, ring)
        qa = r - radius
        if 0 <= qa < height:  # Step 2a: roof edges, high threshold (Sec. V-2a)
            _max_rows(ring, qa, radius, height, threshold_a, okp[qa + pad, pad: pad + width],
                      cand, roof_a[qa])
            _exclude_row(roof_a[qa], okp_b[qa + pad, pad: pad + width], qa, w.shape[0] // 2,
                         lo, hi)
        sb = qa - lag
        if 0 <= sb < height:  # Step 2b: 2a's roof edges excluded too (Sec. V-2b)
            _second_pass_row(zp, okp_b, sb, pad, w, den_table, symmetric, lo, hi, work, num,
                             ring)
        qb = sb - radius
        if 0 <= qb < height:
            _max_rows(ring, qb, radius, height, threshold_b, okp_b[qb + pad, pad: pad + width],
                      cand, roof_b[qb])
    return roof_a, roof_b


def _pad(z: np.ndarray, pad: int) -> tuple[np.ndarray, np.ndarray]:
    """Heights padded with 0 and the usable (not NaN) mask padded with False."""
    height, width = z.shape
    zp = np.zeros((height + 2 * pad, width + 2 * pad))
    okp = np.zeros((height + 2 * pad, width + 2 * pad), dtype=np.bool_)
    zp[pad: pad + height, pad: pad + width] = z
    np.logical_not(np.isnan(z), out=okp[pad: pad + height, pad: pad + width])
    return zp, okp


def _exclude(okp: np.ndarray, pad: int, edges: np.ndarray) -> None:
    """Mark ``edges`` as unusable for later passes (Sec. V-2: masks stop before them)."""
    height, width = edges.shape
    okp[pad: pad + height, pad: pad + width] &= ~edges


def edge_maps(z: np.ndarray, w_step: np.ndarray, step_threshold: float, w_roof: np.ndarray,
              threshold_a: float, threshold_b: float, radius: int, step_symmetric: bool,
              roof_symmetric: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1, 2a and 2b of Sec. V in three compiled passes (see detect_edges_numba).

    Returns
    -------
    step, roof_a, roof_b
        bool (H, W) maps, as :func:`rangeseg_cli.stages.edges.step_edges` and
        :func:`rangeseg_cli.stages.edges.roof_edges` give them.
    """
    pad = max(w_step.shape[0] // 2, w_roof.shape[0] // 2, radius, 1)
    zp, okp = _pad(z, pad)
    # Step 1: step edges, small filter, invalid pixels excluded (Sec. V-1)
    step = edges_pass(zp, okp, pad, w_step, step_threshold, 1, step_symmetric)
    # Steps 2a and 2b: roof edges, large filter, step edges (and for 2b the edges of 2a)
    # excluded (Sec. V-2)
    _exclude(okp, pad, step)
    roof_a, roof_b = roof_passes(zp, okp, pad, w_roof, threshold_a, threshold_b, radius,
                                 roof_symmetric)
    return step, roof_a, roof_b


def detect_edges_numba(z: np.ndarray, w_step: np.ndarray, step_threshold: float,
                       w_roof: np.ndarray, threshold_a: float, threshold_b: float,
                       radius: int, truncation: str
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1 and 2 of Sec. V with the compiled kernels.

    Parameters
    ----------
    z
        (H, W) heights, NaN where invalid.
    w_step, w_roof
        The small (Sec. V-1) and large (Sec. V-2) 1-D Gaussians.
    step_threshold, threshold_a, threshold_b
        AR thresholds of steps 1, 2a and 2b.
    radius
        ``roof.search_radius`` (step 1 uses 1).
    truncation
        ``"symmetric"`` or ``"one-sided"``, for all three passes.

    Returns
    -------
    step, roof_a, roof_b
        bool (H, W) edge maps; exactly those of the numpy reference.
    """
    # One argument type per parameter (C-contiguous, writeable float64 arrays), so that
    # one cached compilation serves all calls, read-only or float32 inputs included.
    symmetric = truncation == "symmetric"
    z = np.require(z, np.float64, ["C", "W"])
    w_step = np.ascontiguousarray(w_step, dtype=np.float64)
    w_roof = np.ascontiguousarray(w_roof, dtype=np.float64)
    if len(row_bands(z.shape[0], z.shape[1], 0)) > 1:
        return edge_maps_in_bands(z, w_step, float(step_threshold), w_roof, float(threshold_a),
                                  float(threshold_b), int(radius), symmetric)
    return edge_maps(z, w_step, float(step_threshold), w_roof, float(threshold_a),
                     float(threshold_b), int(radius), symmetric, symmetric)


def edge_maps_in_bands(z: np.ndarray, w_step: np.ndarray, step_threshold: float,
                       w_roof: np.ndarray, threshold_a: float, threshold_b: float, radius: int,
                       symmetric: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`edge_maps` with each pass on row bands at once (``parallel.map_bands``).

    A pass's edges at a row depend on the padded rows within reach of it
    only: the AR reads ``len(w) // 2`` rows either side (eq. 3, Fig. 8), the
    local maximum ``radius`` rows of AR; pass 2b reads pass 2a's edges
    within its mask's reach. So each band runs the pass on its rows and
    ``margin`` more either side (the rows of the padded image, real data
    inside the image), and keeps its own rows: exactly the maps of one call.
    """
    height, width = z.shape
    pad = max(w_step.shape[0] // 2, w_roof.shape[0] // 2, radius, 1)
    zp, okp = _pad(z, pad)
    step = np.empty((height, width), dtype=np.bool_)
    roof_a = np.empty((height, width), dtype=np.bool_)
    roof_b = np.empty((height, width), dtype=np.bool_)

    def step_band(first: int, stop: int, lo: int, hi: int) -> None:
        found = edges_pass(zp[lo: hi + 2 * pad], okp[lo: hi + 2 * pad], pad, w_step,
                           step_threshold, 1, symmetric)
        step[first:stop] = found[first - lo: stop - lo]

    def roof_band(first: int, stop: int, lo: int, hi: int) -> None:
        a, b = roof_passes(zp[lo: hi + 2 * pad], okp[lo: hi + 2 * pad], pad, w_roof,
                           threshold_a, threshold_b, radius, symmetric)
        roof_a[first:stop] = a[first - lo: stop - lo]
        roof_b[first:stop] = b[first - lo: stop - lo]

    map_bands(step_band, height, width, 2)
    _exclude(okp, pad, step)
    # 2b's maxima (radius) of AR whose masks (half) see 2a's maxima (radius) of AR
    map_bands(roof_band, height, width, 2 * radius + w_roof.shape[0] // 2 + 2)
    return step, roof_a, roof_b


# --------------------------------------------------------------------------- Sec. V-4


@njit(cache=True, nogil=True, error_model="numpy")
def run_moments(z: np.ndarray, runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                n: int, r0: int, c0: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                           np.ndarray]:  # pragma: no cover - compiled
    """Per-region frames and moment sums of the quadric fits (Sec. V-4), in three sweeps.

    The same float64 operations, in the same (raster) order, as the numpy
    reference ``rangeseg_cli.stages.grow._frames`` and ``_moment_sums``.
    ``grow.region_fits`` makes the runs once for this and :func:`run_sse`.

    Parameters
    ----------
    z
        float64 (H, W) heights.
    runs
        The :func:`fitted_runs` of the labels 0..n (or :func:`union_runs`).
    n
        Largest label.
    r0, c0
        Image row and column of ``z[0, 0]`` when ``z`` is a crop: frames and
        sums are those of the whole image (the same pixels in the same order,
        so the same bits) when the crop holds every label.

    Returns
    -------
    counts, cx, cy, scale
        float64 (n+1,): pixels, centre column and row, scale of the frame
        ``u = (x - cx) / scale``, ``v = (y - cy) / scale``.
    sums
        float64 (n+1, 5, 5): ``sum u^a v^b`` at [a, b] for a + b <= 4 (0 elsewhere).
    rhs
        float64 (n+1, 6): ``sum phi_i z`` for phi = (1, u, v, u^2, u v, v^2).
    """
    counts, cx, cy = _region_centres(runs, n, r0, c0)
    safe = np.empty(n + 1)
    for lab in range(n + 1):
        safe[lab] = max(counts[lab], 1.0)
    scale = _region_scale(runs, cx, cy, safe, r0, c0)
    sums, rhs = _region_sums(z, runs, cx, cy, scale, r0, c0)
    return counts, cx, cy, scale, sums, rhs


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _run_end(labels: np.ndarray, r: int, c: int) -> int:  # pragma: no cover - compiled
    """One past the last column of the run of equal labels starting at (r, c)."""
    lab = labels[r, c]
    width = labels.shape[1]
    end = c + 1
    while end < width and labels[r, end] == lab:
        end += 1
    return end


@njit(cache=True, nogil=True, error_model="numpy")
def fitted_runs(z: np.ndarray, labels: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Runs of one positive label at finite heights along the rows, in raster order.

    (row, first column, stop column, label) of each; a run ends where the
    label changes or a height is not finite. The sweeps of
    :func:`run_moments` and :func:`run_sse` visit the fitted pixels
    run by run, in raster order, as the reference does pixel by pixel. Per
    row, the starts and ends are flagged in vectorised loops and found
    eight at a time; one sweep counts the runs, a second records them.
    """
    height, width = labels.shape
    fit = np.zeros(width + 1, dtype=np.uint8)  # fit[width] = 0: every run ends
    starts = np.zeros(8 * ((width + 8) // 8), dtype=np.uint8)
    ends = np.zeros(8 * ((width + 8) // 8), dtype=np.uint8)
    count = 0
    for r in range(height):
        count += _run_flags(z[r], labels[r], fit, starts, ends)
    rows = np.empty(count, dtype=np.int64)
    first = np.empty(count, dtype=np.int64)
    stop = np.empty(count, dtype=np.int64)
    labs = np.empty(count, dtype=np.int64)
    k = _ZERO
    for r in range(height):
        if _run_flags(z[r], labels[r], fit, starts, ends) == 0:
            continue
        _put_flagged(ends, stop, k)
        j = _put_flagged(starts, first, k)
        for i in range(k, j):
            rows[i], labs[i] = r, labels[r, first[i]]
        k = j
    return rows, first, stop, labs


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _run_flags(zr: np.ndarray, lab: np.ndarray, fit: np.ndarray, starts: np.ndarray,
               ends: np.ndarray) -> int:  # pragma: no cover - compiled
    """Flag where the runs of :func:`fitted_runs` of one row start and end; their number.

    ``starts[c]``: a run begins at column c; ``ends[c]``: one ends just
    before column c (c up to the row's width).
    """
    width = lab.shape[0]
    for c in range(width):
        fit[c] = (lab[c] > 0) & np.isfinite(zr[c])
    count = 0
    starts[0] = fit[0]
    ends[0] = 0
    for c in range(1, width):
        change = lab[c] != lab[c - 1]
        starts[c] = fit[c] & ((fit[c - 1] == 0) | change)
        ends[c] = fit[c - 1] & ((fit[c] == 0) | change)
        count += starts[c]
    ends[width] = fit[width - 1] if width > 0 else 0
    return count + starts[0]


@njit(cache=True, nogil=True, error_model="numpy", inline="always", **_NO_REFCOUNTS)
def _put_flagged(flags: np.ndarray, out: np.ndarray, k: int) -> int:  # pragma: no cover
    """Write the indices of the set bytes of ``flags`` (length a multiple of 8) from ``out[k]``.

    Found eight at a time, ascending; returns the index after the last written.
    """
    words = flags.view(np.uint64)
    for i in range(words.shape[0]):
        if words[i] != 0:
            for c in range(8 * i, 8 * i + 8):
                if flags[c]:
                    out[k] = c
                    k += 1
    return k


@njit(cache=True, nogil=True, error_model="numpy")
def union_runs(z: np.ndarray, labels: np.ndarray, pairs: np.ndarray, boxes: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """:func:`fitted_runs` of regions i and j together, for each pair p = (i, j): label p + 1.

    ``boxes[p]`` (first row, stop row, first column, stop column) holds both
    regions. Per pair, the runs of the pixels of either region at finite
    heights, in raster order: a run spans the two where they meet along a
    row, as when the pair's pixels are one label. Pairs may share regions
    (the runs overlap): :func:`run_moments` and :func:`run_sse` sum each
    label's runs in their order, so each pair gets the sums of its own pixels
    fitted alone, bit for bit. One sweep counts the runs, a second records them.
    """
    none = np.empty(0, dtype=np.int64)
    count = _union_sweep(z, labels, pairs, boxes, (none, none, none, none), False)
    runs = (np.empty(count, dtype=np.int64), np.empty(count, dtype=np.int64),
            np.empty(count, dtype=np.int64), np.empty(count, dtype=np.int64))
    _union_sweep(z, labels, pairs, boxes, runs, True)
    return runs


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _union_sweep(z: np.ndarray, labels: np.ndarray, pairs: np.ndarray, boxes: np.ndarray,
                 runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], write: bool
                 ) -> int:  # pragma: no cover - compiled
    """The runs of :func:`union_runs`, written to ``runs`` when ``write``; their number."""
    rows, first, stop, labs = runs
    k = 0
    for p in range(pairs.shape[0]):
        i, j = pairs[p, 0], pairs[p, 1]
        for r in range(boxes[p, 0], boxes[p, 1]):
            c, end = boxes[p, 2], boxes[p, 3]
            while c < end:
                a = c
                while c < end and (labels[r, c] == i or labels[r, c] == j) \
                        and np.isfinite(z[r, c]):
                    c += 1
                if c == a:
                    c += 1
                    continue
                if write:
                    rows[k], first[k], stop[k], labs[k] = r, a, c, p + 1
                k += 1
    return k


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _region_centres(runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray], n: int,
                    r0: int, c0: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Sweep 1 of :func:`run_moments`: pixel count, centre column and row per label.

    The sums are of integers, exact in any order (below 2^53), so they are
    kept as integers (a run's columns summed in closed form).
    """
    rows, first, stop, labs = runs
    counts = np.zeros(n + 1, dtype=np.int64)
    sx = np.zeros(n + 1, dtype=np.int64)
    sy = np.zeros(n + 1, dtype=np.int64)
    for k in range(rows.shape[0]):
        lab, a, b = labs[k], first[k], stop[k]
        length = b - a
        counts[lab] += length
        sx[lab] += length * (a + b - 1) // 2 + length * c0
        sy[lab] += length * (rows[k] + r0)
    pixels, cx, cy = np.empty(n + 1), np.empty(n + 1), np.empty(n + 1)
    for lab in range(n + 1):
        safe = np.float64(max(counts[lab], 1))
        pixels[lab] = np.float64(counts[lab])
        cx[lab] = sx[lab] / safe
        cy[lab] = sy[lab] / safe
    return pixels, cx, cy


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _region_scale(runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                  cx: np.ndarray, cy: np.ndarray, safe: np.ndarray, r0: int, c0: int
                  ) -> np.ndarray:  # pragma: no cover - compiled
    """Sweep 2 of :func:`run_moments`: RMS spread about the centre, at least 1.

    A run is summed in registers, continuing the label's running sums in the
    same order as adding pixel by pixel.
    """
    rows, first, stop, labs = runs
    vx = np.zeros(cx.shape[0])
    vy = np.zeros(cx.shape[0])
    for k in range(rows.shape[0]):
        lab = labs[k]
        ax, ay, x0 = vx[lab], vy[lab], cx[lab]
        dy = (rows[k] + r0) - cy[lab]
        dy2 = dy * dy
        for cc in range(first[k], stop[k]):
            dx = (cc + c0) - x0
            ax += dx * dx
            ay += dy2
        vx[lab], vy[lab] = ax, ay
    for lab in range(vx.shape[0]):  # np.maximum(np.sqrt(...), 1.0), NaN kept
        spread = np.sqrt((vx[lab] + vy[lab]) / (2.0 * safe[lab]))
        vx[lab] = 1.0 if spread < 1.0 else spread
    return vx


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _region_sums(z: np.ndarray, runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
                 cx: np.ndarray, cy: np.ndarray, scale: np.ndarray, r0: int, c0: int
                 ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Sweep 3 of :func:`run_moments`: the monomial sums and right-hand sides.

    Run by run, summed in registers (as in :func:`_region_scale`); v and its
    powers are constant along a row.
    """
    rows, first, stop, labs = runs
    sums = np.zeros((cx.shape[0], 5, 5))
    rhs = np.zeros((cx.shape[0], 6))
    ubuf = np.empty(z.shape[1])
    for k in range(rows.shape[0]):
        lab, r, c, end = labs[k], rows[k], first[k], stop[k]
        x0, s = cx[lab], scale[lab]
        for cc in range(end - c):  # the run's u, divided in a vectorised loop
            ubuf[cc] = ((c + cc + c0) - x0) / s
        _sum_run(z, r, c, end, ubuf, ((r + r0) - cy[lab]) / s, sums[lab], rhs[lab])
    return sums, rhs


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sum_run(z: np.ndarray, r: int, c0: int, c1: int, us: np.ndarray, v: float,
             m: np.ndarray, q: np.ndarray) -> None:  # pragma: no cover - compiled
    """Add the pixels (r, c0..c1-1), all finite, to one label's sums ``m`` and ``rhs`` ``q``."""
    v2 = v * v
    v3, v4 = v2 * v, v2 * v2
    m00, m01, m02, m03, m04 = m[0, 0], m[0, 1], m[0, 2], m[0, 3], m[0, 4]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m20, m21, m22 = m[2, 0], m[2, 1], m[2, 2]
    m30, m31, m40 = m[3, 0], m[3, 1], m[4, 0]
    q0, q1, q2, q3, q4, q5 = q[0], q[1], q[2], q[3], q[4], q[5]
    for c in range(c0, c1):
        zz = z[r, c]
        u = us[c - c0]
        u2 = u * u
        u3, u4 = u2 * u, u2 * u2
        m00 += 1.0
        m01 += v
        m02 += v2
        m03 += v3
        m04 += v4
        m10 += u
        m11 += u * v
        m12 += u * v2
        m13 += u * v3
        m20 += u2
        m21 += u2 * v
        m22 += u2 * v2
        m30 += u3
        m31 += u3 * v
        m40 += u4
        q0 += zz
        q1 += u * zz
        q2 += v * zz
        q3 += u2 * zz
        q4 += u * v * zz
        q5 += v2 * zz
    m[0, 0], m[0, 1], m[0, 2], m[0, 3], m[0, 4] = m00, m01, m02, m03, m04
    m[1, 0], m[1, 1], m[1, 2], m[1, 3] = m10, m11, m12, m13
    m[2, 0], m[2, 1], m[2, 2] = m20, m21, m22
    m[3, 0], m[3, 1], m[4, 0] = m30, m31, m40
    q[0], q[1], q[2], q[3], q[4], q[5] = q0, q1, q2, q3, q4, q5


@njit(cache=True, nogil=True, error_model="numpy")
def image_coefficients(coef: np.ndarray, cx: np.ndarray, cy: np.ndarray, scale: np.ndarray
                       ) -> np.ndarray:  # pragma: no cover - compiled
    """``grow._to_image_coefficients`` of F fits at once: the same operations, in one call.

    ``coef`` float64 (F, n+1, 6) in the frames (u, v) of :func:`run_moments`;
    returns the (F, n+1, 6) coefficients in image coordinates (x = col, y = row).
    """
    out = np.empty_like(coef)
    for f in range(coef.shape[0]):
        for i in range(coef.shape[1]):
            c0, c1, c2 = coef[f, i, 0], coef[f, i, 1], coef[f, i, 2]
            c3, c4, c5 = coef[f, i, 3], coef[f, i, 4], coef[f, i, 5]
            p = 1.0 / scale[i]
            u0, v0 = -cx[i] * p, -cy[i] * p  # u = p x + u0, v = p y + v0
            out[f, i, 0] = (c0 + c1 * u0 + c2 * v0 + c3 * u0 * u0 + c4 * u0 * v0
                            + c5 * v0 * v0)
            out[f, i, 1] = c1 * p + 2.0 * c3 * p * u0 + c4 * p * v0
            out[f, i, 2] = c2 * p + c4 * p * u0 + 2.0 * c5 * p * v0
            out[f, i, 3] = c3 * p * p
            out[f, i, 4] = c4 * p * p
            out[f, i, 5] = c5 * p * p
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def run_sse(z: np.ndarray, runs: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray],
            cx: np.ndarray, cy: np.ndarray, scale: np.ndarray, coef: np.ndarray, r0: int,
            c0: int) -> np.ndarray:  # pragma: no cover - compiled
    """Sum of squared residuals per region of several fits, in one sweep (Sec. V-4, e_A).

    Parameters
    ----------
    z, runs, r0, c0
        As in :func:`run_moments`.
    cx, cy, scale
        The frames of :func:`run_moments`.
    coef
        float64 (F, n+1, 6): F fits in frame coordinates (u, v).

    Returns
    -------
    numpy.ndarray
        float64 (F, n+1): ``sum (z - sum_i c_i phi_i)^2``, the fit summed
        term by term in the order of phi, as the reference does.
    """
    rows, first, stop, labs = runs
    nfit = coef.shape[0]
    out = np.zeros((nfit, coef.shape[1]))
    squares = np.empty(z.shape[1])
    for k in range(rows.shape[0]):
        lab, r, c, end = labs[k], rows[k], first[k], stop[k]
        x0, s = cx[lab], scale[lab]
        v = ((r + r0) - cy[lab]) / s
        for f in range(nfit):
            _squares_run(z[r, c:end], c + c0, x0, v, s, coef[f, lab], squares)
            total = out[f, lab]
            for i in range(end - c):  # added in order
                total += squares[i]
            out[f, lab] = total
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _squares_run(zrun: np.ndarray, c0: int, x0: float, v: float, s: float, a: np.ndarray,
                 out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Squared residuals of the pixels ``zrun`` (columns c0..) to the fit ``a`` (vectorised).

    The fit summed term by term in the order of phi, as the reference does.
    """
    a0, a1, a2, a3, a4, a5 = a[0], a[1], a[2], a[3], a[4], a[5]
    v2 = v * v
    for i in range(zrun.shape[0]):
        u = ((c0 + i) - x0) / s
        fit = a0 * 1.0
        fit = fit + a1 * u
        fit = fit + a2 * v
        fit = fit + a3 * (u * u)
        fit = fit + a4 * (u * v)
        fit = fit + a5 * v2
        res = zrun[i] - fit
        out[i] = res * res


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _single_neighbour(labels: np.ndarray, r: int, c: int) -> int:  # pragma: no cover
    """The one label in the 3x3 neighbourhood of (r, c); 0 for none or two and more."""
    height, width = labels.shape
    found = 0
    for rr in range(max(r - 1, 0), min(r + 2, height)):
        for cc in range(max(c - 1, 0), min(c + 2, width)):
            lab = labels[rr, cc]
            if lab > 0:
                if found == 0:
                    found = lab
                elif lab != found:
                    return 0
    return found


@njit(cache=True, nogil=True, error_model="numpy")
def heights(raw: np.ndarray, factor: float, invalid: float, check_invalid: bool,
            clipped: float, check_clipped: bool
            ) -> tuple[np.ndarray, int, float]:  # pragma: no cover - compiled
    """``rangeimage.to_heights`` of a plain numeric array in one pass: the same heights.

    Each raw value as float64, times ``factor`` (the scale, negated for
    depth); NaN where the value or the product is not finite, or the value
    equals ``invalid`` (when ``check_invalid``) or ``clipped`` (when
    ``check_clipped``). Returns the heights, the number of valid pixels and
    the largest |height| among them (0 if none).
    """
    height, width = raw.shape
    out = np.empty((height, width))
    valid = 0
    peak = 0.0
    for r in range(height):
        for c in range(width):
            v = np.float64(raw[r, c])
            bad = (not np.isfinite(v) or (check_invalid and v == invalid)
                   or (check_clipped and v == clipped))
            v = v * factor
            if bad or not np.isfinite(v):
                out[r, c] = np.nan
            else:
                out[r, c] = v
                valid += 1
                peak = max(peak, abs(v))
    return out, valid, peak


@njit(cache=True, nogil=True, error_model="numpy")
def valid_labels(z: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, int]:  # pragma: no cover
    """``np.where(np.isfinite(z), labels, 0).astype(np.int32)`` and its largest value (>= 0)."""
    height, width = z.shape
    out = np.empty((height, width), dtype=np.int32)
    top = np.int32(0)
    for r in range(height):
        for c in range(width):
            value = np.int32(labels[r, c]) if np.isfinite(z[r, c]) else np.int32(0)
            out[r, c] = value
            top = max(top, value)
    return out, int(top)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _doubled(a: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """A copy of 1-D ``a`` in an array twice as long (the second half uninitialised)."""
    out = np.empty(2 * a.shape[0], dtype=a.dtype)
    for i in range(a.shape[0]):
        out[i] = a[i]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def grow_pass(z: np.ndarray, valid: np.ndarray, labels: np.ndarray, coeffs: np.ndarray,
              limit: np.ndarray) -> int:  # pragma: no cover - compiled
    """One simultaneous growing pass (Sec. V-4), in place; the number of pixels labelled.

    A valid label-0 pixel whose 8-neighbourhood holds exactly one label L joins
    L when ``(z - f_L)^2 < limit[L]``, f_L evaluated as
    :func:`rangeseg_cli.stages.grow.evaluate_quadric` does. Decisions use the labels
    at the start of the pass (joins are written after the sweep).
    """
    height, width = labels.shape
    rows = np.empty(16, dtype=np.int64)
    cols = np.empty(16, dtype=np.int64)
    tags = np.empty(16, dtype=labels.dtype)
    joined = 0
    for r in range(height):
        for c in range(width):
            if labels[r, c] != 0 or not valid[r, c]:
                continue
            lab = _single_neighbour(labels, r, c)
            if lab == 0:
                continue
            a = coeffs[lab]
            x, y = float(c), float(r)
            fit = a[0] + a[1] * x + a[2] * y + a[3] * x * x + a[4] * x * y + a[5] * y * y
            res = z[r, c] - fit
            if res * res < limit[lab]:
                if joined == rows.shape[0]:
                    rows, cols, tags = _doubled(rows), _doubled(cols), _doubled(tags)
                rows[joined], cols[joined], tags[joined] = r, c, lab
                joined += 1
    for k in range(joined):
        labels[rows[k], cols[k]] = tags[k]
    return joined


# --------------------------------------------------------------------------- neighbours


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _half_offsets(reach: int) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """(dy, dx) of half of the offsets within ``reach``, in the reference's order."""
    count = reach + (2 * reach + 1) * reach
    dys = np.empty(count, dtype=np.int64)
    dxs = np.empty(count, dtype=np.int64)
    k = 0
    for dy in range(reach + 1):
        for dx in range(-reach, reach + 1):
            if dy > 0 or dx > 0:
                dys[k], dxs[k] = dy, dx
                k += 1
    return dys, dxs


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _label_runs(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray
                                              ]:  # pragma: no cover - compiled
    """Runs of equal positive labels along the rows: (row starts, first, stop, label).

    The runs of row r are ``first[k]..stop[k]-1`` for k in ``starts[r]..starts[r+1]-1``,
    left to right; label 0 makes no run. One sweep counts the runs, a second
    records them (arrays grown inside a loop would cost more than both).
    """
    height, width = labels.shape
    count = 0
    for r in range(height):
        row = labels[r]
        count += row[0] > 0
        for c in range(1, width):
            count += (row[c] != row[c - 1]) & (row[c] > 0)
    starts = np.zeros(height + 1, dtype=np.int64)
    first = np.empty(count, dtype=np.int64)
    stop = np.empty(count, dtype=np.int64)
    lab = np.empty(count, dtype=np.int64)
    k = 0
    for r in range(height):
        row = labels[r]
        for c in range(width):
            if c > 0 and row[c] == row[c - 1]:
                continue
            if c > 0 and row[c - 1] > 0:
                stop[k - 1] = c
            if row[c] > 0:
                first[k], lab[k] = c, row[c]
                k += 1
        if width > 0 and row[width - 1] > 0:
            stop[k - 1] = width
        starts[r + 1] = k
    return starts, first, stop, lab


@njit(cache=True, nogil=True, error_model="numpy")
def _run_pairs(labels: np.ndarray, reach: int, runs: tuple[np.ndarray, np.ndarray, np.ndarray,
                                                          np.ndarray],
               out: np.ndarray) -> int:  # pragma: no cover - compiled
    """The pairs of :func:`neighbour_pairs` into ``out`` (none: only counted); their number.

    For each of half of the offsets (dy, dx) and each row r, the runs of
    row r and those of row r + dy shifted by ``-dx`` are intersected left to
    right; where the labels differ every column of the overlap is a pair,
    in increasing column order.
    """
    height = labels.shape[0]
    dys, dxs = _half_offsets(reach)
    starts, first, stop, lab = runs
    write = out.shape[0] > 0
    j = 0
    for k in range(dys.shape[0]):
        dy, dx = dys[k], dxs[k]
        for r in range(height - dy):
            a, a_end = starts[r], starts[r + 1]
            b, b_end = starts[r + dy], starts[r + dy + 1]
            while a < a_end and b < b_end:  # branch-free but for the pairs written
                lo = max(first[a], first[b] - dx)
                hi = min(stop[a], stop[b] - dx)
                found = max(hi - lo, 0) * (lab[a] != lab[b])
                if write and found:
                    for c in range(lo, hi):
                        out[j, 0], out[j, 1], out[j, 2], out[j, 3] = r, c, r + dy, c + dx
                        out[j, 4], out[j, 5] = lab[a], lab[b]
                        j += 1
                elif not write:
                    j += found
                step = stop[a] <= stop[b] - dx
                a += step
                b += 1 - step
    return j


@njit(cache=True, nogil=True, error_model="numpy")
def neighbour_pairs(labels: np.ndarray, reach: int) -> np.ndarray:  # pragma: no cover
    """Pixel pairs of different positive labels within ``reach`` (neighbours; Sec. VII).

    The runs of equal labels along the rows (:func:`_label_runs`) of each
    row and of the row dy below, shifted by dx, are intersected for each of
    half of the offsets (dy, dx) (:func:`_run_pairs`): the cost goes with
    the runs and the pairs, not with the pixels of each offset. A first
    sweep counts the pairs, a second writes them. The order is the
    reference's (offset by offset, pixels in raster order), so the rows
    equal :func:`rangeseg_cli.stages.surfaces.neighbour_pairs`' arrays exactly.

    Returns
    -------
    numpy.ndarray
        int64 (P, 6): rows_p, cols_p, rows_q, cols_q, labels_p, labels_q.
    """
    runs = _label_runs(labels)
    out = np.empty((_run_pairs(labels, reach, runs, np.empty((0, 6), dtype=np.int64)), 6),
                   dtype=np.int64)
    _run_pairs(labels, reach, runs, out)
    return out


# --------------------------------------------------------------------------- local planes


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _blur_plane(pad: np.ndarray, w: np.ndarray, acc: np.ndarray, out: np.ndarray
                ) -> None:  # pragma: no cover - compiled
    """Separable Gaussian blur of ``pad`` (zero-padded by ``len(w) // 2`` on every side).

    As :func:`scipy.ndimage.gaussian_filter` with ``mode="constant"``, row by
    row (:func:`_blur_row`; ``acc`` as wide as a padded row).
    """
    for r in range(out.shape[0]):
        _blur_row(pad, w, r, acc, out[r])


@njit(cache=True, nogil=True, error_model="numpy")
def _blur_row(pad: np.ndarray, w: np.ndarray, r: int, acc: np.ndarray, out: np.ndarray
              ) -> None:  # pragma: no cover - compiled
    """Row r of the separable Gaussian blur of ``pad`` (see :func:`_blur_plane`).

    Rows (axis 0) first, into ``acc`` (as wide as a padded row), then
    columns, each tap sum formed as scipy's symmetric correlation forms it
    (centre tap, then the pairs from the farthest in). The loops run along
    the row, so they vectorise without reordering any sum.
    """
    radius = w.shape[0] // 2
    width = out.shape[0]
    wide = acc.shape[0]
    wc = w[radius]
    centre = pad[r + radius]
    for c in range(wide):
        acc[c] = centre[c] * wc
    for d in range(radius, 0, -1):
        above, below, wd = pad[r + radius - d], pad[r + radius + d], w[radius - d]
        for c in range(wide):
            acc[c] += (above[c] + below[c]) * wd
    for c in range(width):
        out[c] = acc[c + radius] * wc
    for d in range(radius, 0, -1):
        left, right = acc[radius - d: radius - d + width], acc[radius + d: radius + d + width]
        wd = w[radius - d]
        for c in range(width):
            out[c] += (left[c] + right[c]) * wd


#: The nine products of the plane fit: (heights instead of the mask?, first factor,
#: second factor), factors 0 none, 1 u, 2 v: m, m u, m v, zc, (m u) u, (m u) v,
#: (m v) v, zc u, zc v.
_PRODUCTS = np.array([[0, 0, 0], [0, 1, 0], [0, 2, 0], [1, 0, 0], [0, 1, 1], [0, 1, 2],
                      [0, 2, 2], [1, 1, 0], [1, 2, 0]], dtype=np.int64)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _factor(kind: int, u: float, v: float) -> float:  # pragma: no cover - compiled
    """1.0, u or v (multiplying by 1.0 changes no value, signed zeros included)."""
    return 1.0 if kind == 0 else (u if kind == 1 else v)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _masked_product(z: np.ndarray, mask: np.ndarray, u0: float, v0: float, which: int,
                    radius: int, pad: np.ndarray) -> None:  # pragma: no cover - compiled
    """Write product ``which`` of :data:`_PRODUCTS` into the interior of ``pad``.

    m is the mask as 0.0/1.0, zc the masked heights, u, v the column and row
    coordinates: the products the reference forms, in its order.
    """
    height, width = z.shape
    use_z, first, second = _PRODUCTS[which, 0], _PRODUCTS[which, 1], _PRODUCTS[which, 2]
    for r in range(height):
        v = r + v0
        row, zr, mr = pad[r + radius, radius:radius + width], z[r], mask[r]
        for c in range(width):  # selects, no branch: the loop vectorises
            u = c + u0
            zv = zr[c] if use_z else 1.0
            base = zv if mr[c] else 0.0
            row[c] = (base * _factor(first, u, v)) * _factor(second, u, v)


@njit(cache=True, nogil=True, error_model="numpy")
def plane_fit(z: np.ndarray, mask: np.ndarray, w: np.ndarray, u0: float, v0: float,
              min_det: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                       np.ndarray]:  # pragma: no cover - compiled
    """Gaussian-weighted local plane fits of ``mask`` (see ``refine.planes.local_planes``).

    The nine masked products (weight, u, v, z, uu, uv, vv, uz, vz) are
    padded once; then, row by row, their blurs (:func:`_blur_row`, the sums
    of :func:`_blur_plane`) and from them the weighted means, covariances and
    slopes by the reference's float64 operations in its order: the same
    values bit for bit, without whole blurred images.

    Returns
    -------
    mu, mv, mz, gx, gy
        float64 (h, w) weighted means of u, v, z and the slopes (NaN where
        the fit is degenerate).
    """
    height, width = z.shape
    radius = w.shape[0] // 2
    pad = np.zeros((9, height + 2 * radius, width + 2 * radius))
    for which in range(9):
        _masked_product(z, mask, u0, v0, which, radius, pad[which])
    acc = np.empty(width + 2 * radius)
    b = np.empty((9, width))
    mu = np.empty((height, width))
    mv = np.empty((height, width))
    mz = np.empty((height, width))
    gx = np.empty((height, width))
    gy = np.empty((height, width))
    for r in range(height):
        for which in range(9):
            _blur_row(pad[which], w, r, acc, b[which])
        for c in range(width):  # selects, no branch: the loop vectorises
            ok = b[0, c] > 1e-3
            s = b[0, c] if ok else 1.0
            a, bb, e = b[1, c] / s, b[2, c] / s, b[3, c] / s
            cuu = b[4, c] / s - a * a
            cuv = b[5, c] / s - a * bb
            cvv = b[6, c] / s - bb * bb
            cuz = b[7, c] / s - a * e
            cvz = b[8, c] / s - bb * e
            det = cuu * cvv - cuv * cuv
            mu[r, c], mv[r, c], mz[r, c] = a, bb, e
            good = ok and det > min_det
            slope_x = (cvv * cuz - cuv * cvz) / det
            slope_y = (cuu * cvz - cuv * cuz) / det
            gx[r, c] = slope_x if good else np.nan
            gy[r, c] = slope_y if good else np.nan
    return mu, mv, mz, gx, gy


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _row_starts(rows: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Where each run of equal ``rows`` starts, and where the last ends: (runs + 1,)."""
    starts = np.empty(rows.shape[0] + 1, np.int64)
    count = 0
    for i in range(rows.shape[0]):
        if i == 0 or rows[i] != rows[i - 1]:
            starts[count] = i
            count += 1
    starts[count] = rows.shape[0]
    return starts[:count + 1]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _column_blurs(pad: np.ndarray, w: np.ndarray, r: int, need: np.ndarray, out: np.ndarray
                  ) -> None:  # pragma: no cover - compiled
    """The first (axis 0) blur of :func:`_blur_row` of one padded product at row r.

    Into ``out[c]`` at the padded columns c where ``need`` is set, run by
    run (the same sums, in the same order, as ``acc`` of :func:`_blur_row`).
    """
    radius = w.shape[0] // 2
    wc = w[radius]
    c, wide = 0, need.shape[0]
    while c < wide:
        if not need[c]:
            c += 1
            continue
        end = c
        while end < wide and need[end]:
            end += 1
        acc, centre = out[c:end], pad[r + radius, c:end]
        for k in range(end - c):
            acc[k] = centre[k] * wc
        for d in range(radius, 0, -1):
            above, below = pad[r + radius - d, c:end], pad[r + radius + d, c:end]
            wd = w[radius - d]
            for k in range(end - c):
                acc[k] += (above[k] + below[k]) * wd
        c = end


@njit(cache=True, nogil=True, error_model="numpy")
def plane_heights_at(z: np.ndarray, mask: np.ndarray, w: np.ndarray, u0: float, v0: float,
                     min_det: float, rows: np.ndarray, cols: np.ndarray
                     ) -> np.ndarray:  # pragma: no cover - compiled
    """Heights of the local planes of :func:`plane_fit` at the pixels (rows, cols) only.

    ``mz + gx (u - mu) + gy (v - mv)`` (``refine.planes.local_planes``' height) from
    the same blurred products, summed in the same order, as :func:`plane_fit`
    forms them for the whole array: the same values bit for bit, NaN where
    the fit is degenerate. The first blur runs only on the rows asked for, over
    the columns within reach of their pixels, one product after the other
    (each stays in the cache), so the cost follows the number of pixels
    asked for rather than the array's size. Pixels in any order; sorted by
    row here when they are not (raster order, as ``np.nonzero`` gives them,
    needs no sort).
    """
    for i in range(1, rows.shape[0]):
        if rows[i] < rows[i - 1]:
            order = np.argsort(rows, kind="mergesort")
            out = np.empty(rows.shape[0])
            out[order] = _heights_in_rows(z, mask, w, u0, v0, min_det, rows[order],
                                          cols[order])
            return out
    return _heights_in_rows(z, mask, w, u0, v0, min_det, rows, cols)


@njit(cache=True, nogil=True, error_model="numpy")
def _heights_in_rows(z: np.ndarray, mask: np.ndarray, w: np.ndarray, u0: float, v0: float,
                     min_det: float, rows: np.ndarray, cols: np.ndarray
                     ) -> np.ndarray:  # pragma: no cover - compiled
    """:func:`plane_heights_at` of pixels sorted by row (each row's blurs formed once)."""
    height, width = z.shape
    radius = w.shape[0] // 2
    wc = w[radius]
    wide = width + 2 * radius
    starts = _row_starts(rows)
    count = starts.shape[0] - 1
    need = np.zeros((count, wide), dtype=np.bool_)
    for q in range(count):
        for i in range(starts[q], starts[q + 1]):
            need[q, cols[i]: cols[i] + 2 * radius + 1] = True
    blurred = np.empty((9, count, wide))
    pad = np.zeros((height + 2 * radius, wide))
    for which in range(9):
        _masked_product(z, mask, u0, v0, which, radius, pad)
        for q in range(count):
            _column_blurs(pad, w, rows[starts[q]], need[q], blurred[which, q])
    out = np.empty(rows.shape[0])
    b = np.empty(9)
    for q in range(count):
        for i in range(starts[q], starts[q + 1]):
            c = cols[i] + radius
            for which in range(9):
                src = blurred[which, q]
                a = src[c] * wc
                for d in range(radius, 0, -1):
                    a += (src[c - d] + src[c + d]) * w[radius - d]
                b[which] = a
            out[i] = _height(b, min_det, cols[i] + u0, rows[i] + v0)
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _height(b: np.ndarray, min_det: float, u: float, v: float) -> float:  # pragma: no cover
    """The plane's height at (u, v) from the nine blurred products, as :func:`plane_fit`."""
    s = b[0]
    ok = s > 1e-3
    if not ok:
        s = 1.0
    a, bb, e = b[1] / s, b[2] / s, b[3] / s
    cuu = b[4] / s - a * a
    cuv = b[5] / s - a * bb
    cvv = b[6] / s - bb * bb
    cuz = b[7] / s - a * e
    cvz = b[8] / s - bb * e
    det = cuu * cvv - cuv * cuv
    if ok and det > min_det:
        gx = (cvv * cuz - cuv * cvz) / det
        gy = (cuu * cvz - cuv * cuz) / det
    else:
        gx = np.nan
        gy = np.nan
    return e + gx * (u - a) + gy * (v - bb)


# --------------------------------------------------------------------------- split helpers


@njit(cache=True, nogil=True, error_model="numpy")
def histogram2d(x: np.ndarray, y: np.ndarray, edges: np.ndarray
                ) -> np.ndarray:  # pragma: no cover - compiled
    """Counts of the points (x, y) in the bins of ``edges`` (both axes), as ``np.histogram2d``.

    A point's bin along an axis is ``np.searchsorted(edges, value, side="right")``
    (by bisection), less one on the last edge; bins 0 and ``len(edges)`` (the
    outliers) are counted too, so the result is the (k + 1, k + 1) array of
    ``np.histogramdd`` before it drops them (k = ``len(edges)``).
    """
    k = edges.shape[0]
    counts = np.zeros((k + 1, k + 1), dtype=np.int64)
    for i in range(x.shape[0]):
        counts[_bin(edges, x[i]), _bin(edges, y[i])] += 1
    return counts


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _bin(edges: np.ndarray, value: float) -> int:  # pragma: no cover - compiled
    """``np.histogramdd``'s bin of ``value`` in the equally spaced ``edges`` (outliers 0, k).

    ``np.searchsorted(edges, value, side="right")``, less one on the last
    edge. The guess from the spacing is corrected by comparing with the edges, so
    the count of edges <= value is exact.
    """
    k = edges.shape[0]
    if value != value:  # NaN sorts last
        return k
    lo, hi = edges[0], edges[k - 1]
    if value < lo:
        return 0
    if value >= hi:
        return k - 1 if value == hi else k
    j = min(max(int((value - lo) / (hi - lo) * (k - 1)), 0), k - 1)
    while j < k and edges[j] <= value:
        j += 1
    while j > 0 and edges[j - 1] > value:
        j -= 1
    return j


@njit(cache=True, nogil=True, error_model="numpy")
def otsu_index(xs: np.ndarray, total: float) -> int:  # pragma: no cover - compiled
    """Split index of Otsu's threshold of the sorted ``xs`` (N >= 2) whose sum is ``total``.

    The first i maximising ``k (n - k) (m0 - m1)^2`` (k = i + 1; m0, m1 the
    means below and above), with the running sum formed as ``np.cumsum``
    forms it and every other value by ``split._otsu``'s float64 operations.
    """
    n = xs.shape[0]
    best, at = 0.0, 0
    csum = 0.0
    for i in range(n - 1):
        csum = xs[0] if i == 0 else csum + xs[i]
        k = i + 1
        d = csum / k - (total - csum) / (n - k)
        between = (k * (n - k)) * (d * d)
        if between != between:  # NaN: np.argmax takes the first
            return i
        if i == 0 or between > best:
            best, at = between, i
    return at


@njit(cache=True, nogil=True, error_model="numpy")
def _flood(labels: np.ndarray, out: np.ndarray, r0: int, c0: int, part: int,
           stack_r: np.ndarray, stack_c: np.ndarray) -> None:  # pragma: no cover - compiled
    """Set ``out`` to ``part`` on the 4-connected pixels of (r0, c0)'s value in ``labels``."""
    height, width = labels.shape
    value = labels[r0, c0]
    out[r0, c0] = part
    stack_r[0], stack_c[0] = r0, c0
    top = 1
    while top > 0:
        top -= 1
        r, c = stack_r[top], stack_c[top]
        for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
            if (0 <= rr < height and 0 <= cc < width and out[rr, cc] == 0
                    and labels[rr, cc] == value):
                out[rr, cc] = part
                stack_r[top], stack_c[top] = rr, cc
                top += 1


@njit(cache=True, nogil=True, error_model="numpy")
def value_parts(labels: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """4-connected parts of every positive value of int32 ``labels``, numbered 1..k.

    Numbered by value, then by the raster order of each part's first pixel,
    as ``split._parts`` numbers them (one ``scipy.ndimage.label`` per value,
    ascending); 0 stays 0. One flood fill in raster order.
    """
    height, width = labels.shape
    out = np.zeros((height, width), dtype=np.int32)
    stack_r = np.empty(height * width, dtype=np.int64)
    stack_c = np.empty(height * width, dtype=np.int64)
    values = np.empty(height * width, dtype=np.int64)
    found = 0
    for r0 in range(height):
        for c0 in range(width):
            value = labels[r0, c0]
            if value <= 0 or out[r0, c0] != 0:
                continue
            values[found] = value
            found += 1
            _flood(labels, out, r0, c0, found, stack_r, stack_c)
    order = np.argsort(values[:found], kind="mergesort")  # by value, then first pixel
    lut = np.zeros(found + 1, dtype=np.int32)
    for rank in range(found):
        lut[order[rank] + 1] = rank + 1
    for r in range(height):
        for c in range(width):
            out[r, c] = lut[out[r, c]]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def first_pixels(labels: np.ndarray, n: int) -> np.ndarray:  # pragma: no cover - compiled
    """Flat index of the first pixel (raster order) of each label 0..n; -1 where absent.

    As ``np.unique(labels.ravel(), return_index=True)`` gives them, in one sweep.
    """
    first = np.full(n + 1, -1, dtype=np.int64)
    flat = labels.ravel()
    for i in range(flat.shape[0]):
        lab = flat[i]
        if first[lab] < 0:
            first[lab] = i
    return first


@njit(cache=True, nogil=True, error_model="numpy")
def nearest_labels(parts: np.ndarray, rows: np.ndarray, cols: np.ndarray, dr: np.ndarray,
                   dc: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """Label of the first labelled pixel at offsets (dr, dc) tried in order from each pixel.

    The offsets are ``split._search_offsets``' (nearest first, ties as
    :func:`scipy.ndimage.distance_transform_edt` breaks them), so the label
    found is the feature transform's; 0 where none lies within them.
    """
    height, width = parts.shape
    found = np.zeros(rows.shape[0], dtype=np.int32)
    for i in range(rows.shape[0]):
        r, c = rows[i], cols[i]
        for k in range(dr.shape[0]):
            rr, cc = r + dr[k], c + dc[k]
            if 0 <= rr < height and 0 <= cc < width and parts[rr, cc] > 0:
                found[i] = parts[rr, cc]
                break
    return found


@njit(cache=True, nogil=True, error_model="numpy")
def fill_nearest(parts: np.ndarray, where: np.ndarray, dr: np.ndarray, dc: np.ndarray
                 ) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``parts`` on ``where`` (0 elsewhere), its unlabelled pixels taking the nearest label.

    The label is that of the first labelled pixel at the offsets (dr, dc)
    tried in order (as :func:`nearest_labels`); pixels with none within them
    get -1, and their number is returned with the array (the caller takes
    their labels from the feature transform). All 0 when ``parts`` has no
    labelled pixel.
    """
    height, width = parts.shape
    out = np.zeros((height, width), dtype=np.int32)
    if parts.size == 0 or parts.max() <= 0:
        return out, 0
    missing = 0
    for r in range(height):
        for c in range(width):
            if not where[r, c]:
                continue
            lab = parts[r, c]
            if lab == 0:
                lab = -1
                for k in range(dr.shape[0]):
                    rr, cc = r + dr[k], c + dc[k]
                    if 0 <= rr < height and 0 <= cc < width and parts[rr, cc] > 0:
                        lab = parts[rr, cc]
                        break
                if lab < 0:
                    missing += 1
            out[r, c] = lab
    return out, missing


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _dense_labels(labels: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """The labels present renumbered 1..k in increasing order, 0 staying 0 (``split._dense``)."""
    top = 0
    for v in labels.ravel():
        top = max(top, v)
    lut = np.zeros(top + 1, np.int32)
    for v in labels.ravel():
        if v > 0:
            lut[v] = 1
    k = 0
    for v in range(1, top + 1):
        if lut[v]:
            k += 1
            lut[v] = k
    out = np.empty_like(labels)
    for r in range(labels.shape[0]):
        for c in range(labels.shape[1]):
            out[r, c] = lut[labels[r, c]]
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _drop_small(parts: np.ndarray, mask: np.ndarray, min_piece: int
                ) -> None:  # pragma: no cover - compiled
    """Set ``parts`` to 0 off ``mask`` and on its parts below ``min_piece`` pixels (in place)."""
    count = 0
    for r in range(parts.shape[0]):
        for c in range(parts.shape[1]):
            if not mask[r, c]:
                parts[r, c] = 0
            count = max(count, parts[r, c])
    sizes = np.zeros(count + 1, np.int64)
    for v in parts.ravel():
        sizes[v] += 1
    for r in range(parts.shape[0]):
        for c in range(parts.shape[1]):
            if sizes[parts[r, c]] < min_piece:
                parts[r, c] = 0


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _wide_numbers(parts: np.ndarray, whole: np.ndarray, mask: np.ndarray, thickness: int,
                  min_piece: int) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """The parts 1..n whose core holds ``min_piece`` pixels numbered 1..m, others 0; m.

    A core pixel lies on ``mask`` with ``whole`` (the parts filled over the
    solid mask) uniform within ``thickness`` (chessboard) of it
    (``split._core``).
    """
    n = 0
    for v in parts.ravel():
        n = max(n, v)
    low, high = window_extremes(whole, thickness, 0)
    cores = np.zeros(n + 1, np.int64)
    for r in range(parts.shape[0]):
        for c in range(parts.shape[1]):
            if low[r, c] == high[r, c] and mask[r, c]:
                cores[parts[r, c]] += 1
    lut = np.zeros(n + 1, np.int32)
    wide = 0
    for k in range(1, n + 1):
        if cores[k] >= min_piece:
            wide += 1
            lut[k] = wide
    return lut, wide


@njit(cache=True, nogil=True, error_model="numpy")
def clean_parts(labels: np.ndarray, mask: np.ndarray, solid: np.ndarray, min_piece: int,
                thickness: int, dr: np.ndarray, dc: np.ndarray
                ) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``split._clean`` in one call: the wide 4-connected parts of ``labels`` on ``mask``.

    The same steps on the same kernels (:func:`fill_nearest`,
    :func:`value_parts`, :func:`window_extremes`): parts below ``min_piece``
    pixels, then parts whose core (pixels ``thickness`` or more from their
    part's border within ``solid``) is below ``min_piece``, go to their
    nearest neighbours. Status 1; 0 when a nearest-label search finds no
    label within the offsets (dr, dc), which the caller's reference answers
    with the feature transform.
    """
    filled, missing = fill_nearest(labels, solid, dr, dc)
    if missing:
        return filled, 0
    parts = value_parts(filled)
    _drop_small(parts, mask, min_piece)
    kept, missing = fill_nearest(parts, mask, dr, dc)
    if missing:
        return kept, 0
    parts = _dense_labels(kept)
    whole, missing = fill_nearest(parts, solid, dr, dc)
    if missing:
        return whole, 0
    lut, wide = _wide_numbers(parts, whole, mask, thickness, min_piece)
    if wide > 0 and wide == lut.shape[0] - 1:  # every pixel of the mask keeps its part
        return parts, 1
    for r in range(parts.shape[0]):
        for c in range(parts.shape[1]):
            parts[r, c] = lut[parts[r, c]]
    out, missing = fill_nearest(parts, mask, dr, dc)
    return out, 0 if missing else 1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _doubt_pixels(low: np.ndarray, high: np.ndarray, mask: np.ndarray, margin: int
                  ) -> tuple[np.ndarray, np.ndarray, int, int, int, int]:  # pragma: no cover
    """Pixels of ``mask`` near two or more parts, in raster order, and their box.

    Near two or more: ``high > 0`` and ``low != high`` (:func:`label_extremes`).
    Returns their rows and columns relative to their bounding box grown by
    ``margin`` and clipped to the array, and that box (r0, r1, c0, c1).
    """
    height, width = mask.shape
    r_lo, r_hi, c_lo, c_hi, count = height, -1, width, -1, 0
    for r in range(height):
        for c in range(width):
            if mask[r, c] and high[r, c] > 0 and low[r, c] != high[r, c]:
                count += 1
                r_lo, r_hi = min(r_lo, r), max(r_hi, r)
                c_lo, c_hi = min(c_lo, c), max(c_hi, c)
    r0, r1 = max(r_lo - margin, 0), min(r_hi + margin + 1, height)
    c0, c1 = max(c_lo - margin, 0), min(c_hi + margin + 1, width)
    rows, cols = np.empty(count, np.int64), np.empty(count, np.int64)
    i = 0
    for r in range(r0, r1):
        for c in range(c0, c1):
            if count and mask[r, c] and high[r, c] > 0 and low[r, c] != high[r, c]:
                rows[i], cols[i] = r - r0, c - c0
                i += 1
    return rows, cols, r0, r1, c0, c1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _near_label(sub: np.ndarray, k: int, r: int, c: int, reach: int
                ) -> bool:  # pragma: no cover - compiled
    """Whether a pixel of ``sub`` within chessboard ``reach`` of (r, c) holds k."""
    for rr in range(max(r - reach, 0), min(r + reach + 1, sub.shape[0])):
        for cc in range(max(c - reach, 0), min(c + reach + 1, sub.shape[1])):
            if sub[rr, cc] == k:
                return True
    return False


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _heights_near(z: np.ndarray, cores: np.ndarray, k: int, box: np.ndarray, w: np.ndarray,
                  min_det: float, rows: np.ndarray, cols: np.ndarray
                  ) -> np.ndarray:  # pragma: no cover - compiled
    """``split._plane_heights``: local plane heights of part k's core at (rows, cols), else NaN.

    ``cores`` holds each core pixel's part, ``box`` part k's core box (first
    and last row, first and last column). On the rows and columns within the
    blur's reach of both the pixels and the core (:func:`plane_heights_at`,
    the same values bit for bit).
    """
    reach = w.shape[0] // 2
    height, width = z.shape
    r0 = max(rows.min() - reach, box[0] - reach, 0)
    r1 = min(rows.max() + reach + 1, box[1] + reach + 1, height)
    c0 = max(cols.min() - reach, box[2] - reach, 0)
    c1 = min(cols.max() + reach + 1, box[3] + reach + 1, width)
    out = np.full(rows.shape[0], np.nan)
    if r1 <= r0 or c1 <= c0:
        return out
    inside = np.flatnonzero((rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1))
    found = plane_heights_at(np.ascontiguousarray(z[r0:r1, c0:c1]), cores[r0:r1, c0:c1] == k,
                             w, c0 - width / 2.0, r0 - height / 2.0, min_det,
                             rows[inside] - r0, cols[inside] - c0)
    for i in range(inside.shape[0]):
        out[inside[i]] = found[i]
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _core_labels(sub: np.ndarray, inner: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``sub`` on ``inner`` (each core pixel's part), 0 elsewhere; each part's core box.

    The box of part k: first and last row, first and last column of its
    core pixels (last row -1 when it has none).
    """
    top = 0
    for v in sub.ravel():
        top = max(top, v)
    boxes = np.empty((top + 1, 4), np.int64)
    boxes[:, 0], boxes[:, 1] = sub.shape[0], -1
    boxes[:, 2], boxes[:, 3] = sub.shape[1], -1
    cores = np.zeros(sub.shape, np.int32)
    for r in range(sub.shape[0]):
        for c in range(sub.shape[1]):
            k = sub[r, c]
            if inner[r, c] and k > 0:
                cores[r, c] = k
                b = boxes[k]
                b[0], b[1], b[2], b[3] = min(b[0], r), max(b[1], r), min(b[2], c), max(b[3], c)
    return cores, boxes


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _near_part(sub: np.ndarray, k: int, low: np.ndarray, high: np.ndarray, rows: np.ndarray,
               cols: np.ndarray, band: int) -> np.ndarray:  # pragma: no cover - compiled
    """Indices of the pixels (rows, cols) within ``band`` of part k (``split._near_part``).

    ``low``, ``high``: the smallest and largest part within ``band`` of each pixel.
    """
    near = np.empty(rows.shape[0], np.int64)
    count = 0
    for i in range(rows.shape[0]):
        lo, hi = low[i], high[i]
        if lo == k or hi == k or (lo < k < hi and _near_label(sub, k, rows[i], cols[i], band)):
            near[count] = i
            count += 1
    return near[:count]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _values_at(a: np.ndarray, b: np.ndarray, c: np.ndarray, rows: np.ndarray, cols: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``a[rows, cols]``, ``b[rows, cols]`` and ``c[rows, cols]`` (int32 arrays)."""
    out = np.empty((3, rows.shape[0]), np.int32)
    for i in range(rows.shape[0]):
        r, k = rows[i], cols[i]
        out[0, i], out[1, i], out[2, i] = a[r, k], b[r, k], c[r, k]
    return out[0], out[1], out[2]


@njit(cache=True, nogil=True, error_model="numpy")
def reassign_parts(z: np.ndarray, parts: np.ndarray, mask: np.ndarray, solid: np.ndarray,
                   band: int, thickness: int, margin: int, w: np.ndarray, min_det: float,
                   dr: np.ndarray, dc: np.ndarray
                   ) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``split._reassign`` in one call: pixels near two parts to the one predicting them best.

    The same steps on the same kernels (:func:`label_extremes`,
    :func:`fill_nearest`, :func:`window_extremes`, :func:`plane_heights_at`),
    the parts taken in increasing order, ties kept by the earlier: the same
    labels. Status 1; 0 when a nearest-label search of the parts' cores finds
    no label within the offsets (dr, dc), which the caller's reference
    answers with the feature transform.
    """
    low, high = label_extremes(parts, band)
    rows, cols, r0, r1, c0, c1 = _doubt_pixels(low, high, mask, margin)
    if rows.shape[0] == 0:
        return parts.copy(), 1
    whole, missing = fill_nearest(parts, solid, dr, dc)
    if missing:
        return whole, 0
    in_low, in_high = window_extremes(whole, thickness, 0)
    inner = (in_low == in_high) & mask
    sub, zb, inner = parts[r0:r1, c0:c1], z[r0:r1, c0:c1], inner[r0:r1, c0:c1]
    low_at, high_at, best = _values_at(low[r0:r1, c0:c1], high[r0:r1, c0:c1], sub, rows, cols)
    best_cost = np.full(rows.shape[0], np.inf)
    cores, boxes = _core_labels(sub, inner)
    for k in range(1, boxes.shape[0]):
        if boxes[k, 1] < 0:  # absent, or no core
            continue
        near = _near_part(sub, k, low_at, high_at, rows, cols, band)
        if near.shape[0] == 0:
            continue
        heights = _heights_near(zb, cores, k, boxes[k], w, min_det, rows[near], cols[near])
        for j in range(near.shape[0]):
            cost = abs(zb[rows[near[j]], cols[near[j]]] - heights[j])
            if np.isfinite(cost) and cost < best_cost[near[j]]:
                best[near[j]], best_cost[near[j]] = k, cost
    out = parts.copy()
    for i in range(rows.shape[0]):
        out[r0 + rows[i], c0 + cols[i]] = best[i]
    return out, 1


@njit(cache=True, nogil=True, error_model="numpy")
def _fold_extremes(lo: np.ndarray, hi: np.ndarray, src_lo: np.ndarray, src_hi: np.ndarray
                   ) -> None:  # pragma: no cover - compiled
    """``lo = min(lo, src_lo)``, ``hi = max(hi, src_hi)`` elementwise (vectorised)."""
    for c in range(lo.shape[0]):
        lo[c] = min(lo[c], src_lo[c])
        hi[c] = max(hi[c], src_hi[c])


@njit(cache=True, nogil=True, error_model="numpy")
def window_extremes(a: np.ndarray, reach: int, cval: int
                    ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Minimum and maximum of int32 ``a`` over every (2 reach + 1)^2 window, ``cval`` outside.

    As :func:`scipy.ndimage.minimum_filter` and ``maximum_filter`` with
    ``mode="constant"`` (integers: exactly): along the rows of a padded copy,
    then down the columns, both in branch-free row loops.
    """
    height, width = a.shape
    span = 2 * reach + 1
    padded = np.full((height + 2 * reach, width + 2 * reach), cval, dtype=np.int32)
    padded[reach:reach + height, reach:reach + width] = a
    return _window_folds(padded, padded, height, width, span)


@njit(cache=True, nogil=True, error_model="numpy")
def _window_folds(pad_lo: np.ndarray, pad_hi: np.ndarray, height: int, width: int, span: int
                  ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Window minima of ``pad_lo`` and maxima of ``pad_hi`` (padded by ``span // 2``).

    Along the rows, then down the columns, both in branch-free row loops.
    """
    row_low = np.empty((height + span - 1, width), dtype=np.int32)
    row_high = np.empty((height + span - 1, width), dtype=np.int32)
    for r in range(height + span - 1):
        row_low[r, :] = pad_lo[r, :width]
        row_high[r, :] = pad_hi[r, :width]
        for d in range(1, span):
            _fold_extremes(row_low[r], row_high[r], pad_lo[r, d:d + width],
                           pad_hi[r, d:d + width])
    low = np.empty((height, width), dtype=np.int32)
    high = np.empty((height, width), dtype=np.int32)
    for r in range(height):
        low[r, :] = row_low[r]
        high[r, :] = row_high[r]
        for d in range(1, span):
            _fold_extremes(low[r], high[r], row_low[r + d], row_high[r + d])
    return low, high


@njit(cache=True, nogil=True, error_model="numpy")
def label_extremes(a: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Smallest positive and largest value of int32 ``a`` over every (2 reach + 1)^2 window.

    The minimum is of ``a`` with its values <= 0 and the outside taken as
    the largest int32, the maximum of ``a`` with 0 outside: what
    :func:`window_extremes` gives for each of the two arrays, in one call.
    """
    height, width = a.shape
    big = np.int32(np.iinfo(np.int32).max)
    span = 2 * reach + 1
    pad_lo = np.full((height + 2 * reach, width + 2 * reach), big, dtype=np.int32)
    pad_hi = np.zeros((height + 2 * reach, width + 2 * reach), dtype=np.int32)
    for r in range(height):
        for c in range(width):
            v = a[r, c]
            pad_lo[r + reach, c + reach] = v if v > 0 else big
            pad_hi[r + reach, c + reach] = v
    return _window_folds(pad_lo, pad_hi, height, width, span)


# --------------------------------------------------------------------------- noise sample


@njit(cache=True, nogil=True, error_model="numpy")
def _symmetric_residual(z: np.ndarray, r: int, axis: int, w: np.ndarray, out: np.ndarray
                        ) -> None:  # pragma: no cover - compiled
    """|correlate1d - z| along ``axis`` at row ``r``, summed as scipy sums a symmetric mask.

    The centre tap, then the pairs of taps from the farthest in:
    ``x0 w0 + (x_-h + x_h) w_-h + ... + (x_-1 + x_1) w_-1``; ``out`` is as
    long as the stretch of row ``r`` whose masks lie inside ``z``: from
    column 0 along axis 0, from column ``half`` along axis 1.
    """
    half, n = w.shape[0] // 2, out.shape[0]
    c0, dy, dx = (0, 1, 0) if axis == 0 else (half, 0, 1)
    centre = z[r, c0: c0 + n]
    for c in range(n):
        out[c] = centre[c] * w[half]
    for j in range(half, 0, -1):
        low = z[r - j * dy, c0 - j * dx: c0 - j * dx + n]
        high = z[r + j * dy, c0 + j * dx: c0 + j * dx + n]
        wj = w[half - j]
        for c in range(n):
            out[c] += (low[c] + high[c]) * wj
    for c in range(n):
        out[c] = abs(out[c] - centre[c])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _residual_row(z: np.ndarray, r: int, axis: int, w: np.ndarray, out: np.ndarray
                  ) -> None:  # pragma: no cover - compiled
    """AR of ``correlate1d(z, w)`` along ``axis`` for row ``r`` where the mask is inside.

    Columns whose mask leaves the image are left as they are.
    """
    half = w.shape[0] // 2
    height, width = z.shape
    if axis == 0 and half <= r < height - half:
        _symmetric_residual(z, r, axis, w, out)
    elif axis == 1 and width > 2 * half:
        _symmetric_residual(z, r, axis, w, out[half: width - half])


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _take_kept(whole: np.ndarray, ar: np.ndarray, i: int, j: int, step: int, out: np.ndarray
               ) -> tuple[int, int]:  # pragma: no cover - compiled
    """Copy the kept values of one row (every ``step``-th whole pixel) to ``out``.

    ``i`` counts the whole pixels before this row, ``j`` the values kept; both
    are returned updated.
    """
    for c in range(whole.shape[0]):
        if whole[c]:
            if i == j * step:
                out[j] = ar[c]
                j += 1
            i += 1
    return i, j


@njit(cache=True, nogil=True, error_model="numpy")
def noise_residuals(z: np.ndarray, w: np.ndarray, max_samples: int
                    ) -> np.ndarray:  # pragma: no cover - compiled
    """The AR sample of the noise estimate (``edges.small_filter_residuals``).

    AR along axis 0 at the pixels whose whole mask is valid, in raster order,
    then along axis 1; of these, every ``step``-th value (``step = total //
    max_samples`` when there are more than ``max_samples``); rows without a
    kept value are skipped.
    """
    height, width = z.shape
    half = w.shape[0] // 2
    whole, counts = _whole_masks(z, half)
    total = 0
    for axis in range(2):
        for r in range(height):
            total += counts[axis, r]
    step = total // max_samples if total > max_samples else 1
    out = np.empty((total + step - 1) // step)
    ar = np.empty(width)
    i = j = _ZERO  # whole pixels seen; values kept
    for axis in range(2):
        for r in range(height):
            count = counts[axis, r]
            if i + count > j * step:  # a kept value in this row
                _residual_row(z, r, axis, w, ar)
                i, j = _take_kept(whole[axis, r], ar, i, j, step, out)
            else:
                i += count
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _whole_masks(z: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels' masks along each axis are whole (valid), per row, and their counts.

    uint8 (2, H, W) flags, as ``scipy.ndimage.minimum_filter1d`` of the
    validity (``mode="constant"``: 0 outside the image) along axis 0 and 1
    of ``2 half + 1`` taps; int64 (2, H) their number per row. Axis 0 from
    the run of valid pixels down each column (a pixel's mask is whole when
    the run at its last row is that long), axis 1 from the run along the
    row; one sweep for both.
    """
    height, width = z.shape
    whole = np.zeros((2, height, width), dtype=np.uint8)
    counts = np.zeros((2, height), dtype=np.int64)
    run = np.zeros(width, dtype=np.int64)
    ok = np.empty(width, dtype=np.uint8)
    for r in range(height):
        for c in range(width):
            ok[c] = np.isfinite(z[r, c])
            run[c] = run[c] + 1 if ok[c] else 0
        q = r - half  # the row whose axis-0 mask ends at row r
        if half <= q < height - half:
            n = 0
            for c in range(width):
                flag = run[c] > 2 * half
                whole[0, q, c] = flag
                n += flag
            counts[0, q] = n
        length = 0
        n = 0
        for c in range(width):
            length = length + 1 if ok[c] else 0
            if length > 2 * half:
                whole[1, r, c - half] = 1
                n += 1
        counts[1, r] = n
    return whole, counts


#: Bits per digit of the radix sort of :func:`smallest_sorted`.
_RADIX_BITS = 13


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _radix_pass(src: np.ndarray, dst: np.ndarray, shift: int) -> bool:  # pragma: no cover
    """One stable counting-sort pass of ``src`` into ``dst`` by the digit at ``shift``.

    Returns False (and leaves ``dst`` alone) when every key has the same digit.
    """
    size = 1 << _RADIX_BITS
    mask = np.uint64(size - 1)
    sh = np.uint64(shift)
    count = np.zeros(size + 1, dtype=np.int64)
    for i in range(src.shape[0]):
        count[((src[i] >> sh) & mask) + 1] += 1
    for d in range(size):
        if count[d + 1] == src.shape[0]:
            return False
    for d in range(size):
        count[d + 1] += count[d]
    for i in range(src.shape[0]):
        d = (src[i] >> sh) & mask
        dst[count[d]] = src[i]
        count[d] += 1
    return True


def smallest_sorted(x: np.ndarray, k: int) -> np.ndarray:
    """``np.sort(x)[:k]`` for finite non-negative float64 ``x`` (e.g. |AR| values).

    The bit patterns of non-negative floats sort as unsigned integers: the
    values at or below the top-16-bit bucket of the k-th smallest are picked,
    then sorted by a least-significant-digit radix sort (digits that are the
    same in every value are skipped; :func:`smallest_keys`).
    """
    return smallest_keys(np.require(x, np.float64, ["C"]).view(np.uint64), k).view(np.float64)


@njit(cache=True, nogil=True, error_model="numpy")
def smallest_keys(keys: np.ndarray, k: int) -> np.ndarray:  # pragma: no cover - compiled
    """The ``k`` smallest of the uint64 ``keys``, sorted (see :func:`smallest_sorted`)."""
    top = np.zeros(1 << 16, dtype=np.int64)
    for i in range(keys.shape[0]):
        top[keys[i] >> np.uint64(48)] += 1
    seen, cut = 0, 0
    while seen + top[cut] < k:
        seen += top[cut]
        cut += 1
    src = np.empty(seen + top[cut], dtype=np.uint64)
    j = 0
    for i in range(keys.shape[0]):
        if keys[i] >> np.uint64(48) <= cut:
            src[j] = keys[i]
            j += 1
    dst = np.empty_like(src)
    for shift in range(0, 64, _RADIX_BITS):
        if _radix_pass(src, dst, shift):
            src, dst = dst, src
    return src[:k]


# --------------------------------------------------------------------------- region pairs


@njit(cache=True, nogil=True, error_model="numpy")
def _counting_order(keys: np.ndarray, n: int, order: np.ndarray) -> np.ndarray:
    """``order`` stably re-sorted by ``keys[order]`` (integers 0..n): one counting-sort pass."""
    count = np.zeros(n + 2, dtype=np.int64)
    for i in order:
        count[keys[i] + 1] += 1
    for k in range(n + 1):
        count[k + 1] += count[k]
    out = np.empty_like(order)
    for i in order:
        out[count[keys[i]]] = i
        count[keys[i]] += 1
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def pair_medians(lo: np.ndarray, hi: np.ndarray, n: int, values: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Median of each row of ``values`` over the pixel pairs of each region pair (lo, hi).

    Parameters
    ----------
    lo, hi
        int (P,) labels 0..n of the pairs' two sides.
    n
        Largest label.
    values
        float64 (m, P) values per pair.

    Returns
    -------
    group_lo, group_hi, medians
        The distinct (lo, hi) in ascending order, and float64 (m, G) medians
        ``0.5 (v[(c - 1) // 2] + v[c // 2])`` of the sorted values of each
        group of c pairs (as ``np.unique`` and ``np.lexsort`` give them).
    """
    order = np.empty(lo.shape[0], dtype=np.int64)
    for i in range(lo.shape[0]):
        order[i] = i
    if (n + 1) * (n + 1) <= 4 * lo.shape[0] + 4096:  # few labels: one pass on (lo, hi)
        keys = np.empty(lo.shape[0], dtype=np.int64)
        for i in range(lo.shape[0]):
            keys[i] = lo[i] * (n + 1) + hi[i]
        order = _counting_order(keys, (n + 1) * (n + 1) - 1, order)
    else:
        order = _counting_order(hi, n, order)
        order = _counting_order(lo, n, order)
    starts = np.empty(order.shape[0] + 1, dtype=np.int64)
    groups = 0
    for k in range(order.shape[0]):
        if k == 0 or lo[order[k]] != lo[order[k - 1]] or hi[order[k]] != hi[order[k - 1]]:
            starts[groups] = k
            groups += 1
    starts[groups] = order.shape[0]
    group_lo = np.empty(groups, dtype=np.int64)
    group_hi = np.empty(groups, dtype=np.int64)
    medians = np.empty((values.shape[0], groups))
    buf = np.empty(order.shape[0])
    for g in range(groups):
        a, b = starts[g], starts[g + 1]
        group_lo[g], group_hi[g] = lo[order[a]], hi[order[a]]
        for m in range(values.shape[0]):
            for i in range(a, b):  # the group's values in the order of their pairs
                buf[i - a] = values[m, order[i]]
            medians[m, g] = _median(buf[: b - a])
    return group_lo, group_hi, medians


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _select(x: np.ndarray, k: int) -> float:  # pragma: no cover - compiled
    """The k-th smallest of ``x`` (0-based), partitioning ``x`` in place around it.

    Quickselect with three-way partitions (ties cost nothing); afterwards
    ``x[:k] <= x[k] <= x[k + 1:]``. Much cheaper to compile than ``np.partition``.
    """
    lo, hi = 0, x.shape[0] - 1
    while lo < hi:
        a, b, c = x[lo], x[(lo + hi) // 2], x[hi]
        pivot = max(min(a, b), min(max(a, b), c))  # median of three
        lt, i, gt = lo, lo, hi
        while i <= gt:
            if x[i] < pivot:
                x[lt], x[i] = x[i], x[lt]
                lt += 1
                i += 1
            elif x[i] > pivot:
                x[i], x[gt] = x[gt], x[i]
                gt -= 1
            else:
                i += 1
        if k < lt:
            hi = lt - 1
        elif k > gt:
            lo = gt + 1
        else:
            return x[k]
    return x[k]


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _median(x: np.ndarray) -> float:  # pragma: no cover - compiled
    """``0.5 (v[(c - 1) // 2] + v[c // 2])`` of ``v = np.sort(x)``, by selection (reorders x)."""
    c = x.shape[0]
    upper = _select(x, c // 2)
    lower = upper
    if c % 2 == 0:  # the largest of the c // 2 smallest, as numba's max: the first
        lower = x[0]  # of equal values, and NaN once one is met
        i = 1
        while i < c // 2 and lower == lower:
            if not x[i] <= lower:
                lower = x[i]
            i += 1
    return 0.5 * (lower + upper)


@njit(cache=True, nogil=True, error_model="numpy")
def label_boxes(labels: np.ndarray, n: int) -> np.ndarray:  # pragma: no cover - compiled
    """Inclusive bounding box (row_min, col_min, row_max, col_max) of each label 0..n.

    Row 0 and absent labels hold (-1, -1, -1, -1); as ``scipy.ndimage.find_objects``.
    """
    height, width = labels.shape
    boxes = np.empty((n + 1, 4), dtype=np.int64)
    for i in range(n + 1):
        boxes[i, 0] = boxes[i, 1] = boxes[i, 2] = boxes[i, 3] = -1
    for r in range(height):
        c = _ZERO
        while c < width:
            lab = labels[r, c]
            end = _run_end(labels, r, c)
            if lab > 0:
                b = boxes[lab]
                if b[0] < 0:
                    b[0], b[1], b[2], b[3] = r, c, r, end - 1
                else:
                    b[1], b[2], b[3] = min(b[1], c), r, max(b[3], end - 1)
            c = end
    return boxes


# --------------------------------------------------------------------------- Sec. V-3


@njit(cache=True, nogil=True, error_model="numpy")
def link_codes(codes: np.ndarray, valid: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Step 3 (Sec. V-3) up to the labelling, as ``link.link_edges`` does it: the same arrays.

    Edges are the valid pixels coded 1 (step) or 2 (roof); a valid non-edge
    pixel with edges on both sides along one of the four directions of
    Fig. 8 (outside the image: no edge) is a closed gap (code 3); the other
    valid non-edge pixels are returned as the bool mask to label
    (``link.label_components``).
    """
    height, width = codes.shape
    out = np.zeros((height, width), dtype=np.uint8)
    edge = np.zeros((height + 2, width + 2), dtype=np.uint8)  # padded: no edge outside
    for r in range(height):
        code, ok, e, o = codes[r], valid[r], edge[r + 1, 1:width + 1], out[r]
        for c in range(width):
            is_edge = ok[c] & ((code[c] == 1) | (code[c] == 2))
            e[c] = is_edge
            o[c] = code[c] if is_edge else 0
    free = np.zeros((height, width), dtype=np.bool_)
    for r in range(height):  # row by row, branch-free: the loops vectorise
        up, mid, down = edge[r], edge[r + 1], edge[r + 2]
        code, ok, f, o = codes[r], valid[r], free[r], out[r]
        for c in range(width):
            gap = ((mid[c] & mid[c + 2]) | (up[c + 1] & down[c + 1]) | (up[c] & down[c + 2])
                   | (up[c + 2] & down[c]))
            usable = ok[c] & (mid[c + 1] == 0)
            o[c] = 3 if usable & (gap != 0) else o[c]
            f[c] = usable & (gap == 0)
    return out, free


# --------------------------------------------------------------------------- Sec. VII


@njit(cache=True, nogil=True, error_model="numpy")
def plane_counts(products: np.ndarray, offsets: np.ndarray, tol: float
                 ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Per plane, the points with ``d <= tol`` and with ``d < -tol``, ``d = n . p + e``.

    ``cell.workspace.plane_shares``' counts: each distance is the same sum
    (``products[i, j] + offsets[j]``), so the same counts; point by point,
    the planes in a vectorised loop.
    """
    planes = offsets.shape[0]
    upto = np.zeros(planes, dtype=np.int64)
    behind = np.zeros(planes, dtype=np.int64)
    for i in range(products.shape[0]):
        row = products[i]
        for j in range(planes):
            d = row[j] + offsets[j]
            upto[j] += d <= tol
            behind[j] += d < -tol
    return upto, behind


@njit(cache=True, nogil=True, error_model="numpy")
def ar_2d(z: np.ndarray, w: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    """2-D AR of Sec. VII as ``edges.ar_2d`` computes it: bitwise the same values.

    ``num`` and ``den`` are the separable correlations (axis 0, then axis 1,
    zeros outside) of the valid heights and of the validity by :func:`_blur_plane`,
    which sums as ``scipy.ndimage.correlate1d`` does; AR ``|num / den - z|``, NaN
    at invalid pixels.
    """
    height, width = z.shape
    radius = w.shape[0] // 2
    pad = np.zeros((height + 2 * radius, width + 2 * radius))
    acc = np.empty(width + 2 * radius)
    num = np.empty((height, width))
    den = np.empty((height, width))
    for r in range(height):
        for c in range(width):
            pad[r + radius, c + radius] = 0.0 if np.isnan(z[r, c]) else z[r, c]
    _blur_plane(pad, w, acc, num)
    for r in range(height):
        for c in range(width):
            pad[r + radius, c + radius] = 0.0 if np.isnan(z[r, c]) else 1.0
    _blur_plane(pad, w, acc, den)
    for r in range(height):
        for c in range(width):
            num[r, c] = np.nan if np.isnan(z[r, c]) else abs(num[r, c] / den[r, c] - z[r, c])
    return num


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _quadric_at(a: np.ndarray, y: float, x: float) -> float:  # pragma: no cover - compiled
    """``grow.evaluate_quadric`` at one point: the same operations in the same order."""
    return a[0] + a[1] * x + a[2] * y + a[3] * x * x + a[4] * x * y + a[5] * y * y


@njit(cache=True, nogil=True, error_model="numpy")
def _coeff_at(coeffs: np.ndarray, lab: int | np.integer[Any], y: float, x: float
              ) -> float:  # pragma: no cover - compiled
    """:func:`_quadric_at` of row ``lab`` of ``coeffs``, without a view of the row."""
    return (coeffs[lab, 0] + coeffs[lab, 1] * x + coeffs[lab, 2] * y + coeffs[lab, 3] * x * x
            + coeffs[lab, 4] * x * y + coeffs[lab, 5] * y * y)


@njit(cache=True, nogil=True, error_model="numpy")
def _unit_normal(coeffs: np.ndarray, lab: int, y: float, x: float, out: np.ndarray, k: int
                 ) -> None:  # pragma: no cover - compiled
    """``surfaces._unit_normals`` of one quadric at a point, into ``out[k]`` (same operations)."""
    fx = coeffs[lab, 1] + 2.0 * coeffs[lab, 3] * x + coeffs[lab, 4] * y
    fy = coeffs[lab, 2] + coeffs[lab, 4] * x + 2.0 * coeffs[lab, 5] * y
    length = np.sqrt(fx * fx + fy * fy + 1.0)
    out[k, 0], out[k, 1], out[k, 2] = -fx / length, -fy / length, 1.0 / length


@njit(cache=True, nogil=True, error_model="numpy")
def boundary_measures(labels: np.ndarray, reach: int, coeffs: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray,
                                 np.ndarray]:  # pragma: no cover - compiled
    """Boundary pairs and what ``surfaces.edge_types`` measures on them, in one call.

    The pairs of :func:`neighbour_pairs`, each ordered so that ``li < lj``
    (p on the side of li); per pair ``gap = |f_i(m) - f_j(m)|`` at the
    midpoint m of p and q and ``above = (f_j(p) - f_i(p)) + (f_i(q) - f_j(q))``,
    each fit evaluated as ``grow.evaluate_quadric`` does, and the unit
    normals of both fits at m as ``surfaces._unit_normals`` gives them:
    bitwise the reference's values.

    Returns
    -------
    li, lj
        int64 (P,) labels of the two sides.
    values
        float64 (4, P): gap, 0 (the angle's place: numpy's arccos is not
        libm's), above, and the signed gap ``f_i(m) - f_j(m)`` as
        :func:`step_gaps` computes it (``f_p - f_q``, negated where p is on
        the side of j).
    ni, nj
        float64 (P, 3) unit normals of the fits of li and lj at the midpoints.
    """
    pairs = neighbour_pairs(labels, reach)
    n = pairs.shape[0]
    li = np.empty(n, dtype=np.int64)
    lj = np.empty(n, dtype=np.int64)
    values = np.zeros((4, n))
    ni = np.empty((n, 3))
    nj = np.empty((n, 3))
    for k in range(n):
        rp, cp, rq, cq, lp, lq = (pairs[k, 0], pairs[k, 1], pairs[k, 2], pairs[k, 3],
                                  pairs[k, 4], pairs[k, 5])
        rm, cm = 0.5 * (rp + rq), 0.5 * (cp + cq)
        signed = _coeff_at(coeffs, lp, rm, cm) - _coeff_at(coeffs, lq, rm, cm)
        if lp > lq:
            rp, cp, rq, cq, lp, lq = rq, cq, rp, cp, lq, lp
            signed = -signed
        li[k], lj[k] = lp, lq
        values[3, k] = signed
        values[0, k] = abs(signed)  # |f_i(m) - f_j(m)|: a - b is exactly -(b - a)
        yp, xp, yq, xq = float(rp), float(cp), float(rq), float(cq)
        values[2, k] = ((_coeff_at(coeffs, lq, yp, xp) - _coeff_at(coeffs, lp, yp, xp))
                        + (_coeff_at(coeffs, lp, yq, xq) - _coeff_at(coeffs, lq, yq, xq)))
        _unit_normal(coeffs, lp, rm, cm, ni, k)
        _unit_normal(coeffs, lq, rm, cm, nj, k)
    return li, lj, values, ni, nj


@njit(cache=True, nogil=True, error_model="numpy")
def step_gaps(labels: np.ndarray, reach: int, coeffs: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """``holdsite.step_gaps`` in one call: median signed gap of the fits per region pair.

    The pairs of :func:`neighbour_pairs`; per pair ``f_p(m) - f_q(m)`` at the
    midpoint m, each fit evaluated as ``grow.evaluate_quadric`` does, negated
    where ``p``'s label is the larger; the medians by :func:`pair_medians`
    (bitwise the reference's values).

    Returns
    -------
    group_lo, group_hi
        int64 (G,): the distinct region pairs lo < hi, ascending.
    medians
        float64 (G,): median of ``f_lo - f_hi`` over each pair's boundary.
    """
    pairs = neighbour_pairs(labels, reach)
    n = pairs.shape[0]
    lo = np.empty(n, dtype=np.int64)
    hi = np.empty(n, dtype=np.int64)
    gaps = np.empty((1, n))
    top = 0
    for k in range(n):
        lp, lq = pairs[k, 4], pairs[k, 5]
        rm, cm = 0.5 * (pairs[k, 0] + pairs[k, 2]), 0.5 * (pairs[k, 1] + pairs[k, 3])
        gap = _coeff_at(coeffs, lp, rm, cm) - _coeff_at(coeffs, lq, rm, cm)
        lo[k], hi[k], gaps[0, k] = (lq, lp, -gap) if lp > lq else (lp, lq, gap)
        top = max(top, lp, lq)
    group_lo, group_hi, medians = pair_medians(lo, hi, top, gaps)
    return group_lo, group_hi, medians[0]


# --------------------------------------------------------------------------- recut knot search


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _plane_sums(x: np.ndarray, y: np.ndarray, zs: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Upper triangle of ``sum a a^T`` and ``sum a z`` for ``a = (1, x, y)``, in pixel order."""
    plane = np.zeros((3, 3))
    plane_rhs = np.zeros(3)
    for i in range(x.shape[0]):
        xi, yi, zi = x[i], y[i], zs[i]
        plane[0, 0] += 1.0
        plane[0, 1] += xi
        plane[0, 2] += yi
        plane[1, 1] += xi * xi
        plane[1, 2] += xi * yi
        plane[2, 2] += yi * yi
        plane_rhs[0] += zi
        plane_rhs[1] += xi * zi
        plane_rhs[2] += yi * zi
    return plane, plane_rhs


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _knot_power(q: float, p: int) -> float:  # pragma: no cover - compiled
    """``q**p`` for p = 1, 2, 3 as the reference computes it (``q * q * q`` for 3)."""
    return q if p == 1 else (q * q if p == 2 else q * q * q)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _knot_terms(u: np.ndarray, x: np.ndarray, y: np.ndarray, zs: np.ndarray,
                knots: np.ndarray, p: int, p2: int) -> np.ndarray:  # pragma: no cover
    """The sums of the knots' columns, (11, K): ``a, x a, y a, a a, a z``, then ``b`` ones.

    With ``a = q**p`` and, when ``p2 > 0``, ``b = q**p2`` (rows 5-10: ``b, x
    b, y b, a b, b b, b z``), for q > 0 (and NaN, as the reference's
    ``np.maximum``). Each knot's sums run over the pixels in their order,
    from +0.0; a pixel with q <= 0 adds zeros, which change no finite sum,
    so the loop over the knots runs without branches and vectorises. (A
    sum of zeros only is +0.0 here where the reference's may be -0.0: the
    SSEs of :func:`projected_sse` are the same.)
    """
    nk = knots.shape[0]
    acc = np.zeros((11, nk))
    for i in range(u.shape[0]):
        ui, xi, yi, zi = u[i], x[i], y[i], zs[i]
        for k in range(nk):
            q = ui - knots[k]
            a = 0.0 if q <= 0.0 else _knot_power(q, p)
            acc[0, k] += 1.0 * a
            acc[1, k] += xi * a
            acc[2, k] += yi * a
            acc[3, k] += a * a
            acc[4, k] += a * zi
            if p2 > 0:  # the same for every knot: the loop is split on it
                b = 0.0 if q <= 0.0 else _knot_power(q, p2)
                acc[5, k] += 1.0 * b
                acc[6, k] += xi * b
                acc[7, k] += yi * b
                acc[8, k] += a * b
                acc[9, k] += b * b
                acc[10, k] += b * zi
    return acc


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def knot_normal_equations(u: np.ndarray, x: np.ndarray, y: np.ndarray, zs: np.ndarray,
                          knots: np.ndarray, powers: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - compiled
    """Normal equations of ``plane + sum_p k_p q^p``, ``q = max(0, u - c)``, per knot c.

    Terms ``a = (1, x, y, q^p1[, q^p2])`` (one or two powers, each 1, 2 or
    3); ``gram[k] = sum a a^T`` and ``rhs[k] = sum a z``, summed in pixel
    order; the plane block once for all knots, the terms with q over the
    pixels with q > 0 only (the others add zeros, :func:`_knot_terms`): bit
    for bit ``rangeseg_cli.refine.recut._knot_normal_equations``.
    """
    nk, t = knots.shape[0], 3 + powers.shape[0]
    plane, plane_rhs = _plane_sums(x, y, zs)
    acc = _knot_terms(u, x, y, zs, knots, powers[0], powers[1] if t == 5 else 0)
    gram = np.zeros((nk, t, t))
    rhs = np.zeros((nk, t))
    for k in range(nk):
        g, r = gram[k], rhs[k]
        for i in range(3):
            for j in range(3):
                g[i, j] = plane[i, j]
            r[i] = plane_rhs[i]
        g[0, 3], g[1, 3], g[2, 3], g[3, 3], r[3] = (acc[0, k], acc[1, k], acc[2, k], acc[3, k],
                                                     acc[4, k])
        if t == 5:
            g[0, 4], g[1, 4], g[2, 4], g[3, 4] = acc[5, k], acc[6, k], acc[7, k], acc[8, k]
            g[4, 4], r[4] = acc[9, k], acc[10, k]
        for s in range(t):
            for v in range(s):
                g[s, v] = g[v, s]
    return gram, rhs


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def projected_sse(gram: np.ndarray, rhs: np.ndarray, zz: float, tol: float
                  ) -> np.ndarray:  # pragma: no cover - compiled
    """``max(0, zz - b^T A^+ b)`` per system: least-squares SSE from normal equations.

    ``A`` is ``gram`` scaled to a unit diagonal; a Cholesky factor is built
    column by column and a column whose pivot is at most ``tol`` (in that
    dependent on the earlier ones) is dropped, which leaves the projection,
    and so the SSE, unchanged. Bit for bit ``rangeseg_cli.refine.recut._projected_sse``.
    """
    nk, t = gram.shape[0], gram.shape[1]
    out = np.empty(nk)
    w = np.zeros(t)
    s = np.empty(t)
    for k in range(nk):
        for i in range(t):
            s[i] = np.sqrt(max(gram[k, i, i], 1e-300))
        low = np.zeros((t, t))
        explained = 0.0
        for j in range(t):
            acc = 0.0
            for m in range(j):
                acc = acc + low[j, m] * low[j, m]
            d = gram[k, j, j] / s[j] / s[j] - acc
            w[j] = 0.0
            if not d > tol:
                continue
            ljj = np.sqrt(d)
            low[j, j] = ljj
            for i in range(j + 1, t):
                acc = 0.0
                for m in range(j):
                    acc = acc + low[i, m] * low[j, m]
                low[i, j] = (gram[k, i, j] / s[i] / s[j] - acc) / ljj
            acc = 0.0
            for m in range(j):
                acc = acc + low[j, m] * w[m]
            w[j] = (rhs[k, j] / s[j] - acc) / ljj
            explained = explained + w[j] * w[j]
        out[k] = max(zz - explained, 0.0)
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def knot_sse(u: np.ndarray, x: np.ndarray, y: np.ndarray, zs: np.ndarray, knots: np.ndarray,
             powers: np.ndarray, tol: float) -> np.ndarray:  # pragma: no cover - compiled
    """SSE of ``plane + sum_p k_p q^p`` per knot (``rangeseg_cli.refine.recut.knot_sse``)."""
    gram, rhs = knot_normal_equations(u, x, y, zs, knots, powers)
    zz = 0.0
    for i in range(zs.shape[0]):
        zz = zz + zs[i] * zs[i]
    return projected_sse(gram, rhs, zz, tol)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _float_range(start: float, stop: float, step: float) -> np.ndarray:  # pragma: no cover
    """``np.arange(start, stop, step)`` of floats as numpy fills it.

    ``ceil((stop - start) / step)`` values: ``start``, ``start + step``, then
    ``start + i * delta`` with ``delta = (start + step) - start``.
    """
    n = int(np.ceil((stop - start) / step))
    out = np.empty(max(n, 0))
    if n > 0:
        out[0] = start
    if n > 1:
        second = start + step
        out[1] = second
        delta = second - start
        for i in range(2, n):
            out[i] = start + i * delta
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _strided_knot_sse(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, d0: float,
                      d1: float, every: int, knots: np.ndarray, powers: np.ndarray,
                      tol: float) -> np.ndarray:  # pragma: no cover - compiled
    """``recut.knot_sse`` of every ``every``-th pixel: the same u, centred x, y and SSE."""
    m = -(-rows.shape[0] // every)
    sr, sc = 0.0, 0.0
    for i in range(m):
        sr += rows[i * every]
        sc += cols[i * every]
    mr, mc = sr / m, sc / m
    u, x, y, z = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    for i in range(m):
        j = i * every
        u[i] = d0 * rows[j] + d1 * cols[j]
        x[i], y[i], z[i] = cols[j] - mc, rows[j] - mr, zs[j]
    return knot_sse(u, x, y, z, knots, powers, tol)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _first_min(values: np.ndarray, picks: np.ndarray) -> int:  # pragma: no cover - compiled
    """``np.argmin(values[picks])``, an index into ``picks``: the first smallest or first NaN."""
    best, low = 0, np.inf
    for i in range(picks.shape[0]):
        value = values[picks[i]]
        if np.isnan(value):
            return i
        if value < low:
            best, low = i, value
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def best_knot(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, d0: float, d1: float,
              powers: np.ndarray, max_mse: float, search: np.ndarray, tol: float
              ) -> tuple[float, float, float]:  # pragma: no cover - compiled
    """``recut.best_knot`` in one call: the best knot along (d0, d1) and two SSEs.

    ``search``: int64 (3,) the coarse search's most knots and pixels and the
    fine search's most pixels. The coarse knots, the subsampled pixels and
    the fine grid as the reference makes them (:func:`_float_range` for
    ``np.arange``), each SSE by :func:`knot_sse`: the same values.
    """
    n = zs.shape[0]
    umin, umax = np.inf, -np.inf
    for j in range(n):
        u = d0 * rows[j] + d1 * cols[j]
        umin, umax = min(umin, u), max(umax, u)
    step = max(1.0, float(np.ceil((umax - umin) / search[0])))
    knots = _float_range(math.floor(umin) + step, umax, step)
    if knots.shape[0] == 0:
        return np.nan, np.inf, np.inf
    sub = max(1, -(-n // search[1]))
    coarse = _strided_knot_sse(rows, cols, zs, d0, d1, sub, knots, powers, tol)
    k = _first_min(coarse, np.arange(coarse.shape[0]))
    if coarse[k] > max_mse * (-(-n // sub)):
        return np.nan, np.inf, np.inf
    grid = _float_range(knots[k] - 1.0, knots[k] + 1.0001, 0.1)
    fine = np.empty(grid.shape[0] + 1)
    fine[0] = umin - 0.5
    fine[1:] = grid
    every = max(1, -(-n // search[2]))
    sse = _strided_knot_sse(rows, cols, zs, d0, d1, every, fine, powers, tol)
    sse *= n / (-(-n // every))
    j = 1 + _first_min(sse, np.arange(1, sse.shape[0]))
    return fine[j], sse[j], sse[0]


# --------------------------------------------------------------------------- recovery


@njit(cache=True, nogil=True, error_model="numpy")
def _plane_of(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, chosen: np.ndarray
              ) -> tuple[bool, float, float, float]:  # pragma: no cover - compiled
    """``recover.fit_plane`` of the ``chosen`` pixels: (clearly conditioned, a0, a1, a2).

    ``plane_sums`` in the pixels' order and ``solve_plane``'s Cramer's rule
    and test, the same operations; False (and zeros) where the pixels lie
    nearly on a line, which only the reference's least squares answers.
    """
    n, sr, sc = 0, 0.0, 0.0
    for j in range(rows.shape[0]):
        if chosen[j]:
            n += 1
            sr += rows[j]
            sc += cols[j]
    cr, cc = sr / n, sc / n
    s = np.zeros(8)
    first = True
    for j in range(rows.shape[0]):
        if not chosen[j]:
            continue
        du, dv = cols[j] - cc, rows[j] - cr
        terms = (du, dv, du * du, du * dv, dv * dv, zs[j], du * zs[j], dv * zs[j])
        for i in range(8):
            s[i] = terms[i] if first else s[i] + terms[i]
        first = False
    su, sv, suu, suv, svv, sz, suz, svz = s[0], s[1], s[2], s[3], s[4], s[5], s[6], s[7]
    nf = float(n)
    m_uu = suu * svv - suv * suv
    det = nf * m_uu - su * (su * svv - sv * suv) + sv * (su * suv - sv * suu)
    t = nf + suu + svv
    if not det > 100.0 * _RCOND * t * t * t:
        return False, 0.0, 0.0, 0.0
    a0 = (sz * m_uu - su * (suz * svv - suv * svz) + sv * (suz * suv - suu * svz)) / det
    a1 = (nf * (suz * svv - suv * svz) - sz * (su * svv - suv * sv)
          + sv * (su * svz - suz * sv)) / det
    a2 = (nf * (suu * svz - suz * suv) - su * (su * svz - suz * sv)
          + sz * (su * suv - suu * sv)) / det
    return True, a0 - a1 * cc - a2 * cr, a1, a2


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _refit_inliers(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, inliers: np.ndarray,
                   tol: float) -> bool:  # pragma: no cover - compiled
    """Refit the plane to ``inliers`` and mark its inliers anew; False: not clearly conditioned.

    :func:`_plane_of` the inliers, then ``|z - plane| < tol`` at every pixel
    (``recover.plane_height``, the same operations).
    """
    ok, b0, b1, b2 = _plane_of(rows, cols, zs, inliers)
    if not ok:
        return False
    for j in range(rows.shape[0]):
        inliers[j] = abs(zs[j] - (b0 + b1 * cols[j] + b2 * rows[j])) < tol
    return True


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _vote(zs: np.ndarray, rows: np.ndarray, cols: np.ndarray, height: float, gx: float,
          gy: float, hr: int, hc: int, tol: float, j: int) -> bool:  # pragma: no cover
    """Whether pixel ``j`` fits the hypothesis plane within ``tol`` (``recover.consensus_plane``).

    The reference's operations in its order, so the same votes.
    """
    pred = height + gx * float(cols[j] - hc) + gy * float(rows[j] - hr)
    return abs(zs[j] - pred) < tol


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _best_hypothesis(zs: np.ndarray, rows: np.ndarray, cols: np.ndarray, height: np.ndarray,
                     gx: np.ndarray, gy: np.ndarray, hr: np.ndarray, hc: np.ndarray,
                     tol: float) -> int:  # pragma: no cover - compiled
    """The first hypothesis with the most votes (the ``argmax`` of ``recover.consensus_plane``).

    Every pixel's vote is counted, in a loop without branches, which
    vectorises (3 times faster on the SR300 frame's calls than one that
    stops a hypothesis once it cannot win). The column and row offsets are
    formed in float64 from exact integers, so each prediction is the
    reference's value bit for bit.
    """
    fr, fc = rows.astype(np.float64), cols.astype(np.float64)
    best, most = 0, -1
    for i in range(hr.shape[0]):
        h, a, b = height[i], gx[i], gy[i]
        r0, c0 = float(hr[i]), float(hc[i])
        count = 0
        for j in range(zs.shape[0]):
            count += abs(zs[j] - (h + a * (fc[j] - c0) + b * (fr[j] - r0))) < tol
        if count > most:
            best, most = i, count
    return best


@njit(cache=True, nogil=True, error_model="numpy")
def _eight_flood(mask: np.ndarray, out: np.ndarray, r0: int, c0: int, part: int,
                 stack: np.ndarray) -> int:  # pragma: no cover - compiled
    """Set ``out`` to ``part`` on the 8-connected part of ``mask`` holding (r0, c0): its size."""
    height, width = mask.shape
    out[r0, c0] = part
    stack[0] = r0 * width + c0
    top, count = 1, 1
    while top > 0:
        top -= 1
        r, c = stack[top] // width, stack[top] % width
        for rr in range(max(r - 1, 0), min(r + 2, height)):
            for cc in range(max(c - 1, 0), min(c + 2, width)):
                if mask[rr, cc] and out[rr, cc] == 0:
                    out[rr, cc] = part
                    stack[top] = rr * width + cc
                    top += 1
                    count += 1
    return count


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _seed_part(found: np.ndarray, r0: int, c0: int) -> np.ndarray:  # pragma: no cover
    """The 8-connected part of ``found`` holding (r0, c0), else its largest (first on ties).

    ``scipy.ndimage.label`` numbers parts by their first pixel in raster
    order, and ``argmax`` of their sizes takes the first of the largest.
    """
    height, width = found.shape
    parts = np.zeros((height, width), np.int64)
    stack = np.empty(height * width, np.int64)
    if found[r0, c0]:
        _eight_flood(found, parts, r0, c0, 1, stack)
        return parts == 1
    best, most, part = 0, 0, 0
    for r in range(height):
        for c in range(width):
            if found[r, c] and parts[r, c] == 0:
                part += 1
                size = _eight_flood(found, parts, r, c, part, stack)
                if size > most:
                    best, most = part, size
    return parts == best


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _left_pixels(z: np.ndarray, left: np.ndarray, gx: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Rows, columns and heights of ``left``'s pixels, in raster order (``np.nonzero``).

    And the indices of those whose local plane is not degenerate (finite ``gx``).
    """
    size = 0
    for r in range(left.shape[0]):
        for c in range(left.shape[1]):
            size += left[r, c]
    rows, cols, zs = np.empty(size, np.int64), np.empty(size, np.int64), np.empty(size)
    usable = np.empty(size, np.int64)
    j, found = 0, 0
    for r in range(left.shape[0]):
        for c in range(left.shape[1]):
            if left[r, c]:
                rows[j], cols[j], zs[j] = r, c, z[r, c]
                if np.isfinite(gx[r, c]):
                    usable[found] = j
                    found += 1
                j += 1
    return rows, cols, zs, usable[:found]


@njit(cache=True, nogil=True, error_model="numpy")
def consensus_plane(z: np.ndarray, left: np.ndarray, w: np.ndarray, u0: float, v0: float,
                    min_det: float, max_hypotheses: int, tol: float
                    ) -> tuple[np.ndarray, int]:  # pragma: no cover - compiled
    """``recover.consensus_plane`` in one call: the winning plane's connected inliers.

    The local planes (:func:`plane_fit`), the hypotheses at the pixels of
    ``left`` whose plane is not degenerate (every ``ceil(count /
    max_hypotheses)``-th in raster order), the votes, two refits and the
    8-connected part: the same operations as the numpy reference, so the
    same pixels.

    Returns
    -------
    found, status
        bool (h, w) and 1; 0 when there is no plane (``found`` empty); 2
        when a refit's pixels lie nearly on a line (the caller takes the
        reference, whose least squares handles them).
    """
    height, width = left.shape
    empty = np.zeros((height, width), np.bool_)
    mu, mv, mz, gx, gy = plane_fit(z, left, w, u0, v0, min_det)
    rows, cols, zs, usable = _left_pixels(z, left, gx)
    if usable.shape[0] == 0:
        return empty, 0
    step = -(-usable.shape[0] // max_hypotheses)
    hr, hc = rows[usable[::step]], cols[usable[::step]]
    hh, hx, hy = np.empty(hr.shape[0]), np.empty(hr.shape[0]), np.empty(hr.shape[0])
    for i in range(hr.shape[0]):
        r, c = hr[i], hc[i]
        hx[i], hy[i] = gx[r, c], gy[r, c]
        hh[i] = mz[r, c] + gx[r, c] * ((c + u0) - mu[r, c]) + gy[r, c] * ((r + v0) - mv[r, c])
    best = _best_hypothesis(zs, rows, cols, hh, hx, hy, hr, hc, tol)
    inliers = np.empty(zs.shape[0], np.bool_)
    for j in range(zs.shape[0]):
        inliers[j] = _vote(zs, rows, cols, hh[best], hx[best], hy[best], hr[best], hc[best], tol, j)
    for _ in range(2):
        if not inliers.any():
            return empty, 0
        if not _refit_inliers(rows, cols, zs, inliers, tol):
            return empty, 2
    if not inliers.any():
        return empty, 0
    for j in range(zs.shape[0]):
        empty[rows[j], cols[j]] = inliers[j]
    return _seed_part(empty, hr[best], hc[best]), 1


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _nearest_planes(cost: np.ndarray, planes: np.ndarray) -> np.ndarray:  # pragma: no cover
    """``np.argmin(cost[planes], axis=0)``: each pixel's cheapest of ``planes`` (an index)."""
    out = np.empty(cost.shape[1], np.int64)
    for j in range(cost.shape[1]):
        out[j] = _first_min(cost[:, j], planes)
    return out


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _k_plane_costs(zs: np.ndarray, rf: np.ndarray, cf: np.ndarray, planes: np.ndarray,
                   s2: float, assign: np.ndarray, table: np.ndarray, smoothness: float
                   ) -> np.ndarray:  # pragma: no cover - compiled
    """The cost of ``facets.k_planes``' passes: squared residuals in ``s2``.

    Plus ``smoothness`` per 8-neighbour in the region that another plane
    holds (none while ``assign[0] < 0``: the first pass).
    """
    k, n = planes.shape[0], zs.shape[0]
    cost = np.empty((k, n))
    for i in range(k):
        for j in range(n):
            d = zs[j] - (planes[i, 0] + planes[i, 1] * cf[j] + planes[i, 2] * rf[j])
            cost[i, j] = d * d / s2
    if assign[0] < 0:
        return cost
    same = np.zeros(k, np.int64)
    for j in range(n):
        held = 0
        same[:] = 0
        for o in range(table.shape[0]):
            t = table[o, j]
            if t >= 0:
                held += 1
                same[assign[t]] += 1
        for i in range(k):
            cost[i, j] = cost[i, j] + smoothness * float(held - same[i])
    return cost


@njit(cache=True, nogil=True, error_model="numpy")
def k_plane_passes(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, table: np.ndarray,
                   planes: np.ndarray, s2: float, passes: int, smoothness: float
                   ) -> tuple[np.ndarray, np.ndarray, int]:  # pragma: no cover - compiled
    """The passes of ``facets.k_planes`` in one call: each pixel's plane, the planes refitted.

    Returns
    -------
    assign, planes, status
        int64 (N,) and float64 (k, 3), status 1; status 0 when fewer than
        two planes keep three pixels; 2 when a refit's pixels lie nearly on
        a line (the caller takes the reference). The same operations as the
        numpy reference, so the same values.
    """
    n = rows.shape[0]
    zs, rf, cf = np.empty(n), np.empty(n), np.empty(n)
    for j in range(n):
        zs[j], rf[j], cf[j] = z[rows[j], cols[j]], float(rows[j]), float(cols[j])
    assign = np.full(n, -1, np.int64)
    if n == 0:
        return assign, planes, 0
    for _ in range(passes):
        k = planes.shape[0]
        cost = _k_plane_costs(zs, rf, cf, planes, s2, assign, table, smoothness)
        new = _nearest_planes(cost, np.arange(k))
        keep = np.flatnonzero(np.bincount(new, minlength=k) >= 3)
        if keep.shape[0] < k:
            if keep.shape[0] < 2:
                return assign, planes, 0
            planes = planes[keep]
            new = _nearest_planes(cost, keep)
        elif assign[0] >= 0 and (new == assign).all():
            break
        assign = new
        fitted = np.empty((planes.shape[0], 3))
        for i in range(planes.shape[0]):
            ok, fitted[i, 0], fitted[i, 1], fitted[i, 2] = _plane_of(rows, cols, zs, assign == i)
            if not ok:
                return assign, planes, 2
        planes = fitted
    return assign, planes, 0 if assign[0] < 0 else 1


# --------------------------------------------------------------------------- fill (edge pixels)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _fill_choice(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, bound: np.ndarray,
                 r: int, c: int) -> int:  # pragma: no cover - compiled
    """``fill._best_neighbour`` of one pixel: the joining label, or 0 (ratio >= 1 or none).

    The 8 neighbours in raster order of the 3x3 window; a later one wins only
    with a strictly smaller ``r^2 / bound`` (the same operations in the same
    order as the numpy reference).
    """
    h, w = labels.shape
    best, ratio = 0, np.inf
    height = z[r, c]
    for dr in range(-1, 2):
        for dc in range(-1, 2):
            rr, cc = r + dr, c + dc
            if (dr == 0 and dc == 0) or rr < 0 or rr >= h or cc < 0 or cc >= w:
                continue
            k = labels[rr, cc]
            if k <= 0:
                continue
            res = height - _quadric_at(coeffs[k], float(r), float(c))
            q = res * res / bound[k]
            if q < ratio:
                ratio, best = q, k
    return best if ratio < 1.0 else 0


@njit(cache=True, nogil=True, error_model="numpy")
def fill_passes(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, bound: np.ndarray
                ) -> None:  # pragma: no cover - compiled
    """``fill.fill_edges``' passes, in place on int32 ``labels`` (0 = open where z is finite).

    Each pass decides every candidate from the labels at its start, then
    applies the joins (simultaneous passes); the next pass's candidates are
    the open pixels 8-adjacent to a pixel that joined. The first pass tests
    every open pixel. The same labels as the numpy reference.
    """
    size = labels.size
    cand = np.empty(size, np.int64)
    join = np.empty(size, np.int64)
    to = np.empty(size, np.int32)
    seen = np.zeros(size, np.bool_)
    n = _open_pixels(z, labels, cand)
    while n > 0:
        m = _fill_decide(z, labels, coeffs, bound, cand, n, join, to)
        if m == 0:
            return
        w = labels.shape[1]
        for i in range(m):
            labels[join[i] // w, join[i] % w] = to[i]
        n = _fill_frontier(z, labels, join, m, cand, seen)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _open_pixels(z: np.ndarray, labels: np.ndarray, out: np.ndarray
                 ) -> int:  # pragma: no cover - compiled
    """Flat indices of the unlabelled finite pixels into ``out``; their number."""
    h, w = labels.shape
    n = 0
    for r in range(h):
        for c in range(w):
            if labels[r, c] == 0 and np.isfinite(z[r, c]):
                out[n] = r * w + c
                n += 1
    return n


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _fill_decide(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, bound: np.ndarray,
                 cand: np.ndarray, n: int, join: np.ndarray, to: np.ndarray
                 ) -> int:  # pragma: no cover - compiled
    """One pass's joins (pixel, label) from the labels as they are; their number."""
    w = labels.shape[1]
    m = 0
    for i in range(n):
        k = _fill_choice(z, labels, coeffs, bound, cand[i] // w, cand[i] % w)
        if k > 0:
            join[m], to[m] = cand[i], k
            m += 1
    return m


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _fill_frontier(z: np.ndarray, labels: np.ndarray, join: np.ndarray, m: int,
                   out: np.ndarray, seen: np.ndarray) -> int:  # pragma: no cover - compiled
    """The open pixels 8-adjacent to the ``m`` joined ones, each once, into ``out``."""
    h, w = labels.shape
    n = 0
    for i in range(m):
        r, c = join[i] // w, join[i] % w
        for rr in range(max(r - 1, 0), min(r + 2, h)):
            for cc in range(max(c - 1, 0), min(c + 2, w)):
                q = rr * w + cc
                if not seen[q] and labels[rr, cc] == 0 and np.isfinite(z[rr, cc]):
                    seen[q] = True
                    out[n] = q
                    n += 1
    for i in range(n):
        seen[out[i]] = False
    return n


@njit(cache=True, nogil=True, error_model="numpy")
def explained_faces(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, ids: np.ndarray, k: int,
                    coeffs: np.ndarray, limit: np.ndarray, regions: np.ndarray
                    ) -> np.ndarray:  # pragma: no cover - compiled
    """``recover._drop_explained``'s test: faces 0..k some region's surface explains.

    Face f is explained when, for a region in ``regions``, the mean of the
    squared residuals of its pixels (``rows``, ``cols``, face ``ids``) to the
    region's surface ``coeffs`` is below the region's ``limit``. The sums run
    in pixel order, as ``np.bincount`` adds them in the reference.
    """
    size = np.zeros(k + 1, np.int64)
    for i in range(ids.size):
        size[ids[i]] += 1
    for f in range(k + 1):
        size[f] = max(size[f], 1)
    explained = np.zeros(k + 1, np.bool_)
    acc = np.empty(k + 1)
    for region in regions:
        for f in range(k + 1):
            acc[f] = 0.0
        a = coeffs[region]
        for i in range(ids.size):
            r = z[rows[i], cols[i]] - _quadric_at(a, float(rows[i]), float(cols[i]))
            acc[ids[i]] += r * r
        for f in range(k + 1):
            if acc[f] / size[f] < limit[region]:
                explained[f] = True
    return explained



# --------------------------------------------------------------------------- crease kinds


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _window_labels(padded: np.ndarray, r: int, c: int, side: int, own: int, seen: np.ndarray,
                   times: np.ndarray) -> int:  # pragma: no cover - compiled
    """The other positive labels of a window into ``seen`` with their pixels; their number."""
    m = 0
    for pr in range(r, r + side):
        for pc in range(c, c + side):
            other = padded[pr, pc]
            if other <= 0 or other == own:
                continue
            k = 0
            while k < m and seen[k] != other:
                k += 1
            if k == m:
                seen[m], times[m] = other, 0
                m += 1
            times[k] += 1
    return m


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _doubled_rows(out: np.ndarray, used: int) -> np.ndarray:  # pragma: no cover - compiled
    """``out`` (V, 3) with twice the rows, the first ``used`` copied."""
    grown = np.empty((2 * out.shape[0], 3), np.int64)
    for q in range(used):  # a loop: slice assignment compiles numba's generic code
        grown[q, 0], grown[q, 1], grown[q, 2] = out[q, 0], out[q, 1], out[q, 2]
    return grown


@njit(cache=True, nogil=True, error_model="numpy")
def crease_votes(padded: np.ndarray, rows: np.ndarray, cols: np.ndarray, own: np.ndarray,
                 mine: np.ndarray, coeffs: np.ndarray, reach: int
                 ) -> np.ndarray:  # pragma: no cover - compiled
    """``refine.boundaries.crease_kinds``' votes, one per pixel and nearby region.

    For each pixel ``rows, cols`` (label ``own``, own surface's height
    ``mine``) and each other positive label within chessboard ``reach``
    (``padded``: the labels padded by ``reach``), the pair key ``own * (n+1)
    + other``, how many of the window's pixels of that label vote "own
    surface lower" (0 or all of them: the comparison is the pixel's) and how
    many there are. Each pair's surface is evaluated once per pixel, as
    ``grow.evaluate_quadric`` evaluates it.

    Returns
    -------
    numpy.ndarray
        int64 (V, 3): key, lower votes, votes.
    """
    n1 = coeffs.shape[0]
    side = 2 * reach + 1
    seen = np.empty(side * side, np.int64)
    times = np.empty(side * side, np.int64)
    out = np.empty((2 * rows.size + side * side, 3), np.int64)  # grown when full
    j = 0
    for i in range(rows.size):
        m = _window_labels(padded, rows[i], cols[i], side, own[i], seen, times)
        if j + m > out.shape[0]:
            out = _doubled_rows(out, j)
        for k in range(m):
            theirs = _coeff_at(coeffs, seen[k], float(rows[i]), float(cols[i]))
            out[j, 0], out[j, 1], out[j, 2] = own[i] * n1 + seen[k], 0, times[k]
            if mine[i] < theirs:
                out[j, 1] = times[k]
            j += 1
    return out[:j]


@njit(cache=True, nogil=True, error_model="numpy")
def boundary_labels(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, scale: float,
                    smoothness: float, kinds: np.ndarray, close: float, creases: bool,
                    out: np.ndarray, first: int, stop: int
                    ) -> None:  # pragma: no cover - compiled
    """``refine.boundaries``' pass on rows ``first..stop-1``: boundary pixels' cheapest labels.

    A boundary pixel is labelled and has an 8-neighbour of another positive
    label; it takes, of its own label and its neighbours' (in raster order of
    the 3x3 window, a tie keeping the earlier), the one of least ``r^2 /
    scale + smoothness * m``; with ``creases``, the crease rule's label
    (``kinds``) where it decides. Residuals as ``grow.evaluate_quadric``.
    Written into ``out`` (a copy of ``labels``, which is only read): row
    bands may run at once and give the same labels.
    """
    height, width = labels.shape
    near = np.zeros(8, np.int64)
    for r in range(first, stop):
        for c in range(width):
            own = np.int64(labels[r, c])
            if own == 0:
                continue
            edge = False
            k = 0
            for dr in range(-1, 2):
                for dc in range(-1, 2):
                    if dr == 0 and dc == 0:
                        continue
                    rr, cc = r + dr, c + dc
                    lab = np.int64(0)
                    if 0 <= rr < height and 0 <= cc < width:
                        lab = np.int64(labels[rr, cc])
                    near[k] = lab
                    if lab > 0 and lab != own:
                        edge = True
                    k += 1
            if edge:
                out[r, c] = _cheapest(z[r, c], near, own, coeffs, float(r), float(c), scale,
                                      smoothness, kinds, close, creases)


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _disagreeing(near: np.ndarray, lab: np.int64) -> int:  # pragma: no cover - compiled
    """The labelled neighbours whose label is not ``lab``."""
    m = 0
    for k in range(8):
        if near[k] > 0 and near[k] != lab:
            m += 1
    return m


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cheapest(h: float, near: np.ndarray, own: np.int64, coeffs: np.ndarray, y: float, x: float,
              scale: float, smoothness: float, kinds: np.ndarray, close: float, creases: bool
              ) -> np.int64:  # pragma: no cover - compiled
    """One boundary pixel of :func:`boundary_labels`."""
    res = h - _coeff_at(coeffs, own, y, x)
    best, lowest = own, res * res / scale + smoothness * _disagreeing(near, own)
    for k in range(8):
        lab = near[k]
        if lab > 0 and lab != best:
            res = h - _coeff_at(coeffs, lab, y, x)
            trial = res * res / scale + smoothness * _disagreeing(near, lab)
            if trial < lowest:
                best, lowest = lab, trial
    if not creases:
        return best
    mine = _coeff_at(coeffs, own, y, x)
    decided, visible, margin = False, own, 0.0
    for k in range(8):
        other = near[k] if near[k] > 0 and near[k] != own else np.int64(0)
        kind = kinds[own, other]
        if kind == 0:
            continue
        theirs = _coeff_at(coeffs, other, y, x)
        if abs(theirs - mine) < close:
            decided = True
            if kind * (theirs - mine) > margin:
                visible, margin = other, kind * (theirs - mine)
    return visible if decided else best


@njit(cache=True, nogil=True, error_model="numpy")
def neighbour_accepts(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, limit: np.ndarray,
                      rows: np.ndarray, cols: np.ndarray, reach: int
                      ) -> np.ndarray:  # pragma: no cover - compiled
    """``refine.recover``'s test: a region within ``reach`` of each pixel would grow into it.

    Pixel i is accepted when a positive label L of ``labels`` within
    chessboard ``reach`` predicts it with a squared residual below
    ``limit[L]``, the residual computed as ``grow.evaluate_quadric`` does.
    """
    height, width = labels.shape
    out = np.zeros(rows.size, np.bool_)
    for i in range(rows.size):
        r, c = rows[i], cols[i]
        y, x = float(r), float(c)
        for rr in range(max(r - reach, 0), min(r + reach + 1, height)):
            for cc in range(max(c - reach, 0), min(c + reach + 1, width)):
                lab = np.int64(labels[rr, cc])  # one signature of _coeff_at
                if lab > 0:
                    res = z[r, c] - _coeff_at(coeffs, lab, y, x)
                    if res * res < limit[lab]:
                        out[i] = True
                        break
            if out[i]:
                break
    return out


compile_ahead_when_cold()
