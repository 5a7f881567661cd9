"""The closed-loop benchmark harness and the speed scripts.

The harness (``piezo benchmark``) owns episodes' set-up, references, plants, metrics tables,
reports and figures; it knows a controller only through its protocol (``reset``, ``act``,
optional ``stats`` and ``describe``):

- :mod:`benchmarks.references`: the named reference signals every controller tracks.
- :mod:`benchmarks.plants`: the nominal and robustness plants (env keyword arguments).
- :mod:`benchmarks.runner`: :class:`~benchmarks.runner.BenchmarkConfig` and
  :func:`~benchmarks.runner.run_benchmark` (episode groups on the local pool or Ray).
- :mod:`benchmarks.cells`: episodes to table cells (means over noise seeds, 95 % intervals).
- :mod:`benchmarks.verdict`: the best controller per reference and what limits it.
- :mod:`benchmarks.reference_checks`: the project's own expectations of its default run.
- :mod:`benchmarks.descriptions`: the controllers' settings and tuned loops as tables.
- :mod:`benchmarks.report`: tables, JSON and the Markdown report.
- :mod:`benchmarks.compare`: what changed between two runs (``piezo compare``).
- :mod:`benchmarks.readme`: the numbers of README.md and docs/*.md, generated from the committed
  results.
- :mod:`benchmarks.figures`: the figures of a run.

The studies and speed scripts sit apart from the harness, each a module run from the project
folder that prints a table and writes it with the machine and the date to
``benchmarks/results/``: :mod:`benchmarks.studies` (what identification and the tolerance box
cost: ``python -m benchmarks.studies.identification_accuracy``, likewise
``identification_precision``, ``arx_estimation``, ``corners``) and :mod:`benchmarks.speed`
(compute times: ``python -m benchmarks.speed.env_speed``, likewise ``controller_latency``,
``inverse_speed``, ``rl_throughput``). ``python -m benchmarks.tracking`` runs the committed
benchmark and ``python -m benchmarks.tuning`` the tuning sweep.
"""
