"""Image files in and out: the only module that touches files.

Reads PNG (8/16 bit), PGM (8/16 bit, as stored), TIFF (uint8/uint16/float32
via tifffile) and NPY range images into 2-D numpy arrays of raw values, in the
file's own pixel type; writes NPY, PNG, JSON and text atomically (a
temporary file in the same folder, then a rename), so a killed run never
leaves a half-written file.

Files and folders are local paths or, where fsspec and the filesystem's
package are installed, URLs (``s3://bucket/frames``, ``memory://...``): see
:func:`location`. A ``file://`` URL is a local path. On object stores
(:data:`OBJECT_STORES`) a file is written by one put of its whole bytes, which
is atomic; on other fsspec filesystems into a temporary file beside it, then
moved over it.
"""

from __future__ import annotations

import errno
import fnmatch
import json
import logging
import math
import os
import re
import secrets
import stat
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from io import BytesIO
from pathlib import Path, PurePath, PurePosixPath
from typing import Any, BinaryIO, TypeAlias
from urllib.parse import unquote, unquote_to_bytes, urlsplit

import numpy as np

from ..config import SPECIAL_FILES
from ..errors import InputError, OutputError, RangesegError, StorageError
from ..stages.rangeimage import check_array

#: Extensions read as range images (lower case).
IMAGE_EXTENSIONS = (".png", ".pgm", ".pnm", ".tif", ".tiff", ".npy")
#: Marks ground truth beside a frame (``<stem>.gt.npy``, ``.gt.background.png``): never read.
GROUND_TRUTH_MARKER = ".gt."
#: Parts of the names of files this tool writes (``find_images`` without its ``written``).
OUTPUT_MARKERS = (".edges.", ".labels.", ".components.", ".range.", ".step.", ".roof.",
                  ".overlay.", ".gt.", ".surfaces.", ".holdsite.", ".linked.")
#: fsspec protocols of object stores: writing a whole object at once is atomic.
OBJECT_STORES = frozenset({"s3", "s3a", "gs", "gcs", "az", "abfs", "abfss", "adl", "memory"})
#: What to install for a protocol whose filesystem package is missing.
INSTALL_HINTS = {"s3": "pip install 'rangeseg[s3]'", "s3a": "pip install 'rangeseg[s3]'",
                 "gs": "pip install gcsfs", "gcs": "pip install gcsfs",
                 "az": "pip install adlfs", "abfs": "pip install adlfs",
                 "abfss": "pip install adlfs", "adl": "pip install adlfs"}
_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


# --------------------------------------------------------------------------- locations


def _reason(exc: BaseException) -> str:
    """First line of an exception's message, or its type when it has none."""
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def is_url(name: str | PurePath) -> bool:
    """Whether ``name`` is a URL (``PROTOCOL://...``) rather than a local path."""
    return isinstance(name, str) and _URL.match(name) is not None


def _open_store(url: str) -> tuple[Any, str]:
    """The fsspec filesystem of ``url`` and the path on it; one-line errors."""
    protocol = url.split("://", 1)[0].lower()
    hint = INSTALL_HINTS.get(protocol, f"install fsspec and the package for {protocol}://")
    try:
        from fsspec.core import url_to_fs
    except ImportError:
        raise StorageError(f"{url}: URLs need fsspec, which is not installed: {hint}") from None
    try:
        return url_to_fs(url)
    except ImportError:
        raise StorageError(f"{url}: the package for {protocol}:// URLs is not installed: "
                           f"{hint}") from None
    except ValueError as exc:
        if "Protocol not known" not in str(exc):
            raise StorageError(f"{url}: not a usable URL ({_reason(exc)})") from None
        raise StorageError(f"{url}: unknown protocol {protocol}://; expected a local path or "
                           "a URL fsspec knows, e.g. s3://bucket/folder") from None
    except Exception as exc:  # noqa: BLE001 - e.g. bad options in FSSPEC_* variables
        raise StorageError(f"{url}: cannot open ({_reason(exc)})") from None


