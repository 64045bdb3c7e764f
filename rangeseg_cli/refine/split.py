"""Split components that fail a quality-of-fit test (Sec. VIII).

Beyond Al-Hujazi & Sood (1990). Their conclusion (Sec. VIII) proposes: "to
improve the robustness of the algorithm a test on the quality of the fit in
each component should be performed. If the test fails the component should
be divided into two or more component[s]." This module does that between the
components of step 3 (Sec. V-3) and the region growing of step 4 (Sec. V-4).

Notes
-----
1. Noise: :func:`rangeseg_cli.stages.noise.estimate_noise` (re-exported here with
   :func:`~rangeseg_cli.stages.noise.noise_scaled_config`).
2. Fit test (:func:`failing_components`). A component fails when the RMS
   error of its quadric fit (e_A of Sec. V-4) exceeds ``split.fit_factor``
   times ``max(noise, sqrt(grow.min_error))``.
3. Split (:func:`split_component`). Surface normals come from local plane
   fits restricted to the component (Gaussian weights, ``split.normal_sigma``
   pixels). They are divided into those near the dominant orientation and
   the rest (:func:`mode_split`); each class falls into its 4-connected
   parts; speckle and thin parts (slivers along a crease, the steep rim of a
   curved surface) go to their nearest wide part (when that leaves one part,
   the class of the dominant orientation is divided again by its own mode:
   :func:`_split_mode_class`); then every pixel near two
   parts goes, twice, to the part whose local plane (fitted to the part's
   core, away from the crease) predicts it better. Pieces that still fail
   the test are split again, breadth first, up to ``split.max_pieces``.
   With ``split.crease_pieces`` (beyond the paper) pieces whose plane fails
   the test are split again too, and a piece the normals do not divide is
   cut along a straight crease (:func:`~rangeseg_cli.refine.recut.crease_side`).
   With ``split.trim_pieces`` (beyond the paper) a failing piece that
   neither divides leaves out the pixels off its dominant surface (a sliver
   of a neighbouring face, :func:`_trim`); they are regrown later, except,
   with ``split.trim_faces``, those that one plane fits: a narrow face (a
   chamfer, a grazing side) becomes a piece of its own
   (:func:`_trimmed_faces`). With ``split.plane_cut``, a failing piece that
   is neither divided nor trimmed (two or three faces a few pixels wide, a
   small frustum's sides with its top) is cut into the planes consensus
   finds in it when they hold most of its pixels (:func:`_plane_cut`).
4. Merging back (:func:`merge_back`). Neighbouring pieces stay apart only
   when one quadric fits their union ``split.min_gain`` times worse than
   their own quadrics (and worse than region growing's noise-free
   tolerance), or when both are planes passing the test that meet at
   ``split.min_crease`` degrees or more (with ``split.crease_pieces`` also
   when two passing planes fit them better than the union's quadric by the
   recut's least crease gain). A genuinely curved surface
   (cylinder, sphere) whose quadric fails the test is cut up and merged
   back whole; two faces meeting at a crease stay apart however shallow
   the crease, as long as it stands out of the noise.
5. Regrowing (:func:`split_regions`). The pieces replace their component,
   separated by a one-pixel line (which stays an edge: "no merging",
   Sec. V-4), components are renumbered in raster order of their first pixel
   (as :func:`~rangeseg_cli.stages.link.label_components` numbers them), and region
   growing (Sec. V-4) runs again on the new components. ``split.rounds``
   (2) repeats the test and the split on the regions so grown.

Everything is a pure function of its arrays: the noise comes from ``z``
alone, so the ``grow`` stage stays a function of (z, edges, components,
config). The loop over failing components is bounded by their number times
``split.max_pieces``; every step inside it is vectorised and works on the
piece's bounding box. Inside a split, each part's local planes are computed
only on the pixels within reach of the pixels they judge and of the part's
core (:func:`_plane_heights`), and nearest parts are found by searching a
few pixels around (:func:`_nearest_labels`): both give bit for bit what the
whole box gives, so the results do not depend on these shortcuts.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from scipy import ndimage

from ..config import Config, GrowConfig, SplitConfig
from ..kernels.backend import Backend, select_deferred, select_kernels
from ..kernels.parallel import map_pixel_bands, map_tasks, row_bands
from ..stages.grow import (
    EIGHT_NEIGHBOURS,
    Fits,
    evaluate_quadric,
    fit_models,
    fit_quadrics,
    grow_regions,
    planar,
    region_fits,
)
from ..stages.link import FOUR_CONNECTED
from ..stages.noise import estimate_noise, noise_scaled_config  # noqa: F401 (re-exported)
from ..stages.rangeimage import consecutive_labels
from ..stages.surfaces import label_boxes
from .graph import RegionGraph, merge_ranked, region_graph
from .planes import (
    blur_radius,
    blur_weights,
    local_gradients,
    local_planes,
    min_det,
    writeable_weights,
)
from .recover import INLIER_FACTOR, consensus_plane, plane_pieces
from .recut import MIN_GAIN, crease_side
from .regions import (
    adjacent_pairs,
    bounding_box,
    box_area,
    c_array,
    crease_angle,
    raster_renumber,
)

#: Bin width of the histogram of normals (x, y components) whose peak is the mode.
_MODE_BIN = 0.05

#: Reassignment rounds of the band around the division.
_REFINE_ROUNDS = 2

#: Radius (pixels) within which the nearest labelled pixel is searched directly.
_SEARCH_RADIUS = 4

#: The same for the compiled search, which tries the offsets of a pixel one by one and
#: stops at the first label: a wide radius costs only for pixels far from every label,
#: which would otherwise take the feature transform of the whole array (on the SR300
#: frame 227 transforms, 60 ms, for a median of 23 such pixels).
_FAR_SEARCH_RADIUS = 16

#: Arrays of fewer pixels take the nearest labelled pixel from the feature transform.
_SEARCH_MIN_PIXELS = 1 << 15


def failing_components(z: np.ndarray, components: np.ndarray, noise: float,
                       cfg: SplitConfig, grow: GrowConfig, *, fits: Fits | None = None
                       ) -> np.ndarray:
    """Ids of the components whose quadric fit fails the quality test (Sec. VIII).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    components
        int (H, W) components 1..n, 0 = none.
    noise
        Noise sigma of the image (:func:`estimate_noise`).
    cfg, grow
        ``config.split`` (``fit_factor``, ``min_piece``) and ``[grow]`` (``min_error``).
    fits
        :func:`~rangeseg_cli.stages.grow.component_fits` of ``z`` and ``components``
        when the caller has them (the components' fits are computed here otherwise).

    Returns
    -------
    numpy.ndarray
        int64 ids, ascending, of components with ``RMS > fit_factor * max(noise,
        sqrt(min_error))`` and at least ``2 * min_piece`` pixels.
    """
    n = int(components.max(initial=0))
    if n == 0:
        return np.zeros(0, np.int64)
    _, mse, counts = fit_quadrics(z, components, n) if fits is None else fits
    if len(mse) != n + 1:
        raise ValueError(f"`fits` are of {len(mse) - 1} regions, the components {n}")
    level = cfg.fit_factor * max(noise, math.sqrt(grow.min_error))
    bad = (mse > level * level) & (counts >= 2 * cfg.min_piece)
    bad[0] = False
    return np.flatnonzero(bad).astype(np.int64)


#: Values from which :func:`_otsu` sorts by radix (below, ``np.sort`` is faster).
_RADIX_FROM = 10_000


def _otsu(x: np.ndarray, backend: Backend = "numpy") -> float:
    """Threshold of ``x`` that maximises the between-class variance (Otsu).

    With the compiled kernels (``backend``) the search over the sorted values
    is :func:`rangeseg_cli.kernels.compiled.otsu_index` (the same threshold), and
    from :data:`_RADIX_FROM` values on the sort is a radix sort of their bits
    (:func:`rangeseg_cli.kernels.compiled.smallest_sorted`: the same array, for the
    non-negative ``x`` here; 3x faster than ``np.sort`` on 270,000 values).
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        xs = (kernels.smallest_sorted(c_array(x, np.float64), x.size)
              if x.size >= _RADIX_FROM and not np.signbit(x).any() else np.sort(x))
        i = int(kernels.otsu_index(xs, float(xs.sum())))
        return 0.5 * (xs[i] + xs[i + 1])
    xs = np.sort(x)
    n = xs.size
    k = np.arange(1, n)
    csum = np.cumsum(xs)[:-1]
    m0 = csum / k
    m1 = (xs.sum() - csum) / (n - k)
    between = k * (n - k) * (m0 - m1) ** 2
    i = int(np.argmax(between))
    return 0.5 * (xs[i] + xs[i + 1])


def mode_split(normals: np.ndarray, *, backend: Backend = "auto") -> np.ndarray:
    """Divide unit normals into those of the dominant orientation and the rest.

    The mode is the peak of a smoothed 2-D histogram of the normals' (x, y)
    components (bins of :data:`_MODE_BIN`), refined to the mean of the
    normals within two bins of it; the normals then split at Otsu's
    threshold on their distance from the mode. A face that covers much of a
    component (a table around a part, one side of a roof) is its mode;
    several other faces end up in the rest together and fall apart into
    their connected parts, or are split again.

    Parameters
    ----------
    normals
        float64 (N, 3) unit normals, N >= 2.
    backend
        Of the histogram and Otsu's search (:func:`_histogram`, :func:`_otsu`):
        the same division either way.

    Returns
    -------
    numpy.ndarray
        bool (N,): True for the normals away from the mode (deterministic).
    """
    xy = normals[:, :2]
    hist = _histogram(xy, backend)
    peak = np.unravel_index(int(np.argmax(ndimage.gaussian_filter(hist, 1.0))), hist.shape)
    mode = -1.0 + (np.array(peak, dtype=np.float64) + 0.5) * _MODE_BIN
    x, y = np.ascontiguousarray(xy[:, 0]), np.ascontiguousarray(xy[:, 1])
    near = _squared_distance(x, y, mode) <= (2.0 * _MODE_BIN) ** 2
    if near.any():
        mode = xy[near].mean(axis=0)
    dist = np.sqrt(_squared_distance(x, y, mode))
    if np.ptp(dist) <= 0:
        return np.zeros(len(normals), bool)
    return dist > _otsu(dist, backend)


def _squared_distance(x: np.ndarray, y: np.ndarray, point: np.ndarray) -> np.ndarray:
    """``np.sum((xy - point) ** 2, axis=1)`` from the columns x, y (the same values)."""
    dx = x - point[0]
    dx *= dx
    dy = y - point[1]
    dy *= dy
    dx += dy
    return dx


@functools.lru_cache(maxsize=1)
def _mode_edges() -> np.ndarray:
    """Bin edges of the histogram of normals: -1..1 in steps of :data:`_MODE_BIN`."""
    edges = np.linspace(-1.0, 1.0, int(round(2.0 / _MODE_BIN)) + 1)
    edges.setflags(write=False)
    return edges


def _histogram(xy: np.ndarray, backend: Backend = "numpy") -> np.ndarray:
    """float64 2-D histogram of the (N, 2) points ``xy`` in the bins of :func:`_mode_edges`.

    What ``np.histogram2d(x, y, bins, range=[[-1, 1], [-1, 1]])`` gives, by
    the same bin search (right-closed last bin, points outside dropped) and
    one ``np.bincount``, without its generic set-up; with the compiled
    kernels (``backend``) in one sweep (:func:`rangeseg_cli.kernels.compiled.histogram2d`).
    """
    edges = _mode_edges()
    kernels = select_kernels(backend)
    if kernels is not None:
        counts = kernels.histogram2d(np.ascontiguousarray(xy[:, 0]),
                                     np.ascontiguousarray(xy[:, 1]), edges)
        return counts[1:-1, 1:-1].astype(np.float64)
    k = edges.size + 1  # with an outlier bin at each end
    index = []
    for column in (xy[:, 0], xy[:, 1]):
        i = np.searchsorted(edges, column, side="right")
        i[column == edges[-1]] -= 1
        index.append(i)
    hist = np.bincount(index[0] * k + index[1], minlength=k * k).reshape(k, k)
    return hist[1:-1, 1:-1].astype(np.float64)


@dataclass(frozen=True)
class _Frame:
    """The pixels being split and the scales of the split.

    Attributes
    ----------
    mask
        bool (h, w): the pixels (a component or a piece).
    solid
        ``mask`` with its holes below ``min_piece`` pixels and its gaps one
        or two pixels wide filled (a closing): the edge pixels and short edge
        curves that noise leaves inside a face are no border.
    min_piece
        Smallest part kept, pixels; also the smallest core of a wide part.
    thickness
        A part's core is its pixels at least this far (chessboard) from its
        border.
    band
        A pixel may change to a part within this distance (chessboard).
    sigma
        Gaussian sigma of the local planes that judge the pixels, pixels.
    backend
        Of the local planes, nearest-label searches and window filters
        (:func:`~rangeseg_cli.kernels.backend.select_kernels`): the same results either way.
    """

    mask: np.ndarray
    solid: np.ndarray
    min_piece: int
    thickness: int
    band: int
    sigma: float
    backend: Backend = "auto"

    @property
    def reach(self) -> int:
        """How far around the doubtful pixels :func:`_reassign` works: ``band`` + 3 sigma."""
        return self.band + int(math.ceil(3.0 * self.sigma))

    @classmethod
    def of(cls, mask: np.ndarray, cfg: SplitConfig, backend: Backend = "auto") -> _Frame:
        """The frame of ``mask`` with the scales of ``config.split`` (from ``[refine]``)."""
        holes, n = _holes(mask, backend)
        small = np.bincount(holes.ravel(), minlength=n + 1) < cfg.min_piece
        small[0] = False
        closed = _closing(mask, backend)
        return cls(mask=mask, solid=mask | small[holes] | closed, min_piece=cfg.min_piece,
                   thickness=int(math.ceil(cfg.normal_sigma)),
                   band=int(math.ceil(2.0 * cfg.normal_sigma)), sigma=2.0 * cfg.normal_sigma,
                   backend=backend)


def _holes(mask: np.ndarray, backend: Backend) -> tuple[np.ndarray, int]:
    """4-connected parts of ``~mask`` numbered 1..n, and n (:func:`scipy.ndimage.label`).

    With the compiled kernels (``backend``) from :func:`rangeseg_cli.kernels.compiled.value_parts`
    (the same numbers).
    """
    kernels = select_kernels(backend)
    if kernels is None:
        holes, n = ndimage.label(~mask, structure=FOUR_CONNECTED)
        return holes, int(n)
    holes = kernels.value_parts(c_array(~mask, np.int32))
    return holes, int(holes.max(initial=0))


def _closing(mask: np.ndarray, backend: Backend) -> np.ndarray:
    """Binary closing of ``mask`` by the 3x3 square (outside counts as unset).

    :func:`scipy.ndimage.binary_closing` (the reference) or, with the compiled
    kernels (``backend``), the minimum of the maximum over 3x3 windows
    (:func:`_window_extremes`, 0 outside): the same pixels.
    """
    if select_kernels(backend) is None:
        return ndimage.binary_closing(mask, structure=np.ones((3, 3), bool))
    _, dilated = _window_extremes(mask.astype(np.int32), 1, 0, backend)
    closed, _ = _window_extremes(dilated, 1, 0, backend)
    return closed.astype(bool)


def _parts(labels: np.ndarray, backend: Backend = "numpy") -> np.ndarray:
    """4-connected parts of every label, numbered 1..k (0 stays 0).

    Numbered by label, then in raster order of their first pixels: one
    ``scipy.ndimage.label`` per label (the reference) or, with the compiled
    kernels (``backend``), one flood fill
    (:func:`rangeseg_cli.kernels.compiled.value_parts`; the same parts and numbers).
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        return kernels.value_parts(c_array(labels, np.int32))
    out = np.zeros(labels.shape, np.int32)
    count = 0
    for value in _present(labels).tolist():
        lab, n = ndimage.label(labels == value, structure=FOUR_CONNECTED)
        out = np.where(lab > 0, lab + count, out)
        count += n
    return out


def _present(labels: np.ndarray) -> np.ndarray:
    """The labels > 0 that occur in ``labels`` (non-negative integers), ascending."""
    ids = np.flatnonzero(np.bincount(labels.ravel()))
    return ids[ids > 0]


def _dense(labels: np.ndarray) -> np.ndarray:
    """Renumber the labels present 1..k in increasing order (0 stays 0)."""
    ids = np.flatnonzero(np.bincount(labels.ravel()))
    lut = np.zeros(int(ids.max(initial=0)) + 1, np.int32)
    lut[ids] = np.arange(ids.size, dtype=np.int32) + (0 if ids[0] == 0 else 1)
    return lut[labels]


def _search_offsets(radius: int) -> tuple[np.ndarray, np.ndarray]:
    """Offsets (rows, cols) within Euclidean ``radius``, nearest first, then by column, row.

    The order in which :func:`scipy.ndimage.distance_transform_edt` breaks
    ties between equally near feature pixels (smaller column, then smaller
    row), so the first labelled pixel met is the one it returns.
    """
    span = np.arange(-radius, radius + 1)
    dr, dc = (a.ravel() for a in np.meshgrid(span, span, indexing="ij"))
    d2 = dr * dr + dc * dc
    keep = (d2 > 0) & (d2 <= radius * radius)
    order = np.lexsort((dr[keep], dc[keep], d2[keep]))
    return dr[keep][order], dc[keep][order]


_OFFSETS = _search_offsets(_SEARCH_RADIUS)
_FAR_OFFSETS = _search_offsets(_FAR_SEARCH_RADIUS)


def _nearest_labels(parts: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    backend: Backend = "numpy") -> np.ndarray:
    """Label of the nearest labelled pixel of ``parts`` (Euclidean) for each pixel (rows, cols).

    The pixels are unlabelled. Those with a labelled pixel within
    :data:`_SEARCH_RADIUS` find it by trying the offsets of
    :func:`_search_offsets` in order; the rest take it from the feature
    transform of the whole array. Both give what the feature transform
    gives for all of them. With the compiled kernels (``backend``) the search
    is :func:`rangeseg_cli.kernels.compiled.nearest_labels`, within
    :data:`_FAR_SEARCH_RADIUS`.
    """
    h, w = parts.shape
    kernels = select_kernels(backend)
    if kernels is not None:
        found = kernels.nearest_labels(c_array(parts, np.int32), rows, cols,
                                       *_FAR_OFFSETS)
        todo = np.flatnonzero(found == 0)
        return found if todo.size == 0 else _nearest_by_transform(parts, rows, cols, found,
                                                                  todo)
    found = np.zeros(rows.size, np.int32)
    todo = np.arange(rows.size)
    for dr, dc in zip(*_OFFSETS, strict=True):
        r, c = rows[todo] + dr, cols[todo] + dc
        inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
        lab = np.zeros(todo.size, np.int32)
        lab[inside] = parts[r[inside], c[inside]]
        hit = lab > 0
        found[todo[hit]] = lab[hit]
        todo = todo[~hit]
        if todo.size == 0:
            return found
    return _nearest_by_transform(parts, rows, cols, found, todo)


def _nearest_by_transform(parts: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                          found: np.ndarray, todo: np.ndarray) -> np.ndarray:
    """``found`` with its entries ``todo`` from the feature transform of ``parts``."""
    ir, ic = ndimage.distance_transform_edt(parts == 0, return_distances=False,
                                            return_indices=True)
    found[todo] = parts[ir[rows[todo], cols[todo]], ic[rows[todo], cols[todo]]]
    return found


def _fill_nearest(parts: np.ndarray, where: np.ndarray, backend: Backend = "auto"
                  ) -> np.ndarray:
    """``parts`` on ``where``, each unlabelled pixel taking its nearest labelled pixel's label.

    Ties go as :func:`scipy.ndimage.distance_transform_edt` breaks them
    (:func:`_nearest_labels`); with the compiled kernels (``backend``) the
    copy and the search are one sweep (:func:`rangeseg_cli.kernels.compiled.fill_nearest`).
    """
    kernels = select_kernels(backend)
    if kernels is not None:  # one sweep; the feature transform for what it leaves
        out, missing = kernels.fill_nearest(c_array(parts, np.int32),
                                            c_array(where, np.bool_), *_FAR_OFFSETS)
        if missing:
            rows, cols = np.nonzero(out < 0)
            out[rows, cols] = _nearest_by_transform(parts, rows, cols,
                                                    np.zeros(rows.size, np.int32),
                                                    np.arange(rows.size))
        return out
    out = np.where(where, parts, 0).astype(np.int32)
    if parts.max(initial=0) == 0:
        return out
    rows, cols = np.nonzero(where & (parts == 0))
    if rows.size == 0:
        return out
    if parts.size < _SEARCH_MIN_PIXELS:  # the transform is cheaper than the search
        ir, ic = ndimage.distance_transform_edt(parts == 0, return_distances=False,
                                                return_indices=True)
        out[rows, cols] = parts[ir[rows, cols], ic[rows, cols]]
    else:
        out[rows, cols] = _nearest_labels(parts, rows, cols)
    return out


def _core(parts: np.ndarray, frame: _Frame) -> np.ndarray:
    """``parts`` where a pixel lies ``frame.thickness`` or more from its part's border.

    The border is where another part or the outside of ``frame.solid``
    begins (small holes are not border).
    """
    filled = _fill_nearest(parts, frame.solid, frame.backend)
    # Within ``thickness`` (chessboard) of p all filled pixels carry p's part and none
    # lies outside the frame: the window's minimum is its maximum.
    low, high = _window_extremes(filled, frame.thickness, 0, frame.backend)
    inner = low == high
    return np.where(inner & frame.mask, parts, 0)


def core_bound(frame: _Frame) -> int:
    """Most pixels the cores of all parts of ``frame`` can hold together (:func:`_core`).

    A core pixel lies on ``frame.mask`` with the whole window of
    ``frame.thickness`` (chessboard) around it inside ``frame.solid`` and
    the array: the count of those pixels. Fewer than ``2 * min_piece`` leave
    no two wide parts (:func:`_clean`), so no split (Sec. VIII, Notes 3).
    """
    low, _ = _window_extremes(frame.solid.astype(np.int32), frame.thickness, 0,
                              frame.backend)
    return int(np.count_nonzero((low > 0) & frame.mask))


def _window_extremes(a: np.ndarray, reach: int, cval: int, backend: Backend
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Minimum and maximum filters of int ``a`` (``2 reach + 1`` square, ``cval`` outside)."""
    kernels = select_kernels(backend)
    if kernels is not None:
        return kernels.window_extremes(c_array(a, np.int32), reach, cval)
    size = 2 * reach + 1
    return (ndimage.minimum_filter(a, size=size, mode="constant", cval=cval),
            ndimage.maximum_filter(a, size=size, mode="constant", cval=cval))


def _label_extremes(parts: np.ndarray, reach: int, backend: Backend
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest label > 0 within ``reach`` (chessboard) of every pixel.

    The smallest is the largest int32 and the largest 0 where there is none:
    two window filters (:func:`_window_extremes`), or with the compiled
    kernels one call of :func:`rangeseg_cli.kernels.compiled.label_extremes`.
    """
    kernels = select_kernels(backend)
    if kernels is not None:
        return kernels.label_extremes(c_array(parts, np.int32), reach)
    big = int(np.iinfo(np.int32).max)
    _, high = _window_extremes(parts, reach, 0, backend)
    low, _ = _window_extremes(np.where(parts > 0, parts, big), reach, big, backend)
    return low, high


def _clean(labels: np.ndarray, frame: _Frame) -> np.ndarray:
    """Wide 4-connected parts of ``labels``, renumbered 1..k, covering ``frame.mask``.

    Parts below ``min_piece`` pixels (speckle of noisy normals) are filled
    from their nearest neighbours first; then parts with a core (:func:`_core`)
    below ``min_piece`` pixels -- a sliver along a crease, the steep rim of a
    curved surface, whose fit could not be judged -- go the same way. Once
    compiled (:func:`~rangeseg_cli.kernels.backend.select_deferred`), in one
    call of :func:`rangeseg_cli.kernels.compiled.clean_parts` (the same parts).
    """
    kernels = select_deferred(frame.backend, "clean_parts")
    if kernels is not None:
        out, status = kernels.clean_parts(
            c_array(labels, np.int32), c_array(frame.mask, np.bool_),
            c_array(frame.solid, np.bool_), frame.min_piece, frame.thickness, *_FAR_OFFSETS)
        if status == 1:  # 0: a pixel far from every label, left to the feature transform
            return out
    parts = np.where(frame.mask, _parts(_fill_nearest(labels, frame.solid, frame.backend),
                                        frame.backend), 0)
    sizes = np.bincount(parts.ravel())
    parts = _dense(_fill_nearest(np.where(sizes[parts] >= frame.min_piece, parts, 0),
                                 frame.mask, frame.backend))
    n = int(parts.max(initial=0))
    wide = np.bincount(_core(parts, frame).ravel(), minlength=n + 1) >= frame.min_piece
    wide[0] = False
    if n > 0 and wide[1:].all():  # every pixel of the mask keeps its part
        return parts
    lut = np.zeros(n + 1, np.int32)
    lut[wide] = np.arange(1, int(wide.sum()) + 1, dtype=np.int32)
    return _fill_nearest(lut[parts], frame.mask, frame.backend)


def _reassign(z: np.ndarray, parts: np.ndarray, frame: _Frame) -> np.ndarray:
    """Give each pixel near two or more parts to the one whose local plane predicts it best.

    Each part's surface near a pixel is the Gaussian-weighted plane (sigma
    ``frame.sigma``) fitted to the part's core (away from the blended
    normals at a crease); a pixel may only go to a part within
    ``frame.band``, so no plane is extrapolated far. Pixels near one part
    only keep their label. The work is confined to the bounding box of the
    doubtful pixels, and each part's planes to the pixels within reach of
    both its doubtful pixels and its core (:func:`_plane_heights`). Once
    compiled (:func:`~rangeseg_cli.kernels.backend.select_deferred`), in one
    call of :func:`rangeseg_cli.kernels.compiled.reassign_parts` (the same labels).
    """
    kernels = select_deferred(frame.backend, "reassign_parts")
    if kernels is not None:
        out, status = kernels.reassign_parts(
            c_array(z, np.float64), c_array(parts, np.int32), c_array(frame.mask, np.bool_),
            c_array(frame.solid, np.bool_), frame.band, frame.thickness,
            frame.reach, writeable_weights(frame.sigma), min_det(frame.sigma), *_FAR_OFFSETS)
        if status == 1:  # 0: a pixel far from every label, left to the feature transform
            return out
    low, high = _label_extremes(parts, frame.band, frame.backend)
    doubt = frame.mask & (high > 0) & (low != high)
    if not doubt.any():
        return parts
    box = bounding_box(doubt, frame.reach)
    sub, zb, doubt = parts[box], z[box], doubt[box]
    core = _core(parts, frame)[box]
    rows, cols = np.nonzero(doubt)
    extremes = (low[box][rows, cols], high[box][rows, cols])
    best = sub[rows, cols].copy()
    best_cost = np.full(rows.size, np.inf)
    for k in _present(sub).tolist():
        core_k = core == k
        if not core_k.any():
            continue
        near = np.flatnonzero(_near_part(sub, k, extremes, frame, rows, cols))
        if near.size == 0:
            continue
        r, c = rows[near], cols[near]
        cost = np.abs(zb[r, c] - _plane_heights(zb, core_k, frame.sigma, r, c, frame.backend))
        cost = np.where(np.isfinite(cost), cost, np.inf)
        better = cost < best_cost[near]
        best[near[better]] = k
        best_cost[near[better]] = cost[better]
    out = parts.copy()
    out[box][rows, cols] = best
    return out


def _near_part(parts: np.ndarray, k: int, extremes: tuple[np.ndarray, np.ndarray],
               frame: _Frame, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Whether pixels (rows, cols) lie within ``frame.band`` of part k (:func:`_near`).

    ``extremes`` are the smallest and largest part within ``frame.band`` of
    each pixel (:func:`_label_extremes`): part k is near where it is one of
    them, and not where it lies outside them; only pixels with k strictly
    between them are searched (none when k is the first or last part, as
    with two parts). ``parts`` holds every pixel within ``frame.band`` of the
    pixels.
    """
    low, high = extremes
    near = (low == k) | (high == k)
    between = (low < k) & (high > k)
    if between.any():
        near |= between & _near(parts == k, frame.band, rows, cols, frame.backend)
    return near


