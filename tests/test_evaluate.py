"""Hoover et al. (1996) classification, the holdsite check and folder evaluation."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from rangeseg_cli.batch.io import write_json, write_npy
from rangeseg_cli.synth.camera import write_camera_scenes
from rangeseg_cli.synth.evaluate import (
    CURVE_TOLERANCES,
    check_holdsite,
    check_object_holdsite,
    connected_parts,
    correct_curve,
    evaluate_folder,
    hoover_compare,
    overlap_table,
    plot_curve,
)
from rangeseg_cli.synth.scenes import render_scene, write_scenes


def counts(gt, pred, **kw):
    kw.setdefault("min_region", 0)
    return hoover_compare(np.asarray(gt), np.asarray(pred), **kw).counts()


def two_halves(width=20, height=10):
    """GT: region 1 on the left half, region 2 on the right half (100 px each)."""
    gt = np.ones((height, width), np.int32)
    gt[:, width // 2:] = 2
    return gt


# --------------------------------------------------------------------------- the five classes


def test_identical_segmentations_are_all_correct_detections():
    gt = two_halves()
    c = counts(gt, gt * 7)  # labels need not agree, only regions
    assert c["correct"] == c["gt_regions"] == c["machine_regions"] == 2
    assert c["over"] == c["under"] == c["missed"] == c["noise"] == 0


def test_correct_detection_needs_the_overlap_on_both_sides():
    gt = two_halves()
    pred = gt.copy()
    pred[:, 10] = 1  # machine region 1: 110 px, 100 inside GT 1; GT 2 keeps 90 of 100
    assert counts(gt, pred, tolerance=0.8)["correct"] == 2
    assert counts(gt, pred, tolerance=0.95)["correct"] == 0  # 100/110 and 90/100 < 0.95
    assert counts(gt, pred, tolerance=0.95)["missed"] == 2


def test_one_truth_split_in_two_is_over_segmentation():
    gt = np.ones((10, 20), np.int32)
    pred = two_halves()
    c = counts(gt, pred)
    assert (c["over"], c["correct"], c["missed"], c["noise"]) == (1, 0, 0, 0)
    inst = hoover_compare(gt, pred, min_region=0).instances
    assert inst[0].kind == "over" and inst[0].gt == (1,) and inst[0].machine == (1, 2)


def test_two_truths_merged_are_one_under_segmentation():
    gt = two_halves()
    pred = np.ones_like(gt)
    c = counts(gt, pred)
    assert (c["under"], c["correct"], c["missed"], c["noise"]) == (1, 0, 0, 0)
    inst = hoover_compare(gt, pred, min_region=0).instances[0]
    assert inst.kind == "under" and inst.gt == (1, 2) and inst.machine == (1,)


def test_unlabelled_truth_is_missed_and_straddling_regions_are_noise():
    gt = two_halves()
    pred = np.zeros_like(gt)
    assert counts(gt, pred)["missed"] == 2
    pred = np.ones_like(gt)  # 60 px of GT 1 ...
    pred[:, 6:14] = 2  # ... 40 + 40 straddling both ...
    pred[:, 14:] = 3  # ... 60 px of GT 2
    c = counts(gt, pred)
    assert (c["correct"], c["missed"], c["noise"]) == (0, 2, 3)


def test_label_zero_is_no_region_on_either_side():
    gt = two_halves()
    gt[:, :4] = 0  # unknown truth
    pred = two_halves()  # machine region 1 spills 40 px onto GT label 0: not held against it
    pred[0, :] = 0  # machine edge pixels: they only lower the overlap
    c = counts(gt, pred)
    assert (c["correct"], c["gt_regions"], c["noise"]) == (2, 2, 0)
    ov = overlap_table(gt, pred, min_region=0)
    assert ov.gt_size.tolist() == [60, 100] and ov.machine_size.tolist() == [54, 90]


# --------------------------------------------------------------------------- min_region and ties


def test_small_truth_is_not_judged_and_small_machine_regions_are_not_noise():
    gt = two_halves()
    gt[0:3, 0:3] = 3  # a 9 px GT region
    pred = two_halves()
    pred[0:3, 0:3] = 5  # found exactly, but too small to judge: ignored
    pred[5:7, 15:17] = 6  # a 4 px fragment inside GT 2
    c = counts(gt, pred, min_region=20)
    assert (c["gt_regions"], c["correct"], c["ignored"], c["small"], c["noise"]) == (2, 2, 1, 1, 0)
    c = counts(gt, pred, min_region=0)
    assert (c["gt_regions"], c["correct"], c["noise"]) == (3, 3, 1)  # now the fragment is noise


def test_tie_at_half_tolerance_goes_to_the_lower_machine_label():
    gt = np.ones((10, 20), np.int32)
    pred = two_halves()  # each half covers exactly 0.5 of the truth
    res = hoover_compare(gt, pred, tolerance=0.5, min_region=0)
    assert [(i.kind, i.machine) for i in res.instances] == [("correct", (1,))]
    assert res.noise == [2]


def test_each_region_joins_at_most_one_instance_best_overlap_first():
    gt = np.zeros((10, 20), np.int32)
    gt[:, :10] = 1  # A: 100 px
    gt[:5, 10:] = 2  # B: 50 px
    pred = np.full_like(gt, 2)
    pred[:5, :] = 1  # m1: top half of A and all of B
    # At T = 0.5, (A, m1), (A, m2) and (B, m1) all qualify; (A, m2) and (B, m1)
    # have the higher mutual overlap (0.75 vs 0.5) and share no region.
    res = hoover_compare(gt, pred, tolerance=0.5, min_region=0)
    pairs = sorted((i.gt, i.machine) for i in res.instances)
    assert pairs == [((1,), (2,)), ((2,), (1,))]
    assert all(i.kind == "correct" for i in res.instances)


def test_tolerance_and_shapes_are_validated():
    gt = two_halves()
    with pytest.raises(ValueError, match="tolerance"):
        hoover_compare(gt, gt, tolerance=0.4)
    with pytest.raises(ValueError, match="shape"):
        hoover_compare(gt, gt[:5])
    with pytest.raises(ValueError, match="integer label"):
        hoover_compare(gt, gt.astype(float))
    with pytest.raises(ValueError, match="min_region"):
        hoover_compare(gt, gt, min_region=-1)


def test_correct_curve_falls_with_tolerance_and_is_flat_for_the_truth():
    scene = render_scene("part1", noise=0)
    flat = correct_curve(scene.gt, scene.gt)
    assert len(flat) == len(CURVE_TOLERANCES) and len(set(flat)) == 1
    rng = np.random.default_rng(0)
    pred = scene.gt.copy()
    pred[rng.random(pred.shape) < 0.12] = 0  # lose 12 % of the pixels
    curve = correct_curve(scene.gt, pred)
    assert curve == sorted(curve, reverse=True) and curve[0] == flat[0] > curve[-1]


def test_every_scene_against_its_own_truth_is_all_correct():
    for name in ("part1", "cup", "part2", "cube-holes", "pile"):
        c = hoover_compare(render_scene(name).gt, render_scene(name).gt).counts()
        assert c["correct"] == c["gt_regions"] > 1, name
        assert c["over"] == c["under"] == c["missed"] == c["noise"] == 0, name


# --------------------------------------------------------------------------- holdsite check


def test_holdsite_inside_the_top_of_an_uncovered_part_passes():
    scene = render_scene("box")
    top = next(s for s in scene.info["surfaces"] if s["name"] == "box top")
    r, c = (int(v) for v in np.argwhere(scene.gt == top["id"]).mean(axis=0))
    ok = check_holdsite({"row": r, "col": c}, scene.gt, scene.info)
    assert ok["ok"] and ok["surface"] == top["id"] and ok["object"] == 1
    rotated = check_holdsite({"row": r, "col": c, "size": [3, 11], "angle": 30}, scene.gt,
                             scene.info)
    assert rotated["ok"]


def test_holdsite_failures_say_why():
    scene = render_scene("box")
    info, gt = scene.info, scene.gt
    assert check_holdsite(None, gt, info)["reason"] == "no holdsite reported"
    assert "leaves the image" in check_holdsite({"row": 1, "col": 60}, gt, info)["reason"]
    assert "background" in check_holdsite({"row": 5, "col": 5}, gt, info)["reason"]
    rows, cols = np.nonzero(gt > 1)
    edge = {"row": int(rows.min()), "col": int(cols[rows == rows.min()][0])}
    assert "crosses surfaces" in check_holdsite(edge, gt, info)["reason"]


def test_holdsite_on_a_covered_part_of_a_pile_fails():
    scene = render_scene("pile", seed=1990)
    covered = [o["id"] for o in scene.info["objects"]
               if not o["background"] and o["id"] not in scene.uncovered]
    assert covered, "the pile should bury at least one part"
    surf = max((s for s in scene.info["surfaces"] if s["object"] in covered),
               key=lambda s: s["pixels"])
    mask = scene.gt == surf["id"]
    from scipy import ndimage

    r, c = np.unravel_index(np.argmax(ndimage.distance_transform_edt(mask)), mask.shape)
    res = check_holdsite({"row": int(r), "col": int(c), "size": [3, 3]}, scene.gt, scene.info)
    assert not res["ok"] and "under another part" in res["reason"]


# --------------------------------------------------------------------------- folders


def _predict_truth(gt_dir, pred_dir):
    """A perfect 'machine': copy each GT as labels, with a holdsite on the top surface."""
    for path in sorted(gt_dir.glob("*.gt.npy")):
        stem = path.name[: -len(".gt.npy")]
        gt = np.load(path)
        write_npy(pred_dir / f"{stem}.labels.npy", gt)
        info = json.loads(path.with_suffix(".json").read_text())
        obj = info["uncovered"][0]
        surf = max((s for s in info["surfaces"] if s["object"] == obj), key=lambda s: s["pixels"])
        r, c = np.argwhere(gt == surf["id"])[len(np.argwhere(gt == surf["id"])) // 2]
        write_json(pred_dir / f"{stem}.holdsite.json",
                   {"holdsite": {"row": int(r), "col": int(c), "size": [1, 1]}})


def test_evaluate_folder_of_the_truth_itself(tmp_path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    write_scenes(gt_dir, ["cup", "box"], [0, 2], seed=3, size=(64, 64))
    _predict_truth(gt_dir, pred_dir)
    res = evaluate_folder(pred_dir, gt_dir, min_region=10)
    total = res["total"]
    assert set(res["images"]) == {"cup-n0", "cup-n2", "box-n0", "box-n2"}
    assert total["correct"] == total["gt_regions"] > 0 and res["errors"] == []
    assert total["over"] == total["under"] == total["missed"] == total["noise"] == 0
    assert total["holdsite"] == {"checked": 4, "ok": 4}
    assert total["curve"]["correct"] == [total["gt_regions"]] * len(CURVE_TOLERANCES)


def test_evaluate_folder_reports_a_missing_prediction_and_goes_on(tmp_path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    write_scenes(gt_dir, ["box", "sphere"], [0], seed=0, size=(48, 48))
    _predict_truth(gt_dir, pred_dir)
    (pred_dir / "box-n0.labels.npy").unlink()
    res = evaluate_folder(pred_dir, gt_dir, min_region=10)
    assert "error" in res["images"]["box-n0"] and len(res["errors"]) == 1
    assert res["total"]["images"] == 1 and res["total"]["correct"] == 2


def test_evaluate_folder_without_ground_truth_is_an_input_error(tmp_path):
    from rangeseg_cli.errors import InputError

    with pytest.raises(InputError, match="no ground truth"):
        evaluate_folder(tmp_path, tmp_path)


def test_plot_curve_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    path = tmp_path / "curve.png"
    assert plot_curve({"tolerance": [0.5, 0.8], "correct": [5, 3]}, path, gt_regions=6)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("file, text, message", [
    ("pred/s.holdsite.json", '{"holdsite": 3}', "s.holdsite.json: not a holdsite.json of rangeseg"),
    ("pred/s.holdsite.json", '[1, 2]', "s.holdsite.json: not a holdsite.json of rangeseg"),
    ("pred/s.holdsite.json", '{"holdsite": {"row": 3}}', "not a holdsite.json"),
    # a window or an angle the check cannot draw (an IndexError that stopped the whole eval)
    ("pred/s.holdsite.json", '{"holdsite": {"row": 5, "col": 5, "size": [9, 3], "angle": NaN}}',
     'not a holdsite.json of rangeseg (its holdsite has "angle" nan, expected a finite number '
     'of degrees)'),
    ("pred/s.holdsite.json", '{"holdsite": {"row": 5, "col": 5, "angle": Infinity}}',
     'not a holdsite.json of rangeseg (its holdsite has "angle" inf'),
    ("pred/s.holdsite.json", '{"holdsite": {"row": 5, "col": 5, "size": [0, 0]}}',
     'not a holdsite.json of rangeseg (its holdsite has "size" [0, 0], expected a list of two '
     'integers >= 1 <= 255 odd)'),
    ("pred/s.holdsite.json", '{"holdsite": {"row": 5, "col": 5, "size": [99999, 9]}}',
     'not a holdsite.json of rangeseg (its holdsite has "size" [99999, 9]'),
    ("pred/s.holdsite.json", '{"holdsite": {"row": 5, "col": 5, "window": "7x7"}}',
     'not a holdsite.json of rangeseg (its holdsite has "window" \'7x7\''),
    ("gt/s.gt.json", '[1, 2]', "s.gt.json: not a gt.json of rangeseg synth"),
    ("gt/s.gt.json", '{"surfaces": 3, "objects": [], "uncovered": []}', "not a gt.json"),
])
def test_malformed_json_beside_the_labels_is_one_line_naming_the_file(tmp_path, file, text,
                                                                      message):
    from rangeseg_cli.cli.main import main

    for d in ("pred", "gt"):
        (tmp_path / d).mkdir()
    labels = np.ones((32, 32), np.int32)
    np.save(tmp_path / "pred" / "s.labels.npy", labels)
    np.save(tmp_path / "gt" / "s.gt.npy", labels)
    (tmp_path / "pred" / "s.holdsite.json").write_text('{"holdsite": null}')
    (tmp_path / "gt" / "s.gt.json").write_text(
        '{"surfaces": [{"id": 1, "object": 1}], "objects": [{"id": 1}], "uncovered": [1]}')
    (tmp_path / file).write_text(text)
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "-q"])
    assert res.exit_code == 1
    assert isinstance(res.exception, SystemExit)  # an exit code, not a traceback
    assert f"s: {tmp_path / file}: {message.split(': ', 1)[-1]}" in res.output


def test_check_holdsite_names_a_key_it_cannot_draw():
    gt = np.ones((32, 32), np.int32)
    info = {"surfaces": [{"id": 1, "object": 1}], "objects": [{"id": 1}], "uncovered": [1]}
    with pytest.raises(ValueError, match='`holdsite`: "angle" nan, expected a finite number'):
        check_holdsite({"row": 5, "col": 5, "size": [9, 3], "angle": float("nan")}, gt, info)
    with pytest.raises(ValueError, match='`holdsite`: no integer "row" and "col"'):
        check_holdsite({"col": 5}, gt, info)
    assert check_holdsite({"row": 16, "col": 16, "size": [9, 3], "angle": 30}, gt, info)["ok"]


def test_tolerances_may_be_any_iterable(tmp_path):
    for d in ("pred", "gt"):
        (tmp_path / d).mkdir()
    labels = np.ones((32, 32), np.int32)
    np.save(tmp_path / "pred" / "s.labels.npy", labels)
    np.save(tmp_path / "gt" / "s.gt.npy", labels)
    out = evaluate_folder(tmp_path / "pred", tmp_path / "gt", tolerances=(t for t in (0.5, 0.9)))
    assert out["total"]["curve"] == {"tolerance": [0.5, 0.9], "correct": [1, 1]}


def test_labels_of_another_shape_name_both_files(tmp_path):
    from rangeseg_cli.cli.main import main

    for d in ("pred", "gt"):
        (tmp_path / d).mkdir()
    np.save(tmp_path / "pred" / "s.labels.npy", np.ones((32, 32), np.int32))
    np.save(tmp_path / "gt" / "s.gt.npy", np.ones((16, 32), np.int32))
    res = CliRunner().invoke(main, ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "-q"])
    assert res.exit_code == 1
    assert (f"{tmp_path / 'pred' / 's.labels.npy'} against {tmp_path / 'gt' / 's.gt.npy'}: "
            "`pred` (shape (32, 32)) must have the shape of `gt`") in res.output


# --------------------------------------------------------------------------- GT patches


def two_patches():
    """GT label 1 in two separate patches (60 and 20 px) with label 2 between them."""
    gt = np.full((10, 20), 2, np.int32)
    gt[:, :6] = 1
    gt[:, 18:] = 1
    return gt


def test_connected_parts_numbers_each_patch_of_a_label():
    gt = two_patches()
    gt[0, 7] = 3  # a one-pixel label touching nothing of its own
    parts = connected_parts(gt)
    assert parts.dtype == np.int64
    assert set(np.unique(parts).tolist()) == {1, 2, 3, 4}
    assert (parts[:, :6] == 1).all() and (parts[:, 18:] == 2).all()  # label 1: two parts
    assert parts[0, 7] == 4 and (parts[gt == 2] == 3).all()
    assert (connected_parts(np.zeros((4, 4), np.int32)) == 0).all()
    diagonal = np.eye(5, dtype=np.int32)  # 8-connected: one part
    assert set(np.unique(connected_parts(diagonal)).tolist()) == {0, 1}
    huge = gt.astype(np.int64)
    huge[gt == 1] = 2**40  # any label values, no table of them
    np.testing.assert_array_equal(connected_parts(huge) > 0, huge > 0)
    assert sorted(np.unique(connected_parts(huge)).tolist()) == [1, 2, 3, 4]
    assert (connected_parts(np.full((3, 3), 7)) == 1).all()  # no 0 in the image


def test_a_surface_in_two_patches_is_correct_only_when_judged_by_patch():
    gt = two_patches()
    pred = np.where(gt == 1, 1, 2).astype(np.int32)
    pred[:, 18:] = 3  # a segmentation of connected regions labels the patches apart
    whole = counts(gt, pred)
    by_patch = counts(gt, pred, gt_parts=True)
    assert whole["gt_regions"] == 2 and whole["correct"] == 1  # 60 of 80 px < 0.8
    assert by_patch["gt_regions"] == 3 and by_patch["correct"] == 3
    assert correct_curve(gt, pred, min_region=0, gt_parts=True) == [3] * len(CURVE_TOLERANCES)
    assert overlap_table(gt, pred, min_region=0, gt_parts=True).gt_labels.tolist() == [1, 2, 3]


def test_eval_gt_parts_option_judges_patches_and_says_so(tmp_path):
    from rangeseg_cli.cli.main import main

    for d in ("pred", "gt"):
        (tmp_path / d).mkdir()
    gt = np.zeros((32, 32), np.int32)
    gt[2:12, 2:30] = 1
    gt[20:30, 2:30] = 1  # one surface seen in two places
    pred = np.zeros_like(gt)
    pred[2:12, 2:30] = 1
    pred[20:30, 2:30] = 2
    np.save(tmp_path / "gt" / "s.gt.npy", gt)
    np.save(tmp_path / "pred" / "s.labels.npy", pred)
    args = ["eval", str(tmp_path / "pred"), str(tmp_path / "gt"), "--json"]
    whole = json.loads(CliRunner().invoke(main, args).output)
    by_patch = json.loads(CliRunner().invoke(main, [*args, "--gt-parts"]).output)
    assert whole["gt_parts"] is False and by_patch["gt_parts"] is True
    assert whole["total"]["correct"] == 0 and whole["total"]["gt_regions"] == 1
    assert by_patch["total"]["correct"] == by_patch["total"]["gt_regions"] == 2


def test_labels_beyond_int64_and_negative_gt_parts_are_refused():
    gt = np.ones((8, 8), np.uint64)
    gt[0, 0] = 2**63 + 5  # used to wrap below 0 and vanish from the count
    with pytest.raises(ValueError, match=r"`gt` has label 9223372036854775813"):
        hoover_compare(gt, np.ones((8, 8), np.int32))
    with pytest.raises(ValueError, match="`gt` has negative labels"):
        connected_parts(np.array([[-1, 0], [0, 0]]))  # the background became a region
    with pytest.raises(ValueError, match="must be a 2-D integer label image"):
        connected_parts(np.zeros(4, np.int32))


# --------------------------------------------------------------------------- object-level holdsite


def cell_scene():
    """40x40 GT: item 1 (surfaces 1 and 2) left, item 2 (surface 3) right, tote wall (4) below."""
    gt = np.zeros((40, 40), np.int32)
    gt[:30, :10] = 1
    gt[:30, 10:20] = 2
    gt[:30, 20:] = 3
    gt[30:, :] = 4
    info = {"surfaces": [{"id": 1, "object": 1}, {"id": 2, "object": 1},
                         {"id": 3, "object": 2}, {"id": 4, "object": 0}],
            "objects": [{"id": 0, "name": "tote", "background": True, "pickable": False},
                        {"id": 1, "name": "box 1", "background": False, "pickable": True},
                        {"id": 2, "name": "box 2", "background": False, "pickable": True}],
            "uncovered": [1, 2], "camera": {"fx": 600.0}}
    return gt, info


def site(row, col, approach=(0.0, 0.0, 1.0)):
    return {"row": row, "col": col, "size": [7, 7], "angle": 0.0,
            "approach_camera": list(approach)}


def test_object_check_accepts_a_window_over_two_surfaces_of_one_item():
    gt, info = cell_scene()
    res = check_object_holdsite(site(10, 10), gt, info)  # columns 7..13: surfaces 1 and 2
    assert res["ok"] and res["object"] == 1 and res["surfaces"] == [1, 2]
    assert res["tilt"] == pytest.approx(0.0)
    assert not check_holdsite(site(10, 10), gt, info)["ok"]  # the surface-level check refuses


def test_object_check_rejects_straddling_wall_invalid_and_tilted_sites():
    gt, info = cell_scene()
    straddle = check_object_holdsite(site(10, 20), gt, info)
    assert not straddle["ok"] and "straddles objects [1, 2]" in straddle["reason"]
    wall = check_object_holdsite(site(35, 20), gt, info)
    assert not wall["ok"] and wall["object"] == 0 and "cannot be picked" in wall["reason"]
    gt_hole = gt.copy()
    gt_hole[12, 26] = 0  # one pixel without a reading under the window
    hole = check_object_holdsite(site(10, 26), gt_hole, info)
    assert not hole["ok"] and "1 window pixels have no valid reading" in hole["reason"]
    assert check_object_holdsite(site(10, 26), gt, info)["ok"]
    tilted = (0.0, np.sin(np.radians(50)), np.cos(np.radians(50)))
    res = check_object_holdsite(site(10, 26, tilted), gt, info)
    assert not res["ok"] and res["tilt"] == pytest.approx(50.0) and "50.0 degrees" in res["reason"]
    assert check_object_holdsite(site(10, 26, tilted), gt, info, max_tilt=55)["ok"]


def test_object_check_judges_the_tilt_from_the_vertical_of_a_tilted_camera():
    from rangeseg_cli.synth.camera import CAMERAS, camera_for

    gt, info = cell_scene()
    cam = camera_for(CAMERAS["ideal"], (40, 40), height=700.0, tilt=(40.0, 0.0))
    info["camera"] = {**info["camera"], "rotation": cam.R.tolist()}
    down = cam.R.T @ np.array([0.0, 0.0, -1.0])  # straight down, in the camera frame
    level = check_object_holdsite(site(10, 26, down), gt, info)
    assert level["ok"] and level["tilt"] == pytest.approx(0.0, abs=1e-9)
    axis = check_object_holdsite(site(10, 26), gt, info)  # along the optical axis: 40 degrees
    assert axis["tilt"] == pytest.approx(40.0) and axis["ok"]
    assert not check_object_holdsite(site(10, 26), gt, info, max_tilt=30)["ok"]


def test_object_check_needs_the_approach_in_a_camera_scene():
    gt, info = cell_scene()
    bare = {"row": 10, "col": 26}
    res = check_object_holdsite(bare, gt, info)
    assert not res["ok"] and "approach_camera" in res["reason"]
    no_camera = {k: v for k, v in info.items() if k != "camera"}
    assert check_object_holdsite(bare, gt, no_camera)["ok"]


def test_null_holdsite_is_right_only_when_nothing_can_be_picked():
    gt, info = cell_scene()
    res = check_object_holdsite(None, gt, info)
    assert not res["ok"] and res["pickable_in_view"] == [1, 2]
    empty = np.where(gt == 4, 4, 0).astype(np.int32)  # an empty tote: the wall alone
    res = check_object_holdsite(None, empty, info)
    assert res["ok"] and res["reason"] == "no holdsite, and nothing to pick"
    assert not check_object_holdsite(site(35, 20), empty, info)["ok"]


def test_object_check_on_a_rendered_empty_tote_takes_no_site(tmp_path):
    write_camera_scenes(tmp_path, ["cam-empty-tote"], [2], size=(120, 160))
    gt = np.load(tmp_path / "cam-empty-tote-s2.gt.npy")
    info = json.loads((tmp_path / "cam-empty-tote-s2.gt.json").read_text())
    assert check_object_holdsite(None, gt, info)["ok"]
    rows, cols = np.nonzero(gt > 0)
    assert not check_object_holdsite(site(int(rows.mean()), int(cols.mean())), gt, info)["ok"]


def test_evaluate_folder_reports_the_object_check(tmp_path):
    gt, info = cell_scene()
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    write_npy(gt_dir / "a.gt.npy", gt)
    write_json(gt_dir / "a.gt.json", info)
    write_npy(pred_dir / "a.labels.npy", gt)
    write_json(pred_dir / "a.holdsite.json", {"holdsite": site(10, 10), "reason": ""})
    res = evaluate_folder(pred_dir, gt_dir)
    assert res["total"]["holdsite_object"] == {"checked": 1, "ok": 1}
    assert res["total"]["holdsite"] == {"checked": 1, "ok": 0}  # the old key, unchanged
    assert res["images"]["a"]["holdsite_object"]["object"] == 1
    straight = evaluate_folder(pred_dir, gt_dir, max_tilt=0.0)  # the approach is the axis
    assert straight["total"]["holdsite_object"]["ok"] == 1
    with pytest.raises(ValueError, match="`max_tilt` 91 must be"):
        evaluate_folder(pred_dir, gt_dir, max_tilt=91)