class URLPath:
    """A file or folder named by an fsspec URL, with the few operations of a ``Path`` we use.

    Parameters
    ----------
    url
        ``PROTOCOL://...``, e.g. ``s3://bucket/frames``; a trailing ``/`` is dropped.
        The filesystem takes its options (endpoint, credentials) from fsspec's
        configuration, e.g. the variable ``FSSPEC_S3_ENDPOINT_URL``; a URLPath
        sent to another process (a Dask worker) opens it there with that
        process's configuration.

    Raises
    ------
    StorageError
        When fsspec or the protocol's package is not installed, or the protocol
        is unknown.
    """

    def __init__(self, url: str, _store: tuple[Any, str] | None = None):
        head, rest = url.split("://", 1)
        self.url = f"{head}://{rest.rstrip('/')}"
        self.protocol = head.lower()
        self.fs, self.path = _open_store(self.url) if _store is None else _store

    def __str__(self) -> str:
        return self.url

    def __repr__(self) -> str:
        return f"URLPath({self.url!r})"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, URLPath) and other.url == self.url

    def __hash__(self) -> int:
        return hash(self.url)

    def __reduce__(self) -> tuple[type[URLPath], tuple[str]]:
        return URLPath, (self.url,)  # the receiver opens the store with its own settings

    def __truediv__(self, name: str) -> URLPath:
        return URLPath(f"{self.url}/{name}", (self.fs, f"{self.path}/{name}"))

    @property
    def name(self) -> str:
        """Last part of the URL."""
        return self.url.rsplit("/", 1)[-1]

    @property
    def suffix(self) -> str:
        """Extension of :attr:`name`, with its dot (``""`` if none)."""
        return PurePosixPath(self.name).suffix

    @property
    def parent(self) -> URLPath:
        """The folder holding this one."""
        return URLPath(self.url.rsplit("/", 1)[0], (self.fs, self.path.rsplit("/", 1)[0]))

    def _call(self, verb: str, method: str, *args: Any, writing: bool = False,
              **kwargs: Any) -> Any:
        """Call the filesystem; its failures become one-line :class:`StorageError`.

        A missing file stays a :class:`FileNotFoundError`, unless ``writing``.
        """
        try:
            return getattr(self.fs, method)(*args, **kwargs)
        except FileNotFoundError:
            if not writing:
                raise
            raise StorageError(f"{self.url}: cannot {verb} (its bucket or folder is "
                               "missing)") from None
        except Exception as exc:  # noqa: BLE001 - every backend's errors become one line
            raise StorageError(f"{self.url}: cannot {verb} ({_reason(exc)})") from None

    def exists(self) -> bool:
        """Whether a file or folder is there (asking the store, not a cached listing)."""
        self.fs.invalidate_cache(self.path)
        return bool(self._call("reach it", "exists", self.path))

    def is_file(self) -> bool:
        """Whether a file is there."""
        self.fs.invalidate_cache(self.path)
        return bool(self._call("reach it", "isfile", self.path))

    def is_dir(self) -> bool:
        """Whether a folder (on object stores: a prefix of some object) is there."""
        self.fs.invalidate_cache(self.path)
        return bool(self._call("reach it", "isdir", self.path))

    def mkdir(self, parents: bool = True, exist_ok: bool = True) -> None:
        """Create the folder; object stores have none, and need none."""
        if self.protocol not in OBJECT_STORES:
            self._call("create it", "makedirs", self.path, exist_ok=True, writing=True)

    def read_bytes(self) -> bytes:
        """The file's bytes; :class:`FileNotFoundError` when it is missing."""
        return bytes(self._call("read it", "cat_file", self.path))

    def write_bytes(self, data: bytes) -> None:
        """Replace the file by ``data`` atomically (one put, or a temporary file moved)."""
        if self.protocol in OBJECT_STORES:
            self._call("write it", "pipe_file", self.path, data, writing=True)
            return
        self.parent.mkdir()
        tmp = self.parent / f".{self.name}.{secrets.token_hex(4)}.tmp"
        try:
            tmp._call("write it", "pipe_file", tmp.path, data, writing=True)
            self._call("write it", "mv", tmp.path, self.path, writing=True)
        except BaseException:
            tmp.unlink()
            raise

    def unlink(self, missing_ok: bool = True) -> None:
        """Delete the file (a missing one is no error)."""
        try:
            self._call("delete it", "rm_file", self.path)
        except FileNotFoundError:
            pass

    def files(self) -> list[str]:
        """Every file below this folder, relative to it; none when it does not exist."""
        self.fs.invalidate_cache()
        try:
            found = self._call("list it", "find", self.path)
        except FileNotFoundError:
            return []
        prefix = self.path.rstrip("/") + "/"
        return [p[len(prefix):] for p in found
                if p.startswith(prefix) and not p.endswith("/")]


#: A local path or a URL.
Location: TypeAlias = Path | URLPath


#: URL protocols fsspec reads but cannot write: never an output folder.
READ_ONLY_PROTOCOLS = ("http", "https", "github", "zip", "tar")


def check_output_protocol(where: str | Location) -> None:
    """Refuse an output folder on a URL protocol that can be read but not written.

    Raises
    ------
    StorageError
        Naming the URL (e.g. ``https://``: the first temporary file could not
        be deleted, ``NotImplementedError``, after the manifest was tried).
    """
    text = str(where)
    protocol = text.split("://", 1)[0].lower() if _URL.match(text) else ""
    if protocol in READ_ONLY_PROTOCOLS:
        raise StorageError(f"{text}: {protocol}:// URLs can be read, not written; OUT must "
                           "be a local folder or a store such as s3://bucket/folder")


def is_empty_path(text: str) -> bool:
    """Whether a path as typed names nothing: ``""``, blanks, or ``file://`` without a path."""
    if text.lower().startswith("file://"):
        parts = urlsplit(text)
        return parts.netloc in ("", "localhost") and not unquote(parts.path).strip()
    return not text.strip()


