"""The ``rangeseg`` command line: a thin click layer over :mod:`rangeseg_cli.batch.runner`.

Exit codes: 0 all images done; 1 at least one image failed (the others are
still done); 2 usage or configuration error, nothing done; 130 interrupted.
Logs, progress and the summary go to stderr; ``--json`` data to stdout.
"""

from __future__ import annotations

import json
import logging
import os
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import click

from .. import __version__

log = logging.getLogger("rangeseg")
PRESET_NAMES = ("paper", "mm-depth", "tenth-mm-depth", "metre-depth")
#: rangeseg_cli.batch.runner.EXECUTORS (not imported: a fast --help).
EXECUTOR_NAMES = ("local", "dask")
MAX_JOBS = 1024  # rangeseg_cli.batch.runner.MAX_JOBS

# --------------------------------------------------------------------------- shared options

config_opt = click.option("--config", "config_path", type=click.Path(dir_okay=False),
                          help="TOML configuration file (see `rangeseg config`).")
preset_opt = click.option("--preset", type=click.Choice(PRESET_NAMES),
                          help="Named settings for a kind of sensor, applied before "
                               "--config (e.g. tenth-mm-depth for depth PNGs in 0.1 mm).")
set_opt = click.option("--set", "settings", multiple=True, metavar="TABLE.KEY=VALUE",
                       help="Override one config value (TOML syntax), e.g. "
                            "--set step.threshold=8. Repeatable; applied last.")
intrinsics_opt = click.option(
    "--intrinsics", "intrinsics_path", metavar="FILE",
    help="Camera intrinsics: a 3x3 matrix as text, a ROS CameraInfo YAML or an Open3D "
         "PinholeCameraIntrinsic JSON. Sets [input] intrinsics after --preset/--config, "
         "before --set (which wins); an image of another size than the file gives fails.")
background_opt = click.option(
    "--background", "background_path", metavar="FILE",
    help="Frame of the empty tote or table, read as the images are: sets [workspace] "
         "background (after --preset/--config, before --set).")
roi_opt = click.option(
    "--roi", "roi_path", metavar="FILE",
    help="Mask image of where a site may be (non-zero = yes): sets [workspace] roi "
         "(after --preset/--config, before --set).")
jobs_opt = click.option("--jobs", "-j", type=click.IntRange(min=1, max=MAX_JOBS), default=None,
                        help="Worker processes (default: all cores; at most one per image); "
                             "with --executor dask, at most N images on the cluster at once "
                             f"(default: no limit). 1 to {MAX_JOBS}.")
threads_opt = click.option("--threads", type=click.IntRange(min=1), default=None,
                           help="Threads for one image (default: the cores shared out among "
                                "--jobs, or RANGESEG_THREADS); the results are the same for "
                                "any number.")
resume_opt = click.option("--resume", is_flag=True,
                          help="Complete only what is missing in OUT (same config).")
overwrite_opt = click.option("--overwrite", is_flag=True,
                             help="Redo every image even if OUT holds results.")
executor_opt = click.option("--executor", type=click.Choice(EXECUTOR_NAMES), default="local",
                            show_default=True,
                            help="Where images are processed: --jobs processes here, or one "
                                 "task per image on a Dask cluster (needs --scheduler and "
                                 "pip install 'rangeseg[dask]').")
scheduler_opt = click.option("--scheduler", metavar="ADDRESS",
                             help="Dask scheduler of --executor dask, e.g. "
                                  "tcp://10.0.0.5:8786; workers must see INPUTS and OUT "
                                  "at the same paths or URLs.")
json_opt = click.option("--json", "as_json", is_flag=True,
                        help="Print the batch summary as JSON on stdout.")
ply_opt = click.option("--ply", is_flag=True,
                       help="Also write labelled point clouds, OUT/<rel>.points.ply and "
                            "holdsite.ply: sets [output] ply = true (before --set).")


