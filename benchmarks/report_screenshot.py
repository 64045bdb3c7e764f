"""The docs' picture of ``rangeseg report``: docs/figures/report.png.

One OUT made as a user would, by three runs: the SR300 tote frame of
``sample_data/arc`` with its empty tote as background (a site), the empty
tote alone ("nothing to pick"), and ``sample_data/synthetic`` with a
truncated copy of one frame (a failure). ``rangeseg report OUT`` writes the
page; headless chromium (Debian's ``/usr/bin/chromium``, driven by
Playwright as in ``tests/test_report_browser.py``) opens it from its
``file://`` URL and takes the first two rows of cards, quantised to 256
colours to stay small. Usage::

    python benchmarks/report_screenshot.py [OUT.png]   # default docs/figures/report.png
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from PIL import Image
from playwright.sync_api import sync_playwright

ROOT = Path(__file__).resolve().parent.parent
ARC = ROOT / "sample_data" / "arc"
RANGESEG = Path(sys.executable).with_name("rangeseg")
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                 "--no-first-run", "--disable-background-networking",
                 "--disable-component-update", "--disable-sync"]
SR300 = ["--preset", "tenth-mm-depth", "--intrinsics", ARC / "suction-camera-intrinsics.txt"]


def batch(work: Path) -> Path:
    """``work/out``, by the three runs in ``work`` (relative names, as a user types them)."""
    arc, synthetic, out = work / "in" / "arc", work / "in" / "synthetic", work / "out"
    arc.mkdir(parents=True)
    shutil.copyfile(ARC / "suction-scene.depth.png", arc / "suction-scene.depth.png")
    shutil.copyfile(ARC / "empty" / "suction-background.depth.png",
                    arc / "suction-empty-tote.depth.png")
    shutil.copytree(ROOT / "sample_data" / "synthetic", synthetic,
                    ignore=shutil.ignore_patterns("*.gt.*", "*.md"))
    frame = (synthetic / "part1-n0.png").read_bytes()
    (synthetic / "broken-frame.png").write_bytes(frame[: len(frame) // 2])
    background = ["--background", ARC / "empty" / "suction-background.depth.png"]
    for include, options in (("arc/suction-scene.depth.png", [*SR300, *background]),
                             ("arc/suction-empty-tote.depth.png", SR300),
                             ("synthetic/*.png", [])):  # OUT/arc/..., OUT/synthetic/...
        done = subprocess.run([RANGESEG, "run", "in", "--include", include, *options,
                               "-o", "out", "-q"], cwd=work, check=False)
        assert done.returncode in (0, 1), done  # 1: the broken frame failed
    subprocess.run([RANGESEG, "report", "out", "-q"], cwd=work, check=True)
    return out


def screenshot(page: Path, target: Path) -> None:
    """The top of ``page`` in chromium, two rows of cards, as a 256-colour PNG."""
    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        tab = browser.new_page(viewport={"width": 1100, "height": 1180})
        tab.goto(page.as_uri())
        tab.wait_for_function("[...document.images].slice(0, 5).every(i => i.complete)")
        tab.screenshot(path=target)
        browser.close()
    Image.open(target).convert("RGB").quantize(256).save(target, optimize=True)


def main(argv: list[str]) -> int:
    target = Path(argv[0]) if argv else ROOT / "docs" / "figures" / "report.png"
    with tempfile.TemporaryDirectory() as tmp:
        screenshot(batch(Path(tmp)) / "index.html", target)
    print(f"wrote {target} ({target.stat().st_size / 1024:.0f} KiB)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
