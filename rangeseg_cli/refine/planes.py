"""Gaussian-weighted local plane fits: a plane at every pixel from a mask's pixels.

Beyond Al-Hujazi & Sood (1990). The split of a failing component (Sec. VIII,
:mod:`rangeseg_cli.refine.split`) takes its surface normals from these fits, and
the recovery of planes (:mod:`rangeseg_cli.refine.recover`) its plane hypotheses.

Notes
-----
At each pixel, the plane fitted by least squares to the ``mask`` pixels
around it, weighted by a Gaussian of ``sigma`` pixels (cut at
:data:`_TRUNCATE` sigmas, :func:`blur_radius` pixels): weighted moments by
Gaussian blurs of the masked products (scipy's, the reference) or, with the
compiled kernels (:func:`~rangeseg_cli.kernels.backend.select_kernels`), by
:func:`rangeseg_cli.kernels.compiled.plane_fit`, bit for bit the same, on row bands
at once when there are threads.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from types import ModuleType

import numpy as np
from scipy import ndimage

from ..kernels.backend import Backend, select_kernels
from ..kernels.parallel import map_bands, row_bands
from .regions import c_array

#: The Gaussian weights of the local plane fits end at this many sigmas.
_TRUNCATE = 3.0


def local_planes(z: np.ndarray, mask: np.ndarray, sigma: float, *,
                 origin: tuple[float, float] | None = None, backend: Backend = "auto"
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Gaussian-weighted local plane fits that use only ``mask`` pixels, at every pixel.

    Parameters
    ----------
    z
        float64 (H, W) heights.
    mask
        bool (H, W) pixels to use.
    sigma
        Gaussian sigma of the weights, pixels (truncated at 3 sigma:
        :func:`blur_radius` pixels).
    origin
        (row, col) coordinates of pixel [0, 0] in the frame of the fits;
        default ``(-H / 2, -W / 2)`` (the array's centre). A crop of a larger
        array given that array's frame gives bit for bit the same values as
        the whole array wherever no ``mask`` pixel outside the crop lies
        within :func:`blur_radius` of the pixel.
    backend
        ``"numpy"``: scipy's blurs (the reference); ``"numba"``: the compiled
        :func:`rangeseg_cli.kernels.compiled.plane_fit` (the same values bit for bit);
        ``"auto"``: numba when available (:func:`~rangeseg_cli.kernels.backend.select_kernels`).

    Returns
    -------
    height, gx, gy
        float64 (H, W): the fitted plane's height at the pixel and its slopes
        dz/dcol and dz/drow; NaN where fewer than a few ``mask`` pixels lie
        within reach or they lie on a line (the fit is degenerate).
    """
    fit = _PlaneFit.of(z, mask, sigma, origin, backend)
    return fit.mz + fit.gx * (fit.u - fit.mu) + fit.gy * (fit.v - fit.mv), fit.gx, fit.gy


@dataclass(frozen=True)
class _PlaneFit:
    """The local plane fits of :func:`local_planes`: slopes and weighted centres.

    ``u`` (1, W) and ``v`` (H, 1) are the column and row coordinates; ``mu``,
    ``mv``, ``mz`` the weighted means of u, v and z; ``gx``, ``gy`` the slopes
    (NaN where the fit is degenerate). All (H, W) but the coordinates.
    """

    u: np.ndarray
    v: np.ndarray
    mu: np.ndarray
    mv: np.ndarray
    mz: np.ndarray
    gx: np.ndarray
    gy: np.ndarray

    @classmethod
    def of(cls, z: np.ndarray, mask: np.ndarray, sigma: float,
           origin: tuple[float, float] | None, backend: Backend = "auto") -> _PlaneFit:
        """Fit the planes (weighted moments by Gaussian blurs of the masked products).

        With the compiled kernels (``backend``, as
        :func:`~rangeseg_cli.kernels.backend.select_kernels` selects them) the same
        values bit for bit from :func:`rangeseg_cli.kernels.compiled.plane_fit`.
        """
        h, w = z.shape
        v0, u0 = (-h / 2.0, -w / 2.0) if origin is None else origin
        u = (np.arange(w, dtype=np.float64) + u0)[None, :]  # exact: integers and halves
        v = (np.arange(h, dtype=np.float64) + v0)[:, None]
        kernels = select_kernels(backend)
        if kernels is not None:
            mu, mv, mz, gx, gy = _compiled_plane_fit(
                kernels, c_array(z, np.float64), c_array(mask, np.bool_),
                writeable_weights(sigma), float(u0), float(v0), min_det(sigma))
            return cls(u=u, v=v, mu=mu, mv=mv, mz=mz, gx=gx, gy=gy)
        m = mask.astype(np.float64)
        zc = np.where(mask, z, 0.0)
        s = _blur(m, sigma)
        ok = s > 1e-3
        s = np.where(ok, s, 1.0)

        def mean(a: np.ndarray) -> np.ndarray:
            out = _blur(a, sigma)
            out /= s
            return out

        mu_w, mv_w = m * u, m * v
        mu, mv, mz = mean(mu_w), mean(mv_w), mean(zc)
        cuu = mean(mu_w * u)
        cuu -= mu * mu
        cuv = mean(mu_w * v)
        cuv -= mu * mv
        cvv = mean(mv_w * v)
        cvv -= mv * mv
        cuz = mean(zc * u)
        cuz -= mu * mz
        cvz = mean(zc * v)
        cvz -= mv * mz
        det = cuu * cvv - cuv * cuv
        ok &= det > min_det(sigma)
        safe = np.where(ok, det, 1.0)
        gx = np.where(ok, (cvv * cuz - cuv * cvz) / safe, np.nan)
        gy = np.where(ok, (cuu * cvz - cuv * cuz) / safe, np.nan)
        return cls(u=u, v=v, mu=mu, mv=mv, mz=mz, gx=gx, gy=gy)


