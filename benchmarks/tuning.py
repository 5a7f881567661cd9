"""Fair tuning: each controller's main knob chosen by one procedure that never sees the test.

A lead in a benchmark table can come from the tuning: a PID tuned to a conservative margin
loses to an MPC whose weights were picked on the very references it is scored on. This module
holds the one procedure every controller family's main knob goes through, and the sweep that
shows its consequence on the benchmark's own references, so a reader sees both.

**The procedure** (:func:`choose`) uses only what a user has before the test:

- the identified model, run as the plant (:class:`ModelPlantEnv`: its nonlinearity and linear
  part in closed loop, with the sensor's uniform noise), as identified and at each vertex of
  the datasheet's tolerance box (:class:`controllers.tolerance_box.ToleranceBox`: static gain
  +-20 %, first resonance +-20 %, its damping 0.01 and 0.04, the further modes moved with it;
  :func:`controllers.tolerance_box.vertex_models`), which a user reads in the datasheet and
  cannot tell from one identification;
- :data:`TUNING_REFERENCES`, another split of frequencies and shapes than the benchmark's
  (:data:`benchmarks.references.REFERENCES`): none of their frequencies or step levels is a
  test reference's.

Its score for a setting is the worst over these nine plants of the geometric mean over the
tuning references of the RMSE (% of the full stroke): the geometric mean weighs a halving at
the noise floor as much as one at a hard reference, and the worst plant asks the setting to
hold on any bender of the datasheet. (The gain's extremes alone are not enough: a controller
that learns the gain, as both MPCs do, meets them at no cost, and the box's resonance and
damping are what a gentler law buys robustness against.) The lowest score wins; a tie
(within 2 %, the single-seed tie of :data:`benchmarks.cells.TIE`) goes to the default, so a
default moves only for a clear gain.

**The knobs** (:data:`KNOBS`): the PID family's sensitivity bound ``ms_max`` (which sets its
proportional, integral and derivative gains through the tuning rule of
:mod:`controllers.pid_tuning`, and with them how hard the feedback works beside ``pid-ff``'s
feedforward), and the input-rate weight ``rate_weight`` of the MPC and of the adaptive MPC,
each tuned on its own (the adaptive MPC learns the resonance, so a gentler law only costs
it). Every default is the procedure's choice but ``pid-notch``'s (the report's tuning
disclosure says why). PPO has none: its policy is trained, not tuned.

``python -m benchmarks.tuning`` writes ``benchmarks/results/tuning.md``: each knob's score on
the tuning references (the procedure's choice marked), and the RMSE each setting gets on the
benchmark's test references on the nominal plant and a tolerance corner, so whether a lead
comes from the tuning can be read off; and :func:`lead`, ``mpc``'s lead over ``pid-ff`` at its
best setting of the sweep, with its interval over noise seeds.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np

from benchmarks.cells import TIE
from benchmarks.references import REFERENCES, fade_in
from piezo_env import signals

__all__ = [
    "KNOBS",
    "TUNING_REFERENCES",
    "Knob",
    "ModelPlantEnv",
    "Tuning",
    "choose",
    "tuning_reference",
]

@dataclass(frozen=True)
class Knob:
    """A controller's main knob: the controller, its option name and the grid swept."""

    controller: str
    option: str
    grid: tuple[float, ...]

    @property
    def default(self) -> float:
        """The shipped default: the controller's settings with its preset and no option."""
        from controllers.registry import resolve_controller

        return getattr(resolve_controller(self.controller, {})[1], self.option)


_MS_MAX_GRID = (1.2, 1.4, 1.6, 1.8, 2.0)
_RATE_WEIGHT_GRID = (1e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0)

KNOBS: dict[str, Knob] = {
    name: Knob(name, option, grid)
    for name, option, grid in (
        ("pid", "ms_max", _MS_MAX_GRID),
        ("pid-notch", "ms_max", _MS_MAX_GRID),
        ("pid-ff", "ms_max", _MS_MAX_GRID),
        ("mpc", "rate_weight", _RATE_WEIGHT_GRID),
        ("mpc-adaptive", "rate_weight", _RATE_WEIGHT_GRID),
    )
}
"""Controller -> its main knob. The ``ms_max`` grid spans Astrom and Murray's usual 1.2-2
(:data:`controllers.settings.MS_MAX`): a sensitivity peak above 2 is outside the robustness
a textbook loop keeps, so the grid's top is a bound, not a guess. The rate weight's grid
steps by about half a decade over three and a half decades, so that its choice lies inside it."""


