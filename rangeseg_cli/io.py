"""Image files in and out: the only module that touches files.

Reads PNG (8/16 bit), PGM, TIFF (uint8/uint16/float32 via tifffile) and NPY
range images into 2-D numpy arrays of raw values; writes NPY, PNG, JSON and
text atomically (a temporary file in the same folder, then a rename), so a
killed run never leaves a half-written file.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError, OutputError
from .rangeimage import check_array

#: Extensions read as range images (lower case).
IMAGE_EXTENSIONS = (".png", ".pgm", ".pnm", ".tif", ".tiff", ".npy")
#: Suffixes of files this tool writes; never read back as inputs.
OUTPUT_MARKERS = (".edges.", ".labels.", ".components.", ".range.", ".step.", ".roof.",
                  ".overlay.", ".gt.", ".surfaces.", ".holdsite.", ".linked.")


def read_image(path: str | Path) -> np.ndarray:
    """Read one range image of raw values.

    Parameters
    ----------
    path
        A ``.png``, ``.pgm``/``.pnm``, ``.tif``/``.tiff`` or ``.npy`` file.

    Returns
    -------
    numpy.ndarray
        Shape (H, W): an (H, W, 1) file is squeezed. dtype as stored.

    Raises
    ------
    InputError
        When the file is missing, unreadable, not an image, has more than one
        channel, or is smaller than 16x16. The message names the file.
    """
    path = Path(path)
    try:
        raw = _read_any(path)
    except InputError:
        raise
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not an image") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied") from None
    except Exception as exc:  # noqa: BLE001 - every decoder failure becomes one line
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise InputError(f"{path}: not a readable image ({reason})") from None
    return check_array(raw, name=str(path))


def _read_any(path: Path) -> np.ndarray:
    suffix = path.suffix.lower()
    if path.stat().st_size == 0:
        raise InputError(f"{path}: empty file")
    if suffix == ".npy":
        return np.load(path, allow_pickle=False)
    if suffix in (".tif", ".tiff"):
        import tifffile

        return tifffile.imread(path)
    if suffix in (".png", ".pgm", ".pnm"):
        import imageio.v3 as iio

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return iio.imread(path)
    raise InputError(f"{path}: unsupported extension {suffix!r}; allowed: "
                     + ", ".join(IMAGE_EXTENSIONS))


def find_images(inputs: Iterable[str | Path], *, exclude: Path | None = None
                ) -> tuple[list[tuple[Path, Path]], list[Path]]:
    """Resolve files and folders (recursively) into image files.

    Parameters
    ----------
    inputs
        Files and folders named on the command line.
    exclude
        A folder never read from (the output folder, when it lies inside an input).

    Returns
    -------
    images
        ``(path, relative stem)`` pairs in a stable order; the relative stem is
        the path below the named folder without its extension (just the stem for
        a file named directly), so outputs go to ``OUT/<rel>.<artifact>``.
    skipped
        Files in the folders that are not images by extension, or are outputs.

    Raises
    ------
    InputError
        When a named input does not exist.
    """
    images: list[tuple[Path, Path]] = []
    skipped: list[Path] = []
    excluded = exclude.resolve() if exclude is not None else None
    for item in inputs:
        root = Path(item)
        if root.is_file():
            images.append((root, Path(_strip(root.name))))
        elif root.is_dir():
            for path in _walk(root, excluded):
                if _is_image_name(path.name):
                    rel = path.relative_to(root)
                    images.append((path, rel.parent / _strip(rel.name)))
                else:
                    skipped.append(path)
        else:
            raise InputError(f"{root}: no such file or folder")
    return images, skipped


def _walk(root: Path, excluded: Path | None) -> Iterator[Path]:
    for dirpath, dirnames, filenames in os.walk(root):
        here = Path(dirpath)
        dirnames[:] = sorted(d for d in dirnames
                             if not d.startswith(".")
                             and (excluded is None or (here / d).resolve() != excluded))
        for name in sorted(filenames):
            if not name.startswith("."):
                yield here / name


def _is_image_name(name: str) -> bool:
    lower = name.lower()
    return lower.endswith(IMAGE_EXTENSIONS) and not any(m in lower for m in OUTPUT_MARKERS)


def _strip(name: str) -> str:
    """File name without its image extension (``a.depth.png`` -> ``a.depth``)."""
    return name[: name.rfind(".")] if "." in name else name


# --------------------------------------------------------------------------- writing


def _file_mode() -> int:
    """Mode of a new file under the process's umask (mkstemp alone gives 0600)."""
    umask = os.umask(0o022)
    os.umask(umask)
    return 0o666 & ~umask


_FILE_MODE = _file_mode()


def _atomic_write(path: Path, write: Any) -> None:
    """Write through ``write(fileobj)`` into a temp file beside ``path``, then rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            write(fh)
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_npy(path: Path, array: np.ndarray) -> None:
    """Write an array as ``.npy`` atomically."""
    _atomic_write(path, lambda fh: np.save(fh, np.ascontiguousarray(array),
                                           allow_pickle=False))


def read_npy(path: Path) -> np.ndarray:
    """Read an ``.npy`` this tool wrote; a missing or broken file is an :class:`OutputError`."""
    try:
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise OutputError(f"{path}: missing; run the earlier stage first") from None
    except (OSError, ValueError) as exc:
        raise OutputError(f"{path}: cannot read ({exc})") from None


def write_png(path: Path, image: np.ndarray) -> None:
    """Write a uint8 grey (H, W) or colour (H, W, 3) picture as PNG atomically."""
    import imageio.v3 as iio

    # zlib level 1: about half the time of the default, and no larger on label pictures.
    data = iio.imwrite("<bytes>", np.ascontiguousarray(image), extension=".png",
                       compress_level=1)
    _atomic_write(path, lambda fh: fh.write(data))


def to_jsonable(value: Any, digits: int = 6) -> Any:
    """Convert numpy scalars/arrays, tuples and floats into plain JSON values.

    Floats are rounded to ``digits`` significant digits; NaN and infinities
    become ``None`` (JSON has no NaN).
    """
    if isinstance(value, dict):
        return {str(k): to_jsonable(v, digits) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [to_jsonable(v, digits) for v in value]
    if isinstance(value, np.ndarray):
        return [to_jsonable(v, digits) for v in value.tolist()]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool) or value is None or isinstance(value, int | str):
        return value
    if isinstance(value, float):
        if not math.isfinite(value):
            return None
        return float(f"{value:.{digits}g}")
    if isinstance(value, Path):
        return value.as_posix()
    raise TypeError(f"cannot write {type(value).__name__} to JSON")


def write_json(path: Path, data: Any, digits: int = 6) -> None:
    """Write JSON with sorted keys and rounded floats, atomically."""
    text = json.dumps(to_jsonable(data, digits), sort_keys=True, indent=2) + "\n"
    _atomic_write(path, lambda fh: fh.write(text.encode()))


def read_json(path: Path) -> Any:
    """Read a JSON file this tool wrote; failures are :class:`OutputError`."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise OutputError(f"{path}: missing; run the earlier stage first") from None
    except (OSError, ValueError) as exc:
        raise OutputError(f"{path}: cannot read ({exc})") from None


def write_text(path: Path, text: str) -> None:
    """Write text atomically."""
    _atomic_write(path, lambda fh: fh.write(text.encode()))
