"""Fit a chamfer between two planes that meet at a crease.

Beyond Al-Hujazi & Sood (1990), after the fills of :mod:`rangeseg_cli.refine.fill`
and before carving (:mod:`rangeseg_cli.refine.carve`). A face 2-4 pixels wide
between two planes -- the chamfer between a nut's top and one of its sides
-- is grown partly into the one and partly into the other (Sec. V-4). At
noise sigma 2 few of its pixels stand out from either plane alone, so a
test of each region's border (carving) finds only scraps of it; but over
the whole strip the two planes' envelope explains the image clearly worse
than the envelope with one more plane between them. The paper's conclusion
(Sec. VIII) asks for a test of the fits; this is that test along a crease.

Notes
-----
1. Pairs. Two touching regions (8-neighbours) that are both planar, each
   plane fitted to the region's interior -- its pixels whose
   ``(2 INTERIOR + 1)^2`` window holds no other label -- when that has
   ``link.min_component`` pixels or more (a chamfer's pixels grown into a
   steep side tilt the side's plane fitted to all of them), and that meet
   at a crease: on most of the zone's pixels of each (2.), its plane is
   the lower of the two (a convex crease, where the image is their lower
   envelope) or on most of each the higher (concave, the upper envelope).
   Across a step neither holds. (The refinement's crease kinds,
   :func:`~rangeseg_cli.refine.boundaries.crease_kinds`, ask for 80 % of the pixels
   next to the boundary; with a chamfer between them the two planes meet
   beyond the labels' boundary, so that test fails on the very pairs
   sought here.)
2. The zone: the pixels of each within ``ZONE`` pixels (chessboard) of the
   other, in the box round the pixels where they touch grown by ``ZONE +
   1``. A first plane is fitted to its pixels within ``SEED_BAND`` of the
   other region; then, up to ``ITERATIONS`` times, the chamfer's pixels are
   those of the zone where its plane is visible -- below both planes at a
   convex crease, above both at a concave one -- and its plane is fitted
   again to them, until they no longer change. Of these iterates whose
   plane meets both planes at ``MIN_ANGLE`` degrees or more (3.), the one
   with the smallest sum of squared residuals of the zone to the three
   planes' envelope plus ``PIXEL_COST * s^2`` per chamfer pixel is kept. At
   noise sigma 2 the iterates go on widening a chamfer into the flatter of
   its two planes (each pixel it takes tilts it towards that plane), and
   the sum of squares barely tells them apart (the nut's facet 35: 57
   pixels of 57 in the third iterate, with 72 pixels, 54 of 111 in the
   last, the sum 4 % lower); the cost keeps the narrow one.
3. The gain: the zone's sum of squared residuals to the two planes'
   envelope less that to the envelope of the three, in units of ``s^2``
   (``s = max(noise, sqrt(grow.min_error))``). A chamfer is kept when its
   gain is ``MIN_GAIN`` or more, it has ``link.min_component`` pixels or
   more, its plane fits them within the split's fit test
   (``split.fit_factor * s``), it meets both planes at ``MIN_ANGLE``
   degrees or more (and ``split.min_crease``), and no other planar region
   touching it has its plane (within ``split.min_crease`` and, on average
   over its pixels, within the fit test: a face an earlier step found). On
   noise-free 8-bit images the quantisation steps of a plane seen at a
   slant give a "chamfer" 14 degrees off it over a band of 66 pixels; the
   nut's chamfers meet its top at 60-85 degrees and its sides at 25-50.
4. A pixel that two chamfers claim (where two meet at a corner) goes to
   the one whose plane is nearer its height; a chamfer left with fewer
   than ``link.min_component`` pixels is dropped (its pixels keep their
   labels). Each chamfer becomes a region of its own, numbered after the
   existing ones in the order of decreasing gain; carving and the boundary
   refinement that follow (:mod:`rangeseg_cli.refine.boundaries`, Notes 5) settle its
   borders.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..config import Config
from ..stages.grow import plane_angle
from ..stages.rangeimage import HALF_NEIGHBOUR_PAIRS, labels_on_valid
from .fill import NEIGHBOUR_OFFSETS, fit_surfaces
from .recover import fit_plane, plane_height

#: Chessboard distance from the other region of a pair within which a pixel is in the zone.
ZONE = 5

#: Pixels within this distance of the other region seed the chamfer's first plane.
SEED_BAND = 2

#: Most refits of the chamfer's plane (Notes 2).
ITERATIONS = 8

#: What each pixel of a chamfer costs, in units of ``s^2``, when its iterates are
#: compared (Notes 2).
PIXEL_COST = 1.0

#: Smallest drop of the zone's sum of squared residuals, in units of ``s^2`` (Notes 3).
MIN_GAIN = 25.0

#: Smallest angle (degrees) between a chamfer's plane and each of the pair's (Notes 3).
MIN_ANGLE = 20.0

#: A region's interior: its pixels whose (2 INTERIOR + 1)^2 window holds no other label.
INTERIOR = 2

#: Fewest seed pixels for a first plane.
_MIN_SEED = 8


def touching_boxes(labels: np.ndarray) -> dict[tuple[int, int], tuple[int, int, int, int]]:
    """Each pair (i < j) of 8-touching regions: the box (r0, r1, c0, c1) of the touching pixels.

    Both pixels of every touching 8-neighbour pair are in the box (end exclusive).
    """
    big = int(labels.max(initial=0)) + 1
    keys, rows, cols = [], [], []
    for first, second in HALF_NEIGHBOUR_PAIRS:
        a, b = labels[first], labels[second]
        r, c = np.nonzero((a > 0) & (b > 0) & (a != b))
        la, lb = a[r, c].astype(np.int64), b[r, c].astype(np.int64)
        key = np.minimum(la, lb) * big + np.maximum(la, lb)
        keys += [key, key]
        rows += [r + (first[0].start or 0), r + (second[0].start or 0)]
        cols += [c + (first[1].start or 0), c + (second[1].start or 0)]
    key, row, col = np.concatenate(keys), np.concatenate(rows), np.concatenate(cols)
    if key.size == 0:
        return {}
    order = np.argsort(key, kind="stable")
    key, row, col = key[order], row[order], col[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    boxes = zip(np.minimum.reduceat(row, starts), np.maximum.reduceat(row, starts) + 1,
                np.minimum.reduceat(col, starts), np.maximum.reduceat(col, starts) + 1,
                strict=True)
    return {(int(k // big), int(k % big)): tuple(int(v) for v in box)  # type: ignore[misc]
            for k, box in zip(key[starts].tolist(), boxes, strict=True)}


def _zone(labels: np.ndarray, i: int, j: int, box: tuple[int, int, int, int]
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The zone's rows and cols (Notes 2), and bool: which of them seed the first plane."""
    h, w = labels.shape
    r0, r1 = max(box[0] - ZONE - 1, 0), min(box[1] + ZONE + 1, h)
    c0, c1 = max(box[2] - ZONE - 1, 0), min(box[3] + ZONE + 1, w)
    sub = labels[r0:r1, c0:c1]
    mi, mj = sub == i, sub == j
    to_j = ndimage.distance_transform_cdt(~mj, metric="chessboard")
    to_i = ndimage.distance_transform_cdt(~mi, metric="chessboard")
    near = np.where(mi, to_j, np.where(mj, to_i, ZONE + 1))
    rows, cols = np.nonzero(near <= ZONE)
    return rows + r0, cols + c0, near[rows, cols] <= SEED_BAND


