"""Speed scripts: compute time of the env, the controllers, the inverse and RL training.

Each runs as a module from the project folder, prints its tables and writes them, with the
machine and the date, to ``benchmarks/results/``:

- :mod:`benchmarks.speed.env_speed`: env steps/s against CartPole-v1 in the same run;
- :mod:`benchmarks.speed.controller_latency`: compute time per step of every controller;
- :mod:`benchmarks.speed.inverse_speed`: the nonlinearity inverse a controller calls every step;
- :mod:`benchmarks.speed.step_overhead`: a closed-loop step's parts (a policy's and ``mpc``'s
  ``act``, the env step, the episode loop) against a CartPole-v1 step;
- :mod:`benchmarks.speed.rl_throughput`: PPO training throughput;
- :mod:`benchmarks.speed.identification_speed`: ``identify()`` in one process and with a helper;
- :mod:`benchmarks.speed.main_job`: the main commands' wall times as a user meets them, also in
  seconds of the reference machine (scaled by a CartPole-v1 step of the same run).
"""
