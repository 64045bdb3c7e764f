"""Fig. 10-style strips: each stage of the segmentation side by side.

For every range image given (default: the sample images), writes one PNG
strip: (a) original, (b) step (jump) edges, (c) roof edges, (d) step and
roof edges, (e) linked edge map with components, (f) final segmentation with
the holdsite, as in Al-Hujazi & Sood (1990), Fig. 10.

Usage::

    .venv/bin/python benchmarks/fig10_strips.py [IMAGES...] [-o docs/figures]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.batch import io, render
from rangeseg_cli.config import Config
from rangeseg_cli.pipeline import PipelineResult

ROOT = Path(__file__).resolve().parent.parent
GAP = 4


def _rgb(img: np.ndarray) -> np.ndarray:
    return np.repeat(img[:, :, None], 3, axis=2) if img.ndim == 2 else img


def panels(result: PipelineResult, config: Config) -> list[np.ndarray]:
    """The six panels (a)-(f) of Fig. 10 as uint8 RGB images."""
    maps = result.edge_maps
    linked = render.label_colors(result.components)
    linked[result.edges > 0] = 255
    return [
        _rgb(render.height_image(result.heights)),
        _rgb(render.mask_image(maps.step)),
        _rgb(render.mask_image(maps.roof)),
        _rgb(render.mask_image(maps.step | maps.roof)),
        linked,
        render.overlay(result.labels, result.holdsite, config.holdsite.size,
                       heights=result.heights),
    ]


def strip(images: list[np.ndarray]) -> np.ndarray:
    """Panels side by side with a white gap."""
    h = images[0].shape[0]
    gap = np.full((h, GAP, 3), 255, np.uint8)
    parts: list[np.ndarray] = []
    for img in images:
        parts += [img, gap]
    return np.concatenate(parts[:-1], axis=1)


def config_for(path: Path) -> Config:
    """The sample folder's own settings where it has them (the real frame)."""
    toml = sorted(path.parent.glob("*.toml"))
    return load_config(toml[0]) if toml else load_config()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("images", nargs="*", type=Path)
    parser.add_argument("-o", "--out", type=Path, default=ROOT / "docs" / "figures")
    args = parser.parse_args(argv)
    paths = args.images or sorted(
        p for p in (ROOT / "sample_data").rglob("*")
        if p.suffix == ".png" and "-n1" not in p.name and ".gt." not in p.name)
    for path in paths:
        config = config_for(path)
        result = run_pipeline(io.read_image(path), config, name=str(path))
        target = args.out / f"{path.name.split('.')[0]}-fig10.png"
        io.write_png(target, strip(panels(result, config)))
        print(f"{path} -> {target}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
