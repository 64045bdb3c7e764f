"""Cut a region that fails the fit test into the planes that explain it.

Beyond Al-Hujazi & Sood (1990). The paper's conclusion (Sec. VIII) asks for
a quality-of-fit test that splits a region whose quadratic fit absorbs a
crease; :mod:`rangeseg_cli.refine.split` is that test on the linked components,
with pieces from clustering surface normals. At noise sigma 2 a small
frustum in a bin pile (sides 4-7 pixels wide) defeats it: the normals blend
across the narrow sides, the pieces hold a few pixels of their neighbours,
and the merge-back glues them together again (a piece's own error, raised
by those pixels, makes the union look "about as bad"). The region that
results fails the fit test -- its quadric leaves about 1.5 times the noise
-- while three or four planes explain it to the noise. This step, on the
final regions, looks for those planes; a curved surface that fails the
test too (a sphere, a lying cylinder) is cut into planes that one quadric
joins again, and is left whole.

Notes
-----
1. Regions: those the split's fit test fails
   (:func:`~rangeseg_cli.refine.split.failing_components`: ``2 * split.min_piece``
   pixels or more, quadric RMS error above the level ``split.fit_factor *
   s``, with ``s = max(noise, sqrt(grow.min_error))``), of ``MAX_REGION``
   pixels or fewer: a bound on the work, which grows with the region's
   pixels (a small frustum's faces at 128 x 128 are a few hundred pixels,
   at 640 x 480 a few thousand; without the pass ``split`` the failing
   components of a 640 x 480 pile, tens of thousands of pixels each, took
   0.7 s without it).
2. Seeds: planes by consensus (:func:`~rangeseg_cli.refine.recover.consensus_plane`,
   each pixel within ``SEED_FACTOR`` times the level), each from the pixels
   the ones before leave, up to ``MAX_PLANES``; those of ``split.min_piece``
   pixels or more are kept, and two are needed, whose inliers hold
   ``SEED_COVER`` of the region or more. (Where the surface is rougher than
   the noise estimate says -- a real camera that smooths its noise reads
   low, as the SR300 frame of ``sample_data/arc`` -- planes fitting within
   the level hold a quarter of a region's pixels or so; those regions are
   left whole without the work of the passes.)
3. k planes: each pixel takes the plane of least cost ``r^2 / s^2 +
   SMOOTHNESS * m``, with ``r`` its residual and ``m`` the number of its
   8-neighbours in the region that another plane holds; the planes are
   fitted again to their pixels, for up to ``PASSES`` passes or until no
   pixel moves. This is the boundary refinement's iterated conditional
   modes (:mod:`rangeseg_cli.refine.boundaries`, Besag 1986) with planes as the
   labels; the first pass has no neighbour term. A plane left with fewer
   than 3 pixels is dropped; so is, after the passes, a plane whose pixels
   another plane explains within ``DROP_GAIN * s^2`` per pixel of its own
   fit (a seed that fitted the noise on the top's pixels), and the passes
   start again.
4. Pieces: the 8-connected parts of each plane's pixels; a part under
   ``split.min_piece`` pixels goes to the nearest larger one.
5. Merge-back: while one quadric explains two touching pieces almost as
   well as their own surfaces (their union's squared error higher by less
   than ``MIN_GAIN * s^2`` per pixel, the recut's least gain of a cut:
   :data:`~rangeseg_cli.refine.recut.MIN_GAIN`), the pair with the least gain is
   merged; a merged piece's own surface is its quadric. The strips of a
   curved surface come back together here.
6. The cut is kept when two pieces or more are left and each one's plane
   passes the fit test; otherwise the region is left as it was. Merging
   cannot lower the planes' squared errors, so a region whose pieces'
   planes leave more than the test allows over all its pixels is left
   before the merge-back (:func:`beyond_planes`; on the SR300 frame of
   ``sample_data/arc`` most regions the passes reach).

New regions are numbered after the existing ones, in the order of the
regions they are cut from; a cut region keeps its id for its first piece in
raster order.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..config import Config
from ..kernels.backend import Backend, select_deferred
from ..kernels.parallel import map_tasks
from ..stages.grow import EIGHT_NEIGHBOURS, RegionFits, region_fits
from ..stages.rangeimage import chessboard_offsets, consecutive_labels, labels_on_valid
from .graph import RegionGraph, merge_cheapest, region_graph
from .recover import consensus_plane, fit_plane
from .recut import MIN_GAIN  # the least gain of a cut, s^2 per pixel (Notes 5)
from .regions import adjacent_pairs, c_array, raster_renumber
from .split import failing_components

#: A pixel fits a seed plane within this many times the fit-test level (Notes 2).
SEED_FACTOR = 1.0

#: The seed planes' inliers hold at least this share of the region (Notes 2).
SEED_COVER = 0.5

#: Most seed planes, and planes, of one region (Notes 2; 6 gains one region in 1,926 on
#: the held-out scenes for 60 % more time on the SR300 frame).
MAX_PLANES = 4

#: Regions with more pixels are left whole (a bound on the work, Notes 1).
MAX_REGION = 20_000

#: Cost of each 8-neighbour a pixel would disagree with, in units of ``s^2`` (Notes 3).
SMOOTHNESS = 1.0

#: Most passes of the k-planes assignment (Notes 3).
PASSES = 8

#: A plane the others explain within this many ``s^2`` per pixel of its pixels is dropped.
DROP_GAIN = 1.0

_OFFSETS = chessboard_offsets(1)


def _seeds(z: np.ndarray, mask: np.ndarray, tol: float, min_piece: int) -> list[np.ndarray]:
    """Consensus planes (a0, a1, a2) of ``min_piece`` pixels or more; none below the cover."""
    left = mask.copy()
    planes = []
    held = 0
    need = SEED_COVER * np.count_nonzero(mask)
    for _ in range(MAX_PLANES):
        if np.count_nonzero(left) < min_piece or held + np.count_nonzero(left) < need:
            break
        piece = consensus_plane(z, left, tol)
        if piece is None:
            break
        left &= ~piece
        size = int(np.count_nonzero(piece))
        if size >= min_piece:
            planes.append(fit_plane(z, *np.nonzero(piece)))
            held += size
    if held < need:
        return []
    return planes


def neighbour_table(rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]
                    ) -> np.ndarray:
    """(8, N): the index of each pixel's 8-neighbour in the region, -1 off it (Notes 3).

    Row ``o`` is the neighbour at offset ``o`` of
    :func:`~rangeseg_cli.stages.rangeimage.chessboard_offsets` ``(1)``; the
    pixels (rows, cols) are the region's, distinct, inside ``shape``. Built
    once per region: the k-planes passes look up the neighbours' planes in it.
    """
    grid = np.full((shape[0] + 2, shape[1] + 2), -1, np.int64)
    grid[rows + 1, cols + 1] = np.arange(rows.size)
    return np.stack([grid[rows + 1 + dr, cols + 1 + dc] for dr, dc in _OFFSETS])


def disagreeing(assign: np.ndarray, table: np.ndarray, k: int) -> np.ndarray:
    """(k, N) float: for each plane, the pixel's 8-neighbours in the region another plane holds.

    ``assign`` holds each pixel's plane 0..k-1; ``table`` is
    :func:`neighbour_table` of the pixels. Counts, exact in float64 (Notes 3).
    """
    inside = table >= 0
    near = np.where(inside, assign[table], -1)
    held = np.count_nonzero(inside, axis=0)
    return np.stack([held - np.count_nonzero(near == i, axis=0) for i in range(k)]
                    ).astype(np.float64)


def _squared_residuals(zs: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                       planes: list[np.ndarray], s2: float) -> np.ndarray:
    """(k, N) ``(z - plane)^2 / s2`` of each plane at the pixels (float rows, cols).

    The values of :func:`~rangeseg_cli.refine.recover.plane_height` bit for bit
    (the same operations, all planes at once).
    """
    p = np.asarray(planes)
    height = p[:, :1] + p[:, 1:2] * cols + p[:, 2:3] * rows
    return (zs - height) ** 2 / s2


def k_planes(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, planes: list[np.ndarray],
             s2: float, shape: tuple[int, int]) -> np.ndarray | None:
    """Plane index of each pixel after the k-planes passes (Notes 3), or None.

    After the passes, the plane whose pixels the other planes explain best
    is dropped when they explain them within ``DROP_GAIN * s^2`` per pixel
    of its own fit (a plane that fits the noise on another plane's pixels),
    and the passes start again with the planes left.

    Parameters
    ----------
    z
        float64 (h, w) heights.
    rows, cols
        The region's pixels.
    planes
        Seed planes (a0, a1, a2), two or more.
    s2
        ``s^2``, the unit of the squared residuals.
    shape
        ``(h, w)``.

    Returns
    -------
    numpy.ndarray or None
        int (N,) indices 0..k-1 of the planes left; None when fewer than two are left.
    """
    zs = z[rows, cols]
    table = neighbour_table(rows, cols, shape)
    rf, cf = rows.astype(np.float64), cols.astype(np.float64)
    while True:
        passed = _passes(z, (rows, cols, rf, cf, table), planes, s2)
        if passed is None:
            return None
        assign, planes = passed
        k = len(planes)
        r2 = _squared_residuals(zs, rf, cf, planes, s2)
        gains = [float(np.mean(np.delete(r2[:, assign == i], i, axis=0).min(axis=0)
                               - r2[i, assign == i])) for i in range(k)]
        weakest = int(np.argmin(gains))
        if gains[weakest] >= DROP_GAIN:
            return assign
        if k == 2:
            return None
        del planes[weakest]


_Pixels = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _passes(z: np.ndarray, pixels: _Pixels, planes: list[np.ndarray], s2: float, *,
            backend: Backend = "auto") -> tuple[np.ndarray, list[np.ndarray]] | None:
    """The passes of :func:`k_planes`: each pixel's plane 0..k-1, and the planes; or None.

    ``pixels``: the region's rows, cols (int and float) and :func:`neighbour_table`.
    None when fewer than two planes are left; the planes are those fitted to
    the returned indices. ``backend``: this numpy reference or, once compiled
    (:func:`~rangeseg_cli.kernels.backend.select_deferred`),
    :func:`rangeseg_cli.kernels.compiled.k_plane_passes` (the same values).
    """
    rows, cols, rf, cf, table = pixels
    kernels = select_deferred(backend, "k_plane_passes")
    if kernels is not None:
        assign, fitted, status = kernels.k_plane_passes(
            c_array(z, np.float64), c_array(rows, np.int64), c_array(cols, np.int64),
            c_array(table, np.int64), np.array(planes, np.float64), s2, PASSES, SMOOTHNESS)
        if status != 2:  # 2: a refit's pixels nearly on a line, left to the reference
            return (assign, list(fitted)) if status == 1 else None
    zs = z[rows, cols]
    assign = None
    for _ in range(PASSES):
        cost = _squared_residuals(zs, rf, cf, planes, s2)
        if assign is not None:
            cost += SMOOTHNESS * disagreeing(assign, table, len(planes))
        new = np.argmin(cost, axis=0)
        counts = np.bincount(new, minlength=len(planes))
        if (counts < 3).any():
            keep = counts >= 3
            if np.count_nonzero(keep) < 2:
                return None
            planes = [p for p, kept in zip(planes, keep, strict=True) if kept]
            new = np.argmin(cost[keep], axis=0)
        elif assign is not None and np.array_equal(new, assign):
            break
        assign = new
        planes = [fit_plane(z, rows[assign == i], cols[assign == i]) for i in range(len(planes))]
    return None if assign is None else (assign, planes)


def _parts(assign: np.ndarray, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int],
           min_piece: int) -> np.ndarray:
    """Pieces 1..m (int (h, w)): 8-connected parts, small ones given to the nearest (Notes 4)."""
    pieces = np.zeros(shape, np.int32)
    grid = np.full(shape, -1)
    grid[rows, cols] = assign
    n = 0
    for i in range(int(assign.max()) + 1):
        parts, m = ndimage.label(grid == i, structure=EIGHT_NEIGHBOURS)
        pieces[parts > 0] = parts[parts > 0] + n
        n += m
    big = np.bincount(pieces.ravel(), minlength=n + 1) >= min_piece
    big[0] = False
    kept = big[pieces]
    if not kept.any():
        return np.zeros(shape, np.int32)
    small = (pieces > 0) & ~kept
    if small.any():
        _, (near_r, near_c) = ndimage.distance_transform_edt(~kept, return_indices=True)
        pieces[small] = pieces[near_r[small], near_c[small]]
    return consecutive_labels(pieces)


def merge_back(z: np.ndarray, pieces: np.ndarray, s2: float,
               fitted: RegionFits | None = None) -> np.ndarray:
    """Merge touching pieces one quadric explains almost as well, least gain first (Notes 5).

    Parameters
    ----------
    z
        float64 (h, w) heights.
    pieces
        int (h, w) pieces 1..m, 0 = none; each piece's own surface is its plane.
    s2
        ``s^2``, the unit of the gain.
    fitted
        ``region_fits(z, pieces, m, (1,))`` when the caller has it (``pieces``
        numbered 1..m then).

    Returns
    -------
    numpy.ndarray
        int32 (h, w) pieces renumbered 1..k in the order of their ids.
    """
    if fitted is None:
        pieces = consecutive_labels(pieces)
        fitted = region_fits(z, pieces, int(pieces.max(initial=0)), (1,))
    n = int(pieces.max(initial=0))
    graph = region_graph(z, pieces, n, fitted.fits[0][1], fitted)  # own surface: the plane

    def gain(g: RegionGraph, a: int, b: int) -> float:
        """Squared error per pixel, in ``s2``, one quadric of a and b adds to their own."""
        return g.excess(a, b, g.union_mse(a, b)) / ((g.counts[a] + g.counts[b]) * s2)

    def union(g: RegionGraph, a: int, b: int) -> float:
        return g.union_mse(a, b)  # the merged piece's own surface: its quadric

    merge_cheapest(graph, adjacent_pairs(pieces, 1), gain, union, limit=MIN_GAIN)
    return consecutive_labels(graph.labels)


#: Relative margin of :func:`beyond_planes` over rounding in the squared errors.
BOUND_MARGIN = 1e-6


def beyond_planes(fitted: RegionFits, level: float) -> bool:
    """Whether no merge of these pieces can leave pieces whose planes all pass (Notes 6).

    The merge-back (Notes 5) only joins pieces, and the best plane of a
    union leaves at least the squared errors of the pieces' own best planes
    together. So when the pieces' planes leave more than ``level^2`` per
    pixel of them all, whatever is merged, some piece's plane fails the fit
    test at the end: the cut is known to be dropped before the merge-back's
    work.

    Parameters
    ----------
    fitted
        ``region_fits(z, pieces, m, (1,))`` of the pieces 1..m.
    level
        RMS error of the fit test, depth units; at 0 nothing is known (False).

    Returns
    -------
    bool
        True when the pieces' planes leave more than ``level^2`` per pixel,
        by :data:`BOUND_MARGIN` of it.
    """
    (_, mse), = fitted.fits
    counts = fitted.counts[1:].astype(np.float64)
    total = float(counts.sum())
    bound = level * level * total * (1.0 + BOUND_MARGIN)
    return bound > 0 and float(mse[1:] @ counts) > bound


def cut_into_planes(z: np.ndarray, mask: np.ndarray, *, level: float, s2: float,
                    min_piece: int) -> np.ndarray | None:
    """Pieces of a region that fails the fit test, one plane each, or None (Notes 2-6).

    Parameters
    ----------
    z
        float64 (h, w) heights, finite on ``mask``.
    mask
        bool (h, w) the region's pixels.
    level
        RMS error of the fit test, depth units.
    s2
        ``s^2 = max(noise^2, grow.min_error)``.
    min_piece
        ``split.min_piece``: the smallest seed plane and piece.

    Returns
    -------
    numpy.ndarray or None
        int32 (h, w) pieces 1..k (k >= 2), 0 outside ``mask``; None when
        the region is to be left whole.
    """
    planes = _seeds(z, mask, SEED_FACTOR * level, min_piece)
    if len(planes) < 2:
        return None
    rows, cols = np.nonzero(mask)
    assign = k_planes(z, rows, cols, planes, s2, mask.shape)
    if assign is None:
        return None
    parts = _parts(assign, rows, cols, mask.shape, min_piece)
    fitted = region_fits(z, parts, int(parts.max(initial=0)), (1,))
    if beyond_planes(fitted, level):
        return None
    pieces = raster_renumber(merge_back(z, parts, s2, fitted))
    k = int(pieces.max(initial=0))
    if k < 2:
        return None
    (_, mse_plane), = region_fits(z, pieces, k, (1,)).fits
    return pieces if (mse_plane[1:] <= level * level).all() else None


def facet_regions(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                  ) -> np.ndarray:
    """Cut each region that fails the fit test into the planes that explain it (Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) regions 1..n, 0 = none.
    config
        ``config.split.fit_factor`` and ``min_piece``; ``[grow] min_error``.
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.stages.noise.estimate_noise`);
        NaN counts as 0.

    Returns
    -------
    numpy.ndarray
        int32 (H, W): ``labels`` with the new pieces numbered n+1, n+2, ...

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, out = labels_on_valid(z, labels)
    sigma = 0.0 if math.isnan(noise) else noise
    s2 = max(sigma * sigma, config.grow.min_error)
    level = config.split.fit_factor * math.sqrt(s2)
    failing = failing_components(z, out, sigma, config.split, config.grow)
    if failing.size == 0:
        return out
    boxes = ndimage.find_objects(out)
    next_id = int(out.max(initial=0)) + 1
    counts = np.bincount(out.ravel(), minlength=int(out.max(initial=0)) + 1)
    todo = failing[counts[failing] <= MAX_REGION].tolist()

    def cut(k: int) -> np.ndarray | None:  # a region's cut reads its own pixels only
        return cut_into_planes(z[boxes[k - 1]], out[boxes[k - 1]] == k, level=level, s2=s2,
                               min_piece=config.split.min_piece)

    # The regions are independent: a real frame's many go to processes (map_tasks).
    for k, pieces in zip(todo, map_tasks(cut, todo, cost=[float(counts[k]) for k in todo]),
                         strict=True):
        for i in range(2, 0 if pieces is None else int(pieces.max()) + 1):
            out[boxes[k - 1]][pieces == i] = next_id
            next_id += 1
    return out
