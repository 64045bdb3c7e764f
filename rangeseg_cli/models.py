"""Result types shared between stages (surfaces, holdsites, the pipeline result).

Coordinates: ``row`` and ``col`` are 0-based pixel indices; surface
coefficients are in image coordinates with ``x = col`` and ``y = row``:
``z = a0 + a1 x + a2 y + a3 x^2 + a4 x y + a5 y^2`` (Sec. V-4), z in height
units (larger = closer to the sensor).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class Neighbor:
    """A region adjacent to a surface and the kind of edge between them.

    ``edge`` is one of ``"step"``, ``"roof-convex"``, ``"roof-concave"`` or
    ``"smooth"``.
    """

    id: int
    edge: str


@dataclass(frozen=True)
class Surface:
    """One final region of the segmentation and its quadratic fit (Sec. V-4).

    Attributes
    ----------
    id
        Label in ``labels.npy`` (1..K).
    pixels
        Number of pixels.
    bbox
        (row_min, col_min, row_max, col_max), inclusive.
    centroid
        (row, col) mean pixel position.
    mean_height
        Mean measured height of the region's pixels.
    coefficients
        (a0..a5) of ``z = a0 + a1 x + a2 y + a3 x^2 + a4 x y + a5 y^2``, x = col, y = row.
    rms_error
        Root mean squared residual of the fit.
    type
        ``"planar"`` or ``"curved"``.
    shape
        Besl & Jain HK sign type: ``"flat"``, ``"peak"``, ``"pit"``, ``"ridge"``,
        ``"valley"``, ``"saddle-ridge"``, ``"saddle-valley"`` or ``"minimal"``.
    neighbors
        Adjacent regions and the edge between them.
    """

    id: int
    pixels: int
    bbox: tuple[int, int, int, int]
    centroid: tuple[float, float]
    mean_height: float
    coefficients: tuple[float, float, float, float, float, float]
    rms_error: float
    type: str
    shape: str
    neighbors: tuple[Neighbor, ...] = field(default_factory=tuple)

    def height_at(self, row: float | np.ndarray, col: float | np.ndarray) -> Any:
        """Fitted height at (row, col)."""
        a0, a1, a2, a3, a4, a5 = self.coefficients
        x, y = col, row
        return a0 + a1 * x + a2 * y + a3 * x * x + a4 * x * y + a5 * y * y

    def gradient_at(self, row: float | np.ndarray, col: float | np.ndarray) -> tuple[Any, Any]:
        """(dz/dx, dz/dy) of the fit at (row, col), x = col, y = row."""
        _, a1, a2, a3, a4, a5 = self.coefficients
        return a1 + 2 * a3 * col + a4 * row, a2 + a4 * col + 2 * a5 * row

    def to_dict(self) -> dict[str, Any]:
        """Plain dict for ``surfaces.json``."""
        return asdict(self)
