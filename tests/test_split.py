"""Issue 9: the quality-of-fit split of Sec. VIII and the noise estimate (rangeseg_cli.refine.split)."""

from __future__ import annotations

import importlib.util
import itertools
from collections.abc import Iterator
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy import ndimage

from conftest import passes_without, small_frustum
from rangeseg_cli.config import Config, load_config
from rangeseg_cli.errors import ConfigError
from rangeseg_cli.pipeline import run_pipeline, stage_edges, stage_grow
from rangeseg_cli.refine import regions
from rangeseg_cli.refine import split as split_module
from rangeseg_cli.refine.planes import local_planes, writeable_weights
from rangeseg_cli.refine.split import (
    estimate_noise,
    failing_components,
    merge_back,
    split_regions,
)
from rangeseg_cli.stages import noise as noise_module
from rangeseg_cli.stages.grow import fit_quadrics, grow_regions
from rangeseg_cli.synth.evaluate import hoover_compare

N = 128
SPLIT = load_config()  # the split is on by default
PAPER = load_config(preset="paper")  # the paper's algorithm alone


def _grid() -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:N, 0:N].astype(np.float64)
    return y, x


def _finish(z: np.ndarray, sigma: float, seed: int) -> np.ndarray:
    """Add Gaussian noise and quantise to 8 bits, as the ERIM images are."""
    if sigma:
        z = z + np.random.default_rng(seed).normal(0.0, sigma, z.shape)
    return np.clip(np.round(z), 0.0, 255.0)


def frustum_scene(sigma: float = 0.0, seed: int = 0, slope: float = 1.5
                  ) -> tuple[np.ndarray, np.ndarray]:
    """A square frustum on a table: sides of ``slope`` (roof AR ~2.4 < 4 at 1.5), top 30 up.

    Returns the image and the true faces: 1 table, 2..5 sides, 6 top.
    """
    y, x = _grid()
    dx, dy = x - 63.5, y - 63.5
    height = np.clip(slope * (44.0 - np.maximum(np.abs(dx), np.abs(dy))), 0.0, 30.0)
    truth = np.ones((N, N), np.int32)
    side = (height > 0) & (height < 30.0)
    across = np.abs(dx) >= np.abs(dy)
    truth[side & across & (dx > 0)] = 2
    truth[side & across & (dx < 0)] = 3
    truth[side & ~across & (dy > 0)] = 4
    truth[side & ~across & (dy < 0)] = 5
    truth[height >= 30.0] = 6
    return _finish(20.0 + height, sigma, seed), truth


def crease_scene(sigma: float = 0.0, seed: int = 0, change: float = 1.0
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Two nearly coplanar faces whose slope changes by ``change`` units per pixel at x = 63.5."""
    y, x = _grid()
    z = 100.0 + 0.1 * y - 0.5 * change * np.abs(x - 63.5)
    return _finish(z, sigma, seed), np.where(x < 63.5, 1, 2).astype(np.int32)


def cylinder_scene(sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    """A cylinder of radius 40 lying on a table at 20, axis along the columns."""
    y, x = _grid()
    z = np.full((N, N), 20.0)
    inside = (np.abs(y - 64.0) < 40.0) & (x >= 16) & (x < 112)
    z[inside] = 60.0 + np.sqrt(1600.0 - (y[inside] - 64.0) ** 2)
    return _finish(z, sigma, seed)


def sphere_scene(sigma: float = 0.0, seed: int = 0) -> np.ndarray:
    """A sphere of radius 40 on a table at 20."""
    y, x = _grid()
    r2 = (x - 63.5) ** 2 + (y - 63.5) ** 2
    z = np.where(r2 < 1600.0, 20.0 + np.sqrt(np.maximum(1600.0 - r2, 0.0)), 20.0)
    return _finish(z, sigma, seed)


def tilted_plane(sigma: float, seed: int) -> np.ndarray:
    y, x = _grid()
    return _finish(40.0 + 0.7 * x - 0.4 * y, sigma, seed)


def large_regions(labels: np.ndarray, min_pixels: int = 50) -> np.ndarray:
    counts = np.bincount(labels.ravel())
    ids = np.flatnonzero(counts >= min_pixels)
    return ids[ids > 0]


def correct(truth: np.ndarray, labels: np.ndarray) -> int:
    """Correct detections of Hoover et al. (1996) at tolerance 0.8."""
    return hoover_compare(truth, labels).counts()["correct"]


# ------------------------------------------------------------------ noise estimate


@pytest.mark.parametrize(("sigma", "rel"), [(0.5, 0.1), (1.0, 0.04), (2.0, 0.04), (4.0, 0.04)])
def test_noise_estimate_recovers_the_sigma_of_a_noisy_plane(sigma: float, rel: float) -> None:
    # The noise plus 8-bit quantisation; at low noise the rounding pattern reads high.
    expected = np.sqrt(sigma**2 + 1.0 / 12.0)
    for seed in (0, 1):
        assert estimate_noise(tilted_plane(sigma, seed)) == pytest.approx(expected, rel=rel)


def test_noise_estimate_is_not_raised_by_step_edges() -> None:
    plane = tilted_plane(1.0, 3)
    boxes = plane.copy()
    boxes[10:50, 10:50] += 80.0
    boxes[70:120, 60:90] += 120.0  # long high step contours on 4 % of the pixels
    assert estimate_noise(boxes) == pytest.approx(estimate_noise(plane), rel=0.05)


def test_noise_estimate_of_noise_free_constant_data_is_zero() -> None:
    assert estimate_noise(np.full((N, N), 37.0)) == 0.0


def test_noise_estimate_leaves_out_invalid_pixels() -> None:
    z = tilted_plane(2.0, 4)
    holed = z.copy()
    holed[30:60, :] = np.nan
    holed[:, 100:] = np.nan
    assert np.isfinite(estimate_noise(holed))
    assert estimate_noise(holed) == pytest.approx(estimate_noise(z), rel=0.08)


def test_pipeline_result_carries_the_noise_estimate() -> None:
    result = run_pipeline(tilted_plane(2.0, 5), stages=1)
    assert result.noise_sigma == estimate_noise(result.heights)
    assert result.noise_sigma == pytest.approx(2.02, rel=0.08)


# ------------------------------------------------------------------ the fit test


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_noisy_plane_passes_the_fit_test(sigma: float) -> None:
    for seed in (0, 1, 2):
        z = tilted_plane(sigma, seed)
        comps = np.ones((N, N), np.int32)
        assert failing_components(z, comps, estimate_noise(z), SPLIT.split,
                                  SPLIT.grow).size == 0


def test_one_component_over_a_crease_fails_the_fit_test() -> None:
    z, _ = crease_scene()
    failing = failing_components(z, np.ones((N, N), np.int32), estimate_noise(z),
                                 SPLIT.split, SPLIT.grow)
    np.testing.assert_array_equal(failing, [1])


# ------------------------------------------------------------------ splitting


@pytest.mark.parametrize("sigma", [0.0, 0.5])
def test_frustum_with_shallow_sides_gives_its_five_faces(sigma: float) -> None:
    z, truth = frustum_scene(sigma, seed=1)
    assert correct(truth, run_pipeline(z, PAPER, stages=3).labels) == 0  # one blob
    labels = run_pipeline(z, SPLIT, stages=3).labels
    assert correct(truth, labels) == 6  # the five faces and the table
    faces = [np.bincount(labels[truth == face]).argmax() for face in range(1, 7)]
    assert len(set(faces)) == 6 and 0 not in faces


@pytest.mark.parametrize("sigma", [0.0, 1.0])
def test_two_coplanar_ish_faces_at_a_one_unit_crease_are_split(sigma: float) -> None:
    z, truth = crease_scene(sigma, seed=2, change=1.0)
    assert len(large_regions(run_pipeline(z, PAPER, stages=3).labels)) == 1
    result = run_pipeline(z, SPLIT, stages=3)
    assert len(large_regions(result.labels)) == 2
    assert correct(truth, result.labels) == 2
    slopes = sorted(s.coefficients[1] for s in result.surfaces if s.pixels >= 50)
    np.testing.assert_allclose(slopes, [-0.5, 0.5], atol=0.02)


def sliver_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two planes at a crease (slopes 1 and 2.5 along x) and, along the bottom edge of
    the left one, a steep sliver of a third face two pixels wide: heights, left, sliver."""
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float64)
    z = np.where(xx < 40, 100 + xx, 140 + 2.5 * (xx - 40))
    sliver = (yy >= 58) & (xx < 30)
    return np.round(np.where(sliver, z + 6.0 * (yy - 57), z)), xx < 40, sliver


