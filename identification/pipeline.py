"""The two-step identification procedure of the paper (section 3.4, steps a-f).

:func:`identify` runs the steps in order, one function each:

a) :func:`excite_prbs`: excite the bender with a PRBS;
b) :func:`estimate_arx`: estimate the ARX part with the uniform-noise Bayesian estimator (order
   chosen by free-run fit on a held-out part of the PRBS record);
b') :func:`refine_linear_part`: refine the linear part by output error, started from the
   Bayesian estimates (``config.refinement``, default ``"output-error"``; ``"none"`` skips it).
   The sensor noise is on the measured output, where equation-error ARX estimates are biased
   (mostly in the zeros, which the inverse of step d and the MPC invert); the prediction-error
   estimate of the output-error model is not (:mod:`identification.refine`). Its order is chosen
   again, by minimum description length. Steps d-f use the refined linear part;
c) :func:`excite_rich`: excite it with a rich signal (RAND +-30 V, hold 10 ms, by default:
   random loops at every amplitude and large-signal power up to about 100 Hz for the linear
   part in step e'; the paper's SINE is ``rich_signal="sine"``);
d) :func:`estimate_hidden_signal`: estimate the hidden signal z_t by inverting the ARX model
   (eq. 25), or by a regularised least-squares deconvolution when the estimated B polynomial is
   not minimum-phase (:mod:`identification.inversion`);
e) :func:`fit_nonlinearity`: fit the neural NLS to (u_t, z_hat_t), choosing its memory features
   on a separate selection record;
e') :func:`identification.steps.refine_nonlinearity`: refine the selected network and the
   linear part together on the free-run output error of the PRBS and rich records
   (``config.nls_refinement``, default ``"output-error"``; ``"none"`` skips it), kept if the
   held-out selection record agrees. Step e's loss weighs an error of z the same at every
   frequency, while the deflection sees it through the linear part, amplified near the first
   bending mode; z_hat carries the equation error filtered by 1/B; and the linear part saw
   only the small PRBS
   (:mod:`identification.nls.output_error`). With learned play radii, step e's play network is
   refined too when step e chose another feature set, and the feature set is chosen after this
   step (:func:`identification.steps.refine_and_choose`): step e scores plays on grid radii;
f) :func:`validate`: validate the Hammerstein model by free-run simulation on fresh RAND data.

The steps and their results live in :mod:`identification.steps`, the experiments on the
environment in :mod:`identification.experiment` (:func:`collect`), records as files in
:mod:`identification.records`, the settings in :mod:`identification.config`, the report and
files in :mod:`identification.outputs`.

One path for simulation and bench: :func:`identify` measures the records on the environment
(:func:`identification.records.records_from_env`), then runs steps b-f on them as
:func:`identify_records` does on records measured elsewhere (a folder written by a bench or
by ``piezo simulate --records``, or arrays). The same records give the same model.

Scale (Bai 2004). Under a two-level input a rate-independent nonlinearity is affine, so the
ARX part fitted to (u, y) of the PRBS run is the linear part up to a gain; taking it as is fixes
the scale: the NLS has unit small-signal gain and z is in equivalent volts.

Every record comes from the bender through its input and its sensor, as from a real
bender: the measured (noisy) deflection is all the identification sees. The records follow the
env's sample time (the bender's default unless ``dt`` is given): the PRBS is counted in samples,
the rich and validation records and their RAND hold in seconds
(:meth:`IdentificationConfig.at_sample_time`).
"""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from numpy.typing import ArrayLike

from identification.config import IdentificationConfig
from identification.experiment import (
    collect,
    experiment_inputs,
    identification_env,
    sample_time,
    step_seeds,
)
from identification.features import reused_features
from identification.outputs import (
    IdentificationResult,
    build_report,
    figure_data,
    jsonable,
    model_metadata,
    validation_signal,
    write_outputs,
)
from identification.records import (
    EXCITATION_FIELDS,
    MANIFEST,
    Records,
    RecordsError,
    read_manifest,
    read_records,
    records_from_arrays,
    records_from_env,
)
from identification.report import format_free_run
from identification.runner import StepRunner, step_runner
from identification.steps import (
    PAST_INPUTS_HOLD,
    ArxEstimate,
    HiddenSignal,
    LinearRefinement,
    NlsFit,
    NlsRefinement,
    Validation,
    estimate_arx,
    estimate_hidden_signal,
    fit_nonlinearity,
    refine_and_choose,
    refine_linear_part,
    validate,
    warm_up,
)
from piezo_env.checks import require_int

