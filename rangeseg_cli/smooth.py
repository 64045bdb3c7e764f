"""Cut a planar face from a curved surface tangent to it (a smooth edge).

Beyond Al-Hujazi & Sood (1990). A smooth edge -- a plane that a curved
surface leaves tangentially, as part1's fillet leaves the top of its block
(Fig. 10, Sec. VI) -- is no edge for the AR of Sec. V-1 and V-2: heights and
slopes are continuous across it. The split of :mod:`rangeseg_cli.split`
(Sec. VIII) divides by surface normals, which leave the plane's only
several pixels into the curved surface, and at noise sigma 2 it does not
divide the pair at all. This stage, run last, fits the model of a smooth
edge instead.

Notes
-----
1. Candidates: every curved region (not planar by ``grow.planar_tolerance``)
   of ``2 * link.min_component`` pixels or more whose quadric fails the
   split's fit test (RMS above ``split.fit_factor * max(noise,
   sqrt(grow.min_error))``), and the union of every pair of touching regions
   (8-neighbours), one of them curved, whose surfaces agree along their
   boundary within ``_MAX_GAP`` times that level and whose union's quadric
   fails the test.
2. Model (:func:`spline_sse`): along the direction ``d`` of the strongest
   curvature of the candidate's quadric (either sign), with ``u = d . (row,
   col)`` and ``q = max(0, u - c)``, the heights are ``plane + k q^2 + m
   q^3``: a plane up to the line ``u = c`` and a surface that leaves it with
   continuous height and slope (a cylinder or cone meets its tangent plane
   along a straight line). The knot ``c`` is searched one pixel apart (on
   at most ``_COARSE_PIXELS`` pixels, every k-th), then 0.1 pixel apart.
3. Test (:func:`split_tangent`): the model's RMS error is within the fit
   test; the plane part (``u < c``) and the curved part have
   ``link.min_component`` pixels or more; the plane part is a plane passing
   the fit test; the model lowers the sum of squared errors, per pixel and
   in units of the noise variance ``s^2 = max(noise^2, grow.min_error)``, by
   ``_MIN_GAIN`` or more against both one quadric and the same model with
   the knot before every pixel (one cubic across: no plane part), and by
   ``_MIN_SMOOTH`` or more against a crease (``plane + k q``, two planes,
   which the split and merge already handle).
4. Candidates that pass are applied by decreasing gain, each region at most
   once: a single region keeps its id for the curved part and the plane part
   gets a new one; a pair becomes the curved part (first id) and the plane
   part (second id). Ids are then made consecutive in their order.

Thresholds (measured on the 12 synthetic scenes, seeds 0-2, sigma 0-2): a
plane with a tangent quarter cylinder gains 0.21-3.6 against one surface and
0.10-2.1 against a crease; two planes at a crease gain at most 0.03 against
a crease; a cylinder alone, cut where it is nearly flat, 0.11.
"""

from __future__ import annotations

import math

import numpy as np

from .config import Config, GrowConfig
from .grow import fit_models, fit_quadrics, planar
from .merge import touching_pairs
from .rangeimage import require_shape_of_z

#: Least gain (SSE per pixel over s^2) against one quadric or one cubic across.
_MIN_GAIN = 0.15
#: Least gain against two planes at a crease.
_MIN_SMOOTH = 0.06
#: Largest mean gap of two touching regions' surfaces, in fit-test levels.
_MAX_GAP = 10.0
#: The coarse knot search uses at most this many pixels.
_COARSE_PIXELS = 1500


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
        absolute eigenvalue.
    """
    x, y = cols - cols.mean(), rows - rows.mean()
    a = np.column_stack([np.ones_like(zs), x, y, x * x, x * y, y * y])
    c = np.linalg.lstsq(a, zs, rcond=None)[0]
    w, v = np.linalg.eigh(np.array([[2 * c[5], c[4]], [c[4], 2 * c[3]]]))
    return np.asarray(v[:, int(np.argmax(np.abs(w)))], dtype=np.float64)


def spline_sse(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, d: np.ndarray,
               knots: np.ndarray, powers: tuple[int, ...] = (2, 3)) -> np.ndarray:
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
        Powers of ``q`` beside the plane: (2, 3) a tangent surface, (1,) a crease.

    Returns
    -------
    numpy.ndarray
        float64 (len(knots),) least-squares sums of squared errors, all knots
        solved at once from their normal equations (scaled, pseudo-inverse).
    """
    u = d[0] * rows + d[1] * cols
    x, y = cols - cols.mean(), rows - rows.mean()
    q = np.maximum(u[None, :] - knots[:, None], 0.0)
    terms = [np.broadcast_to(t, q.shape) for t in (np.ones_like(zs), x, y)]
    a = np.stack(terms + [q ** p for p in powers], axis=-1)          # (knots, n, terms)
    gram = np.einsum("cni,cnj->cij", a, a)
    rhs = np.einsum("cni,n->ci", a, zs)
    scale = np.sqrt(np.maximum(np.einsum("cii->ci", gram), 1e-300))
    inv = np.linalg.pinv(gram / scale[:, :, None] / scale[:, None, :], rcond=1e-10)
    coef = (inv @ (rhs / scale)[:, :, None])[:, :, 0] / scale
    return np.asarray(np.maximum(float(zs @ zs) - np.einsum("ci,ci->c", coef, rhs), 0.0))


