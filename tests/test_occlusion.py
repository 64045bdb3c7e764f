"""Patches of one surface divided by something in front are joined (rangeseg_cli.refine.occlusion)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from conftest import passes_without
from rangeseg_cli.config import load_config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.refine.occlusion import join_occluded

CONFIG = load_config()
BAR = slice(25, 35)  # columns of the strip between the two patches


def _scene(left: np.ndarray, right: np.ndarray, between: float | np.ndarray, sigma: float,
           seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Heights of two patches (columns 0-24 and 35-59) and a strip between; labels 1, 2, 3."""
    y, x = np.mgrid[0:40, 0:60].astype(np.float64)
    z = np.where(x < 30, left, right).astype(np.float64)
    z[:, BAR] = np.broadcast_to(between, z.shape)[:, BAR]
    z = z + (np.random.default_rng(seed).normal(0.0, sigma, z.shape) if sigma else 0.0)
    labels = np.where(x < 30, 1, 2).astype(np.int32)
    labels[:, BAR] = 3
    return z, labels


def _plane() -> np.ndarray:
    y, x = np.mgrid[0:40, 0:60].astype(np.float64)
    return 50.0 + 0.4 * x + 0.2 * y


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_a_plane_under_a_bar_laid_across_it_is_one_region(sigma):
    z, labels = _scene(_plane(), _plane(), 120.0, sigma)
    out = join_occluded(z, labels, CONFIG, noise=max(sigma, 0.5))
    assert out[0, 0] == out[0, -1] != out[0, 30]
    assert len(np.unique(out)) == 2
    np.testing.assert_array_equal(out > 0, labels > 0)


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_a_curved_surface_under_a_bar_is_one_region(sigma):
    y, _ = np.mgrid[0:40, 0:60].astype(np.float64)
    trough = 80.0 - 0.05 * (y - 20.0) ** 2  # a parabolic cylinder lying along the columns
    z, labels = _scene(trough, trough, 140.0, sigma, seed=1)
    out = join_occluded(z, labels, CONFIG, noise=max(sigma, 0.5))
    assert out[5, 2] == out[5, -3] != out[5, 30]


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_two_coplanar_tops_with_the_floor_seen_between_them_stay_apart(sigma):
    """The surface is seen to end: two boxes of one height side by side."""
    z, labels = _scene(_plane(), _plane(), 10.0, sigma, seed=2)
    out = join_occluded(z, labels, CONFIG, noise=max(sigma, 0.5))
    np.testing.assert_array_equal(out, labels)


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.0])
def test_parallel_planes_at_other_heights_under_a_bar_stay_apart(sigma):
    z, labels = _scene(_plane(), _plane() + 8.0, 120.0, sigma, seed=3)
    out = join_occluded(z, labels, CONFIG, noise=max(sigma, 0.5))
    np.testing.assert_array_equal(out, labels)


def test_a_plane_and_a_slightly_tilted_one_under_a_bar_stay_apart():
    """One plane fits both within the fit test, but far worse than their own two."""
    y, x = np.mgrid[0:40, 0:60].astype(np.float64)
    z, labels = _scene(_plane(), _plane() + 0.04 * (x - 47), 120.0, 1.0, seed=4)
    out = join_occluded(z, labels, CONFIG, noise=1.0)
    np.testing.assert_array_equal(out, labels)
    untested = load_config(overrides={"refine": {"crease_evidence": 0.0}})
    assert len(np.unique(join_occluded(z, labels, untested, noise=1.0))) == 2


def test_without_a_noise_estimate_nothing_is_joined():
    z, labels = _scene(_plane(), _plane(), 120.0, 0.0)
    np.testing.assert_array_equal(join_occluded(z, labels, CONFIG, noise=math.nan), labels)


def test_small_patches_are_not_joined():
    z, labels = _scene(_plane(), _plane(), 120.0, 0.0)
    labels[:, :25] = np.where(np.arange(40)[:, None] < 36, 0, 1)  # 4 x 25 = 100 px: kept
    labels[:, 35:] = np.where(np.arange(40)[:, None] < 39, 0, 2)  # 1 x 25 = 25 px: kept
    few = load_config(overrides={"link": {"min_component": 30}})
    np.testing.assert_array_equal(join_occluded(z, labels, few, noise=0.5), labels)


