"""Tests of benchmarks/noise_scale.py: the RMS error of a quadric per window side."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import noise_scale  # noqa: E402


def test_a_quadric_leaves_no_error_in_any_window():
    r, c = np.mgrid[:60, :60].astype(np.float64)
    z = 3.0 + 0.5 * c - 0.2 * r + 0.01 * c * c - 0.02 * r * c + 0.03 * r * r
    for side in (5, 15):
        assert noise_scale.quadric_rms(z, side).max() < 1e-9


def test_white_noise_leaves_its_sigma_at_every_side_and_smoothed_noise_grows():
    rng = np.random.default_rng(3)
    white = rng.normal(0.0, 0.5, (200, 200))
    flat = [np.median(noise_scale.quadric_rms(white, k)) for k in (5, 21)]
    assert flat == pytest.approx([0.5, 0.5], rel=0.1)
    smooth = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (200, 200)), 3.0)
    grows = [np.median(noise_scale.quadric_rms(smooth, k)) for k in (5, 21)]
    assert grows[1] > 3 * grows[0]


def test_windows_with_a_pixel_without_reading_are_left_out():
    z = np.zeros((20, 20))
    z[10, 10] = np.nan
    assert noise_scale.quadric_rms(z, 5, stride=1).size == 16 * 16 - 25
    with pytest.raises(ValueError, match="odd"):
        noise_scale.quadric_rms(z, 4)


def test_a_folder_without_the_arc_frames_is_a_one_line_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        noise_scale.main([str(tmp_path)])
    assert stop.value.code == 2
    assert "no suction-background.depth.png" in capsys.readouterr().err
