"""Tests of benchmarks/pass_ablation.py: its variants, its seed sets and its table."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import pass_ablation  # noqa: E402

from rangeseg_cli.config import REFINE_PASSES  # noqa: E402


def test_the_variants_are_the_defaults_and_each_pass_left_out_once() -> None:
    names = list(pass_ablation.VARIANTS)
    assert names[0] == "defaults" and pass_ablation.VARIANTS["defaults"] is None
    assert names[1:] == [f"without {p}" for p in dict.fromkeys(REFINE_PASSES)]


def test_seed_sets_parse_and_bad_ones_are_refused() -> None:
    assert pass_ablation.set_list("0-8,9-17") == ((0, 8), (9, 17))
    for bad in ("0-8,x", "5-2", "-1-3", ""):
        with pytest.raises(argparse.ArgumentTypeError, match="--sets"):
            pass_ablation.set_list(bad)


def test_the_table_gives_each_variant_its_change_per_set_and_in_all(monkeypatch) -> None:
    monkeypatch.setattr(pass_ablation, "VARIANTS", {"defaults": None, "without merge": "x"})
    report = {"date": "today", "sets": ["0-8", "9-17"],
              "correct": {"defaults": {"0-8": [10, 9, 8], "9-17": [7, 6, 5]},
                          "without merge": {"0-8": [10, 8, 8], "9-17": [7, 6, 6]}}}
    rows = pass_ablation.markdown(report).splitlines()
    assert rows[-2] == "| defaults | 10/9/8 | 7/6/5 | 17/15/13 |"
    assert rows[-1] == "| without merge | +0/-1/+0 | +0/+0/+1 | +0/-1/+1 |"
