"""One BLAS thread for the tiny dense work of building a plant.

Building a drawn plant (eigen-decomposition, one matrix exponential per mode) is a handful of
tiny dense calls, and multi-threaded OpenBLAS stalls on those (measured on 2 cores: median
9.7 ms, p90 220 ms per plant, against 1.4 ms and 9.6 ms single-threaded). The limit is scoped:
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
