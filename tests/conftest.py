"""Shared synthetic scenes with known answers."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

if TYPE_CHECKING:
    from rangeseg_cli.config import Config


def tree_bytes(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` except the manifest (it holds timings)."""
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != "rangeseg-run.json"}


def done_in_manifest(out: Path) -> int:
    """Images the batch writing ``out`` has recorded as done (0 before its manifest)."""
    try:
        images = json.loads((out / "rangeseg-run.json").read_text())["images"]
    except (OSError, ValueError, KeyError):
        return 0
    return sum(v.get("status") == "done" for v in images.values())


def wait_for_done(out: Path, proc: subprocess.Popen | None = None, count: int = 1,
                  timeout: float = 120.0) -> None:
    """Until the batch writing ``out`` (``proc``) has recorded ``count`` images as done.

    Files on disk are not enough: a worker writes them before its result
    reaches the batch, and a stop in between leaves them unrecorded. The
    batch writes its manifest on its first result (``_Manifest.add``), then
    at most every 2 s. A batch that ends first fails here with its stderr.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and done_in_manifest(out) < count:
        if proc is not None and proc.poll() is not None:
            err = proc.stderr.read() if proc.stderr else ""
            pytest.fail(f"the batch ended (exit {proc.returncode}) before {count} image(s) "
                        f"were recorded: {err}")
        time.sleep(0.02)
    assert done_in_manifest(out) >= count, f"no image done in {out}"


def step_image(height: float = 40.0, size: int = 32, col: int = 16) -> np.ndarray:
    """A vertical step: 0 left of ``col``, ``height`` from ``col`` on."""
    z = np.zeros((size, size))
    z[:, col:] = height
    return z


def random_labels(seed: int, shape: tuple[int, int], regions: int, holes: float,
                  invalid: float, *, roof: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Noisy heights with a share ``invalid`` NaN, and random labels 1..regions with a
    share ``holes`` of 0 (for the property tests): sloped (sigma 5), or with ``roof`` two
    planes meeting at a ridge (sigma 1)."""
    rng = np.random.default_rng(seed)
    if roof:
        y, x = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
        z = np.minimum(50.0 + 0.5 * x, 80.0 - 2.0 * y) + rng.normal(0.0, 1.0, shape)
    else:
        z = rng.normal(50.0, 5.0, shape) + rng.uniform(-3, 3) * np.arange(shape[1])[None, :]
    z[rng.random(shape) < invalid] = np.nan
    labels = rng.integers(1, regions + 1, shape).astype(np.int32)
    labels[rng.random(shape) < holes] = 0
    return z, labels


def box_scene(size: int = 64, noise: float = 0.0, seed: int = 0) -> np.ndarray:
    """A 24x24 box of height 120 on a table at 20."""
    z = np.full((size, size), 20.0)
    z[20:44, 20:44] = 120.0
    if noise:
        z = z + np.random.default_rng(seed).normal(0, noise, z.shape)
    return z


CHAMFER = (40, 44)  # columns of the chamfer of :func:`chamfered`


