"""Adaptive MPC over the set of benders the datasheet allows: learn which one from the data.

A bender bought to a datasheet differs from the nominal one in its static gain (free deflection
+-20 %, and the hysteresis strength's +-30 % moves the gain a linear model sees:
:data:`controllers.settings.LEARNED_GAIN_TOLERANCE`), its first resonance (+-20 %) and that
mode's damping (0.01-0.04). The fixed :class:`controllers.mpc.LinearMPC` learns the gain
(:mod:`controllers.gain`); a resonance error it leaves to its observer, and near the
resonance (a 50 Hz reference on a bender whose first mode lies 20 % low) that is its largest
error on the box's corners
(``benchmarks/results/corners.md``, sine-50Hz). :class:`AdaptiveMPC` learns the
resonance and the damping too, and the hysteresis strength (+-30 %, :mod:`controllers.drive`:
each member predicts with its learned drive ``theta_z z + theta_u u`` and inverts that mixed
map), with bounded work per sample.

The set. The identified model's first bending mode is moved over a grid that covers the
datasheet's tolerance box (:func:`controllers.tolerance_box.box_model`: frequency factor
``alpha`` on ``[1 - s, 1 + s]``, damping ratio on ``[zeta_lo, zeta_hi]``, the further modes,
aliases included, moved with it as a stiffness change moves them); with the identified model
itself these are the members. Every member keeps the identified model's orders, so all
share the measured-history realization (state: past deflections and past z) and the observer's
state carries over between them. The grid is fine enough that the plant's mode is never further
from a member than the mode's own half-power bandwidth (:func:`resonance_points`,
:func:`damping_points`).

Which member. Every member runs, from the episode's start, on the z the controller applied,
with its own gain learned (:class:`controllers.gain.GainEstimate` over all members at once: a
few multiply-adds per member and sample), and beside it its drive
(:class:`controllers.drive.DriveEstimate`, which the member predicts with). The gain's misfits
choose the member: the drive's two parameters fit a wrong resonance's phase at a sine's
frequency too, and would keep a wrong member. Each member's misfit is its mean squared residual at
its estimated gain. The MPC predicts with the member in use until the data reject it: a
likelihood-ratio test of the member in use against the best one,
``(misfit_in_use - misfit_best) t / misfit_best > chi2_0.95(2)`` (:data:`SWITCH_CHI2`: two
parameters, frequency and damping, told apart at 95 %), and only when the member in use does
not already explain the data to within the known sensor noise (a chi2 goodness-of-fit test at
95 %, :func:`chi2_upper`): a test repeated at every sample would otherwise, by chance, leave a
model that is as good as the noise allows. The sample counts of both tests are corrected for
the residuals' correlation (:attr:`controllers.gain.GainEstimate.independent_fraction`).

Robust over the set. The data still allow every member the likelihood-ratio test does not
reject (:meth:`AdaptiveMPC.plausible`). When the controller is built, the unconstrained loop of
each member's MPC with each filter of its observer bank is closed around each grid point's
plants, gains matched: its member and, when the task carries the datasheet, its twin moved by
the datasheet's physics (:meth:`AdaptiveMPC.screen_plants`), and the loops' spectral radii are
kept (:meth:`AdaptiveMPC.filter_screen`). A filter whose loop exceeds the sensitivity bound
:data:`controllers.settings.MS_MAX` on its own grid point (its member or that point's twin) is
never used: the margin is what keeps a loop whose drive saturates, which lowers its gain, out
of a limit cycle (:func:`controllers.predictive.screen_bank`). At every sample the bank in use
may select only the filters whose loop is also stable on every grid point the data still
allow, and the MPC swaps only to a member that has such a filter; when the data leave the
member in use without one, it swaps to the best-fitting member that has one. (Nominal margin,
robust stability: the margin asked on every point the data allow would hold, on a 10 Hz sine,
which never narrows the set, the filters that keep it on the whole box all episode, too slow
for a drawn bender's hysteresis: ``benchmarks/results/design_measurements.md``.) At the first
sample that is every member of the box, so the first sample is safe on any bender the
datasheet allows; as the data rule members out, faster filters become allowed and the loop
tends to the one the true plant's model would close.
:meth:`AdaptiveMPC.loop_radii` (each member's prior filter) stays for reports.

Bounded work. Everything a member's MPC needs (condensed prediction, QP matrices, the observer
bank's gains, a QP workspace, the loop radii) is built when the controller is, and the QP
workspaces are set up afresh before each episode, so a swap inside :meth:`act` is a change of
pointers: no Riccati equation, no factorisation, no simulation, no optimisation in the loop.
Per sample the set costs one batched state update and a few vector operations over its members.

The swap is bumpless. Every member is the same ARX structure moved to another resonance and
damping with the identified static gain (:func:`controllers.tolerance_box.box_model` sets it
exactly), so every member's state means the same physical thing: the tip's recent undisturbed
deflections and the recent z in the measured-history realization. The new member's observer
therefore starts from the old one's estimate as it stands (carried to the applied z's scale),
output disturbance included: the total output estimate, the past outputs and the plan are
continuous, and the first plan after the swap differs from the one before only by what the two
models predict differently. Its filters' likelihoods start afresh, since they scored how well
each filter explained the data under the old member. The gain the new member predicts with is
the one it has been learning all along. (Re-deriving the past outputs by running the new member
over the recent inputs from measured outputs, which a set whose members differ in gain would
need, puts the sensor noise of the start and the model's hysteresis error into the state: a
bump of several times the steady error, ``benchmarks/results/design_measurements.md``.)

Each episode starts from the identified model (episodes are independent and reproducible);
``stats.adaptation`` counts the swaps, ``stats.trace`` records the member in use and the set
(the members the test does not reject, and the gain's credible set) over time.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from controllers.base import ControllerStats
from controllers.box_qp import BoxQP
from controllers.condensed import check_well_posed, prediction_matrices
from controllers.drive import DriveEstimate
from controllers.gain import GainEstimate
from controllers.loop import feedback_law, plant_margins, radii_matrix
from controllers.mpc import LinearMPC, MPCSettings, unconstrained_law
from controllers.native import fused_step
from controllers.observer import ObserverBank, make_observer, rescale_states, shift_states
from controllers.prediction import PredictionModel, SteadyStart
from controllers.predictive import filter_margins, task_datasheet_model
from controllers.settings import (
    MS_MAX,
    STRENGTH_TOLERANCE,
    check_settings,
    damping_pair,
    measurement_std,
)
from controllers.task import ControlTask
from controllers.tolerance_box import (
    DAMPING_RANGE,
    RESONANCE_TOLERANCE,
    UnstableFitError,
    Vertex,
    box_model,
)
from identification.arx import ARXModel
from identification.correction import first_mode_pole
from piezo_env.memo import ContentCache

__all__ = [
    "MEMBER_SETS",
    "NORMAL_95",
    "SCREENS_KEPT",
    "SWITCH_CHI2",
    "TRACE_EVERY",
    "AdaptiveMPC",
    "AdaptiveMPCSettings",
    "AdaptiveStats",
    "arx_from_realization",
    "chi2_upper",
    "damping_points",
    "first_damping_ratio",
    "first_resonance_hz",
    "resonance_points",
]

MEMBER_SETS = ("modes", "datasheet")
"""The values of :attr:`AdaptiveMPCSettings.member_set`."""

SWITCH_CHI2 = 5.991464547107979
"""chi2 quantile 0.95 with 2 degrees of freedom (frequency and damping of the first mode)."""

NORMAL_95 = 1.6448536269514722
"""One-sided 95 % quantile of the standard normal distribution."""

TRACE_EVERY = 20
"""Samples between the records of :attr:`AdaptiveStats.trace` (for figures only)."""

SCREENS_KEPT = 8
"""Sets' stability screens kept by content (:meth:`AdaptiveMPC.filter_screen`), one per
identified model and settings. A benchmark worker meets up to six models (three
identification seeds, on the nominal bender and on the bench): 8 keeps them all."""

_screens = ContentCache(SCREENS_KEPT)
_member_sets = ContentCache(SCREENS_KEPT)  # the "modes" sets' members: one per screen
_loop_radii = ContentCache(SCREENS_KEPT)  # :meth:`AdaptiveMPC.loop_radii`, as many
_twin_sets = ContentCache(SCREENS_KEPT)  # the grid points' datasheet twins, as many


@dataclass(frozen=True)
class AdaptiveMPCSettings(MPCSettings):
    """Settings of :class:`AdaptiveMPC`: those of :class:`controllers.mpc.MPCSettings` and

    Attributes
    ----------
    rate_weight : float
        As :class:`controllers.mpc.MPCSettings`'s; its own default, the tuning procedure's
        choice for this controller (:mod:`benchmarks.tuning`): the set learns the resonance,
        so the fixed MPC's gentler law only slows it.
    resonance_tolerance : float
        Relative half-width s of the first resonance the set covers (-), in (0, 1): the
        datasheet's +-20 %.
    damping_range : tuple of float
        (low, high) first-mode damping ratios the set covers (-): the datasheet box's.
    strength_tolerance : float
        As :class:`controllers.mpc.MPCSettings`'s; its own default, the datasheet's +-30 % on
        the hysteresis strength (:data:`STRENGTH_TOLERANCE`): each member learns its drive,
        the gain and the strength together (:mod:`controllers.drive`).
    member_set : str
        How a member is made from the identified model: ``"modes"`` (the default) moves its
        modes (:func:`controllers.tolerance_box.box_model`); ``"datasheet"`` applies the ratio
        by which the datasheet's FE model moves between nominal and vertex, one order more
        (:func:`controllers.tolerance_box.datasheet_model`; needs a task read from a
        ``PiezoBender-v0`` env, which carries the datasheet). The second matches the box's
        benders far better and is not yet the default: with a model identified on another
        hysteresis, the data can rule out the plant's true linear part, and the loop it then
        runs is stable on that part without a margin (``benchmarks/results/corners.md`` and
        ``design_measurements.md``).
    """

    rate_weight: float = 1e-2
    resonance_tolerance: float = RESONANCE_TOLERANCE
    damping_range: tuple[float, float] = DAMPING_RANGE
    strength_tolerance: float = STRENGTH_TOLERANCE
    member_set: str = "modes"

    def __post_init__(self) -> None:
        super().__post_init__()
        check_settings(self, positive=("resonance_tolerance",))
        if not self.resonance_tolerance < 1.0:
            raise ValueError(
                f"resonance_tolerance must be < 1 (relative), got {self.resonance_tolerance!r}"
            )
        object.__setattr__(self, "damping_range", damping_pair("damping_range", self.damping_range))
        if self.gain_tolerance == 0:
            raise ValueError(
                "the adaptive MPC tells its models apart by their misfit at their learned gain: "
                "gain_tolerance must be > 0"
            )
        if self.member_set not in MEMBER_SETS:
            raise ValueError(f"member_set must be one of {MEMBER_SETS}, got {self.member_set!r}")


@dataclass
class AdaptiveStats(ControllerStats):
    """:class:`controllers.base.ControllerStats` plus what the adaptation did.

    Attributes
    ----------
    adaptation : collections.Counter
        ``swaps``: how often the MPC changed the member it predicts with.
    trace : list of tuple
        Every :data:`TRACE_EVERY` samples and at every swap: (step, DC gain (um per
        equivalent V) and first resonance (Hz) of the model in use, the gain's 95 % credible
        set as DC gains (low, high), the first resonances of the members the test does not
        reject (lowest, highest, Hz)).
    """

    adaptation: Counter = field(default_factory=Counter)
    trace: list[tuple[float, ...]] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        """The base summary plus ``"adaptation"`` (the counts)."""
        return {**super().summary(), "adaptation": dict(self.adaptation)}


def arx_from_realization(model: PredictionModel) -> ARXModel:
    """The ARX model whose measured-history realization is ``model``'s linear part.

    Raises
    ------
    ValueError
        If the linear part is not such a realization (e.g. the true plant's modal state
        space of an oracle): the adaptive MPC moves the modes of an identified ARX model.
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
    p = first_mode_pole(arx.poles())
    return math.nan if p is None else float(abs(np.log(p)) / (2.0 * math.pi * arx.dt))


