"""Step 3: edge linking and 4-connected components (Al-Hujazi & Sood 1990, Sec. V-3).

The edge maps of steps 1 and 2 (Sec. V-1, V-2) have thick step contours and
roof curves with one-pixel gaps. The paper closes a one-pixel gap "in any one
of the four directions" once, then labels the non-edge pixels with a
4-connected component algorithm and drops components smaller than 20 pixels
(Sec. VI, item 3).

Notes
-----
1. Gap closing, applied once: a valid non-edge pixel whose two neighbours
   along one of the four directions of Fig. 8 are both edges (codes 1 or 2)
   becomes an edge with code 3 (docs/outputs.md). Pixels already coded 3
   are treated as non-edge on input, so linking a linked map again gives the
   same map (the result depends only on the codes 1 and 2).
2. Components: the valid non-edge pixels are labelled by 4-connectivity;
   components of fewer than ``link.min_component`` pixels are dropped
   (label 0) and the rest renumbered 1..K in raster order of their first
   pixel.

Invalid pixels are never edges and never labelled (docs/sensors.md, units).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ..config import LinkConfig
from ..kernels.backend import Backend, select_kernels
from .edges import (
    DIRECTIONS,
    LINKED_EDGE,
    NO_EDGE,
    ROOF_EDGE,
    STEP_EDGE,
)

#: 4-connectivity structuring element for :func:`scipy.ndimage.label`.
FOUR_CONNECTED = ndimage.generate_binary_structure(2, 1)


def _check_inputs(codes: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate the edge codes and validity mask; return them as arrays."""
    codes = np.asarray(codes)
    valid = np.asarray(valid, dtype=bool)
    if codes.ndim != 2:
        raise ValueError(f"`codes` must be a 2-D edge map, got shape {codes.shape}")
    if valid.shape != codes.shape:
        raise ValueError(f"`valid` (shape {valid.shape}) must have the shape of `codes` "
                         f"({codes.shape})")
    if codes.dtype.kind not in "ui" or (codes.size and (codes.min() < 0 or codes.max() > 3)):
        raise ValueError("`codes` must be integers 0 (none), 1 (step), 2 (roof) or 3 "
                         f"(linked); got dtype {codes.dtype} with values outside 0..3")
    return codes, valid


def close_gaps(edge: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """One-pixel gaps of an edge map along the four directions of Fig. 8 (Sec. V-3).

    Parameters
    ----------
    edge
        bool (H, W) edge pixels.
    valid
        bool (H, W) valid pixels.

    Returns
    -------
    numpy.ndarray
        bool (H, W): valid non-edge pixels p with ``edge[p - d]`` and
        ``edge[p + d]`` for some direction d; pixels outside the image count
        as non-edge.
    """
    h, w = edge.shape
    padded = np.pad(edge, 1, constant_values=False)
    gaps = np.zeros(edge.shape, dtype=bool)
    for dy, dx in DIRECTIONS:
        ahead = padded[1 + dy: 1 + dy + h, 1 + dx: 1 + dx + w]
        behind = padded[1 - dy: 1 - dy + h, 1 - dx: 1 - dx + w]
        gaps |= ahead & behind
    return gaps & ~edge & valid


def label_components(free: np.ndarray, min_size: int) -> np.ndarray:
    """4-connected components of ``free`` of at least ``min_size`` pixels (Sec. V-3).

    Parameters
    ----------
    free
        bool (H, W) pixels to label (valid, non-edge).
    min_size
        Smaller components are dropped (label 0).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) labels 1..K, numbered in raster order of each
        component's first pixel; 0 elsewhere.
    """
    # scipy numbers the components in raster order of their first pixel: its
    # provisional labels grow in raster order and a merge keeps the smaller one
    raw, n = ndimage.label(free, structure=FOUR_CONNECTED)
    keep = np.bincount(raw.ravel(), minlength=n + 1) >= min_size
    keep[0] = False
    lut = np.zeros(n + 1, dtype=np.int32)
    lut[keep] = np.arange(1, np.count_nonzero(keep) + 1, dtype=np.int32)
    return lut[raw]


def link_edges(codes: np.ndarray, valid: np.ndarray, cfg: LinkConfig, *,
               backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Step 3: close one-pixel gaps once, then form the connected components (Sec. V-3).

    Parameters
    ----------
    codes
        uint8 (H, W) edge codes: 0 none, 1 step, 2 roof; 3 (an earlier
        linking) is read as non-edge, which makes the function idempotent.
    valid
        bool (H, W): False at invalid pixels (never edges, never labelled).
    cfg
        ``[link]``: ``min_component`` (20 in the paper, Sec. VI).
    backend
        ``"numpy"``: array operations; ``"numba"``: the codes and the pixels
        to label in one compiled sweep (:func:`rangeseg_cli.kernels.compiled.link_codes`,
        the same arrays); ``"auto"``: as :func:`~rangeseg_cli.stages.edges.detect_edges`.
        Either way :func:`label_components` labels the components.

    Returns
    -------
    codes : numpy.ndarray
        uint8 (H, W): the input's 1s and 2s, 3 at closed gaps, 0 elsewhere
        (always 0 at invalid pixels).
    components : numpy.ndarray
        int32 (H, W) components 1..K in raster order of their first pixel;
        0 at edges, invalid pixels and dropped components.

    Raises
    ------
    ValueError
        When the shapes differ or ``codes`` holds values outside 0..3.
    """
    codes, valid = _check_inputs(codes, valid)
    kernels = select_kernels(backend)
    if kernels is not None:
        out, free = kernels.link_codes(np.require(codes, np.uint8, ["C"]),
                                       np.require(valid, np.bool_, ["C"]))
        return out, label_components(free, cfg.min_component)
    is_step = (codes == STEP_EDGE) & valid
    is_roof = (codes == ROOF_EDGE) & valid
    edge = is_step | is_roof
    # Linking: close a one-pixel gap in any one of the four directions, once (Sec. V-3)
    gaps = close_gaps(edge, valid)
    out = np.full(codes.shape, NO_EDGE, dtype=np.uint8)
    out[is_roof] = ROOF_EDGE
    out[is_step] = STEP_EDGE
    out[gaps] = LINKED_EDGE
    # Connected components of the non-edge pixels, 4-connectivity (Sec. V-3)
    components = label_components(valid & ~edge & ~gaps, cfg.min_component)
    return out, components
