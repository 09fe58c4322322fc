"""What the restoration knows of a rig: its configuration and everything derived from it.

A calibration is read from ``scene.json`` (written by ``wai render``, or by hand for one's own
captures: the ``config`` section alone is enough) or built from a configuration in memory. It
is shared by every frame of the rig and owns what is derived from the rig once: the devices'
models, the dot grid and its panel lookup, the view's gain, the flat-water reference (detected
once) and the view's trace plan. A frame's features become :meth:`Calibration.observe`'s
:class:`~restoration.observations.Observations`. Per-sequence state (a video's level) is not
kept here: see :class:`LevelTrack`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from restoration.features import ReferenceGrid, prepare_reference
from restoration.level import Anchor
from restoration.observations import Observations
from restoration.options import SurfaceOptions
from restoration.reverse_trace import Restoration, SplinePatches, ViewPlan, ViewState, restore_view
from restoration.spot_bias import SpotBiasModel, flat_gain, spot_bias_px
from restoration.undistort import PinholeRemap
from wai_core.config import SystemConfig, config_from_dict
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera, intersect_plane_z
from wai_core.heightfield import Heightfield
from wai_core.images import find_image, read_image
from wai_core.io import read_json
from wai_core.optics import channel_indices
from wai_core.port import PortCamera, camera_model

__all__ = ["Calibration", "LevelTrack", "RigCalibration", "read_scene_record"]

GREY_WEIGHTS = (0.299, 0.587, 0.114)
"""The weights of red, green and blue in OpenCV's ``RGB2GRAY`` (ITU-R BT.601), the grey image
an optical flow of the view reads."""


def read_scene_record(folder: str | Path) -> dict[str, Any]:
    """``folder/scene.json`` as a dict with a ``config`` table (checked)."""
    path = Path(folder) / "scene.json"
    record = read_json(path)
    if not isinstance(record, dict) or not isinstance(record.get("config"), dict):
        raise WaiInputError(f"{path}: needs a 'config' table (the system configuration)")
    return record


def record_view_gain(record: dict[str, Any]) -> float:
    """The factor the view's values carry over the object's radiance: rendered radiance gains
    n^2 entering the water (``derived.view_radiance_gain``, written by the renderer); a
    capture's record has none, and its images are taken as they are (1)."""
    derived = record.get("derived")
    gain = derived.get("view_radiance_gain", 1.0) if isinstance(derived, dict) else 1.0
    if not isinstance(gain, int | float) or not np.isfinite(gain) or gain <= 0:
        raise WaiInputError(f"scene.json: derived.view_radiance_gain must be > 0, not {gain!r}")
    return float(gain)


