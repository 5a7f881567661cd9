"""Figures of the closed-loop benchmark: tracking windows, RMSE summary, robustness map, the
tuned PID loops, and the adaptive MPC's adaptation.

Every figure copes with any selection of controllers, references and plants: a figure with
nothing to show is not written, and :func:`draw_figures` says why instead. Each row keeps its
colour in every figure; the project's rows keep theirs in every run, and the rows of a run
have distinct colours (:func:`benchmarks.rows.row_colors`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cells import aggregate
from benchmarks.references import REFERENCES
from benchmarks.rows import row_colors, seed_groups
from benchmarks.runner import DRAWN_PLANTS, BenchmarkResult
from controllers.metrics import SETTLING_WINDOW_S

__all__ = ["FIGURES", "draw_figures"]

FIGURES = ("tracking.png", "summary.png", "robustness.png", "pid_loops.png", "adaptation.png")
"""The figures a run may draw, in the report's order."""

_WINDOWS = {"sine-50Hz": (0.90, 0.96), "multisine": (0.60, 0.75), "steps": (0.38, 0.46)}
"""Time windows (s) shown per reference: a few periods, a readable stretch, one step."""


def draw_figures(
    result: BenchmarkResult, out: Path, *, identify_on: Sequence[str] = ()
) -> dict[str, Path | str]:
    """Write the figures that have something to show into ``out``.

    ``identify_on`` is the run's ``--identify-on``: the plants after its first ran on a model
    identified on themselves, and the robustness figure labels them so.

    Returns
    -------
    dict
        Figure file name -> the path written, or the reason it was not drawn (a str).
    """
    import matplotlib

    matplotlib.use("Agg")
    drawers: dict[str, Callable[[BenchmarkResult, Path], str | None]] = {
        "tracking.png": _tracking,
        "summary.png": _summary,
        "robustness.png": partial(_robustness, own_model=tuple(identify_on)[1:]),
        "pid_loops.png": _pid_loops,
        "adaptation.png": _adaptation,
    }
    figures = {name: drawers[name] for name in FIGURES}
    done: dict[str, Path | str] = {}
    for name, draw in figures.items():
        path = Path(out) / name
        reason = draw(result, path)
        done[name] = reason if reason else path
    return done


def _colours(result: BenchmarkResult) -> dict[str, str]:
    """Row -> colour for every row of the run."""
    return row_colors(list(result.config.rows))


def _bender(result: BenchmarkResult) -> str:
    return str(getattr(result.config, "bender", "PL140"))


def _wrapped(title: str, fig: Any) -> str:
    """``title`` broken into lines that fit the figure's width (10 pt text, ~13 chars/inch)."""
    import textwrap

    return textwrap.fill(title, width=max(40, int(13 * fig.get_figwidth())))


def _save(fig: Any, path: Path) -> None:
    import matplotlib.pyplot as plt

    fig.savefig(path, dpi=110)
    plt.close(fig)


def _shown_rows(result: BenchmarkResult, refs: list[str]) -> tuple[list[str], list[str]]:
    """Rows worth a curve, and the rows left out: one seed per trained recipe, and no row whose
    RMSE is within 1 % of a row already shown on every reference drawn (nmpc beside mpc)."""
    rmse = {
        (c["controller"], c["reference"]): c["rmse_percent"]
        for c in aggregate(result.episodes)
        if c["plant"] == "nominal"
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


def _tracking(result: BenchmarkResult, path: Path) -> str | None:
    import matplotlib.pyplot as plt

    refs = [r for r in _WINDOWS if result.traces.get(r)]
    if not refs:
        return f"no time series kept: none of {', '.join(_WINDOWS)} was run on the nominal plant"
    shown, omitted = _shown_rows(result, refs)
    if not shown:
        return "no controller ran every reference of the tracking figure"
    fig, axes = plt.subplots(2, len(refs), figsize=(5.2 * len(refs), 7), squeeze=False)
    for j, ref in enumerate(refs):
        traces = result.traces[ref]
        lo, hi = _WINDOWS[ref]
        reference = np.asarray(traces[shown[0]]["reference_um"])
        t = (np.arange(reference.size) + 1) * result.config.dt
        window = (t >= lo) & (t <= hi)
        top, bottom = axes[0, j], axes[1, j]
        for name in shown:
            y = np.asarray(traces[name]["deflection_um"])
            top.plot(t[window], y[window], lw=1.1, label=name, color=_colours(result)[name])
            bottom.plot(t[window], (y - reference)[window], lw=1.1, color=_colours(result)[name])
        top.plot(t[window], reference[window], "k--", lw=1.6, label="reference")
        top.set_title(ref)
        top.set_ylabel("deflection (um)")
        bottom.set_ylabel("error (um)")
        bottom.set_xlabel("time (s)")
        bottom.set_yscale("symlog", linthresh=2.0)
        for ax in (top, bottom):
            ax.grid(True, alpha=0.3)
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=min(len(labels), 8), fontsize=8)
    note = f" (not drawn, overlapping a drawn row or another seed: {', '.join(omitted)})"
    title = f"Nominal {_bender(result)}: tracking (top) and error, symlog beyond 2 um (bottom)"
    fig.suptitle(_wrapped(title + (note if omitted else ""), fig), fontsize=10)
    fig.tight_layout(rect=(0, 0.06, 1, 1))
    _save(fig, path)
    return None


