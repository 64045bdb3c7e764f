"""The region graph: fits of unions from moment sums, kept current through merges."""

from __future__ import annotations

import numpy as np
import pytest

from rangeseg_cli.refine.graph import (
    RegionGraph,
    merge_cheapest,
    merge_ranked,
    region_graph,
)
from rangeseg_cli.stages.grow import fit_quadrics


def _pixel_fit(z: np.ndarray, mask: np.ndarray, order: int) -> tuple[np.ndarray, float]:
    coeffs, mse, _ = fit_quadrics(z, mask.astype(np.int32), 1, order=order)
    return coeffs[1], float(mse[1])


def _scene(rng: np.random.Generator, trial: int) -> tuple[np.ndarray, np.ndarray]:
    """Three regions (a step, curvature, noise, holes, NaNs) on a random grid."""
    h, w = (int(v) for v in rng.integers(20, 100, 2))
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    z = (50.0 + rng.normal(0.0, 3.0) * x / w * 10.0 + 0.02 * rng.normal() * (x - w / 2) ** 2
         + 0.01 * rng.normal() * x * y + rng.normal(0.0, rng.uniform(0.0, 2.0), (h, w))
         + np.where(x > w * rng.uniform(0.3, 0.7), rng.uniform(0.0, 20.0), 0.0))
    if trial % 4 == 0:
        z = np.round(z)  # 8-bit steps, noise-free: the smallest errors
    labels = np.where(x < int(w * rng.uniform(0.2, 0.8)), 1, 2).astype(np.int32)
    labels[y > h * rng.uniform(0.3, 0.7)] = 3
    labels[rng.random((h, w)) < 0.05] = 0
    if trial % 3 == 0:
        z[rng.random((h, w)) < 0.02] = np.nan
        labels[~np.isfinite(z)] = 0
    return z, labels


@pytest.mark.parametrize("order", [2, 1])
def test_union_fits_from_moments_are_the_fits_of_the_union_pixels(order: int) -> None:
    rng = np.random.default_rng(0)
    for trial in range(60):
        z, labels = _scene(rng, trial)
        graph = region_graph(z, labels, 3)
        coeffs, mse = graph.union_fit(1, 2, order)
        want_coeffs, want = _pixel_fit(z, (labels == 1) | (labels == 2), order)
        assert mse == pytest.approx(want, rel=1e-8, abs=1e-9)
        assert graph.union_mse(1, 2, order) == mse
        np.testing.assert_allclose(coeffs, want_coeffs, rtol=1e-6, atol=1e-8)


def test_a_joined_group_fits_as_its_pixels_and_keeps_the_smallest_id() -> None:
    rng = np.random.default_rng(1)
    for trial in range(40):
        z, labels = _scene(rng, trial)
        graph = region_graph(z, labels, 3)
        assert graph.join(3, 2, own=0.5) == 2
        assert set(np.unique(graph.labels)) <= {0, 1, 2}
        assert graph.group.tolist() == [0, 1, 2, 2]
        assert graph.own[2] == 0.5
        both = (labels == 2) | (labels == 3)
        assert graph.counts[2] == both.sum()
        _, want = _pixel_fit(z, both, 2)
        assert graph.fit(2)[1] == pytest.approx(want, rel=1e-8, abs=1e-9)
        _, union = _pixel_fit(z, labels > 0, 2)  # the merged group with region 1
        assert graph.union_mse(1, 2) == pytest.approx(union, rel=1e-8, abs=1e-9)
        assert (graph.labels[graph.boxes[2]] == 2).sum() == both.sum()


def _strips(heights: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Vertical strips 1..k of 10 columns each, with the given heights."""
    z = np.concatenate(heights, axis=1)
    labels = np.repeat(np.arange(1, len(heights) + 1), 10)[None, :].repeat(z.shape[0], 0)
    return z, labels.astype(np.int32)


def _gain(g: RegionGraph, a: int, b: int) -> float:
    return g.excess(a, b, g.union_mse(a, b)) / (g.counts[a] + g.counts[b])


def test_merge_cheapest_joins_one_plane_and_keeps_a_crease() -> None:
    # Four strips: three of one plane, then a plane at a crease along the
    # third's edge. Merging while one quadric adds < 0.5 per pixel joins
    # the three and leaves the fourth.
    rng = np.random.default_rng(2)
    y, x = np.mgrid[0:30, 0:40].astype(np.float64)
    z = np.where(x < 30, 2.0 * x, 60.0 + 8.0 * (x - 30)) + 0.5 * y
    z = z + rng.normal(0.0, 0.3, z.shape)
    labels = (x // 10 + 1).astype(np.int32)
    graph = region_graph(z, labels, 4)
    seen: list[tuple[int, int]] = []

    def accept(g: RegionGraph, a: int, b: int) -> float | None:
        seen.append((a, b))
        return g.union_mse(a, b)

    assert merge_cheapest(graph, [(1, 2), (2, 3), (3, 4)], _gain, accept, limit=0.5)
    assert np.unique(graph.labels[labels < 4]).tolist() == [1]
    assert np.unique(graph.labels[labels == 4]).tolist() == [4]
    assert len(seen) == 2  # two merges; the crease costs 0.5 or more: never judged
    assert _gain(graph, 1, 4) >= 0.5


def test_merge_cheapest_without_accept_changes_nothing() -> None:
    z, labels = _strips([np.ones((5, 10)), np.ones((5, 10))])
    graph = region_graph(z, labels, 2)
    assert not merge_cheapest(graph, [(1, 2)], _gain, lambda g, a, b: None)
    np.testing.assert_array_equal(graph.labels, labels)


def test_merge_ranked_judges_each_pair_once_on_its_groups() -> None:
    z, labels = _strips([np.full((5, 10), float(k)) for k in range(4)])
    graph = region_graph(z, labels, 4)
    calls: list[tuple[int, int, int, int]] = []

    def judge(g: RegionGraph, a: int, b: int, i: int, j: int, cost: float) -> float | None:
        calls.append((a, b, i, j))
        return 0.0 if (i, j) != (3, 4) else None

    ranked = [(0.1, 1, 2), (0.2, 2, 3), (0.3, 1, 3), (0.4, 3, 4)]
    assert merge_ranked(graph, ranked, judge)
    # (1, 3) is already one group when its turn comes: not judged.
    assert calls == [(1, 2, 1, 2), (1, 3, 2, 3), (1, 4, 3, 4)]
    assert np.unique(graph.labels[labels < 4]).tolist() == [1]
    assert np.unique(graph.labels[labels == 4]).tolist() == [4]