def _not_empty(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
    """An empty path is a usage error: the current folder, as an unset ``$OUT`` says it."""
    from ..batch.io import is_empty_path

    for item in value if isinstance(value, tuple) else (value,):
        if isinstance(item, str) and is_empty_path(item):
            raise click.BadParameter("an empty path (an unset shell variable?); for the "
                                     "current folder write .", ctx=ctx, param=param)
    return value


def _name_filter(ctx: click.Context, param: click.Parameter, value: tuple[str, ...]
                 ) -> tuple[str, ...]:
    """--include/--exclude: an empty glob is a usage error."""
    from ..batch.io import NameFilter

    try:
        NameFilter(include=value)
    except ValueError as exc:
        raise click.BadParameter(str(exc), ctx=ctx, param=param) from None
    return value


rerun_opt = click.option(
    "--rerun", metavar="FILE.rrd", type=click.Path(dir_okay=False), callback=_not_empty,
    help="Write a log for the Rerun viewer after the batch: per image its depth, labels, "
         "point cloud coloured by surface and holdsite (pip install 'rangeseg[rerun]').")
include_opt = click.option(
    "--include", "include", multiple=True, metavar="GLOB", callback=_name_filter,
    help="Read only the files of INPUTS folders that GLOB matches (repeatable). A GLOB "
         "without / is matched against the file's name and its folders' names "
         "('*_depth.npy'), one with / against its path below the named folder "
         "('cam1/**/*.png'); * stops at /, ** does not; case-sensitive. --exclude wins "
         "over --include; a file named as an INPUT is always read.")
exclude_opt = click.option(
    "--exclude", "exclude", multiple=True, metavar="GLOB", callback=_name_filter,
    help="Do not read the files of INPUTS folders that GLOB matches (repeatable; globs as "
         "for --include), e.g. --exclude '*_mask.png'; wins over --include.")
output_opt = click.option("--output", "-o", "out", required=True,
                          type=click.Path(file_okay=False), callback=_not_empty,
                          help="Output folder: a path or a URL such as s3://bucket/out.")
inputs_arg = click.argument("inputs", nargs=-1, required=True, type=click.Path(),
                            callback=_not_empty)
outdir_arg = click.argument("out", type=click.Path(file_okay=False), callback=_not_empty)


def verbosity_opts(f: Callable[..., Any]) -> Callable[..., Any]:
    """--version, and -v/-q counted into a log level (rasterio's habit)."""
    f = click.version_option(__version__, prog_name="rangeseg")(f)
    f = click.option("--verbose", "-v", count=True, help="More detail on stderr "
                     "(-vv: tracebacks of internal errors).")(f)
    return click.option("--quiet", "-q", count=True,
                        help="No progress bar or summary table.")(f)


def _config_options(f: Callable[..., Any]) -> Callable[..., Any]:
    """--config, --preset, the shorthands --intrinsics, --background, --roi, and --set."""
    for opt in (set_opt, roi_opt, background_opt, intrinsics_opt, preset_opt, config_opt):
        f = opt(f)
    return f


def _batch_options(f: Callable[..., Any]) -> Callable[..., Any]:
    for opt in (json_opt, rerun_opt, ply_opt, overwrite_opt, resume_opt, scheduler_opt,
                executor_opt, threads_opt, jobs_opt):
        f = opt(f)
    return verbosity_opts(_config_options(f))


# --------------------------------------------------------------------------- helpers


class UsageProblem(click.ClickException):
    """A usage or configuration error: one line on stderr, exit code 2, nothing done."""

    exit_code = 2


def _parse_settings(settings: tuple[str, ...]) -> dict[str, dict[str, Any]]:
    from ..config import parse_settings
    from ..errors import ConfigError

    try:
        return parse_settings(settings)
    except ConfigError as exc:
        raise click.BadParameter(str(exc), param_hint="--set") from None


def _shorthands(opts: dict[str, Any]) -> tuple[dict[str, dict[str, Any]], Any]:
    """The tables --intrinsics, --background, --roi and --ply set, and the intrinsics read.

    The workspace files are recorded as absolute paths (URLs as given), so the
    stage commands, which read the configuration from OUT's manifest, find
    them from any folder; "" (``--background ""``) sets none.
    """
    from ..batch.io import absolute_name, is_empty_path
    from ..cell.intrinsics import read_intrinsics
    from ..errors import ConfigError

    tables: dict[str, dict[str, Any]] = {}
    intrinsics = None
    if opts.get("intrinsics_path") is not None:
        if is_empty_path(opts["intrinsics_path"]):
            raise click.BadParameter("an empty path (an unset shell variable?)",
                                     param_hint="--intrinsics")
        try:
            intrinsics = read_intrinsics(opts["intrinsics_path"])
        except ConfigError as exc:
            raise UsageProblem(str(exc)) from None
        tables.update(intrinsics.settings())
    for key in ("background", "roi"):
        name = opts.get(f"{key}_path")
        if name is not None:
            tables.setdefault("workspace", {})[key] = absolute_name(name) if name else ""
    if opts.get("ply"):
        tables.setdefault("output", {})["ply"] = True
    return tables, intrinsics


def _load_config(config_path: str | None, preset: str | None, settings: tuple[str, ...],
                 fallback_out: Any = None, shorthands: dict[str, Any] | None = None) -> Any:
    """Config from --preset/--config/--set; for stage commands OUT's manifest, --set on top.

    A stage command without --config or --preset goes on with the configuration
    recorded in OUT, its --set changing values of it (``holdsite --set
    holdsite.size=[9,9]`` keeps the rest as the run had it). ``shorthands``
    (:func:`_shorthands`) come after the file and before ``--set``.
    """
    from ..config import build_config, load_config, merge
    from ..errors import ConfigError, OutputError, StorageError

    try:
        overrides = merge(shorthands or {}, _parse_settings(settings))
        if fallback_out is not None and not (config_path or preset):
            from ..batch.runner import manifest_config

            recorded = manifest_config(fallback_out)
            if recorded is not None:
                return build_config(merge(recorded.to_dict(), overrides))
        return load_config(config_path, preset=preset, overrides=overrides)
    except (ConfigError, OutputError, StorageError) as exc:
        raise UsageProblem(str(exc)) from None


def _setup_logging(verbose: int, quiet: int) -> None:
    level = logging.WARNING - 10 * verbose + 10 * quiet
    logging.basicConfig(level=max(level, logging.DEBUG), format="%(message)s",
                        stream=sys.stderr)


def _run(ctx: click.Context, jobs: Any, out: Any, config: Any, stages: tuple[str, ...],
         opts: dict[str, Any], skipped_files: list[str] | None = None) -> None:
    """Run a batch with progress and summary, then exit with the batch's code."""
    from ..batch.runner import default_jobs, run_batch
    from ..errors import ClusterError, ConfigError, OutputError, StorageError
    from .progress import BatchReporter

    _check_executor(opts["executor"], opts["scheduler"])
    if opts["resume"] and opts["overwrite"]:
        raise click.UsageError("--resume and --overwrite exclude each other: --resume "
                               "completes what is missing, --overwrite redoes every image")
    _set_threads(opts["threads"])
    if opts.get("rerun"):
        _check_rerun(opts["rerun"])
    _say_if_compiling(opts)
    _warn_footprint(config, stages, opts)
    _warn_units(jobs, config, stages, opts)
    reporter = BatchReporter(quiet=opts["quiet"] > 0, verbose=opts["verbose"])
    # Dask: --jobs caps the images in flight; without it the cluster sets the parallelism.
    n_jobs = opts["jobs"] if opts["executor"] == "dask" else opts["jobs"] or default_jobs()
    try:
        with _quiet_dask(opts["verbose"]):
            summary = run_batch(
                jobs, out, config, stages, n_jobs=n_jobs,
                resume=opts.get("resume", False), overwrite=opts.get("overwrite", False),
                skipped_files=skipped_files, command=ctx.info_name or "run",
                on_result=reporter.result, on_start=reporter.start,
                executor=opts["executor"], scheduler=opts["scheduler"],
                intrinsics=opts.get("intrinsics"))
    except (ConfigError, OutputError, ClusterError, StorageError) as exc:
        raise UsageProblem(str(exc)) from None
    finally:
        reporter.stop()
    reporter.summary(summary)
    if opts.get("rerun"):
        _write_rerun(opts["rerun"], jobs, out, config, summary)
    if opts["as_json"]:
        _echo_json(ctx, summary.to_dict())
    _exit(ctx, summary)


def _check_rerun(path: str) -> None:
    """``--rerun``: the SDK installed and FILE writable, before any work (exit code 2)."""
    from ..batch.io import check_writable
    from ..batch.rerun_log import require_rerun
    from ..errors import ConfigError, OutputError

    if "://" in path:
        raise UsageProblem(f"--rerun {path}: a local file is needed (the Rerun SDK writes "
                           "files, not objects of a store)")
    if not path.lower().endswith(".rrd"):  # an input or an output's name: it was replaced
        raise UsageProblem(f"--rerun {path}: name the log FILE.rrd, as the Rerun viewer "
                           "opens it (another name could be an input or output)")
    if os.path.lexists(path) and not _is_recording(Path(path)):
        raise UsageProblem(f"--rerun {path}: exists and is no Rerun recording; name a new "
                           "file or remove it")
    try:
        require_rerun()
        check_writable(Path(path))
    except (ConfigError, OutputError) as exc:
        raise UsageProblem(str(exc)) from None


def _is_recording(path: Path) -> bool:
    """Whether ``path`` is a file that starts as a Rerun recording (``RRF``)."""
    try:
        with open(path, "rb") as handle:
            return path.is_file() and handle.read(3) == b"RRF"
    except OSError:
        return False


def _write_rerun(path: str, jobs: list[Any], out: Any, config: Any, summary: Any) -> None:
    """``--rerun``: the log of the images done (or resumed), in input order (exit 1 if not)."""
    from ..batch.rerun_log import write_log
    from ..errors import OutputError

    status = {r.rel: r.status for r in summary.records}
    images = [(k, job.rel) for k, job in enumerate(jobs)
              if status.get(job.rel) in ("done", "skipped")]
    try:
        write_log(Path(path), out, images, config.input)
    except OutputError as exc:
        raise click.ClickException(str(exc)) from None


def _say_if_compiling(opts: dict[str, Any]) -> None:
    """On stderr, unless -q: the first run compiles the numba kernels (the workers' on Dask)."""
    from ..kernels.cache import MESSAGE, cold_kernel_cache

    if not opts["quiet"] and opts["executor"] == "local" and cold_kernel_cache():
        click.echo(MESSAGE, err=True)


def _warn_footprint(config: Any, stages: tuple[str, ...], opts: dict[str, Any]) -> None:
    """On stderr, unless -q: the cup's footprint_mm cannot apply (e.g. no intrinsics)."""
    from ..stages.holdsite import footprint_fallback

    why = footprint_fallback(config) if "holdsite" in stages else ""
    if why and not opts["quiet"]:
        click.echo(f"warning: {why}", err=True)


#: Local inputs :func:`_warn_units` tries until one reads.
HINT_TRIES = 3


def _warn_units(jobs: Any, config: Any, stages: tuple[str, ...], opts: dict[str, Any]
                    ) -> None:
    """On stderr, unless -q: the first readable local input's units may be misread.

    A depth map read as heights, or heights in units too fine for the
    thresholds (:func:`~rangeseg_cli.stages.rangeimage.fine_units_hint`) or
    too coarse for the settings in depth units (metres:
    :func:`~rangeseg_cli.stages.rangeimage.coarse_units_hint`).
    Only when the batch reads inputs and picks holdsites (``run``); the
    first of :data:`HINT_TRIES` local inputs that reads is looked at.
    """
    from ..batch.io import read_image
    from ..errors import RangesegError
    from ..stages.rangeimage import coarse_units_hint, depth_map_hint, fine_units_hint

    if opts["quiet"] or "edges" not in stages or "holdsite" not in stages:
        return
    local = [j.source for j in jobs if j.source and "://" not in str(j.source)]
    for source in local[:HINT_TRIES]:
        try:
            raw = read_image(source)
            why = (depth_map_hint(raw, config.input) or fine_units_hint(raw, config.input)
                   or coarse_units_hint(raw, config.input))
        except (RangesegError, MemoryError, OSError):  # the batch reports the image itself
            continue
        if why:
            click.echo(f"warning: {source} {why}", err=True)
        return


def _set_threads(threads: int | None) -> None:
    """--threads, or a RANGESEG_THREADS that is not a whole number >= 1 as a usage error."""
    from ..kernels import parallel

    try:
        parallel.set_threads(threads)
        parallel.thread_count()
    except ValueError as exc:
        raise UsageProblem(str(exc)) from None


def _exit(ctx: click.Context, summary: Any) -> None:
    """Exit code of a finished batch: 0 done, 1 failed or cluster lost, 130 Ctrl-C, 143 SIGTERM."""
    if summary.error:  # the Dask scheduler was lost: what finished is kept
        click.echo(f"Error: {summary.error}", err=True)
        ctx.exit(1)
    if summary.interrupted:
        how = "terminated (SIGTERM)" if summary.terminated else "interrupted"
        click.echo(f"{how}: {summary.count('done')} images done and kept; rerun the "
                   "same command with --resume to finish", err=True)
        ctx.exit(143 if summary.terminated else 130)
    ctx.exit(1 if summary.count("failed") else 0)


@contextmanager
def _quiet_dask(verbose: int) -> Iterator[None]:
    """Without -v, keep Dask's own log off stderr; our one-line messages say what happened.

    Its client logs a traceback, for one, when it closes after losing the scheduler.
    """
    logger, null = logging.getLogger("distributed"), logging.NullHandler()
    propagate = logger.propagate
    if not verbose:
        logger.addHandler(null)
        logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(null)
        logger.propagate = propagate


def _check_executor(executor: str, scheduler: str | None) -> None:
    if executor == "dask" and not scheduler:
        raise click.BadParameter("--executor dask needs the address of a running Dask "
                                 "scheduler, e.g. --scheduler tcp://10.0.0.5:8786",
                                 param_hint="--scheduler")
    if executor != "dask" and scheduler:
        raise click.BadParameter("--scheduler is used only with --executor dask",
                                 param_hint="--scheduler")


def _location(name: str) -> Any:
    """OUT as a local path or a URL; an unusable URL is a usage error (exit 2)."""
    from ..batch.io import check_output_protocol, location
    from ..errors import StorageError

    try:
        check_output_protocol(name)
        return location(name)
    except StorageError as exc:
        raise UsageProblem(str(exc)) from None


def _input_jobs(inputs: tuple[str, ...], out: Any, opts: dict[str, Any], config: Any
                ) -> tuple[list[Any], list[str]]:
    from ..batch.io import NameFilter
    from ..batch.runner import jobs_from_inputs, workspace_files
    from ..errors import InputError, StorageError

    names = NameFilter(include=opts["include"], exclude=opts["exclude"])
    try:
        jobs, skipped = jobs_from_inputs(
            inputs, out, names, not_frames=[path for _, path in workspace_files(config)])
    except (InputError, StorageError) as exc:
        raise UsageProblem(str(exc)) from None
    if not jobs:
        filters = " and --include/--exclude" if names.include or names.exclude else ""
        raise UsageProblem("no range images found in " + ", ".join(inputs)
                           + f" (extensions: .png .pgm .pnm .tif .tiff .npy{filters})")
    return jobs, skipped


def _output_jobs(out: Any) -> list[Any]:
    from ..batch.runner import jobs_from_output
    from ..errors import OutputError, StorageError

    try:
        return jobs_from_output(out)
    except (OutputError, StorageError) as exc:
        raise UsageProblem(str(exc)) from None


# --------------------------------------------------------------------------- commands


#: ``ctx.meta`` keys: whether ``--json`` was given, and whether its object was printed.
_JSON_WANTED, _JSON_PRINTED = "rangeseg.json", "rangeseg.json_printed"


def _echo_json(ctx: click.Context, data: dict[str, Any]) -> None:
    """Print the one JSON object of ``--json`` on stdout."""
    click.echo(json.dumps(data, sort_keys=True, indent=2))
    ctx.meta[_JSON_PRINTED] = True


def _json_error(ctx: click.Context, message: str, code: int, **more: Any) -> None:
    """With ``--json``, the object of a command that stopped before its own was printed."""
    if ctx.meta.get(_JSON_WANTED) and not ctx.meta.get(_JSON_PRINTED):
        _echo_json(ctx, {"error": message, "exit_code": code, **more})


def _json_requested(args: list[str]) -> bool:
    """Whether ``--json`` is among the options (before a ``--``)."""
    return "--json" in (args[: args.index("--")] if "--" in args else args)


class _Group(click.Group):
    """The command group, with Ctrl-C handled before the batch as during it.

    Ctrl-C while the config is read, IMAGES are listed or the batch is planned
    exits 130 as one during the batch does, not with click's ``Aborted!`` and
    1 (the code of a failed image). With ``--json``, a usage error or such a
    Ctrl-C prints ``{"error": ..., "exit_code": ...}`` on stdout: a parser
    always gets one object.
    """

    def make_context(self, info_name: str | None, args: list[str],
                     parent: click.Context | None = None, **extra: Any) -> click.Context:
        wanted = _json_requested(args)
        try:
            ctx = super().make_context(info_name, args, parent=parent, **extra)
        except click.ClickException as exc:
            if wanted:
                click.echo(json.dumps({"error": exc.format_message(),
                                       "exit_code": exc.exit_code}, sort_keys=True, indent=2))
            raise
        ctx.meta[_JSON_WANTED] = wanted
        return ctx

    def invoke(self, ctx: click.Context) -> Any:
        try:
            return super().invoke(ctx)
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            _json_error(ctx, "interrupted", 130, interrupted=True)
            ctx.exit(130)
        except click.ClickException as exc:
            _json_error(ctx, exc.format_message(), exc.exit_code)
            raise


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="rangeseg")
def main() -> None:
    """Segment range images into surfaces and pick vacuum-gripper holdsites.

    After Al-Hujazi & Sood (1990). `rangeseg run IMAGES -o OUT` does every
    stage; `edges`, `link`, `grow`, `holdsite` run one stage each on OUT.
    """


