"""The region graph: regions, their neighbours and moment sums, kept current as they merge.

Beyond Al-Hujazi & Sood (1990). Region growing (Sec. V-4) fits each region
from its moment sums; the refinement (Sec. VIII's quality-of-fit test) asks,
again and again, whether one surface explains two regions together. The
graph keeps each region's sums (:class:`~rangeseg_cli.stages.grow.RegionMoments`)
and sum of squared heights, so that every such question is answered from
the sums of the two (:func:`~rangeseg_cli.stages.grow.union_moments`, a few
small matrix products) without visiting a pixel, and a merge adds the sums.

:func:`merge_cheapest` and :func:`merge_ranked` are the merges of the
refinement. The first takes the candidate pairs cheapest first (a priority
queue, as ``skimage.graph.merge_hierarchical``) and costs the new group's
pairs with its neighbours again after each merge; the second judges pairs
ranked once, each on the groups its regions then belong to. What "cheapest"
and "one surface" mean is the caller's: the merges of
:mod:`~rangeseg_cli.refine.merge`, :mod:`~rangeseg_cli.refine.facets` and
:mod:`~rangeseg_cli.refine.occlusion` and
:func:`~rangeseg_cli.refine.split.merge_back` pass their cost and test.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..stages.grow import (
    RegionFits,
    RegionMoments,
    image_coefficients,
    moment_fit,
    region_fits,
    sums_of_squares,
    union_moments,
)
from .regions import join_box


@dataclass
class RegionGraph:
    """Groups of regions of a label image with their moment sums (updated in place).

    Attributes
    ----------
    labels
        int32 (H, W): each pixel's group, the smallest region id in it (0 = none).
    moments
        The sums of each group at its id (rows of merged-away ids are stale).
    squares
        float64 (n+1,) sum of squared heights of each group.
    own
        float64 (n+1,) each group's own mean squared error, as its merge rule
        counts it (the caller's model: plane or quadric).
    boxes
        Bounding box of each group, by id.
    group
        int64 (n+1,) the group of each region of the labels the graph was made of.
    """

    labels: np.ndarray
    moments: RegionMoments
    squares: np.ndarray
    own: np.ndarray
    boxes: dict[int, tuple[slice, slice]]
    group: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """float64 (n+1,) pixels of each group."""
        return self.moments.counts

    def fit(self, k: int, order: int = 2) -> tuple[np.ndarray, float]:
        """Image coefficients a0..a5 and mean squared error of group k's surface."""
        m = self.moments
        coef, mse = moment_fit(m.sums[k], m.rhs[k], float(m.counts[k]), float(self.squares[k]),
                               order)
        return image_coefficients(coef, m.cx[k], m.cy[k], m.scale[k]), mse

    def union_mse(self, a: int, b: int, order: int = 2) -> float:
        """Mean squared error of one surface (``order`` 2 quadric, 1 plane) of groups a, b."""
        total, _, _, _, sums, rhs = union_moments(self.moments, a, b)
        return moment_fit(sums, rhs, total, float(self.squares[a] + self.squares[b]), order)[1]

    def union_fit(self, a: int, b: int, order: int = 2) -> tuple[np.ndarray, float]:
        """Image coefficients a0..a5 and mean squared error of one surface of groups a, b."""
        total, cx, cy, scale, sums, rhs = union_moments(self.moments, a, b)
        coef, mse = moment_fit(sums, rhs, total, float(self.squares[a] + self.squares[b]),
                               order)
        return image_coefficients(coef, cx, cy, scale), mse

    def excess(self, a: int, b: int, union_mse: float) -> float:
        """Squared error one surface of a, b (mean ``union_mse``) leaves beyond their own two."""
        c = self.counts
        return float(union_mse * (c[a] + c[b]) - self.own[a] * c[a] - self.own[b] * c[b])

    def join(self, a: int, b: int, own: float) -> int:
        """Merge groups a and b, whose union's own mean squared error is ``own``; its id."""
        keep, gone = min(a, b), max(a, b)
        m = self.moments
        total, cx, cy, scale, sums, rhs = union_moments(m, keep, gone)
        m.counts[keep], m.cx[keep], m.cy[keep], m.scale[keep] = total, cx, cy, scale
        m.sums[keep], m.rhs[keep] = sums, rhs
        self.squares[keep] += self.squares[gone]
        self.own[keep] = own
        box = join_box(self.boxes[keep], self.boxes.pop(gone))
        self.boxes[keep] = box
        sub = self.labels[box]
        sub[sub == gone] = keep
        self.group[self.group == gone] = keep
        return keep


def region_graph(z: np.ndarray, labels: np.ndarray, n: int, own: np.ndarray | None = None,
                 fitted: RegionFits | None = None) -> RegionGraph:
    """The graph of regions 1..n of ``labels`` (copied), each a group of its own.

    Parameters
    ----------
    z
        float64 (H, W) heights, finite on the labelled pixels.
    labels
        int (H, W) regions 0..n.
    n
        Largest label.
    own
        (n+1,) each region's own mean squared error (default: that of the
        first order of ``fitted``, the quadric when it is made here).
    fitted
        ``region_fits(z, labels, n, ...)`` when the caller has it.
    """
    fitted = fitted or region_fits(z, labels, n, (2,))
    m = fitted.moments
    moments = RegionMoments(m.counts.copy(), m.cx.copy(), m.cy.copy(), m.scale.copy(),
                            m.sums.copy(), m.rhs.copy())
    own = fitted.fits[0][1] if own is None else own
    boxes = {k: b for k, b in enumerate(ndimage.find_objects(labels), start=1) if b}
    return RegionGraph(np.array(labels, dtype=np.int32), moments,
                       sums_of_squares(z, labels, n), np.array(own, dtype=np.float64), boxes,
                       np.arange(n + 1))


Cost = Callable[[RegionGraph, int, int], float]
Accept = Callable[[RegionGraph, int, int], float | None]
Judge = Callable[[RegionGraph, int, int, int, int, float], float | None]


def merge_cheapest(graph: RegionGraph, pairs: Iterable[tuple[int, int]], cost: Cost,
                   accept: Accept, limit: float = np.inf) -> bool:
    """Merge neighbouring groups, cheapest pair first, while ``accept`` says so.

    Hierarchical: after a merge the new group's pairs with its neighbours
    are costed again.

    Parameters
    ----------
    graph
        Changed in place.
    pairs
        The neighbours (i < j): the edges of the graph. A merged group's
        neighbours are its members'.
    cost
        ``cost(graph, a, b)`` of two groups; pairs are taken in increasing
        cost (ties by ids).
    accept
        ``accept(graph, a, b)``: the merged group's own mean squared error
        when a and b are one surface, else None.
    limit
        Pairs costing this or more are never merged (the queue stops there).

    Returns
    -------
    bool
        Whether anything was merged.
    """
    near: dict[int, set[int]] = {}
    for i, j in pairs:
        near.setdefault(i, set()).add(j)
        near.setdefault(j, set()).add(i)
    stamp = dict.fromkeys(near, 0)
    queue = [(cost(graph, a, b), a, b, 0, 0) for a in near for b in near[a] if a < b]
    heapq.heapify(queue)
    merged = False
    while queue:
        c, a, b, sa, sb = heapq.heappop(queue)
        if c >= limit:
            break
        if stamp.get(a) != sa or stamp.get(b) != sb:
            continue  # a or b merged since this pair was costed
        own = accept(graph, a, b)
        if own is None:
            continue
        keep = graph.join(a, b, own)
        gone = a + b - keep
        merged = True
        others = (near.pop(a) | near.pop(b)) - {a, b}
        del stamp[gone]
        stamp[keep] += 1
        near[keep] = others
        for k in others:
            near[k].discard(gone)
            near[k].add(keep)
            lo, hi = min(k, keep), max(k, keep)
            heapq.heappush(queue, (cost(graph, lo, hi), lo, hi, stamp[lo], stamp[hi]))
    return merged


def merge_ranked(graph: RegionGraph, ranked: Iterable[tuple[float, int, int]], judge: Judge
                 ) -> bool:
    """Merge groups along pairs of regions ranked once, each pair judged once in that order.

    Parameters
    ----------
    graph
        Changed in place.
    ranked
        ``(cost, i, j)`` of pairs of regions (i < j), in the order they are judged.
    judge
        ``judge(graph, a, b, i, j, cost)`` of the groups a < b of regions i
        and j at their turn: the merged group's own mean squared error when
        they are one surface, else None.

    Returns
    -------
    bool
        Whether anything was merged.
    """
    merged = False
    for c, i, j in ranked:
        a, b = sorted((int(graph.group[i]), int(graph.group[j])))
        if a == b:
            continue
        own = judge(graph, a, b, i, j, c)
        if own is not None:
            graph.join(a, b, own)
            merged = True
    return merged
