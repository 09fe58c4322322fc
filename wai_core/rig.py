"""The rig: everything derived from a configuration's devices, derived once and owned once.

A :class:`~wai_core.config.SystemConfig` says what the rig is made of; its :class:`Rig`
(``cfg.rig``) holds what follows from that: each device as a pinhole camera and with its real
optics (principal point, lens distortion, housing port), the projector's dot grid and the dots
it lights, the diffuser's extent, the flat-water path of every dot and the object plane. The
configuration is immutable, so everything here is computed on first use and kept: every stage
that needs camera s, the dot grid or the flat-water spots asks the one rig instead of building
its own from the configuration.

Examples
--------
>>> from wai_core import load_system
>>> rig = load_system("paper").rig
>>> rig.camera_s is rig.camera_s, rig.camera_v.width_px, len(rig.dot_ij)
(True, 800, 1225)
>>> rig.optics("camera_v").ideal
True
"""

from __future__ import annotations

from functools import cached_property
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from wai_core.geometry import PinholeCamera, pinhole_of

if TYPE_CHECKING:
    from wai_core.lens import DeviceOptics
    from wai_core.light_paths import FlatSpots
    from wai_core.port import PortCamera

__all__ = ["DEVICES", "Rig"]

DEVICES = ("projector", "camera_s", "camera_v")
"""The configuration's device sections."""


