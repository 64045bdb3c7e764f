"""The real SR300 depth frame in sample_data/arc: the holdsite lands on an object.

Hand-checked expectation (looking at the height image and the overlay): the
items lie between the walls that rise along the left (columns < 165) and
right (columns > 465) of the frame; the tote floor behind them is at about
650 mm. The frame is run as a cell would run it: its settings
(``suction.toml``: units, intrinsics, a 21x21 px cup) and the empty tote's
frame as the background (``[workspace] background``). Alone, the frame's
dominant plane is ambiguous (flat items cover most of the floor; a layer of
them is 14 mm above it) and the site is on an item or there is "nothing to
pick" by a hair (tests/test_real_cells.py checks both cameras).
"""

import os
from pathlib import Path

import numpy as np
import pytest

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.batch import io

ARC = Path(__file__).resolve().parent.parent / "sample_data" / "arc"


@pytest.fixture(scope="module")
def result():
    config = load_config(ARC / "suction.toml")
    raw = io.read_image(ARC / "suction-scene.depth.png")
    empty = io.read_image(ARC / "empty" / "suction-background.depth.png")
    return raw, config, run_pipeline(raw, config, background=empty)


def test_real_frame_holdsite_lands_on_an_item_between_the_tote_walls(result):
    raw, config, res = result
    site = res.holdsite.to_dict()["holdsite"]
    assert site is not None
    assert 170 <= site["col"] <= 460


def test_real_frame_holdsite_window_is_all_valid_readings_on_one_surface(result):
    raw, config, res = result
    site = res.holdsite.to_dict()["holdsite"]
    h, w = config.holdsite.size
    r, c = site["row"], site["col"]
    window = (slice(r - h // 2, r + h // 2 + 1), slice(c - w // 2, c + w // 2 + 1))
    assert (raw[window] > 0).all()
    assert np.unique(res.labels[window]).tolist() == [site["surface"]]


def test_real_frame_holdsite_is_above_the_tote_floor_not_on_it(result):
    raw, config, res = result
    site = res.holdsite.to_dict()
    # the tote floor (or its largest piece, and what merged into it): the largest surface
    # between the walls at 640 mm or more (with thresholds that follow the camera, issue 32,
    # the left wall is the largest surface of all)
    floor = max((s for s in res.surfaces if s.mean_height < -640.0 and 165 <= s.centroid[1] <= 465),
                key=lambda s: s.pixels)
    assert site["holdsite"]["surface"] != floor.id
    assert floor.id in site["background"] or site["holdsite"]["object"] != floor.id
    # the item's top is nearer the camera than the floor by several cm (heights = -depth mm)
    assert site["holdsite"]["elevation"] > floor.mean_height + 20.0
    x, y, zc = site["holdsite"]["point_camera"]
    empty = io.read_image(ARC / "empty" / "suction-background.depth.png")
    tote = empty[site["holdsite"]["row"], site["holdsite"]["col"]] * 1e-4  # 0.1 mm -> m
    assert 0.4 < zc < tote - 0.02  # metres from the camera: nearer than the empty tote


def test_real_frame_labels_are_the_same_with_forked_processes_and_one_thread(result,
                                                                              monkeypatch):
    from rangeseg_cli.kernels import parallel

    raw, config, _ = result
    forks = []
    real_fork = os.fork
    monkeypatch.setattr(os, "fork", lambda: forks.append(1) or real_fork())
    parallel.set_threads(2)
    forked = run_pipeline(raw, config)
    assert len(forks) >= 2  # the split's and the recut's many pieces went to a child
    parallel.set_threads(1)
    alone = run_pipeline(raw, config)
    np.testing.assert_array_equal(forked.labels, alone.labels)
    assert forked.holdsite.to_dict() == alone.holdsite.to_dict()


def test_the_arc_bin_height_map_needs_its_units_and_then_gives_an_item():
    # The ARC bin's orthographic height map (0.1 mm above the floor, 0 = floor). Read in
    # raw units the paper's thresholds (6 units = 0.6 mm) make every bump an edge: the
    # hint says so and there is nothing to pick; in mm the site is on an item's top.
    from rangeseg_cli.stages.rangeimage import fine_units_hint

    raw = io.read_image(ARC / "bin-heightmap.depth.png")
    assert "16-bit heights spanning 0..700" in fine_units_hint(raw, load_config().input)
    assert run_pipeline(raw, load_config()).holdsite.holdsite is None
    site = run_pipeline(raw, load_config(overrides={"input": {"scale": 0.1}})).holdsite.holdsite
    assert site is not None
    (r, c), (h, w) = (site.row, site.col), site.size
    window = raw[r - h // 2:r + h // 2 + 1, c - w // 2:c + w // 2 + 1]
    assert window.shape == (h, w) and window.min() >= 100  # 10 mm or more above the floor
