"""Configuration: one frozen dataclass per pipeline stage, loaded from TOML.

The defaults hold the parameters of Al-Hujazi & Sood (1990), Section VI:
step edges with a 5-tap Gaussian (sigma 1) and threshold 6; roof edges with a
17-tap Gaussian (sigma 4) and thresholds 6 (pass 2a) and 4 (pass 2b);
components below 20 pixels dropped; region growing at 10 e_A; a 7x7
holdsite window (Section VII); and the steps beyond the paper, on
(``--preset paper`` turns them off).

Every key is declared once here with its type, its allowed values and a
one-line help text; :func:`default_toml` prints them as commented TOML,
:func:`key_reference` gives them to ``docs/gen_config.py`` (which writes
``docs/configuration.md``), and
:func:`load_config` rejects unknown tables and keys, wrong types and values
out of range with a :class:`~rangeseg_cli.errors.ConfigError` that names the
table, the key, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import math
import os
import stat
import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, get_args

from .errors import ConfigError

Truncation = Literal["symmetric", "one-sided"]
BackgroundRule = Literal["lowest-border", "largest-border", "none"]

# Upper limits of the numeric keys: far beyond any useful setting, and small enough
# that no product or square the stages form overflows (a fit level squared,
# error_factor x e_A, a focal length times a depth; counts in int32).
#: Depth units (thresholds, noise levels): the largest height accepted
#: (:data:`~rangeseg_cli.stages.rangeimage.MAX_ABS_HEIGHT`).
MAX_DEPTH = 1e12
#: Factors on an RMS error or a noise level; squared ratios go to its square.
MAX_FACTOR = 1e3
#: Camera focal lengths and principal point, in pixels.
MAX_PIXELS = 1e6
#: Pixel counts: the largest int32.
MAX_COUNT = 2**31 - 1
#: Significant digits of floats in JSON outputs.
FLOAT_DIGITS = 6


def _opt(default: Any, help: str, **limits: Any) -> Any:
    """Declare a config field with its help text and limits (min, max, choices, odd)."""
    return field(default=default, metadata={"help": help, **limits})


@dataclass(frozen=True)
class InputConfig:
    """How raw pixel values become heights (docs/sensors.md)."""

    scale: float = _opt(1.0, "multiply raw values by this (e.g. 0.1 for depth in 0.1 mm -> mm)",
                        min_excl=0.0, max=1e6)
    larger_is_closer: bool = _opt(True, "true for height maps; false for depth along the "
                                  "optical axis (closer = smaller)")
    invalid: float = _opt(math.nan, "raw no-data value (nan = only NaN is invalid; 0 for most "
                          "depth cameras)")
    clipped_invalid: bool = _opt(True, "raw values at the top of an integer image's range "
                                 "(255 in 8 bits, 65535 in 16) are invalid too: the surface "
                                 "there lies beyond the sensor's range, and the clipped "
                                 "plateau is no surface to describe or to grip")
    metres_per_unit: float = _opt(0.0, "metres per depth unit after scaling (0.001 for mm; "
                                  "0 = unknown)", min=0.0, max=1e3)
    intrinsics: tuple[float, ...] = _opt(
        (0.0, 0.0, 0.0, 0.0), "camera intrinsics [fx, fy, cx, cy] in pixels: focal lengths "
        "and principal point (column, row), as --intrinsics reads them; [0, 0, 0, 0] = none",
        min=-MAX_PIXELS, max=MAX_PIXELS, item=float, length=4, nonempty=True)
    units_per_pixel: float = _opt(0.0, "depth units per pixel of lateral size of a height map "
                                  "(2 for rangeseg synth at 128x128): the lateral scale "
                                  "without camera intrinsics; 0 = unknown", min=0.0,
                                  max=MAX_DEPTH)
    fill_holes: int = _opt(4, "fill each hole of no reading of at most this many pixels "
                           "(8-connected: a camera's speckle) with the median of the readings "
                           "around it, as a suction cup spans it; 0 = off", min=0, max=8)
    auto_thresholds: bool = _opt(True, "scale the step and roof thresholds from the paper's "
                                 "3 depth units per pixel to the image's lateral scale (fx, fy "
                                 "or units_per_pixel) and raise them above its noise sigma 2; "
                                 "beyond twice that noise, median-filter the heights first "
                                 "(false = the thresholds as given, in depth units, and no "
                                 "filter)")

    @property
    def fx(self) -> float:
        """Focal length x in pixels (0 = no intrinsics)."""
        return self.intrinsics[0] if self.intrinsics else 0.0

    @property
    def fy(self) -> float:
        """Focal length y in pixels (0 = no intrinsics)."""
        return self.intrinsics[1] if self.intrinsics else 0.0

    @property
    def cx(self) -> float:
        """Principal point x (column) in pixels."""
        return self.intrinsics[2] if self.intrinsics else 0.0

    @property
    def cy(self) -> float:
        """Principal point y (row) in pixels."""
        return self.intrinsics[3] if self.intrinsics else 0.0

    @property
    def has_intrinsics(self) -> bool:
        """Whether camera intrinsics are configured."""
        return self.fx > 0 and self.fy > 0


@dataclass(frozen=True)
class StepConfig:
    """Step edges, small filter (Sec. V-1)."""

    sigma: float = _opt(1.0, "standard deviation of the 1-D Gaussian, pixels", min=0.5,
                        max=10.0)
    threshold: float = _opt(6.0, "minimum absolute residual (AR, eq. 3) of a step edge, "
                            "depth units (at 3 units per pixel with [input] auto_thresholds)",
                            min_excl=0.0, max=MAX_DEPTH)

    @property
    def taps(self) -> int:
        """Length of the 1-D Gaussian mask: 2 ceil(2 sigma) + 1 (5 at sigma 1, 17 at 4)."""
        return 2 * math.ceil(2 * self.sigma) + 1



@dataclass(frozen=True)
class RoofConfig:
    """Roof edges, large adaptive filter in two passes (Sec. V-2)."""

    sigma: float = _opt(4.0, "standard deviation of the 1-D Gaussian, pixels", min=0.5,
                        max=20.0)
    threshold_a: float = _opt(6.0, "AR threshold of pass 2a (step edges excluded), units as "
                              "[step] threshold",
                              min_excl=0.0, max=MAX_DEPTH)
    threshold_b: float = _opt(4.0, "AR threshold of pass 2b (step and 2a roof edges excluded)",
                              min_excl=0.0, max=MAX_DEPTH)
    search_radius: int = _opt(2, "a roof edge is the AR maximum within +-this many pixels "
                              "along the direction", min=1, max=10)
    truncation: str = _opt("symmetric", "how the adaptive mask is cut at an excluded pixel: "
                           "symmetric (both sides at the shorter reach; no bias on ramps) or "
                           "one-sided (the paper's Fig. 9)", choices=get_args(Truncation))

    @property
    def taps(self) -> int:
        """Length of the 1-D Gaussian mask: 2 ceil(2 sigma) + 1 (5 at sigma 1, 17 at 4)."""
        return 2 * math.ceil(2 * self.sigma) + 1



@dataclass(frozen=True)
class LinkConfig:
    """Linking and connected components (Sec. V-3)."""

    min_component: int = _opt(20, "components with fewer pixels are dropped", min=1,
                             max=MAX_COUNT)


@dataclass(frozen=True)
class GrowConfig:
    """Least-squares quadratic region growing (Sec. V-4)."""

    error_factor: float = _opt(10.0, "a pixel joins a surface when its squared residual is "
                               "below this times the surface's e_A", min=MAX_FACTOR ** -2,
                               max=MAX_FACTOR ** 2)
    passes: int = _opt(1, "growing passes (1 as in the paper; 0 = until nothing changes)",
                       min=0, max=1000)
    min_error: float = _opt(0.25, "floor on e_A in depth units squared (quantisation alone "
                            "gives 1/12)", min=MAX_DEPTH ** -1, max=MAX_DEPTH ** 2)
    planar_tolerance: float = _opt(0.1, "a surface is planar unless the quadratic terms lower "
                                   "its mean squared error by more than this fraction",
                                   min=0.0, max=1.0)
    planar_noise_test: bool = _opt(True, "a surface is also planar when the quadratic terms "
                                   "lower its error by no more than noise would (an F test at "
                                   "1 % on its pixel count: small regions)")


#: The passes of the refinement after growing, in the order they run
#: (:data:`rangeseg_cli.refine.passes.PASSES`): each one cuts, merges or assigns.
REFINE_PASSES = ("split", "recover", "fill", "merge", "recut", "bridge", "chamfers", "carve",
                 "facets", "boundaries", "merge_planes", "join_occluded", "leftovers")
#: Passes that extend another and run only with it (the bridge takes the fill's test farther).
PASS_NEEDS = {"bridge": ("fill",)}


@dataclass(frozen=True)
class RefineConfig:
    """The refinement after growing: cut, merge and assign with one fit test (beyond the paper)."""

    passes: tuple[str, ...] = _opt(REFINE_PASSES, "the passes that run (always in the order "
                                   "of the default list): split, recover and the others cut "
                                   "regions; merge, merge_planes and join_occluded join them; "
                                   "fill, bridge and boundaries give edge and boundary pixels "
                                   "to a neighbour; leftovers gives what no surface took a "
                                   "region (docs/configuration.md); [] = the paper's "
                                   "step 4 alone", names=REFINE_PASSES)
    fit_factor: float = _opt(1.25, "the fit test: one surface of order <= 2 explains a region "
                             "when its RMS error is at most this times the image noise "
                             "(estimated, at least sqrt(grow.min_error))",
                             min_excl=0.0, max=MAX_FACTOR)
    min_crease: float = _opt(10.0, "two planar regions that pass the fit test stay apart when "
                             "their planes meet at this angle in degrees or more",
                             min=0.0, max=90.0)
    crease_evidence: float = _opt(16.0, "merge two planes at min_crease or more all the same "
                                  "when their union leaves less squared error than this many "
                                  "times the noise variance (no evidence of a crease: 16 is "
                                  "chi-square, 3 degrees of freedom, at 0.999); 0 = off",
                                  min=0.0, max=MAX_FACTOR ** 2)
    min_region: int = _opt(20, "smallest region a cut makes, pixels (smaller pieces join "
                           "their nearest neighbour)", min=1, max=MAX_COUNT)
    normal_sigma: float = _opt(2.0, "Gaussian sigma in pixels of the local plane fits that "
                               "give the normals the cuts follow", min_excl=0.0, max=20.0)
    smoothness: float = _opt(1.0, "boundaries: cost of each 8-neighbour a pixel would "
                             "disagree with, against its squared residual in noise units",
                             min=0.0, max=MAX_FACTOR ** 2)
    max_noise: float = _opt(2.5, "recover no narrow face when the image noise is above this, "
                            "depth units", min=0.0, max=MAX_DEPTH)


@dataclass(frozen=True)
class SplitConfig:
    """The refinement's settings as its passes read them (``Config.split``; not a table).

    Derived from ``[refine]`` (:func:`refine_settings`): seven values from
    its keys; every other field is a constant of the refinement, named here
    and nowhere else (:data:`TUNING`). Which passes run is read from
    ``[refine] passes`` (:mod:`rangeseg_cli.refine.passes`), not from here.
    """

    fit_factor: float = _opt(1.25, "a component fails when its RMS fit error exceeds this "
                             "times the noise (estimated, at least sqrt(grow.min_error))",
                             min_excl=0.0, max=MAX_FACTOR)
    normal_sigma: float = _opt(2.0, "Gaussian sigma in pixels of the local plane fits that "
                               "give the surface normals", min_excl=0.0, max=20.0)
    min_gain: float = _opt(1.5, "two pieces stay apart when one quadric fits their "
                           "union this many times worse (RMS) than their own quadrics",
                           min=1.0, max=MAX_FACTOR)
    min_excess: float = _opt(0.0, "two pieces also stay apart when one quadric of their union "
                             "leaves more squared error per pixel than their own quadrics by "
                             "this many times the fit test's level squared (fit_factor x "
                             "noise)^2, as when a small piece's few stray pixels raise its own "
                             "RMS; 0 = off (the default: it needs a noise estimate that holds, "
                             "8 suits the synthetic scenes)", min=0.0,
                             max=MAX_FACTOR ** 2)
    min_crease: float = _opt(10.0, "two planar pieces that pass the fit test also stay apart "
                             "when their planes meet at this angle in degrees or more",
                             min=0.0, max=90.0)
    crease_evidence: float = _opt(16.0, "the merges join two planar pieces at min_crease "
                                  "or more all the same when one surface of their union "
                                  "leaves less squared error beyond their own two than this "
                                  "many times the noise variance (at least grow.min_error): "
                                  "no evidence of a crease, the narrow piece's tilt is noise "
                                  "(16: chi-square, 3 degrees of freedom, at 0.999); 0 = off",
                                  min=0.0, max=MAX_FACTOR ** 2)
    min_piece: int = _opt(20, "smallest piece, and smallest core of a piece (pixels "
                          "normal_sigma or more from its border), in pixels; smaller ones "
                          "join their nearest piece", min=1, max=MAX_COUNT)
    max_pieces: int = _opt(8, "most pieces the split cuts one component into (the pass "
                           "leftovers may add regions for what they drop)", min=2, max=64)
    crease_pieces: bool = _opt(True, "split a piece again when its plane fails the fit test "
                               "(a quadric can absorb the crease of two small faces), along a "
                               "straight crease when its normals do not divide it, and keep "
                               "two pieces apart that two planes fit better than one quadric")
    trim_pieces: bool = _opt(True, "when a piece whose quadric fails the fit test cannot be "
                             "split, leave out (to be regrown) its pixels off its dominant "
                             "surface: a sliver of a neighbouring face too thin to be a piece "
                             "of its own")
    trim_faces: bool = _opt(True, "with trim_pieces, the left-out pixels that one plane fits "
                            "(a face too narrow for the normals to divide: a chamfer, a "
                            "grazing side) become pieces of their own instead of being "
                            "regrown into their neighbours")
    plane_cut: bool = _opt(True, "when a piece whose quadric fails the fit test can be "
                           "neither split nor trimmed, cut it into the planes that consensus "
                           "finds in it (two or three narrow faces, as a small frustum's sides "
                           "with its top) if they hold most of its pixels")
    rounds: int = _opt(2, "rounds of testing and splitting; each round tests the regions "
                       "grown from the last one's pieces", min=1, max=5)
    recover_passes: int = _opt(2, "passes extending a recovered face into edge pixels it fits "
                               "better than their region", min=0, max=100)
    recover_max_noise: float = _opt(2.5, "recover no face when the estimated image noise is "
                                    "above this, depth units", min=0.0, max=MAX_DEPTH)
    refine_passes: int = _opt(3, "passes of the boundary refinement, each with the surfaces "
                              "fitted again", min=1, max=100)
    refine_smoothness: float = _opt(1.0, "cost of each 8-neighbour a pixel would disagree "
                                    "with, against its squared residual in units of the "
                                    "noise (at least grow.min_error)", min=0.0,
                                    max=MAX_FACTOR ** 2)
    refine_creases: bool = _opt(True, "in the boundary refinement, give a pixel near a crease "
                                "to the surface visible there (the lower of the two at a "
                                "convex crease, the higher at a concave one) instead of the "
                                "one with the smaller residual")


@dataclass(frozen=True)
class HoldsiteConfig:
    """Holdsite search for a vacuum gripper (Sec. VII)."""

    size: tuple[int, int] = _opt((7, 7), "gripper footprint [rows, cols] in pixels (odd)",
                                 min=1, max=255, odd=True)
    max_ar_std: float = _opt(1.0, "largest standard deviation of the 2-D AR (5x5 Gaussian, "
                             "sigma 1) inside the window, depth units; beyond the paper's noise "
                             "(with [input] auto_thresholds) plus 2 x the AR spread of the "
                             "noise above it", min=0.0, max=MAX_DEPTH)
    max_candidates: int = _opt(5, "runners-up reported beside the chosen site", min=0,
                               max=100)
    rotation_step: float = _opt(15.0, "rotation step in degrees for a non-square footprint "
                                "(at 0.5 the ends of a 255-pixel footprint move 1.1 pixels a "
                                "step: finer steps add angles, not windows)",
                                min=0.5, max=90.0)
    background: str = _opt("lowest-border", "which regions are background: lowest-border "
                           "(touching the border at the lowest height), largest-border, or "
                           "none", choices=get_args(BackgroundRule))
    max_tilt: float = _opt(45.0, "largest angle in degrees between a site's surface normal and "
                           "the support's normal ([workspace] support), else the sensor's "
                           "axis (the optical axis with camera intrinsics, else the height "
                           "axis with [input] units_per_pixel); tested only when that lateral "
                           "scale is known; 90 = any, as the paper", min=0.0, max=90.0)
    footprint_mm: tuple[float, float] = _opt(
        (0.0, 0.0), "gripper footprint [rows, cols] in millimetres, converted to odd pixel "
        "counts at each surface's depth where intrinsics and [input] metres_per_unit are "
        "known (else size applies); [0, 0] = size in pixels", min=0.0, max=1e4, item=float)
    max_flat_rms: float = _opt(0.0, "largest RMS of a plane fitted to the window's depths, "
                               "depth units; 0 = auto (2 x the image's noise + 1 unit, or "
                               "+ 1 mm with camera depth)", min=0.0, max=MAX_DEPTH)


@dataclass(frozen=True)
class WorkspaceConfig:
    """What may be picked: background frame, region of interest, height band, support."""

    background: str = _opt("", "a frame of the empty tote or table (file, read as [input] "
                           "says); pixels within background_tolerance of it are not picked; "
                           "\"\" = none")
    background_tolerance: float = _opt(0.0, "depth units; 0 = auto (4 x the image's noise, "
                                       "and at least 1 % of the depth with camera depth)",
                                       min=0.0, max=MAX_DEPTH)
    roi: str = _opt("", "a mask image of the pixels that may be picked (non-zero = yes; "
                    "same size as the frames); \"\" = everywhere")
    roi_box: tuple[int, ...] = _opt((), "[row0, col0, row1, col1]: only pixels with row0 <= "
                                    "row < row1 and col0 <= col < col1 may be picked; [] = "
                                    "everywhere", min=0, max=MAX_COUNT, length=4)
    roi_polygon: tuple[tuple[float, float], ...] = _opt(
        (), "[[row, col], ...]: only pixels inside this polygon (3 or more vertices) may be "
        "picked; [] = everywhere", min=-MAX_PIXELS, max=MAX_PIXELS, pairs=True)
    support: bool = _opt(True, "find the support (table or tote floor) as the dominant plane "
                         "by consensus; its pixels are never picked, and with nothing on it "
                         "the answer is 'nothing to pick'")
    support_tolerance: float = _opt(0.0, "pixels within this height of the support are on it, "
                                    "depth units; 0 = auto (4 x the image's noise, and at "
                                    "least 1 % of the depth with camera depth)", min=0.0,
                                    max=MAX_DEPTH)
    min_height: float = _opt(0.0, "only pixels at least this high above the support may be "
                             "picked, depth units (0 = above support_tolerance)", min=0.0,
                             max=MAX_DEPTH)
    max_height: float = _opt(0.0, "only pixels at most this high above the support may be "
                             "picked, depth units; 0 = no upper bound", min=0.0, max=MAX_DEPTH)
    border_structures: bool = _opt(True, "a structure that touches the image border (or its "
                                   "invalid margin) and rises far above the pile (a tote wall, "
                                   "the robot's arm) or above it resting on fingers alone (the "
                                   "arm), or that rings the floor (a tote's "
                                   "rim and walls seen whole, and its floor) or, in an empty "
                                   "view, crosses it (a tote's rim), is not picked "
                                   "while anything else may be; objects part at concave "
                                   "creases (a box leaning on a wall is not the wall), and a "
                                   "crack of no reading under 3 px wide puts no object at the "
                                   "border of the search order")


@dataclass(frozen=True)
class OutputConfig:
    """What is written beside the arrays."""

    png: bool = _opt(True, "write PNG pictures (step, roof, edges, components, labels, "
                     "overlay)")
    ply: bool = _opt(False, "write labelled point clouds, <stem>.points.ply and "
                     "<stem>.holdsite.ply (binary PLY; docs/outputs.md)")

    @property
    def float_digits(self) -> int:
        """Significant digits of floats in JSON outputs."""
        return FLOAT_DIGITS



@dataclass(frozen=True)
class Config:
    """The whole configuration: one table per stage."""

    input: InputConfig = field(default_factory=InputConfig)
    step: StepConfig = field(default_factory=StepConfig)
    roof: RoofConfig = field(default_factory=RoofConfig)
    link: LinkConfig = field(default_factory=LinkConfig)
    grow: GrowConfig = field(default_factory=GrowConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    holdsite: HoldsiteConfig = field(default_factory=HoldsiteConfig)
    workspace: WorkspaceConfig = field(default_factory=WorkspaceConfig)
    output: OutputConfig = field(default_factory=OutputConfig)

    @property
    def split(self) -> SplitConfig:
        """The refinement's settings (:func:`refine_settings` of ``[refine]``)."""
        return refine_settings(self.refine, TUNING)

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (tuples as lists), as written to the manifest."""
        return {
            table.name: {
                f.name: _plain(getattr(getattr(self, table.name), f.name))
                for f in dataclasses.fields(getattr(self, table.name))
            }
            for table in dataclasses.fields(self)
        }

    def digest(self, tables: tuple[str, ...] | None = None) -> str:
        """Short stable hash of the configuration, or of some of its tables (``--resume``).

        ``[output] ply`` counts from the grow stage on (``grow`` among
        ``tables``): the point clouds are written there and by the holdsite.
        """
        whole = self.to_dict()
        chosen = whole if tables is None else {t: whole[t] for t in tables}
        if tables is not None and "output" in chosen and "grow" not in tables:
            chosen["output"] = {k: v for k, v in chosen["output"].items() if k != "ply"}
        text = json.dumps(chosen, sort_keys=True, default=str)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def stage_digests(self) -> dict[str, str]:
        """Per stage, the digest of the tables that its result and the earlier ones depend on.

        A stage's result depends on its own table(s) and on everything the
        stages before it used (:data:`STAGE_TABLES`, cumulative): changing
        ``[holdsite]`` leaves the edges, components and labels current,
        changing ``[grow]`` or ``[refine]`` leaves the edges and components.
        """
        out: dict[str, str] = {}
        used: tuple[str, ...] = ()
        revisions: list[int] = []
        for stage, tables in STAGE_TABLES.items():
            used += tables
            revisions.append(STAGE_REVISIONS.get(stage, 0))
            digest = self.digest(used)
            if any(revisions):  # what a stage computes changed: --resume redoes it
                text = f"{digest}:{revisions}"
                digest = hashlib.sha256(text.encode()).hexdigest()[:16]
            out[stage] = digest
        return out


#: The tables each stage reads, in stage order (``input`` and ``output`` shape every stage's
#: files: heights, camera frame, pictures and digits; the noise-scaled thresholds).
STAGE_TABLES: dict[str, tuple[str, ...]] = {
    "edges": ("input", "output", "step", "roof"), "link": ("link",), "grow": ("grow", "refine"),
    "holdsite": ("holdsite", "workspace"),
}

#: Bumped when a stage gives other results for the same settings, so that ``--resume``
#: redoes what an earlier version made (and every later stage): edges 1 = the edges stage
#: median-filters heights beyond the paper's noise range; holdsite 1 = a tote's ring
#: and floor are structures, and sites report their tilt.
STAGE_REVISIONS: dict[str, int] = {"edges": 1, "holdsite": 1}

_TABLE_CLASSES: dict[str, type] = {
    "input": InputConfig, "step": StepConfig, "roof": RoofConfig, "link": LinkConfig,
    "grow": GrowConfig, "refine": RefineConfig, "holdsite": HoldsiteConfig,
    "workspace": WorkspaceConfig, "output": OutputConfig,
}

#: The constants of the refinement: :class:`SplitConfig`'s defaults.
TUNING = SplitConfig()

#: ``[refine] passes`` entry -> the old ``[split]`` switch it replaces.
PASS_SWITCHES = {"split": "enabled", "recover": "recover", "fill": "fill_edges",
                 "merge": "merge", "recut": "recut", "bridge": "bridge", "chamfers": "chamfers",
                 "carve": "carve", "facets": "facets", "boundaries": "refine",
                 "merge_planes": "merge_planes", "join_occluded": "join_occluded"}

#: ``[refine]`` key -> the :class:`SplitConfig` field it sets.
REFINE_FIELDS = {"fit_factor": "fit_factor", "min_crease": "min_crease",
                 "crease_evidence": "crease_evidence", "min_region": "min_piece",
                 "normal_sigma": "normal_sigma", "smoothness": "refine_smoothness",
                 "max_noise": "recover_max_noise"}


@functools.lru_cache(maxsize=64)
def refine_settings(refine: RefineConfig, tuning: SplitConfig) -> SplitConfig:
    """The refinement's settings: ``tuning`` with the values of ``refine``."""
    return dataclasses.replace(tuning, **{field: getattr(refine, key)
                                          for key, field in REFINE_FIELDS.items()})


