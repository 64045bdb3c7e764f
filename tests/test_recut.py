"""Regions are cut along the straight line where a plane ends (rangeseg_cli.refine.recut)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import passes_without
from rangeseg_cli.config import load_config
from rangeseg_cli.refine.passes import Scene, refine_regions
from rangeseg_cli.refine.recut import crease_side, recut_regions, split_crease, split_tangent
from rangeseg_cli.synth.evaluate import hoover_compare

CONFIG = load_config()
OFF = passes_without("recut")
KNOT = 24.0
RADIUS = 16.0
#: Depth units per pixel of the model, about part1's (its fillet drops 39 units over 14 px).
DEPTH_SCALE = 2.5


def _grid(w: int) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:56, 0:w].astype(np.float64)
    return y, x


def _plane_and_fillet(sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane (x < KNOT) that a cylinder leaves tangentially, and the truth.

    Part1's block top and fillet (Fig. 10) in proportion: the cylinder is
    kept up to 0.9 of its radius, where its slope stays within reach of the
    growing (steeper pixels are step edges in the pipeline).
    """
    y, x = _grid(int(KNOT + 0.9 * RADIUS))
    d = np.clip(x - KNOT, 0.0, None)
    z = 80.0 + 0.1 * x + 0.05 * y - DEPTH_SCALE * (RADIUS - np.sqrt(RADIUS**2 - d**2))
    truth = np.where(x < KNOT, 1, 2).astype(np.int32)
    return z + np.random.default_rng(seed).normal(0.0, sigma, z.shape), truth


