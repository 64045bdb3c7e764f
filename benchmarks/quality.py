"""Segmentation quality over all synthetic scenes, in one process.

Renders every scene of ``rangeseg_cli.synth.scenes.SCENES`` at noise 0, 1, 2 (or
the levels of ``--noises``) for seeds 0, 1, 2 (the same images ``rangeseg
synth OUT --noise 0,1,2 --seed S`` writes), runs ``run_pipeline`` up to the
labels with the given configuration and scores them with Hoover et al.
(1996) at T = 0.8 on GT regions of >= 50 pixels.
Prints one row per noise level (the table of ``docs/quality.md``), with
``--widths`` the same counts by the width of the GT face (:func:`face_width`:
where the narrow faces are lost) and, with ``--misses``, every GT region that
is not correctly detected, with the overlap of the region that came nearest
(:func:`best_overlap`).

Usage::

    .venv/bin/python benchmarks/quality.py                       # defaults
    .venv/bin/python benchmarks/quality.py --preset paper
    .venv/bin/python benchmarks/quality.py --set refine.fit_factor=1.5 --misses
    .venv/bin/python benchmarks/quality.py --seeds 0,1,2 --widths
    .venv/bin/python benchmarks/quality.py --seeds 9,10,11 --noises 0,1,2,3
    .venv/bin/python benchmarks/quality.py --gt-parts   # each patch of a GT surface judged alone
    .venv/bin/python benchmarks/quality.py --json out/quality.json --labels out/labels.npz
    .venv/bin/python benchmarks/quality.py --seeds 0,1,2 --tuning rounds=1  # what a step is worth

``--labels`` saves every label image (key ``<scene>-n<noise>-s<seed>``) so two
trees can be checked for identical output (``--compare A.npz B.npz``).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections import defaultdict
from typing import Any

import numpy as np
from scipy import ndimage

from rangeseg_cli import config as config_module
from rangeseg_cli.config import (
    REFINE_FIELDS,
    TUNING,
    SplitConfig,
    load_config,
    parse_settings,
    refine_settings,
)
from rangeseg_cli.errors import ConfigError
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.synth.evaluate import (
    CURVE_TOLERANCES,
    connected_parts,
    correct_curve,
    hoover_compare,
)
from rangeseg_cli.synth.scenes import SCENES, parse_scenes, parse_size, render_scene

NOISES = (0.0, 1.0, 2.0)
SEEDS = (0, 1, 2)
KEYS = ("gt_regions", "correct", "over", "under", "missed", "noise")
#: Upper ends of the face-width classes of ``--widths`` (pixels); the last is open.
WIDTH_BINS = (3, 5, 9)


def face_width(mask: np.ndarray) -> int:
    """Width of a face in pixels: the widest square of its pixels is ``w x w``.

    ``2 * d - 1`` for the largest chessboard distance ``d`` of a face pixel to
    the nearest pixel outside the face (the image border counts as outside):
    a band 3 pixels thick has width 3 whatever its length or direction
    (rounded to odd widths: a band 2 pixels thick has width 1, 4 has 3).
    """
    padded = np.pad(np.asarray(mask, bool), 1)
    if not padded.any():
        return 0
    return 2 * int(ndimage.distance_transform_cdt(padded, metric="chessboard").max()) - 1


def best_overlap(gt: np.ndarray, pred: np.ndarray, g: int) -> float:
    """How near GT region ``g`` came to a correct detection: the best machine region's overlap.

    The largest, over machine regions R (label > 0), of the smaller of
    ``|R & G| / |G|`` and ``|R & G| / |R|``: a correct detection at tolerance
    T needs both at T or more, so ``--misses`` prints it to tell a face lost
    by a pixel or two (0.75-0.8 at T = 0.8) from one that was not found.
    """
    mask = gt == g
    size = int(np.count_nonzero(mask))
    if size == 0:
        return 0.0
    inside = np.bincount(pred[mask].ravel())
    total = np.bincount(pred.ravel(), minlength=inside.size)[: inside.size]
    inside[0] = 0
    share = np.minimum(inside / size, inside / np.maximum(total, 1))
    return float(share.max())


def width_class(width: int) -> str:
    """The ``--widths`` class of a face width: ``"1-3"``, ``"4-5"``, ``"6-9"``, ``">=10"``."""
    low = 1
    for high in WIDTH_BINS:
        if width <= high:
            return f"{low}-{high}"
        low = high + 1
    return f">={low}"


def seed_list(text: str) -> tuple[int, ...]:
    """``--seeds``: comma-separated integers >= 0 (an argparse ``type``)."""
    try:
        seeds = tuple(int(s) for s in text.split(","))
    except ValueError:
        seeds = ()
    if not seeds or min(seeds) < 0:
        raise argparse.ArgumentTypeError(
            f"{text!r}: allowed comma-separated integers >= 0, e.g. 0,1,2")
    return seeds


def noise_list(text: str) -> tuple[float, ...]:
    """``--noises``: comma-separated noise sigmas >= 0, depth units (an argparse ``type``)."""
    try:
        noises = tuple(float(s) for s in text.split(","))
    except ValueError:
        noises = ()
    if not noises or not all(0.0 <= n < 1e3 for n in noises):
        raise argparse.ArgumentTypeError(
            f"{text!r}: allowed comma-separated numbers >= 0, e.g. 0,1,2,3")
    return noises


def scene_list(text: str) -> list[str]:
    """``--scenes`` as ``rangeseg synth --scenes`` takes it (an argparse ``type``)."""
    try:
        return parse_scenes(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def frame_size(text: str) -> tuple[int, int]:
    """``--size``: ``ROWSxCOLS`` as ``rangeseg synth --size`` takes it (an argparse ``type``)."""
    try:
        return parse_size(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def set_item(text: str) -> str:
    """``--set``: ``TABLE.KEY=VALUE`` as ``rangeseg run --set`` takes it (an argparse ``type``)."""
    try:
        parse_settings([text])
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text


def measure(config: Any, scenes: list[str], seeds: tuple[int, ...], misses: bool,
            size: tuple[int, int] = (128, 128), gt_parts: bool = False,
            noises: tuple[float, ...] = NOISES
            ) -> tuple[dict[float, dict[str, Any]], dict[str, np.ndarray], list[str]]:
    """Per noise level of ``noises``: summed counts and curve; the label images; the misses."""
    rows: dict[float, dict[str, Any]] = defaultdict(
        lambda: {**{k: 0 for k in KEYS}, "curve": [0] * len(CURVE_TOLERANCES),
                 "widths": defaultdict(lambda: [0, 0])})
    labels: dict[str, np.ndarray] = {}
    missed: list[str] = []
    for seed in seeds:
        for name in scenes:
            for noise in noises:
                scene = render_scene(name, size=size, noise=noise, seed=seed)
                pred = run_pipeline(scene.image, config, stages=3).labels  # no holdsite
                key = f"{name}-n{noise:g}-s{seed}"
                labels[key] = pred
                gt = connected_parts(scene.gt) if gt_parts else scene.gt
                result = hoover_compare(gt, pred)
                counts = result.counts()
                row = rows[noise]
                for k in KEYS:
                    row[k] += int(counts[k])
                row["curve"] = [a + b for a, b in zip(row["curve"],
                                                      correct_curve(gt, pred), strict=True)]
                good = {g for i in result.instances if i.kind == "correct" for g in i.gt}
                for g in result.gt_labels.tolist():
                    tally = row["widths"][width_class(face_width(gt == g))]
                    tally[0] += 1
                    tally[1] += g in good
                if misses:
                    names = {s["id"]: s["name"] for s in scene.info["surfaces"]}
                    for g in result.gt_labels.tolist():
                        if g not in good:
                            surface = int(scene.gt[gt == g][0])
                            missed.append(f"{key}: {names.get(surface, surface)} "
                                          f"({int((gt == g).sum())} px, best overlap "
                                          f"{best_overlap(gt, pred, g):.2f})")
    return dict(rows), labels, missed


def _print(rows: dict[float, dict[str, Any]]) -> None:
    print("| σ | GT | correct | over | under | missed | noise | correct at T = 0.5 … 0.95 |")
    print("|---|---|---|---|---|---|---|---|")
    total = {k: 0 for k in KEYS}
    for noise in sorted(rows):
        r = rows[noise]
        pct = 100.0 * r["correct"] / max(r["gt_regions"], 1)
        print(f"| {noise:g} | {r['gt_regions']} | {r['correct']} ({pct:.1f} %) | {r['over']} | "
              f"{r['under']} | {r['missed']} | {r['noise']} | {' '.join(map(str, r['curve']))} |")
        for k in KEYS:
            total[k] += r[k]
    pct = 100.0 * total["correct"] / max(total["gt_regions"], 1)
    print(f"| all | {total['gt_regions']} | {total['correct']} ({pct:.1f} %) | {total['over']} | "
          f"{total['under']} | {total['missed']} | {total['noise']} | |")


def _print_widths(rows: dict[float, dict[str, Any]]) -> None:
    noises = sorted(rows)
    classes = sorted({c for r in rows.values() for c in r["widths"]},
                     key=lambda c: int(c.split("-")[0].lstrip(">=")))
    print()
    print("| face width (px) | GT | " + " | ".join(f"correct σ = {n:g}" for n in noises) + " |")
    print("|---|---|" + "---|" * len(noises))
    for c in classes:
        gt = rows[noises[0]]["widths"][c][0]
        hits = [rows[n]["widths"][c][1] for n in noises]
        cells = " | ".join(f"{h} ({100.0 * h / gt:.0f} %)" for h in hits)
        print(f"| {c} | {gt} | {cells} |")


def tuning_item(text: str) -> tuple[str, Any]:
    """``--tuning FIELD=VALUE``: a field of :class:`~rangeseg_cli.config.SplitConfig`."""
    name, eq, value = text.partition("=")
    fields = {f.name: f for f in dataclasses.fields(SplitConfig)
              if f.name not in REFINE_FIELDS.values()}  # those are [refine] keys: --set
    if not eq or name not in fields:
        raise argparse.ArgumentTypeError(f"{text!r}: FIELD=VALUE with FIELD one of "
                                         + ", ".join(fields))
    default = getattr(TUNING, name)
    if isinstance(default, bool):
        if value.lower() not in ("true", "false"):
            raise argparse.ArgumentTypeError(f"{text!r}: {name} is true or false")
        return name, value.lower() == "true"
    try:
        return name, type(default)(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: {name} is a "
                                         f"{type(default).__name__}") from None


def use_tuning(changes: dict[str, Any]) -> None:
    """Set the refinement's constants (``rangeseg_cli.config.TUNING``) for this process."""
    if changes:
        config_module.TUNING = dataclasses.replace(config_module.TUNING, **changes)
        refine_settings.cache_clear()


