"""Step e's candidates and step e''s refinements computed beside each other on a helper process
(:mod:`identification.runner`) give the model computed in one process, to the bit."""

from __future__ import annotations

import numpy as np
import pytest
from test_nls_output_error import _rate_plant, _step_e

from identification.config import IdentificationConfig
from identification.hammerstein import HammersteinModel
from identification.runner import StepRunner, step_runner
from identification.steps import (
    NlsFit,
    fit_nonlinearity,
    refine_and_choose,
    refine_nonlinearity,
    warm_up,
)


@pytest.fixture(scope="module")
def beside():
    """A runner with a helper process, shared by this module's tests."""
    with step_runner(2, warm_up) as runner:
        assert runner.parallel
        yield runner


def _idle(beside: StepRunner) -> StepRunner:
    """``beside`` once whatever was asked of its helper before (its warm-up, a withdrawn
    refinement an earlier test left running to its end) is over: calls run in order."""
    assert beside.beside(int, "0").result() == 0
    assert beside.idle
    return beside


def _both(beside: StepRunner) -> tuple[StepRunner, StepRunner]:
    """A runner that computes everything here, and ``beside``."""
    return StepRunner(), beside


def _without_times(record):
    """A record with its wall times left out (they differ from run to run)."""
    if isinstance(record, dict):
        return {k: _without_times(v) for k, v in record.items() if not k.endswith("wall_time_s")}
    if isinstance(record, (list, tuple)):
        return [_without_times(v) for v in record]
    return record


def _assert_same_model(a: HammersteinModel, b: HammersteinModel) -> None:
    for key, value in a.nls.arrays().items():
        np.testing.assert_array_equal(value, b.nls.arrays()[key], err_msg=key)
    assert a.nls.feature_map == b.nls.feature_map
    np.testing.assert_array_equal(a.arx.a, b.arx.a)
    np.testing.assert_array_equal(a.arx.b, b.arx.b)
    assert a.arx.noise_bound == b.arx.noise_bound
    assert _without_times(a.nls.training) == _without_times(b.nls.training)


def test_step_b_orders_beside_each_other_are_the_estimates_of_one_process(beside):
    """Step b's orders fitted here one by one, and the smaller ones on the helper: the same
    candidates, held-out scores, order and final estimates, to the bit. A runner queues its
    helper's warm-up once, behind the orders."""
    from identification.arx import ARXModel
    from identification.steps import estimate_arx

    rng = np.random.default_rng(4)
    u = rng.choice([-10.0, 10.0], 1200)
    plant = ARXModel([1.2, -0.5], [0.3, 0.1], dt=1e-3)
    y = plant.simulate(u) + rng.uniform(-0.02, 0.02, u.size)
    config = IdentificationConfig(orders=(1, 2, 3, 4))
    _idle(beside)
    here, there = (estimate_arx(u, y, config, dt=1e-3, runner=r) for r in _both(beside))
    assert here.order == there.order and here.order_scores == there.order_scores
    for a, b in [(here.model, there.model), (here.chebyshev, there.chebyshev)] + [
        (here.candidates[n], there.candidates[n]) for n in config.orders
    ]:
        np.testing.assert_array_equal(
            np.r_[a.a, a.b, a.noise_bound], np.r_[b.a, b.b, b.noise_bound]
        )

    asked: list[str] = []

    class _Helper:
        def submit(self, function, *args):
            asked.append(getattr(function, "__name__", "call"))
            return len(asked)

        def withdraw_later(self, ticket):
            pass

    runner = StepRunner(_Helper(), warm_up)
    runner.warm_up_helper()
    runner.warm_up_helper()
    assert asked == ["warm_up"]


