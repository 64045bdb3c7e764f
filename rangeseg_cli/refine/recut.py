"""Cut regions along the straight line where a plane ends: smooth edges and creases.

Beyond Al-Hujazi & Sood (1990), after the merge of :mod:`rangeseg_cli.refine.merge`.

* A **smooth edge** -- a plane that a curved surface leaves tangentially, as
  part1's fillet leaves the top of its block (Fig. 10, Sec. VI) -- is no
  edge for the AR of Sec. V-1 and V-2: heights and slopes are continuous.
  The split of :mod:`rangeseg_cli.refine.split` (Sec. VIII) divides by surface
  normals, which leave the plane's only several pixels into the curved
  surface; at noise sigma 2 it leaves the two as one region.
* A **crease** between two small planes (a frustum's top and side in a
  pile) can pass the split's fit test as one quadric at sigma 2, and the
  fill of :mod:`rangeseg_cli.refine.fill` can give a strip of one face along a
  crease to its neighbour (part2's chamfer).

Both are fitted here by one model: a plane up to a straight line, and beyond
it the plane plus a function of the distance from the line.

Notes
-----
1. Candidates (:func:`candidates`): every curved region (not planar by
   ``grow.planar_tolerance``) of ``2 * link.min_component`` pixels or more,
   and the union of every pair of touching regions (8-neighbours), one of
   them curved, whose surfaces agree along their boundary within
   ``_MAX_GAP`` times the fit test (``split.fit_factor * max(noise,
   sqrt(grow.min_error))``; across a step they do not). Whether the
   candidate's quadric fails that test is noted: only then is a smooth
   edge tried.
2. Model (:func:`knot_sse`): along the direction ``d`` of the strongest
   curvature of the candidate's quadric (either sign), with ``u = d . (row,
   col)`` and ``q = max(0, u - c)``, heights are ``plane + k q^2 + m q^3``
   for a smooth edge (continuous height and slope at ``u = c``: a cylinder
   or cone meets its tangent plane along a straight line) and ``plane + k
   q`` for a crease (two planes). The knot ``c`` is searched one pixel apart
   (at most ``_COARSE_KNOTS`` knots, farther apart on wide candidates; on at
   most ``_COARSE_PIXELS`` pixels, every k-th), then 0.1 pixel apart within
   a pixel of the best (on at most ``_FINE_PIXELS``, the SSE scaled to all
   pixels). A candidate whose coarse fit is over ``_GIVE_UP`` times the fit
   test (RMS) is dropped there. Each knot is one small least-squares solve.
3. Smooth edge (:func:`split_tangent`), for pairs and for regions whose
   quadric fails the fit test: the model's RMS error passes the fit test;
   both sides have ``link.min_component`` pixels or more; the plane side is
   a plane passing the test; and the model lowers the sum of squared errors,
   per pixel and in units of ``s^2 = max(noise^2, grow.min_error)``, by
   ``MIN_GAIN`` or more against both one quadric and the same model with
   the knot before every pixel (one cubic across), and by ``_MIN_SMOOTH`` or
   more against a crease.
4. Crease (:func:`split_crease`), when no smooth edge is found: the model's
   RMS error and each side's plane pass the fit test, both sides have
   ``link.min_component`` pixels or more. A single region is cut when the
   model gains ``MIN_GAIN`` per pixel or ``TOTAL_GAIN`` in all (both in
   units of ``s^2``) against its quadric and the two planes meet at
   ``split.min_crease`` degrees or more (the split's rule for keeping two
   planes apart). The total lets a wide region's shallow crease through:
   its evidence adds up over the pixels though each gains little (a 15
   degree roof 128 pixels wide at noise sigma 2 gains 0.09 per pixel,
   about 1,460 in all), while on a plane of noise alone the knot search
   gains a few ``s^2`` at most. The total counts only where ``s^2`` is the
   noise's variance: where ``grow.min_error`` stands in for it (an image
   without noise), what is left over a quadric is the model's misfit, not
   noise, and does not add up to evidence. A pair is re-cut when the two
   sides' own planes fit within ``_PAIR_TOLERANCE`` times the sum of
   squared errors of the two regions' own surfaces (the line explains them
   as well as the boundary they had).
5. Cuts are applied by decreasing gain (creases count 0; then pairs before
   single regions, then by ids), each region at most once: a single region
   keeps its id beyond the line and the plane side gets a new one; a pair
   becomes the side beyond the line (first id) and the plane side (second
   id). Ids are then made consecutive.

Thresholds, measured on the 12 synthetic scenes (seeds 0-2, sigma 0-2): a
plane with part1's tangent quarter cylinder gains 0.21-3.6 against one
surface and 0.10-2.1 against a crease; two planes at a crease gain at most
0.03 against a crease; a cylinder alone, cut where it is nearly flat, 0.11.
Only straight lines are modelled: a plane tangent to a sphere or a torus,
or a curved crease, is left as it is.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from scipy import ndimage

from ..config import Config, GrowConfig
from ..kernels.backend import Backend, select_deferred
from ..kernels.parallel import map_tasks
from ..stages.grow import fit_models, planar_regions, plane_angle, union_sse
from ..stages.rangeimage import consecutive_labels, labels_on_valid
from .merge import touching_pairs
from .regions import box_area, c_array, join_box

#: Least gain (SSE per pixel over s^2) of a cut against one surface.
MIN_GAIN = 0.15
#: A crease cut gaining less per pixel is still taken when it gains this much in all
#: (SSE over s^2; Notes 4): on planes of pure noise the crease model gains at most 6.
TOTAL_GAIN = 100.0
#: Least gain of a smooth edge against a crease.
_MIN_SMOOTH = 0.06
#: A pair is re-cut at a crease when its new sides fit within this times the old SSE.
_PAIR_TOLERANCE = 1.05
#: Largest mean gap of two touching regions' surfaces, in fit-test levels.
_MAX_GAP = 10.0
#: The coarse knot search uses at most this many pixels and this many knots.
_COARSE_PIXELS = 1500
_COARSE_KNOTS = 200
#: The fine search uses at most this many pixels (its SSE scaled to all of them).
_FINE_PIXELS = 20000
#: The coarse search gives up above this many fit-test levels of RMS error.
_GIVE_UP = 2.0
#: A knot's column whose Cholesky pivot (unit-diagonal normal equations) is at most
#: this depends on the others and is dropped (as a pseudo-inverse drops it).
_PIVOT_TOL = 1e-10
#: The three bounds of the knot search, for the compiled :func:`best_knot`.
_SEARCH = np.array([_COARSE_KNOTS, _COARSE_PIXELS, _FINE_PIXELS], np.int64)
#: Powers of ``q`` beside the plane: a smooth edge and a crease.
SMOOTH: tuple[int, ...] = (2, 3)
CREASE: tuple[int, ...] = (1,)


def curvature_direction(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Unit (drow, dcol) of the strongest curvature of the pixels' quadric.

    Parameters
    ----------
    rows, cols, zs
        Pixel coordinates and heights (1-D, same length, at least 6).

    Returns
    -------
    numpy.ndarray
        float64 (2,): eigenvector of the quadric's Hessian with the largest
        absolute eigenvalue. The quadric is fitted in centred coordinates
        scaled to unit RMS spread (which scales the Hessian, not its
        eigenvectors), from its 6x6 normal equations.
    """
    x, y = cols - cols.mean(), rows - rows.mean()
    spread = max(1.0, math.sqrt(float(np.mean(x * x + y * y)) / 2.0))
    x, y = x / spread, y / spread
    a = np.column_stack([np.ones_like(x), x, y, x * x, x * y, y * y])
    c = np.linalg.lstsq(a.T @ a, a.T @ zs, rcond=None)[0]
    w, v = np.linalg.eigh(np.array([[2 * c[5], c[4]], [c[4], 2 * c[3]]]))
    return np.asarray(v[:, int(np.argmax(np.abs(w)))], dtype=np.float64)


