"""Identification benchmark: Hammerstein models against the linear ARX and NARX networks.

1. Identifies the default bender (PL140, dt 1 ms, Bouc-Wen hysteresis, 1 um sensor noise) with
   ``identification.identify``: once with ``features="auto"`` (the default ``piezo identify``
   path; its wall time, plus that of writing the model files, reports and figures, is the
   end-to-end figure) and once per NLS feature set ("play", "past-inputs", "bouc-wen"), all
   with the same seed, hence the same PRBS, rich and selection records and the same ARX part.
2. Baselines on the same identification data: the linear ARX part alone, and a NARX network
   without the Hammerstein split (``benchmarks/studies/_narx.py``) trained one step ahead on the
   PRBS and rich records of the pipeline, in two forms: an MLP with an affine skip initialised by
   least squares, and a plain MLP.
3. Scores every model by free-run simulation on held-out test records, each collected fresh
   from the env from rest with its own seeds: RAND +-30 V (hold 1, 10, 50 samples), SINE
   (1, 5, 20 Hz at 30 V and at 10 V), triangle, multisine and chirp.
4. Generalisation: identifies PL122 with Bouc-Wen and PL140 with Prandtl-Ishlinskii hysteresis
   (``features="auto"``) and scores them on held-out RAND (hold 10).

Writes ``benchmarks/results/identification_accuracy.md``. Run:
``python -m benchmarks.studies.identification_accuracy`` (about three minutes on two cores).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace

import gymnasium as gym
import numpy as np

import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from benchmarks._common import header, markdown_table, write_result
from benchmarks.studies._narx import NARXNetwork
from identification.features import FEATURE_SETS
from identification.metrics import fit_metrics
from identification.pipeline import IdentificationConfig, collect, identify, write_outputs
from piezo_env.signals import make_signal

SEED = 0
"""Seed of every identification run (the ``piezo identify`` default)."""
TEST_SEED = 20_240_000
"""Base seed of the held-out test records (signal draws and env noise)."""
TEST_SAMPLES = 6000
"""Length of every test record (6 s at dt = 1 ms)."""
NARX_LAGS = 6
"""Output and input lags of the NARX networks (one above the usual selected ARX order)."""

# label, signal name, parameters (amplitude in V, frequencies in Hz)
TEST_SIGNALS: list[tuple[str, str, dict]] = [
    ("RAND +-30 V, hold 1", "random", {"amplitude": 30.0, "hold": 1}),
    ("RAND +-30 V, hold 10", "random", {"amplitude": 30.0, "hold": 10}),
    ("RAND +-30 V, hold 50", "random", {"amplitude": 30.0, "hold": 50}),
    ("SINE 1 Hz, 30 V", "sine", {"amplitude": 30.0, "frequency": 1.0}),
    ("SINE 5 Hz, 30 V (rich input)", "sine", {"amplitude": 30.0, "frequency": 5.0}),
    ("SINE 20 Hz, 30 V", "sine", {"amplitude": 30.0, "frequency": 20.0}),
    ("SINE 1 Hz, 10 V", "sine", {"amplitude": 10.0, "frequency": 1.0}),
    ("SINE 5 Hz, 10 V", "sine", {"amplitude": 10.0, "frequency": 5.0}),
    ("SINE 20 Hz, 10 V", "sine", {"amplitude": 10.0, "frequency": 20.0}),
    ("triangle 2 Hz, 30 V", "triangle", {"amplitude": 30.0, "frequency": 2.0}),
    (
        "multisine 1-40 Hz, 30 V",
        "multisine",
        {"amplitude": 30.0, "f_min": 1.0, "f_max": 40.0, "n_tones": 40},
    ),
    ("chirp 1-50 Hz, 30 V", "chirp", {"amplitude": 30.0, "f0": 1.0, "f1": 50.0}),
]

GENERALISATION = [
    ("PL122, Bouc-Wen", {"bender": "PL122", "hysteresis": "bouc-wen"}),
    ("PL140, Prandtl-Ishlinskii", {"bender": "PL140", "hysteresis": "prandtl-ishlinskii"}),
]


def make_env(env_kwargs: dict) -> gym.Env:
    """PiezoBender-v0 without reference and without episode limit (open-loop experiments)."""
    return gym.make("piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, **env_kwargs)


def test_records(env: gym.Env, signals=TEST_SIGNALS) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Held-out (u, y) records, one per test signal, each with its own signal and noise seed."""
    dt = env.unwrapped.model.dt
    records = {}
    for i, (label, name, params) in enumerate(signals):
        u = make_signal(
            name, TEST_SAMPLES, dt=dt, rng=np.random.default_rng(TEST_SEED + i), **params
        )
        records[label] = collect(env, u, seed=TEST_SEED + 1000 + i)
    return records


