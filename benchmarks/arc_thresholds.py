"""The SR300 frames with hand-tuned thresholds and with thresholds that follow the sensor.

Runs the two Intel RealSense SR300 frames of the ARC 2017 data (``suction-scene``
and ``bin-scene``, depth in 0.1 mm, Zeng et al. 2018) twice: with the
hand-tuned settings that ``sample_data/arc/suction.toml`` held before issue 32
(step 2, roof 2 / 1.5 mm, fixed) and with ``--preset tenth-mm-depth`` and the
frame's intrinsics alone (the thresholds of Sec. V-1, V-2 scaled to the
lateral scale and the noise: :mod:`rangeseg_cli.stages.noise`). Writes one PNG per
frame, depth and the two label images side by side, and the numbers below.

There is no ground truth; the empty tote of the same camera
(``*-background.depth.png``) tells item from support instead. A valid pixel
is *support* where its depth is within ``SUPPORT_MM`` of the empty tote's,
*item* where it is ``ITEM_MM`` or more closer (others are not counted). Per
configuration:

* ``regions``: final regions of ``MIN_REGION`` pixels or more;
* ``largest``: fraction of the valid pixels in the largest region;
* ``straddling``: regions with ``MIN_REGION`` or more support pixels and as
  many item pixels, each at least ``MIN_SHARE`` of the region: an item leaked
  into the tote (or a tote wall into an item); ``straddling_px``: their
  item pixels, as a fraction of all item pixels;
* ``items_separated``: fraction of the item pixels that lie in regions of
  ``MIN_REGION`` or more pixels that are at least ``PURE`` item;
* ``unlabelled``: fraction of the valid pixels left without a region.

Usage (``ARC``: a folder holding the four frames and the two intrinsics
files, e.g. the team's shared ``data/arc-suction``; ``sample_data/arc`` holds
the scenes, its ``empty/`` the empty totes)::

    .venv/bin/python benchmarks/arc_thresholds.py ARC \\
        --figures docs/figures --json benchmarks/results/arc_thresholds.json
    .venv/bin/python benchmarks/arc_thresholds.py ARC --sweep
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from rangeseg_cli.batch import io, render
from rangeseg_cli.config import Config, load_config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.stages.noise import lateral_scale, sensor_config

FRAMES = ("suction", "bin")
#: ``sample_data/arc/suction.toml`` before issue 32 (its intrinsics: the frame's own).
HAND_TUNED: dict[str, dict[str, Any]] = {
    "input": {"auto_thresholds": False},
    "step": {"threshold": 2.0},
    "roof": {"threshold_a": 2.0, "threshold_b": 1.5},
}
SUPPORT_MM, ITEM_MM = 4.0, 10.0
MIN_REGION, MIN_SHARE, PURE = 200, 0.05, 0.9
#: ``--sweep``: multiples of the sensor-scaled thresholds tried.
SWEEP = (0.5, 0.67, 0.8, 1.0, 1.25, 1.5)


def read_frame(data: Path, frame: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw depth of the scene and of the empty tote, and the 3x3 camera matrix."""
    scene = io.read_image(data / f"{frame}-scene.depth.png")
    empty = io.read_image(data / f"{frame}-background.depth.png")
    camera = np.loadtxt(data / f"{frame}-camera-intrinsics.txt")
    return scene, empty, camera


def configs(camera: np.ndarray) -> dict[str, Config]:
    """The hand-tuned settings and the preset with the intrinsics alone."""
    intrinsics = {"intrinsics": [float(camera[0, 0]), float(camera[1, 1]),
                                 float(camera[0, 2]), float(camera[1, 2])]}
    return {
        "hand-tuned": load_config(preset="tenth-mm-depth", overrides={
            **HAND_TUNED, "input": {**HAND_TUNED["input"], **intrinsics}}),
        "sensor": load_config(preset="tenth-mm-depth", overrides={"input": intrinsics}),
    }