def compare(a: str, b: str) -> int:
    """Print how many label images differ between two ``--labels`` files."""
    la, lb = np.load(a), np.load(b)
    keys = sorted(set(la.files) | set(lb.files))
    diff = [k for k in keys if k not in la.files or k not in lb.files
            or not np.array_equal(la[k], lb[k])]
    print(f"{len(keys) - len(diff)} of {len(keys)} label images identical")
    for k in diff:
        print(f"  differs: {k}")
    return 1 if diff else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--preset", default=None)
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", type=set_item)
    p.add_argument("--tuning", action="append", default=[], metavar="FIELD=VALUE",
                   type=tuning_item, help="a constant of the refinement "
                   "(rangeseg_cli.config.TUNING, e.g. rounds=1 or trim_pieces=false): what "
                   "one of its steps is worth")
    p.add_argument("--scenes", default=list(SCENES), type=scene_list,
                   help="comma-separated scene names")
    p.add_argument("--seeds", default=SEEDS, type=seed_list)
    p.add_argument("--noises", default=NOISES, type=noise_list,
                   help="comma-separated noise sigmas of the rendered scenes (default 0,1,2)")
    p.add_argument("--size", default=(128, 128), type=frame_size,
                   help="ROWSxCOLS of the rendered scenes")
    p.add_argument("--misses", action="store_true", help="list GT regions not correctly detected")
    p.add_argument("--gt-parts", action="store_true",
                   help="judge each 8-connected patch of a GT surface as a region of its own")
    p.add_argument("--widths", action="store_true",
                   help="also count correct detections by the width of the GT face")
    p.add_argument("--json", default=None, help="write the rows as JSON here")
    p.add_argument("--labels", default=None, help="save all label images to this .npz")
    p.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two --labels files")
    args = p.parse_args(argv)
    if args.compare:
        return compare(*args.compare)
    try:
        use_tuning(dict(args.tuning))
        config = load_config(preset=args.preset, overrides=parse_settings(args.set))
    except (ConfigError, TypeError, ValueError) as exc:
        p.error(str(exc))  # one line and exit code 2, as for a bad option
    rows, labels, missed = measure(config, args.scenes, args.seeds, args.misses, args.size,
                                   args.gt_parts, args.noises)
    _print(rows)
    if args.widths:
        _print_widths(rows)
    for line in missed:
        print(line)
    if args.json:
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({f"{k:g}": {**v, "widths": dict(v["widths"])} for k, v in rows.items()},
                      fh, indent=1)
    if args.labels:
        np.savez_compressed(args.labels, **labels)
    return 0


if __name__ == "__main__":
    sys.exit(main())
