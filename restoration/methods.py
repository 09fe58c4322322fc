"""The surface-sensing methods behind one small protocol, and a registry by name.

A method is a callable object configured once (its options: :class:`StructuredLightOptions`,
:class:`AltermanOptions`) and applied to frames: ``method(images, cal) -> RestoreResult``. Each
names its options type and the calibration type it needs, which also knows how to read a
frame's images from a folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Protocol

from numpy.typing import NDArray

from restoration.alterman import AltermanCalibration, restore_alterman
from restoration.calibration import LevelTrack, RigCalibration, read_scene_record
from restoration.options import AltermanOptions, SurfaceOptions, checked_options
from restoration.result import RestoreResult
from restoration.structured_light import StructuredLight
from wai_core.errors import WaiInputError

__all__ = ["METHODS", "Alterman", "Method", "as_method", "get_method", "load_calibration"]


class Method(Protocol):
    """What every restoration method offers."""

    name: ClassVar[str]
    calibration_type: ClassVar[type[RigCalibration]]
    options_type: ClassVar[type[SurfaceOptions]]
    options: SurfaceOptions

    def __call__(
        self, images: dict[str, NDArray], cal: Any, track: LevelTrack | None = None
    ) -> RestoreResult: ...


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


METHODS: dict[str, type] = {StructuredLight.name: StructuredLight, Alterman.name: Alterman}
"""Methods by name: ``structured-light`` (the paper's) and ``alterman`` (the sun sensor)."""


def get_method(name: str, options: SurfaceOptions | None = None, **choices: Any) -> Method:
    """The method called ``name``, configured with ``options`` (default: its own defaults),
    or with the ``choices`` that are not None (``n_refine=0``, ``anchor=None``: a CLI's flags;
    the others at the method's defaults).

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
    if name not in METHODS:
        raise WaiInputError(f"unknown method {name!r} (known: {', '.join(METHODS)})")
    cls = METHODS[name]
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
