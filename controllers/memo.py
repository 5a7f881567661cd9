"""Results of pure, costly design computations kept by the content of their inputs.

A controller's design (a PID's box tuning, the adaptive MPC's stability screen of every filter
on every member) is a deterministic function of numbers: the model's matrices, the sample time
and the settings. A benchmark builds the same controller for every plant it runs, and a test
suite in many tests; :class:`ContentCache` lets each design be computed once per process. The
key is a digest of the inputs' exact bytes (arrays) and representations (everything else), so a
changed input, even in its last bit, computes afresh; every caller gets its own deep copy, so no
controller can change another's design.
"""

from __future__ import annotations

import copy
import hashlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any, TypeVar

import numpy as np

__all__ = ["ContentCache", "content_key"]

T = TypeVar("T")


def content_key(parts: Iterable[Any]) -> bytes:
    """SHA-256 digest of ``parts``: each array by its dtype, shape and bytes (C order), anything
    else by its ``repr`` (settings dataclasses, numbers, strings)."""
    digest = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            array = np.ascontiguousarray(part)
            digest.update(f"{array.dtype.str}{array.shape}".encode())
            digest.update(array.tobytes())
        else:
            digest.update(repr(part).encode())
        digest.update(b"\x00")
    return digest.digest()


class ContentCache:
    """The last ``size`` results of a computation, by :func:`content_key` of its inputs.

    Parameters
    ----------
    size : int
        Results kept (least recently used dropped first), >= 1.
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
        key = content_key(parts)
        if key in self._results:
            self._results.move_to_end(key)
            self.hits += 1
        else:
            self._results[key] = compute()
            self.misses += 1
            if len(self._results) > self.size:
                self._results.popitem(last=False)
        return copy.deepcopy(self._results[key])

    def clear(self) -> None:
        """Forget every result."""
        self._results.clear()
