"""Results of pure, costly design computations kept by the content of their inputs.

A controller's design (a PID's box tuning, an observer bank's Riccati filters, the MPCs'
stability screens, the casadi graphs and generated C of the nonlinearity's inverse), and a
plant's proven bound (the drifting plant's, :mod:`piezo_env.task`), is a deterministic
function of numbers: the model's matrices and parameters, the sample time and the settings. A
benchmark builds the same controller and plant for every run, and a test suite in many tests;
:class:`ContentCache` lets each be computed once per process. It lives in the env's package,
the lowest layer, so that the env and the controllers share it. The key
is a digest of the inputs' exact bytes, so a changed input, even in its last bit, computes
afresh; every caller gets its own deep copy, so no controller can change another's design
(a casadi Function's copy shares its immutable definition). Each cache holds a documented
number of results, derived from what one benchmark worker meets.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import numpy as np

__all__ = ["ContentCache", "content_key"]

T = TypeVar("T")

_SCALARS = (bool, int, float, complex, str, bytes, type(None))


def content_key(parts: Iterable[Any]) -> bytes:
    """SHA-256 digest of ``parts``, exact to the bit.

    Arrays enter by dtype, shape and bytes (C order); tuples, lists, dicts and dataclasses by
    their entries (recursively); scalars, strings and None by ``repr`` (exact for floats).

    Raises
    ------
    ValueError
        For anything else (an object array, an object identified only by its address), whose
        content the key could not see.
    """
    digest = hashlib.sha256()
    _feed(digest, list(parts))
    return digest.digest()


def _feed(digest: Any, part: Any) -> None:
    if isinstance(part, np.ndarray):
        if part.dtype.hasobject:
            raise ValueError("content_key: an object array has no content to key on")
        array = np.ascontiguousarray(part)
        digest.update(f"array{array.dtype.str}{array.shape}".encode())
        digest.update(array.tobytes())
    elif isinstance(part, (np.generic, *_SCALARS)):
        digest.update(f"{type(part).__name__}:{part!r}".encode())
    elif isinstance(part, (tuple, list)):
        digest.update(f"{type(part).__name__}[{len(part)}]".encode())
        for entry in part:
            _feed(digest, entry)
    elif isinstance(part, dict):
        digest.update(f"dict[{len(part)}]".encode())
        for name, entry in part.items():
            _feed(digest, name)
            _feed(digest, entry)
    elif dataclasses.is_dataclass(part) and not isinstance(part, type):
        digest.update(f"{type(part).__qualname__}(".encode())
        for f in dataclasses.fields(part):
            _feed(digest, f.name)
            _feed(digest, getattr(part, f.name))
    else:
        raise ValueError(
            f"content_key: cannot key on a {type(part).__name__}; pass its arrays and numbers"
        )
    digest.update(b"\x00")


class ContentCache:
    """The last ``size`` results of a computation, by :func:`content_key` of its inputs.

    For one thread (each benchmark worker is a process with its own cache).

    Parameters
    ----------
    size : int
        Results kept (least recently used dropped first), >= 1.

    Attributes
    ----------
    hits, misses : int
        Calls answered from the cache, and calls that computed.
    """

    def __init__(self, size: int) -> None:
        if not (isinstance(size, int) and size >= 1):
            raise ValueError(f"size must be an integer >= 1, got {size!r}")
        self.size = size
        self._results: OrderedDict[bytes, Any] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def get(self, parts: Iterable[Any], compute: Callable[[], T]) -> T:
        """A deep copy of ``compute()``'s result for these inputs, computed on the first call
        (an exception is raised each time and nothing is kept)."""
        return self._get(content_key(parts), compute)

    def get_or_compute(self, parts: Iterable[Any] | None, compute: Callable[[], T]) -> T:
        """As :meth:`get`, for inputs whose content may not be known: with ``parts`` None, or
        holding something :func:`content_key` cannot see (an object of a class the caller
        does not know), ``compute()`` runs each time and nothing is kept."""
        if parts is None:
            return compute()
        try:
            key = content_key(parts)
        except ValueError:
            return compute()
        return self._get(key, compute)

    def _get(self, key: bytes, compute: Callable[[], T]) -> T:
        if key in self._results:
            self._results.move_to_end(key)
            self.hits += 1
            return copy.deepcopy(self._results[key])
        # The cache keeps a copy: what compute() returned may hold the caller's own objects
        # (a model's arrays), which the caller may change after.
        result = compute()
        self._results[key] = copy.deepcopy(result)
        self.misses += 1
        if len(self._results) > self.size:
            self._results.popitem(last=False)
        return result

    def clear(self) -> None:
        """Forget every result."""
        self._results.clear()
