"""Labelled point clouds (``--ply``): read back with plyfile and checked against the outputs."""

import errno
import json

import numpy as np
import pytest
from plyfile import PlyData

from conftest import box_scene
from rangeseg_cli.batch.pointcloud import holdsite_vertices
from rangeseg_cli.cli.main import main
from rangeseg_cli.config import InputConfig


def _xyz(vertex) -> np.ndarray:
    return np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float64)


def _run(runner, image, out, *more):
    res = runner.invoke(main, ["run", str(image), "-o", str(out), "-j", "1", "-q", *more])
    assert res.exit_code == 0, res.output
    return res


def test_points_ply_has_a_vertex_per_valid_labelled_pixel_with_its_label_and_height(
        runner, tmp_path, write_png):
    raw = box_scene(64).astype(np.uint8)
    raw[2:7, 50:60] = 255  # clipped: invalid
    out = tmp_path / "out"
    _run(runner, write_png(tmp_path / "box.png", raw), out, "--ply")
    labels, z = np.load(out / "box.labels.npy"), np.load(out / "box.range.npy")
    ply = PlyData.read(out / "box.points.ply")
    assert ply.text is False and ply.byte_order == "<"
    assert any("frame image" in c for c in ply.comments)
    v = ply["vertex"].data
    rows, cols = np.nonzero((labels > 0) & np.isfinite(z))
    assert len(v) == len(rows) < 64 * 64
    np.testing.assert_array_equal(v["row"], rows)
    np.testing.assert_array_equal(v["col"], cols)
    np.testing.assert_array_equal(v["label"], labels[rows, cols])
    np.testing.assert_allclose(_xyz(v), np.stack([cols, rows, z[rows, cols]], axis=1),
                               rtol=1e-6)
    # the box top and the table are level planes: every fitted normal is +height
    np.testing.assert_allclose(np.stack([v["nx"], v["ny"], v["nz"]], axis=1),
                               np.tile([0.0, 0.0, 1.0], (len(v), 1)), atol=1e-5)
    site = json.loads((out / "box.holdsite.json").read_text())["holdsite"]
    corners = _xyz(PlyData.read(out / "box.holdsite.ply")["vertex"].data)[:4]
    np.testing.assert_allclose(corners.mean(axis=0), [site["col"], site["row"],
                                                      site["elevation"]], atol=1e-4)


def test_camera_frame_points_are_the_back_projection_and_the_holdsite_centre_point_camera(
        runner, tmp_path):
    depth = np.full((64, 64), 0.8, dtype=np.float32)  # metres: a table at 0.8 m
    depth[20:44, 20:44] = 0.7  # a box 0.1 m high
    np.save(tmp_path / "cam.npy", depth)
    (tmp_path / "k.txt").write_text("500 0 31.5\n0 500 30\n0 0 1\n")
    out = tmp_path / "out"
    _run(runner, tmp_path / "cam.npy", out, "--preset", "metre-depth", "--intrinsics",
         str(tmp_path / "k.txt"), "--ply")
    v = PlyData.read(out / "cam.points.ply")["vertex"].data
    assert len(v) == 64 * 64
    d = depth[v["row"], v["col"]].astype(np.float64)
    expected = np.stack([(v["col"] - 31.5) * d / 500, (v["row"] - 30) * d / 500, d], axis=1)
    np.testing.assert_allclose(_xyz(v), expected, atol=1e-6)
    np.testing.assert_allclose(v["nz"], -1.0, atol=1e-5)  # the planes face the camera
    site = json.loads((out / "cam.holdsite.json").read_text())["holdsite"]
    ply = PlyData.read(out / "cam.holdsite.ply")
    assert any("metres" in c for c in ply.comments)
    hv = _xyz(ply["vertex"].data)
    np.testing.assert_allclose(hv[:4].mean(axis=0), site["point_camera"], atol=2e-6)
    np.testing.assert_allclose(hv[5], site["point_camera"], atol=2e-6)  # the arrow's tip
    assert np.allclose(hv[:4, 2], 0.7, atol=1e-6)  # the footprint lies on the box top
    side = np.linalg.norm(hv[1] - hv[0])
    np.testing.assert_allclose(side, site["size"][1] * 0.7 / 500, rtol=1e-5)
    arrow = hv[5] - hv[4]  # tail to tip: along approach_camera
    np.testing.assert_allclose(arrow / np.linalg.norm(arrow), site["approach_camera"],
                               atol=1e-5)
    assert [tuple(e) for e in ply["edge"].data][:4] == [(0, 1), (1, 2), (2, 3), (3, 0)]


