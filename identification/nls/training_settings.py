"""The settings of :func:`identification.nls.fit_nls`, and its data, checked."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from identification.arguments import as_range, as_signal
from identification.features import FEATURE_SETS
from piezo_env.checks import require_int, require_number

__all__ = [
    "TrainingSettings",
    "check_signals",
    "input_range",
    "loss_weights",
    "split_record",
]


@dataclass(frozen=True)
class TrainingSettings:
    """Settings of one :func:`~identification.nls.fit_nls` run, validated at construction.

    Attributes
    ----------
    features : {"play", "past-inputs", "bouc-wen"}
        Memory feature set, one of :data:`~identification.features.FEATURE_SETS`.
    n_play : int
        Number of play operators (``features="play"``), radii by
        :func:`~identification.features.default_play_radii`.
    radii : sequence of float, optional
        Explicit play radii, V (overrides ``n_play``).
    n_past : int
        Number of past inputs (``features="past-inputs"``).
    n_bouc_wen : int
        Number of Bouc-Wen operators (``features="bouc-wen"``), levels by
        :func:`~identification.features.default_bouc_wen_levels` (16, as
        :func:`identification.identify` uses).
    levels : sequence of float, optional
        Explicit Bouc-Wen saturation levels, V (overrides ``n_bouc_wen``).
    hidden : tuple of int
        Hidden-layer widths, at least one (three tanh layers in the paper). The default 3 x 32
        learns a hysteresis that the features do not represent exactly (a Prandtl-Ishlinskii
        loop with a cubic term); :func:`identification.identify` trains a 3 x 2 network
        instead, whose residual errors cost the MPC less (why:
        :class:`~identification.config.IdentificationConfig`; the closed-loop comparison:
        ``benchmarks/results/identification_precision.md``).
    u_range : (float, float), optional
        Input range, V, for the play radii and as the inverse's default search range.
        Default: ``(min(u), max(u))`` of the training record.
    initial_input : float
        Rest input, V: the memory state before ``u[0]``.
    seed : int
        Seed of the torch generator (initialization and batch order).
    max_epochs : int
        Maximum number of Adam epochs (>= 0).
    batch_size : int
        Adam mini-batch size, samples.
    learning_rate : float
        Adam learning rate (> 0).
    weight_decay : float
        L2 penalty on the MLP weights (not on the affine skip), added to the loss (>= 0).
    validation_fraction : float
        Fraction of samples held out at the end, in [0, 0.9]; 0 trains ``max_epochs`` epochs
        without early stopping.
    patience : int
        Epochs without validation improvement before stopping.
    lbfgs_iterations : int
        Full-batch L-BFGS iterations after Adam (0: none).
    skip_ridge : float, optional
        Ridge penalty (relative, on normalized features) of the memory features' weights in the
        initial affine skip; the weight of ``u`` itself is not penalized, so the identity stays
        exact. It keeps nearly collinear features (past inputs of a slow signal) from getting
        large cancelling weights that extrapolate wildly on faster inputs. Default (None,
        resolved at construction): 1e-3 for play and Bouc-Wen features (rate-independent, safe
        to extrapolate in rate), 1.0 for past inputs (their spread grows with the input's rate,
        so they get a strong prior towards ``u``).
    num_threads : int
        Torch threads used during training (the previous setting is restored after).
    """

    features: str = "play"
    n_play: int = 10
    radii: Sequence[float] | None = None
    n_past: int = 5
    n_bouc_wen: int = 16
    levels: Sequence[float] | None = None
    hidden: Sequence[int] = (32, 32, 32)
    u_range: Sequence[float] | None = None
    initial_input: float = 0.0
    seed: int = 0
    max_epochs: int = 200
    batch_size: int = 1024
    learning_rate: float = 1e-2
    weight_decay: float = 0.0
    validation_fraction: float = 0.2
    patience: int = 25
    lbfgs_iterations: int = 0
    skip_ridge: float | None = None
    num_threads: int = 1

    def __post_init__(self) -> None:
        if self.features not in FEATURE_SETS:
            raise ValueError(f"features must be one of {FEATURE_SETS}; got {self.features!r}")
        hidden = tuple(require_int("hidden width", h) for h in self.hidden)
        if not hidden:
            raise ValueError("hidden must list at least one layer width")
        object.__setattr__(self, "hidden", hidden)
        for name, minimum in (
            ("max_epochs", 0),
            ("batch_size", 1),
            ("patience", 1),
            ("lbfgs_iterations", 0),
            ("num_threads", 1),
        ):
            object.__setattr__(self, name, require_int(name, getattr(self, name), minimum=minimum))
        self._check_numbers()
        if self.u_range is not None:
            object.__setattr__(self, "u_range", as_range("u_range", self.u_range))

    def _check_numbers(self) -> None:
        """Check the real-valued settings, resolving the default ``skip_ridge``."""
        if self.skip_ridge is None:
            object.__setattr__(self, "skip_ridge", 1.0 if self.features == "past-inputs" else 1e-3)
        for name, low, high, low_open in (
            ("learning_rate", 0.0, None, True),
            ("weight_decay", 0.0, None, False),
            ("skip_ridge", 0.0, None, False),
            ("validation_fraction", 0.0, 0.9, False),
        ):
            value = require_number(name, getattr(self, name), low=low, high=high, low_open=low_open)
            object.__setattr__(self, name, value)


def check_signals(u: ArrayLike, z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Return ``u`` and ``z`` as finite float64 arrays of one length, or raise a ValueError."""
    u_arr = as_signal("u", u)
    z_arr = as_signal("z", z)
    if u_arr.shape != z_arr.shape:
        raise ValueError(f"u and z must have the same length; got {u_arr.size} and {z_arr.size}")
    return u_arr, z_arr


def split_record(n_samples: int, validation_fraction: float) -> tuple[int, int]:
    """Sizes ``(n_train, n_validation)`` of the contiguous training and validation blocks."""
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
    weights = as_signal("z_weights", z_weights)
    if weights.shape != u.shape or np.any(weights < 0.0):
        raise ValueError("z_weights must be non-negative with the same length as u")
    if weights[:n_train].sum() <= 0.0:
        raise ValueError("z_weights are all zero on the training block")
    return weights / weights[:n_train].mean()


def input_range(u_range: tuple[float, float] | None, u: np.ndarray) -> tuple[float, float]:
    """The input range, V: ``u_range`` (already checked), or ``(min(u), max(u))`` if None."""
    if u_range is not None:
        return u_range
    if np.ptp(u) == 0.0:
        raise ValueError("u is constant; give u_range or an input that varies")
    return float(u.min()), float(u.max())
