"""Surface descriptions of the final regions (Al-Hujazi & Sood 1990, Sec. V-4; docs/outputs.md).

After region growing "the quadratic surface fit is then repeated to obtain
the final surface parameters. These parameters can be used to classify the
object surfaces into a number of primitives" (Sec. V-4). This module does
that refit and the classification.

Notes
-----
* **Planar or curved.** A region is planar when the quadric lowers the
  plane's mean squared error by no more than ``grow.planar_tolerance`` of
  ``max(plane MSE, grow.min_error)``; the absolute floor keeps noise-free
  planes (both MSEs ~0) planar. A planar region reports its plane fit
  (a3 = a4 = a5 = 0) and the plane's RMS error: its quadratic terms are
  noise, and extrapolated to the region's border they would tilt its
  normals (edge types, holdsite approach vectors). A curved region reports
  the quadric.
* **Shape.** Besl & Jain's HK sign type of the quadric at the region's
  centroid, from its principal curvatures. Heights grow towards the sensor,
  so a cap bulging towards the sensor has H < 0, K > 0 and is a ``"peak"``.
  A principal curvature counts as zero below :data:`CURVATURE_ABS_TOL` or
  :data:`CURVATURE_REL_TOL` times the larger one. Planar regions are ``"flat"``.
* **Neighbours.** Two regions are neighbours when a pixel of one lies within
  :data:`NEIGHBOUR_REACH` (2) pixels (chessboard distance) of a pixel of the
  other, i.e. across an edge band up to one or two pixels thick. The pixel
  pairs found that way are the boundary; the fits are compared at their
  midpoints.
* **Edge type.** ``"step"`` when the median of ``|f_i - f_j|`` over the
  boundary midpoints exceeds ``step.threshold`` (the jump step 1 would
  detect, Sec. V-1). Otherwise the median angle between the fitted normals
  decides: below :data:`SMOOTH_ANGLE_DEG` the edge is ``"smooth"``; above it
  the edge is a roof, ``"roof-convex"`` when the crease points towards the
  sensor, i.e. each surface's extension passes *above* the other surface's
  boundary pixels (the measured surface is the lower envelope of the two
  fits, as at the ridge of a roof), else ``"roof-concave"``.
* **Cost.** One pass of moment sums gives the fits of both orders and the
  pixel counts, centroids and mean heights (:func:`~rangeseg_cli.stages.grow.region_fits`);
  the boundary pairs come from a band along the boundaries
  (:func:`neighbour_pairs`; compiled, from the runs of equal labels along
  the rows), with the heights and normals of the fits at them in the same
  compiled call (:func:`pair_measures`), their medians per region pair from
  counting sorts (:func:`pair_medians`) and the boxes from one sweep
  (:func:`label_boxes`), all compiled when numba is installed (identical
  results; ``backend="numpy"`` or ``RANGESEG_PURE_NUMPY=1`` for the reference).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy import ndimage

from ..config import Config, check_config
from ..kernels.backend import Backend, select_kernels
from ..models import Neighbor, Surface
from .grow import evaluate_quadric, planar_regions, quadric_gradient, region_fits, valid_labels
from .rangeimage import check_stage_arrays

#: Two regions are neighbours when pixels of both lie within this chessboard distance.
NEIGHBOUR_REACH = 2

#: Fitted normals closer than this (degrees) across a non-step boundary make a
#: "smooth" edge (continuous normal, Sec. III); wider angles make a roof. Ten
#: degrees is well above the normal noise of a fit over a few hundred pixels
#: at sigma 2 and well below the creases of machined parts.
SMOOTH_ANGLE_DEG = 10.0

#: A principal curvature below this magnitude (1 / pixel, heights in depth
#: units) counts as zero for the HK type: a radius of 10,000 pixels.
CURVATURE_ABS_TOL = 1e-4

#: ... or below this fraction of the larger principal curvature's magnitude
#: (a cylinder's axis direction is "zero" even when the fit bends it slightly).
CURVATURE_REL_TOL = 0.1

#: HK type names by the signs (-1, 0, 1) of the two principal curvatures k1 <= k2.
_HK_NAMES: dict[tuple[int, int], str] = {
    (0, 0): "flat", (-1, -1): "peak", (1, 1): "pit", (-1, 0): "ridge", (0, 1): "valley",
}


def curvatures(coefficients: np.ndarray, row: float, col: float) -> tuple[float, float]:
    """Mean and Gaussian curvature (H, K) of a quadric at one point (Monge patch).

    Parameters
    ----------
    coefficients
        (a0..a5) in image coordinates, x = col, y = row.
    row, col
        The point.

    Returns
    -------
    tuple of float
        ``H = ((1 + fx^2) fyy - 2 fx fy fxy + (1 + fy^2) fxx) / (2 w^3)`` and
        ``K = (fxx fyy - fxy^2) / w^4`` with ``w = sqrt(1 + fx^2 + fy^2)``;
        H < 0 where the surface bulges towards the sensor.
    """
    _, a1, a2, a3, a4, a5 = (float(c) for c in coefficients)
    fx = a1 + 2.0 * a3 * col + a4 * row
    fy = a2 + a4 * col + 2.0 * a5 * row
    fxx, fxy, fyy = 2.0 * a3, a4, 2.0 * a5
    w2 = 1.0 + fx * fx + fy * fy
    h = ((1 + fx * fx) * fyy - 2 * fx * fy * fxy + (1 + fy * fy) * fxx) / (2 * w2**1.5)
    k = (fxx * fyy - fxy * fxy) / (w2 * w2)
    return h, k


def hk_shape(h: float, k: float) -> str:
    """Besl & Jain's HK surface type from the mean and Gaussian curvature.

    Parameters
    ----------
    h, k
        Mean and Gaussian curvature (:func:`curvatures`; H < 0 bulges towards
        the sensor).

    Returns
    -------
    str
        ``flat``, ``peak``, ``pit``, ``ridge``, ``valley``, ``saddle-ridge``,
        ``saddle-valley`` or ``minimal``.
    """
    root = math.sqrt(max(h * h - k, 0.0))
    k1, k2 = h - root, h + root
    tol = max(CURVATURE_ABS_TOL, CURVATURE_REL_TOL * max(abs(k1), abs(k2)))
    s1, s2 = (0 if abs(c) < tol else (1 if c > 0 else -1) for c in (k1, k2))
    if s1 * s2 < 0:
        if abs(h) < tol:
            return "minimal"
        return "saddle-ridge" if h < 0 else "saddle-valley"
    return _HK_NAMES[(s1, s2)]


def _half_offsets(reach: int) -> list[tuple[int, int]]:
    """Half of the (2 reach + 1)^2 - 1 offsets (dy, dx) within ``reach``: each pair once."""
    return [(dy, dx) for dy in range(0, reach + 1) for dx in range(-reach, reach + 1)
            if dy > 0 or dx > 0]


def near_other_label(labels: np.ndarray, reach: int = NEIGHBOUR_REACH) -> np.ndarray:
    """Labelled pixels with a pixel of another label within ``reach`` (chessboard distance).

    Parameters
    ----------
    labels
        int (H, W) labels, 0 = none.
    reach
        Chessboard radius.

    Returns
    -------
    numpy.ndarray
        bool (H, W): the only pixels that can be an end of a boundary pair.
        Two separable running-extreme filters: the neighbourhood's largest
        label is above the pixel's, or its smallest positive label below.
    """
    size = 2 * reach + 1
    big = np.iinfo(labels.dtype).max
    high = ndimage.maximum_filter(labels, size=size, mode="constant", cval=0)
    low = ndimage.minimum_filter(np.where(labels > 0, labels, big), size=size,
                                 mode="constant", cval=big)
    return (labels > 0) & ((high > labels) | (low < labels))


def neighbour_pairs(labels: np.ndarray, reach: int = NEIGHBOUR_REACH, *,
                    backend: Backend = "auto") -> tuple[np.ndarray, ...]:
    """Pixel pairs (p, q) of different positive labels within ``reach`` of each other.

    Each unordered pair once: q = p + (dy, dx) for half of the offsets,
    offset by offset, p in raster order. The numpy reference examines only
    the pixels of :func:`near_other_label` (a band along the boundaries), so
    its cost is two filters of the image plus the length of the boundaries;
    the compiled :func:`rangeseg_cli.kernels.compiled.neighbour_pairs` does one sweep
    and gives the same arrays.

    Parameters
    ----------
    labels
        int (H, W) labels, 0 = none.
    reach
        Chessboard radius (:data:`NEIGHBOUR_REACH` for ``Surface.neighbors``).
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` (as
        :func:`rangeseg_cli.stages.edges.detect_edges`).

    Returns
    -------
    tuple of numpy.ndarray
        ``(rows_p, cols_p, rows_q, cols_q, labels_p, labels_q)``.
    """
    labels = np.asarray(labels)
    kernels = select_kernels(backend)
    if kernels is not None:
        lab = np.require(labels, np.int32 if labels.dtype.itemsize <= 4 else np.int64,
                         ["C", "W"])
        pairs = kernels.neighbour_pairs(lab, reach).T
        return (*pairs[:4], *pairs[4:].astype(labels.dtype))
    rp, cp = np.nonzero(near_other_label(labels, reach))
    lp = labels[rp, cp]
    padded = np.pad(labels, reach)
    parts: list[tuple[np.ndarray, ...]] = []
    for dy, dx in _half_offsets(reach):
        lq = padded[rp + reach + dy, cp + reach + dx]
        keep = (lq > 0) & (lq != lp)
        parts.append((rp[keep], cp[keep], rp[keep] + dy, cp[keep] + dx, lp[keep], lq[keep]))
    return tuple(np.concatenate([p[i] for p in parts]) for i in range(6))


def kernel_labels(labels: np.ndarray) -> np.ndarray:
    """``labels`` as the compiled kernels take them: C-ordered int32, int64 when it must be."""
    return np.require(labels, np.int32 if np.can_cast(labels.dtype, np.int32) else np.int64,
                      ["C"])


def _group_median(keys: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique keys and the median of ``values`` within each key."""
    order = np.lexsort((values, keys))
    keys, values = keys[order], values[order]
    uniq, start, count = np.unique(keys, return_index=True, return_counts=True)
    med = 0.5 * (values[start + (count - 1) // 2] + values[start + count // 2])
    return uniq, med


def pair_medians(lo: np.ndarray, hi: np.ndarray, values: np.ndarray, *,
                 backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Median of each row of ``values`` over the pixel pairs of each region pair (lo, hi).

    Parameters
    ----------
    lo, hi
        int (P,) labels of the two sides of each boundary pair (P > 0).
    values
        float (m, P): m values per pair.
    backend
        ``"numpy"``: ``np.lexsort`` per row (the reference); ``"numba"``:
        :func:`rangeseg_cli.kernels.compiled.pair_medians`, counting sorts of the
        labels (the same medians); ``"auto"``: as
        :func:`~rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    group_lo, group_hi : numpy.ndarray
        int64 (G,): the distinct (lo, hi), ascending.
    medians : numpy.ndarray
        float64 (m, G): ``0.5 (v[(c - 1) // 2] + v[c // 2])`` of each group's c sorted values.
    """
    lo, hi = np.asarray(lo, dtype=np.int64), np.asarray(hi, dtype=np.int64)
    values = np.asarray(values, dtype=np.float64)
    n = int(max(lo.max(), hi.max()))
    kernels = select_kernels(backend)
    if kernels is not None:
        return kernels.pair_medians(np.ascontiguousarray(lo), np.ascontiguousarray(hi), n,
                                    np.ascontiguousarray(values))
    key = lo * (n + 1) + hi
    grouped = [_group_median(key, v) for v in values]
    uniq = grouped[0][0]
    return uniq // (n + 1), uniq % (n + 1), np.stack([med for _, med in grouped])


def _unit_normals(coeffs: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals (-fx, -fy, 1) of quadrics at points.

    The length is ``np.linalg.norm``'s, summed in its order (fx^2 + fy^2 + 1),
    column by column: the same bits without a reduction over rows of three.
    """
    fx, fy = quadric_gradient(coeffs, rows, cols)
    length = np.sqrt(fx * fx + fy * fy + 1.0)
    n = np.empty((fx.shape[0], 3))
    np.divide(-fx, length, out=n[:, 0])
    np.divide(-fy, length, out=n[:, 1])
    np.divide(1.0, length, out=n[:, 2])
    return n


def _pair_heights(li: np.ndarray, lj: np.ndarray, rp: np.ndarray, cp: np.ndarray,
                  rq: np.ndarray, cq: np.ndarray, coeffs: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Height gap of the fits at each pair's midpoint, and how far each passes above the other.

    Convex: each fit's extension lies above the other region's boundary
    pixels (``above > 0``).
    """
    ci, cj = coeffs.take(li, axis=0), coeffs.take(lj, axis=0)
    rm, cm = 0.5 * (rp + rq), 0.5 * (cp + cq)
    gap = np.abs(evaluate_quadric(ci, rm, cm) - evaluate_quadric(cj, rm, cm))
    above = ((evaluate_quadric(cj, rp, cp) - evaluate_quadric(ci, rp, cp))
             + (evaluate_quadric(ci, rq, cq) - evaluate_quadric(cj, rq, cq)))
    return gap, above


def pair_measures(labels: np.ndarray, coeffs: np.ndarray, *, backend: Backend = "auto"
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The boundary pairs of neighbouring regions and what :func:`edge_types` measures on them.

    Parameters
    ----------
    labels
        int (H, W) final labels, 0 = none.
    coeffs
        (n+1, 6) image-coordinate quadrics of the labels.
    backend
        ``"numpy"``: :func:`neighbour_pairs` and array operations (the
        reference); ``"numba"``: :func:`rangeseg_cli.kernels.compiled.boundary_measures`,
        the pairs, heights and normals in one compiled call (bitwise the same
        values; the angle's arccos is numpy's in both); ``"auto"``: as
        :func:`~rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    li, lj : numpy.ndarray
        int (P,) labels of the two sides of each pixel pair, ``li < lj``.
    values : numpy.ndarray
        float64 (4, P): the height gap of the two fits at the pair's midpoint,
        the angle between their normals there (degrees), how far each fit
        passes above the other side's pixel (> 0: convex), and the signed gap
        ``f_i - f_j`` at the midpoint as :func:`rangeseg_cli.stages.holdsite.step_gaps`
        computes it (the same bits).
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        li, lj, values, ni, nj = kernels.boundary_measures(
            kernel_labels(labels), NEIGHBOUR_REACH, np.require(coeffs, np.float64, ["C"]))
        np.degrees(_normal_angles(ni, nj), out=values[1])
        return li, lj, values
    rp, cp, rq, cq, lp, lq = neighbour_pairs(labels, backend=backend)
    rm, cm = 0.5 * (rp + rq), 0.5 * (cp + cq)
    signed = evaluate_quadric(coeffs[lp], rm, cm) - evaluate_quadric(coeffs[lq], rm, cm)
    swap = lp > lq
    signed = np.where(swap, -signed, signed)  # as holdsite.step_gaps
    li, lj, rp, cp, rq, cq = (np.where(swap, lq, lp), np.where(swap, lp, lq),
                              np.where(swap, rq, rp), np.where(swap, cq, cp),
                              np.where(swap, rp, rq), np.where(swap, cp, cq))
    ci, cj = coeffs.take(li, axis=0), coeffs.take(lj, axis=0)
    angle = np.degrees(_normal_angles(_unit_normals(ci, rm, cm), _unit_normals(cj, rm, cm)))
    gap, above = _pair_heights(li, lj, rp, cp, rq, cq, coeffs)
    return li, lj, np.stack([gap, angle, above, signed])


def _normal_angles(ni: np.ndarray, nj: np.ndarray) -> np.ndarray:
    """Angles (radians) between the unit normals of two (N, 3) arrays, row by row."""
    return np.arccos(np.clip(np.einsum("ij,ij->i", ni, nj), -1.0, 1.0))


def boundary_medians(labels: np.ndarray, coeffs: np.ndarray, *, backend: Backend = "auto"
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Medians of :func:`pair_measures` over the boundary of each pair of neighbouring regions.

    Parameters
    ----------
    labels
        int (H, W) final labels, 0 = none.
    coeffs
        (n+1, 6) image-coordinate quadrics of the labels.
    backend
        For :func:`pair_measures` and :func:`pair_medians` (identical results).

    Returns
    -------
    group_i, group_j : numpy.ndarray
        int64 (G,) the neighbouring pairs i < j, ascending.
    medians : numpy.ndarray
        float64 (4, G): medians of the height gap, the angle between the
        normals, the "above" sums and the signed gap ``f_i - f_j``.
    """
    li, lj, values = pair_measures(labels, coeffs, backend=backend)
    if li.size == 0:
        none = np.zeros(0, dtype=np.int64)
        return none, none, np.zeros((4, 0))
    return pair_medians(li, lj, values, backend=backend)


def _edge_kinds(group_i: np.ndarray, group_j: np.ndarray, medians: np.ndarray,
                step_threshold: float) -> dict[tuple[int, int], str]:
    """The edge types of :func:`edge_types` from :func:`boundary_medians`."""
    out: dict[tuple[int, int], str] = {}
    gap_med, angle_med, above_med = medians[0], medians[1], medians[2]
    for i, j, g, a, s in zip(group_i.tolist(), group_j.tolist(), gap_med.tolist(),
                             angle_med.tolist(), above_med.tolist(), strict=True):
        if g > step_threshold:
            out[(i, j)] = "step"
        elif a < SMOOTH_ANGLE_DEG:
            out[(i, j)] = "smooth"
        else:
            out[(i, j)] = "roof-convex" if s > 0 else "roof-concave"
    return out


def edge_types(labels: np.ndarray, coeffs: np.ndarray, step_threshold: float, *,
               backend: Backend = "auto") -> dict[tuple[int, int], str]:
    """Neighbouring region pairs and the type of the edge between them (docs/outputs.md).

    Parameters
    ----------
    labels
        int (H, W) final labels, 0 = none.
    coeffs
        (n+1, 6) image-coordinate quadrics of the labels.
    step_threshold
        Median height difference of the fits along the boundary above which
        the edge is a step (``step.threshold``).
    backend
        For :func:`boundary_medians` (identical results).

    Returns
    -------
    dict
        ``{(i, j): edge}`` for i < j, edge one of ``"step"``, ``"smooth"``,
        ``"roof-convex"``, ``"roof-concave"``.
    """
    return _edge_kinds(*boundary_medians(labels, coeffs, backend=backend), step_threshold)


def label_boxes(labels: np.ndarray, n: int, *, backend: Backend = "auto") -> np.ndarray:
    """Inclusive bounding box of every label 0..n.

    Parameters
    ----------
    labels
        int (H, W) labels 0..n.
    n
        Largest label.
    backend
        ``"numpy"``: :func:`scipy.ndimage.find_objects` (the reference);
        ``"numba"``: :func:`rangeseg_cli.kernels.compiled.label_boxes`, one sweep over
        the runs of labels; ``"auto"``: as :func:`~rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    numpy.ndarray
        int64 (n+1, 4): (row_min, col_min, row_max, col_max); -1 for label 0
        and absent labels.
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        return kernels.label_boxes(np.require(labels, np.int32, ["C"]), n)
    boxes = np.full((n + 1, 4), -1, dtype=np.int64)
    for sid, box in enumerate(ndimage.find_objects(labels, max_label=n), start=1):
        if box is not None:
            boxes[sid] = (box[0].start, box[1].start, box[0].stop - 1, box[1].stop - 1)
    return boxes


def describe_surfaces(z: np.ndarray, labels: np.ndarray, config: Config, *,
                      backend: Backend = "auto") -> list[Surface]:
    """Refit the final regions and describe them (Sec. V-4; docs/outputs.md).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final labels of :func:`~rangeseg_cli.stages.grow.grow_regions`;
        0 = none. Labels at invalid pixels are ignored.
    config
        Uses ``grow.planar_tolerance``, ``grow.min_error`` and ``step.threshold``.
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` for the fits and the boundary
        pairs (identical results; see :func:`~rangeseg_cli.stages.grow.region_fits`).

    Returns
    -------
    list of Surface
        One per label present, by id: pixel count, inclusive bbox
        (row_min, col_min, row_max, col_max), centroid (row, col), mean
        height, coefficients in image coordinates (the plane for a planar
        region, else the quadric), RMS error of that fit, type
        (planar/curved), HK shape and neighbours sorted by id (see the module
        Notes for the rules).

    Raises
    ------
    ValueError
        When ``z`` is not a 2-D array of numbers, or ``labels`` not integers
        from 0 to the pixel count of its shape.
    ConfigError, TypeError
        For a configuration value out of range or a table of the wrong class
        (:func:`~rangeseg_cli.config.check_config`).
    """
    check_stage_arrays(z, labels=labels)
    check_config(config)
    return describe_surfaces_and_gaps(z, labels, config, backend=backend)[0]


def describe_surfaces_and_gaps(z: np.ndarray, labels: np.ndarray, config: Config, *,
                               backend: Backend = "auto"
                               ) -> tuple[list[Surface], dict[tuple[int, int], float]]:
    """:func:`describe_surfaces`, and the step gaps of the holdsite search (Sec. VII) with them.

    The gaps come from the same boundary pairs as the edge types (one more
    median per region pair): exactly
    :func:`rangeseg_cli.stages.holdsite.step_gaps` of these labels and surfaces,
    which :func:`~rangeseg_cli.stages.holdsite.find_holdsite` then need not
    compute again.

    Returns
    -------
    surfaces : list of Surface
        As :func:`describe_surfaces`.
    gaps : dict
        ``{(i, j): median(f_i - f_j)}`` for neighbouring regions i < j.
    """
    z = np.asarray(z, dtype=np.float64)
    labels, n = valid_labels(z, labels, backend=backend)
    if n == 0:
        return [], {}
    # Final surface parameters: the quadric fit repeated on the grown regions (Sec. V-4)
    stats = region_fits(z, labels, n, (2, 1), backend=backend)
    (quad, mse_quad), (plane, mse_plane) = stats.fits
    flat = planar_regions(mse_quad, mse_plane, stats.counts, config.grow)
    coeffs = np.where(flat[:, None], plane, quad)
    mse = np.where(flat, mse_plane, mse_quad)
    group_i, group_j, medians = boundary_medians(labels, coeffs, backend=backend)
    edges = _edge_kinds(group_i, group_j, medians, config.step.threshold)
    gaps = dict(zip(zip(group_i.tolist(), group_j.tolist(), strict=True), medians[3].tolist(),
                    strict=True))
    neighbours: dict[int, list[Neighbor]] = {}
    for (i, j), edge in sorted(edges.items()):
        neighbours.setdefault(i, []).append(Neighbor(id=j, edge=edge))
        neighbours.setdefault(j, []).append(Neighbor(id=i, edge=edge))
    boxes = label_boxes(labels, n, backend=backend).tolist()
    # Python numbers of every region at once (the same values as item by item)
    counts, rows, cols = (stats.counts.tolist(), stats.centroid_row.tolist(),
                          stats.centroid_col.tolist())
    heights, fits, errors, planes = (stats.mean_height.tolist(), coeffs.tolist(), mse.tolist(),
                                     flat.tolist())
    surfaces = []
    for sid in range(1, n + 1):
        if boxes[sid][0] < 0 or counts[sid] == 0:
            continue
        row, col = rows[sid], cols[sid]
        a = fits[sid]
        shape = "flat" if planes[sid] else hk_shape(*curvatures(np.asarray(a), row, col))
        surfaces.append(Surface(
            id=sid, pixels=counts[sid],
            bbox=tuple(boxes[sid]),  # type: ignore[arg-type]
            centroid=(row, col), mean_height=heights[sid],
            coefficients=tuple(a),  # type: ignore[arg-type]
            rms_error=math.sqrt(max(errors[sid], 0.0)),
            type="planar" if planes[sid] else "curved", shape=shape,
            neighbors=tuple(sorted(neighbours.get(sid, []), key=lambda nb: nb.id)),
        ))
    return surfaces, gaps


def _plain(value: Any) -> Any:
    """Tuples to lists, recursively, for JSON."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def surfaces_to_json(surfaces: list[Surface]) -> dict[str, Any]:
    """The ``surfaces.json`` document (docs/outputs.md).

    Parameters
    ----------
    surfaces
        From :func:`describe_surfaces`.

    Returns
    -------
    dict
        ``{"surfaces": [{"id", "pixels", "bbox", "centroid", "mean_height",
        "coefficients", "rms_error", "type", "shape", "neighbors": [{"id",
        "edge"}]}, ...]}`` with plain Python ints, floats, strings and lists.
    """
    return {"surfaces": [_plain(s.to_dict()) for s in surfaces]}
