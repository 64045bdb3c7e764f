"""Helpers of the workspace: 3x3 medians, the support's hull and its extent in the image.

Constructed inputs with known answers; each fast helper is checked against
the direct computation it stands for.
"""

import importlib.util
import warnings

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from rangeseg_cli.cell.workspace import (
    extreme_pixels,
    hull_extent,
    inside_hull,
    median9,
    median_of_valid,
    plane_shares,
    prepared_background,
    same_bits,
    support_hull,
)

requires_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                                    reason="numba is not installed")

def windows(z):
    """(H, W, 9) 3x3 neighbourhoods of ``z`` padded with NaN."""
    p = np.pad(z, 1, constant_values=np.nan)
    h, w = z.shape
    return np.stack([p[i:i + h, j:j + w] for i in range(3) for j in range(3)], axis=-1)


def test_median9_is_the_fifth_smallest_of_nine_valid_values():
    z = np.random.default_rng(0).normal(size=(20, 30))
    got = median9(np.pad(z, 1, constant_values=np.nan))
    want = np.median(windows(z), axis=-1)
    inner = (slice(1, -1), slice(1, -1))
    assert np.array_equal(got[inner], want[inner])
    assert np.isnan(got[0]).all() and np.isnan(got[:, -1]).all()  # the NaN frame counts


def test_median9_is_nan_wherever_one_of_the_nine_is():
    z = np.arange(49, dtype=np.float64).reshape(7, 7)
    z[3, 3] = np.nan
    got = median9(np.pad(z, 1, constant_values=np.nan))
    assert np.isnan(got[2:5, 2:5]).all()
    assert got[5, 5] == 40.0  # 32..34, 39..41, 46..48


def test_median_of_valid_takes_the_middle_of_the_valid_values():
    z = np.array([[1.0, np.nan, 3.0],
                  [4.0, 8.0, np.nan],
                  [np.nan, np.nan, np.nan]])
    padded = np.pad(z, 1, constant_values=np.nan)
    got = median_of_valid(padded, np.array([0, 1, 2]), np.array([0, 1, 2]))
    assert got[0] == 4.0  # 1, 4, 8: the middle one
    assert got[1] == 3.5  # 1, 3, 4, 8: the mean of the middle two
    assert got[2] == 8.0  # 8 alone


def test_median_of_valid_is_nan_without_a_valid_value():
    padded = np.full((4, 4), np.nan)
    assert np.isnan(median_of_valid(padded, np.array([0]), np.array([1]))).all()


def test_extreme_pixels_are_the_ends_of_each_row_and_column():
    mask = np.zeros((5, 6), dtype=bool)
    mask[1, 1:5] = True
    mask[2, 2] = True
    mask[3, 0:3] = True
    rows, cols = extreme_pixels(mask)
    assert list(zip(rows.tolist(), cols.tolist(), strict=True)) == [
        (1, 1), (1, 2), (1, 3), (1, 4), (2, 2), (3, 0), (3, 1), (3, 2)]


def test_the_hull_of_the_extreme_pixels_is_the_hull_of_all_pixels():
    rng = np.random.default_rng(1)
    for _ in range(20):
        mask = rng.random((30, 40)) < 0.2
        mask[rng.integers(0, 30), :] = True
        every = np.column_stack(np.nonzero(mask)[::-1]).astype(np.float64)
        ends = np.column_stack(extreme_pixels(mask)[::-1]).astype(np.float64)
        assert np.asarray(ConvexHull(ends).equations).tobytes() == \
            np.asarray(ConvexHull(every).equations).tobytes()


def test_support_hull_of_a_square_floor_and_none_of_a_line():
    on = np.zeros((20, 20), dtype=bool)
    on[4:12, 5:15] = True
    hull = support_hull(on)
    assert hull is not None and len(hull) == 4
    within_a_pixel = np.zeros_like(on)
    within_a_pixel[3:13, 4:16] = True  # a position within a pixel outside counts as in
    assert np.array_equal(hull_extent(hull, on.shape), within_a_pixel)
    line = np.zeros((20, 20), dtype=bool)
    line[3, 2:18] = True
    assert support_hull(line) is None


@pytest.mark.parametrize("inset", [0.0, 0.5, 2.25])
def test_hull_extent_is_inside_hull_at_every_pixel(inset):
    rng = np.random.default_rng(2)
    for k in range(30):
        pts = rng.uniform(-20, 90, (rng.integers(3, 12), 2)) if k % 2 else \
            rng.integers(0, 60, (rng.integers(3, 12), 2)).astype(np.float64)
        hull = np.asarray(ConvexHull(pts).equations)
        shape = (50, 70)
        assert np.array_equal(hull_extent(hull, shape, inset),
                              inside_hull(hull, *np.indices(shape), inset))


