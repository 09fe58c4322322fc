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
