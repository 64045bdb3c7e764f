"""Batch processing: images in, per-stage artefacts and a manifest out.

The command line is a thin layer over :func:`run_batch`. Each image is
processed on its own (in this process or in a worker process), through a
range of the pipeline's stages; every artefact is written atomically, so a
killed run leaves only complete files; a bad image is recorded as failed and
the others go on.

Artefacts of an image with relative stem ``rel`` (docs/outputs.md):

========== ==========================================================
stage      files ``OUT/<rel>.<artifact>``
========== ==========================================================
edges      ``range.npy`` (float64 heights, NaN invalid), ``edges.npy``,
           ``step.png``, ``roof.png``, ``edges.png``
link       ``edges.npy`` (with code 3), ``components.npy``,
           ``components.png``, ``linked.png``
grow       ``labels.npy``, ``labels.png``, ``surfaces.json``
holdsite   ``holdsite.json``, ``overlay.png``
========== ==========================================================

With ``[output] ply``, ``grow`` writes ``points.ply`` and ``holdsite``
``holdsite.ply`` (when a site was found): :mod:`.pointcloud`.

Later stages read what the earlier ones wrote, so running the stages one
after another gives the same bytes as running them all at once.

Inputs and the output folder are local paths or URLs (``s3://bucket/out``;
:func:`rangeseg_cli.batch.io.location`); every file operation is in :mod:`.io`.
"""

from __future__ import annotations

import hashlib
import json
import logging
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path, PurePath
from typing import Any

import numpy as np

from .. import __version__
from ..cell.frames import SharedFrames, read_workspace_frames
from ..cell.intrinsics import Intrinsics
from ..config import MOVED_KEYS, STAGE_TABLES, Config, InputConfig, build_config, from_json
from ..errors import ClusterLost, ConfigError, InputError, OutputError
from ..kernels import parallel
from ..pipeline import STAGES
from . import io, outlock, stopping
from .io import Location
from .jobs import (
    STAGE_CLOUDS,
    STAGE_FILES,
    STAGE_PICTURES,
    Job,
    Record,
    StopFlag,
    Terminated,
    expected_files,
    job_stages,
    process_image,
    remove_failed_outputs,
    remove_stale_temporaries,
    stage_file,
)

MANIFEST = "rangeseg-run.json"

#: Significant digits of the manifest's floats: 17 give every float back exactly, so
#: the configuration the stage commands read from it is the one that was run.
MANIFEST_DIGITS = 17
#: Statuses of an image in the manifest: ``running`` from the start of a run until the
#: image is recorded (an image a killed run left so is redone by ``--resume``).
MANIFEST_STATUSES = ("done", "failed", "running")
#: Status of a record of an image a stopped batch never started: its manifest entry goes
#: back to what it was before the batch (absent for a new image); never written.
NOT_STARTED = "not started"
#: Most ``n_jobs`` a batch takes: worker processes here, or images in flight on Dask.
MAX_JOBS = 1024
log = logging.getLogger(__name__)


@dataclass
class BatchSummary:
    """Outcome of a batch, for the summary table and ``--json``."""

    records: list[Record]
    skipped_files: list[str]
    seconds: float
    interrupted: bool = False  # by Ctrl-C or SIGTERM
    terminated: bool = False  # by SIGTERM (exit code 143, not 130)
    error: str | None = None  # why the batch stopped early (the Dask scheduler was lost)

    def count(self, status: str) -> int:
        """Number of images with ``status``."""
        return sum(r.status == status for r in self.records)

    @property
    def stage_seconds(self) -> dict[str, float]:
        """Total seconds per stage over the batch."""
        totals: dict[str, float] = {}
        for r in self.records:
            for stage, seconds in r.timings.items():
                totals[stage] = totals.get(stage, 0.0) + seconds
        return totals

    def to_dict(self) -> dict[str, Any]:
        """Plain summary for ``--json``.

        An image whose name is no valid UTF-8 is keyed in ``errors`` by its
        :func:`~rangeseg_cli.batch.io.percent_name`, listed in ``percent_encoded``.
        """
        failed = [r for r in self.records if r.status == "failed"]
        encoded = sorted(io.percent_name(r.rel) for r in failed if not io.is_utf8(r.rel))
        return {
            "done": self.count("done"), "failed": self.count("failed"),
            "resumed": self.count("skipped"), "not_images": len(self.skipped_files),
            "seconds": self.seconds, "stage_seconds": self.stage_seconds,
            "interrupted": self.interrupted, "terminated": self.terminated,
            "errors": {manifest_key(r.rel): io.printable(r.error or "") for r in failed},
        } | ({"stopped": self.error} if self.error else {}) | (
            {"percent_encoded": encoded} if encoded else {})


def stage_range(first: str, last: str) -> tuple[str, ...]:
    """Stages from ``first`` to ``last`` inclusive."""
    i, j = STAGES.index(first), STAGES.index(last)
    return STAGES[i: j + 1]


# --------------------------------------------------------------------------- batches


