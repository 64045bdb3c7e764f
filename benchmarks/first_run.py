"""The first ``rangeseg run`` after installing (issue 33, "First run"): compile time.

A fresh install has no compiled kernels on disk: its first run compiles every
numba kernel it calls. This script renders one synthetic 128x128 bin pile
(``rangeseg synth --scenes pile --noise 1``) and times, in fresh processes,
``rangeseg run IMAGE -o OUT -q -j 1``:

* cold: ``NUMBA_CACHE_DIR`` set to a new empty folder. numba caches under
  ``NUMBA_CACHE_DIR`` first when it is set, so the run is cold whatever the
  package's ``__pycache__`` holds; the script checks it by counting the index
  (``.nbi``, one per kernel) and code (``.nbc``, one per signature) files
  written there and in ``__pycache__``;
* cold without the helper that compiles in the background
  (``RANGESEG_COMPILE_AHEAD=0``): the compile work of one process;
* warm: again on the last cold run's cache (it must write no file);
* with ``--compare DIR``, the same for the rangeseg source tree ``DIR`` (e.g. an
  older commit from ``git archive``), run through ``PYTHONPATH``.

The variants are interleaved within each of ``--repeats`` rounds, so that the
machine's load hits them alike; medians of wall and CPU seconds (the CPU of the
run and of its helper) are reported. ``--profile`` runs the command once more
in-process in a cold interpreter with numba's event API
(:mod:`numba.core.event`) listening, without the helper, and reports each
signature's compile seconds exclusive of the signatures it compiles on the way
(they are compiled, and timed, on their own first) and the part spent in LLVM.

Run ``.venv/bin/python benchmarks/first_run.py [--profile] [--compare DIR]``;
results go to ``benchmarks/results/first_run.json``.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "first_run.json"
RANGESEG = [str(Path(sys.executable).parent / "rangeseg")]  # the venv's console script


def _package(source: Path | None) -> Path:
    """The ``rangeseg_cli`` folder a run imports (``source``'s, else the installed one)."""
    if source is not None:
        return source / "rangeseg_cli"
    spec = importlib.util.find_spec("rangeseg_cli")  # without importing it (nor numba)
    if spec is None or spec.origin is None:
        raise SystemExit("rangeseg is not installed")
    return Path(spec.origin).parent


def _cache_files(folder: Path, since: float = 0.0) -> dict[str, int]:
    """Numba index and code files under ``folder`` written at or after ``since``."""
    counts = {"nbi": 0, "nbc": 0}
    for kind in counts:
        for path in folder.rglob(f"*.{kind}"):
            try:
                counts[kind] += path.stat().st_mtime >= since
            except OSError:  # removed meanwhile
                continue
    return counts


def _env(source: Path | None, cache: Path, helper: bool) -> dict[str, str]:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    env.pop("RANGESEG_PURE_NUMPY", None)
    if source is not None:
        env["PYTHONPATH"] = str(source)
    if not helper:
        env["RANGESEG_COMPILE_AHEAD"] = "0"
    return env


def _timed_run(image: Path, out: Path, cache: Path, *, source: Path | None = None,
               helper: bool = True) -> dict[str, Any]:
    """One ``rangeseg run``: wall and CPU seconds, cache files written."""
    start = time.time()
    t0 = time.perf_counter()
    c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([*RANGESEG, "run", str(image), "-o", str(out), "-q", "-j", "1",
                    "--overwrite"], check=True, env=_env(source, cache, helper))
    seconds = time.perf_counter() - t0
    c1 = resource.getrusage(resource.RUSAGE_CHILDREN)  # the helper is waited for too
    cpu = c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime
    return {"seconds": round(seconds, 3), "cpu_seconds": round(cpu, 3),
            "written": _cache_files(cache, start),
            "written_to_package_pycache": _cache_files(_package(source) / "__pycache__", start)}


class _Recorder:
    """numba's compile and LLVM events, per signature (exclusive of nested compiles)."""

    def __init__(self) -> None:
        self.stack: list[list[Any]] = []  # [name, start, nested seconds, LLVM seconds]
        self.llvm_start: list[float] = []
        self.signatures: dict[str, dict[str, float]] = {}

    def compile_started(self, data: dict[str, Any]) -> None:
        name = f"{data['dispatcher'].py_func.__name__}{tuple(str(a) for a in data['args'])}"
        self.stack.append([name, time.perf_counter(), 0.0, 0.0])

    def compile_ended(self) -> None:
        name, start, nested, llvm = self.stack.pop()
        total = time.perf_counter() - start
        self.signatures[name] = {"exclusive_s": total - nested, "llvm_s": llvm}
        if self.stack:
            self.stack[-1][2] += total

    def llvm_started(self) -> None:
        self.llvm_start.append(time.perf_counter())

    def llvm_ended(self) -> None:
        seconds = time.perf_counter() - self.llvm_start.pop()
        if not self.llvm_start and self.stack:  # the outermost lock, within a compile
            self.stack[-1][3] += seconds


def _profile_child(image: Path, out: Path) -> None:
    """In this (cold) interpreter: the command with numba's events recorded, as JSON."""
    from numba.core import event

    from rangeseg_cli.cli.main import main

    rec = _Recorder()

    class Compiles(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            rec.compile_started(ev.data)

        def on_end(self, ev: event.Event) -> None:
            rec.compile_ended()

    class Llvm(event.Listener):
        def on_start(self, ev: event.Event) -> None:
            rec.llvm_started()

        def on_end(self, ev: event.Event) -> None:
            rec.llvm_ended()

    t0 = time.perf_counter()
    with event.install_listener("numba:compile", Compiles()), \
            event.install_listener("numba:llvm_lock", Llvm()):
        main.main(args=["run", str(image), "-o", str(out), "-q", "-j", "1", "--overwrite"],
                  standalone_mode=False)
    print(json.dumps({"wall_s": time.perf_counter() - t0, "signatures": rec.signatures}))


def _profile(image: Path, out: Path, source: Path | None) -> dict[str, Any]:
    """Per-signature compile seconds of one cold in-process run (no helper)."""
    with tempfile.TemporaryDirectory(prefix="first-run-cache-") as cache:
        done = subprocess.run([sys.executable, __file__, "--profile-child", str(image), str(out)],
                              check=True, env=_env(source, Path(cache), helper=False),
                              capture_output=True, text=True)
    data = json.loads(done.stdout.strip().splitlines()[-1])
    per_kernel: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0, 0])
    for name, times in data["signatures"].items():
        entry = per_kernel[name.split("(")[0]]
        entry[0] += times["exclusive_s"]
        entry[1] += times["llvm_s"]
        entry[2] += 1
    ranked = sorted(per_kernel.items(), key=lambda kv: -kv[1][0])
    return {
        "wall_s": round(data["wall_s"], 2),
        "compile_s": round(sum(t[0] for _, t in ranked), 2),
        "llvm_s": round(sum(t[1] for _, t in ranked), 2),
        "signatures": len(data["signatures"]),
        "functions_with_several_signatures": sorted(k for k, t in ranked if t[2] > 1),
        "per_function": {k: {"compile_s": round(t[0], 3), "llvm_s": round(t[1], 3),
                             "signatures": t[2]} for k, t in ranked},
    }


