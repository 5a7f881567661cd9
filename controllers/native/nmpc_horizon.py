"""The NMPC's horizon model: hidden signal z along a voltage plan and its Jacobian dz/du.

Along a plan ``u = (u_t .. u_t+N-1)`` (V) from the memory state ``s_t`` the nonlinearity gives
``z = (z_t .. z_t+N-1)`` (equivalent V); the real-time iteration needs z and the lower
triangular Jacobian ``J[k, j] = dz_t+k / du_t+j``. Three ways to get them:

``StructuredHorizon`` (identified NLS only)
    The memory state never depends on the network output, so the features ``F_k`` and their
    sensitivities ``dF_k/du_j`` come from the feature recursion alone (a small casadi graph,
    unrolled over the horizon and differentiated by casadi), and the network runs over the
    whole horizon as a batch of matrix products with its input gradient by hand-written
    back-propagation: ``dz_k/du_j = grad_F NLS(F_k) . dF_k/du_j``. The feature part is
    generated as C, compiled with the machine's compiler and called through ctypes; without a
    working compiler the same casadi Function runs in casadi's virtual machine. The NMPC
    defers that build to the first use (``defer``): its compiled iteration
    (:mod:`controllers.native.nmpc_step`) computes the features without it.
``GenericHorizon`` (any nonlinearity with ``casadi_step``)
    casadi's Jacobian of the unrolled horizon ``(u, s_t) -> z``: simple and general, but it
    differentiates the network N times over.

Why the fast path is the feature recursion in generated C called through ctypes, with the
network in numpy: generated C of the whole structured step is slower than numpy, because
casadi expands the network's dense matrix products into scalar code, while numpy runs them as
a few batched BLAS calls (all below OpenBLAS's threading threshold, so they stay
single-threaded without a thread limit); and calling the generated recursion through
``casadi.external`` costs more in converting its DM outputs to numpy than the recursion
itself. Every path's cost, measured once on a 3 x 32 network, is in
``benchmarks/results/design_measurements.md``; the NMPC step's is regenerated in
``benchmarks/results/controller_latency.md``.

The compiled library is cached on disk (``$PIEZO_CACHE`` or ``~/.cache/piezo-testbed``), keyed
by the hash of the generated source, compiler and platform, so compilation happens once per
model and horizon (:mod:`controllers.native.codegen`, shared with the compiled NLS inverse).
Each horizon object keeps the record of its build in ``native``
(:class:`controllers.native.codegen.NativeBuild`): compiled, or casadi's virtual machine and
why.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from controllers.native.codegen import CASADI_VM, NativeBuild, as_numpy, compile_function

__all__ = [
    "GenericHorizon",
    "StructuredHorizon",
    "horizon_function",
]


def horizon_function(nonlinearity: Any, horizon: int) -> Any:
    """casadi.Function ``(u (N), s_t) -> z (N)``: the nonlinearity unrolled over the horizon."""
    import casadi

    step = nonlinearity.casadi_step()
    u = casadi.SX.sym("u", horizon)
    state0 = casadi.SX.sym("s", step.size1_in(1))
    state, zs = state0, []
    for k in range(horizon):
        z, state = step(u[k], state)
        zs.append(z)
    return casadi.Function("nmpc_horizon", [u, state0], [casadi.vertcat(*zs)], ["u", "s"], ["z"])


class StructuredHorizon:
    """z and dz/du of the identified NLS along a plan (see the module docstring).

    Parameters
    ----------
    nls : identification.nls.NLS
        Identified network with its memory feature map.
    horizon : int
        N (samples).
    compiled : bool
        Try generated C for the feature recursion (else casadi's virtual machine).
    defer : bool
        With ``compiled``, leave the compilation to :meth:`compile`: the NMPC's compiled
        iteration (:mod:`controllers.native.nmpc_step`) computes the features itself, and only
        its numpy path needs this recursion compiled. The generated C of an unrolled horizon
        with its Jacobian is large (about 12 s of the compiler's time for the default model,
        ``-O1``), so it is built only where it runs: by :meth:`compile`, or by the first
        :meth:`linearize` or :meth:`evaluate`.
    """

    def __init__(
        self, nls: Any, horizon: int, *, compiled: bool = True, defer: bool = False
    ) -> None:
        self._nls = nls
        self._function: Any = None
        self.horizon, self.n_features = horizon, nls.n_features
        self.compile_requested = compiled
        self.backend = "casadi virtual machine (compilation not requested)"
        self.native: list[NativeBuild] = []
        self._features = self._virtual_machine
        if compiled and defer:
            self.backend = (
                "deferred: generated C built on first use (an NMPC's compiled iteration "
                "computes the features without it)"
            )
            self._features = self._first_use
        elif compiled:
            self.compile()
        mlp = nls.to_numpy()
        self._w_t = [np.ascontiguousarray(w.T) for w in mlp.weights]
        self._w = list(mlp.weights)
        self._b = list(mlp.biases)
        self._out, self._skip, self._bias = mlp.out_weight, mlp.skip_weight, mlp.out_bias

    @property
    def function(self) -> Any:
        """casadi.Function ``(u (N), s_t) -> (F (n_f, N), dF (N, n_f N))``: the feature
        recursion unrolled over the horizon, and its sensitivities to the plan.

        Built on first use: the unrolled graph and its Jacobian are most of a deferred
        horizon's construction, and an NMPC whose compiled iteration computes the features
        (:mod:`controllers.native.nmpc_step`) never evaluates them."""
        if self._function is None:
            import casadi

            nls, horizon = self._nls, self.horizon
            fmap = nls.feature_map
            u = casadi.SX.sym("u", horizon)
            state0 = casadi.SX.sym("s", nls.n_state)
            state, columns = state0, []
            for k in range(horizon):
                f, state = fmap.casadi_step(u[k], state)
                columns.append(f)
            features = casadi.horzcat(*columns)  # (n_f, N)
            sens = casadi.densify(casadi.jacobian(casadi.vec(features), u)).T  # (N, n_f N)
            self._function = casadi.Function(
                "nmpc_features",
                [u, state0],
                [casadi.densify(features), sens],
                ["u", "s"],
                ["F", "dF"],
            )
        return self._function

    def compile(self) -> None:
        """Build the generated C of the feature recursion, if it was requested and is not built
        yet. A failure is recorded in :attr:`native` and the virtual machine runs (under
        ``PIEZO_NATIVE=require`` it raises, :mod:`controllers.native.codegen`)."""
        if not self.compile_requested or self.native:
            return
        compiled_fn, build = compile_function(self.function, fallback=CASADI_VM)
        self.backend, self.native = str(build), [build]
        self._features = compiled_fn or self._virtual_machine

    def _virtual_machine(self, u: np.ndarray, state: np.ndarray) -> list[np.ndarray]:
        return as_numpy(self.function(u, state))

    def _first_use(self, u: np.ndarray, state: np.ndarray) -> list[np.ndarray]:
        """A deferred horizon's first evaluation: build, then evaluate as built."""
        self.compile()
        return self._features(u, state)

    def linearize(self, u: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z (N,) (equivalent V) along ``u`` (N,) (V) from ``state``, and dz/du (N, N)."""
        features, sens = self._features(u, state)
        z, grad = self._network(features)
        n = self.horizon
        jac = np.matmul(grad[:, None, :], sens.reshape(n, self.n_features, n))
        return z, jac[:, 0, :]

    def evaluate(self, u: np.ndarray, state: np.ndarray) -> np.ndarray:
        """z (N,) along ``u`` from ``state`` (equivalent V)."""
        return self.linearize(u, state)[0]

    def _network(self, features: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Network output z (N,) and its gradient dz/dF (N, n_f) for a batch of features."""
        layers = []
        h = features
        for w_t, b in zip(self._w_t, self._b, strict=True):
            h = np.tanh(h @ w_t + b)
            layers.append(h)
        z = h @ self._out + features @ self._skip + self._bias
        g = self._out * (1.0 - h * h)
        for i in range(len(layers) - 1, 0, -1):
            g = (g @ self._w[i]) * (1.0 - layers[i - 1] ** 2)
        return z, g @ self._w[0] + self._skip


class GenericHorizon:
    """z and dz/du by casadi's Jacobian of the unrolled horizon, for any nonlinearity.

    Parameters
    ----------
    nonlinearity : InputNonlinearity
        Anything with ``casadi_step()``.
    horizon : int
        N (samples).
    compiled : bool
        Try generated C (else casadi's virtual machine).
    """

    def __init__(self, nonlinearity: Any, horizon: int, *, compiled: bool = True) -> None:
        import casadi

        unrolled = horizon_function(nonlinearity, horizon)
        u, state = unrolled.sx_in()
        z = unrolled(u, state)
        self.function = casadi.Function(
            "nmpc_generic",
            [u, state],
            [z, casadi.densify(casadi.jacobian(z, u))],
            ["u", "s"],
            ["z", "dzdu"],
        )
        compiled_fn, self.backend = None, "casadi virtual machine (compilation not requested)"
        self.native: list[NativeBuild] = []
        if compiled:
            compiled_fn, build = compile_function(self.function, fallback=CASADI_VM)
            self.backend, self.native = str(build), [build]
        self._call = compiled_fn or (lambda *a: as_numpy(self.function(*a)))

    def compile(self) -> None:
        """Nothing to do: the generated C, where requested, is built with the horizon (the
        interface :meth:`StructuredHorizon.compile` defers to)."""

    def linearize(self, u: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """z (N,) (equivalent V) along ``u`` (N,) (V) from ``state``, and dz/du (N, N)."""
        z, jac_t = self._call(u, state)  # (cols, rows) order: jac_t is J transposed
        return z.reshape(-1).copy(), jac_t.T.copy()

    def evaluate(self, u: np.ndarray, state: np.ndarray) -> np.ndarray:
        """z (N,) along ``u`` from ``state`` (equivalent V)."""
        return self.linearize(u, state)[0]
