"""``piezo train-rl``: the command line of :func:`piezo_rl.ppo.train_ppo` (extra ``rl``)."""

from __future__ import annotations

import argparse
import importlib.util
import time

from piezo_cli.arguments import add_env_arguments, env_kwargs, non_negative_int, positive_int, seed
from piezo_cli.command import CommandLineError, Subcommand
from piezo_cli.output import prepare_output_dir

__all__ = ["TRAIN_RL"]

MISSING_EXTRA = 'piezo train-rl needs the optional extra: pip install "piezo-testbed[rl]"'


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``piezo train-rl``."""
    parser.add_argument("--out", default="out/policy", metavar="DIR", help="policy folder")
    parser.add_argument("--seed", type=seed, default=0, help="seed of torch and the envs")
    parser.add_argument(
        "--steps",
        type=positive_int,
        default=None,
        help="env steps over all envs (default 3000000; with --randomize the recipe's)",
    )
    parser.add_argument(
        "--num-envs",
        type=positive_int,
        default=None,
        help="sub-envs of the native vector env (default 16)",
    )
    parser.add_argument(
        "--randomize",
        action="store_true",
        help="domain randomisation: every sub-env draws its plant from the datasheet "
        "tolerances at each reset; trains the recipe of piezo_rl.ppo.RANDOMIZED (observation "
        "version 2 with past deflections; --seeds writes OUT/ppo-dr-seedN)",
    )
    parser.add_argument(
        "--preview", type=non_negative_int, default=10, help="reference samples seen ahead"
    )
    parser.add_argument(
        "--seeds",
        type=_seeds,
        default=None,
        metavar="A,B",
        help="train one policy per seed into OUT/ppo-seedN (OUT/ppo-dr-seedN with --randomize) "
        "instead of --seed, in parallel",
    )
    parser.add_argument("--jobs", type=positive_int, default=1, help="worker processes for --seeds")
    parser.add_argument(
        "--overwrite", action="store_true", help="replace policy folders that exist already"
    )
    parser.add_argument(
        "--backend",
        default="local",
        choices=("local", "ray"),
        help="where the --seeds runs go: local processes or Ray (extra ray)",
    )
    parser.add_argument(
        "--reference-band",
        type=_band,
        default=None,
        metavar="LOW,HIGH",
        help="frequency band (Hz) of the random training references (default: the env's, "
        "0.5,20; the committed policies used 0.5,60, the --randomize recipe's default)",
    )
    add_env_arguments(parser)


def _band(text: str) -> tuple[float, float]:
    parts = [p.strip() for p in text.split(",")]
    try:
        low, high = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected LOW,HIGH in Hz, got {text!r}") from None
    return low, high


def _kwargs(args: argparse.Namespace) -> dict:
    """The env settings of a training run: the bender options and the reference band."""
    kwargs = env_kwargs(args)
    if args.reference_band is not None:
        kwargs["reference_band"] = args.reference_band
    return kwargs


def _training(args: argparse.Namespace) -> tuple[int, dict]:
    """Total steps and the keyword arguments of ``train_ppo`` (nominal or randomised recipe)."""
    if not args.randomize:
        kwargs = {
            "num_envs": args.num_envs or 16,
            "preview": args.preview,
            "env_kwargs": _kwargs(args),
        }
        return args.steps or 3_000_000, kwargs
    from piezo_rl.ppo import RANDOMIZED

    kwargs = RANDOMIZED.train_kwargs(_kwargs(args))
    kwargs["preview"] = args.preview
    if args.num_envs is not None:
        kwargs["num_envs"] = args.num_envs
    return args.steps or RANDOMIZED.total_steps, kwargs


def _seeds(text: str) -> tuple[int, ...]:
    values = tuple(seed(part.strip()) for part in text.split(",") if part.strip())
    if not values or len(set(values)) != len(values):
        raise argparse.ArgumentTypeError(f"expected distinct seeds such as 0,1,2, got {text!r}")
    return values


def run(args: argparse.Namespace) -> int:
    """Refuse a missing extra, check the output folder, then train and write the policy."""
    if importlib.util.find_spec("stable_baselines3") is None:
        raise CommandLineError(MISSING_EXTRA)
    from piezo_rl.ppo import refuse_existing_policies, train_ppo

    if args.seeds is None and not args.overwrite:
        refuse_existing_policies([args.out])
    out = prepare_output_dir(args.out)
    start = time.perf_counter()
    if args.seeds is not None:
        return _run_seeds(args, out, start)
    steps, kwargs = _training(args)
    folder = train_ppo(args.seed, steps, out, progress=print, **kwargs)
    print(
        f"trained in {time.perf_counter() - start:.0f} s; wrote {folder / 'policy.json'} "
        f"and {folder / 'weights.npz'}"
    )
    return 0


def _run_seeds(args: argparse.Namespace, out, start: float) -> int:
    from piezo_parallel.backends import check_backend
    from piezo_rl.ppo import train_seeds

    try:
        check_backend(args.backend)
    except (ValueError, RuntimeError) as error:
        raise CommandLineError(str(error)) from None
    steps, kwargs = _training(args)
    folders = train_seeds(
        args.seeds,
        steps,
        out,
        jobs=args.jobs,
        backend=args.backend,
        overwrite=args.overwrite,
        name="ppo-dr" if args.randomize else "ppo",
        **kwargs,
    )
    print(
        f"trained {len(folders)} policies in {time.perf_counter() - start:.0f} s: "
        + ", ".join(str(f) for f in folders)
    )
    return 0


TRAIN_RL = Subcommand(
    name="train-rl",
    help="train a PPO policy (stable-baselines3) on the native vector env",
    description=(
        "Train a stable-baselines3 PPO policy on the natively batched env with its random "
        "references (steps, sines, triangles, multisines), 2000-step episodes and the "
        "stroke-scaled tracking observation of piezo_env.wrappers, seeded by --seed. Writes "
        "the policy as plain files into --out: policy.json (architecture, observation, "
        "training configuration, versions) and weights.npz (the actor's arrays). Needs the "
        'optional extra: pip install "piezo-testbed[rl]". 3 M steps take about 3 minutes on '
        "2 cores. With --randomize every sub-env draws its plant from the datasheet "
        "tolerances at each reset and the policy sees the past deflections too "
        "(piezo_rl.ppo.RANDOMIZED): a policy for every plant, not only the nominal one."
    ),
    add_arguments=add_arguments,
    run=run,
    examples=(
        "piezo train-rl --seed 0 --out out/ppo-seed0",
        "piezo train-rl --seed 1 --steps 500000 --num-envs 32 --out out/ppo-quick",
        "piezo train-rl --seeds 0,1,2 --jobs 2 --out out/ppo",
        "piezo train-rl --randomize --seeds 0,1,2 --out docs/policies",
    ),
)
