"""What an identification run returns and writes: the result, its report (JSON-safe) and files.

:func:`write_outputs` writes the model folder, ``report.json``, ``report.md`` and the figures.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from identification.arx import ARXModel
from identification.config import IdentificationConfig
from identification.hammerstein import HammersteinModel
from identification.metrics import complex_response
from identification.records import Records
from identification.steps import (
    ArxEstimate,
    HiddenSignal,
    LinearRefinement,
    NlsFit,
    NlsRefinement,
    Validation,
)

__all__ = [
    "IdentificationResult",
    "build_report",
    "complex_list",
    "figure_data",
    "jsonable",
    "model_metadata",
    "validation_signal",
    "write_outputs",
]


@dataclass
class IdentificationResult:
    """Output of :func:`identify`.

    Attributes
    ----------
    model : HammersteinModel
        The identified model (z in equivalent volts, y in um).
    report : dict
        Settings, estimates, metrics and timings (JSON-safe).
    data : dict
        The records (u, y, z_hat, simulations) for figures.
    """

    model: HammersteinModel
    report: dict[str, Any]
    data: dict[str, Any]


def model_metadata(
    records: Records,
    config: IdentificationConfig,
    features: str,
    hidden: HiddenSignal,
    refinement: LinearRefinement | None = None,
    nls_refinement: NlsRefinement | None = None,
) -> dict[str, Any]:
    """What the model files record about their origin (JSON-safe): the bender (its datasheet
    values) and the task it was identified on, so that a controller can refuse another one;
    where the records came from (``records``: the env, or the manifest's path and SHA-256);
    with step b', how the linear part was refined and the output noise it identified on the
    PRBS record (a model saved before step b' existed has no ``linear_part`` entry and loads as
    before); with step e', whether it refined the model further and the free-run error it left
    on the training records (``nls_refinement``)."""
    extra = {}
    if refinement is not None:
        extra["linear_part"] = {
            "step": "b'",
            "method": refinement.model.method,
            "order": refinement.order,
            "output_noise_std_um": refinement.fit.output_error_rms,
            "output_error_bound_um": refinement.fit.output_error_bound,
        }
    if nls_refinement is not None:
        extra["nls_refinement"] = {
            "step": "e'",
            "method": "output-error (network, then network and linear part)",
            "accepted": nls_refinement.accepted,
            "linear_part_refined": nls_refinement.accepted and nls_refinement.note is None,
            "training_rms_um": dict(nls_refinement.training_rms_um),
            "selection_rms_um": dict(nls_refinement.selection_rms_um),
        }
    return {
        **extra,
        "bender": records.bender,
        "datasheet": records.datasheet,
        "task": {
            "dt_s": records.dt,
            "u_max_V": records.u_max,
            "noise_bound_um": records.noise_bound_um,
        },
        "dt": records.dt,
        "features": features,
        "seed": config.seed,
        "records": dict(records.source),
        "z_error_bound_V": hidden.error["z_error_bound_V"],
        "z_error_rms_V": hidden.error["z_error_rms_V"],
    }


def build_report(
    records: Records,
    config: IdentificationConfig,
    est: ArxEstimate,
    hidden: HiddenSignal,
    nls: NlsFit,
    val: Validation,
    timings: dict[str, float],
    refinement: LinearRefinement | None = None,
    nls_refinement: NlsRefinement | None = None,
    *,
    true_plant: Any = None,
) -> dict[str, Any]:
    """The JSON report of a run (keys read by the CLI, the benchmarks and report.md).

    With step b', ``refinement`` compares the step b estimate with the refined linear part,
    and, given the simulated plant's linear part ``true_plant`` (python-control state space),
    each against it: used for the report only, never for fitting; measured records have none.
    """
    return {
        "config": jsonable(asdict(config)),
        "environment": _environment_section(records),
        "arx": _arx_section(est),
        "refinement": _refinement_section(true_plant, est, refinement, val),
        "inversion": {
            "method": hidden.method,
            **hidden.error,
            "error_note": (
                "z_hat - z is the ARX equation error filtered by 1/B: at most "
                "r_hat ||1/B||_1 (z_error_bound_V), RMS r_hat/sqrt(3) ||1/B||_2 "
                "(z_error_rms_V) for independent uniform noise; equivalent V"
            ),
        },
        "nls": {
            "features": nls.features,
            "small_signal_gain": (
                nls.small_signal_gain
                if nls_refinement is None
                else nls_refinement.small_signal_gain
            ),
            "selection_fit_percent": nls.selection_scores,
            "training": jsonable(getattr(nls.model.nls, "training", {})),
            "output_error": _nls_refinement_section(true_plant, nls_refinement),
        },
        "validation": _validation_section(config, records, val),
        "timings_s": timings,
    }


def _nls_refinement_section(true: Any, refinement: NlsRefinement | None) -> dict[str, Any] | None:
    """Step e' before and after (None when the run skipped it); the model's linear part against
    the true plant's when there is one, as in step b' (report only, never for fitting)."""
    if refinement is None:
        return None
    return {
        **refinement.record(),
        "linear_part": _linear_part_entry(
            refinement.model.arx, true, frequencies_hz=list(BODE_CHECK_HZ)
        ),
    }


def _environment_section(records: Records) -> dict[str, Any]:
    """The bender and where its records came from (``hysteresis`` is the simulated plant's, or
    ``"unknown (measured records)"``; ``noise_bound_um`` None when the sensor's is not
    known)."""
    return {
        "bender": records.bender,
        "dt_s": records.dt,
        "hysteresis": records.plant.get("hysteresis", "unknown (measured records)"),
        "noise_bound_um": records.noise_bound_um,
        "stroke_um": records.stroke_um,
        "drive_range_V": list(records.drive_range_V),
        "records": dict(records.source),
    }


def _arx_section(est: ArxEstimate) -> dict[str, Any]:
    arx = est.model
    return {
        "order": est.order,
        "order_scores_fit_percent": {str(k): v for k, v in est.order_scores.items()},
        "a": arx.a.tolist(),
        "b": arx.b.tolist(),
        "noise_bound_um": arx.noise_bound,
        "noise_bound_note": (
            "r_hat bounds the ARX equation error A(q) y - B(q) u: the sensor noise filtered by "
            "A(q) (up to 1 + sum |a_i| times its bound) and what the model misses, so it "
            "exceeds the sensor's bound even for an exact model"
        ),
        "static_gain_um_per_V": arx.static_gain(),
        "poles": complex_list(arx.poles()),
        "zeros": complex_list(arx.zeros()),
        "minimum_phase": bool(arx.is_minimum_phase()),
        "chebyshev": {
            "theta": est.chebyshev.theta.tolist(),
            "noise_bound_um": est.chebyshev.noise_bound,
        },
        "least_squares": {"theta": est.least_squares.theta.tolist()},
    }


BODE_CHECK_HZ = (1.0, 10.0, 50.0, 100.0, 200.0, 400.0)
"""Frequencies (Hz) at which the report compares the linear parts with the true plant's."""


def _refinement_section(
    true: Any, est: ArxEstimate, refinement: LinearRefinement | None, val: Validation
) -> dict[str, Any] | None:
    """Step b' before and after: fits, zeros, poles, and, given the true plant's linear part,
    the frequency response against it (normalised to each model's static gain: z is in
    equivalent volts, so the identified gain differs from the plant's by the NLS's small-signal
    gain)."""
    if refinement is None:
        return None
    models = {"before": est.model, "after": refinement.model}
    section: dict[str, Any] = {
        "method": "output-error (prediction error, free-run least squares from the "
        "bayes-uniform estimate)",
        "order_scores_rms_um": {str(k): v for k, v in refinement.order_scores.items()},
        "order_description_length": {str(k): v for k, v in refinement.description_length.items()},
        "solver": {"evaluations": refinement.fit.iterations, "status": refinement.fit.status},
        "output_noise_std_um": refinement.fit.output_error_rms,
        "output_error_bound_um": refinement.fit.output_error_bound,
        "frequencies_hz": list(BODE_CHECK_HZ),
        "true_plant": None
        if true is None
        else {"zeros": complex_list(_ss_zeros(true)), "poles": complex_list(true.poles())},
    }
    prbs_rms = {
        "before": refinement.unrefined_output_error_rms,
        "after": refinement.fit.output_error_rms,
    }
    validation_fit = {
        "before": val.metrics.get("linear_arx_unrefined", val.metrics["linear_arx"]),
        "after": val.metrics.get("linear_arx_before_e2", val.metrics["linear_arx"]),
    }
    for key, model in models.items():
        section[key] = _linear_part_entry(
            model,
            true,
            static_gain_um_per_V=model.static_gain(),
            noise_bound_um=model.noise_bound,
            prbs_free_run_rms_um=prbs_rms[key],
            validation_linear_fit_percent=(
                None if validation_fit[key] is None else validation_fit[key]["fit_percent"]
            ),
        )
    return section


def _linear_part_entry(model: ARXModel, true: Any, **extra: Any) -> dict[str, Any]:
    """A linear part in the report: order, coefficients, zeros and poles, ``extra``, and its
    response error against the true plant's at :data:`BODE_CHECK_HZ` (None without one)."""
    return {
        "order": model.na,
        "a": model.a.tolist(),
        "b": model.b.tolist(),
        "zeros": complex_list(model.zeros()),
        "poles": complex_list(model.poles()),
        **extra,
        "response_error_vs_plant": None
        if true is None
        else relative_response_error(model, true, BODE_CHECK_HZ).tolist(),
    }


def _ss_zeros(system: Any) -> np.ndarray:
    import control

    return np.asarray(control.zeros(system), dtype=complex)


def relative_response_error(model: ARXModel, true: Any, frequencies_hz: Any) -> np.ndarray:
    """``|G(jw)/G(1) - P(jw)/P(1)| / |P(jw)/P(1)|`` at each frequency (Hz): the error of the
    model's frequency response shape against the plant's linear part ``true`` (python-control
    state space), both normalised to their static gains."""
    import control

    w = 2.0 * np.pi * np.asarray(frequencies_hz, dtype=float)
    g = complex_response(model.to_state_space(), w)
    p = complex_response(true, w)
    g = g / model.static_gain()
    p = p / float(np.real(control.dcgain(true)))
    return np.abs(g - p) / np.abs(p)


def validation_signal(config: IdentificationConfig, records: Records) -> str:
    """What the validation record is, in words: the RAND of step f, or the held-out end of a
    split record."""
    if records.shared:
        return "the last part of the split record (after the selection part)"
    return f"RAND +-{config.validation_amplitude:g} V, hold {config.validation_hold} samples"


def _validation_section(
    config: IdentificationConfig, records: Records, val: Validation
) -> dict[str, Any]:
    return {
        "signal": validation_signal(config, records),
        "samples": len(val.u),
        **val.metrics,
        "equation_error_bound_um": val.equation_error_bound_um,
        "rmse_ratio_hammerstein_to_arx": (
            val.metrics["hammerstein"]["rmse"] / val.metrics["linear_arx"]["rmse"]
        ),
    }


def figure_data(
    u_prbs: np.ndarray,
    y_prbs: np.ndarray,
    u_rich: np.ndarray,
    y_rich: np.ndarray,
    hidden: HiddenSignal,
    model: HammersteinModel,
    val: Validation,
    unrefined: ARXModel | None = None,
) -> dict[str, Any]:
    """The records of a run, for the figures (V, equivalent V, um; ``dt`` in s).

    ``unrefined``: the step b estimate (its history draws the estimates' figure; when step b'
    replaced it, the Bode figure compares both with the plant).
    """
    step_b = model.arx if unrefined is None else unrefined
    return {
        "arx_history": step_b.history,
        "arx_unrefined": None if step_b is model.arx else step_b,
        "u_prbs": u_prbs,
        "y_prbs": y_prbs,
        "u_rich": u_rich,
        "y_rich": y_rich,
        "z_hat": hidden.z_rich,
        "z_model": model.nls_output(u_rich),
        "u_val": val.u,
        "y_val": val.y,
        "y_sim": val.y_sim,
        "y_lin": val.y_lin,
        "dt": model.dt,
        "z_error_bound": hidden.error["z_error_bound_V"],
        "prediction_val": val.y_pred,
    }


def complex_list(values: np.ndarray) -> list[list[float]]:
    return [[float(v.real), float(v.imag)] for v in np.asarray(values, dtype=complex)]


def jsonable(obj: Any) -> Any:
    """Plain JSON types (numpy scalars and arrays converted, non-finite floats as None)."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        value = float(obj)
        return value if math.isfinite(value) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


def write_outputs(
    result: IdentificationResult, out: str | Path, runner: Any | None = None
) -> list[Path]:
    """Write the model files, report.json, report.md and the figures into ``out``; a
    ``runner`` with a helper (:class:`identification.runner.StepRunner`, the one the result
    was identified with) draws some of the figures beside this process."""
    from identification.figures import write_figures
    from identification.report import markdown_report

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [result.model.save(out / "model")]
    report_json = out / "report.json"
    report_json.write_text(json.dumps(result.report, indent=2), encoding="utf-8")
    figures = write_figures(result, out, runner=runner)
    report_md = out / "report.md"
    report_md.write_text(
        markdown_report(result.report, [p.name for p in figures]), encoding="utf-8"
    )
    return [*paths, report_json, report_md, *figures]
