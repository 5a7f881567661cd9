"""Tracking metrics of one closed-loop episode: the single home of every benchmark figure."""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

__all__ = ["SETTLING_WINDOW_S", "step_metrics", "tracking_metrics", "window_settling_ms"]


SETTLING_WINDOW_S = 0.05
"""Window of :func:`window_settling_ms` (s): 50 ms, five periods of a 100 Hz reference and
half a period of a 10 Hz one, short enough to see a start, long enough to average the
sensor noise over 50 samples at 1 kHz."""


def window_settling_ms(
    error: np.ndarray, dt: float, window_s: float = SETTLING_WINDOW_S, floor: float | None = None
) -> float | None:
    """When (ms) the RMS error over consecutive ``window_s`` windows last came within twice
    ``floor`` (default: the error's own second-half RMS; the unit of ``error``): the end of the
    first window from which every later window stays there; one window past the episode's
    end when the last window is still above (never settled). A trailing part shorter than a
    window is not judged; None for an episode shorter than one window or an error that is
    not finite (nothing to judge).

    This is how soon an adaptive controller reaches the error it keeps: twice its own
    second half, so a controller that settles to a lower floor is held to a lower bar.
    """
    width = max(1, round(window_s / dt))
    error = np.asarray(error, float)
    if error.size < width or not np.all(np.isfinite(error)):
        return None
    if floor is None:
        floor = float(np.sqrt(np.mean(error[error.size // 2 :] ** 2)))
    whole = error[: error.size // width * width].reshape(-1, width)
    windows = np.sqrt(np.mean(whole**2, axis=1))
    above = np.flatnonzero(windows > 2.0 * floor)
    windows_ms = (above[-1] + 2 if above.size else 1) * width * dt * 1e3
    return round(float(windows_ms), 6)  # whole windows: no 950.0000000000001 ms


def tracking_metrics(
    *,
    deflection_um: np.ndarray,
    reference_um: np.ndarray,
    voltage_v: np.ndarray,
    saturated: np.ndarray,
    compute_s: np.ndarray,
    stroke_um: float,
    fallbacks: int = 0,
    dt: float | None = None,
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
    dt : float, optional
        Sample time (s): with it, ``deadline_misses`` (steps whose compute time exceeded dt)
        and the step-response figures of :func:`step_metrics` are added.

    Returns
    -------
    dict
        ``rmse_um``, ``rmse_percent``, ``rmse_second_half_percent`` (over the second half
        of the episode: after an adaptive controller has adapted), ``max_error_um``,
        ``max_error_percent``, ``rms_voltage_v``, ``voltage_tv_v`` (total variation,
        sum |u_t - u_t-1|),
        ``saturated_fraction``, ``compute_median_us``, ``compute_p99_us``, ``compute_max_us``,
        ``fallbacks``, ``steps``; with ``dt`` also ``deadline_misses``,
        ``window_settling_ms`` (:func:`window_settling_ms`) and
        ``rise_time_ms``, ``overshoot_percent``, ``settling_time_ms``, ``steps_settled``
        (None on a reference without steps).
    """
    arrays = _checked_arrays(deflection_um, reference_um, voltage_v, saturated, stroke_um)
    error = arrays["deflection_um"] - arrays["reference_um"]
    voltage = arrays["voltage_v"]
    saturated = arrays["saturated"]
    times = np.asarray(compute_s, float) * 1e6
    full_stroke = 2.0 * stroke_um
    rmse = float(np.sqrt(np.mean(error**2)))
    second_half = float(np.sqrt(np.mean(error[error.size // 2 :] ** 2)))
    max_error = float(np.max(np.abs(error)))
    median, p99, worst = np.quantile(times, [0.5, 0.99, 1.0]) if times.size else (0.0,) * 3
    extra: dict[str, Any] = {}
    if dt is not None:
        extra["deadline_misses"] = int(np.sum(times > dt * 1e6))
        extra["window_settling_ms"] = window_settling_ms(error, dt, floor=second_half)
        extra.update(step_metrics(arrays["deflection_um"], arrays["reference_um"], dt, stroke_um))
    return {
        "steps": int(error.size),
        "rmse_um": rmse,
        "rmse_percent": 100.0 * rmse / full_stroke,
        "rmse_second_half_percent": 100.0 * second_half / full_stroke,
        "max_error_um": max_error,
        "max_error_percent": 100.0 * max_error / full_stroke,
        "rms_voltage_v": float(np.sqrt(np.mean(voltage**2))),
        "voltage_tv_v": float(np.sum(np.abs(np.diff(voltage)))),
        "saturated_fraction": float(np.mean(saturated)),
        "compute_median_us": float(median),
        "compute_p99_us": float(p99),
        "compute_max_us": float(worst),
        "fallbacks": int(fallbacks),
        **extra,
    }


def _checked_arrays(
    deflection_um: Any, reference_um: Any, voltage_v: Any, saturated: Any, stroke_um: float
) -> dict[str, np.ndarray]:
    """The episode's columns as arrays, or ValueError naming the one that is wrong."""
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
    return arrays


def step_metrics(
    deflection_um: np.ndarray, reference_um: np.ndarray, dt: float, stroke_um: float
) -> dict[str, Any]:
    """Rise time, overshoot and settling time of the steps in a reference (medians over steps).

    A step is a jump of the reference by more than 1 % of the full stroke between two constant
    levels (a fast sine is not a step); its response is read over the first 3/4 of the hold (a
    controller with preview moves before the next step). With ``s = (y - r_before) / (r_after -
    r_before)``: rise time from s = 0.1 to s = 0.9, overshoot ``100 max(s - 1, 0)`` %, settling
    time from the jump until ``|y - r_after|`` stays within 2 % of the jump (the definitions of
    python-control's ``step_info``). Sample i of the arrays is the outcome of action a_i
    against reference sample r_i; time is counted from the first sample of the new level.

    Returns
    -------
    dict
        ``rise_time_ms``, ``overshoot_percent``, ``settling_time_ms`` (None where there is no
        step, or no step rose or settled) and ``steps_settled`` ("k of n").
    """
    y, r = np.asarray(deflection_um, float), np.asarray(reference_um, float)
    d = np.abs(np.diff(r))
    flat = np.concatenate([[False], d <= 1e-9 * stroke_um, [False]])  # level before / after
    jumps = np.flatnonzero((d > 0.02 * stroke_um) & flat[:-2] & flat[2:]) + 1
    bounds = np.append(jumps, r.size)
    rise, over, settle = [], [], []
    for start, end in itertools.pairwise(bounds):
        stop = start + max((3 * (end - start)) // 4, 1)
        before, after = r[start - 1], r[start]
        s = (y[start:stop] - before) / (after - before)
        ten, ninety = np.flatnonzero(s >= 0.1), np.flatnonzero(s >= 0.9)
        if ten.size and ninety.size:
            rise.append((ninety[0] - ten[0]) * dt)
        over.append(100.0 * max(float(s.max()) - 1.0, 0.0))
        outside = np.flatnonzero(np.abs(s - 1.0) > 0.02)
        if outside.size < s.size and (outside.size == 0 or outside[-1] < s.size - 1):
            settle.append((outside[-1] + 1 if outside.size else 0) * dt)

    def median_ms(values: list[float], scale: float = 1e3) -> float | None:
        return float(np.median(values)) * scale if values else None

    return {
        "rise_time_ms": median_ms(rise),
        "overshoot_percent": median_ms(over, 1.0),
        "settling_time_ms": median_ms(settle),
        "steps_settled": f"{len(settle)} of {jumps.size}" if jumps.size else None,
    }
