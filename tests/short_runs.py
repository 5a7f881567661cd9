"""Short identification settings the tests share, so that a run several modules need is made
once per session (tests/conftest.py)."""

from __future__ import annotations

FAST = {
    "features": "play",
    "prbs_samples": 2000,
    "rich_samples": 2000,
    "validation_samples": 1000,
    "max_epochs": 10,
    "nls_refinement_iterations": 10,
    "orders": (2, 4),
}
"""The cheapest identification the tests run: short records, one feature set, few iterations;
every step runs, step e' with its learned play radii included."""

FAST_SEED = 3
"""The seed of the shared short run of the PL140."""
