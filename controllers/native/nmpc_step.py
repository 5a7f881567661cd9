"""The NMPC's real-time iteration in compiled code: one C call per SQP iteration.

Each Gauss-Newton iteration of :meth:`controllers.nmpc.NonlinearMPC._solve_rti` runs, along
the plan ``u_bar`` from the memory state: the feature recursion and its sensitivities
(:class:`controllers.native.nmpc_horizon.StructuredHorizon`'s casadi Function), the network
over the horizon with its input gradient, the Jacobian ``dz/du``, the QP's Hessian
``w J_y'J_y + R`` and vector ``w J_y'(offset + Gamma z - J_y u_bar)`` with ``J_y = Gamma dz/du``,
and the unconstrained optimum with its bound and rate tests. Called one by one from numpy, the
operations' overhead is most of the step; here :func:`library`'s ``nmpc_iterate`` runs them all
on preallocated buffers. When the unconstrained optimum meets every bound (most steps on smooth
references) Python takes it; otherwise Python's QP path runs on the Hessian and vector computed
here (:meth:`~controllers.nmpc.NonlinearMPC._solve_qp`, which tries numpy's unconstrained
solve first and then the QP solver). ``nmpc_apply`` steps the memory with the applied volts
and gives their z (the nonlinearity's ``step``: the one-step feature map's casadi Function and
the same network code).

The translation unit is the generated C of the two casadi Functions and the hand-written step
below, compiled with :data:`controllers.native.step_kernels.FLAGS` (no fused multiply-adds).
The feature recursion is the same generated code as the horizon's compiled path, so the
features and sensitivities are bitwise those of the numpy path. What differs from numpy in
the last bits: every dot product here is summed left to right, where numpy's matrix products
(BLAS) may pair the terms differently and fuse multiply-adds; ``tanh`` is the C library's, not
numpy's; and the unconstrained optimum comes from a Cholesky factorisation of the (symmetric
positive definite) Hessian where numpy's ``solve`` takes an LU factorisation. The plan may
therefore differ from the numpy path's by about 1e-15 relative, and the float32 volts the
plant receives round alike except where such a difference straddles a float32 rounding
boundary (one float32 ulp, 2e-6 V at 30 V; the tests hold the closed loops to that).

The library is built once per machine and model through
:func:`controllers.native.codegen.compile_source` (cached, digest-verified, the
``PIEZO_NATIVE`` policy applies); without it the NMPC runs its iterations in numpy, and its
``describe()["native"]["nmpc_step"]`` record says why.
"""

from __future__ import annotations

import ctypes
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from controllers.native.codegen import NUMPY, NativeBuild, compile_source
from controllers.native.step_kernels import FLAGS

__all__ = ["ERROR", "INSIDE", "NEED_QP", "IterationKernel", "compile_kernel", "unavailable"]

INSIDE, NEED_QP, ERROR = range(3)
"""Return codes of ``nmpc_iterate`` (``nmpc_apply`` returns INSIDE or ERROR)."""

# Pointer table, integer dimensions and scalars: their indices (as the enums in STEP).
(
    P_U, P_MEMORY, P_OFFSET, P_GAMMA, P_RATE_HESSIAN, P_LOWER, P_UPPER, P_WEIGHTS, P_BIASES,
    P_OUT, P_SKIP, P_Z, P_JAC, P_HESSIAN, P_Q, P_U_NEW, P_LAYERS, P_G, P_G_NEXT, P_GRAD,
    P_JAC_Y, P_CONSTANT, P_FACTOR, P_FEAT_ARG, P_FEAT_RES, P_FEAT_IW, P_FEAT_W, P_FEATURES,
    P_SENS, P_STEP_ARG, P_STEP_RES, P_STEP_IW, P_STEP_W, P_STEP_F, P_STEP_STATE, P_DIMS,
    P_SIZES, P_SCALARS, P_COUNT,
) = range(39)  # fmt: skip
D_N, D_FEATURES, D_LAYERS, D_STATE, D_SHORTCUT, D_SLEW, D_COUNT = range(7)
(
    S_W, S_RATE_WEIGHT, S_U_PREV, S_SLEW_STEP, S_OUT_BIAS, S_STEP, S_U_APPLIED, S_Z_APPLIED,
    S_COUNT,
) = range(9)  # fmt: skip

