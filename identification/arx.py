"""ARX model with uniformly bounded equation noise (the paper's eq. 20).

The linear dynamic part of the Hammerstein model is

    y_t = a_1 y_{t-1} + ... + a_na y_{t-na} + b_1 u_{t-1} + ... + b_nb u_{t-nb} + nu_t,

with ``nu_t ~ U(-r, r)``. In regression form ``y_t = psi_t^T theta + nu_t`` with
``psi_t = [y_{t-1} .. y_{t-na}, u_{t-1} .. u_{t-nb}]`` and ``theta = [a, b]``; :func:`regressors`
builds ``psi_t`` for every estimator. As a transfer function in the shift operator,

    Y(z) / U(z) = (b_1 z^-1 + ... + b_nb z^-nb) / (1 - a_1 z^-1 - ... - a_na z^-na).

Models are saved as plain JSON (never pickled).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.signal

from piezo_env.checks import require_int

if TYPE_CHECKING:
    import control

__all__ = ["ARXModel", "check_io", "regressors"]

_FORMAT = "piezo-arx"
_VERSION = 1


def check_io(u: Any, y: Any) -> tuple[np.ndarray, np.ndarray]:
    """Validate an input/output record and return it as two float64 vectors.

    Parameters
    ----------
    u, y
        Input and output sequences (any array-like of equal length).

    Raises
    ------
    ValueError
        If either is not one-dimensional, their lengths differ, or they contain NaN or inf.
    """
    u = np.asarray(u, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if u.ndim != 1 or y.ndim != 1:
        raise ValueError(
            f"u and y must be one-dimensional sequences, got shapes {u.shape} and {y.shape}"
        )
    if u.shape != y.shape:
        raise ValueError(f"u and y must have the same length, got {u.size} and {y.size}")
    for name, x in (("u", u), ("y", y)):
        bad = ~np.isfinite(x)
        if bad.any():
            i = int(np.argmax(bad))
            raise ValueError(f"{name} contains non-finite values (first: {name}[{i}] = {x[i]})")
    return u, y


def regressors(u: Any, y: Any, na: int, nb: int) -> tuple[np.ndarray, np.ndarray]:
    """Regression matrix of the ARX equation, one row per usable sample.

    Parameters
    ----------
    u, y
        Input and output records of equal length N.
    na, nb
        Number of past outputs and past inputs in the regressor.

    Returns
    -------
    Psi : numpy.ndarray
        Shape (N - p, na + nb) with ``p = max(na, nb)``; row k is
        ``psi_t = [y_{t-1} .. y_{t-na}, u_{t-1} .. u_{t-nb}]`` for ``t = p + k``.
    Y : numpy.ndarray
        Shape (N - p,), the outputs ``y_t`` for the same t.
    """
    na, nb = _check_orders(na, nb)
    u, y = check_io(u, y)
    p = max(na, nb)
    n = u.size
    if n <= p:
        raise ValueError(f"need more than max(na, nb) = {p} samples for an ARX({na},{nb}), got {n}")
    columns = [y[p - i : n - i] for i in range(1, na + 1)]
    columns += [u[p - j : n - j] for j in range(1, nb + 1)]
    psi = np.column_stack(columns) if columns else np.empty((n - p, 0))
    return psi, y[p:].copy()


def _check_orders(na: int, nb: int) -> tuple[int, int]:
    for name, value in (("na", na), ("nb", nb)):
        require_int(name, value, minimum=0)
    if na + nb == 0:
        raise ValueError("an ARX model needs na + nb >= 1")
    return int(na), int(nb)


def _vector(name: str, values: Any) -> np.ndarray:
    x = np.atleast_1d(np.asarray(values, dtype=np.float64))
    if x.ndim != 1:
        raise ValueError(f"{name} must be a one-dimensional coefficient vector, got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name} must be finite, got {x}")
    return x.copy()


class ARXModel:
    """ARX model ``y_t = sum a_i y_{t-i} + sum b_j u_{t-j} + nu_t``, ``|nu_t| <= r``.

    Parameters
    ----------
    a
        Output coefficients ``[a_1 .. a_na]`` (may be empty).
    b
        Input coefficients ``[b_1 .. b_nb]`` (output unit per input unit).
    noise_bound
        Bound r of the uniform equation noise, in the output unit (0 if unknown or noise-free).
    dt
        Sampling period, s.
    history
        Optional time course of an estimate: ``"theta"`` of shape (T, na + nb) and
        ``"noise_bound"`` of shape (T,), plus any other float arrays of length T (for example
        ``"t"``, the sample index of each row).
    method
        Name of the estimator that produced the model, if any.

    Attributes
    ----------
    a, b : numpy.ndarray
        Coefficient vectors (float64).
    na, nb : int
        Orders.
    theta : numpy.ndarray
        ``[a, b]``, the regression parameter vector.
    noise_bound : float
        r, output unit.
    dt : float
        Sampling period, s.
    history : dict[str, numpy.ndarray] or None
    method : str or None
    """

    def __init__(
        self,
        a: Any,
        b: Any,
        *,
        noise_bound: float = 0.0,
        dt: float = 1.0,
        history: Mapping[str, Any] | None = None,
        method: str | None = None,
    ) -> None:
        self.a = _vector("a", a) if np.size(a) else np.zeros(0)
        self.b = _vector("b", b) if np.size(b) else np.zeros(0)
        _check_orders(self.a.size, self.b.size)
        noise_bound = float(noise_bound)
        if not math.isfinite(noise_bound) or noise_bound < 0.0:
            raise ValueError(f"noise_bound must be finite and >= 0, got {noise_bound}")
        dt = float(dt)
        if not math.isfinite(dt) or dt <= 0.0:
            raise ValueError(f"dt (sampling period, s) must be positive, got {dt}")
        self.noise_bound = noise_bound
        self.dt = dt
        self.method = None if method is None else str(method)
        self.history = None if history is None else self._check_history(history)

    def _check_history(self, history: Mapping[str, Any]) -> dict[str, np.ndarray]:
        if not isinstance(history, Mapping):
            raise ValueError("history must be a mapping of names to arrays")
        out = {str(k): np.asarray(v, dtype=np.float64) for k, v in history.items()}
        lengths = {k: v.shape[0] if v.ndim else -1 for k, v in out.items()}
        if len(set(lengths.values())) > 1 or -1 in lengths.values():
            raise ValueError(f"history arrays must share their first dimension, got {lengths}")
        theta = out.get("theta")
        if theta is not None and (theta.ndim != 2 or theta.shape[1] != self.na + self.nb):
            raise ValueError(
                f"history['theta'] must have shape (T, {self.na + self.nb}), got {theta.shape}"
            )
        bound = out.get("noise_bound")
        if bound is not None and bound.ndim != 1:
            raise ValueError(f"history['noise_bound'] must have shape (T,), got {bound.shape}")
        return out

    @property
    def na(self) -> int:
        """Number of past outputs."""
        return int(self.a.size)

    @property
    def nb(self) -> int:
        """Number of past inputs."""
        return int(self.b.size)

    @property
    def theta(self) -> np.ndarray:
        """Parameter vector ``[a_1 .. a_na, b_1 .. b_nb]``."""
        return np.concatenate([self.a, self.b])

    @property
    def _filter(self) -> tuple[np.ndarray, np.ndarray]:
        return np.concatenate([[0.0], self.b]), np.concatenate([[1.0], -self.a])

    def __repr__(self) -> str:
        return (
            f"ARXModel(a={self.a.tolist()}, b={self.b.tolist()}, "
            f"noise_bound={self.noise_bound:.6g}, dt={self.dt:.6g}, method={self.method!r})"
        )

    def simulate(
        self,
        u: Any,
        *,
        y0: Any = None,
        rng: np.random.Generator | None = None,
    ) -> np.ndarray:
        """Free-run (simulation) output for the input ``u``.

        Parameters
        ----------
        u
            Input sequence (input unit), length N.
        y0
            None: the system starts at rest (outputs and inputs before sample 0 are zero).
            Otherwise the first ``na`` outputs ``y_0 .. y_{na-1}`` (e.g. measured ones); they
            are returned unchanged and the recursion continues from them, with inputs before
            sample 0 taken as zero.
        rng
            If given, the equation noise ``nu_t ~ U(-r, r)`` is drawn from it and added
            (the data-generating process of the model); otherwise the run is noise-free.

        Returns
        -------
        numpy.ndarray
            Output sequence of length N (output unit).
        """
        u = np.asarray(u, dtype=np.float64)
        if u.ndim != 1:
            raise ValueError(f"u must be one-dimensional, got shape {u.shape}")
        if not np.all(np.isfinite(u)):
            raise ValueError("u contains non-finite values")
        if u.size == 0:  # no input, no output (scipy's filter refuses an empty one)
            return np.empty(0)
        num, den = self._filter
        x = scipy.signal.lfilter(num, 1.0, u)
        if rng is not None:
            x = x + rng.uniform(-self.noise_bound, self.noise_bound, size=u.size)
        if y0 is None or self.na == 0:
            return scipy.signal.lfilter([1.0], den, x)
        y0 = np.asarray(y0, dtype=np.float64).ravel()
        if y0.size != self.na:
            raise ValueError(f"y0 must hold the first na = {self.na} outputs, got {y0.size}")
        if u.size <= self.na:
            return y0[: u.size].copy()
        zi = scipy.signal.lfiltic([1.0], den, y=y0[::-1])
        tail, _ = scipy.signal.lfilter([1.0], den, x[self.na :], zi=zi)
        return np.concatenate([y0, tail])

    def predict(self, u: Any, y: Any) -> np.ndarray:
        """One-step-ahead prediction ``y_hat_t = psi_t^T theta`` from measured ``u`` and ``y``.

        Samples before the start of the record are taken as zero, so the first ``max(na, nb)``
        predictions use only the data available (``y_hat_0 = 0``).

        Parameters
        ----------
        u, y
            Measured input and output of equal length N.

        Returns
        -------
        numpy.ndarray
            Predictions of length N (output unit).
        """
        u, y = check_io(u, y)
        num, _ = self._filter
        past_outputs = np.concatenate([[0.0], self.a])
        return scipy.signal.lfilter(num, 1.0, u) + scipy.signal.lfilter(past_outputs, 1.0, y)

    def static_gain(self) -> float:
        """DC gain ``sum(b) / (1 - sum(a))`` (output unit per input unit); inf for an integrator."""
        denominator = 1.0 - float(np.sum(self.a))
        numerator = float(np.sum(self.b))
        if denominator == 0.0:
            return math.copysign(math.inf, numerator) if numerator else math.nan
        return numerator / denominator

    def poles(self) -> np.ndarray:
        """Roots of ``z^na - a_1 z^(na-1) - ... - a_na`` (complex array of length na)."""
        return np.roots(np.concatenate([[1.0], -self.a])).astype(np.complex128)

    def zeros(self) -> np.ndarray:
        """Roots of ``b_1 z^(nb-1) + ... + b_nb`` (zeros at the origin from the delay omitted)."""
        if not np.any(self.b):
            return np.zeros(0, dtype=np.complex128)
        return np.roots(self.b).astype(np.complex128)

    def is_stable(self) -> bool:
        """True if every pole lies strictly inside the unit circle."""
        return bool(np.all(np.abs(self.poles()) < 1.0))

    def is_minimum_phase(self) -> bool:
        """True if every zero lies strictly inside the unit circle (eq. 25's inverse is stable)."""
        return bool(np.all(np.abs(self.zeros()) < 1.0))

    def to_transfer_function(self) -> control.TransferFunction:
        """Discrete transfer function in z with sampling time ``dt`` (python-control)."""
        import control

        order = max(self.na, self.nb)
        num = np.zeros(order + 1)
        num[1 : self.nb + 1] = self.b
        den = np.zeros(order + 1)
        den[0] = 1.0
        den[1 : self.na + 1] = -self.a
        return control.tf(num, den, self.dt)

    def state_space_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Matrices (A, B, C, D) of the ARX model in its measured-history realization.

        The state is what the ARX equation reads, so it is known from data:
        ``x_t = [y_t, y_t-1 .. y_t-na+1, u_t-1 .. u_t-nb+1]`` (output unit, input unit), and
        ``x_t+1 = A x_t + B u_t``, ``y_t = C x_t`` (D = 0: y_t depends on u_t-1 and older).
        It has ``max(na, 1) + max(nb, 1) - 1`` states; the states beyond the transfer
        function's order are pure delays (eigenvalues at 0), so the realization is stabilizable
        and detectable (with nb = 0 the input does not enter: B = 0).
        """
        na, nb = max(self.na, 1), self.nb
        n = na + max(nb, 1) - 1
        a = np.zeros((n, n))
        b = np.zeros((n, 1))
        a[0, : self.na] = self.a
        a[1:na, : na - 1] = np.eye(na - 1)
        if nb:
            b[0, 0] = self.b[0]
            a[0, na:] = self.b[1:]
        if nb > 1:
            b[na, 0] = 1.0
            a[na + 1 :, na : n - 1] = np.eye(nb - 2)
        c = np.zeros((1, n))
        c[0, 0] = 1.0
        return a, b, c, np.zeros((1, 1))

    def to_state_space(self) -> control.StateSpace:
        """Discrete state space (python-control, sampling time ``dt``) of the ARX model.

        Input: the ARX input (for the Hammerstein model, the hidden signal z in equivalent V);
        output: y (um). The realization is :meth:`state_space_matrices`'; its transfer function
        equals :meth:`to_transfer_function`.
        """
        import control

        return control.ss(*self.state_space_matrices(), self.dt)

    def to_dict(self, *, include_history: bool = True) -> dict[str, Any]:
        """JSON-safe dictionary of the model (non-finite history entries become None)."""
        data: dict[str, Any] = {
            "format": _FORMAT,
            "version": _VERSION,
            "a": self.a.tolist(),
            "b": self.b.tolist(),
            "noise_bound": self.noise_bound,
            "dt": self.dt,
            "method": self.method,
        }
        if include_history and self.history is not None:
            data["history"] = {k: _nan_to_none(v.tolist()) for k, v in self.history.items()}
        return data

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ARXModel:
        """Rebuild a model from :meth:`to_dict` output; ValueError if it is not one."""
        if not isinstance(data, Mapping) or data.get("format") != _FORMAT:
            raise ValueError(f"not an ARX model description (expected format {_FORMAT!r})")
        if data.get("version") != _VERSION:
            raise ValueError(f"unsupported ARX model version {data.get('version')!r}")
        missing = [k for k in ("a", "b", "noise_bound", "dt") if k not in data]
        if missing:
            raise ValueError(f"ARX model description lacks {', '.join(missing)}")
        history = data.get("history")
        if history is not None:
            if not isinstance(history, Mapping):
                raise ValueError("ARX model history must be a mapping of names to lists")
            history = {k: _none_to_nan(v) for k, v in history.items()}
        try:
            return cls(
                data["a"],
                data["b"],
                noise_bound=data["noise_bound"],
                dt=data["dt"],
                history=history,
                method=data.get("method"),
            )
        except (TypeError, ValueError) as error:
            raise ValueError(f"invalid ARX model description: {error}") from error

    def save(self, path: str | Path, *, include_history: bool = True) -> None:
        """Write the model to ``path`` as JSON."""
        text = json.dumps(self.to_dict(include_history=include_history), allow_nan=False)
        Path(path).write_text(text + "\n", encoding="utf-8")

    @classmethod
    def load(cls, path: str | Path) -> ARXModel:
        """Read a model written by :meth:`save`; ValueError for a corrupted or foreign file."""
        text = Path(path).read_text(encoding="utf-8")
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ValueError(f"{path} is not valid JSON: {error}") from error
        try:
            return cls.from_dict(data)
        except ValueError as error:
            raise ValueError(f"{path}: {error}") from error


def _nan_to_none(values: Any) -> Any:
    if isinstance(values, list):
        return [_nan_to_none(v) for v in values]
    return None if values is None or not math.isfinite(values) else float(values)


def _none_to_nan(values: Any) -> Any:
    if isinstance(values, list):
        return [_none_to_nan(v) for v in values]
    return math.nan if values is None else values
