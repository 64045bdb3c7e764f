"""One image of a batch, and the stop flag of the executors that run them.

A :class:`Job` names an image; :func:`process_image` runs a range of the
pipeline's stages on it and writes their artefacts (:data:`STAGE_FILES`,
:data:`STAGE_PICTURES`, :data:`STAGE_CLOUDS`; docs/outputs.md), and a :class:`Record` says what
happened. Both executors of a batch run images so: the local process pool of
:mod:`rangeseg_cli.batch.runner` and the Dask cluster of
:mod:`rangeseg_cli.batch.dask`, each inside a :class:`StopFlag` (Ctrl-C or
SIGTERM stops between images).
"""

from __future__ import annotations

import signal
import threading
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..cell.frames import SharedFrames, check_frame_size
from ..config import Config
from ..errors import OutputError, RangesegError
from ..kernels import parallel
from ..pipeline import STAGES, stage_edges, stage_grow_and_gaps, stage_holdsite, stage_link
from ..stages.rangeimage import (
    MAX_ABS_HEIGHT,
    MAX_EDGE_CODE,
    clipped_value,
    to_heights,
    value_outside,
)
from . import io, render
from .io import Location

#: Files each stage writes (``png`` ones only when ``[output] png``).
STAGE_FILES: dict[str, tuple[str, ...]] = {
    "edges": ("range.npy", "edges.npy"),
    "link": ("components.npy",),
    "grow": ("labels.npy", "surfaces.json"),
    "holdsite": ("holdsite.json",),
}
STAGE_PICTURES: dict[str, tuple[str, ...]] = {
    "edges": ("step.png", "roof.png", "edges.png"),
    "link": ("components.png", "linked.png"),
    "grow": ("labels.png",),
    "holdsite": ("overlay.png",),
}
#: Point clouds of ``[output] ply`` (``holdsite.ply`` only when a site was found).
STAGE_CLOUDS: dict[str, tuple[str, ...]] = {
    "edges": (), "link": (), "grow": ("points.ply",), "holdsite": ("holdsite.ply",),
}


@dataclass(frozen=True)
class Job:
    """One image of a batch: its source file (for ``edges``) and relative stem.

    ``start``: the first of the batch's stages to run for it (``--resume``
    redoes an image from its first stage out of date); None: the batch's first.
    ``noise``: the noise of its heights as the manifest recorded it
    (``noise_sigma``), for stages that start after ``edges``: the noise a
    median filter left cannot be read back from ``range.npy``.
    """

    rel: str
    source: str | None = None
    start: str | None = None
    noise: float | None = None


def job_stages(job: Job, stages: tuple[str, ...]) -> tuple[str, ...]:
    """The stages of ``stages`` that ``job`` runs: from its ``start`` when that is one."""
    return stages[stages.index(job.start):] if job.start in stages else stages


@dataclass
class Record:
    """What happened to one image."""

    rel: str
    status: str  # "done", "failed" or "skipped" ("running" in the manifest until recorded)
    source: str | None = None
    error: str | None = None
    detail: str | None = None
    timings: dict[str, float] = field(default_factory=dict)
    noise_sigma: float | None = None
    clipped_pixels: int = 0
    input_stamp: str | None = None  # the input's version its results were made from
    first_stage: str | None = None  # the first stage run (None: the batch's first)

    def to_dict(self) -> dict[str, Any]:
        """Manifest entry."""
        out: dict[str, Any] = {"status": self.status, "timings": self.timings}
        if self.source is not None:
            out["input"] = self.source
        if self.input_stamp is not None:
            out["input_stamp"] = self.input_stamp
        if self.error is not None:
            out["error"] = self.error
        if self.detail is not None:
            out["traceback"] = self.detail
        if self.noise_sigma is not None:
            out["noise_sigma"] = self.noise_sigma
        if self.clipped_pixels:
            out["clipped_pixels"] = self.clipped_pixels
        return out