def test_a_sliver_of_a_third_face_does_not_hide_the_crease_between_two_others(
        monkeypatch) -> None:
    # The sliver's normals are the farthest from the mode: Otsu parts them from both
    # planes, and the sliver is too thin to be a part. The mode's class is divided again.
    z, left, sliver = sliver_scene()
    mask = np.ones(z.shape, bool)
    cfg = Config()

    def planes_apart(plane_cut: bool = False) -> bool:
        pieces = split_module.split_component(
            z, mask, noise=0.0, cfg=replace(cfg.split, plane_cut=plane_cut), grow=cfg.grow)
        a, b = (np.bincount(pieces[side & ~sliver]).argmax() for side in (left, ~left))
        return bool(a != b and a > 0 and b > 0)

    assert planes_apart()
    monkeypatch.setattr(split_module, "_split_mode_class", lambda *args, **kwargs: None)
    assert not planes_apart()  # without the second division it stays whole
    assert planes_apart(plane_cut=True)  # unless the plane cut divides it


def test_trim_leaves_out_a_sliver_that_a_piece_cannot_be_split_at() -> None:
    # One plane with a steep strip two pixels wide along its bottom edge: the strip
    # keeps the piece's error far above the fit test, and has no core of its own.
    yy, xx = np.mgrid[0:40, 0:50].astype(np.float64)
    sliver = yy >= 38
    z = np.round(100 + 0.5 * xx + np.where(sliver, 6.0 * (yy - 37), 0.0))
    pieces = np.ones(z.shape, np.int32)
    split_module._trim(z, pieces, 1, level=0.625)
    np.testing.assert_array_equal(pieces, np.where(sliver, 0, 1))  # the sliver, to regrow


