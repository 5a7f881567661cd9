"""Tables, JSON and figures of a :class:`benchmarks.runner.BenchmarkResult`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cells import TIE, aggregate, ci95_half_width
from benchmarks.checkpoint import write_text_atomic
from benchmarks.descriptions import controller_tables, loop_table
from benchmarks.figures import FIGURES, draw_figures
from benchmarks.reference_checks import (
    check_targets,
    missed_checks,
    reference_checks_section,
    strict_status,
    summary_line,
)
from benchmarks.rows import seed_groups
from benchmarks.runner import (
    BOX_CORNERS,
    DRAWN_PLANTS,
    MONTE_CARLO,
    BenchmarkConfig,
    BenchmarkResult,
)
from benchmarks.verdict import (
    cell_index,
    headline_plants,
    tie_rule,
    verdict,
    verdict_plant,
    winners,
)
from controllers.adaptive import AdaptiveMPCSettings
from controllers.mpc import MPCSettings
from controllers.observer import RUNAWAY_MEMORY, RUNAWAY_PERSISTENCE
from identification.outputs import jsonable

__all__ = [
    "SCHEMA",
    "SCHEMA_VERSION",
    "TIE",
    "check_targets",
    "controller_tables",
    "deterministic_json",
    "missed_checks",
    "monte_carlo_table",
    "strict_status",
    "summary_line",
    "tracking_tables",
    "verdict",
    "winners",
    "write_benchmark",
]

SCHEMA = "piezo-testbed/benchmark"
"""The ``schema`` field of benchmark.json."""
SCHEMA_VERSION = 2
"""Its version: 2 adds ``schema``, step-response figures, deadline misses and ``stroke_um``."""

_TIMING_KEYS = ("compute_median_us", "compute_p99_us", "compute_max_us", "deadline_misses")
"""Measured per run, not reproducible: kept out of the deterministic part of the JSON."""


def monte_carlo_table(result: BenchmarkResult, plant: str = MONTE_CARLO) -> str:
    """RMSE (% of the full stroke) over random plants (or the box's corners, ``plant``
    :data:`benchmarks.plants.BOX_CORNERS`), as order statistics of the draws.

    With n draws an empirical 90th percentile is not one (with 10 draws it is the 2nd worst,
    give or take): the table names what it shows, the median, the 2nd worst and the worst of
    the n draws, and says that upper quantiles need more draws.
    """
    draws = [c for c in aggregate(result.episodes) if c["plant"] == plant]
    if not draws:
        return ""
    cfg = result.config
    rows = [c for c in cfg.rows if any(e["controller"] == c for e in draws)]
    refs = [r for r in cfg.references if any(e["reference"] == r for e in draws)]
    counts = {
        len([e for e in draws if (e["controller"], e["reference"]) == (row, ref)])
        for row in rows
        for ref in refs
    } - {0}
    n = max(counts)

    groups = seed_groups(rows)

    def per_draw(row: str, ref: str) -> dict[Any, float]:
        return {
            e.get("draw"): e["rmse_percent"]
            for e in draws
            if (e["controller"], e["reference"]) == (row, ref)
        }

    def cell(row: str, ref: str) -> str:
        members = groups.get(row.removesuffix(" (seeds)")) if row.endswith(" (seeds)") else None
        if members:  # a recipe's seeds: each draw's RMSE is the mean over the seeds
            runs = [per_draw(m, ref) for m in members]
            shared = set.intersection(*(set(r) for r in runs))
            values = sorted(float(np.mean([r[d] for r in runs])) for d in shared)
        else:
            values = sorted(per_draw(row, ref).values())
        return " / ".join(f"{v:.3f}" for v in _order_statistics(values))

    episodes = [e for e in result.episodes if e["plant"] == plant]
    settling = _settling_table(episodes, rows, refs, cfg.steps * cfg.dt * 1e3)
    rows = rows + [f"{name} (seeds)" for name in groups]
    ratios = _oracle_ratio_table(draws, rows, refs, per_draw) + settling
    if plant == BOX_CORNERS:
        head = (
            f"### Corners of the datasheet's tolerance box: the {n} vertices of free deflection "
            "+-20 % x first resonance +-20 % x damping 0.01 / 0.04, RMSE (% of the full "
            f"stroke): {_order_statistics_names(n)}\n\n"
            "Every controller built for the nominal bender runs unchanged on each vertex; "
            "`mpc-oracle` is the MPC on the vertex's own model (`benchmarks/results/corners.md` "
            "gives each vertex).\n"
        )
        return head + "\n" + _table(rows, refs, cell, "controller") + "\n" + ratios
    head = (
        f"### Monte Carlo: {n} plants drawn from the datasheet tolerances, RMSE (% of the full "
        f"stroke): {_order_statistics_names(n)}\n\n"
        f"Order statistics of the {n} draws, not quantiles: an upper percentile such as the "
        f"90th needs many more draws than {n} to be estimated (`BenchmarkConfig.draws`). "
        "`mpc-oracle` is the MPC on each draw's own model.\n"
    )
    return head + "\n" + _table(rows, refs, cell, "controller") + "\n" + ratios


ORACLE = "mpc-oracle"
"""The row a distribution of plants is measured against: the MPC on each draw's own model."""


