"""Settle each boundary pixel on the surface that predicts it best.

Beyond Al-Hujazi & Sood (1990), the last step of the grow stage (after the
fill of :mod:`rangeseg_cli.refine.fill`). Region growing (Sec. V-4) gives a pixel to
the first region whose bound it meets, and the fill to the neighbour that
fits it best *relative to that neighbour's bound*; neither looks again once
a pixel is labelled. Along a crease both neighbours' bounds often hold, so
the boundary can sit a pixel or two off the crease. On a face 2-5 pixels
wide (a grazing side, a chamfer) that is most of the face: a region covering
it is not a correct detection (Hoover et al. 1996, T = 0.8).

Notes
-----
1. Surfaces: each region's plane when planar, else its quadric (the rule of
   :func:`~rangeseg_cli.refine.fill.surface_models`), fitted again before every
   pass.
2. Cost of giving a boundary pixel (a labelled pixel with a differently
   labelled 8-neighbour) label ``L``: ``r_L^2 / s^2 + smoothness * m_L``,
   with ``r_L`` its residual to L's surface, ``s^2 = max(noise^2,
   grow.min_error)`` and ``m_L`` the number of its labelled 8-neighbours
   whose label is not ``L``. The candidates are its own label and its
   neighbours' labels. This is one sweep of iterated conditional modes
   (Besag 1986) on a Potts model whose data term is the fitted surfaces'
   squared residual in units of the noise: the residual moves the pixel
   across a crease, the neighbour count keeps single noisy pixels from
   flipping.
3. Passes (``TUNING.refine_passes``) are simultaneous: every boundary pixel
   takes its cheapest label (its own on a tie), then the surfaces are fitted
   again. They stop early when nothing changes. Unlabelled pixels stay
   unlabelled and labelled pixels stay labelled.
4. A region can lose all its pixels; labels are then made consecutive again
   in the order of their ids.
5. Creases (``TUNING.refine_creases``). Where two surfaces meet at a crease
   the image is their lower envelope (a convex crease: the roof of Fig. 1)
   or their upper one (a concave crease), so the surface that is visible at
   a pixel is known from the two fits alone, and noise does not enter: at
   sigma 2 a pixel one pixel from a crease of 1.7 depth units per pixel
   (a chamfer's) is otherwise given to the wrong side about once in five.
   A pair of touching regions is a convex crease when, on the pixels of
   each within ``CREASE_REACH`` (chessboard) of the other, its own surface
   is the lower of the two at ``CREASE_AGREEMENT`` of them or more, and
   concave when it is the higher; across a step neither holds (the upper
   side's surface is above the lower's on both sides). A boundary pixel
   whose own and neighbour's surfaces differ there by less than
   ``CREASE_CLOSE * s`` takes the visible one of each such pair (the
   neighbour that is visible by the widest margin, else its own label);
   farther from the crease the residual decides, as in 2. (a wrong
   crease kind, or a quadric extrapolated too far, then does no harm).
"""

from __future__ import annotations

import math
from types import ModuleType

import numpy as np
from scipy import ndimage

from ..config import Config
from ..kernels.backend import Backend, select_deferred
from ..kernels.parallel import map_bands, map_pixel_bands
from ..stages.grow import evaluate_quadric
from ..stages.rangeimage import (
    HALF_NEIGHBOUR_PAIRS,
    chessboard_offsets,
    consecutive_labels,
    labels_on_valid,
)
from .fill import NEIGHBOUR_OFFSETS, surface_models
from .regions import c_array

#: Chessboard reach (pixels) of the pixels that tell a pair's crease kind (Notes 5).
CREASE_REACH = 3

#: Fraction of those pixels on which a region's surface must be the visible one.
CREASE_AGREEMENT = 0.8

#: The crease rule decides where two surfaces differ by less than this many ``s``.
CREASE_CLOSE = 3.0


