"""Evaluators of a trained NLS without torch: numpy, casadi (for NMPC), and back to torch.

The numpy arrays are the source of truth after training; :meth:`to_torch` builds a module
(importing torch lazily) only to continue training.
"""

from __future__ import annotations

from typing import Any

__all__ = ["ExportMixin"]


class ExportMixin:
    """Export methods of :class:`identification.nls.NLS` (needs ``feature_map``, ``_mlp``,
    ``_params``, ``n_features`` and ``n_state``)."""

    feature_map: Any
    _mlp: Any
    _params: dict
    n_features: int
    n_state: int

    def to_numpy(self) -> Any:
        """Pure-numpy evaluator ``features -> z`` (normalization folded into the weights)."""
        return self._mlp

    def to_casadi(self) -> Any:
        """casadi.Function ``nls(F) -> z`` (F: n_features x 1, V; z: equivalent V)."""
        import casadi

        f = casadi.SX.sym("F", self.n_features)
        return casadi.Function("nls", [f], [self._casadi_network(f)], ["F"], ["z"])

    def to_casadi_features(self) -> Any:
        """casadi.Function ``(u, state) -> (F, next_state)``: the feature state update.

        Play operators use the max/min form ``max(u - r, min(u + r, p))``.
        """
        import casadi

        u = casadi.SX.sym("u")
        s = casadi.SX.sym("state", self.n_state)
        f, new = self.feature_map.casadi_step(u, s)
        return casadi.Function(
            "nls_features", [u, s], [f, new], ["u", "state"], ["F", "next_state"]
        )

    def to_casadi_step(self) -> Any:
        """casadi.Function ``(u, state) -> (z, next_state)``: one NLS step for NMPC."""
        import casadi

        u = casadi.SX.sym("u")
        s = casadi.SX.sym("state", self.n_state)
        f, new = self.feature_map.casadi_step(u, s)
        return casadi.Function(
            "nls_step", [u, s], [self._casadi_network(f), new], ["u", "state"], ["z", "next_state"]
        )

    def _casadi_network(self, f: Any) -> Any:
        import casadi

        h = f
        for w, b in zip(self._mlp.weights, self._mlp.biases, strict=True):
            h = casadi.tanh(casadi.mtimes(casadi.DM(w), h) + casadi.DM(b))
        return (
            casadi.dot(casadi.DM(self._mlp.out_weight), h)
            + casadi.dot(casadi.DM(self._mlp.skip_weight), f)
            + self._mlp.out_bias
        )

    def to_torch(self) -> Any:
        """torch.nn.Module ``F (T, n_f) -> z (T,)`` in float64 with this network's weights."""
        from identification.nls.torch_module import TorchNLS

        return TorchNLS.from_params(self._params)
