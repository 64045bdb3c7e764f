"""Usable holdsites on synthetic depth-camera frames of bin-picking cells (issue 32).

Renders held-out seeds of the camera scenes of ``rangeseg synth`` (an
SR300-like camera over piles on a table, in totes, with a gripper in view,
and empty totes) at 640x480 into a temporary folder, reads each frame back
from its PNG and runs the library's pipeline on it with ``--preset
tenth-mm-depth`` and the frame's intrinsics (``[input] intrinsics``),
plus any ``--set`` given here; with ``--background`` the frame of the empty
tote or table is passed too. Each holdsite is scored by the object-level
check of ``rangeseg eval`` (:func:`rangeseg_cli.synth.evaluate.check_object_holdsite`):
usable = the gripper window wholly on valid pixels of one pickable object
and the approach within the tilt limit of straight down (the world's
vertical, from the camera's recorded rotation); on an empty
tote, no holdsite is the right answer.

Prints a table per scene kind (usable / frames and %) and writes
``benchmarks/results/real_cells.json`` and ``.md``.

Usage::

    .venv/bin/python benchmarks/real_cells.py                    # seeds 100-119
    .venv/bin/python benchmarks/real_cells.py --background
    .venv/bin/python benchmarks/real_cells.py --seeds 100-104 --set holdsite.size=[21,21]
    .venv/bin/python benchmarks/real_cells.py --seeds 300-324 --dropouts 0.02
    .venv/bin/python benchmarks/real_cells.py --seeds 300-324 --noise 2
    .venv/bin/python benchmarks/real_cells.py --seeds 300-309 --camera-tilt 45

``--dropouts F`` sets a seeded share F of each frame's pixels to no reading
(speckle) before the run; ``--noise MM`` adds seeded Gaussian depth noise of
sigma MM millimetres to every reading (a noisier camera, or one farther
away); ``--camera-tilt DEG`` mounts the camera tilted from straight down;
``--left-band PX`` blanks the first PX columns (a RealSense D4xx's band of
no reading); the site is scored against the true scene.
"""

from __future__ import annotations

import argparse
import inspect
import json
import os
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from rangeseg_cli import __version__
from rangeseg_cli.batch.io import read_image, read_json
from rangeseg_cli.config import load_config, parse_settings
from rangeseg_cli.errors import ConfigError
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.synth.camera import CAMERA_SCENES, CAMERAS, camera_stem, write_camera_scenes
from rangeseg_cli.synth.evaluate import (
    DEFAULT_MAX_TILT,
    check_object_holdsite,
    footprint_at_depth,
    pickable_objects,
)

RESULTS = Path(__file__).parent / "results"
PRESET = "tenth-mm-depth"
DEFAULT_SEEDS = "100-119"


def parse_seeds(text: str) -> list[int]:
    """``"100-119"`` or ``"1,2,5"`` (or both, comma-separated) as a list of seeds.

    Raises ValueError for a part that is no number or a range that runs down.
    """
    seeds: list[int] = []
    for part in text.split(","):
        lo, _, hi = part.strip().partition("-")
        first, last = int(lo), int(hi or lo)
        if last < first:
            raise ValueError(f"{part!r} runs down")
        seeds.extend(range(first, last + 1))
    return seeds


def _size(text: str) -> tuple[int, int] | None:
    """``"480x640"`` as (rows, cols), None unless both are integers of 16 or more."""
    rows, _, cols = text.partition("x")
    try:
        size = (int(rows), int(cols))
    except ValueError:
        return None
    return size if min(size) >= 16 else None


def checked_seeds(parser: argparse.ArgumentParser, text: str) -> list[int]:
    """:func:`parse_seeds` of ``--seeds``, or a one-line usage error naming it."""
    try:
        seeds = parse_seeds(text)
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0:
        parser.error(f"--seeds {text!r}: expected seeds >= 0 as 300-324 or 1,2,5")
    return seeds


def checked_scenes(parser: argparse.ArgumentParser, text: str, allowed: Iterable[str]
                   ) -> list[str]:
    """The comma-separated ``--scenes``, or a one-line usage error naming the unknown ones."""
    allowed = list(allowed)
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in allowed]
    if unknown or not names:
        parser.error(f"--scenes: unknown {', '.join(unknown) or '(none given)'}; allowed: "
                     + ", ".join(allowed))
    return names


def frame_settings(info: dict[str, Any], extra: list[str]) -> list[str]:
    """The frame's intrinsics as ``--set`` items, then the extra ones (which win)."""
    cam = info["camera"]
    values = ", ".join(repr(float(cam[k])) for k in ("fx", "fy", "cx", "cy"))
    return [f"input.intrinsics=[{values}]"] + extra


