"""A static HTML page of a batch: what ``rangeseg report OUT`` writes as ``OUT/index.html``.

One self-contained file, its CSS and a few lines of JavaScript inline (no
server, no network): the batch summary from the manifest, then one card per
image with its overlay, its holdsite or the reason there is none, or the
one-line error of a failure; a filter by status; links to every file of the
image. Links are relative and percent-encoded (a name that is no UTF-8 by its
bytes), so the page works from a ``file://`` URL, a web server or an object
store; every name and message is HTML-escaped.
"""

from __future__ import annotations

import html
import math
import os
from collections import Counter
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import quote

from ..errors import OutputError
from . import io
from .io import Location, URLPath
from .runner import MANIFEST, read_manifest

#: The page's name in OUT.
INDEX = "index.html"
#: The cards' statuses and their labels, in the filter's order.
STATUSES = {"site": "holdsite", "nosite": "no holdsite", "failed": "failed",
            "running": "running"}

_CSS = """body{font:14px system-ui,sans-serif;margin:1em;background:#f4f4f4;color:#222}
h1{font-size:1.3em;overflow-wrap:anywhere}nav{margin:.6em 0}
nav button{margin:0 .3em .3em 0;padding:.3em .9em;border:1px solid #888;border-radius:1em;
background:#fff;cursor:pointer}nav button[aria-pressed=true]{background:#222;color:#fff}
main{display:grid;grid-template-columns:repeat(auto-fill,minmax(290px,1fr));gap:1em}
.card{background:#fff;border-radius:6px;padding:.6em;border-top:5px solid #2a2}
.card[hidden]{display:none}.nosite{border-color:#e90}.failed{border-color:#d22}
.running{border-color:#888}h2{font-size:1em;margin:0 0 .4em;overflow-wrap:anywhere}
h2 small{font-weight:normal;color:#666}.input{color:#666;font-size:.85em;overflow-wrap:anywhere}
img{display:block;width:100%;aspect-ratio:4/3;object-fit:contain;background:#000;
image-rendering:pixelated}
dl{display:grid;grid-template-columns:auto 1fr;gap:.1em .8em;margin:.5em 0}dt{color:#666}
dd{margin:0}.note{overflow-wrap:anywhere}.failed .note{color:#b00}
.files a{margin-right:.6em;font-size:.85em;white-space:nowrap}"""
_JS = """const buttons=document.querySelectorAll("nav button");
for(const b of buttons)b.onclick=()=>{for(const o of buttons)o.setAttribute("aria-pressed",o===b);
for(const c of document.querySelectorAll(".card"))
c.hidden=b.dataset.show!=="all"&&c.dataset.status!==b.dataset.show;};"""


@dataclass(frozen=True)
class Card:
    """One image of the page: its status (a key of :data:`STATUSES`) and what it shows."""

    rel: str
    status: str
    entry: dict[str, Any]
    site: dict[str, Any] | None = None
    note: str = ""  # why there is no site, or the error of a failure
    files: list[str] = field(default_factory=list)  # its files, relative to OUT


def write_report(out: Location) -> dict[str, Any]:
    """Write ``out/index.html``, the page of the batch in ``out``, atomically.

    Parameters
    ----------
    out
        The OUT folder of a batch (a path or a URL), holding its manifest.

    Returns
    -------
    dict
        ``index`` (the page's path), ``images`` and the number of cards of each status.

    Raises
    ------
    OutputError
        One line naming ``out`` or its manifest: no such folder, no manifest, a
        manifest that is not rangeseg's, or a page that cannot be written.
    """
    manifest = _manifest(out)
    cards = make_cards(out, manifest)
    io.write_text(out / INDEX, render_page(manifest, cards, title=io.printable(str(out))))
    counts = Counter(c.status for c in cards)
    return {"index": str(out / INDEX), "images": len(cards)} | {s: counts[s] for s in STATUSES}


def _manifest(out: Location) -> dict[str, Any]:
    expected = f"expected the OUT folder of a batch (`rangeseg run`), holding {MANIFEST}"
    if not out.is_dir():
        raise OutputError(f"{out}: no such folder; {expected}")
    manifest = read_manifest(out)
    if not manifest:
        raise OutputError(f"{out}: no {MANIFEST} in it; {expected}")
    return manifest


