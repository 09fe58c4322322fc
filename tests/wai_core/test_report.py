"""A run's index.html: every figure it names is there, every figure there is named, the command
and the record's values shown, nothing fetched from elsewhere."""

import json
from html.parser import HTMLParser
from pathlib import Path

import numpy as np

from wai_core.io import write_png
from wai_core.outputs import OUTPUT_MARKER, atomic_dir, output_marker
from wai_core.report import REPORT_FILE, write_report


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links, self.text = [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a["src"])
        if tag in ("a", "link", "script") and ("href" in a or "src" in a):
            self.links.append(a.get("href") or a.get("src"))

    def handle_data(self, data):
        self.text.append(data)


def _parse(page: Path) -> _Links:
    p = _Links()
    p.feed(page.read_text())
    return p


def _folder(tmp_path: Path) -> Path:
    folder = tmp_path / "run"
    (folder / "restore").mkdir(parents=True)
    img = np.linspace(0, 1, 48 * 64, dtype=np.float32).reshape(48, 64)
    for rel in ("a.png", "b.png", "restore/c.png"):
        write_png(folder / rel, img)
    (folder / ".hidden.png").write_bytes(b"")
    (folder / "metrics.json").write_text(json.dumps(
        {"status": "ok", "wai_rmse_mm": 0.0213, "timings_ms": {"total": 12.5}, "x": [1, 2]}))
    (folder / "report.md").write_text("| a | b |\n| --- | --- |\n| <1> | 2 |\n")
    return folder


def test_the_page_shows_every_figure_and_the_record(tmp_path):
    folder = _folder(tmp_path)
    page = write_report(folder, "wai restore 'my dir' --quiet")
    parsed = _parse(page)
    assert sorted(parsed.images) == ["a.png", "b.png", "restore/c.png"]
    for src in parsed.images + parsed.links:
        assert not src.startswith(("http:", "https:", "/", "file:")), src
        assert (folder / src).is_file(), src
    text = "".join(parsed.text)
    assert "wai restore 'my dir' --quiet" in text
    assert "wai_rmse_mm" in text and "0.0213" in text and "timings_ms.total" in text
    assert "| <1> | 2 |" in text  # the Markdown shown as written, escaped
    assert "metrics.json" in parsed.links


def test_every_tool_output_folder_gets_its_page_and_lists_it(tmp_path):
    out = tmp_path / "out"
    with atomic_dir(out, command="restore") as tmp:
        write_png(tmp / "figure.png", np.zeros((8, 8), np.float32))
    assert (out / REPORT_FILE).is_file()
    assert _parse(out / REPORT_FILE).images == ["figure.png"]
    assert REPORT_FILE in output_marker(out)["files"]
    assert (out / OUTPUT_MARKER).is_file()


def test_a_page_added_to_an_older_output_keeps_it_the_tools_own(tmp_path):
    import json

    from wai_core.outputs import check_output_dir

    out = tmp_path / "out"
    with atomic_dir(out, command="render") as tmp:
        (tmp / "a.txt").write_text("a")
    marker = json.loads((out / OUTPUT_MARKER).read_text())
    marker["files"] = ["a.txt"]  # as written before folders had a page
    (out / OUTPUT_MARKER).write_text(json.dumps(marker))
    write_report(out)  # a later command rewrites the page
    assert check_output_dir(out, "render") == out  # still replaceable by the next render
