"""Estimation of ARX models (paper eq. 20) from input/output records.

:func:`fit_arx` is the one entry point. Methods:

``"bayes-uniform"``
    The recursive approximate Bayesian estimator for uniformly bounded noise
    (:class:`identification.bayes_uniform.BayesUniformEstimator`, Pavelkova and Karny 2012).
``"chebyshev"``
    The exact maximum-a-posteriori estimate of the same model: ``min r`` subject to
    ``|y_t - psi_t^T theta| <= r`` for all t (L-infinity regression), one linear program solved by
    HiGHS (:func:`scipy.optimize.linprog`), constraints in CSR form.
``"least-squares"``
    Ordinary least squares for comparison; its noise bound is the largest absolute residual.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.optimize
import scipy.sparse

from identification.arx import ARXModel, check_io, regressors
from identification.bayes_uniform import BayesUniformEstimator

__all__ = [
    "METHODS",
    "bayes_uniform_estimator",
    "fit_arx",
    "fit_chebyshev",
    "fit_least_squares",
]

METHODS = ("bayes-uniform", "chebyshev", "least-squares")

_BAYES_OPTIONS = ("window", "reorient_every", "n_init", "record_history", "theta_estimate")


def _check_data(u: Any, y: Any, na: int, nb: int) -> tuple[np.ndarray, np.ndarray]:
    """Reject data an ARX fit cannot use, with a message that says why."""
    u, y = check_io(u, y)
    psi, target = regressors(u, y, na, nb)
    unknowns = na + nb + 1
    if target.size < 2 * unknowns:
        raise ValueError(
            f"too few samples for an ARX({na},{nb}): {u.size} given, need at least "
            f"{max(na, nb) + 2 * unknowns} ({2 * unknowns} regression rows)"
        )
    if np.ptp(u) == 0.0:
        raise ValueError(
            "the input is constant, so it is not persistently exciting: the b coefficients "
            "cannot be identified (use a PRBS or random input)"
        )
    scale = np.abs(psi).max(axis=0)
    if np.any(scale == 0.0):
        raise ValueError("a regressor column is identically zero: the data are not exciting")
    singular = np.linalg.svd(psi / scale, compute_uv=False)
    if singular[-1] <= 1e-9 * singular[0]:
        raise ValueError(
            f"the regressors are linearly dependent (condition number "
            f"{singular[0] / max(singular[-1], 1e-300):.3g}): the input is not persistently "
            f"exciting of order {nb}, or the orders are too high for these data"
        )
    return u, y


def fit_least_squares(u: Any, y: Any, *, na: int = 2, nb: int = 2, dt: float = 1.0) -> ARXModel:
    """Least-squares ARX fit; ``noise_bound`` is the largest absolute residual (output unit)."""
    u, y = _check_data(u, y, na, nb)
    psi, target = regressors(u, y, na, nb)
    theta = np.linalg.lstsq(psi, target, rcond=None)[0]
    bound = float(np.max(np.abs(target - psi @ theta)))
    return ARXModel(theta[:na], theta[na:], noise_bound=bound, dt=dt, method="least-squares")


def fit_chebyshev(u: Any, y: Any, *, na: int = 2, nb: int = 2, dt: float = 1.0) -> ARXModel:
    """Exact MAP estimate under uniform noise: the Chebyshev (L-infinity) ARX fit.

    Solves ``min r s.t. -r <= y_t - psi_t^T theta <= r`` as one LP with HiGHS, for the
    correction delta to the least-squares estimate theta_ls: ``theta = theta_ls + delta``, the
    least-squares residuals e_t taking the place of y_t. Scaled by their peak r_ls (and the
    columns of psi by theirs), the LP's optimum lies in [r_min / r_ls, 1] with r_min >= r_ls /
    sqrt(m) (m samples), so HiGHS's absolute tolerances (about 1e-7) are relative to the noise
    bound, not to the output's level: solved for y directly, a noise bound below 1e-7 of the
    output's peak (a small noise, or an input offset) came out up to twice the minimum. The
    constraint matrix has two rows per sample but only ``na + nb + 1`` columns, so its rows are
    full; it is handed over in CSR form, HiGHS's own layout, to avoid a dense copy inside.
    Noise-free data (r_ls = 0) give the exact fit with a zero bound.
    """
    u, y = _check_data(u, y, na, nb)
    psi, target = regressors(u, y, na, nb)
    theta_ls = np.linalg.lstsq(psi, target, rcond=None)[0]
    residual = target - psi @ theta_ls
    r_ls = float(np.max(np.abs(residual)))
    if r_ls == 0.0:
        return ARXModel(theta_ls[:na], theta_ls[na:], noise_bound=0.0, dt=dt, method="chebyshev")
    column_scale = np.abs(psi).max(axis=0)
    psi_n = psi / column_scale
    target_n = residual / r_ls
    m, p = psi_n.shape
    ones = np.ones((m, 1))
    a_ub = scipy.sparse.csr_array(np.block([[psi_n, -ones], [-psi_n, -ones]]))
    b_ub = np.concatenate([target_n, -target_n])
    cost = np.zeros(p + 1)
    cost[-1] = 1.0
    res = scipy.optimize.linprog(
        cost,
        A_ub=a_ub,
        b_ub=b_ub,
        bounds=[(None, None)] * p + [(0.0, None)],
        method="highs",
    )
    if res.status != 0:
        raise RuntimeError(f"the Chebyshev LP did not solve: {res.message}")
    theta = theta_ls + res.x[:p] * r_ls / column_scale
    bound = float(np.max(np.abs(target - psi @ theta)))
    if bound > r_ls:  # the LP's tolerance cannot make it worse than its starting point
        theta, bound = theta_ls, r_ls
    return ARXModel(theta[:na], theta[na:], noise_bound=bound, dt=dt, method="chebyshev")


def fit_arx(
    u: Any,
    y: Any,
    *,
    na: int = 2,
    nb: int = 2,
    method: str = "bayes-uniform",
    dt: float = 1.0,
    **options: Any,
) -> ARXModel:
    """Fit an ARX(na, nb) model ``y_t = sum a_i y_{t-i} + sum b_j u_{t-j} + nu_t`` to data.

    Parameters
    ----------
    u, y
        Input (e.g. V) and output (e.g. um) records of equal length, sampled every ``dt``.
    na, nb
        Orders: past outputs and past inputs.
    method
        ``"bayes-uniform"``, ``"chebyshev"`` or ``"least-squares"`` (see the module docstring).
    dt
        Sampling period, s, stored in the model.
    **options
        For ``"bayes-uniform"`` only: ``point_estimate`` (``"final"``, default, or ``"mean"``:
        the mean of the recorded time course over its steady part), ``steady_fraction`` (the
        trailing fraction of the time course averaged by ``"mean"``, default 0.5), and the
        :class:`~identification.bayes_uniform.BayesUniformEstimator` keywords ``window``,
        ``reorient_every``, ``n_init``, ``record_history``, ``theta_estimate``.

    Returns
    -------
    ARXModel
        With ``noise_bound`` (r, output unit), ``method`` and, for ``"bayes-uniform"``, the
        ``history`` of the estimates.

    Raises
    ------
    ValueError
        Unknown method or option; data that cannot identify the model (mismatched lengths,
        NaN/inf, too few samples, constant or otherwise not persistently exciting input).
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; valid methods: {', '.join(METHODS)}")
    if method != "bayes-uniform":
        if options:
            raise ValueError(f"method {method!r} takes no options, got {', '.join(options)}")
        fit = fit_chebyshev if method == "chebyshev" else fit_least_squares
        return fit(u, y, na=na, nb=nb, dt=dt)
    return _fit_bayes_uniform(u, y, na, nb, dt, options)


