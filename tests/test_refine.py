"""Boundary pixels settle on the surface that predicts them best (rangeseg_cli.refine.boundaries)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import bad_setting_on_the_command_line, chamfered
from rangeseg_cli.config import load_config
from rangeseg_cli.errors import ConfigError
from rangeseg_cli.refine.boundaries import crease_kinds, refine_boundaries
from rangeseg_cli.refine.carve import carve_faces
from rangeseg_cli.refine.fill import surface_models
from rangeseg_cli.synth.evaluate import hoover_compare

CONFIG = load_config()


def roof(noise: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two planes meeting at a crease along column 31.5, with truth 1 | 2."""
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    z = 100.0 + 3.0 * np.abs(x - 31.5) + 0.5 * y
    z += np.random.default_rng(seed).normal(0.0, noise, z.shape) if noise else 0.0
    return z, np.where(x < 31.5, 1, 2).astype(np.int32)


def strip(lost: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A face 3 pixels wide rising 12 per pixel between two flat planes.

    As a box's side seen at a grazing angle (part1's sides rise 14-18 per
    pixel). The labels give the face's ``lost`` ("left" or "right") column
    to the neighbouring plane.
    """
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    z = 100.0 + 12.0 * np.clip(x - 29.5, 0.0, 3.0) + 0.25 * y
    truth = np.select([x < 30, x < 33], [1, 2], 3).astype(np.int32)
    left, right = (31, 33) if lost == "left" else (30, 32)
    labels = np.select([x < left, x < right], [1, 2], 3).astype(np.int32)
    return z, truth, labels


def test_a_boundary_two_pixels_off_moves_back_to_the_crease():
    z, truth = roof()
    off = np.where(np.arange(64) < 34, 1, 2)[None, :].repeat(48, axis=0).astype(np.int32)
    out = refine_boundaries(z, off, CONFIG, noise=0.0)
    np.testing.assert_array_equal(out, truth)


@pytest.mark.parametrize("lost", ["left", "right"])
def test_a_narrow_face_gets_back_the_column_its_neighbour_took(lost):
    z, truth, labels = strip(lost)
    assert hoover_compare(truth, labels).counts()["correct"] == 2  # the strip is lost
    out = refine_boundaries(z, labels, CONFIG, noise=0.0)
    np.testing.assert_array_equal(out, truth)


def test_smoothness_keeps_noisy_pixels_from_crossing_the_crease(tuning):
    # the crease rule alone puts every pixel right here: off, to test the smoothness
    z, truth = roof(noise=2.0, seed=4)
    tuning(refine_creases=False)
    smooth = refine_boundaries(z, truth, CONFIG, noise=2.0)
    rough = refine_boundaries(z, truth, load_config(overrides={"refine": {
        "smoothness": 0.0}}), noise=2.0)
    assert np.count_nonzero(smooth != truth) < np.count_nonzero(rough != truth)


def two_planes(shape: str) -> tuple[np.ndarray, np.ndarray]:
    """A ridge, a valley or a step between columns 31 and 32, labels 1 | 2, no noise."""
    y, x = np.mgrid[0:40, 0:64].astype(np.float64)
    z = {"ridge": 200.0 - 3.0 * np.abs(x - 31.5), "valley": 100.0 + 3.0 * np.abs(x - 31.5),
         "step": 100.0 + 0.5 * x + 20.0 * (x > 31.5)}[shape] + 0.25 * y
    return z, np.where(x < 31.5, 1, 2).astype(np.int32)


@pytest.mark.parametrize(("shape", "kind"), [("ridge", -1), ("valley", 1), ("step", 0)])
def test_crease_kinds_tell_a_ridge_a_valley_and_a_step(shape, kind):
    z, labels = two_planes(shape)
    coeffs, _ = surface_models(z, labels, 2, CONFIG.grow)
    kinds = crease_kinds(labels, coeffs)
    assert kinds[1, 2] == kinds[2, 1] == kind
    assert not kinds[0].any() and not kinds[:, 0].any()


def test_regions_too_far_apart_have_no_crease_kind():
    z, _ = two_planes("ridge")
    labels = np.select([np.arange(64) < 28, np.arange(64) >= 36], [1, 2], 0)
    labels = labels[None, :].repeat(40, axis=0).astype(np.int32)
    coeffs, _ = surface_models(z, labels, 2, CONFIG.grow)
    assert not crease_kinds(labels, coeffs).any()


@pytest.mark.parametrize("seed", [2, 4])
def test_the_crease_rule_keeps_noisy_pixels_on_their_side_of_the_crease(seed, tuning):
    z, truth = roof(noise=2.0, seed=seed)
    creased = refine_boundaries(z, truth, CONFIG, noise=2.0)
    tuning(refine_creases=False)
    plain = refine_boundaries(z, truth, CONFIG, noise=2.0)
    assert np.count_nonzero(plain != truth) >= 10  # the residual alone moves them
    np.testing.assert_array_equal(creased, truth)


def shallow_strip(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A face 3 pixels wide rising 5 per pixel between two flat planes, noise sigma 2
    (a narrow side at shallow creases, as part2's -y side): heights, the truth 1 | 2 | 3
    and labels that give the face's left column to the left plane."""
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    z = 100.0 + 5.0 * np.clip(x - 29.5, 0.0, 3.0) + 0.25 * y
    z += np.random.default_rng(seed).normal(0.0, 2.0, z.shape)
    truth = np.select([x < 30, x < 33], [1, 2], 3).astype(np.int32)
    return z, truth, np.select([x < 31, x < 33], [1, 2], 3).astype(np.int32)


