"""The documentation's code runs: the ten-line script of docs/api.md and every example."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from tests.conftest import ROOT

EXAMPLES = sorted((ROOT / "examples").glob("*.py"))


def test_the_ten_line_script_runs_and_scores(capsys):
    text = (ROOT / "docs" / "api.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len([line for line in code.splitlines() if line.strip()]) <= 11  # imports + ten
    exec(compile(code, "docs/api.md", "exec"), {})
    out = capsys.readouterr().out.split()
    assert out[0] == "ok"
    rmse = float(out[2])
    assert 0 < rmse < 0.5  # the paper's configuration restores to well under its 1.78 mm


@pytest.mark.parametrize("script", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs_quick(script, tmp_path):
    assert len(EXAMPLES) >= 4
    run = subprocess.run(
        [sys.executable, str(script), "--quick"], cwd=tmp_path, capture_output=True, text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "status" in run.stdout or "RMSE" in run.stdout
