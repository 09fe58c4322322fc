"""Check a built documentation site: every public name of the four packages in the API
reference, at least six gallery examples each with its pictures, and every image the pages
name present. Exits 1 naming what is missing.

    python scripts/check_docs.py docs/_build/html
"""

import importlib
import re
import sys
from pathlib import Path

PACKAGES = ("wai_core", "mitsuba_wai", "restoration", "wai", "wai.sweep", "wai.dataset")


def main(site: Path) -> int:
    problems = []
    for package in PACKAGES:
        page = site / "reference" / f"{package}.html"
        text = page.read_text() if page.is_file() else ""
        names = importlib.import_module(package).__all__
        missing = [n for n in names if not re.search(rf"[.>]{re.escape(n)}<", text)]
        if missing:
            problems.append(f"{page}: no entry for {', '.join(missing[:10])}")
    examples = sorted((site / "auto_examples").glob("plot_*.html"))
    pictured = [p for p in examples if "sphx_glr_" in p.read_text()]
    if len(pictured) < 6:
        problems.append(f"gallery: {len(pictured)} examples with pictures, not >= 6")
    for page in site.rglob("*.html"):
        for src in re.findall(r'<img[^>]+src="([^"]+)"', page.read_text()):
            if src.startswith(("http:", "https:", "data:")):
                continue
            if not (page.parent / src.split("#")[0]).is_file():
                problems.append(f"{page}: image {src} not found")
    for line in problems:
        print(f"check_docs: {line}", file=sys.stderr)
    print(f"check_docs: {len(examples)} gallery examples, reference of {len(PACKAGES)} "
          f"packages checked; {len(problems)} problems")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1] if len(sys.argv) > 1 else "docs/_build/html")))