def chamfered(noise: float, seed: int, *, slope: float = 1.7
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A top plane, a chamfer 4 pixels wide falling ``slope`` per pixel, a steep side
    (tests/test_carve.py, tests/test_refine.py).

    Returns heights, the truth (1 top, 2 chamfer, 3 side) and the labels
    growing leaves: the chamfer grown into the top (1), the side (2).
    """
    y, x = np.mgrid[0:48, 0:64].astype(np.float64)
    top = 150.0 + 0.2 * y + 0.1 * x
    into = np.clip(x - (CHAMFER[0] - 0.5), 0.0, CHAMFER[1] - CHAMFER[0])
    beyond = np.clip(x - (CHAMFER[1] - 0.5), 0.0, None)
    z = top - slope * into - 8.0 * beyond
    z += np.random.default_rng(seed).normal(0.0, noise, z.shape) if noise else 0.0
    truth = np.select([x < CHAMFER[0], x < CHAMFER[1]], [1, 2], 3).astype(np.int32)
    grown = np.where(x < CHAMFER[1], 1, 2).astype(np.int32)
    return z, truth, grown


def small_frustum(noise: float, seed: int, *, half: int = 14, width: int = 5,
                  slope: float = 4.0, size: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A square frustum on a slightly tilted table, sides ``width`` pixels wide rising
    ``slope`` per pixel, its base ``2 * half + 1`` pixels across (a bin pile's small
    frustums: sides 4-7 pixels wide), rounded to whole units as 8-bit images are
    (tests/test_split.py, tests/test_facets.py).

    Returns heights and the truth: 1 table, 2 +x side, 3 -x, 4 +y, 5 -y, 6 top.
    """
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    dx, dy = x - (size / 2 - 0.5), y - (size / 2 - 0.5)
    height = np.clip(slope * (half + 0.5 - np.maximum(np.abs(dx), np.abs(dy))), 0.0,
                     slope * width)
    side, across = (height > 0) & (height < slope * width), np.abs(dx) >= np.abs(dy)
    truth = np.select([height >= slope * width, side & across & (dx > 0),
                       side & across & (dx < 0), side & (dy > 0), side], [6, 2, 3, 4, 5],
                      1).astype(np.int32)
    z = 20.0 + height + 0.05 * x + 0.1 * y
    z += np.random.default_rng(seed).normal(0.0, noise, z.shape) if noise else 0.0
    return np.round(z), truth


def passes_without(*names: str, base: Config | None = None, **refine: Any) -> Config:
    """``base`` (the defaults when None) with the ``[refine] passes`` ``names`` left out.

    The passes that need one of them go too (the bridge with the fill). Other
    ``[refine]`` keys may be given too (``passes_without("merge", fit_factor=1.5)``).
    """
    from rangeseg_cli.config import PASS_NEEDS, REFINE_PASSES

    unknown = set(names) - set(REFINE_PASSES)
    assert not unknown, f"not a refine pass: {sorted(unknown)}"
    gone = set(names) | {p for p, needs in PASS_NEEDS.items() if set(needs) & set(names)}
    on = REFINE_PASSES if base is None else base.refine.passes
    return with_passes(*(p for p in on if p not in gone), base=base, **refine)


def with_passes(*names: str, base: Config | None = None, **refine: Any) -> Config:
    """``base`` (the defaults when None) with ``[refine] passes`` = ``names`` exactly.

    ``with_passes("fill", base=load_config(preset="paper"))`` is the paper with the fill.
    """
    from rangeseg_cli.config import load_config

    values = {} if base is None else base.to_dict()
    values["refine"] = {**values.get("refine", {}), **refine, "passes": list(names)}
    return load_config(overrides=values)


@pytest.fixture
def tuning(monkeypatch: pytest.MonkeyPatch) -> Callable[..., None]:
    """Set constants of the refinement for one test: ``tuning(trim_faces=False)``.

    They are fields of ``rangeseg_cli.config.TUNING``, which ``Config.split`` reads
    when it is accessed; each call starts again from the defaults.
    """
    import dataclasses

    from rangeseg_cli import config

    defaults = config.TUNING

    def _set(**changes: Any) -> None:
        monkeypatch.setattr(config, "TUNING", dataclasses.replace(defaults, **changes))

    return _set


def bad_setting_on_the_command_line(tmp_path: Path, setting: str) -> str:
    """``rangeseg run`` on a small box with ``--set setting``: the last line of its output.

    Asserts it failed without a traceback and wrote nothing.
    """
    import imageio.v3 as iio
    from click.testing import CliRunner

    from rangeseg_cli.cli.main import main
    from rangeseg_cli.synth.scenes import render_scene

    image = tmp_path / "in.png"
    iio.imwrite(image, render_scene("box", size=(32, 32)).image)
    result = CliRunner().invoke(main, ["run", str(image), "-o", str(tmp_path / "out"),
                                       "--set", setting])
    assert result.exit_code != 0 and "Traceback" not in result.output
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    return result.output.strip().splitlines()[-1]


def script_error(main: Callable[[list[str]], Any], argv: list[str],
                 capsys: pytest.CaptureFixture[str]) -> str:
    """A benchmark script's ``main(argv)`` refused: the last line it wrote on stderr.

    Asserts it stopped with exit code 2 and no traceback.
    """
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err and not any("Traceback" in line for line in err)
    return err[-1]


@pytest.fixture(autouse=True)
def _automatic_threads():
    """``--threads`` or a test may set the process's thread count: back to automatic after."""
    yield
    from rangeseg_cli.kernels import parallel

    parallel.set_threads(None)


@pytest.fixture
def runner():
    """click's CliRunner for the command-line tests."""
    from click.testing import CliRunner

    return CliRunner()


@pytest.fixture
def box_png(tmp_path, write_png):
    """A 48x48 box scene written as an 8-bit PNG (:func:`box_scene`)."""
    return write_png(tmp_path / "box.png", box_scene(48).astype(np.uint8))


@pytest.fixture
def write_png():
    """Write a uint8/uint16 array as PNG and return its path."""
    import imageio.v3 as iio

    def _write(path, array):
        iio.imwrite(path, array)
        return path

    return _write


def end_process(proc: subprocess.Popen) -> None:
    """Kill ``proc`` (its whole group when it leads one) if it still runs; reap it, close its pipes."""
    if proc.poll() is None:
        try:
            if os.getpgid(proc.pid) == proc.pid:  # started with start_new_session
                os.killpg(proc.pid, signal.SIGKILL)
            else:
                proc.kill()
        except ProcessLookupError:  # it ended meanwhile
            pass
    for stream in (proc.stdin, proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()
    proc.wait()


@pytest.fixture
def spawn() -> Iterator[Callable[..., subprocess.Popen]]:
    """``subprocess.Popen``, each process it starts ended when the test ends, passed or not.

    A process left running (a test that failed half-way) would hold its files and cores,
    and fail the next module's set-up (``ResourceWarning: subprocess ... is still running``).
    """
    procs: list[subprocess.Popen] = []

    def _spawn(args: Any, **kwargs: Any) -> subprocess.Popen:
        proc = subprocess.Popen(args, **kwargs)
        procs.append(proc)
        return proc

    try:
        yield _spawn
    finally:
        for proc in procs:
            end_process(proc)
