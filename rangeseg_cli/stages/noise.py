"""The noise level of a range image, and thresholds that follow the sensor.

Beyond Al-Hujazi & Sood (1990), who fix their thresholds for 8-bit ERIM
images of noise sigma_o ~ 1-2 (Sec. VI). The estimate feeds the split's fit
test (:mod:`rangeseg_cli.refine.split`), recovery, the merge, the manifest
(``noise_sigma``) and, with ``[input] auto_thresholds``, the step and roof
thresholds (Sec. V-1, V-2).

Notes
-----
1. Noise (:func:`estimate_noise`). The AR of the small filter (Sec. V-1,
   eq. 3) along rows and columns is, on smooth areas, the noise filtered by
   ``G - delta`` (eq. 10), whose power gain is the "sum" of Sec. IV-B (0.48
   for the normalised 5-tap mask): ``std(AR) = sigma_o sqrt(sum)``. Edges
   and strong curvature are a minority with large AR, so the estimate uses
   the smaller half of ``|AR|`` only: the root mean square of the values
   below their median, divided by the same quantity for a standard normal.
   It includes the quantisation (about 0.29 units on sloped 8-bit faces, 0
   on constant ones). On real depth cameras whose noise is smoothed over a
   few pixels it reads low: only the noise's fine grain reaches the AR.
2. Lateral scale (:func:`lateral_scale`): depth units per pixel of lateral
   size. With camera intrinsics (depth input) the footprint of a pixel at
   the median valid depth, ``median(depth) / sqrt(fx fy)``: one value per
   image, robust to the no-reading pixels and the few far or near ones (a
   tote's floor and the items on it differ by 10-20 % in depth; a
   threshold per pixel would need the edge kernels to take a map). Else
   ``[input] units_per_pixel`` for a height map; else unknown.
3. The paper's units (:data:`PAPER_UNITS_PER_PIXEL` = 3). The paper gives
   the depth resolution of its ERIM images (8 bits, 128x128) but not the
   lateral size of a pixel. Its objects (Figs. 10-13) fill the frame
   sideways and much of the 256 levels in depth, so the depth sampling is
   about as fine as the lateral one or finer: 2-4 depth units per pixel
   (``rangeseg synth`` renders them at 2). Within that range we take 3,
   the value at which the scaled thresholds serve a real depth camera: a
   real sensor (as, likely, the ERIM laser's spot) smooths depth jumps into
   ramps over a few pixels, so its edges give less AR than the synthetic
   scenes' sharp ones. On the two SR300 frames (1.05 and 1.27 mm per
   pixel) the thresholds scaled from 3 units per pixel, 2.1 / 2.1 / 1.4 mm
   and 2.5 / 2.5 / 1.7 mm, segment best among 0.5-1.5 times them (from 2
   units per pixel, 1.5 times them, the contours stay open), and they
   reproduce the hand-tuned 2 / 2 / 1.5 mm of ``sample_data/arc``
   (docs/sensors.md, "Thresholds that follow the sensor"). Height maps
   without a scale (the 8-bit synthetic scenes) are not affected: they keep
   the paper's thresholds.
4. Thresholds (:func:`noise_scaled_config`). With ``[input]
   auto_thresholds`` each configured threshold ``T`` (in the paper's units)
   becomes ``T * s * max(1, 1 + NOISE_SLOPE * (noise / s - PAPER_NOISE))``
   with ``s`` = lateral scale / :data:`PAPER_UNITS_PER_PIXEL` (1 when
   unknown). The factor ``s`` keeps the thresholds' geometric meaning: AR
   is linear in the heights, so a scene scaled by ``c`` in all three
   directions (seen from ``c`` times as far with pixels ``c`` times as
   wide, or written in a ``c`` times finer depth unit with ``s`` saying so)
   has ``c`` times the AR, and ``c`` times the noise, and gets ``c`` times
   the thresholds: the same edges for any camera and distance. The second
   factor follows the noise, counted at the paper's scale (``noise / s``):
   the paper's thresholds serve up to its noisiest images, sigma_o = 2
   (Sec. VI, Fig. 13 d, "moderate to high"), which :func:`estimate_noise`
   reads as 2.0-2.26 on the synthetic scenes; above :data:`PAPER_NOISE`
   they rise by :data:`NOISE_SLOPE` of themselves per unit of noise, so a
   noise peak stays about as many standard deviations of AR below them as
   at sigma_o = 2 (step 4.1, roof 3.1: at sigma_o = 3 the factor is 1.5 =
   about 3.1 / 2.1, plus what the later stages, tuned on sigma_o <= 2, lose
   to the noise; the slope was chosen on seeds 0-8, docs/quality.md).
   Without a lateral scale and at an estimated noise up to
   :data:`PAPER_NOISE` (the 8-bit scenes at sigma_o 0-2) the thresholds
   are the paper's, exactly.
5. Noisier than the thresholds can follow (:func:`reduce_noise`). Above
   :data:`DENOISE_FROM` at the paper's scale (twice its noisiest images: a
   depth camera of more than 1.6 mm noise at 1 mm per pixel) raised
   thresholds alone leave one component over most of a pile: every edge is
   a noise peak or missed. The heights are then
   median-filtered (the readings alone; a median keeps depth jumps) over
   the smallest odd window of side n that brings the noise to
   :data:`PAPER_NOISE` (a median of n x n readings keeps ``sqrt(pi / 2) / n``
   of Gaussian noise: :func:`median_noise`, the noise every later step
   then reads), before anything else reads them. A background frame (the
   empty tote) is not filtered: the workspace compares the two after a
   3x3 median of its own, within a tolerance of a few noise levels.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy import ndimage, special

from ..config import Config, InputConfig
from ..kernels.backend import Backend, select_deferred
from .edges import gaussian_taps, small_filter_residuals

#: Depth units per pixel of lateral size assumed for the paper's 8-bit ERIM
#: images (Sec. VI; module notes, 3): the scale the configured thresholds are in.
PAPER_UNITS_PER_PIXEL = 3.0

#: Estimated noise, depth units at the paper's scale, up to which the paper's
#: thresholds hold: its noisiest images, sigma_o = 2 (Fig. 13 d), read 2.0-2.26
#: on the synthetic scenes (seeds 0-26), and 2.4 leaves a margin.
PAPER_NOISE = 2.4

#: Fraction of the paper's thresholds added per depth unit (at the paper's
#: scale) of estimated noise above :data:`PAPER_NOISE` (module notes, 4).
NOISE_SLOPE = 0.75

#: Estimated noise at the paper's scale above which the heights are median-filtered
#: first (module notes, 5): twice :data:`PAPER_NOISE`, so the paper's noise range and
#: the raised thresholds' (docs/quality.md, sigma 3) are left as they were.
DENOISE_FROM = 2.0 * PAPER_NOISE

#: Widest median window of :func:`reduce_noise`, pixels.
MAX_MEDIAN = 9

#: Fraction of the smallest |AR| values the noise estimate uses.
_NOISE_FRACTION = 0.5

#: Most AR samples the noise estimate sorts.
_NOISE_SAMPLES = 1 << 17

#: Step of the sample, and fraction of it, that bound the values sorted by the noise estimate.
_NOISE_SUBSAMPLE, _NOISE_CUT = 16, 0.6


def _truncated_second_moment(fraction: float) -> float:
    """``E[X^2 | |X| < q]`` for a standard normal X and q its ``fraction`` quantile of |X|."""
    t = math.sqrt(2.0) * float(special.erfinv(fraction))
    density = math.exp(-t * t / 2.0) / math.sqrt(2.0 * math.pi)
    return 1.0 - 2.0 * t * density / fraction


def _ar_gain(weights: np.ndarray) -> float:
    """Noise power gain of ``G - delta`` (the "sum" of Sec. IV-B, Table 1)."""
    centre = len(weights) // 2
    g = weights.copy()
    g[centre] -= 1.0
    return float(np.sum(g * g))


def estimate_noise(z: np.ndarray, *, backend: Backend = "auto") -> float:
    """Standard deviation of the image noise, from the AR of the small filter.

    Parameters
    ----------
    z
        float64 (H, W) heights in depth units; NaN where invalid.
    backend
        ``"numpy"``: the reference (``correlate1d`` passes and a sort);
        ``"numba"``: the compiled kernels, which compute only the AR values
        kept (:func:`~rangeseg_cli.stages.edges.small_filter_residuals`) and sort
        their smaller half (:func:`rangeseg_cli.kernels.compiled.smallest_sorted`):
        the same value bit for bit; ``"auto"``: as
        :func:`~rangeseg_cli.stages.edges.detect_edges`.

    Returns
    -------
    float
        Estimated noise sigma in depth units (quantisation included); 0 for
        an image with fewer than 10 pixels whose 5-tap masks are all valid.
        Within a few per cent of ``sqrt(sigma^2 + 1/12)`` on 8-bit data from
        sigma 1 up; below, the regular rounding pattern of a sloped face reads
        high (about 0.55 at sigma 0.25), which no threshold here depends on
        (they are floored at ``sqrt(grow.min_error)`` = 0.5).

    Notes
    -----
    AR along rows and columns with the 5-tap Gaussian of sigma 1 (Sec. V-1),
    at pixels whose whole mask is valid. Only the smaller half of ``|AR|``
    is used, so that edges and curvature (large AR) do not count: ``sigma =
    sqrt(mean(AR^2 | |AR| <= median) / (c * sum))`` with ``c`` the same
    truncated moment of a standard normal and ``sum`` the gain of Sec. IV-B.
    """
    z = np.asarray(z, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"`z` must be a 2-D height image, got shape {z.shape}")
    weights = gaussian_taps(1.0, 5)
    ar = small_filter_residuals(z, weights, _NOISE_SAMPLES, backend=backend)
    k = int(_NOISE_FRACTION * ar.size)
    if k < 10:
        return 0.0
    kernels = select_deferred(backend, "smallest_keys")
    low = _smallest_sorted(ar, k) if kernels is None else kernels.smallest_sorted(ar, k)
    moment = float(np.mean(low * low))
    return math.sqrt(moment / (_truncated_second_moment(_NOISE_FRACTION) * _ar_gain(weights)))


def _smallest_sorted(x: np.ndarray, k: int) -> np.ndarray:
    """``np.sort(x)[:k]`` for finite ``x``, sorting little more than the k smallest values.

    A value ``cut`` above about 60 % of a sparse sample of ``x`` usually has k
    or more values of ``x`` at or below it, and then they include the k
    smallest (the same values, so the same sorted array); else the whole of
    ``x`` is sorted. (``np.partition`` is slow on the many equal values of
    clean data.)
    """
    sample = np.sort(x[:: _NOISE_SUBSAMPLE])
    cut = sample[min(int(_NOISE_CUT * sample.size), sample.size - 1)]
    below = x[x <= cut]
    return np.sort(below if below.size >= k else x)[:k]


def lateral_scale(z: np.ndarray, camera: InputConfig) -> float:
    """Depth units per pixel of lateral size of heights ``z`` (module notes, 2).

    Parameters
    ----------
    z
        float64 (H, W) heights in depth units, NaN where invalid (for depth
        input, the negated depth: :func:`~rangeseg_cli.stages.rangeimage.to_heights`).
    camera
        ``[input]``: the intrinsics ``fx``, ``fy`` or ``units_per_pixel``.

    Returns
    -------
    float
        With intrinsics, ``median(depth) / sqrt(fx fy)`` over the valid pixels
        in front of the camera (0 when there is none); else ``units_per_pixel``
        (0 = unknown).
    """
    if not camera.has_intrinsics:
        return camera.units_per_pixel
    depth = -np.asarray(z, dtype=np.float64)
    depth = depth[depth > 0]  # NaN compares False: the invalid pixels drop out
    if depth.size == 0:
        return 0.0
    return float(np.median(depth)) / math.sqrt(camera.fx * camera.fy)


def paper_scale(units_per_pixel: float) -> float:
    """``s`` of the module notes, 4: ``units_per_pixel / 3``, 1 when unknown (0)."""
    return units_per_pixel / PAPER_UNITS_PER_PIXEL if units_per_pixel > 0 else 1.0


def paper_scale_noise(units_per_pixel: float, noise: float) -> float:
    """``noise`` at the paper's scale (module notes, 4): over :func:`paper_scale`.

    Parameters
    ----------
    units_per_pixel
        Lateral scale, depth units per pixel (:func:`lateral_scale`; 0 = unknown:
        the paper's scale).
    noise
        Estimated noise sigma (:func:`estimate_noise`), depth units.
    """
    return max(noise, 0.0) / paper_scale(units_per_pixel)


def threshold_factor(units_per_pixel: float, noise: float) -> float:
    """What the thresholds of the paper's units are multiplied by (module notes, 4).

    Parameters
    ----------
    units_per_pixel
        Lateral scale of the image, depth units per pixel (:func:`lateral_scale`;
        0 = unknown: the paper's scale).
    noise
        Estimated noise sigma (:func:`estimate_noise`), depth units.

    Returns
    -------
    float
        ``s * max(1, 1 + NOISE_SLOPE * (noise / s - PAPER_NOISE))`` with ``s =
        units_per_pixel / PAPER_UNITS_PER_PIXEL`` (1 when unknown): the
        paper's thresholds (Sec. V-1, V-2) at the image's scale, raised for
        a noise above the paper's at that scale.
    """
    excess = paper_scale_noise(units_per_pixel, noise) - PAPER_NOISE
    return paper_scale(units_per_pixel) * max(1.0, 1.0 + NOISE_SLOPE * excess)


def noise_scaled_config(config: Config, noise: float, units_per_pixel: float = 0.0) -> Config:
    """The step and roof thresholds set from the lateral scale and the noise (``auto_thresholds``).

    Parameters
    ----------
    config
        The configuration; returned unchanged unless ``input.auto_thresholds``.
    noise
        Estimated noise sigma (:func:`estimate_noise`), depth units.
    units_per_pixel
        Lateral scale, depth units per pixel (:func:`lateral_scale`; 0 = unknown).

    Returns
    -------
    Config
        ``step.threshold``, ``roof.threshold_a`` and ``roof.threshold_b``
        each multiplied by :func:`threshold_factor` (Sec. V-1, V-2); the
        same object when the factor is 1 (the paper's scale and noise).
    """
    if not config.input.auto_thresholds:
        return config
    factor = threshold_factor(units_per_pixel, noise)
    if factor == 1.0:
        return config
    step = dataclasses.replace(config.step, threshold=config.step.threshold * factor)
    roof = dataclasses.replace(config.roof, threshold_a=config.roof.threshold_a * factor,
                               threshold_b=config.roof.threshold_b * factor)
    return dataclasses.replace(config, step=step, roof=roof)


def sensor_config(config: Config, z: np.ndarray, noise: float) -> Config:
    """:func:`noise_scaled_config` at the lateral scale of heights ``z`` (:func:`lateral_scale`).

    Parameters
    ----------
    config
        The configuration; returned unchanged unless ``input.auto_thresholds``.
    z
        float64 (H, W) heights, NaN where invalid.
    noise
        Estimated noise sigma of ``z`` (:func:`estimate_noise`), depth units.

    Returns
    -------
    Config
        The configuration with the thresholds that the edge steps use (Sec. V-1, V-2).
    """
    if not config.input.auto_thresholds:
        return config
    return noise_scaled_config(config, noise, lateral_scale(z, config.input))


def median_size(units_per_pixel: float, noise: float) -> int:
    """Side of the median window of :func:`reduce_noise` (module notes, 5); 1 = none.

    Parameters
    ----------
    units_per_pixel
        Lateral scale, depth units per pixel (:func:`lateral_scale`; 0 = unknown).
    noise
        Estimated noise sigma (:func:`estimate_noise`), depth units.

    Returns
    -------
    int
        1 up to :data:`DENOISE_FROM` at the paper's scale; above it the
        smallest odd n >= 3 with ``sqrt(pi / 2) * noise / n`` at most
        :data:`PAPER_NOISE` there, at most :data:`MAX_MEDIAN`.
    """
    paper = paper_scale_noise(units_per_pixel, noise)
    if paper <= DENOISE_FROM:
        return 1
    n = max(3, math.ceil(math.sqrt(math.pi / 2.0) * paper / PAPER_NOISE))
    return min(n + 1 - n % 2, MAX_MEDIAN)


def median_heights(z: np.ndarray, size: int) -> np.ndarray:
    """The median of the readings in each ``size`` x ``size`` window; NaN stays NaN.

    Parameters
    ----------
    z
        (H, W) heights, NaN where invalid.
    size
        Side of the window, pixels (odd).

    Returns
    -------
    numpy.ndarray
        float64 (H, W), a new array. An invalid pixel counts as its nearest
        reading (a window at a hole holds readings alone); the image border
        repeats the edge rows and columns.
    """
    z = np.asarray(z, dtype=np.float64)
    valid = np.isfinite(z)
    filled = z
    if not valid.all():
        nearest = ndimage.distance_transform_edt(~valid, return_distances=False,
                                                 return_indices=True)
        filled = z[tuple(nearest)]
    out = ndimage.median_filter(filled, size=size, mode="nearest")
    out[~valid] = np.nan
    return out


def median_noise(noise: float, size: int) -> float:
    """Gaussian noise ``noise`` after a median of ``size`` x ``size`` readings.

    ``sqrt(pi / 2) * noise / size`` (the median's efficiency, 2 / pi, for
    ``size^2`` samples): what is left, which :func:`estimate_noise` reads a
    third of (the median's output is correlated over its window, so little
    of it reaches the small filter's AR).
    """
    return math.sqrt(math.pi / 2.0) * noise / size


def reduce_noise(z: np.ndarray, camera: InputConfig, noise: float | None = None
                 ) -> tuple[np.ndarray, float | None]:
    """Heights ``z`` median-filtered when their noise is beyond the thresholds' reach.

    Beyond Al-Hujazi & Sood (1990), whose images stop at sigma_o = 2
    (Sec. VI); module notes, 5. With ``[input] auto_thresholds`` a window of
    :func:`median_size` at the image's lateral scale and noise; else, or
    when that is 1, ``z`` itself.

    Parameters
    ----------
    z
        float64 (H, W) heights in depth units, NaN where invalid
        (:func:`~rangeseg_cli.stages.rangeimage.to_heights`).
    camera
        ``[input]``: ``auto_thresholds`` and the lateral scale's intrinsics
        or ``units_per_pixel``.
    noise
        :func:`estimate_noise` of ``z`` when the caller has it.

    Returns
    -------
    tuple
        The heights (``z``, or a new filtered array) and their noise
        (``noise`` as given, or estimated, when ``z`` is returned: None
        stays None without ``auto_thresholds``; after the filter, what it
        leaves: :func:`median_noise`).
    """
    if not camera.auto_thresholds:
        return z, noise
    noise = estimate_noise(z) if noise is None else noise
    size = median_size(lateral_scale(z, camera), noise)
    if size == 1:
        return z, noise
    return median_heights(z, size), median_noise(noise, size)
