import json

import numpy as np
import pytest

from conftest import box_scene
from rangeseg_cli import __version__
from rangeseg_cli.cli.main import main
from rangeseg_cli.config import Config, load_config


@pytest.fixture
def images(tmp_path, write_png):
    folder = tmp_path / "in"
    (folder / "sub").mkdir(parents=True)
    write_png(folder / "box.png", box_scene(48).astype(np.uint8))
    write_png(folder / "sub" / "box2.png", box_scene(48, noise=1.0).clip(0, 255).astype(np.uint8))
    (folder / "README.txt").write_text("not an image")
    return folder


def test_version_and_help_on_every_command(runner):
    res = runner.invoke(main, ["--version"])
    assert res.exit_code == 0 and __version__ in res.output
    for cmd in ("run", "edges", "link", "grow", "holdsite", "config", "synth", "eval"):
        res = runner.invoke(main, [cmd, "--help"])
        assert res.exit_code == 0 and "Usage" in res.output, cmd
        assert "--verbose" in res.output and "--quiet" in res.output, cmd
        res = runner.invoke(main, [cmd, "--version"])
        assert res.exit_code == 0 and __version__ in res.output, cmd
    res = runner.invoke(main, ["edges", "--help"])
    assert "--verbose" in res.output and "--quiet" in res.output and "--config" in res.output


def test_config_prints_commented_toml_that_loads_back(runner, tmp_path):
    res = runner.invoke(main, ["config"])
    assert res.exit_code == 0
    path = tmp_path / "c.toml"
    path.write_text(res.output)
    assert load_config(path) == Config()
    res = runner.invoke(main, ["config", "--preset", "tenth-mm-depth", "--set", "step.threshold=8"])
    assert "scale = 0.1" in res.output and "threshold = 8.0" in res.output


def test_edges_writes_maps_and_pictures_keeping_relative_paths(runner, images, tmp_path):
    out = tmp_path / "out"
    res = runner.invoke(main, ["edges", str(images), "-o", str(out), "-q"])
    assert res.exit_code == 0, res.output
    for rel in ("box", "sub/box2"):
        codes = np.load(out / f"{rel}.edges.npy")
        assert codes.dtype == np.uint8 and set(np.unique(codes)) <= {0, 1, 2}
        assert codes[20:44, 19:21].any()  # the box's left side
        for pic in ("step", "roof", "edges"):
            assert (out / f"{rel}.{pic}.png").exists()
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert manifest["images"]["box"]["status"] == "done"
    assert manifest["images"]["box"]["noise_sigma"] < 0.5  # noise-free box
    assert 0.5 < manifest["images"]["sub/box2"]["noise_sigma"] < 2.0  # noise sigma 1
    assert manifest["config"]["step"]["threshold"] == 6.0


def test_rerun_without_resume_or_overwrite_is_a_usage_error(runner, images, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["edges", str(images), "-o", str(out), "-q"]).exit_code == 0
    res = runner.invoke(main, ["edges", str(images), "-o", str(out), "-q"])
    assert res.exit_code == 2
    assert "--resume" in res.output and "--overwrite" in res.output
    assert runner.invoke(main, ["edges", str(images), "-o", str(out), "-q",
                                "--overwrite"]).exit_code == 0


@pytest.mark.parametrize("args, message", [
    (["--set", "step.sigma=0.1"], "[step] sigma = 0.1: expected a number >= 0.5 <= 10.0"),
    (["--set", "stepp.sigma=5"], "unknown table [stepp]"),
    (["--set", "step.taps=5"], "[step] taps is no longer a setting"),
    (["--set", "split.recut=false"], "[split] recut is now the entry 'recut' of refine.passes"),
    (["--set", "refine.passes=[\"nope\"]"], "[refine] passes = ['nope']: expected a list"),
    (["--set", "nonsense"], "expected TABLE.KEY=VALUE"),
    (["--preset", "cm"], "Invalid value for '--preset'"),
    (["--jobs", "0"], "Invalid value for '--jobs'"),
])
def test_usage_and_config_errors_exit_2_before_any_work(runner, images, tmp_path, args, message):
    out = tmp_path / "out"
    res = runner.invoke(main, ["edges", str(images), "-o", str(out), *args])
    assert res.exit_code == 2
    assert message in res.output
    assert not out.exists()


def test_config_file_errors_are_one_line(runner, images, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[roof]\ntruncation = 'left'\n")
    res = runner.invoke(main, ["edges", str(images), "-o", str(tmp_path / "o"), "--config", str(bad)])
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        f"Error: {bad}: [roof] truncation = 'left': expected one of 'symmetric', 'one-sided'"]


def test_missing_input_and_folder_without_images(runner, tmp_path):
    res = runner.invoke(main, ["edges", str(tmp_path / "nope"), "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "no such file or folder" in res.output
    (tmp_path / "empty").mkdir()
    res = runner.invoke(main, ["edges", str(tmp_path / "empty"), "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "no range images found" in res.output


def test_two_inputs_with_the_same_stem_are_refused(runner, tmp_path, write_png):
    for d in ("a", "b"):
        (tmp_path / d).mkdir()
        write_png(tmp_path / d / "x.png", box_scene(32).astype(np.uint8))
    res = runner.invoke(main, ["edges", str(tmp_path / "a" / "x.png"), str(tmp_path / "b" / "x.png"),
                               "-o", str(tmp_path / "o")])
    assert res.exit_code == 2 and "would both write" in res.output


def test_stage_command_without_earlier_stage_is_a_usage_error(runner, tmp_path):
    res = runner.invoke(main, ["link", str(tmp_path / "nothing")])
    assert res.exit_code == 2 and "run `rangeseg edges` first" in res.output


def test_library_modules_never_import_click_or_rich():
    import re
    from pathlib import Path

    import rangeseg_cli

    package = Path(rangeseg_cli.__file__).parent
    pattern = re.compile(r"^\s*(import|from)\s+(click|rich)\b", re.MULTILINE)
    modules = list(package.rglob("*.py"))
    assert len(modules) > 40  # the subpackages are searched too
    offenders = [str(p.relative_to(package)) for p in modules
                 if p.parent.name != "cli" and pattern.search(p.read_text())]
    assert offenders == []