def jobs_from_inputs(inputs: Iterable[str | Path], out: Location,
                     names: io.NameFilter | None = None, *, not_frames: Iterable[str] = ()
                     ) -> tuple[list[Job], list[str]]:
    """Jobs for the images among ``inputs`` (files and folders, recursive; paths or URLs).

    ``names``: which files of the folders to read (``--include``, ``--exclude``);
    the files it leaves out are listed with the non-images. ``not_frames``:
    files that are no frames to pick from (the ``[workspace]`` background frame
    and ROI mask, :func:`workspace_files`): found in a folder, they are listed
    with the non-images too; named themselves, they are read.

    Raises
    ------
    InputError
        When an input does not exist, or two images would write the same outputs
        (one file named twice is one job).
    StorageError
        When an input URL cannot be used (see :func:`rangeseg_cli.batch.io.location`).
    """
    inputs = list(inputs)
    images, skipped = io.find_images(inputs, exclude=out, written=WrittenHere(), names=names)
    images, skipped = _frames_only(inputs, images, skipped, not_frames)
    named: set[object] | None = None  # the files named themselves, asked only on a repeat
    seen: dict[str, Location] = {}
    files: set[object] = set()
    jobs = []
    for path, rel in images:
        key = rel.as_posix()
        ident = _identity(path)
        if ident in files:
            if named is None:
                named = {_identity(loc) for loc in map(io.location, inputs) if loc.is_file()}
            if ident in named or _same_file(seen.get(key), path):
                continue  # one file named twice (or inside a folder also named) is one
                # image, under the name it was first found by; two names of it in a folder
                # are two
        if key in seen:
            hint = ("rename one of them" if seen[key].parent == path.parent
                    else "name their folders instead")
            raise InputError(f"{seen[key]} and {path} would both write {out / key}.*; "
                             f"{hint}, or run them separately")
        seen[key] = path
        files.add(ident)
        jobs.append(Job(rel=key, source=str(path)))
    _check_manifest_keys(jobs)
    return jobs, [str(p) for p in skipped]


def _check_manifest_keys(jobs: list[Job]) -> None:
    """Refuse two images with one key in the manifest (:func:`manifest_key`).

    Raises
    ------
    InputError
        Naming both, e.g. ``caf%E9.png`` and a Latin-1 ``café.png`` (byte E9).
    """
    by_key: dict[str, Job] = {}
    for job in jobs:
        key = manifest_key(job.rel)
        other = by_key.setdefault(key, job)
        if other is not job:
            raise InputError(f"{io.printable(other.source or other.rel)} and "
                             f"{io.printable(job.source or job.rel)} have one name in the "
                             f"manifest, {key!r} (a name that is no UTF-8 is written "
                             "percent-encoded); rename one of them")


class WrittenHere:
    """Whether a file below an input folder is an output an earlier run wrote there.

    So it is when its name is ``<stem>.<artifact>`` (:data:`STAGE_FILES`,
    :data:`STAGE_PICTURES`) and the manifest of its folder, or of a folder
    above it up to the one searched, lists the image ``stem`` (its path from
    that folder). A camera frame ``cam.step.png`` no run wrote is read as an
    image. Each manifest is read once.
    """

    ARTIFACTS = tuple(n for names in (*STAGE_FILES.values(), *STAGE_PICTURES.values())
                      for n in names)

    def __init__(self) -> None:
        self.images: dict[str, dict[str, Any]] = {}

    def __call__(self, root: Location, rel: PurePath) -> bool:
        """Whether ``root / rel`` is such an output.

        Raises
        ------
        InputError
            Naming a damaged manifest in an input folder.
        """
        stem = next((rel.name[: -len(a) - 1] for a in self.ARTIFACTS
                     if rel.name.endswith(f".{a}")), "")
        if not stem:
            return False
        folders = rel.parts[:-1]
        folder = root
        for depth in range(len(folders) + 1):
            if "/".join((*folders[depth:], stem)) in self._listed(folder):
                return True
            if depth < len(folders):
                folder = folder / folders[depth]
        return False

    def _listed(self, folder: Location) -> dict[str, Any]:
        key = str(folder)
        if key not in self.images:
            try:
                self.images[key] = read_manifest(folder).get("images", {})
            except OutputError as exc:
                raise InputError(str(exc)) from None
        return self.images[key]


def _frames_only(inputs: list[str | Path], images: list[tuple[Location, PurePath]],
                 skipped: list[Location], not_frames: Iterable[str]
                 ) -> tuple[list[tuple[Location, PurePath]], list[Location]]:
    """``images`` without the ``not_frames`` found in folders, which join ``skipped``."""
    others = {_identity(io.location(name)) for name in not_frames}
    if not others:
        return images, skipped
    others -= {_identity(loc) for loc in map(io.location, inputs) if loc.is_file()}
    kept: list[tuple[Location, PurePath]] = []
    left = list(skipped)
    for path, rel in images:
        if _identity(path) in others:
            left.append(path)
        else:
            kept.append((path, rel))
    return kept, left


def _identity(path: Location) -> object:
    """What names one input file: a local path through links, else the URL.

    A link loop is named as it stands (``realpath`` does not raise): reading it
    then fails with one line (:func:`rangeseg_cli.batch.io.read_image`).
    """
    return Path(os.path.realpath(path)) if isinstance(path, Path) else str(path)


def _same_file(a: Location | None, b: Location) -> bool:
    """Whether two inputs name the same file (local paths through links)."""
    return a is not None and _identity(a) == _identity(b)


def check_inputs_kept(jobs: list[Job], out: Location, stages: tuple[str, ...],
                      skipped_files: Iterable[str] = (),
                      files: Iterable[tuple[str, str]] = ()) -> None:
    """Refuse a batch that would write over, or delete, one of its own input files.

    Parameters
    ----------
    jobs, out, stages
        As for :func:`run_batch`: each job with a ``source`` touches the files of
        ``stages[0]`` and the later stages (written, or removed as stale).
    skipped_files
        The files of the input folders that are not read as images.
    files
        Other files the batch reads, as (what, path): e.g. ``("[workspace]
        background", "out/x.range.npy")`` (:func:`workspace_files`).

    Raises
    ------
    OutputError
        One line naming the input and the image whose output would replace it:
        an input image named as another's output (``x.range.npy`` beside
        ``x.png`` in OUT), a file of ``files``, or a file of an input folder
        named like an output (so not read as an image) that no earlier run
        into ``out`` wrote.
    """
    touched = _touched_files(jobs, out, stages)
    if not touched:
        return
    for what, name in files:
        other = _first_hit(name, touched)
        if other is not None:
            raise OutputError(f"{name} is the {what} file, and this run would overwrite it "
                              f"with an output of {other.source}; choose another output "
                              "folder or move the file")
    for job in jobs:
        other = _first_hit(job.source, touched) if job.source else None
        if other is not None:
            raise OutputError(f"{job.source} is an input, and this run would overwrite it "
                              f"with an output of {other.source}; choose another output "
                              "folder or rename one of them")
    ours = None
    for name in skipped_files:
        other = _first_hit(name, touched)
        if other is None:
            continue
        ours = read_manifest(out).get("images", {}) if ours is None else ours
        if other.rel not in ours:  # not a file an earlier run of rangeseg wrote there
            raise OutputError(f"{name} is in an input folder (named like an output of "
                              "rangeseg, it is not read as an image), and this run would "
                              f"overwrite it with an output of {other.source}; choose "
                              "another output folder or rename it")


