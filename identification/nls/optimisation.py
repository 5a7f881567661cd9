"""Steps e-g of :func:`identification.nls.fit_nls`: the torch network at its affine start, Adam
on mini-batches with early stopping on the validation block, optional full-batch L-BFGS."""

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

__all__ = ["AdamResult", "Objective", "initial_network", "refine_lbfgs", "torch_threads",
           "train_adam"]


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

    ``train`` and ``validation`` hold the ``(x, t, w)`` tensors of the training and validation
    blocks (views of the numpy arrays). The validation loss is the training loss when there is
    no validation block. The L2 penalty covers the MLP weights only, never the affine skip.
    """

    def __init__(
        self, net: Any, data: Normalised, weights: np.ndarray, settings: TrainingSettings
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
class AdamResult:
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


def train_adam(
    net: Any, objective: Objective, settings: TrainingSettings, generator: Any
) -> AdamResult:
    """Adam epochs with early stopping; leaves ``net`` at its best-validating weights.

    Each epoch draws a permutation of the training block from ``generator`` and takes one
    step per mini-batch; training stops after ``patience`` epochs without improvement of the
    validation loss (never without a validation block).
    """
    torch = load_torch()
    optimizer = torch.optim.Adam(net.parameters(), lr=settings.learning_rate)
    best_loss = objective.validation_loss()
    initial_loss = best_loss
    best_state = state_copy(net)
    best_epoch = 0
    epochs_run = 0
    for epoch in range(1, settings.max_epochs + 1):
        epochs_run = epoch
        order = torch.randperm(settings.n_train, generator=generator)
        adam_epoch(optimizer, objective, order, settings.batch_size)
        current = objective.validation_loss()
        if current < best_loss:
            best_loss, best_epoch = current, epoch
            best_state = state_copy(net)
        elif settings.n_validation > 0 and epoch - best_epoch >= settings.patience:
            break
    net.load_state_dict(best_state)
    return AdamResult(initial_loss, best_loss, best_epoch, epochs_run, best_state)


def adam_epoch(optimizer: Any, objective: Objective, order: Any, batch_size: int) -> None:
    """One Adam step per mini-batch of the training block, in the sample ``order`` given."""
    x_tr, t_tr, w_tr = objective.train
    for i in range(0, order.numel(), batch_size):
        idx = order[i : i + batch_size]
        optimizer.zero_grad()
        loss = objective.penalised_loss(x_tr[idx], t_tr[idx], w_tr[idx])
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
