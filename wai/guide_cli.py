"""``wai guide [PAGE]``: the user guide's pages, from the install or the checkout."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from wai_core.errors import WaiInputError

__all__ = ["add_guide", "guide_folder", "guide_pages"]


def guide_folder() -> Path:
    """Where the guide's pages are: ``wai/guide`` in an install (built there by setup.py),
    else the checkout's ``docs/``."""
    here = Path(__file__).resolve().parent
    for folder in (here / "guide", here.parent / "docs"):
        if (folder / "rig.md").is_file():
            return folder
    raise WaiInputError("the guide is not installed with this copy of the package (see the "
                        "project's docs/ folder)")


def guide_pages() -> dict[str, str]:
    """Each page's name (its file's stem) and its title (the first heading)."""
    pages = {}
    for page in sorted(guide_folder().glob("*.md")):
        if page.stem == "index":
            continue
        heading = re.search(r"^# (.+)$", page.read_text(), re.M)
        pages[page.stem] = heading.group(1) if heading else page.stem
    return pages


def run_guide(args: argparse.Namespace) -> None:
    """List the pages, or print one (its path with ``--path``)."""
    pages = guide_pages()
    if args.page is None:
        width = max(map(len, pages))
        for name, title in pages.items():
            print(f"{name:<{width}}  {title}")
        print(f"(wai guide PAGE prints one; the pages are in {guide_folder()})")
        return
    name = args.page.removesuffix(".md")
    if name not in pages:
        raise WaiInputError(f"wai guide: no page {args.page!r}: one of {', '.join(pages)}")
    page = guide_folder() / f"{name}.md"
    print(page if args.path else page.read_text(), end="\n" if args.path else "")


def add_guide(sub: argparse._SubParsersAction, formatter: type) -> None:
    """The ``guide`` subcommand."""
    p = sub.add_parser(
        "guide", help="the user guide: list its pages, or print one", formatter_class=formatter,
        description="The user guide, as installed with the package (the same pages as the "
        "project's docs/ and its documentation site). Without PAGE, lists the pages.",
    )
    p.add_argument("page", nargs="?", default=None, help="a page's name, e.g. rig or outputs")
    p.add_argument("--path", action="store_true", help="print the page's file, not its text")
    p.set_defaults(func=_cmd_guide)


def _cmd_guide(args: argparse.Namespace) -> int:
    run_guide(args)
    return 0
