"""Fit metrics of a model output against measured data: the one home of them.

All functions take the measured output ``y`` and the model output ``y_hat`` as 1-D arrays of the
same length, in the same unit (for the bender normally micrometres, um), and return values in
that unit unless a name says percent.

- fit %: ``100 (1 - ||y - y_hat|| / ||y - mean(y)||)``, the normalized root-mean-square fit of
  MATLAB's ``compare`` and of the paper; 100 is perfect, 0 is as good as the mean, and it is
  negative for a model worse than the mean.
- RMSE: ``sqrt(mean((y - y_hat)^2))``.
- maximum absolute error: ``max |y - y_hat|``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["complex_response", "fit_metrics", "fit_percent", "max_abs_error", "rmse"]


def _pair(y: ArrayLike, y_hat: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """Validate and return ``(y, y_hat)`` as finite float64 1-D arrays of equal length."""
    y_arr = np.asarray(y, dtype=np.float64)
    y_hat_arr = np.asarray(y_hat, dtype=np.float64)
    if y_arr.ndim == 2 and 1 in y_arr.shape:
        y_arr = y_arr.reshape(-1)
    if y_hat_arr.ndim == 2 and 1 in y_hat_arr.shape:
        y_hat_arr = y_hat_arr.reshape(-1)
    if y_arr.ndim != 1 or y_hat_arr.ndim != 1:
        raise ValueError(
            f"y and y_hat must be 1-D sequences; got shapes {y_arr.shape} and {y_hat_arr.shape}"
        )
    if y_arr.shape != y_hat_arr.shape:
        raise ValueError(
            f"y and y_hat must have the same length; got {y_arr.size} and {y_hat_arr.size}"
        )
    if y_arr.size == 0:
        raise ValueError("y and y_hat are empty; a metric needs at least one sample")
    for name, arr in (("y", y_arr), ("y_hat", y_hat_arr)):
        bad = ~np.isfinite(arr)
        if bad.any():
            index = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{name} contains {int(bad.sum())} non-finite value(s) "
                f"(first at index {index}: {arr[index]}); metrics need finite data"
            )
    return y_arr, y_hat_arr


def fit_percent(y: ArrayLike, y_hat: ArrayLike) -> float:
    """Normalized fit ``100 (1 - ||y - y_hat|| / ||y - mean(y)||)`` in percent.

    Parameters
    ----------
    y : array_like, shape (T,)
        Measured output (any unit, normally um).
    y_hat : array_like, shape (T,)
        Model output, same unit as ``y``.

    Returns
    -------
    float
        Fit in percent: 100 is perfect, 0 is no better than the mean of ``y``, negative is worse.

    Raises
    ------
    ValueError
        On mismatched lengths, empty or non-finite data, or a constant ``y`` (the fit is then
        undefined).
    """
    y_arr, y_hat_arr = _pair(y, y_hat)
    spread = float(np.linalg.norm(y_arr - y_arr.mean()))
    if spread == 0.0:
        raise ValueError("y is constant; the fit percentage is undefined (use rmse instead)")
    return 100.0 * (1.0 - float(np.linalg.norm(y_arr - y_hat_arr)) / spread)


def rmse(y: ArrayLike, y_hat: ArrayLike) -> float:
    """Root-mean-square error ``sqrt(mean((y - y_hat)^2))``, in the unit of ``y`` (normally um).

    ``y`` (measured) and ``y_hat`` (model) as in :func:`fit_percent`: shape (T,), one unit.
    """
    y_arr, y_hat_arr = _pair(y, y_hat)
    return float(np.sqrt(np.mean((y_arr - y_hat_arr) ** 2)))


def max_abs_error(y: ArrayLike, y_hat: ArrayLike) -> float:
    """Largest absolute error ``max |y - y_hat|``, in the unit of ``y`` (normally um).

    ``y`` (measured) and ``y_hat`` (model) as in :func:`fit_percent`: shape (T,), one unit.
    """
    y_arr, y_hat_arr = _pair(y, y_hat)
    return float(np.max(np.abs(y_arr - y_hat_arr)))


def fit_metrics(y: ArrayLike, y_hat: ArrayLike, *, stroke: float | None = None) -> dict[str, float]:
    """All fit metrics of ``y_hat`` against ``y`` as a JSON-safe dict.

    Parameters
    ----------
    y, y_hat : array_like, shape (T,)
        Measured and model output, same unit (normally um).
    stroke : float, optional
        One-sided stroke of the actuator in the unit of ``y``: the datasheet free deflection
        (1000 um for the +-1000 um PL140). When given, RMSE and maximum error are also
        reported in percent of the full stroke, ``2 * stroke`` (-stroke to +stroke), the scale
        of the benchmark's percentages (:func:`controllers.metrics.tracking_metrics`).

    Returns
    -------
    dict
        ``fit_percent`` (%), ``rmse`` and ``max_abs_error`` (unit of ``y``), ``n_samples``, and
        with ``stroke``: ``stroke``, ``full_stroke`` (``2 * stroke``), ``rmse_percent_stroke``,
        ``max_abs_error_percent_stroke`` (% of the full stroke).

    Raises
    ------
    ValueError
        As :func:`fit_percent`, or if ``stroke`` is not a positive finite number.
    """
    y_arr, y_hat_arr = _pair(y, y_hat)
    result: dict[str, float] = {
        "fit_percent": fit_percent(y_arr, y_hat_arr),
        "rmse": rmse(y_arr, y_hat_arr),
        "max_abs_error": max_abs_error(y_arr, y_hat_arr),
        "n_samples": int(y_arr.size),
    }
    if stroke is not None:
        stroke_value = float(stroke)
        if not np.isfinite(stroke_value) or stroke_value <= 0.0:
            raise ValueError(f"stroke must be a positive finite number; got {stroke!r}")
        full_stroke = 2.0 * stroke_value
        result["stroke"] = stroke_value
        result["full_stroke"] = full_stroke
        result["rmse_percent_stroke"] = 100.0 * result["rmse"] / full_stroke
        result["max_abs_error_percent_stroke"] = 100.0 * result["max_abs_error"] / full_stroke
    return result


def complex_response(system: object, omega: ArrayLike) -> np.ndarray:
    """Complex frequency response of a SISO python-control system at ``omega`` (rad/s).

    ``FrequencyResponseData.complex`` exists from python-control 0.10.1 on; the project's floor
    (0.10.0) has only ``fresp``, which later releases deprecate. This reads whichever the
    installed release has.
    """
    import control

    response = control.frequency_response(system, np.asarray(omega, dtype=float))
    values = getattr(response, "complex", None)
    if values is None:
        values = response.fresp
    return np.asarray(values).ravel()
