"""The choice of backend: the numpy reference or the compiled kernels.

Every stage with compiled kernels (edges, Sec. V-1 and V-2; region growing,
Sec. V-4; and the steps beyond the paper) takes ``backend`` and asks
:func:`select_kernels` for :mod:`rangeseg_cli.kernels.compiled` or None. The numpy
functions of each module are the reference; the kernels give exactly the same
results. When numba is installed, ``"auto"`` selects the kernels; set the
environment variable ``RANGESEG_PURE_NUMPY=1`` (or pass ``backend="numpy"``)
to use the reference.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from types import ModuleType
from typing import Literal, get_args

from .cache import ready

Backend = Literal["auto", "numba", "numpy"]

#: Whether ``backend="auto"`` uses the compiled kernels: numba is installed and
#: ``RANGESEG_PURE_NUMPY`` is not ``1`` (``auto`` falls back to numpy when numba
#: cannot be imported).
_USE_NUMBA: bool = (os.environ.get("RANGESEG_PURE_NUMPY", "") != "1"
                    and importlib.util.find_spec("numba") is not None)


@functools.cache
def _compiled_kernels() -> ModuleType | None:
    """:mod:`rangeseg_cli.kernels.compiled`, or None when numba is missing or cannot load."""
    if importlib.util.find_spec("numba") is None:
        return None
    try:
        from . import compiled
    except (ImportError, RuntimeError):  # numba too old/new for numpy, or no cache dir
        return None
    return compiled


_BACKENDS: tuple[str, ...] = get_args(Backend)


def select_kernels(backend: str) -> ModuleType | None:
    """The compiled kernels when ``backend`` selects them, else None; validates ``backend``.

    The one switch of every stage with compiled kernels (edges, Sec. V-1 and
    V-2; region growing, Sec. V-4): ``"numpy"`` gives None (the reference),
    ``"numba"`` the kernels (an ImportError without numba), ``"auto"`` the
    kernels when numba is installed and ``RANGESEG_PURE_NUMPY`` is not ``1``.
    """
    if backend not in _BACKENDS:
        raise ValueError(f"`backend` ({backend!r}) must be one of {_BACKENDS}")
    if backend == "numpy" or (backend == "auto" and not _USE_NUMBA):
        return None
    kernels = _compiled_kernels()
    if kernels is None and backend == "numba":
        raise ImportError("`backend` 'numba' needs the numba package, which is not installed "
                          "or cannot be imported; use backend='numpy' or 'auto'")
    return kernels


def select_deferred(backend: str, *names: str) -> ModuleType | None:
    """:func:`select_kernels` for ``names``, kernels of :data:`~.cache.DEFERRED`.

    Under ``"auto"`` None until each kernel is compiled or cached in this
    process's reach (:func:`~.cache.ready`): until then the caller takes its
    numpy reference (the same results), and the first run after installing
    does not wait for the kernels to compile.
    """
    kernels = select_kernels(backend)
    if kernels is None or (backend == "auto"
                           and not all([ready(kernels, name) for name in names])):
        return None
    return kernels
