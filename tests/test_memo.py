"""Design results kept by content: a change in any input's last bit computes afresh, callers get
their own copies, failures are not kept, and the least recently used result goes first."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from piezo_env.memo import ContentCache, content_key


@dataclass(frozen=True)
class _Settings:
    weight: float = 1.0
    pair: tuple[float, float] = (0.01, 0.04)


def test_the_key_sees_every_bit_dtype_and_shape():
    a = np.linspace(0.0, 1.0, 6)
    nudged = a.copy()
    nudged[3] = np.nextafter(nudged[3], 2.0)
    base = content_key([a, _Settings(), 3])
    assert content_key([a.copy(), _Settings(), 3]) == base
    strided = np.arange(12.0)[::2]
    assert content_key([strided]) == content_key([strided.copy()])
    square = np.arange(6.0).reshape(2, 3)
    assert content_key([np.asfortranarray(square)]) == content_key([square])
    for other in (
        [nudged, _Settings(), 3],
        [a.reshape(2, 3), _Settings(), 3],
        [a.astype(np.float32), _Settings(), 3],
        [a, _Settings(weight=np.nextafter(1.0, 2.0)), 3],
        [a, _Settings(), 4],
        [a, 3, _Settings()],
        [(a,), _Settings(), 3],
    ):
        assert content_key(other) != base


def test_nested_and_large_arrays_are_keyed_by_every_bit_and_opaque_objects_refused():
    big = np.zeros(2000)
    other = big.copy()
    other[1000] = 1e-300  # where a printed array would show "..."
    assert content_key([(big,)]) != content_key([(other,)])
    assert content_key([{"x": [big]}]) != content_key([{"x": [other]}])
    with pytest.raises(ValueError, match="object array"):
        content_key([np.array([1, None], dtype=object)])
    with pytest.raises(ValueError, match="cannot key on a object"):
        content_key([object()])


def test_results_are_computed_once_and_every_caller_gets_a_copy():
    cache = ContentCache(2)
    calls = []

    def compute():
        calls.append(1)
        return {"radii": np.arange(3.0)}

    first = cache.get([np.ones(2)], compute)
    first["radii"][0] = -1.0
    again = cache.get([np.ones(2)], compute)
    assert len(calls) == 1 and again["radii"][0] == 0.0
    assert (cache.hits, cache.misses) == (1, 1)
    cache.get([np.zeros(2)], compute)
    cache.get([np.ones(2)], compute)  # most recent now: zeros is the oldest
    cache.get([np.full(2, 2.0)], compute)  # drops zeros
    assert len(calls) == 3
    cache.get([np.ones(2)], compute)
    assert len(calls) == 3
    cache.get([np.zeros(2)], compute)
    assert len(calls) == 4


def test_what_the_first_caller_keeps_of_its_result_cannot_change_the_cache():
    cache = ContentCache(2)
    mine = np.arange(3.0)  # the caller's own array, which its result holds
    first = cache.get([mine], lambda: {"model": mine})
    assert first["model"] is mine
    mine[0] = 7.0  # the caller changes its own model after the build
    assert cache.get([np.arange(3.0)], lambda: {"model": None})["model"][0] == 0.0


def test_a_failure_is_raised_each_time_and_not_kept():
    cache = ContentCache(1)

    def fail():
        raise ValueError("no stabilising gains")

    for _ in range(2):
        with pytest.raises(ValueError, match="no stabilising gains"):
            cache.get([1.0], fail)
    assert cache.misses == 0
    with pytest.raises(ValueError, match="size must be an integer >= 1"):
        ContentCache(0)


def test_inputs_without_a_key_are_computed_each_time_and_not_kept():
    cache = ContentCache(2)
    calls = []

    def compute():
        calls.append(1)
        return [1.0]

    for parts in (None, [object()], [np.array([1, None], dtype=object)]):
        for _ in range(2):
            assert cache.get_or_compute(parts, compute) == [1.0]
    assert len(calls) == 6 and (cache.hits, cache.misses) == (0, 0)
    first = cache.get_or_compute([np.ones(2)], compute)
    first.append(2.0)
    assert cache.get_or_compute([np.ones(2)], compute) == [1.0]
    assert len(calls) == 7 and (cache.hits, cache.misses) == (1, 1)