def _fit_bayes_uniform(
    u: Any, y: Any, na: int, nb: int, dt: float, options: dict[str, Any]
) -> ARXModel:
    """The ``"bayes-uniform"`` branch of :func:`fit_arx` (same arguments and options)."""
    point_estimate, steady_fraction = _bayes_options(options)
    if point_estimate == "mean":
        options["record_history"] = True
    model = bayes_uniform_estimator(u, y, na=na, nb=nb, dt=dt, **options).model()
    return _steady_mean(model, steady_fraction) if point_estimate == "mean" else model


def bayes_uniform_estimator(
    u: Any, y: Any, *, na: int, nb: int, dt: float = 1.0, **options: Any
) -> BayesUniformEstimator:
    """The bayes-uniform estimator of an ARX(na, nb) model after the record ``(u, y)``.

    What :func:`fit_arx` reads its ``"bayes-uniform"`` estimate from (``.model()``), for a
    caller that goes on with more of the record: the estimator is recursive, so
    ``update_many`` with the rest gives the whole record's estimate (``tests/test_arx.py``
    holds it against the estimate of the whole record at once).

    Parameters
    ----------
    u, y, na, nb, dt
        As :func:`fit_arx`.
    **options
        :class:`~identification.bayes_uniform.BayesUniformEstimator` keywords.

    Raises
    ------
    ValueError
        As :func:`fit_arx`: data that cannot identify the model, or an unknown option.
    """
    unknown = sorted(set(options) - set(_BAYES_OPTIONS))
    if unknown:
        raise ValueError(
            f"unknown estimator option(s) {', '.join(unknown)}; valid: {', '.join(_BAYES_OPTIONS)}"
        )
    u, y = _check_data(u, y, na, nb)
    estimator = BayesUniformEstimator(na, nb, dt=dt, **options)
    rows = y.size - max(na, nb)
    if rows < estimator.n_init:
        raise ValueError(
            f"too few samples for bayes-uniform: it starts from its first n_init = "
            f"{estimator.n_init} regression rows, so an ARX({na},{nb}) needs at least "
            f"{estimator.n_init + max(na, nb)} samples, {y.size} given (pass a smaller n_init, "
            f">= {na + nb + 1}, or use method='chebyshev')"
        )
    estimator.update_many(u, y)
    if not estimator.initialized:
        raise ValueError(_never_bounded(u, y, na, nb))
    return estimator