def workspace_files(config: Config) -> list[tuple[str, str]]:
    """The files ``[workspace] background`` and ``roi`` name, as (key, path); none for ``""``."""
    ws = config.workspace
    return [(f"[workspace] {key}", path)
            for key, path in (("background", ws.background), ("roi", ws.roi)) if path]


def _touched_files(jobs: list[Job], out: Location, stages: tuple[str, ...]
                   ) -> dict[str, Job]:
    """The output files of the jobs with a source, by :func:`_output_keys`: their jobs."""
    names = [n for s in STAGES[STAGES.index(stages[0]):]
             for n in STAGE_FILES[s] + STAGE_PICTURES[s] + STAGE_CLOUDS[s]]
    folders: dict[str, list[str]] = {}
    touched: dict[str, Job] = {}
    for job in (j for j in jobs if j.source is not None):
        for name in names:
            path = stage_file(out / job.rel, name)
            touched.update((key, job) for key in _output_keys(path, folders))
    return touched


def _output_keys(path: Location, folders: dict[str, list[str]]) -> list[str]:
    """Names of an output file as typed and with its folder's links resolved.

    ``folders`` caches the forms of each folder (one ``realpath`` per folder).
    """
    if isinstance(path, io.URLPath):
        return [str(path)]
    parent = str(path.parent)
    if parent not in folders:
        folders[parent] = list({os.path.abspath(parent), os.path.realpath(parent)})
    return [os.path.join(folder, path.name) for folder in folders[parent]]


def _first_hit(name: str, touched: dict[str, Job]) -> Job | None:
    """The job whose output is the file ``name`` (or the file its link points to)."""
    keys = [name] if io.is_url(name) else [os.path.abspath(name), os.path.realpath(name)]
    return next((touched[k] for k in keys if k in touched), None)


def jobs_from_output(out: Location) -> list[Job]:
    """Jobs for every image the ``edges`` stage has written into ``out``."""
    if not out.is_dir():
        raise OutputError(f"{out}: no such output folder; run `rangeseg edges` first")
    rels = io.find_outputs(out, ".range.npy")
    if not rels:
        raise OutputError(f"{out}: holds no results of `rangeseg edges` (*.range.npy)")
    images = read_manifest(out).get("images", {})
    return [Job(rel=r, noise=recorded_noise(images.get(r, {}))) for r in rels]


def manifest_key(rel: str) -> str:
    """An image's key in the manifest and ``--json``.

    Its name, or its :func:`~rangeseg_cli.batch.io.percent_name` when that is no valid UTF-8.
    """
    return rel if io.is_utf8(rel) else io.percent_name(rel)


def _encode_names(data: dict[str, Any]) -> dict[str, Any]:
    """The manifest as written: names that are no UTF-8 percent-encoded, and so marked.

    The key and ``input`` of such an image are
    :func:`~rangeseg_cli.batch.io.percent_name` forms, and its entry has
    ``"name_encoding": "percent"``; its messages have the bytes as ``%XX``.
    """
    images = {}
    for rel, entry in data.get("images", {}).items():
        entry = {k: io.printable(v) if k in ("error", "traceback") else v
                 for k, v in entry.items()}
        if not (io.is_utf8(rel) and io.is_utf8(entry.get("input", ""))):
            entry["name_encoding"] = "percent"
            rel = io.percent_name(rel)
            if "input" in entry:
                entry["input"] = io.percent_name(entry["input"])
        images[rel] = entry
    return data | {"images": images}


def _decode_names(images: dict[str, Any]) -> dict[str, Any]:
    """The entries of a manifest's images under their names (:func:`_encode_names` undone)."""
    out = {}
    for rel, entry in images.items():
        if entry.get("name_encoding") == "percent":
            entry = {k: v for k, v in entry.items() if k != "name_encoding"}
            rel = io.name_from_percent(rel)
            if "input" in entry:
                entry["input"] = io.name_from_percent(entry["input"])
        out[rel] = entry
    return out


def read_manifest(out: Location) -> dict[str, Any]:
    """The manifest in ``out``, or an empty one.

    Raises
    ------
    OutputError
        One line naming the file, when it is not JSON or not shaped as rangeseg
        writes it (what is read from it is checked: :func:`_manifest_problem`).
    """
    path = out / MANIFEST
    if not path.exists():
        return {}
    data = io.read_json(path)
    problem = _manifest_problem(data)
    if problem:
        raise OutputError(f"{path}: not a manifest of rangeseg ({problem}); repair it, or "
                          "delete it and redo the images with --overwrite")
    return data | {"images": _decode_names(data["images"])}


def _manifest_problem(data: Any) -> str | None:
    """What is wrong with a manifest's shape, or ``None`` when it is right.

    An object, with ``config`` an object and ``images`` an object of entries
    (:func:`_entry_problem`; each with a status of :data:`MANIFEST_STATUSES`),
    both present: what :func:`plan_jobs`, :func:`manifest_config` and
    :class:`_Manifest` read.
    """
    if not isinstance(data, dict):
        return f"it holds {_json_kind(data)}, not an object"
    for key in ("config", "images"):  # every manifest rangeseg writes has both
        if key not in data:
            return f'"{key}" is missing; rangeseg writes it in every manifest'
    if not isinstance(data["config"], dict):
        return f'"config" is {_json_kind(data["config"])}, not an object of tables'
    images = data["images"]
    if not isinstance(images, dict):
        return f'"images" is {_json_kind(images)}, not an object of images'
    for rel, entry in images.items():
        problem = _entry_problem(entry)
        if problem:
            return f'"images" entry {rel!r}: {problem}'
    return None