def _sine(amplitude: float, frequency: float) -> Callable[..., np.ndarray]:
    return lambda n, dt, rng: signals.sine(n, dt=dt, amplitude=amplitude, frequency=frequency)


TUNING_REFERENCES: dict[str, Callable[[int, float, np.random.Generator], np.ndarray]] = {
    "sine-4Hz": _sine(400.0, 4.0),
    "sine-30Hz": _sine(400.0, 30.0),
    "sine-70Hz": _sine(300.0, 70.0),
    "triangle-25Hz": lambda n, dt, rng: signals.triangle(
        n, dt=dt, amplitude=400.0, frequency=25.0
    ),
    "multisine-2-60Hz": lambda n, dt, rng: fade_in(
        signals.multisine(n, dt=dt, amplitude=400.0, f_min=2.0, f_max=60.0, n_tones=6, rng=rng),
        dt,
    ),
    "steps-400um": lambda n, dt, rng: signals.square(n, dt=dt, amplitude=400.0, frequency=3.5),
}
"""The references the procedure tunes on (um at the PL140's 1000 um one-sided stroke; scaled
to another bender's): frequencies 4, 30, 70 Hz, a 25 Hz triangle, a 2-60 Hz multisine of 6
tones (faded in over 50 ms as the test multisine, :func:`benchmarks.references.fade_in`) and
+-400 um steps at 3.5 Hz, none of them a test reference's
(:data:`benchmarks.references.REFERENCES`: 1, 10, 50, 100 Hz sines, a 10 Hz triangle, a 1-40
Hz multisine of 8 tones, a chirp, +-600 um steps at 2.5 Hz and random steps)."""


def _reference_rng(name: str, seed: int) -> np.random.Generator:
    """The generator of the tuning reference ``name`` for ``seed``: seeded by the seed and the
    name, so a name and a seed always give the same array."""
    return np.random.default_rng([seed, len(name), sum(map(ord, name))])


def tuning_reference(
    name: str, n: int, *, dt: float, seed: int, stroke_um: float = 1000.0
) -> np.ndarray:
    """Samples 0 .. n-1 (um) of a tuning reference (ValueError for a test reference's name)."""
    if name not in TUNING_REFERENCES:
        extra = " (a test reference: never tuned on)" if name in REFERENCES else ""
        raise ValueError(
            f"unknown tuning reference {name!r}{extra}; valid: {', '.join(TUNING_REFERENCES)}"
        )
    build = TUNING_REFERENCES[name]
    return np.asarray(build(n, dt, _reference_rng(name, seed)), dtype=float) * (stroke_um / 1000.0)


