"""Open-loop runs of the environment with a chosen input signal, written as CSV and PNG.

This is the logic behind ``piezo simulate``: the env is driven through its Gymnasium interface
exactly as a user would, and the record holds the applied and effective voltage, the true and
measured deflection and the charge.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from piezo_env.checks import require_number
from piezo_env.signals import SIGNAL_DEFAULTS, make_signal

__all__ = ["OpenLoopRecord", "plot_record", "run_open_loop", "write_csv"]


@dataclass(frozen=True)
class OpenLoopRecord:
    """One open-loop run; row i is the state after applying voltage[i].

    Attributes
    ----------
    time : ndarray
        s.
    voltage, effective_voltage : ndarray
        Applied (after clipping) and effective (after hysteresis) voltage, V.
    deflection_um, measured_um : ndarray
        True and measured tip deflection, um.
    charge_uc : ndarray
        Drive charge, uC.
    """

    time: np.ndarray
    voltage: np.ndarray
    effective_voltage: np.ndarray
    deflection_um: np.ndarray
    measured_um: np.ndarray
    charge_uc: np.ndarray


def run_open_loop(
    signal: str = "sine",
    *,
    amplitude: float = 30.0,
    duration: float = 3.0,
    seed: int = 0,
    signal_params: dict | None = None,
    **env_kwargs: object,
) -> OpenLoopRecord:
    """Drive PiezoBender-v0 with a named signal (see piezo_env.signals) and record it.

    Parameters
    ----------
    signal : str
        Signal name (``"step"``, ``"sine"``, ``"triangle"``, ``"random"``, ...).
    amplitude : float
        Signal amplitude (V).
    duration : float
        Length of the run (s).
    seed : int
        Seed of the env and of random signals.
    signal_params : dict, optional
        Overrides of the signal's own parameters (e.g. ``{"frequency": 5.0}``).
    **env_kwargs
        Keyword arguments of PiezoBender-v0 (``bender``, ``hysteresis``, ``noise_bound``, ...).
    """
    if signal not in SIGNAL_DEFAULTS:
        raise ValueError(f"unknown signal {signal!r}; choose one of {sorted(SIGNAL_DEFAULTS)}")
    require_number("duration (s)", duration, low=0.0, low_open=True)
    env_kwargs.setdefault("reference", None)
    env = gym.make("piezo_env:PiezoBender-v0", max_episode_steps=-1, **env_kwargs)
    dt = env.unwrapped.model.dt
    n = max(1, round(duration / dt))
    params = {**SIGNAL_DEFAULTS[signal], **(signal_params or {}), "amplitude": amplitude}
    u = make_signal(signal, n, dt=dt, rng=np.random.default_rng(seed), **params)
    env.reset(seed=seed)
    rows = np.empty((n, 5))
    for i, v in enumerate(u):
        obs, _, _, _, info = env.step(np.array([v], dtype=np.float32))
        rows[i] = (
            info["voltage_V"],
            info["effective_voltage_V"],
            info["deflection_um"],
            obs[0],
            info["charge_uC"],
        )
    env.close()
    return OpenLoopRecord(np.arange(1, n + 1) * dt, *rows.T)


def write_csv(record: OpenLoopRecord, path: str | Path) -> Path:
    """Write the record as CSV with a unit-bearing header."""
    path = Path(path)
    header = [
        "time_s",
        "voltage_V",
        "effective_voltage_V",
        "deflection_um",
        "measured_um",
        "charge_uC",
    ]
    data = np.column_stack(
        [
            record.time,
            record.voltage,
            record.effective_voltage,
            record.deflection_um,
            record.measured_um,
            record.charge_uc,
        ]
    )
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        writer.writerows([f"{v:.9g}" for v in row] for row in data)
    return path


def plot_record(record: OpenLoopRecord, path: str | Path, title: str = "") -> Path:
    """Input and deflection over time, and the hysteresis loop (deflection vs voltage), as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig = plt.figure(figsize=(10, 5.5), dpi=110)
    grid = fig.add_gridspec(2, 2, width_ratios=[1.6, 1])
    ax_u = fig.add_subplot(grid[0, 0])
    ax_y = fig.add_subplot(grid[1, 0], sharex=ax_u)
    ax_loop = fig.add_subplot(grid[:, 1])
    ax_u.plot(record.time, record.voltage, label="applied u")
    ax_u.plot(record.time, record.effective_voltage, "--", label="effective u_eff")
    ax_u.set_ylabel("voltage (V)")
    ax_u.legend(loc="upper right", fontsize=8)
    ax_y.plot(record.time, record.measured_um, color="0.6", lw=0.8, label="measured")
    ax_y.plot(record.time, record.deflection_um, color="tab:red", lw=1.2, label="true")
    ax_y.set_xlabel("time (s)")
    ax_y.set_ylabel("tip deflection (um)")
    ax_y.legend(loc="upper right", fontsize=8)
    ax_loop.plot(record.voltage, record.deflection_um, color="tab:red", lw=1)
    ax_loop.set_xlabel("voltage (V)")
    ax_loop.set_ylabel("tip deflection (um)")
    ax_loop.set_title("hysteresis loop")
    ax_loop.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path
