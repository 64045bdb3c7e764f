"""``rangeseg report`` in a real browser: Debian's chromium, driven by Playwright.

A small real batch (a box, a flat table with nothing to pick, a damaged PNG,
odd and non-UTF-8 names, a subfolder) is run and reported; the page is opened
from its ``file://`` URL. Every card and every overlay must load, the filter
must show exactly the cards of its status, and a screenshot is saved.
``.ci/run`` installs chromium; playwright is in the ``test`` extra.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path
from urllib.parse import unquote_to_bytes, urlsplit

import imageio.v3 as iio
import numpy as np
import pytest
from playwright.sync_api import Page, sync_playwright

RANGESEG = Path(sys.executable).with_name("rangeseg")
#: Debian's chromium (.ci/run installs it), or the one RANGESEG_CHROMIUM names.
CHROMIUM = os.environ.get("RANGESEG_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
#: Chromium as a sandboxed CI job can run it: no GPU, no network of its own.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
#: The batch's images and the status of each one's card.
EXPECTED = {"box": "site", "sub/a b&<c>#1": "site", "caf%E9": "site", "flat": "nosite",
            "broken": "failed"}


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """OUT/index.html of a real batch with one failure and one image without a site."""
    root = tmp_path_factory.mktemp("report")
    (root / "in" / "sub").mkdir(parents=True)
    box = np.full((64, 64), 20, np.uint8)
    box[20:44, 20:44] = 120
    for name in ("box.png", "sub/a b&<c>#1.png", os.fsdecode(b"caf\xe9.png")):
        iio.imwrite(root / "in" / name, box)
    iio.imwrite(root / "in" / "flat.png", np.full((64, 64), 50, np.uint8))
    (root / "in" / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\nnot really a PNG")
    run = subprocess.run([RANGESEG, "run", root / "in", "-o", root / "out", "-j", "1", "-q"],
                         capture_output=True, text=True, timeout=600)
    assert run.returncode == 1, run.stderr  # broken.png failed, the others are done
    done = subprocess.run([RANGESEG, "report", root / "out"], capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 0, done.stderr
    return root / "out" / "index.html"


@pytest.fixture(scope="module")
def page(report: Path):
    """The report open in headless chromium, from its file:// URL."""
    if not Path(CHROMIUM).is_file():
        pytest.fail(f"{CHROMIUM} is missing: apt-get install -y chromium (.ci/run does)")
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        tab = browser.new_page(viewport={"width": 1000, "height": 700})
        tab.goto(report.as_uri())
        yield tab
        browser.close()


def _visible_cards(page: Page) -> dict[str, str]:
    cards = page.locator("article.card:visible")
    return {cards.nth(i).locator("h2").evaluate("h => h.firstChild.textContent.trim()"):
            cards.nth(i).get_attribute("data-status") for i in range(cards.count())}


def test_every_card_is_there_with_its_status(page):
    page.locator("nav button[data-show=all]").click()
    assert _visible_cards(page) == EXPECTED
    assert "not a readable image" in page.locator("article.failed .note").inner_text()
    assert page.locator("article.nosite .note").inner_text().startswith("nothing to pick")
    assert page.locator("article.site dl").count() == 3


def test_every_overlay_loads_from_its_percent_encoded_link(page):
    images = page.locator("article img")
    assert images.count() == 4  # the failed image has none
    for i in range(images.count()):
        image = images.nth(i)
        assert image.get_attribute("loading") == "lazy"
        image.scroll_into_view_if_needed()
        page.wait_for_function("img => img.complete", arg=image.element_handle())
        assert image.evaluate("img => img.naturalWidth") > 0, image.get_attribute("src")


def test_every_file_link_points_at_a_file(page, report):
    links = page.locator("p.files a")
    assert links.count() == 4 * 13
    for i in range(links.count()):
        url = links.nth(i).evaluate("a => a.href")
        path = os.fsdecode(unquote_to_bytes(urlsplit(url).path))
        assert Path(path).is_file(), url


@pytest.mark.parametrize("show", ["site", "nosite", "failed", "all"])
def test_the_filter_shows_the_cards_of_its_status(page, show, tmp_path):
    page.locator(f"nav button[data-show={show}]").click()
    expected = {k: v for k, v in EXPECTED.items() if show in ("all", v)}
    assert _visible_cards(page) == expected
    assert page.locator(f"nav button[data-show={show}]").get_attribute("aria-pressed") == "true"
    page.screenshot(path=tmp_path / f"report-{show}.png", full_page=True)
    assert (tmp_path / f"report-{show}.png").stat().st_size > 1000