def process_image(job: Job, out: Location, config: Config, stages: tuple[str, ...],
                  frames: SharedFrames | None = None) -> Record:
    """Run ``stages`` on one image and write their artefacts; never raises for bad data.

    Parameters
    ----------
    job
        The image: ``source`` is read when its stages start at ``edges``;
        otherwise the earlier stage's files in ``out`` are read. It runs
        ``stages`` from its ``start`` (:func:`job_stages`).
    out
        The output folder (a local path or a :class:`~rangeseg_cli.batch.io.URLPath`).
    config
        The configuration.
    stages
        Consecutive stage names from :data:`~rangeseg_cli.pipeline.STAGES`.
    frames
        The batch's workspace arrays and intrinsics size
        (:func:`shared_frames`); an image of another size fails.

    Returns
    -------
    Record
        ``done`` with stage timings, or ``failed`` with a one-line reason; a
        failed image's files of ``stages`` and the later stages are deleted
        (:func:`remove_failed_outputs`), whichever run wrote them.
    """
    stages = job_stages(job, stages)
    record = Record(rel=job.rel, status="done", source=job.source, first_stage=stages[0])
    base = out / job.rel
    try:
        frames = frames or SharedFrames()
        state = _initial_state(job, out, stages[0], config, frames)
        state["frames"] = frames
        state["then_link"] = "link" in stages  # link writes edges.npy; write it once
        with parallel.blas_one_thread():
            for stage in stages:
                t0 = time.perf_counter()
                _STAGE_RUNNERS[stage](state, base, config)
                record.timings[stage] = time.perf_counter() - t0
        record.noise_sigma = state.get("noise_sigma")
        record.clipped_pixels = state.get("clipped_pixels", 0)
        record.input_stamp = state.get("input_stamp")
        _remove_outputs(base, STAGES[STAGES.index(stages[-1]) + 1:])  # they no longer match
        if not config.output.png:  # pictures of an earlier run would show other results
            _remove_outputs(base, stages, only=STAGE_PICTURES)
        if not config.output.ply:  # and so would its point clouds
            _remove_outputs(base, stages, only=STAGE_CLOUDS)
    except RangesegError as exc:
        record.status, record.error = "failed", str(exc)
    except MemoryError:
        record.status, record.error = "failed", f"{job.source or job.rel}: out of memory"
    except Exception as exc:  # noqa: BLE001 - one bad image never stops the batch
        record.status = "failed"
        record.error = f"{job.source or job.rel}: internal error ({type(exc).__name__}: {exc})"
        record.detail = traceback.format_exc()
    if record.status == "failed":
        remove_failed_outputs(out, record, stages[0])
    return record


def remove_failed_outputs(out: Location, record: Record, first: str) -> None:
    """Delete a failed image's files of stage ``first`` and the later ones.

    They are left from an earlier run (or half written by this one) and would
    otherwise be read, scored or resumed as this run's results; the files of
    the stages before ``first`` are current and stay. The last stage's files go
    first, so a process killed meanwhile leaves the outputs of the first few
    stages only, as a run stopped between stages does. A file that cannot be
    deleted is added to ``record.error``.
    """
    try:
        _remove_outputs(out / record.rel, reversed(STAGES[STAGES.index(first):]))
    except RangesegError as exc:
        record.error = f"{record.error}; its outputs of an earlier run remain ({exc})"


def _remove_outputs(base: Location, stages: Iterable[str], *,
                    only: dict[str, tuple[str, ...]] | None = None) -> None:
    """Delete the image's files (or only those of ``only``) of ``stages``; missing ones are fine."""
    for stage in stages:
        names = only[stage] if only else (STAGE_FILES[stage] + STAGE_PICTURES[stage]
                                          + STAGE_CLOUDS[stage])
        for name in names:
            io.remove_file(stage_file(base, name))


def _initial_state(job: Job, out: Location, first: str, config: Config,
                   frames: SharedFrames) -> dict[str, Any]:
    base = out / job.rel
    if first == "edges":
        if job.source is None:
            raise OutputError(f"{job.rel}: no input image")
        stamp = io.input_stamp(job.source)  # before reading: a change meanwhile is redone
        raw = io.read_image(job.source)
        check_frame_size(raw.shape, frames, job.source)
        top = clipped_value(raw.dtype, config.input)
        return {"z": to_heights(raw, config.input, name=job.source), "input_stamp": stamp,
                "clipped_pixels": 0 if top is None else int(np.count_nonzero(raw == top))}
    z = _read_map(base, "range.npy", "f")
    check_frame_size(z.shape, frames, str(stage_file(base, "range.npy")))
    state: dict[str, Any] = {"z": z}
    if job.noise is not None:  # as edges found it (else estimated where it is needed)
        state["noise_sigma"] = job.noise
    if first in ("link", "grow"):
        state["edges"] = _read_map(base, "edges.npy", "u", z)
    if first == "grow":
        state["components"] = _read_map(base, "components.npy", "i", z)
    if first == "holdsite":
        from ..stages.surfaces import describe_surfaces_and_gaps

        state["labels"] = _read_map(base, "labels.npy", "i", z)
        state["surfaces"], state["gaps"] = describe_surfaces_and_gaps(state["z"],
                                                                      state["labels"], config)
    return state


