"""The designs the controllers keep by content (:mod:`piezo_env.memo`): a kept result is the
fresh computation to the bit, an input changed in its last bit computes afresh, and no caller
can change another's copy."""

from __future__ import annotations

import dataclasses
import itertools
import types
from pathlib import Path

import casadi
import numpy as np
import pytest
from handmade import AffineNonlinearity, first_mode, handmade_nls

import controllers.observer as observer_module
import controllers.prediction as prediction
import controllers.predictive as predictive
from controllers import loop
from controllers.native import codegen, compiled_inverse, nmpc_step
from controllers.native.compiled_inverse import (
    CompiledInverse,
    inverse_function,
    reachable_function,
)
from controllers.observer import DISTURBANCE_RATIOS, PROCESS_RATIOS, ObserverBank
from controllers.predictive import PredictiveController
from controllers.tolerance_box import ToleranceBox, vertex_models
from identification.features import PastInputFeatures
from piezo_env.memo import ContentCache

SIGMA = 0.5  # sensor noise (um)
MODEL_DIR = str(Path(__file__).resolve().parents[1] / "docs" / "benchmark" / "model")


def _fresh_cache(monkeypatch, module, name: str) -> ContentCache:
    """Replace ``module.name`` by an empty cache of the same size (so earlier tests' entries
    do not count), and return it."""
    cache = ContentCache(getattr(module, name).size)
    monkeypatch.setattr(module, name, cache)
    return cache


def _nudged(x: np.ndarray) -> np.ndarray:
    """``x`` with its first entry one ulp larger."""
    out = np.array(x, dtype=float)
    out.flat[0] = np.nextafter(out.flat[0], np.inf)
    return out


def _bank_arrays(bank: ObserverBank) -> list[np.ndarray]:
    return [
        bank.gains,
        bank._half_inverse_var,
        bank._half_log_var,
        bank.a_aug,
        bank.b_aug,
        bank.c_aug,
        np.array(bank.noise_levels),
    ]


def test_a_kept_bank_design_is_the_fresh_one_to_the_bit(monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, observer_module, "_bank_designs")
    a, b, c = first_mode()
    first = ObserverBank(a, b, c, measurement_std=SIGMA)
    again = ObserverBank(a, b, c, measurement_std=SIGMA, memory=50)  # memory is not designed
    assert (cache.misses, cache.hits) == (1, 1)
    ratios = list(itertools.product(PROCESS_RATIOS, DISTURBANCE_RATIOS))
    fresh = observer_module._bank_design(a, b, c, SIGMA, ratios, 0.0)
    variance = fresh["innovation_var"]
    expected = [
        fresh["gains"],
        0.5 / variance,
        0.5 * np.log(variance),
        fresh["a_aug"],
        fresh["b_aug"],
        fresh["c_aug"],
        fresh["noise_levels"],
    ]
    for bank in (first, again):
        for got, want in zip(_bank_arrays(bank), expected, strict=True):
            assert got.dtype == want.dtype and np.array_equal(got, want)
        assert bank.riccati_fallbacks == fresh["riccati_fallbacks"]
        assert bank.slowest_pole_hz(1e-3) == first.slowest_pole_hz(1e-3)
    # and each filter is the single observer of its noise levels, to the bit
    prior = first.prior
    process, disturbance = first.noise_levels[prior]
    single = observer_module.DisturbanceObserver(
        a,
        b,
        c,
        measurement_std=SIGMA,
        process_std=process,
        disturbance_std=disturbance,
    )
    np.testing.assert_allclose(first.gains[prior], single.gain, rtol=1e-9)


def test_a_bank_input_changed_in_its_last_bit_is_designed_afresh(monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, observer_module, "_bank_designs")
    a, b, c = first_mode()
    ObserverBank(a, b, c, measurement_std=SIGMA)
    variants = [
        ((_nudged(a), b, c), {}),
        ((a, _nudged(b), c), {}),
        ((a, b, _nudged(c)), {}),
        ((a, b, c), {"measurement_std": np.nextafter(SIGMA, 1.0)}),
        ((a, b, c), {"disturbance_ratios": (*DISTURBANCE_RATIOS[:-1], 9.000000000000002)}),
        ((a, b, c), {"slope_std": 1e-3}),
    ]
    for count, (model, options) in enumerate(variants, start=2):
        ObserverBank(*model, **{"measurement_std": SIGMA, **options})
        assert (cache.misses, cache.hits) == (count, 0)


