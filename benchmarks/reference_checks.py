"""The project's reference checks: its own expectations of the default PL140 run.

Each check is either a limit set above the value the default run reaches on a 2-core machine
(the committed run's report, ``docs/benchmark/benchmark.md``, lists each check with its value),
kept to notice regressions of the controllers, or a ranking the project claims (the MPC ahead
of the feedforward PID, on the nominal plant and on the plant whose hysteresis the model does
not match). They are the project's, not the user's: a
miss says that a controller did worse on this run than the project expects, never that the
installation is broken. The report frames them so (:func:`reference_checks_section`), the
terminal gives one line, and ``piezo benchmark --strict`` exits non-zero when
:func:`strict_status` says so.
"""

from __future__ import annotations

from typing import Any

from benchmarks.plants import EPISODE_S, sample_time
from benchmarks.references import REFERENCES
from benchmarks.runner import BenchmarkConfig, BenchmarkResult
from benchmarks.verdict import cell_index

__all__ = [
    "CHECKED_BENDER",
    "MISMATCHED_HYSTERESIS",
    "check_targets",
    "checks_apply",
    "condition_line",
    "missed_checks",
    "reference_checks_section",
    "strict_status",
    "summary_line",
]

_PLANT_LIMITS = {
    "damping-0.01": {"sine-10Hz": 0.07, "sine-50Hz": 0.3, "sine-100Hz": 0.7, "multisine": 0.15},
    "damping-0.04": {"sine-10Hz": 0.07, "sine-50Hz": 0.3, "sine-100Hz": 0.7, "multisine": 0.15},
}
"""Plant -> reference -> the largest ``mpc`` RMSE (% of the full stroke) expected there: plants
whose hysteresis the model matches, off only in the first mode's damping. The sine-100Hz limits
moved from 0.5 to 0.7 when the observer bank's screen came to ask for a margin on every vertex
of the tolerance box (the default run went from 0.49 to 0.56 on damping-0.04;
``benchmarks/results/design_measurements.md``)."""

_MAX_ERROR_UM = 6.0
"""The largest ``mpc`` max error (um) expected on a smooth nominal reference: above the 4.5 um
the default run reaches on its sine-100Hz with the rate weight the fair-tuning procedure chose
(0.3; it was 4 um at the rate weight 0.01, which bought less robustness on the box)."""

MISMATCHED_HYSTERESIS = "prandtl-ishlinskii"
"""The plant whose hysteresis the nominal model does not match (play operators with sharp
corners, against the model's Bouc-Wen features). There the MPC's error is set by the model's
hysteresis error, which no absolute figure of the project's bounds (identified on that plant,
the MPC is about 1x its oracle: ``benchmarks/results/rate_aware_identification.md``). What the
project claims there is the ranking: the MPC beats the feedforward PID built from the same
model, because its observer and integrating disturbance model take up the model's error at
every step of the preview, where the PID's feedforward passes it on."""


def check_targets(result: BenchmarkResult) -> list[dict[str, Any]]:
    """The project's expectations of its default run, each with its measured value.

    They were set on the PL140 at its default 1 ms, so other benders and sample times get none.

    Returns
    -------
    list of dict
        ``target`` (what is checked, with its unit), ``value``, ``limit`` (the largest value
        expected) and ``holds``, for every check whose rows this run has.
    """
    if not checks_apply(result):
        return []
    index = cell_index(result)
    checks: list[dict[str, Any]] = []

    def get(plant: str, c: str, r: str) -> float | None:
        e = index.get((plant, c, r))
        return None if e is None else e["rmse_percent"]

    def add(text: str, value: float | None, limit: float) -> None:
        if value is not None:
            checks.append({"target": text, "value": value, "limit": limit, "holds": value <= limit})

    def ratio(a: str, b: str, r: str, plant: str = "nominal") -> float | None:
        x, y = get(plant, a, r), get(plant, b, r)
        return None if x is None or y is None else x / y

    for r in result.config.references:
        smooth = REFERENCES[r].smooth
        if r in ("random-steps", "chirp"):
            continue
        add(f"mpc RMSE on {r} (%)", get("nominal", "mpc", r), 0.05 if smooth else 0.9)
        episode = index.get(("nominal", "mpc", r))
        if smooth and episode is not None:
            add(f"mpc max error on {r} (um)", episode["max_error_um"], _MAX_ERROR_UM)
    for r in ("sine-10Hz", "sine-50Hz", "sine-100Hz"):
        add(f"mpc / pid-notch on {r}", ratio("mpc", "pid-notch", r), 0.1)
    # The claim is the ranking, not a factor: pid-ff at its best setting of the tuning
    # procedure comes within about 12 % of mpc (benchmarks/results/tuning.md).
    for r in ("sine-50Hz", "steps"):
        add(f"mpc / pid-ff on {r} (mpc better)", ratio("mpc", "pid-ff", r), 1.0)
    for r in result.config.references:
        if REFERENCES[r].smooth:
            add(f"mpc / mpc-oracle on {r}", ratio("mpc", "mpc-oracle", r), 2.0)
        add(f"nmpc / mpc on {r}", ratio("nmpc", "mpc", r), 1.1)
    for plant, refs in _PLANT_LIMITS.items():
        for r, limit in refs.items():
            add(f"mpc RMSE on {r}, plant {plant} (%)", get(plant, "mpc", r), limit)
    for r in result.config.references:
        if REFERENCES[r].smooth:
            add(
                f"mpc / pid-ff on {r}, plant {MISMATCHED_HYSTERESIS} (mpc better)",
                ratio("mpc", "pid-ff", r, MISMATCHED_HYSTERESIS),
                1.0,
            )
    return checks