def test_footprint_corners_lie_on_a_tilted_site_plane_around_its_centre():
    gx, gy = 0.5, -0.25  # dz/dcol, dz/drow
    n = np.array([-gx, -gy, 1.0]) / np.linalg.norm([-gx, -gy, 1.0])
    site = {"row": 10, "col": 20, "elevation": 50.0, "normal": n.tolist(), "size": [5, 9],
            "angle": 30.0}
    v = holdsite_vertices(site, InputConfig(units_per_pixel=2.0))
    corners, centre = v[:4], np.array([40.0, 20.0, 50.0])
    np.testing.assert_allclose(corners.mean(axis=0), centre, atol=1e-12)
    off = corners - centre
    np.testing.assert_allclose(off[:, 2], gx * off[:, 0] / 2 + gy * off[:, 1] / 2, atol=1e-12)
    np.testing.assert_allclose(np.hypot(off[:, 0], off[:, 1]), np.hypot(5, 9), atol=1e-12)
    tail = v[4] - v[5]  # the arrow stands on the normal in x, y = 2 col, 2 row; tip at the site
    up = np.array([-gx / 2, -gy / 2, 1.0])
    np.testing.assert_allclose(tail / np.linalg.norm(tail), up / np.linalg.norm(up), atol=1e-12)


def test_a_rerun_without_ply_removes_the_point_clouds_of_an_earlier_run(runner, box_png,
                                                                        tmp_path):
    out = tmp_path / "out"
    _run(runner, box_png, out, "--ply")
    assert (out / "box.points.ply").exists() and (out / "box.holdsite.ply").exists()
    _run(runner, box_png, out, "--overwrite")
    assert not list(out.glob("*.ply"))


@pytest.mark.parametrize("refused, code, line", [
    (".ply", 1, "box.points.ply: cannot write (Read-only file system)"),
    ("", 2, "rangeseg-run.json: cannot write (Read-only file system)"),  # all of OUT
])
def test_ply_on_a_read_only_output_is_one_line(runner, box_png, tmp_path, monkeypatch,
                                               refused, code, line):
    import rangeseg_cli.batch.io as rio

    real_replace = rio.os.replace

    def read_only(src, dst):
        if str(dst).endswith(refused):
            raise OSError(errno.EROFS, "Read-only file system")
        return real_replace(src, dst)

    monkeypatch.setattr(rio.os, "replace", read_only)
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1", "-q", "--ply"])
    assert res.exit_code == code
    assert "Traceback" not in res.output and "internal error" not in res.output
    assert res.output.strip().splitlines()[-1].endswith(line)
    assert not list(out.rglob("*.tmp")) and not list(out.rglob("*.ply"))


def test_grow_ply_adds_the_clouds_to_a_run_made_without(runner, box_png, tmp_path):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1", "-q"]
                         ).exit_code == 0
    edges = (out / "box.edges.npy").stat().st_mtime_ns
    res = runner.invoke(main, ["grow", str(out), "-j", "1", "-q", "--ply"])
    assert res.exit_code == 0, res.output
    labels = np.load(out / "box.labels.npy")
    assert PlyData.read(str(out / "box.points.ply"))["vertex"].count == np.count_nonzero(labels)
    assert (out / "box.edges.npy").stat().st_mtime_ns == edges  # the edges stayed current
    res = runner.invoke(main, ["holdsite", str(out), "-j", "1", "-q", "--ply"])
    assert res.exit_code == 0, res.output
    assert (out / "box.holdsite.ply").exists()
