"""The holdsite search ends soon when the footprint fits nowhere, and stops when asked."""

import time

import numpy as np
import pytest
from scipy import ndimage

from rangeseg_cli import run_pipeline
from rangeseg_cli.batch import io
from rangeseg_cli.batch.stopping import checkpoint, stop_checks
from rangeseg_cli.config import load_config
from rangeseg_cli.stages.holdsite import erode_runs, find_holdsite, footprint


@pytest.fixture(scope="module")
def part1():
    image = io.read_image("sample_data/synthetic/part1-n1.png")
    return run_pipeline(image, load_config(), stages=3)


@pytest.mark.parametrize("size", [(61, 3), (255, 3), (9, 5), (3, 17), (7, 7)])
@pytest.mark.parametrize("angle", [0.0, 7.5, 30.0, 45.0, 89.5, 120.0])
def test_erosion_by_runs_is_scipys_erosion(size, angle):
    rng = np.random.default_rng(int(angle * 10) + size[0])
    mask = ndimage.binary_dilation(rng.random((90, 70)) < 0.02, iterations=9)
    fp = footprint(size, angle)
    np.testing.assert_array_equal(erode_runs(mask, fp),
                                  ndimage.binary_erosion(mask, structure=fp, border_value=0))


def test_a_footprint_that_fits_nowhere_is_ruled_out_at_once(part1):
    # 255x3 at 12 angles took about 50 s (scipy's erosion by each rotated footprint); at
    # every 0.5 degree (360 angles), more than 15 minutes.
    config = load_config(overrides={"holdsite": {"size": [255, 3], "rotation_step": 0.5}})
    t0 = time.perf_counter()
    result = find_holdsite(part1.heights, part1.labels, part1.surfaces, config)
    assert time.perf_counter() - t0 < 10.0  # about 1 s on a loaded 2-core machine
    assert result.holdsite is None
    assert "no surface has a 255x3 window wholly on its valid pixels" in result.reason


def test_a_stop_request_ends_the_search_at_the_next_angle(part1):
    config = load_config(overrides={"holdsite": {"size": [9, 3], "rotation_step": 0.5}})
    calls = []

    def check():
        calls.append(1)
        if len(calls) > 3:
            raise KeyboardInterrupt

    with stop_checks(check), pytest.raises(KeyboardInterrupt):
        find_holdsite(part1.heights, part1.labels, part1.surfaces, config)
    assert len(calls) == 4
    checkpoint()  # outside stop_checks: nothing to call
