"""Restoration: from images plus calibration to a surface and an undistorted view.

Reads only the images and the calibration (``scene.json``); the true surface and view are read
only to score, and only when they exist. Never imports the wave generator or the renderer (it
runs without Mitsuba installed).

A frame in ten lines::

    import restoration as rs

    done = rs.restore_folder("renders/demo")          # calibration, images, truth if any
    print(done.result.status, done.scores.rmse_mm)

    cal = rs.Calibration.from_folder("renders/demo")   # or step by step, from memory
    method = rs.StructuredLight(rs.StructuredLightOptions(integrator="paper"))
    result = method(cal.load_images("renders/demo"), cal)

One path for a frame: the :class:`Calibration` (the rig and everything derived from it, once)
-> the features (:mod:`~restoration.features`: detect, reference, match) -> the frame's
:class:`Observations` (:meth:`Calibration.observe`: rays and diffuser points) -> the stages,
normals (:mod:`~restoration.normals`), integration (:mod:`~restoration.integrate`), level
(:mod:`~restoration.anchor`), surface (:mod:`~restoration.surface`), consistency
(:mod:`~restoration.consistency`), view (:mod:`~restoration.reverse_trace`) -> the
:class:`RestoreResult`. The methods are :mod:`~restoration.structured_light` and
:mod:`~restoration.alterman`; scores are in :mod:`~restoration.scoring` and
:mod:`~restoration.metrics`.

Every result carries a :class:`Status` (a string enum: ``Status.OK == "ok"``). A frame the data
cannot support comes back with status ``failed`` and the reason (the methods catch
:class:`RestorationFailed`); bad input (a wrong shape, NaN in an image, an unknown option)
raises :class:`~wai_core.errors.WaiInputError`.
"""

from restoration import video
from restoration.alterman import AltermanCalibration
from restoration.calibration import Calibration, LevelTrack, RigCalibration
from restoration.consistency import Consistency
from restoration.errors import RestorationFailed
from restoration.folder import FolderRestore, restore_folder
from restoration.methods import (
    ENTRY_POINT_GROUP,
    METHODS,
    Alterman,
    Method,
    as_method,
    get_method,
    load_calibration,
    method_class,
    method_names,
    run_method,
)
from restoration.observations import Observations
from restoration.options import (
    ANCHORS,
    AltermanOptions,
    StructuredLightOptions,
    SurfaceOptions,
)
from restoration.result import STATUSES, RestoredView, RestoreResult, Status
from restoration.rig_score import RigGridScore, rig_grid_score
from restoration.scoring import Scores, Truth, score
from restoration.sequence import SequenceRestore, restore_sequence
from restoration.structured_light import StructuredLight
from restoration.view_check import ViewMatch

__all__ = [
    "ANCHORS",
    "ENTRY_POINT_GROUP",
    "METHODS",
    "STATUSES",
    "Alterman",
    "AltermanCalibration",
    "AltermanOptions",
    "Calibration",
    "Consistency",
    "FolderRestore",
    "LevelTrack",
    "Method",
    "Observations",
    "RestorationFailed",
    "RestoreResult",
    "RestoredView",
    "RigCalibration",
    "RigGridScore",
    "Scores",
    "SequenceRestore",
    "Status",
    "StructuredLight",
    "StructuredLightOptions",
    "SurfaceOptions",
    "Truth",
    "ViewMatch",
    "as_method",
    "get_method",
    "load_calibration",
    "method_class",
    "method_names",
    "restore_folder",
    "restore_sequence",
    "rig_grid_score",
    "run_method",
    "score",
    "video",
]
