"""Tables, JSON and figures of a :class:`benchmarks.runner.BenchmarkResult`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cells import TIE, aggregate, different
from benchmarks.figures import draw_figures
from benchmarks.references import REFERENCES
from benchmarks.rows import seed_groups
from benchmarks.runner import MONTE_CARLO, BenchmarkResult

__all__ = [
    "SCHEMA",
    "SCHEMA_VERSION",
    "check_targets",
    "controller_tables",
    "missed_checks",
    "tracking_tables",
    "verdict",
    "write_benchmark",
]

SCHEMA = "piezo-testbed/benchmark"
"""The ``schema`` field of benchmark.json."""
SCHEMA_VERSION = 2
"""Its version: 2 adds ``schema``, step-response figures, deadline misses and ``stroke_um``."""

_TIMING_KEYS = ("compute_median_us", "compute_p99_us", "compute_max_us", "deadline_misses")
"""Measured per run, not reproducible: kept out of the deterministic part of the JSON."""


def _lookup(result: BenchmarkResult) -> dict[tuple[str, str, str], dict[str, Any]]:
    """Cells (means over the noise seeds) by (plant, controller, reference); the Monte Carlo
    draws are left out."""
    return {
        (c["plant"], c["controller"], c["reference"]): c
        for c in aggregate(result.episodes)
        if c["plant"] != MONTE_CARLO
    }


def monte_carlo_table(result: BenchmarkResult) -> str:
    """RMSE (% of the full stroke) over random plants, as order statistics of the draws.

    With n draws an empirical 90th percentile is not one (with 10 draws it is the 2nd worst,
    give or take): the table names what it shows, the median, the 2nd worst and the worst of n.
    """
    draws = [c for c in aggregate(result.episodes) if c["plant"] == MONTE_CARLO]
    if not draws:
        return ""
    cfg = result.config
    rows = [c for c in cfg.rows if any(e["controller"] == c for e in draws)]
    refs = [r for r in cfg.references if any(e["reference"] == r for e in draws)]

    def cell(row: str, ref: str) -> str:
        values = sorted(
            e["rmse_percent"] for e in draws if (e["controller"], e["reference"]) == (row, ref)
        )
        if not values:
            return ""
        second = f"{values[-2]:.3f} / " if len(values) > 1 else ""
        return f"{np.median(values):.3f} / {second}{values[-1]:.3f}"

    n = cfg.draws
    head = (
        f"### Monte Carlo: {n} plants drawn from the datasheet tolerances, RMSE (% of the full "
        f"stroke): median / 2nd worst / worst of {n}\n"
    )
    return head + "\n" + _table(rows, refs, cell, "controller") + "\n"


def _table(rows: list[str], columns: list[str], cell, header: str) -> str:
    lines = [f"| {header} | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for row in rows:
        lines.append(f"| {row} | " + " | ".join(cell(row, c) for c in columns) + " |")
    return "\n".join(lines)


def winners(index: dict, plant: str, rows: list[str], ref: str) -> list[str]:
    """Rows with the best RMSE on ``ref`` (oracles aside): one, or those the best cannot be
    told apart from (:func:`benchmarks.cells.different`)."""
    cells = {
        r: index[(plant, r, ref)]
        for r in rows
        if (plant, r, ref) in index and not r.endswith("-oracle")
    }
    if not cells:
        return []
    best = min(cells.values(), key=lambda c: c["rmse_percent"])
    return [r for r, c in cells.items() if c is best or not different(c, best)]


def _cell(index, plant: str, key: str, digits: int, groups: dict[str, list[str]]):
    """Table cell of one metric: a row's value, or mean +- sample std over a recipe's seeds;
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
            return f"{np.mean(values):.{digits}f} +- {np.std(values, ddof=1):.{digits}f}"
        e = index.get((plant, row, ref))
        if e is None:
            return ""
        ci = e.get("rmse_ci95_percent") if key == "rmse_percent" else None
        return f"{e[key]:.{digits}f}" + (f" +- {ci:.{digits}f}" if ci is not None else "")

    return cell


def _bender(result: BenchmarkResult) -> str:
    return str(getattr(result.config, "bender", "PL140"))


