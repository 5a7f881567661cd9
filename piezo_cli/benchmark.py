"""``piezo benchmark``: the command line of :mod:`benchmarks.runner` (MPC against PID)."""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import time
from pathlib import Path

from piezo_cli.arguments import (
    bender_name,
    non_negative_int,
    positive_float,
    positive_int,
    seed,
)
from piezo_cli.command import CommandLineError, Subcommand
from piezo_cli.output import clear_incomplete, mark_incomplete, prepare_output_dir

__all__ = ["BENCHMARK", "COMMITTED_POLICIES", "policies_line"]

COMMITTED_POLICIES = ("ppo", "ppo-dr")
"""Names in ``--controllers`` that select the project's committed policies by recipe
(``ppo`` -> ``docs/policies/ppo-seed0..2``), found in the project folder from anywhere."""


def committed_policy_folder() -> Path:
    """The folder of the committed policies: ``docs/policies`` of the project (present in a
    clone or an editable install, absent from an installed wheel)."""
    return Path(__file__).resolve().parents[1] / "docs" / "policies"


def _names(text: str) -> tuple[str, ...]:
    return tuple(part.strip() for part in text.split(",") if part.strip())


def _option(text: str) -> tuple[str, str, object]:
    """``ROW.KEY=VALUE`` as (row, key, value) (argparse type)."""
    target, sep, raw = text.partition("=")
    row, dot, key = target.rpartition(".")
    if not sep or not dot or not row or not key.isidentifier():
        raise argparse.ArgumentTypeError(
            f"expected ROW.KEY=VALUE such as mpc.horizon=10, got {text!r}"
        )
    words = {"true": True, "false": False, "none": None}
    if raw.strip().lower() in words:
        return row, key, words[raw.strip().lower()]
    number = _number(raw)
    if number is not None:
        return row, key, number
    if "," in raw:  # a pair or list of numbers, such as damping_range=0.01,0.04
        numbers = [_number(part) for part in raw.split(",")]
        if all(n is not None for n in numbers):
            return row, key, tuple(numbers)
    return row, key, raw


