import math
import tomllib

import pytest

from rangeseg_cli.config import PRESETS, Config, default_toml, load_config, parse_settings
from rangeseg_cli.errors import ConfigError


def test_defaults_are_the_papers_parameters():
    c = load_config()
    assert (c.step.sigma, c.step.taps, c.step.threshold) == (1.0, 5, 6.0)
    assert (c.roof.sigma, c.roof.taps, c.roof.threshold_a, c.roof.threshold_b) == (4.0, 17, 6.0, 4.0)
    assert c.link.min_component == 20
    assert c.grow.error_factor == 10.0 and c.grow.passes == 1
    assert c.holdsite.size == (7, 7)
    assert c.roof.truncation == "symmetric"


def test_default_toml_loads_back_to_the_same_values(tmp_path):
    text = default_toml()
    assert all(line.startswith("#") for line in text.splitlines()
               if line and not line.startswith("[") and "=" not in line)
    path = tmp_path / "c.toml"
    path.write_text(text)
    assert load_config(path) == Config()


def test_every_key_has_a_comment():
    lines = default_toml().splitlines()
    for i, line in enumerate(lines):
        if "=" in line and not line.startswith("#"):
            assert lines[i - 1].startswith("# "), line


def test_toml_of_a_changed_config_round_trips(tmp_path):
    c = load_config(preset="tenth-mm-depth", overrides={"holdsite": {"size": [5, 9]},
                                                        "roof": {"truncation": "one-sided"}})
    path = tmp_path / "c.toml"
    path.write_text(default_toml(c))
    assert load_config(path) == c
    assert c.holdsite.size == (5, 9)


@pytest.mark.parametrize("values, match", [
    ({"step": {"treshold": 6}}, r"unknown key \[step\] treshold; allowed keys: sigma, taps, threshold"),
    ({"stepp": {}}, r"unknown table \[stepp\]"),
    ({"step": {"taps": 4}}, r"\[step\] taps = 4: expected an integer >= 3 <= 41 odd"),
    ({"step": {"taps": 5.0}}, r"\[step\] taps = 5.0: expected an integer"),
    ({"step": {"threshold": -1}}, r"\[step\] threshold = -1: expected a number > 0.0"),
    ({"step": {"threshold": "6"}}, r"\[step\] threshold = '6'"),
    ({"input": {"larger_is_closer": 1}}, r"\[input\] larger_is_closer = 1: expected true or false"),
    ({"roof": {"truncation": "left"}}, r"\[roof\] truncation = 'left': expected one of 'symmetric', 'one-sided'"),
    ({"holdsite": {"size": [7]}}, r"\[holdsite\] size = \[7\]: expected a list of two integers"),
    ({"holdsite": {"size": [6, 7]}}, r"\[holdsite\] size"),
    ({"roof": {"threshold_a": 3}}, r"\[roof\] threshold_b = 4.0: must be <= threshold_a"),
])
def test_bad_values_name_table_key_value_and_what_is_allowed(values, match):
    with pytest.raises(ConfigError, match=match):
        load_config(overrides=values)


def test_bad_toml_file_is_one_line_error_naming_the_file(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text("[step\nthreshold = 6")
    with pytest.raises(ConfigError, match=r"bad.toml: not valid TOML") as info:
        load_config(path)
    assert "\n" not in str(info.value)
    with pytest.raises(ConfigError, match="config file not found"):
        load_config(tmp_path / "missing.toml")


def test_presets_set_depth_camera_input():
    c = load_config(preset="mm-depth")
    assert c.input.larger_is_closer is False and c.input.invalid == 0.0
    assert set(PRESETS) >= {"mm-depth", "tenth-mm-depth", "metre-depth"}
    with pytest.raises(ConfigError, match="unknown preset 'cm'"):
        load_config(preset="cm")


def test_nan_invalid_survives_toml():
    c = Config()
    assert math.isnan(c.input.invalid)
    assert tomllib.loads(default_toml())["input"]["invalid"] != 0


def test_digest_changes_with_config():
    assert Config().digest() != load_config(overrides={"step": {"threshold": 7}}).digest()
    assert Config().digest() == load_config().digest()


def test_bad_value_in_a_file_names_the_file_and_not_for_command_line_values(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text("[step]\nthreshold = \"8\"\n")
    with pytest.raises(ConfigError, match=r"^.*cell.toml: \[step\] threshold = '8': expected "
                                          r"a number > 0.0$"):
        load_config(path)
    path.write_text("[step]\nthreshold = 8\n")
    with pytest.raises(ConfigError, match=r"^\[step\] taps = 4: expected an integer"):
        load_config(path, overrides={"step": {"taps": 4}})


def test_file_value_fixed_by_an_override_is_accepted(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text("[roof]\nthreshold_b = 7.0\n")  # above the default threshold_a alone
    assert load_config(path, overrides={"roof": {"threshold_a": 8.0}}).roof.threshold_b == 7.0


@pytest.mark.parametrize("table", ["step", "roof"])
def test_gaussian_narrower_than_half_a_pixel_is_refused(table):
    # sigma 1e-300 gave NaN weights (a RuntimeWarning and no edges at all)
    with pytest.raises(ConfigError, match=rf"\[{table}\] sigma = 1e-300: expected a number "
                                          r">= 0.5"):
        load_config(overrides={table: {"sigma": 1e-300}})


def test_one_focal_length_without_the_other_is_refused():
    # fx alone was accepted and the camera-frame output silently left out
    with pytest.raises(ConfigError, match=r"\[input\] fx = 500.0, fy = 0.0: camera intrinsics "
                                          "need both focal lengths"):
        load_config(overrides={"input": {"fx": 500.0}})
    depth = {"fx": 500.0, "fy": 500.0, "larger_is_closer": False}
    assert load_config(overrides={"input": depth}).input.has_intrinsics


def test_intrinsics_on_a_height_map_are_refused() -> None:
    # a height map has no depth along the optical axis: the camera point used to be left out silently
    with pytest.raises(ConfigError, match=r"\[input\] fx = 500.0, larger_is_closer = true: camera "
                                          r"intrinsics need depth"):
        load_config(overrides={"input": {"fx": 500.0, "fy": 500.0}})
    assert load_config(preset="mm-depth",
                       overrides={"input": {"fx": 500.0, "fy": 500.0}}).input.has_intrinsics


def test_parse_settings_reads_values_as_toml_and_bare_words_as_strings():
    got = parse_settings(["step.threshold=8", " roof.truncation = one-sided",
                          "holdsite.size=[21, 21]", "split.recut=false"])
    assert got == {"step": {"threshold": 8}, "roof": {"truncation": "one-sided"},
                   "holdsite": {"size": [21, 21]}, "split": {"recut": False}}
    assert load_config(overrides=got).roof.truncation == "one-sided"
    for bad in ("step.threshold", "threshold=8", ".threshold=8", "step.=8"):
        with pytest.raises(ConfigError, match=f"{bad!r}: expected TABLE.KEY=VALUE"):
            parse_settings([bad])
