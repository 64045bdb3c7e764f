"""Vacuum-gripper holdsites from the segmentation (Al-Hujazi & Sood 1990, Sec. VII).

"The output of the segmentation algorithm is used to determine the highest
surface in the object ... A small area (7x7) in the highest surface is then
determined. The standard deviation of the AR computed using a 5x5 Gaussian
mask is evaluated. If [it] is small ... the selected area is accepted,
otherwise a search for another area is performed. This area should be inside
a single surface as far as possible from the periphery of the object and any
internal holes ... as close as possible to the center of gravity of the
object", approximated by its centre of area (Sec. VII).

Notes
-----
Step 1, background. Border regions lie within :data:`ADJACENCY_RADIUS`
pixels of the image border or of an invalid area that reaches it.
``"lowest-border"`` takes the one with the lowest mean height,
``"largest-border"`` the one with the most pixels (only border regions
with at least :data:`BACKGROUND_MIN_FRACTION` of the segmented pixels are
eligible, unless none has). Every other region at the same level joins it
(a table split by an object or a shadow, or seen through a hole): the
chosen one's fit, extended to its centroid, is within ``step.threshold`` of
its own fit there, or, when the chosen one is level (its fit varies by
``step.threshold`` or less over its box), its mean height is within
``step.threshold`` of the chosen one's. Never a region that meets the chosen
one at a step edge: on a tilted table, a box whose top is as high as the
table's middle is an object. ``"none"``: no background.

Step 2, objects: non-background regions joined by a non-step boundary
(roof or smooth, from ``Surface.neighbors`` where listed, else the median
height gap of the fits <= ``step.threshold``) form one object. A step edge
is an occlusion boundary: there one object lies on or in front of another.
Beyond the paper (``workspace.border_structures``), a concave crease parts
objects too: where an item leans on a wall or lies on another item their
surfaces meet in a valley, while an item's own faces meet in ridges (the
local convexity of Stein et al., "Object partitioning using local
convexity", CVPR 2014). An item with a concave crease of its own (an
L-bracket, an open box) is then two objects.
An object is *covered* when, across a step edge to another object, the other
side is higher (median gap of the fits at the boundary midpoints): the
top-most object of a pile is uncovered (Sec. VII, "the top-most object in
the pile is usually selected"). Beyond the paper (``border_structures``),
also when another object, neither a structure, lies within
:data:`STAND_REACH` px across any gap but the support and its pixels there
are higher by more than ``step.threshold`` (:func:`covered_across_gaps`: a
camera's smoothed depth jump leaves a band of edge pixels between an item
and the one lying on it), on a view from above (:func:`seen_from_above`).

Step 3, order: surfaces of objects wholly in view first (an object within
:data:`ADJACENCY_RADIUS` of the image frame, or of invalid pixels joined to
it, is a bin wall or a part cut off by the frame, whose centre of area is
unknown; beyond the paper only invalid areas :data:`HIDING_WIDTH` px wide
count, not the cracks of no reading along edges that join them, nor a
shadow for its caster (:func:`shadow_casters`)); then those
of uncovered objects before covered ones; within each group highest mean
height first
(Sec. VII: "comparing the range value of the segmented surfaces").
Beyond the paper (``border_structures``), an uncovered object at the
border that lies on an item wholly in view comes after the uncovered
objects in view and before the covered ones (:func:`lying_on_seen_items`:
the item stands or lies on what does, and is no structure; in a heaped
tote the top item often reaches the tote's wall or the frame, and it is
what covers the items under it). The robot's arm over its finger is not
so promoted: a finger held up by nothing holds nothing up. Without a
support nothing tells what is held up, and nothing is promoted.

Step 4, candidates in a surface: window centres where the footprint
(``holdsite.size``; a non-square one at every ``rotation_step`` degrees in
[0, 180)) lies wholly on valid pixels of the surface (binary erosion), and
the standard deviation of the 2-D AR (:func:`~rangeseg_cli.stages.edges.ar_2d`)
over the footprint is <= ``holdsite.max_ar_std`` (window means of AR and
AR^2). The first surface in the order with a candidate holds the site.
Beyond the paper (``border_structures``), a surface's windows keep clear
of the valid pixels beside no reading (a camera's readings at the edge of
a shadow or dropout are the least sure) when any of them is accepted, else
they may touch them (:func:`_collect`).
The paper's bound, 1, is about what noise of its noisiest images (sigma_o
= 2) gives alone (0.525 sigma: :func:`ar_noise_std`); beyond the paper's
noise range (with ``[input] auto_thresholds``, as the thresholds) it grows
by :data:`FLAT_AR_NOISE` times the AR spread of the noise above that range
(:func:`ar_std_limit`), or no window of a noisier camera is flat.

Step 4b, tilt (beyond the paper; ``holdsite.max_tilt`` < 90): a candidate
also needs the normal that a site there would report (Step 6) within
``max_tilt`` degrees of the support's normal when the workspace finds a
support (a camera mounted at a slant sees a box's side as squarely as its
top; the support says which is level), else of the sensor's axis: with
camera intrinsics the camera-frame normal against the optical axis, else
the height map's normal with ``[input] units_per_pixel`` depth units per
pixel of lateral size against the height axis (:func:`tilts`), within
:data:`TILT_TOLERANCE`.
A curved surface's local poses come from moment images
(:func:`local_poses`), computed for its windows in the order they are
wanted, a chunk at a time (:func:`_first_level`).

Step 5, choice: the largest clearance (Euclidean distance transform of the
surface mask: distance in pixels from the window centre to the nearest pixel
that is not on the surface -- its border, a hole, an edge, an invalid pixel
or outside the image), compared in whole pixels; then the nearest to the
object's centre of area; then row, col. Beyond the paper, with a tilt limit
(``holdsite.max_tilt`` < 90), on a curved surface whose widest window has
room to spare (clearance :func:`enough_clearance`: the footprint's half
diagonal + 2 px), the most level of the windows with that much (whole
degrees; ties in the order above) is chosen: where such a surface turns
away from the camera a cup seals worse. A rotated footprint takes, at
that centre, the accepted angle whose footprint stays farthest from the
surface's border (the distance transform's minimum over the footprint),
then the lowest AR std, then the smallest angle.

Runners-up: the best candidate of each next surface in the order, up to
``holdsite.max_candidates``; if fewer surfaces have one, further windows on
the same surfaces (chosen surface first), in rank order, whose centres are
at least the footprint's diagonal from every window already picked on that
surface (so no two windows overlap).

Score (descriptive, in (0, 1), higher is better; the choice follows the
order above): ``c / (c + h) * rho / (rho + d)`` with ``c`` the clearance,
``h`` half the footprint's longer side plus one half (4 for 7x7, so a window
that just fits scores about 0.5 on clearance), ``d`` the distance to the
object's centre of area and ``rho = sqrt(A / pi)`` the radius of a disc of
the object's area ``A``.

Step 6, pose: elevation and gradient at the centre, from the surface's fit
on a planar surface and, on a curved one, from a quadric of the surface's
pixels within the footprint's longer side of the centre, and at least :data:`LOCAL_MIN_REACH` pixels
(:func:`local_reach`; :func:`local_pose`: one quadric of a whole
curved surface can be off by several depth units and degrees at a given
point). The
unit normal ``n ~ (-dz/dx, -dz/dy, 1)`` (x = col, y = row, z up towards the sensor); the
approach vector ``-n`` (the gripper moves against the normal). With camera
intrinsics and depth input (``larger_is_closer = false``, depth ``d = -z``),
the point is ``((col - cx) d / fx, (row - cy) d / fy, d)`` (metres when
``metres_per_unit > 0``, else depth units). The camera-frame normal is the
cross product of the tangents of ``P(u, v) = d(u, v) ((u - cx)/fx, (v - cy)/fy, 1)``:
``n ~ -(-fx d_u, -fy d_v, d + (u - cx) d_u + (v - cy) d_v)``, oriented
towards the camera; it is exact for the fitted depth function, and the one
approximation is the fit itself (a 3-D plane has depth
``1 / (alpha u + beta v + gamma)``, which the quadric approximates over the
region). ``approach_camera = -n``.

Cost: the boundary pairs of step 2 come from
:func:`~rangeseg_cli.stages.surfaces.neighbour_pairs` (a band along the
boundaries); the border regions from the frame's strips (and the invalid
areas reaching the frame, when there are any), computed once; the 2-D AR of
step 4 only on the crops of the surfaces searched (see ``_Scene.ar``), and
a rectangular footprint's erosion as a separable running minimum. The
choice of step 5 needs only each surface's best window; the full ranking is
sorted only for runners-up taken from one surface. With numba installed the
boundary pairs, their medians and the clearance (distance transform) are
compiled (the boundary pairs, gaps and medians of step 2 in one call;
identical results; ``RANGESEG_PURE_NUMPY=1`` for the reference).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import ndimage

from ..batch.stopping import checkpoint
from ..cell.workspace import Plane, Workspace, assess, odd_pixels
from ..config import MAX_DEPTH, Config, HoldsiteConfig, InputConfig, check_config
from ..errors import InputError
from ..kernels.backend import Backend, select_kernels
from ..models import Surface
from .edges import ar_2d, gaussian_taps
from .grow import RCOND, evaluate_quadric, valid_labels
from .noise import PAPER_NOISE, estimate_noise, lateral_scale, paper_scale
from .rangeimage import check_stage_arrays, require_shape_of_z
from .surfaces import (
    NEIGHBOUR_REACH,
    describe_surfaces,
    kernel_labels,
    neighbour_pairs,
    pair_medians,
)

#: Regions whose pixels lie within this chessboard distance are neighbours
#: (across an edge band one or two pixels thick), as in ``Surface.neighbors``:
#: the same reach, so the step gaps that ``describe_surfaces_and_gaps`` gives
#: with the surfaces are those :func:`step_gaps` would compute.
ADJACENCY_RADIUS = NEIGHBOUR_REACH

#: A border region is a candidate for the background only when it holds at
#: least this fraction of all segmented pixels (unless none does): a sliver
#: seen past a bin's rim is lower than the floor but is not the floor.
BACKGROUND_MIN_FRACTION = 0.01

#: Rotated footprints with more pixels than this are averaged by FFT convolution.
FFT_FOOTPRINT_PIXELS = 64

Vector = tuple[float, float, float]


@dataclass(frozen=True)
class Holdsite:
    """One acceptable gripper window (Sec. VII).

    Attributes
    ----------
    row, col
        0-based pixel position of the window's centre.
    elevation
        Height of the surface fit at the centre (height units; for depth
        input this is minus the depth).
    normal, approach
        Unit surface normal (x = col, y = row, z up towards the sensor) and
        approach vector ``-normal``.
    surface, surface_type, object
        Surface id, its type (``"planar"``/``"curved"``) and the object id.
    clearance
        Distance in pixels from the centre to the nearest pixel off the surface.
    ar_std
        Standard deviation of the 2-D AR over the footprint (depth units).
    score
        Descriptive score in (0, 1) (see the module Notes).
    angle
        Footprint rotation in degrees, counter-clockwise as displayed; 0 = the
        footprint's rows along image rows.
    size
        Footprint (rows, cols).
    point_camera, approach_camera
        Camera-frame point (metres, or depth units without ``metres_per_unit``)
        and approach vector; ``None`` when not computable.
    flat_rms
        RMS residual of the least-squares plane of the heights under the
        footprint (depth units); ``None`` when not computed.
    tilt, tilt_from
        Degrees between the site's normal and the axis Step 4b measures
        ``max_tilt`` from, and that axis: ``"support"`` (the workspace's
        support normal), ``"optical axis"`` (camera intrinsics) or
        ``"height axis"`` (``[input] units_per_pixel``); ``None`` without a
        lateral scale (:func:`site_tilt`).
    """

    row: int
    col: int
    elevation: float
    normal: Vector
    approach: Vector
    surface: int
    surface_type: str
    object: int
    clearance: float
    ar_std: float
    score: float
    angle: float
    size: tuple[int, int]
    point_camera: Vector | None = None
    approach_camera: Vector | None = None
    flat_rms: float | None = None
    tilt: float | None = None
    tilt_from: str | None = None

    def to_dict(self, *, camera: bool = False) -> dict[str, Any]:
        """Plain dict of ``holdsite.json``; camera-frame keys only when ``camera``."""
        out: dict[str, Any] = {
            "row": self.row, "col": self.col, "elevation": self.elevation,
            "normal": list(self.normal), "approach": list(self.approach),
            "surface": self.surface, "surface_type": self.surface_type,
            "object": self.object, "clearance": self.clearance, "ar_std": self.ar_std,
            "score": self.score, "angle": self.angle, "size": list(self.size),
        }
        if self.flat_rms is not None:
            out["flat_rms"] = self.flat_rms
        if self.tilt is not None:
            out["tilt"], out["tilt_from"] = self.tilt, self.tilt_from
        if camera:
            out["point_camera"] = _listed(self.point_camera)
            out["approach_camera"] = _listed(self.approach_camera)
        return out


@dataclass(frozen=True)
class ObjectInfo:
    """A connected group of non-background regions (Sec. VII).

    Attributes
    ----------
    id
        Object id (1..M, numbered by smallest surface id).
    surfaces
        Its surface ids.
    pixels
        Total pixel count.
    centroid
        (row, col) centre of area.
    covered_by
        Objects higher than this one across a shared step edge; beyond the
        paper also across a band of edge pixels (:func:`covered_across_gaps`).
    touches_border
        Whether a surface lies within :data:`ADJACENCY_RADIUS` of the image
        frame or of an invalid area reaching it (a bin wall, or a part cut
        off by the frame); beyond the paper, of an invalid area at least
        :data:`HIDING_WIDTH` px wide (:func:`outer_invalid`) that is not
        its own shadow (:func:`shadow_casters`).
    structure
        Whether it is a structure, never picked (the robot's fingers, a
        tote's wall, rim or floor: :func:`mark_structures`).
    stands
        Whether it stands on the support, with at least a footprint's area
        (:func:`mark_structures`).
    """

    id: int
    surfaces: tuple[int, ...]
    pixels: int
    centroid: tuple[float, float]
    covered_by: tuple[int, ...] = ()
    touches_border: bool = False
    structure: bool = False
    stands: bool = False

    @property
    def covered(self) -> bool:
        """Whether another object lies on or in front of this one."""
        return bool(self.covered_by)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for ``holdsite.json``."""
        return {"id": self.id, "surfaces": list(self.surfaces), "pixels": self.pixels,
                "centroid": list(self.centroid), "covered": self.covered,
                "covered_by": list(self.covered_by), "touches_border": self.touches_border,
                "structure": self.structure, "stands_on_support": self.stands}


@dataclass(frozen=True)
class HoldsiteResult:
    """The holdsite of one image, its runners-up and the scene's reading.

    ``holdsite`` is ``None`` when no surface has an acceptable window;
    ``reason`` then says why (never an error). ``background`` holds the
    regions of step 1's rule, ``outside`` the other regions the workspace
    leaves out (step 0).
    """

    holdsite: Holdsite | None
    reason: str
    candidates: tuple[Holdsite, ...] = ()
    background: tuple[int, ...] = ()
    objects: tuple[ObjectInfo, ...] = ()
    camera: bool = False
    outside: tuple[int, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The ``holdsite.json`` document (docs/outputs.md)."""
        site = self.holdsite.to_dict(camera=self.camera) if self.holdsite else None
        return {"holdsite": site, "reason": self.reason,
                "candidates": [c.to_dict(camera=self.camera) for c in self.candidates],
                "background": list(self.background),
                "outside_workspace": list(self.outside),
                "objects": [o.to_dict() for o in self.objects]}


def _listed(v: Vector | None) -> list[float] | None:
    return None if v is None else list(v)


# ---------------------------------------------------------------------------
# Step 1: background; step 2: objects


def _coefficient_table(surfaces: list[Surface], n: int) -> np.ndarray:
    """(n+1, 6) coefficients indexed by label (zeros where no surface)."""
    table = np.zeros((n + 1, 6))
    for s in surfaces:
        if s.id <= n:
            table[s.id] = s.coefficients
    return table


def step_gaps(labels: np.ndarray, coeffs: np.ndarray, known: np.ndarray, *,
              backend: Backend = "auto") -> dict[tuple[int, int], float]:
    """Median signed height gap ``f_i - f_j`` between neighbouring regions i < j.

    Pixel pairs of different known labels within :data:`ADJACENCY_RADIUS`
    (chessboard) are the boundary; both fits are evaluated at each pair's
    midpoint. The pairs come from :func:`~rangeseg_cli.stages.surfaces.neighbour_pairs`,
    which examines only a band along the boundaries.

    Parameters
    ----------
    labels
        int (H, W) labels, 0 = none.
    coeffs
        (n+1, 6) quadric coefficients by label.
    known
        bool (n+1,): labels that have a surface (label 0 is never one).
    backend
        For :func:`~rangeseg_cli.stages.surfaces.neighbour_pairs` and
        :func:`~rangeseg_cli.stages.surfaces.pair_medians` (identical results).

    Returns
    -------
    dict
        ``{(i, j): median(f_i - f_j)}``; positive when i is the higher side.
    """
    labels = np.asarray(labels)
    return _known_gaps(np.where(known[labels], labels, 0), coeffs, backend)


def _known_gaps(labels: np.ndarray, coeffs: np.ndarray, backend: Backend
                ) -> dict[tuple[int, int], float]:
    """:func:`step_gaps` of labels that all have a surface (0 elsewhere).

    Compiled when ``backend`` selects the kernels: pairs, gaps and medians in
    one call (:func:`rangeseg_cli.kernels.compiled.step_gaps`, the same values).
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        group_lo, group_hi, med = kernels.step_gaps(
            kernel_labels(labels), ADJACENCY_RADIUS, np.require(coeffs, np.float64, ["C"]))
        return dict(zip(zip(group_lo.tolist(), group_hi.tolist(), strict=True), med.tolist(),
                        strict=True))
    rp, cp, rq, cq, lp, lq = neighbour_pairs(labels, ADJACENCY_RADIUS, backend=backend)
    if lp.size == 0:
        return {}
    rm, cm = 0.5 * (rp + rq), 0.5 * (cp + cq)
    gap = evaluate_quadric(coeffs[lp], rm, cm) - evaluate_quadric(coeffs[lq], rm, cm)
    swap = lp > lq
    lo, hi, gap = np.where(swap, lq, lp), np.where(swap, lp, lq), np.where(swap, -gap, gap)
    group_lo, group_hi, (med,) = pair_medians(lo, hi, gap[None], backend=backend)
    return {(i, j): g for i, j, g in zip(group_lo.tolist(), group_hi.tolist(), med.tolist(),
                                         strict=True)}


def _present(labels: np.ndarray) -> set[int]:
    """The positive labels of an array (any shape)."""
    flat = labels.ravel()
    if (flat.size and np.can_cast(flat.dtype, np.intp) and flat.min() >= 0
            and flat.max() <= 4 * flat.size + 65536):  # counted, not sorted
        return set((np.flatnonzero(np.bincount(flat)[1:]) + 1).tolist())
    found = np.unique(labels)
    return set(found[found > 0].tolist())


def _framed(labels: np.ndarray) -> set[int]:
    """Labels within :data:`ADJACENCY_RADIUS` of the image frame (the frame's strips)."""
    k = ADJACENCY_RADIUS + 1
    return _present(np.concatenate([strip.ravel() for strip in (
        labels[:k], labels[-k:], labels[:, :k], labels[:, -k:])]))


def _near_outer_invalid(labels: np.ndarray, valid: np.ndarray, width: int = 1) -> set[int]:
    """Labels within :data:`ADJACENCY_RADIUS` of the invalid areas of :func:`outer_invalid`."""
    return _near_zone(labels, outer_invalid(valid, width))


#: Share of a label's crossings of the hiding invalid areas that must find a lower surface
#: beyond them for the label to be their caster (:func:`shadow_casters`), and the fewest
#: crossings that tell.
CASTER_SHARE = 0.75
MIN_CROSSINGS = 3


def shadow_casters(labels: np.ndarray, valid: np.ndarray, z: np.ndarray, tol: float,
                   zone: np.ndarray | None) -> set[int]:
    """Labels beside the invalid areas ``zone`` only as the casters of their shadows.

    Beyond the paper. A depth camera's projector (or its second imager)
    leaves a shadow of no reading beside a near item, on the surfaces behind
    it. Such a shadow hides nothing of its caster. Along each row and each
    column, every run of ``zone`` (:func:`outer_invalid`, ``HIDING_WIDTH``)
    is crossed from the labelled pixel before it to the pixel after it, and
    back: a crossing that ends at a valid pixel lower than its start by more
    than ``tol`` is a caster's; one that ends at the frame, at no reading or
    higher is not. A label with :data:`MIN_CROSSINGS` or more, at least
    :data:`CASTER_SHARE` of them a caster's, is returned.
    """
    if zone is None:
        return set()
    n = int(labels.max(initial=0)) + 1
    total, casts = np.zeros(n, np.int64), np.zeros(n, np.int64)
    for t in (lambda a: a, np.transpose):  # along the rows, then down the columns
        owner, cast = _crossings(t(zone), t(labels), t(valid), t(z), tol)
        total += np.bincount(owner, minlength=n)
        casts += np.bincount(owner[cast], minlength=n)
    return set(np.flatnonzero((total >= MIN_CROSSINGS) & (casts >= CASTER_SHARE * total))
               .tolist())


def _crossings(zone: np.ndarray, labels: np.ndarray, valid: np.ndarray, z: np.ndarray,
               tol: float) -> tuple[np.ndarray, np.ndarray]:
    """The labels starting each crossing of a run of ``zone`` along a row, and whether it casts.

    Both ends of every run start one, from the first labelled pixel within
    :data:`ADJACENCY_RADIUS` beyond it (a valid unlabelled edge pixel may lie
    between); a start must be a valid labelled pixel.
    """
    step = np.diff(np.pad(zone, ((0, 0), (1, 1))).view(np.int8), axis=1)
    rows, first = np.nonzero(step == 1)
    last = np.nonzero(step == -1)[1]  # one past each run, in the same order
    width = zone.shape[1]
    starts = np.concatenate([first - 1, last])  # both ends of every run ...
    ends = np.concatenate([last, first - 1])  # ... and the far end of the crossing
    away = np.sign(starts - ends)  # from the run, outwards
    rows = np.concatenate([rows, rows])
    for _ in range(ADJACENCY_RADIUS):  # over the edge pixels next to the run
        inside = (starts >= 0) & (starts < width)
        edge = np.zeros(starts.size, bool)
        edge[inside] = (labels[rows[inside], starts[inside]] == 0) & valid[rows[inside],
                                                                          starts[inside]]
        starts = np.where(edge, starts + away, starts)
    inside = (starts >= 0) & (starts < width)
    rows, starts, ends = rows[inside], starts[inside], ends[inside]
    owner = labels[rows, starts]
    mine = (owner > 0) & valid[rows, starts]
    rows, starts, ends, owner = rows[mine], starts[mine], ends[mine], owner[mine]
    seen = (ends >= 0) & (ends < width)
    far = np.full(rows.size, np.inf)
    far[seen] = np.where(valid[rows[seen], ends[seen]], z[rows[seen], ends[seen]], np.inf)
    return owner, far < z[rows, starts] - tol


def _near_zone(labels: np.ndarray, zone: np.ndarray | None) -> set[int]:
    """Labels within :data:`ADJACENCY_RADIUS` of ``zone`` (none without one)."""
    if zone is None:
        return set()
    return _present(labels[square_dilation(zone, 2 * ADJACENCY_RADIUS + 1)])


def in_view_border(labels: np.ndarray, valid: np.ndarray, z: np.ndarray, tol: float,
                   space: Workspace | None = None) -> set[int]:
    """Labels near the invalid areas that may hide part of them (beyond the paper, step 3).

    Those within :data:`ADJACENCY_RADIUS` of the invalid areas at least
    :data:`HIDING_WIDTH` px wide that reach the frame (:func:`outer_invalid`),
    but their shadows' casters (:func:`shadow_casters`). Casters count
    only where step 3's heights are heights: above a support, or on a view
    from above (:func:`seen_from_above` of ``space.hidden``). At a slant
    without a support the nearest item along the sensor's axis would go
    first, often not the highest (the SR300 frame of ``sample_data/arc``
    alone).
    """
    zone = outer_invalid(valid, HIDING_WIDTH)
    near = _near_zone(labels, zone)
    if space is not None and space.support is None and not seen_from_above(space.hidden):
        return near
    return near - shadow_casters(labels, valid, z, tol, zone)


#: The narrowest invalid area (px) that may hide part of an object: a depth camera's
#: dropout along an edge, one or two pixels wide, hides nothing.
HIDING_WIDTH = 3


def outer_invalid(valid: np.ndarray, width: int = 1) -> np.ndarray | None:
    """Bool (H, W): invalid pixels 8-connected to an invalid pixel of the frame; ``None``: none.

    With an odd ``width`` > 1, only invalid areas at least that wide count
    (a morphological opening by a ``width`` square, outside the frame counting
    as invalid): the areas joined to the frame through channels as wide, not
    the cracks that run between them.
    """
    if valid.all():
        return None
    lost = ~valid
    square = np.ones((width, width), dtype=bool)
    if width > 1:
        lost = ndimage.binary_erosion(lost, square, border_value=1)
    blobs, count = ndimage.label(lost, structure=np.ones((3, 3)))
    reaching = np.zeros(count + 1, dtype=bool)
    reaching[np.concatenate([blobs[0], blobs[-1], blobs[:, 0], blobs[:, -1]])] = True
    reaching[0] = False
    if not reaching.any():
        return None
    zone = reaching[blobs]
    return ndimage.binary_dilation(zone, square) & ~valid if width > 1 else zone


def square_dilation(mask: np.ndarray, size: int) -> np.ndarray:
    """Binary dilation of ``mask`` by a ``size`` x ``size`` square (odd; outside = False).

    Separable: a row segment, then a column segment (:func:`segment_dilation`);
    the same pixels as :func:`scipy.ndimage.binary_dilation` with that square.
    """
    return segment_dilation(segment_dilation(np.asarray(mask, dtype=bool), size, 1), size, 0)


def segment_dilation(mask: np.ndarray, size: int, axis: int) -> np.ndarray:
    """Whether any pixel of a centred segment of ``size`` (odd) along ``axis`` is in ``mask``.

    The mask framed by ``size // 2`` False pixels on either side; the OR of
    the ``size`` pixels from each one on built by doubling (1, 2, 4, ...
    pixels, then the rest as an overlapping stretch).
    """
    m = np.moveaxis(np.asarray(mask, dtype=bool), axis, -1)
    n, half = m.shape[-1], size // 2
    ahead = np.zeros(m.shape[:-1] + (n + 2 * half,), dtype=bool)
    ahead[..., half:half + n] = m
    total = n + 2 * half
    span = 1  # ahead[..., i]: any of the framed mask's pixels i .. i + span - 1
    while 2 * span <= size:
        ahead[..., :total - span] |= ahead[..., span:total].copy()
        span *= 2
    if span < size:
        rest = size - span
        ahead[..., :total - rest] |= ahead[..., rest:total].copy()
    return np.moveaxis(ahead[..., :n], -1, axis)


def _same_level(base: Surface, other: Surface, tol: float, steps: set[int], level: bool
                ) -> bool:
    """``other`` continues ``base`` (on base's extended fit, or same mean height on a level base).

    Never across a step edge between the two (``steps``: base's step
    neighbours). The mean heights are compared only where ``base`` is
    ``level`` (:func:`_level`: its fit varies by ``tol`` or less over its
    box): on a tilted table a box whose top is as high as the table's middle
    is not the table.
    """
    if other.id in steps:
        return False
    row, col = other.centroid
    if abs(base.height_at(row, col) - other.height_at(row, col)) <= tol:
        return True
    return level and abs(other.mean_height - base.mean_height) <= tol


def _level(surface: Surface, tol: float) -> bool:
    """Whether ``surface``'s fit varies by ``tol`` or less over its box (corners, centre)."""
    r0, c0, r1, c1 = surface.bbox
    rows = np.array([r0, r0, r1, r1, (r0 + r1) / 2])
    cols = np.array([c0, c1, c0, c1, (c0 + c1) / 2])
    heights = surface.height_at(rows, cols)
    return bool(np.ptp(heights) <= tol)


def find_background(surfaces: dict[int, Surface], border: set[int], rule: str, tol: float
                    ) -> set[int]:
    """Step 1: the background regions (never a holdsite).

    Parameters
    ----------
    surfaces
        Surfaces by id.
    border
        Ids of the regions touching the border (or the invalid margin around it).
    rule
        ``"lowest-border"``, ``"largest-border"`` or ``"none"``.
    tol
        Height tolerance (``step.threshold``) for regions at the same level.

    Returns
    -------
    set of int
        Background surface ids: the chosen border region and every region at
        its level.
    """
    candidates = [surfaces[i] for i in sorted(border) if i in surfaces]
    if rule == "none" or not candidates:
        return set()
    floor = BACKGROUND_MIN_FRACTION * sum(s.pixels for s in surfaces.values())
    large = [s for s in candidates if s.pixels >= floor] or candidates
    if rule == "largest-border":
        base = max(large, key=lambda s: (s.pixels, -s.mean_height, -s.id))
    else:
        base = min(large, key=lambda s: (s.mean_height, s.id))
    steps = {nb.id for nb in base.neighbors if nb.edge == "step"}
    level = _level(base, tol)
    return {s.id for s in surfaces.values()
            if s.id == base.id or _same_level(base, s, tol, steps, level)}


def _edge_kinds(surfaces: dict[int, Surface]) -> dict[tuple[int, int], str]:
    """Edge types listed in ``Surface.neighbors``, by (i, j), i < j."""
    kinds = {}
    for s in surfaces.values():
        for nb in s.neighbors:
            kinds[(min(s.id, nb.id), max(s.id, nb.id))] = nb.edge
    return kinds


def _is_step(pair: tuple[int, int], gap: float, kinds: dict[tuple[int, int], str],
             tol: float) -> bool:
    kind = kinds.get(pair)
    return kind == "step" if kind is not None else abs(gap) > tol


def _union_find_groups(ids: list[int], joins: list[tuple[int, int]]) -> dict[int, int]:
    """Connected groups of ``ids`` under ``joins``: id -> smallest id of its group."""
    parent = {i: i for i in ids}

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in joins:
        ra, rb = root(a), root(b)
        parent[max(ra, rb)] = min(ra, rb)
    return {i: root(i) for i in ids}


def find_objects(surfaces: dict[int, Surface], background: set[int],
                 gaps: dict[tuple[int, int], float], tol: float, framed: set[int], *,
                 concave_parts: bool = False) -> tuple[dict[int, int], list[ObjectInfo]]:
    """Step 2: objects (groups joined by non-step, and non-concave, edges) and which are covered.

    Parameters
    ----------
    surfaces
        Surfaces by id.
    background
        Background ids (left out).
    gaps
        Median signed gaps of neighbouring regions (:func:`step_gaps`).
    tol
        ``step.threshold``: larger gaps are steps (when ``neighbors`` is silent).
    framed
        Ids of the regions at the border: touching the image frame or near an
        invalid area joined to it (``ObjectInfo.touches_border``).
    concave_parts
        Also part regions at a ``"roof-concave"`` edge (beyond the paper:
        objects are joined by smooth and convex edges only).

    Returns
    -------
    object_of, objects
        Surface id -> object id, and the objects by id.
    """
    ids = sorted(i for i in surfaces if i not in background)
    kinds = _edge_kinds(surfaces)
    pairs = [(p, g) for p, g in gaps.items() if p[0] in ids and p[1] in ids]
    joins = [p for p, g in pairs if not _is_step(p, g, kinds, tol)
             and not (concave_parts and kinds.get(p) == "roof-concave")]
    group = _union_find_groups(ids, joins)
    numbering = {g: k + 1 for k, g in enumerate(sorted(set(group.values())))}
    object_of = {i: numbering[group[i]] for i in ids}
    covered: dict[int, set[int]] = {k: set() for k in numbering.values()}
    for (i, j), g in pairs:
        oi, oj = object_of[i], object_of[j]
        if oi != oj and _is_step((i, j), g, kinds, tol) and g != 0:
            lower, upper = (oj, oi) if g > 0 else (oi, oj)
            covered[lower].add(upper)
    objects = [_object_info(k, [surfaces[i] for i in ids if object_of[i] == k], covered[k],
                            framed) for k in sorted(covered)]
    return object_of, objects


def _object_info(oid: int, members: list[Surface], covered_by: set[int], framed: set[int]
                 ) -> ObjectInfo:
    pixels = sum(s.pixels for s in members)
    row = sum(s.pixels * s.centroid[0] for s in members) / max(pixels, 1)
    col = sum(s.pixels * s.centroid[1] for s in members) / max(pixels, 1)
    return ObjectInfo(id=oid, surfaces=tuple(s.id for s in members), pixels=pixels,
                      centroid=(row, col), covered_by=tuple(sorted(covered_by)),
                      touches_border=any(s.id in framed for s in members))


# ---------------------------------------------------------------------------
# Step 0: the workspace (beyond the paper)

#: A region is left out when less than this fraction of its pixels may be picked.
PICKABLE_FRACTION = 0.5

#: A structure at the border rises above this many times the pile's top (above the support).
STRUCTURE_RISE = 1.25


def unpickable_regions(labels: np.ndarray, pickable: np.ndarray, n: int) -> set[int]:
    """Labels with less than :data:`PICKABLE_FRACTION` of their pixels pickable."""
    total = np.bincount(labels.ravel(), minlength=n + 1)
    good = np.bincount(labels[pickable].ravel(), minlength=n + 1)
    low = (total > 0) & (good < PICKABLE_FRACTION * total)
    low[0] = False
    return set(np.flatnonzero(low).tolist())


def region_lift(labels: np.ndarray, space: Workspace, z: np.ndarray, n: int,
                ids: Any = None) -> np.ndarray:
    """Median height of each label's pixels above the support (by label), else of ``z``.

    Each label's finite heights are taken from its box
    (:func:`scipy.ndimage.find_objects`) and the median from its two middle
    order statistics (:func:`middle_value`); ``-inf`` for a label without one,
    and for those not in ``ids`` (an iterable of labels; ``None``: all).
    """
    height = space.height if space.height is not None else z
    out = np.full(n + 1, -np.inf)
    wanted = None if ids is None else set(ids)
    for k, box in enumerate(ndimage.find_objects(labels, n), start=1):
        if box is not None and (wanted is None or k in wanted):
            values = height[box][labels[box] == k]
            out[k] = middle_value(values[np.isfinite(values)])
    return out


def middle_value(values: np.ndarray) -> float:
    """Median of a 1-D array: the mean of its two middle order statistics; ``-inf`` when empty.

    The one middle value for an odd count (``0.5 * (v + v)``, as a sort's
    two middle elements give it).
    """
    if not values.size:
        return -math.inf
    lo, hi = (values.size - 1) // 2, values.size // 2
    part = np.partition(values, [lo, hi])
    return float(0.5 * (part[lo] + part[hi]))


def border_zone(valid: np.ndarray, extent: np.ndarray | None = None) -> np.ndarray:
    """Bool (H, W): pixels within :data:`ADJACENCY_RADIUS` of the frame or its invalid margin.

    With ``extent`` (the support's, :class:`~rangeseg_cli.cell.workspace.Workspace`),
    only the invalid pixels outside it count: the shadows among the items of a
    tote are no border, though a depth camera's holes join them to the frame.
    """
    zone = np.zeros(valid.shape, dtype=bool)
    k = ADJACENCY_RADIUS + 1
    zone[:k], zone[-k:], zone[:, :k], zone[:, -k:] = True, True, True, True
    outer = outer_invalid(valid)
    if outer is not None:
        if extent is not None:
            outer &= ~extent
        zone |= square_dilation(outer, 2 * k - 1)
    return zone


class ObjectMap:
    """Where step 2's objects lie in the image (beyond the paper).

    Built once for :func:`mark_structures` and :func:`covered_across_gaps`
    (the flags those set do not move an object).

    Attributes
    ----------
    owner
        int64 (H, W): each pixel's object id, 0 for none.
    boxes
        :func:`scipy.ndimage.find_objects` of ``owner``.
    """

    def __init__(self, objects: list[ObjectInfo], labels: np.ndarray) -> None:
        size = max([int(labels.max(initial=0)), *(max(o.surfaces) for o in objects)]) + 1
        member = np.zeros(size, dtype=np.int64)
        for o in objects:
            member[list(o.surfaces)] = o.id
        self.owner = member[labels]
        self.boxes: list[Any] = ndimage.find_objects(self.owner)

    @functools.cached_property
    def near(self) -> set[tuple[int, int]]:
        """Pairs of objects within :data:`STAND_REACH` px across any gap, both ways."""
        return _near_pairs(self.owner, self.boxes)


def mark_structures(objects: list[ObjectInfo], where: ObjectMap, valid: np.ndarray,
                    space: Workspace, half_width: float, on_support: np.ndarray | None,
                    walls_known: bool = False) -> list[ObjectInfo]:
    """Structures at the border, never picked (module Notes, step 0).

    The border is the image frame and the invalid pixels joined to it outside
    the support's extent (:func:`border_zone`). An object *hovers*
    (:func:`_hovering`) when the lowest of its pixels (5th percentile of
    heights above the support) lies well above whatever is under it: the
    highest top of the lower objects it comes within :data:`STAND_REACH` px
    of across any gap (:func:`_near_pairs`: an item rests on one the
    camera's shadow parts it from), else the support; the robot's arm and
    fingers, a tote's rim. An item rests on the support or on another item
    and shows its sides down to it; a tote's wall rises from the floor. The pile is the
    objects away from the border that do not hover and hold a footprint
    (their widest inscribed disc reaches ``half_width`` px). With a pile, an
    object touching the border is a structure when its top rises above
    :data:`STRUCTURE_RISE` times the pile's highest top plus the support's
    tolerance (the arm, a mount, a tote's wall or rim above the pile) or
    above its top resting on fingers alone (:func:`on_fingers_only`: the
    arm), and so is an object as high touching a
    structure (a finger seen apart from its arm). With nothing else in
    view, one touching the border is a structure when it hovers, rests on
    fingers alone, or (without a background frame:
    ``walls_known`` false) rises towards the border (its pixels at the
    border higher than its median: a tote's wall), and so is a hovering
    object touching it. In a height map (no perspective) a flat item cut by
    the frame looks like a finger: with nothing else in view it is taken
    for one (``[workspace] border_structures = false`` picks it). With
    nothing else in view, an object as high as the highest (:data:`WALL_SHARE`;
    but for those structures: the arm) that crosses the view, touching two
    opposite sides of the image frame (:func:`crossing_the_view`), is a structure
    too: an empty tote's near wall and rim seen from a camera mounted at a
    slant, whose top is level (no rise to the border) and which stands on
    the table beside the tote (no hover). Whatever else is in view, the
    objects as high as the highest (but for the arm) that, alone or
    together, ring the floor or the items on it are structures, and so is
    the floor they ring (:func:`enclosing_rings`: a tote's walls and rim
    seen whole; its floor above the table's tolerance), after the objects
    attached to structures are found (what stands on the floor is no part
    of the tote). Taken for structures too: a ring-shaped item whose hole,
    as large as it, holds a reading (a picture frame, a hoop lying flat),
    tall items that together ring a patch half as large as each, and, with
    nothing else in view, a lone item longer than the view.
    """
    height = space.height
    if height is None or on_support is None or not objects:
        return objects
    owner, boxes, near = where.owner, where.boxes, where.near
    standing = _touching(owner, on_support)
    spans = {o.id: _height_span(*_in_box(height, owner, boxes, o.id)) for o in objects}
    hover = _hovering(spans, near, space.tolerance)
    zone = border_zone(valid, space.extent)
    bordering = _present(owner[zone])
    # the widest disc counts for the pile (away from the border, not hovering), for
    # standing and for what the arm may rest on
    wide = widest_discs(owner, [o.id for o in objects], boxes)
    held = on_fingers_only(spans, near, space.tolerance,
                           {i for i in spans if wide.get(i, 0.0) < half_width}, hover)
    pile = [spans[o.id][1] for o in objects if o.id not in bordering | hover
            and wide.get(o.id, 0.0) >= half_width and np.isfinite(spans[o.id][1])]
    if pile:  # far above the pile, or above it on fingers: the arm, a mount, a wall
        high = STRUCTURE_RISE * max(pile) + space.tolerance
        above = {o.id for o in objects if spans[o.id][1] > high}
        structures = bordering & (above | {i for i in held if spans[i][1] > max(pile)})
    else:  # nothing else in view: what hovers or (a wall: the tallest) rises to the border
        above = hover
        tallest = max((spans[i][1] for i in bordering if i in spans and np.isfinite(
            spans[i][1])), default=math.inf)
        structures = {o.id for o in objects if o.id in bordering and (o.id in hover | held or (
            not walls_known and spans[o.id][1] >= WALL_SHARE * tallest and _rises_to_border(
                owner == o.id, height, zone, space.tolerance)))}
        structures |= crossing_the_view(owner, valid) & _tall(spans, structures)
    arm = (hover | held) & structures  # not to set the highest of the tote's rings
    walls, floors = enclosing_rings(owner, boxes, valid, near, _tall(spans, arm))
    structures |= walls
    structures |= _attached(objects, owner, structures, above)
    structures |= floors  # after: what lies on the floor is not attached to the tote
    return [dataclasses.replace(o, structure=o.id in structures,
                                stands=o.id in standing and wide.get(o.id, 0.0) >= half_width)
            for o in objects]


def covered_across_gaps(objects: list[ObjectInfo], where: ObjectMap, z: np.ndarray,
                        tol: float, on_support: np.ndarray | None = None
                        ) -> list[ObjectInfo]:
    """``objects`` also covered by what is higher within :data:`STAND_REACH` px of them.

    Beyond the paper (step 2, ``border_structures``). A depth camera smooths a
    depth jump into a ramp of edge pixels wider than the boundary pairs'
    reach, so an item lying on another often shares no boundary with it. Two
    objects within :data:`STAND_REACH` px of each other across any gap
    (:func:`_near_pairs`), neither a structure, are compared by the median
    heights ``z`` (above the support, when there is one) of their pixels
    within that reach of the other: the lower is covered by the higher when
    they differ by more than ``tol`` (``step.threshold``), as across a step
    edge. Not two already covered one by the other, nor two with mostly
    ``on_support`` pixels (bool, the support's) between them: side by side
    on the table. Used only on a view from above (:func:`seen_from_above`).
    """
    owner, boxes = where.owner, where.boxes
    structure = {o.id for o in objects if o.structure}
    size = 2 * STAND_REACH + 1
    extra: dict[int, set[int]] = {}
    known = {(o.id, k) for o in objects for k in o.covered_by}
    for i, j in where.near:
        if i > j or i in structure or j in structure or (i, j) in known or (j, i) in known:
            continue
        box = _grown(_union_box([boxes[i - 1], boxes[j - 1]]), STAND_REACH, owner.shape)
        a, b = owner[box] == i, owner[box] == j
        near_a, near_b = square_dilation(a, size), square_dilation(b, size)
        if on_support is not None:
            between = on_support[box][near_a & near_b & ~a & ~b]
            if between.size and np.count_nonzero(between) > between.size / 2:
                continue
        ha, hb = z[box][a & near_b], z[box][b & near_a]
        ha, hb = ha[np.isfinite(ha)], hb[np.isfinite(hb)]
        if not (ha.size and hb.size):
            continue
        gap = float(np.median(hb) - np.median(ha))
        if abs(gap) > tol:
            lower, upper = (i, j) if gap > 0 else (j, i)
            extra.setdefault(lower, set()).add(upper)
    return [dataclasses.replace(o, covered_by=tuple(sorted(set(o.covered_by) | extra[o.id])))
            if o.id in extra else o for o in objects]


#: Degrees between the sensor's axis and the support's normal up to which a view is from above.
VIEW_SLANT = 20.0


def seen_from_above(support: Plane | None) -> bool:
    """Whether the sensor looks at ``support`` within :data:`VIEW_SLANT` degrees of its normal.

    True without a plane (nothing says otherwise); either side of the plane
    (its normal points to the sensor). Without intrinsics the angle is in
    the height map's units (``units_per_pixel``, else pixels against
    height units). Beyond the paper: at a
    slant the pixels facing each other across a band of edge pixels are
    often an item's near top edge and the face it hides part of, not an
    item and the one lying on it (:func:`covered_across_gaps`).
    """
    return support is None or abs(support.normal[2]) >= math.cos(math.radians(VIEW_SLANT))


def _covered_from_above(objects: list[ObjectInfo], where: ObjectMap, z: np.ndarray,
                        space: Workspace, tol: float, on_support: np.ndarray | None
                        ) -> list[ObjectInfo]:
    """:func:`covered_across_gaps` by the heights above the support, on a view from above.

    The plane judged is the support, else the image's dominant plane that
    holds too little to be one (``space.hidden``: heaped items).
    """
    if not seen_from_above(space.support or space.hidden):
        return objects
    if space.height is None:
        return covered_across_gaps(objects, where, z, tol)
    return covered_across_gaps(objects, where, space.height, tol, on_support)


def _tall(spans: dict[int, tuple[float, float]], left_out: set[int]) -> set[int]:
    """Objects but ``left_out`` whose top reaches :data:`WALL_SHARE` of the highest of them.

    ``spans``: each object's (low, top) heights (:func:`_height_span`);
    ``left_out``: what is not to set the highest (the arm).
    """
    tops = {i: top for i, (_, top) in spans.items() if i not in left_out and np.isfinite(top)}
    highest = max(tops.values(), default=math.inf)
    return {i for i, top in tops.items() if top >= WALL_SHARE * highest}


#: A ring encloses something when at least this share of its holes holds a reading, and
#: its holes hold at least :data:`RING_SHARE` of its largest piece's pixels when several
#: objects make it (a tote's floor seen from 55 degrees off the vertical: 0.7 of its
#: near wall; gaps between items: far less), as many as its one object's when one does.
ENCLOSED_VALID, RING_SHARE = 0.5, 0.5


def enclosing_rings(owner: np.ndarray, boxes: list[Any], valid: np.ndarray,
                    pairs: set[tuple[int, int]] | None = None,
                    among: set[int] | None = None) -> tuple[set[int], set[int]]:
    """Objects of ``owner`` (0 = none) that ring other things, and their floors: a tote.

    The objects (those of ``among``; ``None``: all) fall into groups, joined
    by ``pairs`` (:func:`_near_pairs`; ``None``: each object alone). A
    group's pixels, grown by :data:`ADJACENCY_RADIUS` over the edges between
    its objects, make a ring when :data:`ENCLOSED_VALID` of their holes (what
    :func:`scipy.ndimage.binary_fill_holes` fills in the group's box, the
    image frame counting as outside) hold a reading (``valid``: a tote's
    floor, or the items on it). Its pieces are the objects that line the
    holes and reach the ring's outside; they are structures when the holes
    hold at least :data:`RING_SHARE` of the largest piece's pixels (as many
    as the piece's own when it is the only one). A tote seen whole at a
    slant parts into its rim, near wall and far wall at their creases, none
    of which closes the ring alone; an item inside, leaning on a wall, lies
    within the ring; an item outside, touching the ring, lines no hole. Not
    a thick roll of tape (its hole is smaller than it), nor items around a
    gap of no reading. Taken for structures: a picture frame lying flat,
    and items that together ring a patch at least half as large as each.
    The floors are the objects in the holes that line :data:`FLOOR_SHARE`
    of them (:func:`_floors`). ``boxes``: :func:`scipy.ndimage.find_objects`
    of ``owner``.

    Returns
    -------
    walls, floors
        The pieces of the rings, and the objects each ring stands on.
    """
    walls: set[int] = set()
    floors: set[int] = set()
    members = [k for k, b in enumerate(boxes, start=1)
               if b is not None and (among is None or k in among)]
    chosen = set(members)
    root = _union_find_groups(members, [(i, j) for i, j in pairs or () if {i, j} <= chosen])
    groups: dict[int, list[int]] = {}
    for k in members:
        groups.setdefault(root[k], []).append(k)
    for group in groups.values():
        box = _grown(_union_box([boxes[k - 1] for k in group]), ADJACENCY_RADIUS + 1,
                     owner.shape)
        crop = owner[box]
        mine = np.isin(crop, group)
        ring = square_dilation(mine, 2 * ADJACENCY_RADIUS + 1)
        inner = ndimage.binary_fill_holes(ring)
        hole = inner & ~ring
        inside = int(np.count_nonzero(hole))
        if not inside or np.count_nonzero(valid[box] & hole) < ENCLOSED_VALID * inside:
            continue
        lining = hole & square_dilation(ring, 3)
        pieces = _ring_pieces(crop, mine, inner, lining, pairs or set())
        if not pieces.size:  # the ring lines the image frame: nothing outside it in view
            continue
        sizes = np.bincount(crop[mine], minlength=int(crop.max()) + 1)
        if inside >= (RING_SHARE if pieces.size > 1 else 1.0) * sizes[pieces].max():
            walls.update(pieces.tolist())
            floors.update(_floors(crop, hole, lining))
    return walls, floors


def _ring_pieces(owner: np.ndarray, mine: np.ndarray, inner: np.ndarray, lining: np.ndarray,
                 pairs: set[tuple[int, int]]) -> np.ndarray:
    """The objects of a ring (``mine``, filled: ``inner``) that reach its outside and line it.

    An object lines the ring within ``ADJACENCY_RADIUS + 1`` px of the
    hole's ``lining``, or touching (``pairs``) two objects that do: a
    tote's far rim beyond its far wall's inner face; an item outside that
    touches the ring lines nothing.
    """
    reach = 2 * ADJACENCY_RADIUS + 3
    outer = np.unique(owner[square_dilation(~inner, 2 * reach - 1) & mine])
    lines = set(np.unique(owner[square_dilation(lining, reach) & mine]).tolist())
    return np.array([k for k in outer.tolist() if k in lines or sum(
        (k, j) in pairs for j in lines) >= 2], dtype=np.int64)


#: An object inside a ring is its floor when it lines at least this share of the ring.
FLOOR_SHARE = 0.5


def _floors(owner: np.ndarray, hole: np.ndarray, lining: np.ndarray) -> list[int]:
    """Objects of ``owner`` in ``hole`` within reach of :data:`FLOOR_SHARE` of its ``lining``.

    The lining is the hole's pixels next to the ring; an object within
    ``ADJACENCY_RADIUS + 1`` px of that share of it is the floor the ring
    stands on (a tote's floor above the table's tolerance); an item inside
    lines a wall or two. A floor in pieces (an item lying from wall to wall
    across it) is none. Each object's test works in its own box.
    """
    total = int(np.count_nonzero(lining))
    reach = 2 * ADJACENCY_RADIUS + 3
    ids = np.unique(owner[square_dilation(lining, reach) & hole])
    boxes = ndimage.find_objects(owner)
    out = []
    for k in ids[ids > 0].tolist():
        box = _grown(boxes[k - 1], ADJACENCY_RADIUS + 1, owner.shape)
        near = square_dilation(owner[box] == k, reach) & lining[box]
        if total and np.count_nonzero(near) >= FLOOR_SHARE * total:
            out.append(k)
    return out


def _union_box(boxes: list[tuple[slice, slice]]) -> tuple[slice, slice]:
    """The smallest 2-D box holding ``boxes``."""
    return (slice(min(b[0].start for b in boxes), max(b[0].stop for b in boxes)),
            slice(min(b[1].start for b in boxes), max(b[1].stop for b in boxes)))


def crossing_the_view(owner: np.ndarray, valid: np.ndarray | None = None) -> set[int]:
    """Labels of ``owner`` (0 = none) within :data:`ADJACENCY_RADIUS` of two opposite frame sides.

    The left and the right side, or the top and the bottom: a structure
    crosses the view, an item lies within it (:func:`mark_structures`).
    With ``valid`` (bool, H x W), a side reaches over the pixels of no
    reading that run from it along their row (left, right) or column (top,
    bottom): a depth camera's band of no reading along its left edge.
    """
    k = ADJACENCY_RADIUS + 1
    sides = np.zeros((4, *owner.shape), dtype=bool)  # left, right, top, bottom
    sides[0][:, :k], sides[1][:, -k:], sides[2][:k], sides[3][-k:] = True, True, True, True
    if valid is not None and not valid.all():
        lost = ~valid
        runs = (np.logical_and.accumulate(lost, axis=1),
                np.logical_and.accumulate(lost[:, ::-1], axis=1)[:, ::-1],
                np.logical_and.accumulate(lost, axis=0),
                np.logical_and.accumulate(lost[::-1], axis=0)[::-1])
        for side, run in zip(sides, runs, strict=True):
            side |= square_dilation(run, 2 * k - 1)
    near = [set(np.unique(owner[side]).tolist()) - {0} for side in sides]
    return (near[0] & near[1]) | (near[2] & near[3])


#: An object hovers when its lowest pixels lie above what is under it by this share of
#: its height over that, and by this many support tolerances (an item on another shows
#: little of its lower side: a ball on a box, 28 mm above it in a synthetic cell).
HOVER_SHARE, HOVER_TOLERANCES = 0.5, 8.0


def rests_on(span: tuple[float, float], h: float, tol: float) -> bool:
    """Whether an object of (low, top) ``span`` may rest on height ``h`` (not hover over it).

    Its lowest pixels lie above ``h`` by no more than :data:`HOVER_SHARE`
    of its top's height above ``h`` or :data:`HOVER_TOLERANCES` times
    ``tol`` (the support's tolerance): the test of :func:`_hovering` and
    :func:`on_fingers_only`.
    """
    low, top = span
    return bool(low - h <= max(HOVER_SHARE * (top - h), HOVER_TOLERANCES * tol))


def _hovering(spans: dict[int, tuple[float, float]], touching: set[tuple[int, int]],
              tol: float) -> set[int]:
    """Objects whose lowest pixels lie well above the tops of the lower objects they touch.

    ``spans``: (low, top) of each object; ``touching``: pairs of objects
    near each other (:func:`_near_pairs`), both ways. What is under an
    object is the highest top among the touching objects lower than it,
    else the support (0).
    """
    under = dict.fromkeys(spans, 0.0)
    for a, b in touching:
        for one, other in ((a, b), (b, a)):
            if one in spans and other in spans and spans[other][1] < spans[one][1]:
                under[one] = max(under[one], spans[other][1])
    return {i for i, span in spans.items() if np.isfinite(span).all() and span[1] > 2 * tol
            and not rests_on(span, under[i], tol)}


def on_fingers_only(spans: dict[int, tuple[float, float]], touching: set[tuple[int, int]],
                    tol: float, narrow: set[int], hover: set[int]) -> set[int]:
    """Objects that rest on fingers alone, not on the support nor on an item (the arm).

    ``spans``: (low, top) of each object; ``touching``: pairs of objects
    near each other (:func:`_near_pairs`; either way round); ``narrow``:
    objects too narrow to hold a footprint; ``hover``: :func:`_hovering`. An
    object rests (:func:`rests_on`) on the support's 0 or on the top of a
    lower object it touches. A finger is narrow and hovers, or is narrow and rests on fingers alone
    (transitively): what hangs from the robot's arm. So judged, the arm
    rests on its fingers (beyond the paper); an item rests on the support,
    on an item, or on a piece of one that rests on something.
    """
    under: dict[int, set[int]] = {i: set() for i in spans}
    for pair in touching:
        for a, b in (pair, pair[::-1]):
            if (a in spans and b in spans and spans[b][1] < spans[a][1]
                    and rests_on(spans[a], spans[b][1], tol)):
                under[a].add(b)

    def on_these(i: int, these: set[int]) -> bool:
        return bool(under[i]) and under[i] <= these and not rests_on(spans[i], 0.0, tol)

    narrow = narrow & spans.keys()
    fingers = narrow & hover
    grew = True
    while grew:
        new = {i for i in narrow - fingers if on_these(i, fingers)}
        fingers |= new
        grew = bool(new)
    return {i for i in spans if np.isfinite(spans[i][1]) and on_these(i, fingers)}


def _near_pairs(owner: np.ndarray, boxes: list[Any]) -> set[tuple[int, int]]:
    """Pairs of objects within :data:`STAND_REACH` px of each other, across any gap.

    A depth camera's shadows and the edges between items part an item from
    the one it rests on; what is seen that near is what it may rest on.
    Each object's :func:`_touching` is taken in its box grown by the reach:
    the cost follows the boxes' areas.
    """
    pairs = set()
    for i, box in enumerate(boxes, start=1):
        if box is not None:
            crop = owner[_grown(box, STAND_REACH, owner.shape)]
            pairs |= {(i, j) for j in _touching(crop, crop == i) if j != i}
    return pairs


def _grown(box: tuple[slice, slice], reach: int, shape: tuple[int, ...]
           ) -> tuple[slice, slice]:
    """A 2-D box of :func:`scipy.ndimage.find_objects` grown by ``reach`` px within ``shape``."""
    return (slice(max(box[0].start - reach, 0), min(box[0].stop + reach, shape[0])),
            slice(max(box[1].start - reach, 0), min(box[1].stop + reach, shape[1])))


def _in_box(values: np.ndarray, owner: np.ndarray, boxes: list[Any], oid: int
            ) -> tuple[np.ndarray, np.ndarray]:
    """``values`` and the mask of object ``oid`` in its box (``boxes``: of ``owner``)."""
    box = boxes[oid - 1] if oid <= len(boxes) else None
    if box is None:
        return values[:0, :0], np.zeros((0, 0), dtype=bool)
    return values[box], owner[box] == oid


def _height_span(height: np.ndarray, mask: np.ndarray) -> tuple[float, float]:
    """(5th, 95th) percentiles of ``height`` over ``mask`` (NaN when none is finite)."""
    values = height[mask]
    values = values[np.isfinite(values)]
    if not values.size:
        return math.nan, math.nan
    low, top = np.percentile(values, [5, 95])
    return float(low), float(top)


def widest_discs(owner: np.ndarray, ids: list[int], boxes: list[Any] | None = None
                 ) -> dict[int, float]:
    """Radius in px of the widest disc inside each object's pixels (its clearance).

    The distance of each pixel of an object to the nearest pixel that is not
    in its interior (:func:`same_neighbours`: a pixel whose neighbour belongs
    to another object is a border), taken in the object's box grown by one
    pixel (within the image; ``boxes``: :func:`scipy.ndimage.find_objects`
    of ``owner`` when known): the nearest such pixel of the whole image is
    one of the box's (a nearer pixel off the object is always a border), so
    the distances are those of the whole image's transform.
    """
    if not ids:
        return {}
    boxes = ndimage.find_objects(owner) if boxes is None else boxes
    out = {}
    for i in ids:
        box = boxes[i - 1] if i <= len(boxes) else None
        if box is None:
            out[i] = 0.0
            continue
        crop = owner[_grown(box, 1, owner.shape)]
        mine = crop == i
        edt = ndimage.distance_transform_edt(mine & same_neighbours(crop))
        out[i] = float(edt[mine].max())
    return out


def same_neighbours(owner: np.ndarray) -> np.ndarray:
    """Bool: pixels whose 4-neighbours (those in the array) all have their value."""
    same = np.ones(owner.shape, dtype=bool)
    across = owner[1:] != owner[:-1]
    same[1:] &= ~across
    same[:-1] &= ~across
    along = owner[:, 1:] != owner[:, :-1]
    same[:, 1:] &= ~along
    same[:, :-1] &= ~along
    return same


#: With nothing in view, a wall rises to the border and is about the tallest there.
WALL_SHARE = 0.8

#: Pixels within which an object touches the support or a structure.
STAND_REACH = 6


def _touching(owner: np.ndarray, mask: np.ndarray) -> set[int]:
    """Objects (``owner`` ids) within :data:`STAND_REACH` pixels of ``mask``."""
    return _present(owner[square_dilation(mask, 2 * STAND_REACH + 1)])


def _attached(objects: list[ObjectInfo], owner: np.ndarray, structures: set[int],
              hover: set[int]) -> set[int]:
    """Objects of ``hover`` touching a structure, transitively (a gripper's fingers)."""
    found: set[int] = set()
    frontier = set(structures)
    while frontier:
        near = _touching(owner, np.isin(owner, list(frontier)))
        frontier = {o.id for o in objects if o.id in near and o.id in hover
                    and o.id not in structures | found}
        found |= frontier
    return found


def _rises_to_border(mine: np.ndarray, height: np.ndarray, zone: np.ndarray, tol: float
                     ) -> bool:
    """Whether an object's pixels at the border stand higher than its median (a wall)."""
    edge = height[mine & zone]
    edge = edge[np.isfinite(edge)]
    if not edge.size:
        return False
    return float(np.median(edge)) > float(np.nanmedian(height[mine])) + tol


def _unit_note(config: Config) -> str:
    """What the reason says when ``footprint_mm`` cannot apply (:func:`footprint_fallback`)."""
    why = footprint_fallback(config)
    return f" ({why})" if why else ""


def footprint_fallback(config: Config) -> str:
    """Why ``holdsite.footprint_mm`` cannot size the footprint ("" when it can or is unset).

    The cup's size in mm becomes pixels only with camera intrinsics, metric
    depth and depth along the optical axis (:func:`footprint_in_mm`); without
    them the search uses ``holdsite.size`` in pixels, which on a real frame is
    seldom the cup (Sec. VII: the window is the gripper's footprint).
    """
    hold = config.holdsite
    lacking = _footprint_lacks(config.input)
    if not any(hold.footprint_mm) or not lacking:
        return ""
    return (f"holdsite.footprint_mm = {list(hold.footprint_mm)} needs {' and '.join(lacking)}:"
            f" the footprint is holdsite.size, {hold.size[0]}x{hold.size[1]} px")


def sub_pixel_footprint(config: Config, depth: float) -> str:
    """Why no site can be sought: ``footprint_mm`` spans less than a pixel ("" when not).

    ``depth`` (depth units) is the frame's median. A cup smaller than one
    pixel at the frame's depth is no camera over a bin: the depth unit
    (``[input] metres_per_unit``) or the cup's size is wrong, and a site
    found with the depth unit wrong would send the gripper metres or
    kilometres away. So the holdsite is ``None`` with this reason.
    """
    camera = config.input
    if not footprint_in_mm(config.holdsite, camera) or depth <= 0:
        return ""
    mm = depth * camera.metres_per_unit * 1000.0
    short = min(config.holdsite.footprint_mm[0] * camera.fy,
                config.holdsite.footprint_mm[1] * camera.fx) / mm
    if short >= 1.0:
        return ""
    return (f"no site sought: holdsite.footprint_mm = {list(config.holdsite.footprint_mm)} "
            f"spans {short:.3g} px at the frame's median depth of {mm / 1000.0:.3g} m "
            f"([input] metres_per_unit = {camera.metres_per_unit:g}); a cup smaller than a "
            "pixel means a wrong unit: check --preset, [input] metres_per_unit and "
            "holdsite.footprint_mm")


def _footprint_lacks(camera: InputConfig) -> list[str]:
    """What ``footprint_mm`` needs and ``camera`` lacks (none: it applies when set)."""
    return [what for what, missing in (
        ("camera intrinsics (--intrinsics or [input] intrinsics)", not camera.has_intrinsics),
        ("metric depth ([input] metres_per_unit)", camera.metres_per_unit <= 0),
        ("depth along the optical axis ([input] larger_is_closer = false)",
         camera.larger_is_closer)) if missing]


def carve_pickable(z: np.ndarray, labels: np.ndarray, pickable: np.ndarray,
                   on_support: np.ndarray | None, n: int, area: int, config: Config,
                   backend: Backend, low: set[int] | None = None
                   ) -> tuple[np.ndarray, list[Surface], dict[int, int]]:
    """Pickable pieces of regions the workspace leaves out, as surfaces of their own.

    Growing can join a thin item to the floor (its contour not closed); the
    workspace leaves that region out (most of it lies on the support), but
    the item's pixels are pickable. Each 8-connected piece of pickable
    pixels of such a region, of ``area`` pixels or more (a footprint), gets
    a new label (``n + 1``, ...) and a :class:`Surface` fitted to it.

    Returns
    -------
    labels, surfaces, origin
        The labels with the pieces, their surfaces, and each piece's region
        in the input ``labels`` (new id -> old id); unchanged and empty when
        nothing is carved.
    """
    low = unpickable_regions(labels, pickable, n) if low is None else low
    if not low:
        return labels, [], {}
    is_low = np.zeros(n + 1, dtype=bool)
    is_low[list(low)] = True
    pieces, count = ndimage.label(is_low[labels] & pickable, structure=np.ones((3, 3)))
    sizes = np.bincount(pieces.ravel(), minlength=count + 1)
    keep = np.flatnonzero(sizes >= max(area, 1))
    keep = keep[(keep > 0) & _lying_on(pieces, count, on_support, np.isfinite(z))[keep]]
    if not keep.size:
        return labels, [], {}
    new_id = np.zeros(count + 1, dtype=labels.dtype)
    new_id[keep] = n + 1 + np.arange(keep.size)
    mine = new_id[pieces]
    only = np.where(mine > 0, mine, 0)
    carved = describe_surfaces(z, only, config, backend=backend)
    rows, cols = np.nonzero(only)
    first = np.unique(only[rows, cols], return_index=True)[1]
    origin = {int(only[rows[k], cols[k]]): int(labels[rows[k], cols[k]]) for k in first}
    return np.where(mine > 0, mine, labels), carved, origin


#: A carved piece lies on the support when this share of the valid pixels around it is on it.
ON_SUPPORT_SHARE = 0.6


def _lying_on(pieces: np.ndarray, count: int, on_support: np.ndarray | None,
              valid: np.ndarray) -> np.ndarray:
    """Bool (count + 1,): pieces ringed mostly by the support (:data:`ON_SUPPORT_SHARE`).

    An item on a tote's floor is ringed by the floor; the rounded band where
    the floor meets a wall has the wall on one side. Counted over the valid
    pixels up to 3 px around each piece (not the shadows).
    """
    if on_support is None:
        return np.ones(count + 1, dtype=bool)
    near = ndimage.grey_dilation(pieces, size=(7, 7))
    ring = (pieces == 0) & (near > 0) & valid
    total = np.bincount(near[ring], minlength=count + 1)
    on = np.bincount(near[ring & on_support], minlength=count + 1)
    return on >= ON_SUPPORT_SHARE * np.maximum(total, 1)


def _named_as_labelled(objects: list[ObjectInfo], origin: dict[int, int]) -> list[ObjectInfo]:
    """Objects with carved pieces named by their region in the label image."""
    if not origin:
        return objects
    return [dataclasses.replace(o, surfaces=tuple(sorted({origin.get(i, i) for i in o.surfaces})))
            for o in objects]


def floating_objects(objects: list[ObjectInfo]) -> set[int]:
    """Objects that neither stand on the support nor lie on one that does (transitively).

    An object lies on another when it is higher across a step edge between
    them, or across a band of edge pixels (``covered_by``; the latter,
    :func:`covered_across_gaps`, can also take a hovering object near a
    higher item for lying on it). A floating object hangs in the air: the robot's
    finger seen without the arm that holds it. The search tries it last.
    """
    supported = {o.id for o in objects if o.stands}
    grew = True
    while grew:
        grew = False
        for o in objects:
            new = set(o.covered_by) - supported
            if o.id in supported and new:
                supported |= new
                grew = True
    return {o.id for o in objects} - supported


#: Share of a frame's pixels behind the background frame above which the reason says so.
BEHIND_NOTE = 0.5


def _background_note(space: Workspace) -> str:
    """What the reason adds when most of the frame lies behind its background frame."""
    if space.behind <= BEHIND_NOTE:
        return ""
    return (f"; the frame lies behind the background frame at {space.behind:.0%} of the "
            "pixels both read: is the background of another camera, pose or depth unit?")


def _hidden_support_note(space: Workspace) -> str:
    """What the reason adds when, without a background frame, the floor was mostly hidden."""
    if space.hidden is None:
        return ""
    return (f"; without a background frame the image's dominant plane holds only "
            f"{space.hidden.inliers:.0%} of the valid pixels (the floor mostly hidden or "
            "unread), too few to take it for the support, so no support test applies and "
            "objects touching the image border are picked only when none in view can be; "
            "give a frame of the empty scene (--background)")


def _nothing_to_pick(by_id: dict[int, Surface], objects: list[ObjectInfo],
                     space: Workspace) -> str:
    """The reason of an image with no candidate object."""
    if not by_id:
        return "nothing to pick: no surfaces in the segmentation"
    structures = sum(o.structure for o in objects)
    if space.support is not None:
        text = ("nothing to pick: nothing of a footprint's area stands on the support (the "
                f"dominant plane, within {space.tolerance:.3g} depth units)")
    else:
        text = "nothing to pick: every surface lies in the background or outside the workspace"
    if structures:
        text += (f", besides {structures} structure(s) (a tote's wall or rim, the robot's "
                 "fingers) that are never picked")
    return text


# ---------------------------------------------------------------------------
# Step 4: footprints and window statistics


def footprint(size: tuple[int, int], angle: float) -> np.ndarray:
    """Boolean structuring element of a ``size`` (rows, cols) rectangle rotated by ``angle``.

    Parameters
    ----------
    size
        (rows, cols) of the unrotated footprint.
    angle
        Degrees, counter-clockwise as displayed (rows grow downwards); 0 keeps
        the footprint's rows along image rows.

    Returns
    -------
    numpy.ndarray
        bool (k, k), k odd: pixel centres inside the rotated rectangle.
    """
    rows, cols = size
    t = math.radians(angle)
    cos, sin = math.cos(t), math.sin(t)
    if abs(sin) < 1e-12 or abs(cos) < 1e-12:  # axis-aligned: exact rectangle
        shape = (rows, cols) if abs(sin) < 1e-12 else (cols, rows)
        return np.ones(shape, dtype=bool)
    half = int(math.ceil(math.hypot(rows, cols) / 2))
    dr, dc = np.mgrid[-half: half + 1, -half: half + 1].astype(np.float64)
    along = dc * cos - dr * sin   # along the footprint's rows (its column axis)
    across = dc * sin + dr * cos  # along the footprint's columns (its row axis)
    fp = (np.abs(along) <= cols / 2 + 1e-9) & (np.abs(across) <= rows / 2 + 1e-9)
    keep_r, keep_c = np.nonzero(fp.any(axis=1))[0], np.nonzero(fp.any(axis=0))[0]
    trim = min(keep_r[0], keep_c[0], len(fp) - 1 - keep_r[-1], len(fp) - 1 - keep_c[-1])
    return fp[trim: len(fp) - trim, trim: len(fp) - trim]


def window_mean(a: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Mean of ``a`` over the footprint centred at each pixel (zeros outside the image).

    A full rectangle uses a box filter; a small rotated footprint sums shifted
    copies (one per footprint pixel); a large one is an FFT convolution. All
    are vectorised over the image.
    """
    if fp.all():
        return ndimage.uniform_filter(a, size=fp.shape, mode="constant", cval=0.0)
    if fp.sum() > FFT_FOOTPRINT_PIXELS:
        return fft_correlate(a, fp.astype(np.float64)) / fp.sum()
    kr, kc = fp.shape[0] // 2, fp.shape[1] // 2
    padded = np.pad(a, ((kr, kr), (kc, kc)))
    h, w = a.shape
    total = np.zeros_like(a)
    for dr, dc in zip(*np.nonzero(fp), strict=True):
        total += padded[dr: dr + h, dc: dc + w]
    return total / fp.sum()


def window_ar_std(ar: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Standard deviation of the 2-D AR over the footprint at each pixel (Sec. VII).

    Parameters
    ----------
    ar
        float64 (H, W) AR of :func:`~rangeseg_cli.stages.edges.ar_2d`; NaN (invalid)
        counts as 0, and such windows are never candidates anyway.
    fp
        Boolean footprint (the window means of :func:`window_mean`).

    Returns
    -------
    numpy.ndarray
        float64 (H, W) ``sqrt(E[AR^2] - E[AR]^2)`` over the window.
    """
    a = np.where(np.isnan(ar), 0.0, ar)
    m1 = window_mean(a, fp)
    m2 = window_mean(a * a, fp)
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0))


def erode(mask: np.ndarray, fp: np.ndarray, *, backend: Backend = "auto") -> np.ndarray:
    """Centres where the footprint lies wholly on ``mask`` (binary erosion, outside = False).

    A full rectangle is eroded as a running minimum
    (:func:`scipy.ndimage.minimum_filter`, which is separable: a row segment,
    then a column segment); other footprints (rotated ones) by
    :func:`erode_runs` (``backend="numpy"``: :func:`scipy.ndimage.binary_erosion`,
    the reference; the same result).
    """
    if fp.all():
        out = ndimage.minimum_filter(mask.view(np.uint8), size=fp.shape, mode="constant",
                                     cval=0)
        return out.view(bool)
    if backend == "numpy":
        return ndimage.binary_erosion(mask, structure=fp, border_value=0)
    return erode_runs(mask, fp)


def erode_runs(mask: np.ndarray, fp: np.ndarray) -> np.ndarray:
    """Binary erosion of ``mask`` by ``fp`` (outside = False), one run of ``fp`` at a time.

    Each run of consecutive pixels of a footprint line (a row, or a column
    when it has fewer non-empty columns) fits at a centre when the line of
    ``mask`` it falls on has as many consecutive True pixels from the run's
    start: one lookup in the lengths of the True runs of ``mask`` per
    footprint run, instead of one pass per footprint pixel
    (:func:`scipy.ndimage.binary_erosion`: 1.6 s for a 255x3 footprint
    rotated by 15 degrees on a 400x400 crop). The outermost runs go first,
    and an erosion that leaves no centre stops there: a footprint longer
    than the surface is ruled out after a run or two.

    Returns
    -------
    numpy.ndarray
        bool of ``mask``'s shape, identical to
        ``scipy.ndimage.binary_erosion(mask, structure=fp, border_value=0)``.
    """
    mask = np.asarray(mask, dtype=bool)
    fp = np.asarray(fp, dtype=bool)
    if np.count_nonzero(fp.any(axis=0)) < np.count_nonzero(fp.any(axis=1)):
        return np.ascontiguousarray(erode_runs(mask.T, fp.T).T)
    h, w = mask.shape
    kr, kc = fp.shape[0] // 2, fp.shape[1] // 2
    # run_length[r, c]: consecutive True pixels of mask's row r from column c on (0 outside)
    lengths = np.zeros((h + fp.shape[0], w + fp.shape[1]), dtype=np.int64)
    cols = np.broadcast_to(np.arange(w), mask.shape)
    stops = np.minimum.accumulate(np.where(mask, w, cols)[:, ::-1], axis=1)[:, ::-1]
    lengths[kr: kr + h, kc: kc + w] = stops - cols
    out = np.ones(mask.shape, dtype=bool)
    for k, (i, start, size) in enumerate(_footprint_runs(fp.shape, fp.tobytes())):
        out &= lengths[i: i + h, start: start + w] >= size
        if k % 8 in (0, 1) and not out.any():
            break
    return out


@functools.lru_cache(maxsize=1024)
def _footprint_runs(shape: tuple[int, ...], data: bytes) -> list[tuple[int, int, int]]:
    """(row, first column, length) of each run of True in a footprint's rows, outermost first.

    The footprint is given as its shape and bool bytes (cached: each angle's
    footprint serves every surface).
    """
    fp = np.frombuffer(data, dtype=bool).reshape(shape)
    padded = np.zeros((fp.shape[0], fp.shape[1] + 2), dtype=np.int8)
    padded[:, 1:-1] = fp
    step = np.diff(padded, axis=1)
    rows, starts = np.nonzero(step == 1)
    _, ends = np.nonzero(step == -1)
    centre = fp.shape[0] // 2
    order = np.argsort(-np.abs(rows - centre), kind="stable")
    return [(int(rows[k]), int(starts[k]), int(ends[k] - starts[k])) for k in order]


def clearance_map(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance of each pixel to the nearest pixel off ``mask`` (step 5's clearance).

    Parameters
    ----------
    mask
        bool (h, w) with a border of False (a padded crop of one surface).

    Returns
    -------
    numpy.ndarray
        float64 (h, w) distances in pixels, 0 off the mask
        (:func:`scipy.ndimage.distance_transform_edt`).
    """
    return ndimage.distance_transform_edt(mask)


def _window_sums(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """``sum_k kernel[k] a[p + k - centre]`` at each pixel p (zeros outside the image)."""
    if kernel.size > FFT_FOOTPRINT_PIXELS:
        return fft_correlate(a, kernel)
    return ndimage.correlate(a, kernel, mode="constant", cval=0.0)


def fft_correlate(a: np.ndarray, kernel: np.ndarray) -> np.ndarray:
    """:func:`scipy.ndimage.correlate` of ``a`` with ``kernel`` (odd sides, zeros outside) by FFT.

    The values of ``scipy.signal.fftconvolve(a, kernel[::-1, ::-1], mode="same")``
    (real FFTs of the padded full size, a fast length per axis), from
    :mod:`scipy.fft` alone: importing :mod:`scipy.signal` costs about 0.5 s, once
    per process, which a run of one camera frame would otherwise spend here
    (:mod:`scipy.fft`, about 30 ms, is imported here too: only runs that need it).
    """
    from scipy import fft as sp_fft

    full = [n + k - 1 for n, k in zip(a.shape, kernel.shape, strict=True)]
    fast = [sp_fft.next_fast_len(n, True) for n in full]
    spectrum = sp_fft.rfft2(a, fast) * sp_fft.rfft2(kernel[::-1, ::-1], fast)
    out = sp_fft.irfft2(spectrum, fast)
    r0, c0 = (kernel.shape[0] - 1) // 2, (kernel.shape[1] - 1) // 2  # fftconvolve's "same"
    return np.ascontiguousarray(out[r0: r0 + a.shape[0], c0: c0 + a.shape[1]])


def window_flat_rms(z: np.ndarray, fp: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
    """RMS residual of the least-squares plane of ``z`` over the footprint at each pixel.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    fp
        Boolean footprint (odd sides).
    at
        bool (H, W): the pixels wanted (NaN elsewhere), or ``None``: all.

    Returns
    -------
    numpy.ndarray
        float64 (H, W); NaN where a footprint pixel is invalid or outside.

    Notes
    -----
    The normal equations of ``z = a + b x + c y`` over the footprint (x, y
    the offsets from its centre) have a constant matrix; only the moments
    ``sum z, sum x z, sum y z, sum z^2`` vary, each a correlation of the
    image with a fixed kernel. The heights are taken from their median
    first, so that the squares do not cancel. With ``at`` and a footprint
    that is correlated directly (not by FFT), the moments are summed at
    those pixels only (:func:`sums_at`, the same bits), and a window is full
    where the footprint fits on the valid pixels (:func:`erode`: then the
    count of valid pixels under it is the footprint's).
    """
    valid = np.isfinite(z)
    base = float(np.median(z[valid])) if valid.any() else 0.0
    zc = np.where(valid, z - base, 0.0)
    w = fp.astype(np.float64)
    y, x = np.indices(fp.shape, dtype=np.float64)
    y -= fp.shape[0] // 2
    x -= fp.shape[1] // 2
    n = w.sum()
    a = np.array([[n, (w * x).sum(), (w * y).sum()],
                  [(w * x).sum(), (w * x * x).sum(), (w * x * y).sum()],
                  [(w * y).sum(), (w * x * y).sum(), (w * y * y).sum()]])
    kernels = (w, w * x, w * y)
    if at is None or w.size > FFT_FOOTPRINT_PIXELS:
        moments = [_window_sums(zc, k) for k in kernels]
        squares = _window_sums(zc * zc, w)
        full = _window_sums(valid.astype(np.float64), w) >= n - 0.5
    else:  # a window is full where the footprint lies wholly on valid pixels
        rows, cols = np.nonzero(at)
        pixels = (rows, cols)
        moments = [sums_at(zc, k, at, pixels) for k in kernels]
        squares = sums_at(zc * zc, w, at, pixels)
        full = erode(valid, fp) & at
    b = np.stack(moments, axis=-1)
    coef = b @ np.linalg.pinv(a).T
    rss = squares - np.einsum("...i,...i->...", b, coef)
    return np.where(full, np.sqrt(np.maximum(rss, 0.0) / n), np.nan)


def pixel_sums(a: np.ndarray, kernel: np.ndarray, rows: np.ndarray, cols: np.ndarray
               ) -> np.ndarray:
    """:func:`scipy.ndimage.correlate` of ``a`` (zeros outside) at the pixels ``(rows, cols)``.

    The same bits: the products of the kernel's non-zero weights (``|w| >
    eps``, row by row) and the values under them, added one after the other
    from 0, as scipy does at each pixel.

    Parameters
    ----------
    a
        float64 (H, W).
    kernel
        float64 (kr, kc), odd sides, centred.
    rows, cols
        int (N,) pixels of ``a``.

    Returns
    -------
    numpy.ndarray
        float64 (N,).
    """
    kr, kc = kernel.shape[0] // 2, kernel.shape[1] // 2
    padded = np.pad(a, ((kr, kr), (kc, kc)))
    dr, dc = np.nonzero(np.abs(kernel) > np.finfo(np.float64).eps)
    flat = (rows[None, :] + dr[:, None]) * padded.shape[1] + cols[None, :] + dc[:, None]
    terms = np.zeros((dr.size + 1, rows.size))
    np.multiply(padded.ravel()[flat], kernel[dr, dc][:, None], out=terms[1:])
    return np.cumsum(terms, axis=0)[-1]


#: :func:`sums_at` sums pixel by pixel (:func:`pixel_sums`) when the pixels wanted are
#: fewer than this share of their box: each costs about as much as ten of a correlation.
PIXEL_SUMS_SHARE = 0.1


def sums_at(a: np.ndarray, kernel: np.ndarray, at: np.ndarray,
            pixels: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """:func:`scipy.ndimage.correlate` of ``a`` (zeros outside), right at the pixels ``at``.

    The correlation of the box of ``at`` grown by the kernel's half sides
    (within ``a``: the sums there see the same values, added in the same
    order), or, for few pixels, :func:`pixel_sums`. Elsewhere zeros, or the
    box's sums: not to be read. ``pixels``: ``np.nonzero(at)`` when known.
    """
    rows, cols = np.nonzero(at) if pixels is None else pixels
    out = np.zeros(a.shape)
    if not rows.size:
        return out
    kr, kc = kernel.shape[0] // 2, kernel.shape[1] // 2
    box = (slice(max(int(rows.min()) - kr, 0), int(rows.max()) + kr + 1),
           slice(max(int(cols.min()) - kc, 0), int(cols.max()) + kc + 1))
    sub = a[box]
    if rows.size < PIXEL_SUMS_SHARE * sub.size:
        out[rows, cols] = pixel_sums(a, kernel, rows, cols)
    else:
        out[box] = ndimage.correlate(sub, kernel, mode="constant", cval=0.0)
    return out


#: Beyond the paper's noise range the bound on a window's AR standard deviation grows
#: by this many times the AR spread of the noise above that range (Step 4).
FLAT_AR_NOISE = 2.0


@functools.cache
def ar_noise_std() -> float:
    """Standard deviation of the 2-D AR (Step 4) of Gaussian noise of sigma 1 alone.

    ``sqrt(gain (1 - 2 / pi))``: AR is ``|(G - delta) * z|``, of which noise
    keeps the power ``gain`` (the "sum" of Sec. IV-B for the 5x5 Gaussian
    of sigma 1, 0.758), and ``|X|`` of a normal X has the variance
    ``(1 - 2 / pi) var(X)``: 0.525.
    """
    g = np.outer(gaussian_taps(1.0, 5), gaussian_taps(1.0, 5))
    g[2, 2] -= 1.0
    return math.sqrt(float(np.sum(g * g)) * (1.0 - 2.0 / math.pi))


def ar_std_limit(cfg: HoldsiteConfig, camera: InputConfig, noise: float,
                 units_per_pixel: float) -> float:
    """The bound on a window's AR standard deviation (Step 4).

    ``max_ar_std``; with ``[input] auto_thresholds``, plus
    :data:`FLAT_AR_NOISE` times :func:`ar_noise_std` times the noise above the
    paper's range (``noise`` less :data:`~rangeseg_cli.stages.noise.PAPER_NOISE`
    times the image's :func:`~rangeseg_cli.stages.noise.paper_scale`, depth
    units): no step where the range ends. To 3 decimals.
    """
    excess = noise - PAPER_NOISE * paper_scale(units_per_pixel)
    if not camera.auto_thresholds or excess <= 0:
        return cfg.max_ar_std
    return round(cfg.max_ar_std + FLAT_AR_NOISE * ar_noise_std() * excess, 3)


def flat_limit(cfg: HoldsiteConfig, camera: InputConfig, noise: float) -> float:
    """``max_flat_rms``, or its default: 2 x noise + 1 unit (+ 1 mm with metric depth).

    ``max_flat_rms`` at its largest allowed value (``--preset paper``) is no limit: inf.
    """
    if cfg.max_flat_rms >= MAX_DEPTH:
        return math.inf
    if cfg.max_flat_rms > 0:
        return cfg.max_flat_rms
    floor = 1.0
    if camera.has_intrinsics and camera.metres_per_unit > 0:
        floor = 0.001 / camera.metres_per_unit
    return 2.0 * max(noise, 0.0) + floor


#: Margin of the heights around a crop for its AR: the 5x5 Gaussian's half-width.
AR_MARGIN = 2


def footprint_in_mm(cfg: HoldsiteConfig, camera: InputConfig) -> bool:
    """Whether ``footprint_mm`` applies: set, with intrinsics and metric depth."""
    return any(cfg.footprint_mm) and not _footprint_lacks(camera)


def footprint_pixels(cfg: HoldsiteConfig, camera: InputConfig, depth: float
                     ) -> tuple[int, int]:
    """The footprint (rows, cols) in pixels: ``size``, or ``footprint_mm`` at ``depth``.

    A side of ``L`` mm at depth ``d`` mm spans ``L f / d`` pixels (pinhole);
    rounded to the nearest odd count, 1 to 255. ``depth`` is in depth units.
    """
    if not footprint_in_mm(cfg, camera) or depth <= 0:
        return cfg.size
    mm = depth * camera.metres_per_unit * 1000.0
    return (odd_pixels(cfg.footprint_mm[0], camera.fy, mm),
            odd_pixels(cfg.footprint_mm[1], camera.fx, mm))



@dataclass
class _Scene:
    """Per-image inputs of the search.

    The 2-D AR (Sec. VII) is computed per surface crop, on demand, from the
    heights ``z`` (see :meth:`ar`).
    """

    labels: np.ndarray
    valid: np.ndarray
    z: np.ndarray
    cfg: HoldsiteConfig
    angles: tuple[float, ...]
    backend: Backend = "auto"
    camera: InputConfig = field(default_factory=InputConfig)
    flat_limit: float = math.inf
    up: Vector | None = None
    _footprints: dict[float, np.ndarray] = field(default_factory=dict)
    _sized: dict[tuple[int, int], _Scene] = field(default_factory=dict)
    _ar_area: int = 0
    _ar_whole: np.ndarray | None = None

    def for_surface(self, s: Surface) -> _Scene:
        """The scene with the footprint in pixels at ``s``'s depth (``footprint_mm``)."""
        size = footprint_pixels(self.cfg, self.camera, -s.mean_height)
        if size == self.cfg.size:
            return self
        if size not in self._sized:
            cfg = dataclasses.replace(self.cfg, size=size)
            self._sized[size] = _Scene(self.labels, self.valid, self.z, cfg, _angles(cfg),
                                       self.backend, self.camera, self.flat_limit, self.up)
        return self._sized[size]

    def footprint(self, angle: float) -> np.ndarray:
        if angle not in self._footprints:
            self._footprints[angle] = footprint(self.cfg.size, angle)
        return self._footprints[angle]

    def ar(self, sl: tuple[slice, slice]) -> np.ndarray:
        """:func:`~rangeseg_cli.stages.edges.ar_2d` of the image, in the crop ``sl``.

        Computed on the crop grown by :data:`AR_MARGIN`, which is exact (equal
        to the whole image's AR: the 5x5 mask sees the same heights, and
        ``correlate1d`` adds each pixel's taps alike wherever it lies); once
        the crops asked for would add up to more than the image, the whole
        image's AR is computed once and sliced instead.
        """
        h, w = self.z.shape
        m = AR_MARGIN
        r0, r1 = max(sl[0].start - m, 0), min(sl[0].stop + m, h)
        c0, c1 = max(sl[1].start - m, 0), min(sl[1].stop + m, w)
        self._ar_area += (r1 - r0) * (c1 - c0)
        if self._ar_whole is None and self._ar_area > h * w:
            self._ar_whole = ar_2d(self.z, backend=self.backend)
        if self._ar_whole is not None:
            return self._ar_whole[sl]
        ar = ar_2d(self.z[r0:r1, c0:c1], backend=self.backend)
        return ar[sl[0].start - r0: sl[0].stop - r0, sl[1].start - c0: sl[1].stop - c0]


@dataclass
class _Hits:
    """Accepted window centres of one surface, and why other windows failed.

    ``rows``, ``cols`` and ``clearance`` list the centres where the window is
    accepted at one angle at least; ``ok`` and ``std`` (angles, h, w) hold,
    in the surface's crop (``offset`` from image coordinates), which angles
    are accepted and their AR std; ``edt`` is the crop's distance transform.
    ``poses`` keeps the (elevation, dz/dx, dz/dy) of :func:`site_poses` that
    the tilt test computed, by window (curved surfaces: Step 6 reuses them).
    """

    surface: Surface
    rows: np.ndarray
    cols: np.ndarray
    clearance: np.ndarray
    offset: tuple[int, int] = (0, 0)
    edt: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    ok: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0), bool))
    std: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    max_clearance: float = 0.0
    fitting: int = 0
    min_ar_std: float = math.inf
    steep: int = 0
    min_tilt: float = math.inf
    tilt_state: np.ndarray | None = None
    poses: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    rough: int = 0
    min_rms: float = math.inf
    scene: Any = None


