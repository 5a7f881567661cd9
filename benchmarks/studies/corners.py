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
(``gain_tolerance=0``), without learning the plant's gain; ``mpc-adaptive, datasheet set`` the
adaptive MPC whose set moves the identified model by the datasheet's physics
(``member_set="datasheet"``, :func:`controllers.tolerance_box.datasheet_model`) instead of
mode by mode; ``nmpc`` the nonlinear MPC, which learns the gain as ``mpc`` does. Whole 2 s
episodes, seed 0, noise on, preview 20; RMSE in % of the full
stroke, and for the adaptive rows the RMSE over the
second half and two settling times in parentheses: when the RMS error over 50 ms windows last
came within twice the episode's own second half
(:func:`controllers.metrics.window_settling_ms`), and within twice the
second half of ``mpc-oracle`` on the same vertex and reference ("> 2 s" where the last window
is still above). The first is relative: a controller that settles to a lower floor takes
longer to come within twice it, so the second, against one floor for every controller, says
how soon the error is small.

Another bender runs at its own sample time (:func:`benchmarks.plants.sample_time`), on its
own references (the PL140's scaled to its stroke), from a model identified on it:
``python -m benchmarks.studies.corners --bender PL127 --model DIR`` writes ``corners-PL127.md``.

The box's fourth tolerance, the hysteresis strength (+-30 %, as the env's randomisation draws
it: :func:`piezo_env.randomization.scale_hysteresis`, the hysteretic part scaled at the same
major-loop peak), is not a vertex of the table above: the identified model inverts the nominal
strength; ``mpc-adaptive`` learns it (:mod:`controllers.drive`), the other rows do not.
``--hysteresis 0.7 1.3`` runs the same vertices at those strengths instead and writes
``corners[-BENDER]-hysteresis.md``, so what the strength costs is measured, not assumed.

Run: ``python -m benchmarks.studies.corners`` (about three minutes on 2 cores).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks._common import header, markdown_table, write_result
from benchmarks.plants import EPISODE_S, VERTICES, sample_time, stroke_um, vertex_options
from controllers.metrics import window_settling_ms

MODEL_DIR = "docs/benchmark/model"
BENDER = "PL140"
PREVIEW = 20
"""Reference samples each observation previews (as ``piezo benchmark``'s default)."""
REFERENCES_RUN = ("sine-10Hz", "sine-50Hz", "multisine")
ROWS = {
    "mpc-oracle": ("mpc", {}),
    "mpc, model's gain": ("mpc", {"gain_tolerance": 0.0}),
    "mpc": ("mpc", {}),
    "mpc-adaptive": ("mpc-adaptive", {}),
    "mpc-adaptive, datasheet set": ("mpc-adaptive", {"member_set": "datasheet"}),
    "nmpc": ("nmpc", {}),
    "pid-notch": ("pid-notch", {}),
    "pid-ff": ("pid-ff", {}),
}


def vertex_env(
    vertex: tuple[float, float, float],
    bender: str = BENDER,
    hysteresis_scale: float = 1.0,
    **options: Any,
) -> Any:
    """``PiezoBender-v0`` on one vertex (free deflection, resonance, damping) of ``bender``'s
    box, at the bender's benchmark sample time, for one 2 s episode; its hysteresis (the env's
    default, or ``options["hysteresis"]``) with the hysteretic part times ``hysteresis_scale``
    (-)."""
    import gymnasium as gym

    from piezo_env.config import TaskConfig
    from piezo_env.hysteresis import make_hysteresis
    from piezo_env.randomization import scale_hysteresis

    dt = sample_time(bender)
    kwargs = {**vertex_options(bender, vertex), **options}
    if hysteresis_scale != 1.0:  # the map the env would build, scaled
        rated = kwargs["bender"].rated_voltage
        own = make_hysteresis(kwargs.get("hysteresis", TaskConfig.hysteresis), rated, dt=dt)
        kwargs["hysteresis"] = scale_hysteresis(own, hysteresis_scale, rated)
    return gym.make(
        "piezo_env:PiezoBender-v0",
        preview=PREVIEW,
        dt=dt,
        max_episode_steps=round(EPISODE_S / dt),
        **kwargs,
    )


def vertex_reference(name: str, bender: str = BENDER) -> np.ndarray:
    """The reference ``name`` (um) of one episode on ``bender``, seed 0, scaled to its stroke,
    with the PREVIEW samples the last step's observation reads: an array that ends earlier is
    held at its last value by the env, and the controllers would brake for an end the
    reference does not have."""
    from benchmarks.references import make_reference

    dt = sample_time(bender)
    steps = round(EPISODE_S / dt)
    return make_reference(name, steps + PREVIEW + 1, dt=dt, seed=0, stroke_um=stroke_um(bender))


