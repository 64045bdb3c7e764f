"""A synthetic depth camera for ``rangeseg synth``: bin-picking cells as a real sensor sees them.

Renders scenes like the frames of an Intel RealSense SR300 looking down into
a tote (the frames of ``sample_data/arc``): a perspective camera 0.5-0.9 m
above a table or a tote floor, items of 3-15 cm (boxes, lying and standing
cylinders, balls, bottles, frustums) dropped onto it and onto each other, the
tote's walls and rim at the image border, a gripper reaching in from one
border, and the defects of a structured-light sensor. Each frame comes with a
ground-truth surface label per pixel and the object of every surface, for
``rangeseg eval`` (:func:`rangeseg_cli.synth.evaluate.check_object_holdsite`).

Notes
-----
1. World and camera. The world is in millimetres, z up, the support (table
   or tote floor) at ``z = 0``. The camera looks down, tilted by a few
   degrees; its frame has x along image columns, y along rows and z along
   the optical axis. Pixel ``(u, v)`` (column, row) casts the ray
   ``((u - cx) / fx, (v - cy) / fy, 1)``: the ray parameter of a hit is its
   depth along the optical axis.
2. Ray casting (:func:`convex_entry`). Every solid is a convex body of
   :mod:`rangeseg_cli.synth.scenes` (half-spaces and at most one sphere or
   cylinder); a ray enters it at the largest of its entry parameters and
   leaves at the smallest exit. A z-buffer over all solids of all objects
   gives per pixel the depth, the object, the face and (from the face) the
   surface normal. All rays share the camera centre, so one solid costs a
   few vector operations over the image.
3. Placement. Items are dropped one after another on the support and the
   items below, on a 2 mm grid of vertical lines (as ``rangeseg synth``
   drops its parts), so they rest and lean on each other without
   interpenetrating.
4. Sensor (:class:`SensorModel`; each step a function of its own, seeded
   by its own stream): jumps smoothed over a few pixels
   (:func:`smooth_jumps`), flying pixels at jumps (:func:`flying_pixels`),
   the projector's shadow beside jumps (:func:`projector_shadow`), holes on
   steep faces (:func:`steep_holes`), dark items that return little light
   (:func:`dark_item_holes`), random dropouts (:func:`dropouts`), the
   working range, depth noise growing with the square of the depth
   (:func:`depth_noise`), disparity quantisation (:func:`quantise_disparity`,
   steps growing with the square of the depth) and the output unit
   (:func:`to_raw`).
5. Ground truth. Every face of an object seen by the camera is a surface
   (faces of one object with one name, such as the four rims of a tote's
   top, are one surface). A pixel's label is 0 where the sensor gives no
   reading and where smoothing or a flying pixel moved its depth more than
   ``gt_tolerance_mm`` off the surface: there the frame shows no surface.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Iterable, Sequence
from dataclasses import asdict, dataclass, field, replace
from itertools import combinations
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from .scenes import Convex, Grid, Pose, box, cylinder, frustum, pose, rotation, sphere

#: The SR300 of the ARC 2017 frames (suction-camera-intrinsics.txt), at 640x480.
SR300_INTRINSICS = (616.521545, 616.521606, 311.354492, 231.087402)
#: Image size (rows, cols) the camera models' intrinsics are given for.
MODEL_SIZE = (480, 640)


@dataclass(frozen=True)
class DepthUnit:
    """How depth is written: raw value per metre, file type and the preset that reads it."""

    name: str
    metres_per_raw: float
    suffix: str
    preset: str


#: Output depth units (``--depth-unit``): uint16 PNG or float32 NPY.
DEPTH_UNITS: dict[str, DepthUnit] = {u.name: u for u in (
    DepthUnit("0.1mm", 1e-4, ".png", "tenth-mm-depth"),
    DepthUnit("1mm", 1e-3, ".png", "mm-depth"),
    DepthUnit("m", 1.0, ".npy", "metre-depth"),
)}


@dataclass(frozen=True)
class SensorModel:
    """Parameters of the sensor's defects (module Notes, 4); zero turns a step off.

    Attributes
    ----------
    blur_px
        Depth jumps are smoothed into ramps over about twice this many pixels.
    jump_mm
        A 3x3 depth range above this is a jump (smoothing, flying pixels).
    flying_fraction
        Share of the pixels at jumps given a depth between both sides.
    baseline_mm
        Projector offset along the camera's +x axis (negative: -x); pixels
        the projector cannot light are invalid. 0 = no shadow, no
        disparity quantisation.
    steep_start_deg, steep_end_deg, steep_drop
        Faces seen at more than ``steep_start_deg`` from their normal lose
        pixels, up to the share ``steep_drop`` at ``steep_end_deg``.
    dark_fraction, dark_drop
        Share of the items that are dark (or shiny) and the share of their
        pixels without a reading.
    dropout_fraction
        Share of the pixels that start a small hole (a 3x3 blob).
    noise_at_1m_mm
        Standard deviation of the depth noise at 1 m; it grows with depth².
    smooth_noise_at_1m_mm, smooth_noise_px
        Standard deviation at 1 m (growing with depth²) of a second, spatially
        correlated depth error: white noise smoothed by a Gaussian of
        ``smooth_noise_px`` pixels, scaled to this deviation
        (:func:`smooth_depth_noise`). A real camera smooths its depth: its
        error over a surface grows with the surface's extent
        (``benchmarks/noise_scale.py``). 0 = off.
    disparity_step_px
        The disparity is rounded to this step (depth steps grow with depth²).
    min_range_mm, max_range_mm
        No reading closer or farther than these.
    gt_tolerance_mm
        Ground truth is 0 where smoothing or a flying pixel moved the depth more.
    """

    blur_px: float = 1.5
    jump_mm: float = 10.0
    flying_fraction: float = 0.3
    baseline_mm: float = 25.0
    steep_start_deg: float = 65.0
    steep_end_deg: float = 82.0
    steep_drop: float = 0.95
    dark_fraction: float = 0.1
    dark_drop: float = 0.7
    dropout_fraction: float = 0.0005
    noise_at_1m_mm: float = 3.0
    smooth_noise_at_1m_mm: float = 0.0
    smooth_noise_px: float = 2.0
    disparity_step_px: float = 1.0 / 32.0
    min_range_mm: float = 150.0
    max_range_mm: float = 1500.0
    gt_tolerance_mm: float = 3.0

    @classmethod
    def ideal(cls) -> SensorModel:
        """A perfect sensor: exact depth, only the output unit's rounding."""
        return cls(blur_px=0.0, flying_fraction=0.0, baseline_mm=0.0, steep_drop=0.0,
                   dark_fraction=0.0, dropout_fraction=0.0, noise_at_1m_mm=0.0,
                   disparity_step_px=0.0, min_range_mm=0.0, max_range_mm=1e9)

    @classmethod
    def smooth(cls) -> SensorModel:
        """The SR300's depth error as measured on the ARC frames' empty tote.

        Its own filtering leaves about 0.16 mm of noise per pixel but an
        error that grows with a surface's extent: the RMS of a quadric fitted
        to a k x k window is 0.18, 0.28 and 0.36 mm at k = 5, 15, 31
        (25th percentile, ``benchmarks/results/noise_scale.md``), and no
        steps of disparity show in its 0.1 mm readings. White noise of 0.4
        mm at 1 m and correlated noise of 0.7 mm at 1 m over 2 pixels, with
        no disparity rounding, give 0.18, 0.28 and 0.35 mm on the synthetic
        empty tote of seed 300 (0.23, 0.37, 0.47 on seed 301, its camera
        higher; the other defects as :class:`SensorModel`'s).
        """
        return cls(noise_at_1m_mm=0.4, smooth_noise_at_1m_mm=0.7, smooth_noise_px=2.0,
                   disparity_step_px=0.0)


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics at :data:`MODEL_SIZE`, the sensor's defects and a tilt of the mount.

    ``tilt``: degrees the camera is turned about its x axis (its rows look
    along the table) on top of each scene's few random degrees; 0 looks
    straight down.
    """

    name: str
    intrinsics: tuple[float, float, float, float]
    sensor: SensorModel
    tilt: float = 0.0


#: Named cameras of ``rangeseg synth --camera``.
CAMERAS: dict[str, CameraModel] = {c.name: c for c in (
    CameraModel("sr300", SR300_INTRINSICS, SensorModel()),
    CameraModel("sr300-smooth", SR300_INTRINSICS, SensorModel.smooth()),
    CameraModel("ideal", SR300_INTRINSICS, SensorModel.ideal()),
)}


# =========================================================================== the camera


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera: intrinsics, image size and pose in the world.

    ``R`` has the camera's x, y, z axes (columns, rows, optical axis) as its
    columns in world coordinates; ``t`` is the camera centre (mm).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    shape: tuple[int, int]
    R: np.ndarray = field(default_factory=lambda: np.diag([1.0, -1.0, -1.0]))
    t: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 600.0]))

    def rays(self) -> np.ndarray:
        """(H*W, 3) camera-frame rays ``((u - cx)/fx, (v - cy)/fy, 1)``, row-major."""
        h, w = self.shape
        v, u = np.mgrid[0:h, 0:w].astype(float)
        return np.stack([((u - self.cx) / self.fx).ravel(), ((v - self.cy) / self.fy).ravel(),
                         np.ones(h * w)], axis=-1)

    def pixel_ray(self, u: float, v: float) -> np.ndarray:
        """World direction of the ray through pixel ``(u, v)`` (column, row), depth 1."""
        return self.R @ np.array([(u - self.cx) / self.fx, (v - self.cy) / self.fy, 1.0])

    def on_plane(self, u: float, v: float, z: float = 0.0) -> np.ndarray:
        """World point where the ray through ``(u, v)`` meets the plane of height ``z``."""
        d = self.pixel_ray(u, v)
        return self.t + (z - self.t[2]) / d[2] * d

    def matrix(self) -> np.ndarray:
        """The 3x3 camera matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def camera_for(model: CameraModel, shape: tuple[int, int], *, height: float,
               tilt: tuple[float, float] = (0.0, 0.0)) -> Camera:
    """A camera of ``model`` at ``shape``, ``height`` mm above the support, looking down.

    The intrinsics scale with the image (``fx`` by cols / 640, ``fy`` by
    rows / 480); ``tilt`` turns the camera about its x and y axes (degrees);
    the optical axis meets the support at the world origin.
    """
    fx, fy, cx, cy = model.intrinsics
    sy, sx = shape[0] / MODEL_SIZE[0], shape[1] / MODEL_SIZE[1]
    r = np.diag([1.0, -1.0, -1.0]) @ rotation(roll=tilt[0], pitch=tilt[1])
    axis = r[:, 2]  # points down: the optical axis reaches z = 0 after height / -axis[2]
    centre = np.array([-height / -axis[2] * axis[0], -height / -axis[2] * axis[1], height])
    return Camera(fx * sx, fy * sy, (cx + 0.5) * sx - 0.5, (cy + 0.5) * sy - 0.5,
                  (int(shape[0]), int(shape[1])), r, centre)