def crease_kind(first: np.ndarray, planes: tuple[np.ndarray, np.ndarray], rows: np.ndarray,
                cols: np.ndarray) -> int:
    """The pair's crease: -1 convex, +1 concave, 0 neither (Notes 1).

    Convex when on most pixels of each side its plane is the lower of the
    two, concave when the higher. ``first``: bool, which of the pixels are
    the first region's.
    """
    below = plane_height(planes[0], rows, cols) < plane_height(planes[1], rows, cols)
    own_lower = np.where(first, below, ~below)
    if first.all() or not first.any():
        return 0
    a, b = own_lower[first].mean(), own_lower[~first].mean()
    return -1 if a > 0.5 and b > 0.5 else 1 if a < 0.5 and b < 0.5 else 0


def _chamfer(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, seed: np.ndarray,
             planes: tuple[np.ndarray, np.ndarray], kind: int, cost: float, min_angle: float
             ) -> tuple[float, np.ndarray, np.ndarray] | None:
    """Gain (unscaled), plane and bool pixels of the zone's chamfer (Notes 2, 3); None if none.

    ``cost``: what each pixel of the chamfer adds to the zone's sum of squares
    when the iterates are compared (Notes 2); iterates whose plane is within
    ``min_angle`` degrees of either plane are not compared.
    """
    if kind == 0 or np.count_nonzero(seed) < _MIN_SEED:
        return None
    heights = z[rows, cols]
    pick = np.minimum if kind < 0 else np.maximum
    both = pick(plane_height(planes[0], rows, cols), plane_height(planes[1], rows, cols))
    plane, mine = fit_plane(z, rows[seed], cols[seed]), seed
    best: tuple[float, float, np.ndarray, np.ndarray] | None = None
    for _ in range(ITERATIONS):
        own = plane_height(plane, rows, cols)
        visible = own < both if kind < 0 else own > both
        if np.count_nonzero(visible) < _MIN_SEED:
            break
        sse = float(np.sum((heights - pick(both, own)) ** 2))
        score = sse + cost * np.count_nonzero(visible)
        steep = min(plane_angle(plane, planes[0]), plane_angle(plane, planes[1])) >= min_angle
        if steep and (best is None or score < best[0]):
            best = (score, sse, plane, visible)
        if np.array_equal(visible, mine):
            break
        mine = visible
        plane = fit_plane(z, rows[mine], cols[mine])
    if best is None:
        return None
    return float(np.sum((heights - both) ** 2)) - best[1], best[2], best[3]