def test_the_crease_rule_finds_a_narrow_face_at_shallow_creases_at_sigma_2(tuning):
    """With the crease rule the face is a correct detection (T = 0.8) on each of ten
    seeds; by the residual alone noisy pixels cross its creases and it is on few."""
    def found(labels, truth):
        return any(i.kind == "correct" and 2 in i.gt
                   for i in hoover_compare(truth, labels).instances)

    scenes = [shallow_strip(seed) for seed in range(10)]
    assert not any(found(labels, truth) for _, truth, labels in scenes)
    creased = [found(refine_boundaries(z, labels, CONFIG, noise=2.0), truth)
               for z, truth, labels in scenes]
    tuning(refine_creases=False)
    plain = [found(refine_boundaries(z, labels, CONFIG, noise=2.0), truth)
             for z, truth, labels in scenes]
    assert all(creased)
    assert sum(plain) <= 5


def test_labelled_pixels_stay_labelled_and_the_input_is_kept():
    z, truth = roof(noise=1.0, seed=1)
    z[5:9, 10:20] = np.nan
    labels = np.where(np.arange(64) < 33, 1, 2)[None, :].repeat(48, axis=0).astype(np.int32)
    labels[:, 40:42] = 0  # an edge band
    before = labels.copy()
    out = refine_boundaries(z, labels, CONFIG, noise=1.0)
    np.testing.assert_array_equal(labels, before)
    np.testing.assert_array_equal(out > 0, (before > 0) & np.isfinite(z))
    assert set(np.unique(out).tolist()) == {0, 1, 2}


def test_a_region_that_loses_every_pixel_leaves_consecutive_labels():
    z, truth = roof()
    labels = truth.copy()
    labels[20, 10] = 3  # one pixel of plane 1 labelled as a region of its own
    labels[30, 50] = 4  # and one of plane 2
    out = refine_boundaries(z, labels, CONFIG, noise=0.0)
    np.testing.assert_array_equal(out, truth)


def test_shapes_must_agree():
    with pytest.raises(ValueError):
        refine_boundaries(np.zeros((4, 4)), np.zeros((4, 5), np.int32), CONFIG, noise=0.0)


