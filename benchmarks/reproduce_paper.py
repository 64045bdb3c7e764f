"""Reproduce Table 1 and the localisation experiments of Al-Hujazi & Sood (1990).

Section IV-B of the paper ("Performance Analysis") gives two things this script
recomputes:

* Table 1 -- the noise response ``sum = sum_{i != 0} G(i)^2 + (G(0) - 1)^2`` of
  the AR operator ``f = G - delta`` (eqs. 10-14) over a window of 4*sigma + 1
  taps, for sigma = 0.5, 1, 2, 3, 4, 5.
* Figs. 5-7 -- the probability distribution of the delocalisation ``x0`` of the
  AR maximum (eq. 3) for noisy 1-D roof, asymmetric-step and step edges built
  on the edge model of Fig. 4 / eq. (1), 12 800 trials per case.

Run ``.venv/bin/python benchmarks/reproduce_paper.py`` (or ``make reproduce``).
It prints both tables and writes ``benchmarks/results/paper.json`` plus the PNG
plots ``paper_fig5_roof.png``, ``paper_fig6_asymmetric.png`` and
``paper_fig7_step.png`` (skipped, with one line, when matplotlib is missing).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: Table 1 of the paper, sigma -> sum (Sec. IV-B-1).
PAPER_TABLE1: dict[float, float] = {
    0.5: 0.137,
    1.0: 0.713,
    2.0: 0.924,
    3.0: 0.97,
    4.0: 0.98,
    5.0: 0.98,
}

#: Figures quoted in the text of Sec. IV-B-2 (the plotted curves are not in the text).
PAPER_LOCALIZATION: dict[str, dict[str, float]] = {
    "roof": {"F4_sigma5_within1": 0.98},
    "step": {"F5_sigma0.5_within1": 0.91},
}

DEFAULT_SEED = 1990
DEFAULT_TRIALS = 12800
#: Half-width W of the area searched for the AR maximum: offsets -W..W pixels.
DEFAULT_SEARCH = 5
RESULTS_DIR = Path(__file__).resolve().parent / "results"

KINDS = ("roof", "asymmetric", "step")


@dataclass(frozen=True)
class EdgeCase:
    """One synthetic edge of Fig. 4 / eq. (1) and its experiment grid.

    Attributes
    ----------
    k1, k2 : float
        Slopes left (x < 0) and right (x >= 0) of the edge.
    h : float
        Step height at x = 0.
    contrast : float
        Numerator of the figure of merit F = contrast / sigma_o
        (|k2 - k1| for roof and asymmetric edges, h for a step; Sec. IV-B-2).
    figures : tuple of float
        The values of F tried.
    sigmas : tuple of float
        The smoothing filters tried.
    """

    k1: float
    k2: float
    h: float
    contrast: float
    figures: tuple[float, ...]
    sigmas: tuple[float, ...]


#: The three experiments of Sec. IV-B-2 (Figs. 5, 6 and 7).
CASES: dict[str, EdgeCase] = {
    "roof": EdgeCase(2.0, -2.0, 0.0, 4.0, (4.0, 2.0, 1.0), (3.0, 5.0, 7.0, 9.0)),
    "asymmetric": EdgeCase(2.0, -2.0, 2.0, 4.0, (4.0, 2.0, 1.0), (3.0, 5.0, 7.0, 9.0)),
    "step": EdgeCase(0.0, 0.0, 20.0, 20.0, (10.0, 5.0, 2.0), (0.5, 1.0, 2.0, 3.0)),
}


# --------------------------------------------------------------------------- kernels


def window_taps(sigma: float, rounding: str = "up") -> int:
    """Return the number of taps of the 4*sigma + 1 window, made odd and at least 3.

    Parameters
    ----------
    sigma : float
        Standard deviation of the Gaussian (pixels).
    rounding : {"up", "down"}
        How a non-odd ``4*sigma + 1`` is made odd. Sec. IV-B-1 says "a window
        of size 4 sigma + 1"; for every sigma of Table 1 and Figs. 5-7 it is
        already an odd integer, so both roundings agree there.

    Returns
    -------
    int
        Odd window length (5 for sigma = 1 and 17 for sigma = 4, as in Sec. V).
    """
    n = 4.0 * sigma + 1.0
    if rounding == "up":
        taps = math.ceil(n - 1e-9)
        if taps % 2 == 0:
            taps += 1
    elif rounding == "down":
        taps = math.floor(n + 1e-9)
        if taps % 2 == 0:
            taps -= 1
    else:
        raise ValueError(f"rounding must be 'up' or 'down', got {rounding!r}")
    return max(taps, 3)


def gaussian_1d(sigma: float, taps: int | None = None, normalise: bool = True) -> np.ndarray:
    """Return a sampled 1-D Gaussian of the paper's G(x) (Sec. IV-A).

    Parameters
    ----------
    sigma : float
        Standard deviation in pixels.
    taps : int, optional
        Odd window length; default :func:`window_taps` (4*sigma + 1).
    normalise : bool
        True: sample then scale to sum 1 (what our edge detector uses).
        False: the continuous density 1/sqrt(2 pi sigma^2) exp(-x^2 / 2 sigma^2)
        sampled at the integers.

    Returns
    -------
    numpy.ndarray
        Weights w_{-r}..w_r, shape (taps,).
    """
    if taps is None:
        taps = window_taps(sigma)
    r = taps // 2
    x = np.arange(-r, r + 1, dtype=float)
    w = np.exp(-(x**2) / (2.0 * sigma**2)) / math.sqrt(2.0 * math.pi * sigma**2)
    return w / w.sum() if normalise else w


# --------------------------------------------------------------------------- Table 1

#: name -> (dimension, normalised to sum 1, window rounding, circular 2-D support).
TABLE1_VARIANTS: dict[str, tuple[int, bool, str, bool]] = {
    "1d-normalised": (1, True, "up", False),
    "1d-normalised-down": (1, True, "down", False),
    "1d-density": (1, False, "up", False),
    "1d-density-down": (1, False, "down", False),
    "2d-normalised": (2, True, "up", False),
    "2d-normalised-down": (2, True, "down", False),
    "2d-density": (2, False, "up", False),
    "2d-density-down": (2, False, "down", False),
    "2d-normalised-disc": (2, True, "up", True),
    "2d-density-disc": (2, False, "up", True),
}
#: The discretisation of our edge detector (SPEC, step 1): 1-D, sampled, sum 1.
OURS = "1d-normalised"


def table1_sum(sigma: float, variant: str = OURS) -> float:
    """Return Table 1's noise response of the AR operator for one sigma.

    ``sum = sum_{i != 0} G(i)^2 + (G(0) - 1)^2`` (Sec. IV-B-1, the discrete
    form of eq. 14), i.e. N^2 / n_o^2 for white noise: the squared norm of
    the discrete operator f = G - delta (eq. 10).

    Parameters
    ----------
    sigma : float
        Standard deviation of the Gaussian.
    variant : str
        A key of :data:`TABLE1_VARIANTS`: "1d"/"2d" kernel, "normalised"
        (sampled then scaled to sum 1) or "density" (the continuous density
        sampled), "-down" to round an even window down instead of up, "-disc"
        for a circular 2-D support of diameter 4*sigma + 1.

    Returns
    -------
    float
        The sum.
    """
    dim, normalise, rounding, disc = TABLE1_VARIANTS[variant]
    taps = window_taps(sigma, rounding)
    g = gaussian_1d(sigma, taps, normalise=False)
    if dim == 2:
        g = np.outer(g, g)
        if disc:
            r = taps // 2
            yy, xx = np.mgrid[-r : r + 1, -r : r + 1]
            g = np.where(xx**2 + yy**2 <= r * r, g, 0.0)
    if normalise:
        g = g / g.sum()
    f = g.copy()
    f[tuple(n // 2 for n in f.shape)] -= 1.0
    return float(np.sum(f**2))


def table1(variant: str = OURS) -> dict[float, float]:
    """Return Table 1 (sigma -> sum) for one discretisation, see :func:`table1_sum`."""
    return {s: table1_sum(s, variant) for s in PAPER_TABLE1}


def table1_max_error(variant: str) -> float:
    """Return max over sigma of |table1_sum(sigma, variant) - paper's value|."""
    return max(abs(v - PAPER_TABLE1[s]) for s, v in table1(variant).items())


