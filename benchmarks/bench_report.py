"""Time ``rangeseg report OUT`` on a 200-image batch with failures (issue 35: under 2 s).

The batch is made from two real results, run once: the paper's ``part1-n0``
(128x128, small JSON) and the SR300 tote frame of ``sample_data/arc``
(640x480 with intrinsics and its empty tote: a large ``holdsite.json`` with
``point_camera``). Their files are copied under 200 names in 10 folders:
170 with a holdsite, 10 without (their ``holdsite.json`` with ``null``), 20
failed (a one-line error, no files), with the manifest entries to match.
Then the page is built ``--runs`` times in this process
(:func:`rangeseg_cli.batch.report.write_report`) and as the command a user
types (a new process each time: imports included). Medians go to
``benchmarks/results/report.json``. Usage::

    python benchmarks/bench_report.py [--runs 7] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rangeseg_cli import __version__
from rangeseg_cli.batch.report import write_report

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
RANGESEG = Path(sys.executable).with_name("rangeseg")
ARC = ROOT / "sample_data" / "arc"
IMAGES, FAILED, NO_SITE, FOLDERS = 200, 20, 10, 10


def real_results(work: Path) -> dict[str, Path]:
    """OUT folders of the two real images, run as a user would."""
    part1, arc = work / "part1", work / "arc"
    subprocess.run([RANGESEG, "run", ROOT / "sample_data/synthetic/part1-n0.png", "-o", part1,
                    "-q", "-j", "1"], check=True)
    subprocess.run([RANGESEG, "run", ARC / "suction-scene.depth.png", "-o", arc, "-q", "-j", "1",
                    "--preset", "tenth-mm-depth",
                    "--intrinsics", ARC / "suction-camera-intrinsics.txt",
                    "--background", ARC / "empty/suction-background.depth.png"], check=True)
    return {"part1-n0": part1, "suction-scene.depth": arc}


def synthetic_batch(sources: dict[str, Path], out: Path) -> None:
    """OUT with :data:`IMAGES` images copied from ``sources``; some failed, some without site."""
    manifests = {stem: json.loads((o / "rangeseg-run.json").read_text())
                 for stem, o in sources.items()}
    first = next(iter(manifests.values()))
    images = {}
    for i in range(IMAGES):
        stem = list(sources)[i % len(sources)]
        rel = f"cell{i % FOLDERS}/frame-{i:04d}"
        entry = dict(manifests[stem]["images"][stem], input=f"/data/{rel}.png")
        if i % (IMAGES // FAILED) == 3:
            images[rel] = entry | {"status": "failed", "stages": [], "timings": {},
                                   "error": f"/data/{rel}.png: not a readable image (truncated)"}
            continue
        images[rel] = entry
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        for src in sources[stem].glob(f"{stem}.*"):
            shutil.copyfile(src, out / f"{rel}{src.name[len(stem):]}")
        if i % (IMAGES // NO_SITE) == 5:
            site = out / f"{rel}.holdsite.json"
            data = json.loads(site.read_text())
            site.write_text(json.dumps(data | {"holdsite": None,
                                               "reason": "nothing to pick: (benchmark)"}))
    (out / "rangeseg-run.json").write_text(json.dumps(first | {"images": images}, indent=2))


def median_seconds(call, runs: int) -> float:
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=7, help="builds timed (median)")
    parser.add_argument("--keep", type=Path, help="make the batch here and keep it")
    parser.add_argument("--results", type=Path, default=RESULTS, help="output folder")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep or Path(tmp) / "out"
        synthetic_batch(real_results(Path(tmp)), out)
        counts = write_report(out)
        library = median_seconds(lambda: write_report(out), args.runs)
        command = median_seconds(lambda: subprocess.run([RANGESEG, "report", out, "-q"],
                                                        check=True), args.runs)
        size = (out / "index.html").stat().st_size
    result = {"counts": counts | {"index": "OUT/index.html"}, "runs": args.runs,
              "write_report_median_s": round(library, 4),
              "command_median_s": round(command, 4), "index_html_bytes": size,
              "command": "python benchmarks/bench_report.py",
              "machine": {"python": platform.python_version(), "rangeseg": __version__,
                          "cpu": platform.processor() or platform.machine()}}
    print(f"{IMAGES} images ({counts['failed']} failed, {counts['nosite']} without a site): "
          f"write_report {library:.3f} s, `rangeseg report OUT` {command:.3f} s "
          f"(medians of {args.runs}); index.html {size / 1024:.0f} KiB")
    args.results.mkdir(parents=True, exist_ok=True)
    (args.results / "report.json").write_text(json.dumps(result, indent=2, sort_keys=True)
                                              + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