def grazing_side_scene(yaw: float = 17.0, fold: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    """A plate with a block on it, both seen on their +y side at a grazing angle (part1's
    base, block and +y side, Fig. 10), 96 x 96, noise-free, 8-bit.

    The plate's top (50 + 0.2 x + 0.3 y) folds down by ``fold`` units per pixel from 8
    pixels in from its +y edge: a crease the edges miss, so the top's component holds two
    faces and is split (part1's base top shares one with the roof). The +y side is one
    plane falling 19 units per pixel across, ``yaw`` degrees off the rows, through the
    top's edge: 24 units deep below the plate (about 1.3 pixels wide, then a step to the
    table at 30) and, flush with it, 32 more below the block's top (about 3 pixels). The
    block ends in a side falling 14 per pixel (grazing too). Returns the image and the
    true faces: 1 table, 2 plate top, 3 the +y side, 4 block top, 5 block end, 6 the fold.
    """
    y, x = np.mgrid[0:96, 0:96].astype(np.float64)
    t = np.radians(yaw)
    u = (y - 56.25) * np.cos(t) - (x - 56.0) * np.sin(t)  # across the +y side, outwards
    v = (x - 56.0) * np.cos(t) + (y - 56.25) * np.sin(t)  # along it
    plane = 50.0 + 0.2 * x + 0.3 * y
    side = plane - 19.0 * u
    top = np.minimum(plane, plane - fold * (-u - 8.0))
    plate = (u >= -24.0) & (np.abs(v + 5.0) <= 55.0) & (side >= plane - 24.0)
    caps = np.stack([plane + 32.0, side, plane + 32.0 - 14.0 * (v + 20.0)])  # block top, +y, end
    block = plate & (caps.min(axis=0) > top)
    z = np.where(block, caps.min(axis=0), np.where(plate, np.minimum(top, side), 30.0))
    truth = np.ones(z.shape, np.int32)
    truth[plate] = np.select([side < top, u < -8.0], [3, 6], 2)[plate]
    truth[block] = np.array([4, 3, 5])[np.argmin(caps, axis=0)][block]
    return np.round(z), truth


@pytest.mark.parametrize("yaw", [16.0, 17.0])
@pytest.mark.parametrize("fold", [1.0, 1.4])
def test_trimming_finds_a_grazing_side_flush_with_a_blocks_side(tuning, yaw: float,
                                                                 fold: float) -> None:
    # The plate's side is a strip 1-2 pixels wide, seen at a grazing angle, flush with the
    # block's (one true face: part1's base +y & block +y). Without the trim, a few of its
    # pixels stay in the piece of the plate's top beside it, whose fit they spoil; the
    # top's region then holds pixels across the strip and cuts it, and the side's region
    # does not reach along it (a fifth of the side or more is elsewhere). The effect holds
    # for yaw 15-17 degrees and fold 0.8-1.6 (at yaw 14 or 18-20 the side is found either
    # way; at fold 0-0.3 neither): a change that moves that band fails here.
    image, truth = grazing_side_scene(yaw, fold)
    found = {}
    # the bridge (rangeseg_cli.refine.fill.bridge_gaps) finds it without the trim: off
    config = passes_without("bridge")
    for trim in (True, False):
        tuning(trim_pieces=trim)
        result = hoover_compare(truth, run_pipeline(image, config, stages=3).labels)
        found[trim] = {g for i in result.instances if i.kind == "correct" for g in i.gt}
    assert 3 in found[True] and 3 not in found[False]
    assert found[False] <= found[True]


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
@pytest.mark.parametrize("scene", [cylinder_scene, sphere_scene], ids=["cylinder", "sphere"])
def test_genuinely_curved_surface_is_not_split(scene, sigma: float) -> None:
    z = scene(sigma, seed=3)
    labels = run_pipeline(z, SPLIT, stages=3).labels
    assert len(large_regions(labels)) == 2  # the object and the table
    on_top = labels[64, 64]
    assert on_top > 0 and np.count_nonzero(labels == on_top) > 3000


@pytest.mark.parametrize("scene", [cylinder_scene, sphere_scene], ids=["cylinder", "sphere"])
def test_curved_surface_fails_the_fit_test_so_the_merge_back_keeps_it_whole(scene) -> None:
    # Noise-free, a quadric does not fit a circle's profile to the noise: the split is
    # tried, and it is merging the pieces back that keeps the surface whole.
    result = run_pipeline(scene(), PAPER, stages=2)
    noise = estimate_noise(result.heights)
    failing = failing_components(result.heights, result.components, noise, SPLIT.split,
                                 SPLIT.grow)
    assert result.components[64, 64] in failing


def test_merge_back_joins_two_halves_of_one_plane_and_keeps_a_crease() -> None:
    y, x = _grid()
    halves = np.where(x < 64, 1, 2).astype(np.int32)
    rules = {"level": 0.625, "floor": 1.58, "min_gain": 1.5, "min_crease": 10.0,
             "planar_tolerance": 0.1, "min_error": 0.25}
    plane = np.round(30.0 + 0.3 * x + 0.2 * y)
    assert merge_back(plane, halves, **rules).max() == 1
    z, _ = crease_scene(change=1.0)
    assert merge_back(z, halves, **rules).max() == 2


def test_merge_back_keeps_a_ramp_apart_whose_piece_holds_stray_floor_pixels() -> None:
    """A ramp rising from a floor, its piece with a column of the floor beyond its top.

    The stray column raises the ramp piece's own RMS error (2.7) above two
    thirds of the union's (2.8), so the RMS rule merges the two; the union's
    quadric leaves 6 squared units per pixel more than the pieces' own, over
    the 3.1 of ``excess`` = 8 x level^2: they stay apart. Two halves of one
    plane and a parabolic cylinder cut in two stay merged with the rule on.
    """
    rules = {"level": 0.625, "floor": 1.58, "min_gain": 1.5, "min_crease": 10.0,
             "planar_tolerance": 0.1, "min_error": 0.25}
    excess = 8.0 * 0.625**2
    y, x = np.mgrid[0:40, 0:40].astype(np.float64)
    ramp = (y >= 8) & (y < 32) & (x >= 12) & (x < 26)
    z = np.round(30.0 + 0.1 * y + np.where(ramp, x - 12.0, 0.0))
    pieces = np.where(ramp, 2, 1).astype(np.int32)
    pieces[8:32, 26] = 2  # floor pixels just past the ramp's top
    assert merge_back(z, pieces, **rules).max() == 1
    assert merge_back(z, pieces, **rules, excess=excess).max() == 2
    halves = np.where(x < 20, 1, 2).astype(np.int32)
    assert merge_back(np.round(30.0 + 0.3 * x + 0.2 * y), halves, **rules,
                      excess=excess).max() == 1
    cylinder = np.round(50.0 + 0.2 * y + 20.0 * (x / 40.0) ** 2)
    assert merge_back(cylinder, halves, **rules, excess=excess).max() == 1


def test_min_excess_is_off_by_default_and_reaches_merge_back(monkeypatch) -> None:
    seen = []
    real = split_module.merge_back

    def spy(*args, **kwargs):
        seen.append(kwargs["excess"])
        return real(*args, **kwargs)

    monkeypatch.setattr(split_module, "merge_back", spy)
    z, _ = crease_scene(change=1.0)
    mask = np.ones(z.shape, bool)
    for value in (0.0, 8.0):
        split_module.split_component(z, mask, noise=1.0, cfg=replace(SPLIT.split,
                                                                     min_excess=value),
                                     grow=SPLIT.grow)
    assert load_config().split.min_excess == 0.0
    assert seen[0] is None and seen[1] == pytest.approx(8.0 * 1.25**2)


def test_max_pieces_bounds_the_split(tuning) -> None:
    z, _ = frustum_scene()
    many = len(large_regions(run_pipeline(z, SPLIT, stages=3).labels))
    # the carving would give the two pieces' absorbed sides regions again, and the
    # leftovers the pixels dropped beyond max_pieces: off, to count the split's own pieces
    config = passes_without("carve", "leftovers")
    tuning(max_pieces=2)
    few = len(large_regions(run_pipeline(z, config, stages=3).labels))
    assert few == 2 < many == 6


# ------------------------------------------------------------------ exact shortcuts


def test_nearest_label_search_breaks_ties_as_the_feature_transform_does() -> None:
    from scipy import ndimage

    rng = np.random.default_rng(11)
    for trial in range(300):
        h, w = (int(v) for v in rng.integers(3, 40, size=2))
        parts = np.where(rng.random((h, w)) < rng.uniform(0.02, 0.4),
                         rng.integers(1, 5, (h, w)), 0).astype(np.int32)
        if trial % 10 == 0:
            parts[:] = 0
            parts[h // 2, w // 2] = 3  # one label far from most pixels: the slow path
        if not parts.any():
            continue
        rows, cols = np.nonzero(parts == 0)
        ir, ic = ndimage.distance_transform_edt(parts == 0, return_distances=False,
                                                return_indices=True)
        np.testing.assert_array_equal(split_module._nearest_labels(parts, rows, cols),
                                      parts[ir[rows, cols], ic[rows, cols]])


def test_local_planes_of_a_crop_equal_those_of_the_whole_array_bit_for_bit() -> None:
    rng = np.random.default_rng(12)
    z = rng.normal(50.0, 10.0, (90, 110))
    mask = np.zeros(z.shape, bool)
    mask[20:45, 30:70] = True
    mask[50:60, 10:20] = True
    rows = rng.integers(0, 90, 400)
    cols = rng.integers(0, 110, 400)
    height, _, _ = local_planes(z, mask, 4.0)
    cropped = split_module._plane_heights(z, mask, 4.0, rows, cols)
    np.testing.assert_array_equal(cropped, height[rows, cols])  # NaN where out of reach


def _block_parts(rng: np.random.Generator
                 ) -> Iterator[tuple[np.ndarray, np.ndarray, split_module._Frame]]:
    """200 random labels of 4x4 blocks (0-3, up to 29x29) with their masks and frames."""
    for _ in range(200):
        h, w = (int(v) for v in rng.integers(2, 30, size=2))
        coarse = rng.integers(0, 4, (h // 4 + 1, w // 4 + 1))
        parts = np.kron(coarse, np.ones((4, 4), int))[:h, :w].astype(np.int32)
        mask = parts > 0
        if mask.any():
            yield parts, mask, split_module._Frame.of(mask, SPLIT.split)


def test_core_from_window_extremes_equals_the_chessboard_depth_rule() -> None:
    for parts, _, frame in _block_parts(np.random.default_rng(13)):
        padded = np.pad(split_module._fill_nearest(parts, frame.solid), 1)
        uniform = (ndimage.minimum_filter(padded, size=3)
                   == ndimage.maximum_filter(padded, size=3))
        depth = ndimage.distance_transform_cdt(uniform, metric="chessboard")[1:-1, 1:-1]
        reference = np.where((depth >= frame.thickness) & frame.mask, parts, 0)
        np.testing.assert_array_equal(split_module._core(parts, frame), reference)


def test_core_bound_holds_every_core_and_counts_the_eroded_mask() -> None:
    for parts, mask, frame in _block_parts(np.random.default_rng(17)):
        bound = split_module.core_bound(frame)
        assert np.count_nonzero(split_module._core(parts, frame)) <= bound
        assert np.count_nonzero(split_module._core(mask.astype(np.int32), frame)) == bound


def test_core_bound_of_a_square_and_of_a_thin_strip() -> None:
    cfg = SPLIT.split
    t = int(np.ceil(cfg.normal_sigma))
    square = np.zeros((20, 20), bool)
    square[2:18, 2:18] = True
    assert split_module.core_bound(split_module._Frame.of(square, cfg)) == (16 - 2 * t) ** 2
    strip = np.zeros((9, 40), bool)
    strip[3:3 + 2 * t, :] = True  # thinner than a core's window
    assert split_module.core_bound(split_module._Frame.of(strip, cfg)) == 0


# ------------------------------------------------------------------ stage contract


def test_component_that_passes_leaves_the_grown_labels_untouched() -> None:
    z = tilted_plane(1.0, 6)
    z[40:80, 40:90] += 60.0  # a box: step edges only, every face planar
    result = run_pipeline(z, PAPER, stages=3)
    again = split_regions(result.heights, result.edges, result.components, result.labels,
                          SPLIT)
    assert again is result.labels


def test_grow_stage_with_split_is_a_pure_function_of_its_inputs() -> None:
    z, _ = frustum_scene(sigma=1.0, seed=7)
    result = run_pipeline(z, SPLIT, stages=3)
    edges, comps = result.edges.copy(), result.components.copy()
    labels, surfaces = stage_grow(result.heights, result.edges, result.components, SPLIT)
    np.testing.assert_array_equal(labels, result.labels)
    assert surfaces == result.surfaces
    np.testing.assert_array_equal(result.edges, edges)  # inputs untouched
    np.testing.assert_array_equal(result.components, comps)


def test_split_disabled_gives_the_papers_region_growing() -> None:
    z, _ = crease_scene(sigma=1.0, seed=8)
    result = run_pipeline(z, PAPER, stages=3)
    plain = grow_regions(result.heights, result.edges, result.components, PAPER.grow)
    np.testing.assert_array_equal(result.labels, plain)


def test_split_pieces_are_numbered_in_raster_order_and_never_cover_invalid_pixels() -> None:
    z, _ = crease_scene(sigma=1.0, seed=9)
    z[:, 20:24] = np.nan
    labels = run_pipeline(z, SPLIT, stages=3).labels
    assert np.all(labels[:, 20:24] == 0)
    ids = large_regions(labels)
    assert len(ids) >= 2
    firsts = [np.flatnonzero(labels.ravel() == i)[0] for i in np.unique(labels[labels > 0])]
    assert firsts == sorted(firsts)


# ------------------------------------------------------------------ config, thresholds


# the old [split] keys (max_pieces, min_gain, trim_pieces, ...): tests/test_config.py
@pytest.mark.parametrize(("values", "match"), [
    ({"refine": {"fit_factor": 0}}, r"\[refine\] fit_factor = 0"),
    ({"input": {"auto_thresholds": 1}}, r"\[input\] auto_thresholds = 1: expected true"),
])
def test_fit_factor_and_auto_threshold_keys_are_validated(values: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        load_config(overrides=values)


def test_split_is_on_by_default_and_off_in_the_paper_preset() -> None:
    assert "split" in Config().refine.passes and "split" not in PAPER.refine.passes
    assert "split" not in passes_without("split").refine.passes
    assert Config().input.auto_thresholds and not PAPER.input.auto_thresholds  # issue 32


# the thresholds that follow the noise and the lateral scale: tests/test_noise_thresholds.py


def test_auto_thresholds_drop_noise_edges_on_a_noisy_plane() -> None:
    z = tilted_plane(4.0, 10)  # above the paper's noise (issue 32: it follows from there)
    fixed = stage_edges(z, replace(SPLIT, input=replace(SPLIT.input,
                                                       auto_thresholds=False))).codes
    auto = stage_edges(z, SPLIT).codes
    assert np.count_nonzero(auto) < 0.5 * np.count_nonzero(fixed)


def test_split_handles_small_holed_and_flat_images_deterministically() -> None:
    rng = np.random.default_rng(123)
    eager = load_config(overrides={"refine": {"fit_factor": 0.5}})  # split whatever it can
    for trial in range(12):
        h, w = (int(v) for v in rng.integers(16, 60, size=2))
        y, x = np.mgrid[0:h, 0:w].astype(np.float64)
        z = 50.0 + rng.uniform(-3, 3) * np.abs(x - rng.uniform(0, w)) + rng.uniform(-2, 2) * y
        z = np.round(z + rng.normal(0.0, rng.uniform(0, 3), (h, w)))
        if trial % 3 == 0:
            z[rng.random((h, w)) < 0.2] = np.nan
        if trial % 4 == 1:
            z = np.full((h, w), 17.0)
        result = run_pipeline(z, eager, stages=3)
        first = result.labels
        np.testing.assert_array_equal(first, run_pipeline(z, eager, stages=3).labels)
        assert np.all(first[np.isnan(result.heights)] == 0)  # small holes are filled
        assert not (np.isnan(result.heights) & ~np.isnan(z)).any()


requires_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None,
                                    reason="numba is not installed")


@requires_numba
def test_far_nearest_label_search_breaks_ties_as_the_feature_transform_does() -> None:
    # The compiled search's wide radius: sparse labels (pixels up to 16 away) and labels
    # on a grid (many equally near ones), against scipy's feature transform.
    from scipy import ndimage

    from rangeseg_cli.kernels import compiled as _kernels

    rng = np.random.default_rng(31)
    dr, dc = split_module._FAR_OFFSETS
    for trial in range(200):
        h, w = (int(v) for v in rng.integers(5, 60, size=2))
        parts = np.where(rng.random((h, w)) < rng.choice([0.003, 0.02, 0.1]),
                         rng.integers(1, 6, (h, w)), 0).astype(np.int32)
        if trial % 4 == 0:
            parts[:] = 0
            step = int(rng.integers(3, 12))
            parts[::step, ::step] = rng.integers(1, 6, parts[::step, ::step].shape)
        if not parts.any():
            continue
        rows, cols = np.nonzero(parts == 0)
        found = _kernels.nearest_labels(parts, rows.astype(np.int64), cols.astype(np.int64),
                                        dr, dc)
        ir, ic = ndimage.distance_transform_edt(parts == 0, return_distances=False,
                                                return_indices=True)
        hit = found > 0
        np.testing.assert_array_equal(found[hit], parts[ir[rows, cols], ic[rows, cols]][hit])
        filled = split_module._fill_nearest(parts, np.ones(parts.shape, bool), "numba")
        np.testing.assert_array_equal(filled, split_module._fill_nearest(
            parts, np.ones(parts.shape, bool), "numpy"))


@requires_numba
def test_local_planes_numba_equal_the_scipy_blurs_bit_for_bit() -> None:
    rng = np.random.default_rng(5)
    for sigma in (1.0, 2.0, 4.0):
        z = rng.normal(0.0, 30.0, (37, 53)) + np.arange(53.0)
        mask = rng.random(z.shape) < 0.6
        for origin in (None, (-7.5, 12.0)):
            ref = local_planes(z, mask, sigma, origin=origin, backend="numpy")
            fast = local_planes(z, mask, sigma, origin=origin, backend="numba")
            for a, b in zip(ref, fast, strict=True):
                assert a.tobytes() == b.tobytes()  # NaNs and signed zeros included


@requires_numba
def test_plane_heights_at_the_asked_pixels_equal_the_whole_arrays_bit_for_bit() -> None:
    rng = np.random.default_rng(16)
    for trial in range(40):
        h, w = (int(v) for v in rng.integers(3, 60, size=2))
        z = rng.normal(0.0, 20.0, (h, w)) + rng.normal() * np.arange(float(w))
        mask = rng.random((h, w)) < rng.uniform(0.05, 0.9)
        sigma = float(rng.choice([1.0, 2.0, 2.5, 4.0]))
        rows, cols = np.nonzero(rng.random((h, w)) < 0.3)
        if trial % 2:  # any order, repeats included
            order = rng.integers(0, max(rows.size, 1), rows.size)
            rows, cols = rows[order], cols[order]
        ref = split_module._plane_heights(z, mask, sigma, rows, cols, backend="numpy")
        fast = split_module._plane_heights(z, mask, sigma, rows, cols, backend="numba")
        assert ref.tobytes() == fast.tobytes()  # NaNs and signed zeros included
        whole, _, _ = local_planes(z, mask, sigma, backend="numpy")
        assert whole[rows, cols].tobytes() == fast.tobytes()


@pytest.mark.parametrize("scene", ["part1", "frustum"])
def test_the_components_fits_given_by_the_caller_change_nothing(scene: str) -> None:
    from rangeseg_cli.stages.grow import component_fits
    from rangeseg_cli.synth.scenes import render_scene

    image = render_scene(scene, size=(96, 128), noise=1.0, seed=0).image
    result = run_pipeline(image, PAPER, stages=3)
    z, edges, components = result.heights, result.edges, result.components
    z[:3, :5] = np.nan  # invalid pixels are left out of the fits alike
    fits = component_fits(z, components)
    n = int(np.where(np.isfinite(z), components, 0).max())
    assert all(a.tobytes() == b.tobytes()
               for a, b in zip(fits, fit_quadrics(z, np.where(np.isfinite(z), components, 0), n),
                               strict=True))
    plain = grow_regions(z, edges, components, SPLIT.grow)
    seeded = grow_regions(z, edges, components, SPLIT.grow, fits=fits)
    np.testing.assert_array_equal(seeded, plain)
    np.testing.assert_array_equal(
        split_regions(z, edges, components, seeded, SPLIT, fits=fits),
        split_regions(z, edges, components, plain, SPLIT))
    with pytest.raises(ValueError, match="fits"):
        grow_regions(z, edges, components, SPLIT.grow, fits=fit_quadrics(z, components, n + 1))


@requires_numba
@pytest.mark.parametrize("scene", ["part1", "wedge", "frustum"])
def test_split_numba_and_numpy_paths_give_identical_labels(scene: str) -> None:
    from rangeseg_cli.synth.scenes import render_scene

    image = render_scene(scene, size=(96, 128), noise=1.0, seed=0).image
    result = run_pipeline(image, PAPER, stages=3)
    z = result.heights
    outs = [split_regions(z, result.edges, result.components, result.labels, SPLIT,
                          backend=backend) for backend in ("numpy", "numba")]
    assert outs[0] is not result.labels  # a component was split
    assert outs[0].dtype == outs[1].dtype
    assert outs[0].tobytes() == outs[1].tobytes()


@requires_numba
def test_compiled_nearest_labels_and_window_extremes_equal_scipys() -> None:
    rng = np.random.default_rng(14)
    for trial in range(200):
        h, w = (int(v) for v in rng.integers(1, 40, size=2))
        parts = np.where(rng.random((h, w)) < rng.uniform(0.02, 0.4),
                         rng.integers(1, 5, (h, w)), 0).astype(np.int32)
        if trial % 10 == 0:
            parts[:] = 0
            parts[h // 2, w // 2] = 3  # beyond the search radius: the transform
        rows, cols = np.nonzero(parts == 0)
        if parts.any() and rows.size:
            np.testing.assert_array_equal(
                split_module._nearest_labels(parts, rows, cols, "numba"),
                split_module._nearest_labels(parts, rows, cols, "numpy"))
        reach, cval = int(rng.integers(0, 5)), int(rng.choice([0, 2**31 - 1]))
        for a, b in zip(split_module._window_extremes(parts, reach, cval, "numba"),
                        split_module._window_extremes(parts, reach, cval, "numpy"),
                        strict=True):
            np.testing.assert_array_equal(a, b)


@requires_numba
def test_compiled_parts_and_raster_renumbering_equal_scipys_and_uniques() -> None:
    rng = np.random.default_rng(17)
    for trial in range(150):
        h, w = (int(v) for v in rng.integers(1, 45, size=2))
        labels = np.where(rng.random((h, w)) < rng.uniform(0.1, 1.0),
                          rng.integers(1, int(rng.integers(2, 8)), (h, w)), 0).astype(np.int32)
        if trial % 3 == 0:  # blobs rather than speckle
            labels = np.repeat(np.repeat(labels[::4, ::4], 4, axis=0), 4, axis=1)[:h, :w]
        for a, b in ((split_module._parts(labels, "numba"), split_module._parts(labels, "numpy")),
                     (regions.raster_renumber(labels, "numba"),
                      regions.raster_renumber(labels, "numpy"))):
            assert a.dtype == b.dtype
            np.testing.assert_array_equal(a, b)
    assert split_module._parts(np.array([[1, 0, 1], [1, 2, 2]], np.int32), "numba").tolist() \
        == [[1, 0, 2], [1, 3, 3]]


@requires_numba
def test_compiled_closing_equals_scipys_binary_closing() -> None:
    rng = np.random.default_rng(19)
    for _ in range(150):
        h, w = (int(v) for v in rng.integers(1, 40, size=2))
        mask = rng.random((h, w)) < rng.uniform(0.1, 0.95)
        np.testing.assert_array_equal(split_module._closing(mask, "numba"),
                                      split_module._closing(mask, "numpy"))


@requires_numba
def test_compiled_fill_nearest_equals_the_feature_transforms() -> None:
    rng = np.random.default_rng(21)
    for trial in range(200):
        h, w = (int(v) for v in rng.integers(1, 50, size=2))
        parts = np.where(rng.random((h, w)) < rng.uniform(0.005, 0.5),
                         rng.integers(1, 6, (h, w)), 0).astype(np.int32)
        if trial % 10 == 0:  # none, or one far away: the transform
            parts[:] = 0
            if trial % 20 == 0:
                parts[0, 0] = 2
        where = rng.random((h, w)) < rng.uniform(0.2, 1.0)
        np.testing.assert_array_equal(split_module._fill_nearest(parts, where, "numba"),
                                      split_module._fill_nearest(parts, where, "numpy"))


@requires_numba
def test_compiled_label_extremes_holes_and_adjacent_pairs_equal_the_references() -> None:
    rng = np.random.default_rng(22)
    for trial in range(150):
        h, w = (int(v) for v in rng.integers(1, 40, size=2))
        parts = np.where(rng.random((h, w)) < rng.uniform(0.0, 1.0),
                         rng.integers(1, 7, (h, w)), 0).astype(np.int32)
        if trial % 3 == 0:  # blobs
            parts = np.repeat(np.repeat(parts[::5, ::5], 5, axis=0), 5, axis=1)[:h, :w]
        reach = int(rng.integers(0, 5))
        for a, b in zip(split_module._label_extremes(parts, reach, "numba"),
                        split_module._label_extremes(parts, reach, "numpy"), strict=True):
            np.testing.assert_array_equal(a, b)
        fast, slow = (split_module._holes(parts > 0, b) for b in ("numba", "numpy"))
        assert fast[1] == slow[1]
        np.testing.assert_array_equal(fast[0], slow[0])
        assert regions.adjacent_pairs(parts, reach, backend="numba") \
            == regions.adjacent_pairs(parts, reach, backend="numpy")
        if parts.any():
            rows, cols = np.nonzero(rng.random((h, w)) < 0.5)
            np.testing.assert_array_equal(
                split_module._near(parts == parts.max(), reach, rows, cols, "numba"),
                split_module._near(parts == parts.max(), reach, rows, cols, "numpy"))


def test_refitting_the_new_pieces_alone_gives_their_fits_bit_for_bit() -> None:
    rng = np.random.default_rng(23)
    z = rng.normal(50.0, 5.0, (60, 70)) + np.arange(70.0) * 0.3
    pieces = np.repeat(np.repeat(rng.integers(0, 6, (12, 14)), 5, axis=0), 5, axis=1)
    pieces = pieces.astype(np.int32)
    ids = [2, 5]
    mse, mse_plane, counts = split_module._fit_pieces(z, pieces, ids, "auto")
    ((_, all_mse), (_, all_plane)), all_counts = split_module.fit_models(z, pieces, 5, (2, 1))
    assert mse[ids].tobytes() == all_mse[ids].tobytes()
    assert mse_plane[ids].tobytes() == all_plane[ids].tobytes()
    np.testing.assert_array_equal(counts[ids], all_counts[ids])
    assert counts[1] == 0 and all_counts[1] > 0  # the others are left out
    box = (slice(20, 60), slice(20, 70))
    outside = np.ones(pieces.shape, bool)
    outside[box] = False
    pieces[outside & np.isin(pieces, ids)] = 0  # the box holds every pixel of 2 and 5
    boxed = split_module._fit_pieces(z, pieces, ids, "auto", box)
    whole = split_module._fit_pieces(z, pieces, ids, "auto")
    for a, b in zip(boxed, whole, strict=True):
        assert a[ids].tobytes() == b[ids].tobytes()


def test_histogram_of_normals_equals_numpys_histogram2d() -> None:
    rng = np.random.default_rng(18)
    for trial in range(100):
        xy = rng.uniform(-1.05, 1.05, (int(rng.integers(1, 400)), 2))
        if trial % 2:
            xy = np.round(xy * 20.0) / 20.0  # on the bin edges, -1 and 1 included
        if trial % 5 == 0:  # just inside the outer edges, and NaN (an outlier)
            xy[::3, 0] = np.nextafter(1.0, 0.0)
            xy[::4, 1] = np.nextafter(-1.0, 0.0)
            xy[::7, 1] = np.nan
        ref, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=40, range=[[-1, 1], [-1, 1]])
        for backend in ("numpy", "numba") if importlib.util.find_spec("numba") else ("numpy",):
            fast = split_module._histogram(xy, backend)  # type: ignore[arg-type]
            assert fast.dtype == ref.dtype
            np.testing.assert_array_equal(fast, ref)


def _reference_mode_split(normals: np.ndarray) -> np.ndarray:
    """mode_split as first written: np.histogram2d, (N, 2) sums and Otsu by a full search."""
    xy = normals[:, :2]
    hist, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=40, range=[[-1, 1], [-1, 1]])
    peak = np.unravel_index(int(np.argmax(ndimage.gaussian_filter(hist, 1.0))), hist.shape)
    mode = -1.0 + (np.array(peak, dtype=np.float64) + 0.5) * 0.05
    near = np.sum((xy - mode) ** 2, axis=1) <= 0.1**2
    if near.any():
        mode = xy[near].mean(axis=0)
    dist = np.sqrt(np.sum((xy - mode) ** 2, axis=1))
    if np.ptp(dist) <= 0:
        return np.zeros(len(normals), bool)
    xs = np.sort(dist)
    k = np.arange(1, xs.size)
    csum = np.cumsum(xs)[:-1]
    between = k * (xs.size - k) * (csum / k - (xs.sum() - csum) / (xs.size - k)) ** 2
    i = int(np.argmax(between))
    return dist > 0.5 * (xs[i] + xs[i + 1])


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=requires_numba)])
def test_mode_split_equals_its_first_form(backend: str) -> None:
    rng = np.random.default_rng(20)
    for trial in range(150):
        n = int(rng.integers(2, 2000))
        g = rng.normal(0.0, rng.uniform(0.01, 1.0), (n, 2))
        g += rng.normal(0.0, 0.5, 2) * (rng.random((n, 1)) < 0.5)  # two faces
        if trial % 4 == 0:
            g = np.round(g * 10.0) / 10.0  # ties
        if trial % 9 == 0:
            g[:] = g[0]  # one normal: no split
        norm = np.sqrt(1.0 + np.sum(g * g, axis=1))
        normals = np.stack([-g[:, 0] / norm, -g[:, 1] / norm, 1.0 / norm], axis=1)
        np.testing.assert_array_equal(split_module.mode_split(normals, backend=backend),
                                      _reference_mode_split(normals))


