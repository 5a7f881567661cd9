"""``piezo excite``: the input records of the identification, for a bench to play
(:func:`identification.records.write_excitation`)."""

from __future__ import annotations

import argparse

from piezo_cli.arguments import bender_name, positive_float, seed
from piezo_cli.command import Subcommand
from piezo_cli.output import prepare_output_dir
from piezo_env import TaskConfig, default_dt

__all__ = ["EXCITE"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``piezo excite``."""
    parser.add_argument(
        "--bender",
        type=bender_name,
        default=TaskConfig().bender,
        metavar="NAME",
        help="PI PICMA bender type (PL112, PL122, PL127, PL128 or PL140): sets the drive range "
        "and the default sample time",
    )
    parser.add_argument(
        "--dt",
        type=positive_float,
        default=None,
        metavar="S",
        help="sample time of the bench in seconds (default: the bender's, piezo_env.default_dt)",
    )
    parser.add_argument(
        "--seed", type=seed, default=0, help="seed of the signals (and later of the training)"
    )
    parser.add_argument("--out", default="out/excite", metavar="DIR", help="output folder")


def run(args: argparse.Namespace) -> int:
    """Check the output folder, write the input records and the manifest, and list them."""
    from identification.config import IdentificationConfig
    from identification.records import read_manifest, write_excitation

    dt = args.dt if args.dt is not None else default_dt(args.bender)
    config = IdentificationConfig(seed=args.seed, env_kwargs={"bender": args.bender, "dt": dt})
    config.at_sample_time(dt)  # refuses a dt at which a record would be too short
    out = prepare_output_dir(args.out)
    paths = write_excitation(out, config, bender=args.bender, dt=dt)
    manifest = read_manifest(out)
    peaks = _simulated_peaks(out, args.bender, dt, args.seed)
    stroke = manifest["datasheet"]["free_deflection"] * 1e6
    print(
        f"input records of the identification of the {manifest['bender']} at dt = {dt:g} s, "
        f"seed {args.seed}, drive range {manifest['drive_range_V']} V:"
    )
    for name, purpose in manifest["purposes"].items():
        print(
            f"  {name}.csv: {purpose}; on the simulated bender its peak deflection is "
            f"{peaks[name]:.0f} um ({peaks[name] / stroke:.1f} x the rated {stroke:g} um)"
        )
    print(
        "play each from rest at dt and record time_s,voltage_V,deflection_um (see 'measure' in "
        "records.json); then piezo identify --records FOLDER"
    )
    print(f"files in {out}: {', '.join(p.name for p in paths)}")
    return 0


def _simulated_peaks(folder, bender: str, dt: float, seed: int) -> dict[str, float]:
    """Peak |deflection| (um) of each record on the simulated bender, without sensor noise:
    what the bench's bender will be asked to do, to check against its stroke before playing."""
    import gymnasium as gym

    from identification.records import read_excitation, records_from_env

    _, inputs = read_excitation(folder)
    env = gym.make(
        "piezo_env:PiezoBender-v0",
        reference=None,
        max_episode_steps=-1,
        bender=bender,
        dt=dt,
        noise_bound=0.0,
    )
    records = records_from_env(env, inputs, seed)
    return {name: float(abs(y).max()) for name, (_, y) in records.records.items()}


EXCITE = Subcommand(
    name="excite",
    help="write the identification's input records (CSV, NPZ, records.json) for a real bench",
    description=(
        "Write the input voltages of the identification experiment (PRBS of step a, rich "
        "record of step c, selection record of step e, validation record of step f) as "
        "NAME.csv (time_s,voltage_V) and NAME.npz, with a manifest records.json: exactly the "
        "signals 'piezo identify' drives the simulated bender with for this bender, sample time "
        "and seed. Play them on the bench, record the applied voltage and the deflection, and "
        "identify with 'piezo identify --records'; 'piezo simulate --records' measures them on "
        "the simulated bender. The peak deflection each record reaches on the simulated "
        "bender is printed: check it against your bender's stroke and mounting before playing "
        "it (the white PRBS and the RAND records ring the first bending mode)."
    ),
    add_arguments=add_arguments,
    run=run,
    examples=(
        "piezo excite --bender PL140 --out out/excite-pl140",
        "piezo excite --bender PL127 --dt 0.0005 --seed 1 --out out/excite-pl127",
    ),
)