def location(name: str | PurePath | URLPath) -> Location:
    """The local path or :class:`URLPath` that ``name`` (as typed by a user) names.

    Raises
    ------
    StorageError
        For a URL whose protocol is unknown or whose package is missing, or a
        ``file://`` URL naming another host.
    """
    if isinstance(name, URLPath | Path):
        return name
    text = str(name)
    if not is_url(text):
        return Path(text)
    if text.lower().startswith("file://"):
        parts = urlsplit(text)
        if parts.netloc not in ("", "localhost"):
            raise StorageError(f"{text}: a file:// URL names a file of this machine, "
                               f"file:///path; got host {parts.netloc!r}")
        if is_empty_path(text):  # Path("") is the current folder
            raise StorageError(f"{text}: a file:// URL without a path (an unset shell "
                               "variable?); for the current folder write .")
        return Path(unquote(parts.path))
    return URLPath(text)


def absolute(where: Location) -> Location:
    """``where`` with a local path made absolute (URLs are absolute already)."""
    return Path(os.path.abspath(where)) if isinstance(where, Path) else where


def absolute_name(name: str) -> str:
    """A file name or URL as given, with a local path made absolute."""
    return name if is_url(name) else os.path.abspath(name)


def read_image(path: str | Path | URLPath) -> np.ndarray:
    """Read one range image of raw values.

    Parameters
    ----------
    path
        A ``.png``, ``.pgm``/``.pnm``, ``.tif``/``.tiff`` or ``.npy`` file: a
        local path or a URL (:func:`location`).

    Returns
    -------
    numpy.ndarray
        Shape (H, W): an (H, W, 1) file is squeezed. dtype as stored: a
        16-bit PNG or PGM is uint16 (not the int32 Pillow widens it to), so
        that its clipped value is 65535.

    Raises
    ------
    InputError
        When the file is missing, unreadable, not an image, has more than one
        channel, or is smaller than 16x16. The message names the file.
    StorageError
        When a URL's store cannot be used or reached.
    """
    path = location(path)
    try:
        raw = _read_any(path)
    except RangesegError:
        raise
    except FileNotFoundError:
        raise InputError(f"{path}: file not found") from None
    except IsADirectoryError:
        raise InputError(f"{path}: is a folder, not an image") from None
    except PermissionError:
        raise InputError(f"{path}: permission denied") from None
    except Exception as exc:  # noqa: BLE001 - every decoder failure becomes one line
        raise _unreadable(path, exc) from None
    return check_array(raw, name=str(path))


def _unreadable(path: Location, exc: Exception) -> InputError:
    """The one-line error of a file that could not be decoded (``exc``)."""
    if isinstance(exc, OSError) and exc.errno == errno.ELOOP:
        return InputError(f"{path}: {LINK_LOOP}, not an image; remove the link or point it "
                          "at a file")
    reason = _reason(exc)
    if reason.startswith("Could not find a backend"):  # imageio names a file object
        reason = "its content is no image format rangeseg reads: PNG, PGM/PNM, TIFF, NPY"
    return InputError(f"{path}: not a readable image ({reason})")


#: What a link that leads back to itself is called in messages.
LINK_LOOP = "a symbolic link loop (the link leads back to itself)"


def input_stamp(path: str | Path | URLPath) -> str | None:
    """A stamp of the version of an input file: its size and modification time.

    ``"<size>:<mtime in ns>"`` for a local file (the quick check of make and
    rsync); on a store, its size and ETag (or modification time). ``--resume``
    redoes an image whose input's stamp is not the one its results were made
    from: a frame replaced under the same name is not kept as done. Not a
    content hash, which would read every input again to plan a run (on a
    store, download it): a file put back with its old size and modification
    time (``cp -p`` of an older copy) is taken for unchanged.

    Returns
    -------
    str or None
        ``None`` when the file cannot be reached (reading it then fails with
        its own one-line error).
    """
    where = location(path)
    try:
        if isinstance(where, URLPath):
            info = where._call("reach it", "info", where.path)
            version = next((info[k] for k in ("ETag", "etag", "mtime", "LastModified",
                                              "last_modified", "created") if info.get(k)), "")
            return f"{info.get('size', '')}:{version}"
        st = where.stat()
    except (OSError, RangesegError):
        return None
    return f"{st.st_size}:{st.st_mtime_ns}"


def _read_any(path: Location) -> np.ndarray:
    suffix = path.suffix.lower()
    if isinstance(path, URLPath):
        data = path.read_bytes()
        if not data:
            raise InputError(f"{path}: empty file")
        return _decode_explained(BytesIO(data), suffix, path, data[:_HEAD])
    _check_regular(path)  # a FIFO is never opened: reading it could wait forever
    with path.open("rb") as fh:
        head = fh.read(_HEAD)
    return _decode_explained(path, suffix, path, head)


