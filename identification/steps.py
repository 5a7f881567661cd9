"""The steps a-f of the paper's procedure (section 3.4), one function each, and their results.

Each step takes what the earlier steps returned, the measured records and the settings. The
records come from a bender, simulated or real: :func:`identification.experiment.measure`
drives the environment with the inputs of :func:`identification.experiment.experiment_inputs`
(:func:`excite_prbs` and :func:`excite_rich` measure one record each), and
:mod:`identification.records` reads them from files.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import gymnasium as gym
import numpy as np

from identification.arx import ARXModel
from identification.bayes_uniform import BayesUniformEstimator
from identification.config import ORDER_TIE_PERCENT, RADIUS_ITERATIONS, IdentificationConfig
from identification.estimation import bayes_uniform_estimator, fit_arx
from identification.experiment import (
    collect,
    experiment_inputs,
    rand_signal,
    sample_time,
    step_seeds,
)
from identification.features import FEATURE_SETS, PastInputFeatures, PlayFeatures
from identification.hammerstein import HammersteinModel
from identification.inversion import inverse_arx, inverse_error_bounds
from identification.metrics import fit_metrics
from identification.nls import NLS, fit_nls
from identification.nls.output_error import (
    NlsOutputErrorFit,
    move_gain,
    rate_is_determined,
    refine_nls_output_error,
)
from identification.refine import OutputErrorFit, refine_output_error
from identification.runner import StepRunner

__all__ = [
    "ArxEstimate",
    "HiddenSignal",
    "LinearRefinement",
    "NlsFit",
    "NlsRefinement",
    "Validation",
    "estimate_arx",
    "estimate_hidden_signal",
    "excite_prbs",
    "excite_rich",
    "fit_nonlinearity",
    "rand_signal",
    "refine_and_choose",
    "refine_linear_part",
    "refine_nonlinearity",
    "step_seeds",
    "validate",
]


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
    candidates : dict
        The bayes-uniform estimate of every candidate order on the first three quarters of
        the record (the starting points of step b').
    """

    model: ARXModel
    order: int
    order_scores: dict[int, float]
    chebyshev: ARXModel
    least_squares: ARXModel
    candidates: dict[int, ARXModel] = field(default_factory=dict)


