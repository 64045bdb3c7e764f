"""Segmenting a depth camera's frame as depth or as inverse depth (issue 33, a measurement).

A structured-light or stereo camera measures disparity: its depth noise
grows with the square of the depth, and a plane seen in perspective is not
a plane in (row, col, depth). In inverse depth both change: a plane
``n . X = c`` seen through a pinhole has ``1 / depth`` affine in (row,
col), and the noise of ``1 / depth`` is the same at every depth. This
script renders the synthetic camera frames of ``rangeseg synth --scenes
cam-*`` (as ``benchmarks/real_cells.py`` does) and segments each twice:

* ``depth``: as a user runs it today, ``--preset tenth-mm-depth`` with the
  frame's intrinsics;
* ``inverse``: the defaults on ``d0**2 / depth`` in millimetres (``d0`` the
  frame's median depth, so that heights near ``d0`` keep their scale), no
  intrinsics, ``units_per_pixel`` the pixel's size at ``d0``.

Each is scored against the frame's ground truth by Hoover's metric at
T = 0.8 (:func:`rangeseg_cli.synth.evaluate.hoover_compare`, surfaces of
1,000 valid pixels or more). Only the segmentation is compared: the
holdsite needs metric heights, which the inverse path does not give it.

Usage::

    .venv/bin/python benchmarks/inverse_depth.py --seeds 300-309
    .venv/bin/python benchmarks/inverse_depth.py --seeds 325-334 --out benchmarks/results/x

Writes ``benchmarks/results/inverse_depth.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from rangeseg_cli import __version__
from rangeseg_cli.batch.io import read_image
from rangeseg_cli.config import load_config, parse_settings
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.synth.camera import CAMERAS
from rangeseg_cli.synth.evaluate import hoover_compare

sys.path.insert(0, str(Path(__file__).parent))
from real_cells import (  # noqa: E402
    PRESET,
    checked_scenes,
    checked_seeds,
    depth_in_mm,
    frame_settings,
    render_frame,
)

RESULTS = Path(__file__).parent / "results"
SCENES = ("cam-pile", "cam-tote", "cam-gripper", "cam-full-tote")
KEYS = ("gt_regions", "correct", "over", "under", "missed")
MIN_REGION = 1000


def inverse_heights(depth: np.ndarray, d0: float) -> np.ndarray:
    """``d0**2 / depth``: larger = closer, NaN where ``depth`` is not a positive number."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(depth > 0, d0 * d0 / depth, np.nan)


def one_frame(job: tuple[str, int, str]) -> dict[str, Any]:
    """Hoover counts of one frame, segmented as depth and as inverse depth."""
    name, seed, model = job
    with tempfile.TemporaryDirectory() as tmp:
        stem, info, gt = render_frame(Path(tmp) / "frames", name, seed, (480, 640),
                                      camera=model)
        raw = read_image(stem.with_name(stem.name + ".png"))
    camera = info["camera"]
    depth = depth_in_mm(raw, camera)
    d0 = float(np.nanmedian(depth))
    as_depth = load_config(preset=PRESET, overrides=parse_settings(frame_settings(info, [])))
    as_inverse = load_config(overrides={"input": {"units_per_pixel": d0 / float(camera["fx"]),
                                                  "metres_per_unit": 0.001}})
    truth = np.where(np.isfinite(depth), gt, 0)
    out: dict[str, Any] = {"scene": name, "seed": seed}
    for tag, image, config in (("depth", raw, as_depth),
                               ("inverse", inverse_heights(depth, d0), as_inverse)):
        labels = run_pipeline(image, config).labels
        counts = hoover_compare(truth, labels, tolerance=0.8, min_region=MIN_REGION).counts()
        out[tag] = {k: counts[k] for k in KEYS}
    return out


def summarise(frames: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, int]]]:
    """Counts summed per scene and over all, for each way."""
    table: dict[str, dict[str, dict[str, int]]] = {}
    for f in frames:
        for key in (f["scene"], "all"):
            for tag in ("depth", "inverse"):
                row = table.setdefault(key, {}).setdefault(tag, dict.fromkeys(KEYS, 0))
                row.update(Counter(row) + Counter(f[tag]))
    return table


def markdown(table: dict[str, dict[str, dict[str, int]]], seeds: str, camera: str = "sr300"
             ) -> str:
    """The summary as a Markdown table."""
    lines = ["# Segmenting depth or inverse depth (benchmarks/inverse_depth.py)", "",
             f"rangeseg {__version__}; seeds {seeds}; 640x480 synthetic camera frames "
             f"(camera {camera}); "
             f"Hoover's metric at T = 0.8 on surfaces of {MIN_REGION} valid px or more. "
             "depth: `--preset tenth-mm-depth` + intrinsics; inverse: the defaults on "
             "d0^2 / depth (mm), no intrinsics.", "",
             "| scene | GT surfaces | correct (depth -> inverse) | over | under | missed |",
             "|---|---|---|---|---|---|"]
    for key in sorted(table, key=lambda k: k == "all"):  # "all" last
        d, i = table[key]["depth"], table[key]["inverse"]
        lines.append(f"| {key} | {d['gt_regions']} | {d['correct']} -> {i['correct']} | "
                     f"{d['over']} -> {i['over']} | {d['under']} -> {i['under']} | "
                     f"{d['missed']} -> {i['missed']} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="300-309", help="e.g. 300-309 or 325,330")
    parser.add_argument("--scenes", default=",".join(SCENES),
                        help="camera scenes with items (default: all four)")
    parser.add_argument("--camera", choices=tuple(CAMERAS), default="sr300",
                        help="the synthetic camera (default sr300)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=RESULTS / "inverse_depth",
                        help="results path without suffix")
    args = parser.parse_args(argv)
    names = checked_scenes(parser, args.scenes, SCENES)
    seeds = checked_seeds(parser, args.seeds)
    if args.jobs < 1:
        parser.error(f"--jobs {args.jobs}: expected 1 or more")
    jobs = [(name, seed, args.camera) for name in names for seed in seeds]
    with ProcessPoolExecutor(args.jobs) as pool:
        frames = list(pool.map(one_frame, jobs))
    table = summarise(frames)
    text = markdown(table, args.seeds, args.camera)
    print(text)
    args.out.with_suffix(".json").write_text(json.dumps(
        {"version": __version__, "seeds": args.seeds, "camera": args.camera, "summary": table,
         "frames": frames},
        indent=1) + "\n")
    args.out.with_suffix(".md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
