"""Narrow faces grown into a planar region's border get regions of their own (rangeseg_cli.refine.carve)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from conftest import chamfered, passes_without
from rangeseg_cli.config import load_config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.refine.boundaries import refine_boundaries
from rangeseg_cli.refine.carve import carve_faces
from rangeseg_cli.synth.evaluate import hoover_compare

CONFIG = load_config()
@pytest.mark.parametrize(("noise", "seed"), [(0.0, 0), (1.0, 0), (1.0, 1), (2.0, 2)])
def test_a_chamfer_grown_into_the_top_is_carved_out(noise, seed):
    z, truth, grown = chamfered(noise, seed)
    out = carve_faces(z, grown, CONFIG, noise=noise)
    new = out == 3
    assert np.count_nonzero(new) >= CONFIG.link.min_component
    assert np.count_nonzero(new & (truth == 2)) >= 0.8 * np.count_nonzero(new)
    np.testing.assert_array_equal(out[out != 3], grown[out != 3])  # the rest is kept


@pytest.mark.parametrize("seed", [0, 1])
def test_with_the_refinement_the_chamfer_is_a_correct_detection(seed):
    z, truth, grown = chamfered(1.0, seed)
    assert hoover_compare(truth, grown).counts()["correct"] == 2  # top and side only
    out = refine_boundaries(z, carve_faces(z, grown, CONFIG, noise=1.0), CONFIG, noise=1.0)
    assert hoover_compare(truth, out).counts()["correct"] == 3


@pytest.mark.parametrize("seed", range(4))
def test_noise_alone_carves_nothing(seed):
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    z = 120.0 + 0.3 * x - 0.2 * y + np.random.default_rng(seed).normal(0.0, 2.0, x.shape)
    labels = np.where(x < 40, 1, 2).astype(np.int32)
    np.testing.assert_array_equal(carve_faces(z, labels, CONFIG, noise=2.0), labels)


@pytest.mark.parametrize("given", [0.0, 1.5])
def test_noise_alone_carves_nothing_when_the_noise_given_is_too_low(given):
    # a noise estimate too low (as on a real sensor, or a rough surface): the interior's
    # inlier share and its plane's RMS error keep its border whole
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    z = 120.0 + 0.3 * x - 0.2 * y + np.random.default_rng(5).normal(0.0, 2.0, x.shape)
    labels = np.where(x < 40, 1, 2).astype(np.int32)
    np.testing.assert_array_equal(carve_faces(z, labels, CONFIG, noise=given), labels)


def test_a_band_parallel_to_the_plane_is_no_crease():
    # a border band raised by a step is no chamfer: its plane meets the region's at 0 degrees
    z, _, grown = chamfered(0.5, 3, slope=0.0)
    z[:, 41:44] += 6.0
    np.testing.assert_array_equal(carve_faces(z, grown, CONFIG, noise=0.5), grown)


def test_a_piece_an_earlier_face_took_is_skipped(monkeypatch):
    # a piece whose pixels an earlier face's extension took (here: every piece twice)
    import rangeseg_cli.refine.carve as carve

    z, _, grown = chamfered(1.0, 0)
    once = carve_faces(z, grown, CONFIG, noise=1.0)
    pieces = carve._pieces
    monkeypatch.setattr(carve, "_pieces", lambda *a, **k: [p for p in pieces(*a, **k)
                                                          for _ in range(2)])
    np.testing.assert_array_equal(carve_faces(z, grown, CONFIG, noise=1.0), once)


def test_curved_regions_are_left_alone():
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    z = 200.0 - 0.05 * (x - 20.0) ** 2 - 0.02 * (y - 24.0) ** 2
    labels = np.ones(z.shape, dtype=np.int32)
    np.testing.assert_array_equal(carve_faces(z, labels, CONFIG, noise=0.0), labels)


def test_the_input_is_kept_and_invalid_pixels_stay_unlabelled():
    z, _, grown = chamfered(1.0, 0)
    z[10:14, 42:50] = np.nan
    before, heights = grown.copy(), z.copy()
    out = carve_faces(z, grown, CONFIG, noise=1.0)
    np.testing.assert_array_equal(grown, before)
    np.testing.assert_array_equal(z, heights)
    assert not out[10:14, 42:50].any() and out.dtype == np.int32


def test_shapes_must_agree():
    with pytest.raises(ValueError):
        carve_faces(np.zeros((4, 4)), np.zeros((4, 5), np.int32), CONFIG, noise=0.0)


@pytest.mark.parametrize("seed", range(4))
def test_the_pipeline_finds_a_chamfer_grown_into_the_top_only_with_carving(seed):
    """The whole pipeline on :func:`chamfered` at sigma 1: the chamfer 4 pixels wide is a
    correct detection with carving and not without. The chamfer pass, which finds it
    too, is off in both runs."""
    z, truth, _ = chamfered(1.0, seed)

    def found(*without):
        labels = run_pipeline(z, passes_without("chamfers", *without), stages=3).labels
        return 2 in {g for i in hoover_compare(truth, labels).instances
                     if i.kind == "correct" for g in i.gt}

    assert found() and not found("carve")


def test_paper_preset_turns_it_off():
    # the old key [split] carve is refused naming refine.passes: tests/test_config.py
    assert "carve" not in load_config(preset="paper").refine.passes
    assert "carve" in CONFIG.refine.passes


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**32 - 1), noise=st.floats(0.0, 3.0),
       slope=st.floats(0.5, 6.0), invalid=st.floats(0.0, 0.2))
def test_carving_only_relabels_pixels_of_one_region_each(seed, noise, slope, invalid):
    z, _, grown = chamfered(noise, seed, slope=slope)
    z[np.random.default_rng(seed + 1).random(z.shape) < invalid] = np.nan
    out = carve_faces(z, grown, CONFIG, noise=noise)
    valid = np.isfinite(z)
    assert out.dtype == np.int32 and np.all(out[~valid] == 0)
    same = out <= grown.max()
    np.testing.assert_array_equal(out[same & valid], grown[same & valid])
    for k in np.unique(out[~same]).tolist():  # each new face lies within one old region
        assert len(np.unique(grown[out == k])) == 1
        assert np.count_nonzero(out == k) >= CONFIG.link.min_component
