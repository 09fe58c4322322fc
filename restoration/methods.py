"""The surface-sensing methods behind one small protocol, and a registry by name.

A method is a callable object configured once (its options: :class:`StructuredLightOptions`,
:class:`AltermanOptions`) and applied to frames: ``method(images, cal) -> RestoreResult``. Each
names its options type and the calibration type it needs, which also knows how to read a
frame's images from a folder.

Methods of one's own join by the same protocol (:class:`Method`), named in three ways
(:func:`method_class`): a built-in name (:data:`METHODS`), ``"module:Class"`` (imported), or
the name of an entry point in the group :data:`ENTRY_POINT_GROUP` of an installed package
(``[project.entry-points."wai.methods"] my-method = "my_package.module:MyMethod"``).
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from dataclasses import replace
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from numpy.typing import NDArray

from restoration.alterman import AltermanCalibration, restore_alterman
from restoration.calibration import Calibration, LevelTrack, RigCalibration, read_scene_record
from restoration.inverse_rendering import restore_inverse_rendering
from restoration.options import (
    AltermanOptions,
    InverseRenderingOptions,
    SchlierenOptions,
    SurfaceOptions,
    checked_options,
)
from restoration.protocol import BUILT_IN, Method
from restoration.result import RestoreResult
from restoration.schlieren import SchlierenCalibration, restore_schlieren
from restoration.schlieren_level import SchlierenLevelled
from restoration.structured_light import StructuredLight
from restoration.view_level import StructuredLightView
from wai_core.errors import WaiInputError

__all__ = [
    "ENTRY_POINT_GROUP", "METHODS", "Alterman", "InverseRendering", "InverseRenderingView",
    "Schlieren", "as_method",
    "get_method", "load_calibration", "method_class", "method_names",
]


class Alterman:
    """Alterman et al.'s sun-and-pinhole sensor (STELLA MARIS), configured once.

    Its normals do not depend on the height, so the level is always the gauge's: its options
    (:class:`AltermanOptions`) have no anchor.

    Examples
    --------
    >>> from restoration import Alterman, AltermanOptions
    >>> Alterman(AltermanOptions(n_refine=0)).options.n_refine
    0
    """

    name = "alterman"
    calibration_type = AltermanCalibration
    options_type = AltermanOptions

    def __init__(self, options: AltermanOptions | None = None) -> None:
        self.options = checked_options(self.name, AltermanOptions, options)

    def __repr__(self) -> str:
        return f"Alterman({self.options!r})"

    def __call__(
        self,
        images: dict[str, NDArray],
        cal: AltermanCalibration,
        track: LevelTrack | None = None,
    ) -> RestoreResult:
        """Restore one frame (``sunspots``, ``sunspots_flat``, ``view``); ``track`` is
        accepted for the protocol's sake (the level is always the gauge's)."""
        return restore_alterman(images, cal, self.options)


class Schlieren:
    """Free-surface synthetic Schlieren from camera v's view and its flat-water view
    (:mod:`restoration.schlieren`), configured once. Its slopes do not pin the level: it is
    always the gauge's.

    Examples
    --------
    >>> from restoration import Schlieren, SchlierenOptions
    >>> Schlieren(SchlierenOptions(sample_step_px=4)).options.sample_step_px
    4
    """

    name = "schlieren"
    calibration_type = SchlierenCalibration
    options_type = SchlierenOptions

    def __init__(self, options: SchlierenOptions | None = None) -> None:
        self.options = checked_options(self.name, SchlierenOptions, options)

    def __repr__(self) -> str:
        return f"Schlieren({self.options!r})"

    def __call__(
        self,
        images: dict[str, NDArray],
        cal: SchlierenCalibration,
        track: LevelTrack | None = None,
    ) -> RestoreResult:
        """Restore one frame (``view``, ``view_flat``); ``track`` is accepted for the
        protocol's sake (the level is always the gauge's)."""
        return restore_schlieren(images, cal, self.options)


class InverseRendering:
    """The structured light's surface refitted to the whole pattern image through a
    differentiable model of it (:mod:`restoration.inverse_rendering`), configured once.

    Examples
    --------
    >>> from restoration import InverseRendering, InverseRenderingOptions
    >>> InverseRendering(InverseRenderingOptions(iterations=10)).options.iterations
    10
    """

    name = "inverse-rendering"
    calibration_type = Calibration
    options_type = InverseRenderingOptions
    fixed_start: str | None = None
    """The ``start`` the options always take (a method named for its start); None: theirs."""

    def __init__(self, options: InverseRenderingOptions | None = None) -> None:
        options = checked_options(self.name, InverseRenderingOptions, options)
        self.options = options if self.fixed_start is None else replace(
            options, start=self.fixed_start)
        if self.options.start != StructuredLight.name:  # its start reads the view's
            self.calibration_type = StructuredLightView.calibration_type

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.options!r})"

    def __call__(
        self,
        images: dict[str, NDArray],
        cal: Calibration,
        track: LevelTrack | None = None,
    ) -> RestoreResult:
        """Restore one frame (``pattern``, ``pattern_flat``, ``view``); ``track``: as the
        structured light's, for its start."""
        return restore_inverse_rendering(images, cal, self.options, track)


