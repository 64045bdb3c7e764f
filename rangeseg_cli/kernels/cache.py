"""The compiled kernels' cache, and the first run after installing, which fills it.

numba compiles :mod:`rangeseg_cli.kernels.compiled` on first use and caches the
machine code beside the package, in ``__pycache__`` (or under
``NUMBA_CACHE_DIR``, or in the user's cache folder when the package is
read-only), one index file (``compiled.<function>-<line>.py311.nbi``)
per kernel; later processes load them in about half a second. The command
line asks :func:`cold_kernel_cache` before a batch so that it can say why the
first image takes long (:data:`MESSAGE`). The check only lists a folder: it
imports nothing.

Notes
-----
The first run: ``rangeseg run`` of a 128x128 image with the defaults, on two
idle cores, cache empty (``benchmarks/first_run.py``, medians of 3). It took
29.3 s, nearly all of it compiling 88 signatures of 79 kernels (and about 90
of numba's own functions); it takes about 6 s now (about 25 s in one
process, without the helper, which then compiles every kernel it calls;
the machine's speed varies between days), by three means, chosen by
measuring each:

1. Less to compile: 30 kernels of one signature each (29.3 s to 14.9 s).
   A literal ``0`` or ``1`` passed to another kernel, or a read-only array,
   compiled that kernel once more; helpers called from one place are
   inlined into their caller (``inline="always"``: compiling a function on
   its own costs about 0.1 s more than typing it within its caller);
   kernels that only chained others are Python; loops stand where slice
   assignment, ``np.full``, ``.max()`` or array arithmetic compiled numba's
   generic code; and the labelling of the components, the clearance, box
   means and erosion of the holdsite search are :mod:`scipy.ndimage`'s, as
   their numpy references were (their compiled twins took 5 s). The outputs
   are the same bytes, and warm runs as fast.
2. Compiling in two processes (14.9 s to 8.3 s): on a cold cache, the
   first kernel compiled starts one helper process (:func:`compile_ahead`)
   that compiles :data:`FIRST_RUN` from its end (:func:`ahead_order`) while
   the run compiles from its start; each loads from the cache what the
   other has compiled. It stops when done or, after the kernel it is
   compiling, when the process that started it has ended
   (``RANGESEG_COMPILE_AHEAD=0``: no helper).
3. Kernels that only speed up a step whose numpy reference gives the same
   bits (:data:`DEFERRED`) run once compiled or cached (:func:`ready`): the
   first run takes the reference while the helper compiles them, after
   the kernels the run waits for. Among them the edges' and the noise
   estimate's (5.4 s of compiling; their references take 8 ms more on a
   128x128 image, 170 ms more on 640x480, until they are compiled): a cold
   first run of a 128x128 image went from 10.9 s to 6.3 s on a machine
   where it once took 9.2 s.

Measured and not taken: numba's options (``error_model="python"``,
reference counts everywhere, no ``nogil``, no inlining: each within 1 s of
31 s); LLVM's optimisation level (``NUMBA_OPT=1``: 10 % less, but it is
numba's setting for the whole process; at 0 numba cannot cache);
numba's ahead-of-time compiler (``numba.pycc``, pending deprecation in numba
0.68, and a C compiler at install); a cache built at install (pip runs no
step after installing a wheel, a build hook runs in a throw-away
environment, and numba keys its cache on the source, by its hash from
numba 0.68 and by its modification time before, and on the CPU).
"""

from __future__ import annotations

import atexit
import functools
import hashlib
import importlib.util
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import ModuleType
from typing import Any

SOURCE = Path(__file__).with_name("compiled.py")

#: What the command line prints on stderr when the cache is cold.
MESSAGE = ("rangeseg: compiling the numba kernels (first run after installing only, "
           "a few seconds; later runs load them in under a second)...")