def cylinder_under_a_bar(sigma: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder lying on a table (z = 30) along the columns, 40 rows across and 40
    high, with a bar (z about 150) laid across it at columns 42-53: a pile's cylinder
    crossed by another part. 8-bit rounded heights and the cylinder's pixels."""
    y, x = np.mgrid[0:80, 0:96].astype(np.float64)
    height = 2.0 * np.sqrt(np.clip(400.0 - (y - 40.0) ** 2, 0.0, None))
    bar = (x >= 42) & (x < 54)
    z = np.where(bar, 150.0 + 0.1 * y, 30.0 + height)
    z += np.random.default_rng(seed).normal(0.0, sigma, z.shape)
    return np.clip(np.round(z), 0.0, 255.0), ~bar & (height > 1.0)


@pytest.mark.parametrize("seed", range(3))
def test_a_cylinder_crossed_by_a_bar_is_one_region_by_the_pipeline(seed):
    """The whole pipeline at sigma 2: the cylinder's two patches get one label with the
    pass (all but a few pixels), and two labels of half the pixels each without it."""
    z, side = cylinder_under_a_bar(2.0, seed)

    def shares(config):
        labels = run_pipeline(z, config, stages=3).labels[side]
        counts = np.bincount(labels[labels > 0])
        return sorted((counts[counts > 0] / side.sum()).tolist(), reverse=True)

    assert shares(CONFIG)[0] > 0.99
    assert [round(s, 1) for s in shares(passes_without("join_occluded"))[:2]] == [0.5, 0.5]


def test_the_paper_preset_joins_nothing():
    # the old key [split] join_occluded is refused naming refine.passes: tests/test_config.py
    assert "join_occluded" not in load_config(preset="paper").refine.passes
    assert "join_occluded" in CONFIG.refine.passes


@pytest.mark.parametrize("seed", range(4))
def test_the_screen_in_row_blocks_is_the_whole_matrix_screen(seed, monkeypatch):
    # The (n, n) screen took gigabytes on a 5 MP frame of thousands of regions; in
    # blocks of rows it keeps the same pairs in the same order.
    from rangeseg_cli.refine import occlusion
    from rangeseg_cli.stages.grow import evaluate_quadric

    rng = np.random.default_rng(seed)
    n = 37
    coeffs = rng.normal(0, 1, (n, 6)) * [50, 0.5, 0.5, 0.002, 0.002, 0.002]
    coeffs[::3] = coeffs[0]  # some surfaces shared: pairs to keep
    rows, cols = rng.uniform(0, 200, n), rng.uniform(0, 300, n)
    at = evaluate_quadric(coeffs[:, None, :], rows[None, :], cols[None, :])
    off = np.abs(at - np.diag(at)[None, :])
    want = np.nonzero(np.triu(np.minimum(off, off.T) <= 5.0, 1))
    monkeypatch.setattr(occlusion, "SCREEN_ROWS", 5)
    got = occlusion.screened_pairs(coeffs, rows, cols, 5.0)
    assert want[0].size > 0
    np.testing.assert_array_equal(got[0], want[0])
    np.testing.assert_array_equal(got[1], want[1])


def test_a_groups_border_found_in_its_own_box_is_the_one_in_any_larger_box():
    # Each pair's test found both borders again in the pair's box (a binary erosion
    # of up to the whole frame per pair: 108 of 158 s on a 5 MP frame).
    from rangeseg_cli.refine import occlusion
    from rangeseg_cli.refine.graph import region_graph

    rng = np.random.default_rng(3)
    labels = ndimage_label_blobs(rng)
    n = int(labels.max())
    graph = region_graph(np.zeros(labels.shape), labels, n)
    cache: dict = {}
    for a in range(1, n + 1):
        got = occlusion.group_border(graph, a, cache)
        for box in ((slice(0, 60), slice(0, 80)), occlusion.join_box(graph.boxes[a],
                                                                     graph.boxes[n + 1 - a])):
            start = np.array([box[0].start, box[1].start])
            np.testing.assert_array_equal(got - start,
                                          occlusion._border(labels[box] == a))
    keep = graph.join(1, 2, 0.0)  # a group that grew is found again, not taken from the cache
    whole = occlusion._border(graph.labels == keep)
    np.testing.assert_array_equal(occlusion.group_border(graph, keep, cache), whole)


def ndimage_label_blobs(rng: np.random.Generator) -> np.ndarray:
    """Labels of random blobs on a 60 x 80 grid (some touching the frame)."""
    from scipy import ndimage

    noise = ndimage.gaussian_filter(rng.normal(size=(60, 80)), 3)
    labels, _ = ndimage.label(noise > 0.05)
    return labels.astype(np.int32)
