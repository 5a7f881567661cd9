"""The two-step identification procedure of the paper (section 3.4, steps a-f).

a) excite the bender with a PRBS; b) estimate the ARX part with the uniform-noise Bayesian
estimator (order chosen by free-run fit on a held-out part of the PRBS record); c) excite it with
a rich signal (SINE by default, as in the paper); d) estimate the hidden signal z_t by inverting
the ARX model (eq. 25), or by a regularised least-squares deconvolution when the estimated B
polynomial is not minimum-phase; e) fit the neural NLS to (u_t, z_hat_t), choosing its memory
features on a separate selection record; f) validate the Hammerstein model by free-run
simulation on fresh RAND data.

Scale (Bai 2004). Under a two-level input a rate-independent nonlinearity is affine, so the
ARX part fitted to (u, y) of the PRBS run is the linear part up to a gain; taking it as is fixes
the scale: the NLS has unit small-signal gain and z is in equivalent volts.

Every record comes from the environment through its Gymnasium interface, as from a real
bender: the measured (noisy) deflection is all the identification sees.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import scipy.signal
import scipy.sparse
import scipy.sparse.linalg

import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from identification.arx import ARXModel
from identification.estimation import fit_arx
from identification.features import FEATURE_SETS
from identification.hammerstein import HammersteinModel
from identification.metrics import fit_metrics
from identification.nls import fit_nls
from piezo_env.signals import SIGNAL_DEFAULTS, make_signal

__all__ = [
    "IdentificationConfig",
    "IdentificationResult",
    "collect",
    "identify",
    "inverse_arx",
    "write_outputs",
]


ORDER_TIE_PERCENT = 0.25
"""Held-out fits (percentage points) this close to the best count as a tie between orders."""


@dataclass(frozen=True)
class IdentificationConfig:
    """Settings of :func:`identify` (validated at construction).

    Attributes
    ----------
    seed : int
        Seeds every signal, the environment and the network training.
    env_kwargs : dict
        Keyword arguments of PiezoBender-v0 (``reference`` is always None here).
    prbs_amplitude : float
        PRBS level C_P (V). The paper's 1 V keeps the ringing first mode well inside the stroke
        (a white +-30 V PRBS would drive a PL140 to ~11x its rated deflection).
    prbs_clock : int
        PRBS clock period (samples).
    prbs_samples : int
        Length of the PRBS record; its last quarter scores the candidate orders.
    orders : tuple of int
        Candidate ARX orders n (na = nb = n), scored by free-run fit on the last quarter of the
        PRBS record; near-ties (ORDER_TIE_PERCENT) go to the larger order.
    rich_signal : str
        Rich excitation for the NLS: ``"sine"`` (paper), ``"multisine"``, ``"random"``, ...
    rich_amplitude : float
        Its amplitude (V).
    rich_params : dict or None
        Further parameters of the rich signal (e.g. frequency, Hz); None: 5 Hz for the sine,
        ``piezo_env.signals.SIGNAL_DEFAULTS`` for the others.
    rich_samples : int
        Length of the rich record.
    features : str
        NLS memory features: ``"auto"`` (chosen on the selection record), or one of
        ``"play"``, ``"past-inputs"``, ``"bouc-wen"``.
    hidden : tuple of int
        Hidden layer widths of the NLS network (three tanh layers in the paper).
    max_epochs : int
        Training epochs at most (early stopping on a validation split).
    validation_amplitude : float
        RAND amplitude C_R (V) of the selection and validation records.
    validation_hold : int
        RAND hold (samples).
    validation_samples : int
        Length of the validation record.
    """

    seed: int = 0
    env_kwargs: dict = field(default_factory=dict)
    prbs_amplitude: float = 1.0
    prbs_clock: int = 1
    prbs_samples: int = 8000
    orders: tuple[int, ...] = (2, 3, 4, 5, 6)
    rich_signal: str = "sine"
    rich_amplitude: float = 30.0
    rich_params: dict | None = None
    rich_samples: int = 12000
    features: str = "auto"
    hidden: tuple[int, ...] = (32, 32, 32)
    max_epochs: int = 200
    validation_amplitude: float = 30.0
    validation_hold: int = 10
    validation_samples: int = 6000

    def __post_init__(self) -> None:
        if self.features != "auto" and self.features not in FEATURE_SETS:
            raise ValueError(
                f"features must be 'auto' or one of {FEATURE_SETS}, got {self.features!r}"
            )
        if not self.orders or not all(isinstance(n, int) and n >= 1 for n in self.orders):
            raise ValueError(f"orders must be positive integers, got {self.orders!r}")
        if not self.hidden or not all(isinstance(h, int) and h >= 1 for h in self.hidden):
            raise ValueError(f"hidden must be positive layer widths, got {self.hidden!r}")
        for name in ("prbs_samples", "rich_samples", "validation_samples"):
            if getattr(self, name) < 200:
                raise ValueError(f"{name} must be at least 200 samples, got {getattr(self, name)}")
        for name in ("prbs_clock", "validation_hold", "max_epochs"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        for name in ("prbs_amplitude", "rich_amplitude", "validation_amplitude"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number of volts, got {value!r}")
        if "reference" in self.env_kwargs:
            raise ValueError("env_kwargs must not set 'reference': identification runs open loop")
        # Build a few samples of the rich signal now, so that a wrong name or parameter fails
        # here and not after the PRBS experiment.
        make_signal(
            self.rich_signal,
            16,
            dt=float(self.env_kwargs.get("dt", 1e-3)),
            rng=np.random.default_rng(0),
            amplitude=self.rich_amplitude,
            **self.rich_signal_params(),
        )

    def rich_signal_params(self) -> dict:
        """Parameters of the rich signal besides its amplitude."""
        if self.rich_params is not None:
            return dict(self.rich_params)
        if self.rich_signal == "sine":
            return {"frequency": 5.0}
        return dict(SIGNAL_DEFAULTS.get(self.rich_signal, {}))


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


def collect(env: gym.Env, u: np.ndarray, *, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Drive ``env`` open loop with ``u`` (V) from rest and return (u, y) sample-aligned.

    ``y[t]`` is the measured deflection (um) before ``u[t]`` is applied, so that
    ``y[t]`` depends on ``u[t-1], u[t-2], ...`` (the ARX convention). Truncation flags are
    ignored (a record may be longer than an episode); termination raises ValueError.
    """
    obs, _ = env.reset(seed=seed)
    y = np.empty(len(u))
    y[0] = obs[0]
    for t in range(len(u) - 1):
        obs, _, terminated, _, _ = env.step(np.array([u[t]], dtype=np.float32))
        if terminated:
            raise ValueError(
                f"the env terminated at sample {t + 1} (deflection limit); identify on an env "
                "without deflection_limit or with a smaller excitation"
            )
        y[t + 1] = obs[0]
    return np.clip(u, env.action_space.low[0], env.action_space.high[0]), y


