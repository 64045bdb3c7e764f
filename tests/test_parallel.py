"""Threads within one image (rangeseg_cli.kernels.parallel): row bands give the same bits as one call.

Every kernel run on bands (edges of Sec. V-1, V-2; the split's local plane
fits) is checked against one call on the whole image, with bands of a few
rows so that every band edge falls among edges and creases.
"""

from __future__ import annotations

import os
import threading
import time
from concurrent.futures import Future

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rangeseg_cli.config import load_config
from rangeseg_cli.kernels import parallel
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.refine import planes
from rangeseg_cli.refine import split as split_module
from rangeseg_cli.stages.edges import detect_edges
from rangeseg_cli.synth.scenes import render_scene

CFG = load_config()


@pytest.fixture
def tiny_bands(monkeypatch):
    """Any image is cut into bands of a few rows; restores the automatic count after."""
    monkeypatch.setattr(parallel, "MIN_BAND_ROWS", 1)
    monkeypatch.setattr(parallel, "MIN_BAND_PIXELS", 1)
    monkeypatch.setattr(parallel, "MIN_TASKS_COST", 0)  # and any components split at once
    yield
    parallel.set_threads(None)


def pile(size: tuple[int, int] = (96, 112), noise: float = 1.0, seed: int = 3) -> np.ndarray:
    """A bin pile with invalid pixels: steps, creases, curved faces and holes."""
    z = render_scene("pile", size=size, noise=noise, seed=seed).image.astype(np.float64)
    z[np.random.default_rng(seed).random(z.shape) < 0.02] = np.nan
    return z


def in_threads(n: int, fn, *args, **kwargs):
    parallel.set_threads(n)
    try:
        return fn(*args, **kwargs)
    finally:
        parallel.set_threads(None)


@pytest.mark.parametrize("threads", [2, 3, 7])
@pytest.mark.parametrize("truncation", ["symmetric", "one-sided"])
def test_edges_on_bands_are_those_of_one_pass(tiny_bands, threads, truncation) -> None:
    config = load_config(overrides={"roof": {"truncation": truncation}})
    z = pile()
    whole = in_threads(1, detect_edges, z, config)
    banded = in_threads(threads, detect_edges, z, config)
    assert whole.roof_a.any() and whole.roof_b.any() and whole.step.any()
    for name in ("step", "roof_a", "roof_b", "codes"):
        np.testing.assert_array_equal(getattr(banded, name), getattr(whole, name), err_msg=name)


def test_edge_bands_with_fewer_rows_than_the_filter_reach(tiny_bands) -> None:
    # 7 bands of 3-4 rows: each band reads far more rows than it keeps.
    z = pile(size=(24, 40))
    whole = in_threads(1, detect_edges, z, CFG)
    banded = in_threads(7, detect_edges, z, CFG)
    np.testing.assert_array_equal(banded.codes, whole.codes)


@pytest.mark.parametrize("threads", [2, 5])
def test_local_planes_on_bands_are_bitwise_those_of_one_call(tiny_bands, threads) -> None:
    z = np.nan_to_num(pile(noise=0.5), nan=40.0)
    mask = z > np.median(z)
    whole = in_threads(1, planes.local_planes, z, mask, 2.0)
    banded = in_threads(threads, planes.local_planes, z, mask, 2.0)
    assert np.isfinite(whole[1]).sum() > 1000
    for a, b in zip(whole, banded, strict=True):
        np.testing.assert_array_equal(a, b)


def test_plane_heights_on_bands_are_bitwise_those_of_one_call(tiny_bands) -> None:
    z = np.nan_to_num(pile(noise=0.5), nan=40.0)
    mask = z > np.median(z)
    rows, cols = np.nonzero(np.arange(z.size).reshape(z.shape) % 3 == 0)
    whole = in_threads(1, split_module._plane_heights, z, mask, 4.0, rows, cols)
    banded = in_threads(4, split_module._plane_heights, z, mask, 4.0, rows, cols)
    assert np.isfinite(whole).sum() > 500
    np.testing.assert_array_equal(banded, whole)
    shuffled = np.random.default_rng(0).permutation(rows.size)  # not raster order: one call
    np.testing.assert_array_equal(
        in_threads(4, split_module._plane_heights, z, mask, 4.0, rows[shuffled],
                   cols[shuffled]), whole[shuffled])


def test_pipeline_labels_do_not_depend_on_the_threads(tiny_bands) -> None:
    z = pile(size=(80, 96), noise=1.0, seed=5)
    one = in_threads(1, run_pipeline, z, CFG)
    three = in_threads(3, run_pipeline, z, CFG)
    assert one.labels.max() > 3
    np.testing.assert_array_equal(three.edges, one.edges)
    np.testing.assert_array_equal(three.labels, one.labels)
    assert three.holdsite == one.holdsite