#: Bytes read to tell a file's format by its signature.
_HEAD = 16
#: Formats by their first bytes: those rangeseg reads, and a few others met beside them.
_SIGNATURES = ((b"\x89PNG\r\n\x1a\n", "PNG"), (b"II*\x00", "TIFF"), (b"MM\x00*", "TIFF"),
               (b"II+\x00", "TIFF"), (b"MM\x00+", "TIFF"), (b"\x93NUMPY", "NPY"),
               (b"PK\x03\x04", "zip (NPZ?)"), (b"\xff\xd8\xff", "JPEG"), (b"GIF8", "GIF"))
#: The format each extension names, and the extension of each format rangeseg reads.
_FORMAT_OF = {".png": "PNG", ".pgm": "PGM/PNM", ".pnm": "PGM/PNM", ".tif": "TIFF",
              ".tiff": "TIFF", ".npy": "NPY"}
_SUFFIX_OF = {"PNG": ".png", "PGM/PNM": ".pgm", "TIFF": ".tif", "NPY": ".npy"}

def content_format(head: bytes) -> str | None:
    """The format whose signature ``head`` (a file's first bytes) starts with, if known.

    Returns
    -------
    str or None
        ``"PNG"``, ``"PGM/PNM"``, ``"TIFF"``, ``"NPY"``, or another format met
        beside depth frames (``"JPEG"``, ``"GIF"``, ``"zip (NPZ?)"``); ``None``
        for anything else.
    """
    if re.match(rb"P[1-7]\s", head):
        return "PGM/PNM"
    return next((kind for magic, kind in _SIGNATURES if head.startswith(magic)), None)


def _check_regular(path: Path) -> None:
    """Refuse an empty file, or one that is no regular file (a FIFO, a device), unopened.

    Raises
    ------
    InputError
        Naming the file and what it is.
    """
    info = path.stat()
    kind = SPECIAL_FILES.get(stat.S_IFMT(info.st_mode))
    if kind is not None:
        raise InputError(f"{path}: {kind}, not a regular file; rangeseg reads image files: "
                         f"{READS}")
    if stat.S_ISREG(info.st_mode) and info.st_size == 0:
        raise InputError(f"{path}: empty file")


#: The formats rangeseg reads, for messages.
READS = "PNG, PGM/PNM, TIFF or NPY"


def _decode_explained(source: Path | BytesIO, suffix: str, path: Location, head: bytes
                      ) -> np.ndarray:
    """:func:`_decode`, its failure said in one line: what the file holds, what is read."""
    try:
        return _decode(source, suffix, path)
    except RangesegError:
        raise
    except (FileNotFoundError, IsADirectoryError, PermissionError):
        raise
    except Exception as exc:  # noqa: BLE001 - every decoder failure becomes one line
        why = _why_unreadable(_reason(exc), content_format(head), suffix)
        raise InputError(f"{path}: not a readable image ({why})") from None


def _why_unreadable(reason: str, kind: str | None, suffix: str) -> str:
    """Why a file of format ``kind`` (by its first bytes) named ``*suffix`` failed to decode."""
    expected = _FORMAT_OF.get(suffix, suffix)
    if kind is not None and kind != expected:
        fix = (f"rename it to {_SUFFIX_OF[kind]}" if kind in _SUFFIX_OF
               else f"convert it to {READS}")
        return (f"it holds {kind} data, not {expected} as its extension {suffix} says; "
                f"rangeseg picks the reader by the extension: {fix}")
    if "Object arrays cannot be loaded" in reason:
        return ("an NPY array of Python objects, which rangeseg never loads; save numbers, "
                "e.g. numpy.save(name, depth.astype('float32'))")
    if kind is None and suffix == ".npy":
        return f"no NPY header: not a file numpy.save wrote; rangeseg reads {READS}"
    if kind is None:
        return f"its content is no image format rangeseg reads: {READS}"
    if "decompression bomb" in reason:  # Pillow's limit on the pixels of one image
        size = re.search(r"\((\d+) pixels\) exceeds limit of (\d+)", reason)
        said = (f"{int(size[1]):,} pixels, beyond the {int(size[2]):,}"
                if size else "more pixels than")
        return (f"{said} the {kind} reader takes in one image; crop or downsample it, or "
                "save it as NPY or TIFF")
    return f"a damaged or truncated {kind} file: {reason}"


def _decode(source: Path | BytesIO, suffix: str, path: Location) -> np.ndarray:
    """Decode a local file, or the bytes of a remote one, by the name's extension."""
    if suffix == ".npy":
        arr = np.load(source, allow_pickle=False)
        if not isinstance(arr, np.ndarray):  # an NPZ archive
            arr.close()
            raise ValueError("an NPZ archive of arrays, not one array")
        return arr
    if suffix in (".tif", ".tiff"):
        return _decode_tiff(source)
    if suffix in (".png", ".pgm", ".pnm"):
        if isinstance(source, Path):
            with source.open("rb") as fh:  # closed even when the decoder fails
                return _decode_png_pnm(fh, suffix, path)
        return _decode_png_pnm(source, suffix, path)
    raise InputError(f"{path}: unsupported extension {suffix!r}; allowed: "
                     + ", ".join(IMAGE_EXTENSIONS))