def _summary(result: BenchmarkResult, path: Path) -> str | None:
    """Nominal RMSE bars per reference; the seeds of one recipe as one bar (mean, min-max)."""
    import matplotlib.pyplot as plt

    cfg = result.config
    nominal = {
        (c["controller"], c["reference"]): c["rmse_percent"]
        for c in aggregate(result.episodes)
        if c["plant"] == "nominal"
    }
    if not nominal:
        return "the nominal plant was not run"
    bars = _bars([c for c in cfg.rows if any(k[0] == c for k in nominal)])
    refs = [r for r in cfg.references if any(k[1] == r for k in nominal)]
    fig, ax = plt.subplots(figsize=(max(6.0, 1.6 * len(refs) + 3), 5.2))
    width = 0.8 / len(bars)
    x = np.arange(len(refs))
    for i, (label, members) in enumerate(bars.items()):
        values = [[nominal[(m, r)] for m in members if (m, r) in nominal] for r in refs]
        height = np.array([np.mean(v) if v else np.nan for v in values])
        offset = (i - (len(bars) - 1) / 2) * width
        spread = None
        if len(members) > 1:  # whiskers from the best to the worst seed
            low = np.array([min(v) if v else np.nan for v in values])
            high = np.array([max(v) if v else np.nan for v in values])
            spread = np.nan_to_num(np.stack([height - low, high - height]))
        ax.bar(
            x + offset,
            height,
            width,
            label=label,
            color=_colours(result)[members[0]],
            yerr=spread,
            capsize=2,
        )
    ax.set_yscale("log")
    ax.set_xticks(x, refs, rotation=20)
    ax.set_ylabel("RMSE (% of full stroke)")
    title = f"Nominal {_bender(result)}: tracking RMSE per controller and reference (log scale)"
    if any(len(m) > 1 for m in bars.values()):
        title += "; seeds of one recipe: mean, whiskers min to max"
    ax.set_title(_wrapped(title, fig), fontsize=10)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=min(len(bars), 6), loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.tight_layout()
    _save(fig, path)
    return None


def _bars(rows: list[str]) -> dict[str, list[str]]:
    """Bar label -> the rows it stands for: a row, or every seed of one trained recipe."""
    groups = seed_groups(rows)
    bars: dict[str, list[str]] = {}
    for row in rows:
        recipe = next((name for name, members in groups.items() if row in members), None)
        if recipe is None:
            bars[row] = [row]
        else:
            bars.setdefault(f"{recipe} ({len(groups[recipe])} seeds)", groups[recipe])
    return bars


def _robustness_grid(result: BenchmarkResult) -> tuple[np.ndarray, list[str], list[str], list]:
    """Mean RMSE over the smooth references: controllers x plants (NaN where not run)."""
    cfg = result.config
    index = {
        (c["plant"], c["controller"], c["reference"]): c["rmse_percent"]
        for c in aggregate(result.episodes)
        if c["plant"] not in DRAWN_PLANTS
    }
    plants = [p for p in cfg.plants if p not in DRAWN_PLANTS]
    controllers = [c for c in cfg.rows if any(k[1] == c and k[0] != "nominal" for k in index)]
    # Smooth references only: a step's RMSE, set by the drive limit, would swamp them in the
    # mean.
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
    return grid, controllers, plants, refs


