"""Batch behaviour: bad inputs, atomic outputs, resume after SIGKILL, --jobs, stage identity."""

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from conftest import box_scene, tree_bytes, wait_for_done
from rangeseg_cli import load_config, run_pipeline
from rangeseg_cli.cli.main import main
from rangeseg_cli.errors import InputError


def scene(i: int, size: int = 48) -> np.ndarray:
    z = box_scene(size, noise=1.0, seed=i)
    z[10 + i % 5: 18 + i % 5, 30:40] += 30.0  # a second block, moving with i
    return z.clip(0, 255).astype(np.uint8)


@pytest.fixture
def good_folder(tmp_path, write_png):
    folder = tmp_path / "good"
    folder.mkdir()
    for i in range(4):
        write_png(folder / f"img{i}.png", scene(i))
    return folder


def test_mixed_folder_reports_each_bad_file_once_and_does_the_rest(tmp_path, write_png):
    folder = tmp_path / "mixed"
    folder.mkdir()
    write_png(folder / "good1.png", scene(1))
    write_png(folder / "good2.png", scene(2))
    (folder / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"x" * 50)
    (folder / "empty.png").write_bytes(b"")
    write_png(folder / "rgb.png", np.zeros((32, 32, 3), np.uint8))
    write_png(folder / "tiny.png", np.zeros((2, 2), np.uint8))
    np.save(folder / "cube.npy", np.zeros((20, 20, 3, 2)))
    np.save(folder / "nan.npy", np.full((32, 32), np.nan))
    (folder / "notes.txt").write_text("skip me")
    out = tmp_path / "out"
    res = CliRunner().invoke(main, ["run", str(folder), "-o", str(out), "--jobs", "1", "-q"])
    assert res.exit_code == 1, res.output
    lines = res.output.strip().splitlines()
    bad = ["corrupt.png", "empty.png", "rgb.png", "tiny.png", "cube.npy", "nan.npy"]
    for name in bad:
        assert sum(name in line for line in lines) == 1, (name, lines)
    assert "Traceback" not in res.output
    for good in ("good1", "good2"):
        assert (out / f"{good}.labels.npy").exists() and (out / f"{good}.holdsite.json").exists()
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    statuses = {k: v["status"] for k, v in manifest["images"].items()}
    assert statuses["good1"] == "done" and statuses["corrupt"] == "failed"
    assert sum(s == "failed" for s in statuses.values()) == len(bad)
    assert manifest["summary"]["not_images"] == 1


def test_json_summary_on_stdout(good_folder, tmp_path):
    res = CliRunner().invoke(main, ["run", str(good_folder), "-o", str(tmp_path / "o"),
                                    "--jobs", "1", "-q", "--json"])
    assert res.exit_code == 0
    summary = json.loads(res.output)
    assert summary["done"] == 4 and summary["failed"] == 0 and "edges" in summary["stage_seconds"]


def test_stages_one_by_one_give_the_same_bytes_as_run(good_folder, tmp_path):
    runner = CliRunner()
    whole, staged = tmp_path / "whole", tmp_path / "staged"
    assert runner.invoke(main, ["run", str(good_folder), "-o", str(whole), "-j", "1", "-q"]).exit_code == 0
    assert runner.invoke(main, ["edges", str(good_folder), "-o", str(staged), "-j", "1", "-q"]).exit_code == 0
    for stage in ("link", "grow", "holdsite"):
        res = runner.invoke(main, [stage, str(staged), "-j", "1", "-q"])
        assert res.exit_code == 0, res.output
    a, b = tree_bytes(whole), tree_bytes(staged)
    assert a.keys() == b.keys() and len(a) == 4 * 13
    assert all(a[k] == b[k] for k in a)


def test_jobs_2_gives_the_same_bytes_as_jobs_1(good_folder, tmp_path):
    runner = CliRunner()
    for n in ("1", "2"):
        res = runner.invoke(main, ["run", str(good_folder), "-o", str(tmp_path / n), "-j", n, "-q"])
        assert res.exit_code == 0, res.output
    assert tree_bytes(tmp_path / "1") == tree_bytes(tmp_path / "2")


def test_inputs_are_never_modified_and_out_inside_input_is_not_reread(good_folder):
    before = tree_bytes(good_folder)
    out = good_folder / "results"
    runner = CliRunner()
    assert runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q"]).exit_code == 0
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q", "--json",
                               "--overwrite"])
    assert json.loads(res.output)["done"] == 4  # the PNGs in results/ were not read as inputs
    after = {k: v for k, v in tree_bytes(good_folder).items() if not k.startswith("results/")}
    assert after == before


