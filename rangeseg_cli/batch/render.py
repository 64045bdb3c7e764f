"""Pictures for eyes: edge maps, components, labels in colour, holdsite overlays.

Everything here returns uint8 arrays; :mod:`rangeseg_cli.batch.io` writes them.
The layout follows the paper's Figs. 10-13: edges white on black, regions
in colour, the holdsite a white square. The overlay shades each surface's
colour by height (nearer the sensor = brighter), so that it can be laid
beside the scene.
"""

from __future__ import annotations

from typing import Any

import numpy as np


def mask_image(mask: np.ndarray) -> np.ndarray:
    """A boolean map as a uint8 picture: 255 where true, 0 elsewhere."""
    return np.where(mask, np.uint8(255), np.uint8(0))


def edge_code_image(codes: np.ndarray) -> np.ndarray:
    """Edge codes (0 none, 1 step, 2 roof, 3 linked) as a colour picture.

    Step edges white, roof edges orange, pixels added by linking cyan.
    """
    palette = np.array([[0, 0, 0], [255, 255, 255], [255, 140, 0], [0, 200, 255]],
                       dtype=np.uint8)
    return palette[np.clip(codes, 0, 3)]


def height_image(z: np.ndarray) -> np.ndarray:
    """Heights stretched to 0..255 grey (invalid pixels black), for figures."""
    valid = ~np.isnan(z)
    out = np.zeros(z.shape, dtype=np.uint8)
    if valid.any():
        lo, hi = np.percentile(z[valid], [1, 99])
        scaled = (z[valid] - lo) / max(hi - lo, 1e-12)
        out[valid] = (np.clip(scaled, 0, 1) * 254 + 1).astype(np.uint8)
    return out


def label_colors(labels: np.ndarray) -> np.ndarray:
    """Labels in colour: a fixed, well-spread palette per id; 0 is black.

    Parameters
    ----------
    labels
        int (H, W) labels.

    Returns
    -------
    numpy.ndarray
        uint8 (H, W, 3); the same id always gets the same colour.
    """
    n = int(labels.max(initial=0))
    ids = np.arange(n + 1, dtype=np.float64)
    hue = (ids * 0.618033988749895) % 1.0
    sat = 0.55 + 0.35 * ((ids * 0.381966) % 1.0)
    val = 0.65 + 0.35 * ((ids * 0.7548776662) % 1.0)
    palette = (_hsv_to_rgb(hue, sat, val) * 255).round().astype(np.uint8)
    palette[0] = 0
    return palette[np.clip(labels, 0, n)]


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    i = np.floor(h * 6).astype(int) % 6
    f = h * 6 - np.floor(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    table = np.stack([np.stack(c, axis=-1) for c in
                      ((v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q))])
    return table[i, np.arange(len(h))]


def _stamp(image: np.ndarray, mask: np.ndarray, row: int, col: int) -> None:
    """Paint ``mask`` (odd shape, centred at (row, col)) white, clipped to the image."""
    h, w = image.shape[:2]
    kr, kc = mask.shape[0] // 2, mask.shape[1] // 2
    rr, cc = np.nonzero(mask)
    rr, cc = rr + row - kr, cc + col - kc
    keep = (rr >= 0) & (rr < h) & (cc >= 0) & (cc < w)
    image[rr[keep], cc[keep]] = 255


#: Brightness of the lowest (farthest) labelled pixels of an overlay; the highest get 1.
SHADE_FLOOR = 0.35


def shade_by_height(image: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Scale a colour picture's brightness by height: nearer the sensor = brighter.

    Parameters
    ----------
    image
        uint8 (H, W, 3) colours (e.g. :func:`label_colors`).
    z
        float (H, W) heights (larger = closer), NaN where invalid.

    Returns
    -------
    numpy.ndarray
        uint8 (H, W, 3): each pixel's colour times :data:`SHADE_FLOOR` at the
        1st percentile of the valid heights up to 1 at the 99th (clipped);
        invalid pixels keep their colour.
    """
    if z.shape != image.shape[:2]:
        raise ValueError(f"`z` (shape {z.shape}) must have the shape of `image` "
                         f"({image.shape[:2]})")
    valid = np.isfinite(z)
    if not valid.any():
        return image.copy()
    lo, hi = np.percentile(z[valid], [1, 99])
    t = np.clip((np.where(valid, z, hi) - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    factor = SHADE_FLOOR + (1.0 - SHADE_FLOOR) * t
    return (image * factor[..., None]).round().astype(np.uint8)


def overlay(labels: np.ndarray, holdsite: Any, size: tuple[int, int] | None = None,
            *, heights: np.ndarray | None = None) -> np.ndarray:
    """Segmentation in colour with the holdsite drawn as in the paper's Figs. 10-13.

    Parameters
    ----------
    labels
        int (H, W) final labels.
    holdsite
        A :class:`~rangeseg_cli.stages.holdsite.HoldsiteResult` or its ``to_dict()``
        (``holdsite.json``); ``None`` draws the labels only.
    size
        Footprint (rows, cols); by default each site's own ``size``.
    heights
        float (H, W) heights (NaN invalid): each surface's colour is shaded by
        them, nearer = brighter (:func:`shade_by_height`); ``None``: flat colours.

    Returns
    -------
    numpy.ndarray
        uint8 (H, W, 3): :func:`label_colors` (shaded), the chosen window
        filled white (rotated by its ``angle``), the runners-up outlined in white.
    """
    from scipy import ndimage

    from ..stages.holdsite import footprint

    image = label_colors(labels)
    if heights is not None:
        image = shade_by_height(image, heights)
    doc = holdsite.to_dict() if hasattr(holdsite, "to_dict") else (holdsite or {})
    sites = [(s, False) for s in doc.get("candidates", [])]
    if doc.get("holdsite"):
        sites.append((doc["holdsite"], True))  # drawn last, on top
    for site, chosen in sites:
        fp = footprint(tuple(size or site["size"]), float(site.get("angle", 0.0)))
        if not chosen:
            fp = fp & ~ndimage.binary_erosion(fp, border_value=0)
        _stamp(image, fp, int(site["row"]), int(site["col"]))
    return image
