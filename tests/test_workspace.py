"""The workspace (support plane, pickable pixels), structures, footprint_mm and flatness.

Constructed scenes with known answers: height maps (larger = closer) and depth
images rendered by a pinhole camera (fx = fy = 200, depth in mm).
"""

import math

import numpy as np
import pytest
from scipy import ndimage

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.cell.workspace import (
    BACKGROUND_REACH,
    HIDDEN_SUPPORT,
    MAX_BELOW,
    assess,
    find_support,
    matches_background,
    points,
    polygon_mask,
    region_of_interest,
)
from rangeseg_cli.config import ConfigError, HoldsiteConfig, InputConfig, WorkspaceConfig
from rangeseg_cli.stages.holdsite import (
    effective_holdsite,
    enough_clearance,
    flat_limit,
    footprint,
    footprint_pixels,
    site_flat_rms,
    window_flat_rms,
)

# --- helpers ---------------------------------------------------------------------------

FX = 200.0
SHAPE = (120, 160)
CX, CY = (SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2


def noisy(z, sigma=0.5, seed=0):
    return z + np.random.default_rng(seed).normal(0.0, sigma, z.shape)


def camera(**kw):
    return InputConfig(intrinsics=(FX, FX, CX, CY), larger_is_closer=False, invalid=0.0,
                       metres_per_unit=0.001, **kw)


def cam_config(**tables):
    over: dict = {"input": {"intrinsics": [FX, FX, CX, CY]}}
    for table, values in tables.items():
        over.setdefault(table, {}).update(values)
    return load_config(preset="mm-depth", overrides=over)


def floor_frame(tilt_deg, dist=600.0):
    """Origin and rows (x, y, normal) of a floor through (0, 0, dist), normal tilted about x."""
    t = math.radians(tilt_deg)
    n = np.array([0.0, -math.sin(t), -math.cos(t)])  # towards the camera
    e1 = np.array([1.0, 0.0, 0.0])
    return np.array([0.0, 0.0, dist]), np.stack([e1, np.cross(n, e1), n])


def rays(shape=SHAPE):
    h, w = shape
    v, u = np.indices(shape, dtype=np.float64)
    return np.stack([(u - (w - 1) / 2) / FX, (v - (h - 1) / 2) / FX, np.ones(shape)], axis=-1)


def render(tilt_deg=30.0, boxes=(), dist=600.0, shape=SHAPE):
    """Depth (mm) of the floor of :func:`floor_frame` with boxes (x0, x1, y0, y1, h) on it."""
    d = rays(shape)
    origin, rot = floor_frame(tilt_deg, dist)
    n = rot[2]
    depth = (n @ origin) / (d @ n)
    o, dq = rot @ (-origin), d @ rot.T  # the camera and the rays in floor coordinates
    for x0, x1, y0, y1, bh in boxes:
        lo, hi = np.array([x0, y0, 0.0]), np.array([x1, y1, bh])
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - o) / dq, (hi - o) / dq
        near = np.nanmax(np.minimum(t1, t2), axis=-1)
        far = np.nanmin(np.maximum(t1, t2), axis=-1)
        hit = (near <= far) & (near > 0) & (near < depth)
        depth = np.where(hit, near, depth)
    return depth


def plane_depth(tilt_deg, point, shape=SHAPE):
    """Depth of the 3-D plane through ``point`` with its normal tilted about the x axis."""
    t = math.radians(tilt_deg)
    n = np.array([0.0, -math.sin(t), -math.cos(t)])
    return (n @ np.asarray(point, dtype=np.float64)) / (rays(shape) @ n)


def to_pixel(p):
    return int(round(FX * p[1] / p[2] + CY)), int(round(FX * p[0] / p[2] + CX))


def site_of(result):
    return result.holdsite.holdsite


def label_at(result, row, col):
    return int(result.labels[row, col])


def run_assess(z, config, noise=0.5, **frames):
    return assess(z, config, noise, **frames)


def tote(shape=(96, 128), floor=20.0, rim=120.0, wall=12, right_margin=0):
    """A tote's floor with four walls rising to its rim towards the image border."""
    h, w = shape
    v, u = np.indices(shape, dtype=np.float64)
    inner = np.minimum.reduce([v, h - 1 - v, u, w - right_margin - 1 - u])
    return floor + np.clip((wall - inner) / wall, 0, 1) * (rim - floor)


# --- 1. the support plane --------------------------------------------------------------


def test_support_of_a_tilted_table_with_boxes_is_the_table_and_boxes_are_off_it():
    a, b, c = 20.0, 0.3, -0.2
    v, u = np.indices((96, 96), dtype=np.float64)
    table = a + b * u + c * v
    z = table.copy()
    boxes = np.zeros(z.shape, dtype=bool)
    boxes[8:40, 8:60] = boxes[52:88, 30:80] = True  # ~40 % of the image
    assert 0.35 < boxes.mean() < 0.45
    z[boxes] += 40.0
    plane = find_support(z, InputConfig(), 1.0)
    norm = math.sqrt(b * b + c * c + 1)
    np.testing.assert_allclose(plane.normal, (-b / norm, -c / norm, 1 / norm), atol=1e-6)
    assert plane.offset == pytest.approx(-a / norm, abs=1e-4)
    assert plane.inliers == pytest.approx(1 - boxes.mean(), abs=0.02)
    dist = plane.distance(points(z, InputConfig()))
    assert np.all(dist[boxes] > 30) and np.all(np.abs(dist[~boxes]) < 1e-4)


