"""Hammerstein identification of the piezo bender (ICINCO 2024 paper, section 3.4).

- :mod:`identification.arx`: the ARX model with uniformly bounded noise (eq. 20).
- :mod:`identification.estimation`: ``fit_arx`` with the recursive approximate Bayesian
  estimator (``"bayes-uniform"``), the exact MAP (``"chebyshev"``) and least squares.
- :mod:`identification.nls`: the neural static nonlinearity with memory features.
- :mod:`identification.hammerstein`: the model object the controllers use, saved as plain files.
- :mod:`identification.pipeline`: ``identify``, the paper's steps a-f on the environment, and
  ``identify_records``, steps b-f on measured records (:mod:`identification.records`: the
  files a bench reads and writes), one function per step (:mod:`identification.steps`), with
  its settings (:mod:`identification.config`, ``IdentificationConfig``), its experiments
  (:mod:`identification.experiment`: ``collect`` drives the environment open loop), the inverse
  ARX model (:mod:`identification.inversion`), and its result, report and files
  (:mod:`identification.outputs`: ``IdentificationResult``, ``write_outputs``; the report's
  Markdown in :mod:`identification.report`, the figures in :mod:`identification.figures`).
- :mod:`identification.metrics`: fit %, RMSE, max error.

Importing the package is light: only the ARX model and the metrics load with it; every other name
is imported on first use (PEP 562). The pipeline (the environment model) loads only when
``identify`` or ``collect`` is used, torch only when an NLS is trained.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from identification.arx import ARXModel, regressors
from identification.metrics import fit_metrics, fit_percent, max_abs_error, rmse

if TYPE_CHECKING:
    from identification.bayes_uniform import BayesUniformEstimator
    from identification.config import IdentificationConfig
    from identification.estimation import METHODS, fit_arx, fit_chebyshev, fit_least_squares
    from identification.experiment import collect
    from identification.features import FEATURE_SETS
    from identification.hammerstein import HammersteinModel
    from identification.nls import NLS, fit_nls
    from identification.outputs import IdentificationResult, write_outputs
    from identification.pipeline import identify, identify_records

_LAZY = {
    "BayesUniformEstimator": "identification.bayes_uniform",
    "METHODS": "identification.estimation",
    "fit_arx": "identification.estimation",
    "fit_chebyshev": "identification.estimation",
    "fit_least_squares": "identification.estimation",
    "FEATURE_SETS": "identification.features",
    "HammersteinModel": "identification.hammerstein",
    "NLS": "identification.nls",
    "fit_nls": "identification.nls",
    "IdentificationConfig": "identification.config",
    "IdentificationResult": "identification.outputs",
    "collect": "identification.experiment",
    "identify": "identification.pipeline",
    "identify_records": "identification.pipeline",
    "write_outputs": "identification.outputs",
}

__all__ = [
    "FEATURE_SETS",
    "METHODS",
    "NLS",
    "ARXModel",
    "BayesUniformEstimator",
    "HammersteinModel",
    "IdentificationConfig",
    "IdentificationResult",
    "collect",
    "fit_arx",
    "fit_chebyshev",
    "fit_least_squares",
    "fit_metrics",
    "fit_nls",
    "fit_percent",
    "identify",
    "identify_records",
    "max_abs_error",
    "regressors",
    "rmse",
    "write_outputs",
]


def __getattr__(name: str) -> Any:
    """Import the pipeline and estimator names on first use (PEP 562)."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'identification' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