def test_banks_cannot_change_each_others_design(monkeypatch) -> None:
    _fresh_cache(monkeypatch, observer_module, "_bank_designs")
    a, b, c = first_mode()
    first = ObserverBank(a, b, c, measurement_std=SIGMA)
    expected = [x.copy() for x in _bank_arrays(first)]
    for x in _bank_arrays(first):
        x[...] = -1.0
    first.noise_levels[0] = (-1.0, -1.0)
    again = ObserverBank(a, b, c, measurement_std=SIGMA)
    for got, want in zip(_bank_arrays(again), expected, strict=True):
        assert np.array_equal(got, want)


def test_a_failing_bank_design_is_refused_each_time(monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, observer_module, "_bank_designs")
    a, b, c = first_mode()
    for _ in range(2):
        with pytest.raises(ValueError, match="DC gain"):
            ObserverBank(a, np.zeros_like(b), c, measurement_std=SIGMA)
    assert cache.misses == 0


# -- the MPCs' box screen (controllers.predictive) ----------------------------------------------


@pytest.fixture(scope="module")
def mpc():
    """The linear MPC on the committed benchmark model for the nominal PL140."""
    import gymnasium as gym

    import controllers

    env = gym.make("piezo_env:PiezoBender-v0", preview=20, max_episode_steps=100)
    return controllers.make("mpc", MODEL_DIR, env)


def _kept(cache: ContentCache, parts: list):
    """What ``cache`` holds for ``parts`` (fails if it holds nothing)."""
    return cache.get(parts, lambda: pytest.fail("nothing kept for these inputs"))


def test_a_kept_box_screen_is_the_fresh_one_to_the_bit(mpc, monkeypatch) -> None:
    screens = _fresh_cache(monkeypatch, predictive, "_box_screens")
    margins = _fresh_cache(monkeypatch, predictive, "_margins")
    law, plants = mpc.feedback_law(), mpc.box_plants()
    banks = [ObserverBank.for_controller(mpc.model, mpc.task, mpc.settings) for _ in range(2)]
    first, again = (predictive.screen_bank(bank, law, plants) for bank in banks)
    assert first == again and (screens.misses, screens.hits) == (1, 1)
    assert (margins.misses, margins.hits) == (1, 1)
    np.testing.assert_array_equal(banks[0].admissible, banks[1].admissible)
    bank = banks[1]
    fresh = loop.radii_matrix(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants)
    on_plants = loop.plant_margins(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants)
    parts = [bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants]
    radii, kept_margins = _kept(screens, parts)
    assert np.array_equal(radii, fresh.max(axis=1))
    assert np.array_equal(kept_margins, on_plants.min(axis=1))
    fresh = loop.modulus_margins(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, n=bank.n)
    kept = predictive.filter_margins(bank, bank.gains, law)
    assert np.array_equal(kept, fresh)
    # the description reads the screen's sweep
    assert mpc.observer_description()["modulus_margin_prior"] == float(fresh[bank.prior])


def test_a_box_screen_input_changed_in_its_last_bit_is_screened_afresh(mpc, monkeypatch) -> None:
    screens = _fresh_cache(monkeypatch, predictive, "_box_screens")
    margins = _fresh_cache(monkeypatch, predictive, "_margins")
    law, plants = mpc.feedback_law(), mpc.box_plants()
    bank = ObserverBank.for_controller(mpc.model, mpc.task, mpc.settings)
    predictive.screen_bank(bank, law, plants)
    moved = [(_nudged(plants[3][0]), *plants[3][1:]), *plants[1:]]
    for count, (k_e, k_z, on) in enumerate(
        [(_nudged(law[0]), law[1], plants), (law[0], np.nextafter(law[1], 2.0), plants)],
        start=2,
    ):
        predictive.screen_bank(bank, (k_e, k_z), on)
        assert (screens.misses, margins.misses) == (count, count)
    predictive.screen_bank(bank, law, moved)  # the plants are the screen's only
    assert (screens.misses, margins.misses, margins.hits) == (4, 3, 1)
    bank._gains[0, 0] = np.nextafter(bank._gains[0, 0], np.inf)
    predictive.screen_bank(bank, law, plants)
    assert (screens.misses, margins.misses) == (5, 4)


