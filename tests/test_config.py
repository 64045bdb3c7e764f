import dataclasses
import math
import tomllib
from typing import Any

import pytest

from rangeseg_cli.config import (
    _TABLE_CLASSES,
    PRESETS,
    Config,
    default_toml,
    load_config,
    parse_settings,
)
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
                                          r"a number > 0.0 <= 1e\+12$"):
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
    assert parse_settings([" step . threshold = 8"]) == {"step": {"threshold": 8}}


def test_a_line_break_in_a_setting_is_refused_not_half_read():
    # TOML read the value "8\nroof.taps = 4" as 8 and a table it then dropped
    with pytest.raises(ConfigError, match="one TABLE.KEY=VALUE per --set, on one line"):
        parse_settings(["step.threshold=8\nroof.taps = 4"])


@pytest.mark.parametrize("items, named", [
    ("step.threshold=8", "got str"),
    ([3], "got 3"),
    (None, "got NoneType"),
])
def test_parse_settings_wants_a_list_of_strings(items, named):
    with pytest.raises(TypeError, match=named):
        parse_settings(items)


def test_overrides_must_be_a_dict_and_numpy_scalars_are_numbers():
    with pytest.raises(TypeError, match="`overrides` must be a dict of tables"):
        load_config(overrides=["step.threshold=8"])
    import numpy as np

    cfg = load_config(overrides={"step": {"taps": np.int64(7), "threshold": np.float32(6.5)},
                                 "split": {"enabled": np.bool_(False)}})
    assert (cfg.step.taps, cfg.step.threshold, cfg.split.enabled) == (7, 6.5, False)
    assert type(cfg.step.taps) is int and type(cfg.split.enabled) is bool
    with pytest.raises(ConfigError, match=r"\[step\] taps = 4: expected an integer >= 3"):
        load_config(overrides={"step": {"taps": np.int64(4)}})


@pytest.mark.parametrize("values, match", [
    # an integer too large for a float gave a 44-line OverflowError traceback (math.isnan)
    ({"link": {"min_component": 10 ** 400}},
     r"^\[link\] min_component = 1000000000.*<401 characters>: expected an integer >= 1 "
     r"<= 2147483647$"),
    ({"step": {"threshold": 10 ** 400}},
     r"^\[step\] threshold = 1000000000.*: expected a number > 0.0 <= 1e\+12 \(this integer "
     r"is beyond the floating-point range\)$"),
    ({"input": {"invalid": -10 ** 400}},
     r"^\[input\] invalid = -1000000000.*: expected a number \(this integer is beyond"),
    ({"link": {"min_component": 10 ** 5000}},
     r"^\[link\] min_component = <an integer of more than 4300 digits>: expected an integer"),
    # accepted, then numba failed on every image ("Int value is too large")
    ({"link": {"min_component": 10 ** 20}},
     r"^\[link\] min_component = 100000000000000000000: expected an integer >= 1 <= "
     r"2147483647$"),
    ({"split": {"min_piece": 2 ** 31}}, r"^\[split\] min_piece = 2147483648: expected an "),
])
def test_huge_integers_are_one_line_errors_not_overflows(values, match):
    with pytest.raises(ConfigError, match=match) as info:
        load_config(overrides=values)
    assert "\n" not in str(info.value)


def test_huge_integers_in_a_file_or_on_the_command_line_are_one_line_errors(tmp_path):
    path = tmp_path / "big.toml"
    path.write_text("[link]\nmin_component = 1" + "0" * 400 + "\n")
    with pytest.raises(ConfigError, match=r"big.toml: \[link\] min_component = 1000"):
        load_config(path)
    path.write_text("[link]\nmin_component = 1" + "0" * 5000 + "\n")  # tomllib: ValueError
    with pytest.raises(ConfigError, match=r"big.toml: not valid TOML \(Exceeds the limit"):
        load_config(path)
    overrides = parse_settings(["link.min_component=1" + "0" * 5000])
    with pytest.raises(ConfigError, match=r"^\[link\] min_component = '1000.*expected an "
                                          r"integer") as info:
        load_config(overrides=overrides)
    assert len(str(info.value)) < 200


