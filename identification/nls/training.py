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

import math
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.features import (
    FEATURE_SETS,
    BoucWenFeatures,
    FeatureMap,
    PastInputFeatures,
    PlayFeatures,
    _as_range,
    _as_scalar,
    _as_signal,
    default_bouc_wen_levels,
    default_play_radii,
)
from identification.nls.network import NLS
from identification.nls.torch_module import TorchNLS, load_torch

__all__ = ["TorchNLS", "fit_nls"]  # TorchNLS: re-exported from its own module


# ---------------------------------------------------------------------------------------------
# fit_nls: the recipe


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
    u_arr, z_arr = _check_signals(u, z)
    settings = _check_training_args(
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
    weights = _loss_weights(z_weights, u_arr, settings.n_train)
    input_range = _input_range(u_range, u_arr)
    feature_map = _feature_map(
        settings.features,
        input_range,
        n_play=n_play,
        radii=radii,
        n_past=n_past,
        n_bouc_wen=n_bouc_wen,
        levels=levels,
        initial_input=initial_input,
    )
    data = _normalisation(feature_map, u_arr, z_arr, settings.n_train)
    n_train = settings.n_train
    coef = _ridge_skip(data.x[:n_train], data.t[:n_train], weights[:n_train], settings.skip_ridge)
    with _torch_threads(settings.num_threads):
        # one generator: the hidden-layer initialisation draws first, then the batch orders
        generator = torch.Generator().manual_seed(int(seed))
        net = _initial_network(feature_map.n_features, settings.hidden, data, coef, generator)
        objective = _Objective(net, data, weights, settings)
        adam = _train_adam(net, objective, settings, generator)
        best_loss, lbfgs_improved = _refine_lbfgs(net, objective, settings, adam)
        params = TorchNLS.to_params(net)
        train_loss = objective.training_loss()
    training = _training_record(
        seed, settings, adam, best_loss, lbfgs_improved, train_loss, data.z_scale, start
    )
    return NLS(feature_map, params, u_range=input_range, training=training)


# ---------------------------------------------------------------------------------------------
# step a: argument checks


@dataclass(frozen=True)
class _TrainingSettings:
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


def _positive_int(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def _check_signals(u: ArrayLike, z: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Return ``u`` and ``z`` as finite float64 arrays of one length, or raise a ValueError."""
    u_arr = _as_signal("u", u)
    z_arr = _as_signal("z", z)
    if u_arr.shape != z_arr.shape:
        raise ValueError(f"u and z must have the same length; got {u_arr.size} and {z_arr.size}")
    return u_arr, z_arr


def _check_training_args(
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
) -> _TrainingSettings:
    """Validate the training settings of :func:`fit_nls` (same meanings) for ``n_samples``.

    Raises
    ------
    ValueError
        Naming the first invalid setting, in the order of :func:`fit_nls`'s parameters.
    """
    if features not in FEATURE_SETS:
        raise ValueError(f"features must be one of {FEATURE_SETS}; got {features!r}")
    hidden_t = tuple(_positive_int("hidden width", h) for h in hidden)
    if not hidden_t:
        raise ValueError("hidden must list at least one layer width")
    max_epochs = _positive_int("max_epochs", max_epochs, 0)
    batch_size = _positive_int("batch_size", batch_size)
    patience = _positive_int("patience", patience)
    lbfgs_iterations = _positive_int("lbfgs_iterations", lbfgs_iterations, 0)
    num_threads = _positive_int("num_threads", num_threads)
    learning_rate = _as_scalar("learning_rate", learning_rate)
    weight_decay = _as_scalar("weight_decay", weight_decay)
    if skip_ridge is None:
        skip_ridge = 1.0 if features == "past-inputs" else 1e-3
    skip_ridge = _as_scalar("skip_ridge", skip_ridge)
    if skip_ridge < 0.0:
        raise ValueError(f"skip_ridge must be >= 0; got {skip_ridge}")
    if learning_rate <= 0.0 or weight_decay < 0.0:
        raise ValueError("learning_rate must be > 0 and weight_decay >= 0")
    n_train, n_validation = _split(n_samples, validation_fraction)
    return _TrainingSettings(
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


def _split(n_samples: int, validation_fraction: float) -> tuple[int, int]:
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


def _loss_weights(z_weights: ArrayLike | None, u: np.ndarray, n_train: int) -> np.ndarray:
    """Per-sample loss weights, ones or ``z_weights`` scaled to mean 1 on the training block."""
    if z_weights is None:
        return np.ones(u.size)
    weights = _as_signal("z_weights", z_weights)
    if weights.shape != u.shape or np.any(weights < 0.0):
        raise ValueError("z_weights must be non-negative with the same length as u")
    if weights[:n_train].sum() <= 0.0:
        raise ValueError("z_weights are all zero on the training block")
    return weights / weights[:n_train].mean()


def _input_range(u_range: Sequence[float] | None, u: np.ndarray) -> tuple[float, float]:
    """The input range, V: ``u_range`` checked, or ``(min(u), max(u))`` if it is None."""
    if u_range is None:
        if np.ptp(u) == 0.0:
            raise ValueError("u is constant; give u_range or an input that varies")
        u_range = (float(u.min()), float(u.max()))
    return _as_range("u_range", u_range)


# ---------------------------------------------------------------------------------------------
# steps b-d: features, normalisation, affine start


def _feature_map(
    features: str,
    u_range: tuple[float, float],
    *,
    n_play: int,
    radii: ArrayLike | None,
    n_past: int,
    n_bouc_wen: int,
    levels: ArrayLike | None,
    initial_input: float,
) -> FeatureMap:
    """The memory feature map named by ``features`` (parameters as in :func:`fit_nls`)."""
    if features == "play":
        r = default_play_radii(u_range, n_play) if radii is None else np.asarray(radii, float)
        return PlayFeatures(radii=tuple(np.sort(r)), initial_input=initial_input)
    if features == "bouc-wen":
        lv = default_bouc_wen_levels(u_range, n_bouc_wen) if levels is None else levels
        return BoucWenFeatures(
            levels=tuple(np.sort(np.asarray(lv, float))), initial_input=initial_input
        )
    return PastInputFeatures(n_past=n_past, initial_input=initial_input)


@dataclass(frozen=True, eq=False)
class _Normalised:
    """Features and target in the network's normalized coordinates, with the normalization.

    Attributes
    ----------
    x : numpy.ndarray, shape (T, n_f)
        Normalized features ``(F - feature_mean) / feature_scale`` of the whole record.
    t : numpy.ndarray, shape (T,)
        Normalized target ``(z - z_mean) / z_scale``.
    feature_mean, feature_scale : numpy.ndarray, shape (n_f,)
        Feature mean and standard deviation on the training block (1 where constant), V.
    z_mean, z_scale : float
        Mean and standard deviation of ``z`` on the training block (1 if constant), equiv. V.
    """

    x: np.ndarray
    t: np.ndarray
    feature_mean: np.ndarray
    feature_scale: np.ndarray
    z_mean: float
    z_scale: float


def _normalisation(
    feature_map: FeatureMap, u: np.ndarray, z: np.ndarray, n_train: int
) -> _Normalised:
    """Features of ``u`` from rest, and features and ``z`` normalized on the training block."""
    feats, _ = feature_map.features(u, feature_map.initial_state())
    f_train, z_train = feats[:n_train], z[:n_train]
    feature_mean = f_train.mean(axis=0)
    feature_scale = f_train.std(axis=0)
    feature_scale[feature_scale < 1e-12] = 1.0
    z_mean = float(z_train.mean())
    z_scale = float(z_train.std()) or 1.0
    x = (feats - feature_mean) / feature_scale
    t = (z - z_mean) / z_scale
    return _Normalised(x, t, feature_mean, feature_scale, z_mean, z_scale)


def _ridge_skip(x: np.ndarray, t: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted ridge fit ``t ~ x @ coef[:-1] + coef[-1]``; column 0 (u) and the offset free."""
    n, n_f = x.shape
    design = np.column_stack([x, np.ones(n)])
    gram = design.T @ (design * w[:, None])
    rhs = design.T @ (w * t)
    penalty = np.full(n_f + 1, ridge * float(w.sum()))
    penalty[0] = penalty[-1] = 0.0
    return np.linalg.lstsq(gram + np.diag(penalty), rhs, rcond=None)[0]


# ---------------------------------------------------------------------------------------------
# steps e-g: torch network, Adam with early stopping, L-BFGS


@contextmanager
def _torch_threads(num_threads: int) -> Iterator[None]:
    """Run the block with ``num_threads`` torch threads; restore the previous number after."""
    torch = load_torch()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)


def _initial_network(
    n_features: int, hidden: tuple[int, ...], data: _Normalised, coef: np.ndarray, generator: Any
) -> Any:
    """The torch network at the affine start: skip = ``coef``, MLP output zero.

    Hidden layers get Glorot-uniform weights drawn from ``generator`` (layer by layer) and zero
    biases; the normalization buffers hold ``data``'s statistics.
    """
    torch = load_torch()
    net = TorchNLS.build(n_features, hidden)
    with torch.no_grad():
        for layer in net.layers:
            bound = math.sqrt(6.0 / (layer.in_features + layer.out_features))
            layer.weight.uniform_(-bound, bound, generator=generator)
            layer.bias.zero_()
        net.out.weight.zero_()
        net.out.bias.zero_()
        net.skip.weight.copy_(torch.from_numpy(coef[:-1][None, :]))
        net.skip.bias.fill_(float(coef[-1]))
        net.feature_mean.copy_(torch.from_numpy(data.feature_mean))
        net.feature_scale.copy_(torch.from_numpy(data.feature_scale))
        net.z_mean.fill_(data.z_mean)
        net.z_scale.fill_(data.z_scale)
    return net


class _Objective:
    """Weighted mean squared error of ``net`` in normalized units, on the two blocks.

    ``train`` and ``validation`` hold the ``(x, t, w)`` tensors of the training and validation
    blocks (views of the numpy arrays). The validation loss is the training loss when there is
    no validation block. The L2 penalty covers the MLP weights only, never the affine skip.
    """

    def __init__(
        self, net: Any, data: _Normalised, weights: np.ndarray, settings: _TrainingSettings
    ) -> None:
        torch = load_torch()
        x = torch.from_numpy(data.x)
        t = torch.from_numpy(data.t)
        w = torch.from_numpy(weights)
        n_train = settings.n_train
        self.net = net
        self.train = (x[:n_train], t[:n_train], w[:n_train])
        self.validation = (x[n_train:], t[n_train:], w[n_train:])
        self.has_validation = settings.n_validation > 0
        self.weight_decay = settings.weight_decay
        self.mlp_params = [p for m in (*net.layers, net.out) for p in m.parameters()]

    def data_loss(self, xb: Any, tb: Any, wb: Any) -> Any:
        """Weighted MSE of the normalized output on the samples ``(xb, tb, wb)`` (a tensor)."""
        return load_torch().mean(wb * (self.net.normalized(xb) - tb) ** 2)

    def penalised_loss(self, xb: Any, tb: Any, wb: Any) -> Any:
        """The data loss plus the L2 penalty on the MLP weights (if any): what is minimized."""
        loss = self.data_loss(xb, tb, wb)
        if self.weight_decay:
            torch = load_torch()
            loss = loss + self.weight_decay * sum(torch.sum(p**2) for p in self.mlp_params)
        return loss

    def validation_loss(self) -> float:
        """Data loss on the validation block (on the training block if there is none)."""
        with load_torch().no_grad():
            if not self.has_validation:
                return float(self.data_loss(*self.train))
            return float(self.data_loss(*self.validation))

    def training_loss(self) -> float:
        """Data loss on the training block."""
        with load_torch().no_grad():
            return float(self.data_loss(*self.train))


@dataclass(frozen=True, eq=False)
class _AdamResult:
    """Outcome of :func:`_train_adam`; losses in normalized units.

    Attributes
    ----------
    initial_loss : float
        Validation loss of the affine start.
    best_loss : float
        Best validation loss, that of ``best_state``.
    best_epoch : int
        Epoch of ``best_state`` (0: the affine start).
    epochs : int
        Epochs run.
    best_state : dict
        State dict of the best-validating network (loaded into the network).
    """

    initial_loss: float
    best_loss: float
    best_epoch: int
    epochs: int
    best_state: dict[str, Any]


def _train_adam(
    net: Any, objective: _Objective, settings: _TrainingSettings, generator: Any
) -> _AdamResult:
    """Adam epochs with early stopping; leaves ``net`` at its best-validating weights.

    Each epoch draws a permutation of the training block from ``generator`` and takes one
    step per mini-batch; training stops after ``patience`` epochs without improvement of the
    validation loss (never without a validation block).
    """
    torch = load_torch()
    optimizer = torch.optim.Adam(net.parameters(), lr=settings.learning_rate)
    best_loss = objective.validation_loss()
    initial_loss = best_loss
    best_state = _state_copy(net)
    best_epoch = 0
    epochs_run = 0
    for epoch in range(1, settings.max_epochs + 1):
        epochs_run = epoch
        order = torch.randperm(settings.n_train, generator=generator)
        _adam_epoch(optimizer, objective, order, settings.batch_size)
        current = objective.validation_loss()
        if current < best_loss:
            best_loss, best_epoch = current, epoch
            best_state = _state_copy(net)
        elif settings.n_validation > 0 and epoch - best_epoch >= settings.patience:
            break
    net.load_state_dict(best_state)
    return _AdamResult(initial_loss, best_loss, best_epoch, epochs_run, best_state)


def _adam_epoch(optimizer: Any, objective: _Objective, order: Any, batch_size: int) -> None:
    """One Adam step per mini-batch of the training block, in the sample ``order`` given."""
    x_tr, t_tr, w_tr = objective.train
    for i in range(0, order.numel(), batch_size):
        idx = order[i : i + batch_size]
        optimizer.zero_grad()
        loss = objective.penalised_loss(x_tr[idx], t_tr[idx], w_tr[idx])
        loss.backward()
        optimizer.step()


def _state_copy(net: Any) -> dict[str, Any]:
    """A detached copy of ``net``'s state dict."""
    return {k: v.clone() for k, v in net.state_dict().items()}


def _refine_lbfgs(
    net: Any, objective: _Objective, settings: _TrainingSettings, adam: _AdamResult
) -> tuple[float, bool]:
    """Full-batch L-BFGS from the Adam result, kept only if it lowers the validation loss.

    Returns
    -------
    best_loss : float
        Validation loss of the network ``net`` is left with (normalized units).
    improved : bool
        Whether L-BFGS ran and was kept (otherwise ``net`` holds the Adam result).
    """
    if not settings.lbfgs_iterations:
        return adam.best_loss, False
    torch = load_torch()
    lbfgs = torch.optim.LBFGS(
        net.parameters(),
        max_iter=settings.lbfgs_iterations,
        history_size=20,
        line_search_fn="strong_wolfe",
    )

    def closure() -> Any:
        lbfgs.zero_grad()
        loss = objective.penalised_loss(*objective.train)
        loss.backward()
        return loss

    lbfgs.step(closure)
    current = objective.validation_loss()
    if math.isfinite(current) and current < adam.best_loss:
        return current, True
    net.load_state_dict(adam.best_state)
    return adam.best_loss, False


# ---------------------------------------------------------------------------------------------
# step h: training record


def _training_record(
    seed: int,
    settings: _TrainingSettings,
    adam: _AdamResult,
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
