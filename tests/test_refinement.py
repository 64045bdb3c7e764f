"""Issue 33: cut, merge and assign of the refinement (rangeseg_cli.refine.passes) with known answers.

Every scene is built here with numpy from analytic surfaces (heights in depth
units, larger = closer), optionally with Gaussian noise of a fixed seed, and
quantised to integers as an 8-bit sensor gives them. The whole pipeline runs
with the defaults and without the refinement (``--preset paper``, or the
defaults with ``[refine] passes = []``), and the labels are compared with the
truth. Angles are between the normals of the height map ``z(row, col)`` with
one depth unit per pixel, as the refinement measures them
(:func:`rangeseg_cli.stages.grow.plane_angle`, ``[refine] min_crease``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import ndimage

from rangeseg_cli import pipeline
from rangeseg_cli.config import REFINE_PASSES, Config, load_config
from rangeseg_cli.errors import ConfigError
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.refine import passes as refinement
from rangeseg_cli.refine.fill import fill_edges
from rangeseg_cli.refine.recut import crease_side

N = 128
DEFAULTS = load_config()
PAPER = load_config(preset="paper")
UNREFINED = load_config(overrides={"refine": {"passes": []}})  # the defaults, no pass
ASSIGNS = {p.name for p in refinement.PASSES if p.op == "assign"}
WITHOUT_ASSIGNS = load_config(overrides={"refine": {
    "passes": [name for name in REFINE_PASSES if name not in ASSIGNS]}})
CREASE = 15.0  # degrees between the normals: above min_crease (10), missed by the paper's edges


def _grid() -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:N, 0:N].astype(np.float64)
    return y, x


def _finish(z: np.ndarray, sigma: float, seed: int = 0) -> np.ndarray:
    """Add Gaussian noise of ``sigma`` depth units and quantise to 8 bits."""
    if sigma:
        z = z + np.random.default_rng(seed).normal(0.0, sigma, z.shape)
    return np.clip(np.round(z), 0.0, 255.0)


def _majority(labels: np.ndarray, mask: np.ndarray) -> tuple[int, float]:
    """The most frequent label under ``mask`` and the fraction of ``mask`` it covers."""
    counts = np.bincount(labels[mask])
    return int(counts.argmax()), float(counts.max() / mask.sum())


def _inside(mask: np.ndarray, width: int) -> np.ndarray:
    """``mask`` without the pixels within ``width`` of its border (or the image's)."""
    return ndimage.binary_erosion(mask, iterations=width, border_value=0)


def roof(angle: float, sigma: float = 0.0, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two planes meeting at a ridge along column 63.5 at ``angle`` degrees; truth 1 | 2."""
    y, x = _grid()
    slope = math.tan(math.radians(angle / 2.0))
    z = 100.0 + 0.1 * y - slope * np.abs(x - 63.5)
    return _finish(z, sigma, seed), np.where(x < 63.5, 1, 2).astype(np.int32)


def _sides(labels: np.ndarray, truth: np.ndarray) -> list[tuple[int, float]]:
    """Majority label and its share on each side of the ridge, 2 pixels from the ridge."""
    return [_majority(labels, _inside(truth == side, 2)) for side in (1, 2)]


# ------------------------------------------------------------------ cut


def test_two_planes_at_a_shallow_crease_are_cut_apart():
    z, truth = roof(CREASE)
    (left, left_share), (right, right_share) = _sides(run_pipeline(z, DEFAULTS).labels, truth)
    assert left != right
    assert left > 0 and right > 0
    assert left_share >= 0.9 and right_share >= 0.9


@pytest.mark.parametrize("config", [PAPER, UNREFINED], ids=["paper", "defaults-without-passes"])
def test_without_the_refinement_a_shallow_crease_is_one_region(config: Config):
    """The paper's roof edges miss the ridge, so growing makes one region: the cut is the refinement's."""
    z, truth = roof(CREASE)
    (left, left_share), (right, right_share) = _sides(run_pipeline(z, config).labels, truth)
    assert left == right > 0
    assert left_share >= 0.9 and right_share >= 0.9


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_a_crease_of_a_few_degrees_is_cut_once_min_crease_is_below_it(sigma: float):
    # 6 degrees: below the default min_crease (10), above 3
    fine = load_config(overrides={"refine": {"min_crease": 3.0}})
    z, truth = roof(6.0, sigma, seed=1)
    (left, _), (right, _) = _sides(run_pipeline(z, fine, stages=3).labels, truth)
    assert left != right and left > 0 and right > 0
    (left, _), (right, _) = _sides(run_pipeline(z, DEFAULTS, stages=3).labels, truth)
    assert left == right > 0


def cylinder(sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A half cylinder of radius 40 lying along the columns on a tilted plane; its mask."""
    y, x = _grid()
    across = x - 63.5
    mask = np.abs(across) < 40.0
    bulge = np.sqrt(np.maximum(1600.0 - across**2, 0.0))
    return _finish(30.0 + 0.15 * x + 0.1 * y + bulge, sigma, seed), mask


def cap(sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A spherical cap (sphere of radius 60, 30 high, 52 wide) on a tilted plane; its mask."""
    y, x = _grid()
    bulge = np.maximum(np.sqrt(np.maximum(3600.0 - (x - 63.5) ** 2 - (y - 63.5) ** 2, 0.0))
                       - 30.0, 0.0)
    return _finish(30.0 + 0.15 * x + 0.1 * y + bulge, sigma, seed), bulge > 0


@pytest.mark.parametrize("sigma", [0.0, 1.0])
@pytest.mark.parametrize("scene", [cylinder, cap], ids=["cylinder", "cap"])
def test_a_curved_surface_is_not_cut(scene, sigma: float):
    z, mask = scene(sigma, seed=1)
    labels = run_pipeline(z, DEFAULTS).labels
    curved, share = _majority(labels, _inside(mask, 3))
    plane, _ = _majority(labels, _inside(~mask, 3))
    assert share >= 0.9
    assert curved not in (0, plane)


# ------------------------------------------------------------------ merge


def plane_under_a_bar(sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A tilted plane with a bar 16 pixels wide standing on it across every row; truth
    1 (left patch), 2 (right patch), 3 (the bar's top)."""
    y, x = _grid()
    bar = (x >= 56) & (x < 72)
    z = np.where(bar, 200.0, 40.0 + 0.3 * x + 0.2 * y)
    truth = np.select([x < 56, bar], [1, 3], 2).astype(np.int32)
    return _finish(z, sigma, seed), truth


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_two_patches_of_a_plane_divided_by_an_occluder_are_one_surface(sigma: float):
    z, truth = plane_under_a_bar(sigma, seed=2)
    labels = run_pipeline(z, DEFAULTS).labels
    (left, left_share), (right, right_share), (bar, _) = (
        _majority(labels, _inside(truth == k, 2)) for k in (1, 2, 3))
    assert left == right > 0
    assert left_share >= 0.9 and right_share >= 0.9
    assert bar not in (0, left)


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
@pytest.mark.parametrize("config", ["paper", "no passes", "no join_occluded"])
def test_without_join_occluded_the_patches_beside_an_occluder_stay_apart(config: str,
                                                                        sigma: float):
    configs = {"paper": PAPER, "no passes": UNREFINED,
               "no join_occluded": _passes(*(p for p in REFINE_PASSES if p != "join_occluded"))}
    z, truth = plane_under_a_bar(sigma, seed=2)
    labels = run_pipeline(z, configs[config], stages=3).labels
    left, right = (_majority(labels, _inside(truth == k, 2))[0] for k in (1, 2))
    assert left != right


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
@pytest.mark.parametrize("between", ["floor", "offset"])
def test_patches_across_a_gap_or_a_step_are_not_joined(between: str, sigma: float):
    # "floor": the bar is a trench, nothing in front; "offset": the right patch is 4 higher
    y, x = _grid()
    bar = (x >= 56) & (x < 72)
    plane = 40.0 + 0.3 * x + 0.2 * y + (4.0 * (x >= 72) if between == "offset" else 0.0)
    z = _finish(np.where(bar, 10.0 if between == "floor" else 200.0, plane), sigma, seed=2)
    labels = run_pipeline(z, DEFAULTS, stages=3).labels
    (left, left_share), (right, right_share) = (
        _majority(labels, _inside(m, 2)) for m in (x < 56, x >= 72))
    assert left != right and left > 0 and right > 0
    assert min(left_share, right_share) >= 0.9


# ------------------------------------------------------------------ assign


def box_on_a_plane(sigma: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A box 48 x 68 pixels, 40 above a tilted plane, its top tilted the other way;
    truth 1 (the plane) and 2 (the box's top)."""
    y, x = _grid()
    plane = 40.0 + 0.2 * x + 0.1 * y
    box = (y >= 40) & (y < 88) & (x >= 30) & (x < 98)
    z = np.where(box, plane + 40.0 - 0.1 * x, plane)
    return _finish(z, sigma, seed), np.where(box, 2, 1).astype(np.int32)


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_edge_pixels_at_a_step_go_to_the_surface_they_lie_on(sigma: float):
    z, truth = box_on_a_plane(sigma, seed=3)
    labels = run_pipeline(z, DEFAULTS).labels
    unassigned = run_pipeline(z, WITHOUT_ASSIGNS).labels
    assert 0.0 < (unassigned == 0).mean()  # the step's edge pixels, left by growing and cuts
    assert (labels == 0).mean() < 0.02
    assert (labels == 0).sum() <= 0.5 * (unassigned == 0).sum()
    # each surface's label, and every labelled pixel off the true boundary carries its own
    own = np.zeros(3, np.int32)
    own[1:] = [_majority(labels, truth == k)[0] for k in (1, 2)]
    assert own[1] != own[2]
    off_boundary = ndimage.maximum_filter(truth, 3) == ndimage.minimum_filter(truth, 3)
    judged = (labels > 0) & off_boundary
    np.testing.assert_array_equal(labels[judged], own[truth[judged]])


@pytest.mark.parametrize("sigma", [0.0, 1.0])
def test_pixels_at_a_crease_go_to_the_face_they_lie_on(sigma: float):
    # A right-angle roof: beside the crease the two faces differ by 2 per pixel, so
    # each pixel has one face that predicts it; nothing is left unlabelled.
    z, truth = roof(90.0, sigma, seed=3)
    labels = run_pipeline(z, DEFAULTS, stages=3).labels
    own = np.array([0] + [_majority(labels, truth == k)[0] for k in (1, 2)])
    assert 0 not in own[1:] and own[1] != own[2]
    assert np.count_nonzero(labels == 0) <= 4
    judged = labels > 0
    np.testing.assert_array_equal(labels[judged], own[truth[judged]])


def test_the_labels_of_a_run_leave_nothing_to_fill():
    # The fill runs again after the merge and the recut: what their surfaces explain
    # joins them (without that second fill, 104 of the cylinder's pixels stay out).
    result = run_pipeline(cylinder(0.0)[0], DEFAULTS, stages=3)
    np.testing.assert_array_equal(fill_edges(result.heights, result.labels, DEFAULTS.grow),
                                  result.labels)


# ------------------------------------------------------------------ noise


@pytest.mark.parametrize(("angle", "sigma"), [
    (CREASE, 1.0),
    (CREASE, 2.0),  # 0.09 noise variances per pixel, 1,460 in all: cut by its total gain
    (25.0, 2.0),
], ids=["15deg-sigma1", "15deg-sigma2", "25deg-sigma2"])
def test_a_shallow_crease_in_noise_is_still_cut(angle: float, sigma: float):
    z, truth = roof(angle, sigma, seed=4)
    (left, left_share), (right, right_share) = _sides(run_pipeline(z, DEFAULTS).labels, truth)
    assert left != right
    assert left > 0 and right > 0
    assert left_share >= 0.9 and right_share >= 0.9


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("sigma", [0.5, 2.0])
def test_the_crease_model_cuts_a_wide_shallow_crease_and_never_a_plane_of_noise(seed, sigma):
    # The crease's gain over one quadric is small per pixel but adds up over a wide
    # region (recut.TOTAL_GAIN); a plane's noise alone never gains that much.
    y, x = _grid()
    level = DEFAULTS.split.fit_factor * max(sigma, math.sqrt(DEFAULTS.grow.min_error))

    def side(z: np.ndarray) -> np.ndarray | None:
        return crease_side(z, np.ones(z.shape, bool), noise=sigma, level=level,
                           min_pixels=DEFAULTS.split.min_piece,
                           min_crease=DEFAULTS.split.min_crease, grow=DEFAULTS.grow)

    assert side(_finish(100.0 + 0.1 * y - 0.13 * x, sigma, seed=seed)) is None
    z, truth = roof(CREASE, sigma, seed=seed)
    cut = side(z)
    assert cut is not None
    left = cut[truth == 1].mean()
    assert min(left, 1.0 - left) < 0.02 and abs(cut[truth == 2].mean() - (1.0 - left)) < 0.02


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_a_plane_in_noise_is_not_cut(sigma: float):
    y, x = _grid()
    z = _finish(100.0 + 0.1 * y - 0.13 * x, sigma, seed=5)
    label, share = _majority(run_pipeline(z, DEFAULTS).labels, np.ones((N, N), bool))
    assert label > 0 and share >= 0.99


# ------------------------------------------------------------------ the table


def _passes(*names: str) -> Config:
    return load_config(overrides={"refine": {"passes": list(names)}})


def test_the_paper_preset_runs_no_pass():
    assert refinement.active_passes(PAPER) == ()
    assert not refinement.uses_noise(PAPER)
    assert not refinement.shares_work(PAPER)
    assert not pipeline.uses_noise(PAPER)


def test_each_pass_is_the_cut_merge_or_assign_of_issue_33():
    ops = {p.name: p.op for p in refinement.PASSES}
    assert {name for name, op in ops.items() if op == "cut"} == {
        "split", "recover", "recut", "chamfers", "carve", "facets"}
    assert {name for name, op in ops.items() if op == "merge"} == {
        "merge", "merge_planes", "join_occluded"}
    assert {name for name, op in ops.items() if op == "assign"} == {
        "fill", "bridge", "boundaries", "leftovers"}


@pytest.mark.parametrize("name", [n for n in REFINE_PASSES if n != "bridge"])
def test_noise_and_threads_are_derived_from_the_passes_on(name: str):
    """All but the fill and the leftovers read the noise; the split, recovery, recut and facets
    share work."""
    config = _passes(name)
    assert [p.name for p in refinement.active_passes(config)] == [name]
    assert refinement.uses_noise(config) == (name not in ("fill", "leftovers"))
    assert refinement.shares_work(config) == (name in {"split", "recover", "recut", "facets"})


def test_the_bridge_runs_only_with_the_fill():
    with pytest.raises(ConfigError, match=r"^\[refine\] passes = \['bridge'\]: 'bridge' needs 'fill'"):
        _passes("bridge")
    assert {p.name for p in refinement.PASSES} == set(REFINE_PASSES)
    with_fill = _passes("fill", "bridge")
    assert [p.name for p in refinement.active_passes(with_fill)] == ["fill", "bridge"]
    assert not refinement.uses_noise(with_fill)
    assert refinement.uses_noise(_passes("fill", "bridge", "merge"))
    assert not refinement.shares_work(_passes("fill", "merge", "boundaries"))
    assert refinement.shares_work(_passes("fill", "split"))


def test_the_fill_runs_again_after_a_merge_or_a_recut():
    assert [p.name for p in refinement.active_passes(_passes("fill", "merge"))] == [
        "fill", "merge", "fill"]
    assert [p.name for p in refinement.active_passes(_passes("fill", "recut"))] == [
        "fill", "recut", "fill"]
    assert [p.name for p in refinement.active_passes(_passes("fill", "carve"))] == [
        "fill", "carve"]


def test_the_defaults_run_every_pass_in_the_order_of_the_table():
    assert set(DEFAULTS.refine.passes) == set(REFINE_PASSES)
    assert refinement.active_passes(DEFAULTS) == refinement.PASSES