def _robustness(
    result: BenchmarkResult, path: Path, own_model: Sequence[str] = ()
) -> str | None:
    """Mean RMSE per controller and plant; a plant in ``own_model`` ran on a model identified
    on itself, and its label says so (every other plant ran on the first plant's model)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm

    grid, controllers, plants, refs = _robustness_grid(result)
    if not controllers or not refs:
        return "no robustness plant was run on a smooth reference"
    fig, ax = plt.subplots(figsize=(1.3 * len(plants) + 3, 0.6 * len(controllers) + 2))
    finite = grid[np.isfinite(grid)]
    low, high = max(float(finite.min()), 1e-3), max(float(finite.max()), 2e-3)
    norm = LogNorm(vmin=low, vmax=max(high, low * 1.01))
    image = ax.imshow(np.ma.masked_invalid(grid), cmap="viridis", norm=norm, aspect="auto")
    for (i, j), value in np.ndenumerate(grid):
        if np.isfinite(value):
            dark = value < np.sqrt(norm.vmin * norm.vmax)
            ax.text(
                j,
                i,
                f"{value:.3g}",
                ha="center",
                va="center",
                fontsize=8,
                color="white" if dark else "black",
            )
    labels = [f"{p}\n(model identified on it)" if p in own_model else p for p in plants]
    ax.set_xticks(range(len(plants)), labels, rotation=25, ha="right")
    ax.set_yticks(range(len(controllers)), controllers)
    fig.colorbar(image, ax=ax, label="mean RMSE (% of full stroke)")
    ax.set_title(
        "Same model and settings on other plants: mean RMSE over " + ", ".join(refs), fontsize=9
    )
    fig.tight_layout()
    _save(fig, path)
    return None


def _loops(result: BenchmarkResult) -> dict[str, dict[str, Any]]:
    """Rows whose description carries a usable loop (``describe()["loop"]``: num, den, dt)."""
    loops = {}
    for name, d in result.controllers.items():
        loop = d.get("loop") if isinstance(d, dict) else None
        if isinstance(loop, dict) and {"num", "den", "dt"} <= loop.keys() and loop["dt"]:
            loops[name] = d
    return loops


_MARGINS = (
    ("gain_margin_db", "GM {:.1f} dB"),
    ("phase_margin_deg", "PM {:.0f} deg"),
    ("ms", "Ms {:.2f}"),
    ("crossover_hz", "crossover {:.3g} Hz"),
)
"""The margins a loop's description may give, as its legend shows them."""


def _number(d: dict[str, Any], key: str) -> float | None:
    """``d[key]`` when it is a finite number, else None."""
    value = d.get(key)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
    return float(value) if ok else None


def _margins_label(name: str, d: dict[str, Any]) -> str:
    """Legend text: the row and the margins its description gives."""
    given = [text.format(_number(d, key)) for key, text in _MARGINS if _number(d, key) is not None]
    return name + (": " + ", ".join(given) if given else " (no margins given)")