def inverse_arx(
    arx: ARXModel, y: np.ndarray, *, regularization: float = 1e-3
) -> tuple[np.ndarray, str]:
    """Hidden signal z_hat (input units) from the output y by inverting the ARX model.

    With e_t = y_t - sum_i a_i y_{t-i} = sum_j b_j z_{t-j} (outputs and inputs before the record
    at rest), a minimum-phase B polynomial makes the paper's eq. 25 recursion stable:
    ``z_{t-1} = (e_t - sum_{j>=2} b_j z_{t-j}) / b_1``. Otherwise the recursion would blow up,
    and a Tikhonov-regularised least-squares deconvolution
    ``min ||B z - e||^2 + lambda (sum |b_j|)^2 ||z||^2`` is solved instead (sparse LSQR).

    Returns
    -------
    z_hat : ndarray
        Same length as y; the last sample, which no output observes, repeats the one before.
    method : str
        ``"eq25"`` or ``"regularized-deconvolution"``.
    """
    y = np.asarray(y, dtype=float)
    e = scipy.signal.lfilter(np.r_[1.0, -arx.a], [1.0], y)
    if arx.is_minimum_phase():
        z = scipy.signal.lfilter([1.0], arx.b, e[1:])
        return np.r_[z, z[-1]], "eq25"
    n = len(y)
    rows, cols, vals = [], [], []
    for j, bj in enumerate(arx.b, start=1):
        t = np.arange(j, n)
        rows.append(t)
        cols.append(t - j)
        vals.append(np.full(len(t), bj))
    matrix = scipy.sparse.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    damp = math.sqrt(regularization) * float(np.abs(arx.b).sum())
    z = scipy.sparse.linalg.lsqr(matrix, e, damp=damp, atol=1e-12, btol=1e-12)[0]
    return z, "regularized-deconvolution"


