"""Speed of the pipeline (issue 7): per-stage medians, Gaussian-pass ratios, batch throughput.

For synthetic bin scenes of 128x128, 640x480, 1280x1024 and 1920x1200 pixels
(``rangeseg_cli.synth.scenes`` ``pile``, 8-bit, noise 1, fixed seeds) it measures,
interleaved within every repeat so that load on the machine hits all figures
alike:

* the baseline ``scipy.ndimage.gaussian_filter(z, 4)`` on the frame's float64
  heights (one "Gaussian pass", G),
* each stage of Sec. V and VII -- ``to_heights``, edges (compiled kernels and
  the numpy reference), the noise estimate (``noise.estimate_noise``, compiled
  and its numpy reference, which gives the same value), link, grow (+ surface
  descriptions) with the fit-test split (the pass ``split`` of ``[refine] passes``, on by
  default) and without it, and
  the two parts of the latter (``grow_regions``, ``describe_surfaces``),
  holdsite -- and ``run_pipeline`` as a whole, with and without the split,

and reports medians of ``--repeats`` runs after one warm-up, as milliseconds
and as multiples of G. Then the numba compile time (cold cache) and the
start-up cost with a warm cache, each in a fresh interpreter, and the batch
throughput of the real CLI, ``rangeseg run DIR -o OUT --jobs N -q``, on a
folder of 128x128 PNGs (``--jobs 1``, ``--jobs 2`` and ``--jobs 1 --threads
1``, I/O and interpreter start-up included). Stages run with the automatic
threads of :mod:`rangeseg_cli.kernels.parallel` (every core); the ``_1thread``
columns with one.

Run ``.venv/bin/python benchmarks/bench_pipeline.py`` (or ``make bench``);
``--quick`` times 128x128 and 640x480 only, with 5 repeats and 50 batch images.
Results go to ``benchmarks/results/bench.json`` and ``bench.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import gaussian_filter

from rangeseg_cli import __version__
from rangeseg_cli.batch import io
from rangeseg_cli.config import REFINE_PASSES, Config, load_config
from rangeseg_cli.kernels import parallel
from rangeseg_cli.pipeline import (
    run_pipeline,
    stage_edges,
    stage_grow,
    stage_holdsite,
    stage_link,
)
from rangeseg_cli.stages.edges import detect_edges
from rangeseg_cli.stages.grow import grow_regions
from rangeseg_cli.stages.noise import estimate_noise
from rangeseg_cli.stages.rangeimage import to_heights
from rangeseg_cli.stages.surfaces import describe_surfaces

#: Frame sizes as (rows, cols): the paper's 128x128 and common sensor formats.
SIZES: tuple[tuple[int, int], ...] = ((128, 128), (480, 640), (1024, 1280), (1200, 1920))
QUICK_SIZES = SIZES[:2]
#: The synthetic frame whose refinement passes are timed one by one.
PASSES_FRAME = (480, 640)
RESULTS = Path(__file__).resolve().parent / "results"
ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------- scenes


def bin_scene(rows: int, cols: int, seed: int, noise: float = 1.0) -> np.ndarray:
    """8-bit range image of a bin pile (``synth`` ``pile``), or random boxes without synth."""
    try:
        from rangeseg_cli.synth.scenes import render_scene
    except ImportError:
        return _random_boxes(rows, cols, seed, noise)
    return render_scene("pile", size=(rows, cols), noise=noise, seed=seed).image


def _random_boxes(rows: int, cols: int, seed: int, noise: float) -> np.ndarray:
    """Tilted boxes on a table (np.mgrid), rounded to 8 bits."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols].astype(np.float64)
    z = 30.0 + 0.01 * xx
    unit = min(rows, cols) / 128.0
    for _ in range(8):
        r0, c0 = rng.uniform(0, rows * 0.8), rng.uniform(0, cols * 0.8)
        h, w = rng.uniform(15, 45, 2) * unit
        a, b = rng.uniform(-0.5, 0.5, 2) / unit
        top = rng.uniform(50, 200) + a * (xx - c0) + b * (yy - r0)
        inside = (yy >= r0) & (yy < r0 + h) & (xx >= c0) & (xx < c0 + w)
        z = np.where(inside, np.maximum(z, top), z)
    z += rng.normal(0.0, noise, z.shape)
    return np.clip(np.rint(z), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- frames


def _timed(fn: Callable[[], Any]) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def frame_tasks(image: np.ndarray, config: Config, numpy_edges: bool
                ) -> dict[str, Callable[[], Any]]:
    """The timed calls for one frame, with the inputs of each stage precomputed.

    ``grow`` (``stage_grow``) and ``run_pipeline`` use ``config`` (every
    pass beyond the paper on by default); the ``_nosplit`` tasks the same
    with the pass ``split`` left out of ``[refine] passes`` (recovery, fill,
    merge, recut and the others still on), ``run_pipeline_norecut`` with
    ``recut`` left out, ``run_pipeline_paper`` with every pass left out
    (``[refine] passes = []`` as ``--preset paper``), whose growth is
    ``grow_regions`` + ``describe``.
    """
    nosplit = without_passes(config, "split")
    result = run_pipeline(image, config)
    z = result.heights
    plain = grow_regions(z, result.edges, result.components, config.grow)
    baseline = np.nan_to_num(z)
    tasks: dict[str, Callable[[], Any]] = {
        "gaussian": lambda: gaussian_filter(baseline, 4),
        "to_heights": lambda: to_heights(image, config.input),
        "edges": lambda: stage_edges(z, config),
    }
    if numpy_edges:
        tasks["edges_numpy"] = lambda: detect_edges(z, config, backend="numpy")
    tasks["noise"] = lambda: estimate_noise(z)
    tasks["noise_numpy"] = lambda: estimate_noise(z, backend="numpy")
    tasks["link"] = lambda: stage_link(z, result.edge_maps.codes, config)
    tasks["grow_regions"] = lambda: grow_regions(z, result.edges, result.components,
                                                 config.grow)
    tasks["describe"] = lambda: describe_surfaces(z, plain, config)
    tasks["grow_nosplit"] = lambda: stage_grow(z, result.edges, result.components, nosplit)
    tasks["grow"] = lambda: stage_grow(z, result.edges, result.components, config)
    tasks["holdsite"] = lambda: stage_holdsite(z, result.labels, result.surfaces, config)
    tasks["run_pipeline_nosplit"] = lambda: run_pipeline(image, nosplit)
    paper = without_passes(config, *REFINE_PASSES)
    tasks["run_pipeline_paper"] = lambda: run_pipeline(image, paper)
    norecut = without_passes(config, "recut")
    tasks["run_pipeline_norecut"] = lambda: run_pipeline(image, norecut)
    tasks["run_pipeline_paper_1thread"] = _one_thread(lambda: run_pipeline(image, paper))
    tasks["run_pipeline_1thread"] = _one_thread(lambda: run_pipeline(image, config))
    tasks["run_pipeline"] = lambda: run_pipeline(image, config)
    return tasks


def without_passes(config: Config, *names: str) -> Config:
    """``config`` with the passes ``names`` left out of its ``[refine] passes``."""
    passes = tuple(p for p in config.refine.passes if p not in names)
    return dataclasses.replace(config, refine=dataclasses.replace(config.refine, passes=passes))


def _one_thread(fn: Callable[[], Any]) -> Callable[[], Any]:
    """``fn`` with the kernels of one image on one thread (``--threads 1``)."""
    def run() -> Any:
        parallel.set_threads(1)
        try:
            return fn()
        finally:
            parallel.set_threads(None)

    return run


def interleaved(tasks: dict[str, Callable[[], Any]], repeats: int) -> dict[str, list[float]]:
    """Seconds of each task in ``repeats`` rounds of all of them, after one warm-up round.

    The warm-up loads the compiled kernels and fills caches; interleaving
    lets load on the machine hit every task alike.
    """
    for fn in tasks.values():
        fn()
    times: dict[str, list[float]] = {name: [] for name in tasks}
    for _ in range(repeats):
        for name, fn in tasks.items():
            times[name].append(_timed(fn))
    return times


def bench_frame(rows: int, cols: int, repeats: int, numpy_edges: bool) -> dict[str, Any]:
    """Median seconds of every task over ``repeats`` interleaved runs after a warm-up."""
    config = load_config()
    image = bin_scene(rows, cols, seed=rows + cols)
    times = interleaved(frame_tasks(image, config, numpy_edges), repeats)
    median = {name: float(np.median(t)) for name, t in times.items()}
    g = median["gaussian"]
    passes = None
    if (rows, cols) == PASSES_FRAME:
        result = run_pipeline(image, config)
        passes = bench_passes(result.heights, result.edges, result.components, config, repeats)
    return {
        "rows": rows, "cols": cols, "pixels": rows * cols, "repeats": repeats,
        "passes": passes,
        "median_ms": {k: v * 1e3 for k, v in median.items()},
        "min_ms": {k: float(np.min(t)) * 1e3 for k, t in times.items()},
        "gaussian_passes": {k: v / g for k, v in median.items() if k != "gaussian"},
        "ms_per_megapixel": {k: v * 1e3 / (rows * cols / 1e6) for k, v in median.items()},
    }


#: The real depth frame of ``sample_data/arc`` (Intel RealSense SR300) and its settings.
REAL_FRAME = ROOT / "sample_data" / "arc" / "suction-scene.depth.png"
REAL_CONFIG = ROOT / "sample_data" / "arc" / "suction.toml"


def _threads_only(fn: Callable[[], Any]) -> Callable[[], Any]:
    """``fn`` with many tasks on threads, as few are (no forked processes)."""
    def run() -> Any:
        saved = parallel.MIN_PROCESS_ITEMS
        parallel.MIN_PROCESS_ITEMS = 1 << 62
        try:
            return fn()
        finally:
            parallel.MIN_PROCESS_ITEMS = saved

    return run


def bench_real_frame(repeats: int) -> dict[str, Any]:
    """The SR300 frame with ``suction.toml``: stages and ``run_pipeline`` three ways.

    ``run_pipeline`` with the automatic threads (many independent tasks of
    the split and the recut in forked processes), ``run_pipeline_threads``
    with every task on threads, ``run_pipeline_1thread`` on one thread, and
    ``--preset paper`` with the frame's settings.
    """
    from rangeseg_cli.batch.io import read_image

    config = load_config(REAL_CONFIG)
    image = read_image(str(REAL_FRAME))
    result = run_pipeline(image, config)
    z = result.heights
    paper = without_passes(config, *REFINE_PASSES)
    tasks: dict[str, Callable[[], Any]] = {
        "gaussian": lambda: gaussian_filter(np.nan_to_num(z), 4),
        "edges": lambda: stage_edges(z, config),
        "grow": lambda: stage_grow(z, result.edges, result.components, config),
        "holdsite": lambda: stage_holdsite(z, result.labels, result.surfaces, config),
        "run_pipeline_paper": lambda: run_pipeline(image, paper),
        "run_pipeline_1thread": _one_thread(lambda: run_pipeline(image, config)),
        "run_pipeline_threads": _threads_only(lambda: run_pipeline(image, config)),
        "run_pipeline": lambda: run_pipeline(image, config),
    }
    median = {name: float(np.median(t)) for name, t in interleaved(tasks, repeats).items()}
    return {"rows": int(z.shape[0]), "cols": int(z.shape[1]), "repeats": repeats,
            "regions": int(result.labels.max()),
            "passes": bench_passes(z, result.edges, result.components, config, repeats),
            "median_ms": {k: v * 1e3 for k, v in median.items()},
            "gaussian_passes": {k: v / median["gaussian"] for k, v in median.items()
                                if k != "gaussian"}}


def pass_tasks(z: np.ndarray, edges: np.ndarray, components: np.ndarray, config: Config
               ) -> dict[str, Callable[[], Any]]:
    """Each active pass of ``[refine] passes`` on the labels it gets in a run, as a task.

    Passes that run twice (the fill, the facets, the bridge) are named
    ``name`` and ``name#2``; the inputs are those of one ``stage_grow``.
    """
    from rangeseg_cli.refine import passes as refinement
    from rangeseg_cli.stages.grow import component_fits

    fits = component_fits(z, components)
    labels = grow_regions(z, edges, components, config.grow, fits=fits)
    scene = refinement.Scene(z, edges, components, config, estimate_noise(z), fits)
    tasks: dict[str, Callable[[], Any]] = {}
    for step in refinement.active_passes(config):
        name = step.name if step.name not in tasks else f"{step.name}#2"
        tasks[name] = lambda step=step, labels=labels: step.run(scene, labels)
        labels = step.run(scene, labels)
    return tasks


def moved_pixels(before: np.ndarray, after: np.ndarray) -> int:
    """Pixels a pass gives another surface: outside the largest overlap of their old region.

    Merges move none (each old region lies in one new region); a cut moves
    the pixels of its new pieces but the largest; an unlabelled pixel that
    gets a label counts.
    """
    a, b = before.ravel().astype(np.int64), after.ravel().astype(np.int64)
    used = (a > 0) | (b > 0)
    keys, counts = np.unique(a[used] * (int(b.max()) + 1) + b[used], return_counts=True)
    largest = np.zeros(int(a.max()) + 1, np.int64)
    np.maximum.at(largest, keys // (int(b.max()) + 1), counts)
    largest[0] = 0  # every unlabelled pixel labelled counts
    return int(counts.sum() - largest.sum())


def pass_changes(z: np.ndarray, edges: np.ndarray, components: np.ndarray, config: Config
                 ) -> dict[str, list[int]]:
    """Per pass of :func:`pass_tasks`: [pixels moved, regions before, regions after]."""
    from rangeseg_cli.refine import passes as refinement
    from rangeseg_cli.stages.grow import component_fits

    fits = component_fits(z, components)
    labels = grow_regions(z, edges, components, config.grow, fits=fits)
    scene = refinement.Scene(z, edges, components, config, estimate_noise(z), fits)
    out: dict[str, list[int]] = {}
    for step in refinement.active_passes(config):
        name = step.name if step.name not in out else f"{step.name}#2"
        new = step.run(scene, labels)
        out[name] = [moved_pixels(labels, new), int(labels.max()), int(new.max())]
        labels = new
    return out


def bench_passes(z: np.ndarray, edges: np.ndarray, components: np.ndarray, config: Config,
                 repeats: int) -> dict[str, Any]:
    """Median ms and G of each refinement pass (:func:`pass_tasks`) and of G itself."""
    tasks = {"gaussian": lambda: gaussian_filter(np.nan_to_num(z), 4),
             **pass_tasks(z, edges, components, config)}
    median = {name: float(np.median(t)) for name, t in interleaved(tasks, repeats).items()}
    return {"median_ms": {k: v * 1e3 for k, v in median.items()},
            "gaussian_passes": {k: v / median["gaussian"] for k, v in median.items()
                                if k != "gaussian"},
            "changes": pass_changes(z, edges, components, config)}


def scaling_exponent(frames: list[dict[str, Any]], task: str) -> float | None:
    """Slope of log(time) against log(pixels): 1 means time linear in pixels."""
    if len(frames) < 2:
        return None
    px = np.log([f["pixels"] for f in frames])
    ms = np.log([f["median_ms"][task] for f in frames])
    return float(np.polyfit(px, ms, 1)[0])


# --------------------------------------------------------------------------- compile


_STARTUP = """
import json, time
t0 = time.perf_counter()
import numpy as np
from rangeseg_cli import run_pipeline
from rangeseg_cli.kernels import compiled as _kernels
from rangeseg_cli.config import load_config
t1 = time.perf_counter()
z = np.full((64, 64), 20.0)
z[20:44, 16:40] = 120.0
z += np.random.default_rng(0).normal(0.0, 1.0, z.shape)
run_pipeline(z, load_config())
t2 = time.perf_counter()
run_pipeline(z, load_config())
t3 = time.perf_counter()
print(json.dumps({"import_s": t1 - t0, "first_call_s": t2 - t1, "second_call_s": t3 - t2}))
"""


def bench_compile() -> dict[str, Any]:
    """First ``run_pipeline`` in fresh interpreters (all kernels): empty numba cache, then warm.

    The cold run starts the helper that compiles kernels in the background, as
    a user's first run does; the helper stops when the run ends (after the
    kernel it is compiling: waited for, :func:`_helper_done`), so kernels the
    run took the numpy reference for may not be cached yet. Before the warm
    run (which starts no helper and compiles what it misses) every kernel of
    the helper's list is compiled into the cache (:data:`_COMPILE_ALL`): the
    warm figure is loading alone, as from the second or third run on.
    """
    with tempfile.TemporaryDirectory(prefix="rangeseg-numba-") as cache:
        runs = {}
        for label, ahead in (("cold_cache", "1"), ("warm_cache", "0")):
            env = {**os.environ, "NUMBA_CACHE_DIR": cache, "RANGESEG_COMPILE_AHEAD": ahead}
            if label == "warm_cache":
                subprocess.run([sys.executable, "-c", _COMPILE_ALL], env=env, cwd=ROOT,
                               check=True)
            out = subprocess.run([sys.executable, "-c", _STARTUP], env=env, cwd=ROOT,
                                 capture_output=True, text=True, check=True)
            runs[label] = json.loads(out.stdout)
            _helper_done(Path(cache))
    return runs


#: Compile every kernel of the helper's list into the cache (``kernels.cache.compile_ahead``
#: with this process's parent, which outlives it).
_COMPILE_ALL = """
import os
from rangeseg_cli.kernels.backend import select_kernels
from rangeseg_cli.kernels.cache import compile_ahead
compile_ahead(select_kernels("numba"), os.getppid())
"""


def _helper_done(cache: Path) -> None:
    """Wait until no helper holds the lock of ``cache`` (``kernels.cache.LOCK_FILE``)."""
    import fcntl

    from rangeseg_cli.kernels.cache import LOCK_FILE

    lock = cache / LOCK_FILE
    if lock.exists():
        with open(lock) as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)  # blocks while the helper compiles


# --------------------------------------------------------------------------- batch


def write_batch(folder: Path, count: int, size: int = 128) -> None:
    """``count`` 8-bit PNGs: 10 pile layouts, each with its own noise per image."""
    layouts = [bin_scene(size, size, seed=s, noise=0.0).astype(np.float64) for s in range(10)]
    rng = np.random.default_rng(7)
    for i in range(count):
        z = layouts[i % len(layouts)] + rng.normal(0.0, 1.0, (size, size))
        io.write_png(folder / f"img{i:04d}.png", np.clip(np.rint(z), 0, 255).astype(np.uint8))


def _cli() -> list[str]:
    exe = shutil.which("rangeseg", path=str(Path(sys.executable).parent))
    run = "from rangeseg_cli.cli.main import main; main()"
    return [exe] if exe else [sys.executable, "-c", run]


#: The batch commands timed: name, and the options after ``rangeseg run DIR -o OUT -q``.
BATCH_RUNS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("jobs1", ("--jobs", "1")), ("jobs2", ("--jobs", "2")),
    ("jobs1_threads1", ("--jobs", "1", "--threads", "1")))


