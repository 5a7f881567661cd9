"""Reinforcement-learning training: PPO (stable-baselines3) on the native vector env.

Training lives here, inference does not: a trained policy is plain files that
``controllers.make("policy", folder, env)`` runs in numpy without this package or its extra
(``pip install "piezo-testbed[rl]"``). See :mod:`piezo_rl.ppo`.
"""
