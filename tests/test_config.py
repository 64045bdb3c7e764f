import dataclasses
import math
import tomllib
from typing import Any

import numpy as np
import pytest

from conftest import bad_setting_on_the_command_line, passes_without
from rangeseg_cli import config as config_module
from rangeseg_cli.config import (
    _TABLE_CLASSES,
    PRESETS,
    REFINE_PASSES,
    TUNING,
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
    assert c.refine.passes == REFINE_PASSES and load_config(preset="paper").refine.passes == ()


@pytest.mark.parametrize(("sigma", "taps"), [(0.5, 3), (1.0, 5), (1.25, 7), (4.0, 17),
                                             (10.0, 41), (20.0, 81)])
def test_the_gaussian_masks_length_follows_sigma(sigma, taps):
    # [step] taps and [roof] taps were keys; 2 ceil(2 sigma) + 1 gives the defaults 5 and 17
    assert load_config(overrides={"roof": {"sigma": sigma}}).roof.taps == taps
    if sigma <= 10.0:
        assert load_config(overrides={"step": {"sigma": sigma}}).step.taps == taps


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
    ({"step": {"treshold": 6}}, r"unknown key \[step\] treshold; allowed keys: sigma, threshold$"),
    ({"stepp": {}}, r"unknown table \[stepp\]"),
    ({"link": {"min_component": 5.0}}, r"\[link\] min_component = 5.0: expected an integer"),
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


#: The 30 keys of the old [split] table (before [refine]): what each became.
OLD_SPLIT_KEYS = {
    **{old: ("refine.passes", repr(new)) for old, new in [
        ("enabled", "split"), ("recover", "recover"), ("fill_edges", "fill"),
        ("merge", "merge"), ("recut", "recut"), ("bridge", "bridge"),
        ("chamfers", "chamfers"), ("carve", "carve"), ("facets", "facets"),
        ("refine", "boundaries"), ("merge_planes", "merge_planes"),
        ("join_occluded", "join_occluded")]},
    **{old: (f"refine.{new}",) for old, new in [
        ("fit_factor", "fit_factor"), ("normal_sigma", "normal_sigma"),
        ("min_crease", "min_crease"), ("crease_evidence", "crease_evidence"),
        ("min_piece", "min_region"), ("refine_smoothness", "smoothness"),
        ("recover_max_noise", "max_noise")]},
    **{old: ("no longer a setting",) for old in [
        "min_gain", "min_excess", "max_pieces", "crease_pieces", "trim_pieces", "trim_faces",
        "plane_cut", "rounds", "recover_passes", "refine_passes", "refine_creases"]},
}

#: Every key that moved or went: (table, key, a value it took, what its message names).
OLD_KEYS = [
    *(("split", key, getattr(TUNING, key, False), named) for key, named in OLD_SPLIT_KEYS.items()),
    *(("input", key, 500.0, ("input.intrinsics",)) for key in ("fx", "fy", "cx", "cy")),
    ("step", "taps", 5, ("no longer a setting", "sigma")),
    ("roof", "taps", 17, ("no longer a setting", "sigma")),
    ("holdsite", "pose", "local", ("no longer a setting",)),
    ("output", "float_digits", 6, ("no longer a setting",)),
    ("holdsite", "units_per_pixel", 2.0, ("input.units_per_pixel",)),
]


def test_the_old_split_table_had_thirty_keys_and_each_has_a_fate():
    assert len(OLD_SPLIT_KEYS) == 30
    # the switches became refine.passes; the other keys, SplitConfig's fields
    switches = set(config_module.PASS_SWITCHES.values())
    assert {f.name for f in dataclasses.fields(config_module.SplitConfig)} == set(
        OLD_SPLIT_KEYS) - switches
    assert {(t, k) for t, k, _, _ in OLD_KEYS} == set(config_module.MOVED_KEYS)


@pytest.mark.parametrize("table, key, value, named", OLD_KEYS,
                         ids=[f"{t}.{k}" for t, k, _, _ in OLD_KEYS])
def test_an_old_key_is_refused_naming_the_new_one(tmp_path, table, key, value, named):
    with pytest.raises(ConfigError, match=rf"\[{table}\] {key} ") as info:
        load_config(overrides={table: {key: value}})
    message = str(info.value)
    assert "\n" not in message and all(n in message for n in named), message
    # among valid keys of its table (or of [refine]) it is still refused
    others = {"refine": {"fit_factor": 1.5}, table: {key: value}}
    with pytest.raises(ConfigError, match=rf"\[{table}\] {key} "):
        load_config(overrides=others)
    # in a file, named with the file
    path = tmp_path / "old.toml"
    path.write_text(f"[{table}]\n{key} = {tomllib_value(value)}\n")
    with pytest.raises(ConfigError, match=rf"old.toml: \[{table}\] {key} "):
        load_config(path)
    # on the command line: one line, no traceback
    last = bad_setting_on_the_command_line(tmp_path, f"{table}.{key}={tomllib_value(value)}")
    assert f"[{table}] {key} " in last and all(n in last for n in named), last


def tomllib_value(value: Any) -> str:
    """``value`` as TOML writes it (true, 1.25, "local")."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return f'"{value}"' if isinstance(value, str) else repr(value)


def test_an_unknown_key_of_the_old_split_table_says_it_is_now_refine():
    with pytest.raises(ConfigError, match=r"the table \[split\] is now \[refine\]; allowed "
                                          r"tables: .*refine"):
        load_config(overrides={"split": {"enable": True}})


@pytest.mark.parametrize("values, match", [
    ({"passes": ["nope"]}, r"\[refine\] passes = \['nope'\]: expected a list of distinct names "
                           r"among 'split', 'recover', 'fill'"),
    ({"passes": ["fill", "fill"]}, r"\[refine\] passes = \['fill', 'fill'\]: expected a list "
                                   r"of distinct names"),
    ({"passes": "fill"}, r"\[refine\] passes = 'fill': expected a list of distinct names"),
    ({"passes": [1]}, r"\[refine\] passes = \[1\]: expected a list"),
    ({"passes": ["Fill"]}, r"\[refine\] passes = \['Fill'\]"),
    ({"enabled": False}, r"unknown key \[refine\] enabled; allowed keys: passes, fit_factor, "
                         r"min_crease, crease_evidence, min_region, normal_sigma, smoothness, "
                         r"max_noise$"),
    ({"fit_factor": 0}, r"\[refine\] fit_factor = 0: expected a number > 0.0 <= 1000.0$"),
    ({"min_crease": 91}, r"\[refine\] min_crease = 91: expected a number >= 0.0 <= 90.0$"),
    ({"crease_evidence": -1.0}, r"\[refine\] crease_evidence = -1.0: expected a number >= 0.0"),
    ({"min_region": 0}, r"\[refine\] min_region = 0: expected an integer >= 1"),
    ({"min_region": 20.5}, r"\[refine\] min_region = 20.5: expected an integer"),
    ({"normal_sigma": 0.0}, r"\[refine\] normal_sigma = 0.0: expected a number > 0.0 <= 20.0$"),
    ({"smoothness": -1.0}, r"\[refine\] smoothness = -1.0: expected a number >= 0.0"),
    ({"max_noise": -0.5}, r"\[refine\] max_noise = -0.5: expected a number >= 0.0"),
    ({"max_noise": "2"}, r"\[refine\] max_noise = '2': expected a number"),
])
def test_bad_refine_values_are_refused(values, match):
    with pytest.raises(ConfigError, match=match):
        load_config(overrides={"refine": values})


def test_bad_refine_values_on_the_command_line_are_one_line_errors(tmp_path):
    last = bad_setting_on_the_command_line(tmp_path, 'refine.passes=["fill", "nope"]')
    assert "[refine] passes = ['fill', 'nope']: expected a list of distinct names" in last
    assert "[refine] min_region = 0" in bad_setting_on_the_command_line(tmp_path,
                                                                        "refine.min_region=0")


def test_refine_passes_run_in_their_own_order_whatever_the_order_given():
    given = ["join_occluded", "fill", "split"]
    config = load_config(overrides={"refine": {"passes": given}})
    assert config.refine.passes == ("split", "fill", "join_occluded")
    assert config == load_config(overrides={"refine": {"passes": sorted(given)}})
    assert load_config(overrides={"refine": {"passes": []}}).refine.passes == ()


def test_config_split_derives_the_passes_settings_from_refine_and_the_constants():
    assert Config().split == TUNING  # the defaults: the keys at their defaults
    # which passes run is read from [refine] passes alone: Config.split holds no switch
    # every pass but the one added after the [split] table was retired replaced a switch
    assert set(config_module.PASS_SWITCHES) == set(REFINE_PASSES) - {"leftovers"}
    assert load_config(preset="paper").split == TUNING == passes_without("split").split
    keys = {"fit_factor": ("fit_factor", 1.5), "min_crease": ("min_crease", 20.0),
            "crease_evidence": ("crease_evidence", 0.0), "min_region": ("min_piece", 30),
            "normal_sigma": ("normal_sigma", 3.0), "smoothness": ("refine_smoothness", 2.0),
            "max_noise": ("recover_max_noise", 1.0)}
    assert set(keys) | {"passes"} == {f.name for f in dataclasses.fields(config_module.RefineConfig)}
    for key, (field, value) in keys.items():
        split = load_config(overrides={"refine": {key: value}}).split
        assert getattr(split, field) == value
        assert dataclasses.replace(split, **{field: getattr(TUNING, field)}) == TUNING


def test_config_split_reads_the_constants_when_it_is_read(tuning):
    config = passes_without("facets")
    assert config.split.trim_faces is True and config.split.max_pieces == 8
    tuning(trim_faces=False, max_pieces=3)
    assert config.split.trim_faces is False and config.split.max_pieces == 3
    assert "facets" not in config.refine.passes  # [refine] still says
    tuning()
    assert config.split.trim_faces is True and config.split.max_pieces == 8


def test_the_old_split_table_cannot_be_given_to_config():
    with pytest.raises(TypeError, match="split"):
        Config(split=TUNING)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="split"):
        dataclasses.replace(Config(), split=TUNING)  # type: ignore[call-arg]


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
    with pytest.raises(ConfigError, match=r"^\[step\] sigma = 0.1: expected a number >= 0.5"):
        load_config(path, overrides={"step": {"sigma": 0.1}})


def test_file_value_fixed_by_an_override_is_accepted(tmp_path):
    path = tmp_path / "cell.toml"
    path.write_text("[roof]\nthreshold_b = 7.0\n")  # above the default threshold_a alone
    assert load_config(path, overrides={"roof": {"threshold_a": 8.0}}).roof.threshold_b == 7.0


@pytest.mark.parametrize("table, entries, message", [
    ("workspace", {"min_height": 10.0, "max_height": 5.0},
     "[workspace] min_height = 10.0: must be below max_height (5.0)"),
    ("workspace", {"roi_box": [10, 10, 5, 5]}, "[workspace] roi_box = [10, 10, 5, 5]: "),
    ("input", {"intrinsics": [-616.0, 616.0, 311.0, 231.0]},
     "[input] intrinsics = [-616.0, 616.0, 311.0, 231.0]: camera intrinsics need"),
])
def test_keys_of_a_file_that_clash_name_the_file_and_not_for_command_line_values(
        tmp_path, table, entries, message):
    path = tmp_path / "cell.toml"
    path.write_text(f"[{table}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items()))
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert str(info.value).startswith(f"{path}: {message}")
    path.write_text("")
    with pytest.raises(ConfigError) as info:
        load_config(path, overrides={table: entries})
    assert str(info.value).startswith(message)


@pytest.mark.parametrize("table", ["step", "roof"])
def test_gaussian_narrower_than_half_a_pixel_is_refused(table):
    # sigma 1e-300 gave NaN weights (a RuntimeWarning and no edges at all)
    with pytest.raises(ConfigError, match=rf"\[{table}\] sigma = 1e-300: expected a number "
                                          r">= 0.5"):
        load_config(overrides={table: {"sigma": 1e-300}})


def test_one_focal_length_without_the_other_is_refused():
    # fx alone was accepted and the camera-frame output silently left out
    with pytest.raises(ConfigError, match=r"\[input\] intrinsics = \[500.0, 0.0, 0.0, 0.0\]: "
                                          "camera intrinsics need both focal lengths"):
        load_config(overrides={"input": {"intrinsics": [500.0, 0.0, 0.0, 0.0]}})
    with pytest.raises(ConfigError, match=r"\[input\] intrinsics = \[-500.0, -500.0, 0.0, 0.0\]: "
                                          "camera intrinsics need both focal lengths fx, fy > 0"):
        load_config(overrides={"input": {"intrinsics": [-500.0, -500.0, 0.0, 0.0]}})
    depth = {"intrinsics": [500.0, 400.0, 31.5, 32.5], "larger_is_closer": False}
    camera = load_config(overrides={"input": depth}).input
    assert camera.has_intrinsics and camera.intrinsics == (500.0, 400.0, 31.5, 32.5)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (500.0, 400.0, 31.5, 32.5)


@pytest.mark.parametrize("value, match", [
    ([500.0, 500.0, 32.0], r"expected a list of 4 numbers >="),
    ([500.0, 500.0, 32.0, 32.0, 1.0], r"expected a list of 4 numbers"),
    (500.0, r"expected a list of 4 numbers"),
    ([500.0, 500.0, 32.0, "32"], r"expected a list of 4 numbers"),
    ([2e6, 2e6, 0.0, 0.0], r"expected a list of 4 numbers >= -1000000.0 <= 1000000.0$"),
])
def test_intrinsics_are_a_list_of_four_numbers(value, match):
    with pytest.raises(ConfigError, match=r"^\[input\] intrinsics = .*: " + match):
        load_config(preset="mm-depth", overrides={"input": {"intrinsics": value}})


def test_intrinsics_on_a_height_map_are_refused() -> None:
    # a height map has no depth along the optical axis: the camera point used to be left out silently
    camera = {"intrinsics": [500.0, 500.0, 0.0, 0.0]}
    with pytest.raises(ConfigError, match=r"\[input\] intrinsics = \[500.0, 500.0, 0.0, 0.0\], "
                                          r"larger_is_closer = true: camera intrinsics need depth"):
        load_config(overrides={"input": camera})
    assert load_config(preset="mm-depth", overrides={"input": camera}).input.has_intrinsics


def test_parse_settings_reads_values_as_toml_and_bare_words_as_strings():
    got = parse_settings(["step.threshold=8", " roof.truncation = one-sided",
                          "holdsite.size=[21, 21]", 'refine.passes=["recut", "split"]'])
    assert got == {"step": {"threshold": 8}, "roof": {"truncation": "one-sided"},
                   "holdsite": {"size": [21, 21]}, "refine": {"passes": ["recut", "split"]}}
    config = load_config(overrides=got)
    assert config.roof.truncation == "one-sided" and config.refine.passes == ("split", "recut")
    for bad in ("step.threshold", "threshold=8", ".threshold=8", "step.=8"):
        with pytest.raises(ConfigError, match=f"{bad!r}: expected TABLE.KEY=VALUE"):
            parse_settings([bad])
    assert parse_settings([" step . threshold = 8"]) == {"step": {"threshold": 8}}


def test_a_line_break_in_a_setting_is_refused_not_half_read():
    # TOML read the value "8\nroof.sigma = 2" as 8 and a table it then dropped
    with pytest.raises(ConfigError, match="one TABLE.KEY=VALUE per --set, on one line"):
        parse_settings(["step.threshold=8\nroof.sigma = 2"])


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

    cfg = load_config(overrides={"refine": {"min_region": np.int64(7)},
                                 "step": {"threshold": np.float32(6.5)},
                                 "output": {"png": np.bool_(False)}})
    assert (cfg.refine.min_region, cfg.step.threshold, cfg.output.png) == (7, 6.5, False)
    assert type(cfg.refine.min_region) is int and type(cfg.output.png) is bool
    with pytest.raises(ConfigError, match=r"\[refine\] min_region = 0: expected an integer >= 1"):
        load_config(overrides={"refine": {"min_region": np.int64(0)}})


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
    ({"refine": {"min_region": 2 ** 31}}, r"^\[refine\] min_region = 2147483648: expected an "),
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
    ("refine", "fit_factor", 1e155, r"expected a number > 0.0 <= 1000.0$"),
    ("refine", "crease_evidence", 1e300, r"expected a number >= 0.0 <= 1000000.0$"),
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
            if isinstance(f.default, int | float | tuple) and not isinstance(f.default, bool)
            and "names" not in f.metadata]  # [refine] passes: a list of names


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
        if f.name == "intrinsics":  # focal lengths > 0, any principal point
            cases += [(table, f.name, [meta["max"], meta["max"], 0.0, 0.0]),
                      (table, f.name, [500.0, 500.0, low, meta["max"]]),
                      (table, f.name, [500.0, 500.0, meta["max"], low])]
            continue
        for value in (low, meta.get("max")):
            if value is not None and f.name not in ("invalid", "size", "roi_box",
                                                    "roi_polygon"):
                cases.append((table, f.name, [value, value] if f.name == "footprint_mm"
                              else value))
    return cases


def _varied_scene() -> np.ndarray:
    """A 64 x 64 8-bit image with something for every stage: a table, a box whose top
    meets a chamfer at a crease, a lying half cylinder (curved), steps between them;
    sigma 2 (the noise estimate and the passes that use it)."""
    y, x = np.mgrid[0:64, 0:64].astype(np.float64)
    z = 30.0 + 0.1 * x + 0.05 * y
    box = (y >= 6) & (y < 30) & (x >= 6) & (x < 40)
    z[box] = (110.0 + 0.2 * x - 2.5 * np.clip(x - 28.0, 0.0, None))[box]  # a crease at 28
    u = y - 46.0
    cylinder = (np.abs(u) < 12.0) & (x >= 10) & (x < 58)
    z[cylinder] = 60.0 + 3.0 * np.sqrt(np.maximum(144.0 - u * u, 0.0))[cylinder]
    z += np.random.default_rng(1).normal(0.0, 2.0, z.shape)
    return np.clip(np.round(z), 0, 255).astype(np.uint8)


def test_the_varied_scene_gives_the_refinement_work():
    # the limits below are run on it: noisy, four surfaces, labels the refinement changes
    from rangeseg_cli.pipeline import run_pipeline

    result = run_pipeline(_varied_scene())
    assert result.noise_sigma == pytest.approx(2.0, rel=0.25)
    assert len(result.surfaces) >= 4
    paper = run_pipeline(_varied_scene(), load_config(preset="paper"))
    assert not np.array_equal(result.labels, paper.labels)


@pytest.mark.parametrize("table, key, value", _at_limits())
def test_pipeline_runs_with_any_key_at_the_end_of_its_range(table, key, value):
    # no overflow (warnings are errors here) nor internal error at any limit
    from rangeseg_cli.pipeline import run_pipeline

    overrides: dict[str, dict[str, Any]] = {table: {key: value}}
    if table == "input" and key == "intrinsics":
        overrides["input"]["larger_is_closer"] = False
    if table == "holdsite" and key == "max_tilt":  # a tilt is tested with a lateral scale
        overrides["input"] = {"units_per_pixel": 2.0}
    if table == "holdsite" and key == "footprint_mm" and any(value):  # needs a camera
        overrides["input"] = {"intrinsics": [500.0, 500.0, 0.0, 0.0], "larger_is_closer": False,
                              "metres_per_unit": 0.001}
    if table == "roof" and key == "threshold_b":
        overrides["roof"]["threshold_a"] = max(value, 6.0)
    if table == "roof" and key == "threshold_a":
        overrides["roof"]["threshold_b"] = min(value, 4.0)
    result = run_pipeline(_varied_scene(), load_config(overrides=overrides))
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


def test_the_point_clouds_count_from_the_grow_stage_on():
    # `grow OUT --ply` after a run without: the edges and links stay current
    plain, ply = load_config(), load_config(overrides={"output": {"ply": True}})
    before, after = plain.stage_digests(), ply.stage_digests()
    assert before["edges"] == after["edges"] and before["link"] == after["link"]
    assert before["grow"] != after["grow"] and before["holdsite"] != after["holdsite"]
    assert plain.digest() != ply.digest()


def test_intrinsics_are_four_numbers_not_an_empty_list():
    with pytest.raises(ConfigError, match=r"^\[input\] intrinsics = \[\]: expected a list of 4 "
                       r"numbers >="):
        load_config(overrides={"input": {"intrinsics": []}})
