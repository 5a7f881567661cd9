"""The free run of step e''s linear part, differentiable for the refinement's L-BFGS.

:class:`FreeRun` gives the free run from rest of ``B(q) / (1 - A(q))`` on one record as a torch
function of the network's output and of the coefficients; :func:`free_run` is the recursion
with its exact adjoint (:func:`scipy.signal.lfilter` both ways).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from identification.nls.torch_module import load_torch

__all__ = ["FreeRun", "free_run"]


class FreeRun:
    """The ARX part's free run from rest on a record of ``n`` samples, ``y = B(q) / (1 - A(q))
    z``, differentiable in ``z``, ``a`` and ``b``.

    The recursion itself with its exact adjoint (:func:`free_run`), O(n (na + nb)) per pass,
    wherever its squared error is a float64 number: the true free run, continuous across the
    stability boundary and growing as ``|p|^(2n)`` beyond it, a barrier to a line search that
    probes there (the joint stage's may). A part so far beyond the boundary that it is not
    (``4 sum y^2`` overflows; then ``sum (y - m)^2 <= 2 sum y^2 + 2 sum m^2`` can too, for a
    measured record ``m``) is evaluated as the product of spectra ``irfft(Z * B / (1 - A))`` on
    a zero-padded grid of at least twice the record's length, finite off the unit circle: a
    value for the line search's interpolation, which an infinite one turns into a NaN step.
    That value is the unstable poles' anticausal response and may be lower than the stable
    side's; a stage that ends beyond the boundary is refused
    (:func:`identification.nls.output_error.refine_nls_output_error`)."""

    def __init__(self, n: int, na: int, nb: int, torch: object) -> None:
        self.n, self.na, self.nb, self.torch = n, na, nb, torch
        self._spectral: tuple[int, Any, Any] | None = None

    def free_run(self, z: object, a: object, b: object) -> object:
        """The free run (um) of ``z`` (equivalent V, a torch tensor of the record's length)
        through the linear part ``(a, b)`` (torch tensors)."""
        y = free_run(z, a, b)
        y_np = y.detach().numpy()
        with np.errstate(over="ignore", invalid="ignore"):  # numpy's sum, not a BLAS dot,
            # whose threads would wait on a core that another process needs
            representable = bool(np.isfinite(4.0 * np.add.reduce(y_np * y_np)))
        return y if representable else self._spectral_run(z, a, b)

    def _spectral_run(self, z: Any, a: Any, b: Any) -> Any:
        torch = self.torch
        if self._spectral is None:
            size = 1 << (2 * self.n).bit_length()
            omega = torch.arange(size // 2 + 1, dtype=torch.float64) * (2.0 * math.pi / size)
            lags_a = torch.arange(1, self.na + 1, dtype=torch.float64)
            lags_b = torch.arange(1, self.nb + 1, dtype=torch.float64)
            self._spectral = (
                size,
                torch.exp(-1j * torch.outer(omega, lags_a)),
                torch.exp(-1j * torch.outer(omega, lags_b)),
            )
        size, basis_a, basis_b = self._spectral
        numerator = basis_b @ b.to(torch.complex128)
        denominator = 1.0 - basis_a @ a.to(torch.complex128)
        spectrum = torch.fft.rfft(z, size) * numerator / denominator
        return torch.fft.irfft(spectrum, size)[: self.n]


_FREE_RUN: Any = None


def free_run(z: Any, a: Any, b: Any) -> Any:
    """``y = B(q) / (1 - A(q)) z`` from rest, ``y_t = sum_j b_j v_(t-j)`` with
    ``v_t = z_t + sum_i a_i v_(t-i)``: a torch function of the tensors ``z`` (T,), ``a`` (na,)
    and ``b`` (nb,), float64, computed by :func:`scipy.signal.lfilter` in O(T (na + nb)).

    Its backward pass is the recursion's adjoint, for the incoming gradient ``g = dL/dy``:
    ``dL/db_j = sum_t g_t v_(t-j)``; ``h = B^T g``, ``h_s = sum_j b_j g_(s+j)``; ``w = F^-T h``,
    the recursion ``w_s = h_s + sum_i a_i w_(s+i)`` run backwards in time (``F = 1 - A``
    lower-triangular Toeplitz, so its transpose is solved from the end); then ``dL/dz = w``
    and ``dL/da_i = sum_t w_t v_(t-i)`` (``F v = z`` gives ``F dv/da_i = q^-i v``). Each is a
    filter or an inner product of the record, so a gradient costs about two forward passes
    (``tests/test_nls_output_error.py`` checks it against finite differences)."""
    global _FREE_RUN
    if _FREE_RUN is None:
        _FREE_RUN = _free_run_function()
    return _FREE_RUN.apply(z, a, b)


def _free_run_function() -> Any:
    """The :class:`torch.autograd.Function` of :func:`free_run`, built on first use (torch is
    imported lazily)."""
    import scipy.signal

    torch = load_torch()

    def lagged_products(x: np.ndarray, v: np.ndarray, lags: int) -> np.ndarray:
        """``sum_t x_t v_(t-k)`` for k = 1..lags, each summed by numpy's own reduction, not by
        BLAS: a multi-threaded BLAS dot sums in an order that depends on its thread count,
        and the identified model would then depend on the machine's cores."""
        n = x.size
        return np.array(
            [np.add.reduce(x[k:] * v[: n - k]) if k < n else 0.0 for k in range(1, lags + 1)]
        )

    class _FreeRun(torch.autograd.Function):
        @staticmethod
        def forward(ctx: Any, z: Any, a: Any, b: Any) -> Any:
            a_np, b_np = a.detach().numpy(), b.detach().numpy()
            v = scipy.signal.lfilter([1.0], np.r_[1.0, -a_np], z.detach().numpy())
            ctx.arrays = (v, a_np.copy(), b_np.copy())
            return torch.from_numpy(np.convolve(v, np.r_[0.0, b_np])[: v.size])

        @staticmethod
        def backward(ctx: Any, g: Any) -> tuple[Any, Any, Any]:
            v, a_np, b_np = ctx.arrays
            g_np = np.ascontiguousarray(g.detach().numpy())
            need_z, need_a, need_b = ctx.needs_input_grad
            grad_z = grad_a = grad_b = None
            if need_b:
                grad_b = torch.from_numpy(lagged_products(g_np, v, b_np.size))
            if need_z or need_a:
                h = np.convolve(g_np[::-1], np.r_[0.0, b_np])[: g_np.size]
                w = scipy.signal.lfilter([1.0], np.r_[1.0, -a_np], h)[::-1].copy()
                if need_z:
                    grad_z = torch.from_numpy(w)
                if need_a:
                    grad_a = torch.from_numpy(lagged_products(w, v, a_np.size))
            return grad_z, grad_a, grad_b

    return _FreeRun
