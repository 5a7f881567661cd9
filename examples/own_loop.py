"""Any registry controller in your own loop: two functions to the hardware, a fixed rate.

On a bench, a controller of :mod:`controllers` needs two functions of yours,

- ``read_deflection_um() -> float``: the sensor's tip deflection now (um), and
- ``write_voltage(v)``: put ``v`` volts (around the amplifier's bias) on the bender, held
  until the next write,

and :func:`run_loop` calls them once per sample: read y_t, build the observation the controller
sees in the benchmark (``[y_t, r_t, r_t+1 .. r_t+P]``, um), time ``act``, write u_t, wait for
the next tick. The compute time of each ``act`` is measured as the benchmark measures it
(:func:`controllers.episode.run_episode`) and a step whose compute time exceeds dt is a
deadline miss (:func:`controllers.metrics.tracking_metrics`), so the figures compare with the
benchmark's; BLAS runs on one thread, as in the benchmark (small dense products stall on
several). The loop also counts late ticks: steps that began more than dt after their tick
(the step before, reading and writing included, overran); the schedule then restarts from
that moment rather than rushing the missed samples.

Here the simulated bender stands in for the hardware (:class:`SimulatedBench`); replace its two
methods with your data-acquisition calls. The controller is built for the task of an env that
describes the bench (bender, dt, preview; never stepped), on an identified model: one from
``piezo identify --records`` on your bench's records. Run it from the project folder::

    python -m examples.own_loop --controller mpc --model docs/identify/model --seconds 2
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np

import controllers
from controllers.metrics import tracking_metrics

__all__ = ["SimulatedBench", "run_loop", "sine_reference"]


class SimulatedBench:
    """The stand-in for a bench: the simulated bender behind the two hardware functions.

    Parameters
    ----------
    seed : int
        Seed of the sensor noise.
    **env_kwargs
        ``PiezoBender-v0`` options of the plant (bender, dt, hysteresis, noise_bound, ...).
    """

    def __init__(self, *, seed: int = 0, **env_kwargs: Any) -> None:
        self.env = gym.make(
            "piezo_env:PiezoBender-v0", reference=None, max_episode_steps=-1, **env_kwargs
        )
        observation, _ = self.env.reset(seed=seed)
        self._measured = float(observation[0])

    def read_deflection_um(self) -> float:
        """The measured tip deflection now (um)."""
        return self._measured

    def write_voltage(self, volts: float) -> None:
        """Apply ``volts`` (V) for one sample; the sensor then reads the deflection after it."""
        observation, *_ = self.env.step(np.array([volts], dtype=np.float32))
        self._measured = float(observation[0])


def sine_reference(
    stroke_um: float, dt: float, steps: int, *, frequency_hz: float = 10.0, fraction: float = 0.3
) -> np.ndarray:
    """A sine of ``fraction`` of the one-sided stroke at ``frequency_hz`` (um per sample)."""
    return fraction * stroke_um * np.sin(2.0 * np.pi * frequency_hz * dt * np.arange(steps))


def run_loop(
    controller: Any,
    read_deflection_um: Callable[[], float],
    write_voltage: Callable[[float], None],
    reference_um: np.ndarray,
    *,
    dt: float,
    preview: int,
    stroke_um: float,
    u_max: float,
    realtime: bool = True,
    clock: Callable[[], float] = time.perf_counter,
) -> dict[str, Any]:
    """Run ``controller`` at a fixed rate against the two hardware functions.

    Parameters
    ----------
    controller : object
        A controller of :func:`controllers.make` (or any object of the protocol).
    read_deflection_um, write_voltage : callable
        The hardware: the measured deflection now (um), and the voltage to apply (V).
    reference_um : numpy.ndarray
        The reference, one sample per step (um); ``len - 1`` steps are run (a_t is scored
        against r_t+1), the preview holding its last sample at the end.
    dt : float
        Sample time (s): the loop's period.
    preview : int
        Future reference samples in the observation after r_t (the task's).
    stroke_um : float
        One-sided stroke (um) the percentages refer to.
    u_max : float
        Drive limit (V): a voltage at it counts as saturated.
    realtime : bool
        Wait for each tick (a bench); False runs as fast as it can (a simulation check).
    clock : callable
        Monotonic time (s).

    Returns
    -------
    dict
        :func:`controllers.metrics.tracking_metrics` of the run on the measured deflection
        (with ``deadline_misses``: steps whose ``act`` took longer than dt) and ``late_ticks``
        (steps that began after their tick), ``measured_um`` and ``voltage_V``.
    """
    steps = len(reference_um) - 1
    padded = np.r_[reference_um, np.full(preview, reference_um[-1])]
    measured, voltage, compute = np.empty(steps), np.empty(steps), np.empty(steps)
    late = 0
    y = read_deflection_um()
    controller.reset(np.r_[y, padded[: preview + 1]].astype(np.float32))
    tick = clock()
    for t in range(steps):
        if realtime:
            now = clock()
            if now > tick + dt:  # the last step overran its period: restart the schedule now
                late, tick = late + 1, now
            while (wait := tick - clock()) > 0:
                if wait > 1e-3:  # sleep coarsely, then spin the last half millisecond
                    time.sleep(wait - 5e-4)
        tick += dt
        observation = np.r_[y, padded[t : t + preview + 1]].astype(np.float32)
        begin = clock()
        action = controller.act(observation)
        compute[t] = clock() - begin
        voltage[t] = float(action[0])
        write_voltage(voltage[t])
        y = read_deflection_um()
        measured[t] = y
    metrics = tracking_metrics(
        deflection_um=measured,
        reference_um=reference_um[1:],
        voltage_v=voltage,
        saturated=np.abs(voltage) >= u_max * (1 - 1e-6),
        compute_s=compute,
        stroke_um=stroke_um,
        dt=dt,
    )
    return {**metrics, "late_ticks": late, "measured_um": measured, "voltage_V": voltage}


def main(argv: list[str] | None = None) -> int:
    """Run a registry controller against the simulated bench at its rate; print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--controller", default="mpc", help="a name of controllers.CONTROLLERS")
    parser.add_argument(
        "--model", default="docs/identify/model", help="identified model folder, or 'plant'"
    )
    parser.add_argument("--bender", default="PL140")
    parser.add_argument("--seconds", type=float, default=2.0)
    parser.add_argument("--frequency", type=float, default=10.0, help="reference sine, Hz")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-realtime", action="store_true", help="do not wait for the ticks")
    args = parser.parse_args(argv)

    # The task of the bench: bender, sample time, drive range and preview (never stepped).
    task_env = gym.make("piezo_env:PiezoBender-v0", bender=args.bender, preview=20)
    base = task_env.unwrapped
    dt, stroke = float(base.task.model.dt), float(base.task.stroke_um)
    controller = controllers.make(args.controller, args.model, task_env)
    bench = SimulatedBench(seed=args.seed, bender=args.bender)
    steps = round(args.seconds / dt) + 1
    reference = sine_reference(stroke, dt, steps, frequency_hz=args.frequency)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        result = run_loop(
            controller,
            bench.read_deflection_um,
            bench.write_voltage,
            reference,
            dt=dt,
            preview=int(base.observation_space.shape[0]) - 2,
            stroke_um=stroke,
            u_max=float(task_env.action_space.high[0]),
            realtime=not args.no_realtime,
        )
    print(
        f"{args.controller} on the {args.bender} at {1 / dt:g} Hz, {steps - 1} steps: RMSE "
        f"{result['rmse_percent']:.3f} % of the full stroke (measured deflection), compute "
        f"median {result['compute_median_us']:.0f} us, p99 {result['compute_p99_us']:.0f} us, "
        f"deadline misses {result['deadline_misses']}, late ticks {result['late_ticks']}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