class InverseRenderingView(InverseRendering):
    """Inverse rendering started at the view's level: the fit starts from
    :class:`~restoration.StructuredLightView`'s surface (the structured light whose level
    camera v's view pins) and keeps its level; its options' ``start`` is always that.

    Examples
    --------
    >>> from restoration import InverseRenderingOptions, InverseRenderingView
    >>> InverseRenderingView(InverseRenderingOptions(iterations=10)).options.start
    'structured-light-view'
    """

    name = "inverse-rendering-view"
    calibration_type = StructuredLightView.calibration_type
    fixed_start = StructuredLightView.name


class InverseRenderingSchlieren(InverseRendering):
    """Inverse rendering that falls back on Schlieren's surface: the fit starts from
    :class:`~restoration.StructuredLightView`'s surface where that is ``ok``, else from
    :class:`~restoration.SchlierenLevelled`'s, its dots labelled by the spots that surface
    predicts (:func:`~restoration.inverse_rendering.refit_schlieren`); its options' ``start``
    is always ``"schlieren-sl"``.

    Examples
    --------
    >>> from restoration import InverseRenderingOptions, InverseRenderingSchlieren
    >>> InverseRenderingSchlieren(InverseRenderingOptions(iterations=10)).options.start
    'schlieren-sl'
    """

    name = "inverse-rendering-schlieren"
    calibration_type = SchlierenLevelled.calibration_type
    fixed_start = SchlierenLevelled.name


METHODS: dict[str, type] = {StructuredLight.name: StructuredLight, Alterman.name: Alterman,
                            Schlieren.name: Schlieren, InverseRendering.name: InverseRendering,
                            StructuredLightView.name: StructuredLightView,
                            SchlierenLevelled.name: SchlierenLevelled,
                            InverseRenderingView.name: InverseRenderingView,
                            InverseRenderingSchlieren.name: InverseRenderingSchlieren}
"""Methods by name: ``structured-light`` (the paper's), ``alterman`` (the sun sensor),
``schlieren`` (synthetic Schlieren on camera v's view), ``inverse-rendering`` (the
structured light's surface refitted to the pattern image), ``structured-light-view`` (the
structured light, its level pinned by camera v's view: :mod:`restoration.view_level`),
``schlieren-sl`` (synthetic Schlieren at that structured light's level, or where it gives
none at the level camera s's spots show: :mod:`restoration.schlieren_level`) and
``inverse-rendering-view`` (the refit started from ``structured-light-view``'s surface) and
``inverse-rendering-schlieren`` (from ``schlieren-sl``'s where that start is not ``ok``)."""
BUILT_IN.update(METHODS.values())


ENTRY_POINT_GROUP = "wai.methods"
"""The entry-point group in which installed packages register their methods."""


def _plugins() -> dict[str, Any]:
    return {ep.name: ep for ep in entry_points(group=ENTRY_POINT_GROUP)}


def method_names() -> list[str]:
    """The built-in methods' names, then those registered by installed packages."""
    return [*METHODS, *(n for n in sorted(_plugins()) if n not in METHODS)]


