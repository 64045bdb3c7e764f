"""Helpers of the holdsite search (Sec. VII): medians, dilations, per-region reductions.

Constructed inputs with known answers; each fast helper is checked against
the direct computation it stands for.
"""

import math

import numpy as np
import pytest
from scipy import ndimage

from rangeseg_cli.cell.workspace import Workspace
from rangeseg_cli.models import Neighbor, Surface
from rangeseg_cli.stages.holdsite import (
    HIDING_WIDTH,
    fft_correlate,
    find_objects,
    footprint,
    middle_value,
    on_fingers_only,
    outer_invalid,
    pixel_sums,
    region_lift,
    same_neighbours,
    segment_dilation,
    square_dilation,
    sums_at,
    widest_discs,
    window_flat_rms,
)


@pytest.mark.parametrize("values, expected", [
    ([3.0], 3.0), ([5.0, 1.0], 3.0), ([4.0, 1.0, 9.0], 4.0), ([7.0, 1.0, 3.0, 2.0], 2.5)])
def test_middle_value_is_the_median(values, expected):
    assert middle_value(np.array(values)) == expected


def test_middle_value_of_nothing_is_minus_infinity():
    assert middle_value(np.zeros(0)) == -math.inf


def test_middle_value_equals_the_sorted_middle_elements():
    rng = np.random.default_rng(0)
    for size in range(1, 40):
        v = rng.normal(size=size)
        s = np.sort(v)
        assert middle_value(v) == 0.5 * (s[(size - 1) // 2] + s[size // 2])


def test_region_lift_is_each_labels_median_height_above_the_support():
    labels = np.array([[1, 1, 2, 0],
                       [1, 3, 2, 2],
                       [3, 3, 3, 0]])
    height = np.array([[1.0, 2.0, 10.0, 50.0],
                       [3.0, np.nan, 30.0, 20.0],
                       [5.0, 7.0, 6.0, 50.0]])
    space = Workspace(np.ones(labels.shape, bool), height, None, 1.0)
    lift = region_lift(labels, space, np.zeros(labels.shape), 4)
    assert lift.tolist() == [-math.inf, 2.0, 20.0, 6.0, -math.inf]


def test_region_lift_without_a_support_takes_the_heights():
    labels = np.array([[1, 1], [2, 2]])
    z = np.array([[4.0, 6.0], [np.nan, np.nan]])
    lift = region_lift(labels, Workspace(np.ones((2, 2), bool), None, None, 1.0), z, 2)
    assert lift.tolist() == [-math.inf, 5.0, -math.inf]


@pytest.mark.parametrize("size", [1, 3, 7, 13])
def test_square_dilation_is_binary_dilation_by_a_square(size):
    mask = np.random.default_rng(size).random((40, 50)) < 0.02
    mask[0, 0] = mask[-1, 20] = True
    want = ndimage.binary_dilation(mask, structure=np.ones((size, size), dtype=bool))
    got = square_dilation(mask, size)
    assert got.dtype == bool and np.array_equal(got, want)


def test_same_neighbours_marks_the_pixels_away_from_other_values():
    owner = np.array([[1, 1, 1, 2],
                      [1, 1, 1, 2],
                      [1, 1, 1, 2],
                      [3, 3, 1, 2]])
    assert same_neighbours(owner).astype(int).tolist() == [[1, 1, 0, 0],
                                                           [1, 1, 0, 0],
                                                           [0, 0, 0, 0],
                                                           [0, 0, 0, 0]]


def test_widest_disc_of_each_object_and_none_for_a_missing_one():
    owner = np.zeros((20, 30), dtype=np.int64)
    owner[2:17, 2:17] = 1  # 15 x 15: its centre 7 px from its outermost (border) pixels
    owner[2:7, 20:28] = 2  # 5 rows, the last a border with object 3 too: 2 px
    owner[7:9, 20:28] = 3  # 2 rows, both borders: no interior
    wide = widest_discs(owner, [1, 2, 3, 4])
    assert wide == {1: 7.0, 2: 2.0, 3: 0.0, 4: 0.0}


def test_pixel_sums_and_sums_at_are_the_correlation_at_those_pixels():
    rng = np.random.default_rng(4)
    a = rng.normal(0.0, 50.0, (30, 40))
    kernel = rng.normal(size=(5, 7))
    kernel[2, 3] = 0.0  # a zero weight is left out, as scipy leaves it out
    want = ndimage.correlate(a, kernel, mode="constant", cval=0.0)
    rows, cols = np.array([0, 3, 29, 15]), np.array([0, 39, 20, 17])
    assert pixel_sums(a, kernel, rows, cols).tobytes() == want[rows, cols].tobytes()
    for share in (0.005, 0.5):  # few pixels one by one, many by their box
        at = rng.random(a.shape) < share
        got = sums_at(a, kernel, at)
        assert got[at].tobytes() == want[at].tobytes()


def test_window_flat_rms_at_some_pixels_is_the_same_there_and_nan_elsewhere():
    rng = np.random.default_rng(5)
    z = 300.0 + rng.normal(0.0, 1.5, (25, 35))
    z[4, 6] = np.nan
    at = rng.random(z.shape) < 0.3
    at[4, 5] = True  # a window with the invalid pixel in it: NaN
    for fp in (np.ones((7, 7), dtype=bool), footprint((3, 7), 30.0)):
        every, some = window_flat_rms(z, fp), window_flat_rms(z, fp, at=at)
        assert some[at].tobytes() == every[at].tobytes() and np.isnan(some[~at]).all()
        assert np.isnan(some[4, 5])


def test_a_curved_sites_pose_is_its_local_pose_also_when_its_tilt_was_tested():
    from rangeseg_cli import load_config, run_pipeline
    from rangeseg_cli.stages.holdsite import local_poses, local_reach

    v, u = np.indices((64, 80), dtype=np.float64)
    z = np.full((64, 80), 20.0)
    dome = 90.0 - 0.02 * ((u - 40) ** 2 + (v - 32) ** 2)
    inside = (np.abs(u - 40) < 24) & (np.abs(v - 32) < 20)
    z[inside] = dome[inside]
    z += np.random.default_rng(7).normal(0.0, 0.2, z.shape)
    for tilt in (90.0, 30.0):  # without and with the tilt test (a pose per window tested)
        config = load_config(overrides={"input": {"units_per_pixel": 1.0},
                                        "holdsite": {"max_tilt": tilt, "max_candidates": 3}})
        result = run_pipeline(z, config)
        surfaces = {s.id: s for s in result.surfaces}
        sites = [result.holdsite.holdsite, *result.holdsite.candidates]
        curved = [site for site in sites if site.surface_type == "curved"]
        assert curved
        for site in curved:
            height, gx, gy, ok = local_poses(
                result.heights, result.labels, surfaces[site.surface], np.array([site.row]),
                np.array([site.col]), local_reach(site.size))
            assert ok[0] and site.elevation == float(height[0])
            norm = math.sqrt(gx[0] ** 2 + gy[0] ** 2 + 1.0)
            assert site.normal[2] == pytest.approx(1.0 / norm, rel=1e-12)


@pytest.mark.parametrize("size", [1, 3, 5, 7, 11, 15])
def test_segment_dilation_is_binary_dilation_by_a_segment(size):
    mask = np.random.default_rng(size).random((9, 31)) < 0.05
    mask[4, 0] = mask[2, -1] = True
    for axis, shape in ((1, (1, size)), (0, (size, 1))):
        want = ndimage.binary_dilation(mask, structure=np.ones(shape, dtype=bool))
        assert np.array_equal(segment_dilation(mask, size, axis), want)


def test_outer_invalid_is_the_invalid_areas_joined_to_the_frame():
    valid = np.ones((8, 10), dtype=bool)
    assert outer_invalid(valid) is None
    valid[3:5, 4:6] = False  # a hole inside: not joined
    assert outer_invalid(valid) is None
    valid[0, 0] = valid[1, 1] = False  # diagonal: 8-connected to the frame
    valid[7, 9] = False
    got = outer_invalid(valid)
    assert got is not None
    assert sorted(zip(*np.nonzero(got), strict=True)) == [(0, 0), (1, 1), (7, 9)]


def test_outer_invalid_of_a_width_leaves_out_the_cracks_that_join_the_frame():
    valid = np.ones((20, 24), dtype=bool)
    valid[:, :4] = False  # a margin of no reading along the left of the frame
    valid[10, 4:15] = False  # a 1-px crack from it into the view
    valid[14:16, 16:] = False  # a 2-px crack from the right frame
    valid[5:9, 10:14] = False  # a hole inside
    assert outer_invalid(valid).sum() == 20 * 4 + 11 + 2 * 8  # width 1: all joined areas
    got = outer_invalid(valid, HIDING_WIDTH)
    assert got is not None
    want = np.zeros_like(valid)
    want[:, :4] = True
    assert np.array_equal(got, want)
    valid[:, :4] = True  # only cracks reach the frame
    assert outer_invalid(valid, HIDING_WIDTH) is None
    valid[2:7, 17:22] = False  # a wide area joined to the frame by the 1-px crack alone
    valid[7:10, 19] = False
    valid[0:2, 19] = False
    assert outer_invalid(valid).any()
    assert outer_invalid(valid, HIDING_WIDTH) is None
    valid[0:2, 18:21] = False  # a 3-px channel: it and the area count
    got = outer_invalid(valid, HIDING_WIDTH)
    assert got is not None and got[4, 19] and got[0, 19] and not got[10, 8]


def _surface(sid, col, *neighbors):
    return Surface(id=sid, pixels=100, bbox=(0, col, 9, col + 9), centroid=(4.5, col + 4.5),
                   mean_height=50.0, coefficients=(50.0, 0, 0, 0, 0, 0), rms_error=0.1,
                   type="planar", shape="flat",
                   neighbors=tuple(Neighbor(id=i, edge=e) for i, e in neighbors))


@pytest.mark.parametrize("concave_parts", [False, True])
def test_a_concave_crease_parts_two_objects_beyond_the_paper(concave_parts):
    # A box's top (1) meets its side (2) at a convex crease and a tote wall (3), which
    # rises to the frame, at a concave one: an item leaning on the wall is not the wall.
    surfaces = {1: _surface(1, 10, (2, "roof-convex"), (3, "roof-concave")),
                2: _surface(2, 0, (1, "roof-convex")),
                3: _surface(3, 20, (1, "roof-concave"))}
    gaps = {(1, 2): 0.5, (1, 3): -0.5}
    object_of, objects = find_objects(surfaces, set(), gaps, 6.0, {3},
                                      concave_parts=concave_parts)
    assert object_of[1] == object_of[2]
    box = next(o for o in objects if o.id == object_of[1])
    assert (object_of[3] != object_of[1]) == concave_parts
    assert box.touches_border != concave_parts  # the paper: one object, at the border


def test_local_poses_of_sites_in_shared_and_separate_columns_are_the_direct_fits():
    from rangeseg_cli.models import Surface
    from rangeseg_cli.stages.holdsite import local_poses

    v, u = np.indices((40, 50), dtype=np.float64)
    z = 50.0 + 0.3 * u - 0.2 * v + 0.01 * u * v
    labels = np.ones(z.shape, dtype=np.int32)
    s = Surface(id=1, pixels=z.size, bbox=(0, 0, 39, 49), centroid=(19.5, 24.5),
                mean_height=float(z.mean()), coefficients=(0.0,) * 6, rms_error=0.0,
                type="curved", shape="saddle-ridge")
    rows, cols = np.array([10, 20, 30, 20]), np.array([15, 15, 30, 40])
    together = local_poses(z, labels, s, rows, cols, 7)
    for k in range(rows.size):  # one site at a time: the same bits
        alone = local_poses(z, labels, s, rows[k:k + 1], cols[k:k + 1], 7)
        assert all(a[0] == t[k] for a, t in zip(alone, together, strict=True))
    height, gx, gy, ok = together
    assert ok.all()
    np.testing.assert_allclose(height, z[rows, cols], atol=1e-9)
    np.testing.assert_allclose(gx, 0.3 + 0.01 * rows, atol=1e-9)
    np.testing.assert_allclose(gy, -0.2 + 0.01 * cols, atol=1e-9)


@pytest.mark.parametrize("shape, kernel", [((40, 57), (9, 11)), ((30, 20), (25, 25)),
                                           ((7, 9), (13, 5))])
def test_fft_correlate_is_the_correlation_with_zeros_outside(shape, kernel):
    from scipy.signal import fftconvolve

    rng = np.random.default_rng(1)
    a, k = rng.normal(size=shape), rng.normal(size=kernel)
    want = ndimage.correlate(a, k, mode="constant", cval=0.0)
    got = fft_correlate(a, k)
    assert np.allclose(got, want, rtol=0, atol=1e-10)
    assert np.array_equal(got, fftconvolve(a, k[::-1, ::-1], mode="same"))  # the same bits


def test_a_camera_run_with_a_large_footprint_does_not_import_scipy_signal():
    # scipy.signal costs about 0.5 s to import: a one-frame run must not pay it.
    import subprocess
    import sys

    code = (
        "import sys, numpy as np\n"
        "from rangeseg_cli import load_config, run_pipeline\n"
        "z = np.full((120, 160), 600.0); z[30:90, 40:120] = 520.0\n"
        "over = {'input': {'intrinsics': [200.0, 200.0, 79.5, 59.5]},\n"
        "        'holdsite': {'footprint_mm': [40.0, 20.0]}}\n"
        "site = run_pipeline(z, load_config(preset='mm-depth', overrides=over)).holdsite\n"
        "assert site.holdsite is not None and site.holdsite.size[0] * site.holdsite.size[1] > 64\n"
        "assert 'scipy.signal' not in sys.modules\n")
    subprocess.run([sys.executable, "-c", code], check=True)


ARM_AND_FINGERS = {1: (45.0, 48.0), 2: (40.0, 42.0), 3: (40.0, 42.0)}


@pytest.mark.parametrize("spans, touching, narrow, hover, expected", [
    # the arm (top 48) rests on its two fingers just below it, narrow and hanging in the air
    (ARM_AND_FINGERS, {(1, 2), (1, 3)}, {2, 3}, {2, 3}, {1}),
    # ... or on a finger that rests on a hanging one (and so does that finger)
    ({1: (45.0, 48.0), 2: (40.0, 42.0), 3: (38.0, 39.5)}, {(1, 2), (2, 3)}, {2, 3}, {3},
     {1, 2}),
    # an item on narrow pieces that rest on something (its own face's fragments)
    (ARM_AND_FINGERS, {(1, 2), (1, 3)}, {2, 3}, set(), set()),
    # a box lying on a wide box is an item
    (ARM_AND_FINGERS, {(1, 2)}, {3}, {2, 3}, set()),
    # on a finger and on a wide object: the wide one may hold it up
    (ARM_AND_FINGERS, {(1, 2), (1, 3)}, {2}, {2, 3}, set()),
    # low enough to stand on the support (0) whatever it touches
    ({1: (3.0, 48.0), 2: (40.0, 42.0)}, {(1, 2)}, {2}, {2}, set()),
    # far above the finger: it does not rest on it, it hovers (another rule's case)
    ({1: (45.0, 48.0), 2: (10.0, 12.0)}, {(1, 2)}, {2}, {2}, set()),
    # touching nothing lower
    ({1: (45.0, 48.0), 2: (50.0, 52.0)}, {(1, 2)}, {2}, {2}, set()),
])
def test_on_fingers_only_finds_what_rests_on_hanging_narrow_objects_alone(
        spans, touching, narrow, hover, expected):
    both_ways = touching | {(b, a) for a, b in touching}
    assert on_fingers_only(spans, both_ways, 1.0, narrow, hover) == expected
    assert on_fingers_only(spans, touching, 1.0, narrow, hover) == expected  # one way round
    assert on_fingers_only(spans, both_ways, 1.0, narrow | {99}, hover) == expected
