"""Camera intrinsics files: a 3x3 matrix as text, ROS CameraInfo YAML, Open3D JSON.

``rangeseg run --intrinsics FILE`` sets ``[input] intrinsics`` from one of

- a 3x3 camera matrix as text, whitespace or comma separated (fx at [0, 0],
  fy at [1, 1], cx at [0, 2], cy at [1, 2]; the last row 0 0 1, no skew);
- a ROS ``sensor_msgs/CameraInfo`` as YAML: camera_calibration's file
  (``camera_matrix: {rows: 3, cols: 3, data: [...]}``, ``image_width``,
  ``image_height``) or ``rostopic echo``'s form (``K: [...]``, or ROS 2's
  ``k:``, with ``width``, ``height``), the matrix row-major;
- an Open3D ``PinholeCameraIntrinsic`` as JSON (``width``, ``height``,
  ``intrinsic_matrix``: 9 numbers, column-major);
- a JSON or YAML mapping of ``fx``, ``fy`` and ``cx``, ``cy`` -- or
  librealsense's ``ppx``, ``ppy`` (``rs2_intrinsics``, as pyrealsense2 gives
  a stream's intrinsics) -- with ``width``, ``height`` when known; its
  distortion (``model``, ``coeffs``) is not used, as the other formats'.

The format is told by the content, not the name. Every problem is a one-line
:class:`~rangeseg_cli.errors.ConfigError` naming the file (exit code 2 on
the command line).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from typing import Any

from ..config import MAX_PIXELS, read_setting_file
from ..errors import ConfigError, RangesegError

#: What an intrinsics file may be, for messages.
ALLOWED = ("allowed: a 3x3 camera matrix as text (whitespace or comma separated), a ROS "
           "CameraInfo YAML (camera_matrix or K), an Open3D PinholeCameraIntrinsic JSON "
           "(intrinsic_matrix) or a JSON/YAML mapping of fx, fy, cx (or ppx), cy (or ppy)")
#: Largest skew (K[0, 1]) taken for none, relative to fx; and the tolerance of the 0 0 1 row.
SKEW_TOLERANCE = 1e-6
ROW_TOLERANCE = 1e-9
_SEPARATORS = re.compile(r"[\s,;\[\]]+")  # numpy prints a matrix in brackets


@dataclass(frozen=True)
class Intrinsics:
    """A pinhole camera's intrinsics, in pixels.

    Attributes
    ----------
    fx, fy
        Focal lengths, pixels (> 0).
    cx, cy
        Principal point: column and row, pixels.
    width, height
        The image size the intrinsics are for, when the file says (else ``None``).
    source
        The file they were read from, for messages.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int | None = None
    height: int | None = None
    source: str = ""

    def settings(self) -> dict[str, dict[str, list[float]]]:
        """``{"input": {"intrinsics": [fx, fy, cx, cy]}}``: overrides for ``load_config``."""
        return {"input": {"intrinsics": [self.fx, self.fy, self.cx, self.cy]}}


def read_intrinsics(path: str) -> Intrinsics:
    """Read camera intrinsics from a file of any of the module's formats.

    Parameters
    ----------
    path
        A local path or a URL (:func:`rangeseg_cli.batch.io.location`).

    Returns
    -------
    Intrinsics
        fx, fy, cx, cy and, when the file gives them, width and height.

    Raises
    ------
    ConfigError
        One line naming the file: missing or unreadable, not text, of no
        supported format, not a 3x3 camera matrix (last row 0 0 1, no skew,
        fx and fy > 0), or with values that are not numbers.
    """
    text = _read_text(path)
    try:
        return _parse(text, path)
    except _Bad as exc:
        raise ConfigError(f"{path}: {exc}") from None


class _Bad(ValueError):
    """What is wrong with the content (the caller adds the file's name)."""