def best_knot(rows: np.ndarray, cols: np.ndarray, zs: np.ndarray, d: np.ndarray,
              powers: tuple[int, ...]) -> tuple[float, float, float]:
    """The best knot along ``d``, its SSE, and the SSE with no plane part (Notes 2).

    Returns
    -------
    tuple
        (knot c, SSE at c, SSE with the knot before every pixel); NaN and
        infinities when the pixels span less than a pixel along ``d``.
    """
    u = d[0] * rows + d[1] * cols
    knots = np.arange(math.floor(u.min()) + 1.0, u.max(), 1.0)
    if knots.size == 0:
        return math.nan, math.inf, math.inf
    sub = slice(None, None, max(1, -(-zs.size // _COARSE_PIXELS)))
    coarse = spline_sse(rows[sub], cols[sub], zs[sub], d, knots, powers)
    c = float(knots[int(np.argmin(coarse))])
    fine = np.concatenate([[u.min() - 0.5], np.arange(c - 1.0, c + 1.0001, 0.1)])
    sse = spline_sse(rows, cols, zs, d, fine, powers)
    j = int(np.argmin(sse[1:])) + 1
    return float(fine[j]), float(sse[j]), float(sse[0])


def split_tangent(z: np.ndarray, mask: np.ndarray, *, noise: float, level: float,
                  min_pixels: int, grow: GrowConfig) -> tuple[np.ndarray, float] | None:
    """The plane part of ``mask`` when it is a plane with a tangent surface (Notes 2, 3).

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
        Smallest plane part and curved part.
    grow
        ``min_error`` (noise floor) and ``planar_tolerance``.

    Returns
    -------
    tuple or None
        (bool (H, W) plane part, gain against one surface in units of s^2),
        or None when the test fails.
    """
    rows, cols = np.nonzero(mask)
    zs = z[rows, cols]
    n = zs.size
    d0 = curvature_direction(rows, cols, zs)
    fits = [(best_knot(rows, cols, zs, d, (2, 3)), d) for d in (d0, -d0)]
    (c, sse, sse_cubic), d = min(fits, key=lambda f: f[0][1])
    flat = d[0] * rows + d[1] * cols < c
    n_flat = int(flat.sum())
    if n_flat < min_pixels or n - n_flat < min_pixels or sse > n * level ** 2:
        return None
    plane_part = np.zeros_like(mask)
    plane_part[rows[flat], cols[flat]] = True
    ((_, mse_q), (_, mse_p)), _ = fit_models(z, plane_part.astype(np.int32), 1, (2, 1))
    if mse_p[1] > level ** 2 or not planar(mse_q[1:], mse_p[1:], grow.planar_tolerance,
                                           grow.min_error)[0]:
        return None
    _, mse_one, _ = fit_quadrics(z, mask.astype(np.int32), 1)
    s2n = n * max(noise ** 2, grow.min_error)
    gain = (min(float(mse_one[1]) * n, sse_cubic) - sse) / s2n
    if gain < _MIN_GAIN:
        return None
    sse_crease = min(best_knot(rows, cols, zs, e, (1,))[1] for e in (d0, -d0))
    if (sse_crease - sse) / s2n < _MIN_SMOOTH:
        return None
    return plane_part, gain


def _pixels(lab: np.ndarray, i: int, j: int) -> np.ndarray:
    """Pixels of region i, or of regions i and j (j > 0)."""
    return (lab == i) | (lab == j) if j else lab == i


def _candidates(z: np.ndarray, lab: np.ndarray, config: Config, level: float
                ) -> list[tuple[int, int]]:
    """Regions (k, 0) and touching pairs (i, j) to test (Notes 1)."""
    n = int(lab.max(initial=0))
    ((quad, mse), (planes, mse_plane)), _ = fit_models(z, lab, n, (2, 1))
    curved = ~planar(mse, mse_plane, config.grow.planar_tolerance, config.grow.min_error)
    curved[0] = False
    sizes = np.bincount(lab.ravel(), minlength=n + 1)
    out = [(k, 0) for k in np.nonzero(curved)[0].tolist()
           if mse[k] > level ** 2 and sizes[k] >= 2 * config.link.min_component]
    coeffs = np.where(curved[:, None], quad, planes)
    for i, j in touching_pairs(lab, coeffs, _MAX_GAP * level):
        if curved[i] or curved[j]:
            _, mse_union, _ = fit_quadrics(z, _pixels(lab, i, j).astype(np.int32), 1)
            if mse_union[1] > level ** 2:
                out.append((i, j))
    return out


def separate_tangent_planes(z: np.ndarray, labels: np.ndarray, config: Config, *,
                            noise: float) -> np.ndarray:
    """Cut planes from the curved surfaces tangent to them (see Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n, 0 = none.
    config
        Uses ``[split]`` (``fit_factor``), ``[grow]`` (``min_error``,
        ``planar_tolerance``) and ``[link] min_component``.
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.noise.estimate_noise`).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) regions 1..k, k >= n, numbered in order of their ids.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z = np.asarray(z, dtype=np.float64)
    require_shape_of_z(z, labels=labels)
    lab = np.where(np.isfinite(z), labels, 0).astype(np.int32)
    if lab.max(initial=0) < 1:
        return lab
    zc = np.where(np.isfinite(z), z, 0.0)
    level = config.split.fit_factor * max(noise, math.sqrt(config.grow.min_error))
    found = []
    for i, j in _candidates(zc, lab, config, level):
        got = split_tangent(zc, _pixels(lab, i, j), noise=noise, level=level,
                            min_pixels=config.link.min_component, grow=config.grow)
        if got is not None:
            found.append((-got[1], i, j, got[0]))
    out = lab.copy()
    used: set[int] = set()
    next_id = int(lab.max()) + 1
    for _, i, j, part in sorted(found, key=lambda f: f[:3]):
        if i in used or (j and j in used):
            continue
        out[_pixels(lab, i, j)] = i
        out[part] = j if j else next_id
        next_id += 0 if j else 1
        used.update((i, j))
    _, dense = np.unique(np.concatenate([[0], out.ravel()]), return_inverse=True)
    return dense[1:].reshape(out.shape).astype(np.int32)
