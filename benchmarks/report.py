"""Tables, JSON and figures of a :class:`benchmarks.runner.BenchmarkResult`."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.figures import draw_figures
from benchmarks.references import REFERENCES
from benchmarks.rows import seed_groups
from benchmarks.runner import MONTE_CARLO, BenchmarkResult

__all__ = ["check_targets", "tracking_tables", "write_benchmark"]

_TIMING_KEYS = ("compute_median_us", "compute_p99_us", "compute_max_us")


def _lookup(result: BenchmarkResult) -> dict[tuple[str, str, str], dict[str, Any]]:
    """Episodes by (plant, controller, reference); the Monte Carlo draws are left out."""
    return {
        (e["plant"], e["controller"], e["reference"]): e
        for e in result.episodes
        if e["plant"] != MONTE_CARLO
    }


def monte_carlo_table(result: BenchmarkResult) -> str:
    """RMSE (% of the full stroke) over random plants: median, 90th percentile and worst."""
    draws = [e for e in result.episodes if e["plant"] == MONTE_CARLO]
    if not draws:
        return ""
    cfg = result.config
    rows = [c for c in cfg.rows if any(e["controller"] == c for e in draws)]
    refs = [r for r in cfg.references if any(e["reference"] == r for e in draws)]

    def cell(row: str, ref: str) -> str:
        values = [
            e["rmse_percent"] for e in draws if (e["controller"], e["reference"]) == (row, ref)
        ]
        if not values:
            return ""
        median, p90, worst = np.quantile(values, [0.5, 0.9, 1.0])
        return f"{median:.3f} / {p90:.3f} / {worst:.3f}"

    n = cfg.draws
    head = (
        f"### Monte Carlo: {n} plants drawn from the datasheet tolerances, RMSE (% of the full "
        "stroke), median / 90th percentile / worst\n"
    )
    return head + "\n" + _table(rows, refs, cell, "controller") + "\n"


def _table(rows: list[str], columns: list[str], cell, header: str) -> str:
    lines = [f"| {header} | " + " | ".join(columns) + " |", "|---" * (len(columns) + 1) + "|"]
    for row in rows:
        lines.append(f"| {row} | " + " | ".join(cell(row, c) for c in columns) + " |")
    return "\n".join(lines)


def _cell(index, plant: str, key: str, digits: int, groups: dict[str, list[str]]):
    """Table cell of one metric: a row's value, or mean +- sample std over a recipe's seeds."""

    def cell(row: str, ref: str) -> str:
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
        return "" if e is None else f"{e[key]:.{digits}f}"

    return cell


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

        title = "Nominal PL140" if plant == "nominal" else f"Plant: {plant}"
        parts.append(f"### {title}: RMSE (% of the full stroke)\n")
        parts.append(_table(controllers, refs, rmse, "controller") + "\n")
        if plant == "nominal" and max_errors:
            parts.append(f"### {title}: max |error| (um)\n")
            parts.append(_table(controllers, refs, max_error, "controller") + "\n")
    return "\n".join(parts)


def _effort_table(result: BenchmarkResult) -> str:
    rows = [c for c in result.config.rows]
    nominal = [e for e in result.episodes if e["plant"] == "nominal"]
    columns = [
        "RMS voltage (V)",
        "voltage TV (V)",
        "saturated (%)",
        "step median (us)",
        "step p99 (us)",
        "step max (us)",
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
            "fallbacks": sum(e["fallbacks"] for e in eps),
        }
        v = values[col]
        return f"{v:d}" if isinstance(v, int) else f"{v:.1f}"

    return _table(rows, columns, cell, "controller (nominal, mean over references)")


def check_targets(result: BenchmarkResult) -> list[dict[str, Any]]:
    """The product's stated targets, each with its measured value and whether it holds."""
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


def _markdown(result: BenchmarkResult, meta: dict[str, Any], checks: list[dict]) -> str:
    cfg = result.config
    m = meta["machine"]
    lines = [
        "# Closed-loop benchmark: MPC against PID on PiezoBender-v0",
        "",
        f"{m['date']}; {m['platform']}, {m['processor']}, {m['cores']} cores, Python "
        f"{m['python']}; one BLAS thread in the control loop; "
        + ", ".join(f"{k} {v}" for k, v in m["packages"].items() if v),
        "",
        f"Seed {cfg.seed}; {cfg.steps} steps of {meta['dt'] * 1e3:g} ms per episode; every "
        f"controller observes the measured deflection (sensor noise +-{meta['noise_bound_um']:g} "
        f"um) and a preview of {cfg.preview} reference samples; the same noise and references "
        "for all. RMSE and max error: true deflection against the reference sample each action "
        "is scored against, in % of the full 2000 um stroke. `-oracle`: the same controller on "
        "the true plant's model instead of the identified one.",
        "",
        "Who gets what: `pid` and `pid-notch` use only the error r_t+1 - y_t (no preview, no "
        "model inverse); `pid-ff` adds the model-inverse feedforward of r_t+1 (one sample of "
        "preview); `mpc` and `nmpc` predict over the whole preview with the model. Every "
        "controller is built for the nominal task (sensor noise 1 um, stroke 1000 um) and runs "
        "unchanged on the robustness plants; an oracle differs only in its prediction model "
        "(the plant's hysteresis and exact beam; its z is the plant's effective voltage).",
        "",
        "Tuning disclosure: the controllers' defaults were chosen on this benchmark's "
        "references (the MPC observer speed on the nominal 50 Hz sine against the "
        "Prandtl-Ishlinskii plant's 10 Hz sine; the narrow feedforward notch of `pid-ff` on the "
        "50 Hz sine); the PID gains come from a tuning rule on the identified model alone.",
        "",
        f"Model: {meta['model']}. Time: "
        + ", ".join(f"{k} {v} s" for k, v in meta["timing"].items()),
        "",
        "## Tracking",
        "",
        tracking_tables(result),
        monte_carlo_table(result),
        "## Effort and compute time",
        "",
        _effort_table(result),
        "",
        "## Targets",
        "",
        "| target | measured | limit | holds |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {c['target']} | {c['value']:.4g} | {c['limit']:.4g} | {'yes' if c['holds'] else 'NO'} |"
        for c in checks
    ]
    lines += ["", "## Controllers", ""]
    for name, description in result.controllers.items():
        lines.append(f"- `{name}`: `{json.dumps(_short(description))}`")
    return "\n".join(lines) + "\n"


def _short(description: dict[str, Any]) -> dict[str, Any]:
    """The description without long arrays, for the Markdown list."""
    return {k: v for k, v in description.items() if not (isinstance(v, list) and len(v) > 8)}


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
    """Write ``benchmark.md``, ``benchmark.json`` and (optionally) the figures into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {**meta, "timing": {**meta.get("timing", {}), **result.timing}}
    checks = check_targets(result)
    md = out / "benchmark.md"
    md.write_text(_markdown(result, meta, checks), encoding="utf-8")
    data = {
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
    paths = [md, path]
    if figures:
        paths += draw_figures(result, out)
    return paths