def _entry_problem(entry: Any) -> str | None:
    """What is wrong with one image's manifest entry, or ``None``."""
    if not isinstance(entry, dict):
        return f"{_json_kind(entry)}, not an object"
    for key in ("status", "config", "input", "input_stamp"):
        if key in entry and not isinstance(entry[key], str):
            return f'"{key}" is {_json_kind(entry[key])}, not a string'
    stages = entry.get("stages", [])
    if not (isinstance(stages, list) and all(isinstance(s, str) for s in stages)):
        return '"stages" is not a list of stage names'
    digests = entry.get("stage_configs", {})
    if not (isinstance(digests, dict) and all(isinstance(d, str) for d in digests.values())):
        return '"stage_configs" is not an object of stage names and digests'
    if entry.get("name_encoding", "percent") != "percent":
        return f'"name_encoding" is {json.dumps(entry["name_encoding"])}; allowed: "percent"'
    if entry.get("status") not in MANIFEST_STATUSES:
        what = json.dumps(entry["status"]) if "status" in entry else "missing"
        return f'"status" is {what}; allowed: ' + ", ".join(map(json.dumps, MANIFEST_STATUSES))
    return None


def _stage_configs(entry: dict[str, Any], whole: str, digests: dict[str, str]
                   ) -> dict[str, str]:
    """The entry's current stages and the digests of the tables they were made with.

    ``whole`` and ``digests`` (:meth:`~rangeseg_cli.config.Config.digest` and
    :meth:`~rangeseg_cli.config.Config.stage_digests` of this run's
    configuration) stand in for a manifest written before per-stage digests
    (``stage_configs``): there the entry's stages are current under the same
    whole configuration only.
    """
    recorded = entry.get("stage_configs")
    if isinstance(recorded, dict):
        return {s: d for s, d in recorded.items() if s in entry.get("stages", [])}
    if entry.get("config") != whole:
        return {}
    return {s: digests[s] for s in entry.get("stages", []) if s in digests}


def _json_kind(value: Any) -> str:
    """``a number``, ``a list``, ...: a JSON value's kind, for messages."""
    if value is None or isinstance(value, bool):
        return json.dumps(value)
    kinds = {dict: "an object", list: "a list", str: "a string", int: "a number",
             float: "a number"}
    return kinds.get(type(value), type(value).__name__)


def manifest_config(out: Location) -> Config | None:
    """The configuration recorded in ``out``'s manifest, if any.

    Raises
    ------
    ConfigError
        When the manifest's settings are not this version's: an older
        rangeseg's keys are named, with what to do.
    """
    data = read_manifest(out).get("config")
    if not isinstance(data, dict):
        return None
    where = str(out / MANIFEST)
    try:
        return build_config(from_json(data), where)
    except ConfigError as exc:
        if any(isinstance(keys, dict) and any((table, key) in MOVED_KEYS for key in keys)
               for table, keys in data.items()):
            raise ConfigError(f"{where}: made by an older rangeseg, whose settings changed "
                              f"({str(exc).removeprefix(where + ': ')}); give --config or "
                              "--preset, or run the images again with --overwrite") from None
        raise


def plan_jobs(jobs: list[Job], out: Location, config: Config, stages: tuple[str, ...], *,
              resume: bool, overwrite: bool, frames: SharedFrames | None = None
              ) -> tuple[list[Job], list[Record]]:
    """Split jobs into those to run and records of the others.

    ``frames``: the batch's workspace arrays, whose content counts as the
    holdsite's settings (:func:`stage_digests`).

    Returns
    -------
    todo, records
        The jobs to run; ``skipped`` records of images already complete
        (``resume``), and ``failed`` ones of images whose earlier stage is
        missing or out of date (stage commands, see :func:`_refuse_stale`).

    Raises
    ------
    OutputError
        When ``out`` already holds results for these images and neither
        ``resume`` nor ``overwrite`` is set.
    """
    images = read_manifest(out).get("images", {})
    jobs, refused = _refuse_stale(jobs, images, stages[0], config)
    if overwrite:
        return jobs, refused
    exists = io.file_checker(out)
    done_before = [j for j in jobs if j.rel in images or exists(f"{j.rel}.edges.npy")]
    if not resume:
        if done_before:
            raise OutputError(
                f"{out} already holds results for {len(done_before)} of these images "
                f"(e.g. {done_before[0].rel}); use --resume to complete what is missing "
                "or --overwrite to redo all")
        return jobs, refused
    todo, skipped = [], list(refused)
    whole, digests = config.digest(), stage_digests(config, frames)
    for job in jobs:
        entry = images.get(job.rel, {})
        made = _stage_configs(entry, whole, digests)
        current = [entry.get("status") == "done" and made.get(s) == digests[s]
                   and all(exists(f"{job.rel}.{n}") for n in expected_files(job.rel, (s,), config))
                   for s in stages]
        if not _same_input(job, entry, stages[0]) or not current[0]:
            todo.append(job)
        elif all(current):
            skipped.append(Record(rel=job.rel, status="skipped", source=job.source))
        else:  # its stages before the first out of date stay: redone from that one on
            start = stages[current.index(False)]
            if start == "link" and "edges" in stages:  # link wrote over edges.npy: from edges
                start = "edges"
            todo.append(replace(job, start=start, noise=recorded_noise(entry)))
    return todo, skipped


def recorded_noise(entry: dict[str, Any]) -> float | None:
    """The manifest entry's ``noise_sigma`` when it is a number >= 0, else None."""
    value = entry.get("noise_sigma")
    if isinstance(value, bool) or not isinstance(value, int | float) or not value >= 0:
        return None
    return float(value)