def _pad1(a: np.ndarray) -> np.ndarray:
    """``np.pad(a, 1)`` (zeros around a 2-D array) without its per-call overhead."""
    out = np.zeros((a.shape[0] + 2, a.shape[1] + 2), dtype=a.dtype)
    out[1:-1, 1:-1] = a
    return out


def _crop(scene: _Scene, s: Surface, reach: int) -> tuple[tuple[slice, slice], tuple[int, int]]:
    """Slices of the surface's box grown by ``reach``, and the offset of a 1-px padded crop."""
    h, w = scene.labels.shape
    r0, c0, r1, c1 = s.bbox
    sl = (slice(max(0, r0 - reach), min(h, r1 + reach + 1)),
          slice(max(0, c0 - reach), min(w, c1 + reach + 1)))
    return sl, (sl[0].start - 1, sl[1].start - 1)


def _inside(scene: _Scene, mask: np.ndarray, angle: float, extent: tuple[int, int]
            ) -> np.ndarray:
    """Centres where the footprint at ``angle`` lies wholly on ``mask`` (binary erosion).

    ``extent`` is the (rows, cols) span of ``mask``'s pixels: a footprint
    that spans more rows or columns fits nowhere (no erosion needed).
    """
    fp = scene.footprint(angle)
    if _span(fp, 1) > extent[0] or _span(fp, 0) > extent[1]:
        return np.zeros(mask.shape, dtype=bool)
    return erode(mask, fp, backend=scene.backend)


