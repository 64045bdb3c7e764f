"""A log of a batch for the Rerun viewer (``--rerun FILE.rrd``; ``pip install 'rangeseg[rerun]'``).

One step per image on the timeline ``image`` (its position in the batch, in
input order): its name (``image``), depth (``camera/depth``; heights for a
height map; under a ``Pinhole`` with intrinsics), labels as a segmentation
image in the colours of ``labels.png`` (``camera/labels``), the point cloud
by surface (``points``, in the frame of :mod:`.pointcloud`) and the
holdsite's footprint and approach arrow (``holdsite/...``); what an image
lacks (labels after ``edges``, a site) is cleared at its step.

With ``--jobs N`` the workers never log: the main process writes the log
after the batch from each finished image's files in OUT (``range.npy``,
``labels.npy``, ``holdsite.json``), in input order. One process writes the
file, the log is the same for any ``--jobs`` and executor, and it goes to a
temporary file renamed at the end (a killed run leaves none half written);
the price is that it appears when the batch ends. Imported only for ``--rerun``.
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from ..config import InputConfig
from ..errors import ConfigError, OutputError
from . import io
from .io import Location
from .pointcloud import cloud, holdsite_vertices
from .render import label_colors

#: What to install for ``--rerun``.
INSTALL_HINT = "pip install 'rangeseg[rerun]'"


def require_rerun() -> Any:
    """The ``rerun`` module.

    Raises
    ------
    ConfigError
        One line saying how to install it, when it is not installed.
    """
    try:
        import rerun
    except ImportError:
        raise ConfigError("--rerun needs the Rerun SDK (rerun-sdk), which is not installed: "
                          f"{INSTALL_HINT}") from None
    return rerun


def write_log(path: Path, out: Location, images: Iterable[tuple[int, str]],
              camera: InputConfig) -> None:
    """Write the ``.rrd`` log of ``images``, ``(time step, relative stem)``, from ``out``.

    Raises
    ------
    OutputError
        Naming a file of an image that cannot be read, or ``path`` when the
        log cannot be written (the folders missing above it are made).
    """
    rr = require_rerun()
    tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}.tmp")
    rec = rr.RecordingStream("rangeseg")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        _write(rr, rec, tmp, out, images, camera)
        os.replace(tmp, path)
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise OutputError(f"{path}: cannot write the Rerun log ({exc})") from None
    except BaseException:
        rec.disconnect()
        tmp.unlink(missing_ok=True)
        raise


def _write(rr: Any, rec: Any, tmp: Path, out: Location, images: Iterable[tuple[int, str]],
           camera: InputConfig) -> None:
    """:func:`write_log`'s recording into ``tmp``."""
    rec.save(tmp)
    rec.log("/", rr.ViewCoordinates.RDF if camera.has_intrinsics else rr.ViewCoordinates.RDB,
            static=True)
    for step, rel in images:
        rec.set_time("image", sequence=step)
        _log_image(rr, rec, out, rel, camera)
    rec.flush()
    rec.disconnect()


def _log_image(rr: Any, rec: Any, out: Location, rel: str, camera: InputConfig) -> None:
    """One image's step: what its files in ``out`` hold, and a clear for what they lack."""
    def file(name: str) -> Location | None:
        where = out / f"{rel}.{name}"
        return where if where.exists() else None

    z = io.read_npy(out / f"{rel}.range.npy")
    rec.log("image", rr.TextDocument(rel))
    if camera.has_intrinsics:
        rec.log("camera", rr.Pinhole(focal_length=[camera.fx, camera.fy], width=z.shape[1],
                                     principal_point=[camera.cx, camera.cy],
                                     height=z.shape[0]))
    depth = np.nan_to_num(z if camera.larger_is_closer else -z, nan=0.0).astype(np.float32)
    rec.log("camera/depth", rr.DepthImage(depth, meter=1.0 / (camera.metres_per_unit or 1.0)))
    labels_file, site_file = file("labels.npy"), file("holdsite.json")
    if labels_file is None:
        for entity in ("camera/labels", "points"):
            rec.log(entity, rr.Clear(recursive=False))
    else:
        labels = io.read_npy(labels_file)
        colors = label_colors(np.arange(int(labels.max(initial=0)) + 1))
        rec.log("/", rr.AnnotationContext([(i, f"surface {i}", tuple(int(v) for v in c))
                                           for i, c in enumerate(colors) if i]))
        rec.log("camera/labels", rr.SegmentationImage(labels))
        rows, cols, xyz = cloud(z, labels, camera)
        rec.log("points", rr.Points3D(xyz, class_ids=labels[rows, cols]))
    site = io.read_json(site_file).get("holdsite") if site_file is not None else None
    if not site:
        rec.log("holdsite", rr.Clear(recursive=True))
        return
    v = holdsite_vertices(site, camera)
    rec.log("holdsite/footprint", rr.LineStrips3D([v[[0, 1, 2, 3, 0]]], colors=[255, 255, 255]))
    rec.log("holdsite/approach", rr.Arrows3D(origins=[v[4]], vectors=[v[5] - v[4]],
                                             colors=[255, 255, 255]))
