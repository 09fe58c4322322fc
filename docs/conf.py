"""Sphinx configuration: the user guide (docs/*.md), the API reference of the four packages
(generated from each package's ``__all__``), and the gallery (docs/gallery/*.py, run at build
time). Build with ``./scripts/docs.sh``."""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(ROOT))
os.environ.setdefault("MPLBACKEND", "Agg")

project = "Wavy-water testbed"
author = "The wavy-water testbed developers"
copyright = "2026, the wavy-water testbed developers"  # noqa: A001
release = importlib.import_module("wai").__version__ if hasattr(
    importlib.import_module("wai"), "__version__") else "0.1.0"

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.napoleon",
    "sphinx_gallery.gen_gallery",
]
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build", "auto_examples/*.ipynb", "auto_examples/*.py",
                    "auto_examples/*.zip", "auto_examples/*.json", "auto_examples/*.md5",
                    "gallery/README.rst"]
myst_heading_anchors = 3
html_theme = "furo"
html_title = "Wavy-water testbed"

napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
autosummary_generate = True
autodoc_default_options = {"members": False, "show-inheritance": False}
autodoc_typehints = "none"
autodoc_mock_imports: list[str] = []

sphinx_gallery_conf = {
    "examples_dirs": "gallery",
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",
    "download_all_examples": False,
    "remove_config_comments": True,
    "within_subsection_order": "FileNameSortKey",
    "matplotlib_animations": False,
}

PACKAGES = {
    "wai_core": "Shared geometry, configuration, rig and I/O.",
    "mitsuba_wai": "Waves, meshes, Mitsuba 3 scenes and renders.",
    "restoration": "Renders or captures and a calibration to a surface and a restored view.",
    "wai": "The command line and the experiments.",
    "wai.sweep": "Sweeps of points on a Dask cluster, their tables.",
    "wai.dataset": "Datasets of frames for learned methods.",
}


def _home(package: str, name: str, obj: object) -> str:
    """Where ``name`` is documented: a class's or function's own module; for a constant, the
    module of the package that assigns it (its docstring sits there), else the package."""
    import inspect
    import pkgutil
    import re

    if inspect.isclass(obj) or inspect.isroutine(obj):
        return f"{obj.__module__}.{obj.__qualname__}"
    if inspect.ismodule(obj):
        return obj.__name__
    pkg = importlib.import_module(package)
    assigned = re.compile(rf"^{re.escape(name)}\s*(:[^=]*)?=", re.M)
    for info in pkgutil.walk_packages(pkg.__path__, package + "."):
        spec = importlib.util.find_spec(info.name)
        if spec is None or not spec.origin or not spec.origin.endswith(".py"):
            continue
        if assigned.search(Path(spec.origin).read_text()):
            return f"{info.name}.{name}"
    return f"{package}.{name}"


def _write_reference() -> None:
    """One page per package listing every name of its ``__all__`` (its API), each with a
    generated page: the reference is complete by construction."""
    out = HERE / "reference"
    out.mkdir(exist_ok=True)
    pages = []
    for name, what in PACKAGES.items():
        module = importlib.import_module(name)
        names = sorted(getattr(module, "__all__", []))
        # The table first: autosummary's generator reads names against the module that an
        # automodule above would set (each name here is its home's full name).
        lines = [name, "=" * len(name), "", what, "", ".. autosummary::",
                 "   :toctree: generated", ""]
        lines += [f"   {_home(name, n, getattr(module, n))}" for n in names]
        lines += ["", "About the package", "-" * 17, "", f".. automodule:: {name}"]
        text = "\n".join(lines) + "\n"
        page = out / f"{name}.rst"
        if not page.exists() or page.read_text() != text:
            page.write_text(text)
        pages.append(name)
    index = ["API reference", "=============", "",
             "Every public name of the four packages (their ``__all__``).", "",
             ".. toctree::", "   :maxdepth: 1", ""] + [f"   {p}" for p in pages]
    text = "\n".join(index) + "\n"
    if not (out / "index.rst").exists() or (out / "index.rst").read_text() != text:
        (out / "index.rst").write_text(text)


_write_reference()