def speckle(raw: np.ndarray, fraction: float, seed: int) -> np.ndarray:
    """``raw`` with a seeded ``fraction`` of its pixels set to 0 (no reading), as speckle."""
    if fraction <= 0:
        return raw
    out = raw.copy()
    out[np.random.default_rng([seed, 99]).random(raw.shape) < fraction] = 0
    return out


def depth_noise(raw: np.ndarray, sigma_mm: float, metres_per_raw: float, seed: int
                ) -> np.ndarray:
    """``raw`` with seeded Gaussian noise of ``sigma_mm`` on its readings (0 stays 0)."""
    if sigma_mm <= 0:
        return raw
    step = sigma_mm / (1000.0 * metres_per_raw)  # in raw units
    noisy = raw + np.random.default_rng([seed, 98]).normal(0.0, step, raw.shape)
    top = np.iinfo(raw.dtype).max if raw.dtype.kind in "ui" else np.inf
    out = np.clip(np.round(noisy), 1, top).astype(raw.dtype)
    return np.where(raw > 0, out, raw)


def one_frame(job: tuple[str, int, tuple[int, int], list[str], bool, float, str, float,
                         float, float, int, str, float]) -> dict[str, Any]:
    """Render, run and score one frame (in a worker process)."""
    (name, seed, size, extra, background, max_tilt, tmp, dropouts, noise, mount, band, camera,
     soft) = job
    stem, info, gt = render_frame(Path(tmp) / camera_stem(name, seed), name, seed, size, mount,
                                  camera, soft)
    gt[:, :band] = 0  # no reading there: nothing to judge a window on
    config = load_config(preset=PRESET, overrides=parse_settings(frame_settings(info, extra)))
    kwargs: dict[str, Any] = {}
    if background and "background" in inspect.signature(run_pipeline).parameters:
        kwargs["background"] = read_image(stem.with_name(stem.name + ".gt.background.png"))
    start = time.perf_counter()
    raw = read_image(stem.with_name(stem.name + ".png"))
    raw[:, :band] = 0  # a D4xx's band of no reading along its left edge
    metres = float(info["camera"]["metres_per_raw"])
    result = run_pipeline(speckle(depth_noise(raw, noise, metres, seed), dropouts, seed),
                          config, **kwargs)
    seconds = time.perf_counter() - start
    doc = result.holdsite.to_dict()
    depth_mm = depth_in_mm(raw, info["camera"])
    height_mm = world_heights(depth_mm, info["camera"])
    window = (footprint_at_depth(config.holdsite.footprint_mm, info["camera"], depth_mm)
              if any(config.holdsite.footprint_mm) else None)
    check = check_object_holdsite(doc["holdsite"], gt, info, max_tilt=max_tilt,
                                  size=tuple(config.holdsite.size), footprint=window)
    site = doc["holdsite"]
    return {"scene": name, "seed": seed, "ok": check["ok"], "reason": check["reason"],
            "uncovered": None if site is None else check["object"] in info["uncovered"],
            "object": check["object"], "tilt": check["tilt"], "seconds": seconds,
            "height_mm": None if site is None else _round(height_mm[site["row"], site["col"]]),
            "top_height_mm": _round(np.nanmax(np.where(_pickable(gt, info), height_mm, np.nan),
                                              initial=-np.inf)),
            "holdsite": None if doc["holdsite"] is None else
            {k: doc["holdsite"][k] for k in ("row", "col", "size", "angle")},
            "pipeline_reason": doc.get("reason", "")}


def render_frame(folder: Path, name: str, seed: int, size: tuple[int, int], tilt: float = 0.0,
                 camera: str = "sr300", soft: float = 0.0
                 ) -> tuple[Path, dict[str, Any], np.ndarray]:
    """Render one camera frame into ``folder``: its file stem, gt.json and GT labels."""
    write_camera_scenes(folder, [name], [seed], size=size, tilt=tilt, camera=camera, soft=soft)
    stem = folder / camera_stem(name, seed)
    return (stem, read_json(stem.with_name(stem.name + ".gt.json")),
            np.load(stem.with_name(stem.name + ".gt.npy")))


def depth_in_mm(raw: np.ndarray, camera: dict[str, Any]) -> np.ndarray:
    """A frame's raw depth in mm along the optical axis, NaN where it has no reading."""
    return np.where(raw > 0, raw * 1000.0 * float(camera["metres_per_raw"]), np.nan)