def first_damping_ratio(arx: ARXModel) -> float:
    """Damping ratio (-) of the model's first bending mode, ``-Re ln p / |ln p|``; NaN without
    a complex pair."""
    p = first_mode_pole(arx.poles())
    return math.nan if p is None else float(-np.log(p).real / abs(np.log(p)))


def chi2_upper(dof: float) -> float:
    """The 95 % quantile of chi2 with ``dof`` degrees of freedom (Wilson-Hilferty: within
    1 % for dof >= 2), so that a sum of ``dof`` squared noise samples over the noise
    variance exceeds it with probability 5 %."""
    dof = max(dof, 1.0)
    spread = 2.0 / (9.0 * dof)
    return dof * (1.0 - spread + NORMAL_95 * math.sqrt(spread)) ** 3


def resonance_points(tolerance: float, damping_low: float) -> np.ndarray:
    """Frequency factors of the set's grid over ``[1 - s, 1 + s]`` (-).

    Evenly spaced, with half a step at most the half-power bandwidth ``2 zeta_lo`` (relative)
    of the lightest-damped mode: ``n - 1 >= s / (2 zeta_lo)`` steps, and the nominal (1) on the
    grid (an even number of steps).
    """
    steps = math.ceil(tolerance / (2.0 * damping_low) - 1e-9)
    steps += steps % 2
    return np.linspace(1.0 - tolerance, 1.0 + tolerance, steps + 1)