def _input_command(name: str, last: str, help_text: str) -> None:
    @main.command(name=name, help=help_text)
    @inputs_arg
    @output_opt
    @include_opt
    @exclude_opt
    @_batch_options
    @click.pass_context
    def command(ctx: click.Context, inputs: tuple[str, ...], out: str, **opts: Any) -> None:
        _setup_logging(opts["verbose"], opts["quiet"])
        shorthands, opts["intrinsics"] = _shorthands(opts)
        config = _load_config(opts["config_path"], opts["preset"], opts["settings"],
                              shorthands=shorthands)
        out_path = _location(out)
        jobs, skipped = _input_jobs(inputs, out_path, opts, config)
        from ..batch.runner import stage_range

        _run(ctx, jobs, out_path, config, stage_range("edges", last), opts, skipped)


def _stage_command(name: str, help_text: str) -> None:
    @main.command(name=name, help=help_text)
    @outdir_arg
    @_batch_options
    @click.pass_context
    def command(ctx: click.Context, out: str, **opts: Any) -> None:
        _setup_logging(opts["verbose"], opts["quiet"])
        out_path = _location(out)
        shorthands, _ = _shorthands(opts)  # no image read: the intrinsics' size is not checked
        config = _load_config(opts["config_path"], opts["preset"], opts["settings"],
                              fallback_out=out_path, shorthands=shorthands)
        if not (opts["resume"] or opts["overwrite"]):
            opts["overwrite"] = True  # a stage command redoes its stage unless --resume
        _run(ctx, _output_jobs(out_path), out_path, config, (name,), opts)


