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
   (ties by ids), and a pair whose regions already belong to larger groups is
   tested again on the groups, so no group is merged that its union would
   not pass. Merged regions take the smallest id of the group; ids are then
   made consecutive in their order.
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
from scipy import ndimage

from ..config import Config
from ..stages.grow import evaluate_quadric, fit_models, fit_quadrics, planar_regions
from ..stages.rangeimage import HALF_NEIGHBOUR_PAIRS, consecutive_labels, labels_on_valid
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


def _union_rms(z: np.ndarray, groups: np.ndarray, boxes: dict[int, tuple[slice, slice]],
               a: int, b: int, order: int = 2) -> float:
    """RMS error of one quadric (``order`` 2) or plane (1) fitted to the pixels of groups a, b."""
    box = join_box(boxes[a], boxes[b])
    both = np.isin(groups[box], (a, b)).astype(np.int32)
    _, mse, _ = fit_quadrics(z[box], both, 1, order=order)
    return math.sqrt(max(float(mse[1]), 0.0))


class _Groups:
    """Union-find over region ids with each group's pixels, box and RMS error."""

    def __init__(self, labels: np.ndarray, rms: np.ndarray, counts: np.ndarray):
        self.labels = labels.copy()
        self.rms = rms.copy()
        self.parent = np.arange(rms.size)
        self.boxes = {k + 1: b for k, b in enumerate(ndimage.find_objects(labels)) if b}
        self.counts = counts.astype(np.float64)  # pixels per group, as the fits counted them

    def root(self, k: int) -> int:
        """The group of region k (the smallest id in it)."""
        while self.parent[k] != k:
            k = int(self.parent[k])
        return k

    def join(self, a: int, b: int, rms: float) -> None:
        """Merge groups a and b (roots) whose union fits with RMS error ``rms``."""
        keep, gone = min(a, b), max(a, b)
        self.parent[gone] = keep
        box = join_box(self.boxes[keep], self.boxes.pop(gone))
        self.boxes[keep] = box
        sub = self.labels[box]
        sub[sub == gone] = keep
        self.rms[keep] = rms
        self.counts[keep] += self.counts[gone]

    def excess(self, a: int, b: int, union: float) -> float:
        """Squared error one surface of groups a, b leaves beyond their own two surfaces."""
        return union_excess(union, self.rms, self.counts, a, b)


def union_excess(union: float, rms: np.ndarray, counts: np.ndarray, a: int, b: int) -> float:
    """Squared error one surface of a and b (RMS ``union``) leaves beyond their own two.

    ``rms`` and ``counts``: each region's (or group's) own RMS error and pixel
    count. For two pieces of one surface it is the noise variance times a
    chi-square variable (3 degrees of freedom for planes): the statistic of
    ``split.crease_evidence``.
    """
    return float(union ** 2 * (counts[a] + counts[b]) - rms[a] ** 2 * counts[a]
                 - rms[b] ** 2 * counts[b])


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
    ((quad, mse), (planes, mse_plane)), counts = fit_models(zc, lab, n, (2, 1))
    is_plane = planar_regions(mse, mse_plane, counts, config.grow)
    if order == 2:
        rms = np.sqrt(np.maximum(mse, 0.0))
        flat = (rms <= level) & is_plane
        pairs = touching_pairs(lab, np.where(is_plane[:, None], planes, quad), 3.0 * level)
    else:  # planes only; the crease angle is tested on every pair
        rms, flat = np.sqrt(np.maximum(mse_plane, 0.0)), is_plane
        pairs = [(i, j) for i, j in touching_pairs(lab, planes, 3.0 * level)
                 if is_plane[i] and is_plane[j]]
    if not pairs:
        return consecutive_labels(lab)
    groups = _Groups(lab, rms, counts)
    first = [(_union_rms(zc, lab, groups.boxes, i, j, order), i, j) for i, j in pairs]
    floor = math.sqrt(config.grow.min_error)
    for union, i, j in sorted(first):
        a, b = groups.root(i), groups.root(j)
        if a == b:
            continue
        if (a, b) != (i, j):
            union = _union_rms(zc, groups.labels, groups.boxes, a, b, order)
        bound = min(level, config.split.min_gain * max(groups.rms[a], groups.rms[b], floor))
        if union > bound:
            continue
        if (flat[i] and flat[j] and crease_angle(lab, planes, i, j) >= config.split.min_crease
                and _crease_shown(groups.excess(a, b, union), noise, config)):
            continue
        groups.join(a, b, union)
    roots = np.array([groups.root(k) for k in range(n + 1)])
    roots[0] = 0
    return consecutive_labels(roots[lab])  # a group's root is its smallest id