def world_heights(depth_mm: np.ndarray, camera: dict[str, Any]) -> np.ndarray:
    """Height in mm of each pixel's point above the world's floor (z = 0), NaN without depth.

    The point ``d ((u - cx) / fx, (v - cy) / fy, 1)`` in the camera frame,
    taken to the world by gt.json's ``rotation`` (its rows are the world's
    axes in the camera frame) and ``position_mm``: along the world's
    vertical however the camera is mounted.
    """
    rows, cols = np.indices(depth_mm.shape, dtype=np.float64)
    up = np.asarray(camera["rotation"], dtype=np.float64)[2]
    x = (cols - float(camera["cx"])) / float(camera["fx"]) * depth_mm
    y = (rows - float(camera["cy"])) / float(camera["fy"]) * depth_mm
    return float(camera["position_mm"][2]) + up[0] * x + up[1] * y + up[2] * depth_mm


def _pickable(gt: np.ndarray, info: dict[str, Any]) -> np.ndarray:
    """Bool mask of the GT pixels of pickable objects."""
    keep = pickable_objects(info)
    surfaces = [s["id"] for s in info["surfaces"] if s["object"] in keep]
    return np.isin(gt, surfaces)


def _median(values: list[Any]) -> float | None:
    """Median of the numbers given (None among them left out), to 0.1; None when none."""
    kept = [float(v) for v in values if v is not None]
    return round(float(np.median(kept)), 1) if kept else None


def _round(value: float) -> float | None:
    return round(float(value), 1) if np.isfinite(value) else None


def summarise(frames: list[dict[str, Any]], names: list[str]) -> dict[str, Any]:
    """Usable / total and % per scene kind and over all, with the commonest failures."""
    kinds = {}
    for name in [*names, "all"]:
        these = [f for f in frames if name in (f["scene"], "all")]
        usable = sum(f["ok"] for f in these)
        kinds[name] = {"usable": usable, "total": len(these),
                       "uncovered": sum(bool(f.get("uncovered")) for f in these if f["ok"]),
                       "percent": round(100.0 * usable / len(these), 1) if these else None,
                       "tilt_median": _median([f["tilt"] for f in these if f["ok"]]),
                       "below_top_median": _median([
                           f["top_height_mm"] - f["height_mm"] for f in these
                           if f.get("height_mm") is not None
                           and f.get("top_height_mm") is not None])}
    failures = Counter(_reason_kind(f["reason"]) for f in frames if not f["ok"])
    return {"kinds": kinds, "failures": dict(failures.most_common())}


def _reason_kind(reason: str) -> str:
    """A failure's reason without its numbers, to count alike failures together."""
    return "".join("#" if ch.isdigit() else ch for ch in reason).split("[")[0].strip()


