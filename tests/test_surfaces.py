"""Surface descriptions: refit, planar/curved, HK shape, neighbours and edge types."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rangeseg_cli.config import Config
from rangeseg_cli.pipeline import run_pipeline
from rangeseg_cli.stages.surfaces import curvatures, describe_surfaces, hk_shape, surfaces_to_json

N = 128
CONFIG = Config()


def _grid(n: int = N) -> tuple[np.ndarray, np.ndarray]:
    y, x = np.mgrid[0:n, 0:n].astype(np.float64)
    return y, x


def _two_halves(band: int) -> np.ndarray:
    """Label 1 left of column 63, label 2 right of it, ``band`` unlabelled columns between."""
    labels = np.zeros((N, N), dtype=np.int32)
    labels[:, :63] = 1
    labels[:, 63 + band:] = 2
    return labels


def _by_id(surfaces: list) -> dict:
    return {s.id: s for s in surfaces}


# ------------------------------------------------------------------ end to end


def test_box_top_and_table_are_flat_planes_separated_by_a_step() -> None:
    z = np.full((N, N), 20.0)
    z[40:88, 30:98] = 120.0
    result = run_pipeline(z, stages=3)
    surfaces = _by_id(result.surfaces)
    top, table = surfaces[result.labels[64, 64]], surfaces[result.labels[5, 5]]
    for s, height in ((top, 120.0), (table, 20.0)):
        assert (s.type, s.shape) == ("planar", "flat")
        np.testing.assert_allclose(s.coefficients, [height, 0, 0, 0, 0, 0], atol=1e-9)
        assert s.rms_error < 1e-6
    assert [(n.id, n.edge) for n in top.neighbors] == [(table.id, "step")]
    assert [(n.id, n.edge) for n in table.neighbors] == [(top.id, "step")]
    assert top.bbox[0] >= 39 and top.bbox[2] <= 88 and top.mean_height == pytest.approx(120.0)


def test_cylinder_on_table_is_a_curved_ridge() -> None:
    y, x = _grid()
    z = np.full((N, N), 20.0)
    inside = (np.abs(y - 64.0) < 40.0) & (x >= 16) & (x < 112)
    z[inside] = 60.0 + np.sqrt(1600.0 - (y[inside] - 64.0) ** 2)
    result = run_pipeline(np.round(z), stages=3)
    cylinder = _by_id(result.surfaces)[result.labels[64, 64]]
    assert cylinder.type == "curved"
    assert cylinder.shape == "ridge"  # bulges towards the sensor along one direction
    assert cylinder.coefficients[5] < 0 and abs(cylinder.coefficients[3]) < 1e-4


# ------------------------------------------------------------------ edge types


@pytest.mark.parametrize("band", [0, 1])
def test_ridge_is_a_convex_roof_and_valley_a_concave_roof(band: int) -> None:
    y, x = _grid()
    left, right = 30.0 + 2.0 * x + 0.1 * y, 30.0 + 2.0 * (126 - x) + 0.1 * y
    labels = _two_halves(band)
    ridge = _by_id(describe_surfaces(np.minimum(left, right), labels, CONFIG))
    valley = _by_id(describe_surfaces(300.0 - np.minimum(left, right), labels, CONFIG))
    assert ridge[1].neighbors[0].edge == "roof-convex"
    assert ridge[2].neighbors[0].edge == "roof-convex"
    assert valley[1].neighbors[0].edge == "roof-concave"
    np.testing.assert_allclose(ridge[1].coefficients, [30.0, 2.0, 0.1, 0, 0, 0], atol=1e-8)


def test_coplanar_regions_across_a_line_are_smooth_neighbours() -> None:
    y, x = _grid()
    surfaces = describe_surfaces(10.0 + 0.5 * x + 0.3 * y, _two_halves(1), CONFIG)
    assert [(n.id, n.edge) for n in surfaces[0].neighbors] == [(2, "smooth")]


def test_small_height_offset_is_not_a_step_but_a_large_one_is() -> None:
    labels = _two_halves(1)
    z = np.where(labels == 2, 15.0, 10.0)
    small = describe_surfaces(z, labels, CONFIG)  # 5 <= step.threshold (6)
    large = describe_surfaces(np.where(labels == 2, 17.0, 10.0), labels, CONFIG)
    assert small[0].neighbors[0].edge == "smooth"
    assert large[0].neighbors[0].edge == "step"


def test_regions_two_pixels_apart_are_neighbours_three_apart_are_not() -> None:
    z = np.zeros((N, N))
    assert describe_surfaces(z, _two_halves(1), CONFIG)[0].neighbors  # distance 2
    assert not describe_surfaces(z, _two_halves(2), CONFIG)[0].neighbors  # distance 3


def test_neighbours_are_sorted_by_id_and_symmetric() -> None:
    labels = np.zeros((N, N), dtype=np.int32)
    labels[:, :40] = 3
    labels[:, 41:80] = 1
    labels[:60, 81:] = 2
    labels[61:, 81:] = 4
    surfaces = _by_id(describe_surfaces(np.zeros((N, N)), labels, CONFIG))
    assert [n.id for n in surfaces[1].neighbors] == [2, 3, 4]
    for s in surfaces.values():
        for n in s.neighbors:
            assert s.id in [m.id for m in surfaces[n.id].neighbors]


# ------------------------------------------------------------- type and shape


@pytest.mark.parametrize(("coefficients", "shape"), [
    ((0, 0, 0, -0.01, 0, -0.01), "peak"),  # a cap bulging towards the sensor
    ((0, 0, 0, 0.01, 0, 0.01), "pit"),
    ((0, 0, 0, -0.01, 0, 0), "ridge"),
    ((0, 0, 0, 0.01, 0, 0), "valley"),
    ((0, 0, 0, 0.01, 0, -0.01), "minimal"),
    ((0, 0, 0, -0.02, 0, 0.01), "saddle-ridge"),
    ((0, 0, 0, 0.02, 0, -0.01), "saddle-valley"),
    ((5, 0.3, -0.2, 0, 0, 0), "flat"),
])
def test_hk_shape_names_follow_besl_and_jain(coefficients: tuple, shape: str) -> None:
    assert hk_shape(*curvatures(np.array(coefficients, float), 0.0, 0.0)) == shape


def test_noise_free_plane_is_planar_and_paraboloid_is_a_curved_pit() -> None:
    y, x = _grid()
    labels = np.ones((N, N), dtype=np.int32)
    plane = describe_surfaces(np.round(3.0 + 0.7 * x - 0.4 * y), labels, CONFIG)[0]
    bowl = describe_surfaces(20.0 + 0.01 * ((x - 64) ** 2 + (y - 64) ** 2), labels, CONFIG)[0]
    assert (plane.type, plane.shape) == ("planar", "flat")
    assert plane.coefficients[3:] == (0.0, 0.0, 0.0)
    assert (bowl.type, bowl.shape) == ("curved", "pit")
    np.testing.assert_allclose(bowl.coefficients[3:], [0.01, 0.0, 0.01], atol=1e-9)


@pytest.mark.parametrize("sigma", [1.0, 2.0])
def test_noisy_plane_stays_planar(sigma: float) -> None:
    rng = np.random.default_rng(17)
    y, x = _grid()
    z = np.round(40.0 + 0.2 * x + 0.1 * y + rng.normal(0.0, sigma, (N, N)))
    labels = np.zeros((N, N), dtype=np.int32)
    labels[20:60, 20:60] = 1
    s = describe_surfaces(z, labels, CONFIG)[0]
    assert (s.type, s.shape) == ("planar", "flat")
    assert s.rms_error == pytest.approx(np.sqrt(sigma**2 + 1 / 12), rel=0.1)


# ------------------------------------------------------------ geometry, JSON


def test_counts_bbox_centroid_and_mean_height_of_a_rectangle() -> None:
    y, x = _grid()
    labels = np.zeros((N, N), dtype=np.int32)
    labels[10:20, 30:50] = 3  # ids 1 and 2 are absent: skipped
    z = 5.0 + x
    z[0, 0] = np.nan
    labels[0, 0] = 3  # an invalid pixel never counts
    (s,) = describe_surfaces(z, labels, CONFIG)
    assert s.id == 3 and s.pixels == 200
    assert s.bbox == (10, 30, 19, 49)
    assert s.centroid == pytest.approx((14.5, 39.5))
    assert s.mean_height == pytest.approx(5.0 + 39.5)


def test_surfaces_json_follows_the_file_contract() -> None:
    y, x = _grid()
    labels = _two_halves(1)
    doc = surfaces_to_json(describe_surfaces(np.minimum(2 * x, 2 * (126 - x)), labels, CONFIG))
    text = json.dumps(doc, sort_keys=True, allow_nan=False)
    back = json.loads(text)
    assert [s["id"] for s in back["surfaces"]] == [1, 2]
    first = back["surfaces"][0]
    assert {"id", "pixels", "mean_height", "coefficients", "rms_error", "type", "neighbors",
            "bbox", "centroid", "shape"} <= set(first)
    assert first["neighbors"] == [{"id": 2, "edge": "roof-convex"}]
    assert len(first["coefficients"]) == 6 and isinstance(first["pixels"], int)


def test_no_labels_give_no_surfaces() -> None:
    assert describe_surfaces(np.zeros((N, N)), np.zeros((N, N), np.int32), CONFIG) == []
