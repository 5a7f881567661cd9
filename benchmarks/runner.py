"""The closed-loop benchmark: every controller on the same env, seeds and references.

:func:`run_benchmark` runs each selected controller on each reference of the nominal bender
(the PL140 by default) and on the robustness plants (the same identified model and settings on
plants it was not identified on), and returns every episode's metrics. Every env steps at the
nominal bender's sample time (:func:`benchmarks.plants.sample_time`, its default dt), and an
episode lasts 2 s whatever that is. ``piezo benchmark`` calls it and writes
the tables and figures (:mod:`benchmarks.report`).

Fairness. Every controller sees the same observation: the measured deflection and a preview
of the reference (``preview`` samples, 20 by default), on the same noise sequence (the same
env seed) and the same reference arrays. A controller name with the suffix ``-oracle`` runs on
the true plant's model (its hysteresis and exact beam, seen through the plant's sensor, and
steering the tip) instead of the identified one: the distance between the two rows is what
identification costs, and behind a sensor what steering the measurement instead of the tip
costs.

Reproducibility. Episodes are grouped by (plant, controller); each group builds its env and its
controller afresh and runs its references in a fixed order, in a worker process (``jobs``).
Nothing depends on which worker runs a group or when, so the tracking results are bitwise the
same for any ``jobs``; only the measured compute times differ from run to run. Every group is
seeded from its own key (the config's seed, the draw and the seed index), so a group rerun
because its worker died (:mod:`piezo_parallel.pool`) or taken from the checkpoint of an
interrupted run (:mod:`benchmarks.checkpoint`) gives the same bits.
"""

from __future__ import annotations

import gc
import json
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.checkpoint import Checkpoint, plain_json
from benchmarks.plants import (
    BOX_CORNERS,
    DEFAULT_BENDER,
    DRAWN_PLANTS,
    EPISODE_S,
    MONTE_CARLO,
    MONTE_CARLO_REFERENCES,
    PLANTS,
    VERTICES,
    sample_time,
    stroke_um,
    vertex_options,
)
from benchmarks.references import REFERENCES, make_reference
from controllers.registry import CONTROLLERS
from piezo_env.checks import require_int, require_number
from piezo_parallel.backends import BACKENDS, DEFAULT_RETRIES, Prerequisite, run_tasks

__all__ = [
    "BOX_CORNERS",
    "DEFAULT_CONTROLLERS",
    "DRAWN_PLANTS",
    "MONTE_CARLO",
    "PLANTS",
    "BenchmarkConfig",
    "BenchmarkResult",
    "model_folders",
    "no_collection",
    "run_benchmark",
]

DEFAULT_CONTROLLERS = (
    "pid",
    "pid-notch",
    "pid-ff",
    "mpc",
    "mpc-adaptive",
    "nmpc",
    "mpc-oracle",
    "nmpc-oracle",
)
"""Controllers of ``piezo benchmark`` (nmpc-ipopt, 20-60 ms per step, is opt-in)."""

ROBUSTNESS_CONTROLLERS = ("pid-notch", "pid-ff", "mpc", "mpc-adaptive", "nmpc", "mpc-oracle")
"""The controllers also run on the robustness plants (when selected)."""

ROBUSTNESS_REFERENCES = ("sine-10Hz", "sine-50Hz", "sine-100Hz", "multisine", "steps")
"""The references run on the robustness plants (when selected)."""

TRACE_REFERENCES = ("sine-50Hz", "multisine", "steps")
"""References whose nominal time series are kept for the tracking figure."""

ADAPTATION_PLANTS = ("stiffness+20%", "drift")
"""Plants whose ``ADAPTATION_REFERENCE`` episode of ``mpc`` and ``mpc-adaptive`` is kept for
the adaptation figure (a tolerance plant and the plant that drifts)."""

ADAPTATION_REFERENCE = "sine-10Hz"

ADAPTATION_ROWS = ("mpc", "mpc-adaptive")


