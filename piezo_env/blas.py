"""One BLAS thread for the tiny dense work of building a plant.

Building a drawn plant (eigen-decomposition, one matrix exponential per mode) is a handful of
tiny dense calls, and multi-threaded OpenBLAS stalls on those: its threads wake and synchronise
for matrices of a few dozen entries, so a plant takes several times longer and its tail far
longer than on one thread (``benchmarks/results/design_measurements.md``). The limit is scoped:
it holds only inside the ``with`` block.
"""

from __future__ import annotations

import functools
from typing import Any

from threadpoolctl import ThreadpoolController

__all__ = ["single_blas_thread"]


def single_blas_thread() -> Any:
    """Context manager: one BLAS thread inside (for building tiny models)."""
    return _blas_controller().limit(limits=1)


@functools.cache
def _blas_controller() -> ThreadpoolController:
    """One controller per process (creating one scans the loaded libraries, ~1 ms)."""
    return ThreadpoolController()