STEP = r"""
/* Vectorise the row updates below (GCC's -O2 cost model leaves loops of unknown length
   scalar). Vectors compute each element with the same IEEE operations in the same order, so
   the results are those of the scalar loops. */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("tree-vectorize", "vect-cost-model=dynamic")
#endif
#include <stddef.h>
#include <stdint.h>
enum { P_U, P_MEMORY, P_OFFSET, P_GAMMA, P_RATE_HESSIAN, P_LOWER, P_UPPER, P_WEIGHTS, P_BIASES,
       P_OUT, P_SKIP, P_Z, P_JAC, P_HESSIAN, P_Q, P_U_NEW, P_LAYERS, P_G, P_G_NEXT, P_GRAD,
       P_JAC_Y, P_CONSTANT, P_FACTOR, P_FEAT_ARG, P_FEAT_RES, P_FEAT_IW, P_FEAT_W, P_FEATURES,
       P_SENS, P_STEP_ARG, P_STEP_RES, P_STEP_IW, P_STEP_W, P_STEP_F, P_STEP_STATE, P_DIMS,
       P_SIZES, P_SCALARS };
enum { D_N, D_FEATURES, D_LAYERS, D_STATE, D_SHORTCUT, D_SLEW };
enum { S_W, S_RATE_WEIGHT, S_U_PREV, S_SLEW_STEP, S_OUT_BIAS, S_STEP, S_U_APPLIED,
       S_Z_APPLIED };
enum { INSIDE, NEED_QP, ERROR };

#define D(p, i) (((const int64_t *)(p)[P_DIMS])[i])
#define S(p) ((double *)(p)[P_SCALARS])
#define F(p, i) ((double *)(p)[i])

/* The network on `rows` feature rows (row-major, n_f each): z, and with `grad` (not NULL)
   dz/dF (rows x n_f). StructuredHorizon._network's operations in its order: each hidden unit
   tanh(sum + bias), z = (h . out + F . skip) + bias, the gradient by back-propagation. */
static void network(void **p, const double *features, int64_t rows, double *z, double *grad)
{
    const int64_t n_f = D(p, D_FEATURES), n_layers = D(p, D_LAYERS);
    const int64_t *sizes = (const int64_t *)p[P_SIZES];
    const double *weights = F(p, P_WEIGHTS), *biases = F(p, P_BIASES);
    const double *out = F(p, P_OUT), *skip = F(p, P_SKIP), bias = S(p)[S_OUT_BIAS];
    double *layers = F(p, P_LAYERS);
    const double *h = features, *w = weights, *b = biases;
    double *next = layers;
    int64_t width = n_f;
    for (int64_t l = 0; l < n_layers; ++l) {
        const int64_t m = sizes[l + 1];
        for (int64_t k = 0; k < rows; ++k)
            for (int64_t a = 0; a < m; ++a) {
                double sum = 0.0;
                for (int64_t c = 0; c < width; ++c) sum += h[k * width + c] * w[a * width + c];
                next[k * m + a] = tanh(sum + b[a]);
            }
        h = next;
        next += rows * m;
        w += m * width;
        b += m;
        width = m;
    }
    for (int64_t k = 0; k < rows; ++k) {
        double hidden = 0.0, direct = 0.0;
        for (int64_t a = 0; a < width; ++a) hidden += h[k * width + a] * out[a];
        for (int64_t f = 0; f < n_f; ++f) direct += features[k * n_f + f] * skip[f];
        z[k] = hidden + direct + bias;
    }
    if (grad == NULL) return;
    double *g = F(p, P_G), *g_next = F(p, P_G_NEXT);
    for (int64_t k = 0; k < rows; ++k)
        for (int64_t a = 0; a < width; ++a) {
            const double v = h[k * width + a];
            g[k * width + a] = out[a] * (1.0 - v * v);
        }
    /* back through the hidden layers: layer l's weights (sizes[l+1] x sizes[l]) start at the
       sum of the earlier layers' sizes */
    for (int64_t l = n_layers - 1; l >= 0; --l) {
        int64_t offset = 0, layer_offset = 0;
        for (int64_t i = 0; i < l; ++i) {
            offset += sizes[i + 1] * sizes[i];
            layer_offset += rows * sizes[i + 1];
        }
        const double *wl = weights + offset;
        const int64_t m = sizes[l + 1], width_in = sizes[l];
        if (l == 0) {
            for (int64_t k = 0; k < rows; ++k)
                for (int64_t f = 0; f < n_f; ++f) {
                    double sum = 0.0;
                    for (int64_t a = 0; a < m; ++a) sum += g[k * m + a] * wl[a * n_f + f];
                    grad[k * n_f + f] = sum + skip[f];
                }
            return;
        }
        const double *below = layers + layer_offset - rows * width_in;
        for (int64_t k = 0; k < rows; ++k)
            for (int64_t c = 0; c < width_in; ++c) {
                double sum = 0.0;
                for (int64_t a = 0; a < m; ++a) sum += g[k * m + a] * wl[a * width_in + c];
                const double v = below[k * width_in + c];
                g_next[k * width_in + c] = sum * (1.0 - v * v);
            }
        double *t = g; g = g_next; g_next = t;
    }
}

/* One Gauss-Newton iteration along P_U from P_MEMORY (see the module docstring). */
int nmpc_iterate(void **p)
{
    const int64_t n = D(p, D_N), n_f = D(p, D_FEATURES);
    const double *sc = S(p);
    if (nmpc_features((const casadi_real **)p[P_FEAT_ARG], (casadi_real **)p[P_FEAT_RES],
                      p[P_FEAT_IW], p[P_FEAT_W], 0))
        return ERROR;
    const double *features = F(p, P_FEATURES), *sens = F(p, P_SENS);
    double *z = F(p, P_Z), *grad = F(p, P_GRAD), *jac = F(p, P_JAC);
    network(p, features, n, z, grad);
    /* Each sum below runs over its index in order, as a dot product would, but the loops
       update whole rows (j innermost, independent sums), so that the compiler may vectorise
       them without reordering any sum. dz/du and Gamma are lower triangular (causal: z_t+k
       and y_t+k+1 depend on no later voltage; Gamma checked at setup), and the terms with a
       structural zero factor are left out (adding them adds zeros). */
    /* dz_k/du_j = sum_f dz_k/dF_kf dF_kf/du_j (sensitivities: row (k n_f + f), column j) */
    for (int64_t k = 0; k < n; ++k) {
        double *restrict row = jac + k * n;
        for (int64_t j = 0; j < n; ++j) row[j] = 0.0;
        for (int64_t f = 0; f < n_f; ++f) {
            const double g = grad[k * n_f + f], *restrict s = sens + (k * n_f + f) * n;
            for (int64_t j = 0; j <= k; ++j) row[j] += g * s[j];
        }
    }
    const double *gamma = F(p, P_GAMMA), *u = F(p, P_U), *offset = F(p, P_OFFSET);
    double *jac_y = F(p, P_JAC_Y), *constant = F(p, P_CONSTANT);
    for (int64_t i = 0; i < n; ++i) {  /* J_y = Gamma dz/du */
        double *restrict row = jac_y + i * n;
        for (int64_t j = 0; j < n; ++j) row[j] = 0.0;
        for (int64_t k = 0; k <= i; ++k) {
            const double g = gamma[i * n + k], *restrict s = jac + k * n;
            for (int64_t j = 0; j <= k; ++j) row[j] += g * s[j];
        }
    }
    for (int64_t i = 0; i < n; ++i) {  /* offset + Gamma z - J_y u_bar */
        double gz = 0.0, ju = 0.0;
        for (int64_t k = 0; k <= i; ++k) gz += gamma[i * n + k] * z[k];
        for (int64_t j = 0; j <= i; ++j) ju += jac_y[i * n + j] * u[j];
        constant[i] = offset[i] + gz - ju;
    }
    double *hessian = F(p, P_HESSIAN), *q = F(p, P_Q);
    const double *rate = F(p, P_RATE_HESSIAN), w = sc[S_W];
    for (int64_t i = 0; i < n; ++i) {  /* w J_y' J_y + R: the lower triangle, row by row */
        double *restrict row = hessian + i * n;
        for (int64_t j = 0; j <= i; ++j) row[j] = 0.0;
        for (int64_t k = i; k < n; ++k) {
            const double a = jac_y[k * n + i], *restrict s = jac_y + k * n;
            for (int64_t j = 0; j <= i; ++j) row[j] += a * s[j];
        }
        for (int64_t j = 0; j <= i; ++j) row[j] = w * row[j] + rate[i * n + j];
    }
    for (int64_t i = 0; i < n; ++i)  /* and the upper one: J_y' J_y and R are symmetric */
        for (int64_t j = i + 1; j < n; ++j) hessian[i * n + j] = hessian[j * n + i];
    for (int64_t i = 0; i < n; ++i) q[i] = 0.0;  /* w J_y' constant */
    for (int64_t k = 0; k < n; ++k) {
        const double c = constant[k], *restrict s = jac_y + k * n;
        for (int64_t i = 0; i <= k; ++i) q[i] += s[i] * c;
    }
    for (int64_t i = 0; i < n; ++i) q[i] = w * q[i];
    q[0] -= sc[S_RATE_WEIGHT] * sc[S_U_PREV];
    if (!D(p, D_SHORTCUT)) return NEED_QP;
    /* the unconstrained optimum -P^-1 q by Cholesky (P = L L'); not positive definite: the QP
       path decides */
    double *l = F(p, P_FACTOR), *x = F(p, P_U_NEW);
    for (int64_t j = 0; j < n; ++j) {
        double d = hessian[j * n + j];
        for (int64_t k = 0; k < j; ++k) d -= l[j * n + k] * l[j * n + k];
        if (!(d > 0.0)) return NEED_QP;
        const double root = sqrt(d);
        l[j * n + j] = root;
        for (int64_t i = j + 1; i < n; ++i) {
            double s = hessian[i * n + j];
            for (int64_t k = 0; k < j; ++k) s -= l[i * n + k] * l[j * n + k];
            l[i * n + j] = s / root;
        }
    }
    for (int64_t i = 0; i < n; ++i) {  /* L y = -q */
        double s = -q[i];
        for (int64_t k = 0; k < i; ++k) s -= l[i * n + k] * x[k];
        x[i] = s / l[i * n + i];
    }
    for (int64_t i = n - 1; i >= 0; --i) {  /* L' x = y */
        double s = x[i];
        for (int64_t k = i + 1; k < n; ++k) s -= l[k * n + i] * x[k];
        x[i] = s / l[i * n + i];
    }
    const double *lower = F(p, P_LOWER), *upper = F(p, P_UPPER);
    double step = 0.0;
    for (int64_t i = 0; i < n; ++i) {
        if (!(x[i] >= lower[i] && x[i] <= upper[i])) return NEED_QP;
        if (D(p, D_SLEW) && i > 0 && !(fabs(x[i] - x[i - 1]) <= sc[S_SLEW_STEP])) return NEED_QP;
        const double moved = fabs(x[i] - u[i]);
        if (moved > step || moved != moved) step = moved;
    }
    S(p)[S_STEP] = step;
    return INSIDE;
}

/* The nonlinearity's step with the applied volts S_U_APPLIED: P_MEMORY updated in place,
   z in S_Z_APPLIED. */
int nmpc_apply(void **p)
{
    if (nmpc_memory_step((const casadi_real **)p[P_STEP_ARG], (casadi_real **)p[P_STEP_RES],
                         p[P_STEP_IW], p[P_STEP_W], 0))
        return ERROR;
    double z;
    network(p, F(p, P_STEP_F), 1, &z, NULL);
    double *memory = F(p, P_MEMORY);
    const double *state = F(p, P_STEP_STATE);
    for (int64_t i = 0; i < D(p, D_STATE); ++i) memory[i] = state[i];
    S(p)[S_Z_APPLIED] = z;
    return INSIDE;
}
"""


