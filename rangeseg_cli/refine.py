"""Settle each boundary pixel on the surface that predicts it best.

Beyond Al-Hujazi & Sood (1990), the last step of the grow stage (after the
fill of :mod:`rangeseg_cli.fill`). Region growing (Sec. V-4) gives a pixel to
the first region whose bound it meets, and the fill to the neighbour that
fits it best *relative to that neighbour's bound*; neither looks again once
a pixel is labelled. Along a crease both neighbours' bounds often hold, so
the boundary can sit a pixel or two off the crease. On a face 2-5 pixels
wide (a grazing side, a chamfer) that is most of the face: a region covering
it is not a correct detection (Hoover et al. 1996, T = 0.8).

Notes
-----
1. Surfaces: each region's plane when planar, else its quadric (the rule of
   :func:`~rangeseg_cli.fill.surface_models`), fitted again before every
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
3. Passes (``split.refine_passes``) are simultaneous: every boundary pixel
   takes its cheapest label (its own on a tie), then the surfaces are fitted
   again. They stop early when nothing changes. Unlabelled pixels stay
   unlabelled and labelled pixels stay labelled.
4. A region can lose all its pixels; labels are then made consecutive again
   in the order of their ids.
"""

from __future__ import annotations

import math

import numpy as np

from .config import Config
from .fill import NEIGHBOUR_OFFSETS, surface_models
from .grow import evaluate_quadric
from .rangeimage import HALF_NEIGHBOUR_PAIRS, consecutive_labels, labels_on_valid


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


def _one_pass(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, scale: float,
              smoothness: float) -> np.ndarray:
    """Each boundary pixel's cheapest label (Notes 2); ``labels`` elsewhere."""
    rows, cols = np.nonzero(_boundary(labels))
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
    out = labels.copy()
    out[rows, cols] = best
    return out


def refine_boundaries(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                      ) -> np.ndarray:
    """Move boundary pixels to the neighbouring surface that predicts them best (Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n, 0 = none.
    config
        ``[split]`` ``refine_passes`` and ``refine_smoothness``; ``[grow]``
        ``planar_tolerance`` and ``min_error`` (the surfaces and ``s``).
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.noise.estimate_noise`);
        NaN counts as 0.

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
        moved = _one_pass(z, out, coeffs, scale, config.split.refine_smoothness)
        if np.array_equal(moved, out):
            break
        out = moved
    return consecutive_labels(out)