_input_command("run", "holdsite", """Run every stage on INPUTS (files or folders, recursive).

    INPUTS and OUT may be URLs such as s3://bucket/frames (pip install
    'rangeseg[s3]'; endpoint and credentials from FSSPEC_S3_* or AWS_*).

    Writes OUT/<rel>.{edges,components,labels}.npy, surfaces.json,
    holdsite.json, PNG pictures and the manifest OUT/rangeseg-run.json.
    """)
_input_command("edges", "edges", """Step 1 and 2: step and roof edges of INPUTS (Sec. V-1, V-2).

    Writes OUT/<rel>.range.npy (heights), OUT/<rel>.edges.npy (uint8: 0 none,
    1 step, 2 roof) and step/roof/edges PNG pictures.
    """)
_stage_command("link", """Step 3: link edges and label components of the images in OUT (Sec. V-3).

    Reads what `rangeseg edges` wrote; writes components.npy/png and adds
    code 3 (linked) to edges.npy.
    """)
_stage_command("grow", """Step 4: quadratic region growing on the images in OUT (Sec. V-4).

    Reads what `rangeseg link` wrote; writes labels.npy/png and surfaces.json.
    """)
_stage_command("holdsite", """Holdsites for a vacuum gripper on the images in OUT (Sec. VII).

    Reads what `rangeseg grow` wrote; writes holdsite.json and overlay.png.
    """)