@pytest.mark.parametrize("seed", range(4))
def test_a_carved_chamfer_becomes_a_correct_detection_by_the_refinement_alone(seed):
    """Carving cuts the chamfer (a top, a chamfer 4 pixels wide
    falling 1.7 per pixel, a steep side: conftest's
    :func:`chamfered`; sigma 1) out of the top with its border off;
    the refinement moves it back (part2's chamfer at sigma 2 was found so)."""
    z, truth, grown = chamfered(1.0, seed)
    carved = carve_faces(z, grown, CONFIG, noise=1.0)
    assert carved.max() == 3  # the chamfer has a region ...
    assert hoover_compare(truth, carved).counts()["correct"] == 2  # ... not a correct one
    out = refine_boundaries(z, carved, CONFIG, noise=1.0)
    assert hoover_compare(truth, out).counts()["correct"] == 3


def test_paper_preset_turns_it_off():
    assert "boundaries" not in load_config(preset="paper").refine.passes
    assert "boundaries" in CONFIG.refine.passes


# the old keys [split] refine, refine_passes, refine_smoothness, refine_creases:
# tests/test_config.py
@pytest.mark.parametrize(("values", "match"), [
    ({"refine": {"smoothness": -1.0}}, r"\[refine\] smoothness = -1.0"),
    ({"refine": {"smoothness": "1"}}, r"\[refine\] smoothness = '1': expected a number"),
])
def test_refine_keys_are_validated(values, match):
    with pytest.raises(ConfigError, match=match):
        load_config(overrides=values)


def test_a_bad_refine_key_on_the_command_line_is_one_line(tmp_path):
    assert "smoothness = -1" in bad_setting_on_the_command_line(tmp_path,
                                                                "refine.smoothness=-1")