def tracking_tables(
    result: BenchmarkResult, *, plants: tuple[str, ...] | None = None, max_errors: bool = True
) -> str:
    """RMSE and max-error tables per plant (deterministic: bitwise equal for any ``jobs``).

    Several seeds of one trained recipe also get a row ``NAME (seeds)`` with mean +- std.
    ``plants`` selects the plants (default all but the Monte Carlo draws); ``max_errors``
    adds the nominal plant's max-error table.
    """
    index = _lookup(result)
    cfg = result.config
    parts = []
    chosen = cfg.plants if plants is None else plants
    for plant in (p for p in chosen if p != MONTE_CARLO):
        controllers = [c for c in cfg.rows if any(k[:2] == (plant, c) for k in index)]
        refs = [r for r in cfg.references if any(k[0] == plant and k[2] == r for k in index)]
        if not controllers:
            continue
        groups = seed_groups(controllers)
        controllers += [f"{name} (seeds)" for name in groups]
        rmse = _cell(index, plant, "rmse_percent", 3, groups)
        max_error = _cell(index, plant, "max_error_um", 1, groups)

        title = f"Nominal {_bender(result)}" if plant == "nominal" else f"Plant: {plant}"
        parts.append(f"### {title}: RMSE (% of the full stroke)\n")
        parts.append(_table(controllers, refs, rmse, "controller") + "\n")
        if plant == "nominal" and max_errors:
            parts.append(f"### {title}: max |error| (um)\n")
            parts.append(_table(controllers, refs, max_error, "controller") + "\n")
    return "\n".join(parts)


def _effort_table(result: BenchmarkResult) -> str:
    nominal = [e for e in result.episodes if e["plant"] == "nominal"]
    rows = [c for c in result.config.rows if any(e["controller"] == c for e in nominal)]
    columns = [
        "RMS voltage (V)",
        "voltage TV (V)",
        "saturated (%)",
        "step median (us)",
        "step p99 (us)",
        "step max (us)",
        "deadline misses",
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
            "fallbacks": sum(e["fallbacks"] for e in eps),
        }
        v = values[col]
        return f"{v:d}" if isinstance(v, (int, np.integer)) else f"{v:.1f}"

    return _table(rows, columns, cell, "controller (nominal, mean over references)")


def check_targets(result: BenchmarkResult) -> list[dict[str, Any]]:
    """The project's expectations of its default run, each with its measured value and whether
    it holds. They were set on the PL140, so other benders get none."""
    if getattr(result.config, "bender", "PL140").split(".")[0] != "PL140":
        return []
    index = _lookup(result)
    checks: list[dict[str, Any]] = []

    def get(plant, c, r):
        e = index.get((plant, c, r))
        return None if e is None else e["rmse_percent"]

    def add(text, value, limit):
        if value is not None:
            checks.append({"target": text, "value": value, "limit": limit, "holds": value <= limit})

    for r in result.config.references:
        smooth = REFERENCES[r].smooth
        if r in ("random-steps", "chirp"):
            continue
        add(f"mpc RMSE on {r} (%)", get("nominal", "mpc", r), 0.05 if smooth else 0.9)
        episode = index.get(("nominal", "mpc", r))
        if smooth and episode is not None:
            add(f"mpc max error on {r} (um)", episode["max_error_um"], 4.0)
    for r in ("sine-10Hz", "sine-50Hz", "sine-100Hz"):
        m, p = get("nominal", "mpc", r), get("nominal", "pid-notch", r)
        if m is not None and p is not None:
            add(f"mpc / pid-notch on {r}", m / p, 0.1)
    for r in ("sine-50Hz", "steps"):
        m, p = get("nominal", "mpc", r), get("nominal", "pid-ff", r)
        if m is not None and p is not None:
            add(f"mpc / pid-ff on {r} (>= 3x better)", m / p, 1 / 3)
    for r in result.config.references:
        m, o = get("nominal", "mpc", r), get("nominal", "mpc-oracle", r)
        if m is not None and o is not None and REFERENCES[r].smooth:
            add(f"mpc / mpc-oracle on {r}", m / o, 2.0)
        n = get("nominal", "nmpc", r)
        if m is not None and n is not None:
            add(f"nmpc / mpc on {r}", n / m, 1.1)
    limits = {
        "damping-0.01": {"sine-10Hz": 0.07, "sine-50Hz": 0.3, "sine-100Hz": 0.5, "multisine": 0.15},
        "damping-0.04": {"sine-10Hz": 0.07, "sine-50Hz": 0.3, "sine-100Hz": 0.5, "multisine": 0.15},
        "prandtl-ishlinskii": {
            "sine-10Hz": 0.15,
            "sine-50Hz": 0.5,
            "sine-100Hz": 0.9,
            "multisine": 0.3,
        },
    }
    for plant, refs in limits.items():
        for r, limit in refs.items():
            add(f"mpc RMSE on {r}, plant {plant} (%)", get(plant, "mpc", r), limit)
    return checks


