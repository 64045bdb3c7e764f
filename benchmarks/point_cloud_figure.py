"""The README's picture of a labelled point cloud: the ARC bin frame's ``points.ply``.

Runs ``rangeseg run`` on ``sample_data/arc/bin-scene.depth.png`` as ``make
run`` does, with ``--ply``; reads ``points.ply`` and ``holdsite.ply`` back
with plyfile and draws a matplotlib 3-D scatter in the camera frame
(metres): each point in its surface's colour of ``labels.png``, the
holdsite's footprint and approach arrow in black, nearer the camera higher.
Every point is drawn but the farthest 0.5 % on each axis (stray pixels).
Usage::

    python benchmarks/point_cloud_figure.py [OUT.png]   # default docs/figures/point-cloud.png
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from plyfile import PlyData  # noqa: E402

from rangeseg_cli.batch.render import label_colors  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ARC = ROOT / "sample_data" / "arc"


def run(out: Path) -> Path:
    """``rangeseg run ... --ply`` on the bin frame; the path stem of its outputs."""
    rangeseg = Path(sys.executable).with_name("rangeseg")
    subprocess.run([str(rangeseg), "run", str(ARC / "bin-scene.depth.png"), "--preset",
                    "tenth-mm-depth", "--intrinsics", str(ARC / "bin-camera-intrinsics.txt"),
                    "--background", str(ARC / "empty" / "bin-background.depth.png"),
                    "-o", str(out), "--ply", "-q"], check=True)
    return out / "bin-scene.depth"


def view(xyz: np.ndarray) -> np.ndarray:
    """Camera frame (x right, y down, z ahead) to the plot's (x, -y, -z): nearer is higher."""
    return xyz * np.array([1.0, -1.0, -1.0])


def draw(stem: Path, target: Path) -> None:
    v = PlyData.read(f"{stem}.points.ply")["vertex"].data
    site = PlyData.read(f"{stem}.holdsite.ply")
    hv = view(np.stack([site["vertex"][k] for k in "xyz"], axis=1))
    pts = view(np.stack([v["x"], v["y"], v["z"]], axis=1))
    lo, hi = np.percentile(pts, [0.5, 99.5], axis=0)  # a few stray pixels far off
    keep = np.all((pts >= lo) & (pts <= hi), axis=1)
    pts, v = pts[keep], v[keep]
    fig = plt.figure(figsize=(6.4, 4.8), dpi=100)
    ax = fig.add_subplot(projection="3d", computed_zorder=False)  # the site on top
    ax.scatter(*pts.T, c=label_colors(v["label"]) / 255.0, s=0.5, marker=".",
               linewidths=0, depthshade=False, rasterized=True)
    for a, b in site["edge"].data:
        ax.plot(*hv[[a, b]].T, color="black", linewidth=2, zorder=3)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("-y (m)")
    ax.set_zlabel("-depth (m)")
    ax.view_init(elev=50, azim=-75)
    ax.set_box_aspect(np.ptp(pts, axis=0), zoom=1.05)
    fig.subplots_adjust(left=0, right=0.95, bottom=0.05, top=1)
    fig.savefig(target, dpi=100)
    print(f"wrote {target} ({target.stat().st_size // 1024} KB, {len(v)} points drawn)")


def main() -> None:
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT / "docs/figures/point-cloud.png"
    with tempfile.TemporaryDirectory() as tmp:
        draw(run(Path(tmp)), target)


if __name__ == "__main__":
    main()