def _retired_split_keys() -> dict[tuple[str, str], str]:
    """What became of each key of the old ``[split]`` table (refused, with this said)."""
    out = {("split", switch): f"is now the entry {name!r} of refine.passes (leave it out to "
           "turn the pass off)" for name, switch in PASS_SWITCHES.items()}
    out.update({("split", old): f"is now refine.{new}; set it there"
                for new, old in REFINE_FIELDS.items()})
    for f in dataclasses.fields(SplitConfig):
        out.setdefault(("split", f.name), "is no longer a setting (a constant of the "
                       "refinement: rangeseg_cli.config.TUNING); remove it")
    return out


#: Keys that moved or went: (table, key) -> what to say when the old one is used.
MOVED_KEYS: dict[tuple[str, str], str] = {
    ("holdsite", "units_per_pixel"): "is now input.units_per_pixel; set it there",
    **{("input", k): "is now part of input.intrinsics = [fx, fy, cx, cy]; set it there"
       for k in ("fx", "fy", "cx", "cy")},
    **{(t, "taps"): "is no longer a setting (the mask is 2 ceil(2 sigma) + 1 taps long); "
       "set sigma" for t in ("step", "roof")},
    ("holdsite", "pose"): "is no longer a setting (a curved surface's site takes the "
    "normal of a local quadric, a plane's its plane); remove it",
    ("output", "float_digits"): f"is no longer a setting (JSON floats have {FLOAT_DIGITS} "
    "significant digits); remove it",
    **_retired_split_keys(),
}