@dataclass(frozen=True)
class BenchmarkConfig:
    """What to run.

    Attributes
    ----------
    controllers : tuple of str
        Registry names (:data:`controllers.CONTROLLERS`), optionally suffixed ``-oracle``, and
        a user's controllers as entry points ``package.module:Factory`` (row named
        ``Factory``) or ``label=package.module:Factory`` (see :mod:`controllers.protocol`);
        they run on the nominal and the robustness plants.
    references : tuple of str
        Names in :data:`benchmarks.references.REFERENCES`.
    plants : tuple of str
        Names in :data:`PLANTS`; ``"nominal"`` runs every reference and controller, the
        others (the robustness plants) those selected by :attr:`every_reference` and
        :attr:`every_controller`.
    seed : int
        Env seed (sensor noise) and seed of the random references.
    steps : int or None
        Steps per episode; None (the default): :data:`benchmarks.plants.EPISODE_S` (2 s) at
        the bender's sample time :attr:`dt` (2000 steps on the PL140, 8000 on the PL127).
        Resolved at construction: :func:`dataclasses.replace` with another bender keeps it.
    preview : int
        Reference samples after r_t in every controller's observation (>= 1: the action a_t
        is scored against r_t+1).
    jobs : int
        Worker processes (1: run in this process).
    backend : str
        Where the workers run (:data:`piezo_parallel.backends.BACKENDS`); results do not depend
        on it.
    controller_options : dict
        Per controller row, options passed to :func:`controllers.make` (a user's factory gets
        them as keywords).
    policies : tuple of str
        Folders of trained policies (:func:`controllers.policy.save_policy`), each run as a
        controller named after its folder (``ppo-seed0`` ...), on every plant.
    draws : int
        Random plants of the Monte Carlo table (``random-plants``), seeds seed .. seed+draws-1.
    seeds : int
        Noise seeds per cell (seed .. seed+seeds-1): the tables give the mean and its 95 %
        interval. The random plants keep one seed per draw (the draws are their spread).
    identification_seeds : int
        Identified models the run is given (``run_benchmark``'s ``model_dir``, one folder per
        identification seed, seed .. seed+identification_seeds-1): every row built on the
        identified model runs on each of them with the same noise seeds, and a cell's mean and
        interval are over identification seeds x noise seeds. The oracles and the policies do
        not use the identified model and run once.
    bender : str
        Catalogue name of the nominal bender (``"PL140"``, ``"PL112"``, ``"PL122"``,
        ``"PL127"``, ``"PL128"``): its references are scaled to its stroke, its robustness
        plants derived from its datasheet, and every env steps at its sample time :attr:`dt`.
        A policy trained at another sample time is refused.
    dt : float or None
        Sample time of every env of the benchmark (s); None (the default): the bender's,
        :func:`benchmarks.plants.sample_time`. Resolved at construction, as ``steps``. The
        model must have been identified at it.
    every_reference : bool
        Whether the robustness plants run every reference of :attr:`references` (True) or
        only those among :data:`ROBUSTNESS_REFERENCES` (among
        :data:`benchmarks.plants.MONTE_CARLO_REFERENCES` on the drawn plants, random-plants
        and box-corners): the default, which keeps the default run's time. ``piezo
        benchmark`` sets it when ``--references`` is given.
    every_controller : bool
        Whether the robustness plants run every row (True) or only the controllers among
        :data:`ROBUSTNESS_CONTROLLERS`, the policies and a user's rows (the default).
        ``piezo benchmark`` sets it when ``--controllers`` is given.
    """

    controllers: tuple[str, ...] = DEFAULT_CONTROLLERS
    references: tuple[str, ...] = tuple(REFERENCES)
    plants: tuple[str, ...] = tuple(PLANTS)
    seed: int = 0
    steps: int | None = None
    preview: int = 20
    jobs: int = 1
    backend: str = "local"
    controller_options: dict[str, dict[str, Any]] = field(default_factory=dict)
    policies: tuple[str, ...] = ()
    draws: int = 10
    bender: str = DEFAULT_BENDER
    seeds: int = 1
    dt: float | None = None
    identification_seeds: int = 1
    every_reference: bool = False
    every_controller: bool = False

    def __post_init__(self) -> None:
        for name in ("controllers", "references", "plants"):
            if not isinstance(getattr(self, name), tuple):
                raise ValueError(f"{name} must be a tuple of names, got {getattr(self, name)!r}")
        if not self.rows:
            raise ValueError("no controller to run: name at least one (or a policy folder)")
        if not self.references or not self.plants:
            raise ValueError("name at least one reference and one plant")
        self._check_controllers()
        for kind, names in (("references", self.references), ("plants", self.plants)):
            twice = sorted({name for name in names if names.count(name) > 1})
            if twice:
                raise ValueError(
                    f"{kind} must be distinct, got {', '.join(twice)} more than once (a repeat "
                    "would be averaged as if it were another seed)"
                )
        for name in self.references:
            if name not in REFERENCES:
                raise ValueError(f"unknown reference {name!r}; valid: {', '.join(REFERENCES)}")
        for name in self.plants:
            if name not in PLANTS:
                raise ValueError(f"unknown plant {name!r}; valid: {', '.join(PLANTS)}")
        from piezo_env import get_datasheet

        get_datasheet(self.bender)  # an unknown bender is refused with the catalogue's names
        if self.dt is None:
            object.__setattr__(self, "dt", sample_time(self.bender))
        object.__setattr__(self, "dt", require_number("dt", self.dt, low=0.0, low_open=True))
        if self.steps is None:
            object.__setattr__(self, "steps", max(1, round(EPISODE_S / self.dt)))
        for name in ("steps", "jobs", "draws", "preview", "seeds", "identification_seeds"):
            require_int(name, getattr(self, name))  # preview >= 1: a_t is scored against r_t+1
        if self.backend not in BACKENDS:
            raise ValueError(f"unknown backend {self.backend!r}; valid: {', '.join(BACKENDS)}")
        self._check_policies()
        self._check_options()
        for name in ("every_reference", "every_controller"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name} must be True or False, got {getattr(self, name)!r}")
            # Canonical: a switch that changes no group is off, so that two configurations
            # that run the same episodes are equal (a checkpoint of one resumes the other).
            if getattr(self, name):
                on = self.groups()
                object.__setattr__(self, name, False)
                if self.groups() != on:
                    object.__setattr__(self, name, True)
        self._check_plants_run()

    def _check_plants_run(self) -> None:
        """Refuse a selected plant on which none of the selected rows and references runs
        (a robustness plant runs a subset of them unless every_reference or every_controller
        says otherwise): it would leave its section of the report empty without a word."""
        ran = {plant for plant, _, _ in self.groups()}
        for plant in (p for p in self.plants if p not in ran):
            subset = _plant_references(plant)
            raise ValueError(
                f"the {plant} plant would run nothing: it runs the references "
                f"{', '.join(subset)} with the controllers {', '.join(ROBUSTNESS_CONTROLLERS)}, "
                "the policies and your own rows unless every_reference / every_controller "
                "(piezo benchmark: --references / --controllers given) ask for all of those "
                "selected"
            )

    def _check_controllers(self) -> None:
        """Built-in names (also as NAME-oracle) and entry points that import; unique rows."""
        from controllers.protocol import is_entry_point, load_entry_point

        for entry in self.controllers:
            if is_entry_point(entry.rpartition("=")[2]):
                continue
            if "=" in entry:
                raise ValueError(
                    f"{entry!r}: label=... names a row of your own controller, as "
                    "label=package.module:Factory"
                )
            if entry.removesuffix("-oracle") == "policy":
                raise ValueError(
                    f"{entry!r} is not a row of its own: a policy row is a trained policy's "
                    "folder (piezo train-rl), given in policies (--policies DIR), one row per "
                    "folder (on the command line the committed ones are also --controllers "
                    "ppo,ppo-dr)"
                )
            if entry.removesuffix("-oracle") not in CONTROLLERS:
                raise ValueError(
                    f"unknown controller {entry!r}; valid: {', '.join(CONTROLLERS)} (each also "
                    "as NAME-oracle), or your own as package.module:Factory (or "
                    "label=package.module:Factory)"
                )
        for label, spec in self.entry_points.items():
            load_entry_point(spec)  # a module that does not import is refused here
            if label in CONTROLLERS or label.endswith("-oracle"):
                raise ValueError(f"controller row name {label!r} is taken; name it label=...")
        labels = [*self.controller_rows, *self.policy_folders]
        if len(set(labels)) != len(labels):
            raise ValueError(f"controller rows must have distinct names, got {labels}")

    @property
    def entry_points(self) -> dict[str, str]:
        """Row name -> entry point of the user's controllers (``label=module:attr`` names a row;
        by default the row is named after the attribute)."""
        from controllers.protocol import is_entry_point

        return {
            _row_name(entry): entry.rpartition("=")[2]
            for entry in self.controllers
            if is_entry_point(entry.rpartition("=")[2])
        }

    @property
    def controller_rows(self) -> tuple[str, ...]:
        """The named controllers' rows: built-in names, and entry points by their row name."""
        return tuple(_row_name(entry) for entry in self.controllers)

    def _check_options(self) -> None:
        """Every controller option is a valid setting of that controller: a built-in's
        ``Settings`` field with a valid value, or a keyword a user's factory takes (its values
        the factory checks when it is built, before any episode: :func:`run_benchmark`)."""
        from controllers.protocol import check_factory_options
        from controllers.registry import resolve_controller

        for controller, options in self.controller_options.items():
            if controller not in self.rows:
                raise ValueError(
                    f"options given for {controller!r}, which is not benchmarked (rows: "
                    f"{', '.join(self.rows)})"
                )
            if controller in self.entry_points:
                check_factory_options(self.entry_points[controller], options)
            elif controller in self.policy_folders:
                resolve_controller("policy", options)
            else:
                resolve_controller(controller.removesuffix("-oracle"), options)

    def _check_policies(self) -> None:
        from controllers.policy import load_policy

        labels = [Path(folder).name for folder in self.policies]
        if len(set(labels)) != len(labels):
            raise ValueError(f"policy folders must have distinct names, got {labels}")
        clash = set(labels) & set(CONTROLLERS)
        if clash:
            raise ValueError(f"policy folder names {sorted(clash)} clash with controller names")
        for folder in self.policies:
            policy = load_policy(folder)  # a folder that does not load fails here, before work
            trained_dt = policy.metadata.get("task", {}).get("dt_s")
            if trained_dt is not None and abs(float(trained_dt) - self.dt) > 1e-9 * self.dt:
                raise ValueError(
                    f"policy {folder} was trained at dt = {float(trained_dt):g} s but the "
                    f"{self.bender} benchmark steps at dt = {self.dt:g} s (its default sample "
                    "time, piezo_env.default_dt); leave the policy out or train one at that dt"
                )
            if policy.observation.preview > self.preview:
                raise ValueError(
                    f"policy {folder} was trained with a preview of {policy.observation.preview} "
                    f"samples but the benchmark shows {self.preview}; raise --preview to at "
                    f"least {policy.observation.preview} or leave the policy out"
                )

    @property
    def stroke_um(self) -> float:
        """One-sided stroke of the nominal bender (um): the percentages' scale."""
        return stroke_um(self.bender)

    @property
    def policy_folders(self) -> dict[str, str]:
        """Policy label -> folder."""
        return {Path(folder).name: str(folder) for folder in self.policies}

    @property
    def rows(self) -> tuple[str, ...]:
        """Every controller row: the named controllers, then the policies."""
        return (*self.controller_rows, *self.policy_folders)

    def identified(self, controller: str) -> bool:
        """Whether the row ``controller`` is built on the identified model (so runs once per
        identification seed): every row but the oracles and the policies."""
        return not controller.endswith("-oracle") and controller not in self.policy_folders

    def runs(self) -> list[tuple[str, str, tuple[str, ...], int]]:
        """(plant, controller, references, model index) of every run of a group: a row built
        on the identified model once per identification seed, any other row once."""
        return [
            (plant, controller, refs, k)
            for plant, controller, refs in self.groups()
            for k in range(self.identification_seeds if self.identified(controller) else 1)
        ]

    def run_key(self, plant: str, controller: str, k: int) -> tuple[Any, ...]:
        """The checkpoint's name of a run: (plant, controller), and the model index when the
        run has several identification seeds."""
        return (plant, controller) if self.identification_seeds == 1 else (plant, controller, k)

    def episodes_of(self, plant: str, references: tuple[str, ...]) -> int:
        """Episodes of one run of a group on ``plant`` over ``references``: one per reference
        and noise seed, or per reference and draw (vertex) on a distribution of plants."""
        if plant == MONTE_CARLO:
            return len(references) * self.draws
        if plant == BOX_CORNERS:
            return len(references) * len(VERTICES)
        return len(references) * self.seeds

    def groups(self) -> list[tuple[str, str, tuple[str, ...]]]:
        """(plant, controller, references) of every group, in report order."""
        out = []
        for plant in self.plants:
            every = plant == "nominal"
            chosen = _plant_references(plant)
            refs = tuple(r for r in self.references if every or self.every_reference or r in chosen)
            robust = (*ROBUSTNESS_CONTROLLERS, *self.policy_folders, *self.entry_points)
            for controller in self.rows:
                # On a distribution of plants an oracle runs each draw's own model.
                if refs and (every or self.every_controller or controller in robust):
                    out.append((plant, controller, refs))
        return out


