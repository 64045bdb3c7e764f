"""Camera intrinsics files (issue 32): three formats, told by content; bad files are one line."""

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from rangeseg_cli.cell.intrinsics import Intrinsics, read_intrinsics
from rangeseg_cli.cli.main import main
from rangeseg_cli.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]
FX, FY, CX, CY = 616.521545, 616.521606, 311.354492, 231.087402

ROS_CALIBRATION = f"""\
image_width: 640
image_height: 480
camera_name: sr300
camera_matrix:
  rows: 3
  cols: 3
  data: [{FX}, 0.0, {CX}, 0.0, {FY}, {CY}, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [0.0, 0.0, 0.0, 0.0, 0.0]
"""

ROS_ECHO = f"""\
header:
  seq: 12
  stamp:
    secs: 1600000000
    nsecs: 5
  frame_id: "camera_depth_optical_frame"
height: 480
width: 640
distortion_model: "plumb_bob"
D: [0.0, 0.0, 0.0, 0.0, 0.0]
K: [{FX}, 0.0, {CX}, 0.0, {FY}, {CY}, 0.0, 0.0, 1.0]
R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
P: [{FX}, 0.0, {CX}, 0.0, 0.0, {FY}, {CY}, 0.0, 0.0, 0.0, 1.0, 0.0]
binning_x: 0
binning_y: 0
---
"""

ROS2_ECHO = f"""\
height: 240
width: 320
k:
- {FX}
- 0.0
- {CX}
- 0.0
- {FY}
- {CY}
- 0.0
- 0.0
- 1.0
"""

OPEN3D = {"width": 1280, "height": 720,
          "intrinsic_matrix": [FX, 0.0, 0.0, 0.0, FY, 0.0, CX, CY, 1.0]}  # column-major


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_the_sr300_matrix_file_gives_its_focal_lengths_and_principal_point():
    got = read_intrinsics(str(ROOT / "sample_data" / "arc" / "suction-camera-intrinsics.txt"))
    assert (got.fx, got.fy, got.cx, got.cy) == (FX, FY, CX, CY)
    assert got.width is None and got.height is None


@pytest.mark.parametrize("text", [
    f"{FX} 0 {CX}\n0 {FY} {CY}\n0 0 1\n",
    f"{FX}, 0, {CX}\n0, {FY}, {CY}\n0, 0, 1\n",
    f"# K of the depth camera\n[[{FX} 0. {CX}]\n [0. {FY} {CY}]\n [0. 0. 1.]]\n",
    json.dumps([[FX, 0, CX], [0, FY, CY], [0, 0, 1]]),  # was "a 1x9 matrix"
    json.dumps([[FX, 0, CX], [0, FY, CY], [0, 0, 1]], indent=2),
])
def test_a_matrix_as_text_is_read_whitespace_comma_or_numpy_printed(tmp_path, text):
    got = read_intrinsics(write(tmp_path, "k.dat", text))
    assert got == Intrinsics(FX, FY, CX, CY, source=str(tmp_path / "k.dat"))


@pytest.mark.parametrize("text, size", [(ROS_CALIBRATION, (640, 480)), (ROS_ECHO, (640, 480)),
                                        (ROS2_ECHO, (320, 240))])
def test_ros_camera_info_yaml_in_its_three_forms(tmp_path, text, size):
    got = read_intrinsics(write(tmp_path, "camera.txt", text))  # told by content, not name
    assert (got.fx, got.fy, got.cx, got.cy) == (FX, FY, CX, CY)
    assert (got.width, got.height) == size


def test_open3d_json_is_column_major(tmp_path):
    got = read_intrinsics(write(tmp_path, "cam.json", json.dumps(OPEN3D)))
    assert (got.fx, got.fy, got.cx, got.cy) == (FX, FY, CX, CY)
    assert (got.width, got.height) == (1280, 720)


@pytest.mark.parametrize("name, text, size", [
    # pyrealsense2's stream intrinsics (rs2_intrinsics) as a user dumps them
    ("realsense.json", json.dumps({"width": 640, "height": 480, "ppx": CX, "ppy": CY, "fx": FX,
                                   "fy": FY, "model": "distortion.inverse_brown_conrady",
                                   "coeffs": [0.1, -0.2, 0.0, 0.0, 0.05]}), (640, 480)),
    ("camera.yaml", f"fx: {FX}\nfy: {FY}\ncx: {CX}\ncy: {CY}\n", None)])
def test_a_mapping_of_fx_fy_and_the_principal_point_realsense_names_too(tmp_path, name, text,
                                                                          size):
    got = read_intrinsics(write(tmp_path, name, text))
    assert (got.fx, got.fy, got.cx, got.cy) == (FX, FY, CX, CY)
    assert (got.width, got.height) == (size or (None, None))


def test_unknown_size_written_as_zero_or_minus_one_is_no_size(tmp_path):
    got = read_intrinsics(write(tmp_path, "o.json", json.dumps(OPEN3D | {"width": -1,
                                                                       "height": -1})))
    assert got.width is None and got.height is None


