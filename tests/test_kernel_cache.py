"""The first run says on stderr that it compiles the kernels; later runs say nothing."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from rangeseg_cli.cli.main import main
from rangeseg_cli.kernels import cache as kernel_cache


@pytest.fixture
def package(tmp_path, monkeypatch):
    """A copy of the kernels' source with an empty cache beside it."""
    source = tmp_path / "compiled.py"
    source.write_text("# kernels\n")
    (tmp_path / "__pycache__").mkdir()
    monkeypatch.setattr(kernel_cache, "SOURCE", source)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.delenv("RANGESEG_PURE_NUMPY", raising=False)
    return tmp_path


def index(folder: Path, age: float = 0.0) -> Path:
    path = folder / "compiled.edges_pass-196.py311.nbi"
    path.write_bytes(b"")
    stamp = (folder.parent / "compiled.py").stat().st_mtime + age
    os.utime(path, (stamp, stamp))
    return path


def test_an_empty_cache_is_cold(package):
    assert kernel_cache.cold_kernel_cache()


def test_an_index_newer_than_the_source_is_warm(package):
    index(package / "__pycache__", age=5.0)
    assert not kernel_cache.cold_kernel_cache()


def test_an_index_older_than_the_source_is_cold(package):
    index(package / "__pycache__", age=-5.0)
    assert kernel_cache.cold_kernel_cache()


def test_an_older_index_of_the_same_source_is_warm(package):
    # numba 0.68 stamps an index with the source's SHA-256, not its time: a checkout
    # or a reinstall that rewrites the same source leaves the cache valid. Read as
    # cold, every run printed the compiling message and ran the numpy references.
    source = package / "compiled.py"
    path = index(package / "__pycache__", age=-5.0)
    path.write_bytes(b"\x80\x05header" + hashlib.sha256(source.read_bytes()).digest() + b"tail")
    stamp = source.stat().st_mtime - 5.0
    os.utime(path, (stamp, stamp))
    assert not kernel_cache.cold_kernel_cache()
    assert kernel_cache.cached("edges_pass")
    source.write_text("# kernels, edited\n")  # a new source: the same index is stale
    os.utime(source, (stamp + 10.0, stamp + 10.0))
    assert kernel_cache.cold_kernel_cache()
    assert not kernel_cache.cached("edges_pass")


def test_a_cache_under_numba_cache_dir_counts(package, tmp_path, monkeypatch):
    elsewhere = tmp_path / "cache" / "some" / "path"
    elsewhere.mkdir(parents=True)
    path = elsewhere / "compiled.edges_pass-196.py311.nbi"
    path.write_bytes(b"")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert not kernel_cache.cold_kernel_cache()


def test_pure_numpy_compiles_nothing(package, monkeypatch):
    monkeypatch.setenv("RANGESEG_PURE_NUMPY", "1")
    assert not kernel_cache.cold_kernel_cache()


def test_a_cold_cache_is_said_on_stderr_and_json_stays_clean(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_cache, "cold_kernel_cache", lambda: True)
    image = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic" / "part1-n0.png"
    runner = CliRunner()
    done = runner.invoke(main, ["run", str(image), "-o", str(tmp_path / "o"), "--json"])
    assert done.exit_code == 0, done.stderr
    assert "compiling the numba kernels" in done.stderr
    assert json.loads(done.stdout)["done"] == 1
    quiet = runner.invoke(main, ["run", str(image), "-o", str(tmp_path / "q"), "-q"])
    assert quiet.exit_code == 0 and "compiling" not in quiet.stderr


def test_a_warm_cache_says_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_cache, "cold_kernel_cache", lambda: False)
    image = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic" / "part1-n0.png"
    done = CliRunner().invoke(main, ["run", str(image), "-o", str(tmp_path / "o"), "--json"])
    assert done.exit_code == 0 and "compiling" not in done.stderr


requires_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                                    reason="numba is not installed")