def _boundary(labels: np.ndarray) -> np.ndarray:
    """Labelled pixels with an 8-neighbour of another label (not 0)."""
    out = np.zeros(labels.shape, dtype=bool)
    for one, other in HALF_NEIGHBOUR_PAIRS:
        a, b = labels[one], labels[other]
        differ = (a != b) & (a > 0) & (b > 0)
        out[one] |= differ
        out[other] |= differ
    return out


def _neighbour_labels(labels: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The 8-neighbours' labels of the pixels ``rows, cols``, int (N, 8), 0 beyond the image."""
    width = labels.shape[1] + 2
    steps = np.array([dr * width + dc for dr, dc in NEIGHBOUR_OFFSETS])
    flat = (rows + 1) * width + (cols + 1)
    return np.pad(labels, 1).ravel()[flat[:, None] + steps]


def pair_sums(keys: np.ndarray, lower: np.ndarray, votes: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pair keys present (sorted) and, per key, the sums of ``lower`` and ``votes``.

    Summed in input order per key (as ``np.bincount`` over a table of every
    key): sparse, since a frame of thousands of regions has millions of keys
    and few pairs.
    """
    pairs, where = np.unique(keys, return_inverse=True)
    return (pairs, np.bincount(where, weights=lower, minlength=pairs.size),
            np.bincount(where, weights=votes, minlength=pairs.size))


def crease_table(pairs: np.ndarray, lower: np.ndarray, total: np.ndarray, n: int,
                 agreement: float) -> np.ndarray:
    """int8 (n+1, n+1) kinds of :func:`crease_kinds` from the sums of :func:`pair_sums`.

    A pair is told when both of its keys (i, j) and (j, i) got votes.
    """
    kinds = np.zeros((n + 1, n + 1), dtype=np.int8)
    first, second = np.divmod(pairs, n + 1)
    back = np.searchsorted(pairs, second * (n + 1) + first)
    back = np.minimum(back, max(pairs.size - 1, 0))
    frac = lower / np.maximum(total, 1)
    seen = (total > 0) & (pairs[back] == second * (n + 1) + first) & (total[back] > 0)
    convex = seen & (frac >= agreement) & (frac[back] >= agreement)
    concave = seen & (frac <= 1 - agreement) & (frac[back] <= 1 - agreement)
    kinds[first[convex], second[convex]] = -1
    kinds[first[concave], second[concave]] = 1
    return kinds


def _crease_votes(padded: np.ndarray, rows: np.ndarray, cols: np.ndarray, own: np.ndarray,
                  mine: np.ndarray, coeffs: np.ndarray, reach: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pair keys and votes of :func:`crease_kinds`, one per pixel and offset (the reference)."""
    n1 = coeffs.shape[0]
    width = padded.shape[1]
    flat, spread = padded.ravel(), (rows + reach) * width + cols + reach
    keys, below = [], []
    for dr, dc in chessboard_offsets(reach):
        other = flat[spread + dr * width + dc]
        use = np.nonzero((other > 0) & (other != own))[0]
        keys.append(own[use].astype(np.int64) * n1 + other[use])
        below.append(mine[use] < evaluate_quadric(coeffs[other[use]], rows[use], cols[use]))
    key = np.concatenate(keys)
    return key, np.concatenate(below).astype(np.float64), np.ones(key.size)


def _compiled_votes(kernels: ModuleType, padded: np.ndarray, rows: np.ndarray,
                    cols: np.ndarray, own: np.ndarray, mine: np.ndarray, coeffs: np.ndarray,
                    reach: int) -> np.ndarray:
    """:func:`rangeseg_cli.kernels.compiled.crease_votes` by row bands of the pixels, at once.

    The pixels come in raster order; each band's votes are those of its
    pixels, and the bands' votes follow each other in that order: the same
    (V, 3) rows, transposed, as one call.
    """
    padded, rows, cols = c_array(padded, np.int32), c_array(rows, np.int64), c_array(cols, np.int64)
    own = own.astype(np.int64)
    parts = {-1: np.empty((0, 3), np.int64)}  # none when no pixel is near a boundary

    def band(i: int, j: int, _lo: int, _hi: int) -> None:
        parts[i] = kernels.crease_votes(padded, rows[i:j], cols[i:j], own[i:j], mine[i:j],
                                        coeffs, reach)

    map_pixel_bands(band, rows, padded.shape[0] - 2 * reach, padded.shape[1] - 2 * reach, 0)
    return np.concatenate([parts[k] for k in sorted(parts)]).T


def crease_kinds(labels: np.ndarray, coeffs: np.ndarray, *, reach: int = CREASE_REACH,
                 agreement: float = CREASE_AGREEMENT, boundary: np.ndarray | None = None,
                 backend: Backend = "auto") -> np.ndarray:
    """The kind of crease between each pair of nearby regions (Notes 5).

    Parameters
    ----------
    labels
        int (H, W) regions 1..n, 0 = none.
    coeffs
        float64 (n+1, 6) each region's surface (:func:`~rangeseg_cli.stages.grow.evaluate_quadric`).
    reach
        Chessboard distance (pixels) within which a pixel of one region
        compares its surface with the other region's.
    agreement
        Fraction of those pixels on which the region's own surface must be
        the lower (convex crease) or the higher one (concave crease).
    boundary
        bool (H, W) the labelled pixels with an 8-neighbour of another label,
        when the caller has them (computed otherwise).
    backend
        ``"numpy"``: the reference, a vote per pixel and offset; ``"numba"``:
        :func:`rangeseg_cli.kernels.compiled.crease_votes`, one vote per pixel
        and nearby region weighted by its pixels (the same counts); ``"auto"``:
        numba when installed and the kernel compiled
        (:func:`~rangeseg_cli.kernels.cache.ready`).

    Returns
    -------
    numpy.ndarray
        int8 (n+1, n+1), symmetric: -1 where the image is the pair's lower
        envelope (convex), +1 where it is the upper one (concave), 0 for
        neither (a step, or too few pixels to tell) and for regions that are
        not within ``reach`` of each other.
    """
    n = int(labels.max(initial=0))
    coeffs = c_array(coeffs[: n + 1], np.float64)
    boundary = _boundary(labels) if boundary is None else boundary
    near = ndimage.maximum_filter(boundary, size=2 * reach + 1)
    rows, cols = np.nonzero(near & (labels > 0))
    own = labels[rows, cols]
    mine = evaluate_quadric(coeffs[own], rows, cols)
    padded = np.pad(labels, reach)
    kernels = select_deferred(backend, "crease_votes")
    if kernels is None:
        keys, below, votes = _crease_votes(padded, rows, cols, own, mine, coeffs, reach)
    else:
        keys, below, votes = _compiled_votes(kernels, padded, rows, cols, own, mine, coeffs,
                                             reach)
    return crease_table(*pair_sums(keys, below, votes), n, agreement)


def _visible(kinds: np.ndarray, own: np.ndarray, near: np.ndarray, rows: np.ndarray,
             cols: np.ndarray, coeffs: np.ndarray, close: float) -> tuple[np.ndarray, np.ndarray]:
    """The label the crease rule gives each pixel, and where it decides (Notes 5)."""
    mine = evaluate_quadric(coeffs[own], rows, cols)
    decided = np.zeros(own.size, dtype=bool)
    best, margin = own.copy(), np.zeros(own.size)
    for k in range(near.shape[1]):
        other = np.where((near[:, k] > 0) & (near[:, k] != own), near[:, k], 0)
        kind = kinds[own, other]
        theirs = evaluate_quadric(coeffs[np.where(kind != 0, other, own)], rows, cols)
        here = (kind != 0) & (np.abs(theirs - mine) < close)
        wins = here & (kind * (theirs - mine) > margin)
        decided |= here
        best[wins], margin[wins] = other[wins], (kind * (theirs - mine))[wins]
    return best, decided


def _one_pass(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, scale: float,
              smoothness: float, creases: bool, backend: Backend) -> np.ndarray:
    """Each boundary pixel's cheapest label (Notes 2, 5); ``labels`` elsewhere.

    ``backend``: numpy calls over the boundary pixels (the reference) or
    :func:`rangeseg_cli.kernels.compiled.boundary_labels`, one compiled sweep
    (the same labels), as :func:`crease_kinds` chooses.
    """
    kernels = select_deferred(backend, "boundary_labels")
    if kernels is not None:  # the kernel finds the boundary pixels itself
        kinds = (crease_kinds(labels, coeffs, backend=backend) if creases
                 else np.zeros((1, 1), np.int8))
        z, labels = c_array(z, np.float64), c_array(labels, np.int32)
        out = labels.copy()
        coeffs, kinds = c_array(coeffs, np.float64), c_array(kinds, np.int8)

        def band(first: int, stop: int, _lo: int, _hi: int) -> None:  # reads rows +-1
            kernels.boundary_labels(z, labels, coeffs, scale, smoothness, kinds,
                                    CREASE_CLOSE * math.sqrt(scale), creases, out, first, stop)

        map_bands(band, labels.shape[0], labels.shape[1], 1)
        return out
    boundary = _boundary(labels)
    rows, cols = np.nonzero(boundary)
    near = _neighbour_labels(labels, rows, cols)
    heights = z[rows, cols]

    def cost(ids: np.ndarray) -> np.ndarray:
        residual = heights - evaluate_quadric(coeffs[ids], rows, cols)
        disagree = ((near > 0) & (near != ids[:, None])).sum(axis=1)
        return residual * residual / scale + smoothness * disagree

    own = labels[rows, cols]
    best, lowest = own.copy(), cost(own)
    for k in range(len(NEIGHBOUR_OFFSETS)):
        ids = near[:, k]
        usable = (ids > 0) & (ids != best)
        trial = np.where(usable, cost(np.where(usable, ids, own)), np.inf)
        better = trial < lowest
        best[better], lowest[better] = ids[better], trial[better]
    if creases:  # told again in every pass, as the boundaries move
        kinds = crease_kinds(labels, coeffs, boundary=boundary, backend=backend)
        visible, decided = _visible(kinds, own, near, rows, cols, coeffs,
                                    CREASE_CLOSE * math.sqrt(scale))
        best = np.where(decided, visible, best)
    out = labels.copy()
    out[rows, cols] = best
    return out


def refine_boundaries(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float,
                      backend: Backend = "auto") -> np.ndarray:
    """Move boundary pixels to the neighbouring surface that predicts them best (Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n, 0 = none.
    config
        ``config.split`` (from ``[refine]``) ``refine_passes``, ``refine_smoothness`` and
        ``refine_creases``; ``[grow]``
        ``planar_tolerance`` and ``min_error`` (the surfaces and ``s``).
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.stages.noise.estimate_noise`);
        NaN counts as 0.
    backend
        Of the crease votes (:func:`crease_kinds`) and of each pass (numpy or one
        compiled sweep): the same labels either way.

    Returns
    -------
    numpy.ndarray
        int32 (H, W) regions 1..k, k <= n, numbered in the order of their
        ids; the same pixels are labelled as in ``labels``.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, out = labels_on_valid(z, labels)
    sigma = 0.0 if math.isnan(noise) else noise
    scale = max(sigma * sigma, config.grow.min_error)
    for _ in range(config.split.refine_passes):
        n = int(out.max(initial=0))
        if n < 2:
            break
        coeffs, _ = surface_models(z, out, n, config.grow)
        moved = _one_pass(z, out, coeffs, scale, config.split.refine_smoothness,
                          config.split.refine_creases, backend)
        if np.array_equal(moved, out):
            break
        out = moved
    return consecutive_labels(out)