# collect, IdentificationConfig and write_outputs: the public names of their own modules,
# importable from here as well (the command line and the benchmarks do)
__all__ = [
    "IdentificationConfig",
    "IdentificationResult",
    "collect",
    "identify",
    "identify_records",
    "read_records_folder",
    "write_outputs",
]


def identify(
    env: gym.Env | None = None,
    *,
    config: IdentificationConfig | None = None,
    progress: Callable[[str], None] | None = None,
    jobs: int = 1,
    runner: StepRunner | None = None,
    **overrides: Any,
) -> IdentificationResult:
    """Identify the Hammerstein model of a bender (paper section 3.4, steps a-f).

    Measures the records of the experiment on ``env`` (step a's PRBS, step c's rich record,
    the selection and validation records), then runs steps b-f on them as
    :func:`identify_records` does on records measured elsewhere.

    Parameters
    ----------
    env : gymnasium.Env, optional
        The bender to identify; default ``PiezoBender-v0`` with ``config.env_kwargs``.
    config : IdentificationConfig, optional
        All settings; keyword ``overrides`` build one when it is not given. Its durations are
        counted in samples at the env's sample time (:meth:`IdentificationConfig.
        at_sample_time`); ``report["config"]`` holds the counts used.
    progress : callable, optional
        Called with one line of text per step.
    jobs : int
        Processes to use (>= 1): with 2 or more, step e's candidate networks and step e''s
        refinements that do not depend on each other run beside each other on a helper process
        started now (:mod:`identification.runner`). The model is the same to the bit; only
        the time changes.
    runner : StepRunner, optional
        A runner the caller started (:func:`identification.runner.step_runner`) instead of
        ``jobs``: its helper outlives the call, so that :func:`write_outputs` can draw figures
        on it too.

    Returns
    -------
    IdentificationResult
        ``.model`` (HammersteinModel), ``.report`` (metrics, estimates, timings), ``.data``.
    """
    config = _settings(config, overrides)
    log = _StepLog(progress)
    env = env if env is not None else identification_env(config)
    dt = sample_time(env)
    config = config.at_sample_time(dt)
    with _runner(jobs, runner) as runner:  # the helper's start-up overlaps the experiment
        records = records_from_env(env, experiment_inputs(config, dt), config.seed)
        true_plant = env.unwrapped.model.state_space()
        return _identify(records, config, log, true_plant=true_plant, runner=runner)