def test_support_of_a_camera_floor_tilted_30_degrees_and_box_heights_above_it():
    boxes = [(-120, -40, -60, 40, 50.0), (30, 110, -10, 70, 30.0)]
    depth = render(30.0, boxes)
    cam = camera()
    plane = find_support(-depth, cam, 6.0)
    origin, rot = floor_frame(30.0)
    cos = float(np.dot(plane.normal, rot[2]))
    assert math.degrees(math.acos(min(cos, 1.0))) < 1.0
    assert plane.offset == pytest.approx(-rot[2] @ origin, abs=2.0)
    pts = points(-depth, cam)
    for x0, x1, y0, y1, h in boxes:
        top = origin + rot.T @ np.array([(x0 + x1) / 2, (y0 + y1) / 2, h])
        row, col = to_pixel(top)
        assert depth[row, col] < render(30.0)[row, col] - 10  # on the box
        assert plane.distance(pts[row, col]) == pytest.approx(h, abs=3.0)


def test_support_is_deterministic():
    depth = noisy(render(30.0, [(-60, 20, -40, 40, 40.0)]), 1.0)
    cam = camera()
    first, second = (find_support(-depth, cam, 6.0) for _ in range(2))
    assert first == second
    assert find_support(-depth, cam, 6.0, seed=3).normal == pytest.approx(first.normal, abs=0.01)


def test_a_plane_with_the_floor_behind_it_is_not_the_support():
    z = np.zeros((100, 100))
    z[:, :60] = 30.0  # a flat slab over 60 %: the floor, 40 %, lies behind its plane
    plane = find_support(noisy(z, 0.2), InputConfig(), 1.0)
    np.testing.assert_allclose(plane.normal, (0, 0, 1), atol=0.01)
    assert plane.offset == pytest.approx(0.0, abs=0.2)
    assert plane.inliers == pytest.approx(0.4, abs=0.02)
    # with less than MAX_BELOW of the points behind it, the slab's plane is the support
    z[:, :92] = 30.0
    assert 1 - 0.92 < MAX_BELOW
    plane = find_support(noisy(z, 0.2), InputConfig(), 1.0)
    assert plane.offset == pytest.approx(-30.0, abs=0.2)


def test_no_support_without_enough_valid_pixels():
    z = np.full((64, 64), np.nan)
    z[:5, :5] = 1.0
    assert find_support(z, InputConfig(), 1.0) is None


# --- 2. pickable pixels ----------------------------------------------------------------


def test_roi_box_mask_and_triangle_polygon():
    shape = (40, 50)
    box = region_of_interest(shape, WorkspaceConfig(roi_box=(5, 10, 20, 30)))
    expected = np.zeros(shape, dtype=bool)
    expected[5:20, 10:30] = True
    np.testing.assert_array_equal(box, expected)
    mask = np.zeros(shape, dtype=bool)
    mask[:, 20:] = True
    both = region_of_interest(shape, WorkspaceConfig(roi_box=(5, 10, 20, 30)), mask)
    np.testing.assert_array_equal(both, expected & mask)
    tri = ((2.3, 3.1), (35.7, 12.2), (10.4, 46.9))
    inside = polygon_mask(shape, tri)
    assert inside[10, 15] and not inside[30, 40] and not inside[0, 0]
    (r0, c0), (r1, c1), (r2, c2) = tri
    rows, cols = np.indices(shape, dtype=np.float64)

    def side(ra, ca, rb, cb):
        return (cb - ca) * (rows - ra) - (rb - ra) * (cols - ca)

    s0, s1, s2 = side(r0, c0, r1, c1), side(r1, c1, r2, c2), side(r2, c2, r0, c0)
    brute = ((s0 > 0) & (s1 > 0) & (s2 > 0)) | ((s0 < 0) & (s1 < 0) & (s2 < 0))
    np.testing.assert_array_equal(inside, brute)
    np.testing.assert_array_equal(
        region_of_interest(shape, WorkspaceConfig(roi_polygon=tri)), brute)


def test_height_band_keeps_only_the_box_between_min_and_max_height():
    z = np.full((64, 96), 20.0)
    z[10:30, 8:28] = 30.0    # 10 above the table
    z[10:30, 38:58] = 60.0   # 40 above
    z[10:30, 68:88] = 100.0  # 80 above
    config = load_config(overrides={"workspace": {"min_height": 20, "max_height": 60}})
    space = run_assess(z, config)
    assert space.support is not None
    np.testing.assert_array_equal(np.argwhere(space.pickable).min(axis=0), (10, 38))
    np.testing.assert_array_equal(np.argwhere(space.pickable).max(axis=0), (29, 57))
    assert space.pickable[11:29, 39:57].all()  # the corners go to the 3x3 median
    open_band = run_assess(z, load_config()).pickable
    assert open_band[11:29, 9:27].all() and open_band[11:29, 69:87].all()
    assert not open_band[40:, :].any()  # the table itself


