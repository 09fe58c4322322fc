"""Parts of the labelled dots that a neck joins to the rest, and whose labels another shift
fits far better: labels carried across the neck by whole dots, dropped before the surface.

The structured light labels the spots by growing from an anchor (:mod:`restoration.features`).
Where the labelled lattice narrows to a neck one or two dots wide (caustics of short waves cut
it), a part beyond the neck can take labels shifted by whole dots. Its normals then pair each
spot with another dot's ray and describe a surface carrying a height ramp from the neck (on
U = 1.5 m/s capillary waves to 6 omega_p: 3.3-4.7 mm at the part's far edge), and the forward
check reproduces its spots, since the surface was built from them (docs/results.md, "A part the
lattice joins by a neck"). What betrays it is the part's own integrability: integrated alone,
its slopes fit one surface far better under the right labels than under the wrong ones (the
integration residual falls 4-60x at the true shift, where a right part's is lowest at its own
labels or within 1.7x of it).

Labelling already refuses a patch joined to the checked squares by fewer than two links
(:func:`restoration.features.ordering._braced_piece`, ``JOIN_LINKS``): a closed loop must run
through the join. The parts here were joined by necks wide enough to close such loops, yet a
loop through a neck of one or two dots still carried the shift; this test reads the part's
own integrability instead of the join's width.

Each part that a 3 x 3 opening of the labelled lattice separates from the largest, of at
least :data:`MIN_PART` dots, is integrated alone under its labels and under every shift within
:data:`SHIFT_REACH` dots; where a shift lowers its integration residual more than
:data:`MAX_SHIFT_GAIN` times, its dots are dropped with the neck's beside it
(``rejected_shifted_part``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from wai_core.errors import RestorationFailed, WaiInputError

__all__ = ["MAX_SHIFT_GAIN", "MIN_PART", "SHIFT_REACH", "misplaced_parts", "necked_parts"]

MIN_PART = 20
"""Fewest dots in a part that is tested (smaller parts' residuals are noise: on rough water a
part of 12 right dots fitted a shifted labelling 3.6x better)."""
SHIFT_REACH = (6, 1)
"""The largest label shifts tried along the lattice's ``i`` and ``j``, dots."""
MAX_SHIFT_GAIN = 2.5
"""A part whose integration residual another shift lowers more than this many times is
dropped: on the compare cases (U = 1 and 1.5 m/s, seeds 0-3, the weak conditions; 24 parts of
20 dots or more), right parts 1.0-1.66, parts whose labels were shifted 3.2, 3.7 and 59 (and
1.37 on a frame at roughness 0.02 whose flat reference failed)."""

_OPENING = np.ones((3, 3), bool)


def necked_parts(ij: NDArray) -> list[tuple[NDArray[np.bool_], NDArray[np.bool_]]]:
    """The parts of the labelled dots ``ij`` (K, 2) that a 3 x 3 opening of their lattice
    separates from the largest, each of :data:`MIN_PART` dots or more: per part, masks over
    the dots (K,) of the part and of the neck's dots within two steps of it (which carry its
    labels too, or some of them).

    Examples
    --------
    >>> import numpy as np
    >>> block = np.array([(i, j) for i in range(6) for j in range(6)])
    >>> neck = np.array([(6, 2), (7, 2)])
    >>> ij = np.vstack([block, neck, block + (8, 0)])
    >>> [(int(part.sum()), int(neck.sum())) for part, neck in necked_parts(ij)]
    [(36, 2)]
    """
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    if len(ij) == 0:
        return []
    cell = ij - ij.min(axis=0)
    grid = np.zeros(tuple(cell.max(axis=0) + 1), bool)
    grid[cell[:, 0], cell[:, 1]] = True
    labels, n = ndimage.label(ndimage.binary_opening(grid, _OPENING), _OPENING)
    part = labels[cell[:, 0], cell[:, 1]]
    sizes = np.bincount(part, minlength=n + 1)
    sizes[0] = 0
    largest = int(np.argmax(sizes))
    necks = grid & (labels == 0)
    parts = []
    for c in range(1, n + 1):
        if c == largest or sizes[c] < MIN_PART:
            continue
        # The neck's dots beside the part (within two steps) carry its labels too.
        beside = ndimage.binary_dilation(labels == c, _OPENING, iterations=2) & necks
        parts.append((part == c, beside[cell[:, 0], cell[:, 1]]))
    return parts


def misplaced_parts(ij: NDArray, residual_of: Callable[[NDArray[np.bool_], NDArray], float]
                    ) -> tuple[NDArray[np.bool_], list[float]]:
    """The dots of ``ij`` (K, 2) in parts whose labels a shift fits far better (module notes),
    with their necks' dots, and each tested part's gain (its residual under its labels over the
    lowest).

    ``residual_of(mask, shift)``: the integration residual of the dots ``mask`` (K,) integrated
    alone, their labels moved by ``shift`` (2,) dots (NaN, or
    :class:`~wai_core.errors.RestorationFailed`, where no surface can be made).

    Examples
    --------
    >>> import numpy as np
    >>> block = np.array([(i, j) for i in range(6) for j in range(6)])
    >>> ij = np.vstack([block, [(6, 2), (7, 2)], block + (8, 0)])
    >>> drop, gains = misplaced_parts(ij, lambda m, s: 1.0 + abs(s[0] - 3) + abs(s[1]))
    >>> int(drop.sum()), gains
    (38, [4.0])
    """
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    drop = np.zeros(len(ij), bool)
    gains = []
    shifts = [np.array((di, dj)) for di in range(-SHIFT_REACH[0], SHIFT_REACH[0] + 1)
              for dj in range(-SHIFT_REACH[1], SHIFT_REACH[1] + 1)]
    for part, neck in necked_parts(ij):
        residuals = []
        for shift in shifts:
            try:
                residuals.append(float(residual_of(part, shift)))
            except (RestorationFailed, WaiInputError):  # no surface: no candidate
                residuals.append(np.nan)
        own = residuals[len(shifts) // 2]
        lowest = np.nanmin(residuals) if np.isfinite(residuals).any() else np.nan
        if not (np.isfinite(own) and lowest > 0):
            continue
        gains.append(float(own / lowest))
        if own / lowest > MAX_SHIFT_GAIN:
            drop |= part | neck
    return drop, gains
