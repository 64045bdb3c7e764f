"""Labelled point clouds and the holdsite as binary PLY files (docs/outputs.md).

``<stem>.points.ply`` holds one vertex per labelled pixel with a valid height:
its 3-D point, label, the unit normal of its surface's fit there and its
pixel. ``<stem>.holdsite.ply`` holds the site's footprint and approach arrow.
Both are binary little-endian PLY: a few header lines, then the bytes of a
numpy structured array.

Notes
-----
The frame (named in the header's ``comment`` lines) is
:func:`rangeseg_cli.cell.workspace.points`'s: with intrinsics the camera frame
(metres when ``[input] metres_per_unit`` is known, else depth units), else the
image frame ``(col s, row s, height)``, ``s`` = ``units_per_pixel`` (1 when
unknown). The surface's tangents ``dP/dcol`` and ``dP/drow`` are central
differences of that back-projection along the fit (height ``+- gradient / 2``
at ``+- 1/2`` pixel), exact because ``P`` is at most bilinear in pixel and
height; the normal is their cross product, turned towards the sensor. The
footprint's corners are the site's point plus the tangents times the
corners' pixel offsets: they lie in the site's tangent plane and their mean
is the site's point (``point_camera`` of ``holdsite.json`` with intrinsics).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any

import numpy as np

from .. import __version__
from ..cell.workspace import points
from ..config import InputConfig
from ..models import Surface
from ..stages.grow import evaluate_quadric, quadric_gradient

#: The vertices of ``points.ply``.
POINT_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("label", "<i4"),
                        ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"), ("row", "<i4"),
                        ("col", "<i4")])
_PLY_TYPES = {"f4": "float", "f8": "double", "i4": "int", "u1": "uchar", "u2": "ushort"}
#: Edges of ``holdsite.ply``: the footprint's outline, the arrow's shaft and head.
HOLDSITE_EDGES = ((0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (5, 7))


def ply_bytes(elements: Mapping[str, np.ndarray], comments: Sequence[str] = ()) -> bytes:
    """A binary little-endian PLY file: one element per structured array, in order.

    The arrays' fields are scalars of :data:`_PLY_TYPES`, little-endian.
    """
    lines = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments)]
    for name, data in elements.items():
        lines.append(f"element {name} {len(data)}")
        lines += [f"property {_PLY_TYPES[data.dtype[f].str.lstrip('<|')]} {f}"
                  for f in data.dtype.names or ()]
    header = "\n".join([*lines, "end_header"]) + "\n"
    return header.encode("ascii") + b"".join(d.tobytes() for d in elements.values())


def _table(columns: np.ndarray, names: str, kind: str) -> np.ndarray:
    """A structured array of the (N, K) ``columns``: fields ``names`` of type ``kind``."""
    return np.rec.fromarrays(list(columns.T), dtype=[(n, kind) for n in names.split()])


def frame(camera: InputConfig) -> str:
    """The header comment naming the frame and units of :func:`frame_points`."""
    if camera.has_intrinsics:
        unit = "metres" if camera.metres_per_unit > 0 else "depth units (no metres_per_unit)"
        return f"frame camera (x right, y down, z along the optical axis), {unit}"
    s = camera.units_per_pixel or 1.0
    return f"frame image (x = col * {s:g}, y = row * {s:g}, z = height), depth units"


def frame_points(z: np.ndarray, camera: InputConfig, rows: np.ndarray, cols: np.ndarray
                 ) -> np.ndarray:
    """:func:`~rangeseg_cli.cell.workspace.points` in metres where the camera's unit is known."""
    metric = camera.has_intrinsics and camera.metres_per_unit > 0
    return points(z, camera, rows, cols) * (camera.metres_per_unit if metric else 1.0)


