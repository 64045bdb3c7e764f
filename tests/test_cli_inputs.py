"""Inputs a newcomer's folders hold (issue 34): link loops, names like outputs, files that
are not what their names say, names that are not UTF-8, filters; a manifest checked field by
field, and ``--json`` that always prints an object. Each ends in one clear line."""

import json

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import box_scene
from rangeseg_cli.cli import main


@pytest.fixture
def runner():
    return CliRunner()


@pytest.fixture
def box_png(tmp_path, write_png):
    return write_png(tmp_path / "box.png", box_scene(48).astype(np.uint8))


def no_traceback(res) -> None:
    assert "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)


# --------------------------------------------------------------------------- manifest (6)


@pytest.mark.parametrize("damage, problem", [
    (lambda m: m | {"images": {"box": m["images"]["box"] | {"status": "bogus"}}},
     "\"images\" entry 'box': \"status\" is \"bogus\"; allowed: \"done\", \"failed\", "
     "\"running\""),
    (lambda m: m | {"images": {"box": {}}},
     "\"images\" entry 'box': \"status\" is missing; allowed: \"done\", \"failed\", "
     "\"running\""),
    (lambda m: {k: v for k, v in m.items() if k != "config"},
     '"config" is missing; rangeseg writes it in every manifest'),
    (lambda m: {k: v for k, v in m.items() if k != "images"},
     '"images" is missing; rangeseg writes it in every manifest'),
])
def test_a_manifest_with_a_bad_status_or_no_config_stops_with_one_line(runner, box_png,
                                                                         tmp_path, damage,
                                                                         problem):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    path = out / "rangeseg-run.json"
    path.write_text(json.dumps(damage(json.loads(path.read_text()))))
    before = path.read_bytes()
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "--resume", "-j", "1"])
    no_traceback(res)
    assert res.exit_code == 2
    assert res.output.strip().splitlines()[-1] == (
        f"Error: {path}: not a manifest of rangeseg ({problem}); repair it, or delete it and "
        "redo the images with --overwrite")
    assert path.read_bytes() == before
