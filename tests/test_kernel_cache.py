"""The first run says on stderr that it compiles the kernels; later runs say nothing."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest
from click.testing import CliRunner

from rangeseg_cli import kernel_cache
from rangeseg_cli.cli import main


@pytest.fixture
def package(tmp_path, monkeypatch):
    """A copy of the kernels' source with an empty cache beside it."""
    source = tmp_path / "_kernels.py"
    source.write_text("# kernels\n")
    (tmp_path / "__pycache__").mkdir()
    monkeypatch.setattr(kernel_cache, "SOURCE", source)
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    monkeypatch.delenv("RANGESEG_PURE_NUMPY", raising=False)
    return tmp_path


def index(folder: Path, age: float = 0.0) -> Path:
    path = folder / "_kernels.edges_pass-196.py311.nbi"
    path.write_bytes(b"")
    stamp = (folder.parent / "_kernels.py").stat().st_mtime + age
    os.utime(path, (stamp, stamp))
    return path


def test_an_empty_cache_is_cold(package):
    assert kernel_cache.cold_kernel_cache()


def test_an_index_newer_than_the_source_is_warm(package):
    index(package / "__pycache__", age=5.0)
    assert not kernel_cache.cold_kernel_cache()


def test_an_index_older_than_the_source_is_cold(package):
    index(package / "__pycache__", age=-5.0)
    assert kernel_cache.cold_kernel_cache()


def test_a_cache_under_numba_cache_dir_counts(package, tmp_path, monkeypatch):
    elsewhere = tmp_path / "cache" / "some" / "path"
    elsewhere.mkdir(parents=True)
    path = elsewhere / "_kernels.edges_pass-196.py311.nbi"
    path.write_bytes(b"")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "cache"))
    assert not kernel_cache.cold_kernel_cache()


def test_pure_numpy_compiles_nothing(package, monkeypatch):
    monkeypatch.setenv("RANGESEG_PURE_NUMPY", "1")
    assert not kernel_cache.cold_kernel_cache()


def test_a_cold_cache_is_said_on_stderr_and_json_stays_clean(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_cache, "cold_kernel_cache", lambda: True)
    image = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic" / "part1-n0.png"
    runner = CliRunner()
    done = runner.invoke(main, ["run", str(image), "-o", str(tmp_path / "o"), "--json"])
    assert done.exit_code == 0, done.stderr
    assert "compiling the numba kernels" in done.stderr
    assert json.loads(done.stdout)["done"] == 1
    quiet = runner.invoke(main, ["run", str(image), "-o", str(tmp_path / "q"), "-q"])
    assert quiet.exit_code == 0 and "compiling" not in quiet.stderr


def test_a_warm_cache_says_nothing(tmp_path, monkeypatch):
    monkeypatch.setattr(kernel_cache, "cold_kernel_cache", lambda: False)
    image = Path(__file__).resolve().parents[1] / "sample_data" / "synthetic" / "part1-n0.png"
    done = CliRunner().invoke(main, ["run", str(image), "-o", str(tmp_path / "o"), "--json"])
    assert done.exit_code == 0 and "compiling" not in done.stderr
