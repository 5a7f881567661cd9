"""Argument types and the environment options shared by every ``piezo`` subcommand.

The type functions reject a malformed value while argparse parses it (one line, exit status
2), so nothing starts with a NaN duration or a negative seed. Checks that need two options at
once (an amplitude against the bender's rated voltage, a frequency against the sample time)
live with the subcommand that has both.
"""

from __future__ import annotations

import argparse
import math

from piezo_env import CATALOGUE, default_dt

__all__ = [
    "BENDER_CHOICES",
    "HYSTERESIS_CHOICES",
    "add_env_arguments",
    "bender_name",
    "env_kwargs",
    "finite_float",
    "non_negative_float",
    "non_negative_int",
    "positive_float",
    "positive_int",
    "sample_time",
    "seed",
    "whole_number",
]

BENDER_CHOICES: tuple[str, ...] = tuple(
    sorted({*CATALOGUE, *(name.split(".")[0] for name in CATALOGUE)})
)
"""Catalogue names accepted by ``--bender``, with and without the ``.10`` suffix."""

_SHORT_NAMES = sorted({name.split(".")[0] for name in CATALOGUE})

HYSTERESIS_CHOICES: dict[str, str | None] = {
    "bouc-wen": "bouc-wen",
    "prandtl-ishlinskii": "prandtl-ishlinskii",
    "rate-dependent": "rate-dependent",
    "none": None,
}
"""``--hysteresis`` words and the env's ``hysteresis`` argument each stands for."""


def finite_float(text: str) -> float:
    """A finite real number (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_float(text: str) -> float:
    """A finite number > 0 (argparse type)."""
    value = finite_float(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be greater than 0, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    """A finite number >= 0 (argparse type); ``off`` means 0."""
    if text.strip().lower() == "off":
        return 0.0
    value = finite_float(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be 0 or more, got {text!r}")
    return value


def whole_number(text: str, minimum: int) -> int:
    """``text`` as a whole number >= ``minimum``, or an argparse error saying so."""
    try:
        value = int(text)
    except ValueError:
        value = minimum - 1
    if value < minimum:
        raise argparse.ArgumentTypeError(f"expected a whole number >= {minimum}, got {text!r}")
    return value


def seed(text: str) -> int:
    """A non-negative whole number (argparse type), as numpy and Gymnasium accept for seeds."""
    return whole_number(text, 0)


def non_negative_int(text: str) -> int:
    """A whole number >= 0 (argparse type)."""
    return whole_number(text, 0)


def positive_int(text: str) -> int:
    """A whole number >= 1 (argparse type)."""
    return whole_number(text, 1)


def bender_name(text: str) -> str:
    """A catalogue bender name, with or without the .10 suffix (argparse type)."""
    name = text.strip().upper()
    if name not in BENDER_CHOICES:
        raise argparse.ArgumentTypeError(
            f"unknown bender {text!r}; choose {_or(_SHORT_NAMES)} (the .10 suffix is optional)"
        )
    return name


def _or(words: list[str]) -> str:
    return ", ".join(words[:-1]) + " or " + words[-1] if len(words) > 1 else words[0]


def _hysteresis(text: str) -> str:
    word = text.strip().lower()
    return "none" if word == "off" else word


def add_env_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options that configure the simulated bender (``--bender``, ``--dt``, ...).

    Their defaults are the task's own (:class:`piezo_env.TaskConfig`), written once there.
    """
    from piezo_env import TaskConfig

    task = TaskConfig()
    hysteresis = next(k for k, v in HYSTERESIS_CHOICES.items() if v == task.hysteresis)
    env = parser.add_argument_group("simulated bender")
    env.add_argument(
        "--bender",
        type=bender_name,
        default=task.bender,
        choices=BENDER_CHOICES,
        metavar="NAME",
        help=f"PI PICMA bender type: {_or(_SHORT_NAMES)} (the .10 suffix is optional)",
    )
    env.add_argument(
        "--hysteresis",
        type=_hysteresis,
        default=hysteresis,
        choices=tuple(HYSTERESIS_CHOICES),
        help="input hysteresis model",
    )
    env.add_argument(
        "--noise-bound",
        type=non_negative_float,
        default=task.noise_bound,
        metavar="UM",
        help="sensor noise bound r in micrometres: uniform noise in [-r, r]; 0 for none",
    )
    env.add_argument(
        "--dt",
        type=positive_float,
        default=None,
        metavar="S",
        help="sample time in seconds (default: the bender's, piezo_env.default_dt: its first "
        "resonance within the datasheet tolerance at most a quarter of the sampling rate; "
        + ", ".join(f"{_ms(default_dt(name))} ms for the {name}" for name in _SHORT_NAMES)
        + ")",
    )
    env.add_argument(
        "--creep", action="store_true", default=bool(task.creep), help="add linear creep"
    )


def env_kwargs(args: argparse.Namespace) -> dict[str, object]:
    """The PiezoBender-v0 keyword arguments the options of :func:`add_env_arguments` give.

    ``dt`` is left out without ``--dt``: the env then takes the bender's default.
    """
    kwargs: dict[str, object] = {
        "bender": args.bender,
        "hysteresis": HYSTERESIS_CHOICES[args.hysteresis],
        "noise_bound": args.noise_bound,
        "creep": args.creep,
    }
    if args.dt is not None:
        kwargs["dt"] = args.dt
    return kwargs


def sample_time(args: argparse.Namespace) -> float:
    """The sample time (s) of the run: ``--dt``, else the bender's default."""
    return args.dt if args.dt is not None else default_dt(args.bender)


def _ms(seconds: float) -> str:
    return f"{seconds * 1e3:g}"
