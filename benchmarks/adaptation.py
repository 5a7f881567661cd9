"""Adaptive MPC: which estimator and which candidates, measured on the benchmark's plants.

The evidence behind :class:`controllers.adaptive.AdaptiveMPCSettings`' defaults. Every variant
of ``mpc-adaptive`` (the full ARX re-estimation by the uniform-noise window posterior or by RLS
with forgetting, the three-number modal correction, both) runs on the same episodes as the
fixed-model ``mpc``: the PL140 model of the committed benchmark run (``docs/benchmark/model``),
seed 0, noise on, preview 20, 2 s, on the nominal plant and the robustness plants, references
at one frequency (the hard case for re-estimation: a single sine excites few directions) and
the multisine. RMSE over the second half of each episode (after adaptation), % of the full
stroke, and the per-sample and per-review costs of the estimators.

Run: ``python -m benchmarks.adaptation`` (a few minutes; ``--jobs 2`` runs two plants at a time).
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from benchmarks._common import header, markdown_table, write_result

MODEL_DIR = "docs/benchmark/model"
PLANTS_RUN = (
    "nominal",
    "stiffness+20%",
    "stiffness-20%",
    "damping-0.01",
    "damping-0.04",
    "prandtl-ishlinskii",
    "drift",
    "bench",
)
REFERENCES_RUN = ("sine-1Hz", "sine-10Hz", "sine-50Hz", "sine-100Hz", "multisine")
VARIANTS: dict[str, tuple[str, dict[str, Any]]] = {
    "mpc (fixed model)": ("mpc", {}),
    "adaptive: window posterior + modal (default)": ("mpc-adaptive", {}),
    "adaptive: RLS + modal": ("mpc-adaptive", {"estimator": "rls"}),
    "adaptive: window posterior only": ("mpc-adaptive", {"structure": "full"}),
    "adaptive: RLS only": ("mpc-adaptive", {"structure": "full", "estimator": "rls"}),
    "adaptive: modal only": ("mpc-adaptive", {"structure": "modal"}),
}


def run_plant(plant: str) -> dict[tuple[str, str], tuple[float, float, float]]:
    """(variant, reference) -> (whole RMSE %, second-half RMSE %, step median us) on ``plant``."""
    import gymnasium as gym
    from threadpoolctl import threadpool_limits

    import controllers
    from benchmarks.plants import PLANTS
    from benchmarks.references import make_reference

    def env_for(name: str, **extra: Any) -> Any:
        return gym.make(
            "piezo_env:PiezoBender-v0",
            preview=20,
            max_episode_steps=2000,
            **{**PLANTS[name]("PL140"), **extra},
        )

    env = env_for(plant)
    amplifier = env.unwrapped.config.amplifier
    nominal = env_for("nominal", **({"amplifier": amplifier} if amplifier else {}))
    out = {}
    with threadpool_limits(1):
        for label, (name, options) in VARIANTS.items():
            controller = controllers.make(name, MODEL_DIR, nominal, **options)
            for ref in REFERENCES_RUN:
                reference = make_reference(ref, 2021, dt=1e-3, seed=0)
                episode = controllers.run_episode(
                    env, controller, seed=0, reference=reference, stroke_um=1000.0
                )
                m = episode.metrics
                out[(label, ref)] = (
                    m["rmse_percent"],
                    m["rmse_second_half_percent"],
                    m["compute_median_us"],
                )
    return out


def _pair(cell: tuple[float, float, float]) -> str:
    return f"{cell[0]:.3f} / {cell[1]:.3f}"


def estimator_costs() -> list[list[str]]:
    """Per-sample update and per-estimate cost (us) of the two estimators, ARX(6, 6)."""
    from identification.hammerstein import HammersteinModel
    from identification.online import RecursiveLeastSquares, SlidingWindowBayes, regressor_scales

    arx = HammersteinModel.load(MODEL_DIR).arx
    rng = np.random.default_rng(0)
    z = rng.uniform(-30, 30, 3000)
    y = arx.simulate(z) + rng.uniform(-1, 1, 3000)
    rows = []
    for label, estimator, estimate in (
        (
            "RLS, forgetting 0.998",
            RecursiveLeastSquares(arx, regressor_scales(arx, 30.0)),
            "model",
        ),
        ("uniform-noise posterior, window 300", SlidingWindowBayes(6, 6, window=300), "estimate"),
    ):
        times = []
        for z_t, y_t in zip(z, y, strict=True):
            start = time.perf_counter()
            estimator.update(z_t, y_t)
            times.append(time.perf_counter() - start)
        fits = []
        for _ in range(20):
            start = time.perf_counter()
            getattr(estimator, estimate)()
            fits.append(time.perf_counter() - start)
        rows.append([label, f"{np.median(times) * 1e6:.1f}", f"{np.median(fits) * 1e6:.0f}"])
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.adaptation", description=__doc__)
    parser.add_argument("--jobs", type=int, default=1, help="plants run at a time")
    args = parser.parse_args(argv)
    from piezo_parallel.backends import run_tasks

    results = run_tasks(run_plant, [(p,) for p in PLANTS_RUN], jobs=args.jobs)
    lines = header("Adaptive MPC: estimators and candidates", "adaptation.py")
    lines += [
        "PL140 model of the committed benchmark run; seed 0, noise on, preview 20, 2000 steps. "
        "Each cell: RMSE over the whole episode / over its second half (after adaptation), % "
        "of the full stroke. The default (`mpc-adaptive`) proposes both the window "
        "posterior's estimate and the modal correction; the safeguard picks.",
        "",
    ]
    for plant, out in zip(PLANTS_RUN, results, strict=True):
        rows = [
            [label, *(_pair(out[(label, r)]) for r in REFERENCES_RUN)]
            for label in VARIANTS
        ]
        lines += [f"## {plant}", "", markdown_table(["variant", *REFERENCES_RUN], rows), ""]
    medians = {
        label: np.median([out[(label, r)][2] for out in results for r in REFERENCES_RUN])
        for label in VARIANTS
    }
    lines += [
        "## Cost",
        "",
        "Step median over every episode above (us, one BLAS thread; the review every 100 "
        "steps sits in the p99, not the median): "
        + ", ".join(f"{label} {value:.0f}" for label, value in medians.items())
        + ".",
        "",
        markdown_table(
            ["estimator", "update per sample (us, median)", "estimate (us, median)"],
            estimator_costs(),
        ),
        "",
    ]
    write_result("adaptation", lines)


if __name__ == "__main__":
    main()