@dataclass
class RigCalibration:
    """The basics every method's calibration holds: the system configuration (water, camera v,
    object) and the view's radiance gain.

    Attributes
    ----------
    cfg : SystemConfig
    view_gain : float
        The view image divided by this is the object's radiance scale (1 for captures, n^2 for
        renders).
    rig : dict or None
        The rig applied over the folder's configuration (:func:`restoration.with_rig`):
        ``{"file": path or None, "config_keys": {...}}``, recorded in ``metrics.json``; None
        when the configuration is the folder's own.
    """

    cfg: SystemConfig
    view_gain: float = 1.0
    rig: dict[str, Any] | None = field(default=None, compare=False, kw_only=True)
    _view_plans: dict[tuple[int, float], ViewPlan] = field(
        default_factory=dict, init=False, repr=False, compare=False
    )

    IMAGES: ClassVar[tuple[str, ...]] = ("view",)
    """Stems of the images a frame of this method needs."""
    DEVICES: ClassVar[dict[str, str]] = {"view": "camera_v", "view_flat": "camera_v",
                                         "view_truth": "camera_v"}
    """The device (config section) that takes each image."""

    @classmethod
    def from_record(cls, record: dict[str, Any]) -> RigCalibration:
        """From a ``scene.json`` record (see :func:`read_scene_record`): its configuration and
        the view's gain."""
        return cls(config_from_dict(record["config"]), record_view_gain(record))

    @classmethod
    def from_folder(cls, folder: str | Path) -> RigCalibration:
        """From ``folder/scene.json``."""
        return cls.from_record(read_scene_record(folder))

    @cached_property
    def _remaps(self) -> dict[str, PinholeRemap]:
        """The pinhole remap of each device whose optics are not its ideal pinhole's."""
        remaps = {}
        for device in set(self.DEVICES.values()):
            remap = PinholeRemap.of(self.cfg.rig.optics(device), device)
            if remap is not None:
                remaps[device] = remap
        return remaps

    def resamples(self, name: str) -> bool:
        """Whether image ``name`` is resampled into its device's ideal pinhole."""
        return self.DEVICES.get(name, "") in self._remaps

    def recorded(self, name: str) -> NDArray[np.bool_] | None:
        """(H, W) bool: the pixels of image ``name`` in its device's ideal pinhole
        (:meth:`to_pinhole`) that hold the camera's data; None for an ideal device (all)."""
        remap = self._remaps.get(self.DEVICES.get(name, ""))
        return None if remap is None else remap.seen

    def to_pinhole(self, name: str, image: NDArray) -> NDArray:
        """Image ``name`` of a real device resampled into its ideal pinhole's geometry (the
        one every stage models; :mod:`restoration.undistort`); itself for an ideal device.
        :meth:`load_images` and the truth readers do this when they read a file."""
        remap = self._remaps.get(self.DEVICES.get(name, ""))
        return image if remap is None else remap.apply(image)

    @property
    def camera_v(self) -> PinholeCamera | PortCamera:
        """The observation camera as the restoration models it (the rig's
        :meth:`~wai_core.rig.Rig.camera_model`: its pinhole, or behind a port the
        :class:`~wai_core.port.PortCamera`)."""
        return self.cfg.rig.camera_model("camera_v")

    @property
    def camera_v_grey(self) -> PinholeCamera | PortCamera:
        """Camera v as a grey image of its view sees through the water: :attr:`camera_v`,
        behind a port with the water of :attr:`view_index` beyond it."""
        optics = self.cfg.rig.optics("camera_v")
        if not optics.has_port or self.view_index == float(self.cfg.water.n_water):
            return self.camera_v
        return camera_model(optics, self.view_index)

    def radiance(self, view: NDArray) -> NDArray:
        """A view image of this rig on the object's radiance scale: divided by
        :attr:`view_gain` (what scores and restored images are expressed in)."""
        return view / self.view_gain

    @property
    def view_indices(self) -> tuple[float, ...]:
        """The water's index for each colour channel of the view: ``(n_water,)`` for one
        index, Quan & Fry's at the channels' wavelengths
        (:func:`wai_core.optics.channel_indices`) when the scene states sea water
        (``[water] index_model = "quan_fry"``): each channel is then restored with its own."""
        w = self.cfg.water
        if w.index_model == "quan_fry":
            return channel_indices(w.salinity_psu, w.temperature_c)
        return (float(w.n_water),)

    @property
    def view_index(self) -> float:
        """One index for the view seen as one grey image (an optical flow's, OpenCV's
        ``RGB2GRAY``): :attr:`view_indices` weighted as that grey weighs the channels (sea
        water's disperses by 0.006 across them)."""
        n = np.asarray(self.view_indices, dtype=float)
        return float(n[0]) if n.size == 1 else float(np.dot(GREY_WEIGHTS, n))

    def view_plan(self, warp_step_px: int = SurfaceOptions.warp_step_px,
                  n_water: float | None = None) -> ViewPlan:
        """The flat-water trace of camera v's nodes every ``warp_step_px`` pixels through water
        of index ``n_water`` (default the scene's), built once per step and index and kept
        (every frame's view resamples into it)."""
        cfg = self.cfg
        n = float(cfg.water.n_water if n_water is None else n_water)
        plan = self._view_plans.get((int(warp_step_px), n))
        if plan is None:
            camera = self.camera_v
            if isinstance(camera, PortCamera) and camera.n_water != n:
                camera = PortCamera(camera.optics, n)
            plan = ViewPlan.build(camera, cfg.water.h0_mm, n, cfg.object_z_mm,
                                  int(warp_step_px))
            self._view_plans[int(warp_step_px), n] = plan
        return plan

    def restore_view(
        self, distorted: NDArray, surface: Heightfield,
        warp_step_px: int = SurfaceOptions.warp_step_px, gain: float = 1.0,
        patches: SplinePatches | None = None, state: ViewState | None = None,
    ) -> Restoration:
        """The view ``distorted`` ((H, W, 3)) restored into the flat-water view's geometry by
        reverse ray tracing through ``surface`` (absolute heights, mm), solving every
        ``warp_step_px``-th pixel, on the radiance scale: ``gain`` is divided out of the
        restored pixels (:attr:`view_gain` for a raw view; 1 for one already divided).
        Resampling is linear, so this equals dividing first, without a copy of the view.
        ``patches``: the surface's spline table when the frame has built it already;
        ``state``: a sequence's :class:`~restoration.reverse_trace.ViewState` (each frame's
        solve starts from the previous frame's; the view then agrees with a cold start's to
        the solver's tolerance). With an index per channel (:attr:`view_indices`) each
        channel is restored through its own; a pixel is valid where every channel's is (the
        counts, warp and timings are the middle channel's)."""
        distorted = np.asarray(distorted)
        if not np.issubdtype(distorted.dtype, np.floating):  # integer captures
            distorted = distorted.astype(np.float64)
        indices = self.view_indices
        if len(indices) == 1 or distorted.ndim != 3 or distorted.shape[2] != len(indices):
            return self._restore_channel(distorted, surface, warp_step_px, gain, patches,
                                         state, indices[len(indices) // 2])
        middle = len(indices) // 2
        views = [self._restore_channel(distorted[..., c], surface, warp_step_px, gain,
                                       patches, state if c == middle else None, n)
                 for c, n in enumerate(indices)]
        valid = np.logical_and.reduce([v.valid for v in views])
        image = np.stack([v.image for v in views], axis=-1)
        image[~valid] = 0
        return replace(views[middle], image=image, valid=valid)

    def _restore_channel(
        self, distorted: NDArray, surface: Heightfield, warp_step_px: int, gain: float,
        patches: SplinePatches | None, state: ViewState | None, n_water: float,
    ) -> Restoration:
        cfg = self.cfg
        camera = self.camera_v
        if isinstance(camera, PortCamera) and camera.n_water != n_water:
            camera = PortCamera(camera.optics, n_water)  # the port refracts this channel too
        view = restore_view(
            distorted, camera, surface, cfg.water.h0_mm, n_water, cfg.object_z_mm,
            warp_step_px=warp_step_px, gain=gain, plan=self.view_plan(warp_step_px, n_water),
            patches=patches, state=state,
        )
        remap = self._remaps.get("camera_v")
        if remap is not None:  # a real lens: its pinhole image holds no data past the sensor
            view.restrict(remap.seen_at(view.map_cols, view.map_rows))
        return view

    def image_size(self, name: str) -> tuple[int, int]:
        """``(height, width)`` in pixels that image ``name`` must have (camera v's flat-water
        view, ``view_flat``, as its view)."""
        if name in ("view", "view_flat"):
            dev = self.cfg.camera_v
            return dev.height_px, dev.width_px
        raise KeyError(name)

    def image_files(self, folder: str | Path) -> dict[str, Path]:
        """The file of each of a frame's images (:attr:`IMAGES`) in ``folder`` (EXR, PNG or
        TIFF by stem)."""
        return {name: find_image(folder, name) for name in self.IMAGES}

    def load_images(self, folder: str | Path) -> dict[str, NDArray[np.float32]]:
        """A frame's images from ``folder`` (:meth:`image_files`), sizes checked, in the
        devices' ideal pinholes' geometry (:meth:`to_pinhole`)."""
        return self.load_files(self.image_files(folder))

    def load_files(self, files: Mapping[str, Path]) -> dict[str, NDArray[np.float32]]:
        """:meth:`load_images` from the named files (image name: path)."""
        images = {}
        for name, path in files.items():
            img = read_image(path)
            h, w = self.image_size(name)
            if img.shape[:2] != (h, w):
                raise WaiInputError(
                    f"{path} is {img.shape[1]}x{img.shape[0]} but the calibration says {w}x{h}"
                )
            images[name] = self.to_pinhole(name, img)
        return images


@dataclass
class Calibration(RigCalibration):
    """The structured light's calibration: the rig, and once prepared the flat-water
    reference grid (detected and labelled once per rig, reused by every frame).

    Examples
    --------
    >>> from restoration import Calibration
    >>> from wai_core import load_system
    >>> cal = Calibration(load_system("paper"))
    >>> cal.image_size("pattern")
    (600, 800)
    """

    reference: ReferenceGrid | None = None
    _flat_bias_px: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _bias_gain: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    IMAGES: ClassVar[tuple[str, ...]] = ("pattern", "pattern_flat", "view")

    def flat_spot_bias_px(self, model: SpotBiasModel) -> NDArray[np.float64]:
        """Every dot's spot bias on flat water at the gauge's level (N, 2), camera s pixels,
        in the order of :attr:`wai_core.rig.Rig.dot_panel_px`
        (:func:`restoration.spot_bias.spot_bias_px`); computed once per model."""
        if model not in self._flat_bias_px:
            rig = self.cfg.rig
            self._flat_bias_px[model] = spot_bias_px(rig, rig.dot_panel_px, None,
                                                     float(self.cfg.water.h0_mm), model)
        return self._flat_bias_px[model]

    def spot_bias_gain(self, model: SpotBiasModel) -> NDArray[np.float64]:
        """The share of the modelled spot bias the flat reference's spots show, per axis (2,)
        (:func:`restoration.spot_bias.flat_gain`: its spots' shifts from the calibrated
        places against :meth:`flat_spot_bias_px`; 1 on smooth water); computed once per model
        from the prepared reference (ones before :meth:`prepare`)."""
        if self.reference is None or self.reference.shift_px is None:
            return np.ones(2)
        if model not in self._bias_gain:
            ref = self.reference
            use = ref.observed & ref.lit  # projected dots seen on flat water
            dots = self.cfg.rig.dot_index(ref.ij[use])
            self._bias_gain[model] = flat_gain(ref.shift_px[use],
                                               self.flat_spot_bias_px(model)[dots],
                                               model.roughness)
        return self._bias_gain[model]

    @property
    def projector(self) -> PinholeCamera:
        """The projector as a pinhole device (its panel pixels' rays; the rig's)."""
        return self.cfg.rig.projector

    @property
    def camera_s(self) -> PinholeCamera:
        """The diffuser camera (the rig's)."""
        return self.cfg.rig.camera_s

    @property
    def diffuser_z_mm(self) -> float:
        """Height of the diffuser plane, mm."""
        return float(self.cfg.diffuser.z_mm)

    @cached_property
    def diffuser_mm_per_px(self) -> float:
        """The diffuser plane's extent of one camera-s pixel at the image centre, mm: the
        scale of what camera s resolves (its distance to the plane over its focal length).

        Examples
        --------
        >>> from restoration import Calibration
        >>> from wai_core import load_system
        >>> round(Calibration(load_system("paper")).diffuser_mm_per_px, 3)  # 250 mm / 320 px
        0.781
        """
        cam = self.camera_s
        o, d = cam.pixel_rays(np.array([(cam.width_px - 1) / 2.0]),
                              np.array([(cam.height_px - 1) / 2.0]))
        hit, _ = intersect_plane_z(o, d, self.diffuser_z_mm)
        return float(np.linalg.norm(hit[0] - np.broadcast_to(o, hit.shape)[0]) / cam.focal_px)

    def panel_px(self, ij: NDArray) -> NDArray[np.float64]:
        """Projector panel ``(col, row)`` (K, 2) px of the dots with grid indices ``ij`` (K, 2),
        as the projector's ideal pinhole has them (:attr:`wai_core.rig.Rig.dot_rays_px`).

        Examples
        --------
        >>> import numpy as np
        >>> from restoration import Calibration
        >>> from wai_core import load_system
        >>> cal = Calibration(load_system("paper"))
        >>> step = cal.panel_px(np.array([[1, 0], [0, 1]])) - cal.panel_px(np.array([[0, 0]]))
        >>> bool(np.array_equal(step, np.eye(2) * cal.cfg.pattern.spacing_px))
        True
        """
        rig = self.cfg.rig
        return rig.dot_rays_px[rig.dot_index(ij)]

    def dot_rays(self, ij: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The rays in the water of the dots with grid indices ``ij`` (K, 2): origins (3,), or
        behind a port (K, 3), mm, and unit directions (K, 3)
        (:meth:`wai_core.rig.Rig.dot_rays_of`)."""
        return self.cfg.rig.dot_rays_of(ij)

    def observe(self, ij: NDArray, spot_px: NDArray, *, flat_referenced: bool = False
                ) -> Observations:
        """The features with grid indices ``ij`` (K, 2) and spots ``spot_px`` (K, 2) px in
        the rig's geometry (features without a finite spot left out), weighted for
        integration at the gauge's level (:class:`~restoration.observations.Observations`).
        ``flat_referenced``: each spot less its dot's flat-water shift
        (:meth:`~restoration.features.ReferenceGrid.flat_shift_at`; needs :meth:`prepare`)."""
        keep = np.isfinite(spot_px).all(axis=1)
        ij, spot_px = ij[keep], spot_px[keep]
        if flat_referenced:
            if self.reference is None:
                raise WaiInputError("observe: flat_referenced needs the flat-water reference "
                                    "(Calibration.prepare)")
            spot_px = spot_px - self.reference.flat_shift_at(ij)
        return Observations.build(
            ij, self.panel_px(ij), spot_px, self.projector, self.camera_s, self.diffuser_z_mm,
            weight_h_mm=self.cfg.water.h0_mm, rays=self.dot_rays(ij),
        )

    def image_size(self, name: str) -> tuple[int, int]:
        if name in ("pattern", "pattern_flat"):
            dev = self.cfg.camera_s
            return dev.height_px, dev.width_px
        return super().image_size(name)

    def prepare(self, pattern_flat: NDArray) -> ReferenceGrid:
        """Detect and label the flat-water pattern once; later frames reuse it."""
        if self.reference is None:
            self.reference = prepare_reference(pattern_flat, self.cfg)
        return self.reference


@dataclass
class LevelTrack:
    """A sequence's water level between frames: where each frame's level search starts.

    A video's mean level drifts far less between frames than the search's first step, so
    starting at the previous frame's level saves evaluations. Per sequence, never per rig:
    one calibration may serve several sequences at once.

    Examples
    --------
    >>> track = LevelTrack()
    >>> track.start_mm is None
    True
    """

    start_mm: float | None = None

    def update(self, anchor: Anchor) -> None:
        """Take the level of a frame whose level came from integrability."""
        if anchor.method == "integrability":
            self.start_mm = float(anchor.anchor_mm)
