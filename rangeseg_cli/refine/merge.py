"""Merge neighbouring regions that one surface fits to the noise.

Beyond Al-Hujazi & Sood (1990), the counterpart of the split of
:mod:`rangeseg_cli.refine.split` (Sec. VIII). Noise edges of the roof passes
(Sec. V-2) and the cuts of linking (Sec. V-3) can leave one face in several
components, which region growing (Sec. V-4, "no merging is allowed") keeps
apart: at noise sigma 2 the base of part1 (Fig. 10) comes out in three
pieces around the block, and faces in a pile in two.

Notes
-----
1. Candidates are regions that touch (8-neighbours) after the fill of
   :mod:`rangeseg_cli.refine.fill` -- a step between two regions leaves a band of
   pixels that fit neither, so regions across a step do not touch -- and
   whose surfaces agree along the boundary: the mean difference of their
   predicted heights at the touching pixels is within three times the fit test
   (a cheap, vectorised screen; only the pairs that pass are fitted).
2. Two groups of regions are merged when one quadric fits their union with
   an RMS error within the split's fit test (``split.fit_factor *
   max(noise, sqrt(grow.min_error))``, the test a component must pass not to
   be split) and at most ``split.min_gain`` times the larger RMS error of
   the two (floored at ``sqrt(grow.min_error)``), and, when both were
   planes passing the test, their planes meet at less than
   ``split.min_crease`` degrees along the boundary: the rules by which
   :func:`~rangeseg_cli.refine.split.merge_back` glues pieces of a split back. The
   angle keeps them apart only when the union's surface leaves at least
   ``split.crease_evidence`` times the noise variance of squared error
   beyond their own two (the F-test's idea: a narrow piece's plane, a ring
   segment of a nut's top with a few pixels of its chamfer, can tilt by
   18 degrees at noise sigma 2 while one plane fits both pieces as well as
   their own).
3. Order: candidate pairs are taken by increasing RMS error of their union
   (ties by ids), each once (:func:`~rangeseg_cli.refine.graph.merge_ranked`);
   a pair whose regions already belong to larger groups is tested on the
   groups, from the moment sums of the region graph
   (:mod:`rangeseg_cli.refine.graph`). A pair whose two regions both still
   give their groups' ids keeps the union error it was ranked by, of the
   two regions alone, though one may have grown since: the passes after
   the merge are tuned with this (testing the grown groups there costs 1-3
   correct detections at noise sigma 2 on each seed set of docs/quality.md).
   Merged regions take the smallest id of the group; ids are then made
   consecutive in their order.
4. Planes (:func:`merge_planes`, the pass ``merge_planes``, after the
   boundary refinement of :mod:`rangeseg_cli.refine.boundaries`). The same rules with
   a plane in the quadric's place, on planar regions only, the crease angle
   tested on every pair: two pieces of one face that later steps left apart
   (the recut, carving and the refinement change regions after the merge
   of 1-3 has run; at noise sigma 1 and 2 part1's grazing sides end in
   two pieces on some seeds). Not a quadric here: merged by 1-3 again at
   that point, carved chamfer facets went back into their planes and
   frustum faces at shallow creases into their neighbours.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import Config
from ..stages.grow import evaluate_quadric, planar_regions, region_fits
from ..stages.rangeimage import HALF_NEIGHBOUR_PAIRS, consecutive_labels, labels_on_valid
from .graph import RegionGraph, merge_ranked, region_graph
from .regions import crease_angle, join_box


def touching_pairs(labels: np.ndarray, coeffs: np.ndarray, max_gap: float
                   ) -> list[tuple[int, int]]:
    """Pairs (i < j) of touching regions whose surfaces agree along the boundary.

    Parameters
    ----------
    labels
        int32 (H, W) regions 1..n, 0 = none.
    coeffs
        float64 (n+1, 6) each region's surface (image coordinates, Sec. V-4).
    max_gap
        Largest mean absolute difference of the two surfaces' heights at the
        pixels where the regions touch (8-neighbours).

    Returns
    -------
    list of tuple
        Sorted unique pairs.
    """
    big = int(labels.max(initial=0)) + 1
    keys, gaps = [], []
    for first, second in HALF_NEIGHBOUR_PAIRS:
        a, b = labels[first], labels[second]
        rows, cols = np.nonzero((a > 0) & (b > 0) & (a != b))
        la, lb = a[rows, cols].astype(np.int64), b[rows, cols].astype(np.int64)
        cols = cols + (first[1].start or 0)
        gaps.append(np.abs(evaluate_quadric(coeffs[la], rows, cols)
                           - evaluate_quadric(coeffs[lb], rows, cols)))
        keys.append(np.minimum(la, lb) * big + np.maximum(la, lb))
    key = np.concatenate(keys)
    if key.size == 0:
        return []
    uniq, inverse = np.unique(key, return_inverse=True)
    mean_gap = np.bincount(inverse, np.concatenate(gaps)) / np.bincount(inverse)
    return [(int(k // big), int(k % big)) for k in uniq[mean_gap <= max_gap]]


def merge_regions(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                  ) -> np.ndarray:
    """Merge touching regions whose union one quadric fits to the noise (see Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n, 0 = none.
    config
        Uses ``config.split`` (``fit_factor``, ``min_gain``, ``min_crease``,
        ``crease_evidence``) and
        ``[grow]`` (``min_error``, ``planar_tolerance``).
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.stages.noise.estimate_noise`).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) regions 1..k, k <= n, numbered in the order of their
        smallest old id (also when nothing is merged: the ids that only
        invalid pixels held are gone).

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    return _merged(z, labels, config, noise, order=2)


def merge_planes(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                 ) -> np.ndarray:
    """Merge touching planar regions whose union one plane fits to the noise (Notes 4).

    Parameters, return value and errors as :func:`merge_regions`.
    """
    return _merged(z, labels, config, noise, order=1)


def union_bound(g: RegionGraph, a: int, b: int, level: float, config: Config) -> float:
    """The largest RMS error of one surface of groups a, b that lets them merge (Notes 2).

    The fit test's ``level``, and at most ``split.min_gain`` times the larger
    of the two groups' own RMS errors (``g.own``), floored at
    ``sqrt(grow.min_error)``; :mod:`~rangeseg_cli.refine.occlusion` joins by it too.
    """
    worst = math.sqrt(max(g.own[a], g.own[b], config.grow.min_error))
    return min(level, config.split.min_gain * worst)


def _crease_shown(excess: float, noise: float, config: Config) -> bool:
    """Whether a union's excess squared error is evidence of a crease (Notes 2).

    ``excess`` is what one surface of the union leaves beyond the pieces' own
    two; for two pieces of one plane it is the noise variance times a
    chi-square variable of 3 degrees of freedom (mean 3). Below
    ``split.crease_evidence`` times the variance (``max(noise^2,
    grow.min_error)``) the angle between the pieces' planes is noise in the
    tilt of a narrow piece, not a crease. ``crease_evidence = 0``: always.
    """
    bound = config.split.crease_evidence * max(noise ** 2, config.grow.min_error)
    return bound <= 0 or not math.isfinite(bound) or excess >= bound


def _merged(z: np.ndarray, labels: np.ndarray, config: Config, noise: float, *, order: int
            ) -> np.ndarray:
    """:func:`merge_regions` (``order`` 2, Notes 1-3) or :func:`merge_planes` (1, Notes 4)."""
    z, lab = labels_on_valid(z, labels)
    n = int(lab.max(initial=0))
    if n < 2:
        return consecutive_labels(lab)  # a label only on invalid pixels leaves a gap
    zc = np.where(np.isfinite(z), z, 0.0)
    level = config.split.fit_factor * max(noise, math.sqrt(config.grow.min_error))
    fitted = region_fits(zc, lab, n, (2, 1))
    ((quad, mse), (planes, mse_plane)), counts = fitted.fits, fitted.counts
    is_plane = planar_regions(mse, mse_plane, counts, config.grow)
    if order == 2:
        own = mse
        flat = (np.sqrt(np.maximum(mse, 0.0)) <= level) & is_plane
        pairs = touching_pairs(lab, np.where(is_plane[:, None], planes, quad), 3.0 * level)
    else:  # planes only; the crease angle is tested on every pair
        own, flat = mse_plane, is_plane
        pairs = [(i, j) for i, j in touching_pairs(lab, planes, 3.0 * level)
                 if is_plane[i] and is_plane[j]]
    if not pairs:
        return consecutive_labels(lab)
    graph = region_graph(zc, lab, n, np.maximum(own, 0.0), fitted)
    boxes = dict(graph.boxes)  # the regions' own, before any merge

    def judge(g: RegionGraph, a: int, b: int, i: int, j: int, first: float) -> float | None:
        union = first if (a, b) == (i, j) else g.union_mse(a, b, order)  # Notes 3
        if math.sqrt(union) > union_bound(g, a, b, level, config):
            return None
        if (flat[i] and flat[j]
                and crease_angle(lab, planes, i, j, join_box(boxes[i], boxes[j]))
                >= config.split.min_crease
                and _crease_shown(g.excess(a, b, union), noise, config)):
            return None
        return union

    ranked = sorted((graph.union_mse(i, j, order), i, j) for i, j in pairs)
    if not merge_ranked(graph, ranked, judge):
        return consecutive_labels(lab)
    return consecutive_labels(graph.labels)  # a group's id is its smallest region id