@dataclass
class LinearRefinement:
    """Result of step b': the output-error refinement of the linear part.

    Attributes
    ----------
    model : ARXModel
        The refined linear part on the whole PRBS record (method ``"output-error"``).
    order : int
        Its order n (na = nb = n).
    fit : OutputErrorFit
        The refinement on the whole record (output-error RMS and bound, solver facts).
    order_scores : dict
        Held-out output-error RMS (um) of every candidate order, refined on the first three
        quarters of the record and run free over the last quarter.
    description_length : dict
        Minimum description length of every candidate order on the estimation part (the
        smallest wins).
    unrefined_output_error_rms : float or None
        Free-run RMS error (um) of the step b estimate on the whole PRBS record, for comparison
        with ``fit.output_error_rms``; None when that estimate is unstable (it has no free run;
        step b' refines every candidate order, and reaches a stable model from the others).
    """

    model: ARXModel
    order: int
    fit: OutputErrorFit
    order_scores: dict[int, float]
    description_length: dict[int, float]
    unrefined_output_error_rms: float | None


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
    selection_record : tuple of numpy.ndarray
        The selection record (u V, y um), held out from the training; step e' is judged on it.
    selection_lead_in : int
        Samples at the start of the selection record that the model runs over but that are
        not scored (the estimation part before a split record's held-out part: the model
        starts from rest where the record starts).
    candidates : dict
        The trained network (:class:`identification.nls.NLS`) of every candidate feature set,
        for step e' to refine a rival beside the chosen one (:func:`refine_and_choose`).
    """

    model: HammersteinModel
    features: str
    selection_scores: dict[str, float]
    small_signal_gain: float
    selection_record: tuple[np.ndarray, np.ndarray]
    selection_lead_in: int = 0
    candidates: dict = field(default_factory=dict)

    def rival(self, features: str, u_prbs: np.ndarray) -> NlsFit:
        """Step e's fit had it chosen ``features`` (same linear part and selection record;
        ``u_prbs`` V, the PRBS record, measures its small-signal gain)."""
        model = HammersteinModel(self.candidates[features], self.model.arx)
        gain = _small_signal_gain(model, u_prbs)
        return replace(self, model=model, features=features, small_signal_gain=gain)


@dataclass
class NlsRefinement:
    """Result of step e': the output-error refinement of the whole Hammerstein model.

    Attributes
    ----------
    model : HammersteinModel
        The refined model (network and linear part), or step e's unchanged when the refinement
        was refused (``accepted`` False, ``refusal`` says why).
    accepted : bool
        Whether the refined model was kept.
    refusal : str or None
        Why it was not: no lower error on the held-out selection record, a refined network
        without a positive small-signal gain, or an unstable step e linear part.
    note : str or None
        Why the joint stage's linear part was dropped for the network-only stage (it lost
        stability or minimum phase); None when it was kept.
    training_rms_um : dict
        Free-run RMS output error on the training records (PRBS and rich), um, ``before`` and
        ``after`` (empty when the refinement did not run).
    selection_rms_um : dict
        The same on the held-out selection record, um: the acceptance test (``after`` absent
        when there was no refined model to score).
    stages : tuple of dict
        L-BFGS ``iterations``, ``evaluations``, ``stopped`` (``"tolerance"``, ``"converged"``
        or ``"cap"``) and ``capped`` of each stage.
    small_signal_gain : float
        Slope of the kept model's z against u on the PRBS record (1 after :func:`move_gain`).
    wall_time_s : float
        Time of the refinement, s.
    feature_choice : dict or None
        When step e' also refined a rival feature set (:func:`refine_and_choose`): step e's
        choice, the held-out RMS error (um) each reached, which was kept and why; or why no
        rival was refined. None when the question did not arise (features fixed, grid radii,
        or play already chosen).
    rate_choice : dict or None
        With ``rate="auto"``: whether the records determine a rate constant
        (:func:`identification.nls.output_error.rate_is_determined`; if not, no rate-dependent
        model is fitted), and if they do the held-out RMS errors (um) of the rate-independent
        and the rate-dependent model, the threshold (um^2, :func:`rate_threshold`), the time of
        both refinements (s); and whether the rate-dependent one was kept. None otherwise.
    """

    model: HammersteinModel
    accepted: bool
    refusal: str | None
    note: str | None
    training_rms_um: dict[str, float]
    selection_rms_um: dict[str, float]
    stages: tuple[dict, ...]
    small_signal_gain: float
    wall_time_s: float
    rate_choice: dict | None = None
    feature_choice: dict | None = None

    @property
    def iterations(self) -> int:
        """L-BFGS iterations over both stages."""
        return sum(stage["iterations"] for stage in self.stages)

    def record(self) -> dict:
        """JSON-safe summary (for the report and the refined network's training record)."""
        return {
            "method": "free-run output error: (with learned play radii) the radii and the "
            "network, then the network, then network and linear part, L-BFGS from steps e and "
            "b'; the gain then moved to keep the network's unit small-signal gain",
            "accepted": self.accepted,
            "refusal": self.refusal,
            "note": self.note,
            "training_rms_um": dict(self.training_rms_um),
            "selection_rms_um": dict(self.selection_rms_um),
            "stages": [dict(stage) for stage in self.stages],
            "small_signal_gain": self.small_signal_gain,
            "wall_time_s": self.wall_time_s,
            **({"rate_choice": dict(self.rate_choice)} if self.rate_choice else {}),
            **({"feature_choice": dict(self.feature_choice)} if self.feature_choice else {}),
        }


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
        ``hammerstein``, ``linear_arx``, ``hammerstein_one_step``: :func:`fit_metrics` dicts;
        with an unrefined model given, also ``linear_arx_unrefined`` (its free run); with
        step e's model given, ``hammerstein_unrefined_nls`` and, when step e' changed the
        linear part, ``linear_arx_before_e2`` (step e's linear part alone).
    equation_error_bound_um : float
        r_hat of the model's linear part: its largest equation error A(q) y - B(q) z on the
        records it was fitted on (um), the bound its one-step-ahead residuals are drawn
        against. Step b's r_hat is of step b's estimate, before steps b' and e' changed it.
    """

    u: np.ndarray
    y: np.ndarray
    y_sim: np.ndarray
    y_lin: np.ndarray
    y_pred: np.ndarray
    metrics: dict[str, dict[str, float]]
    equation_error_bound_um: float


def excite_prbs(
    env: gym.Env, config: IdentificationConfig, seeds: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Step a: drive the bender with a PRBS of level ``config.prbs_amplitude`` (V); (u, y)."""
    u = experiment_inputs(config, sample_time(env), seeds)["prbs"]
    return collect(env, u, seed=seeds["env"])


def estimate_arx(
    u: np.ndarray,
    y: np.ndarray,
    config: IdentificationConfig,
    *,
    dt: float,
    runner: StepRunner | None = None,
) -> ArxEstimate:
    """Step b: the ARX part by the uniform-noise Bayesian estimator, order by held-out fit.

    Every order of ``config.orders`` is fitted to the first three quarters of the PRBS record
    and scored by free-run fit (%) on the last quarter; near-ties (ORDER_TIE_PERCENT) go to the
    larger order: the higher bending modes it captures barely show in a PRBS free run, but they
    shrink the equation-error bound r and so the error of z_hat. The chosen order's estimator
    then goes on over the last quarter: the estimator is recursive, so that is its estimate on
    the whole record (to the bit where its blocks align, to rounding otherwise), for the
    quarter's cost. The Chebyshev and least-squares cross-checks are fitted to the whole record.

    ``runner`` (:mod:`identification.runner`; default: all here) may fit the orders beside each
    other: the helper takes them from the smallest, this process from the largest (the
    slowest), the same estimates to the bit; the helper's warm-up for step e is queued behind
    them (:meth:`~identification.runner.StepRunner.warm_up_helper`).
    """
    runner = StepRunner() if runner is None else runner
    split = (3 * len(u)) // 4
    pending = {n: runner.beside(_fit_order, u, y, n, split, dt) for n in config.orders}
    runner.warm_up_helper()
    runner.take_back_from_last([pending[n] for n in config.orders])
    estimators = {n: pending[n].result() for n in config.orders}
    candidates = {n: estimator.model() for n, estimator in estimators.items()}
    scores = {n: _held_out_fit(candidate, u, y, split) for n, candidate in candidates.items()}
    best_fit = max(scores.values())
    order = max(n for n, fit in scores.items() if fit >= best_fit - ORDER_TIE_PERCENT)
    estimators[order].update_many(u[split:], y[split:])
    fits = {"bayes-uniform": estimators[order].model()}
    fits.update(
        (method, fit_arx(u, y, na=order, nb=order, dt=dt, method=method))
        for method in ("chebyshev", "least-squares")
    )
    return ArxEstimate(
        fits["bayes-uniform"],
        order,
        scores,
        fits["chebyshev"],
        fits["least-squares"],
        candidates,
    )


def _fit_order(
    u: np.ndarray, y: np.ndarray, n: int, split: int, dt: float
) -> BayesUniformEstimator:
    """Step b for one order: the bayes-uniform estimator of ARX(n, n) after the first
    ``split`` samples, its history recorded (the figure of the chosen order's whole-record
    estimate shows it)."""
    return bayes_uniform_estimator(u[:split], y[:split], na=n, nb=n, dt=dt)


def _held_out_fit(candidate: ARXModel, u: np.ndarray, y: np.ndarray, split: int) -> float:
    """Free-run fit (%) of ``candidate`` on the samples from ``split`` on (-inf: unstable)."""
    sim = candidate.simulate(u)
    if not (candidate.is_stable() and np.all(np.isfinite(sim))):
        return -math.inf
    return float(fit_metrics(y[split:], sim[split:])["fit_percent"])


def refine_linear_part(est: ArxEstimate, u: np.ndarray, y: np.ndarray) -> LinearRefinement:
    """Step b': output-error refinement of the linear part, order by description length.

    The equation-error ARX estimate of step b is biased when the noise is on the measured
    output, as the sensor's is, and the bias lands in the zeros (:mod:`identification.refine`).
    Every candidate of step b (fitted to the first three quarters of the PRBS record) is refined
    there by minimising its free-run error, and so is the refined model of the next lower order
    taken as a model of this order (an extra pole and zero at the origin): the better of the
    two is kept, so that a local minimum of the output-error cost (a pole pushed against the
    unit circle, cancelled by a zero) does not decide the order, and the refined cost never
    rises with the order. The order minimising Rissanen's minimum description length on the
    estimation part, ``N ln V + d ln N`` (V the free-run mean square error, d = 2n parameters,
    N samples; Ljung 1999, sec. 16.4), wins: an extra order must cut V by about ln N / N per
    parameter, so an order that only fits noise, with the spurious pole-zero pairs the
    controllers would invert, loses, while the second bending mode (a few percent of V over
    thousands of samples) wins, unless the next smaller order predicts the last quarter,
    unseen by the fits, at least as well (then that order, and so on down): near the MDL's
    threshold an extra pole-zero pair must also pay on new data. The free-run RMS error on the
    last quarter is reported for every order. The winner is then refined on the whole
    record, starting from its held-out refinement. Under the PRBS the nonlinearity is affine
    (Bai 2004), so ``u`` is the linear part's input up to the scale fixed in step b.
    """
    split = (3 * len(u)) // 4
    refined, errors, estimation = {}, {}, {}
    previous = None
    for n in sorted(est.candidates):
        starts = [est.candidates[n]]
        if previous is not None:  # the lower order's optimum, as an order-n model
            starts.append(ARXModel(np.r_[previous.a, 0.0], np.r_[previous.b, 0.0], dt=previous.dt))
        fits = []
        for start in starts:
            try:
                fits.append(refine_output_error(start, u[:split], y[:split]))
            except ValueError:
                continue  # an unstable start or end point
        if not fits:
            continue
        fit = min(fits, key=lambda f: f.output_error_rms)
        previous = refined[n] = fit.model
        estimation[n] = fit.output_error_rms**2
        errors[n] = (y[split:] - fit.model.simulate(u)[split:]) ** 2
    if not errors:
        raise ValueError(
            "no candidate ARX order gave a stable output-error model; check the PRBS record "
            "(amplitude, length) or the candidate orders"
        )
    mdl = {n: split * math.log(v) + 2 * n * math.log(split) for n, v in estimation.items()}
    order = min(mdl, key=mdl.get)
    while order - 1 in errors and errors[order - 1].mean() <= errors[order].mean():
        order -= 1  # the larger order must also predict unseen data better
    scores = {n: float(np.sqrt(e.mean())) for n, e in errors.items()}
    fit = refine_output_error(refined[order], u, y)
    unrefined = None
    if est.model.is_stable():
        unrefined = float(np.sqrt(np.mean((y - est.model.simulate(u)) ** 2)))
    return LinearRefinement(fit.model, order, fit, scores, mdl, unrefined)


def excite_rich(
    env: gym.Env, config: IdentificationConfig, seeds: dict[str, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Step c: drive the bender with the rich signal of ``config`` (V); (u, y)."""
    u = experiment_inputs(config, sample_time(env), seeds)["rich"]
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
    arx: ARXModel,
    u_train: np.ndarray,
    z_train: np.ndarray,
    selection: tuple[np.ndarray, np.ndarray],
    config: IdentificationConfig,
    seeds: dict[str, int],
    *,
    u_max: float,
    u_prbs: np.ndarray,
    lead_in: int = 0,
    say: Callable[[str], None] = lambda _msg: None,
    runner: StepRunner | None = None,
) -> NlsFit:
    """Step e: fit the NLS to (u, z_hat); choose its features on the held-out selection record.

    Every feature set of ``config.features`` ("auto": all of them) is trained and the Hammerstein
    model it makes with ``arx`` scored by free-run fit (%) on ``selection`` (u V, y um).
    ``u_max`` (V) bounds the drive range the network is scaled to; ``u_prbs`` (V), the PRBS
    record, measures its small-signal gain; the first ``lead_in`` samples of ``selection`` are
    run over but not scored. ``runner`` (:mod:`identification.runner`; default: all here) may
    train the candidates beside each other: the same networks to the bit.
    """
    u_sel, y_sel = selection
    runner = StepRunner() if runner is None else runner
    candidates = FEATURE_SETS if config.features == "auto" else (config.features,)
    data = (u_train, z_train, arx, selection, config, seeds["nls"] % 2**31, u_max, lead_in)
    # With a helper every candidate goes to it, in order, while this process imports torch and
    # makes its first training (warm_up; step e' needs both here), then takes back from the
    # last the candidates the helper has not started: the helper is busy from the start, and
    # neither process waits for the other longer than one candidate. With one job all are
    # computed here, in order.
    pending = {f: runner.beside(_fit_candidate, f, *data) for f in candidates}
    if runner.parallel:
        warm_up()
    runner.take_back_from_last([pending[f] for f in candidates])
    fitted, scores = {}, {}
    for features in candidates:
        fitted[features], scores[features] = pending[features].result()
        say(f"e) NLS with {features} features: selection fit {scores[features]:.2f} %")
    best = max(scores, key=scores.get)
    model = HammersteinModel(fitted[best], arx)
    gain = _small_signal_gain(model, u_prbs)
    return NlsFit(model, best, scores, gain, (u_sel, y_sel), lead_in, fitted)


def warm_up() -> None:
    """What a helper process of :mod:`identification.runner` runs first: this module's imports
    (torch among them, through the training and refinement modules), then one epoch of a small
    network on a short ramp, since a process's first training pays about a second for torch's
    first autograd and optimiser calls (measured on the PL140's step e)."""
    u = np.linspace(-1.0, 1.0, 200)
    fit_nls(u, u, features="past-inputs", hidden=(8,), max_epochs=1, u_range=(-1.0, 1.0))


def _fit_candidate(
    features: str,
    u_train: np.ndarray,
    z_train: np.ndarray,
    arx: ARXModel,
    selection: tuple[np.ndarray, np.ndarray],
    config: IdentificationConfig,
    seed: int,
    u_max: float,
    lead_in: int,
) -> tuple[NLS, float]:
    """Step e for one feature set: the network fitted to (u, z_hat), and the free-run fit (%)
    on the selection record (u V, y um; its first ``lead_in`` samples not scored) of the
    Hammerstein model it makes with ``arx``."""
    nls = fit_nls(
        u_train,
        z_train,
        features=features,
        hidden=config.hidden,
        n_bouc_wen=config.n_bouc_wen,
        seed=seed,
        max_epochs=config.max_epochs,
        u_range=(-u_max, u_max),
    )
    u_sel, y_sel = selection
    y_hat = HammersteinModel(nls, arx).simulate(u_sel)
    return nls, float(fit_metrics(y_sel[lead_in:], y_hat[lead_in:])["fit_percent"])


def refine_and_choose(
    nls: NlsFit,
    records: list[tuple[np.ndarray, np.ndarray]],
    config: IdentificationConfig,
    *,
    sensor_noise_bound: float | None,
    runner: StepRunner | None = None,
) -> tuple[NlsFit, NlsRefinement]:
    """Step e' on step e's choice and, where step e could not judge it, on the play features
    too; the feature set is then chosen on the held-out selection record after step e'.

    Step e scores every feature set with its play radii still on the grid, and step e' learns
    them (and a rate constant): a play model can lose step e and win after step e', as on the
    bench plant, whose rate-dependent plays the grid's radii without a rate draw badly
    (``benchmarks/results/rate_aware_identification.md`` gives the features chosen and the
    validation fit per seed). So, with learned radii, step e' also refines step e's play
    network when step e chose another set, and keeps whichever reaches the lower free-run RMS
    error on the selection record (held out from the training of both). Only play gains
    parameters in step e' that step e does not fit; every other set is judged fairly by step e.

    The rival is not refined when step e's choice, refined, already sits at the sensor's noise
    floor: its held-out mean squared error exceeds the noise's, sigma^2 = (bound^2)/3 for
    uniform noise of half-width ``sensor_noise_bound`` (um), by no more than
    :func:`rate_threshold`, the lowering no rival could show beyond noise. With no known
    sensor bound (measured records without one) the rival is always refined.

    Returns
    -------
    (NlsFit, NlsRefinement)
        Step e's fit of the kept feature set and its refinement, whose ``feature_choice``
        records the comparison (None when the question did not arise).
    """
    runner = StepRunner() if runner is None else runner
    if not (
        config.play_radii == "learned" and "play" in nls.candidates and nls.features != "play"
    ):
        return nls, refine_nonlinearity(nls, records, config, runner=runner)
    # Without a sensor bound the rival is always refined: it starts beside the choice's
    # refinement. With one it waits for the noise-floor test, which often finds it unneeded
    # (the nominal PL140): refined beside the choice and then withdrawn, it slows the choice's
    # refinement more than it could save (``design_measurements.md``, identification.runner).
    # Refined here, the rival hands its own rate-dependent refinement to the helper, which the
    # choice's refinement left idle (step e chose a set without a rate variant); refined on the
    # helper, it computes that there.
    rival_pending = (
        runner.beside(_refine_rival, nls, records, config)
        if sensor_noise_bound is None
        else runner.here(_refine_rival, nls, records, config, runner=runner)
    )
    refinement = refine_nonlinearity(nls, records, config, runner=runner)
    held_out = _kept_rms(refinement)
    n = nls.selection_record[0].size - nls.selection_lead_in
    choice: dict = {"step_e": nls.features, "held_out_rms_um": {nls.features: held_out}}
    if sensor_noise_bound is not None:
        excess = held_out**2 - sensor_noise_bound**2 / 3.0
        threshold = rate_threshold(sensor_noise_bound, held_out, n)
        choice.update(excess_over_noise_um2=excess, threshold_um2=threshold)
        if excess <= threshold:
            choice.update(
                kept=nls.features,
                why="step e's choice is at the sensor's noise floor on the held-out record: "
                "no rival can do measurably better, so play was not refined",
            )
            rival_pending.withdraw()
            return nls, replace(refinement, feature_choice=choice)
    rival, rival_refinement = rival_pending.result()
    choice["held_out_rms_um"]["play"] = _kept_rms(rival_refinement)
    choice["play_wall_time_s"] = rival_refinement.wall_time_s
    if choice["held_out_rms_um"]["play"] < held_out:
        nls, refinement = rival, rival_refinement
    choice.update(
        kept=nls.features,
        why="the lower free-run RMS error on the held-out selection record after step e'",
    )
    return nls, replace(refinement, feature_choice=choice)


def _refine_rival(
    nls: NlsFit,
    records: list[tuple[np.ndarray, np.ndarray]],
    config: IdentificationConfig,
    runner: StepRunner | None = None,
) -> tuple[NlsFit, NlsRefinement]:
    """Step e's play network as the rival of its choice, and its step e' refinement (whose
    rate-dependent refinement ``runner`` may compute beside it)."""
    rival = nls.rival("play", records[0][0])
    return rival, refine_nonlinearity(rival, records, config, runner=runner)


def _kept_rms(refinement: NlsRefinement) -> float:
    """Held-out RMS error (um) of the model a refinement kept."""
    selection = refinement.selection_rms_um
    return selection["after"] if refinement.accepted else selection["before"]


def refine_nonlinearity(
    nls: NlsFit,
    records: list[tuple[np.ndarray, np.ndarray]],
    config: IdentificationConfig,
    *,
    runner: StepRunner | None = None,
) -> NlsRefinement:
    """Step e': refine the network, then the network and the linear part together, on the
    free-run output error of ``records`` (the PRBS record first, then the rich record; u V,
    y um), then move the gain so that the network keeps unit small-signal gain on the PRBS
    record (:mod:`identification.nls.output_error`).

    The refined model is kept only if its free-run error on the held-out selection record is
    lower than step e's; otherwise step e's model stays and ``refusal`` says why (so it does
    when step e's linear part is unstable and has no free run to refine). A joint stage that
    ends at an unstable or no longer minimum-phase linear part (the inverse of step d and the
    feedforward invert B) is dropped for the network-only stage, and ``note`` says so.

    With ``rate="auto"`` and learned play radii, the rate-dependent refinement starts beside
    the rate-independent one (``runner``, :mod:`identification.runner`), and is withdrawn if
    the learned radii leave the rate undetermined.
    """
    runner = StepRunner() if runner is None else runner
    start = nls.model
    selection = {"before": _selection_rms(start, nls)}
    if not start.arx.is_stable():
        return NlsRefinement(
            model=start,
            accepted=False,
            refusal="step e's linear part is unstable: it has no free run to refine",
            note=None,
            training_rms_um={},
            selection_rms_um=selection,
            stages=(),
            small_signal_gain=_small_signal_gain(start, records[0][0]),
            wall_time_s=0.0,
        )
    # The radius stage (which the rate question needs) runs on play features with learned radii.
    learns_radii = config.play_radii == "learned" and isinstance(
        start.nls.feature_map, PlayFeatures
    )
    rate_pending = (
        runner.beside(_refine, start, records, config, learn_rate=True)
        if config.rate == "auto" and learns_radii
        else None
    )
    fit, refined, gain = _refine(start, records, config, learn_rate=config.rate == "on")
    rate_choice = None
    if rate_pending is not None and refined is not None:
        rate_choice = {
            "determined": rate_is_determined(fit.stages[0]["radii_after"], records, start.arx.dt)
        }
        if rate_choice["determined"]:
            rate_fit, rate_refined, rate_gain = rate_pending.result()
            rate_choice.update(_rate_choice(refined, rate_refined, nls))
            rate_choice["wall_time_s"] = fit.wall_time_s + rate_fit.wall_time_s
            if rate_choice["kept"]:
                fit, refined, gain = rate_fit, rate_refined, rate_gain
        else:
            rate_choice["kept"] = False
    if rate_pending is not None:  # not needed (a no-op once its result was taken)
        rate_pending.withdraw()
    model, refusal = start, None
    if refined is None:
        refusal = f"the refined network's small-signal gain is {gain:.3g}, not positive"
    else:
        selection["after"] = _selection_rms(refined, nls)
        if selection["after"] < selection["before"]:
            model = refined
        else:
            refusal = "no lower free-run error on the held-out selection record"
    result = NlsRefinement(
        model=model,
        accepted=refusal is None,
        refusal=refusal,
        note=fit.linear_note,
        training_rms_um={"before": fit.rms_before, "after": fit.rms_after},
        selection_rms_um=selection,
        stages=fit.stages,
        small_signal_gain=_small_signal_gain(model, records[0][0]),
        wall_time_s=fit.wall_time_s,
        rate_choice=rate_choice,
    )
    if result.accepted:  # the saved network's training record tells what was done to it
        model.nls.training["output_error_refinement"] = result.record()
    return result


PAST_INPUTS_HOLD = (
    "past-input features make the network a filter of the input: refined together, it and the "
    "linear part trade dynamics (their split is not identifiable, the static gain included), "
    "so the linear part is held"
)
"""Why step e' holds the linear part under past-input features (its ``note``): a Hammerstein
model's static nonlinearity fixes the split of the gain and of the dynamics between its blocks;
a network of past inputs does not, and a z no longer in equivalent volts gives the controllers
wrong bounds on it (the case that showed it: ``benchmarks/results/design_measurements.md``)."""


def _refine(
    start: HammersteinModel,
    records: list[tuple[np.ndarray, np.ndarray]],
    config: IdentificationConfig,
    *,
    learn_rate: bool,
) -> tuple[NlsOutputErrorFit, HammersteinModel | None, float]:
    """Step e''s refinement of ``start`` on ``records``: the fit, the refined model with the
    gain moved to the linear part (None when its small-signal gain is not positive) and that
    gain."""
    hold = isinstance(start.nls.feature_map, PastInputFeatures)
    fit = refine_nls_output_error(
        start.nls,
        start.arx,
        records,
        max_iterations=config.nls_refinement_iterations,
        refine_linear=not hold,
        radius_iterations=RADIUS_ITERATIONS if config.play_radii == "learned" else 0,
        learn_rate=learn_rate,
    )
    if hold:
        fit = replace(fit, linear_note=PAST_INPUTS_HOLD)
    gain = _small_signal_gain(HammersteinModel(fit.nls, fit.arx), records[0][0])
    if not (np.isfinite(gain) and gain > 0):
        return fit, None, gain
    return fit, HammersteinModel(*move_gain(fit.nls, fit.arx, gain)), gain


def rate_threshold(noise_bound: float, rms_um: float, n_samples: int) -> float:
    """Lowering of the held-out mean squared error (um^2) that ``rate="auto"`` asks of the
    rate-dependent model before keeping it.

    On a record y = m + v with model error m and white sensor noise v of standard deviation
    sigma, the mean squared errors of two models differ by the difference of their own plus
    2 <m_1 - m_2, v> / N, whose standard deviation is at most 2 sigma (rms_1 + rms_2) / sqrt(N)
    <= 4 sigma rms / sqrt(N) with ``rms`` the larger RMS error. Three of those: a lowering that
    noise alone gives with probability below about 0.3 %. The noise is uniform within
    ``noise_bound`` (um; the linear part's bound, which holds the sensor's), so
    sigma = noise_bound / sqrt(3).
    """
    sigma = noise_bound / np.sqrt(3.0)
    return float(3.0 * 4.0 * sigma * rms_um / np.sqrt(n_samples))


def _rate_choice(plain: HammersteinModel, rate: HammersteinModel | None, nls: NlsFit) -> dict:
    """Whether ``rate="auto"`` keeps the rate-dependent model: its held-out mean squared error
    lower than the rate-independent one's by more than :func:`rate_threshold`."""
    plain_rms = _selection_rms(plain, nls)
    n = nls.selection_record[0].size - nls.selection_lead_in
    threshold = rate_threshold(plain.arx.noise_bound, plain_rms, n)
    choice = {"plain_rms_um": plain_rms, "threshold_um2": threshold, "kept": False}
    if rate is not None:
        rate_rms = _selection_rms(rate, nls)
        choice["rate_rms_um"] = rate_rms
        choice["rate_time_s"] = rate.nls.feature_map.rate_time
        choice["kept"] = bool(plain_rms**2 - rate_rms**2 > threshold)
    return choice


def _selection_rms(model: HammersteinModel, nls: NlsFit) -> float:
    """Free-run RMS output error (um) of ``model`` on step e's selection record, after its
    lead-in (:func:`identification.nls.output_error.free_run_rms` of one record when there is
    none)."""
    u, y = nls.selection_record
    error = model.arx.simulate(model.nls.evaluate(u)) - np.asarray(y, dtype=np.float64)
    error = error[nls.selection_lead_in :]
    return float(np.sqrt(float(error @ error) / error.size))


def _small_signal_gain(model: HammersteinModel, u_prbs: np.ndarray) -> float:
    """Slope of z against u on the PRBS record (1 by the scale convention)."""
    return float(np.polyfit(u_prbs, model.nls_output(u_prbs), 1)[0])


def validate(
    record: tuple[np.ndarray, np.ndarray],
    model: HammersteinModel,
    *,
    stroke_um: float | None,
    unrefined: ARXModel | None = None,
    unrefined_nls: HammersteinModel | None = None,
    lead_in: int = 0,
) -> Validation:
    """Step f: free-run simulation of the model (and of its ARX part alone) on fresh data.

    ``record``: the validation record (u V, y um), aligned as by :func:`collect`;
    ``stroke_um``: the bender's one-sided stroke (um) the metrics' percentages refer to (None:
    no percentages); ``unrefined``: the step b estimate when step b' replaced it, run free as
    well (its metrics are None when it is unstable: it has no free run); ``unrefined_nls``:
    step e's model when step e' replaced it, run free as well; ``lead_in``: samples at the
    start of ``record`` that every model runs over from rest but that are not scored (the
    estimation and selection parts before a split record's validation part).
    """
    full = record[0]
    u, y = (np.asarray(x)[lead_in:] for x in record)
    runs = (model.simulate(full), model.arx.simulate(full), model.predict(*record))
    y_sim, y_lin, y_pred = (x[lead_in:] for x in runs)

    def tail(x: np.ndarray) -> np.ndarray:
        return x[lead_in:]

    stroke = stroke_um  # the metrics' percentages refer to it
    metrics = {
        "hammerstein": fit_metrics(y, y_sim, stroke=stroke),
        "linear_arx": fit_metrics(y, y_lin, stroke=stroke),
        "hammerstein_one_step": fit_metrics(y, y_pred, stroke=stroke),
    }
    if unrefined is not None and unrefined is not model.arx:
        metrics["linear_arx_unrefined"] = (
            fit_metrics(y, tail(unrefined.simulate(full)), stroke=stroke)
            if unrefined.is_stable()
            else None
        )
    if unrefined_nls is not None and unrefined_nls is not model:
        metrics["hammerstein_unrefined_nls"] = fit_metrics(
            y, tail(unrefined_nls.simulate(full)), stroke=stroke
        )
        if unrefined_nls.arx is not model.arx:
            metrics["linear_arx_before_e2"] = fit_metrics(
                y, tail(unrefined_nls.arx.simulate(full)), stroke=stroke
            )
    return Validation(u, y, y_sim, y_lin, y_pred, metrics, model.arx.noise_bound)
