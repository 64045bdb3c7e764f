"""Holdsites (Sec. VII) on synthetic scenes with known answers, end to end."""

import dataclasses
import json
import math
import re

import numpy as np
import pytest

from conftest import passes_without
from rangeseg_cli.batch.io import to_jsonable
from rangeseg_cli.batch.render import overlay
from rangeseg_cli.config import load_config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.stages import holdsite as holdsite_module
from rangeseg_cli.stages.holdsite import HoldsiteResult, find_holdsite, footprint, window_ar_std

CONTRACT_KEYS = {"row", "col", "elevation", "normal", "approach", "surface", "surface_type",
                 "object", "clearance", "ar_std", "score", "angle", "size", "flat_rms"}


def table(shape=(64, 64), height=20.0):
    return np.full(shape, height)


def noisy(z, sigma=0.5, seed=0):
    return z + np.random.default_rng(seed).normal(0.0, sigma, z.shape)


def run(z, units_per_pixel=None, **holdsite):
    overrides: dict = {"holdsite": holdsite} if holdsite else {}
    if units_per_pixel is not None:  # the lateral scale of a height map
        overrides["input"] = {"units_per_pixel": units_per_pixel}
    return run_pipeline(z, load_config(overrides=overrides or None))


def site_label(result):
    site = result.holdsite.holdsite
    return result.labels[site.row, site.col]


