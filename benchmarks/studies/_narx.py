"""NARX network baseline of the identification benchmark: one MLP, no Hammerstein split.

``y_t = f(y_{t-1}, ..., y_{t-ny}, u_{t-1}, ..., u_{t-nu})`` with ``f`` a tanh MLP, trained
one step ahead (series-parallel, measured past outputs as regressors) and used in free run
(parallel, its own past outputs fed back). It is the comparison "a neural network on the same
data, without the paper's linear-dynamics / nonlinearity split".

Kept honest as a baseline:

- inputs and target normalised by the training statistics;
- optionally (``skip=True``) an affine skip from the regressors to the output, initialised by
  least squares, with the MLP output layer initialised at zero: training starts from the
  least-squares ARX model of the same order and the MLP learns the residual. ``skip=False`` is
  the plain MLP of the classic NARX network;
- Adam on shuffled mini-batches with a cosine learning-rate decay, float64, a seeded
  ``torch.Generator``, one torch thread;
- early stopping on the *free-run* fit of a held-out tail of every training record (the
  criterion the model is judged by), checked every few epochs; the best weights (the
  initialisation included) are kept. The free-run fit typically improves only late in the
  learning-rate decay, so the patience spans the whole schedule by default: in effect the best
  checkpoint of the schedule is kept.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from identification.metrics import fit_percent


def _regressors(u: np.ndarray, y: np.ndarray, ny: int, nu: int) -> np.ndarray:
    """Rows ``[y_{t-1..t-ny}, u_{t-1..t-nu}]`` for t = 0..T-1, values before the record zero."""
    n = len(y)
    lag = max(ny, nu)
    yp = np.r_[np.zeros(lag), y]
    up = np.r_[np.zeros(lag), u]
    cols = [yp[lag - i : lag - i + n] for i in range(1, ny + 1)]
    cols += [up[lag - i : lag - i + n] for i in range(1, nu + 1)]
    return np.stack(cols, axis=1)


@dataclass
class NARXNetwork:
    """Tanh MLP NARX model ``y_t = f(y_{t-1..t-ny}, u_{t-1..t-nu})`` in um and V.

    Parameters
    ----------
    ny, nu : int
        Output and input lags.
    hidden : tuple of int
        Hidden tanh layer widths.
    seed : int
        Seed of the torch generator (initialisation and batch order).
    max_epochs : int
        Adam epochs at most.
    batch_size : int
        Mini-batch size, samples.
    learning_rate : float
        Adam learning rate.
    check_every : int
        Epochs between free-run validations.
    patience : int
        Validations without improvement before stopping.
    validation_fraction : float
        Tail fraction of each record held out for early stopping.
    skip : bool
        Affine skip initialised by least squares (see the module docstring).
    training : dict
        Filled by :meth:`fit`: epochs, best epoch, validation fit, wall time.
    """

    ny: int = 6
    nu: int = 6
    hidden: tuple[int, ...] = (32, 32, 32)
    seed: int = 0
    max_epochs: int = 100
    batch_size: int = 256
    learning_rate: float = 1e-3
    check_every: int = 5
    patience: int = 20
    validation_fraction: float = 0.2
    skip: bool = True
    training: dict = field(default_factory=dict)

    def fit(self, records: Sequence[tuple[np.ndarray, np.ndarray]]) -> NARXNetwork:
        """Train on sample-aligned ``(u, y)`` records (V, um), each starting from rest.

        Returns
        -------
        NARXNetwork
            ``self``, with ``training`` (epochs, validation fit, wall time) filled in.
        """
        import torch

        start = time.perf_counter()
        splits = [round((1.0 - self.validation_fraction) * len(y)) for _, y in records]
        xn, tn, skip = self._normalised(records, splits)
        previous_threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            gen = torch.Generator().manual_seed(self.seed)
            layers, out, lin = self._initial_modules(skip, gen)
            epochs, best_epoch, best_fit = self._train(
                layers,
                out,
                lin,
                torch.from_numpy(xn),
                torch.from_numpy(tn),
                gen,
                records,
                splits,
            )
        finally:
            torch.set_num_threads(previous_threads)
        self.training = {
            "epochs": epochs,
            "best_epoch": best_epoch,
            "validation_free_run_fit_percent": best_fit,
            "training_samples": len(xn),
            "wall_time_s": time.perf_counter() - start,
        }
        return self

    def _normalised(self, records, splits) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Training regressors and targets, normalised; the least-squares affine skip."""
        pairs = list(zip(records, splits, strict=True))
        x_tr = np.concatenate([_regressors(u, y, self.ny, self.nu)[:s] for (u, y), s in pairs])
        t_tr = np.concatenate([y[:s] for (_, y), s in pairs])
        self.y_mean = float(t_tr.mean())
        self.y_scale = float(t_tr.std())
        self.u_scale = float(np.concatenate([u[:s] for (u, _), s in pairs]).std())
        self.x_mean = np.r_[np.full(self.ny, self.y_mean), np.zeros(self.nu)]
        self.x_scale = np.r_[np.full(self.ny, self.y_scale), np.full(self.nu, self.u_scale)]
        xn = (x_tr - self.x_mean) / self.x_scale
        tn = (t_tr - self.y_mean) / self.y_scale
        skip = np.linalg.lstsq(np.c_[xn, np.ones(len(xn))], tn, rcond=None)[0]
        return xn, tn, skip

    def _initial_modules(self, skip: np.ndarray, gen: Any) -> tuple[list, Any, Any]:
        """Hidden layers (Glorot-uniform), a zero output layer and the affine skip (or none)."""
        import torch

        widths = [self.ny + self.nu, *self.hidden]
        layers = [torch.nn.Linear(a, b, dtype=torch.float64) for a, b in itertools.pairwise(widths)]
        out = torch.nn.Linear(widths[-1], 1, dtype=torch.float64)
        lin = torch.nn.Linear(widths[0], 1, dtype=torch.float64)
        with torch.no_grad():
            for layer in layers:
                bound = math.sqrt(6.0 / (layer.in_features + layer.out_features))
                layer.weight.uniform_(-bound, bound, generator=gen)
                layer.bias.zero_()
            out.weight.zero_()
            out.bias.zero_()
            if self.skip:
                lin.weight.copy_(torch.from_numpy(skip[:-1][None, :]))
                lin.bias.fill_(float(skip[-1]))
            else:
                lin.weight.zero_()
                lin.bias.zero_()
                out.weight.uniform_(-0.1, 0.1, generator=gen)
        if not self.skip:
            lin.weight.requires_grad_(False)
            lin.bias.requires_grad_(False)
        return layers, out, lin

    def _train(self, layers, out, lin, x, t, gen, records, splits) -> tuple[int, int, float]:
        """Adam with a cosine schedule, early-stopped on the free-run fit; best weights kept."""
        import torch

        modules = torch.nn.ModuleList([*layers, out, lin])

        def forward(inputs: torch.Tensor) -> torch.Tensor:
            h = inputs
            for layer in layers:
                h = torch.tanh(layer(h))
            return (out(h) + lin(inputs))[:, 0]

        optimizer = torch.optim.Adam(
            [p for p in modules.parameters() if p.requires_grad], lr=self.learning_rate
        )
        schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, self.max_epochs)
        self._store(layers, out, lin)
        best_fit = self._validation_fit(records, splits)
        best_state = {k: v.clone() for k, v in modules.state_dict().items()}
        best_epoch, stale, epochs = 0, 0, 0
        for epoch in range(1, self.max_epochs + 1):
            epochs = epoch
            order = torch.randperm(len(x), generator=gen)
            for i in range(0, len(x), self.batch_size):
                idx = order[i : i + self.batch_size]
                optimizer.zero_grad()
                loss = torch.mean((forward(x[idx]) - t[idx]) ** 2)
                loss.backward()
                optimizer.step()
            schedule.step()
            if epoch % self.check_every:
                continue
            self._store(layers, out, lin)
            current = self._validation_fit(records, splits)
            if current > best_fit:
                best_fit, best_epoch, stale = current, epoch, 0
                best_state = {k: v.clone() for k, v in modules.state_dict().items()}
            else:
                stale += 1
                if stale >= self.patience:
                    break
        modules.load_state_dict(best_state)
        self._store(layers, out, lin)
        return epochs, best_epoch, best_fit

    def _store(self, layers: list, out: object, lin: object) -> None:
        """Copy the torch weights into numpy arrays for the free-run loop."""
        self._w = [
            (m.weight.detach().numpy().copy(), m.bias.detach().numpy().copy()) for m in layers
        ]
        self._out = (out.weight.detach().numpy()[0].copy(), float(out.bias.detach()[0]))
        self._lin = (lin.weight.detach().numpy()[0].copy(), float(lin.bias.detach()[0]))

    def _validation_fit(
        self, records: Sequence[tuple[np.ndarray, np.ndarray]], splits: Sequence[int]
    ) -> float:
        """Mean free-run fit (%) on the held-out tails (the run covers each whole record)."""
        fits = []
        for (u, y), s in zip(records, splits, strict=True):
            y_sim = self.simulate(u)
            fits.append(fit_percent(y[s:], y_sim[s:]) if np.all(np.isfinite(y_sim)) else -np.inf)
        return float(np.mean(fits))

    def simulate(self, u: np.ndarray) -> np.ndarray:
        """Free-run output (um) for the drive ``u`` (V), from rest.

        A diverging run is stopped at the first output beyond 1e6 times the training spread and
        the rest filled with NaN.
        """
        u = np.asarray(u, dtype=float)
        n, ny, nu = len(u), self.ny, self.nu
        lag = max(ny, nu)
        yb = np.zeros(n + lag)
        un = np.r_[np.zeros(lag), u] / self.u_scale
        ym, ys = self.y_mean, self.y_scale
        w_out, b_out = self._out
        w_lin, b_lin = self._lin
        yn_hist = np.full(n + lag, -ym / ys)  # normalised outputs (zero output before the record)
        limit = 1e6
        for t in range(n):
            k = t + lag
            x = np.concatenate((yn_hist[k - ny : k][::-1], un[k - nu : k][::-1]))
            h = x
            for w, b in self._w:
                h = np.tanh(w @ h + b)
            yn = w_out @ h + b_out + w_lin @ x + b_lin
            if not abs(yn) < limit:
                yb[k:] = np.nan
                break
            yn_hist[k] = yn
            yb[k] = ym + ys * yn
        return yb[lag:]
