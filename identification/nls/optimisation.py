"""The torch part of :func:`identification.nls.fit_nls`: the network at its affine start, Adam
on mini-batches with early stopping on the validation block, optional full-batch L-BFGS.

:func:`train_network` runs them in that order and returns the plain parameter arrays.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from identification.nls.torch_module import TorchNLS, load_torch
from identification.nls.training_data import Normalised
from identification.nls.training_settings import TrainingSettings

__all__ = [
    "AdamResult",
    "Objective",
    "TrainedNetwork",
    "initial_network",
    "refine_lbfgs",
    "torch_threads",
    "train_adam",
    "train_network",
]


@contextmanager
def torch_threads(num_threads: int) -> Iterator[None]:
    """Run the block with ``num_threads`` torch threads; restore the previous number after."""
    torch = load_torch()
    previous_threads = torch.get_num_threads()
    torch.set_num_threads(num_threads)
    try:
        yield
    finally:
        torch.set_num_threads(previous_threads)


def initial_network(
    n_features: int, hidden: tuple[int, ...], data: Normalised, coef: np.ndarray, generator: Any
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


class Objective:
    """Weighted mean squared error of ``net`` in normalized units, on the two blocks.

    ``train`` and ``validation`` hold the ``(x, t, w)`` tensors of the training block (the
    first ``n_train`` samples) and of the validation block (the rest), views of the numpy arrays.
    The validation loss is the training loss when there is no validation block. The L2 penalty
    (``weight_decay``) covers the MLP weights only, never the affine skip.
    """

    def __init__(
        self, net: Any, data: Normalised, weights: np.ndarray, n_train: int, weight_decay: float
    ) -> None:
        torch = load_torch()
        x = torch.from_numpy(data.x)
        t = torch.from_numpy(data.t)
        w = torch.from_numpy(weights)
        self.net = net
        self.n_train = n_train
        self.train = (x[:n_train], t[:n_train], w[:n_train])
        self.validation = (x[n_train:], t[n_train:], w[n_train:])
        self.has_validation = n_train < len(data.t)
        self.weight_decay = weight_decay
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
class AdamResult:
    """Outcome of :func:`train_adam`; losses in normalized units.

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


def train_adam(
    net: Any, objective: Objective, settings: TrainingSettings, generator: Any
) -> AdamResult:
    """Adam epochs with early stopping; leaves ``net`` at its best-validating weights.

    Each epoch draws a permutation of the training block from ``generator`` and takes one
    step per mini-batch; training stops after ``patience`` epochs without improvement of the
    validation loss (never without a validation block). Adam runs its multi-tensor
    (``foreach``) update: on the CPU that applies the single-tensor update's operations to each
    parameter in turn, with the same result and less Python work per step.
    """
    torch = load_torch()
    optimizer = torch.optim.Adam(net.parameters(), lr=settings.learning_rate, foreach=True)
    best_loss = objective.validation_loss()
    initial_loss = best_loss
    best_state = state_copy(net)
    best_epoch = 0
    epochs_run = 0
    for epoch in range(1, settings.max_epochs + 1):
        epochs_run = epoch
        order = torch.randperm(objective.n_train, generator=generator)
        adam_epoch(optimizer, objective, order, settings.batch_size)
        current = objective.validation_loss()
        if current < best_loss:
            best_loss, best_epoch = current, epoch
            best_state = state_copy(net)
        elif objective.has_validation and epoch - best_epoch >= settings.patience:
            break
    net.load_state_dict(best_state)
    return AdamResult(initial_loss, best_loss, best_epoch, epochs_run, best_state)


def adam_epoch(optimizer: Any, objective: Objective, order: Any, batch_size: int) -> None:
    """One Adam step per mini-batch of the training block, in the sample ``order`` given.

    The block is gathered in that order once per epoch; the mini-batches are slices of it.
    """
    x_ep, t_ep, w_ep = (a[order] for a in objective.train)
    for i in range(0, order.numel(), batch_size):
        batch = slice(i, i + batch_size)
        optimizer.zero_grad()
        loss = objective.penalised_loss(x_ep[batch], t_ep[batch], w_ep[batch])
        loss.backward()
        optimizer.step()


def state_copy(net: Any) -> dict[str, Any]:
    """A detached copy of ``net``'s state dict."""
    return {k: v.clone() for k, v in net.state_dict().items()}


def refine_lbfgs(
    net: Any, objective: Objective, settings: TrainingSettings, adam: AdamResult
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


@dataclass(frozen=True, eq=False)
class TrainedNetwork:
    """Outcome of :func:`train_network`; losses in normalized units.

    Attributes
    ----------
    params : dict of numpy.ndarray
        The kept network as plain float64 arrays (:meth:`TorchNLS.to_params`).
    adam : AdamResult
        The Adam phase.
    validation_loss : float
        Validation loss of the kept network.
    lbfgs_improved : bool
        Whether L-BFGS ran and was kept.
    train_loss : float
        Training-block loss of the kept network.
    """

    params: dict[str, np.ndarray]
    adam: AdamResult
    validation_loss: float
    lbfgs_improved: bool
    train_loss: float


def train_network(
    data: Normalised,
    weights: np.ndarray,
    coef: np.ndarray,
    settings: TrainingSettings,
    n_train: int,
) -> TrainedNetwork:
    """Train the network from the affine start ``coef`` on the first ``n_train`` samples.

    Runs with ``settings.num_threads`` torch threads; one generator seeded with
    ``settings.seed`` draws the hidden-layer initialisation first, then the batch orders.
    """
    torch = load_torch()
    with torch_threads(settings.num_threads):
        generator = torch.Generator().manual_seed(int(settings.seed))
        net = initial_network(data.x.shape[1], settings.hidden, data, coef, generator)
        objective = Objective(net, data, weights, n_train, settings.weight_decay)
        adam = train_adam(net, objective, settings, generator)
        validation_loss, improved = refine_lbfgs(net, objective, settings, adam)
        params = TorchNLS.to_params(net)
        return TrainedNetwork(params, adam, validation_loss, improved, objective.training_loss())