@requires_numba
def test_mode_split_of_many_normals_sorts_by_radix_to_the_same_division() -> None:
    rng = np.random.default_rng(21)
    assert split_module._RADIX_FROM <= 12_000
    for trial in range(6):
        n = int(rng.integers(12_000, 60_000))
        g = rng.normal(0.0, 0.05, (n, 2)) + rng.normal(0.0, 0.5, 2) * (rng.random((n, 1)) < 0.3)
        if trial % 2:
            g = np.round(g * 50.0) / 50.0  # ties, and distances exactly 0
        norm = np.sqrt(1.0 + np.sum(g * g, axis=1))
        normals = np.stack([-g[:, 0] / norm, -g[:, 1] / norm, 1.0 / norm], axis=1)
        np.testing.assert_array_equal(split_module.mode_split(normals, backend="numba"),
                                      _reference_mode_split(normals))
    signed = rng.normal(0.0, 1.0, 20_000)  # not the distances of mode_split: np.sort
    signed[:5] = -0.0
    assert (split_module._otsu(signed, backend="numba")
            == split_module._otsu(signed, backend="numpy"))


def test_smallest_sorted_equals_the_head_of_a_full_sort() -> None:
    rng = np.random.default_rng(15)
    for trial in range(200):
        n = int(rng.integers(1, 3000))
        x = np.abs(np.round(rng.normal(0.0, float(rng.choice([0.1, 1.0, 10.0])), n)))
        if trial % 5 == 0:
            x = np.sort(x)[::-1].copy()  # a sparse sample unlike the whole
        k = int(rng.integers(0, n + 1))
        assert noise_module._smallest_sorted(x, k).tobytes() == np.sort(x)[:k].tobytes()