def _crease(sigma: float, bend: float, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Two planes meeting at x = KNOT, the slope changing by ``bend`` units per pixel."""
    y, x = _grid(40)
    z = 80.0 + 0.1 * x + 0.05 * y - bend * np.clip(x - KNOT, 0.0, None)
    truth = np.where(x < KNOT, 1, 2).astype(np.int32)
    return z + np.random.default_rng(seed).normal(0.0, sigma, z.shape), truth


def _correct(truth: np.ndarray, labels: np.ndarray) -> int:
    return sum(i.kind == "correct" for i in hoover_compare(truth, labels).instances)


def _refined(z: np.ndarray, labels: np.ndarray, config, sigma: float) -> np.ndarray:
    """The refinement passes of ``config`` on ``labels`` (no edges; the components are them)."""
    scene = Scene(z, np.zeros(z.shape, np.uint8), labels, config, max(sigma, 0.3))
    return refine_regions(scene, labels)


@pytest.mark.parametrize("sigma", [0.0, 1.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_region_holding_a_plane_and_its_fillet_is_cut(sigma, seed):
    z, truth = _plane_and_fillet(sigma, seed)
    out = recut_regions(z, np.ones_like(truth), CONFIG, noise=max(sigma, 0.3))
    assert _correct(truth, out) == 2


@pytest.mark.parametrize("sigma", [0.0, 1.0])
def test_two_regions_cut_in_the_fillet_are_recut_at_the_tangent_line(sigma):
    z, truth = _plane_and_fillet(sigma)
    x = _grid(z.shape[1])[1]
    labels = np.where(x < KNOT + 5, 1, 2).astype(np.int32)   # the split's cut, too far out
    assert _correct(truth, labels) < 2
    out = recut_regions(z, labels, CONFIG, noise=max(sigma, 0.3))
    assert _correct(truth, out) == 2


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_one_region_holding_two_planes_at_a_crease_is_cut(sigma):
    z, truth = _crease(sigma, 1.5)
    out = recut_regions(z, np.ones_like(truth), CONFIG, noise=max(sigma, 0.3))
    assert _correct(truth, out) == 2


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_a_strip_given_to_the_wrong_plane_goes_back(sigma):
    z, truth = _crease(sigma, 1.5)
    x = _grid(z.shape[1])[1]
    labels = np.where(x < KNOT - 5, 1, 2).astype(np.int32)
    assert _correct(truth, labels) < 2
    out = recut_regions(z, labels, CONFIG, noise=max(sigma, 0.3))
    assert _correct(truth, out) == 2


def test_a_crease_below_min_crease_is_left_alone():
    z, truth = _crease(2.0, 0.05)
    labels = np.ones_like(truth)
    assert np.array_equal(recut_regions(z, labels, CONFIG, noise=2.0), labels)


@pytest.mark.parametrize("sigma", [0.0, 2.0])
def test_a_cylinder_alone_is_left_alone(sigma):
    y, x = _grid(64)
    z = 30.0 + DEPTH_SCALE * np.sqrt(40.0**2 - (x - 30.0) ** 2)
    z += np.random.default_rng(4).normal(0.0, sigma, z.shape)
    labels = np.ones(z.shape, np.int32)
    assert np.array_equal(recut_regions(z, labels, CONFIG, noise=max(sigma, 0.3)), labels)


def test_split_tangent_returns_the_plane_side_and_split_crease_the_crease_side():
    z, truth = _plane_and_fillet(1.0)
    got = split_tangent(z, np.ones(z.shape, bool), noise=1.0, level=1.25,
                        min_pixels=20, grow=CONFIG.grow)
    assert got is not None
    side, gain = got
    assert gain > 0.15
    assert np.mean(side[truth == 1]) > 0.95 and np.mean(side[truth == 2]) < 0.05
    z, truth = _crease(1.0, 1.5)
    side = split_crease(z, np.ones_like(truth), 1, 0, noise=1.0, level=1.25, config=CONFIG)
    assert side is not None
    # two planes: either may be the side before the line
    assert min(np.mean(side != (truth == 1)), np.mean(side != (truth == 2))) < 0.05


def test_labels_without_regions_and_bad_shapes():
    z, truth = _plane_and_fillet(0.0)
    assert np.all(recut_regions(z, np.zeros_like(truth), CONFIG, noise=0.3) == 0)
    with pytest.raises(ValueError):
        recut_regions(z, truth[:, :10], CONFIG, noise=0.3)


@pytest.mark.parametrize("sigma", [0.0, 1.0])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_refinement_finds_a_plane_and_its_fillet_grown_as_one_only_with_the_recut(
        sigma, seed):
    """A plane left tangentially by a cylinder (part1's block top and fillet in
    proportion), grown as one region: no other pass cuts it at the tangent line."""
    z, truth = _plane_and_fillet(sigma, seed)
    one = np.ones_like(truth)
    assert _correct(truth, _refined(z, one, CONFIG, sigma)) == 2
    assert _correct(truth, _refined(z, one, OFF, sigma)) < 2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_refinement_cuts_two_planes_at_a_crease_grown_as_one_at_sigma_2(seed):
    """A frustum's top and side (slope change 1.5 per pixel) as one region at sigma 2:
    the recut finds both; without it neither is a correct detection."""
    z, truth = _crease(2.0, 1.5, seed)
    one = np.ones_like(truth)
    assert _correct(truth, _refined(z, one, CONFIG, 2.0)) == 2
    assert _correct(truth, _refined(z, one, OFF, 2.0)) == 0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_refinement_gives_a_strip_back_across_a_crease_at_sigma_2(seed):
    """Two planes at a crease, the 5 columns before it given to the far plane (a chamfer
    that lost its strip). Without the boundary refinement and the recovery, which also
    give it back (test_refine.py), only the recut does."""
    z, truth = _crease(2.0, 1.5, seed)
    x = _grid(z.shape[1])[1]
    labels = np.where(x < KNOT - 5, 1, 2).astype(np.int32)
    alone = passes_without("boundaries", "recover")
    assert _correct(truth, _refined(z, labels, alone, 2.0)) == 2
    assert _correct(truth, _refined(z, labels, passes_without("recut", base=alone), 2.0)) == 0


def test_paper_preset_turns_it_off():
    assert "recut" not in load_config(preset="paper").refine.passes
    assert "recut" in CONFIG.refine.passes


def test_searching_within_a_box_finds_the_same_cuts():
    """The pipeline passes each candidate's box; the cut is the one the whole image gives."""
    z, truth = _plane_and_fillet(0.5)
    z = np.pad(z, ((7, 9), (5, 11)), constant_values=60.0)  # the candidate away from the corner
    labels = np.pad(truth, ((7, 9), (5, 11)))
    mask = labels > 0
    box = (slice(7, 7 + truth.shape[0]), slice(5, 5 + truth.shape[1]))
    kwargs = {"noise": 0.5, "level": 1.25 * 0.5, "min_pixels": 20, "grow": CONFIG.grow}
    whole = split_tangent(z, mask, **kwargs)
    boxed = split_tangent(z, mask, **kwargs, box=box)
    assert whole is not None and boxed is not None
    np.testing.assert_array_equal(whole[0], boxed[0])
    assert whole[1] == boxed[1]
    crease_z, crease_truth = _crease(1.0, 1.5)
    one = np.pad(np.ones_like(crease_truth), 4)  # both planes as one region
    crease_z = np.pad(crease_z, 4, constant_values=60.0)
    crease_box = (slice(4, 4 + crease_truth.shape[0]), slice(4, 4 + crease_truth.shape[1]))
    cut = {"noise": 1.0, "level": 1.25, "config": CONFIG}
    whole_side = split_crease(crease_z, one, 1, 0, **cut)
    boxed_side = split_crease(crease_z, one, 1, 0, **cut, box=crease_box)
    assert whole_side is not None and boxed_side is not None
    np.testing.assert_array_equal(whole_side, boxed_side)


def test_crease_side_within_a_box_is_the_whole_images_on_its_grid():
    z, truth = _crease(1.0, 1.5)
    padded = np.pad(z, ((3, 6), (8, 2)), constant_values=60.0)
    mask = np.pad(np.ones(truth.shape, bool), ((3, 6), (8, 2)))
    box = (slice(3, 3 + truth.shape[0]), slice(8, 8 + truth.shape[1]))
    kwargs = {"noise": 1.0, "level": 1.25, "min_pixels": 20,
              "min_crease": CONFIG.split.min_crease, "grow": CONFIG.grow}
    whole = crease_side(padded, mask, **kwargs)
    boxed = crease_side(padded, mask, **kwargs, box=box)
    assert whole is not None and boxed is not None
    assert boxed.shape == mask.shape and not boxed[~mask].any()
    np.testing.assert_array_equal(whole, boxed)