#: The kernels a default run calls from Python, with the argument types its call
#: sites give them, in the order of first call (``heights``, whose type follows
#: the input, is compiled first by the run itself). A test checks the list
#: against a run; ``benchmarks/first_run.py --profile`` shows what compiles.
FIRST_RUN: tuple[tuple[str, str], ...] = (
    ("noise_residuals", "(float64[:, ::1], float64[::1], int64)"),
    ("smallest_keys", "(uint64[::1], int64)"),
    ("edges_pass", "(float64[:, ::1], boolean[:, ::1], int64, float64[::1], float64, int64,"
                   " boolean)"),
    ("roof_passes", "(float64[:, ::1], boolean[:, ::1], int64, float64[::1], float64, float64,"
                    " int64, boolean)"),
    ("link_codes", "(uint8[:, ::1], boolean[:, ::1])"),
    ("valid_labels", "(float64[:, ::1], int32[:, ::1])"),
    ("fitted_runs", "(float64[:, ::1], int32[:, ::1])"),
    ("run_moments", "(float64[:, ::1], UniTuple(int64[::1], 4), int64, int64, int64)"),
    ("run_sse", "(float64[:, ::1], UniTuple(int64[::1], 4), float64[::1], float64[::1],"
                " float64[::1], float64[:, :, ::1], int64, int64)"),
    ("image_coefficients", "(float64[:, :, ::1], float64[::1], float64[::1], float64[::1])"),
    ("grow_pass", "(float64[:, ::1], boolean[:, ::1], int32[:, ::1], float64[:, ::1],"
                  " float64[::1])"),
    ("neighbour_accepts", "(float64[:, ::1], int32[:, ::1], float64[:, ::1], float64[::1],"
                          " int64[::1], int64[::1], int64)"),
    ("consensus_plane", "(float64[:, ::1], boolean[:, ::1], float64[::1], float64, float64,"
                        " float64, int64, float64)"),
    ("explained_faces", "(float64[:, ::1], int64[:], int64[:], int64[::1], int64,"
                        " float64[:, ::1], float64[::1], int64[::1])"),
    ("neighbour_pairs", "(int32[:, ::1], int64)"),
    ("fill_passes", "(float64[:, ::1], int32[:, ::1], float64[:, ::1], float64[::1])"),
    ("crease_votes", "(int32[:, ::1], int64[::1], int64[::1], int64[::1], float64[::1],"
                     " float64[:, ::1], int64)"),
    ("boundary_labels", "(float64[:, ::1], int32[:, ::1], float64[:, ::1], float64, float64,"
                        " int8[:, ::1], float64, boolean, int32[:, ::1], int64, int64)"),
    ("boundary_measures", "(int32[:, ::1], int64, float64[:, ::1])"),
    ("pair_medians", "(int64[::1], int64[::1], int64, float64[:, ::1])"),
    ("label_boxes", "(int32[:, ::1], int64)"),
    ("ar_2d", "(float64[:, ::1], float64[::1])"),
)

#: Kernels of :data:`DEFERRED` that the first run does without (it takes their
#: reference, on the kernels of :data:`FIRST_RUN`): the helper compiles them after
#: those (:func:`ahead_order`). ``k_plane_passes`` only a real frame's run calls.
LATER: tuple[tuple[str, str], ...] = (
    ("best_knot", "(int64[::1], int64[::1], float64[::1], float64, float64, int64[::1],"
                  " float64, int64[::1], float64)"),
    ("k_plane_passes", "(float64[:, ::1], int64[::1], int64[::1], int64[:, ::1],"
                       " float64[:, ::1], float64, int64, float64)"),
    ("clean_parts", "(int32[:, ::1], boolean[:, ::1], boolean[:, ::1], int64, int64,"
                    " int64[::1], int64[::1])"),
    ("reassign_parts", "(float64[:, ::1], int32[:, ::1], boolean[:, ::1], boolean[:, ::1],"
                       " int64, int64, int64, float64[::1], float64, int64[::1], int64[::1])"),
    ("union_runs", "(float64[:, ::1], int32[:, ::1], int64[:, ::1], int64[:, ::1])"),
    ("plane_counts", "(float64[:, ::1], float64[::1], float64)"),
    ("knot_sse", "(float64[::1], float64[::1], float64[::1], float64[::1], float64[::1],"
                 " int64[::1], float64)"),
)

#: Set in the helper's environment: it compiles, it starts no helper.
_HELPER = "RANGESEG_COMPILING_AHEAD"

_helper: subprocess.Popen[bytes] | None = None
_no_helper = False  # the helper could not be started: the kernels compile here
_asked = False  # whether this process has started (or tried to start) the helper
_asking = threading.Lock()


def _cache_dir() -> Path:
    """The folder numba caches the kernels in, chosen as numba does.

    ``NUMBA_CACHE_DIR`` when set; else ``__pycache__`` beside the source when
    it can be written, else (a package installed read-only) numba's folder in
    the user's cache.
    """
    in_tree = SOURCE.parent / "__pycache__"
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"])
    if _writable(in_tree):
        return in_tree
    return _user_wide_dir() or in_tree


def _writable(folder: Path) -> bool:
    """Whether numba can write ``folder`` (or make it in its writable parent)."""
    if folder.exists():
        return folder.is_dir() and os.access(folder, os.W_OK | os.X_OK)
    return os.access(folder.parent, os.W_OK | os.X_OK)


