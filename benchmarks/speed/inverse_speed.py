"""NLS inverse speed: the identified nonlinearity's inverse per call, three methods.

A closed-loop-like sequence: hidden-signal targets z_t from sines of 10, 20 and 50 Hz (24 V
amplitude, 1 kHz sampling) through the shipped model's NLS (``docs/identify/model``), inverted
sample by sample with the memory state carried, as a controller does. Old: a grid (65 points)
plus Brent's method, the derivative-free baseline; numpy: ``NLS.solve_inverse`` (one
batched grid pass, then safeguarded Newton); compiled: the generated-C inverse the controllers
use (:class:`controllers.native.compiled_inverse.CompiledInverse`: range ends, warm start, then
Newton with the exact derivative, in one ctypes call). Each call is timed with
``time.perf_counter``; a
CartPole-v1 step through ``gymnasium.make`` is measured in the same run, in alternating rounds,
as the reference. BLAS is limited to one thread (threadpoolctl) for the whole run. Writes
``benchmarks/results/inverse_speed.md``.

Run: ``python -m benchmarks.speed.inverse_speed`` (about ten seconds; the first run also compiles
the inverse, a few seconds).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import scipy.optimize
import threadpoolctl

from benchmarks._common import header, markdown_table, single_env_step_times, write_result
from controllers.native.compiled_inverse import CompiledInverse
from identification.hammerstein import HammersteinModel

MODEL = Path(__file__).resolve().parents[2] / "docs" / "identify" / "model"
FREQUENCIES = (10.0, 20.0, 50.0)
SAMPLES = 1000  # per frequency, 1 kHz
ROUNDS = 5
CARTPOLE_STEPS = 4000  # per round


def _network_size(hidden: tuple[int, ...]) -> str:
    """``3 x 32`` for three layers of 32, ``16-8`` for unequal widths."""
    if len(set(hidden)) == 1:
        return f"{len(hidden)} x {hidden[0]}"
    return "-".join(map(str, hidden))


def old_solve_inverse(nls, target: float, state: np.ndarray, n_grid: int = 65):
    """The baseline: a grid over the range, Brent's method in each sign change.

    Returns (u, state after u).
    """
    fm, mlp = nls.feature_map, nls.to_numpy()
    low, high = nls.u_range
    grid = np.linspace(low, high, n_grid)
    residual = mlp(fm.candidates(grid, state)) - target
    u_ref = float(state[0])

    def residual_at(u: float) -> float:
        return mlp.evaluate_one(fm.step(u, state)[0]) - target

    brackets = np.flatnonzero(np.sign(residual[:-1]) * np.sign(residual[1:]) < 0.0)
    roots = [float(grid[i]) for i in np.flatnonzero(residual == 0.0)]
    roots += [
        scipy.optimize.brentq(residual_at, grid[i], grid[i + 1], xtol=1e-10) for i in brackets
    ]
    if roots:
        u = min(roots, key=lambda root: abs(root - u_ref))
    else:
        u = float(grid[int(np.argmin(np.abs(residual)))])
    return u, fm.step(u, state)[1]


def new_solve_inverse(nls, target: float, state: np.ndarray):
    """``NLS.solve_inverse``; returns (u, state after u)."""
    result = nls.solve_inverse(target, state)
    return result.u, result.state


def compiled_solver(inverse: CompiledInverse):
    """The compiled inverse as a solver ``(nls, target, state) -> (u, state after u)``."""

    def solve(nls, target: float, state: np.ndarray):
        result = inverse.solve(target, state)
        return result.u, result.state

    return solve


def compiled_passes(inverse: CompiledInverse, z: np.ndarray) -> float:
    """Mean network passes per compiled call over the sequence (ends, warm start, Newton)."""
    state, passes = inverse.map.nls.initial_state(), 0
    for target in z:
        state = inverse.solve(float(target), state).state
        passes += inverse.passes
    return passes / z.size


def inverse_times(nls, solver, u_true: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, float]:
    """Per-call wall times (s) over the sequence and the largest voltage error (V)."""
    state = nls.initial_state()
    times = np.empty(z.size)
    error = 0.0
    clock = time.perf_counter
    for t, target in enumerate(z):
        start = clock()
        u, state = solver(nls, float(target), state)
        times[t] = clock() - start
        error = max(error, abs(u - u_true[t]))
    return times, error


def pass_statistics(nls, z: np.ndarray) -> tuple[float, float]:
    """Mean batched network passes per new inverse call, and the median time (s) of one pass
    of two rows (features + network), the unit a Newton step costs."""
    fm = nls.feature_map
    passes = 0
    state = nls.initial_state()
    original = fm.candidates

    def counting(u, s):
        nonlocal passes
        passes += 1
        return original(u, s)

    object.__setattr__(fm, "candidates", counting)
    try:
        for target in z:
            state = nls.solve_inverse(float(target), state).state
    finally:
        object.__delattr__(fm, "candidates")
    rows, mlp = np.array([1.0, 1.0 + 6e-6]), nls.to_numpy()
    times = np.empty(2000)
    for i in range(times.size):
        start = time.perf_counter()
        mlp.evaluate_rows(fm.candidates(rows, state))
        times[i] = time.perf_counter() - start
    return passes / z.size, float(np.median(times))


def targets(nls) -> tuple[np.ndarray, np.ndarray]:
    """(u, z): the sine sequences back to back and their NLS output from rest."""
    t = np.arange(SAMPLES) * 1e-3
    u = np.concatenate([24.0 * np.sin(2 * np.pi * f * t) for f in FREQUENCIES])
    return u, nls.evaluate(u)


METHODS = (
    ("old", "grid (65) + brentq (before)"),
    ("new", "NLS.solve_inverse, numpy"),
    ("compiled", "compiled inverse (generated C)"),
)


def run_rounds(nls, solvers: dict, u_true: np.ndarray, z: np.ndarray) -> tuple[dict, dict]:
    """Per-call times of each solver and CartPole steps, ROUNDS rounds back to back, and the
    largest voltage error of each solver."""
    results: dict[str, list[np.ndarray]] = {name: [] for name in (*solvers, "cart")}
    errors = dict.fromkeys(solvers, 0.0)
    for r in range(ROUNDS):
        for name, solver in solvers.items():
            times, error = inverse_times(nls, solver, u_true, z)
            results[name].append(times)
            errors[name] = max(errors[name], error)
        results["cart"].append(single_env_step_times("CartPole-v1", CARTPOLE_STEPS, seed=r))
    return results, errors


def result_rows(results: dict, errors: dict, cart: float) -> list[list[str]]:
    """Table rows: median and p99 per call (medians over rounds), ratio to CartPole, error."""
    rows = []
    for name, label in METHODS:
        median = float(np.median([np.median(t) for t in results[name]]))
        p99 = float(np.median([np.percentile(t, 99) for t in results[name]]))
        calls = sum(t.size for t in results[name])
        rows.append(
            [
                label,
                f"{median * 1e6:.1f}",
                f"{p99 * 1e6:.1f}",
                f"{median / cart:.2f}",
                f"{errors[name]:.1e}",
                f"{calls}",
            ]
        )
    return rows


def speedup(results: dict, slow: str, fast: str) -> float:
    """Median of the per-round ratios of median call times."""
    pairs = zip(results[slow], results[fast], strict=True)
    return float(np.median([np.median(s) / np.median(f) for s, f in pairs]))


def main() -> None:
    nls = HammersteinModel.load(MODEL).nls
    u_true, z = targets(nls)
    inverse = CompiledInverse(nls, nls.u_range)
    if not inverse.compiled:
        raise SystemExit(f"the compiled inverse is unavailable: {inverse.backend}")
    solvers = {
        "old": old_solve_inverse,
        "new": new_solve_inverse,
        "compiled": compiled_solver(inverse),
    }
    with threadpoolctl.threadpool_limits(limits=1, user_api="blas"):
        results, errors = run_rounds(nls, solvers, u_true, z)
        mean_passes, pass_time = pass_statistics(nls, z)
        passes_c = compiled_passes(inverse, z)
        head = header("NLS inverse speed", __spec__.name)
    cart = float(np.median([np.median(t) for t in results["cart"]]))
    lines = [
        *head,
        f"Model: `docs/identify/model` ({nls!r}). Targets: z of 24 V sines at "
        f"{', '.join(f'{f:g}' for f in FREQUENCIES)} Hz (1 kHz sampling, {SAMPLES} samples "
        "each), inverted sample by sample with the memory state carried. BLAS limited to one "
        "thread (threadpoolctl) for the whole run. Medians and p99 are medians over "
        f"{ROUNDS} rounds; each round times the three methods and {CARTPOLE_STEPS} CartPole-v1 "
        "steps (gym.make, random actions) back to back.",
        "",
        markdown_table(
            [
                "method",
                "median us/call",
                "p99 us/call",
                "median / CartPole step",
                "max |u - u_true| (V)",
                "calls",
            ],
            result_rows(results, errors, cart),
        ),
        "",
        f"CartPole-v1 step (same run): median {cart * 1e6:.2f} us. Speed-up (median of "
        f"per-round ratios): numpy / old {speedup(results, 'old', 'new'):.1f}x, compiled / "
        f"numpy {speedup(results, 'new', 'compiled'):.1f}x. Target: <= 20 us median, exact to "
        "1e-6 V.",
        "",
        f"The numpy method makes {mean_passes:.2f} batched network passes per call on average "
        "(a grid pass for the reachable range and the bracket, then Newton passes of two "
        "rows); one two-row pass (features + "
        f"{_network_size(nls.hidden)} tanh network in numpy) costs "
        f"{pass_time * 1e6:.1f} us here, so numpy's per-call overhead on these tiny arrays, not "
        "the algorithm, sets its floor near two such passes plus the final state update.",
        "",
        f"The compiled inverse makes {passes_c:.2f} scalar network passes per call in generated "
        "C (both range ends and the warm start without derivative, then Newton passes with the "
        "exact derivative; about 1.5 and 2.9 us each), in one ctypes call from preallocated "
        f"buffers; backend: {inverse.backend}.",
    ]
    write_result("inverse_speed", lines)


if __name__ == "__main__":
    main()
