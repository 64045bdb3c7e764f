"""The compiled kernels (rangeseg_cli.kernels.compiled) give exactly the numpy reference's results.

Edges (Sec. V-1, V-2): identical maps. Region growing and surfaces (Sec. V-4)
and holdsites (Sec. VII): identical moment sums, labels, boundary pairs and
holdsites, coefficients equal within 1e-9 (they are in fact bitwise equal).
"""

import dataclasses
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import box_scene, passes_without, step_image
from rangeseg_cli.batch import io
from rangeseg_cli.config import load_config
from rangeseg_cli.kernels import backend as backend_module
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.stages import edges
from rangeseg_cli.stages.edges import DIRECTIONS, absolute_residual, detect_edges, gaussian_taps
from rangeseg_cli.stages.grow import grow_regions, region_fits, union_sse
from rangeseg_cli.stages.surfaces import describe_surfaces, neighbour_pairs

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
        "step": {"sigma": 1.5, "threshold": 3.0},
        "roof": {"sigma": 2.5, "threshold_a": 2.0, "threshold_b": 1.0, "search_radius": 4},
    })
    assert (config.step.taps, config.roof.taps) == (7, 11)
    assert_same_edges(random_boxes(45, 61, seed=seed, noise=2.0), config)


@requires_numba
@pytest.mark.parametrize(("taps", "radius"), [(17, 4), (5, 6), (9, 4)])
def test_pass_2b_reusing_2a_away_from_its_roof_edges_gives_identical_maps(taps, radius):
    # The compiled pass 2b recomputes the AR only in blocks of columns near the roof
    # edges of 2a and reuses 2a's elsewhere: wide scenes (many blocks), and lags
    # set by the mask (taps // 2) or by the search radius.
    config = load_config(overrides={"roof": {
        "sigma": (taps - 1) / 4.0, "threshold_a": 3.0, "threshold_b": 1.5,
        "search_radius": radius}})
    assert config.roof.taps == taps
    for seed in range(3):
        z = random_boxes(70, 150, seed=seed, noise=1.0, holes=0.005)
        ref = assert_same_edges(z, config)
        assert ref.roof_a.any() and ref.roof_b.any()


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
    from rangeseg_cli.kernels import compiled as _kernels

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


# --------------------------------------------------------------------------- noise estimate


def _bits(a):
    return np.ascontiguousarray(a, dtype=np.float64).view(np.uint64)


@requires_numba
@pytest.mark.parametrize("shape", [(41, 59), (5, 5), (4, 30), (30, 4), (3, 3), (128, 130)])
@pytest.mark.parametrize("max_samples", [1 << 17, 333, 1])
def test_small_filter_residuals_are_bitwise_equal_to_the_reference(shape, max_samples):
    z = random_boxes(*shape, seed=sum(shape), holes=0.03) if min(shape) > 4 else (
        np.random.default_rng(0).normal(50.0, 2.0, shape))
    w = gaussian_taps(1.0, 5)
    ref = edges.small_filter_residuals(z, w, max_samples, backend="numpy")
    fast = edges.small_filter_residuals(z, w, max_samples, backend="numba")
    assert ref.shape == fast.shape
    np.testing.assert_array_equal(_bits(ref), _bits(fast))


