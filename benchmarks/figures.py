"""Figures of the closed-loop benchmark: tracking windows, RMSE summary, robustness map."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.references import REFERENCES
from benchmarks.rows import seed_groups
from benchmarks.runner import DT, MONTE_CARLO, BenchmarkResult

__all__ = ["draw_figures"]

_WINDOWS = {"sine-50Hz": (0.90, 0.96), "multisine": (0.60, 0.75), "steps": (0.38, 0.46)}
"""Time windows (s) shown per reference: a few periods, a readable stretch, one step."""


def draw_figures(result: BenchmarkResult, out: Path) -> list[Path]:
    """Write tracking.png, summary.png and robustness.png into ``out``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    return [
        _tracking(result, out / "tracking.png"),
        _summary(result, out / "summary.png"),
        _robustness(result, out / "robustness.png"),
    ]


def _shown_rows(result: BenchmarkResult, refs: list[str]) -> tuple[list[str], list[str]]:
    """Rows worth a curve, and the rows left out: one seed per trained recipe, and no row whose
    RMSE is within 1 % of a row already shown on every reference drawn (nmpc beside mpc)."""
    rmse = {
        (e["controller"], e["reference"]): e["rmse_percent"]
        for e in result.episodes
        if e["plant"] == "nominal"
    }
    rows = [c for c in result.config.rows if all(c in result.traces[r] for r in refs)]
    later_seeds = {m for members in seed_groups(rows).values() for m in members[1:]}
    shown: list[str] = []
    for row in rows:
        twin = any(
            all(abs(rmse[(row, r)] / rmse[(s, r)] - 1.0) < 0.01 for r in refs) for s in shown
        )
        if row not in later_seeds and not twin:
            shown.append(row)
    return shown, [r for r in rows if r not in shown]


def _tracking(result: BenchmarkResult, path: Path) -> Path:
    import matplotlib.pyplot as plt

    refs = [r for r in _WINDOWS if r in result.traces]
    shown, omitted = _shown_rows(result, refs)
    columns = max(len(refs), 1)
    fig, axes = plt.subplots(2, columns, figsize=(5.2 * columns, 7), squeeze=False, sharex="col")
    for j, ref in enumerate(refs):
        traces = result.traces[ref]
        lo, hi = _WINDOWS[ref]
        reference = np.asarray(traces[shown[0]]["reference_um"])
        t = (np.arange(reference.size) + 1) * DT
        window = (t >= lo) & (t <= hi)
        top, bottom = axes[0, j], axes[1, j]
        for name in shown:
            y = np.asarray(traces[name]["deflection_um"])
            top.plot(t[window], y[window], lw=1.1, label=name)
            bottom.plot(t[window], (y - reference)[window], lw=1.1)
        top.plot(t[window], reference[window], "k--", lw=1.6, label="reference")
        top.set_title(ref)
        top.set_ylabel("deflection (um)")
        bottom.set_ylabel("error (um)")
        bottom.set_xlabel("time (s)")
        bottom.set_yscale("symlog", linthresh=2.0)
        bottom.grid(True, alpha=0.3)
        top.grid(True, alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=8)
    note = f" (not drawn, overlapping a drawn row or another seed: {', '.join(omitted)})"
    fig.suptitle(
        "Nominal PL140: tracking (top) and error, symlog beyond 2 um (bottom)"
        + (note if omitted else ""),
        fontsize=10,
    )
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _summary(result: BenchmarkResult, path: Path) -> Path:
    import matplotlib.pyplot as plt

    cfg = result.config
    nominal = {
        (e["controller"], e["reference"]): e for e in result.episodes if e["plant"] == "nominal"
    }
    controllers = [c for c in cfg.rows if any(k[0] == c for k in nominal)]
    refs = [r for r in cfg.references if any(k[1] == r for k in nominal)]
    fig, ax = plt.subplots(figsize=(11, 5.2))
    width = 0.8 / max(len(controllers), 1)
    x = np.arange(len(refs))
    for i, c in enumerate(controllers):
        values = [nominal[(c, r)]["rmse_percent"] if (c, r) in nominal else np.nan for r in refs]
        ax.bar(x + (i - (len(controllers) - 1) / 2) * width, values, width, label=c)
    ax.set_yscale("log")
    ax.set_xticks(x, refs, rotation=20)
    ax.set_ylabel("RMSE (% of full stroke)")
    ax.set_title("Nominal PL140: tracking RMSE per controller and reference (log scale)")
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=6, loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _robustness(result: BenchmarkResult, path: Path) -> Path:
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    cfg = result.config
    index = {
        (e["plant"], e["controller"], e["reference"]): e["rmse_percent"]
        for e in result.episodes
        if e["plant"] != MONTE_CARLO
    }
    plants = [p for p in cfg.plants if p != MONTE_CARLO]
    controllers = [c for c in cfg.rows if sum(1 for k in index if k[1] == c and k[0] != "nominal")]
    # Smooth references only: a step's ~0.9 % (the drive limit) would swamp them in the mean.
    refs = sorted(
        {k[2] for k in index if k[0] != "nominal" and REFERENCES[k[2]].smooth},
        key=list(cfg.references).index,
    )
    grid = np.full((len(controllers), len(plants)), np.nan)
    for i, c in enumerate(controllers):
        for j, p in enumerate(plants):
            values = [index[(p, c, r)] for r in refs if (p, c, r) in index]
            if values:
                grid[i, j] = float(np.mean(values))
    fig, ax = plt.subplots(figsize=(1.3 * len(plants) + 3, 0.6 * len(controllers) + 2))
    finite = grid[np.isfinite(grid)]
    norm = LogNorm(vmin=max(finite.min(), 1e-3), vmax=finite.max()) if finite.size else None
    image = ax.imshow(grid, cmap="viridis", norm=norm, aspect="auto")
    for i in range(grid.shape[0]):
        for j in range(grid.shape[1]):
            if np.isfinite(grid[i, j]):
                ax.text(
                    j,
                    i,
                    f"{grid[i, j]:.3g}",
                    ha="center",
                    va="center",
                    fontsize=8,
                    color="white"
                    if norm and grid[i, j] < np.sqrt(norm.vmin * norm.vmax)
                    else "black",
                )
    ax.set_xticks(range(len(plants)), plants, rotation=25, ha="right")
    ax.set_yticks(range(len(controllers)), controllers)
    fig.colorbar(image, ax=ax, label="mean RMSE (% of full stroke)")
    ax.set_title(
        "Same model and settings on other plants: mean RMSE over " + ", ".join(refs), fontsize=9
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