def stage_digests(config: Config, frames: SharedFrames | None = None) -> dict[str, str]:
    """Each stage's settings digest (``Config.stage_digests``), the workspace pixels in holdsite's.

    The config names the background and ROI files; their content counts too,
    so ``--resume`` redoes the holdsites when a file changed under its name.
    """
    digests = config.stage_digests()
    if frames is not None and frames.digest:
        both = f"{digests['holdsite']}:{frames.digest}".encode()
        digests["holdsite"] = hashlib.sha256(both).hexdigest()[:16]
    return digests


def _same_input(job: Job, entry: dict[str, Any], first: str) -> bool:
    """Whether ``job``'s input is the version its recorded results were made from.

    Only a run that reads the input (from ``edges``) asks: the stage commands
    after it go on from the files in OUT. An entry with no stamp (a manifest
    written before stamps were recorded) cannot vouch for its input: redone.
    """
    if first != STAGES[0] or job.source is None:
        return True
    stamp = entry.get("input_stamp")
    return stamp is not None and stamp == io.input_stamp(job.source)


def _refuse_stale(jobs: list[Job], images: dict[str, Any], first: str, config: Config
                  ) -> tuple[list[Job], list[Record]]:
    """Jobs whose earlier stage is current, and failed records for the others.

    A stage command (``link``, ``grow``, ``holdsite``) needs the result of the
    stage before it, made with the settings it runs with (the tables of
    :data:`~rangeseg_cli.config.STAGE_TABLES` up to that stage). The manifest
    lists, per image, the stages whose outputs are current and the digests of
    their settings: running a stage again (``edges --overwrite``) drops the
    later ones, so ``holdsite`` never combines new heights with old labels.
    An image the manifest does not list (a folder copied without it) is
    refused too: nothing tells what made its files. A refused image's entry
    and files are left as they are: nothing was run.
    """
    if first == STAGES[0]:
        return jobs, []
    before = STAGES[STAGES.index(first) - 1]
    whole, digests = config.digest(), config.stage_digests()
    wanted = digests[before]
    upto = list(STAGE_TABLES)[: STAGES.index(before) + 1]
    tables = ", ".join(f"[{t}]" for stage in upto for t in STAGE_TABLES[stage])
    todo, refused = [], []
    again = (f"`rangeseg {before} IMAGES -o OUT --resume`" if before == STAGES[0]
             else f"`rangeseg {before} OUT --resume`")
    for job in jobs:
        entry = images.get(job.rel)
        made = _stage_configs(entry, whole, digests) if isinstance(entry, dict) else {}
        if made.get(before) != wanted:
            why = _why_stale(entry, made, before, tables)
            refused.append(Record(rel=job.rel, status="failed", error=(
                f"{job.rel}: its `{before}` result {why}; run {again} first" + (
                    ", or give this command the settings that made it"
                    if before in made else ""))))
        else:
            todo.append(job)
    return todo, refused


def _why_stale(entry: Any, made: dict[str, str], before: str, tables: str) -> str:
    """Why an image's ``before`` result cannot go on (:func:`_refuse_stale`)."""
    if not isinstance(entry, dict):
        return "is not recorded in the manifest (nothing tells what made its files)"
    if before in made:
        return f"was made with other settings of {tables} than these"
    if entry.get("status") == "failed":
        return "is missing: the image failed in the last run"
    return ("is missing, or out of date since an earlier stage was redone (or the "
            "manifest was written before per-stage settings)")


class _Manifest:
    """The batch manifest, updated as images finish and rewritten atomically."""

    def __init__(self, out: Location, config: Config, command: str, stages: tuple[str, ...],
                 frames: SharedFrames | None = None):
        self.out, self.config, self.stages = out, config, stages
        self.data = read_manifest(out) if out.exists() else {}
        # the configuration the results were last made with: recorded once an image is run
        # (the stage commands' default); a command that runs none leaves it as it was
        self.whole, self.digests = config.digest(), stage_digests(config, frames)
        self.header: dict[str, Any] = {"version": __version__, "config": config.to_dict(),
                                       "config_digest": self.whole, "command": command}
        if "config" not in self.data:
            self.data.update(self.header)
        self.data.setdefault("images", {})
        self.last_write = 0.0
        self.before: dict[str, Any] = {}  # entries of the images to run, before the run

    def forget(self, rel: str) -> None:
        """An image the batch never started: its entry as before the batch (or none)."""
        old = self.before.get(rel)
        if old is None:
            self.data["images"].pop(rel, None)
        else:
            self.data["images"][rel] = old

    def add(self, record: Record) -> None:
        if record.status == "skipped":
            return
        if self.header:  # the first image run: its configuration is the folder's now
            self.data.update(self.header)
            self.header = {}
        entry = record.to_dict()
        old = self.data["images"].get(record.rel, {})
        first = STAGES.index(record.first_stage or self.stages[0])
        # the stages before these stay current when the tables they read are unchanged;
        # these and the later ones are redone or lost
        made = _stage_configs(old, self.whole, self.digests)
        kept = {s: d for s, d in made.items()
                if s in STAGES and STAGES.index(s) < first and self.digests.get(s) == d}
        if record.status == "done":
            kept.update({s: self.digests[s] for s in self.stages if STAGES.index(s) >= first})
        entry["stages"] = [s for s in STAGES if s in kept]
        entry["stage_configs"] = {s: kept[s] for s in entry["stages"]}
        entry["config"] = self.whole
        for key in ("input", "input_stamp", "noise_sigma", "clipped_pixels"):
            if key not in entry and key in old:
                entry[key] = old[key]
        self.data["images"][record.rel] = entry
        if time.monotonic() - self.last_write > 2.0:
            self.write()

    def start(self, todo: list[Job]) -> None:
        """Write it before any image: OUT exists then, also on an object store.

        Every image about to run is recorded ``running``, its stages from the
        first one run on no longer current: a run killed before it records an
        image (SIGKILL, power loss) leaves that image to be redone, never its
        files of the new settings under the entry of the old ones.
        """
        for job in todo:
            first = STAGES.index(job_stages(job, self.stages)[0])
            self.before[job.rel] = self.data["images"].get(job.rel)
            entry = dict(self.data["images"].get(job.rel, {}))
            entry["status"] = "running"
            entry["stages"] = [s for s in entry.get("stages", [])
                               if s in STAGES and STAGES.index(s) < first]
            self.data["images"][job.rel] = entry
        io.make_folder(self.out)
        io.write_json(self.out / MANIFEST, _encode_names(self.data), digits=MANIFEST_DIGITS)

    def write(self, summary: BatchSummary | None = None) -> None:
        if summary is not None:
            self.data["summary"] = summary.to_dict()
        io.make_folder(self.out)
        io.write_json(self.out / MANIFEST, _encode_names(self.data), digits=MANIFEST_DIGITS)
        self.last_write = time.monotonic()