def best_table1_variant() -> str:
    """Return the variant of :data:`TABLE1_VARIANTS` closest to the paper's Table 1."""
    return min(TABLE1_VARIANTS, key=table1_max_error)


# --------------------------------------------------------------------------- localisation


def edge_signal(kind: str, x: np.ndarray) -> np.ndarray:
    """Return the noise-free edge model of eq. (1) / Fig. 4 with c = 0.

    ``z(x) = k1 x`` for x < 0 and ``k2 x + h`` for x >= 0: the paper puts
    x = 0 on the right-hand side of the jump.

    Parameters
    ----------
    kind : {"roof", "asymmetric", "step"}
        Which experiment of Sec. IV-B-2.
    x : numpy.ndarray
        Integer sample positions.

    Returns
    -------
    numpy.ndarray
        z(x), float.
    """
    c = CASES[kind]
    x = np.asarray(x, dtype=float)
    return np.where(x < 0, c.k1 * x, c.k2 * x + c.h)


def ar_profile(z: np.ndarray, sigma: float, search: int = DEFAULT_SEARCH) -> np.ndarray:
    """Return AR = |z_s - z| (eq. 3) at the 2*search + 1 central samples.

    Parameters
    ----------
    z : numpy.ndarray
        Signals, shape (..., n) with n = 2 * (search + r) + 1, r the filter's
        half-width, the true edge (x = 0) at index n // 2. Only samples inside
        the signal enter the filter ("valid" convolution, no border effects).
    sigma : float
        Standard deviation of the 1-D Gaussian (4*sigma + 1 taps, sum 1).
    search : int
        Half-width of the searched area.

    Returns
    -------
    numpy.ndarray
        AR at offsets -search..search, shape (..., 2*search + 1).
    """
    w = gaussian_1d(sigma)
    taps = w.size
    m = 2 * search + 1
    if z.shape[-1] != m + taps - 1:
        raise ValueError(f"signal length {z.shape[-1]} != {m + taps - 1} for sigma={sigma}")
    smoothed = np.zeros(z.shape[:-1] + (m,))
    for k in range(taps):  # the kernel is symmetric: correlation == convolution
        smoothed += w[k] * z[..., k : k + m]
    r = taps // 2
    return np.abs(smoothed - z[..., r : r + m])