@requires_numba
def test_the_kernels_compiled_ahead_are_those_a_default_run_calls(monkeypatch):
    """FIRST_RUN: the kernels a default run calls from Python, their types, in that order.

    The helper compiles exactly these signatures into the cache, for the run to load.
    """
    from numba import typeof
    from numba.core.registry import CPUDispatcher
    from numba.core.sigutils import normalize_signature

    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.pipeline import run_pipeline
    from rangeseg_cli.synth.scenes import render_scene

    monkeypatch.delenv("RANGESEG_PURE_NUMPY", raising=False)
    monkeypatch.setenv("RANGESEG_THREADS", "1")
    later = {name for name, _ in kernel_cache.LATER}  # a first run does without these
    monkeypatch.setattr(kernel_cache, "_ready", set(kernel_cache.DEFERRED) - later)
    monkeypatch.setattr(kernel_cache, "cached", lambda name: name not in later)
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: None)
    calls: list[tuple[str, tuple]] = []

    def recording(name, dispatcher):
        def call(*args):
            key = (name, tuple(typeof(a) for a in args))
            if key not in calls:
                calls.append(key)
            return dispatcher(*args)
        return call

    for name, value in vars(_kernels).copy().items():
        if isinstance(value, CPUDispatcher):
            monkeypatch.setattr(_kernels, name, recording(name, value))
    run_pipeline(render_scene("pile", size=(128, 128), noise=1.0, seed=0).image)
    listed = [(name, tuple(normalize_signature(sig)[0])) for name, sig in kernel_cache.FIRST_RUN]
    assert [c for c in calls if c[0] != "heights"] == listed


class _Dispatcher:
    """A stand-in for the dispatcher of numba's ``numba:compile`` event."""

    def __init__(self, module):
        self.py_func = type("F", (), {"__module__": module})()


def test_the_first_kernel_compiled_starts_one_helper(monkeypatch):
    started = []
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: started.append(1))
    monkeypatch.setattr(kernel_cache, "_asked", False)
    kernel_cache._on_compile(_Dispatcher("numba.np.arraymath"))
    assert started == []  # numba's own code does not count
    for _ in range(2):
        kernel_cache._on_compile(_Dispatcher("rangeseg_cli.kernels.compiled"))
    assert started == [1]


@pytest.mark.parametrize("variable", ["RANGESEG_COMPILE_AHEAD", "RANGESEG_COMPILING_AHEAD"])
def test_no_helper_when_switched_off_or_in_the_helper(monkeypatch, variable):
    monkeypatch.setenv(variable, "0" if variable == "RANGESEG_COMPILE_AHEAD" else "1")
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: pytest.fail("helper started"))
    kernel_cache.compile_ahead_when_cold()  # registers nothing, so starts nothing


def test_one_helper_per_cache(tmp_path, monkeypatch):
    pytest.importorskip("fcntl")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    held = kernel_cache._lock()
    assert held
    assert kernel_cache._lock() is False
    held.close()
    again = kernel_cache._lock()
    assert again
    again.close()


@requires_numba
def test_the_helper_stops_once_its_run_has_ended(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))

    class Kernels:
        def __getattr__(self, name):
            pytest.fail(f"{name} compiled for a run that has ended")

    kernel_cache.compile_ahead(Kernels(), parent=-1)  # not this process's parent


def test_a_deferred_kernel_runs_once_compiled_or_cached(tmp_path, monkeypatch):
    # the first run after installing takes the numpy reference (the same bits) for
    # these; the helper compiles them meanwhile and later runs load them
    monkeypatch.setattr(kernel_cache, "_ready", set())
    monkeypatch.setattr(kernel_cache, "_looked", {})
    monkeypatch.setattr(kernel_cache, "RECHECK_S", 0.0)
    monkeypatch.setattr(kernel_cache, "_cache_dir", lambda: tmp_path)
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: None)

    class Dispatcher:  # nothing compiled in this process
        overloads: dict = {}

    kernels = type("Kernels", (), {name: Dispatcher() for name in kernel_cache.DEFERRED})
    assert not kernel_cache.ready(kernels, "crease_votes")
    (tmp_path / "cache").mkdir()
    (tmp_path / "cache" / "compiled.crease_votes-2450.py311.nbi").write_bytes(b"")
    assert kernel_cache.ready(kernels, "crease_votes")
    assert not kernel_cache.ready(kernels, "neighbour_accepts")
    Dispatcher.overloads = {"(int64,)": object()}  # compiled here
    assert kernel_cache.ready(kernels, "neighbour_accepts")


