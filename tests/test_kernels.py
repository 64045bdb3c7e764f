"""The compiled edge kernels (rangeseg_cli._kernels) give exactly the numpy reference's maps."""

import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import box_scene, step_image
from rangeseg_cli import edges
from rangeseg_cli.config import load_config
from rangeseg_cli.edges import DIRECTIONS, absolute_residual, detect_edges, gaussian_taps
from rangeseg_cli.pipeline import run_pipeline

CFG = load_config()
ONE_SIDED = load_config(overrides={"roof": {"truncation": "one-sided"}})
HAVE_NUMBA = importlib.util.find_spec("numba") is not None
requires_numba = pytest.mark.skipif(not HAVE_NUMBA, reason="numba is not installed")


def assert_same_edges(z, config=CFG):
    ref = detect_edges(z, config, backend="numpy")
    fast = detect_edges(z, config, backend="numba")
    for name in ("step", "roof_a", "roof_b", "codes"):
        a, b = getattr(ref, name), getattr(fast, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    return ref


def roof_image(rows=64, cols=64, slope=2.0):
    x = np.arange(cols, dtype=float)
    return np.tile(100.0 - slope * np.abs(x - cols // 2), (rows, 1))


def tilted_step(slope=1.0, rows=64, cols=64, jump=30.0):
    z = np.tile(slope * np.arange(float(cols)), (rows, 1))
    z[:, cols // 2:] += jump
    return z


def random_boxes(rows, cols, seed, noise=1.0, holes=0.02):
    """Random tilted boxes on a table, Gaussian noise and NaN holes (deterministic)."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:rows, 0:cols].astype(float)
    z = 30.0 + 0.05 * xx
    for _ in range(rng.integers(2, 7)):
        r0, c0 = rng.integers(0, rows - 4), rng.integers(0, cols - 4)
        r1, c1 = r0 + rng.integers(4, rows // 2 + 5), c0 + rng.integers(4, cols // 2 + 5)
        a, b = rng.uniform(-1.5, 1.5, 2)
        top = rng.uniform(40, 150) + a * (xx - c0) + b * (yy - r0)
        box = (yy >= r0) & (yy < r1) & (xx >= c0) & (xx < c1)
        z = np.where(box, np.maximum(z, top), z)
    z = z + rng.normal(0.0, noise, z.shape)
    z[rng.random(z.shape) < holes] = np.nan
    return z


# --------------------------------------------------------------------------- scenes


@requires_numba
def test_step_gives_identical_maps():
    ref = assert_same_edges(step_image(40.0))
    assert ref.step.any()


@requires_numba
def test_roof_gives_identical_maps():
    ref = assert_same_edges(roof_image())
    assert ref.roof.any()


@requires_numba
def test_tilted_plane_beside_step_gives_identical_maps_and_no_roof_edge():
    ref = assert_same_edges(tilted_step())
    assert ref.step.any() and not ref.roof.any()


@requires_numba
def test_one_sided_truncation_gives_identical_maps_with_the_ramp_bias():
    z = tilted_step(slope=2.0, jump=40.0)
    ref = assert_same_edges(z, ONE_SIDED)
    assert ref.roof.any()  # the false roof edges of one-sided masks (SPEC *Truncation*)


@requires_numba
def test_nan_holes_give_identical_maps_and_no_edge_inside():
    z = step_image(40.0, size=48, col=24)
    z[10:20, 5:40] = np.nan
    z[30:33, 3:6] = np.nan
    for config in (CFG, ONE_SIDED):
        ref = assert_same_edges(z, config)
        assert not ref.codes[np.isnan(z)].any()


@requires_numba
@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("shape", [(37, 53), (53, 37), (16, 16), (64, 64), (17, 90)])
def test_random_noisy_scenes_give_identical_maps(seed, shape):
    z = random_boxes(*shape, seed=seed)
    assert_same_edges(z, CFG)
    assert_same_edges(z, ONE_SIDED)


@requires_numba
@pytest.mark.parametrize("seed", range(3))
def test_non_default_filters_give_identical_maps(seed):
    config = load_config(overrides={
        "step": {"sigma": 1.5, "taps": 7, "threshold": 3.0},
        "roof": {"sigma": 2.5, "taps": 11, "threshold_a": 2.0, "threshold_b": 1.0,
                 "search_radius": 4},
    })
    assert_same_edges(random_boxes(45, 61, seed=seed, noise=2.0), config)


@requires_numba
def test_read_only_and_float32_heights_give_identical_maps():
    z = random_boxes(40, 50, seed=4)
    z.flags.writeable = False
    assert_same_edges(z)
    assert_same_edges(z.astype(np.float32))


@requires_numba
def test_noise_free_integer_scene_with_exact_ties_gives_identical_maps():
    # Noise-free integer heights make many ARs equal in exact arithmetic: the tie
    # tolerance of local_maximum must give the same answer on both paths.
    assert_same_edges(np.round(random_boxes(40, 70, seed=11, noise=0.0, holes=0.0)))
    assert_same_edges(box_scene())


@requires_numba
@pytest.mark.parametrize("truncation", ["symmetric", "one-sided"])
def test_absolute_residuals_are_bitwise_equal_to_the_reference(truncation):
    from rangeseg_cli import _kernels

    z = random_boxes(41, 59, seed=5)
    excluded = detect_edges(z, CFG, backend="numpy").step
    w = gaussian_taps(4.0, 17)
    pad = 8
    zp = np.pad(np.nan_to_num(z), pad)
    okp = np.pad(~(excluded | np.isnan(z)), pad)
    fast = _kernels.absolute_residuals(zp, okp, pad, w, truncation == "symmetric")
    for d, direction in enumerate(DIRECTIONS):
        ref = absolute_residual(z, excluded, w, direction, truncation=truncation)
        np.testing.assert_array_equal(fast[d], ref, err_msg=str(direction))


# --------------------------------------------------------------------------- pipeline


def pipeline_scenes():
    scenes = [box_scene(noise=1.0, seed=1), random_boxes(96, 80, seed=3)]
    if importlib.util.find_spec("rangeseg_cli.synth") is not None:
        from rangeseg_cli.synth import render_scene

        scenes.append(render_scene("pile", size=(96, 112), noise=1.0, seed=2).image)
    return scenes


@requires_numba
@pytest.mark.parametrize("index", range(3))
def test_run_pipeline_gives_identical_labels_with_both_backends(index, monkeypatch):
    scenes = pipeline_scenes()
    if index >= len(scenes):
        pytest.skip("rangeseg_cli.synth (the pile scene) is not there")
    image = scenes[index]
    stages = 3 if importlib.util.find_spec("rangeseg_cli.grow") else 2
    results = []
    for use_numba in (False, True):
        monkeypatch.setattr(edges, "_USE_NUMBA", use_numba)
        results.append(run_pipeline(image, CFG, stages=stages))
    ref, fast = results
    np.testing.assert_array_equal(ref.edges, fast.edges)
    np.testing.assert_array_equal(ref.components, fast.components)
    if stages >= 3:
        np.testing.assert_array_equal(ref.labels, fast.labels)
        assert ref.labels.max() > 0


# --------------------------------------------------------------------------- switch


def test_unknown_backend_is_an_error_naming_the_allowed_values():
    with pytest.raises(ValueError, match=r"`backend` \('fortran'\) must be one of"):
        detect_edges(step_image(), CFG, backend="fortran")


@pytest.fixture
def no_numba(monkeypatch):
    """Make numba look uninstalled (find_spec gives None, import fails)."""
    monkeypatch.setitem(sys.modules, "numba", None)
    edges._compiled_kernels.cache_clear()
    yield
    edges._compiled_kernels.cache_clear()


def test_without_numba_auto_uses_numpy_and_numba_backend_is_an_error(no_numba, monkeypatch):
    monkeypatch.setattr(edges, "_USE_NUMBA", True)
    maps = detect_edges(step_image(40.0), CFG)
    assert maps.step[:, 15:17].all()
    with pytest.raises(ImportError, match="needs the numba package"):
        detect_edges(step_image(40.0), CFG, backend="numba")


def test_pure_numpy_environment_variable_turns_the_kernels_off():
    code = "import rangeseg_cli.edges as e; print(e._USE_NUMBA)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, "RANGESEG_PURE_NUMPY": "1"})
    assert out.stdout.strip() == "False"