def _oracle_ratio_table(draws: list[dict[str, Any]], rows: list[str], refs: list[str],
                        per_draw: Any) -> str:
    """Each row's RMSE over the oracle's on the same draw, as order statistics of the draws:
    what not knowing that plant costs (empty without the oracle row)."""
    if not any(e["controller"] == ORACLE for e in draws):
        return ""
    plain = [r for r in rows if not r.endswith(" (seeds)") and not r.endswith("-oracle")]

    def cell(row: str, ref: str) -> str:
        mine, oracle = per_draw(row, ref), per_draw(ORACLE, ref)
        values = sorted(mine[d] / oracle[d] for d in set(mine) & set(oracle) if oracle[d] > 0)
        return " / ".join(f"{v:.3g}" for v in _order_statistics(values))

    return (
        f"\nRatio to `{ORACLE}` on the same plant (1 = as good as knowing the plant), "
        "same order statistics:\n\n" + _table(plain, refs, cell, "controller") + "\n"
    )


def _settling_table(
    episodes: list[dict[str, Any]], rows: list[str], refs: list[str], episode_ms: float
) -> str:
    """When each of the project's rows settled on each draw (the 50 ms-window RMS error back
    within twice the episode's own second half, :func:`controllers.metrics.window_settling_ms`),
    as order statistics of the draws in ms, each draw's the latest over its episodes (models
    identified on other seeds): a mean of a settled and a never-settled episode would be
    neither. Empty for a run without the figure."""
    shown = [r for r in rows if r.removesuffix("-oracle") in _BUILT_IN]
    if not shown or not any(e.get("window_settling_ms") is not None for e in episodes):
        return ""

    def cell(row: str, ref: str) -> str:
        latest: dict[Any, float] = {}
        for e in episodes:
            value = e.get("window_settling_ms")
            if (e["controller"], e["reference"]) == (row, ref) and value is not None:
                latest[e.get("draw")] = max(value, latest.get(e.get("draw"), value))
        values = sorted(latest.values())
        return " / ".join(
            f"> {episode_ms / 1e3:g} s" if v > episode_ms else f"{v:.0f}"
            for v in _order_statistics(values)
        )

    return (
        "\nSettling (ms): when the RMS error over 50 ms windows last came within twice the "
        "episode's own second half (how soon a controller reaches the error it keeps; a "
        "lower floor is a higher bar: at the sensor noise's floor, as the oracle's, the "
        "windows' own scatter can cross twice it late in an episode), same order "
        "statistics:\n\n"
        + _table(shown, refs, cell, "controller")
        + "\n"
    )


def _order_statistics(values: list[float]) -> list[float]:
    """Median, 2nd worst and worst of sorted ``values`` (fewer for fewer than 3 draws)."""
    if len(values) < 3:
        return values[-1:] if len(values) == 1 else values
    return [float(np.median(values)), values[-2], values[-1]]


def _order_statistics_names(n: int) -> str:
    """What :func:`_order_statistics` gives for ``n`` draws."""
    if n <= 2:
        return "the one draw" if n == 1 else "better / worse of 2"
    return f"median / 2nd worst / worst of {n}"


