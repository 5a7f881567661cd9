"""Small hand-made models the tests share."""

from __future__ import annotations

import numpy as np

from identification.features import PastInputFeatures
from identification.nls import NLS


def handmade_nls(out_weight: float) -> NLS:
    """z = u + out_weight * tanh(u) on +-5 V with identity normalization (past-input features).

    Monotone in u for out_weight > -1, not monotone below.
    """
    params = {
        "feature_mean": np.zeros(2),
        "feature_scale": np.ones(2),
        "z_mean": np.array(0.0),
        "z_scale": np.array(1.0),
        "layer0_weight": np.array([[1.0, 0.0]]),
        "layer0_bias": np.zeros(1),
        "out_weight": np.array([out_weight]),
        "out_bias": np.array(0.0),
        "skip_weight": np.array([1.0, 0.0]),
        "skip_bias": np.array(0.0),
    }
    return NLS(PastInputFeatures(n_past=1), params, u_range=(-5.0, 5.0))