@requires_numba
def test_smallest_sorted_is_the_start_of_numpy_sort():
    from rangeseg_cli.kernels import compiled as _kernels

    rng = np.random.default_rng(7)
    samples = [np.abs(rng.normal(size=5000)), np.round(np.abs(rng.normal(size=999)) * 4) / 4,
               np.zeros(40), np.array([0.0, 5e-324, 1e300, 2.5, 1e-300] * 9)]
    for x in samples:
        for k in (1, x.size // 2, x.size):
            np.testing.assert_array_equal(_bits(_kernels.smallest_sorted(x, k)),
                                          _bits(np.sort(x)[:k]))


@requires_numba
def test_compiled_noise_estimate_is_the_numpy_one_bit_for_bit():
    from rangeseg_cli.stages.noise import estimate_noise

    scenes = [io.read_image(p).astype(np.float64) for p in SAMPLES[:4]]
    scenes += [random_boxes(200, 260, seed=1, noise=n, holes=0.02) for n in (0.0, 0.5, 2.0)]
    scenes += [np.full((20, 20), 7.0), np.zeros((4, 4))]
    rng = np.random.default_rng(4)  # masks cut by invalid pixels along both axes
    for shape in ((3, 40), (40, 3), (9, 9), (60, 45)):
        z = rng.normal(20.0, 1.5, shape)
        z[rng.random(shape) < 0.15] = np.nan
        scenes.append(z)
    stripes = rng.normal(20.0, 1.0, (50, 50))
    stripes[:, ::7] = np.nan
    stripes[::5, :] = np.nan
    scenes.append(stripes)
    for z in scenes:
        assert repr(estimate_noise(z, backend="numba")) == repr(estimate_noise(z, backend="numpy"))


# --------------------------------------------------------------------------- pipeline


def pipeline_scenes():
    from rangeseg_cli.synth.scenes import render_scene

    return [box_scene(noise=1.0, seed=1), random_boxes(96, 80, seed=3),
            render_scene("pile", size=(96, 112), noise=1.0, seed=2).image]


@requires_numba
@pytest.mark.parametrize("index", range(3))
def test_run_pipeline_gives_identical_labels_with_both_backends(index, monkeypatch):
    image = pipeline_scenes()[index]
    stages = 3
    results = []
    for use_numba in (False, True):
        monkeypatch.setattr(backend_module, "_USE_NUMBA", use_numba)
        results.append(run_pipeline(image, CFG, stages=stages))
    ref, fast = results
    np.testing.assert_array_equal(ref.edges, fast.edges)
    np.testing.assert_array_equal(ref.components, fast.components)
    if stages >= 3:
        np.testing.assert_array_equal(ref.labels, fast.labels)
        assert ref.labels.max() > 0


# --------------------------------------------------------------------------- Sec. V-4, VII

SAMPLES = sorted((Path(__file__).resolve().parent.parent / "sample_data" / "synthetic")
                 .glob("*.png"))
NO_SPLIT = passes_without("split")


def _stage3(z, config=NO_SPLIT):
    """Heights, linked edges and components of a scene (numpy edges)."""
    res = run_pipeline(z, config, stages=2)
    return res.heights, res.edges, res.components


def _assert_close_tree(a, b, path="surfaces"):
    """Equal structure, ints and strings; floats equal within 1e-9 relative."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for key in a:
            _assert_close_tree(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_close_tree(x, y, f"{path}[{i}]")
    elif isinstance(a, float):
        np.testing.assert_allclose(b, a, rtol=1e-9, atol=1e-12, err_msg=path)
    else:
        assert a == b, path


def assert_same_results(ref, fast):
    assert ref.noise_sigma == fast.noise_sigma
    np.testing.assert_array_equal(ref.edges, fast.edges)
    np.testing.assert_array_equal(ref.components, fast.components)
    np.testing.assert_array_equal(ref.labels, fast.labels)
    _assert_close_tree([dataclasses.asdict(s) for s in ref.surfaces],
                       [dataclasses.asdict(s) for s in fast.surfaces])
    _assert_close_tree(ref.holdsite.to_dict(), fast.holdsite.to_dict(), "holdsite")


def run_both(image, config, monkeypatch):
    """``run_pipeline`` with every stage on numpy, then on the compiled kernels."""
    results = []
    for use_numba in (False, True):
        monkeypatch.setattr(backend_module, "_USE_NUMBA", use_numba)
        results.append(run_pipeline(image, config))
    return results


@requires_numba
@pytest.mark.parametrize("split", [False, True])
@pytest.mark.parametrize("path", SAMPLES, ids=lambda p: p.stem)
def test_sample_scenes_give_identical_labels_surfaces_and_holdsites(path, split, monkeypatch):
    config = load_config() if split else NO_SPLIT
    ref, fast = run_both(io.read_image(path), config, monkeypatch)
    assert_same_results(ref, fast)
    assert len(ref.surfaces) >= 3 and ref.holdsite.holdsite is not None


@requires_numba
@pytest.mark.parametrize("seed", range(4))
def test_random_noisy_scenes_give_identical_labels_surfaces_and_holdsites(seed, monkeypatch):
    config = load_config(overrides={"holdsite": {"size": [5, 9], "max_candidates": 12}})
    ref, fast = run_both(random_boxes(90, 110, seed=seed, noise=1.5), config, monkeypatch)
    assert_same_results(ref, fast)
    assert ref.labels.max() >= 2


@requires_numba
@pytest.mark.parametrize("size", [(7, 7), (5, 5), (3, 9)])
def test_compiled_window_search_gives_the_hits_of_the_reference(size, monkeypatch):
    from rangeseg_cli.stages import holdsite

    config = load_config(preset="paper", overrides={"holdsite": {"size": list(size),
                                                                 "rotation_step": 90}})
    result = run_pipeline(random_boxes(90, 110, seed=3, noise=1.5), config)
    z, labels = holdsite._check(result.heights, result.labels)
    angles = (0.0,)  # one angle of a full rectangle: the compiled case
    found = 0
    for s in result.surfaces:
        hits = [holdsite.surface_windows(holdsite._Scene(labels, np.isfinite(z), z,
                                                         config.holdsite, angles, backend), s)
                for backend in ("numpy", "numba")]
        ref, fast = (dataclasses.asdict(h) for h in hits)
        for key, value in ref.items():
            if isinstance(value, np.ndarray):
                np.testing.assert_array_equal(_bits(fast[key]), _bits(value), err_msg=key)
            else:
                assert fast[key] == value, key
        found += hits[0].rows.size
    assert found > 0


@requires_numba
@pytest.mark.parametrize("seed", range(4))
def test_region_fits_are_bitwise_equal_to_the_reference(seed):
    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.stages.grow import _reference_moments

    z, _, components = _stage3(random_boxes(70, 90, seed=seed))
    n = int(components.max())
    ref, _ = _reference_moments(z, components, n)
    fast = _kernels.run_moments(z, _kernels.fitted_runs(z, components), n, 0, 0)
    for name, got in zip(("counts", "cx", "cy", "scale", "sums", "rhs"), fast, strict=True):
        np.testing.assert_array_equal(got, getattr(ref, name), err_msg=name)
    for dtype, orders in ((np.int32, (2, 1, 0)), (np.int64, (2, 1)), (np.uint8, (1, 2))):
        a = region_fits(z, components.astype(dtype), n, orders, backend="numpy")
        b = region_fits(z, components.astype(dtype), n, orders, backend="numba")
        for (ca, ea), (cb, eb) in zip(a.fits, b.fits, strict=True):
            np.testing.assert_array_equal(ca, cb)
            np.testing.assert_array_equal(ea, eb)
        for name in ("counts", "centroid_row", "centroid_col", "mean_height"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@requires_numba
@pytest.mark.parametrize("passes", [1, 0, 3])
@pytest.mark.parametrize("seed", range(3))
def test_grow_regions_gives_identical_labels(seed, passes):
    z, codes, components = _stage3(random_boxes(64, 96, seed=seed, noise=2.0))
    cfg = dataclasses.replace(NO_SPLIT.grow, passes=passes)
    ref = grow_regions(z, codes, components, cfg, backend="numpy")
    fast = grow_regions(z, codes, components, cfg, backend="numba")
    np.testing.assert_array_equal(ref, fast)
    assert (ref > 0).sum() > (components > 0).sum()  # the passes did grow


@requires_numba
@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint16])
@pytest.mark.parametrize("reach", [1, 2, 3])
def test_neighbour_pairs_are_identical_in_value_order_and_dtype(dtype, reach):
    rng = np.random.default_rng(reach)
    labels = rng.integers(0, 5, (33, 47)).astype(dtype)
    labels[5:20, 10:30] = 3  # a large region, so that most pixels are not on a boundary
    ref = neighbour_pairs(labels, reach, backend="numpy")
    fast = neighbour_pairs(labels, reach, backend="numba")
    for a, b in zip(ref, fast, strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)
    assert ref[0].size > 0


@requires_numba
@pytest.mark.parametrize("reach", [2, 3, 5])
def test_neighbour_pairs_of_arrays_narrower_than_the_reach_are_identical(reach):
    rng = np.random.default_rng(40 + reach)
    for shape in [(1, 1), (1, 2), (2, 1), (3, 2), (2, 4), (6, 1), (5, 3)]:
        labels = rng.integers(0, 4, shape).astype(np.int32)
        ref = neighbour_pairs(labels, reach, backend="numpy")
        fast = neighbour_pairs(labels, reach, backend="numba")
        for a, b in zip(ref, fast, strict=True):
            np.testing.assert_array_equal(a, b)


@requires_numba
@pytest.mark.parametrize("seed", range(3))
def test_pair_medians_are_identical_to_the_lexsort_reference(seed):
    from rangeseg_cli.stages.surfaces import pair_medians

    rng = np.random.default_rng(seed)
    size = int(rng.integers(1, 3000))
    lo = rng.integers(0, 40, size)
    hi = lo + rng.integers(1, 9, size)
    values = np.round(rng.normal(size=(3, size)), 1)  # ties, odd and even groups
    values[1, ::7] = -0.0
    ref = pair_medians(lo, hi, values, backend="numpy")
    fast = pair_medians(lo, hi, values, backend="numba")
    for a, b in zip(ref, fast, strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


@requires_numba
def test_label_boxes_are_those_of_find_objects():
    from rangeseg_cli.stages.surfaces import label_boxes

    labels = np.random.default_rng(3).integers(0, 6, (29, 41)).astype(np.int32)
    labels[labels == 4] = 0  # an absent label
    labels[3:20, 5:30] = 2
    for n in (5, 8):
        np.testing.assert_array_equal(label_boxes(labels, n, backend="numba"),
                                      label_boxes(labels, n, backend="numpy"))
    assert (label_boxes(labels, 5, backend="numba")[[0, 4]] == -1).all()


@requires_numba
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16, np.int32, np.float32, np.float64])
@pytest.mark.parametrize("larger_is_closer", [True, False])
def test_compiled_heights_are_bitwise_the_reference(dtype, larger_is_closer):
    from rangeseg_cli.config import InputConfig
    from rangeseg_cli.stages.rangeimage import to_heights

    rng = np.random.default_rng(3)
    raw = (rng.random((20, 24)) * 250).astype(dtype)
    if raw.dtype.kind == "f":
        raw[2, 3], raw[4, 5] = np.nan, np.inf
    else:
        raw[2, 3] = np.iinfo(dtype).max  # clipped
    for invalid in (np.nan, 0.0):
        for clipped in (True, False):
            cfg = InputConfig(scale=0.1, larger_is_closer=larger_is_closer, invalid=invalid,
                              clipped_invalid=clipped, fill_holes=0)  # the conversion alone
            ref = to_heights(raw, cfg, backend="numpy")
            fast = to_heights(raw, cfg, backend="numba")
            np.testing.assert_array_equal(_bits(fast), _bits(ref))
            assert np.isnan(ref[2, 3]) == (clipped or raw.dtype.kind == "f")


@requires_numba
@pytest.mark.parametrize("dtype", [np.int32, np.int64, np.uint16, np.bool_])
def test_valid_labels_are_those_of_the_reference(dtype):
    from rangeseg_cli.stages.grow import valid_labels

    rng = np.random.default_rng(5)
    z = rng.normal(size=(23, 31))
    z[rng.random(z.shape) < 0.2] = np.nan
    z[0, 0] = np.inf
    labels = rng.integers(0, 2**33 if dtype is np.int64 else 2, z.shape).astype(dtype)
    ref = valid_labels(z, labels, backend="numpy")
    fast = valid_labels(z, labels, backend="numba")
    assert fast[0].dtype == ref[0].dtype == np.int32 and fast[1] == ref[1]
    np.testing.assert_array_equal(fast[0], ref[0])


@requires_numba
@pytest.mark.parametrize("seed", range(3))
def test_compiled_linking_gives_the_reference_codes_and_components(seed):
    from rangeseg_cli.config import LinkConfig
    from rangeseg_cli.stages.link import link_edges

    rng = np.random.default_rng(20 + seed)
    for _ in range(12):
        shape = tuple(rng.integers(1, 50, 2))
        codes = rng.choice(np.array([0, 0, 0, 0, 1, 2, 3], dtype=np.uint8), shape)
        valid = rng.random(shape) > 0.1
        for min_size in (1, 5):
            cfg = LinkConfig(min_component=min_size)
            for ref, fast in zip(link_edges(codes, valid, cfg, backend="numpy"),
                                 link_edges(codes, valid, cfg, backend="numba"), strict=True):
                assert ref.dtype == fast.dtype
                np.testing.assert_array_equal(ref, fast)


@requires_numba
@pytest.mark.parametrize("seed", range(3))
def test_ar_2d_is_bitwise_the_reference(seed):
    rng = np.random.default_rng(seed)
    for _ in range(20):
        z = rng.normal(100.0, 3.0, rng.integers(1, 45, 2))
        z[rng.random(z.shape) < 0.1] = np.nan
        ref = edges.ar_2d(z, backend="numpy")
        np.testing.assert_array_equal(_bits(edges.ar_2d(z, backend="numba")), _bits(ref))


@requires_numba
@pytest.mark.parametrize("seed", range(3))
def test_pair_measures_are_bitwise_the_reference(seed):
    from rangeseg_cli.stages.surfaces import pair_measures

    rng = np.random.default_rng(seed)
    labels = rng.integers(0, 7, (40, 50)).astype(np.int32)
    labels[5:30, 8:40] = 2
    coeffs = rng.normal(0.0, 1.0, (7, 6)) * [50.0, 1.0, 1.0, 1e-2, 1e-2, 1e-2]
    ref = pair_measures(labels, coeffs, backend="numpy")
    fast = pair_measures(labels, coeffs, backend="numba")
    for a, b in zip(ref, fast, strict=True):
        np.testing.assert_array_equal(_bits(b), _bits(a))
    assert ref[0].size > 0


@requires_numba
@pytest.mark.parametrize("seed", range(3))
def test_compiled_step_gaps_are_bitwise_the_reference(seed):
    from rangeseg_cli.stages.holdsite import step_gaps

    rng = np.random.default_rng(10 + seed)
    labels = rng.integers(0, 7, (40, 50)).astype(np.int32)
    labels[5:30, 8:40] = 2
    coeffs = rng.normal(0.0, 1.0, (7, 6)) * [50.0, 1.0, 1.0, 1e-2, 1e-2, 1e-2]
    known = np.ones(7, dtype=bool)
    known[[0, 4]] = False
    ref = step_gaps(labels, coeffs, known, backend="numpy")
    fast = step_gaps(labels, coeffs, known, backend="numba")
    assert list(fast) == list(ref)
    np.testing.assert_array_equal(_bits(np.array(list(fast.values()))),
                                  _bits(np.array(list(ref.values()))))
    assert ref


@requires_numba
@pytest.mark.parametrize("seed", range(4))
def test_neighbour_pairs_of_long_runs_and_many_labels_are_identical(seed):
    rng = np.random.default_rng(60 + seed)
    blocks = rng.integers(0, 9, (12, 9))
    labels = np.repeat(np.repeat(blocks, 5, axis=0), 7, axis=1)[:57, :61].astype(np.int32)
    labels[rng.random(labels.shape) < 0.02] = rng.integers(0, 9)  # single-pixel runs
    for reach in (1, 2, 4):
        ref = neighbour_pairs(labels, reach, backend="numpy")
        fast = neighbour_pairs(labels, reach, backend="numba")
        for a, b in zip(ref, fast, strict=True):
            np.testing.assert_array_equal(a, b)


@requires_numba
def test_describe_surfaces_on_nan_holes_gives_identical_surfaces():
    z, codes, components = _stage3(random_boxes(80, 80, seed=9, holes=0.05))
    labels = grow_regions(z, codes, components, NO_SPLIT.grow, backend="numpy")
    ref = describe_surfaces(z, labels, NO_SPLIT, backend="numpy")
    fast = describe_surfaces(z, labels, NO_SPLIT, backend="numba")
    _assert_close_tree([dataclasses.asdict(s) for s in ref],
                       [dataclasses.asdict(s) for s in fast])
    assert len(ref) >= 2


# --------------------------------------------------------------------------- switch


def test_unknown_backend_is_an_error_naming_the_allowed_values():
    with pytest.raises(ValueError, match=r"`backend` \('fortran'\) must be one of"):
        detect_edges(step_image(), CFG, backend="fortran")


@pytest.fixture
def no_numba(monkeypatch):
    """Make numba look uninstalled (find_spec gives None, import fails)."""
    monkeypatch.setitem(sys.modules, "numba", None)
    backend_module._compiled_kernels.cache_clear()
    yield
    backend_module._compiled_kernels.cache_clear()


def test_without_numba_auto_uses_numpy_and_numba_backend_is_an_error(no_numba, monkeypatch):
    monkeypatch.setattr(backend_module, "_USE_NUMBA", True)
    maps = detect_edges(step_image(40.0), CFG)
    assert maps.step[:, 15:17].all()
    with pytest.raises(ImportError, match="needs the numba package"):
        detect_edges(step_image(40.0), CFG, backend="numba")


def test_without_numba_grow_and_surfaces_use_numpy_and_numba_backend_is_an_error(
        no_numba, monkeypatch):
    monkeypatch.setattr(backend_module, "_USE_NUMBA", True)
    z, codes, components = _stage3(box_scene(noise=1.0, seed=2))
    labels = grow_regions(z, codes, components, NO_SPLIT.grow)
    assert len(describe_surfaces(z, labels, NO_SPLIT)) == 2
    with pytest.raises(ImportError, match="needs the numba package"):
        grow_regions(z, codes, components, NO_SPLIT.grow, backend="numba")
    with pytest.raises(ImportError, match="needs the numba package"):
        neighbour_pairs(labels, backend="numba")


def test_unknown_backend_of_the_fits_is_an_error():
    z, _, components = _stage3(box_scene())
    with pytest.raises(ValueError, match=r"`backend` \('cuda'\) must be one of"):
        region_fits(z, components, int(components.max()), backend="cuda")


def test_pure_numpy_environment_variable_turns_the_kernels_off():
    code = "import rangeseg_cli.kernels.backend as b; print(b._USE_NUMBA)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, "RANGESEG_PURE_NUMPY": "1"})
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=requires_numba)])
@pytest.mark.parametrize("seed", range(3))
def test_fits_of_a_crop_with_its_origin_are_those_of_the_whole_frame(seed, backend):
    z, _, components = _stage3(random_boxes(70, 90, seed=seed, noise=1.0))
    z[5:9, 40:47] = np.nan  # left out either way
    n = int(components.max())
    sizes = np.bincount(components.ravel())[1:]
    ids = np.argsort(np.where(sizes > 0, sizes, sizes.max() + 1))[:2] + 1  # two smallest
    keep = np.isin(components, ids) * components
    rows, cols = np.nonzero(keep)
    box = (slice(rows.min(), rows.max() + 1), slice(cols.min(), cols.max() + 1))
    whole = region_fits(z, keep, n, (2, 1), backend=backend)
    crop = region_fits(z[box], keep[box], n, (2, 1), backend=backend,
                       origin=(box[0].start, box[1].start))
    assert box[0].start > 0 or box[1].start > 0
    for (cw, ew), (cc, ec) in zip(whole.fits, crop.fits, strict=True):
        np.testing.assert_array_equal(cw, cc)
        np.testing.assert_array_equal(ew, ec)
    np.testing.assert_array_equal(whole.centroid_col, crop.centroid_col)
    np.testing.assert_array_equal(whole.centroid_row, crop.centroid_row)
    off = region_fits(z[box], keep[box], n, (2, 1), backend=backend)
    assert not np.array_equal(off.fits[0][0][ids[0]], whole.fits[0][0][ids[0]])


def _knot_problem(seed: int, n: int = 300):
    rng = np.random.default_rng(seed)
    rows = rng.integers(0, 60, n).astype(np.float64)
    cols = rng.integers(0, 80, n).astype(np.float64)
    d = np.array([0.6, 0.8])
    u = d[0] * rows + d[1] * cols
    c = float(np.median(u))
    zs = 5.0 + 0.3 * cols - 0.2 * rows + 0.7 * np.maximum(u - c, 0.0) + rng.normal(0, 1, n)
    knots = np.concatenate([[u.min() - 0.5], np.linspace(u.min() + 1, u.max() + 1, 17)])
    return rows, cols, zs, d, u, knots


@requires_numba
@pytest.mark.parametrize("powers", [(1,), (2, 3), (2,), (3,)])
@pytest.mark.parametrize("seed", range(3))
def test_knot_search_kernels_are_bitwise_equal_to_the_reference(seed, powers):
    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.refine import recut

    rows, cols, zs, d, u, knots = _knot_problem(seed)
    x, y = cols - cols.mean(), rows - rows.mean()
    p = np.asarray(powers, dtype=np.int64)
    ref = recut._knot_normal_equations(u, x, y, zs, knots, p)
    fast = _kernels.knot_normal_equations(u, x, y, zs, knots, p)
    for a, b in zip(ref, fast, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(recut._projected_sse(*ref, 123.0, 1e-10),
                                  _kernels.projected_sse(*fast, 123.0, 1e-10))
    np.testing.assert_array_equal(recut.knot_sse(rows, cols, zs, d, knots, powers, "numpy"),
                                  recut.knot_sse(rows, cols, zs, d, knots, powers, "numba"))


@requires_numba
@pytest.mark.parametrize("powers", [(1,), (2, 3)])
def test_knot_sums_carry_a_nan_as_the_reference_does(powers):
    # The kernel adds zeros for q <= 0 without a branch; a NaN q must still count.
    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.refine import recut

    u = np.array([0.5, np.nan, 2.0, 3.0, 4.5])
    x, y, zs = np.arange(5.0), np.array([0.0, 1, 0, 1, 0]), np.array([1.0, 2, 3, 4, 5])
    knots, p = np.array([1.0, np.nan, 2.5]), np.asarray(powers, dtype=np.int64)
    ref = recut._knot_normal_equations(u, x, y, zs, knots, p)
    fast = _kernels.knot_normal_equations(u, x, y, zs, knots, p)
    assert np.isnan(ref[1][:, 3]).all()
    for a, b in zip(ref, fast, strict=True):
        np.testing.assert_array_equal(a, b)


@requires_numba
def test_the_compiled_knot_search_gives_the_references_knot_and_errors():
    # creases and smooth edges across a line in any direction, few and many pixels (the
    # coarse and the fine searches subsample above 1,500 and 20,000), pixels on one row,
    # and bounds that make the search give up
    from rangeseg_cli.kernels import compiled as _kernels
    from rangeseg_cli.refine import recut

    rng = np.random.default_rng(3)
    outcomes = set()
    for trial in range(60):
        size = int(rng.choice([8, 400, 3000, 25000]))
        rows, cols = np.sort(rng.integers(0, 200, size)), rng.integers(0, 200, size)
        if trial % 13 == 0:
            rows = np.full(size, 7)
        angle = rng.uniform(0.0, np.pi)
        d = np.array([np.cos(angle), np.sin(angle)])
        u = d[0] * rows + d[1] * cols
        zs = (0.3 * rows - 0.1 * cols + np.maximum(u - rng.uniform(u.min(), u.max() + 1e-9), 0)
              ** rng.choice([1, 2]) + rng.normal(0.0, rng.choice([0.0, 0.5, 2.0]), size))
        powers = recut.SMOOTH if trial % 2 else recut.CREASE
        max_mse = float(rng.choice([np.inf, 0.5, 5.0]))
        numpy = recut.best_knot(rows, cols, zs, d, powers, max_mse, backend="numpy")
        compiled = _kernels.best_knot(rows, cols, zs.astype(np.float64), float(d[0]),
                                      float(d[1]), np.asarray(powers, np.int64), max_mse,
                                      recut._SEARCH, recut._PIVOT_TOL)
        np.testing.assert_array_equal(np.array(compiled), np.array(numpy))
        outcomes.add((bool(np.isnan(numpy[0])), size))
    assert {(False, 25000), (False, 3000), (True, 8)} <= outcomes


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=requires_numba)])
@pytest.mark.parametrize("powers", [(1,), (2, 3)])
def test_knot_sse_is_the_least_squares_error_at_every_knot(powers, backend):
    from rangeseg_cli.refine.recut import knot_sse

    rows, cols, zs, d, u, knots = _knot_problem(7)
    got = knot_sse(rows, cols, zs, d, knots, powers, backend=backend)
    for k, c in enumerate(knots):  # knot 0 lies before every pixel: q is linear (crease)
        q = np.maximum(u - c, 0.0)
        a = np.column_stack([np.ones_like(zs), cols, rows] + [q ** e for e in powers])
        coef = np.linalg.lstsq(a, zs, rcond=None)[0]
        want = float(np.sum((zs - a @ coef) ** 2))
        assert got[k] == pytest.approx(want, rel=1e-6, abs=1e-6), k
    assert 1 <= int(np.argmin(got[1:])) <= len(knots) - 3  # the crease is found inside


@pytest.mark.parametrize("backend", ["numpy", pytest.param("numba", marks=requires_numba)])
@pytest.mark.parametrize("seed", range(3))
def test_each_pairs_union_sse_is_that_of_its_pixels_fitted_as_one_region(seed, backend):
    # Pairs share regions and meet along rows (a run spans both); NaN pixels are left out.
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:60, 0:70].astype(np.float64)
    z = 0.02 * (x - 30) ** 2 + 0.5 * y + rng.normal(0.0, 1.0, x.shape)
    z[10:14, 20:30] = np.nan
    labels = rng.integers(1, 7, size=(6, 7)).repeat(10, 0).repeat(10, 1).astype(np.int32)
    pairs = np.array([(1, 2), (2, 3), (1, 3), (4, 6), (5, 6), (2, 5)], dtype=np.int64)
    boxes = []
    for i, j in pairs.tolist():
        rows, cols = np.nonzero((labels == i) | (labels == j))
        boxes.append((rows.min(), rows.max() + 1, cols.min(), cols.max() + 1))
    got = union_sse(z, labels, pairs, np.array(boxes, dtype=np.int64), backend=backend)
    for (i, j), union in zip(pairs.tolist(), got.tolist(), strict=True):
        fitted = region_fits(z, ((labels == i) | (labels == j)).astype(np.int32), 1, (2,))
        assert union == float(fitted.fits[0][1][1]) * int(fitted.counts[1])


def test_a_union_sse_box_outside_the_image_is_refused():
    labels = np.ones((10, 12), np.int32)
    labels[:, 6:] = 2
    z = np.zeros(labels.shape)
    pairs = np.array([[1, 2]])
    for box in ([0, 11, 0, 12], [-1, 10, 0, 12], [0, 10, 3, 2]):
        with pytest.raises(ValueError, match="is not within the image 10x12"):
            union_sse(z, labels, pairs, np.array([box]))
    with pytest.raises(ValueError, match=r"must be \(P, 2\) and \(P, 4\)"):
        union_sse(z, labels, pairs, np.array([[0, 10, 0]]))
    assert union_sse(z, labels, pairs, np.array([[0, 10, 0, 12]])).tolist() == [0.0]