def _read_map(base: Location, name: str, kind: str, z: np.ndarray | None = None
              ) -> np.ndarray:
    """An earlier stage's array, checked: 2-D, of dtype ``kind`` and the shape of ``z``.

    Raises
    ------
    OutputError
        Naming the file, when it is missing, unreadable or not what that stage writes
        (a file replaced by hand, or left from another image).
    """
    path = stage_file(base, name)
    arr = io.read_npy(path)
    if arr.ndim != 2 or arr.dtype.kind != kind:
        what = {"f": "floating-point", "u": "unsigned integer", "i": "integer"}[kind]
        raise OutputError(f"{path}: holds {arr.dtype} of shape {arr.shape}, not the 2-D "
                          f"{what} map rangeseg writes; run the stages before it again")
    if z is not None and arr.shape != z.shape:
        raise OutputError(f"{path}: shape {arr.shape} differs from the heights "
                          f"{stage_file(base, 'range.npy')} {z.shape}; "
                          "run the stages before it again")
    if kind in "iu":  # labels 0..the pixel count (tables are sized by them), edge codes 0..3
        top = arr.size if kind == "i" else MAX_EDGE_CODE
        bad = value_outside(arr, top)
        if bad is not None:
            what = (f"label {bad} is outside 0..{top} (the pixel count): not a label map"
                    if kind == "i" else f"edge code {bad} is outside 0..{top}: not an edge map")
            raise OutputError(f"{path}: {what} rangeseg writes; run the stages before it again")
    elif kind == "f":
        finite = np.abs(arr[np.isfinite(arr)])
        if finite.size == 0 or float(finite.max()) > MAX_ABS_HEIGHT:
            what = "no valid height" if finite.size == 0 else f"height {finite.max():.3g}"
            raise OutputError(f"{path}: {what}; rangeseg writes heights within "
                              f"+-{MAX_ABS_HEIGHT:.0e}, finite somewhere; run the stages "
                              "before it again")
    return arr


def stage_file(base: Location, name: str) -> Location:
    """Path of the artefact ``name`` of the image whose outputs start with ``base``."""
    return base.parent / f"{base.name}.{name}"


def _run_edges(state: dict[str, Any], base: Location, config: Config) -> None:
    from ..stages.noise import estimate_noise, reduce_noise

    # beyond the paper's noise range the heights are median-filtered first; the
    # manifest's noise is that of the heights segmented (robust, Sec. IV-B)
    state["z"], state["noise_sigma"] = reduce_noise(state["z"], config.input,
                                                    estimate_noise(state["z"]))
    z = state["z"]
    maps = stage_edges(z, config, noise=state["noise_sigma"])
    state["edges"] = maps.codes
    io.write_npy(stage_file(base, "range.npy"), z)
    if not state.get("then_link"):  # else link writes the final edges.npy (code 3 added)
        io.write_npy(stage_file(base, "edges.npy"), maps.codes)
    if config.output.png:
        io.write_png(stage_file(base, "step.png"), render.mask_image(maps.step))
        io.write_png(stage_file(base, "roof.png"), render.mask_image(maps.roof))
        io.write_png(stage_file(base, "edges.png"), render.edge_code_image(maps.codes))


def _run_link(state: dict[str, Any], base: Location, config: Config) -> None:
    codes, components = stage_link(state["z"], state["edges"], config)
    state["edges"], state["components"] = codes, components
    io.write_npy(stage_file(base, "edges.npy"), codes)
    io.write_npy(stage_file(base, "components.npy"), components)
    if config.output.png:
        io.write_png(stage_file(base, "components.png"), render.label_colors(components))
        io.write_png(stage_file(base, "linked.png"), render.edge_code_image(codes))


