"""Region graph basics: adjacency, renumbering, boxes and crease angles of labels.

Beyond Al-Hujazi & Sood (1990). The steps after region growing (Sec. V-4)
that cut, merge and recover regions (:mod:`rangeseg_cli.refine.split`,
:mod:`rangeseg_cli.refine.recut`, :mod:`rangeseg_cli.refine.merge`,
:mod:`rangeseg_cli.refine.recover`, :mod:`rangeseg_cli.refine.facets`,
:mod:`rangeseg_cli.refine.occlusion`) share these small operations on a label
image: which regions are neighbours (:func:`adjacent_pairs`), labels
renumbered in raster order as linking numbers its components
(:func:`raster_renumber`), bounding boxes (:func:`bounding_box`,
:func:`join_box`, :func:`box_area`) and the angle at which the fitted
surfaces of two neighbours meet (:func:`crease_angle`); and the arrays the
compiled kernels take (:func:`c_array`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..kernels.backend import Backend, select_kernels


def c_array(a: np.ndarray, dtype: type) -> np.ndarray:
    """``a`` as a C-contiguous array of ``dtype``: ``a`` itself when it is one.

    What ``np.require(a, dtype, ["C"])`` gives (a copy only when needed), in a
    tenth of its time: the refinement hands thousands of small arrays a frame
    to the compiled kernels.
    """
    if a.dtype == dtype and a.flags.c_contiguous:
        return a
    return np.ascontiguousarray(a, dtype)


def adjacent_pairs(pieces: np.ndarray, reach: int = 2, *, backend: Backend = "auto"
                   ) -> list[tuple[int, int]]:
    """Pairs (i < j) of labels with pixels within chessboard distance ``reach``.

    Parameters
    ----------
    pieces
        int (h, w) labels, 0 = none.
    reach
        Largest chessboard distance between pixels of two neighbours (2: across
        a one-pixel line).
    backend
        ``"numpy"``: shifted comparisons of the array (the reference);
        ``"numba"``: the pixel pairs of :func:`rangeseg_cli.kernels.compiled.neighbour_pairs`
        (the same pairs); ``"auto"``: as :func:`~rangeseg_cli.kernels.backend.select_kernels`.

    Returns
    -------
    list of tuple
        Sorted unique pairs.
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        found = kernels.neighbour_pairs(c_array(pieces, np.int32), reach)
        big = int(pieces.max(initial=0)) + 1
        a, b = found[:, 4], found[:, 5]
        uniq = np.unique(np.minimum(a, b) * big + np.maximum(a, b))
        return [(int(k // big), int(k % big)) for k in uniq]
    h, w = pieces.shape
    padded = np.pad(pieces, reach)
    keys = []
    big = int(pieces.max(initial=0)) + 1
    for dy in range(0, reach + 1):
        for dx in range(-reach, reach + 1):
            if dy == 0 and dx <= 0:
                continue
            other = padded[reach + dy: reach + dy + h, reach + dx: reach + dx + w]
            hit = (pieces > 0) & (other > 0) & (pieces != other)
            a, b = pieces[hit].astype(np.int64), other[hit].astype(np.int64)
            keys.append(np.minimum(a, b) * big + np.maximum(a, b))
    uniq = np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)
    return [(int(k // big), int(k % big)) for k in uniq]


def raster_renumber(labels: np.ndarray, backend: Backend = "auto") -> np.ndarray:
    """Renumber labels 1..K in raster order of their first pixel (as link does).

    The first pixels come from ``np.unique`` (the reference) or, with the
    compiled kernels (``backend``), from one sweep
    (:func:`rangeseg_cli.kernels.compiled.first_pixels`): the same numbering.
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        first = kernels.first_pixels(c_array(labels, np.int32),
                                     int(labels.max(initial=0)))
        ids = np.flatnonzero(first >= 0)
        first = first[ids]
    else:
        ids, first = np.unique(labels.ravel(), return_index=True)
    keep = ids > 0
    order = ids[keep][np.argsort(first[keep], kind="stable")]
    lut = np.zeros(int(ids.max(initial=0)) + 1, np.int32)
    lut[order] = np.arange(1, order.size + 1, dtype=np.int32)
    return lut[labels]


def bounding_box(where: np.ndarray, pad: int) -> tuple[slice, slice]:
    """Bounding box of ``where``, grown by ``pad`` and clipped to the array."""
    rows, cols = np.nonzero(where.any(axis=1))[0], np.nonzero(where.any(axis=0))[0]
    h, w = where.shape
    return (slice(max(int(rows[0]) - pad, 0), min(int(rows[-1]) + pad + 1, h)),
            slice(max(int(cols[0]) - pad, 0), min(int(cols[-1]) + pad + 1, w)))


def join_box(p: tuple[slice, slice], q: tuple[slice, slice]) -> tuple[slice, slice]:
    """The bounding box of two boxes."""
    return (slice(min(p[0].start, q[0].start), max(p[0].stop, q[0].stop)),
            slice(min(p[1].start, q[1].start), max(p[1].stop, q[1].stop)))


def box_area(box: tuple[slice, slice]) -> int:
    """Pixels of a box of slices with set ends."""
    return int((box[0].stop - box[0].start) * (box[1].stop - box[1].start))


def crease_angle(pieces: np.ndarray, coeffs: np.ndarray, i: int, j: int,
                 within: tuple[slice, slice] | None = None) -> float:
    """Median angle in degrees between the fits of pieces i and j along their boundary.

    ``within``: a box of ``pieces`` (slices with set ends) that holds both
    pieces, when the caller knows one; only it is searched for them (the
    same angle, without a pass over the whole array).
    """
    r0, c0 = (within[0].start, within[1].start) if within else (0, 0)
    area = pieces[within] if within else pieces
    inner = bounding_box((area == i) | (area == j), 0)
    h, w = pieces.shape
    box = (slice(max(r0 + inner[0].start - 2, 0), min(r0 + inner[0].stop + 2, h)),
           slice(max(c0 + inner[1].start - 2, 0), min(c0 + inner[1].stop + 2, w)))
    sub = pieces[box]
    near = _within_two(sub == i) & _within_two(sub == j)
    rows, cols = np.nonzero(near)
    if rows.size == 0:
        return 0.0
    rows = rows + box[0].start
    cols = cols + box[1].start
    cos = np.sum(_normals(coeffs[i], rows, cols) * _normals(coeffs[j], rows, cols), axis=1)
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))


def _within_two(where: np.ndarray) -> np.ndarray:
    """Pixels within chessboard distance 2 of ``where`` (bool; nothing outside the array).

    The binary dilation by the 3 x 3 square twice, as one maximum filter of
    the 5 x 5 square: the same pixels, in a third of the time.
    """
    return np.asarray(ndimage.maximum_filter(where, size=5, mode="constant", cval=0))


def _normals(a: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals (-fx, -fy, 1) of one quadric (a0..a5) at pixels."""
    fx = a[1] + 2.0 * a[3] * cols + a[4] * rows
    fy = a[2] + a[4] * cols + 2.0 * a[5] * rows
    n = np.stack([-fx, -fy, np.ones_like(fx)], axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)