def _near(where: np.ndarray, reach: int, rows: np.ndarray, cols: np.ndarray,
          backend: Backend = "numpy") -> np.ndarray:
    """Whether pixels (rows, cols) lie within chessboard distance ``reach`` of ``where``.

    The maximum filter runs on the bounding box of ``where`` grown by
    ``reach`` only (the same values as on the whole array); with the compiled
    kernels (``backend``) it is :func:`_window_extremes`' maximum (the same pixels).
    """
    box = bounding_box(where, reach)
    inside = ((rows >= box[0].start) & (rows < box[0].stop)
              & (cols >= box[1].start) & (cols < box[1].stop))
    out = np.zeros(rows.size, bool)
    if select_kernels(backend) is not None:
        _, grown = _window_extremes(where[box].astype(np.int32), reach, 0, backend)
    else:
        grown = ndimage.maximum_filter(where[box], size=2 * reach + 1, mode="constant")
    out[inside] = grown[rows[inside] - box[0].start, cols[inside] - box[1].start]
    return out


def _plane_heights(z: np.ndarray, mask: np.ndarray, sigma: float, rows: np.ndarray,
                   cols: np.ndarray, backend: Backend = "auto") -> np.ndarray:
    """Heights at (rows, cols) of the local planes of ``mask`` in ``z`` (:mod:`.planes`).

    Bit for bit the values of ``local_planes(z, mask, sigma)[0][rows, cols]``,
    computed on the pixels within reach
    (:func:`~rangeseg_cli.refine.planes.blur_radius`) of both the
    pixels asked for and ``mask``; NaN where no ``mask`` pixel is within reach.
    With the compiled kernels (``backend``) only at the pixels asked for
    (:func:`rangeseg_cli.kernels.compiled.plane_heights_at`, the same values bit for
    bit; fastest with the pixels in raster order, as ``np.nonzero`` gives them).
    """
    reach = blur_radius(sigma)
    h, w = z.shape
    spans = []
    for axis, at in enumerate((rows, cols)):
        used = np.flatnonzero(mask.any(axis=1 - axis))
        lo = max(int(at.min()) - reach, int(used[0]) - reach, 0)
        hi = min(int(at.max()) + reach + 1, int(used[-1]) + reach + 1, z.shape[axis])
        spans.append((lo, hi))
    out = np.full(rows.size, np.nan)
    (r0, r1), (c0, c1) = spans
    if r1 <= r0 or c1 <= c0:
        return out
    inside = (rows >= r0) & (rows < r1) & (cols >= c0) & (cols < c1)
    kernels = select_kernels(backend)
    if kernels is not None:  # the planes at the pixels asked for only
        out[inside] = _compiled_heights(
            kernels, c_array(z[r0:r1, c0:c1], np.float64),
            c_array(mask[r0:r1, c0:c1], np.bool_), blur_weights(sigma),
            (float(c0 - w / 2.0), float(r0 - h / 2.0), min_det(sigma)),
            np.ascontiguousarray(rows[inside] - r0, np.int64),
            np.ascontiguousarray(cols[inside] - c0, np.int64))
        return out
    height, _, _ = local_planes(z[r0:r1, c0:c1], mask[r0:r1, c0:c1], sigma,
                                origin=(r0 - h / 2.0, c0 - w / 2.0), backend=backend)
    out[inside] = height[rows[inside] - r0, cols[inside] - c0]
    return out