#: The sensor presets' footprint in mm: a 20 mm suction cup (a common bin-picking size,
#: as the 21x21 px window at 0.65 m of the SR300 sample).
CUP_MM = [20.0, 20.0]

#: Named presets: overrides applied before the TOML file and the command line.
PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    # the paper's algorithm alone: no refinement after growing, no workspace rules
    "paper": {"input": {"auto_thresholds": False, "fill_holes": 0},
              "grow": {"planar_noise_test": False},
              "holdsite": {"max_tilt": 90.0, "max_flat_rms": MAX_DEPTH},
              "workspace": {"support": False, "border_structures": False},
              "refine": {"passes": []}},
    "mm-depth": {"input": {"scale": 1.0, "larger_is_closer": False, "invalid": 0.0,
                           "metres_per_unit": 0.001, "auto_thresholds": True},
                 "holdsite": {"footprint_mm": CUP_MM}},
    "tenth-mm-depth": {"input": {"scale": 0.1, "larger_is_closer": False, "invalid": 0.0,
                                 "metres_per_unit": 0.001, "auto_thresholds": True},
                       "holdsite": {"footprint_mm": CUP_MM}},
    "metre-depth": {"input": {"scale": 1000.0, "larger_is_closer": False, "invalid": 0.0,
                              "metres_per_unit": 0.001, "auto_thresholds": True},
                    "holdsite": {"footprint_mm": CUP_MM}},
}


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    return value