def test_box_screens_cannot_change_each_others_results(mpc, monkeypatch) -> None:
    _fresh_cache(monkeypatch, predictive, "_box_screens")
    _fresh_cache(monkeypatch, predictive, "_margins")
    law = mpc.feedback_law()
    bank = ObserverBank.for_controller(mpc.model, mpc.task, mpc.settings)
    margins = predictive.filter_margins(bank, bank.gains, law)
    expected = margins.copy()
    margins[:] = -1.0
    assert np.array_equal(predictive.filter_margins(bank, bank.gains, law), expected)
    parts = [bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, mpc.box_plants()]
    predictive.screen_bank(bank, law, mpc.box_plants())
    radii, on_plants = _kept(predictive._box_screens, parts)
    expected = radii.copy(), on_plants.copy()
    radii[:] = -1.0
    on_plants[:] = -1.0
    again = _kept(predictive._box_screens, parts)
    assert all(np.array_equal(x, y) for x, y in zip(again, expected, strict=True))


def test_kept_box_plants_are_the_fresh_ones_to_the_bit(mpc, monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, predictive, "_box_plants")

    def plants_of(model):  # a task without a datasheet: the mode-by-mode vertices alone
        task = dataclasses.replace(mpc.task, datasheet=None)
        holder = types.SimpleNamespace(model=model, task=task, _box_plants=None)
        return PredictiveController.box_plants(holder)

    first, again = plants_of(mpc.model), plants_of(mpc.model)
    assert (cache.misses, cache.hits) == (1, 1)
    box = ToleranceBox()
    fresh = [m for _, m in vertex_models(mpc.model, box, further_modes=True)]
    matched = dataclasses.replace(box, gain=0.0)
    fresh += [m for _, m in vertex_models(mpc.model, matched, further_modes=True)]
    assert len(first) == len(fresh) == 12
    for plants in (first, again):
        for (a, b, c), model in zip(plants, fresh, strict=True):
            assert all(np.array_equal(x, y) for x, y in ((a, model.a), (b, model.b), (c, model.c)))
    first[0][0][:] = -1.0  # a caller's copy
    assert np.array_equal(plants_of(mpc.model)[0][0], fresh[0].a)
    for changed in ("a", "b", "c"):
        nudged = dataclasses.replace(mpc.model, **{changed: _nudged(getattr(mpc.model, changed))})
        plants_of(nudged)
    plants_of(dataclasses.replace(mpc.model, dt=np.nextafter(mpc.model.dt, 1.0)))
    assert cache.misses == 5
    # With the bender's datasheet, every vertex a second time, moved by its physics.
    with_physics = mpc.box_plants()
    assert len(with_physics) == 24 and mpc.box_plant_counts["datasheet"] == 12
    for (a, b, c), model in zip(with_physics, fresh, strict=False):
        assert all(np.array_equal(x, y) for x, y in ((a, model.a), (b, model.b), (c, model.c)))
    assert mpc.describe()["observer"]["box_screen"]["vertex_plants"] == mpc.box_plant_counts


# -- generated code and the graphs it is generated from (controllers.native) -------------------


def _probe(constant: float = 2.0) -> casadi.Function:
    x = casadi.SX.sym("x", 3)
    return casadi.Function("design_cache_probe", [x], [casadi.sin(x) * constant + casadi.sumsqr(x)])


def test_kept_generated_c_is_casadis_to_the_byte(monkeypatch, tmp_path) -> None:
    cache = _fresh_cache(monkeypatch, codegen, "_sources")
    first = codegen.generated_c("probe.c", [_probe()])
    again = codegen.generated_c("probe.c", [_probe()])  # an equal function built again
    assert (cache.misses, cache.hits) == (1, 1)
    generator = casadi.CodeGenerator("probe.c", {"with_header": False})
    generator.add(_probe())
    generator.generate(f"{tmp_path}/")
    assert first == again == (tmp_path / "probe.c").read_bytes()
    assert codegen.generated_text("probe.c", [_probe()]) == (tmp_path / "probe.c").read_text(
        encoding="utf-8"
    )
    nudged = codegen.generated_c("probe.c", [_probe(np.nextafter(2.0, 3.0))])
    other_name = codegen.generated_c("other.c", [_probe()])
    assert cache.misses == 3 and nudged != first and other_name != first


def _nls(out_weight: float = 0.5):
    return handmade_nls(out_weight)


