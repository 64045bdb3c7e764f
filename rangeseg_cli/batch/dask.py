"""Run a batch on an existing Dask distributed cluster: one task per image (issue 10).

:func:`execute_on_dask` is the cluster counterpart of the local process pool
of :mod:`rangeseg_cli.batch.runner`: it submits :func:`~rangeseg_cli.batch.jobs.process_image`
once per image and hands each :class:`~rangeseg_cli.batch.jobs.Record` back as its
task completes, so the manifest and the progress bar are fed exactly as in a
local run.

Storage. Workers read the inputs and write the outputs themselves, so they
must see the same paths as the client: a shared folder mounted at the same
place everywhere, or a store named by fsspec URLs (``s3://bucket/frames``)
that every worker reaches with its own settings (its environment, e.g.
``FSSPEC_S3_ENDPOINT_URL``). Local paths are made absolute before they are
sent, and every worker is asked whether it sees the output folder and the
first input before any task is submitted.

Guarantees, as for local runs:

* outputs are written atomically by the worker (temporary file + rename, or
  one put of the whole object on an object store); temporaries left by a
  worker killed mid-write are removed at the end;
* a task's key is a digest of the image, its input, the output folder, the
  stages and the config digest, so submitting it again is idempotent;
* a worker that dies mid-task: the scheduler runs the task on another worker
  (up to ``distributed.scheduler.allowed-failures`` times, then the image is
  recorded as failed); each image gets one record, and its files, rewritten
  whole by deterministic code, have the same bytes;
* a task that raises (not a bad image: those are records) is retried
  :data:`RETRIES` times;
* at most ``limit`` images are in flight at once when a limit is given;
* Ctrl-C cancels the tasks that have not finished and records those that have;
* a scheduler lost mid-batch ends the batch with :class:`~.errors.ClusterLost`
  after recording what finished.

``dask[distributed]`` is an optional dependency (``pip install rangeseg[dask]``),
imported only when a Dask batch starts.
"""

from __future__ import annotations

import hashlib
import itertools
import json
from asyncio import CancelledError
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from types import ModuleType
from typing import TYPE_CHECKING, Any

from .. import __version__
from ..cell.frames import SharedFrames
from ..config import Config
from ..errors import ClusterError, ClusterLost, RangesegError
from . import io
from .io import Location
from .jobs import (
    Job,
    Record,
    StopFlag,
    job_stages,
    process_image,
    remove_failed_outputs,
    remove_stale_temporaries,
)

if TYPE_CHECKING:  # pragma: no cover
    from distributed import Client, Future

#: Seconds to wait for the scheduler to answer.
CONNECT_TIMEOUT_S = 10.0
#: Seconds to wait for a first worker to join a scheduler that has none.
WORKER_WAIT_S = 10.0
#: Retries of a task that raises (worker deaths are handled by the scheduler).
RETRIES = 2


def _distributed() -> ModuleType:
    try:
        import distributed
    except ImportError:
        raise ClusterError("executor 'dask' needs dask.distributed, which is not installed: "
                           "pip install 'rangeseg[dask]'") from None
    return distributed


@contextmanager
def connect(scheduler: str, *, timeout: float | None = None) -> Iterator[Client]:
    """A client of the Dask scheduler at ``scheduler``, closed on exit.

    Parameters
    ----------
    scheduler
        Address of a running scheduler, e.g. ``tcp://10.0.0.5:8786``.
    timeout
        Seconds to wait for it; default :data:`CONNECT_TIMEOUT_S`.

    Raises
    ------
    ClusterError
        When dask.distributed is missing, the address is malformed or nothing
        answers there in time.
    """
    distributed = _distributed()
    seconds = CONNECT_TIMEOUT_S if timeout is None else timeout
    try:  # checked first: a Client that fails on a malformed address hangs on exit
        distributed.comm.get_address_host_port(scheduler)
    except ValueError as exc:
        raise ClusterError(f"{scheduler!r} is not the address of a Dask scheduler "
                           f"({exc}); expected tcp://HOST:PORT") from None
    try:
        client = distributed.Client(scheduler, timeout=seconds, set_as_default=False)
    except OSError:
        raise ClusterError(f"no Dask scheduler answers at {scheduler} within {seconds:g} s: "
                           "is it running, and is the address right?") from None
    try:
        yield client
    finally:
        client.close()