def _decode_tiff(source: Path | BytesIO) -> np.ndarray:
    """A TIFF's first image; tifffile's own log lines are kept off stderr.

    Raises
    ------
    ValueError
        When tifffile gives no pixels (it logs a damaged file and returns an empty array).
    """
    import tifffile

    logger = logging.getLogger("tifffile")
    disabled, logger.disabled = logger.disabled, True
    try:
        arr = tifffile.imread(source)
    finally:
        logger.disabled = disabled
    if arr.size == 0:
        raise ValueError("no image data tifffile can decode")
    return arr


def _decode_png_pnm(fh: BinaryIO, suffix: str, path: Location) -> np.ndarray:
    """A PNG or netpbm file at its own bit depth; a grey map (P2, P5) by :func:`_read_graymap`.

    Pillow widens 16-bit samples to its 32-bit mode (int32, whose top 2^31-1
    is no clipped value) and rescales a netpbm maxval other than 255 and
    65535 to the full range (raw values changed); PNG and netpbm hold at
    most 16 bits a sample, so an int32 image whose values fit is uint16.
    """
    if fh.read(2) in (b"P2", b"P5"):
        fh.seek(0)
        return _read_graymap(fh.read(), str(path))
    fh.seek(0)
    import imageio.v3 as iio

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        arr = iio.imread(fh, extension=suffix)
    if arr.dtype == np.int32 and arr.size and 0 <= arr.min() and arr.max() <= 65535:
        return arr.astype(np.uint16)
    return arr


#: A header field of a netpbm file: whitespace and comments, then the number.
_NETPBM_FIELD = re.compile(rb"(?:\s|#[^\r\n]*)+([0-9]+)")


def _read_graymap(data: bytes, name: str) -> np.ndarray:
    """The raw values of a PGM file (P5 binary or P2 plain): uint8, or uint16 above 255.

    Parameters
    ----------
    data
        The file's bytes; an image after the first is ignored.
    name
        Named in error messages.

    Returns
    -------
    numpy.ndarray
        (H, W) as stored: uint8 when the header's maxval is below 256, else
        uint16 (netpbm's one or two bytes a sample), never rescaled.

    Raises
    ------
    InputError
        For a malformed header, a maxval outside 1..65535, too few pixels or
        a value above maxval.
    """
    fields, pos = [], 2
    for _ in range(3):  # width, height, maxval
        match = _NETPBM_FIELD.match(data, pos)
        if match is None:
            raise InputError(f"{name}: not a readable image (malformed PGM header)")
        fields.append(int(match.group(1)))
        pos = match.end()
    width, height, maxval = fields
    if not 0 < maxval < 65536 or not data[pos:pos + 1].isspace():
        raise InputError(f"{name}: not a readable image (PGM maxval {maxval}; allowed: "
                         "1 to 65535, then one whitespace character)")
    dtype = np.dtype(np.uint8 if maxval < 256 else np.uint16)
    count = width * height
    if data[:2] == b"P5":
        if len(data) - pos - 1 < count * dtype.itemsize:
            raise InputError(f"{name}: not a readable image (PGM data truncated)")
        values = np.frombuffer(data, dtype.newbyteorder(">"), count, pos + 1)
    else:
        values = _plain_values(data[pos:], count, name)
    if values.size and int(values.max()) > maxval:
        raise InputError(f"{name}: not a readable image (pixel value {int(values.max())} "
                         f"above the header's maxval {maxval})")
    return values.astype(dtype).reshape(height, width)


def _plain_values(text: bytes, count: int, name: str) -> np.ndarray:
    """The first ``count`` numbers of a plain (P2) PGM's raster, as int64."""
    tokens = re.sub(rb"#[^\r\n]*", b"", text).split(None, count)[:count]
    if len(tokens) < count or not all(t.isdigit() and len(t.lstrip(b"0")) <= 5 for t in tokens):
        raise InputError(f"{name}: not a readable image (PGM data truncated or not "
                         "numbers 0 to 65535)")
    return np.array(tokens, dtype=np.int64)


#: Decides whether a file below a searched folder (the folder, the file's path relative
#: to it) is an output an earlier run of rangeseg wrote there.
WrittenCheck: TypeAlias = Callable[[Location, PurePath], bool]


@dataclass(frozen=True)
class NameFilter:
    """Which files of a searched folder are read: ``--include`` and ``--exclude`` globs.

    A glob without ``/`` is matched against each part of a file's path below
    the named folder (its name and its folders' names: ``*_mask.png``,
    ``masks``); one with ``/`` against the path itself and the folders above
    the file (``cam1/*.npy``, ``cam1/masks``; a leading ``/`` is dropped).
    ``*`` and ``?`` stop at ``/``, a ``**`` piece matches any number of
    folders, ``[abc]`` is one of the characters; matching is case-sensitive,
    as in rsync and ripgrep.

    Attributes
    ----------
    include
        With any, only the files some include glob matches are read.
    exclude
        The files an exclude glob matches are not read, whatever the includes say.
    """

    include: tuple[str, ...] = ()
    exclude: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        for glob in (*self.include, *self.exclude):
            if not glob.strip("/"):
                raise ValueError(f"{glob!r}: an empty glob; expected e.g. '*_depth.npy'")

    def accepts(self, rel: PurePath) -> bool:
        """Whether the file at ``rel`` (below the named folder) is read."""
        if any(_glob_matches(g, rel) for g in self.exclude):
            return False
        return not self.include or any(_glob_matches(g, rel) for g in self.include)


