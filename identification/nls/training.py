"""Training of the NLS network (paper section 3.4 e): :func:`fit_nls`.

The only part of :mod:`identification.nls` that uses torch (through
:mod:`~identification.nls.optimisation`, which imports it inside its functions), so that loading
and evaluating a model never imports it. :func:`fit_nls` runs its recipe as one function per
step, in this order:

a. :class:`~identification.nls.training_settings.TrainingSettings` (validated at construction),
   :func:`~identification.nls.training_settings.check_signals`,
   :func:`~identification.nls.training_settings.split_record`,
   :func:`~identification.nls.training_settings.loss_weights` and
   :func:`~identification.nls.training_settings.input_range`: settings, data and input range;
b. :func:`~identification.nls.training_data.feature_map_for`: the memory features;
c. :func:`~identification.nls.training_data.normalisation`: features and ``z`` normalized on the
   training block;
d. :func:`~identification.nls.training_data.ridge_skip`: the affine start, a weighted ridge fit
   of ``z`` on the features;
e. :func:`~identification.nls.optimisation.train_network`: the torch network at the affine start
   (MLP output zero), Adam on mini-batches with early stopping on the validation block, and
   optional full-batch L-BFGS, kept only if it validates better;
f. :func:`training_record`: epochs, losses and wall time.
"""

from __future__ import annotations

import time
from typing import Any

from numpy.typing import ArrayLike

from identification.nls.network import NLS
from identification.nls.optimisation import TrainedNetwork, train_network
from identification.nls.training_data import feature_map_for, normalisation, ridge_skip
from identification.nls.training_settings import (
    TrainingSettings,
    check_signals,
    input_range,
    loss_weights,
    split_record,
)

__all__ = ["fit_nls", "training_record"]


def fit_nls(
    u: ArrayLike,
    z: ArrayLike,
    *,
    z_weights: ArrayLike | None = None,
    settings: TrainingSettings | None = None,
    **overrides: Any,
) -> NLS:
    """Fit the NLS network to input/hidden-signal data ``(u_t, z_t)`` (paper section 3.4 e).

    Training minimizes the (weighted) mean squared error of ``z`` on a contiguous training block;
    the last ``validation_fraction`` of the record (a contiguous block, never shuffled across
    time) is held out for early stopping, and the best-validating weights are kept. Adam on
    mini-batches (samples shuffled inside the training block: the features carry the memory), then
    optionally full-batch L-BFGS, kept only if it improves the validation loss. The affine skip
    term starts at the weighted least-squares fit and the MLP output at zero (see
    :mod:`identification.nls.network`), so a map affine in the features is learnt exactly.

    Deterministic: float64, a seeded ``torch.Generator`` for initialization and batches, and
    ``num_threads`` torch threads during training (the previous setting is restored).

    Parameters
    ----------
    u : array_like, shape (T,)
        Input voltage, V, starting from the rest state (memory at ``initial_input``).
    z : array_like, shape (T,)
        Hidden signal, equivalent V (e.g. estimated by the inverse ARX model).
    z_weights : array_like, shape (T,), optional
        Non-negative per-sample loss weights (e.g. inverse squared uncertainty of ``z``).
    settings : TrainingSettings, optional
        All training settings (features, network, optimiser); keyword ``overrides`` (its field
        names, e.g. ``features="bouc-wen", max_epochs=50``) build one when it is not given.

    Returns
    -------
    NLS
        The fitted nonlinearity; ``nls.training`` records epochs, losses and wall time.

    Raises
    ------
    ValueError
        On an invalid setting, non-finite or mismatched data, or too few samples.
    """
    if settings is None:
        settings = TrainingSettings(**overrides)
    elif overrides:
        raise ValueError("pass either settings or keyword overrides, not both")
    start = time.perf_counter()
    u_arr, z_arr = check_signals(u, z)
    n_train, _ = split_record(u_arr.size, settings.validation_fraction)
    weights = loss_weights(z_weights, u_arr, n_train)
    u_bounds = input_range(settings.u_range, u_arr)
    feature_map = feature_map_for(settings, u_bounds)
    data = normalisation(feature_map, u_arr, z_arr, n_train)
    coef = ridge_skip(data.x[:n_train], data.t[:n_train], weights[:n_train], settings.skip_ridge)
    trained = train_network(data, weights, coef, settings, n_train)
    record = training_record(settings, trained, n_train, u_arr.size, data.z_scale, start)
    return NLS(feature_map, trained.params, u_range=u_bounds, training=record)


def training_record(
    settings: TrainingSettings,
    trained: TrainedNetwork,
    n_train: int,
    n_samples: int,
    z_scale: float,
    start: float,
) -> dict[str, Any]:
    """JSON-safe record of the run; losses back in equivalent V^2, wall time since ``start``."""
    return {
        "seed": int(settings.seed),
        "n_train": int(n_train),
        "n_validation": int(n_samples - n_train),
        "epochs": int(trained.adam.epochs),
        "best_epoch": int(trained.adam.best_epoch),
        "lbfgs_improved": trained.lbfgs_improved,
        "affine_validation_mse": trained.adam.initial_loss * z_scale**2,
        "validation_mse": trained.validation_loss * z_scale**2,
        "train_mse": trained.train_loss * z_scale**2,
        "wall_time_s": time.perf_counter() - start,
        "mse_unit": "equivalent V^2",
    }