def _describe_allowed(f: dataclasses.Field) -> str:
    meta = f.metadata
    kind = _kind(f)
    if "choices" in meta:
        return "one of " + ", ".join(repr(c) for c in meta["choices"])
    if "names" in meta:
        return "a list of distinct names among " + ", ".join(repr(c) for c in meta["names"])
    parts = []
    if kind is tuple:
        item = "numbers" if meta.get("item") is float else "integers"
        if meta.get("pairs"):
            parts.append("a list of [row, col] pairs of numbers (3 or more, or none)")
        elif "length" in meta:
            empty = "" if meta.get("nonempty") else " (or an empty list)"
            parts.append(f"a list of {meta['length']} {item}{empty}")
        else:
            parts.append(f"a list of two {item}")
    else:
        parts.append({bool: "true or false", int: "an integer", float: "a number",
                      str: "a string"}[kind])
    if "min" in meta:
        parts.append(f">= {_limit(meta['min'])}")
    if "min_excl" in meta:
        parts.append(f"> {_limit(meta['min_excl'])}")
    if "max" in meta:
        parts.append(f"<= {_limit(meta['max'])}")
    if meta.get("odd"):
        parts.append("odd")
    return " ".join(parts)


def _kind(f: dataclasses.Field) -> type:
    default = f.default
    return type(default) if not isinstance(default, tuple) else tuple


