"""Write docs/performance.md from benchmarks/results/{bench,tradeoffs,dask}.json.

Usage: ``.venv/bin/python benchmarks/report.py`` after ``make bench`` (and
``make tradeoffs``, ``benchmarks/bench_dask.py``); ``--check`` exits 1 when
the committed page differs from what the results give (``tests/test_docs.py``).
The page holds one current table per measurement, never older runs: the
results' history is in git.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
OUT = ROOT / "docs" / "performance.md"

#: bench.json task -> column heading of the main table.
COLUMNS = {
    "edges": "edges", "holdsite": "holdsite",
    "run_pipeline_paper": "defaults, `[refine] passes = []`",
    "run_pipeline_norecut": "defaults without `recut`",
    "run_pipeline_1thread": "defaults, 1 thread", "run_pipeline": "defaults",
}

HOW = """\
## How to measure

```
make bench                                   # benchmarks/bench_pipeline.py, ~10 min: bench.json
make tradeoffs                               # benchmarks/tradeoffs.py, ~20 min: tradeoffs.json
.venv/bin/python benchmarks/bench_dask.py    # the Dask executor against the local pool: dask.json
.venv/bin/python benchmarks/report.py        # this page from benchmarks/results/
```

`bench_pipeline.py` times each stage and `run_pipeline` on synthetic bin
scenes (`rangeseg synth` `pile`) at four sizes and on the SR300 frame of
`sample_data/arc`, as medians of interleaved runs after a warm-up, against
`scipy.ndimage.gaussian_filter(z, 4)` (G, one thread) on the same frame in
the same run. Compare runs in multiples of G: a shared machine's state
changes absolute times by up to 2× between runs. Speed is measured in
`benchmarks/`, never in tests.

## What to expect

- The defaults spend most of their time in the refinement's passes: on the
  real frame the split, the facets and the recut, which test hundreds of
  regions and change few of them ("Where the defaults' time goes" says
  what each pass costs and changes); the holdsite's workspace step (the
  support, the background, the border structures) costs several Gaussian
  passes more. `--preset paper` leaves the passes out. "Speed or quality"
  says what each pass costs and earns.
- Time grows about linearly with the pixels or slower (exponents below).
- A real camera frame costs more than a synthetic pile of its size: its
  noise estimate reads low (the camera smooths its noise), so many regions
  fail the fit test and are split.
- `--threads` splits one image into row bands and shares independent pieces
  of work out; on Linux, 24 or more pieces go to forked processes. `--jobs`
  runs images in parallel processes; each worker keeps BLAS to one thread.
  Results are the same bits for any `--jobs` and `--threads`.
- The first command after installing compiles the numba kernels (once;
  cached beside the package); later commands load them in about half a
  second. Each command also pays about half a second of imports.
"""


def _ms(x: float) -> str:
    return f"{x / 1000:.2f} s" if x >= 1000 else f"{x:.1f} ms" if x < 100 else f"{x:.0f} ms"


def _speed(bench: dict[str, Any]) -> list[str]:
    m = bench["machine"]
    lines = ["## Speed", "",
             f"rangeseg {m['rangeseg']}, {m['cores']} cores ({m['threads']} threads), "
             f"Python {m['python']}, numpy {m['numpy']}, numba {m['numba']}. Medians; in "
             "brackets the time in Gaussian passes G. The automatic threads unless "
             "\"1 thread\".", "",
             "| frame | G | " + " | ".join(COLUMNS.values()) + " |",
             "| --- | --- | " + " | ".join("---" for _ in COLUMNS) + " |"]
    frames = [(f"{f['cols']}×{f['rows']} pile", f) for f in bench["frames"]]
    real = bench["real_frame"]
    frames.append((f"SR300 frame ({real['cols']}×{real['rows']}, {real['regions']} regions)",
                   real))
    for name, f in frames:
        g = f["median_ms"]["gaussian"]
        cells = [f"{_ms(f['median_ms'][k])} ({f['median_ms'][k] / g:.1f} G)"
                 if k in f["median_ms"] else "" for k in COLUMNS]
        lines.append(f"| {name} | {g:.2f} ms | " + " | ".join(cells) + " |")
    exps = ", ".join(f"{k} {v:.2f}" for k, v in sorted(bench["scaling_exponent"].items()))
    lines += ["", f"Time ∝ pixels^k: {exps}."]
    c = bench["compile"]
    cold = c["cold_cache"]["first_call_s"]
    lines += ["", f"First `run_pipeline` in a fresh interpreter: {cold:.0f} s "
              f"with a cold numba cache (compiling), {c['warm_cache']['first_call_s']:.2f} s with "
              f"a warm one (loading), after {c['warm_cache']['import_s']:.2f} s of imports."]
    one = bench.get("one_frame")
    if one:
        lines += ["", f"One SR300 frame through the command (`rangeseg run` of the frame "
                  f"with `--preset tenth-mm-depth` and its intrinsics, start to exit): "
                  f"{one['wall_s']:.2f} s, of which {one['run_pipeline_s']:.2f} s in "
                  f"`run_pipeline` and {one['overhead_s']:.2f} s start-up, imports and I/O."]
    b = bench["batch"]
    lines += ["", f"Batch, `rangeseg run` on {b['images']} PNGs of {b['size'][0]}×{b['size'][1]} "
              f"with every output: {b['jobs1']['images_per_s']:.1f} images/s with `--jobs 1`, "
              f"{b['jobs2']['images_per_s']:.1f} with `--jobs 2` ({b['speedup_jobs2']:.2f}×; "
              f"{b['speedup_jobs2_steady']:.2f}× without the "
              f"{b['jobs2']['startup_s']:.1f} s start-up of a command)."]
    return lines


def _pass_order() -> list[str]:
    """The default passes in the order they run, a second run named ``name#2``."""
    from rangeseg_cli.config import load_config
    from rangeseg_cli.refine.passes import active_passes

    names: list[str] = []
    for step in active_passes(load_config()):
        names.append(step.name if step.name not in names else f"{step.name}#2")
    return names


