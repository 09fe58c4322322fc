"""The package's one build step beyond pyproject.toml: the guide (docs/*.md and the pictures
they show) copied into the package as ``wai/guide``, so that an install carries it and
``wai guide`` can show it (a checkout reads docs/ itself)."""

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py


class BuildWithGuide(build_py):
    """``build_py``, then the guide into the built ``wai`` package."""

    def run(self) -> None:
        super().run()
        docs = Path(__file__).resolve().parent / "docs"
        target = Path(self.build_lib) / "wai" / "guide"
        (target / "images").mkdir(parents=True, exist_ok=True)
        for page in docs.glob("*.md"):
            shutil.copy2(page, target / page.name)
        for image in (docs / "images").glob("*.png"):
            shutil.copy2(image, target / "images" / image.name)


setup(cmdclass={"build_py": BuildWithGuide})
