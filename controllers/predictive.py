"""What the linear and the nonlinear MPC share: model, settings, observer, prediction, start.

Both predict the deflection over the horizon with the condensed linear part
(:mod:`controllers.condensed`), estimate ``[x; d]`` with the offset-free observer
(:mod:`controllers.observer`), penalise the rate of their plan (z for
:class:`controllers.mpc.LinearMPC`, volts for :class:`controllers.nmpc.NonlinearMPC`), learn the
bender's static gain from the first sample (:mod:`controllers.gain`), and start each episode
from the model's steady state that holds the first measurement:

- within the sensor noise bound, rest at 0 V (the measurement is noise);
- beyond it (an env reset with ``initial_voltage``), the linear state holding y_0 and the
  nonlinearity's memory after the voltage that holds it (:meth:`PredictionModel.steady_start`).

A subclass builds its solver in :meth:`PredictiveController._set_up` and sets its plan from the
start in :meth:`PredictiveController._start`.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import Any, ClassVar

import numpy as np

from controllers.base import Controller, _clock
from controllers.condensed import (
    blocking_matrix,
    check_well_posed,
    move_blocks,
    prediction_matrices,
    qp_matrices,
    rate_hessian,
)
from controllers.drive import DriveEstimate, slope_range
from controllers.gain import GainEstimate
from controllers.loop import feedback_law, modulus_margins, plant_margins, radii_matrix
from controllers.observer import ObserverBank, make_observer
from controllers.prediction import PredictionModel, SteadyStart
from controllers.settings import MS_MAX, check_initial_voltage, measurement_std
from controllers.task import ControlTask
from controllers.tolerance_box import (
    ToleranceBox,
    UnstableFitError,
    Vertex,
    arx_of,
    datasheet_model,
    vertex_models,
)
from identification.arx import ARXModel
from piezo_env.memo import ContentCache

_FLOAT32, _FLOAT64 = np.dtype(np.float32), np.dtype(np.float64)

__all__ = [
    "BOX_PLANTS_KEPT",
    "BOX_SCREENS_KEPT",
    "MARGINS_KEPT",
    "PredictiveController",
    "filter_margins",
    "screen_bank",
    "task_datasheet_model",
]

BOX_SCREENS_KEPT = 16
"""Box screens kept by content (:func:`screen_bank`), one per bank and feedback law. A
benchmark worker meets up to six identified models (three identification seeds, on the nominal
bender and on the bench), each screened by the linear and the nonlinear MPC's laws: 12."""

BOX_PLANTS_KEPT = 8
"""Tolerance boxes' vertex models kept by content (:meth:`PredictiveController.box_plants`),
one per identified model: a benchmark worker meets up to six (as :data:`BOX_SCREENS_KEPT`)."""

MARGINS_KEPT = 256
"""Filters' modulus margins kept by content (:func:`filter_margins`), one per observer and
feedback law. A benchmark worker meets up to six identified models, each with the two MPCs'
laws on its bank and the adaptive MPC's 34 members' (the one in use when it is described),
and the oracles of its plants (two per plant, 12 plants): 6 x 36 + 24 = 240."""

SLOPES_KEPT = 16
"""Models whose nonlinearity's slope range is kept (:meth:`PredictiveController.model_slopes`:
about 2,000 steps of the map each)."""

SLOPE_SAMPLES = 240
"""Samples per full-stroke leg of :meth:`PredictiveController.model_slopes`' triangle (0.25 V
per sample at +-30 V): a secant's slope differs from the map's at its ends by the curvature
times the step; against a step ten times finer the slopes moved by 0.03 % on the identified
maps (``benchmarks/results/design_measurements.md``), inside the box's 30 % widths."""

_box_screens = ContentCache(BOX_SCREENS_KEPT)
_slopes_kept = ContentCache(SLOPES_KEPT)
_box_plants = ContentCache(BOX_PLANTS_KEPT)
_margins = ContentCache(MARGINS_KEPT)


def filter_margins(
    observer: Any, gains: np.ndarray, law: tuple[np.ndarray, float]
) -> np.ndarray:
    """:func:`controllers.loop.modulus_margins` of the loops the filter ``gains`` ((F, m) or
    (m,)) of ``observer``'s augmented model close with the feedback ``law``, kept by content
    (:data:`MARGINS_KEPT`): the box screen and the description read the same sweep, and a
    controller built again on the same model reads it from the first."""
    a_aug, b_aug, c_aug, n = observer.a_aug, observer.b_aug, observer.c_aug, observer.n
    return _margins.get(
        [a_aug, b_aug, c_aug, gains, *law, n],
        lambda: modulus_margins(a_aug, b_aug, c_aug, gains, *law, n=n),
    )


