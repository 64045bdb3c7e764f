"""The library's front door: stage functions and run_pipeline check what they are given.

A user importing ``rangeseg_cli`` gets a one-line ``ValueError``/``ConfigError``/
``InputError`` naming the argument, never an internal exception or gigabytes
asked for by one label (a black-box audit of the API found each case below).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from conftest import box_scene
from rangeseg_cli.config import (
    Config,
    HoldsiteConfig,
    LinkConfig,
    RoofConfig,
    StepConfig,
    check_config,
    load_config,
)
from rangeseg_cli.errors import ConfigError, InputError
from rangeseg_cli.pipeline import run_pipeline, stage_edges, stage_grow, stage_link
from rangeseg_cli.stages.holdsite import find_holdsite
from rangeseg_cli.stages.surfaces import describe_surfaces

CFG = load_config()


@pytest.fixture(scope="module")
def staged() -> dict[str, np.ndarray]:
    z = box_scene(48).astype(np.float64)
    edges = stage_edges(z, CFG).codes
    codes, components = stage_link(z, edges, CFG)
    labels, _ = stage_grow(z, codes, components, CFG)
    return {"z": z, "codes": codes, "components": components, "labels": labels}


@pytest.mark.parametrize("config, named", [
    (Config(step=StepConfig(threshold=math.nan)), "[step] threshold = nan"),
    (Config(roof=RoofConfig(truncation="one-side")), "[roof] truncation = 'one-side'"),
    (Config(link=LinkConfig(min_component=0)), "[link] min_component = 0"),
    (Config(holdsite=HoldsiteConfig(size=(0, 0))), "[holdsite] size"),
    (Config(holdsite=HoldsiteConfig(size=(9, 3), rotation_step=0.0)),
     "[holdsite] rotation_step = 0"),
    (replace(CFG, roof=replace(CFG.roof, threshold_b=CFG.roof.threshold_a + 1)),
     "threshold_b"),
])
def test_a_config_built_by_hand_is_checked_as_load_config_checks_it(config, named) -> None:
    with pytest.raises(ConfigError) as err:
        run_pipeline(box_scene(32), config)
    assert named in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ConfigError):
        check_config(config)


def test_a_table_of_the_wrong_class_is_a_type_error() -> None:
    with pytest.raises(TypeError, match="config.step must be a StepConfig"):
        run_pipeline(box_scene(32), Config(step="x"))  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="must be a rangeseg_cli.config.Config"):
        run_pipeline(box_scene(32), {"step": {}})  # type: ignore[arg-type]
    check_config(CFG)  # the defaults pass


@pytest.mark.parametrize("stages", [0, -1, 5, 2.5, math.nan, True, "4", None])
def test_stages_must_be_an_integer_from_1_to_4(stages) -> None:
    with pytest.raises(ValueError, match="`stages`"):
        run_pipeline(box_scene(32), stages=stages)


def test_every_stage_count_from_1_to_4_runs() -> None:
    for k in range(1, 5):
        result = run_pipeline(box_scene(32), stages=k)
        assert (result.holdsite is not None) == (k == 4)


def test_a_huge_label_is_refused_before_any_table_is_sized(staged) -> None:
    z, labels = staged["z"], staged["labels"].copy()
    labels[0, 0] = 2**31 - 1  # a legal int32: 16 GB of tables if believed
    with pytest.raises(ValueError, match=r"`labels` holds 2147483647: labels .* 0\.\.2304"):
        describe_surfaces(z, labels, CFG)
    big = np.where(staged["labels"] == 1, 1, 2**32).astype(np.int64)
    with pytest.raises(InputError, match=r"`labels` holds 4294967296"):
        find_holdsite(z, big, [], CFG)
    components = staged["components"].copy()
    components[0, 0] = 2**31 - 1
    with pytest.raises(ValueError, match="`components` holds 2147483647"):
        stage_grow(z, staged["codes"], components, CFG)


def test_negative_labels_are_refused(staged) -> None:
    z = staged["z"]
    with pytest.raises(ValueError, match="`labels` holds -1"):
        describe_surfaces(z, -np.ones(z.shape, np.int32), CFG)
    with pytest.raises(InputError, match=r"`labels` holds -\d+: labels \(at most the pixel "
                                         r"count\) must lie in 0\.\.2304"):
        find_holdsite(z, -staged["labels"] - 1, [], CFG)


def test_a_surface_id_beyond_the_labels_asks_for_no_table(staged) -> None:
    z, labels = staged["z"], staged["labels"]
    surfaces = describe_surfaces(z, labels, CFG)
    far = replace(surfaces[0], id=2**40)
    site = find_holdsite(z, labels, [*surfaces, far], CFG)
    assert site == find_holdsite(z, labels, surfaces, CFG)


@pytest.mark.parametrize("call, named", [
    (lambda s: stage_edges(s["z"].ravel(), CFG), "`z` must be a 2-D array"),
    (lambda s: stage_edges(s["z"][:, :, None], CFG), "`z` must be a 2-D array"),
    (lambda s: stage_edges(s["z"].astype(complex), CFG), "dtype complex128"),
    (lambda s: stage_link(s["z"], s["codes"][:-1], CFG), "`edges` (shape (47, 48))"),
    (lambda s: stage_link(s["z"], np.where(s["codes"] > 0, 77, 0).astype(np.uint8), CFG),
     "`edges` holds 77: edge codes must lie in 0..3"),
    (lambda s: stage_grow(s["z"], s["codes"], s["components"][:-1], CFG),
     "`components` (shape (47, 48))"),
    (lambda s: stage_grow(s["z"], s["codes"], s["components"] + 0.5, CFG),
     "`components` must hold integers"),
    (lambda s: describe_surfaces(s["z"], s["labels"][:-1], CFG), "`labels` (shape (47, 48))"),
    (lambda s: stage_grow(np.zeros((0, 0)), np.zeros((0, 0), np.uint8),
                          np.zeros((0, 0), np.int32), CFG), "with a pixel at least"),
])
def test_stage_arguments_of_the_wrong_shape_or_kind_are_named(staged, call, named) -> None:
    with pytest.raises(ValueError) as err:
        call(staged)
    assert named in str(err.value) and "\n" not in str(err.value)
