"""The workspace: which pixels a gripper may pick (beyond Al-Hujazi & Sood 1990, Sec. VII).

The paper takes the highest surface of the scene (Sec. VII). In a real cell
the highest things in view are often not to be picked: the robot's own
fingers, a tote's wall or rim, things outside the tote; and an empty tote
still has a highest surface. This module says, per pixel, what may be
picked; :mod:`rangeseg_cli.stages.holdsite` searches only there.

Notes
-----
1. Support (``[workspace] support``): the table or tote floor is the
   dominant plane of the background frame when there is one (the empty
   scene shows all of it), else of the image, by consensus (RANSAC,
   Fischler & Bolles 1981). Points are
   the camera-frame points ``d ((u - cx)/fx, (v - cy)/fy, 1)`` with camera
   intrinsics (a 3-D plane, whatever the camera's tilt), else ``(col s, row
   s, z)`` with ``s`` = ``[input] units_per_pixel`` (1 when unknown).
   :data:`HYPOTHESES` planes through three points of a fixed sample
   (:data:`SAMPLE`, seeded: the same image gives the same plane); a plane
   counts only when at most :data:`MAX_BELOW` of the points lie farther than
   the tolerance behind it (a plane through the items' tops has the floor
   behind it) and, with a camera, when it faces the camera within
   :data:`MAX_SUPPORT_TILT` degrees (a tote wall does not). The plane with
   the most points within the tolerance wins, refitted to them by least
   squares (twice). ``height`` is the signed distance from it, towards the
   camera (or up). Without a background frame, a plane holding under
   :data:`HIDDEN_SUPPORT` of the points is no support (a full tote hides its
   floor): the workspace is then the valid pixels of the region of interest,
   and the holdsite's reason asks for a background frame.
2. Tolerance: ``support_tolerance``, or by default ``max(4 sigma, 1 unit)``
   with ``sigma`` the image's noise (:func:`~rangeseg_cli.stages.noise.estimate_noise`),
   and with metric camera depth at least :data:`DEPTH_FRACTION` of the
   median depth (depth cameras err by about 0.5-1 % of the depth, more than
   their fine-grained noise shows; on the SR300 frames the tote floor's
   residuals from one plane have a 90th percentile of 3-7 mm at 0.65-0.8 m).
3. Pickable pixels: valid; inside the region of interest (mask, box,
   polygon); not within ``background_tolerance`` of the background frame nor
   behind it (Zeng et al., ICRA 2018, subtract the empty tote's frame the
   same way); higher than the tolerance (and ``min_height``) above the
   support, and no higher than ``max_height`` when set; standing over the
   support's extent (:func:`over_support`: things outside a tote stand over
   no floor of it), shrunk by :data:`INSET_MM` with a camera
   (:func:`hull_inset`: where a tote's floor meets its walls). Heights are the
   data's, median-filtered over 3x3 valid pixels (a region's fit would carry
   its errors into the workspace where growing joined a wall to the floor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull

from ..config import Config, InputConfig, WorkspaceConfig
from ..kernels.backend import Backend, select_deferred

#: Points of the consensus sample.
SAMPLE = 20000

#: Points of the sample each hypothesis is scored on (a random subset of it).
SCORED = 5000

#: Planes tried by the consensus.
HYPOTHESES = 256

#: Largest fraction of the points that may lie behind (below) the support.
MAX_BELOW = 0.15

#: Largest angle in degrees between the support's normal and the optical axis.
MAX_SUPPORT_TILT = 60.0

#: With metric camera depth, the tolerances are at least this fraction of the median depth.
DEPTH_FRACTION = 0.01

#: Pixels a background frame's nearest reading may stand in for a pixel it has none of.
BACKGROUND_REACH = 10

#: Millimetres the support's extent is shrunk by (:func:`hull_inset`).
INSET_MM = 12.0

#: Without a background frame, a plane found on the image that holds a smaller share of
#: the points is not taken for the support (module Notes, 1): the floor is mostly hidden
#: (a full tote) or unread, and the plane a guess. The SR300 frame of ``sample_data/arc``
#: reads 12 % (a plane 5 degrees and 14 mm off its empty tote's floor, which took one
#: item and a wall together out of the workspace); its empty tote 44 %, the ARC bin
#: frame 46 %, the synthetic camera cells 59-92 %.
HIDDEN_SUPPORT = 0.25

#: Pieces of the support of at least this fraction of the largest one make its extent: the
#: floor seen between heaped items (6-8 % on a synthetic full tote), not the specks at the
#: floor's level outside a bin (under 3 % on the ARC bin frame).
HULL_PIECE = 0.05

#: Noise levels of the default tolerances.
NOISE_LEVELS = 4.0


@dataclass(frozen=True)
class Plane:
    """A plane ``n . p + e = 0`` with ``n`` a unit normal; ``n . p + e`` > 0 towards the sensor."""

    normal: tuple[float, float, float]
    offset: float
    inliers: float

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed distances of (..., 3) points, positive towards the sensor."""
        n = np.asarray(self.normal)
        return points @ n + self.offset