def task_key(job: Job, out: Location, config: Config, stages: tuple[str, ...],
             frames: SharedFrames | None = None) -> str:
    """Dask key of one image's task: the same work always gets the same key."""
    shared = "" if frames is None else f"{frames.digest}:{frames.size}"
    what = json.dumps([job.rel, job.source, str(out), list(job_stages(job, stages)),
                       config.digest(), shared])
    return "rangeseg-" + hashlib.sha256(what.encode()).hexdigest()[:32]


def worker_report(paths: list[str]) -> tuple[str, list[bool | str]]:
    """On a worker: its rangeseg version and, for each of ``paths``, whether it sees it.

    A path the worker cannot even ask about (a URL whose filesystem package is
    missing there, a store it cannot reach) gets the one-line reason instead.
    """
    return __version__, [_sees(p) for p in paths]


def _sees(name: str) -> bool | str:
    try:
        return io.location(name).exists()
    except RangesegError as exc:
        return str(exc)


def execute_on_dask(todo: list[Job], out: Location, config: Config, stages: tuple[str, ...],
                    scheduler: str | Client, finish: Callable[[Record], None], *,
                    limit: int | None = None, frames: SharedFrames | None = None) -> None:
    """Process ``todo`` on a Dask cluster, calling ``finish(record)`` as images complete.

    Parameters
    ----------
    todo
        Images to process (planned by :func:`~rangeseg_cli.batch.runner.plan_jobs`).
    out
        Output folder; it must exist and be visible to every worker (a shared
        folder, or a URL every worker reaches).
    config
        The configuration, sent with every task.
    stages
        Consecutive stages to run.
    scheduler
        Address of the scheduler (``tcp://HOST:PORT``), or a connected
        ``distributed.Client`` (kept open).
    finish
        Called in this process with each image's record, in completion order.
    limit
        At most this many images in flight at once; ``None``: submit them all.
    frames
        The batch's workspace arrays and intrinsics size
        (:func:`~rangeseg_cli.batch.runner.shared_frames`), sent to the workers once.

    Raises
    ------
    ClusterError
        Before any task is submitted, when the scheduler cannot be reached or
        a worker cannot import rangeseg, runs another version of it, or does
        not see ``out`` or the first input.
    ClusterLost
        When the scheduler goes away mid-batch, after ``finish`` was called for
        every image that completed before.
    KeyboardInterrupt
        After cancelling the tasks that have not finished (those that have are
        passed to ``finish``).
    """
    frames = frames or SharedFrames()
    if isinstance(scheduler, str):
        with connect(scheduler) as client:
            _run_tasks(client, todo, out, config, stages, frames, finish, limit)
    else:
        _run_tasks(scheduler, todo, out, config, stages, frames, finish, limit)


@dataclass
class _Batch:
    """What every task of a batch shares, and the tasks in flight."""

    client: Client
    distributed: ModuleType
    address: str  # of the scheduler, for messages once it is gone
    out: Location
    config: Config
    stages: tuple[str, ...]
    frames: SharedFrames = field(default_factory=SharedFrames)
    shared: Any = None  # ``frames`` on the cluster (scattered once), or ``frames``
    pending: dict[Future, tuple[Job, Job]] = field(default_factory=dict)

    def submit(self, job: Job, sent: Job) -> Future:
        """Submit one image (``sent``: with absolute paths); remember the user's job."""
        key = task_key(sent, self.out, self.config, self.stages, self.frames)
        future = self.client.submit(process_image, sent, self.out, self.config, self.stages,
                                    self.shared, retries=RETRIES, key=key)
        self.pending[future] = (job, sent)
        return future

    def record(self, future: Future) -> Record:
        """The finished image's record, as a local run would give it (the user's paths)."""
        job, sent = self.pending.pop(future)
        name = job.source or job.rel
        try:
            record: Record = future.result()
        except self.distributed.KilledWorker:
            return self.failed(job, f"{name}: every Dask worker that ran it died "
                                    "(out of memory?)")
        except (Exception, CancelledError) as exc:  # noqa: BLE001 - fails its image only
            if self.lost(exc):
                raise ClusterLost(self.lost_message()) from None
            return self.failed(job, f"{name}: Dask task failed ({type(exc).__name__}: {exc})")
        if sent.source and job.source and record.error:
            record.error = record.error.replace(sent.source, job.source)
        record.source = job.source
        return record

    def failed(self, job: Job, error: str) -> Record:
        """A failed record for an image whose task gave none; its stale outputs are removed."""
        first = job_stages(job, self.stages)[0]
        record = Record(rel=job.rel, status="failed", source=job.source, error=error,
                        first_stage=first)
        remove_failed_outputs(self.out, record, first)
        return record

    def lost(self, exc: BaseException) -> bool:
        """Whether a task's result is out of reach because the scheduler went away.

        Tasks never raise ``OSError`` (:func:`process_image` makes errors records),
        so one here is the connection (e.g. ``CommClosedError`` while fetching).
        """
        return (isinstance(exc, OSError) or self.client.status != "running"
                or getattr(exc, "reason", None) == "scheduler-connection-lost")

    def lost_message(self) -> str:
        """One line naming the scheduler."""
        return (f"lost the Dask scheduler at {self.address} mid-batch; what finished is "
                "kept: rerun with --resume once it is back")

    def stop(self, finish: Callable[[Record], None]) -> None:
        """Cancel what has not finished; record what has (Ctrl-C, or ``finish`` failed)."""
        if self.client.status == "running":
            self.client.cancel([f for f in self.pending if f.status != "finished"])
        for future in [f for f in self.pending if f.status == "finished"]:
            try:
                finish(self.record(future))
            except ClusterLost:
                return


