"""Load every kind of run's index.html in a real browser (headless Chromium) and check it.

Makes a render and its restoration (``wai demo``), checkerboards and their calibration
(``wai render --checkerboards``, ``wai calibrate``), an experiment (``wai experiment
seawater --quick``), a sequence and its restoration, and a dataset in a temporary folder,
then opens each folder's ``index.html`` with Chromium: every image the page names must load
(a probe added to a copy of the page reports, once loaded, each image whose pixels did not
arrive and every error the page raised), the browser must show them all, and its screenshot
must not be blank. Exits 1 naming what failed.

    python scripts/check_reports.py [--keep DIR]
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def _browser() -> str | None:
    return next((b for b in (shutil.which(n) for n in BROWSERS) if b), None)


def _wai(*args: str, quiet: bool = True) -> None:
    extra = ["--quiet"] if quiet else []
    subprocess.run([sys.executable, "-m", "wai", *args, *extra], check=True,
                   stdout=subprocess.DEVNULL)


def make_runs(root: Path) -> list[Path]:
    """The folders whose pages are checked."""
    _wai("demo", "--out", str(root / "demo"))
    _wai("render", "paper", "--checkerboards", "6", "--out", str(root / "boards"))
    _wai("calibrate", str(root / "boards" / "checkerboards"), "--out", str(root / "rig.json"))
    _wai("experiment", "seawater", "--quick", "--out", str(root / "experiment"), quiet=False)
    _wai("render", "paper", "--frames", "2", "--spp", "1", "--out", str(root / "sequence"))
    _wai("restore", str(root / "sequence"))
    _wai("dataset", "--frames", "2", "--size", "160x120", "--spp", "1", "--out",
         str(root / "dataset"))
    return [root / "demo", root / "demo" / "restore", root / "boards", root / "rig_figures",
            root / "experiment", root / "sequence", root / "sequence" / "restore",
            root / "dataset"]


PROBE = """<script>
window.__errors = [];
window.addEventListener("error", e => window.__errors.push(String(e.message || e.target.src)),
                        true);
window.addEventListener("load", () => {
  const broken = [...document.images].filter(i => !i.complete || i.naturalWidth === 0)
    .map(i => i.getAttribute("src"));
  document.body.setAttribute("data-images", String(document.images.length));
  document.body.setAttribute("data-broken", JSON.stringify(broken));
  document.body.setAttribute("data-errors", JSON.stringify(window.__errors));
});
</script>"""
"""Added to a copy of the page (beside it, so its links resolve): after loading, the body
says how many images it holds, which did not load, and what errors the page raised."""


def check_page(browser: str, page: Path, shot: Path) -> list[str]:
    """What is wrong with ``page`` in the browser (empty: nothing)."""
    import html
    import json

    text = page.read_text()
    expected = re.findall(r'<img[^>]+src="([^"]+)"', text)
    probe = page.with_name(".index_check.html")
    probe.write_text(text.replace("</head>", PROBE + "</head>", 1))
    common = [browser, "--headless=new", "--no-sandbox", "--disable-gpu",
              "--allow-file-access-from-files", "--virtual-time-budget=10000"]
    try:
        run = subprocess.run([*common, "--dump-dom", probe.as_uri()], capture_output=True,
                             text=True, timeout=120)
    finally:
        probe.unlink()
    problems = []
    body = re.search(r"<body([^>]*)>", run.stdout)
    attrs = dict(re.findall(r'(data-[a-z]+)="([^"]*)"', body.group(1))) if body else {}
    if "data-images" not in attrs:
        return [f"{page}: the browser did not finish loading it"]
    if int(attrs["data-images"]) != len(expected):
        problems.append(f"{page}: the browser shows {attrs['data-images']} images, the page "
                        f"names {len(expected)}")
    broken = json.loads(html.unescape(attrs.get("data-broken", "[]")))
    errors = json.loads(html.unescape(attrs.get("data-errors", "[]")))
    problems += [f"{page}: image {src} did not load" for src in broken]
    problems += [f"{page}: error {e}" for e in errors if not any(b in e for b in broken)]
    subprocess.run([*common, f"--screenshot={shot}", "--window-size=1200,1600",
                    page.as_uri()], capture_output=True, timeout=120)
    if not shot.is_file() or shot.stat().st_size < 10_000:
        problems.append(f"{page}: no screenshot, or a blank one")
    elif expected:
        import numpy as np
        from PIL import Image

        pixels = np.asarray(Image.open(shot).convert("L"), float)
        if pixels.std() < 5.0:
            problems.append(f"{page}: the screenshot is uniform")
    return problems


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, default=None, help="make the runs here and keep "
                        "them (default: a temporary folder, removed)")
    args = parser.parse_args()
    browser = _browser()
    if browser is None:
        print("check_reports: no Chromium (install the chromium package)", file=sys.stderr)
        return 1
    root = args.keep or Path(tempfile.mkdtemp(prefix="wai-reports-"))
    try:
        folders = make_runs(root)
        problems = []
        for k, folder in enumerate(folders):
            page = folder / "index.html"
            if not page.is_file():
                problems.append(f"{folder}: no index.html")
                continue
            problems += check_page(browser, page, root / f"screenshot_{k}.png")
    finally:
        if args.keep is None:
            shutil.rmtree(root, ignore_errors=True)
    for line in problems:
        print(f"check_reports: {line}", file=sys.stderr)
    print(f"check_reports: {len(folders)} pages loaded in {Path(browser).name}; "
          f"{len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