@main.command(name="config")
@_config_options
@verbosity_opts
def config_cmd(config_path: str | None, preset: str | None, settings: tuple[str, ...],
               verbose: int, quiet: int, **paths: str | None) -> None:
    """Print the configuration as commented TOML (the defaults unless options say more)."""
    from ..config import default_toml

    shorthands, _ = _shorthands(paths)
    given = [("--preset", preset), ("--config", config_path),
             *((f"--{k.removesuffix('_path')}", v) for k, v in paths.items())]
    made_by = " ".join([f"{opt} {value}" for opt, value in given if value is not None]
                       + [f"--set {item}" for item in settings])
    click.echo(default_toml(_load_config(config_path, preset, settings, shorthands=shorthands),
                            made_by=made_by), nl=False)


# --------------------------------------------------------------------------- synth and eval


def _split_csv(value: str, param: str) -> list[str]:
    items = [v.strip() for v in value.split(",") if v.strip()]
    if not items:
        raise click.BadParameter(f"{value!r}: expected a comma-separated list", param_hint=param)
    return items


def _parse_scenes(ctx: click.Context, param: click.Parameter, value: str | None
                  ) -> tuple[list[str], list[str]] | None:
    """``--scenes``: the range-image scenes of :mod:`synth` and the camera scenes, apart."""
    from ..synth.camera import split_scene_names
    from ..synth.scenes import SCENES

    if value is None:
        return None
    try:
        return split_scene_names(value, SCENES)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--scenes") from None