def test_background_frame_leaves_only_the_new_box_pickable():
    v, u = np.indices((64, 64), dtype=np.float64)
    bg = 20.0 + 0.1 * u
    bg[5:20, 40:60] += 50.0  # a fixture present in the empty scene too
    scene = bg.copy()
    scene[30:50, 10:30] += 25.0
    box = np.zeros(scene.shape, dtype=bool)
    box[30:50, 10:30] = True
    space = run_assess(noisy(scene, 0.3), load_config(), noise=0.3,
                       background=noisy(bg, 0.3, seed=1))
    assert not space.pickable[~box].any()
    assert space.pickable[31:49, 11:29].all()
    without = run_assess(noisy(scene, 0.3), load_config(), noise=0.3).pickable
    assert without[8:17, 43:57].all()  # the fixture, without the background frame


def test_a_frame_behind_its_background_says_so_in_the_reason():
    # A background in mm beside a frame in 0.1 mm: "nothing stands on the support",
    # and nothing said of why.
    depth = plane_depth(0, (0, 0, 600))
    depth[20:70, 20:80] = plane_depth(0, (0, 0, 560))[20:70, 20:80]
    cfg = cam_config()
    table = noisy(plane_depth(0, (0, 0, 600)), 0.5, seed=1)
    right = run_pipeline(noisy(depth, 0.5), cfg, background=table)
    assert site_of(right) is not None
    assert "behind the background" not in right.holdsite.reason
    for other in (table / 10.0, table - 100.0):  # another unit; the camera moved back
        wrong = run_pipeline(noisy(depth, 0.5), cfg, background=other).holdsite
        assert wrong.reason.endswith("; the frame lies behind the background frame at 100% "
                                     "of the pixels both read: is the background of "
                                     "another camera, pose or depth unit?")


def test_background_holes_are_filled_from_their_neighbours_within_reach():
    bg = np.full((64, 64), 20.0)
    bg[10:18, 10:18] = np.nan  # a small hole: every pixel within reach of a reading
    bg[30:64, 30:64] = np.nan  # a large one at the corner
    scene = np.full((64, 64), 20.0)
    match = matches_background(scene, bg, 1.0)
    assert match[10:18, 10:18].all()
    assert match[30:30 + BACKGROUND_REACH, 30:].all()
    assert not match[30 + BACKGROUND_REACH + 2:, 30 + BACKGROUND_REACH + 2:].any()
    config = load_config(overrides={"workspace": {"support": False}})
    space = run_assess(scene, config, background=bg)
    assert not space.pickable[10:18, 10:18].any()
    assert space.pickable[50:, 50:].all()  # farther than the reach: nothing known


def test_a_scene_behind_the_background_is_not_pickable():
    bg = np.full((64, 64), 20.0)
    scene = bg.copy()
    scene[10:30, 10:30] = -10.0  # farther than the empty scene (a hole dug, a lid gone)
    scene[40:60, 40:60] = 50.0
    assert matches_background(scene, bg, 1.0)[10:30, 10:30].all()
    config = load_config(overrides={"workspace": {"support": False}})
    pickable = run_assess(scene, config, background=bg).pickable
    assert not pickable[10:30, 10:30].any()
    assert pickable[41:59, 41:59].all()
    assert not pickable[:, :38].any()


# --- 3. holdsites in the workspace -----------------------------------------------------


def test_roi_mask_over_one_of_two_equal_boxes_puts_the_site_on_that_box():
    z = np.full((64, 96), 20.0)
    z[20:44, 10:40] = 80.0
    z[20:44, 56:86] = 80.0
    free = site_of(run_pipeline(noisy(z), load_config()))
    assert 56 <= free.col < 86  # the tie goes to the right-hand box
    roi = np.zeros(z.shape, dtype=bool)
    roi[:, :48] = True
    result = run_pipeline(noisy(z), load_config(), roi=roi)
    site = site_of(result)
    assert 20 <= site.row < 44 and 10 <= site.col < 40
    assert label_at(result, 30, 70) in result.holdsite.outside
    assert result.holdsite.to_dict()["outside_workspace"] == list(result.holdsite.outside)


def test_a_tall_bar_from_the_border_is_a_structure_and_the_box_is_picked():
    z = np.full((80, 80), 20.0)
    z[44:64, 40:64] = 50.0  # a low box
    z[0:30, 10:22] = 200.0  # a finger entering from the top border
    result = run_pipeline(noisy(z), load_config())
    site = site_of(result)
    assert 44 <= site.row < 64 and 40 <= site.col < 64
    objects = {tuple(o["surfaces"]): o for o in result.holdsite.to_dict()["objects"]}
    bar = objects[(label_at(result, 10, 15),)]
    box = objects[(label_at(result, 54, 52),)]
    assert bar["structure"] and bar["touches_border"]
    assert not box["structure"] and box["stands_on_support"]


def test_an_empty_tote_has_nothing_to_pick_and_one_box_in_it_is_picked():
    z = tote()
    result = run_pipeline(noisy(z), load_config())
    assert site_of(result) is None
    assert result.holdsite.reason.startswith("nothing to pick")
    assert result.holdsite.to_dict()["holdsite"] is None
    z[36:60, 50:80] = 60.0
    result = run_pipeline(noisy(z), load_config())
    site = site_of(result)
    assert 36 <= site.row < 60 and 50 <= site.col < 80
    assert site.surface == label_at(result, 48, 65)


