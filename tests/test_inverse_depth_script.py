"""Tests of benchmarks/inverse_depth.py: a plane is affine in inverse depth, the summary."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import script_error

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import inverse_depth  # noqa: E402


def _affine_residual(values: np.ndarray) -> float:
    rows, cols = np.indices(values.shape, dtype=float)
    a = np.column_stack([np.ones(values.size), rows.ravel(), cols.ravel()])
    coef, *_ = np.linalg.lstsq(a, values.ravel(), rcond=None)
    return float(np.abs(a @ coef - values.ravel()).max())


def test_a_tilted_plane_is_affine_in_inverse_depth_not_in_depth():
    # a pinhole camera (f = 300 px, centre 40, 60) sees the plane 0.4 x + 0.2 y + 0.9 z = 500 (mm)
    rows, cols = np.indices((80, 120), dtype=float)
    x, y = (cols - 60.0) / 300.0, (rows - 40.0) / 300.0  # the ray through each pixel
    depth = 500.0 / (0.4 * x + 0.2 * y + 0.9)  # z along the optical axis where the ray meets it
    d0 = float(np.median(depth))
    assert _affine_residual(depth) > 1.0  # mm: curved in depth
    assert _affine_residual(inverse_depth.inverse_heights(depth, d0)) < 1e-9
    # larger = closer, no reading where the depth is 0
    assert inverse_depth.inverse_heights(np.array([400.0, 0.0]), 500.0)[0] > 500.0
    assert np.isnan(inverse_depth.inverse_heights(np.array([400.0, 0.0]), 500.0)[1])


def test_summary_sums_each_way_per_scene_and_over_all():
    counts = {"gt_regions": 4, "correct": 3, "over": 1, "under": 0, "missed": 0}
    better = dict(counts, correct=4, over=0)
    frames = [{"scene": "cam-pile", "seed": 1, "depth": counts, "inverse": better},
              {"scene": "cam-tote", "seed": 1, "depth": counts, "inverse": counts}]
    table = inverse_depth.summarise(frames)
    assert table["all"]["depth"]["correct"] == 6
    assert table["all"]["inverse"]["correct"] == 7
    assert table["cam-pile"]["inverse"]["over"] == 0
    text = inverse_depth.markdown(table, "1")
    assert "| all | 8 | 6 -> 7 |" in text.splitlines()[-1]


@pytest.mark.parametrize(("argv", "named"), [
    (["--scenes", "cam-pile,cam-nothing"], "--scenes: unknown cam-nothing"),
    (["--scenes", "cam-empty-tote"], "--scenes: unknown cam-empty-tote"),
    (["--seeds", "abc"], "--seeds 'abc'"),
    (["--seeds", "5-2"], "--seeds '5-2'"),
    (["--jobs", "0"], "--jobs 0"),
])
def test_bad_options_are_one_line_errors_naming_the_option(argv, named, capsys):
    assert named in script_error(inverse_depth.main, argv, capsys)