def _parse_noise(ctx: click.Context, param: click.Parameter, value: str) -> list[float]:
    from ..synth.scenes import MAX_NOISE

    out = []
    for item in _split_csv(value, "--noise"):
        try:
            noise = float(item) + 0.0  # -0 is 0: one file name, n0
        except ValueError:
            noise = float("nan")
        if not 0 <= noise <= MAX_NOISE:
            raise click.BadParameter(f"{item!r}: expected numbers from 0 to {MAX_NOISE:g} "
                                     "(depth units), e.g. 0,1,2", param_hint="--noise")
        out.append(noise)
    return out


def _parse_size(ctx: click.Context, param: click.Parameter, value: str | None
                ) -> tuple[int, int] | None:
    from ..synth.scenes import parse_size

    if value is None:
        return None
    try:
        return parse_size(value)
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--size") from None


#: Cameras and depth units of ``synth`` (rangeseg_cli.synth.camera.CAMERAS and DEPTH_UNITS,
#: not imported: fast --help).
CAMERA_NAMES = ("sr300", "sr300-smooth", "ideal")
DEPTH_UNIT_NAMES = ("0.1mm", "1mm", "m")


@main.command(name="synth")
@outdir_arg
@click.option("--scenes", callback=_parse_scenes, metavar="A,B",
              help="Scenes to render (default: all range-image scenes; the paper's test "
                   "objects are part1, cup, part2, cube-holes; depth-camera scenes: "
                   "cam-pile, cam-tote, cam-gripper, cam-empty-tote, cam-full-tote).")
