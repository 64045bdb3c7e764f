"""Inputs a newcomer's folders hold (issue 34): link loops, names like outputs, files that
are not what their names say, names that are not UTF-8, filters; a manifest checked field by
field, and ``--json`` that always prints an object. Each ends in one clear line."""

import json

import numpy as np
import pytest

from conftest import box_scene
from rangeseg_cli.cli.main import main
from rangeseg_cli.config import SETTING_BYTES


def no_traceback(res) -> None:
    assert "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)


# --------------------------------------------------------------------------- manifest (6)


@pytest.mark.parametrize("damage, problem", [
    (lambda m: m | {"images": {"box": m["images"]["box"] | {"status": "bogus"}}},
     "\"images\" entry 'box': \"status\" is \"bogus\"; allowed: \"done\", \"failed\", "
     "\"running\""),
    (lambda m: m | {"images": {"box": {}}},
     "\"images\" entry 'box': \"status\" is missing; allowed: \"done\", \"failed\", "
     "\"running\""),
    (lambda m: {k: v for k, v in m.items() if k != "config"},
     '"config" is missing; rangeseg writes it in every manifest'),
    (lambda m: {k: v for k, v in m.items() if k != "images"},
     '"images" is missing; rangeseg writes it in every manifest'),
])
def test_a_manifest_with_a_bad_status_or_no_config_stops_with_one_line(runner, box_png,
                                                                         tmp_path, damage,
                                                                         problem):
    out = tmp_path / "out"
    assert runner.invoke(main, ["run", str(box_png), "-o", str(out), "-j", "1"]).exit_code == 0
    path = out / "rangeseg-run.json"
    path.write_text(json.dumps(damage(json.loads(path.read_text()))))
    before = path.read_bytes()
    res = runner.invoke(main, ["run", str(box_png), "-o", str(out), "--resume", "-j", "1"])
    no_traceback(res)
    assert res.exit_code == 2
    assert res.output.strip().splitlines()[-1] == (
        f"Error: {path}: not a manifest of rangeseg ({problem}); repair it, or delete it and "
        "redo the images with --overwrite")
    assert path.read_bytes() == before


# --------------------------------------------------------------------------- link loop (1)


def test_a_symlink_loop_in_an_input_folder_fails_alone(runner, tmp_path, write_png):
    folder = tmp_path / "in"
    folder.mkdir()
    write_png(folder / "good.png", box_scene(48).astype(np.uint8))
    (folder / "a.png").symlink_to("b.png")
    (folder / "b.png").symlink_to("a.png")
    out = tmp_path / "out"
    res = runner.invoke(main, ["run", str(folder), "-o", str(out), "-j", "1", "-q", "--json"])
    no_traceback(res)
    assert res.exit_code == 1
    for name in ("a.png", "b.png"):
        assert (f"{folder / name}: a symbolic link loop (the link leads back to itself), "
                "not an image") in res.stderr
    summary = json.loads(res.stdout)
    assert summary["done"] == 1 and sorted(summary["errors"]) == ["a", "b"]
    assert (out / "good.holdsite.json").is_file()


def test_a_symlink_loop_named_as_input_is_one_line_exit_2(runner, tmp_path):
    (tmp_path / "a.png").symlink_to("a.png")
    res = runner.invoke(main, ["run", str(tmp_path / "a.png"), "-o", str(tmp_path / "out")])
    no_traceback(res)
    assert res.exit_code == 2
    assert "a.png: a symbolic link loop" in res.output.strip().splitlines()[-1]


# --------------------------------------------------------------------------- read errors (4)


def test_png_bytes_named_npy_say_what_they_are_not_numpys_pickle_hint(tmp_path, box_png):
    from rangeseg_cli.batch import io
    from rangeseg_cli.errors import InputError

    fake = tmp_path / "x.npy"
    fake.write_bytes(box_png.read_bytes())
    with pytest.raises(InputError) as info:
        io.read_image(fake)
    assert str(info.value) == (f"{fake}: not a readable image (it holds PNG data, not NPY as "
                               "its extension .npy says; rangeseg picks the reader by the "
                               "extension: rename it to .png)")
    np.save(tmp_path / "objects.npy", np.array([{}, 1], dtype=object))
    with pytest.raises(InputError, match=r"objects.npy: not a readable image \(an NPY array "
                                         r"of Python objects, which rangeseg never loads"):
        io.read_image(tmp_path / "objects.npy")