def _table(rows: list[str], columns: list[str], cell, header: str) -> str:
    lines = [f"| {header} | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for row in rows:
        lines.append(f"| {row} | " + " | ".join(cell(row, c) for c in columns) + " |")
    return "\n".join(lines)


def _cell(index, plant: str, key: str, digits: int, groups: dict[str, list[str]]):
    """Table cell of one metric: a row's value, or the mean over a recipe's training seeds +-
    the half-width of its 95 % interval (:func:`benchmarks.cells.ci95_half_width`);
    the single best row of an RMSE column in bold (a tie bolds nothing)."""
    bold = {}
    if key == "rmse_percent":
        rows = sorted({k[1] for k in index if k[0] == plant})
        for ref in {k[2] for k in index if k[0] == plant}:
            best = winners(index, plant, rows, ref)
            if len(best) == 1:
                bold[ref] = best[0]

    def cell(row: str, ref: str) -> str:
        text = plain(row, ref)
        return f"**{text}**" if text and bold.get(ref) == row else text

    def plain(row: str, ref: str) -> str:
        if row.endswith(" (seeds)"):
            values = [
                index[(plant, m, ref)][key]
                for m in groups[row.removesuffix(" (seeds)")]
                if (plant, m, ref) in index
            ]
            if not values:
                return ""
            ci = ci95_half_width(values)
            return f"{np.mean(values):.{digits}f}" + (
                f" +- {ci:.{digits}f}" if ci is not None else ""
            )
        e = index.get((plant, row, ref))
        if e is None:
            return ""
        ci = e.get("rmse_ci95_percent") if key == "rmse_percent" else None
        return f"{e[key]:.{digits}f}" + (f" +- {ci:.{digits}f}" if ci is not None else "")

    return cell


def _bender(result: BenchmarkResult) -> str:
    return str(getattr(result.config, "bender", "PL140"))


def tracking_tables(
    result: BenchmarkResult,
    *,
    plants: tuple[str, ...] | None = None,
    max_errors: bool = True,
    identify_on: list[str] | tuple[str, ...] = (),
) -> str:
    """RMSE and max-error tables per plant (deterministic: bitwise equal for any ``jobs``).

    Several seeds of one trained recipe also get a row ``NAME (seeds)``: the mean over the
    training seeds +- the half-width of its 95 % interval.
    ``plants`` selects the plants (default all but the Monte Carlo draws); ``max_errors``
    adds the nominal plant's max-error table; ``identify_on`` (the run's ``--identify-on``)
    names in each title the plant its model was identified on.
    """
    index = cell_index(result)
    chosen = result.config.plants if plants is None else plants
    parts = []
    for plant in (p for p in chosen if p not in DRAWN_PLANTS):
        parts += _plant_tables(
            result, index, plant, rmse=True, max_errors=max_errors, identify_on=identify_on
        )
    return "\n".join(parts)


def _plant_tables(
    result: BenchmarkResult,
    index: dict,
    plant: str,
    *,
    rmse: bool,
    max_errors: bool,
    identify_on: list[str] | tuple[str, ...] = (),
) -> list[str]:
    """The tables of one plant as headings and tables: its RMSE table (and, with an adaptive
    row, the RMSE over the episodes' second halves) when ``rmse``, then, for the nominal plant
    and when ``max_errors``, its max-error table; none for a plant without episodes."""
    cfg = result.config
    controllers = [c for c in cfg.rows if any(k[:2] == (plant, c) for k in index)]
    refs = [r for r in cfg.references if any(k[0] == plant and k[2] == r for k in index)]
    if not controllers:
        return []
    groups = seed_groups(controllers)
    controllers += [f"{name} (seeds)" for name in groups]
    title = f"Nominal {_bender(result)}" if plant == "nominal" else f"Plant: {plant}"
    parts = []
    if rmse:
        source = _identified_on(plant, identify_on)
        parts.append(f"### {title}{source}: RMSE (% of the full stroke)\n")
        rmse_cell = _cell(index, plant, "rmse_percent", 3, groups)
        parts.append(_table(controllers, refs, rmse_cell, "controller") + "\n")
        if any("adaptive" in c for c in controllers):
            second = _cell(index, plant, "rmse_second_half_percent", 3, groups)
            parts.append(
                f"{title}, RMSE over the second half of each episode (after adaptation):\n"
            )
            parts.append(_table(controllers, refs, second, "controller") + "\n")
    if plant == "nominal" and max_errors:
        max_error = _cell(index, plant, "max_error_um", 1, groups)
        parts.append(f"### {title}: max |error| (um)\n")
        parts.append(_table(controllers, refs, max_error, "controller") + "\n")
    return parts


def _headline_sentence(headline: list[str]) -> str:
    """What the headline tables are."""
    if headline == ["nominal"]:
        return "The paper's clean plant: the nominal bender, sensor noise only."
    if headline[:1] == ["nominal"] and len(headline) > 1:
        rest = ", ".join(f"`{p}`" for p in headline[1:])
        return (
            "The paper's clean plant (the nominal bender, sensor noise only), then "
            f"{rest} as a user meets it: with a model identified on that plant itself."
        )
    return f"The plants this run reads its verdict on: {', '.join(f'`{p}`' for p in headline)}."


def max_error_table(result: BenchmarkResult, plant: str) -> str:
    """The max |error| table (um) of one plant with its heading: the nominal plant's, as in
    :func:`tracking_tables`; empty for any other plant."""
    parts = _plant_tables(result, cell_index(result), plant, rmse=False, max_errors=True)
    return "\n".join(parts)


def oracle_ratio_table(result: BenchmarkResult, row: str = "mpc") -> str:
    """``row``'s RMSE over ``mpc-oracle``'s (the same MPC on the true plant's model) on every
    plant and reference both ran: what the identified model costs on each plant, those whose
    hysteresis it was not designed around included (the Prandtl-Ishlinskii plant, the bench;
    the random plants' ratios are in their own table)."""
    index = cell_index(result)
    plants = [
        p for p in result.config.plants
        if any(k[:2] == (p, row) for k in index) and any(k[:2] == (p, ORACLE) for k in index)
    ]
    if not plants:
        return ""
    refs = [r for r in result.config.references if any(k[2] == r for k in index)]

    def cell(plant: str, ref: str) -> str:
        mine, oracle = index.get((plant, row, ref)), index.get((plant, ORACLE, ref))
        if mine is None or oracle is None or not oracle["rmse_percent"]:
            return ""
        return f"{mine['rmse_percent'] / oracle['rmse_percent']:.3g}"

    return (
        f"### `{row}` over `{ORACLE}` per plant (RMSE ratio: 1 = as good as knowing the plant)"
        "\n\n" + _table(plants, refs, cell, "plant") + "\n"
    )


def _identified_on(plant: str, identify_on: list[str] | tuple[str, ...]) -> str:
    """``, model identified on X`` for a plant whose model was not identified on the nominal
    plant (empty otherwise, or when the run does not say)."""
    if not identify_on:
        return ""
    source = plant if plant in identify_on[1:] else identify_on[0]
    if source == "nominal":
        return ""
    return ", model identified on it" if source == plant else f", model identified on `{source}`"


def observer_fallback_section(result: BenchmarkResult) -> str:
    """Where a model-based controller's observer bank detected a runaway loop and fell back to
    its most robust filter (:class:`controllers.observer.ObserverBank`): in how many of the
    cell's episodes, and at which step. Those cells' RMSE is the guard's, not the likelihood's
    choice."""
    episodes: dict[tuple, list[int | None]] = {}
    for e in result.episodes:
        key = (e["controller"], e["plant"], e["reference"], e.get("draw"))
        episodes.setdefault(key, []).append(e.get("observer_fallback_step"))
    fired = {k: v for k, v in episodes.items() if any(step is not None for step in v)}
    head = "### Runaway guard of the observer bank\n\n"
    if not fired:
        return head + "It did not fire in any episode.\n"
    lines = [
        head + "The cells where it fired: the most likely filter's innovations were far beyond "
        "the sensor noise and alternated in sign (an oscillation near the Nyquist frequency) "
        f"for {RUNAWAY_PERSISTENCE} samples in a row, "
        "and the controller read the bank's most robust filter for the rest of the episode "
        "(`controllers.observer.ObserverBank`).\n",
        "| controller | plant | reference | episodes | step of the fall-back, per episode |",
        "|---|---|---|---|---|",
    ]
    for (controller, plant, reference, draw), steps in fired.items():
        where = plant if draw is None else f"{plant} (draw {draw})"
        count = f"{sum(step is not None for step in steps)} of {len(steps)}"
        when = ", ".join("-" if step is None else str(step) for step in steps)
        lines.append(f"| {controller} | {where} | {reference} | {count} | {when} |")
    return "\n".join(lines) + "\n"


def set_invalidation_section(result: BenchmarkResult) -> str:
    """In how many episodes, and at which step (median), the data invalidated each MPC's model
    at the sensor's noise bound: no gain in the datasheet's interval, with the model or any
    member of its set, explained every measurement to within the bound
    (:attr:`controllers.predictive.PredictiveController.set_invalidated_step`). A row appears
    once the data invalidated its model in some episode (then "0 of n" where they did not);
    empty when they never did (or no row learns a gain)."""
    episodes: dict[tuple[str, str], list[int | None]] = {}
    for e in result.episodes:
        if "set_invalidated_step" in e:
            episodes.setdefault((e["plant"], e["controller"]), []).append(
                e["set_invalidated_step"]
            )
    learned = {key for key, steps in episodes.items() if any(s is not None for s in steps)}
    rows = [c for c in result.config.rows if any(key[1] == c for key in learned)]
    # Each such row's oracle too: the same MPC on the plant's own model, in the model class.
    paired = (r for c in rows for r in (c, f"{c}-oracle") if r in result.config.rows)
    rows = list(dict.fromkeys(paired))  # an oracle row of its own is listed once
    if not rows:
        return ""
    plants = list(dict.fromkeys(key[0] for key in episodes))

    def cell(plant: str, row: str) -> str:
        steps = episodes.get((plant, row))
        if not steps:
            return "-"
        hit = [s for s in steps if s is not None]
        median = f", step {np.median(hit):.0f}" if hit else ""
        return f"{len(hit)} of {len(steps)}{median}"

    return (
        "### Is the plant in the model class? The exact set at the sensor's noise bound\n\n"
        "Besides the credible set the MPCs act on, each learns the exact set of the gains that "
        "explain every measurement to within the sensor's noise bound "
        "(`controllers.gain.GainEstimate`): in the model class (the linear part right up to "
        "the gain) it holds the plant's gain for any noise within the bound. Once it is "
        "empty, for the model and every member of the set, the data have invalidated the "
        "model class: the model's own error exceeds the noise bound, and only a set that "
        "counts model error, as the credible set does through the residual's variance, can "
        "be acted on. Episodes in which that happened, and the median step (an `-oracle` "
        "row predicts with the plant's own model, in the class up to a proven bound of the "
        "modes it leaves out, which its set counts):\n\n"
        + _table(plants, rows, cell, "plant")
        + "\n"
    )


def solver_iterations_section(result: BenchmarkResult) -> str:
    """The worst step's solver iterations of every row with a solver, per plant, over every
    episode of the run, beside the cap that bounds them; empty without such a row.

    The nominal column of the effort table sizes the nominal task; a real-time target is sized
    by the worst case over every plant the controller may meet. The cell is measured, not
    certified: DAQP's Python interface has no offline certificate of its iteration count (the
    parametric certification of its authors is a separate Julia package, ASCertain.jl), so the
    bound a target can rely on is the solver's iteration cap, past which a step applies the
    shifted plan and counts a fallback (:mod:`controllers.box_qp`)."""
    worst: dict[tuple[str, str], tuple[int, str]] = {}
    for e in result.episodes:
        value = e.get("solver_iterations_max")
        if value is None:
            continue
        key = (e["plant"], e["controller"])
        if key not in worst or int(value) > worst[key][0]:
            worst[key] = (int(value), e["reference"])
    rows = [c for c in result.config.rows if any(key[1] == c for key in worst)]
    if not rows:
        return ""
    plants = list(dict.fromkeys(key[0] for key in worst))

    def cell(plant: str, row: str) -> str:
        value = worst.get((plant, row))
        return "-" if value is None else str(value[0])

    overall = {
        row: max((v, plant, ref) for (plant, c), (v, ref) in worst.items() if c == row)
        for row in rows
    }
    where = "; ".join(
        f"`{row}` {v} ({plant}, {ref})" if v else f"`{row}` 0"
        for row, (v, plant, ref) in overall.items()
    )

    def cap(row: str) -> str:
        settings = (result.controllers.get(row) or {}).get("settings") or {}
        if settings.get("solver") == "ipopt":
            return f"`{row}`: IPOPT's {settings.get('ipopt_max_iter', '-')}"
        if "max_qp_iterations" in settings:
            return (
                f"`{row}`: {settings['max_qp_iterations']} per QP, "
                f"{settings.get('sqp_iterations', 1)} QPs a step"
            )
        if "max_iter" in settings:
            return f"`{row}`: {settings['max_iter']}"
        return f"`{row}`: -"

    return (
        "### Solver iterations over every plant\n\n"
        "The worst step's solver iterations per plant, over every episode of the run (the "
        "effort table above gives one plant's), each row's solver as its description below "
        "names it: a QP solver's summed over a step's QPs (one for the linear MPCs, up to "
        "`sqp_iterations` for `nmpc`; a DAQP iteration adds or removes one active constraint, "
        "a few rank-one updates of a 20 x 20 factor), IPOPT's its own. Worst over the run: "
        f"{where}.\n\n"
        + _table(plants, rows, cell, "plant")
        + "\n\nThese are measured, not certified: DAQP's Python interface offers no offline "
        "certificate of its iteration count (its authors' parametric certification is a "
        "separate Julia package, ASCertain.jl), so what bounds a step on a real-time target is "
        "the iteration cap ("
        + "; ".join(cap(row) for row in rows)
        + "): a solve that reaches it is not used, and the step applies the shifted plan (after "
        "a good first SQP iteration, its iterate) and counts a fallback (the effort table's "
        "last column).\n"
    )


def bench_gap_table(result: BenchmarkResult) -> str:
    """What each controller loses from the nominal plant to the ``bench`` plant (RMSE, % of
    the full stroke, and the factor), on the references both ran; empty without it."""
    index = cell_index(result)
    rows = [c for c in result.config.rows if any(k[:2] == ("bench", c) for k in index)]
    refs = [
        r for r in result.config.references if any(k[0] == "bench" and k[2] == r for k in index)
    ]
    if not rows or not refs:
        return ""

    def cell(row: str, ref: str) -> str:
        nominal, bench = index.get(("nominal", row, ref)), index.get(("bench", row, ref))
        if nominal is None or bench is None:
            return "-"
        a, b = nominal["rmse_percent"], bench["rmse_percent"]
        return f"{a:.3f} -> {b:.3f} (x{b / a:.1f})" if a > 0 else f"{a:.3f} -> {b:.3f}"

    return (
        "### From the nominal plant to the bench\n\n"
        "The `bench` plant drives the bender through a current-limited amplifier (a slew "
        "limit), reads it through a sensor with a bandwidth, and has hysteresis whose loop "
        "widens with the drive's rate (`benchmarks/plants.py`). The slew limit is a datasheet "
        "value, not identified: the MPC holds it as a constraint on its moves and the PID as "
        "an anti-windup on its voltage rate. RMSE (% of the full stroke), nominal -> bench:\n\n"
        + _table(rows, refs, cell, "controller")
        + "\n"
    )


def _effort_table(result: BenchmarkResult, plant: str) -> str:
    nominal = [e for e in result.episodes if e["plant"] == plant]
    rows = [c for c in result.config.rows if any(e["controller"] == c for e in nominal)]
    if not rows:
        return ""  # the caller says that no episode ran on the plant
    columns = [
        "RMS voltage (V)",
        "voltage TV (V)",
        "saturated (%)",
        "step median (us)",
        "step p99 (us)",
        "step max (us)",
        "deadline misses",
        "solver iterations (max)",
        "fallbacks",
    ]

    def cell(c, col):
        eps = [e for e in nominal if e["controller"] == c]
        if not eps:
            return ""
        values = {
            "RMS voltage (V)": np.mean([e["rms_voltage_v"] for e in eps]),
            "voltage TV (V)": np.mean([e["voltage_tv_v"] for e in eps]),
            "saturated (%)": 100 * np.mean([e["saturated_fraction"] for e in eps]),
            "step median (us)": np.median([e["compute_median_us"] for e in eps]),
            "step p99 (us)": np.max([e["compute_p99_us"] for e in eps]),
            "step max (us)": np.max([e["compute_max_us"] for e in eps]),
            "deadline misses": sum(int(e.get("deadline_misses", 0)) for e in eps),
            "solver iterations (max)": max(
                (int(e["solver_iterations_max"]) for e in eps if e.get("solver_iterations_max")),
                default=0,
            ),
            "fallbacks": sum(e["fallbacks"] for e in eps),
        }
        v = values[col]
        return f"{v:d}" if isinstance(v, (int, np.integer)) else f"{v:.1f}"

    return _table(
        rows,
        columns,
        cell,
        f"controller ({plant}, over its episodes: means; median of medians; worst p99, max and "
        "iterations; total misses and fallbacks)",
    )


def _step_table(result: BenchmarkResult, dt: float, plant: str = "nominal") -> str:
    """Rise time, overshoot and settling time on ``plant``'s step references (``dt`` in s)."""
    episodes = [
        c
        for c in aggregate(result.episodes)
        if c["plant"] == plant and c.get("steps_settled") is not None
    ]
    if not episodes:
        return ""
    lines = [
        "| controller | reference | rise (ms) | overshoot (%) | settling (ms) | settled |",
        "|---|---|---|---|---|---|",
    ]

    def fmt(value: float | None, digits: int) -> str:
        return "-" if value is None else f"{value:.{digits}f}"

    for e in episodes:
        lines.append(
            f"| {e['controller']} | {e['reference']} | {fmt(e['rise_time_ms'], 1)} | "
            f"{fmt(e['overshoot_percent'], 1)} | {fmt(e['settling_time_ms'], 1)} | "
            f"{e['steps_settled']} |"
        )
    return (
        "Medians over the steps of each reference (`controllers.metrics.step_metrics`); 10-90 "
        "% rise, 2 % settling band, read over the first 3/4 of each hold (a controller with "
        f"preview moves before the next step). Times at the sample's resolution ({dt * 1e3:g} "
        "ms): a rise of 0 went from 10 % to 90 % within one sample.\n\n" + "\n".join(lines) + "\n"
    )


def _seeds_sentence(cfg: Any) -> str:
    seeds = getattr(cfg, "seeds", 1)
    models = getattr(cfg, "identification_seeds", 1)
    noise = (
        f"noise seed {cfg.seed}"
        if seeds == 1
        else f"noise seeds {cfg.seed} .. {cfg.seed + seeds - 1}"
    )
    if models == 1 and seeds == 1:
        return f"Noise seed {cfg.seed}, one per cell;"
    if models > 1:
        what = (
            f"identification seeds {cfg.seed} .. {cfg.seed + models - 1} (the rows built on the "
            f"identified model; the oracles and policies have none) x {noise}"
        )
    else:
        what = noise
    count = f"{models} x {seeds}" if models > 1 else f"{seeds}"
    return (
        f"{what[0].upper() + what[1:]}: every cell is the mean over {count} seeds +- the "
        "half-width of its 95 % interval (Student's t), the same meaning of +- everywhere;"
    )


_BUILT_IN = ("pid", "pid-notch", "pid-ff", "mpc", "mpc-adaptive", "nmpc")
"""The project's controllers the 'who gets what' and tuning paragraphs speak of."""


def _disclosure_lines(result: BenchmarkResult) -> list[str]:
    """What each of the project's controllers sees and how they were tuned (when any ran)."""
    if not {r.removesuffix("-oracle") for r in result.config.rows} & set(_BUILT_IN):
        return []
    return [
        "Who gets what: `pid` and `pid-notch` use only the error r_t+1 - y_t (no preview, no "
        "model inverse); `pid-ff` adds the model-inverse feedforward of r_t+1 (one sample of "
        "preview); `mpc` and `nmpc` predict over the whole preview with the model and the "
        "static gain they learn from the first sample within the datasheet's tolerance "
        "(free deflection and hysteresis strength: +-31 %); "
        "`mpc-adaptive` is `mpc` that also learns which first resonance and damping of the "
        "datasheet's tolerance box the bender has, from a set of models built beforehand, and "
        "its hysteresis strength (+-30 %), each "
        "episode starting from the identified model (`adaptation.png`); the PIDs are tuned "
        "over the same box (their loop meets its margin on every vertex). Every "
        "controller is built for the nominal task and runs unchanged on the robustness "
        "plants; an oracle differs only in its prediction model (the plant's hysteresis and "
        "exact beam; its z is the plant's effective voltage; behind the bench's sensor, the "
        "beam seen through the sensor, and it steers the tip, not the measurement).",
        "",
        "### Tuning disclosure",
        "",
        "Defaults chosen by looking at this benchmark's references, its plants or the oracle, "
        "and what each was chosen on (a reader discounts a lead that rests on them; "
        "`benchmarks/results/tuning.md` gives the main knobs' sweeps):",
        "",
        *(f"- {what}: {on}" for what, on in CHOSEN_ON_THE_BENCHMARK),
        "",
        "Not chosen on them: the PID gains (a tuning rule on the identified model and the "
        "datasheet's tolerance box, whose sensitivity bound is the fair-tuning procedure's "
        "choice within the textbook range for `pid` and `pid-ff`: Ms <= 1.8) and the MPCs' "
        f"rate weights (the same procedure's: {MPCSettings().rate_weight:g} for `mpc`, "
        f"{AdaptiveMPCSettings().rate_weight:g} for `mpc-adaptive`; `benchmarks/tuning.py`, "
        "which never reads these references); the learned gain and the adaptive MPC's set "
        "(a 95 % credible set, chi2 tests at 95 %, and a grid "
        "whose step is the lightest-damped mode's half-power bandwidth).",
        "",
    ]


CHOSEN_ON_THE_BENCHMARK: tuple[tuple[str, str], ...] = (
    (
        "identification: the PRBS level (+-2 V), the rich signal (RAND +-30 V held 10 ms, "
        "the paper's 10 samples at 1 ms), the 3 x 2 network, the 16 play operators and the "
        "cap of 300 + 300 L-BFGS iterations of step e', and its stopping rule's fraction "
        "(0.01 of the estimation's excess error; its window of 20 iterations was measured "
        "on the PL122 and the Prandtl-Ishlinskii plant)",
        "the identified MPC's ratio to the oracle on this benchmark's references and seeds, "
        "nominal PL140",
    ),
    (
        "identification: the feature grid's Bouc-Wen-type levels",
        "with the plant's own hysteresis in view (one level lies 3 % from the plant's)",
    ),
    (
        "MPC observer bank: the span of its noise levels and its 200-sample memory",
        "the nominal PL140's references and the Prandtl-Ishlinskii plant",
    ),
    (
        'MPC single filter (`observer="fixed"`): its noise levels',
        "the nominal 50 Hz sine against the Prandtl-Ishlinskii plant's 10 Hz sine",
    ),
    (
        f"the bank's runaway guard: its two thresholds, the {RUNAWAY_MEMORY} samples it "
        f"averages over and the {RUNAWAY_PERSISTENCE} it asks in a row",
        "the robustness plants of the PL127 and the PL140",
    ),
    (
        "MPC: the 20-move horizon",
        "the nominal references",
    ),
    (
        '`mpc-adaptive`: its members made by moving the identified model\'s modes '
        '(`member_set="modes"`), not the datasheet\'s physics (`"datasheet"`, which matches '
        "the box's corners better: `benchmarks/results/corners.md`)",
        "the Prandtl-Ishlinskii plant, where at 50 Hz the datasheet's members do worse than "
        "the fixed `mpc` (`benchmarks/results/design_measurements.md`)",
    ),
    (
        "`mpc-adaptive`: its members chosen on the learned gain's misfits, not on the learned "
        "drive's (which it predicts with)",
        "the box's corner x1.2 / x0.8 / 0.04 at 50 Hz, where the drive's misfits kept a member "
        "20 % off the resonance for 1.4 s; on 11 other corners they chose as well or better "
        "(`benchmarks/results/design_measurements.md`)",
    ),
    (
        "`pid-notch`: Ms <= 1.8",
        "the textbook range, as the other PIDs; the fair-tuning procedure over the tolerance "
        "box would choose 2.0 (`benchmarks/results/tuning.md`), at which the loop's "
        "sensitivity peak on the true benders of the box's vertices (the env's FE models, "
        "with their aliased second modes) reaches 2.03, beyond the bound it was tuned to",
    ),
)
"""Every default of the identification and the controllers chosen by looking at the
benchmark's references, plants or oracle: (what, what it was chosen on)."""


def _setup_lines(result: BenchmarkResult, meta: dict[str, Any]) -> list[str]:
    cfg = result.config
    m = meta["machine"]
    stroke = float(meta["stroke_um"])
    noise = float(meta["noise_bound_um"])
    return [
        f"{m['date']}; {m['platform']}, {m['processor']}, {m['cores']} cores, Python "
        f"{m['python']}; one BLAS thread in the control loop; "
        + ", ".join(f"{k} {v}" for k, v in m["packages"].items() if v),
        "",
        _seeds_sentence(cfg) + f" {cfg.steps} steps of {meta['dt'] * 1e3:g} ms per episode; every "
        f"controller observes the measured deflection (sensor noise +-{noise:g} um) and a "
        f"preview of {cfg.preview} reference samples; the same noise and references for all. "
        "RMSE and max error: true deflection against the reference sample each action is "
        f"scored against, in % of the full stroke (2 x {stroke:g} um = {2 * stroke:g} um). "
        "`-oracle`: the same controller on the true plant's model instead of the identified "
        "one (not deployable: it shows what identification costs, and behind a sensor what "
        "steering the measurement instead of the tip costs; it is left out of the verdict).",
        "",
        *_disclosure_lines(result),
        *_left_out_lines(meta),
        f"Model: {meta['model']}. Time: "
        + ", ".join(f"{k} {v} s" for k, v in meta["timing"].items()),
        "",
        native_code_line(result),
    ]


def _left_out_lines(meta: dict[str, Any]) -> list[str]:
    """The policies ``piezo benchmark`` added and left out, and why, in one line (when any):
    ``meta["policies"]``, the line the command printed, else one made of
    ``meta["policies_left_out"]``."""
    if meta.get("policies"):
        return [f"{meta['policies'][0].upper()}{meta['policies'][1:]}.", ""]
    left_out = meta.get("policies_left_out") or {}
    if not left_out:
        return []
    reasons = "; ".join(f"`{Path(folder).name}` {why}" for folder, why in left_out.items())
    return [f"Policies left out (their task differs from this benchmark's): {reasons}.", ""]


def native_code_line(result: BenchmarkResult) -> str:
    """Which generated functions ran compiled and which ran in numpy, and why (one paragraph):
    a failed build, or a configuration without a compiled variant."""
    builds = {
        (row, name): build
        for row, description in result.controllers.items()
        for name, build in (description.get("native") or {}).items()
    }
    if not builds:
        return "Native code: none of these controllers uses generated code."
    fell_back = {key: b for key, b in builds.items() if not b["compiled"]}
    compilers = sorted({b["compiler"] for b in builds.values() if b["compiled"]})
    if not fell_back:
        return (
            f"Native code: every generated function ran compiled ({'; '.join(compilers)}); "
            "results are bitwise reproducible on this compiler and architecture."
        )
    listed = "; ".join(f"`{row}` {name}: {b['reason']}" for (row, name), b in fell_back.items())
    return (
        f"**Native code did not run everywhere**: {listed}. These ran in numpy (numbers that "
        "can differ from compiled code's by rounding, and longer compute times). A build that "
        "failed is an error under PIEZO_NATIVE=require; a configuration that has no compiled "
        "variant (a plant model or a horizon the kernels do not take) is not."
    )


def _markdown(
    result: BenchmarkResult,
    meta: dict[str, Any],
    checks: list[dict],
    figures: dict[str, Any],
) -> str:
    plant = verdict_plant(result) or "nominal"
    headline = headline_plants(result, meta)
    identify_on = meta.get("identify_on") or ()
    where = " and ".join(
        "the nominal plant" if p == "nominal" else f"the plant `{p}`" for p in headline
    ) or "the nominal plant"
    lines = [f"# Closed-loop benchmark on PiezoBender-v0 ({_bender(result)})", ""]
    if headline:
        lines += [
            "## Headline",
            "",
            _headline_sentence(headline),
            "",
            tracking_tables(
                result, plants=tuple(headline), max_errors=False, identify_on=identify_on
            ),
        ]
    others = tuple(p for p in result.config.plants if p not in headline)
    lines += [
        "## Verdict",
        "",
        f"Best controller per reference on {where} (RMSE, % of the full stroke), "
        "winners in bold, and what limits it. " + tie_rule(getattr(result.config, "seeds", 1)),
        "",
        *verdict(result, meta),
        "",
        *_setup_lines(result, meta),
        "",
        "## Tracking",
        "",
        max_error_table(result, plant) if plant in headline else "",
        tracking_tables(result, plants=others, identify_on=identify_on),
        oracle_ratio_table(result),
        bench_gap_table(result),
        monte_carlo_table(result, BOX_CORNERS),
        monte_carlo_table(result),
        observer_fallback_section(result),
        set_invalidation_section(result),
    ]
    steps = _step_table(result, meta["dt"], plant)
    if steps:
        lines += [f"## Step responses ({plant})", "", steps]
    effort = _effort_table(result, plant)
    lines += ["## Effort and compute time", "", effort or f"No episodes on `{plant}`.", ""]
    cores = meta["machine"]["cores"]
    jobs = result.config.jobs
    lines += [
        f"A deadline miss is a step whose compute time exceeded the sample time "
        f"({meta['dt'] * 1e3:g} ms). Measured with {jobs} worker(s) on {cores} core(s), one "
        "BLAS thread, after a warm-up and with the garbage collector off inside episodes"
        + (
            "; with as many workers as cores the maxima include waits for a core (run with "
            "fewer `--jobs` than cores to time the controllers alone)."
            if jobs >= cores
            else "."
        ),
        "",
        "Solver iterations (max): the worst step's solver iterations over the nominal episodes "
        "(each controller's solver is in its description below): for `mpc` its QP's (a DAQP "
        "iteration adds or removes one active constraint, so this sizes a step's work on a "
        "real-time target), for `nmpc` the sum over its SQP iterations' QPs, for IPOPT its "
        "iterations; 0 for a controller without a solver.",
        "",
        solver_iterations_section(result),
    ]
    if figures:
        lines += ["## Figures", ""]
        lines += [
            f"- {name}: " + (f"![{name}]({name})" if not isinstance(v, str) else f"not drawn ({v})")
            for name, v in figures.items()
        ]
        lines.append("")
    lines += ["## Controllers", ""]
    loops = loop_table(result)
    if loops:
        title = "Tuned feedback loops (margins on the identified model; `pid_loops.png`):"
        lines += [title, "", loops, ""]
    lines += [controller_tables(result), ""]
    lines += reference_checks_section(checks, result)
    return "\n".join(lines) + "\n"


def deterministic_json(result: BenchmarkResult) -> dict[str, Any]:
    """Episode results without measured times: bitwise equal for any ``jobs``."""
    return {
        "config": dataclasses.asdict(result.config) | {"jobs": None, "backend": None},
        "episodes": [
            {k: v for k, v in e.items() if k not in _TIMING_KEYS} for e in result.episodes
        ],
    }


def write_benchmark(
    result: BenchmarkResult, out: str | Path, meta: dict[str, Any], *, figures: bool = True
) -> list[Path]:
    """Write ``benchmark.md``, ``benchmark.json`` and (optionally) the figures into ``out``.

    The report and the JSON are each written to a temporary file renamed into place, the JSON
    last: a ``benchmark.json`` is always whole and comes after everything else.

    ``meta`` holds ``model``, ``dt`` (s), ``noise_bound_um``, ``stroke_um`` (one-sided, um),
    ``machine`` and ``timing``, and optionally ``policies_left_out`` (folder -> reason). A
    figure with nothing to show is not written; the report says why. A number that is not
    finite in a controller's description (a user's controller may report an infinite margin)
    is written as null in the JSON, which has no infinity (:func:`identification.outputs.
    jsonable`, as the identification's report.json); this report shows it as it is, one
    rewritten from the JSON (:func:`rewrite_report`) as None.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "timing": {**meta.get("timing", {}), **result.timing}}
    checks = check_targets(result)
    drawn = draw_figures(result, out, identify_on=meta.get("identify_on") or ()) if figures else {}
    md = out / "benchmark.md"
    write_text_atomic(md, _markdown(result, meta, checks, drawn))
    data = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "meta": meta,
        "results": deterministic_json(result),
        "timing": [
            {k: e[k] for k in ("plant", "controller", "reference", *_TIMING_KEYS)}
            for e in result.episodes
        ],
        "controllers": jsonable(result.controllers),
        "targets": checks,
    }
    path = out / "benchmark.json"
    write_text_atomic(path, json.dumps(data, indent=1, allow_nan=False) + "\n")
    return [md, path, *(v for v in drawn.values() if isinstance(v, Path))]


def rewrite_report(out: str | Path) -> Path:
    """Rewrite ``benchmark.md`` (and the checks in ``benchmark.json``) in ``out`` with this
    version's report from the run's own ``benchmark.json``, without running an episode.

    The JSON holds every episode's metrics, measured times and the controllers' descriptions,
    so every table, the verdict and the reference checks are rebuilt from it. It does not hold
    the traces, so the figures already in ``out`` are kept as they are and linked, not redrawn;
    a figure the run did not draw stays absent. For a run whose report code changed after it
    ran (a committed run, a long run on another machine).

    Raises
    ------
    ValueError
        When ``out`` holds no ``benchmark.json`` of this schema.
    """
    out = Path(out)
    path = out / "benchmark.json"
    if not path.is_file():
        raise ValueError(f"{out} holds no benchmark.json: run piezo benchmark --out {out} first")
    data = json.loads(path.read_text(encoding="utf-8"))
    if data.get("schema") != SCHEMA or data.get("schema_version") != SCHEMA_VERSION:
        raise ValueError(
            f"{path} is not a {SCHEMA} report of schema version {SCHEMA_VERSION}; rerun the "
            "benchmark with this version"
        )
    fields = {f.name for f in dataclasses.fields(BenchmarkConfig)}
    stored = data["results"]["config"]
    config = BenchmarkConfig(
        **{
            k: tuple(v) if isinstance(v, list) else v
            for k, v in stored.items()
            if k in fields and k not in ("jobs", "backend")
        },
        jobs=int(data["meta"].get("jobs") or 1),
    )
    episodes = data["results"]["episodes"]
    timing = data["timing"]
    if len(timing) != len(episodes):
        raise ValueError(f"{path}: {len(timing)} timing entries for {len(episodes)} episodes")
    merged = []
    for episode, times in zip(episodes, timing, strict=True):
        if any(episode[k] != times[k] for k in ("plant", "controller", "reference")):
            raise ValueError(f"{path}: the timing entries are not in the episodes' order")
        merged.append({**episode, **{k: times[k] for k in _TIMING_KEYS}})
    meta = data["meta"]
    result = BenchmarkResult(config, merged, data["controllers"], {}, {})
    checks = check_targets(result)
    drawn: dict[str, Any] = {
        name: out / name if (out / name).is_file() else "not in the run's folder"
        for name in FIGURES
    }
    md = out / "benchmark.md"
    write_text_atomic(md, _markdown(result, meta, checks, drawn))
    write_text_atomic(
        path, json.dumps({**data, "targets": checks}, indent=1, allow_nan=False) + "\n"
    )
    return md