def test_hull_extent_of_level_and_nearly_level_edges_and_of_no_hull():
    shape = (30, 40)
    for a in (0.0, 1e-12, 1e-7, -3e-8):
        hull = np.array([[a, 1.0, -20.0], [-a, -1.0, 3.0], [1.0, a, -30.0], [-1.0, 0.0, 2.0]])
        assert np.array_equal(hull_extent(hull, shape), inside_hull(hull, *np.indices(shape)))
    assert hull_extent(None, shape).all()


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=requires_numba)])
def test_plane_shares_are_the_means_of_the_two_tests(backend):
    rng = np.random.default_rng(3)
    products = rng.normal(0.0, 3.0, (1000, 17))
    offsets = rng.normal(0.0, 1.0, 17)
    products[5, 2], products[6, 3] = -2.0 - offsets[2], 2.0 - offsets[3]  # at the limits
    dist = products + offsets
    on, below = plane_shares(products, offsets, 2.0, backend=backend)
    assert on.tobytes() == (np.abs(dist) <= 2.0).mean(axis=0).tobytes()
    assert below.tobytes() == (dist < -2.0).mean(axis=0).tobytes()


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=requires_numba)])
def test_plane_shares_of_points_on_in_front_and_behind(backend):
    products = np.array([[0.0], [0.5], [-3.0], [3.0], [1.0], [-1.0], [-1.0000001]])
    on, below = plane_shares(products, np.array([0.0]), 1.0, backend=backend)
    assert on.tolist() == [4 / 7] and below.tolist() == [2 / 7]


def test_median9_by_row_blocks_of_a_tall_image_equals_the_direct_median():
    z = np.random.default_rng(6).normal(size=(75, 9))  # more rows than MEDIAN_ROWS
    want = np.median(windows(z), axis=-1)
    got = median9(np.pad(z, 1, constant_values=np.nan))
    assert np.array_equal(got[1:-1, 1:-1], want[1:-1, 1:-1])


def test_same_bits_tells_nan_and_signed_zeros_apart_only_by_their_bits():
    a = np.array([1.0, np.nan, 0.0])
    assert same_bits(a, a.copy())
    assert not same_bits(a, np.array([1.0, np.nan, -0.0]))
    assert not same_bits(a, a.astype(np.float32)) and not same_bits(a, a[:2])


def test_prepared_background_is_the_median_filled_and_its_points_kept_for_one_frame():
    from rangeseg_cli.cell.workspace import BACKGROUND_REACH, matches_background, points
    from rangeseg_cli.config import InputConfig

    rng = np.random.default_rng(8)
    bg = rng.normal(20.0, 0.5, (30, 40))
    bg[5:9, 5:9] = np.nan
    camera = InputConfig()
    smooth, filled, pts = prepared_background(bg, camera)
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN windows
        want = np.where(np.isfinite(bg), np.nanmedian(windows(bg), axis=-1), np.nan)
    np.testing.assert_allclose(smooth, want, rtol=0, atol=1e-12)
    assert np.isfinite(filled[5:9, 5:9]).all() and BACKGROUND_REACH >= 4
    assert np.array_equal(pts, points(smooth, camera), equal_nan=True)
    scene = bg + 5.0
    assert matches_background(scene, smooth, 1.0, filled=filled).tobytes() == \
        matches_background(scene, smooth, 1.0).tobytes()
    again = prepared_background(bg.copy(), camera)
    assert all(x is y for x, y in zip(again, (smooth, filled, pts), strict=True))
    other = prepared_background(bg + 1.0, camera)
    assert other[0] is not smooth and not smooth.flags.writeable


def test_inside_hull_of_many_positions_in_chunks_is_the_test_of_every_half_plane():
    rng = np.random.default_rng(9)
    hull = np.asarray(ConvexHull(rng.uniform(0.0, 50.0, (12, 2))).equations)
    rows, cols = rng.uniform(-5.0, 55.0, (2, 20000))  # more than HULL_CHUNK
    rows[::97] = np.nan  # unknown feet count as in
    want = np.ones(rows.shape, dtype=bool)
    for a, b, c in hull:
        with np.errstate(invalid="ignore"):
            want &= ~(a * cols + b * rows + c > 1.0 - 1.5)
    assert np.array_equal(inside_hull(hull, rows, cols, 1.5), want)
    assert inside_hull(hull, rows[:0], cols[:0]).shape == (0,)
