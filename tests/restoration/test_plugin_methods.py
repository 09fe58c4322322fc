"""Methods of one's own join through the protocol: by module:Class, by a file's path, or by an
entry point; a view-only method is scored on its view; bad names give one line."""

import pytest

from restoration import Calibration, StructuredLight, get_method, method_class
from tests.conftest import ROOT
from wai_core.errors import WaiInputError

EXAMPLE = ROOT / "examples" / "plugin_method.py"


def test_a_method_by_module_and_by_file():
    assert method_class("restoration:StructuredLight") is StructuredLight
    cls = method_class(f"{EXAMPLE}:AsSeen")
    assert cls.name == "as-seen" and cls.calibration_type is Calibration
    assert get_method(f"{EXAMPLE}:AsSeen").options is not None


@pytest.mark.parametrize(("spec", "says"), [
    ("no-such-method", "unknown method 'no-such-method'"),
    ("no_such_module_xyz:Thing", "cannot import it"),
    ("restoration:no_such_name", "cannot import it"),
    ("os:path", "is not a class"),
    ("restoration:Calibration", "has no name"),
    ("missing_file.py:AsSeen", "cannot import it"),
])
def test_bad_methods_say_why(spec, says):
    with pytest.raises(WaiInputError, match=says):
        method_class(spec)


def test_an_entry_point_is_found(monkeypatch):
    import restoration.methods as methods

    class EntryPoint:
        name = "as-seen"

        def load(self):
            return method_class(f"{EXAMPLE}:AsSeen")

    monkeypatch.setattr(methods, "_plugins", lambda: {"as-seen": EntryPoint()})
    assert method_class("as-seen").name == "as-seen"
    assert "as-seen" in methods.method_names()


BROKEN = ROOT / "tests" / "restoration" / "broken_methods.py"


@pytest.fixture(scope="module")
def frame(tmp_path_factory, small_cfg):
    from mitsuba_wai.render import render_folder

    out = tmp_path_factory.mktemp("plugin") / "frame"
    render_folder(small_cfg.replace("render", spp_pattern=1, spp_view=1), out, progress=False)
    return out


@pytest.mark.parametrize(("cls", "says"), [
    ("Raises", "method 'raises' raised RuntimeError: a bug of mine"),
    ("ReturnsNone", "method 'returns-none' returned NoneType, not a RestoreResult"),
    ("WrongShape", "method 'wrong-shape' returned a view image of shape (5, 5, 3), not the "
                   "frame's (150, 200[, 3])"),
    ("Exits", "method 'exits' raised SystemExit: 3"),
])
def test_a_method_that_fails_on_a_frame_is_one_line_naming_it(frame, capsys, cls, says):
    from wai.cli import main

    assert main(["restore", str(frame), "--method", f"{BROKEN}:{cls}", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"wai: error: {says}"), err
    assert not (frame / "restore").exists()