@click.option("--noise", default="0,1,2", show_default=True, callback=_parse_noise,
              metavar="S1,S2", help="Gaussian noise levels in depth units; one image each "
                                    "(range-image scenes).")
@click.option("--seed", type=click.IntRange(min=0), default=0, show_default=True,
              help="Seeds the noise and the pile layout; same seed, same bytes.")
@click.option("--size", default=None, callback=_parse_size, metavar="ROWSxCOLS",
              help="Image size [default: 128x128; 480x640 for the cam-* scenes].")
@click.option("--bits", type=click.Choice(["8", "16"]), default="8", show_default=True,
              help="8-bit (depth units) or 16-bit (1/256 depth units) PNG (range-image "
                   "scenes).")
@click.option("--camera", type=click.Choice(CAMERA_NAMES), default="sr300", show_default=True,
              help="cam-* scenes: the depth camera, with its intrinsics and defects "
                   "(sr300-smooth: the SR300's error as measured, fine per pixel and "
                   "correlated over a few; ideal: none).")
@click.option("--depth-unit", type=click.Choice(DEPTH_UNIT_NAMES), default="0.1mm",
              show_default=True, help="cam-* scenes: uint16 PNG in 0.1 mm or 1 mm, or "
                                      "float32 metres as .npy (read with --preset "
                                      "tenth-mm-depth, mm-depth, metre-depth).")
@click.option("--frames", type=click.IntRange(1, 100000), default=1, show_default=True,
              help="cam-* scenes: frames of each, with seeds SEED, SEED+1, ...")
@verbosity_opts
def synth_cmd(out: str, scenes: tuple[list[str], list[str]] | None, noise: list[float],
              seed: int, size: tuple[int, int] | None, bits: str, camera: str,
              depth_unit: str, frames: int, verbose: int, quiet: int) -> None:
    """Render synthetic range images with ground truth into OUT.

    Writes OUT/<scene>-n<noise>.png, .gt.npy (int32 surface labels) and
    .gt.json (surfaces, objects, uncovered parts) for `rangeseg eval`.
    A depth-camera scene (cam-*) is written as OUT/<scene>-s<seed>.png
    (or .npy) with .gt.npy, .gt.json (objects marked pickable, the camera),
    .intrinsics.txt (3x3 matrix) and .gt.background.png (the empty support,
    for --background); `rangeseg run OUT` reads only the frames.
    """
    from ..errors import OutputError
    from ..synth.camera import MODEL_SIZE, write_camera_scenes
    from ..synth.scenes import SCENES, write_scenes

    classic, cams = scenes or (list(SCENES), [])
    try:
        written = write_scenes(Path(out), classic, noise, seed, size or (128, 128),
                               int(bits)) if classic else []
        count = len(written) // 3
        if cams:
            cam_files = write_camera_scenes(Path(out), cams, range(seed, seed + frames),
                                            size=size or MODEL_SIZE, camera=camera,
                                            depth_unit=depth_unit)
            written += cam_files
            count += len(cam_files) // 5
    except ValueError as exc:  # the options are checked; two noise levels with one name
        raise click.BadParameter(str(exc), param_hint="--noise") from None
    except OutputError as exc:  # OUT cannot be written
        raise UsageProblem(str(exc)) from None
    if not quiet:
        click.echo(f"wrote {count} scenes ({len(written)} files) to {out}", err=True)


