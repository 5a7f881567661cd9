"""Figures of an identification run (the paper's Figs. 5-10 and a residual check), as PNG."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from identification.metrics import complex_response

__all__ = ["hysteresis_loops", "write_figures"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, path: Path) -> Path:
    """Lay ``fig`` out tightly, write it to ``path`` as PNG and close it; return ``path``.

    ``tight_layout`` leaves a placeholder layout engine on the figure, and ``savefig`` first
    draws a figure that has any layout engine once without rendering, to lay it out. The
    layout is done by then: without the engine the figure is drawn once, to the same pixels.
    The engine is removed with the rc settings that would otherwise install another one in
    its place (``figure.autolayout``, ``figure.constrained_layout.use``, from a user's
    matplotlibrc or style) turned off, so the tight layout stands whatever they say.
    """
    fig.tight_layout()
    with plt.rc_context({"figure.autolayout": False, "figure.constrained_layout.use": False}):
        fig.set_layout_engine(None)
    fig.savefig(path)
    plt.close(fig)
    return path


def write_figures(result: Any, out: str | Path, runner: Any | None = None) -> list[Path]:
    """Write the figures of an :class:`IdentificationResult` into ``out``; return their paths.

    Four always; a fifth, the Bode plot of the linear part after steps b, b' and e' against the
    true plant's, when the run refined it and its data hold the plant's linear part. A
    ``runner`` whose helper is idle (:class:`identification.runner.StepRunner`) draws the
    hysteresis and validation figures there meanwhile (about half of the drawing time; with
    matplotlib's default settings there, not a style set in this process).
    """
    from identification.runner import StepRunner

    out = Path(out)
    data = result.data
    runner = runner if runner is not None and runner.idle else StepRunner()
    where = Path(os.path.abspath(out))  # the helper may have started in another folder
    loops = {k: data[k] for k in ("u_rich", "z_hat")}
    errors = {k: data[k] for k in ("dt", "y_val", "y_lin", "y_sim")}
    beside = {
        "hysteresis": runner.beside(_hysteresis, loops, result.model, where / "hysteresis.png"),
        "validation": runner.beside(_validation, errors, result.report, where / "validation.png"),
    }
    paths = [_arx_estimates(data, result.report, out / "arx_estimates.png")]
    paths += [out / f"{name}.png" for name in beside]  # drawn beside, in this order
    paths.append(_residuals(data, result.report, out / "residuals.png"))
    if data.get("arx_unrefined") is not None and data.get("plant_linear") is not None:
        paths.append(_bode(data, result.model.arx, out / "linear_part_bode.png"))
    for pending in beside.values():
        pending.result()
    return paths


def _bode(data: dict, refined: Any, path: Path) -> Path:
    """Frequency response of the step b estimate, the step b' refinement and the model's linear
    part (after step e', when it refined it further) against the true plant's linear part, each
    normalised to its static gain (z is in equivalent volts)."""
    import control

    plt = _pyplot()
    plant = data["plant_linear"]
    nyquist = 0.5 / data["dt"]
    f = np.logspace(0, np.log10(nyquist * 0.999), 400)
    w = 2.0 * np.pi * f
    curves = (
        ("true plant (linear part)", plant, float(np.real(control.dcgain(plant))), "k", "-", 2.4),
        (
            "step b: bayes-uniform ARX",
            data["arx_unrefined"].to_state_space(),
            data["arx_unrefined"].static_gain(),
            "tab:blue",
            "--",
            1.2,
        ),
    )
    step_b2 = data.get("arx_step_b2")
    if step_b2 is not None and step_b2 is not refined:
        curves += (
            (
                "step b': output-error refinement",
                step_b2.to_state_space(),
                step_b2.static_gain(),
                "tab:red",
                "-.",
                1.2,
            ),
        )
    label = "step b': output-error refinement"
    if data.get("linear_refined_by_e2"):
        label = "step e': refined with the network"
    curves += ((label, refined.to_state_space(), refined.static_gain(), "tab:green", "-", 1.2),)
    fig, (ax_m, ax_p, ax_e) = plt.subplots(3, 1, figsize=(8, 9), dpi=110, sharex=True)
    truth = None
    for label, system, gain, colour, style, width in curves:
        response = complex_response(system, w) / gain
        ax_m.loglog(f, np.abs(response), color=colour, ls=style, lw=width, label=label)
        ax_p.semilogx(
            f, np.degrees(np.unwrap(np.angle(response))), color=colour, ls=style, lw=width
        )
        if truth is None:
            truth = response
        else:
            error = np.abs(response - truth) / np.abs(truth)
            ax_e.loglog(f, 100 * error, color=colour, ls=style, lw=width, label=label)
    ax_m.set_ylabel("|G| / static gain")
    ax_p.set_ylabel("phase (deg)")
    ax_e.set_ylabel("|G - P| / |P| (%)")
    ax_e.set_xlabel("frequency (Hz)")
    ax_m.legend(fontsize=8, loc="lower left")
    ax_e.legend(fontsize=8, loc="upper left")
    for ax in (ax_m, ax_p, ax_e):
        ax.grid(alpha=0.3, which="both")
        ax.set_xlim(f[0], f[-1])
    fig.suptitle("Linear part before and after the output-error refinements, against the plant")
    return _save(plt, fig, path)


def _arx_estimates(data: dict, report: dict, path: Path) -> Path:
    plt = _pyplot()
    history = data.get("arx_history") or {}
    order = report["arx"]["order"]
    fig, (ax_a, ax_b, ax_r) = plt.subplots(3, 1, figsize=(8, 7.5), dpi=110, sharex=True)
    if history:
        t = np.asarray(history["t"]) * data["dt"]
        theta = np.asarray(history["theta"])
        for i in range(order):
            ax_a.plot(t, theta[:, i], lw=1, label=f"a{i + 1}")
            ax_b.plot(t, theta[:, order + i], lw=1, label=f"b{i + 1}")
        ax_r.plot(t, np.asarray(history["noise_bound"]), color="k", lw=1)
    ax_a.set_ylabel("a_i")
    ax_b.set_ylabel("b_j (um/V)")
    ax_r.set_ylabel("r_hat (um)")
    ax_r.set_xlabel("time of the PRBS record (s)")
    for ax in (ax_a, ax_b):
        ax.legend(ncol=order, fontsize=7, loc="upper right")
    for ax in (ax_a, ax_b, ax_r):
        ax.grid(alpha=0.3)
    fig.suptitle(f"ARX({order},{order}) estimates by the uniform-noise Bayesian recursion")
    return _save(plt, fig, path)


LOOP_FRACTIONS = (1 / 3, 2 / 3, 1.0)
"""Amplitudes of the loops in hysteresis.png, as fractions of the rich record's largest |u|."""

LOOP_SAMPLES = 400
"""Samples per quarter period of each loop's triangle: the memory features are rate
independent, so only the drawing's smoothness depends on it."""


def hysteresis_loops(model: Any, u_max: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The model's nonlinearity over one slow triangle period at each of
    :data:`LOOP_FRACTIONS` of ``u_max`` (V): (u, z) pairs from the top of the loop down and
    back up.

    Each triangle starts at rest (0 V) and rises to its amplitude first; the period drawn
    follows a settling one, so it runs on the closed loop, not on the first-loading curve
    (a Bouc-Wen memory overshoots on its first cycle).
    """
    first = np.linspace(0.0, 1.0, LOOP_SAMPLES, endpoint=False)  # from rest to the top
    down = np.linspace(1.0, -1.0, 2 * LOOP_SAMPLES, endpoint=False)
    up = np.linspace(-1.0, 1.0, 2 * LOOP_SAMPLES, endpoint=False)
    shape = np.r_[first, down, up, down, up, 1.0]  # a settling period, then the drawn one
    drawn = down.size + up.size + 1
    loops = []
    for fraction in LOOP_FRACTIONS:
        u = fraction * u_max * shape
        z = np.asarray(model.nls_output(u))
        loops.append((u[-drawn:], z[-drawn:]))
    return loops


def _hysteresis(data: dict, model: Any, path: Path) -> Path:
    """The identified loops: z against u (left) and the loops' width, z - u (right), over
    the rich record's z_hat; the network's small-signal gain is 1, so z - u is the hysteresis."""
    plt = _pyplot()
    fig, (ax, ax_width) = plt.subplots(1, 2, figsize=(11, 5), dpi=110)
    u_rich, z_hat = data["u_rich"], data["z_hat"]
    loops = hysteresis_loops(model, float(np.max(np.abs(u_rich))))
    for axis, offset in ((ax, 0.0), (ax_width, 1.0)):
        axis.plot(
            u_rich, z_hat - offset * u_rich, ".", ms=1, color="0.8", label="z_hat (inverse ARX)"
        )
        for (u, z), colour in zip(loops, ("tab:blue", "tab:orange", "tab:red"), strict=True):
            axis.plot(u, z - offset * u, lw=1, color=colour, label=f"model, +-{u.max():.0f} V")
        axis.set_xlabel("drive voltage u (V)")
        axis.grid(alpha=0.3)
    ax.set_ylabel("hidden signal z (equivalent V)")
    ax_width.set_ylabel("z - u (equivalent V): the hysteresis")
    ax.legend(loc="upper left", markerscale=6, fontsize=8)
    fig.suptitle("Identified hysteresis: one slow triangle period per amplitude, on the rich data")
    return _save(plt, fig, path)


ZOOM_S = 0.2
"""Length of the zoom window of the validation figure, s."""


RMS_WINDOW_S = 0.05
"""Window of the moving RMS drawn over the error traces, s."""


def _moving_rms(x: np.ndarray, n: int) -> np.ndarray:
    """Centred moving RMS of ``x`` over ``n`` samples (shorter at the ends)."""
    power = np.convolve(x**2, np.ones(n), mode="same")
    count = np.convolve(np.ones_like(x), np.ones(n), mode="same")
    return np.sqrt(power / count)


def _validation(data: dict, report: dict, path: Path) -> Path:
    """Error over time of both models (um, with the sensor-noise band) and a 200 ms zoom."""
    plt = _pyplot()
    dt, y = data["dt"], np.asarray(data["y_val"])
    t = np.arange(len(y)) * dt
    val = report["validation"]
    noise = report["environment"]["noise_bound_um"]
    models = (
        ("linear ARX", "linear_arx", np.asarray(data["y_lin"]), "tab:blue", "-"),
        ("Hammerstein", "hammerstein", np.asarray(data["y_sim"]), "tab:red", "--"),
    )
    errors = {key: y - y_hat for _, key, y_hat, _, _ in models}
    half = max(1, round(ZOOM_S / dt / 2))
    centre = int(np.argmax(np.abs(errors["hammerstein"])))
    lo = min(max(0, centre - half), max(0, len(y) - 2 * half))
    hi = min(len(y), lo + 2 * half)
    fig, axes = plt.subplots(
        4, 1, figsize=(10, 11), dpi=110, gridspec_kw={"height_ratios": [1, 1, 1.3, 0.8]}
    )
    _error_panels(axes[:2], t, models, errors, val, noise, (lo, hi), dt)
    _zoom_panels(axes[2], axes[3], t, y, models, errors, val, noise, (lo, hi, centre))
    fig.suptitle(f"Validation on fresh {val['signal']}, {val['samples']} samples, free run")
    return _save(plt, fig, path)


def _error_panels(axes, t, models, errors, val, noise, window, dt) -> None:
    """Both models' error over the whole record, its moving RMS and the zoom window."""
    lo, hi = window
    n_rms = max(1, round(RMS_WINDOW_S / dt))
    for ax, (name, key, _, colour, _) in zip(axes, models, strict=True):
        m, err = val[key], errors[key]
        ax.plot(t, err, color=colour, lw=0.5, alpha=0.45, label="error")
        ax.plot(
            t,
            _moving_rms(err, n_rms),
            color="k",
            lw=1.2,
            label=f"moving RMS ({RMS_WINDOW_S * 1e3:.0f} ms)",
        )
        ax.axvspan(t[lo], t[hi - 1], color="gold", alpha=0.3, lw=0, label="zoom window")
        ax.set_ylabel("error (um)")
        ax.set_title(
            f"{name} free run, error = measured - simulated: fit {m['fit_percent']:.2f} %, "
            f"RMSE {m['rmse']:.2f} um, max {m['max_abs_error']:.1f} um",
            fontsize=10,
        )
        ax.set_xlim(t[0], t[-1])
        ax.grid(alpha=0.3)
    for sign in (-1, 1) if noise is not None else ():  # what a perfect model would leave
        axes[1].axhline(
            sign * noise,
            color="k",
            ls=":",
            lw=1.2,
            label=f"sensor noise bound +-{noise:g} um" if sign > 0 else None,
        )
    for ax in axes:
        ax.legend(loc="upper right", fontsize=8, ncol=4)
    axes[1].set_xlabel("time (s)")


def _zoom_panels(zoom, zoom_err, t, y, models, errors, val, noise, window) -> None:
    """The measured and simulated deflections around the largest error, and that error."""
    lo, hi, centre = window
    tz = (t[lo:hi] - t[lo]) * 1e3
    zoom.plot(tz, y[lo:hi], color="k", lw=2.4, label="measured")
    for name, key, y_hat, colour, style in models:
        zoom.plot(
            tz,
            y_hat[lo:hi],
            color=colour,
            lw=1.2,
            ls=style,
            label=f"{name} ({val[key]['fit_percent']:.1f} %)",
        )
    zoom_err.plot(tz, errors["hammerstein"][lo:hi], color="tab:red", lw=1.2, label="Hammerstein")
    if noise is not None:  # the sensor's bound, when the records say it
        zoom_err.axhspan(-noise, noise, color="0.6", alpha=0.5, lw=0, label=f"+-{noise:g} um noise")
    zoom.set_ylabel("tip deflection (um)")
    zoom.set_title(
        f"{ZOOM_S * 1e3:.0f} ms zoom around the largest Hammerstein error "
        f"({abs(errors['hammerstein'][centre]):.1f} um at t = {t[centre]:.3f} s)",
        fontsize=10,
    )
    zoom_err.set_ylabel("Hammerstein\nerror (um)")
    zoom_err.set_xlabel(f"time from t = {t[lo]:.3f} s (ms)")
    for ax in (zoom, zoom_err):
        ax.set_xlim(tz[0], tz[-1])
        ax.grid(alpha=0.3)
    zoom.legend(loc="upper center", bbox_to_anchor=(0.5, -0.04), fontsize=8, ncol=3)
    zoom_err.legend(loc="upper right", fontsize=8, ncol=2)


def _residuals(data: dict, report: dict, path: Path) -> Path:
    """Histograms of the validation residuals, each against the bound of its own noise: the
    one-step-ahead residual is the linear part's equation error (bounded by its r_hat), the
    free-run residual the sensor's output noise plus the model's error (the sensor's bound)."""
    plt = _pyplot()
    r_model = report["validation"]["equation_error_bound_um"]
    noise = report["environment"]["noise_bound_um"]
    one_step = data["y_val"] - data["prediction_val"]
    free_run = data["y_val"] - data["y_sim"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=110)
    panels = (
        (axes[0], one_step, "one-step-ahead", r_model, "r_hat of the model's linear part"),
        (axes[1], free_run, "free run", noise, "sensor noise bound"),
    )
    for ax, res, title, bound, label in panels:
        ax.hist(res, bins=80, color="tab:gray")
        if bound is None:  # measured records without the sensor's bound
            ax.set_title(f"{title} residuals")
        else:
            for sign in (-1, 1):
                ax.axvline(sign * bound, color="tab:red", ls="--", lw=1)
            ax.set_title(f"{title} residuals; dashed: {label} +-{bound:.2f} um", fontsize=9)
        ax.set_xlabel("residual (um)")
    axes[0].set_ylabel("count")
    return _save(plt, fig, path)