def _interior_planes(z: np.ndarray, labels: np.ndarray, n: int, config: Config
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Each region's surface fitted to its interior (Notes 1), and bool: which are planes.

    Regions with fewer than ``link.min_component`` interior pixels keep the fit
    of all their pixels.
    """
    size = 2 * INTERIOR + 1
    inner = (ndimage.minimum_filter(labels, size=size, mode="nearest")
             == ndimage.maximum_filter(labels, size=size, mode="nearest"))
    interior = np.where(inner, labels, 0)
    use = np.bincount(interior.ravel(), minlength=n + 1) >= config.link.min_component
    core, _, core_flat = fit_surfaces(z, interior, n, config.grow)
    if use[1:].all():
        return core, core_flat
    rest = np.where(use[labels], 0, labels)  # the regions without an interior, whole
    whole, _, whole_flat = fit_surfaces(z, rest, n, config.grow)
    return np.where(use[:, None], core, whole), np.where(use, core_flat, whole_flat)


def _candidates(z: np.ndarray, labels: np.ndarray, config: Config, s: float
                ) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
    """Every pair's kept chamfer (Notes 1-3): (gain, rows, cols, plane)."""
    coeffs, flat = _interior_planes(z, labels, int(labels.max(initial=0)), config)
    planes = coeffs[:, :3]
    out = []
    for (i, j), box in touching_boxes(labels).items():
        if not (flat[i] and flat[j]):
            continue
        rows, cols, seed = _zone(labels, i, j, box)
        pair = (planes[i], planes[j])
        found = _chamfer(z, rows, cols, seed, pair,
                         crease_kind(labels[rows, cols] == i, pair, rows, cols),
                         PIXEL_COST * s * s, max(config.split.min_crease, MIN_ANGLE))
        if found is not None and found[0] >= MIN_GAIN * s * s:
            plane, mine = found[1], found[2]
            if _kept(z, labels, rows[mine], cols[mine], plane, (i, j), (planes, flat), config,
                     s):
                out.append((found[0], rows[mine], cols[mine], plane))
    return out


def _kept(z: np.ndarray, labels: np.ndarray, rows: np.ndarray, cols: np.ndarray,
          plane: np.ndarray, pair: tuple[int, int], planes: tuple[np.ndarray, np.ndarray],
          config: Config, s: float) -> bool:
    """The tests of Notes 3 but the gain's and the angle's (made in :func:`_chamfer`)."""
    level = config.split.fit_factor * s
    if rows.size < config.link.min_component:
        return False
    rms = math.sqrt(float(np.mean((z[rows, cols] - plane_height(plane, rows, cols)) ** 2)))
    return (rms <= level
            and not _a_neighbours(labels, rows, cols, plane, pair, planes, level,
                                  config.split.min_crease))


def _a_neighbours(labels: np.ndarray, rows: np.ndarray, cols: np.ndarray, plane: np.ndarray,
                  pair: tuple[int, int], planes: tuple[np.ndarray, np.ndarray], level: float,
                  min_crease: float) -> bool:
    """Whether a planar region touching the chamfer (not of the pair) has its plane (Notes 3).

    Within ``min_crease`` degrees and, on average over the chamfer's pixels,
    within ``level``: a face that an earlier step has found already, which
    the refinement will settle. ``planes``: the regions' (n+1, 3) planes and
    bool (n+1,) which of them are planar.
    """
    h, w = labels.shape
    offsets = np.array(NEIGHBOUR_OFFSETS)
    r = np.clip(rows[:, None] + offsets[:, 0], 0, h - 1)
    c = np.clip(cols[:, None] + offsets[:, 1], 0, w - 1)
    own = plane_height(plane, rows, cols)
    coeffs, flat = planes
    for k in np.unique(labels[r, c]).tolist():
        if k == 0 or k in pair or not flat[k]:
            continue
        if (plane_angle(plane, coeffs[k]) < min_crease
                and np.mean(np.abs(own - plane_height(coeffs[k], rows, cols))) <= level):
            return True
    return False


def chamfer_faces(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                  ) -> np.ndarray:
    """Give a chamfer between two planes at a crease a region of its own (Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) regions 1..n, 0 = none.
    config
        ``[link] min_component``; ``[grow] planar_tolerance`` and
        ``min_error``; ``config.split.fit_factor`` and ``min_crease``.
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.stages.noise.estimate_noise`);
        NaN counts as 0.

    Returns
    -------
    numpy.ndarray
        int32 (H, W): ``labels`` with the chamfers numbered n+1, n+2, ... in
        the order of decreasing gain (Notes 4); the same pixels are labelled.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, out = labels_on_valid(z, labels)
    if int(out.max(initial=0)) < 2:
        return out
    sigma = 0.0 if math.isnan(noise) else noise
    s = math.sqrt(max(sigma * sigma, config.grow.min_error))
    known = np.nan_to_num(z)
    found = sorted(_candidates(known, out, config, s), key=lambda c: -c[0])
    owner = _owners(known, out.shape, found)
    next_id = int(out.max()) + 1
    for k, (_, rows, cols, _) in enumerate(found):
        won = owner[rows, cols] == k
        if np.count_nonzero(won) >= config.link.min_component:
            out[rows[won], cols[won]] = next_id
            next_id += 1
    return out.astype(np.int32, copy=False)


def _owners(z: np.ndarray, shape: tuple[int, ...],
            found: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
    """Per pixel, the index of the chamfer that takes it, -1 for none (Notes 4).

    A pixel two chamfers claim (where two chamfers meet at a corner) goes to
    the one whose plane is nearer its height; on a tie, to the larger gain.
    """
    owner = np.full(shape, -1)
    best = np.full(shape, np.inf)
    for k, (_, rows, cols, plane) in enumerate(found):
        residual = np.abs(z[rows, cols] - plane_height(plane, rows, cols))
        nearer = residual < best[rows, cols]
        owner[rows[nearer], cols[nearer]] = k
        best[rows[nearer], cols[nearer]] = residual[nearer]
    return owner
