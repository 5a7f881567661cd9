"""Controller latency: compute time per step of every controller, against a CartPole-v1 step.

Each controller runs closed loop on PiezoBender-v0 (PL140, noise on, preview 20) tracking a
half-stroke 50 Hz sine, with one BLAS thread (threadpoolctl); the time of each ``act`` call
(observer, solver, inverse: everything) is recorded, and a step longer than the sample time is
a deadline miss. The adaptive MPC also runs where it adapts (the box's corner with its gain 20 %
up, its resonance 20 % low, damping 0.04), and the MPCs run on the PL127 at its own 0.25 ms (model
``tests/data/pl127-model``; on its corner with gain and resonance 20 % up, damping 0.01).
Beside it, in the same process: the OSQP solve alone (the MPC forced to call OSQP at every
step), the nonlinearity inverse alone, and a CartPole-v1 step through ``gymnasium.make``, the
reference the ratios are taken against (absolute times on shared machines drift; ratios
travel). IPOPT (``nmpc-ipopt``) runs a shorter
episode. Writes ``benchmarks/results/controller_latency.md``.

Run: ``python -m benchmarks.controller_latency`` (a few minutes).
"""

from __future__ import annotations

import time

import gymnasium as gym
import numpy as np
from threadpoolctl import threadpool_limits

import controllers
import piezo_env  # noqa: F401  (registers PiezoBender-v0)
from benchmarks._common import header, markdown_table, single_env_step_times, write_result
from benchmarks.corners import vertex_env
from benchmarks.plants import EPISODE_S, sample_time

MODEL_DIR = "docs/identify/model"
PL127_MODEL = "tests/data/pl127-model"
STEPS = 2000
IPOPT_STEPS = 200


def timed(obj: object, name: str, sink: list[float]) -> None:
    """Wrap ``obj.name`` so that each call's wall time (us) goes into ``sink``."""
    method = getattr(obj, name)

    def wrapper(*args, **kwargs):
        start = time.perf_counter()
        out = method(*args, **kwargs)
        sink.append((time.perf_counter() - start) * 1e6)
        return out

    setattr(obj, name, wrapper)


def controller_times(
    env, name: str, steps: int, plant=None, model: str = MODEL_DIR, **options
) -> dict[str, np.ndarray]:
    """Step times (us) of one controller, plus its QP and inverse times where it has them.

    The controller is built from ``model`` for ``env``'s (nominal) task and runs on ``plant``
    (default: ``env``), as in the benchmark.
    """
    c = controllers.make(name, model, env, **options)
    parts: dict[str, list[float]] = {"qp": [], "inverse": []}
    if hasattr(c, "_setup_solver"):
        # The OSQP solver is set up afresh at each reset: time the solve of each new one.
        setup = c._setup_solver

        def timed_setup(*args, **kwargs):
            solver = setup(*args, **kwargs)
            timed(solver, "solve", parts["qp"])
            return solver

        c._setup_solver = timed_setup
    nonlinearity = getattr(getattr(c, "model", None), "nonlinearity", None)
    if nonlinearity is not None:
        timed(nonlinearity, "inverse", parts["inverse"])
    dt = env.unwrapped.model.dt
    stroke = env.unwrapped.model.stroke_um
    t = np.arange(1, steps + 22) * dt
    reference = 0.5 * stroke * np.sin(2 * np.pi * 50.0 * t)
    episode = controllers.run_episode(
        plant or env, c, seed=0, reference=reference, max_steps=steps, stroke_um=stroke
    )
    return {
        "step": episode.compute_s * 1e6,
        "misses": np.array([int(np.sum(episode.compute_s > dt))]),
        "qp": np.asarray(parts["qp"]),
        "inverse": np.asarray(parts["inverse"]),
        "rmse": np.array([episode.metrics["rmse_percent"]]),
    }