def run_batch(jobs: list[Job], out: Location, config: Config, stages: tuple[str, ...], *,
              n_jobs: int | None = None, resume: bool = False, overwrite: bool = False,
              skipped_files: list[str] | None = None, command: str = "run",
              on_result: Callable[[Record], None] | None = None,
              on_start: Callable[[int], None] | None = None,
              executor: str = "local", scheduler: str | None = None,
              intrinsics: Intrinsics | None = None) -> BatchSummary:
    """Process ``jobs`` through ``stages`` and write the manifest.

    Parameters
    ----------
    jobs
        Images to process (:func:`jobs_from_inputs` or :func:`jobs_from_output`).
    out
        Output folder (created if missing): a local path or a
        :class:`~rangeseg_cli.batch.io.URLPath` (:func:`rangeseg_cli.batch.io.location`).
    config
        The configuration, recorded in the manifest with its digest.
    stages
        Consecutive stages to run (e.g. ``STAGES`` for ``run``).
    n_jobs
        1 to :data:`MAX_JOBS`. Local: worker processes, at most one per image
        to run (``None`` or 1 runs in this process). Dask: at most this many
        images in flight on the cluster at once (``None``: all are submitted
        and the cluster's workers set the parallelism).
    resume, overwrite
        See :func:`plan_jobs`. Stage commands after ``edges`` pass ``overwrite``.
    skipped_files
        Non-image files found in the inputs, for the summary.
    command
        Recorded in the manifest.
    on_result, on_start
        Callbacks for progress: ``on_start(number of images to process)`` and
        ``on_result(record)`` for each finished image.
    executor, scheduler
        Where images are processed (:data:`EXECUTORS`): ``"local"``, ``n_jobs``
        processes of this machine, or ``"dask"``, one task per image on the
        Dask cluster whose scheduler is at ``scheduler`` (``tcp://HOST:PORT``;
        see :mod:`rangeseg_cli.batch.dask` for the storage it needs).
    intrinsics
        The camera intrinsics the configuration's ``[input] intrinsics``
        came from: when they give the image size, an image of another size fails.

    Returns
    -------
    BatchSummary
        Per-image records, the skipped files and the wall time; ``error`` says
        why a Dask batch stopped early (its scheduler was lost), and the
        manifest records what finished before.

    Raises
    ------
    rangeseg_cli.errors.ClusterError
        With ``executor="dask"``, before any work, when the cluster cannot be
        used (dask missing, scheduler unreachable, workers without rangeseg
        or without the shared storage).
    ConfigError
        Before any work, when a file ``[workspace]`` names (with the
        ``holdsite`` stage) cannot be read or used (:func:`shared_frames`).
    OutputError, rangeseg_cli.errors.StorageError
        When ``out`` holds results and neither ``resume`` nor ``overwrite`` is
        set, or its store cannot be written (an https:// URL:
        :func:`~rangeseg_cli.batch.io.check_output_protocol`), or its manifest is
        damaged, or the batch would write over an input file
        (:func:`check_inputs_kept`).
    ValueError
        For ``n_jobs`` outside 1..:data:`MAX_JOBS`.
    """
    t0 = time.perf_counter()
    if n_jobs is not None and not 1 <= n_jobs <= MAX_JOBS:
        raise ValueError(f"`n_jobs` = {n_jobs!r}: expected 1 to {MAX_JOBS}, or None")
    io.check_output_protocol(out)
    check_inputs_kept(jobs, out, stages, skipped_files or [], workspace_files(config))
    frames = shared_frames(config, stages, intrinsics)
    with (_executor(executor, scheduler, n_jobs) as execute,  # dask: connect before any work
          outlock.held(out, command)):  # then one batch at a time in OUT
        remove_stale_temporaries(out)
        todo, records = plan_jobs(jobs, out, config, stages, resume=resume,
                                  overwrite=overwrite, frames=frames)
        io.make_folder(out)
        manifest = _Manifest(out, config, command, stages, frames)
        manifest.start(todo)
        refused = [r for r in records if r.status == "failed"]
        records = [r for r in records if r.status != "failed"]
        if on_start is not None:
            on_start(len(todo) + len(refused))
        interrupted, terminated, error = False, False, None

        def finish(record: Record, *, ran: bool = True) -> None:
            if record.status == NOT_STARTED:  # a stopped batch: its files are untouched
                manifest.forget(record.rel)
                return
            records.append(record)
            if ran:  # a refused image: its entry and files stay as they are
                manifest.add(record)
            if on_result is not None:
                on_result(record)

        for record in refused:
            finish(record, ran=False)
        try:
            execute(todo, out, config, stages, frames, finish)
        except KeyboardInterrupt as exc:
            interrupted, terminated = True, isinstance(exc, Terminated)
        except ClusterLost as exc:
            error = str(exc)
        summary = BatchSummary(records=sorted(records, key=lambda r: r.rel),
                               skipped_files=skipped_files or [],
                               seconds=time.perf_counter() - t0, interrupted=interrupted,
                               terminated=terminated, error=error)
        manifest.write(summary)
    return summary


