"""Raw pixel values to heights (docs/sensors.md, "Units").

Heights grow towards the sensor, as in the paper's ERIM images. Depth images
(closer = smaller) are negated; a configured no-data value, the top of an
integer type's range (a clipped value, :func:`clipped_value`), NaN and
infinities become NaN, which every later stage treats as "invalid": never
inside a smoothing mask, a fit or a holdsite, and labelled 0; small holes of
them are filled from the readings around them first (``[input] fill_holes``,
:func:`fill_small_holes`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from scipy import ndimage

from ..config import MAX_DEPTH, InputConfig
from ..errors import InputError
from ..kernels.backend import Backend, select_kernels

MIN_SIZE = 16
#: Largest |height| accepted, in depth units: far beyond any sensor, and small
#: enough that squares and moment sums of the fit stay finite in float64.
MAX_ABS_HEIGHT = MAX_DEPTH


def check_array(raw: Any, *, name: str = "image") -> np.ndarray:
    """Check that ``raw`` is a 2-D numeric array of at least 16x16.

    Parameters
    ----------
    raw
        Array-like of shape (H, W) or (H, W, 1).
    name
        Named in error messages (a file path or ``"image"``).

    Returns
    -------
    numpy.ndarray
        The (H, W) array (a view where possible; the input is never modified).

    Raises
    ------
    InputError
        For a non-numeric dtype, another shape, or a side below 16 pixels.
    """
    try:
        arr = np.asarray(raw)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name}: not an array ({exc})") from None
    if arr.dtype.kind not in "buif":
        raise InputError(f"{name}: pixel type {arr.dtype} is not numeric; allowed: integer "
                         "or floating-point")
    if arr.ndim == 3 and arr.shape[2] == 1:
        arr = arr[:, :, 0]
    if arr.ndim == 3 and arr.shape[2] in (2, 3, 4):
        raise InputError(f"{name}: has {arr.shape[2]} channels (shape {arr.shape}): a colour "
                         "or palette image; a range image has one (grey, 8 or 16 bits)")
    if arr.ndim != 2:
        raise InputError(f"{name}: shape {arr.shape} is not a 2-D range image; allowed: "
                         "(H, W) or (H, W, 1)")
    if min(arr.shape) < MIN_SIZE:
        raise InputError(f"{name}: size {arr.shape[1]}x{arr.shape[0]} pixels (width x "
                         f"height) is too small; at least {MIN_SIZE}x{MIN_SIZE} is needed")
    return arr


def to_heights(raw: Any, cfg: InputConfig, *, name: str = "image", backend: Backend = "auto"
               ) -> np.ndarray:
    """Convert raw values to heights in depth units, NaN where invalid.

    Parameters
    ----------
    raw
        Array-like (H, W) or (H, W, 1) of raw sensor values; the masked pixels
        of a ``numpy.ma.MaskedArray`` are invalid.
    cfg
        ``[input]``: ``scale``, ``larger_is_closer``, the ``invalid`` value,
        ``clipped_invalid`` (:func:`clipped_value`) and ``fill_holes``.
    name
        Named in error messages.
    backend
        ``"numpy"``: array operations (the reference); ``"numba"``:
        :func:`rangeseg_cli.kernels.compiled.heights`, one pass over a plain array of
        8- to 64-bit numbers (the same heights; masked arrays and other
        types take the reference); ``"auto"``: as
        :func:`~rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    numpy.ndarray
        float64 (H, W): ``raw * scale``, negated when smaller values are
        closer; NaN at invalid pixels but in the small holes
        :func:`fill_small_holes` fills (``cfg.fill_holes``). A new array: the
        input is not modified.

    Raises
    ------
    InputError
        When the array is not a usable range image or has no valid pixel.
    """
    masked = np.ma.getmaskarray(raw) if isinstance(raw, np.ma.MaskedArray) else None
    arr = check_array(raw if masked is None else np.ma.getdata(raw), name=name)
    factor = cfg.scale if cfg.larger_is_closer else -cfg.scale
    clipped = clipped_value(arr.dtype, cfg)
    kernels = select_kernels(backend)
    if kernels is not None and masked is None and arr.dtype in _COMPILED_TYPES:
        z, valid, peak = kernels.heights(np.ascontiguousarray(arr), float(factor),
                                         float(cfg.invalid), not math.isnan(cfg.invalid),
                                         float(clipped or 0), clipped is not None)
        _check_heights(valid == 0, peak, cfg, name)
        return fill_small_holes(z, cfg.fill_holes)
    z = arr.astype(np.float64)
    invalid = ~np.isfinite(z)
    if masked is not None:  # a masked array's masked pixels are invalid
        invalid |= masked.reshape(z.shape)
    if not math.isnan(cfg.invalid):
        invalid |= z == cfg.invalid
    if clipped is not None:
        invalid |= z == clipped
    with np.errstate(over="ignore", invalid="ignore"):
        z *= factor
    invalid |= ~np.isfinite(z)
    z[invalid] = np.nan
    none_valid = bool(invalid.all())
    _check_heights(none_valid, 0.0 if none_valid else float(np.nanmax(np.abs(z))), cfg, name)
    return fill_small_holes(z, cfg.fill_holes)


def fill_small_holes(z: np.ndarray, max_pixels: int) -> np.ndarray:
    """``z`` with each hole of at most ``max_pixels`` pixels filled from around it (in place).

    Beyond Al-Hujazi & Sood (1990), whose range images have a reading at
    every pixel. A depth camera leaves scattered pixels without a reading
    (speckle, on dark or shiny spots); the holdsite wants a window of
    readings on one surface (Sec. VII), and at 2 % of such pixels none of a
    20 mm cup's size is left on the SR300 frame of ``sample_data/arc``,
    though the cup spans every hole. Each 8-connected set of NaN pixels of
    ``max_pixels`` or fewer (at most 8: each pixel then touches a reading,
    but at the frame's border) takes, pixel by pixel, the median of the
    readings among its 8 neighbours, when they span at most
    :data:`HOLE_SPREAD` times the image's step between neighbouring readings
    (:func:`neighbour_step`); a pixel beside a depth jump stays NaN (it is
    part of the edge, and no height between the two surfaces is made up), as
    do larger holes (shadows, the frame's margin) and a pixel with no reading
    beside it.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    max_pixels
        ``[input] fill_holes``: 0 leaves ``z`` as it is.

    Returns
    -------
    numpy.ndarray
        ``z``, filled.
    """
    holes = np.isnan(z)
    if max_pixels <= 0 or not holes.any():
        return z
    parts, _ = ndimage.label(holes, structure=np.ones((3, 3), bool))
    rows, cols = np.nonzero(holes)  # the hole pixels alone from here on
    part = parts[rows, cols]
    small = np.bincount(part)[part] <= max_pixels
    rows, cols = rows[small], cols[small]
    if rows.size == 0:
        return z
    around = _neighbour_readings(z, rows, cols)
    ordered = np.sort(around, axis=1)  # NaN last
    count = np.count_nonzero(np.isfinite(around), axis=1)
    read = count > 0  # a pixel with no reading beside it stays NaN
    rows, cols, ordered, count = rows[read], cols[read], ordered[read], count[read]
    at = np.arange(rows.size)
    spread = ordered[at, count - 1] - ordered[:, 0]
    calm = spread <= HOLE_SPREAD * neighbour_step(z)  # not at a depth jump
    median = (ordered[at, (count - 1) // 2] + ordered[at, count // 2]) / 2.0
    z[rows[calm], cols[calm]] = median[calm]
    return z


def _neighbour_readings(z: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """(N, 8) heights of the 8 neighbours of pixels (rows, cols); NaN off the frame."""
    offsets = np.array(chessboard_offsets(1))
    r = rows[:, None] + offsets[:, 0]
    c = cols[:, None] + offsets[:, 1]
    inside = (r >= 0) & (r < z.shape[0]) & (c >= 0) & (c < z.shape[1])
    values = z[np.clip(r, 0, z.shape[0] - 1), np.clip(c, 0, z.shape[1] - 1)]
    return np.where(inside, values, np.nan)


#: :func:`fill_small_holes` fills a pixel whose neighbours' readings span at most this
#: many times :func:`neighbour_step` (else it lies at a depth jump).
HOLE_SPREAD = 8.0


#: :func:`neighbour_step` reads every k-th row and column, k the least that leaves about
#: this many differences of each.
STEP_SAMPLE = 32768


def neighbour_step(z: np.ndarray) -> float:
    """The image's step between adjacent readings: their median absolute difference.

    Of the horizontal and vertical neighbours in every k-th row and column
    (:data:`STEP_SAMPLE`); at least the smallest non-zero difference, the
    heights' quantum (a flat frame of whole millimetres has a median step of
    0, and a fill bounded by it would fill nothing but holes in flat patches).
    0 when no two readings are adjacent.
    """
    k = max(1, z.size // STEP_SAMPLE)
    steps = np.concatenate([np.abs(np.diff(z[::k], axis=1)).ravel(),
                            np.abs(np.diff(z[:, ::k], axis=0)).ravel()])
    steps = steps[np.isfinite(steps)]
    if not steps.size:
        return 0.0
    moved = steps[steps > 0]
    return max(float(np.median(steps)), float(moved.min()) if moved.size else 0.0)


def clipped_value(dtype: np.dtype, cfg: InputConfig) -> int | None:
    """The raw value that is clipped, not measured: the top of an integer type's range.

    255 for 8-bit images, 65535 for 16-bit (``np.iinfo(dtype).max``); None
    for floating-point images and when ``[input] clipped_invalid`` is off.
    A sensor (or a renderer) whose surface lies beyond its range writes
    this value: a flat plateau that no segmentation should describe as a
    surface, nor a holdsite grip (the object's top is closer than it says).
    """
    if not cfg.clipped_invalid or np.dtype(dtype).kind not in "ui":
        return None
    return int(np.iinfo(dtype).max)


#: :func:`depth_map_hint`: a depth map's nearest readings are at least this share of its
#: median (a camera over a bin sees no surface near 0); a height map's floor is near 0.
DEPTH_NEAR_SHARE = 0.4

#: :func:`depth_map_hint`: the least share of holes (0, or NaN in floating point), a depth
#: camera's "no reading".
DEPTH_LEAST_HOLES = 0.005

#: :func:`depth_map_hint`: the least median reading of a depth map in mm or 0.1 mm (beyond
#: 8-bit heights).
DEPTH_LEAST_MEDIAN = 256

#: :func:`depth_map_hint`: medians of a floating-point depth map in metres (0.1 to 10 m).
DEPTH_METRES = (0.1, 10.0)


#: :func:`depth_map_hint` reads every k-th row and column of a larger image, k the least
#: that leaves at most this many pixels.
DEPTH_HINT_PIXELS = 1_000_000


def depth_map_hint(raw: np.ndarray, cfg: InputConfig) -> str:
    """Why ``raw`` may be a camera's depth map read as heights, or ``""``.

    A depth map (depth along the optical axis, closer = smaller) read with
    ``[input]`` at its defaults, as a height map, puts the holdsite on the
    farthest surface: the tote's floor or rim. An image of 16 bits or more
    with :data:`DEPTH_LEAST_HOLES` of its pixels holes (0, or NaN in
    floating point: a depth camera's "no reading"), none negative, whose
    other readings have a 5th percentile of :data:`DEPTH_NEAR_SHARE` of
    their median or more (no floor near 0) and a median of
    :data:`DEPTH_LEAST_MEDIAN` or more (mm, 0.1 mm) or, in floating point,
    within :data:`DEPTH_METRES` (metres), reads as one. A height map with
    its floor at 0 reads as one too: setting any ``[input]`` key (e.g.
    ``units_per_pixel``) says what the image is.

    Parameters
    ----------
    raw
        The image as read (before :func:`to_heights`); one of more than
        :data:`DEPTH_HINT_PIXELS` pixels is read at a stride.
    cfg
        ``[input]``; anything but its defaults gives ``""``.

    Returns
    -------
    str
        ``""``, or what the readings are and what to pass instead.
    """
    raw = np.asarray(raw)
    seen = _hint_sample(raw, cfg, "uif")
    if seen is None:
        return ""
    with np.errstate(invalid="ignore"):
        if np.any(seen < 0) or np.isinf(seen).any():
            return ""  # signed heights
        readings = seen[seen > 0]
    holes = seen.size - readings.size
    if holes < DEPTH_LEAST_HOLES * seen.size or readings.size < max(100, seen.size // 10):
        return ""
    near, median = (float(v) for v in np.percentile(readings, [5, 50]))
    metres = raw.dtype.kind == "f" and DEPTH_METRES[0] <= median <= DEPTH_METRES[1]
    if near < DEPTH_NEAR_SHARE * median or not (metres or median >= DEPTH_LEAST_MEDIAN):
        return ""
    presets = ("metre-depth (depth in metres)" if metres
               else "mm-depth or tenth-mm-depth (depth in mm or 0.1 mm)")
    return (f"may be a depth map ({raw.dtype.itemsize * 8}-bit, {holes / seen.size:.0%} "
            f"holes; 95 % of its readings above {near:.4g}, median {median:.4g}) read as "
            "heights (larger = closer): the holdsite would go to the farthest surface. "
            f"For depth pass --preset {presets} with --intrinsics; for a height map set "
            "an [input] key (e.g. units_per_pixel) to say so")


#: :func:`fine_units_hint`: the top of an 8-bit image, whose heights the paper's
#: thresholds (6 / 6 / 4 depth units, Sec. VI) are set for.
EIGHT_BIT_TOP = 255


def fine_units_hint(raw: np.ndarray, cfg: InputConfig) -> str:
    """Why integer ``raw`` may hold heights in units too fine for the thresholds, or ``""``.

    The paper's images are 8-bit (Sec. VI), and its thresholds (a jump of 6
    depth units is a step edge) are set for their 0..255. A 16-bit height
    map in 0.1 mm (the ARC bin's ``bin-heightmap.depth.png``) read in raw
    units with ``[input]`` at its defaults turns every bump of a surface
    into an edge, and the holdsite finds nothing to pick. An integer image
    of 16 bits or more whose readings (all but the clipped top value,
    :func:`clipped_value`) reach down to :data:`EIGHT_BIT_TOP` or below (a
    height map's floor) and span more than it reads as one; setting an
    ``[input]`` key of the units (``scale`` to convert them, or
    ``units_per_pixel``) says what the image is.

    Parameters
    ----------
    raw
        The image as read (before :func:`to_heights`); one of more than
        :data:`DEPTH_HINT_PIXELS` pixels is read at a stride.
    cfg
        ``[input]``; anything but its defaults gives ``""``.

    Returns
    -------
    str
        ``""``, or the span of the readings and what to set.
    """
    raw = np.asarray(raw)
    seen = _hint_sample(raw, cfg, "ui")
    if seen is None:
        return ""
    top = clipped_value(raw.dtype, cfg)
    readings = seen[seen != top] if top is not None else seen
    if readings.size == 0:
        return ""
    low, high = int(readings.min()), int(readings.max())
    if high - low <= EIGHT_BIT_TOP or low > EIGHT_BIT_TOP:  # no floor near 0: no height map
        return ""
    return (f"has {raw.dtype.itemsize * 8}-bit heights spanning {low}..{high}, more than the "
            f"0..{EIGHT_BIT_TOP} of the 8-bit images the paper's thresholds are set for (a "
            "jump of 6 units is an edge): in units much finer than 1 mm every bump is an "
            "edge. Set input.scale to the unit in mm (e.g. --set input.scale=0.1 for 0.1 mm); "
            "if the units are right, set an [input] key (e.g. units_per_pixel) to say so")


#: :func:`coarse_units_hint`: depth units of this many metres or more are too coarse for
#: the settings in depth units (set for about 1 mm).
COARSE_UNIT_METRES = 0.01


def coarse_units_hint(raw: np.ndarray, cfg: InputConfig) -> str:
    """Why the heights of ``raw`` may be in units too coarse for the settings, or ``""``.

    The settings in depth units (the floor ``[grow] min_error`` of the
    growing of Sec. V-4, the workspace's and the holdsite's tolerances) are
    set for about 1 mm, as the sensor presets make every frame. Depth in
    metres (a float32 TIFF or ``.npy``, ROS's ``32FC1``) read with ``[input]
    scale = 1`` is 1,000 times coarser: every surface fits within them, the
    whole frame lies on the support, and there is nothing to pick. Says so
    when ``[input] metres_per_unit`` is :data:`COARSE_UNIT_METRES` or more;
    when a floating-point image read as depth (``larger_is_closer = false``)
    has a median reading of :data:`DEPTH_METRES` at ``scale = 1`` with
    ``metres_per_unit`` unknown (0); and when the units are said but make
    its median depth less than :data:`COARSE_UNIT_METRES` (metres read with
    ``--preset mm-depth``: no camera reads depth of 1 cm).

    Parameters
    ----------
    raw
        The image as read (before :func:`to_heights`); one of more than
        :data:`DEPTH_HINT_PIXELS` pixels is read at a stride.
    cfg
        ``[input]``.

    Returns
    -------
    str
        ``""``, or the units and what to set.
    """
    fix = ("the settings in depth units ([grow] min_error, the workspace's and the "
           "holdsite's tolerances) are set for about 1 mm, so every surface fits and there "
           "is nothing to pick. Read it in mm: "
           + ("input.scale to mm with input.metres_per_unit=0.001" if cfg.larger_is_closer
              else "--preset metre-depth (depth in metres), or input.scale to mm with "
              "input.metres_per_unit=0.001"))
    if cfg.metres_per_unit >= COARSE_UNIT_METRES:
        return f"is read in depth units of {cfg.metres_per_unit:g} m (input.metres_per_unit): {fix}"
    raw = np.asarray(raw)
    if cfg.larger_is_closer or raw.ndim != 2 or raw.dtype.kind != "f" or raw.size == 0:
        return ""
    seen = _strided(raw)
    readings = seen[np.isfinite(seen) & (seen > 0)]
    if readings.size < 100:
        return ""
    median = float(np.median(readings))
    if cfg.metres_per_unit > 0:  # the units are said: a camera reads no depth under 1 cm
        metres = median * cfg.scale * cfg.metres_per_unit
        if metres >= COARSE_UNIT_METRES:
            return ""
        return (f"has depth readings of median {median:.4g}, read as {metres * 1000:.3g} mm "
                f"(input.scale {cfg.scale:g}, metres_per_unit {cfg.metres_per_unit:g}): "
                "metres read as a finer unit. Read it with --preset metre-depth")
    if cfg.scale != 1.0 or not DEPTH_METRES[0] <= median <= DEPTH_METRES[1]:
        return ""
    return f"has depth readings of median {median:.4g}, metres read as mm (input.scale = 1): {fix}"


def _hint_sample(raw: np.ndarray, cfg: InputConfig, kinds: str) -> np.ndarray | None:
    """The pixels a units hint reads, or None when it has nothing to say.

    None unless ``cfg``'s units keys are at their defaults and ``raw`` is a
    2-D image of 16 bits or more of a numpy kind in ``kinds``; else
    :func:`_strided`.
    """
    if (not _at_defaults(cfg) or raw.ndim != 2 or raw.dtype.kind not in kinds
            or raw.dtype.itemsize < 2 or raw.size == 0):
        return None
    return _strided(raw)


def _strided(raw: np.ndarray) -> np.ndarray:
    """Every k-th row and column of 2-D ``raw``: :data:`DEPTH_HINT_PIXELS` or fewer."""
    step = math.ceil(math.sqrt(raw.size / DEPTH_HINT_PIXELS))
    return raw[::step, ::step]


#: ``[input]`` keys that say nothing of the units: setting them silences no hint.
_NOT_UNITS = ("fill_holes",)


def _at_defaults(cfg: InputConfig) -> bool:
    """Whether every units key of ``cfg`` has its default value (NaN equal to NaN)."""
    default = InputConfig()
    for f in dataclasses.fields(cfg):
        if f.name in _NOT_UNITS:
            continue
        a, b = getattr(cfg, f.name), getattr(default, f.name)
        if a != b and not (isinstance(a, float) and isinstance(b, float)
                           and math.isnan(a) and math.isnan(b)):
            return False
    return True


#: Raw pixel types :func:`to_heights` converts with the compiled kernel.
_COMPILED_TYPES = tuple(np.dtype(t) for t in (np.uint8, np.uint16, np.uint32, np.int8,
                                               np.int16, np.int32, np.int64, np.float32,
                                               np.float64))


def _check_heights(none_valid: bool, peak: float, cfg: InputConfig, name: str) -> None:
    """The checks of :func:`to_heights` on its result: a valid pixel, heights in range."""
    if none_valid:
        clipped = (", or at the top of an integer type's range, clipped: [input] "
                   "clipped_invalid = false keeps those") if cfg.clipped_invalid else ""
        raise InputError(f"{name}: no valid pixel (all NaN, infinite, equal to the "
                         f"no-data value {cfg.invalid}{clipped})")
    if peak > MAX_ABS_HEIGHT:
        raise InputError(f"{name}: height {peak:.3g} is outside the supported range "
                         f"(|height| <= {MAX_ABS_HEIGHT:.0e} depth units); set [input] "
                         "invalid to the sensor's no-data value or adjust [input] scale")


def require_shape_of_z(z: np.ndarray, **arrays: Any) -> None:
    """Check that every named array has the shape of the heights ``z``.

    Raises
    ------
    ValueError
        Naming the first array whose shape differs, its shape and ``z``'s.
    """
    for name, arr in arrays.items():
        if np.shape(arr) != np.shape(z):
            raise ValueError(f"`{name}` (shape {np.shape(arr)}) must have the shape of `z` "
                             f"({np.shape(z)})")


#: Highest edge code of the edge maps (none 0, step 1, roof 2, linked 3: ``edges.py``).
MAX_EDGE_CODE = 3


def value_outside(values: np.ndarray, top: int) -> int | None:
    """A value of ``values`` outside ``0..top`` (the lowest when below), or None.

    The range of a label map (``top`` = its pixel count: the stages size their
    tables by the largest label, so a label of 2^31 would ask for gigabytes)
    or of an edge map (``top`` = :data:`MAX_EDGE_CODE`).
    """
    if values.size == 0:
        return None
    low, high = int(values.min()), int(values.max())
    return low if low < 0 else high if high > top else None


def check_stage_arrays(z: Any, *, edges: Any = None, **label_maps: Any) -> None:
    """Check the arrays a stage function is given, before any work (the library's front door).

    ``z``: a 2-D array of real numbers (heights, NaN where invalid), not empty.
    ``edges`` (optional): edge codes 0..3 of ``z``'s shape. Each of
    ``label_maps`` (components, labels): integers of ``z``'s shape from 0 to
    the pixel count (:func:`value_outside`).

    Raises
    ------
    ValueError
        One line naming the argument, what it is and what is allowed.
    """
    zs = np.asarray(z)
    if zs.ndim != 2 or zs.size == 0 or zs.dtype.kind not in "biuf":
        raise ValueError(f"`z` must be a 2-D array of heights (real numbers) with a pixel at "
                         f"least; got shape {zs.shape}, dtype {zs.dtype}")
    maps = dict(label_maps) if edges is None else {"edges": edges, **label_maps}
    require_shape_of_z(zs, **maps)
    for name, arr in maps.items():
        values = np.asarray(arr)
        if values.dtype.kind not in "biu":
            raise ValueError(f"`{name}` must hold integers; got dtype {values.dtype}")
        top = MAX_EDGE_CODE if name == "edges" else values.size
        bad = value_outside(values, top)
        if bad is not None:
            what = "edge codes" if name == "edges" else "labels (at most the pixel count)"
            raise ValueError(f"`{name}` holds {bad}: {what} must lie in 0..{top}")


def labels_on_valid(z: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Heights as float64 and labels as int32, 0 wherever the height is not finite.

    Raises
    ------
    ValueError
        When the shapes of ``z`` and ``labels`` differ.
    """
    z = np.asarray(z, dtype=np.float64)
    require_shape_of_z(z, labels=labels)
    return z, np.where(np.isfinite(z), labels, 0).astype(np.int32)


def chessboard_offsets(reach: int) -> tuple[tuple[int, int], ...]:
    """Offsets (drow, dcol) within chessboard ``reach``, without (0, 0), in raster order."""
    span = range(-reach, reach + 1)
    return tuple((dr, dc) for dr in span for dc in span if dr or dc)


#: Index pairs ``(first, second)`` of two views of an (H, W) array whose elements are
#: 8-neighbouring pixels, every pair of 8-neighbours once: offsets (drow, dcol) (0, 1),
#: (1, -1), (1, 0), (1, 1) from ``first`` to ``second``. ``first`` starts at row 0 and at
#: column ``first[1].start or 0``.
HALF_NEIGHBOUR_PAIRS: tuple[tuple[tuple[slice, slice], tuple[slice, slice]], ...] = (
    ((slice(None), slice(None, -1)), (slice(None), slice(1, None))),
    ((slice(None, -1), slice(1, None)), (slice(1, None), slice(None, -1))),
    ((slice(None, -1), slice(None)), (slice(1, None), slice(None))),
    ((slice(None, -1), slice(None, -1)), (slice(1, None), slice(1, None))),
)


def consecutive_labels(labels: np.ndarray) -> np.ndarray:
    """Labels renumbered 1..k in the order of their ids, 0 kept (ids no pixel has dropped).

    Parameters
    ----------
    labels
        Non-negative int (H, W) labels.

    Returns
    -------
    numpy.ndarray
        int32 (H, W).
    """
    present = np.bincount(labels.ravel()) > 0
    present[0] = True
    if present.all():  # already consecutive: a copy, without the lookup
        return labels.astype(np.int32)
    return (np.cumsum(present, dtype=np.int32) - 1)[labels]
