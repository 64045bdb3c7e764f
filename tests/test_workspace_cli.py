"""--background, --roi and the frame size of --intrinsics in batches (issue 32, parts 2-3)."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import box_scene, tree_bytes
from rangeseg_cli import run_pipeline
from rangeseg_cli.cli.main import main
from rangeseg_cli.config import load_config
from rangeseg_cli.errors import ConfigError, InputError
from rangeseg_cli.stages import holdsite as holdsite_module
from rangeseg_cli.stages.rangeimage import to_heights


def two_boxes(size: int = 48) -> np.ndarray:
    """A table at 20 with a box of 120 (left) and one of 100 (right): 8-bit heights."""
    z = np.full((size, size), 20.0)
    z[12:36, 4:20] = 120.0
    z[12:36, 28:44] = 100.0
    return z.astype(np.uint8)


def table(size: int = 48) -> np.ndarray:
    return np.full((size, size), 20, np.uint8)


def invoke(*args: str):
    res = CliRunner().invoke(main, [*args, "-j", "1", "-q"])
    return res.exit_code, res.output


@pytest.fixture
def scene(tmp_path, write_png):
    folder = tmp_path / "in"
    folder.mkdir()
    write_png(folder / "a.png", two_boxes())
    write_png(folder / "b.png", box_scene(48).astype(np.uint8))
    write_png(tmp_path / "bg.png", table())
    roi = np.zeros((48, 48), np.uint8)
    roi[:, 24:] = 255  # the right half: the lower box only
    write_png(tmp_path / "roi.png", roi)
    return tmp_path


def test_background_and_roi_reach_find_holdsite_as_heights_and_bool(scene, monkeypatch):
    seen = []
    real = holdsite_module.find_holdsite

    def spy(*args, **kwargs):
        seen.append(kwargs)
        return real(*args, **kwargs)

    monkeypatch.setattr(holdsite_module, "find_holdsite", spy)
    code, out = invoke("run", str(scene / "in" / "a.png"), "-o", str(scene / "out"),
                       "--background", str(scene / "bg.png"), "--roi", str(scene / "roi.png"))
    assert code == 0, out
    (kwargs,) = seen
    expected = to_heights(table(), load_config().input)
    assert kwargs["background"].dtype == np.float64
    np.testing.assert_array_equal(kwargs["background"], expected)
    assert kwargs["roi"].dtype == bool and kwargs["roi"][:, 24:].all()
    assert not kwargs["roi"][:, :24].any()


def test_an_roi_over_one_of_two_boxes_puts_the_site_on_that_box(scene):
    out = scene / "out"
    code, output = invoke("run", str(scene / "in" / "a.png"), "-o", str(out))
    assert code == 0, output
    site = json.loads((out / "a.holdsite.json").read_text())["holdsite"]
    assert site["col"] < 24  # without an ROI: the higher box, on the left
    code, output = invoke("run", str(scene / "in" / "a.png"), "-o", str(out), "--overwrite",
                          "--roi", str(scene / "roi.png"))
    assert code == 0, output
    site = json.loads((out / "a.holdsite.json").read_text())["holdsite"]
    assert site is not None and 28 <= site["col"] < 44 and 12 <= site["row"] < 36


def test_the_workspace_files_are_recorded_as_absolute_paths(scene, monkeypatch):
    monkeypatch.chdir(scene)
    code, output = invoke("run", "in/a.png", "-o", "out", "--background", "bg.png",
                          "--roi", "roi.png")
    assert code == 0, output
    recorded = json.loads((scene / "out" / "rangeseg-run.json").read_text())["config"]
    assert recorded["workspace"]["background"] == str(scene / "bg.png")
    assert recorded["workspace"]["roi"] == str(scene / "roi.png")


def test_stage_commands_read_the_recorded_files_and_give_the_bytes_of_run(scene, monkeypatch):
    monkeypatch.chdir(scene)
    files = ["--background", "bg.png", "--roi", "roi.png"]
    assert invoke("run", "in", "-o", "whole", *files)[0] == 0
    assert invoke("edges", "in", "-o", "staged", *files)[0] == 0
    monkeypatch.chdir(scene / "in")  # the stage commands run from elsewhere
    for stage in ("link", "grow", "holdsite"):
        code, output = invoke(stage, str(scene / "staged"))
        assert code == 0, (stage, output)
    whole, staged = tree_bytes(scene / "whole"), tree_bytes(scene / "staged")
    assert whole.keys() == staged.keys() and "a.holdsite.json" in whole
    assert all(whole[k] == staged[k] for k in whole)


def test_a_frame_of_another_size_fails_that_image_only(scene, write_png):
    write_png(scene / "in" / "big.png", box_scene(64)[:, :40].astype(np.uint8))  # 40 wide
    out = scene / "out"
    code, output = invoke("run", str(scene / "in"), "-o", str(out),
                          "--background", str(scene / "bg.png"))
    assert code == 1
    lines = [line for line in output.splitlines() if "big.png" in line]
    assert len(lines) == 1
    assert (f"size 40x64 pixels (width x height) differs from [workspace] background "
            f"{scene / 'bg.png'} (48x48)" in lines[0])
    assert (out / "a.holdsite.json").exists() and (out / "b.holdsite.json").exists()
    assert not (out / "big.holdsite.json").exists()
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    assert images["big"]["status"] == "failed" and images["a"]["status"] == "done"


@pytest.mark.parametrize("option, make, message", [
    ("--background", None, "[workspace] background: {path}: file not found"),
    ("--roi", None, "[workspace] roi: {path}: file not found"),
    ("--roi", np.zeros((48, 48, 3), np.uint8), "[workspace] roi: {path}: has 3 channels"),
    ("--roi", np.zeros((48, 48), np.float32), "[workspace] roi: {path}: pixel type float32 "
                                              "is not a mask"),
    ("--roi", np.zeros((48, 48), np.uint8), "[workspace] roi: {path}: every pixel is 0, so "
                                            "no site could be picked anywhere"),
    ("--background", np.zeros((48, 48), np.float32),
     "[workspace] background: {path}: no valid"),
])
def test_an_unusable_workspace_file_is_exit_2_before_any_work(scene, option, make, message):
    path = scene / ("w.npy" if make is not None else "missing.png")
    if make is not None:
        np.save(path, make)
    bad_args = ["--set", "input.invalid=0"] if option == "--background" else []
    code, output = invoke("run", str(scene / "in"), "-o", str(scene / "out"), option,
                          str(path), *bad_args)
    assert code == 2, output
    last = output.strip().splitlines()[-1]
    assert last.startswith("Error: " + message.format(path=path)), last
    assert not (scene / "out").exists()


def test_resume_redoes_the_holdsites_when_the_background_file_changed(scene, write_png):
    out = scene / "out"
    args = ["run", str(scene / "in"), "-o", str(out), "--background", str(scene / "bg.png"),
            "--json"]
    assert invoke(*args)[0] == 0
    code, output = invoke(*args, "--resume")
    assert code == 0 and json.loads(output)["resumed"] == 2
    write_png(scene / "bg.png", table() + 1)  # another frame under the same name
    code, output = invoke(*args, "--resume")
    assert code == 0 and json.loads(output)["done"] == 2


def intrinsics_yaml(tmp_path, width, height):
    path = tmp_path / "camera.yaml"
    path.write_text(f"image_width: {width}\nimage_height: {height}\ncamera_matrix:\n"
                    "  rows: 3\n  cols: 3\n  data: [60.0, 0, 24.0, 0, 60.0, 24.0, 0, 0, 1]\n")
    return path


def test_an_image_of_another_size_than_the_intrinsics_fails_with_both_sizes(tmp_path,
                                                                             write_png):
    folder = tmp_path / "in"
    folder.mkdir()
    depth = (1000 - box_scene(48)).astype(np.uint16)
    write_png(folder / "good.png", depth)
    write_png(folder / "wide.png", np.tile(depth, (1, 2)))
    cam = intrinsics_yaml(tmp_path, 48, 48)
    code, output = invoke("run", str(folder), "-o", str(tmp_path / "out"), "--preset",
                          "mm-depth", "--intrinsics", str(cam))
    assert code == 1
    (line,) = [line for line in output.splitlines() if "wide.png" in line]
    assert f"the image is 96x48 pixels (width x height), the camera intrinsics {cam} are " \
           "for 48x48" in line
    site = json.loads((tmp_path / "out" / "good.holdsite.json").read_text())["holdsite"]
    assert site is not None and len(site["point_camera"]) == 3


def test_run_pipeline_reads_the_configured_files_or_takes_arrays(scene):
    config = load_config(overrides={"workspace": {"roi": str(scene / "roi.png")}})
    from_file = run_pipeline(two_boxes(), config).holdsite.to_dict()["holdsite"]
    roi = np.zeros((48, 48), bool)
    roi[:, 24:] = True
    given = run_pipeline(two_boxes(), roi=roi).holdsite.to_dict()["holdsite"]
    assert from_file == given and from_file["col"] >= 28
    with pytest.raises(InputError, match=r"image: size 48x48 pixels \(width x height\) "
                                         r"differs from `background` \(40x32\)"):
        run_pipeline(two_boxes(), background=np.pad(table(32), ((0, 0), (0, 8)), mode="edge"))
    missing = load_config(overrides={"workspace": {"background": str(scene / "no.png")}})
    with pytest.raises(ConfigError, match=r"\[workspace\] background: .*no.png: file not"):
        run_pipeline(two_boxes(), missing)


@pytest.mark.parametrize("extra, warned", [
    ((), "needs camera intrinsics (--intrinsics or [input] intrinsics)"),
    (("--set", "input.metres_per_unit=0"), "needs camera intrinsics (--intrinsics or [input] "
     "intrinsics) and metric depth ([input] metres_per_unit)"),
    (("--intrinsics", "CAM"), None),
    (("--set", "holdsite.footprint_mm=[0, 0]"), None)])
def test_a_depth_run_warns_once_when_the_cup_size_cannot_apply(tmp_path, write_png, extra,
                                                                warned):
    depth = (1000 - box_scene(48)).astype(np.uint16)
    write_png(tmp_path / "a.png", depth)
    write_png(tmp_path / "b.png", depth)
    cam = str(intrinsics_yaml(tmp_path, 48, 48))
    args = [a.replace("CAM", cam) for a in extra]
    res = CliRunner().invoke(main, ["run", str(tmp_path / "a.png"), str(tmp_path / "b.png"),
                                    "-o", str(tmp_path / "out"), "--preset", "mm-depth",
                                    "-j", "1", *args])
    assert res.exit_code == 0, res.output
    lines = [line for line in res.stderr.splitlines() if line.startswith("warning:")]
    reason = json.loads((tmp_path / "out" / "a.holdsite.json").read_text())["reason"]
    if warned is None:
        assert lines == [] and "footprint_mm" not in reason
    else:
        assert len(lines) == 1 and warned in lines[0] and "holdsite.size, 7x7 px" in lines[0]
        assert warned in reason
        quiet = CliRunner().invoke(main, ["run", str(tmp_path / "a.png"), "-o",
                                          str(tmp_path / "q"), "--preset", "mm-depth", "-q",
                                          *args])
        assert quiet.exit_code == 0 and "warning" not in quiet.stderr


@pytest.mark.parametrize(("option", "name"), [("--background", "a.range.npy"),
                                              ("--roi", "a.labels.png")])
def test_a_workspace_file_an_output_would_replace_is_refused_before_any_work(
        scene, write_png, option, name):
    # The batch wrote a.range.npy and a.labels.png over the background and the ROI
    # it had been given in OUT: both lost, and the next run failed on them.
    out = scene / "out"
    out.mkdir()
    kept = out / name
    if name.endswith(".npy"):
        np.save(kept, table().astype(np.float64))
    else:
        write_png(kept, np.full((48, 48), 255, np.uint8))
    before = kept.read_bytes()
    code, output = invoke("run", str(scene / "in"), "-o", str(out), option, str(kept))
    assert code == 2
    assert output.strip().splitlines() == [
        f"Error: {kept} is the [workspace] {option[2:]} file, and this run would overwrite "
        f"it with an output of {scene / 'in' / 'a.png'}; choose another output folder or "
        "move the file"]
    assert kept.read_bytes() == before
    assert sorted(p.name for p in out.iterdir()) == [name]


def tote_depth(holes: float = 0.1) -> np.ndarray:
    """A 16-bit depth frame in 0.1 mm: a floor with a box 100 mm closer, ``holes`` zeros."""
    depth = np.full((64, 80), 7000, np.uint16)
    depth[20:40, 20:50] = 6000
    if holes:
        depth.ravel()[:: round(1 / holes)] = 0
    return depth


def metres(depth: np.ndarray) -> np.ndarray:
    """The 0.1 mm frame as float32 metres, NaN where it has no reading."""
    return np.where(depth > 0, depth / 10000.0, np.nan).astype(np.float32)


@pytest.mark.parametrize("image, overrides, hinted", [
    (tote_depth(), {}, True),
    (tote_depth(holes=0.0), {}, False),  # a 16-bit height map of a raised table: no holes
    (np.where(tote_depth() > 0, 7001 - tote_depth(), 0).astype(np.uint16), {},
     False),  # a height map of the tote: its floor at 1, the box 1000 above it
    ((tote_depth() // 40).astype(np.uint8), {}, False),  # 8 bits: the paper's heights
    (tote_depth(), {"input": {"larger_is_closer": False}}, False),
    (tote_depth(), {"input": {"invalid": 0.0}}, False),
    (tote_depth(), {"input": {"metres_per_unit": 0.001}}, False),
    (metres(tote_depth()), {}, True),  # float32 metres, NaN where no reading
    (metres(tote_depth(holes=0.0)), {}, False),
    (metres(tote_depth()) * 100, {}, False),  # float heights of 60-70 units: no depth scale
    (tote_depth().astype(np.int16) - 20, {}, False),  # signed heights, below 0 somewhere
    (tote_depth(), {"input": {"units_per_pixel": 2.0}}, False),  # a height map, said so
    (tote_depth(), {"input": {"scale": 0.1}}, False),
    (np.kron(tote_depth(), np.ones((16, 16), np.uint16)), {}, True)])  # 1.3 MP: at a stride
def test_a_depth_map_read_as_heights_is_named(image, overrides, hinted):
    from rangeseg_cli.stages.rangeimage import depth_map_hint

    hint = depth_map_hint(image, load_config(overrides=overrides).input)
    assert bool(hint) is hinted
    if hinted and image.dtype == np.uint16:
        assert "16-bit, " in hint and "% holes" in hint and "median 7000" in hint
        assert "--preset mm-depth or tenth-mm-depth" in hint
        assert "for a height map set an [input] key (e.g. units_per_pixel)" in hint
    elif hinted:
        assert "32-bit, 10% holes" in hint and "median 0.7" in hint
        assert "--preset metre-depth (depth in metres)" in hint


@pytest.mark.parametrize("image, overrides, hinted", [
    (metres(tote_depth()), {"input": {"larger_is_closer": False}}, "median 0.7"),
    (metres(tote_depth()), {"input": {"larger_is_closer": False, "metres_per_unit": 1.0}},
     "depth units of 1 m"),
    (tote_depth(), {"input": {"metres_per_unit": 0.05}}, "depth units of 0.05 m"),
    (metres(tote_depth()), {"input": {"larger_is_closer": False, "scale": 1000.0}}, ""),
    (metres(tote_depth()) * 1000, {"input": {"larger_is_closer": False,
                                             "metres_per_unit": 0.001}}, ""),  # mm, said so
    (metres(tote_depth()) * 1000, {"input": {"larger_is_closer": False}}, ""),  # float mm
    (metres(tote_depth()), {}, ""),  # read as heights: depth_map_hint's case
    (tote_depth(), {"input": {"larger_is_closer": False}}, ""),  # integers: 0.1 mm or mm
    (tote_depth(), {"input": {"metres_per_unit": 0.001}}, ""),
    (metres(tote_depth()), {"input": {"larger_is_closer": False, "metres_per_unit": 0.001}},
     "read as 0.7 mm"),  # metres read with --preset mm-depth's units
    (metres(tote_depth()), {"input": {"larger_is_closer": False, "scale": 0.1,
                                      "metres_per_unit": 0.001}}, "read as 0.07 mm")])
def test_depth_in_units_coarser_than_the_settings_is_named(image, overrides, hinted):
    from rangeseg_cli.stages.rangeimage import coarse_units_hint

    hint = coarse_units_hint(image, load_config(overrides=overrides).input)
    assert (hinted in hint) if hinted else hint == ""
    if hinted:  # depth: the preset; a height map: its scale
        said = "--preset metre-depth" if "larger_is_closer" in overrides["input"] else (
            "input.scale to mm with input.metres_per_unit=0.001")
        assert said in hint


def test_a_run_on_depth_in_metres_read_as_mm_warns_and_the_preset_picks_the_box(tmp_path):
    path = tmp_path / "a.npy"
    np.save(path, metres(tote_depth(holes=0.01)))
    def run(*args: str) -> tuple[list[str], dict]:
        out = tmp_path / "out"
        res = CliRunner().invoke(main, ["run", str(path), "-o", str(out), "--overwrite", *args])
        assert res.exit_code == 0, res.output
        said = [line for line in res.stderr.splitlines() if line.startswith("warning:")]
        return said, json.loads((out / "a.holdsite.json").read_text())

    said, found = run("--set", "input.larger_is_closer=false")
    assert len(said) == 1 and "metres read as mm" in said[0]
    assert found["holdsite"] is None
    said, found = run("--preset", "metre-depth")
    assert not any("metres read as mm" in line for line in said)
    site = found["holdsite"]
    assert site is not None and 20 <= site["row"] < 40 and 20 <= site["col"] < 50  # the box


def test_a_run_on_a_depth_map_without_a_preset_warns_once(tmp_path, write_png):
    for name in ("a.png", "b.png"):
        write_png(tmp_path / name, tote_depth())
    inputs = [str(tmp_path / "a.png"), str(tmp_path / "b.png")]

    def warnings(*args: str, code: int = 0) -> list[str]:
        res = CliRunner().invoke(main, ["run", *inputs, "-o", str(tmp_path / "out"),
                                        "--overwrite", "-j", "1", *args])
        assert res.exit_code == code, res.output
        return [line for line in res.stderr.splitlines() if "may be a depth map" in line]

    said = warnings()
    assert len(said) == 1 and said[0].startswith(f"warning: {inputs[0]} may be a depth map")
    assert warnings("-q") == []
    assert warnings("--preset", "tenth-mm-depth") == []
    assert warnings("--set", "input.units_per_pixel=1") == []
    (tmp_path / "a.png").write_bytes(b"not an image")  # the next input is looked at
    said = warnings(code=1)  # a.png fails
    assert len(said) == 1 and said[0].startswith(f"warning: {inputs[1]} may be a depth map")
    res = CliRunner().invoke(main, ["edges", inputs[1], "-o", str(tmp_path / "e")])
    assert res.exit_code == 0 and "depth map" not in res.stderr  # no holdsite: no word


def test_the_background_and_roi_files_in_an_input_folder_are_no_frames(scene):
    # Kept beside the frames, the empty scene and the mask are not run as frames of their
    # own (they are counted with the files not read); named themselves, they are.
    folder = scene / "in"
    (scene / "bg.png").rename(folder / "bg.png")
    (scene / "roi.png").rename(folder / "roi.png")
    out = scene / "out"
    code, output = invoke("run", str(folder), "-o", str(out),
                          "--background", str(folder / "bg.png"), "--roi", str(folder / "roi.png"))
    assert code == 0, output
    assert sorted(p.name for p in out.glob("*.holdsite.json")) == ["a.holdsite.json",
                                                                   "b.holdsite.json"]
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert sorted(manifest["images"]) == ["a", "b"]
    assert manifest["summary"]["not_images"] == 2
    code, output = invoke("run", str(folder / "bg.png"), "-o", str(scene / "named"),
                          "--background", str(folder / "bg.png"))
    assert code == 0, output
    assert (scene / "named" / "bg.holdsite.json").exists()
    code, output = invoke("run", str(folder), "-o", str(scene / "plain"))
    assert code == 0, output
    assert len(list((scene / "plain").glob("*.holdsite.json"))) == 4  # without them: frames


def table_heights(relief: int, dtype: type = np.uint16) -> np.ndarray:
    """A height map: a floor at 0 and a wedge rising to ``relief`` units above it.

    Most pixels 0 as a depth camera's holes, but its readings reach down
    near the floor: no depth map (:func:`depth_map_hint`).
    """
    heights = np.zeros((64, 80), dtype)
    heights[20:40, 20:50] = np.linspace(relief / 10, relief, 30).round().astype(dtype)
    return heights


@pytest.mark.parametrize("image, overrides, hinted", [
    (table_heights(700), {}, True),  # 0.1 mm: a 70 mm box
    (table_heights(255), {}, False),  # within an 8-bit image's range
    (table_heights(700).astype(np.int32) - 300, {}, True),  # signed: the span counts
    (table_heights(200, np.uint8), {}, False),  # the paper's 8 bits
    (table_heights(700).astype(np.float32), {}, False),  # floating point: units unknown
    (np.where(table_heights(700) > 300, 65535, 100).astype(np.uint16), {},
     False),  # the wedge's top is the clipped top value: no reading
    (table_heights(700), {"input": {"scale": 0.1}}, False),
    (table_heights(700), {"input": {"units_per_pixel": 20.0}}, False),
    (table_heights(700), {"input": {"fill_holes": 0}}, True),  # no key of the units
    (table_heights(500) + 6000, {}, False),  # readings far from 0: no height map's floor
    (np.kron(table_heights(700), np.ones((16, 16), np.uint16)), {}, True)])  # at a stride
def test_heights_in_units_finer_than_the_thresholds_are_named(image, overrides, hinted):
    from rangeseg_cli.stages.rangeimage import fine_units_hint

    hint = fine_units_hint(image, load_config(overrides=overrides).input)
    assert bool(hint) is hinted
    if hinted:
        low = int(image.min())
        assert f"heights spanning {low}..{low + 700}, more than the 0..255" in hint
        assert "--set input.scale=0.1 for 0.1 mm" in hint


def test_a_run_on_a_fine_height_map_warns_once_and_a_scale_silences_it(tmp_path, write_png):
    path = write_png(tmp_path / "a.png", table_heights(700))

    def warnings(*args: str) -> list[str]:
        res = CliRunner().invoke(main, ["run", str(path), "-o", str(tmp_path / "out"),
                                        "--overwrite", *args])
        assert res.exit_code == 0, res.output
        return [line for line in res.stderr.splitlines() if line.startswith("warning:")]

    said = warnings()
    assert len(said) == 1 and said[0].startswith(f"warning: {path} has 16-bit heights")
    assert "depth map" not in said[0]
    assert warnings("--set", "input.scale=0.1") == []
    assert warnings("-q") == []
