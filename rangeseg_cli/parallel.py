"""Threads within one image: row bands of a kernel, and independent pieces, at once.

Beyond the paper (an implementation matter). The compiled kernels release
the GIL (``nogil``), so Python threads run them on several cores. A kernel
whose output row depends only on the input rows within a fixed reach of it
(the AR of Sec. V-1, V-2 and its maxima; the Gaussian-weighted plane fits of
the split) is run on horizontal bands of the image (:func:`map_bands`), each
band with ``margin`` extra rows either side, and each band keeps its own
rows: the same values bit for bit as one call on the whole image. Pieces of
work that do not depend on each other (the components the split divides)
are shared among the threads (:func:`map_tasks`) and their results used in
their order: the same result as one after the other.

How many threads (:func:`thread_count`): :func:`set_threads` (or the
environment variable ``RANGESEG_THREADS``); unset, every core this process
may use when called from the main thread, and one thread from any other
thread (a Dask worker's or a caller's own thread pool, which already keeps
the cores busy). ``rangeseg run --jobs N`` gives each of its N worker
processes ``cores // N`` threads.

While a pipeline runs with more than one thread, BLAS (OpenBLAS under
numpy) is held to one thread (:func:`blas_one_thread`): its matrices here
are 6x6 normal equations, and its idle threads spin for a while after each
call, taking the core a band needs (measured: the bands' AR passes 6.4 ms
with BLAS on one thread, 10.3 ms with it on two, against 9.4 ms unbanded).
"""

from __future__ import annotations

import contextlib
import functools
import os
import threading
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

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
    count = thread_count() if count is None else count
    fit = min(height // MIN_BAND_ROWS, (height * width) // MIN_BAND_PIXELS)
    k = max(1, min(count, fit))
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


def map_tasks(run: Callable[[T], R], items: Sequence[T], cost: Sequence[float] | None = None
              ) -> list[R]:
    """``[run(item) for item in items]``, the items shared among the threads.

    For independent pieces of one image (the components the split divides).
    With more than one thread (:func:`thread_count`) and item, and a total
    ``cost`` (pixels) of :data:`MIN_TASKS_COST` or more, the items are
    taken in order of cost: the pool's threads take the costliest first,
    this thread the cheapest first, until they meet (a large item starts at
    once, and this thread's GIL-bound small ones overlap with it). Inside
    the tasks the kernels run on one thread each. The results come back in
    the order of ``items``. Small work stays in this thread: the tasks'
    Python code takes turns on the GIL, and on many small tasks the turns
    cost more than the second core gives.
    """
    threads = min(thread_count(), len(items))
    if threads <= 1 or cost is None or sum(cost) < MIN_TASKS_COST:
        return [run(item) for item in items]
    queue = _Ends(sorted(range(len(items)), key=lambda i: -cost[i]))
    results: list[Any] = [None] * len(items)

    def work(costliest_first: bool) -> None:
        while (i := queue.take(costliest_first)) is not None:
            results[i] = run(items[i])

    pool = _executor(threads - 1)
    futures = [pool.submit(_as_task, work, True) for _ in range(threads - 1)]
    try:
        _as_task(work, False)
    finally:
        for future in futures:
            future.result()
    return results


class _Ends:
    """Indices taken from either end of a list, each once, under a lock."""

    def __init__(self, order: list[int]) -> None:
        self._order, self._lo, self._hi = order, 0, len(order)
        self._lock = threading.Lock()

    def take(self, first: bool) -> int | None:
        with self._lock:
            if self._lo >= self._hi:
                return None
            if first:
                self._lo += 1
                return self._order[self._lo - 1]
            self._hi -= 1
            return self._order[self._hi]


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
def blas_one_thread() -> Iterator[None]:
    """BLAS on one thread inside the block when the kernels use more than one."""
    if thread_count() == 1:
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
