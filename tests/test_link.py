"""Step 3: linking and 4-connected components (Sec. V-3)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from rangeseg_cli.config import LinkConfig
from rangeseg_cli.stages.edges import DIRECTIONS, LINKED_EDGE, ROOF_EDGE, STEP_EDGE
from rangeseg_cli.stages.link import FOUR_CONNECTED, label_components, link_edges

CFG = LinkConfig()


def _valid(shape: tuple[int, int] = (32, 32)) -> np.ndarray:
    return np.ones(shape, dtype=bool)


@pytest.mark.parametrize("direction", DIRECTIONS)
@pytest.mark.parametrize("code", [STEP_EDGE, ROOF_EDGE])
def test_one_pixel_gap_is_closed_in_each_direction(direction: tuple[int, int],
                                                   code: int) -> None:
    dy, dx = direction
    codes = np.zeros((32, 32), dtype=np.uint8)
    codes[16 - dy, 16 - dx] = code
    codes[16 + dy, 16 + dx] = code
    out, _ = link_edges(codes, _valid(), CFG)
    assert out[16, 16] == LINKED_EDGE
    assert np.count_nonzero(out == LINKED_EDGE) == 1
    assert out.dtype == np.uint8


def test_gap_between_step_and_roof_edge_is_closed() -> None:
    codes = np.zeros((32, 32), dtype=np.uint8)
    codes[10, 9], codes[10, 11] = STEP_EDGE, ROOF_EDGE
    out, _ = link_edges(codes, _valid(), CFG)
    assert out[10, 10] == LINKED_EDGE


def test_two_pixel_gap_is_not_closed() -> None:
    codes = np.zeros((32, 32), dtype=np.uint8)
    codes[10, 9], codes[10, 12] = STEP_EDGE, STEP_EDGE
    out, _ = link_edges(codes, _valid(), CFG)
    assert not np.any(out == LINKED_EDGE)


def test_knight_move_gap_is_not_closed_as_spec_says() -> None:
    # Edges at (1, 4) and (2, 2): no pixel has both neighbours along one direction
    # on an edge, so the one-pixel rule (SPEC 3) leaves this gap open.
    codes = np.zeros((32, 32), dtype=np.uint8)
    codes[1, 4], codes[2, 2] = ROOF_EDGE, ROOF_EDGE
    out, _ = link_edges(codes, _valid(), CFG)
    assert not np.any(out == LINKED_EDGE)


def test_gaps_are_closed_once_not_iteratively() -> None:
    # (5, 5) is a gap between (5, 4) and (5, 6). (6, 5) lies between the linked
    # pixel (5, 5) and the edge (7, 5): a second round would close it, one does not.
    codes = np.zeros((32, 32), dtype=np.uint8)
    codes[5, 4] = codes[5, 6] = codes[7, 5] = STEP_EDGE
    out, _ = link_edges(codes, _valid(), CFG)
    assert out[5, 5] == LINKED_EDGE
    assert out[6, 5] == 0
    assert np.count_nonzero(out == LINKED_EDGE) == 1


def test_linking_a_linked_map_gives_the_same_result() -> None:
    rng = np.random.default_rng(42)
    codes = rng.choice(np.array([0, 1, 2], dtype=np.uint8), size=(64, 64), p=[0.8, 0.1, 0.1])
    valid = rng.random((64, 64)) > 0.05
    once, comp_once = link_edges(codes, valid, LinkConfig(min_component=3))
    twice, comp_twice = link_edges(once, valid, LinkConfig(min_component=3))
    assert np.any(once == LINKED_EDGE)
    np.testing.assert_array_equal(once, twice)
    np.testing.assert_array_equal(comp_once, comp_twice)


def test_stray_linked_code_is_read_as_non_edge() -> None:
    codes = np.zeros((32, 32), dtype=np.uint8)
    codes[8, 8] = LINKED_EDGE  # no edge neighbours: not a gap
    out, comps = link_edges(codes, _valid(), CFG)
    assert out[8, 8] == 0
    assert comps[8, 8] == 1


def test_component_of_19_pixels_is_dropped_and_of_20_kept() -> None:
    # Bounded by invalid pixels rather than edges, so no gap closing nibbles the shapes.
    codes = np.zeros((20, 40), dtype=np.uint8)
    valid = np.zeros((20, 40), dtype=bool)
    valid[2, 2:21] = True  # 19 pixels
    valid[6, 2:22] = True  # 20 pixels
    valid[10:15, 2:6] = True  # 5 x 4 = 20 pixels
    _, comps = link_edges(codes, valid, CFG)
    assert np.all(comps[2, 2:21] == 0)
    assert np.all(comps[6, 2:22] == 1)
    assert np.all(comps[10:15, 2:6] == 2)
    assert comps.max() == 2
    assert comps.dtype == np.int32


def test_component_smaller_than_configured_minimum_is_dropped() -> None:
    codes = np.zeros((20, 20), dtype=np.uint8)
    valid = np.zeros((20, 20), dtype=bool)
    valid[2:7, 2:7] = True  # 25 pixels
    _, kept = link_edges(codes, valid, LinkConfig(min_component=25))
    _, dropped = link_edges(codes, valid, LinkConfig(min_component=26))
    assert kept.max() == 1 and dropped.max() == 0


def test_components_are_four_connected() -> None:
    # An 8-connected diagonal edge line separates the two triangles.
    codes = np.zeros((32, 32), dtype=np.uint8)
    idx = np.arange(32)
    codes[idx, idx] = ROOF_EDGE
    _, comps = link_edges(codes, _valid(), CFG)
    assert comps.max() == 2
    assert comps[0, 31] != comps[31, 0]


def test_components_are_numbered_in_raster_order_of_first_pixel() -> None:
    codes = np.zeros((30, 30), dtype=np.uint8)
    codes[:, 10] = STEP_EDGE
    codes[:, 20] = STEP_EDGE
    codes[15, :10] = STEP_EDGE  # left strip split into top and bottom
    _, comps = link_edges(codes, _valid((30, 30)), CFG)
    assert comps[0, 0] == 1 and comps[0, 15] == 2 and comps[0, 25] == 3
    assert comps[29, 0] == 4


def test_components_keep_their_first_pixels_order_where_parts_join_late() -> None:
    # label_components takes scipy's numbering as that order; a comb's teeth meet
    # only at the bottom, and random masks join runs in every way
    rng = np.random.default_rng(3)
    comb = np.ones((30, 40), dtype=bool)
    comb[:25, 1::2] = False
    for free in [comb, *(rng.random((37, 53)) < p for p in (0.45, 0.6, 0.75))]:
        raw, _ = ndimage.label(free, structure=FOUR_CONNECTED)
        ids, first, sizes = np.unique(raw, return_index=True, return_counts=True)
        for min_size in (1, 4):
            kept = [i for i in ids[np.argsort(first)] if i and sizes[ids == i][0] >= min_size]
            expected = np.zeros(raw.shape, dtype=np.int32)
            for k, i in enumerate(kept, start=1):
                expected[raw == i] = k
            np.testing.assert_array_equal(label_components(free, min_size), expected)


def test_invalid_pixels_are_never_edges_nor_labelled() -> None:
    codes = np.zeros((32, 32), dtype=np.uint8)
    valid = _valid()
    valid[:, 16] = False
    codes[4, 15], codes[4, 17] = STEP_EDGE, STEP_EDGE  # the gap (4, 16) is invalid
    codes[20, 16] = ROOF_EDGE  # an edge code on an invalid pixel is dropped
    out, comps = link_edges(codes, valid, CFG)
    assert out[4, 16] == 0 and out[20, 16] == 0
    assert np.all(comps[:, 16] == 0)
    assert comps[10, 5] != comps[10, 25]  # the invalid column separates


def test_rejects_mismatched_shapes_and_unknown_codes() -> None:
    with pytest.raises(ValueError, match="`valid`"):
        link_edges(np.zeros((8, 8), np.uint8), np.ones((8, 9), bool), CFG)
    with pytest.raises(ValueError, match="0..3"):
        link_edges(np.full((8, 8), 7, np.uint8), np.ones((8, 8), bool), CFG)