def _read_text(path: str) -> str:
    from ..batch import io

    try:
        where = io.location(path)
        data = (where.read_bytes() if isinstance(where, io.URLPath)
                else read_setting_file(where, f"an intrinsics file; {ALLOWED}"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: intrinsics file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: is a folder, not an intrinsics file") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read the intrinsics file ({exc.strerror or exc})"
                          ) from None
    except RangesegError as exc:  # a URL that cannot be used or reached
        raise ConfigError(str(exc)) from None
    try:
        return data.removeprefix(b"\xef\xbb\xbf").decode("utf-8")
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text file; {ALLOWED}") from None


def _parse(text: str, source: str) -> Intrinsics:
    """The intrinsics in ``text``: a table of numbers, else a JSON or YAML mapping."""
    if not text.strip():
        raise _Bad(f"empty file; {ALLOWED}")
    nested = _json_rows(text)
    if nested is not None:  # [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]: a matrix as JSON
        return _from_matrix_rows(nested, source)
    rows = _number_rows(text)
    if rows == []:
        raise _Bad(f"holds only comments; {ALLOWED}")
    if rows is not None:
        return _from_matrix_rows(rows, source)
    mapping = _mapping(text)
    if mapping is None:
        key = re.search(r"^\s*([A-Za-z_]\w*)\s*:", text, re.MULTILINE)
        if key:  # a mapping that YAML cannot read: not a table with a typo
            raise _Bad(f"has keys ({key.group(1)}:) but reads as no YAML or JSON mapping "
                       f"(check its brackets and indentation); {ALLOWED}")
        _first_non_number(text)  # a table with a typo: name it
        raise _Bad(f"not a camera intrinsics file; {ALLOWED}")
    return _from_mapping(mapping, source)


def _json_rows(text: str) -> list[list[float]] | None:
    """``text`` as a JSON list of rows of numbers (booleans are none), else None."""
    try:
        data = json.loads(text)
    except ValueError:  # also an integer of more than 4300 digits
        return None
    if (isinstance(data, list) and data and all(isinstance(r, list) and r for r in data)
            and all(isinstance(v, int | float) and not isinstance(v, bool)
                    for r in data for v in r)):
        try:
            return [[float(v) for v in r] for r in data]
        except OverflowError:  # an integer beyond float64: no camera matrix
            raise _Bad("a value of the matrix is too large to be a number of a camera "
                       "matrix") from None
    return None


def _lines(text: str) -> list[str]:
    """Non-empty lines without ``#`` comments."""
    return [s for s in (line.split("#", 1)[0].strip() for line in text.splitlines()) if s]


def _number_rows(text: str) -> list[list[float]] | None:
    """Each line's numbers, or None when a line holds anything else."""
    rows = []
    for line in _lines(text):
        try:
            row = [float(t) for t in _SEPARATORS.split(line.strip(" ,;[]")) if t]
        except ValueError:
            return None
        if row:  # not a line of brackets alone
            rows.append(row)
    return rows


def _first_non_number(text: str) -> None:
    """Raise naming the first word that is not a number, in a text that looks like a table."""
    lines = _lines(text)
    tokens = [[t for t in _SEPARATORS.split(line.strip(" ,;[]")) if t] for line in lines]
    numeric = sum(_is_number(t) for row in tokens for t in row)
    if numeric * 2 < sum(map(len, tokens)):  # mostly words: not a table
        return
    for i, row in enumerate(tokens, 1):
        for token in row:
            if not _is_number(token):
                raise _Bad(f"{token!r} (row {i} of the matrix) is not a number; expected a "
                           "3x3 camera matrix of numbers")


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


def _from_matrix_rows(rows: list[list[float]], source: str) -> Intrinsics:
    shape = f"{len(rows)}x{len(rows[0])}" if len({len(r) for r in rows}) == 1 else (
        f"{len(rows)} rows of " + ", ".join(str(len(r)) for r in rows) + " numbers")
    if len(rows) != 3 or any(len(r) != 3 for r in rows):
        raise _Bad(f"a {shape} matrix; expected a 3x3 camera matrix (fx 0 cx / 0 fy cy / 0 0 1)")
    return _from_matrix(rows, source)


def _mapping(text: str) -> dict[str, Any] | None:
    """``text`` as a JSON object, else a YAML mapping (the first document), else None."""
    try:
        data = json.loads(text)
    except ValueError:
        data = _yaml(text)
    return data if isinstance(data, dict) else None


def _yaml(text: str) -> Any:
    import yaml

    try:  # `rostopic echo` ends each message with `---`: take the first document
        return next((d for d in yaml.safe_load_all(text) if d is not None), None)
    except yaml.YAMLError:
        return None


def _from_mapping(data: dict[str, Any], source: str) -> Intrinsics:
    """Open3D's ``intrinsic_matrix`` (column-major) or ROS's ``camera_matrix``/``K``/``k``."""
    if "intrinsic_matrix" in data:
        m = _numbers(data["intrinsic_matrix"], "intrinsic_matrix", 9)
        rows = [[m[0], m[3], m[6]], [m[1], m[4], m[7]], [m[2], m[5], m[8]]]
        return _from_matrix(rows, source, _size(data, "width", "height"))
    if "camera_matrix" in data:
        values = _ros_matrix(data["camera_matrix"])
        size = _size(data, "image_width", "image_height")
    elif "K" in data or "k" in data:
        key = "K" if "K" in data else "k"
        values, size = _numbers(data[key], key, 9), _size(data, "width", "height")
    elif "fx" in data or "fy" in data:
        values, size = _focal_matrix(data), _size(data, "width", "height")
    else:
        raise _Bad("holds no camera matrix (camera_matrix, K or k of a ROS CameraInfo, "
                   f"intrinsic_matrix of Open3D, or fx and fy); {ALLOWED}")
    return _from_matrix([values[0:3], values[3:6], values[6:9]], source, size)


def _focal_matrix(data: dict[str, Any]) -> list[float]:
    """The row-major matrix of ``fx``, ``fy``, ``cx``/``ppx``, ``cy``/``ppy`` (librealsense)."""
    names = (("fx",), ("fy",), ("cx", "ppx"), ("cy", "ppy"))
    missing = [" or ".join(pair) for pair in names if not any(k in data for k in pair)]
    if missing:
        raise _Bad(f"has fx or fy but no {', '.join(missing)} (fx, fy: focal lengths; cx, "
                   "cy: the principal point; pixels)")
    keys = [next(k for k in pair if k in data) for pair in names]
    fx, fy, cx, cy = (_numbers([data[k]], k, 1)[0] for k in keys)
    return [fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0]


def _ros_matrix(entry: Any) -> list[float]:
    """camera_calibration's ``camera_matrix: {rows: 3, cols: 3, data: [9 numbers]}``."""
    if not isinstance(entry, dict) or "data" not in entry:
        raise _Bad("camera_matrix must be a mapping with rows: 3, cols: 3 and data: "
                   "[9 numbers]")
    rows, cols = entry.get("rows", 3), entry.get("cols", 3)
    if (rows, cols) != (3, 3):
        raise _Bad(f"camera_matrix is {rows}x{cols}; expected rows: 3, cols: 3")
    return _numbers(entry["data"], "camera_matrix data", 9)


def _numbers(values: Any, key: str, count: int) -> list[float]:
    """A list of ``count`` finite numbers (not booleans)."""
    if not isinstance(values, list) or len(values) != count:
        got = f"{len(values)} values" if isinstance(values, list) else repr(values)[:40]
        raise _Bad(f"{key} must be a list of {count} numbers, got {got}")
    for v in values:  # YAML 1.1 reads 1e-3 (no dot) as a string: taken as the number
        if isinstance(v, bool) or not (isinstance(v, int | float) or (
                isinstance(v, str) and _is_number(v))):
            raise _Bad(f"{key} holds {v!r}, not a number")
    return [float(v) for v in values]


def _size(data: dict[str, Any], width_key: str, height_key: str) -> tuple[int, int] | None:
    """(width, height) when both are given and > 0 (ROS and Open3D write 0 or -1 for unknown)."""
    width, height = data.get(width_key), data.get(height_key)
    for key, v in ((width_key, width), (height_key, height)):
        if v is not None and (isinstance(v, bool) or not isinstance(v, int)):
            raise _Bad(f"{key} = {v!r}: expected a whole number of pixels")
    if width is None or height is None or width <= 0 or height <= 0:
        return None
    return int(width), int(height)


def _from_matrix(k: list[list[float]], source: str, size: tuple[int, int] | None = None
                 ) -> Intrinsics:
    """Check a 3x3 camera matrix (row-major) and take fx, fy, cx, cy from it."""
    flat = [v for row in k for v in row]
    if not all(math.isfinite(v) for v in flat):
        raise _Bad("the camera matrix holds a value that is not a finite number")
    fx, fy, cx, cy = k[0][0], k[1][1], k[0][2], k[1][2]
    if fx <= 0 or fy <= 0:
        raise _Bad(f"fx = {fx:g}, fy = {fy:g}: focal lengths must be > 0 (an uncalibrated "
                   "camera writes 0)")
    if max(fx, fy, abs(cx), abs(cy)) > MAX_PIXELS:
        raise _Bad(f"fx = {fx:g}, fy = {fy:g}, cx = {cx:g}, cy = {cy:g}: expected at most "
                   f"{MAX_PIXELS:g} pixels")
    if any(abs(a - b) > ROW_TOLERANCE for a, b in zip(k[2], (0.0, 0.0, 1.0), strict=True)) or (
            abs(k[1][0]) > ROW_TOLERANCE):
        raise _Bad(f"last row {_row(k[2])} (and [1, 0] = {k[1][0]:g}): expected 0 0 1 and 0, "
                   "a camera matrix fx 0 cx / 0 fy cy / 0 0 1")
    if abs(k[0][1]) > SKEW_TOLERANCE * fx:
        raise _Bad(f"skew {k[0][1]:g} (the matrix's [0, 1]): expected 0; rangeseg's camera "
                   "has square pixel axes")
    width, height = size if size is not None else (None, None)
    return Intrinsics(fx, fy, cx, cy, width=width, height=height, source=source)


def _row(values: list[float]) -> str:
    return " ".join(f"{v:g}" for v in values)