def make_cards(out: Location, manifest: dict[str, Any]) -> list[Card]:
    """The cards of the images in ``manifest`` (as :func:`read_manifest` gives it), by name."""
    images = manifest["images"]
    files: dict[str, list[str]] = {}
    for name in sorted(_listing(out)):
        owner = _owner(name, images)
        if owner is not None and name not in (INDEX, MANIFEST):
            files.setdefault(owner, []).append(name)
    return [_card(out, rel, images[rel], files.get(rel, [])) for rel in sorted(images)]


def _listing(out: Location) -> list[str]:
    """Every file below ``out``, relative to it (``/``-separated): one listing."""
    if isinstance(out, URLPath):
        return out.files()
    return [os.path.relpath(os.path.join(top, f), out).replace(os.sep, "/")
            for top, _, names in os.walk(out) for f in names]


def _owner(name: str, images: dict[str, Any]) -> str | None:
    """The image whose file ``name`` is (``<rel>.<what>``, the longest such ``rel``)."""
    slash, cut = name.rfind("/"), len(name)
    while (cut := name.rfind(".", 0, cut)) > slash + 1:
        if name[:cut] in images:
            return name[:cut]
    return None


def _card(out: Location, rel: str, entry: dict[str, Any], files: list[str]) -> Card:
    if entry["status"] != "done":
        note = entry.get("error", "left by a killed run, or being processed: "
                                  "`--resume` redoes it")
        return Card(rel, entry["status"], entry, note=str(note), files=files)
    if f"{rel}.holdsite.json" not in files:
        return Card(rel, "nosite", entry, note="no holdsite.json (stages run: "
                    + ", ".join(entry.get("stages", [])) + ")", files=files)
    try:
        data = io.read_json(out / f"{rel}.holdsite.json")
    except OutputError as exc:
        return Card(rel, "nosite", entry, note=str(exc), files=files)
    site, reason = _dict(data).get("holdsite"), str(_dict(data).get("reason", ""))
    if isinstance(site, dict):
        return Card(rel, "site", entry, site, reason, files)
    return Card(rel, "nosite", entry, note=reason, files=files)


def render_page(manifest: dict[str, Any], cards: list[Card], *, title: str) -> str:
    """The page: its head, the summary and filter, and the cards."""
    upp = _dict(manifest["config"].get("input")).get("units_per_pixel", 0.0)
    body = "\n".join(_card_html(c, upp) for c in cards)
    return (f"<!doctype html>\n<html lang=en><head><meta charset=utf-8>"
            f"<meta name=viewport content='width=device-width'>"
            f"<title>rangeseg: {_text(title)}</title><style>{_CSS}</style></head><body>\n"
            f"<header><h1>rangeseg: {_text(title)}</h1>\n{_summary(manifest, cards)}</header>\n"
            f"<main>\n{body}\n</main>\n<script>{_JS}</script></body></html>\n")


def _summary(manifest: dict[str, Any], cards: list[Card]) -> str:
    """The filter's buttons with the counts, and the batch's times."""
    counts = Counter(c.status for c in cards)
    shown = [("all", f"all {len(cards)}")] + [
        (s, f"{label} {counts[s]}") for s, label in STATUSES.items() if counts[s]]
    buttons = "".join(f'<button data-show={s} aria-pressed={str(s == "all").lower()}>'
                      f"{label}</button>" for s, label in shown)
    stages: Counter[str] = Counter()
    for entry in manifest["images"].values():
        stages.update({k: v for k, v in _dict(entry.get("timings")).items() if _is_num(v)})
    summary = _dict(manifest.get("summary"))
    seconds, skipped = summary.get("seconds"), summary.get("not_images")
    line = (f"rangeseg {_text(manifest.get('version', '?'))}; last command "
            f"<code>{_text(manifest.get('command', '?'))}</code>"
            + (f" took {seconds:.1f} s" if _is_num(seconds) else "")
            + (f", {_text(skipped)} files not images" if skipped else "")
            + "; stage seconds over all images: "
            + (", ".join(f"{k} {v:.1f}" for k, v in sorted(stages.items())) or "none"))
    return f'<p class="summary">{line}</p>\n<nav>{buttons}</nav>'


