"""``piezo identify``: the command line of :mod:`identification.pipeline` (paper 3.4, a-f)."""

from __future__ import annotations

import argparse

from piezo_cli.arguments import add_env_arguments, env_kwargs, positive_int, seed
from piezo_cli.command import CommandLineError, Subcommand
from piezo_cli.output import prepare_output_dir

__all__ = ["FEATURES", "IDENTIFY", "summary"]

FEATURES = ("auto", "play", "past-inputs", "bouc-wen")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``piezo identify``."""
    parser.add_argument("--out", default="out/identify", metavar="DIR", help="output folder")
    parser.add_argument(
        "--seed",
        type=seed,
        default=None,
        help="seed of every signal, the noise and the training (default: 0; with --records, "
        "the seed in records.json, so that records measured on the simulated bender give the "
        "model 'piezo identify' gives)",
    )
    parser.add_argument(
        "--records",
        default=None,
        metavar="DIR",
        help="identify from measured records (a folder with records.json listing NAME.csv "
        "files of time_s,voltage_V,deflection_um, as a bench or 'piezo simulate --records' "
        "writes them) instead of the simulated bender; the bender options are then not used",
    )
    parser.add_argument(
        "--split",
        type=_fraction,
        default=None,
        metavar="FRACTION",
        help="with --records holding a single long record: its first FRACTION is the "
        "estimation record (steps b-e'), the first half of the rest the selection record "
        "(step e), the second half the validation record (step f)",
    )
    parser.add_argument(
        "--features",
        default="auto",
        choices=FEATURES,
        help="memory features of the neural nonlinearity (auto: chosen on a selection record)",
    )
    parser.add_argument(
        "--rate",
        default="auto",
        choices=("off", "on", "auto"),
        help="with play features: plays whose radii grow with the drive's rate, the rate "
        "constant learned with the radii in step e' (auto: kept only if the held-out selection "
        "record's error falls by more than its noise allows)",
    )
    from piezo_parallel.backends import default_jobs

    parser.add_argument(
        "--jobs",
        type=positive_int,
        default=default_jobs(),
        help="processes: 2 or more let step e's candidate networks and step e''s independent "
        "refinements run beside each other on a second process (the same model to the bit)",
    )
    add_env_arguments(parser)


def _fraction(text: str) -> float:
    """A number strictly between 0 and 1 (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a fraction between 0 and 1, got {text!r}")
    return value


def run(args: argparse.Namespace) -> int:
    """Check the call and the output folder, then identify (from the simulated bender or from
    measured records), write the model and report, and summarise."""
    if args.split is not None and args.records is None:
        raise CommandLineError(
            "--split applies to --records (a single long record); add --records DIR"
        )
    from identification.config import env_sample_time
    from identification.pipeline import (
        IdentificationConfig,
        identify,
        identify_records,
        read_records_folder,
        write_outputs,
    )
    from identification.runner import step_runner
    from identification.steps import warm_up

    if args.records is not None:  # a malformed folder is refused before --out is made
        records, settings = read_records_folder(
            args.records,
            IdentificationConfig(features=args.features, rate=args.rate),
            split=args.split,
        )
    else:
        config = IdentificationConfig(
            seed=0 if args.seed is None else args.seed,
            features=args.features,
            rate=args.rate,
            env_kwargs=env_kwargs(args),
        )
        # a dt at which a record would be too short or too long is refused before --out is made
        config.at_sample_time(env_sample_time(config.env_kwargs))
    out = prepare_output_dir(args.out)
    with step_runner(args.jobs, warm_up) as runner:  # its helper draws figures too
        if args.records is None:
            result = identify(config=config, progress=print, runner=runner)
        else:
            result = identify_records(
                records, seed=args.seed, config=settings, progress=print, runner=runner
            )
        paths = write_outputs(result, out, runner=runner)
    print()
    print(summary(result.report))
    names = ", ".join(p.name + ("/" if p.is_dir() else "") for p in paths)
    print(f"files in {out}: {names}")
    return 0


def summary(report: dict) -> str:
    """A few lines a user reads first: the chosen order and features, the noise bound, the fits."""
    arx, nls, validation = report["arx"], report["nls"], report["validation"]
    how = "chosen on a selection record" if report["config"]["features"] == "auto" else "as asked"
    lines = [
        f"ARX order {arx['order']} (chosen by held-out free-run fit), static gain "
        f"{arx['static_gain_um_per_V']:.2f} um/V, estimated noise bound "
        f"{arx['noise_bound_um']:.2f} um (equation error: model error and sensor noise)",
    ]
    refined = (report.get("refinement") or {}).get("after")
    again = (report["nls"].get("output_error") or {}).get("accepted", False)
    if refined:
        lines.append(
            f"linear part refined by output error (step b'): order {refined['order']}"
            + (", then with the network (step e')" if again else "")
            + ": the one the controllers use"
        )
    rate = ""
    stages = (report["nls"].get("output_error") or {}).get("stages") or []
    if again and stages and "rate_time_s" in stages[0]:  # the plays' rate constant, learned
        c = stages[0]["rate_time_s"]
        rate = f", rate-dependent (c = {c:.3g} s)" if c > 0 else ", rate-independent"
        if stages[0].get("rate_note"):
            rate += f": {stages[0]['rate_note']}"
    lines += [
        f"NLS memory features: {nls['features']} ({how}){rate}",
        f"validation on {validation['signal']}, free run:",
    ]
    for name, label in (("hammerstein", "Hammerstein model"), ("linear_arx", "linear ARX alone")):
        fit = validation[name]
        lines.append(
            f"  {label}: fit {fit['fit_percent']:.2f} %, RMSE {fit['rmse']:.1f} um, "
            f"max error {fit['max_abs_error']:.1f} um"
        )
    lines.append("(the whole report is report.md / report.json in the output folder)")
    return "\n".join(lines)


IDENTIFY = Subcommand(
    name="identify",
    help="identify the Hammerstein model of the bender (paper 3.4, steps a-f)",
    description=(
        "Identify a Hammerstein model of the simulated bender as in section 3.4 of the paper: "
        "PRBS excitation, ARX part by the uniform-noise Bayesian estimator (then refined by "
        "output error), rich excitation, hidden signal by the inverse ARX model, neural "
        "nonlinearity (then the whole model refined by output error), free-run validation. "
        "Writes the model (model/), report.json, report.md and figures into --out; takes "
        "10-20 s on 2 cores, most of it the network's training and refinement. With --records "
        "the same steps b-f run on measured records (see 'piezo excite'), checked first: a "
        "malformed record is refused in one line naming the file and the line."
    ),
    add_arguments=add_arguments,
    run=run,
    examples=(
        "piezo identify --out out/pl140",
        "piezo identify --bender PL122 --noise-bound 0.5 --out out/pl122",
        "piezo identify --records out/measured-pl140 --out out/pl140-bench",
        "piezo identify --records out/one-long-run --split 0.7 --out out/long",
    ),
)