def _limit(x: float) -> str:
    """A limit as written in messages: ``0.5``, ``41``, ``1e+12``."""
    text = repr(x)
    return text if len(text) <= 10 else f"{x:.4g}"


def shown_value(value: Any) -> str:
    """``repr(value)`` for a message, cut short: an integer may have 4,000 digits."""
    try:
        text = repr(value)
    except ValueError:  # an integer beyond Python's limit on digits in a string
        return "<an integer of more than 4300 digits>"
    return text if len(text) <= 40 else f"{text[:30]}...<{len(text)} characters>"


def _beyond_floats(x: Any) -> bool:
    """Whether ``x`` is an integer too large for a float (TOML has integers of any size)."""
    if isinstance(x, bool) or not isinstance(x, int):
        return False
    try:
        float(x)
    except OverflowError:
        return True
    return False


def _check_number(x: Any, f: dataclasses.Field, integer: bool) -> bool:
    """Whether ``x`` is an integer (or a finite number) within ``f``'s limits.

    An integer too large for a float is refused for a float key, as any
    value beyond the key's ``max``, rather than overflowing in a comparison.
    """
    meta = f.metadata
    if isinstance(x, bool) or not isinstance(x, int if integer else int | float):
        return False
    if not integer:
        if _beyond_floats(x):
            return False
        x = float(x)
        if math.isnan(x):
            return f.name == "invalid"  # NaN: "no no-data value besides NaN"
        if math.isinf(x):
            return False
    if "min" in meta and x < meta["min"]:
        return False
    if "min_excl" in meta and x <= meta["min_excl"]:
        return False
    if "max" in meta and x > meta["max"]:
        return False
    return not (meta.get("odd") and int(x) % 2 == 0)


def _coerce(table: str, f: dataclasses.Field, value: Any) -> Any:
    """Check one value against its declaration; return it in the field's type."""
    if type(value).__module__ == "numpy" and getattr(value, "shape", None) == ():
        value = value.item()  # a numpy scalar (np.int64(5), np.float32(0.5), np.bool_)
    kind = _kind(f)
    ok: bool
    if kind is bool:
        ok = isinstance(value, bool)
    elif kind is str:
        ok = isinstance(value, str) and value in f.metadata.get("choices", (value,))
    elif kind is tuple:
        ok, value = _coerce_list(f, value)
    else:
        ok = _check_number(value, f, integer=kind is int)
        value = float(value) if ok and kind is float else value
        if ok and kind is float and math.isnan(value):
            value = math.nan  # the one NaN object, so that configs compare equal
    if not ok:
        beyond = kind is float and _beyond_floats(value)
        raise ConfigError(
            f"[{table}] {f.name} = {shown_value(value)}: expected {_describe_allowed(f)}"
            + (" (this integer is beyond the floating-point range)" if beyond else "")
        )
    return value


