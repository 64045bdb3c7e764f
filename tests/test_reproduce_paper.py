"""Tests of benchmarks/reproduce_paper.py (Table 1 and Figs. 5-7 of Sec. IV-B)."""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import reproduce_paper as rp  # noqa: E402

SIGMAS = sorted(rp.PAPER_TABLE1)


def test_window_is_4_sigma_plus_1_odd_at_least_3() -> None:
    assert [rp.window_taps(s) for s in (0.5, 1, 2, 3, 4, 5, 9)] == [3, 5, 9, 13, 17, 21, 37]
    assert rp.window_taps(0.25) == 3
    assert rp.window_taps(1.25) == 7  # 6 rounded up to odd
    assert rp.window_taps(1.25, "down") == 5


def test_our_table1_sum_matches_a_hand_computation() -> None:
    # sigma = 1, 5 taps, sampled and normalised to sum 1.
    g = [math.exp(-(i * i) / 2.0) for i in range(-2, 3)]
    w = [v / sum(g) for v in g]
    expected = sum(v * v for v in w) - 2.0 * w[2] + 1.0
    assert rp.table1_sum(1.0) == pytest.approx(expected, rel=1e-12)
    assert rp.table1_sum(1.0, "1d-density") != pytest.approx(expected, abs=1e-3)


def test_no_1d_variant_reproduces_table1() -> None:
    # The paper's values are far above any 1-D discretisation (N^2 ~ 1 - 0.52/sigma).
    for name, (dim, *_rest) in rp.TABLE1_VARIANTS.items():
        if dim == 1:
            assert rp.table1_max_error(name) > 0.2, name


def test_2d_variants_come_closest_to_table1() -> None:
    best = rp.best_table1_variant()
    assert rp.TABLE1_VARIANTS[best][0] == 2
    assert rp.table1_max_error(best) < 0.03
    assert rp.table1_max_error("2d-normalised") < 0.05
    # for the larger filters the 2-D kernel agrees to the paper's two decimals
    for s in (3.0, 4.0):
        assert rp.table1_sum(s, "2d-normalised") == pytest.approx(rp.PAPER_TABLE1[s], abs=0.005)


def test_table1_sum_is_below_one_and_grows_with_sigma() -> None:
    # "The table shows that N <= n_o" (Sec. IV-B-1).
    for name in rp.TABLE1_VARIANTS:
        vals = [rp.table1_sum(s, name) for s in SIGMAS]
        assert all(0.0 < v < 1.0 for v in vals), name
        assert vals == sorted(vals), name


@pytest.mark.parametrize("kind", rp.KINDS)
def test_noise_free_ar_maximum_is_at_the_edge(kind: str) -> None:
    search = 5
    for sigma in rp.CASES[kind].sigmas:
        r = rp.window_taps(sigma) // 2
        z = rp.edge_signal(kind, np.arange(-(search + r), search + r + 1))
        ar = rp.ar_profile(z, sigma, search)
        offsets = np.arange(-search, search + 1)
        top = ar.max()
        if kind == "step":
            # both pixels adjacent to the jump, and only they, share the maximum
            assert np.isclose(ar[offsets == -1][0], top)
            assert np.isclose(ar[offsets == 0][0], top)
            assert np.all(ar[(offsets < -1) | (offsets > 0)] < top - 1e-9)
        else:
            assert np.argmax(ar) == search
            assert np.all(np.delete(ar, search) < top - 1e-9)
        x0 = rp.localization(kind, math.inf, sigma, 4, np.random.default_rng(0), search)
        assert np.all(x0 == 0), (kind, sigma)


def test_step_offset_counts_both_sides_of_the_jump_as_zero() -> None:
    j = np.array([-3, -2, -1, 0, 1, 2])
    assert rp.edge_offset("step", j).tolist() == [-2, -1, 0, 0, 1, 2]
    assert rp.edge_offset("roof", j).tolist() == j.tolist()


def test_roof_and_step_localization_match_the_papers_trend() -> None:
    rng = np.random.default_rng(7)
    roof = rp.localization("roof", 4.0, 5.0, 2000, rng)
    step = rp.localization("step", 5.0, 0.5, 2000, rng)
    assert rp.within_probabilities(roof)[1] > 0.9  # paper: ~0.98
    assert rp.within_probabilities(step)[1] > 0.7  # paper: 0.91, ours ~0.80 at W = 5
    # a smaller search area can only help: W = 2 gets near the paper's 0.91
    step2 = rp.localization("step", 5.0, 0.5, 2000, np.random.default_rng(7), search=2)
    assert rp.within_probabilities(step2)[1] > 0.9
    noisy = rp.localization("roof", 1.0, 3.0, 2000, rng)
    assert rp.within_probabilities(noisy)[1] < rp.within_probabilities(roof)[1]


def test_localization_is_deterministic_per_seed() -> None:
    a = rp.run_localization(300, seed=11)
    b = rp.run_localization(300, seed=11)
    c = rp.run_localization(300, seed=12)
    for kind in rp.KINDS:
        for key in a[kind]:
            np.testing.assert_array_equal(a[kind][key], b[kind][key])
    assert any(not np.array_equal(a[k][key], c[k][key]) for k in rp.KINDS for key in a[k])


def test_main_writes_paper_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["--trials", "200", "--seed", "5", "--out-dir", str(tmp_path), "--no-plots"]
    assert rp.main(argv) == 0
    text = (tmp_path / "paper.json").read_text()
    data = json.loads(text)
    assert text == json.dumps(data, indent=2, sort_keys=True) + "\n"
    assert set(data) == {"table1", "table1_paper", "localization", "seed", "trials"}
    assert data["seed"] == 5 and data["trials"] == 200
    keys = ["0.5", "1.0", "2.0", "3.0", "4.0", "5.0"]
    assert sorted(data["table1"]) == keys and sorted(data["table1_paper"]) == keys
    assert data["table1_paper"]["1.0"] == 0.713
    assert data["table1"]["1.0"] == pytest.approx(rp.table1_sum(1.0), abs=1e-6)
    loc = data["localization"]
    assert set(loc) == {"roof", "asymmetric", "step"}
    assert all(len(block) == 4 * 3 * 3 for block in loc.values())
    assert "F4_sigma5_within1" in loc["roof"] and "F5_sigma0.5_within1" in loc["step"]
    assert "F1_sigma9_within2" in loc["asymmetric"]
    for block in loc.values():
        for key, p in block.items():
            if key.endswith("_within0"):
                assert p <= block[key[:-1] + "1"] <= block[key[:-1] + "2"]
    assert not list(tmp_path.glob("*.png"))
    assert "Table 1" in capsys.readouterr().out
    assert rp.main(argv) == 0
    assert (tmp_path / "paper.json").read_text() == text


def test_main_writes_the_three_figures(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    assert rp.main(["--trials", "50", "--out-dir", str(tmp_path)]) == 0
    for name in ("paper_fig5_roof.png", "paper_fig6_asymmetric.png", "paper_fig7_step.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
