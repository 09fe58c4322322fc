"""Does the restored view show what the rig sees? Truth-free checks of the view stage.

A surface can pass its own check (:mod:`restoration.consistency`) while the view it undistorts
is of another moment, another camera or turned: one frame's images cannot show that. Two
things a user has can:

- a flat-water view (``view_flat``), captured once with the rig: a restored view lies in the
  flat-water view's geometry, so the two must agree where the view was restored;
- a sequence of a still object: every frame's restored view must agree with the others'
  (their per-pixel median).

Agreement is the normalised cross-correlation (NCC) of the grey images over the restored
pixels, which ignores the camera's gain and offset. A restored frame of the paper's rig reaches
0.998 against the flat view; the view of a moment 0.5 s away 0.39-0.69, one turned by 180°
below 0.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["VIEW_MATCH_MIN_NCC", "ViewMatch", "match_flat_view", "match_sequence", "ncc"]

VIEW_MATCH_MIN_NCC = 0.9
"""A restored view whose NCC with its reference is below this is a ``view_mismatch``."""

MIN_COMPARED_PX = 100
"""Fewer restored pixels than this compare nothing (the match is then not judged)."""


@dataclass(frozen=True)
class ViewMatch:
    """A restored view compared with a reference of what the rig sees through flat water.

    Attributes
    ----------
    reference : str
        ``view_flat`` or ``sequence median``.
    ncc_restored : float
        NCC of the restored view with the reference over the restored pixels (NaN when fewer
        than :data:`MIN_COMPARED_PX` were compared).
    ncc_distorted : float
        The same for the distorted view, over the same pixels (how far the waves moved it).
    compared_px : int
        Pixels compared.
    """

    reference: str
    ncc_restored: float
    ncc_distorted: float
    compared_px: int

    @property
    def consistent(self) -> bool:
        """False only when enough pixels were compared and they disagree."""
        return not (self.ncc_restored < VIEW_MATCH_MIN_NCC)

    @property
    def message(self) -> str:
        """Why the frame is a ``view_mismatch`` (empty when consistent)."""
        if self.consistent:
            return ""
        return (
            f"the restored view does not match the {self.reference} (NCC "
            f"{self.ncc_restored:.2f} < {VIEW_MATCH_MIN_NCC}; distorted {self.ncc_distorted:.2f}): "
            "a view of another moment or camera, or turned?"
        )

    def summary(self) -> dict[str, Any]:
        """Plain values for ``metrics.json``."""
        return {"reference": self.reference, "ncc_restored": self.ncc_restored,
                "ncc_distorted": self.ncc_distorted, "compared_px": self.compared_px,
                "consistent": self.consistent}


def _grey(image: NDArray) -> NDArray:
    img = np.asarray(image, np.float64)
    return img.mean(axis=-1) if img.ndim == 3 else img


def ncc(a: NDArray, b: NDArray, mask: NDArray) -> float:
    """Normalised cross-correlation of two images over ``mask``.

    Parameters
    ----------
    a, b : (H, W) or (H, W, 3) ndarray
        Images of one geometry (colour is averaged to grey).
    mask : (H, W) ndarray of bool
        Pixels compared.

    Returns
    -------
    float
        In [-1, 1]; NaN when fewer than :data:`MIN_COMPARED_PX` pixels are compared or either
        image is constant there.

    Examples
    --------
    >>> import numpy as np
    >>> x = np.random.default_rng(0).random((20, 20))
    >>> round(ncc(x, 3 * x + 1, np.ones((20, 20), bool)), 6)
    1.0
    """
    m = np.asarray(mask, bool) & np.isfinite(_grey(a)) & np.isfinite(_grey(b))
    if m.sum() < MIN_COMPARED_PX:
        return float("nan")
    x, y = _grey(a)[m], _grey(b)[m]
    x, y = x - x.mean(), y - y.mean()
    den = float(np.sqrt((x * x).sum() * (y * y).sum()))
    return float((x * y).sum() / den) if den > 0 else float("nan")


def match_flat_view(
    restored: NDArray, valid: NDArray, distorted: NDArray, view_flat: NDArray
) -> ViewMatch:
    """The restored view against a flat-water view of the same rig.

    Parameters
    ----------
    restored : (H, W, 3) ndarray
        The restored view (flat-water geometry).
    valid : (H, W) ndarray of bool
        Its restored pixels.
    distorted : (H, W, 3) ndarray
        The view as captured through the waves.
    view_flat : (H, W, 3) ndarray
        The rig's view through flat water (any gain).

    Returns
    -------
    ViewMatch
    """
    return ViewMatch("view_flat", ncc(restored, view_flat, valid),
                     ncc(distorted, view_flat, valid), int(np.count_nonzero(valid)))


def match_sequence(
    restored: list[NDArray], valid: list[NDArray], distorted: list[NDArray], step: int = 2
) -> list[ViewMatch | None]:
    """Each frame's restored view against the per-pixel median of all restored views.

    A still object's restored views agree; a frame whose view is of another moment or camera
    stands out. Needs three restored frames (the median is then the others' view).

    Parameters
    ----------
    restored, distorted : list of (H, W, 3) ndarray
        Every frame's restored and distorted view.
    valid : list of (H, W) ndarray of bool
        Every frame's restored pixels (all False for a frame not restored).
    step : int
        Compare every ``step``-th pixel in each direction (the median of a long sequence is
        the cost; agreement needs no full resolution).

    Returns
    -------
    list of ViewMatch or None
        One per frame; None for frames not restored, and for all when fewer than three were.
    """
    sub = np.s_[::step, ::step]
    masks = [np.asarray(m, bool)[sub] for m in valid]
    used = [k for k, m in enumerate(masks) if np.count_nonzero(m) >= MIN_COMPARED_PX]
    if len(used) < 3:
        return [None] * len(restored)
    stack = np.stack([np.where(masks[k], _grey(restored[k][sub]), np.nan).astype(np.float32)
                      for k in used])
    with warnings.catch_warnings():  # pixels no frame restored: NaN, as wanted
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(stack, axis=0)
    seen = np.isfinite(median)
    out: list[ViewMatch | None] = [None] * len(restored)
    for k in used:
        both = masks[k] & seen
        out[k] = ViewMatch("sequence median", ncc(restored[k][sub], median, both),
                           ncc(distorted[k][sub], median, both), int(np.count_nonzero(both)))
    return out
