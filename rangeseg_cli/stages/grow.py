"""Step 4: least-squares quadratic region growing (Al-Hujazi & Sood 1990, Sec. V-4).

Each connected component of step 3 is fitted with the quadric
``z = a0 + a1 x + a2 y + a3 x^2 + a4 x y + a5 y^2`` (x = col, y = row). Its
average error ``e_A`` is the total squared error over the number of pixels.
An edge pixel joins a neighbouring surface when its squared residual to that
surface is below ``10 e_A``; one-pixel-thick edges between two surfaces stay
("no merging is allowed"). One pass sufficed in the paper; the fit is then
repeated for the final surface parameters (:mod:`rangeseg_cli.stages.surfaces`).

Notes
-----
Decisions where the paper is silent (docs/REPRODUCTION.md):

* **Simultaneous passes.** Every pixel of a pass is decided from the labels
  at the start of that pass, so the result does not depend on a scan order
  and the pass is a handful of whole-image array operations. A consequence:
  the two pixels of a two-pixel-thick edge band, each touching only its own
  side, both join their sides in the same pass, and the two regions then
  abut (still two labels; nothing is merged).
* **Fixed seed fits.** The surfaces and their e_A come from the components
  and are not refitted between passes: the components lie "well inside the
  object faces" (Sec. V-3), so growth cannot drag a fit across an edge.
* **e_A floor.** ``e_A = max(MSE of the component, grow.min_error)``.
  Noise-free 8-bit data has an MSE of about 1/12 from quantisation alone, and
  an exactly planar synthetic face an MSE of 0, which would block all growth;
  the floor (0.25 by default) keeps the acceptance band at least
  ``error_factor * min_error`` (2.5 squared units, 1.6 units of residual).
* **passes = 0** repeats until a pass changes nothing. Growth only ever turns
  label 0 into a label, so this ends after at most as many passes as there
  are unlabelled pixels, which is the safety cap.

Backends: the numpy functions of this module (``np.bincount`` moment sums over
the fitted pixels, whole-image array operations for a pass) are the
reference. When numba is installed, :func:`region_fits` and :func:`grow_pass`
run the compiled kernels of :mod:`rangeseg_cli.kernels.compiled` instead: per-region
sums accumulated in the same raster order from the same float64 operations,
so the fits, their e_A and hence every growing decision (a residual compared
with ``error_factor * e_A``) are bitwise the same. ``RANGESEG_PURE_NUMPY=1``
or ``backend="numpy"`` selects the reference, as for the edges
(:func:`rangeseg_cli.kernels.backend.select_kernels`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from scipy import ndimage, special

from ..config import GrowConfig
from ..kernels.backend import Backend, select_deferred, select_kernels
from .rangeimage import require_shape_of_z

#: Number of terms of the quadric, of the plane and of the constant model.
ORDER_TERMS: dict[int, int] = {2: 6, 1: 3, 0: 1}

#: A normalised moment matrix whose smallest / largest eigenvalue is below this
#: is singular for the quadric, and the fit falls back to the plane (pseudo-inverse
#: with this relative cut-off).
RCOND = 1e-10

#: The 8-neighbourhood used by the growing test (Sec. V-4).
EIGHT_NEIGHBOURS = np.ones((3, 3), dtype=bool)


#: Exponents (of u, of v) of the six quadric terms 1, u, v, u^2, u v, v^2.
_EXPONENTS: tuple[tuple[int, int], ...] = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))


#: Exponents of u and of v of the entries phi_i phi_j of the normal equations (6, 6).
_POWER_U = np.add.outer(*[np.array([e[0] for e in _EXPONENTS])] * 2)
_POWER_V = np.add.outer(*[np.array([e[1] for e in _EXPONENTS])] * 2)


def _basis(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The six quadric terms (1, u, v, u^2, u v, v^2), stacked as (6, N)."""
    return np.stack([np.ones_like(u), u, v, u * u, u * v, v * v])


@dataclass(frozen=True)
class RegionMoments:
    """Per-region sums of the quadric fits of Sec. V-4 (labels 0..n; row 0 unused).

    Attributes
    ----------
    counts
        float64 (n+1,) pixels fitted.
    cx, cy
        float64 (n+1,) centre column and row (the centroid).
    scale
        float64 (n+1,) RMS spread of the pixels about the centre, at least 1:
        the frame ``u = (x - cx) / scale``, ``v = (y - cy) / scale``.
    sums
        float64 (n+1, 5, 5): ``sum u^a v^b`` at [a, b], a + b <= 4.
    rhs
        float64 (n+1, 6): ``sum phi_i z``, phi = (1, u, v, u^2, u v, v^2); its
        column 0 is the sum of the heights.
    """

    counts: np.ndarray
    cx: np.ndarray
    cy: np.ndarray
    scale: np.ndarray
    sums: np.ndarray
    rhs: np.ndarray


@dataclass(frozen=True)
class _Pixels:
    """The fitted pixels of the numpy reference: labels, heights and frame coordinates."""

    lab: np.ndarray
    zs: np.ndarray
    u: np.ndarray
    v: np.ndarray