def test_a_second_round_splits_what_the_first_left_whole(tuning) -> None:
    """Two planes at a crease (the slope changes by 1.5 per pixel at x = 29.5) grown as one
    region from a component on one plane alone. The component passes the fit test, so
    round one splits nothing; round two tests the grown region, which fails, and cuts it
    at the crease (a frustum's top grown with its side when the component held the table)."""
    y, x = np.mgrid[0:40, 0:60].astype(np.float64)
    truth = np.where(x < 30, 1, 2).astype(np.int32)
    components = np.zeros(x.shape, np.int32)
    components[10:30, 5:20] = 1  # on the first plane
    grown = np.ones(x.shape, np.int32)  # across the crease
    codes = np.zeros(x.shape, np.uint8)
    for sigma, seed in ((0.0, 0), (1.0, 1), (2.0, 2), (2.0, 3)):
        z = _finish(100.0 + 0.1 * x + 0.05 * y - 1.5 * np.clip(x - 29.5, 0.0, None), sigma, seed)
        found = {}
        for rounds in (1, 2):
            tuning(rounds=rounds)
            found[rounds] = correct(truth, split_regions(z, codes, components, grown,
                                                         load_config(), noise=max(sigma, 0.3)))
        assert (found[1], found[2]) == (0, 2), (sigma, seed)