def _number(text: str) -> int | float | None:
    """``text`` as an int, else as a float; None if it is neither. A non-finite number is
    refused: the run's JSON, which records the options, has no NaN or infinity."""
    for kind in (int, float):
        try:
            value = kind(text)
        except ValueError:
            continue
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(
                f"{text.strip()!r} is not a finite number; an option's value is a finite "
                "number, true/false, none or text"
            )
        return value
    return None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``piezo benchmark``."""
    from benchmarks.plants import MONTE_CARLO_REFERENCES
    from benchmarks.runner import (
        DEFAULT_CONTROLLERS,
        PLANTS,
        ROBUSTNESS_CONTROLLERS,
        ROBUSTNESS_REFERENCES,
    )
    from piezo_parallel.backends import DEFAULT_RETRIES, default_jobs

    parser.add_argument("--out", default="out/benchmark", metavar="DIR", help="output folder")
    parser.add_argument(
        "--bender",
        type=bender_name,
        default="PL140",
        help="the PICMA bender: PL112, PL122, PL127, PL128 or PL140 (references scale with its "
        "stroke, robustness plants come from its datasheet)",
    )
    parser.add_argument(
        "--model",
        default=None,
        metavar="DIR",
        help="folder of an identified model (model.json + weights.npz); default: identify the "
        "default PL140 first (its duration is in the report's time line; 10-20 s on 2 cores) "
        "and save it in OUT/model",
    )
    parser.add_argument(
        "--controllers",
        type=_names,
        default=None,  # run(): the default controllers and the committed policies
        metavar="A,B",
        help="comma-separated controllers (NAME-oracle runs NAME on the true plant's model; "
        "also available: nmpc-ipopt, 20-60 ms per step); ppo and ppo-dr: the committed PPO "
        "policies (three seeds each, docs/policies; left out, with the reason, on a task they "
        "were not trained for); your own as package.module:Factory or "
        "label=package.module:Factory (see examples/feedforward_pi.py). Default: "
        + ", ".join((*DEFAULT_CONTROLLERS, *COMMITTED_POLICIES))
        + "; the robustness plants run "
        + ", ".join(ROBUSTNESS_CONTROLLERS)
        + ", the policies and your rows of them, unless this option names the rows: then "
        "every plant runs them all",
    )
    parser.add_argument(
        "--references",
        type=_names,
        default=None,  # run(): every reference
        metavar="A,B",
        help="comma-separated references. Default: every one; the robustness plants run "
        + ", ".join(ROBUSTNESS_REFERENCES)
        + " of them (random-plants and box-corners: "
        + ", ".join(MONTE_CARLO_REFERENCES)
        + "), unless this option names the references: then every plant runs them all",
    )
    parser.add_argument(
        "--plants", type=_names, default=tuple(PLANTS), metavar="A,B", help="comma-separated plants"
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of the noise and references")
    parser.add_argument(
        "--seeds",
        type=positive_int,
        default=1,
        help="noise seeds per cell (from --seed on): the tables give means with 95 %% intervals "
        "and call differences within them ties",
    )
    parser.add_argument(
        "--identification-seeds",
        type=positive_int,
        default=1,
        metavar="K",
        help="identify the model K times (seeds --seed .. --seed+K-1, each on its own data) and "
        "run every row built on it on each: the tables' means and 95 %% intervals are then "
        "over identification seeds x noise seeds (not with --model)",
    )
    parser.add_argument(
        "--identify-on",
        type=_names,
        default=("nominal",),
        metavar="P,Q",
        help="the plant(s) the model is identified on, as a user can only identify on their "
        "own bench: the first's model runs on every plant, and each later one (which must be "
        "run) gets its own, e.g. nominal,bench runs the bench on a model identified on the "
        "bench; plants of the bender itself only (default nominal; not with --model)",
    )
    parser.add_argument(
        "--draws",
        type=positive_int,
        default=None,
        help="plants drawn from the datasheet tolerances for the random-plants table "
        "(default: BenchmarkConfig's)",
    )
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="steps per episode (default: 2 s at the bender's sample time, piezo_env.default_dt:"
        " 2000 on the PL140, 8000 on the PL127)",
    )
    parser.add_argument(
        "--dt",
        type=positive_float,
        default=None,
        metavar="S",
        help="sample time of every env (s); default: the --model's, else the bender's "
        "(piezo_env.default_dt); without --model the default model is identified at it "
        "(--dt 1e-4: the PL140 at 10 kHz)",
    )
    parser.add_argument(
        "--preview", type=int, default=20, help="reference samples every controller sees ahead"
    )
    parser.add_argument(
        "--jobs", type=positive_int, default=default_jobs(), help="worker processes"
    )
    parser.add_argument(
        "--backend",
        default="local",
        metavar="NAME",
        help="where the episodes run: local (a process pool of --jobs workers) or ray (Ray "
        'tasks; needs pip install "piezo-testbed[ray]"); results are the same on both',
    )
    parser.add_argument(
        "--address",
        default=None,
        metavar="ADDR",
        help="with --backend ray: an existing Ray cluster (auto, HOST:PORT or ray://HOST:PORT; "
        "every node needs this project and the --model folder); default: a local Ray instance "
        "of --jobs CPUs started for the run",
    )
    parser.add_argument(
        "--policies",
        default="none",
        metavar="GLOB",
        help="folders of your trained policies (piezo train-rl) to run as controllers, a glob "
        "or comma-separated folders (the committed ones are ppo and ppo-dr in --controllers)",
    )
    parser.add_argument(
        "--option",
        action="append",
        default=[],
        type=_option,
        metavar="ROW.KEY=VALUE",
        help="an option of one controller row, e.g. mpc.horizon=10 or MyController.gain=2 "
        "(repeatable; numbers, true/false and none are read as such, numbers separated by "
        "commas as a tuple, e.g. mpc-adaptive.damping_range=0.01,0.04, anything else as text)",
    )
    parser.add_argument(
        "--retries",
        type=non_negative_int,
        default=DEFAULT_RETRIES,
        help="reruns of a group whose worker process died (killed by the out-of-memory killer, "
        "a crash), each on a new worker; the results are the same",
    )
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue the run interrupted in --out: run only the groups its checkpoint "
        "(OUT/checkpoint.jsonl) lacks, with the model it identified; refused if anything that "
        "decides the results changed (configuration, model, code, libraries, native code). "
        "Without it a run starts afresh",
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument(
        "--strict",
        action="store_true",
        help="exit with status 1 when a reference check of the report is missed (the "
        "project's own expectations of the default run; for CI)",
    )


def _config(args: argparse.Namespace, policies: tuple[str, ...]):
    from benchmarks.runner import BenchmarkConfig

    if args.draws is not None and "random-plants" not in args.plants:
        raise CommandLineError(
            "--draws sets the random-plants table's plants; add random-plants to --plants, or "
            "leave --draws out"
        )
    try:
        return BenchmarkConfig(
            controllers=tuple(c for c in args.controllers if c not in COMMITTED_POLICIES),
            references=args.references,
            plants=args.plants,
            seed=args.seed,
            steps=args.steps,
            preview=args.preview,
            jobs=args.jobs,
            backend=args.backend,
            policies=policies,
            controller_options=_options(args.option),
            bender=args.bender,
            seeds=args.seeds,
            dt=args.dt,
            identification_seeds=args.identification_seeds,
            every_reference=args.every_reference,
            every_controller=args.every_controller,
            **({} if args.draws is None else {"draws": args.draws}),
        )
    except ValueError as error:
        raise CommandLineError(str(error)) from None


def _options(options: list[tuple[str, str, object]]) -> dict[str, dict[str, object]]:
    """``--option`` values grouped by row."""
    grouped: dict[str, dict[str, object]] = {}
    for row, key, value in options:
        grouped.setdefault(row, {})[key] = value
    return grouped


def _model_dt(folder: str) -> float | None:
    """The sample time (s) a saved model was identified at (None when its file does not say:
    the model is then checked, and refused with the reason, when it is loaded)."""
    import json

    try:
        metadata = json.loads((Path(folder) / "model.json").read_text(encoding="utf-8"))
        value = metadata["metadata"].get("task", {}).get("dt_s", metadata["metadata"].get("dt"))
        return None if value is None else float(value)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def _policies(
    text: str, bender: str, dt: float | None = None
) -> tuple[tuple[str, ...], dict[str, str]]:
    """Policy folders from ``--policies`` ('none', a glob, or comma-separated folders), and
    the folders a glob found but left out, each with the reason.

    A glob keeps the policies trained for this bender's task (its stroke and sample time): the
    default finds the committed PPO policies, trained on the PL140 at 1 ms, and leaves them out
    for another bender. A named folder is kept, and :class:`benchmarks.runner.BenchmarkConfig`
    refuses it if it does not fit.
    """
    import glob

    if text.strip().lower() == "none":
        return (), {}
    folders: list[str] = []
    left_out: dict[str, str] = {}
    for part in _names(text):
        matches = sorted(glob.glob(part))
        if any(ch in part for ch in "*?["):
            for match in matches:
                if not os.path.isfile(os.path.join(match, "policy.json")):
                    continue
                reason = _policy_misfit(match, bender, dt)
                if reason is None:
                    folders.append(match)  # also one that does not load: refused with why
                else:
                    left_out[match] = reason
        else:
            folders.append(part)  # an explicit folder must load: BenchmarkConfig checks it
    return tuple(folders), left_out


def _committed_policies(
    names: tuple[str, ...], bender: str, dt: float | None = None
) -> tuple[tuple[str, ...], dict[str, str]]:
    """The committed policies of the recipes in ``names`` (``ppo``, ``ppo-dr``) that fit the
    ``bender`` benchmark's task, and the ones left out (folder or recipe -> why)."""
    folder = committed_policy_folder()
    kept: list[str] = []
    left_out: dict[str, str] = {}
    found: list[Path] = []
    for recipe in (n for n in COMMITTED_POLICIES if n in names):
        matches = [p for p in folder.glob(f"{recipe}-seed*") if (p / "policy.json").is_file()]
        if not matches:
            left_out[recipe] = (
                f"not found in {folder}: the committed policies come with the project's "
                "repository, not with an installed package"
            )
        found += matches
    for path in sorted(found):  # the order of the folders' names, as a glob lists them
        shown = os.path.relpath(path) if path.is_relative_to(Path.cwd()) else str(path)
        reason = _policy_misfit(str(path), bender, dt)
        if reason is None:
            kept.append(shown)
        else:
            left_out[shown] = reason
    return tuple(kept), left_out