def _plant_references(plant: str) -> tuple[str, ...]:
    """The references a robustness plant runs unless every_reference asks for all."""
    return MONTE_CARLO_REFERENCES if plant in DRAWN_PLANTS else ROBUSTNESS_REFERENCES


def _row_name(entry: str) -> str:
    """``label=module:attr`` -> label; ``module:attr`` -> attr; a built-in name as it is."""
    from controllers.protocol import entry_point_label, is_entry_point

    label, _, spec = entry.rpartition("=")
    if label:
        return label
    return entry_point_label(spec) if is_entry_point(spec) else spec


@dataclass
class BenchmarkResult:
    """Every episode's metrics, the controllers' descriptions, traces and run facts."""

    config: BenchmarkConfig
    episodes: list[dict[str, Any]]
    controllers: dict[str, dict[str, Any]]
    traces: dict[str, dict[str, dict[str, list[float]]]]
    timing: dict[str, float]


def _make_env(config: BenchmarkConfig, plant: str, **extra: Any) -> Any:
    import gymnasium as gym

    return gym.make(
        "piezo_env:PiezoBender-v0",
        preview=config.preview,
        max_episode_steps=config.steps,
        **{**PLANTS[plant](config.bender), "dt": config.dt, **extra},
    )


def _build(controller: str, model_dir: str, plant_env: Any, config: BenchmarkConfig) -> Any:
    """The controller as the nominal task defines it; an oracle predicts with the plant's model.

    Built against the nominal env, so a controller never learns a robustness plant's sensor
    noise or stroke: the same settings everywhere, only the oracle's model is the plant's own.
    The one exception is a datasheet value of the bench: a plant driven through a
    current-limited amplifier gives the controllers its slew limit (the nominal env with the
    same amplifier), as a control engineer would read it off the amplifier's datasheet.
    """
    import controllers as ctl

    name = controller.removesuffix("-oracle")
    amplifier = plant_env.unwrapped.config.amplifier
    nominal = _make_env(config, "nominal", **({"amplifier": amplifier} if amplifier else {}))
    if controller in config.entry_points:
        name, model = config.entry_points[controller], model_dir
    elif controller in config.policy_folders:
        name, model = "policy", config.policy_folders[controller]
    elif controller.endswith("-oracle"):
        model = ctl.prediction_model("plant", plant_env)  # the plant and its sensor
    else:
        model = model_dir
    built = ctl.make(name, model, nominal, **config.controller_options.get(controller, {}))
    nominal.close()
    return built


