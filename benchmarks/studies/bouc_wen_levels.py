"""Bouc-Wen plants whose loop shape falls between the features' levels: identified as well as
one on them?

The ``bouc-wen`` memory features (:class:`identification.features.BoucWenFeatures`) are
``IdentificationConfig.n_bouc_wen`` (16) normalized Bouc-Wen operators whose saturation levels
are fixed on a geometric grid from 0.1 to 2 half-spans of the drive range
(:func:`identification.features.default_bouc_wen_levels`: 3 to 60 V on the PL140, 22 % apart);
the network weighs them. Play radii are learned in step e', because a sharp-cornered
Prandtl-Ishlinskii loop needs its radii exactly
(``rate_aware_identification.md``). This study asks whether Bouc-Wen levels need the same.

The PL140's Bouc-Wen hysteresis has beta = gamma = b, whose loop is the features' operator of
level 1 / (2 b) (21.46 V by default). Each plant here sets b for one level: on the grid
(22.10 V), between two grid levels (at their geometric middle: 11.0, 20.0, 44.5 V), and beyond
its ends (2.5 and 75 V), at the default sensor noise (uniform within +-1 um) and at a tenth of
it. Each is identified with the default configuration, seed 0, and the report gives the
features chosen, the validation record's free-run fit and RMSE, and the model's own error,
``sqrt(RMSE^2 - sigma^2)`` with sigma = bound / sqrt(3) the noise's standard deviation (0 when
the RMSE is within the noise).

Writes ``benchmarks/results/bouc_wen_levels.md``. Run:
``python -m benchmarks.studies.bouc_wen_levels`` (about 4 minutes on 2 cores).
"""

from __future__ import annotations

import math

from benchmarks._common import header, markdown_table, write_result
from identification.features import default_bouc_wen_levels
from identification.pipeline import IdentificationConfig, identify
from piezo_env.hysteresis import BoucWen

BENDER = "PL140"
LEVELS_V = (2.5, 11.0, 20.0, 22.10, 44.5, 75.0)
"""Plant levels 1 / (2 b) (V): beyond the grid's ends, between grid levels, on one."""
NOISE_BOUNDS_UM = (1.0, 0.1)
"""Sensor noise bounds (um): the default, and a tenth of it."""


def _where(level: float, grid: list[float]) -> str:
    """"on the grid", "between a and b" or "beyond the grid" for a plant level."""
    if any(math.isclose(level, g, rel_tol=2e-3) for g in grid):
        return "on the grid"
    if level < grid[0] or level > grid[-1]:
        return "beyond the grid"
    above = min(g for g in grid if g > level)
    below = max(g for g in grid if g < level)
    return f"between {below:.2f} and {above:.2f}"


def main() -> None:
    """Identify every plant and write the report."""
    grid = None
    rows = []
    for bound in NOISE_BOUNDS_UM:
        sigma = bound / math.sqrt(3.0)
        for level in LEVELS_V:
            b = 0.5 / level
            env = {"bender": BENDER, "hysteresis": BoucWen(beta=b, gamma=b), "noise_bound": bound}
            result = identify(config=IdentificationConfig(seed=0, env_kwargs=env), jobs=2)
            if grid is None:
                u_max = result.report["environment"]["drive_range_V"]
                count = IdentificationConfig().n_bouc_wen
                grid = [float(g) for g in default_bouc_wen_levels(u_max, count)]
            fit = result.report["validation"]["hammerstein"]
            rmse = fit["rmse"]
            own = math.sqrt(max(rmse**2 - sigma**2, 0.0))
            rows.append(
                [
                    f"{bound:g}",
                    f"{level:.2f}",
                    _where(level, grid),
                    result.report["nls"]["features"],
                    f"{fit['fit_percent']:.3f}",
                    f"{rmse:.3f}",
                    f"{sigma:.3f}",
                    f"{own:.3f}",
                ]
            )
            print(" | ".join(rows[-1]), flush=True)
    lines = [
        *header("Bouc-Wen plants between the features' levels", __spec__.name),
        f"The {BENDER} with Bouc-Wen hysteresis of beta = gamma = 1 / (2 level), identified with "
        "the default configuration (seed 0). The features' 16 levels (V): "
        + ", ".join(f"{g:.2f}" for g in grid)
        + ". Fit and RMSE of the free run on the validation record; sigma is the sensor "
        "noise's standard deviation, and the model's own error is sqrt(RMSE^2 - sigma^2).",
        "",
        markdown_table(
            ["noise bound (um)", "plant level (V)", "where", "features", "fit %", "RMSE (um)",
             "sigma (um)", "model's own error (um)"],
            rows,
        ),
        "",
    ]
    write_result("bouc_wen_levels", lines)


if __name__ == "__main__":
    main()