def test_row_bands_cover_every_row_once_and_read_their_margin() -> None:
    bands = parallel.row_bands(100, 3000, 5, count=3)
    assert [b[:2] for b in bands] == [(0, 33), (33, 67), (67, 100)]
    assert [b[2:] for b in bands] == [(0, 38), (28, 72), (62, 100)]
    assert parallel.row_bands(40, 40, 5, count=4) == [(0, 40, 0, 40)]  # too small to divide
    assert len(parallel.row_bands(128, 128, 5, count=2)) == 1  # not worth a thread
    assert len(parallel.row_bands(10_000, 10_000, 5, count=64)) == 64


def test_a_band_error_is_raised_to_the_caller(tiny_bands) -> None:
    parallel.set_threads(3)

    def run(first, stop, lo, hi):
        if first > 0:
            raise RuntimeError(f"band {first}")

    with pytest.raises(RuntimeError, match="band"):
        parallel.map_bands(run, 90, 90, 2)


@pytest.mark.parametrize("bad", [0, -1, 1.5, True, "2"])
def test_set_threads_refuses_what_is_not_a_count(bad) -> None:
    with pytest.raises(ValueError, match="threads"):
        parallel.set_threads(bad)


def test_threads_from_the_environment(monkeypatch) -> None:
    parallel.set_threads(None)
    monkeypatch.setenv("RANGESEG_THREADS", "3")
    assert parallel.thread_count() == 3
    assert parallel.per_process(2) == 3
    monkeypatch.setenv("RANGESEG_THREADS", "many")
    with pytest.raises(ValueError, match="RANGESEG_THREADS = 'many'"):
        parallel.thread_count()


def test_automatic_threads_share_the_cores(monkeypatch) -> None:
    parallel.set_threads(None)
    monkeypatch.delenv("RANGESEG_THREADS", raising=False)
    monkeypatch.setattr(parallel, "cores", lambda: 8)
    assert parallel.thread_count() == 8
    assert parallel.per_process(3) == 2
    assert parallel.per_process(16) == 1
    seen = []
    worker = threading.Thread(target=lambda: seen.append(parallel.thread_count()))
    worker.start()
    worker.join()
    assert seen == [1]  # a thread of someone else's pool does not divide its image again


def test_tasks_come_back_in_order_and_run_their_kernels_on_one_thread(tiny_bands) -> None:
    parallel.set_threads(2)
    out = parallel.map_tasks(lambda item: (item * 10, parallel.thread_count()), [1, 2, 3, 4],
                             cost=[1.0, 1.0, 5.0, 1.0])
    assert out == [(10, 1), (20, 1), (30, 1), (40, 1)]
    assert parallel.thread_count() == 2  # this thread is not a task


def test_the_pool_takes_the_costliest_tasks_first_and_this_thread_the_cheapest(
        tiny_bands, monkeypatch) -> None:
    calls = []

    class Inline:  # runs a submitted worker at once: it drains the queue, costliest first
        def submit(self, fn, *args):
            future = Future()
            future.set_result(fn(*args))
            return future

    monkeypatch.setattr(parallel, "_executor", lambda workers: Inline())
    parallel.set_threads(2)
    out = parallel.map_tasks(lambda item: calls.append(item) or str(item), [1, 2, 3, 4],
                             cost=[1.0, 2.0, 5.0, 0.5])
    assert out == list("1234") and calls == [3, 2, 1, 4]
    for shared in (False, True):
        ends = parallel._Ends(3, shared=shared)
        assert [ends.take(False), ends.take(True), ends.take(False), ends.take(True)] == \
            [2, 0, 1, None]


def test_many_tasks_on_real_threads_come_back_complete(tiny_bands, monkeypatch) -> None:
    monkeypatch.setattr(parallel, "MIN_PROCESS_ITEMS", 10_000)
    parallel.set_threads(3)
    items = list(range(200))
    out = parallel.map_tasks(lambda i: i * i, items, cost=[float(i % 7) for i in items])
    assert out == [i * i for i in items]


def test_a_task_error_is_raised_to_the_caller(tiny_bands) -> None:
    parallel.set_threads(2)

    def run(i):
        if i == 5:
            raise RuntimeError("task 5")
        return i

    with pytest.raises(RuntimeError, match="task 5"):
        parallel.map_tasks(run, list(range(10)), cost=[1.0] * 10)


def test_small_task_lists_stay_in_this_thread(monkeypatch) -> None:
    parallel.set_threads(2)
    names = parallel.map_tasks(lambda _: threading.current_thread().name, [0, 1],
                               cost=[10.0, 10.0])
    assert names == [threading.current_thread().name] * 2


# --------------------------------------------------------------------------- processes


@pytest.fixture
def in_processes(tiny_bands, monkeypatch):
    """Any list of two or more tasks goes to forked processes."""
    monkeypatch.setattr(parallel, "MIN_PROCESS_ITEMS", 2)
    monkeypatch.setattr(parallel, "ITEMS_PER_CHILD", 1)
    parallel.set_threads(2)


