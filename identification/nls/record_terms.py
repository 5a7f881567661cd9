"""Step e''s free-run objective one record at a time, so that two processes can share it.

The objective of :func:`identification.nls.output_error.refine_nls_output_error` is a sum over
the records, ``J = (S_1 + S_2) / N`` with ``S_r`` the sum of squared free-run errors of record
``r`` and ``N`` the samples of both. Each record's term and its gradient depend only on the
current parameters, so one process can compute one record while another computes the other,
at every evaluation of the L-BFGS run (a helper of :mod:`identification.runner`; the training
records of an identification are two, the PRBS and the rich one, about 40 % and 60 % of the
work).

The split gives the single computation's numbers to the bit, for two records: each record's
term is computed by the same operations as in the single graph (a :class:`RecordTerm` holds a
copy of the network and of the linear part and runs the record's free run, its squared error
sum and the backward pass of ``S_r / N``); the single graph adds the two sums once
(``(0 + S_1) + S_2``) and accumulates each parameter's gradient from its two uses (every
parameter enters a record's free run once: each layer's weight and bias once, ``a`` and ``b``
once in the response), and floating-point addition of two numbers does not depend on their
order. With three or more records neither holds, so only two are ever split (a test holds the
two ways equal on every feature set, and a whole identification with and without the split).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from identification.nls.optimisation import torch_threads
from identification.nls.torch_module import TorchNLS, load_torch

__all__ = ["FreeRunGrid", "RecordTerm", "close_term", "evaluate_term", "new_key", "open_term"]


class FreeRunGrid:
    """The ARX part's free run from rest on a record of ``n`` samples, as a product of spectra:
    ``irfft(Z * B / (1 - A))`` on a zero-padded grid of at least twice the record's length
    (linear convolution; the IIR tail wraps around by ``|p|^n`` only). The Fourier bases of the
    lags are the same at every evaluation and are built once."""

    def __init__(self, n: int, na: int, nb: int, torch: object) -> None:
        self.n, self.size, self.torch = n, 1 << (2 * n).bit_length(), torch
        omega = torch.arange(self.size // 2 + 1, dtype=torch.float64) * (2.0 * math.pi / self.size)
        lags_a = torch.arange(1, na + 1, dtype=torch.float64)
        lags_b = torch.arange(1, nb + 1, dtype=torch.float64)
        self.basis_a = torch.exp(-1j * torch.outer(omega, lags_a))
        self.basis_b = torch.exp(-1j * torch.outer(omega, lags_b))

    def response(self, a: object, b: object) -> tuple[object, object]:
        """``B`` and ``1 - A`` on the grid, for the coefficients ``a`` and ``b``. A stage that
        holds the linear part computes them once and passes them to every :meth:`free_run`."""
        torch = self.torch
        numerator = self.basis_b @ b.to(torch.complex128)
        denominator = 1.0 - self.basis_a @ a.to(torch.complex128)
        return numerator, denominator

    def free_run(self, z: object, response: tuple[object, object]) -> object:
        """The free run (um) of ``z`` (equivalent V) through ``B / (1 - A)``, given as
        ``response = (B, 1 - A)`` on the grid (:meth:`response`)."""
        numerator, denominator = response
        spectrum = self.torch.fft.rfft(z, self.size) * numerator / denominator
        return self.torch.fft.irfft(spectrum, self.size)[: self.n]


class RecordTerm:
    """One record's share of the free-run objective and of its gradient.

    Parameters
    ----------
    params : dict of numpy.ndarray
        The network's arrays (:meth:`identification.nls.network.NLS.arrays`) at the stage's
        start.
    x : numpy.ndarray
        The record's normalized network input, shape (T, features) (fixed over the stage).
    y : numpy.ndarray
        The record's measured output (um), shape (T,).
    a, b : numpy.ndarray
        The linear part's coefficients at the stage's start.
    count : int
        Samples of all the records (the objective's divisor ``N``).
    linear : bool
        Whether the stage varies ``a`` and ``b`` (then they follow the network's parameters in
        :meth:`evaluate`'s values); otherwise the linear part is held at ``a``, ``b``.
    """

    def __init__(
        self,
        params: dict[str, np.ndarray],
        x: np.ndarray,
        y: np.ndarray,
        a: np.ndarray,
        b: np.ndarray,
        count: int,
        linear: bool,
    ) -> None:
        torch = load_torch()
        self._torch, self._count = torch, int(count)
        self._module = TorchNLS.from_params(params)
        self._x, self._y = torch.from_numpy(np.asarray(x)), torch.from_numpy(np.asarray(y))
        self._a = torch.tensor(np.asarray(a), dtype=torch.float64, requires_grad=linear)
        self._b = torch.tensor(np.asarray(b), dtype=torch.float64, requires_grad=linear)
        with torch_threads(1):  # as in the one graph: a thread count can change the last bit
            self._grid = FreeRunGrid(self._y.numel(), len(a), len(b), torch)
            self._held = None if linear else self._grid.response(self._a, self._b)
        self._parameters = [*self._module.parameters(), *((self._a, self._b) if linear else ())]

    def evaluate(
        self, values: Sequence[np.ndarray], grad: bool
    ) -> tuple[float, list[np.ndarray] | None]:
        """The record's sum of squared free-run errors (um^2) at the parameters ``values``
        (the network's, in ``module.parameters()`` order, then ``a`` and ``b`` when the stage
        varies them) and, with ``grad``, the gradient of that sum over the objective's
        divisor, one array per parameter."""
        torch = self._torch
        with torch_threads(1):
            with torch.no_grad():
                for parameter, value in zip(self._parameters, values, strict=True):
                    parameter.copy_(torch.from_numpy(np.asarray(value)))
            if not grad:
                with torch.no_grad():
                    return float(self._squared_error()), None
            for parameter in self._parameters:
                parameter.grad = None
            total = self._squared_error()
            (total / self._count).backward()
            return float(total.detach()), [p.grad.numpy().copy() for p in self._parameters]

    def _squared_error(self) -> Any:
        response = self._grid.response(self._a, self._b) if self._held is None else self._held
        error = self._grid.free_run(self._module.output_of(self._x), response) - self._y
        return (error * error).sum()


_OPEN: dict[int, RecordTerm] = {}
"""The terms this process holds for another (:func:`open_term`), by key."""

_KEYS = itertools.count()


def new_key() -> int:
    """A key not used before by this process (the process that opens terms names them)."""
    return next(_KEYS)


def open_term(key: int, *args: Any) -> None:
    """Build :class:`RecordTerm` ``(*args)`` in this process and hold it under ``key``."""
    _OPEN[key] = RecordTerm(*args)


def evaluate_term(
    key: int, values: Sequence[np.ndarray], grad: bool
) -> tuple[float, list[np.ndarray] | None]:
    """:meth:`RecordTerm.evaluate` of the term held under ``key``."""
    return _OPEN[key].evaluate(values, grad)


def close_term(key: int) -> None:
    """Drop the term held under ``key`` (none held: nothing to do)."""
    _OPEN.pop(key, None)