def _run_group(
    plant: str,
    controller: str,
    references: dict[str, np.ndarray],
    model_dir: str,
    config: BenchmarkConfig,
    model_index: int = 0,
) -> tuple[list[dict[str, Any]], dict[str, Any], dict[str, dict[str, list[float]]]]:
    """Run one controller on one plant over its references (in a worker process), on the
    identified model ``model_dir`` of identification seed ``config.seed + model_index``.

    The loop does what a real-time Python loop does: one BLAS thread, a warm-up before the
    timed episodes (a first call may load generated code or fill caches), and no garbage
    collection inside them (:func:`no_collection`: collected after set-up, re-enabled after
    the group).
    """
    from threadpoolctl import threadpool_limits

    import controllers as ctl

    env = _make_env(config, plant)
    episodes, traces = [], {}
    draws: Any = [None]
    envs = {None: env}
    if plant == MONTE_CARLO:
        draws = range(config.draws)
        envs = dict.fromkeys(draws, env)  # the env draws its plant at each reset
    elif plant == BOX_CORNERS:
        draws = range(len(VERTICES))
        envs = {
            d: _make_env(config, plant, **vertex_options(config.bender, VERTICES[d])) for d in draws
        }
    with threadpool_limits(1), _user_faults(controller, plant, config):
        built = _build(controller, model_dir, env, config)
        _warm_up(env, built, next(iter(references.values())), config.seed)
        oracles = {}
        if plant in DRAWN_PLANTS and controller.endswith("-oracle"):
            # The oracle of a distribution of plants is each draw's own: built on the plant
            # the env draws from the episode's seed (a reset with that seed draws it again).
            for draw in draws:
                envs[draw].reset(seed=config.seed + draw)
                oracles[draw] = _build(controller, model_dir, envs[draw], config)
        with no_collection():
            seeds = [0] if plant in DRAWN_PLANTS else range(config.seeds)
            for ref_name, reference in references.items():
                for draw in draws:
                    for seed_index in seeds:
                        episode = ctl.run_episode(
                            envs[draw],
                            oracles.get(draw, built),
                            seed=config.seed + (draw or 0) + seed_index,
                            reference=reference,
                            stroke_um=config.stroke_um,
                            describe=False,  # described once, after the group
                        )
                        record = {"plant": plant, "controller": controller, "reference": ref_name}
                        if draw is not None:
                            record["draw"] = draw
                        if config.seeds > 1:
                            record["seed_index"] = seed_index
                        if config.identification_seeds > 1 and config.identified(controller):
                            record["identification_seed"] = config.seed + model_index
                        episodes.append({**record, **episode.metrics})
                        if seed_index == 0:
                            traced = episode  # the figures draw the first seed
                            if (
                                plant in ADAPTATION_PLANTS
                                and ref_name == ADAPTATION_REFERENCE
                                and controller in ADAPTATION_ROWS
                            ):
                                traces[f"adaptation:{plant}"] = _adaptation_trace(episode, built)
                if plant == "nominal" and ref_name in TRACE_REFERENCES:
                    traces[ref_name] = {
                        "deflection_um": traced.deflection_um.tolist(),
                        "reference_um": traced.reference_um.tolist(),
                        "voltage_V": traced.voltage_V.tolist(),
                    }

    for each in {id(e): e for e in envs.values()}.values():
        each.close()
    return episodes, built.describe() if hasattr(built, "describe") else {}, traces