def memory_step_function(nls: Any) -> Any:
    """casadi.Function ``(u, s) -> (F, s_next)``: the one-step feature map."""
    import casadi

    u = casadi.SX.sym("u")
    state = casadi.SX.sym("s", nls.n_state)
    features, new = nls.feature_map.casadi_step(u, state)
    return casadi.Function(
        "nmpc_memory_step", [u, state], [features, new], ["u", "s"], ["F", "s_next"]
    )


def kernel_source(features: Any, memory_step: Any) -> str:
    """The translation unit: the generated C of the horizon's feature Function
    (``nmpc_features``) and the one-step feature map (``nmpc_memory_step``), and the step."""
    import casadi

    with tempfile.TemporaryDirectory() as folder:
        generator = casadi.CodeGenerator("nmpc_step.c", {"with_header": False})
        generator.add(features)
        generator.add(memory_step)
        generator.generate(f"{folder}/")
        generated = (Path(folder) / "nmpc_step.c").read_text(encoding="utf-8")
    return "\n".join((generated, STEP))


def compile_kernel(features: Any, memory_step: Any) -> tuple[ctypes.CDLL | None, NativeBuild]:
    """The library of :func:`kernel_source` (None and the record of why when there is none)."""
    return compile_source(
        "nmpc_step", kernel_source(features, memory_step), flags=FLAGS, cache="kernels"
    )