def identify_records(
    records: str
    | os.PathLike[str]
    | Records
    | Mapping[str, tuple[ArrayLike, ArrayLike]]
    | tuple[ArrayLike, ArrayLike],
    *,
    split: float | None = None,
    seed: int | None = None,
    dt: float | None = None,
    drive_range_V: tuple[float, float] | None = None,
    bender: str | None = None,
    config: IdentificationConfig | None = None,
    progress: Callable[[str], None] | None = None,
    jobs: int = 1,
    runner: StepRunner | None = None,
    **overrides: Any,
) -> IdentificationResult:
    """Identify the Hammerstein model from measured records (steps b-f of section 3.4).

    Parameters
    ----------
    records : path, Records or mapping
        A records folder (``records.json`` and the files it lists,
        :func:`identification.records.read_records`); :class:`Records`; or arrays: record
        name (``prbs``, ``rich``, ``selection``, ``validation``) -> ``(u, y)``, applied
        voltage (V) and measured deflection (um, ``y[k]`` read before ``u[k]`` is applied),
        or one ``(u, y)`` pair with ``split``.
    split : float, optional
        For a single record: the fraction (0-1) that is the estimation record; the rest is
        held out, its first half selecting the network (step e), its second half validating
        (step f) (:mod:`identification.records`).
    seed : int, optional
        Seed of the network's training; default the records' (the seed their inputs were
        drawn with, so that records measured on the env give the model :func:`identify` gives).
    dt, drive_range_V, bender
        For arrays: sample time (s), drive range (V) and bender name (a catalogue name gives
        the datasheet the model files record). A folder's manifest holds them.
    config : IdentificationConfig, optional
        Settings of the steps (orders, network, refinements); keyword ``overrides`` build one
        when it is not given. The settings of the input signals and the record lengths come
        from the records (a manifest written by ``piezo excite`` carries the former).
    progress : callable, optional
        Called with one line of text per step.
    jobs : int
        Processes to use (>= 1), as in :func:`identify`.
    runner : StepRunner, optional
        A runner the caller started, instead of ``jobs``, as in :func:`identify`.

    Returns
    -------
    IdentificationResult
        As :func:`identify`; the model's metadata names the records' source (the manifest's
        path and SHA-256). The report's comparisons with the true plant are absent: a bench has
        none.

    Raises
    ------
    identification.records.RecordsError
        A malformed record (one line naming the file and the line or field), before any work.
    """
    config = _settings(config, overrides)
    log = _StepLog(progress)
    if seed is not None:
        require_int("seed", seed, minimum=0)
    if isinstance(records, (str, os.PathLike, Records)):
        named = {"dt": dt, "drive_range_V": drive_range_V, "bender": bender}
        given = [name for name, value in named.items() if value is not None]
        if given:  # they would be ignored: the records say what they are
            raise ValueError(
                f"{', '.join(given)}: for arrays only; a records folder's manifest (or a "
                "Records) holds the sample time, drive range and bender: leave them out"
            )
    if isinstance(records, (str, os.PathLike)):
        records, config = read_records_folder(records, config, split=split)
    elif not isinstance(records, Records):
        missing = [k for k, v in (("dt", dt), ("drive_range_V", drive_range_V)) if v is None]
        if missing or bender is None:
            raise ValueError(
                "arrays need dt (s), drive_range_V (V) and bender; missing "
                + ", ".join(missing + ([] if bender is not None else ["bender"]))
            )
        records = records_from_arrays(
            records, dt=dt, drive_range_V=drive_range_V, bender=bender, config=config, split=split
        )
    if seed is not None:
        records = dataclasses.replace(records, seed=int(seed))
    config = dataclasses.replace(config, seed=records.seed).at_sample_time(records.dt)
    lengths = {
        name: len(u) - records.lead_in.get(name, 0) for name, (u, _) in records.records.items()
    }
    config = dataclasses.replace(
        config,
        prbs_samples=lengths["prbs"],
        rich_samples=lengths["rich"],
        validation_samples=lengths["validation"],
    )
    with _runner(jobs, runner) as runner:  # records checked first: no process for bad input
        return _identify(records, config, log, true_plant=None, runner=runner)


def read_records_folder(
    folder: str | os.PathLike[str],
    config: IdentificationConfig,
    *,
    split: float | None = None,
) -> tuple[Records, IdentificationConfig]:
    """Read and check a records folder, and the settings its excitation was drawn with.

    What :func:`identify_records` does first with a folder, callable on its own so that a
    malformed folder is refused before anything is written; pass both results to
    :func:`identify_records` to identify from them.

    Parameters
    ----------
    folder : str or path-like
        A folder holding ``records.json`` and the files it lists.
    config : IdentificationConfig
        Settings of the steps; the manifest's excitation settings (``piezo excite``) replace
        its own.
    split : float, optional
        For a single record: the estimation fraction (see :func:`identify_records`).

    Returns
    -------
    (Records, IdentificationConfig)

    Raises
    ------
    identification.records.RecordsError
        A malformed record (one line naming the file and the line or field).
    """
    manifest = Path(folder) / MANIFEST
    excitation = read_manifest(folder).get("excitation")
    if excitation is not None and not isinstance(excitation, dict):
        raise RecordsError(
            f"{manifest}: field 'excitation' must be an object (the settings piezo excite "
            f"drew the inputs with) or null; got {excitation!r}"
        )
    if excitation:  # the signals the bench was driven with
        known = {k: v for k, v in excitation.items() if k in EXCITATION_FIELDS}
        try:
            config = dataclasses.replace(config, **known)
        except ValueError as error:
            raise RecordsError(f"{manifest}: field 'excitation': {error}") from None
    return read_records(folder, config, split=split), config


@contextmanager
def _runner(jobs: int, runner: StepRunner | None) -> Iterator[StepRunner]:
    """``runner`` if given (left running), else a new :func:`step_runner` of ``jobs``."""
    if runner is None:
        with step_runner(jobs, warm_up) as started:
            yield started
        return
    if jobs != 1:
        raise ValueError(f"pass jobs or runner, not both (got jobs={jobs!r} and a runner)")
    yield runner