def _compiled_heights(kernels: ModuleType, z: np.ndarray, mask: np.ndarray, w: np.ndarray,
                      frame: tuple[float, float, float], rows: np.ndarray, cols: np.ndarray
                      ) -> np.ndarray:
    """:func:`rangeseg_cli.kernels.compiled.plane_heights_at` (``frame``: u0, v0, min_det) in bands.

    The pixels (in raster order) are divided by row among the bands of
    :func:`~rangeseg_cli.kernels.parallel.map_pixel_bands`; each band's call sees its rows
    and the blur's reach either side, with its own row origin: the same
    heights bit for bit (as the local plane fits of :mod:`rangeseg_cli.refine.planes`).
    """
    u0, v0, min_det = frame
    height, width = z.shape
    reach = w.shape[0] // 2
    if len(row_bands(height, width, reach)) == 1 or np.any(rows[1:] < rows[:-1]):
        return kernels.plane_heights_at(z, mask, w, u0, v0, min_det, rows, cols)
    out = np.empty(rows.size)

    def band(i: int, j: int, lo: int, hi: int) -> None:
        out[i:j] = kernels.plane_heights_at(z[lo:hi], mask[lo:hi], w, u0, v0 + lo, min_det,
                                            rows[i:j] - lo, cols[i:j])

    map_pixel_bands(band, rows, height, width, reach)
    return out


