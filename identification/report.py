"""Markdown summary of an identification report (the dict of IdentificationResult.report)."""

from __future__ import annotations

from typing import Any

from identification.config import RAND_HOLD_S

__all__ = ["markdown_report"]


def _row(cells: list[Any]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _inversion_error(inversion: dict[str, Any], r: float) -> str:
    """One paragraph on the error of z_hat (the equation error filtered by 1/B)."""
    bound, rms = inversion.get("z_error_bound_V"), inversion.get("z_error_rms_V")
    if bound is None or rms is None:
        return (
            "The hidden signal comes from the regularised deconvolution (B is not "
            "minimum-phase): no worst-case error bound is given for it."
        )
    return (
        f"Error of z_hat: the equation error (|nu| <= r_hat = {r:.4g} um) filtered by 1/B, at "
        f"most r_hat ||1/B||_1 = {bound:.3g} V, RMS r_hat/sqrt(3) ||1/B||_2 = {rms:.3g} V for "
        "independent uniform noise (equivalent V)."
    )


def markdown_report(report: dict[str, Any], figures: list[str]) -> str:
    """Render the report as Markdown, with the figure files linked."""
    env = report["environment"]
    noise = env["noise_bound_um"]
    lines = [
        f"# Hammerstein identification of {env['bender']}",
        "",
        f"dt = {env['dt_s'] * 1e3:g} ms, plant hysteresis {env['hysteresis']}, sensor noise "
        + ("not given" if noise is None else f"+-{noise:g} um")
        + _stroke_text(env.get("stroke_um"))
        + ".",
        "",
        *_source_section(env.get("records")),
        *_validation_section(report["validation"]),
        *_arx_section(report["arx"], report["inversion"]),
        *_refinement_section(report.get("refinement")),
        *_nls_section(report["nls"], env["noise_bound_um"]),
        *_scope_section(report),
        "## Timings (s)",
        "",
        ", ".join(f"{k}: {v}" for k, v in report["timings_s"].items()),
        "",
        "## Figures",
        "",
        *[f"![{name}]({name})" for name in figures],
        "",
    ]
    return "\n".join(lines)


def _source_section(source: dict[str, Any] | None) -> list[str]:
    """Where the records came from, when not from the simulated env."""
    if not source or source.get("kind") == "env":
        return []
    if source.get("kind") == "records":
        split = source.get("split")
        how = "" if split is None else f", one record split at {split:g}"
        return [
            f"Records: {source['manifest']} (SHA-256 {source['manifest_sha256'][:12]}...{how}).",
            "",
        ]
    return ["Records: arrays passed to identify_records.", ""]


def _final_linear_part(report: dict[str, Any]) -> dict[str, Any] | None:
    """The linear part the model ships (after step e' when it was kept, else after b')."""
    refined = (report["nls"].get("output_error") or {}).get("linear_part")
    if refined is not None and report["nls"]["output_error"].get("accepted"):
        return refined
    refinement = report.get("refinement")
    if refinement is None:
        return None
    # step b''s section holds the check frequencies once, beside its before and after
    return {"frequencies_hz": refinement.get("frequencies_hz"), **refinement["after"]}


def _rate_dependent(report: dict[str, Any]) -> bool:
    """Whether the kept network runs on rate-dependent plays (``rate`` on or kept by auto)."""
    refinement = report["nls"].get("output_error") or {}
    if not refinement.get("accepted"):
        return False
    stages = refinement.get("stages") or []
    return bool(stages) and stages[0].get("rate_time_s", 0.0) > 0.0


def _scope_section(report: dict[str, Any]) -> list[str]:
    """What the identified model is good for and what not, from this run's own figures."""
    config, val, env = report["config"], report["validation"], report["environment"]
    noise = env["noise_bound_um"]
    noise_rms = None if noise is None else noise / 3**0.5  # uniform sensor noise
    fit, rmse = val["hammerstein"]["fit_percent"], val["hammerstein"]["rmse"]
    rich = config["rich_signal"]
    band = ""
    if rich == "random":
        params = config.get("rich_params") or {}
        hold_s = params["hold"] * env["dt_s"] if "hold" in params else RAND_HOLD_S
        # The held signal's band reaches 1 / hold; sampled, nothing beyond Nyquist, 1 / (2 dt).
        top = min(1.0 / hold_s, 0.5 / env["dt_s"])
        band = f" and references up to about {top:.0f} Hz (its band)"
    loops = {
        "random": "loops of every size",
        "decaying-multisine": "nested loops of every size",
        "sine": "one major loop only",
    }.get(rich, "what that record drew")
    if noise_rms is None:
        check = "the sensor's noise bound is not given (noise_bound_um in records.json)"
    elif rmse <= 1.1 * noise_rms:
        check = "what a measurement can check of it, it predicts"
    else:
        check = "the model misses part of what the sensor sees"
    against = (
        "the sensor noise (not given)"
        if noise_rms is None
        else f"{noise_rms:.2f} um RMS of sensor noise"
    )
    good = [
        f"- **Good for** model-based control of this bender (MPC, feedforward) with drive "
        f"voltages within +-{config['rich_amplitude']:g} V, the range of the rich record"
        f"{band}: the network saw {loops} there ({rich} record). On fresh data (RAND "
        f"+-{config['validation_amplitude']:g} V) the free run errs by {rmse:.2f} um RMS (fit "
        f"{fit:.2f} %), against {against}: {check}. What it costs "
        "an MPC against the plant's own model is measured in "
        "`benchmarks/results/identification_precision.md`.",
    ]
    linear = _final_linear_part(report)
    if linear is not None and linear.get("response_error_vs_plant") is not None:
        pairs = list(zip(linear["frequencies_hz"], linear["response_error_vs_plant"], strict=True))
        within = [e for f, e in pairs if f <= 100.0]
        above = [f"{100 * e:.2f} % at {f:g} Hz" for f, e in pairs if f > 100.0]
        good.append(
            f"- Its linear part (order {linear['order']}) follows the plant's within "
            f"{100 * max(within):.3f} % up to 100 Hz (response shape against the true plant, "
            "simulation only); above, where only the small PRBS informed it, "
            + (", ".join(above) if above else "nothing was checked")
            + "."
        )
    one_step = val.get("hammerstein_one_step", {}).get("fit_percent")
    not_good = [
        "- **Not good for** voltages beyond the identified range (the network continues along "
        "its affine part: the physics of small signals, not of saturation or depolarisation);",
        "- rate-dependent hysteresis or creep: the memory features are rate-independent, and "
        "records of seconds do not show a drift over minutes;"
        if not _rate_dependent(report)
        else "- creep: records of seconds do not show a drift over minutes (the plays' "
        "rate dependence covers loops that widen with the drive's rate, not drift);",
    ]
    if one_step is not None:
        not_good.append(
            "- one-step-ahead prediction with the ARX part's own noise model (fit "
            f"{one_step:.2f} %, below the free run's {fit:.2f} %): its equation error is not the "
            "sensor's output noise, so an observer should be designed for output noise, as the "
            "MPC's is (`controllers.observer`);"
        )
    not_good.append(
        "- another bender of the family, or this one after its parameters moved (temperature, "
        "load, ageing): the model is fixed; the robustness rows of `piezo benchmark` measure "
        "what that costs, and `mpc-adaptive` re-estimates the linear part online."
    )
    return ["## What this model is good for, and what not", "", *good, *not_good, ""]


def format_free_run(value: float | None, spec: str) -> str:
    """A free-run figure, or why there is none (an unstable estimate)."""
    return "unstable (no free run)" if value is None else format(value, spec)


def _stroke_text(stroke_um: float | None) -> str:
    """The stroke in the report's first line: one-sided, and the full stroke percentages use."""
    if stroke_um is None:
        return ", stroke not given"
    return f", stroke +-{stroke_um:g} um (full stroke {2 * stroke_um:g} um)"


def _validation_section(val: dict[str, Any]) -> list[str]:
    full = val["hammerstein"].get("full_stroke")
    percent = "RMSE, % of the full stroke" + (f" ({full:g} um)" if full else " (not given)")
    lines = [
        "## Validation (free run on fresh data)",
        "",
        f"Signal: {val['signal']}, {val['samples']} samples.",
        "",
        _row(["model", "fit %", "RMSE (um)", percent, "max error (um)"]),
        _row(["---"] * 5),
    ]
    for name, key in (
        ("Hammerstein (free run)", "hammerstein"),
        ("Hammerstein before step e' (free run)", "hammerstein_unrefined_nls"),
        ("linear ARX (free run)", "linear_arx"),
        ("Hammerstein (one step ahead)", "hammerstein_one_step"),
    ):
        if key not in val:  # step e' skipped, or a report made before it existed
            continue
        m = val[key]
        lines.append(
            _row(
                [
                    name,
                    f"{m['fit_percent']:.2f}",
                    f"{m['rmse']:.2f}",
                    format(m["rmse_percent_stroke"], ".2f") if full else "-",
                    f"{m['max_abs_error']:.1f}",
                ]
            )
        )
    r_model = val.get("equation_error_bound_um")
    bound = (
        []
        if r_model is None
        else [
            f"r_hat of the model's linear part +-{r_model:.2f} um: its largest equation error "
            "A(q) y - B(q) z on the records it was fitted on, the bound of the one-step-ahead "
            "residuals (residuals.png); the r_hat of step b below is of step b's estimate, "
            "before steps b' and e' changed the linear part.",
            "",
        ]
    )
    return [
        *lines,
        "",
        f"RMSE ratio Hammerstein / linear ARX: {val['rmse_ratio_hammerstein_to_arx']:.3f}.",
        "",
        *bound,
    ]


def _scores(scores: dict[str, float | None], spec: str, unit: str = "") -> str:
    """``n = 2: 97.10 %, n = 4: unstable``: an order whose score is not finite (an unstable
    candidate, stored as null in report.json) is named so instead of formatted."""
    return ", ".join(
        f"n = {k}: " + ("unstable" if v is None else f"{v:{spec}}{unit}") for k, v in scores.items()
    )


def _arx_section(arx: dict[str, Any], inversion: dict[str, Any]) -> list[str]:
    lines = [
        "## ARX part",
        "",
        f"Order ARX({arx['order']},{arx['order']}), chosen by held-out PRBS free-run fit: "
        + _scores(arx["order_scores_fit_percent"], ".2f", " %")
        + ".",
        "",
        _row(["", "bayes-uniform", "chebyshev (exact MAP)", "least squares"]),
        _row(["---"] * 4),
    ]
    theta = arx["a"] + arx["b"]
    names = [f"a{i + 1}" for i in range(len(arx["a"]))]
    names += [f"b{i + 1}" for i in range(len(arx["b"]))]
    for i, name in enumerate(names):
        lines.append(
            _row(
                [
                    name,
                    f"{theta[i]:.6g}",
                    f"{arx['chebyshev']['theta'][i]:.6g}",
                    f"{arx['least_squares']['theta'][i]:.6g}",
                ]
            )
        )
    lines.append(
        _row(
            [
                "r (um)",
                f"{arx['noise_bound_um']:.4g}",
                f"{arx['chebyshev']['noise_bound_um']:.4g}",
                "",
            ]
        )
    )
    return [
        *lines,
        "",
        f"{arx['noise_bound_note']}. Minimum-phase B: {arx['minimum_phase']}; hidden signal by "
        f"{inversion['method']}.",
        "",
        _inversion_error(inversion, arx["noise_bound_um"]),
        "",
    ]


def _roots(values: list[list[float]]) -> str:
    """Complex roots as ``a+bj`` text, one decimal place more than a table needs."""
    return ", ".join(f"{complex(re, im):.3f}".strip("()") for re, im in values) or "none"


def _refinement_section(refinement: dict[str, Any] | None) -> list[str]:
    """Step b': the linear part before and after the output-error refinement (absent in a
    report of ``refinement="none"`` or of a run made before the step existed)."""
    if refinement is None:
        return []
    freqs = refinement["frequencies_hz"]
    before, after = refinement["before"], refinement["after"]
    lines = [
        "## Output-error refinement of the linear part (step b')",
        "",
        f"Method: {refinement['method']}; order {after['order']}: the smallest minimum "
        "description length on the first three quarters of the PRBS record, unless a smaller "
        "order predicts the last quarter at least as well ("
        + _scores(refinement["order_description_length"], ".1f")
        + "); free-run RMS error on the last quarter (um): "
        + _scores(refinement["order_scores_rms_um"], ".3f")
        + ". Identified output noise: white, RMS "
        f"{refinement['output_noise_std_um']:.3f} um, largest "
        f"{refinement['output_error_bound_um']:.3f} um on the PRBS record.",
        "",
        _row(["", "before (step b)", "after (step b')"]),
        _row(["---"] * 3),
        _row(["order", before["order"], after["order"]]),
        _row(
            [
                "free-run RMS on the PRBS record (um)",
                format_free_run(before["prbs_free_run_rms_um"], ".3f"),
                format_free_run(after["prbs_free_run_rms_um"], ".3f"),
            ]
        ),
        _row(
            [
                "linear free-run fit on the validation record (%)",
                format_free_run(before["validation_linear_fit_percent"], ".2f"),
                format_free_run(after["validation_linear_fit_percent"], ".2f"),
            ]
        ),
        _row(["zeros", _roots(before["zeros"]), _roots(after["zeros"])]),
        _row(["poles", _roots(before["poles"]), _roots(after["poles"])]),
    ]
    plant = refinement["true_plant"]
    if plant is None:  # measured records: no true plant to compare with
        return [*lines, ""]
    for i, f in enumerate(freqs):
        lines.append(
            _row(
                [
                    f"response error vs plant at {f:g} Hz (%)",
                    f"{100 * before['response_error_vs_plant'][i]:.2f}",
                    f"{100 * after['response_error_vs_plant'][i]:.2f}",
                ]
            )
        )
    return [
        *lines,
        "",
        "Response error: |G/G(1) - P/P(1)| / |P/P(1)| against the true plant's linear part P "
        "(each normalised to its static gain: z is in equivalent volts). The true plant is "
        "known in simulation only and is used for this comparison, never for fitting. Its "
        f"zeros: {_roots(plant['zeros'])}; poles: {_roots(plant['poles'])}.",
        "",
    ]


_STOPS = {
    "cap": "stopped at the cap",
    "converged": "converged",
    "tolerance": "stopped by the tolerance: a window gained less than the data resolve",
}
"""How an L-BFGS stage of step e' ended (:func:`identification.nls.output_error._lbfgs`); a
stage record without ``stopped`` is read from its ``capped``."""


def _nls_refinement_section(
    refinement: dict[str, Any] | None, noise_bound: float | None
) -> list[str]:
    """Step e': the model before and after the output-error refinement of both blocks."""
    if refinement is None:
        return []
    training, selection = refinement["training_rms_um"], refinement["selection_rms_um"]
    if refinement["accepted"]:
        verdict = "kept"
    else:
        verdict = f"not kept ({refinement['refusal']}): step e's model stays"
    stages = " and ".join(
        f"{stage['iterations']} iterations ({stage['evaluations']} evaluations"
        + f", {_STOPS[stage.get('stopped', 'cap' if stage['capped'] else 'converged')]})"
        for stage in refinement["stages"]
    )
    rows = [
        _row(["free-run RMS output error (um)", "before (steps b', e)", "after (step e')"]),
        _row(["---"] * 3),
        _row(["training records (PRBS and rich)", *_um_pair(training)]),
        _row(["held-out selection record", *_um_pair(selection)]),
    ]
    linear = refinement["linear_part"]
    response = linear["response_error_vs_plant"]
    errors = (
        "; response error against the true plant's linear part (as in step b'): "
        + ", ".join(
            f"{f:g} Hz: {100 * e:.2f} %"
            for f, e in zip(linear["frequencies_hz"], response, strict=True)
        )
        if response is not None
        else ""
    )
    floor = (
        f"The sensor noise alone gives r/sqrt(3) = {noise_bound / 3**0.5:.3f} um RMS."
        if noise_bound is not None
        else "The sensor's noise bound was not given."
    )
    note = f" {refinement['note'].capitalize()}." if refinement.get("note") else ""
    note += _radii_note(refinement) + _feature_choice_note(refinement.get("feature_choice"))
    return [
        "### Output-error refinement of the whole model (step e')",
        "",
        f"Method: {refinement['method']}. Stages: {stages or 'none run'}; "
        f"{refinement['wall_time_s']:.1f} s; {verdict}.{note} Small-signal gain of the "
        f"model's network: {refinement['small_signal_gain']:.3f}.",
        "",
        *rows,
        "",
        f"The model's linear part: zeros {_roots(linear['zeros'])}; poles "
        f"{_roots(linear['poles'])}{errors}.",
        "",
        "Step e fits z_hat, which weighs an error of z the same at every frequency, while the "
        "deflection sees it through the linear part, most where a reference's harmonics meet "
        "the first bending mode; and step b' saw only the small PRBS. Step e' minimises the "
        f"deflection's error itself, over both blocks. {floor}",
        "",
    ]


def _feature_choice_note(choice: dict[str, Any] | None) -> str:
    """Whether step e' also refined play beside step e's choice, and which set it kept."""
    if not choice:
        return ""
    rms = ", ".join(f"{name} {value:.3f} um" for name, value in choice["held_out_rms_um"].items())
    return (
        f" Step e chose {choice['step_e']} features; held-out RMS after step e': {rms}; "
        f"kept {choice['kept']} ({choice['why']})."
    )


def _radii_note(refinement: dict[str, Any]) -> str:
    """The learned play radii and rate constant of the radius stage, and the ``rate="auto"``
    choice; empty when no radius stage ran."""
    stages = refinement.get("stages") or []
    if not stages or "radii_after" not in stages[0]:
        return ""
    first = stages[0]
    radii = ", ".join(f"{r:.2f}" for r in first["radii_after"])
    text = f" Play radii learned: {radii} V"
    if "rate_time_s" in first:
        text += f"; rate constant {first['rate_time_s']:.3g} s"
        if first.get("rate_note"):
            text += f" ({first['rate_note']})"
    choice = refinement.get("rate_choice")
    if choice and not choice.get("determined", True):
        text += "; rate-dependent plays not fitted (the records do not determine a rate constant)"
    elif choice:
        verdict = "kept" if choice["kept"] else "not kept"
        rate_rms = choice.get("rate_rms_um")
        text += (
            f"; rate-dependent plays {verdict} (held-out RMS "
            f"{'n/a' if rate_rms is None else f'{rate_rms:.3f}'} um against "
            f"{choice['plain_rms_um']:.3f} um, threshold {choice['threshold_um2']:.3g} um^2 on "
            "the mean square)"
        )
    return text + "."


def _um_pair(values: dict[str, float | None]) -> list[str]:
    """``before`` and ``after`` in um, "n/a" where absent (not run, or not finite)."""
    return [
        "n/a" if values.get(key) is None else f"{values[key]:.3f}" for key in ("before", "after")
    ]


def _nls_section(nls: dict[str, Any], noise_bound: float | None) -> list[str]:
    return [
        *_nls_section_head(nls),
        *_nls_refinement_section(nls.get("output_error"), noise_bound),
    ]


def _nls_section_head(nls: dict[str, Any]) -> list[str]:
    return [
        "## NLS",
        "",
        f"Features: {nls['features']} (selection fits: "
        + ", ".join(f"{k} {v:.2f} %" for k, v in nls["selection_fit_percent"].items())
        + f"). Small-signal gain on the PRBS record: {nls['small_signal_gain']:.3f} "
        "(1 by the scale convention: z is in equivalent volts).",
        "",
        "The default simulated plant's hysteresis is Bouc-Wen, the family of the bouc-wen "
        "features, so those features can represent it closely; on other plants the selection "
        "record decides (see benchmarks/results/identification_accuracy.md).",
        "",
    ]