def policies_line(added: tuple[str, ...], left_out: dict[str, str]) -> str:
    """One line on the policies a run added and left out ('' when none were asked for)."""
    parts = []
    if added:
        parts.append("running " + ", ".join(Path(f).name for f in added))
    by_reason: dict[str, list[str]] = {}
    for folder, reason in left_out.items():
        by_reason.setdefault(reason, []).append(Path(folder).name)
    parts += [f"left out {', '.join(names)}: {why}" for why, names in by_reason.items()]
    return "policies: " + "; ".join(parts) if parts else ""


def _policy_misfit(folder: str, bender: str, dt: float | None = None) -> str | None:
    """Why the policy in ``folder`` does not fit the ``bender`` benchmark's task (its stroke
    and sample time ``dt``, default the bender's), or None: also when it does not load (the
    config then says why)."""
    from benchmarks.plants import sample_time
    from controllers.policy import load_policy
    from piezo_env import get_datasheet

    try:
        policy = load_policy(folder)
    except ValueError:
        return None
    sheet = get_datasheet(bender)
    stroke_um = sheet.free_deflection * 1e6
    dt = sample_time(bender) if dt is None else dt
    trained_dt = policy.metadata.get("task", {}).get("dt_s")
    reasons = []
    if abs(policy.observation.stroke_um - stroke_um) > 1e-9 * stroke_um:
        reasons.append(f"a stroke of {policy.observation.stroke_um:g} um")
    if trained_dt is not None and abs(float(trained_dt) - dt) > 1e-9 * dt:
        reasons.append(f"dt = {float(trained_dt):g} s")
    if not reasons:
        return None
    return (
        f"trained for {' and '.join(reasons)}, but the {sheet.name} has a stroke of "
        f"{stroke_um:g} um and steps at dt = {dt:g} s"
    )


