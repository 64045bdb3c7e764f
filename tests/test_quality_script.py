"""Tests of benchmarks/quality.py: face widths (the ``--widths`` table of docs/quality.md), options."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import script_error

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import quality  # noqa: E402


@pytest.mark.parametrize("thickness", [1, 3, 5, 7])
def test_a_band_has_its_thickness_as_width_whatever_its_length(thickness: int) -> None:
    for length in (20, 36):
        band = np.zeros((40, 40), bool)
        band[10:10 + thickness, 2:2 + length] = True
        assert quality.face_width(band) == thickness
        assert quality.face_width(band.T) == thickness


def test_an_even_thickness_rounds_down_to_the_odd_square_inside() -> None:
    band = np.zeros((30, 30), bool)
    band[5:9, 3:27] = True  # 4 thick: a 3x3 square fits, a 5x5 does not
    assert quality.face_width(band) == 3


def test_a_face_at_the_image_border_is_measured_against_the_border() -> None:
    face = np.zeros((20, 20), bool)
    face[:, :4] = True  # 4 wide along the left edge: the widest square is 3x3
    assert quality.face_width(face) == 3
    assert quality.face_width(np.ones((9, 9), bool)) == 9
    assert quality.face_width(np.zeros((5, 5), bool)) == 0


def test_width_classes_cover_every_width_once() -> None:
    classes = [quality.width_class(w) for w in range(1, 14)]
    assert classes[:3] == ["1-3"] * 3
    assert classes[3:5] == ["4-5"] * 2
    assert classes[5:9] == ["6-9"] * 4
    assert set(classes[9:]) == {">=10"}


@pytest.mark.parametrize(("args", "named"), [
    (["--seeds", "0,x"], "'0,x'"),
    (["--seeds", "-1"], "'-1'"),
    (["--scenes", "nut,teapot"], "teapot"),
    (["--size", "8x128"], "'8x128'"),
    (["--set", "rounds=1"], "'rounds=1'"),
    (["--set", "refine.nope=1"], "nope"),
    (["--set", "refine.min_region=0"], "min_region = 0"),
    (["--set", "refine.passes=[\"nope\"]"], "passes = ['nope']"),
    (["--preset", "fast"], "'fast'"),
])
def test_a_bad_option_gets_one_line_naming_it_and_exit_code_2(
        args: list[str], named: str, capsys: pytest.CaptureFixture[str]) -> None:
    err = script_error(quality.main, args, capsys)
    assert named in err and ("allowed" in err or "expected" in err)


@pytest.mark.parametrize(("item", "named"), [
    ("split.merge=false", "refine.passes"), ("split.fit_factor=1.5", "refine.fit_factor"),
    ("split.rounds=1", "no longer a setting"),
])
def test_an_old_split_key_gets_one_line_naming_the_new_one(
        item: str, named: str, capsys: pytest.CaptureFixture[str]) -> None:
    err = script_error(quality.main, ["--set", item], capsys)
    assert named in err and f"[split] {item.split('.')[1].split('=')[0]} " in err


def test_the_options_are_parsed_into_seeds_scenes_and_size() -> None:
    assert quality.seed_list("3,0,12") == (3, 0, 12)
    assert quality.scene_list("nut, cup") == ["nut", "cup"]
    assert quality.frame_size("480X640") == (480, 640)
    assert quality.frame_size("64") == (64, 64)
    assert quality.set_item("refine.fit_factor=1.5") == "refine.fit_factor=1.5"


def test_best_overlap_is_the_smaller_share_of_the_nearest_region() -> None:
    gt = np.zeros((4, 10), np.int32)
    gt[:, :5] = 1  # 20 pixels
    pred = np.zeros((4, 10), np.int32)
    pred[:, :4] = 3  # 16 of them: 16/20 of G, 16/16 of R
    pred[:, 4:] = 5  # 4 of them in a region of 24: 4/20, 4/24
    assert quality.best_overlap(gt, pred, 1) == pytest.approx(0.8)
    pred[:, 4] = 3  # R holds all of G and nothing else
    assert quality.best_overlap(gt, pred, 1) == pytest.approx(1.0)
    pred[:, 5] = 3  # R grows beyond G: 20/24 of R
    assert quality.best_overlap(gt, pred, 1) == pytest.approx(20 / 24)
    pred[:] = 0  # unlabelled pixels are no region
    assert quality.best_overlap(gt, pred, 1) == 0.0
    assert quality.best_overlap(gt, pred, 7) == 0.0  # no such GT region


def test_tuning_sets_a_constant_of_the_refinement_for_the_run(monkeypatch) -> None:
    import argparse

    from rangeseg_cli import config as config_module
    from rangeseg_cli.config import load_config

    monkeypatch.setattr(config_module, "TUNING", config_module.TUNING)
    assert quality.tuning_item("rounds=1") == ("rounds", 1)
    assert quality.tuning_item("trim_pieces=False") == ("trim_pieces", False)
    for bad in ("rounds=x", "trim_pieces=maybe", "nope=1", "fit_factor=2", "rounds"):
        with pytest.raises(argparse.ArgumentTypeError):
            quality.tuning_item(bad)  # fit_factor is a [refine] key: --set
    before = load_config().split
    quality.use_tuning({"rounds": 1, "trim_pieces": False})
    after = load_config().split
    assert (after.rounds, after.trim_pieces) == (1, False)
    assert (before.rounds, before.trim_pieces) == (2, True)
    assert after.fit_factor == before.fit_factor
