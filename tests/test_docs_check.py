"""scripts/check_docs.py, the built site's check, tells a complete site from one missing a
public name, a gallery picture or an image file."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _checker():
    spec = importlib.util.spec_from_file_location("check_docs", ROOT / "scripts/check_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _site(tmp_path: Path, drop: str | None = None) -> Path:
    site = tmp_path / "html"
    (site / "reference").mkdir(parents=True)
    checker = _checker()
    for package in checker.PACKAGES:
        names = importlib.import_module(package).__all__
        rows = "".join(f"<span>{package}.x.{n}</span>" for n in names if n != drop)
        (site / "reference" / f"{package}.html").write_text(rows)
    (site / "auto_examples" / "images").mkdir(parents=True)
    for k in range(6):
        png = f"images/sphx_glr_plot_{k}_001.png"
        (site / "auto_examples" / png).write_bytes(b"png")
        (site / "auto_examples" / f"plot_{k}.html").write_text(f'<img src="{png}">')
    return site


def test_a_complete_site_passes_and_a_missing_name_or_image_fails(tmp_path, capsys):
    checker = _checker()
    assert checker.main(_site(tmp_path / "a")) == 0
    assert checker.main(_site(tmp_path / "b", drop="restore_folder")) == 1
    assert "restore_folder" in capsys.readouterr().err
    site = _site(tmp_path / "c")
    (site / "auto_examples" / "images" / "sphx_glr_plot_0_001.png").unlink()
    assert checker.main(site) == 1
