"""Tests of benchmarks/tradeoffs.py: its variants are what their names say; its table."""

from __future__ import annotations

import sys
import tomllib
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import tradeoffs  # noqa: E402

from rangeseg_cli.config import REFINE_PASSES, load_config, parse_settings  # noqa: E402


def test_each_set_variant_changes_the_one_refine_key_its_name_gives() -> None:
    defaults = load_config()
    sets = [name for name, _ in tradeoffs.VARIANTS if name.startswith("--set ")]
    assert sets == [f"--set {item}" for item in tradeoffs.SETS] and sets
    for name, overrides in tradeoffs.VARIANTS:
        if not name.startswith("--set "):
            continue
        key, value = name.removeprefix("--set refine.").split("=")
        assert overrides == {"refine": {key: tomllib.loads(f"v = {value}")["v"]}}
        config = tradeoffs.variant_config(None, overrides)
        assert (getattr(config.refine, key) == overrides["refine"][key]
                != getattr(defaults.refine, key))
        assert config.grow == defaults.grow and config.step == defaults.step
        assert config.refine.passes == defaults.refine.passes


def test_each_pass_is_left_out_alone_once() -> None:
    defaults = load_config()
    left_out = []
    for name, overrides in tradeoffs.VARIANTS:
        if not name.startswith("without "):
            continue
        config = tradeoffs.variant_config(None, overrides)
        gone = set(defaults.refine.passes) - set(config.refine.passes)
        alone = name.removeprefix("without ")
        # the bridge, which needs the fill, goes with it
        assert gone == ({alone, "bridge"} if alone == "fill" else {alone}), name
        assert config == load_config(overrides={"refine": {"passes": [
            p for p in REFINE_PASSES if p not in gone]}})
        # the name's --set item on the command line gives the same
        assert overrides == parse_settings([tradeoffs.without(alone)])
        left_out.append(alone)
    assert left_out == list(REFINE_PASSES)
    with pytest.raises(ValueError, match="'nope' is not a pass"):
        tradeoffs.without("nope")


def test_the_paper_variant_is_the_paper_preset_and_the_defaults_are_the_defaults() -> None:
    variants = dict(tradeoffs.VARIANTS)
    assert tradeoffs.variant_config(None, variants["--preset paper"]) == load_config(
        preset="paper")
    assert tradeoffs.variant_config(None, variants["defaults"]) == load_config()
    real = tradeoffs.variant_config(tradeoffs.REAL_CONFIG, variants["without facets"])
    assert real.step == load_config(tradeoffs.REAL_CONFIG).step
    assert real.input == load_config(tradeoffs.REAL_CONFIG).input and real.input.has_intrinsics
    assert "facets" not in real.refine.passes


def test_the_table_gives_each_variant_its_change_against_the_defaults() -> None:
    names = [name for name, _ in tradeoffs.VARIANTS]
    frames = ("a", "b")
    report = {
        "date": "today", "seeds": [0, 1], "repeats": 3,
        "median_ms": {n: {f: 10.0 + i for f in frames} for i, n in enumerate(names)},
        "correct": {n: {"0": 50 - i, "1": 40 + i, "2": 30, "gt_regions": 60}
                    for i, n in enumerate(names)},
    }
    lines = tradeoffs.markdown(report).splitlines()
    rows = {line.split(" | ")[0].removeprefix("| "): line for line in lines
            if line.startswith("| ") and not line.startswith("| variant")}
    assert list(rows) == names
    assert rows["defaults"].endswith("| 50 | 40 | 30 |")
    assert rows["without split"].endswith("| 49 (-1) | 41 (+1) | 30 (+0) |")
    assert "| 11 | 11 |" in rows["without split"]
    assert "correct σ = 0 (of 60)" in lines[2]


@pytest.mark.parametrize(("args", "named"), [
    (["--seeds", "1,x"], "'1,x'"), (["--scenes", "teapot"], "teapot"),
    (["--repeats", "0"], "--repeats 0"),
])
def test_a_bad_option_stops_before_any_run_with_one_line(
        args: list[str], named: str, capsys: pytest.CaptureFixture[str],
        monkeypatch: pytest.MonkeyPatch) -> None:
    def never(*_: object) -> None:
        raise AssertionError("ran before checking its options")

    monkeypatch.setattr(tradeoffs, "time_variants", never)
    monkeypatch.setattr(tradeoffs, "quality_variants", never)
    with pytest.raises(SystemExit) as stop:
        tradeoffs.main(args)
    assert stop.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert named in last and "allowed" in last
