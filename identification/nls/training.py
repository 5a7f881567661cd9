"""Training of the NLS network (paper section 3.4 e): :func:`fit_nls` and the torch module.

The only part of :mod:`identification.nls` that uses torch, imported inside the functions, so
that loading and evaluating a model never imports it.

:func:`fit_nls` runs its recipe as one function per step, in this order:

a. :func:`_check_training_args` (with :func:`_check_signals`, :func:`_loss_weights` and
   :func:`_input_range`): validated settings, data and input range;
b. :func:`_feature_map`: the memory features;
c. :func:`_normalisation`: features and ``z`` normalized on the training block;
d. :func:`_ridge_skip`: the affine start, a weighted ridge fit of ``z`` on the features;
e. :func:`_initial_network`: the torch network at the affine start, MLP output zero;
f. :func:`_train_adam`: Adam on mini-batches with early stopping on the validation block;
g. :func:`_refine_lbfgs`: optional full-batch L-BFGS, kept only if it validates better;
h. :func:`_training_record`: epochs, losses and wall time.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

from numpy.typing import ArrayLike

from identification.nls.network import NLS
from identification.nls.optimisation import (
    AdamResult,
    Objective,
    initial_network,
    refine_lbfgs,
    torch_threads,
    train_adam,
)
from identification.nls.torch_module import TorchNLS, load_torch
from identification.nls.training_data import feature_map_for, normalisation, ridge_skip
from identification.nls.training_settings import (
    TrainingSettings,
    check_signals,
    check_training_args,
    input_range,
    loss_weights,
)

__all__ = ["TorchNLS", "fit_nls"]  # TorchNLS: re-exported from its own module


def fit_nls(
    u: ArrayLike,
    z: ArrayLike,
    *,
    features: str = "play",
    n_play: int = 10,
    radii: ArrayLike | None = None,
    n_past: int = 5,
    n_bouc_wen: int = 8,
    levels: ArrayLike | None = None,
    hidden: Sequence[int] = (32, 32, 32),
    u_range: Sequence[float] | None = None,
    initial_input: float = 0.0,
    seed: int = 0,
    max_epochs: int = 200,
    batch_size: int = 1024,
    learning_rate: float = 1e-2,
    weight_decay: float = 0.0,
    validation_fraction: float = 0.2,
    patience: int = 25,
    lbfgs_iterations: int = 0,
    skip_ridge: float | None = None,
    z_weights: ArrayLike | None = None,
    num_threads: int = 1,
) -> NLS:
    """Fit the NLS network to input/hidden-signal data ``(u_t, z_t)`` (paper section 3.4 e).

    Training minimizes the (weighted) mean squared error of ``z`` on a contiguous training block;
    the last ``validation_fraction`` of the record (a contiguous block, never shuffled across
    time) is held out for early stopping, and the best-validating weights are kept. Adam on
    mini-batches (samples shuffled inside the training block: the features carry the memory), then
    optionally full-batch L-BFGS, kept only if it improves the validation loss. The affine skip
    term starts at the weighted least-squares fit and the MLP output at zero (see the module
    docstring), so a map affine in the features is learnt exactly.

    Deterministic: float64, a seeded ``torch.Generator`` for initialization and batches, and
    ``num_threads`` torch threads during training (the previous setting is restored).

    Parameters
    ----------
    u : array_like, shape (T,)
        Input voltage, V, starting from the rest state (memory at ``initial_input``).
    z : array_like, shape (T,)
        Hidden signal, equivalent V (e.g. estimated by the inverse ARX model).
    features : {"play", "past-inputs", "bouc-wen"}
        Memory feature set.
    n_play : int
        Number of play operators (``features="play"``), radii by :func:`default_play_radii`.
    radii : array_like, optional
        Explicit play radii, V (overrides ``n_play``).
    n_past : int
        Number of past inputs (``features="past-inputs"``).
    n_bouc_wen : int
        Number of Bouc-Wen operators (``features="bouc-wen"``), levels by
        :func:`default_bouc_wen_levels`.
    levels : array_like, optional
        Explicit Bouc-Wen saturation levels, V (overrides ``n_bouc_wen``).
    hidden : sequence of int
        Hidden-layer widths (three tanh layers in the paper).
    u_range : (float, float), optional
        Input range, V, for the play radii and as the inverse's default search range.
        Default: ``(min(u), max(u))``.
    initial_input : float
        Rest input, V: the memory state before ``u[0]``.
    seed : int
        Seed of the torch generator (initialization and batch order).
    max_epochs : int
        Maximum number of Adam epochs.
    batch_size : int
        Adam mini-batch size, samples.
    learning_rate : float
        Adam learning rate.
    weight_decay : float
        L2 penalty on the MLP weights (not on the affine skip), added to the loss.
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
        large cancelling weights that extrapolate wildly on faster inputs. Default: 1e-3 for
        play features (rate-independent, safe to extrapolate in rate), 1.0 for past inputs
        (their spread grows with the input's rate, so they get a strong prior towards ``u``).
    z_weights : array_like, shape (T,), optional
        Non-negative per-sample loss weights (e.g. inverse squared uncertainty of ``z``).
    num_threads : int
        Torch threads used during training.

    Returns
    -------
    NLS
        The fitted nonlinearity; ``nls.training`` records epochs, losses and wall time.
    """
    torch = load_torch()
    start = time.perf_counter()
    u_arr, z_arr = check_signals(u, z)
    settings = check_training_args(
        u_arr.size,
        features=features,
        hidden=hidden,
        max_epochs=max_epochs,
        batch_size=batch_size,
        learning_rate=learning_rate,
        weight_decay=weight_decay,
        validation_fraction=validation_fraction,
        patience=patience,
        lbfgs_iterations=lbfgs_iterations,
        skip_ridge=skip_ridge,
        num_threads=num_threads,
    )
    weights = loss_weights(z_weights, u_arr, settings.n_train)
    u_bounds = input_range(u_range, u_arr)
    feature_map = feature_map_for(
        settings.features,
        u_bounds,
        n_play=n_play,
        radii=radii,
        n_past=n_past,
        n_bouc_wen=n_bouc_wen,
        levels=levels,
        initial_input=initial_input,
    )
    data = normalisation(feature_map, u_arr, z_arr, settings.n_train)
    n_train = settings.n_train
    coef = ridge_skip(data.x[:n_train], data.t[:n_train], weights[:n_train], settings.skip_ridge)
    with torch_threads(settings.num_threads):
        # one generator: the hidden-layer initialisation draws first, then the batch orders
        generator = torch.Generator().manual_seed(int(seed))
        net = initial_network(feature_map.n_features, settings.hidden, data, coef, generator)
        objective = Objective(net, data, weights, settings)
        adam = train_adam(net, objective, settings, generator)
        best_loss, lbfgs_improved = refine_lbfgs(net, objective, settings, adam)
        params = TorchNLS.to_params(net)
        train_loss = objective.training_loss()
    training = _training_record(
        seed, settings, adam, best_loss, lbfgs_improved, train_loss, data.z_scale, start
    )
    return NLS(feature_map, params, u_range=u_bounds, training=training)


def _training_record(
    seed: int,
    settings: TrainingSettings,
    adam: AdamResult,
    best_loss: float,
    lbfgs_improved: bool,
    train_loss: float,
    z_scale: float,
    start: float,
) -> dict[str, Any]:
    """JSON-safe record of the run; losses back in equivalent V^2, wall time since ``start``."""
    return {
        "seed": int(seed),
        "n_train": int(settings.n_train),
        "n_validation": int(settings.n_validation),
        "epochs": int(adam.epochs),
        "best_epoch": int(adam.best_epoch),
        "lbfgs_improved": lbfgs_improved,
        "affine_validation_mse": adam.initial_loss * z_scale**2,
        "validation_mse": best_loss * z_scale**2,
        "train_mse": train_loss * z_scale**2,
        "wall_time_s": time.perf_counter() - start,
        "mse_unit": "equivalent V^2",
    }
