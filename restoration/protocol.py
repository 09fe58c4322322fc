"""What every restoration method offers (:class:`Method`), and running one on a frame
(:func:`run_method`): the methods of this package as they are, a method of one's own guarded,
so that a call that raises or returns something else than a :class:`RestoreResult` of the
frame's size ends in one line naming it. The registry of methods by name is
:mod:`restoration.methods`."""

from __future__ import annotations

from typing import Any, ClassVar, Protocol

import numpy as np
from numpy.typing import NDArray

from restoration.calibration import LevelTrack, RigCalibration
from restoration.options import SurfaceOptions
from restoration.result import RestoreResult
from wai_core.errors import WaiInputError

__all__ = ["BUILT_IN", "Method", "run_method"]

BUILT_IN: set[type] = set()
"""The package's own methods (:mod:`restoration.methods` registers them), which
:func:`run_method` runs unguarded."""


class Method(Protocol):
    """What every restoration method offers."""

    name: ClassVar[str]
    calibration_type: ClassVar[type[RigCalibration]]
    options_type: ClassVar[type[SurfaceOptions]]
    options: SurfaceOptions

    def __call__(
        self, images: dict[str, NDArray], cal: Any, track: LevelTrack | None = None
    ) -> RestoreResult: ...


def run_method(
    method: Method, images: dict[str, NDArray], cal: Any, track: LevelTrack | None = None
) -> RestoreResult:
    """``method(images, cal, track)``, guarded when it is a method of one's own.

    The package's own methods (:data:`BUILT_IN`) run as they are. Any other method is the user's
    code: one whose call raises (``SystemExit`` included), or returns anything but a
    :class:`RestoreResult` whose view, if any, is an image of the frame's size with a boolean
    mask of it, ends the frame with one line naming the method (its own
    :class:`~wai_core.errors.WaiInputError`, bad input it noticed, passes as it is).

    Raises
    ------
    WaiInputError
        ``method 'NAME' raised ...`` or ``method 'NAME' returned ...``.

    Examples
    --------
    >>> from restoration import Calibration, SurfaceOptions
    >>> class Broken:
    ...     name, calibration_type, options_type = "broken", Calibration, SurfaceOptions
    ...     def __call__(self, images, cal, track=None):
    ...         return None
    >>> try:
    ...     run_method(Broken(), {}, None)
    ... except WaiInputError as exc:
    ...     print(exc)
    method 'broken' returned NoneType, not a RestoreResult (see restoration.Method)
    """
    if type(method) in BUILT_IN:
        return method(images, cal, track)
    name = getattr(method, "name", type(method).__name__)
    try:
        result = method(images, cal, track)
    except WaiInputError:
        raise
    except (Exception, SystemExit) as exc:
        raise WaiInputError(f"method {name!r} raised {type(exc).__name__}: {exc}") from None
    problem = _result_problem(result, cal)
    if problem:
        raise WaiInputError(f"method {name!r} returned {problem} (see restoration.Method)")
    return result


def _result_problem(result: Any, cal: Any) -> str | None:
    """What is wrong with a method's result for a frame of ``cal``'s rig, or None."""
    if not isinstance(result, RestoreResult):
        return f"{type(result).__name__}, not a RestoreResult"
    if not isinstance(result.timings_ms, dict):
        return "timings_ms that is not a dict"
    view = result.view
    if view is None:
        return None
    h, w = cal.image_size("view")
    image, valid = (np.asarray(getattr(view, a, None)) for a in ("image", "valid"))
    if image.ndim not in (2, 3) or image.shape[:2] != (h, w) or not np.issubdtype(
            image.dtype, np.number):
        return f"a view image of shape {image.shape}, not the frame's ({h}, {w}[, 3])"
    if valid.shape != (h, w) or valid.dtype != bool:
        return (f"a view mask of shape {valid.shape} and type {valid.dtype}, not the frame's "
                f"({h}, {w}) of bool")
    return None