@main.command(name="eval")
@click.argument("pred_dir", type=click.Path(file_okay=False), callback=_not_empty)
@click.argument("gt_dir", type=click.Path(file_okay=False), callback=_not_empty)
@click.option("--tolerance", type=click.FloatRange(0.5, 1.0), default=0.8, show_default=True,
              callback=lambda ctx, param, value: _tolerance_not_nan(value),
              help="Overlap tolerance T of Hoover et al. (1996).")
@click.option("--min-region", type=click.IntRange(min=0), default=50, show_default=True,
              help="Smaller GT regions are not judged.")
@click.option("--gt-parts", is_flag=True,
              help="Judge each 8-connected patch of a GT label as a region of its own.")
@click.option("--plot", type=click.Path(dir_okay=False), callback=_not_empty,
              help="Write a PNG of correct detections vs tolerance (needs matplotlib).")
@json_opt
@verbosity_opts
@click.pass_context
def eval_cmd(ctx: click.Context, pred_dir: str, gt_dir: str, tolerance: float,
             min_region: int, gt_parts: bool, plot: str | None, as_json: bool, verbose: int,
             quiet: int) -> None:
    """Score PRED_DIR/<stem>.labels.npy against GT_DIR/<stem>.gt.npy.

    Correct detections, over- and under-segmentations, missed and noise
    regions (Hoover et al. 1996), and whether each <stem>.holdsite.json lies
    inside one surface of an uncovered part. Exit code 1 when an image fails.
    """
    from ..batch.io import check_writable
    from ..errors import InputError, OutputError
    from ..synth.evaluate import evaluate_folder

    try:
        if plot:
            check_writable(Path(plot))
        result = evaluate_folder(pred_dir, gt_dir, tolerance=tolerance, min_region=min_region,
                                 gt_parts=gt_parts)
    except (InputError, OutputError) as exc:
        raise UsageProblem(str(exc)) from None
    for reason in result["errors"]:
        click.echo(reason, err=True)
    if as_json:
        _echo_json(ctx, result)
    elif not quiet:
        from .progress import print_eval_table

        print_eval_table(result)
    if plot:
        _plot(result["total"], Path(plot))
    ctx.exit(1 if result["errors"] else 0)


def _plot(total: dict[str, Any], path: Path) -> None:
    """``eval --plot``: the curve as a PNG; a failed write is one line and exit code 1."""
    from ..errors import OutputError
    from ..synth.evaluate import plot_curve

    try:
        if not plot_curve(total["curve"], path, gt_regions=total["gt_regions"]):
            click.echo("--plot: matplotlib is not installed; no plot written", err=True)
    except OutputError as exc:
        raise click.ClickException(str(exc)) from None


def _tolerance_not_nan(value: float) -> float:
    """``eval --tolerance`` by the library's check (``evaluate.check_tolerance``).

    NaN, which click's FloatRange lets through, is refused in click's words
    for a value out of range.
    """
    from ..synth.evaluate import check_tolerance

    try:
        return check_tolerance(value)
    except ValueError:
        raise click.BadParameter(f"{value} is not in the range 0.5<=x<=1.0") from None


@main.command(name="report")
@outdir_arg
@click.option("--json", "as_json", is_flag=True,
              help="Print {index, images, site, nosite, failed, running} as JSON on stdout.")
@verbosity_opts
@click.pass_context
def report_cmd(ctx: click.Context, out: str, as_json: bool, verbose: int, quiet: int) -> None:
    """Write OUT/index.html: a static page of the batch in OUT.

    The batch summary, then one card per image: its overlay, holdsite (or why
    there is none) or error, and links to its files; a filter by status. No
    server or network needed: open it from disk or from an object store.
    """
    from ..batch.report import write_report
    from ..errors import OutputError, StorageError

    try:
        result = write_report(_location(out))
    except (OutputError, StorageError) as exc:
        raise UsageProblem(str(exc)) from None
    if as_json:
        _echo_json(ctx, result)
    elif not quiet:
        click.echo(f"wrote {result['index']} ({result['images']} images)", err=True)


if __name__ == "__main__":  # pragma: no cover
    main()
