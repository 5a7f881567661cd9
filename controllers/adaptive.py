"""Adaptive MPC: the identified linear part follows the actuator while it is controlled.

A controller identified on one bender runs on another bender of the same type, or on the same
bender warmer or older; the datasheet allows +-20 % on stiffness and resonance, and the fixed
model then costs 10-100x in tracking error. :class:`AdaptiveMPC` is the linear MPC of
:mod:`controllers.mpc` whose linear part (the ARX model from z to the deflection) is
re-estimated in closed loop, on the regressors the controller already has: the measured
deflection y and the hidden signal z its own nonlinearity model produced from the voltages it
applied.

Candidates. Every ``period`` samples the controller proposes candidate linear parts from the
data so far:

- ``"full"``: all ARX coefficients, from an online estimator started at the offline model:
  ``estimator="rls"`` (recursive least squares, exponential forgetting) or ``"bayes"`` (the
  paper's uniform-noise posterior over a sliding window, its mode by LP): see
  :mod:`identification.online`;
- ``"modal"``: the offline model with three numbers corrected (DC gain, frequency and damping
  of the first bending mode; :mod:`identification.correction`), fit by least squares on the
  multi-step prediction error of the last ``window`` samples. A stiffer or softer bender, a
  warmer one, a better or worse damped one differ from the nominal in just these, and they are
  identifiable from a reference at a single frequency, where the full re-estimation is not;
- ``"revert"``: the model in use before the last swap.

The safeguard. A candidate is validated on the ``period`` samples that follow its proposal
(held-out data: it was fit before they arrived), by the mean squared 1 .. ``criterion_horizon``
step-ahead prediction error on the measured data (what the MPC's horizon needs). It replaces
the model in use only if it is stable (every pole inside ``max_pole_modulus``), has no more
zeros outside the unit circle than the offline model (a zero crossing the unit circle, from
data that do not excite the frequencies where it acts, is an artefact that would change what
the MPC can achieve), and its error is at least ``improvement`` (relative) below the current
model's. Then the closed loop is watched: if the measured tracking error over the period after a
swap is much larger than over the period before (``monitor_ratio``), the controller returns
to the model before the swap at once and pauses the adaptation; and if, at any later time, it
grows beyond ``monitor_ratio`` times (in RMS) the error of the identified model's last period
before the adaptation left it, the controller returns to the identified model (at once when a
single sample's error exceeds twice the one-period watch's limit). A loop the identified model
did not hold is never handed back to it by this guard. The revert candidate watches a swap
over longer times: if the data turn against it, the model before comes back by the
validation rule. Adapting blindly is dangerous (a linear part that absorbs a hysteresis
mismatch makes things worse); this gate is what should keep the adaptive controller at least
as good as the fixed one where there is nothing to gain (see the measured limits in the
benchmark's notes).

The swap. The ARX model's measured-history realization has the same state for every parameter value
of given orders (past y and past z), so a swap keeps the observer's state, the nonlinearity's
memory, the plan (warm start) and the last z; it rebuilds what depends on the model (condensed
prediction, QP matrices, OSQP set-up, the observer's gain). One thing is re-derived: the state's
past outputs are the old model's, which a model of another gain reads as far from its own steady
state, so they are recomputed by running the new model over the recent inputs, and the output
disturbance takes the rest (the total output estimate is continuous; carrying the old state over
made a bump of 1-2 % of the stroke on a 1 Hz sine). The closed loop then continues exactly as a
fresh controller built on the new model with that state would.

The gain. Like :class:`controllers.mpc.LinearMPC`, the adaptive MPC learns the plant's static
gain from the first sample (:mod:`controllers.gain`); the candidates are fit on the z the
nonlinearity applied, so they carry that gain themselves, and after a swap the gain is learned
afresh around the new model.

Cost. Per sample the estimator stores one datum and the step's median is close to the fixed
MPC's (``benchmarks/results/controller_latency.md``). Every ``period`` samples the review (the
window's LP and the modal fit) runs inside that step and takes tens of milliseconds (the
benchmark report gives each row's max step and deadline misses), so those steps miss a 1 ms
deadline; on a real-time bench the review belongs beside the loop, its result swapped in at a
later sample (the swap itself is cheap).

Each episode starts from the offline model (episodes are independent and reproducible);
``stats.adaptation`` counts proposals, acceptances and rejections, ``stats.trace`` records the
model in use at every review, and :attr:`AdaptiveMPC.dc_gain` and
:attr:`AdaptiveMPC.resonance_hz` read the current model at any time.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from controllers.base import ControllerStats
from controllers.condensed import check_well_posed, prediction_matrices
from controllers.loop import feedback_law, loop_is_stable, output_feedback
from controllers.mpc import LinearMPC, MPCSettings
from controllers.observer import DisturbanceObserver, ObserverBank, make_observer
from controllers.prediction import PredictionModel
from controllers.settings import check_settings, measurement_std
from controllers.task import ControlTask
from identification.arx import ARXModel
from identification.correction import ModalCorrection, fit_modal_correction, multi_step_errors
from identification.online import RecursiveLeastSquares, SlidingWindowBayes, regressor_scales

__all__ = [
    "AdaptiveMPC",
    "AdaptiveMPCSettings",
    "AdaptiveStats",
    "arx_from_realization",
    "first_resonance_hz",
]

ESTIMATORS = ("rls", "bayes")
STRUCTURES = ("both", "full", "modal")


@dataclass(frozen=True)
class AdaptiveMPCSettings(MPCSettings):
    """Settings of :class:`AdaptiveMPC`: those of :class:`controllers.mpc.MPCSettings` and

    Attributes
    ----------
    structure : {"both", "full", "modal"}
        Which candidates are proposed (see the module docstring).
    estimator : {"rls", "bayes"}
        Online estimator of the full candidate.
    forgetting : float
        RLS forgetting factor lambda (memory about 1 / (1 - lambda) samples).
    window : int
        Samples the Bayesian window and the modal fit use (also: no candidate before this
        many samples of the episode).
    period : int
        Samples between reviews; each candidate is validated on the next ``period`` samples.
    criterion_horizon : int
        Steps ahead of the prediction criterion (samples).
    improvement : float
        Relative improvement a candidate needs over the current model to replace it.
    max_pole_modulus : float
        A candidate with a pole of larger modulus is rejected: the slowest physical pole is
        the first bending mode's, 0.98 at 1 kHz for the PL140's damping ratio 0.02 and 0.995
        for 0.005; slower poles estimated from closed-loop data are near-cancelling artefacts
        that let the loop drift.
    monitor_ratio : float
        Closed-loop monitor: a swap is undone when, in the period after it, the measured
        tracking error's mean square exceeds this multiple of the period's before it (plus
        twice the sensor noise's variance), or a single measured error exceeds this multiple
        of the RMS before it plus five noise bounds (checked every sample). Each undone swap
        pauses the adaptation for twice as many periods as the one before.
    confirmations : int
        Consecutive held-out periods a candidate must win before it is swapped in. A model
        fit to a stretch of a slow reference can explain the next stretch and not the one
        after (hysteresis the linear part cannot hold: a Prandtl-Ishlinskii plant on a 1 Hz
        sine); two wins cost one period of delay.
    dead_zone : float
        No swap while the model in use predicts the last period within this many sensor
        noise standard deviations (RMS of its 1 .. ``criterion_horizon``-step errors): the
        noise alone, propagated from the measured history, gives one to three, and below this
        the data cannot tell a better model from a luckier one. On the nominal PL140 the
        identified model's error is 1-3 noise standard deviations, on a bender 20 % stiffer
        80-150 before adaptation.
    modal_stride : int
        The modal fit uses every ``modal_stride``-th start of its record (cost vs accuracy).
    """

    structure: str = "both"
    estimator: str = "bayes"
    forgetting: float = 0.998
    window: int = 300
    period: int = 100
    criterion_horizon: int = 20
    improvement: float = 0.1
    max_pole_modulus: float = 0.995
    monitor_ratio: float = 2.0
    dead_zone: float = 5.0
    confirmations: int = 2
    modal_stride: int = 4

    def __post_init__(self) -> None:
        super().__post_init__()
        check_settings(
            self,
            integers=("window", "period", "criterion_horizon", "modal_stride", "confirmations"),
            non_negative=("improvement", "dead_zone"),
            positive=("monitor_ratio",),
        )
        if self.structure not in STRUCTURES:
            raise ValueError(f"structure must be one of {STRUCTURES}, got {self.structure!r}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"estimator must be one of {ESTIMATORS}, got {self.estimator!r}")
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"forgetting must lie in (0, 1], got {self.forgetting!r}")
        if not 0.0 < self.max_pole_modulus <= 1.0:
            raise ValueError(f"max_pole_modulus must lie in (0, 1], got {self.max_pole_modulus!r}")
        if self.period <= self.criterion_horizon:
            raise ValueError(
                f"period ({self.period}) must exceed criterion_horizon "
                f"({self.criterion_horizon}): a candidate is validated on one period's data"
            )


@dataclass
class AdaptiveStats(ControllerStats):
    """:class:`controllers.base.ControllerStats` plus what the adaptation did.

    Attributes
    ----------
    adaptation : collections.Counter
        ``proposed-<kind>``, ``accepted-<kind>`` (kind: full, modal, revert),
        ``rejected-unstable``, ``rejected-nonminimum-phase`` (candidates refused before
        validation), ``kept-within-noise`` (reviews where the model in use predicted within
        the noise dead zone), ``rejected-worse`` (reviews where no candidate beat the model
        in use), ``rejected-closed-loop-unstable`` (the best candidate's MPC would not
        stabilise the model in use),
        ``reverted-closed-loop`` (swaps the closed-loop monitor undid), ``no-estimate`` (the
        estimator had none to offer).
    trace : list of (int, float, float)
        At every review: (step, DC gain (um per equivalent V), first resonance (Hz)) of the
        model in use after it.
    """

    adaptation: Counter = field(default_factory=Counter)
    trace: list[tuple[int, float, float]] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The base summary plus ``"adaptation"`` (the counts)."""
        return {**super().summary(), "adaptation": dict(self.adaptation)}


def arx_from_realization(model: PredictionModel) -> ARXModel:
    """The ARX model whose measured-history realization is ``model``'s linear part.

    Raises
    ------
    ValueError
        If the linear part is not such a realization (e.g. the true plant's modal state
        space of an oracle): the adaptive MPC re-estimates ARX coefficients.
    """
    a, b, c = model.a, model.b, model.c
    n = a.shape[0]
    for na in range(1, n + 1):
        arx = ARXModel(a[0, :na], np.r_[b[0, 0], a[0, na:]], dt=model.dt)
        a2, b2, c2, _ = arx.state_space_matrices()
        same = a2.shape == a.shape and np.array_equal(a2, a) and np.array_equal(b2, b)
        if same and np.array_equal(c2, c):
            return arx
    raise ValueError(
        f"the {model.source} model's linear part is not an ARX model's measured-history "
        "realization; the adaptive MPC needs an identified model (not the plant's)"
    )


def first_resonance_hz(arx: ARXModel) -> float:
    """Natural frequency (Hz) of the model's first bending mode: the complex pole pair of
    largest modulus, ``|ln p| / (2 pi dt)``; NaN without a complex pair."""
    poles = arx.poles()
    upper = poles[poles.imag > 1e-9]
    if upper.size == 0:
        return math.nan
    p = upper[np.argmax(np.abs(upper))]
    return float(abs(np.log(p)) / (2.0 * math.pi * arx.dt))


def _outside_unit_circle(roots: np.ndarray) -> int:
    return int(np.sum(np.abs(roots) >= 1.0))


@dataclass
class _Candidate:
    kind: str
    arx: ARXModel
    correction: ModalCorrection | None = None
    wins: int = 0


class AdaptiveMPC(LinearMPC):
    """Linear MPC whose ARX linear part is re-estimated online behind a safeguard.

    ``AdaptiveMPC(model, task, settings=None, *, name="mpc-adaptive")`` with
    :class:`AdaptiveMPCSettings`; the model must be an identified one (its linear part an ARX
    model, :func:`arx_from_realization`). See the module docstring.
    """

    Settings = AdaptiveMPCSettings
    name = "mpc-adaptive"
    stats_type = AdaptiveStats

    def __init__(
        self,
        model: PredictionModel,
        task: ControlTask,
        settings: AdaptiveMPCSettings | None = None,
        *,
        name: str | None = None,
    ) -> None:
        settings = settings or AdaptiveMPCSettings()
        self._offline = model
        self._offline_arx = arx = arx_from_realization(model)
        self._offline_nonminimum = _outside_unit_circle(arx.zeros())
        self._history_length = max(arx.na, arx.nb)
        self._scales = regressor_scales(arx, task.u_max)
        self._buffer = settings.window + 2 * settings.period + self._history_length
        super().__init__(model, task, settings, name=name)

    # -- model in use ---------------------------------------------------------------------------

    @property
    def arx(self) -> ARXModel:
        """The ARX linear part in use (z in equivalent V -> um)."""
        return self._arx

    @property
    def dc_gain(self) -> float:
        """DC gain of the linear part in use (um per equivalent V)."""
        return self._arx.static_gain()

    @property
    def resonance_hz(self) -> float:
        """First bending mode of the linear part in use (Hz), :func:`first_resonance_hz`."""
        return first_resonance_hz(self._arx)

    # -- episode --------------------------------------------------------------------------------

    def _reset(self, observation: np.ndarray | None) -> None:
        if getattr(self, "_arx", None) is not self._offline_arx:
            self._arx = self._offline_arx
            if self.model is not self._offline:
                self._rebuild(self._offline)
        super()._reset(observation)
        s = self.settings
        self._estimator = self._make_estimator()
        self._z = np.zeros(self._buffer)
        self._y = np.zeros(self._buffer)
        self._error = np.zeros(self._buffer)  # measured tracking error y_t - r_t (um)
        self._swapped_at: int | None = None
        self._baseline_mse: float | None = None  # the identified model's last period
        self._standing_limit: float | None = None  # a per-sample error that returns at once
        self._watch_limit: float | None = None
        self._failures = 0
        self._paused_until = 0
        self._step = 0
        self._pending: list[_Candidate] = []
        self._previous: ARXModel | None = None
        self._correction = ModalCorrection()
        self._next_review = max(s.window, s.period)

    def _make_estimator(self) -> RecursiveLeastSquares | SlidingWindowBayes | None:
        s = self.settings
        if s.structure == "modal":
            return None
        if s.estimator == "rls":
            return RecursiveLeastSquares(self._offline_arx, self._scales, forgetting=s.forgetting)
        return SlidingWindowBayes(
            self._offline_arx.na, self._offline_arx.nb, window=s.window, dt=self._offline.dt
        )

    def _act(self, observation: np.ndarray) -> float:
        u = super()._act(observation)
        y = float(observation[0])
        self._record(self._z_applied, y, y - float(observation[1]))
        return u

    # -- adaptation -----------------------------------------------------------------------------

    def _record(self, z_t: float, y_t: float, error_t: float) -> None:
        """Store the sample (z_t applied now, y_t measured now, the measured tracking error)
        and review when it is time."""
        if self._estimator is not None:
            self._estimator.update(z_t, y_t)
        slot = self._step % self._buffer
        self._z[slot], self._y[slot], self._error[slot] = z_t, y_t, error_t
        self._step += 1
        if self._watch_limit is not None and abs(error_t) > self._watch_limit:
            self._undo_swap()
        elif self._standing_limit is not None and abs(error_t) > self._standing_limit:
            self._previous = None  # diverging long after the swap: back to the identified model
            self._undo_swap()
        if self._step >= self._next_review:
            self._next_review += self.settings.period
            self._review()

    def _last(self, samples: int) -> np.ndarray:
        """Buffer slots of the last ``samples`` samples, oldest first (fewer at the start)."""
        samples = min(samples, self._step, self._buffer)
        return np.arange(self._step - samples, self._step) % self._buffer

    def _recent(self, samples: int) -> tuple[np.ndarray, np.ndarray]:
        """The last ``samples`` samples (z, y), oldest first (fewer at the episode's start)."""
        index = self._last(samples)
        return self._z[index], self._y[index]

    def _criterion(self, arx: ARXModel, z: np.ndarray, y: np.ndarray) -> float:
        errors = multi_step_errors(arx, z, y, self.settings.criterion_horizon)
        return float(np.mean(errors**2)) if errors.size else math.inf

    def _review(self) -> None:
        """Check the last swap in closed loop, validate the pending candidates on the data
        since their proposal, then propose new ones."""
        self._watch_limit = None  # the per-sample watch covers one period after a swap
        if self._swap_failed():
            self._undo_swap()
        elif self._diverged():
            self._previous = None  # the model before may be no better: the identified one
            self._undo_swap()
        winners: list[_Candidate] = []
        if self._pending and self._step >= self._paused_until:
            winners = self._validate(self._pending)
        self._pending = winners + self._propose()
        self.stats.trace.append((self._step, self.dc_gain, self.resonance_hz))

    def _validate(self, pending: list[_Candidate]) -> list[_Candidate]:
        """Score the pending candidates on the last period (held out: it arrived after they
        were fit); swap in the best one that has now won ``confirmations`` periods in a row.
        Returns the winners still waiting for confirmation."""
        s = self.settings
        stats = self.stats.adaptation
        z, y = self._recent(s.period + self._history_length)
        current = self._criterion(self._arx, z, y)
        if current < (s.dead_zone * measurement_std(None, self.task)) ** 2:
            stats["kept-within-noise"] += 1
            return []
        scores = [self._criterion(c.arx, z, y) for c in pending]
        bar = (1.0 - s.improvement) * current
        winners = [c for c, score in zip(pending, scores, strict=True) if score < bar]
        if not winners:
            stats["rejected-worse"] += 1
            return []
        for candidate in winners:
            candidate.wins += 1
        ready = [c for c in winners if c.wins >= s.confirmations]
        if not ready:
            return winners
        chosen = min(ready, key=lambda c: scores[pending.index(c)])
        if not self.stabilises(chosen.arx, self._arx):
            stats["rejected-closed-loop-unstable"] += 1
            return [c for c in winners if c is not chosen]
        stats[f"accepted-{chosen.kind}"] += 1
        self._swap(chosen)
        return []

    def _error_limit(self, factor: float = 1.0) -> float:
        """The measured error (um) that undoes a swap at once: ``factor`` times
        ``monitor_ratio`` times the RMS of the last period, plus five sensor noise bounds
        (``factor`` 1: the watch of a fresh swap; 2: the standing guard)."""
        errors = self._error[self._last(self.settings.period)]
        rms = float(np.sqrt(np.mean(errors**2))) if errors.size else 0.0
        return factor * self.settings.monitor_ratio * rms + 5.0 * self.task.noise_bound_um

    def _much_worse(self, mse: float, baseline_mse: float, ratio: float) -> bool:
        """Whether a period's mean squared tracking error (um^2) exceeds ``ratio`` times a
        baseline's, beyond twice the sensor noise variance."""
        noise_variance = self.task.noise_bound_um**2 / 3.0
        return bool(mse > ratio * baseline_mse + 2.0 * noise_variance)

    def _undo_swap(self) -> None:
        """Return to the model in use before the last swap (it held the loop better) and
        pause the adaptation; the failed model is not offered again as a revert."""
        self.stats.adaptation["reverted-closed-loop"] += 1
        self._failures += 1
        self._swap(_Candidate("revert", self._previous or self._offline_arx))
        self._previous = None
        self._swapped_at = None
        self._watch_limit = None
        self._pending = []
        self._paused_until = self._step + self.settings.period * 2**self._failures

    def stabilises(self, candidate: ARXModel, plant: ARXModel) -> bool:
        """True if the unconstrained MPC and observer built on ``candidate`` stabilise
        ``plant`` (the model in use, which the closed loop has been running on).

        The unconstrained MPC with its observer is a linear controller from y to z
        (:func:`controllers.loop.output_feedback`), so the loop around ``plant`` is a linear
        system; its spectral radius must be < 1. With the observer bank, the observer is the
        filter at the bank's prior noise levels, or at its fallback's once the bank's runaway
        guard has fallen back (the filter the loop then runs with).
        """
        s = self.settings
        a, b, c, _ = candidate.state_space_matrices()
        phi, gamma = prediction_matrices(a, b, c, s.horizon)
        hessian, q_matrix = self._qp_matrices(phi, gamma)
        bank = self.observer
        if isinstance(bank, ObserverBank):
            index = bank.prior if bank.runaway_at is None else bank.fallback
            process_std, disturbance_std = bank.noise_levels[index]
        else:
            process_std, disturbance_std = s.process_std, s.disturbance_std
        observer = DisturbanceObserver(
            a,
            b,
            c,
            measurement_std=measurement_std(s.measurement_std, self.task),
            disturbance_std=disturbance_std,
            process_std=process_std,
            slope_std=s.slope_std,
        )
        k_estimate, k_previous = feedback_law(hessian, q_matrix, observer.a_aug.shape[0])
        controller = output_feedback(
            observer.a_aug, observer.b_aug, observer.c_aug, observer.gain, k_estimate, k_previous
        )
        ap, bp, cp, _ = plant.state_space_matrices()
        return loop_is_stable(controller, ap, bp, cp)

    def _diverged(self) -> bool:
        """True when, at any time after the adaptation left the identified model, the measured
        tracking error over the last period is more than ``monitor_ratio`` times (in RMS) the
        error of the identified model's last period: a loop that drifts to instability long
        after the one-period watch of :meth:`_swap_failed`."""
        if self._arx is self._offline_arx or self._baseline_mse is None:
            return False
        errors = self._error[self._last(self.settings.period)]
        ratio = self.settings.monitor_ratio**2
        return self._much_worse(float(np.mean(errors**2)), self._baseline_mse, ratio)

    def _swap_failed(self) -> bool:
        """True when the measured tracking error got much worse in the period after the last
        swap than in the period before it."""
        period = self.settings.period
        if self._swapped_at is None or self._step - self._swapped_at != period:
            return False
        if self._step < 2 * period:
            return False
        errors = self._error[self._last(2 * period)]
        before, after = np.mean(errors.reshape(2, period) ** 2, axis=1)
        return self._much_worse(after, before, self.settings.monitor_ratio)

    def _propose(self) -> list[_Candidate]:
        s = self.settings
        stats = self.stats.adaptation
        candidates: list[_Candidate] = []
        if self._estimator is not None:
            estimator = self._estimator
            estimate = estimator.model() if s.estimator == "rls" else estimator.estimate()
            if estimate is None:
                stats["no-estimate"] += 1
            else:
                candidates.append(_Candidate("full", estimate))
        if s.structure in ("both", "modal"):
            z, y = self._recent(s.window)
            correction, arx = fit_modal_correction(
                self._offline_arx,
                z,
                y,
                horizon=s.criterion_horizon,
                start=self._correction,
                stride=s.modal_stride,
            )
            candidates.append(_Candidate("modal", arx, correction))
        if self._previous is not None:
            candidates.append(_Candidate("revert", self._previous))
        kept = []
        for candidate in candidates:
            stats[f"proposed-{candidate.kind}"] += 1
            refusal = self.refusal(candidate.arx)
            if refusal is None:
                kept.append(candidate)
            else:
                stats[refusal] += 1
        return kept

    def refusal(self, arx: ARXModel) -> str | None:
        """Why the candidate ``arx`` is refused before validation (the ``stats.adaptation``
        key), or None: ``"rejected-unstable"`` (a pole beyond ``max_pole_modulus``) or
        ``"rejected-nonminimum-phase"`` (more zeros outside the unit circle than the offline
        model)."""
        if np.max(np.abs(arx.poles()), initial=0.0) >= self.settings.max_pole_modulus:
            return "rejected-unstable"
        if _outside_unit_circle(arx.zeros()) > self._offline_nonminimum:
            return "rejected-nonminimum-phase"
        return None

    def _swap(self, candidate: _Candidate) -> None:
        """Predict with the candidate's linear part from now on (see the module docstring)."""
        self._watch_limit = self._error_limit()
        if candidate.arx is self._offline_arx:  # back on the identified model: nothing to guard
            self._baseline_mse = self._standing_limit = None
        elif self._arx is self._offline_arx and self._step > 0:
            # leaving the identified model: how well it held the loop is the standing bar
            # (a loop the identified model could not hold is never handed back to it)
            errors = self._error[self._last(self.settings.period)]
            self._baseline_mse = float(np.mean(errors**2))
            self._standing_limit = self._error_limit(2.0)
        self._previous = self._arx
        self._arx = candidate.arx
        self._swapped_at = self._step
        if candidate.correction is not None:
            self._correction = candidate.correction
        a, b, c, _ = candidate.arx.state_space_matrices()
        # The candidate was fit on the applied z, so it carries the gain the MPC had learned:
        # back to the applied scale, and the gain is learned afresh around the new model.
        self.observer.rescale_input(1.0 / self._g)
        self._plan = self._plan / self._g
        self._z_prev = self._z_applied
        estimate_before = self.observer.estimate.copy()
        self._rebuild(dataclasses.replace(self._offline, a=a, b=b, c=c))
        self._reset_observer(self._consistent_estimate(estimate_before, candidate.arx))
        self._restart_gain(self.observer.estimate[: self.observer.n])

    def _reset_observer(
        self, estimate: np.ndarray, selected: int | None = None, runaway_at: int | None = None
    ) -> None:
        """Set the observer's estimate; a bank keeps the noise levels the data chose and its
        runaway guard's decision (``runaway_at``: that of the bank it replaces)."""
        observer = self.observer
        if isinstance(observer, ObserverBank):
            runaway_at = observer.runaway_at if runaway_at is None else runaway_at
            observer.reset(estimate, selected=observer.selected if selected is None else selected)
            if runaway_at is not None:
                observer.fall_back(runaway_at)
        else:
            observer.reset(estimate)

    def _consistent_estimate(self, estimate: np.ndarray, arx: ARXModel) -> np.ndarray:
        """The observer estimate for ``arx`` at a swap: its own past outputs, same total.

        The state's first ``na`` entries are the model's past outputs, the rest past inputs
        (z, exact). A model with another gain would read the old model's outputs as far from
        its own steady state and predict a jump; so the outputs are re-derived by running the
        new model over the recent inputs (from the measured outputs ``window`` samples ago:
        its modes have decayed long before), and the output disturbance d takes what they do
        not explain, so that the total output estimate ``C x + d`` is unchanged at the swap.
        """
        estimate = estimate.copy()
        n, na = self.observer.n, max(arx.na, 1)
        z, y = self._recent(self.settings.window)
        if z.size <= na:
            return estimate
        outputs = arx.simulate(np.r_[z, 0.0], y0=y[: arx.na]) if arx.na else None
        total = estimate[0] + estimate[n]
        estimate[:na] = outputs[::-1][:na]  # y_t+1, y_t, .. as the state holds them
        estimate[n:] = 0.0
        estimate[n] = total - estimate[0]
        return estimate

    def _rebuild(self, model: PredictionModel) -> None:
        """Rebuild what depends on the linear part, keeping the observer's state, the
        nonlinearity's memory, the plan and the last z."""
        settings = self.settings
        if model.a.shape != self.model.a.shape:
            raise ValueError(
                f"a swapped model must keep the state size {self.model.a.shape[0]}, "
                f"got {model.a.shape[0]}"
            )
        estimate = self.observer.estimate.copy()
        selected = getattr(self.observer, "selected", None)
        runaway_at = getattr(self.observer, "runaway_at", None)
        self.model = model
        self._phi, self._gamma = prediction_matrices(model.a, model.b, model.c, settings.horizon)
        check_well_posed(self._gamma, settings.rate_weight, 1.0, name=self.name)
        self.observer = make_observer(model, self.task, settings)
        self._reset_observer(estimate, selected, runaway_at)
        self._set_up()
        if hasattr(self, "_qp"):
            self._qp = self._setup_solver()

    def describe(self) -> dict:
        """The linear MPC's description plus the adaptation's settings and the offline and
        current linear parts' DC gain and first resonance."""
        out = super().describe()
        out["settings"] = asdict(self.settings)
        out["adaptation"] = {
            "offline_dc_gain": self._offline_arx.static_gain(),
            "offline_resonance_hz": first_resonance_hz(self._offline_arx),
        }
        return out