def test_a_corrupt_tiff_is_one_line_without_tifffiles_own(runner, tmp_path, caplog):
    import tifffile

    tifffile.imwrite(tmp_path / "good.tif", np.zeros((32, 32), np.uint16))
    data = (tmp_path / "good.tif").read_bytes()
    (tmp_path / "bad.tif").write_bytes(data[:8] + bytes(200))  # the header, then zeros
    res = runner.invoke(main, ["run", str(tmp_path / "bad.tif"), "-o", str(tmp_path / "out"),
                               "-j", "1", "-q"])
    no_traceback(res)
    assert res.exit_code == 1
    assert res.stderr == (f"{tmp_path / 'bad.tif'}: not a readable image (a damaged or "
                          "truncated TIFF file: no image data tifffile can decode)\n")
    assert not [r for r in caplog.records if r.name.startswith("tifffile")]


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="no named pipes")
def test_a_fifo_named_png_is_named_a_fifo_and_never_opened(runner, tmp_path, box_png):
    import os

    folder = tmp_path / "in"
    folder.mkdir()
    os.mkfifo(folder / "pipe.png")  # opening it to read would wait for a writer forever
    (folder / "box.png").write_bytes(box_png.read_bytes())
    res = runner.invoke(main, ["run", str(folder), "-o", str(tmp_path / "out"), "-j", "1",
                               "-q"])
    no_traceback(res)
    assert res.exit_code == 1
    assert res.stderr == (f"{folder / 'pipe.png'}: a named pipe (FIFO), not a regular file; "
                          "rangeseg reads image files: PNG, PGM/PNM, TIFF or NPY\n")
    res = runner.invoke(main, ["run", str(folder / "pipe.png"), "-o", str(tmp_path / "o2")])
    assert res.exit_code == 2
    assert "pipe.png: a named pipe (FIFO), not a file or folder" in res.output


def _unblock_later(fifo) -> None:
    """Open ``fifo`` for writing in 10 s and close it: a reader that waits is freed then."""
    import threading
    import time

    def late() -> None:
        time.sleep(10)
        with open(fifo, "wb"):
            pass

    threading.Thread(target=late, daemon=True).start()


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo"), reason="no named pipes")
@pytest.mark.parametrize("option, what", [
    ("--config", "nothing was written to, not a config file; name a TOML file"),
    ("--intrinsics", "nothing was written to, not an intrinsics file; allowed:")])
def test_a_named_pipe_nobody_writes_to_is_refused_without_waiting(runner, tmp_path, box_png,
                                                                  option, what):
    # reading --config or --intrinsics from a named pipe waited for a writer forever
    import os

    os.mkfifo(tmp_path / "pipe")
    _unblock_later(tmp_path / "pipe")  # a reader that waits gets an empty file at 10 s
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"),
                               option, str(tmp_path / "pipe")])
    no_traceback(res)
    assert res.exit_code == 2
    assert f"{tmp_path / 'pipe'}: a named pipe (FIFO) {what}" in res.output
    assert not (tmp_path / "out").exists()


@pytest.mark.skipif(not hasattr(__import__("os"), "pipe"), reason="no pipes")
def test_settings_from_a_pipe_with_a_writer_are_read(runner, tmp_path, box_png):
    # --config <(...) and --config /dev/stdin: a pipe the shell writes to
    import os

    read, write = os.pipe()
    os.write(write, b"[holdsite]\nrotation_step = 5\n")
    os.close(write)
    try:
        res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), "-q",
                                   "--config", f"/dev/fd/{read}"])
    finally:
        os.close(read)
    assert res.exit_code == 0, res.output
    manifest = json.loads((tmp_path / "out" / "rangeseg-run.json").read_text())
    assert manifest["config"]["holdsite"]["rotation_step"] == 5.0
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "null"), "-q",
                               "--config", os.devnull])  # empty: every default
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "zero"),
                               "--config", "/dev/zero"])  # never ends: refused
    assert res.exit_code == 2 and "/dev/zero: a character device, not a config" in res.output


@pytest.mark.skipif(not hasattr(__import__("os"), "mkfifo")
                    or not __import__("os").path.isdir("/dev/fd"), reason="no named pipes")
def test_reading_a_settings_pipe_leaves_no_descriptor_open(tmp_path, monkeypatch):
    # a FIFO that became a folder between its stat and its open leaked a descriptor
    import os

    from rangeseg_cli import config
    from rangeseg_cli.errors import ConfigError

    os.mkfifo(tmp_path / "pipe")
    _unblock_later(tmp_path / "pipe")
    folder = tmp_path / "folder"
    folder.mkdir()
    before = len(os.listdir("/dev/fd"))
    with pytest.raises(ConfigError, match="nothing was written to"):
        config.read_toml(tmp_path / "pipe")
    monkeypatch.setattr(config, "special_file", lambda path: "a named pipe (FIFO)")
    with pytest.raises(ConfigError) as err:
        config.read_toml(folder)
    assert str(err.value) == f"{folder}: cannot read config file (Is a directory)"
    assert len(os.listdir("/dev/fd")) == before