def _run_tasks(client: Client, todo: list[Job], out: Location, config: Config,
               stages: tuple[str, ...], frames: SharedFrames,
               finish: Callable[[Record], None], limit: int | None) -> None:
    out = io.absolute(out)
    sent = [Job(rel=j.rel, source=None if j.source is None else io.absolute_name(j.source),
                start=j.start, noise=j.noise) for j in todo]
    _check_workers(client, [str(out)] + [j.source for j in sent[:1] if j.source])
    # the workspace arrays go to the workers once, not with every task
    shared = client.scatter(frames, broadcast=True) if frames.digest and todo else frames
    batch = _Batch(client, _distributed(), client.scheduler.address, out, config, stages,
                   frames, shared)
    with StopFlag() as stop:
        _drive(batch, iter(zip(todo, sent, strict=True)), limit or max(1, len(todo)),
               finish, stop)
    remove_stale_temporaries(out)


def _drive(batch: _Batch, jobs: Iterator[tuple[Job, Job]], limit: int,
           finish: Callable[[Record], None], stop: StopFlag) -> None:
    """Keep up to ``limit`` tasks in flight; hand each record to ``finish`` as it completes."""
    done = batch.distributed.as_completed([], loop=batch.client.loop)

    def top_up() -> None:
        for job, sent in itertools.islice(jobs, limit - len(batch.pending)):
            done.add(batch.submit(job, sent))

    try:
        top_up()
        while batch.pending:
            with stop.interruptible():  # waiting for the cluster: Ctrl-C stops at once
                finished = done.next_batch()
            for future in finished:
                finish(batch.record(future))
            stop.check()
            top_up()
    except BaseException:  # Ctrl-C, the scheduler lost, or ``finish`` failed
        batch.stop(finish)
        raise


def _check_workers(client: Client, paths: list[str]) -> None:
    """Fail before any work when a worker cannot run rangeseg or see the shared paths."""
    address = client.scheduler.address
    try:
        client.wait_for_workers(1, timeout=WORKER_WAIT_S)
    except TimeoutError:
        raise ClusterError(f"the Dask scheduler at {address} has no workers (none joined "
                           f"within {WORKER_WAIT_S:g} s): start workers with "
                           f"`dask worker {address}`") from None
    try:
        answers: dict[str, Any] = client.run(worker_report, paths)
    except Exception as exc:  # noqa: BLE001 - e.g. rangeseg not installed on a worker
        raise ClusterError(f"the workers of {address} cannot run rangeseg "
                           f"({type(exc).__name__}: {exc}); install rangeseg {__version__} "
                           "on every worker") from None
    for worker, (version, seen) in sorted(answers.items()):
        if version != __version__:
            raise ClusterError(f"worker {worker} runs rangeseg {version}, this client "
                               f"{__version__}: install the same version on every worker")
        _check_seen(worker, paths, seen)


def _check_seen(worker: str, paths: list[str], seen: list[bool | str]) -> None:
    for path, answer in zip(paths, seen, strict=True):
        if isinstance(answer, str):
            raise ClusterError(f"worker {worker}: {answer}")
        if not answer:
            raise ClusterError(f"worker {worker} does not see {path}: workers must read and "
                               "write the same paths as the client (shared storage)")