def test_step_e_candidates_beside_each_other_are_the_networks_of_one_process(beside):
    """The three candidate feature sets trained here one by one, and two of them on the
    helper: the same networks, selection scores and choice."""
    from identification.arx import ARXModel
    from piezo_env.operators import play_sequence

    rng = np.random.default_rng(2)
    u = np.repeat(rng.uniform(-30, 30, 300), 10)
    plays, _ = play_sequence(u, np.array([7.0, 16.0]), np.zeros(2))
    z = 0.7 * u + plays @ np.array([0.15, 0.15])
    arx = ARXModel([0.6], [0.4], dt=1e-3)
    y = arx.simulate(z) + rng.uniform(-0.05, 0.05, u.size)
    config = IdentificationConfig(hidden=(2,), max_epochs=3)

    def step_e(runner):
        return fit_nonlinearity(
            arx,
            u,
            z,
            (u[:1000], y[:1000]),
            config,
            {"nls": 5},
            u_max=30.0,
            u_prbs=u,
            runner=runner,
        )

    _idle(beside)
    here, there = (step_e(r) for r in _both(beside))
    # A helper kept busy for ten minutes: this process takes every candidate back and trains
    # it itself (the helper, which runs its calls in order, is still in the first when step e
    # is over; closing it ends that call).
    import time

    with step_runner(2) as kept_busy:
        assert kept_busy.beside(int, "1").result() == 1  # started
        busy = kept_busy.beside(time.sleep, 600.0)
        taken = step_e(kept_busy)
        assert not kept_busy.idle and not busy.take_back()
    assert list(here.candidates) == ["play", "past-inputs", "bouc-wen"]
    for other in (there, taken):
        assert here.features == other.features
        assert here.selection_scores == other.selection_scores
        for features, nls in here.candidates.items():
            _assert_same_model(
                HammersteinModel(nls, arx), HammersteinModel(other.candidates[features], arx)
            )


def _same_refinement(a, b) -> None:
    _assert_same_model(a.model, b.model)
    assert _without_times(a.record()) == _without_times(b.record())


def test_the_play_rival_refined_beside_is_the_rival_refined_here(beside):
    """Step e chose past-inputs on plays off the grid, and no sensor bound can rule the play
    rival out: its refinement on the helper, started before the choice's, wins as it does
    here, with the same records."""
    config = IdentificationConfig(nls_refinement_iterations=40, rate="off")
    results = []
    for runner in _both(beside):
        fit, records = _step_e("past-inputs", (7.0, 16.0), seed=0)
        results.append(
            refine_and_choose(fit, records, config, sensor_noise_bound=None, runner=runner)
        )
    (kept_here, here), (kept_there, there) = results
    assert kept_here.features == kept_there.features == "play"
    _same_refinement(here, there)


def test_the_rate_refinement_started_beside_is_used_or_withdrawn_as_here(beside):
    """Play chosen, rate="auto": the rate-dependent refinement starts on the helper beside the
    rate-independent one. On moving inputs the learned radii determine the rate and the
    helper's refinement is the one used; on held inputs they do not and it is withdrawn. Both
    give what one process gives."""
    config = IdentificationConfig(nls_refinement_iterations=20, rate="auto")
    start, arx, records = _rate_plant(7e-4)
    selection = _rate_plant(7e-4, seed=1)[2][0]
    fit = NlsFit(HammersteinModel(start, arx), "play", {}, 1.0, selection, 0, {"play": start})
    here, there = (refine_nonlinearity(fit, records, config, runner=r) for r in _both(beside))
    assert here.rate_choice["determined"] and "rate_rms_um" in here.rate_choice
    _same_refinement(here, there)
    held, records = _step_e("play", (7.0, 16.0), seed=1)
    here, there = (refine_nonlinearity(held, records, config, runner=r) for r in _both(beside))
    assert here.rate_choice == {"determined": False, "kept": False}
    _same_refinement(here, there)
    assert beside.beside(int, "7").result() == 7  # the helper is still at work


def test_beside_runs_on_another_process_and_here_runs_here(beside):
    import os

    assert beside.beside(os.getpid).result() != os.getpid()
    assert StepRunner().beside(os.getpid).result() == os.getpid()
    assert beside.here(os.getpid).result() == os.getpid()


