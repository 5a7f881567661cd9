"""The numbers of README.md and docs/*.md, generated from the committed results, never typed
by hand.

``python -m benchmarks.readme`` rewrites the parts of each page between marker comments
(``<!-- NAME:begin -->`` .. ``<!-- NAME:end -->``); :data:`BLOCKS` says which page holds which
block:

- ``headline`` (README.md) from ``docs/benchmark/benchmark.json`` (``python -m
  benchmarks.tracking``): the nominal RMSE table (winners bold, near ties not, divergences
  marked), each controller's median step time, and the bad news of the same run (worst cases on
  random plants and on the robustness plants, divergences, what identification costs, the
  reference checks that were missed);
- ``headline-PL127`` (README.md) from ``docs/benchmark-PL127/benchmark.json``: the same for the
  PL127;
- ``adaptation`` (docs/controllers.md) from ``docs/benchmark/benchmark.json``: ``mpc`` against
  ``mpc-adaptive`` on the robustness plants, whole episode and second half, and the Monte Carlo
  worst cases;
- ``identification`` (docs/identification.md) from ``docs/identify/report.json`` (``piezo
  identify --out docs/identify``);
- ``latency`` (docs/controllers.md) from ``benchmarks/results/controller_latency.json``
  (``python -m benchmarks.speed.controller_latency``): step times as ratios to a CartPole-v1 step of
  the same run, deadline misses, the MPC at 10 kHz, and the speed targets they miss;
- ``main-job`` (README.md) from ``benchmarks/results/main_job.json`` (``python -m
  benchmarks.speed.main_job``): the main commands' wall times, also in seconds of the
  reference machine, against their targets.

Links in the blocks are written from the repository's root and made relative to the page that
holds them. ``--check`` only compares (a test runs it).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cells import aggregate, ci95_half_width
from benchmarks.verdict import winners

__all__ = [
    "BLOCKS",
    "DIVERGED_MAX_ERROR_PERCENT",
    "PAGES",
    "bad_news",
    "diverged",
    "headline",
    "headline_table",
    "identification",
    "latency",
    "main_job",
    "render",
    "update_pages",
]

ROOT = Path(__file__).resolve().parents[1]

DIVERGED_MAX_ERROR_PERCENT = 100.0
"""An episode whose largest error exceeds this (% of the full stroke) has diverged. Every
benchmark reference stays within +-600 um of the PL140's +-1000 um (the same fractions on
another bender, :mod:`benchmarks.references`), so an error beyond the full stroke puts the
deflection at least 1.4 times beyond the rated stroke: a loop that has lost the reference and
swings against the drive limits. In the committed runs every episode that is not such a loop
stays below 75 %, and every one that is exceeds 140 %."""


def diverged(episodes: list[dict[str, Any]]) -> set[tuple[str, str, str, Any]]:
    """(plant, controller, reference, draw) of every cell with a diverged episode
    (:data:`DIVERGED_MAX_ERROR_PERCENT`)."""
    return {
        (e["plant"], e["controller"], e["reference"], e.get("draw"))
        for e in episodes
        if not np.isfinite(e["max_error_percent"])
        or e["max_error_percent"] > DIVERGED_MAX_ERROR_PERCENT
    }


def _label(row: str, data: dict[str, Any], members: dict[str, list[str]]) -> str:
    """A row's name, with the QP solver the run recorded for the MPCs (from its description,
    so that the label states what produced the numbers)."""
    if row in members:
        return row
    described = data.get("controllers", {}).get(row, {})
    solver = described.get("qp_solver") or described.get("solver")
    if row in ("mpc", "nmpc") and solver:
        name = str(solver).split()[0].upper()
        rti = row == "nmpc" and described.get("settings", {}).get("solver") == "rti"
        return f"`{row}` ({'RTI, ' if rti else ''}{name})"
    return f"`{row}`"


def _plant_rmse(data: dict[str, Any], plant: str = "nominal") -> dict[tuple[str, str], float]:
    """Mean RMSE (%) per (controller, reference) on ``plant``."""
    return {
        (c["controller"], c["reference"]): c["rmse_percent"]
        for c in aggregate(data["results"]["episodes"])
        if c["plant"] == plant
    }


def _oracle_span(rmse: dict[tuple[str, str], float]) -> str | None:
    """``mpc`` over ``mpc-oracle`` on the smooth references, as "low-high" (one decimal)."""
    ratios = [rmse[("mpc", r)] / rmse[("mpc-oracle", r)] for (c, r) in rmse
              if c == "mpc" and ("mpc-oracle", r) in rmse and "step" not in r]
    if not ratios:
        return None
    low, high = f"{min(ratios):.1f}", f"{max(ratios):.1f}"
    return low if low == high else f"{low}-{high}"


def _rows(data: dict[str, Any]) -> tuple[list[str], dict[str, list[str]]]:
    """Row names in order, with the seeds of each trained recipe gathered in one row."""
    config = data["results"]["config"]
    recipes: dict[str, list[str]] = {}
    for folder in config.get("policies", []):
        label = Path(folder).name
        recipes.setdefault(re.sub(r"-seed\d+$", "", label), []).append(label)
    labels = {f"{name.upper()}, {len(m)} seeds": m for name, m in recipes.items()}
    return list(config["controllers"]) + list(labels), labels


def headline_table(data: dict[str, Any], plant: str = "nominal") -> str:
    """RMSE (% of the full stroke) on ``plant`` per controller and reference, and step medians.

    The winner of a column is bolded as in the report's verdict (:func:`benchmarks.verdict.
    winners`): oracles aside, and not when it ties; a trained recipe's seeds share one row,
    their mean +- the half-width of its 95 % interval. A cell with a diverged episode
    (:data:`DIVERGED_MAX_ERROR_PERCENT`) reads "diverged", with how many of a recipe's seeds
    did, instead of an RMSE that would only measure the swing.
    """
    index = {
        (plant, c["controller"], c["reference"]): c
        for c in aggregate(data["results"]["episodes"])
        if c["plant"] == plant
    }
    refs = [r for r in data["results"]["config"]["references"] if any(k[2] == r for k in index)]
    rows, members = _rows(data)
    rows = [r for r in rows if any(k[1] in members.get(r, [r]) for k in index)]
    best = {ref: winners(index, plant, rows, ref) for ref in refs}
    lost = diverged(data["results"]["episodes"])
    steps: dict[str, list[float]] = {}
    for t in data["timing"]:
        if t["plant"] == plant:
            steps.setdefault(t["controller"], []).append(t["compute_median_us"])

    def cell(row: str, ref: str) -> str:
        names = [n for n in members.get(row, [row]) if (plant, n, ref) in index]
        values = [index[(plant, n, ref)]["rmse_percent"] for n in names]
        gone = sum((plant, n, ref, None) in lost for n in names)
        if gone:
            return "diverged" if len(names) == 1 else f"diverged ({gone} of {len(names)} seeds)"
        if len(values) > 1:
            ci = ci95_half_width(values)
            return f"{np.mean(values):.2f} +- {ci:.2f}"
        text = f"{values[0]:.3f}" if values else ""
        return f"**{text}**" if text and best[ref] == [row] else text

    head = (
        "| controller (RMSE, % of the full stroke) | " + " | ".join(refs) + " | step median (us) |"
    )
    lines = [head, "|---" * (len(refs) + 2) + "|"]
    for row in rows:
        medians = [m for n in members.get(row, [row]) for m in steps.get(n, [])]
        step = f"{np.median(medians):.0f}" if medians else ""
        label = _label(row, data, members)
        lines.append(f"| {label} | " + " | ".join(cell(row, r) for r in refs) + f" | {step} |")
    return "\n".join(lines)


def bad_news(data: dict[str, Any]) -> list[str]:
    """What the same run says against the project: one line each, worst first."""
    episodes = aggregate(data["results"]["episodes"])
    news = []
    drawn = (("box-corners", "on the corners of the datasheet's tolerance box", "vertices"),
             ("random-plants", "on plants drawn from the datasheet tolerances", "draws"))
    for plant, where, unit in drawn:
        cells = [e for e in episodes if e["plant"] == plant]
        for row in ("pid-notch", "pid-ff", "mpc", "mpc-adaptive", "nmpc"):
            worst = max((e for e in cells if e["controller"] == row),
                        key=lambda e: e["rmse_percent"], default=None)
            if worst is not None and worst["rmse_percent"] > 1.0:
                n = sum(1 for e in cells if e["controller"] == row and e["reference"] ==
                        worst["reference"])
                news.append(
                    f"`{row}` {where}: worst {worst['rmse_percent']:.1f} % on "
                    f"{worst['reference']} (of {n} {unit})."
                )
    worst: dict[str, dict[str, Any]] = {}
    for e in episodes:
        if e["plant"] in ("nominal", "random-plants", "box-corners") or e["rmse_percent"] <= 1.0:
            continue
        row = e["controller"]
        if row in ("pid-notch", "pid-ff", "mpc", "mpc-adaptive", "nmpc") and (
            row not in worst or e["rmse_percent"] > worst[row]["rmse_percent"]
        ):
            worst[row] = e
    if worst:
        listed = ", ".join(
            f"`{c}` {e['rmse_percent']:.3g} % ({e['plant']}, {e['reference']})"
            for c, e in sorted(worst.items(), key=lambda item: -item[1]["rmse_percent"])
        )
        news.append(f"Worst case of each controller on the robustness plants: {listed}.")
    news += _divergences(data)
    span = _oracle_span(_plant_rmse(data))
    if span:
        bench = _oracle_span(_plant_rmse(data, "bench"))
        own = "bench" in (data["meta"].get("identify_on") or ())[1:]
        news.append(
            f"Identification costs {span}x the oracle's RMSE on smooth references on the "
            "nominal plant (`mpc` against `mpc-oracle`)"
            + (
                f"; on the bench, with a model identified {'on it' if own else 'on the nominal'}"
                f", {bench}x: the oracle knows the bench's sensor and steers the tip, which "
                "the measurement lags by the sensor's lag."
                if bench else "."
            )
        )
    missed = [c for c in data.get("targets", []) if not c["holds"]]
    if missed:
        news.append(
            f"{len(missed)} of {len(data['targets'])} of the project's own reference checks "
            "were missed in this run, e.g. "
            + "; ".join(f"{c['target']}: {c['value']:.3g} (limit {c['limit']:.3g})"
                        for c in missed[:3])
            + "."
        )
    return news


def _divergences(data: dict[str, Any]) -> list[str]:
    """One line per row with diverged cells: on which plants, how many of their cells."""
    lost = diverged(data["results"]["episodes"])
    if not lost:
        return []
    rows, members = _rows(data)
    cells: dict[tuple[str, str], set[tuple]] = {}
    for e in data["results"]["episodes"]:
        cells.setdefault((e["controller"], e["plant"]), set()).add((e["reference"],
                                                                    e.get("draw")))
    news = []
    for row in rows:
        names = members.get(row, [row])
        parts = []
        for plant in data["results"]["config"]["plants"]:
            total = sum(len(cells.get((n, plant), ())) for n in names)
            gone = sum(1 for (p, c, _, _) in lost if p == plant and c in names)
            if gone:
                parts.append(f"{gone} of {total} cells on {plant}")
        if parts:
            news.append(f"{_label(row, data, members)}: diverged (an episode's largest error "
                        f"beyond the full stroke) in {', '.join(parts)}.")
    return news


def headline(data: dict[str, Any]) -> str:
    """The whole generated block: date and machine, table, bad news."""
    machine, timing = data["meta"]["machine"], data["meta"]["timing"]
    jobs = data["results"]["config"].get("jobs") or data["meta"].get("jobs", "?")
    took = ", ".join(f"{k.removesuffix('_s').replace('_', ' ')} {v:.0f} s" for k, v in
                     timing.items() if k in ("identification_s", "benchmark_s"))
    lines = [
        f"Committed run of {machine['date']} on {machine['processor']}, {machine['cores']} "
        f"cores, {jobs} worker(s): {took} (generated by `python -m benchmarks.readme` from "
        "[docs/benchmark/benchmark.json](docs/benchmark/benchmark.json)):",
        "",
        headline_table(data),
        "",
        *_own_model_tables(data),
        *_diverged_note(data),
        "The bad news of the same run:",
        "",
        *[f"- {line}" for line in bad_news(data)],
    ]
    return "\n".join(lines)


def _diverged_note(data: dict[str, Any]) -> list[str]:
    """What "diverged" means, when a headline table has such a cell."""
    plants = ["nominal", *(data["meta"].get("identify_on") or [])[1:]]
    if not any(p in plants for (p, *_) in diverged(data["results"]["episodes"])):
        return []
    return [
        f"*diverged*: an episode's largest error exceeded the full stroke "
        f"({DIVERGED_MAX_ERROR_PERCENT:g} %); the references stay within 60 % of the one-sided "
        "stroke, so the loop had lost the reference and swung beyond the rated stroke.",
        "",
    ]


def _own_model_tables(data: dict[str, Any]) -> list[str]:
    """The table of each plant the run identified its own model on (``--identify-on``'s later
    plants: the bench identified on the bench), after a line saying what it is."""
    lines = []
    for plant in (data["meta"].get("identify_on") or [])[1:]:
        lines += [
            f"The `{plant}` plant as a user meets it, with a model identified on it "
            f"({_PLANT_WORDS.get(plant, 'see the report')}):",
            "",
            headline_table(data, plant),
            "",
        ]
    return lines


_PLANT_WORDS = {
    "bench": "a current-limited amplifier, a 20 kHz sensor, rate-dependent hysteresis, the "
    "amplifier's output noise, floor vibration and a 16-bit sensor",
}


ADAPTATION_REFERENCES = ("sine-10Hz", "sine-50Hz", "multisine")


def adaptation(data: dict[str, Any]) -> str:
    """``mpc`` against ``mpc-adaptive`` on every plant the model was not identified on: RMSE
    over the whole episode and over its second half (after adaptation), and the Monte Carlo
    worst cases."""
    cells = {
        (c["plant"], c["controller"], c["reference"]): c
        for c in aggregate(data["results"]["episodes"])
        if "draw" not in c
    }
    plants = [p for p in data["results"]["config"]["plants"] if p not in ("nominal",
              "random-plants")]
    plants = [p for p in plants if any((p, "mpc-adaptive", r) in cells
                                       for r in ADAPTATION_REFERENCES)]
    if not plants:
        return "(`mpc-adaptive` was not run on a robustness plant in the committed run.)"
    head = "| plant | " + " | ".join(f"{r}: mpc | {r}: adaptive (2nd half)"
                                     for r in ADAPTATION_REFERENCES) + " |"
    lines = [
        "RMSE in % of the full stroke, committed run (generated from "
        "[docs/benchmark/benchmark.json](docs/benchmark/benchmark.json)); `mpc` holds its "
        "identified model, `mpc-adaptive` starts every episode from it:",
        "",
        head,
        "|---|" + "---|" * (2 * len(ADAPTATION_REFERENCES)),
    ]
    for plant in ["nominal", *plants]:
        row = [plant]
        for ref in ADAPTATION_REFERENCES:
            fixed, adaptive = cells.get((plant, "mpc", ref)), cells.get(
                (plant, "mpc-adaptive", ref))
            row.append("-" if fixed is None else f"{fixed['rmse_percent']:.3f}")
            row.append("-" if adaptive is None else (
                f"{adaptive['rmse_percent']:.3f} ({adaptive['rmse_second_half_percent']:.3f})"))
        lines.append("| " + " | ".join(row) + " |")
    random = [e for e in data["results"]["episodes"] if e["plant"] == "random-plants"]
    worst = []
    for ref in ADAPTATION_REFERENCES:
        for row in ("mpc", "mpc-adaptive"):
            members = [e for e in random if e["controller"] == row and e["reference"] == ref]
            if members:
                whole = max(e["rmse_percent"] for e in members)
                half = max(e["rmse_second_half_percent"] for e in members)
                worst.append(f"`{row}` {whole:.3g} % ({half:.3g} % over the second half) on "
                             f"{ref}")
    if worst:
        lines += ["", f"Worst of the {len({e.get('draw') for e in random})} random plants: "
                  + "; ".join(worst) + "."]
    return "\n".join(lines)


def identification(report: dict[str, Any]) -> str:
    """The identification figures of the committed ``piezo identify`` report."""
    validation, arx, inversion = report["validation"], report["arx"], report["inversion"]
    rows = [("Hammerstein (identified)", validation["hammerstein"])]
    if "hammerstein_unrefined_nls" in validation:
        rows.append(("Hammerstein before step e'", validation["hammerstein_unrefined_nls"]))
    rows.append(("linear ARX alone", validation["linear_arx"]))
    table = ["| model | fit % | RMSE (um) | max error (um) |", "|---|---|---|---|"]
    table += [f"| {name} | {m['fit_percent']:.2f} | {m['rmse']:.1f} | {m['max_abs_error']:.1f} |"
              for name, m in rows]
    return "\n".join([
        f"Default PL140, validation on {validation['signal']}, free run (generated from "
        "[docs/identify/report.json](docs/identify/report.json)):",
        "",
        *table,
        "",
        f"ARX order {arx['order']} (chosen by held-out free-run fit{_refined_order(report)}). "
        "The ARX equation error A(q) y - B(q) u holds the sensor noise filtered by A(q), up to "
        f"1 + sum |a_i| = {1 + sum(abs(a) for a in arx['a']):.2f} times its bound, and what the "
        f"model misses, so the estimated noise bound r_hat ({arx['noise_bound_um']:.2f} um "
        f"against {_sensor_bound(report):g} um of sensor noise) exceeds the sensor's. The "
        "hidden signal z_hat of step d) carries that error "
        f"filtered by 1/B: at most r_hat ||1/B||_1 = {inversion['z_error_bound_V']:.2f} V, RMS "
        f"r_hat / sqrt(3) ||1/B||_2 = {inversion['z_error_rms_V']:.2f} V for independent "
        f"uniform noise (equivalent V). {_identification_time(report['timings_s'])}",
    ])


def _sensor_bound(report: dict[str, Any]) -> float:
    """The sensor noise bound r (um) of the identified env."""
    return float(report["config"]["env_kwargs"]["noise_bound"])


def _refined_order(report: dict[str, Any]) -> str:
    refinement = report.get("refinement")
    if refinement is None:
        return ""
    return f"; order {refinement['after']['order']} after the output-error refinement of step b'"


def _identification_time(timings: dict[str, float]) -> str:
    text = f"Identification took {timings['total']:.0f} s: the network's training "
    text += f"{timings['e_nls_training']:.0f} s"
    if "e2_nls_output_error" in timings:
        text += f", step e' {timings['e2_nls_output_error']:.0f} s"
    return text + "."


def other_bender(data: dict[str, Any]) -> str:
    """The headline of another bender's committed run: its table and its bad news."""
    bender = data["meta"].get("bender", "?")
    stroke = data["meta"]["stroke_um"]
    return "\n".join([
        f"{bender} (stroke 2 x {stroke:g} um; references at the same fractions of it as on the "
        f"PL140), committed run of {data['meta']['machine']['date']} (generated from "
        f"[docs/benchmark-{bender.split('.')[0]}/benchmark.json]"
        f"(docs/benchmark-{bender.split('.')[0]}/benchmark.json)):",
        "",
        headline_table(data),
        "",
        *_diverged_note(data),
        *[f"- {line}" for line in bad_news(data)],
    ])


LATENCY_ROWS = (
    "pid-ff",
    "mpc",
    "mpc (DAQP every step)",
    "mpc (OSQP every step)",
    "mpc-adaptive",
    "nmpc",
    "nmpc (step not fused)",
    "mpc (PL127, 0.25 ms)",
    "mpc-adaptive (PL127, 0.25 ms)",
    "mpc-adaptive (PL127 corner x1.2, x1.2, 0.01)",
)
"""The rows of the latency block, in its order."""


def _own_cost(rows: list[dict[str, Any]]) -> tuple[int, dict[str, Any]]:
    """Misses of the per-step minimum over repeated runs, summed over the 10 kHz rows, and the
    row with the slowest such step."""
    return sum(r["own_misses"] for r in rows), max(rows, key=lambda r: r["own_max_us"])


def latency(data: dict[str, Any]) -> str:
    """Step times against a CartPole-v1 step, the MPC at 10 kHz, and the targets missed."""
    rows = {r["label"]: r for r in data["controllers"]}
    paired = all("cartpole_beside_us" in r for r in data["controllers"])
    reference = (
        "each row's ratios are to the CartPole-v1 steps timed just before and after its "
        f"episode (median over the rows {data['cartpole_median_us']:.1f} us)"
        if paired
        else f"a CartPole-v1 step took {data['cartpole_median_us']:.1f} us in the same run"
    )
    lines = [
        f"Committed run of {data['date']} ({data['machine']}), one BLAS thread; {reference}.",
        "",
        "| controller | step median (us) | median / CartPole | p99 / CartPole | deadline misses "
        "| solver iterations (max) |",
        "|---|---|---|---|---|---|",
    ]
    for label in LATENCY_ROWS:
        if label in rows:
            r = rows[label]
            name, _, detail = label.partition(" ")
            shown = f"`{name}` {detail}".rstrip()
            own = f" ({r['own_misses']} in the minimum over runs)" if "own_misses" in r else ""
            lines.append(
                f"| {shown} | {r['median_us']:.1f} | {r['median_ratio']:.1f} | "
                f"{r['p99_ratio']:.1f} | {r['misses']} of {r['steps']}{own} | "
                f"{r['qp_iterations_max']} |"
            )
    fast = data.get("mpc_10khz", [])
    if fast:
        clean = sum(r["misses"] == 0 for r in fast)
        misses = ", ".join(f"{r['label']} {r['misses']}" for r in fast if r["misses"])
        medians = [r["median_us"] for r in fast]
        lines += [
            "",
            f"`mpc` at 10 kHz (PL140, 0.1 ms, deadline 100 us, {fast[0]['steps']} steps each): "
            f"{clean} of {len(fast)} references without a deadline miss; step medians "
            f"{min(medians):.0f}-{max(medians):.0f} us, at most "
            f"{max(r['qp_iterations_max'] for r in fast)} QP iterations; misses: "
            f"{misses or 'none'}.",
        ]
        if all("own_max_us" in r for r in fast):
            own, worst = _own_cost(fast)
            lines[-1] += (
                f" Each step's minimum over repeated runs (the controller's own cost, without "
                f"the machine's interruptions): {own} misses, slowest step "
                f"{worst['own_max_us']:.0f} us ({worst['label']})."
            )
        period = data.get("mpc_10khz_resonance", [])
        if period and all("own_max_us" in r for r in period):
            own, worst = _own_cost(period)
            lines[-1] += (
                f" Predicting over one period of the first mode "
                f"({data['resonance_prediction_samples']} samples, 20 moves): "
                f"{sum(r['misses'] for r in period)} misses in the first runs, {own} in the "
                f"per-step minimum, slowest step {worst['own_max_us']:.0f} us."
            )
    mpc, adaptive, nmpc = (rows.get(k) for k in ("mpc", "mpc-adaptive", "nmpc"))
    missed = []
    if mpc and mpc["median_ratio"] > 2.0:
        ratio = mpc["median_ratio"]
        missed.append(f"`mpc`'s median step is {ratio:.1f}x a CartPole step (target 2x)")
    if mpc and mpc["p99_ratio"] > 5.0:
        missed.append(f"its p99 {mpc['p99_ratio']:.2f}x (target 5x)")
    if nmpc and nmpc["median_ratio"] > 10.0:
        missed.append(f"`nmpc`'s median {nmpc['median_ratio']:.1f}x (target 10x)")
    if mpc and adaptive and adaptive["median_us"] > 1.5 * mpc["median_us"]:
        ratio = adaptive["median_us"] / mpc["median_us"]
        missed.append(f"`mpc-adaptive`'s median {ratio:.2f}x `mpc`'s (target 1.5x)")
    if missed:
        lines += ["", "Speed targets missed in this run: " + "; ".join(missed) + "."]
    return "\n".join(lines)


MAIN_JOB_NAMES = {
    "quick start": "`piezo benchmark`",
    "identify": "`piezo identify`",
    "PL127": "`piezo benchmark --bender PL127`",
    "bench identification": "the bench plant's identification (`identify(jobs=2)`, per seed)",
}
"""How the main-job block names each row of ``main_job.json``."""


def _span(values: list[float], digits: int = 0) -> str:
    """One value, or "low-high"."""
    low, high = min(values), max(values)
    if round(low, digits) == round(high, digits):
        return f"{low:.{digits}f}"
    return f"{low:.{digits}f}-{high:.{digits}f}"


def main_job(data: dict[str, Any]) -> str:
    """The main commands' wall times, here and in seconds of the reference machine, against
    their targets (``benchmarks/results/main_job.json``; every row of its targets present)."""
    rows, targets = data["rows"], data["targets_s"]
    if set(rows) != set(targets) or set(rows) != set(MAIN_JOB_NAMES):
        raise ValueError(
            f"main_job.json has the rows {sorted(rows)}, the block needs {sorted(targets)}: "
            "run python -m benchmarks.speed.main_job without --skip-pl127"
        )
    reference = data["reference_cartpole_us"]
    here, there, bursts = [], [], []
    for name in targets:
        runs = rows[name]
        walls = [run["wall_s"] for run in runs]
        scaled = [run["wall_s"] * reference / run["cartpole_us"] for run in runs]
        bursts += [c for run in runs for c in run["bursts_us"]]
        target = targets[name]
        verdict = "" if max(scaled) <= target else ": missed"
        here.append(f"{MAIN_JOB_NAMES[name]} {_span(walls)} s")
        there.append(f"{MAIN_JOB_NAMES[name]} {_span(scaled)} s (target {target:g} s{verdict})")
    return (
        f"Measured on {data['date']} ({data['machine'].split(', Python')[0]}), each command in a "
        "fresh process, the commands with an empty native-code cache, the bench plant's "
        "identification after its imports ([benchmarks/results/main_job.md]"
        "(benchmarks/results/main_job.md)): " + ", ".join(here) + ". On the reference "
        f"machine (a CartPole-v1 step of {reference:g} us; bursts of {_span(bursts, 1)} us "
        "while the commands ran here): " + ", ".join(there) + "."
    )


BLOCKS = {
    "headline": ("README.md", "docs/benchmark/benchmark.json", headline),
    "headline-PL127": ("README.md", "docs/benchmark-PL127/benchmark.json", other_bender),
    "identification": ("docs/identification.md", "docs/identify/report.json", identification),
    "adaptation": ("docs/controllers.md", "docs/benchmark/benchmark.json", adaptation),
    "latency": ("docs/controllers.md", "benchmarks/results/controller_latency.json", latency),
    "main-job": ("README.md", "benchmarks/results/main_job.json", main_job),
}
"""Marker name -> (the page that holds it, the committed file it is generated from, the function
that renders it). Paths are from the repository's root."""

PAGES = tuple(dict.fromkeys(page for page, _, _ in BLOCKS.values()))
"""Every page with generated blocks."""

_LINK = re.compile(r"\]\(([^)\s:#]+)\)")


def _relink(text: str, page: str) -> str:
    """``text``'s links, written from the repository's root, made relative to ``page``."""
    folder = os.path.dirname(page) or "."
    return _LINK.sub(lambda m: f"]({Path(os.path.relpath(m.group(1), folder)).as_posix()})",
                     text)


def render(text: str, root: Path = ROOT, page: str = "README.md") -> str:
    """``text`` (the page ``page``, from the root) with each of its generated blocks replaced
    (ValueError for missing markers)."""
    for name, (where, source, make) in BLOCKS.items():
        if where != page:
            continue
        begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
        start, stop = text.find(begin), text.find(end)
        if start < 0 or stop < start:
            raise ValueError(f"{page} needs the markers {begin} and {end}")
        data = json.loads((root / source).read_text(encoding="utf-8"))
        block = _relink(make(data), page)
        text = text[: start + len(begin)] + "\n" + block + "\n" + text[stop:]
    return text


def update_pages(root: Path = ROOT, *, check: bool = False) -> list[str]:
    """Rewrite (or with ``check`` only compare) every page's blocks; the pages that were stale."""
    stale = []
    for page in PAGES:
        path = root / page
        text = path.read_text(encoding="utf-8")
        fresh = render(text, root, page)
        if fresh != text:
            stale.append(page)
            if not check:
                path.write_text(fresh, encoding="utf-8")
    return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.readme", description=__doc__)
    parser.add_argument("--check", action="store_true", help="only compare; exit 1 if stale")
    args = parser.parse_args(argv)
    stale = update_pages(ROOT, check=args.check)
    if args.check and stale:
        print(f"{', '.join(stale)}: generated blocks differ from the committed results; run "
              "python -m benchmarks.readme", file=sys.stderr)
        return 1
    if not stale:
        print(f"{', '.join(PAGES)}: up to date")
    else:
        print(f"{', '.join(stale)}: generated blocks rewritten")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