def damping_points(low: float, high: float) -> np.ndarray:
    """Damping ratios of the set's grid over ``[low, high]`` (-): geometric, neighbours at most
    a factor 2 apart (a resonance peak 1 / (2 zeta) then lies within 3 dB of a member's)."""
    if high == low:
        return np.array([low])
    steps = math.ceil(math.log2(high / low) - 1e-9)
    return np.geomspace(low, high, steps + 1)


def _set_members(arx: list[ARXModel]) -> dict[str, Any]:
    """The members ``arx`` of a set with what the controller reads of them: their state-space
    matrices, first resonances (Hz) and static gains."""
    return {
        "arx": arx,
        "matrices": [m.state_space_matrices()[:3] for m in arx],
        "resonances_hz": np.array([first_resonance_hz(m) for m in arx]),
        "static_gains": np.array([m.static_gain() for m in arx]),
    }


@dataclass
class _Member:
    """One model of the set and what the MPC needs to predict with it."""

    arx: ARXModel
    model: PredictionModel
    phi: np.ndarray
    gamma: np.ndarray
    hessian: np.ndarray
    q_matrix: np.ndarray
    unconstrained: np.ndarray
    observer: Any
    qp: BoxQP | None = None


class AdaptiveMPC(LinearMPC):
    """Linear MPC that learns which bender of the datasheet's set it controls (module
    docstring).

    ``AdaptiveMPC(model, task, settings=None, *, name="mpc-adaptive")`` with
    :class:`AdaptiveMPCSettings`; the model must be an identified one (its linear part an ARX
    model, :func:`arx_from_realization`).
    """

    Settings = AdaptiveMPCSettings
    name = "mpc-adaptive"
    stats_type = AdaptiveStats
    _selects = True

    def __init__(
        self,
        model: PredictionModel,
        task: ControlTask,
        settings: AdaptiveMPCSettings | None = None,
        *,
        name: str | None = None,
    ) -> None:
        settings = settings or AdaptiveMPCSettings()
        self._offline_arx = arx = arx_from_realization(model)
        zeta = first_damping_ratio(arx)
        if not math.isfinite(zeta):
            raise ValueError("the identified linear part has no bending mode to adapt")
        self._grid = [(1.0, zeta)] + [
            (float(alpha), float(z))
            for alpha in resonance_points(settings.resonance_tolerance, settings.damping_range[0])
            for z in damping_points(*settings.damping_range)
        ]
        self.fit_error: float | None = None
        """The datasheet set's largest relative fit error (-), None for the modes' set."""
        if settings.member_set == "datasheet":
            self._member_arx = self._datasheet_members(arx, task)
            a, b, c, _ = self._member_arx[0].state_space_matrices()
            model = dataclasses.replace(model, a=a, b=b, c=c)
            members = _set_members(self._member_arx)
        else:
            # The ARX part is read from the model's matrices, and the members are moved from it
            # to the grid's points: a pure function of both, kept by content.
            grid = self._grid
            members = _member_sets.get(
                [model.a, model.b, model.c, model.dt, grid],
                lambda: _set_members(
                    [arx] + [box_model(arx, Vertex(1.0, alpha, z)) for alpha, z in grid[1:]]
                ),
            )
            self._member_arx = members["arx"]
        self._member_models = [
            dataclasses.replace(model, a=a, b=b, c=c) for a, b, c in members["matrices"]
        ]
        # Read once: the trace and the properties must not find poles inside the loop.
        self._member_hz = members["resonances_hz"]
        self._member_gains = members["static_gains"]
        self._check_shared_state()
        self.twin_class: str | None = None
        """The model class of the grid points' twins (``"datasheet"`` or ``"modes"``), None
        when the screen has no second class (a task without a datasheet)."""
        self._twins = self._twin_models(arx, task, settings)
        self._members: list[_Member] = []
        self._bindings: list[np.ndarray] = []
        self._plausible_key: bytes | None = None
        self._noise_variance = measurement_std(settings.measurement_std, task) ** 2
        """The sensor noise's variance the tests use (um^2)."""
        super().__init__(model, task, settings, name=name)

    # -- the set --------------------------------------------------------------------------------

    def _datasheet_members(self, arx: ARXModel, task: ControlTask) -> list[ARXModel]:
        """The identified model, padded one order, and each grid point's
        :func:`controllers.tolerance_box.datasheet_model` of the same order."""
        if task.datasheet is None or task.damping_ratio is None:
            raise ValueError(
                "member_set='datasheet' needs the bender's datasheet, which a task read from a "
                "PiezoBender-v0 env carries (ControlTask.from_env); use member_set='modes'"
            )
        order = max(arx.na, arx.nb) + 1
        first = ARXModel(
            np.pad(arx.a, (0, order - arx.na)),
            np.pad(arx.b, (0, order - arx.nb)),
            dt=arx.dt,
            noise_bound=arx.noise_bound,
            method=arx.method,
        )
        members, errors = [first], []
        for point in self._grid[1:]:
            member, error = task_datasheet_model(arx, task, Vertex(1.0, *point), order)
            # The same static gain to the last bit: a swap carries the state over.
            member = ARXModel(
                member.a,
                member.b * (first.static_gain() / member.static_gain()),
                dt=arx.dt,
                noise_bound=arx.noise_bound,
                method=member.method,
            )
            members.append(member)
            errors.append(error)
        self.fit_error = max(errors)
        return members

    def _twin_models(
        self, arx: ARXModel, task: ControlTask, settings: AdaptiveMPCSettings
    ) -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
        """Each grid point's linear part (a, b, c) in the model class the members are not in:
        for the ``"modes"`` set the datasheet's physics
        (:func:`controllers.tolerance_box.datasheet_model`, when the task carries the
        datasheet; None where the fit is unstable), for the ``"datasheet"`` set the modes
        moved (:func:`controllers.tolerance_box.box_model`). Static gains as the members'.

        Why. The members move only the first mode of the identified model; a bender at the same
        grid point also moves its other modes, aliases included, and with them its damping
        (the env's stiffness-proportional damping). On the PL128 at 2 kHz, with free
        deflection x1.2, resonance x0.91 and damping 0.01, the data narrowed the set to one
        member (resonance x0.88), and the bank's fastest filter allowed there (margin 0.61 on
        that member) closed a loop with spectral radius 1.13 on that point's datasheet twin
        and 1.15 on the bender's: a half-stroke 337 Hz sine rang it into a limit cycle
        between the drive's ends (32 % of the stroke), which went on after the reference
        stopped. A filter the set's loop may use is screened on both classes."""
        grid = self._grid
        if settings.member_set == "datasheet":
            self.twin_class = "modes"
            moved = [arx] + [box_model(arx, Vertex(1.0, alpha, z)) for alpha, z in grid[1:]]
            return [m.state_space_matrices()[:3] for m in moved]
        if task.datasheet is None or not task.damping_ratio:
            return [None] * len(grid)
        self.twin_class = "datasheet"
        order = max(arx.na, arx.nb) + 1

        def compute() -> list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]:
            twins: list[tuple[np.ndarray, np.ndarray, np.ndarray] | None] = []
            for point in grid:
                try:
                    twin, _ = task_datasheet_model(arx, task, Vertex(1.0, *point), order)
                except UnstableFitError:  # the point is screened on its member (counted)
                    twins.append(None)
                    continue
                twins.append(twin.state_space_matrices()[:3])
            return twins

        parts = [arx.a, arx.b, arx.dt, grid, repr(task.datasheet), task.damping_ratio]
        return _twin_sets.get([*parts, task.n_elements], compute)

    def _check_shared_state(self) -> None:
        """The swap carries the observer's state over (module docstring), which needs every
        member's state to mean the same: one realization (the same rows of A and B below the
        first, the same C) and the same static gain (to 1e-9 relative: the gain is set last
        by :func:`controllers.tolerance_box.box_model`, exact to rounding)."""
        first = self._member_models[0]
        for grid, member in zip(self._grid[1:], self._member_models[1:], strict=True):
            same = (
                member.a.shape == first.a.shape
                and np.array_equal(member.a[1:], first.a[1:])
                and np.array_equal(member.b[1:], first.b[1:])
                and np.array_equal(member.c, first.c)
            )
            if not same:
                raise ValueError(
                    f"the set's member {grid} (frequency factor, damping ratio) has another "
                    "state realization than the identified model's; a swap could not carry "
                    "the observer's state over"
                )
        gains = self._member_gains
        if np.max(np.abs(gains - gains[0])) > 1e-9 * abs(gains[0]):
            raise ValueError(
                "the set's members differ in static gain; a swap could not carry the "
                "observer's state over"
            )

    def _set_up(self) -> None:
        super()._set_up()
        if self._members:
            return
        offline = _Member(
            self._member_arx[0],
            self.model,
            self._phi,
            self._gamma,
            self._hessian,
            self._q_matrix,
            self._unconstrained,
            self.observer,
        )
        pairs = zip(self._member_models[1:], self._member_arx[1:], strict=True)
        self._members = [offline, *(self._member(m, a) for m, a in pairs)]
        self._radii = self.loop_radii()
        self._filter_radii, self._filter_margins = self.filter_screen()
        # Per grid point, which (member, filter) loops may run on it: (K point, K, F),
        # so that the set's test reads contiguous blocks (:meth:`_allow`).
        self._robust_on = np.ascontiguousarray(np.moveaxis(self._robust(), 2, 0))
        fused = self._fused
        if fused is not None:
            # Read once, so that a swap writes the compiled step's table by one slice.
            self._bindings = [
                fused.bank_addresses(
                    m.observer,
                    m.unconstrained,
                    self._vector,
                    self._lower,
                    self._upper,
                    m.q_matrix,
                )
                for m in self._members
            ]
            scalars = fused.scalars
            scalars[fused_step.S_NOISE_VARIANCE] = self._noise_variance
            scalars[fused_step.S_SWITCH_CHI2] = SWITCH_CHI2
            scalars[fused_step.S_NORMAL_95] = NORMAL_95

    def _screen(self, observer: Any, law: tuple[np.ndarray, float]) -> dict[str, Any]:
        """The set screens its banks itself, as the data narrow it (:meth:`_allow`)."""
        robust = self._robust()  # (member, filter, grid point)
        return {
            "applied": True,
            "dynamic": True,
            "filters": int(robust.shape[1]),
            "filters_kept_at_start": [int(n) for n in np.all(robust, axis=2).sum(axis=1)],
            "ms_max": MS_MAX,
            "twins": self.twin_class,
            "twins_missing": int(sum(t is None for t in self._twins)),
        }

    def _robust(self) -> np.ndarray:
        """(K, F, K): the loop of member k's MPC with filter f keeps the modulus margin
        1 / :data:`MS_MAX` on its own grid point and is stable on grid point p's plants
        (member and twin; :meth:`filter_screen`)."""
        return self._filter_radii < 1.0

    def screen_plants(self) -> tuple[list[tuple[np.ndarray, np.ndarray, np.ndarray]], list[int]]:
        """The linear parts (a, b, c) the filters are screened on, gains matched: the K
        members, then the grid points' twins in the other model class (:meth:`_twin_models`;
        none where a point has none); and for each grid point the index of its twin in that
        list (its member's where it has none)."""
        plants = [(m.model.a, m.model.b, m.model.c) for m in self._members]
        twin_of = []
        for index, twin in enumerate(self._twins):
            if twin is not None:
                plants.append(twin)
            twin_of.append(index if twin is None else len(plants) - 1)
        return plants, twin_of

    def filter_screen(self) -> tuple[np.ndarray, np.ndarray]:
        """Each member's MPC with each filter of its bank: the spectral radius (-) of its loop
        closed around each grid point's plants (:meth:`screen_plants`: the member and its twin,
        the larger of the two), (K, F, K); and its modulus margin (-) on its own grid point
        (the smaller on its member and its twin, 0 where either loop is unstable), (K, F). A
        filter whose margin there is
        below 1 / :data:`controllers.settings.MS_MAX` is never selected (radius infinite).

        Most of the controller's construction (K x F x 2K closed loops); kept by the content
        of its inputs (:mod:`piezo_env.memo`), so the same set built again screens once."""
        plants, twin_of = self.screen_plants()
        count = len(self._members)
        banks = [(m, m.observer) for m in self._members]
        gains = [
            np.atleast_2d(b.gains if isinstance(b, ObserverBank) else b.gain) for _, b in banks
        ]

        def compute() -> tuple[np.ndarray, np.ndarray]:
            radii_out, margins_out = [], []
            for index, ((member, bank), filters) in enumerate(zip(banks, gains, strict=True)):
                law = feedback_law(member.hessian, member.q_matrix, bank.a_aug.shape[0])
                # On its member: the sweep the description of this member's loop reads too.
                margins = filter_margins(bank, filters, law)
                loop = (bank.a_aug, bank.b_aug, bank.c_aug)
                if twin_of[index] != index:  # and on its twin, 0 where that loop is unstable
                    twin = [plants[twin_of[index]]]
                    on_twin = plant_margins(*loop, filters, *law, twin)[:, 0]
                    stable = radii_matrix(*loop, filters, *law, twin)[:, 0] < 1.0
                    margins = np.minimum(margins, np.where(stable, on_twin, 0.0))
                within = margins >= 1.0 / MS_MAX
                radii = np.full((len(filters), len(plants)), np.inf)
                if within.any():
                    radii[within] = radii_matrix(*loop, filters[within], *law, plants)
                radii_out.append(np.maximum(radii[:, :count], radii[:, twin_of]))
                margins_out.append(margins)
            return np.array(radii_out), np.array(margins_out)

        parts: list[Any] = [MS_MAX, plants, twin_of]
        for (member, bank), filters in zip(banks, gains, strict=True):
            parts += [member.hessian, member.q_matrix, bank.a_aug, bank.b_aug, bank.c_aug]
            parts += [filters, bank.n]
        return _screens.get(parts, compute)

    def _allow_bank(self, plausible: np.ndarray) -> None:
        """Narrow the in-use member's bank to its row of the allowed filters (or, when its row
        is empty, to one filter: the one of the smallest worst radius on ``plausible``; when
        none keeps the margin on its own point, the one of the largest margin there; when none
        closes a stable loop there, the bank's fallback (the least process noise); counted in
        ``stats.adaptation["no_stable_filter"]``). Reached only when no member has a usable
        filter for the set (:meth:`_select` swaps otherwise), or at an episode's start when
        the identified member has none for the whole box (none of the catalogue's models)."""
        bank = self.observer
        if isinstance(bank, ObserverBank):
            row = self._allowed[self._member]
            if not row.any():
                worst = self._filter_radii[self._member][:, plausible].max(axis=1)
                row = np.zeros(len(worst), dtype=bool)
                margins = self._filter_margins[self._member]
                if np.isfinite(worst.min()):
                    row[int(np.argmin(worst))] = True
                elif margins.max() > 0.0:  # none keeps the margin on its own point
                    row[int(np.argmax(margins))] = True
                else:  # none closes a stable loop there: the bank's own fallback
                    row[bank.fallback] = True
                self.stats.adaptation["no_stable_filter"] += 1
            bank.allow(row)

    def _member(self, model: PredictionModel, arx: ARXModel) -> _Member:
        samples = self.prediction_samples
        phi, gamma = prediction_matrices(model.a, model.b, model.c_tracked, samples)
        check_well_posed(self._blocked(gamma), self.settings.rate_weight, 1.0, name=self.name)
        hessian, q_matrix = self._qp_matrices(phi, gamma)
        unconstrained = unconstrained_law(hessian, q_matrix)
        observer = make_observer(model, self.task, self.settings)
        return _Member(arx, model, phi, gamma, hessian, q_matrix, unconstrained, observer)

    def _fused_addresses(self) -> np.ndarray:
        """The member in use's table entries, read when the set was built."""
        if not self._bindings:  # while the set is built (LinearMPC._set_up)
            return super()._fused_addresses()
        return self._bindings[self._member]

    def _gain_estimate(self) -> GainEstimate | DriveEstimate:
        models = self._member_models
        return self._estimate_for(
            np.array([m.a for m in models]),
            np.array([m.b[:, 0] for m in models]),
            np.array([m.c[0] for m in models]),
        )

    def _use(self, index: int) -> None:
        """Predict with member ``index`` (pointers only)."""
        member = self._members[index]
        self._member = index
        self.model, self._phi, self._gamma = member.model, member.phi, member.gamma
        self._hessian, self._q_matrix = member.hessian, member.q_matrix
        self._unconstrained, self.observer = member.unconstrained, member.observer
        if member.qp is not None:
            self._qp = member.qp
        if getattr(self, "_fused", None) is not None:
            # The gain estimate's arrays are every member's: only the model in use changes.
            self._bind_fused_model()

    @property
    def arx(self) -> ARXModel:
        """The ARX linear part in use (z in equivalent V -> um), without the learned gain."""
        return self._member_arx[self._member]

    @property
    def dc_gain(self) -> float:
        """DC gain of the model in use, learned gain included (um per equivalent V; with a
        learned drive, the gain estimated beside it: the gain a linear model of the network's
        z sees, which theta_z alone is not)."""
        gain = self._g if self._mix is None else float(self._gain.value[self._member])
        return float(self._member_gains[self._member]) * gain

    @property
    def resonance_hz(self) -> float:
        """First bending mode of the linear part in use (Hz), :func:`first_resonance_hz`."""
        return float(self._member_hz[self._member])

    def plausible(self) -> np.ndarray:
        """Indices of the members the likelihood-ratio test does not reject against the best
        one (the set the data still allow)."""
        gain = self._gain
        misfit = gain.misfit
        index = int(misfit.argmin())
        best = float(misfit[index])
        variance = max(best, self._noise_variance)
        samples = gain.count * gain.independent_fraction_of(index)
        return np.flatnonzero((misfit - best) * samples / variance <= SWITCH_CHI2)

    # -- episode --------------------------------------------------------------------------------

    def _reset(self, observation: np.ndarray | None) -> None:
        if self._members:
            self._use(0)
        self._step = 0
        super()._reset(observation)

    def _start(self, start: SteadyStart) -> None:
        super()._start(start)
        # Every member's QP set up afresh (as the fixed MPC's): no step size or duals carry
        # over between episodes, and no set-up is left for the loop.
        for index, member in enumerate(self._members):
            member.qp = self._qp if index == self._member else self._setup_solver(member.hessian)
        self._narrow(np.arange(len(self._members)))
        self._trace()

    def _narrow(self, plausible: np.ndarray, *, bank: bool = True) -> None:
        """The data now allow the members ``plausible``: the filters each member's loop may
        use (K, F: stable on every one of them and on their twins), the
        members the MPC may swap to, and the compiled step's copy of both
        (:mod:`controllers.native.fused_step` tests with them); with ``bank``, the in-use
        member's bank is narrowed too (:meth:`_allow_bank`)."""
        if plausible.size == 0:  # every misfit NaN: the gain estimate has failed
            raise RuntimeError(f"{self.name}: no member of the set fits the data (NaN misfits)")
        self._plausible_key = plausible.tobytes()
        self._allowed = np.logical_and.reduce(self._robust_on[plausible], axis=0)
        self._swappable = np.flatnonzero(self._allowed.any(axis=1))
        if bank:
            self._allow_bank(plausible)
        fused = self._fused
        if fused is not None:
            fused.plausible[:] = 0.0
            fused.plausible[plausible] = 1.0
            fused.allowed[:] = 0.0
            fused.allowed[self._swappable] = 1.0

    def _act(self, observation: np.ndarray) -> float:
        u = super()._act(observation)
        self._record()
        return u

    def _act_fused(self, observation: np.ndarray) -> float:
        u = super()._act_fused(observation)
        self._record()
        return u

    def _record(self) -> None:
        """Count the sample, and trace."""
        self._step += 1
        if self._step % TRACE_EVERY == 0:
            self._trace()

    def _select(self) -> None:
        """Narrow the banks to what the data allow, and swap to the best member when the tests
        reject the one in use or the set leaves it no filter it may use (module
        docstring; the compiled step runs the same tests and calls this whenever the set
        changes or the tests may swap)."""
        plausible = self.plausible()
        gain = self._gain
        misfit = gain.misfit
        if plausible.tobytes() != self._plausible_key:
            self._narrow(plausible, bank=False)
            if not self._allowed[self._member].any() and self._swappable.size:
                # The member in use has no filter whose loop is stable on what the data now
                # allow: predict with the best-fitting member that has one.
                allowed = self._swappable
                self._swap(int(allowed[misfit[allowed].argmin()]), plausible)
                return
            self._allow_bank(plausible)
        noise = self._noise_variance
        member = self._member
        in_use = gain.count * gain.independent_fraction_of(member)
        if misfit[member] * in_use / noise <= chi2_upper(in_use):
            return  # the model in use explains the data to within the sensor noise
        # Only members with a filter whose loop is stable on every point still allowed.
        allowed = self._swappable
        if allowed.size == 0:
            return
        best = int(allowed[misfit[allowed].argmin()])
        if best == member:
            return
        variance = max(float(misfit[best]), noise)
        samples = gain.count * gain.independent_fraction_of(best)
        if (misfit[member] - misfit[best]) * samples / variance > SWITCH_CHI2:
            self._swap(best, plausible)

    def _swap(self, index: int, plausible: np.ndarray | None = None) -> None:
        """Predict with member ``index`` from now on (see the module docstring); ``plausible``
        is :meth:`plausible` now where the caller has it, for the trace."""
        old = self.observer
        # Only the estimate carried over is rescaled (to the applied z's scale); its C x is
        # one exact product (the realization's output row is [1, 0, ...]), so it is the
        # same number the whole bank's rescale gives.
        estimate = old.estimate[None].copy()
        if self._mix is not None:  # to the drive (1, 0): x moved by the model's states' change
            xz, xu = self._gain.states(self._member)
            shift_states(estimate, old.c_aug, old.n, (1.0 - self._g) * xz - self._b * xu)
            self._b = 0.0
            self._mix.set_parameters((1.0, 0.0))
        else:
            rescale_states(estimate, old.c_aug, old.n, 1.0 / self._g)
        estimate = estimate[0]
        self._plan = self._plan / self._g
        self._use(index)
        self._g = 1.0
        self._z_prev = self._z_applied
        if self._slew_step is not None:
            self._qp.set_rate(self._rate())
        observer = self.observer
        if isinstance(observer, ObserverBank):
            row = self._allowed[index]
            selected = old.selected if row[old.selected] else int(np.flatnonzero(row)[0])
            observer.allow(row)
            observer.reset(estimate, selected=selected)
            if old.runaway_at is not None:
                observer.fall_back(old.runaway_at)
        else:
            observer.reset(estimate)
        self.stats.adaptation["swaps"] += 1
        self._trace(plausible)

    def _trace(self, plausible: np.ndarray | None = None) -> None:
        """Record the member in use and the set (``plausible``: :meth:`plausible` when the
        caller has it)."""
        gain = self._gain
        index, base = self._member, float(self._member_gains[self._member])
        if gain.count == 0:
            resonances = self._member_hz
        else:
            resonances = self._member_hz[self.plausible() if plausible is None else plausible]
        self.stats.trace.append(
            (
                self._step,
                self.dc_gain,
                self.resonance_hz,
                base * float(gain.low[index]),
                base * float(gain.high[index]),
                float(np.min(resonances)),
                float(np.max(resonances)),
            )
        )

    # -- analysis -------------------------------------------------------------------------------

    def loop_radii(self) -> np.ndarray:
        """Spectral radius (-) of the unconstrained loop of each member's MPC (with its bank's
        prior filter, or its single filter) around each member, gains matched: (K, K), row =
        the MPC's member, column = the plant's; below 1 where that loop is stable.

        Kept by content as :meth:`filter_screen` is (a closed loop per member pair)."""
        plants = [(m.model.a, m.model.b, m.model.c) for m in self._members]
        loops = []
        for member in self._members:
            bank = member.observer
            filter_gain = bank.gains[bank.prior] if isinstance(bank, ObserverBank) else bank.gain
            loops.append((member, bank, filter_gain))

        def compute() -> np.ndarray:
            radii = []
            for member, bank, filter_gain in loops:
                law = feedback_law(member.hessian, member.q_matrix, bank.a_aug.shape[0])
                radii.append(
                    radii_matrix(bank.a_aug, bank.b_aug, bank.c_aug, filter_gain, *law, plants)
                )
            return np.concatenate(radii)

        parts: list[Any] = []
        for member, bank, filter_gain in loops:
            parts += [member.hessian, member.q_matrix, bank.a_aug, bank.b_aug, bank.c_aug]
            parts += [filter_gain, member.model.a, member.model.b, member.model.c]
        return _loop_radii.get(parts, compute)

    def describe(self) -> dict:
        """The linear MPC's description plus the set: its members' first resonances and
        damping ratios, the worst spectral radius of :meth:`loop_radii`, and how many members
        have no filter they may use on the whole box (:meth:`filter_screen`)."""
        out = super().describe()
        out["settings"] = asdict(self.settings)
        out["adaptation"] = {
            "offline_dc_gain": self._offline_arx.static_gain(),
            "offline_resonance_hz": first_resonance_hz(self._offline_arx),
            "members": len(self._members),
            "member_resonances_hz": sorted(
                {round(first_resonance_hz(a), 3) for a in self._member_arx}
            ),
            "member_damping_ratios": sorted(
                {round(first_damping_ratio(a), 5) for a in self._member_arx}
            ),
            "identified_loop_radius": float(np.max(self._radii[0])),
            "worst_loop_radius": float(np.max(self._radii)),
            "unstable_pairs": int(np.sum(self._radii >= 1.0)),
            "member_set": self.settings.member_set,
            "datasheet_fit_error": self.fit_error,
            "members_without_a_filter_for_the_whole_box": int(
                np.sum(~np.any(np.all(self._robust(), axis=2), axis=1))
            ),
        }
        return out