def _many(tmp_path, write_png, count: int):
    """A folder of ``count`` 96x96 scenes, for batches long enough to be signalled."""
    folder = tmp_path / "many"
    folder.mkdir()
    for i in range(count):
        write_png(folder / f"s{i:02d}.png", scene(i, size=96))
    return folder


def _two_workers(pid: int) -> set[int]:
    """The two worker processes of the batch ``pid``, once both run (60 s at most)."""
    deadline = time.monotonic() + 60
    workers: set[int] = set()
    while time.monotonic() < deadline and len(workers) < 2:
        workers = _children(pid)
        time.sleep(0.02)
    assert len(workers) == 2
    return workers


def test_resume_after_sigkill_completes_with_identical_bytes(tmp_path, write_png, spawn):
    folder = _many(tmp_path, write_png, 24)
    ref, out = tmp_path / "ref", tmp_path / "out"
    cmd = [sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder), "-j", "1", "-q"]
    subprocess.run([*cmd, "-o", str(ref)], check=True, capture_output=True)
    proc = spawn([*cmd, "-o", str(out)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    wait_for_done(out, proc)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    done_before = len(list(out.glob("*.holdsite.json")))
    assert 1 <= done_before < 24, "the run was not killed part-way"
    res = subprocess.run([*cmd, "-o", str(out), "--resume", "--json"], capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["done"] + summary["resumed"] == 24 and summary["done"] < 24
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    assert tree_bytes(out) == tree_bytes(ref)


def test_resume_redoes_images_made_with_another_config(good_folder, tmp_path):
    runner = CliRunner()
    out = tmp_path / "o"
    runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q"])
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q", "--resume", "--json"])
    assert json.loads(res.output)["resumed"] == 4
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q", "--resume",
                               "--json", "--set", "step.threshold=7"])
    assert json.loads(res.output)["done"] == 4


@pytest.mark.parametrize("jobs", ["1", "2"])
@pytest.mark.parametrize(("setting", "redone"), [
    ("holdsite.max_tilt=30", ["holdsite"]),
    ("grow.min_error=0.3", ["grow", "holdsite"]),
    # link writes the linked edges over edges.npy: its input is gone, all is redone
    ("link.min_component=40", ["edges", "link", "grow", "holdsite"]),
])
def test_resume_redoes_an_image_from_its_first_stage_out_of_date(good_folder, tmp_path, jobs,
                                                                  setting, redone):
    # A new holdsite setting redid edges, link and grow too (50 s on a 5 MP frame); the
    # files of the stages before stay, and the results are those of a fresh run.
    runner = CliRunner()
    out, fresh = tmp_path / "o", tmp_path / "fresh"
    run = ["run", str(good_folder), "-j", jobs, "-q"]
    runner.invoke(main, [*run, "-o", str(out)])
    stamps = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    res = runner.invoke(main, [*run, "-o", str(out), "--resume", "--json", "--set", setting])
    summary = json.loads(res.output)
    assert res.exit_code == 0 and summary["done"] == 4
    assert sorted(summary["stage_seconds"]) == sorted(redone)
    rewritten = {p.name.split(".", 1)[1] for p in out.iterdir()
                 if p.name != "rangeseg-run.json" and p.stat().st_mtime_ns != stamps[p.name]}
    kept = {"range.npy", "edges.npy", "components.npy"} if "edges" not in redone else set()
    assert not rewritten & kept and "holdsite.json" in rewritten
    assert ("labels.npy" in rewritten) == ("grow" in redone)
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    assert all(e["stages"] == ["edges", "link", "grow", "holdsite"] and "noise_sigma" in e
               and "input_stamp" in e for e in images.values())
    again = runner.invoke(main, [*run, "-o", str(out), "--resume", "--json", "--set", setting])
    assert json.loads(again.output)["resumed"] == 4
    runner.invoke(main, [*run, "-o", str(fresh), "--set", setting])
    assert {k: v for k, v in tree_bytes(out).items() if k != "rangeseg-run.json"} == \
        {k: v for k, v in tree_bytes(fresh).items() if k != "rangeseg-run.json"}


def test_resume_redoes_an_image_whose_input_was_replaced(good_folder, tmp_path, write_png):
    """A frame replaced under the same name (cron over a camera folder) is not kept as done."""
    runner = CliRunner()
    out = tmp_path / "o"
    runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q"])
    before = np.load(out / "img2.labels.npy")
    new = scene(0)[::-1].copy()  # other content, same name and size
    write_png(good_folder / "img2.png", new)
    stat = os.stat(good_folder / "img2.png")
    os.utime(good_folder / "img2.png", ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q", "--resume", "--json"])
    summary = json.loads(res.output)
    assert res.exit_code == 0 and (summary["done"], summary["resumed"]) == (1, 3)
    after = np.load(out / "img2.labels.npy")
    assert not np.array_equal(after, before)
    np.testing.assert_array_equal(after, run_pipeline(new).labels)
    entry = json.loads((out / "rangeseg-run.json").read_text())["images"]["img2"]
    stamp = os.stat(good_folder / "img2.png")
    assert entry["input_stamp"] == f"{stamp.st_size}:{stamp.st_mtime_ns}"


def test_resume_redoes_an_image_whose_entry_has_no_input_stamp(good_folder, tmp_path):
    """A manifest that cannot vouch for the input's version (written before stamps) is redone."""
    runner = CliRunner()
    out = tmp_path / "o"
    runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q"])
    manifest = out / "rangeseg-run.json"
    data = json.loads(manifest.read_text())
    del data["images"]["img1"]["input_stamp"]
    manifest.write_text(json.dumps(data))
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-j", "1", "-q", "--resume", "--json"])
    summary = json.loads(res.output)
    assert (summary["done"], summary["resumed"]) == (1, 3)
    assert "input_stamp" in json.loads(manifest.read_text())["images"]["img1"]


def test_a_stage_command_keeps_the_input_stamp_of_its_image(good_folder, tmp_path):
    runner = CliRunner()
    out = tmp_path / "o"
    assert runner.invoke(main, ["edges", str(good_folder), "-o", str(out), "-q"]).exit_code == 0
    stamps = {k: v["input_stamp"] for k, v in
              json.loads((out / "rangeseg-run.json").read_text())["images"].items()}
    assert runner.invoke(main, ["link", str(out), "-q"]).exit_code == 0
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    assert {k: v["input_stamp"] for k, v in images.items()} == stamps
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-q", "--resume", "--json"])
    assert json.loads(res.output)["done"] == 4  # grow and holdsite were missing
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(out), "-q", "--resume", "--json"])
    assert json.loads(res.output)["resumed"] == 4