def _split_once(z: np.ndarray, mask: np.ndarray, cfg: SplitConfig, backend: Backend = "auto"
                ) -> np.ndarray | None:
    """One split of the pixels of ``mask`` by their normals; None when there is none.

    The normals are divided in two (:func:`mode_split`); each class falls into
    its 4-connected parts, of which the wide ones are kept (:func:`_clean`);
    then, twice, every pixel goes to the part whose local plane predicts it
    best (:func:`_reassign`). A round that leaves fewer than two wide parts
    (on a face a few pixels wider than the planes' reach, reassignment can
    thin a part below the core it needs) is not taken: the parts from
    before it are kept, and later splits and :func:`merge_back` judge them.
    Returns int32 pieces 1..k (k >= 2) on ``mask``'s grid, 0 off ``mask``. A frame
    without room for two parts' cores (:func:`core_bound`) returns None at once.
    """
    frame = _Frame.of(mask, cfg, backend)
    if core_bound(frame) < 2 * frame.min_piece:  # no room for two wide parts
        return None
    rows, cols = np.nonzero(mask)
    gx, gy = local_gradients(z, mask, cfg.normal_sigma, backend=backend)
    gxs, gys = gx[rows, cols], gy[rows, cols]
    norm = np.sqrt(1.0 + gxs * gxs + gys * gys)
    normals = np.stack([-gxs / norm, -gys / norm, 1.0 / norm], axis=1)
    cls = mode_split(normals, backend=backend)
    if cls.all() or not cls.any():
        return None
    parts = _wide_parts(np.where(cls, 2, 1), rows, cols, frame)
    if parts is None:
        parts = _split_mode_class(normals, cls, rows, cols, frame)
    if parts is None:
        return None
    for _ in range(_REFINE_ROUNDS):
        refined = _clean(_reassign(z, parts, frame), frame)
        if refined.max(initial=0) < 2:
            break
        parts = refined
    return parts


