"""``piezo``: command line of the testbed. Each subcommand parses its arguments and calls the
package that owns the work; no logic lives here.

    piezo simulate --signal sine --amplitude 30 --frequency 1 --out out/simulate
    piezo identify --out out/pl140
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

__all__ = ["main"]


def _float_or_none(text: str) -> float | None:
    return None if text.lower() in ("none", "off") else float(text)


def _hysteresis(text: str) -> str | None:
    return None if text.lower() in ("none", "off") else text


def _add_env_arguments(parser: argparse.ArgumentParser) -> None:
    env = parser.add_argument_group("environment")
    env.add_argument("--bender", default="PL140", help="catalogue name (default PL140)")
    env.add_argument(
        "--hysteresis",
        type=_hysteresis,
        default="bouc-wen",
        help="bouc-wen | prandtl-ishlinskii | none",
    )
    env.add_argument("--noise-bound", type=float, default=1.0, help="sensor noise bound (um)")
    env.add_argument("--dt", type=float, default=1e-3, help="sample time (s)")
    env.add_argument("--creep", action="store_true", help="add linear creep")


def _env_kwargs(args: argparse.Namespace) -> dict:
    return {
        "bender": args.bender,
        "hysteresis": args.hysteresis,
        "noise_bound": args.noise_bound,
        "dt": args.dt,
        "creep": args.creep,
    }


def _simulate(args: argparse.Namespace) -> int:
    from piezo_env.simulate import plot_record, run_open_loop, write_csv

    params = {}
    if args.frequency is not None:
        params["frequency"] = args.frequency
    record = run_open_loop(
        args.signal,
        amplitude=args.amplitude,
        duration=args.duration,
        seed=args.seed,
        signal_params=params,
        **_env_kwargs(args),
    )
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    csv_path = write_csv(record, out / "simulate.csv")
    title = f"{args.bender}: {args.signal} {args.amplitude:g} V, hysteresis {args.hysteresis}"
    png_path = plot_record(record, out / "simulate.png", title=title)
    print(f"peak deflection {abs(record.deflection_um).max():.1f} um over {record.time[-1]:.3f} s")
    print(f"wrote {csv_path} and {png_path}")
    return 0


def _identify(args: argparse.Namespace) -> int:
    from identification.pipeline import IdentificationConfig, identify, write_outputs

    config = IdentificationConfig(
        seed=args.seed, features=args.features, env_kwargs=_env_kwargs(args)
    )
    result = identify(config=config, progress=print)
    paths = write_outputs(result, args.out)
    print(json.dumps(result.report["validation"], indent=2))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    parser = argparse.ArgumentParser(prog="piezo", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("simulate", help="drive the bender open loop; write CSV and PNG")
    sim.add_argument(
        "--signal",
        default="sine",
        choices=[
            "step",
            "sine",
            "triangle",
            "square",
            "random",
            "prbs",
            "multisine",
            "chirp",
            "decaying-multisine",
        ],
    )
    sim.add_argument("--amplitude", type=float, default=30.0, help="signal amplitude (V)")
    sim.add_argument(
        "--frequency", type=float, default=None, help="frequency (Hz), periodic signals"
    )
    sim.add_argument("--duration", type=float, default=3.0, help="length (s)")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--out", default="out/simulate", help="output folder")
    _add_env_arguments(sim)
    sim.set_defaults(func=_simulate)

    ident = sub.add_parser("identify", help="identify the Hammerstein model (paper 3.4, steps a-f)")
    ident.add_argument("--out", default="out/identify", help="output folder")
    ident.add_argument("--seed", type=int, default=0)
    ident.add_argument(
        "--features",
        default="auto",
        choices=["auto", "play", "past-inputs", "bouc-wen"],
        help="memory features of the neural nonlinearity (auto: chosen on a selection record)",
    )
    _add_env_arguments(ident)
    ident.set_defaults(func=_identify)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``piezo`` console script."""
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as error:
        print(f"piezo {args.command}: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
