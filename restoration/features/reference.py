"""The flat-water reference lattice: where every dot of the grid lands in camera s for flat
water, predicted from calibration alone (:func:`predict_flat_spots`); which spots the diffuser's
edge cuts (:func:`flag_diffuser_edge`); the flat-water spots labelled with grid indices by
proximity to the prediction, the lattice extended by virtual nodes beyond the grid
(:func:`match_reference`, which returns a :class:`ReferenceGrid`); and the whole of it, computed
once per rig rather than per frame (:func:`prepare_reference`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from restoration.features._lattice import _DIRS4, _Lattice, _LatticeTables
from restoration.features._outline import (
    _diffuser,
    _edge_distances,
    _outline_px,
    _visible_outline,
)
from restoration.features._types import BoolArray, FloatArray, IntArray
from restoration.features.camera_s import image_scale, in_real_image, pinhole_spots
from restoration.features.detect import (
    _TUNED_SIGMA_PX,
    Spots,
    SpotScales,
    _scales_for,
    detect_spots,
)
from wai_core.config import SystemConfig
from wai_core.errors import RestorationFailed, WaiInputError
from wai_core.light_paths import real_spot_px


@dataclass(frozen=True)
class ReferenceGrid:
    """The dot lattice in camera s for flat water: where each dot's spot is, or would be.

    The lattice holds every grid dot plus a margin of *virtual* nodes beyond the grid (never lit),
    which let the correspondence notice a labelling shifted by whole spacings.

    Attributes
    ----------
    ij : (G, 2) ndarray of int
        Lattice index ``(i, j)`` of each node (grid dots as in :func:`wai_core.pattern.dot_grid`).
    ref_px : (G, 2) ndarray
        Flat-water spot centre, pixels: detected where ``observed``, else the calibrated
        prediction (which may lie off the diffuser or off the image).
    pred_px : (G, 2) ndarray or None
        The calibrated prediction of every node (:func:`predict_flat_spots`), pixels; None
        for a grid made by hand.
    observed : (G,) ndarray of bool
        The dot's spot was detected on flat water.
    lit : (G,) ndarray of bool
        The node is a projected dot (False for virtual nodes and unlit dots).
    spacing_px : (G,) ndarray
        Local spot spacing: distance to the nearest lattice neighbour in the image, pixels.
    cov_px2 : (G, 2, 2) ndarray
        Flat-water spot covariance where ``observed`` (NaN elsewhere), pixels^2.
    unmatched_ij : (M, 2) ndarray of int
        Dots predicted in view for which no flat-water spot was found.
    counts : dict of str to int
        ``predicted_in_view``, ``observed``, ``unmatched_predicted``, ``unassigned_spots``.
    rms_px : float
        RMS distance between detected and calibration-predicted centres, pixels: over every
        matched spot from :func:`match_reference`, over the spots the image does not cut
        from :func:`prepare_reference` (:func:`whole_spots_rms`).
    spot_sigma_px : float
        Calibrated spot standard deviation in camera s (:func:`spot_sigma_px`), pixels: the
        length that the pixel-scale constants of detection and matching follow; NaN when the
        grid was built without a configuration (the tuned constants then apply).
    outline_px : (4, 2) ndarray or None
        The diffuser's corners in camera s, pixels, in order around it (read-only): where
        spots are cut by its edge (:func:`flag_diffuser_edge`). None when the grid was built
        without a configuration.
    visible_px : (M, 2) ndarray or None
        Where camera s can see a spot: the diffuser's outline clipped to the image, pixels
        (read-only; ``visible_px`` of the matching). None as ``outline_px``.
    spot_scales : SpotScales
        The detection's pixel-scale parameters at ``spot_sigma_px`` (the tuned ones when it is
        NaN), built with the grid for every frame's :func:`detect_spots`.
    shift_px : (G, 2) ndarray or None
        Each node's flat-water spot less its calibrated prediction, pixels (read-only;
        :func:`flat_shifts`): what refers a frame's spots to the flat reference
        (:meth:`flat_shift_at`). None when the grid was built without a configuration.
    real_px : (G, 2) ndarray or None
        ``ref_px`` in camera s's real image (its lens and port,
        :func:`wai_core.light_paths.real_spot_px`), where the image's edge cuts spots; None:
        ``ref_px`` itself (an ideal camera, or a grid built without a configuration).
    image_scale : float
        Camera s's real-image pixels per pinhole pixel at the spots (:func:`image_scale`; 1
        but behind a port): spots are detected in the image as taken, at
        :attr:`detect_sigma_px`.
    joined : bool
        The flat-water spots run together (a rough surface's pedestal joins them): every
        frame's detection splits joined segments at their saddles
        (:meth:`~restoration.features.detect.SpotScales.joined`).
    median_spacing_px : float
        The median of ``spacing_px`` where it is not NaN, pixels (NaN when it is all NaN):
        the spacing a frame's checks and statuses are scaled by.
    """

    ij: IntArray
    ref_px: FloatArray
    observed: BoolArray
    lit: BoolArray
    spacing_px: FloatArray
    cov_px2: FloatArray
    unmatched_ij: IntArray
    counts: dict[str, int]
    rms_px: float
    tables: _LatticeTables = field(init=False, repr=False, compare=False)
    spot_sigma_px: float = float("nan")
    outline_px: FloatArray | None = field(default=None, repr=False, compare=False)
    visible_px: FloatArray | None = field(default=None, repr=False, compare=False)
    spot_scales: SpotScales = field(init=False, repr=False, compare=False)
    pred_px: FloatArray | None = field(default=None, repr=False, compare=False)
    fit_px: FloatArray | None = field(default=None, repr=False, compare=False)
    shift_px: FloatArray | None = field(default=None, repr=False, compare=False)
    real_px: FloatArray | None = field(default=None, repr=False, compare=False)
    image_scale: float = 1.0
    joined: bool = False
    median_spacing_px: float = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        # Neighbour tables for the per-frame matching: they depend on the lattice only.
        object.__setattr__(self, "tables", _LatticeTables.of(self.ij, self.lit))
        scales = _scales_for(self.detect_sigma_px)
        object.__setattr__(self, "spot_scales", scales.joined() if self.joined else scales)
        known = self.spacing_px[~np.isnan(self.spacing_px)]  # np.nanmedian, without its warning
        object.__setattr__(self, "median_spacing_px",
                           float(np.median(known)) if known.size else float("nan"))

    def lit_at(self, ij: NDArray) -> BoolArray:
        """Whether each lattice index ``ij`` (K, 2) is a lit dot of this lattice."""
        node = self.tables.lat.lookup(ij)
        return (node >= 0) & self.lit[np.maximum(node, 0)]

    def flat_shift_at(self, ij: NDArray) -> FloatArray:
        """The flat-water shift (:attr:`shift_px`) of the dots with grid indices ``ij`` (K, 2),
        pixels: zero for a dot the lattice lacks, or a grid built without a configuration."""
        out = np.zeros((len(ij), 2))
        if self.shift_px is None:
            return out
        node = self.tables.lat.lookup(ij)
        known = node >= 0
        out[known] = self.shift_px[node[known]]
        return out

    @property
    def pixel_scale(self) -> float:
        """Calibrated spot size over the one the pixel constants were tuned at (1 when not
        calibrated): multiply a tuned pixel constant by this."""
        s = self.spot_sigma_px
        return float(s / _TUNED_SIGMA_PX) if np.isfinite(s) and s > 0 else 1.0

    @property
    def detect_sigma_px(self) -> float | None:
        """``spot_sigma_px`` in the image as taken (times :attr:`image_scale`), for
        :func:`~restoration.features.detect.detect_spots` (None when not calibrated)."""
        s = self.spot_sigma_px
        return float(s * self.image_scale) if np.isfinite(s) and s > 0 else None


def predict_flat_spots(
    cfg: SystemConfig, margin_px: float = 0.0
) -> tuple[IntArray, FloatArray, FloatArray, BoolArray]:
    """Where every dot of the grid lands in camera s when the water is flat.

    The rig's flat-water path of every dot (:func:`wai_core.light_paths.flat_spots`): projector
    ray through the dot's panel position -> plane ``z = h0`` -> mirror reflection about
    ``(0, 0, 1)`` -> diffuser plane ``z = z_h`` -> camera s. Panel -> camera s is then a plane
    projective map (a homography), so grid lines stay straight.

    Parameters
    ----------
    cfg : SystemConfig
        The system (projector, pattern, water level, diffuser height and extent, camera s).
    margin_px : float
        Keep spots at least this far inside the image, pixels.

    Returns
    -------
    ij : (K, 2) ndarray of int
        Grid index of every dot (:func:`wai_core.pattern.dot_grid`).
    panel_px : (K, 2) ndarray
        Dot centre on the projector panel, panel pixels.
    spot_px : (K, 2) ndarray
        Predicted spot centre in camera s, pixels (NaN where the ray misses).
    in_view : (K,) ndarray of bool
        The ray goes up to the water, comes down onto the (finite) diffuser, and the spot is in
        front of and inside camera s.
    """
    rig = cfg.rig
    flat = rig.flat_spots
    spot_px = flat.px
    with np.errstate(invalid="ignore"):
        in_view = (
            flat.upward
            & flat.on_diffuser(_diffuser(cfg))
            & np.isfinite(spot_px).all(axis=1)
            & flat.in_front
            & in_real_image(cfg, spot_px, margin_px)
        )
    ij, panel = rig.dot_grid
    return ij.astype(np.int64), panel, spot_px, in_view


def node_flat_px(cfg: SystemConfig, ij: IntArray) -> FloatArray:
    """Where grid nodes ``ij`` (K, 2) would land in camera s on flat water, pixels: the dots'
    own path (:func:`predict_flat_spots`) for nodes the panel has no dot at too, from their
    place on the panel's plane (:func:`wai_core.pattern.grid_panel_px`). NaN where the ray
    goes down, misses the diffuser's plane or lands behind the camera.

    Behind a projector port the map from panel to camera s is not projective, and the
    reference's lattice is extended past the grid (:func:`match_reference`) with these.
    """
    from wai_core.light_paths import flat_spots
    from wai_core.pattern import grid_panel_px

    rig = cfg.rig
    flat = flat_spots(rig, grid_panel_px(cfg.pattern, rig.projector, ij))
    px = flat.px.copy()
    px[~(flat.upward & flat.in_front)] = np.nan
    return px


def spot_sigma_px(cfg: SystemConfig) -> float:
    """Expected standard deviation of a dot's spot in camera s, pixels, from calibration alone.

    Flat water makes panel -> camera s a plane projective map (:func:`predict_flat_spots`); the
    panel dot's Gaussian sigma (``cfg.pattern.sigma_px``) times that map's local linear
    magnification ``sqrt(|det J|)`` (the geometric mean over the spot's two axes), median over
    the dots in view. It sets the scale of every pixel constant of spot detection and matching:
    1.518 px for the paper's rig at 800 x 600, twice that at 1600 x 1200. Per rig:
    :func:`prepare_reference` keeps it (:attr:`ReferenceGrid.spot_sigma_px`).

    Parameters
    ----------
    cfg : SystemConfig

    Returns
    -------
    float
        Pixels; NaN when fewer than 4 dots reach camera s.
    """
    _, panel, spot, in_view = predict_flat_spots(cfg)
    use = in_view if in_view.sum() >= 4 else np.isfinite(spot).all(axis=1)
    if use.sum() < 4:
        return float("nan")
    hom, _ = cv2.findHomography(panel[use].astype(np.float64), spot[use].astype(np.float64), 0)
    if hom is None:
        return float("nan")
    # Jacobian of p -> (H p)_xy / (H p)_z at every dot, in closed form.
    q = np.c_[panel[use], np.ones(int(use.sum()))] @ hom.T
    wq = q[:, 2:]
    jac = (hom[None, :2, :2] * wq[:, :, None] - q[:, :2, None] * hom[None, 2:3, :2]) / wq[
        :, :, None
    ] ** 2
    mag = np.sqrt(np.abs(np.linalg.det(jac)))
    return float(cfg.pattern.sigma_px * np.median(mag))


def flag_diffuser_edge(spots: Spots, outline_px: FloatArray, n_sigma: float = 2.5) -> Spots:
    """Flag as ``border`` the spots that the diffuser's edge cuts (or that lie off it).

    A spot is cut when its centre is closer to an edge of the outline than ``n_sigma`` of its
    own standard deviation across that edge; its centroid is then pulled inwards.

    Parameters
    ----------
    spots : Spots
        Detected spots.
    outline_px : (M, 2) ndarray
        Convex outline of the diffuser in the image, pixels, in order around it.
    n_sigma : float
        Clearance needed, in spot standard deviations.

    Returns
    -------
    Spots
        A copy with ``border`` updated.
    """
    if len(spots) == 0:
        return spots
    dist, normal = _edge_distances(np.asarray(outline_px, dtype=float), spots.centres_px)
    sd = np.sqrt(np.einsum("mk,pkl,ml->pm", normal, spots.cov_px2, normal))
    cut = (dist < n_sigma * sd).any(axis=1)
    return replace(spots, border=spots.border | cut)


def _local_spacing(ij: IntArray, px: FloatArray) -> FloatArray:
    """Distance in the image from each node to its nearest present 4-neighbour, pixels."""
    lat = _Lattice(ij)
    dist = np.full((len(ij), 4), np.inf)
    for n, step in enumerate(_DIRS4):
        nb = lat.neighbour(step)
        ok = nb >= 0
        dist[ok, n] = np.linalg.norm(px[nb[ok]] - px[ok], axis=1)
    out = dist.min(axis=1)
    finite = np.isfinite(out)
    fallback = float(np.median(out[finite])) if finite.any() else 1.0
    return np.where(finite, out, fallback)


def _mutual_nearest(
    a: FloatArray, b: FloatArray, radius: FloatArray
) -> tuple[IntArray, IntArray]:
    """Pairs (ia, ib) that are each other's nearest neighbour and closer than ``radius[ia]``."""
    if len(a) == 0 or len(b) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    d_ab, nn_ab = cKDTree(b).query(a)
    _, nn_ba = cKDTree(a).query(b)
    ia = np.flatnonzero((nn_ba[nn_ab] == np.arange(len(a))) & (d_ab < radius))
    return ia, nn_ab[ia]


def _lattice_homography(ij: IntArray, px: FloatArray) -> FloatArray:
    """Homography (3, 3) from lattice indices to image pixels (exact for flat water: panel ->
    camera s is a plane projective map and the panel position is affine in ``(i, j)``)."""
    hom, _ = cv2.findHomography(ij.astype(np.float64), px.astype(np.float64), 0)
    if hom is None:
        raise WaiInputError("cannot relate the dot grid to camera s: degenerate prediction")
    return hom


def _apply_homography(hom: FloatArray, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Map points (N, 2); also return the projective depth ``w`` (its sign marks the side)."""
    p = np.c_[pts, np.ones(len(pts))] @ hom.T
    with np.errstate(divide="ignore", invalid="ignore"):
        return p[:, :2] / p[:, 2:], p[:, 2]


def _extended_lattice(ij: IntArray, margin: int) -> IntArray:
    """All lattice indices of the grid's bounding box grown by ``margin`` nodes, (G, 2)."""
    lo, hi = ij.min(axis=0) - margin, ij.max(axis=0) + margin
    jj, ii = np.mgrid[lo[1] : hi[1] + 1, lo[0] : hi[0] + 1]
    return np.stack([ii.ravel(), jj.ravel()], axis=1)


def match_reference(
    ref_spots: Spots,
    predicted: tuple[IntArray, FloatArray, FloatArray, BoolArray],
    *,
    tol: float = 0.35,
    lit: BoolArray | None = None,
    margin: int = 6,
    node_px: Callable[[IntArray], FloatArray] | None = None,
) -> ReferenceGrid:
    """Label the flat-water spots with grid indices by proximity to the prediction.

    A first mutual-nearest pass (radius 0.5 spacing) fits a homography from predicted to detected
    centres (RANSAC): both lie on the diffuser plane, so a small calibration error of camera s is
    a plane projective map. The final pass pairs mutual nearest neighbours closer than ``tol`` x
    the local spacing, so each dot and each spot is used once. The lattice is then extended by
    ``margin`` virtual nodes on every side (positions from the same homography).

    Parameters
    ----------
    ref_spots : Spots
        Spots detected in the flat-water image; suspicious ones are not used.
    predicted : tuple
        The output of :func:`predict_flat_spots`.
    tol : float
        Acceptance radius, in units of the local spot spacing.
    lit : (K,) ndarray of bool, optional
        Which grid dots the projector lights, in :func:`~wai_core.pattern.dot_grid` order
        (default: all).
    margin : int
        Virtual nodes added beyond the grid on each side.
    node_px : callable, optional
        Flat-water pixel (K, 2) of lattice nodes ``ij`` (K, 2), NaN where none
        (:func:`node_flat_px`): where the panel -> camera s map is not projective (a projector
        behind a port), the virtual nodes are placed by it rather than by the homography, which
        would put the first ones past the grid's edge a few pixels out of line (2.7 px at a
        5 mm port on the paper's rig) and send the wavy frame's labelling astray there.

    Returns
    -------
    ReferenceGrid
    """
    ij_grid, _, pred_grid, in_view = predicted
    lit_grid = np.ones(len(ij_grid), bool) if lit is None else np.asarray(lit, bool)
    finite = np.isfinite(pred_grid).all(axis=1)
    if finite.sum() < 4:
        raise WaiInputError(f"too few dots reach camera s: {int(finite.sum())}")
    to_px = _lattice_homography(ij_grid[finite], pred_grid[finite])
    ij = _extended_lattice(ij_grid, margin)
    pred, depth = _apply_homography(to_px, ij.astype(np.float64))
    # Nodes on the far side of the horizon (depth sign flipped) have no spot at all.
    _, grid_depth = _apply_homography(to_px, ij_grid[finite].astype(np.float64))
    keep = np.sign(depth) == np.sign(np.median(grid_depth))
    ij, pred = ij[keep], pred[keep]
    grid_lat = _Lattice(ij_grid)
    node_dot = grid_lat.lookup(ij)  # index into the grid arrays, -1 for virtual nodes
    is_dot = node_dot >= 0
    # A port makes the projector non-central: its panel -> camera s map is then not quite
    # projective, and the grid's own dots keep their prediction (the fit places the virtual
    # nodes). A pinhole projector's fit is its prediction to rounding: kept as it is.
    exact = np.zeros(len(ij), bool)
    exact[is_dot] = np.isfinite(pred_grid[node_dot[is_dot]]).all(axis=1)
    if np.max(np.abs(pred[exact] - pred_grid[node_dot[exact]]), initial=0.0) > 1e-3:
        pred = pred.copy()
        pred[exact] = pred_grid[node_dot[exact]]
        if node_px is not None and not is_dot.all():
            placed = node_px(ij[~is_dot])
            found = np.isfinite(placed).all(axis=1)
            pred[np.flatnonzero(~is_dot)[found]] = placed[found]
    view = np.zeros(len(ij), bool)
    view[is_dot] = in_view[node_dot[is_dot]]
    lit_node = np.zeros(len(ij), bool)
    lit_node[is_dot] = lit_grid[node_dot[is_dot]]
    spacing = _local_spacing(ij, pred)

    good = ~ref_spots.suspicious
    det, det_cov = ref_spots.centres_px[good], ref_spots.cov_px2[good]
    cand = np.flatnonzero(view & lit_node)
    pa, pb = _mutual_nearest(pred[cand], det, 0.5 * spacing[cand])
    moved = pred
    if len(pa) >= 8:
        corr, _ = cv2.findHomography(
            pred[cand[pa]], det[pb], cv2.RANSAC, max(0.5, 0.05 * float(np.median(spacing)))
        )
        if corr is not None:
            moved, _ = _apply_homography(corr, pred)
    pa, pb = _mutual_nearest(moved[cand], det, tol * spacing[cand])
    observed = np.zeros(len(ij), bool)
    observed[cand[pa]] = True
    ref_px = moved.copy()
    ref_px[cand[pa]] = det[pb]
    cov = np.full((len(ij), 2, 2), np.nan)
    cov[cand[pa]] = det_cov[pb]
    res = det[pb] - pred[cand[pa]]
    rms = float(np.sqrt(np.mean(np.sum(res**2, axis=1)))) if len(pa) else 0.0
    counts = {
        "predicted_in_view": int(np.sum(view & lit_node)),
        "observed": int(len(pa)),
        "unmatched_predicted": int(np.sum(view & lit_node & ~observed)),
        "unassigned_spots": int(len(ref_spots) - len(pa)),
    }
    return ReferenceGrid(
        ij=ij,
        ref_px=ref_px,
        observed=observed,
        lit=lit_node,
        spacing_px=_local_spacing(ij, ref_px),
        cov_px2=cov,
        unmatched_ij=ij[view & lit_node & ~observed],
        counts=counts,
        rms_px=rms,
        pred_px=pred,
        fit_px=moved,
    )


FLAT_SHIFT_MAX_PX = 1.0
"""A flat-water spot further than this (pixels, at the tuned spot size; scaled with it) from
the plane projective map of the predictions that fits the whole grid is not trusted to refer
frames to: a stray match. A calibration error of camera s moves every spot by that map, not
away from it (docs/results.md, "Calibrating a real rig")."""


def whole_in_image(ref: ReferenceGrid, image_shape: tuple[int, int]) -> BoolArray:
    """(G,) bool: the nodes whose flat-water spot lies further than four spot sigmas from the
    image's edge (in the real image: :attr:`ReferenceGrid.real_px`), so that the image does
    not cut it (a cut spot's centroid is pulled inwards by pixels)."""
    h, w = image_shape
    sigma = ref.spot_sigma_px if np.isfinite(ref.spot_sigma_px) else _TUNED_SIGMA_PX
    edge = 4.0 * sigma * ref.image_scale  # in the image as taken
    px = ref.ref_px if ref.real_px is None else ref.real_px
    x, y = px[:, 0], px[:, 1]
    with np.errstate(invalid="ignore"):
        return (x > edge - 0.5) & (y > edge - 0.5) & (x < w - 0.5 - edge) & (y < h - 0.5 - edge)


def whole_spots_rms(ref: ReferenceGrid, image_shape: tuple[int, int]) -> float:
    """RMS distance, pixels, between the flat-water spots the image does not cut
    (:func:`whole_in_image`) and their calibration-predicted centres: the calibration's
    check (docs/rig.md). NaN without a prediction or such a spot."""
    if ref.pred_px is None:
        return float("nan")
    used = ref.observed & whole_in_image(ref, image_shape)
    if not used.any():
        return float("nan")
    d = ref.ref_px[used] - ref.pred_px[used]
    return float(np.sqrt(np.mean(np.sum(d**2, axis=1))))


def flat_shifts(ref: ReferenceGrid, image_shape: tuple[int, int]) -> FloatArray:
    """Every node's flat-water spot less its calibrated prediction, pixels (G, 2).

    Referred to these shifts, a frame's spots see the flat reference exactly where the
    calibrated model puts flat water, so what displaces both images alike (an error of camera
    s's intrinsics or of the projector's, the spot's centroid bias from the reflectance across
    it) drops out, as it does in the dot shifts the paper measures. Shifts near the image's
    edge (:func:`whole_in_image`) or off the grid's projective fit by more than
    :data:`FLAT_SHIFT_MAX_PX` are not trusted; a lit
    node without a trusted shift takes the mean of its trusted neighbours', else zero.

    Examples
    --------
    >>> import numpy as np
    >>> ij = np.array([[0, 0], [1, 0], [2, 0]])
    >>> px = np.array([[100.0, 100.0], [110.0, 100.0], [120.0, 100.0]])
    >>> ref = ReferenceGrid(ij, px + [0.1, 0.0], np.array([True, False, True]),
    ...                     np.ones(3, bool), np.full(3, 10.0), np.full((3, 2, 2), np.nan),
    ...                     np.zeros((0, 2), int), {}, 0.1, pred_px=px)
    >>> flat_shifts(ref, (600, 800))[:, 0].round(3).tolist()
    [0.1, 0.1, 0.1]
    """
    shift = np.full(ref.ref_px.shape, np.nan)
    if ref.pred_px is None:
        return np.zeros(ref.ref_px.shape)
    inside = whole_in_image(ref, image_shape)
    d = ref.ref_px - ref.pred_px
    # A stray spot departs from the plane projective map that fits the whole grid (what a
    # calibration error of camera s is): measured from that fit, not from the prediction,
    # a rig a pixel off keeps every shift.
    fit = ref.pred_px if ref.fit_px is None else ref.fit_px
    stray = np.hypot(*(ref.ref_px - fit).T) > FLAT_SHIFT_MAX_PX * ref.pixel_scale
    trusted = ref.observed & inside & ~stray
    shift[trusted] = d[trusted]
    nbr = ref.tables.nbrs8  # (G, 8) neighbour nodes, G where absent
    vals = np.vstack([shift, np.full((1, 2), np.nan)])[nbr]
    n = np.sum(np.isfinite(vals[..., 0]), axis=1)
    mean = np.nansum(vals, axis=1) / np.maximum(n, 1)[:, None]
    fill = ~trusted & (n > 0)
    shift[fill] = mean[fill]
    return np.nan_to_num(shift, nan=0.0)


JOINED_SHARE = 0.5
"""Below this share of the spots predicted in view found on flat water, the reference looks for
spots run together (:func:`prepare_reference`)."""


def prepare_reference(
    pattern_flat_img: NDArray, cfg: SystemConfig, *, lit: BoolArray | None = None,
    min_features: int = 16,
) -> ReferenceGrid:
    """The flat-water reference grid: calibration, computed once per rig, not per frame.

    Spots are detected at the calibrated spot size (:func:`spot_sigma_px`). Where they have run
    together (a rough surface: a segment no spot makes, or fewer than :data:`JOINED_SHARE` of
    the spots predicted in view found), they are detected again with every large segment split
    at its saddles, and the grid keeps that for every frame (``joined``) when it finds more.
    The grid keeps what every frame's detection and matching need of the rig: the spot size
    (``spot_sigma_px``, ``spot_scales``) and the diffuser's outlines in camera s
    (``outline_px``, ``visible_px``).

    Raises
    ------
    WaiInputError
        On a bad image (shape, NaN) or a configuration whose dots cannot reach camera s.
    RestorationFailed
        When fewer than ``min_features`` dots are seen on flat water.
    """
    sigma = spot_sigma_px(cfg)
    scale = image_scale(cfg)
    sigma_ok = float(sigma * scale) if np.isfinite(sigma) and sigma > 0 else None
    outline = _outline_px(cfg)
    scales = _scales_for(sigma_ok)
    predicted = predict_flat_spots(cfg)
    lit = cfg.rig.lit if lit is None else lit

    def matched(scales: SpotScales) -> tuple[ReferenceGrid, int]:
        flat = pinhole_spots(detect_spots(pattern_flat_img, scales=scales), cfg)
        return (match_reference(flag_diffuser_edge(flat, outline), predicted, lit=lit,
                                node_px=functools.partial(node_flat_px, cfg)), flat.joined)

    ref, n_joined = matched(scales)
    joined = n_joined > 0 or (
        ref.counts["observed"] < JOINED_SHARE * ref.counts["predicted_in_view"])
    if joined:
        split, _ = matched(scales.joined())
        joined = split.counts["observed"] > ref.counts["observed"]
        ref = split if joined else ref
    ref = replace(
        ref, spot_sigma_px=float(sigma), outline_px=outline, visible_px=_visible_outline(cfg),
        image_scale=scale, joined=joined,
    )
    if not cfg.rig.optics("camera_s").ideal:
        ref = replace(ref, real_px=real_spot_px(cfg.rig, ref.ref_px))
    shape = (cfg.camera_s.height_px, cfg.camera_s.width_px)
    ref = replace(ref, shift_px=flat_shifts(ref, shape), rms_px=whole_spots_rms(ref, shape))
    if ref.counts["observed"] < min_features:
        raise RestorationFailed(f"too few features on flat water: {ref.counts['observed']}")
    return ref
