"""Segmentation against ground truth: the metrics of Hoover et al. (1996), ``rangeseg eval``.

Hoover, Jean-Baptiste, Jiang, Flynn, Bunke, Goldgof, Bowyer, Eggert,
Fitzgibbon and Fisher, "An experimental comparison of range image
segmentation algorithms", IEEE Trans. PAMI 18(7), 1996, classify each region
of a ground truth (GT) and of a machine segmentation (MS) at a tolerance
0.5 <= T <= 1. With ``O(m, n)`` the pixels machine region ``m`` and GT region
``n`` share and ``|r|`` a region's size:

* correct detection: ``O >= T |m|`` and ``O >= T |n|``;
* over-segmentation: GT ``n`` and machine ``m1..mk`` (k >= 2), each
  ``O(mi, n) >= T |mi|``, and ``sum O(mi, n) >= T |n|``;
* under-segmentation: machine ``m`` and GT ``n1..nk`` (k >= 2), each
  ``O(m, ni) >= T |ni|``, and ``sum O(m, ni) >= T |m|``;
* missed: a GT region in no instance above; noise: a machine region in none.

Notes
-----
Rules chosen where the paper leaves room:

1. Label 0 is no region on either side (GT: no surface; MS: edge,
   unlabelled or invalid pixels). GT regions below ``min_region`` pixels are
   dropped to 0 as well (too small to judge). Machine pixels on GT label 0
   are left out of ``|m|`` (unknown truth costs nothing); GT pixels under
   machine label 0 still count in ``|n|`` (unlabelled pixels cost overlap).
2. A region takes part in at most one instance. Correct detections are
   taken first (for T = 0.5, where a region may qualify twice, the pair of
   highest mutual overlap ``(O/|m| + O/|n|) / 2`` wins; equal scores go to
   the lower GT, then machine, label). Then over- and under-segmentations
   are taken greedily on the regions still free, highest mutual overlap
   first (``sum O`` over the union's sizes on both sides), over before under
   on equal scores, then the lower label. For T > 0.5 the instances left
   after the correct detections never share a region, so this order only
   matters at T = 0.5.
3. Machine regions below ``min_region`` pixels take part in instances like
   any other; left over, they are counted as ``small``, not as ``noise``.
   A machine region lying wholly on GT label 0 is ``ignored``.

4. A GT label is judged as one region however many separate patches of
   the image it covers (a hole's wall seen at its mouth and again through a
   crossing hole, a surface split by an object lying on it). With
   ``gt_parts`` each 8-connected patch is judged as a region of its own
   (:func:`connected_parts`): a segmentation into connected regions can
   never give two separate patches one label, so otherwise such a surface
   counts as correct only when its largest patch alone holds ``T`` of it.

The holdsite check (Sec. VII of Al-Hujazi & Sood) asks whether a reported
gripper window lies wholly inside one GT surface of an uncovered part that is
not the background (the table). The object-level check
(:func:`check_object_holdsite`, for the depth-camera scenes of
:mod:`rangeseg_cli.synth.camera`) asks what a robot cell needs: the window
wholly on valid pixels of one pickable object, any of its surfaces, and the
approach within a tilt limit of straight down (the world's vertical when the
scene records the camera's rotation, else the optical axis); no holdsite is
right when nothing can be picked.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from ..cell.workspace import odd_pixels
from ..config import check_value, shown_value
from ..errors import ConfigError

#: Tolerances of the correct-detection curve (Hoover et al. plot 0.5..0.95).
CURVE_TOLERANCES: tuple[float, ...] = tuple(round(0.5 + 0.05 * i, 2) for i in range(10))
#: Default tolerance T (Hoover et al. report their tables at 0.8).
DEFAULT_TOLERANCE = 0.8
#: Default smallest GT region that is judged, in pixels.
DEFAULT_MIN_REGION = 50
#: Counts of :meth:`Classification.counts`, in table order.
COUNT_KEYS = ("gt_regions", "machine_regions", "correct", "over", "under", "missed", "noise",
              "small", "ignored")


@dataclass(frozen=True)
class Instance:
    """One classified instance: its kind, GT labels, machine labels and mutual overlap."""

    kind: str
    gt: tuple[int, ...]
    machine: tuple[int, ...]
    score: float


@dataclass
class Classification:
    """Hoover classification of one image at one tolerance."""

    tolerance: float
    gt_labels: np.ndarray
    machine_labels: np.ndarray
    instances: list[Instance] = field(default_factory=list)
    missed: list[int] = field(default_factory=list)
    noise: list[int] = field(default_factory=list)
    small: list[int] = field(default_factory=list)
    ignored: list[int] = field(default_factory=list)

    def counts(self) -> dict[str, int]:
        """Counts per class (``under`` counts machine regions, the others GT regions)."""
        kinds = [i.kind for i in self.instances]
        return {"gt_regions": len(self.gt_labels), "machine_regions": len(self.machine_labels),
                "correct": kinds.count("correct"), "over": kinds.count("over"),
                "under": kinds.count("under"), "missed": len(self.missed),
                "noise": len(self.noise), "small": len(self.small),
                "ignored": len(self.ignored)}


@dataclass(frozen=True)
class Overlap:
    """Overlap table of GT regions (rows) and machine regions (columns).

    Attributes
    ----------
    gt_labels, machine_labels
        Labels of the rows and columns.
    table
        int64 (G, M): shared pixels ``O(m, n)``.
    gt_size
        Pixels of each judged GT region, ``|n|``.
    machine_size
        Pixels of each machine region on judged GT pixels, ``|m|``.
    machine_full
        All pixels of each machine region (for the ``min_region`` rule).
    """

    gt_labels: np.ndarray
    machine_labels: np.ndarray
    table: np.ndarray
    gt_size: np.ndarray
    machine_size: np.ndarray
    machine_full: np.ndarray
    min_region: int


def _check_label_image(name: str, a: np.ndarray) -> None:
    """A 2-D image of labels 0 (none) to 2^63 - 1, or ``ValueError`` naming ``name``."""
    if a.ndim != 2 or a.dtype.kind not in "iu":
        raise ValueError(f"`{name}` (shape {a.shape}, dtype {a.dtype}) must be a 2-D "
                         "integer label image")
    if a.size and a.min() < 0:
        raise ValueError(f"`{name}` has negative labels; allowed: 0 (no region) and up")
    if a.size and int(a.max()) > np.iinfo(np.int64).max:  # uint64: would wrap below 0
        raise ValueError(f"`{name}` has label {int(a.max())}; allowed: 0 to 2^63 - 1")


def _check_labels(gt: np.ndarray, pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gt, pred = np.asarray(gt), np.asarray(pred)
    _check_label_image("gt", gt)
    _check_label_image("pred", pred)
    if gt.shape != pred.shape:
        raise ValueError(f"`pred` (shape {pred.shape}) must have the shape of `gt` "
                         f"({gt.shape})")
    return gt.astype(np.int64), pred.astype(np.int64)


def _index(labels: np.ndarray, values: np.ndarray) -> np.ndarray:
    """1-based position of each value in the sorted ``labels``; 0 where it is not there."""
    if len(labels) == 0:
        return np.zeros(values.shape, np.int64)
    pos = np.minimum(np.searchsorted(labels, values), len(labels) - 1)
    return np.where(labels[pos] == values, pos + 1, 0)


def connected_parts(gt: np.ndarray) -> np.ndarray:
    """Each 8-connected patch of each GT label as a label of its own (Notes, rule 4).

    Parameters
    ----------
    gt
        (H, W) non-negative integer labels, 0 = no surface.

    Returns
    -------
    numpy.ndarray
        int64 (H, W): 0 where ``gt`` is 0; else 1..k, numbered by GT label,
        then by the raster order of each patch's first pixel. A label whose
        pixels are all 8-connected becomes one part.

    Raises
    ------
    ValueError
        When ``gt`` is not a 2-D integer array or holds a negative label.
    """
    gt = np.asarray(gt)
    _check_label_image("gt", gt)
    values, inverse = np.unique(gt, return_inverse=True)  # any label values, dense 0..m
    dense = inverse.reshape(gt.shape) + (1 if values.size and values[0] != 0 else 0)
    out = np.zeros(gt.shape, np.int64)
    count = 0
    for label, box in enumerate(ndimage.find_objects(dense), start=1):
        if box is None:
            continue
        parts, n = ndimage.label(dense[box] == label, structure=np.ones((3, 3), bool))
        out[box] = np.where(parts > 0, parts + count, out[box])
        count += n
    return out


def overlap_table(gt: np.ndarray, pred: np.ndarray, *,
                  min_region: int = DEFAULT_MIN_REGION, gt_parts: bool = False) -> Overlap:
    """Count the pixels each GT region shares with each machine region.

    Parameters
    ----------
    gt, pred
        (H, W) integer labels, 0 = no region.
    min_region
        GT regions with fewer pixels are not judged (set to 0).
    gt_parts
        Judge each 8-connected patch of a GT label as a region of its own
        (:func:`connected_parts`; the table's GT labels are then the parts').

    Returns
    -------
    Overlap
        The table and the region sizes (see the module notes).

    Raises
    ------
    ValueError
        When the arrays are not 2-D integer label images of one shape, or
        ``min_region`` is negative.
    """
    gt, pred = _check_labels(gt, pred)
    if not _is_int(min_region) or min_region < 0:
        raise ValueError(f"`min_region` {min_region!r} must be an integer >= 0")
    if gt_parts:
        gt = connected_parts(gt)
    values, counts = np.unique(gt, return_counts=True)
    kept = values[(values > 0) & (counts >= max(min_region, 1))]
    machine_labels = np.unique(pred[pred > 0])
    rows, cols = _index(kept, gt.ravel()), _index(machine_labels, pred.ravel())
    full = np.zeros((len(kept) + 1, len(machine_labels) + 1), np.int64)
    np.add.at(full, (rows, cols), 1)
    return Overlap(gt_labels=kept, machine_labels=machine_labels, table=full[1:, 1:],
                   gt_size=full[1:, :].sum(axis=1), machine_size=full[1:, 1:].sum(axis=0),
                   machine_full=full[:, 1:].sum(axis=0), min_region=min_region)


def check_tolerance(tolerance: float) -> float:
    """The Hoover tolerance as a float; a ValueError unless it is a number from 0.5 to 1."""
    if not (isinstance(tolerance, int | float) and 0.5 <= tolerance <= 1.0):
        raise ValueError(f"`tolerance` {tolerance!r} must be a number from 0.5 to 1 "
                         "(Hoover et al. 1996)")
    return float(tolerance)


def _correct_pairs(ov: Overlap, t: float) -> list[tuple[float, int, int]]:
    o = ov.table.astype(float)
    ok = (o > 0) & (o >= t * ov.machine_size[None, :]) & (o >= t * ov.gt_size[:, None])
    g, m = np.nonzero(ok)
    score = (o[g, m] / ov.gt_size[g] + o[g, m] / ov.machine_size[m]) / 2
    return sorted(zip((-score).tolist(), g.tolist(), m.tolist(), strict=True))


def _best_split(ov: Overlap, t: float, free_g: np.ndarray, free_m: np.ndarray
                ) -> Instance | None:
    """The over- or under-segmentation of highest mutual overlap among free regions."""
    o = np.where(free_g[:, None] & free_m[None, :], ov.table, 0).astype(float)
    best: tuple[float, int, int, Instance] | None = None
    # Over-segmentation: rows with >= 2 machine regions mostly inside them.
    inside = (o > 0) & (o >= t * ov.machine_size[None, :])
    for g in np.flatnonzero(inside.sum(axis=1) >= 2):
        ms = np.flatnonzero(inside[g])
        shared = o[g, ms].sum()
        if shared >= t * ov.gt_size[g]:
            score = (shared / ov.gt_size[g] + shared / ov.machine_size[ms].sum()) / 2
            key = (-score, 0, int(ov.gt_labels[g]))
            if best is None or key < best[:3]:
                best = (*key, Instance("over", (int(ov.gt_labels[g]),),
                                       tuple(int(x) for x in ov.machine_labels[ms]),
                                       float(score)))
    # Under-segmentation: columns holding >= 2 GT regions mostly.
    holds = (o > 0) & (o >= t * ov.gt_size[:, None])
    for m in np.flatnonzero(holds.sum(axis=0) >= 2):
        gs = np.flatnonzero(holds[:, m])
        shared = o[gs, m].sum()
        if shared >= t * ov.machine_size[m]:
            score = (shared / ov.machine_size[m] + shared / ov.gt_size[gs].sum()) / 2
            key = (-score, 1, int(ov.gt_labels[gs[0]]))
            if best is None or key < best[:3]:
                best = (*key, Instance("under", tuple(int(x) for x in ov.gt_labels[gs]),
                                       (int(ov.machine_labels[m]),), float(score)))
    return None if best is None else best[3]


def classify(ov: Overlap, tolerance: float = DEFAULT_TOLERANCE) -> Classification:
    """Hoover et al. (1996) classification of an :class:`Overlap` at ``tolerance``.

    Parameters
    ----------
    ov
        From :func:`overlap_table`.
    tolerance
        T, from 0.5 to 1.

    Returns
    -------
    Classification
        Instances, missed, noise, small and ignored regions (rules in the module notes).
    """
    t = check_tolerance(tolerance)
    g_idx = {int(v): i for i, v in enumerate(ov.gt_labels)}
    m_idx = {int(v): i for i, v in enumerate(ov.machine_labels)}
    free_g = np.ones(len(ov.gt_labels), bool)
    free_m = ov.machine_size > 0  # machine regions wholly on GT label 0 are ignored
    out = Classification(t, ov.gt_labels, ov.machine_labels)
    for neg, g, m in _correct_pairs(ov, t):
        if free_g[g] and free_m[m]:
            free_g[g] = free_m[m] = False
            out.instances.append(Instance("correct", (int(ov.gt_labels[g]),),
                                          (int(ov.machine_labels[m]),), -neg))
    while (inst := _best_split(ov, t, free_g, free_m)) is not None:
        out.instances.append(inst)
        for label in inst.gt:
            free_g[g_idx[label]] = False
        for label in inst.machine:
            free_m[m_idx[label]] = False
    out.missed = [int(v) for v in ov.gt_labels[free_g]]
    small = ov.machine_full < ov.min_region
    out.noise = [int(v) for v in ov.machine_labels[free_m & ~small]]
    out.small = [int(v) for v in ov.machine_labels[free_m & small]]
    out.ignored = [int(v) for v in ov.machine_labels[ov.machine_size == 0]]
    return out


def hoover_compare(gt: np.ndarray, pred: np.ndarray, *, tolerance: float = DEFAULT_TOLERANCE,
                   min_region: int = DEFAULT_MIN_REGION, gt_parts: bool = False
                   ) -> Classification:
    """Compare a machine segmentation with ground truth (Hoover et al. 1996).

    Parameters
    ----------
    gt
        (H, W) integer ground-truth labels, 0 = no surface.
    pred
        (H, W) integer machine labels (``labels.npy``), 0 = no region.
    tolerance
        T, from 0.5 to 1 (0.8 as in Hoover et al.'s tables).
    min_region
        GT regions with fewer pixels are not judged.
    gt_parts
        Judge each 8-connected patch of a GT label on its own (Notes, rule 4).

    Returns
    -------
    Classification
        ``.counts()`` gives ``gt_regions, correct, over, under, missed, noise``
        and more.

    Raises
    ------
    ValueError
        For label images of different shapes or types, or an option out of range.
    """
    return classify(overlap_table(gt, pred, min_region=min_region, gt_parts=gt_parts),
                    tolerance)


def correct_curve(gt: np.ndarray, pred: np.ndarray, *,
                  tolerances: Sequence[float] = CURVE_TOLERANCES,
                  min_region: int = DEFAULT_MIN_REGION, gt_parts: bool = False) -> list[int]:
    """Correct detections at each tolerance (Hoover et al.'s curves, 0.5..0.95).

    Returns
    -------
    list of int
        One count per tolerance.
    """
    ov = overlap_table(gt, pred, min_region=min_region, gt_parts=gt_parts)
    return [classify(ov, t).counts()["correct"] for t in tolerances]


# --------------------------------------------------------------------------- holdsites


def _window(holdsite: Mapping[str, Any], size: tuple[int, int]
            ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel rows and columns under a holdsite's gripper window (as the search draws it)."""
    from ..stages.holdsite import footprint

    rows, cols = holdsite.get("size") or holdsite.get("window") or size
    fp = footprint((int(rows), int(cols)), float(holdsite.get("angle") or 0.0))
    dr, dc = np.nonzero(fp)
    return (int(holdsite["row"]) + dr - fp.shape[0] // 2,
            int(holdsite["col"]) + dc - fp.shape[1] // 2)


def _check_max_tilt(max_tilt: Any) -> None:
    """``max_tilt`` is a number of degrees from 0 to 90 (ValueError naming it otherwise)."""
    if not (isinstance(max_tilt, int | float) and 0 <= max_tilt <= 90):
        raise ValueError(f"`max_tilt` {max_tilt!r} must be a number of degrees from 0 to 90")


def _labels_under(holdsite: Mapping[str, Any], gt: np.ndarray, size: tuple[int, int]
                  ) -> np.ndarray | None:
    """GT labels under a holdsite's window; ``None`` when the window leaves the image.

    Raises
    ------
    ValueError
        For a holdsite whose window cannot be drawn (naming the key).
    """
    problem = _holdsite_problem(holdsite)
    if problem:
        raise ValueError(f"`holdsite`: {problem}")
    r, c = _window(holdsite, size)
    h, w = gt.shape
    if r.min() < 0 or c.min() < 0 or r.max() >= h or c.max() >= w:
        return None
    return gt[r, c]


def check_holdsite(holdsite: Mapping[str, Any] | None, gt: np.ndarray,
                   info: Mapping[str, Any], *, size: tuple[int, int] = (7, 7)
                   ) -> dict[str, Any]:
    """Check that a holdsite's window lies wholly inside one surface of an uncovered part.

    Parameters
    ----------
    holdsite
        The ``"holdsite"`` of ``holdsite.json``: ``row``, ``col``, optional
        ``size`` ([rows, cols]) and ``angle`` (degrees); ``None`` when no
        site was found.
    gt
        (H, W) ground-truth labels of the scene.
    info
        The scene's ``gt.json``: ``surfaces`` (``id``, ``object``),
        ``objects`` (``id``, ``background``) and ``uncovered``.
    size
        Window size when the holdsite does not give one (the paper's 7x7, Sec. VII).

    Returns
    -------
    dict
        ``ok`` (bool), ``reason``, ``surface`` and ``object`` (GT ids or None).

    Raises
    ------
    ValueError
        For a holdsite without integer ``row`` and ``col``, or with a window
        or angle :func:`check_holdsite` cannot draw (naming the key).
    """
    result: dict[str, Any] = {"ok": False, "surface": None, "object": None}
    if holdsite is None:
        return {**result, "reason": "no holdsite reported"}
    under = _labels_under(holdsite, gt, size)
    if under is None:
        return {**result, "reason": "window leaves the image"}
    labels = np.unique(under)
    if len(labels) != 1 or labels[0] == 0:
        ids = ", ".join(str(v) for v in labels)
        return {**result, "reason": f"window crosses surfaces {ids}"}
    surface = int(labels[0])
    obj = {s["id"]: s["object"] for s in info["surfaces"]}.get(surface)
    result.update(surface=surface, object=obj)
    background = {o["id"] for o in info["objects"] if o.get("background")}
    if obj is None or obj in background:
        return {**result, "reason": f"surface {surface} is the background"}
    if obj not in set(info["uncovered"]):
        return {**result, "reason": f"object {obj} lies under another part"}
    return {**result, "ok": True, "reason": f"inside surface {surface} of uncovered "
            f"object {obj}"}


#: Default largest tilt of a usable holdsite's approach from straight down, degrees.
DEFAULT_MAX_TILT = 45.0


def pickable_objects(info: Mapping[str, Any]) -> set[int]:
    """Ids of the objects a gripper may take: ``pickable`` in ``gt.json``, else not background."""
    return {int(o["id"]) for o in info["objects"]
            if o.get("pickable", not o.get("background", False))}


def approach_tilt(approach: Sequence[float] | None,
                  rotation: Sequence[Sequence[float]] | None = None) -> float | None:
    """Degrees between a camera-frame approach vector and straight down.

    Straight down is the optical axis (0, 0, 1), or with ``rotation`` (the
    camera's axes in world coordinates, as columns: ``gt.json``'s
    ``camera.rotation``) the world's -z, the support's inward normal: a
    robot approaches against gravity's "up", whatever the camera's mount.
    None when ``approach`` is missing, not three finite numbers, or zero.
    """
    if approach is None or len(approach) != 3:
        return None
    try:
        a = np.array(approach, dtype=float)
    except (TypeError, ValueError):
        return None
    norm = float(np.linalg.norm(a))
    if not np.all(np.isfinite(a)) or norm == 0:
        return None
    down = np.array([0.0, 0.0, 1.0]) if rotation is None else -np.asarray(rotation, float)[2]
    cosine = float(a @ down) / norm / float(np.linalg.norm(down))
    return math.degrees(math.acos(max(-1.0, min(1.0, cosine))))


def _fits_somewhere(gt: np.ndarray, surfaces: Sequence[Mapping[str, Any]], objects: set[int],
                    size: tuple[int, int] | Callable[[np.ndarray], tuple[int, int]]
                    ) -> list[int]:
    """Objects of ``objects`` with a surface on whose GT pixels a window fits (unrotated).

    A suction cup seals on one face, not across an edge: the window must fit
    in one GT surface. ``size`` is the window, or a function of a surface's
    mask that gives it (a footprint in millimetres at its depth).
    """
    fits = set()
    for s in surfaces:
        o = int(s["object"])
        if o not in objects or o in fits:
            continue
        mask = gt == int(s["id"])
        window = size(mask) if callable(size) else size
        if mask.any() and ndimage.binary_erosion(mask, np.ones(window, bool)).any():
            fits.add(o)
    return sorted(fits)


def footprint_at_depth(footprint_mm: tuple[float, float], camera: Mapping[str, Any],
                       depth_mm: np.ndarray) -> Callable[[np.ndarray], tuple[int, int]]:
    """The window (odd rows, cols) of a footprint in mm at the median depth of a mask.

    As ``rangeseg`` converts ``[holdsite] footprint_mm`` (pinhole: ``L f /
    d`` pixels, the nearest odd count, 1 to 255).
    """
    def window(mask: np.ndarray) -> tuple[int, int]:
        d = depth_mm[mask]
        d = d[np.isfinite(d) & (d > 0)]
        if not d.size:
            return (255, 255)
        m = float(np.median(d))
        return (odd_pixels(footprint_mm[0], float(camera["fy"]), m),
                odd_pixels(footprint_mm[1], float(camera["fx"]), m))

    return window


def check_object_holdsite(holdsite: Mapping[str, Any] | None, gt: np.ndarray,
                          info: Mapping[str, Any], *, max_tilt: float = DEFAULT_MAX_TILT,
                          size: tuple[int, int] = (7, 7),
                          footprint: Callable[[np.ndarray], tuple[int, int]] | None = None
                          ) -> dict[str, Any]:
    """Whether a holdsite is usable by a suction gripper: the object-level check.

    Usable: the gripper window (``row``, ``col``, ``size``, ``angle``) lies
    wholly on GT pixels of one pickable object (any of its surfaces; GT is 0
    where the sensor gives no reading, so every pixel under the window is
    valid), and the approach is within ``max_tilt`` degrees of straight
    down: the angle between ``approach_camera`` and the world's -z in the
    camera frame when ``camera.rotation`` is recorded (a tilted mount), else
    the optical axis (0, 0, 1) (:func:`approach_tilt`). When the
    scene has a ``camera`` and the holdsite no ``approach_camera``, the site
    is not usable (its tilt cannot be judged); in a scene without a camera
    the tilt is not checked. No holdsite is correct when no surface of a
    pickable object holds a ``size`` window (an empty tote; a cup seals on
    one face), and wrong otherwise.

    Parameters
    ----------
    holdsite
        The ``"holdsite"`` of ``holdsite.json``, or ``None``.
    gt
        (H, W) ground-truth surface labels, 0 = no surface or no reading.
    info
        The scene's ``gt.json``: ``surfaces`` (``id``, ``object``),
        ``objects`` (``id``, ``pickable`` or ``background``), optional ``camera``.
    max_tilt
        Largest tilt of the approach from straight down, degrees.
    size
        Window when the holdsite gives none, and the window a null holdsite
        is judged with.
    footprint
        The window a null holdsite is judged with, per object mask, instead
        of ``size`` (:func:`footprint_at_depth`: a cup in millimetres).

    Returns
    -------
    dict
        ``ok`` (bool), ``reason``, ``object`` (GT id or None), ``surfaces``
        (GT ids under the window), ``tilt`` (degrees or None) and
        ``pickable_in_view`` (ids of the pickable objects that hold a window).

    Raises
    ------
    ValueError
        For a holdsite :func:`check_holdsite` cannot draw, or ``max_tilt``
        outside 0..90.
    """
    _check_max_tilt(max_tilt)
    pickable = pickable_objects(info)
    in_view = _fits_somewhere(gt, info["surfaces"], pickable, footprint or size)
    result: dict[str, Any] = {"ok": False, "object": None, "surfaces": [], "tilt": None,
                              "pickable_in_view": in_view}
    if holdsite is None:
        if in_view:
            return {**result, "reason": f"no holdsite, but objects {in_view} can be picked"}
        return {**result, "ok": True, "reason": "no holdsite, and nothing to pick"}
    labels = _labels_under(holdsite, gt, size)
    if labels is None:
        return {**result, "reason": "window leaves the image"}
    result["surfaces"] = [int(v) for v in np.unique(labels)]
    return _judge_window(holdsite, labels, info, pickable, max_tilt, result)


def _judge_window(holdsite: Mapping[str, Any], labels: np.ndarray, info: Mapping[str, Any],
                  pickable: set[int], max_tilt: float, result: dict[str, Any]
                  ) -> dict[str, Any]:
    """The object, validity and tilt tests of :func:`check_object_holdsite`."""
    unseen = int(np.count_nonzero(labels == 0))
    if unseen:
        return {**result, "reason": f"{unseen} window pixels have no valid reading or no "
                "surface"}
    owner = {int(s["id"]): int(s["object"]) for s in info["surfaces"]}
    objs = sorted({owner.get(int(v), -1) for v in np.unique(labels)})
    if len(objs) != 1:
        return {**result, "reason": f"window straddles objects {objs}"}
    obj = objs[0]
    result["object"] = obj
    if obj not in pickable:
        return {**result, "reason": f"object {obj} cannot be picked"}
    tilt = approach_tilt(holdsite.get("approach_camera"),
                         (info.get("camera") or {}).get("rotation"))
    result["tilt"] = tilt
    if tilt is None and info.get("camera"):
        return {**result, "reason": "no approach_camera to judge the tilt by (run with "
                "camera intrinsics)"}
    if tilt is not None and tilt > max_tilt:
        return {**result, "reason": f"approach tilted {tilt:.1f} degrees, more than "
                f"{max_tilt:g}"}
    return {**result, "ok": True, "reason": f"on pickable object {obj}"}


# --------------------------------------------------------------------------- folders


def _pairs(pred_dir: Path, gt_dir: Path) -> list[tuple[str, Path, Path]]:
    from ..errors import InputError

    if not gt_dir.is_dir():
        raise InputError(f"{gt_dir}: no such folder")
    if not pred_dir.is_dir():
        raise InputError(f"{pred_dir}: no such folder")
    found = sorted(gt_dir.rglob("*.gt.npy"))
    if not found:
        raise InputError(f"{gt_dir}: no ground truth (*.gt.npy) found")
    out = []
    for path in found:
        rel = path.relative_to(gt_dir).as_posix()[: -len(".gt.npy")]
        out.append((rel, path, pred_dir / f"{rel}.labels.npy"))
    return out


def _failed_in_run(pred_dir: Path) -> dict[str, str]:
    """Images the manifest in ``pred_dir`` marks failed or running before their labels were made.

    ``running``: a run was killed before it recorded the image.

    Returns
    -------
    dict
        Relative stem: one line saying why (none without a manifest).

    Raises
    ------
    InputError
        When the manifest is damaged.
    """
    from ..batch.runner import MANIFEST, read_manifest
    from ..errors import InputError, OutputError

    try:
        images = read_manifest(pred_dir).get("images", {})
    except OutputError as exc:
        raise InputError(str(exc)) from None
    why = {"failed": lambda e: f"records that it failed ({e.get('error', 'no reason given')})",
           "running": lambda e: "records that a run stopped before it was done (killed?); "
                                "finish it with --resume"}
    return {rel: f"not scored: {pred_dir / MANIFEST} {why[entry['status']](entry)}"
            for rel, entry in images.items()
            if entry.get("status") in why and "grow" not in entry.get("stages", [])}


def _one_image(rel: str, gt_path: Path, pred_path: Path, pred_dir: Path, tolerance: float,
               min_region: int, tolerances: Sequence[float], gt_parts: bool,
               max_tilt: float = DEFAULT_MAX_TILT) -> dict[str, Any]:
    from ..batch.io import read_npy
    from ..errors import InputError

    gt, pred = read_npy(gt_path), read_npy(pred_path)
    try:
        ov = overlap_table(gt, pred, min_region=min_region, gt_parts=gt_parts)
    except ValueError as exc:  # `pred` is the labels, `gt` the ground truth: name the files
        raise InputError(f"{pred_path} against {gt_path}: {exc}") from None
    res = classify(ov, tolerance)
    out: dict[str, Any] = {
        **res.counts(),
        "curve": [classify(ov, t).counts()["correct"] for t in tolerances],
        "instances": [{"kind": i.kind, "gt": list(i.gt), "machine": list(i.machine),
                       "score": i.score} for i in res.instances],
        "missed_labels": res.missed, "noise_labels": res.noise,
    }
    hs_path = pred_dir / f"{rel}.holdsite.json"
    if hs_path.exists():
        info_path = gt_path.with_name(gt_path.name[: -len(".npy")] + ".json")
        site, info = _read_holdsite(hs_path), _read_gt_info(info_path)
        out["holdsite"] = check_holdsite(site, gt, info)
        out["holdsite_object"] = check_object_holdsite(site, gt, info, max_tilt=max_tilt)
    return out


def _read_holdsite(path: Path) -> dict[str, Any] | None:
    """The ``"holdsite"`` of a ``holdsite.json``, checked: ``None`` or integer ``row``/``col``."""
    from ..batch.io import read_json
    from ..errors import InputError

    data = read_json(path)
    site = data.get("holdsite", ...) if isinstance(data, dict) else ...
    if site is None:
        return None
    if not isinstance(site, dict):
        raise InputError(f"{path}: not a holdsite.json of rangeseg (expected "
                         '{"holdsite": null or {"row": int, "col": int, ...}})')
    problem = _holdsite_problem(site)
    if problem:
        raise InputError(f"{path}: not a holdsite.json of rangeseg (its holdsite has {problem})")
    return site


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _holdsite_problem(site: Mapping[str, Any]) -> str | None:
    """What keeps a holdsite from being drawn, or None (:func:`check_holdsite`).

    Integer ``row`` and ``col``; a ``size`` (or ``window``) that ``[holdsite]
    size`` allows; a finite ``angle`` in degrees.
    """
    if not all(_is_int(site.get(k)) for k in ("row", "col")):
        return 'no integer "row" and "col"'
    for key in ("size", "window"):
        if site.get(key) is not None:
            try:
                check_value("holdsite", "size", site[key])
            except ConfigError as exc:  # "... = [0, 0]: expected a list of two integers ..."
                allowed = str(exc).rsplit(": expected ", 1)[-1]
                return f'"{key}" {shown_value(site[key])}, expected {allowed}'
    angle = site.get("angle")
    if angle is not None and not (isinstance(angle, int | float) and not isinstance(angle, bool)
                                  and math.isfinite(angle)):
        return f'"angle" {shown_value(angle)}, expected a finite number of degrees'
    return None


def _read_gt_info(path: Path) -> dict[str, Any]:
    """A ``gt.json`` of ``rangeseg synth``, checked to hold what :func:`check_holdsite` reads."""
    from ..batch.io import read_json
    from ..errors import InputError

    data = read_json(path)
    ok = (isinstance(data, dict) and isinstance(data.get("uncovered"), list)
          and all(isinstance(data.get(k), list) and all(isinstance(e, dict) and "id" in e
                                                        for e in data[k])
                  for k in ("surfaces", "objects"))
          and all("object" in e for e in data["surfaces"]))
    if not ok:
        raise InputError(f"{path}: not a gt.json of rangeseg synth (expected lists "
                         '"surfaces" [{"id", "object"}], "objects" [{"id"}], "uncovered")')
    return data


def evaluate_folder(pred_dir: str | Path, gt_dir: str | Path, *,
                    tolerance: float = DEFAULT_TOLERANCE,
                    min_region: int = DEFAULT_MIN_REGION,
                    tolerances: Sequence[float] = CURVE_TOLERANCES,
                    gt_parts: bool = False, max_tilt: float = DEFAULT_MAX_TILT
                    ) -> dict[str, Any]:
    """Score every ``GT/<stem>.gt.npy`` against ``PRED/<stem>.labels.npy``.

    Parameters
    ----------
    pred_dir
        Output folder of ``rangeseg run`` (``<stem>.labels.npy``, and
        ``<stem>.holdsite.json`` when present). An image its manifest records
        as failed before its labels were made is an error, not scored.
    gt_dir
        Folder of ``rangeseg synth`` (``<stem>.gt.npy`` and ``<stem>.gt.json``),
        searched recursively; ``a/b.gt.npy`` pairs with ``PRED/a/b.labels.npy``.
    tolerance, min_region
        As in :func:`hoover_compare`.
    tolerances
        Tolerances of the correct-detection curve.
    gt_parts
        Judge each 8-connected patch of a GT label on its own (Notes, rule
        4); the instances' and ``missed_labels``' GT labels are then those of
        :func:`connected_parts`. The holdsite check uses the GT labels as
        they are.
    max_tilt
        Largest tilt of a usable holdsite's approach (:func:`check_object_holdsite`).

    Returns
    -------
    dict
        ``{"total": {gt_regions, correct, over, under, missed, noise, ...,
        "curve": {"tolerance": [...], "correct": [...]}, "holdsite":
        {"checked", "ok"}, "holdsite_object": {"checked", "ok"}}, "images":
        {stem: {...} or {"error": ...}},
        "errors": [...], "tolerance", "min_region", "gt_parts"}``.

    Raises
    ------
    InputError
        When a folder is missing or holds no ground truth, or PRED's manifest
        is damaged.
    ValueError
        For a tolerance or ``min_region`` out of range.
    """
    from ..errors import InputError, RangesegError

    tolerance = check_tolerance(tolerance)
    tolerances = tuple(tolerances)  # read twice: checked here, then counted
    for t in tolerances:
        check_tolerance(t)
    if not _is_int(min_region) or min_region < 0:
        raise ValueError(f"`min_region` {min_region!r} must be an integer >= 0")
    _check_max_tilt(max_tilt)
    pred_dir, gt_dir = Path(pred_dir), Path(gt_dir)
    images: dict[str, Any] = {}
    errors: list[str] = []
    pairs = _pairs(pred_dir, gt_dir)
    failed = _failed_in_run(pred_dir)
    for rel, gt_path, pred_path in pairs:
        try:
            if rel in failed:
                raise InputError(failed[rel])
            images[rel] = _one_image(rel, gt_path, pred_path, pred_dir, tolerance,
                                     min_region, tolerances, bool(gt_parts), max_tilt)
        except (RangesegError, ValueError, KeyError, TypeError) as exc:
            reason = f"{rel}: {exc}"
            images[rel] = {"error": reason}
            errors.append(reason)
    return {"total": _totals(images, tolerances), "images": images, "errors": errors,
            "tolerance": tolerance, "min_region": min_region, "gt_parts": bool(gt_parts)}


def _totals(images: Mapping[str, Any], tolerances: Sequence[float]) -> dict[str, Any]:
    done = [v for v in images.values() if "error" not in v]
    total: dict[str, Any] = {k: sum(v[k] for v in done) for k in COUNT_KEYS}
    total["images"] = len(done)
    total["curve"] = {"tolerance": list(tolerances),
                      "correct": [sum(v["curve"][i] for v in done)
                                  for i in range(len(tolerances))]}
    checks = [v["holdsite"] for v in done if "holdsite" in v]
    total["holdsite"] = {"checked": len(checks), "ok": sum(c["ok"] for c in checks)}
    objects = [v["holdsite_object"] for v in done if "holdsite_object" in v]
    total["holdsite_object"] = {"checked": len(objects), "ok": sum(c["ok"] for c in objects)}
    return total


# --------------------------------------------------------------------------- plot


def plot_curve(curve: Mapping[str, Sequence[float]], path: str | Path, *,
               gt_regions: int | None = None, title: str = "") -> bool:
    """Plot correct detections against tolerance (Hoover et al.'s Fig. style) as a PNG.

    Parameters
    ----------
    curve
        ``{"tolerance": [...], "correct": [...]}`` as in :func:`evaluate_folder`.
    path
        PNG file to write (atomically).
    gt_regions
        Drawn as a dashed line: the most correct detections possible.
    title
        Plot title.

    Returns
    -------
    bool
        False when matplotlib is not installed (nothing written).
    """
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError:
        return False
    from ..batch.io import write_png

    fig = Figure(figsize=(5, 3.5), dpi=100)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(curve["tolerance"], curve["correct"], "o-", label="correct detections")
    if gt_regions is not None:
        ax.axhline(gt_regions, ls="--", color="grey", label=f"GT regions ({gt_regions})")
    ax.set_xlabel("compare tool tolerance T")
    ax.set_ylabel("correct detections")
    ax.set_ylim(bottom=0)
    ax.set_title(title or "Hoover et al. (1996) correct detections")
    ax.legend(loc="lower left")
    fig.tight_layout()
    canvas.draw()
    write_png(Path(path), np.asarray(canvas.buffer_rgba())[..., :3].copy())
    return True
