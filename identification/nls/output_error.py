"""Output-error refinement of the Hammerstein model (step e' of :func:`identify`).

Step e fits the network to ``z_hat``, the hidden signal recovered by inverting the ARX model
(eq. 25). That target carries the equation error filtered by ``1/B``, and its loss weighs an
error in ``z`` the same at every frequency, although the deflection sees it through the linear
part: an error at 150 Hz reaches the tip amplified by the first bending mode (about 160 Hz on a
PL140), an error at 1 Hz at the static gain. The linear part, for its part, was fitted on the
small PRBS alone. Step e' therefore continues from both and minimises the error that matters,
the free-run output error of the whole model on every record,

    J(theta, a, b) = sum_t (y_t - (G_ab * NLS_theta(u))_t)^2,

where ``G_ab = B(q) / (1 - A(q))`` is the ARX part and ``*`` the free run from rest. With white
sensor noise on ``y`` this is the maximum-likelihood (prediction-error) estimate of the
Hammerstein output-error model, the standard refinement of a two-step Hammerstein estimate
(Ljung, *System Identification*, 2nd ed., sections 5.2 and 7.3; Bai, Automatica 34 (3), 1998).

The free run is the ARX recursion itself, differentiated by its exact adjoint (a filter run
backwards in time; :class:`identification.nls.free_run.FreeRun`): a pass costs O(T (na +
nb)), a few times less than the product of spectra on a zero-padded FFT grid this module used
before, which cost O(T log T) per pass and dominated the refinement's time
(``benchmarks/results/design_measurements.md``). Only a linear part so far beyond the stability
boundary that its free run overflows, which the joint stage's line search may probe, is still
evaluated on that grid, to give the line search a finite value. A network
whose input is held between samples (play and Bouc-Wen features under a held voltage) is
evaluated once per run of equal features.

The split of the gain between the two blocks is not identifiable from input-output data (``k``
times the network and ``1/k`` times ``B`` give the same output); :func:`move_gain` restores the
scale convention afterwards (unit small-signal gain of the network on the PRBS record).
Full-batch L-BFGS in float64 with one torch thread, from the step e and b' estimates:
deterministic. With play features and ``radius_iterations``, a first stage learns the play
radii with the network (:mod:`identification.nls.play_radii`), and the network and joint
stages run at the learned radii. Each stage stops when the data can no longer tell its
iterations apart (:data:`STOP_FRACTION`), or at its cap.

Every sample of every record weighs the same, as the likelihood under one sensor noise asks.
Another weighting of the records (a per-record error variance concentrated out,
``sum_r N_r log SSE_r``, which weighs the small PRBS up, or a fixed factor on one record) is the
likelihood of a noise that differs from record to record, which records of one sensor do not
have; the weightings compared in closed loop are in ``benchmarks/results/design_measurements.md``.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np

from identification.arx import ARXModel
from identification.features import (
    FeatureMap,
    PlayFeatures,
    RatePlayFeatures,
    sequence_features,
)
from identification.nls.free_run import FreeRun
from identification.nls.network import NLS
from identification.nls.optimisation import torch_threads
from identification.nls.play_radii import (
    PlayRadiusFunction,
    RatePlayFunction,
    radii_from_coordinates,
    radius_coordinates,
    rate_play_outputs,
    rate_play_runs,
)
from identification.nls.torch_module import TorchNLS, load_torch

__all__ = [
    "NlsOutputErrorFit",
    "free_run_rms",
    "move_gain",
    "rate_is_determined",
    "refine_nls_output_error",
]


@dataclass(frozen=True)
class NlsOutputErrorFit:
    """Result of :func:`refine_nls_output_error`.

    Attributes
    ----------
    nls : NLS
        The refined network (same features, widths and input range as the start).
    arx : ARXModel
        The refined linear part, its ``noise_bound`` the largest equation error over the
        records (the start's when ``refine_linear`` was False or its joint stage was refused).
    rms_before, rms_after : float
        Free-run RMS output error over all the records, um, at the start and at the end (by the
        ARX recursion).
    iterations, evaluations : int
        L-BFGS iterations and objective evaluations over the stages (properties, from
        ``stages``).
    wall_time_s : float
        Time of the refinement, s.
    stages : tuple of dict
        Per stage (radii, when learned; network; then network and linear part):
        ``iterations``, ``evaluations``, ``stopped`` (``"tolerance"``, ``"converged"`` or
        ``"cap"``, see :func:`_lbfgs`) and ``capped`` (stopped at the iteration or evaluation
        cap).
    linear_note : str or None
        Why the joint stage's linear part was not kept (unstable, or no longer minimum-phase
        when the start was); its network-only stage is returned then. None otherwise.
    """

    nls: NLS
    arx: ARXModel
    rms_before: float
    rms_after: float
    wall_time_s: float
    stages: tuple[dict, ...] = ()
    linear_note: str | None = None

    @property
    def iterations(self) -> int:
        """L-BFGS iterations over the stages."""
        return sum(stage["iterations"] for stage in self.stages)

    @property
    def evaluations(self) -> int:
        """Objective and gradient evaluations over the stages (line search included)."""
        return sum(stage["evaluations"] for stage in self.stages)


def free_run_rms(
    nls: NLS, arx: ARXModel, records: Sequence[tuple[np.ndarray, np.ndarray]]
) -> float:
    """Free-run RMS output error (um) of ``NLS -> ARX`` over ``records`` of (u V, y um).

    Each record starts at rest and is aligned as by :func:`identification.experiment.collect`
    (``y[t]`` before ``u[t]`` is applied), so the model output is ``arx.simulate(nls(u))``.
    """
    squared, count = 0.0, 0
    for u, y in records:
        error = arx.simulate(nls.evaluate(u)) - np.asarray(y, dtype=np.float64)
        squared += float(np.add.reduce(error * error))  # not BLAS: its sum order varies
        count += error.size
    return float(np.sqrt(squared / count))


def move_gain(nls: NLS, arx: ARXModel, gain: float) -> tuple[NLS, ARXModel]:
    """Move the gain ``gain`` from the network to the linear part: ``z' = z / gain``,
    ``B' = gain B``. The model's output is unchanged (up to rounding)."""
    if not np.isfinite(gain) or gain <= 0:
        raise ValueError(f"gain must be finite and positive, got {gain}")
    params = nls.arrays()
    params["z_mean"] = params["z_mean"] / gain
    params["z_scale"] = params["z_scale"] / gain
    scaled = NLS(nls.feature_map, params, u_range=nls.u_range, training=nls.training)
    linear = ARXModel(
        arx.a,
        arx.b * gain,
        noise_bound=arx.noise_bound,
        dt=arx.dt,
        method=arx.method,
    )
    return scaled, linear


def refine_nls_output_error(
    nls: NLS,
    arx: ARXModel,
    records: Sequence[tuple[np.ndarray, np.ndarray]],
    *,
    max_iterations: int = 100,
    refine_linear: bool = True,
    radius_iterations: int = 0,
    learn_rate: bool = False,
    num_threads: int = 1,
) -> NlsOutputErrorFit:
    """Refine ``NLS -> arx`` by minimising its free-run output error on ``records``.

    Parameters
    ----------
    nls : NLS
        The starting network (step e), left unchanged.
    arx : ARXModel
        The starting linear part z (equivalent V) -> y (um); must be stable.
    records : sequence of (u, y)
        Input (V) and measured output (um) records, each from rest, aligned as by
        :func:`identification.experiment.collect`.
    max_iterations : int
        L-BFGS iterations at most (>= 1) of each stage: the network alone, then (with
        ``refine_linear``) the network and the ARX coefficients together.
    refine_linear : bool
        Refine the ARX coefficients too (default); False holds the linear part fixed.
    radius_iterations : int
        With play features: L-BFGS iterations at most of a first stage that learns the play
        radii and the network together, the linear part held (:mod:`identification.nls.
        play_radii`); the later stages run at the learned radii. 0 (default) keeps the radii.
    learn_rate : bool
        With ``radius_iterations``: the radius stage also learns a rate constant c >= 0 (s) and
        the network then runs on rate-dependent plays of radii ``r_i + c |u_t-1 - u_t-2| / dt``
        (:class:`identification.features.RatePlayFeatures`, ``dt`` the linear part's).
    num_threads : int
        Torch threads during the refinement (the previous setting is restored).

    Returns
    -------
    NlsOutputErrorFit
        The refined network and linear part, and the RMS output error before and after. The
        gain split between them is the optimiser's: see :func:`move_gain`.

    Raises
    ------
    ValueError
        On an unstable linear part, no records, mismatched or non-finite records, or a
        non-positive ``max_iterations``.
    """
    if int(max_iterations) != max_iterations or max_iterations < 1:
        raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
    if not arx.is_stable():
        raise ValueError(
            "the linear part is unstable: its free run diverges, so there is no output error "
            "to minimise; identify a stable ARX model first"
        )
    if int(radius_iterations) != radius_iterations or radius_iterations < 0:
        raise ValueError(f"radius_iterations must be an integer >= 0, got {radius_iterations!r}")
    if learn_rate and not radius_iterations:
        raise ValueError("learn_rate needs radius_iterations > 0: the rate is learned there")
    data = _check_records(records)
    torch = load_torch()
    start = time.perf_counter()
    feature_map = nls.feature_map
    with torch_threads(num_threads):
        outputs = [torch.from_numpy(y) for _, y in data]
        grids = [FreeRun(y.size, arx.na, arx.nb, torch) for _, y in data]
        count = sum(y.size for _, y in data)
        module = TorchNLS.from_params(nls.arrays())
        a = torch.tensor(arx.a, dtype=torch.float64)
        b = torch.tensor(arx.b, dtype=torch.float64)
        stages = []
        if radius_iterations and isinstance(feature_map, PlayFeatures):
            targets = (outputs, grids, count)
            learn = partial(_learn_rate_radii, dt=arx.dt) if learn_rate else _learn_radii
            feature_map, stage = learn(
                feature_map, module, data, targets, (a, b), radius_iterations
            )
            stages.append(stage)
        # The features and their normalization stay fixed from here. Consecutive samples with
        # equal features (a held input leaves a play or Bouc-Wen state where it is) give the
        # network the same output: it is evaluated once per such run and spread over the run.
        inputs = []
        with torch.no_grad():
            for u, _ in data:
                rows, index = distinct_rows(
                    sequence_features(feature_map, u, feature_map.initial_state())[0]
                )
                inputs.append((module.input_of(torch.from_numpy(rows)), torch.from_numpy(index)))
        def objective() -> object:
            """Mean squared free-run error over the records (through ``a`` and ``b``, held
            where they do not require gradients)."""
            total = 0
            for (x, index), y, grid in zip(inputs, outputs, grids, strict=True):
                error = grid.free_run(module.output_of(x)[index], a, b) - y
                total = total + (error * error).sum()
            return total / count

        def stage(parameters: list, iterations: int) -> dict:
            """An L-BFGS stage on ``parameters``."""
            return _lbfgs(parameters, _autograd(objective, torch), iterations, torch, count)

        # The network first, the linear part held (the step e network is far from this
        # optimum, the step b' linear part close to it); then both together. Started at once,
        # L-BFGS meets the network's and the poles' very different curvatures and stalls.
        stages.append(stage(list(module.parameters()), int(max_iterations)))
        network_only = TorchNLS.to_params(module)
        if refine_linear:
            a.requires_grad_(True)
            b.requires_grad_(True)
            stages.append(stage([*module.parameters(), a, b], int(max_iterations)))
        params = TorchNLS.to_params(module)
        a_new, b_new = a.detach().numpy().copy(), b.detach().numpy().copy()
    linear, linear_note = arx, None
    if refine_linear:
        candidate, linear_note = _joint_end(arx, a_new, b_new, params)
        if candidate is not None:
            linear = _with_equation_error_bound(candidate, params, feature_map, nls, data)
        else:  # the line search may end beyond the stability boundary: keep the first stage
            params = network_only
    refined = NLS(feature_map, params, u_range=nls.u_range, training=nls.training)
    return NlsOutputErrorFit(
        nls=refined,
        arx=linear,
        rms_before=free_run_rms(nls, arx, data),
        rms_after=free_run_rms(refined, linear, data),
        wall_time_s=time.perf_counter() - start,
        stages=tuple(stages),
        linear_note=linear_note,
    )


def _joint_end(
    start: ARXModel, a: np.ndarray, b: np.ndarray, params: dict[str, np.ndarray]
) -> tuple[ARXModel | None, str | None]:
    """The joint stage's end, the linear part ``(a, b)`` with the network ``params``: the
    linear part as a model (with ``start``'s noise bound, dt and method) and None, or None and
    why it cannot be kept."""
    values = [a, b, *params.values()]
    if not all(np.all(np.isfinite(value)) for value in values):
        return None, (
            "the joint stage's line search ended at non-finite values; its network-only stage "
            "is kept"
        )
    candidate = ARXModel(a, b, noise_bound=start.noise_bound, dt=start.dt, method=start.method)
    if not candidate.is_stable():
        return None, (
            "the joint stage ended at an unstable linear part; its network-only stage is kept"
        )
    if start.is_minimum_phase() and not candidate.is_minimum_phase():
        return None, (
            "the joint stage ended at a non-minimum-phase linear part; its network-only stage "
            "is kept"
        )
    return candidate, None


def _with_equation_error_bound(
    arx: ARXModel,
    params: dict,
    feature_map: FeatureMap,
    nls: NLS,
    data: list[tuple[np.ndarray, np.ndarray]],
) -> ARXModel:
    """``arx`` with its ``noise_bound`` re-estimated as the largest equation error over the
    records (the step b and b' meaning of r_hat), with the refined network's z."""
    network = NLS(feature_map, params, u_range=nls.u_range)
    skip = max(arx.na, arx.nb)
    bound = 0.0
    for u, y in data:
        error = y - arx.predict(network.evaluate(u), y)
        bound = max(bound, float(np.max(np.abs(error[skip:]))))
    return ARXModel(arx.a, arx.b, noise_bound=bound, dt=arx.dt, method=arx.method)


def _radius_stage(
    feature_map: PlayFeatures,
    module: Any,
    network_inputs: Callable[[Any], Iterable[Any]],
    spread: list[Any],
    targets: tuple[list, list, int],
    linear: tuple[Any, Any],
    max_iterations: int,
    extra: Sequence[Any] = (),
) -> tuple[np.ndarray, dict[str, Any]]:
    """L-BFGS on the play radii (from ``feature_map``'s), the parameters ``extra`` and the
    network (``module``, updated in place), the linear part ``linear = (a, b)`` held, on the
    mean squared free-run error over the records ``targets = (outputs, grids, count)``.

    ``network_inputs(radii)`` yields each record's network input (one row per distinct
    feature vector) at the radii (a torch tensor, V), and ``spread`` indexes each record's
    samples into its rows. Returns the learned radii (V) and the stage's record (with
    ``radii_before`` and ``radii_after``, V).
    """
    torch = load_torch()
    outputs, grids, count = targets
    a, b = linear
    start = np.asarray(feature_map.radii)
    coordinates = torch.tensor(radius_coordinates(start), requires_grad=True)

    def objective() -> object:
        radii = radii_from_coordinates(coordinates)
        total = 0
        records = zip(network_inputs(radii), spread, outputs, grids, strict=True)
        for f, index, y, grid in records:
            error = grid.free_run(module(f)[index], a, b) - y
            total = total + (error * error).sum()
        return total / count

    parameters = [coordinates, *extra, *module.parameters()]
    stage = _lbfgs(parameters, _autograd(objective, torch), max_iterations, torch, count)
    with torch.no_grad():
        learned = radii_from_coordinates(coordinates).numpy().copy()
    return learned, {**stage, "radii_before": start.tolist(), "radii_after": learned.tolist()}


def _learn_radii(
    feature_map: PlayFeatures,
    module: Any,
    data: list[tuple[np.ndarray, np.ndarray]],
    targets: tuple[list, list, int],
    linear: tuple[Any, Any],
    max_iterations: int,
) -> tuple[PlayFeatures, dict[str, int | bool]]:
    """The radius stage: L-BFGS on the play radii and the network (``module``, updated in
    place), the linear part ``linear = (a, b)`` held; returns the feature map at the learned
    radii and the stage's record (with ``radii_before`` and ``radii_after``, V)."""
    torch = load_torch()
    plays = PlayRadiusFunction()
    rest = feature_map.initial_input
    # A held input leaves every play where it is, so the features (and the network's output)
    # are computed once per run of equal inputs and spread over the run.
    runs = [distinct_rows(u[:, None]) for u, _ in data]
    inputs = [torch.from_numpy(rows[:, 0]) for rows, _ in runs]
    spread = [torch.from_numpy(index) for _, index in runs]

    def network_inputs(radii: Any) -> Iterator[Any]:
        for u in inputs:
            yield torch.cat([u[:, None], plays(radii, u, rest)], dim=1)

    learned, stage = _radius_stage(
        feature_map, module, network_inputs, spread, targets, linear, max_iterations
    )
    return PlayFeatures(radii=tuple(learned), initial_input=rest), stage


RATE_START = 0.1
"""Rate constant (in sample times dt) the rate stage starts from: small against the plant's
(0.716 dt at its default, :data:`piezo_env.hysteresis.RATE_TIME` at 1 ms), and away from 0,
where the softplus that keeps it positive has no slope."""


def _learn_rate_radii(
    feature_map: PlayFeatures,
    module: Any,
    data: list[tuple[np.ndarray, np.ndarray]],
    targets: tuple[list, list, int],
    linear: tuple[Any, Any],
    max_iterations: int,
    dt: float,
) -> tuple[RatePlayFeatures, dict[str, Any]]:
    """The radius stage with a rate constant: L-BFGS on the base radii, the rate constant
    ``c = dt softplus(s)`` (s) and the network (updated in place), the linear part held;
    returns the rate-dependent feature map learned (rates over ``dt``, s) and the stage's
    record."""
    torch = load_torch()
    dt = float(dt)
    plays = RatePlayFunction()
    rest = feature_map.initial_input
    # Plays move only when the input does: the features at each move, spread to the samples
    # up to the next (a leading row for the samples before the first move, at rest).
    moves, spread = [], []
    for u, _ in data:
        u_moves, direction, rate, last = rate_play_runs(u, dt, rest)
        moves.append((u_moves, direction, rate))
        spread.append(torch.from_numpy(last + 1))
    rate_coordinate = torch.tensor(float(np.log(np.expm1(RATE_START))), requires_grad=True)
    rest_row = torch.full((1, 1 + len(feature_map.radii)), float(rest), dtype=torch.float64)

    def rate_time() -> Any:
        return dt * torch.nn.functional.softplus(rate_coordinate)

    def network_inputs(radii: Any) -> Iterator[Any]:
        c = rate_time()
        for move in moves:
            u = torch.from_numpy(move[0])
            yield torch.cat([rest_row, torch.cat([u[:, None], plays(radii, c, move, rest)], 1)])

    learned, stage = _radius_stage(
        feature_map,
        module,
        network_inputs,
        spread,
        targets,
        linear,
        max_iterations,
        extra=(rate_coordinate,),
    )
    with torch.no_grad():
        c = float(rate_time())
    if not any(_rate_moves_a_play(move, learned, c, rest) for move in moves):
        # No play edge was met right after a move: the objective does not depend on c, which
        # would keep its start. A rate-independent map is what the records support.
        c = 0.0
        stage["rate_note"] = (
            "no play met its edge at a sample following a move: the records do not determine "
            "the rate constant; set to 0"
        )
    stage["rate_time_s"] = c
    learned_map = RatePlayFeatures(radii=tuple(learned), rate_time=c, dt=dt, initial_input=rest)
    return learned_map, stage


def rate_is_determined(
    radii: Sequence[float], records: Sequence[tuple[np.ndarray, np.ndarray]], dt: float
) -> bool:
    """Whether ``records`` (u V, y um) can determine a rate constant of plays of ``radii`` (V)
    at sample time ``dt`` (s): some play is set by its edge at a move whose previous sample
    moved too. Checked at c = 0; a positive c moves every such edge away from the play, so
    records that fail here fail at every c."""
    r = np.asarray(radii, dtype=np.float64)
    for u, _ in _check_records(records):
        moves = rate_play_runs(u, dt, 0.0)[:3]
        if _rate_moves_a_play(moves, r, 0.0, 0.0):
            return True
    return False


def _rate_moves_a_play(
    move: tuple[np.ndarray, np.ndarray, np.ndarray], radii: np.ndarray, c: float, rest: float
) -> bool:
    """Whether some play output of a record (its moves, :func:`rate_play_runs`) was set by its
    edge at a move whose previous sample moved too: where the output depends on c."""
    u, direction, rate = move
    _, _, touch = rate_play_outputs(u, direction, c * rate, radii, rest)
    at_edge = touch == np.arange(u.size)[:, None]
    return bool(np.any(at_edge & (rate[:, None] > 0.0)))


def distinct_rows(features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of ``features`` (T, n) that differ from the row before, and each sample's row
    among them: ``rows[index]`` equals ``features`` exactly."""
    features = np.asarray(features)
    new_row = np.empty(features.shape[0], dtype=bool)
    new_row[:1] = True
    np.any(features[1:] != features[:-1], axis=1, out=new_row[1:])
    return features[new_row], np.cumsum(new_row) - 1


STOP_FRACTION = 0.01
"""Share of the estimation's own excess error below which a window of L-BFGS iterations is not
worth another (:func:`_lbfgs`). With p parameters estimated from N samples of residual
variance sigma^2, the expected excess mean squared error of the estimate on fresh data is
p sigma^2 / N (Akaike's final prediction error; Ljung, *System Identification*, 2nd ed.,
sec. 16.4): the price of estimating from finite data, which no optimiser removes. A window that
lowers the training objective by less than a hundredth of it leaves the optimiser's shortfall
two orders below that price if each later window would gain at most half the one before (then
what remains is at most the last window's gain; with a ratio rho, gain rho / (1 - rho)). The
rule is a heuristic where that fails: a slowly converging, ill-conditioned problem can stop a
few tolerances short, and a plateau longer than a window can hide a later drop altogether
(:data:`STOP_WINDOW`).
A hundredth, not a tenth: the closed loop resolves the linear part near the first resonance
better than the mean squared error does. At a tenth the MPCs on the nominal PL140 lost
measurably at 50-100 Hz against a refinement run to its cap, from a training error within its
own standard error of the cap's; at a hundredth they matched it
(``benchmarks/results/design_measurements.md``)."""

STOP_WINDOW = 20
"""L-BFGS iterations over which :func:`_lbfgs` measures the objective's decrease. Long enough
to cross a plateau of the objective before a drop: with 10, the network stage on the nominal
PL122 and the Prandtl-Ishlinskii PL140 stopped on a plateau that further iterations left
(``benchmarks/results/design_measurements.md``)."""


def stop_tolerance(loss: float, n_parameters: int, n_samples: int) -> float:
    """Decrease (um^2) of the mean squared free-run error over :data:`STOP_WINDOW` iterations
    below which :func:`_lbfgs` stops: :data:`STOP_FRACTION` of ``n_parameters loss /
    n_samples``, the excess error of estimating ``n_parameters`` from ``n_samples`` with the
    current mean squared error ``loss`` (um^2) taken as the residual variance (it is, at the
    noise floor; above it, a misfit the parameters cannot remove acts on their precision as
    noise does)."""
    return STOP_FRACTION * n_parameters * loss / n_samples


def _autograd(objective: Callable[[], object], torch: Any) -> Callable[[bool], object]:
    """The ``evaluate(grad)`` of :func:`_lbfgs` for an ``objective`` that returns a loss
    differentiable by autograd: the loss, with ``grad`` also its backward pass."""

    def evaluate(grad: bool) -> object:
        if not grad:
            with torch.no_grad():
                return objective()
        loss = objective()
        loss.backward()
        return loss

    return evaluate


def _lbfgs(
    parameters: list,
    evaluate: Callable[[bool], object],
    max_iterations: int,
    torch: object,
    n_samples: int,
) -> dict[str, int | bool | str]:
    """Full-batch L-BFGS (strong Wolfe line search) on ``parameters``, the mean squared error
    over ``n_samples`` samples that ``evaluate(grad)`` returns (with ``grad``, each parameter's
    ``.grad`` set too: :func:`_autograd`), in windows of
    :data:`STOP_WINDOW` iterations.

    A window is :data:`STOP_WINDOW` iterations or 1.25 times as many evaluations (torch's
    default ratio), whichever ends first, so that a window stands for a fixed amount of work.
    Stops when a window lowered the objective by less than :func:`stop_tolerance` (``stopped``
    ``"tolerance"``), when L-BFGS meets its own tests (``"converged"``: zero gradient or no
    descent direction left), or at ``max_iterations`` iterations or about ``1.25
    max_iterations`` evaluations (torch's line search may take one more; ``"cap"``). The
    windows continue one L-BFGS run: its history carries over (the path is the one uncut run's),
    and each window adds one evaluation at its start and one forward pass at its end. Returns
    the stage's record: ``iterations``, ``evaluations``, ``stopped`` and ``capped``.
    """
    window = min(STOP_WINDOW, max_iterations)
    optimiser = torch.optim.LBFGS(
        parameters,
        lr=1.0,
        max_iter=window,
        history_size=50,
        tolerance_grad=1e-12,
        tolerance_change=1e-15,
        line_search_fn="strong_wolfe",
    )
    n_parameters = sum(p.numel() for p in parameters)
    max_evaluations = max_iterations * 5 // 4
    group, state = optimiser.param_groups[0], optimiser.state

    def closure() -> object:
        optimiser.zero_grad()
        return evaluate(True)

    def current() -> float:
        return float(evaluate(False))

    loss, iterations, evaluations = current(), 0, 0
    while True:
        steps = min(window, max_iterations - iterations)
        group["max_iter"] = steps
        group["max_eval"] = min(steps * 5 // 4, max_evaluations - evaluations)
        optimiser.step(closure)
        record = state[parameters[0]]
        done = int(record.get("n_iter", 0)) - iterations
        spent = int(record.get("func_evals", 0)) - evaluations
        iterations, evaluations = iterations + done, evaluations + spent
        previous, loss = loss, current()
        if iterations >= max_iterations or evaluations >= max_evaluations:
            stopped = "cap"
        elif done < steps and spent < group["max_eval"]:  # torch's own tests ended the window
            stopped = "converged"
        elif previous - loss < stop_tolerance(loss, n_parameters, n_samples):
            stopped = "tolerance"
        else:
            continue
        return {
            "iterations": iterations,
            "evaluations": evaluations,
            "stopped": stopped,
            "capped": stopped == "cap",
        }


def _check_records(
    records: Sequence[tuple[np.ndarray, np.ndarray]],
) -> list[tuple[np.ndarray, np.ndarray]]:
    data = []
    for i, (u, y) in enumerate(records):
        u_arr = np.asarray(u, dtype=np.float64).ravel()
        y_arr = np.asarray(y, dtype=np.float64).ravel()
        if u_arr.size != y_arr.size or u_arr.size < 2:
            raise ValueError(
                f"record {i}: u and y need the same length >= 2, got {u_arr.size} and {y_arr.size}"
            )
        if not (np.all(np.isfinite(u_arr)) and np.all(np.isfinite(y_arr))):
            raise ValueError(f"record {i} holds non-finite samples")
        data.append((u_arr, y_arr))
    if not data:
        raise ValueError("give at least one (u, y) record")
    return data
