"""Speed against quality of the passes beyond the paper (issues 7 and 9), one pass at a time.

The defaults add to the paper's pipeline (``--preset paper``) the passes of
``[refine] passes`` (the fit-test split, the recovery of narrow faces, the
fill of edge pixels, the merges, the recut, ...). Each costs time and gains
correct detections. For every variant of :data:`VARIANTS` -- the defaults,
each pass left out alone (``without facets``: ``--set refine.passes=[...]``
with every other pass, :func:`without`), the numeric keys of :data:`SETS`
and ``--preset paper`` -- this script measures, in one process:

* the median time of ``run_pipeline`` (automatic threads) on the bench's
  frames: the 128x128 and 640x480 bin piles of ``bench_pipeline.py`` and the
  real SR300 frame of ``sample_data/arc`` with ``suction.toml``; the variants
  run interleaved in every repeat, so that load on the machine hits them
  alike;
* the correct detections (Hoover et al. at T = 0.8, GT regions of >= 50
  pixels) over every synthetic scene at noise 0, 1 and 2, as
  ``quality.py`` counts them.

It prints one markdown table (times in ms, and per noise level the correct
detections with their change against the defaults) and writes
``benchmarks/results/tradeoffs.{json,md}``. The README's "Speed or quality"
table comes from it.

Usage::

    .venv/bin/python benchmarks/tradeoffs.py                 # seeds 0-8, 5 repeats (~20 min)
    .venv/bin/python benchmarks/tradeoffs.py --seeds 0,1,2 --repeats 3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_pipeline import (  # noqa: E402
    QUICK_SIZES,
    REAL_CONFIG,
    REAL_FRAME,
    RESULTS,
    bin_scene,
    interleaved,
)
from quality import NOISES, measure, scene_list, seed_list  # noqa: E402

from rangeseg_cli.batch.io import read_image  # noqa: E402
from rangeseg_cli.config import (  # noqa: E402
    PASS_NEEDS,
    PRESETS,
    REFINE_PASSES,
    Config,
    load_config,
    parse_settings,
)
from rangeseg_cli.pipeline import run_pipeline  # noqa: E402
from rangeseg_cli.synth.scenes import SCENES  # noqa: E402


def without(name: str) -> str:
    """The ``--set`` item that leaves the pass ``name`` out of the defaults' ``[refine] passes``.

    The passes that need it (``PASS_NEEDS``: the bridge, the fill's) go with it.
    """
    if name not in REFINE_PASSES:
        raise ValueError(f"{name!r} is not a pass of [refine] passes; allowed: "
                         + ", ".join(REFINE_PASSES))
    gone = {name} | {p for p, needs in PASS_NEEDS.items() if name in needs}
    return "refine.passes=[" + ", ".join(f'"{p}"' for p in REFINE_PASSES if p not in gone) + "]"


#: The numeric keys of ``[refine]`` set to turn a rule off, as ``--set`` items.
SETS: tuple[str, ...] = ("refine.crease_evidence=0",)

#: Name (``without <pass>``, or as on the command line) and the ``--set`` item of each
#: variant between the defaults and the paper.
ITEMS: dict[str, str] = {**{f"without {name}": without(name) for name in REFINE_PASSES},
                         **{f"--set {item}": item for item in SETS}}

#: Name and the overrides of each variant.
VARIANTS: tuple[tuple[str, dict[str, dict[str, Any]]], ...] = (
    ("defaults", {}),
    *((name, parse_settings([item])) for name, item in ITEMS.items()),
    ("--preset paper", PRESETS["paper"]),
)


def variant_config(base: str | Path | None, overrides: dict[str, dict[str, Any]]) -> Config:
    """The configuration of ``base`` (a TOML file or the defaults) with ``overrides`` on top."""
    return load_config(base, overrides=overrides or None)


def frames() -> dict[str, tuple[np.ndarray, str | Path | None]]:
    """The timed frames and the configuration file each is read with (None: the defaults).

    The bench's piles (``bench_pipeline.bench_frame``: seed rows + cols) and its real frame.
    """
    piles: dict[str, tuple[np.ndarray, str | Path | None]] = {
        f"{cols}x{rows} pile": (bin_scene(rows, cols, seed=rows + cols), None)
        for rows, cols in QUICK_SIZES}
    return {**piles, "SR300 frame": (read_image(str(REAL_FRAME)), REAL_CONFIG)}


def time_variants(repeats: int) -> dict[str, dict[str, float]]:
    """Median ms of ``run_pipeline`` per variant and frame, the variants interleaved."""
    tasks: dict[str, Callable[[], Any]] = {}
    for frame, (image, base) in frames().items():
        for name, overrides in VARIANTS:
            config = variant_config(base, overrides)
            tasks[f"{name}|{frame}"] = (lambda im=image, c=config: run_pipeline(im, c))
    times = interleaved(tasks, repeats)
    out: dict[str, dict[str, float]] = {name: {} for name, _ in VARIANTS}
    for key, seconds in times.items():
        name, frame = key.split("|")
        out[name][frame] = float(np.median(seconds)) * 1e3
    return out


def quality_variants(seeds: tuple[int, ...], scenes: list[str]) -> dict[str, dict[str, int]]:
    """Correct detections per variant and noise level (``quality.measure``)."""
    out: dict[str, dict[str, int]] = {}
    for name, overrides in VARIANTS:
        rows, _, _ = measure(variant_config(None, overrides), scenes, seeds, False)
        out[name] = {f"{noise:g}": int(rows[noise]["correct"]) for noise in NOISES}
        out[name]["gt_regions"] = int(rows[NOISES[0]]["gt_regions"])
    return out


def markdown(report: dict[str, Any]) -> str:
    """The table: ms per frame, correct detections per noise level (change vs the defaults)."""
    ms, correct = report["median_ms"], report["correct"]
    frame_names = list(next(iter(ms.values())))
    base = correct["defaults"]
    head = ([f"{f} ms" for f in frame_names]
            + [f"correct σ = {n:g} (of {base['gt_regions']})" for n in NOISES])
    lines = [f"{report['date']}, seeds {','.join(map(str, report['seeds']))}, medians of "
             f"{report['repeats']} interleaved runs (automatic threads); \"without X\": "
             "`--set refine.passes=[...]` with every pass but X.", "",
             "| variant | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
    for name, _ in VARIANTS:
        cells = [f"{ms[name][f]:.0f}" for f in frame_names]
        for n in NOISES:
            value, delta = correct[name][f"{n:g}"], correct[name][f"{n:g}"] - base[f"{n:g}"]
            cells.append(f"{value}" if name == "defaults" else f"{value} ({delta:+d})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", default=tuple(range(9)), type=seed_list)
    parser.add_argument("--scenes", default=list(SCENES), type=scene_list,
                        help="comma-separated scene names")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs per variant and frame")
    parser.add_argument("--results", type=Path, default=RESULTS, help="output folder")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats {args.repeats}: allowed an integer >= 1")
    report: dict[str, Any] = {"date": time.strftime("%Y-%m-%d %H:%M"), "seeds": list(args.seeds),
                              "repeats": args.repeats,
                              "median_ms": time_variants(args.repeats),
                              "correct": quality_variants(args.seeds, args.scenes)}
    text = markdown(report)
    print(text)
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "tradeoffs.json").write_text(json.dumps(report, indent=2) + "\n")
    (args.results / "tradeoffs.md").write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
