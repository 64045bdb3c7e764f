"""The README's picture of the real tote frames: the holdsite with and without the empty tote.

For each camera of ``sample_data/arc`` (the SR300 "suction" frame and the
"bin" frame), three overlays side by side, run as a user would (``--preset
tenth-mm-depth``, the camera's intrinsics file, nothing hand-tuned):

1. the frame with its empty-tote frame as ``--background``;
2. the frame alone;
3. the empty-tote frame alone ("nothing to pick": no square).

Surfaces in colour, the chosen site a filled white square of the gripper's
footprint (20 mm), the runners-up hollow squares. Usage::

    python benchmarks/real_frames_figure.py [OUT.png]   # default docs/figures/real-frames.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.batch import io, render
from rangeseg_cli.cell.intrinsics import read_intrinsics

ARC = Path(__file__).resolve().parent.parent / "sample_data" / "arc"
GAP = 8


def panels(camera: str) -> list[np.ndarray]:
    """The three overlays of one camera (with background, alone, empty tote)."""
    k = read_intrinsics(ARC / f"{camera}-camera-intrinsics.txt")
    config = load_config(preset="tenth-mm-depth",
                         overrides=k.settings())
    scene = io.read_image(ARC / f"{camera}-scene.depth.png")
    empty = io.read_image(ARC / "empty" / f"{camera}-background.depth.png")
    out = []
    for image, background in ((scene, empty), (scene, None), (empty, None)):
        result = run_pipeline(image, config, background=background)
        doc = result.holdsite.to_dict()
        site = doc["holdsite"]
        where = f"site at row {site['row']}, col {site['col']}" if site else doc["reason"][:60]
        print(f"{camera}: {'with background' if background is not None else 'alone'}: {where}")
        out.append(render.overlay(result.labels, doc, heights=result.heights))
    return out


def compose(rows: list[list[np.ndarray]]) -> np.ndarray:
    """Panels in a grid with white gaps."""
    lines = []
    for row in rows:
        h = row[0].shape[0]
        gap = np.full((h, GAP, 3), 255, np.uint8)
        parts = [p for panel in row for p in (panel, gap)][:-1]
        lines.append(np.hstack(parts))
    width = lines[0].shape[1]
    bar = np.full((GAP, width, 3), 255, np.uint8)
    return np.vstack([p for line in lines for p in (line, bar)][:-1])


def main() -> None:
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else (
        Path(__file__).resolve().parent.parent / "docs" / "figures" / "real-frames.png")
    picture = compose([panels(camera) for camera in ("suction", "bin")])
    io.write_png(target, picture)
    print(f"wrote {target}")


if __name__ == "__main__":
    main()