def tangents(camera: InputConfig, rows: np.ndarray, cols: np.ndarray, height: np.ndarray,
             gx: np.ndarray, gy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``dP/dcol``, ``dP/drow`` (N, 3) of a fitted surface, and its unit normal (N, 3).

    ``height`` and ``(gx, gy) = (dz/dcol, dz/drow)`` are the fit's at the
    pixels; the units are :func:`frame_points`'s (module Notes).
    The normal faces the sensor (the camera, or +height).
    """
    def at(dz: np.ndarray | float, dr: float, dc: float) -> np.ndarray:
        return frame_points(height + dz, camera, rows + dr, cols + dc)

    du = at(gx / 2, 0.0, 0.5) - at(-gx / 2, 0.0, -0.5)
    dv = at(gy / 2, 0.5, 0.0) - at(-gy / 2, -0.5, 0.0)
    n = np.cross(du, dv) * (-1.0 if camera.has_intrinsics else 1.0)
    return du, dv, n / np.linalg.norm(n, axis=-1, keepdims=True)


def cloud(z: np.ndarray, labels: np.ndarray, camera: InputConfig
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows, cols (N,) of the labelled pixels with a valid height, and their points (N, 3).

    Row by row; the points in the frame of :func:`frame`.
    """
    rows, cols = np.nonzero((labels > 0) & np.isfinite(z))
    return rows, cols, frame_points(z[rows, cols], camera, rows, cols)


def labelled_points(z: np.ndarray, labels: np.ndarray, surfaces: Iterable[Surface],
                    camera: InputConfig) -> np.ndarray:
    """The vertices of ``points.ply`` (:data:`POINT_DTYPE`).

    Parameters
    ----------
    z
        float (H, W) heights, NaN = invalid (``range.npy``).
    labels
        int (H, W) labels, 0 = none (``labels.npy``).
    surfaces
        The surfaces of ``labels``, one per label (their fits give the normals).
    camera
        ``[input]``: intrinsics, ``metres_per_unit``, ``units_per_pixel``.
    """
    table = np.zeros((int(labels.max(initial=0)) + 1, 6))
    for s in surfaces:
        table[s.id] = s.coefficients
    rows, cols, xyz = cloud(z, labels, camera)
    ids = labels[rows, cols]
    gx, gy = quadric_gradient(table[ids], rows, cols)
    fitted = evaluate_quadric(table[ids], rows, cols)
    normal = tangents(camera, rows, cols, fitted, gx, gy)[2]
    out = np.empty(len(rows), POINT_DTYPE)
    for k, name in enumerate("xyz"):
        out[name], out[f"n{name}"] = xyz[:, k], normal[:, k]
    out["label"], out["row"], out["col"] = ids, rows, cols
    return out


def points_ply(z: np.ndarray, labels: np.ndarray, surfaces: Iterable[Surface],
               camera: InputConfig) -> bytes:
    """``points.ply``: :func:`labelled_points` with the header naming the frame."""
    return ply_bytes({"vertex": labelled_points(z, labels, surfaces, camera)}, [
        f"rangeseg {__version__}: one vertex per labelled pixel with a valid height",
        frame(camera), "nx ny nz: unit normal of the pixel's surface fit, towards the sensor"])


def holdsite_vertices(site: Mapping[str, Any], camera: InputConfig) -> np.ndarray:
    """(8, 3): the footprint's corners, the approach arrow's tail, tip and head's barbs.

    ``site`` is a site of ``holdsite.json`` (``row``, ``col``, ``elevation``,
    ``normal``, ``size``, ``angle``); the corners go round the footprint, their
    mean is the tip, the site's point (module Notes); the arrow is twice the
    footprint's longer side, along the approach (against the normal).
    """
    nx, ny, nz = site["normal"]
    row, col, h = (np.array([float(site[k])]) for k in ("row", "col", "elevation"))
    du, dv, normal = (v[0] for v in tangents(camera, row, col, h, np.array([-nx / nz]),
                                             np.array([-ny / nz])))
    tip = frame_points(h, camera, row, col)[0]
    t = math.radians(float(site["angle"]))
    along = np.array([-1.0, 1.0, 1.0, -1.0]) * site["size"][1] / 2
    across = np.array([-1.0, -1.0, 1.0, 1.0]) * site["size"][0] / 2
    dc, dr = along * math.cos(t) + across * math.sin(t), across * math.cos(t) - along * math.sin(t)
    corners = tip + dc[:, None] * du + dr[:, None] * dv
    side = np.linalg.norm(np.diff(corners[:3], axis=0), axis=1).max()
    across_arrow = (corners[1] - corners[0]) / np.linalg.norm(corners[1] - corners[0])
    barbs = [tip + side * (0.5 * normal + 0.25 * s * across_arrow) for s in (1, -1)]
    return np.vstack([corners, tip + 2 * side * normal, tip, *barbs])


def holdsite_ply(site: Mapping[str, Any], camera: InputConfig) -> bytes:
    """``holdsite.ply``: :func:`holdsite_vertices` and :data:`HOLDSITE_EDGES`."""
    vertex = _table(holdsite_vertices(site, camera), "x y z", "<f4")
    edge = _table(np.array(HOLDSITE_EDGES), "vertex1 vertex2", "<i4")
    return ply_bytes({"vertex": vertex, "edge": edge}, [
        f"rangeseg {__version__}: the holdsite of pixel (row {site['row']}, col "
        f"{site['col']})", frame(camera),
        "vertices 0-3: the footprint's corners, their mean the site's point",
        "vertices 4, 5: the approach arrow's tail and tip (the site's point); 6, 7: its head"])
