"""Step a of :func:`identification.nls.fit_nls`: the training settings and data, checked."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from identification.features import (
    FEATURE_SETS,
    _as_range,
    _as_scalar,
    _as_signal,
)

__all__ = [
    "TrainingSettings",
    "check_signals",
    "check_training_args",
    "input_range",
    "loss_weights",
    "positive_int",
    "split_record",
]


@dataclass(frozen=True)
class TrainingSettings:
    """Validated training settings of one :func:`fit_nls` run (units as in its parameters).

    Attributes
    ----------
    features : str
        Memory feature set, one of :data:`~identification.features.FEATURE_SETS`.
    hidden : tuple of int
        Hidden-layer widths, at least one.
    max_epochs : int
        Maximum number of Adam epochs (>= 0).
    batch_size : int
        Adam mini-batch size, samples.
    learning_rate : float
        Adam learning rate (> 0).
    weight_decay : float
        L2 penalty on the MLP weights (>= 0).
    patience : int
        Epochs without validation improvement before stopping.
    lbfgs_iterations : int
        Full-batch L-BFGS iterations after Adam (0: none).
    skip_ridge : float
        Ridge penalty of the memory features in the initial affine skip (default resolved).
    num_threads : int
        Torch threads during training.
    n_train : int
        Samples in the training block, the first ``n_train`` of the record.
    n_validation : int
        Samples in the validation block, the last ``n_validation`` (0: no early stopping).
    """

    features: str
    hidden: tuple[int, ...]
    max_epochs: int
    batch_size: int
    learning_rate: float
    weight_decay: float
    patience: int
    lbfgs_iterations: int
    skip_ridge: float
    num_threads: int
    n_train: int
    n_validation: int


def positive_int(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def check_signals(u: ArrayLike, z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Return ``u`` and ``z`` as finite float64 arrays of one length, or raise a ValueError."""
    u_arr = _as_signal("u", u)
    z_arr = _as_signal("z", z)
    if u_arr.shape != z_arr.shape:
        raise ValueError(f"u and z must have the same length; got {u_arr.size} and {z_arr.size}")
    return u_arr, z_arr


def check_training_args(
    n_samples: int,
    *,
    features: str,
    hidden: Sequence[int],
    max_epochs: int,
    batch_size: int,
    learning_rate: float,
    weight_decay: float,
    validation_fraction: float,
    patience: int,
    lbfgs_iterations: int,
    skip_ridge: float | None,
    num_threads: int,
) -> TrainingSettings:
    """Validate the training settings of :func:`fit_nls` (same meanings) for ``n_samples``.

    Raises
    ------
    ValueError
        Naming the first invalid setting, in the order of :func:`fit_nls`'s parameters.
    """
    if features not in FEATURE_SETS:
        raise ValueError(f"features must be one of {FEATURE_SETS}; got {features!r}")
    hidden_t = tuple(positive_int("hidden width", h) for h in hidden)
    if not hidden_t:
        raise ValueError("hidden must list at least one layer width")
    max_epochs = positive_int("max_epochs", max_epochs, 0)
    batch_size = positive_int("batch_size", batch_size)
    patience = positive_int("patience", patience)
    lbfgs_iterations = positive_int("lbfgs_iterations", lbfgs_iterations, 0)
    num_threads = positive_int("num_threads", num_threads)
    learning_rate = _as_scalar("learning_rate", learning_rate)
    weight_decay = _as_scalar("weight_decay", weight_decay)
    if skip_ridge is None:
        skip_ridge = 1.0 if features == "past-inputs" else 1e-3
    skip_ridge = _as_scalar("skip_ridge", skip_ridge)
    if skip_ridge < 0.0:
        raise ValueError(f"skip_ridge must be >= 0; got {skip_ridge}")
    if learning_rate <= 0.0 or weight_decay < 0.0:
        raise ValueError("learning_rate must be > 0 and weight_decay >= 0")
    n_train, n_validation = split_record(n_samples, validation_fraction)
    return TrainingSettings(
        features=features,
        hidden=hidden_t,
        max_epochs=max_epochs,
        batch_size=batch_size,
        learning_rate=learning_rate,
        weight_decay=weight_decay,
        patience=patience,
        lbfgs_iterations=lbfgs_iterations,
        skip_ridge=skip_ridge,
        num_threads=num_threads,
        n_train=n_train,
        n_validation=n_validation,
    )


def split_record(n_samples: int, validation_fraction: float) -> tuple[int, int]:
    """Sizes ``(n_train, n_validation)`` of the contiguous training and validation blocks."""
    validation_fraction = _as_scalar("validation_fraction", validation_fraction)
    if not 0.0 <= validation_fraction <= 0.9:
        raise ValueError(f"validation_fraction must be in [0, 0.9]; got {validation_fraction}")
    n_validation = round(validation_fraction * n_samples)
    n_train = n_samples - n_validation
    if n_train < 8 or (validation_fraction > 0.0 and n_validation < 2):
        raise ValueError(
            f"too few samples ({n_samples}) for a training block and a validation block "
            f"(validation_fraction={validation_fraction})"
        )
    return n_train, n_validation


def loss_weights(z_weights: ArrayLike | None, u: np.ndarray, n_train: int) -> np.ndarray:
    """Per-sample loss weights, ones or ``z_weights`` scaled to mean 1 on the training block."""
    if z_weights is None:
        return np.ones(u.size)
    weights = _as_signal("z_weights", z_weights)
    if weights.shape != u.shape or np.any(weights < 0.0):
        raise ValueError("z_weights must be non-negative with the same length as u")
    if weights[:n_train].sum() <= 0.0:
        raise ValueError("z_weights are all zero on the training block")
    return weights / weights[:n_train].mean()


def input_range(u_range: Sequence[float] | None, u: np.ndarray) -> tuple[float, float]:
    """The input range, V: ``u_range`` checked, or ``(min(u), max(u))`` if it is None."""
    if u_range is None:
        if np.ptp(u) == 0.0:
            raise ValueError("u is constant; give u_range or an input that varies")
        u_range = (float(u.min()), float(u.max()))
    return _as_range("u_range", u_range)