def _coerce_list(f: dataclasses.Field, value: Any) -> tuple[bool, Any]:
    """A list key's value checked (its length, items and their limits); as a tuple when ok."""
    meta = f.metadata
    if not isinstance(value, list | tuple):
        return False, value
    if "names" in meta:
        ok = all(isinstance(v, str) and v in meta["names"] for v in value) and len(
            set(value)) == len(value)
        return ok, tuple(n for n in meta["names"] if n in value) if ok else value
    integer = meta.get("item", int) is int
    if meta.get("pairs"):
        ok = (len(value) == 0 or len(value) >= 3) and all(
            isinstance(p, list | tuple) and len(p) == 2
            and all(_check_number(v, f, integer=False) for v in p) for p in value)
        return ok, tuple(tuple(float(v) for v in p) for p in value) if ok else value
    length = meta.get("length", 2)
    empty_ok = "length" in meta and not meta.get("nonempty")
    ok = (len(value) == length or (empty_ok and len(value) == 0)) and all(
        _check_number(v, f, integer=integer) for v in value)
    if not ok:
        return False, value
    return True, tuple(value) if integer else tuple(float(v) for v in value)


def check_value(table: str, key: str, value: Any) -> Any:
    """One value checked as ``[table] key`` is (its type and range); returned in its type.

    For values read elsewhere that mean the same thing (a holdsite's window in
    ``holdsite.json`` is a ``[holdsite] size``).

    Raises
    ------
    ConfigError
        For a wrong type or a value out of range (the message of :func:`load_config`).
    KeyError
        For an unknown table or key.
    """
    fields = {f.name: f for f in dataclasses.fields(_TABLE_CLASSES[table])}
    return _coerce(table, fields[key], value)


def from_json(values: dict[str, Any]) -> dict[str, Any]:
    """Tables read from JSON, with ``null`` as NaN where a key may be NaN.

    JSON has no NaN: :func:`~rangeseg_cli.batch.io.to_jsonable` writes it as
    ``null``, and the one key that may be NaN is ``[input] invalid`` (no
    no-data value besides NaN). A ``null`` elsewhere stays ``None``, so that
    :func:`build_config` names it as it is in the file.
    """
    out = {t: dict(e) if isinstance(e, dict) else e for t, e in values.items()}
    entries = out.get("input")
    if isinstance(entries, dict) and entries.get("invalid", 0) is None:
        entries["invalid"] = math.nan
    return out


def build_config(values: dict[str, Any], source: str = "config") -> Config:
    """Build a :class:`Config` from nested ``{table: {key: value}}`` overrides.

    Parameters
    ----------
    values
        Tables and keys to set; missing ones keep their defaults.
    source
        Named in error messages (usually the TOML file's path).

    Raises
    ------
    ConfigError
        On an unknown table or key, a wrong type or a value out of range.
    """
    config = Config(**_build_tables(values, source))
    try:
        _check_consistency(config)
    except ConfigError as exc:  # a clash of keys: named with the file too
        if source == "config" or str(exc).startswith(f"{source}: "):
            raise
        raise ConfigError(f"{source}: {exc}") from None
    return config


def _build_tables(values: dict[str, Any], source: str) -> dict[str, Any]:
    """One dataclass per table in ``values``; a bad value's error names ``source``.

    ``source`` ``"config"`` (the defaults, presets and overrides) is not named.
    """
    tables: dict[str, Any] = {}
    for table, entries in values.items():
        if table not in _TABLE_CLASSES:
            if not isinstance(entries, dict):  # `threshold = 8` above any [table]
                raise ConfigError(f"{source}: key {table} = {shown_value(entries)} is outside any "
                                  "table; put it under its table, e.g. [step] threshold = 8 "
                                  "(tables: " + ", ".join(_TABLE_CLASSES) + ")")
            _refuse_retired(table, entries, source)
            raise ConfigError(f"{source}: unknown table [{table}]; allowed tables: "
                              + ", ".join(_TABLE_CLASSES))
        if not isinstance(entries, dict):
            raise ConfigError(f"{source}: [{table}] must be a table, got {entries!r}")
        cls = _TABLE_CLASSES[table]
        fields = {f.name: f for f in dataclasses.fields(cls)}
        kwargs = {}
        for key, value in entries.items():
            _refuse_moved(table, key, source)
            if key not in fields:
                raise ConfigError(f"{source}: unknown key [{table}] {key}; allowed keys: "
                                  + ", ".join(fields))
            try:
                kwargs[key] = _coerce(table, fields[key], value)
            except ConfigError as exc:
                raise ConfigError(str(exc) if source == "config" else f"{source}: {exc}"
                                  ) from None
        tables[table] = cls(**kwargs)
    return tables


def _refuse_retired(table: str, entries: dict[str, Any], source: str) -> None:
    """A table that went (``[split]``): name what became of its first key, or of it."""
    for key in entries:
        _refuse_moved(table, key, source)
    if table == "split":
        raise ConfigError(f"{_where(source)}the table [split] is now [refine]; allowed "
                          "tables: " + ", ".join(_TABLE_CLASSES))


def _refuse_moved(table: str, key: str, source: str) -> None:
    """A key that moved or went (:data:`MOVED_KEYS`): one line saying what became of it."""
    if (table, key) in MOVED_KEYS:
        raise ConfigError(f"{_where(source)}[{table}] {key} {MOVED_KEYS[(table, key)]}")


def _where(source: str) -> str:
    """``source`` as a message's prefix; none for ``"config"`` (the options given)."""
    return "" if source == "config" else f"{source}: "


def _check_consistency(config: Config) -> None:
    passes = config.refine.passes
    for name, needs in PASS_NEEDS.items():
        if name in passes and not set(needs) <= set(passes):
            raise ConfigError(f"[refine] passes = {list(passes)}: {name!r} needs "
                              + " and ".join(repr(n) for n in needs) + " in the list too")
    cam = config.input
    if cam.intrinsics and (cam.fx < 0 or cam.fy < 0 or (cam.fx > 0) != (cam.fy > 0)):
        raise ConfigError(
            f"[input] intrinsics = {list(cam.intrinsics)}: camera intrinsics need both focal "
            "lengths fx, fy > 0 (or [0, 0, 0, 0]: none)")
    if cam.has_intrinsics and cam.larger_is_closer:
        raise ConfigError(
            f"[input] intrinsics = {list(cam.intrinsics)}, larger_is_closer = true: camera "
            "intrinsics need depth along the optical axis (larger_is_closer = false, e.g. "
            "--preset mm-depth); a height map has no camera frame")
    hold = config.holdsite
    if any(hold.footprint_mm) and not all(hold.footprint_mm):
        raise ConfigError(f"[holdsite] footprint_mm = {list(hold.footprint_mm)}: both sides "
                          "must be > 0 (or both 0: the footprint is size, in pixels)")
    _check_workspace(config)
    box = config.workspace.roi_box
    if box and not (box[0] < box[2] and box[1] < box[3]):
        raise ConfigError(f"[workspace] roi_box = {list(box)}: expected [row0, col0, row1, "
                          "col1] with row0 < row1 and col0 < col1")
    if config.roof.threshold_b > config.roof.threshold_a:
        raise ConfigError(
            f"[roof] threshold_b = {config.roof.threshold_b}: must be <= threshold_a "
            f"({config.roof.threshold_a}); pass 2b uses the lower threshold (Sec. V-2)"
        )


