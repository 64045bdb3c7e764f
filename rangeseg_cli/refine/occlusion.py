"""Join the patches of one surface that an object lying across it divides.

Beyond Al-Hujazi & Sood (1990). Region growing (Sec. V-4) labels connected
components (Sec. V-3), so a surface that something closer to the sensor
crosses -- a lying cylinder under a part laid across it, a box top half
covered, the table seen through a nut's bore -- comes out as two regions,
each of them a good fit. They are one surface, with one description
(``surfaces.json``): its extent, its fit and its holdsite clearance are those
of the whole. This module gives such patches one label.

Notes
-----
1. Candidates. Regions of at least ``link.min_component`` pixels whose
   surface (plane when planar, else quadric; the rule of
   :func:`~rangeseg_cli.refine.fill.surface_models`) passes the fit test of the
   split (RMS error within ``split.fit_factor * s``, ``s = max(noise,
   sqrt(grow.min_error))``, Sec. VIII), taken in pairs that do not touch
   (8-neighbours), one of whose surfaces predicts the other's height at its
   centroid within ``SCREEN`` fit levels, and one quadric of whose union
   passes the fit test (from the moment sums).
2. One surface. One surface of the pair's model (a plane when both are
   planes, else a quadric) fits the union within the fit test and at most
   ``split.min_gain`` times the larger of the two RMS errors: the rules by
   which :mod:`rangeseg_cli.refine.merge` joins touching regions; and it leaves
   less than ``split.crease_evidence`` times ``s^2`` of squared error beyond
   the two patches' own surfaces (the chi-square bound of the merges'
   crease rule: two nearly coplanar faces of different parts pass the fit
   test at noise 2, not this; 0 = not tested).
3. Occlusion. Along the shortest straight segment from one patch to the
   other, every valid pixel between them lies on that surface (within
   ``OCCLUSION_MARGIN * s``) or above it (closer to the sensor), and some
   pixel lies clearly above: the surface goes on under something in front
   of it. A pixel clearly below it means the surface is seen to end there
   (two coplanar box tops with the floor between them): not joined.
4. Order: pairs by increasing RMS error of their union; a pair whose regions
   already belong to groups is tested again on the groups. A joined region
   keeps the smallest id; ids are then made consecutive.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..config import Config
from ..stages.grow import RegionFits, evaluate_quadric, planar_regions, region_fits
from ..stages.rangeimage import consecutive_labels, labels_on_valid
from .graph import RegionGraph, merge_ranked, region_graph
from .merge import union_bound
from .regions import adjacent_pairs, join_box

#: Pixels between two patches must lie within this many ``s`` of the surface, or above it.
OCCLUSION_MARGIN = 3.0

#: Screen of the pairs: one surface predicts the other's centroid within this many fit levels.
SCREEN = 10.0


def join_occluded(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                  ) -> np.ndarray:
    """Give separate patches of one surface, divided by something in front, one label.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n, 0 = none.
    config
        Uses ``config.split`` (``fit_factor``, ``min_gain``, ``crease_evidence``), ``[link]``
        (``min_component``) and ``[grow]`` (``min_error``, ``planar_tolerance``).
    noise
        The image's noise estimate, depth units (NaN: nothing is joined).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) labels 1..k; regions joined take the smallest id, ids
        made consecutive; pixels never change between labelled and 0.
    """
    z, lab = labels_on_valid(z, labels)
    n = int(lab.max(initial=0))
    if n < 2 or not math.isfinite(noise):
        return lab
    s = max(noise, math.sqrt(config.grow.min_error))
    level = config.split.fit_factor * s
    zc = np.where(np.isfinite(z), z, 0.0)
    fits = region_fits(zc, lab, n, (2, 1))
    ((quad, mse_quad), (plane, mse_plane)) = fits.fits
    flat = planar_regions(mse_quad, mse_plane, fits.counts, config.grow)
    coeffs = np.where(flat[:, None], plane, quad)  # the rule of fill.surface_models
    rms = np.sqrt(np.maximum(np.where(flat, mse_plane, mse_quad), 0.0))
    graph = region_graph(zc, lab, n, rms * rms, fits)
    pairs = _candidate_pairs(graph, fits, coeffs, rms, level, config.link.min_component)
    if not pairs or not _join(z, graph, pairs, flat, s, config):
        return lab
    return consecutive_labels(graph.labels)


def _candidate_pairs(graph: RegionGraph, fits: RegionFits, coeffs: np.ndarray,
                     rms: np.ndarray, level: float, min_pixels: int
                     ) -> list[tuple[float, int, int]]:
    """Pairs (i < j) of well-fitted regions that do not touch and may be one surface (Notes 1).

    Screens, cheapest first: one of the two surfaces predicts the other's
    height at its centroid within :data:`SCREEN` times the level (all pairs
    at once; a narrow patch's quadric extrapolates badly, the wide one's does
    not), and one quadric of the union passes the fit test, from the regions'
    moment sums (:class:`~rangeseg_cli.refine.graph.RegionGraph`, without
    visiting a pixel; a plane of the union fits no better).

    Returns
    -------
    list of (float, int, int)
        The union quadric's mean squared error and the pair, in increasing order.
    """
    ids = np.nonzero((fits.counts >= min_pixels) & (rms <= level))[0]
    ids = ids[ids > 0]
    if ids.size < 2:
        return []
    first, second = screened_pairs(coeffs[ids], fits.centroid_row[ids],
                                   fits.centroid_col[ids], SCREEN * level)
    if first.size == 0:
        return []
    touching = set(adjacent_pairs(graph.labels, 1))
    pairs = [(int(ids[a]), int(ids[b])) for a, b in zip(first, second, strict=True)]
    scored = [(graph.union_mse(i, j), i, j) for i, j in pairs if (i, j) not in touching]
    return sorted(t for t in scored if t[0] <= level * level)


#: Rows of the screen of :func:`screened_pairs` at once: its (ids, ids) matrices took
#: gigabytes on a 5 MP frame of thousands of regions.
SCREEN_ROWS = 512


def screened_pairs(coeffs: np.ndarray, rows: np.ndarray, cols: np.ndarray, limit: float
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (i < j, row-major) where one surface predicts the other's centroid height.

    Surface i at centroid j against surface j's own height there, and j at
    i against i's own, within ``limit`` for either (Notes 1): (n, 6)
    coefficients, (n,) centroids. :data:`SCREEN_ROWS` rows of the (n, n)
    comparison at a time.
    """
    n = rows.shape[0]
    own = evaluate_quadric(coeffs, rows, cols)  # each surface at its own centroid
    firsts, seconds = [np.zeros(0, np.intp)], [np.zeros(0, np.intp)]
    for lo in range(0, n, SCREEN_ROWS):
        hi = min(lo + SCREEN_ROWS, n)
        ahead = np.abs(evaluate_quadric(coeffs[lo:hi, None, :], rows[None, :], cols[None, :])
                       - own[None, :])
        back = np.abs(evaluate_quadric(coeffs[None, :, :], rows[lo:hi, None],
                                       cols[lo:hi, None]) - own[lo:hi, None])
        ok = (np.minimum(ahead, back) <= limit) & (np.arange(n) > np.arange(lo, hi)[:, None])
        first, second = np.nonzero(ok)
        firsts.append(first + lo)
        seconds.append(second)
    return np.concatenate(firsts), np.concatenate(seconds)