@dataclass(frozen=True)
class Workspace:
    """What may be picked in one image.

    Attributes
    ----------
    pickable
        bool (H, W): pixels a gripper's window may lie on.
    height
        float64 (H, W) height above the support (depth units; NaN where
        unknown), or ``None`` without a support.
    support
        The support plane, or ``None`` (not searched, or none found).
    tolerance
        The support's height tolerance, depth units.
    extent
        bool (H, W): pixels inside the support's extent in the image (the
        convex hull of its large pieces), or ``None`` without a support.
    behind
        Share of the pixels both frames read that lie behind the background
        frame by more than its tolerance (0 without one): most of them, and
        the background is of another camera, pose or unit.
    hidden
        Without a background frame, the plane found on the image when it
        holds under :data:`HIDDEN_SUPPORT` of the points and so is not used
        as the support (``support`` is ``None``); else ``None``.
    """

    pickable: np.ndarray
    height: np.ndarray | None
    support: Plane | None
    tolerance: float
    extent: np.ndarray | None = None
    behind: float = 0.0
    hidden: Plane | None = None


def default_tolerance(z: np.ndarray, camera: InputConfig, noise: float) -> float:
    """``max(4 sigma, 1 unit)``, and with metric camera depth >= 1 % of the median depth."""
    tol = max(NOISE_LEVELS * max(noise, 0.0), 1.0)
    if camera.has_intrinsics and camera.metres_per_unit > 0:
        depth = -z[np.isfinite(z)]
        if depth.size:
            tol = max(tol, DEPTH_FRACTION * float(np.median(depth)))
    return tol


def points(z: np.ndarray, camera: InputConfig, rows: np.ndarray | None = None,
           cols: np.ndarray | None = None) -> np.ndarray:
    """(..., 3) points of heights ``z`` at ``rows, cols`` (module Notes, 1).

    Camera-frame points with intrinsics (depth ``d = -z``), else ``(col s,
    row s, z)`` with ``s`` = ``units_per_pixel`` (1 when unknown). Without
    ``rows``/``cols``, ``z`` is the whole image.
    """
    if rows is None or cols is None:
        grid = np.indices(z.shape, dtype=np.float64)
        rows, cols = grid[0], grid[1]
    if camera.has_intrinsics:
        d = -z
        return np.stack([(cols - camera.cx) * d / camera.fx,
                         (rows - camera.cy) * d / camera.fy, d], axis=-1)
    s = camera.units_per_pixel or 1.0
    return np.stack([cols * s, rows * s, z], axis=-1)


def _oriented(normals: np.ndarray, offsets: np.ndarray, camera: bool
              ) -> tuple[np.ndarray, np.ndarray]:
    """Normals and offsets turned so that the sensor's side is positive."""
    # camera frame: the camera (origin) is at distance e; height map: up is +z
    flip = offsets < 0 if camera else normals[:, 2] < 0
    sign = np.where(flip, -1.0, 1.0)
    return normals * sign[:, None], offsets * sign


def _hypotheses(sample: np.ndarray, rng: np.random.Generator, camera: bool
                ) -> tuple[np.ndarray, np.ndarray]:
    """:data:`HYPOTHESES` planes through three sample points each (unit normals, offsets)."""
    idx = rng.integers(0, sample.shape[0], size=(HYPOTHESES, 3))
    a, b, c = sample[idx[:, 0]], sample[idx[:, 1]], sample[idx[:, 2]]
    normals = np.cross(b - a, c - a)
    norm = np.linalg.norm(normals, axis=1)
    keep = norm > 0
    normals = normals[keep] / norm[keep, None]
    offsets = -np.einsum("ij,ij->i", normals, a[keep])
    return _oriented(normals, offsets, camera)