def _adaptation_trace(episode: Any, controller: Any) -> dict[str, Any]:
    """Tracking error (um) of an episode, the step at which the data invalidated the model at
    the noise bound (None: not, or no gain learned) and, for an adaptive controller, the model
    in use at each review ((step, DC gain, first resonance) and the offline values)."""
    out: dict[str, Any] = {
        "error_um": (episode.deflection_um - episode.reference_um).tolist(),
        "invalidated_step": episode.metrics.get("set_invalidated_step"),
    }
    trace = getattr(getattr(controller, "stats", None), "trace", None)
    if trace is not None:
        described = controller.describe()["adaptation"]
        out["models"] = [list(row) for row in trace]
        out["offline"] = [described["offline_dc_gain"], described["offline_resonance_hz"]]
    return out


class RowFailed(ValueError):
    """A user's controller raised while its row ran: one line naming the row, the plant and
    the error (the other rows' finished groups stay in the checkpoint)."""


@contextmanager
def _user_faults(controller: str, plant: str, config: BenchmarkConfig) -> Iterator[None]:
    """Turn an exception of a user's row (an entry point) into :class:`RowFailed`; the
    package's own rows raise as they are, their traceback being the report of a bug."""
    if controller not in config.entry_points:
        yield
        return
    try:
        yield
    except Exception as error:
        raise RowFailed(
            f"the row {controller!r} failed on the {plant} plant: {type(error).__name__}: "
            f"{error}"
        ) from error