def _check_backend(args: argparse.Namespace) -> None:
    """Refuse a backend that cannot run here; with ``--address``, connect to the cluster now.

    The connection stays open for the run (:func:`piezo_parallel.backends.run_tasks` uses an open
    one), so an unreachable cluster is refused before the identification or the benchmark.
    """
    from piezo_parallel.backends import check_backend, connect_ray

    try:
        check_backend(args.backend)
    except (ValueError, RuntimeError) as error:
        raise CommandLineError(str(error)) from None
    if args.address is None:
        return
    address = args.address.strip()
    if args.backend != "ray":
        raise CommandLineError(f"--address is for --backend ray, not --backend {args.backend}")
    if not address:
        raise CommandLineError("--address needs a Ray address: auto, HOST:PORT or ray://HOST:PORT")
    try:
        connect_ray(address)
    except (ConnectionError, RuntimeError) as error:
        raise CommandLineError(
            f"--address {address}: cannot connect to the Ray cluster: {error}"
        ) from None


def _check_model_bender(folder: str, model, bender: str, dt: float | None = None) -> None:
    """Refuse, before any work, a model identified on another bender or sample time (``dt``,
    default the bender's)."""
    import gymnasium as gym

    from controllers.registry import check_model_fits_env

    rate = {} if dt is None else {"dt": dt}
    env = gym.make("piezo_env:PiezoBender-v0", preview=1, bender=bender, **rate)
    try:
        check_model_fits_env(model.metadata, env)
    except ValueError as error:
        raise CommandLineError(f"--model {folder}: {error}") from None
    finally:
        env.close()


def _check_model(args: argparse.Namespace) -> None:
    """Refuse a ``--model`` that does not load or was identified on another bender or sample
    time, before the output folder is made."""
    from identification.hammerstein import HammersteinModel

    if args.model is None:
        return
    try:
        model = HammersteinModel.load(args.model)
    except (OSError, ValueError) as error:
        raise CommandLineError(f"--model {args.model}: cannot load the model: {error}") from None
    _check_model_bender(args.model, model, args.bender, args.dt)


def identification_plants(bender: str) -> tuple[str, ...]:
    """The plants a model can be identified on (``--identify-on``): those of the bender itself
    under other conditions (an amplifier, a sensor, another hysteresis, noise, creep, drift).
    A plant with other datasheet values (the tolerance plants) or a distribution of plants
    would give a model of another bender, which the controllers, built for this one, refuse."""
    from benchmarks.plants import DRAWN_PLANTS, PLANTS

    return tuple(
        name
        for name, options in PLANTS.items()
        if name not in DRAWN_PLANTS and options(bender).get("bender") == bender
    )


