"""Threads (and processes) within one image: row bands of a kernel, and independent pieces.

Beyond the paper (an implementation matter). The compiled kernels release
the GIL (``nogil``), so Python threads run them on several cores. A kernel
whose output row depends only on the input rows within a fixed reach of it
(the AR of Sec. V-1, V-2 and its maxima; the Gaussian-weighted plane fits of
the split) is run on horizontal bands of the image (:func:`map_bands`), each
band with ``margin`` extra rows either side, and each band keeps its own
rows: the same values bit for bit as one call on the whole image. Pieces of
work that do not depend on each other (the components the split divides,
the recut's candidates) are shared out (:func:`map_tasks`) and their results
used in their order: the same result as one after the other. A few pieces
share the threads; many (:data:`MIN_PROCESS_ITEMS`) go to processes forked
for the call (:func:`map_processes`, Linux): their work is mostly Python,
on which threads take turns (the GIL).

How many threads (:func:`thread_count`; the processes of a call are this
count, the caller's included): :func:`set_threads` (or the environment
variable ``RANGESEG_THREADS``); unset, every core this process may use when
called from the main thread, and one thread from any other thread (a Dask
worker's or a caller's own thread pool, which already keeps the cores
busy). ``rangeseg run --jobs N`` gives each of its N worker processes
``cores // N`` threads.

While a pipeline runs with more than one thread, BLAS (OpenBLAS under
numpy) is held to one thread (:func:`blas_one_thread`): its matrices here
are 6x6 normal equations, and its idle threads spin for a while after each
call, taking the core a band needs (measured: the bands' AR passes 6.4 ms
with BLAS on one thread, 10.3 ms with it on two, against 9.4 ms unbanded).
"""

from __future__ import annotations

import contextlib
import functools
import mmap
import multiprocessing
import os
import pickle
import select
import signal
import struct
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

import numpy as np

from .cache import skip_helper

T = TypeVar("T")
R = TypeVar("R")

#: Fewest rows a band gets (below this the image is not divided).
MIN_BAND_ROWS = 32
#: Fewest pixels of a band: smaller work is not worth a thread's hand-over (a 128x128
#: frame is one band: two were 4 % slower in a batch of such frames).
MIN_BAND_PIXELS = 32768

#: Least total cost (pixels) of :func:`map_tasks`' items to share them among threads
#: (measured: 128x128 frames got slower with their components on two threads).
MIN_TASKS_COST = 65536

#: Fewest items :func:`map_tasks` gives to processes rather than threads. Measured (2
#: cores): the SR300 frame's split rounds (71, 100 components) and recut (379
#: candidates) took 336 / 394 / 363 ms in one thread, 259 / 333 / 336 on two threads,
#: 204 / 219 / 203 in two processes; a 640x480 pile's split (6 components, the bin's
#: floor 2/3 of the work) 161 ms, 120 and 146 (a fork of this 200 MB process costs
#: about 9 ms, and the floor's kernels release the GIL).
MIN_PROCESS_ITEMS = 24

#: :func:`map_processes` forks at most one child per this many items, and at most
#: ``MAX_CHILDREN``: this process forks them one after the other (about 9 ms each here,
#: more for a larger process), and a child must have enough work to be worth it. (Not
#: measured beyond 2 cores.)
ITEMS_PER_CHILD, MAX_CHILDREN = 8, 7

#: Seconds a forked child may take beyond 10 times this process's own share before it
#: is taken for hung and killed (its pieces are then done here).
CHILD_PATIENCE = 60.0

_requested: int | None = None
_inside = threading.local()  # .task: this thread runs a task of map_tasks
_pool: ThreadPoolExecutor | None = None
_pool_size = 0
_lock = threading.Lock()


