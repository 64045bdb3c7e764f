"""Recover narrow faces from the unlabelled band after region growing.

Beyond Al-Hujazi & Sood (1990). Region growing (Sec. V-4) only extends the
components of step 3 (Sec. V-3), and a face 2-4 pixels wide -- a side of a
tilted box seen at a grazing angle, a cup's rim, a chamfer, the wall of a
hole -- has no component: every pixel of it is a step or roof edge pixel
(the thick contours of Sec. V-1, V-2 and the 17-tap roof mask leave no 20
pixels inside it). The paper lists such faces among what was "not
classified" (Figs. 11-13) and its conclusion (Sec. VIII) asks for a test of
the quality of the fits. This module gives such a band its own region when
one plane fits it to the noise and no neighbouring surface does.

Notes
-----
1. Seeds. A valid pixel still labelled 0 is the boundary of a neighbour when
   a region within ``REACH`` pixels (chessboard) predicts it as region
   growing would accept it: squared residual below ``grow.error_factor *
   e_A`` of that region (Sec. V-4). The other label-0 pixels fall into
   8-connected groups (8, so that a diagonal band one pixel thick stays in
   one piece).
2. Planes. Groups of at least half ``link.min_component`` pixels are
   candidates. A group whose least-squares plane has an RMS error within the
   fit test of the split (``split.fit_factor * max(noise,
   sqrt(grow.min_error))``, Sec. VIII) is a face. A group that fails -- two
   narrow faces meeting at a corner, a band and the pixels across a step --
   is cut into planes by consensus (:func:`plane_pieces`): every pixel's
   local plane (:func:`~rangeseg_cli.refine.planes.local_planes`) is a hypothesis,
   the one that most pixels fit within twice that level wins and is refitted
   to them, its connected part becomes a piece, and the rest is cut again.
   Faces whose pixels some existing region's surface fits (the table seen
   through a hole, say) are dropped: they are not new surfaces.
3. Extension. In ``split.recover_passes`` simultaneous passes, a pixel of
   the band (no component of step 3) next to exactly one face joins it when
   its squared residual to the face's plane is below ``grow.error_factor *
   e_A`` of the face (Sec. V-4) and below its residual to the region it
   belongs to (if any): growing gave the band's pixels to whichever
   neighbour fitted within tolerance, and a narrow face's pixels often fit
   the neighbour across the crease too. Pixels of components are never
   taken.
4. Acceptance. Faces within two pixels of each other that one plane fits
   are merged. A face is kept when it has ``link.min_component`` pixels or
   more, its plane passes the fit test, and it is not a fragment of a
   surface that neighbouring regions swallowed: the pixels of other regions
   within ``PARTIAL_REACH`` of it that its plane predicts better than their
   own surface number less than ``PARTIAL_FRACTION`` of its size. Pixels of
   faces not kept get their labels back.
5. Noise. Above ``split.recover_max_noise`` depth units of estimated noise
   (:func:`~rangeseg_cli.stages.noise.estimate_noise`) nothing is recovered. At
   noise sigma 2 a band 2-4 pixels wide comes out as a face whose boundary
   is a pixel off; the boundary refinement of :mod:`rangeseg_cli.refine.boundaries`
   puts it back, so recovery gains correct detections at sigma 2 (the
   synthetic scenes were measured up to sigma 2, estimate 2.0; without the
   refinement such faces only added regions: ``docs/quality.md``).

New regions are numbered after the existing ones, in raster order of their
first pixel; existing labels keep their ids. Everything is a function of
``z``, the components and the grown labels, so the ``grow`` stage stays a
pure function of (z, edges, components, config).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..config import Config
from ..kernels.backend import Backend, select_deferred, select_kernels
from ..kernels.parallel import map_tasks
from ..stages.grow import (
    EIGHT_NEIGHBOURS,
    RCOND,
    evaluate_quadric,
    fit_quadrics,
    single_neighbour_label_at,
)
from ..stages.noise import estimate_noise
from ..stages.rangeimage import require_shape_of_z
from .planes import local_planes, min_det, writeable_weights
from .regions import adjacent_pairs, c_array, join_box

#: Chessboard reach (pixels) of the neighbours a label-0 pixel may be the boundary of.
REACH = 2

#: Chessboard reach (pixels) around a face within which swallowed pixels are counted.
PARTIAL_REACH = 3

#: A face whose plane predicts this fraction of its size in pixels of neighbouring
#: regions better than their own surfaces is a fragment, and is dropped.
PARTIAL_FRACTION = 0.2

#: Faces this close (chessboard, pixels) that one plane fits are merged.
MERGE_REACH = 2

#: A pixel fits a consensus plane within this many times the fit-test level.
INLIER_FACTOR = 2.0

#: Gaussian sigma (pixels) of the local planes that are the consensus hypotheses.
HYPOTHESIS_SIGMA = 1.0

#: Most hypotheses tried per piece, and most pieces cut from one group.
MAX_HYPOTHESES, MAX_PIECES = 128, 3

#: Groups with more pixels that fail the plane test are not cut (a bound on the work).
MAX_GROUP = 4000



@dataclass(frozen=True)
class _Fits:
    """Surfaces of the labels 1..n: coefficients and the growing bound (Sec. V-4).

    Attributes
    ----------
    coeffs
        float64 (n+1, 6) image-coordinate coefficients (quadric or plane).
    limit
        float64 (n+1,) ``error_factor * max(mse, min_error)``: the largest
        squared residual region growing accepts.
    mse
        float64 (n+1,) mean squared residual of each fit.
    counts
        int64 (n+1,) pixels fitted.
    """

    coeffs: np.ndarray
    limit: np.ndarray
    mse: np.ndarray
    counts: np.ndarray

    @classmethod
    def of(cls, z: np.ndarray, labels: np.ndarray, n: int, config: Config, order: int
           ) -> _Fits:
        """Fit every label 1..n of ``labels`` at ``order`` (2 quadric, 1 plane)."""
        coeffs, mse, counts = fit_quadrics(z, labels, n, order=order)
        limit = config.grow.error_factor * np.maximum(mse, config.grow.min_error)
        return cls(coeffs=coeffs, limit=limit, mse=mse, counts=counts)


def _squared_residuals(z: np.ndarray, coeffs: np.ndarray, ids: np.ndarray, rows: np.ndarray,
                       cols: np.ndarray) -> np.ndarray:
    """Squared residuals of pixels (rows, cols) to the surfaces ``coeffs[ids]``."""
    r = z[rows, cols] - evaluate_quadric(coeffs[ids], rows, cols)
    return r * r


def fits_a_neighbour(z: np.ndarray, labels: np.ndarray, coeffs: np.ndarray, limit: np.ndarray,
                     rows: np.ndarray, cols: np.ndarray, reach: int = REACH, *,
                     backend: Backend = "auto") -> np.ndarray:
    """Whether a region within ``reach`` of each pixel would accept it (Sec. V-4).

    Parameters
    ----------
    z
        float64 (H, W) heights.
    labels
        int (H, W) regions 1..n, 0 = none.
    coeffs, limit
        float64 (n+1, 6) and (n+1,): the regions' surfaces and growing bounds.
    rows, cols
        (N,) the pixels.
    reach
        Chessboard distance to look for regions.
    backend
        ``"numpy"``: the reference, offset by offset; ``"numba"``:
        :func:`rangeseg_cli.kernels.compiled.neighbour_accepts`, pixel by
        pixel (the same answer); ``"auto"``: numba when installed and the
        kernel compiled (:func:`~rangeseg_cli.kernels.cache.ready`).

    Returns
    -------
    numpy.ndarray
        bool (N,): some region with a pixel within ``reach`` predicts the
        pixel with a squared residual below its ``limit``.
    """
    kernels = select_deferred(backend, "neighbour_accepts")
    if kernels is not None:
        return np.asarray(kernels.neighbour_accepts(
            c_array(z, np.float64), c_array(labels, np.int32), c_array(coeffs, np.float64),
            c_array(limit, np.float64), c_array(rows, np.int64), c_array(cols, np.int64),
            reach))
    h, w = labels.shape
    out = np.zeros(rows.size, bool)
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            r, c = rows + dr, cols + dc
            inside = np.flatnonzero((r >= 0) & (r < h) & (c >= 0) & (c < w) & ~out)
            ids = labels[r[inside], c[inside]]
            near = ids > 0
            at, ids = inside[near], ids[near]
            res = _squared_residuals(z, coeffs, ids, rows[at], cols[at])
            out[at[res < limit[ids]]] = True
    return out


def fit_plane(z: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Least-squares plane (a0, a1, a2) of ``z = a0 + a1 col + a2 row`` through pixels.

    From the 3x3 normal equations in centred coordinates (:func:`plane_sums`,
    :func:`solve_plane`) when they are well-conditioned (the consensus refits
    planes thousands of times per frame); pixels on a line get the
    minimum-norm solution (``lstsq``). The compiled consensus
    (:func:`rangeseg_cli.kernels.compiled.consensus_plane`) makes the same
    sums and solve, so the same bits.
    """
    cr, cc = rows.sum(dtype=np.float64) / rows.size, cols.sum(dtype=np.float64) / cols.size
    du, dv, zs = cols - cc, rows - cr, z[rows, cols]
    plane = solve_plane(float(rows.size), plane_sums(du, dv, zs), cr, cc)
    if plane is not None:
        return plane
    a = np.column_stack([np.ones(rows.size), du, dv])  # pixels on a line: the minimum norm
    gram = a.T @ a
    if _conditioned(gram):
        coef = np.linalg.solve(gram, a.T @ zs)
    else:
        coef = np.linalg.lstsq(a, zs, rcond=None)[0]
    return np.array([coef[0] - coef[1] * cc - coef[2] * cr, coef[1], coef[2]])