def _warm_up(env: Any, controller: Any, reference: np.ndarray, seed: int, steps: int = 25) -> None:
    """A few untimed steps; the episodes then reset the env and the controller."""
    obs, _ = env.reset(seed=seed, options={"reference": reference})
    controller.reset(obs)
    for _ in range(steps):
        obs, _, terminated, truncated, _ = env.step(controller.act(obs))
        if terminated or truncated:
            break


_base_frozen = False


@contextmanager
def no_collection() -> Iterator[None]:
    """Collect what set-up left, and keep the collector off inside.

    The first use in a process also freezes everything then alive: imported modules and torch,
    which live as long as the process and which a full collection would otherwise walk again
    before every group (``benchmarks/results/design_measurements.md``). Later uses collect
    only what was made since. The first group's own objects are frozen with them: they are
    freed by reference counting when the group ends, and any reference cycle among them
    stays until the process ends (a bounded amount, once per process)."""
    global _base_frozen
    gc.collect()
    if not _base_frozen:
        gc.freeze()
        _base_frozen = True
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def model_folders(config: BenchmarkConfig, model_dir: Any) -> dict[str, tuple[str, ...]]:
    """The identified models' folders of each plant that has its own, one per identification
    seed: ``{plant: folders}``. ``model_dir`` is one folder, a sequence of them (one per
    identification seed), or a mapping from plant to either; a plain folder or sequence is
    every plant's, and a plant without its own model runs the mapping's first (ValueError if a
    later plant of the mapping is not run or a number of folders is not
    ``config.identification_seeds``)."""
    if isinstance(model_dir, Mapping):
        given = dict(model_dir)
    else:
        given = {config.plants[0]: model_dir}
    out = {}
    for i, (plant, folders) in enumerate(given.items()):
        if i and plant not in config.plants:
            raise ValueError(
                f"a model was given for the plant {plant!r}, which is not run (plants: "
                f"{', '.join(config.plants)})"
            )
        folders = (
            (str(folders),) if isinstance(folders, (str, Path)) else tuple(map(str, folders))
        )
        if len(folders) != config.identification_seeds:
            raise ValueError(
                f"the run has identification_seeds = {config.identification_seeds} but "
                f"{len(folders)} model folder(s) were given for the {plant} plant; pass one "
                "folder per identification seed"
            )
        out[plant] = folders
    return out