def _has_mode(model: PredictionModel) -> bool:
    """True if the model's linear part has a complex pole pair (a bending mode to move)."""
    return bool(np.any(np.abs(np.linalg.eigvals(model.a).imag) > 1e-9))


def screen_bank(
    bank: ObserverBank,
    law: tuple[np.ndarray, float],
    plants: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> dict[str, Any]:
    """Let ``bank`` select only the filters whose unconstrained loop (feedback ``law``,
    :func:`controllers.loop.feedback_law`) has a sensitivity peak of at most
    :data:`controllers.settings.MS_MAX` on the bank's own model and on every one of ``plants``
    (stable there too).

    Why. The bank selects the filter whose innovations are the most likely, which says nothing
    about whether the loop it closes is stable on the plant at hand; on a bender within the
    datasheet's tolerances whose resonance is off, the fast filters' loops can be unstable and
    their growing innovations make them still more likely. Screening on the box's vertices
    removes those filters before the first sample. Stability alone on the vertices was not
    enough: a filter whose loop was stable on every vertex with a modulus margin of 0.07 on
    one (Ms 14: resonance and gain x1.2, damping 0.01) was the bank's prior, and a transient
    that drove the drive to its ends (a sine switched on at 50 Hz, a random step) rang that
    bender into a limit cycle between the drive's ends (68 % of the stroke) that the bank never
    left. The margin is the distance of the loop's Nyquist curve from the critical point, so
    Ms <= MS_MAX on every vertex keeps the loop stable under any gain change of the loop
    between 1 / (1 + 1/Ms) and 1 / (1 - 1/Ms) (0.64-2.25 at Ms 1.8), which is what a drive
    at its ends (a gain below 1) and the hysteresis's local slope (above or below) do to it;
    it also covers what the box's models do not hold. The check is at the vertices (and the
    gain's midpoint), not a proof over the box's interior; the tests check random interior
    plants as well.

    If no filter passes, the bank keeps those that are stable on every vertex within the bound
    on its own model, or else the one of the smallest worst radius, and the result says so
    (``robust`` False) and warns: the loop is then not known to keep its margin on the box.

    Returns
    -------
    dict
        ``applied`` True, ``robust``, ``filters_kept``, ``filters``, ``worst_radius`` (the
        largest spectral radius over the kept filters and the plants, -), ``worst_margin``
        (their smallest modulus margin over the plants, -), ``ms_max``.
    """

    def compute() -> tuple[np.ndarray, np.ndarray]:
        args = (bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants)
        return radii_matrix(*args).max(axis=1), plant_margins(*args).min(axis=1)

    # A closed loop and a frequency sweep per filter and plant, and a sweep per filter on the
    # model: kept by content, so the same bank screened with the same law on the same plants
    # is screened once.
    parts = [bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants]
    radii, on_plants = _box_screens.get(parts, compute)
    margins = filter_margins(bank, bank.gains, law)
    stable = (radii < 1.0) & (margins >= 1.0 / MS_MAX)
    admissible = stable & (on_plants >= 1.0 / MS_MAX)
    robust = bool(admissible.any())
    if not robust:
        admissible = stable if stable.any() else radii == radii.min()
        warnings.warn(
            f"no filter of the observer bank keeps Ms <= {MS_MAX} on every vertex of the "
            f"tolerance box (largest smallest margin {on_plants[radii < 1.0].max(initial=0.0):.3f}"
            f", smallest worst spectral radius {radii.min():.4f}); the bank keeps "
            f"{int(admissible.sum())} filter(s) not known to keep that margin on the box",
            RuntimeWarning,
            stacklevel=3,
        )
    bank.restrict(admissible)
    return {
        "applied": True,
        "robust": robust,
        "filters_kept": int(admissible.sum()),
        "filters": int(admissible.size),
        "worst_radius": float(radii[admissible].max()),
        "worst_margin": float(on_plants[admissible].min()),
        "ms_max": MS_MAX,
    }


def task_datasheet_model(
    arx: ARXModel, task: ControlTask, vertex: Vertex, order: int
) -> tuple[ARXModel, float]:
    """:func:`controllers.tolerance_box.datasheet_model` of ``arx`` at ``vertex``, with the
    datasheet, first-mode damping and beam elements of ``task`` (a task read from a
    ``PiezoBender-v0`` env carries them)."""
    return datasheet_model(
        arx,
        task.datasheet,
        vertex,
        damping_ratio=task.damping_ratio,
        order=order,
        n_elements=task.n_elements,
    )


def datasheet_vertex_plants(
    model: PredictionModel, task: ControlTask, boxes: list[ToleranceBox]
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The linear parts (a, b, c) of the vertices of ``boxes`` around ``model``'s, moved by the
    datasheet's physics (:func:`controllers.tolerance_box.datasheet_model`, one order above
    the model's, as the adaptive MPC's datasheet members). A vertex whose fit is unstable is
    left out, and the screen's description counts it (``vertex_plants``)."""
    arx = arx_of(model)
    order = max(arx.na, arx.nb) + 1
    shapes: dict[tuple[float, Any], tuple[np.ndarray, np.ndarray, np.ndarray] | None] = {}
    plants = []
    for box in boxes:
        for vertex in box.vertices():
            # One fit per resonance and damping: the free deflection scales the FE response
            # (and the fit, whose error is relative) by the vertex's gain alone.
            key = (vertex.resonance, vertex.damping)
            if key not in shapes:
                try:
                    shape = dataclasses.replace(vertex, gain=1.0)
                    member, _ = task_datasheet_model(arx, task, shape, order)
                    a, b, c, _ = member.state_space_matrices()
                    shapes[key] = (a, b, c)
                except UnstableFitError:  # no plant to screen on (counted)
                    shapes[key] = None
            shape = shapes[key]
            if shape is not None:
                plants.append((shape[0], shape[1] * vertex.gain, shape[2]))
    return plants


class PredictiveController(Controller):
    """Base of the MPCs (see the module docstring).

    Parameters
    ----------
    model : PredictionModel
        Identified Hammerstein model or the plant (oracle).
    task : ControlTask
        Sample time, drive range, preview layout.
    settings
        The subclass's ``Settings`` (default: its defaults). Has ``horizon``, ``rate_weight``
        and the observer's fields; ``tracking_weight`` if the cost weighs the error.
    name : str, optional
        Name in reports (default: the class's).

    Raises
    ------
    ValueError
        When the QP would be singular (:func:`controllers.condensed.check_well_posed`).
    """

    Settings: ClassVar[type]
    _gain: GainEstimate | None = None  # set by a subclass's _set_up where it learns the gain
    _g = 1.0  # the gain it predicts with, relative to its model's
    _member = 0  # which linear part of the gain estimate it predicts with

    def __init__(
        self,
        model: PredictionModel,
        task: ControlTask,
        settings: Any | None = None,
        *,
        name: str | None = None,
    ) -> None:
        super().__init__(task)
        if name is not None:
            self.name = name
        self.model = model
        self.settings = settings = settings or self.Settings()
        check_initial_voltage(settings, task.u_max)
        n_hor = settings.horizon
        self.prediction_samples = samples = self._prediction_samples(model, settings)
        self._phi, self._gamma = prediction_matrices(model.a, model.b, model.c_tracked, samples)
        self.blocks = move_blocks(n_hor, samples)
        self._blocking = None if samples == n_hor else blocking_matrix(self.blocks)
        self._rate_hessian = rate_hessian(n_hor, settings.rate_weight)
        weight = getattr(settings, "tracking_weight", 1.0)  # the linear MPC weighs error by 1
        check_well_posed(self._blocked(self._gamma), settings.rate_weight, weight, name=self.name)
        self.observer = make_observer(model, task, settings)
        self._box_plants: list[tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
        self._set_up()
        self.screen = self._screen(self.observer, self.feedback_law())
        self._reset(None)

    def box_plants(self) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The linear parts (a, b, c) the observer bank's filters are screened on: the vertices
        of the datasheet's tolerance box around the model, at the gain factors ``1 - w``,
        ``1`` and ``1 + w`` (w the datasheet's free-deflection tolerance: the plant's gain
        relative to the one the MPC predicts with lies between 1 and the plant's own, as the MPC
        learns it, :mod:`controllers.gain`), each vertex moved mode by mode
        (:func:`controllers.tolerance_box.vertex_models`) and, when the task carries the
        bender's datasheet, also by the datasheet's physics
        (:func:`controllers.tolerance_box.datasheet_model`).

        Why both. Mode by mode, a vertex keeps every mode the model holds as something else
        where the nominal bender has it: the PL140's second mode at 1 kHz sampling (1.0 kHz,
        folded onto 3 Hz) is a real pole of the identified model, and at resonance x1.2 it
        folds onto 214 Hz, next to the first mode at 192 Hz. The datasheet's FE model moves
        every mode and alias; the mode-by-mode vertices stay for a task without a datasheet.
        Computed once, and kept by content (:data:`BOX_PLANTS_KEPT`) for the next controller
        on the same model and task."""
        if self._box_plants is None:
            model, task = self.model, self.task
            box = ToleranceBox()
            has_mode = _has_mode(model)
            if not has_mode:  # nothing to move but the gain
                box = dataclasses.replace(box, resonance=0.0, damping=None)
            boxes = [box]
            matched = dataclasses.replace(box, gain=0.0)
            if not matched.is_nominal:
                boxes.append(matched)
            physics = has_mode and task.datasheet is not None and bool(task.damping_ratio)

            def compute() -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
                models = [m for b in boxes for _, m in vertex_models(model, b, further_modes=True)]
                plants = [(m.a, m.b, m.c) for m in models]
                if physics:
                    plants += datasheet_vertex_plants(model, task, boxes)
                return plants

            # What the vertices read of the model and the task, and the box's defaults.
            parts = [model.a, model.b, model.c, model.dt, ToleranceBox()]
            parts += [repr(task.datasheet), task.damping_ratio, task.n_elements]
            self._box_plants = _box_plants.get(parts, compute)
            vertices = sum(len(b.vertices()) for b in boxes)
            self.box_plant_counts = {
                "mode_by_mode": vertices,
                "datasheet": len(self._box_plants) - vertices,
                "datasheet_asked": vertices if physics else 0,
            }
        return self._box_plants

    def _screen(self, observer: Any, law: tuple[np.ndarray, float]) -> dict[str, Any]:
        """Restrict ``observer`` (a bank) to the filters :func:`screen_bank` admits, and say
        what was done (JSON-safe, for ``describe()``)."""
        if not isinstance(observer, ObserverBank):
            return {"applied": False, "why": "a single filter (observer='fixed')"}
        if not getattr(self.settings, "robust_bank", True):
            return {"applied": False, "why": "robust_bank=False"}
        if self.model.source != "identified":
            return {"applied": False, "why": "the model is the plant's own (oracle)"}
        screen = screen_bank(observer, law, self.box_plants())
        return {**screen, "vertex_plants": dict(self.box_plant_counts)}

    def _reset(self, observation: np.ndarray | None) -> None:
        y0 = 0.0 if observation is None else float(observation[0])
        voltage = getattr(self.settings, "initial_voltage", None)
        start = self.model.steady_start(y0, self.task.noise_bound_um, voltage)
        # d starts at 0 even when y0 lies beyond the model's reach (the voltage holding it
        # clipped): the part left unexplained is then mostly that one sample's noise, and
        # starting d there makes the first 50 steps worse, not better (the plant starting at
        # 30 V: benchmarks/results/design_measurements.md).
        self.observer.reset(np.r_[start.x, np.zeros(self.observer.n_disturbance)])
        self._memory = start.memory
        self._start(start)

    def act(self, observation: Any) -> np.ndarray:
        """The base class's step, and the step at which the observer bank's runaway guard fell
        back, recorded in :attr:`stats` (``observer_fallback_step``)."""
        action = super().act(observation)
        stats = self.stats
        if stats.observer_fallback_step is None:
            if getattr(self.observer, "runaway_at", None) is not None:
                stats.observer_fallback_step = len(stats.compute_s) - 1
        return action

    def _act_compiled(self, observation: Any, buffer: np.ndarray, runaway: Any) -> np.ndarray:
        """:meth:`act` around a compiled step (the linear MPC's and the NMPC's fused calls,
        :meth:`_act_fused`): the observation checked as the base class checks it, but for a
        float array of the right shape only its measurement against the observation bound (the
        compiled step refuses a non-finite entry before it moves anything), copied into the
        step's ``buffer``; the volts held in the drive range, the compute time recorded, and
        the observer bank's fallback step from ``runaway()`` (its runaway sample, < 0: none)."""
        start = _clock()
        if (
            type(observation) is not np.ndarray
            or observation.shape != buffer.shape
            or (observation.dtype is not _FLOAT32 and observation.dtype is not _FLOAT64)
        ):
            observation = self.task.check_observation(observation)  # raises, or converts
        elif not abs(observation.item(0)) <= self._observation_bound:  # a fault or NaN: why
            self.task.check_observation(observation)
        buffer[:] = observation
        u = self._act_fused(observation)
        stats = self.stats
        if not -self._u_max <= u <= self._u_max:  # as the base class
            if u != u:
                raise RuntimeError(f"{self.name} computed a NaN voltage")
            u = self._u_max if u > 0 else -self._u_max
            stats.saturated += 1
        if stats.observer_fallback_step is None and runaway() >= 0:
            stats.observer_fallback_step = len(stats.compute_s)
        action = np.empty(1, dtype=np.float32)  # as np.array([u], dtype=np.float32)
        action[0] = u
        stats.compute_s.append(_clock() - start)
        return action

    def _act_fused(self, observation: np.ndarray) -> float:
        """The volts of one step by the subclass's compiled step (:meth:`_act_compiled`)."""
        raise NotImplementedError

    def _into_buffers(self, plan: np.ndarray, memory: np.ndarray) -> None:
        """The plan and the nonlinearity's memory, which Python may have replaced (a new
        episode, the numpy path), copied into the compiled step's buffers ``plan`` and
        ``memory``; the attributes then are those buffers, which the step updates in place."""
        if self._plan is not plan:
            plan[:] = self._plan
            self._plan = plan
        if self._memory is not memory:
            memory[:] = self._memory
            self._memory = memory

    def feedback_law(self) -> tuple[np.ndarray, float]:
        """``(k_e, k_z)``: the unconstrained first move's gains on the observer's estimate and
        on the previous move (:func:`controllers.loop.feedback_law`).

        For the nonlinear MPC this is its law linearised at unit slope of the nonlinearity
        (dz/du = 1, the network's small-signal gain on the identification data): the tracking
        weight w and the rate penalty in volts then act as the linear MPC's with
        ``rate_weight / w``. Where the slope m differs (along a major loop, or the oracle's
        hysteresis, which has no unit-gain convention) its rate penalty in z is
        ``rate_weight / (w m^2)``, so its reported margin is an approximation.

        Returns
        -------
        k_e : numpy.ndarray
            Gains on ``[x; d (; s)]`` (equivalent V per um; per um/sample for s).
        k_z : float
            Gain on z_t-1 (dimensionless).
        """
        hessian, q_matrix = self._qp_matrices(self._phi, self._gamma)
        return feedback_law(hessian, q_matrix, self.observer.n + self.observer.n_disturbance)

    def _qp_matrices(self, phi: np.ndarray, gamma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The settings' QP (:func:`controllers.condensed.qp_matrices`) on the condensed
        prediction ``(phi, gamma)``, its moves blocked (:attr:`blocks`): the rate penalty over
        the tracking weight (1 for the linear MPC), and the disturbance slope when
        ``slope_std`` > 0."""
        s = self.settings
        weight = getattr(s, "tracking_weight", 1.0)
        slope = getattr(s, "slope_std", 0.0) > 0
        return qp_matrices(phi, self._blocked(gamma), s.rate_weight / weight, slope=slope)

    def _blocked(self, gamma: np.ndarray) -> np.ndarray:
        """Gamma of the M moves: times the blocking matrix when the moves are blocked."""
        return gamma if self._blocking is None else gamma @ self._blocking

    def _prediction_samples(self, model: PredictionModel, settings: Any) -> int:
        """Np, the samples the output is predicted over: the horizon's (no blocking); the
        linear MPC may predict further (:func:`controllers.mpc.covering_samples`)."""
        return settings.horizon

    def observer_description(self) -> dict[str, Any]:
        """Modulus margin of the loop this controller closes around its own model, unconstrained
        (:mod:`controllers.loop`): the single filter's, or the bank's range over the filters it
        may select and its prior filter's, with what the box screen kept (:func:`screen_bank`)
        (JSON-safe; dimensionless, 0 when that loop is unstable)."""
        observer = self.observer
        bank = isinstance(observer, ObserverBank)
        law = self.feedback_law()
        # A frequency sweep per filter, the box screen's (filter_margins keeps it by content).
        margins = filter_margins(observer, observer.gains if bank else observer.gain, law)
        if not bank:
            return {"modulus_margin": float(margins[0])}
        kept = margins[observer.admissible]
        return {
            "modulus_margin_range": [float(kept.min()), float(kept.max())],
            "modulus_margin_prior": float(margins[observer.prior]),
            "riccati_fallbacks": int(observer.riccati_fallbacks),
            "box_screen": self.screen,
        }

    def _slew_window(self) -> tuple[float, float]:
        """Voltages (V) this sample's move may take: the drive range, and with the amplifier's
        slew limit S (``self._slew_step`` = S dt, set by the subclass) u_t-1 +- S dt within it
        (``self._u_prev`` = u_t-1)."""
        if self._slew_step is None:
            return -self._u_max, self._u_max
        step = self._slew_step
        return max(self._u_prev - step, -self._u_max), min(self._u_prev + step, self._u_max)

    def _set_up(self) -> None:
        """Build what stays fixed over episodes (called once, before the first reset)."""
        raise NotImplementedError

    def _start(self, start: SteadyStart) -> None:
        """Set the plan and the solver for an episode that starts at ``start``."""
        raise NotImplementedError

    def _gain_estimate(self) -> GainEstimate | DriveEstimate | None:
        """The gain estimate of the model (None with ``gain_tolerance`` 0), or with a
        ``strength_tolerance`` the drive's (:mod:`controllers.drive`)."""
        settings = self.settings
        if settings.gain_tolerance == 0:
            return None
        return self._estimate_for(self.model.a, self.model.b, self.model.c)

    def _estimate_for(
        self, a: np.ndarray, b: np.ndarray, c: np.ndarray
    ) -> GainEstimate | DriveEstimate:
        """The gain's estimate over the linear parts ``(a, b, c)``, or the drive's where the
        settings learn the hysteresis strength too."""
        settings = self.settings
        strength = getattr(settings, "strength_tolerance", 0.0)
        if strength == 0:
            return GainEstimate(a, b, c, tolerance=settings.gain_tolerance, **self._gain_noise())
        return DriveEstimate(
            a,
            b,
            c,
            tolerance=settings.gain_tolerance,
            strength=strength,
            slopes=self.model_slopes(),
            **self._gain_noise(),
        )

    def model_slopes(self) -> tuple[float, float]:
        """The model's nonlinearity's smallest and largest slope dz/du (equivalent V per V,
        :func:`controllers.drive.slope_range`, at 1/240 of the drive range per sample), kept
        by content."""
        nonlinearity = self.model.nonlinearity
        content = getattr(nonlinearity, "content", None)
        step = (nonlinearity.u_range[1] - nonlinearity.u_range[0]) / SLOPE_SAMPLES
        return _slopes_kept.get_or_compute(
            None if content is None else ["slopes", *content(), nonlinearity.u_range, step],
            lambda: slope_range(nonlinearity, step),
        )

    def _gain_noise(self) -> dict[str, float]:
        """The gain estimate's noise: the sensor's standard deviation (the floor of the
        residual's), and the bound of the exact set, the sensor's plus the model's proven
        error bound."""
        return {
            "noise_std": measurement_std(self.settings.measurement_std, self.task),
            "noise_bound": self.task.noise_bound_um + self.model.error_bound_um,
        }

    def _restart_gain(self, x0: np.ndarray, u0: float = 0.0) -> None:
        """The gain back at the model's (1), learned afresh from the model's state ``x0``
        (at rest under the voltage ``u0``, V)."""
        self._g = 1.0
        self._member = 0  # which linear part of the gain estimate the MPC predicts with
        if isinstance(self._gain, DriveEstimate):
            self._gain.reset(x0, u0)
        elif self._gain is not None:
            self._gain.reset(x0)

    @property
    def gain(self) -> float:
        """The plant's gain relative to the model the MPC predicts with now (-; with a learned
        drive, its theta_z, :mod:`controllers.drive`)."""
        return self._g

    @property
    def gain_set(self) -> tuple[float, float]:
        """The gain's 95 % credible set within the settings' ``gain_tolerance`` (-, relative to
        the model)."""
        if self._gain is None:
            return (1.0, 1.0)
        return float(self._gain.low[self._member]), float(self._gain.high[self._member])

    @property
    def set_invalidated_step(self) -> int | None:
        """The step (from 0) of this episode at which the data invalidated the model at the
        sensor's noise bound: no gain in the datasheet's interval, with the model (or any
        member of the set the MPC predicts from), explains every measurement to within the
        bound (the exact sets of :class:`controllers.gain.GainEstimate`). None while some
        does, and without a gain estimate."""
        if self._gain is None or not np.all(self._gain.emptied_at > 0.0):
            return None
        return int(self._gain.emptied_at.max()) - 1