def _median(runs: list[dict[str, Any]], key: str) -> float:
    return round(statistics.median(r[key] for r in runs), 2)


def _summary(runs: dict[str, list[dict[str, Any]]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for label, rs in runs.items():
        out[label] = {"median_s": _median(rs, "seconds"),
                      "median_cpu_s": _median(rs, "cpu_seconds"),
                      "kernels_compiled": rs[-1]["written"]["nbi"],
                      "signatures_compiled": rs[-1]["written"]["nbc"], "runs": rs}
    return out


def _measure(image: Path, work: Path, repeats: int, compare: Path | None
             ) -> dict[str, list[dict[str, Any]]]:
    """The cold and warm runs of each variant, interleaved round by round."""
    variants: list[tuple[str, Path | None, bool]] = [("cold", None, True),
                                                      ("cold_without_helper", None, False)]
    if compare is not None:
        variants.append(("compare_cold", compare, True))
    runs: dict[str, list[dict[str, Any]]] = defaultdict(list)
    last: dict[str | None, Path] = {}
    for i in range(repeats):
        for label, source, helper in variants:
            cache = work / f"cache-{label}-{i}"
            cache.mkdir()
            runs[label].append(_timed_run(image, work / "out", cache, source=source,
                                          helper=helper))
            last[str(source)] = cache
            print(f"round {i + 1} {label}: {runs[label][-1]['seconds']:.2f} s", file=sys.stderr)
        for label, source in [("warm", None)] + ([("compare_warm", compare)] if compare else []):
            runs[label].append(_timed_run(image, work / "out", last[str(source)],
                                          source=source))
    return runs


def main(argv: list[str] | None = None) -> int:
    """Time cold and warm first runs; optionally profile the compiles; write the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="rounds (default 3)")
    parser.add_argument("--size", default="128x128", help="image size ROWSxCOLS")
    parser.add_argument("--compare", type=Path, help="another rangeseg source tree to time")
    parser.add_argument("--compare-name", help="what --compare is (default: its path)")
    parser.add_argument("--profile", action="store_true", help="per-kernel compile seconds")
    parser.add_argument("--output", type=Path, default=RESULTS, help="JSON results file")
    parser.add_argument("--profile-child", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.profile_child:
        _profile_child(*args.profile_child)
        return 0
    with tempfile.TemporaryDirectory(prefix="first-run-") as tmp:
        work = Path(tmp)
        subprocess.run([*RANGESEG, "synth", str(work / "image"), "--scenes", "pile", "--noise",
                        "1", "--seed", "0", "--size", args.size, "-q"], check=True)
        image = work / "image" / "pile-n1.png"
        runs = _measure(image, work, args.repeats, args.compare)
        report: dict[str, Any] = {
            "command": f"rangeseg run <{args.size} pile, noise 1> -o OUT -q -j 1 --overwrite",
            "compare": args.compare_name or (str(args.compare) if args.compare else None),
            "machine": {"python": platform.python_version(), "cpus": os.cpu_count(),
                        "load_average_1min_at_end": round(os.getloadavg()[0], 2)},
            **_summary(runs),
        }
        if any(sum(r["written_to_package_pycache"].values()) for rs in runs.values() for r in rs):
            print("warning: a run wrote to the package's __pycache__", file=sys.stderr)
        if any(sum(r["written"].values()) for r in runs["warm"] + runs.get("compare_warm", [])):
            print("warning: a warm run compiled kernels", file=sys.stderr)
        if args.profile:
            report["profile"] = _profile(image, work / "out", None)
    import numba

    report["machine"]["numba"] = numba.__version__
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(report, indent=2, sort_keys=True) + "\n")
    for label in runs:
        r = report[label]
        print(f"{label:28s} median {r['median_s']:6.2f} s (CPU {r['median_cpu_s']:6.2f} s), "
              f"{r['kernels_compiled']} kernels / {r['signatures_compiled']} signatures written")
    if args.profile:
        prof = report["profile"]
        print(f"profile: {prof['compile_s']:.1f} s compiling ({prof['llvm_s']:.1f} s in LLVM), "
              f"{prof['signatures']} signatures; slowest:")
        for name, t in list(prof["per_function"].items())[:12]:
            print(f"  {t['compile_s']:6.2f} s  {name} ({t['signatures']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
