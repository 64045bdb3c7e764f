"""Inputs and outputs named by fsspec URLs: s3:// on a moto server on loopback, memory://.

A moto S3 server runs in this process on 127.0.0.1 at a free port. s3fs finds
it through fsspec's configuration: ``FSSPEC_S3`` in the environment (so the
Dask workers started afterwards get the same settings) and, for this process,
``fsspec.config.conf`` (fsspec read the environment when it was imported).
Nothing goes to the network but 127.0.0.1.
"""

import json
import logging
import os
import sys
from collections import Counter
from pathlib import Path

import fsspec
import imageio.v3 as iio
import numpy as np
import pytest
from click.testing import CliRunner
from distributed import LocalCluster
from moto.server import ThreadedMotoServer

from conftest import box_scene, tree_bytes
from rangeseg_cli import run_pipeline
from rangeseg_cli.batch import io
from rangeseg_cli.cli.main import main
from rangeseg_cli.errors import StorageError

BUCKET = "frames"
NAMES = ("a.png", "b.png", "sub/c.png", "sub/d.png")


def scene(i: int) -> np.ndarray:
    z = box_scene(64, noise=1.0, seed=i)
    z[8 + i: 16 + i, 44:56] += 30.0  # a second block, moving with i
    return z.clip(0, 255).astype(np.uint8)


def png_bytes(i: int) -> bytes:
    return iio.imwrite("<bytes>", scene(i), extension=".png")


def run_cli(*args: str) -> tuple[int, str]:
    res = CliRunner().invoke(main, ["run", *args, "-q"])
    return res.exit_code, res.output


def store_bytes(fs, root: str) -> dict[str, bytes]:
    """Every object below ``root`` except the manifest, by relative path (as tree_bytes)."""
    fs.invalidate_cache()
    return {p[len(root) + 1:]: fs.cat_file(p) for p in sorted(fs.find(root))
            if not p.endswith("rangeseg-run.json")}


def store_manifest(fs, root: str) -> dict:
    return json.loads(fs.cat_file(f"{root}/rangeseg-run.json"))


@pytest.fixture(scope="module")
def s3(tmp_path_factory):
    """The s3fs filesystem of a moto server on loopback, with frames in s3://frames/in."""
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    options = {"endpoint_url": f"http://{host}:{port}", "key": "testing", "secret": "testing"}
    with pytest.MonkeyPatch.context() as mp:
        for name, value in {"AWS_ACCESS_KEY_ID": "testing", "AWS_SECRET_ACCESS_KEY": "testing",
                            "AWS_DEFAULT_REGION": "us-east-1", "AWS_EC2_METADATA_DISABLED": "true",
                            "AWS_CONFIG_FILE": os.devnull, "AWS_SHARED_CREDENTIALS_FILE": os.devnull,
                            "FSSPEC_S3": json.dumps(options)}.items():
            mp.setenv(name, value)
        mp.setitem(fsspec.config.conf, "s3", options)
        mp.setattr(logging.getLogger("werkzeug"), "level", logging.ERROR)  # moto's request log
        fs = fsspec.filesystem("s3")
        fs.mkdir(BUCKET)
        for i, name in enumerate(NAMES):
            fs.pipe_file(f"{BUCKET}/in/{name}", png_bytes(i))
        fs.pipe_file(f"{BUCKET}/in/notes.txt", b"not an image")
        fs.pipe_file(f"{BUCKET}/in/.hidden.png", b"not read")
        try:
            yield fs
        finally:
            type(fs).clear_instance_cache()
            server.stop()


