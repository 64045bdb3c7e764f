"""Give the edge pixels left after growing to the surface that fits them best.

Beyond Al-Hujazi & Sood (1990). Region growing (Sec. V-4) leaves a pixel
unlabelled when it touches two surfaces ("no merging is allowed") and, after
its passes, wherever the band of edge pixels was thicker than the growth
reached. The paper's figures show these bands as the boundaries between
surfaces; a user of the labels (and the region-based metrics of Hoover et
al. 1996) loses them from every surface. At noise sigma 2 the bands of the
thick contours of Sec. V-1 and V-2 take a fifth of a face 10 pixels wide.

This last step runs the growing test once more, on the final regions, with
one change: a pixel that touches several regions joins the one whose surface
predicts it best relative to its bound, instead of staying an edge. Regions
then abut; their boundary is where the labels change, and
:mod:`rangeseg_cli.stages.surfaces` finds neighbours across it as before. The
pipeline fills twice: before the merge and the recut, which judge the
filled regions, and after them, since a merged region's surface or a recut
piece's plane can explain edge pixels that no surface explained before (the
walls of the cube's holes at noise 0, ``docs/quality.md``).

Notes
-----
* Surfaces: every final region's plane when it is planar, else its quadric
  (the rule of :mod:`rangeseg_cli.stages.surfaces`), with the bound ``error_factor
  * max(e_A, min_error)`` (Sec. V-4), fitted once and kept fixed.
* Test: an unlabelled valid pixel with labelled 8-neighbours joins the
  neighbouring region L with the smallest ``r_L^2 / bound_L`` when that is
  below 1 (``r_L`` its residual to L's quadric): the same acceptance as
  growing, so a pixel that no neighbouring surface explains (a true outlier,
  a jump pixel on a step edge) stays 0.
* Passes are simultaneous and repeat until nothing joins; growth only turns
  0 into a label, so this ends. Ties go to the first neighbour in raster
  order of the 3x3 window, so the result is deterministic.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..config import GrowConfig
from ..kernels.backend import Backend, select_kernels
from ..stages.grow import evaluate_quadric, fit_models, planar_regions
from ..stages.link import FOUR_CONNECTED
from ..stages.rangeimage import chessboard_offsets, labels_on_valid

#: The eight neighbour offsets (drow, dcol) in raster order of the 3x3 window.
NEIGHBOUR_OFFSETS: tuple[tuple[int, int], ...] = chessboard_offsets(1)


def _best_neighbour(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, bound: np.ndarray,
                    rows: np.ndarray, cols: np.ndarray,
                    offsets: tuple[tuple[int, int], ...] = NEIGHBOUR_OFFSETS
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the neighbouring label with the smallest ``r^2 / bound`` and that ratio.

    Neighbours are the pixels at ``offsets``; a label whose bound is 0 is never taken.

    Returns
    -------
    best : numpy.ndarray
        int32 (N,) label, 0 where no neighbour is labelled.
    ratio : numpy.ndarray
        float64 (N,) ``r^2 / bound`` of that label, inf where none.
    """
    h, w = labels.shape
    best = np.zeros(rows.size, np.int32)
    ratio = np.full(rows.size, np.inf)
    heights = z[rows, cols]
    for dr, dc in offsets:
        r, c = rows + dr, cols + dc
        at = np.flatnonzero((r >= 0) & (r < h) & (c >= 0) & (c < w))
        ids = labels[r[at], c[at]]
        keep = (ids > 0) & (bound[ids] > 0)
        at, ids = at[keep], ids[keep]
        res = heights[at] - evaluate_quadric(coeffs[ids], rows[at], cols[at])
        q = res * res / bound[ids]
        better = q < ratio[at]
        ratio[at[better]] = q[better]
        best[at[better]] = ids[better]
    return best, ratio


