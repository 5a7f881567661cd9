"""The NLS network as a torch module, built lazily (importing this module does not import torch).

:class:`TorchNLS` builds the module, and converts between it and the plain parameter arrays the
numpy network (:class:`identification.nls.network.NLS`) and the model files hold. Training
(:mod:`identification.nls.training`) and export (:mod:`identification.nls.export`) both use it.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["TorchNLS", "load_torch"]


def load_torch() -> Any:
    import torch

    return torch


class TorchNLS:
    """Builders of the torch module (lazy: importing this module does not import torch)."""

    @staticmethod
    def build(n_features: int, hidden: Sequence[int]) -> Any:
        torch = load_torch()
        nn = torch.nn

        class TorchNLS(nn.Module):
            """``z = z_m + z_s (w^T x + c + MLP(x))``, ``x = (F - m) / s``; float64."""

            def __init__(self) -> None:
                super().__init__()
                widths = [n_features, *hidden]
                self.layers = nn.ModuleList(
                    nn.Linear(a, b, dtype=torch.float64) for a, b in itertools.pairwise(widths)
                )
                self.out = nn.Linear(widths[-1], 1, dtype=torch.float64)
                self.skip = nn.Linear(n_features, 1, dtype=torch.float64)
                self.register_buffer("feature_mean", torch.zeros(n_features, dtype=torch.float64))
                self.register_buffer("feature_scale", torch.ones(n_features, dtype=torch.float64))
                self.register_buffer("z_mean", torch.zeros((), dtype=torch.float64))
                self.register_buffer("z_scale", torch.ones((), dtype=torch.float64))

            def normalized(self, x: Any) -> Any:
                h = x
                for layer in self.layers:
                    h = torch.tanh(layer(h))
                return (self.out(h) + self.skip(x)).squeeze(-1)

            def input_of(self, features: Any) -> Any:
                """``x = (F - m) / s``: the normalized input for the features ``F``."""
                return (features - self.feature_mean) / self.feature_scale

            def output_of(self, x: Any) -> Any:
                """``z`` for the normalized input ``x`` (:meth:`input_of`): features fixed over
                many evaluations are normalized once, with the same result as ``forward``."""
                return self.z_mean + self.z_scale * self.normalized(x)

            def forward(self, features: Any) -> Any:
                return self.output_of(self.input_of(features))

        return TorchNLS()

    @staticmethod
    def from_params(params: dict[str, np.ndarray]) -> Any:
        torch = load_torch()
        n_layers = sum(1 for k in params if k.startswith("layer") and k.endswith("_weight"))
        hidden = [params[f"layer{i}_weight"].shape[0] for i in range(n_layers)]
        module = TorchNLS.build(params["feature_mean"].size, hidden)
        state = {
            "feature_mean": params["feature_mean"],
            "feature_scale": params["feature_scale"],
            "z_mean": params["z_mean"],
            "z_scale": params["z_scale"],
            "out.weight": params["out_weight"][None, :],
            "out.bias": params["out_bias"].reshape(1),
            "skip.weight": params["skip_weight"][None, :],
            "skip.bias": params["skip_bias"].reshape(1),
        }
        for i in range(n_layers):
            state[f"layers.{i}.weight"] = params[f"layer{i}_weight"]
            state[f"layers.{i}.bias"] = params[f"layer{i}_bias"]
        module.load_state_dict({k: torch.from_numpy(np.array(v)) for k, v in state.items()})
        return module

    @staticmethod
    def to_params(module: Any) -> dict[str, np.ndarray]:
        sd = {k: v.detach().numpy().astype(np.float64) for k, v in module.state_dict().items()}
        params = {
            "feature_mean": sd["feature_mean"],
            "feature_scale": sd["feature_scale"],
            "z_mean": sd["z_mean"].reshape(()),
            "z_scale": sd["z_scale"].reshape(()),
            "out_weight": sd["out.weight"].reshape(-1),
            "out_bias": sd["out.bias"].reshape(()),
            "skip_weight": sd["skip.weight"].reshape(-1),
            "skip_bias": sd["skip.bias"].reshape(()),
        }
        for i in range(len(module.layers)):
            params[f"layer{i}_weight"] = sd[f"layers.{i}.weight"]
            params[f"layer{i}_bias"] = sd[f"layers.{i}.bias"]
        return params