def _user_wide_dir() -> Path | None:
    """The user-wide cache folder numba takes for the kernels' source (none without numba)."""
    try:
        from numba.misc.appdirs import AppDirs
    except ImportError:
        return None
    folder = os.path.dirname(os.path.abspath(SOURCE))
    sub = f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"
    return Path(AppDirs(appname="numba", appauthor=False).user_cache_dir) / sub


#: Kernels that only speed up a step whose numpy reference gives the same bits: a run
#: whose cache lacks them takes the reference and leaves their compiling to the helper
#: (:func:`ready`), so that the first run after installing does not wait for them.
DEFERRED: tuple[str, ...] = ("noise_residuals", "smallest_keys", "edges_pass", "roof_passes",
                              "crease_votes", "neighbour_accepts", "boundary_labels",
                              "consensus_plane", "k_plane_passes", "best_knot", "clean_parts",
                              "reassign_parts", "union_runs", "plane_counts", "knot_sse")

_ready: set[str] = set()

#: Seconds between two looks into the cache for a kernel not ready yet (a look is a
#: directory listing, and the consensus asks thousands of times a frame).
RECHECK_S = 0.5

_looked: dict[str, float] = {}  # when each kernel not ready was last looked for


def ready(kernels: ModuleType, name: str) -> bool:
    """Whether kernel ``name`` of :data:`DEFERRED` can run without compiling in this process.

    True once this process has it compiled or loaded, or when the cache holds
    it (an index file ``compiled.<name>-*.nbi`` of the current source);
    the callers take the numpy reference otherwise (the same results), and
    the helper is started to compile it (once per process). Where no helper
    can compile it (``RANGESEG_COMPILE_AHEAD=0``, a frozen app, no process
    to spare), always True: the kernel compiles in this process.
    """
    if name in _ready:
        return True
    found = (bool(getattr(getattr(kernels, name), "overloads", None))
             or _no_helper or not _helper_allowed())  # no helper: it compiles here
    if not found and name in _looked and time.monotonic() - _looked[name] < RECHECK_S:
        return False
    _looked[name] = time.monotonic()
    found = found or cached(name)
    if found:
        _ready.add(name)
    else:  # the helper compiles it (a first run's helper may have ended before it)
        _ask_helper()
    return found


def cached(name: str) -> bool:
    """Whether the cache holds kernel ``name``: an index file of the current source."""
    # where numba looks: NUMBA_CACHE_DIR when it is set
    return _fresh_index(_cache_dir(), f"compiled.{name}-*.nbi")


def _fresh_index(folder: Path, pattern: str) -> bool:
    """Whether cache directory ``folder`` holds an index file ``pattern`` of the current source.

    An index is of the current source when it holds the source's SHA-256 (the
    stamp numba 0.68 and later write: a checkout or a reinstall that rewrites
    the same source leaves it valid), or, for older numba, whose stamp is the
    source's modification time, when it is no older than the source. False
    when either cannot be read.
    """
    try:
        stamp = SOURCE.stat().st_mtime
        digest = _source_digest(SOURCE, stamp)
        hits = folder.glob(pattern) if folder.name == "__pycache__" else folder.rglob(pattern)
        return any(p.stat().st_mtime >= stamp or digest in p.read_bytes() for p in hits)
    except OSError:
        return False


@functools.lru_cache(maxsize=4)
def _source_digest(path: Path, mtime: float) -> bytes:
    """SHA-256 of the kernels' source (``mtime`` keys the memo: an edit hashes again)."""
    return hashlib.sha256(path.read_bytes()).digest()


def cold_kernel_cache() -> bool:
    """True when the kernels will be compiled, not loaded, by this process's first call.

    False without numba or with ``RANGESEG_PURE_NUMPY=1`` (nothing is compiled),
    and when an index file of the kernels is of their current source
    (:func:`cached`; numba recompiles a kernel whose source changed since it
    was cached).
    """
    if os.environ.get("RANGESEG_PURE_NUMPY") == "1" or importlib.util.find_spec("numba") is None:
        return False
    try:
        SOURCE.stat()
    except OSError:
        return False
    return not _fresh_index(_cache_dir(), "compiled.*.nbi")  # where numba looks


