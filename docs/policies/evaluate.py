"""RMSE (% of stroke) of policy folders on the nominal, stiffness +-20 % and random plants.

The benchmark's conventions (:mod:`benchmarks.runner`): ``PiezoBender-v0`` with preview 20,
2000-step episodes, the references of :func:`benchmarks.references.make_reference` for
evaluation seed 0, the controller built on the nominal env and run unchanged on each plant,
percentages of the nominal stroke. The random plants (``randomize=True``) are drawn with env
seeds 0 .. draws-1, one episode each, as the benchmark's Monte Carlo table draws them.

Run: ``python docs/policies/evaluate.py docs/policies/ppo-seed0 docs/policies/ppo-dr-seed0``
(about 10 s per policy and 20 draws).
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from benchmarks.plants import DT, PLANTS
from benchmarks.references import make_reference
from controllers.episode import run_episode
from controllers.policy import make_policy_controller

REFERENCES = ("sine-10Hz", "sine-50Hz", "multisine")
STEPS = 2000
PREVIEW = 20
STROKE_UM = 1000.0


def _env(kwargs: dict[str, Any]) -> gym.Env:
    return gym.make("piezo_env:PiezoBender-v0", preview=PREVIEW, max_episode_steps=STEPS, **kwargs)


def evaluate(
    folder: str | Path | Callable[[gym.Env], Any], *, draws: int = 20, seed: int = 0
) -> dict[str, dict[str, Any]]:
    """RMSE (% of stroke) of one policy: reference -> plant -> value (random plants: a list).

    Parameters
    ----------
    folder : str, Path or callable
        A policy folder, or a function of the nominal env that builds the controller.
    draws : int
        Random plants (env seeds seed .. seed + draws - 1).
    seed : int
        Evaluation seed (references and sensor noise).
    """
    nominal = _env(PLANTS["nominal"]("PL140"))
    if callable(folder):
        controller = folder(nominal)
    else:
        controller = make_policy_controller(folder, nominal)
    references = {
        name: make_reference(name, STEPS + PREVIEW + 1, dt=DT, seed=seed) for name in REFERENCES
    }
    plants = {name: PLANTS[name]("PL140") for name in ("nominal", "stiffness+20%", "stiffness-20%")}
    out: dict[str, dict[str, Any]] = {name: {} for name in REFERENCES}
    for plant, kwargs in plants.items():
        env = _env(kwargs)
        for name, reference in references.items():
            episode = run_episode(
                env, controller, seed=seed, reference=reference, stroke_um=STROKE_UM
            )
            out[name][plant] = float(episode.metrics["rmse_percent"])
        env.close()
    env = _env(PLANTS["random-plants"]("PL140"))
    for name, reference in references.items():
        out[name]["random"] = [
            float(
                run_episode(
                    env, controller, seed=seed + d, reference=reference, stroke_um=STROKE_UM
                ).metrics["rmse_percent"]
            )
            for d in range(draws)
        ]
    env.close()
    nominal.close()
    return out


def summary_row(result: dict[str, dict[str, Any]]) -> dict[str, float]:
    """Flat figures: ``ref/plant`` and ``ref/random-median``, ``ref/random-worst``."""
    row: dict[str, float] = {}
    for ref, plants in result.items():
        for plant, value in plants.items():
            if plant == "random":
                row[f"{ref}/random-median"] = float(np.median(value))
                row[f"{ref}/random-worst"] = float(np.max(value))
            else:
                row[f"{ref}/{plant}"] = value
    return row


def markdown_tables(results: dict[str, dict[str, float]]) -> str:
    """One table per reference: a row per policy and, per recipe, mean +- std over its seeds."""
    import re

    columns = ("nominal", "stiffness+20%", "stiffness-20%", "random-median", "random-worst")
    recipes: dict[str, list[str]] = {}
    for name in results:
        match = re.fullmatch(r"(.+)-seed\d+", name)
        if match:
            recipes.setdefault(match.group(1), []).append(name)
    parts = []
    for ref in REFERENCES:
        lines = [
            f"{ref}: RMSE (% of the 2000 um stroke)",
            "",
            "| policy | " + " | ".join(columns) + " |",
            "|---" * (len(columns) + 1) + "|",
        ]
        for name, row in results.items():
            cells = [f"{row[f'{ref}/{c}']:.2f}" for c in columns]
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
        for recipe, members in recipes.items():
            if len(members) < 2:
                continue
            cells = []
            for c in columns:
                values = [results[m][f"{ref}/{c}"] for m in members]
                cells.append(f"{np.mean(values):.2f} ± {np.std(values, ddof=1):.2f}")
            lines.append(f"| {recipe} (mean ± std) | " + " | ".join(cells) + " |")
        parts.append("\n".join(lines))
    return "\n\n".join(parts) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+")
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--json", default=None, help="write the figures to this file")
    parser.add_argument("--markdown", action="store_true", help="print the tables in Markdown")
    args = parser.parse_args()
    results = {}
    for folder in args.folders:
        row = summary_row(evaluate(folder, draws=args.draws))
        results[Path(folder).name] = row
        print(Path(folder).name, json.dumps({k: round(v, 2) for k, v in row.items()}))
    if args.markdown:
        print(markdown_tables(results))
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