def _cell(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def markdown(summary: dict[str, Any], meta: dict[str, Any]) -> str:
    """The results as a Markdown page."""
    lines = ["# Usable holdsites on synthetic camera cells (benchmarks/real_cells.py)", "",
             f"rangeseg {meta['version']}; seeds {meta['seeds']}; {meta['size'][1]}x"
             f"{meta['size'][0]}; --preset {PRESET} + intrinsics; background: "
             f"{meta['background']}; settings: {' '.join(meta['settings']) or 'none'}; "
             f"tilt limit {meta['max_tilt']:g} degrees; dropouts "
             f"{meta.get('dropouts', 0.0):g}; depth noise {meta.get('noise_mm', 0.0):g} mm; "
             f"camera tilt {meta.get('camera_tilt', 0.0):g} degrees; "
             f"left band of no reading {meta.get('left_band', 0)} px; "
             f"camera {meta.get('camera', 'sr300')}; soft items {meta.get('soft', 0.0):g}; "
             f"{meta['seconds']:.0f} s on "
             f"{meta['jobs']} processes.", "",
             "Tilt: median angle (degrees) of the usable sites' approach to straight down "
             "(the world's vertical). Below top: median height (mm, along the world's "
             "vertical) of the site's centre below the highest pixel of any pickable "
             "object (0 = the top of the pile), over all sites. Uncovered: usable sites "
             "on an item nothing else lies on (the render's `uncovered`).", "",
             "| scene | usable | frames | % | uncovered | tilt | below top |",
             "|---|---|---|---|---|---|---|"]
    for name, k in summary["kinds"].items():
        lines.append(f"| {name} | {k['usable']} | {k['total']} | {k['percent']} | "
                     f"{k.get('uncovered', '-')} | {_cell(k.get('tilt_median'))} | "
                     f"{_cell(k.get('below_top_median'))} |")
    if summary["failures"]:
        lines += ["", "| failure | frames |", "|---|---|"]
        lines += [f"| {r} | {n} |" for r, n in summary["failures"].items()]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", default=DEFAULT_SEEDS,
                        help=f"held-out seeds, e.g. 100-119 or 1,2,5 (default {DEFAULT_SEEDS})")
    parser.add_argument("--scenes", default=",".join(CAMERA_SCENES),
                        help="camera scenes (default: all)")
    parser.add_argument("--size", default="480x640", help="ROWSxCOLS (default 480x640)")
    parser.add_argument("--set", dest="settings", action="append", default=[],
                        metavar="TABLE.KEY=VALUE", help="extra config value (repeatable)")
    parser.add_argument("--background", action="store_true",
                        help="pass each frame's empty-support frame as the background")
    parser.add_argument("--max-tilt", type=float, default=DEFAULT_MAX_TILT,
                        help="tilt limit of a usable approach, degrees (default 45)")
    parser.add_argument("--dropouts", type=float, default=0.0,
                        help="share of each frame's pixels set to no reading at random, as "
                             "a camera's speckle on shiny spots (default 0)")
    parser.add_argument("--noise", type=float, default=0.0, metavar="MM",
                        help="sigma of Gaussian depth noise added to each reading, mm "
                             "(default 0)")
    parser.add_argument("--camera-tilt", type=float, default=0.0, metavar="DEG",
                        help="the camera's mount tilted from straight down, degrees "
                             "(default 0; each scene adds a few random ones)")
    parser.add_argument("--left-band", type=int, default=0, metavar="PX",
                        help="columns of no reading along the left edge, as a RealSense "
                             "D4xx's (default 0)")
    parser.add_argument("--camera", choices=tuple(CAMERAS), default="sr300",
                        help="the synthetic camera (sr300-smooth: the SR300's error as "
                             "measured on the ARC frames; default sr300)")
    parser.add_argument("--soft", type=float, default=0.0, metavar="SHARE",
                        help="share of the items that are soft, a bag or a cloth: their faces "
                             "creased by folds of about 4 mm (default 0)")
    parser.add_argument("--jobs", type=int, default=min(2, os.cpu_count() or 1))
    parser.add_argument("--out", type=Path, default=RESULTS / "real_cells",
                        help="results stem (default benchmarks/results/real_cells)")
    args = parser.parse_args(argv)
    names = checked_scenes(parser, args.scenes, CAMERA_SCENES)
    if not -60.0 <= args.camera_tilt <= 60.0:
        parser.error(f"--camera-tilt {args.camera_tilt:g}: expected degrees from -60 to 60")
    size = _size(args.size)
    if size is None:
        parser.error(f"--size {args.size!r}: expected ROWSxCOLS of 16 or more, e.g. 480x640")
    if not 0 <= args.left_band < size[1]:
        parser.error(f"--left-band {args.left_band}: expected 0 to {size[1] - 1} columns")
    seeds = checked_seeds(parser, args.seeds)
    if args.jobs < 1:
        parser.error(f"--jobs {args.jobs}: expected 1 or more")
    if not 0.0 <= args.soft <= 1.0:
        parser.error(f"--soft {args.soft:g}: expected a share from 0 to 1")
    try:
        load_config(preset=PRESET, overrides=parse_settings(args.settings))  # fail early
    except ConfigError as exc:
        parser.error(f"--set: {exc}")
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="real_cells-") as tmp:
        jobs = [(n, s, size, args.settings, args.background, args.max_tilt, tmp,
                 args.dropouts, args.noise, args.camera_tilt, args.left_band, args.camera,
                 args.soft)
                for n in names for s in seeds]
        with ProcessPoolExecutor(max_workers=max(1, args.jobs)) as pool:
            frames = list(pool.map(one_frame, jobs))
    meta = {"version": __version__, "seeds": args.seeds, "size": list(size),
            "settings": args.settings, "background": args.background,
            "max_tilt": args.max_tilt, "dropouts": args.dropouts, "noise_mm": args.noise,
            "camera_tilt": args.camera_tilt, "left_band": args.left_band,
            "camera": args.camera, "soft": args.soft,
            "jobs": args.jobs,
            "seconds": time.perf_counter() - start}
    summary = summarise(frames, names)
    page = markdown(summary, meta)
    print(page, end="")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps(
        {**meta, **summary, "frames": frames}, sort_keys=True, indent=2) + "\n")
    args.out.with_suffix(".md").write_text(page)
    return 0


if __name__ == "__main__":
    sys.exit(main())