arrays = hnp.arrays(
    dtype=st.sampled_from([np.uint8, np.uint16, np.int32, np.float32, np.float64, np.bool_]),
    shape=st.one_of(hnp.array_shapes(min_dims=1, max_dims=4, min_side=1, max_side=40),
                    st.tuples(st.integers(16, 40), st.integers(16, 40))),
    elements=None)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(arrays)
def test_run_pipeline_gives_a_result_or_a_clean_input_error(array):
    try:
        result = run_pipeline(array)
    except InputError as exc:
        assert "\n" not in str(exc)
        return
    assert result.labels.shape == result.edges.shape == np.squeeze(array).shape[:2]
    assert result.labels.dtype == np.int32 and result.edges.dtype == np.uint8
    invalid = np.isnan(result.heights)
    assert not result.labels[invalid].any() and not result.edges[invalid].any()
    assert result.holdsite is not None


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.0, 0.6))
def test_random_nan_patterns_never_leak_into_labels(seed, frac):
    rng = np.random.default_rng(seed)
    z = box_scene(32, noise=1.0, seed=seed)
    z[rng.random(z.shape) < frac] = np.nan
    z[rng.random(z.shape) < 0.01] = np.inf
    for fill in (0, 4):  # [input] fill_holes: holes as given, or the small ones filled
        try:
            result = run_pipeline(z, load_config(overrides={"input": {"fill_holes": fill}}))
        except InputError:
            return
        bad = ~np.isfinite(result.heights)
        assert not result.labels[bad].any() and not result.edges[bad].any()
        kept = ~np.isfinite(z)
        assert (bad == kept).all() if fill == 0 else not (bad & ~kept).any()


