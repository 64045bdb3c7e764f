"""The synthetic depth camera of ``rangeseg synth``: geometry, sensor steps, files, CLI."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from rangeseg_cli.batch.io import find_images, read_image
from rangeseg_cli.cli.main import CAMERA_NAMES, DEPTH_UNIT_NAMES, main
from rangeseg_cli.synth.camera import (
    CAMERA_SCENES,
    CAMERAS,
    DEPTH_UNITS,
    Item,
    SensorModel,
    camera_for,
    depth_noise,
    flying_pixels,
    projector_shadow,
    quantise_disparity,
    render_camera_scene,
    render_items,
    sense,
    smooth_jumps,
    split_scene_names,
    steep_holes,
    support_plane,
    write_camera_scenes,
)
from rangeseg_cli.synth.scenes import box, pose, sphere

SMALL = (120, 160)


def ideal_camera(height=600.0, tilt=(0.0, 0.0)):
    return camera_for(CAMERAS["ideal"], SMALL, height=height, tilt=tilt)


# --------------------------------------------------------------------------- geometry


def test_plane_at_known_distance_renders_that_depth_in_tenth_mm():
    cam = ideal_camera(600.0)
    render = render_items(cam, [support_plane("table")])
    np.testing.assert_allclose(render.depth, 600.0, atol=1e-9)
    raw, truthful = sense(render, cam, SensorModel.ideal(), DEPTH_UNITS["0.1mm"],
                          lambda k: np.random.default_rng(k))
    assert raw.dtype == np.uint16 and np.all(raw == 6000) and truthful.all()


def test_tilted_camera_sees_a_plane_at_the_depth_of_each_ray():
    cam = ideal_camera(700.0, tilt=(6.0, -4.0))
    depth = render_items(cam, [support_plane("table")]).depth
    rays = cam.rays() @ cam.R.T  # world directions with camera depth 1
    expected = (cam.t[2] / -rays[:, 2]).reshape(SMALL)
    np.testing.assert_allclose(depth, expected, rtol=1e-12)
    assert depth[0, 0] != pytest.approx(depth[-1, -1])  # the tilt shows


def test_box_of_known_size_spans_the_pinhole_width():
    cam = ideal_camera(600.0)
    item = Item("box", (box(100.0, 60.0, 50.0, "box"),), True, "box")
    render = render_items(cam, [support_plane("table"), item])
    top = [s["id"] for s in render.surfaces if s["name"] == "box top"][0]
    row = render.gt[SMALL[0] // 2]
    width = np.count_nonzero(row == top)
    expected = cam.fx * 100.0 / 550.0  # top face 50 mm above the table, 550 mm away
    assert abs(width - expected) <= 1.0
    np.testing.assert_allclose(render.depth[render.gt == top], 550.0, atol=1e-9)


def test_sphere_depth_matches_the_analytic_intersection():
    cam = ideal_camera(600.0)
    ball = Item("ball", (sphere(50.0, "ball").moved(pose(0, 0, 100.0)),), True, "ball")
    render = render_items(cam, [support_plane("table"), ball])
    on = render.obj == 1
    d = cam.rays()[on.ravel()]
    centre = cam.R.T @ (np.array([0.0, 0.0, 100.0]) - cam.t)  # (0, 0, 500) in the camera
    dc, dd = d @ centre, np.einsum("ij,ij->i", d, d)
    s = (dc - np.sqrt(dc**2 - dd * (centre @ centre - 50.0**2))) / dd
    np.testing.assert_allclose(render.depth[on], s, rtol=1e-10)
    assert render.depth[on].min() == pytest.approx(450.0, abs=0.5)


def test_standing_item_is_covered_only_by_a_pickable_item_in_front():
    cam = ideal_camera(600.0)
    low = Item("low", (box(120.0, 120.0, 20.0, "low"),), True, "box")
    high = Item("high", (box(40.0, 40.0, 30.0, "high").moved(pose(0, 0, 20.0)),), True, "box")
    render = render_items(cam, [support_plane("table"), low, high])
    assert render.covered[1:] == [True, False]  # the table is covered too, but not an item


# --------------------------------------------------------------------------- sensor steps


def test_projector_shadow_lies_on_the_far_side_away_from_the_projector():
    depth = np.full((4, 100), 600.0)
    depth[:, 60:] = 500.0  # a near surface on the right, the projector at +x
    shadow = projector_shadow(depth, fx=600.0, baseline_mm=50.0)
    width = 600.0 * 50.0 * (1 / 500.0 - 1 / 600.0)  # 10 px
    cols = np.flatnonzero(shadow[0])
    assert cols.size == pytest.approx(width, abs=1) and cols.max() == 59
    assert not shadow[:, 60:].any()
    # The projector on the other side: the shadow moves to the other side of a near strip.
    depth[:, :20] = 500.0
    depth[:, 60:] = 600.0
    mirrored = projector_shadow(depth, fx=600.0, baseline_mm=-50.0)
    assert np.flatnonzero(mirrored[0]).min() == 20 and not mirrored[:, :20].any()


def step_depth():
    depth = np.full((6, 40), 600.0)
    depth[:, 20:] = 500.0
    return depth


def test_jumps_are_smoothed_into_ramps_and_flat_parts_kept():
    depth = step_depth()
    smooth = smooth_jumps(depth, blur_px=1.5, jump_mm=10.0)
    row = smooth[0]
    assert np.all(np.diff(row) <= 1e-9)  # a monotone ramp from 600 down to 500
    between = np.flatnonzero((row < 599.0) & (row > 501.0))
    assert 3 <= between.size <= 8 and between.min() >= 14 and between.max() <= 25
    np.testing.assert_array_equal(smooth[:, :12], 600.0)
    np.testing.assert_array_equal(smooth_jumps(depth, blur_px=0, jump_mm=10.0), depth)


def test_flying_pixels_fall_between_both_sides_of_a_jump_only():
    depth = step_depth()
    out = flying_pixels(depth, np.random.default_rng(3), fraction=1.0, jump_mm=10.0)
    moved = out != depth
    assert moved[:, 19:21].all() and not moved[:, :19].any() and not moved[:, 21:].any()
    assert np.all((out[moved] > 500.0) & (out[moved] < 600.0))
    same = flying_pixels(depth, np.random.default_rng(3), fraction=1.0, jump_mm=10.0)
    np.testing.assert_array_equal(out, same)


def test_steep_faces_lose_pixels_and_facing_ones_keep_them():
    rng = np.random.default_rng(0)
    cos = np.concatenate([np.full(1000, 1.0), np.full(1000, np.cos(np.radians(85)))])
    lost = steep_holes(cos, rng, start_deg=65, end_deg=82, drop=0.9)
    assert not lost[:1000].any()
    assert 0.85 < lost[1000:].mean() < 0.95


def test_depth_noise_grows_with_the_square_of_depth():
    rng = np.random.default_rng(1)
    depth = np.concatenate([np.full(20000, 500.0), np.full(20000, 1000.0)])
    noisy = depth_noise(depth, rng, noise_at_1m_mm=2.0)
    near, far = np.std(noisy[:20000] - 500.0), np.std(noisy[20000:] - 1000.0)
    assert far == pytest.approx(2.0, rel=0.05) and far / near == pytest.approx(4.0, rel=0.08)


def test_smooth_depth_noise_has_its_sigma_and_is_correlated_over_its_pixels():
    from rangeseg_cli.synth.camera import smooth_depth_noise

    depth = np.full((300, 300), 1000.0)
    depth[:, 150:] = 500.0
    noisy = smooth_depth_noise(depth, np.random.default_rng(2), noise_at_1m_mm=0.8,
                               sigma_px=2.0) - depth
    far, near = noisy[:, :150], noisy[:, 150:]
    assert np.std(far) == pytest.approx(0.8, rel=0.15)
    assert np.std(far) / np.std(near) == pytest.approx(4.0, rel=0.15)  # grows with depth²
    assert np.corrcoef(far[:, :-1].ravel(), far[:, 1:].ravel())[0, 1] > 0.8  # neighbours
    assert abs(np.corrcoef(far[:, :-20].ravel(), far[:, 20:].ravel())[0, 1]) < 0.1  # far apart
    off = smooth_depth_noise(depth, np.random.default_rng(2), noise_at_1m_mm=0.0, sigma_px=2.0)
    np.testing.assert_array_equal(off, depth)


def test_the_smooth_camera_fits_its_error_to_window_size_as_the_arc_empty_tote_does():
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
    from noise_scale import quadric_rms

    def growth(camera: str) -> float:
        raw = render_camera_scene("cam-empty-tote", seed=300, camera=camera).background
        z = np.where(raw > 0, -0.1 * raw.astype(np.float64), np.nan)  # mm
        small, large = (np.percentile(quadric_rms(z, k), 25) for k in (5, 31))
        return large / small

    assert growth("sr300-smooth") > 1.6  # the SR300's empty tote: 0.36 / 0.18 mm
    assert growth("sr300") < 1.2  # white noise: flat


def test_soft_items_are_creased_inside_their_border_and_keep_their_ground_truth():
    plain = render_camera_scene("cam-pile", seed=300, camera="ideal")
    soft = render_camera_scene("cam-pile", seed=300, camera="ideal", soft=1.0)
    np.testing.assert_array_equal(soft.gt, plain.gt)
    creased = soft.info["soft"]
    assert creased and "soft" not in plain.info
    moved = np.abs(soft.depth - plain.depth)
    moved[~np.isfinite(moved)] = 0.0
    ids = {o["id"] for o in plain.info["objects"] if not o["pickable"]}
    assert not ids & set(creased)  # the table is never soft
    assert moved.max() > 2.0  # folds of about 4 mm
    with pytest.raises(ValueError, match="`soft` 1.5 must be a share from 0 to 1"):
        render_camera_scene("cam-pile", seed=300, soft=1.5)


def test_a_crease_fades_to_nothing_at_the_items_border():
    from rangeseg_cli.synth.camera import crease

    depth = np.full((80, 80), 600.0)
    obj = np.zeros((80, 80), np.int32)
    obj[10:70, 10:70] = 1
    out = crease(depth, obj, [1], np.random.default_rng(0))
    assert (out[obj == 0] == 600.0).all()
    ring = (obj == 1) & ~np.pad(np.ones((58, 58), bool), 11)  # the item's outermost pixels
    assert np.abs(out[ring] - 600.0).max() < 0.15 * np.abs(out - 600.0).max()  # a tenth


def test_disparity_quantisation_steps_grow_with_depth_squared():
    depth = np.linspace(590.0, 610.0, 2001)
    q = quantise_disparity(depth, fx=600.0, baseline_mm=25.0, step_px=1 / 16)
    steps = np.diff(np.unique(q))
    expected = 600.0**2 / (600.0 * 25.0) / 16  # z^2 step / (fx b) = 1.5 mm at 600 mm
    assert steps.mean() == pytest.approx(expected, rel=0.05)
    assert np.max(np.abs(q - depth)) <= expected / 2 + 0.05


# --------------------------------------------------------------------------- scenes


def test_same_seed_same_bytes_and_another_seed_another_scene():
    a = render_camera_scene("cam-gripper", size=SMALL, seed=3)
    b = render_camera_scene("cam-gripper", size=SMALL, seed=3)
    c = render_camera_scene("cam-gripper", size=SMALL, seed=4)
    assert a.image.tobytes() == b.image.tobytes() and a.gt.tobytes() == b.gt.tobytes()
    assert a.background.tobytes() == b.background.tobytes() and a.info == b.info
    assert a.image.tobytes() != c.image.tobytes()


@pytest.mark.parametrize("name", list(CAMERA_SCENES))
def test_ground_truth_ids_match_the_surface_and_object_lists(name):
    scene = render_camera_scene(name, size=SMALL, seed=5)
    info = scene.info
    ids = [s["id"] for s in info["surfaces"]]
    assert ids == list(range(1, len(ids) + 1))
    assert set(np.unique(scene.gt)) <= {0, *ids}
    counts = np.bincount(scene.gt.ravel(), minlength=len(ids) + 1)
    assert [s["pixels"] for s in info["surfaces"]] == counts[1:].tolist()
    objects = {o["id"]: o for o in info["objects"]}
    assert all(s["object"] in objects for s in info["surfaces"])
    assert all(o["pickable"] == (o["kind"] not in ("support", "tote", "gripper"))
               for o in objects.values())
    kinds = {o["kind"] for o in objects.values()}
    assert ("gripper" in kinds) == (name == "cam-gripper")
    assert ("tote" in kinds) >= (name in ("cam-tote", "cam-empty-tote", "cam-full-tote"))
    has_items = any(o["pickable"] for o in objects.values())
    assert has_items == (name != "cam-empty-tote")
    assert info["camera"]["preset"] == "tenth-mm-depth"
    assert scene.image.dtype == np.uint16 and np.all(scene.gt[scene.image == 0] == 0)


def test_a_full_tote_hides_its_floor_more_than_a_tote_and_stays_out_of_the_camera():
    # Heaped up to 250 mm below the camera: every frame has readings (a heap grown into
    # the camera left none), and the items hide more of the floor than in cam-tote.
    hidden = {}
    for name in ("cam-tote", "cam-full-tote"):
        shares = []
        for seed in range(3):
            scene = render_camera_scene(name, size=SMALL, seed=seed, camera="ideal")
            floor = [o["id"] for o in scene.info["objects"] if o["name"] == "tote floor"]
            on_floor = np.isin(scene.gt, [s["id"] for s in scene.info["surfaces"]
                                          if s["object"] in floor])
            shares.append(on_floor.mean())
            assert np.isfinite(scene.depth).any() and (scene.image > 0).any()
            if name == "cam-full-tote":
                top = float(np.nanmin(scene.depth))
                assert top >= 150.0  # nothing within the sensor's 150 mm minimum range
        hidden[name] = float(np.mean(shares))
    assert hidden["cam-full-tote"] < 0.5 * hidden["cam-tote"]


def test_background_frame_holds_no_items_and_no_gripper():
    scene = render_camera_scene("cam-gripper", size=SMALL, seed=2, camera="ideal")
    item_px = np.isin(scene.gt, [s["id"] for s in scene.info["surfaces"]
                                 if not scene.info["objects"][s["object"]]["pickable"]],
                      invert=True) & (scene.gt > 0)
    assert item_px.any()
    # Without the items, every one of their pixels shows the support farther away.
    assert np.all(scene.background[item_px] > scene.image[item_px])


def test_ideal_camera_has_no_invalid_pixels_and_sr300_has_some():
    ideal = render_camera_scene("cam-tote", size=SMALL, seed=1, camera="ideal")
    real = render_camera_scene("cam-tote", size=SMALL, seed=1)
    assert np.all(ideal.image > 0)
    assert 0 < np.mean(real.image == 0) < 0.5


def test_unknown_options_are_one_line_errors_naming_the_option():
    with pytest.raises(ValueError, match="`camera` 'kinect' is unknown; allowed: sr300, sr300-smooth, ideal"):
        render_camera_scene("cam-tote", camera="kinect")
    with pytest.raises(ValueError, match="`depth_unit` 'cm' is unknown"):
        render_camera_scene("cam-tote", depth_unit="cm")
    with pytest.raises(ValueError, match="scene 'cam-x' is unknown; allowed: cam-pile"):
        render_camera_scene("cam-x")
    with pytest.raises(ValueError, match="unknown scene cam-x; allowed: .*cam-tote"):
        split_scene_names("cup,cam-x", ["cup"])
    assert split_scene_names("cup, cam-tote", ["cup"]) == (["cup"], ["cam-tote"])


# --------------------------------------------------------------------------- files and CLI


def test_written_files_round_trip_and_run_reads_only_the_frames(tmp_path):
    written = write_camera_scenes(tmp_path, ["cam-tote"], [7], size=SMALL)
    names = sorted(p.name for p in written)
    assert names == ["cam-tote-s7.gt.background.png", "cam-tote-s7.gt.json",
                     "cam-tote-s7.gt.npy", "cam-tote-s7.intrinsics.txt", "cam-tote-s7.png"]
    scene = render_camera_scene("cam-tote", size=SMALL, seed=7)
    np.testing.assert_array_equal(read_image(tmp_path / "cam-tote-s7.png"), scene.image)
    matrix = np.loadtxt(tmp_path / "cam-tote-s7.intrinsics.txt")
    np.testing.assert_allclose(matrix, scene.camera.matrix(), rtol=1e-9)
    info = json.loads((tmp_path / "cam-tote-s7.gt.json").read_text())
    assert info["camera"]["fx"] == pytest.approx(scene.camera.fx, rel=1e-9)
    images, _ = find_images([tmp_path])
    assert [str(rel) for _, rel in images] == ["cam-tote-s7"]


def test_metre_depth_is_float32_with_nan_where_invalid(tmp_path):
    write_camera_scenes(tmp_path, ["cam-pile"], [1], size=SMALL, depth_unit="m")
    image = read_image(tmp_path / "cam-pile-s1.npy")
    assert image.dtype == np.float32 and np.isnan(image).any()
    assert 0.3 < np.nanmedian(image) < 1.0
    info = json.loads((tmp_path / "cam-pile-s1.gt.json").read_text())
    assert info["camera"]["preset"] == "metre-depth"


def test_cli_writes_camera_frames_for_each_seed(tmp_path):
    res = CliRunner().invoke(main, ["synth", str(tmp_path), "--scenes", "cam-empty-tote",
                                    "--size", "120x160", "--seed", "3", "--frames", "2",
                                    "--depth-unit", "1mm"])
    assert res.exit_code == 0, res.output
    assert "wrote 2 scenes (10 files)" in res.output
    info = json.loads((tmp_path / "cam-empty-tote-s4.gt.json").read_text())
    assert info["camera"]["preset"] == "mm-depth" and info["size"] == [120, 160]


def test_cli_refuses_bad_camera_options_with_usage_errors(tmp_path):
    res = CliRunner().invoke(main, ["synth", str(tmp_path), "--scenes", "cam-tote",
                                    "--camera", "kinect"])
    assert res.exit_code == 2 and "--camera" in res.output and "sr300" in res.output
    res = CliRunner().invoke(main, ["synth", str(tmp_path), "--scenes", "cam-tot"])
    assert res.exit_code == 2 and "unknown scene cam-tot" in res.output
    assert "cam-empty-tote" in res.output


def test_cli_choices_are_the_library_names():
    assert CAMERA_NAMES == tuple(CAMERAS) and DEPTH_UNIT_NAMES == tuple(DEPTH_UNITS)


def test_a_tilted_mount_turns_the_optical_axis_by_its_angle():
    from rangeseg_cli.synth.camera import render_camera_scene

    straight = render_camera_scene("cam-tote", size=(48, 64), seed=3)
    again = render_camera_scene("cam-tote", size=(48, 64), seed=3, tilt=0.0)
    assert straight.image.tobytes() == again.image.tobytes()
    tilted = render_camera_scene("cam-tote", size=(48, 64), seed=3, tilt=30.0)
    axes = [np.asarray(s.info["camera"]["rotation"])[:, 2] for s in (straight, tilted)]
    angle = np.degrees(np.arccos(np.clip(axes[0] @ axes[1], -1.0, 1.0)))
    assert angle == pytest.approx(30.0, abs=1e-6)
    for bad in (75.0, True, float("nan")):
        with pytest.raises(ValueError, match="`tilt`"):
            render_camera_scene("cam-tote", size=(48, 64), seed=3, tilt=bad)
    same = render_camera_scene("cam-tote", size=(48, 64), seed=3, tilt=np.float32(30.0))
    assert same.image.tobytes() == tilted.image.tobytes()