def run_benchmark(
    config: BenchmarkConfig,
    model_dir: str | Path | Sequence[str | Path] | Mapping[str, Any],
    *,
    progress: Callable[[int, int, str], None] | None = None,
    checkpoint: Checkpoint | None = None,
    retries: int = DEFAULT_RETRIES,
    identification: Prerequisite | None = None,
) -> BenchmarkResult:
    """Run the benchmark on the identified model(s) saved in ``model_dir``.

    Parameters
    ----------
    config : BenchmarkConfig
    model_dir : str, pathlib.Path, sequence of them, or mapping
        Folder of a saved :class:`identification.HammersteinModel` (workers load it), or one
        folder per identification seed (``config.identification_seeds`` of them, in seed
        order); or a mapping from plant to either, for plants that have their own model (a
        model identified on that plant, as on a user's bench: ``piezo benchmark
        --identify-on``), the others running the first plant's (:func:`model_folders`). The
        figures, the traces and the controllers' descriptions come from each plant's first.
    progress : callable, optional
        ``progress(done, total, label)`` after each run of a group (runs taken from
        ``checkpoint`` count as done from the start).
    checkpoint : benchmarks.checkpoint.Checkpoint, optional
        Runs it holds are taken from it, not run; each run that finishes is appended to it at
        once, so an interruption loses only the runs still going. The result is bitwise the
        same with or without it, resumed or not.
    retries : int
        Reruns of a group whose worker process died, each on a new worker (see
        :func:`piezo_parallel.backends.run_tasks`).
    identification : piezo_parallel.Prerequisite, optional
        What writes the models into ``model_dir`` (``piezo benchmark`` identifying them): the
        runs built on the identified model wait for it, and the others (the oracles and the
        policies) run beside it on the pool's other workers, so that the identification's
        time overlaps theirs. Its ``then`` returns the checkpoint to keep the runs in, opened
        once the models exist (or None); the runs finished before are appended to it then,
        and ``progress`` starts then. Give no ``checkpoint`` with it.

    Returns
    -------
    BenchmarkResult
        Episodes ordered by plant, controller, model and reference, whatever ``jobs`` is. Its
        ``timing["episodes_s"]`` is this call's wall time: with ``identification``, the
        identification it ran beside included.

    Notes
    -----
    With ``jobs > 1`` the groups run in spawned worker processes (no forked BLAS or torch
    thread state), so a script calling this must do so under ``if __name__ == "__main__":``.
    See :mod:`piezo_parallel.backends`.
    """
    if identification is not None and checkpoint is not None:
        raise ValueError(
            "a run that identifies its models opens its checkpoint once they exist: pass it "
            "as the identification's then, not as checkpoint"
        )
    models = model_folders(config, model_dir)
    default = next(iter(models.values()))
    runs = config.runs()
    keys = [config.run_key(p, c, k) for p, c, _, k in runs]
    start = time.perf_counter()
    # Built here, not in the workers, so references registered in this process run anywhere.
    arrays = {
        name: make_reference(
            name,
            config.steps + config.preview + 1,
            dt=config.dt,
            seed=config.seed,
            stroke_um=config.stroke_um,
        )
        for name in config.references
    }

    def check_entry_points() -> None:  # built once here: a broken one stops before its episodes
        for label in config.entry_points:
            nominal = _make_env(config, "nominal")
            with _user_faults(label, "nominal", config):
                built = _build(label, default[0], nominal, config)
            nominal.close()
            if hasattr(built, "describe"):  # what the checkpoint and benchmark.json will hold
                try:
                    json.dumps(built.describe(), default=plain_json)
                except (TypeError, ValueError) as error:
                    raise ValueError(
                        f"{label}: describe() cannot be written as JSON: {error}"
                    ) from None

    finished = checkpoint.finished if checkpoint is not None else {}
    outputs = [finished.get(key) for key in keys]
    # Largest groups first (by episodes), so that the pool's last tasks are short and its
    # workers end together (the longest-processing-time-first rule); the results do not
    # depend on the order.
    todo = sorted(
        (i for i, key in enumerate(keys) if key not in finished),
        key=lambda i: -config.episodes_of(runs[i][0], runs[i][2]),
    )
    waiting: list[tuple[int, Any]] = []  # finished before the checkpoint was opened
    shown: list[tuple[int, int, str]] = []  # progress held while the models are identified
    opened = identification is None

    def keep(j: int, output: Any) -> None:
        i = todo[j]
        if not opened:
            outputs[i] = output
            waiting.append((i, output))
        else:
            outputs[i] = output if checkpoint is None else checkpoint.append(keys[i], output)

    def show(done: int, total: int, label: str) -> None:
        skipped = len(runs) - len(todo)
        if not opened:
            shown[:] = [(done, total, label)]
            return
        progress(skipped + done, skipped + total, label)  # type: ignore[misc]

    def identified(result: Any) -> None:
        nonlocal checkpoint, opened
        assert identification is not None
        checkpoint = identification.then(result)
        check_entry_points()
        opened = True
        for i, output in waiting:
            outputs[i] = output if checkpoint is None else checkpoint.append(keys[i], output)
        if shown and progress:
            show(*shown[-1])

    def label(i: int) -> str:
        plant, controller, _, k = runs[i]
        model = f" (identification seed {config.seed + k})" if len(default) > 1 else ""
        return f"{controller} on {plant}{model}"

    if identification is None:
        check_entry_points()
    run_tasks(
        _run_group,
        [
            (p, c, {r: arrays[r] for r in refs}, models.get(p, default)[k], config, k)
            for p, c, refs, k in (runs[i] for i in todo)
        ],
        jobs=config.jobs,
        backend=config.backend,
        labels=[label(i) for i in todo],
        progress=show if progress else None,
        on_result=keep,
        retries=retries,
        prerequisite=None
        if identification is None
        else replace(identification, then=identified),
        waits=[config.identified(runs[i][1]) for i in todo],
    )
    episodes, described, traces = [], {}, {}
    for (plant, controller, _, k), (eps, description, trace) in zip(runs, outputs, strict=True):
        episodes.extend(eps)
        if k:
            continue  # the figures and the descriptions are the first model's
        if plant == "nominal" or controller not in described:
            described[controller] = description
        for ref, data in trace.items():
            traces.setdefault(ref, {})[controller] = data
    timing = {"episodes_s": round(time.perf_counter() - start, 1)}
    return BenchmarkResult(config, episodes, described, traces, timing)