def cores() -> int:
    """The cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _from_environment() -> int | None:
    """``RANGESEG_THREADS`` as a positive int; None when unset or empty."""
    text = os.environ.get("RANGESEG_THREADS", "").strip()
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise ValueError(f"RANGESEG_THREADS = {text!r}: expected a whole number >= 1")
    return value


def set_threads(n: int | None) -> None:
    """Use ``n`` threads per image from now on in this process (None: automatic).

    Parameters
    ----------
    n
        Threads, at least 1; None restores the automatic choice (see the
        module's notes).

    Raises
    ------
    ValueError
        When ``n`` is not a whole number >= 1.
    """
    global _requested
    if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
        raise ValueError(f"threads = {n!r}: expected a whole number >= 1 (or None: automatic)")
    _requested = n


def thread_count() -> int:
    """Threads the kernels of one image may use now (see the module's notes).

    1 inside :func:`map_tasks` (its tasks already share the threads out).
    """
    if getattr(_inside, "task", False):
        return 1
    if _requested is not None:
        return _requested
    env = _from_environment()
    if env is not None:
        return env
    return cores() if threading.current_thread() is threading.main_thread() else 1


def per_process(processes: int) -> int:
    """Threads of each of ``processes`` worker processes (``--jobs``).

    :func:`set_threads` or ``RANGESEG_THREADS`` when set, else the cores
    shared out: ``cores // processes``, at least 1.
    """
    if _requested is not None:
        return _requested
    env = _from_environment()
    return env if env is not None else max(1, cores() // max(processes, 1))


def row_bands(height: int, width: int, margin: int, count: int | None = None
              ) -> list[tuple[int, int, int, int]]:
    """Bands of rows for :func:`map_bands`: (first, stop, first read, stop read).

    Rows ``first..stop-1`` are the band's own; the kernel reads rows
    ``first read..stop read-1``, ``margin`` more either side (clipped to the
    image). At most ``count`` bands (default :func:`thread_count`), none
    below :data:`MIN_BAND_ROWS` rows or :data:`MIN_BAND_PIXELS` pixels.
    """
    fit = min(height // MIN_BAND_ROWS, (height * width) // MIN_BAND_PIXELS)
    if fit > 1 and count is None:  # else one band whatever the threads
        count = thread_count()
    k = max(1, min(count or 1, fit))
    edges = [round(i * height / k) for i in range(k + 1)]
    return [(a, b, max(a - margin, 0), min(b + margin, height))
            for a, b in zip(edges[:-1], edges[1:], strict=True)]


def map_bands(run: Callable[[int, int, int, int], None], height: int, width: int,
              margin: int) -> None:
    """Call ``run(first, stop, first_read, stop_read)`` for each band, at once.

    The first band runs in this thread, the others in a process-wide pool;
    every band is finished when this returns, and an error of any band is
    raised here.
    """
    bands = row_bands(height, width, margin)
    if len(bands) == 1:
        run(*bands[0])
        return
    pool = _executor(len(bands) - 1)
    futures: list[Future[None]] = [pool.submit(run, *band) for band in bands[1:]]
    try:
        run(*bands[0])
    finally:
        for future in futures:
            future.result()


def map_pixel_bands(run: Callable[[int, int, int, int], None], rows: np.ndarray, height: int,
                    width: int, margin: int) -> None:
    """:func:`map_bands` over pixels in raster order: ``run(i, j, first_read, stop_read)``.

    ``rows`` (ascending) are the pixels' rows; each band with pixels gets
    those of its own rows, ``i..j-1``, and reads the rows of its band.
    """
    def band(first: int, stop: int, lo: int, hi: int) -> None:
        i, j = np.searchsorted(rows, (first, stop))
        if j > i:
            run(int(i), int(j), lo, hi)

    map_bands(band, height, width, margin)


def map_tasks(run: Callable[[T], R], items: Sequence[T], cost: Sequence[float] | None = None
              ) -> list[R]:
    """``[run(item) for item in items]``, the items shared among threads or processes.

    For independent pieces of one image (the components the split divides,
    the recut's candidates). With more than one thread (:func:`thread_count`)
    and item, and a total ``cost`` (pixels) of :data:`MIN_TASKS_COST` or
    more, the items are taken in order of cost: the others take the
    costliest first, this thread the cheapest first, until they meet (a
    large item starts at once). Inside the tasks the kernels run on one
    thread each. The results come back in the order of ``items``.

    A few items share this process's threads: their time goes mostly to
    compiled kernels, which release the GIL. :data:`MIN_PROCESS_ITEMS` or
    more go to forked processes (:func:`map_processes`): many small items
    are mostly Python, whose turns on the GIL would leave the second core
    idle. Small work stays in this thread.
    """
    threads = min(thread_count(), len(items))
    if threads <= 1 or cost is None or sum(cost) < MIN_TASKS_COST:
        return [run(item) for item in items]
    if len(items) >= MIN_PROCESS_ITEMS and _can_fork():
        return map_processes(run, items, cost)  # else as a few, on threads
    order = sorted(range(len(items)), key=lambda i: -cost[i])
    queue = _Ends(len(order))
    results: list[Any] = [None] * len(items)

    def work(costliest_first: bool) -> None:
        while (k := queue.take(costliest_first)) is not None:
            results[order[k]] = run(items[order[k]])

    pool = _executor(threads - 1)
    futures = [pool.submit(_as_task, work, True) for _ in range(threads - 1)]
    try:
        _as_task(work, False)
    finally:
        for future in futures:
            future.result()
    return results


def map_processes(run: Callable[[T], R], items: Sequence[T], cost: Sequence[float]
                  ) -> list[R]:
    """``[run(item) for item in items]``, the items shared with forked processes.

    For independent pieces of one image whose work is mostly Python (the
    split's components, the recut's candidates): threads would take turns
    on the GIL, processes do not. The results come back in the order of
    ``items``: the same values as one after the other here (results that do
    not pickle are made here again).

    With :func:`thread_count` ``k`` above 1, a total ``cost`` of
    :data:`MIN_TASKS_COST` pixels or more (on Linux, in the main thread, not
    in a daemon process), this process forks ``k - 1`` children for the call
    (at most one per :data:`ITEMS_PER_CHILD` items, and :data:`MAX_CHILDREN`).
    They see ``run`` and the items as they are (no copying), take the items
    costliest first while this process takes the cheapest first, until they
    meet; each child sends its results back when it is done and exits. An
    item a child could not finish (an error, or the child killed) is run
    here, so its error is raised here. Inside, the kernels use one thread.
    Otherwise everything runs here. The environment variable
    ``RANGESEG_FORK=0`` turns forking off (for a host program whose
    libraries must not be forked): many tasks then share the threads as a
    few do.
    """
    children = _child_count(thread_count(), len(items))
    if children < 1 or sum(cost) < MIN_TASKS_COST or not _can_fork():
        return [run(item) for item in items]
    order = sorted(range(len(items)), key=lambda i: -cost[i])
    try:
        ends = _Ends(len(order), shared=True)
    except OSError:  # no shared semaphores here (a locked-down container): all here
        return [run(item) for item in items]
    forked: list[tuple[int, int]] = []
    results: dict[int, Any] = {}
    try:
        with warnings.catch_warnings():  # 3.12+: forking while the band threads exist
            warnings.simplefilter("ignore", DeprecationWarning)
            for _ in range(children):
                try:
                    forked.append(_fork_child(run, items, order, ends))
                except OSError:  # out of memory or processes, no pipe: fewer children
                    break
        start = time.perf_counter()
        while (k := ends.take(False)) is not None:
            results[order[k]] = _as_task(run, items[order[k]])
        patience = CHILD_PATIENCE + 10.0 * (time.perf_counter() - start)
        for pid, fd in forked:
            results.update(_child_results(pid, fd, patience))
    finally:
        for pid, fd in forked:
            _reap(pid, fd)
    for i in range(len(items)):  # left by a child that failed: here, errors and all
        if i not in results:
            results[i] = _as_task(run, items[i])
    return [results[i] for i in range(len(items))]


def _child_count(threads: int, items: int) -> int:
    """Children :func:`map_processes` forks for ``items`` with ``threads`` (0: none)."""
    return max(0, min(threads - 1, items // ITEMS_PER_CHILD, MAX_CHILDREN))


def _can_fork() -> bool:
    """Whether :func:`map_processes` may fork here (see there; ``RANGESEG_FORK=0``: never)."""
    return (sys.platform.startswith("linux") and hasattr(os, "fork")
            and os.environ.get("RANGESEG_FORK", "").strip() != "0"
            and threading.current_thread() is threading.main_thread()
            and not multiprocessing.current_process().daemon)


def _fork_child(run: Callable[[T], R], items: Sequence[T], order: list[int],
                ends: _Ends) -> tuple[int, int]:
    """Fork a child that runs items costliest first and pickles ``{index: result}`` back."""
    read, write = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        os.close(read)
        os.close(write)
        raise
    if pid:
        os.close(write)
        return pid, read
    code = 1
    try:  # the child: never returns into the caller's code
        os.close(read)
        _inside.task = True
        skip_helper()
        done: dict[int, Any] = {}
        try:
            while (k := ends.take(True)) is not None:
                done[order[k]] = run(items[order[k]])
        except Exception:  # noqa: BLE001 - the parent runs this item again and raises
            pass
        with os.fdopen(write, "wb") as out:
            pickle.dump(done, out, protocol=pickle.HIGHEST_PROTOCOL)
        code = 0
    finally:
        os._exit(code)


def _child_results(pid: int, fd: int, patience: float) -> dict[int, Any]:
    """A child's results; empty when it died before sending them or sent none in time.

    A child that has not begun to send within ``patience`` seconds is taken
    for hung (a lock held at the fork, which should not happen) and killed:
    its items are then run here, late but right.
    """
    poll = select.poll()  # not select.select: no limit on the descriptor's number
    poll.register(fd, select.POLLIN | select.POLLHUP | select.POLLERR)
    if not poll.poll(patience * 1000.0):
        os.kill(pid, signal.SIGKILL)
        return {}
    with os.fdopen(os.dup(fd), "rb") as pipe:
        try:
            got = pickle.load(pipe)
        except Exception:  # noqa: BLE001 - cut short (the child died): its items run here
            return {}
    return got if isinstance(got, dict) else {}


def _reap(pid: int, fd: int) -> None:
    """Close a child's pipe and wait for it (killed first when it is still running)."""
    os.close(fd)
    try:
        done, _ = os.waitpid(pid, os.WNOHANG)
        if not done:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
    except ChildProcessError:  # pragma: no cover - reaped already
        pass


class _Ends:
    """Indices 0..n-1 taken from either end, each once, under a lock.

    With ``shared`` the two ends live in shared memory under a
    process-shared lock, so that children forked afterwards take from the
    same queue (:func:`map_processes`); an OSError where the system has no
    such locks.
    """

    def __init__(self, n: int, shared: bool = False) -> None:
        self._ends: mmap.mmap | bytearray
        if shared:
            self._ends = mmap.mmap(-1, 16)  # MAP_SHARED: seen by forked children
            self._lock: Any = multiprocessing.get_context("fork").Lock()
        else:
            self._ends = bytearray(16)
            self._lock = threading.Lock()
        self._ends[:] = struct.pack("qq", 0, n)

    def take(self, first: bool) -> int | None:
        with self._lock:
            lo, hi = struct.unpack("qq", self._ends[:])
            if lo >= hi:
                return None
            lo, hi, k = (lo + 1, hi, lo) if first else (lo, hi - 1, hi - 1)
            self._ends[:] = struct.pack("qq", lo, hi)
            return k


def _as_task(run: Callable[[T], R], item: T) -> R:
    """``run(item)`` with this thread marked as running a task of :func:`map_tasks`."""
    _inside.task = True
    try:
        return run(item)
    finally:
        _inside.task = False


def _executor(workers: int) -> ThreadPoolExecutor:
    """The process-wide pool, with at least ``workers`` threads."""
    global _pool, _pool_size
    with _lock:
        if _pool is None or _pool_size < workers:
            if _pool is not None:
                _pool.shutdown(wait=False)
            _pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="rangeseg")
            _pool_size = workers
        return _pool


@functools.cache
def _blas_controller() -> Any:
    """Controller of the loaded BLAS libraries (threadpoolctl; made once, about 1 ms)."""
    from threadpoolctl import ThreadpoolController

    return ThreadpoolController()


@contextlib.contextmanager
def blas_one_thread(shared: bool = True) -> Iterator[None]:
    """BLAS on one thread inside the block when the kernels use more than one.

    ``shared=False`` says that the block's work runs in this thread alone
    (one band, no pieces shared out): BLAS is then left as it is, which
    saves threadpoolctl's cost (about 0.1 ms, most of a 128x128 frame's
    overhead).
    """
    if thread_count() == 1 or not shared:  # thread_count first: it checks RANGESEG_THREADS
        yield
        return
    with _blas_controller().limit(limits=1, user_api="blas"):
        yield


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist here."""
    global _pool, _pool_size, _lock
    _pool, _pool_size, _lock = None, 0, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)