def _settings(
    config: IdentificationConfig | None, overrides: dict[str, Any]
) -> IdentificationConfig:
    if config is None:
        return IdentificationConfig(**overrides)
    if overrides:
        raise ValueError("pass either config or keyword overrides, not both")
    return config


def _identify(
    records: Records,
    config: IdentificationConfig,
    log: _StepLog,
    *,
    true_plant: Any,
    runner: StepRunner,
) -> IdentificationResult:
    """Steps b-f on measured records (``true_plant``: the simulated plant's linear part, for
    the report's comparisons only, or None). The models of a run share their feature maps and
    are evaluated on the same records many times: their features are computed once each."""
    with reused_features():
        return _identify_steps(records, config, log, true_plant=true_plant, runner=runner)


def _identify_steps(
    records: Records,
    config: IdentificationConfig,
    log: _StepLog,
    *,
    true_plant: Any,
    runner: StepRunner,
) -> IdentificationResult:
    """The body of :func:`_identify`."""
    seeds, dt = step_seeds(config.seed), records.dt
    u_prbs, y_prbs = records.records["prbs"]
    log("a_prbs_experiment", _prbs_line(config, records, y_prbs))
    est = estimate_arx(u_prbs, y_prbs, config, dt=dt, runner=runner)
    log("b_arx_estimation", _arx_line(est))
    refinement = None
    if config.refinement == "output-error":
        refinement = refine_linear_part(est, u_prbs, y_prbs)
        log("b2_output_error", _refinement_line(refinement))
    linear = est.model if refinement is None else refinement.model
    u_rich, y_rich = records.records["rich"]
    log("c_rich_experiment", _rich_line(config, records, u_rich))
    hidden = estimate_hidden_signal(linear, y_rich, y_prbs)
    log("d_inverse_arx", _hidden_line(hidden))
    if records.shared:  # one record split: the PRBS record is the rich record
        u_train, z_train, training = u_prbs, hidden.z_prbs, [(u_prbs, y_prbs)]
    else:
        u_train, z_train = np.r_[u_prbs, u_rich], np.r_[hidden.z_prbs, hidden.z_rich]
        training = [(u_prbs, y_prbs), (u_rich, y_rich)]
    nls = fit_nonlinearity(
        linear,
        u_train,
        z_train,
        records.records["selection"],
        config,
        seeds,
        u_max=records.u_max,
        u_prbs=u_prbs,
        lead_in=records.lead_in.get("selection", 0),
        say=log.say,
        runner=runner,
    )
    log("e_nls_training", _gain_line(nls))
    nls_refinement = None
    if config.nls_refinement == "output-error":
        nls, nls_refinement = refine_and_choose(
            nls, training, config, sensor_noise_bound=records.noise_bound_um, runner=runner
        )
        log("e2_nls_output_error", _nls_refinement_line(nls_refinement))
    model = nls.model if nls_refinement is None else nls_refinement.model
    model.metadata.update(
        model_metadata(records, config, nls.features, hidden, refinement, nls_refinement)
    )
    val = validate(
        records.records["validation"],
        model,
        stroke_um=records.stroke_um,
        unrefined=est.model,
        unrefined_nls=nls.model,
        lead_in=records.lead_in.get("validation", 0),
    )
    log("f_validation", _validation_line(validation_signal(config, records), val))

    report = build_report(
        records,
        config,
        est,
        hidden,
        nls,
        val,
        log.timings(),
        refinement,
        nls_refinement,
        true_plant=true_plant,
    )
    data = figure_data(u_prbs, y_prbs, u_rich, y_rich, hidden, model, val, est.model)
    data["arx_step_b2"] = linear if refinement is not None else None
    data["linear_refined_by_e2"] = model.arx is not nls.model.arx
    data["plant_linear"] = true_plant  # the report's Bode figure only
    return IdentificationResult(model=model, report=jsonable(report), data=data)


def _prbs_line(config: IdentificationConfig, records: Records, y_prbs: np.ndarray) -> str:
    what = (
        "estimation part of the split record"
        if records.shared
        else f"PRBS +-{config.prbs_amplitude:g} V"
    )
    return f"a) {what}, {len(y_prbs)} samples: peak |y| = {np.abs(y_prbs).max():.1f} um"