def surface_models(z: np.ndarray, labels: np.ndarray, n: int, cfg: GrowConfig
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Each region's surface: its plane when planar, else its quadric (Sec. V-4).

    A region is planar when the quadric lowers the plane's mean squared error
    by at most ``cfg.planar_tolerance`` of it (floored at ``cfg.min_error``),
    the rule of :func:`~rangeseg_cli.stages.surfaces.describe_surfaces`. On a narrow
    face the quadric's curvature terms follow the noise across the few
    pixels of its width and extrapolate badly along it; the plane does not.

    Returns
    -------
    coeffs : numpy.ndarray
        float64 (n+1, 6) image-coordinate coefficients.
    mse : numpy.ndarray
        float64 (n+1,) mean squared residual of the chosen model.
    """
    coeffs, mse, _ = fit_surfaces(z, labels, n, cfg)
    return coeffs, mse


def fit_surfaces(z: np.ndarray, labels: np.ndarray, n: int, cfg: GrowConfig
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`surface_models`, and bool (n+1,) which of them are planes.

    A plane's coefficients are (a0, a1, a2, 0, 0, 0): ``z = a0 + a1 col + a2 row``.
    """
    ((quad, mse_quad), (plane, mse_plane)), counts = fit_models(z, labels, n, (2, 1))
    flat = planar_regions(mse_quad, mse_plane, counts, cfg)
    return np.where(flat[:, None], plane, quad), np.where(flat, mse_plane, mse_quad), flat


def fill_edges(z: np.ndarray, labels: np.ndarray, cfg: GrowConfig, *,
               backend: Backend = "auto") -> np.ndarray:
    """Give each remaining edge pixel to the neighbouring surface that fits it best.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions 1..n (after growing, splitting and recovery), 0 = none.
    cfg
        ``[grow]``: ``error_factor`` and ``min_error`` give each surface's
        bound (Sec. V-4).
    backend
        ``"numpy"``: the passes as numpy calls over the pixels to test (the
        reference); ``"numba"``: :func:`rangeseg_cli.kernels.compiled.fill_passes`,
        all passes in one compiled call (the same labels); ``"auto"``: as
        :func:`~rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    numpy.ndarray
        int32 (H, W): ``labels`` with the unlabelled valid pixels that some
        neighbouring surface explains joined to the best one (see the module
        Notes); invalid pixels stay 0, existing labels are unchanged.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, out = labels_on_valid(z, labels)
    valid = np.isfinite(z)
    n = int(out.max(initial=0))
    if n == 0:
        return out
    coeffs, mse = surface_models(z, out, n, cfg)
    bound = cfg.error_factor * np.maximum(mse, cfg.min_error)
    bound[0] = 1.0  # never used: label 0 is not a neighbour
    kernels = select_kernels(backend)
    if kernels is not None:
        kernels.fill_passes(np.require(z, np.float64, ["C"]), out,
                            np.ascontiguousarray(coeffs, dtype=np.float64),
                            np.ascontiguousarray(bound, dtype=np.float64))
        return out
    open_ = valid & (out == 0)
    rows, cols = np.nonzero(open_)
    while rows.size:
        best, ratio = _best_neighbour(z, out, coeffs, bound, rows, cols)
        join = ratio < 1.0
        if not join.any():
            break
        out[rows[join], cols[join]] = best[join]
        open_[rows[join], cols[join]] = False
        rows, cols = _frontier(open_, rows[join], cols[join])
    return out


#: Chessboard reach (pixels) of the planar regions an edge pixel may bridge to.
BRIDGE_REACH = 2


def bridge_gaps(z: np.ndarray, labels: np.ndarray, cfg: GrowConfig, *,
                reach: int = BRIDGE_REACH) -> np.ndarray:
    """Give edge pixels left by the fill to a planar region within ``reach`` that explains them.

    Beyond Al-Hujazi & Sood (1990), after :func:`fill_edges`. A face 2-4
    pixels wide running diagonally across the pixel grid (part1's side, seen
    at a grazing angle) is a staircase of short runs joined at their corners.
    When growing gives a corner pixel of each run to the plane beside it,
    the runs' edge pixels no longer touch the face's region, and the fill,
    which looks at 8-neighbours only, leaves them unlabelled though the
    face's plane explains them. Here the test of the fill (Notes: ``r_L^2 /
    bound_L`` below 1, the smallest wins) is made against the regions within
    ``reach`` pixels (chessboard) whose surface is a plane; passes repeat
    until nothing joins. Curved surfaces are left out: a quadric fitted to a
    narrow region (a cup's handle) extrapolates loosely and would take the
    pixels of a face that has no region (the cup's rim).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) regions 1..n, 0 = none.
    cfg
        ``[grow]``: ``error_factor``, ``min_error`` (the bounds) and
        ``planar_tolerance`` (which surfaces are planes).
    reach
        Chessboard distance (pixels) of the regions considered, >= 1.

    Returns
    -------
    numpy.ndarray
        int32 (H, W): ``labels`` with the pixels joined; invalid pixels stay 0.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, out = labels_on_valid(z, labels)
    n = int(out.max(initial=0))
    if n == 0:
        return out
    coeffs, mse, flat = fit_surfaces(z, out, n, cfg)
    bound = np.where(flat, cfg.error_factor * np.maximum(mse, cfg.min_error), 0.0)
    bound[0] = 0.0
    offsets = chessboard_offsets(reach)
    open_ = np.isfinite(z) & (out == 0)
    # only pixels within reach of a planar region can join
    near = ndimage.maximum_filter(bound[out] > 0, size=2 * reach + 1, mode="constant")
    rows, cols = np.nonzero(open_ & near)
    while rows.size:
        best, ratio = _best_neighbour(z, out, coeffs, bound, rows, cols, offsets)
        join = ratio < 1.0
        if not join.any():
            break
        out[rows[join], cols[join]] = best[join]
        open_[rows[join], cols[join]] = False
        rows, cols = _frontier(open_, rows[join], cols[join], offsets)
    return out


def _frontier(open_: np.ndarray, rows: np.ndarray, cols: np.ndarray,
              offsets: tuple[tuple[int, int], ...] = NEIGHBOUR_OFFSETS
              ) -> tuple[np.ndarray, np.ndarray]:
    """The open pixels at ``offsets`` (8-adjacent) from the pixels ``rows, cols``, in raster order.

    Surfaces are fixed, so a pixel whose neighbours did not change in a pass
    gets the same test result in the next one: only the pixels next to the
    ones that just joined need testing again (on a real 640x480 frame the
    passes run a hundred times over a shrinking band).
    """
    h, w = open_.shape
    r = (rows[:, None] + np.array([dr for dr, _ in offsets])).ravel()
    c = (cols[:, None] + np.array([dc for _, dc in offsets])).ravel()
    inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
    flat = np.unique(r[inside] * w + c[inside])
    flat = flat[open_.ravel()[flat]]
    return flat // w, flat % w


def keep_leftovers(labels: np.ndarray, components: np.ndarray, min_pixels: int) -> np.ndarray:
    """Give each group of component pixels that no region holds a region of its own.

    Beyond Al-Hujazi & Sood (1990). The paper's growing (Sec. V-4) labels
    every pixel of a component of step 3 (Sec. V-3). The cuts of the
    refinement do not: a piece regrows only over the pixels its surface
    explains, and a trim leaves pixels out to be regrown. Where no surface
    of order <= 2 explains a patch -- a crumpled bag, a cloth, a real
    camera's surfaces whose error grows with their extent -- the patch is
    left with no region, and neither the surface descriptions nor the
    holdsite see it. This last pass gives each 4-connected group of such
    pixels (connected as the components of step 3 are) of at least
    ``min_pixels`` that is 3 pixels wide somewhere (a pixel with its four
    neighbours in it) a region of its own; its surface description reports
    how well a quadric fits it (``rms_error``). Strips 1-2 pixels wide stay
    unlabelled, as edges do.

    Parameters
    ----------
    labels
        int (H, W) regions 1..n, 0 = none.
    components
        int (H, W) components of step 3, 0 = none (edges and invalid pixels).
    min_pixels
        ``[link] min_component``: smaller groups stay unlabelled, as step 3
        drops smaller components; so do groups no 3x3 cross fits in.

    Returns
    -------
    numpy.ndarray
        int32 (H, W): ``labels`` with the groups numbered n+1, n+2, ... in
        raster order of their first pixel; every other pixel unchanged.

    Raises
    ------
    ValueError
        When the shapes of ``labels`` and ``components`` differ.
    """
    out = np.asarray(labels, dtype=np.int32).copy()
    if np.shape(components) != out.shape:
        raise ValueError(f"`labels` {out.shape} and `components` {np.shape(components)} "
                         "must have the same shape")
    left = (np.asarray(components) > 0) & (out == 0)
    groups, n = ndimage.label(left, structure=FOUR_CONNECTED)
    if n == 0:
        return out
    keep = np.bincount(groups.ravel(), minlength=n + 1) >= min_pixels
    core = ndimage.binary_erosion(left, structure=FOUR_CONNECTED)  # 3 px wide or more
    keep &= np.bincount(groups[core], minlength=n + 1) > 0
    keep[0] = False
    ids = np.zeros(n + 1, dtype=np.int32)
    first = int(out.max(initial=0)) + 1
    ids[keep] = np.arange(first, first + int(np.count_nonzero(keep)), dtype=np.int32)
    out[left] = ids[groups[left]]
    return out