def test_a_kernel_not_ready_is_looked_for_at_most_once_per_recheck_interval(tmp_path,
                                                                              monkeypatch):
    # the consensus asks thousands of times a frame: one directory listing per interval
    clock = [100.0]
    monkeypatch.setattr(kernel_cache.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: None)
    monkeypatch.setattr(kernel_cache, "_ready", set())
    monkeypatch.setattr(kernel_cache, "_looked", {})
    monkeypatch.setattr(kernel_cache, "_cache_dir", lambda: tmp_path)

    class Dispatcher:
        overloads: dict = {}

    kernels = type("Kernels", (), {name: Dispatcher() for name in kernel_cache.DEFERRED})
    name = kernel_cache.DEFERRED[-1]
    assert not kernel_cache.ready(kernels, name)
    (tmp_path / f"compiled.{name}-1.py311.nbi").write_bytes(b"")  # the helper is done
    clock[0] += kernel_cache.RECHECK_S / 2
    assert not kernel_cache.ready(kernels, name)  # not looked for again yet
    clock[0] += kernel_cache.RECHECK_S
    assert kernel_cache.ready(kernels, name)


def test_select_deferred_gives_the_reference_until_the_kernel_is_ready(monkeypatch):
    from rangeseg_cli.kernels import backend

    kernels = backend.select_kernels("numba")
    name = kernel_cache.DEFERRED[-1]
    monkeypatch.setattr(backend, "_USE_NUMBA", True)  # "auto" picks numba (installed)
    monkeypatch.setattr(backend, "ready", lambda found, which: False)  # cold cache
    assert backend.select_deferred("auto", name) is None
    assert backend.select_deferred("numba", name) is kernels  # asked for by name
    assert backend.select_deferred("numpy", name) is None
    monkeypatch.setattr(backend, "ready", lambda found, which: which == name)
    assert backend.select_deferred("auto", name) is kernels


def test_a_run_missing_a_deferred_kernel_starts_the_helper_once(tmp_path, monkeypatch):
    # the first run's helper may end before it reaches the deferred kernels (they come
    # last); a later run that finds one uncompiled asks for the helper again
    started = []
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: started.append(1))
    monkeypatch.setattr(kernel_cache, "_asked", False)
    monkeypatch.setattr(kernel_cache, "_ready", set())
    monkeypatch.setattr(kernel_cache, "_looked", {})
    monkeypatch.setattr(kernel_cache, "RECHECK_S", 0.0)
    monkeypatch.setattr(kernel_cache, "_cache_dir", lambda: tmp_path)
    monkeypatch.delenv("RANGESEG_COMPILE_AHEAD", raising=False)
    monkeypatch.delenv("RANGESEG_COMPILING_AHEAD", raising=False)

    class Dispatcher:
        overloads: dict = {}

    kernels = type("Kernels", (), {name: Dispatcher() for name in kernel_cache.DEFERRED})
    for name in kernel_cache.DEFERRED:
        assert not kernel_cache.ready(kernels, name)
    assert started == [1]


