"""Synthetic range images with ground truth, for ``rangeseg synth`` and ``rangeseg eval``.

Renders the test objects of Al-Hujazi & Sood (1990), Section VI -- the
industrial part with step, roof and smooth edges of Fig. 10 (``part1``), the
coffee cup with its handle and hollow of Fig. 11 (``cup``), the second part
of Fig. 12 (``part2``) and the cube with through holes of Fig. 13
(``cube-holes``) -- plus simple solids, a machined nut (a triangle mesh) and
bin piles, as range images with a ground-truth surface label per pixel, to be
scored with the metrics of Hoover et al. (1996) in
:mod:`rangeseg_cli.synth.evaluate`.

Notes
-----
1. Geometry. A solid is a convex body -- half-spaces and at most one quadric
   (sphere or cylinder) -- minus convex holes (constructive solid geometry),
   a torus segment (the cup's handle) or a triangle mesh (the nut). A part
   is a union of solids. Scenes are designed for a 128x128 image in *design
   units* (one unit = one pixel at 128x128; other sizes scale uniformly by
   ``min(H, W) / 128``); x is the column, y the row, z points to the sensor.
2. Projection. Orthographic, looking down: a pixel's height is the highest
   point of any solid on the vertical line through the pixel centre
   (z-buffer), exact for planes and quadrics, by sampling and bisection for
   tori, by barycentric interpolation for triangles.
3. Placement. Parts are dropped one after another: each is lowered or
   raised until it rests on the height map of the table and of the parts
   placed before it, so parts never interpenetrate (checked at the pixel
   centres).
4. Heights. ``height = table_height + units_per_pixel * z`` in depth units
   like the 8-bit ERIM images of Sec. VI (table 30, parts rising to
   40-150), then Gaussian noise of ``noise`` units, then rounding to 8 bits,
   or to 16 bits in 1/256 units (``info["input_scale"]`` is the ``[input]
   scale`` that reads them back in depth units).
   At a roof edge the AR of the 17-tap, sigma-4 mask (Sec. V-2) is about
   1.47 x the change of slope in depth units per pixel, so pass 2b
   (threshold 4) needs a change of >= 2.7 and pass 2a (threshold 6) >= 4.1.
   The roof edges of the designed scenes change slope by about 3 units/pixel
   or more (>= 2.9 after the tilts; faces rise >= 1.5 pixels per pixel);
   the nut's 45-degree chamfers (2 units/pixel) are a deliberately hard case.
5. Ground truth. Every visible surface -- a face of a solid, the wall or
   bottom of a hole, a group of adjacent coplanar mesh triangles, the table
   -- gets an int32 label 1..K in the order of declaration (0 = no surface).
   Planar faces of one object that touch in the image and lie in one plane
   (two solids flush, as part1's base and block on their +y side) are one
   surface (:func:`join_flush_faces`): no segmenter can see where they meet.
   Where a surface's noise-free height lies beyond the raw range (above 255
   in 8 bits: a tall pile's top parts), the image holds the clipped value
   only and the ground truth is 0 there (:func:`_in_range`); the surfaces'
   ``pixels`` count what is left and ``info["saturated"]`` the pixels so lost.
   An object is *uncovered* when no other part lies above any of its pixels.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

#: Height of the table in depth units, as in the paper's ERIM images (Sec. VI).
TABLE_HEIGHT = 30.0
#: Largest height off one plane (design units) of faces joined by :func:`join_flush_faces`.
FLUSH_TOLERANCE = 1e-6
#: Depth units per design unit (a pixel at 128x128); see the module notes on roof edges.
UNITS_PER_DESIGN_UNIT = 2.0
#: Side of the design frame in design units (the paper's images are 128x128).
DESIGN_SIZE = 128
#: Raw 16-bit values per depth unit.
RAW_PER_UNIT_16 = 256.0
#: Allowed image depths.
BITS = (8, 16)
_EPS = 1e-7

Face = tuple[str, str]  # (surface name, kind)

# =========================================================================== poses


def rotation(roll: float = 0.0, pitch: float = 0.0, yaw: float = 0.0) -> np.ndarray:
    """Rotation matrix ``Rz(yaw) @ Ry(pitch) @ Rx(roll)``.

    Parameters
    ----------
    roll, pitch, yaw
        Angles in degrees about the x, y and z axes.

    Returns
    -------
    numpy.ndarray
        (3, 3) rotation matrix.
    """
    a, b, c = np.radians([roll, pitch, yaw])
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
    return rz @ ry @ rx


@dataclass(frozen=True, eq=False)
class Pose:
    """Rigid motion ``p_outer = R @ p_local + t``."""

    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def then(self, outer: Pose) -> Pose:
        """Compose: first this motion, then ``outer``."""
        return Pose(outer.R @ self.R, outer.R @ self.t + outer.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Map (N, 3) local points to the outer frame."""
        return points @ self.R.T + self.t

    def ray(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vertical lines through ``(x, y)`` in the local frame.

        Returns the (N, 3) local points at world height 0 and the local
        direction of world +z: the world height of ``o + s d`` is ``s``.
        """
        p = np.stack([x - self.t[0], y - self.t[1], np.full_like(x, -self.t[2])], axis=-1)
        return p @ self.R, self.R[2].copy()


def pose(x: float = 0.0, y: float = 0.0, z: float = 0.0, *, roll: float = 0.0,
         pitch: float = 0.0, yaw: float = 0.0) -> Pose:
    """Pose from a position and roll, pitch, yaw in degrees."""
    return Pose(rotation(roll, pitch, yaw), np.array([x, y, z], dtype=float))


# =========================================================================== grid and spans


@dataclass(frozen=True, eq=False)
class Grid:
    """Pixel centres of an H x W image in design units.

    ``col = cx + scale * x`` and ``row = cy + scale * y``, with ``(cx, cy)``
    the image centre; ``x`` and ``y`` are flat (H*W,) arrays, row-major.
    """

    shape: tuple[int, int]
    scale: float
    x: np.ndarray
    y: np.ndarray

    @classmethod
    def for_image(cls, shape: tuple[int, int]) -> Grid:
        """The grid of an image of ``shape`` (rows, cols)."""
        h, w = shape
        scale = min(h, w) / DESIGN_SIZE
        rows, cols = np.mgrid[0:h, 0:w].astype(float)
        return cls(shape, scale, ((cols - (w - 1) / 2) / scale).ravel(),
                   ((rows - (h - 1) / 2) / scale).ravel())

    @property
    def half_extent(self) -> tuple[float, float]:
        """Half width and half height of the image in design units."""
        return (self.shape[1] / 2 / self.scale, self.shape[0] / 2 / self.scale)


@dataclass(frozen=True, eq=False)
class Span:
    """Where vertical lines meet a body: lowest and highest point and their faces.

    ``lo = +inf`` and ``hi = -inf`` where a line misses the body.
    """

    lo: np.ndarray
    hi: np.ndarray
    face_lo: np.ndarray
    face_hi: np.ndarray

    @classmethod
    def make(cls, lo: np.ndarray, hi: np.ndarray, face_lo: np.ndarray, face_hi: np.ndarray,
             miss: np.ndarray) -> Span:
        """Build a span, marking ``miss`` and empty intervals as misses."""
        miss = miss | (lo > hi)
        return cls(np.where(miss, np.inf, lo), np.where(miss, -np.inf, hi), face_lo, face_hi)


def _tighten(t: np.ndarray, k: int, upper: bool, bounds: list[np.ndarray]) -> None:
    """Narrow ``[lo, hi]`` to ``t`` (an upper or a lower bound) and record face ``k``."""
    lo, hi, face_lo, face_hi = bounds
    if upper:
        better = t < hi
        hi[better] = t[better]
        face_hi[better] = k
    else:
        better = t > lo
        lo[better] = t[better]
        face_lo[better] = k


# =========================================================================== bodies


@dataclass(frozen=True, eq=False)
class Convex:
    """A convex body: half-spaces ``n . q <= h`` and at most one quadric.

    Attributes
    ----------
    planes
        (m, 4) rows ``(nx, ny, nz, h)`` in the local frame.
    faces
        One ``(name, kind)`` per plane, then one for the quadric.
    quadric
        ``None``, ``"sphere"`` (centred at the origin) or ``"cylinder"``
        (about the local z axis), of radius ``radius``.
    pose
        Local frame to world (design units).
    """

    planes: np.ndarray
    faces: tuple[Face, ...]
    quadric: str | None = None
    radius: float = 0.0
    pose: Pose = field(default_factory=Pose)

    def moved(self, outer: Pose) -> Convex:
        """The body moved by ``outer``."""
        return replace(self, pose=self.pose.then(outer))

    def span(self, grid: Grid) -> Span:
        """Lowest and highest point on each vertical line of ``grid``."""
        o, d = self.pose.ray(grid.x, grid.y)
        n = len(o)
        bounds = [np.full(n, -np.inf), np.full(n, np.inf), np.zeros(n, np.int32),
                  np.zeros(n, np.int32)]
        miss = np.zeros(n, bool)
        for k, row in enumerate(self.planes):
            normal, h = row[:3], row[3]
            nd = float(normal @ d)
            no = o @ normal
            if abs(nd) < 1e-12:
                miss |= no > h
                continue
            _tighten((h - no) / nd, k, nd > 0, bounds)
        if self.quadric is not None:
            miss |= self._quadric(o, d, bounds)
        return Span.make(bounds[0], bounds[1], bounds[2], bounds[3], miss=miss)

    def _quadric(self, o: np.ndarray, d: np.ndarray, bounds: list[np.ndarray]) -> np.ndarray:
        axes = slice(0, 3) if self.quadric == "sphere" else slice(0, 2)
        oo, dd = o[:, axes], d[axes]
        a = float(dd @ dd)
        c = np.einsum("ij,ij->i", oo, oo) - self.radius**2
        if a < 1e-12:  # a cylinder parallel to the line of sight
            return c > 0
        b = 2.0 * (oo @ dd)
        disc = b * b - 4 * a * c
        root = np.sqrt(np.maximum(disc, 0.0))
        k = len(self.planes)
        _tighten((-b - root) / (2 * a), k, False, bounds)
        _tighten((-b + root) / (2 * a), k, True, bounds)
        return disc < 0


@dataclass(frozen=True, eq=False)
class Torus:
    """A torus about the local z axis, cut by half-spaces (the cup's handle, Fig. 11).

    Highest and lowest points are found by sampling each line inside the
    bounding sphere and refining by bisection.
    """

    major: float
    minor: float
    clip: np.ndarray
    faces: tuple[Face, ...]
    pose: Pose = field(default_factory=Pose)
    samples: int = 160

    def moved(self, outer: Pose) -> Torus:
        """The body moved by ``outer``."""
        return replace(self, pose=self.pose.then(outer))

    def _inside(self, q: np.ndarray) -> np.ndarray:
        ring = np.hypot(q[..., 0], q[..., 1]) - self.major
        ok = ring**2 + q[..., 2] ** 2 <= self.minor**2
        for row in self.clip:
            ok &= q @ row[:3] <= row[3]
        return ok

    def span(self, grid: Grid) -> Span:
        """Lowest and highest point on each vertical line of ``grid``."""
        o, d = self.pose.ray(grid.x, grid.y)
        n = len(o)
        lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
        od = o @ d
        disc = od**2 - (np.einsum("ij,ij->i", o, o) - (self.major + self.minor) ** 2)
        sel = np.flatnonzero(disc > 0)
        if sel.size:
            root = np.sqrt(disc[sel])
            ts = (-od[sel] - root)[:, None] + (2 * root)[:, None] * np.linspace(
                0.0, 1.0, self.samples)
            inside = self._inside(o[sel, None, :] + ts[..., None] * d)
            found = inside.any(axis=1)
            rows, os_, ts, inside = sel[found], o[sel[found]], ts[found], inside[found]
            last = self.samples - 1 - np.argmax(inside[:, ::-1], axis=1)
            first = np.argmax(inside, axis=1)
            idx = np.arange(len(rows))
            hi[rows] = self._bisect(os_, d, ts[idx, last],
                                    ts[idx, np.minimum(last + 1, self.samples - 1)])
            lo[rows] = self._bisect(os_, d, ts[idx, first], ts[idx, np.maximum(first - 1, 0)])
        zero = np.zeros(n, np.int32)
        return Span.make(lo, hi, zero, zero, miss=~np.isfinite(hi))

    def _bisect(self, o: np.ndarray, d: np.ndarray, t_in: np.ndarray, t_out: np.ndarray
                ) -> np.ndarray:
        for _ in range(40):
            mid = 0.5 * (t_in + t_out)
            ins = self._inside(o + mid[:, None] * d)
            t_in = np.where(ins, mid, t_in)
            t_out = np.where(ins, t_out, mid)
        return t_in


@dataclass(frozen=True, eq=False)
class Mesh:
    """A closed triangle mesh; ``groups`` gives each triangle's face in ``faces``.

    Rasterised by a vectorised z-buffer over all (triangle, pixel) pairs.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    groups: np.ndarray
    faces: tuple[Face, ...]
    pose: Pose = field(default_factory=Pose)

    def moved(self, outer: Pose) -> Mesh:
        """The body moved by ``outer``."""
        return replace(self, pose=self.pose.then(outer))

    def span(self, grid: Grid) -> Span:
        """Lowest and highest point on each pixel's vertical line (``grid`` = a whole image)."""
        h, w = grid.shape
        v = self.pose.apply(self.vertices)
        v = np.column_stack([(w - 1) / 2 + grid.scale * v[:, 0],
                             (h - 1) / 2 + grid.scale * v[:, 1], v[:, 2]])
        tri, pix, z = _rasterise(v[self.triangles], (h, w))
        n = h * w
        lo, hi = np.full(n, np.inf), np.full(n, -np.inf)
        face_lo, face_hi = np.zeros(n, np.int32), np.zeros(n, np.int32)
        if pix.size:
            order = np.lexsort((z, pix))
            pix, z, tri = pix[order], z[order], tri[order]
            change = pix[1:] != pix[:-1]
            first, last = np.r_[True, change], np.r_[change, True]
            lo[pix[first]], face_lo[pix[first]] = z[first], self.groups[tri[first]]
            hi[pix[last]], face_hi[pix[last]] = z[last], self.groups[tri[last]]
        return Span.make(lo, hi, face_lo, face_hi, miss=~np.isfinite(hi))


def _rasterise(tri: np.ndarray, shape: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (triangle, pixel, z) where a pixel centre lies in a triangle's projection.

    ``tri`` is (F, 3, 3) in (col, row, z). Edges are inclusive, so a mesh
    without gaps covers every pixel centre of its silhouette.
    """
    h, w = shape
    x, y = tri[:, :, 0], tri[:, :, 1]
    c0 = np.clip(np.ceil(x.min(1) - 1e-9), 0, w).astype(np.int64)
    c1 = np.clip(np.floor(x.max(1) + 1e-9), -1, w - 1).astype(np.int64)
    r0 = np.clip(np.ceil(y.min(1) - 1e-9), 0, h).astype(np.int64)
    r1 = np.clip(np.floor(y.max(1) + 1e-9), -1, h - 1).astype(np.int64)
    nc, nr = np.maximum(c1 - c0 + 1, 0), np.maximum(r1 - r0 + 1, 0)
    den = (y[:, 1] - y[:, 2]) * (x[:, 0] - x[:, 2]) + (x[:, 2] - x[:, 1]) * (y[:, 0] - y[:, 2])
    counts = np.where(np.abs(den) > 1e-12, nc * nr, 0)
    idx = np.repeat(np.arange(len(tri)), counts)
    k = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
    px = c0[idx] + k % nc[idx]
    py = r0[idx] + k // nc[idx]
    xs, ys, dd = x[idx], y[idx], den[idx]
    l0 = ((ys[:, 1] - ys[:, 2]) * (px - xs[:, 2]) + (xs[:, 2] - xs[:, 1]) * (py - ys[:, 2])) / dd
    l1 = ((ys[:, 2] - ys[:, 0]) * (px - xs[:, 2]) + (xs[:, 0] - xs[:, 2]) * (py - ys[:, 2])) / dd
    l2 = 1.0 - l0 - l1
    ok = (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
    zs = tri[idx, :, 2]
    z = l0 * zs[:, 0] + l1 * zs[:, 1] + l2 * zs[:, 2]
    return idx[ok], (py * w + px)[ok], z[ok]


Body = Convex | Torus | Mesh


@dataclass(frozen=True, eq=False)
class Solid:
    """A body minus convex holes (constructive solid geometry)."""

    base: Body
    holes: tuple[Convex, ...] = ()

    @property
    def faces(self) -> tuple[Face, ...]:
        """Faces of the base, then of each hole."""
        out = tuple(self.base.faces)
        for hole in self.holes:
            out += hole.faces
        return out

    def moved(self, outer: Pose) -> Solid:
        """The solid moved by ``outer``."""
        return Solid(self.base.moved(outer), tuple(h.moved(outer) for h in self.holes))

    def extent(self, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Top height, the face seen there (index into :attr:`faces`) and bottom height.

        The top of ``base - holes`` on a line is the highest of the base's
        top and the holes' bottoms that lies in the base and in no hole.
        """
        sb = self.base.span(grid)
        if not self.holes:
            return sb.hi, sb.face_hi, sb.lo
        spans = [h.span(grid) for h in self.holes]
        offsets = np.cumsum([len(self.base.faces)] + [len(h.faces) for h in self.holes])[:-1]
        pairs = list(zip(offsets, spans, strict=True))
        top, face = _first_valid([sb.hi] + [s.lo for s in spans],
                                 [sb.face_hi] + [o + s.face_lo for o, s in pairs],
                                 sb, spans, highest=True)
        bottom, _ = _first_valid([sb.lo] + [s.hi for s in spans],
                                 [sb.face_lo] + [o + s.face_hi for o, s in pairs],
                                 sb, spans, highest=False)
        return top, face, bottom


def _first_valid(cands: list[np.ndarray], faces: list[np.ndarray], base: Span,
                 holes: list[Span], *, highest: bool) -> tuple[np.ndarray, np.ndarray]:
    z, f = np.stack(cands), np.stack(faces)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(z) & (z >= base.lo - _EPS) & (z <= base.hi + _EPS)
        for s in holes:
            ok &= ~((z > s.lo + _EPS) & (z < s.hi - _EPS))
    fill = -np.inf if highest else np.inf
    z = np.where(ok, z, fill)
    pick = np.argmax(z, axis=0) if highest else np.argmin(z, axis=0)
    return (np.take_along_axis(z, pick[None], 0)[0], np.take_along_axis(f, pick[None], 0)[0])


@dataclass(frozen=True, eq=False)
class Part:
    """An object of the scene: a union of solids with named surfaces."""

    name: str
    solids: tuple[Solid, ...]
    background: bool = False

    def moved(self, outer: Pose) -> Part:
        """The part moved by ``outer``."""
        return replace(self, solids=tuple(s.moved(outer) for s in self.solids))

    @property
    def surfaces(self) -> list[Face]:
        """Distinct ``(name, kind)`` of the part's faces in order of declaration."""
        seen: dict[Face, None] = {}
        for solid in self.solids:
            seen.update(dict.fromkeys(solid.faces))
        return list(seen)

    def maps(self, grid: Grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Top height, surface index (into :attr:`surfaces`) and bottom height per pixel."""
        index = {face: i for i, face in enumerate(self.surfaces)}
        tops, surfs, bottoms = [], [], []
        for solid in self.solids:
            top, face, bottom = solid.extent(grid)
            lookup = np.array([index[f] for f in solid.faces], dtype=np.int32)
            tops.append(top)
            surfs.append(lookup[face])
            bottoms.append(bottom)
        pick = np.argmax(np.stack(tops), axis=0)[None]
        return (np.take_along_axis(np.stack(tops), pick, 0)[0],
                np.take_along_axis(np.stack(surfs), pick, 0)[0],
                np.min(np.stack(bottoms), axis=0))


# =========================================================================== primitives

_PLANE, _CYL, _SPHERE, _TORUS = "planar", "cylindrical", "spherical", "toroidal"


def _named(prefix: str, names: Sequence[str], kinds: Sequence[str]) -> tuple[Face, ...]:
    return tuple((f"{prefix} {n}".strip(), k) for n, k in zip(names, kinds, strict=True))


def box(sx: float, sy: float, sz: float, prefix: str = "") -> Convex:
    """Box centred on the z axis, ``0 <= z <= sz``; faces +x -x +y -y top bottom."""
    planes = np.array([[1, 0, 0, sx / 2], [-1, 0, 0, sx / 2], [0, 1, 0, sy / 2],
                       [0, -1, 0, sy / 2], [0, 0, 1, sz], [0, 0, -1, 0]], dtype=float)
    names = ("+x", "-x", "+y", "-y", "top", "bottom")
    return Convex(planes, _named(prefix, names, [_PLANE] * 6))


def prism(profile: Sequence[tuple[float, float]], length: float, names: Sequence[str],
          prefix: str = "") -> Convex:
    """Convex polygon in the x-z plane (counter-clockwise) extruded over ``|y| <= length/2``.

    ``names`` names the polygon's edges (from vertex i to i+1), then the
    +y and -y caps.
    """
    p = np.asarray(profile, dtype=float)
    e = np.roll(p, -1, axis=0) - p
    normals = np.column_stack([e[:, 1], np.zeros(len(p)), -e[:, 0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", normals[:, [0, 2]], p)
    planes = np.vstack([np.column_stack([normals, h]),
                        [[0, 1, 0, length / 2], [0, -1, 0, length / 2]]])
    return Convex(planes, _named(prefix, names, [_PLANE] * len(planes)))


def frustum(bottom: float, top: float, height: float, prefix: str = "") -> Convex:
    """Square pyramid frustum, ``0 <= z <= height``; faces +x -x +y -y top bottom."""
    run = (bottom - top) / 2
    k = math.hypot(height, run)
    a, c, h = height / k, run / k, height / k * bottom / 2
    planes = np.array([[a, 0, c, h], [-a, 0, c, h], [0, a, c, h], [0, -a, c, h],
                       [0, 0, 1, height], [0, 0, -1, 0]], dtype=float)
    return Convex(planes, _named(prefix, ("+x", "-x", "+y", "-y", "top", "bottom"),
                                 [_PLANE] * 6))


def cylinder(radius: float, length: float, prefix: str = "",
             clip: Sequence[Sequence[float]] = (), clip_names: Sequence[str] = ()) -> Convex:
    """Cylinder about the z axis, ``0 <= z <= length``, optionally cut by more half-spaces.

    Faces: bottom, top, the clip planes, then the curved side.
    """
    planes = np.array([[0, 0, -1, 0], [0, 0, 1, length], *clip], dtype=float)
    names = ("bottom", "top", *clip_names, "side")
    kinds = [_PLANE] * (len(planes)) + [_CYL]
    return Convex(planes, _named(prefix, names, kinds), "cylinder", radius)


def sphere(radius: float, prefix: str = "") -> Convex:
    """Sphere about the origin."""
    return Convex(np.zeros((0, 4)), _named(prefix, ("surface",), [_SPHERE]), "sphere", radius)


# =========================================================================== the nut mesh


def read_ply(path: str | Path | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Read a binary little-endian PLY triangle mesh (by default the packaged nut).

    Parameters
    ----------
    path
        A PLY file with ``float x, y, z`` vertices and ``list uchar int``
        triangles; ``None`` reads ``rangeseg_cli/data/nut.ply`` (MIT, from
        the PyVista sample files; see ``data/LICENSE-nut``).

    Returns
    -------
    vertices, triangles
        (V, 3) float64 and (F, 3) int64.

    Raises
    ------
    ValueError
        For another PLY layout than the one above, or a face that is not a triangle.
    """
    if path is None:
        data = resources.files("rangeseg_cli").joinpath("data/nut.ply").read_bytes()
    else:
        data = Path(path).read_bytes()
    end = data.find(b"end_header\n")
    header = data[:end].decode("ascii", "replace").split("\n")
    counts = {ln.split()[1]: int(ln.split()[2]) for ln in header if ln.startswith("element")}
    if ("format binary_little_endian 1.0" not in header or set(counts) != {"vertex", "face"}
            or header.count("property float x") != 1):
        raise ValueError(f"{path}: only binary little-endian PLY with float x y z vertices "
                         "and triangle faces is supported")
    offset = end + len(b"end_header\n")
    nprop = sum(1 for ln in header if ln.startswith("property float"))
    verts = np.frombuffer(data, "<f4", counts["vertex"] * nprop, offset).reshape(-1, nprop)
    faces = np.frombuffer(data, [("n", "u1"), ("i", "<i4", (3,))], counts["face"],
                          offset + verts.nbytes)
    if np.any(faces["n"] != 3):
        raise ValueError(f"{path}: only triangle faces are supported")
    return verts[:, :3].astype(np.float64), faces["i"].astype(np.int64)


def coplanar_groups(vertices: np.ndarray, triangles: np.ndarray, *, angle: float = 0.02
                    ) -> np.ndarray:
    """Group adjacent coplanar triangles: the ground-truth surfaces of a mesh.

    Two triangles sharing an edge are in one group when their normals differ
    by less than ``angle`` degrees (they share the edge, so the planes agree).

    Returns
    -------
    numpy.ndarray
        (F,) group index per triangle, numbered in order of first triangle.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    p = vertices[triangles]
    normal = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    edges = np.sort(triangles[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2), axis=1)
    owner = np.repeat(np.arange(len(triangles)), 3)
    order = np.lexsort((edges[:, 1], edges[:, 0]))
    e, o = edges[order], owner[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    a, b = o[:-1][same], o[1:][same]
    flat = np.einsum("ij,ij->i", normal[a], normal[b]) > math.cos(math.radians(angle))
    n = len(triangles)
    graph = coo_matrix((np.ones(int(flat.sum())), (a[flat], b[flat])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels, return_index=True)
    rank = np.empty(len(first), np.int64)
    rank[np.argsort(np.argsort(first))] = np.arange(len(first))
    return rank[labels]


_NUT: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def nut(size: float, prefix: str = "nut") -> Mesh:
    """The machined nut (``data/nut.ply``), centred, axis along z, ``size`` across."""
    global _NUT
    if _NUT is None:
        v, t = read_ply()
        _NUT = (v, t, coplanar_groups(v, t))
    v, t, groups = _NUT
    v = v - (v.min(0) + v.max(0)) / 2
    v = v[:, [0, 2, 1]] * (size / np.ptp(v[:, [0, 2]], axis=0).max())
    faces = tuple((f"{prefix} facet {i + 1}", _PLANE) for i in range(int(groups.max()) + 1))
    return Mesh(v, t, groups, faces)


# =========================================================================== scenes

Builder = Callable[[Grid, np.random.Generator], list[Part]]


@dataclass(frozen=True)
class SceneSpec:
    """A named scene of :data:`SCENES`."""

    name: str
    description: str
    figure: str | None
    build: Builder


def _one(name: str, *solids: Solid, at: Pose) -> Part:
    return Part(name, tuple(s.moved(at) for s in solids))


def _part1(grid: Grid, rng: np.random.Generator) -> list[Part]:
    """Industrial part with step, roof and smooth edges (Fig. 10)."""
    base = box(90, 56, 12, "base").moved(pose(-1))
    block = box(24, 56, 16, "block").moved(pose(-18, 0, 12))
    # A quarter cylinder tangent to the block's top: a smooth edge (Sec. VI).
    fillet = cylinder(16, 56, "fillet", clip=[[1, 0, 0, 0], [0, 1, 0, 0]],
                      clip_names=["cut x", "cut z"]).moved(
        pose(0, 0, -28).then(pose(-30, 0, 12, roll=-90)))
    roof = prism([(-16, 0), (16, 0), (0, 27)], 36,
                 ["bottom", "face a", "face b", "gable a", "gable b"], "roof").moved(
        pose(22, 0, 12, yaw=90))
    solids = [Solid(base), Solid(block), Solid(fillet), Solid(roof)]
    return [_one("part1", *solids, at=pose(2, 0, roll=6, pitch=-8, yaw=15))]


def _cup(grid: Grid, rng: np.random.Generator) -> list[Part]:
    """Coffee cup with a handle and a hollow inside (Fig. 11), tilted to show the hollow."""
    outer = cylinder(22, 36, "cup")
    outer = replace(outer, faces=(("cup bottom", _PLANE), ("cup rim", _PLANE),
                                  ("cup outer wall", _CYL)))
    hollow = replace(cylinder(19, 40).moved(pose(0, 0, 4)),
                     faces=(("cup inside bottom", _PLANE), ("cup opening", _PLANE),
                            ("cup inner wall", _CYL)))
    handle = Torus(10, 3, np.array([[-1.0, 0, 0, 0]]), (("cup handle", _TORUS),),
                   pose(21, 0, 18, roll=-90))
    return [_one("cup", Solid(outer, (hollow,)), Solid(handle),
                 at=pose(-4, 4, roll=35, yaw=20))]


def _part2(grid: Grid, rng: np.random.Generator) -> list[Part]:
    """Second industrial part (Fig. 12): a narrow chamfer on the left, a bored boss, a ramp."""
    base = prism([(-40, 0), (40, 0), (40, 14), (-35, 14), (-40, 5)], 50,
                 ["bottom", "+x end", "top", "chamfer", "-x end", "+y side", "-y side"], "base")
    boss = cylinder(13, 16, "boss").moved(pose(14, 0, 14))
    bore = cylinder(6, 12, "bore").moved(pose(14, 0, 20))
    ramp = prism([(-16, 0), (-4, 0), (-4, 20)], 24, ["bottom", "back", "slope", "+y", "-y"],
                 "ramp").moved(pose(0, 0, 14))
    return [_one("part2", Solid(base), Solid(boss, (bore,)), Solid(ramp),
                 at=pose(0, 2, roll=-5, pitch=4, yaw=-20))]


def _cube_holes(grid: Grid, rng: np.random.Generator) -> list[Part]:
    """Cube with a through hole drilled in every face (Fig. 13)."""
    cube = box(36, 36, 36, "cube").moved(pose(0, 0, -18))
    holes = tuple(
        replace(cylinder(7, 60).moved(pose(0, 0, -30).then(pose(roll=r, pitch=p))),
                faces=((f"hole {a} end", _PLANE),) * 2 + ((f"hole {a} wall", _CYL),))
        for a, r, p in (("z", 0, 0), ("x", 0, 90), ("y", 90, 0)))
    return [_one("cube-holes", Solid(cube, holes), at=pose(0, 0, roll=30, pitch=-25, yaw=20))]


def _box(grid: Grid, rng: np.random.Generator) -> list[Part]:
    return [_one("box", Solid(box(56, 40, 24, "box")), at=pose(yaw=20))]


def _tilted_box(grid: Grid, rng: np.random.Generator) -> list[Part]:
    return [_one("box", Solid(box(50, 36, 26, "box")), at=pose(roll=20, pitch=25, yaw=30))]


def _wedge(grid: Grid, rng: np.random.Generator) -> list[Part]:
    w = prism([(-14, 0), (14, 0), (14, 42)], 44, ["bottom", "back", "slope", "+y", "-y"],
              "wedge")
    return [_one("wedge", Solid(w), at=pose(yaw=15))]


def _frustum(grid: Grid, rng: np.random.Generator) -> list[Part]:
    return [_one("frustum", Solid(frustum(64, 28, 30, "frustum")), at=pose(yaw=10))]


def _lying(radius: float, length: float, prefix: str) -> Convex:
    return cylinder(radius, length, prefix).moved(pose(0, 0, -length / 2).then(pose(pitch=90)))


def _cylinders(grid: Grid, rng: np.random.Generator) -> list[Part]:
    lying = _lying(14, 70, "lying")
    standing = cylinder(16, 30, "standing")
    return [_one("lying cylinder", Solid(lying), at=pose(-8, -24, yaw=25)),
            _one("standing cylinder", Solid(standing), at=pose(32, 30))]


def _sphere(grid: Grid, rng: np.random.Generator) -> list[Part]:
    return [_one("sphere", Solid(sphere(26, "sphere")), at=pose())]


def _nut(grid: Grid, rng: np.random.Generator) -> list[Part]:
    return [_one("nut", Solid(nut(60)), at=pose(roll=25, yaw=10))]


def _pile_part(kind: str, i: int, rng: np.random.Generator) -> Solid:
    j = rng.uniform(0.85, 1.15, size=3)
    name = f"{kind} {i}"
    if kind == "box":
        body: Body = box(34 * j[0], 24 * j[1], 14 * j[2], name)
    elif kind == "cylinder":
        body = _lying(8 * j[0], 38 * j[1], name)
    elif kind == "sphere":
        body = sphere(10 * j[0], name)
    elif kind == "wedge":
        body = prism([(-6 * j[0], 0), (6 * j[0], 0), (6 * j[0], 18 * j[1])], 22 * j[2],
                     ["bottom", "back", "slope", "+y", "-y"], name)
    elif kind == "frustum":
        body = frustum(30 * j[0], 16 * j[0], 12 * j[1], name)
    else:
        body = nut(32 * j[0], name)
    return Solid(body)


#: Parts a pile is made of.
PILE_KINDS = ("box", "cylinder", "sphere", "wedge", "frustum", "nut")


def _pile(grid: Grid, rng: np.random.Generator, count: int = 7) -> list[Part]:
    """Parts dropped one after another onto the table and each other (a bin pile)."""
    hx, hy = grid.half_extent
    parts = []
    for i in range(1, count + 1):
        kind = PILE_KINDS[int(rng.integers(len(PILE_KINDS)))]
        solid = _pile_part(kind, i, rng)
        roll, pitch = rng.uniform(-15, 15, size=2)
        x = rng.uniform(-min(hx - 22, 30), min(hx - 22, 30))
        y = rng.uniform(-min(hy - 22, 30), min(hy - 22, 30))
        at = pose(x, y, roll=roll, pitch=pitch, yaw=rng.uniform(0, 360))
        parts.append(_one(f"{kind} {i}", solid, at=at))
    return parts


#: Named scenes; the paper's test objects first (Sec. VI, Figs. 10-13).
SCENES: dict[str, SceneSpec] = {s.name: s for s in (
    SceneSpec("part1", "industrial part with step, roof and smooth edges", "Fig. 10", _part1),
    SceneSpec("cup", "coffee cup with a handle and a hollow inside", "Fig. 11", _cup),
    SceneSpec("part2", "second industrial part: narrow chamfer, bored boss, ramp", "Fig. 12",
              _part2),
    SceneSpec("cube-holes", "cube with a through hole in every face", "Fig. 13", _cube_holes),
    SceneSpec("box", "box lying flat (step edges only)", None, _box),
    SceneSpec("tilted-box", "box at an oblique pose (roof edges between faces)", None,
              _tilted_box),
    SceneSpec("frustum", "square pyramid frustum (convex and concave roof edges)", None,
              _frustum),
    SceneSpec("cylinder", "a lying and a standing cylinder", None, _cylinders),
    SceneSpec("sphere", "sphere on the table", None, _sphere),
    SceneSpec("wedge", "wedge: a ramp and a step", None, _wedge),
    SceneSpec("nut", "machined nut (triangle mesh) at an oblique pose", None, _nut),
    SceneSpec("pile", "bin pile: parts dropped onto each other (layout from the seed)", None,
              _pile),
)}

#: The paper's test objects (Sec. VI), as in ``sample_data/synthetic``.
PAPER_SCENES = ("part1", "cup", "part2", "cube-holes")


# =========================================================================== rendering


@dataclass(frozen=True, eq=False)
class Scene:
    """A rendered scene.

    Attributes
    ----------
    name
        The scene's name in :data:`SCENES`.
    heights
        float64 (H, W) noise-free heights in depth units (larger = closer).
    image
        uint8 or uint16 (H, W) raw image: heights plus noise, rounded (16-bit:
        in 1/256 depth units).
    gt
        int32 (H, W) ground-truth surface labels, 0 = no surface.
    info
        JSON-ready description: ``surfaces`` ``[{id, object, kind, name,
        pixels}]``, ``objects`` ``[{id, name, background}]`` (the table is
        object 0), ``uncovered`` object ids, and the rendering parameters.
    layers
        Per object, in placement order: (bottom, top) heights in depth units,
        NaN where the object is not on a pixel's line (for checks).
    """

    name: str
    heights: np.ndarray
    image: np.ndarray
    gt: np.ndarray
    info: dict[str, Any]
    layers: tuple[tuple[np.ndarray, np.ndarray], ...] = ()

    @property
    def uncovered(self) -> list[int]:
        """Ids of the objects no other part lies on."""
        return list(self.info["uncovered"])


def _table() -> Part:
    plane = Convex(np.array([[0, 0, 1, 0.0], [0, 0, -1, 1000.0]]),
                   (("table", _PLANE), ("table underside", _PLANE)))
    return Part("table", (Solid(plane),), background=True)


@dataclass
class _Stack:
    tops: list[np.ndarray] = field(default_factory=list)
    surfs: list[np.ndarray] = field(default_factory=list)
    bottoms: list[np.ndarray] = field(default_factory=list)


def _drop(parts: Sequence[Part], grid: Grid) -> _Stack:
    """Place the parts in order, each resting on what is below it (no interpenetration)."""
    stack = _Stack()
    envelope = np.full(grid.x.shape, -np.inf)
    for part in parts:
        top, surf, bottom = part.maps(grid)
        hit = np.isfinite(bottom)
        if not part.background and hit.any():
            dz = float(np.max(envelope[hit] - bottom[hit]))
            top, bottom = top + dz, bottom + dz
        envelope = np.maximum(envelope, top)
        stack.tops.append(top)
        stack.surfs.append(surf)
        stack.bottoms.append(bottom)
    return stack


def _labels(parts: Sequence[Part], stack: _Stack
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
    """Z-buffer: winning object, height and ground-truth label per pixel."""
    tops = np.stack(stack.tops)
    winner = np.argmax(tops, axis=0)
    z = np.take_along_axis(tops, winner[None], 0)[0]
    surf = np.take_along_axis(np.stack(stack.surfs), winner[None], 0)[0]
    width = max(len(p.surfaces) for p in parts)
    code = np.where(np.isfinite(z), winner * width + surf, -1)
    present = np.unique(code[code >= 0])
    lookup = np.zeros(len(parts) * width, np.int32)
    lookup[present] = np.arange(1, len(present) + 1)
    gt = np.where(code >= 0, lookup[np.maximum(code, 0)], 0).astype(np.int32)
    counts = np.bincount(gt.ravel(), minlength=len(present) + 1)
    surfaces = []
    for k, c in enumerate(present, start=1):
        obj, s = divmod(int(c), width)
        name, kind = parts[obj].surfaces[s]
        surfaces.append({"id": k, "object": obj, "kind": kind, "name": name,
                         "pixels": int(counts[k])})
    return winner, z, gt, surfaces


def _touching_pairs(gt: np.ndarray) -> set[tuple[int, int]]:
    """Pairs ``(a, b)``, ``0 < a < b``, of labels that are 8-neighbours somewhere."""
    pairs: set[tuple[int, int]] = set()
    for a, b in ((gt[:, :-1], gt[:, 1:]), (gt[:-1, :], gt[1:, :]),
                 (gt[:-1, :-1], gt[1:, 1:]), (gt[:-1, 1:], gt[1:, :-1])):
        lo, hi = np.minimum(a, b), np.maximum(a, b)
        keep = (lo > 0) & (lo != hi)
        pairs.update(zip(lo[keep].tolist(), hi[keep].tolist(), strict=True))
    return pairs


def _one_plane(z: np.ndarray, mask: np.ndarray) -> bool:
    """Whether ``mask`` spans a plane that holds all its exact heights (design units)."""
    rows, cols = np.nonzero(mask)
    design = np.column_stack([np.ones(rows.size), rows, cols])
    coef, _, rank, _ = np.linalg.lstsq(design, z[mask], rcond=None)
    return bool(rank == 3 and np.max(np.abs(design @ coef - z[mask])) <= FLUSH_TOLERANCE)


def join_flush_faces(gt: np.ndarray, z: np.ndarray, surfaces: list[dict[str, Any]]
                     ) -> tuple[np.ndarray, list[dict[str, Any]]]:
    """One ground-truth surface for touching coplanar faces of one object (Notes, 5).

    A part built of solids can have faces of two solids flush in one plane
    (part1's base, block and fillet end on one side, Fig. 10): in the image
    they are one planar surface, with no edge for any segmenter to find.
    Planar faces of the same object that are 8-neighbours and lie in one
    plane (every exact height of both within :data:`FLUSH_TOLERANCE` of the
    plane fitted to them) become one surface, named by their names joined
    with ``" & "``. A face too small to span a plane on its own (fewer than
    three pixels, or all in a line) is never joined: any plane holds it.

    Parameters
    ----------
    gt
        int32 (H, W) labels 1..K, 0 = no surface.
    z
        float (H, W) exact heights in design units (non-finite where ``gt`` is 0).
    surfaces
        ``{id, object, kind, name, pixels}`` per label, ids 1..K in order.

    Returns
    -------
    tuple
        The labels renumbered 1..K' in the order of each surface's first
        member, and their descriptions.
    """
    parent = list(range(len(surfaces) + 1))

    def root(k: int) -> int:
        while parent[k] != k:
            k = parent[k]
        return k

    by_id = {s["id"]: s for s in surfaces}
    spans = {k: by_id[k]["kind"] == _PLANE and _one_plane(z, gt == k) for k in by_id}
    for a, b in sorted(_touching_pairs(gt)):
        ra, rb = root(a), root(b)
        if ra == rb or by_id[a]["object"] != by_id[b]["object"] or not (spans[a] and spans[b]):
            continue
        group = np.isin(gt, [k for k in by_id if root(k) in (ra, rb)])
        if _one_plane(z, group):
            parent[max(ra, rb)] = min(ra, rb)
    roots = sorted({root(s["id"]) for s in surfaces})
    new_id = {r: i for i, r in enumerate(roots, start=1)}
    lookup = np.array([0] + [new_id[root(k)] for k in range(1, len(surfaces) + 1)], np.int32)
    joined = []
    for r in roots:
        members = [s for s in surfaces if root(s["id"]) == r]
        joined.append({**members[0], "id": new_id[r],
                       "name": " & ".join(s["name"] for s in members),
                       "pixels": sum(s["pixels"] for s in members)})
    return lookup[gt], joined


def _in_range(gt: np.ndarray, surfaces: list[dict[str, Any]], raw: np.ndarray, top: int
              ) -> tuple[np.ndarray, list[dict[str, Any]], int]:
    """Ground truth 0 where a surface's noise-free raw value rounds out of ``0..top`` (Notes, 5).

    There the image holds the clipped value (a flat plateau at 255 in 8
    bits), not the surface: no segmenter can find it. Returns the labels,
    the surfaces with their ``pixels`` counted again, and how many surface
    pixels were set to 0 (the labels are returned as they are when none).
    """
    rounded = np.rint(raw)
    out = (gt > 0) & ((rounded > top) | (rounded < 0))
    saturated = int(np.count_nonzero(out))
    if saturated == 0:
        return gt, surfaces, 0
    gt = np.where(out, 0, gt).astype(gt.dtype)
    counts = np.bincount(gt.ravel(), minlength=len(surfaces) + 1)
    return gt, [{**s, "pixels": int(counts[s["id"]])} for s in surfaces], saturated


def _uncovered(parts: Sequence[Part], stack: _Stack, winner: np.ndarray, z: np.ndarray
               ) -> list[int]:
    background = np.array([p.background for p in parts])
    out = []
    for i, part in enumerate(parts):
        if part.background:
            continue
        top = stack.tops[i]
        with np.errstate(invalid="ignore"):
            above = (np.isfinite(top) & (winner != i) & ~background[winner]
                     & (z > top + 1e-6))
        if not above.any():
            out.append(i)
    return out


def _check_name(name: str) -> None:
    if name not in SCENES:
        raise ValueError(f"scene {name!r} is unknown; allowed: " + ", ".join(SCENES))


def parse_scenes(text: str) -> list[str]:
    """Comma-separated names of :data:`SCENES` (spaces around them ignored).

    Raises
    ------
    ValueError
        One line naming the unknown scenes and what is allowed.
    """
    names = [v.strip() for v in text.split(",") if v.strip()]
    if not names:
        raise ValueError(f"{text!r}: expected a comma-separated list")
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise ValueError(f"unknown scene {', '.join(unknown)}; allowed: " + ", ".join(SCENES))
    return names


def parse_size(text: str) -> tuple[int, int]:
    """``"ROWSxCOLS"`` (or one number for a square) as (rows, cols), each 16..8192.

    Raises
    ------
    ValueError
        One line naming ``text`` and what is allowed.
    """
    rows, sep, cols = text.lower().partition("x")
    try:
        size = (int(rows), int(cols if sep else rows))
    except ValueError:
        size = (0, 0)
    if not all(16 <= s <= 8192 for s in size):
        raise ValueError(f"{text!r}: expected ROWSxCOLS, each 16..8192, e.g. 128x128")
    return size


#: Largest noise sigma of a rendered scene, depth units (the 8-bit range is 255 of them).
MAX_NOISE = 1000.0


def _real(value: Any) -> bool:
    """Whether ``value`` is a finite real number (not a bool, a string or NaN)."""
    return (isinstance(value, int | float | np.integer | np.floating)
            and not isinstance(value, bool | np.bool_) and math.isfinite(value))


def _check_options(size: Sequence[int], noise: float, bits: int,
                   units_per_pixel: float | None, table_height: float = TABLE_HEIGHT
                   ) -> tuple[int, int]:
    if (isinstance(size, str | bytes) or not hasattr(size, "__len__") or len(size) != 2
            or not all(isinstance(s, int | np.integer) and not isinstance(s, bool)
                       and 16 <= s <= 8192 for s in size)):
        raise ValueError(f"`size` {size!r} must be two integers (rows, cols) from 16 to 8192")
    if not (_real(noise) and 0 <= noise <= MAX_NOISE):
        raise ValueError(f"`noise` {noise!r} must be a number from 0 to {MAX_NOISE:g} "
                         "(depth units)")
    if bits not in BITS:
        raise ValueError(f"`bits` {bits!r} must be 8 or 16")
    if units_per_pixel is not None and not (_real(units_per_pixel) and units_per_pixel > 0):
        raise ValueError(f"`units_per_pixel` {units_per_pixel!r} must be a number > 0")
    if not _real(table_height):
        raise ValueError(f"`table_height` {table_height!r} must be a finite number (depth "
                         "units)")
    return int(size[0]), int(size[1])


def render_scene(name: str, *, size: Sequence[int] = (128, 128), noise: float = 0.0,
                 seed: int = 0, bits: int = 8, units_per_pixel: float | None = None,
                 table_height: float = TABLE_HEIGHT) -> Scene:
    """Render a named scene of :data:`SCENES` as a range image with ground truth.

    Parameters
    ----------
    name
        A key of :data:`SCENES`, e.g. ``"cup"`` (Fig. 11 of Al-Hujazi & Sood).
    size
        (rows, cols) of the image, each 16..8192. Scenes are designed for
        128x128 and scale with ``min(rows, cols)``.
    noise
        Standard deviation of the Gaussian noise added to the heights, in
        depth units (the paper's Fig. 13 uses 1 and 2).
    seed
        Seeds the noise and, for ``"pile"``, the layout. Same seed, same bytes.
    bits
        8 (raw = depth units, clipped to 0..255) or 16 (raw = 256 x depth
        units, clipped to 0..65535).
    units_per_pixel
        Depth units per pixel of lateral size; default ``256 / min(rows,
        cols)`` (2 at 128x128), so heights do not depend on the size.
    table_height
        Height of the table (the background) in depth units.

    Returns
    -------
    Scene
        Heights, raw image, ground-truth labels and description.

    Raises
    ------
    ValueError
        For an unknown scene or an option out of range (the message names it).
    """
    _check_name(name)
    shape = _check_options(size, noise, bits, units_per_pixel, table_height)
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ValueError(f"`seed` {seed!r} must be an integer >= 0")
    spec = SCENES[name]
    grid = Grid.for_image(shape)
    upp = UNITS_PER_DESIGN_UNIT / grid.scale if units_per_pixel is None else units_per_pixel
    per_design = upp * grid.scale  # depth units per design unit
    layout_rng = np.random.default_rng([seed, 0])
    parts = [_table(), *spec.build(grid, layout_rng)]
    stack = _drop(parts, grid)
    winner, z, gt, surfaces = _labels(parts, stack)
    gt, surfaces = join_flush_faces(gt.reshape(shape), z.reshape(shape), surfaces)
    heights = (table_height + per_design * z).reshape(shape)
    noisy = heights + noise * np.random.default_rng([seed, 1]).standard_normal(shape)
    raw_per_unit = 1.0 if bits == 8 else RAW_PER_UNIT_16
    top = 255 if bits == 8 else 65535
    image = np.clip(np.rint(noisy * raw_per_unit), 0, top).astype(
        np.uint8 if bits == 8 else np.uint16)
    gt, surfaces, saturated = _in_range(gt, surfaces, heights * raw_per_unit, top)
    info = {
        "scene": name, "description": spec.description, "figure": spec.figure,
        "size": list(shape), "noise": float(noise), "seed": int(seed), "bits": int(bits),
        "units_per_pixel": upp, "table_height": table_height,
        "input_scale": 1.0 / raw_per_unit,
        "surfaces": surfaces, "saturated": saturated,
        "objects": [{"id": i, "name": p.name, "background": p.background}
                    for i, p in enumerate(parts)],
        "uncovered": _uncovered(parts, stack, winner, z),
        "generator": "rangeseg synth (orthographic z-buffer, Al-Hujazi & Sood 1990 Sec. VI)",
    }
    layers = tuple(
        (np.where(np.isfinite(b), table_height + per_design * b, np.nan).reshape(shape),
         np.where(np.isfinite(t), table_height + per_design * t, np.nan).reshape(shape))
        for b, t in zip(stack.bottoms, stack.tops, strict=True))
    return Scene(name, heights, image, gt.reshape(shape), info, layers)


# =========================================================================== batch


def scene_stem(name: str, noise: float) -> str:
    """File stem of a scene at a noise level: ``cup-n1``, ``pile-n0.5``."""
    return f"{name}-n{noise:g}"


def write_scenes(out_dir: str | Path, names: Iterable[str], noises: Iterable[float], seed: int,
                 size: Sequence[int] = (128, 128), bits: int = 8) -> list[Path]:
    """Render scenes at noise levels and write them with their ground truth.

    For each scene and noise level writes ``OUT/<stem>.png`` (the range
    image), ``OUT/<stem>.gt.npy`` (int32 labels) and ``OUT/<stem>.gt.json``
    (:attr:`Scene.info`), atomically; ``<stem>`` is :func:`scene_stem`.
    The same arguments give the same bytes. A scene and noise level given
    twice is written once.

    Parameters
    ----------
    out_dir
        Output folder (created if missing).
    names
        Keys of :data:`SCENES`.
    noises
        Noise standard deviations in depth units.
    seed, size, bits
        As in :func:`render_scene`.

    Returns
    -------
    list of Path
        The files written, three per scene and noise level.

    Raises
    ------
    ValueError
        For an unknown scene, an option out of range, or two noise levels that
        would be written under one name (:func:`scene_stem`), before anything
        is written.
    """
    from ..batch.io import write_json, write_npy, write_png

    names, noises = list(names), list(noises)
    for name in names:
        _check_name(name)
    for noise in noises:
        _check_options(size, noise, bits, None)
    out = Path(out_dir)
    written: list[Path] = []
    for stem, (name, noise) in _stems(names, noises).items():
        scene = render_scene(name, size=size, noise=noise, seed=seed, bits=bits)
        paths = (out / f"{stem}.png", out / f"{stem}.gt.npy", out / f"{stem}.gt.json")
        write_png(paths[0], scene.image)
        write_npy(paths[1], scene.gt)
        write_json(paths[2], scene.info)
        written.extend(paths)
    return written


def _stems(names: list[str], noises: list[float]) -> dict[str, tuple[str, float]]:
    """The scene and noise level of each file stem to write, in the order requested.

    Raises
    ------
    ValueError
        When two noise levels give one stem (``0.123456789`` and ``0.1234567891``
        are both ``-n0.123457``): the second would replace the first.
    """
    stems: dict[str, tuple[str, float]] = {}
    for name in names:
        for noise in noises:
            stem = scene_stem(name, noise)
            if stem in stems and stems[stem] != (name, noise):
                raise ValueError(f"noise levels {stems[stem][1]!r} and {noise!r} would both "
                                 f"be written as {stem}.*; give levels that differ within "
                                 "6 significant digits")
            stems[stem] = (name, noise)
    return stems