def _glob_matches(glob: str, rel: PurePath) -> bool:
    """Whether ``glob`` matches ``rel`` or a folder above it (:class:`NameFilter`)."""
    glob, parts = glob.strip("/"), rel.parts
    if "/" not in glob:
        return any(fnmatch.fnmatchcase(part, glob) for part in parts)
    pieces = glob.split("/")
    return any(_pieces_match(pieces, parts[:n]) for n in range(1, len(parts) + 1))


def _pieces_match(pieces: Sequence[str], parts: Sequence[str]) -> bool:
    """Whether the ``/``-separated pieces of a glob match a path's parts, one each.

    A ``**`` piece matches any number of parts.
    """
    if not pieces:
        return not parts
    if pieces[0] == "**":
        return any(_pieces_match(pieces[1:], parts[k:]) for k in range(len(parts) + 1))
    return (bool(parts) and fnmatch.fnmatchcase(parts[0], pieces[0])
            and _pieces_match(pieces[1:], parts[1:]))


def find_images(inputs: Iterable[str | Path], *, exclude: Location | None = None,
                written: WrittenCheck | None = None, names: NameFilter | None = None
                ) -> tuple[list[tuple[Location, PurePath]], list[Location]]:
    """Resolve files and folders (recursively) into image files.

    Parameters
    ----------
    inputs
        Files and folders named on the command line: local paths or URLs
        (:func:`location`). Files and folders whose names start with ``.`` are
        not searched.
    exclude
        A folder never read from (the output folder, when it lies inside an input).
    written
        Which files of the searched folders are outputs of an earlier run (read
        from its manifest: :func:`rangeseg_cli.batch.runner.jobs_from_inputs`); those
        are not read. Without it, every file named like an output
        (:data:`OUTPUT_MARKERS`) is taken for one. Ground truth
        (``<stem>.gt.*``, as ``rangeseg synth`` writes beside its frames) is
        never read.
    names
        Which files of the searched folders to read (``--include``,
        ``--exclude``); a file named in ``inputs`` is always read.

    Returns
    -------
    images
        ``(path, relative stem)`` pairs in a stable order; the relative stem is
        the path below the named folder without its extension (just the stem for
        a file named directly), so outputs go to ``OUT/<rel>.<artifact>``.
    skipped
        Files in the folders that are not images by extension, ground truth,
        outputs, or left out by ``names``.

    Raises
    ------
    InputError
        When a named input does not exist.
    StorageError
        When a URL's store cannot be used or reached.
    """
    images: list[tuple[Location, PurePath]] = []
    skipped: list[Location] = []
    excluded = exclude.resolve() if isinstance(exclude, Path) else exclude
    for item in inputs:
        root = location(item)
        if root.is_file():
            images.append((root, Path(_strip(root.name))))
        elif root.is_dir():
            for path, rel in _walk(root, excluded):
                if (names is None or names.accepts(rel)) and _is_input_image(root, rel,
                                                                             written):
                    images.append((path, rel.parent / _strip(rel.name)))
                else:
                    skipped.append(path)
        else:
            raise _missing_input(root)
    return images, skipped


def _missing_input(root: Location) -> InputError:
    """The error of a named input that is no file or folder: missing, or a broken link."""
    if isinstance(root, Path) and root.is_symlink():
        try:
            root.stat()
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                return InputError(f"{root}: {LINK_LOOP}; name a file or folder")
        return InputError(f"{root}: a symbolic link to {os.readlink(root)}, which does not "
                          "exist; name a file or folder")
    if isinstance(root, Path) and root.exists():
        kind = SPECIAL_FILES.get(stat.S_IFMT(root.stat().st_mode), "not a regular file")
        return InputError(f"{root}: {kind}, not a file or folder; rangeseg reads image "
                          f"files: {READS}")
    return InputError(f"{root}: no such file or folder")


def _walk(root: Location, excluded: Location | None) -> Iterator[tuple[Location, PurePath]]:
    """Files below ``root`` with their paths relative to it, in a stable order."""
    if isinstance(root, URLPath):
        yield from _walk_url(root, excluded if isinstance(excluded, URLPath) else None)
        return
    for path in _walk_local(root, excluded if isinstance(excluded, Path) else None):
        yield path, path.relative_to(root)


