"""Small holes of no reading are filled from the readings around them ([input] fill_holes).

A depth camera leaves scattered pixels without a reading (speckle); a suction
cup spans them. Constructed cases with a known answer, then the real SR300
frame of sample_data/arc with dropouts added.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.batch import io
from rangeseg_cli.config import InputConfig
from rangeseg_cli.stages.rangeimage import fill_small_holes, to_heights

ARC = Path(__file__).resolve().parent.parent / "sample_data" / "arc"


def tilted_plane(shape: tuple[int, int] = (40, 50)) -> np.ndarray:
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    return 100.0 + 0.7 * cols - 0.4 * rows


def test_single_pixel_holes_on_a_plane_get_the_plane_back():
    plane = tilted_plane()
    z = plane.copy()
    rng = np.random.default_rng(3)
    holes = rng.random(z.shape) < 0.03
    holes[0, :] = holes[-1, :] = holes[:, 0] = holes[:, -1] = False
    # keep the holes apart (each one pixel, all 8 neighbours read): the median is exact
    apart = holes & (np.add.reduce([np.roll(np.roll(holes, dr, 0), dc, 1)
                                    for dr in (-1, 0, 1) for dc in (-1, 0, 1)]) == 1)
    assert apart.sum() > 20
    z[apart] = np.nan
    out = fill_small_holes(z, 4)
    assert np.isfinite(out).all()
    np.testing.assert_allclose(out, plane, atol=1e-9)


def test_holes_larger_than_the_bound_stay_and_zero_is_off():
    z = tilted_plane()
    z[10:12, 10:12] = np.nan  # 4 pixels: filled
    z[20:23, 30:33] = np.nan  # 9 pixels: a shadow, kept
    z[30, 5:10] = np.nan  # a line of 5: kept
    off = fill_small_holes(z.copy(), 0)
    assert np.isnan(off).sum() == 4 + 9 + 5
    out = fill_small_holes(z.copy(), 4)
    assert np.isfinite(out[10:12, 10:12]).all()
    assert np.isnan(out[20:23, 30:33]).all() and np.isnan(out[30, 5:10]).all()
    # each filled pixel took the median of the readings among its 8 neighbours
    plane = tilted_plane()
    assert out[10, 10] == pytest.approx(np.median(plane[[9, 9, 9, 10, 11], [9, 10, 11, 9, 9]]))


def test_to_heights_fills_after_the_units_and_leaves_the_input_alone():
    raw = np.full((16, 16), 5000, np.uint16)
    raw[5, 5] = 0
    cfg = load_config(preset="tenth-mm-depth").input
    assert to_heights(raw, cfg)[5, 5] == pytest.approx(-500.0)
    assert np.isnan(to_heights(raw, replace(cfg, fill_holes=0))[5, 5])
    assert raw[5, 5] == 0
    assert load_config(preset="paper").input.fill_holes == 0
    assert InputConfig().fill_holes == 4


def box_with_speckle(fraction: float, seed: int = 0) -> np.ndarray:
    """A height map: a table at 20 and a 40x40 box top at 60, ``fraction`` of pixels NaN."""
    z = np.full((96, 96), 20.0)
    z[28:68, 28:68] = 60.0
    z += np.random.default_rng(seed).normal(0.0, 0.5, z.shape)
    z[np.random.default_rng(seed + 1).random(z.shape) < fraction] = np.nan
    return z


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_box_top_with_speckle_still_gets_the_site(seed):
    overrides = {"holdsite": {"size": [11, 11]}}
    z = box_with_speckle(0.08, seed)
    site = run_pipeline(z, load_config(overrides=overrides)).holdsite.holdsite
    assert site is not None and 28 <= site.row < 68 and 28 <= site.col < 68
    assert site.elevation == pytest.approx(60.0, abs=1.0)
    # unfilled, no 11x11 window of readings is left anywhere (8 % of pixels missing)
    off = load_config(overrides={**overrides, "input": {"fill_holes": 0}})
    assert run_pipeline(box_with_speckle(0.08, seed), off).holdsite.holdsite is None


@pytest.fixture(scope="module")
def sr300():
    config = load_config(ARC / "suction.toml")
    raw = io.read_image(ARC / "suction-scene.depth.png")
    empty = io.read_image(ARC / "empty" / "suction-background.depth.png")
    return raw, config, empty


@pytest.mark.parametrize("fraction", [0.02, 0.05])
def test_the_sr300_frame_with_dropouts_still_gets_a_site_on_an_item(sr300, fraction):
    raw, config, empty = sr300
    speckled = raw.copy()
    speckled[np.random.default_rng(7).random(raw.shape) < fraction] = 0
    res = run_pipeline(speckled, config, background=empty)
    site = res.holdsite.holdsite
    assert site is not None and len(res.holdsite.candidates) >= 3
    # between the tote's walls (columns 165-465), and 20 mm or more above its floor
    assert 165 < site.col < 465
    floor = np.median(empty[200:300, 250:400][empty[200:300, 250:400] > 0]) * 0.1
    assert -site.elevation < floor - 20.0


def test_a_hole_in_the_frames_corner_with_no_reading_beside_it_stays(recwarn):
    z = tilted_plane()
    z[:2, :2] = np.nan  # (0, 0) touches no reading: its neighbours are holes or off the frame
    out = fill_small_holes(z, 4)
    assert np.isnan(out[0, 0]) and np.isfinite(out[[0, 1, 1], [1, 0, 1]]).all()
    assert not [w for w in recwarn if issubclass(w.category, RuntimeWarning)]


def test_a_hole_at_a_depth_jump_stays_a_hole():
    # two levels 30 units apart: a hole on the jump is part of the edge (no height is made
    # up between the levels); one on either level is filled from that level
    z = tilted_plane()
    z[:, 25:] += 30.0
    z[10, 24] = z[20, 25] = np.nan  # beside the jump
    z[10, 10] = z[20, 40] = np.nan  # on a level
    out = fill_small_holes(z.copy(), 4)
    assert np.isnan(out[10, 24]) and np.isnan(out[20, 25])
    plane = tilted_plane()
    assert out[10, 10] == pytest.approx(plane[10, 10])
    assert out[20, 40] == pytest.approx(plane[20, 40] + 30.0)


def test_holes_in_whole_millimetres_are_filled_too():
    # A camera in whole mm over a gentle slope: most neighbouring readings are equal, the
    # median step is 0, and the bound on a hole's neighbours is the heights' quantum (1)
    plane = 100.0 + 0.12 * np.arange(50)[None, :] + 0.05 * np.arange(40)[:, None]
    z = np.round(plane)
    z[5:35:6, 5:45:6] = np.nan  # single holes, 6 apart
    holes = np.isnan(z)
    out = fill_small_holes(z.copy(), 4)
    assert np.isfinite(out[holes]).all()
    assert np.abs(out[holes] - plane[holes]).max() <= 1.0


def test_a_depth_hint_is_not_silenced_by_the_fill():
    from rangeseg_cli.stages.rangeimage import depth_map_hint

    depth = np.full((64, 80), 7000, np.uint16)
    depth[20:40, 20:50] = 6000
    depth.ravel()[::10] = 0
    assert depth_map_hint(depth, load_config(overrides={"input": {"fill_holes": 0}}).input)


@pytest.mark.parametrize("value", ["9", "-1", "2.5", "true"])
def test_a_bad_fill_holes_is_one_line_naming_the_key(value, tmp_path):
    from click.testing import CliRunner

    from rangeseg_cli.cli.main import main

    res = CliRunner().invoke(main, ["run", str(ARC / "bin-heightmap.depth.png"), "-o",
                                    str(tmp_path / "out"), "--set", f"input.fill_holes={value}"])
    assert res.exit_code == 2
    lines = res.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: [input] fill_holes = ")
    assert "expected an integer >= 0 <= 8" in lines[0] and "Traceback" not in res.output
    assert not (tmp_path / "out").exists()