CHECKED_BENDER = "PL140"
"""The bender the checks were set on, at its default sample time (benchmarks.plants.sample_time)."""


DEFAULT_PREVIEW = BenchmarkConfig.preview
"""The preview (samples) of the default run the checks were set on."""


def _settings_departures(result: BenchmarkResult) -> list[str]:
    """How the run's settings depart from the default run the checks were set on, bender and
    sample time aside (empty: they do not)."""
    config = result.config
    bender = str(getattr(config, "bender", CHECKED_BENDER)).split(".")[0]
    dt = float(getattr(config, "dt", None) or sample_time(bender))
    out = []
    steps = getattr(config, "steps", None)
    if steps is not None and steps != round(EPISODE_S / dt):
        out.append(f"its episodes are {steps} steps, not {EPISODE_S:g} s")
    if getattr(config, "preview", DEFAULT_PREVIEW) != DEFAULT_PREVIEW:
        out.append(f"its preview is {config.preview} samples, not {DEFAULT_PREVIEW}")
    options = sorted(getattr(config, "controller_options", None) or {})
    if options:
        out.append(f"it sets options of {', '.join(options)}")
    return out


def _on_checked_bender(result: BenchmarkResult) -> bool:
    bender = str(getattr(result.config, "bender", CHECKED_BENDER))
    dt = getattr(result.config, "dt", None)
    same_dt = dt is None or abs(dt - sample_time(CHECKED_BENDER)) <= 1e-12
    return bender.split(".")[0] == CHECKED_BENDER and same_dt


def checks_apply(result: BenchmarkResult) -> bool:
    """Whether the run is the default run the checks judge: the checks' bender at its default
    sample time, whole episodes, the default preview and every row at its defaults."""
    return _on_checked_bender(result) and not _settings_departures(result)


def condition_line(result: BenchmarkResult) -> str:
    """One sentence: when the checks apply, and whether this run meets that condition."""
    bender = str(getattr(result.config, "bender", CHECKED_BENDER)).split(".")[0]
    dt = float(getattr(result.config, "dt", None) or sample_time(bender))
    condition = (
        f"The checks apply to a run on the {CHECKED_BENDER} at dt = "
        f"{sample_time(CHECKED_BENDER) * 1e3:g} ms (its default), to the rows and plants each "
        "names that the run has, with whole episodes, the default preview and the rows' default "
        "settings"
    )
    this = f"this run is on the {bender} at dt = {dt * 1e3:g} ms"
    departures = _settings_departures(result)
    if departures:
        this += ", but " + "; ".join(departures)
    if checks_apply(result):
        return f"{condition}; {this}, so they apply."
    return f"{condition}; {this}, so they do not apply."


def missed_checks(checks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The reference checks that do not hold (``piezo benchmark --strict`` fails on any)."""
    return [c for c in checks if not c["holds"]]


def strict_status(checks: list[dict[str, Any]], *, strict: bool) -> int:
    """The exit status of ``piezo benchmark``: 1 under ``--strict`` when a check was missed."""
    return 1 if strict and missed_checks(checks) else 0


def summary_line(checks: list[dict[str, Any]]) -> str:
    """One terminal line on the checks, framed as the project's ('' when the run has none)."""
    if not checks:
        return ""
    missed = missed_checks(checks)
    return (
        f"reference checks (the project's own expectations, not an install test; see the "
        f"report): {len(checks) - len(missed)} of {len(checks)} met"
        + ("" if not missed else "; --strict fails on a miss")
    )


def reference_checks_section(
    checks: list[dict[str, Any]], result: BenchmarkResult | None = None
) -> list[str]:
    """The report's section on the checks, framed as the project's expectations (lines), with
    the condition under which they apply and whether ``result``'s run meets it."""
    condition = [condition_line(result), ""] if result is not None else []
    if not checks:
        why = (
            "none of the rows and plants they compare ran"
            if result is not None and checks_apply(result)
            else "the run is not the one they were set on"
        )
        return ["## Reference checks", "", *condition, f"None for this run: {why}."]
    missed = missed_checks(checks)
    lines = [
        "## Reference checks",
        "",
        *condition,
        "The project's own expectations of this run: limits set from earlier measurements of "
        "the default run on a 2-core machine, kept to notice regressions, and the rankings the "
        "project claims (a ratio with limit 1: the first row ahead). A miss is news about "
        "the controllers on this run, not an installation error; `piezo benchmark --strict` "
        f"turns misses into a failing exit code. {len(checks) - len(missed)} of {len(checks)} "
        "met.",
        "",
        "| check | measured | limit | met |",
        "|---|---|---|---|",
    ]
    lines += [
        f"| {c['target']} | {c['value']:.4g} | {c['limit']:.4g} | {'yes' if c['holds'] else 'NO'} |"
        for c in checks
    ]
    return lines