def _ordered_sum(a: np.ndarray) -> np.ndarray:
    """Sum over the last axis in index order (as a compiled loop adds)."""
    return np.asarray(np.cumsum(a, axis=-1)[..., -1])


def _knot_normal_equations(u: np.ndarray, x: np.ndarray, y: np.ndarray, zs: np.ndarray,
                           knots: np.ndarray, powers: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations of ``plane + sum_p k_p q**p``, ``q = max(0, u - c)``, per knot c.

    The numpy reference of :func:`rangeseg_cli.kernels.compiled.knot_normal_equations`
    (bit for bit: every sum in pixel order).

    Returns
    -------
    gram : numpy.ndarray
        float64 (len(knots), t, t) ``sum a a^T``, ``a = (1, x, y, q**p, ...)``.
    rhs : numpy.ndarray
        float64 (len(knots), t) ``sum a z``.
    """
    t = 3 + len(powers)
    q = np.maximum(u[None, :] - knots[:, None], 0.0)
    qt = [q if p == 1 else (q * q if p == 2 else q * q * q) for p in powers.tolist()]
    terms = [np.broadcast_to(b, q.shape) for b in (np.ones_like(x), x, y)] + qt
    gram = np.empty((knots.size, t, t))
    rhs = np.empty((knots.size, t))
    for s in range(t):
        rhs[:, s] = _ordered_sum(terms[s] * zs)
        for v in range(s, t):
            gram[:, s, v] = gram[:, v, s] = _ordered_sum(terms[s] * terms[v])
    return gram, rhs


def _projected_sse(gram: np.ndarray, rhs: np.ndarray, zz: float, tol: float) -> np.ndarray:
    """``max(0, zz - b^T A^+ b)`` per knot, all knots at once.

    The numpy reference of :func:`rangeseg_cli.kernels.compiled.projected_sse`: a
    Cholesky factor of the unit-diagonal normal equations, column by column,
    a column whose pivot is at most ``tol`` dropped (it depends on the
    earlier ones; the projection, and so the SSE, is the same without it).
    """
    nk, t = gram.shape[:2]
    s = np.sqrt(np.maximum(np.diagonal(gram, axis1=1, axis2=2), 1e-300))
    low = np.zeros((nk, t, t))
    w = np.zeros((nk, t))
    explained = np.zeros(nk)
    for j in range(t):
        d = gram[:, j, j] / s[:, j] / s[:, j] - _dot_rows(low[:, j, :j], low[:, j, :j])
        keep = d > tol
        ljj = np.sqrt(np.where(keep, d, 1.0))
        low[:, j, j] = np.where(keep, ljj, 0.0)
        for i in range(j + 1, t):
            acc = _dot_rows(low[:, i, :j], low[:, j, :j])
            low[:, i, j] = np.where(keep, (gram[:, i, j] / s[:, i] / s[:, j] - acc) / ljj, 0.0)
        w[:, j] = np.where(keep, (rhs[:, j] / s[:, j] - _dot_rows(low[:, j, :j], w[:, :j]))
                           / ljj, 0.0)
        explained = explained + w[:, j] * w[:, j]
    return np.asarray(np.maximum(zz - explained, 0.0))


def _dot_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``sum_m a[:, m] * b[:, m]``, added in order of m from 0.0."""
    acc = np.zeros(a.shape[0])
    for m in range(a.shape[1]):
        acc = acc + a[:, m] * b[:, m]
    return acc


def knot_sse(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, d: np.ndarray,
             knots: np.ndarray, powers: tuple[int, ...], backend: Backend = "auto"
             ) -> np.ndarray:
    """SSE of ``plane + sum_p k_p q**p``, ``q = max(0, d . (row, col) - c)``, per knot c.

    Parameters
    ----------
    rows, cols, zs
        Pixel coordinates and heights (1-D, same length).
    d
        Unit direction (drow, dcol) across the knot line.
    knots
        Knot positions ``c`` along ``d``.
    powers
        Powers of ``q`` beside the plane: :data:`SMOOTH` or :data:`CREASE`
        (one or two of 1, 2, 3).
    backend
        ``"numba"`` (:func:`rangeseg_cli.kernels.compiled.knot_sse`), ``"numpy"``
        (the reference) or ``"auto"`` (the kernel once compiled:
        :func:`~rangeseg_cli.kernels.backend.select_deferred`): the same values.

    Returns
    -------
    numpy.ndarray
        float64 (len(knots),) least-squares sums of squared errors, from each
        knot's normal equations (plane coordinates centred; scaled to a unit
        diagonal; a column that depends on the others, as ``q`` does on the
        plane when the knot lies before every pixel, dropped).

    Raises
    ------
    ValueError
        When ``powers`` is not one or two of 1, 2, 3.
    """
    if len(powers) not in (1, 2) or any(p not in (1, 2, 3) for p in powers):
        raise ValueError(f"`powers` = {powers!r}: one or two of 1, 2, 3")
    u = np.ascontiguousarray(d[0] * rows + d[1] * cols, dtype=np.float64)
    x = np.ascontiguousarray(cols - cols.mean(), dtype=np.float64)
    y = np.ascontiguousarray(rows - rows.mean(), dtype=np.float64)
    z = np.ascontiguousarray(zs, dtype=np.float64)
    args = (u, x, y, z, np.ascontiguousarray(knots, dtype=np.float64),
            np.asarray(powers, dtype=np.int64))
    kernels = select_deferred(backend, "knot_sse")
    if kernels is not None:
        return np.asarray(kernels.knot_sse(*args, _PIVOT_TOL))
    gram, rhs = _knot_normal_equations(*args)
    return _projected_sse(gram, rhs, float(_ordered_sum(z * z)), _PIVOT_TOL)


def best_knot(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, d: np.ndarray,
              powers: tuple[int, ...], max_mse: float = math.inf, *,
              backend: Backend = "auto") -> tuple[float, float, float]:
    """The best knot along ``d``, its SSE, and the SSE with no plane side (Notes 2).

    Parameters
    ----------
    rows, cols, zs, d, powers
        As for :func:`knot_sse`.
    max_mse
        Give up (NaN, infinities) when the coarse search's best mean squared
        error is above this: the model cannot pass (a step between the regions).
    backend
        This numpy reference (with :func:`knot_sse`) or, once compiled
        (:func:`~rangeseg_cli.kernels.backend.select_deferred`),
        :func:`rangeseg_cli.kernels.compiled.best_knot` in one call (the same values).

    Returns
    -------
    tuple
        (knot c, SSE at c, SSE with the knot before every pixel); NaN and
        infinities when the pixels span less than a pixel along ``d``.
    """
    kernels = select_deferred(backend, "best_knot")
    if kernels is not None:
        c, sse, across = kernels.best_knot(
            c_array(rows, np.int64), c_array(cols, np.int64), c_array(zs, np.float64),
            float(d[0]), float(d[1]), np.asarray(powers, np.int64), float(max_mse),
            _SEARCH, _PIVOT_TOL)
        return float(c), float(sse), float(across)
    u = d[0] * rows + d[1] * cols
    step = max(1.0, float(np.ceil((u.max() - u.min()) / _COARSE_KNOTS)))
    knots = np.arange(math.floor(u.min()) + step, u.max(), step)
    if knots.size == 0:
        return math.nan, math.inf, math.inf
    sub = slice(None, None, max(1, -(-zs.size // _COARSE_PIXELS)))
    coarse = knot_sse(rows[sub], cols[sub], zs[sub], d, knots, powers, backend)
    k = int(np.argmin(coarse))
    if coarse[k] > max_mse * zs[sub].size:
        return math.nan, math.inf, math.inf
    c = float(knots[k])
    fine = np.concatenate([[u.min() - 0.5], np.arange(c - 1.0, c + 1.0001, 0.1)])
    every = max(1, -(-zs.size // _FINE_PIXELS))
    sse = knot_sse(rows[::every], cols[::every], zs[::every], d, fine, powers, backend)
    sse *= zs.size / zs[::every].size
    j = int(np.argmin(sse[1:])) + 1
    return float(fine[j]), float(sse[j]), float(sse[0])


Box = tuple[slice, slice]


def _whole(shape: tuple[int, ...]) -> Box:
    """The box of a whole (H, W) array."""
    return slice(0, shape[0]), slice(0, shape[1])


def _box_of(shape: tuple[int, ...], box: Box | None) -> Box:
    """``box``, or the whole array's when None."""
    return _whole(shape) if box is None else box


def _embed(part: np.ndarray, box: Box, shape: tuple[int, ...]) -> np.ndarray:
    """The bool ``part`` of ``box`` on an array of ``shape`` (False elsewhere)."""
    if part.shape == tuple(shape):
        return part
    out = np.zeros(shape, bool)
    out[box] = part
    return out


def _coords(mask: np.ndarray, box: Box) -> tuple[np.ndarray, np.ndarray]:
    """Image coordinates of the pixels of ``mask``, the pixels of ``box`` (its shape)."""
    rows, cols = np.nonzero(mask)
    return rows + box[0].start, cols + box[1].start


class _Points(NamedTuple):
    """A candidate's pixels, their heights and its direction of strongest curvature.

    Computed once per candidate (:func:`_points`) and shared by the smooth-edge
    and crease searches, which fit the same pixels along the same direction.
    """

    rows: np.ndarray  #: int row of each pixel
    cols: np.ndarray  #: int column of each pixel
    zs: np.ndarray    #: float64 height of each pixel
    d0: np.ndarray    #: :func:`curvature_direction` of the pixels


def _points(mask: np.ndarray, z: np.ndarray, box: Box) -> _Points:
    """The :class:`_Points` of ``mask``, the pixels of ``box`` (image coordinates)."""
    rows, cols = _coords(mask, box)
    zs = z[rows, cols]
    return _Points(rows, cols, zs, curvature_direction(rows, cols, zs))


def _line_fit(mask: np.ndarray, box: Box, pts: _Points, powers: tuple[int, ...],
              min_pixels: int, level: float) -> tuple[np.ndarray, float, float] | None:
    """Plane side (bool, ``mask``'s box), SSE and no-plane-side SSE of the best line."""
    rows, cols, zs, d0 = pts
    fits = [(best_knot(rows, cols, zs, d, powers, (_GIVE_UP * level) ** 2), d)
            for d in (d0, -d0)]
    (c, sse, sse_across), d = min(fits, key=lambda f: f[0][1])
    if not math.isfinite(sse):
        return None
    side = d[0] * rows + d[1] * cols < c
    n_side = int(side.sum())
    if n_side < min_pixels or zs.size - n_side < min_pixels or sse > zs.size * level ** 2:
        return None
    plane_side = np.zeros_like(mask)
    plane_side[rows[side] - box[0].start, cols[side] - box[1].start] = True
    return plane_side, sse, sse_across


def _crease_sse(pts: _Points) -> float:
    """SSE of the best crease along the candidate's curvature direction (either sign)."""
    rows, cols, zs, d0 = pts
    return min(best_knot(rows, cols, zs, d, CREASE)[1] for d in (d0, -d0))


def _fits(z: np.ndarray, labels: np.ndarray, n: int, box: Box,
          orders: tuple[int, ...] = (2, 1)
          ) -> tuple[list[tuple[np.ndarray, np.ndarray]], np.ndarray]:
    """Fits of labels 1..n (quadric, plane); ``labels`` are the pixels of ``box``.

    The same bits as fitting the whole image
    (:func:`~rangeseg_cli.stages.grow.region_fits`'s origin).
    """
    return fit_models(z[box], labels.astype(np.int32), n, orders,
                      origin=(box[0].start, box[1].start))


def _quadric_sse(z: np.ndarray, mask: np.ndarray, box: Box) -> float:
    """Sum of squared errors of one quadric of ``mask``, the pixels of ``box``."""
    ((_, mse),), counts = _fits(z, mask, 1, box, (2,))
    return float(mse[1]) * int(counts[1])


def split_tangent(z: np.ndarray, mask: np.ndarray, *, noise: float, level: float,
                  min_pixels: int, grow: GrowConfig, box: Box | None = None,
                  pts: _Points | None = None, quadric_sse: float | None = None
                  ) -> tuple[np.ndarray, float] | None:
    """The plane side of ``mask`` when it is a plane with a tangent surface (Notes 2, 3).

    Parameters
    ----------
    z
        float64 (H, W) heights, finite.
    mask
        bool (H, W) the candidate's pixels.
    noise
        Noise sigma of ``z``.
    level
        The split's fit test (largest RMS error of a passing fit).
    min_pixels
        Smallest plane side and curved side.
    grow
        ``min_error`` (noise floor) and ``planar_tolerance``.
    box
        A box holding all of ``mask`` (searched instead of the whole image).
    pts, quadric_sse
        :func:`_points` of ``mask`` and :func:`_quadric_sse`, when the caller has them.

    Returns
    -------
    tuple or None
        (bool (H, W) plane side, gain against one surface in units of s^2),
        or None when the test fails.
    """
    box = _box_of(mask.shape, box)
    got = _tangent(z, mask[box], box, noise=noise, level=level, min_pixels=min_pixels,
                   grow=grow, pts=pts, quadric_sse=quadric_sse)
    return None if got is None else (_embed(got[0], box, mask.shape), got[1])


def _tangent(z: np.ndarray, mask: np.ndarray, box: Box, *, noise: float, level: float,
             min_pixels: int, grow: GrowConfig, pts: _Points | None,
             quadric_sse: float | None) -> tuple[np.ndarray, float] | None:
    """:func:`split_tangent` of ``mask``, the pixels of ``box``; the plane side in the box."""
    pts = _points(mask, z, box) if pts is None else pts
    fit = _line_fit(mask, box, pts, SMOOTH, min_pixels, level)
    if fit is None:
        return None
    plane_side, sse, sse_across = fit
    ((_, mse_q), (_, mse_p)), counts = _fits(z, plane_side, 1, box)
    if mse_p[1] > level ** 2 or not planar_regions(mse_q[1:], mse_p[1:], counts[1:], grow)[0]:
        return None
    s2n = pts.rows.size * max(noise ** 2, grow.min_error)
    if quadric_sse is None:
        quadric_sse = _quadric_sse(z, mask, box)
    gain = (min(quadric_sse, sse_across) - sse) / s2n
    if gain < MIN_GAIN or (_crease_sse(pts) - sse) / s2n < _MIN_SMOOTH:
        return None
    return plane_side, gain


def _own_sse(z: np.ndarray, two: np.ndarray, grow: GrowConfig, box: Box) -> float:
    """Sum of squared errors of labels 1 and 2 of ``two`` (``box``'s pixels), each its own."""
    ((_, mse_q), (_, mse_p)), counts = _fits(z, two, 2, box)
    flat = planar_regions(mse_q, mse_p, counts, grow)
    count = np.bincount(two.ravel(), minlength=3)
    return float(sum(count[k] * (mse_p[k] if flat[k] else mse_q[k]) for k in (1, 2)))


class _Crease(NamedTuple):
    """The best straight crease of a region and the planes either side of it."""

    side: np.ndarray       #: bool the side before the line (the plane side), in the box
    sse: float             #: sum of squared errors of the crease model
    two: np.ndarray        #: int32 2 = the side before the line, 1 = beyond, 0 = off (box)
    planes: np.ndarray     #: (3, 6) image coefficients of the planes of labels 1 and 2
    mse: np.ndarray        #: (3,) their mean squared errors


def _crease_planes(mask: np.ndarray, z: np.ndarray, min_pixels: int, level: float,
                   box: Box, pts: _Points | None = None) -> _Crease | None:
    """The best crease of ``mask`` (``box``'s pixels, Notes 2) when each side's plane passes."""
    pts = _points(mask, z, box) if pts is None else pts
    fit = _line_fit(mask, box, pts, CREASE, min_pixels, level)
    if fit is None:
        return None
    side, sse, _ = fit
    two = side.astype(np.int32) + mask.astype(np.int32)
    ((_, _), (planes, mse)), _ = _fits(z, two, 2, box)
    if np.any(mse[1:] > level ** 2):
        return None
    return _Crease(side, sse, two, planes, mse)


def split_crease(z: np.ndarray, labels: np.ndarray, i: int, j: int, *, noise: float,
                 level: float, config: Config, box: Box | None = None,
                 pts: _Points | None = None, quadric_sse: float | None = None
                 ) -> np.ndarray | None:
    """The plane side of region i (and j) when two planes meet along a line (Notes 4).

    Parameters
    ----------
    z
        float64 (H, W) heights, finite.
    labels
        int32 (H, W) regions.
    i, j
        The region, or the two touching regions (j = 0: region i alone).
    noise, level
        Noise sigma of ``z`` and the split's fit test.
    config
        ``[link] min_component``, ``config.split.min_crease``, ``[grow]``.
    box
        A box holding regions i and j (searched instead of the whole image).
    pts, quadric_sse
        :func:`_points` of the pixels of i (and j), and the SSE of their quadric
        (:func:`_quadric_sse`), when the caller has them.

    Returns
    -------
    numpy.ndarray or None
        bool (H, W) the side before the line, or None when the test fails.
    """
    box = _box_of(labels.shape, box)
    side = _crease_cut(z, labels[box], i, j, box, noise=noise, level=level, config=config,
                       pts=pts, quadric_sse=quadric_sse)
    return None if side is None else _embed(side, box, labels.shape)


def _crease_cut(z: np.ndarray, labels: np.ndarray, i: int, j: int, box: Box, *,
                noise: float, level: float, config: Config, pts: _Points | None,
                quadric_sse: float | None) -> np.ndarray | None:
    """:func:`split_crease` of ``labels``, the regions within ``box``; the side in the box."""
    mask = _pixels(labels, i, j)
    if not j:
        return _side(z, mask, box, noise=noise, level=level,
                     min_pixels=config.link.min_component,
                     min_crease=config.split.min_crease, grow=config.grow, pts=pts,
                     quadric_sse=quadric_sse)
    crease = _crease_planes(mask, z, config.link.min_component, level, box, pts)
    if crease is None:
        return None
    count = np.bincount(crease.two.ravel(), minlength=3)
    new = float(count[1] * crease.mse[1] + count[2] * crease.mse[2])
    before = ((labels == i).astype(np.int32) + 2 * (labels == j)).astype(np.int32)
    if new > _PAIR_TOLERANCE * _own_sse(z, before, config.grow, box):
        return None
    return crease.side


def crease_side(z: np.ndarray, mask: np.ndarray, *, noise: float, level: float,
                min_pixels: int, min_crease: float, grow: GrowConfig, box: Box | None = None,
                pts: _Points | None = None, quadric_sse: float | None = None
                ) -> np.ndarray | None:
    """The side before the line when two planes along a straight crease fit ``mask`` (Notes 4).

    Parameters
    ----------
    z
        float64 (H, W) heights, finite on ``mask``.
    mask
        bool (H, W) one region's pixels.
    noise, level
        Noise sigma of ``z`` and the split's fit test.
    min_pixels
        Smallest side.
    min_crease
        Least angle (degrees) between the two planes.
    grow
        ``min_error``.
    box
        A box holding all of ``mask`` (searched instead of the whole image).
    pts, quadric_sse
        :func:`_points` of ``mask`` and :func:`_quadric_sse`, when the caller has them.

    Returns
    -------
    numpy.ndarray or None
        bool (H, W) the side before the line, or None: the model or a side's
        plane fails the fit test, a side is under ``min_pixels``, the model
        lowers the squared error against one quadric by less than
        ``MIN_GAIN`` s^2 per pixel and (or where ``s^2`` is ``grow.min_error``,
        not the noise's variance) less than ``TOTAL_GAIN`` s^2 in all, or the
        planes meet at less than ``min_crease``.
    """
    box = _box_of(mask.shape, box)
    side = _side(z, mask[box], box, noise=noise, level=level, min_pixels=min_pixels,
                 min_crease=min_crease, grow=grow, pts=pts, quadric_sse=quadric_sse)
    return None if side is None else _embed(side, box, mask.shape)


def _side(z: np.ndarray, mask: np.ndarray, box: Box, *, noise: float, level: float,
          min_pixels: int, min_crease: float, grow: GrowConfig, pts: _Points | None,
          quadric_sse: float | None) -> np.ndarray | None:
    """:func:`crease_side` of ``mask``, the pixels of ``box``; the side in the box."""
    crease = _crease_planes(mask, z, min_pixels, level, box, pts)
    if crease is None:
        return None
    if quadric_sse is None:
        quadric_sse = _quadric_sse(z, mask, box)
    pixels = int(np.count_nonzero(mask))
    gain = (quadric_sse - crease.sse) / (pixels * max(noise ** 2, grow.min_error))
    evidence = noise ** 2 > grow.min_error and gain * pixels >= TOTAL_GAIN  # Notes 4
    if ((gain < MIN_GAIN and not evidence)
            or plane_angle(crease.planes[1], crease.planes[2]) < min_crease):
        return None
    return crease.side


def _pixels(labels: np.ndarray, i: int, j: int) -> np.ndarray:
    """Pixels of region i, or of regions i and j (j > 0)."""
    return (labels == i) | (labels == j) if j else labels == i


def candidates(z: np.ndarray, labels: np.ndarray, config: Config, level: float
               ) -> list[tuple[int, int, bool, float]]:
    """Regions (k, 0) and touching pairs (i, j) to test, and whether their quadric fails.

    Parameters
    ----------
    z
        float64 (H, W) heights, finite.
    labels
        int32 (H, W) regions 1..n.
    config
        ``[grow]`` (planar rule) and ``[link] min_component``.
    level
        The split's fit test.

    Returns
    -------
    list of tuple
        (i, j, fails, sse) per Notes 1; j = 0 for a single region; ``sse`` is
        the sum of squared errors of the candidate's quadric (whose RMS error
        ``fails`` the fit test or not), as :func:`_quadric_sse` gives it.
    """
    n = int(labels.max(initial=0))
    ((quad, mse), (planes, mse_plane)), counts = fit_models(z, labels, n, (2, 1))
    curved = ~planar_regions(mse, mse_plane, counts, config.grow)
    curved[0] = False
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    # Each region's quadric here is the one of its pixels alone (the same moments and
    # the same solve, so the same bits): its SSE is not fitted again.
    out = [(k, 0, bool(mse[k] > level ** 2), float(mse[k]) * int(sizes[k]))
           for k in np.nonzero(curved)[0].tolist() if sizes[k] >= 2 * config.link.min_component]
    coeffs = np.where(curved[:, None], quad, planes)
    boxes = ndimage.find_objects(labels)
    pairs = [(i, j) for i, j in touching_pairs(labels, coeffs, _MAX_GAP * level)
             if curved[i] or curved[j]]
    if not pairs:
        return out
    spans = [join_box(boxes[i - 1], boxes[j - 1]) for i, j in pairs]
    unions = union_sse(z, labels, np.array(pairs, dtype=np.int64),
                       np.array([(r.start, r.stop, c.start, c.stop) for r, c in spans],
                                dtype=np.int64))
    return out + [(i, j, bool(union > level ** 2 * (sizes[i] + sizes[j])), float(union))
                  for (i, j), union in zip(pairs, unions.tolist(), strict=True)]


_Test = tuple[int, int, bool, float, Box]
_Cut = tuple[float, int, int, int, Box, np.ndarray]


def _recut_one(zc: np.ndarray, lab: np.ndarray, test: _Test, *, noise: float, level: float,
               config: Config) -> _Cut | None:
    """The cut of one candidate (Notes 3, 4): sort key, box, and the new side in the box."""
    i, j, fails, sse, box = test
    mask = _pixels(lab[box], i, j)  # the work stays within the candidate's box
    pts = _points(mask, zc, box)  # both searches fit these pixels along the same direction
    got = None
    if fails:
        got = _tangent(zc, mask, box, noise=noise, level=level, pts=pts, quadric_sse=sse,
                       min_pixels=config.link.min_component, grow=config.grow)
    if got is None:
        side = _crease_cut(zc, lab[box], i, j, box, noise=noise, level=level, config=config,
                           pts=pts, quadric_sse=sse)
        got = None if side is None else (side, 0.0)
    return None if got is None else (-got[1], 0 if j else 1, i, j, box, got[0])


def recut_regions(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                  ) -> np.ndarray:
    """Cut regions, and re-cut touching pairs, along smooth edges and creases (see Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n, 0 = none.
    config
        Uses ``config.split`` (``fit_factor``, ``min_crease``), ``[grow]``
        (``min_error``, ``planar_tolerance``) and ``[link] min_component``.
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.stages.noise.estimate_noise`).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) regions 1..k, k >= n, numbered in order of their ids.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, lab = labels_on_valid(z, labels)
    if lab.max(initial=0) < 1:
        return lab
    zc = np.where(np.isfinite(z), z, 0.0)
    level = config.split.fit_factor * max(noise, math.sqrt(config.grow.min_error))
    boxes = ndimage.find_objects(lab)
    tests = [(i, j, fails, sse, join_box(boxes[i - 1], boxes[j - 1]) if j else boxes[i - 1])
             for i, j, fails, sse in candidates(zc, lab, config, level)]
    # The candidates are independent; their work is mostly Python, so many of them go to
    # processes (on threads they take turns on the GIL).
    cuts = map_tasks(
        lambda test: _recut_one(zc, lab, test, noise=noise, level=level, config=config),
        tests, cost=[float(box_area(t[4])) for t in tests])  # pixels of each box
    found = [cut for cut in cuts if cut is not None]
    out = lab.copy()
    used: set[int] = set()
    next_id = int(lab.max()) + 1
    for _, _, i, j, box, side in sorted(found, key=lambda f: f[:4]):
        if i in used or (j and j in used):
            continue
        out[box][_pixels(lab[box], i, j)] = i
        out[box][side] = j if j else next_id
        next_id += 0 if j else 1
        used.update((i, j))
    return consecutive_labels(out)