def _split_mode_class(normals: np.ndarray, away: np.ndarray, rows: np.ndarray,
                      cols: np.ndarray, frame: _Frame) -> np.ndarray | None:
    """Parts from the mode class divided again, when the normals away from it made none.

    Beyond the paper. With three faces in a piece (two large ones at a crease
    and a sliver of a third, steeper one), Otsu's threshold can part the
    sliver from the two others, which then stay in the mode's class: the
    sliver is too thin to be a part, and the crease between the two large
    faces is never cut. Here the mode's class alone is divided by its own
    mode (:func:`mode_split`); the sliver's pixels are a third class, which
    :func:`_clean` gives to their neighbours when it is too thin. None when
    that makes fewer than two wide parts.
    """
    near = ~away
    if np.count_nonzero(near) < 2:
        return None
    sub = mode_split(normals[near], backend=frame.backend)
    if sub.all() or not sub.any():
        return None
    labels = np.full(rows.size, 3, np.int32)
    labels[near] = np.where(sub, 2, 1)
    return _wide_parts(labels, rows, cols, frame)


def _wide_parts(labels: np.ndarray, rows: np.ndarray, cols: np.ndarray, frame: _Frame
                ) -> np.ndarray | None:
    """:func:`_clean` of the class ``labels`` of the pixels (rows, cols); None below two parts."""
    classes = np.zeros(frame.mask.shape, np.int32)
    classes[rows, cols] = labels
    parts = _clean(classes, frame)
    return parts if parts.max(initial=0) >= 2 else None