def identification_records(result) -> list[tuple[np.ndarray, np.ndarray]]:
    """The PRBS and rich (u, y) records the pipeline identified from (``result.data``)."""
    data = result.data
    return [
        (np.asarray(data["u_prbs"]), np.asarray(data["y_prbs"])),
        (np.asarray(data["u_rich"]), np.asarray(data["y_rich"])),
    ]


def score(y: np.ndarray, y_hat: np.ndarray, stroke: float) -> dict | None:
    """Fit metrics of a free run, or None when the run diverged (non-finite output)."""
    if not np.all(np.isfinite(y_hat)):
        return None
    return fit_metrics(y, y_hat, stroke=stroke)


def cell(metrics: dict | None) -> str:
    """Table cell "fit % / RMSE um"."""
    if metrics is None:
        return "diverged"
    return f"{metrics['fit_percent']:.1f} / {metrics['rmse']:.1f}"


def main() -> None:
    """Identify, score on held-out records and other benders, write the report."""
    script_start = time.perf_counter()
    base = IdentificationConfig(seed=SEED)
    env = make_env(base.env_kwargs)
    runs = _identify_every_way(base)
    models = {f"Hammerstein {f}": runs["by_features"][f].model for f in FEATURE_SETS}
    models["linear ARX"] = runs["auto"].model.arx
    records = identification_records(runs["auto"])
    narx = _narx_baselines(records)
    models.update(narx)
    tests = test_records(env)
    stroke = env.unwrapped.model.stroke_um
    scores = {
        label: {name: score(y, model.simulate(u), stroke) for name, model in models.items()}
        for label, (u, y) in tests.items()
    }
    lines = [
        *header("Identification benchmark", __spec__.name),
        *_setup_lines(runs["auto"], base, stroke),
        *_timing_section(runs, tests),
        *_held_out_section(runs, models, tests, scores, narx, records),
        *_other_benders_section(base),
        f"Whole script: {time.perf_counter() - script_start:.0f} s.",
    ]
    write_result("identification_accuracy", lines)


def _identify_every_way(base: IdentificationConfig) -> dict:
    """The default path once (timed, with its files written), then each feature set."""
    start = time.perf_counter()
    auto = identify(config=base, progress=print)
    identify_time = time.perf_counter() - start
    with tempfile.TemporaryDirectory() as out:
        start = time.perf_counter()
        n_files = len(write_outputs(auto, out))
        write_time = time.perf_counter() - start
    by_features = {}
    for features in FEATURE_SETS:
        print(f"-- identify with features={features}")
        by_features[features] = identify(config=replace(base, features=features))
    return {
        "auto": auto,
        "by_features": by_features,
        "identify_s": identify_time,
        "write_s": write_time,
        "n_files": n_files,
    }


def _narx_baselines(records) -> dict:
    """NARX networks on the pipeline's PRBS and rich records, with and without a skip."""
    narx = {}
    for label, skip in (("NARX (skip)", True), ("NARX (plain)", False)):
        print(f"-- train {label}")
        narx[label] = NARXNetwork(ny=NARX_LAGS, nu=NARX_LAGS, seed=SEED, skip=skip).fit(records)
    return narx


