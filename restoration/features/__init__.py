"""Pattern features on camera s and their correspondence with the projector's dot grid.

The paper (Jian et al. 2022, section 3.2.1) needs, for every projected dot ``k``, its spot
``s_k`` on the diffuser in the wavy image and the dot's grid index, so that the projector ray
``v_k^p`` is known; section 4.2 (eq. 33) states when ordering alone can make this
correspondence. The stage's modules:

- :mod:`~restoration.features.detect`: detect the spots with sub-pixel centres
  (:func:`detect_spots`), at pixel scales set by the calibrated spot size
  (:class:`SpotScales`, built once per rig).
- :mod:`~restoration.features.reference`: predict the flat-water spots from calibration
  (:func:`predict_flat_spots`, of any grid node: :func:`node_flat_px`) and label the
  flat-water spots with grid indices (:func:`match_reference`, :func:`prepare_reference`);
  the calibrated spot size that
  sets every pixel-scale constant (:func:`spot_sigma_px`). The prepared
  :class:`ReferenceGrid` holds all the per-frame steps need of the rig.
- :mod:`~restoration.features.match`: label the wavy-water spots by region growing, the
  ordering check and anchoring (:func:`match_distorted`); per frame
  (:func:`features_from_reference`) or all steps at once (:func:`find_features`).
- :mod:`~restoration.features.decode`: label the spots of the coded pattern
  (``[pattern] code = "colour"``) by their colour windows, without ordering
  (:func:`decode_distorted`, :func:`features_from_code`).
- ``_lattice``, ``_outline``, ``_types``: private helpers shared by the above.
"""

from restoration.features.decode import Decoded, decode_distorted, features_from_code
from restoration.features.detect import Spots, SpotScales, detect_spots
from restoration.features.match import (
    REGROW_BELOW,
    Matches,
    features_from_reference,
    find_features,
    match_distorted,
)
from restoration.features.ordering import order_violations
from restoration.features.reference import (
    ReferenceGrid,
    flag_diffuser_edge,
    flat_shifts,
    match_reference,
    node_flat_px,
    predict_flat_spots,
    prepare_reference,
    spot_sigma_px,
)
from restoration.features.symbols import node_symbols, spot_symbols

__all__ = [
    "REGROW_BELOW",
    "Decoded",
    "Matches",
    "ReferenceGrid",
    "SpotScales",
    "Spots",
    "decode_distorted",
    "detect_spots",
    "features_from_code",
    "features_from_reference",
    "find_features",
    "flag_diffuser_edge",
    "flat_shifts",
    "match_distorted",
    "match_reference",
    "node_flat_px",
    "node_symbols",
    "order_violations",
    "predict_flat_spots",
    "prepare_reference",
    "spot_sigma_px",
    "spot_symbols",
]