def plane_sums(du: np.ndarray, dv: np.ndarray, zs: np.ndarray) -> list[float]:
    """Sums of u, v, uu, uv, vv, z, uz and vz over the pixels, one after another.

    Summed in the pixels' order (``cumsum``), as a loop sums them, so that a
    compiled loop gets the same bits (:func:`fit_plane`).
    """
    terms = np.stack([du, dv, du * du, du * dv, dv * dv, zs, du * zs, dv * zs])
    return np.cumsum(terms, axis=1)[:, -1].tolist()  # type: ignore[no-any-return]


def solve_plane(n: float, sums: list[float], cr: float, cc: float) -> np.ndarray | None:
    """The plane of :func:`fit_plane` by Cramer's rule; None unless clearly conditioned.

    ``sums`` are :func:`plane_sums` (su, sv, suu, suv, svv, sz, suz, svz) of
    ``n`` pixels centred on (cr, cc). The Gram matrix ``[[n, su, sv], [su,
    suu, suv], [sv, suv, svv]]`` is clearly conditioned when its determinant
    exceeds ``100 RCOND t^3`` (``t`` its trace): its largest eigenvalue is at
    most ``t`` and its smallest at least ``det / t^2``, so their ratio is a
    hundred times above RCOND (the region fits' test). Scalar float64
    operations, in the order of the compiled twin.
    """
    su, sv, suu, suv, svv, sz, suz, svz = sums
    m_uu = suu * svv - suv * suv
    det = n * m_uu - su * (su * svv - sv * suv) + sv * (su * suv - sv * suu)
    t = n + suu + svv
    if not det > 100.0 * RCOND * t * t * t:
        return None
    a0 = (sz * m_uu - su * (suz * svv - suv * svz) + sv * (suz * suv - suu * svz)) / det
    a1 = (n * (suz * svv - suv * svz) - sz * (su * svv - suv * sv) + sv * (su * svz - suz * sv)
          ) / det
    a2 = (n * (suu * svz - suz * suv) - su * (su * svz - suz * sv) + sz * (su * suv - suu * sv)
          ) / det
    return np.array([a0 - a1 * cc - a2 * cr, a1, a2])