@pytest.mark.parametrize("text, message", [
    ("", "empty file"),
    (f"{FX} 0 {CX} 0\n0 {FY} {CY} 0\n0 0 1 0\n", "a 3x4 matrix; expected a 3x3 camera matrix"),
    (f"{FX} 0 {CX}\n0 {FY} {CY}\n", "a 2x3 matrix; expected a 3x3"),
    (f"0 0 {CX}\n0 {FY} {CY}\n0 0 1\n", "fx = 0, fy = 616.522: focal lengths must be > 0"),
    (f"-5 0 {CX}\n0 {FY} {CY}\n0 0 1\n", "focal lengths must be > 0"),
    (f"{FX} 0 {CX}\n0 abc {CY}\n0 0 1\n", "'abc' (row 2 of the matrix) is not a number"),
    (f"{FX} 0 {CX}\n0 {FY} {CY}\n0 0 2\n", "last row 0 0 2"),
    (f"{FX} 3 {CX}\n0 {FY} {CY}\n0 0 1\n", "skew 3"),
    (f"{FX} 0 nan\n0 {FY} {CY}\n0 0 1\n", "not a finite number"),
    ("image_width: 640\ncamera_name: x\n", "holds no camera matrix"),
    (f"fx: {FX}\nfy: {FY}\nppx: {CX}\n", "has fx or fy but no cy or ppy"),
    (f"fx: {FX}\nfy: {FY}\ncx: {CX}\ncy: [1, 2]\n", "cy holds [1, 2], not a number"),
    (f'{{"fx": 0, "fy": {FY}, "cx": {CX}, "cy": {CY}}}', "focal lengths must be > 0"),
    ('{"width": 640, "intrinsic_matrix": [1, 2, 3]}', "intrinsic_matrix must be a list of 9"),
    ("K: [1, 0, 1, 0, true, 1, 0, 0, 1]\n", "K holds True, not a number"),
    ("camera_matrix: {rows: 3, cols: 4, data: [1]}\n", "camera_matrix is 3x4"),
    ("just some words in a file\n", "not a camera intrinsics file"),
    (f"width: 640\nheight: 480\nK: [{FX},0,{CX},0,{FY},{CY},0,0,1\n",  # no closing bracket
     "has keys (width:) but reads as no YAML or JSON mapping (check its brackets"),
    (json.dumps([[FX, 0, CX, 0], [0, FY, CY, 0], [0, 0, 1, 0]]), "a 3x4 matrix"),
])
def test_bad_files_are_one_line_naming_the_file(tmp_path, text, message):
    path = write(tmp_path, "bad.txt", text)
    with pytest.raises(ConfigError, match="^" + str(path)) as info:
        read_intrinsics(path)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(ConfigError, match="nope.txt: intrinsics file not found"):
        read_intrinsics(str(tmp_path / "nope.txt"))
    (tmp_path / "k.png").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(ConfigError, match="k.png: not a text file; allowed: a 3x3"):
        read_intrinsics(str(tmp_path / "k.png"))


def config_output(*args):
    res = CliRunner().invoke(main, ["config", "--preset", "mm-depth", *args])
    return res.exit_code, res.output


def test_intrinsics_option_sets_the_input_keys_and_set_still_wins(tmp_path):
    path = write(tmp_path, "cam.yaml", ROS_CALIBRATION)
    code, out = config_output("--intrinsics", path)
    assert code == 0, out
    assert f"intrinsics = [{FX}, {FY}, {CX}, {CY}]" in out
    code, out = config_output("--intrinsics", path, "--set", "input.intrinsics=[500, 500, 320, 240]")
    assert code == 0 and "intrinsics = [500.0, 500.0, 320.0, 240.0]" in out


def test_intrinsics_option_comes_after_the_config_file(tmp_path):
    toml = tmp_path / "c.toml"
    toml.write_text("[input]\nintrinsics = [100.0, 100.0, 0.0, 0.0]\n")
    code, out = config_output("--config", str(toml), "--intrinsics",
                              write(tmp_path, "o.json", json.dumps(OPEN3D)))
    assert code == 0 and f"intrinsics = [{FX}, {FY}, {CX}, {CY}]" in out


@pytest.mark.parametrize("command", ["config", "run", "edges"])
def test_a_bad_intrinsics_file_is_exit_2_with_one_line(tmp_path, command, write_png):
    import numpy as np

    image = write_png(tmp_path / "a.png", np.full((20, 20), 500, np.uint16))
    bad = write(tmp_path, "k.txt", f"{FX} 0 {CX} 0\n0 {FY} {CY} 0\n0 0 1 0\n")
    args = [] if command == "config" else [str(image), "-o", str(tmp_path / "out")]
    res = CliRunner().invoke(main, [command, *args, "--preset", "mm-depth",
                                    "--intrinsics", bad])
    assert res.exit_code == 2
    assert res.output.strip().splitlines()[-1] == (
        f"Error: {bad}: a 3x4 matrix; expected a 3x3 camera matrix (fx 0 cx / 0 fy cy / 0 0 1)")
    assert not (tmp_path / "out").exists()


def test_intrinsics_on_a_height_map_is_the_config_error_of_fx(tmp_path):
    path = write(tmp_path, "k.txt", f"{FX} 0 {CX}\n0 {FY} {CY}\n0 0 1\n")
    res = CliRunner().invoke(main, ["config", "--intrinsics", path])
    assert res.exit_code == 2 and "larger_is_closer = true" in res.output


def test_help_says_intrinsics_come_before_set():
    res = CliRunner().invoke(main, ["run", "--help"])
    assert "--intrinsics" in res.output and "before --set" in res.output


@pytest.mark.parametrize("name", ["camera_info.yaml", "intrinsic.json",
                                  "realsense_intrinsics.json"])
def test_the_documented_example_files_are_the_sr300s_intrinsics(name):
    # README and docs/sensors.md point users at these: each format reads as the same camera
    from pathlib import Path

    got = read_intrinsics(str(Path(__file__).resolve().parent.parent / "docs" / "examples"
                              / name))
    assert (got.fx, got.fy, got.cx, got.cy) == pytest.approx((FX, FY, CX, CY))
    assert (got.width, got.height) == (640, 480)
