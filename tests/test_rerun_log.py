"""``--rerun FILE.rrd``: read back with the Rerun SDK's own reader, not a viewer."""

import sys

import numpy as np
from rerun.chunk import RrdReader

from conftest import box_scene
from rangeseg_cli.cli.main import main


def _steps(rrd) -> dict[str, dict[int, object]]:
    """Per entity, the ``image`` time steps it was logged at (the text of ``/image``)."""
    out: dict[str, dict[int, object]] = {}
    for chunk in RrdReader(rrd).stream().to_chunks():
        batch = chunk.to_record_batch()
        if "image" not in batch.schema.names:
            continue
        values = (batch.column("TextDocument:text").to_pylist()
                  if chunk.entity_path == "/image" else [None] * chunk.num_rows)
        for step, value in zip(batch.column("image").to_pylist(), values, strict=True):
            out.setdefault(chunk.entity_path, {})[step] = value
    return out


def test_rerun_log_has_one_time_step_per_image_in_input_order_with_workers(
        runner, tmp_path, write_png):
    (tmp_path / "in").mkdir()
    names = ["a", "b", "c"]
    for k, name in enumerate(names):
        write_png(tmp_path / "in" / f"{name}.png", box_scene(64, noise=k).astype(np.uint8))
    out, rrd = tmp_path / "out", tmp_path / "batch.rrd"
    res = runner.invoke(main, ["run", str(tmp_path / "in"), "-o", str(out), "-j", "2", "-q",
                               "--rerun", str(rrd)])
    assert res.exit_code == 0, res.output
    steps = _steps(rrd)
    assert steps["/image"] == {0: ["a"], 1: ["b"], 2: ["c"]}
    for entity in ("/camera/depth", "/camera/labels", "/points", "/holdsite/footprint",
                   "/holdsite/approach"):
        assert sorted(steps[entity]) == [0, 1, 2], entity
    assert not list(tmp_path.glob(".*.tmp"))


def test_rerun_without_the_sdk_is_one_line_that_says_how_to_install_it(
        runner, box_png, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` raises ImportError
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1",
                               "--rerun", str(tmp_path / "x.rrd")])
    assert res.exit_code == 2
    assert "Traceback" not in res.output
    assert res.output.strip().splitlines() == [
        "Error: --rerun needs the Rerun SDK (rerun-sdk), which is not installed: "
        "pip install 'rangeseg[rerun]'"]
    assert not out.exists() and not (tmp_path / "x.rrd").exists()


def test_rerun_makes_the_missing_folders_and_refuses_a_store(runner, box_png, tmp_path):
    nested = tmp_path / "logs" / "night" / "x.rrd"
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), "-j", "1",
                               "-q", "--rerun", str(nested)])
    assert res.exit_code == 0, res.output
    assert list(_steps(nested)["/image"]) == [0]
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out2"), "-j", "1",
                               "--rerun", "s3://bucket/x.rrd"])
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        "Error: --rerun s3://bucket/x.rrd: a local file is needed (the Rerun SDK writes "
        "files, not objects of a store)"]
    assert not (tmp_path / "out2").exists()


def test_rerun_refuses_a_name_that_is_no_recording_before_any_work(runner, box_png, tmp_path):
    # `--rerun` wrote its log over the file it was given: the input image, the
    # intrinsics, an output of the batch.
    out = tmp_path / "out"
    before = box_png.read_bytes()
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "--rerun", str(box_png)])
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        f"Error: --rerun {box_png}: name the log FILE.rrd, as the Rerun viewer opens it "
        "(another name could be an input or output)"]
    other = tmp_path / "notes.rrd"
    other.write_text("my notes")
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "--rerun", str(other)])
    assert res.exit_code == 2
    assert res.output.strip().splitlines() == [
        f"Error: --rerun {other}: exists and is no Rerun recording; name a new file or "
        "remove it"]
    assert box_png.read_bytes() == before and other.read_text() == "my notes"
    assert not out.exists()
    log = tmp_path / "again.rrd"  # a recording is written over, as before
    for _ in range(2):
        res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "-q", "--overwrite",
                                   "--rerun", str(log)])
        assert res.exit_code == 0, res.output
    assert list(_steps(log)["/image"]) == [0]