def _check_identification(args: argparse.Namespace) -> None:
    """Refuse, before any work, identification options that cannot be honoured."""
    plants = identification_plants(args.bender)
    for i, plant in enumerate(args.identify_on):
        if plant not in plants:
            raise CommandLineError(
                f"--identify-on {plant}: not a plant a model of the {args.bender} can be "
                f"identified on; choose from {', '.join(plants)}"
            )
        if i and plant not in args.plants:
            raise CommandLineError(
                f"--identify-on {plant}: a later plant gets its own model for its own rows, "
                f"and the {plant} plant is not run; add it to --plants or put it first"
            )
    if len(set(args.identify_on)) != len(args.identify_on):
        raise CommandLineError(f"--identify-on names a plant twice: {','.join(args.identify_on)}")
    if args.model is not None and args.identification_seeds > 1:
        raise CommandLineError(
            f"--identification-seeds {args.identification_seeds} identifies the model "
            f"{args.identification_seeds} times, and --model gives one: drop one of the two"
        )
    if args.model is not None and args.identify_on != ("nominal",):
        raise CommandLineError(
            "--identify-on chooses where the model is identified, and --model gives one "
            "identified already: drop one of the two"
        )


def _model_folder(out, plant: str, k: int, first: bool):
    """Where the run keeps the model identified on ``plant`` with its k-th identification
    seed (``OUT/model`` for the first plant's first seed)."""
    name = "model" if first else f"model-{plant}"
    return out / (name if k == 0 else f"{name}-{k}")


def _models(args: argparse.Namespace, out) -> tuple[dict[str, list[str]], bool]:
    """The model folders to benchmark, per plant identified on and one per identification seed,
    and whether they are still to be identified (:func:`identify_models`).

    With ``--model`` that model is used; with ``--resume`` the models the interrupted run
    identified in ``OUT`` are used again (each loaded once to check it).
    """
    from identification.hammerstein import HammersteinModel

    count = args.identification_seeds
    folders = {
        plant: [_model_folder(out, plant, k, i == 0) for k in range(count)]
        for i, plant in enumerate(args.identify_on)
    }
    every = [f for fs in folders.values() for f in fs]
    if args.model is None and args.resume and all((f / "model.json").is_file() for f in every):
        for folder in every:
            try:
                HammersteinModel.load(folder)
            except (OSError, ValueError) as error:
                raise CommandLineError(
                    f"--resume: cannot load the model the run identified in {folder}: {error}; "
                    "run without --resume to start afresh"
                ) from None
        print(f"resuming with the model(s) identified in {', '.join(map(str, every))}")
        return {p: [str(f) for f in fs] for p, fs in folders.items()}, False
    if args.model is not None:  # loaded and checked before the output folder: _check_model
        return {"nominal": [str(args.model)]}, False
    return {p: [str(f) for f in fs] for p, fs in folders.items()}, True


def identify_models(
    bender: str, folders: dict[str, list[str]], seed: int, dt: float | None
) -> dict[str, float]:
    """Identify the models of ``folders`` (plant identified on -> one folder per
    identification seed, seeds ``seed``, ``seed + 1``, ...), printing each step; a worker of
    ``piezo benchmark`` runs it beside the rows that do not need a model.

    Returns
    -------
    dict
        ``{"identification_s": seconds}``, the time it took.
    """
    from benchmarks.plants import PLANTS
    from identification.pipeline import IdentificationConfig, identify

    def say(line: str) -> None:  # at once: the episodes' progress runs beside it
        print(line, flush=True)

    start = time.perf_counter()
    rate = {} if dt is None else {"dt": dt}
    for plant, plant_folders in folders.items():
        env = {**PLANTS[plant](bender), **rate}
        where = "" if plant == "nominal" else f" on the {plant} plant"
        for k, folder in enumerate(plant_folders):
            config = IdentificationConfig(seed=seed + k, env_kwargs=env)
            result = identify(config=config, progress=say)
            result.model.save(folder)
            fit = result.report["validation"]["hammerstein"]["fit_percent"]
            say(
                f"identified{where} with seed {seed + k}, saved in {folder} (validation "
                f"fit {fit:.2f} %)"
            )
    return {"identification_s": round(time.perf_counter() - start, 1)}


def _results() -> tuple[str, ...]:
    """The files a finished run writes: an earlier run's are removed before this one starts,
    so that a figure this run does not draw is not taken for its own."""
    from benchmarks.figures import FIGURES

    return ("benchmark.json", "benchmark.md", *FIGURES)


