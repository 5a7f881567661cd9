"""``piezo simulate``: the command line of :mod:`piezo_env.simulate` (open-loop runs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from piezo_cli.arguments import (
    add_env_arguments,
    env_kwargs,
    finite_float,
    positive_float,
    sample_time,
    seed,
)
from piezo_cli.command import CommandLineError, Subcommand
from piezo_cli.output import prepare_output_dir
from piezo_env import CATALOGUE, get_datasheet
from piezo_env.signals import SIGNAL_DEFAULTS

__all__ = ["MAX_SAMPLES", "PERIODIC_SIGNALS", "SIGNALS", "SIMULATE", "check_arguments"]

SIGNALS = (
    "step",
    "sine",
    "triangle",
    "square",
    "random",
    "prbs",
    "multisine",
    "chirp",
    "decaying-multisine",
)
PERIODIC_SIGNALS = ("sine", "triangle", "square")
"""The signals ``--frequency`` applies to."""

MAX_SAMPLES = 1_000_000
"""Longest run in samples (``--duration / --dt``): 1000 s at 1 ms, about a minute of work
(100 s on the PL112 at its default 0.1 ms)."""

_RATED_VOLTAGES = "/".join(f"{v:g}" for v in sorted({s.rated_voltage for s in CATALOGUE.values()}))
_DEFAULT_FREQUENCY = SIGNAL_DEFAULTS["sine"]["frequency"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``piezo simulate``."""
    parser.add_argument("--signal", default="sine", choices=SIGNALS, help="input signal")
    parser.add_argument(
        "--amplitude",
        type=finite_float,
        default=30.0,
        metavar="V",
        help=f"peak drive voltage in volts, 0 up to the bender's rated {_RATED_VOLTAGES} V",
    )
    parser.add_argument(
        "--frequency",
        type=finite_float,
        default=None,
        metavar="HZ",
        help=(
            "frequency in Hz of the sine, triangle and square, above 0 and below the Nyquist "
            f"frequency 1 / (2 dt) (default: {_DEFAULT_FREQUENCY:g})"
        ),
    )
    parser.add_argument(
        "--duration",
        type=positive_float,
        default=3.0,
        metavar="S",
        help=f"length of the run in seconds, at most {MAX_SAMPLES:,} samples",
    )
    parser.add_argument("--seed", type=seed, default=0, help="seed of noise and random signals")
    parser.add_argument("--out", default="out/simulate", metavar="DIR", help="output folder")
    parser.add_argument(
        "--records",
        default=None,
        metavar="DIR",
        help="play the input records of an excitation folder ('piezo excite') instead of "
        "--signal, each from rest at its dt, and write the measured records "
        "(time_s,voltage_V,deflection_um, records.json) into --out, as a bench would; the "
        "bender options set the plant, --bender must be the folder's, --dt its dt if given",
    )
    add_env_arguments(parser)


def check_arguments(args: argparse.Namespace) -> None:
    """Refuse what the run would otherwise clip, alias or fail on after a long wait.

    Raises
    ------
    CommandLineError
        Amplitude outside 0 .. the rated voltage, a frequency for a signal that has none or
        outside (0, Nyquist), or a run longer than :data:`MAX_SAMPLES` samples.
    """
    sheet = get_datasheet(args.bender)
    dt = sample_time(args)
    if not 0 <= args.amplitude <= sheet.rated_voltage:
        raise CommandLineError(
            f"--amplitude {args.amplitude:g} V is outside the drive range of the {sheet.name}: "
            f"choose 0 to {sheet.rated_voltage:g} V (its rated voltage; the amplifier would clip "
            "anything beyond it)"
        )
    if args.frequency is not None and args.signal not in PERIODIC_SIGNALS:
        raise CommandLineError(
            f"--frequency applies only to --signal {', '.join(PERIODIC_SIGNALS)}; "
            f"{args.signal} uses its own frequencies"
        )
    if args.signal in PERIODIC_SIGNALS:
        if args.frequency is None:
            frequency, given = SIGNAL_DEFAULTS[args.signal]["frequency"], " (the default)"
        else:
            frequency, given = args.frequency, ""
        nyquist = 0.5 / dt
        if not 0 < frequency < nyquist:
            raise CommandLineError(
                f"--frequency {frequency:g} Hz{given} is out of range: choose above 0 and below "
                f"{nyquist:g} Hz (the Nyquist frequency of --dt {dt:g} s)"
            )
    samples = round(args.duration / dt)
    if samples > MAX_SAMPLES:
        raise CommandLineError(
            f"--duration {args.duration:g} s at --dt {dt:g} s is {samples:,} samples; "
            f"the limit is {MAX_SAMPLES:,} ({MAX_SAMPLES * dt:g} s at this --dt)"
        )


