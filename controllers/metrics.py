"""Tracking metrics of one closed-loop episode: the single home of every benchmark figure."""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["tracking_metrics"]


def tracking_metrics(
    *,
    deflection_um: np.ndarray,
    reference_um: np.ndarray,
    voltage_v: np.ndarray,
    saturated: np.ndarray,
    compute_s: np.ndarray,
    stroke_um: float,
    fallbacks: int = 0,
) -> dict[str, Any]:
    """Figures of merit of an episode.

    Parameters
    ----------
    deflection_um : ndarray, shape (T,)
        True (noise-free) tip deflection after each action (um).
    reference_um : ndarray, shape (T,)
        The reference sample each action is scored against (um).
    voltage_v : ndarray, shape (T,)
        Applied voltages (V).
    saturated : ndarray of bool, shape (T,)
        Whether the amplifier clipped each voltage.
    compute_s : ndarray, shape (T,)
        Controller compute time per step (s).
    stroke_um : float
        One-sided stroke (um); percentages are of the full stroke, 2 x stroke_um.
    fallbacks : int
        Steps where the controller used its fallback input.

    Returns
    -------
    dict
        ``rmse_um``, ``rmse_percent``, ``max_error_um``, ``max_error_percent``,
        ``rms_voltage_v``, ``voltage_tv_v`` (total variation, sum |u_t - u_t-1|),
        ``saturated_fraction``, ``compute_median_us``, ``compute_p99_us``, ``compute_max_us``,
        ``fallbacks``, ``steps``.
    """
    arrays = {
        "deflection_um": np.asarray(deflection_um, float),
        "reference_um": np.asarray(reference_um, float),
        "voltage_v": np.asarray(voltage_v, float),
        "saturated": np.asarray(saturated, bool),
    }
    steps = arrays["deflection_um"].shape
    for name, values in arrays.items():
        if values.ndim != 1 or values.shape != steps or values.size == 0:
            raise ValueError(
                f"{name} must be a non-empty 1-D array as long as deflection_um {steps}, "
                f"got shape {values.shape}"
            )
        if not np.isfinite(values).all():
            raise ValueError(f"{name} holds non-finite values")
    if not (np.isfinite(stroke_um) and stroke_um > 0):
        raise ValueError(f"stroke_um must be a positive number (um), got {stroke_um!r}")
    error = arrays["deflection_um"] - arrays["reference_um"]
    voltage = arrays["voltage_v"]
    saturated = arrays["saturated"]
    times = np.asarray(compute_s, float) * 1e6
    full_stroke = 2.0 * stroke_um
    rmse = float(np.sqrt(np.mean(error**2)))
    max_error = float(np.max(np.abs(error)))
    median, p99, worst = np.quantile(times, [0.5, 0.99, 1.0]) if times.size else (0.0,) * 3
    return {
        "steps": int(error.size),
        "rmse_um": rmse,
        "rmse_percent": 100.0 * rmse / full_stroke,
        "max_error_um": max_error,
        "max_error_percent": 100.0 * max_error / full_stroke,
        "rms_voltage_v": float(np.sqrt(np.mean(voltage**2))),
        "voltage_tv_v": float(np.sum(np.abs(np.diff(voltage)))),
        "saturated_fraction": float(np.mean(saturated)),
        "compute_median_us": float(median),
        "compute_p99_us": float(p99),
        "compute_max_us": float(worst),
        "fallbacks": int(fallbacks),
    }