def shared_frames(config: Config, stages: tuple[str, ...], intrinsics: Intrinsics | None = None
                  ) -> SharedFrames:
    """What every image of the batch is checked against or combined with, read once.

    The files of ``[workspace]`` when the batch runs the ``holdsite`` stage
    (:func:`~rangeseg_cli.cell.frames.read_workspace_frames`), and the image size
    of ``intrinsics`` when they give one and the batch reads images.

    Raises
    ------
    ConfigError
        One line naming a ``[workspace]`` file that cannot be read or used.
    """
    frames = read_workspace_frames(config) if "holdsite" in stages else SharedFrames()
    if intrinsics is not None and intrinsics.width and intrinsics.height and (
            stages[0] == STAGES[0]):
        frames = replace(frames, size=(intrinsics.height, intrinsics.width),
                         size_name=intrinsics.source)
    return frames


#: Where a batch can run: this machine's process pool, or an existing Dask cluster.
EXECUTORS = ("local", "dask")
_Execute = Callable[[list[Job], Location, Config, tuple[str, ...], SharedFrames,
                     Callable[[Record], None]], None]


@contextmanager
def _executor(executor: str, scheduler: str | None, n_jobs: int | None
              ) -> Iterator[_Execute]:
    """The function that processes the planned jobs; a Dask client connects first."""
    if executor == "local":
        yield lambda todo, out, config, stages, frames, finish: _execute(
            todo, out, config, stages, frames, n_jobs or 1, finish)
    elif executor == "dask":
        if not scheduler:
            raise ValueError("executor='dask' needs `scheduler`, the address of a Dask "
                             "scheduler such as tcp://10.0.0.5:8786")
        from .dask import connect, execute_on_dask

        with connect(scheduler) as client:
            yield lambda todo, out, config, stages, frames, finish: execute_on_dask(
                todo, out, config, stages, client, finish, limit=n_jobs, frames=frames)
    else:
        raise ValueError(f"`executor` = {executor!r}: expected one of {', '.join(EXECUTORS)}")


def _execute(todo: list[Job], out: Location, config: Config, stages: tuple[str, ...],
             frames: SharedFrames, n_jobs: int, finish: Callable[[Record], None]) -> None:
    workers = min(n_jobs, len(todo))  # a worker more than images would only start up
    with StopFlag() as stop:
        if workers <= 1:
            _execute_here(todo, out, config, stages, frames, finish, stop)
            return
        _execute_pool(todo, out, config, stages, frames, workers, finish, stop)


def _execute_here(todo: list[Job], out: Location, config: Config, stages: tuple[str, ...],
                  frames: SharedFrames, finish: Callable[[Record], None], stop: StopFlag
                  ) -> None:
    """Process ``todo`` in this process; a stop is honoured between images and inside one.

    The pipeline's long loops call :func:`rangeseg_cli.batch.stopping.checkpoint`,
    which raises here once Ctrl-C or SIGTERM has asked to stop: the image in
    progress stays ``running`` (redone by ``--resume``), the later ones were
    never started (:data:`NOT_STARTED`).
    """
    for k, job in enumerate(todo):
        try:
            stop.check()
        except KeyboardInterrupt:
            _not_started(todo[k:], finish)
            raise
        try:
            with stopping.stop_checks(stop.check):
                record = process_image(job, out, config, stages, frames)
        except KeyboardInterrupt:
            _not_started(todo[k + 1:], finish)
            raise
        finish(record)


def _not_started(jobs: Iterable[Job], finish: Callable[[Record], None]) -> None:
    """Record ``jobs`` as never started (their manifest entries go back as they were)."""
    for job in jobs:
        finish(Record(rel=job.rel, status=NOT_STARTED, source=job.source))


def _execute_pool(todo: list[Job], out: Location, config: Config, stages: tuple[str, ...],
                  frames: SharedFrames, n_jobs: int, finish: Callable[[Record], None],
                  stop: StopFlag) -> None:
    """Process ``todo`` on ``n_jobs`` worker processes; a new pool when a worker dies."""
    warm_up(config)
    left = list(todo)
    while left:
        rest = _pool_round(left, out, config, stages, frames, n_jobs, finish, stop)
        if len(rest) == len(left):  # a pool that broke before taking any image: no retry
            for job in rest:
                finish(_lost(job, out, job_stages(job, stages)[0]))
            return
        left = rest


def _pool_round(jobs: list[Job], out: Location, config: Config, stages: tuple[str, ...],
                frames: SharedFrames, n_jobs: int, finish: Callable[[Record], None],
                stop: StopFlag) -> list[Job]:
    """Run ``jobs`` on one pool; the jobs not yet submitted when a worker died.

    A worker that dies (killed by the OOM killer or by hand) breaks the pool:
    the images in flight then are recorded failed -- any of them may be the
    one that took the memory -- with their partial outputs removed, and the
    rest of the batch goes on in a new pool.
    """
    # At most 2 images per worker in flight: memory stays bounded for any batch size.
    pending: dict[Future[Record], Job] = {}
    submitted = 0
    stopping_now = multiprocessing.Event()  # set: the workers stop mid-image, start none
    with ProcessPoolExecutor(max_workers=n_jobs, initializer=_init_worker,
                             initargs=(parallel.per_process(n_jobs), os.getpid(),
                                       stopping_now)) as pool:
        try:
            for job in jobs:
                stop.check()
                pending[pool.submit(_work, job, out, config, stages, frames)] = job
                submitted += 1
                while len(pending) >= 2 * n_jobs:
                    _collect(pending, finish, stop)
            while pending:
                _collect(pending, finish, stop)
        except BrokenProcessPool:
            pool.shutdown(wait=True)  # the other workers are stopped: none writes any more
            if stop.requested is not None:  # a SIGTERM to the whole group ended them too:
                _keep_finished(pending, finish)  # the others stay `running`, redone later
                _not_started(jobs[submitted:], finish)
                stop.check()
            for fut, job in pending.items():
                finish(fut.result() if _finished(fut) else
                       _lost(job, out, job_stages(job, stages)[0]))
            return jobs[submitted:]
        except KeyboardInterrupt:
            stopping_now.set()
            pool.shutdown(wait=True, cancel_futures=True)
            _keep_finished(pending, finish)  # and those no worker started
            _not_started([job for fut, job in pending.items() if fut.cancelled()]
                         + jobs[submitted:], finish)
            raise
    return []


