"""Whether the compiled kernels are cached: the first run after installing compiles them.

numba compiles :mod:`rangeseg_cli._kernels` on first use (20-85 s, once) and
caches the machine code beside the package, in ``__pycache__`` (or under
``NUMBA_CACHE_DIR``), one index file (``_kernels.<function>-<line>.py311.nbi``)
per kernel; later processes load them in about half a second. The command
line asks :func:`cold_kernel_cache` before a batch so that it can say why the
first image takes long. The check only lists a folder: it imports nothing.
"""

from __future__ import annotations

import importlib.util
import os
from pathlib import Path

SOURCE = Path(__file__).with_name("_kernels.py")

#: What the command line prints on stderr when the cache is cold.
MESSAGE = ("rangeseg: compiling the numba kernels (first run after installing only, "
           "about 30 s; later runs load them in under a second)...")


def _cache_dirs() -> list[Path]:
    dirs = [SOURCE.parent / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        dirs.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    return dirs


def cold_kernel_cache() -> bool:
    """True when the kernels will be compiled, not loaded, by this process's first call.

    False without numba or with ``RANGESEG_PURE_NUMPY=1`` (nothing is compiled),
    and when an index file of the kernels is newer than their source (numba
    recompiles a kernel whose source changed since it was cached).
    """
    if os.environ.get("RANGESEG_PURE_NUMPY") == "1" or importlib.util.find_spec("numba") is None:
        return False
    try:
        stamp = SOURCE.stat().st_mtime
    except OSError:
        return False
    for folder in _cache_dirs():
        pattern = "_kernels.*.nbi"
        found = folder.glob(pattern) if folder.name == "__pycache__" else folder.rglob(pattern)
        try:
            if any(p.stat().st_mtime >= stamp for p in found):
                return False
        except OSError:
            continue
    return True
