"""The own-loop example: a registry controller against two hardware functions at a fixed rate."""

from __future__ import annotations

import time

import numpy as np

from examples.own_loop import SimulatedBench, main, run_loop, sine_reference


def test_the_example_runs_a_registry_controller_in_real_time(capsys):
    assert main(["--controller", "pid-ff", "--seconds", "0.2"]) == 0
    out = capsys.readouterr().out
    assert "pid-ff on the PL140 at 1000 Hz, 200 steps" in out and "deadline misses" in out


def test_the_loop_tracks_and_counts_deadline_misses_as_the_benchmark_does():
    """A controller slower than dt misses every deadline; the loop still writes every voltage
    and the measured deflection follows the writes."""

    class Slow:
        def reset(self, observation):
            self.first = observation

        def act(self, observation):
            time.sleep(2e-3)
            return np.array([5.0], dtype=np.float32)

    bench = SimulatedBench(seed=0, noise_bound=0.0)
    reference = sine_reference(1000.0, 1e-3, 21)
    result = run_loop(
        Slow(),
        bench.read_deflection_um,
        bench.write_voltage,
        reference,
        dt=1e-3,
        preview=3,
        stroke_um=1000.0,
        u_max=30.0,
    )
    assert result["steps"] == 20 and result["deadline_misses"] == 20
    assert result["late_ticks"] >= 19
    np.testing.assert_array_equal(result["voltage_V"], np.full(20, 5.0))
    assert result["measured_um"][-1] > 0.0  # +5 V bends the PL140 up