def _wall(path: Path, out: Path, options: tuple[str, ...]) -> float:
    """Wall time of one ``rangeseg run PATH -o out OPTIONS -q`` (a folder or one image)."""
    cmd = [*_cli(), "run", str(path), "-o", str(out), *options, "-q"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    wall = time.perf_counter() - t0
    shutil.rmtree(out)
    return wall


def bench_batch(count: int, runs: int) -> dict[str, Any]:
    """Images per second of ``rangeseg run DIR -o OUT OPTIONS -q`` (median of ``runs``).

    For each of :data:`BATCH_RUNS`: ``--jobs 1`` (one process, its image's
    kernels on every core), ``--jobs 2`` (two processes of one thread each on
    2 cores) and ``--jobs 1 --threads 1``, the runs interleaved so that load
    on the machine hits all alike. Also the wall time of the same command on
    the first 2 images (start-up: interpreter, imports, loading the compiled
    kernels, forking the workers) and the steady throughput without it,
    ``(count - 2) / (wall - wall_2)``: the start-up is paid once per command,
    and with ``--jobs 2`` it is not shared, so it caps the wall-time speed-up
    of a short batch (Amdahl).
    """
    result: dict[str, Any] = {"images": count, "size": [128, 128], "runs": runs}
    walls: dict[str, list[float]] = {name: [] for name, _ in BATCH_RUNS}
    starts: dict[str, list[float]] = {name: [] for name, _ in BATCH_RUNS}
    with tempfile.TemporaryDirectory(prefix="rangeseg-bench-") as tmp:
        folder, two = Path(tmp) / "in", Path(tmp) / "two"
        folder.mkdir()
        two.mkdir()
        write_batch(folder, count)
        for name in sorted(p.name for p in folder.iterdir())[:2]:
            shutil.copy(folder / name, two / name)
        for _ in range(runs):
            for name, options in BATCH_RUNS:
                walls[name].append(_wall(folder, Path(tmp) / "out", options))
                starts[name].append(_wall(two, Path(tmp) / "out", options))
    for name, _ in BATCH_RUNS:
        wall, start = float(np.median(walls[name])), float(np.median(starts[name]))
        result[name] = {"wall_s": wall, "images_per_s": count / wall, "startup_s": start,
                        "steady_images_per_s": (count - 2) / max(wall - start, 1e-9)}
    two_ = result["jobs2"]
    for base, key in (("jobs1", "speedup_jobs2"), ("jobs1_threads1", "speedup_jobs2_vs_1x1")):
        result[key] = two_["images_per_s"] / result[base]["images_per_s"]
        result[key + "_steady"] = (two_["steady_images_per_s"]
                                   / result[base]["steady_images_per_s"])
    return result


def bench_one_frame(runs: int) -> dict[str, Any]:
    """Wall time of ``rangeseg run`` on the SR300 frame alone, as a cell would call it.

    ``rangeseg run suction-scene.depth.png --preset tenth-mm-depth
    --intrinsics suction-camera-intrinsics.txt -o OUT -q`` from process start
    to exit (median of ``runs``, compiled kernels already cached): the
    latency of one pick when the command is run per frame. ``overhead_s`` is
    that less the median of ``run_pipeline`` on the same frame with the same
    settings in this process, measured in the same minutes: start-up,
    imports, reading and writing.
    """
    from rangeseg_cli.batch.io import read_image
    from rangeseg_cli.cell.intrinsics import read_intrinsics

    intrinsics = ROOT / "sample_data" / "arc" / "suction-camera-intrinsics.txt"
    options = ("--preset", "tenth-mm-depth", "--intrinsics", str(intrinsics))
    config = load_config(preset="tenth-mm-depth",
                         overrides=read_intrinsics(intrinsics).settings())
    image = read_image(str(REAL_FRAME))
    walls, inside = [], []
    with tempfile.TemporaryDirectory(prefix="rangeseg-bench-") as tmp:
        for _ in range(runs):
            walls.append(_wall(REAL_FRAME, Path(tmp) / "out", options))
            inside.append(_timed(lambda: run_pipeline(image, config)))
    wall, pipeline = float(np.median(walls)), float(np.median(inside))
    return {"runs": runs, "wall_s": wall, "run_pipeline_s": pipeline,
            "overhead_s": wall - pipeline}


# --------------------------------------------------------------------------- report


def machine() -> dict[str, Any]:
    import numba
    import scipy

    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count()
    return {"python": platform.python_version(), "numpy": np.__version__,
            "scipy": scipy.__version__, "numba": numba.__version__, "cores": cores,
            "threads": parallel.thread_count(),
            "cpu": platform.processor() or platform.machine(), "rangeseg": __version__}


COLUMNS = ("to_heights", "edges", "edges_numpy", "noise", "noise_numpy", "link", "grow_regions",
           "describe", "grow_nosplit", "grow", "holdsite", "run_pipeline_nosplit",
           "run_pipeline_paper", "run_pipeline_paper_1thread", "run_pipeline_norecut",
           "run_pipeline_1thread", "run_pipeline")


def markdown(report: dict[str, Any]) -> str:
    """The small tables of ``bench.md``."""
    lines = [
        f"# rangeseg benchmarks{' (quick)' if report['quick'] else ''}",
        "",
        f"{report['date']}, {report['machine']['cores']} cores, numpy "
        f"{report['machine']['numpy']}, numba {report['machine']['numba']}. Medians of "
        f"{report['frames'][0]['repeats']} interleaved runs after a warm-up; G = "
        "`gaussian_filter(z, 4)` on the same float64 frame in the same run. Cells: ms (x G). "
        "`grow` and `run_pipeline` with the defaults, `_nosplit` with the pass `split` left "
        "out of `[refine] passes` (the fit-test split off; recovery, fill, merge, recut and "
        "the others still on), `run_pipeline_norecut` with `recut` left out, "
        "`run_pipeline_paper` with `[refine] passes = []` as `--preset paper` (every pass "
        "beyond the paper off); "
        "`grow_regions` + `describe` (surface descriptions) = the paper's growth; "
        "`noise` is the noise estimate (`noise.estimate_noise`) `run_pipeline` makes when "
        "its configuration uses it (the defaults, not `--preset paper`), `noise_numpy` "
        "the same value by its numpy reference. Every task with the "
        f"automatic threads ({report['machine'].get('threads', '?')} here: row bands of "
        "the edge passes and the split's plane fits, the split's components and the "
        "recut's candidates at once, on threads or, 24 or more, in forked processes; "
        "`rangeseg_cli.kernels.parallel`) but the `_1thread` ones (`--threads 1`).",
        "",
        "| frame | G ms | " + " | ".join(COLUMNS) + " | pipeline ms/Mpx |",
        "|---" * (len(COLUMNS) + 3) + "|",
    ]
    for f in report["frames"]:
        cells = [f"{f['cols']}x{f['rows']}", f"{f['median_ms']['gaussian']:.2f}"]
        for c in COLUMNS:
            if c in f["median_ms"]:
                cells.append(f"{f['median_ms'][c]:.1f} ({f['gaussian_passes'][c]:.1f})")
            else:
                cells.append("-")
        cells.append(f"{f['ms_per_megapixel']['run_pipeline']:.0f}")
        lines.append("| " + " | ".join(cells) + " |")
    real = report.get("real_frame")
    if real:
        order = ["edges", "grow", "holdsite", "run_pipeline_paper", "run_pipeline_1thread",
                 "run_pipeline_threads", "run_pipeline"]
        lines += ["", f"Real frame: the SR300 frame of `sample_data/arc` ({real['cols']}x"
                  f"{real['rows']}, `suction.toml`, {real['regions']} regions), medians of "
                  f"{real['repeats']} interleaved runs. `run_pipeline` with the automatic "
                  "threads (many tasks of the split and the recut in forked processes), "
                  "`_threads` with every task on threads, `_1thread` on one.", "",
                  "| G ms | " + " | ".join(order) + " |", "|---" * (len(order) + 1) + "|",
                  f"| {real['median_ms']['gaussian']:.2f} | " + " | ".join(
                      f"{real['median_ms'][k]:.1f} ({real['gaussian_passes'][k]:.1f})"
                      for k in order) + " |"]
    lines += pass_table(report)
    exps = report["scaling_exponent"]
    lines += ["", "Time ~ pixels^k: " + ", ".join(
        f"{k} k = {v:.2f}" for k, v in exps.items() if v is not None) + "."]
    c = report["compile"]
    lines += ["", f"Numba, fresh interpreter, first `run_pipeline` on 64x64 (all kernels): "
              f"cold cache (compile) {c['cold_cache']['first_call_s']:.2f} s, warm cache "
              f"(load) {c['warm_cache']['first_call_s']:.2f} s, after "
              f"{c['warm_cache']['import_s']:.2f} s of imports."]
    one = report.get("one_frame")
    if one:
        lines += ["", "One frame, `rangeseg run suction-scene.depth.png --preset "
                  "tenth-mm-depth --intrinsics suction-camera-intrinsics.txt -o OUT -q` "
                  f"(the SR300 frame alone, kernels cached), median of {one['runs']}: "
                  f"{one['wall_s']:.2f} s from start to exit, of which `run_pipeline` "
                  f"{one['run_pipeline_s']:.2f} s (in this process, same minutes) and "
                  f"start-up, imports and I/O {one['overhead_s']:.2f} s."]
    b = report["batch"]
    if b:
        lines += ["", f"Batch, `rangeseg run DIR -o OUT OPTIONS -q`, {b['images']} PNGs of "
                  "128x128, wall time incl. start-up and I/O (median of "
                  f"{b['runs']}):", "",
                  "| options | s | images/s | start-up s (2 images) | steady images/s |",
                  "|---|---|---|---|---|"]
        for name, options in BATCH_RUNS:
            if name in b:
                j = b[name]
                lines.append(f"| {' '.join(options)} | {j['wall_s']:.2f} | "
                             f"{j['images_per_s']:.1f} | {j['startup_s']:.2f} | "
                             f"{j['steady_images_per_s']:.1f} |")
        if "speedup_jobs2" in b:
            lines += ["", f"--jobs 2 / --jobs 1 throughput: {b['speedup_jobs2']:.2f}x "
                      f"(wall time); {b['speedup_jobs2_steady']:.2f}x without the start-up. "
                      f"--jobs 2 / --jobs 1 --threads 1: {b['speedup_jobs2_vs_1x1']:.2f}x "
                      f"(wall), {b['speedup_jobs2_vs_1x1_steady']:.2f}x (steady)."]
    return "\n".join(lines) + "\n"


def pass_table(report: dict[str, Any]) -> list[str]:
    """The lines of the per-pass table (ms and G of each refinement pass)."""
    columns = [(f"{f['cols']}x{f['rows']} pile", f["passes"]) for f in report["frames"]
               if f.get("passes")]
    real = report.get("real_frame")
    if real and real.get("passes"):
        columns.append(("SR300 frame", real["passes"]))
    if not columns:
        return []
    names = list(dict.fromkeys(n for _, p in columns for n in p["gaussian_passes"]))
    lines = ["", "Each refinement pass of the defaults alone, on the labels it gets in a run "
             "(medians, interleaved; `#2` = its second run). Cells: ms (x G; pixels the "
             "pass gives another surface, regions before -> after).", "",
             "| pass | " + " | ".join(c for c, _ in columns) + " |",
             "|---" * (len(columns) + 1) + "|"]
    for name in names + ["all passes"]:
        cells = []
        for _, p in columns:
            ms, g = p["median_ms"], p["gaussian_passes"]
            if name == "all passes":
                total = sum(ms[k] for k in g)
                cells.append(f"{total:.1f} ({total / ms['gaussian']:.1f})")
            else:
                moved = p.get("changes", {}).get(name)
                change = (f"; {moved[0]} px, {moved[1]}->{moved[2]} regions" if moved
                          else "")
                cells.append(f"{ms[name]:.1f} ({g[name]:.1f}{change})" if name in g else "-")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true",
                        help="128x128 and 640x480 only, 5 repeats, 50 batch images, 1 run")
    parser.add_argument("--repeats", type=int, default=None, help="timed runs per frame (>= 5)")
    parser.add_argument("--batch-images", type=int, default=None)
    parser.add_argument("--no-batch", action="store_true", help="skip the CLI batch runs")
    parser.add_argument("--results", type=Path, default=RESULTS, help="output folder")
    args = parser.parse_args(argv)
    repeats = max(5, args.repeats or (5 if args.quick else 7))
    sizes = QUICK_SIZES if args.quick else SIZES
    frames = []
    for rows, cols in sizes:
        frame = bench_frame(rows, cols, repeats, numpy_edges=True)
        frames.append(frame)
        print(f"{cols}x{rows}: " + ", ".join(
            f"{k} {v:.1f} ms" for k, v in frame["median_ms"].items()), flush=True)
    report: dict[str, Any] = {
        "date": time.strftime("%Y-%m-%d %H:%M"), "quick": args.quick, "machine": machine(),
        "frames": frames,
        "scaling_exponent": {t: scaling_exponent(frames, t)
                             for t in ("edges", "run_pipeline_nosplit", "run_pipeline_paper",
                                       "run_pipeline_norecut", "run_pipeline_1thread",
                                       "run_pipeline")},
        "real_frame": bench_real_frame(repeats),
        "compile": bench_compile(), "one_frame": bench_one_frame(3 if args.quick else 5),
        "batch": {},
    }
    if not args.no_batch:
        count = args.batch_images or (50 if args.quick else 200)
        report["batch"] = bench_batch(count, runs=1 if args.quick else 3)
    text = markdown(report)
    print(text)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "bench.json").write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    (args.results / "bench.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