def merge_back(z: np.ndarray, pieces: np.ndarray, *, level: float, floor: float,
               min_gain: float, min_crease: float, planar_tolerance: float,
               min_error: float, creases: float | None = None, excess: float | None = None,
               noise_test: bool = False) -> np.ndarray:
    """Merge neighbouring pieces that are one surface after all.

    Two neighbouring pieces i, j stay apart when one quadric fits their
    union with an RMS error above ``max(floor, min_gain * max(rms_i,
    rms_j))`` -- a crease between two faces makes the union's error many
    times the pieces' (which is the noise), while a genuinely curved surface
    cut in two (a cylinder or a sphere, which a quadric fits only
    approximately) fits about as badly whole as in pieces -- or, when both
    are planes that pass the fit test (so their fits are trustworthy and a
    crease between them well defined), when the planes meet at a median
    angle of ``min_crease`` degrees or more along the boundary, or (with
    ``excess``) when the union's quadric leaves much more error than the
    pieces' own. Otherwise they are merged: every pair is judged on its own
    two pieces, and pieces linked by pairs judged one surface become one
    region (:func:`~rangeseg_cli.refine.graph.merge_ranked`, whose judge here
    ignores what joined them before). A piece is a plane when its
    quadric lowers the plane's mean squared error by at most
    ``planar_tolerance`` of it (floored at ``min_error``), as in
    :func:`~rangeseg_cli.stages.surfaces.describe_surfaces`.

    Parameters
    ----------
    z
        float64 (h, w) heights.
    pieces
        int32 (h, w) pieces 1..n, 0 = none.
    level
        RMS error of the fit test (``fit_factor`` times the noise).
    floor
        An RMS error of the union that never keeps pieces apart by itself:
        ``sqrt(grow.error_factor * grow.min_error)``, the residual region
        growing accepts on a noise-free surface (Sec. V-4). Without it, on
        noise-free data a quadric's small misfit of a cylinder would count
        as a crease.
    min_gain, min_crease
        ``split.min_gain`` and ``split.min_crease``.
    planar_tolerance, min_error
        ``grow.planar_tolerance`` and ``grow.min_error``.
    creases
        With ``split.crease_pieces`` (beyond the paper), a gain in squared
        depth units per pixel: two pieces whose planes both pass the fit
        test also stay apart when their planes fit them better by this much
        than one quadric fits their union, and meet at ``min_crease``
        degrees or more, even if the planar rule calls one of them curved
        (at noise sigma 2 a quadric lowers a small face's error by more
        than ``planar_tolerance`` when it holds a few pixels of its
        neighbour). None: the rule is off.
    excess
        With ``split.min_excess`` (beyond the paper), squared depth units per
        pixel: two pieces also stay apart when one quadric of their union
        leaves more than this per pixel beyond the sum of their own quadrics'
        squared errors. The RMS rule compares the union with the worse of
        the two pieces; a small piece holding a few pixels of its neighbour
        (a ramp's piece beside the floor it rises from) has a high RMS of
        its own, and the union's far larger error then passes as "about as
        bad". A curved surface cut in two leaves little excess. None: off.
    noise_test
        ``grow.planar_noise_test``: the planar rule's noise test
        (:func:`~rangeseg_cli.stages.grow.planar`) on the pieces' pixel counts.

    Returns
    -------
    numpy.ndarray
        int32 (h, w) pieces renumbered 1..k in order of their smallest old id.
    """
    n = int(pieces.max(initial=0))
    if n < 2:
        return pieces
    fitted = region_fits(z, pieces, n, (2, 1))
    ((_, mse), (planes, mse_plane)), counts = fitted.fits, fitted.counts
    graph = region_graph(z, pieces, n, mse, fitted)
    rms = np.sqrt(np.maximum(mse, 0.0))
    flat = (rms <= level) & planar(mse, mse_plane, planar_tolerance, min_error,
                                   counts if noise_test else None)

    def judge(g: RegionGraph, a: int, b: int, i: int, j: int, union: float) -> float | None:
        """Pieces i, j judged on their own, whatever joined them before (0: one surface)."""
        apart = union > max(floor, min_gain * max(rms[i], rms[j]))
        if not apart and excess is not None:
            both = counts[i] + counts[j]
            own = counts[i] * mse[i] + counts[j] * mse[j]
            apart = union * union * both - own > excess * both
        if not apart and flat[i] and flat[j]:
            apart = crease_angle(pieces, planes, i, j) >= min_crease
        elif (not apart and creases is not None and mse_plane[i] <= level * level
              and mse_plane[j] <= level * level):
            apart = _two_planes(pieces, i, j, float(counts[i] * mse_plane[i]
                                                    + counts[j] * mse_plane[j]),
                                union, planes, min_crease, creases)
        return None if apart else 0.0

    ranked = [(math.sqrt(graph.union_mse(i, j)), i, j) for i, j in adjacent_pairs(pieces)]
    merge_ranked(graph, ranked, judge)
    return consecutive_labels(graph.labels)  # a group's id is its smallest piece's


def _replace(pieces: np.ndarray, k: int, sub: np.ndarray, n: int, max_pieces: int
             ) -> list[int]:
    """Put the pieces ``sub`` in the place of piece k, in place; return their ids.

    ``pieces`` may be a view of the box ``sub`` covers; ``n`` is the number
    of pieces in all. ``sub``'s piece 1 keeps id k, the others get the next
    free ids; pieces beyond ``max_pieces`` in all are dropped (0, to be
    regrown).
    """
    m = min(int(sub.max()), max_pieces - n + 1)
    ids = np.concatenate([[0, k], np.arange(n + 1, n + m)]).astype(np.int32)
    inside = pieces == k
    pieces[inside] = np.where(sub[inside] <= m, ids[np.minimum(sub[inside], m)], 0)
    return ids[1:].tolist()