# =========================================================================== ray casting


def convex_entry(body: Convex, origin: np.ndarray, dirs: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Where rays ``origin + s * dirs`` (s > 0) enter a convex body, and through which face.

    Parameters
    ----------
    body
        A :class:`~rangeseg_cli.synth.scenes.Convex` (half-spaces, at most one quadric).
    origin
        (3,) common start of the rays, world coordinates.
    dirs
        (N, 3) ray directions, world coordinates (not necessarily unit).

    Returns
    -------
    s, face
        (N,) entry parameters (``inf`` where a ray misses or starts inside)
        and int32 face indices into ``body.faces``.
    """
    o = body.pose.R.T @ (origin - body.pose.t)
    d = dirs @ body.pose.R
    n = len(d)
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    face = np.zeros(n, np.int32)
    miss = np.zeros(n, bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for k, row in enumerate(body.planes):
            nd, gap = d @ row[:3], row[3] - float(o @ row[:3])
            s = gap / nd
            enter = (nd < 0) & (s > lo)
            lo[enter], face[enter] = s[enter], k
            hi = np.where(nd > 0, np.minimum(hi, s), hi)
            miss |= (nd == 0) & (gap < 0)
        if body.quadric is not None:
            q0, q1 = _quadric_interval(body, o, d)
            enter = q0 > lo
            lo[enter], face[enter] = q0[enter], len(body.planes)
            hi = np.minimum(hi, q1)
    hit = ~miss & (lo <= hi) & (lo > 0)
    return np.where(hit, lo, np.inf), face


def _quadric_interval(body: Convex, o: np.ndarray, d: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Entry and exit parameters of rays through the body's sphere or infinite cylinder."""
    axes = 3 if body.quadric == "sphere" else 2
    oo, dd = o[:axes], d[:, :axes]
    a = np.einsum("ij,ij->i", dd, dd)
    b = 2.0 * (dd @ oo)
    c = float(oo @ oo) - body.radius**2
    with np.errstate(divide="ignore", invalid="ignore"):
        disc = b * b - 4 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        q0, q1 = (-b - root) / (2 * a), (-b + root) / (2 * a)
    parallel = a < 1e-12  # a cylinder along the ray: inside it all along, or never
    out = (disc < 0) | (parallel & (c > 0))
    q0 = np.where(parallel & ~out, -np.inf, np.where(out, np.inf, q0))
    q1 = np.where(parallel & ~out, np.inf, np.where(out, -np.inf, q1))
    return q0, q1


def body_corners(body: Convex) -> np.ndarray | None:
    """(K, 3) world points whose convex hull holds ``body``; None for an unbounded body.

    The corners of the body's half-spaces (with, for a quadric, the box
    around its sphere or cylinder), found by intersecting every three planes
    and keeping the points inside all of them.
    """
    planes = body.planes
    if body.quadric is not None:
        r = body.radius
        extra = [[1, 0, 0, r], [-1, 0, 0, r], [0, 1, 0, r], [0, -1, 0, r]]
        if body.quadric == "sphere":
            extra += [[0, 0, 1, r], [0, 0, -1, r]]
        planes = np.vstack([planes, extra]) if len(planes) else np.array(extra, float)
    corners = []
    for i, j, k in combinations(range(len(planes)), 3):
        a = planes[[i, j, k], :3]
        if abs(np.linalg.det(a)) < 1e-9:
            continue
        p = np.linalg.solve(a, planes[[i, j, k], 3])
        if np.all(planes[:, :3] @ p <= planes[:, 3] + 1e-6):
            corners.append(p)
    if len(corners) < 4 or np.max(np.abs(corners)) > 1e5:
        return None
    return body.pose.apply(np.array(corners))


def bounding_sphere(body: Convex) -> tuple[np.ndarray, float] | None:
    """A sphere (world centre, radius) holding ``body``, or None for an unbounded body."""
    pts = body_corners(body)
    if pts is None:
        return None
    centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
    return centre, float(np.max(np.linalg.norm(pts - centre, axis=1)))


def face_normals(body: Convex, face: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) outward unit normals (world) of ``body`` at world ``points`` on faces ``face``."""
    local = (points - body.pose.t) @ body.pose.R
    n = np.zeros_like(local)
    planar = face < len(body.planes)
    n[planar] = body.planes[face[planar], :3]
    curved = ~planar
    if body.quadric == "sphere":
        n[curved] = local[curved]
    elif body.quadric == "cylinder":
        n[curved, :2] = local[curved, :2]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n @ body.pose.R.T


# =========================================================================== scene objects


@dataclass(frozen=True, eq=False)
class Item:
    """An object of a camera scene: convex solids, pickable or not (support, tote, gripper)."""

    name: str
    solids: tuple[Convex, ...]
    pickable: bool
    kind: str

    def moved(self, outer: Pose) -> Item:
        """The item moved by ``outer``."""
        return replace(self, solids=tuple(s.moved(outer) for s in self.solids))

    @property
    def surface_names(self) -> list[tuple[str, str]]:
        """Distinct ``(name, kind)`` of the faces, in order of declaration."""
        seen: dict[tuple[str, str], None] = {}
        for s in self.solids:
            seen.update(dict.fromkeys(s.faces))
        return list(seen)


@dataclass(frozen=True, eq=False)
class Render:
    """The noise-free view: depth (mm), object, surface label and incidence per pixel."""

    depth: np.ndarray
    obj: np.ndarray
    gt: np.ndarray
    cos_incidence: np.ndarray
    surfaces: list[dict[str, Any]]
    covered: list[bool]


def pixels_near(camera: Camera, body: Convex) -> np.ndarray | None:
    """Flat indices of the pixels whose rays may meet ``body``; None = all of them.

    The box of the image around the projections of the body's
    :func:`body_corners` (all pixels for an unbounded body or one reaching
    behind the camera).
    """
    pts = body_corners(body)
    if pts is None:
        return None
    cam = (pts - camera.t) @ camera.R
    if np.min(cam[:, 2]) <= 1.0:
        return None
    us = camera.cx + camera.fx * cam[:, 0] / cam[:, 2]
    vs = camera.cy + camera.fy * cam[:, 1] / cam[:, 2]
    h, w = camera.shape
    u0, u1 = max(math.floor(us.min()), 0), min(math.ceil(us.max()), w - 1)
    v0, v1 = max(math.floor(vs.min()), 0), min(math.ceil(vs.max()), h - 1)
    if u0 > u1 or v0 > v1:
        return np.zeros(0, np.int64)
    rows, cols = np.arange(v0, v1 + 1), np.arange(u0, u1 + 1)
    return (rows[:, None] * w + cols[None, :]).ravel()


def render_items(camera: Camera, items: Sequence[Item]) -> Render:
    """Z-buffer the items' solids along the camera's rays (module Notes, 2).

    Returns
    -------
    Render
        (H, W) arrays: ``depth`` in mm along the optical axis (``inf`` where
        nothing is hit), ``obj`` (index into ``items``, -1 = none), ``gt``
        (surface labels 1..K, 0 = none), ``cos_incidence`` (cosine of the
        angle between the surface normal and the line of sight), and per
        surface ``{id, object, kind, name, pixels}``; ``covered`` per item:
        whether another pickable item lies in front of it somewhere.
    """
    rays = camera.rays()
    world = rays @ camera.R.T
    n = len(rays)
    best = np.full(n, np.inf)
    obj = np.full(n, -1, np.int32)
    code = np.full(n, -1, np.int64)
    normal = np.zeros((n, 3))
    width = max(len(it.surface_names) for it in items) if items else 1
    nearest = []
    every = np.arange(n)
    for i, item in enumerate(items):
        index = {f: j for j, f in enumerate(item.surface_names)}
        own = np.full(n, np.inf)
        for solid in item.solids:
            idx = pixels_near(camera, solid)
            idx = every if idx is None else idx
            s, face = convex_entry(solid, camera.t, world[idx])
            own[idx] = np.minimum(own[idx], s)
            better = s < best[idx]
            if not better.any():
                continue
            win, s, face = idx[better], s[better], face[better]
            lookup = np.array([index[f] for f in solid.faces], np.int64)
            best[win], obj[win] = s, i
            code[win] = i * width + lookup[face]
            normal[win] = face_normals(solid, face, camera.t + s[:, None] * world[win])
        nearest.append(own)
    gt, surfaces = _surface_labels(items, code, width)
    sight = world / np.linalg.norm(world, axis=1, keepdims=True)
    cos = np.abs(np.einsum("ij,ij->i", normal, sight))
    shape = camera.shape
    covered = _covered(items, nearest, obj, best)
    return Render(best.reshape(shape), obj.reshape(shape), gt.reshape(shape),
                  cos.reshape(shape), surfaces, covered)


def _surface_labels(items: Sequence[Item], code: np.ndarray, width: int
                    ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    present = np.unique(code[code >= 0])
    lookup = np.zeros(len(items) * width + 1, np.int32)
    lookup[present] = np.arange(1, len(present) + 1)
    gt = np.where(code >= 0, lookup[np.maximum(code, 0)], 0).astype(np.int32)
    counts = np.bincount(gt, minlength=len(present) + 1)
    surfaces = []
    for k, c in enumerate(present.tolist(), start=1):
        i, j = divmod(c, width)
        name, kind = items[i].surface_names[j]
        surfaces.append({"id": k, "object": i, "kind": kind, "name": name,
                         "pixels": int(counts[k])})
    return gt, surfaces


def _covered(items: Sequence[Item], nearest: list[np.ndarray], obj: np.ndarray,
             best: np.ndarray) -> list[bool]:
    pickable = np.array([it.pickable for it in items] + [False])
    front = pickable[obj]  # obj -1 picks the trailing False
    out = []
    for i, own in enumerate(nearest):
        seen = np.isfinite(own) & (obj != i) & front & (best < own - 1e-6)
        out.append(bool(seen.any()))
    return out


# =========================================================================== sensor steps


def jump_mask(depth: np.ndarray, jump_mm: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans more than ``jump_mm`` of depth."""
    spread = ndimage.maximum_filter(depth, 3) - ndimage.minimum_filter(depth, 3)
    return spread > jump_mm


def smooth_jumps(depth: np.ndarray, *, blur_px: float, jump_mm: float) -> np.ndarray:
    """Depth jumps smoothed into ramps, as a real sensor's matching window does.

    Within ``ceil(2 * blur_px)`` pixels of a jump (:func:`jump_mask`) the
    depth is replaced by its Gaussian blur of sigma ``blur_px``; elsewhere
    it is kept. ``blur_px = 0`` returns the depth unchanged.
    """
    if blur_px <= 0:
        return depth.copy()
    near = ndimage.binary_dilation(jump_mask(depth, jump_mm),
                                   iterations=max(1, math.ceil(2 * blur_px)))
    return np.where(near, ndimage.gaussian_filter(depth, blur_px, mode="nearest"), depth)


def flying_pixels(depth: np.ndarray, rng: np.random.Generator, *, fraction: float,
                  jump_mm: float) -> np.ndarray:
    """A share ``fraction`` of the pixels at jumps set between the near and far side.

    Each chosen pixel takes ``near + t (far - near)``, ``t`` uniform in
    0.15..0.85, with near and far the least and largest depth of its 3x3
    neighbourhood: the mixed returns seen along object outlines.
    """
    out = depth.copy()
    if fraction <= 0:
        return out
    at = np.flatnonzero(jump_mask(depth, jump_mm).ravel())
    draw = rng.random(at.size)
    pick = at[draw < fraction]
    lo = ndimage.minimum_filter(depth, 3).ravel()[pick]
    hi = ndimage.maximum_filter(depth, 3).ravel()[pick]
    out.ravel()[pick] = lo + rng.uniform(0.15, 0.85, pick.size) * (hi - lo)
    return out


def projector_shadow(depth: np.ndarray, *, fx: float, baseline_mm: float,
                     slack_px: float = 0.25) -> np.ndarray:
    """Pixels the projector cannot light: the shadow beside each jump, on its far side.

    With the projector ``baseline_mm`` along the camera's +x axis, a point at
    column ``u`` and depth ``z`` lies on projector column ``u - fx b / z``.
    Along a row (an epipolar line) the projector column must grow with ``u``;
    a pixel whose projector column is beyond that of a pixel farther toward
    the projector is hidden from it by that nearer surface. The shadow lies
    on the far (background) side of a jump, away from the projector, and is
    about ``fx b (1/z_near - 1/z_far)`` pixels wide.

    Returns
    -------
    numpy.ndarray
        bool (H, W), True where shadowed; all False for ``baseline_mm = 0``.
    """
    if baseline_mm == 0:
        return np.zeros(depth.shape, bool)
    if baseline_mm < 0:
        return projector_shadow(depth[:, ::-1], fx=fx, baseline_mm=-baseline_mm,
                                slack_px=slack_px)[:, ::-1]
    cols = np.arange(depth.shape[1], dtype=float)
    with np.errstate(divide="ignore"):
        proj = cols[None, :] - fx * baseline_mm / depth
    ahead = np.minimum.accumulate(proj[:, ::-1], axis=1)[:, ::-1]
    ahead = np.concatenate([ahead[:, 1:], np.full((depth.shape[0], 1), np.inf)], axis=1)
    return proj > ahead + slack_px


def steep_holes(cos_incidence: np.ndarray, rng: np.random.Generator, *, start_deg: float,
                end_deg: float, drop: float) -> np.ndarray:
    """Pixels lost on faces seen at a grazing angle.

    The chance of losing a pixel rises linearly from 0 at ``start_deg``
    between the surface normal and the line of sight to ``drop`` at
    ``end_deg`` and beyond.
    """
    angle = np.degrees(np.arccos(np.clip(cos_incidence, 0.0, 1.0)))
    span = max(end_deg - start_deg, 1e-9)
    chance = drop * np.clip((angle - start_deg) / span, 0.0, 1.0)
    return rng.random(angle.shape) < chance


def dark_item_holes(obj: np.ndarray, dark: Sequence[int], rng: np.random.Generator, *,
                    drop: float) -> np.ndarray:
    """Pixels lost on dark or shiny items: a share ``drop`` of each one's pixels, in blobs."""
    on = np.isin(obj, list(dark))
    seeds = on & (rng.random(obj.shape) < drop / 3)
    return ndimage.binary_dilation(seeds, np.ones((2, 2), bool)) & on


#: :func:`crease`: height (mm) and width (pixels, the Gaussian's sigma) of a soft item's folds.
CREASE_MM, CREASE_PX = 4.0, 5.0


def crease(depth: np.ndarray, obj: np.ndarray, soft: Sequence[int],
           rng: np.random.Generator) -> np.ndarray:
    """The depth of the ``soft`` items (a bag, a cloth) creased into bumps and folds.

    :func:`smooth_field` over :data:`CREASE_PX` pixels, scaled to
    :data:`CREASE_MM`, moves each soft item's visible pixels along the ray,
    tapered by the distance to the item's border over twice that width (a
    tenth at its outermost pixels) so that no step of more than a fold's
    tenth appears there: a face no surface of order <= 2 explains, as a
    real bin's bags and cloths are (the ARC frame's, ``docs/quality.md``).
    Its ground truth stays one surface.
    """
    if not soft:
        return depth
    field = CREASE_MM * smooth_field(depth.shape, rng, CREASE_PX)
    out = depth.copy()
    for i in soft:
        on = obj == i
        taper = np.minimum(ndimage.distance_transform_edt(on) / (2.0 * CREASE_PX), 1.0)
        out[on] += (field * taper)[on]
    return out


def dropouts(shape: tuple[int, int], rng: np.random.Generator, *, fraction: float
             ) -> np.ndarray:
    """Small random holes: a share ``fraction`` of the pixels start a 3x3 blob."""
    seeds = rng.random(shape) < fraction
    return ndimage.binary_dilation(seeds, np.ones((3, 3), bool))


def depth_noise(depth: np.ndarray, rng: np.random.Generator, *, noise_at_1m_mm: float
                ) -> np.ndarray:
    """Gaussian depth noise of sigma ``noise_at_1m_mm * (z / 1 m)**2``."""
    sigma = noise_at_1m_mm * (depth / 1000.0) ** 2
    return depth + sigma * rng.standard_normal(depth.shape)


def smooth_field(shape: tuple[int, ...], rng: np.random.Generator, sigma_px: float
                 ) -> np.ndarray:
    """White noise smoothed by a Gaussian of ``sigma_px`` pixels, scaled to unit variance."""
    field = ndimage.gaussian_filter(rng.standard_normal(shape), sigma_px)
    return field / max(float(field.std()), 1e-12)


def smooth_depth_noise(depth: np.ndarray, rng: np.random.Generator, *,
                       noise_at_1m_mm: float, sigma_px: float) -> np.ndarray:
    """Correlated depth error of sigma ``noise_at_1m_mm * (z / 1 m)**2``.

    :func:`smooth_field` (its correlation length is about ``2 * sigma_px``)
    scaled by that sigma; none when either is 0.
    """
    if noise_at_1m_mm <= 0 or sigma_px <= 0:
        return depth.copy()
    return depth + noise_at_1m_mm * (depth / 1000.0) ** 2 * smooth_field(depth.shape, rng,
                                                                         sigma_px)


def quantise_disparity(depth: np.ndarray, *, fx: float, baseline_mm: float,
                       step_px: float) -> np.ndarray:
    """Depth from a disparity ``fx b / z`` rounded to ``step_px``: steps of ``z² step / (fx b)``."""
    if baseline_mm == 0 or step_px <= 0:
        return depth.copy()
    k = fx * abs(baseline_mm)
    disparity = np.maximum(np.rint(k / depth / step_px), 1.0) * step_px
    return k / disparity


def to_raw(depth_mm: np.ndarray, valid: np.ndarray, unit: DepthUnit) -> np.ndarray:
    """Depth in ``unit``: uint16 (0 = invalid, also beyond 65534) or float32 metres (NaN)."""
    metres = depth_mm / 1000.0
    if unit.suffix == ".npy":
        return np.where(valid, metres, np.nan).astype(np.float32)
    raw = np.rint(np.where(valid, metres / unit.metres_per_raw, 0.0))
    return np.where(raw > 65534, 0, raw).astype(np.uint16)


# =========================================================================== scenes


def support_plane(name: str, z: float = 0.0) -> Item:
    """An endless horizontal support (table) whose top is at height ``z`` (mm), not pickable."""
    plane = Convex(np.array([[0, 0, 1, z], [0, 0, -1, 1000.0 - z]]),
                   ((name, "planar"), (f"{name} underside", "planar")))
    return Item(name, (plane,), False, "support")


def _centred(body: Convex, sz: float) -> Convex:
    return body.moved(pose(0, 0, -sz / 2))


def _random_item(rng: np.random.Generator, i: int) -> tuple[str, tuple[Convex, ...]]:
    """One item of 3-15 cm: kind and solids, resting on z = 0 before it is posed."""
    kind = ITEM_KINDS[int(rng.integers(len(ITEM_KINDS)))]
    name = f"{kind} {i}"
    if kind == "box":
        sx, sy, sz = rng.uniform(40, 150), rng.uniform(30, 110), rng.uniform(30, 100)
        return name, (box(sx, sy, sz, name),)
    if kind == "lying cylinder":
        r, length = rng.uniform(18, 45), rng.uniform(60, 150)
        return name, (_centred(cylinder(r, length, name), length).moved(pose(pitch=90)),)
    if kind == "standing cylinder":
        return name, (cylinder(rng.uniform(18, 45), rng.uniform(40, 140), name),)
    if kind == "ball":
        r = rng.uniform(20, 50)
        return name, (sphere(r, name).moved(pose(z=r)),)
    if kind == "bottle":
        return name, _bottle(rng, name)
    bottom = rng.uniform(50, 120)
    return name, (frustum(bottom, bottom * rng.uniform(0.4, 0.8), rng.uniform(30, 80), name),)


def _bottle(rng: np.random.Generator, name: str) -> tuple[Convex, ...]:
    """A lying bottle: body, rounded shoulder and neck along x."""
    r, length = rng.uniform(25, 40), rng.uniform(90, 140)
    lie = pose(pitch=90)
    body = _centred(cylinder(r, length, f"{name} body"), length).moved(lie)
    shoulder = sphere(r, f"{name} shoulder").moved(pose(length / 2))
    neck_r = r * 0.4
    neck = cylinder(neck_r, r * 1.6, f"{name} neck").moved(pose(pitch=90)).moved(
        pose(length / 2, 0, 0))
    return tuple(s.moved(pose(z=r)) for s in (body, shoulder, neck))


#: Kinds of items in a pile.
ITEM_KINDS = ("box", "lying cylinder", "standing cylinder", "ball", "bottle", "frustum")


def _drop_items(shapes: list[tuple[str, tuple[Convex, ...]]], spots: np.ndarray,
                rng: np.random.Generator, area: tuple[float, float, float, float],
                ceiling: float = math.inf) -> list[Item]:
    """Pose the items at ``spots`` and lower each onto what lies below (Notes, 3).

    An item whose top would come to rest above ``ceiling`` (mm) is left out:
    a heaped tote's items stay out of the camera's range limit.
    """
    x0, x1, y0, y1 = area
    xs, ys = np.meshgrid(np.arange(x0, x1, 2.0), np.arange(y0, y1, 2.0))
    grid = Grid(xs.shape, 1.0, xs.ravel(), ys.ravel())
    envelope = np.zeros(grid.x.shape)
    out = []
    for (name, solids), (x, y) in zip(shapes, spots, strict=True):
        roll, pitch = rng.uniform(-12, 12, 2) * (rng.random() < 0.6)
        at = pose(x, y, roll=roll, pitch=pitch, yaw=rng.uniform(0, 360))
        placed = tuple(s.moved(at) for s in solids)
        sel = _under(placed, grid)
        sub = Grid((1, sel.size), 1.0, grid.x[sel], grid.y[sel])
        spans = [s.span(sub) for s in placed]
        lo = np.min([sp.lo for sp in spans], axis=0)
        hi = np.max([sp.hi for sp in spans], axis=0)
        hit = np.isfinite(lo)
        dz = float(np.max(envelope[sel][hit] - lo[hit])) if hit.any() else 0.0
        if hit.any() and float(np.max(hi[hit])) + dz > ceiling:
            continue
        envelope[sel[hit]] = np.maximum(envelope[sel[hit]], hi[hit] + dz)
        kind = name.rsplit(" ", 1)[0]
        out.append(Item(name, tuple(s.moved(pose(z=dz)) for s in placed), True, kind))
    return out


def _under(solids: Sequence[Convex], grid: Grid) -> np.ndarray:
    """Indices of the grid's vertical lines that may meet one of ``solids``."""
    keep = np.zeros(grid.x.shape, bool)
    for solid in solids:
        bound = bounding_sphere(solid)
        if bound is None:
            return np.arange(grid.x.size)
        (cx, cy, _), r = bound
        keep |= (np.abs(grid.x - cx) <= r) & (np.abs(grid.y - cy) <= r)
    return np.flatnonzero(keep)


def _spots(camera: Camera, rng: np.random.Generator, count: int,
           bounds: tuple[float, float, float, float]) -> np.ndarray:
    """``count`` support points seen near the image's middle, kept inside ``bounds``."""
    h, w = camera.shape
    u = rng.uniform(0.25 * w, 0.75 * w, count)
    v = rng.uniform(0.25 * h, 0.75 * h, count)
    pts = np.array([camera.on_plane(a, b)[:2] for a, b in zip(u, v, strict=True)])
    x0, x1, y0, y1 = bounds
    return np.column_stack([np.clip(pts[:, 0], x0, x1), np.clip(pts[:, 1], y0, y1)])


def _view_box(camera: Camera, z: float = 0.0) -> tuple[float, float, float, float]:
    """Bounding box (x0, x1, y0, y1) of the support seen in the image at height ``z``."""
    h, w = camera.shape
    corners = np.array([camera.on_plane(u, v, z)[:2]
                        for u, v in ((0, 0), (w - 1, 0), (0, h - 1), (w - 1, h - 1))])
    return (float(corners[:, 0].min()), float(corners[:, 0].max()),
            float(corners[:, 1].min()), float(corners[:, 1].max()))


def _pile_items(camera: Camera, rng: np.random.Generator, count: int,
                bounds: tuple[float, float, float, float], ceiling: float = math.inf
                ) -> list[Item]:
    shapes = [_random_item(rng, i) for i in range(1, count + 1)]
    spots = _spots(camera, rng, count, bounds)
    x0, x1, y0, y1 = bounds
    return _drop_items(shapes, spots, rng, (x0 - 150, x1 + 150, y0 - 150, y1 + 150), ceiling)


def _tote(rng: np.random.Generator, inner: tuple[float, float, float, float]
          ) -> tuple[Item, Item]:
    """The tote's floor and its walls, flaring outward by a draft angle, with a rim on top.

    ``inner`` is the floor inside the walls (x0, x1, y0, y1); the floor is 10 mm
    thick and stands on the table.
    """
    x0, x1, y0, y1 = inner
    height, t, draft = rng.uniform(140, 260), 6.0, rng.uniform(3, 12)
    rim_w, rim_t = rng.uniform(18, 30), 8.0
    flare = height * math.tan(math.radians(draft))  # how far the top edge moves out
    slant = height / math.cos(math.radians(draft))
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    lx, ly = x1 - x0 + 2 * flare + 2 * t, y1 - y0 + 2 * flare + 2 * t
    walls = [box(t, ly, slant, "tote wall x").moved(pose(-t / 2)).moved(
                 pose(x0, cy, pitch=-draft)),
             box(t, ly, slant, "tote wall x").moved(pose(t / 2)).moved(
                 pose(x1, cy, pitch=draft)),
             box(lx, t, slant, "tote wall y").moved(pose(0, -t / 2)).moved(
                 pose(cx, y0, roll=draft)),
             box(lx, t, slant, "tote wall y").moved(pose(0, t / 2)).moved(
                 pose(cx, y1, roll=-draft))]
    ox0, ox1, oy0, oy1 = x0 - flare, x1 + flare, y0 - flare, y1 + flare  # the opening
    oly = oy1 - oy0
    olx = ox1 - ox0 + 2 * rim_w - 4
    rims = [box(rim_w, oly, rim_t, "tote rim").moved(pose(ox0 - rim_w / 2 + 2, cy, height)),
            box(rim_w, oly, rim_t, "tote rim").moved(pose(ox1 + rim_w / 2 - 2, cy, height)),
            box(olx, rim_w, rim_t, "tote rim").moved(pose(cx, oy0 - rim_w / 2 + 2, height)),
            box(olx, rim_w, rim_t, "tote rim").moved(pose(cx, oy1 + rim_w / 2 - 2, height))]
    floor = box(x1 - x0 + 2 * t, y1 - y0 + 2 * t, 10.0, "tote floor").moved(pose(cx, cy, -10.0))
    return Item("tote floor", (floor,), False, "support"), Item(
        "tote", tuple(walls + rims), False, "tote")


def _camera(model: CameraModel, shape: tuple[int, int], rng: np.random.Generator,
            heights: tuple[float, float]) -> Camera:
    tilt = rng.uniform(-12, 12, 2)
    return camera_for(model, shape, height=rng.uniform(*heights),
                      tilt=(tilt[0] + model.tilt, tilt[1]))


def _table_scene(model: CameraModel, shape: tuple[int, int], rng: np.random.Generator
                 ) -> tuple[Camera, list[Item], list[Item]]:
    cam = _camera(model, shape, rng, (500, 900))
    table = support_plane("table")
    bounds = _view_box(cam)
    items = _pile_items(cam, rng, int(rng.integers(6, 15)), bounds)
    return cam, [table, *items], [table]


def _tote_scene(model: CameraModel, shape: tuple[int, int], rng: np.random.Generator,
                count: int, packed: bool = False) -> tuple[Camera, list[Item], list[Item]]:
    """A tote with ``count`` items; ``packed``: heaped up to 250 mm below the camera.

    Many items hide the floor (the support is then no plane of the image);
    none comes within the sensor's range limit of the camera.
    """
    cam = _camera(model, shape, rng, (600, 900))
    x0, x1, y0, y1 = _view_box(cam)
    wx, wy = x1 - x0, y1 - y0
    inset = rng.uniform(-0.04, 0.14, 4)
    inner = (x0 + inset[0] * wx, x1 - inset[1] * wx, y0 + inset[2] * wy, y1 - inset[3] * wy)
    floor, tote = _tote(rng, inner)
    table = support_plane("table", -10.0)
    margin = 40.0
    bounds = (inner[0] + margin, inner[1] - margin, inner[2] + margin, inner[3] - margin)
    ceiling = float(cam.t[2]) - 250.0 if packed else math.inf
    items = _pile_items(cam, rng, count, bounds, ceiling) if count else []
    return cam, [floor, tote, table, *items], [floor, tote, table]


def _gripper(cam: Camera, rng: np.random.Generator, clearance: float) -> Item:
    """Arm, suction tool and two fingers reaching in from one image border, near the camera."""
    h, w = cam.shape
    depth = rng.uniform(180.0, 300.0)
    depth = max(120.0, min(depth, clearance - 90.0))
    side = int(rng.integers(4))
    reach = rng.uniform(0.3, 0.5)
    across = rng.uniform(0.3, 0.7)
    ends = {0: ((-0.2, across), (reach, across)), 1: ((1.2, across), (1 - reach, across)),
            2: ((across, -0.2), (across, reach)), 3: ((across, 1.2), (across, 1 - reach))}
    (ua, va), (ub, vb) = ends[side]
    a = np.array([(ua * w - cam.cx) / cam.fx * depth, (va * h - cam.cy) / cam.fy * depth, depth])
    b = np.array([(ub * w - cam.cx) / cam.fx * depth, (vb * h - cam.cy) / cam.fy * depth, depth])
    length = float(np.linalg.norm(b - a))
    yaw = math.degrees(math.atan2(b[1] - a[1], b[0] - a[0]))
    wide = rng.uniform(40, 60)
    # Built in the camera frame: x along the arm, z along the optical axis (away from it).
    arm = box(length, wide, 30, "gripper arm").moved(pose(length / 2, 0, -15))
    tool = cylinder(rng.uniform(12, 20), 70, "gripper tool").moved(pose(length - wide / 2, 0, 0))
    fingers = [box(10, 18, 80, "gripper finger").moved(pose(length - wide / 2, s * wide / 2, 0))
               for s in (-1, 1)]
    to_cam = Pose(rotation(yaw=yaw), a)
    to_world = Pose(cam.R, cam.t)
    solids = tuple(s.moved(to_cam).moved(to_world) for s in (arm, tool, *fingers))
    return Item("gripper", solids, False, "gripper")


def _with_gripper(model: CameraModel, shape: tuple[int, int], rng: np.random.Generator
                  ) -> tuple[Camera, list[Item], list[Item]]:
    if rng.random() < 0.5:
        cam, items, empty = _table_scene(model, shape, rng)
        top = 150.0
    else:
        cam, items, empty = _tote_scene(model, shape, rng, int(rng.integers(6, 15)))
        top = 260.0
    clearance = float(cam.t[2]) - top
    return cam, [*items, _gripper(cam, rng, clearance)], empty


@dataclass(frozen=True)
class CameraSceneSpec:
    """A named camera scene of :data:`CAMERA_SCENES`."""

    name: str
    description: str
    build: Callable[[CameraModel, tuple[int, int], np.random.Generator],
                    tuple[Camera, list[Item], list[Item]]]


#: Named camera scenes of ``rangeseg synth`` (layout from the seed).
CAMERA_SCENES: dict[str, CameraSceneSpec] = {s.name: s for s in (
    CameraSceneSpec("cam-pile", "items piled on a table, camera 0.5-0.9 m above it",
                    _table_scene),
    CameraSceneSpec("cam-tote", "items in a tote; its walls and rim at the image border",
                    lambda m, s, r: _tote_scene(m, s, r, int(r.integers(5, 13)))),
    CameraSceneSpec("cam-gripper", "a table or tote pile with the robot's gripper reaching "
                    "in from an image border", _with_gripper),
    CameraSceneSpec("cam-empty-tote", "an empty tote: nothing to pick",
                    lambda m, s, r: _tote_scene(m, s, r, 0)),
    CameraSceneSpec("cam-full-tote", "a tote heaped full: items hide most of its floor",
                    lambda m, s, r: _tote_scene(m, s, r, int(r.integers(30, 46)), packed=True)),
)}


# =========================================================================== rendering


@dataclass(frozen=True, eq=False)
class CameraScene:
    """A rendered camera frame.

    Attributes
    ----------
    name
        The scene's name in :data:`CAMERA_SCENES`.
    depth
        float64 (H, W) noise-free depth along the optical axis, mm.
    image
        The raw frame: uint16 (0 = no reading) or float32 metres (NaN).
    background
        The raw frame of the same camera and support with no items and no gripper.
    gt
        int32 (H, W) surface labels, 0 = no surface or no reading.
    info
        JSON-ready description (the ``gt.json``).
    camera
        The camera (intrinsics and pose).
    """

    name: str
    depth: np.ndarray
    image: np.ndarray
    background: np.ndarray
    gt: np.ndarray
    info: dict[str, Any]
    camera: Camera


def sense(render: Render, camera: Camera, sensor: SensorModel, unit: DepthUnit,
          rng_of: Callable[[int], np.random.Generator], dark: Sequence[int] = ()
          ) -> tuple[np.ndarray, np.ndarray]:
    """The sensor's frame of a noise-free render (Notes, 4), and where its depth is true.

    Returns
    -------
    raw, truthful
        The raw frame in ``unit`` and a bool (H, W) map of the valid pixels
        whose depth was not moved by more than ``gt_tolerance_mm`` by the
        smoothing of jumps or a flying pixel.
    """
    s = sensor
    true = np.where(np.isfinite(render.depth), render.depth, 1e6)
    z = smooth_jumps(true, blur_px=s.blur_px, jump_mm=s.jump_mm)
    z = flying_pixels(z, rng_of(1), fraction=s.flying_fraction, jump_mm=s.jump_mm)
    moved = np.abs(z - true) > s.gt_tolerance_mm
    invalid = projector_shadow(true, fx=camera.fx, baseline_mm=s.baseline_mm)
    invalid |= steep_holes(render.cos_incidence, rng_of(2), start_deg=s.steep_start_deg,
                           end_deg=s.steep_end_deg, drop=s.steep_drop)
    if dark:
        invalid |= dark_item_holes(render.obj, dark, rng_of(3), drop=s.dark_drop)
    invalid |= dropouts(true.shape, rng_of(4), fraction=s.dropout_fraction)
    invalid |= (true < s.min_range_mm) | (true > s.max_range_mm) | ~np.isfinite(render.depth)
    z = depth_noise(z, rng_of(5), noise_at_1m_mm=s.noise_at_1m_mm)
    z = smooth_depth_noise(z, rng_of(6), noise_at_1m_mm=s.smooth_noise_at_1m_mm,
                           sigma_px=s.smooth_noise_px)
    z = quantise_disparity(z, fx=camera.fx, baseline_mm=s.baseline_mm,
                           step_px=s.disparity_step_px)
    raw = to_raw(z, ~invalid, unit)
    valid = raw > 0 if raw.dtype.kind == "u" else np.isfinite(raw)
    return raw, valid & ~moved


def check_camera_options(name: str, shape: Sequence[int], camera: str, depth_unit: str,
                         seed: int) -> tuple[int, int]:
    """Check the options of :func:`render_camera_scene`; the image shape (rows, cols).

    Raises
    ------
    ValueError
        One line naming the option, its value and what is allowed.
    """
    if name not in CAMERA_SCENES:
        raise ValueError(f"scene {name!r} is unknown; allowed: " + ", ".join(CAMERA_SCENES))
    if camera not in CAMERAS:
        raise ValueError(f"`camera` {camera!r} is unknown; allowed: " + ", ".join(CAMERAS))
    if depth_unit not in DEPTH_UNITS:
        raise ValueError(f"`depth_unit` {depth_unit!r} is unknown; allowed: "
                         + ", ".join(DEPTH_UNITS))
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"`seed` {seed!r} must be an integer >= 0")
    if (isinstance(shape, str | bytes) or len(shape) != 2
            or not all(isinstance(v, int | np.integer) and not isinstance(v, bool)
                       and 16 <= v <= 8192 for v in shape)):
        raise ValueError(f"`size` {shape!r} must be two integers (rows, cols) from 16 to 8192")
    return int(shape[0]), int(shape[1])


