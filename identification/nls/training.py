"""Training of the NLS network (paper section 3.4 e): :func:`fit_nls` and the torch module.

The only part of :mod:`identification.nls` that uses torch, imported inside the functions, so
that loading and evaluating a model never imports it.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
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

__all__ = ["TorchNLS", "fit_nls"]


# ---------------------------------------------------------------------------------------------
# torch network and training


def _torch() -> Any:
    import torch

    return torch


class TorchNLS:
    """Builders of the torch module (lazy: importing this module does not import torch)."""

    @staticmethod
    def build(n_features: int, hidden: Sequence[int]) -> Any:
        torch = _torch()
        nn = torch.nn

        class TorchNLS(nn.Module):
            """``z = z_m + z_s (w^T x + c + MLP(x))``, ``x = (F - m) / s``; float64."""

            def __init__(self) -> None:
                super().__init__()
                widths = [n_features, *hidden]
                self.layers = nn.ModuleList(
                    nn.Linear(a, b, dtype=torch.float64) for a, b in itertools.pairwise(widths)
                )
                self.out = nn.Linear(widths[-1], 1, dtype=torch.float64)
                self.skip = nn.Linear(n_features, 1, dtype=torch.float64)
                self.register_buffer("feature_mean", torch.zeros(n_features, dtype=torch.float64))
                self.register_buffer("feature_scale", torch.ones(n_features, dtype=torch.float64))
                self.register_buffer("z_mean", torch.zeros((), dtype=torch.float64))
                self.register_buffer("z_scale", torch.ones((), dtype=torch.float64))

            def normalized(self, x: Any) -> Any:
                h = x
                for layer in self.layers:
                    h = torch.tanh(layer(h))
                return (self.out(h) + self.skip(x)).squeeze(-1)

            def forward(self, features: Any) -> Any:
                x = (features - self.feature_mean) / self.feature_scale
                return self.z_mean + self.z_scale * self.normalized(x)

        return TorchNLS()

    @staticmethod
    def from_params(params: dict[str, np.ndarray]) -> Any:
        torch = _torch()
        n_layers = sum(1 for k in params if k.startswith("layer") and k.endswith("_weight"))
        hidden = [params[f"layer{i}_weight"].shape[0] for i in range(n_layers)]
        module = TorchNLS.build(params["feature_mean"].size, hidden)
        state = {
            "feature_mean": params["feature_mean"],
            "feature_scale": params["feature_scale"],
            "z_mean": params["z_mean"],
            "z_scale": params["z_scale"],
            "out.weight": params["out_weight"][None, :],
            "out.bias": params["out_bias"].reshape(1),
            "skip.weight": params["skip_weight"][None, :],
            "skip.bias": params["skip_bias"].reshape(1),
        }
        for i in range(n_layers):
            state[f"layers.{i}.weight"] = params[f"layer{i}_weight"]
            state[f"layers.{i}.bias"] = params[f"layer{i}_bias"]
        module.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()})
        return module

    @staticmethod
    def to_params(module: Any) -> dict[str, np.ndarray]:
        sd = {k: v.detach().numpy().astype(np.float64) for k, v in module.state_dict().items()}
        params = {
            "feature_mean": sd["feature_mean"],
            "feature_scale": sd["feature_scale"],
            "z_mean": sd["z_mean"].reshape(()),
            "z_scale": sd["z_scale"].reshape(()),
            "out_weight": sd["out.weight"].reshape(-1),
            "out_bias": sd["out.bias"].reshape(()),
            "skip_weight": sd["skip.weight"].reshape(-1),
            "skip_bias": sd["skip.bias"].reshape(()),
        }
        for i in range(len(module.layers)):
            params[f"layer{i}_weight"] = sd[f"layers.{i}.weight"]
            params[f"layer{i}_bias"] = sd[f"layers.{i}.bias"]
        return params


def _positive_int(name: str, value: int, minimum: int = 1) -> int:
    if isinstance(value, bool) or int(value) != value or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}; got {value!r}")
    return int(value)


def _ridge_skip(x: np.ndarray, t: np.ndarray, w: np.ndarray, ridge: float) -> np.ndarray:
    """Weighted ridge fit ``t ~ x @ coef[:-1] + coef[-1]``; column 0 (u) and the offset free."""
    n, n_f = x.shape
    design = np.column_stack([x, np.ones(n)])
    gram = design.T @ (design * w[:, None])
    rhs = design.T @ (w * t)
    penalty = np.full(n_f + 1, ridge * float(w.sum()))
    penalty[0] = penalty[-1] = 0.0
    return np.linalg.lstsq(gram + np.diag(penalty), rhs, rcond=None)[0]


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
    torch = _torch()
    start = time.perf_counter()
    u_arr = _as_signal("u", u)
    z_arr = _as_signal("z", z)
    if u_arr.shape != z_arr.shape:
        raise ValueError(f"u and z must have the same length; got {u_arr.size} and {z_arr.size}")
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
    validation_fraction = _as_scalar("validation_fraction", validation_fraction)
    if not 0.0 <= validation_fraction <= 0.9:
        raise ValueError(f"validation_fraction must be in [0, 0.9]; got {validation_fraction}")
    n = u_arr.size
    n_val = round(validation_fraction * n)
    n_train = n - n_val
    if n_train < 8 or (validation_fraction > 0.0 and n_val < 2):
        raise ValueError(
            f"too few samples ({n}) for a training block and a validation block "
            f"(validation_fraction={validation_fraction})"
        )
    if z_weights is None:
        weights = np.ones(n)
    else:
        weights = _as_signal("z_weights", z_weights)
        if weights.shape != u_arr.shape or np.any(weights < 0.0):
            raise ValueError("z_weights must be non-negative with the same length as u")
        if weights[:n_train].sum() <= 0.0:
            raise ValueError("z_weights are all zero on the training block")
        weights = weights / weights[:n_train].mean()
    if u_range is None:
        if np.ptp(u_arr) == 0.0:
            raise ValueError("u is constant; give u_range or an input that varies")
        u_range = (float(u_arr.min()), float(u_arr.max()))
    u_range = _as_range("u_range", u_range)
    feature_map: FeatureMap
    if features == "play":
        r = default_play_radii(u_range, n_play) if radii is None else np.asarray(radii, float)
        feature_map = PlayFeatures(radii=tuple(np.sort(r)), initial_input=initial_input)
    elif features == "bouc-wen":
        lv = default_bouc_wen_levels(u_range, n_bouc_wen) if levels is None else levels
        feature_map = BoucWenFeatures(
            levels=tuple(np.sort(np.asarray(lv, float))), initial_input=initial_input
        )
    else:
        feature_map = PastInputFeatures(n_past=n_past, initial_input=initial_input)

    feats, _ = feature_map.features(u_arr, feature_map.initial_state())
    f_train, z_train, w_train = feats[:n_train], z_arr[:n_train], weights[:n_train]
    feature_mean = f_train.mean(axis=0)
    feature_scale = f_train.std(axis=0)
    feature_scale[feature_scale < 1e-12] = 1.0
    z_mean = float(z_train.mean())
    z_scale = float(z_train.std()) or 1.0
    x_all = (feats - feature_mean) / feature_scale
    t_all = (z_arr - z_mean) / z_scale

    coef = _ridge_skip(x_all[:n_train], t_all[:n_train], w_train, skip_ridge)

    previous_threads = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        generator = torch.Generator().manual_seed(int(seed))
        net = TorchNLS.build(feature_map.n_features, hidden_t)
        with torch.no_grad():
            for layer in net.layers:
                bound = math.sqrt(6.0 / (layer.in_features + layer.out_features))
                layer.weight.uniform_(-bound, bound, generator=generator)
                layer.bias.zero_()
            net.out.weight.zero_()
            net.out.bias.zero_()
            net.skip.weight.copy_(torch.from_numpy(coef[:-1][None, :]))
            net.skip.bias.fill_(float(coef[-1]))
            net.feature_mean.copy_(torch.from_numpy(feature_mean))
            net.feature_scale.copy_(torch.from_numpy(feature_scale))
            net.z_mean.fill_(z_mean)
            net.z_scale.fill_(z_scale)
        x = torch.from_numpy(x_all)
        t = torch.from_numpy(t_all)
        w = torch.from_numpy(weights)
        x_tr, t_tr, w_tr = x[:n_train], t[:n_train], w[:n_train]
        x_va, t_va, w_va = x[n_train:], t[n_train:], w[n_train:]
        mlp_params = [p for m in (*net.layers, net.out) for p in m.parameters()]

        def data_loss(xb: Any, tb: Any, wb: Any) -> Any:
            return torch.mean(wb * (net.normalized(xb) - tb) ** 2)

        def penalty() -> Any:
            return weight_decay * sum(torch.sum(p**2) for p in mlp_params)

        def validation_loss() -> float:
            with torch.no_grad():
                if n_val == 0:
                    return float(data_loss(x_tr, t_tr, w_tr))
                return float(data_loss(x_va, t_va, w_va))

        optimizer = torch.optim.Adam(net.parameters(), lr=learning_rate)
        best_loss = validation_loss()
        initial_loss = best_loss
        best_state = {k: v.clone() for k, v in net.state_dict().items()}
        best_epoch = 0
        epochs_run = 0
        for epoch in range(1, max_epochs + 1):
            epochs_run = epoch
            order = torch.randperm(n_train, generator=generator)
            for i in range(0, n_train, batch_size):
                idx = order[i : i + batch_size]
                optimizer.zero_grad()
                loss = data_loss(x_tr[idx], t_tr[idx], w_tr[idx])
                if weight_decay:
                    loss = loss + penalty()
                loss.backward()
                optimizer.step()
            current = validation_loss()
            if current < best_loss:
                best_loss, best_epoch = current, epoch
                best_state = {k: v.clone() for k, v in net.state_dict().items()}
            elif n_val > 0 and epoch - best_epoch >= patience:
                break
        net.load_state_dict(best_state)
        lbfgs_improved = False
        if lbfgs_iterations:
            lbfgs = torch.optim.LBFGS(
                net.parameters(),
                max_iter=lbfgs_iterations,
                history_size=20,
                line_search_fn="strong_wolfe",
            )

            def closure() -> Any:
                lbfgs.zero_grad()
                loss = data_loss(x_tr, t_tr, w_tr)
                if weight_decay:
                    loss = loss + penalty()
                loss.backward()
                return loss

            lbfgs.step(closure)
            current = validation_loss()
            if math.isfinite(current) and current < best_loss:
                best_loss, lbfgs_improved = current, True
            else:
                net.load_state_dict(best_state)
        params = TorchNLS.to_params(net)
        with torch.no_grad():
            train_loss = float(data_loss(x_tr, t_tr, w_tr))
    finally:
        torch.set_num_threads(previous_threads)

    training = {
        "seed": int(seed),
        "n_train": int(n_train),
        "n_validation": int(n_val),
        "epochs": int(epochs_run),
        "best_epoch": int(best_epoch),
        "lbfgs_improved": lbfgs_improved,
        "affine_validation_mse": initial_loss * z_scale**2,
        "validation_mse": best_loss * z_scale**2,
        "train_mse": train_loss * z_scale**2,
        "wall_time_s": time.perf_counter() - start,
        "mse_unit": "equivalent V^2",
    }
    return NLS(feature_map, params, u_range=u_range, training=training)