def _frames(rows: np.ndarray, cols: np.ndarray, lab: np.ndarray, n: int
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-region centre (cx, cy), scale and pixel count for conditioning."""
    counts = np.bincount(lab, minlength=n + 1).astype(np.float64)
    safe = np.maximum(counts, 1.0)
    cx = np.bincount(lab, cols, minlength=n + 1) / safe
    cy = np.bincount(lab, rows, minlength=n + 1) / safe
    var = (np.bincount(lab, (cols - cx[lab]) ** 2, minlength=n + 1)
           + np.bincount(lab, (rows - cy[lab]) ** 2, minlength=n + 1)) / (2.0 * safe)
    scale = np.maximum(np.sqrt(var), 1.0)
    return cx, cy, scale, counts


def _moment_sums(u: np.ndarray, v: np.ndarray, zs: np.ndarray, lab: np.ndarray, n: int
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The 15 monomial sums ``sum u^a v^b`` (a + b <= 4) and the 6 ``sum phi_i z`` per region.

    Each is summed per region once with ``np.bincount`` (in raster order, as
    the compiled :func:`rangeseg_cli.kernels.compiled.run_moments` adds them).
    """
    pu = [np.ones_like(u), u, u * u, u * u * u, (u * u) ** 2]
    pv = [np.ones_like(v), v, v * v, v * v * v, (v * v) ** 2]
    sums = np.zeros((n + 1, 5, 5))
    for a in range(5):
        for b in range(5 - a):
            sums[:, a, b] = np.bincount(lab, pu[a] * pv[b], minlength=n + 1)
    rhs = np.stack([np.bincount(lab, pu[a] * pv[b] * zs, minlength=n + 1)
                    for a, b in _EXPONENTS], axis=1)
    return sums, rhs


def _reference_moments(z: np.ndarray, labels: np.ndarray, n: int,
                       origin: tuple[int, int] = (0, 0)) -> tuple[RegionMoments, _Pixels]:
    """The numpy reference of :func:`~rangeseg_cli.kernels.compiled.run_moments`; the pixels."""
    rows_i, cols_i = np.nonzero((labels > 0) & np.isfinite(z))
    lab = labels[rows_i, cols_i].astype(np.intp)
    zs = np.asarray(z, dtype=np.float64)[rows_i, cols_i]
    rows = (rows_i + origin[0]).astype(np.float64)
    cols = (cols_i + origin[1]).astype(np.float64)
    cx, cy, scale, counts = _frames(rows, cols, lab, n)
    u, v = (cols - cx[lab]) / scale[lab], (rows - cy[lab]) / scale[lab]
    sums, rhs = _moment_sums(u, v, zs, lab, n)
    return RegionMoments(counts, cx, cy, scale, sums, rhs), _Pixels(lab, zs, u, v)


def _reference_sse(pixels: _Pixels, coef: np.ndarray, n: int) -> np.ndarray:
    """Sum of squared residuals per region of fits ``coef`` (F, n+1, 6) in frame coordinates.

    The fit is summed term by term in the order of phi, as
    :func:`rangeseg_cli.kernels.compiled.run_sse` does.
    """
    phi = _basis(pixels.u, pixels.v)
    out = np.zeros((coef.shape[0], n + 1))
    for f in range(coef.shape[0]):
        c = coef[f][pixels.lab]
        fit = c[:, 0] * phi[0]
        for i in range(1, 6):
            fit = fit + c[:, i] * phi[i]
        resid = pixels.zs - fit
        out[f] = np.bincount(pixels.lab, resid * resid, minlength=n + 1)
    return out


def _normal_equations(m: RegionMoments) -> tuple[np.ndarray, np.ndarray]:
    """Per-region normal equations divided by the pixel count: (n+1, 6, 6) and (n+1, 6).

    The 36 entries need only the 15 monomial sums of :class:`RegionMoments`.
    """
    safe = np.maximum(m.counts, 1.0)
    mat = m.sums[:, _POWER_U, _POWER_V]  # one gather
    return mat / safe[:, None, None], m.rhs / safe[:, None]


def _solve_cascade(mat: np.ndarray, rhs: np.ndarray, counts: np.ndarray, order: int
                   ) -> np.ndarray:
    """Solve each region's normal equations at the highest usable order <= ``order``.

    A region gets the quadric (6 terms) when it has at least 6 pixels and a
    well-conditioned moment matrix (smallest / largest eigenvalue > RCOND);
    every other region gets the plane: solved directly when its 3x3 matrix
    is well-conditioned by the same test (and it has 3 pixels or more), else
    through the pseudo-inverse, which drops exactly the degenerate
    directions: pixels on a line give a line fit along it, a single pixel (or
    ``order=0``) the constant. Each order is one batched call per case over
    the stacked systems (the pseudo-inverse's eigendecomposition costs ~8
    times a direct solve; the split, merge and recut fit planes thousands
    of times per frame).
    """
    coef = np.zeros(rhs.shape)
    todo = np.flatnonzero(counts > 0)  # indices: each system as a boolean mask would take it
    if order == 2:
        todo = _solve_conditioned(mat, rhs, counts, todo, 6, coef)
    k = ORDER_TERMS[min(order, 1)]
    if k == 3:
        todo = _solve_conditioned(mat, rhs, counts, todo, 3, coef)
    if todo.size:
        pinv = np.linalg.pinv(mat[todo, :k, :k], rcond=RCOND, hermitian=True)
        coef[todo, :k] = (pinv @ rhs[todo, :k, None])[..., 0]
    return coef


def _solve_conditioned(mat: np.ndarray, rhs: np.ndarray, counts: np.ndarray, todo: np.ndarray,
                       k: int, coef: np.ndarray) -> np.ndarray:
    """Solve the leading k x k systems of ``todo`` that are well-conditioned, into ``coef``.

    Well-conditioned: at least k pixels and smallest / largest eigenvalue >
    RCOND. Returns the indices left (for a lower order or the pseudo-inverse).
    """
    if not todo.size:
        return todo
    if todo.size == 1:  # one system (a crop's region, most calls): no gathers, same bits
        t = int(todo[0])
        if counts[t] < k:
            return todo
        eig = np.linalg.eigvalsh(mat[t, :k, :k])
        if not eig[0] > RCOND * eig[-1]:
            return todo
        coef[t, :k] = np.linalg.solve(mat[t, :k, :k], rhs[t, :k, None])[:, 0]
        return todo[:0]
    eig = np.linalg.eigvalsh(mat[todo, :k, :k])
    good = (counts[todo] >= k) & (eig[:, 0] > RCOND * eig[:, -1])
    ok = todo[good]
    if ok.size:
        coef[ok, :k] = np.linalg.solve(mat[ok, :k, :k], rhs[ok, :k, None])[..., 0]
    return todo[~good]


def _to_image_coefficients(coef: np.ndarray, cx: np.ndarray, cy: np.ndarray,
                           scale: np.ndarray) -> np.ndarray:
    """Expand ``sum c_i phi_i(u, v)`` with ``u = (x - cx)/s``, ``v = (y - cy)/s`` in x, y."""
    c0, c1, c2, c3, c4, c5 = coef.T
    p = 1.0 / scale
    u0, v0 = -cx * p, -cy * p  # u = p x + u0, v = p y + v0
    a = np.empty_like(coef)
    a[:, 0] = c0 + c1 * u0 + c2 * v0 + c3 * u0 * u0 + c4 * u0 * v0 + c5 * v0 * v0
    a[:, 1] = c1 * p + 2.0 * c3 * p * u0 + c4 * p * v0
    a[:, 2] = c2 * p + c4 * p * u0 + 2.0 * c5 * p * v0
    a[:, 3] = c3 * p * p
    a[:, 4] = c4 * p * p
    a[:, 5] = c5 * p * p
    return a


def _check_labels(z: np.ndarray, labels: np.ndarray, n: int, orders: tuple[int, ...]) -> None:
    """Validate the inputs of :func:`fit_models`."""
    require_shape_of_z(z, labels=labels)
    if labels.size and (labels.min() < 0 or labels.max() > n):
        raise ValueError(f"`labels` must lie in 0..n = 0..{n}, got {labels.min()}.."
                         f"{labels.max()}")
    bad = [o for o in orders if o not in ORDER_TERMS]
    if bad:
        raise ValueError(f"`order` = {bad[0]!r}: allowed 0, 1 or 2")


@dataclass(frozen=True)
class RegionFits:
    """Least-squares fits of regions 1..n at several orders, with the regions' statistics.

    Attributes
    ----------
    fits
        Per order asked for: (coeffs, mse) as :func:`fit_quadrics` returns them.
    counts
        int64 (n+1,) pixels fitted per region.
    centroid_row, centroid_col
        float64 (n+1,) centre of area of each region (0 for empty ones).
    mean_height
        float64 (n+1,) mean of the fitted heights.
    moments
        The moment sums the fits were solved from (for
        :class:`~rangeseg_cli.refine.graph.RegionGraph`).
    """

    fits: list[tuple[np.ndarray, np.ndarray]]
    counts: np.ndarray
    centroid_row: np.ndarray
    centroid_col: np.ndarray
    mean_height: np.ndarray
    moments: RegionMoments


def region_fits(z: np.ndarray, labels: np.ndarray, n: int, orders: tuple[int, ...] = (2,),
                *, backend: Backend = "auto", origin: tuple[int, int] = (0, 0)
                ) -> RegionFits:
    """Least-squares fits of every region 1..n at several model orders at once (Sec. V-4).

    The moment sums are gathered once and shared by all orders (the plane's
    normal equations are the leading 3x3 block of the quadric's); so are the
    regions' pixel counts, centroids and mean heights.

    Parameters
    ----------
    z
        float64 (H, W) heights; NaN pixels are left out.
    labels
        int (H, W) region labels 0..n; 0 is not fitted.
    n
        Number of regions (the largest label).
    orders
        Highest model order of each fit: 2 quadric, 1 plane, 0 constant.
    backend
        ``"numpy"``: ``np.bincount`` over the pixels (the reference);
        ``"numba"``: :func:`rangeseg_cli.kernels.compiled.run_moments` and
        ``run_sse``, which add the same terms in the same order (identical
        results); ``"auto"``: as :func:`rangeseg_cli.stages.edges.detect_edges`.
    origin
        Image (row, col) of ``z[0, 0]`` when ``z`` and ``labels`` are a crop
        of a frame: the fits are in the frame's coordinates, bit for bit
        those of the whole frame when the crop holds every labelled pixel,
        for the cost of the crop only.

    Returns
    -------
    RegionFits
        The fits per order and the regions' statistics.

    Raises
    ------
    ValueError
        When the shapes differ, a label is outside 0..n, an order is not 0, 1,
        2 or ``backend`` is unknown.
    """
    labels = np.asarray(labels)
    _check_labels(z, labels, n, orders)
    kernels = select_kernels(backend)
    if kernels is None:
        moments, pixels = _reference_moments(z, labels, n, origin)
        coef = _solve_orders(moments, orders)
        sse = _reference_sse(pixels, coef, n)
        image = np.stack([_to_image_coefficients(c, moments.cx, moments.cy, moments.scale)
                          for c in coef])
    else:
        zc = np.require(z, np.float64, ["C", "W"])
        runs = kernels.fitted_runs(zc, np.require(labels, np.int32, ["C", "W"]))
        moments, coef, sse = _run_fits(kernels, zc, runs, n, orders, origin)
        image = kernels.image_coefficients(coef, moments.cx, moments.cy, moments.scale)
    safe = np.maximum(moments.counts, 1.0)
    fits = [(a, e / safe) for a, e in zip(image, sse, strict=True)]
    return RegionFits(fits, moments.counts.astype(np.int64), moments.cy, moments.cx,
                      moments.rhs[:, 0] / safe, moments)


def _solve_orders(moments: RegionMoments, orders: tuple[int, ...]) -> np.ndarray:
    """Coefficients (F, n+1, 6), in the regions' frames, of each order's fits from ``moments``."""
    mat, rhs = _normal_equations(moments)
    return np.stack([_solve_cascade(mat, rhs, moments.counts, order) for order in orders])


def _run_fits(kernels: ModuleType, zc: np.ndarray, runs: tuple[np.ndarray, ...], n: int,
              orders: tuple[int, ...], origin: tuple[int, int]
              ) -> tuple[RegionMoments, np.ndarray, np.ndarray]:
    """The compiled sweeps of :func:`region_fits` over the runs of labels 1..n.

    Returns the moments, the coefficients (F, n+1, 6) in the regions' frames
    and the sums of squared errors (F, n+1).
    """
    moments = RegionMoments(*kernels.run_moments(zc, runs, n, *origin))
    coef = _solve_orders(moments, orders)
    sse = kernels.run_sse(zc, runs, moments.cx, moments.cy, moments.scale, coef, *origin)
    return moments, coef, sse


def union_moments(moments: RegionMoments, i: int, j: int
                  ) -> tuple[float, float, float, float, np.ndarray, np.ndarray]:
    """The moment sums of regions i and j together, as one region's (Sec. V-4).

    Each region's sums (in its own frame, :class:`RegionMoments`) are carried
    into a frame of the union (``u' = a u + b``: the binomial expansion, a
    small matrix product per region) and added.

    Returns
    -------
    tuple
        ``(count, cx, cy, scale, sums (5, 5), rhs (6,))``: one row of
        :class:`RegionMoments` for the union.
    """
    ci, cj = moments.counts[i], moments.counts[j]
    total = ci + cj
    cx = (ci * moments.cx[i] + cj * moments.cx[j]) / total
    cy = (ci * moments.cy[i] + cj * moments.cy[j]) / total
    scale = max(moments.scale[i], moments.scale[j])
    sums = np.zeros((5, 5))
    rhs = np.zeros((3, 3))
    for k in (i, j):
        a = moments.scale[k] / scale
        tu = _affine_powers(a, (moments.cx[k] - cx) / scale)
        tv = _affine_powers(a, (moments.cy[k] - cy) / scale)
        sums += tu @ moments.sums[k] @ tv.T
        r = moments.rhs[k]  # (1, u, v, u^2, u v, v^2) z as [power of u, power of v]
        rhs += tu[:3, :3] @ np.array([[r[0], r[2], r[5]], [r[1], r[4], 0.0],
                                      [r[3], 0.0, 0.0]]) @ tv[:3, :3].T
    vec = np.array([rhs[e] for e in _EXPONENTS])
    return float(total), float(cx), float(cy), float(scale), sums, vec


def moment_fit(sums: np.ndarray, rhs: np.ndarray, count: float, square: float,
               order: int = 2) -> tuple[np.ndarray, float]:
    """The least-squares fit of one region from its moment sums (Sec. V-4).

    Solved as :func:`region_fits` solves it (:func:`_solve_cascade`); the
    squared error is ``sum z^2 - 2 c.r + c.M c``.

    Parameters
    ----------
    sums, rhs
        (5, 5) and (6,): one row of :class:`RegionMoments`.
    count
        Pixels of the region (> 0).
    square
        Sum of its squared heights.
    order
        2 quadric, 1 plane, 0 constant.

    Returns
    -------
    tuple
        The six coefficients in the region's frame (``u, v``; zeros beyond
        the order) and the mean squared error, at least 0.
    """
    mat = sums[_POWER_U, _POWER_V]
    coef = _solve_cascade((mat / count)[None], (rhs / count)[None], np.array([count]),
                          order)[0]
    sse = square - 2.0 * float(coef @ rhs) + float(coef @ mat @ coef)
    return coef, max(sse / count, 0.0)


def image_coefficients(coef: np.ndarray, cx: float, cy: float, scale: float) -> np.ndarray:
    """One fit's six coefficients in a region's frame, as image coefficients a0..a5."""
    return _to_image_coefficients(coef[None], np.array([cx]), np.array([cy]),
                                  np.array([scale]))[0]


def sums_of_squares(z: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Sum of squared heights of each label's finite pixels, float64 (n+1,).

    The ``squares`` of :class:`~rangeseg_cli.refine.graph.RegionGraph`.
    """
    keep = (labels > 0) & np.isfinite(z)
    return np.bincount(labels[keep], z[keep] ** 2, minlength=n + 1)


def _affine_powers(a: float, b: float) -> np.ndarray:
    """(5, 5) T with ``(a u + b)^p = sum_k T[p, k] u^k`` for p = 0..4 (binomial)."""
    t = np.zeros((5, 5))
    for p in range(5):
        for k in range(p + 1):
            t[p, k] = math.comb(p, k) * a**k * b ** (p - k)
    return t


def fit_models(z: np.ndarray, labels: np.ndarray, n: int, orders: tuple[int, ...] = (2,),
               *, backend: Backend = "auto", origin: tuple[int, int] = (0, 0)
               ) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """Least-squares fits of every region 1..n at several model orders at once (Sec. V-4).

    The moment sums are gathered once and shared by all orders (see
    :func:`region_fits`, which also gives the regions' statistics).

    Parameters
    ----------
    z
        float64 (H, W) heights; NaN pixels are left out.
    labels
        int (H, W) region labels 0..n; 0 is not fitted.
    n
        Number of regions (the largest label).
    orders
        Highest model order of each fit: 2 quadric, 1 plane, 0 constant.
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` (identical results; see
        :func:`region_fits`).
    origin
        Of a crop, as in :func:`region_fits`.

    Returns
    -------
    fits : list of (coeffs, mse)
        Per order, as :func:`fit_quadrics` returns them.
    counts : numpy.ndarray
        int64 (n+1,): number of pixels fitted per region.
    """
    result = region_fits(z, labels, n, orders, backend=backend, origin=origin)
    return result.fits, result.counts


def union_sse(z: np.ndarray, labels: np.ndarray, pairs: np.ndarray, boxes: np.ndarray, *,
              backend: Backend = "auto") -> np.ndarray:
    """Squared error of one quadric of regions i and j together, for each pair (Sec. V-4).

    Beyond the paper: the recut (Sec. VIII's fit test on touching pairs)
    asks it of every pair of touching regions at once. Each pair's sum is
    the one :func:`region_fits` gives its pixels as one region (mean squared
    error times pixels), bit for bit: the reference fits each pair in its
    box; once compiled (:func:`~rangeseg_cli.kernels.backend.select_deferred`),
    :func:`rangeseg_cli.kernels.compiled.union_runs` gives every pair's runs
    at once, and one :func:`region_fits`-like sweep fits them all.

    Parameters
    ----------
    z
        float64 (H, W) heights; NaN pixels are left out.
    labels
        int32 (H, W) regions.
    pairs
        int64 (P, 2) the two regions of each pair.
    boxes
        int64 (P, 4) first row, stop row, first column, stop column of a box
        holding both regions of the pair.
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` (the same values).

    Returns
    -------
    numpy.ndarray
        float64 (P,).

    Raises
    ------
    ValueError
        When ``pairs`` or ``boxes`` is not (P, 2) and (P, 4), or a box is not
        within the image.
    """
    pairs = np.require(pairs, np.int64, ["C"])
    boxes = np.require(boxes, np.int64, ["C"])
    _check_boxes(labels.shape, pairs, boxes)
    kernels = select_deferred(backend, "union_runs")
    if kernels is None:
        return np.array([_union_sse(z, labels, i, j, box, backend) for (i, j), box
                         in zip(pairs.tolist(), boxes.tolist(), strict=True)], dtype=np.float64)
    zc = np.require(z, np.float64, ["C", "W"])
    runs = kernels.union_runs(zc, np.require(labels, np.int32, ["C", "W"]), pairs, boxes)
    moments, _, sse = _run_fits(kernels, zc, runs, pairs.shape[0], (2,), (0, 0))
    mse = sse[0] / np.maximum(moments.counts, 1.0)
    return (mse * moments.counts.astype(np.int64))[1:]


def _check_boxes(shape: tuple[int, ...], pairs: np.ndarray, boxes: np.ndarray) -> None:
    """Validate the pairs and boxes of :func:`union_sse` against an image of ``shape``."""
    if pairs.ndim != 2 or pairs.shape[1] != 2 or boxes.shape != (pairs.shape[0], 4):
        raise ValueError(f"`pairs` and `boxes` must be (P, 2) and (P, 4), got {pairs.shape} "
                         f"and {boxes.shape}")
    r0, r1, c0, c1 = boxes.T
    bad = (r0 < 0) | (r1 < r0) | (r1 > shape[0]) | (c0 < 0) | (c1 < c0) | (c1 > shape[1])
    if bad.any():
        raise ValueError(f"box {boxes[np.argmax(bad)].tolist()} is not within the image "
                         f"{shape[0]}x{shape[1]} (first row, stop row, first column, "
                         "stop column)")


def _union_sse(z: np.ndarray, labels: np.ndarray, i: int, j: int, box: list[int],
               backend: Backend) -> float:
    """:func:`union_sse` of one pair: its pixels in its box, fitted as one region."""
    r0, r1, c0, c1 = box
    sub = labels[r0:r1, c0:c1]
    ((_, mse),), counts = fit_models(z[r0:r1, c0:c1], ((sub == i) | (sub == j)).astype(np.int32),
                                     1, (2,), backend=backend, origin=(r0, c0))
    return float(mse[1]) * int(counts[1])


def fit_quadrics(z: np.ndarray, labels: np.ndarray, n: int, *, order: int = 2,
                 backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares quadric of every region 1..n at once (Sec. V-4).

    Moment sums of per-region centred and scaled coordinates (u, v: zero
    mean, unit RMS spread) are gathered with ``np.bincount`` (or the
    compiled kernel that adds the same terms in the same order) and the
    stacked 6x6 normal equations are solved in one batched call; there is no
    Python loop over pixels or regions. The solution is expanded back to
    image coordinates exactly.

    Parameters
    ----------
    z
        float64 (H, W) heights; NaN pixels are left out.
    labels
        int (H, W) region labels 0..n; 0 is not fitted.
    n
        Number of regions (the largest label).
    order
        Highest model order: 2 quadric (default), 1 plane, 0 constant.
        Regions with fewer than 6 pixels or a singular quadric system
        (e.g. all pixels on a line) fall back to the plane, solved with the
        pseudo-inverse, which degrades to a line fit or the constant when
        the plane is singular too.
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` (identical results; see
        :func:`region_fits`).

    Returns
    -------
    coeffs : numpy.ndarray
        float64 (n+1, 6): (a0..a5) of ``z = a0 + a1 x + a2 y + a3 x^2 + a4 x y
        + a5 y^2`` in image coordinates (x = col, y = row); unused terms and
        row 0 are 0.
    mse : numpy.ndarray
        float64 (n+1,): mean squared residual of each fit (e_A); 0 for empty regions.
    counts : numpy.ndarray
        int64 (n+1,): number of pixels fitted.

    Raises
    ------
    ValueError
        When the shapes differ, a label is outside 0..n or ``order`` is not 0, 1, 2.
    """
    ((coeffs, mse),), counts = fit_models(z, labels, n, (order,), backend=backend)
    return coeffs, mse, counts


#: Level of the F test by which the quadric's lower error is noise (:func:`planar`).
PLANAR_TEST_LEVEL = 0.01

#: Degrees of freedom up to which the F test's critical values are tabulated (beyond,
#: the last is used: 3.79 at 4096, 3.78 in the limit).
_F_TABLE = 4096


@functools.lru_cache(maxsize=1)
def _f_critical() -> np.ndarray:
    """float64 (_F_TABLE + 1,): the F(3, d) critical value at PLANAR_TEST_LEVEL for d pixels.

    From ``scipy.special.fdtri`` (the values of ``scipy.stats.f.ppf``, whose
    import alone takes 0.5-0.8 s of every process's start-up).
    """
    dof = np.maximum(np.arange(_F_TABLE + 1), 1).astype(np.float64)
    return np.asarray(special.fdtri(3.0, dof, 1.0 - PLANAR_TEST_LEVEL), dtype=np.float64)


def planar(mse_quad: np.ndarray, mse_plane: np.ndarray, planar_tolerance: float,
           min_error: float, counts: np.ndarray | None = None) -> np.ndarray:
    """Which fits are planes: the quadric lowers the plane's error by little (Sec. V-4).

    Parameters
    ----------
    mse_quad, mse_plane
        (n+1,) mean squared residuals of each region's quadric and plane.
    planar_tolerance, min_error
        ``grow.planar_tolerance`` and ``grow.min_error``.
    counts
        (n+1,) pixels of each region, for the noise test (``grow.planar_noise_test``);
        None: the tolerance alone.

    Returns
    -------
    numpy.ndarray
        bool (n+1,): ``mse_plane - mse_quad <= planar_tolerance * max(mse_plane,
        min_error)``, the one rule of the surface types of
        :mod:`rangeseg_cli.stages.surfaces`, used alike by the split, fill and merge;
        with ``counts``, also where the quadric's three more terms lower the
        error by no more than they would fitting noise: ``F = (SSE_plane -
        SSE_quad) / 3 / (SSE_quad / (k - 6))`` below the F(3, k - 6) critical
        value at ``PLANAR_TEST_LEVEL`` for a region of k > 6 pixels (its SSE_quad
        floored at ``k * min_error``). On a region of 30 pixels at noise sigma
        2 those terms lower the error by 10 % on average from the noise alone,
        so the tolerance by itself calls about 40 % of such planes curved.
    """
    close = (mse_plane - mse_quad) <= planar_tolerance * np.maximum(mse_plane, min_error)
    if counts is None:
        return close
    k = np.asarray(counts, dtype=np.float64)
    dof = np.maximum(k - 6.0, 1.0)
    f = (mse_plane - mse_quad) * dof / (3.0 * np.maximum(mse_quad, min_error))
    critical = _f_critical()[np.minimum(dof, _F_TABLE).astype(np.intp)]
    return close | ((k > 6) & (f < critical))


def planar_regions(mse_quad: np.ndarray, mse_plane: np.ndarray, counts: np.ndarray,
                   cfg: GrowConfig) -> np.ndarray:
    """:func:`planar` by the rules ``cfg`` turns on (the noise test with ``planar_noise_test``)."""
    return planar(mse_quad, mse_plane, cfg.planar_tolerance, cfg.min_error,
                  counts if cfg.planar_noise_test else None)


def plane_angle(p: np.ndarray, q: np.ndarray) -> float:
    """Angle in degrees (0-90) between two planes (image coefficients a0, a1 (col), a2 (row))."""
    n1 = np.array([-p[1], -p[2], 1.0])
    n2 = np.array([-q[1], -q[2], 1.0])
    cos = abs(float(n1 @ n2)) / float(np.linalg.norm(n1) * np.linalg.norm(n2))
    return math.degrees(math.acos(min(1.0, cos)))


def evaluate_quadric(coeffs: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Heights of quadrics at pixel positions.

    Parameters
    ----------
    coeffs
        (N, 6) or (6,) image-coordinate coefficients (see :func:`fit_quadrics`).
    rows, cols
        (N,) or broadcastable positions (y = row, x = col).

    Returns
    -------
    numpy.ndarray
        ``a0 + a1 x + a2 y + a3 x^2 + a4 x y + a5 y^2``.
    """
    a = np.asarray(coeffs, dtype=np.float64)
    x = np.asarray(cols, dtype=np.float64)
    y = np.asarray(rows, dtype=np.float64)
    return (a[..., 0] + a[..., 1] * x + a[..., 2] * y + a[..., 3] * x * x
            + a[..., 4] * x * y + a[..., 5] * y * y)


def quadric_gradient(coeffs: np.ndarray, rows: np.ndarray, cols: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """``(dz/dx, dz/dy)`` of (N, 6) quadrics (:func:`evaluate_quadric`) at pixel positions."""
    _, a1, a2, a3, a4, a5 = np.asarray(coeffs, dtype=np.float64).T
    return a1 + 2.0 * a3 * cols + a4 * rows, a2 + a4 * cols + 2.0 * a5 * rows


def single_neighbour_label(labels: np.ndarray) -> np.ndarray:
    """The one label in each pixel's 8-neighbourhood, or 0 (none, or two and more).

    Parameters
    ----------
    labels
        int (H, W) labels, 0 = unlabelled.

    Returns
    -------
    numpy.ndarray
        int (H, W): L where the labelled pixels of the 3x3 neighbourhood all
        carry L; 0 where none is labelled or where two or more labels meet
        (a one-pixel boundary, Sec. V-4 "no merging").
    """
    big = np.iinfo(labels.dtype).max
    high = ndimage.maximum_filter(labels, footprint=EIGHT_NEIGHBOURS, mode="constant", cval=0)
    low = ndimage.minimum_filter(np.where(labels > 0, labels, big), footprint=EIGHT_NEIGHBOURS,
                                 mode="constant", cval=big)
    return np.where((high > 0) & (high == low), high, 0)



def single_neighbour_label_at(labels: np.ndarray, rows: np.ndarray, cols: np.ndarray
                              ) -> np.ndarray:
    """:func:`single_neighbour_label` at the pixels ``rows, cols`` only.

    For a few pixels of a large image: their 3x3 neighbourhoods are read
    instead of filtering the whole image. int (N,), 0 beyond the image.
    """
    width = labels.shape[1] + 2
    steps = np.array([dr * width + dc for dr in (-1, 0, 1) for dc in (-1, 0, 1)])
    near = np.pad(labels, 1).ravel()[((rows + 1) * width + cols + 1)[:, None] + steps]
    big = np.iinfo(labels.dtype).max
    high = near.max(axis=1, initial=0)
    low = np.where(near > 0, near, big).min(axis=1, initial=big)
    return np.where((high > 0) & (high == low), high, 0)

def grow_pass(z: np.ndarray, valid: np.ndarray, labels: np.ndarray, coeffs: np.ndarray,
              limit: np.ndarray, *, backend: Backend = "auto") -> int:
    """One simultaneous growing pass, in place; return the number of pixels labelled.

    Parameters
    ----------
    z
        float64 (H, W) heights.
    valid
        bool (H, W) valid pixels.
    labels
        int32 (H, W) labels, updated in place.
    coeffs
        (n+1, 6) image-coordinate quadrics of the labels.
    limit
        (n+1,) squared-residual bound per label (``error_factor * e_A``).
    backend
        ``"numpy"``: whole-image array operations (the reference); ``"numba"``:
        :func:`rangeseg_cli.kernels.compiled.grow_pass`, the same test and arithmetic
        in one sweep (identical labels); ``"auto"``: as
        :func:`rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    int
        How many pixels joined a surface.
    """
    kernels = select_kernels(backend)
    if kernels is not None and labels.dtype == np.int32 and labels.flags.c_contiguous:
        return int(kernels.grow_pass(np.require(z, np.float64, ["C", "W"]),
                                     np.require(valid, np.bool_, ["C", "W"]), labels,
                                     np.require(coeffs, np.float64, ["C", "W"]),
                                     np.require(limit, np.float64, ["C", "W"])))
    target = single_neighbour_label(labels)
    rows, cols = np.nonzero((labels == 0) & valid & (target > 0))
    cand = target[rows, cols]
    resid = z[rows, cols] - evaluate_quadric(coeffs[cand], rows, cols)
    join = resid * resid < limit[cand]
    labels[rows[join], cols[join]] = cand[join]
    return int(join.sum())


#: Quadric fits of regions as :func:`fit_quadrics` returns them: (coeffs, mse, counts).
Fits = tuple[np.ndarray, np.ndarray, np.ndarray]


def component_fits(z: np.ndarray, components: np.ndarray, *, backend: Backend = "auto"
                   ) -> Fits:
    """Quadric fits of the components at their valid pixels (Sec. V-4).

    What :func:`grow_regions` fits to seed the growth, and
    :func:`rangeseg_cli.refine.split.failing_components` tests; a caller that runs
    both computes them once.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    components
        int (H, W) components 1..n of step 3, 0 = none.
    backend
        As for :func:`fit_quadrics`.

    Returns
    -------
    coeffs, mse, counts
        :func:`fit_quadrics` of ``components`` with invalid pixels left out,
        n = the largest label at a valid pixel.
    """
    z = np.asarray(z, dtype=np.float64)
    labels, n = valid_labels(z, components, backend=backend)
    return fit_quadrics(z, labels, n, backend=backend)


def valid_labels(z: np.ndarray, labels: np.ndarray, *, backend: Backend = "auto"
                 ) -> tuple[np.ndarray, int]:
    """``labels`` as int32, 0 where the heights ``z`` are not finite, and the largest label.

    Parameters
    ----------
    z
        float64 (H, W) heights.
    labels
        int (H, W) labels (cast to int32 as ``astype`` does).
    backend
        ``"numpy"``: ``np.where`` and ``max`` (the reference); ``"numba"``:
        :func:`rangeseg_cli.kernels.compiled.valid_labels`, one pass (the same
        values); ``"auto"``: as :func:`rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    labels : numpy.ndarray
        int32 (H, W).
    n : int
        Its largest value, 0 when it has none above 0.
    """
    kernels = select_kernels(backend)
    labels = np.asarray(labels)
    if (kernels is not None and labels.shape == z.shape and z.ndim == 2
            and labels.dtype.kind in "iub"):
        out, n = kernels.valid_labels(np.require(z, np.float64, ["C"]),
                                      np.ascontiguousarray(labels))
        return out, int(n)
    out = np.where(np.isfinite(z), labels, 0).astype(np.int32)
    return out, int(out.max(initial=0))


def grow_regions(z: np.ndarray, codes: np.ndarray, components: np.ndarray, cfg: GrowConfig,
                 *, backend: Backend = "auto", fits: Fits | None = None) -> np.ndarray:
    """Step 4: iterative least-squares region growing (Sec. V-4).

    Every valid pixel with label 0 (edge, linked gap or dropped component)
    whose 8-neighbourhood holds exactly one label L joins L when its squared
    residual to L's quadric is below ``error_factor * e_A(L)``; a pixel
    touching two or more labels stays an edge. ``e_A(L) = max(MSE of L's
    component fit, min_error)``: the floor keeps noise-free or exactly
    fitted faces (MSE 1/12 or 0) from blocking all growth. Passes are
    simultaneous (decided from the labels at the start of the pass) and the
    component fits are kept fixed while growing (see the module Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    codes
        uint8 (H, W) linked edge codes of step 3 (checked for shape; the
        candidates are all label-0 pixels, edges or not).
    components
        int (H, W) connected components of step 3, 0 = none.
    cfg
        ``[grow]``: ``error_factor`` (10), ``passes`` (1; 0 = until nothing
        changes), ``min_error`` (the e_A floor).
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` for the fits and the passes
        (identical labels; see :func:`region_fits` and :func:`grow_pass`).
    fits
        :func:`component_fits` of ``z`` and ``components`` when the caller has
        them (they are computed here otherwise).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) labels: the components' ids, grown; 0 at remaining edges
        and invalid pixels.

    Raises
    ------
    ValueError
        When the shapes of ``z``, ``codes`` and ``components`` differ.
    """
    z = np.asarray(z, dtype=np.float64)
    require_shape_of_z(z, codes=codes, components=components)
    valid = np.isfinite(z)
    labels, n = valid_labels(z, components, backend=backend)
    if n == 0:
        return labels
    # Quadric fit of each component and its average error e_A, floored (Sec. V-4)
    coeffs, mse, _ = fit_quadrics(z, labels, n, backend=backend) if fits is None else fits
    if len(mse) != n + 1:
        raise ValueError(f"`fits` are of {len(mse) - 1} regions, the components {n}")
    limit = cfg.error_factor * np.maximum(mse, cfg.min_error)
    # Growing passes: an edge pixel joins its one neighbouring surface if r^2 < 10 e_A
    max_passes = cfg.passes or int(np.count_nonzero(valid & (labels == 0))) + 1
    for _ in range(max_passes):
        if grow_pass(z, valid, labels, coeffs, limit, backend=backend) == 0:
            break
    return labels
