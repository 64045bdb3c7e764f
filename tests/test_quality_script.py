"""Tests of benchmarks/quality.py's face widths (the ``--widths`` table of docs/QUALITY.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import quality  # noqa: E402


@pytest.mark.parametrize("thickness", [1, 3, 5, 7])
def test_a_band_has_its_thickness_as_width_whatever_its_length(thickness: int) -> None:
    for length in (20, 36):
        band = np.zeros((40, 40), bool)
        band[10:10 + thickness, 2:2 + length] = True
        assert quality.face_width(band) == thickness
        assert quality.face_width(band.T) == thickness


def test_an_even_thickness_rounds_down_to_the_odd_square_inside() -> None:
    band = np.zeros((30, 30), bool)
    band[5:9, 3:27] = True  # 4 thick: a 3x3 square fits, a 5x5 does not
    assert quality.face_width(band) == 3


def test_a_face_at_the_image_border_is_measured_against_the_border() -> None:
    face = np.zeros((20, 20), bool)
    face[:, :4] = True  # 4 wide along the left edge: the widest square is 3x3
    assert quality.face_width(face) == 3
    assert quality.face_width(np.ones((9, 9), bool)) == 9
    assert quality.face_width(np.zeros((5, 5), bool)) == 0


def test_width_classes_cover_every_width_once() -> None:
    classes = [quality.width_class(w) for w in range(1, 14)]
    assert classes[:3] == ["1-3"] * 3
    assert classes[3:5] == ["4-5"] * 2
    assert classes[5:9] == ["6-9"] * 4
    assert set(classes[9:]) == {">=10"}