def _pid_loops(result: BenchmarkResult, path: Path) -> str | None:
    """Bode plot of every tuned loop L = C N P (magnitude, phase) and its sensitivity
    |S| = |1 / (1 + L)|, with the crossover, the phase margin and Ms marked."""
    import control
    import matplotlib.pyplot as plt

    loops = _loops(result)
    if not loops:
        return "no controller described a feedback loop (the tuned PID rows do)"
    fig, (mag, phase, sens) = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    for name, d in loops.items():
        loop = control.tf(d["loop"]["num"], d["loop"]["den"], d["loop"]["dt"])
        freqs = np.geomspace(0.1, 0.4999 / loop.dt, 3000)
        response = loop(np.exp(2j * np.pi * freqs * loop.dt))
        degrees = np.degrees(np.unwrap(np.angle(response)))
        colour = _colours(result)[name]
        mag.loglog(freqs, np.abs(response), color=colour, label=_margins_label(name, d))
        phase.semilogx(freqs, degrees, color=colour)
        sens.loglog(freqs, np.abs(1.0 / (1.0 + response)), color=colour)
        _mark_margins(d, colour, (mag, phase, sens))
    mag.axhline(1.0, color="k", lw=0.8)
    phase.axhline(-180.0, color="k", lw=0.8)
    mag.set_ylabel("|L| (loop gain)")
    phase.set_ylabel("phase of L (deg)")
    sens.set_ylabel("|S| = |1 / (1 + L)|")
    sens.set_xlabel("frequency (Hz)")
    for ax in (mag, phase, sens):
        ax.grid(True, which="both", alpha=0.3)
    mag.legend(fontsize=8)
    title = (
        f"Tuned loops on the identified {_bender(result)} model: crossover dashed, phase margin "
        "as a bar above -180 deg, Ms dotted"
    )
    mag.set_title(_wrapped(title, fig), fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    return None


def _mark_margins(d: dict[str, Any], colour: str, axes: tuple) -> None:
    """Crossover (dashed, every panel), phase margin (a bar up from -180 deg), Ms (dotted)."""
    _, phase, sens = axes
    crossover, margin, ms = (_number(d, k) for k in ("crossover_hz", "phase_margin_deg", "ms"))
    if crossover is not None and crossover > 0:
        for ax in axes:
            ax.axvline(crossover, color=colour, lw=0.8, ls="--")
        if margin is not None:
            phase.plot([crossover] * 2, [-180.0, margin - 180.0], color=colour, lw=3, alpha=0.5)
    if ms is not None:
        sens.axhline(ms, color=colour, lw=0.8, ls=":")


def plant_ratios(plant: str, bender: str, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plant's DC gain and first resonance relative to the nominal bender's, over ``times``
    (s): the truth the adaptive MPC's estimates are drawn against.

    A tolerance plant's datasheet gives both (free deflection and resonance ratios); the drift
    plant's gain moves as piezo / stiffness and its resonance as sqrt(stiffness)
    (:mod:`piezo_env.drift`); any other plant is taken as nominal.
    """
    from benchmarks.plants import PLANTS
    from piezo_env import get_datasheet

    options = PLANTS[plant](bender)
    ones = np.ones_like(times, dtype=float)
    drift = options.get("drift")
    if drift is not None:
        piezo, stiffness = drift.factors(times)
        return piezo / stiffness, np.sqrt(stiffness)
    sheet = options.get("bender")
    if sheet is None or isinstance(sheet, str):
        return ones, ones
    nominal = get_datasheet(bender)
    return (
        ones * sheet.free_deflection / nominal.free_deflection,
        ones * sheet.resonance / nominal.resonance,
    )


def _rolling_rms(error: np.ndarray, width: int) -> np.ndarray:
    squares = np.convolve(np.asarray(error, float) ** 2, np.ones(width) / width, mode="valid")
    return np.sqrt(squares)


def _adaptation(result: BenchmarkResult, path: Path) -> str | None:
    """Tracking error envelope of mpc and mpc-adaptive on each adaptation plant, and the
    adaptive model's DC gain and first resonance against the plant's (relative to nominal)."""
    import matplotlib.pyplot as plt

    from benchmarks.runner import ADAPTATION_REFERENCE

    plants = [
        key.split(":", 1)[1]
        for key, rows in result.traces.items()
        if key.startswith("adaptation:") and any("models" in row for row in rows.values())
    ]
    if not plants:
        return "mpc-adaptive was not run on an adaptation plant (stiffness+20%, drift)"
    bender = _bender(result)
    full_stroke = 2.0 * float(result.config.stroke_um)
    fig, axes = plt.subplots(2, len(plants), figsize=(5.2 * len(plants), 6.4), squeeze=False)
    dt = result.config.dt
    window_s = SETTLING_WINDOW_S
    width = max(1, round(window_s / dt))  # samples of the rolling RMS
    for j, plant in enumerate(plants):
        rows = result.traces[f"adaptation:{plant}"]
        top, bottom = axes[0, j], axes[1, j]
        for name, row in rows.items():
            rms = 100.0 * _rolling_rms(row["error_um"], width) / full_stroke
            t = (np.arange(rms.size) + width) * dt
            top.semilogy(t, rms, color=_colours(result)[name], label=name, lw=1.2)
        top.set_title(
            f"{plant}, {ADAPTATION_REFERENCE}: RMSE over {window_s * 1e3:g} ms", fontsize=9
        )
        top.set_ylabel("% of full stroke")
        top.legend(fontsize=8)
        adaptive = next(row for row in rows.values() if "models" in row)
        models = np.asarray(adaptive["models"], float)
        gain0, resonance0 = adaptive["offline"]
        times = np.r_[0.0, models[:, 0] * dt, len(adaptive["error_um"]) * dt]
        gains = np.r_[1.0, models[:, 1] / gain0, models[-1, 1] / gain0]
        resonances = np.r_[1.0, models[:, 2] / resonance0, models[-1, 2] / resonance0]
        true_gain, true_resonance = plant_ratios(plant, bender, times)
        if models.shape[1] >= 7:  # the set the data still allow: gain and resonance bands
            edges = np.r_[models[:, 0] * dt, len(adaptive["error_um"]) * dt]
            for low, high, base, colour in ((3, 4, gain0, "C0"), (5, 6, resonance0, "C3")):
                bottom.fill_between(
                    edges,
                    np.r_[models[:, low], models[-1, low]] / base,
                    np.r_[models[:, high], models[-1, high]] / base,
                    step="post",
                    color=colour,
                    alpha=0.15,
                    lw=0,
                )
        bottom.step(
            times, gains, where="post", color="C0", lw=2.2, label="model DC gain (band: its set)"
        )
        bottom.step(
            times,
            resonances,
            where="post",
            color="C3",
            label="model first resonance (band: its set)",
        )
        bottom.plot(times, true_gain, "--", color="C0", lw=1, label="plant DC gain")
        bottom.plot(times, true_resonance, "--", color="C3", lw=1, label="plant resonance")
        step = adaptive.get("invalidated_step")
        if step is not None:  # from here no member explains the data within the noise bound
            bottom.axvline(
                step * dt, color="0.4", ls=":", lw=1, label="model class invalidated (noise bound)"
            )
        bottom.set_xlabel("time (s)")
        bottom.set_ylabel("relative to the nominal")
        bottom.legend(fontsize=7)
    fig.suptitle("Adaptive MPC: tracking error and the model it predicts with", fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    return None