def _run_grow(state: dict[str, Any], base: Location, config: Config) -> None:
    from ..stages.surfaces import surfaces_to_json

    labels, surfaces, gaps = stage_grow_and_gaps(state["z"], state["edges"],
                                                 state["components"], config,
                                                 noise=state.get("noise_sigma"))
    state["labels"], state["surfaces"], state["gaps"] = labels, surfaces, gaps
    io.write_npy(stage_file(base, "labels.npy"), labels)
    io.write_json(stage_file(base, "surfaces.json"), surfaces_to_json(surfaces),
                  config.output.float_digits)
    if config.output.png:
        io.write_png(stage_file(base, "labels.png"), render.label_colors(labels))
    if config.output.ply:
        from .pointcloud import points_ply

        io.write_bytes(stage_file(base, "points.ply"), points_ply(state["z"], labels, surfaces,
                                                         config.input))


def _run_holdsite(state: dict[str, Any], base: Location, config: Config) -> None:
    frames = state["frames"]
    result = stage_holdsite(state["z"], state["labels"], state["surfaces"], config,
                            gaps=state.get("gaps"), background=frames.background,
                            roi=frames.roi, noise=state.get("noise_sigma"))
    io.write_json(stage_file(base, "holdsite.json"), result.to_dict(), config.output.float_digits)
    if config.output.png:
        io.write_png(stage_file(base, "overlay.png"),
                     render.overlay(state["labels"], result, heights=state["z"]))
    if config.output.ply and result.holdsite is not None:
        from .pointcloud import holdsite_ply

        io.write_bytes(stage_file(base, "holdsite.ply"), holdsite_ply(result.holdsite.to_dict(),
                                                             config.input))
    else:  # no site: the file of an earlier run would show one
        io.remove_file(stage_file(base, "holdsite.ply"))


_STAGE_RUNNERS: dict[str, Callable[[dict[str, Any], Location, Config], None]] = {
    "edges": _run_edges, "link": _run_link, "grow": _run_grow, "holdsite": _run_holdsite,
}


def expected_files(rel: str, stages: Iterable[str], config: Config) -> list[str]:
    """Artefact names the given stages write for one image."""
    names: list[str] = []
    for stage in stages:
        names += STAGE_FILES[stage]
        if config.output.png:
            names += STAGE_PICTURES[stage]
        if config.output.ply:  # holdsite.ply only when a site was found
            names += [n for n in STAGE_CLOUDS[stage] if n != "holdsite.ply"]
    return names


def remove_stale_temporaries(out: Location) -> None:
    """Delete temporary files a killed run left behind (``.<name>.<random>.tmp``)."""
    io.remove_temporaries(out)


class Terminated(KeyboardInterrupt):
    """The batch was asked to stop by SIGTERM (``timeout``, ``docker stop``, a scheduler)."""


class StopFlag:
    """Ctrl-C or SIGTERM sets a flag and the batch stops between images; a second stops at once.

    An interrupt raised inside a numba kernel would surface as a ``SystemError``
    and be recorded as a failed image; a flag checked between images keeps
    every finished image complete and the interrupted one simply not done.
    Inside :meth:`interruptible` (a wait that does no work) it stops at once.
    SIGTERM raises :class:`Terminated` (exit code 143), Ctrl-C
    :class:`KeyboardInterrupt` (130); the manifest is written either way.
    """

    SIGNALS = (signal.SIGINT, signal.SIGTERM)

    def __init__(self) -> None:
        self.requested: int | None = None  # the signal that asked to stop
        self._waiting = False
        self._previous: dict[int, Any] = {}

    def __enter__(self) -> StopFlag:
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handle) for s in self.SIGNALS}
        return self

    def __exit__(self, *exc: object) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)

    def _handle(self, signum: int, frame: Any) -> None:
        if self.requested is None:
            self.requested = signum
            if not self._waiting:
                return  # stop between images
        self._raise()

    def _raise(self) -> None:
        raise Terminated if self.requested == signal.SIGTERM else KeyboardInterrupt

    @contextmanager
    def interruptible(self) -> Iterator[None]:
        """A block where Ctrl-C or SIGTERM stops at once."""
        self.check()
        self._waiting = True
        try:
            yield
        finally:
            self._waiting = False

    def check(self) -> None:
        """Raise :class:`KeyboardInterrupt` (:class:`Terminated`) once asked to stop."""
        if self.requested is not None:
            self._raise()
