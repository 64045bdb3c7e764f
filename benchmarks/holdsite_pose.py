"""How far the holdsites' reported pose is from the true surface.

Renders every synthetic scene at noise 0, 1, 2 for the given seeds, runs
the pipeline with the defaults and, for the chosen site
and each runner-up whose 3x3 neighbourhood lies on one ground-truth face,
compares the reported elevation and normal with the noise-free heights of
the scene (normal from their central differences). Prints, per noise level,
the median, 95th percentile and largest elevation error (depth
units) and normal angle (degrees).

Usage::

    .venv/bin/python benchmarks/holdsite_pose.py               # seeds 0, 1, 2
    .venv/bin/python benchmarks/holdsite_pose.py --seeds 3,4,5
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from rangeseg_cli.config import load_config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.synth.scenes import SCENES, Scene, render_scene


def pose_errors(scene: Scene, site: object) -> tuple[float, float] | None:
    """(elevation error, normal angle in degrees) of a site, or None off a single face."""
    r, c = site.row, site.col  # type: ignore[attr-defined]
    h, gt = scene.heights, scene.gt
    near = gt[r - 1:r + 2, c - 1:c + 2]
    if near.shape != (3, 3) or near[1, 1] == 0 or not (near == near[1, 1]).all():
        return None
    true = np.array([-(h[r, c + 1] - h[r, c - 1]) / 2, -(h[r + 1, c] - h[r - 1, c]) / 2, 1.0])
    cosine = float(np.dot(site.normal, true) / np.linalg.norm(true))  # type: ignore[attr-defined]
    return (abs(site.elevation - h[r, c]),  # type: ignore[attr-defined]
            math.degrees(math.acos(min(1.0, cosine))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default="0,1,2", help="comma-separated seeds (default 0,1,2)")
    args = parser.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    config = load_config()
    print("| σ | sites | elevation error median / p95 / max "
          "| angle (°) median / p95 / max |")
    print("|---|---|---|---|")
    for noise in (0.0, 1.0, 2.0):
        errors: list[tuple[float, float]] = []
        for name in SCENES:
            for seed in seeds:
                scene = render_scene(name, noise=noise, seed=seed)
                found = run_pipeline(scene.image, config).holdsite
                if found.holdsite is None:
                    continue
                for site in (found.holdsite, *found.candidates):
                    e = pose_errors(scene, site)
                    if e is not None:
                        errors.append(e)
        a = np.array(errors).reshape(-1, 2)
        stats = [f"{np.median(a[:, k]):.2f} / {np.percentile(a[:, k], 95):.2f} / "
                 f"{a[:, k].max():.2f}" for k in (0, 1)]
        print(f"| {noise:g} | {len(a)} | {stats[0]} | {stats[1]} |")


if __name__ == "__main__":
    main()