def _checkpoint(args: argparse.Namespace, out, config, model_dir):
    """The run's checkpoint in ``out``: resumed with ``--resume``, else started afresh.

    The results of an earlier run in ``out`` (its report, JSON and figures) are removed and the
    folder is marked incomplete
    until this run writes its own, so that neither a kill that nothing can catch (SIGKILL) nor
    an interruption leaves a report that looks finished.
    """
    from benchmarks.checkpoint import CHECKPOINT, Checkpoint, CheckpointMismatch, run_identity

    identity = run_identity(config, model_dir)
    if not args.resume and (out / CHECKPOINT).exists():
        print(
            f"starting afresh: the checkpoint of an earlier run in {out} is replaced (--resume "
            "would have continued it)"
        )
    try:
        checkpoint = (Checkpoint.resume if args.resume else Checkpoint.start)(out, identity)
    except CheckpointMismatch as error:
        raise CommandLineError(f"--resume: {error}") from None
    total = len(config.runs())
    if args.resume:
        print(f"resuming: {len(checkpoint.finished)} of {total} groups done in {checkpoint.path}")
    for name in _results():
        (out / name).unlink(missing_ok=True)
    mark_incomplete(out, "piezo benchmark", "has not finished", hint=_resume_hint(checkpoint))
    return checkpoint


def _resume_hint(checkpoint) -> str:
    return (
        f"The groups that finished are kept in {checkpoint.path.name}: run the same command "
        "with --resume to run only the others."
    )


def _left_behind(out, checkpoint, total: int, error: BaseException) -> None:
    """After a run stopped early: a checkpoint with finished groups stays and the folder says
    the run is incomplete; one with none is removed with the mark (an empty new folder then
    goes too)."""
    from piezo_cli.output import INCOMPLETE

    kept = checkpoint.kept()
    if not kept:
        checkpoint.remove()
        (out / INCOMPLETE).unlink(missing_ok=True)
        return
    if isinstance(error, KeyboardInterrupt):
        what = str(error) if str(error).startswith("interrupted") else "interrupted"
    else:
        what = f"stopped: {' '.join(str(error).split()) or type(error).__name__}"
    mark_incomplete(
        out,
        "piezo benchmark",
        f"was {what} after {kept} of {total} groups",
        hint=_resume_hint(checkpoint),
    )