def _checked_class(cls: Any, spec: str) -> type:
    """``cls`` when it offers the :class:`Method` protocol's class attributes."""
    problems = []
    if not isinstance(cls, type) or not callable(cls):
        problems.append("is not a class")
    else:
        if not isinstance(getattr(cls, "name", None), str):
            problems.append("has no name (str)")
        cal = getattr(cls, "calibration_type", None)
        if not (isinstance(cal, type) and issubclass(cal, RigCalibration)):
            problems.append("has no calibration_type (a RigCalibration subclass)")
        opts = getattr(cls, "options_type", None)
        if not (isinstance(opts, type) and issubclass(opts, SurfaceOptions)):
            problems.append("has no options_type (a SurfaceOptions subclass)")
    if problems:
        raise WaiInputError(f"method {spec!r} {', '.join(problems)} (see restoration.Method)")
    return cls


def _import(module: str) -> Any:
    """A module by dotted name (the working directory searched too, as ``python -m`` does), or
    a Python file by its path (``my_method.py``)."""
    if module.endswith(".py"):
        path = Path(module)
        if not path.is_file():
            raise ImportError(f"no file {module}")
        spec = importlib.util.spec_from_file_location(path.stem, path)
        found = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(found)
        return found
    if "" not in sys.path and str(Path.cwd()) not in sys.path:
        sys.path.append(str(Path.cwd()))
    return importlib.import_module(module)


def method_class(spec: str) -> type:
    """The method class that ``spec`` names: a built-in name (:data:`METHODS`),
    ``"module:Class"`` (a dotted module, found from the working directory too, or a Python
    file, ``"path/to/mine.py:Class"``), or an entry point of :data:`ENTRY_POINT_GROUP`.

    Raises
    ------
    WaiInputError
        When nothing of that name exists, its module does not import, or the class does not
        offer the protocol (:class:`Method`).

    Examples
    --------
    >>> from restoration.methods import method_class
    >>> method_class("alterman").__name__, method_class("restoration:StructuredLight").name
    ('Alterman', 'structured-light')
    """
    if spec in METHODS:
        return METHODS[spec]
    if ":" in spec:
        module, _, attr = spec.rpartition(":")
        try:
            found = getattr(_import(module), attr)
        except (ImportError, AttributeError, OSError) as exc:
            raise WaiInputError(f"method {spec!r}: cannot import it ({exc})") from None
        except (Exception, SystemExit) as exc:  # the module's own code failed while importing
            raise WaiInputError(f"method {spec!r}: importing it raised "
                                f"{type(exc).__name__}: {exc}") from None
        return _checked_class(found, spec)
    plugin = _plugins().get(spec)
    if plugin is None:
        raise WaiInputError(f"unknown method {spec!r} (known: {', '.join(method_names())}; "
                            "or module:Class)")
    try:
        found = plugin.load()
    except (Exception, SystemExit) as exc:
        raise WaiInputError(f"method {spec!r}: its entry point does not load "
                            f"({type(exc).__name__}: {exc})") from None
    return _checked_class(found, spec)


def get_method(name: str, options: SurfaceOptions | None = None, **choices: Any) -> Method:
    """The method called ``name`` (:func:`method_class`), configured with ``options``
    (default: its own defaults), or with the ``choices`` that are not None (``n_refine=0``,
    ``anchor=None``: a CLI's flags; the others at the method's defaults).

    Raises
    ------
    WaiInputError
        For an unknown name, another method's options, or a choice the method does not have.

    Examples
    --------
    >>> from restoration import get_method
    >>> get_method("alterman", n_refine=0, anchor=None).options.n_refine
    0
    """
    cls = method_class(name)
    if options is None and choices:
        options = cls.options_type.from_choices(**choices)
    return cls(options)


def as_method(method: str | Method, options: SurfaceOptions | None = None) -> Method:
    """``method`` itself when it is a configured method object, else :func:`get_method`
    ``(method, options)``."""
    return get_method(method, options) if isinstance(method, str) else method


def load_calibration(folder: str | Path) -> RigCalibration:
    """The calibration in ``folder/scene.json``: a sun-sensor one when the record has an
    ``alterman`` table, else the structured light's."""
    record = read_scene_record(folder)
    cls = AltermanCalibration if "alterman" in record else StructuredLight.calibration_type
    return cls.from_record(record)
