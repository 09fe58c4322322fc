"""The documentation's code runs: the ten-line script of docs/api.md and every example (as the
installed package runs them, ``python -m wai.examples NAME``)."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT

EXAMPLES = sorted(p for p in (ROOT / "wai" / "examples").glob("*.py") if not p.stem.startswith("_"))


def test_the_ten_line_script_runs_and_scores(capsys):
    text = (ROOT / "docs" / "api.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len([line for line in code.splitlines() if line.strip()]) <= 11  # imports + ten
    exec(compile(code, "docs/api.md", "exec"), {})
    out = capsys.readouterr().out.split()
    assert out[0] == "ok"
    rmse = float(out[2])
    assert 0 < rmse < 0.5  # the paper's configuration restores to well under its 1.78 mm


def test_every_example_is_listed_and_packaged():
    import setuptools

    from wai.examples import NAMES

    assert sorted(NAMES) == [p.stem for p in EXAMPLES] and len(NAMES) >= 4
    # pyproject's package search (what `pip install .` installs) finds the examples' package.
    assert "wai.examples" in setuptools.find_packages(ROOT, include=["wai*"])
    assert (ROOT / "examples").resolve() == (ROOT / "wai" / "examples").resolve()


@pytest.mark.slow
@pytest.mark.parametrize("script", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs_quick(script, tmp_path):
    here, scratch = tmp_path / "cwd", tmp_path / "tmp"
    here.mkdir()
    scratch.mkdir()
    # Without --out an example writes to a fresh temporary folder: here, the test's own.
    env = {**os.environ, "TMPDIR": str(scratch)}
    run = subprocess.run(
        [sys.executable, "-m", "wai.examples", script.stem, "--quick"], cwd=here,
        capture_output=True, text=True, timeout=120, env=env,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "status" in run.stdout or "RMSE" in run.stdout
    assert not any(here.iterdir())  # nothing written into the folder it ran from
    for made in scratch.iterdir():  # and what it wrote, in a folder whose path it printed
        assert made.name.startswith("wai-") and str(made) in run.stdout