def verdict(result: BenchmarkResult) -> list[str]:
    """Per nominal reference: the best controller (oracles aside), its lead and why, one line."""
    index = _lookup(result)
    rows = [r for r in result.config.rows if not r.endswith("-oracle")]
    lines = []
    for ref in result.config.references:
        ranked = sorted(
            (index[("nominal", r, ref)]["rmse_percent"], r)
            for r in rows
            if ("nominal", r, ref) in index
        )
        if not ranked:
            continue
        best_value, best = ranked[0]
        tied = winners(index, "nominal", rows, ref)
        rest = [(v, r) for v, r in ranked if r not in tied]
        if len(tied) > 1:
            head = f"tie between {', '.join(f'`{t}`' for t in tied)} ({best_value:.3f} %)"
            if rest:
                head += f", {rest[0][0] / best_value:.1f}x better than `{rest[0][1]}`"
        elif len(ranked) > 1:
            lead = ranked[1][0] / best_value
            head = f"**`{best}`** ({best_value:.3f} %), {lead:.1f}x better than `{ranked[1][1]}`"
        else:
            head = f"`{best}` ({best_value:.3f} %), the only controller run"
        lines.append(f"- {ref}: {head}; {_why(index, best, ref)}")
    return lines


def _why(index: dict, row: str, ref: str) -> str:
    """One reason for the best row's figure: the drive limit, the oracle's floor or model error."""
    episode = index[("nominal", row, ref)]
    if episode["saturated_fraction"] > 0.05:
        return (
            f"the drive limit binds ({100 * episode['saturated_fraction']:.0f} % of the steps "
            "saturated): the amplifier, not the controller, sets the floor"
        )
    oracle = index.get(("nominal", "mpc-oracle", ref))
    if oracle is None:
        return "no oracle row to compare with"
    ratio = episode["rmse_percent"] / oracle["rmse_percent"]
    if ratio < 1.25 and not REFERENCES[ref].smooth:
        return (
            f"at the oracle's level ({ratio:.2f}x `mpc-oracle`): a jump takes several samples "
            "at the drive limit, so the drive range sets the floor"
        )
    if ratio < 1.25:
        return f"at the oracle's level ({ratio:.2f}x `mpc-oracle`): noise sets the floor"
    return f"{ratio:.1f}x `mpc-oracle`: model error sets the floor"


def _step_table(result: BenchmarkResult) -> str:
    """Rise time, overshoot and settling time on the nominal step references."""
    episodes = [
        c
        for c in aggregate(result.episodes)
        if c["plant"] == "nominal" and c.get("steps_settled") is not None
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
        "Medians over the steps of each reference; 10-90 % rise, 2 % settling band, read over "
        "the first 3/4 of each hold (a controller with preview moves before the next step).\n\n"
        + "\n".join(lines)
        + "\n"
    )


