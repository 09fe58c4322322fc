"""The surface-sensing methods behind one small protocol, and a registry by name.

A method is a callable object configured once (its :class:`RestoreOptions`) and applied to
frames: ``method(images, cal) -> RestoreResult``. Each names the calibration type it needs,
which also knows how to read a frame's images from a folder.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar, Protocol

from numpy.typing import NDArray

from restoration.alterman import DEFAULT_OPTIONS as ALTERMAN_OPTIONS
from restoration.alterman import AltermanCalibration, restore_alterman
from restoration.calibration import LevelTrack, RigCalibration, read_scene_record
from restoration.options import RestoreOptions
from restoration.result import RestoreResult
from restoration.structured_light import StructuredLight
from wai_core.errors import WaiInputError

__all__ = ["METHODS", "Alterman", "Method", "as_method", "get_method", "load_calibration"]


class Method(Protocol):
    """What every restoration method offers."""

    name: ClassVar[str]
    calibration_type: ClassVar[type[RigCalibration]]
    options: RestoreOptions

    def __call__(
        self, images: dict[str, NDArray], cal: Any, track: LevelTrack | None = None
    ) -> RestoreResult: ...


class Alterman:
    """Alterman et al.'s sun-and-pinhole sensor (STELLA MARIS), configured once.

    Its normals do not depend on the height, so the level is always the gauge's
    (``options.anchor`` must be ``gauge``, the default here).

    Examples
    --------
    >>> from restoration import Alterman
    >>> Alterman().options.anchor
    'gauge'
    """

    name = "alterman"
    calibration_type = AltermanCalibration

    def __init__(self, options: RestoreOptions | None = None) -> None:
        self.options = ALTERMAN_OPTIONS if options is None else options

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


def get_method(name: str, options: RestoreOptions | None = None) -> Method:
    """The method called ``name``, configured with ``options`` (default: its own defaults).

    Raises
    ------
    WaiInputError
        For an unknown name.
    """
    if name not in METHODS:
        raise WaiInputError(f"unknown method {name!r} (known: {', '.join(METHODS)})")
    return METHODS[name](options)


def as_method(method: str | Method, options: RestoreOptions | None = None) -> Method:
    """``method`` itself when it is a configured method object, else :func:`get_method`
    ``(method, options)``."""
    return get_method(method, options) if isinstance(method, str) else method


def load_calibration(folder: str | Path) -> RigCalibration:
    """The calibration in ``folder/scene.json``: a sun-sensor one when the record has an
    ``alterman`` table, else the structured light's."""
    record = read_scene_record(folder)
    cls = AltermanCalibration if "alterman" in record else StructuredLight.calibration_type
    return cls.from_record(record)