def _border(mask: np.ndarray) -> np.ndarray:
    """(k, 2) row, col of the pixels of ``mask`` with a 4-neighbour outside it."""
    inner = ndimage.binary_erosion(mask, border_value=0)
    return np.argwhere(mask & ~inner)


def group_border(graph: RegionGraph, a: int, cache: dict[int, tuple[float, np.ndarray]]
                 ) -> np.ndarray:
    """(k, 2) image row, col of group a's border pixels (:func:`_border`), in raster order.

    Taken in the group's own box: a pixel of the group on that box's edge has
    its outer neighbour outside the group, so the set and its order are those
    found in any box that holds the group. ``cache`` keeps each group's, keyed
    by its pixel count (a join grows it: found again).
    """
    count = float(graph.counts[a])
    hit = cache.get(a)
    if hit is None or hit[0] != count:
        box = graph.boxes[a]
        hit = (count, _border(graph.labels[box] == a) + (box[0].start, box[1].start))
        cache[a] = hit
    return hit[1]


def _occluded(z: np.ndarray, groups: np.ndarray, borders: tuple[np.ndarray, np.ndarray],
              ab: tuple[int, int], coeffs: np.ndarray, box: tuple[slice, slice], s: float
              ) -> bool:
    """Whether the shortest segment from patch a to patch b runs under something (Notes 3).

    ``box`` holds both patches (``ab``); ``borders`` are their border pixels
    in image coordinates (:func:`group_border`); ``coeffs`` is their union's
    surface in image coordinates. The closest pair of their border pixels
    ends the segment.
    """
    a, b = ab
    sub, zs = groups[box], z[box]
    start = np.array([box[0].start, box[1].start])
    pa, pb = borders[0] - start, borders[1] - start
    dist, near = cKDTree(pa).query(pb)
    k = int(np.argmin(dist))
    p, q = pb[k], pa[int(near[k])]
    steps = int(np.abs(p - q).max()) + 1
    r = np.rint(np.linspace(q[0], p[0], steps)).astype(int)
    c = np.rint(np.linspace(q[1], p[1], steps)).astype(int)
    between = ~np.isin(sub[r, c], (a, b)) & np.isfinite(zs[r, c])
    if not between.any():
        return False
    r, c = r[between], c[between]
    above = zs[r, c] - evaluate_quadric(coeffs, r + box[0].start, c + box[1].start)
    return bool(above.min() >= -OCCLUSION_MARGIN * s and above.max() > OCCLUSION_MARGIN * s)


def _join(z: np.ndarray, graph: RegionGraph, pairs: list[tuple[float, int, int]],
          flat: np.ndarray, s: float, config: Config) -> bool:
    """Join the pairs that pass Notes 2 and 3, by increasing union error (Notes 4).

    ``graph.own``: each region's own mean squared error. Returns whether any
    pair was joined.
    """
    level = config.split.fit_factor * s
    evidence = config.split.crease_evidence * s * s
    cache: dict[int, tuple[float, np.ndarray]] = {}  # each group's border (group_border)

    def one_surface(g: RegionGraph, a: int, b: int, union: float) -> bool:  # Notes 2
        if union > union_bound(g, a, b, level, config):
            return False
        return not 0 < evidence <= g.excess(a, b, union * union)

    def judge(g: RegionGraph, a: int, b: int, i: int, j: int, mse_quadric: float
              ) -> float | None:
        if (a, b) == (i, j) and not one_surface(g, a, b, math.sqrt(mse_quadric)):
            return None  # the union's quadric fits no worse than its plane: a bound
        coeffs, mse = g.union_fit(a, b, 1 if flat[i] and flat[j] else 2)
        union = math.sqrt(max(mse, 0.0))
        box = join_box(g.boxes[a], g.boxes[b])
        if not one_surface(g, a, b, union):
            return None
        borders = (group_border(g, a, cache), group_border(g, b, cache))
        if not _occluded(z, g.labels, borders, (a, b), coeffs, box, s):
            return None
        return union * union

    return merge_ranked(graph, pairs, judge)