def compile_ahead_when_cold() -> None:
    """Start :func:`compile_ahead` in a helper process at this process's first compile.

    Called once by :mod:`rangeseg_cli.kernels.compiled` on import: numba's
    ``numba:compile`` event, which it sends only when a kernel is not in the
    cache, starts the helper (not in the helper itself, nor with
    ``RANGESEG_COMPILE_AHEAD=0``). The helper stops after this process exits
    (:func:`_end_helper`).
    """
    if not _helper_allowed():
        return
    from numba.core import event

    class Compiles(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            _on_compile(ev.data["dispatcher"])

        def on_end(self, ev: event.Event) -> None:
            pass

    event.register("numba:compile", Compiles())


def _helper_allowed() -> bool:
    """Whether this process may start the helper (not the helper itself, nor switched off)."""
    return not (os.environ.get(_HELPER) or os.environ.get("RANGESEG_COMPILE_AHEAD") == "0"
                or getattr(sys, "frozen", False))  # a frozen app's executable is not python


def _on_compile(dispatcher: Any) -> None:
    """At the first compilation of a kernel (not of numba's own code), start the helper."""
    module = getattr(dispatcher.py_func, "__module__", "")
    if module == "rangeseg_cli.kernels.compiled":
        _ask_helper()


def _ask_helper() -> None:
    """Start the helper, once per process (:func:`skip_helper`: never)."""
    global _asked
    with _asking:
        if _asked or not _helper_allowed():
            return
        _asked = True
    _start_helper()


def skip_helper() -> None:
    """Never start the helper from this process.

    For a child of :func:`~.parallel.map_processes`: it ends with its share
    of one pass, and the helper ends with the process that started it. (No
    lock: a fork may copy it held.)
    """
    global _asked
    _asked = True


def _start_helper() -> None:
    """The helper process of :func:`compile_ahead` (kept, and ended at exit)."""
    global _helper, _no_helper
    code = ("from rangeseg_cli.kernels.backend import select_kernels\n"
            "from rangeseg_cli.kernels.cache import compile_ahead\n"
            f"compile_ahead(select_kernels('numba'), {os.getpid()})")
    try:
        _helper = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.DEVNULL,
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                   env={**os.environ, _HELPER: "1"})
    except OSError:  # no process to spare: the run compiles alone
        _no_helper = True
        return
    atexit.register(_end_helper)


def _end_helper() -> None:
    """At exit: the helper finishes the kernel it compiles, then stops (:func:`compile_ahead`).

    Each short run thus adds a kernel to the cache, where ending the helper
    at once left the DEFERRED ones uncompiled for good. It is not waited
    for (its ``returncode`` set, so the interpreter does not warn of it).
    """
    if _helper is not None and _helper.poll() is None:
        _helper.returncode = 0


def ahead_order() -> list[tuple[str, str]]:
    """The helper's order: :data:`FIRST_RUN` last first (:data:`DEFERRED` after), :data:`LATER`.

    The run compiles from the first on, and the two meet. The run does
    without a kernel of :data:`DEFERRED` until it is ready, so the helper
    first compiles what the run would wait for: a cold first run of a
    128x128 image ends about 2 s sooner than with FIRST_RUN's own order,
    which had the helper spend 5 s (the consensus, 4 s) on kernels the run
    could not use in time. Kernels already in the cache (:func:`cached`)
    are left out.
    """
    now = [k for k in reversed(FIRST_RUN) if k[0] not in DEFERRED]
    later = [k for k in FIRST_RUN if k[0] in DEFERRED]
    return [k for k in (*now, *later, *LATER) if not cached(k[0])]


def compile_ahead(kernels: ModuleType, parent: int) -> None:
    """Compile the kernels in :func:`ahead_order` while ``parent`` lives.

    The run that started the helper compiles from the first kernel on; once
    one reaches what the other has compiled, numba loads it from the cache.
    One helper per cache at a time (a lock file beside the cache, where the
    platform has ``fcntl``).
    """
    lock = _lock()
    if lock is False:
        return  # another helper compiles
    from numba.core.sigutils import normalize_signature

    try:
        for name, signature in ahead_order():
            if os.getppid() != parent:
                return
            args, _ = normalize_signature(signature)
            # a tuple of types, as a call from Python gives: the cache's key is what
            # compile gets
            getattr(kernels, name).compile(tuple(args))
    finally:
        if lock is not None:
            lock.close()


#: The helper's lock file in the cache folder: held while it compiles (:func:`compile_ahead`).
LOCK_FILE = "rangeseg-compile-ahead.lock"


def _lock() -> Any:
    """An exclusive lock (an open file) for the helper of this cache; False when held."""
    try:
        import fcntl
    except ImportError:
        return None
    folder = _cache_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
        handle = open(folder / LOCK_FILE, "w")  # noqa: SIM115
    except OSError:
        return None
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        handle.close()
        return False
    return handle