def classes(scene: np.ndarray, empty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Support and item masks from the empty tote (depth in 0.1 mm, 0 = no reading)."""
    both = (scene > 0) & (empty > 0)
    rise = (empty.astype(np.float64) - scene.astype(np.float64)) / 10.0  # mm closer
    return both & (np.abs(rise) <= SUPPORT_MM), both & (rise >= ITEM_MM)


def scores(labels: np.ndarray, valid: np.ndarray, support: np.ndarray, item: np.ndarray
           ) -> dict[str, float]:
    """The numbers of the module docstring for one label image."""
    n = int(labels.max(initial=0)) + 1
    size = np.bincount(labels[valid], minlength=n)
    on_support = np.bincount(labels[support], minlength=n)
    on_item = np.bincount(labels[item], minlength=n)
    size[0] = on_support[0] = on_item[0] = 0
    big = size >= MIN_REGION
    share = np.maximum(size, 1)
    straddle = (big & (on_support >= MIN_REGION) & (on_item >= MIN_REGION)
                & (on_support >= MIN_SHARE * share) & (on_item >= MIN_SHARE * share))
    pure = big & (on_item >= PURE * share)
    items = max(int(item.sum()), 1)
    return {
        "regions": int(big.sum()),
        "largest": round(float(size.max(initial=0)) / max(int(valid.sum()), 1), 4),
        "straddling": int(straddle.sum()),
        "straddling_px": round(float(on_item[straddle].sum()) / items, 4),
        "items_separated": round(float(on_item[pure].sum()) / items, 4),
        "unlabelled": round(float(np.count_nonzero(valid & (labels == 0)))
                            / max(int(valid.sum()), 1), 4),
    }


def run(scene: np.ndarray, empty: np.ndarray, config: Config) -> tuple[np.ndarray,
                                                                       dict[str, Any]]:
    """Labels and numbers of one configuration on one frame."""
    result = run_pipeline(scene, config, stages=3)
    labels = np.asarray(result.labels)
    z = result.heights
    used = sensor_config(config, z, result.noise_sigma)
    support, item = classes(scene, empty)
    numbers: dict[str, Any] = scores(labels, ~np.isnan(z), support, item)
    numbers["thresholds_mm"] = [round(used.step.threshold, 3), round(used.roof.threshold_a, 3),
                                round(used.roof.threshold_b, 3)]
    numbers["mm_per_pixel"] = round(lateral_scale(z, config.input), 4)
    numbers["noise_mm"] = round(result.noise_sigma, 4)
    return labels, numbers


def figure(path: Path, title: str, panels: list[tuple[str, np.ndarray]]) -> None:
    """Panels side by side with their captions, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(5.2 * len(panels), 4.6), dpi=100)
    for ax, (caption, image) in zip(axes, panels, strict=True):
        ax.imshow(image, cmap="gray", interpolation="nearest")
        ax.set_title(caption, fontsize=9)
        ax.axis("off")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0.0, 0.0, 1.0, 0.93))
    fig.savefig(path)
    plt.close(fig)


def caption(name: str, n: dict[str, Any]) -> str:
    """A panel's caption: the configuration, its thresholds and numbers."""
    t = n["thresholds_mm"]
    return (f"{name}: step {t[0]:.2f}, roof {t[1]:.2f} / {t[2]:.2f} mm\n"
            f"{n['regions']} regions, largest {100 * n['largest']:.0f} % of valid px,\n"
            f"{n['straddling']} straddle tote and item, items separated "
            f"{100 * n['items_separated']:.0f} %")


def sweep(scene: np.ndarray, empty: np.ndarray, config: Config) -> list[dict[str, Any]]:
    """The numbers at multiples of the sensor-scaled thresholds (fixed at those values)."""
    z = run_pipeline(scene, config, stages=1)
    base = sensor_config(config, z.heights, z.noise_sigma)
    rows = []
    for m in SWEEP:
        fixed = load_config(preset="tenth-mm-depth", overrides={
            "input": {"auto_thresholds": False, "intrinsics": list(config.input.intrinsics)},
            "step": {"threshold": base.step.threshold * m},
            "roof": {"threshold_a": base.roof.threshold_a * m,
                     "threshold_b": base.roof.threshold_b * m}})
        _, numbers = run(scene, empty, fixed)
        rows.append({"multiple": m, **numbers})
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("data", type=Path,
                   help="folder of the ARC frames, their empty totes and intrinsics")
    p.add_argument("--figures", type=Path, default=None, help="write the PNGs here")
    p.add_argument("--json", type=Path, default=None, help="write the numbers here")
    p.add_argument("--sweep", action="store_true",
                   help="also the numbers at multiples of the sensor-scaled thresholds")
    args = p.parse_args(argv)
    out: dict[str, Any] = {}
    for frame in FRAMES:
        scene, empty, camera = read_frame(args.data, frame)
        panels = [("depth (0.1 mm; black = no reading)", render.height_image(
            np.where(scene > 0, -scene.astype(np.float64), np.nan)))]
        out[frame] = {}
        for name, config in configs(camera).items():
            labels, numbers = run(scene, empty, config)
            out[frame][name] = numbers
            panels.append((caption(name, numbers), render.label_colors(labels)))
            print(frame, name, json.dumps(numbers))
        if args.sweep:
            out[frame]["sweep"] = sweep(scene, empty, configs(camera)["sensor"])
            for row in out[frame]["sweep"]:
                print(frame, "sweep", json.dumps(row))
        if args.figures:
            args.figures.mkdir(parents=True, exist_ok=True)
            figure(args.figures / f"arc-{frame}-thresholds.png",
                   f"ARC {frame}-scene (0.1 mm depth): hand-tuned thresholds vs --preset "
                   "tenth-mm-depth + intrinsics", panels)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