def _refit(sample: np.ndarray, normal: np.ndarray, offset: float, tol: float, camera: bool
           ) -> tuple[np.ndarray, float]:
    """The least-squares plane (total least squares) of the points within ``tol``."""
    near = sample[np.abs(sample @ normal + offset) <= tol]
    if near.shape[0] < 3:
        return normal, offset
    centre = near.mean(axis=0)
    _, _, vt = np.linalg.svd(near - centre, full_matrices=False)
    n = vt[2]
    normals, offsets = _oriented(n[None], np.array([-n @ centre]), camera)
    return normals[0], float(offsets[0])


def find_support(z: np.ndarray, camera: InputConfig, tol: float, *, seed: int = 0
                 ) -> Plane | None:
    """The support plane by consensus (module Notes, 1), or ``None``.

    Parameters
    ----------
    z
        float64 (H, W) heights (depth ``-z`` with intrinsics), NaN where invalid.
    camera
        ``[input]``: intrinsics, ``units_per_pixel``.
    tol
        Points within ``tol`` of a plane are on it (depth units).
    seed
        Seeds the sample and the hypotheses: the same image, the same plane.

    Returns
    -------
    Plane or None
        ``None`` when fewer than 3 % of the pixels (or 100) are valid, or no
        plane passes the tests.
    """
    valid = np.isfinite(z) & ((-z > 0) if camera.has_intrinsics else True)
    flat = np.flatnonzero(valid)  # row-major, as np.nonzero's rows and columns
    if flat.size < max(100, 0.03 * z.size):
        return None
    rng = np.random.default_rng(seed)
    pick = rng.choice(flat.size, size=min(SAMPLE, flat.size), replace=False)
    pick.sort()
    rows, cols = np.divmod(flat[pick], z.shape[1])
    sample = points(z[rows, cols], camera, rows.astype(np.float64), cols.astype(np.float64))
    normals, offsets = _hypotheses(sample, rng, camera.has_intrinsics)
    scored = sample[:: max(1, sample.shape[0] // SCORED)]  # spread over the image
    on, below = plane_shares(scored @ normals.T, offsets, tol)  # (points, planes) products
    ok = below <= MAX_BELOW
    if camera.has_intrinsics:
        ok &= np.degrees(np.arccos(np.clip(np.abs(normals[:, 2]), 0, 1))) <= MAX_SUPPORT_TILT
    if not ok.any():
        return None
    best = int(np.flatnonzero(ok)[np.argmax(on[ok])])
    normal, offset = normals[best], float(offsets[best])
    for _ in range(2):
        normal, offset = _refit(sample, normal, offset, tol, camera.has_intrinsics)
    share = float((np.abs(sample @ normal + offset) <= tol).mean())
    nx, ny, nz = (float(v) for v in normal)
    return Plane((nx, ny, nz), offset, share)


#: Points whose distances :func:`plane_shares` takes at once (they stay in the cache).
VOTE_ROWS = 256


def plane_shares(products: np.ndarray, offsets: np.ndarray, tol: float, *,
                 backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Shares of the points within ``tol`` of each plane and behind it by more than ``tol``.

    Parameters
    ----------
    products
        float64 (points, planes): ``n . p`` of each point and plane normal.
    offsets
        float64 (planes,): the planes' offsets (distances ``n . p + e``).
    tol
        Tolerance (depth units).
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` (the same values).

    Returns
    -------
    on, below : numpy.ndarray
        float64 (planes,): ``mean(|d| <= tol)`` and ``mean(d < -tol)`` over the
        points (the same bits: counts over the count). Counted
        :data:`VOTE_ROWS` points at a time, ``|d| <= tol`` as ``d <= tol``
        less ``d < -tol``; once compiled
        (:func:`~rangeseg_cli.kernels.backend.select_deferred`), by
        :func:`rangeseg_cli.kernels.compiled.plane_counts` (the same counts).
    """
    count, planes = products.shape
    kernels = select_deferred(backend, "plane_counts")
    if kernels is not None:
        upto, behind = kernels.plane_counts(np.require(products, np.float64, ["C"]),
                                            np.require(offsets, np.float64, ["C"]), float(tol))
        return (upto - behind) / count, behind / count
    upto = np.zeros(planes, dtype=np.int64)
    behind = np.zeros(planes, dtype=np.int64)
    dist = np.empty((min(VOTE_ROWS, count), planes))
    test = np.empty(dist.shape, dtype=bool)
    for start in range(0, count, VOTE_ROWS):
        k = min(VOTE_ROWS, count - start)
        d, t = dist[:k], test[:k]
        np.add(products[start:start + k], offsets, out=d)
        np.less(d, -tol, out=t)
        behind += t.view(np.uint8).sum(axis=0, dtype=np.int64)
        np.less_equal(d, tol, out=t)
        upto += t.view(np.uint8).sum(axis=0, dtype=np.int64)
    return (upto - behind) / count, behind / count


def polygon_mask(shape: tuple[int, int], vertices: tuple[tuple[float, float], ...]
                 ) -> np.ndarray:
    """Bool (H, W): pixel centres inside the polygon of (row, col) vertices (even-odd rule)."""
    rows, cols = np.indices(shape, dtype=np.float64)
    inside = np.zeros(shape, dtype=bool)
    vr = np.array([v[0] for v in vertices])
    vc = np.array([v[1] for v in vertices])
    for k in range(len(vertices)):
        r0, c0, r1, c1 = vr[k - 1], vc[k - 1], vr[k], vc[k]
        if r0 == r1:
            continue
        crosses = (rows >= min(r0, r1)) & (rows < max(r0, r1))
        at = c0 + (rows - r0) * (c1 - c0) / (r1 - r0)
        inside ^= crosses & (cols < at)
    return inside


def region_of_interest(shape: tuple[int, int], ws: WorkspaceConfig,
                       roi: np.ndarray | None = None) -> np.ndarray:
    """Bool (H, W): the pixels the region of interest allows (mask, box, polygon)."""
    allowed = np.ones(shape, dtype=bool)
    if roi is not None:
        allowed &= np.asarray(roi, dtype=bool)
    if ws.roi_box:
        r0, c0, r1, c1 = ws.roi_box
        box = np.zeros(shape, dtype=bool)
        box[r0:r1, c0:c1] = True
        allowed &= box
    if ws.roi_polygon:
        allowed &= polygon_mask(shape, ws.roi_polygon)
    return allowed


def matches_background(z: np.ndarray, background: np.ndarray, tol: float, *,
                       filled: np.ndarray | None = None) -> np.ndarray:
    """Bool (H, W): pixels within ``tol`` of the background frame, or behind it.

    Both frames come median-filtered over 3x3 valid pixels (:func:`assess`:
    a pixel's noise should not make it an object). Where the background has
    no reading, its nearest reading within :data:`BACKGROUND_REACH` pixels
    stands in (a depth camera's holes move from frame to frame, most of all
    along a tote's rim); farther away nothing is known: False. ``filled``:
    the background so filled already (:func:`prepared_background`).
    """
    a, b = z, _filled(background, BACKGROUND_REACH) if filled is None else filled
    known = np.isfinite(a) & np.isfinite(b)
    out = np.zeros(z.shape, dtype=bool)
    out[known] = a[known] - b[known] <= tol
    return out


#: The last background frame :func:`prepared_background` was given, and what it made of it.
_PREPARED: list[tuple[InputConfig, np.ndarray, tuple[np.ndarray, np.ndarray, np.ndarray]]] = []


def prepared_background(background: np.ndarray, camera: InputConfig
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The background's 3x3 median, that filled (:func:`matches_background`) and its points.

    A batch checks every image against one background frame: the three
    (read-only) arrays are kept for the last frame given and handed out
    again while the next frame has the same bits and ``[input]`` (the
    values :func:`assess` would compute).

    Parameters
    ----------
    background
        float64 (H, W) heights of the empty scene, NaN where no reading.
    camera
        ``[input]`` (:func:`points`).

    Returns
    -------
    smooth, filled, pts : numpy.ndarray
        (H, W), (H, W) and (H, W, 3).
    """
    frame = np.ascontiguousarray(background)
    for known_camera, known, made in _PREPARED:
        if known_camera == camera and same_bits(known, frame):
            return made
    smooth = _median3(frame)
    made = (smooth, _filled(smooth, BACKGROUND_REACH), points(smooth, camera))
    for arr in made:
        arr.flags.writeable = False
    _PREPARED[:] = [(camera, frame.copy(), made)]
    return made


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two arrays have the same shape, type and bytes (NaN and -0.0 included)."""
    if a.shape != b.shape or a.dtype != b.dtype:
        return False
    return bool(np.array_equal(np.ascontiguousarray(a).view(np.uint8),
                               np.ascontiguousarray(b).view(np.uint8)))


def _filled(z: np.ndarray, reach: int) -> np.ndarray:
    """``z`` with each NaN replaced by its nearest finite value within ``reach`` pixels."""
    hole = ~np.isfinite(z)
    if not hole.any() or hole.all():
        return z
    dist, (rows, cols) = ndimage.distance_transform_edt(hole, return_indices=True)
    out = z[rows, cols]
    return np.where(dist <= reach, out, np.nan)


def _median3(z: np.ndarray) -> np.ndarray:
    """3x3 median of the valid values (NaN where the centre is invalid).

    Where all nine values are valid, the fifth smallest (:func:`median9`);
    elsewhere (near an invalid pixel or the image's frame), and where that
    is a zero (the sort decides its sign), the middle of the pixel's valid
    ones, from the sorted nine (:func:`median_of_valid`):
    :func:`scipy.ndimage.median_filter` has no NaN-aware mode, and
    :func:`numpy.nanmedian` is several times slower.
    """
    padded = np.pad(z, 1, mode="constant", constant_values=np.nan)
    finite = np.isfinite(z)
    out = median9(padded if finite.all() or not np.isinf(z).any()
                  else np.pad(np.where(finite, z, np.nan), 1, constant_values=np.nan))
    # near an invalid pixel; and a zero, whose sign only the sort tells (0.0 or -0.0 first)
    rows, cols = np.nonzero((np.isnan(out) & finite) | (out == 0))
    out[rows, cols] = median_of_valid(padded, rows, cols)
    return out


#: Rows of the image :func:`median9` takes at once (its buffers stay in the cache).
MEDIAN_ROWS = 32


def median9(padded: np.ndarray) -> np.ndarray:
    """Median of each pixel's 3x3 neighbourhood in ``padded`` (its 1-px frame dropped).

    Each column of three sorted once (shared by three windows); the median of
    nine is then the middle of the largest of the three smallest, the middle
    of the middles and the smallest of the largest (exact: one of the nine
    values). NaN wherever one of the nine is NaN (an infinity is not).
    :data:`MEDIAN_ROWS` rows at a time, in buffers.

    Parameters
    ----------
    padded
        float64 (H + 2, W + 2).

    Returns
    -------
    numpy.ndarray
        float64 (H, W).
    """
    h, w = padded.shape[0] - 2, padded.shape[1] - 2
    out = np.empty((h, w))
    n = max(min(MEDIAN_ROWS, h), 0)
    columns = np.empty((4, n, w + 2))
    spare = np.empty((3, n, w))
    for r0 in range(0, h, MEDIAN_ROWS):
        k = min(MEDIAN_ROWS, h - r0)
        low, mid, high, scratch = columns[:, :k]
        _sort_columns(padded[r0:r0 + k], padded[r0 + 1:r0 + 1 + k], padded[r0 + 2:r0 + 2 + k],
                      (low, mid, high), scratch)
        most_low, mid_mid, least_high = spare[:, :k]
        np.maximum(low[:, :-2], low[:, 1:-1], out=most_low)
        np.maximum(most_low, low[:, 2:], out=most_low)
        np.minimum(high[:, :-2], high[:, 1:-1], out=least_high)
        np.minimum(least_high, high[:, 2:], out=least_high)
        rows = out[r0:r0 + k]
        _middle(mid[:, :-2], mid[:, 1:-1], mid[:, 2:], mid_mid, rows)
        _middle(most_low, mid_mid, least_high, rows, most_low)
    return out


def _sort_columns(a: np.ndarray, b: np.ndarray, c: np.ndarray,
                  out: tuple[np.ndarray, np.ndarray, np.ndarray], scratch: np.ndarray) -> None:
    """Element-wise smallest, middle and largest of ``a, b, c`` into ``out`` (NaN to all)."""
    low, mid, high = out
    np.minimum(a, b, out=low)
    np.maximum(a, b, out=high)
    np.minimum(high, c, out=scratch)
    np.maximum(high, c, out=high)
    np.maximum(low, scratch, out=mid)
    np.minimum(low, scratch, out=low)


def _middle(a: np.ndarray, b: np.ndarray, c: np.ndarray, out: np.ndarray,
            scratch: np.ndarray) -> None:
    """Element-wise middle of ``a, b, c`` into ``out`` (NaN where any is NaN).

    ``scratch`` may be ``a`` (overwritten); ``out`` none of the three.
    """
    np.maximum(a, b, out=out)
    np.minimum(out, c, out=out)
    np.minimum(a, b, out=scratch)
    np.maximum(scratch, out, out=out)


def median_of_valid(padded: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Median of the valid values of the 3x3 neighbourhoods at ``(rows, cols)`` of the image.

    ``padded`` is the image with a 1-px NaN frame. The nine values sorted
    (NaN last), and the middle of the valid ones taken (the mean of the two
    middle ones for an even count); NaN where none is valid.
    """
    stack = np.sort(np.stack([padded[rows + i, cols + j] for i in range(3) for j in range(3)]),
                    axis=0)
    count = np.isfinite(stack).sum(axis=0)
    low = np.take_along_axis(stack, np.maximum(count - 1, 0)[None] // 2, axis=0)[0]
    high = np.take_along_axis(stack, (count // 2)[None], axis=0)[0]
    return 0.5 * (low + high)


def assess(z: np.ndarray, config: Config, noise: float, *,
           background: np.ndarray | None = None, roi: np.ndarray | None = None
           ) -> Workspace:
    """The pickable pixels of one segmented image (module Notes).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    config
        ``[workspace]`` and ``[input]``.
    noise
        The image's noise sigma, depth units.
    background
        float64 (H, W) heights of the empty scene (NaN where no reading), or None.
    roi
        bool (H, W) mask of the pixels that may be picked, or None.

    Returns
    -------
    Workspace
    """
    ws = config.workspace
    valid = np.isfinite(z)
    pickable = valid & region_of_interest(z.shape, ws, roi)
    auto = default_tolerance(z, config.input, noise)
    tol = ws.support_tolerance or auto
    if background is None and not ws.support:
        return Workspace(pickable, None, None, tol)
    smooth = _median3(z)
    # the empty scene shows the whole support: found there when given
    ref, filled, ref_pts, behind = smooth, None, None, 0.0
    if background is not None:
        ref, filled, ref_pts = prepared_background(background, config.input)
        bg_tol = ws.background_tolerance or auto
        pickable &= ~matches_background(smooth, ref, bg_tol, filled=filled)
        behind = behind_share(smooth, filled, bg_tol)
    plane = find_support(ref, config.input, tol) if ws.support else None
    if plane is not None and background is None and plane.inliers < HIDDEN_SUPPORT:
        return Workspace(pickable, None, None, tol, behind=behind, hidden=plane)
    if plane is None:
        return Workspace(pickable, None, None, tol, behind=behind)
    pts = points(smooth, config.input)
    height = plane.distance(pts)
    with np.errstate(invalid="ignore"):
        on = np.abs(height if ref_pts is None else plane.distance(ref_pts)) <= tol
        pickable &= height > max(tol, ws.min_height)
        if ws.max_height > 0:
            pickable &= height <= ws.max_height
    hull = support_hull(on)
    extent = hull_extent(hull, z.shape)
    if config.input.has_intrinsics:
        pickable = over_support(pts, height, hull, plane, config.input, where=pickable)
    else:  # a height map's feet are its pixels, and its extent is not shrunk
        pickable &= extent
    return Workspace(pickable, height, plane, tol, extent, behind)


def behind_share(z: np.ndarray, background: np.ndarray, tol: float) -> float:
    """Share of the pixels both frames read where ``z`` lies more than ``tol`` below ``background``.

    Heights; 0 when no pixel is read by both.
    """
    known = np.isfinite(z) & np.isfinite(background)
    if not known.any():
        return 0.0
    return float(np.count_nonzero(z[known] - background[known] < -tol)) / int(known.sum())


def support_hull(on: np.ndarray) -> np.ndarray | None:
    """Half-planes ``(a, b, c)`` (``a col + b row + c <= 0`` inside) of the support's extent.

    The convex hull, in the image, of the 8-connected pieces of the
    support's pixels ``on`` with at least :data:`HULL_PIECE` of the largest
    one's pixels (a tote's floor; a table seen on both sides of a wall);
    ``None`` when it has no area. The hull is taken of their
    :func:`extreme_pixels` only (every pixel on the hull's boundary is one).
    """
    pieces, count = ndimage.label(on, structure=np.ones((3, 3), dtype=bool))
    if count == 0:
        return None
    sizes = np.bincount(pieces.ravel())
    sizes[0] = 0
    large = sizes >= HULL_PIECE * sizes.max()
    rows, cols = extreme_pixels(large[pieces])
    if int(sizes[large].sum()) < 3 or np.ptp(rows) == 0 or np.ptp(cols) == 0:
        return None
    return np.asarray(ConvexHull(np.column_stack([cols, rows]).astype(np.float64)).equations)


def extreme_pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the first and last pixel of ``mask`` in each row and in each column.

    Every pixel on the boundary of the convex hull of ``mask``'s pixels is
    one of them (no pixel of its row, or of its column for a level edge,
    lies beyond it), so they have the same hull. Row-major order, each once.
    """
    h, w = mask.shape
    keep = np.zeros(mask.shape, dtype=bool)
    r = np.flatnonzero(mask.any(axis=1))
    keep[r, np.argmax(mask[r], axis=1)] = True
    keep[r, w - 1 - np.argmax(mask[r, ::-1], axis=1)] = True
    c = np.flatnonzero(mask.any(axis=0))
    keep[np.argmax(mask[:, c], axis=0), c] = True
    keep[h - 1 - np.argmax(mask[::-1, c], axis=0), c] = True
    rows, cols = np.nonzero(keep)
    return rows, cols


#: Positions :func:`inside_hull` tests at once (its buffers stay in the cache).
HULL_CHUNK = 8192


def inside_hull(hull: np.ndarray | None, rows: np.ndarray, cols: np.ndarray,
                inset: float = 0.0) -> np.ndarray:
    """Whether image positions lie in the hull shrunk by ``inset`` px (all True without one).

    The hull runs through pixel centres: a position within a pixel outside it
    counts as in (at ``inset`` 0). Flat positions are tested
    :data:`HULL_CHUNK` at a time, in buffers (the same arithmetic).
    """
    rows, cols = np.broadcast_arrays(rows, cols)
    shape = rows.shape
    inside = np.ones(rows.size, dtype=bool)
    if hull is None:
        return inside.reshape(shape)
    rows, cols = rows.ravel(), cols.ravel()
    limit = 1.0 - inset
    size = min(HULL_CHUNK, rows.size)
    value, term, out = np.empty(size), np.empty(size), np.empty(size, dtype=bool)
    for start in range(0, rows.size, HULL_CHUNK):
        stop = min(start + HULL_CHUNK, rows.size)
        rr, cc, k = rows[start:stop], cols[start:stop], stop - start
        v, t, o, keep = value[:k], term[:k], out[:k], inside[start:stop]
        for a, b, c in hull:  # unit normals (a, b), outwards
            np.multiply(a, cc, out=v)
            np.multiply(b, rr, out=t)
            np.add(v, t, out=v)
            np.add(v, c, out=v)
            with np.errstate(invalid="ignore"):
                np.greater(v, limit, out=o)
            keep &= ~o
    return inside.reshape(shape)


def hull_extent(hull: np.ndarray | None, shape: tuple[int, int], inset: float = 0.0
                ) -> np.ndarray:
    """Bool ``shape``: :func:`inside_hull` at every pixel of the image (the same bits).

    Along a row a half-plane's test is monotonic in the column, so each row
    is inside between two columns: per half-plane and row, the column where
    the test turns, estimated and then checked with the test itself on a few
    columns around it (:func:`_turning_columns`). A half-plane whose turn is
    not found there (a level one) is tested at every pixel.
    """
    h, w = shape
    inside = np.ones(shape, dtype=bool)
    if hull is None:
        return inside
    rows = np.arange(h)[:, None]
    first, stop = np.zeros((h, 1), dtype=np.int64), np.full((h, 1), w, dtype=np.int64)
    limit = 1.0 - inset
    for a, b, c in hull:
        turn = _turning_columns(a, b, c, rows, w, limit) if abs(a) > 1e-9 else None
        if turn is None:
            cols = np.arange(w)[None, :]
            with np.errstate(invalid="ignore"):
                inside &= ~(a * cols + b * rows + c > limit)
        elif a > 0:
            stop = np.minimum(stop, turn)
        else:
            first = np.maximum(first, turn)
    cols = np.arange(w)[None, :]
    return inside & (cols >= first) & (cols < stop)


#: Columns around the estimated turn where :func:`_turning_columns` checks the test.
TURN_WINDOW = 8


def _turning_columns(a: float, b: float, c: float, rows: np.ndarray, w: int, limit: float
                     ) -> np.ndarray | None:
    """Per row, the first column where the test turns; ``None`` when not found.

    The test is :func:`inside_hull`'s ``a col + b row + c > limit``; it turns
    from false to true along a row when ``a > 0``, from true to false when
    ``a < 0`` (``w``: it never does). Evaluated, as :func:`inside_hull` does,
    on :data:`TURN_WINDOW` columns from a little before the real-valued
    crossing, and on the column before them: the turn is found when that
    column is on the first side (or there is none) and a column of the
    window on the other (or past the image).

    Parameters
    ----------
    a, b, c
        The half-plane (``a`` not 0).
    rows
        int (H, 1) row numbers.
    w
        Image width.
    limit
        ``1 - inset``.

    Returns
    -------
    numpy.ndarray or None
        int64 (H, 1) columns in [0, w].
    """
    with np.errstate(all="ignore"):
        cross = np.floor((limit - c - b * rows.astype(np.float64)) / a)
        start = (np.clip(cross, -TURN_WINDOW, w) + 1 - TURN_WINDOW // 2).astype(np.int64)
    start = np.clip(start, 0, w)
    cols = start + np.arange(-1, TURN_WINDOW)[None, :]
    turned = a * cols + b * rows + c > limit
    if a < 0:
        turned = ~turned
    turned[cols >= w] = True
    window = turned[:, 1:]
    if not ((~turned[:, 0] | (start[:, 0] == 0)) & window.any(axis=1)).all():
        return None
    return start + np.count_nonzero(~window, axis=1)[:, None]


def over_support(pts: np.ndarray, height: np.ndarray, hull: np.ndarray | None, plane: Plane,
                 camera: InputConfig, where: np.ndarray | None = None) -> np.ndarray:
    """Bool (H, W): pixels whose foot on the support lies within the support's extent.

    A pixel's foot is its point moved down the support's normal by its
    height, projected into the image (with intrinsics; a height map's foot is
    the pixel itself: :func:`hull_extent`); the extent is :func:`support_hull`.
    Things outside a tote stand over no floor of it. With ``where``, only its
    pixels are tested (False elsewhere).
    """
    inset = hull_inset(pts, camera)
    if not camera.has_intrinsics:
        out = hull_extent(hull, height.shape, inset)
        return out if where is None else out & where
    at = np.nonzero(np.ones(height.shape, dtype=bool) if where is None else where)
    out = np.zeros(height.shape, dtype=bool)
    out[at] = inside_hull(hull, *_feet(pts[at], height[at], plane, camera), inset)
    return out


def odd_pixels(side_mm: float, focal: float, depth_mm: float) -> int:
    """Pixels a side of ``side_mm`` spans at ``depth_mm`` (pinhole): the nearest odd, 1 to 255."""
    k = int(math.floor(side_mm * focal / depth_mm / 2.0)) * 2 + 1
    return min(max(k, 1), 255)


def hull_inset(pts: np.ndarray, camera: InputConfig) -> float:
    """Pixels the support's extent is shrunk by: :data:`INSET_MM` at the median depth.

    Where a tote's floor meets its walls a depth camera shows a rounded,
    rising band (the jump smoothed, the floor's own warp), higher than the
    support's tolerance and without a step to the floor: on the two ARC
    empty totes, bands 16-35 mm high and up to 1,100 px; none keeps a tenth
    of its pixels 10 px inside the floor's hull, the items in the totes
    nearly all. Only with metric camera depth (a height map's table fills
    the view); 0 otherwise.
    """
    if not (camera.has_intrinsics and camera.metres_per_unit > 0):
        return 0.0
    depth = pts[..., 2][np.isfinite(pts[..., 2])]
    if not depth.size:
        return 0.0
    mm = float(np.median(depth)) * camera.metres_per_unit * 1000.0
    return INSET_MM * math.sqrt(camera.fx * camera.fy) / max(mm, 1e-9)


def _feet(pts: np.ndarray, height: np.ndarray, plane: Plane, camera: InputConfig
          ) -> tuple[np.ndarray, np.ndarray]:
    """Image (row, col) of each point's foot on the support plane (NaN where unknown)."""
    if not camera.has_intrinsics:
        grid = np.indices(height.shape, dtype=np.float64)
        return grid[0], grid[1]
    foot = pts - height[..., None] * np.asarray(plane.normal)
    with np.errstate(divide="ignore", invalid="ignore"):
        col = camera.fx * foot[..., 0] / foot[..., 2] + camera.cx
        row = camera.fy * foot[..., 1] / foot[..., 2] + camera.cy
    return row, col
