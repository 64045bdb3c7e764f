"""Step and roof edges by the absolute residual of Gaussian smoothing.

After Al-Hujazi & Sood (1990), Sections IV and V-1, V-2. The absolute
residual (AR, eq. 3) of a 1-D Gaussian smoothing is maximal at a step or a
roof edge (Theorem, Sec. IV-A); the image is treated as 1-D along the four
directions of Fig. 8.

Notes
-----
Step 1 (Sec. V-1): a 5-tap Gaussian (sigma 1); a pixel is a step edge where,
in any direction, AR >= ``step.threshold`` and AR is a local maximum along
that direction. Both sides of a noise-free jump carry the same AR, so both
are marked (the paper's thick contour).

Step 2 (Sec. V-2): a 17-tap Gaussian (sigma 4) with an adaptive mask that
stops before the first excluded pixel (Fig. 9). Pass 2a excludes step edges
(threshold 6); pass 2b also excludes the roof edges of 2a (threshold 4). A
roof edge is AR >= threshold and the maximum of AR within
``roof.search_radius`` along the direction.

Truncation: the paper zeroes the mask from the excluded pixel on
(``"one-sided"``), which biases the smoothed value on a sloped face by the
slope times the shift of the mask's centroid. The default ``"symmetric"``
cuts both sides at the shorter reach, which leaves AR exactly 0 on any
planar ramp (docs/REPRODUCTION.md, "Where the paper is vague"). Invalid
pixels and pixels outside the image are always excluded.

Backends: the numpy functions of this module are the reference. When numba is
installed, :func:`detect_edges` runs the fused compiled kernels of
:mod:`rangeseg_cli.kernels.compiled` instead, which give exactly the same maps; set
the environment variable ``RANGESEG_PURE_NUMPY=1`` (or pass
``backend="numpy"``) to use the reference.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from ..config import Config, RoofConfig, StepConfig
from ..kernels.backend import Backend, select_deferred, select_kernels

#: The four search directions of Fig. 8, as (row step, column step).
DIRECTIONS: tuple[tuple[int, int], ...] = ((0, 1), (1, 0), (1, 1), (1, -1))

#: Codes of the edge map (docs/outputs.md).
NO_EDGE, STEP_EDGE, ROOF_EDGE, LINKED_EDGE = 0, 1, 2, 3


@dataclass(frozen=True)
class EdgeMaps:
    """Result of the edge stage.

    Attributes
    ----------
    step, roof_a, roof_b
        Boolean (H, W) maps of step edges (Sec. V-1) and roof edges of passes
        2a and 2b (Sec. V-2).
    codes
        uint8 (H, W): 0 none, 1 step edge, 2 roof edge.
    """

    step: np.ndarray
    roof_a: np.ndarray
    roof_b: np.ndarray
    codes: np.ndarray

    @property
    def roof(self) -> np.ndarray:
        """Roof edges of either pass."""
        return self.roof_a | self.roof_b


def gaussian_taps(sigma: float, taps: int) -> np.ndarray:
    """Sampled 1-D Gaussian of ``taps`` (odd) samples, normalised to sum 1.

    Parameters
    ----------
    sigma
        Standard deviation in pixels.
    taps
        Odd mask length (5 for sigma 1, 17 for sigma 4 in the paper).

    Returns
    -------
    numpy.ndarray
        float64 weights w_k for k = -taps//2 .. taps//2.
    """
    return _taps(float(sigma), int(taps)).copy()


@functools.lru_cache(maxsize=64)
def _taps(sigma: float, taps: int) -> np.ndarray:
    """:func:`gaussian_taps`, made once per (sigma, taps) and read-only."""
    half = taps // 2
    k = np.arange(-half, half + 1, dtype=np.float64)
    w = np.exp(-(k**2) / (2.0 * sigma**2))
    w = w / w.sum()
    w.flags.writeable = False
    return w


def _view(padded: np.ndarray, pad: int, dy: int, dx: int, shape: tuple[int, int]
          ) -> np.ndarray:
    """The (H, W) window of ``padded`` shifted so that ``out[p] = a[p + (dy, dx)]``."""
    h, w = shape
    return padded[pad + dy: pad + dy + h, pad + dx: pad + dx + w]


def _reach(ok_padded: np.ndarray, pad: int, dy: int, dx: int, half: int,
           shape: tuple[int, int]) -> np.ndarray:
    """Number of consecutive usable pixels from p along (dy, dx), at most ``half``."""
    run = np.ones(shape, dtype=bool)
    reach = np.zeros(shape, dtype=np.int16)
    for k in range(1, half + 1):
        run &= _view(ok_padded, pad, k * dy, k * dx, shape)
        reach += run
    return reach


def absolute_residual(z: np.ndarray, excluded: np.ndarray, weights: np.ndarray,
                      direction: tuple[int, int], *, truncation: str = "symmetric"
                      ) -> np.ndarray:
    """AR along one direction with an adaptive mask (eq. 3, Fig. 9).

    Parameters
    ----------
    z
        float64 (H, W) heights; NaN where invalid.
    excluded
        bool (H, W): pixels that stop the mask (earlier edges, invalid pixels).
    weights
        Odd-length 1-D Gaussian (:func:`gaussian_taps`).
    direction
        (row step, column step), one of :data:`DIRECTIONS`.
    truncation
        ``"symmetric"`` (cut both sides at the shorter reach) or
        ``"one-sided"`` (the paper's Fig. 9: cut each side at its own reach).

    Returns
    -------
    numpy.ndarray
        float64 (H, W) AR = |sum_k w_k z(p + k d) / sum_k w_k - z(p)| over the
        kept taps; 0 at excluded pixels.
    """
    shape = z.shape
    half = len(weights) // 2
    dy, dx = direction
    excluded = excluded | np.isnan(z)
    zp = np.pad(z, half, constant_values=np.nan)
    okp = np.pad(~excluded, half, constant_values=False)
    r_plus = _reach(okp, half, dy, dx, half, shape)
    r_minus = _reach(okp, half, -dy, -dx, half, shape)
    if truncation == "symmetric":
        r_plus = r_minus = np.minimum(r_plus, r_minus)
    zc = np.where(excluded, 0.0, z)
    num = weights[half] * zc
    den = np.full(shape, weights[half])
    for k in range(1, half + 1):
        for sign, reach in ((1, r_plus), (-1, r_minus)):
            keep = reach >= k
            num += np.where(keep, _view(zp, half, sign * k * dy, sign * k * dx, shape), 0.0
                            ) * weights[half + sign * k]
            den += keep * weights[half + sign * k]
    ar = np.abs(num / den - zc)
    ar[excluded] = 0.0
    return ar


def local_maximum(ar: np.ndarray, direction: tuple[int, int], radius: int) -> np.ndarray:
    """Where AR is >= every AR within +-``radius`` pixels along ``direction``."""
    shape = ar.shape
    arp = np.pad(ar, radius, constant_values=-np.inf)
    dy, dx = direction
    # Ties within rounding error count as maxima: both sides of a noise-free jump
    # carry the same AR in exact arithmetic (eq. 7), and both are marked.
    level = ar + 1e-9 * (1.0 + ar)
    keep = np.ones(shape, dtype=bool)
    for k in range(1, radius + 1):
        keep &= level >= _view(arp, radius, k * dy, k * dx, shape)
        keep &= level >= _view(arp, radius, -k * dy, -k * dx, shape)
    return keep


def _edges_pass(z: np.ndarray, excluded: np.ndarray, weights: np.ndarray, threshold: float,
                radius: int, truncation: str) -> np.ndarray:
    """Pixels whose AR passes ``threshold`` and is a maximum in any direction."""
    found = np.zeros(z.shape, dtype=bool)
    for direction in DIRECTIONS:
        ar = absolute_residual(z, excluded, weights, direction, truncation=truncation)
        found |= (ar >= threshold) & local_maximum(ar, direction, radius)
    return found & ~excluded


def step_edges(z: np.ndarray, cfg: StepConfig, *, truncation: str = "symmetric"
               ) -> np.ndarray:
    """Step 1: step edges with the small filter (Sec. V-1).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    cfg
        ``[step]``: sigma, taps, threshold.
    truncation
        How masks are cut at invalid pixels and the image border.

    Returns
    -------
    numpy.ndarray
        bool (H, W) step edges; never at an invalid pixel.
    """
    weights = gaussian_taps(cfg.sigma, cfg.taps)
    invalid = np.isnan(z)
    return _edges_pass(z, invalid, weights, cfg.threshold, 1, truncation)


def roof_edges(z: np.ndarray, step: np.ndarray, cfg: RoofConfig
               ) -> tuple[np.ndarray, np.ndarray]:
    """Step 2: roof edges with the large adaptive filter, passes 2a and 2b (Sec. V-2).

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    step
        bool (H, W) step edges of step 1; excluded from both passes.
    cfg
        ``[roof]``: sigma, taps, threshold_a, threshold_b, search_radius, truncation.

    Returns
    -------
    roof_a, roof_b
        bool (H, W) roof edges of pass 2a and of pass 2b (disjoint).
    """
    weights = gaussian_taps(cfg.sigma, cfg.taps)
    invalid = np.isnan(z)
    # Step 2a: roof edges, large filter, high threshold, step edges excluded (Sec. V-2a)
    excluded = invalid | step
    roof_a = _edges_pass(z, excluded, weights, cfg.threshold_a, cfg.search_radius,
                         cfg.truncation)
    # Step 2b: lower threshold, step and 2a roof edges excluded (Sec. V-2b)
    excluded = excluded | roof_a
    roof_b = _edges_pass(z, excluded, weights, cfg.threshold_b, cfg.search_radius,
                         cfg.truncation)
    return roof_a, roof_b


def detect_edges(z: np.ndarray, config: Config, *, backend: Backend = "auto") -> EdgeMaps:
    """Steps 1 and 2 of Sec. V: step edges, then roof edges in two passes.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid
        (:func:`~rangeseg_cli.stages.rangeimage.to_heights`).
    config
        The whole configuration (``[step]`` and ``[roof]`` are used).
    backend
        ``"numpy"``: the reference functions of this module; ``"numba"``: the
        fused compiled kernels of :mod:`rangeseg_cli.kernels.compiled` (identical
        maps); ``"auto"``: the kernels once compiled
        (:func:`~rangeseg_cli.kernels.backend.select_deferred`: a first run
        after installing takes the reference while they compile), when numba
        is installed and ``RANGESEG_PURE_NUMPY`` is not ``1``.

    Returns
    -------
    EdgeMaps
        Step and roof edge maps and the uint8 code map (0 none, 1 step, 2 roof).

    Raises
    ------
    ValueError
        For an unknown ``backend``.
    ImportError
        For ``backend="numba"`` without numba installed.
    """
    kernels = select_deferred(backend, "edges_pass", "roof_passes")
    if kernels is not None:
        step, roof_a, roof_b = kernels.detect_edges_numba(
            z, gaussian_taps(config.step.sigma, config.step.taps), config.step.threshold,
            gaussian_taps(config.roof.sigma, config.roof.taps), config.roof.threshold_a,
            config.roof.threshold_b, config.roof.search_radius, config.roof.truncation)
    else:
        step = step_edges(z, config.step, truncation=config.roof.truncation)
        roof_a, roof_b = roof_edges(z, step, config.roof)
    codes = np.zeros(z.shape, dtype=np.uint8)
    codes[roof_a | roof_b] = ROOF_EDGE
    codes[step] = STEP_EDGE
    return EdgeMaps(step=step, roof_a=roof_a, roof_b=roof_b, codes=codes)


def ar_2d(z: np.ndarray, *, sigma: float = 1.0, size: int = 5, backend: Backend = "auto"
          ) -> np.ndarray:
    """2-D AR, |G_sigma * z - z| with a ``size`` x ``size`` Gaussian (Sec. VII, footnote 2).

    Invalid pixels are left out of the mask (normalised convolution) and get NaN.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    sigma, size
        The Gaussian of Sec. VII: sigma 1 on a 5x5 window.
    backend
        ``"numpy"``: ``scipy.ndimage.correlate1d`` along each axis (the
        reference); ``"numba"``: :func:`rangeseg_cli.kernels.compiled.ar_2d`, the same
        sums in one compiled pass (bitwise the same); ``"auto"``: as
        :func:`detect_edges`.

    Returns
    -------
    numpy.ndarray
        float64 (H, W) AR; NaN at invalid pixels.
    """
    w = gaussian_taps(sigma, size)
    kernels = select_kernels(backend)
    if kernels is not None:
        return kernels.ar_2d(np.require(z, np.float64, ["C"]), w)
    from scipy import ndimage

    valid = ~np.isnan(z)
    zc = np.where(valid, z, 0.0)
    num = ndimage.correlate1d(ndimage.correlate1d(zc, w, axis=0, mode="constant"), w, axis=1,
                              mode="constant")
    den = ndimage.correlate1d(ndimage.correlate1d(valid.astype(np.float64), w, axis=0,
                                                  mode="constant"), w, axis=1, mode="constant")
    with np.errstate(invalid="ignore", divide="ignore"):
        ar = np.abs(num / den - z)
    ar[~valid] = np.nan
    return ar


def small_filter_residuals(z: np.ndarray, weights: np.ndarray, max_samples: int, *,
                           backend: Backend = "auto") -> np.ndarray:
    """A regular sample of |AR| of a symmetric 1-D mask along rows and columns (eq. 3).

    The values the noise estimate (:func:`rangeseg_cli.stages.noise.estimate_noise`,
    Sec. IV-B) works on: the AR of ``scipy.ndimage.correlate1d`` along axis
    0 at the pixels whose whole mask is valid (finite), in raster order, then
    along axis 1; when there are more than ``max_samples`` of them, every
    ``size // max_samples``-th value.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN (or infinite) where invalid.
    weights
        Odd-length symmetric mask (:func:`gaussian_taps`; 5 taps, sigma 1, for Sec. V-1).
    max_samples
        Values beyond which the sample is thinned.
    backend
        ``"numpy"``: two ``correlate1d`` and ``minimum_filter1d`` passes (the
        reference); ``"numba"``: :func:`rangeseg_cli.kernels.compiled.noise_residuals`,
        which computes the kept values only, summed as ``correlate1d`` sums
        them (bitwise the same); ``"auto"``: as :func:`detect_edges`.

    Returns
    -------
    numpy.ndarray
        float64 1-D |AR| values.
    """
    z = np.asarray(z, dtype=np.float64)
    kernels = select_deferred(backend, "noise_residuals")
    if kernels is not None:
        return kernels.noise_residuals(np.require(z, np.float64, ["C"]),
                                       np.ascontiguousarray(weights, dtype=np.float64),
                                       int(max_samples))
    from scipy import ndimage

    valid = np.isfinite(z)
    zc = np.where(valid, z, 0.0)
    parts = []
    for axis in (0, 1):
        smooth = ndimage.correlate1d(zc, weights, axis=axis, mode="constant")
        whole = ndimage.minimum_filter1d(valid.view(np.uint8), len(weights), axis=axis,
                                         mode="constant") > 0
        parts.append(np.abs(smooth - zc)[whole])
    ar = np.concatenate(parts)
    if ar.size > max_samples:
        ar = ar[:: ar.size // max_samples]
    return ar