@pytest.fixture(scope="module")
def cluster(s3):
    """Two worker processes on loopback, started after FSSPEC_S3 is set: they inherit it."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=":0") as c:
        yield c


@pytest.fixture(scope="module")
def local_frames(tmp_path_factory):
    folder = tmp_path_factory.mktemp("frames") / "in"
    for i, name in enumerate(NAMES):
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(png_bytes(i))
    (folder / "notes.txt").write_bytes(b"not an image")
    return folder


@pytest.fixture(scope="module")
def local_bytes(local_frames, tmp_path_factory):
    out = tmp_path_factory.mktemp("local") / "out"
    code, output = run_cli(str(local_frames), "-o", str(out), "--jobs", "1")
    assert code == 0, output
    return tree_bytes(out)


def executor_args(executor: str, cluster) -> list[str]:
    if executor == "dask":
        return ["--executor", "dask", "--scheduler", cluster.scheduler_address]
    return ["--executor", "local", "--jobs", "2"]


@pytest.mark.parametrize("executor", ["local", "dask"])
def test_s3_in_and_out_gives_the_bytes_of_a_local_folder_run(s3, cluster, local_bytes, executor):
    inputs_before = store_bytes(s3, f"{BUCKET}/in")
    out = f"{BUCKET}/out-{executor}"
    code, output = run_cli(f"s3://{BUCKET}/in/", "-o", f"s3://{out}",
                           *executor_args(executor, cluster))
    assert code == 0, output
    assert store_bytes(s3, out) == local_bytes
    manifest = store_manifest(s3, out)
    assert {k: v["status"] for k, v in manifest["images"].items()} == {
        "a": "done", "b": "done", "sub/c": "done", "sub/d": "done"}
    assert manifest["images"]["sub/c"]["input"] == f"s3://{BUCKET}/in/sub/c.png"
    assert manifest["summary"]["not_images"] == 1  # notes.txt; .hidden.png is not searched
    assert store_bytes(s3, f"{BUCKET}/in") == inputs_before  # inputs never modified


def test_s3_resume_on_dask_redoes_only_the_missing_image(s3, cluster, local_bytes):
    out = f"{BUCKET}/resume"
    args = [f"s3://{BUCKET}/in", "-o", f"s3://{out}", *executor_args("dask", cluster)]
    assert run_cli(*args)[0] == 0
    s3.rm_file(f"{out}/sub/d.labels.npy")
    res = CliRunner().invoke(main, ["run", *args, "--resume", "-q", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert (summary["done"], summary["resumed"]) == (1, 3)
    assert store_bytes(s3, out) == local_bytes
    res = CliRunner().invoke(main, ["run", *args, "-q"])
    assert res.exit_code == 2 and "use --resume" in res.output and f"s3://{out}" in res.output


@pytest.mark.parametrize("executor", ["local", "dask"])
def test_corrupt_frame_on_s3_is_one_failed_image_and_exit_1(s3, cluster, executor):
    s3.pipe_file(f"{BUCKET}/mixed-{executor}/good.png", png_bytes(1))
    s3.pipe_file(f"{BUCKET}/mixed-{executor}/corrupt.png", b"\x89PNG\r\n\x1a\n" + b"x" * 50)
    out = f"{BUCKET}/mixed-out-{executor}"
    code, output = run_cli(f"s3://{BUCKET}/mixed-{executor}", "-o", f"s3://{out}",
                           *executor_args(executor, cluster))
    assert code == 1, output
    url = f"s3://{BUCKET}/mixed-{executor}/corrupt.png"
    assert [line for line in output.splitlines() if "corrupt" in line] == [
        line for line in output.splitlines() if line.startswith(f"{url}: not a readable image")]
    assert sum(url in line for line in output.splitlines()) == 1, output
    images = store_manifest(s3, out)["images"]
    assert images["good"]["status"] == "done" and images["corrupt"]["status"] == "failed"
    assert images["corrupt"]["error"].startswith(f"{url}: not a readable image")
    assert s3.exists(f"{out}/good.holdsite.json") and not s3.exists(f"{out}/corrupt.edges.npy")


def test_s3_input_to_a_local_folder_and_local_input_to_s3(s3, local_frames, local_bytes,
                                                          tmp_path):
    code, output = run_cli(f"s3://{BUCKET}/in", "-o", str(tmp_path / "out"), "--jobs", "1")
    assert code == 0, output
    assert tree_bytes(tmp_path / "out") == local_bytes
    code, output = run_cli(str(local_frames), "-o", f"s3://{BUCKET}/from-local", "--jobs", "1")
    assert code == 0, output
    assert store_bytes(s3, f"{BUCKET}/from-local") == local_bytes


def test_s3_resume_redoes_a_frame_replaced_under_the_same_key(s3, tmp_path):
    """The input's ETag is its stamp: a new object under the old key is redone, the rest kept."""
    src = f"{BUCKET}/replaced"
    for i, name in enumerate(NAMES[:3]):
        s3.pipe_file(f"{src}/{name}", png_bytes(i))
    out = tmp_path / "out"
    assert run_cli(f"s3://{src}", "-o", str(out), "--jobs", "1")[0] == 0
    s3.pipe_file(f"{src}/b.png", png_bytes(3))
    res = CliRunner().invoke(main, ["run", f"s3://{src}", "-o", str(out), "--jobs", "1", "-q",
                                    "--resume", "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert (summary["done"], summary["resumed"]) == (1, 2)
    np.testing.assert_array_equal(np.load(out / "b.labels.npy"),
                                  run_pipeline(scene(3)).labels)


def test_stage_commands_on_an_s3_output_give_the_bytes_of_run(s3, local_bytes):
    out = f"s3://{BUCKET}/staged"
    runner = CliRunner()
    res = runner.invoke(main, ["edges", f"s3://{BUCKET}/in", "-o", out, "-j", "1", "-q"])
    assert res.exit_code == 0, res.output
    for stage in ("link", "grow", "holdsite"):
        res = runner.invoke(main, [stage, out, "-j", "1", "-q"])
        assert res.exit_code == 0, res.output
    assert store_bytes(s3, f"{BUCKET}/staged") == local_bytes


def test_missing_bucket_for_out_is_one_line_naming_it(s3):
    code, output = run_cli(f"s3://{BUCKET}/in", "-o", "s3://no-such-bucket/out", "--jobs", "1")
    assert code == 2, output
    assert len(output.strip().splitlines()) == 1 and "s3://no-such-bucket/out" in output, output


def test_missing_s3fs_is_one_line_naming_the_url_and_the_extra(local_frames, tmp_path,
                                                               monkeypatch):
    monkeypatch.setitem(sys.modules, "s3fs", None)  # import s3fs fails
    monkeypatch.delitem(sys.modules["fsspec.registry"]._registry, "s3", raising=False)
    for args in ([f"s3://{BUCKET}/in", "-o", str(tmp_path / "out")],
                 [str(local_frames), "-o", "s3://bucket/out"]):
        code, output = run_cli(*args, "--jobs", "1")
        assert code == 2, output
        url = next(a for a in args if a.startswith("s3://"))
        assert len(output.strip().splitlines()) == 1, output
        assert url in output and "pip install 'rangeseg[s3]'" in output, output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("url", "message"), [
    ("nosuch://bucket/in", "unknown protocol nosuch://"),
    ("file://otherhost/in", "file:///path; got host 'otherhost'"),
])
def test_unusable_urls_are_one_line_usage_errors(url, message, tmp_path):
    for args in ([url, "-o", str(tmp_path / "out")], [str(tmp_path), "-o", url]):
        code, output = run_cli(*args, "--jobs", "1")
        assert code == 2, output
        assert len(output.strip().splitlines()) == 1 and url in output and message in output


# --------------------------------------------------------------------------- memory:// and file://


@pytest.fixture
def memory_frames():
    fs = fsspec.filesystem("memory")
    for i, name in enumerate(NAMES):
        fs.pipe_file(f"/rangeseg-test/in/{name}", png_bytes(i))
    yield fs
    fs.rm("/rangeseg-test", recursive=True)


def test_memory_urls_with_the_out_folder_inside_the_input(memory_frames, local_bytes):
    out = "memory://rangeseg-test/in/results"
    args = ["memory://rangeseg-test/in", "-o", out, "--jobs", "1"]
    assert run_cli(*args)[0] == 0
    res = CliRunner().invoke(main, ["run", *args, "--overwrite", "-q", "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["done"] == 4  # results/ not read
    assert store_bytes(memory_frames, "/rangeseg-test/in/results") == local_bytes


def test_each_file_on_an_object_store_is_one_put_of_its_whole_bytes(memory_frames, local_bytes,
                                                                   monkeypatch):
    # memory:// puts through a file object it commits on close: allowed inside pipe_file only.
    puts: list[str] = []
    putting: list[str] = []
    fs_type = type(memory_frames)
    pipe_file, open_file = fs_type.pipe_file, fs_type._open

    def spy_pipe_file(self, path, value, *args, **kwargs):
        puts.append(path)
        putting.append(path)
        try:
            return pipe_file(self, path, value, *args, **kwargs)
        finally:
            putting.pop()

    def no_streaming(self, path, mode="rb", *args, **kwargs):
        if "r" not in mode and not putting:
            raise AssertionError(f"{path} written outside one put of the whole object")
        return open_file(self, path, mode, *args, **kwargs)

    monkeypatch.setattr(fs_type, "pipe_file", spy_pipe_file)
    monkeypatch.setattr(fs_type, "_open", no_streaming)
    code, output = run_cli("memory://rangeseg-test/in", "-o", "memory://rangeseg-test/out",
                           "--jobs", "1")
    assert code == 0, output
    counts = Counter(p.removeprefix("/rangeseg-test/out/") for p in puts
                     if not p.endswith("rangeseg-run.json"))
    # every file once: `run` leaves edges.npy to `link`, which adds code 3
    assert counts == dict.fromkeys(local_bytes, 1)


def test_memory_urls_on_dask_are_refused_before_any_work(memory_frames, cluster):
    code, output = run_cli("memory://rangeseg-test/in", "-o", "memory://rangeseg-test/out",
                           "--executor", "dask", "--scheduler", cluster.scheduler_address)
    assert code == 2, output
    assert "does not see memory://rangeseg-test/out" in output and "shared storage" in output
    assert memory_frames.find("/rangeseg-test/out") == ["/rangeseg-test/out/rangeseg-run.json"]


def test_file_urls_are_local_paths(local_frames, local_bytes, tmp_path):
    assert io.location(f"file://{local_frames}") == local_frames
    code, output = run_cli(f"file://{local_frames}", "-o", f"file://{tmp_path}/out", "-j", "1")
    assert code == 0, output
    assert tree_bytes(tmp_path / "out") == local_bytes


def test_urlpath_joins_like_a_path_and_pickles_as_its_url():
    import pickle

    where = io.location("memory://bucket/out/")
    leaf = where / "sub/img.labels.npy"
    assert str(leaf) == "memory://bucket/out/sub/img.labels.npy"
    assert (leaf.name, leaf.suffix, str(leaf.parent)) == ("img.labels.npy", ".npy",
                                                         "memory://bucket/out/sub")
    assert pickle.loads(pickle.dumps(leaf)) == leaf
    with pytest.raises(StorageError, match="unknown protocol nosuch://"):
        io.location("nosuch://x")


def test_writes_to_a_filesystem_without_atomic_puts_go_through_a_moved_temporary(tmp_path):
    # local:// is fsspec's local filesystem reached by URL: not an object store,
    # so each file is written beside itself and moved over it.
    where = io.location(f"local://{tmp_path}/out")
    io.write_npy(where / "a.npy", np.arange(4))
    io.write_json(where / "sub/a.json", {"b": 1})
    assert sorted(p.relative_to(tmp_path).as_posix() for p in tmp_path.rglob("*")) == [
        "out", "out/a.npy", "out/sub", "out/sub/a.json"]
    np.testing.assert_array_equal(io.read_npy(where / "a.npy"), np.arange(4))
    assert io.read_json(where / "sub/a.json") == {"b": 1}
    (Path(tmp_path) / "out" / ".a.npy.1234.tmp").write_bytes(b"half")
    io.remove_temporaries(where)
    assert not list(tmp_path.rglob("*.tmp"))


@pytest.mark.parametrize("name", ["file://", "file://localhost", "FILE://"])
def test_a_file_url_without_a_path_is_refused_not_the_current_folder(name):
    from rangeseg_cli.batch.io import location
    from rangeseg_cli.errors import StorageError

    with pytest.raises(StorageError, match="without a path"):
        location(name)
    assert location("file:///") == Path("/")


def test_run_batch_refuses_an_out_it_cannot_write_before_any_work(tmp_path):
    from rangeseg_cli.batch.io import check_output_protocol, location
    from rangeseg_cli.batch.runner import run_batch
    from rangeseg_cli.config import load_config
    from rangeseg_cli.errors import StorageError

    with pytest.raises(StorageError, match="https:// URLs can be read, not written"):
        run_batch([], location("https://example.com/out"), load_config(), ("edges",))
    check_output_protocol(tmp_path)  # a local folder, and
    check_output_protocol("memory://out")  # a store that can be written, pass


def test_a_damaged_intermediate_array_is_named_with_what_to_do(tmp_path):
    # numpy's own text said "... use allow_pickle=", which no user of rangeseg can.
    from rangeseg_cli.errors import OutputError

    garbage, objects = tmp_path / "a.labels.npy", tmp_path / "b.labels.npy"
    garbage.write_bytes(b"garbage")
    np.save(objects, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    for path in (garbage, objects):
        with pytest.raises(OutputError) as info:
            io.read_npy(path)
        message = str(info.value)
        assert message.startswith(f"{path}: cannot read: damaged, or not an array rangeseg "
                                  "wrote (")
        assert message.endswith("); redo its stage (--overwrite)")
        assert "allow_pickle" not in message