def edge_offset(kind: str, j: np.ndarray) -> np.ndarray:
    """Map the position j of the AR maximum to the delocalisation x0.

    For the roof and the asymmetric step the noise-free AR maximum is the
    single pixel x = 0 (the theorem of Sec. IV-A), so ``x0 = j``. A pure
    step's jump lies between the pixels -1 and 0, and the noise-free AR is
    equal on both (eq. 7 for a symmetric discrete kernel); so x0 is the signed
    distance from the nearer of the two: ``x0 = j`` for j >= 0 and
    ``x0 = j + 1`` for j < 0. Both pixels adjacent to the jump give x0 = 0.

    Parameters
    ----------
    kind : {"roof", "asymmetric", "step"}
        The edge type.
    j : numpy.ndarray
        Offsets of the AR maxima from the model's x = 0 (integers).

    Returns
    -------
    numpy.ndarray
        x0, integers.
    """
    j = np.asarray(j)
    if kind == "step":
        return np.where(j < 0, j + 1, j)
    return j


def localization(
    kind: str,
    F: float,
    sigma: float,
    trials: int,
    rng: np.random.Generator,
    search: int = DEFAULT_SEARCH,
) -> np.ndarray:
    """Run the localisation experiment of Sec. IV-B-2 for one (edge, F, sigma).

    Each trial adds white Gaussian noise of std sigma_o = contrast / F to the
    edge of eq. (1), smooths it with a 1-D Gaussian of std sigma, computes AR
    (eq. 3) and takes the AR maximum within +-search pixels of the true edge.
    All trials are one (trials, n) array.

    Parameters
    ----------
    kind : {"roof", "asymmetric", "step"}
        Fig. 5, 6 or 7.
    F : float
        Figure of merit: |k2 - k1| / sigma_o (roof, asymmetric) or
        h / sigma_o (step). ``math.inf`` gives the noise-free signal.
    sigma : float
        Standard deviation of the smoothing Gaussian.
    trials : int
        Number of noisy signals (the paper: 12 800).
    rng : numpy.random.Generator
        Source of the noise.
    search : int
        Half-width of the searched area.

    Returns
    -------
    numpy.ndarray
        x0 of every trial (int64, shape (trials,)), see :func:`edge_offset`.
    """
    sigma_o = CASES[kind].contrast / F
    r = window_taps(sigma) // 2
    x = np.arange(-(search + r), search + r + 1)
    z = edge_signal(kind, x) + sigma_o * rng.standard_normal((trials, x.size))
    ar = ar_profile(z, sigma, search)
    j = np.argmax(ar, axis=-1) - search
    return edge_offset(kind, j).astype(np.int64)


