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
:class:`RestoreResult`. The methods are :mod:`~restoration.structured_light`,
:mod:`~restoration.alterman`, :mod:`~restoration.schlieren` and
:mod:`~restoration.inverse_rendering` (the structured light's spots optionally corrected
for their light centre's bias, :mod:`~restoration.spot_bias`); scores are in
:mod:`~restoration.scoring` and :mod:`~restoration.metrics`.

Every result carries a :class:`Status` (a string enum: ``Status.OK == "ok"``). A frame the data
cannot support comes back with status ``failed`` and the reason (the methods catch
:class:`RestorationFailed`); bad input (a wrong shape, NaN in an image, an unknown option)
raises :class:`~wai_core.errors.WaiInputError`.
"""

from restoration import video
from restoration._compile import COMPILE_NOTICE, kernel_activity, kernels_cached
from restoration.alterman import AltermanCalibration, reconstruct_alterman
from restoration.calibration import Calibration, LevelTrack, RigCalibration
from restoration.consistency import Consistency
from restoration.features import detect_spots, features_from_reference, prepare_reference
from restoration.folder import restore_folder
from restoration.frame import FolderRestore, restore_frame
from restoration.integrate import COMPARISON_INTEGRATORS, INTEGRATORS
from restoration.methods import (
    ENTRY_POINT_GROUP,
    METHODS,
    Alterman,
    InverseRendering,
    InverseRenderingSchlieren,
    InverseRenderingView,
    Schlieren,
    as_method,
    get_method,
    load_calibration,
    method_class,
    method_names,
)
from restoration.metrics import image_metrics, surface_errors
from restoration.normals import spots_on_diffuser
from restoration.observations import Observations
from restoration.options import (
    ANCHORS,
    AltermanOptions,
    InverseRenderingOptions,
    SchlierenOptions,
    StructuredLightOptions,
    SurfaceOptions,
)
from restoration.pattern_level import PatternLevel, find_pattern_level
from restoration.port_calibration import PortFit, calibrate_port
from restoration.protocol import Method, run_method
from restoration.ray_surface import RaySurface
from restoration.result import STATUSES, RestoredView, RestoreResult, Status
from restoration.rig_calibration import (
    PORT_UNDETERMINED,
    UNDETERMINED,
    BoardSpec,
    calibrate_device,
    is_written_rig,
    read_rig,
    refine_on_flat_water,
    rig_keys,
    rig_undetermined,
    write_rig,
)
from restoration.rig_score import RigGridScore, rig_grid_score
from restoration.schlieren import SchlierenCalibration, restore_schlieren
from restoration.schlieren_level import SchlierenLevelled
from restoration.scoring import OBJECT_MIN_LEVEL, Scores, Truth, score
from restoration.sequence import (
    SequenceRestore,
    load_sequence,
    restore_sequence,
    sequence_frames,
)
from restoration.spot_bias import SpotBiasModel, spot_bias_px
from restoration.structured_light import StructuredLight, estimate_surface, fit_to_spots
from restoration.tracking import SequenceState
from restoration.view_check import ViewMatch
from restoration.view_level import StructuredLightView, ViewLevelCalibration
from wai_core.errors import RestorationFailed

__all__ = [
    "ANCHORS",
    "COMPARISON_INTEGRATORS",
    "COMPILE_NOTICE",
    "ENTRY_POINT_GROUP",
    "INTEGRATORS",
    "METHODS",
    "OBJECT_MIN_LEVEL",
    "PORT_UNDETERMINED",
    "STATUSES",
    "UNDETERMINED",
    "Alterman",
    "AltermanCalibration",
    "AltermanOptions",
    "BoardSpec",
    "Calibration",
    "Consistency",
    "FolderRestore",
    "InverseRendering",
    "InverseRenderingOptions",
    "InverseRenderingSchlieren",
    "InverseRenderingView",
    "LevelTrack",
    "Method",
    "Observations",
    "PatternLevel",
    "PortFit",
    "RaySurface",
    "RestorationFailed",
    "RestoreResult",
    "RestoredView",
    "RigCalibration",
    "RigGridScore",
    "Schlieren",
    "SchlierenCalibration",
    "SchlierenLevelled",
    "SchlierenOptions",
    "Scores",
    "SequenceRestore",
    "SequenceState",
    "SpotBiasModel",
    "Status",
    "StructuredLight",
    "StructuredLightOptions",
    "StructuredLightView",
    "SurfaceOptions",
    "Truth",
    "ViewLevelCalibration",
    "ViewMatch",
    "as_method",
    "calibrate_device",
    "calibrate_port",
    "detect_spots",
    "estimate_surface",
    "features_from_reference",
    "find_pattern_level",
    "fit_to_spots",
    "get_method",
    "image_metrics",
    "is_written_rig",
    "kernel_activity",
    "kernels_cached",
    "load_calibration",
    "load_sequence",
    "method_class",
    "method_names",
    "prepare_reference",
    "read_rig",
    "reconstruct_alterman",
    "refine_on_flat_water",
    "restore_folder",
    "restore_frame",
    "restore_schlieren",
    "restore_sequence",
    "rig_grid_score",
    "rig_keys",
    "rig_undetermined",
    "run_method",
    "score",
    "sequence_frames",
    "spot_bias_px",
    "spots_on_diffuser",
    "surface_errors",
    "video",
    "write_rig",
]