def test_kept_inverse_graphs_are_the_fresh_ones(monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, compiled_inverse, "_graphs")
    first = CompiledInverse(_nls(), (-5.0, 5.0))
    again = CompiledInverse(_nls(), (-5.0, 5.0))  # an equal NLS of its own
    if first.functions is None:
        pytest.skip(f"no compiled inverse here: {first.backend}")
    assert (cache.misses, cache.hits) == (2, 2)
    fresh = (inverse_function(_nls()), reachable_function(_nls()))
    for inverse in (first, again):
        for kept, built in zip(inverse.functions, fresh, strict=True):
            assert kept.serialize() == built.serialize()
    assert all(a is not b for a, b in zip(first.functions, again.functions, strict=True))
    state = _nls().initial_state()
    for target in (-3.0, 0.25, 4.0):
        one, other = first.solve(target, state), again.solve(target, state)
        assert (one.u, one.z, one.status) == (other.u, other.z, other.status)
        assert np.array_equal(one.state, other.state)
    CompiledInverse(_nls(np.nextafter(0.5, 1.0)), (-5.0, 5.0))
    CompiledInverse(_nls(), (-5.0, 5.0), max_iter=39)  # the inverse's settings are keyed
    assert (cache.misses, cache.hits) == (5, 3)


def test_kept_z_bounds_are_the_fresh_ones(monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, prediction, "_z_bounds_kept")
    nonlinearity = prediction.IdentifiedNLS(_nls(), (-5.0, 5.0))
    first = prediction._z_bounds(nonlinearity)
    again = prediction._z_bounds(prediction.IdentifiedNLS(_nls(), (-5.0, 5.0)))
    assert first == again == prediction._triangle_extremes(nonlinearity)
    assert (cache.misses, cache.hits) == (1, 1)
    prediction._z_bounds(prediction.IdentifiedNLS(_nls(np.nextafter(0.5, 1.0)), (-5.0, 5.0)))
    prediction._z_bounds(prediction.IdentifiedNLS(_nls(), (-5.0, np.nextafter(5.0, 6.0))))
    assert (cache.misses, cache.hits) == (3, 1)
    affine = AffineNonlinearity()  # says nothing about what it computes from: not kept
    assert prediction._z_bounds(affine) == prediction._triangle_extremes(affine)
    assert cache.misses == 3


def test_kept_partials_are_the_fresh_ones(monkeypatch) -> None:
    cache = _fresh_cache(monkeypatch, nmpc_step, "_partials")
    first, again = nmpc_step.partials_function(_nls()), nmpc_step.partials_function(_nls(0.9))
    assert (cache.misses, cache.hits) == (1, 1)  # the network is not differentiated
    assert first is not again
    assert first.serialize() == again.serialize() == nmpc_step._partials_of(_nls()).serialize()
    longer = handmade_nls(0.5)
    longer = type(longer)(
        PastInputFeatures(n_past=1, initial_input=np.nextafter(0.0, 1.0)),
        longer.arrays(),
        u_range=longer.u_range,
    )
    nmpc_step.partials_function(longer)
    assert cache.misses == 2


def test_a_bank_takes_its_ratios_as_any_sequence(monkeypatch) -> None:
    _fresh_cache(monkeypatch, observer_module, "_bank_designs")
    a, b, c = first_mode()
    given = ObserverBank(a, b, c, measurement_std=SIGMA, process_ratios=range(0, 2))
    listed = ObserverBank(a, b, c, measurement_std=SIGMA, process_ratios=[0, 1])
    for got, want in zip(_bank_arrays(given), _bank_arrays(listed), strict=True):
        assert np.array_equal(got, want)


def test_a_vertex_whose_datasheet_fit_is_unstable_is_left_out_and_counted(mpc, monkeypatch):
    """A vertex moved by the datasheet's physics whose fit comes out unstable has no plant to
    screen on: it is left out and the description counts it; any other error of the fit
    propagates (a bad datasheet is not screened around)."""
    from controllers.tolerance_box import UnstableFitError

    original = predictive.task_datasheet_model

    def unstable_above_nominal(arx, task, vertex, order):
        if vertex.resonance > 1.0:
            raise UnstableFitError("forced")
        return original(arx, task, vertex, order)

    def plants_with(fit):
        _fresh_cache(monkeypatch, predictive, "_box_plants")
        monkeypatch.setattr(predictive, "task_datasheet_model", fit)
        holder = types.SimpleNamespace(model=mpc.model, task=mpc.task, _box_plants=None)
        return PredictiveController.box_plants(holder), holder.box_plant_counts

    plants, counts = plants_with(unstable_above_nominal)
    # 12 vertices (8 of the box, 4 with the gain matched), half of them above the resonance.
    assert counts == {"mode_by_mode": 12, "datasheet": 6, "datasheet_asked": 12}
    assert len(plants) == 18

    def broken(arx, task, vertex, order):
        raise ValueError("a datasheet the FE model refuses")

    with pytest.raises(ValueError, match="refuses"):
        plants_with(broken)
