import numpy as np
import pytest

from conftest import step_image
from rangeseg_cli.config import load_config
from rangeseg_cli.stages.edges import (
    DIRECTIONS,
    absolute_residual,
    ar_2d,
    detect_edges,
    gaussian_taps,
)

CFG = load_config()


def roof_image(size: int = 64, slope: float = 2.0, noise: float = 0.0, seed: int = 0):
    x = np.arange(size, dtype=float)
    z = np.tile(100.0 - slope * np.abs(x - size // 2), (size, 1))
    if noise:
        z += np.random.default_rng(seed).normal(0, noise, z.shape)
    return z


def test_gaussian_taps_are_normalised_and_symmetric():
    w = gaussian_taps(4.0, 17)
    assert w.sum() == pytest.approx(1.0) and np.allclose(w, w[::-1]) and w.argmax() == 8


def test_step_of_40_is_found_on_both_sides_in_every_row_and_nowhere_else():
    maps = detect_edges(step_image(40.0), CFG)
    expected = np.zeros((32, 32), bool)
    expected[:, 15:17] = True
    np.testing.assert_array_equal(maps.step, expected)
    assert not maps.roof.any()
    assert set(np.unique(maps.codes)) == {0, 1}


def test_step_below_threshold_is_not_a_step_edge():
    assert not detect_edges(step_image(10.0), CFG).step.any()  # AR = 10 * 0.30 = 3 < 6


def test_symmetric_roof_is_found_at_its_ridge_without_noise():
    maps = detect_edges(roof_image(), CFG)
    cols = np.unique(np.nonzero(maps.roof)[1])
    assert cols.tolist() == [32]
    assert maps.roof[:, 32].all()


def test_roof_with_noise_sigma_1_is_within_one_pixel_in_90_percent_of_rows():
    hits = []
    for seed in range(3):
        roof = detect_edges(roof_image(noise=1.0, seed=seed), CFG).roof
        hits += [roof[r, 31:34].any() for r in range(8, 56)]
    assert np.mean(hits) >= 0.9


def test_tilted_plane_beside_step_has_no_roof_edge_in_symmetric_mode():
    z = np.tile(np.arange(64.0), (64, 1))  # slope 1 per pixel
    z[:, 32:] += 30.0
    maps = detect_edges(z, CFG)
    assert np.unique(np.nonzero(maps.step)[1]).tolist() == [31, 32]
    assert not maps.roof.any()


def test_one_sided_truncation_shows_the_ramp_bias_beside_a_step():
    z = np.tile(2.0 * np.arange(64.0), (64, 1))  # slope 2 per pixel
    z[:, 32:] += 40.0
    one = load_config(overrides={"roof": {"truncation": "one-sided"}})
    sym_ar = absolute_residual(z, detect_edges(z, CFG).step, gaussian_taps(4, 17), (0, 1))
    one_ar = absolute_residual(z, detect_edges(z, one).step, gaussian_taps(4, 17), (0, 1),
                               truncation="one-sided")
    assert np.abs(sym_ar[:, 8:56]).max() < 1e-9
    # one-sided: slope 2 x centroid shift (about 3 px) next to the step
    assert one_ar[32, 30] > 4.0 and one_ar[32, 33] > 4.0
    roof = detect_edges(z, one).roof
    assert roof[16:48, 28:31].any()  # false roof edges along the step (the bias SPEC warns of)


def test_invalid_pixels_never_become_edges_and_never_enter_a_mask():
    z = step_image(40.0, size=48, col=24)
    z[10:20, 5:40] = np.nan
    maps = detect_edges(z, CFG)
    assert not (maps.codes[np.isnan(z)]).any()
    # a NaN hole in a flat area does not create edges around it
    flat = np.full((48, 48), 50.0)
    flat[20:28, 20:28] = np.nan
    assert not detect_edges(flat, CFG).codes.any()


def test_ar_is_zero_on_any_planar_ramp_in_every_direction():
    yy, xx = np.mgrid[0:40, 0:40]
    z = 3.0 + 1.7 * xx - 0.9 * yy
    excluded = np.zeros(z.shape, bool)
    for d in DIRECTIONS:
        assert np.abs(absolute_residual(z, excluded, gaussian_taps(4, 17), d)).max() < 1e-9


def test_ar_2d_is_zero_on_a_plane_and_nan_on_invalid():
    yy, xx = np.mgrid[0:20, 0:20]
    z = 2.0 * xx + 1.0 * yy
    ar = ar_2d(z)
    assert np.abs(ar[3:-3, 3:-3]).max() < 1e-9
    z[5, 5] = np.nan
    assert np.isnan(ar_2d(z)[5, 5])