def run_vertex(
    vertex: tuple[float, float, float],
    bender: str = BENDER,
    model_dir: str = MODEL_DIR,
    hysteresis_scale: float = 1.0,
) -> dict[tuple[str, str], tuple[float, ...]]:
    """(row, reference) -> (RMSE, second-half RMSE in % of the full stroke, settling in ms,
    settling against ``mpc-oracle``'s second half in ms) on one vertex of ``bender``'s box
    (hysteresis strength times ``hysteresis_scale``), every controller built from the model in
    ``model_dir`` (``mpc-oracle``, the first row, sets the floor of the last)."""
    import gymnasium as gym
    from threadpoolctl import threadpool_limits

    import controllers as ctl

    dt = sample_time(bender)
    steps = round(EPISODE_S / dt)
    stroke = stroke_um(bender)
    env = vertex_env(vertex, bender, hysteresis_scale)
    nominal = gym.make(
        "piezo_env:PiezoBender-v0", bender=bender, preview=PREVIEW, dt=dt, max_episode_steps=steps
    )
    out = {}
    floors: dict[str, float] = {}  # reference -> mpc-oracle's second-half RMS error (um)
    with threadpool_limits(1):
        for row, (name, options) in ROWS.items():
            model = model_dir
            if row.endswith("-oracle"):
                model = ctl.prediction_model("plant", env)
            controller = ctl.make(name, model, nominal, **options)
            for ref_name in REFERENCES_RUN:
                reference = vertex_reference(ref_name, bender)
                episode = ctl.run_episode(
                    env, controller, seed=0, reference=reference, stroke_um=stroke
                )
                error = episode.deflection_um - episode.reference_um
                half_um = float(np.sqrt(np.mean(error[error.size // 2 :] ** 2)))
                floors.setdefault(ref_name, half_um)
                out[row, ref_name] = (
                    episode.metrics["rmse_percent"],
                    half_um / (2 * stroke) * 100,
                    window_settling_ms(error, dt),
                    window_settling_ms(error, dt, floor=floors[ref_name]),
                )
    return out


def _cell(value: float) -> str:
    return "diverged" if not math.isfinite(value) or value > 100 else f"{value:.3f}"


def main(argv: list[str] | None = None) -> None:
    """Run every row on every vertex and write ``corners[-BENDER].md``."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.studies.corners", description=__doc__
    )
    parser.add_argument("--bender", default=BENDER, help="catalogue name (default: PL140)")
    parser.add_argument(
        "--model",
        default=None,
        help=f"identified model folder (default: {MODEL_DIR}; required for another bender)",
    )
    parser.add_argument(
        "--hysteresis",
        type=float,
        nargs="+",
        default=None,
        metavar="SCALE",
        help="hysteresis strengths (-) to run the vertices at instead of the nominal one, e.g. "
        "0.7 1.3 (the datasheet's +-30 %%); writes corners[-BENDER]-hysteresis.md",
    )
    args = parser.parse_args(argv)
    from piezo_env import get_datasheet

    bender = get_datasheet(args.bender).name.split(".")[0]
    if args.model is None and bender != BENDER:
        parser.error(f"--model is required for {bender}: run `piezo identify --bender {bender}`")
    scales = args.hysteresis or [1.0]
    if not all(0.0 < s < 2.0 for s in scales):
        parser.error(f"--hysteresis takes strengths in (0, 2), got {scales}")
    model_dir = args.model or MODEL_DIR
    title = f"Controllers on the corners of the {bender}'s tolerance box"
    options = "" if bender == BENDER else f"--bender {bender} --model DIR"
    if args.hysteresis:
        title += ", hysteresis strength " + " and ".join(f"x{s:g}" for s in scales)
        options += " --hysteresis " + " ".join(f"{s:g}" for s in scales)
    lines = header(title, __spec__.name, options.strip())
    lines += [__doc__.split("\n\nRun:")[0].split("\n\n", 1)[1], "", model_line(model_dir), ""]
    for scale in scales:
        results = {vertex: run_vertex(vertex, bender, model_dir, scale) for vertex in VERTICES}
        for ref_name in REFERENCES_RUN:
            heading = ref_name if not args.hysteresis else f"{ref_name}, hysteresis x{scale:g}"
            lines += [f"## {heading}", "", _table(results, ref_name), ""]
    name = "corners" if bender == BENDER else f"corners-{bender}"
    write_result(name + ("-hysteresis" if args.hysteresis else ""), lines)


def model_line(model_dir: str) -> str:
    """The identified model these tables ran: its bender and identification seed, and the
    command that identifies it again (the rows move with the model's identification seed, so
    a table names the seed it was made with)."""
    meta = json.loads((Path(model_dir) / "model.json").read_text(encoding="utf-8"))["metadata"]
    bender, seed = str(meta["bender"]).split(".")[0], meta["seed"]
    return (
        f"Model: identified on the {meta['bender']} with identification seed {seed} "
        f"(`piezo identify --bender {bender} --seed {seed}` identifies it again)."
    )


def _table(results: dict[tuple[float, float, float], dict], ref_name: str) -> str:
    """The Markdown table of one reference: a row per vertex, then the worst of each column."""
    head = ["free deflection, resonance, damping", *ROWS]
    rows = []
    for vertex, cells in results.items():
        row = [f"x{vertex[0]:g}, x{vertex[1]:g}, {vertex[2]:g}"]
        for name in ROWS:
            whole, half, settle, settle_oracle = cells[name, ref_name]
            text = _cell(whole)
            if name.startswith("mpc-adaptive"):
                late = settle_oracle > EPISODE_S * 1e3
                against = f"> {EPISODE_S:g} s" if late else f"{settle_oracle:.0f} ms"
                text = f"{text} ({_cell(half)}; {settle:.0f} ms; {against})"
            row.append(text)
        rows.append(row)
    worst = ["worst"]
    for name in ROWS:
        whole = max(cells[name, ref_name][0] for cells in results.values())
        worst.append(f"**{_cell(whole)}**")
    rows.append(worst)
    return markdown_table(head, rows)


if __name__ == "__main__":
    main()