def _split_frustum(z: np.ndarray, truth: np.ndarray, noise: float, **flags: bool) -> int:
    """Correct detections of the faces of a small frustum (:func:`conftest.small_frustum`)
    that :func:`split_component` makes of it as one component (the table left out), with
    ``flags`` of ``[refine]`` changed."""
    cfg = replace(SPLIT.split, **flags)
    pieces = split_module.split_component(z, truth > 1, noise=noise, cfg=cfg, grow=SPLIT.grow)
    return correct(np.where(truth > 1, truth, 0), pieces)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_small_frustums_whose_pieces_pass_as_quadrics_are_cut_at_their_creases(seed) -> None:
    """A small frustum, sides 5 pixels wide rising 4 per pixel, at sigma 1.

    A piece holding the top and a side passes the fit test as a quadric, so
    without ``crease_pieces`` it is not split again and the merge-back glues
    every face back to it; ``crease_pieces`` splits a piece whose plane fails
    the test, along a straight crease when its normals do not divide it.
    """
    z, truth = small_frustum(1.0, seed, half=14, width=5, slope=4.0)
    assert _split_frustum(z, truth, 1.0) >= 2
    assert _split_frustum(z, truth, 1.0, crease_pieces=False) == 0


def test_a_noise_free_frustum_with_shallow_narrow_sides_needs_the_crease_pieces() -> None:
    # sides 7 pixels wide rising 2.5 per pixel: every face with them, two without
    z, truth = small_frustum(0.0, 0, half=14, width=7, slope=2.5)
    assert _split_frustum(z, truth, 0.3) == 5
    assert _split_frustum(z, truth, 0.3, crease_pieces=False) <= 2


def test_merge_back_keeps_two_planes_apart_that_fit_better_than_one_quadric() -> None:
    """A 6-pixel face beside a wider one at a steep crease, noise 2 (beyond the paper).

    The narrow piece holds one column of its neighbour, so the planar rule
    calls it curved and the crease-angle rule does not apply; on 20 x 20
    pixels one quadric bends round the crease within ``min_gain`` of the
    pieces' errors. Each piece's plane passes the fit test and the two
    planes fit better than the union's quadric: ``creases`` keeps them
    apart. A parabolic cylinder cut the same way (one quadric) is glued.
    """
    y, x = np.mgrid[0:20, 0:20].astype(np.float64)
    pieces = np.where(x < 13, 1, 2).astype(np.int32)
    rules = {"level": 2.75, "floor": 1.58, "min_gain": 1.5, "min_crease": 10.0,
             "planar_tolerance": 0.1, "min_error": 0.25}
    for seed in (0, 1):
        z = 50.0 + 0.2 * y + np.where(x < 14, 0.0, 2.0 * (x - 14))
        z += np.random.default_rng(seed).normal(0.0, 2.0, z.shape)
        assert merge_back(z, pieces, **rules).max() == 1
        assert merge_back(z, pieces, **rules, creases=0.6).max() == 2
        cylinder = 50.0 + 0.2 * y + 20.0 * (x / 20.0) ** 2
        cylinder += np.random.default_rng(seed).normal(0.0, 2.0, z.shape)
        assert merge_back(cylinder, pieces, **rules, creases=0.6).max() == 1


def test_crease_cut_divides_a_piece_along_the_crease_or_returns_none() -> None:
    y, x = np.mgrid[0:40, 0:40].astype(np.float64)
    z = 50.0 + 0.2 * y + np.where(x < 30, 0.0, 0.8 * (x - 30))
    z += np.random.default_rng(6).normal(0.0, 1.0, z.shape)
    mask = np.ones(z.shape, bool)
    cfg = load_config()
    sub = split_module._crease_cut(z, mask, noise=1.0, level=1.25, cfg=cfg.split,
                                   grow=cfg.grow)
    assert sub is not None and set(np.unique(sub)) == {1, 2}
    agree = np.mean(sub == np.where(x < 30, 1, 2))
    assert max(agree, 1.0 - agree) > 0.95  # either side may come first
    flat = 50.0 + 0.2 * y + np.random.default_rng(6).normal(0.0, 1.0, z.shape)
    assert split_module._crease_cut(flat, mask, noise=1.0, level=1.25, cfg=cfg.split,
                                    grow=cfg.grow) is None


def test_the_paper_pipeline_estimates_the_noise_only_when_asked(monkeypatch) -> None:
    import rangeseg_cli.pipeline as pipeline

    calls = []
    monkeypatch.setattr(pipeline, "estimate_noise",
                        lambda z: calls.append(1) or estimate_noise(z))
    z = tilted_plane(2.0, 5)
    paper = load_config(preset="paper")
    fill_only = load_config(preset="paper", overrides={"refine": {"passes": ["fill"]}})
    assert not pipeline.uses_noise(paper) and not pipeline.uses_noise(fill_only)
    assert pipeline.uses_noise(load_config())
    assert pipeline.uses_noise(load_config(preset="paper",
                                           overrides={"input": {"auto_thresholds": True}}))
    result = run_pipeline(z, paper)
    run_pipeline(z, fill_only)
    assert calls == []  # nothing of these configurations uses it
    assert result.noise_sigma == estimate_noise(result.heights)  # on first use
    assert result.noise_sigma == result.noise_sigma and len(calls) == 1  # then kept
    run_pipeline(z)
    assert len(calls) == 2  # the defaults: once, shared by every stage that uses it