def render_camera_scene(name: str, *, size: Sequence[int] = MODEL_SIZE, seed: int = 0,
                        camera: str = "sr300", depth_unit: str = "0.1mm",
                        sensor: SensorModel | None = None, tilt: float = 0.0,
                        soft: float = 0.0) -> CameraScene:
    """Render a named scene of :data:`CAMERA_SCENES` as a depth camera's frame.

    Parameters
    ----------
    name
        A key of :data:`CAMERA_SCENES`, e.g. ``"cam-tote"``.
    size
        (rows, cols) of the image, each 16..8192 (640x480 is ``(480, 640)``);
        the intrinsics of :data:`CAMERAS` scale with it.
    seed
        Seeds the layout and every sensor step. Same seed, same bytes.
    camera
        A key of :data:`CAMERAS`: ``"sr300"`` (with its defects) or ``"ideal"``.
    depth_unit
        A key of :data:`DEPTH_UNITS`: ``"0.1mm"``, ``"1mm"`` (uint16) or ``"m"`` (float32).
    sensor
        Replaces the camera's :class:`SensorModel`.
    tilt
        Degrees the camera's mount is tilted from straight down (about the
        camera's x axis), -60 to 60; the layout follows the view.
    soft
        Share (0 to 1) of the pickable items that are soft, a bag or a cloth:
        their faces creased (:func:`crease`), chosen by a stream of their own
        (0: none, the frames of before).

    Returns
    -------
    CameraScene
        The frame, its background frame, ground truth and description.

    Raises
    ------
    ValueError
        For an unknown scene, camera or unit, or a size or seed out of range.
    """
    shape = check_camera_options(name, size, camera, depth_unit, seed)
    if isinstance(tilt, bool) or not (isinstance(tilt, numbers.Real) and -60.0 <= tilt <= 60.0):
        raise ValueError(f"`tilt` {tilt!r} must be a number of degrees from -60 to 60")
    if isinstance(soft, bool) or not (isinstance(soft, numbers.Real) and 0.0 <= soft <= 1.0):
        raise ValueError(f"`soft` {soft!r} must be a share from 0 to 1")
    model = replace(CAMERAS[camera], tilt=float(tilt))
    model = replace(model, sensor=sensor) if sensor is not None else model
    kind = list(CAMERA_SCENES).index(name)
    cam, items, empty = CAMERA_SCENES[name].build(model, shape, np.random.default_rng(
        [seed, kind, 0]))
    unit = DEPTH_UNITS[depth_unit]
    render = render_items(cam, items)
    dark_rng = np.random.default_rng([seed, kind, 9])
    dark = [i for i, it in enumerate(items)
            if it.pickable and dark_rng.random() < model.sensor.dark_fraction]
    soft_rng = np.random.default_rng([seed, kind, 10])
    creased = [i for i, it in enumerate(items) if it.pickable and soft_rng.random() < soft]
    if creased:
        render = replace(render, depth=crease(render.depth, render.obj, creased, soft_rng))
    raw, truthful = sense(render, cam, model.sensor, unit,
                          lambda k: np.random.default_rng([seed, kind, 1, k]), dark)
    background, _ = sense(render_items(cam, empty), cam, model.sensor, unit,
                          lambda k: np.random.default_rng([seed, kind, 2, k]))
    gt = np.where(truthful, render.gt, 0).astype(np.int32)
    info = _info(name, seed, model, unit, cam, items, render, gt, dark)
    if creased:
        info["soft"] = creased
    return CameraScene(name, render.depth, raw, background, gt, info, cam)