class Rig:
    """What a configuration's devices imply, computed on first use and kept.

    Build it as ``cfg.rig`` (one per configuration object); ``Rig(cfg)`` makes a fresh one.

    Parameters
    ----------
    cfg : Any
        The configuration (its ``projector``, ``camera_s`` and ``camera_v`` must be set).

    Attributes
    ----------
    cfg : Any
    projector, camera_s, camera_v : PinholeCamera
        The devices' ideal pinholes (pose, focal length, image size).
    """

    def __init__(self, cfg: Any) -> None:
        self.cfg = cfg

    def __repr__(self) -> str:
        return f"Rig({', '.join(f'{d}={getattr(self.cfg, d) is not None}' for d in DEVICES)})"

    def __reduce__(self) -> tuple:
        return (Rig, (self.cfg,))  # what it derives is cheap to derive again

    @cached_property
    def projector(self) -> PinholeCamera:
        """The projector as a pinhole device (its panel pixels' rays)."""
        return pinhole_of(self.cfg.projector)

    @cached_property
    def camera_s(self) -> PinholeCamera:
        """Camera s, which images the diffuser."""
        return pinhole_of(self.cfg.camera_s)

    @cached_property
    def camera_v(self) -> PinholeCamera:
        """Camera v, which looks up through the water at the object."""
        return pinhole_of(self.cfg.camera_v)

    def device(self, name: str) -> PinholeCamera:
        """The pinhole of device ``name`` (one of :data:`DEVICES`)."""
        if name not in DEVICES:
            raise KeyError(f"no device {name!r}: one of {', '.join(DEVICES)}")
        return getattr(self, name)

    @cached_property
    def _optics(self) -> dict[str, DeviceOptics]:
        from wai_core.lens import DeviceOptics

        return {name: DeviceOptics.of(getattr(self.cfg, name), self.device(name))
                for name in DEVICES if getattr(self.cfg, name) is not None}

    def optics(self, name: str) -> DeviceOptics:
        """Device ``name`` with its real optics: principal point, lens distortion and housing
        port (:class:`~wai_core.lens.DeviceOptics`)."""
        return self._optics[name]

    @cached_property
    def ported(self) -> bool:
        """Whether any device sits behind a housing port."""
        return any(optics.has_port for optics in self._optics.values())

    @cached_property
    def _port_indices(self) -> dict[str, float]:
        from wai_core.optics import pattern_index

        n_pattern = pattern_index(self.cfg)
        return {name: float(self.cfg.water.n_water) if name == "camera_v" else n_pattern
                for name in DEVICES}

    def port_index(self, name: str) -> float:
        """The water's index where device ``name``'s rays cross its port: camera s's and the
        projector's carry the pattern's light (:func:`wai_core.optics.pattern_index`), camera
        v's the object's (``[water] n_water``; the restoration's view takes each channel's).

        Examples
        --------
        >>> from wai_core import load_system
        >>> load_system("paper").rig.port_index("camera_s")
        1.3333333333
        """
        return self._port_indices[name]

    @cached_property
    def _models(self) -> dict[str, PinholeCamera | PortCamera]:
        from wai_core.port import camera_model

        return {name: camera_model(optics, self.port_index(name))
                for name, optics in self._optics.items()}

    def camera_model(self, name: str) -> PinholeCamera | PortCamera:
        """Device ``name`` as the restoration models it once its lens is undone (images and
        spot centres in its ideal pinhole's pixels): that pinhole, or behind a housing port
        the non-central :class:`~wai_core.port.PortCamera`."""
        return self._models[name]

    @cached_property
    def dot_grid(self) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Every dot's grid index ``(i, j)`` (G, 2) and panel position ``(col, row)`` (G, 2)
        px, row by row (:func:`wai_core.pattern.dot_grid`)."""
        from wai_core.pattern import dot_grid

        return dot_grid(self.cfg.pattern, self.projector)

    @property
    def dot_ij(self) -> NDArray[np.int64]:
        """Every dot's grid index (G, 2)."""
        return self.dot_grid[0]

    @property
    def dot_panel_px(self) -> NDArray[np.float64]:
        """Every dot's panel position (G, 2), panel pixels."""
        return self.dot_grid[1]

    def dot_index(self, ij: NDArray) -> NDArray[np.intp]:
        """The rows of the dot grid (:attr:`dot_grid`) of the dots with grid indices ``ij``
        (K, 2) (the grid is laid out row by row from its lowest indices)."""
        grid = self.dot_ij
        ni, nj = int(grid[:, 0].max()), int(grid[:, 1].max())
        ij = np.asarray(ij)
        return (ij[:, 1] + nj) * (2 * ni + 1) + (ij[:, 0] + ni)

    @cached_property
    def dot_rays_px(self) -> NDArray[np.float64]:
        """Every dot's panel position (G, 2) whose ray through the projector's ideal pinhole
        is the dot's real ray (the lens's principal point and distortion undone:
        :meth:`~wai_core.lens.DeviceOptics.pinhole_px`; :attr:`dot_panel_px` itself for an
        ideal projector)."""
        return self.optics("projector").pinhole_px(self.dot_panel_px)

    @cached_property
    def dot_rays(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Every dot's ray in the water through the projector's real optics
        (:func:`wai_core.light_paths.dot_rays`): origins, the projector's centre (3,) or, behind
        a port, each ray's own (G, 3) mm, and unit directions (G, 3)."""
        from wai_core.light_paths import dot_rays

        return dot_rays(self, self.dot_panel_px)

    def dot_rays_of(self, ij: NDArray) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """:attr:`dot_rays` of the dots with grid indices ``ij`` (K, 2): origins (3,) or
        (K, 3) mm, directions (K, 3)."""
        origin, dirs = self.dot_rays
        index = self.dot_index(ij)
        return (origin if origin.ndim == 1 else origin[index]), dirs[index]

    @cached_property
    def diffuser_rect(self) -> NDArray:
        """Extent ``[[x0, x1], [y0, y1]]`` of the diffuser, mm: camera s's view of its plane
        (:func:`wai_core.layout.diffuser_rect`)."""
        from wai_core.layout import footprint_on_plane

        return footprint_on_plane(self.camera_s, self.cfg.diffuser.z_mm)

    @cached_property
    def flat_spots(self) -> FlatSpots:
        """Every dot's path through flat water at ``h0`` to camera s
        (:func:`wai_core.light_paths.flat_spots`)."""
        from wai_core.light_paths import flat_spots

        return flat_spots(self)

    @cached_property
    def lit(self) -> NDArray[np.bool_]:
        """The dots the projector lights (G,) (:func:`wai_core.layout.lit_dots`)."""
        from wai_core.layout import lit_dots

        return lit_dots(self.cfg)

    @cached_property
    def dot_weights(self) -> NDArray:
        """Each dot's brightness (G,) in [0, 1] (:func:`wai_core.layout.dot_weights`)."""
        from wai_core.layout import dot_weights

        return dot_weights(self.cfg)

    @cached_property
    def panel_image(self) -> NDArray[np.float32]:
        """The projector's panel (H, W, 3) in [0, 1], its dots at their brightness
        (:func:`wai_core.pattern.pattern_image`), read-only: every scene of system S loaded
        for this configuration (a dataset's mesh levels, flat water) projects the same one."""
        from wai_core.pattern import pattern_image

        image = pattern_image(self.cfg.pattern, self.projector, self.dot_weights)
        image.setflags(write=False)
        return image

    @cached_property
    def object_center_mm(self) -> NDArray:
        """Centre (3,) mm of the object rectangle (:func:`wai_core.layout.object_plane_center`)."""
        from wai_core.layout import object_plane_center

        return object_plane_center(self.cfg)