@pytest.mark.parametrize("table, key, value, match", [
    # level = fit_factor x noise; level ** 2 overflowed in recut.py on every image
    ("split", "fit_factor", 1e155, r"expected a number > 0.0 <= 1000.0$"),
    ("split", "min_excess", 1e300, r"expected a number >= 0.0 <= 1000000.0$"),
    ("grow", "error_factor", 1e300, r"expected a number >= 1e-06 <= 1000000.0$"),
    ("grow", "min_error", 0.0, r"expected a number >= 1e-12 <= 1e\+24$"),
    ("holdsite", "max_ar_std", 1e200, r"expected a number >= 0.0 <= 1e\+12$"),
    ("input", "scale", 1e308, r"expected a number > 0.0 <= 1000000.0$"),
    # 180 / step angles: 0.001 took 50 s and 9.7 GB, 1e-300 never ended
    ("holdsite", "rotation_step", 0.001, r"expected a number >= 0.5 <= 90.0$"),
    ("holdsite", "rotation_step", 1e-300, r"expected a number >= 0.5 <= 90.0$"),
])
def test_numbers_beyond_a_keys_sane_range_are_refused(table, key, value, match):
    with pytest.raises(ConfigError, match=rf"^\[{table}\] {key} = .*: {match}"):
        load_config(overrides={table: {key: value}})


def _numeric_keys() -> list[tuple[str, Any]]:
    return [(table, f) for table, cls in _TABLE_CLASSES.items() for f in dataclasses.fields(cls)
            if isinstance(f.default, int | float | tuple) and not isinstance(f.default, bool)]


def test_every_numeric_key_has_a_finite_range():
    for table, f in _numeric_keys():
        if f.name == "invalid":  # any raw value (or NaN) may be the no-data value
            continue
        assert math.isfinite(f.metadata.get("max", math.inf)), f"[{table}] {f.name}"
        assert "min" in f.metadata or "min_excl" in f.metadata, f"[{table}] {f.name}"


def _at_limits() -> list[tuple[str, str, Any]]:
    cases = []
    for table, f in _numeric_keys():
        meta = f.metadata
        low = meta.get("min", meta.get("min_excl"))
        if "min_excl" in meta:
            low = 1 if isinstance(f.default, int) else math.nextafter(low, math.inf)
        for value in (low, meta.get("max")):
            if value is not None and f.name not in ("invalid", "size", "roi_box",
                                                    "roi_polygon"):
                cases.append((table, f.name, [value, value] if f.name == "footprint_mm"
                              else value))
    return cases


@pytest.mark.parametrize("table, key, value", _at_limits())
def test_pipeline_runs_with_any_key_at_the_end_of_its_range(table, key, value):
    # no overflow (warnings are errors here) nor internal error at any limit
    from rangeseg_cli.pipeline import run_pipeline
    from rangeseg_cli.synth import render_scene

    overrides: dict[str, dict[str, Any]] = {table: {key: value}}
    if table == "input" and key in ("fx", "fy", "cx", "cy"):
        focal = value if key in ("fx", "fy") and value else 500.0
        overrides["input"] = {"fx": focal, "fy": focal, "larger_is_closer": False,
                              **({key: value} if key in ("cx", "cy") else {})}
    if table == "holdsite" and key == "max_tilt":  # a tilt is tested with a lateral scale
        overrides["input"] = {"units_per_pixel": 2.0}
    if table == "holdsite" and key == "footprint_mm" and any(value):  # needs a camera
        overrides["input"] = {"fx": 500.0, "fy": 500.0, "larger_is_closer": False,
                              "metres_per_unit": 0.001}
    if table == "roof" and key == "threshold_b":
        overrides["roof"]["threshold_a"] = max(value, 6.0)
    if table == "roof" and key == "threshold_a":
        overrides["roof"]["threshold_b"] = min(value, 4.0)
    image = render_scene("part1", size=(64, 64), noise=2.0, seed=1).image
    result = run_pipeline(image, load_config(overrides=overrides))
    assert result.labels.shape == (64, 64)


def test_a_toml_file_with_a_byte_order_mark_is_read(tmp_path):
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf[step]\nthreshold = 7\n")
    assert load_config(path).step.threshold == 7


def test_a_key_above_every_table_says_so(tmp_path):
    path = tmp_path / "flat.toml"
    path.write_text("threshold = 8\n")
    with pytest.raises(ConfigError, match=r"key threshold = 8 is outside any table; put it "
                                          r"under its table, e\.g\. \[step\] threshold = 8"):
        load_config(path)


def test_every_table_counts_in_the_digest_of_some_stage():
    # a table added later to the config but to no stage would change no stage's digest
    from rangeseg_cli.config import _TABLE_CLASSES, STAGE_TABLES

    tables = [t for stage in STAGE_TABLES.values() for t in stage]
    assert sorted(tables) == sorted(_TABLE_CLASSES) and len(set(tables)) == len(tables)
    digests = load_config().stage_digests()
    changed = load_config(overrides={"holdsite": {"max_candidates": 3}}).stage_digests()
    assert [s for s in digests if digests[s] != changed[s]] == ["holdsite"]
