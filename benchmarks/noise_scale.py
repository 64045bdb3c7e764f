"""How a frame's error grows with the extent of the surface fitted (issue 33, a measurement).

The fit test of the refinement asks whether one surface of order <= 2
explains a region to ``[refine] fit_factor`` times the image's noise, and
:func:`rangeseg_cli.stages.noise.estimate_noise` measures that noise from
the residual of a 5-tap filter: a pixel-scale figure. Where the noise is
white (the paper's scenes, the synthetic camera of ``rangeseg synth
--scenes cam-*``) a quadric fitted to a larger square leaves the same RMS
error; where it is correlated (a real camera smooths its depth) the RMS
error grows with the square, and large real surfaces fail a test set at
the pixel scale. This script prints, per frame, the estimate and the 25th
and 50th percentiles of the RMS error of a least-squares quadric in every
``k x k`` window (at a stride) whose pixels are all valid, for the
window sides of :data:`SIDES`.

Frames: the ARC SR300 frames and their empty totes in ``ARC`` (a folder of
the four ``*.depth.png``, the empty totes also in its ``empty/``:
``sample_data/arc`` or the team's shared ``data/arc-suction``), read as
``sample_data/arc/suction.toml`` reads its frame (mm), and the synthetic
camera's frames (``benchmarks/real_cells.py``'s rendering) of ``--seeds``.

Usage::

    .venv/bin/python benchmarks/noise_scale.py ARC --seeds 300-301

Writes ``benchmarks/results/noise_scale.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from rangeseg_cli import __version__
from rangeseg_cli.batch.io import read_image
from rangeseg_cli.config import load_config, parse_settings
from rangeseg_cli.stages.noise import estimate_noise
from rangeseg_cli.stages.rangeimage import to_heights

sys.path.insert(0, str(Path(__file__).parent))
from real_cells import PRESET, checked_seeds, frame_settings, render_frame  # noqa: E402

RESULTS = Path(__file__).parent / "results"
ROOT = Path(__file__).resolve().parents[1]
#: Sides of the square windows, pixels.
SIDES = (5, 9, 15, 21, 31)
#: Windows at every STRIDE-th row and column.
STRIDE = 4
ARC_FRAMES = ("suction-background", "suction-scene", "bin-background", "bin-scene")
CAMERA_SCENES = ("cam-pile", "cam-tote")


def quadric_rms(z: np.ndarray, side: int, stride: int = STRIDE) -> np.ndarray:
    """RMS error of the least-squares quadric in each ``side x side`` window of valid pixels.

    Parameters
    ----------
    z
        float64 (H, W) heights, NaN where invalid.
    side
        Odd window side, at least 3 pixels.
    stride
        Windows at every ``stride``-th row and column.

    Returns
    -------
    numpy.ndarray
        float64 (n,): per window with no NaN, ``sqrt(SSE / (side^2 - 6))``.
    """
    if side < 3 or side % 2 == 0:
        raise ValueError(f"`side` = {side}: expected an odd number of 3 or more")
    windows = sliding_window_view(np.asarray(z, np.float64), (side, side))[::stride, ::stride]
    flat = windows.reshape(-1, side * side)
    flat = flat[np.isfinite(flat).all(axis=1)]
    r, c = (a.ravel() - side // 2 for a in np.mgrid[:side, :side])
    design = np.column_stack([np.ones(side * side), c, r, c * c, c * r, r * r]).astype(float)
    residual = np.eye(side * side) - design @ np.linalg.pinv(design)
    return np.sqrt(((flat @ residual.T) ** 2).sum(axis=1) / (side * side - 6))


def profile(z: np.ndarray) -> dict[str, Any]:
    """The estimate and the quartile and median of :func:`quadric_rms` per window side."""
    row: dict[str, Any] = {"estimate": round(estimate_noise(z), 3)}
    for side in SIDES:
        rms = quadric_rms(z, side)
        row[str(side)] = ([round(float(v), 3) for v in np.percentile(rms, [25, 50])]
                          if rms.size else None)
    return row


def arc_frame(folder: Path, name: str) -> Path | None:
    """``folder/<name>.depth.png``, else in ``folder/empty`` (as ``sample_data/arc`` keeps them)."""
    for path in (folder / f"{name}.depth.png", folder / "empty" / f"{name}.depth.png"):
        if path.is_file():
            return path
    return None


def arc_heights(folder: Path) -> dict[str, np.ndarray]:
    """The ARC frames in mm as ``sample_data/arc/suction.toml`` reads the SR300's (no filter)."""
    cfg = load_config(ROOT / "sample_data" / "arc" / "suction.toml").input
    return {name: to_heights(read_image(arc_frame(folder, name)), cfg)  # type: ignore[arg-type]
            for name in ARC_FRAMES}


def camera_heights(seeds: list[int]) -> dict[str, np.ndarray]:
    """The synthetic camera's frames of ``seeds``, in mm as real_cells.py reads them."""
    out = {}
    with tempfile.TemporaryDirectory(prefix="noise_scale-") as tmp:
        for name in CAMERA_SCENES:
            for seed in seeds:
                stem, info, _ = render_frame(Path(tmp), name, seed, (480, 640))
                cfg = load_config(preset=PRESET,
                                  overrides=parse_settings(frame_settings(info, []))).input
                out[f"{name} {seed}"] = to_heights(read_image(stem.with_name(stem.name + ".png")),
                                                   cfg)
    return out


def markdown(rows: dict[str, dict[str, Any]]) -> str:
    """The table: per frame the estimate and the RMS errors per window side."""
    lines = ["# Error against the extent of the fit (benchmarks/noise_scale.py)", "",
             f"rangeseg {__version__}. Per frame (mm): the noise estimate of the pipeline, and "
             "the 25th / 50th percentile of the RMS error of a quadric fitted to each k x k "
             "window of valid pixels.", "",
             "| frame | estimate | " + " | ".join(f"{k} x {k}" for k in SIDES) + " |",
             "|---|---|" + "---|" * len(SIDES)]
    for name, row in rows.items():
        cells = [("-" if row[str(k)] is None else "{:.2f} / {:.2f}".format(*row[str(k)]))
                 for k in SIDES]
        lines.append(f"| {name} | {row['estimate']:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("arc", type=Path, help="folder of the four ARC depth frames")
    parser.add_argument("--seeds", default="300-301", help="synthetic camera seeds")
    parser.add_argument("--out", type=Path, default=RESULTS / "noise_scale",
                        help="results path without suffix")
    args = parser.parse_args(argv)
    missing = [n for n in ARC_FRAMES if arc_frame(args.arc, n) is None]
    if missing:
        parser.error(f"{args.arc}: no {missing[0]}.depth.png (the ARC frames' folder)")
    seeds = checked_seeds(parser, args.seeds)
    frames = {**arc_heights(args.arc), **camera_heights(seeds)}
    rows = {name: profile(z) for name, z in frames.items()}
    text = markdown(rows)
    print(text)
    args.out.with_suffix(".json").write_text(json.dumps(
        {"version": __version__, "sides": list(SIDES), "stride": STRIDE, "frames": rows},
        indent=1) + "\n")
    args.out.with_suffix(".md").write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