def chamfered_block_scene(width: int = 3, slope: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """A block 48 pixels square and 90 up whose top has a chamfer ``width`` pixels wide.

    The chamfers fall ``slope`` units per pixel from the top's edge (a nut's
    45-degree chamfers: 2 per pixel at 128x128); noise-free, 8-bit. Returns
    the image and the true faces: 1 table, 2 top, 3..6 chamfers.
    """
    y, x = np.mgrid[0:96, 0:96].astype(np.float64)
    lo, hi = 24, 72
    inside = (y >= lo) & (y < hi) & (x >= lo) & (x < hi)
    top = 120.0 + 0.3 * (x - 48.0) + 0.1 * (y - 48.0)
    into = np.stack([x - (hi - 1 - width + 0.5), (lo + width - 0.5) - x,
                     y - (hi - 1 - width + 0.5), (lo + width - 0.5) - y])
    drop = np.maximum(into, 0.0).max(axis=0)
    z = np.where(inside, top - slope * drop, 30.0)
    truth = np.where(inside, np.where(drop > 0, np.argmax(into, axis=0) + 3, 2), 1)
    return np.clip(np.round(z), 0.0, 255.0), truth.astype(np.int32)


def test_trimmed_chamfers_become_faces_of_their_own(tuning) -> None:
    # The top's component holds its chamfers (too narrow for the normals to divide, no
    # straight crease around four sides); the trim leaves them out, and with
    # trim_faces (a constant: config.TUNING) the planes among them become regions instead
    # of being regrown into the top.
    image, truth = chamfered_block_scene()
    regions = {}
    # the carving (rangeseg_cli.refine.carve) and the facets (rangeseg_cli.refine.facets) would find
    # the chamfers too: off, to test the trim
    config = passes_without("carve", "facets")
    for faces in (True, False):
        tuning(trim_faces=faces)
        regions[faces] = run_pipeline(image, config, stages=3).labels
    on, off = regions[True], regions[False]
    top = {g for i in hoover_compare(truth, on).instances if i.kind == "correct" for g in i.gt}
    assert 2 in top  # the top alone, at T = 0.8
    chamfer_regions = 0
    for k in np.unique(on[on > 0]).tolist():
        values, counts = np.unique(truth[on == k], return_counts=True)
        g, share = int(values[np.argmax(counts)]), counts.max() / counts.sum()
        if g >= 3 and share >= 0.9 and counts.max() >= 0.6 * np.count_nonzero(truth == g):
            chamfer_regions += 1  # mostly one chamfer, and most of it
    assert chamfer_regions >= 3
    # Without them the top's region swallows every chamfer (an under-segmentation).
    top_region = np.bincount(off[truth == 2]).argmax()
    for g in range(3, 7):
        assert np.mean(off[truth == g] == top_region) > 0.8


def narrow_faces(width: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Three faces about ``width`` pixels wide at two roof creases (a ridge), 40 rows, 8 bits.

    Returns the heights and the faces 1, 2, 3 (0 on the two crease columns, which lie
    on two faces).
    """
    yy, xx = np.mgrid[0:40, 0:3 * width].astype(np.float64)
    rise = np.minimum(xx, width) - np.maximum(xx - 2 * width, 0.0)  # up, level, down
    truth = np.minimum(xx // width, 2).astype(np.int32) + 1
    truth[(xx == width) | (xx == 2 * width)] = 0
    return np.round(100.0 + 3.0 * rise + 0.3 * yy), truth


def test_plane_cut_gives_each_of_three_narrow_faces_a_piece() -> None:
    z, truth = narrow_faces()
    pieces = np.ones(z.shape, np.int32)
    assert split_module._plane_cut(z, pieces, 1, 1, 0.625, Config().split)
    owners = [np.bincount(pieces[truth == g], minlength=4) for g in (1, 2, 3)]
    assert len({int(o.argmax()) for o in owners}) == 3 and min(o.argmax() for o in owners) > 0
    for g, o in zip((1, 2, 3), owners, strict=True):
        assert o.max() == np.count_nonzero(truth == g)


def test_plane_cut_leaves_a_piece_whole_that_its_planes_do_not_hold() -> None:
    # A sphere cap: the consensus planes hold too little of it (PLANE_CUT_COVER).
    y, x = np.mgrid[0:60, 0:60].astype(np.float64)
    r2 = (x - 30.0) ** 2 + (y - 30.0) ** 2
    z = np.round(20.0 + np.sqrt(np.maximum(1600.0 - r2, 0.0)))
    pieces = (r2 < 28.0 ** 2).astype(np.int32)
    before = pieces.copy()
    assert not split_module._plane_cut(z, pieces, 1, 1, 0.625, Config().split)
    np.testing.assert_array_equal(pieces, before)


def test_plane_cut_stays_within_max_pieces() -> None:
    z, _ = narrow_faces()
    cfg = replace(Config().split, max_pieces=3)
    pieces = np.ones(z.shape, np.int32)
    assert not split_module._plane_cut(z, pieces, 1, 2, 0.625, cfg)  # 2 + 2 new > 3
    assert (pieces == 1).all()
    assert split_module._plane_cut(z, pieces, 1, 1, 0.625, cfg)
    assert set(np.unique(pieces).tolist()) <= {0, 1, 2, 3}


@pytest.mark.parametrize(("sigma", "seed"), [(0.0, 0), (0.5, 0), (0.5, 1), (0.5, 2),
                                           (1.0, 0), (1.0, 1), (1.0, 2)])
def test_a_small_frustum_is_cut_into_its_faces_by_the_plane_cut(sigma, seed) -> None:
    """A small frustum whose top is as narrow as its sides (7 pixels, rising 4 per pixel).

    The split divides its component, but one piece holds two sides and a
    strip of the top; it fails the fit test, nothing else divides it, and
    merge_back glues every other piece to it: without ``plane_cut`` no face
    is found. The plane cut cuts that piece into the planes consensus finds.
    """
    z, truth = small_frustum(sigma, seed, half=10, width=7, slope=4.0)
    noise = max(sigma, 0.3)
    assert _split_frustum(z, truth, noise) >= (4 if sigma == 0.0 else 2)
    assert _split_frustum(z, truth, noise, plane_cut=False) == 0


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), shape=st.tuples(st.integers(12, 48), st.integers(12, 48)),
       before=st.integers(1, 7), sigma=st.sampled_from([0.0, 1.0, 2.0]))
def test_a_plane_cut_stays_inside_its_piece_and_within_max_pieces(seed, shape, before, sigma):
    # Heights: the lower envelope of three random planes (two creases), plus noise;
    # piece 1 a box of it, pieces 2..before elsewhere.
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    planes = rng.uniform(-3.0, 3.0, (3, 2))
    z = np.min([100.0 + a * x + b * y + rng.uniform(-10, 10) for a, b in planes], axis=0)
    z = np.round(z + rng.normal(0.0, sigma, shape))
    pieces = rng.integers(2, before + 2, shape).astype(np.int32) if before > 1 else np.zeros(
        shape, np.int32)
    blob = np.zeros(shape, bool)  # a box of at least half of each side
    r0, c0 = rng.integers(0, shape[0] // 2), rng.integers(0, shape[1] // 2)
    blob[r0:r0 + shape[0] // 2 + 1, c0:c0 + shape[1] // 2 + 1] = True
    pieces[blob] = 1
    n = int(pieces.max())
    cfg = Config().split
    old = pieces.copy()
    cut = split_module._plane_cut(z, pieces, 1, n, 0.625 * max(sigma, 1.0), cfg)
    if not cut:
        np.testing.assert_array_equal(pieces, old)
        return
    assert (pieces[~blob] == old[~blob]).all()  # nothing outside the piece moves
    new = np.unique(pieces[blob]).tolist()
    assert set(new) <= {0, 1, *range(n + 1, cfg.max_pieces + 1)} and len(new) >= 2
    held = np.count_nonzero(pieces[blob])
    assert held >= split_module.PLANE_CUT_COVER * np.count_nonzero(blob)
    for k in set(new) - {0}:
        assert np.count_nonzero(pieces[blob] == k) >= cfg.min_piece


def test_plane_pieces_with_the_first_plane_given_are_the_plane_pieces() -> None:
    from rangeseg_cli.refine.recover import INLIER_FACTOR, consensus_plane, plane_pieces

    y, x = np.mgrid[0:30, 0:36].astype(np.float64)
    z = np.where(x < 14, 50.0 + 0.5 * x, 57.0 - 0.8 * (x - 14))  # a roof's two faces
    z = np.where(y > 20, z + 0.9 * (y - 20), z)  # and a third face
    for seed in range(4):
        noisy = z + np.random.default_rng(seed).normal(0.0, 0.5, z.shape)
        mask = np.ones(z.shape, bool)
        mask[:3, :5] = False
        first = consensus_plane(noisy, mask, INLIER_FACTOR * 0.625)
        got = plane_pieces(noisy, mask, level=0.625, min_pixels=20, found=(first,))
        want = plane_pieces(noisy, mask, level=0.625, min_pixels=20)
        assert len(got) == len(want) >= 2
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a, b)
    assert plane_pieces(z, mask, level=0.625, min_pixels=20, found=(None,)) == []


def test_near_part_from_the_label_extremes_equals_the_window_search() -> None:
    rng = np.random.default_rng(23)
    cfg = SPLIT.split
    for _ in range(100):
        h, w = (int(v) for v in rng.integers(4, 40, size=2))
        coarse = rng.integers(0, 5, (h // 5 + 1, w // 5 + 1))
        parts = np.kron(coarse, np.ones((5, 5), int))[:h, :w].astype(np.int32)
        if not (parts > 0).any():
            continue
        frame = split_module._Frame.of(parts > 0, cfg)
        low, high = split_module._label_extremes(parts, frame.band, "auto")
        rows, cols = np.nonzero((high > 0) & (low != high))
        extremes = (low[rows, cols], high[rows, cols])
        for k in np.unique(parts[parts > 0]).tolist():
            want = split_module._near(parts == k, frame.band, rows, cols)
            got = split_module._near_part(parts, k, extremes, frame, rows, cols)
            np.testing.assert_array_equal(got, want)


def test_c_array_is_the_array_itself_when_it_conforms_else_a_c_contiguous_copy() -> None:
    a = np.arange(12, dtype=np.int32).reshape(3, 4)
    assert regions.c_array(a, np.int32) is a
    b = regions.c_array(a[:, ::2], np.int32)  # a strided view: copied
    assert b.flags.c_contiguous and b.dtype == np.int32
    np.testing.assert_array_equal(b, a[:, ::2])
    c = regions.c_array(a > 5, np.int32)  # another dtype: converted
    assert c.dtype == np.int32 and c.flags.c_contiguous
    np.testing.assert_array_equal(c, (a > 5).astype(np.int32))
    mask = a > 5
    assert regions.c_array(mask, np.bool_) is mask


def test_within_two_is_the_square_dilation_twice() -> None:
    from scipy import ndimage

    rng = np.random.default_rng(29)
    square = np.ones((3, 3), bool)
    for _ in range(200):
        h, w = (int(v) for v in rng.integers(1, 30, size=2))
        where = rng.random((h, w)) < rng.random() * 0.3
        want = ndimage.binary_dilation(where, structure=square, iterations=2)
        np.testing.assert_array_equal(regions._within_two(where), want)


def test_clean_keeps_parts_that_are_all_wide_as_they_are() -> None:
    cfg = SPLIT.split
    parts = np.zeros((30, 40), np.int32)
    parts[2:28, 2:20] = 1
    parts[2:28, 20:38] = 2  # two wide halves
    frame = split_module._Frame.of(parts > 0, cfg)
    np.testing.assert_array_equal(split_module._clean(parts, frame), parts)
    parts[2:28, 36:38] = 3  # a sliver: given to its wide neighbour
    out = split_module._clean(parts, frame)
    assert set(np.unique(out).tolist()) == {0, 1, 2}
    assert (out[2:28, 36:38] == 2).all()


@requires_numba
def test_compiled_clean_gives_the_references_parts_or_hands_back() -> None:
    # clean_parts is split._clean in one compiled call: the same parts (numbers and
    # dtype included); status 0 where a pixel lies beyond the far nearest-label search,
    # which the reference answers with the feature transform.
    from rangeseg_cli.kernels import compiled as _kernels

    rng = np.random.default_rng(31)
    answered = cases = 0
    for parts, mask, frame in _block_parts(rng):
        noisy = np.where(rng.random(parts.shape) < 0.1, rng.integers(0, 4, parts.shape),
                         parts).astype(np.int32) * mask
        reference = split_module._clean(noisy, replace(frame, backend="numpy"))
        compiled = split_module._clean(noisy, replace(frame, backend="numba"))
        assert compiled.dtype == reference.dtype
        np.testing.assert_array_equal(compiled, reference)
        _, status = _kernels.clean_parts(noisy, mask, frame.solid, frame.min_piece,
                                         frame.thickness, *split_module._FAR_OFFSETS)
        answered += status
        cases += 1
    assert answered >= 0.8 * cases  # the kernel answers, the reference rarely does
    far = np.zeros((40, 40), np.int32)
    far[0, 0] = 1  # the opposite corner is beyond the far search
    whole = np.ones(far.shape, bool)
    _, status = _kernels.clean_parts(far, whole, whole, 1, 1, *split_module._FAR_OFFSETS)
    assert status == 0
    frame = split_module._Frame.of(whole, SPLIT.split, "numba")
    np.testing.assert_array_equal(split_module._clean(far, frame),
                                  split_module._clean(far, replace(frame, backend="numpy")))


def _scattered_parts(rng: np.random.Generator) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """60 piecewise-planar scenes of about 70 x 80 with parts of gapped ids (7, 2, 9, 12).

    A background part and three rectangles inside it, away from the border,
    so that the pixels near two parts fill only part of the array; heights
    a plane per part plus noise.
    """
    for _ in range(60):
        h, w = (int(v) for v in rng.integers(60, 80, size=2))
        parts = np.full((h, w), 7, np.int32)
        for k in (2, 9, 12):
            r0, c0 = int(rng.integers(20, h - 30)), int(rng.integers(20, w - 30))
            parts[r0:r0 + int(rng.integers(6, 14)), c0:c0 + int(rng.integers(6, 14))] = k
        parts[rng.random(parts.shape) < 0.02] = 0  # a few edge pixels
        y, x = np.mgrid[0:h, 0:w].astype(np.float64)
        slopes = rng.normal(0.0, 0.5, (13, 3))
        z = slopes[parts, 0] * x + slopes[parts, 1] * y + 10.0 * slopes[parts, 2]
        yield parts, z + rng.normal(0.0, 0.3, z.shape)


@requires_numba
def test_compiled_reassign_gives_the_references_labels_or_hands_back() -> None:
    # reassign_parts is split._reassign in one compiled call: each pixel near two parts
    # goes to the part whose local plane predicts it best, with the same labels as the
    # reference; status 0 where the parts' nearest-label fill over the solid mask needs
    # the feature transform.
    from rangeseg_cli.kernels import compiled as _kernels

    rng = np.random.default_rng(37)
    changed = smaller_box = 0
    blocks = ((p, m, f, 0.5 * np.mgrid[0:p.shape[0], 0:p.shape[1]][1] + rng.normal(0, .3, p.shape))
              for p, m, f in _block_parts(rng))
    scattered = ((p, p > 0, split_module._Frame.of(p > 0, SPLIT.split), z)
                 for p, z in _scattered_parts(rng))
    for parts, mask, frame, z in itertools.chain(blocks, scattered):
        reference = split_module._reassign(z, parts, replace(frame, backend="numpy"))
        compiled = split_module._reassign(z, parts, replace(frame, backend="numba"))
        assert compiled.dtype == reference.dtype
        np.testing.assert_array_equal(compiled, reference)
        out, status = _kernels.reassign_parts(
            z, parts, mask, frame.solid, frame.band, frame.thickness,
            frame.band + int(np.ceil(3.0 * frame.sigma)), writeable_weights(frame.sigma),
            1e-3 * frame.sigma**4, *split_module._FAR_OFFSETS)
        assert status == 1
        np.testing.assert_array_equal(out, reference)
        changed += int(not np.array_equal(out, parts))
        low, high = split_module._label_extremes(parts, frame.band, "numpy")
        doubt = mask & (high > 0) & (low != high)
        if doubt.any():
            box = regions.bounding_box(doubt, frame.band + int(np.ceil(3.0 * frame.sigma)))
            smaller_box += regions.box_area(box) < parts.size
    assert changed > 30 and smaller_box > 30  # pixels move; the work is cropped
    far = np.zeros((40, 40), np.int32)
    far[0, 0], far[0, 1] = 1, 2  # the opposite corner is beyond the far search
    whole = np.ones(far.shape, bool)
    _, status = _kernels.reassign_parts(np.zeros(far.shape), far, whole, whole, 2, 1, 8,
                                        writeable_weights(2.0), 1e-3, *split_module._FAR_OFFSETS)
    assert status == 0