def _check_workspace(config: Config) -> None:
    """The workspace's keys agree: a band above a support, with room; a polygon with area."""
    ws = config.workspace
    if (ws.min_height or ws.max_height) and not ws.support:
        raise ConfigError(f"[workspace] min_height = {ws.min_height}, max_height = "
                          f"{ws.max_height}: a height band is measured above the support; it "
                          "needs [workspace] support = true")
    if ws.max_height and ws.min_height >= ws.max_height:
        raise ConfigError(f"[workspace] min_height = {ws.min_height}: must be below "
                          f"max_height ({ws.max_height}), or max_height = 0 (no upper bound)")
    poly = ws.roi_polygon
    if poly:
        twice = sum(r0 * c1 - r1 * c0 for (r0, c0), (r1, c1) in zip(poly, poly[1:] + poly[:1],
                                                                     strict=True))
        if abs(twice) < 1e-9:
            raise ConfigError(f"[workspace] roi_polygon = {[list(p) for p in poly]}: the "
                              "polygon has no area; give 3 or more [row, col] vertices that "
                              "enclose the pixels that may be picked")


def check_config(config: Any) -> None:
    """Check a :class:`Config` made without :func:`load_config` (a table built by hand).

    The tables are frozen dataclasses: ``Config(step=StepConfig(threshold=nan))``
    or :func:`dataclasses.replace` skips the checks of :func:`load_config`.
    This makes them on every value and across tables, as :func:`load_config` does.

    Raises
    ------
    TypeError
        When ``config`` is not a :class:`Config`, or one of its tables not
        the table's class.
    ConfigError
        For a value of the wrong type or out of range, or tables that do not
        agree (the messages of :func:`load_config`).
    """
    if not isinstance(config, Config):
        raise TypeError(f"config must be a rangeseg_cli.config.Config (load_config() makes "
                        f"one), got {type(config).__name__}")
    try:
        _checked(config)  # once per configuration: every stage function asks
    except TypeError as exc:  # a value that cannot be hashed (a list, built by hand)
        if "unhashable" not in str(exc):
            raise
        _check_tables(config)


@functools.lru_cache(maxsize=32)
def _checked(config: Config) -> None:
    """:func:`_check_tables`, remembered for configurations that passed (frozen, hashable)."""
    _check_tables(config)


def _check_tables(config: Config) -> None:
    for name, cls in _TABLE_CLASSES.items():
        table = getattr(config, name)
        if not isinstance(table, cls):
            raise TypeError(f"config.{name} must be a {cls.__name__}, got "
                            f"{type(table).__name__}")
    build_config(config.to_dict())  # every value and the tables' agreement, as loaded


def merge(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """Merge two nested ``{table: {key: value}}`` dicts; ``extra`` wins."""
    out = {t: dict(v) if isinstance(v, dict) else v for t, v in base.items()}
    for table, entries in extra.items():
        if isinstance(entries, dict) and isinstance(out.get(table), dict):
            out[table].update(entries)
        else:
            out[table] = entries
    return out


def load_config(
    path: str | Path | None = None,
    *,
    preset: str | None = None,
    overrides: dict[str, Any] | None = None,
) -> Config:
    """Load the configuration: defaults, then a preset, a TOML file and overrides.

    Parameters
    ----------
    path
        A TOML file with ``[input] [step] [roof] [link] [grow] [refine]
        [holdsite] [output]`` tables; ``None`` gives the defaults.
    preset
        A name from :data:`PRESETS` (e.g. ``"mm-depth"``).
    overrides
        Nested ``{table: {key: value}}``, applied last (command-line options).

    Returns
    -------
    Config
        The frozen configuration.

    Raises
    ------
    ConfigError
        For an unreadable file, invalid TOML, an unknown preset, table or key,
        a wrong type or a value out of range.
    TypeError
        When ``overrides`` is not a dict.
    """
    if overrides is not None and not isinstance(overrides, dict):
        raise TypeError(f"`overrides` must be a dict of tables, {{table: {{key: value}}}} "
                        f"(parse_settings makes one), got {type(overrides).__name__}")
    values: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise ConfigError(f"unknown preset {preset!r}; allowed: " + ", ".join(PRESETS))
        values = merge(values, PRESETS[preset])
    filed = None
    if path is not None:
        from_file = read_toml(Path(path))
        _build_tables(from_file, str(path))  # a bad value is named with its file
        values = filed = merge(values, from_file)
    if overrides:
        values = merge(values, overrides)
    try:
        return build_config(values)
    except ConfigError:
        if filed is not None:  # a clash of the file's own keys (min_height > max_height)
            build_config(filed, str(path))  # raises it, named with the file
        raise


def parse_settings(items: Iterable[str]) -> dict[str, dict[str, Any]]:
    """``TABLE.KEY=VALUE`` items (``--set``) as nested overrides for :func:`load_config`.

    A value is read as TOML (``8``, ``true``, ``"x"``, ``[21, 21]``); a bare
    word that is not TOML is taken as a string (a choice such as
    ``one-sided``). The keys and values are checked by :func:`load_config`.

    Raises
    ------
    ConfigError
        For an item without ``=``, without a table and a key, or with a line break.
    TypeError
        When ``items`` is not a list (a tuple, ...) of strings.
    """
    if isinstance(items, str | bytes) or not isinstance(items, Iterable):
        raise TypeError(f"`items` must be a list of 'TABLE.KEY=VALUE' strings, got "
                        f"{type(items).__name__}")
    out: dict[str, dict[str, Any]] = {}
    for item in items:
        if not isinstance(item, str):
            raise TypeError(f"`items` must hold 'TABLE.KEY=VALUE' strings, got {item!r}")
        if "\n" in item or "\r" in item:  # TOML would read the lines after the first too
            raise ConfigError(f"{item!r}: one TABLE.KEY=VALUE per --set, on one line")
        key, sep, raw = item.partition("=")
        table, dot, name = (part.strip() for part in key.partition("."))
        if not sep or not dot or not table or not name:
            raise ConfigError(f"{item!r}: expected TABLE.KEY=VALUE, e.g. step.threshold=8")
        try:
            value = tomllib.loads(f"v = {raw.strip()}")["v"]
        except ValueError:  # TOMLDecodeError, or an integer of more than 4300 digits
            value = raw.strip()  # a bare word: a string choice such as one-sided
        out.setdefault(table, {})[name] = value
    return out


#: Kinds of file that are not regular files, as messages name them.
SPECIAL_FILES = {stat.S_IFIFO: "a named pipe (FIFO)", stat.S_IFSOCK: "a socket",
                 stat.S_IFCHR: "a character device", stat.S_IFBLK: "a block device"}


def special_file(path: str | Path) -> str | None:
    """What ``path`` is when it is a FIFO, a socket or a device.

    Parameters
    ----------
    path
        A local path; links are followed.

    Returns
    -------
    str or None
        Its kind as :data:`SPECIAL_FILES` names it; ``None`` for a regular
        file, a folder or a path that cannot be read.
    """
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return SPECIAL_FILES.get(stat.S_IFMT(mode))


def read_setting_file(path: str | Path, what: str) -> bytes:
    """The bytes of a settings file (``--config``, ``--intrinsics``), never waiting forever.

    A pipe with a writer (``<(...)``, ``/dev/stdin``) is read to its end,
    and ``/dev/null`` reads as empty. A named pipe nobody writes to, a
    socket or another device is refused: opening a FIFO waits for a writer,
    so it is opened without waiting, and one that gives nothing is refused.

    Parameters
    ----------
    path
        A local path.
    what
        What the file should be, for messages (``"a config file; name a TOML file"``).

    Raises
    ------
    ConfigError
        One line naming the file and what it is.
    OSError
        From reading (missing, a folder, no permission): the caller names it.
    """
    kind = special_file(path)
    if kind is None or os.path.realpath(path) == os.devnull:
        with open(path, "rb") as fh:
            return _at_most(fh.read(SETTING_BYTES + 1), path, what)
    if kind != SPECIAL_FILES[stat.S_IFIFO]:
        raise ConfigError(f"{path}: {kind}, not {what}")
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)  # returns at once, writer or not
    try:
        os.set_blocking(fd, True)  # a writer's data is waited for; none gives the end
        with open(fd, "rb", closefd=False) as fh:  # fd is closed below, whatever fails
            data = _at_most(fh.read(SETTING_BYTES + 1), path, what)
    finally:
        os.close(fd)
    if not data:
        raise ConfigError(f"{path}: a named pipe (FIFO) nothing was written to, not {what}")
    return data


