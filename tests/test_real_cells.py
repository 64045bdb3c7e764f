"""Real tote frames (sample_data/arc, Intel RealSense SR300 and a second camera; issue 32).

Run as a user of a bin-picking cell would: the unit preset, the camera's
intrinsics file and a frame of the empty tote (and once without it), nothing
hand-tuned. No ground truth comes with these frames; what is checked needs
none (the empty frame judges the site even when the run did not see it):

- an *item*: the site's window, and each runner-up's, is nearer the camera
  than the empty tote by more than 10 mm at most of its pixels (the empty
  frame has no item there);
- *inside the tote*: the empty frame shows the tote's floor under the site
  (the floor is the empty frame's dominant plane: within 10 mm of it);
- the approach is within 45 degrees of the camera's axis;
- *the top of the pile*: no flat cup-sized window on an item over the tote's
  floor stands more than 20 mm higher above that floor than the top of the
  site's surface (Sec. VII: the top-most object is picked);
- the empty-tote frames alone have nothing to pick.
"""

import math
from pathlib import Path

import numpy as np
import pytest
from scipy import ndimage

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.batch import io
from rangeseg_cli.cell.intrinsics import read_intrinsics
from rangeseg_cli.cell.workspace import find_support, points

ARC = Path(__file__).resolve().parent.parent / "sample_data" / "arc"
CAMERAS = ("suction", "bin")


def _config(camera: str):
    k = read_intrinsics(ARC / f"{camera}-camera-intrinsics.txt")
    return load_config(preset="tenth-mm-depth", overrides=k.settings())


def _depth_mm(raw: np.ndarray) -> np.ndarray:
    return np.where(raw > 0, raw * 0.1, np.nan)


def _window(site: dict) -> tuple[slice, slice]:
    rows, cols = site["size"]
    r, c = site["row"], site["col"]
    return slice(r - rows // 2, r + rows // 2 + 1), slice(c - cols // 2, c + cols // 2 + 1)


@pytest.fixture(scope="module", params=[(c, given) for c in CAMERAS for given in (True, False)],
                ids=lambda p: f"{p[0]}-{'with' if p[1] else 'without'}-background")
def picked(request):
    """A frame's holdsite and labels, run with its empty tote as background and without it."""
    camera, given = request.param
    raw = io.read_image(ARC / f"{camera}-scene.depth.png")
    empty = io.read_image(ARC / "empty" / f"{camera}-background.depth.png")
    config = _config(camera)
    result = run_pipeline(raw, config, background=empty if given else None)
    return raw, empty, config, result.holdsite.to_dict(), result.labels


def test_the_site_lies_on_an_item_that_the_empty_tote_does_not_have(picked):
    raw, empty, _, doc, _ = picked
    site = doc["holdsite"]
    assert site is not None, doc["reason"]
    window = _window(site)
    scene, tote = _depth_mm(raw[window]), _depth_mm(empty[window])
    assert np.isfinite(scene).all()  # a valid reading under every cup pixel
    nearer = tote - scene > 10.0
    assert np.mean(nearer[np.isfinite(tote)]) > 0.8


def test_every_runner_up_lies_on_an_item_too(picked):
    # A robot tries the runners-up when the first pick fails: none on a tote wall.
    raw, empty, _, doc, _ = picked
    for site in doc["candidates"]:
        window = _window(site)
        scene, tote = _depth_mm(raw[window]), _depth_mm(empty[window])
        nearer = tote - scene > 10.0
        assert np.mean(nearer[np.isfinite(tote)]) > 0.8, site


def test_the_site_lies_over_the_tote_floor(picked):
    raw, empty, config, doc, _ = picked
    site = doc["holdsite"]
    z = -_depth_mm(empty)
    floor = find_support(z, config.input, 10.0)
    assert floor is not None
    r, c = site["row"], site["col"]
    patch = z[r - 10: r + 11, c - 10: c + 11]
    rows, cols = np.nonzero(np.isfinite(patch))
    pts = points(patch[rows, cols], config.input, rows + r - 10.0, cols + c - 10.0)
    assert np.median(np.abs(floor.distance(pts))) < 10.0  # the empty tote's floor is there


def test_the_approach_is_within_45_degrees_of_the_camera_axis(picked):
    doc = picked[3]
    approach = doc["holdsite"]["approach_camera"]
    assert math.degrees(math.acos(approach[2])) <= 45.0
    assert doc["holdsite"]["flat_rms"] < 2.0  # mm: flat enough for a cup to seal


def _heights_above(floor, depth_mm: np.ndarray, config) -> np.ndarray:
    """Height (mm) of each pixel above the plane ``floor`` (NaN where no reading)."""
    rows, cols = np.indices(depth_mm.shape, dtype=np.float64)
    z = -np.nan_to_num(depth_mm, nan=1.0)
    height = np.abs(floor.distance(points(z.ravel(), config.input, rows.ravel(), cols.ravel())))
    return np.where(np.isfinite(depth_mm), height.reshape(depth_mm.shape), np.nan)


def _plane_rms(a: np.ndarray, n: int) -> np.ndarray:
    """RMS residual of the least-squares plane of ``a`` over each n x n window (no NaN)."""
    v, u = np.indices(a.shape, dtype=np.float64)
    a = a - np.mean(a)

    def mean(x):
        return ndimage.uniform_filter(x, n, mode="nearest")

    var = mean(a * a) - mean(a) ** 2
    for w in (u, v):  # the square window's x and y are uncorrelated
        var -= (mean(w * a) - mean(w) * mean(a)) ** 2 / (mean(w * w) - mean(w) ** 2)
    return np.sqrt(np.maximum(var, 0.0))


def test_the_site_is_on_the_top_of_the_pile(picked):
    # Every window of the site's size that lies on items (nearer than the empty tote by
    # 10 mm), over the empty tote's floor, and is flat (plane RMS < 1.5 mm) is one a cup
    # could take; the highest of them above the floor is at most 20 mm above the top of
    # the site's surface (its 95th percentile: the site itself may sit where the surface
    # faces the camera best).
    raw, empty, config, doc, labels = picked
    site = doc["holdsite"]
    scene, tote = _depth_mm(raw), _depth_mm(empty)
    floor = find_support(-tote, config.input, 10.0)
    n = site["size"][0]
    square = np.ones((n, n), dtype=bool)
    item = ndimage.binary_erosion(np.nan_to_num(tote - scene) > 10.0, square)
    on_floor = ndimage.binary_erosion(np.nan_to_num(_heights_above(floor, tote, config),
                                                    nan=99.0) < 10.0, square)
    height = _heights_above(floor, scene, config)
    flat = _plane_rms(np.nan_to_num(height), n) < 1.5
    tops = ndimage.uniform_filter(np.nan_to_num(height), n)[item & on_floor & flat]
    assert tops.size
    surface = height[(labels == site["surface"]) & np.isfinite(height)]
    assert tops.max() - np.percentile(surface, 95) <= 20.0


@pytest.mark.parametrize("camera", CAMERAS)
def test_an_empty_tote_has_nothing_to_pick(camera):
    empty = io.read_image(ARC / "empty" / f"{camera}-background.depth.png")
    doc = run_pipeline(empty, _config(camera)).holdsite.to_dict()
    assert doc["holdsite"] is None
    assert doc["reason"].startswith("nothing to pick")
