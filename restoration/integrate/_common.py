"""Definitions shared by the modules of :mod:`restoration.integrate`: array type aliases and the
input limits that integration and gridding both enforce (fewest samples, largest grid)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

MIN_SAMPLES = 4
"""Fewest samples that integration and gridding accept."""

# Largest (i, j) index span, and largest output grid, accepted (a dot pattern has ~10^3 dots).
_MAX_GRID_NODES = 4_000_000