def test_identify_with_a_helper_gives_the_model_of_one_process(fast_pl140_identification):
    """The pipeline end to end with ``jobs=2`` (play features: the rate-dependent refinement
    starts on the helper) against the session's one-process identification."""
    from short_runs import FAST, FAST_SEED

    from identification.pipeline import identify

    config = IdentificationConfig(seed=FAST_SEED, env_kwargs={"bender": "PL140"}, **FAST)
    here, there = fast_pl140_identification, identify(config=config, jobs=2)
    _assert_same_model(here.model, there.model)
    assert _without_times(here.report["nls"]) == _without_times(there.report["nls"])


def test_jobs_must_be_a_positive_integer():
    for jobs in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="jobs must be an integer >= 1"):
            with step_runner(jobs):
                pass


class _Recording(StepRunner):
    """A runner that records the name of each computation it is asked to run beside."""

    def __init__(self, helper) -> None:
        super().__init__(helper)
        self.asked: list[str] = []

    def beside(self, function, *args, **kwargs):
        self.asked.append(function.__name__)
        return super().beside(function, *args, **kwargs)


def test_a_rival_refined_here_refines_its_rate_dependent_variant_beside(beside):
    """Step e chose past-inputs on a plant of rate-dependent plays, with a sensor bound that
    does not put the choice at the noise floor: the play rival is refined here, and its
    rate-dependent refinement (which its learned radii determine) on the helper. The same
    choice and refinement as in one process."""
    from identification.nls import fit_nls

    start, arx, records = _rate_plant(7e-4)
    u = records[0][0]
    past = fit_nls(u, u, features="past-inputs", hidden=(2,), max_epochs=5, u_range=(-30, 30))
    selection = _rate_plant(7e-4, seed=1)[2][0]
    candidates = {"play": start, "past-inputs": past}
    fit = NlsFit(HammersteinModel(past, arx), "past-inputs", {}, 1.0, selection, 0, candidates)
    config = IdentificationConfig(nls_refinement_iterations=20, rate="auto")
    recording = _Recording(beside._helper)
    results = [
        refine_and_choose(fit, records, config, sensor_noise_bound=0.05, runner=r)
        for r in (StepRunner(), recording)
    ]
    (kept_here, here), (kept_there, there) = results
    assert recording.asked == ["_refine"]  # the rival's rate-dependent refinement, nothing else
    assert kept_here.features == kept_there.features == "play"
    assert here.rate_choice["determined"] and "rate_rms_um" in here.rate_choice
    _same_refinement(here, there)


def test_the_runner_is_idle_only_when_its_helper_computes_nothing(beside):
    """The figures are drawn beside only on a helper that would start at once."""
    import time

    _idle(beside)
    assert not StepRunner().idle
    pending = beside.beside(time.sleep, 0.5)
    assert not beside.idle
    pending.result()
    assert beside.idle


def test_figures_drawn_beside_are_the_figures_drawn_here(
    beside, fast_pl140_identification, tmp_path
):
    from identification.figures import write_figures

    (tmp_path / "here").mkdir()
    (tmp_path / "there").mkdir()
    here = write_figures(fast_pl140_identification, tmp_path / "here")
    _idle(beside)  # so that the figures below are drawn there, not here
    there = write_figures(fast_pl140_identification, tmp_path / "there", runner=beside)
    assert [p.name for p in here] == [p.name for p in there]
    assert len(here) == 5
    for a, b in zip(here, there, strict=True):
        assert a.parent == tmp_path / "here" and b.parent == tmp_path / "there"
        assert a.read_bytes() == b.read_bytes(), a.name


def test_a_runner_and_jobs_are_not_both_given(beside):
    from identification.pipeline import identify

    with pytest.raises(ValueError, match="pass jobs or runner, not both"):
        identify(jobs=2, runner=beside)
