"""The designs the controllers keep by content (:mod:`controllers.memo`): a kept result is the
fresh computation to the bit, an input changed in its last bit computes afresh, and no caller
can change another's copy."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from handmade import first_mode

import controllers.observer as observer_module
from controllers.memo import ContentCache
from controllers.observer import DISTURBANCE_RATIOS, PROCESS_RATIOS, ObserverBank

SIGMA = 0.5  # sensor noise (um)


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