def _arx_line(est: ArxEstimate) -> str:
    arx = est.model
    return (
        f"b) ARX({est.order},{est.order}) by bayes-uniform (held-out PRBS fit "
        + ", ".join(f"n={k}: {v:.1f} %" for k, v in est.order_scores.items())
        + f"); r_hat = {arx.noise_bound:.2f} um, minimum-phase B: {arx.is_minimum_phase()}"
    )


def _refinement_line(refinement: LinearRefinement) -> str:
    fit = refinement.fit
    return (
        f"b') output-error refinement: order {refinement.order} (held-out free-run RMS "
        + ", ".join(f"n={k}: {v:.3f}" for k, v in refinement.order_scores.items())
        + " um); free-run RMS on the PRBS record "
        + format_free_run(refinement.unrefined_output_error_rms, ".3f")
        + f" -> {fit.output_error_rms:.3f} um, zeros "
        + ", ".join(f"{z:.3f}" for z in refinement.model.zeros())
    )


def _rich_line(config: IdentificationConfig, records: Records, u_rich: np.ndarray) -> str:
    if records.shared:
        return f"c) the estimation part again as the rich record, {len(u_rich)} samples"
    return f"c) {config.rich_signal} {config.rich_amplitude:g} V, {len(u_rich)} samples"


def _hidden_line(hidden: HiddenSignal) -> str:
    bound, rms = hidden.error["z_error_bound_V"], hidden.error["z_error_rms_V"]
    return (
        f"d) z_hat by {hidden.method}; error from r_hat: worst case {_volts(bound)}, "
        f"RMS {_volts(rms)}"
    )


def _gain_line(nls: NlsFit) -> str:
    return (
        f"   NLS small-signal gain on the PRBS record: {nls.small_signal_gain:.3f} "
        "(1 by construction)"
    )


def _nls_refinement_line(refinement: NlsRefinement) -> str:
    training, selection = refinement.training_rms_um, refinement.selection_rms_um
    if not training:
        return f"e') output-error refinement not run: {refinement.refusal}"
    held_out = f"{selection['before']:.3f}"
    if "after" in selection:
        held_out += f" -> {selection['after']:.3f}"
    verdict = "kept" if refinement.accepted else f"not kept: {refinement.refusal}"
    if refinement.note:
        verdict += f"; {refinement.note}"
    choice = refinement.feature_choice
    if choice and "play" in choice["held_out_rms_um"]:
        verdict += (
            f"; play refined beside {choice['step_e']} "
            f"({choice['held_out_rms_um']['play']:.3f} um held out): {choice['kept']} kept"
        )
    stages = "of the network, then of network and linear part"
    if refinement.note == PAST_INPUTS_HOLD:
        stages = "of the network, the linear part held"
    return (
        f"e') output-error refinement {stages} "
        f"({' + '.join(str(stage['iterations']) for stage in refinement.stages)} L-BFGS "
        f"iterations, {refinement.wall_time_s:.1f} s): free-run RMS on the training records "
        f"{training['before']:.3f} -> {training['after']:.3f} um, on the held-out selection "
        f"record {held_out} um ({verdict})"
    )


def _validation_line(signal: str, val: Validation) -> str:
    hammer, linear = val.metrics["hammerstein"], val.metrics["linear_arx"]
    return (
        f"f) validation on {signal}: Hammerstein fit {hammer['fit_percent']:.2f} %, "
        f"RMSE {hammer['rmse']:.2f} um; linear ARX fit {linear['fit_percent']:.2f} %, "
        f"RMSE {linear['rmse']:.2f} um"
    )


def _volts(value: float | None) -> str:
    return "n/a (not eq. 25)" if value is None else f"{value:.2f} V"


class _StepLog:
    """Progress lines and wall time per step (s).

    ``log(name, line)`` reports the line of a step that has just ended and closes its time;
    ``log.say(line)`` reports a line within a step; ``timings()`` adds the total.
    """

    def __init__(self, progress: Callable[[str], None] | None) -> None:
        self.say = progress or (lambda _line: None)
        self._start = self._last = time.perf_counter()
        self._laps: dict[str, float] = {}

    def __call__(self, name: str, line: str) -> None:
        self.say(line)
        now = time.perf_counter()
        self._laps[name] = round(now - self._last, 3)
        self._last = now

    def timings(self) -> dict[str, float]:
        return {**self._laps, "total": round(time.perf_counter() - self._start, 3)}
