"""One frame's matched features in the rig's geometry: what every stage after matching reads.

The features stage gives grid indices and spot pixels; the calibration turns them into the
projector's rays and the spots' points on the diffuser once (:meth:`Calibration.observe
<restoration.calibration.Calibration.observe>`), and the stages (normals, integration, level,
consistency) read them from here. The integration structures that depend on the samples'
grid indices alone are kept on :attr:`Observations.plans` for the frame's many passes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from restoration.integrate.plans import IntegrationPlans
from restoration.normals import points_on_rays, projector_rays, spots_on_diffuser
from wai_core.errors import WaiInputError
from wai_core.geometry import PinholeCamera

__all__ = ["Observations"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Observations:
    """Matched features of one frame with their rays, in ``lab`` (mm).

    Attributes
    ----------
    ij : (K, 2) ndarray of int
        Grid index of each feature's dot.
    panel_px : (K, 2) ndarray
        The dots' projector panel positions ``(col, row)``, pixels.
    spot_px : (K, 2) ndarray
        Their detected spots in camera s ``(col, row)``, pixels.
    spots_mm : (K, 3) ndarray
        The spots back-projected onto the diffuser plane, mm.
    origin_mm : (3,) or (K, 3) ndarray
        The projector's centre, or behind a port each ray's origin (where it enters the
        water), mm.
    dirs : (K, 3) ndarray
        Unit projector rays of the dots.
    z_h_mm : float
        Height of the diffuser plane, mm.
    weight_xy_mm : (K, 2) ndarray or None
        Positions that weigh the integration's differences in every reconstruction of these
        features (the rays' points at the gauge's level), so that the level search's
        reconstructions share one factorisation; None: each reconstruction's first pass.
    plans : IntegrationPlans
        Edges, graphs and factorisations of these samples, kept for the frame.

    Examples
    --------
    >>> import numpy as np
    >>> from restoration import Observations
    >>> from wai_core import load_system
    >>> cfg = load_system("paper")
    >>> obs = Observations.build(
    ...     np.array([[0, 0]]), np.array([[400.0, 300.0]]), np.array([[400.0, 300.0]]),
    ...     cfg.rig.projector, cfg.rig.camera_s, cfg.diffuser.z_mm)
    >>> len(obs), obs.spots_mm.shape, bool(np.isclose(obs.spots_mm[0, 2], cfg.diffuser.z_mm))
    (1, (1, 3), True)
    """

    ij: NDArray[np.int64]
    panel_px: Array
    spot_px: Array
    spots_mm: Array
    origin_mm: Array
    dirs: Array
    z_h_mm: float
    weight_xy_mm: Array | None = None
    plans: IntegrationPlans = field(default_factory=IntegrationPlans, repr=False, compare=False)

    @classmethod
    def build(
        cls,
        ij: ArrayLike,
        panel_px: ArrayLike,
        spot_px: ArrayLike,
        projector: PinholeCamera,
        camera_s: PinholeCamera,
        z_h_mm: float,
        weight_h_mm: float | None = None,
        weight_xy_mm: ArrayLike | None = None,
        rays: tuple[Array, Array] | None = None,
    ) -> Observations:
        """Rays and diffuser points of the features ``ij`` (K, 2) with panel positions
        ``panel_px`` and spots ``spot_px`` (K, 2) px: the integration weights are the rays'
        points at height ``weight_h_mm`` (mm), or ``weight_xy_mm`` (K, 2) mm as given, or
        (neither) each reconstruction's own first pass. ``rays``: the dots' rays (origins
        (3,) or (K, 3) mm, directions (K, 3); :meth:`wai_core.rig.Rig.dot_rays_of`) when the
        projector is more than its pinhole ``projector`` (a port); else from ``panel_px``.

        Raises
        ------
        WaiInputError
            When the arrays differ in length, ``ij`` is not integer, or the weights are not
            (K, 2).
        """
        ij_arr = np.asarray(ij)
        n = {np.shape(a)[0] if np.ndim(a) else -1 for a in (ij_arr, panel_px, spot_px)}
        if len(n) != 1:
            raise WaiInputError("reconstruct_surface: ij, panel_px and spot_px differ in length")
        if not np.issubdtype(ij_arr.dtype, np.integer):
            raise WaiInputError("reconstruct_surface: ij must hold integer grid indices")
        spots = spots_on_diffuser(spot_px, camera_s, z_h_mm)
        origin, dirs = projector_rays(panel_px, projector) if rays is None else rays
        weights = None
        if weight_xy_mm is not None:
            weights = np.asarray(weight_xy_mm, dtype=float)
            if weights.shape != (ij_arr.shape[0], 2):
                raise WaiInputError("reconstruct_surface: weight_xy_mm must be (K, 2)")
        elif weight_h_mm is not None:
            weights = points_on_rays(origin, dirs, weight_h_mm)[:, :2]
        return cls(
            ij_arr, np.asarray(panel_px), np.asarray(spot_px), spots, origin, dirs,
            float(z_h_mm), weights,
        )

    def __len__(self) -> int:
        return int(self.ij.shape[0])

    def rows_of(self, ij: ArrayLike) -> NDArray[np.intp]:
        """The rows (K,) of the samples with grid indices ``ij`` (K, 2), which must be among
        these observations' (a surface's samples: the integrator may drop some).

        Examples
        --------
        >>> import numpy as np
        >>> from wai_core import load_system
        >>> rig = load_system("paper").rig
        >>> ij = np.array([[0, 0], [1, 0], [0, 1]])
        >>> obs = Observations.build(ij, rig.dot_panel_px[rig.dot_index(ij)],
        ...                          np.full((3, 2), 400.0), rig.projector, rig.camera_s, 60.0)
        >>> obs.rows_of(np.array([[0, 1], [0, 0]])).tolist()
        [2, 0]
        """
        ij = np.asarray(ij)
        base = int(np.abs(self.ij).max()) + 1 if len(self) else 1
        keys = (self.ij[:, 0] + base) * (2 * base + 1) + self.ij[:, 1] + base
        order = np.argsort(keys)
        want = (ij[:, 0] + base) * (2 * base + 1) + ij[:, 1] + base
        return order[np.searchsorted(keys, want, sorter=order)]

    def take(self, rows: ArrayLike) -> Observations:
        """The observations of rows ``rows`` (an index array or a mask), in that order (a new
        :class:`~restoration.integrate.plans.IntegrationPlans`: another sample set)."""
        rows = np.asarray(rows)
        weights = None if self.weight_xy_mm is None else self.weight_xy_mm[rows]
        origin = self.origin_mm if self.origin_mm.ndim == 1 else self.origin_mm[rows]
        return Observations(self.ij[rows], self.panel_px[rows], self.spot_px[rows],
                            self.spots_mm[rows], origin, self.dirs[rows], self.z_h_mm,
                            weights)
