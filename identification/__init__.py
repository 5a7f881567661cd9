"""Hammerstein identification of the piezo bender (ICINCO 2024 paper, section 3.4).

- :mod:`identification.arx`: the ARX model with uniformly bounded noise (eq. 20).
- :mod:`identification.estimation`: ``fit_arx`` with the recursive approximate Bayesian
  estimator (``"bayes-uniform"``), the exact MAP (``"chebyshev"``) and least squares.
- :mod:`identification.nls`: the neural static nonlinearity with memory features.
- :mod:`identification.hammerstein`: the model object the controllers use, saved as plain files.
- :mod:`identification.pipeline`: ``identify``, the paper's steps a-f on the environment.
- :mod:`identification.metrics`: fit %, RMSE, max error.
"""

from identification.arx import ARXModel, regressors
from identification.bayes_uniform import BayesUniformEstimator
from identification.estimation import METHODS, fit_arx, fit_chebyshev, fit_least_squares
from identification.features import FEATURE_SETS
from identification.hammerstein import HammersteinModel
from identification.metrics import fit_metrics, fit_percent, max_abs_error, rmse
from identification.nls import NLS, fit_nls
from identification.pipeline import IdentificationConfig, IdentificationResult, identify

__all__ = [
    "FEATURE_SETS",
    "METHODS",
    "NLS",
    "ARXModel",
    "BayesUniformEstimator",
    "HammersteinModel",
    "IdentificationConfig",
    "IdentificationResult",
    "fit_arx",
    "fit_chebyshev",
    "fit_least_squares",
    "fit_metrics",
    "fit_nls",
    "fit_percent",
    "identify",
    "max_abs_error",
    "regressors",
    "rmse",
]
