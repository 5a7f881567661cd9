"""Figures of an identification run (the paper's Figs. 5-10 and a residual check), as PNG."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["write_figures"]


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_figures(result: Any, out: str | Path) -> list[Path]:
    """Write the four figures of an :class:`IdentificationResult` into ``out``; return paths."""
    out = Path(out)
    data = result.data
    return [
        _arx_estimates(data, result.report, out / "arx_estimates.png"),
        _hysteresis(data, out / "hysteresis.png"),
        _validation(data, result.report, out / "validation.png"),
        _residuals(data, out / "residuals.png"),
    ]


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
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _hysteresis(data: dict, path: Path) -> Path:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 5), dpi=110)
    ax.plot(data["u_rich"], data["z_hat"], ".", ms=1.5, color="0.65", label="z_hat (inverse ARX)")
    ax.plot(data["u_rich"], data["z_model"], lw=1, color="tab:red", label="NLS output")
    ax.set_xlabel("drive voltage u (V)")
    ax.set_ylabel("hidden signal z (equivalent V)")
    ax.set_title("Identified hysteresis (rich data)")
    ax.legend(loc="upper left", markerscale=6)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _validation(data: dict, report: dict, path: Path) -> Path:
    plt = _pyplot()
    t = np.arange(len(data["y_val"])) * data["dt"]
    val = report["validation"]
    fig, ax = plt.subplots(figsize=(10, 4.8), dpi=110)
    # The linear ARX underneath, the measurement and the identified model on top.
    ax.plot(
        t,
        data["y_lin"],
        color="tab:blue",
        lw=0.7,
        alpha=0.6,
        label=f"linear ARX ({val['linear_arx']['fit_percent']:.1f} %)",
    )
    ax.plot(t, data["y_val"], color="0.35", lw=1.2, label="measured")
    ax.plot(
        t,
        data["y_sim"],
        color="tab:red",
        lw=0.8,
        ls="--",
        label=f"Hammerstein, free run ({val['hammerstein']['fit_percent']:.1f} %)",
    )
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tip deflection (um)")
    ax.set_title(f"Validation on fresh {val['signal']}")
    ax.legend(loc="lower left", fontsize=8)
    # Zoomed inset on a short window around the largest excursion.
    centre = int(np.argmax(np.abs(data["y_val"])))
    half = max(25, len(t) // 200)
    lo, hi = max(0, centre - half), min(len(t), centre + half)
    inset = ax.inset_axes([0.68, 0.62, 0.3, 0.34])
    inset.plot(t[lo:hi], data["y_lin"][lo:hi], color="tab:blue", lw=0.8, alpha=0.6)
    inset.plot(t[lo:hi], data["y_val"][lo:hi], color="0.35", lw=1.5)
    inset.plot(t[lo:hi], data["y_sim"][lo:hi], color="tab:red", lw=1, ls="--")
    inset.tick_params(labelsize=7)
    ax.indicate_inset_zoom(inset, edgecolor="0.3")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def _residuals(data: dict, path: Path) -> Path:
    plt = _pyplot()
    r = data["noise_bound"]
    one_step = data["y_val"] - data["prediction_val"]
    free_run = data["y_val"] - data["y_sim"]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=110)
    for ax, res, title in ((axes[0], one_step, "one-step-ahead"), (axes[1], free_run, "free run")):
        ax.hist(res, bins=80, color="tab:gray")
        for sign in (-1, 1):
            ax.axvline(sign * r, color="tab:red", ls="--", lw=1)
        ax.set_title(f"{title} residuals; dashed: +-r_hat = {r:.2f} um")
        ax.set_xlabel("residual (um)")
    axes[0].set_ylabel("count")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path
