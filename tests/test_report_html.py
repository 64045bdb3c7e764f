"""``rangeseg report``'s page without a browser: its cards, escaping, links and bad input.

OUT folders are made by hand here (a manifest as rangeseg writes it, a few
files); tests/test_report_browser.py runs a real batch and opens the page.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from urllib.parse import unquote_to_bytes

import pytest
from click.testing import CliRunner

from rangeseg_cli.batch.report import tilt, write_report
from rangeseg_cli.cli.main import main

SITE = {"row": 12, "col": 34, "clearance": 7.5, "surface": 3, "surface_type": "planar",
        "normal": [0.6, 0.0, 0.8], "approach": [-0.6, 0.0, -0.8]}


def make_out(root: Path, images: dict[str, dict], holdsites: dict[str, dict | None],
             *, files: tuple[str, ...] = ("overlay.png", "labels.npy"),
             config: dict | None = None) -> Path:
    """An OUT folder: a manifest of ``images``, their ``holdsite.json`` and ``files``."""
    root.mkdir(parents=True, exist_ok=True)
    manifest = {"version": "0.1.0", "command": "run", "config": config or {},
                "summary": {"seconds": 2.5, "not_images": 1}, "images": images}
    (root / "rangeseg-run.json").write_text(json.dumps(manifest))
    for rel, entry in images.items():
        if entry["status"] != "done":
            continue
        name = os.fsdecode(unquote_to_bytes(rel)) if entry.get("name_encoding") else rel
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        for suffix in files:
            (root / f"{name}.{suffix}").write_bytes(b"x")
        if rel in holdsites:
            reason = "nothing to pick: too small" if holdsites[rel] is None else "the first"
            (root / f"{name}.holdsite.json").write_text(
                json.dumps({"holdsite": holdsites[rel], "reason": reason}))
    return root


def done(**more) -> dict:
    return {"status": "done", "stages": ["edges", "link", "grow", "holdsite"],
            "timings": {"edges": 0.5, "grow": 1.0}} | more


def cards(page: str) -> dict[str, str]:
    """Each card's status by its (escaped) title."""
    return dict((name, status) for status, name in re.findall(
        r'<article class="card \w+" data-status=(\w+)>\n<h2>(.*?) <small>', page))


def test_each_image_has_a_card_with_its_status_and_the_counts_are_returned(tmp_path):
    images = {"a": done(), "b": done(), "c": {"status": "failed", "error": "c.png: unreadable"},
              "d": {"status": "running"}, "e": done(stages=["edges"])}
    out = make_out(tmp_path / "out", images, {"a": SITE, "b": None})
    result = write_report(out)
    page = (out / "index.html").read_text()
    assert cards(page) == {"a": "site", "b": "nosite", "c": "failed", "d": "running",
                           "e": "nosite"}
    assert result == {"index": str(out / "index.html"), "images": 5, "site": 1, "nosite": 2,
                      "failed": 1, "running": 1}
    assert "nothing to pick: too small" in page and "c.png: unreadable" in page
    assert "no holdsite.json (stages run: edges)" in page
    assert "--resume" in page  # the running image says what to do
    for label in ("all 5", "holdsite 1", "no holdsite 2", "failed 1", "running 1"):
        assert f">{label}</button>" in page
    assert "took 2.5 s" in page and "1 files not images" in page
    assert "edges 1.5, grow 3.0" in page  # summed over the 3 images with timings


def test_a_site_shows_pixel_clearance_surface_and_with_intrinsics_point_and_tilt(tmp_path):
    camera = SITE | {"point_camera": [-0.114921, 0.173746, 0.608927],
                     "approach_camera": [0.0, 0.5, 0.866025]}
    out = make_out(tmp_path / "out", {"a": done(), "b": done()}, {"a": SITE, "b": camera})
    write_report(out)
    page = (out / "index.html").read_text()
    a, b = page.split("<article")[1:]
    assert "<dd>row 12, col 34</dd>" in a and "<dd>7.5 px</dd>" in a
    assert "<dd>3 (planar)</dd>" in a and "unknown (no lateral scale)" in a
    assert "point" not in a
    assert "<dd>(-0.1149, 0.1737, 0.6089) m</dd>" in b and "<dd>30.0°</dd>" in b
    # holdsite.json's own tilt, with the axis it is measured from, comes first
    level = camera | {"tilt": 2.25, "tilt_from": "support"}
    out = make_out(tmp_path / "out2", {"c": done()}, {"c": level})
    write_report(out)
    page = (out / "index.html").read_text()
    assert "<dd>2.2° from the support&#x27;s normal</dd>" in page and "30.0°" not in page


def test_tilt_is_taken_as_the_holdsite_search_takes_it():
    assert tilt({"approach_camera": [0.0, 0.6, 0.8]}) == pytest.approx(36.8699, abs=1e-4)
    assert tilt(SITE) is None  # a height map's normal needs its lateral scale
    assert tilt(SITE, units_per_pixel=1.0) == pytest.approx(36.8699, abs=1e-4)
    assert tilt(SITE, units_per_pixel=0.75) == pytest.approx(45.0)
    assert tilt({"normal": "bad"}, units_per_pixel=1.0) is None
    assert tilt(SITE | {"tilt": 3.5, "tilt_from": "support"}) == 3.5
    assert tilt({"approach_camera": [0.0, 0.6, 0.8], "tilt": "bad"}) == pytest.approx(36.8699,
                                                                                    abs=1e-4)