def test_the_helper_compiles_what_the_first_run_waits_for_last_first_then_the_rest(
        tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_cache, "_cache_dir", lambda: tmp_path)
    order = [name for name, _ in kernel_cache.ahead_order()]
    first_run = [name for name, _ in kernel_cache.FIRST_RUN]
    waits = [name for name in first_run if name not in kernel_cache.DEFERRED]
    deferred = [name for name in first_run if name in kernel_cache.DEFERRED]
    later = [name for name, _ in kernel_cache.LATER]
    assert deferred  # the run does without these until they are ready: after the others
    assert order == waits[::-1] + deferred + later
    assert set(later) <= set(kernel_cache.DEFERRED) and not set(later) & set(first_run)
    (tmp_path / f"compiled.{later[0]}-1.py311.nbi").write_bytes(b"")  # cached: skipped
    assert [name for name, _ in kernel_cache.ahead_order()] == waits[::-1] + deferred + later[1:]


def test_a_forked_child_of_a_pass_never_starts_the_helper(monkeypatch):
    started = []
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: started.append(1))
    monkeypatch.setattr(kernel_cache, "_asked", False)
    monkeypatch.delenv("RANGESEG_COMPILE_AHEAD", raising=False)
    monkeypatch.delenv("RANGESEG_COMPILING_AHEAD", raising=False)
    kernel_cache.skip_helper()  # what parallel.map_processes' children call first
    kernel_cache._ask_helper()
    assert started == []


@requires_numba
def test_the_kernels_conditioning_bound_is_the_region_fits():
    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.stages.grow import RCOND

    assert _kernels._RCOND == RCOND


@requires_numba
def test_the_later_kernels_signatures_are_those_their_callers_give(monkeypatch):
    from numba import typeof
    from numba.core.sigutils import normalize_signature

    from rangeseg_cli.cell.workspace import plane_shares
    from rangeseg_cli.config import Config
    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.refine import facets, recut, split
    from rangeseg_cli.stages.grow import union_sse

    # best_knot calls knot_sse inside compiled code: compiled before knot_sse is wrapped
    recut.best_knot(np.arange(9), np.arange(9), np.arange(9.0), np.array([0.0, 1.0]),
                    recut.CREASE, backend="numba")
    seen: dict[str, list] = {}
    for name, _ in kernel_cache.LATER:
        real = getattr(_kernels, name)
        monkeypatch.setattr(_kernels, name, lambda *args, name=name, real=real: seen.setdefault(
            name, []).append(tuple(typeof(a) for a in args)) or real(*args))
    y, x = np.mgrid[0:20, 0:20].astype(np.float64)
    z = np.minimum(x, 20.0 - x) + 0.1 * y
    rows, cols = np.nonzero(np.ones_like(z, bool))
    pixels = (rows, cols, rows.astype(np.float64), cols.astype(np.float64),
              facets.neighbour_table(rows, cols, z.shape))
    facets._passes(z, pixels, [np.array([0.0, 1.0, 0.1]), np.array([20.0, -1.0, 0.1])], 1.0,
                   backend="numba")
    recut.best_knot(rows, cols, z[rows, cols], np.array([0.0, 1.0]), recut.CREASE,
                    backend="numba")
    halves = np.where(x < 10, 1, 2).astype(np.int32)
    frame = split._Frame.of(halves > 0, Config().split, "numba")
    split._clean(halves, frame)
    split._reassign(z, halves, frame)
    union_sse(z, halves, np.array([[1, 2]], np.int64), np.array([[0, 20, 0, 20]], np.int64),
              backend="numba")
    plane_shares(np.ones((3, 2)), np.zeros(2), 1.0, backend="numba")
    recut.knot_sse(rows, cols, z[rows, cols], np.array([0.0, 1.0]), np.array([5.0, 9.0]),
                   recut.CREASE, backend="numba")
    assert {name: calls[0] for name, calls in seen.items()} == {
        name: tuple(normalize_signature(signature)[0]) for name, signature in kernel_cache.LATER}


def test_deferred_kernels_are_selected_only_when_each_of_them_is_ready(monkeypatch):
    from rangeseg_cli.kernels import backend

    ready = {"edges_pass"}
    monkeypatch.setattr(backend, "ready", lambda kernels, name: name in ready)
    assert backend.select_deferred("auto", "edges_pass") is not None
    assert backend.select_deferred("auto", "edges_pass", "roof_passes") is None
    assert backend.select_deferred("numba", "edges_pass", "roof_passes") is not None
    ready.add("roof_passes")
    assert backend.select_deferred("auto", "edges_pass", "roof_passes") is not None


