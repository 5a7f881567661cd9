"""The two-step identification procedure of the paper (section 3.4, steps a-f).

:func:`identify` runs the steps in order, one function each:

a) :func:`excite_prbs`: excite the bender with a PRBS;
b) :func:`estimate_arx`: estimate the ARX part with the uniform-noise Bayesian estimator (order
   chosen by free-run fit on a held-out part of the PRBS record);
c) :func:`excite_rich`: excite it with a rich signal (SINE by default, as in the paper);
d) :func:`estimate_hidden_signal`: estimate the hidden signal z_t by inverting the ARX model
   (eq. 25), or by a regularised least-squares deconvolution when the estimated B polynomial is
   not minimum-phase (:mod:`identification.inversion`);
e) :func:`fit_nonlinearity`: fit the neural NLS to (u_t, z_hat_t), choosing its memory features
   on a separate selection record;
f) :func:`validate`: validate the Hammerstein model by free-run simulation on fresh RAND data.

:func:`collect` drives the environment open loop; its ``y[t]`` is the deflection before
``u[t]`` is applied (the alignment of :meth:`HammersteinModel.simulate`).

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
from numpy.typing import ArrayLike

import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from identification.arx import ARXModel
from identification.estimation import fit_arx
from identification.features import FEATURE_SETS
from identification.hammerstein import HammersteinModel
from identification.inversion import inverse_arx, inverse_error_bounds
from identification.metrics import fit_metrics
from identification.nls import fit_nls
from piezo_env.signals import SIGNAL_DEFAULTS, make_signal
from piezo_env.task import TaskConfig

__all__ = [
    "ArxEstimate",
    "HiddenSignal",
    "IdentificationConfig",
    "IdentificationResult",
    "NlsFit",
    "Validation",
    "collect",
    "estimate_arx",
    "estimate_hidden_signal",
    "excite_prbs",
    "excite_rich",
    "fit_nonlinearity",
    "identify",
    "inverse_arx",
    "validate",
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
            dt=float(self.env_kwargs.get("dt", TaskConfig().dt)),
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


def collect(
    env: gym.Env, u: ArrayLike, *, seed: int | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Drive ``env`` open loop with the voltage sequence ``u`` from rest; return ``(u, y)``.

    Alignment: ``y[t]`` is the measured deflection *before* ``u[t]`` is applied, i.e. the
    observation returned by ``reset`` (t = 0) or by the ``step`` that applied ``u[t-1]``. So
    ``y[t]`` depends on ``u[t-1], u[t-2], ...`` (the ARX convention, and the convention of
    :meth:`HammersteinModel.simulate`): compare ``model.simulate(u)`` with this ``y``. If you step
    the env yourself with ``u`` and collect the observations *returned by step*, you get
    ``y[1:]`` plus one more sample: a one-sample shift, which on white input costs almost all of
    the fit. ``u[-1]`` is never applied (no output of the record would see it).

    Parameters
    ----------
    env : gymnasium.Env
        A ``PiezoBender-v0`` environment (or wrapper) with deflection in um as ``obs[0]``; its
        ``reference`` should be None. Truncation flags are ignored (a record may be longer than
        an episode).
    u : array_like, shape (T,)
        Drive voltage, V.
    seed : int, optional
        Seed of ``env.reset`` (sensor noise and initial state draws).

    Returns
    -------
    u : numpy.ndarray, shape (T,)
        The voltage the env applied, V: ``u`` clipped to the action space, as the amplifier
        saturates.
    y : numpy.ndarray, shape (T,)
        Measured tip deflection, um, ``y[t]`` before ``u[t]``.

    Raises
    ------
    ValueError
        If ``u`` is not a finite 1-D sequence of at least 2 samples, or the env terminates
        (deflection limit).
    """
    u = np.asarray(u, dtype=float)
    if u.ndim != 1 or u.size < 2 or not np.all(np.isfinite(u)):
        raise ValueError(f"u must be a finite 1-D voltage sequence of >= 2 samples; got {u!r}")
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


# -- the steps of section 3.4 -----------------------------------------------------------------


@dataclass
class ArxEstimate:
    """Result of step b.

    Attributes
    ----------
    model : ARXModel
        The bayes-uniform estimate on the whole PRBS record (z in V, y in um).
    order : int
        Chosen order n (na = nb = n).
    order_scores : dict
        Held-out PRBS free-run fit (%) of every candidate order.
    chebyshev, least_squares : ARXModel
        The exact MAP and least-squares estimates of the same order (cross-checks).
    """

    model: ARXModel
    order: int
    order_scores: dict[int, float]
    chebyshev: ARXModel
    least_squares: ARXModel