def test_many_tasks_go_to_a_forked_process_and_come_back_in_order(in_processes) -> None:
    def run(i):
        time.sleep(0.02)  # long enough for the child to take its share
        return i * i, os.getpid(), parallel.thread_count()

    items = list(range(30))
    out = parallel.map_tasks(run, items, cost=[float(i) for i in items])
    assert [o[0] for o in out] == [i * i for i in items]
    pids = {o[1] for o in out}
    assert os.getpid() in pids and len(pids) == 2  # this process and one child
    assert {o[2] for o in out} == {1}  # every task's kernels on one thread
    child = next(p for p in pids if p != os.getpid())
    assert out[-1][1] == child  # the costliest item went to the child
    assert out[0][1] == os.getpid()  # the cheapest stayed here
    with pytest.raises(ChildProcessError):  # the child has exited and been waited for
        os.waitpid(child, os.WNOHANG)


def test_an_error_in_a_process_is_raised_here(in_processes) -> None:
    def run(i):
        if i == 7:
            raise RuntimeError(f"task {i} in {os.getpid()}")
        return i

    with pytest.raises(RuntimeError, match=f"task 7 in {os.getpid()}"):  # re-run here
        parallel.map_tasks(run, list(range(10)), cost=[float(i) for i in range(10)])


def test_items_of_a_child_that_dies_are_run_here(in_processes) -> None:
    parent = os.getpid()

    def run(i):
        if os.getpid() != parent and i == 9:
            os._exit(3)  # killed, as by the out-of-memory killer
        return i + 100

    items = list(range(10))
    assert parallel.map_tasks(run, items, cost=[float(i) for i in items]) == \
        [i + 100 for i in items]


def test_results_that_do_not_pickle_are_made_here(in_processes) -> None:
    out = parallel.map_tasks(lambda i: (lambda: i), list(range(6)), cost=[1.0] * 6)
    assert [f() for f in out] == list(range(6))


def test_pipeline_labels_do_not_depend_on_processes(in_processes) -> None:
    z = pile(size=(96, 112), noise=2.0, seed=6)
    forked = run_pipeline(z, CFG)
    one = in_threads(1, run_pipeline, z, CFG)
    assert one.labels.max() > 3
    np.testing.assert_array_equal(forked.labels, one.labels)
    assert forked.holdsite == one.holdsite


def test_no_processes_from_another_thread(in_processes) -> None:
    seen = []

    def from_thread():
        parallel.set_threads(2)
        seen.append(parallel.map_tasks(lambda i: os.getpid(), list(range(30)),
                                       cost=[1.0] * 30))

    worker = threading.Thread(target=from_thread)
    worker.start()
    worker.join()
    assert set(seen[0]) == {os.getpid()}


def test_forking_can_be_turned_off(in_processes, monkeypatch) -> None:
    monkeypatch.setenv("RANGESEG_FORK", "0")
    pids = parallel.map_tasks(lambda i: os.getpid(), list(range(30)), cost=[1.0] * 30)
    assert set(pids) == {os.getpid()}


def test_a_failed_fork_leaves_the_work_to_this_process(in_processes, monkeypatch) -> None:
    def no_fork():
        raise OSError(12, "Cannot allocate memory")

    monkeypatch.setattr(os, "fork", no_fork)
    assert parallel.map_tasks(lambda i: (i, os.getpid()), list(range(30)), cost=[1.0] * 30) \
        == [(i, os.getpid()) for i in range(30)]


def test_children_are_few_for_few_items_and_capped() -> None:
    per, cap = parallel.ITEMS_PER_CHILD, parallel.MAX_CHILDREN
    assert parallel._child_count(2, 100) == 1
    assert parallel._child_count(1, 100) == 0
    assert parallel._child_count(64, per - 1) == 0
    assert parallel._child_count(64, 3 * per) == 3
    assert parallel._child_count(64, 1000 * per) == cap


def test_a_child_that_hangs_is_killed_and_its_items_run_here(in_processes, monkeypatch) -> None:
    monkeypatch.setattr(parallel, "CHILD_PATIENCE", 0.5)
    parent = os.getpid()

    def run(i):
        if os.getpid() != parent:
            time.sleep(60)  # as if a lock held at the fork never came free
        return i * 3

    started = time.perf_counter()
    assert parallel.map_tasks(run, list(range(12)), cost=[float(i) for i in range(12)]) == \
        [i * 3 for i in range(12)]
    assert time.perf_counter() - started < 20


@settings(max_examples=20, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(costs=st.lists(st.floats(0.0, 1e6), min_size=2, max_size=60))
def test_forked_tasks_give_what_one_after_the_other_gives(in_processes, costs) -> None:
    items = list(range(len(costs)))
    out = parallel.map_tasks(lambda i: (i, np.arange(i % 7) * costs[i]), items, cost=costs)
    assert [o[0] for o in out] == items
    for (_, got), i in zip(out, items, strict=True):
        np.testing.assert_array_equal(got, np.arange(i % 7) * costs[i])
