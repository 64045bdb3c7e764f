"""The refinement after growing, as one table of passes (beyond the paper, Sec. VIII).

Each pass takes the labels and gives new ones; each is a **cut** (a region
that the fit test fails becomes the surfaces that explain it), a **merge**
(touching regions that one surface explains become one) or an **assign**
(edge and boundary pixels go to the neighbouring surface that predicts them
best). :data:`PASSES` lists them in the order they run; ``[refine] passes``
says which are on (``--preset paper``: none, the paper's step 4 alone).
Which passes use the image's noise, which share work out over threads, and
whether anything runs at all are read from this table, never listed
elsewhere. The fit test they share is
:func:`~rangeseg_cli.stages.grow.component_fits` against ``[refine] fit_factor``
times the noise (:func:`~rangeseg_cli.stages.noise.estimate_noise`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from ..config import PASS_NEEDS, Config

Op = Literal["cut", "merge", "assign"]


@dataclass(frozen=True)
class Scene:
    """What the passes read besides the labels: heights, edges, components, noise."""

    z: np.ndarray
    edges: np.ndarray
    components: np.ndarray
    config: Config
    sigma: float
    fits: object = None


Run = Callable[[Scene, np.ndarray], np.ndarray]


def _function(module: str, name: str) -> Callable[..., np.ndarray]:
    """``rangeseg_cli.refine.<module>.<name>``, imported when a pass first runs."""
    found = importlib.import_module(f".{module}", __package__)
    return getattr(found, name)  # type: ignore[no-any-return]


def _with_noise(module: str, name: str) -> Run:
    """A pass called as ``f(z, labels, config, noise=sigma)``."""
    return lambda s, labels: _function(module, name)(s.z, labels, s.config, noise=s.sigma)


def _on_growth(module: str, name: str) -> Run:
    """A pass called as ``f(z, labels, config.grow)`` (the growing's own bound)."""
    return lambda s, labels: _function(module, name)(s.z, labels, s.config.grow)


def _split(s: Scene, labels: np.ndarray) -> np.ndarray:
    return _function("split", "split_regions")(s.z, s.edges, s.components, labels, s.config,
                                               noise=s.sigma, fits=s.fits)


def _leftovers(s: Scene, labels: np.ndarray) -> np.ndarray:
    return _function("fill", "keep_leftovers")(labels, s.components,
                                                s.config.link.min_component)


def _recover(s: Scene, labels: np.ndarray) -> np.ndarray:
    return _function("recover", "recover_faces")(s.z, s.components, labels, s.config,
                                                 noise=s.sigma)


@dataclass(frozen=True)
class Pass:
    """One entry of :data:`PASSES`.

    Attributes
    ----------
    name
        The ``[refine] passes`` entry that turns it on.
    op
        Cut, merge or assign.
    about
        What it does, in one line (docs/configuration.md).
    run
        The pass: ``run(scene, labels) -> labels``.
    needs
        Other entries that must be on too (the bridge extends the fill).
    after_any
        When not empty, it runs only if one of these is on (a second fill
        after the merges, for what their new surfaces explain).
    uses_noise
        Whether it reads the noise estimate.
    shares_work
        Whether it shares its pieces out over threads
        (:func:`~rangeseg_cli.kernels.parallel.map_tasks`).
    """

    name: str
    op: Op
    about: str
    run: Run
    needs: tuple[str, ...] = ()
    after_any: tuple[str, ...] = ()
    uses_noise: bool = True
    shares_work: bool = False


_FILL = _on_growth("fill", "fill_edges")
_BRIDGE = _on_growth("fill", "bridge_gaps")
_FACETS = _with_noise("facets", "facet_regions")

#: The passes in the order they run.
PASSES: tuple[Pass, ...] = (
    Pass("split", "cut", "a component that fails the fit test is split at its creases "
         "(normals, then planes by consensus) and regrown, in two rounds", _split,
         shares_work=True),
    Pass("recover", "cut", "a band of unlabelled pixels that one plane fits and no "
         "neighbour does becomes a narrow face of its own", _recover, shares_work=True),
    Pass("fill", "assign", "each edge pixel goes to the neighbouring surface that fits it "
         "best within the growing bound (again after merge and recut)", _FILL,
         uses_noise=False),
    Pass("merge", "merge", "touching regions whose union one quadric fits within the fit "
         "test become one", _with_noise("merge", "merge_regions")),
    Pass("recut", "cut", "a region is cut along the straight line where a plane ends "
         "(a tangent curved surface or another plane)", _with_noise("recut", "recut_regions"),
         shares_work=True),
    Pass("fill", "assign", "", _FILL, after_any=("merge", "recut"), uses_noise=False),
    Pass("bridge", "assign", "an edge pixel still unlabelled goes to a planar region within "
         "2 pixels whose plane explains it (runs again at the end)", _BRIDGE,
         needs=PASS_NEEDS["bridge"], uses_noise=False),
    Pass("chamfers", "cut", "a narrow face between two planes at a crease gets a region "
         "when a plane between them explains the crease clearly better",
         _with_noise("chamfer", "chamfer_faces")),
    Pass("carve", "cut", "a narrow face grown into a planar region's border gets a region "
         "when one plane fits it at a crease with the region's",
         _with_noise("carve", "carve_faces")),
    Pass("facets", "cut", "a region that fails the fit test is cut into the planes that "
         "explain it when no quadric joins two of them (runs again after boundaries)",
         _FACETS, shares_work=True),
    Pass("boundaries", "assign", "each boundary pixel moves to the neighbouring surface "
         "that predicts it best, counting the neighbours it would disagree with "
         "(smoothness)", _with_noise("boundaries", "refine_boundaries")),
    Pass("merge_planes", "merge", "touching planar regions whose union one plane fits "
         "become one", _with_noise("merge", "merge_planes")),
    Pass("facets", "cut", "", _FACETS, after_any=("boundaries", "merge_planes"),
         shares_work=True),
    Pass("bridge", "assign", "", _BRIDGE, needs=PASS_NEEDS["bridge"],
         after_any=("chamfers", "carve", "boundaries", "merge_planes", "facets"),
         uses_noise=False),
    Pass("join_occluded", "merge", "patches of one surface that something in front divides "
         "get one label", _with_noise("occlusion", "join_occluded")),
    Pass("leftovers", "assign", "pixels of a component that no surface took, in 4-connected "
         "groups of at least [link] min_component and 3 pixels wide, get a region each (the "
         "paper's growing leaves none)", _leftovers, uses_noise=False),
)


def active_passes(config: Config) -> tuple[Pass, ...]:
    """The entries of :data:`PASSES` that run under ``config``, in order."""
    on = set(config.refine.passes)
    return tuple(p for p in PASSES if p.name in on and on.issuperset(p.needs)
                 and (not p.after_any or on.intersection(p.after_any)))


def refine_regions(scene: Scene, labels: np.ndarray) -> np.ndarray:
    """Run the active passes of :data:`PASSES` on the grown ``labels`` (Sec. V-4 onwards)."""
    for step in active_passes(scene.config):
        labels = step.run(scene, labels)
    return labels


def uses_noise(config: Config) -> bool:
    """Whether a pass of ``config`` reads the image's noise estimate."""
    return any(p.uses_noise for p in active_passes(config))


def shares_work(config: Config) -> bool:
    """Whether a pass of ``config`` shares its work out over threads."""
    return any(p.shares_work for p in active_passes(config))