def _passes(bench: dict[str, Any]) -> list[str]:
    """Each refinement pass alone, where bench.json has them (the 640x480 pile, SR300)."""
    columns = [(f"{f['cols']}×{f['rows']} pile", f["passes"]) for f in bench["frames"]
               if f.get("passes")]
    if bench["real_frame"].get("passes"):
        columns.append(("SR300 frame", bench["real_frame"]["passes"]))
    if not columns:
        return []
    names = [n for n in _pass_order() if any(n in p["gaussian_passes"] for _, p in columns)]
    lines = ["", "### Where the defaults' time goes", "",
             "Each refinement pass alone, on the labels it gets in a run (medians; `#2`: "
             "the pass's second run), with the pixels it gives another surface and the "
             "regions before and after it.", "",
             "| pass | " + " | ".join(c for c, _ in columns) + " |",
             "| --- | " + " | ".join("---" for _ in columns) + " |"]
    for name in [*names, "all passes"]:
        cells = []
        for _, p in columns:
            ms, g = p["median_ms"], p["gaussian_passes"]
            total = sum(ms[k] for k in g) if name == "all passes" else ms.get(name)
            moved = p.get("changes", {}).get(name)
            change = f"; {moved[0]} px, {moved[1]} → {moved[2]} regions" if moved else ""
            cells.append("" if total is None else
                         f"{_ms(total)} ({total / ms['gaussian']:.1f} G{change})")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return lines


def _dask(dask: dict[str, Any]) -> list[str]:
    b = dask["batch"]
    return ["", f"Dask: the same {b['images']} images through `rangeseg run` on a LocalCluster "
            f"of the same machine: {b['cli_dask']['images_per_s']:.1f} images/s against "
            f"{b['cli_local']['images_per_s']:.1f} with the local pool "
            f"(+{b['cli_overhead']['ms_per_image_median']:.1f} ms per image; through "
            f"`run_batch` in one process +{b['library_overhead']['ms_per_image_median']:.1f} "
            "ms). The cluster pays off when it has more cores than one machine; the "
            "outputs are byte-identical."]


def _tradeoffs(t: dict[str, Any]) -> list[str]:
    frames = list(t["median_ms"]["defaults"])
    seeds = t["seeds"]
    gt = t["correct"]["defaults"]["gt_regions"]
    lines = ["", "## Speed or quality", "",
             f"Each pass beyond the paper left out alone (\"without `facets`\": `--set "
             "refine.passes=[...]` with every other pass): `run_pipeline`'s time (medians of "
             f"{t['repeats']}) and correct detections over the twelve synthetic scenes, seeds "
             f"{seeds[0]}–{seeds[-1]} ({gt} GT regions per noise level; "
             "[quality.md](quality.md)).", "",
             "| variant | " + " | ".join(frames) + " | correct σ = 0 | σ = 1 | σ = 2 |",
             "| --- | " + " | ".join("---" for _ in frames) + " | --- | --- | --- |"]
    base = t["correct"]["defaults"]
    for variant, times in t["median_ms"].items():
        correct = t["correct"][variant]
        cells = [_ms(times[f]) for f in frames]
        for level in ("0", "1", "2"):
            d = correct[level] - base[level]
            cells.append(str(correct[level]) if variant == "defaults"
                         else f"{correct[level]} ({d:+d})")
        name = (variant if variant == "defaults"
                else f"without `{variant.removeprefix('without ')}`"
                if variant.startswith("without ") else f"`{variant}`")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    lines += ["", "Where a holdsite is needed in well under a second, the rows say which "
              "passes cost the most time for the fewest correct detections: leave them out "
              "of `[refine] passes`; every row loses correct detections at some noise level "
              "or on the held-out seeds, which is why each pass is on by default."]
    return lines


def render() -> str:
    """The Markdown text of docs/performance.md."""
    bench = json.loads((RESULTS / "bench.json").read_text())
    lines = ["# Performance", "",
             "<!-- Generated by benchmarks/report.py from benchmarks/results/: do not edit. -->",
             "", *_speed(bench), *_passes(bench)]
    if (RESULTS / "dask.json").exists():
        lines += _dask(json.loads((RESULTS / "dask.json").read_text()))
    if (RESULTS / "tradeoffs.json").exists():
        lines += _tradeoffs(json.loads((RESULTS / "tradeoffs.json").read_text()))
    return "\n".join(lines) + "\n\n" + HOW


def main(argv: list[str] | None = None) -> int:
    """Write the page, or with ``--check`` say whether it is current."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="exit 1 when docs/performance.md differs from the results")
    args = parser.parse_args(argv)
    text = render()
    if args.check:
        if not OUT.exists() or OUT.read_text(encoding="utf-8") != text:
            print(f"{OUT} is stale: run python benchmarks/report.py", file=sys.stderr)
            return 1
        return 0
    OUT.write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