def _info(name: str, seed: int, model: CameraModel, unit: DepthUnit, cam: Camera,
          items: Sequence[Item], render: Render, gt: np.ndarray, dark: Sequence[int]
          ) -> dict[str, Any]:
    counts = np.bincount(gt.ravel(), minlength=len(render.surfaces) + 1)
    surfaces = [{**s, "pixels": int(counts[s["id"]])} for s in render.surfaces]
    return {
        "scene": name, "description": CAMERA_SCENES[name].description, "figure": None,
        "size": list(cam.shape), "seed": int(seed),
        "camera": {"model": model.name, "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                   "depth_unit": unit.name, "metres_per_raw": unit.metres_per_raw,
                   "metres_per_unit": 0.001, "preset": unit.preset,
                   "height_mm": float(cam.t[2]), "rotation": cam.R.tolist(),
                   "position_mm": cam.t.tolist()},
        "sensor": asdict(model.sensor),
        "surfaces": surfaces, "saturated": 0,
        "objects": [{"id": i, "name": it.name, "kind": it.kind, "background": not it.pickable,
                     "pickable": it.pickable, "dark": i in dark}
                    for i, it in enumerate(items)],
        "uncovered": [i for i, it in enumerate(items) if it.pickable and not render.covered[i]],
        "unseen_pixels": int(np.count_nonzero((gt == 0) & (render.gt > 0))),
        "generator": "rangeseg synth (perspective ray casting, synthetic depth camera)",
    }