def _walk_local(root: Path, excluded: Path | None) -> Iterator[Path]:
    """Files below ``root``; symbolic links to folders are followed, except into a loop.

    Raises
    ------
    InputError
        When a folder below ``root`` cannot be listed (no permission): its
        images would otherwise be left out without a word.
    """
    for dirpath, dirnames, filenames in os.walk(root, onerror=_unreadable_folder,
                                                followlinks=True):
        here = Path(dirpath)
        dirnames[:] = [d for d in sorted(dirnames)
                       if not d.startswith(".") and _walk_into(here, d, excluded)]
        for name in sorted(filenames):
            if not name.startswith("."):
                yield here / name


def _walk_into(here: Path, name: str, excluded: Path | None) -> bool:
    """Whether to search folder ``here / name``: not the output, not a link to an ancestor."""
    target = (here / name).resolve()
    if excluded is not None and target == excluded:
        return False
    return target not in (here.resolve(), *here.resolve().parents)


def _unreadable_folder(exc: OSError) -> None:
    raise InputError(f"{exc.filename}: cannot read folder ({_os_reason(exc)})")


def _walk_url(root: URLPath, excluded: URLPath | None) -> Iterator[tuple[URLPath, PurePath]]:
    """As :func:`_walk_local` on a store: one listing, the same order and the same skips."""
    skip = None
    if excluded is not None and excluded.url.startswith(root.url + "/"):
        skip = excluded.url[len(root.url) + 1:] + "/"
    rels = [rel for rel in root.files()
            if not any(part.startswith(".") for part in rel.split("/"))
            and not (skip and rel.startswith(skip))]
    for rel in sorted(rels, key=_walk_order):
        yield root / rel, PurePosixPath(rel)


def _walk_order(rel: str) -> list[tuple[int, str]]:
    """Sort key of os.walk top-down with sorted names: a folder's files, then its folders."""
    parts = rel.split("/")
    return [(1, d) for d in parts[:-1]] + [(0, parts[-1])]


def find_outputs(root: Location, suffix: str) -> list[str]:
    """Relative stems of the files below ``root`` whose names end with ``suffix``, sorted."""
    if isinstance(root, URLPath):
        names = [rel for rel in root.files() if rel.endswith(suffix)]
    else:
        names = [p.relative_to(root).as_posix() for p in root.rglob(f"*{suffix}")]
    return sorted(n[: -len(suffix)] for n in names)


def file_checker(root: Location) -> Callable[[str], bool]:
    """``exists(rel)``: whether ``root / rel`` exists (on a store: one listing, not a call each)."""
    if isinstance(root, URLPath):
        return set(root.files()).__contains__
    return lambda rel: (root / rel).exists()


def remove_temporaries(root: Location) -> None:
    """Delete temporary files a killed run left behind (``.<name>.<random>.tmp``)."""
    if isinstance(root, URLPath):
        if root.protocol not in OBJECT_STORES:  # object stores never hold ours
            for rel in root.files():
                name = rel.rsplit("/", 1)[-1]
                if name.startswith(".") and name.endswith(".tmp"):
                    (root / rel).unlink()
    elif root.is_dir():
        for tmp in root.rglob(".*.tmp"):
            tmp.unlink(missing_ok=True)


def _is_input_image(root: Location, rel: PurePath, written: WrittenCheck | None) -> bool:
    """Whether file ``rel`` below folder ``root`` is read as an image.

    So it is by its extension, unless it is ground truth or an output of an
    earlier run (by ``written``, else by its name).
    """
    lower = rel.name.lower()
    if not lower.endswith(IMAGE_EXTENSIONS) or GROUND_TRUTH_MARKER in lower:
        return False
    if written is None:
        return not any(m in lower for m in OUTPUT_MARKERS)
    return not written(root, rel)


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


def make_folder(where: Location) -> None:
    """Create the output folder ``where`` and its parents (none needed on object stores).

    Raises
    ------
    OutputError
        One line naming the folder, when it cannot be created (a file in the
        way, no permission, a read-only or full file system).
    StorageError
        When a URL's store cannot be written.
    """
    if isinstance(where, URLPath):
        where.mkdir()
        return
    try:
        where.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise OutputError(f"{where}: cannot create the output folder: a file of that name "
                          "is in its way") from None
    except OSError as exc:
        raise OutputError(f"{where}: cannot create the output folder "
                          f"({_os_reason(exc)})") from None


def check_writable(path: Location) -> None:
    """Check, before a long computation, that a file can be written at ``path``.

    A temporary file is made and removed in the nearest existing folder above
    ``path`` (the write makes the folders missing below it); on a URL nothing
    is checked (the store's rights show only in a write).

    Raises
    ------
    OutputError
        One line naming the file, when that folder cannot be written (no
        permission, a read-only or special file system, a file in the way).
    """
    if isinstance(path, URLPath):
        return
    folder = Path(os.path.abspath(path)).parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({_os_reason(exc)})") from None


def _os_reason(exc: OSError) -> str:
    """``No space left on device`` and the like: the system's words, without the path."""
    return exc.strerror or _reason(exc)


