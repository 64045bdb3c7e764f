"""What every image of a batch is checked against or combined with.

The ``[workspace]`` files -- a frame of the empty tote or table
(``background``, raw values read as an input image is) and a
region-of-interest mask (``roi``, non-zero = may be picked) -- are read
once per batch through :mod:`rangeseg_cli.batch.io` (:func:`read_workspace_frames`)
and handed to :func:`~rangeseg_cli.pipeline.stage_holdsite` as arrays; the
image size that camera intrinsics were made for comes from the intrinsics
file (:mod:`rangeseg_cli.cell.intrinsics`). :func:`check_frame_size` fails an
image of another size with one line naming both sizes.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..batch import io
from ..config import Config
from ..errors import ConfigError, InputError, RangesegError
from ..stages.rangeimage import check_array, to_heights


@dataclass(frozen=True)
class SharedFrames:
    """Arrays and sizes shared by the images of a batch.

    Attributes
    ----------
    background
        Raw values (H, W) of ``[workspace] background``, as read; ``None``: none.
    roi
        bool (H, W) of ``[workspace] roi``: True where a site may be; ``None``: none.
    background_name, roi_name
        How messages name them: ``[workspace] background FILE``, or
        ``"`background`"`` for an array given to the library.
    size
        (rows, cols) the camera intrinsics are for; ``None``: not known.
    size_name
        The intrinsics file, for messages.
    """

    background: np.ndarray | None = None
    roi: np.ndarray | None = None
    background_name: str = ""
    roi_name: str = ""
    size: tuple[int, int] | None = None
    size_name: str = ""

    @property
    def digest(self) -> str:
        """Short hash of the background's and the ROI's pixels; ``""`` when neither is set.

        ``--resume`` redoes the holdsites when a workspace file's content changed
        under the same name.
        """
        if self.background is None and self.roi is None:
            return ""
        h = hashlib.sha256()
        for arr in (self.background, self.roi):
            if arr is not None:
                h.update(f"{arr.dtype.str}{arr.shape}".encode())
                h.update(np.ascontiguousarray(arr).tobytes())
            h.update(b"|")
        return h.hexdigest()[:16]


def read_workspace_frames(config: Config) -> SharedFrames:
    """Read the files ``[workspace] background`` and ``roi`` name (``""``: none).

    Parameters
    ----------
    config
        The configuration; its ``[input]`` is applied once to the background
        to check it (as :func:`~rangeseg_cli.pipeline.stage_holdsite` does
        for each image).

    Returns
    -------
    SharedFrames
        The raw background and the boolean ROI (``None`` where not named).

    Raises
    ------
    ConfigError
        One line naming the key and the file: missing, unreadable, not an
        image, a colour image, a background without a valid pixel, a mask
        of floating-point values.
    """
    ws = config.workspace
    background = roi = None
    if ws.background:
        background = _read("background", ws.background)
        try:
            to_heights(background, config.input, name=ws.background)
        except InputError as exc:
            raise ConfigError(f"[workspace] background: {exc}") from None
    if ws.roi:
        try:
            roi = roi_mask(_read("roi", ws.roi), name=ws.roi)
        except InputError as exc:
            raise ConfigError(f"[workspace] roi: {exc}") from None
    return SharedFrames(background=background, roi=roi,
                        background_name=f"[workspace] background {ws.background}",
                        roi_name=f"[workspace] roi {ws.roi}")


def _read(key: str, name: str) -> np.ndarray:
    try:
        return io.read_image(name)
    except RangesegError as exc:  # InputError, StorageError: one line naming the file
        raise ConfigError(f"[workspace] {key}: {exc}") from None


def roi_mask(raw: Any, *, name: str = "`roi`") -> np.ndarray:
    """A region-of-interest mask as bool: non-zero = a site may be there.

    Parameters
    ----------
    raw
        Array-like (H, W) or (H, W, 1) of integers or booleans (an 8-bit PNG
        of 0 and 255, say).
    name
        Named in error messages.

    Raises
    ------
    InputError
        For floating-point values, a colour image or another shape, and a
        mask without a non-zero pixel (nothing could ever be picked).
    """
    arr = check_array(raw, name=name)
    if arr.dtype.kind not in "biu":
        raise InputError(f"{name}: pixel type {arr.dtype} is not a mask; allowed: integer or "
                         "boolean values (non-zero = may be picked)")
    mask = arr != 0
    if not mask.any():
        raise InputError(f"{name}: every pixel is 0, so no site could be picked anywhere; "
                         "non-zero marks where one may be")
    return mask


def check_frame_size(shape: tuple[int, ...], frames: SharedFrames, name: str) -> None:
    """Fail an image whose size is not that of the shared frames or of the intrinsics.

    Parameters
    ----------
    shape
        The image's (rows, cols).
    frames
        What the batch shares.
    name
        The image, named in the message.

    Raises
    ------
    InputError
        One line naming the image, the other file and both sizes.
    """
    rows, cols = int(shape[0]), int(shape[1])
    if frames.size is not None and frames.size != (rows, cols):
        h, w = frames.size
        raise InputError(f"{name}: the image is {cols}x{rows} pixels (width x height), the "
                         f"camera intrinsics {frames.size_name} are for {w}x{h}; intrinsics "
                         "of another resolution would put every point wrong")
    for arr, what in ((frames.background, frames.background_name),
                      (frames.roi, frames.roi_name)):
        if arr is not None and arr.shape[:2] != (rows, cols):
            raise InputError(f"{name}: size {cols}x{rows} pixels (width x height) differs "
                             f"from {what} ({arr.shape[1]}x{arr.shape[0]}); it must be a "
                             "frame of the same camera and size")