# =========================================================================== files


def intrinsics_text(camera: Camera) -> str:
    """The 3x3 camera matrix as text, one row a line (like ``suction-camera-intrinsics.txt``)."""
    return "".join(" ".join(f"{v:.9e}" for v in row) + "\n" for row in camera.matrix())


def camera_stem(name: str, seed: int) -> str:
    """File stem of a camera scene: ``cam-tote-s3``."""
    return f"{name}-s{seed}"


def write_camera_scenes(out_dir: str | Path, names: Iterable[str], seeds: Iterable[int], *,
                        size: Sequence[int] = MODEL_SIZE, camera: str = "sr300",
                        depth_unit: str = "0.1mm", tilt: float = 0.0, soft: float = 0.0
                        ) -> list[Path]:
    """Render camera scenes for each seed and write them with their ground truth.

    Per scene and seed, with ``<stem>`` = :func:`camera_stem`, writes
    ``OUT/<stem>.png`` (uint16; ``.npy`` float32 metres for ``depth_unit =
    "m"``), ``<stem>.gt.npy`` (int32 labels), ``<stem>.gt.json``,
    ``<stem>.intrinsics.txt`` and ``<stem>.gt.background.png`` (or ``.npy``):
    the empty support for ``[workspace] background``. ``tilt``, ``soft``: as
    :func:`render_camera_scene`. ``rangeseg run OUT``
    reads only the frames: names holding ``.gt.`` are skipped as ground
    truth, and ``.txt`` is no image.

    Returns
    -------
    list of Path
        The files written, five per scene and seed.

    Raises
    ------
    ValueError
        For an unknown scene, camera or unit, or a size or seed out of range,
        before anything is written.
    """
    from ..batch.io import write_json, write_npy, write_png, write_text

    names, seeds = list(names), list(seeds)
    for name in names:
        for seed in seeds:
            check_camera_options(name, size, camera, depth_unit, seed)
    out = Path(out_dir)
    suffix = DEPTH_UNITS[depth_unit].suffix
    written: list[Path] = []
    for name in dict.fromkeys(names):
        for seed in dict.fromkeys(seeds):
            scene = render_camera_scene(name, size=size, seed=seed, camera=camera,
                                        depth_unit=depth_unit, tilt=tilt, soft=soft)
            stem = camera_stem(name, seed)
            paths = [out / f"{stem}{suffix}", out / f"{stem}.gt.background{suffix}",
                     out / f"{stem}.gt.npy", out / f"{stem}.gt.json",
                     out / f"{stem}.intrinsics.txt"]
            for path, image in zip(paths[:2], (scene.image, scene.background), strict=True):
                (write_npy if suffix == ".npy" else write_png)(path, image)
            write_npy(paths[2], scene.gt)
            write_json(paths[3], scene.info, digits=10)
            write_text(paths[4], intrinsics_text(scene.camera))
            written.extend(paths)
    return written


def split_scene_names(text: str, classic: Iterable[str]) -> tuple[list[str], list[str]]:
    """Comma-separated scene names, split into ``classic`` ones and :data:`CAMERA_SCENES`.

    Raises
    ------
    ValueError
        One line naming the unknown scenes and what is allowed.
    """
    known = list(classic)
    names = list(dict.fromkeys(v.strip() for v in text.split(",") if v.strip()))
    if not names:
        raise ValueError(f"{text!r}: expected a comma-separated list")
    unknown = [n for n in names if n not in known and n not in CAMERA_SCENES]
    if unknown:
        raise ValueError(f"unknown scene {', '.join(unknown)}; allowed: "
                         + ", ".join([*known, *CAMERA_SCENES]))
    return [n for n in names if n in known], [n for n in names if n in CAMERA_SCENES]
