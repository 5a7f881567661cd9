"""One-off studies: what a design choice or the identification costs, measured once.

Each runs as a module from the project folder, prints its tables and writes them, with the
machine and the date, to ``benchmarks/results/``:

- :mod:`benchmarks.studies.identification_accuracy`: held-out fits of the Hammerstein model
  against a linear ARX and NARX networks;
- :mod:`benchmarks.studies.identification_precision`: how the identified model's precision
  shows in closed loop;
- :mod:`benchmarks.studies.arx_estimation`: accuracy and speed of the three ARX estimators;
- :mod:`benchmarks.studies.corners`: every controller on the corners of the datasheet's
  tolerance box;
- :mod:`benchmarks.studies.rate_aware_identification`: the default identification on plants
  with and without rate-dependent hysteresis, over identification seeds;
- :mod:`benchmarks.studies.bouc_wen_levels`: Bouc-Wen plants between the features' levels.
"""
