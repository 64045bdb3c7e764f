"""Throughput of a batch on a Dask LocalCluster vs the local process pool (issue 10).

On one folder of 200 PNGs of 128x128 (the bin piles of ``bench_pipeline.py``)
it times, for the local process pool (2 processes) and for a ``LocalCluster``
of 2 worker processes with 1 thread each on loopback (started once by this
script; its start-up is reported on its own):

* ``cli``: the real command, interpreter start-up, imports and I/O included,
  ``rangeseg run DIR -o OUT -q --jobs 2`` or ``... --executor dask --scheduler ADDR``;
* ``library``: :func:`rangeseg_cli.batch.runner.run_batch` in this process, which
  leaves out the start-up and shows the executor's own overhead.

Runs alternate between the four so that load on the machine hits all alike;
the first round is a warm-up (the Dask workers import rangeseg and load the
compiled kernels then; the local pool does so in every run) and is reported
on its own; the figures are medians and minima of the later rounds. Each run
writes into a fresh OUT; the bytes of the two executors are compared.

Run ``.venv/bin/python benchmarks/bench_dask.py`` (``--images``, ``--runs``).
Results go to ``benchmarks/results/dask.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench_pipeline import RESULTS, _cli, machine, write_batch

MODES = ("cli", "library")
EXECUTORS = ("local", "dask")


def tree_bytes(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != "rangeseg-run.json"}


def timed_run(folder: Path, out: Path, extra: list[str]) -> float:
    cmd = [*_cli(), "run", str(folder), "-o", str(out), "-q", *extra]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - t0


def library_run(folder: Path, out: Path, executor: str, scheduler: str) -> float:
    from rangeseg_cli import load_config
    from rangeseg_cli.batch.runner import jobs_from_inputs, run_batch
    from rangeseg_cli.pipeline import STAGES

    jobs, _ = jobs_from_inputs([folder], out)
    t0 = time.perf_counter()
    # Dask: no cap on the images in flight (n_jobs=None), as the CLI without --jobs.
    run_batch(jobs, out, load_config(), STAGES, executor=executor,
              n_jobs=2 if executor == "local" else None,
              scheduler=scheduler if executor == "dask" else None)
    return time.perf_counter() - t0


def _runs(folder: Path, tmp: Path, address: str, rounds: int) -> dict[str, list[float]]:
    cli_args = {"local": ["--jobs", "2"], "dask": ["--executor", "dask", "--scheduler", address]}
    walls: dict[str, list[float]] = {f"{m}_{e}": [] for m in MODES for e in EXECUTORS}
    for r in range(rounds):
        for mode in MODES:
            for executor in EXECUTORS:
                out = tmp / f"{mode}-{executor}-{r}"
                wall = (timed_run(folder, out, cli_args[executor]) if mode == "cli"
                        else library_run(folder, out, executor, address))
                walls[f"{mode}_{executor}"].append(wall)
                print(f"round {r} {mode:7} {executor:5}: {wall:6.2f} s", flush=True)
    return walls



def bench(count: int, runs: int) -> dict[str, Any]:
    from distributed import LocalCluster

    with tempfile.TemporaryDirectory(prefix="rangeseg-bench-dask-") as tmp:
        folder = Path(tmp) / "in"
        folder.mkdir()
        write_batch(folder, count)
        t0 = time.perf_counter()
        with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                          host="127.0.0.1", dashboard_address=":0") as cluster:
            cluster_start = time.perf_counter() - t0
            walls = _runs(folder, Path(tmp), cluster.scheduler_address, runs + 1)
        identical = all(tree_bytes(Path(tmp) / f"{m}-local-0")
                        == tree_bytes(Path(tmp) / f"{m}-dask-0") for m in MODES)
    result: dict[str, Any] = {"images": count, "size": [128, 128], "runs": runs,
                              "cluster_start_s": cluster_start, "identical_bytes": identical}
    for name, w in walls.items():
        median, best = statistics.median(w[1:]), min(w[1:])
        result[name] = {"median_s": median, "best_s": best, "warmup_s": w[0],
                        "images_per_s": count / median, "images_per_s_best": count / best,
                        "all_runs_s": w}
    for mode in MODES:
        local, dask = result[f"{mode}_local"], result[f"{mode}_dask"]
        result[f"{mode}_overhead"] = {
            "dask_over_local_throughput": dask["images_per_s"] / local["images_per_s"],
            "ms_per_image_median": 1000 * (dask["median_s"] - local["median_s"]) / count,
            "ms_per_image_best": 1000 * (dask["best_s"] - local["best_s"]) / count}
    return result


def table(result: dict[str, Any]) -> str:
    lines = [f"{result['images']} PNGs of 128x128, 2 processes each; wall time, median and "
             f"best of {result['runs']} rounds after a warm-up:", "",
             "| how | executor | median s | images/s | best s | images/s (best) | "
             "dask overhead ms/image (median, best) |", "|---" * 7 + "|"]
    for mode in MODES:
        o = result[f"{mode}_overhead"]
        for executor in EXECUTORS:
            r = result[f"{mode}_{executor}"]
            extra = (f"{o['ms_per_image_median']:+.1f}, {o['ms_per_image_best']:+.1f}"
                     if executor == "dask" else "")
            lines.append(f"| {mode} | {executor} | {r['median_s']:.2f} | "
                         f"{r['images_per_s']:.1f} | {r['best_s']:.2f} | "
                         f"{r['images_per_s_best']:.1f} | {extra} |")
    lines += ["", f"LocalCluster start {result['cluster_start_s']:.2f} s; first Dask CLI run "
              f"(cold workers) {result['cli_dask']['warmup_s']:.2f} s; identical bytes: "
              f"{result['identical_bytes']}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--images", type=int, default=200)
    parser.add_argument("--runs", type=int, default=3, help="timed runs after the first")
    parser.add_argument("--results", type=Path, default=RESULTS, help="output folder")
    args = parser.parse_args(argv)
    result = bench(args.images, args.runs)
    report = {"date": time.strftime("%Y-%m-%d %H:%M"), "machine": machine(), "batch": result}
    print(table(result))
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "dask.json").write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    return 0 if result["identical_bytes"] else 1


if __name__ == "__main__":
    sys.exit(main())