def _flatten(description: dict[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """(key, value) pairs of a description's scalars, nested dicts as ``a.b``; lists left out."""
    pairs = []
    for key, value in description.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            pairs += _flatten(value, name + ".")
        elif isinstance(value, float):
            pairs.append((name, f"{value:.4g}"))
        elif isinstance(value, (str, int, bool)) or value is None:
            pairs.append((name, str(value)))
    return pairs


def controller_tables(result: BenchmarkResult) -> str:
    """Every controller's settings and derived facts (gains, margins, horizon) as a table."""
    parts = []
    for name, description in result.controllers.items():
        pairs = [(k, v) for k, v in _flatten(description) if k not in ("name", "stats")]
        rows = "\n".join(f"| {k} | {v} |" for k, v in pairs)
        parts.append(f"### `{name}`\n\n| setting or fact | value |\n|---|---|\n{rows}\n")
    return "\n".join(parts)


def reference_checks_section(checks: list[dict[str, Any]]) -> list[str]:
    """The project's own expectations of the default run, framed as such."""
    if not checks:
        return [
            "## Reference checks",
            "",
            "None for this run: the project's expectations were set on the PL140's default run.",
        ]
    missed = [c for c in checks if not c["holds"]]
    lines = [
        "## Reference checks",
        "",
        "The project's own expectations of its default run (limits set from earlier "
        "measurements on a 2-core machine), kept to notice regressions. A miss is news about "
        "the controllers on this run, not an installation error; `piezo benchmark --strict` "
        f"turns misses into a failing exit code. {len(checks) - len(missed)} of {len(checks)} "
        "met.",
        "",
        "| check | measured | limit | met |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {c['target']} | {c['value']:.4g} | {c['limit']:.4g} | "
        f"{'yes' if c['holds'] else 'NO'} |"
        for c in checks
    ]
    return lines


def _seeds_sentence(cfg: Any) -> str:
    seeds = getattr(cfg, "seeds", 1)
    if seeds == 1:
        return (
            f"Seed {cfg.seed}, one noise seed per cell (differences under {100 * TIE:g} % are "
            "called ties; --seeds N gives intervals);"
        )
    return (
        f"Noise seeds {cfg.seed} .. {cfg.seed + seeds - 1}: every cell is the mean over {seeds} "
        "seeds +- the half-width of its 95 % interval (Student's t); differences within the "
        "intervals are called ties and not bolded;"
    )


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
        _seeds_sentence(cfg)
        + f" {cfg.steps} steps of {meta['dt'] * 1e3:g} ms per episode; every "
        f"controller observes the measured deflection (sensor noise +-{noise:g} um) and a "
        f"preview of {cfg.preview} reference samples; the same noise and references for all. "
        "RMSE and max error: true deflection against the reference sample each action is "
        f"scored against, in % of the full stroke (2 x {stroke:g} um = {2 * stroke:g} um). "
        "`-oracle`: the same controller on the true plant's model instead of the identified "
        "one (not deployable: it shows what identification costs, and is left out of the "
        "verdict).",
        "",
        "Who gets what: `pid` and `pid-notch` use only the error r_t+1 - y_t (no preview, no "
        "model inverse); `pid-ff` adds the model-inverse feedforward of r_t+1 (one sample of "
        "preview); `mpc` and `nmpc` predict over the whole preview with the model. Every "
        "controller is built for the nominal task and runs unchanged on the robustness "
        "plants; an oracle differs only in its prediction model (the plant's hysteresis and "
        "exact beam; its z is the plant's effective voltage).",
        "",
        "Tuning disclosure: the controllers' defaults were chosen on this benchmark's "
        "references (the MPC observer speed on the nominal 50 Hz sine against the "
        "Prandtl-Ishlinskii plant's 10 Hz sine; the narrow feedforward notch of `pid-ff` on the "
        "50 Hz sine); the PID gains come from a tuning rule on the identified model alone.",
        "",
        f"Model: {meta['model']}. Time: "
        + ", ".join(f"{k} {v} s" for k, v in meta["timing"].items()),
        "",
        native_code_line(result),
    ]


def native_code_line(result: BenchmarkResult) -> str:
    """Which generated functions ran compiled and which fell back, and why (one paragraph)."""
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
        f"**Native code fell back** (the numbers differ from a compiled run by rounding, and the "
        f"compute times are longer): {listed}. Set PIEZO_NATIVE=require to make this an error."
    )


def _markdown(
    result: BenchmarkResult,
    meta: dict[str, Any],
    checks: list[dict],
    figures: dict[str, Any],
) -> str:
    lines = [
        f"# Closed-loop benchmark on PiezoBender-v0 ({_bender(result)})",
        "",
        "## Verdict",
        "",
        "Best controller per reference on the nominal plant (RMSE, % of the full stroke):",
        "",
        *verdict(result),
        "",
        *_setup_lines(result, meta),
        "",
        "## Tracking",
        "",
        tracking_tables(result),
        monte_carlo_table(result),
    ]
    steps = _step_table(result)
    if steps:
        lines += ["## Step responses (nominal)", "", steps]
    lines += ["## Effort and compute time", "", _effort_table(result), ""]
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
    ]
    if figures:
        lines += ["## Figures", ""]
        lines += [
            f"- {name}: " + (f"![{name}]({name})" if not isinstance(v, str) else f"not drawn ({v})")
            for name, v in figures.items()
        ]
        lines.append("")
    lines += ["## Controllers", "", controller_tables(result), ""]
    lines += reference_checks_section(checks)
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

    ``meta`` holds ``model``, ``dt`` (s), ``noise_bound_um``, ``stroke_um`` (one-sided, um),
    ``machine`` and ``timing``. A figure with nothing to show is not written; the report says
    why.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "timing": {**meta.get("timing", {}), **result.timing}}
    checks = check_targets(result)
    drawn = draw_figures(result, out) if figures else {}
    md = out / "benchmark.md"
    md.write_text(_markdown(result, meta, checks, drawn), encoding="utf-8")
    data = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "meta": meta,
        "results": deterministic_json(result),
        "timing": [
            {k: e[k] for k in ("plant", "controller", "reference", *_TIMING_KEYS)}
            for e in result.episodes
        ],
        "controllers": result.controllers,
        "targets": checks,
    }
    path = out / "benchmark.json"
    path.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    return [md, path, *(v for v in drawn.values() if isinstance(v, Path))]


def missed_checks(checks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The reference checks that do not hold (``piezo benchmark --strict`` fails on any)."""
    return [c for c in checks if not c["holds"]]