def _span(a: np.ndarray, axis: int) -> int:
    """Rows (``axis=1``) or columns (``axis=0``) from the first to the last one with a pixel."""
    hit = np.flatnonzero(a.any(axis=axis))
    return int(hit[-1] - hit[0] + 1) if hit.size else 0


def _accept_angle(scene: _Scene, inside: np.ndarray, ar: np.ndarray, heights: np.ndarray,
                  angle: float, hits: _Hits) -> tuple[np.ndarray, np.ndarray]:
    """Step 4 at one angle: (accepted centres, AR std) in the crop.

    A window is accepted when the footprint lies wholly on the surface's
    valid pixels (``inside``: :func:`_inside`) and the AR std over it is
    small. Every window pixel of an accepted centre is inside the crop, so
    the crop's window means are exact there.
    """
    if not inside.any():
        return inside, np.full(inside.shape, np.inf)
    fp = scene.footprint(angle)
    std = window_ar_std(ar, fp)
    hits.fitting += int(inside.sum())
    hits.min_ar_std = min(hits.min_ar_std, float(std[inside].min()))
    return _flat_enough(scene, heights, fp, inside & (std <= scene.cfg.max_ar_std), hits), std


def _flat_enough(scene: _Scene, heights: np.ndarray, fp: np.ndarray, ok: np.ndarray,
                 hits: _Hits) -> np.ndarray:
    """``ok`` less the windows whose plane-fit RMS exceeds the limit (:func:`flat_limit`)."""
    if not math.isfinite(scene.flat_limit) or not ok.any():
        return ok
    rms = window_flat_rms(heights, fp, at=ok)
    flat = ok & (rms <= scene.flat_limit)
    rough = ok & ~flat
    hits.rough += int(rough.sum())
    if rough.any():
        hits.min_rms = min(hits.min_rms, float(np.nanmin(rms[rough])))
    return flat