def test_units_per_pixel_comes_from_the_manifest_config(tmp_path):
    out = make_out(tmp_path / "out", {"a": done()}, {"a": SITE},
                   config={"input": {"units_per_pixel": 0.75}})
    write_report(out)
    assert "<dd>45.0°</dd>" in (out / "index.html").read_text()


def test_names_and_messages_are_escaped_and_links_percent_encoded(tmp_path):
    evil = 'sub/<script>alert("x")</script> & #1?'
    images = {evil: done(), "bad<b>": {"status": "failed", "error": "<img src=x onerror=1>"}}
    out = make_out(tmp_path / "out", images, {evil: SITE | {"surface_type": "<i>"}})
    write_report(out)
    page = (out / "index.html").read_text()
    assert "<script>alert" not in page and "<img src=x" not in page and "<i>" not in page
    assert "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; #1?" in page
    assert "&lt;img src=x onerror=1&gt;" in page
    encoded = "sub/%3Cscript%3Ealert%28%22x%22%29%3C/script%3E%20%26%20%231%3F"
    assert f'<img src="{encoded}.overlay.png" loading="lazy"' in page
    assert f'<a href="{encoded}.labels.npy">labels.npy</a>' in page


def test_a_name_that_is_no_utf8_links_to_its_bytes(tmp_path):
    out = make_out(tmp_path / "out", {"caf%E9": done(name_encoding="percent")},
                   {"caf%E9": SITE})
    assert (out / os.fsdecode(b"caf\xe9.overlay.png")).is_file()
    write_report(out)
    page = (out / "index.html").read_text(encoding="utf-8")
    assert cards(page) == {"caf%E9": "site"}
    assert '<img src="caf%E9.overlay.png"' in page


def test_files_belong_to_the_longest_stem_and_the_page_and_manifest_to_none(tmp_path):
    images = {"a": done(), "a.depth": done(), "index": done(), "rangeseg-run": done()}
    out = make_out(tmp_path / "out", images, {})
    (out / ".a.overlay.png.1f2e.tmp").write_bytes(b"")  # a killed run's temporary file
    write_report(out)
    page = (out / "index.html").read_text()
    links = dict(re.findall(r"<h2>(.*?) <small>.*?<p class=\"files\">(.*?)</p>", page, re.S))
    assert re.findall(r'href="([^"]+)"', links["a"]) == ["a.labels.npy", "a.overlay.png"]
    assert re.findall(r'href="([^"]+)"', links["a.depth"]) == [
        "a.depth.labels.npy", "a.depth.overlay.png"]
    assert "index.html" not in links["index"] and "rangeseg-run.json" not in links["rangeseg-run"]
    assert "1f2e.tmp" not in page


def test_the_page_needs_no_network_and_is_written_atomically(tmp_path):
    out = make_out(tmp_path / "out", {"a": done()}, {"a": SITE})
    write_report(out)
    page = (out / "index.html").read_text()
    assert not re.search(r"(src|href)=\"?(https?:)?//", page)
    assert "<link" not in page and "<script src" not in page and "@import" not in page
    assert "loading=\"lazy\"" in page
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == []


def test_report_command_prints_one_line_or_one_json_object(tmp_path):
    out = make_out(tmp_path / "out", {"a": done()}, {"a": SITE})
    said = CliRunner().invoke(main, ["report", str(out)])
    assert said.exit_code == 0, said.output
    assert said.output.strip() == f"wrote {out / 'index.html'} (1 images)"
    printed = CliRunner().invoke(main, ["report", str(out), "--json"])
    assert printed.exit_code == 0
    assert json.loads(printed.stdout)["site"] == 1


@pytest.mark.parametrize(("make", "expected"), [
    (lambda p: p / "missing", "missing: no such folder; expected the OUT folder of a batch"),
    (lambda p: p, ": no rangeseg-run.json in it; expected the OUT folder of a batch"),
    (lambda p: (p / "rangeseg-run.json").write_text("{not json") and p,
     "rangeseg-run.json: cannot read"),
    (lambda p: (p / "rangeseg-run.json").write_text('{"config": {}, "images": []}') and p,
     'rangeseg-run.json: not a manifest of rangeseg ("images" is a list'),
])
def test_bad_out_is_one_line_naming_it_and_exit_code_2(tmp_path, make, expected):
    where = make(tmp_path)
    said = CliRunner().invoke(main, ["report", str(where)])
    assert said.exit_code == 2
    lines = said.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"Error: {tmp_path}"), said.output
    assert expected in lines[0]
    printed = CliRunner().invoke(main, ["report", str(where), "--json"])
    assert printed.exit_code == 2 and expected in json.loads(printed.stdout)["error"]
    assert not (tmp_path / "index.html").exists()


def test_a_batch_on_an_object_store_gets_its_page_there(tmp_path):
    import fsspec

    from rangeseg_cli.batch.io import location

    local = make_out(tmp_path / "out", {"a": done(), "b": {"status": "failed", "error": "x"}},
                     {"a": SITE})
    store = fsspec.filesystem("memory")
    for path in local.iterdir():
        store.pipe_file(f"/report-test/out/{path.name}", path.read_bytes())
    assert write_report(location("memory://report-test/out"))["site"] == 1
    page = store.cat_file("/report-test/out/index.html").decode()
    assert cards(page) == {"a": "site", "b": "failed"}
    assert '<img src="a.overlay.png"' in page