#: In a worker process: the batch's stop event (:func:`_init_worker`), else None.
_worker_stop: Any = None


def _work(job: Job, out: Location, config: Config, stages: tuple[str, ...],
          frames: SharedFrames) -> Record:
    """:func:`process_image` in a worker, which a stop of the batch ends mid-image.

    Once the batch is stopping, an image not yet begun is :data:`NOT_STARTED`
    and one in progress raises ``KeyboardInterrupt`` at its next
    :func:`~rangeseg_cli.batch.stopping.checkpoint` (it stays ``running``).
    """
    event = _worker_stop
    if event is None:
        return process_image(job, out, config, stages, frames)
    if event.is_set():
        return Record(rel=job.rel, status=NOT_STARTED, source=job.source)

    def check() -> None:
        if event.is_set():
            raise KeyboardInterrupt

    with stopping.stop_checks(check):
        return process_image(job, out, config, stages, frames)


def _finished(fut: Future[Record]) -> bool:
    """Whether a worker finished ``fut``'s image (its record can be had)."""
    return fut.done() and not fut.cancelled() and fut.exception() is None


def _keep_finished(pending: dict[Future[Record], Job], finish: Callable[[Record], None]
                   ) -> None:
    """Record the images of ``pending`` that the workers finished before a stop."""
    for fut in pending:
        if _finished(fut):
            finish(fut.result())


def _lost(job: Job, out: Location, first: str) -> Record:
    """The failed record of an image in flight when a worker died; its outputs removed."""
    record = Record(rel=job.rel, status="failed", source=job.source, first_stage=first, error=(
        f"{job.source or job.rel}: its worker process died (killed, or out of memory?) while "
        "it was in progress; rerun with --resume, with fewer --jobs if memory is short"))
    remove_failed_outputs(out, record, first)
    return record


def warm_up(config: Config) -> None:
    """Run the pipeline once on a tiny scene, so compiled kernels are loaded.

    Worker processes forked afterwards inherit them instead of each loading
    numba's cache again (about 0.7 s per worker).
    """
    from ..pipeline import run_pipeline

    yy, xx = np.mgrid[0:32, 0:32]
    scene = 20.0 + 0.5 * xx + np.where((abs(yy - 16) < 8) & (abs(xx - 16) < 8), 60.0, 0.0)
    plain = replace(config, input=InputConfig(),  # not the workspace files of other frames
                    workspace=replace(config.workspace, background="", roi=""))
    try:
        run_pipeline(scene, plain)
    except Exception:  # noqa: BLE001 - a warm-up never stops a batch; the real run reports
        log.debug("warm-up failed", exc_info=True)


def _collect(pending: dict[Future[Record], Job], finish: Callable[[Record], None],
             stop: StopFlag) -> None:
    """Finish the images done within a short wait, taking them out of ``pending``.

    A future whose worker died raises ``BrokenProcessPool`` and stays in
    ``pending`` (:func:`_pool_round` names its image); a stop raised here
    leaves only unfinished images in it.
    """
    done, _ = wait(list(pending), timeout=0.2, return_when=FIRST_COMPLETED)
    for fut in done:
        record = fut.result()
        del pending[fut]
        finish(record)
    stop.check()


def _init_worker(threads: int = 1, parent: int | None = None, stop: Any = None) -> None:
    """Set up a worker process: Ctrl-C, its threads and BLAS threads are the batch's.

    ``threads`` is the worker's share of the cores for the kernels of one
    image (:func:`rangeseg_cli.kernels.parallel.per_process`); ``parent`` the pid of
    the batch's process, which the worker does not outlive
    (:func:`_exit_with_parent`); ``stop`` the batch's stop event (a
    ``multiprocessing.Event``), which ends the worker's images (:func:`_work`).

    Workers leave Ctrl-C to the main process, which stops the batch cleanly;
    SIGTERM ends a worker (a broken pool terminates the others with it).
    Each worker keeps its BLAS to one thread: the batch already uses a process
    per core, and OpenBLAS's own threads (one per core in every worker) would
    spin against each other; on 2 cores that took ``--jobs 2`` from about
    1.6x to 1.1x the throughput of ``--jobs 1``.
    """
    global _worker_stop
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # not the batch's StopFlag, inherited by fork
    _worker_stop = stop
    if parent is not None:
        _exit_with_parent(parent)
    parallel.set_threads(threads)
    from threadpoolctl import threadpool_limits

    threadpool_limits(limits=1, user_api="blas")  # set now; kept until the worker exits


#: ``prctl`` option: the signal a process gets when its parent dies (Linux).
_PR_SET_PDEATHSIG = 1


def _exit_with_parent(parent: int) -> None:
    """Linux: end this worker with SIGTERM when the batch's process ``parent`` dies.

    A batch killed with SIGKILL (by an OOM killer, a scheduler's time limit,
    ``kill -9``) cannot stop its pool, and the workers waited for work
    forever, each holding its memory. Elsewhere, or where ``prctl`` cannot
    be called, nothing changes.
    """
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
            return
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # it died before the request was made
        os._exit(1)


def default_jobs() -> int:
    """Default number of worker processes: the cores this process may use (<= MAX_JOBS)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    return min(max(1, cores), MAX_JOBS)
