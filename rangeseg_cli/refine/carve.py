"""Carve narrow faces out of the border of a planar region.

Beyond Al-Hujazi & Sood (1990), after the fill of :mod:`rangeseg_cli.refine.fill`
and before the boundary refinement of :mod:`rangeseg_cli.refine.boundaries`. Region
growing (Sec. V-4) accepts a pixel whose squared residual is below
``grow.error_factor`` times the region's error: ten times, by default. A
face 2-5 pixels wide along a plane's border -- the chamfer round a nut's
top, rising 1.7 depth units per pixel against it -- stays within that bound
for its first pixels and is grown into the plane, so no later step sees it
as unlabelled (:mod:`rangeseg_cli.refine.recover`) or as a failed fit
(:mod:`rangeseg_cli.refine.split`: a few dozen pixels barely move the RMS error of
a region of a thousand). The paper's conclusion (Sec. VIII) asks for a test
of the fits; this is that test on a region's border.

Notes
-----
1. Regions. A region of ``4 * link.min_component`` pixels or more whose
   interior -- its pixels ``INTERIOR + 1`` or more pixels (chessboard) from
   any other -- has ``2 * link.min_component`` pixels or more and is planar
   by ``grow.planar_tolerance`` (:func:`~rangeseg_cli.stages.grow.planar`). Its
   plane is fitted to the interior only, which an absorbed face barely
   reaches, and fitted again without the interior pixels farther than
   ``OUTLIER_FACTOR`` times the fit-test level from it (the face's first
   pixels); the planar test is made on the rest, which must be
   ``INLIER_SHARE`` of the interior or more. Where that plane fits the
   inliers with an RMS error above the noise (a real surface that is not
   quite a plane), the error takes the noise's place in ``s`` below.
2. Candidates. On the region's border (its pixels not in the interior), the
   residual to that plane, averaged over the region's pixels in the 3x3
   window, is a face's when it is over ``SIGNIFICANCE * s / sqrt(k)``, with
   ``k`` the pixels averaged and ``s = max(noise, sqrt(grow.min_error))``:
   the mean of pure noise stays below that. Candidates fall into 8-connected
   groups; groups of ``SEED_PIXELS`` or more are cut into planes by
   consensus (:func:`~rangeseg_cli.refine.recover.plane_pieces`, each pixel within
   twice ``PIECE_FACTOR`` times the fit test level: two faces of a chamfer
   meeting at a corner are two pieces).
3. Faces. A piece's plane is fitted again after one pass of extension: the
   region's pixels next to it whose residual to its plane is below their
   residual to the region's plane join it. It becomes a region of its own
   when it has ``link.min_component`` pixels or more, its RMS error passes
   the split's fit test (``split.fit_factor * s``, Sec. VIII) and its plane
   meets the region's at ``split.min_crease`` degrees or more (the split's
   rule for two planes that stay apart; a piece of the region's own plane,
   at a step's mixed pixels, does not).

The boundary refinement that follows settles the new faces' borders
(:mod:`rangeseg_cli.refine.boundaries`, Notes 5: the crease rule). New regions are
numbered after the existing ones, in the order of the regions they are cut
from; existing labels keep their ids.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from ..config import Config
from ..stages.grow import fit_models, planar_regions, plane_angle
from ..stages.rangeimage import labels_on_valid
from .recover import fit_plane, plane_height, plane_pieces

#: Erosions (3x3) of a region that leave its interior (Notes 1).
INTERIOR = 2

#: A border pixel's mean residual over its 3x3 window is a face's above this many
#: ``s / sqrt(k)`` (Notes 2).
SIGNIFICANCE = 2.5

#: Smallest group of candidates cut into pieces, and smallest piece (pixels).
SEED_PIXELS = 8

#: A candidate pixel fits a consensus plane within ``2 * PIECE_FACTOR`` times the
#: fit-test level (Notes 2).
PIECE_FACTOR = 0.7

#: Interior pixels farther than this many fit-test levels from its first plane are
#: outliers (the first pixels of an absorbed face); the plane is fitted again without them.
OUTLIER_FACTOR = 2.0

#: A region whose interior has fewer inliers than this share is not a plane (Notes 1).
INLIER_SHARE = 0.9

#: Pixels round a group's box in which its consensus planes are found.
PIECE_PAD = 4

_SQUARE = np.ones((3, 3), dtype=bool)


def _box(where: tuple[slice, slice], shape: tuple[int, ...]) -> tuple[slice, slice]:
    """``where`` grown by one pixel on every side, within ``shape``."""
    rows, cols = where
    return (slice(max(rows.start - 1, 0), min(rows.stop + 1, shape[0])),
            slice(max(cols.start - 1, 0), min(cols.stop + 1, shape[1])))


def _planar_fit(z: np.ndarray, mask: np.ndarray, config: Config, level: float
                ) -> tuple[np.ndarray, float] | None:
    """The interior's plane, fitted again without its outliers, and its RMS error (Notes 1).

    Plane (a0, a1, a2) of ``z = a0 + a1 col + a2 row``
    (:func:`~rangeseg_cli.stages.grow.fit_models`);
    None when the interior is curved.
    """
    [(first, _)], _ = fit_models(z, mask.astype(np.int32), 1, (1,))
    rows, cols = np.nonzero(mask)
    off = np.abs(z[rows, cols] - plane_height(first[1], rows, cols)) > OUTLIER_FACTOR * level
    if np.count_nonzero(~off) < INLIER_SHARE * rows.size:
        return None
    inliers = mask.astype(np.int32)
    inliers[rows[off], cols[off]] = 0
    [(_, mse_quad), (plane, mse_plane)], counts = fit_models(z, inliers, 1, (2, 1))
    flat = planar_regions(mse_quad, mse_plane, counts, config.grow)
    return (plane[1, :3], math.sqrt(float(mse_plane[1]))) if bool(flat[1]) else None


def _candidates(z: np.ndarray, region: np.ndarray, interior: np.ndarray, plane: np.ndarray,
                s: float) -> np.ndarray:
    """Border pixels whose 3x3 mean residual is significant (Notes 2): bool like ``region``.

    Summed over the border pixels' windows only (a region can fill a frame).
    """
    rows, cols = np.nonzero(region & ~interior)
    inside, heights = np.pad(region, 1), np.pad(z, 1)
    count, total = np.zeros(rows.size), np.zeros(rows.size)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            r, c = rows + dr, cols + dc
            there = inside[r + 1, c + 1]
            count += there
            total += np.where(there, heights[r + 1, c + 1] - plane_height(plane, r, c), 0.0)
    mean = total / np.maximum(count, 1.0)
    significant = np.abs(mean) * np.sqrt(count) > SIGNIFICANCE * s
    out = np.zeros(region.shape, dtype=bool)
    out[rows[significant], cols[significant]] = True
    return out


def _extended(z: np.ndarray, piece: np.ndarray, free: np.ndarray, region_plane: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """The piece after one pass of extension into ``free`` pixels, and its plane (Notes 3)."""
    rows, cols = np.nonzero(piece)
    plane = fit_plane(z, rows, cols)
    box = (slice(max(rows.min() - 1, 0), rows.max() + 2),
           slice(max(cols.min() - 1, 0), cols.max() + 2))
    ring = ndimage.binary_dilation(piece[box], _SQUARE) & free[box] & ~piece[box]
    rr, rc = np.nonzero(ring)
    rr, rc = rr + box[0].start, rc + box[1].start
    own = (z[rr, rc] - plane_height(plane, rr, rc)) ** 2
    theirs = (z[rr, rc] - plane_height(region_plane, rr, rc)) ** 2
    face = piece.copy()
    face[rr[own < theirs], rc[own < theirs]] = True
    rows, cols = np.nonzero(face[box])
    rows, cols = rows + box[0].start, cols + box[1].start
    return face, fit_plane(z, rows, cols)


def _pieces(z: np.ndarray, groups: np.ndarray, g: int, where: tuple[slice, slice],
            level: float) -> list[np.ndarray]:
    """Group ``g``'s planes by consensus (Notes 2), as masks of the whole of ``groups``.

    The consensus runs on the group's box grown by ``PIECE_PAD`` (the local
    planes of the hypotheses see only the group's pixels, so the box gives
    the same pieces as the region's whole frame, faster).
    """
    box = tuple(slice(max(s.start - PIECE_PAD, 0), s.stop + PIECE_PAD) for s in where)
    pieces = []
    for part in plane_pieces(z[box], groups[box] == g, level=level, min_pixels=SEED_PIXELS):
        whole = np.zeros(groups.shape, dtype=bool)
        whole[box] = part
        pieces.append(whole)
    return pieces


def _faces_of(z: np.ndarray, region: np.ndarray, config: Config, s: float) -> list[np.ndarray]:
    """The faces carved out of one region (Notes), bool masks like ``region``."""
    minimum = config.link.min_component
    if np.count_nonzero(region) < 4 * minimum:
        return []
    interior = ndimage.minimum_filter(region.view(np.uint8), size=2 * INTERIOR + 1,
                                      mode="constant").view(bool)  # INTERIOR 3x3 erosions
    if np.count_nonzero(interior) < 2 * minimum:
        return []
    fit = _planar_fit(z, interior, config, config.split.fit_factor * s)
    if fit is None:
        return []
    plane, rms = fit
    s = max(s, rms)  # a real surface that a plane fits less well than the noise: its error
    level = config.split.fit_factor * s
    groups, count = ndimage.label(_candidates(z, region, interior, plane, s), _SQUARE)
    sizes = np.bincount(groups.ravel(), minlength=count + 1)
    faces: list[np.ndarray] = []
    free = region.copy()
    for g, where in enumerate(ndimage.find_objects(groups), start=1):
        if where is None or sizes[g] < SEED_PIXELS:
            continue
        for piece in _pieces(z, groups, g, where, PIECE_FACTOR * level):
            piece &= free  # an earlier face's extension may have taken some of it
            if np.count_nonzero(piece) < SEED_PIXELS:
                continue
            face, own = _extended(z, piece, free, plane)
            rows, cols = np.nonzero(face)
            rms = math.sqrt(float(np.mean((z[rows, cols] - plane_height(own, rows, cols)) ** 2)))
            if (rows.size >= minimum and rms <= level
                    and plane_angle(own, plane) >= config.split.min_crease):
                faces.append(face)
                free &= ~face
    return faces


def carve_faces(z: np.ndarray, labels: np.ndarray, config: Config, *, noise: float
                ) -> np.ndarray:
    """Give narrow faces grown into a planar region's border regions of their own (Notes).

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
        int32 (H, W): ``labels`` with the carved faces numbered n+1, n+2, ...

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z, out = labels_on_valid(z, labels)
    sigma = 0.0 if math.isnan(noise) else noise
    s = math.sqrt(max(sigma * sigma, config.grow.min_error))
    known = np.nan_to_num(z)
    next_id = int(out.max(initial=0)) + 1
    for k, where in enumerate(ndimage.find_objects(out), start=1):
        if where is None:
            continue
        box = _box(where, out.shape)
        region = out[box] == k
        for face in _faces_of(known[box], region, config, s):
            out[box][face & region] = next_id
            next_id += 1
    return out.astype(np.int32, copy=False)