def window(site):
    rows, cols = site.size
    return (slice(site.row - rows // 2, site.row + rows // 2 + 1),
            slice(site.col - cols // 2, site.col + cols // 2 + 1))


def surface_at(result, row, col):
    return next(s for s in result.surfaces if s.id == result.labels[row, col])


# --- the scenes of Sec. VII ------------------------------------------------------------


def test_box_on_table_gives_site_on_box_top_near_its_centre_with_clearance():
    z = table()
    z[20:44, 20:44] = 120.0
    result = run(noisy(z))
    site = result.holdsite.holdsite
    assert site is not None
    assert site.surface == result.labels[32, 32]
    assert site.clearance >= 3 and abs(site.row - 31.5) <= 2 and abs(site.col - 31.5) <= 2
    assert np.all(result.labels[window(site)] == site.surface)
    assert site.elevation == pytest.approx(120.0, abs=1.0)
    assert result.holdsite.background == (result.labels[2, 2],)


def test_box_with_through_hole_keeps_window_off_the_hole():
    z = table()
    z[8:56, 8:56] = 120.0
    z[26:38, 26:38] = 20.0  # a 12x12 through hole: the table shows through
    result = run(noisy(z))
    site = result.holdsite.holdsite
    hole = np.zeros(z.shape, bool)
    hole[26:38, 26:38] = True
    assert site.surface == result.labels[14, 14]
    assert not hole[window(site)].any()
    assert result.labels[32, 32] in result.holdsite.background  # the table seen through it
    assert all(c.surface == site.surface for c in result.holdsite.candidates)
    # farthest from both the rim and the hole: in a corner band, not at the centre
    assert site.clearance >= 5
    assert max(abs(site.row - 31.5), abs(site.col - 31.5)) >= 12


def test_top_surface_too_small_for_window_passes_to_next_surface():
    z = table()
    z[12:52, 12:52] = 120.0
    z[20:34, 24:30] = 200.0  # a 14x6 post on the box: highest, but a 7x7 window never fits
    result = run(noisy(z))
    post = surface_at(result, 27, 27)
    assert post.mean_height == pytest.approx(200.0, abs=2.0)  # it was segmented
    site = result.holdsite.holdsite
    assert site.surface == result.labels[45, 45] != post.id
    assert f"surfaces {post.id}" in result.holdsite.reason


def test_no_surface_large_enough_gives_null_with_reason():
    z = table()
    z[10:22, 10:22] = 120.0
    z[40:52, 30:42] = 90.0
    result = run(noisy(z), size=[15, 15])
    assert result.holdsite.holdsite is None
    reason = result.holdsite.reason
    assert "no surface has a 15x15 window" in reason and "largest clearance found" in reason
    assert result.holdsite.to_dict()["holdsite"] is None


def test_rough_surfaces_give_null_naming_the_ar_threshold():
    z = table()
    z[16:48, 16:48] = 120.0
    result = run(noisy(z, sigma=1.0), max_ar_std=0.05)
    assert result.holdsite.holdsite is None
    assert "AR std <= 0.05" in result.holdsite.reason


def test_two_stacked_boxes_give_site_on_upper_box_and_lower_is_covered():
    z = table()
    z[8:56, 8:56] = 80.0
    z[12:30, 34:52] = 160.0  # upper box off-centre on the lower one
    result = run(noisy(z))
    site = result.holdsite.holdsite
    upper, lower = result.labels[21, 43], result.labels[45, 20]
    assert site.surface == upper
    objects = {o.id: o for o in result.holdsite.objects}
    upper_obj = next(o for o in objects.values() if upper in o.surfaces)
    lower_obj = next(o for o in objects.values() if lower in o.surfaces)
    assert not upper_obj.covered and lower_obj.covered_by == (upper_obj.id,)


def test_plank_leaning_on_box_is_preferred_to_the_higher_box_it_covers():
    # The plank rests on the box's edge: lower on average, but the top of the pile.
    z = table()
    z[16:48, 34:62] = 100.0
    cols = np.arange(64, dtype=float)
    plank = 40.0 + 2.8 * (cols - 4.0)  # 40 at col 4, 110 at col 29, above the box after
    z[26:38, 4:44] = plank[4:44]
    result = run(noisy(z))
    box, plank_id = result.labels[30, 55], result.labels[32, 20]
    heights = {s.id: s.mean_height for s in result.surfaces}
    assert heights[box] > heights[plank_id]  # highest-first alone would take the box
    assert result.holdsite.holdsite.surface == plank_id


def plank_from_the_frame_onto_a_box():
    """A box wholly in view and a plank rising onto it from the image frame's left side."""
    z = table((64, 72))
    z[16:48, 30:60] = 100.0
    cols = np.arange(36, dtype=float)
    z[26:38, 0:36] = 30.0 + 2.34 * cols  # 30 at the frame, 112 at its end on the box
    return z


def test_an_item_at_the_border_lying_on_one_in_view_comes_before_the_covered_one():
    result = run(noisy(plank_from_the_frame_onto_a_box()))
    box, plank = result.labels[20, 45], result.labels[32, 15]
    objects = {o.id: o for o in result.holdsite.objects}
    plank_obj = next(o for o in objects.values() if plank in o.surfaces)
    box_obj = next(o for o in objects.values() if box in o.surfaces)
    assert plank_obj.touches_border and not box_obj.touches_border
    assert box_obj.covered_by == (plank_obj.id,)
    assert result.holdsite.holdsite.surface == plank
    assert "lying on an item in view" in result.holdsite.reason
    # the paper's order, or no support (nothing tells what is held up): the box in view
    for config in (load_config(preset="paper"),
                   load_config(overrides={"workspace": {"support": False}})):
        other = run_pipeline(noisy(plank_from_the_frame_onto_a_box()), config)
        assert other.holdsite.holdsite.surface == other.labels[20, 45]
        assert "lying on an item in view" not in other.holdsite.reason


def _object(oid, covered_by=(), border=False, structure=False):
    return holdsite_module.ObjectInfo(oid, (oid,), 100, (0.0, 0.0), covered_by, border,
                                      structure)


@pytest.mark.parametrize(("lower", "floating", "expected"), [
    (_object(1, (2,)), set(), {2}),  # an item in view holds it up
    (_object(1, (2,)), {1}, set()),  # a finger under the arm holds nothing up
    (_object(1, (2,), border=True), set(), set()),  # not wholly in view
    (_object(1, (2,), structure=True), set(), set()),  # a tote's floor
])
def test_lying_on_seen_items_needs_an_item_in_view_that_is_held_up(lower, floating, expected):
    upper = _object(2, border=True)
    assert holdsite_module.lying_on_seen_items([lower, upper], floating) == expected


def test_bin_wall_on_image_border_is_tried_after_a_box_in_view():
    z = table()
    rows = np.arange(64, dtype=float)[:, None]
    z[:, :10] = 150.0 + 2.0 * rows  # a tall wall along the left border, tilted
    z[24:44, 30:50] = 90.0
    result = run(noisy(z))
    assert result.holdsite.holdsite.surface == result.labels[34, 40]
    # the wall stands over no part of the table (the support): outside the workspace
    assert result.labels[30, 4] in result.holdsite.outside
    paper = run_pipeline(noisy(z), load_config(preset="paper"))
    assert paper.holdsite.holdsite.surface == paper.labels[34, 40]
    wall = next(o for o in paper.holdsite.objects if paper.labels[30, 4] in o.surfaces)
    assert wall.touches_border


def test_approach_of_tilted_plane_is_minus_its_unit_normal():
    z = table()
    r, c = np.mgrid[0:64, 0:64].astype(float)
    top = 120.0 + 0.8 * (c - 32) - 0.5 * (r - 32)  # dz/dx = 0.8, dz/dy = -0.5
    z[12:52, 12:52] = top[12:52, 12:52]
    site = run(z).holdsite.holdsite
    expected = np.array([-0.8, 0.5, 1.0]) / math.sqrt(0.64 + 0.25 + 1.0)
    np.testing.assert_allclose(site.normal, expected, atol=1e-3)
    np.testing.assert_allclose(site.approach, -expected, atol=1e-3)
    assert site.approach[2] < 0  # pointing down, into the surface


def test_long_footprint_on_diagonal_bar_takes_the_bar_orientation():
    z = table((80, 80))
    r, c = np.mgrid[0:80, 0:80].astype(float)
    t = math.radians(30.0)  # counter-clockwise as displayed: up and to the right
    along = (c - 40) * math.cos(t) - (r - 40) * math.sin(t)
    across = (c - 40) * math.sin(t) + (r - 40) * math.cos(t)
    z[(np.abs(along) <= 30) & (np.abs(across) <= 3.5)] = 100.0
    result = run(noisy(z, seed=3), size=[3, 9], rotation_step=15.0)
    site = result.holdsite.holdsite
    assert site.surface == result.labels[40, 40]
    assert site.angle == pytest.approx(30.0, abs=15.0)
    fp = footprint((3, 9), site.angle)
    k = fp.shape[0] // 2, fp.shape[1] // 2
    patch = result.labels[site.row - k[0]: site.row + k[0] + 1, site.col - k[1]: site.col + k[1] + 1]
    assert np.all(patch[fp] == site.surface)


def test_camera_point_and_approach_for_known_intrinsics():
    # Depth camera in 0.1 mm: floor 600 mm, box top 500 mm, fx = fy = 400, centre (31.5, 31.5).
    raw = np.full((64, 64), 6000, dtype=np.uint16)
    raw[16:48, 16:48] = 5000
    raw[0, :5] = 0  # no reading: never part of a window
    config = load_config(preset="tenth-mm-depth", overrides={
        "input": {"intrinsics": [400.0, 400.0, 31.5, 31.5]}})
    site = run_pipeline(raw, config).holdsite.holdsite
    x, y, zc = site.point_camera
    assert zc == pytest.approx(0.5, abs=1e-6)
    assert x == pytest.approx((site.col - 31.5) * 0.5 / 400.0, abs=1e-6)
    assert y == pytest.approx((site.row - 31.5) * 0.5 / 400.0, abs=1e-6)
    np.testing.assert_allclose(site.approach_camera, (0.0, 0.0, 1.0), atol=1e-6)


def test_camera_approach_of_tilted_plane_is_minus_its_3d_normal():
    fx = fy = 300.0
    cx, cy = 40.0, 30.0
    n = np.array([0.3, -0.2, -1.0])
    n /= np.linalg.norm(n)  # unit normal facing the camera (negative Z)
    p0 = np.array([0.0, 0.0, 500.0])  # mm
    v, u = np.mgrid[0:64, 0:80].astype(float)
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    depth = (n @ p0) / (ray @ n)  # the plane n.P = n.p0 seen along each ray
    raw = np.full(depth.shape, 8000.0)
    raw[12:52, 16:64] = depth[12:52, 16:64] * 10.0
    config = load_config(preset="tenth-mm-depth",
                         overrides={"input": {"intrinsics": [fx, fy, cx, cy]}})
    site = run_pipeline(np.round(raw).astype(np.uint16), config).holdsite.holdsite
    np.testing.assert_allclose(site.approach_camera, -n, atol=5e-3)
    assert site.point_camera[2] == pytest.approx(depth[site.row, site.col] / 1000, abs=5e-4)


# --- candidates, background, contract ---------------------------------------------------


def test_runners_up_take_other_surfaces_first_then_spaced_windows_on_the_same_surface():
    z = table((64, 96))
    z[12:52, 8:48] = 120.0
    z[16:48, 58:90] = 100.0
    result = run(noisy(z), max_candidates=3)
    site, others = result.holdsite.holdsite, result.holdsite.candidates
    high, low = result.labels[32, 28], result.labels[32, 74]
    assert site.surface == high and others[0].surface == low and len(others) == 3
    spots = [(s.row, s.col) for s in (site, *others) if s.surface == high]
    for a in range(len(spots)):
        for b in range(a):
            assert math.dist(spots[a], spots[b]) >= math.hypot(7, 7)


def test_background_rules_lowest_largest_and_none():
    z = table()
    z[20:44, 20:44] = 120.0
    z = noisy(z)
    table_id = run(z).labels[2, 2]
    assert run(z).holdsite.background == (table_id,)
    assert run(z, background="largest-border").holdsite.background == (table_id,)
    no_rule = load_config(overrides={"holdsite": {"background": "none"},
                                     "workspace": {"support": False}})
    free = run_pipeline(z, no_rule).holdsite
    assert free.background == () and free.holdsite.surface != table_id  # box in view first
    assert run(z, background="none").holdsite.outside == (table_id,)  # the support


def test_split_table_at_the_same_level_is_all_background():
    z = table()
    z[:, 30:34] = 150.0  # a wall across the image splits the table in two
    z[8:24, 6:22] = 100.0
    apart = passes_without("join_occluded")
    result = run_pipeline(noisy(z), apart)
    left, right = result.labels[50, 5], result.labels[50, 60]
    assert left != right and set(result.holdsite.background) == {left, right}
    result = run(noisy(z))  # the table goes on under the wall: one surface, the background
    left, right = result.labels[50, 5], result.labels[50, 60]
    assert left == right and set(result.holdsite.background) == {left}


def test_result_dict_follows_the_file_contract_and_is_json_ready():
    z = table()
    z[20:44, 20:44] = 120.0
    doc = run(noisy(z)).holdsite.to_dict()
    assert set(doc) == {"holdsite", "reason", "candidates", "background", "objects",
                        "outside_workspace"}
    assert set(doc["holdsite"]) == CONTRACT_KEYS
    json.dumps(to_jsonable(doc))
    raw = np.full((64, 64), 6000, dtype=np.uint16)
    raw[16:48, 16:48] = 5000
    config = load_config(preset="mm-depth",
                         overrides={"input": {"intrinsics": [500.0, 500.0, 0.0, 0.0]}})
    camera_doc = run_pipeline(raw, config).holdsite.to_dict()
    assert set(camera_doc["holdsite"]) == CONTRACT_KEYS | {
        "point_camera", "approach_camera", "tilt", "tilt_from"}


def test_labels_of_another_shape_are_an_input_error():
    from rangeseg_cli.errors import InputError

    with pytest.raises(InputError, match="`labels` \\(shape \\(3, 3\\)\\)"):
        find_holdsite(table(), np.zeros((3, 3), np.int32), [], load_config())


def test_all_background_scene_gives_null_not_an_error():
    result = run(noisy(table()))
    assert isinstance(result.holdsite, HoldsiteResult)
    assert result.holdsite.holdsite is None
    assert result.holdsite.reason.startswith("nothing to pick: ")


# --- building blocks ------------------------------------------------------------------


def test_footprint_is_the_rectangle_at_0_and_90_degrees_and_keeps_its_area_rotated():
    assert footprint((3, 9), 0.0).shape == (3, 9) and footprint((3, 9), 0.0).all()
    assert footprint((3, 9), 90.0).shape == (9, 3)
    fp = footprint((3, 9), 30.0)
    assert fp.shape[0] % 2 == 1 and abs(int(fp.sum()) - 27) <= 4
    np.testing.assert_array_equal(fp, fp[::-1, ::-1])  # symmetric about its centre


def test_window_ar_std_matches_a_direct_computation():
    ar = np.random.default_rng(1).random((20, 30))
    for fp in (np.ones((7, 7), bool), footprint((3, 9), 45.0)):
        std = window_ar_std(ar, fp)
        kr, kc = fp.shape[0] // 2, fp.shape[1] // 2
        direct = ar[10 - kr: 10 + kr + 1, 15 - kc: 15 + kc + 1][fp].std()
        assert std[10, 15] == pytest.approx(direct, abs=1e-9)


def test_overlay_fills_the_site_white_and_outlines_runners_up():
    z = table((64, 96))
    z[12:52, 8:48] = 120.0
    z[16:48, 58:90] = 100.0
    result = run(noisy(z), max_candidates=1)
    image = overlay(result.labels, result.holdsite)
    site, other = result.holdsite.holdsite, result.holdsite.candidates[0]
    assert image.shape == (64, 96, 3) and image.dtype == np.uint8
    assert np.all(image[window(site)] == 255)
    ring = image[window(other)]
    assert np.all(ring[0] == 255) and not np.all(ring[3, 3] == 255)


def test_window_mean_of_large_rotated_footprint_matches_shift_sum():
    from rangeseg_cli.stages.holdsite import window_mean

    a = np.random.default_rng(2).random((40, 50))
    fp = footprint((9, 21), 30.0)
    kr, kc = fp.shape[0] // 2, fp.shape[1] // 2
    mean = window_mean(a, fp)
    assert mean[20, 25] == pytest.approx(a[20 - kr: 20 + kr + 1, 25 - kc: 25 + kc + 1][fp].mean())


@pytest.mark.parametrize("backend", ["numpy", "auto"])
@pytest.mark.parametrize("seed", range(3))
def test_step_gaps_given_with_the_surfaces_are_those_the_search_computes(backend, seed):
    from rangeseg_cli.stages.holdsite import _coefficient_table, step_gaps
    from rangeseg_cli.stages.surfaces import describe_surfaces, describe_surfaces_and_gaps
    from rangeseg_cli.synth.scenes import render_scene

    config = load_config(preset="paper")
    result = run_pipeline(render_scene("pile", noise=1.0, seed=seed).image, config)
    surfaces, gaps = describe_surfaces_and_gaps(result.heights, result.labels, config,
                                                backend=backend)
    assert surfaces == describe_surfaces(result.heights, result.labels, config,
                                         backend=backend)
    n = int(result.labels.max())
    known = np.zeros(n + 1, dtype=bool)
    known[[s.id for s in surfaces]] = True
    labels = np.where(np.isfinite(result.heights), result.labels, 0)
    ref = step_gaps(labels, _coefficient_table(surfaces, n), known, backend=backend)
    assert list(gaps) == list(ref) and len(gaps) >= 3
    assert all(math.copysign(1.0, gaps[k]) == math.copysign(1.0, ref[k]) and gaps[k] == ref[k]
               for k in ref)
    with_gaps = find_holdsite(result.heights, result.labels, surfaces, config, gaps=gaps)
    assert with_gaps == find_holdsite(result.heights, result.labels, surfaces, config)


def test_a_plateau_clipped_at_255_is_not_gripped_a_measured_surface_is():
    # An 8-bit height map: a box top at 120 the image measures, and a taller box whose top
    # at 300 lies beyond 8 bits: the image holds a flat plateau at 255 there, the highest
    # and flattest "surface" in view. Clipped values are invalid ([input] clipped_invalid),
    # so the holdsite goes to the measured top; without the rule, to the plateau.
    z = table((64, 96))
    z[12:52, 8:40] = 120.0
    z[14:50, 54:88] = 300.0
    image = np.clip(np.rint(noisy(z, 1.0)), 0, 255).astype(np.uint8)
    plateau = image == 255
    assert plateau[14:50, 54:88].all() and plateau.sum() == 36 * 34  # only the tall box
    found = {}
    for clipped in (True, False):
        config = load_config(overrides={"input": {"clipped_invalid": clipped}})
        result = run_pipeline(image, config).holdsite
        found[clipped] = (result.holdsite, *result.candidates)
    measured = found[True]
    assert measured[0] is not None and len(measured) >= 2
    assert all(12 <= s.row < 52 and 8 <= s.col < 40 for s in measured)  # on the box top
    assert not any(plateau[window(s)].any() for s in measured)
    assert measured[0].elevation == pytest.approx(120.0, abs=0.5)
    site = found[False][0]  # without the rule: on the plateau, at its clipped height
    assert plateau[window(site)].all() and site.elevation == pytest.approx(255.0)


def test_clipped_invalid_is_a_boolean_key():
    from rangeseg_cli.errors import ConfigError

    assert load_config().input.clipped_invalid is True
    with pytest.raises(ConfigError, match=r"\[input\] clipped_invalid = 'no': expected true"):
        load_config(overrides={"input": {"clipped_invalid": "no"}})


@pytest.mark.parametrize("top", [50.0, 45.0, 55.0])
def test_a_box_as_high_as_the_middle_of_a_tilted_table_is_an_object(top):
    # The table rises 0.3 per column (38 over the image): its mean height is 49. A box top
    # near that height was taken into the background by the mean-height rule: no holdsite.
    yy, xx = np.mgrid[0:128, 0:128].astype(float)
    z = 30 + 0.3 * xx
    z[44:84, 8:48] = top  # 7 to 17 units above the table where it stands
    result = run_pipeline(z, load_config()).holdsite
    assert result.holdsite is not None, result.reason
    assert 44 <= result.holdsite.row < 84 and 8 <= result.holdsite.col < 48
    assert len(result.background) == 1


def test_a_level_table_split_by_a_wall_still_joins_by_mean_height():
    # a level table divided by a wall is still all background (two regions, one level)
    z = np.full((96, 96), 20.0)
    z[:, 44:52] = 90.0  # a wall from top to bottom splits the table
    result = run_pipeline(z, passes_without("join_occluded"))
    assert len(result.holdsite.background) == 2


# --- Step 6: the pose of a site on a curved surface (a local quadric) -------------------


def run_with_pose(z, pose, monkeypatch):
    """``run(z)`` with Step 6 as it is (``"local"``: a curved surface's site takes a local
    quadric) or with every site on its surface's own fit (``"surface"``: the setting
    ``holdsite.pose = "surface"`` of before, now gone)."""
    with monkeypatch.context() as patch:
        if pose == "surface":
            patch.setattr(holdsite_module, "_local_pose_used", lambda scene, s: False)
        return run(z)


def _pose_errors(site, height, normal):
    """Elevation error and normal angle (degrees) of a site against the true height and
    the true unit normal (-dz/dx, -dz/dy, 1) / norm there."""
    cosine = float(np.dot(site.normal, normal))
    return abs(site.elevation - height), math.degrees(math.acos(min(1.0, cosine)))


def sphere_on_table(radius=26.0, units_per_pixel=2.0, shape=(96, 96), floor=20.0):
    """A sphere resting on a table in the middle of the image, heights in depth units
    (``units_per_pixel`` of them per pixel of lateral size), and its true pose
    ``(height, unit normal)`` at a pixel."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    y, x = rows - (shape[0] - 1) / 2, cols - (shape[1] - 1) / 2
    centre = floor + units_per_pixel * radius  # the sphere's centre, in depth units
    up = np.sqrt(np.maximum(radius ** 2 - x ** 2 - y ** 2, 0.0))  # above the centre, px
    z = table(shape, floor)
    on = x ** 2 + y ** 2 < radius ** 2
    z[on] = centre + units_per_pixel * up[on]

    def truth(row, col):  # dz/dx = -upp x / up: the normal is along (upp x, upp y, up)
        normal = np.array([units_per_pixel * x[row, col], units_per_pixel * y[row, col],
                           up[row, col]])
        return z[row, col], normal / np.linalg.norm(normal)
    return z, truth


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_sites_on_a_sphere_take_the_pose_of_the_sphere_under_the_gripper(noise, monkeypatch):
    z, truth = sphere_on_table()  # radius 26 px, 52 depth units, on a table at 20
    z = noisy(z, noise) if noise else z
    errors = {}
    for pose in ("local", "surface"):
        result = run_with_pose(z, pose, monkeypatch)
        sites = (result.holdsite.holdsite, *result.holdsite.candidates)
        assert len(sites) >= 4 and all(s.surface_type == "curved" for s in sites)
        assert all(math.hypot(s.row - 47.5, s.col - 47.5) < 26 for s in sites)
        errors[pose] = np.array([_pose_errors(s, *truth(s.row, s.col)) for s in sites])
    # one quadric of the whole sphere misses its top by ~3.5 units and tilts the sites
    # away from it by ~11 degrees; the local quadric follows the sphere
    assert errors["surface"][0, 0] > 2.0 and errors["surface"][:, 1].max() > 8.0
    assert errors["local"][:, 0].max() < 0.5 and errors["local"][:, 1].max() < 4.0


def test_a_site_on_a_plane_keeps_the_plane_of_the_whole_face(monkeypatch):
    z = table()
    z[12:52, 12:52] = 60.0 + 0.5 * np.arange(64)[None, 12:52]  # a ramp: planar, tilted
    local, whole = (run_with_pose(noisy(z, 1.0), p, monkeypatch).holdsite
                    for p in ("local", "surface"))
    assert local.holdsite.surface_type == "planar"
    assert local.to_dict() == whole.to_dict()


def test_local_pose_needs_enough_pixels_and_is_exact_on_a_quadric():
    from rangeseg_cli.models import Surface
    from rangeseg_cli.stages.holdsite import LOCAL_FIT_MIN_PIXELS, local_pose

    rows, cols = np.mgrid[0:40, 0:40].astype(float)
    z = 50.0 + 0.3 * cols - 0.2 * rows + 0.01 * (cols - 20) ** 2 + 0.02 * (rows - 20) * cols
    labels = np.ones(z.shape, np.int32)
    s = Surface(1, z.size, (0, 0, 39, 39), (19.5, 19.5), float(z.mean()), (0.0,) * 6, 0.0,
                "curved", "ridge")
    elevation, (gx, gy) = local_pose(z, labels, s, 20, 20, 7)
    assert elevation == pytest.approx(z[20, 20], abs=1e-9)
    assert gx == pytest.approx(0.3, abs=1e-9)  # dz/dcol: 0.3 + 0.02 (col - 20) + 0.02 (row - 20)
    assert gy == pytest.approx(-0.2 + 0.02 * 20, abs=1e-9)  # dz/drow: -0.2 + 0.02 col
    few = np.zeros(z.shape, np.int32)
    few[20, 20 - LOCAL_FIT_MIN_PIXELS // 2:20 + LOCAL_FIT_MIN_PIXELS // 2 - 1] = 1
    assert local_pose(z, few, s, 20, 20, 7) is None  # too few pixels
    line = np.zeros(z.shape, np.int32)
    line[20, :] = 1
    assert local_pose(z, line, s, 20, 20, 7) is None  # one row: no quadric


def test_local_poses_match_a_least_squares_fit_at_every_site_border_and_holes_included():
    from rangeseg_cli.models import Surface
    from rangeseg_cli.stages.holdsite import local_pose, local_poses

    rng = np.random.default_rng(3)
    rows, cols = np.mgrid[0:30, 0:40].astype(float)
    z = 80.0 + 0.4 * cols - 0.03 * (rows - 12) ** 2 + 0.01 * cols * rows + rng.normal(0, 1, rows.shape)
    labels = np.ones(z.shape, np.int32)
    labels[10:14, 5:25] = 2  # another surface inside the square of some sites
    z[20:23, 30:33] = np.nan  # invalid pixels
    s = Surface(1, int((labels == 1).sum()), (0, 0, 29, 39), (15.0, 20.0), 85.0, (0.0,) * 6,
                0.0, "curved", "saddle-ridge")
    sites = np.array([[0, 0], [15, 20], [29, 39], [21, 31], [5, 37]])
    height, gx, gy, ok = local_poses(z, labels, s, sites[:, 0], sites[:, 1], 6)
    assert ok.all()
    for k, (r, c) in enumerate(sites):
        box = (slice(max(r - 6, 0), r + 7), slice(max(c - 6, 0), c + 7))
        rr, cc = np.nonzero((labels[box] == 1) & np.isfinite(z[box]))
        y, x = rr + box[0].start - r, cc + box[1].start - c
        design = np.column_stack([np.ones(x.size), x, y, x * x, x * y, y * y]).astype(float)
        coef = np.linalg.lstsq(design, z[box][rr, cc], rcond=None)[0]
        assert (height[k], gx[k], gy[k]) == pytest.approx(tuple(coef[:3]), abs=1e-8)
        assert local_pose(z, labels, s, int(r), int(c), 6) == (height[k], (gx[k], gy[k]))


# --- Step 4b: a tilt limit (holdsite.max_tilt) -----------------------------------------


def _tilt(site, units_per_pixel=2.0):
    """A height-map site's tilt in degrees from its reported normal (2 units/px: synth)."""
    slope = math.hypot(site.normal[0], site.normal[1]) / site.normal[2]
    return math.degrees(math.atan(slope / units_per_pixel))


def _sites(found):
    return (found.holdsite, *found.candidates) if found.holdsite else ()


def test_max_tilt_is_tested_only_with_the_lateral_scale_of_the_image():
    from rangeseg_cli.errors import ConfigError
    from rangeseg_cli.stages.holdsite import effective_holdsite

    assert load_config().holdsite.max_tilt == 45.0
    assert effective_holdsite(load_config()).max_tilt == 90.0  # no scale: not testable
    scaled = load_config(overrides={"input": {"units_per_pixel": 2.0}})
    assert effective_holdsite(scaled).max_tilt == 45.0
    assert load_config(preset="paper").holdsite.max_tilt == 90.0
    with pytest.raises(ConfigError, match=r"max_tilt = 91.*<= 90"):
        load_config(overrides={"holdsite": {"max_tilt": 91}})
    with pytest.raises(ConfigError, match=r"\[holdsite\] units_per_pixel is now "
                                          r"input.units_per_pixel"):
        load_config(overrides={"holdsite": {"units_per_pixel": 2.0}})


def roof_beside_a_box():
    """Two planar faces meeting at a ridge, falling 3 units per pixel (56.3 degrees at 2
    units per pixel), higher than a level box top at 90."""
    cols = np.mgrid[0:80, 0:96][1].astype(float)
    z = table((80, 96))
    z[10:70, 8:49] = 200.0 - 3.0 * np.abs(cols[10:70, 8:49] - 28)
    z[20:60, 60:90] = 90.0
    return z


def steep_ramp_beside_a_gentle_one():
    """A ramp rising 3 units per pixel across the columns (56.3 degrees) up to 145, higher
    than a ramp rising 1 unit per pixel down the rows (26.6 degrees: tilted, within 45)."""
    rows, cols = np.mgrid[0:80, 0:96].astype(float)
    z = table((80, 96))
    z[10:70, 8:44] = 40.0 + 3.0 * (cols[10:70, 8:44] - 8)
    z[20:60, 60:90] = 60.0 + 1.0 * (rows[20:60, 60:90] - 20)
    return z


def leaning_cylinder_beside_a_box(alpha=55.0, radius=14.0):
    """A cylinder whose axis rises ``alpha`` degrees along the columns (curved; every
    normal at least ``alpha`` off the vertical), higher than a level box top at 90: the
    cylinder ``w^2 + y^2 = R^2`` with ``w = z cos(alpha) - x sin(alpha)``, at 2 units/px."""
    rows, cols = np.mgrid[0:80, 0:96].astype(float)
    a = math.radians(alpha)
    x, y, r = 2.0 * (cols - 8), 2.0 * (rows - 40), 2.0 * radius  # depth units
    z = table((80, 96))
    on = (np.abs(y) < r) & (cols >= 8) & (cols < 44)
    z[on] = 20.0 + x[on] * math.tan(a) + np.sqrt(r ** 2 - y[on] ** 2) / math.cos(a)
    z[20:60, 60:90] = 90.0
    return z


@pytest.mark.parametrize("scene", [roof_beside_a_box, steep_ramp_beside_a_gentle_one,
                                   leaning_cylinder_beside_a_box])
def test_max_tilt_keeps_every_site_within_the_limit(scene):
    z = noisy(scene(), 1.0)
    free = run(z, max_tilt=90.0, units_per_pixel=2.0)
    limited = run(z, max_tilt=45.0, units_per_pixel=2.0)
    assert max(_tilt(s) for s in _sites(free.holdsite)) > 50  # the paper's rule takes steep faces
    assert free.holdsite.holdsite.col < 49  # the highest object first: the steep one
    assert _sites(limited.holdsite)
    assert all(_tilt(s) <= 45.0 + 1e-9 for s in _sites(limited.holdsite))
    # every site within the limit is on the level top or the gentle ramp
    assert all(20 <= s.row < 60 and 60 <= s.col < 90 for s in _sites(limited.holdsite))
    assert "tilt <= 45 degrees" in limited.holdsite.reason
    if scene is leaning_cylinder_beside_a_box:  # the steep sites are curved: local poses tested
        steep = [s for s in _sites(free.holdsite) if _tilt(s) > 45]
        assert steep and all(s.surface_type == "curved" for s in steep)


def wedge():
    """A ramp rising 3 units per pixel (56.3 degrees at 2 units/px), then a step down."""
    cols = np.mgrid[0:64, 0:64][1].astype(float)
    z = table()
    z[12:52, 12:52] = 30.0 + 3.0 * (cols[12:52, 12:52] - 12)
    return z


def roof():
    """Two faces meeting at a ridge, falling 3 units per pixel on either side."""
    cols = np.mgrid[0:64, 0:64][1].astype(float)
    z = table()
    z[12:52, 8:56] = 160.0 - 3.0 * np.abs(cols[12:52, 8:56] - 31.5)
    return z


@pytest.mark.parametrize("scene", [wedge, roof])
def test_max_tilt_with_no_level_window_says_so(scene):
    found = run(noisy(scene(), 0.5), max_tilt=45.0, units_per_pixel=2.0).holdsite
    assert found.holdsite is None and not found.candidates
    assert re.search(r"tilt <= 45 degrees from the support's normal; \d+ window\(s\) passed "
                     r"the AR test, least tilt 56", found.reason)  # the table is the support


def test_max_tilt_with_a_camera_takes_the_optical_axis():
    from rangeseg_cli.batch.io import read_image

    image = read_image("sample_data/arc/suction-scene.depth.png")
    angles = {}
    for limit in (90.0, 15.0):
        config = load_config("sample_data/arc/suction.toml",  # the tilt alone: no workspace
                             overrides={"holdsite": {"max_tilt": limit},
                                        "workspace": {"support": False}})
        found = run_pipeline(image, config).holdsite
        angles[limit] = [math.degrees(math.acos(s.approach_camera[2])) for s in _sites(found)]
    assert max(angles[90.0]) > 30  # the default site itself is 36 degrees off the axis
    assert angles[15.0] and max(angles[15.0]) <= 15.0 + 1e-9


def test_tilts_of_a_camera_agree_with_the_reported_approach():
    from rangeseg_cli.stages.holdsite import camera_pose, tilts

    camera = load_config("sample_data/arc/suction.toml").input
    rng = np.random.default_rng(0)
    for _ in range(50):
        row, col = rng.uniform(0, 480), rng.uniform(0, 640)
        height, grad = -rng.uniform(300, 900), tuple(rng.normal(0, 2, 2))
        _, approach = camera_pose(row, col, height, grad, camera)
        expected = math.degrees(math.acos(approach[2]))
        assert float(tilts(camera, 0.0, row, col, height, *grad)) == pytest.approx(expected,
                                                                                   abs=1e-9)


def lying_cylinder(radius=16.0, yaw=25.0, length=70.0, shape=(96, 96), floor=20.0):
    """A cylinder lying on a table, its axis ``yaw`` degrees from the columns, heights at
    2 depth units per pixel, and its true pose ``(height, unit normal)`` at a pixel."""
    rows, cols = np.mgrid[0:shape[0], 0:shape[1]].astype(float)
    y, x = rows - (shape[0] - 1) / 2, cols - (shape[1] - 1) / 2
    t = math.radians(yaw)
    along = x * math.cos(t) - y * math.sin(t)
    across = x * math.sin(t) + y * math.cos(t)
    up = np.sqrt(np.maximum(radius ** 2 - across ** 2, 0.0))  # above the axis, px
    z = table(shape, floor)
    on = (np.abs(across) < radius) & (np.abs(along) <= length / 2)
    z[on] = floor + 2.0 * (radius + up[on])

    def truth(row, col):  # dz/d(across) = -2 across / up
        slope = -2.0 * across[row, col] / up[row, col]
        normal = np.array([-slope * math.sin(t), -slope * math.cos(t), 1.0])
        return floor + 2.0 * (radius + up[row, col]), normal / np.linalg.norm(normal)
    return z, truth


def test_a_small_footprint_still_takes_its_local_pose_from_enough_pixels():
    # a 3x3 footprint's own 7x7 square held a quadric of 49 noisy pixels: 10-20 degrees off
    from rangeseg_cli.stages.holdsite import LOCAL_MIN_REACH, local_reach

    assert local_reach((3, 3)) == LOCAL_MIN_REACH == local_reach((7, 1))
    assert local_reach((21, 7)) == 21
    z, truth = lying_cylinder()
    for seed in (1, 3):
        found = run(noisy(z, 2.0, seed), size=[3, 3]).holdsite
        assert all(s.surface_type == "curved" for s in _sites(found))
        errors = [_pose_errors(s, *truth(s.row, s.col)) for s in _sites(found)]
        assert len(errors) >= 4 and max(angle for _, angle in errors) < 6.0


def test_max_tilt_zero_takes_a_level_top():
    z = table()
    z[20:44, 20:44] = 120.0  # level to rounding: its plane's tilt is ~1e-14 degrees
    found = run(z, max_tilt=0.0, units_per_pixel=2.0).holdsite
    assert found.holdsite is not None and found.holdsite.elevation == pytest.approx(120.0)


def test_max_tilt_without_depth_in_front_of_the_camera_says_so():
    depth = np.full((64, 64), -800.0)  # a depth map behind the camera: no tilt anywhere
    depth[20:44, 20:44] = -900.0
    config = load_config(overrides={
        "input": {"intrinsics": [500.0, 500.0, 32.0, 32.0], "larger_is_closer": False},
        "holdsite": {"max_tilt": 45.0}})
    found = run_pipeline(noisy(depth, 0.3), config).holdsite
    assert found.holdsite is None
    assert "none with a tilt (no depth in front of the camera there)" in found.reason
    assert "inf" not in found.reason


def test_tilts_computed_a_chunk_at_a_time_choose_as_all_at_once(monkeypatch):
    from rangeseg_cli.stages import holdsite
    from rangeseg_cli.synth.scenes import render_scene

    for name in ("cup", "part1", "sphere"):
        image = render_scene(name, noise=1.0, seed=2).image
        results = []
        for chunk in (1, 10**9):
            monkeypatch.setattr(holdsite, "TILT_CHUNK", chunk)
            results.append(run(image, max_tilt=40.0, units_per_pixel=2.0).holdsite.to_dict())
        assert results[0] == results[1]
        assert results[0]["holdsite"] is not None


def test_the_noise_the_pipeline_has_gives_the_holdsite_it_would_estimate():
    z = table()
    z[20:44, 20:44] = 120.0
    z[30:34, 26:30] = 90.0  # a hole: the window must move
    z = noisy(z, sigma=1.0)
    result = run(z)
    config = load_config()
    alone = find_holdsite(result.heights, result.labels, result.surfaces, config)
    given = find_holdsite(result.heights, result.labels, result.surfaces, config,
                          noise=result.noise_sigma)
    assert given.to_dict() == alone.to_dict() == result.holdsite.to_dict()
    rough = find_holdsite(result.heights, result.labels, result.surfaces, config, noise=40.0)
    assert rough.to_dict() != alone.to_dict()  # the noise is used


@pytest.mark.parametrize("noise", ["x", -1.0, float("nan"), float("inf")])
def test_a_bad_noise_given_to_the_holdsite_is_one_line(noise):
    z = table()
    z[20:44, 20:44] = 120.0
    result = run(z)
    with pytest.raises(ValueError, match=r"^`noise` must be a finite number >= 0 .*, got ") as err:
        find_holdsite(result.heights, result.labels, result.surfaces, load_config(), noise=noise)
    assert "\n" not in str(err.value)


def _plane_view(camera, normal, offset, row, col):
    """Height (-depth) and its image gradient at (row, col) of the camera-frame plane
    ``normal . P + offset = 0`` (central differences of the exact depth)."""
    def height(r, c):
        ray = np.array([(c - camera.cx) / camera.fx, (r - camera.cy) / camera.fy, 1.0])
        return offset / float(np.dot(normal, ray))  # -depth, depth = -offset / (n . ray)
    h = 1e-3
    gx = (height(row, col + h) - height(row, col - h)) / (2 * h)
    gy = (height(row + h, col) - height(row - h, col)) / (2 * h)
    return height(row, col), gx, gy


@pytest.mark.parametrize("mount", [0.0, 30.0, 55.0])
def test_tilts_against_the_support_whatever_the_camera_mount(mount):
    from rangeseg_cli.stages.holdsite import tilts

    camera = load_config("sample_data/arc/suction.toml").input
    t = math.radians(mount)
    up = (0.0, -math.sin(t), -math.cos(t))  # the floor's normal towards a camera tilted `mount`
    wall = (0.0, math.cos(t), -math.sin(t))  # a wall standing on it, facing the camera
    for row, col in ((100.0, 200.0), (400.0, 500.0)):
        floor = _plane_view(camera, np.array(up), 700.0, row, col)
        assert float(tilts(camera, 0.0, row, col, *floor, up=up)) == pytest.approx(0, abs=1e-4)
        assert float(tilts(camera, 0.0, row, col, *floor)) == pytest.approx(mount, abs=1e-4)
    face = _plane_view(camera, np.array(wall), 500.0, 100.0, 200.0)  # above the centre
    assert float(tilts(camera, 0.0, 100.0, 200.0, *face, up=up)) == pytest.approx(90, abs=1e-4)


def test_tilts_of_a_height_map_against_a_tilted_support():
    from rangeseg_cli.stages.holdsite import tilts

    camera = load_config().input
    s, slope = 2.0, 0.5  # a plane rising 0.5 depth units per pixel at 2 units per pixel
    normal = np.array([-slope, 0.0, s]) / math.hypot(slope, s)
    assert float(tilts(camera, s, 5, 5, 30.0, slope, 0.0)) == pytest.approx(
        math.degrees(math.atan(slope / s)))
    assert float(tilts(camera, s, 5, 5, 30.0, slope, 0.0, up=tuple(normal))) == pytest.approx(
        0, abs=1e-9)


def tilted_camera_view(mount, shape=(240, 320)):
    """A box on a table seen by a camera tilted ``mount`` degrees from straight down:
    the depth image, its config, the camera and the render (GT faces)."""
    from rangeseg_cli.synth.camera import CAMERAS, Item, camera_for, render_items, support_plane
    from rangeseg_cli.synth.scenes import box, pose

    cam = camera_for(CAMERAS["ideal"], shape, height=700.0, tilt=(mount, 0.0))
    axis = cam.R[:, 2]
    yaw = math.degrees(math.atan2(axis[1], axis[0]))
    item = box(120.0, 90.0, 60.0, "item").moved(pose(-40.0, 0.0, 0.0, yaw=yaw + 20))
    view = render_items(cam, [support_plane("table"), Item("item", (item,), True, "item")])
    depth = np.where(np.isfinite(view.depth), view.depth, 0.0)
    config = load_config(overrides={"input": {
        "larger_is_closer": False, "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
        "metres_per_unit": 0.001}})
    return depth, config, cam, view


@pytest.mark.parametrize("mount", [45.0, 50.0])
def test_a_steep_camera_mount_picks_the_level_top_not_a_side(mount):
    depth, config, cam, view = tilted_camera_view(mount)
    found = run_pipeline(depth, config).holdsite
    assert found.holdsite is not None, found.reason
    for site in _sites(found):
        face = view.surfaces[view.gt[site.row, site.col] - 1]["name"]
        assert face == "item top"
        down = -cam.R[2]  # the world's -z in the camera frame
        level = math.degrees(math.acos(float(np.dot(site.approach_camera, down))))
        assert level < 5.0


def test_a_site_reports_its_tilt_from_the_axis_the_limit_used():
    # a level box top seen from a camera mounted 45 degrees off the vertical
    depth, config, cam, view = tilted_camera_view(45.0)
    found = run_pipeline(depth, config).holdsite
    for site in _sites(found):
        down = -cam.R[2]  # the world's -z in the camera frame
        level = math.degrees(math.acos(float(np.dot(site.approach_camera, down))))
        off_axis = math.degrees(math.acos(site.approach_camera[2]))
        assert site.tilt_from == "support" and site.tilt == pytest.approx(level, abs=1.0)
        assert site.tilt < 5.0 and off_axis > 35.0  # level, though far off the optical axis
        assert site.to_dict(camera=True)["tilt"] == site.tilt
    # without a support (the workspace off) it is measured from the optical axis
    bare = load_config(overrides={"input": dataclasses.asdict(config.input),
                                  "workspace": {"support": False}, "holdsite": {"max_tilt": 90.0}})
    site = run_pipeline(depth, bare).holdsite.holdsite
    assert site.tilt_from == "optical axis"
    assert site.tilt == pytest.approx(math.degrees(math.acos(site.approach_camera[2])), abs=1e-6)
    # a height map without a lateral scale has no tilt to report
    z = table()
    z[20:44, 20:44] = 120.0
    site = run(noisy(z)).holdsite.holdsite
    assert site.tilt is None and "tilt" not in site.to_dict()
    site = run(noisy(z), units_per_pixel=1.0).holdsite.holdsite
    assert site.tilt_from in {"support", "height axis"} and site.tilt < 1.0


def test_an_object_crossing_the_view_is_told_by_opposite_sides():
    from rangeseg_cli.stages.holdsite import crossing_the_view

    owner = np.zeros((40, 60), np.int64)
    owner[30:34, :] = 1  # a rim from the left side to the right
    owner[:, 20:23] = 2  # a rail from the top to the bottom
    owner[5:15, 0:10] = 3  # an item cut by the left side only
    owner[5:15, 40:50] = 4  # an item within the view
    assert crossing_the_view(owner) == {1, 2}
    # a depth camera's band of no reading along the left edge: the rim starts past it
    owner[:, :12] = 0
    valid = np.ones(owner.shape, bool)
    valid[:, :12] = False
    assert crossing_the_view(owner) == {2}
    assert crossing_the_view(owner, valid) == {1, 2}
    valid[20:24, :] = False  # a crack across the view adds no crossing object
    assert crossing_the_view(owner, valid) == {1, 2}


def test_an_object_around_the_floor_encloses_it_a_ring_shaped_item_does_not():
    from scipy import ndimage

    from rangeseg_cli.stages.holdsite import enclosing_rings

    owner = np.zeros((60, 80), np.int64)
    owner[5:55, 5:75] = 1
    owner[8:52, 8:72] = 0  # a tote's walls around its floor
    owner[20:30, 20:30] = 2
    owner[23:27, 23:27] = 0  # a roll of tape: its hole is smaller than it
    owner[35:45, 40:60] = 3
    owner[37:43, 42:58] = 0  # a ring of 3 around a gap of no reading
    valid = np.ones(owner.shape, bool)
    valid[37:43, 42:58] = False
    assert enclosing_rings(owner, ndimage.find_objects(owner), valid) == ({1}, set())
    # a roll of duct tape, its hole 0.63 of it: one object rings a hole as large as itself
    yy, xx = np.mgrid[:60, :60]
    radius = np.hypot(yy - 30, xx - 30)
    tape = ((radius <= 20) & (radius >= 12)).astype(np.int64)
    assert enclosing_rings(tape, ndimage.find_objects(tape), np.ones(tape.shape, bool)) == (
        set(), set())


def test_objects_that_close_a_ring_together_are_its_structures_what_lies_within_is_not():
    from scipy import ndimage

    from rangeseg_cli.stages.holdsite import enclosing_rings

    owner = np.full((70, 100), 7, np.int64)  # the table beyond the tote
    owner[5:65, 5:85] = 0
    owner[5:12, 5:85] = 1  # the far rim
    owner[12:58, 5:9] = owner[12:58, 81:85] = 2  # the side rims, one object
    owner[58:65, 5:85] = 3  # the near wall, its outer face
    owner[12:22, 9:81] = 4  # the far wall's inner face
    owner[22:34, 9:24] = 5  # an item leaning on the side wall
    owner[40:50, 50:60] = 6  # an item on the floor
    owner[22:58, 9] = 0  # the edge line between the side rim and the floor
    owner[30:45, 88:96] = 9  # an item outside, touching the side rim
    valid = np.ones(owner.shape, bool)
    boxes = ndimage.find_objects(owner)
    pairs = {(1, 2), (2, 3), (1, 4), (2, 4), (4, 5), (2, 5), (2, 9)}
    pairs |= {(j, i) for i, j in pairs}
    tall = {1, 2, 3, 4, 5, 9}
    assert enclosing_rings(owner, boxes, valid, among=tall) == (set(), set())  # none alone
    # the far rim lines the floor through the far wall's face: it touches two that do
    assert enclosing_rings(owner, boxes, valid, pairs, tall) == ({1, 2, 3}, set())
    owner[(owner == 0) & (np.arange(100) < 81)] = 8  # a floor above the table's tolerance
    owner[22:58, 9] = 0
    walls, floors = enclosing_rings(owner, ndimage.find_objects(owner), valid, pairs, tall)
    assert walls == {1, 2, 3} and floors == {8}
    # a cluttered bin: tall items around a gap less than half as large as each of them
    bin_ = np.zeros((40, 40), np.int64)
    bin_[5:35, 5:20], bin_[5:35, 22:35] = 1, 2
    bin_[5:12, 20:22], bin_[28:35, 20:22] = 1, 2
    bin_[14:26, 12:28] = 0  # the gap between them
    assert enclosing_rings(bin_, ndimage.find_objects(bin_), np.ones(bin_.shape, bool),
                           {(1, 2), (2, 1)}) == (set(), set())


def height_map_tote(floor, boxes=()):
    """A tote (200 mm walls, 6 px thick) on a table at 20 mm, seen whole from above
    as a height map, its floor at ``floor`` mm, ``boxes`` (rows, cols, top) in it."""
    z = table((160, 160))
    z[20:140, 20:140] = 200.0
    z[26:134, 26:134] = floor
    for rows, cols, top in boxes:
        z[rows, cols] = top
    return noisy(z)


def test_a_raised_tote_floor_is_a_structure_the_items_on_it_are_not():
    found = run(height_map_tote(35.0, [(np.s_[50:80], np.s_[40:75], 95.0),
                                       (np.s_[90:120], np.s_[80:120], 75.0)])).holdsite
    assert found.holdsite is not None and found.holdsite.elevation > 90.0, found.reason
    structures = {o.id for o in found.objects if o.structure}
    assert len(structures) == 2  # the walls and the floor, not the boxes standing on it
    assert run(height_map_tote(35.0)).holdsite.holdsite is None  # empty: nothing to pick


def test_items_that_ring_a_lower_item_in_a_tote_are_not_its_walls():
    z = table((160, 160))
    z[:8, :] = z[-8:, :] = z[:, :8] = z[:, -8:] = 220.0  # the tote's walls along the frame
    z[40:60, 40:120] = z[100:120, 40:120] = 120.0  # four boxes in a square
    z[60:100, 40:60] = z[60:100, 100:120] = 120.0
    z[62:98, 62:98] = 60.0  # a lower box inside it
    found = run(noisy(z)).holdsite
    assert found.holdsite is not None and found.holdsite.elevation > 115.0, found.reason
    assert not any(o.structure for o in found.objects if o.pixels < 3000)


def tote_view(mount, width=700.0, height=800.0, item=False, shape=(240, 320), tool=False,
              lift=0.0):
    """An empty tote (200 mm walls with a 25 mm rim, on a table) seen by a camera
    ``height`` mm above the floor, tilted ``mount`` degrees; ``width`` mm across; with
    ``item`` a box in it, with ``tool`` an arm reaching in from the far side of the view
    350 mm above the floor; its floor ``lift`` mm above the table (at 0 within the
    support's tolerance of it). Depth image, config (a 20 mm cup) and the render."""
    from rangeseg_cli.synth.camera import CAMERAS, Item, camera_for, render_items, support_plane
    from rangeseg_cli.synth.scenes import box, pose

    cam = camera_for(CAMERAS["ideal"], shape, height=height, tilt=(mount, 0.0))
    axis = cam.R[:, 2]
    turn = pose(yaw=math.degrees(math.atan2(axis[1], axis[0])))
    lx, ly, t, rim, wall = width, 500.0, 6.0, 25.0, 200.0
    parts = [box(t, ly + 2 * t, wall, "wall").moved(pose(x)) for x in (-lx / 2 - t / 2,
                                                                        lx / 2 + t / 2)]
    parts += [box(lx, t, wall, "wall").moved(pose(0, y)) for y in (-ly / 2 - t / 2,
                                                                   ly / 2 + t / 2)]
    parts += [box(rim, ly + 2 * rim, 8.0, "rim").moved(pose(x, 0, wall))
              for x in (-lx / 2 - rim / 2, lx / 2 + rim / 2)]
    parts += [box(lx + 2 * rim, rim, 8.0, "rim").moved(pose(0, y, wall))
              for y in (-ly / 2 - rim / 2, ly / 2 + rim / 2)]
    floor = box(lx, ly, 10.0, "floor").moved(pose(0, 0, lift - 10.0)).moved(turn)
    items = [support_plane("table", -10.0), Item("floor", (floor,), False, "support"),
             Item("tote", tuple(p.moved(turn) for p in parts), False, "tote")]
    if item:
        things = box(120.0, 90.0, 60.0, "item").moved(pose(-40.0, 30.0, lift, yaw=20))
        things = things.moved(turn)
        items.append(Item("item", (things,), True, "item"))
    if tool:
        arm = box(900.0, 60.0, 60.0, "arm").moved(pose(450.0, 0, 350.0)).moved(turn)
        items.append(Item("arm", (arm,), False, "gripper"))
    view = render_items(cam, items)
    config = load_config(overrides={
        "input": {"larger_is_closer": False, "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy],
                  "metres_per_unit": 0.001},
        "holdsite": {"footprint_mm": [20.0, 20.0]}})
    return np.where(np.isfinite(view.depth), view.depth, 0.0), config, view


@pytest.mark.parametrize("mount", [30.0, 45.0])
@pytest.mark.parametrize("tool", [False, True])
def test_an_empty_tote_seen_at_a_slant_has_nothing_to_pick_not_its_rim(mount, tool):
    # the near wall crosses the view; the robot's arm over the tote changes nothing
    depth, config, view = tote_view(mount, width=1600.0, tool=tool)
    found = run_pipeline(depth, config).holdsite
    assert found.holdsite is None, (found.holdsite, found.reason)


@pytest.mark.parametrize(("mount", "height", "lift"), [(45.0, 1000.0, 0.0), (0.0, 1300.0, 15.0),
                                                      (20.0, 1300.0, 15.0)])
def test_a_tote_seen_whole_gives_its_item_not_its_rim(mount, height, lift):
    # at a slant the tote parts into rim, near wall and far wall, none a ring alone; with
    # its floor above the table the support is the table and the floor an object in the ring
    depth, config, view = tote_view(mount, height=height, item=True, lift=lift)
    found = run_pipeline(depth, config).holdsite
    faces = [view.surfaces[view.gt[s.row, s.col] - 1]["name"] for s in _sites(found)]
    assert faces[0] == "item top", found.reason
    assert not any(face.startswith(("rim", "wall", "floor")) for face in faces)
    # empty, the tote has nothing to pick: not its rim, not its floor
    depth, config, view = tote_view(mount, height=height, lift=lift)
    found = run_pipeline(depth, config).holdsite
    assert found.holdsite is None, found.holdsite


def test_a_tote_seen_whole_from_above_is_never_picked_its_item_is():
    depth, config, view = tote_view(0.0, height=1300.0)  # the rim all round, in view
    assert run_pipeline(depth, config).holdsite.holdsite is None
    depth, config, view = tote_view(0.0, height=1300.0, item=True)
    found = run_pipeline(depth, config).holdsite
    faces = {view.surfaces[view.gt[s.row, s.col] - 1]["name"] for s in _sites(found)}
    assert faces == {"item top"}


def test_an_item_lying_on_another_across_a_band_of_edge_pixels_covers_it():
    from rangeseg_cli.stages.holdsite import ObjectInfo, ObjectMap, covered_across_gaps

    labels = np.zeros((60, 100), np.int32)
    z = np.full(labels.shape, np.nan)
    labels[10:50, 5:40], z[10:50, 5:40] = 1, 60.0  # an item
    labels[15:45, 45:70], z[15:45, 45:70] = 2, 140.0  # one lying on it, 5 px of ramp between
    labels[15:45, 78:95], z[15:45, 78:95] = 3, 50.0  # one 8 px beyond: too far to tell
    labels[52:58, 5:40], z[52:58, 5:40] = 4, 200.0  # a structure (the arm) beside the item
    objects = [ObjectInfo(id=k, surfaces=(k,), pixels=int((labels == k).sum()),
                          centroid=(0.0, 0.0), structure=k == 4) for k in (1, 2, 3, 4)]
    where = ObjectMap(objects, labels)
    covered = {o.id: o.covered_by for o in covered_across_gaps(objects, where, z, 6.0)}
    assert covered == {1: (2,), 2: (), 3: (), 4: ()}
    # within the step threshold the two are side by side, not one on the other
    z[15:45, 45:70] = 64.0
    assert all(not o.covered_by for o in covered_across_gaps(objects, where, z, 6.0))


def test_items_are_compared_across_edge_bands_only_on_a_view_from_above():
    from rangeseg_cli.cell.workspace import Plane
    from rangeseg_cli.stages.holdsite import VIEW_SLANT, seen_from_above

    def support(degrees: float) -> Plane:
        t = np.radians(degrees)
        return Plane((0.0, -float(np.sin(t)), float(np.cos(t))), -1000.0, 0.9)

    assert seen_from_above(None)
    assert seen_from_above(support(0.0)) and seen_from_above(support(VIEW_SLANT - 1))
    assert not seen_from_above(support(VIEW_SLANT + 1))
    assert not seen_from_above(support(45.0)) and not seen_from_above(support(-30.0))
    flipped = support(10.0)  # a camera's support normal may point either way along z
    flipped = Plane(tuple(-v for v in flipped.normal), 1000.0, 0.9)
    assert flipped.normal[2] < 0 and seen_from_above(flipped)


def test_items_side_by_side_on_the_support_do_not_cover_each_other():
    from rangeseg_cli.stages.holdsite import ObjectInfo, ObjectMap, covered_across_gaps

    labels = np.zeros((60, 100), np.int32)
    height = np.zeros(labels.shape)  # the table between them
    labels[10:50, 5:40], height[10:50, 5:40] = 1, 60.0
    labels[15:45, 45:70], height[15:45, 45:70] = 2, 140.0
    objects = [ObjectInfo(id=k, surfaces=(k,), pixels=int((labels == k).sum()),
                          centroid=(0.0, 0.0)) for k in (1, 2)]
    on_table = np.abs(height) <= 5.0
    where = ObjectMap(objects, labels)
    assert all(not o.covered_by for o in covered_across_gaps(objects, where, height, 6.0,
                                                             on_table))
    on_table[:] = False  # a band of edge pixels between them: the higher lies on the lower
    found = {o.id: o.covered_by for o in covered_across_gaps(objects, where, height, 6.0,
                                                             on_table)}
    assert found == {1: (2,), 2: ()}
    # a pair the step edges already relate is left as it is (never covered both ways)
    objects[1] = dataclasses.replace(objects[1], covered_by=(1,))
    found = {o.id: o.covered_by for o in covered_across_gaps(objects, where, height, 6.0)}
    assert found == {1: (), 2: (1,)}


def test_a_shadow_joined_to_the_frame_hides_nothing_of_its_caster():
    from rangeseg_cli.stages.holdsite import HIDING_WIDTH, in_view_border, outer_invalid
    from rangeseg_cli.stages.holdsite import shadow_casters as casters

    def shadow_casters(labels, valid, z, tol):
        return casters(labels, valid, z, tol, outer_invalid(valid, HIDING_WIDTH))

    z = np.full((60, 90), 10.0)  # the table, label 1
    labels = np.ones(z.shape, np.int32)
    labels[20:40, 20:40], z[20:40, 20:40] = 2, 80.0  # a box
    labels[20:40, 39] = 0  # with a band of edge pixels along its right side
    valid = np.ones(z.shape, bool)
    valid[15:40, 40:48] = False  # its shadow on the table, right of it ...
    valid[:16, 44:48] = False  # ... joined to the frame by a channel of no reading
    assert shadow_casters(labels, valid, z, 6.0) == {2}
    assert 2 not in in_view_border(labels, valid, z, 6.0)
    # without a support, at a slant the order's heights are along the sensor's axis
    from rangeseg_cli.cell.workspace import Plane, Workspace

    def hidden(degrees):
        t = np.radians(degrees)
        return Workspace(valid, None, None, 5.0, hidden=Plane(
            (0.0, float(np.sin(t)), float(np.cos(t))), 0.0, 0.1))

    assert 2 not in in_view_border(labels, valid, z, 6.0, hidden(5.0))
    assert 2 in in_view_border(labels, valid, z, 6.0, hidden(35.0))
    # what lies beyond at the box's height may go on under the invalid area
    z[15:40, 48:60], labels[15:40, 48:60] = 80.0, 3
    assert shadow_casters(labels, valid, z, 6.0) == set()
    assert 2 in in_view_border(labels, valid, z, 6.0)
    # as does a box whose invalid area runs on to the frame
    z[15:40, 48:60], labels[15:40, 48:60] = 10.0, 1
    valid[20:40, 40:] = False
    assert 2 not in shadow_casters(labels, valid, z, 6.0)
    # or that meets it mostly down the columns: a few crossings along the rows tell nothing
    valid = np.ones(z.shape, bool)
    valid[:20, 15:45] = False  # an area over the box's top, reaching the frame
    assert 2 not in shadow_casters(labels, valid, z, 6.0)


def test_items_are_compared_by_their_height_above_the_support_not_along_the_axis():
    from rangeseg_cli.cell.workspace import Plane, Workspace
    from rangeseg_cli.stages.holdsite import ObjectInfo, ObjectMap, _covered_from_above

    labels = np.zeros((60, 100), np.int32)
    labels[10:50, 5:40], labels[15:45, 45:70] = 1, 2
    z = np.where(labels == 1, 90.0, np.where(labels == 2, 40.0, np.nan))  # 1 nearer the camera
    height = np.where(labels == 1, 30.0, np.where(labels == 2, 80.0, np.nan))  # 2 higher
    objects = [ObjectInfo(id=k, surfaces=(k,), pixels=int((labels == k).sum()),
                          centroid=(0.0, 0.0)) for k in (1, 2)]
    where = ObjectMap(objects, labels)

    def space(degrees: float) -> Workspace:
        t = np.radians(degrees)
        return Workspace(labels > 0, height, Plane((0.0, float(np.sin(t)), float(np.cos(t))),
                                                   0.0, 0.9), 5.0)

    on_support = np.abs(height) <= 5.0
    found = {o.id: o.covered_by
             for o in _covered_from_above(objects, where, z, space(10), 6.0, on_support)}
    assert found == {1: (2,), 2: ()}
    assert _covered_from_above(objects, where, z, space(40), 6.0, on_support) == objects


def test_windows_keep_clear_of_pixels_beside_no_reading_when_the_surface_allows():
    from scipy import ndimage

    z = table()
    z[12:52, 12:52] = 120.0
    result = run(noisy(z))
    heights, labels = holdsite_module._check(result.heights, result.labels)
    box = surface_at(result, 32, 32)
    valid = np.isfinite(heights)
    valid[28:31, 20:23] = False  # a dropout in the box's top (its pixels left unlabelled)
    labels = np.where(valid, labels, 0)
    beside = ndimage.binary_dilation(~valid, np.ones((3, 3), bool)) & valid
    cfg = holdsite_module.effective_holdsite(load_config())

    def scene(mask):
        return holdsite_module._Scene(labels, mask, heights, cfg, holdsite_module._angles(cfg))

    def touching(hits):
        return [bool(beside[window(Site(int(r), int(c), cfg.size))].any())
                for r, c in zip(hits.rows, hits.cols, strict=True)]

    plain = scene(valid)
    found, _ = holdsite_module._collect(plain, [box], 1)
    assert any(touching(found[0]))  # the windows beside the dropout are accepted ...
    clear = scene(valid & ~beside)
    found, _ = holdsite_module._collect(plain, [box], 1, (clear, {box.id}))
    assert found[0].scene is clear and not any(touching(found[0]))  # ... but left out
    found, _ = holdsite_module._collect(plain, [box], 1, (scene(valid & False), {box.id}))
    assert found[0].scene is plain  # with none clear, the surface keeps its windows
    found, _ = holdsite_module._collect(plain, [box], 1, (clear, set()))
    assert found[0].scene is plain  # a surface with no pixel beside no reading: one search


@dataclasses.dataclass
class Site:
    row: int
    col: int
    size: tuple[int, int]