def stats(x: np.ndarray) -> tuple[str, str, str]:
    if x.size == 0:
        return ("-", "-", "-")
    return tuple(f"{v:.1f}" for v in np.quantile(x, [0.5, 0.99, 1.0]))


def main() -> None:
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    corner = vertex_env((1.2, 0.8, 0.04))
    dt127 = sample_time("PL127")
    steps127 = round(EPISODE_S / dt127)
    env127 = gym.make(
        "piezo_env:PiezoBender-v0",
        bender="PL127",
        preview=20,
        dt=dt127,
        max_episode_steps=steps127,
    )
    corner127 = vertex_env((1.2, 1.2, 0.01), "PL127")
    pl127 = {"env": env127, "model": PL127_MODEL}
    runs = [
        ("pid", "pid", STEPS, {}),
        ("pid-notch", "pid-notch", STEPS, {}),
        ("pid-ff", "pid-ff", STEPS, {}),
        ("mpc", "mpc", STEPS, {}),
        ("mpc (OSQP every step)", "mpc", STEPS, {"shortcut": False}),
        ("mpc-adaptive", "mpc-adaptive", STEPS, {}),
        ("mpc-adaptive (corner x1.2, x0.8, 0.04)", "mpc-adaptive", STEPS, {"plant": corner}),
        ("nmpc", "nmpc", STEPS, {}),
        ("nmpc-ipopt", "nmpc-ipopt", IPOPT_STEPS, {}),
        ("mpc (PL127, 0.25 ms)", "mpc", steps127, pl127),
        ("mpc-adaptive (PL127, 0.25 ms)", "mpc-adaptive", steps127, pl127),
        (
            "mpc-adaptive (PL127 corner x1.2, x1.2, 0.01)",
            "mpc-adaptive",
            steps127,
            {**pl127, "plant": corner127},
        ),
    ]
    rows = []
    with threadpool_limits(1):
        cart = single_env_step_times("CartPole-v1", 20_000) * 1e6
        cart_median = float(np.median(cart))
        for label, name, steps, options in runs:
            options = dict(options)
            run_env = options.pop("env", env)
            try:
                r = controller_times(run_env, name, steps, **options)
            except Exception as error:  # a missing optional solver must not hide the rest
                rows.append([label, f"failed: {error}", "", "", "", "", "", "", ""])
                continue
            median = float(np.median(r["step"]))
            rows.append(
                [
                    label,
                    *stats(r["step"]),
                    f"{int(r['misses'][0])} of {r['step'].size}",
                    f"{median / cart_median:.1f}",
                    stats(r["qp"])[0],
                    stats(r["inverse"])[0],
                    f"{r['rmse'][0]:.3f}",
                ]
            )
        lines = header("Controller latency (one BLAS thread)", "controller_latency.py")
    lines += [
        f"CartPole-v1 step through gym.make, same run: median {cart_median:.1f} us, p99 "
        f"{np.quantile(cart, 0.99):.1f} us. Episodes: 2 s, noise on, preview 20, half-stroke "
        f"50 Hz sine; PL140 at 1 ms ({STEPS} steps, {IPOPT_STEPS} for IPOPT), PL127 at "
        f"{dt127 * 1e3:g} ms ({steps127} steps). A deadline miss is a step whose compute time "
        "exceeded the sample time (1 ms; 0.25 ms on the PL127). The adaptive MPC updates the "
        "gain estimates of all its models every step and, when the data reject the model in "
        "use, swaps to a model whose QP and observer were built beforehand: no step solves a "
        "Riccati equation or sets up a QP.",
        "",
        markdown_table(
            [
                "controller",
                "step median (us)",
                "step p99 (us)",
                "step max (us)",
                "deadline misses",
                "median / CartPole step",
                "QP solve median (us)",
                "inverse median (us)",
                "RMSE (% stroke)",
            ],
            rows,
        ),
    ]
    write_result("controller_latency", lines)


if __name__ == "__main__":
    main()
