"""Batches on a Dask cluster (issue 10): same bytes as local, a killed worker, resume, errors.

One LocalCluster of two worker processes on loopback serves the module; the
CLI runs in this process through CliRunner with ``--executor dask``, or in a
subprocess where a test sends it Ctrl-C or kills its scheduler.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
from click.testing import CliRunner
from distributed import Client, LocalCluster
from distributed.diagnostics.plugin import SchedulerPlugin

from conftest import box_scene, tree_bytes, wait_for_done
from rangeseg_cli import load_config
from rangeseg_cli.batch import dask as dask_executor
from rangeseg_cli.batch.dask import ClusterError, execute_on_dask
from rangeseg_cli.batch.jobs import Job
from rangeseg_cli.cli import progress as cli_report
from rangeseg_cli.cli.main import main
from rangeseg_cli.pipeline import STAGES

N_IMAGES = 16


def scene(i: int, size: int = 160) -> np.ndarray:
    z = box_scene(size, noise=1.0, seed=i)
    z[60 + i % 7: 90 + i % 7, 100:140] += 30.0  # a second block, moving with i
    return z.clip(0, 255).astype(np.uint8)


def run_cli(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["run", *args, "-q"])
    return res.exit_code, res.output


def manifest(out: Path) -> dict:
    return json.loads((out / "rangeseg-run.json").read_text())


@pytest.fixture(scope="module")
def cluster():
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=":0") as c:
        yield c


@pytest.fixture(scope="module")
def client(cluster):
    with Client(cluster.scheduler_address, set_as_default=False, timeout=60) as c:
        yield c


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dask") / "images"
    (folder / "sub").mkdir(parents=True)
    for i in range(N_IMAGES):
        iio.imwrite(folder / ("sub" if i % 4 == 0 else ".") / f"img{i:02d}.png", scene(i))
    return folder


@pytest.fixture(scope="module")
def local_bytes(images, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "out"
    code, output = run_cli(str(images), "-o", str(out), "--executor", "local", "--jobs", "1")
    assert code == 0, output
    return tree_bytes(out)


def dask_args(cluster) -> list[str]:
    return ["--executor", "dask", "--scheduler", cluster.scheduler_address]


def test_dask_run_gives_the_same_bytes_as_a_local_run(cluster, images, local_bytes, tmp_path):
    out = tmp_path / "out"
    code, output = run_cli(str(images), "-o", str(out), *dask_args(cluster))
    assert code == 0, output
    assert tree_bytes(out) == local_bytes
    statuses = [e["status"] for e in manifest(out)["images"].values()]
    assert statuses == ["done"] * N_IMAGES


def test_bad_image_on_dask_is_recorded_as_in_a_local_run_with_exit_1(cluster, tmp_path):
    folder = tmp_path / "mixed"
    folder.mkdir()
    iio.imwrite(folder / "good.png", scene(1))
    (folder / "corrupt.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"x" * 50)
    runs = {}
    for executor, extra in (("local", ["--jobs", "1"]), ("dask", dask_args(cluster)[2:])):
        out = tmp_path / executor
        code, output = run_cli(str(folder), "-o", str(out), "--executor", executor, *extra)
        assert code == 1, output
        assert sum("corrupt.png" in line for line in output.splitlines()) == 1, output
        runs[executor] = manifest(out)["images"]
    assert runs["dask"]["good"]["status"] == "done"
    assert runs["dask"]["corrupt"]["status"] == "failed"
    assert runs["dask"]["corrupt"]["error"] == runs["local"]["corrupt"]["error"]
    assert runs["dask"]["corrupt"]["input"] == runs["local"]["corrupt"]["input"]


def test_dask_resume_redoes_only_what_is_missing(cluster, images, local_bytes, tmp_path):
    out = tmp_path / "out"
    assert run_cli(str(images), "-o", str(out), *dask_args(cluster))[0] == 0
    (out / "img05.labels.npy").unlink()
    res = CliRunner().invoke(main, ["run", str(images), "-o", str(out), *dask_args(cluster),
                                    "--resume", "-q", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert (summary["done"], summary["resumed"]) == (1, N_IMAGES - 1)
    assert tree_bytes(out) == local_bytes


def test_unreachable_scheduler_exits_2_with_one_line_before_any_work(images, tmp_path,
                                                                      monkeypatch):
    monkeypatch.setattr(dask_executor, "CONNECT_TIMEOUT_S", 1.0)
    for address in ("tcp://127.0.0.1:1", "127.0.0.1"):
        out = tmp_path / "out"
        code, output = run_cli(str(images), "-o", str(out), "--executor", "dask",
                               "--scheduler", address)
        assert code == 2, output
        assert len(output.strip().splitlines()) == 1 and address in output, output
        assert not out.exists()


def test_missing_dask_is_one_line_naming_the_extra(images, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed fails
    out = tmp_path / "out"
    code, output = run_cli(str(images), "-o", str(out), "--executor", "dask",
                           "--scheduler", "tcp://127.0.0.1:8786")
    assert code == 2, output
    assert len(output.strip().splitlines()) == 1 and "pip install 'rangeseg[dask]'" in output
    assert not out.exists()


@pytest.mark.parametrize(("args", "message"), [
    (["--executor", "dask"], "--executor dask needs"),
    (["--scheduler", "tcp://127.0.0.1:8786"], "only with --executor dask"),
])
def test_executor_and_scheduler_must_go_together(images, tmp_path, args, message):
    code, output = run_cli(str(images), "-o", str(tmp_path / "out"), *args)
    assert code == 2 and message in output, output


def test_workers_that_do_not_see_the_output_folder_are_refused(cluster, tmp_path):
    with pytest.raises(ClusterError, match="does not see .*shared storage"):
        execute_on_dask([Job(rel="x", source=str(tmp_path / "x.png"))], tmp_path / "nowhere",
                        load_config(), STAGES, cluster.scheduler_address, lambda r: None)


def test_image_whose_workers_all_died_keeps_no_results_of_an_earlier_run(tmp_path):
    import distributed

    out = tmp_path / "out"
    out.mkdir()
    old = [out / f"img.{name}" for name in ("range.npy", "labels.npy", "holdsite.json")]
    for path in old:
        path.write_text("from an earlier run")

    class DeadTask:
        def result(self):
            raise distributed.KilledWorker("task", None, 3)

    job = Job(rel="img", source=str(tmp_path / "img.png"))
    batch = dask_executor._Batch(client=None, distributed=distributed, address="tcp://x:1",
                                 out=out, config=load_config(), stages=STAGES)
    batch.pending[DeadTask()] = (job, job)
    record = batch.record(next(iter(batch.pending)))
    assert record.status == "failed" and "every Dask worker that ran it died" in record.error
    assert not any(path.exists() for path in old)


def test_worker_killed_mid_batch_still_completes_with_identical_bytes(
        cluster, client, images, local_bytes, tmp_path, monkeypatch):
    # When the first image is reported, SIGKILL a worker that holds one of the
    # batch's tasks (like the OOM killer would); its nanny starts a new one.
    pids = client.run(os.getpid)
    killed: list[str] = []
    report = cli_report.BatchReporter.result

    def result_then_kill(self, record):
        report(self, record)
        if not killed:
            busy = [w for w, keys in client.processing().items()
                    if any(str(k).startswith("rangeseg-") for k in keys)]
            assert busy, "no worker holds a task of the batch"
            killed.append(busy[0])
            os.kill(pids[busy[0]], signal.SIGKILL)

    monkeypatch.setattr(cli_report.BatchReporter, "result", result_then_kill)
    out = tmp_path / "out"
    code, output = run_cli(str(images), "-o", str(out), *dask_args(cluster))
    assert code == 0, output
    assert killed and killed[0] not in client.scheduler_info()["workers"]
    assert tree_bytes(out) == local_bytes  # no stray temporaries either
    statuses = [e["status"] for e in manifest(out)["images"].values()]
    assert statuses == ["done"] * N_IMAGES
    client.wait_for_workers(2, timeout=60)  # leave the cluster whole


def test_scheduler_without_workers_exits_2_with_one_line(images, tmp_path, monkeypatch):
    from distributed import LocalCluster

    monkeypatch.setattr(dask_executor, "WORKER_WAIT_S", 1.0)
    with LocalCluster(n_workers=0, processes=True, host="127.0.0.1",
                      dashboard_address=":0") as empty:
        out = tmp_path / "out"
        code, output = run_cli(str(images), "-o", str(out), "--executor", "dask",
                               "--scheduler", empty.scheduler_address)
    assert code == 2, output
    assert len(output.strip().splitlines()) == 1 and "has no workers" in output, output
    assert not list(out.glob("*.npy"))


# --------------------------------------------------------------------------- --jobs


class InFlight(SchedulerPlugin):
    """Records the most tasks of a batch the scheduler held unfinished at once."""

    name = "rangeseg-test-in-flight"
    UNFINISHED = ("waiting", "queued", "processing", "no-worker")

    def __init__(self):
        self.keys, self.most = set(), 0

    def transition(self, key, start, finish, *args, **kwargs):
        if str(key).startswith("rangeseg-"):
            if finish in self.UNFINISHED:
                self.keys.add(key)
            else:
                self.keys.discard(key)
            self.most = max(self.most, len(self.keys))


def most_in_flight(cluster, client, *args: str) -> int:
    client.register_plugin(InFlight())
    try:
        code, output = run_cli(*args)
        assert code == 0, output
        return cluster.scheduler.plugins[InFlight.name].most
    finally:
        client.unregister_scheduler_plugin(InFlight.name)


def test_jobs_caps_the_images_in_flight_on_dask(cluster, client, images, local_bytes, tmp_path):
    capped = most_in_flight(cluster, client, str(images), "-o", str(tmp_path / "capped"),
                            *dask_args(cluster), "--jobs", "1")
    assert capped == 1
    assert tree_bytes(tmp_path / "capped") == local_bytes
    free = most_in_flight(cluster, client, str(images), "-o", str(tmp_path / "free"),
                          *dask_args(cluster))
    assert free > 2  # without --jobs every image is submitted at once


# --------------------------------------------------------------------------- Ctrl-C, lost scheduler

N_MANY = 32


@pytest.fixture(scope="module")
def many(tmp_path_factory):
    """A batch long enough to be stopped part-way, and the bytes of a whole local run."""
    folder = tmp_path_factory.mktemp("many") / "images"
    folder.mkdir()
    for i in range(N_MANY):
        iio.imwrite(folder / f"m{i:02d}.png", scene(i, size=128))
    out = tmp_path_factory.mktemp("many-local") / "out"
    code, output = run_cli(str(folder), "-o", str(out), "--jobs", "2")
    assert code == 0, output
    return folder, tree_bytes(out)


def start_cli(spawn, folder: Path, out: Path, address: str) -> subprocess.Popen:
    return spawn([sys.executable, "-m", "rangeseg_cli.cli.main", "run", str(folder),
                             "-o", str(out), "-q", "--executor", "dask", "--scheduler", address],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def executing(dask_worker) -> int:
    return dask_worker.state.executing_count  # cancelled tasks still running included


def wait_until_idle(client) -> None:
    """Cancelled tasks that were running finish on the workers; wait for them to end."""
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and any(client.run(executing).values()):
        time.sleep(0.05)
    assert not any(client.run(executing).values())


def check_partial_run(out: Path, reference: dict[str, bytes]) -> list[str]:
    """The manifest's done images are complete; every file there is a whole, right file.

    Workers may have written images whose results never reached the client:
    those are complete too, and not in the manifest.
    """
    done = [k for k, v in manifest(out)["images"].items() if v["status"] == "done"]
    assert 1 <= len(done) < N_MANY, "the batch was not stopped part-way"
    files = tree_bytes(out)
    assert all(f"{k}.{n}" in files for k in done for n in ("labels.npy", "holdsite.json",
                                                            "overlay.png"))
    partial = {k: v for k, v in files.items() if not k.endswith(".tmp")}
    assert all(reference[k] == v for k, v in partial.items())  # no half-written output
    return done


def resume_on(cluster, folder: Path, out: Path, reference: dict[str, bytes], done: list[str]):
    res = CliRunner().invoke(main, ["run", str(folder), "-o", str(out), *dask_args(cluster),
                                    "--resume", "-q", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert summary["resumed"] >= len(done) and summary["done"] + summary["resumed"] == N_MANY
    assert tree_bytes(out) == reference  # and no temporaries left


def test_ctrl_c_on_dask_exits_130_keeps_what_finished_and_resumes(cluster, client, many, spawn,
                                                                  tmp_path):
    folder, reference = many
    out = tmp_path / "out"
    proc = start_cli(spawn, folder, out, cluster.scheduler_address)
    wait_for_done(out, proc)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "--resume" in err and "Traceback" not in err
    wait_until_idle(client)
    done = check_partial_run(out, reference)
    resume_on(cluster, folder, out, reference, done)


DOOMED_CLUSTER = """
import time
from distributed import LocalCluster
with LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                  host="127.0.0.1", dashboard_address=":0") as cluster:
    print(cluster.scheduler_address, flush=True)
    while True:
        time.sleep(1)
"""


def test_losing_the_scheduler_mid_batch_is_one_line_naming_it(cluster, many, tmp_path, spawn):
    # A scheduler (and its one worker) in a subprocess, killed with SIGKILL mid-batch.
    folder, reference = many
    out = tmp_path / "out"
    doomed = spawn([sys.executable, "-c", DOOMED_CLUSTER], stdout=subprocess.PIPE, text=True)
    try:
        address = doomed.stdout.readline().strip()
        proc = start_cli(spawn, folder, out, address)
        wait_for_done(out, proc)
    finally:
        doomed.kill()
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert err.splitlines() == [f"Error: lost the Dask scheduler at {address} mid-batch; what "
                                "finished is kept: rerun with --resume once it is back"]
    assert "lost the Dask scheduler" in manifest(out)["summary"]["stopped"]
    done = check_partial_run(out, reference)
    resume_on(cluster, folder, out, reference, done)
