"""A batch stopped mid-image, images it never started, and one batch at a time in OUT."""

import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from conftest import box_scene, tree_bytes, wait_for_done
from rangeseg_cli.batch.outlock import LOCK

CLI = [sys.executable, "-m", "rangeseg_cli.cli.main", "run"]


@pytest.fixture
def folder(tmp_path, write_png):
    images = tmp_path / "in"
    images.mkdir()
    for i in range(16):
        z = box_scene(80, noise=1.0, seed=i)
        z[10 + i % 5: 18 + i % 5, 50:60] += 30.0
        write_png(images / f"s{i:02d}.png", z.clip(0, 255).astype(np.uint8))
    return images


def _wait_for(out, pattern, count, timeout=60.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and len(list(out.glob(pattern))) < count:
        time.sleep(0.02)
    assert len(list(out.glob(pattern))) >= count, f"no {pattern} in {out}"


def _slow_image(tmp_path, write_png):
    """A large face and a long footprint at every 0.5 degree: a minute or more of search."""
    z = np.full((384, 384), 20.0)
    z[42:342, 42:342] = 120.0
    z += np.random.default_rng(0).normal(0, 1.0, z.shape)
    return write_png(tmp_path / "big.png", z.clip(0, 255).astype(np.uint8))


SLOW = ["--set", "holdsite.size=[61,3]", "--set", "holdsite.rotation_step=0.5"]


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_images_a_stopped_batch_never_started_read_as_not_started(folder, tmp_path, spawn,
                                                                  jobs):
    # They stayed `running` in the manifest after Ctrl-C between images. A long
    # footprint turned every 2 degrees keeps each image at a tenth of a second or
    # more, so the batch is still going when the stop comes.
    out, fresh = tmp_path / "out", tmp_path / "fresh"
    cmd = [*CLI, str(folder), "-j", jobs, "-q", "--set", "holdsite.size=[21,3]",
           "--set", "holdsite.rotation_step=2"]
    proc = spawn([*cmd, "-o", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                 text=True)
    wait_for_done(out, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    status = [v["status"] for v in images.values()]
    assert status.count("done") >= 1
    assert status.count("running") <= int(jobs)  # the ones in progress at the stop, at most
    assert len(images) < 16  # the others: no entry, as before the batch
    res = subprocess.run([*cmd, "-o", str(out), "--resume"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert subprocess.run([*cmd, "-o", str(fresh)], capture_output=True).returncode == 0
    assert tree_bytes(out) == tree_bytes(fresh)


def test_a_stop_is_honoured_inside_one_long_image(tmp_path, spawn, write_png):
    # A long footprint at every 0.5 degree on a large face: the holdsite search takes
    # a minute or more; SIGTERM waited for it (the batch stopped between images only).
    image, out = _slow_image(tmp_path, write_png), tmp_path / "out"
    proc = spawn([*CLI, str(image), "-o", str(out), "-j", "1", "-q", *SLOW],
                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _wait_for(out, "*.labels.npy", 1, timeout=120)  # the holdsite search has begun
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    t0 = time.monotonic()
    _, err = proc.communicate(timeout=60)
    assert time.monotonic() - t0 < 15.0, err  # within a second or two when not loaded
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    assert images["big"]["status"] == "running"  # begun, not finished: --resume redoes it
    assert not (out / "big.holdsite.json").exists()


def test_a_second_run_into_the_same_folder_stops_at_once_naming_the_first(tmp_path, spawn,
                                                                          write_png):
    # Both runs processed every image, writing over each other's files. The first run
    # is held in a long holdsite search, so it cannot finish before the second starts.
    image, out = _slow_image(tmp_path, write_png), tmp_path / "out"
    first = spawn([*CLI, str(image), "-o", str(out), "-j", "1", "-q", *SLOW],
                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    _wait_for(out, "*.labels.npy", 1, timeout=120)
    res = subprocess.run([*CLI, str(image), "-o", str(out), "-j", "1", "-q", "--resume"],
                         capture_output=True, text=True, timeout=60)
    assert first.poll() is None, "the first run ended before the second one asked"
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "another batch is running into this folder" in lines[0]
    assert f"pid {first.pid} on {socket.gethostname()}, started " in lines[0]
    assert (out / LOCK).exists()
    first.send_signal(signal.SIGTERM)
    _, err = first.communicate(timeout=60)
    assert first.returncode == 143, err
    assert not (out / LOCK).exists()  # released on the way out


def test_a_lock_left_by_a_killed_run_is_taken_over(folder, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / LOCK).write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname(),
                                        "started": "2026-01-01 00:00:00 +0000",
                                        "command": "run"}))
    res = subprocess.run([*CLI, str(folder), "-o", str(out), "-j", "1", "-q", "--json"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    assert json.loads(res.stdout)["done"] == 16
    assert not (out / LOCK).exists()


def test_the_lock_is_held_in_this_process_too(folder, tmp_path):
    """The library's batch refuses a folder another batch of this process holds."""
    from rangeseg_cli.batch import outlock
    from rangeseg_cli.batch import runner as batch
    from rangeseg_cli.config import load_config
    from rangeseg_cli.errors import OutputError

    out = tmp_path / "out"
    jobs, _ = batch.jobs_from_inputs([str(folder)], out)
    with outlock.held(out, "edges"):
        with pytest.raises(OutputError, match=f"pid {os.getpid()} on"):
            batch.run_batch(jobs, out, load_config(), ("edges",), n_jobs=1)
    assert not (out / LOCK).exists() and not list(out.glob("*.npy"))