@dataclass
class HiddenSignal:
    """Result of step d.

    Attributes
    ----------
    z_rich, z_prbs : numpy.ndarray
        Hidden signal z_hat (equivalent V) of the rich and of the PRBS record.
    method : str
        ``"eq25"`` or ``"regularized-deconvolution"``.
    error : dict
        :func:`inverse_error_bounds` of the ARX model: ``z_error_bound_V``,
        ``z_error_rms_V`` (equivalent V), ``inverse_gain_l1``, ``inverse_gain_l2`` (V/um).
    """

    z_rich: np.ndarray
    z_prbs: np.ndarray
    method: str
    error: dict[str, float | None]


@dataclass
class NlsFit:
    """Result of step e.

    Attributes
    ----------
    model : HammersteinModel
        The selected NLS in series with the ARX model.
    features : str
        Its feature set.
    selection_scores : dict
        Free-run fit (%) on the selection record of every candidate feature set.
    small_signal_gain : float
        Slope of z against u on the PRBS record (1 by the scale convention).
    """

    model: HammersteinModel
    features: str
    selection_scores: dict[str, float]
    small_signal_gain: float


@dataclass
class Validation:
    """Result of step f: free-run simulation on fresh RAND data.

    Attributes
    ----------
    u, y : numpy.ndarray
        Validation record (V, um), aligned as by :func:`collect`.
    y_sim, y_lin, y_pred : numpy.ndarray
        Hammerstein free run, linear ARX free run, Hammerstein one step ahead (um).
    metrics : dict
        ``hammerstein``, ``linear_arx``, ``hammerstein_one_step``: :func:`fit_metrics` dicts.
    """

    u: np.ndarray
    y: np.ndarray
    y_sim: np.ndarray
    y_lin: np.ndarray
    y_pred: np.ndarray
    metrics: dict[str, dict[str, float]]