#: Most bytes a settings file may hold (the defaults' TOML is about 3 KB): a pipe that
#: never ends (``--config <(yes)``) or a wrong, huge file is refused, not read to the end.
SETTING_BYTES = 1 << 20


def _at_most(data: bytes, path: str | Path, what: str) -> bytes:
    """``data`` (read up to one byte past :data:`SETTING_BYTES`) unless it is longer."""
    if len(data) > SETTING_BYTES:
        raise ConfigError(f"{path}: more than {SETTING_BYTES // (1 << 20)} MiB, not {what}")
    return data


def read_toml(path: Path) -> dict[str, Any]:
    """Read a TOML file, turning every failure into a one-line :class:`ConfigError`."""
    try:
        data = read_setting_file(path, "a config file; name a TOML file")
        # a UTF-8 byte order mark (Windows editors write one) is not TOML's, but harmless
        return tomllib.loads(data.removeprefix(b"\xef\xbb\xbf").decode("utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config file ({exc.strerror})") from None
    except ValueError as exc:  # TOMLDecodeError, UnicodeDecodeError, 4300-digit integers
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        return repr(value)
    if isinstance(value, tuple | list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return json.dumps(value)
    return str(value)


@dataclass(frozen=True)
class KeyReference:
    """One configuration key as documented: its table, name, default, allowed values, help."""

    table: str
    table_help: str
    key: str
    default: str
    allowed: str
    help: str


def key_reference() -> list[KeyReference]:
    """Every key of :class:`Config` in order, with its default, allowed values and help text.

    The one source of ``rangeseg config``'s comments and of ``docs/configuration.md``.
    """
    config = Config()
    out = []
    for table_field in dataclasses.fields(config):
        table = getattr(config, table_field.name)
        table_help = str(type(table).__doc__).splitlines()[0]
        for f in dataclasses.fields(table):
            out.append(KeyReference(table_field.name, table_help, f.name,
                                    _toml_value(getattr(table, f.name)), _describe_allowed(f),
                                    f.metadata["help"]))
    return out


#: Where ``rangeseg config``'s output points for the whole reference.
DOCS = "docs/configuration.md and docs/sensors.md in rangeseg's repository"


def default_toml(config: Config | None = None, made_by: str = "") -> str:
    """Render a configuration as TOML with a comment on every key.

    Parameters
    ----------
    config
        The configuration to print; the defaults when ``None``.
    made_by
        What made ``config`` (e.g. ``"--preset mm-depth --set step.threshold=2"``),
        said in the header when it differs from the defaults.

    Returns
    -------
    str
        TOML text that :func:`load_config` reads back to the same values; a key
        whose value differs from the default says the default in its comment.
    """
    config = config or Config()
    defaults = Config()
    if config.digest() == defaults.digest():
        lines = ["# rangeseg configuration: the defaults (the parameters of Al-Hujazi & Sood",
                 "# 1990, Section VI, and the steps beyond the paper). Every key is optional."]
    else:
        lines = ["# rangeseg configuration from " + (made_by or "the options given")
                 + " (not the defaults):",
                 "# keys that differ from the defaults say their default. Every key is optional."]
    lines.append(f"# Reference: {DOCS}.")
    for table_field in dataclasses.fields(config):
        table = getattr(config, table_field.name)
        default_table = getattr(defaults, table_field.name)
        lines += ["", f"# {str(type(table).__doc__).splitlines()[0]}", f"[{table_field.name}]"]
        for f in dataclasses.fields(table):
            value = _toml_value(getattr(table, f.name))
            default = _toml_value(getattr(default_table, f.name))
            changed = f"; default {default}" if value != default else ""
            lines.append(f"# {f.metadata['help']} ({_describe_allowed(f)}{changed})")
            lines.append(f"{f.name} = {value}")
    return "\n".join(lines) + "\n"
