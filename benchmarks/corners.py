"""The corners of the datasheet's tolerance box: every controller on every bender a user can buy.

A bender bought to the datasheet is one draw from its tolerances. The tip's response to the
voltage depends on three of them (free deflection: the static gain; first resonance; its
damping ratio; the blocking force changes the stiffness and the piezo moment together and leaves
the response as it is), so the 8 vertices of free deflection +-20 % x resonance +-20 % x damping
0.01 / 0.04 are the extremes of what a controller meets (hysteresis at its nominal strength).
Each controller is built for the nominal bender, from the identified model of the committed
benchmark run (``docs/benchmark/model``), and runs unchanged on each vertex, as in
``piezo benchmark``; ``mpc-oracle`` is the same MPC on the vertex's own model (the achievable
floor) and ``mpc, model's gain`` the MPC that predicts with the identified gain
(``gain_tolerance=0``), the design before the gain was learned. Whole 2 s episodes, seed 0,
noise on, preview 20; RMSE in % of the full stroke, and for ``mpc-adaptive`` the RMSE over the
second half and its settling time in parentheses (when the RMS error over 50 ms windows last
came within twice the second half's: :func:`settling_ms`).

Run: ``python -m benchmarks.corners`` (about three minutes on 2 cores).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from benchmarks._common import header, markdown_table, write_result
from benchmarks.plants import VERTICES, vertex_options

MODEL_DIR = "docs/benchmark/model"
BENDER = "PL140"
REFERENCES_RUN = ("sine-10Hz", "sine-50Hz", "multisine")
ROWS = {
    "mpc-oracle": ("mpc", {}),
    "mpc, model's gain": ("mpc", {"gain_tolerance": 0.0}),
    "mpc": ("mpc", {}),
    "mpc-adaptive": ("mpc-adaptive", {}),
    "pid-notch": ("pid-notch", {}),
    "pid-ff": ("pid-ff", {}),
}
STEPS = 2000
STROKE_UM = 1000.0


def vertex_env(vertex: tuple[float, float, float], **options: Any) -> Any:
    """``PiezoBender-v0`` on one vertex (free deflection, resonance, damping) of the box."""
    import gymnasium as gym

    return gym.make(
        "piezo_env:PiezoBender-v0",
        preview=20,
        max_episode_steps=STEPS,
        **vertex_options(BENDER, vertex),
        **options,
    )


def settling_ms(error: np.ndarray, dt: float = 1e-3, window_s: float = 0.05) -> float:
    """When (ms) the RMS error over consecutive ``window_s`` windows last came within twice its
    second-half value: the end of the first window from which every later window stays there."""
    width = round(window_s / dt)
    half = np.sqrt(np.mean(error[error.size // 2 :] ** 2))
    windows = np.sqrt(np.mean(error[: error.size // width * width].reshape(-1, width) ** 2, axis=1))
    above = np.flatnonzero(windows > 2.0 * half)
    return float((above[-1] + 2 if above.size else 1) * width * dt * 1e3)


def run_vertex(vertex: tuple[float, float, float]) -> dict[tuple[str, str], tuple[float, ...]]:
    """(row, reference) -> (RMSE, second-half RMSE in % of the full stroke, settling in ms)
    on one vertex."""
    import gymnasium as gym
    from threadpoolctl import threadpool_limits

    import controllers as ctl
    from benchmarks.references import make_reference

    env = vertex_env(vertex)
    nominal = gym.make("piezo_env:PiezoBender-v0", preview=20, max_episode_steps=STEPS)
    out = {}
    with threadpool_limits(1):
        for row, (name, options) in ROWS.items():
            model = MODEL_DIR
            if row.endswith("-oracle"):
                model = ctl.PredictionModel.from_plant(env.unwrapped.model)
            controller = ctl.make(name, model, nominal, **options)
            for ref_name in REFERENCES_RUN:
                reference = make_reference(ref_name, STEPS + 1, dt=1e-3, seed=0)
                episode = ctl.run_episode(
                    env, controller, seed=0, reference=reference, stroke_um=STROKE_UM
                )
                error = episode.deflection_um - episode.reference_um
                half = np.sqrt(np.mean(error[error.size // 2 :] ** 2)) / (2 * STROKE_UM) * 100
                out[row, ref_name] = (
                    episode.metrics["rmse_percent"],
                    float(half),
                    settling_ms(error),
                )
    return out


def _cell(value: float) -> str:
    return "diverged" if not math.isfinite(value) or value > 100 else f"{value:.3f}"


def main() -> None:
    results = {vertex: run_vertex(vertex) for vertex in VERTICES}
    lines = header("Controllers on the corners of the PL140's tolerance box", "corners.py")
    lines += [__doc__.split("\n\nRun:")[0].split("\n\n", 1)[1], ""]
    for ref_name in REFERENCES_RUN:
        head = ["free deflection, resonance, damping", *ROWS]
        rows = []
        for vertex, cells in results.items():
            label = f"x{vertex[0]:g}, x{vertex[1]:g}, {vertex[2]:g}"
            row = [label]
            for name in ROWS:
                whole, half, settle = cells[name, ref_name]
                text = _cell(whole)
                if name == "mpc-adaptive":
                    text = f"{text} ({_cell(half)}; {settle:.0f} ms)"
                row.append(text)
            rows.append(row)
        worst = ["worst"]
        for name in ROWS:
            whole = max(cells[name, ref_name][0] for cells in results.values())
            worst.append(f"**{_cell(whole)}**")
        rows.append(worst)
        lines += [f"## {ref_name}", "", markdown_table(head, rows), ""]
    write_result("corners", lines)


if __name__ == "__main__":
    main()