def _atomic_write(path: Location, write: Any) -> None:
    """Write through ``write(fileobj)`` into a temp file beside ``path``, then rename.

    The bytes are made in memory first, so a full disk or a read-only folder is
    reported by the system call that failed. To a URL: one
    :meth:`URLPath.write_bytes`.

    Raises
    ------
    OutputError
        One line naming the file when it cannot be written; no file is left.
    """
    buffer = BytesIO()
    write(buffer)
    if isinstance(path, URLPath):
        path.write_bytes(buffer.getvalue())
        return
    make_folder(path.parent)
    try:
        _replace_file(path, buffer.getbuffer())
    except OSError as exc:
        raise OutputError(f"{path}: cannot write ({_os_reason(exc)})") from None


def _replace_file(path: Path, data: memoryview) -> None:
    """Write ``data`` into a temporary file beside ``path`` and rename it over ``path``."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, _FILE_MODE)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def remove_file(path: Location) -> None:
    """Delete a file; a missing one (or a missing folder above it) is no error.

    Raises
    ------
    OutputError
        One line naming the file, when it is there and cannot be deleted.
    StorageError
        When a URL's store refuses.
    """
    if isinstance(path, URLPath):
        path.unlink()
        return
    try:
        path.unlink(missing_ok=True)
    except NotADirectoryError:
        pass  # a file stands where its folder would be: no file of that name is there
    except OSError as exc:
        raise OutputError(f"{path}: cannot delete ({_os_reason(exc)})") from None


def write_npy(path: Location, array: np.ndarray) -> None:
    """Write an array as ``.npy`` atomically."""
    _atomic_write(path, lambda fh: np.save(fh, np.ascontiguousarray(array),
                                           allow_pickle=False))


def read_npy(path: Location) -> np.ndarray:
    """Read an ``.npy`` this tool wrote; a missing or broken file is an :class:`OutputError`."""
    try:
        if isinstance(path, URLPath):
            return np.load(BytesIO(path.read_bytes()), allow_pickle=False)
        return np.load(path, allow_pickle=False)
    except FileNotFoundError:
        raise OutputError(f"{path}: missing; run the earlier stage first") from None
    except (OSError, ValueError) as exc:
        why = "it holds Python objects" if "allow_pickle" in str(exc) else str(exc)
        raise OutputError(f"{path}: cannot read: damaged, or not an array rangeseg wrote "
                          f"({why}); redo its stage (--overwrite)") from None


def write_png(path: Location, image: np.ndarray) -> None:
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


def is_utf8(name: str) -> bool:
    """Whether ``name`` is valid UTF-8 text (a file name that is not holds surrogate escapes)."""
    try:
        name.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def percent_name(name: str) -> str:
    """A file name that is no valid UTF-8, as written in JSON: reversible, plain text.

    Each byte of the name that is not part of valid UTF-8, and each ``%``, is
    written ``%XX`` (two upper-case hex digits); the rest stays as it is. So
    Latin-1 ``café.png`` (byte E9) is ``"caf%E9.png"``, and the bytes come back
    with ``urllib.parse.unquote_to_bytes`` (:func:`name_from_percent`).
    """
    return "".join(f"%{ord(c) - 0xDC00:02X}" if 0xDC80 <= ord(c) <= 0xDCFF
                   else "%25" if c == "%" else c for c in name)


def name_from_percent(text: str) -> str:
    """The file name :func:`percent_name` wrote (undecodable bytes as surrogate escapes)."""
    return unquote_to_bytes(text).decode("utf-8", "surrogateescape")


def printable(text: str) -> str:
    """``text`` (a message naming files) with each byte that is no UTF-8 written ``%XX``."""
    if is_utf8(text):
        return text
    return "".join(f"%{ord(c) - 0xDC00:02X}" if 0xDC80 <= ord(c) <= 0xDCFF else c
                   for c in text).encode("utf-8", "replace").decode("utf-8")


def write_json(path: Location, data: Any, digits: int = 6) -> None:
    """Write JSON with sorted keys and rounded floats, atomically."""
    text = json.dumps(to_jsonable(data, digits), sort_keys=True, indent=2) + "\n"
    _atomic_write(path, lambda fh: fh.write(text.encode()))


def read_json(path: Location) -> Any:
    """Read a JSON file this tool wrote; failures are :class:`OutputError`."""
    try:
        return json.loads(path.read_bytes().decode() if isinstance(path, URLPath)
                          else path.read_text())
    except FileNotFoundError:
        raise OutputError(f"{path}: missing; run the earlier stage first") from None
    except (OSError, ValueError) as exc:
        raise OutputError(f"{path}: cannot read ({exc})") from None


def write_text(path: Location, text: str) -> None:
    """Write text atomically."""
    _atomic_write(path, lambda fh: fh.write(text.encode()))


def write_bytes(path: Location, data: bytes) -> None:
    """Write bytes (a PLY file) atomically."""
    _atomic_write(path, lambda fh: fh.write(data))