def fmt_num(v: float) -> str:
    """Format F or sigma for a JSON key: 4.0 -> "4", 0.5 -> "0.5"."""
    return f"{v:g}"


def within_probabilities(x0: np.ndarray, radii: Sequence[int] = (0, 1, 2)) -> dict[int, float]:
    """Return P(|x0| <= k) for each k in radii."""
    a = np.abs(x0)
    return {k: float(np.mean(a <= k)) for k in radii}


def run_localization(
    trials: int, seed: int, search: int = DEFAULT_SEARCH
) -> dict[str, dict[tuple[float, float], np.ndarray]]:
    """Run all 36 cases of Figs. 5-7 from one seeded generator, in a fixed order.

    Returns
    -------
    dict
        kind -> (F, sigma) -> x0 array.
    """
    rng = np.random.default_rng(seed)
    out: dict[str, dict[tuple[float, float], np.ndarray]] = {}
    for kind in KINDS:
        case = CASES[kind]
        out[kind] = {
            (F, s): localization(kind, F, s, trials, rng, search)
            for F in case.figures
            for s in case.sigmas
        }
    return out


def localization_summary(
    runs: dict[str, dict[tuple[float, float], np.ndarray]],
) -> dict[str, dict[str, float]]:
    """Return the ``localization`` block of paper.json: P(|x0| <= 0, 1, 2) per case."""
    summary: dict[str, dict[str, float]] = {}
    for kind, cases in runs.items():
        block: dict[str, float] = {}
        for (F, s), x0 in cases.items():
            for k, p in within_probabilities(x0).items():
                block[f"F{fmt_num(F)}_sigma{fmt_num(s)}_within{k}"] = round(p, 6)
        summary[kind] = block
    return summary


def search_sensitivity(
    trials: int, seed: int, radii: Sequence[int] = (2, 3, 4, 5)
) -> dict[str, dict[int, float]]:
    """Return the paper's two quoted figures as a function of the searched area.

    The paper searches "a small area around the known edge point" without
    giving its size (Sec. IV-B-2); P(|x0| <= 1) falls as the area grows,
    because every extra pixel is one more chance for noise to win.

    Returns
    -------
    dict
        "roof F4 sigma5" / "step F5 sigma0.5" -> search half-width -> P(|x0| <= 1).
    """
    out: dict[str, dict[int, float]] = {"roof F4 sigma5": {}, "step F5 sigma0.5": {}}
    for w in radii:
        rng = np.random.default_rng(seed)
        roof = localization("roof", 4.0, 5.0, trials, rng, w)
        step = localization("step", 5.0, 0.5, trials, rng, w)
        out["roof F4 sigma5"][w] = within_probabilities(roof, (1,))[1]
        out["step F5 sigma0.5"][w] = within_probabilities(step, (1,))[1]
    return out


# --------------------------------------------------------------------------- output


def build_results(
    runs: dict[str, dict[tuple[float, float], np.ndarray]], seed: int, trials: int
) -> dict:
    """Return the content of paper.json."""
    return {
        "table1": {f"{s:.1f}": round(v, 6) for s, v in table1(OURS).items()},
        "table1_paper": {f"{s:.1f}": v for s, v in PAPER_TABLE1.items()},
        "localization": localization_summary(runs),
        "seed": seed,
        "trials": trials,
    }


def print_table1() -> None:
    """Print Table 1: paper, ours, and the closest variant tried."""
    best = best_table1_variant()
    ours, theirs = table1(OURS), table1(best)
    print("Table 1 (Sec. IV-B-1): sum = sum_{i!=0} G(i)^2 + (G(0)-1)^2, window 4*sigma+1")
    print(f"  ours = {OURS}; closest variant tried = {best}")
    print(f"  {'sigma':>5} {'paper':>7} {'ours':>7} {'|diff|':>7} {'closest':>8} {'|diff|':>7}")
    for s, p in PAPER_TABLE1.items():
        print(
            f"  {s:5.1f} {p:7.3f} {ours[s]:7.3f} {abs(ours[s] - p):7.3f}"
            f" {theirs[s]:8.3f} {abs(theirs[s] - p):7.3f}"
        )
    print("  max |diff| per variant:")
    for name in sorted(TABLE1_VARIANTS, key=table1_max_error):
        print(f"    {name:20s} {table1_max_error(name):.3f}")
    match = table1_max_error(best) <= 0.01
    print(f"  variant within 0.01 for every sigma: {best if match else 'none'}")


