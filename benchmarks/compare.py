"""What changed between two benchmark runs (``piezo compare OLD.json NEW.json``).

Cells are matched by plant, controller, reference and draw (:mod:`benchmarks.cells`), and
compared on the seeds both runs ran: an episode's seeds are its noise seed (the run's seed plus
its ``seed_index``) and, for a row built on the identified model, its identification seed (an
episode without one ran on the run's single model, identified with the run's seed, which is
what ``piezo benchmark`` does without ``--model``). The same seeds give the same sensor noise
and the same model, so the two runs are paired:

- one shared seed: a change is marked when it is more than :data:`benchmarks.cells.TIE`
  relative (the same code gives the same bits);
- several: the mean of the per-seed log ratios log(new / old) is marked when it lies outside
  their own 95 % interval (a paired t-test, :func:`benchmarks.cells.ci95_half_width`, on the
  relative change: a seed's RMSE can be several times another's, and a change scales it);
- none (the runs have disjoint seeds): the cells' means are compared as before, outside their
  combined 95 % intervals (:func:`benchmarks.cells.different`).

The table gives each cell's RMSE over the shared seeds, and the output says when the two runs'
seed sets differ. Cells only one run has are listed as added or removed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.cells import KEYS, TIE, aggregate, ci95_half_width, different

__all__ = ["SAME_TASK", "compare_files", "compare_runs", "load_run"]


def load_run(path: str | Path) -> dict[str, Any]:
    """A benchmark.json, checked enough to compare: its episodes, each with its cell's names,
    a finite RMSE and integer seeds (ValueError names the file and what is wrong)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"{path}: not a readable benchmark.json ({error})") from None
    results = data.get("results") if isinstance(data, dict) else None
    if not isinstance(results, dict) or not isinstance(results.get("episodes"), list):
        raise ValueError(f"{path}: no results.episodes: not a benchmark.json of piezo benchmark")
    if not isinstance(results.get("config", {}), dict):
        raise ValueError(f"{path}: results.config is not an object")
    for i, episode in enumerate(results["episodes"]):
        where = f"{path}: results.episodes[{i}]"
        if not isinstance(episode, dict):
            raise ValueError(f"{where} is not an object")
        missing = [key for key in ("plant", "controller", "reference") if key not in episode]
        if missing:
            raise ValueError(f"{where} has no {', '.join(missing)}")
        rmse = episode.get("rmse_percent")
        if not (
            isinstance(rmse, (int, float)) and not isinstance(rmse, bool) and math.isfinite(rmse)
        ):
            raise ValueError(f"{where}.rmse_percent is not a finite number: {rmse!r}")
        for key in ("seed_index", "identification_seed"):
            value = episode.get(key, 0)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{where}.{key} is not an integer: {value!r}")
    seed = results.get("config", {}).get("seed", 0)
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ValueError(f"{path}: results.config.seed is not an integer: {seed!r}")
    return data


def _seeds(data: dict[str, Any], episode: dict[str, Any]) -> tuple[int, int]:
    """(noise seed, identification seed) of one episode of the run ``data``."""
    seed = int(data["results"].get("config", {}).get("seed", 0))
    return seed + int(episode.get("seed_index", 0)), int(episode.get("identification_seed", seed))


def _episodes(data: dict[str, Any]) -> dict[tuple, dict[tuple[int, int], dict[str, Any]]]:
    """Cell key -> (noise seed, identification seed) -> episode."""
    out: dict[tuple, dict[tuple[int, int], dict[str, Any]]] = {}
    for e in data["results"]["episodes"]:
        out.setdefault(tuple(e.get(k) for k in KEYS), {})[_seeds(data, e)] = e
    return out


def _seed_set(data: dict[str, Any]) -> set[tuple[int, int]]:
    return {_seeds(data, e) for e in data["results"]["episodes"]}


SAME_TASK = ("bender", "dt", "steps", "preview")
"""Settings of ``results.config`` two runs must share to be compared: another bender, sample
time, episode length or preview makes every cell another experiment."""