def _setup_lines(auto, base: IdentificationConfig, stroke: float) -> list[str]:
    environment = auto.report["environment"]
    base = base.at_sample_time(environment["dt_s"])  # durations in samples, as identify ran
    return [
        f"Default bender: {environment['bender']}, dt = {environment['dt_s'] * 1e3:g} ms, "
        f"{environment['hysteresis']} hysteresis, +-{environment['noise_bound_um']:g} um sensor "
        f"noise, stroke {stroke:.0f} um; drive +-30 V. Identification seed {SEED} (pipeline "
        f"defaults: PRBS +-{base.prbs_amplitude:g} V x {base.prbs_samples}, step b' "
        f"{base.refinement}, rich {base.rich_signal} {_signal_params(base)}"
        f"{base.rich_amplitude:g} V x {base.rich_samples}, step e' {base.nls_refinement}).",
        "",
    ]


def _signal_params(config: IdentificationConfig) -> str:
    """The rich signal's parameters as text (``"frequency 5 Hz, "``), empty without any."""
    params = config.rich_signal_params()
    return "".join(f"{key} {value}, " for key, value in params.items())


def _timing_section(runs: dict, tests: dict) -> list[str]:
    auto, by_features = runs["auto"], runs["by_features"]
    selected = auto.report["nls"]["features"]
    timings, arx = auto.report["timings_s"], auto.report["arx"]
    u_check = tests["RAND +-30 V, hold 10"][0]
    same = float(
        np.max(np.abs(auto.model.simulate(u_check) - by_features[selected].model.simulate(u_check)))
    )
    nls_rows = [
        [
            f,
            f"{auto.report['nls']['selection_fit_percent'][f]:.2f}",
            f"{by_features[f].report['validation']['hammerstein']['fit_percent']:.2f}",
            f"{by_features[f].report['timings_s']['e_nls_training']:.1f}",
            f"{by_features[f].report['nls']['training']['epochs']}",
        ]
        for f in FEATURE_SETS
    ]
    total = runs["identify_s"] + runs["write_s"]
    return [
        '## End-to-end time of `identify` (features="auto", the `piezo identify` path)',
        "",
        f"`identify`: **{runs['identify_s']:.1f} s** wall time, of which "
        + ", ".join(f"{k} {v:.1f} s" for k, v in timings.items() if k != "total")
        + f"; writing the model files, reports and figures (`write_outputs`, {runs['n_files']} "
        f"files): {runs['write_s']:.1f} s; together **{total:.1f} s** (target for "
        "`piezo identify`: under 120 s). Selected ARX order "
        f"{arx['order']} (held-out PRBS fit "
        + ", ".join(f"n={k}: {v:.1f} %" for k, v in arx["order_scores_fit_percent"].items())
        + f"), r_hat = {arx['noise_bound_um']:.2f} um, B minimum-phase: "
        f"{arx['minimum_phase']}; selected NLS features: **{selected}**.",
        "",
        markdown_table(
            ["NLS features", "selection fit %", "pipeline validation fit %", "NLS fit s", "epochs"],
            nls_rows,
        ),
        "",
        "Selection: RAND +-30 V hold 10 record of the pipeline; validation: its fresh RAND record.",
        f"The auto model equals the {selected} model (max |difference| of the free runs "
        f"{same:.1e} um).",
        "",
    ]


def _held_out_section(runs, models, tests, scores, narx, records) -> list[str]:
    selected = runs["auto"].report["nls"]["features"]
    rand10 = scores["RAND +-30 V, hold 10"]
    h_sel, h_lin = rand10[f"Hammerstein {selected}"], rand10["linear ARX"]
    return [
        "## Free-run fit on held-out test records: fit % / RMSE um",
        "",
        f"Each record: {TEST_SAMPLES} samples from rest, signal and noise seeds disjoint from "
        "identification. H = Hammerstein model with that NLS feature set (same ARX part); "
        "linear ARX = that ARX part alone; NARX = "
        f"y_t = MLP(y_t-1..t-{NARX_LAGS}, u_t-1..t-{NARX_LAGS}), 3 x 32 tanh, trained one step "
        "ahead on the pipeline's PRBS + rich records, early-stopped on the free-run fit of their "
        "last 20 %; (skip): plus an affine skip initialised by least squares, (plain): MLP only. "
        "SINE 5 Hz 30 V is the rich identification input (fresh noise).",
        "",
        _held_out_table(list(models), tests, scores, selected),
        "",
        f"Targets on RAND +-30 V hold 10 (selected model, {selected}): fit "
        f"{h_sel['fit_percent']:.2f} % (target >= 95 %), RMSE ratio Hammerstein / ARX "
        f"{h_sel['rmse'] / h_lin['rmse']:.3f} (target <= 0.333).",
        "",
        _narx_table(narx),
        "",
        f"NARX training data: {sum(len(u) for u, _ in records)} samples: the pipeline's PRBS and "
        "rich records.",
        "",
    ]