@pytest.mark.skipif(not hasattr(__import__("os"), "pipe"), reason="no pipes")
@pytest.mark.parametrize("option, what", [("--config", "a config file; name a TOML file"),
                                          ("--intrinsics", "an intrinsics file; allowed:")])
def test_a_settings_file_or_pipe_beyond_a_mib_is_refused_not_read_to_its_end(
        runner, tmp_path, box_png, option, what):
    # --config <(yes) read until memory ran out; a huge file was read whole
    import os
    import threading

    big = tmp_path / "big.toml"
    big.write_bytes(b"#" * (SETTING_BYTES + 1))
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), option,
                               str(big)])
    no_traceback(res)
    assert res.exit_code == 2
    assert f"{big}: more than 1 MiB, not {what}" in res.output
    read, write = os.pipe()  # --config <(yes): a pipe whose writer never stops

    written = [0]

    def endless() -> None:  # stops at 16 MiB, so a reader without a limit fails, not hangs
        try:
            for _ in range(2048):
                written[0] += os.write(write, b"y\n" * 4096)
        except OSError:  # the read end closed: as `yes`, stop
            pass
        finally:
            os.close(write)

    writer = threading.Thread(target=endless, daemon=True)
    writer.start()
    try:
        res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), option,
                                   f"/dev/fd/{read}"])
    finally:
        os.close(read)
    writer.join(timeout=10)
    assert written[0] < 4 * SETTING_BYTES  # the reader stopped at the limit
    no_traceback(res)
    assert res.exit_code == 2
    assert f"/dev/fd/{read}: more than 1 MiB, not {what}" in res.output
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------------------- names like outputs (3)