def _compiled_plane_fit(kernels: ModuleType, z: np.ndarray, mask: np.ndarray, w: np.ndarray,
                        u0: float, v0: float, min_det: float) -> tuple[np.ndarray, ...]:
    """:func:`rangeseg_cli.kernels.compiled.plane_fit`, on row bands at once when there are threads.

    A fit reads the rows within the blur's reach only, so a band with that
    many rows more either side (and its own row origin, ``v0`` + its first
    row: integers and halves, exact) gives its rows bit for bit
    (:func:`~rangeseg_cli.kernels.parallel.map_bands`).
    """
    height, width = z.shape
    reach = w.shape[0] // 2
    if len(row_bands(height, width, reach)) == 1:
        return tuple(kernels.plane_fit(z, mask, w, u0, v0, min_det))
    out = tuple(np.empty((height, width)) for _ in range(5))

    def band(first: int, stop: int, lo: int, hi: int) -> None:
        parts = kernels.plane_fit(z[lo:hi], mask[lo:hi], w, u0, v0 + lo, min_det)
        for whole, part in zip(out, parts, strict=True):
            whole[first:stop] = part[first - lo: stop - lo]

    map_bands(band, height, width, reach)
    return out


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur of the local plane fits: zero outside, cut at :data:`_TRUNCATE` sigmas."""
    return ndimage.gaussian_filter(a, sigma, mode="constant", truncate=_TRUNCATE)


@functools.lru_cache(maxsize=16)
def blur_weights(sigma: float) -> np.ndarray:
    """The taps of :func:`_blur` (its response to a unit impulse: scipy's weights exactly)."""
    impulse = np.zeros(2 * blur_radius(sigma) + 1)
    impulse[impulse.size // 2] = 1.0
    weights = _blur(impulse, sigma)
    weights.setflags(write=False)
    return weights


@functools.lru_cache(maxsize=16)
def writeable_weights(sigma: float) -> np.ndarray:
    """:func:`blur_weights` as a writeable array, for the kernel typed for one (never written).

    Made once per sigma: a copy per call (``np.require(..., ["W"])``) took a
    tenth of the consensus planes' time.
    """
    return np.array(blur_weights(sigma))


def min_det(sigma: float) -> float:
    """Smallest determinant of a local plane fit's covariance (blur ``sigma``): ``1e-3 sigma^4``.

    Below it the mask's pixels near a point lie nearly on a line and the
    fit is degenerate (its slopes NaN).
    """
    return 1e-3 * sigma**4


def blur_radius(sigma: float) -> int:
    """Reach in pixels of the Gaussian weights of :func:`local_planes` (as scipy truncates)."""
    return int(_TRUNCATE * sigma + 0.5)


def local_gradients(z: np.ndarray, mask: np.ndarray, sigma: float, *,
                    backend: Backend = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Slopes of Gaussian-weighted local plane fits that use only ``mask`` pixels.

    Parameters
    ----------
    z
        float64 (H, W) heights.
    mask
        bool (H, W) pixels to use (one component).
    sigma
        Gaussian sigma of the weights, pixels.
    backend
        As for :func:`local_planes`.

    Returns
    -------
    gx, gy
        float64 (H, W) slopes dz/dcol and dz/drow; 0 outside ``mask`` and
        where the local fit is degenerate (the mask's pixels on a line).
    """
    fit = _PlaneFit.of(z, mask, sigma, None, backend)
    gx, gy = fit.gx, fit.gy
    keep = mask & np.isfinite(gx)
    return np.where(keep, gx, 0.0), np.where(keep, gy, 0.0)