def run(args: argparse.Namespace) -> int:
    """Check everything, identify (or load) the model, run the benchmark, write the report."""
    from benchmarks.references import REFERENCES
    from benchmarks.runner import DEFAULT_CONTROLLERS

    # Named on the command line, the references and controllers run on every selected plant;
    # left out, the robustness plants run their subsets (BenchmarkConfig.every_reference).
    args.every_reference, args.every_controller = (
        args.references is not None,
        args.controllers is not None,
    )
    args.references = tuple(REFERENCES) if args.references is None else args.references
    if args.controllers is None:  # the committed policies too
        args.controllers = (*DEFAULT_CONTROLLERS, *COMMITTED_POLICIES)
    if args.dt is None and args.model is not None:
        args.dt = _model_dt(args.model)
    committed, left_out = _committed_policies(args.controllers, args.bender, args.dt)
    own, own_left_out = _policies(args.policies, args.bender, args.dt)
    chosen = {os.path.realpath(p): p for p in (*committed, *own)}  # a folder named twice runs once
    policies, left_out = tuple(chosen.values()), {**left_out, **own_left_out}
    if left_out and not policies and all(c in COMMITTED_POLICIES for c in args.controllers):
        raise CommandLineError(  # the run would be empty: say why, not only that it is
            "no controller to run: " + policies_line(policies, left_out)
        )
    config = _config(args, policies)
    _check_identification(args)
    _check_backend(args)
    _check_model(args)
    out = prepare_output_dir(args.out)
    policy_line = policies_line(policies, left_out)
    if policy_line:
        print(policy_line)
    from benchmarks.machine import machine
    from benchmarks.report import (
        check_targets,
        missed_checks,
        strict_status,
        summary_line,
        tracking_tables,
        verdict,
        write_benchmark,
    )
    from benchmarks.runner import run_benchmark
    from benchmarks.verdict import headline_plants
    from piezo_cli.output import terminal_progress
    from piezo_env import TaskConfig
    from piezo_parallel import Prerequisite

    models, unidentified = _models(args, out)
    start = time.perf_counter()
    timing: dict[str, float] = {}
    if args.backend == "ray":  # workers on other nodes do not share this working directory
        models = {p: [os.path.abspath(f) for f in fs] for p, fs in models.items()}
        config = dataclasses.replace(
            config, policies=tuple(os.path.abspath(p) for p in config.policies)
        )
    first = next(iter(models.values()))
    if len(models) > 1:
        model_dir = models
    else:
        model_dir = first[0] if len(first) == 1 else first
    checkpoint = None
    resumed = 0

    def open_checkpoint(identified: dict[str, float] | None = None):
        nonlocal checkpoint, resumed
        timing.update(identified or {})
        opened = time.perf_counter()
        checkpoint = _checkpoint(args, out, config, model_dir)
        resumed = len(checkpoint.finished)
        timing["checkpoint_s"] = round(time.perf_counter() - opened, 2)
        return checkpoint

    identification = None
    if unidentified:  # beside the rows that need no model; the checkpoint (whose identity
        # holds the models) opens once they exist
        identification = Prerequisite(
            identify_models,
            (args.bender, models, args.seed, args.dt),
            label="the identification",
            then=open_checkpoint,
        )
    else:
        open_checkpoint()
    try:
        result = run_benchmark(
            config,
            model_dir,
            progress=terminal_progress(args.quiet),
            checkpoint=checkpoint,
            retries=args.retries,
            identification=identification,
        )
    except BaseException as error:
        if checkpoint is not None:  # else stopped during the identification: main marks
            # the folder incomplete if it holds something, and removes it if empty
            _left_behind(out, checkpoint, len(config.runs()), error)
        raise
    timing["benchmark_s"] = round(time.perf_counter() - start, 1)
    task = TaskConfig(bender=config.bender, dt=config.dt)
    meta = {
        "model": first[0],
        "dt": task.dt,
        "noise_bound_um": task.noise_bound,
        "stroke_um": config.stroke_um,
        "bender": config.bender,
        "jobs": config.jobs,
        "machine": machine(),
        "timing": timing,
    }
    if len(models) > 1 or len(first) > 1:
        meta["models"] = models
    meta["identify_on"] = list(args.identify_on) if args.model is None else None
    meta["identification_seeds"] = (
        None if args.model is not None else [args.seed + k for k in range(len(first))]
    )
    if policy_line:
        meta["policies"] = policy_line
    if left_out:
        meta["policies_left_out"] = left_out
    if resumed:
        meta["resumed_groups"] = resumed
    paths = write_benchmark(result, out, meta)
    clear_incomplete(out, "piezo benchmark")
    headline = headline_plants(result, meta)
    print(f"verdict ({' and '.join(headline) or 'no single'} plant, RMSE in % of the full stroke):")
    print("\n".join(line.replace("**", "").replace("`", "") for line in verdict(result, meta)))
    if headline:
        print()
        tables = tracking_tables(
            result, plants=tuple(headline), max_errors=False, identify_on=meta["identify_on"] or ()
        )
        print(tables.replace("**", ""))
    checks = check_targets(result)
    line = summary_line(checks)
    if line:
        print(line)
    print("time: " + ", ".join(f"{k} {v} s" for k, v in timing.items()))
    print("wrote " + ", ".join(str(p) for p in paths))
    if args.strict:
        for c in missed_checks(checks):
            print(f"  missed: {c['target']}: {c['value']:.4g} (limit {c['limit']:.4g})")
    return strict_status(checks, strict=args.strict)


BENCHMARK = Subcommand(
    name="benchmark",
    help="benchmark MPC against PID (and more) in closed loop on the bender",
    description=(
        "Identify the default PL140 model (or load one with --model) and run every "
        "controller on the same PiezoBender-v0 environment, seeds and references (the rows "
        "that need no model, the oracles and the policies, run beside the identification), on the "
        "nominal bender and on plants the model was not identified on. Writes benchmark.md, "
        "benchmark.json and figures into --out."
    ),
    add_arguments=add_arguments,
    run=run,
    examples=(
        "piezo benchmark --out out/benchmark",
        "piezo benchmark --model out/pl140/model --controllers mpc,pid-ff --plants nominal",
        "piezo benchmark --model out/pl140/model --backend ray --address auto",
        "piezo benchmark --out out/benchmark --resume",
    ),
)