def compare_runs(old: dict[str, Any], new: dict[str, Any]) -> tuple[str, int]:
    """A Markdown table of every cell's RMSE in both runs, and the number of marked changes
    (see the module docstring for when a change is marked).

    Raises
    ------
    ValueError
        The runs differ in a setting of :data:`SAME_TASK` (one a run does not record is not
        checked).
    """
    config_old = old["results"].get("config", {})
    config_new = new["results"].get("config", {})
    differ = [
        f"{key} {config_old[key]!r} against {config_new[key]!r}"
        for key in SAME_TASK
        if key in config_old and key in config_new and config_old[key] != config_new[key]
    ]
    if differ:
        raise ValueError(
            "the runs are of different tasks (" + ", ".join(differ) + "): their cells are not "
            "the same experiments; compare runs of one bender, sample time, episode length and "
            "preview"
        )
    before, after = _episodes(old), _episodes(new)
    cells_before = {tuple(c.get(k) for k in KEYS): c for c in aggregate(old["results"]["episodes"])}
    cells_after = {tuple(c.get(k) for k in KEYS): c for c in aggregate(new["results"]["episodes"])}
    lines = []
    seeds_old, seeds_new = _seed_set(old), _seed_set(new)
    if seeds_old != seeds_new:
        shared = len(seeds_old & seeds_new)
        lines += [
            f"The runs' seeds differ (old: {_describe(seeds_old)}; new: {_describe(seeds_new)}): "
            f"each cell is compared on the seeds both ran ({shared} pair(s) of noise and "
            "identification seed in all).",
            "",
        ]
    lines += [
        "| plant | controller | reference | old RMSE % | new RMSE % | change | seeds | "
        "beyond noise |",
        "|---|---|---|---|---|---|---|---|",
    ]
    marked = 0
    for key in [*before, *(k for k in after if k not in before)]:
        label = " | ".join(str(k) for k in key[:3])
        label += f" (draw {key[3]})" if key[3] is not None else ""
        if key not in after or key not in before:
            state = "removed" if key not in after else "added"
            lines.append(
                f"| {label} | {_value(cells_before.get(key))} | {_value(cells_after.get(key))} "
                f"| {state} | | |"
            )
            continue
        shared = sorted(set(before[key]) & set(after[key]))
        if shared:
            a = np.array([before[key][s]["rmse_percent"] for s in shared])
            b = np.array([after[key][s]["rmse_percent"] for s in shared])
            beyond = _paired_change(a, b)
            old_text, new_text = _mean(a), _mean(b)
            mean_a, mean_b = float(a.mean()), float(b.mean())
            seeds = f"{len(shared)} shared"
        else:
            ca, cb = cells_before[key], cells_after[key]
            beyond = different(ca, cb)
            old_text, new_text = _value(ca), _value(cb)
            mean_a, mean_b = ca["rmse_percent"], cb["rmse_percent"]
            seeds = "none shared"
        change = 100.0 * (mean_b / mean_a - 1.0) if mean_a else 0.0
        marked += beyond
        lines.append(
            f"| {label} | {old_text} | {new_text} | {change:+.1f} % | {seeds} | "
            f"{'**yes**' if beyond else ''} |"
        )
    return "\n".join(lines), marked


def _paired_change(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether RMSEs ``b`` differ from ``a`` on the same seeds beyond the noise."""
    if a.size == 1:
        return bool(abs(b[0] - a[0]) > TIE * min(a[0], b[0]))
    positive = bool(np.all(a > 0.0) and np.all(b > 0.0))
    d = np.log(b) - np.log(a) if positive else b - a
    half = ci95_half_width(d)
    return bool(abs(d.mean()) > (half or 0.0)) and bool(np.any(d != 0.0))


def _describe(seeds: set[tuple[int, int]]) -> str:
    noise = sorted({s[0] for s in seeds})
    models = sorted({s[1] for s in seeds})
    return f"noise seeds {_span(noise)}, identification seeds {_span(models)}"


def _span(values: list[int]) -> str:
    if len(values) > 2 and values == list(range(values[0], values[-1] + 1)):
        return f"{values[0]} .. {values[-1]}"
    return ", ".join(map(str, values))


def _mean(values: np.ndarray) -> str:
    ci = ci95_half_width(values)
    return f"{values.mean():.3f}" + (f" +- {ci:.3f}" if ci is not None else "")


def _value(cell: dict[str, Any] | None) -> str:
    if cell is None:
        return ""
    ci = cell.get("rmse_ci95_percent")
    return f"{cell['rmse_percent']:.3f}" + (f" +- {ci:.3f}" if ci is not None else "")


def compare_files(old_path: str | Path, new_path: str | Path) -> tuple[str, int]:
    """:func:`compare_runs` of two benchmark.json files."""
    return compare_runs(load_run(old_path), load_run(new_path))
