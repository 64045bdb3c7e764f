"""What each refinement pass earns, on every seed set of docs/quality.md (issue 33).

For the defaults and each pass of ``[refine] passes`` left out alone (the
variants of ``tradeoffs.py`` without their timing), counts the correct
detections (Hoover et al. at T = 0.8, GT regions of >= 50 pixels, as
``quality.py`` counts them) at noise 0, 1 and 2 on each seed set: the tuning
set 0-8 and the held-out sets 9-17, 18-26, 27-35 and 36-44. A pass whose
removal loses no detection on any set at any level could go without
lowering issue 9's figures; the table shows which. The (variant, set) runs
share the machine's cores (one process each).

Prints a markdown table (the defaults' counts, then each variant's change
per set as ``σ0/σ1/σ2``) and writes ``benchmarks/results/pass_ablation.{json,md}``.

Usage::

    .venv/bin/python benchmarks/pass_ablation.py               # five sets (~20 min on 2 cores)
    .venv/bin/python benchmarks/pass_ablation.py --sets 0-2,3-5
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_pipeline import RESULTS  # noqa: E402
from quality import NOISES, measure  # noqa: E402
from tradeoffs import ITEMS, variant_config  # noqa: E402

from rangeseg_cli.config import parse_settings  # noqa: E402
from rangeseg_cli.synth.scenes import SCENES  # noqa: E402

#: The seed sets of docs/quality.md: the tuning set and four held-out sets.
SETS: tuple[tuple[int, int], ...] = ((0, 8), (9, 17), (18, 26), (27, 35), (36, 44))

#: The variants: the defaults and each pass left out alone (``tradeoffs.without``).
VARIANTS: dict[str, str | None] = {
    "defaults": None,
    **{name: item for name, item in ITEMS.items() if name.startswith("without ")},
}


def set_list(text: str) -> tuple[tuple[int, int], ...]:
    """``--sets``: comma-separated ``FIRST-LAST`` seed ranges (an argparse ``type``)."""
    try:
        sets = tuple((int(a), int(b)) for a, b in (part.split("-") for part in text.split(",")))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--sets {text!r}: give comma-separated FIRST-LAST ranges, e.g. 0-8,9-17") from None
    if not sets or any(a < 0 or b < a for a, b in sets):
        raise argparse.ArgumentTypeError(f"--sets {text!r}: each range needs 0 <= FIRST <= LAST")
    return sets


def count(task: tuple[str, tuple[int, int]]) -> tuple[str, str, list[int], int]:
    """Correct detections per noise level of one variant on one seed set, and GT regions."""
    name, (first, last) = task
    item = VARIANTS[name]
    config = variant_config(None, parse_settings([item]) if item else {})
    rows, _, _ = measure(config, list(SCENES), tuple(range(first, last + 1)), False)
    return (name, f"{first}-{last}", [int(rows[n]["correct"]) for n in NOISES],
            int(rows[NOISES[0]]["gt_regions"]))


def markdown(report: dict[str, Any]) -> str:
    """The defaults' counts per set, then each variant's change per set and in all."""
    sets, correct = report["sets"], report["correct"]
    base = correct["defaults"]
    lines = [f"{report['date']}: correct detections at noise {'/'.join(f'{n:g}' for n in NOISES)}"
             " per seed set; each row but the first is the change when that pass is left out "
             "of `[refine] passes` alone (the passes that need it go with it).", "",
             "| variant | " + " | ".join(f"seeds {s}" for s in sets) + " | all |",
             "|---" * (len(sets) + 2) + "|"]
    for name in VARIANTS:
        cells, total = [], [0] * len(NOISES)
        for s in sets:
            values = correct[name][s] if name == "defaults" else [
                a - b for a, b in zip(correct[name][s], base[s], strict=True)]
            total = [t + v for t, v in zip(total, values, strict=True)]
            cells.append("/".join(f"{v}" if name == "defaults" else f"{v:+d}" for v in values))
        cells.append("/".join(f"{v}" if name == "defaults" else f"{v:+d}" for v in total))
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sets", default=SETS, type=set_list,
                        help="comma-separated FIRST-LAST seed ranges (default: the five sets)")
    args = parser.parse_args(argv)
    tasks = [(name, s) for name in VARIANTS for s in args.sets]
    start = time.time()
    correct: dict[str, dict[str, list[int]]] = {name: {} for name in VARIANTS}
    gt: dict[str, int] = {}
    with ProcessPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        for name, key, values, regions in pool.map(count, tasks):
            correct[name][key] = values
            gt[key] = regions
    report = {"date": time.strftime("%Y-%m-%d %H:%M"), "sets": [f"{a}-{b}" for a, b in args.sets],
              "noises": list(NOISES), "gt_regions": gt, "correct": correct,
              "seconds": round(time.time() - start)}
    text = markdown(report)
    print(text, end="")
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "pass_ablation.json").write_text(json.dumps(report, indent=1) + "\n",
                                                encoding="utf-8")
    (RESULTS / "pass_ablation.md").write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