def run(args: argparse.Namespace) -> int:
    """Check the call and the output folder, then run, write and summarise the open-loop run."""
    if args.records is not None:
        return _measure_records(args)
    check_arguments(args)
    out = prepare_output_dir(args.out)
    from piezo_env.simulate import plot_record, run_open_loop, write_csv

    frequency = {} if args.frequency is None else {"frequency": args.frequency}
    record = run_open_loop(
        args.signal,
        amplitude=args.amplitude,
        duration=args.duration,
        seed=args.seed,
        signal_params=frequency,
        **env_kwargs(args),
    )
    csv_path = write_csv(record, out / "simulate.csv")
    title = f"{args.bender}: {args.signal} {args.amplitude:g} V, hysteresis {args.hysteresis}"
    png_path = plot_record(record, out / "simulate.png", title=title)
    print(f"peak deflection {abs(record.deflection_um).max():.1f} um over {record.time[-1]:.3f} s")
    print(f"wrote {csv_path} and {png_path}")
    return 0


def _measure_records(args: argparse.Namespace) -> int:
    """``--records``: measure an excitation folder's records on the simulated bender."""
    import gymnasium as gym

    from identification.records import MANIFEST, read_excitation, records_from_env, write_measured

    manifest, inputs = read_excitation(args.records)
    sheet = get_datasheet(args.bender)
    if get_datasheet(str(manifest["bender"])).name != sheet.name:
        raise CommandLineError(
            f"the records in {args.records} were made for the {manifest['bender']}, not the "
            f"{sheet.name}: pass --bender {str(manifest['bender']).split('.')[0]}"
        )
    dt = float(manifest["dt"])
    if args.dt is not None and abs(args.dt - dt) > 1e-12 * dt:
        raise CommandLineError(
            f"--dt {args.dt:g} s differs from the records' dt {dt:g} s; drop --dt (the records "
            "set it)"
        )
    out = prepare_output_dir(args.out)
    kwargs = {**env_kwargs(args), "dt": dt}
    env = gym.make("piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, **kwargs)
    records = records_from_env(env, inputs, int(manifest.get("seed", 0)))
    paths = write_measured(out, records, excitation=Path(args.records) / MANIFEST)
    for name, (u, y) in records.records.items():
        print(
            f"{name}: {len(u)} samples, peak |y| {abs(y).max():.1f} um, |u| <= {abs(u).max():.3g} V"
        )
    print(f"files in {out}: {', '.join(p.name for p in paths)}")
    return 0


SIMULATE = Subcommand(
    name="simulate",
    help="drive the bender open loop with a test signal; write CSV and PNG",
    description=(
        "Drive the simulated bender open loop with a test signal and write the record "
        "(simulate.csv: voltage, effective voltage, true and measured deflection, charge) and a "
        "figure (simulate.png: input, deflection and the hysteresis loop) into --out."
    ),
    add_arguments=add_arguments,
    run=run,
    examples=(
        "piezo simulate --signal sine --amplitude 30 --frequency 1",
        "piezo simulate --signal chirp --amplitude 10 --duration 5 --out out/chirp",
        "piezo simulate --bender PL122 --hysteresis none --noise-bound 0",
        "piezo simulate --records out/excite --hysteresis rate-dependent --out out/measured",
    ),
)