def _card_html(card: Card, units_per_pixel: float) -> str:
    name, overlay = _text(card.rel), f"{card.rel}.overlay.png"
    parts = [f'<article class="card {card.status}" data-status={card.status}>',
             f"<h2>{name} <small>{STATUSES.get(card.status, card.status)}</small></h2>"]
    if overlay in card.files:
        parts.append(f'<a href="{_href(overlay)}"><img src="{_href(overlay)}" '
                     f'loading="lazy" alt="overlay of {name}"></a>')
    if card.site is not None:
        parts.append(_site_html(card.site, units_per_pixel))
        if card.note:
            parts.append(f"<details><summary>why this site</summary>{_text(card.note)}"
                         "</details>")
    elif card.note:
        parts.append(f'<p class="note">{_text(card.note)}</p>')
    if "input" in card.entry:
        parts.append(f'<div class="input">input: {_text(card.entry["input"])}</div>')
    if card.files:
        parts.append('<p class="files">' + " ".join(
            f'<a href="{_href(f)}">{_text(f[len(card.rel) + 1:])}</a>' for f in card.files)
            + "</p>")
    return "\n".join([*parts, "</article>"])


def _site_html(site: dict[str, Any], units_per_pixel: float) -> str:
    """The holdsite's pixel, 3-D point, tilt, clearance and surface as a list."""
    rows = [("pixel", f"row {site.get('row')}, col {site.get('col')}")]
    point = site.get("point_camera")
    if isinstance(point, list):
        rows.append(("point", "(" + ", ".join(_num(v, ".4f") for v in point) + ") m"))
    angle = tilt(site, units_per_pixel)
    axis = site.get("tilt_from") if _is_num(site.get("tilt")) else None
    rows.append(("tilt", "unknown (no lateral scale)" if angle is None else f"{angle:.1f}°"
                 + (f" from the {TILT_AXES.get(str(axis), str(axis))}" if axis else "")))
    rows.append(("clearance", f"{_num(site.get('clearance'))} px"))
    rows.append(("surface", f"{site.get('surface')} ({site.get('surface_type', '?')})"))
    return "<dl>" + "".join(f"<dt>{k}</dt><dd>{_text(v)}</dd>" for k, v in rows) + "</dl>"


#: How the report names the axes of holdsite.json's ``tilt_from``.
TILT_AXES = {"support": "support's normal", "optical axis": "optical axis",
             "height axis": "height axis"}


def tilt(site: dict[str, Any], units_per_pixel: float = 0.0) -> float | None:
    """Degrees between a site's normal and the axis Step 4b measured it from.

    The site's ``tilt`` when holdsite.json has it (from the support's normal
    where the workspace found one: ``tilt_from``); else, for files written
    before it, from ``approach_camera`` (with intrinsics) against the
    optical axis, or from the height map's ``normal`` with
    ``units_per_pixel`` > 0, whatever axis the search used then; ``None``
    when neither is known (or the site's values are not numbers).
    """
    if _is_num(site.get("tilt")):
        return float(site["tilt"])
    try:
        if site.get("approach_camera"):
            return math.degrees(math.acos(max(-1.0, min(1.0, site["approach_camera"][2]))))
        nx, ny, nz = site["normal"]
        if units_per_pixel > 0:
            return math.degrees(math.atan(math.hypot(nx, ny) / nz / units_per_pixel))
    except (KeyError, TypeError, ValueError, IndexError, ZeroDivisionError):
        pass
    return None


def _dict(value: Any) -> dict[str, Any]:
    """``value`` if it is a JSON object, else an empty one (a hand-edited file)."""
    return value if isinstance(value, dict) else {}


def _is_num(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _num(value: Any, spec: str = ".3g") -> str:
    return format(value, spec) if _is_num(value) else str(value)


def _text(value: Any) -> str:
    """Plain text as HTML: escaped, bytes that are no UTF-8 as ``%XX``."""
    return html.escape(io.printable(str(value)))


def _href(name: str) -> str:
    """A relative link to file ``name`` below OUT: percent-encoded (by bytes), escaped."""
    return html.escape(quote(name, errors="surrogateescape"))