def _conditioned(gram: np.ndarray) -> bool:
    """The region fits' test: smallest / largest eigenvalue of ``gram`` above RCOND."""
    eig = np.linalg.eigvalsh(gram)
    return bool(eig[0] > RCOND * eig[-1])


def plane_height(plane: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Heights of the plane (a0, a1, a2) of ``z = a0 + a1 col + a2 row`` (:func:`fit_plane`)."""
    return plane[0] + plane[1] * cols + plane[2] * rows


def plane_pieces(z: np.ndarray, mask: np.ndarray, *, level: float, min_pixels: int,
                 found: tuple[np.ndarray | None] | None = None) -> list[np.ndarray]:
    """Cut the pixels of ``mask`` into planes by consensus (Notes, step 2).

    Parameters
    ----------
    z
        float64 (h, w) heights (usually the group's bounding box).
    mask
        bool (h, w) the group's pixels.
    level
        RMS error of the fit test, depth units; a pixel fits a plane within
        ``INLIER_FACTOR * level``.
    min_pixels
        Smallest piece kept.
    found
        The first consensus plane's pixels, ``consensus_plane(z, mask,
        INLIER_FACTOR * level)``, in a 1-tuple when the caller has already
        found it (None inside: there is none); None: found here.

    Returns
    -------
    list of numpy.ndarray
        bool (h, w) pieces, disjoint, each 8-connected, at most ``MAX_PIECES``.
        Deterministic: hypotheses are taken in raster order, ties go to the first.
    """
    left = mask.copy()
    pieces: list[np.ndarray] = []
    tol = INLIER_FACTOR * level
    for i in range(MAX_PIECES):
        if np.count_nonzero(left) < min_pixels:
            break
        piece = found[0] if i == 0 and found is not None else consensus_plane(z, left, tol)
        if piece is None:
            break
        left &= ~piece
        if np.count_nonzero(piece) >= min_pixels:
            pieces.append(piece)
    return pieces


def _votes_of(zs: np.ndarray, rows: np.ndarray, cols: np.ndarray, height: np.ndarray,
              gx: np.ndarray, gy: np.ndarray, hr: np.ndarray, hc: np.ndarray, tol: float
              ) -> np.ndarray:
    """The pixels each hypothesis plane fits within ``tol``: bool (..., pixels) (numpy)."""
    pred = (np.asarray(height)[..., None]
            + np.asarray(gx)[..., None] * (cols - np.asarray(hc)[..., None])
            + np.asarray(gy)[..., None] * (rows - np.asarray(hr)[..., None]))
    return np.abs(zs - pred) < tol


#: Hypotheses voted on at once by the numpy reference (:func:`_votes`): a bound on
#: its temporaries (hypotheses x pixels).
VOTE_CHUNK = 16


def _votes(zs: np.ndarray, rows: np.ndarray, cols: np.ndarray, height: np.ndarray,
           gx: np.ndarray, gy: np.ndarray, hr: np.ndarray, hc: np.ndarray, tol: float
           ) -> np.ndarray:
    """How many pixels each hypothesis plane fits within ``tol``: int (hypotheses,)."""
    return np.concatenate([
        _votes_of(zs, rows, cols, height[k:k + VOTE_CHUNK], gx[k:k + VOTE_CHUNK],
                  gy[k:k + VOTE_CHUNK], hr[k:k + VOTE_CHUNK], hc[k:k + VOTE_CHUNK],
                  tol).sum(axis=1)
        for k in range(0, hr.size, VOTE_CHUNK)])


def consensus_plane(z: np.ndarray, left: np.ndarray, tol: float, *, backend: Backend = "auto"
                    ) -> np.ndarray | None:
    """The connected inliers of the local plane most pixels of ``left`` fit; None if none.

    Every pixel's local plane (:data:`HYPOTHESIS_SIGMA`) is a hypothesis (at most
    :data:`MAX_HYPOTHESES`, in raster order); the one most pixels fit within ``tol`` wins,
    is refitted twice to its inliers, and the connected part (8-neighbours) of the
    inliers holding the winning pixel is returned (bool, ``left``'s shape).
    ``backend``: this numpy reference or, once compiled
    (:func:`~rangeseg_cli.kernels.backend.select_deferred`),
    :func:`rangeseg_cli.kernels.compiled.consensus_plane` in one call (the
    same pixels).
    """
    kernels = select_deferred(backend, "consensus_plane")
    if kernels is not None:
        h, w = left.shape
        found, status = kernels.consensus_plane(
            c_array(z, np.float64), c_array(left, np.bool_), writeable_weights(HYPOTHESIS_SIGMA),
            -w / 2.0, -h / 2.0, min_det(HYPOTHESIS_SIGMA), MAX_HYPOTHESES, float(tol))
        if status != 2:  # 2: a refit's pixels nearly on a line, left to the reference
            return found if status == 1 else None
    # the reference, numpy throughout under "auto" (the kernel is not compiled yet)
    rows, cols = np.nonzero(left)
    height, gx, gy = local_planes(z, left, HYPOTHESIS_SIGMA,
                                  backend="numpy" if backend == "auto" else backend)
    hyp = np.flatnonzero(np.isfinite(gx[rows, cols]))
    if hyp.size == 0:
        return None
    hyp = hyp[:: -(-hyp.size // MAX_HYPOTHESES)]
    hr, hc = rows[hyp], cols[hyp]
    zs = z[rows, cols]
    best = int(np.argmax(_votes(zs, rows, cols, height[hr, hc], gx[hr, hc],
                                gy[hr, hc], hr, hc, tol)))
    inliers = _votes_of(zs, rows, cols, height[hr[best], hc[best]],
                        gx[hr[best], hc[best]], gy[hr[best], hc[best]], hr[best], hc[best], tol)
    for _ in range(2):  # refit to the inliers
        if not inliers.any():  # no hypothesis won a single vote (e.g. NaN-ridden bands)
            return None
        a = fit_plane(z, rows[inliers], cols[inliers])
        inliers = np.abs(zs - plane_height(a, rows, cols)) < tol
    if not inliers.any():
        return None
    found = np.zeros(left.shape, bool)
    found[rows[inliers], cols[inliers]] = True
    parts, _ = ndimage.label(found, structure=EIGHT_NEIGHBOURS)
    seed = parts[hr[best], hc[best]]
    if seed == 0:
        seed = int(np.argmax(np.bincount(parts.ravel())[1:])) + 1
    return parts == seed


def _seed_faces(z: np.ndarray, labels: np.ndarray, fits: _Fits, config: Config, *,
                level: float, min_seed: int) -> np.ndarray:
    """Faces 1..k from the label-0 pixels no neighbour accepts (Notes, steps 1-2)."""
    rows, cols = np.nonzero(np.isfinite(z) & (labels == 0))
    free = np.zeros(labels.shape, bool)
    free[rows, cols] = ~fits_a_neighbour(z, labels, fits.coeffs, fits.limit, rows, cols)
    groups, k = ndimage.label(free, structure=EIGHT_NEIGHBOURS)
    faces = np.zeros(labels.shape, np.int32)
    if k == 0:
        return faces
    planes = _Fits.of(z, groups, k, config, order=1)
    boxes = ndimage.find_objects(groups)
    seeds = [g for g in np.flatnonzero(planes.counts >= min_seed).tolist()
             if g > 0 and (planes.mse[g] <= level * level or planes.counts[g] <= MAX_GROUP)]
    cut = [g for g in seeds if planes.mse[g] > level * level]

    def pieces_of(g: int) -> list[np.ndarray]:
        return plane_pieces(z[boxes[g - 1]], groups[boxes[g - 1]] == g, level=level,
                            min_pixels=min_seed)

    # The groups are independent: many with enough pixels go to processes
    # (parallel.map_tasks' cost, in pixels as for the other passes).
    found = dict(zip(cut, map_tasks(pieces_of, cut, cost=[float(planes.counts[g]) for g in cut]),
                     strict=True))
    count = 0
    for g in seeds:
        box = boxes[g - 1]
        for piece in found[g] if g in found else [groups[box] == g]:
            count += 1
            faces[box][piece] = count
    return faces


def _drop_explained(z: np.ndarray, faces: np.ndarray, fits: _Fits, *,
                    backend: Backend = "auto") -> np.ndarray:
    """Faces, renumbered, without those whose pixels an existing region's surface fits.

    A face is explained when, for some region, the mean squared residual of
    the face's pixels to the region's surface is below the region's growing
    bound (Sec. V-4). ``backend``: numpy calls per region (the reference) or
    :func:`rangeseg_cli.kernels.compiled.explained_faces` (the same faces), as
    :func:`~rangeseg_cli.kernels.backend.select_kernels` chooses.
    """
    k = int(faces.max(initial=0))
    rows, cols = np.nonzero(faces)
    ids = faces[rows, cols]
    regions = np.flatnonzero(fits.counts > 0)
    kernels = select_kernels(backend)
    if kernels is not None:
        explained = kernels.explained_faces(
            np.require(z, np.float64, ["C"]), rows, cols, ids.astype(np.int64), k,
            np.ascontiguousarray(fits.coeffs, np.float64),
            np.ascontiguousarray(fits.limit, np.float64), regions.astype(np.int64))
    else:
        size = np.maximum(np.bincount(ids, minlength=k + 1), 1)
        explained = np.zeros(k + 1, bool)
        for region in regions.tolist():
            res = _squared_residuals(z, fits.coeffs, np.full(rows.size, region), rows, cols)
            explained |= np.bincount(ids, res, minlength=k + 1) / size < fits.limit[region]
    keep = ~explained
    keep[0] = False
    keep &= np.bincount(ids, minlength=k + 1) > 0
    lut = np.zeros(k + 1, np.int32)
    lut[keep] = np.arange(1, int(keep.sum()) + 1, dtype=np.int32)
    return lut[faces]


def _extend(z: np.ndarray, band: np.ndarray, labels: np.ndarray, faces: np.ndarray,
            fits: _Fits, passes: int, config: Config) -> np.ndarray:
    """Let the faces take band pixels they fit better than their region (Notes, step 3)."""
    faces = faces.copy()
    k = int(faces.max(initial=0))
    for _ in range(passes):
        planes = _Fits.of(z, faces, k, config, order=1)
        rows, cols = np.nonzero(band & (faces == 0))
        f = single_neighbour_label_at(faces, rows, cols)
        rows, cols, f = rows[f > 0], cols[f > 0], f[f > 0]
        if rows.size == 0:
            break
        res = _squared_residuals(z, planes.coeffs, f, rows, cols)
        own = labels[rows, cols]
        mine = np.full(rows.size, np.inf)
        has = own > 0
        mine[has] = _squared_residuals(z, fits.coeffs, own[has], rows[has], cols[has])
        join = (res < planes.limit[f]) & (res < mine)
        if not join.any():
            break
        faces[rows[join], cols[join]] = f[join]
    return faces


def _merge_coplanar(z: np.ndarray, faces: np.ndarray, level: float) -> np.ndarray:
    """Merge faces within ``MERGE_REACH`` whose union one plane fits within ``level``."""
    k = int(faces.max(initial=0))
    if k < 2:
        return faces
    root = np.arange(k + 1)
    boxes = dict(enumerate(ndimage.find_objects(faces), start=1))  # of each root's group
    for i, j in adjacent_pairs(faces, MERGE_REACH):
        a, b = root[i], root[j]
        if a == b:
            continue
        box = join_box(boxes[a], boxes[b])
        sub = root[faces[box]]
        rows, cols = np.nonzero((sub == a) | (sub == b))  # raster order, as in the frame
        rows, cols = rows + box[0].start, cols + box[1].start
        plane = fit_plane(z, rows, cols)
        r = z[rows, cols] - plane_height(plane, rows, cols)
        if float(np.mean(r * r)) <= level * level:
            root[root == max(a, b)] = min(a, b)
            boxes[min(a, b)] = box
    return root.astype(np.int32)[faces]


def _swallowed(z: np.ndarray, faces: np.ndarray, f: int, where: tuple[slice, slice],
               others: np.ndarray, plane: np.ndarray, limit: float, fits: _Fits) -> int:
    """Pixels of other regions near face ``f`` (box ``where``) its plane predicts better."""
    box = tuple(slice(max(s.start - PARTIAL_REACH, 0), s.stop + PARTIAL_REACH) for s in where)
    near = ndimage.binary_dilation(faces[box] == f, EIGHT_NEIGHBOURS, iterations=PARTIAL_REACH)
    rows, cols = np.nonzero(near & (others[box] > 0))
    rows, cols = rows + box[0].start, cols + box[1].start
    ids = others[rows, cols]
    res = _squared_residuals(z, plane[None, :], np.zeros(rows.size, np.intp), rows, cols)
    own = _squared_residuals(z, fits.coeffs, ids, rows, cols)
    return int(np.count_nonzero((res < limit) & (res < own)))


def _accepted(z: np.ndarray, faces: np.ndarray, labels: np.ndarray, fits: _Fits, *,
              level: float, config: Config) -> np.ndarray:
    """Ids of the faces kept (Notes, step 4): big enough, planar, not a swallowed fragment."""
    k = int(faces.max(initial=0))
    planes = _Fits.of(z, faces, k, config, order=1)
    ok = (planes.counts >= config.link.min_component) & (planes.mse <= level * level)
    ok[0] = False
    others = np.where(faces > 0, 0, labels)
    boxes = ndimage.find_objects(faces)
    for f in np.flatnonzero(ok).tolist():
        swallowed = _swallowed(z, faces, f, boxes[f - 1], others, planes.coeffs[f],
                               float(planes.limit[f]), fits)
        ok[f] = swallowed < PARTIAL_FRACTION * planes.counts[f]
    return np.flatnonzero(ok)


def _raster_ids(faces: np.ndarray, kept: np.ndarray, first_id: int) -> np.ndarray:
    """Map face ids to ``first_id``, ``first_id + 1``, ... in raster order of their first pixel."""
    ids, first = np.unique(faces.ravel(), return_index=True)
    chosen = np.isin(ids, kept)
    order = ids[chosen][np.argsort(first[chosen], kind="stable")]
    lut = np.zeros(int(faces.max(initial=0)) + 1, np.int32)
    lut[order] = np.arange(first_id, first_id + order.size, dtype=np.int32)
    return lut


def recover_faces(z: np.ndarray, components: np.ndarray, labels: np.ndarray, config: Config,
                  *, noise: float | None = None) -> np.ndarray:
    """Give narrow faces in the unlabelled band regions of their own (beyond Sec. V-4, VIII).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    components
        int (H, W) components of step 3 (Sec. V-3); their pixels are never
        taken from their regions.
    labels
        int32 (H, W) regions after growing (and splitting), 0 = none.
    config
        Uses ``config.split`` (``fit_factor``, ``recover_passes``,
        ``recover_max_noise``), ``[grow]`` (``error_factor``, ``min_error``)
        and ``link.min_component``.
    noise
        Noise sigma of ``z`` (:func:`~rangeseg_cli.stages.noise.estimate_noise`);
        estimated when None.

    Returns
    -------
    numpy.ndarray
        int32 (H, W): ``labels`` with the recovered faces numbered n+1, n+2,
        ... (n = ``labels.max()``) in raster order of their first pixel;
        ``labels`` itself (the same object) when nothing is recovered.

    Raises
    ------
    ValueError
        When the shapes of ``z``, ``components`` and ``labels`` differ.
    """
    z = np.asarray(z, dtype=np.float64)
    require_shape_of_z(z, components=components, labels=labels)
    n = int(np.max(labels, initial=0))
    noise = estimate_noise(z) if noise is None else noise
    if n == 0 or noise > config.split.recover_max_noise:
        return labels
    level = config.split.fit_factor * max(noise, math.sqrt(config.grow.min_error))
    current = np.where(np.isfinite(z), labels, 0).astype(np.int32)
    fits = _Fits.of(z, current, n, config, order=2)
    # Steps 1-2: seeds and their planes
    faces = _seed_faces(z, current, fits, config, level=level,
                        min_seed=max(config.link.min_component // 2, 3))
    faces = _drop_explained(z, faces, fits)
    if faces.max(initial=0) == 0:
        return labels
    # Step 3: extension into the band
    band = np.isfinite(z) & (np.asarray(components) == 0)
    faces = _extend(z, band, current, faces, fits, config.split.recover_passes, config)
    # Step 4: merging and acceptance
    faces = _merge_coplanar(z, faces, level)
    kept = _accepted(z, faces, current, fits, level=level, config=config)
    if kept.size == 0:
        return labels
    new = _raster_ids(faces, kept, n + 1)[faces]
    return np.where(new > 0, new, current).astype(np.int32)