def test_a_box_outside_the_tote_is_never_the_site():
    z = tote(right_margin=20)
    z[:, 108:] = 10.0          # the table outside the tote, below its floor
    z[30:60, 112:126] = 70.0   # a box out there: the highest thing in view
    z[36:60, 40:70] = 45.0     # a lower box in the tote
    result = run_pipeline(noisy(z), load_config())
    site = site_of(result)
    assert 36 <= site.row < 60 and 40 <= site.col < 70
    outside = label_at(result, 45, 119)
    assert outside in result.holdsite.outside
    assert all(c.surface != outside for c in result.holdsite.candidates)
    z[36:60, 40:70] = 20.0     # nothing in the tote
    result = run_pipeline(noisy(z), load_config())
    assert site_of(result) is None and result.holdsite.reason.startswith("nothing to pick")
    assert label_at(result, 45, 119) in result.holdsite.outside
    paper = run_pipeline(noisy(z), load_config(preset="paper"))
    assert site_of(paper).surface == label_at(paper, 45, 119)  # the paper's highest surface


def test_the_paper_preset_has_no_workspace_and_picks_the_highest_surface():
    z = np.full((80, 80), 20.0)
    z[0:30, 10:22] = (200.0 - 2.0 * np.arange(30))[:, None]  # a finger rising to the border
    default = run_pipeline(noisy(z), load_config())
    assert site_of(default) is None
    assert default.holdsite.reason.startswith("nothing to pick")
    assert "structure" in default.holdsite.reason
    assert [o.structure for o in default.holdsite.objects] == [True]
    paper = run_pipeline(noisy(z), load_config(preset="paper"))
    site = site_of(paper)
    assert site.row < 30 and 10 <= site.col < 22
    assert paper.holdsite.outside == ()
    assert not any(o.structure or o.stands for o in paper.holdsite.objects)
    empty = run_pipeline(noisy(tote()), load_config(preset="paper"))
    site = site_of(empty)  # the empty tote's floor, in view
    assert 12 <= site.row < 84 and 12 <= site.col < 116


# --- 4. footprint_mm -------------------------------------------------------------------


@pytest.mark.parametrize(("mm", "depth", "expected"), [
    (20.0, 600.0, 21),   # 20 px: a tie, rounded up
    (20.6, 600.0, 21),   # 20.6 px
    (22.4, 600.0, 23),   # 22.4 px
    (10.0, 600.0, 11),   # 10 px: a tie
    (0.5, 600.0, 1),     # half a pixel
    (1000.0, 600.0, 255),  # 1000 px: clipped
    (20.0, 1200.0, 11),  # 10 px at twice the depth
])
def test_footprint_pixels_are_odd_and_scale_with_depth(mm, depth, expected):
    cam = InputConfig(intrinsics=(600.0, 600.0, 0.0, 0.0), larger_is_closer=False,
                      metres_per_unit=0.001)
    cfg = HoldsiteConfig(footprint_mm=(mm, mm))
    assert footprint_pixels(cfg, cam, depth) == (expected, expected)


def test_footprint_pixels_rows_follow_fy_and_cols_fx_and_need_intrinsics():
    cam = InputConfig(intrinsics=(600.0, 300.0, 0.0, 0.0), larger_is_closer=False,
                      metres_per_unit=0.001)
    cfg = HoldsiteConfig(footprint_mm=(40.0, 20.0))
    assert footprint_pixels(cfg, cam, 600.0) == (21, 21)
    metres = InputConfig(intrinsics=(600.0, 600.0, 0.0, 0.0), larger_is_closer=False,
                         metres_per_unit=1.0)
    assert footprint_pixels(cfg, metres, 0.6) == (41, 21)  # depth in metres
    assert footprint_pixels(cfg, InputConfig(), 600.0) == cfg.size
    assert footprint_pixels(HoldsiteConfig(size=(5, 9)), cam, 600.0) == (5, 9)


def test_footprint_mm_with_one_side_is_a_config_error_naming_the_key():
    with pytest.raises(ConfigError, match="footprint_mm"):
        load_config(overrides={"holdsite": {"footprint_mm": [20.0, 0.0]}})


