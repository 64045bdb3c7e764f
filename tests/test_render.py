"""The overlay picture: surfaces in colour shaded by height, the chosen site filled."""

from __future__ import annotations

import numpy as np
import pytest

from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.batch.render import label_colors, overlay, shade_by_height


def two_boxes() -> np.ndarray:
    z = np.full((64, 96), 20.0)
    z[12:52, 8:48] = 120.0
    z[16:48, 58:90] = 60.0
    return z + np.random.default_rng(0).normal(0.0, 0.5, z.shape)


def brightness(image: np.ndarray) -> np.ndarray:
    return image.astype(float).sum(axis=-1)


def test_nearer_surfaces_are_brighter_than_their_flat_colour_says():
    z = two_boxes()
    result = run_pipeline(z, load_config(overrides={"holdsite": {"max_candidates": 0}}))
    flat = label_colors(result.labels)
    shaded = overlay(result.labels, None, heights=result.heights)
    ratio = brightness(shaded) / np.maximum(brightness(flat), 1)
    high, low, floor = ratio[30, 20], ratio[30, 75], ratio[60, 4]
    assert high > low > floor
    assert high == pytest.approx(1.0, abs=0.02)  # the nearest surface keeps its colour


def test_shading_keeps_the_hue_and_leaves_unlabelled_pixels_black():
    labels = np.array([[1, 1], [0, 2]])
    z = np.array([[10.0, 0.0], [5.0, np.nan]])
    image = shade_by_height(label_colors(labels), z)
    assert np.all(image[1, 0] == 0)
    a, b = image[0, 0].astype(float), image[0, 1].astype(float)  # one label, two heights
    assert brightness(a[None])[0] > brightness(b[None])[0]
    assert np.allclose(a / a.sum(), b / b.sum(), atol=0.02)
    assert np.array_equal(image[1, 1], label_colors(labels)[1, 1])  # invalid: unshaded


def test_shading_needs_heights_of_the_picture_size():
    with pytest.raises(ValueError, match="must have the shape"):
        shade_by_height(np.zeros((4, 4, 3), np.uint8), np.zeros((4, 5)))


def test_the_chosen_site_stays_filled_white_and_runners_up_hollow_on_a_shaded_overlay():
    result = run_pipeline(two_boxes(), load_config(overrides={"holdsite": {"max_candidates": 1}}))
    image = overlay(result.labels, result.holdsite, heights=result.heights)
    site, other = result.holdsite.holdsite, result.holdsite.candidates[0]
    r, c = site.size[0] // 2, site.size[1] // 2
    assert np.all(image[site.row - r:site.row + r + 1, site.col - c:site.col + c + 1] == 255)
    r, c = other.size[0] // 2, other.size[1] // 2
    ring = image[other.row - r:other.row + r + 1, other.col - c:other.col + c + 1]
    assert np.all(ring[0] == 255) and not np.all(ring[r, c] == 255)
