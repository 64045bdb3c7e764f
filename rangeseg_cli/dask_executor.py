"""Run a batch on an existing Dask distributed cluster: one task per image (issue 10).

:func:`execute_on_dask` is the cluster counterpart of the local process pool
of :mod:`rangeseg_cli.batch`: it submits :func:`~rangeseg_cli.batch.process_image`
once per image and hands each :class:`~rangeseg_cli.batch.Record` back as its
task completes, so the manifest and the progress bar are fed exactly as in a
local run.

Storage. Workers read the inputs and write the outputs themselves, so they
must see the same paths as the client: a shared folder mounted at the same
place everywhere. Paths are made absolute before they are sent, and every
worker is asked whether it sees the output folder before any task is
submitted. fsspec URLs (``s3://...``) are not supported.

Guarantees, as for local runs:

* outputs are written atomically by the worker (temporary file + rename);
  temporaries left by a worker killed mid-write are removed at the end;
* a task's key is a digest of the image, its input, the output folder, the
  stages and the config digest, so submitting it again is idempotent;
* a worker that dies mid-task: the scheduler runs the task on another worker
  (up to ``distributed.scheduler.allowed-failures`` times, then the image is
  recorded as failed); each image gets one record, and its files, rewritten
  whole by deterministic code, have the same bytes;
* a task that raises (not a bad image: those are records) is retried
  :data:`RETRIES` times;
* Ctrl-C cancels the tasks that have not run.

``dask[distributed]`` is an optional dependency (``pip install rangeseg[dask]``),
imported only when a Dask batch starts.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING, Any

from . import __version__
from .batch import Job, Record, process_image, remove_stale_temporaries
from .config import Config
from .errors import ClusterError

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


def task_key(job: Job, out: Path, config: Config, stages: tuple[str, ...]) -> str:
    """Dask key of one image's task: the same work always gets the same key."""
    what = json.dumps([job.rel, job.source, str(out), list(stages), config.digest()])
    return "rangeseg-" + hashlib.sha256(what.encode()).hexdigest()[:32]


def worker_report(paths: list[str]) -> tuple[str, list[bool]]:
    """On a worker: its rangeseg version and whether it sees each of ``paths``."""
    return __version__, [os.path.exists(p) for p in paths]


def execute_on_dask(todo: list[Job], out: Path, config: Config, stages: tuple[str, ...],
                    scheduler: str | Client, finish: Callable[[Record], None]) -> None:
    """Process ``todo`` on a Dask cluster, calling ``finish(record)`` as images complete.

    Parameters
    ----------
    todo
        Images to process (planned by :func:`~rangeseg_cli.batch.plan_jobs`).
    out
        Output folder; it must exist and be visible to every worker.
    config
        The configuration, sent with every task.
    stages
        Consecutive stages to run.
    scheduler
        Address of the scheduler (``tcp://HOST:PORT``), or a connected
        ``distributed.Client`` (kept open).
    finish
        Called in this process with each image's record, in completion order.

    Raises
    ------
    ClusterError
        Before any task is submitted, when the scheduler cannot be reached or
        a worker cannot import rangeseg, runs another version of it, or does
        not see ``out`` or the first input.
    KeyboardInterrupt
        After cancelling the tasks that have not finished.
    """
    if isinstance(scheduler, str):
        with connect(scheduler) as client:
            _run_tasks(client, todo, out, config, stages, finish)
    else:
        _run_tasks(scheduler, todo, out, config, stages, finish)


def _run_tasks(client: Client, todo: list[Job], out: Path, config: Config,
               stages: tuple[str, ...], finish: Callable[[Record], None]) -> None:
    distributed = _distributed()
    out = Path(os.path.abspath(out))
    sent = [Job(rel=j.rel, source=None if j.source is None else os.path.abspath(j.source))
            for j in todo]
    _check_workers(client, [str(out)] + [j.source for j in sent[:1] if j.source])
    futures: dict[Future, tuple[Job, Job]] = {
        client.submit(process_image, s, out, config, stages, retries=RETRIES,
                      key=task_key(s, out, config, stages)): (job, s)
        for job, s in zip(todo, sent, strict=True)}
    try:
        for future in distributed.as_completed(list(futures), loop=client.loop):
            job, s = futures.pop(future)
            finish(_record(future, job, s, distributed))
    except BaseException:  # Ctrl-C, or ``finish`` failed: stop what has not run
        client.cancel(list(futures))
        raise
    remove_stale_temporaries(out)


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
        missing = [p for p, ok in zip(paths, seen, strict=True) if not ok]
        if missing:
            raise ClusterError(f"worker {worker} does not see {missing[0]}: workers must "
                               "read and write the same paths as the client (shared storage)")


def _record(future: Future, job: Job, sent: Job, distributed: ModuleType) -> Record:
    """The image's record as a local run would give it (the user's paths in messages)."""
    name = job.source or job.rel
    try:
        record: Record = future.result()
    except distributed.KilledWorker:
        return Record(rel=job.rel, status="failed", source=job.source,
                      error=f"{name}: every Dask worker that ran it died (out of memory?)")
    except Exception as exc:  # noqa: BLE001 - a lost task fails its image, not the batch
        return Record(rel=job.rel, status="failed", source=job.source,
                      error=f"{name}: Dask task failed ({type(exc).__name__}: {exc})")
    if sent.source and job.source and record.error:
        record.error = record.error.replace(sent.source, job.source)
    record.source = job.source
    return record