@pytest.mark.parametrize(("jobs", "signum", "code", "said"), [
    ("1", signal.SIGINT, 130, "interrupted:"), ("2", signal.SIGINT, 130, "interrupted:"),
    # `timeout`, `docker stop`, a scheduler's time limit: the manifest was left behind
    ("2", signal.SIGTERM, 143, "terminated (SIGTERM):"),
])
def test_ctrl_c_stops_cleanly_keeps_what_is_done_and_says_how_to_resume(tmp_path, write_png,
                                                                        spawn, jobs, signum,
                                                                        code, said):
    folder = _many(tmp_path, write_png, 30)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder), "-j", jobs, "-q"]
    proc = spawn([*cmd, "-o", str(out)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    wait_for_done(out, proc)
    proc.send_signal(signum)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert said in err and "--resume" in err and "Traceback" not in err
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    done = [k for k, v in manifest["images"].items() if v["status"] == "done"]
    assert 1 <= len(done) < 30
    # the count said is the count recorded (with -j 2 an image was finished twice)
    assert f"{said} {len(done)} images done and kept" in err
    assert all((out / f"{k}.holdsite.json").exists() for k in done)
    res = subprocess.run([*cmd, "-o", str(out), "--resume", "--json"], capture_output=True, text=True)
    assert res.returncode == 0 and json.loads(res.stdout)["resumed"] >= len(done)


def test_a_run_killed_with_new_settings_leaves_nothing_certified_under_the_old(
        tmp_path, write_png, spawn):
    # SIGKILL (an OOM killer, power loss) lands between writing an image's files and the
    # next write of the manifest: those images used to keep their entries of the old
    # settings, and --resume with the old settings kept their new files, exit 0.
    folder = _many(tmp_path, write_png, 24)
    out, fresh = tmp_path / "out", tmp_path / "fresh"
    cmd = [sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder), "-j", "1", "-q"]
    assert subprocess.run([*cmd, "-o", str(out)], capture_output=True).returncode == 0
    before = {p: p.stat().st_mtime_ns for p in out.glob("*.holdsite.json")}
    proc = spawn([*cmd, "-o", str(out), "--overwrite", "--set", "step.threshold=8"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and sum(
            p.stat().st_mtime_ns != t for p, t in before.items() if p.exists()) < 3:
        time.sleep(0.01)
    proc.kill()
    proc.wait(timeout=30)
    manifest = json.loads((out / "rangeseg-run.json").read_text())
    assert any(v["status"] == "running" for v in manifest["images"].values())
    res = subprocess.run([*cmd, "-o", str(out), "--resume"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert subprocess.run([*cmd, "-o", str(fresh)], capture_output=True).returncode == 0
    assert tree_bytes(out) == tree_bytes(fresh)


def _children(pid: int) -> set[int]:
    """Pids of the processes ``pid`` forked (Linux ``/proc``), but the compile helper.

    A batch whose warm-up finds a deferred kernel not yet cached starts the
    helper that compiles it (``rangeseg_cli.kernels.cache``): not a worker.
    """
    kids: set[int] = set()
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except FileNotFoundError:  # the process has ended
        return kids
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children") as fh:
                kids.update(int(k) for k in fh.read().split())
        except (FileNotFoundError, ProcessLookupError):  # the thread ended since the listing
            continue
    return {k for k in kids if not _compile_helper(k)}


def _compile_helper(pid: int) -> bool:
    """Whether process ``pid`` is the kernel cache's compile helper (its command line)."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return b"compile_ahead" in fh.read()
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc is Linux's")
def test_children_of_a_process_whose_threads_come_and_go(monkeypatch, spawn):
    # A thread listed in /proc/<pid>/task that has ended before its `children` is read
    # raised FileNotFoundError, and the batch the test had started was left running.
    kid = spawn([sys.executable, "-c", "import time; time.sleep(60)"])
    real = os.listdir
    monkeypatch.setattr(os, "listdir", lambda path: [*real(path), "999999999"])
    assert kid.pid in _children(os.getpid())
    assert _children(999999999) == set()  # a process that has ended: none


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie does not)."""
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl and /proc are Linux's")
def test_workers_do_not_outlive_a_batch_killed_with_sigkill(tmp_path, write_png, spawn):
    # An OOM killer or a scheduler's time limit sends SIGKILL: the pool cannot be stopped,
    # and the workers used to wait for work for ever, each holding its memory.
    folder = _many(tmp_path, write_png, 40)
    out = tmp_path / "out"
    proc = spawn([sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder),
                             "-o", str(out), "-j", "2", "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers = _two_workers(proc.pid)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(_alive(w) for w in workers):
        time.sleep(0.05)
    left = [w for w in workers if _alive(w)]
    for w in left:  # not to leave them on the machine when the test fails
        os.kill(w, signal.SIGKILL)
    assert not left


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc is Linux's")
def test_a_worker_killed_mid_batch_fails_its_images_and_the_batch_goes_on(tmp_path, write_png,
                                                                         spawn):
    # The OOM killer takes one worker: the pool broke and the batch ended in a
    # BrokenProcessPool traceback, the images after it never run.
    folder = _many(tmp_path, write_png, 30)
    out, fresh = tmp_path / "out", tmp_path / "fresh"
    cmd = [sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder), "-j", "2", "-q"]
    proc = spawn([*cmd, "-o", str(out)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    workers = _two_workers(proc.pid)
    time.sleep(0.3)
    os.kill(min(workers), signal.SIGKILL)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, err
    assert "Traceback" not in err and "BrokenProcessPool" not in err
    assert "its worker process died (killed, or out of memory?)" in err
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    assert len(images) == 30 and all(v["status"] in ("done", "failed") for v in images.values())
    lost = [k for k, v in images.items() if v["status"] == "failed"]
    assert 1 <= len(lost) <= 4  # the images in flight, at most 2 per worker
    assert not any((out / f"{k}.holdsite.json").exists() for k in lost)
    res = subprocess.run([*cmd, "-o", str(out), "--resume"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert subprocess.run([*cmd, "-o", str(fresh)], capture_output=True).returncode == 0
    assert tree_bytes(out) == tree_bytes(fresh)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc is Linux's")
def test_sigterm_to_the_whole_group_stops_as_sigterm_to_the_batch(tmp_path, write_png, spawn):
    # systemd or a container runtime signals every process: the workers die with the pool
    folder = _many(tmp_path, write_png, 30)
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder), "-j", "2", "-q"]
    proc = spawn([*cmd, "-o", str(out)], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    wait_for_done(out, proc)
    os.killpg(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143, err
    assert "terminated (SIGTERM)" in err and "worker process died" not in err
    images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    assert not any(v["status"] == "failed" for v in images.values())
    res = subprocess.run([*cmd, "-o", str(out), "--resume"], capture_output=True, text=True)
    assert res.returncode == 0, res.stderr


def _die_at_start(*args, **kwargs):
    os._exit(3)  # a worker that cannot start (fork limits, no memory)


def test_workers_that_die_before_any_image_fail_the_batch_instead_of_looping(
        tmp_path, write_png, monkeypatch):
    from rangeseg_cli.batch import runner as batch

    folder = tmp_path / "in"
    folder.mkdir()
    for i in range(5):
        write_png(folder / f"s{i}.png", scene(i, size=48))
    out = tmp_path / "out"
    monkeypatch.setattr(batch, "_init_worker", _die_at_start)  # forked workers inherit it
    jobs, _ = batch.jobs_from_inputs([str(folder)], out)
    summary = batch.run_batch(jobs, out, load_config(), ("edges",), n_jobs=2)
    assert summary.count("failed") == 5 and summary.count("done") == 0
    assert all("its worker process died" in r.error for r in summary.records)
    assert not list(out.glob("*.npy"))


def _blas_threads() -> list[int]:
    from threadpoolctl import threadpool_info

    return [pool["num_threads"] for pool in threadpool_info() if pool["user_api"] == "blas"]


def test_pool_workers_keep_blas_to_one_thread():
    # Two workers with a BLAS thread per core each would spin against each other.
    from concurrent.futures import ProcessPoolExecutor

    from rangeseg_cli.batch.runner import _init_worker

    with ProcessPoolExecutor(max_workers=2, initializer=_init_worker) as pool:
        threads = pool.submit(_blas_threads).result()
    assert threads and all(n == 1 for n in threads)


def _kernel_threads() -> int:
    from rangeseg_cli.kernels import parallel

    return parallel.thread_count()


def test_pool_workers_get_their_share_of_the_cores():
    from concurrent.futures import ProcessPoolExecutor

    from rangeseg_cli.batch.runner import _init_worker

    with ProcessPoolExecutor(max_workers=2, initializer=_init_worker, initargs=(3,)) as pool:
        assert pool.submit(_kernel_threads).result() == 3


def test_threads_option_gives_the_same_bytes(good_folder, tmp_path, monkeypatch):
    from rangeseg_cli.kernels import parallel

    monkeypatch.setattr(parallel, "MIN_BAND_ROWS", 1)  # the small images are cut into bands too
    monkeypatch.setattr(parallel, "MIN_BAND_PIXELS", 1)
    runner = CliRunner()
    for n in ("1", "3"):
        res = runner.invoke(main, ["run", str(good_folder), "-o", str(tmp_path / n), "-j", "1",
                                   "--threads", n, "-q"])
        assert res.exit_code == 0, res.output
    assert tree_bytes(tmp_path / "1") == tree_bytes(tmp_path / "3")


@pytest.mark.parametrize("jobs", ["1025", "99999999999999999999", "0"])
def test_absurd_job_counts_are_one_line_range_errors(good_folder, tmp_path, jobs):
    res = CliRunner().invoke(main, ["run", str(good_folder), "-o", str(tmp_path / "o"),
                                    "-j", jobs])
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert res.output.strip().splitlines()[-1] == (
        f"Error: Invalid value for '--jobs' / '-j': {jobs} is not in the range 1<=x<=1024.")
    assert not (tmp_path / "o").exists()


def test_cli_and_library_agree_on_the_most_jobs():
    from rangeseg_cli.batch import runner as batch
    from rangeseg_cli.cli import main as cli

    assert cli.MAX_JOBS == batch.MAX_JOBS


def test_pool_has_at_most_one_worker_per_image(good_folder, tmp_path, monkeypatch):
    from concurrent.futures import ProcessPoolExecutor

    from rangeseg_cli.batch import runner as batch

    started = []

    def pool(max_workers, **kwargs):
        started.append(max_workers)
        return ProcessPoolExecutor(max_workers=max_workers, **kwargs)

    monkeypatch.setattr(batch, "ProcessPoolExecutor", pool)
    res = CliRunner().invoke(main, ["run", str(good_folder / "img0.png"),
                                    str(good_folder / "img1.png"), "-o", str(tmp_path / "o"),
                                    "-j", "1000", "-q"])
    assert res.exit_code == 0, res.output
    assert started == [2]


def test_run_batch_refuses_n_jobs_out_of_range(good_folder, tmp_path):
    from rangeseg_cli import load_config
    from rangeseg_cli.batch.runner import MAX_JOBS, jobs_from_inputs, run_batch
    from rangeseg_cli.pipeline import STAGES

    jobs, _ = jobs_from_inputs([good_folder], tmp_path / "o")
    for n in (0, MAX_JOBS + 1):
        with pytest.raises(ValueError, match=f"`n_jobs` = {n}: expected 1 to {MAX_JOBS}"):
            run_batch(jobs, tmp_path / "o", load_config(), STAGES, n_jobs=n)
    assert not (tmp_path / "o").exists()


def test_bad_thread_counts_are_usage_errors(good_folder, tmp_path, monkeypatch):
    runner = CliRunner()
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(tmp_path / "a"), "--threads", "0"])
    assert res.exit_code == 2 and "--threads" in res.output
    monkeypatch.setenv("RANGESEG_THREADS", "lots")
    res = runner.invoke(main, ["run", str(good_folder), "-o", str(tmp_path / "b")])
    assert res.exit_code == 2 and "RANGESEG_THREADS = 'lots'" in res.output
    assert not (tmp_path / "b").exists()


def test_a_file_named_and_inside_a_named_folder_is_one_image(tmp_path, write_png):
    from rangeseg_cli.batch.runner import jobs_from_inputs

    folder = tmp_path / "in"
    (folder / "a").mkdir(parents=True)
    write_png(folder / "a" / "b.png", scene(1, size=32))
    write_png(folder / "c.png", scene(2, size=32))
    (folder / "link.png").symlink_to(folder / "c.png")  # two names in a folder: two images
    out = tmp_path / "out"
    inner = str(folder / "a" / "b.png")
    for inputs, expected in (([str(folder), inner], ["a/b", "c", "link"]),
                             ([inner, str(folder)], ["b", "c", "link"]),
                             ([inner, inner], ["b"]),
                             ([str(folder / "a"), inner], ["b"])):
        jobs, _ = jobs_from_inputs(inputs, out)
        assert sorted(j.rel for j in jobs) == expected, inputs