def _pad_nan(a: np.ndarray) -> np.ndarray:
    """``a`` with one NaN pixel around it (a crop padded as :func:`_pad1` pads the masks)."""
    return np.pad(np.asarray(a, dtype=np.float64), 1, constant_values=np.nan)


def surface_windows(scene: _Scene, s: Surface) -> _Hits:
    """Step 4: every acceptable window centre on surface ``s``, unsorted.

    Parameters
    ----------
    scene
        Labels, validity, AR and the holdsite configuration.
    s
        The surface.

    Returns
    -------
    _Hits
        Accepted centres with their clearance, the accepted angles and AR
        stds, and the largest clearance, number of fitting windows and lowest
        AR std seen (for the reason when nothing is accepted).
    """
    return _drop_steep(scene, _level_windows(scene, s))


def _level_windows(scene: _Scene, s: Surface) -> _Hits:
    """:func:`surface_windows` before the tilt test."""
    rows, cols = scene.cfg.size
    sl, offset = _crop(scene, s, max(rows, cols) // 2 + 2)
    mask = _pad1((scene.labels[sl] == s.id) & scene.valid[sl])
    edt = clearance_map(mask)
    none = np.zeros(0, dtype=np.int64)
    hits = _Hits(s, none, none, none.astype(np.float64), max_clearance=float(edt.max()))
    if hits.max_clearance < (min(rows, cols) + 1) / 2:
        return hits  # not even the footprint's short side fits
    extent = (_span(mask, 1), _span(mask, 0))
    insides = []
    for angle in scene.angles:
        checkpoint()  # a stop requested meanwhile (a fine rotation_step takes long)
        insides.append(_inside(scene, mask, angle, extent))
    if not any(inside.any() for inside in insides):
        return hits  # the footprint fits nowhere on it, at any angle
    ar = _pad1(scene.ar(sl))
    heights = _pad_nan(scene.z[sl])
    accepted = []
    for angle, inside in zip(scene.angles, insides, strict=True):
        checkpoint()
        accepted.append(_accept_angle(scene, inside, ar, heights, angle, hits))
    ok = np.stack([a for a, _ in accepted])
    r, c = np.nonzero(ok.any(axis=0))
    hits.rows, hits.cols, hits.clearance = r + offset[0], c + offset[1], edt[r, c]
    hits.offset, hits.edt, hits.ok = offset, edt, ok
    hits.std = np.stack([std for _, std in accepted])
    return hits


def window_angle(scene: _Scene, hits: _Hits, k: int) -> tuple[float, float]:
    """(angle, AR std) at accepted centre ``k``: the footprint farthest from the border.

    Among the accepted angles, the one whose footprint's smallest distance to
    the surface's border (the distance transform's minimum over the
    footprint) is largest; then the lowest AR std; then the smallest angle.
    """
    r, c = hits.rows[k] - hits.offset[0], hits.cols[k] - hits.offset[1]
    if len(scene.angles) == 1 and hits.ok[0, r, c]:  # the one angle, accepted here
        return scene.angles[0], float(hits.std[0, r, c])
    best = (-math.inf, math.inf, 0.0)
    for a, angle in enumerate(scene.angles):
        if not hits.ok[a, r, c]:
            continue
        fp = scene.footprint(angle)
        fr, fc = np.nonzero(fp)
        margin = float(hits.edt[r + fr - fp.shape[0] // 2, c + fc - fp.shape[1] // 2].min())
        std = float(hits.std[a, r, c])
        if (margin, -std) > (best[0], -best[1]):
            best = (margin, std, angle)
    return best[2], best[1]


# ---------------------------------------------------------------------------
# Step 4b: tilt (holdsite.max_tilt)


def tilts(camera: InputConfig, units_per_pixel: float, rows: Any, cols: Any, heights: Any,
          gx: Any, gy: Any, up: Vector | None = None) -> np.ndarray:
    """Angles in degrees between surface normals and the support's or sensor's axis (Step 4b).

    Parameters
    ----------
    camera
        ``[input]``: with intrinsics (depth input), the normal of
        :func:`camera_pose` in the camera frame.
    units_per_pixel
        Without intrinsics, depth units per pixel of lateral size: the normal
        ``(-dz/dx, -dz/dy, units_per_pixel)`` of the height map in the frame
        ``(col s, row s, z)`` of :func:`~rangeseg_cli.cell.workspace.points`.
    rows, cols, heights, gx, gy
        Positions, heights and gradients (dz/dx, dz/dy; x = col) of the fits.
    up
        Unit normal of the support, towards the sensor, in the same frame
        (:class:`~rangeseg_cli.cell.workspace.Plane`); ``None``: the sensor's
        axis (the optical axis, or the height axis).

    Returns
    -------
    numpy.ndarray
        float64 angles in [0, 180]; NaN where the depth is not positive.
    """
    r, c, h, dx, dy = (np.asarray(a, dtype=np.float64) for a in (rows, cols, heights, gx, gy))
    if camera.has_intrinsics:  # the surface's normal towards the camera: -approach
        nx, ny, nz = (-v for v in _camera_approach(camera, r, c, h, dx, dy))
        ux, uy, uz = (0.0, 0.0, -1.0) if up is None else up
    else:
        nx, ny, nz = -dx, -dy, np.full_like(dx, units_per_pixel)
        ux, uy, uz = (0.0, 0.0, 1.0) if up is None else up
    cross = np.sqrt((ny * uz - nz * uy) ** 2 + (nz * ux - nx * uz) ** 2
                    + (nx * uy - ny * ux) ** 2)
    angle = np.degrees(np.arctan2(cross, nx * ux + ny * uy + nz * uz))
    return np.where(-h > 0, angle, np.nan) if camera.has_intrinsics else angle


def _camera_approach(cfg: InputConfig, row: Any, col: Any, height: Any, gx: Any, gy: Any
                     ) -> tuple[Any, Any, Any]:
    """Components of the camera-frame approach vector, not normalised (module Notes, step 6).

    ``-(P_u x P_v)`` of ``P(u, v) = d(u, v) r(u, v)`` with ``d = -height``: the
    normal faces the camera and the gripper moves against it. Scalars or arrays.
    """
    d, d_u, d_v = -height, -gx, -gy
    return (-cfg.fx * d_u, -cfg.fy * d_v, d + (col - cfg.cx) * d_u + (row - cfg.cy) * d_v)


#: Degrees a site's tilt may exceed ``max_tilt`` by: a level plane's fit is level
#: only to rounding (a tilt of 1e-14 degrees), and ``max_tilt = 0`` should take it.
TILT_TOLERANCE = 1e-6

#: Windows whose local pose is computed at once, first (Step 4b); doubled each time.
TILT_CHUNK = 64


def _drop_steep(scene: _Scene, hits: _Hits) -> _Hits:
    """Step 4b: the windows whose pose is tilted beyond ``holdsite.max_tilt`` do not count.

    The pose is the one a site there would report (:func:`site_poses`), so a
    site's normal is always within the limit. Where that pose is the
    surface's fit (a planar surface) every window
    is tested here at once and the steep ones dropped. A curved surface's
    local poses cost a fit each, so they are computed in the order the
    windows are wanted, a chunk at a time (:func:`_first_level`), and
    ``hits.tilt_state`` says which are known: 1 level enough, 0 too steep,
    -1 not yet computed.
    """
    if scene.cfg.max_tilt >= 90 or not hits.rows.size:
        return hits
    if _local_pose_used(scene, hits.surface):
        hits.tilt_state = np.full(hits.rows.size, -1, dtype=np.int8)
        return hits
    keep = _judge_tilts(scene, hits, np.arange(hits.rows.size))
    hits.rows, hits.cols, hits.clearance = hits.rows[keep], hits.cols[keep], hits.clearance[keep]
    return hits


def _judge_tilts(scene: _Scene, hits: _Hits, idx: np.ndarray) -> np.ndarray:
    """Whether windows ``idx`` are level enough (bool); counts the steep ones in ``hits``."""
    r, c = hits.rows[idx], hits.cols[idx]
    poses = site_poses(scene, hits.surface, r, c)
    t = tilts(scene.camera, scene.camera.units_per_pixel, r, c, *poses, up=scene.up)
    if hits.tilt_state is not None:  # the windows stay where they are: keep their poses
        hits.poses.update(zip(idx.tolist(), zip(*(p.tolist() for p in poses), strict=True),
                              strict=True))
    ok = t <= scene.cfg.max_tilt + TILT_TOLERANCE  # NaN (no depth): not level
    hits.steep += int(np.count_nonzero(~ok))
    if np.isfinite(t[~ok]).any():
        hits.min_tilt = min(hits.min_tilt, float(np.nanmin(t[~ok])))
    if hits.tilt_state is not None:
        hits.tilt_state[idx] = ok
    return ok


def _first_level(scene: _Scene, hits: _Hits, order: np.ndarray) -> int:
    """Position in ``order`` of its first window that is level enough, or -1 (Step 4b).

    Unknown tilts are computed a chunk at a time (:data:`TILT_CHUNK`,
    doubling), so a surface whose best windows are level costs one chunk.
    """
    state = hits.tilt_state
    assert state is not None  # callers take the windows as they are without a limit
    start, size = 0, TILT_CHUNK
    while start < order.size:
        chunk = order[start:start + size]
        unknown = chunk[state[chunk] < 0]
        if unknown.size:
            _judge_tilts(scene, hits, unknown)
        level = np.flatnonzero(state[chunk] == 1)
        if level.size:
            return start + int(level[0])
        start, size = start + size, size * 2
    return -1


# ---------------------------------------------------------------------------
# Step 5: choice and runners-up


def _rank_keys(hits: _Hits, centre: tuple[float, float]) -> tuple[np.ndarray, ...]:
    """Sort keys of the hits, last one first: clearance (whole pixels) down, distance up."""
    dist = np.hypot(hits.rows - centre[0], hits.cols - centre[1])
    return hits.cols, hits.rows, dist, -np.floor(hits.clearance + 1e-9)


def _rank(hits: _Hits, centre: tuple[float, float]) -> np.ndarray:
    """Order of the hits: clearance (whole pixels) down, distance to ``centre`` up."""
    return np.lexsort(_rank_keys(hits, centre))


def _best(hits: _Hits, centre: tuple[float, float]) -> int:
    """``_rank(hits, centre)[0]`` without sorting: narrow down key by key (Sec. VII).

    The keys of :func:`_rank_keys`, each computed for the hits still in the
    running only (the same values).
    """
    whole = np.floor(hits.clearance + 1e-9)  # clearance in whole pixels, largest first
    keep = np.flatnonzero(whole == whole.max())
    if keep.size > 1:
        dist = np.hypot(hits.rows[keep] - centre[0], hits.cols[keep] - centre[1])
        keep = keep[dist == dist.min()]
    for key in (hits.rows, hits.cols):
        if keep.size == 1:
            break
        values = key[keep]
        keep = keep[values == values.min()]
    return int(keep[0])


def _spread(hits: _Hits, order: np.ndarray, count: int, gap: float,
            scene: _Scene | None = None) -> list[int]:
    """Up to ``count`` indices in ``order`` whose centres are >= ``gap`` apart (greedy).

    With ``scene``, windows too steep for ``holdsite.max_tilt`` are passed
    over (their tilts computed as they come up: :func:`_first_level`).
    """
    picked: list[int] = []
    left = np.ones(order.size, dtype=bool)
    r, c = hits.rows[order], hits.cols[order]
    state = hits.tilt_state if scene is not None else None
    while len(picked) < count and left.any():
        if state is None or scene is None:
            k = int(np.argmax(left))
        else:
            rest = np.flatnonzero(left)
            pos = _first_level(scene, hits, order[rest])
            left &= state[order] != 0  # the steep ones found meanwhile
            if pos < 0:
                break
            k = int(rest[pos])
        picked.append(int(order[k]))
        left &= np.hypot(r - r[k], c - c[k]) >= gap
    return picked


def _has_level(scene: _Scene, hits: _Hits) -> bool:
    """Whether ``hits`` holds a window level enough (widest clearance tried first; Step 4b)."""
    if hits.tilt_state is None:
        return bool(hits.rows.size)
    return _first_level(scene, hits, np.argsort(-hits.clearance, kind="stable")) >= 0


def _first(scene: _Scene, hits: _Hits, centre: tuple[float, float]) -> int:
    """The best window of ``hits`` (:func:`_best`) that is level enough (Step 4b).

    On a curved surface with a tilt limit (``hits.tilt_state`` kept) whose
    widest window has room to spare, the most level of the windows whose
    clearance reaches :func:`enough_clearance` (:func:`_most_level`).
    """
    if hits.tilt_state is None:
        return _best(hits, centre)
    order = _rank(hits, centre)
    level = _most_level(scene, hits, order)
    return level if level >= 0 else int(order[_first_level(scene, hits, order)])


def enough_clearance(size: tuple[int, int]) -> float:
    """Clearance (px) beyond which a wider one is no better: the footprint's half diagonal + 2.

    A window this far from its surface's border keeps a cup on the surface
    whatever its rotation and a boundary off by two pixels (Step 5).
    """
    return math.hypot(size[0] - 1, size[1] - 1) / 2 + 2


def _most_level(scene: _Scene, hits: _Hits, order: np.ndarray) -> int:
    """Among ``order``'s windows with enough clearance, the least tilted one; else -1.

    Beyond the paper: on a curved surface the widest window may lie where the
    surface turns away from the camera (a bag's flank); a suction cup seals
    and the arm reaches more easily where it faces the camera. Tilts in
    whole degrees, then ``order``.
    """
    whole = np.floor(hits.clearance[order] + 1e-9)
    enough = math.floor(enough_clearance(scene.cfg.size))
    if whole[0] < enough:  # no room to spare: the widest window, as the paper
        return -1
    wide = order[whole >= enough]
    state = hits.tilt_state
    assert state is not None  # callers take the windows as they are without a limit
    unknown = wide[state[wide] < 0]
    if unknown.size:
        _judge_tilts(scene, hits, unknown)  # keeps their poses and states
    level = wide[state[wide] == 1]
    if not level.size:
        return -1
    height, gx, gy = (np.array(v) for v in zip(*(hits.poses[k] for k in level.tolist()),
                                                strict=True))
    tilt = tilts(scene.camera, scene.camera.units_per_pixel, hits.rows[level],
                 hits.cols[level], height, gx, gy, up=scene.up)
    return int(level[np.argmin(np.round(tilt))])


def score(clearance: float, distance: float, size: tuple[int, int], area: float) -> float:
    """Descriptive score in (0, 1): ``c / (c + h) * rho / (rho + d)`` (module Notes)."""
    h = (max(size) + 1) / 2
    rho = math.sqrt(max(area, 1.0) / math.pi)
    return clearance / (clearance + h) * rho / (rho + distance)


# ---------------------------------------------------------------------------
# Step 6: pose


def _unit(v: np.ndarray) -> Vector:
    """``v / np.linalg.norm(v)`` of a 3-vector (the norm as numpy takes it: ``sqrt(v.dot(v))``)."""
    x, y, z = (v / np.sqrt(v.dot(v))).tolist()
    return x, y, z


def camera_pose(row: float, col: float, height: float, grad: tuple[float, float],
                cfg: InputConfig) -> tuple[Vector | None, Vector | None]:
    """Camera-frame point and approach vector of a site (module Notes, step 6).

    Parameters
    ----------
    row, col
        Pixel position.
    height
        Fitted height there (``-depth`` for depth input).
    grad
        (dz/dx, dz/dy) of the fit, x = col, y = row.
    cfg
        ``[input]`` with intrinsics, ``larger_is_closer`` and ``metres_per_unit``.

    Returns
    -------
    point, approach
        ``(X, Y, Z)`` (metres when ``metres_per_unit > 0``, else depth units)
        and the unit approach vector; ``(None, None)`` without intrinsics, for
        height maps (``larger_is_closer``: no depth along the optical axis) or
        a non-positive depth.
    """
    if not cfg.has_intrinsics or cfg.larger_is_closer or -height <= 0:
        return None, None
    d = -height
    u0, v0 = col - cfg.cx, row - cfg.cy
    unit = cfg.metres_per_unit if cfg.metres_per_unit > 0 else 1.0
    point = (u0 * d / cfg.fx * unit, v0 * d / cfg.fy * unit, d * unit)
    return point, _unit(np.array(_camera_approach(cfg, row, col, height, *grad)))


#: Fewest pixels of a local quadric fit (Step 6); fewer: the surface's own fit.
LOCAL_FIT_MIN_PIXELS = 12

#: Smallest reach of a local fit (Step 6), the default 7x7 footprint's: a quadric of
#: 49 pixels (a 3x3 footprint's square) follows the noise, tens of degrees at sigma 2.
LOCAL_MIN_REACH = 7


def local_reach(size: tuple[int, int]) -> int:
    """Half side of the square of a site's local fit: the footprint's longer side, >= 7."""
    return max(max(size), LOCAL_MIN_REACH)


def local_pose(z: np.ndarray, labels: np.ndarray, s: Surface, row: int, col: int, reach: int
               ) -> tuple[float, tuple[float, float]] | None:
    """Step 6 (a curved surface): height and gradient at a site from nearby pixels.

    A least-squares quadric (Sec. V-4's model) of the valid pixels of surface
    ``s`` within ``reach`` pixels (chessboard) of ``(row, col)``, in
    coordinates centred on the site, so its constant term is the elevation
    and its linear terms the gradient there. One quadric of a whole curved
    surface approximates it everywhere at once, so at a given point it can
    be off (a noise-free sphere's top by 3.5 depth units); the local fit
    follows the surface under the gripper. The one-site case of
    :func:`local_poses` (the same bits).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    labels
        int (H, W) final regions (0 = none).
    s
        The site's surface.
    row, col
        The site (the window's centre).
    reach
        Half side of the square of pixels used.

    Returns
    -------
    tuple or None
        ``(elevation, (dz/dx, dz/dy))``, x = col, y = row; ``None`` when fewer
        than :data:`LOCAL_FIT_MIN_PIXELS` pixels are there or they do not
        determine a quadric (the caller then keeps the surface's fit).
    """
    height, gx, gy, ok = local_poses(z, labels, s, np.array([row]), np.array([col]), reach)
    if not ok[0]:
        return None
    return float(height[0]), (float(gx[0]), float(gy[0]))


#: Powers (x, y) of the quadric's terms 1, x, y, x^2, xy, y^2 (Sec. V-4).
_TERMS = ((0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2))


def local_poses(z: np.ndarray, labels: np.ndarray, s: Surface, rows: np.ndarray,
                cols: np.ndarray, reach: int
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`local_pose` at many sites of surface ``s`` at once.

    The normal equations of every site's quadric are gathered from moment
    images: sums of ``m x^a y^b`` (a + b <= 4) and ``m z x^a y^b`` (a + b <= 2)
    over the square of half side ``reach`` around each pixel, with ``m`` the
    surface's valid pixels and x, y the offsets divided by ``reach``, by two
    1-D correlations each (the square's weights are separable; the second
    only down the sites' columns). Heights are taken relative to the
    surface's mean height.

    Returns
    -------
    height, gx, gy : numpy.ndarray
        float64 (N,) elevation and gradient (dz/dx, dz/dy) at each site.
    ok : numpy.ndarray
        bool (N,): the site's pixels determine a quadric (at least
        :data:`LOCAL_FIT_MIN_PIXELS`, normal equations not singular); where
        False the other values are meaningless.
    """
    h, w = z.shape
    box = (slice(max(int(rows.min()) - reach, 0), min(int(rows.max()) + reach + 1, h)),
           slice(max(int(cols.min()) - reach, 0), min(int(cols.max()) + reach + 1, w)))
    mine = (labels[box] == s.id) & np.isfinite(z[box])
    weight = mine.astype(np.float64)
    rel = np.where(mine, z[box] - s.mean_height, 0.0)
    taps = np.arange(-reach, reach + 1, dtype=np.float64) / max(reach, 1)
    # the second (column) pass only down the sites' columns: each column is summed alone
    used, column = np.unique(cols - box[1].start, return_inverse=True)
    at = (rows - box[0].start, column.ravel())

    def moments(image: np.ndarray, degree: int) -> dict[tuple[int, int], np.ndarray]:
        across = [ndimage.correlate1d(image, taps ** a, axis=1, mode="constant")[:, used]
                  for a in range(degree + 1)]
        return {(a, b): ndimage.correlate1d(across[a], taps ** b, axis=0, mode="constant")[at]
                for a in range(degree + 1) for b in range(degree + 1 - a)}

    m, mz = moments(weight, 4), moments(rel, 2)
    gram = np.stack([np.stack([m[(ax + bx, ay + by)] for bx, by in _TERMS], axis=-1)
                     for ax, ay in _TERMS], axis=-2)
    rhs = np.stack([mz[t] for t in _TERMS], axis=-1)
    eig = np.linalg.eigvalsh(gram)
    ok = (m[(0, 0)] >= LOCAL_FIT_MIN_PIXELS - 0.5) & (eig[:, 0] > RCOND * eig[:, -1])
    coef = np.zeros(rhs.shape)
    if ok.any():
        coef[ok] = np.linalg.solve(gram[ok], rhs[ok][..., None])[..., 0]
    scale = max(reach, 1)
    return coef[:, 0] + s.mean_height, coef[:, 1] / scale, coef[:, 2] / scale, ok


def _local_pose_used(scene: _Scene, s: Surface) -> bool:
    """Whether a site on ``s`` takes :func:`local_pose` (a curved surface)."""
    return s.type != "planar"


def site_poses(scene: _Scene, s: Surface, rows: np.ndarray, cols: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Step 6: elevation and gradient (dz/dx, dz/dy) of sites on ``s``, float64 (N,) each.

    A planar surface keeps its plane (its fit over the whole face is the
    most precise estimate of a plane); a curved one gets the local quadric of its pixels within
    :func:`local_reach` of each site (:func:`local_poses`), or its own fit
    where those pixels determine none.
    """
    height = np.asarray(s.height_at(rows, cols), dtype=np.float64)
    gx, gy = (np.asarray(g, dtype=np.float64) for g in s.gradient_at(rows, cols))
    if _local_pose_used(scene, s):
        lh, lx, ly, ok = local_poses(scene.z, scene.labels, s, rows, cols,
                                     local_reach(scene.cfg.size))
        height, gx, gy = np.where(ok, lh, height), np.where(ok, lx, gx), np.where(ok, ly, gy)
    return height, gx, gy


def site_pose(scene: _Scene, s: Surface, row: int, col: int
              ) -> tuple[float, tuple[float, float]]:
    """:func:`site_poses` of one site: ``(elevation, (dz/dx, dz/dy))``."""
    height, gx, gy = site_poses(scene, s, np.array([row]), np.array([col]))
    return float(height[0]), (float(gx[0]), float(gy[0]))


def make_site(s: Surface, row: int, col: int, *, object_id: int, clearance: float,
              ar_std: float, angle: float, site_score: float, config: Config,
              pose: tuple[float, tuple[float, float]] | None = None) -> Holdsite:
    """Step 6: a :class:`Holdsite` with elevation, normal and approach.

    ``pose`` is ``(elevation, (dz/dx, dz/dy))`` at the site
    (:func:`site_pose`); ``None``: from the surface's fit.
    """
    if pose is None:
        pose = float(s.height_at(row, col)), s.gradient_at(row, col)
    elevation, (gx, gy) = pose
    normal = _unit(np.array([-gx, -gy, 1.0]))
    point, approach_cam = camera_pose(row, col, elevation, (gx, gy), config.input)
    return Holdsite(
        row=int(row), col=int(col), elevation=elevation, normal=normal,
        approach=(-normal[0], -normal[1], -normal[2]), surface=s.id, surface_type=s.type,
        object=object_id, clearance=float(clearance), ar_std=float(ar_std),
        score=float(site_score), angle=float(angle), size=config.holdsite.size,
        point_camera=point, approach_camera=approach_cam)


# ---------------------------------------------------------------------------
# The whole search


def _angles(cfg: HoldsiteConfig) -> tuple[float, ...]:
    rows, cols = cfg.size
    if rows == cols:
        return (0.0,)
    n = int(math.ceil(180.0 / cfg.rotation_step - 1e-9))
    return tuple(float(k * cfg.rotation_step) for k in range(n))


def effective_holdsite(config: Config) -> HoldsiteConfig:
    """``[holdsite]`` as the search applies it: no tilt limit without a lateral scale.

    The tilt of a height map's normal needs its lateral scale: camera
    intrinsics, or ``[input] units_per_pixel``; without either, ``max_tilt``
    cannot be tested and is taken as 90 (any), as in the paper.
    """
    hold = config.holdsite
    if hold.max_tilt < 90 and not (config.input.has_intrinsics
                                   or config.input.units_per_pixel > 0):
        return dataclasses.replace(hold, max_tilt=90.0)
    return hold


def lying_on_seen_items(objects: list[ObjectInfo], floating: set[int]) -> set[int]:
    """Objects that lie on an item wholly in view, which stands or lies on what does.

    The item is no structure and not floating (:func:`floating_objects`): a
    finger hanging under the robot's arm holds nothing up.
    """
    return set().union(*(o.covered_by for o in objects if not (
        o.touches_border or o.structure or o.id in floating)))


def _group(obj: ObjectInfo, on_seen: set[int]) -> int:
    """Step 3's group: in view and uncovered; on top at the border; covered; the border."""
    if not obj.touches_border:
        return 2 if obj.covered else 0
    return 1 if not obj.covered and obj.id in on_seen else 3


def _preference(obj: ObjectInfo, s: Surface, lift: np.ndarray, on_seen: set[int]
                ) -> tuple[int, bool, float, int]:
    """Sort key of step 3: group (:func:`_group`), uncovered, highest (above the support)."""
    return _group(obj, on_seen), obj.covered, -float(lift[s.id]), s.id


def _check(z: np.ndarray, labels: np.ndarray, backend: Backend = "auto", **frames: Any
           ) -> tuple[np.ndarray, np.ndarray]:
    """``z`` as float64 and ``labels`` on its valid pixels, checked (:func:`find_holdsite`).

    ``frames``: the workspace arrays given (``background``, ``roi``), of ``z``'s shape.
    """
    try:
        check_stage_arrays(z, labels=labels)
        require_shape_of_z(z, **{k: v for k, v in frames.items() if v is not None})
    except ValueError as exc:  # find_holdsite's documented error
        raise InputError(str(exc)) from None
    z = np.asarray(z, dtype=np.float64)
    labels = np.asarray(labels)
    # int32 where it holds every label: the compiled boundary pairs run twice as wide
    if np.can_cast(labels.dtype, np.int32):
        return z, valid_labels(z, labels, backend=backend)[0]
    return z, np.where(np.isfinite(z), labels, 0).astype(np.int64)


def _site_of(scene: _Scene, hits: _Hits, k: int, obj: ObjectInfo, config: Config
             ) -> Holdsite:
    r, c = int(hits.rows[k]), int(hits.cols[k])
    dist = math.hypot(r - obj.centroid[0], c - obj.centroid[1])
    angle, ar_std = window_angle(scene, hits, k)
    pose = _known_pose(scene, hits, k)
    site = make_site(hits.surface, r, c, object_id=obj.id, clearance=hits.clearance[k],
                     ar_std=ar_std, angle=angle,
                     site_score=score(hits.clearance[k], dist, scene.cfg.size, obj.pixels),
                     config=config, pose=pose)
    return dataclasses.replace(site, size=scene.cfg.size,
                               flat_rms=site_flat_rms(scene.z, r, c, scene.footprint(angle)),
                               **site_tilt(scene.camera, scene.up, r, c, pose))


def site_tilt(camera: InputConfig, up: Vector | None, row: int, col: int,
              pose: tuple[float, tuple[float, float]]) -> dict[str, Any]:
    """``tilt`` and ``tilt_from`` of the site at (row, col) with ``pose`` (Step 4b, :func:`tilts`).

    From the support's normal ``up`` when there is one, else from the
    optical axis (intrinsics) or the height axis (``units_per_pixel`` > 0);
    both ``None`` without a lateral scale or depth at the site.
    """
    if not (camera.has_intrinsics or camera.units_per_pixel > 0):
        return {"tilt": None, "tilt_from": None}
    elevation, (gx, gy) = pose
    angle = float(tilts(camera, camera.units_per_pixel, [row], [col], [elevation], [gx], [gy],
                        up=up)[0])
    if not math.isfinite(angle):
        return {"tilt": None, "tilt_from": None}
    axis = "optical axis" if camera.has_intrinsics else "height axis"
    return {"tilt": angle, "tilt_from": axis if up is None else "support"}


def _known_pose(scene: _Scene, hits: _Hits, k: int) -> tuple[float, tuple[float, float]]:
    """:func:`site_pose` of window ``k``, as its tilt test computed it when it did."""
    if k in hits.poses:
        height, gx, gy = hits.poses[k]
        return height, (gx, gy)
    return site_pose(scene, hits.surface, int(hits.rows[k]), int(hits.cols[k]))


def site_flat_rms(z: np.ndarray, row: int, col: int, fp: np.ndarray) -> float:
    """RMS residual of the least-squares plane of the heights under a footprint at (row, col)."""
    fr, fc = np.nonzero(fp)
    rr, cc = row + fr - fp.shape[0] // 2, col + fc - fp.shape[1] // 2
    inside = (rr >= 0) & (rr < z.shape[0]) & (cc >= 0) & (cc < z.shape[1])
    h = z[rr[inside], cc[inside]]
    ok = np.isfinite(h)
    if ok.sum() < 3:
        return math.nan
    a = np.column_stack([np.ones(ok.sum()), fc[inside][ok], fr[inside][ok]]).astype(np.float64)
    centred = h[ok] - h[ok].mean()
    coef, *_ = np.linalg.lstsq(a, centred, rcond=None)
    return float(np.sqrt(np.mean((centred - a @ coef) ** 2)))


def _in_view_if_any(found: list[_Hits], object_of: dict[int, int],
                    objects: dict[int, ObjectInfo]) -> list[_Hits]:
    """The hits on objects wholly in view when there are any, else all (no support known).

    Without a support (:attr:`~rangeseg_cli.cell.workspace.Workspace.hidden`)
    nothing tells a tote's wall or rim from an item cut by the image border:
    the site and its runners-up then stay on objects wholly in view.
    """
    inside = [h for h in found if not objects[object_of[h.surface.id]].touches_border]
    return inside or found


def _clear_of_no_reading(scene: _Scene, valid: np.ndarray, args: tuple[Any, ...]
                         ) -> tuple[_Scene, set[int]]:
    """``scene`` without the valid pixels beside no reading, and the surfaces that have them.

    ``args``: the scene's arguments after its labels and mask (:func:`_collect`).
    """
    beside = valid & square_dilation(~valid, 3)
    return (_Scene(scene.labels, scene.valid & ~beside, *args),
            _present(scene.labels[beside]))


def _collect(scene: _Scene, order: list[Surface], wanted: int,
             clear: tuple[_Scene, set[int]] | None = None) -> tuple[list[_Hits], list[_Hits]]:
    """Search surfaces in order until ``wanted`` have accepted windows; (found, missed).

    With ``clear`` (the scene without the pixels beside no reading, and the
    surfaces that have such pixels), such a surface's windows come from
    that scene when one is accepted there; the others' are the same in both.
    """
    found: list[_Hits] = []
    missed: list[_Hits] = []
    for s in order:
        for one in (clear[0], scene) if clear and s.id in clear[1] else (scene,):
            sized = one.for_surface(s)
            hits = surface_windows(sized, s)
            hits.scene = sized
            accepted = _has_level(sized, hits)
            if accepted:
                break
        (found if accepted else missed).append(hits)
        if len(found) >= wanted:
            break
    return found, missed


def _choose(scene: _Scene, found: list[_Hits], objects: dict[int, ObjectInfo],
            object_of: dict[int, int], config: Config) -> list[Holdsite]:
    """Step 5: the chosen site first, then the runners-up (module Notes)."""
    wanted = 1 + config.holdsite.max_candidates
    ranked = [(hits, objects[object_of[hits.surface.id]]) for hits in found]
    picks = [(h, o, _first(h.scene, h, o.centroid)) for h, o in ranked]
    for (hits, obj), (_, _, first) in zip(ranked, list(picks), strict=True):
        if len(picks) >= wanted:
            break
        gap = math.hypot(*hits.scene.cfg.size)
        order = _rank(hits, obj.centroid)
        order = np.concatenate([[first], order[order != first]])  # the surface's site first
        extra = _spread(hits, order, wanted - len(picks) + 1, gap, hits.scene)[1:]
        picks += [(hits, obj, k) for k in extra]
    return [_site_of(h.scene, h, k, o, config) for h, o, k in picks[:wanted]]


def _failure(cfg: HoldsiteConfig, missed: list[_Hits], limit: float, axis: str = "") -> str:
    """Why no window was accepted (``limit``: the plane-fit RMS limit; ``axis``: :func:`_axis`)."""
    win = f"{cfg.size[0]}x{cfg.size[1]}"
    sizes = {h.scene.cfg.size for h in missed if h.scene is not None}
    if len(sizes) > 1 or (sizes and cfg.size not in sizes):
        win = "footprint (" + ", ".join(f"{r}x{c}" for r, c in sorted(sizes)) + " px)"
    widest = max(missed, key=lambda h: h.max_clearance)
    clear = (f"largest clearance found: {widest.max_clearance:.1f} px "
             f"(surface {widest.surface.id})")
    fitting = [h for h in missed if h.fitting]
    if not fitting:  # nothing holds the footprint: no object to pick, as an empty support
        return f"nothing to pick: no surface has a {win} window wholly on its valid pixels; {clear}"
    rough = [h for h in missed if h.rough]
    if rough and not any(h.steep for h in missed):
        flat = min(rough, key=lambda h: h.min_rms)
        return (f"no surface has a {win} window with AR std <= {cfg.max_ar_std:g} and a "
                f"plane-fit RMS <= {limit:.3g}; {sum(h.rough for h in rough)} window(s) passed "
                f"the AR test, lowest RMS {flat.min_rms:.3g} (surface {flat.surface.id}); "
                f"{clear}")
    steep = [h for h in missed if h.steep]
    if steep:
        level = min(steep, key=lambda h: h.min_tilt)
        least = (f"least tilt {level.min_tilt:.6g} degrees (surface {level.surface.id})"
                 if math.isfinite(level.min_tilt) else
                 "none with a tilt (no depth in front of the camera there)")
        return (f"no surface has a {win} window with AR std <= {cfg.max_ar_std:g} and a tilt "
                f"<= {cfg.max_tilt:g} degrees{axis}; {sum(h.steep for h in steep)} window(s) "
                f"passed the AR test, {least}; {clear}")
    calm = min(fitting, key=lambda h: h.min_ar_std)
    return (f"no surface has a {win} window with AR std <= {cfg.max_ar_std:g}; "
            f"{sum(h.fitting for h in fitting)} window(s) fit, lowest AR std "
            f"{calm.min_ar_std:.3g} (surface {calm.surface.id}); {clear}")


def _axis(scene: _Scene) -> str:
    """What a tilt is measured from, for a reason: the support's normal, or nothing said."""
    return "" if scene.up is None else " from the support's normal"


def _success(site: Holdsite, obj: ObjectInfo, missed: list[_Hits], cfg: HoldsiteConfig,
             axis: str = "", on_top: bool = False) -> str:
    """How the chosen site was found (``on_top``: in step 3's group 1, :func:`_group`)."""
    state = ("touching the image border" if obj.touches_border else "in view") + (
        ", covered" if obj.covered else ", uncovered")
    if on_top:
        state += ", lying on an item in view: before the covered ones in view"
    text = (f"surface {site.surface} ({site.surface_type}) of object {obj.id} ({state}) is the "
            f"first in the search order (objects in view, uncovered, highest surface first) "
            f"with a {site.size[0]}x{site.size[1]} window with AR std <= {cfg.max_ar_std:g}")
    if cfg.max_tilt < 90:
        text += f" and a tilt <= {cfg.max_tilt:g} degrees{axis}"
    if missed:
        ids = ", ".join(str(h.surface.id) for h in missed[:10])
        more = ", ..." if len(missed) > 10 else ""
        text += f"; tried before it without an acceptable window: surfaces {ids}{more}"
    return text


def _check_noise(noise: Any) -> None:
    """Raise a one-line ValueError unless ``noise`` is None or a finite number >= 0."""
    if noise is None:
        return
    try:
        ok = math.isfinite(float(noise)) and float(noise) >= 0
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise ValueError(f"`noise` must be a finite number >= 0 (the image's noise in depth "
                         f"units, as estimate_noise gives it), got {noise!r}")


def find_holdsite(z: np.ndarray, labels: np.ndarray, surfaces: list[Surface],
                  config: Config, *, backend: Backend = "auto",
                  gaps: dict[tuple[int, int], float] | None = None,
                  background: np.ndarray | None = None,
                  roi: np.ndarray | None = None, noise: float | None = None
                  ) -> HoldsiteResult:
    """Find the vacuum-gripper holdsite of a segmented range image (Sec. VII).

    Parameters
    ----------
    z
        float64 (H, W) heights (larger = closer), NaN where invalid.
    labels
        int (H, W) final segmentation, 0 = edge/unlabelled/invalid.
    surfaces
        The :class:`~rangeseg_cli.models.Surface` of each label (image
        coordinates, x = col, y = row).
    config
        Uses ``[holdsite]``, ``step.threshold`` (height tolerance) and
        ``[input]`` (intrinsics, depth sign, ``metres_per_unit``).
    backend
        ``"auto"``, ``"numba"`` or ``"numpy"`` for the boundary pairs of
        :func:`step_gaps` and the clearance (:func:`clearance_map`); identical
        results.
    gaps
        :func:`step_gaps` of ``labels`` and the surfaces' fits when the
        caller has them
        (:func:`~rangeseg_cli.stages.surfaces.describe_surfaces_and_gaps`, which
        gives them with the surfaces); computed here otherwise.
    background
        float64 (H, W) heights of the empty scene (``[workspace]
        background``, converted as ``z`` is; NaN where it has no reading),
        or ``None``.
    roi
        bool (H, W) mask of the pixels that may be picked (``[workspace]
        roi``), or ``None``.
    noise
        :func:`~rangeseg_cli.stages.noise.estimate_noise` of ``z`` when the
        caller has it (estimated here otherwise).

    Returns
    -------
    HoldsiteResult
        The chosen site (or ``None`` with a reason), up to
        ``holdsite.max_candidates`` runners-up, the background ids and the
        objects. See the module Notes for every rule.

    Raises
    ------
    InputError
        When ``labels`` is not an integer array of the shape of ``z`` with
        labels from 0 to its pixel count.
    ConfigError, TypeError
        For a configuration value out of range or a table of the wrong class
        (:func:`~rangeseg_cli.config.check_config`).
    ValueError
        When ``noise`` is given and is not a finite number >= 0.
    """
    z, labels = _check(z, labels, backend, background=background, roi=roi)
    _check_noise(noise)
    check_config(config)
    valid = np.isfinite(z)
    n = int(labels.max(initial=0))
    by_id = {s.id: s for s in surfaces if 0 < s.id <= n}  # the others have no pixel
    known = np.zeros(n + 1, dtype=bool)
    known[list(by_id)] = True
    labels = np.where(known[labels], labels, 0)
    tol = config.step.threshold
    noise = estimate_noise(z, backend=backend) if noise is None else noise
    coeffs = _coefficient_table(surfaces, n)
    # Step 0: the workspace (beyond the paper): what may be picked
    space = assess(z, config, noise, background=background, roi=roi)
    # the median depth only sizes a footprint_mm (the median costs a pass over the image)
    depth = (-float(np.nanmedian(z)) if valid.any() else 0.0) if footprint_in_mm(
        config.holdsite, config.input) else 0.0
    wrong_unit = sub_pixel_footprint(config, depth)
    if wrong_unit:
        return HoldsiteResult(None, wrong_unit, camera=config.input.has_intrinsics)
    area = math.prod(footprint_pixels(config.holdsite, config.input, depth))
    on_support = None
    if space.height is not None:
        with np.errstate(invalid="ignore"):
            on_support = np.abs(space.height) <= space.tolerance
    low = unpickable_regions(labels, space.pickable, n)
    labels, carved, origin = carve_pickable(z, labels, space.pickable, on_support, n, area,
                                            config, backend, low)
    if origin:  # items grown into the floor: their pickable pieces are surfaces of their own
        by_id.update({c.id: c for c in carved})
        n, gaps = int(labels.max()), None
        coeffs = _coefficient_table(list(by_id.values()), n)
    # Step 1: background (lowest border regions, and regions the workspace leaves out)
    framed = _framed(labels)
    border = framed | _near_outer_invalid(labels, valid)
    background_ids = find_background(by_id, border, config.holdsite.background, tol)
    if origin:  # the labels changed
        low = unpickable_regions(labels, space.pickable, n)
    excluded = low - background_ids
    left_out = background_ids | excluded
    # Step 2: objects, and which are covered by another
    if gaps is None:
        gaps = _known_gaps(labels, coeffs, backend)  # known labels
    # beyond the paper: objects part at concave creases, and neither a crack of no reading
    # that joins the frame nor a shadow puts an object at the border
    beyond = config.workspace.border_structures
    in_frame = framed | in_view_border(labels, valid, z, tol, space) if beyond else border
    object_of, objects = find_objects(by_id, left_out, gaps, tol, in_frame,
                                      concave_parts=beyond)
    lift = region_lift(labels, space, z, n, ids=object_of)  # step 3 orders only these
    if beyond:
        half = (min(footprint_pixels(config.holdsite, config.input, depth)) - 1) / 2
        where = ObjectMap(objects, labels)
        objects = mark_structures(objects, where, valid, space, half, on_support,
                                  walls_known=background is not None)
        objects = _covered_from_above(objects, where, z, space, tol, on_support)
    floating = floating_objects(objects) if space.support is not None else set()
    obj_by_id = {o.id: o for o in objects}
    candidates = {i: o for i, o in object_of.items() if not obj_by_id[o].structure}
    # Step 3: objects on the support (or on what is) first, then wholly in view (or, with a
    # support, uncovered at the border and lying on an item in view), then uncovered;
    # each group highest first. Without a support nothing tells a finger from an item.
    on_seen = (lying_on_seen_items(objects, floating)
               if beyond and space.support is not None else set())
    order = sorted((by_id[i] for i in candidates), key=lambda s: (
        object_of[s.id] in floating, *_preference(obj_by_id[object_of[s.id]], s, lift,
                                                  on_seen)))
    # Step 4: acceptable windows, surface by surface
    hold = effective_holdsite(config)
    if config.input.auto_thresholds:  # else the bound as given: no lateral scale needed
        hold = dataclasses.replace(hold, max_ar_std=ar_std_limit(
            hold, config.input, noise, lateral_scale(z, config.input)))
    args = (z, hold, _angles(hold), backend, config.input, flat_limit(hold, config.input, noise),
            None if space.support is None else space.support.normal)
    scene = _Scene(labels, valid & space.pickable, *args)
    clear = _clear_of_no_reading(scene, valid, args) if beyond else None
    found, missed = _collect(scene, order, 1 + config.holdsite.max_candidates, clear)
    if space.hidden is not None:  # no support: the border is the one cue to a wall or a rim
        found = _in_view_if_any(found, object_of, obj_by_id)
    bg, camera = tuple(sorted(background_ids)), config.input.has_intrinsics
    objs, out = tuple(_named_as_labelled(objects, origin)), tuple(sorted(excluded))
    if not found:
        reason = (_failure(hold, missed, scene.flat_limit, _axis(scene)) if order
                  else _nothing_to_pick(by_id, objects, space)) + _unit_note(config) \
            + _background_note(space) + _hidden_support_note(space)
        return HoldsiteResult(None, reason, (), bg, objs, camera, out)
    # Step 5: the best window, then the runners-up
    sites = [dataclasses.replace(site, surface=origin.get(site.surface, site.surface))
             for site in _choose(scene, found, obj_by_id, object_of, config)]
    rank = {s.id: k for k, s in enumerate(order)}
    first = rank[found[0].surface.id]  # (carved pieces are named by their region below)
    before = [h for h in missed if rank[h.surface.id] < first]
    chosen = obj_by_id[sites[0].object]
    reason = (_success(sites[0], chosen, before, hold, _axis(scene),
                       _group(chosen, on_seen) == 1)
              + _unit_note(config) + _background_note(space)
              + _hidden_support_note(space))
    return HoldsiteResult(sites[0], reason, tuple(sites[1:]), bg, objs, camera, out)