def print_localization(summary: dict[str, dict[str, float]]) -> None:
    """Print P(|x0| <= 1) for every case and the paper's two quoted figures."""
    print("Localisation (Sec. IV-B-2, Figs. 5-7): P(|x0| <= 1)")
    for kind in KINDS:
        case = CASES[kind]
        print(f"  {kind}: rows F, columns sigma " + " ".join(f"{s:>6g}" for s in case.sigmas))
        for F in case.figures:
            row = " ".join(
                f"{summary[kind][f'F{fmt_num(F)}_sigma{fmt_num(s)}_within1']:6.3f}"
                for s in case.sigmas
            )
            print(f"    F={F:<4g}{'':25s}{row}")
    for kind, quoted in PAPER_LOCALIZATION.items():
        for key, p in quoted.items():
            print(f"  paper {kind} {key}: {p:.2f}, ours {summary[kind][key]:.3f}")


def plot_figures(
    runs: dict[str, dict[tuple[float, float], np.ndarray]], out_dir: Path, search: int
) -> list[Path]:
    """Plot the probability distributions of x0 like Figs. 5-7 (one panel per F).

    Returns
    -------
    list of pathlib.Path
        The PNG files written, or an empty list when matplotlib is missing.
    """
    try:
        import matplotlib
    except ImportError:
        print("matplotlib is not installed: plots skipped")
        return []
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = {"roof": "fig5_roof", "asymmetric": "fig6_asymmetric", "step": "fig7_step"}
    titles = {
        "roof": "Fig. 5: roof edge, |k2-k1| = 4",
        "asymmetric": "Fig. 6: asymmetric step, h = 2, |k2-k1| = 4",
        "step": "Fig. 7: step edge, h = 20",
    }
    written = []
    for kind in KINDS:
        case = CASES[kind]
        # a folded step offset (edge_offset) never reaches -search
        bins = np.arange(-search + (kind == "step"), search + 1)
        fig, axes = plt.subplots(1, len(case.figures), figsize=(4 * len(case.figures), 3.4))
        for ax, F in zip(axes, case.figures, strict=True):
            for s in case.sigmas:
                x0 = runs[kind][(F, s)]
                p = np.array([np.mean(x0 == b) for b in bins])
                ax.plot(bins, p, marker="o", ms=3, label=f"σ = {s:g}")
            ax.set_title(f"F = {F:g}")
            ax.set_xlabel("x0 (pixels)")
            ax.set_ylim(0, 1)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("P(x0)")
        axes[-1].legend(fontsize=8)
        fig.suptitle(titles[kind])
        fig.tight_layout()
        path = out_dir / f"paper_{names[kind]}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """Parse the command line."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seed", type=int, default=DEFAULT_SEED, help="noise seed (default 1990)")
    p.add_argument(
        "--trials", type=int, default=DEFAULT_TRIALS, help="trials per case (default 12800)"
    )
    p.add_argument(
        "--search",
        type=int,
        default=DEFAULT_SEARCH,
        help="half-width of the searched area in pixels (default 5)",
    )
    p.add_argument("--out-dir", type=Path, default=RESULTS_DIR, help="where to write results")
    p.add_argument("--no-plots", action="store_true", help="write paper.json only")
    args = p.parse_args(argv)
    if args.trials < 1 or args.search < 1:
        p.error("--trials and --search must be >= 1")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    """Compute Table 1 and Figs. 5-7, print them, write paper.json and the plots."""
    args = parse_args(argv)
    t0 = time.perf_counter()
    print_table1()
    runs = run_localization(args.trials, args.seed, args.search)
    results = build_results(runs, args.seed, args.trials)
    print_localization(results["localization"])
    print("P(|x0| <= 1) against the half-width W of the searched area (not in paper.json):")
    for name, by_w in search_sensitivity(args.trials, args.seed).items():
        print(f"  {name:17s} " + "  ".join(f"W={w}: {p:.3f}" for w, p in by_w.items()))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    path = args.out_dir / "paper.json"
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(results, indent=2, sort_keys=True) + "\n")
    tmp.replace(path)
    print(f"wrote {path}")
    if not args.no_plots:
        for png in plot_figures(runs, args.out_dir, args.search):
            print(f"wrote {png}")
    print(f"done in {time.perf_counter() - t0:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