def test_site_size_on_a_camera_scene_is_footprint_mm_at_its_depth():
    depth = plane_depth(0, (0, 0, 600))
    depth[20:70, 20:80] = plane_depth(0, (0, 0, 560))[20:70, 20:80]
    cfg = cam_config(holdsite={"footprint_mm": [30.0, 30.0]})
    result = run_pipeline(noisy(depth, 0.5), cfg)
    site = site_of(result)
    surface = next(s for s in result.surfaces if s.id == site.surface)
    assert surface.mean_height == pytest.approx(-560.0, abs=1.0)
    # 30 mm at 560 mm and f = 200: 10.7 px, the odd 11
    assert site.size == (11, 11) == footprint_pixels(cfg.holdsite, cfg.input, 560.0)
    assert result.holdsite.to_dict()["holdsite"]["size"] == [11, 11]
    rows, cols = site.size
    window = result.labels[site.row - rows // 2: site.row + rows // 2 + 1,
                           site.col - cols // 2: site.col + cols // 2 + 1]
    assert np.all(window == site.surface)


@pytest.mark.parametrize(("tables", "said"), [
    ({"input": {"metres_per_unit": 1.0}}, "spans 0.00667 px at the frame's median depth of 600 m"),
    ({"holdsite": {"footprint_mm": [0.02, 0.02]}}, "spans 0.00667 px at the frame's median "
                                                  "depth of 0.6 m"),
])
def test_a_cup_smaller_than_a_pixel_is_a_wrong_unit_and_no_site(tables, said):
    # Millimetres read as metres: a 1x1 px site 600 m away, given without a word.
    depth = plane_depth(0, (0, 0, 600))
    depth[20:70, 20:80] = plane_depth(0, (0, 0, 560))[20:70, 20:80]
    assert site_of(run_pipeline(noisy(depth, 0.5), cam_config())) is not None
    result = run_pipeline(noisy(depth, 0.5), cam_config(**tables)).holdsite
    assert result.holdsite is None and result.candidates == ()
    assert result.reason.startswith("no site sought: holdsite.footprint_mm = ")
    assert said in result.reason and "check --preset" in result.reason


# --- 5. flatness -----------------------------------------------------------------------


def brute_flat_rms(z, fp):
    h, w = z.shape
    kr, kc = fp.shape[0] // 2, fp.shape[1] // 2
    fr, fc = np.nonzero(fp)
    out = np.full(z.shape, np.nan)
    for r in range(h):
        for c in range(w):
            rr, cc = r + fr - kr, c + fc - kc
            if rr.min() < 0 or cc.min() < 0 or rr.max() >= h or cc.max() >= w:
                continue
            vals = z[rr, cc]
            if not np.isfinite(vals).all():
                continue
            a = np.column_stack([np.ones(vals.size), cc, rr]).astype(np.float64)
            coef, *_ = np.linalg.lstsq(a, vals, rcond=None)
            out[r, c] = np.sqrt(np.mean((vals - a @ coef) ** 2))
    return out


@pytest.mark.parametrize("fp", [np.ones((5, 7), dtype=bool), footprint((3, 7), 30.0)],
                         ids=["rectangle", "rotated"])
def test_window_flat_rms_is_the_plane_fit_rms_of_each_window(fp):
    rng = np.random.default_rng(1)
    z = 500.0 + rng.normal(0.0, 2.0, (20, 24))
    z[9, 11] = np.nan
    got = window_flat_rms(z, fp)
    want = brute_flat_rms(z, fp)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    assert np.isnan(got[9, 11]) and np.isfinite(want).sum() > 50
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    for r, c in np.argwhere(np.isfinite(want))[::17]:
        assert site_flat_rms(z, int(r), int(c), fp) == pytest.approx(want[r, c], rel=1e-6)


def test_window_flat_rms_of_a_plane_is_zero():
    v, u = np.indices((30, 30), dtype=np.float64)
    z = 800.0 + 3.5 * u - 2.25 * v
    got = window_flat_rms(z, footprint((5, 9), 45.0))
    assert np.nanmax(got) < 1e-5 and np.isfinite(got).sum() > 200
    assert site_flat_rms(z, 15, 15, np.ones((7, 7), dtype=bool)) < 1e-9


def wavy_box():
    v, u = np.indices((64, 64), dtype=np.float64)
    z = np.full((64, 64), 20.0)
    bumps = 3.0 * np.sin(2 * np.pi * u / 12) * np.sin(2 * np.pi * v / 12)
    z[12:52, 12:52] = 80.0 + bumps[12:52, 12:52]
    return noisy(z, 0.2)


def test_a_rough_box_top_is_refused_naming_the_plane_fit_rms():
    result = run_pipeline(wavy_box(), load_config(overrides={"holdsite": {
        "max_flat_rms": 0.5}}))
    assert site_of(result) is None
    reason = result.holdsite.reason
    # an object is there, too rough to seal on: not "nothing to pick"
    assert not reason.startswith("nothing to pick") and "plane-fit RMS <= 0.5" in reason
    limit = 1.0
    result = run_pipeline(wavy_box(), load_config(overrides={"holdsite": {
        "max_flat_rms": limit}}))
    sites = [site_of(result), *result.holdsite.candidates]
    assert sites[0] is not None
    for site in sites:
        assert site.flat_rms <= limit
        fp = footprint(site.size, site.angle)
        assert site.flat_rms == pytest.approx(
            site_flat_rms(result.heights, site.row, site.col, fp), rel=1e-9)
    auto = run_pipeline(wavy_box(), load_config())
    limit = flat_limit(effective_holdsite(load_config()), load_config().input,
                       auto.noise_sigma)
    assert limit == pytest.approx(2 * auto.noise_sigma + 1.0)
    assert site_of(auto).flat_rms <= limit


def test_flat_limit_defaults():
    hold = HoldsiteConfig()
    assert flat_limit(hold, InputConfig(), 0.5) == pytest.approx(2.0)
    assert flat_limit(hold, camera(), 0.5) == pytest.approx(2.0)  # + 1 mm, in mm
    metres = InputConfig(intrinsics=(FX, FX, 0.0, 0.0), larger_is_closer=False,
                         metres_per_unit=1.0)
    assert flat_limit(hold, metres, 0.0005) == pytest.approx(0.002)
    assert flat_limit(HoldsiteConfig(max_flat_rms=0.3), camera(), 5.0) == 0.3
    paper = load_config(preset="paper").holdsite
    assert flat_limit(paper, InputConfig(), 0.5) == math.inf


# --- 6. max_tilt -----------------------------------------------------------------------


def test_max_tilt_applies_with_a_lateral_scale_only():
    assert effective_holdsite(load_config()).max_tilt == 90.0
    assert effective_holdsite(load_config(overrides={
        "input": {"units_per_pixel": 1.0}})).max_tilt == 45.0
    assert effective_holdsite(cam_config()).max_tilt == 45.0


def test_a_60_degree_camera_face_is_refused_and_the_level_box_below_is_picked():
    depth = plane_depth(0, (0, 0, 600))
    depth[20:60, 20:60] = plane_depth(0, (0, 0, 560))[20:60, 20:60]
    depth[48:78, 95:140] = plane_depth(60, (0, 0, 480))[48:78, 95:140]
    assert depth[48:78, 95:140].max() < 540  # the tilted face is higher all over
    img = noisy(depth, 0.5)
    site = site_of(run_pipeline(img, cam_config()))
    assert 20 <= site.row < 60 and 20 <= site.col < 60
    assert site.approach_camera[2] == pytest.approx(1.0, abs=0.01)
    steep = site_of(run_pipeline(img, cam_config(holdsite={"max_tilt": 90.0})))
    assert 48 <= steep.row < 78 and 95 <= steep.col < 140
    tilt = math.degrees(math.acos(abs(steep.approach_camera[2])))
    assert tilt == pytest.approx(60.0, abs=3.0)


def test_a_steep_ramp_in_a_height_map_counts_only_with_units_per_pixel():
    z = np.full((64, 96), 20.0)
    z[16:48, 8:40] = 60.0
    z[16:48, 52:88] = 80.0 + 2.0 * np.arange(36)[None, :]  # 63 degrees at 1 unit/pixel
    site = site_of(run_pipeline(noisy(z), load_config()))
    assert 52 <= site.col < 88  # no lateral scale: no tilt test, the higher ramp
    scaled = site_of(run_pipeline(noisy(z), load_config(overrides={
        "input": {"units_per_pixel": 1.0}})))
    assert 8 <= scaled.col < 40


@pytest.mark.parametrize("side, expected", [(21.0, 21), (19.5, 19), (7.0, 7), (1.0, 1),
                                            (22.4, 23)])
def test_footprint_mm_rounds_to_the_nearest_odd_count(side, expected):
    from rangeseg_cli.config import HoldsiteConfig, InputConfig
    from rangeseg_cli.stages.holdsite import footprint_pixels

    camera = InputConfig(larger_is_closer=False, metres_per_unit=0.001,
                         intrinsics=(600.0, 600.0, 0.0, 0.0))
    cfg = HoldsiteConfig(footprint_mm=(side, side))
    assert footprint_pixels(cfg, camera, 600.0) == (expected, expected)


@pytest.mark.parametrize("workspace, match", [
    ({"support": False, "min_height": 30.0}, r"height band is measured above the support"),
    ({"support": False, "max_height": 30.0}, r"height band is measured above the support"),
    ({"min_height": 50.0, "max_height": 10.0}, r"min_height = 50.0: must be below max_height"),
    ({"roi_polygon": [[0, 0], [1, 1], [2, 2]]}, r"roi_polygon .*: the polygon has no area"),
])
def test_workspace_keys_that_contradict_each_other_are_refused(workspace, match):
    with pytest.raises(ConfigError, match=match):
        load_config(overrides={"workspace": workspace})


def test_a_flat_finger_from_the_border_over_an_empty_table_is_not_picked():
    z = np.full((80, 80), 20.0)
    z[0:30, 10:24] = 200.0  # hovering: its lowest pixels as high as its top
    result = run_pipeline(noisy(z), load_config())
    assert site_of(result) is None and result.holdsite.reason.startswith("nothing to pick")
    finger = next(o for o in result.holdsite.objects if label_at(result, 10, 16) in o.surfaces)
    assert finger.structure
    paper = run_pipeline(noisy(z), load_config(preset="paper"))
    assert label_at(paper, paper.holdsite.holdsite.row, paper.holdsite.holdsite.col) == \
        label_at(paper, 10, 16)


def arm_with_fingers(z, top=68.0, drop=6.0):
    """``z`` with a flat arm reaching in from the top border and two narrow fingers below it."""
    z = z.copy()
    z[0:40, 64:84] = top
    z[40:50, 64:70] = z[40:50, 78:84] = top - drop
    return z


def test_an_arm_on_its_fingers_over_an_empty_table_is_not_picked():
    # the fingers hang just below the arm: it rests on them, so it does not hover
    result = run_pipeline(noisy(arm_with_fingers(np.full((96, 96), 20.0))), load_config())
    assert site_of(result) is None and result.holdsite.reason.startswith("nothing to pick")
    arm = next(o for o in result.holdsite.objects if label_at(result, 20, 74) in o.surfaces)
    assert arm.structure and arm.touches_border


def test_an_arm_on_its_fingers_a_little_above_the_pile_is_a_structure():
    z = np.full((96, 96), 20.0)
    z[50:84, 16:26] = 20.0 + 4.0 * np.arange(1, 11)[None, :]  # the item's side, up to its top
    z[50:84, 26:50] = 60.0  # its top, 40 above the table; the arm's 48 is not far above it
    result = run_pipeline(noisy(arm_with_fingers(z)), load_config())
    arm = next(o for o in result.holdsite.objects if label_at(result, 20, 74) in o.surfaces)
    item = next(o for o in result.holdsite.objects if label_at(result, 66, 38) in o.surfaces)
    assert arm.structure and not item.structure
    assert site_of(result).object == item.id


def test_an_item_at_the_border_on_a_narrow_piece_that_rests_on_an_item_is_picked():
    # the narrow piece stands on the item below, so it is no finger and the top item no arm
    z = np.full((96, 96), 20.0)
    z[0:30, 30:60] = 76.0  # an item cut by the top border, 56 above the table
    z[30:44, 42:48] = 70.0  # a narrow piece under its edge
    z[44:84, 16:26] = 20.0 + 4.0 * np.arange(1, 11)[None, :]  # the side of the item below
    z[44:84, 26:70] = 64.0  # its top, 44 above the table: 56 is not far above it
    result = run_pipeline(noisy(z), load_config())
    top = next(o for o in result.holdsite.objects if label_at(result, 15, 45) in o.surfaces)
    assert top.touches_border and not top.structure
    assert site_of(result).object == top.id


def test_workspace_arrays_of_another_shape_are_one_input_error():
    from rangeseg_cli.errors import InputError
    from rangeseg_cli.stages.holdsite import find_holdsite

    z = np.full((32, 32), 20.0)
    labels = np.ones((32, 32), dtype=np.int32)
    with pytest.raises(InputError, match=r"`background` \(shape \(8, 8\)\) must have the shape"):
        find_holdsite(z, labels, [], load_config(), background=np.zeros((8, 8)))
    with pytest.raises(InputError, match=r"`roi` \(shape \(32, 31\)\) must have the shape"):
        find_holdsite(z, labels, [], load_config(), roi=np.ones((32, 31), bool))


def test_an_roi_box_that_encloses_nothing_is_refused():
    with pytest.raises(ConfigError, match=r"\[workspace\] roi_box = \[5, 10, 5, 30\]: expected"):
        load_config(overrides={"workspace": {"roi_box": [5, 10, 5, 30]}})


def full_tote_boxes(gap=12.0):
    """A 4x4 grid of boxes of different heights covering the view but for ``gap`` mm aisles."""
    xs, ys = np.linspace(-260.0, 260.0, 5), np.linspace(-200.0, 200.0, 5)
    heights = np.random.default_rng(3).permutation(np.linspace(40.0, 160.0, 16))
    return tuple((xs[i] + gap / 2, xs[i + 1] - gap / 2, ys[j] + gap / 2, ys[j + 1] - gap / 2,
                  heights[4 * i + j]) for i in range(4) for j in range(4))


def in_view_tops(boxes, shape=SHAPE):
    """Heights of the boxes (of :func:`render`, tilt 0) whose top lies wholly inside the view."""
    out = []
    for box in boxes:
        rows, cols = np.nonzero(np.abs(600.0 - render(0.0, (box,), shape=shape) - box[4]) < 0.5)
        if rows.size and rows.min() > 0 and cols.min() > 0 and rows.max() < shape[0] - 1 \
                and cols.max() < shape[1] - 1:
            out.append(box[4])
    return out


def test_a_hidden_floor_is_no_support_and_the_highest_box_in_view_is_picked():
    # Boxes cover the floor but for narrow aisles: the dominant plane of the image holds
    # too few pixels to be the floor, so it is not used (it would be a guess), the reason
    # says so and asks for a background frame, and the site is on the highest box top
    # wholly in view. With the empty scene given, or the floor in view, the support is used.
    cfg = cam_config()
    boxes = full_tote_boxes()
    full = noisy(render(0.0, boxes), 0.5)
    space = run_assess(-full, cfg, noise=0.5)
    assert space.support is None and space.height is None
    assert space.hidden is not None and space.hidden.inliers < HIDDEN_SUPPORT
    result = run_pipeline(full, cfg).holdsite
    assert result.reason.endswith(
        f"; without a background frame the image's dominant plane holds only "
        f"{space.hidden.inliers:.0%} of the valid pixels (the floor mostly hidden or unread), "
        "too few to take it for the support, so no support test applies and objects "
        "touching the image border are picked only when none in view can be; give a frame "
        "of the empty scene (--background)")
    site = result.holdsite
    assert site is not None
    tops = in_view_tops(boxes)
    assert 600.0 - render(0.0, boxes)[site.row, site.col] == pytest.approx(max(tops), abs=1.0)
    assert result.candidates  # the runners-up too lie on boxes wholly in view
    for other in result.candidates:
        height = 600.0 - render(0.0, boxes)[other.row, other.col]
        assert min(abs(height - top) for top in tops) < 1.0
    empty = noisy(render(0.0), 0.5, seed=1)
    given = run_assess(-full, cfg, noise=0.5, background=-empty)
    assert given.support is not None and given.hidden is None
    assert "--background" not in run_pipeline(full, cfg, background=empty).holdsite.reason
    one_box = noisy(render(0.0, ((-40.0, 40.0, -30.0, 30.0, 60.0),)), 0.5)
    assert run_assess(-one_box, cfg, noise=0.5).support.inliers >= HIDDEN_SUPPORT
    assert "--background" not in run_pipeline(one_box, cfg).holdsite.reason


def dome(shape, centre, radius, base, top):
    """Heights of a spherical-looking cap from ``base`` at its rim to ``top``; -inf outside."""
    v, u = np.indices(shape, dtype=np.float64)
    r2 = ((v - centre[0]) ** 2 + (u - centre[1]) ** 2) / radius ** 2
    return np.where(r2 < 1, base + (top - base) * np.sqrt(np.clip(1 - r2, 0, 1)), -np.inf)


@pytest.mark.parametrize("shadow", [0, 4])
def test_a_shadow_around_an_item_on_another_makes_no_box_at_the_border_a_structure(shadow):
    # An item resting on another is parted from it by the camera's shadow (no reading):
    # what it rests on is still seen within reach, so the item counts for the pile's
    # height, and a box at the border a little above the pile stays an item, as it does
    # without the shadow (shadow=0, the control).
    shape = (96, 128)
    z = np.maximum(np.full(shape, 20.0), dome(shape, (50, 50), 32, 20, 150))
    upper = dome(shape, (50, 50), 12, 140, 200)
    on_top = upper > z
    z = np.maximum(z, upper)
    z[30:70, 110:] = 220.0  # a box cut by the border, a little above the pile
    if shadow:
        z[ndimage.binary_dilation(on_top, iterations=shadow) & ~on_top] = np.nan
    result = run_pipeline(noisy(z), load_config())
    objects = {o.id: o for o in result.holdsite.objects}
    of = {s: o for o in objects.values() for s in o.surfaces}
    box, item = of[label_at(result, 50, 120)], of[label_at(result, 50, 50)]
    assert box.touches_border and not box.structure
    assert item.id != of[label_at(result, 50, 25)].id  # the two domes are two objects
    assert not item.structure


def test_items_over_small_glimpses_of_a_heaped_floor_lie_in_the_workspace():
    # The floor shows in full on the left only; on the right, heaped boxes hide it but for
    # two gaps of a twelfth of that piece each. The gaps belong to the floor's extent, so
    # the highest box, out there, may be picked; a box outside the tote still may not
    # (test_a_box_outside_the_tote_is_never_the_site).
    z = np.full((96, 128), 20.0)
    z[:, 40:] = 60.0 + 10.0 * (np.arange(88)[None, :] // 22)  # four box tops, 60 to 90
    z[10:28, 100:118] = 20.0
    z[66:84, 100:118] = 20.0
    z[38:58, 92:120] = 140.0  # the highest box, beyond the floor seen in full
    result = run_pipeline(noisy(z), load_config())
    site = site_of(result)
    assert site is not None and 38 <= site.row < 58 and 92 <= site.col < 120


@pytest.mark.parametrize("structures", [True, False])
def test_a_box_against_a_tote_wall_is_an_object_of_its_own(structures):
    # A full tote (the floor hidden) with a wall rising beyond the right of the view and
    # the highest box leaning on it: the box's top meets the wall's face at a concave
    # crease, no step. Beyond the paper the crease parts them, so the box is an object
    # wholly in view; with the paper's objects (border_structures off) it is one object
    # with the wall, at the border.
    boxes = [b for b in full_tote_boxes(gap=6.0) if b[1] < 0]
    boxes += [(3.0, 57.0, -200.0, -63.0, 60.0), (3.0, 57.0, -60.0, 60.0, 100.0),
              (3.0, 57.0, 63.0, 200.0, 80.0), (60.0, 117.0, -200.0, -63.0, 70.0),
              (60.0, 117.0, 63.0, 200.0, 90.0)]
    wall, leaning = (120.0, 400.0, -400.0, 400.0, 250.0), (60.0, 120.0, -60.0, 60.0, 180.0)
    z = render(0.0, (*boxes, wall, leaning))
    cfg = cam_config(workspace={"border_structures": structures})
    result = run_pipeline(noisy(z, 0.5), cfg)
    of = {s: o for o in result.holdsite.objects for s in o.surfaces}
    box = of[label_at(result, 60, 122)]  # the leaning box's top
    assert 600.0 - z[60, 122] == pytest.approx(180.0)
    face = result.labels[60, 138]  # the wall's face, seen above the box
    assert 180.0 < 600.0 - z[60, 138] < 250.0
    assert (of.get(face) is box) != structures
    assert box.touches_border != structures


def test_on_a_curved_top_the_most_level_wide_window_is_the_site():
    # A parabolic top, level at one end and turning to 50 degrees at the other: the widest
    # window lies where it is tilted; beyond the paper (a tilt limit) the site is the most
    # level window among those with enough clearance, where a cup faces the sensor.
    z = np.full((96, 128), 20.0)
    v, u = np.indices(z.shape, dtype=np.float64)
    inside = (v >= 20) & (v < 76) & (u >= 14) & (u < 114)
    z[inside] = (60.0 + 0.0072 * (u - 24.0) ** 2)[inside]
    cfg = load_config(overrides={"input": {"units_per_pixel": 1.0}})
    site = site_of(run_pipeline(noisy(z), cfg))
    assert site.clearance >= enough_clearance(cfg.holdsite.size)
    assert math.degrees(math.acos(site.normal[2])) < 5.0
    assert abs(site.col - 24) <= 3