def _fit_pieces(z: np.ndarray, pieces: np.ndarray, ids: list[int], backend: Backend,
                box: tuple[slice, slice] | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean squared errors of quadric and plane, and counts, valid for the pieces ``ids`` only.

    :func:`~rangeseg_cli.stages.grow.fit_models` (orders 2 and 1, one sweep) of
    ``pieces`` with the other pieces left out; a region's fit depends only
    on its own pixels (summed in raster order on the same grid), so the fits
    of ``ids`` are bit for bit those of all pieces fitted together. ``box``,
    when it holds every pixel of ``ids``, is all that is swept (the fits in
    the whole array's coordinates: ``origin`` of ``fit_models``).
    """
    n = int(pieces.max())
    keep = np.zeros(n + 1, bool)
    keep[ids] = True
    box = box or (slice(0, pieces.shape[0]), slice(0, pieces.shape[1]))
    sub = pieces[box]
    ((_, mse), (_, mse_plane)), counts = fit_models(
        z[box], np.where(keep[sub], sub, 0), n, (2, 1), backend=backend,
        origin=(box[0].start, box[1].start))
    return mse, mse_plane, counts


def _crease_cut(z: np.ndarray, mask: np.ndarray, *, noise: float, level: float,
                cfg: SplitConfig, grow: GrowConfig) -> np.ndarray | None:
    """Pieces 1, 2 of ``mask`` either side of a straight crease, or None (beyond the paper).

    For a piece whose normals the split cannot divide (two faces, one a few
    pixels wide): :func:`~rangeseg_cli.refine.recut.crease_side` -- two planes
    meeting along a line, each passing the fit test, at ``min_crease``
    degrees or more, fitting better than one quadric.
    """
    side = crease_side(z, mask, noise=noise, level=level, min_pixels=cfg.min_piece,
                       min_crease=cfg.min_crease, grow=grow)
    if side is None:
        return None
    return np.where(mask, np.where(side, 1, 2), 0).astype(np.int32)


def _crease_gain(noise: float, cfg: SplitConfig, grow: GrowConfig) -> float | None:
    """The ``creases`` gain of :func:`merge_back`: the recut's least gain of a crease.

    ``MIN_GAIN`` of :mod:`rangeseg_cli.refine.recut` times ``max(noise^2,
    grow.min_error)``; None without ``split.crease_pieces``.
    """
    return MIN_GAIN * max(noise * noise, grow.min_error) if cfg.crease_pieces else None


def _two_planes(pieces: np.ndarray, i: int, j: int, sse_planes: float, union_rms: float,
                planes: np.ndarray, min_crease: float, gain: float) -> bool:
    """Whether pieces i, j are two planes at a crease rather than one quadric (beyond the paper).

    ``sse_planes`` (each piece's own plane: 6 coefficients in all) is below
    the sum of squared errors of one quadric of their union (also 6; its
    RMS error ``union_rms``, from
    :meth:`~rangeseg_cli.refine.graph.RegionGraph.union_mse`) by ``gain`` per pixel or
    more, and the planes meet at ``min_crease`` degrees or more along the
    boundary.
    """
    n = int(((pieces == i) | (pieces == j)).sum())
    return (sse_planes + gain * n <= union_rms ** 2 * n
            and crease_angle(pieces, planes, i, j) >= min_crease)


def split_component(z: np.ndarray, mask: np.ndarray, *, noise: float, cfg: SplitConfig,
                    grow: GrowConfig, backend: Backend = "auto") -> np.ndarray:
    """Split one component that fails the fit test into pieces at its creases (Sec. VIII).

    Pieces that still fail are split again (breadth first) until none fails
    or can be split, or there are ``cfg.max_pieces``; then neighbouring
    pieces that one quadric fits about as well are merged back
    (:func:`merge_back`). With ``split.crease_pieces`` (beyond the paper) a
    piece whose plane fails the test is split again too (on a small piece
    a quadric can pass the test across the crease of two faces, a
    frustum's top and side at noise sigma 2), and a piece the normals do
    not divide is cut along a straight crease when two planes fit it
    (:func:`_crease_cut`). With ``split.trim_pieces`` (beyond the paper) a
    piece whose quadric fails and that neither divides leaves out, to be
    regrown, the pixels off its dominant surface (:func:`_trim`); with
    ``split.trim_faces`` the planes among them become pieces
    (:func:`_trimmed_faces`). With ``split.plane_cut`` (beyond the paper) a
    failing piece that none of these divide or trim is cut into the planes
    that consensus finds in it, when they hold most of it (:func:`_plane_cut`).

    Parameters
    ----------
    z
        float64 (h, w) heights (usually the component's bounding box).
    mask
        bool (h, w): the component's pixels.
    noise
        Noise sigma of the image (:func:`estimate_noise`).
    cfg, grow
        ``config.split`` (from ``[refine]``) and ``[grow]`` (``min_error``, ``error_factor``,
        ``planar_tolerance``).
    backend
        Of the local plane fits (:func:`~.planes.local_planes`): the same pieces either way.

    Returns
    -------
    numpy.ndarray
        int32 (h, w) pieces 1..k (k = 1: no split), 0 outside ``mask`` and
        at pixels dropped beyond ``max_pieces``.
    """
    level = cfg.fit_factor * max(noise, math.sqrt(grow.min_error))
    pieces = mask.astype(np.int32)
    queue = [1]
    quadric_passes: set[int] = set()  # pieces queued because their plane alone fails
    while queue and (n := int(pieces.max())) < cfg.max_pieces:
        k = queue.pop(0)
        box = bounding_box(pieces == k, 0)
        sub = _split_once(z[box], pieces[box] == k, cfg, backend)
        if sub is None and cfg.crease_pieces:
            sub = _crease_cut(z[box], pieces[box] == k, noise=noise, level=level, cfg=cfg,
                              grow=grow)
        if sub is None:
            if k not in quadric_passes:
                _trim_or_cut(z[box], pieces[box], k, n, level, cfg)
            continue
        ids = _replace(pieces[box], k, sub, n, cfg.max_pieces)
        mse, mse_plane, counts = _fit_pieces(z, pieces, ids, backend, box)
        fails = mse > level * level
        quadric_passes.update(i for i in ids if not fails[i])
        if cfg.crease_pieces:
            fails |= mse_plane > level * level
        queue += [i for i in ids if fails[i] and counts[i] >= 2 * cfg.min_piece]
    return merge_back(z, pieces, level=level,
                      floor=math.sqrt(grow.error_factor * grow.min_error),
                      min_gain=cfg.min_gain, min_crease=cfg.min_crease,
                      planar_tolerance=grow.planar_tolerance, min_error=grow.min_error,
                      creases=_crease_gain(noise, cfg, grow),
                      excess=cfg.min_excess * level * level if cfg.min_excess > 0 else None,
                      noise_test=grow.planar_noise_test)


#: A trimmed piece keeps at least this share of its pixels (else it is left whole).
_TRIM_KEEP = 0.6


#: A consensus plane's pixels (None: there is none) that a caller found, in a 1-tuple.
Found = tuple[np.ndarray | None]


def _trim(z: np.ndarray, pieces: np.ndarray, k: int, level: float,
          found: Found | None = None) -> np.ndarray | None:
    """Leave out the pixels of piece k that its dominant surface does not fit (in place).

    Beyond the paper. For a piece whose quadric fails the fit test (the
    caller does not pass one queued for its plane only, ``crease_pieces``;
    a component is split because its quadric fails) and that neither
    the normals nor a straight crease divide: usually one face with a sliver
    of its neighbour along the crease, too thin for a core of its own. The
    sliver keeps the piece's error high, and :func:`merge_back` then glues
    the piece to its neighbours across real creases. The dominant surface
    starts from the consensus plane of the recovery
    (:func:`~rangeseg_cli.refine.recover.consensus_plane`: the local plane most
    pixels fit within ``INLIER_FACTOR`` times the fit test's level), whose
    inliers a quadric is fitted to twice, each time taking the piece's
    pixels it fits within that tolerance. The rest are set to 0 (regrown
    later, or recovered as a narrow face) when the inliers are at least
    :data:`_TRIM_KEEP` of the piece and their quadric passes the fit test;
    else the piece is left as it is. A piece of a curved surface can lose
    its steepest margin, where the quadric misfits the circle's profile (up
    to a fifth of a quarter sphere noise-free); region growing gives those
    pixels back, and merge-back still glues the pieces of a cylinder or a
    sphere (``tests/test_split.py``).

    ``found`` holds that consensus plane's pixels when the caller has them
    (:func:`_trim_or_cut` finds them once for the trim and the plane cut).
    Returns the pixels left out (bool, ``pieces``' shape), None when the
    piece is left as it is.
    """
    mask = pieces == k
    tol = INLIER_FACTOR * level
    inliers = consensus_plane(z, mask, tol) if found is None else found[0]
    if inliers is None:
        return None
    rows, cols = np.nonzero(mask)
    for _ in range(2):
        coef, _, _ = fit_quadrics(z, inliers.astype(np.int32), 1)
        fitted = evaluate_quadric(coef[1], rows.astype(np.float64), cols.astype(np.float64))
        keep = np.abs(z[rows, cols] - fitted) < tol
        inliers = np.zeros_like(mask)
        inliers[rows[keep], cols[keep]] = True
    kept = int(np.count_nonzero(inliers))
    if kept == rows.size or kept < _TRIM_KEEP * rows.size:
        return None
    _, mse, _ = fit_quadrics(z, inliers.astype(np.int32), 1)
    if mse[1] > level * level:
        return None
    trimmed = mask & ~inliers
    pieces[trimmed] = 0
    return trimmed


def _trimmed_faces(z: np.ndarray, pieces: np.ndarray, trimmed: np.ndarray, n: int,
                   level: float, cfg: SplitConfig) -> None:
    """Give the planes among a trim's pixels pieces of their own, ids n+1... (in place).

    Beyond the paper (``split.trim_faces``). What :func:`_trim` leaves out
    is often a whole narrow face along the piece's border -- a chamfer 2-3
    pixels wide around a nut's top, a side seen at a grazing angle -- whose
    normals are too few and too blended for :func:`mode_split` to give it a
    core. Each 8-connected group of the trimmed pixels of at least
    ``split.min_piece`` pixels is cut into planes by consensus
    (:func:`~rangeseg_cli.refine.recover.plane_pieces`: the pixels within
    ``INLIER_FACTOR`` times the fit test's level of a consensus plane, as
    the recovery cuts a band); each plane of at least
    ``min_piece`` pixels becomes a piece, up to ``split.max_pieces`` in
    all. :func:`merge_back` then judges them as any other piece; the rest
    of the trim is regrown.
    """
    if np.count_nonzero(trimmed) < cfg.min_piece:  # no group of min_piece
        return
    groups, count = ndimage.label(trimmed, structure=EIGHT_NEIGHBOURS)
    sizes = np.bincount(groups.ravel(), minlength=count + 1)
    boxes = ndimage.find_objects(groups)
    for g in np.flatnonzero(sizes[1:] >= cfg.min_piece) + 1:
        box = boxes[g - 1]  # the group's own box: its planes see its pixels only
        for face in plane_pieces(z[box], groups[box] == g, level=level,
                                 min_pixels=cfg.min_piece):
            if n >= cfg.max_pieces:
                return
            n += 1
            pieces[box][face] = n


def _trim_or_cut(z: np.ndarray, pieces: np.ndarray, k: int, n: int, level: float,
                 cfg: SplitConfig) -> None:
    """A failing piece k that nothing divides: trimmed, else cut into planes (in place).

    With ``split.trim_pieces`` :func:`_trim` (and with ``split.trim_faces``
    :func:`_trimmed_faces` on what it leaves out); when there is no trim,
    with ``split.plane_cut`` :func:`_plane_cut`. ``n`` is the number of
    pieces of the whole component. Both start from the consensus plane of
    the piece (:func:`~rangeseg_cli.refine.recover.consensus_plane`), found once.
    """
    if not (cfg.trim_pieces or cfg.plane_cut):
        return
    found = (consensus_plane(z, pieces == k, INLIER_FACTOR * level),)
    trimmed = _trim(z, pieces, k, level, found) if cfg.trim_pieces else None
    if trimmed is not None:
        if cfg.trim_faces:
            _trimmed_faces(z, pieces, trimmed, n, level, cfg)
    elif cfg.plane_cut:
        _plane_cut(z, pieces, k, n, level, cfg, found)


#: The planes of a plane cut hold at least this share of the piece's pixels.
PLANE_CUT_COVER = 0.8


def _plane_cut(z: np.ndarray, pieces: np.ndarray, k: int, n: int, level: float,
               cfg: SplitConfig, found: Found | None = None) -> bool:
    """Cut piece k into the planes consensus finds in it, ids k, n+1, ... (in place).

    Beyond the paper (``split.plane_cut``). For a piece whose quadric fails
    the fit test and that neither the normals (:func:`_split_once`), a
    straight crease (:func:`_crease_cut`) nor a trim (:func:`_trim`: no
    surface holds :data:`_TRIM_KEEP` of it) divide: two or three faces each
    a few pixels wide, as a small frustum's sides with a strip of its top in
    a bin pile. Their normals blend over the whole width, so no class has a
    core; and the piece, failing, glues the others of its component back to
    it in :func:`merge_back` (a failing piece's own RMS makes any union look
    "about as bad"). The piece is cut into planes by consensus
    (:func:`~rangeseg_cli.refine.recover.plane_pieces`: the largest connected set
    of pixels one plane fits within ``INLIER_FACTOR`` times the fit test's
    level, then the next in what is left) when there are two or more of at
    least ``split.min_piece`` pixels, together :data:`PLANE_CUT_COVER` of
    the piece or more, and no more than ``split.max_pieces`` pieces in all
    result; the rest of its pixels are left to be regrown. A piece of a
    curved surface whose planes leave more than a fifth of it is left
    whole; where they hold it, :func:`merge_back` judges the planes as any
    other pieces. ``found`` holds the piece's consensus plane when the
    caller has it (the first plane of
    :func:`~rangeseg_cli.refine.recover.plane_pieces`).
    Returns whether the piece was cut.
    """
    mask = pieces == k
    faces = plane_pieces(z, mask, level=level, min_pixels=cfg.min_piece, found=found)
    held = sum(int(np.count_nonzero(f)) for f in faces)
    if (len(faces) < 2 or held < PLANE_CUT_COVER * np.count_nonzero(mask)
            or n + len(faces) - 1 > cfg.max_pieces):
        return False
    pieces[mask] = 0
    for i, face in enumerate(faces):
        pieces[face] = k if i == 0 else n + i
    return True


def _separate(labels: np.ndarray) -> np.ndarray:
    """Unlabel the pixel of higher label of every 4-adjacent pair of different labels.

    Pieces of one component touch; this leaves a one-pixel line between them,
    which region growing keeps as an edge ("no merging", Sec. V-4).
    """
    out = labels.copy()
    for axis in (0, 1):
        a = np.moveaxis(labels, axis, 0)
        o = np.moveaxis(out, axis, 0)
        lo, hi = a[:-1], a[1:]
        clash = (lo > 0) & (hi > 0) & (lo != hi)
        o[:-1][clash & (lo > hi)] = 0
        o[1:][clash & (hi > lo)] = 0
    return out


def split_components(z: np.ndarray, components: np.ndarray, config: Config,
                     noise: float, *, backend: Backend = "auto", fits: Fits | None = None
                     ) -> np.ndarray | None:
    """Components with every failing one replaced by its pieces (Sec. VIII).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    components
        int (H, W) components 1..n of step 3 (Sec. V-3), 0 = none.
    config
        Uses ``config.split`` (from ``[refine]``) and ``grow.min_error``.
    noise
        Noise sigma of the image (:func:`estimate_noise`).
    backend
        Of the local plane fits (:func:`~.planes.local_planes`): the same result either way.
    fits
        For :func:`failing_components` (the components' fits, when known).

    Returns
    -------
    numpy.ndarray or None
        int32 (H, W) new components 1..K in raster order of their first
        pixel, pieces separated by a one-pixel unlabelled line; None when no
        component was split.
    """
    cfg = config.split
    failing = failing_components(z, components, noise, cfg, config.grow, fits=fits)
    out = np.asarray(components, dtype=np.int32).copy()
    next_id = int(out.max(initial=0)) + 1
    boxes = label_boxes(out, next_id - 1, backend=backend) if failing.size else None
    spans = [(slice(r0, r1 + 1), slice(c0, c1 + 1))
             for r0, c0, r1, c1 in (boxes[failing].tolist() if boxes is not None else [])]

    def split_one(task: tuple[int, tuple[slice, slice]]) -> np.ndarray:
        cid, box = task
        return split_component(z[box], out[box] == cid, noise=noise, cfg=cfg,
                               grow=config.grow, backend=backend)

    tasks = list(zip(failing.tolist(), spans, strict=True))
    # The components are disjoint: split at once (many of them in processes: their work
    # is mostly Python), then numbered in order as one by one.
    results = map_tasks(split_one, tasks, cost=[float(box_area(box)) for box in spans])
    for (cid, box), pieces in zip(tasks, results, strict=True):
        inside = out[box] == cid
        k = int(pieces.max())
        if k < 2:
            continue
        ids = np.concatenate([[0, cid], np.arange(next_id, next_id + k - 1)]).astype(np.int32)
        next_id += k - 1
        out[box] = np.where(inside, ids[pieces], out[box])
    if next_id == int(np.max(components, initial=0)) + 1:
        return None
    return raster_renumber(_separate(out), backend)


def split_regions(z: np.ndarray, codes: np.ndarray, components: np.ndarray,
                  labels: np.ndarray, config: Config, *, noise: float | None = None,
                  backend: Backend = "auto", fits: Fits | None = None) -> np.ndarray:
    """Test every component's fit, split the failing ones and regrow (Sec. VIII, V-4).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    codes
        uint8 (H, W) linked edge codes of step 3.
    components
        int (H, W) components of step 3.
    labels
        int32 (H, W) the regions grown from ``components`` (returned when
        nothing is split).
    config
        The whole configuration (``config.split`` (from ``[refine]``) and ``[grow]``).
    noise
        Noise sigma of ``z`` (:func:`estimate_noise`); estimated when None.
    backend
        Of the local plane fits (:func:`~.planes.local_planes`): the same labels either way.
    fits
        :func:`~rangeseg_cli.stages.grow.component_fits` of ``z`` and ``components``
        when the caller has them (for the first round's fit test).

    Returns
    -------
    numpy.ndarray
        int32 (H, W) final labels: ``labels`` when no component fails the
        fit test or none can be split at a crease, else the regions grown
        (:func:`~rangeseg_cli.stages.grow.grow_regions`) from the split components.
        With ``split.rounds`` above 1 the grown regions (also those grown
        from unsplit components) are tested and split again: a piece of a
        large component (a frustum's top with one of its sides, when the
        component also held the table) can be left whole by the first round.
    """
    z = np.asarray(z, dtype=np.float64)
    noise = estimate_noise(z) if noise is None else noise
    valid = np.isfinite(z)
    for _ in range(config.split.rounds):
        new = split_components(z, np.where(valid, components, 0), config, noise,
                               backend=backend, fits=fits)
        fits = None  # they are of the first round's components
        if new is not None:
            labels = grow_regions(z, codes, new, config.grow)
        elif components is labels:
            break
        components = labels  # the next round tests the grown regions
    return labels
