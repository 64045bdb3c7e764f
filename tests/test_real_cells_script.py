"""Tests of benchmarks/real_cells.py: heights along the world's vertical, the summary."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import script_error

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import real_cells  # noqa: E402

from rangeseg_cli.synth.camera import (  # noqa: E402
    CAMERAS,
    Item,
    camera_for,
    render_items,
    support_plane,
)
from rangeseg_cli.synth.scenes import box, pose  # noqa: E402


@pytest.mark.parametrize("mount", [0.0, 30.0, 50.0])
def test_world_heights_are_heights_above_the_floor_however_the_camera_is_mounted(mount):
    cam = camera_for(CAMERAS["ideal"], (120, 160), height=700.0, tilt=(mount, 0.0))
    axis = cam.R[:, 2]
    yaw = math.degrees(math.atan2(axis[1], axis[0]))
    item = box(120.0, 90.0, 60.0, "item").moved(pose(0.0, 0.0, 0.0, yaw=yaw + 20))
    view = render_items(cam, [support_plane("table"), Item("item", (item,), True, "item")])
    camera = {"cx": cam.cx, "cy": cam.cy, "fx": cam.fx, "fy": cam.fy,
              "rotation": cam.R.tolist(), "position_mm": cam.t.tolist()}
    heights = real_cells.world_heights(view.depth, camera)
    names = {s["id"]: s["name"] for s in view.surfaces}
    faces = {name: heights[np.isin(view.gt, [i for i, n in names.items() if n == name])]
             for name in ("table", "item top")}
    assert all(v.size for v in faces.values())
    np.testing.assert_allclose(faces["table"], 0.0, atol=1e-6)
    np.testing.assert_allclose(faces["item top"], 60.0, atol=1e-6)


def test_the_summary_counts_uncovered_sites_and_heights_below_the_top():
    frames = [{"scene": "cam-pile", "ok": True, "tilt": 2.0, "uncovered": True,
               "height_mm": 90.0, "top_height_mm": 100.0},
              {"scene": "cam-pile", "ok": True, "tilt": 4.0, "uncovered": False,
               "height_mm": 40.0, "top_height_mm": 100.0},
              {"scene": "cam-pile", "ok": False, "reason": "no holdsite, but objects",
               "tilt": None, "uncovered": None, "height_mm": None, "top_height_mm": 100.0}]
    kinds = real_cells.summarise(frames, ["cam-pile"])["kinds"]
    assert kinds["cam-pile"]["usable"] == 2 and kinds["cam-pile"]["uncovered"] == 1
    assert kinds["all"]["below_top_median"] == 35.0  # the median of 10 and 60


@pytest.mark.parametrize(("argv", "named"), [
    (["--seeds", "abc"], "--seeds 'abc'"),
    (["--seeds", "5-2"], "--seeds '5-2'"),
    (["--seeds", "300-309,5-2"], "--seeds '300-309,5-2'"),
    (["--scenes", ","], "--scenes: unknown (none given)"),
    (["--size", "480"], "--size '480'"),
    (["--size", "8x8"], "--size '8x8'"),
    (["--jobs", "0"], "--jobs 0"),
    (["--set", "holdsite.size=7"], "--set: [holdsite] size"),
    (["--scenes", "cam-nothing"], "--scenes: unknown cam-nothing"),
])
def test_bad_options_are_one_line_errors_naming_the_option(argv, named, capsys):
    assert named in script_error(real_cells.main, argv, capsys)