def _held_out_table(names: list[str], tests: dict, scores: dict, selected: str) -> str:
    """Fit % / RMSE of every model on every test record, and each model's worst fit."""
    head = [
        "test signal",
        "peak abs(y) um",
        *[
            n.replace("Hammerstein ", "H ")
            + (" (selected)" if n == f"Hammerstein {selected}" else "")
            for n in names
        ],
    ]
    rows = [
        [label, f"{np.abs(tests[label][1]).max():.0f}", *[cell(scores[label][n]) for n in names]]
        for label in tests
    ]
    worst = []
    for n in names:
        fits = {
            label: (s[n]["fit_percent"] if s[n] is not None else -np.inf)
            for label, s in scores.items()
        }
        label = min(fits, key=fits.get)
        worst.append(f"{fits[label]:.1f} ({label})")
    rows.append(["**worst fit %**", "", *worst])
    return markdown_table(head, rows)


def _narx_table(narx: dict) -> str:
    """Training record of each NARX baseline."""
    rows = [
        [
            label,
            f"{m.training['epochs']}",
            f"{m.training['best_epoch']}",
            f"{m.training['validation_free_run_fit_percent']:.2f}",
            f"{m.training['wall_time_s']:.1f}",
        ]
        for label, m in narx.items()
    ]
    head = ["NARX", "epochs", "best epoch", "validation free-run fit %", "training s"]
    return markdown_table(head, rows)


def _other_bender_row(label: str, env_kwargs: dict, base: IdentificationConfig) -> list[str]:
    print(f"-- identify {label}")
    t0 = time.perf_counter()
    other = identify(config=replace(base, env_kwargs=env_kwargs))
    elapsed = time.perf_counter() - t0
    other_env = make_env(env_kwargs)
    u, y = test_records(other_env, [TEST_SIGNALS[1]])[TEST_SIGNALS[1][0]]
    other_stroke = other_env.unwrapped.model.stroke_um
    ham = score(y, other.model.simulate(u), other_stroke)
    lin = score(y, other.model.arx.simulate(u), other_stroke)
    sel = other.report["nls"]["selection_fit_percent"]
    order = other.report["arx"]["order"]
    return [
        label,
        f"{other_stroke:.0f}",
        f"ARX({order},{order})",
        other.report["nls"]["features"],
        ", ".join(f"{k} {v:.1f}" for k, v in sel.items()),
        cell(ham),
        cell(lin),
        f"{ham['rmse'] / lin['rmse']:.3f}" if ham and lin else "-",
        f"{elapsed:.1f}",
    ]


def _other_benders_section(base: IdentificationConfig) -> list[str]:
    rows = [_other_bender_row(label, env_kwargs, base) for label, env_kwargs in GENERALISATION]
    head = [
        "env",
        "stroke um",
        "ARX order",
        "selected",
        "selection fit % per feature set",
        "Hammerstein",
        "linear ARX",
        "RMSE ratio",
        "identify s",
    ]
    return [
        '## Other benders and hysteresis models (features="auto")',
        "",
        "Held-out RAND +-30 V hold 10, free run, fit % / RMSE um.",
        "",
        markdown_table(head, rows),
        "",
    ]


if __name__ == "__main__":
    main()