def excite_prbs(
    env: gym.Env, config: IdentificationConfig, seeds: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Step a: drive the bender with a PRBS of level ``config.prbs_amplitude`` (V); (u, y)."""
    u = make_signal(
        "prbs",
        config.prbs_samples,
        dt=_dt(env),
        rng=np.random.default_rng(seeds["prbs"]),
        amplitude=config.prbs_amplitude,
        clock_period=config.prbs_clock,
    )
    return collect(env, u, seed=seeds["env"])


def estimate_arx(
    u: np.ndarray, y: np.ndarray, config: IdentificationConfig, *, dt: float
) -> ArxEstimate:
    """Step b: the ARX part by the uniform-noise Bayesian estimator, order by held-out fit.

    Every order of ``config.orders`` is fitted to the first three quarters of the PRBS record
    and scored by free-run fit (%) on the last quarter; near-ties (ORDER_TIE_PERCENT) go to the
    larger order: the higher bending modes it captures barely show in a PRBS free run, but they
    shrink the equation-error bound r and so the error of z_hat. The chosen order is then
    refitted on the whole record (with the Chebyshev and least-squares cross-checks).
    """
    split = (3 * len(u)) // 4
    scores = {}
    for n in config.orders:
        candidate = fit_arx(
            u[:split], y[:split], na=n, nb=n, dt=dt, method="bayes-uniform", record_history=False
        )
        sim = candidate.simulate(u)
        stable = candidate.is_stable() and np.all(np.isfinite(sim))
        scores[n] = (
            float(fit_metrics(y[split:], sim[split:])["fit_percent"]) if stable else -math.inf
        )
    best_fit = max(scores.values())
    order = max(n for n, fit in scores.items() if fit >= best_fit - ORDER_TIE_PERCENT)
    fits = {
        method: fit_arx(u, y, na=order, nb=order, dt=dt, method=method)
        for method in ("bayes-uniform", "chebyshev", "least-squares")
    }
    return ArxEstimate(
        fits["bayes-uniform"], order, scores, fits["chebyshev"], fits["least-squares"]
    )


def excite_rich(
    env: gym.Env, config: IdentificationConfig, seeds: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Step c: drive the bender with the rich signal of ``config`` (V); (u, y)."""
    u = make_signal(
        config.rich_signal,
        config.rich_samples,
        dt=_dt(env),
        rng=np.random.default_rng(seeds["rich"]),
        amplitude=config.rich_amplitude,
        **config.rich_signal_params(),
    )
    return collect(env, u, seed=seeds["env"] + 1)


def estimate_hidden_signal(arx: ARXModel, y_rich: np.ndarray, y_prbs: np.ndarray) -> HiddenSignal:
    """Step d: z_hat by the inverse ARX model (eq. 25) on the rich and the PRBS records.

    On the PRBS record z = u by the scale convention; training the NLS on both records pins its
    small-signal gain. The error of z_hat is the equation error filtered by 1/B, bounded by
    ``r ||1/B||_1`` (see :func:`identification.inversion.inverse_error_bounds`).
    """
    z_rich, method = inverse_arx(arx, y_rich)
    z_prbs, _ = inverse_arx(arx, y_prbs)
    return HiddenSignal(z_rich, z_prbs, method, inverse_error_bounds(arx))


def fit_nonlinearity(
    env: gym.Env,
    arx: ARXModel,
    u_train: np.ndarray,
    z_train: np.ndarray,
    config: IdentificationConfig,
    seeds: dict[str, int],
    *,
    say: Callable[[str], None] = lambda _msg: None,
) -> NlsFit:
    """Step e: fit the NLS to (u, z_hat); choose its features on a fresh RAND selection record.

    Every feature set of ``config.features`` ("auto": all of them) is trained and the Hammerstein
    model it makes with ``arx`` scored by free-run fit (%) on the selection record.
    """
    u_max = float(env.action_space.high[0])
    record = _rand(config, config.validation_samples // 2, _dt(env), seeds["selection"])
    u_sel, y_sel = collect(env, record, seed=seeds["env"] + 2)
    candidates = FEATURE_SETS if config.features == "auto" else (config.features,)
    fitted, scores = {}, {}
    for features in candidates:
        fitted[features] = fit_nls(
            u_train,
            z_train,
            features=features,
            hidden=config.hidden,
            seed=seeds["nls"] % 2**31,
            max_epochs=config.max_epochs,
            u_range=(-u_max, u_max),
        )
        y_hat = HammersteinModel(fitted[features], arx).simulate(u_sel)
        scores[features] = float(fit_metrics(y_sel, y_hat)["fit_percent"])
        say(f"e) NLS with {features} features: selection fit {scores[features]:.2f} %")
    best = max(scores, key=scores.get)
    model = HammersteinModel(fitted[best], arx)
    n_prbs = config.prbs_samples
    gain = float(np.polyfit(u_train[:n_prbs], model.nls_output(u_train[:n_prbs]), 1)[0])
    return NlsFit(model, best, scores, gain)


def validate(
    env: gym.Env, model: HammersteinModel, config: IdentificationConfig, seeds: dict[str, int]
) -> Validation:
    """Step f: free-run simulation of the model (and of its ARX part alone) on fresh RAND data."""
    record = _rand(config, config.validation_samples, _dt(env), seeds["validation"])
    u, y = collect(env, record, seed=seeds["env"] + 3)
    y_sim, y_lin, y_pred = model.simulate(u), model.arx.simulate(u), model.predict(u, y)
    stroke = env.unwrapped.model.stroke_um
    metrics = {
        "hammerstein": fit_metrics(y, y_sim, stroke=stroke),
        "linear_arx": fit_metrics(y, y_lin, stroke=stroke),
        "hammerstein_one_step": fit_metrics(y, y_pred, stroke=stroke),
    }
    return Validation(u, y, y_sim, y_lin, y_pred, metrics)


# -- the procedure ----------------------------------------------------------------------------


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
    seeds, dt, lap = _seeds(config.seed), _dt(env), _Stopwatch()

    u_prbs, y_prbs = excite_prbs(env, config, seeds)
    say(
        f"a) PRBS +-{config.prbs_amplitude:g} V, {len(u_prbs)} samples: peak |y| = "
        f"{np.abs(y_prbs).max():.1f} um"
    )
    lap("a_prbs_experiment")

    est = estimate_arx(u_prbs, y_prbs, config, dt=dt)
    arx = est.model
    say(
        f"b) ARX({est.order},{est.order}) by bayes-uniform (held-out PRBS fit "
        + ", ".join(f"n={k}: {v:.1f} %" for k, v in est.order_scores.items())
        + f"); r_hat = {arx.noise_bound:.2f} um, minimum-phase B: {arx.is_minimum_phase()}"
    )
    lap("b_arx_estimation")

    u_rich, y_rich = excite_rich(env, config, seeds)
    say(f"c) {config.rich_signal} {config.rich_amplitude:g} V, {len(u_rich)} samples")
    lap("c_rich_experiment")

    hidden = estimate_hidden_signal(arx, y_rich, y_prbs)
    say(
        f"d) z_hat by {hidden.method}; error from r_hat: worst case "
        f"{_volts(hidden.error['z_error_bound_V'])}, RMS {_volts(hidden.error['z_error_rms_V'])}"
    )
    lap("d_inverse_arx")

    u_train, z_train = np.r_[u_prbs, u_rich], np.r_[hidden.z_prbs, hidden.z_rich]
    nls = fit_nonlinearity(env, arx, u_train, z_train, config, seeds, say=say)
    model = nls.model
    model.metadata.update(_model_metadata(env, config, nls.features, hidden))
    say(
        f"   NLS small-signal gain on the PRBS record: {nls.small_signal_gain:.3f} "
        "(1 by construction)"
    )
    lap("e_nls_training")

    val = validate(env, model, config, seeds)
    hammer, linear = val.metrics["hammerstein"], val.metrics["linear_arx"]
    say(
        f"f) validation on RAND +-{config.validation_amplitude:g} V "
        f"(hold {config.validation_hold}): Hammerstein fit {hammer['fit_percent']:.2f} %, "
        f"RMSE {hammer['rmse']:.2f} um; linear ARX fit {linear['fit_percent']:.2f} %, "
        f"RMSE {linear['rmse']:.2f} um"
    )
    lap("f_validation")

    report = _report(env, config, est, hidden, nls, val, lap.timings())
    data = _figure_data(u_prbs, y_prbs, u_rich, y_rich, hidden, model, val)
    return IdentificationResult(model=model, report=_jsonable(report), data=data)


# -- helpers ----------------------------------------------------------------------------------


def _make_env(config: IdentificationConfig) -> gym.Env:
    return gym.make(
        "piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, **config.env_kwargs
    )


def _dt(env: gym.Env) -> float:
    return float(env.unwrapped.model.dt)


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


def _volts(value: float | None) -> str:
    return "n/a (not eq. 25)" if value is None else f"{value:.2f} V"


class _Stopwatch:
    """Wall time per step (s): ``lap(name)`` closes a step, ``timings()`` adds the total."""

    def __init__(self) -> None:
        self._start = self._last = time.perf_counter()
        self._laps: dict[str, float] = {}

    def __call__(self, name: str) -> None:
        now = time.perf_counter()
        self._laps[name] = round(now - self._last, 3)
        self._last = now

    def timings(self) -> dict[str, float]:
        return {**self._laps, "total": round(time.perf_counter() - self._start, 3)}


def _model_metadata(
    env: gym.Env, config: IdentificationConfig, features: str, hidden: HiddenSignal
) -> dict[str, Any]:
    """What the model files record about their origin (JSON-safe)."""
    return {
        "bender": env.unwrapped.model.name,
        "dt": _dt(env),
        "features": features,
        "seed": config.seed,
        "z_error_bound_V": hidden.error["z_error_bound_V"],
        "z_error_rms_V": hidden.error["z_error_rms_V"],
    }


def _report(
    env: gym.Env,
    config: IdentificationConfig,
    est: ArxEstimate,
    hidden: HiddenSignal,
    nls: NlsFit,
    val: Validation,
    timings: dict[str, float],
) -> dict[str, Any]:
    """The JSON report of a run (keys read by the CLI, the benchmarks and report.md)."""
    plant, arx = env.unwrapped.model, est.model
    return {
        "config": _jsonable(asdict(config)),
        "environment": {
            "bender": plant.name,
            "dt_s": plant.dt,
            "hysteresis": plant.hysteresis.name,
            "noise_bound_um": float(env.unwrapped.noise_bound),
            "stroke_um": plant.stroke_um,
        },
        "arx": {
            "order": est.order,
            "order_scores_fit_percent": {str(k): v for k, v in est.order_scores.items()},
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
            "chebyshev": {
                "theta": est.chebyshev.theta.tolist(),
                "noise_bound_um": est.chebyshev.noise_bound,
            },
            "least_squares": {"theta": est.least_squares.theta.tolist()},
        },
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
            "small_signal_gain": nls.small_signal_gain,
            "selection_fit_percent": nls.selection_scores,
            "training": _jsonable(getattr(nls.model.nls, "training", {})),
        },
        "validation": {
            "signal": f"RAND +-{config.validation_amplitude:g} V, hold {config.validation_hold}",
            "samples": len(val.u),
            **val.metrics,
            "rmse_ratio_hammerstein_to_arx": (
                val.metrics["hammerstein"]["rmse"] / val.metrics["linear_arx"]["rmse"]
            ),
        },
        "timings_s": timings,
    }


def _figure_data(
    u_prbs: np.ndarray,
    y_prbs: np.ndarray,
    u_rich: np.ndarray,
    y_rich: np.ndarray,
    hidden: HiddenSignal,
    model: HammersteinModel,
    val: Validation,
) -> dict[str, Any]:
    """The records of a run, for the figures (V, equivalent V, um; ``dt`` in s)."""
    return {
        "arx_history": model.arx.history,
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
        "noise_bound": model.arx.noise_bound,
        "z_error_bound": hidden.error["z_error_bound_V"],
        "prediction_val": val.y_pred,
    }


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