def test_frames_named_like_outputs_are_read_when_no_run_wrote_them(runner, tmp_path, box_png):
    folder = tmp_path / "in"
    folder.mkdir()
    for name in ("cam.step.png", "tote.labels.png"):  # a camera's names, no manifest here
        (folder / name).write_bytes(box_png.read_bytes())
    res = runner.invoke(main, ["edges", str(folder), "-o", str(tmp_path / "out"), "-j", "1",
                               "-q", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["done"] == 2 and summary["not_images"] == 0
    assert (tmp_path / "out" / "cam.step.edges.npy").is_file()


def test_outputs_an_earlier_run_wrote_and_ground_truth_are_not_read(runner, tmp_path, box_png):
    folder = tmp_path / "in"
    (folder / "sub").mkdir(parents=True)
    (folder / "sub" / "box.png").write_bytes(box_png.read_bytes())
    np.save(folder / "sub" / "box.gt.npy", np.zeros((48, 48), np.int32))  # rangeseg synth's
    first = runner.invoke(main, ["edges", str(folder), "-o", str(folder / "old"), "-j", "1"])
    assert first.exit_code == 0, first.output
    res = runner.invoke(main, ["edges", str(folder), "-o", str(tmp_path / "out"), "-j", "1",
                               "-q", "--json"])  # old/ is searched now: its manifest says
    assert res.exit_code == 0, res.output
    summary = json.loads(res.stdout)
    assert summary["done"] == 1  # sub/box only; old/sub/box.* were written by rangeseg
    assert summary["not_images"] == 7  # 5 outputs, the manifest and the ground truth


# --------------------------------------------------------------------------- filters (10)


@pytest.fixture
def camera_folder(tmp_path, box_png):
    """Depth frames with a mask beside each, in two camera folders, and a masks folder."""
    folder = tmp_path / "in"
    for cam in ("cam1", "cam2"):
        (folder / cam / "masks").mkdir(parents=True)
        np.save(folder / cam / "frame_0_depth.npy", box_scene(48))
        (folder / cam / "frame_0_mask.png").write_bytes(box_png.read_bytes())
        (folder / cam / "masks" / "m.png").write_bytes(box_png.read_bytes())
    return folder


@pytest.mark.parametrize("args, done", [
    (["--exclude", "*_mask.png", "--exclude", "masks"],
     ["cam1/frame_0_depth", "cam2/frame_0_depth"]),
    (["--include", "*_depth.npy"], ["cam1/frame_0_depth", "cam2/frame_0_depth"]),
    (["--include", "cam1/**", "--exclude", "*_mask.png"],
     ["cam1/frame_0_depth", "cam1/masks/m"]),
    (["--include", "cam1/*.png", "--include", "/cam2/masks"],
     ["cam1/frame_0_mask", "cam2/masks/m"]),
    (["--include", "*_depth.npy", "--exclude", "cam2"], ["cam1/frame_0_depth"]),
])
def test_include_and_exclude_globs_choose_the_files_of_a_folder(runner, camera_folder,
                                                               tmp_path, args, done):
    out = tmp_path / "out"
    res = runner.invoke(main, ["edges", str(camera_folder), "-o", str(out), "-j", "1", "-q",
                               "--json", *args])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["done"] == len(done)
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert sorted(manifest["images"]) == done


def test_filters_leave_a_named_file_alone_and_say_when_they_leave_nothing(runner,
                                                                       camera_folder,
                                                                       tmp_path):
    mask = camera_folder / "cam1" / "frame_0_mask.png"
    res = runner.invoke(main, ["edges", str(mask), "-o", str(tmp_path / "out"), "-j", "1",
                               "-q", "--exclude", "*_mask.png"])
    assert res.exit_code == 0, res.output
    res = runner.invoke(main, ["run", str(camera_folder), "-o", str(tmp_path / "o2"),
                               "--include", "*.tif"])
    assert res.exit_code == 2
    assert "no range images found" in res.output and "--include/--exclude" in res.output
    res = runner.invoke(main, ["run", str(camera_folder), "-o", str(tmp_path / "o2"),
                               "--exclude", ""])
    assert res.exit_code == 2 and "an empty glob" in res.output


# --------------------------------------------------------------------------- --json (8)


@pytest.mark.parametrize("args, message", [
    (["run", "--json", "-o", "{tmp}/out"], "Missing argument 'INPUTS...'."),
    (["run", "{tmp}/nothere", "-o", "{tmp}/out", "--json"], "{tmp}/nothere: no such file or "
                                                             "folder"),
    (["grow", "{tmp}/out", "--json", "--jobs", "0"], None),
    (["eval", "{tmp}", "--json"], "Missing argument 'GT_DIR'."),
])
def test_json_prints_one_object_on_a_usage_error(runner, tmp_path, args, message):
    res = runner.invoke(main, [a.format(tmp=tmp_path) for a in args])
    assert res.exit_code == 2
    data = json.loads(res.stdout)  # one object, nothing else on stdout
    assert data["exit_code"] == 2 and data["error"]
    if message is not None:
        assert data["error"] == message.format(tmp=tmp_path)
    assert "Error:" in res.stderr  # the line on stderr stays


def test_json_prints_one_object_on_ctrl_c_before_the_first_image(runner, box_png, tmp_path,
                                                                 monkeypatch):
    import rangeseg_cli.cli.main as cli

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C while IMAGES are listed

    monkeypatch.setattr(cli, "_input_jobs", interrupted)
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out"), "--json"])
    assert res.exit_code == 130
    assert json.loads(res.stdout) == {"error": "interrupted", "exit_code": 130,
                                      "interrupted": True}
    res = runner.invoke(main, ["run", str(box_png), "-o", str(tmp_path / "out")])
    assert res.exit_code == 130 and res.stdout == ""  # without --json: nothing on stdout


# --------------------------------------------------------------------------- names (5)


@pytest.fixture
def latin1_folder(tmp_path, box_png):
    """A Latin-1 name (no UTF-8) of a good image, one of a bad image, a UTF-8 name with %."""
    import os

    folder = tmp_path / "in"
    folder.mkdir()
    try:
        (folder / os.fsdecode(b"caf\xe9.png")).write_bytes(box_png.read_bytes())
        (folder / os.fsdecode(b"bad\xff.png")).write_bytes(b"not an image")
    except (OSError, UnicodeError):
        pytest.skip("this file system takes UTF-8 names only")
    (folder / "d\u00e9j\u00e0 100%.png").write_bytes(box_png.read_bytes())
    return folder


def test_names_that_are_not_utf8_are_percent_encoded_and_resumed(runner, latin1_folder,
                                                                  tmp_path):
    import os
    from urllib.parse import unquote_to_bytes

    out = tmp_path / "out"
    args = ["edges", str(latin1_folder), "-o", str(out), "-j", "1", "-q", "--json"]
    res = runner.invoke(main, args)
    assert res.exit_code == 1
    assert "\\udc" not in res.stdout
    summary = json.loads(res.stdout)
    assert list(summary["errors"]) == ["bad%FF"] and summary["percent_encoded"] == ["bad%FF"]
    text = (out / "rangeseg-run.json").read_text()
    assert "\\udc" not in text  # no lone surrogates, which jq and node turn into U+FFFD
    images = json.loads(text)["images"]
    assert sorted(images) == ["bad%FF", "caf%E9", "d\u00e9j\u00e0 100%"]  # UTF-8 as given
    cafe = images["caf%E9"]
    assert cafe["name_encoding"] == "percent"
    assert "name_encoding" not in images["d\u00e9j\u00e0 100%"]
    assert unquote_to_bytes(cafe["input"]) == os.fsencode(latin1_folder) + b"/caf\xe9.png"
    res = runner.invoke(main, [*args, "--resume"])
    assert json.loads(res.stdout)["resumed"] == 2  # matched by name: not redone
    res = runner.invoke(main, ["link", str(out), "-j", "1", "-q", "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["done"] == 2, res.output