class ModelPlantEnv(gym.Env):
    """The identified model as the plant, with ``PiezoBender-v0``'s interface.

    The nonlinearity's step and the linear part (``x+ = A x + B z``, ``y = C x``) of a
    :class:`controllers.PredictionModel` in closed loop, read through the task's sensor: uniform
    noise within the task's bound, the same observation layout (measurement, then the reference
    from r_t to r_t+preview), the same drive-range clip and the same ``info`` keys as the env
    (:func:`controllers.run_episode` runs on it unchanged).

    Parameters
    ----------
    model : controllers.PredictionModel
        The plant: the identified model, or one of the tolerance box's vertices of it
        (:func:`vertex_models`).
    like : gymnasium.Env
        A ``PiezoBender-v0`` whose task (drive range, stroke, noise bound, preview, dt) this
        one copies.
    steps : int
        Steps per episode (truncation).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(self, model: Any, like: gym.Env, *, steps: int) -> None:
        base = like.unwrapped
        self.task = base.task
        self.model = model
        self.preview = int(base.preview)
        self.noise_bound = float(base.task.noise_bound)
        self.action_space = like.action_space
        self.observation_space = like.observation_space
        self._u_max = float(like.action_space.high[0])
        self._c = np.asarray(model.c[0], dtype=float)
        self._steps = int(steps)
        self._reference = np.zeros(0)

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        reference = (options or {}).get("reference")
        if reference is None:
            raise ValueError("ModelPlantEnv needs options={'reference': array} (um)")
        self._reference = np.asarray(reference, dtype=float)
        if len(self._reference) < self._steps + self.preview + 1:
            raise ValueError(
                f"the reference has {len(self._reference)} samples; an episode of "
                f"{self._steps} steps with a preview of {self.preview} needs "
                f"{self._steps + self.preview + 1}"
            )
        self._x = np.zeros(self.model.n_states)
        self._state = self.model.nonlinearity.initial_state()
        self._t = 0
        return self._observe(0.0), {"deflection_um": 0.0}

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        command = float(np.asarray(action).reshape(-1)[0])
        voltage = min(max(command, -self._u_max), self._u_max)
        z, self._state = self.model.nonlinearity.step(voltage, self._state)
        self._x = self.model.a @ self._x + self.model.b[:, 0] * z
        self._t += 1
        deflection = float(self._c @ self._x)
        reference = float(self._reference[self._t])
        error = (deflection - reference) / float(self.task.stroke_um)
        info = {
            "deflection_um": deflection,
            "reference_um": reference,
            "voltage_V": voltage,
            "saturated": voltage != command,
        }
        truncated = self._t >= self._steps
        return self._observe(deflection), -(error**2), False, truncated, info

    def _observe(self, deflection_um: float) -> np.ndarray:
        noise = self.np_random.uniform(-self.noise_bound, self.noise_bound)
        window = self._reference[self._t : self._t + self.preview + 1]
        return np.concatenate([[deflection_um + noise], window]).astype(np.float32)


@dataclass(frozen=True)
class Tuning:
    """The procedure's result for one controller's knob.

    Attributes
    ----------
    controller : str
    knob : Knob
    scores : dict
        Setting -> worst over the model and the tolerance box's vertices of the geometric-mean
        RMSE (% of the full stroke)
        on the tuning references.
    chosen : float
        The setting the procedure chose.
    """

    controller: str
    knob: Knob
    scores: dict[float, float]
    chosen: float


def choose(
    controller: str,
    model_dir: str,
    *,
    bender: str = "PL140",
    references: Mapping[str, Callable[..., np.ndarray]] | None = None,
    seed: int = 0,
    steps: int = 1000,
    preview: int = 20,
) -> Tuning:
    """Choose ``controller``'s main knob (:data:`KNOBS`) by the procedure of the module
    docstring, on the identified model in ``model_dir``.

    Parameters
    ----------
    controller : str
        A key of :data:`KNOBS`.
    model_dir : str
        Folder of the identified model (the plant of the procedure, and what the controller
        is built on).
    bender : str
        The bender the model was identified on (its task: drive range, stroke, noise).
    references : mapping, optional
        Name -> ``build(n, dt, rng)`` (um at a 1000 um stroke); default
        :data:`TUNING_REFERENCES`. The test references are never among them.
    seed : int
        Seed of the sensor noise and of the random-phase references.
    steps : int
        Steps per tuning episode (1 s at 1 ms by default).
    preview : int
        Reference samples the controller sees ahead, as in the benchmark.

    Returns
    -------
    Tuning
    """
    import controllers as ctl
    from benchmarks.plants import sample_time, stroke_um
    from controllers.tolerance_box import ToleranceBox, vertex_models

    if controller not in KNOBS:
        raise ValueError(f"no main knob for {controller!r}; tuned here: {', '.join(KNOBS)}")
    knob = KNOBS[controller]
    references = dict(TUNING_REFERENCES if references is None else references)
    dt = sample_time(bender)
    stroke = stroke_um(bender)
    nominal = gym.make("piezo_env:PiezoBender-v0", bender=bender, dt=dt, preview=preview)
    model = ctl.PredictionModel.from_hammerstein(model_dir, float(nominal.action_space.high[0]))
    n = steps + preview + 1
    arrays = {
        name: np.asarray(build(n, dt, _reference_rng(name, seed)), float) * (stroke / 1000.0)
        for name, build in references.items()
    }
    box = vertex_models(model, ToleranceBox(), further_modes=True)
    plants = [ModelPlantEnv(m, nominal, steps=steps) for m in (model, *(m for _, m in box))]
    scores = {}
    for value in knob.grid:
        built = ctl.make(controller, model_dir, nominal, **{knob.option: value})
        worst = 0.0
        for plant in plants:
            logs = [
                math.log(
                    max(
                        ctl.run_episode(
                            plant, built, seed=seed, reference=ref, stroke_um=stroke
                        ).metrics["rmse_percent"],
                        1e-12,
                    )
                )
                for ref in arrays.values()
            ]
            worst = max(worst, math.exp(float(np.mean(logs))))
        scores[value] = worst
    nominal.close()
    best = min(scores, key=scores.__getitem__)
    chosen = knob.default if scores[knob.default] <= (1 + TIE) * scores[best] else best
    return Tuning(controller, knob, scores, chosen)


SWEEP_PLANTS = ("nominal", "stiffness+20%")
"""Plants of the sweep on the test references: the nominal bender and a tolerance plant (what
a knob trades: tracking where the model holds against robustness where it does not)."""

SWEEP_REFERENCES = ("sine-10Hz", "sine-50Hz", "multisine", "steps")
"""Test references of the sweep (:data:`benchmarks.references.REFERENCES`)."""


def sweep(controller: str, model_dir: str, *, bender: str = "PL140", seed: int = 0) -> dict:
    """RMSE (% of the full stroke) of every setting of ``controller``'s knob on the benchmark's
    test references (:data:`SWEEP_REFERENCES`) and plants (:data:`SWEEP_PLANTS`; a row the
    benchmark does not run on a robustness plant, ``pid``, has only the nominal cells):
    ``{setting: {(plant, reference): rmse}}``. What the reader checks the choice against; the
    procedure never reads it."""
    from benchmarks.runner import ROBUSTNESS_CONTROLLERS, BenchmarkConfig, run_benchmark

    knob = KNOBS[controller]
    plants = SWEEP_PLANTS if controller in ROBUSTNESS_CONTROLLERS else ("nominal",)
    out = {}
    for value in knob.grid:
        config = BenchmarkConfig(
            controllers=(controller,),
            references=SWEEP_REFERENCES,
            plants=plants,
            seed=seed,
            bender=bender,
            controller_options={controller: {knob.option: value}},
        )
        result = run_benchmark(config, model_dir)
        out[value] = {(e["plant"], e["reference"]): e["rmse_percent"] for e in result.episodes}
    return out


LEAD_SEEDS = 5
"""Noise seeds of the lead of ``mpc`` over ``pid-ff`` at its best setting (:func:`lead`): with
4 degrees of freedom the 95 % interval of a mean log ratio is 2.8 standard errors wide on
either side, enough to call the leads of a few percent at the noise floor."""


def lead(
    model_dir: str, best: Mapping[str, float], *, bender: str = "PL140", seeds: int = LEAD_SEEDS
) -> dict[str, dict[str, float | str]]:
    """The lead of ``mpc`` (its defaults) over ``pid-ff`` at ``best[reference]``, its
    ``ms_max`` with the lowest RMSE on that reference in the sweep (the setting most generous
    to it), on the nominal plant and the test references of the sweep, over ``seeds`` noise
    seeds run by both (paired).

    Returns, per reference: ``ratio``, the geometric mean over the seeds of pid-ff's RMSE over
    mpc's (above 1: mpc leads), ``low`` and ``high``, its 95 % interval (Student's t on the
    log ratios), ``ms_max`` and ``verdict``: "mpc leads", "pid-ff leads" or "tie" when the
    interval holds 1.
    """
    from benchmarks.cells import ci95_half_width
    from benchmarks.runner import BenchmarkConfig, run_benchmark

    def episodes(controller: str, references: tuple[str, ...], options: dict) -> list[dict]:
        config = BenchmarkConfig(
            controllers=(controller,),
            references=references,
            plants=("nominal",),
            seeds=seeds,
            bender=bender,
            controller_options={controller: options} if options else {},
        )
        return run_benchmark(config, model_dir).episodes

    # mpc at its defaults is one run over every reference (each episode resets the controller,
    # the env from its seed and reads its reference array, seeded by the reference's name: the
    # same numbers as one run per reference); pid-ff has a setting per reference.
    runs = episodes("mpc", SWEEP_REFERENCES, {})
    for reference in SWEEP_REFERENCES:
        runs += episodes("pid-ff", (reference,), {"ms_max": best[reference]})
    rmse: dict[tuple[str, str], dict[int, float]] = {}
    for e in runs:
        cell = rmse.setdefault((e["controller"], e["reference"]), {})
        cell[int(e.get("seed_index", 0))] = e["rmse_percent"]
    out: dict[str, dict[str, float | str]] = {}
    for reference in SWEEP_REFERENCES:
        mpc, pid = rmse[("mpc", reference)], rmse[("pid-ff", reference)]
        d = np.log([pid[k] / mpc[k] for k in sorted(mpc)])
        half = ci95_half_width(d) or 0.0
        low, high = math.exp(d.mean() - half), math.exp(d.mean() + half)
        verdict = "mpc leads" if low > 1.0 else "pid-ff leads" if high < 1.0 else "tie"
        out[reference] = {
            "ratio": math.exp(d.mean()),
            "low": low,
            "high": high,
            "ms_max": best[reference],
            "verdict": verdict,
        }
    return out


def _report(model_dir: str) -> list[str]:
    from benchmarks._common import header, markdown_table

    lines = header("Fair tuning: each main knob by one procedure, and its sweep", __spec__.name)
    lines += [
        "The procedure (`benchmarks/tuning.py`) runs each setting on the identified model "
        f"(`{model_dir}`) as the plant, as identified and at the 8 vertices of the datasheet's "
        "tolerance box (static gain and first resonance +-20 %, damping 0.01 / 0.04), on the "
        f"tuning references ({', '.join(TUNING_REFERENCES)}), and scores it by the worst "
        "plant's geometric-mean RMSE (% of the full stroke); the lowest score wins, a tie "
        "within 2 % going to the default. It never reads the test references. The sweep then "
        "gives each setting's RMSE on the benchmark's test references (nominal plant and "
        "`stiffness+20%`, seed 0, whole 2 s episodes): **bold** = the procedure's choice, "
        "(default) = the shipped default.",
        "",
    ]
    swept_pid_ff: dict = {}
    for controller, knob in KNOBS.items():
        tuning = choose(controller, model_dir)
        swept = sweep(controller, model_dir)
        if controller == "pid-ff":
            swept_pid_ff = swept
        cells = [f"{p} {r}" for p in SWEEP_PLANTS for r in SWEEP_REFERENCES]
        rows = []
        for value in knob.grid:
            label = f"{value:g}" + (" (default)" if value == knob.default else "")
            label = f"**{label}**" if value == tuning.chosen else label
            rows.append(
                [label, f"{tuning.scores[value]:.4f}"]
                + [
                    f"{swept[value][(p, r)]:.4f}" if (p, r) in swept[value] else "-"
                    for p in SWEEP_PLANTS
                    for r in SWEEP_REFERENCES
                ]
            )
        lines += [
            f"## `{controller}`: `{knob.option}`",
            "",
            markdown_table([knob.option, "tuning score", *cells], rows),
            "",
        ]
    best = {
        r: min(swept_pid_ff, key=lambda v: swept_pid_ff[v][("nominal", r)])
        for r in SWEEP_REFERENCES
    }
    leads = lead(model_dir, best)
    lines += [
        "## `mpc` against `pid-ff` at its best setting",
        "",
        f"`pid-ff` at the `ms_max` of the sweep with the lowest RMSE on each reference (the "
        f"setting most generous to it, chosen on the test itself), `mpc` at its defaults; "
        f"nominal plant, noise seeds 0-{LEAD_SEEDS - 1} run by both. The lead is the geometric "
        "mean over the seeds of `pid-ff`'s RMSE over `mpc`'s (above 1: `mpc` better), with its "
        "95 % interval (Student's t on the log ratios); a tie when the interval holds 1.",
        "",
        markdown_table(
            ["reference", "pid-ff ms_max", "lead of mpc", "95 % interval", "verdict"],
            [
                [
                    r,
                    f"{v['ms_max']:g}",
                    f"{v['ratio']:.3f}x",
                    f"{v['low']:.3f}-{v['high']:.3f}x",
                    str(v["verdict"]),
                ]
                for r, v in leads.items()
            ],
        ),
        "",
    ]
    return lines


def main() -> None:
    """Write ``benchmarks/results/tuning.md`` (about two minutes on 2 cores)."""
    import argparse

    from benchmarks._common import write_result

    parser = argparse.ArgumentParser(description=main.__doc__)
    parser.add_argument("--model", default="docs/benchmark/model", help="identified model folder")
    args = parser.parse_args()
    write_result("tuning", _report(args.model))


if __name__ == "__main__":
    main()