def _never_bounded(u: np.ndarray, y: np.ndarray, na: int, nb: int) -> str:
    """Why the bayes-uniform estimator never bounded its noise-bound support: data an ARX
    model fits without noise (the support of 1/r is unbounded), or data that do not excite it.
    "Without noise": a least-squares residual within 1e-6 of the output's peak, ten times the
    default feasibility tolerance (1e-7) of HiGHS, which solves the estimator's LPs on data
    scaled to unit peak, so below it the LPs cannot resolve the bound."""
    psi, target = regressors(u, y, na, nb)
    theta = np.linalg.lstsq(psi, target, rcond=None)[0]
    r_ls, peak = float(np.max(np.abs(target - psi @ theta))), float(np.max(np.abs(target)))
    if r_ls <= 1e-6 * peak:
        return (
            f"the data fit an ARX({na},{nb}) with (almost) no noise (largest least-squares "
            f"residual {r_ls:.3g} against an output peak of {peak:.3g}): the uniform-noise "
            "posterior needs a noise bound above the numbers' resolution; fit noise-free data "
            "with method='chebyshev' or 'least-squares'"
        )
    return "the data never bounded the noise-bound support (not persistently exciting)"


def _bayes_options(options: dict[str, Any]) -> tuple[str, float]:
    """Pop and check ``point_estimate`` and ``steady_fraction``; refuse unknown options."""
    point_estimate = options.pop("point_estimate", "final")
    steady_fraction = float(options.pop("steady_fraction", 0.5))
    unknown = sorted(set(options) - set(_BAYES_OPTIONS))
    if unknown:
        raise ValueError(
            f"unknown option(s) {', '.join(unknown)} for 'bayes-uniform'; accepted: "
            f"point_estimate, steady_fraction, {', '.join(_BAYES_OPTIONS)}"
        )
    if point_estimate not in ("final", "mean"):
        raise ValueError(f"point_estimate must be 'final' or 'mean', got {point_estimate!r}")
    if not 0.0 < steady_fraction <= 1.0:
        raise ValueError(f"steady_fraction must be in (0, 1], got {steady_fraction}")
    return point_estimate, steady_fraction


def _steady_mean(model: ARXModel, steady_fraction: float) -> ARXModel:
    """The mean of the recorded estimates over the trailing ``steady_fraction`` of the run."""
    history = model.history
    start = int(len(history["t"]) * (1.0 - steady_fraction))
    theta = history["theta"][start:].mean(axis=0)
    return ARXModel(
        theta[: model.na],
        theta[model.na :],
        noise_bound=float(history["noise_bound"][start:].mean()),
        dt=model.dt,
        history=history,
        method="bayes-uniform",
    )
