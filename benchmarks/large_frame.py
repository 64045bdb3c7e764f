"""A 5 MP frame of thousands of regions: the whole run and each refinement pass, once.

The SR300 frame of ``sample_data/arc`` (0.1 mm depth) enlarged 4 times by
repeating each pixel (2560x1920) and read with the defaults, as a user who
forgot ``--preset`` would: its no-reading zeros count as heights and the
refinement gets about 6,000 regions, 10,000 after the cuts. Such a frame
found work that grows faster than the pixels (pair tests over the whole
frame, tables of every pair of regions): this script shows each pass's
seconds, so that one that does not scale stands out. One run each (the
frame takes a minute); medians are for ``bench_pipeline.py``.

Usage::

    .venv/bin/python benchmarks/large_frame.py [--output FILE]

Results go to ``benchmarks/results/large_frame.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from rangeseg_cli.batch.io import read_image
from rangeseg_cli.config import load_config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.refine import passes as refinement

ROOT = Path(__file__).resolve().parents[1]
FRAME = ROOT / "sample_data" / "arc" / "suction-scene.depth.png"
RESULTS = ROOT / "benchmarks" / "results" / "large_frame.json"
SCALE = 4


def large_frame() -> np.ndarray:
    """The SR300 frame with each pixel repeated ``SCALE`` x ``SCALE`` times."""
    return np.kron(read_image(str(FRAME)), np.ones((SCALE, SCALE), np.uint16))


def timed_passes(log: list[dict[str, Any]]) -> tuple[refinement.Pass, ...]:
    """:data:`~rangeseg_cli.refine.passes.PASSES` with each run's seconds and regions in ``log``."""
    def timed(step: refinement.Pass) -> Callable[[refinement.Scene, np.ndarray], np.ndarray]:
        def run(scene: refinement.Scene, labels: np.ndarray) -> np.ndarray:
            t0 = time.perf_counter()
            out = step.run(scene, labels)
            log.append({"pass": step.name, "seconds": time.perf_counter() - t0,
                        "regions_before": int(labels.max()), "regions_after": int(out.max())})
            return out
        return run

    return tuple(dataclasses.replace(p, run=timed(p)) for p in refinement.PASSES)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--output", type=Path, default=RESULTS, help="JSON results file")
    args = parser.parse_args()
    image = large_frame()
    config = load_config()
    run_pipeline(image[:64, :64], config)  # the kernels loaded
    log: list[dict[str, Any]] = []
    saved, refinement.PASSES = refinement.PASSES, timed_passes(log)
    try:
        t0 = time.perf_counter()
        result = run_pipeline(image, config)
        total = time.perf_counter() - t0
    finally:
        refinement.PASSES = saved
    print(f"{image.shape[1]}x{image.shape[0]}: run_pipeline {total:.1f} s, "
          f"{int(result.labels.max())} regions")
    for k, stage in result.timings.items():
        print(f"  stage {k:12s} {stage:7.2f} s")
    for entry in log:
        print(f"  pass {entry['pass']:13s} {entry['seconds']:7.2f} s  regions "
              f"{entry['regions_before']} -> {entry['regions_after']}")
    report = {"date": time.strftime("%Y-%m-%d %H:%M"), "frame": f"{FRAME.name} x{SCALE}",
              "shape": list(image.shape), "seconds": total, "timings": result.timings,
              "regions": int(result.labels.max()), "passes": log}
    args.output.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
