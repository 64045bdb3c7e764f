"""A demanding user's unhappy paths: every one ends in one clear line, never a traceback."""

import errno
import json

import numpy as np
import pytest

from conftest import box_scene
from rangeseg_cli.cli.main import main
from rangeseg_cli.config import REFINE_PASSES


def one_line_error(res) -> str:
    """The output's last line, after checking there is no traceback."""
    assert "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)
    return res.output.strip().splitlines()[-1]


# --------------------------------------------------------------------------- output folder


def test_output_folder_below_a_file_is_one_line_exit_2(runner, box_png, tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file, not a folder")
    res = runner.invoke(main, ["run", str(box_png), "-o", str(blocker / "out"), "-j", "1"])
    assert res.exit_code == 2
    assert "cannot create the output folder" in one_line_error(res)
    assert blocker.read_text() == "a file, not a folder"


@pytest.mark.parametrize("args", [
    ["run", "{png}", "-o", ""],          # -o "$OUT" with OUT unset: not the current folder
    ["run", "", "-o", "{tmp}/out"],      # an unset input: not every image below here
    ["run", "{png}", " ", "-o", "{tmp}/out"],
    ["grow", ""],
    ["synth", ""],
    ["eval", "", "{tmp}"],
    ["eval", "{tmp}", "{tmp}", "--plot", ""],
    ["run", "{png}", "-o", "file://"],   # -o "file://$OUT" with OUT unset
    ["run", "file://localhost", "-o", "{tmp}/out"],
])
def test_an_empty_path_is_a_usage_error_not_the_current_folder(runner, box_png, tmp_path,
                                                               monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    before = sorted(p.name for p in tmp_path.iterdir())
    res = runner.invoke(main, [a.format(png=box_png, tmp=tmp_path) for a in args])
    assert res.exit_code == 2
    assert "an empty path" in one_line_error(res)
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # nothing written here


def test_output_subfolder_blocked_by_a_file_fails_that_image_only(runner, tmp_path, write_png):
    (tmp_path / "in" / "sub").mkdir(parents=True)
    write_png(tmp_path / "in" / "a.png", box_scene(48).astype(np.uint8))
    write_png(tmp_path / "in" / "sub" / "b.png", box_scene(48).astype(np.uint8))
    out = tmp_path / "out"
    out.mkdir()
    (out / "sub").write_text("in the way")
    res = runner.invoke(main, ["run", str(tmp_path / "in"), "-o", str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    assert "Traceback" not in res.output and "internal error" not in res.output
    assert "sub: cannot create the output folder" in res.output
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert manifest["images"]["a"]["status"] == "done"
    assert manifest["images"]["sub/b"]["status"] == "failed"


def test_full_disk_is_one_line_per_image_and_leaves_no_temporary(runner, box_png, tmp_path,
                                                                 monkeypatch):
    import rangeseg_cli.batch.io as rio

    real_replace = rio.os.replace

    def full_disk(src, dst):
        if str(dst).endswith(".npy"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_replace(src, dst)

    monkeypatch.setattr(rio.os, "replace", full_disk)
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    assert "box.range.npy: cannot write (No space left on device)" in res.output
    assert "internal error" not in res.output and "Traceback" not in res.output
    assert list(out.rglob("*.tmp")) == []


def test_manifest_that_cannot_be_written_is_one_line_exit_2(runner, box_png, tmp_path,
                                                            monkeypatch):
    import rangeseg_cli.batch.io as rio

    def read_only(src, dst):
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr(rio.os, "replace", read_only)
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), "-j", "1"])
    assert res.exit_code == 2
    assert one_line_error(res) == (f"Error: {tmp_path / 'out' / 'rangeseg-run.json'}: cannot "
                                   "write (Read-only file system)")


# --------------------------------------------------------------------------- input folders


def test_symlinked_folder_is_searched_and_a_link_loop_ends(runner, tmp_path, write_png):
    (tmp_path / "real").mkdir()
    write_png(tmp_path / "real" / "box.png", box_scene(48).astype(np.uint8))
    (tmp_path / "in").mkdir()
    (tmp_path / "in" / "linked").symlink_to(tmp_path / "real", target_is_directory=True)
    (tmp_path / "in" / "loop").symlink_to(tmp_path / "in", target_is_directory=True)
    out = tmp_path / "out"
    res = runner.invoke(main, ["edges", str(tmp_path / "in"), "-o", str(out), "-j", "1",
                               "--json", "-q"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["done"] == 1
    assert (out / "linked" / "box.edges.npy").exists()


def test_unreadable_subfolder_stops_before_any_work(runner, tmp_path, write_png, monkeypatch):
    import os

    (tmp_path / "in" / "locked").mkdir(parents=True)
    write_png(tmp_path / "in" / "a.png", box_scene(48).astype(np.uint8))
    write_png(tmp_path / "in" / "locked" / "b.png", box_scene(48).astype(np.uint8))
    real_scandir = os.scandir

    def scandir(path="."):  # what chmod 000 does to a user other than root
        if os.fspath(path).endswith("locked"):
            raise PermissionError(errno.EACCES, "Permission denied", os.fspath(path))
        return real_scandir(path)

    monkeypatch.setattr(os, "scandir", scandir)
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(tmp_path / "in"), "-o", str(out), "-j", "1"])
    assert res.exit_code == 2
    assert one_line_error(res) == (f"Error: {tmp_path / 'in' / 'locked'}: cannot read folder "
                                   "(Permission denied)")
    assert not out.exists()


# --------------------------------------------------------------------------- stage commands


def test_redone_edges_make_later_stages_out_of_date(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    res = runner.invoke(main, ["edges", str(box_png), "-o", str(out), "-j", "1", "--overwrite",
                               "--set", "step.threshold=20"])
    assert res.exit_code == 0
    # the old labels and holdsite no longer match the new edges: gone, not left to mislead
    assert not (out / "box.labels.npy").exists() and not (out / "box.holdsite.json").exists()
    assert (out / "box.edges.npy").exists()
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1"])
    assert res.exit_code == 1
    assert "box: its `grow` result is missing, or out of date since an earlier stage was " \
           "redone (or the manifest was written before per-stage settings); run " \
           "`rangeseg grow OUT --resume` first" in res.output
    assert "give this command the settings" not in res.output
    for stage in ("link", "grow", "holdsite"):
        assert runner.invoke(main, [stage, str(out), "-j", "1", "-q"]).exit_code == 0
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert manifest["images"]["box"]["stages"] == ["edges", "link", "grow", "holdsite"]


def test_grow_before_link_names_the_stage_to_run(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["edges", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    res = runner.invoke(main, ["grow", str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    assert "run `rangeseg link OUT --resume` first" in one_line_error(res)


def test_resume_redoes_later_stages_after_edges_were_redone(runner, box_png, tmp_path):
    out = tmp_path / "out"
    run = ["run", str(box_png), "-o", str(out), "-j", "1", "--json", "-q"]
    assert runner.invoke(main, run).exit_code == 0
    assert runner.invoke(main, ["edges", str(box_png), "-o", str(out), "-j", "1",
                                "--overwrite"]).exit_code == 0
    res = runner.invoke(main, [*run, "--resume"])
    assert res.exit_code == 0 and json.loads(res.stdout)["done"] == 1
    assert (out / "box.holdsite.json").exists()


@pytest.mark.parametrize("name, array, message", [
    ("labels.npy", np.zeros((5, 5), np.int32), "shape (5, 5) differs from the heights"),
    ("labels.npy", np.zeros((48, 48)), "holds float64 of shape (48, 48), not the 2-D integer"),
    ("range.npy", np.zeros((48, 48), np.int32), "not the 2-D floating-point map"),
    ("range.npy", np.zeros((48, 48, 2)), "holds float64 of shape (48, 48, 2)"),
])
def test_replaced_intermediate_file_is_named_not_an_internal_error(runner, box_png, tmp_path,
                                                                   name, array, message):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    np.save(out / f"box.{name}", array)
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    line = one_line_error(res)
    assert line.startswith(f"{out / ('box.' + name)}: ") and message in line
    assert "internal error" not in res.output


@pytest.mark.parametrize("name, command, label", [
    ("components.npy", "grow", 48 * 48 + 1),  # 2^31-1 took 16 GB or was killed
    ("components.npy", "grow", -1),
    ("labels.npy", "holdsite", 48 * 48 + 1),
])
def test_label_map_with_a_label_beyond_the_pixel_count_is_named(runner, box_png, tmp_path,
                                                                name, command, label):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    labels = np.load(out / f"box.{name}")
    labels[labels == labels.max()] = label
    np.save(out / f"box.{name}", labels)
    res = runner.invoke(main, [command, str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    assert one_line_error(res) == (f"{out / ('box.' + name)}: label {label} is outside "
                                   "0..2304 (the pixel count): not a label map rangeseg "
                                   "writes; run the stages before it again")


def test_label_map_with_labels_up_to_the_pixel_count_is_used(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["edges", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    assert runner.invoke(main, ["link", str(out), "-j", "1", "-q"]).exit_code == 0
    components = np.load(out / "box.components.npy")
    components[components == components.max()] = 48 * 48
    np.save(out / "box.components.npy", components)
    assert runner.invoke(main, ["grow", str(out), "-j", "1", "-q"]).exit_code == 0


def test_stage_command_with_resume_completes_only_what_is_missing(runner, tmp_path, write_png):
    for name in ("a", "b"):
        write_png(tmp_path / f"{name}.png", box_scene(48).astype(np.uint8))
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(tmp_path / "a.png"), str(tmp_path / "b.png"),
                                "-o", str(out), "-j", "1"]).exit_code == 0
    (out / "b.labels.npy").unlink()
    res = runner.invoke(main, ["grow", str(out), "-j", "1", "--resume", "--json", "-q"])
    assert res.exit_code == 0
    assert json.loads(res.stdout) | {"seconds": 0, "stage_seconds": {}} == {
        "done": 1, "resumed": 1, "failed": 0, "not_images": 0, "interrupted": False,
        "terminated": False, "errors": {}, "seconds": 0, "stage_seconds": {}}
    assert (out / "b.labels.npy").exists()


# --------------------------------------------------------------------------- failed images


def outputs_of(out, stem: str) -> list[str]:
    return sorted(p.name for p in out.iterdir() if p.name.startswith(f"{stem}."))


@pytest.fixture
def cup_scene(tmp_path):
    """A synthetic cup (PNG in ``in/``) and its ground truth (in ``gt/``)."""
    from rangeseg_cli.synth.scenes import write_scenes

    write_scenes(tmp_path / "scene", ["cup"], [0.0], seed=0, size=(64, 64))
    (tmp_path / "in").mkdir()
    (tmp_path / "gt").mkdir()
    (tmp_path / "scene" / "cup-n0.png").rename(tmp_path / "in" / "cup-n0.png")
    for name in ("cup-n0.gt.npy", "cup-n0.gt.json"):
        (tmp_path / "scene" / name).rename(tmp_path / "gt" / name)
    return tmp_path / "in" / "cup-n0.png", tmp_path / "gt"


def test_failed_overwrite_leaves_no_old_results_and_eval_does_not_score_them(runner, cup_scene,
                                                                             tmp_path):
    image, gt = cup_scene
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(image.parent), "-o", str(out), "-j", "1",
                                "-q"]).exit_code == 0
    assert len(outputs_of(out, "cup-n0")) == 13
    image.write_bytes(image.read_bytes()[:100])  # the input is damaged since
    res = runner.invoke(main, ["run", str(image.parent), "-o", str(out), "-j", "1", "-q",
                               "--overwrite"])
    assert res.exit_code == 1 and "not a readable image" in one_line_error(res)
    assert outputs_of(out, "cup-n0") == []  # the old results are not left to be taken as new
    res = runner.invoke(main, ["eval", str(out), str(gt), "-q"])
    assert res.exit_code == 1
    assert one_line_error(res).startswith("cup-n0: not scored: ")


def test_eval_does_not_score_labels_the_manifest_records_as_failed(runner, cup_scene, tmp_path):
    image, gt = cup_scene
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(image), "-o", str(out), "-j", "1",
                                "-q"]).exit_code == 0
    assert runner.invoke(main, ["eval", str(out), str(gt), "-q"]).exit_code == 0
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    manifest["images"]["cup-n0"] |= {"status": "failed", "stages": [], "error": "it broke"}
    (out / "rangeseg-run.json").write_text(json.dumps(manifest))  # labels of an older run
    res = runner.invoke(main, ["eval", str(out), str(gt), "-q"])
    assert res.exit_code == 1
    assert one_line_error(res) == (f"cup-n0: not scored: {out / 'rangeseg-run.json'} records "
                                   "that it failed (it broke)")
    manifest["images"]["cup-n0"]["stages"] = ["edges", "link", "grow"]  # holdsite failed
    (out / "rangeseg-run.json").write_text(json.dumps(manifest))
    assert runner.invoke(main, ["eval", str(out), str(gt), "-q"]).exit_code == 0


def test_image_failing_at_a_later_stage_keeps_no_results_of_an_earlier_run(
        runner, box_png, tmp_path, monkeypatch):
    from rangeseg_cli.batch import jobs
    from rangeseg_cli.errors import InputError

    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0

    def broken(*args):
        raise InputError("box: no surface fits")

    monkeypatch.setitem(jobs._STAGE_RUNNERS, "grow", broken)
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1", "-q",
                               "--overwrite", "--set", "step.threshold=20"])
    assert res.exit_code == 1 and "box: no surface fits" in res.output
    # new edges beside old labels and holdsite would be two runs in one folder
    assert outputs_of(out, "box") == []


def test_stage_command_failing_removes_its_stale_files_and_keeps_the_earlier_stages(
        runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    np.save(out / "box.components.npy", np.zeros((5, 5), np.int32))
    res = runner.invoke(main, ["grow", str(out), "-j", "1", "-q"])
    assert res.exit_code == 1 and "box.components.npy" in one_line_error(res)
    assert outputs_of(out, "box") == [
        "box.components.npy", "box.components.png", "box.edges.npy", "box.edges.png",
        "box.linked.png", "box.range.npy", "box.roof.png", "box.step.png"]


def test_rerun_without_pictures_removes_the_old_pictures(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1", "--overwrite",
                               "--set", "output.png=false", "--set", "step.threshold=20"])
    assert res.exit_code == 0
    assert [n for n in outputs_of(out, "box") if n.endswith(".png")] == []


# --------------------------------------------------------------------------- inputs kept


def test_input_named_as_another_inputs_output_is_refused_before_any_work(runner, box_png,
                                                                         tmp_path):
    other = tmp_path / "box.range.npy"
    np.save(other, np.random.default_rng(0).random((48, 48)) * 100)
    before = other.read_bytes()
    res = runner.invoke(main, ["run", str(box_png), str(other), "-o", str(tmp_path), "-j", "1"])
    assert res.exit_code == 2
    assert one_line_error(res) == (f"Error: {other} is an input, and this run would overwrite "
                                   f"it with an output of {box_png}; choose another output "
                                   "folder or rename one of them")
    assert other.read_bytes() == before
    assert not (tmp_path / "rangeseg-run.json").exists() and outputs_of(tmp_path, "box") == [
        "box.png", "box.range.npy"]


def test_input_linked_to_an_output_is_refused(runner, box_png, tmp_path):
    data = tmp_path / "box.range.npy"
    np.save(data, box_scene(48))
    (tmp_path / "elsewhere").mkdir()
    link = tmp_path / "elsewhere" / "frame.npy"
    link.symlink_to(data)
    res = runner.invoke(main, ["run", str(box_png), str(link), "-o", str(tmp_path), "-j", "1"])
    assert res.exit_code == 2 and f"{link} is an input" in one_line_error(res)
    assert np.array_equal(np.load(data), box_scene(48))


def test_file_named_like_an_output_in_the_input_folder_is_not_overwritten(runner, box_png,
                                                                          tmp_path):
    mine = tmp_path / "box.range.npy"  # the user's (no manifest lists it): an input image
    np.save(mine, box_scene(48))
    before = mine.read_bytes()
    res = runner.invoke(main, ["run", str(tmp_path), "-o", str(tmp_path), "-j", "1"])
    assert res.exit_code == 2
    line = one_line_error(res)
    assert line.startswith(f"Error: {mine} is an input, and this run would overwrite it")
    assert str(box_png) in line
    assert mine.read_bytes() == before


def test_rerun_into_the_input_folder_may_overwrite_its_own_results(runner, box_png, tmp_path):
    args = ["run", str(tmp_path), "-o", str(tmp_path), "-j", "1", "-q", "--json"]
    assert runner.invoke(main, args).exit_code == 0
    res = runner.invoke(main, [*args, "--overwrite"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["done"] == 1


# --------------------------------------------------------------------------- damaged manifest


@pytest.mark.parametrize("damage, problem", [
    (lambda m: m | {"images": 5}, '"images" is a number, not an object of images'),
    (lambda m: m | {"images": {"box": [1]}}, "\"images\" entry 'box': a list, not an object"),
    (lambda m: m | {"images": {"box": {"stages": "edges"}}},
     "\"images\" entry 'box': \"stages\" is not a list of stage names"),
    (lambda m: m | {"images": {"box": {"status": None}}},
     "\"images\" entry 'box': \"status\" is null, not a string"),
    (lambda m: m | {"images": {"box": {"input_stamp": 5}}},
     "\"images\" entry 'box': \"input_stamp\" is a number, not a string"),
    (lambda m: m | {"config": []}, '"config" is a list, not an object of tables'),
    (lambda m: [m], "it holds a list, not an object"),
])
@pytest.mark.parametrize("command", ["run --resume", "link --overwrite", "grow", "eval"])
def test_manifest_of_the_wrong_shape_is_one_line_naming_it(runner, box_png, tmp_path, damage,
                                                           problem, command):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    path = out / "rangeseg-run.json"
    path.write_text(json.dumps(damage(json.loads(path.read_text()))))
    before = path.read_bytes()
    (tmp_path / "box.gt.npy").write_bytes(b"")  # for eval: one ground truth to pair
    res = runner.invoke(main, {
        "run --resume": ["run", str(box_png), "-o", str(out), "--resume", "-j", "1"],
        "link --overwrite": ["link", str(out), "--overwrite", "-j", "1"],
        "grow": ["grow", str(out), "-j", "1"],
        "eval": ["eval", str(out), str(tmp_path)]}[command])
    assert res.exit_code == 2
    assert one_line_error(res) == (f"Error: {path}: not a manifest of rangeseg ({problem}); "
                                   "repair it, or delete it and redo the images with "
                                   "--overwrite")
    assert path.read_bytes() == before


# --------------------------------------------------------------------------- options


@pytest.mark.parametrize("command", ["run", "grow"])
def test_resume_with_overwrite_is_a_usage_error(runner, box_png, tmp_path, command):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    before = (out / "rangeseg-run.json").read_bytes()
    args = ([str(box_png), "-o", str(out)] if command == "run" else [str(out)])
    res = runner.invoke(main, [command, *args, "--resume", "--overwrite"])
    assert res.exit_code == 2
    assert "--resume and --overwrite exclude each other" in one_line_error(res)
    assert (out / "rangeseg-run.json").read_bytes() == before


def test_one_file_named_twice_is_one_image(runner, box_png, tmp_path):
    res = runner.invoke(main, ["edges", str(box_png), str(box_png), str(tmp_path),
                               "-o", str(tmp_path / "out"), "-j", "1", "--json", "-q"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["done"] == 1


def test_same_stem_in_one_folder_says_to_rename(runner, box_png, tmp_path):
    np.save(tmp_path / "box.npy", box_scene(48))
    res = runner.invoke(main, ["edges", str(tmp_path), "-o", str(tmp_path / "out")])
    assert res.exit_code == 2
    assert "would both write" in res.output and "rename one of them" in res.output


# --------------------------------------------------------------------------- Python API


def test_masked_pixels_of_a_masked_array_are_invalid():
    from rangeseg_cli import run_pipeline

    z = np.full((32, 32), 20.0)
    mask = np.zeros(z.shape, bool)
    mask[:, :8] = True
    z[:, :8] = 1e6  # garbage under the mask
    result = run_pipeline(np.ma.masked_array(z, mask=mask))
    assert np.isnan(result.heights[:, :8]).all()
    assert (result.labels[:, :8] == 0).all()


@pytest.mark.parametrize("config", [{"step": {"threshold": 3}}, "my.toml"])
def test_run_pipeline_with_a_config_that_is_not_a_config_says_so(config):
    from rangeseg_cli import run_pipeline

    with pytest.raises(TypeError, match="config"):
        run_pipeline(np.ones((32, 32)), config)


# --------------------------------------------------------------------------- numbers and eval


@pytest.mark.parametrize("setting, message", [
    ("link.min_component=1" + "0" * 400, "[link] min_component = 1000000000"),
    ("step.threshold=1" + "0" * 400, "beyond the floating-point range"),
    ("link.min_component=100000000000000000000", "expected an integer >= 1 <= 2147483647"),
    ("refine.fit_factor=1e200", "[refine] fit_factor = 1e+200: expected a number > 0.0 <= 1000.0"),
    ("holdsite.rotation_step=0.001", "expected a number >= 0.5 <= 90.0"),
])
def test_out_of_range_number_on_the_command_line_is_one_line_exit_2(runner, box_png, tmp_path,
                                                                    setting, message):
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), "--set",
                               setting])
    assert res.exit_code == 2 and message in one_line_error(res)
    assert len(res.output.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


@pytest.fixture
def scored(tmp_path):
    """``(pred, gt)`` folders: one scene and its own truth as the labels."""
    from rangeseg_cli.synth.scenes import write_scenes

    gt, pred = tmp_path / "gt", tmp_path / "pred"
    write_scenes(gt, ["box"], [0], seed=0, size=(32, 32))
    pred.mkdir()
    np.save(pred / "box-n0.labels.npy", np.load(gt / "box-n0.gt.npy"))
    return str(pred), str(gt)


def test_eval_tolerance_nan_is_a_usage_error(runner, scored):
    # click's FloatRange lets NaN through: a 31-line ValueError traceback
    res = runner.invoke(main, ["eval", *scored, "--tolerance", "nan"])
    assert res.exit_code == 2
    assert one_line_error(res) == ("Error: Invalid value for '--tolerance': nan is not in the "
                                   "range 0.5<=x<=1.0")


def test_eval_plot_that_cannot_be_written_stops_before_scoring(runner, scored, tmp_path):
    (tmp_path / "afile").write_text("")
    plot = tmp_path / "afile" / "curve.png"
    res = runner.invoke(main, ["eval", *scored, "--plot", str(plot)])
    assert res.exit_code == 2
    assert res.output.strip() == f"Error: {plot}: cannot write (Not a directory)"


def test_eval_plot_write_failing_after_scoring_is_one_line(runner, scored, tmp_path,
                                                           monkeypatch):
    # the table, then a traceback ending in OutputError: cannot write
    from rangeseg_cli.errors import OutputError
    from rangeseg_cli.synth import evaluate

    def fail(curve, path, **kwargs):
        raise OutputError(f"{path}: cannot write (No space left on device)")

    monkeypatch.setattr(evaluate, "plot_curve", fail)
    plot = tmp_path / "curve.png"
    res = runner.invoke(main, ["eval", *scored, "--plot", str(plot), "-q"])
    assert res.exit_code == 1
    assert one_line_error(res) == f"Error: {plot}: cannot write (No space left on device)"
    assert not plot.exists()


def _entry(out) -> dict:
    return json.loads((out / "rangeseg-run.json").read_text())["images"]["box"]


def test_a_stage_command_twice_with_a_config_of_many_digits_is_current(runner, box_png,
                                                                        tmp_path):
    # The manifest used to round the configuration to 6 digits: the stage commands read
    # it back changed, so the second `holdsite` found every earlier stage "older" and
    # marked the image failed.
    toml = tmp_path / "c.toml"
    toml.write_text("[step]\nthreshold = 6.123456789\n[holdsite]\nmax_ar_std = 1.000000123\n")
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1",
                               "--config", str(toml)])
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert manifest["config"]["step"]["threshold"] == 6.123456789
    first = (out / "box.holdsite.json").read_bytes()
    for _ in range(2):
        res = runner.invoke(main, ["holdsite", str(out), "-j", "1"])
        assert res.exit_code == 0, res.output
        assert _entry(out)["stages"] == ["edges", "link", "grow", "holdsite"]
        assert (out / "box.holdsite.json").read_bytes() == first


def test_new_settings_of_a_later_stage_keep_the_earlier_stages_current(runner, box_png,
                                                                       tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1",
                               "--set", "holdsite.max_ar_std=2"])
    assert res.exit_code == 0, res.output
    assert _entry(out)["stages"] == ["edges", "link", "grow", "holdsite"]
    no_facets = json.dumps([p for p in REFINE_PASSES if p != "facets"])
    res = runner.invoke(main, ["grow", str(out), "-j", "1", "--set", f"refine.passes={no_facets}"])
    assert res.exit_code == 0, res.output
    entry = _entry(out)
    assert entry["stages"] == ["edges", "link", "grow"]  # the holdsite came from old labels
    assert not (out / "box.holdsite.json").exists()
    assert entry["stage_configs"]["link"] != entry["stage_configs"]["grow"]


def test_a_refused_image_keeps_its_entry_and_its_files(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    before = _entry(out)
    site = (out / "box.holdsite.json").read_bytes()
    # other settings of an earlier stage than the labels were made with: refused, not mixed
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1",
                               "--set", "link.min_component=50"])
    assert res.exit_code == 1
    assert "box: its `grow` result was made with other settings of [input], [output], " \
           "[step], [roof], [link], [grow], [refine] than these; run `rangeseg grow OUT " \
           "--resume` first, or give this command the settings that made it" in res.output
    after = _entry(out)
    assert after["status"] == "done" and after["stages"] == before["stages"]
    assert after["stage_configs"] == before["stage_configs"]
    assert (out / "box.holdsite.json").read_bytes() == site
    # and the folder still goes on as it was
    assert runner.invoke(main, ["holdsite", str(out), "-j", "1", "-q"]).exit_code == 0


def test_a_manifest_without_stage_digests_keeps_its_stages_under_the_same_config(
        runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    path = out / "rangeseg-run.json"
    manifest = json.loads(path.read_text())
    del manifest["images"]["box"]["stage_configs"]  # as written before they were recorded
    path.write_text(json.dumps(manifest))
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1"])
    assert res.exit_code == 0, res.output
    assert _entry(out)["stages"] == ["edges", "link", "grow", "holdsite"]
    manifest = json.loads(path.read_text())
    manifest["images"]["box"]["stage_configs"] = {"grow": 7}
    path.write_text(json.dumps(manifest))
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1"])
    assert res.exit_code == 2
    assert '"stage_configs" is not an object of stage names and digests' in res.output


@pytest.mark.parametrize("name, command, edit, message", [
    ("edges.npy", "grow", lambda a: np.where(a == a.max(), 77, a).astype(a.dtype),
     "edge code 77 is outside 0..3: not an edge map rangeseg writes"),
    ("range.npy", "link", lambda a: np.full_like(a, np.nan), "no valid height"),
    ("range.npy", "grow", lambda a: np.where(np.isfinite(a), 1e300, a), "height 1e+300"),
])
def test_a_hand_edited_edge_or_height_map_is_named_not_an_internal_error(
        runner, box_png, tmp_path, name, command, edit, message):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    np.save(out / f"box.{name}", edit(np.load(out / f"box.{name}")))
    res = runner.invoke(main, [command, str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    line = one_line_error(res)
    assert line.startswith(f"{out / ('box.' + name)}: ") and message in line
    assert "internal error" not in res.output and "Warning" not in res.output


def test_ctrl_c_before_the_batch_exits_130_not_aborted(runner, box_png, tmp_path,
                                                       monkeypatch):
    import rangeseg_cli.cli.main as cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C while the config is read or IMAGES are listed

    monkeypatch.setattr(cli, "_load_config", interrupted)
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out")])
    assert res.exit_code == 130
    assert "interrupted" in res.output and "Aborted" not in res.output
    assert not (tmp_path / "out").exists()


def test_ctrl_c_while_the_modules_load_exits_130_without_a_traceback(monkeypatch, capsys):
    import importlib.abc
    import sys

    from rangeseg_cli import _entry

    class Interrupt(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name == "rangeseg_cli.cli.main":
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "rangeseg_cli.cli.main")
    monkeypatch.setattr(sys, "meta_path", [Interrupt(), *sys.meta_path])
    with pytest.raises(SystemExit) as stop:
        _entry.main()
    assert stop.value.code == 130
    assert capsys.readouterr().err == "interrupted\n"


@pytest.mark.parametrize("out", ["http://localhost:9/out", "HTTPS://example.com/x"])
def test_an_out_that_can_only_be_read_is_a_usage_error(runner, box_png, out):
    res = runner.invoke(main, ["run", str(box_png), "-o", out, "-j", "1"])
    assert res.exit_code == 2
    assert one_line_error(res).endswith(
        "URLs can be read, not written; OUT must be a local folder or a store such as "
        "s3://bucket/folder")
    assert "NotImplementedError" not in res.output


def test_a_stage_command_refuses_an_image_the_manifest_does_not_list(runner, box_png,
                                                                     tmp_path):
    # a folder copied without its manifest: nothing tells which settings made its edges
    out = tmp_path / "out"
    res = runner.invoke(main, ["edges", str(box_png), "-o", str(out), "-j", "1",
                               "--set", "step.threshold=8"])
    assert res.exit_code == 0
    (out / "rangeseg-run.json").unlink()
    res = runner.invoke(main, ["link", str(out), "-j", "1", "-q"])
    assert res.exit_code == 1
    assert "box: its `edges` result is not recorded in the manifest (nothing tells what " \
           "made its files)" in one_line_error(res)
    assert "run `rangeseg edges IMAGES -o OUT --resume` first" in one_line_error(res)
    assert not (out / "box.components.npy").exists()


def test_eval_does_not_score_an_image_a_killed_run_left_running(runner, tmp_path):
    from rangeseg_cli.synth.scenes import write_scenes

    gt = tmp_path / "gt"
    write_scenes(gt, ["box"], [0], 0, size=(48, 48))
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(gt), "-o", str(out), "-j", "1", "-q"]).exit_code == 0
    path = out / "rangeseg-run.json"
    manifest = json.loads(path.read_text())
    manifest["images"]["box-n0"].update(status="running", stages=["edges"])  # as start() left
    path.write_text(json.dumps(manifest))
    res = runner.invoke(main, ["eval", str(out), str(gt), "-q"])
    assert res.exit_code == 1
    assert "box-n0: not scored: " in res.output
    assert "records that a run stopped before it was done (killed?); finish it with " \
           "--resume" in res.output


def test_set_on_a_stage_command_changes_values_of_the_recorded_config(runner, box_png,
                                                                      tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text("[step]\nthreshold = 7.5\n")
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1",
                               "--config", str(toml)])
    assert res.exit_code == 0
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1", "--set", "holdsite.size=[9,9]"])
    assert res.exit_code == 0, res.output  # was refused: --set started from the defaults
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert manifest["config"]["step"]["threshold"] == 7.5
    assert manifest["config"]["holdsite"]["size"] == [9, 9]
    assert manifest["images"]["box"]["stages"] == ["edges", "link", "grow", "holdsite"]
    # --preset (or --config) still replaces it: other [step] settings than the labels'
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1", "--preset", "paper"])
    assert res.exit_code == 1 and "made with other settings" in res.output


def test_a_null_in_the_manifest_config_is_named_as_null(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    path = out / "rangeseg-run.json"
    manifest = json.loads(path.read_text())
    assert manifest["config"]["input"]["invalid"] is None  # NaN, written as JSON's null
    manifest["config"]["step"]["threshold"] = None  # a hand edit
    path.write_text(json.dumps(manifest))
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1"])
    assert res.exit_code == 2
    assert "[step] threshold = None: expected" in one_line_error(res)  # not "= nan"
    manifest["config"]["step"]["threshold"] = 6.0
    path.write_text(json.dumps(manifest))
    assert runner.invoke(main, ["holdsite", str(out), "-j", "1", "-q"]).exit_code == 0


def test_a_stage_command_on_an_older_versions_output_says_what_to_do(runner, box_png, tmp_path):
    import json

    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1", "-q"]
                         ).exit_code == 0
    manifest = out / "rangeseg-run.json"
    data = json.loads(manifest.read_text())
    data["config"]["input"] = {**data["config"]["input"], "fx": 0.0}  # an older release's key
    manifest.write_text(json.dumps(data))
    res = runner.invoke(main, ["grow", str(out), "-j", "1"])
    assert res.exit_code == 2 and "Traceback" not in res.output
    line, = res.output.strip().splitlines()
    assert "made by an older rangeseg" in line and "[input] fx is now part of input.intrinsics" \
        in line and "--overwrite" in line
