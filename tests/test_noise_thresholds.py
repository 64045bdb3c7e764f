"""Issue 32: step and roof thresholds that follow the sensor (rangeseg_cli.stages.noise, Sec. V-1, V-2).

Constructed cases with known answers: the paper's thresholds at the paper's
scale and noise, thresholds in proportion to the lateral scale, rising with
the noise, and the same edges for one scene written in two depth units or
seen from two distances.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rangeseg_cli.config import Config, load_config
from rangeseg_cli.pipeline import stage_edges, uses_noise
from rangeseg_cli.stages.noise import (
    NOISE_SLOPE,
    PAPER_NOISE,
    PAPER_UNITS_PER_PIXEL,
    estimate_noise,
    lateral_scale,
    noise_scaled_config,
    sensor_config,
    threshold_factor,
)
from rangeseg_cli.stages.rangeimage import to_heights

AUTO = load_config()  # auto_thresholds is on by default
FIXED = load_config(overrides={"input": {"auto_thresholds": False}})
PAPER_T = (6.0, 6.0, 4.0)


def thresholds(config: Config) -> tuple[float, float, float]:
    return config.step.threshold, config.roof.threshold_a, config.roof.threshold_b


def scene(noise: float = 0.0, seed: int = 0, n: int = 96) -> np.ndarray:
    """A block with a sloped top and a roof on a tilted table: step and roof edges, heights."""
    y, x = np.mgrid[0:n, 0:n].astype(np.float64)
    z = 40.0 + 0.3 * x - 0.2 * y
    block = (abs(y - n / 2) < n / 4) & (abs(x - n / 2) < n / 4)
    roof = 90.0 - 2.5 * np.abs(x - n / 2)
    z[block] = roof[block]
    if noise:
        z += np.random.default_rng(seed).normal(0.0, noise, z.shape)
    return z


def test_the_defaults_and_sensor_presets_follow_the_sensor_and_the_paper_preset_does_not():
    assert AUTO.input.auto_thresholds and uses_noise(AUTO)
    for preset in ("mm-depth", "tenth-mm-depth", "metre-depth"):
        assert load_config(preset=preset).input.auto_thresholds
    paper = load_config(preset="paper")
    assert not paper.input.auto_thresholds and not uses_noise(paper)
    for noise in (0.0, 3.0, 10.0):
        for upp in (0.0, 1.0, 7.0):
            assert noise_scaled_config(paper, noise, upp) is paper


@pytest.mark.parametrize("noise", [0.0, 1.0, 2.0, PAPER_NOISE])
def test_at_the_paper_scale_and_noise_the_thresholds_are_the_papers(noise: float) -> None:
    assert noise_scaled_config(AUTO, noise) is AUTO  # no scale: the paper's units
    at_scale = noise_scaled_config(AUTO, noise, PAPER_UNITS_PER_PIXEL)
    assert thresholds(at_scale) == PAPER_T


def test_the_thresholds_are_in_proportion_to_the_lateral_scale() -> None:
    for upp in (0.25, 1.05, 3.0, 6.0, 30.0):
        s = upp / PAPER_UNITS_PER_PIXEL
        scaled = noise_scaled_config(AUTO, 0.1 * s, upp)
        assert thresholds(scaled) == pytest.approx(tuple(t * s for t in PAPER_T))
    # the SR300 of sample_data/arc: about 1.05 mm per pixel -> about the hand-tuned 2 / 2 / 1.5
    sr300 = thresholds(noise_scaled_config(AUTO, 0.2, 650.0 / 616.5))
    assert sr300 == pytest.approx((2.1, 2.1, 1.4), abs=0.02)


def test_the_thresholds_rise_with_the_noise_above_the_papers() -> None:
    noises = [0.0, 1.0, 2.0, PAPER_NOISE, 2.6, 3.0, 4.0, 8.0]
    for upp in (0.0, PAPER_UNITS_PER_PIXEL, 12.0):
        s = upp / PAPER_UNITS_PER_PIXEL if upp else 1.0  # the noise counts at the image's scale
        levels = [thresholds(noise_scaled_config(AUTO, n * s, upp)) for n in noises]
        for low, high in zip(levels, levels[1:], strict=False):
            assert all(a <= b for a, b in zip(low, high, strict=True))
        assert levels[-1][0] > levels[3][0] and levels[-1][2] > levels[3][2]
    # sigma_o = 3, as estimate_noise reads it on 8-bit scenes: about 1.5 x the paper's
    assert threshold_factor(0.0, 3.11) == pytest.approx(1.0 + NOISE_SLOPE * (3.11 - PAPER_NOISE))
    assert 1.4 < threshold_factor(0.0, 3.11) < 1.7
    # the same noise counted at the image's scale: twice the scale, twice the noise, twice T
    assert threshold_factor(6.0, 8.0) == pytest.approx(2.0 * threshold_factor(3.0, 4.0))


def test_lateral_scale_is_the_footprint_at_the_median_depth_or_units_per_pixel() -> None:
    camera = load_config(preset="mm-depth",
                         overrides={"input": {"intrinsics": [500.0, 500.0, 0.0, 0.0]}}).input
    depth = np.full((40, 50), 600.0)
    depth[:5] = 2000.0  # a few far pixels and no readings do not move it
    depth[-4:] = 0.0
    z = to_heights(depth, camera)
    assert lateral_scale(z, camera) == pytest.approx(600.0 / 500.0)
    assert lateral_scale(np.full((4, 4), np.nan), camera) == 0.0
    height_map = load_config(overrides={"input": {"units_per_pixel": 2.5}}).input
    assert lateral_scale(scene(), height_map) == 2.5
    assert lateral_scale(scene(), AUTO.input) == 0.0


@pytest.mark.parametrize("noise", [0.0, 1.5, 4.0])
def test_one_scene_in_two_depth_units_gives_the_same_edges(noise: float) -> None:
    z = scene(noise, seed=3)
    coarse = load_config(overrides={"input": {"units_per_pixel": 2.0}})
    fine = load_config(overrides={"input": {"units_per_pixel": 8.0}})  # 4 x finer units
    a, b = stage_edges(z, coarse), stage_edges(4.0 * z, fine)
    np.testing.assert_array_equal(a.codes, b.codes)
    assert a.step.any() and a.roof.any()
    # with the thresholds as given, the finer units find edges the coarse ones do not
    fixed = replace(fine, input=replace(fine.input, auto_thresholds=False))
    assert np.count_nonzero(stage_edges(4.0 * z, fixed).codes) > np.count_nonzero(a.codes)


def test_one_scene_seen_from_twice_as_far_with_a_camera_gives_the_same_edges() -> None:
    """A scene twice as large at twice the distance: the same pixels, depths doubled."""
    camera = {"intrinsics": [600.0, 600.0, 48.0, 48.0]}
    config = load_config(preset="mm-depth", overrides={"input": camera})
    depth = 700.0 - scene(0.5, seed=5)  # mm, closer = smaller
    near = to_heights(depth, config.input)
    far = to_heights(2.0 * depth, config.input)
    a, b = stage_edges(near, config), stage_edges(far, config)
    np.testing.assert_array_equal(a.codes, b.codes)
    used = sensor_config(config, far, estimate_noise(far))
    assert used.step.threshold == pytest.approx(6.0 * 2.0 * np.median(depth) / 600.0 / 3.0)


def test_noise_below_the_papers_leaves_the_edges_of_a_height_map_as_they_were() -> None:
    for noise in (0.0, 1.0, 2.0):
        z = np.round(scene(noise, seed=7))  # 8-bit style
        np.testing.assert_array_equal(stage_edges(z, AUTO).codes, stage_edges(z, FIXED).codes)


def test_above_the_papers_noise_the_thresholds_drop_noise_edges() -> None:
    rng = np.random.default_rng(11)
    y, x = np.mgrid[0:96, 0:96].astype(np.float64)
    z = np.round(60.0 + 0.5 * x - 0.3 * y + rng.normal(0.0, 3.5, x.shape))  # a noisy plane
    auto, fixed = stage_edges(z, AUTO).codes, stage_edges(z, FIXED).codes
    assert np.count_nonzero(auto) < 0.5 * np.count_nonzero(fixed)