def _make_env(config: IdentificationConfig) -> gym.Env:
    return gym.make(
        "piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, **config.env_kwargs
    )


def _seeds(seed: int) -> dict[str, int]:
    names = ("prbs", "rich", "selection", "validation", "env", "nls")
    children = np.random.SeedSequence(seed).spawn(len(names))
    return {name: int(c.generate_state(1)[0]) for name, c in zip(names, children, strict=True)}


def _rand(config: IdentificationConfig, n: int, dt: float, seed: int) -> np.ndarray:
    return make_signal(
        "random",
        n,
        dt=dt,
        rng=np.random.default_rng(seed),
        amplitude=config.validation_amplitude,
        hold=config.validation_hold,
    )


def identify(
    env: gym.Env | None = None,
    *,
    config: IdentificationConfig | None = None,
    progress: Callable[[str], None] | None = None,
    **overrides: Any,
) -> IdentificationResult:
    """Identify the Hammerstein model of a bender (paper section 3.4, steps a-f).

    Parameters
    ----------
    env : gymnasium.Env, optional
        The bender to identify; default ``PiezoBender-v0`` with ``config.env_kwargs``.
    config : IdentificationConfig, optional
        All settings; keyword ``overrides`` build one when it is not given.
    progress : callable, optional
        Called with one line of text per step.

    Returns
    -------
    IdentificationResult
        ``.model`` (HammersteinModel), ``.report`` (metrics, estimates, timings), ``.data``.
    """
    if config is None:
        config = IdentificationConfig(**overrides)
    elif overrides:
        raise ValueError("pass either config or keyword overrides, not both")
    say = progress or (lambda _msg: None)
    env = env if env is not None else _make_env(config)
    model_env = env.unwrapped.model
    dt = model_env.dt
    u_max = float(env.action_space.high[0])
    seeds = _seeds(config.seed)
    timings: dict[str, float] = {}
    start_all = clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = round(now - clock, 3)
        clock = now

    # a) PRBS experiment.
    u_prbs = make_signal(
        "prbs",
        config.prbs_samples,
        dt=dt,
        rng=np.random.default_rng(seeds["prbs"]),
        amplitude=config.prbs_amplitude,
        clock_period=config.prbs_clock,
    )
    u_prbs, y_prbs = collect(env, u_prbs, seed=seeds["env"])
    say(
        f"a) PRBS +-{config.prbs_amplitude:g} V, {len(u_prbs)} samples: peak |y| = "
        f"{np.abs(y_prbs).max():.1f} um"
    )
    lap("a_prbs_experiment")

    # b) ARX part by the uniform-noise Bayesian estimator; order by held-out free-run fit.
    split = (3 * len(u_prbs)) // 4
    order_scores = {}
    for n in config.orders:
        candidate = fit_arx(
            u_prbs[:split],
            y_prbs[:split],
            na=n,
            nb=n,
            dt=dt,
            method="bayes-uniform",
            record_history=False,
        )
        sim = candidate.simulate(u_prbs)
        order_scores[n] = (
            float(fit_metrics(y_prbs[split:], sim[split:])["fit_percent"])
            if candidate.is_stable() and np.all(np.isfinite(sim))
            else -math.inf
        )
    # Near-ties go to the larger order: the higher bending modes it captures barely show in a
    # PRBS free run, but they shrink the equation-error bound r and so the noise of z_hat.
    best_fit = max(order_scores.values())
    order = max(n for n, fit in order_scores.items() if fit >= best_fit - ORDER_TIE_PERCENT)
    arx = fit_arx(u_prbs, y_prbs, na=order, nb=order, dt=dt, method="bayes-uniform")
    cheb = fit_arx(u_prbs, y_prbs, na=order, nb=order, dt=dt, method="chebyshev")
    lsq = fit_arx(u_prbs, y_prbs, na=order, nb=order, dt=dt, method="least-squares")
    say(
        f"b) ARX({order},{order}) by bayes-uniform (held-out PRBS fit "
        + ", ".join(f"n={k}: {v:.1f} %" for k, v in order_scores.items())
        + f"); r_hat = {arx.noise_bound:.2f} um, minimum-phase B: {arx.is_minimum_phase()}"
    )
    lap("b_arx_estimation")

    # c) rich experiment.
    u_rich = make_signal(
        config.rich_signal,
        config.rich_samples,
        dt=dt,
        rng=np.random.default_rng(seeds["rich"]),
        amplitude=config.rich_amplitude,
        **config.rich_signal_params(),
    )
    u_rich, y_rich = collect(env, u_rich, seed=seeds["env"] + 1)
    say(f"c) {config.rich_signal} {config.rich_amplitude:g} V, {len(u_rich)} samples")
    lap("c_rich_experiment")

    # d) hidden signal by the inverse ARX model, on the rich record and on the PRBS record,
    # where z = u by the scale convention: training on both pins the NLS's small-signal gain.
    z_hat, inversion = inverse_arx(arx, y_rich)
    z_prbs, _ = inverse_arx(arx, y_prbs)
    u_train, z_train = np.r_[u_prbs, u_rich], np.r_[z_prbs, z_hat]
    z_support = arx.noise_bound / abs(arx.b[0]) if arx.b[0] != 0 else math.inf
    say(f"d) z_hat by {inversion}; noise support +-r/b_1 = +-{z_support:.2f} V")
    lap("d_inverse_arx")

    # e) NLS: features chosen on a selection record (RAND, its own seed).
    u_sel, y_sel = collect(
        env,
        _rand(config, config.validation_samples // 2, dt, seeds["selection"]),
        seed=seeds["env"] + 2,
    )
    candidates = FEATURE_SETS if config.features == "auto" else (config.features,)
    fitted, selection_scores = {}, {}
    for features in candidates:
        nls = fit_nls(
            u_train,
            z_train,
            features=features,
            hidden=config.hidden,
            seed=seeds["nls"] % 2**31,
            max_epochs=config.max_epochs,
            u_range=(-u_max, u_max),
        )
        candidate = HammersteinModel(nls, arx)
        selection_scores[features] = float(
            fit_metrics(y_sel, candidate.simulate(u_sel))["fit_percent"]
        )
        fitted[features] = nls
        say(f"e) NLS with {features} features: selection fit {selection_scores[features]:.2f} %")
    best = max(selection_scores, key=selection_scores.get)
    model = HammersteinModel(
        fitted[best],
        arx,
        metadata={
            "bender": model_env.name,
            "dt": dt,
            "features": best,
            "seed": config.seed,
            "z_noise_support_V": z_support,
        },
    )
    lap("e_nls_training")
    z_small = model.nls_output(u_prbs)
    small_signal_gain = float(np.polyfit(u_prbs, z_small, 1)[0])
    say(f"   NLS small-signal gain on the PRBS record: {small_signal_gain:.3f} (1 by construction)")

    # f) validation on fresh RAND data, free run.
    u_val, y_val = collect(
        env,
        _rand(config, config.validation_samples, dt, seeds["validation"]),
        seed=seeds["env"] + 3,
    )
    y_sim = model.simulate(u_val)
    y_lin = arx.simulate(u_val)
    stroke = model_env.stroke_um
    hammer = fit_metrics(y_val, y_sim, stroke=stroke)
    linear = fit_metrics(y_val, y_lin, stroke=stroke)
    one_step = fit_metrics(y_val, model.predict(u_val, y_val), stroke=stroke)
    say(
        f"f) validation on RAND +-{config.validation_amplitude:g} V "
        f"(hold {config.validation_hold}): "
        f"Hammerstein fit {hammer['fit_percent']:.2f} %, RMSE {hammer['rmse']:.2f} um; "
        f"linear ARX fit {linear['fit_percent']:.2f} %, RMSE {linear['rmse']:.2f} um"
    )
    lap("f_validation")
    timings["total"] = round(time.perf_counter() - start_all, 3)

    report = {
        "config": _jsonable(asdict(config)),
        "environment": {
            "bender": model_env.name,
            "dt_s": dt,
            "hysteresis": model_env.hysteresis.name,
            "noise_bound_um": float(env.unwrapped.noise_bound),
            "stroke_um": stroke,
        },
        "arx": {
            "order": order,
            "order_scores_fit_percent": {str(k): v for k, v in order_scores.items()},
            "a": arx.a.tolist(),
            "b": arx.b.tolist(),
            "noise_bound_um": arx.noise_bound,
            "noise_bound_note": (
                "r_hat bounds the ARX equation error: unmodelled bending modes and the sensor "
                "noise together, so it measures model error more than sensor noise"
            ),
            "static_gain_um_per_V": arx.static_gain(),
            "poles": _complex_list(arx.poles()),
            "zeros": _complex_list(arx.zeros()),
            "minimum_phase": bool(arx.is_minimum_phase()),
            "chebyshev": {"theta": cheb.theta.tolist(), "noise_bound_um": cheb.noise_bound},
            "least_squares": {"theta": lsq.theta.tolist()},
        },
        "inversion": {"method": inversion, "z_noise_support_V": z_support},
        "nls": {
            "features": best,
            "small_signal_gain": small_signal_gain,
            "selection_fit_percent": selection_scores,
            "training": _jsonable(getattr(fitted[best], "training", {})),
        },
        "validation": {
            "signal": f"RAND +-{config.validation_amplitude:g} V, hold {config.validation_hold}",
            "samples": len(u_val),
            "hammerstein": hammer,
            "linear_arx": linear,
            "hammerstein_one_step": one_step,
            "rmse_ratio_hammerstein_to_arx": hammer["rmse"] / linear["rmse"],
        },
        "timings_s": timings,
    }
    data = {
        "arx_history": arx.history,
        "u_prbs": u_prbs,
        "y_prbs": y_prbs,
        "u_rich": u_rich,
        "y_rich": y_rich,
        "z_hat": z_hat,
        "z_model": model.nls_output(u_rich),
        "u_val": u_val,
        "y_val": y_val,
        "y_sim": y_sim,
        "y_lin": y_lin,
        "dt": dt,
        "noise_bound": arx.noise_bound,
        "prediction_val": model.predict(u_val, y_val),
    }
    return IdentificationResult(model=model, report=_jsonable(report), data=data)


def _complex_list(values: np.ndarray) -> list[list[float]]:
    return [[float(v.real), float(v.imag)] for v in np.asarray(values, dtype=complex)]


def _jsonable(obj: Any) -> Any:
    """Plain JSON types (numpy scalars and arrays converted, non-finite floats as None)."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        value = float(obj)
        return value if math.isfinite(value) else None
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (np.bool_,)):
        return bool(obj)
    return obj


def write_outputs(result: IdentificationResult, out: str | Path) -> list[Path]:
    """Write the model files, report.json, report.md and the figures into ``out``."""
    from identification.figures import write_figures
    from identification.report import markdown_report

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = [result.model.save(out / "model")]
    report_json = out / "report.json"
    report_json.write_text(json.dumps(result.report, indent=2), encoding="utf-8")
    figures = write_figures(result, out)
    report_md = out / "report.md"
    report_md.write_text(
        markdown_report(result.report, [p.name for p in figures]), encoding="utf-8"
    )
    return [*paths, report_json, report_md, *figures]