def pyramid_and_dome(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A four-sided pyramid beside a dome on a tilted floor, noise 1.5, and rough labels.

    The labels are the true faces with 30 % of the pixels taken from the faces
    shifted by two pixels, so the pass has pixels to move across creases, steps
    and a curved surface's rim.
    """
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:72, 0:96].astype(np.float64)
    floor = 50.0 + 0.2 * x + 0.1 * y
    peak = 160.0 - 2.5 * np.maximum(np.abs(x - 30), np.abs(y - 36))
    dome = 140.0 - 0.06 * ((x - 72) ** 2 + (y - 36) ** 2)
    z = np.maximum.reduce([floor, peak, dome])
    face = np.select([peak >= np.maximum(floor, dome), dome >= floor],
                     [np.where(np.abs(x - 30) >= np.abs(y - 36), 1 + (x > 30), 3 + (y > 36)),
                      5], 6)
    shifted = np.roll(face, (2, -2), axis=(0, 1))
    rough = np.where(rng.random(face.shape) < 0.3, shifted, face).astype(np.int32)
    return z + rng.normal(0.0, 1.5, z.shape), rough


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("creases", [True, False])
def test_the_compiled_pass_gives_the_references_labels(seed, creases, tuning):
    z, rough = pyramid_and_dome(seed)
    tuning(refine_creases=creases)
    reference = refine_boundaries(z, rough, CONFIG, noise=1.5, backend="numpy")
    compiled = refine_boundaries(z, rough, CONFIG, noise=1.5, backend="numba")
    assert np.count_nonzero(reference != rough) > 50  # the pass moves pixels here
    np.testing.assert_array_equal(compiled, reference)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_compiled_crease_votes_give_the_references_kinds(seed):
    z, rough = pyramid_and_dome(seed)
    coeffs, _ = surface_models(z, rough, 6, CONFIG.grow)
    reference = crease_kinds(rough, coeffs, backend="numpy")
    assert (reference == -1).any() and (reference == 0).any()
    np.testing.assert_array_equal(crease_kinds(rough, coeffs, backend="numba"), reference)


@pytest.mark.parametrize("threads", [2, 5])
def test_the_compiled_pass_in_row_bands_gives_the_references_labels(monkeypatch, threads,
                                                                    tuning):
    # bands of a few rows: each band's boundary pixels read the rows either side, and
    # the crease votes of the bands follow each other in raster order
    from rangeseg_cli.kernels import parallel

    monkeypatch.setattr(parallel, "MIN_BAND_ROWS", 1)
    monkeypatch.setattr(parallel, "MIN_BAND_PIXELS", 1)
    parallel.set_threads(threads)
    assert len(parallel.row_bands(72, 96, 1)) == threads
    z, rough = pyramid_and_dome(3)
    tuning(refine_creases=True)
    reference = refine_boundaries(z, rough, CONFIG, noise=1.5, backend="numpy")
    np.testing.assert_array_equal(refine_boundaries(z, rough, CONFIG, noise=1.5,
                                                    backend="numba"), reference)
    coeffs, _ = surface_models(z, rough, 6, CONFIG.grow)
    np.testing.assert_array_equal(crease_kinds(rough, coeffs, backend="numba"),
                                  crease_kinds(rough, coeffs, backend="numpy"))
    rng = np.random.default_rng(7)  # many regions near each pixel: every vote counts
    labels = rng.integers(1, 25, (30, 30)).astype(np.int32)
    coeffs = np.zeros((25, 6))
    coeffs[:, 0] = rng.normal(100.0, 5.0, 25)
    coeffs[:, 1:3] = rng.normal(0.0, 1.0, (25, 2))
    for agreement in (0.5, 0.6, 0.7):
        np.testing.assert_array_equal(
            crease_kinds(labels, coeffs, agreement=agreement, backend="numba"),
            crease_kinds(labels, coeffs, agreement=agreement, backend="numpy"))


def test_crease_kinds_of_many_small_regions_match_the_reference():
    # every pixel sees a dozen regions within reach: the compiled votes outgrow their
    # first buffer
    rng = np.random.default_rng(7)
    labels = rng.integers(1, 25, (30, 30)).astype(np.int32)
    coeffs = np.zeros((25, 6))
    coeffs[:, 0] = rng.normal(100.0, 5.0, 25)
    coeffs[:, 1:3] = rng.normal(0.0, 1.0, (25, 2))
    reference = crease_kinds(labels, coeffs, agreement=0.5, backend="numpy")
    assert (reference == -1).any() and (reference == 1).any()
    np.testing.assert_array_equal(
        crease_kinds(labels, coeffs, agreement=0.5, backend="numba"), reference)


@pytest.mark.parametrize("seed", range(5))
def test_the_sparse_crease_table_is_the_dense_one(seed):
    # The table was made from dense (n+1)^2 float sums: 800 MB arrays, 19 s a pass on
    # a 5 MP frame of 10,000 regions. From the keys present it is the same.
    from rangeseg_cli.refine.boundaries import crease_table, pair_sums

    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 30))
    keys = rng.integers(0, (n + 1) ** 2, 400)
    keys = np.concatenate([keys, (keys % (n + 1)) * (n + 1) + keys // (n + 1)])  # both ways
    keys = keys[rng.permutation(keys.size)][: int(rng.integers(1, keys.size))]
    below = (rng.random(keys.size) < rng.random()).astype(np.float64)
    votes = rng.integers(1, 4, keys.size).astype(np.float64)
    lower = np.bincount(keys, weights=below * votes, minlength=(n + 1) ** 2)
    total = np.bincount(keys, weights=votes, minlength=(n + 1) ** 2)
    frac = (lower / np.maximum(total, 1)).reshape(n + 1, n + 1)
    seen = total.reshape(n + 1, n + 1) > 0
    seen &= seen.T
    want = np.zeros((n + 1, n + 1), np.int8)
    want[seen & (frac >= 0.8) & (frac.T >= 0.8)] = -1
    want[seen & (frac <= 1 - 0.8) & (frac.T <= 1 - 0.8)] = 1
    got = crease_table(*pair_sums(keys, below * votes, votes), n, 0.8)
    np.testing.assert_array_equal(got, want)
    assert not crease_table(*pair_sums(keys[:0], below[:0], votes[:0]), n, 0.8).any()
