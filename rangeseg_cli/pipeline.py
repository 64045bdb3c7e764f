"""The whole segmentation of Al-Hujazi & Sood (1990), stage by stage.

Notes
-----
1. Step edges, small filter (Sec. V-1) and 2. roof edges, large adaptive
   filter in passes 2a and 2b (Sec. V-2): :mod:`rangeseg_cli.stages.edges`.
3. Linking and 4-connected components (Sec. V-3): :mod:`rangeseg_cli.stages.link`.
4. Least-squares quadratic region growing (Sec. V-4): :mod:`rangeseg_cli.stages.grow`;
   surface descriptions: :mod:`rangeseg_cli.stages.surfaces`.
5. Holdsite on the highest surface (Sec. VII): :mod:`rangeseg_cli.stages.holdsite`.

Each stage is a pure function of the arrays the earlier stages produced, so
running the stages one by one from files gives the same results as
:func:`run_pipeline`. Each stage function checks its arguments before any
work: ``ValueError`` for arrays that are not what it takes
(:func:`~rangeseg_cli.stages.rangeimage.check_stage_arrays`; a label of 2^31 would
size tables of gigabytes), ``ConfigError`` or ``TypeError`` for a
configuration value out of range or a table of the wrong class
(:func:`~rangeseg_cli.config.check_config`: a table built by hand).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .cell.frames import SharedFrames, check_frame_size, read_workspace_frames, roi_mask
from .config import Config, check_config, load_config
from .kernels.parallel import blas_one_thread, row_bands
from .models import Surface
from .refine import passes as refinement
from .stages.edges import EdgeMaps, detect_edges
from .stages.noise import estimate_noise, reduce_noise
from .stages.rangeimage import check_array, check_stage_arrays, require_shape_of_z, to_heights

#: Stage names in order.
STAGES = ("edges", "link", "grow", "holdsite")


@dataclass
class PipelineResult:
    """Everything the pipeline computes for one image.

    Attributes
    ----------
    heights
        float64 (H, W) heights the stages read, NaN where invalid: the image
        converted (:func:`~rangeseg_cli.stages.rangeimage.to_heights`) and,
        when noisier than the thresholds follow, median-filtered
        (:func:`~rangeseg_cli.stages.noise.reduce_noise`).
    edge_maps
        Step and roof edges (Sec. V-1, V-2).
    edges
        uint8 (H, W): 0 none, 1 step, 2 roof, 3 added by linking.
    components
        int32 (H, W) connected components after linking (0 = edge/dropped/invalid).
    labels
        int32 (H, W) final segmentation (0 = unlabelled/edge/invalid, 1..K).
    surfaces
        One :class:`~rangeseg_cli.models.Surface` per final label.
    holdsite
        The holdsite result (``.to_dict()`` gives ``holdsite.json``).
    timings
        Seconds spent per stage.
    noise_sigma
        Estimated noise of the heights, depth units
        (:func:`~rangeseg_cli.stages.noise.estimate_noise`): estimated while the
        pipeline runs when its configuration uses it (:func:`uses_noise`),
        else on first use of this attribute (the paper's pipeline, ``--preset
        paper``, does not need it: about a tenth of its time at 640x480).
    """

    heights: np.ndarray
    edge_maps: EdgeMaps
    edges: np.ndarray
    components: np.ndarray | None = None
    labels: np.ndarray | None = None
    surfaces: list[Surface] | None = None
    holdsite: Any = None
    timings: dict[str, float] = field(default_factory=dict)
    _noise: float | None = field(default=None, repr=False)

    @property
    def noise_sigma(self) -> float:
        """The noise estimate of :attr:`heights` (see the class notes)."""
        if self._noise is None:
            self._noise = estimate_noise(self.heights)
        return self._noise


def uses_noise(config: Config) -> bool:
    """Whether a stage of ``config`` uses the image's noise estimate.

    The thresholds that follow the sensor (``[input] auto_thresholds``, Sec. V-1, V-2)
    and the passes of ``[refine]`` that read it
    (:func:`~rangeseg_cli.refine.passes.uses_noise`: all but the fill and the bridge).
    """
    return config.input.auto_thresholds or refinement.uses_noise(config)


def stage_edges(z: np.ndarray, config: Config, *, noise: float | None = None) -> EdgeMaps:
    """Steps 1 and 2 (Sec. V-1, V-2) on heights ``z``.

    ``z`` as :func:`run_pipeline` reads it: :func:`~rangeseg_cli.stages.rangeimage.to_heights`,
    then :func:`~rangeseg_cli.stages.noise.reduce_noise` (a median filter of a
    frame noisier than the thresholds follow; the same ``z`` otherwise).

    With ``[input] auto_thresholds`` the thresholds follow the lateral scale
    and the noise of ``z`` (:func:`~rangeseg_cli.stages.noise.sensor_config`):
    ``noise`` when the caller has estimated it, computed here otherwise.
    """
    check_stage_arrays(z)
    check_config(config)
    if config.input.auto_thresholds:
        from .stages.noise import sensor_config

        config = sensor_config(config, z, estimate_noise(z) if noise is None else noise)
    return detect_edges(z, config)


def stage_link(z: np.ndarray, codes: np.ndarray, config: Config
               ) -> tuple[np.ndarray, np.ndarray]:
    """Step 3 (Sec. V-3): linked edge codes and connected components."""
    from .stages.link import link_edges

    check_stage_arrays(z, edges=codes)
    check_config(config)
    return link_edges(codes, ~np.isnan(z), config.link)


def stage_grow(z: np.ndarray, edges: np.ndarray, components: np.ndarray, config: Config,
               *, noise: float | None = None) -> tuple[np.ndarray, list[Surface]]:
    """Step 4 (Sec. V-4): final labels and their surface descriptions.

    :func:`stage_grow_and_gaps` without the step gaps.
    """
    labels, surfaces, _ = stage_grow_and_gaps(z, edges, components, config, noise=noise)
    return labels, surfaces


def stage_grow_and_gaps(z: np.ndarray, edges: np.ndarray, components: np.ndarray,
                        config: Config, *, noise: float | None = None
                        ) -> tuple[np.ndarray, list[Surface], dict[tuple[int, int], float]]:
    """Step 4 (Sec. V-4): final labels, their surface descriptions and step gaps.

    The step gaps (:func:`~rangeseg_cli.stages.surfaces.describe_surfaces_and_gaps`)
    are what :func:`stage_holdsite` would compute again from the labels and
    surfaces: pass them on (``gaps=``).

    With ``[refine] passes``, the refinement's passes follow growing, in
    the order of :data:`~rangeseg_cli.refine.passes.PASSES` (cut, merge and
    assign: beyond the paper); without, this is the paper's step 4.
    ``noise`` is :func:`~rangeseg_cli.stages.noise.estimate_noise` of ``z`` when the
    caller has it already (it is computed here otherwise).
    """
    from .stages.grow import component_fits, grow_regions
    from .stages.surfaces import describe_surfaces_and_gaps

    check_stage_arrays(z, edges=edges, components=components)
    check_config(config)
    fits = component_fits(z, components)  # seeds the growth; the split tests them
    labels = grow_regions(z, edges, components, config.grow, fits=fits)
    if not refinement.active_passes(config):
        return labels, *describe_surfaces_and_gaps(z, labels, config)  # the paper's step 4
    if uses_noise(config):  # the fill alone does not
        noise = estimate_noise(z) if noise is None else noise
    sigma = math.nan if noise is None else noise
    scene = refinement.Scene(z, edges, components, config, sigma, fits)
    labels = refinement.refine_regions(scene, labels)
    return labels, *describe_surfaces_and_gaps(z, labels, config)


def stage_holdsite(z: np.ndarray, labels: np.ndarray, surfaces: list[Surface],
                   config: Config, *, gaps: dict[tuple[int, int], float] | None = None,
                   background: Any = None, roi: Any = None, noise: float | None = None
                   ) -> Any:
    """Sec. VII: the holdsite on the highest usable surface.

    Parameters
    ----------
    z, labels, surfaces, config
        Heights, final labels and their surfaces, and the configuration.
    gaps
        The step gaps of :func:`stage_grow_and_gaps` when the caller has them
        (computed here otherwise).
    background
        The raw (H, W) frame of the empty workspace, in the units of the image
        ``z`` was made from: converted to heights by ``[input]`` as the image
        was (:func:`~rangeseg_cli.stages.rangeimage.to_heights`); ``None``: none.
    roi
        (H, W) mask, non-zero where a site may be (integers or booleans);
        ``None``: everywhere.
    noise
        :func:`~rangeseg_cli.stages.noise.estimate_noise` of ``z`` when the
        caller has it (estimated here otherwise).

    Raises
    ------
    ValueError
        When ``background`` or ``roi`` is not of the shape of ``z``.
    InputError
        When ``background`` is no usable range image, or ``roi`` no mask
        (:func:`~rangeseg_cli.cell.frames.roi_mask`).
    """
    from .stages.holdsite import find_holdsite

    bg_heights = roi_bool = None
    if background is not None:
        bg_heights = to_heights(background, config.input, name="`background`")
        require_shape_of_z(z, background=bg_heights)
    if roi is not None:
        roi_bool = roi_mask(roi)
        require_shape_of_z(z, roi=roi_bool)
    return find_holdsite(z, labels, surfaces, config, gaps=gaps, background=bg_heights,
                         roi=roi_bool, noise=noise)


def _finish(result: PipelineResult, z: np.ndarray, edges: np.ndarray, components: np.ndarray,
            config: Config, stages: int, frames: SharedFrames) -> None:
    """Stages 3 and 4 of :func:`run_pipeline`, into ``result``."""
    t0 = time.perf_counter()
    labels, surfaces, gaps = stage_grow_and_gaps(z, edges, components, config,
                                                 noise=result._noise)
    result.labels, result.surfaces = labels, surfaces
    result.timings["grow"] = time.perf_counter() - t0
    if stages >= 4:
        t0 = time.perf_counter()
        result.holdsite = stage_holdsite(z, labels, surfaces, config, gaps=gaps,
                                         background=frames.background, roi=frames.roi,
                                         noise=result._noise)  # None: it estimates
        result.timings["holdsite"] = time.perf_counter() - t0


def run_pipeline(image: Any, config: Config | None = None, *, stages: int = len(STAGES),
                 name: str = "image", background: Any = None, roi: Any = None
                 ) -> PipelineResult:
    """Segment one range image and find its holdsite.

    Parameters
    ----------
    image
        Array-like (H, W) or (H, W, 1) of raw values, read as ``[input]`` says.
    config
        The configuration; the defaults of :func:`~rangeseg_cli.config.load_config`
        when ``None`` (``load_config(preset="paper")`` is the paper's pipeline).
    stages
        How many stages of :data:`STAGES` to run, 1 to 4 (4 = all).
    name
        Named in error messages.
    background
        The raw (H, W) frame of the empty tote or table, in the units of
        ``image`` (converted to heights by ``[input]`` as ``image`` is);
        ``None``: the file ``[workspace] background`` names, read through
        :mod:`rangeseg_cli.batch.io`, if any. Used by the holdsite stage only.
    roi
        (H, W) mask, non-zero where a site may be (integers or booleans);
        ``None``: the file ``[workspace] roi`` names, if any.

    Returns
    -------
    PipelineResult
        Edges, components, labels, surfaces and holdsite (those of the stages run).

    Raises
    ------
    InputError
        When ``image`` is not a usable range image, or ``background`` or
        ``roi`` (given, or read from the files of ``[workspace]``) is not
        usable or not of its size.
    TypeError
        When ``config`` is not a :class:`~rangeseg_cli.config.Config`.
    ConfigError
        When a value of ``config`` is of the wrong type or out of range (a
        table built by hand: :func:`~rangeseg_cli.config.check_config`), or
        a file ``[workspace]`` names cannot be read or used
        (:func:`~rangeseg_cli.cell.frames.read_workspace_frames`).
    ValueError
        When ``stages`` is not an integer from 1 to 4.
    """
    if isinstance(stages, bool) or not isinstance(stages, int | np.integer) or not (
            1 <= stages <= len(STAGES)):
        raise ValueError(f"`stages` = {stages!r}: expected an integer from 1 to {len(STAGES)}")
    if config is None:
        config = load_config()
    else:
        check_config(config)  # a table built by hand skips load_config's checks
    frames = _workspace_frames(config, stages, background, roi)
    with blas_one_thread(shares_threads(getattr(image, "shape", None), config)):
        return _run(image, config, stages, name, frames)


def _workspace_frames(config: Config, stages: int, background: Any, roi: Any
                      ) -> SharedFrames:
    """The background and ROI of :func:`run_pipeline`: as given, else the configured files."""
    if stages < len(STAGES):
        return SharedFrames()
    ws = config.workspace
    if (background is None and ws.background) or (roi is None and ws.roi):
        files = read_workspace_frames(config)
    else:
        files = SharedFrames()
    if background is not None:
        files = replace(files, background=check_array(background, name="`background`"),
                        background_name="`background`")
    if roi is not None:
        files = replace(files, roi=roi_mask(roi), roi_name="`roi`")
    return files


def shares_threads(shape: tuple[int, ...] | None, config: Config) -> bool:
    """Whether :func:`run_pipeline` may run work of one image on several threads at once.

    The edge passes of an image of more than one row band
    (:func:`~rangeseg_cli.kernels.parallel.row_bands`), and the passes that share
    their pieces out (the split, recovery, recut and facets:
    :func:`~rangeseg_cli.refine.passes.shares_work`);
    ``shape`` None (not known yet) counts as yes. The paper's pipeline on a
    128x128 frame runs in the calling thread alone.
    """
    if shape is None or len(shape) < 2 or refinement.shares_work(config):
        return True
    return len(row_bands(int(shape[0]), int(shape[1]), 0)) > 1


def _run(image: Any, config: Config, stages: int, name: str, frames: SharedFrames
         ) -> PipelineResult:
    """:func:`run_pipeline` after its checks."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    z = to_heights(image, config.input, name=name)
    check_frame_size(z.shape, frames, name)
    noise = estimate_noise(z) if uses_noise(config) else None  # else when asked for
    z, noise = reduce_noise(z, config.input, noise)  # beyond the paper's noise range
    maps = stage_edges(z, config, noise=noise)
    timings["edges"] = time.perf_counter() - t0
    result = PipelineResult(heights=z, edge_maps=maps, edges=maps.codes, timings=timings,
                            _noise=noise)
    if stages >= 2:
        t0 = time.perf_counter()
        edges, components = stage_link(z, maps.codes, config)
        result.edges, result.components = edges, components
        timings["link"] = time.perf_counter() - t0
        if stages >= 3:
            _finish(result, z, edges, components, config, stages, frames)
    return result