def unavailable(reason: str) -> NativeBuild:
    """The record of an NMPC whose iterations run in numpy, and why."""
    return NativeBuild("nmpc_step", NUMPY, reason)


class IterationKernel:
    """The compiled iteration bound to one controller's arrays (module docstring).

    Parameters
    ----------
    library : ctypes.CDLL
        The library of :func:`kernel_source`.
    features, memory_step : casadi.Function
        The Functions it was generated from (for their work sizes).
    network : identification.nls.network.NumpyMLP-like
        ``weights``, ``biases``, ``out_weight``, ``skip_weight``, ``out_bias`` (the NLS's
        ``to_numpy()``).
    gamma, rate_hessian : numpy.ndarray
        The prediction matrix Gamma (N, N) and the rate penalty's Hessian R (N, N).
    lower, upper : numpy.ndarray
        The controller's bound arrays (N,), read at each call.
    tracking_weight, rate_weight : float
        w and lambda of the cost.
    slew_step : float or None
        S dt (V), None without a slew limit.
    shortcut : bool
        Try the unconstrained optimum.

    Attributes
    ----------
    u, memory, offset : numpy.ndarray
        Inputs the caller writes: the plan u_bar (N,), the memory state, the offset (N,).
    z, jac, hessian, q, u_new : numpy.ndarray
        Outputs: z (N,), dz/du (N, N), the QP's Hessian (N, N) and vector (N,), and the
        unconstrained optimum (N,) when the call returned :data:`INSIDE`.
    scalars : numpy.ndarray
        w, lambda, u_t-1 (written by the caller), S dt, the network's output bias, the
        largest move of the iteration (V), the applied volts (written by the caller) and
        their z.
    calls : int
        Compiled calls made (iterations and applies), for tests of the fusion.
    """

    def __init__(
        self,
        library: ctypes.CDLL,
        features: Any,
        memory_step: Any,
        network: Any,
        gamma: np.ndarray,
        rate_hessian: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        *,
        tracking_weight: float,
        rate_weight: float,
        slew_step: float | None,
        shortcut: bool,
    ) -> None:
        n = gamma.shape[0]
        n_f = features.size1_out(0)
        n_state = features.numel_in(1)
        if gamma.shape != (n, n) or rate_hessian.shape != (n, n) or lower.shape != (n,):
            raise ValueError(f"Gamma, R and the bounds must be ({n}, {n}) and ({n},)")
        if features.numel_in(0) != n or network.skip_weight.size != n_f:
            raise ValueError("the feature Function's sizes do not match the horizon's")
        if np.any(np.triu(gamma, 1) != 0.0):
            raise ValueError("Gamma must be lower triangular (a causal prediction)")
        if np.any(rate_hessian != rate_hessian.T):
            raise ValueError("the rate penalty's Hessian R must be symmetric")
        self.table = np.zeros(P_COUNT, dtype=np.uint64)
        self._keep: list[Any] = []
        sizes = [n_f, *(b.size for b in network.biases)]
        widths = sum(sizes[1:])
        self.dims = np.array(
            [n, n_f, len(network.biases), n_state, int(shortcut), int(slew_step is not None)],
            dtype=np.int64,
        )
        self.sizes = np.array(sizes, dtype=np.int64)
        self.scalars = np.zeros(S_COUNT)
        self.scalars[[S_W, S_RATE_WEIGHT, S_SLEW_STEP, S_OUT_BIAS]] = (
            tracking_weight,
            rate_weight,
            0.0 if slew_step is None else slew_step,
            float(network.out_bias),
        )
        self.u, self.memory, self.offset = np.zeros(n), np.zeros(n_state), np.zeros(n)
        self.z, self.jac = np.zeros(n), np.zeros((n, n))
        self.hessian, self.q, self.u_new = np.zeros((n, n)), np.zeros(n), np.zeros(n)
        own = {
            P_U: self.u,
            P_MEMORY: self.memory,
            P_OFFSET: self.offset,
            P_GAMMA: np.ascontiguousarray(gamma, dtype=np.float64),
            P_RATE_HESSIAN: np.ascontiguousarray(rate_hessian, dtype=np.float64),
            P_LOWER: lower,
            P_UPPER: upper,
            P_WEIGHTS: np.concatenate([np.ravel(w) for w in network.weights]),
            P_BIASES: np.concatenate([np.ravel(b) for b in network.biases]),
            P_OUT: np.ascontiguousarray(network.out_weight, dtype=np.float64).ravel(),
            P_SKIP: np.ascontiguousarray(network.skip_weight, dtype=np.float64).ravel(),
            P_Z: self.z,
            P_JAC: self.jac,
            P_HESSIAN: self.hessian,
            P_Q: self.q,
            P_U_NEW: self.u_new,
            P_LAYERS: np.zeros(n * widths),
            P_G: np.zeros(n * max(sizes)),
            P_G_NEXT: np.zeros(n * max(sizes)),
            P_GRAD: np.zeros(n * n_f),
            P_JAC_Y: np.zeros((n, n)),
            P_CONSTANT: np.zeros(n),
            P_FACTOR: np.zeros((n, n)),
            P_DIMS: self.dims,
            P_SIZES: self.sizes,
            P_SCALARS: self.scalars,
        }
        for index, buffer in own.items():
            self._point(index, buffer)
        feature_out = self._casadi(
            features, (P_FEAT_ARG, P_FEAT_RES, P_FEAT_IW, P_FEAT_W), [self.u, self.memory]
        )
        self._point(P_FEATURES, feature_out[0])
        self._point(P_SENS, feature_out[1])
        self._u_applied = self.scalars[S_U_APPLIED : S_U_APPLIED + 1]  # a view: C reads it
        step_out = self._casadi(
            memory_step,
            (P_STEP_ARG, P_STEP_RES, P_STEP_IW, P_STEP_W),
            [self._u_applied, self.memory],
        )
        self._point(P_STEP_F, step_out[0])
        self._point(P_STEP_STATE, step_out[1])
        if feature_out[1].size != n * n_f * n or step_out[1].size != n_state:
            raise ValueError("the generated Functions' outputs do not match the horizon's sizes")
        pointer = self.table.ctypes.data
        functions = {}
        for name in ("nmpc_iterate", "nmpc_apply"):
            function = getattr(library, name)
            function.argtypes, function.restype = [ctypes.c_void_p], ctypes.c_int
            functions[name] = function
        self._library = library
        self._iterate = lambda: functions["nmpc_iterate"](pointer)
        self._apply = lambda: functions["nmpc_apply"](pointer)
        self.calls = 0

    def iterate(self) -> int:
        """One iteration along :attr:`u` from :attr:`memory` (:data:`INSIDE`,
        :data:`NEED_QP`; RuntimeError when the generated code reports an error)."""
        self.calls += 1
        code = self._iterate()
        if code == ERROR:
            raise RuntimeError("the compiled NMPC iteration's feature function failed")
        return code

    def apply(self, u: float) -> float:
        """Step :attr:`memory` with the applied volts ``u``; their z (equivalent V)."""
        self.calls += 1
        self.scalars[S_U_APPLIED] = u
        if self._apply() == ERROR:
            raise RuntimeError("the compiled NMPC memory step's feature function failed")
        return float(self.scalars[S_Z_APPLIED])

    def _point(self, index: int, buffer: np.ndarray) -> None:
        if not (buffer.flags.c_contiguous and buffer.dtype in (np.float64, np.int64)):
            raise ValueError(f"table entry {index}: needs a C-contiguous float64 or int64 array")
        self.table[index] = buffer.ctypes.data
        self._keep.append(buffer)

    def _casadi(
        self, function: Any, slots: tuple[int, int, int, int], inputs: list[np.ndarray]
    ) -> list[np.ndarray]:
        """Argument, result and work arrays of a generated Function, its inputs pointing at
        ``inputs``; returns its output buffers (dense, casadi's column-major order)."""
        for i, buffer in enumerate(inputs):
            if buffer.size != function.numel_in(i):
                raise ValueError(f"{function.name()}: input {i} needs {function.numel_in(i)}")
        outputs = [np.zeros(function.numel_out(i)) for i in range(function.n_out())]
        pointer = ctypes.c_void_p
        arg = (pointer * max(function.sz_arg(), 1))(*[b.ctypes.data for b in inputs])
        res = (pointer * max(function.sz_res(), 1))(*[b.ctypes.data for b in outputs])
        iw = np.zeros(max(function.sz_iw(), 1), dtype=np.int64)
        w = np.zeros(max(function.sz_w(), 1))
        for slot, address in zip(
            slots,
            (ctypes.addressof(arg), ctypes.addressof(res), iw.ctypes.data, w.ctypes.data),
            strict=True,
        ):
            self.table[slot] = address
        self._keep += [inputs, outputs, arg, res, iw, w]
        return outputs
