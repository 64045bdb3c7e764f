"""Compiled (numba) kernels of the edge stage, Sec. V-1 and V-2 of Al-Hujazi & Sood (1990).

The fast path of :func:`rangeseg_cli.edges.detect_edges`. The numpy functions
in :mod:`rangeseg_cli.edges` are the reference: these kernels give bit-for-bit
the same AR values and hence exactly the same edge maps, because every pixel's
sums are made of the same float64 operations in the same order (no fastmath,
so no reassociation and no fused multiply-add).

Notes
-----
One pass of Sec. V (step 1, 2a or 2b) is one sweep down the image rows:

1. For each row and each of the four directions of Fig. 8, the reach of the
   adaptive mask along +d and -d (consecutive usable pixels, at most half the
   mask; Fig. 9), cut to the shorter side for ``"symmetric"`` truncation.
2. AR_d = |sum_k w_k z(p + k d) / sum_k w_k - z(p)| over the kept taps (eq. 3),
   summed as the reference does: centre tap, then +1, -1, +2, -2, ...
3. The AR rows of the last ``2 radius + 1`` rows are kept in a ring buffer;
   once row ``q + radius`` is done, row ``q`` gets the threshold and
   local-maximum test along each direction (ties within ``1e-9 (1 + AR)``
   count as maxima, as in :func:`rangeseg_cli.edges.local_maximum`).

Memory beyond the inputs: one padded copy of the heights and of the usable
mask, and a few row buffers; no per-direction image temporaries.

Importing this module imports numba and needs it; :mod:`rangeseg_cli.edges`
imports it lazily and only when numba is installed.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Row and column steps of the four directions of Fig. 8 (as ``edges.DIRECTIONS``).
_DY = np.array([0, 1, 1, 1], dtype=np.int64)
_DX = np.array([1, 0, 1, -1], dtype=np.int64)


@njit(cache=True, nogil=True, error_model="numpy")
def _reach_row(okp: np.ndarray, row: int, pad: int, dy: int, dx: int, half: int,
               run: np.ndarray, reach: np.ndarray) -> None:  # pragma: no cover - compiled
    """Consecutive usable pixels from each pixel of ``row`` along (dy, dx), at most ``half``.

    Fig. 9: the adaptive mask stops before the first excluded pixel.
    ``okp`` is the usable mask padded by ``pad`` >= ``half`` with False.
    """
    width = reach.shape[0]
    for c in range(width):
        run[c] = 1
        reach[c] = 0
    for k in range(1, half + 1):
        src = okp[row + pad + k * dy, pad + k * dx: pad + k * dx + width]
        for c in range(width):
            run[c] &= src[c]
            reach[c] += run[c]


@njit(cache=True, nogil=True, error_model="numpy")
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


@njit(cache=True, nogil=True, error_model="numpy")
def _ar_row(zp: np.ndarray, okp: np.ndarray, row: int, pad: int, dy: int, dx: int,
            w: np.ndarray, den_table: np.ndarray, symmetric: bool, work: np.ndarray,
            num: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """AR along (dy, dx) for every pixel of ``row`` with the adaptive mask (eq. 3, Fig. 9).

    ``work`` holds four uint8 row buffers (run, reach +d, run, reach -d); ``num``
    a float64 row buffer; ``out`` receives the AR row (0 at excluded pixels).
    """
    half = w.shape[0] // 2
    width = out.shape[0]
    rp, rm = work[1], work[3]
    _reach_row(okp, row, pad, dy, dx, half, work[0], rp)
    _reach_row(okp, row, pad, -dy, -dx, half, work[2], rm)
    if symmetric:
        for c in range(width):
            m = min(rp[c], rm[c])
            rp[c] = m
            rm[c] = m
    ok0 = okp[row + pad, pad: pad + width]
    z0 = zp[row + pad, pad: pad + width]
    for c in range(width):
        num[c] = w[half] * (z0[c] if ok0[c] else 0.0)
    for k in range(1, half + 1):
        wp, wm = w[half + k], w[half - k]
        kk = np.uint8(k)
        zplus = zp[row + pad + k * dy, pad + k * dx: pad + k * dx + width]
        zminus = zp[row + pad - k * dy, pad - k * dx: pad - k * dx + width]
        for c in range(width):
            xp, xm = zplus[c], zminus[c]
            num[c] += (xp if rp[c] >= kk else 0.0) * wp
            num[c] += (xm if rm[c] >= kk else 0.0) * wm
    den = out  # the AR row is filled last: first hold the mask sums there
    for c in range(width):
        den[c] = den_table[rp[c], rm[c]]
    for c in range(width):
        x = z0[c]
        zc = x if ok0[c] else 0.0
        ar = abs(num[c] / den[c] - zc)
        out[c] = ar if ok0[c] else 0.0


@njit(cache=True, nogil=True, error_model="numpy")
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


@njit(cache=True, nogil=True, error_model="numpy")
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
        Cut both sides of the mask at the shorter reach (SPEC *Truncation*).

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
                _ar_row(zp, okp, r, pad, _DY[d], _DX[d], w, den_table, symmetric, work, num,
                        ring[d, r % nring])
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
            _ar_row(zp, okp, r, pad, _DY[d], _DX[d], w, den_table, symmetric, work, num,
                    out[d, r])
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def _pad(z: np.ndarray, pad: int) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover
    """Heights padded with 0 and the usable (not NaN) mask padded with False."""
    height, width = z.shape
    zp = np.zeros((height + 2 * pad, width + 2 * pad))
    okp = np.zeros((height + 2 * pad, width + 2 * pad), dtype=np.bool_)
    for r in range(height):
        for c in range(width):
            v = z[r, c]
            zp[r + pad, c + pad] = v
            okp[r + pad, c + pad] = not np.isnan(v)
    return zp, okp


@njit(cache=True, nogil=True, error_model="numpy")
def _exclude(okp: np.ndarray, pad: int, edges: np.ndarray) -> None:  # pragma: no cover
    """Mark ``edges`` as unusable for later passes (Sec. V-2: masks stop before them)."""
    height, width = edges.shape
    for r in range(height):
        for c in range(width):
            if edges[r, c]:
                okp[r + pad, c + pad] = False


@njit(cache=True, nogil=True, error_model="numpy")
def edge_maps(z: np.ndarray, w_step: np.ndarray, step_threshold: float, w_roof: np.ndarray,
              threshold_a: float, threshold_b: float, radius: int, step_symmetric: bool,
              roof_symmetric: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Steps 1, 2a and 2b of Sec. V in three fused passes (compiled; see detect_edges_numba).

    Returns
    -------
    step, roof_a, roof_b
        bool (H, W) maps, as :func:`rangeseg_cli.edges.step_edges` and
        :func:`rangeseg_cli.edges.roof_edges` give them.
    """
    pad = max(w_step.shape[0] // 2, w_roof.shape[0] // 2, radius, 1)
    zp, okp = _pad(z, pad)
    # Step 1: step edges, small filter, invalid pixels excluded (Sec. V-1)
    step = edges_pass(zp, okp, pad, w_step, step_threshold, 1, step_symmetric)
    # Step 2a: roof edges, large filter, high threshold, step edges excluded (Sec. V-2a)
    _exclude(okp, pad, step)
    roof_a = edges_pass(zp, okp, pad, w_roof, threshold_a, radius, roof_symmetric)
    # Step 2b: lower threshold, step and 2a roof edges excluded (Sec. V-2b)
    _exclude(okp, pad, roof_a)
    roof_b = edges_pass(zp, okp, pad, w_roof, threshold_b, radius, roof_symmetric)
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
    return edge_maps(np.require(z, np.float64, ["C", "W"]),
                     np.ascontiguousarray(w_step, dtype=np.float64), float(step_threshold),
                     np.ascontiguousarray(w_roof, dtype=np.float64), float(threshold_a),
                     float(threshold_b), int(radius), symmetric, symmetric)