def test_without_a_helper_a_deferred_kernel_compiles_in_the_run(monkeypatch):
    class Dispatcher:  # nothing compiled in this process
        overloads: dict = {}

    kernels = type("Kernels", (), {name: Dispatcher() for name in kernel_cache.DEFERRED})
    monkeypatch.setattr(kernel_cache, "_ready", set())
    monkeypatch.setattr(kernel_cache, "cached", lambda name: False)
    monkeypatch.setattr(kernel_cache, "_start_helper", lambda: None)
    monkeypatch.delenv("RANGESEG_COMPILE_AHEAD", raising=False)
    monkeypatch.delenv("RANGESEG_COMPILING_AHEAD", raising=False)
    name = kernel_cache.DEFERRED[0]
    monkeypatch.setattr(kernel_cache, "_looked", {})
    assert not kernel_cache.ready(kernels, name)  # a helper will compile it
    monkeypatch.setenv("RANGESEG_COMPILE_AHEAD", "0")
    assert kernel_cache.ready(kernels, name)  # no helper: the run compiles it
    assert name in kernel_cache._ready  # remembered: later calls do not ask again
    monkeypatch.delenv("RANGESEG_COMPILE_AHEAD")
    kernel_cache._ready.clear()
    assert not kernel_cache.ready(kernels, name)
    monkeypatch.setattr(kernel_cache, "_no_helper", True)  # the helper could not start
    monkeypatch.setattr(kernel_cache, "_looked", {})
    assert kernel_cache.ready(kernels, name)


@pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="needs numba")
def test_the_check_reads_a_real_numba_index_like_numba(tmp_path, monkeypatch):
    # A real index of numba's own, its source rewritten with the same bytes later.
    import numba

    source = tmp_path / "compiled.py"
    source.write_text("import numba\n\n\n@numba.njit(cache=True)\ndef twice(x):\n"
                      "    return 2 * x\n")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    subprocess.run([sys.executable, "-c", "import compiled; compiled.twice(2)"], cwd=tmp_path,
                   env=env, check=True)
    monkeypatch.setattr(kernel_cache, "SOURCE", source)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert kernel_cache.cached("twice")
    stamp = source.stat().st_mtime + 60.0
    source.write_bytes(source.read_bytes())
    os.utime(source, (stamp, stamp))
    hashed = tuple(int(p) for p in numba.__version__.split(".")[:2]) >= (0, 68)
    assert kernel_cache.cached("twice") == hashed  # numba 0.68 on: still valid


@pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="needs numba")
def test_a_read_only_package_is_looked_for_in_the_users_cache(tmp_path, monkeypatch):
    # numba caches a package it cannot write in the user's cache folder; looking in
    # __pycache__ alone read that cache as cold for good (the message on every run,
    # the numpy references of the deferred kernels). Here numba cannot use
    # __pycache__ because a file holds its name.
    package, home = tmp_path / "pkg", tmp_path / "xdg"
    package.mkdir()
    (package / "__pycache__").write_text("not a folder")
    source = package / "compiled.py"
    source.write_text("import numba\n\n\n@numba.njit(cache=True)\ndef twice(x):\n"
                      "    return 2 * x\n")
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env["XDG_CACHE_HOME"] = str(home)
    monkeypatch.setattr(kernel_cache, "SOURCE", source)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(home))
    monkeypatch.delenv("RANGESEG_PURE_NUMPY", raising=False)
    assert kernel_cache.cold_kernel_cache()
    subprocess.run([sys.executable, "-c", "import compiled; compiled.twice(2)"], cwd=package,
                   env=env, check=True)
    assert list(home.rglob("compiled.twice-*.nbi"))  # where numba put it
    assert kernel_cache.cached("twice")
    assert not kernel_cache.cold_kernel_cache()
