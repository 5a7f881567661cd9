"""The NMPC's real-time iteration in compiled code: one C call per step on smooth references.

Each Gauss-Newton iteration of :meth:`controllers.nmpc.NonlinearMPC._solve_rti` needs, along
the plan ``u_bar`` from the memory state: the features and their sensitivities ``dF_k/du_j``,
the network over the horizon with its input gradient, the Jacobian ``dz/du``, the QP's Hessian
``w J_y'J_y + R`` and vector ``w J_y'(offset + Gamma z - J_y u_bar)`` with ``J_y = Gamma dz/du``,
and the unconstrained optimum with its bound and rate tests. Called one by one from numpy, the
operations' overhead is most of the step; here ``nmpc_iterate`` runs them all on preallocated
buffers, and ``nmpc_rti`` runs the iterations (the same stops) as long as each unconstrained
optimum meets every bound (most steps on smooth references). An iteration whose optimum
does not goes back to Python's QP path, on the Hessian and vector computed here
(:meth:`~controllers.nmpc.NonlinearMPC._solve_qp`, which tries numpy's unconstrained solve
first, then the QP solver). ``nmpc_apply`` steps the memory with the applied volts and gives
their z (the nonlinearity's ``step``).

``nmpc_step`` is the whole step of :meth:`controllers.nmpc.NonlinearMPC._act` in one call: the
gain estimate's and the observer bank's updates (the estimator kernels of
:mod:`controllers.native.step_kernels`, in this translation unit), the observation over the
learned gain and clipped to the static reach, ``nmpc_prepare``, ``nmpc_rti`` and, when every
iteration stayed inside the bounds, ``nmpc_finish`` (the first move in the slew window rounded
to float32, ``nmpc_apply``, the estimators' time updates; its cost against the unfused step's:
``benchmarks/results/controller_latency.md``). Every operation is the Python step's on the
same operands, the rescaling of the bank's output estimates by a new gain included (summed
left to right on both paths), so the fused and the unfused steps give the same volts to the
bit (``tests/test_nmpc_speed.py``).

The sensitivities come by the chain rule through one step of the feature map: a casadi
Function (:func:`partials_function`) gives the step's features, next state and their partial
derivatives in the input and the state (the state ones sparse: for Bouc-Wen features, 2
nonzeros per row), generated as C; ``nmpc_iterate`` carries the state's tangents
``ds_k/du_j`` along the plan and contracts them with the network's gradient, so that
``dz_k/du_j = (dz/dF)' dF/ds ds_k-1/du_j`` (``dz/dF . dF/du`` on the diagonal). casadi's
Jacobian of the unrolled horizon (the numpy path's,
:class:`controllers.native.nmpc_horizon.StructuredHorizon`) computes the same products, but
through every branch of the step's expressions for each of the N directions, which made it
most of the numpy path's iteration. The Jacobian is lower triangular (causal) and the
prediction matrix Gamma too (checked at setup): the products skip their structural zeros.

The translation unit is the generated C of the step's Function and the hand-written step
below, compiled with :data:`controllers.native.step_kernels.FLAGS` (no fused multiply-adds);
the loops over a row are vectorised where GCC can (each element keeps its own sum in its own
order, so vectors change no result). What differs from the numpy path in the last bits: the
sensitivities' products are associated differently from casadi's forward sweep; every dot
product here is summed left to right, where numpy's matrix products (BLAS) may pair the terms
differently and fuse multiply-adds; ``tanh`` is the C library's, not numpy's; the
unconstrained optimum comes from a Cholesky factorisation of the (symmetric positive definite)
Hessian where numpy's ``solve`` takes an LU factorisation; and the memory step is casadi's
expression of the feature map where the numpy path runs the feature map's numpy code (Bouc-Wen
features: the same formula, operations grouped differently). The plan may therefore differ
from the numpy path's by about 1e-12 V and the memory by about 1e-13 V, and the float32 volts
the plant receives round alike except where such a difference straddles a float32 rounding
boundary (one float32 ulp, 2e-6 V at 30 V; the tests hold the closed loops to that on the
benchmark's references). Where the plan sits on a kink of the feature map (two neighbouring
voltages equal to the last bits: du = 0, as on plateaus of a plan held against the drive
bound by a reference beyond reach), the Jacobian jumps between its one-sided values, and such
a difference can pick the other side: the two paths then follow different plans, each the
algorithm's own (on a reference about 25 % beyond reach the first QP's plans came out 1.8e-13 V
apart and the second QP's Hessians 42 % apart).

The library is built once per machine and model through
:func:`controllers.native.codegen.compile_source` (cached, digest-verified, the
``PIEZO_NATIVE`` policy applies); without it the NMPC runs its iterations in numpy, and its
``describe()["native"]["nmpc_step"]`` record says why.
"""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

from controllers.native.codegen import (
    NUMPY,
    NativeBuild,
    call_buffers,
    compile_source,
    generated_text,
)
from controllers.native.step_kernels import FLAGS
from controllers.native.step_kernels import SOURCE as KERNELS
from piezo_env.memo import ContentCache

__all__ = [
    "ERROR",
    "INSIDE",
    "NEED_QP",
    "PARTIALS_KEPT",
    "IterationKernel",
    "compile_kernel",
    "unavailable",
]

INSIDE, NEED_QP, ERROR, NON_FINITE = range(4)
"""Return codes of ``nmpc_iterate`` (``nmpc_apply`` returns INSIDE or ERROR; ``nmpc_step``
also NON_FINITE, for an observation with a NaN or an infinity)."""

# Pointer table, integer dimensions and scalars: their indices (as the enums in STEP).
(
    P_U, P_MEMORY, P_OFFSET, P_GAMMA, P_RATE_HESSIAN, P_LOWER, P_UPPER, P_WEIGHTS, P_BIASES,
    P_OUT, P_SKIP, P_Z, P_JAC, P_HESSIAN, P_Q, P_U_NEW, P_LAYERS, P_G, P_G_NEXT, P_GRAD,
    P_JAC_Y, P_CONSTANT, P_FACTOR, P_ARG, P_RES, P_IW, P_W, P_STEP_U, P_STATE, P_TANGENTS,
    P_TANGENTS_NEXT, P_COMBINED, P_FS_COLUMNS, P_FS_ROWS, P_SS_STARTS, P_SS_COLUMNS, P_SS_ORDER,
    P_DIMS, P_SIZES, P_SCALARS, P_OBSERVATION, P_ESTIMATE, P_PHI, P_PLAN, P_SHIFTED,
    P_GAIN_DIMS, P_GAIN_PAR, P_GAIN_C, P_GAIN_X, P_GAIN_ST, P_GAIN_A, P_GAIN_B, P_BANK_DIMS,
    P_BANK_PAR, P_BANK_C, P_BANK_GAINS, P_BANK_HLV, P_BANK_HIV, P_BANK_ST, P_BANK_COUNTERS,
    P_BANK_COUNTS, P_BANK_A, P_BANK_B, P_COUNT,
) = range(64)  # fmt: skip
(
    D_N, D_FEATURES, D_LAYERS, D_STATE, D_SHORTCUT, D_SLEW, D_ITERATIONS, D_DONE, D_OBSERVATION,
    D_LINEAR, D_HAS_GAIN, D_COUNT,
) = range(12)  # fmt: skip
(
    S_W, S_RATE_WEIGHT, S_U_PREV, S_SLEW_STEP, S_OUT_BIAS, S_STEP, S_U_APPLIED, S_Z_APPLIED,
    S_TOLERANCE, S_G, S_U_MAX, S_REACH_LOW, S_REACH_HIGH, S_RUNAWAY, S_COUNT,
) = range(15)  # fmt: skip
PARTIALS = ("F", "s_next", "dF_du", "ds_du", "dF_ds", "ds_ds")
"""Outputs of :func:`partials_function`, in order (the last two sparse)."""

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
       P_JAC_Y, P_CONSTANT, P_FACTOR, P_ARG, P_RES, P_IW, P_W, P_STEP_U, P_STATE, P_TANGENTS,
       P_TANGENTS_NEXT, P_COMBINED, P_FS_COLUMNS, P_FS_ROWS, P_SS_STARTS, P_SS_COLUMNS, P_SS_ORDER,
       P_DIMS, P_SIZES, P_SCALARS, P_OBSERVATION, P_ESTIMATE, P_PHI, P_PLAN, P_SHIFTED,
       P_GAIN_DIMS, P_GAIN_PAR, P_GAIN_C, P_GAIN_X, P_GAIN_ST, P_GAIN_A, P_GAIN_B, P_BANK_DIMS,
       P_BANK_PAR, P_BANK_C, P_BANK_GAINS, P_BANK_HLV, P_BANK_HIV, P_BANK_ST, P_BANK_COUNTERS,
       P_BANK_COUNTS, P_BANK_A, P_BANK_B };
enum { R_F, R_S_NEXT, R_DF_DU, R_DS_DU, R_DF_DS, R_DS_DS };
enum { D_N, D_FEATURES, D_LAYERS, D_STATE, D_SHORTCUT, D_SLEW, D_ITERATIONS, D_DONE,
       D_OBSERVATION, D_LINEAR, D_HAS_GAIN };
enum { S_W, S_RATE_WEIGHT, S_U_PREV, S_SLEW_STEP, S_OUT_BIAS, S_STEP, S_U_APPLIED,
       S_Z_APPLIED, S_TOLERANCE, S_G, S_U_MAX, S_REACH_LOW, S_REACH_HIGH, S_RUNAWAY };
enum { INSIDE, NEED_QP, ERROR, NON_FINITE };

#define D(p, i) (((const int64_t *)(p)[P_DIMS])[i])
#define S(p) ((double *)(p)[P_SCALARS])
#define F(p, i) ((double *)(p)[i])

/* The network on one feature vector (n_f): z, and with `grad` (not NULL) dz/dF (n_f).
   StructuredHorizon._network's operations in its order: each hidden unit tanh(sum + bias),
   z = (h . out + F . skip) + bias, the gradient by back-propagation. */
static void network(void **p, const double *features, double *z, double *grad)
{
    const int64_t rows = 1;  /* the buffers hold one row */
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

/* The feature map's step and its partial derivatives at (P_STEP_U, P_STATE) (nmpc_partials:
   outputs in P_RES, see PARTIALS). */
static int partials(void **p)
{
    return nmpc_partials((const casadi_real **)p[P_ARG], (casadi_real **)p[P_RES], p[P_IW],
                         p[P_W], 0);
}

/* One Gauss-Newton iteration along P_U from P_MEMORY (see the module docstring). */
int nmpc_iterate(void **p)
{
    const int64_t n = D(p, D_N), n_f = D(p, D_FEATURES), n_s = D(p, D_STATE);
    const double *sc = S(p);
    double *z = F(p, P_Z), *grad = F(p, P_GRAD), *jac = F(p, P_JAC);
    double **res = (double **)p[P_RES];
    double *step_u = F(p, P_STEP_U), *state = F(p, P_STATE), *combined = F(p, P_COMBINED);
    double *tangents = F(p, P_TANGENTS), *next = F(p, P_TANGENTS_NEXT);
    const int64_t *fs_columns = (const int64_t *)p[P_FS_COLUMNS];
    const int64_t *fs_rows = (const int64_t *)p[P_FS_ROWS];
    /* ds/ds by rows: row r's entries are ss_order[ss_starts[r] .. ss_starts[r+1]) of its
       nonzeros (casadi's column-major order), in columns ss_columns[...] */
    const int64_t *ss_starts = (const int64_t *)p[P_SS_STARTS];
    const int64_t *ss_columns = (const int64_t *)p[P_SS_COLUMNS];
    const int64_t *ss_order = (const int64_t *)p[P_SS_ORDER];
    const double *memory = F(p, P_MEMORY), *plan = F(p, P_U);
    for (int64_t i = 0; i < n_s; ++i) state[i] = memory[i];
    /* Forward along the plan, with tangents[r][j] = d s_k-1,r / du_j (j < k; state-major,
       so that the loops over j are whole rows): dF_k/du_j is dF/ds tangents[.][j] (and
       dF/du for j = k), so that dz_k/du_j = sum_c combined[c] tangents[c][j] with combined =
       (dz/dF)' dF/ds; then tangents <- ds/ds tangents and tangents[.][k] = ds/du. */
    for (int64_t k = 0; k < n; ++k) {
        step_u[0] = plan[k];
        if (partials(p)) return ERROR;
        double *g = grad + k * n_f;
        network(p, res[R_F], z + k, g);
        const double *dF_du = res[R_DF_DU], *dF_ds = res[R_DF_DS], *ds_ds = res[R_DS_DS];
        double *restrict row = jac + k * n;
        double diagonal = 0.0;
        for (int64_t f = 0; f < n_f; ++f) diagonal += g[f] * dF_du[f];
        for (int64_t c = 0; c < n_s; ++c) {
            double sum = 0.0;
            for (int64_t i = fs_columns[c]; i < fs_columns[c + 1]; ++i)
                sum += g[fs_rows[i]] * dF_ds[i];
            combined[c] = sum;
        }
        for (int64_t j = 0; j < n; ++j) row[j] = 0.0;
        for (int64_t c = 0; c < n_s; ++c) {
            const double a = combined[c], *restrict t = tangents + c * n;
            for (int64_t j = 0; j < k; ++j) row[j] += a * t[j];
        }
        row[k] = diagonal;
        const double *ds_du = res[R_DS_DU], *s_next = res[R_S_NEXT];
        for (int64_t r = 0; r < n_s; ++r) {
            double *restrict t_next = next + r * n;
            for (int64_t j = 0; j < k; ++j) t_next[j] = 0.0;
            for (int64_t i = ss_starts[r]; i < ss_starts[r + 1]; ++i) {
                const double a = ds_ds[ss_order[i]], *restrict t = tangents + ss_columns[i] * n;
                for (int64_t j = 0; j < k; ++j) t_next[j] += a * t[j];
            }
            t_next[k] = ds_du[r];
            state[r] = s_next[r];
        }
        double *swap = tangents; tangents = next; next = swap;
    }
    /* Each sum below runs over its index in order, as a dot product would, but the loops
       update whole rows (j innermost, independent sums), so that the compiler may vectorise
       them without reordering any sum. dz/du and Gamma are lower triangular (causal: z_t+k
       and y_t+k+1 depend on no later voltage; Gamma checked at setup), and the terms with a
       structural zero factor are left out (adding them adds zeros). */
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

/* Python's max(a, b) and min(a, b): the first argument unless the second compares beyond it. */
static double py_max(double a, double b) { return b > a ? b : a; }
static double py_min(double a, double b) { return b < a ? b : a; }

/* The start of NonlinearMPC._act after the observer's update (P_ESTIMATE = [x; d], the
   bounds' first entries set to the slew window): the targets r_t+1 .. r_t+N from
   P_OBSERVATION (ControlTask.targets: the last preview sample holds), P_OFFSET =
   Phi x + (d - r), and in P_U the previous plan P_PLAN shifted by one sample and made feasible
   (NonlinearMPC._feasible). */
void nmpc_prepare(void **p)
{
    const int64_t n = D(p, D_N), n_x = D(p, D_LINEAR), size = D(p, D_OBSERVATION);
    const double *obs = F(p, P_OBSERVATION), *estimate = F(p, P_ESTIMATE), *phi = F(p, P_PHI);
    const double *plan = F(p, P_PLAN), *lower = F(p, P_LOWER), *upper = F(p, P_UPPER);
    double *offset = F(p, P_OFFSET), *u = F(p, P_U);
    const int64_t seen = n < size - 2 ? n : size - 2;
    for (int64_t i = 0; i < n; ++i) {
        const double target = i < seen ? obs[2 + i] : obs[size - 1];
        double sum = 0.0;
        for (int64_t j = 0; j < n_x; ++j) sum += phi[i * n_x + j] * estimate[j];
        offset[i] = sum + (estimate[n_x] - target);
    }
    for (int64_t i = 0; i < n; ++i) {
        double v = plan[i + 1 < n ? i + 1 : n - 1];
        if (v < lower[i]) v = lower[i];  /* np.maximum, np.minimum (NaN passes) */
        if (v > upper[i]) v = upper[i];
        u[i] = v;
    }
    if (!D(p, D_SLEW)) return;
    const double step = S(p)[S_SLEW_STEP];
    double previous = S(p)[S_U_PREV];
    for (int64_t i = 0; i < n; ++i)
        previous = u[i] = py_min(py_max(u[i], previous - step), previous + step);
}

/* NonlinearMPC._solve_rti while every iteration's unconstrained optimum meets the bounds:
   iterate, move P_U to the optimum, stop after D_ITERATIONS or once no voltage moved more
   than S_TOLERANCE. INSIDE: P_U is the plan. NEED_QP: iteration D_DONE (counted from 0)
   needs the QP, on P_HESSIAN and P_Q along P_U (the iterate before it). */
int nmpc_rti(void **p)
{
    const int64_t n = D(p, D_N), iterations = D(p, D_ITERATIONS);
    int64_t *dims = (int64_t *)p[P_DIMS];
    double *u = F(p, P_U);
    const double *u_new = F(p, P_U_NEW);
    for (int64_t i = 0; i < iterations; ++i) {
        dims[D_DONE] = i;
        const int code = nmpc_iterate(p);
        if (code != INSIDE) return code;
        for (int64_t j = 0; j < n; ++j) u[j] = u_new[j];
        if (S(p)[S_STEP] <= S(p)[S_TOLERANCE]) break;
    }
    return INSIDE;
}

/* The nonlinearity's step with the applied volts S_U_APPLIED: P_MEMORY updated in place,
   z in S_Z_APPLIED. */
int nmpc_apply(void **p)
{
    double *memory = F(p, P_MEMORY), *state = F(p, P_STATE);
    for (int64_t i = 0; i < D(p, D_STATE); ++i) state[i] = memory[i];
    F(p, P_STEP_U)[0] = S(p)[S_U_APPLIED];
    if (partials(p)) return ERROR;
    double **res = (double **)p[P_RES];
    double z;
    network(p, res[R_F], &z, NULL);
    for (int64_t i = 0; i < D(p, D_STATE); ++i) memory[i] = res[R_S_NEXT][i];
    S(p)[S_Z_APPLIED] = z;
    return INSIDE;
}

/* controllers.mpc.float32_within: u rounded to the float32 the plant receives, kept inside
   [low, high], the ends compared as float32 (as the Python function does explicitly). */
static double float32_within(double u, double low, double high)
{
    float rounded = (float)u;
    if (rounded > (float)high) rounded = nextafterf(rounded, -INFINITY);
    else if (rounded < (float)low) rounded = nextafterf(rounded, INFINITY);
    return (double)rounded;
}

/* The end of NonlinearMPC._act once the plan (P_PLAN) is chosen: its first move, clipped to
   the first move's bounds (the slew window) and rounded to float32 within them, steps the
   memory (nmpc_apply), the observer bank and the gain estimate (time updates with its z);
   the volts in S_U_APPLIED and S_U_PREV. */
int nmpc_finish(void **p)
{
    double *sc = S(p);
    const double low = F(p, P_LOWER)[0], high = F(p, P_UPPER)[0];
    sc[S_U_APPLIED] = float32_within(py_min(py_max(F(p, P_PLAN)[0], low), high), low, high);
    if (nmpc_apply(p) == ERROR) return ERROR;
    const double z = sc[S_Z_APPLIED];
    bank_predict(p[P_BANK_DIMS], p[P_BANK_A], p[P_BANK_B], p[P_BANK_ST], z);
    if (D(p, D_HAS_GAIN)) gain_advance(p[P_GAIN_DIMS], p[P_GAIN_A], p[P_GAIN_B], p[P_GAIN_X], z);
    sc[S_U_PREV] = sc[S_U_APPLIED];
    return INSIDE;
}

/* NonlinearMPC._act in one call, for the identified NLS with the observer bank: the
   observation's check, the gain estimate's update and the observation over g
   (NonlinearMPC._learn_gain: a new g rescales every filter's output estimate,
   controllers.observer.rescale_output_states), the preview clipped to the static reach
   (S_REACH_LOW, S_REACH_HIGH), the bank's measurement update (its runaway sample in
   S_RUNAWAY), the first move's bounds (the slew window), nmpc_prepare (the shifted plan also
   in P_SHIFTED, the fallback of a failed QP) and nmpc_rti. INSIDE: the plan went on to
   nmpc_finish. NEED_QP: Python solves the QP of iteration D_DONE and calls nmpc_finish. */
int nmpc_step(void **p)
{
    double *sc = S(p), *obs = F(p, P_OBSERVATION);
    const int64_t size = D(p, D_OBSERVATION), n = D(p, D_N), n_x = D(p, D_LINEAR);
    for (int64_t i = 0; i < size; ++i)
        if (!isfinite(obs[i])) return NON_FINITE;
    const int64_t *bank_dims = (const int64_t *)p[P_BANK_DIMS];
    const int64_t filters = bank_dims[0], m = bank_dims[1];
    double *est = F(p, P_BANK_ST);
    if (D(p, D_HAS_GAIN)) {
        gain_update(p[P_GAIN_DIMS], p[P_GAIN_PAR], p[P_GAIN_C], p[P_GAIN_X], p[P_GAIN_ST], obs[0]);
        const int64_t k = ((const int64_t *)p[P_GAIN_DIMS])[0];
        const double g = F(p, P_GAIN_ST)[9 * k];  /* value[0] */
        if (g != sc[S_G]) {
            const double ratio = sc[S_G] / g, *c = F(p, P_BANK_C);
            for (int64_t f = 0; f < filters; ++f) {
                double *e = est + f * m, output = 0.0;
                for (int64_t j = 0; j < n_x; ++j) output += e[j] * c[j];
                e[n_x] = ratio * (output + e[n_x]) - output;
                for (int64_t j = n_x + 1; j < m; ++j) e[j] *= ratio;
            }
            sc[S_G] = g;
        }
        if (g != 1.0)
            for (int64_t i = 0; i < size; ++i) obs[i] = obs[i] / g;
    }
    const double low = sc[S_REACH_LOW], high = sc[S_REACH_HIGH];
    int beyond = 0;
    for (int64_t i = 1; i < size; ++i)
        if (obs[i] < low || obs[i] > high) beyond = 1;
    if (beyond)  /* numpy's clip: minimum(maximum(r, low), high) */
        for (int64_t i = 1; i < size; ++i) {
            const double v = obs[i] > low ? obs[i] : low;
            obs[i] = v < high ? v : high;
        }
    bank_correct(p[P_BANK_DIMS], p[P_BANK_PAR], F(p, P_BANK_C), p[P_BANK_GAINS], p[P_BANK_HLV],
                 p[P_BANK_HIV], est, p[P_BANK_COUNTERS], p[P_BANK_COUNTS], obs[0]);
    const int64_t *counters = (const int64_t *)p[P_BANK_COUNTERS];
    sc[S_RUNAWAY] = (double)counters[3];
    const double *selected = est + counters[0] * m;
    double *estimate = F(p, P_ESTIMATE);
    for (int64_t j = 0; j <= n_x; ++j) estimate[j] = selected[j];
    double *lower = F(p, P_LOWER), *upper = F(p, P_UPPER);
    const double u_max = sc[S_U_MAX];
    if (D(p, D_SLEW)) {  /* PredictiveController._slew_window */
        lower[0] = py_max(sc[S_U_PREV] - sc[S_SLEW_STEP], -u_max);
        upper[0] = py_min(sc[S_U_PREV] + sc[S_SLEW_STEP], u_max);
    } else {
        lower[0] = -u_max;
        upper[0] = u_max;
    }
    nmpc_prepare(p);
    const double *u = F(p, P_U);
    double *shifted = F(p, P_SHIFTED), *plan = F(p, P_PLAN);
    for (int64_t i = 0; i < n; ++i) shifted[i] = u[i];
    const int code = nmpc_rti(p);
    if (code != INSIDE) return code;
    for (int64_t i = 0; i < n; ++i) plan[i] = u[i];
    return nmpc_finish(p);
}
"""


PARTIALS_KEPT = 8
"""Feature maps' :func:`partials_function` kept by content, one per identified model: a
benchmark worker meets up to six (three identification seeds, on the nominal bender and on the
bench)."""

_partials = ContentCache(PARTIALS_KEPT)


def partials_function(nls: Any) -> Any:
    """casadi.Function ``(u, s) -> (F, s_next, dF/du, ds/du, dF/ds, ds/ds)``: one step of the
    NLS's feature map and its partial derivatives (the last two keep their sparsity; common
    subexpressions merged, which changes no value).

    A pure function of the feature map (a frozen dataclass of numbers), kept by content
    (:data:`PARTIALS_KEPT`): an NMPC built again on the same model differentiates none."""
    return _partials.get_or_compute(["partials", nls.feature_map], lambda: _partials_of(nls))


def _partials_of(nls: Any) -> Any:
    """:func:`partials_function`, computed."""
    import casadi

    u = casadi.SX.sym("u")
    state = casadi.SX.sym("s", nls.n_state)
    features, new = nls.feature_map.casadi_step(u, state)
    outputs = [
        casadi.densify(features),
        casadi.densify(new),
        casadi.densify(casadi.jacobian(features, u)),
        casadi.densify(casadi.jacobian(new, u)),
        casadi.jacobian(features, state),
        casadi.jacobian(new, state),
    ]
    return casadi.Function(
        "nmpc_partials", [u, state], outputs, ["u", "s"], list(PARTIALS), {"cse": True}
    )


def kernel_source(partials: Any) -> str:
    """The translation unit: the generated C of :func:`partials_function`'s Function
    (``nmpc_partials``) and the step."""
    generated = generated_text("nmpc_step.c", [partials])
    return "\n".join((generated, KERNELS, STEP))


def compile_kernel(partials: Any) -> tuple[ctypes.CDLL | None, NativeBuild]:
    """The library of :func:`kernel_source` (None and the record of why when there is none)."""
    return compile_source("nmpc_step", kernel_source(partials), flags=FLAGS, cache="kernels")


def unavailable(reason: str, function: str = "nmpc_step") -> NativeBuild:
    """The record of an NMPC whose iterations (``nmpc_step``), or whose step around them
    (``nmpc_fused``), run in numpy and Python, and why."""
    return NativeBuild(function, NUMPY, reason)


def _ccs(sparsity: Any) -> tuple[np.ndarray, np.ndarray]:
    """Column starts and row indices (int64) of a casadi Sparsity."""
    columns, rows = sparsity.get_ccs()
    return np.array(columns, dtype=np.int64), np.array(rows, dtype=np.int64)


def _crs(sparsity: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Row starts, column indices and the nonzeros' positions in casadi's column-major order
    (int64) of a casadi Sparsity, row by row (columns ascending within a row)."""
    starts, rows = _ccs(sparsity)
    columns = np.repeat(np.arange(starts.size - 1), np.diff(starts))
    order = np.argsort(rows, kind="stable")
    row_starts = np.searchsorted(rows[order], np.arange(sparsity.size1() + 1))
    return row_starts.astype(np.int64), columns[order].astype(np.int64), order.astype(np.int64)


class IterationKernel:
    """The compiled iteration bound to one controller's arrays (module docstring).

    Parameters
    ----------
    library : ctypes.CDLL
        The library of :func:`kernel_source`.
    partials : casadi.Function
        The Function it was generated from (:func:`partials_function`: sizes, sparsity).
    network : identification.nls.network.NumpyMLP-like
        ``weights``, ``biases``, ``out_weight``, ``skip_weight``, ``out_bias`` (the NLS's
        ``to_numpy()``).
    gamma, rate_hessian : numpy.ndarray
        The prediction matrix Gamma (N, N), lower triangular, and the rate penalty's
        symmetric Hessian R (N, N).
    lower, upper : numpy.ndarray
        The controller's bound arrays (N,), read at each call.
    tracking_weight, rate_weight : float
        w and lambda of the cost.
    slew_step : float or None
        S dt (V), None without a slew limit.
    shortcut : bool
        Try the unconstrained optimum.
    iterations, step_tolerance : int, float
        The SQP's iterations per step and its early stop (V), for :meth:`run`.
    phi, observation_size : numpy.ndarray, int
        The prediction matrix Phi (N, n) of the linear state and the observation's size, for
        :meth:`prepare`.

    Attributes
    ----------
    u, memory, offset : numpy.ndarray
        Inputs the caller writes (or :meth:`prepare`): the plan u_bar (N,), the memory state,
        the offset (N,). :meth:`apply` steps ``memory`` in place.
    observation, estimate, plan : numpy.ndarray
        Inputs of :meth:`prepare` the caller writes: the observation, the observer's
        ``[x; d]`` and the previous plan (N,).
    z, jac, hessian, q, u_new : numpy.ndarray
        Outputs: z (N,), dz/du (N, N), the QP's Hessian (N, N) and vector (N,), and the
        unconstrained optimum (N,) when the call returned :data:`INSIDE`.
    scalars : numpy.ndarray
        w, lambda, u_t-1 (written by the caller), S dt, the network's output bias, the
        largest move of the iteration (V), the applied volts and their z.
    calls : int
        Compiled calls made (prepare, run, iterate, apply), for tests of the fusion.
    """

    def __init__(
        self,
        library: ctypes.CDLL,
        partials: Any,
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
        iterations: int,
        step_tolerance: float,
        phi: np.ndarray,
        observation_size: int,
    ) -> None:
        n = gamma.shape[0]
        n_f, n_state = partials.numel_out(0), partials.numel_out(1)
        if gamma.shape != (n, n) or rate_hessian.shape != (n, n) or lower.shape != (n,):
            raise ValueError(f"Gamma, R and the bounds must be ({n}, {n}) and ({n},)")
        if partials.numel_in(1) != n_state or network.skip_weight.size != n_f:
            raise ValueError("the feature map's sizes do not match the network's")
        if np.any(np.triu(gamma, 1) != 0.0):
            raise ValueError("Gamma must be lower triangular (a causal prediction)")
        if np.any(rate_hessian != rate_hessian.T):
            raise ValueError("the rate penalty's Hessian R must be symmetric")
        if phi.ndim != 2 or phi.shape[0] != n or observation_size < 3:
            raise ValueError(f"Phi must be ({n}, n) and the observation hold a preview")
        self.table = np.zeros(P_COUNT, dtype=np.uint64)
        self._keep: list[Any] = []
        sizes = [n_f, *(b.size for b in network.biases)]
        self.dims = np.array(
            [
                n,
                n_f,
                len(network.biases),
                n_state,
                int(shortcut),
                int(slew_step is not None),
                iterations,
                0,
                observation_size,
                phi.shape[1],
                0,  # D_HAS_GAIN: bind_estimators
            ],
            dtype=np.int64,
        )
        self.sizes = np.array(sizes, dtype=np.int64)
        self.scalars = np.zeros(S_COUNT)
        self.scalars[[S_W, S_RATE_WEIGHT, S_SLEW_STEP, S_OUT_BIAS, S_TOLERANCE]] = (
            tracking_weight,
            rate_weight,
            0.0 if slew_step is None else slew_step,
            float(network.out_bias),
            step_tolerance,
        )
        self.u, self.memory, self.offset = np.zeros(n), np.zeros(n_state), np.zeros(n)
        self.z, self.jac = np.zeros(n), np.zeros((n, n))
        self.hessian, self.q, self.u_new = np.zeros((n, n)), np.zeros(n), np.zeros(n)
        step_u, state = np.zeros(1), np.zeros(n_state)
        self.observation, self.plan = np.zeros(observation_size), np.zeros(n)
        self.shifted = np.zeros(n)
        self.estimate = np.zeros(phi.shape[1] + 1)
        fs_columns, fs_rows = _ccs(partials.sparsity_out(4))
        ss_starts, ss_columns, ss_order = _crs(partials.sparsity_out(5))
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
            P_LAYERS: np.zeros(sum(sizes[1:])),
            P_G: np.zeros(max(sizes)),
            P_G_NEXT: np.zeros(max(sizes)),
            P_GRAD: np.zeros(n * n_f),
            P_JAC_Y: np.zeros((n, n)),
            P_CONSTANT: np.zeros(n),
            P_FACTOR: np.zeros((n, n)),
            P_STEP_U: step_u,
            P_STATE: state,
            P_TANGENTS: np.zeros(n * n_state),
            P_TANGENTS_NEXT: np.zeros(n * n_state),
            P_COMBINED: np.zeros(n_state),
            P_FS_COLUMNS: fs_columns,
            P_FS_ROWS: fs_rows,
            P_SS_STARTS: ss_starts,
            P_SS_COLUMNS: ss_columns,
            P_SS_ORDER: ss_order,
            P_DIMS: self.dims,
            P_SIZES: self.sizes,
            P_SCALARS: self.scalars,
            P_OBSERVATION: self.observation,
            P_ESTIMATE: self.estimate,
            P_PHI: np.ascontiguousarray(phi, dtype=np.float64),
            P_PLAN: self.plan,
            P_SHIFTED: self.shifted,
        }
        for index, buffer in own.items():
            self._point(index, buffer)
        outputs = self._casadi(library, partials, [step_u, state])
        expected = [n_f, n_state, n_f, n_state, fs_rows.size, ss_order.size]
        if [o.size for o in outputs] != expected or fs_columns.size != n_state + 1:
            raise ValueError("the partials Function's outputs do not match the feature map")
        pointer = self.table.ctypes.data
        functions = {}
        for name in ("nmpc_iterate", "nmpc_apply", "nmpc_rti", "nmpc_step", "nmpc_finish"):
            function = getattr(library, name)
            function.argtypes, function.restype = [ctypes.c_void_p], ctypes.c_int
            functions[name] = function
        self._library = library
        self._iterate = lambda: functions["nmpc_iterate"](pointer)
        self._apply = lambda: functions["nmpc_apply"](pointer)
        self._rti = lambda: functions["nmpc_rti"](pointer)
        self._step = lambda: functions["nmpc_step"](pointer)
        self._finish = lambda: functions["nmpc_finish"](pointer)
        self.fused = False  # bind_estimators: the bank's and the gain's arrays are bound
        prepare = library.nmpc_prepare
        prepare.argtypes, prepare.restype = [ctypes.c_void_p], None
        self._prepare = lambda: prepare(pointer)
        self.calls = 0

    def prepare(self) -> None:
        """Targets, :attr:`offset` and the shifted, feasible plan in :attr:`u` from
        :attr:`observation`, :attr:`estimate` and :attr:`plan` (``nmpc_prepare``)."""
        self.calls += 1
        self._prepare()

    def run(self) -> tuple[int, int]:
        """The iterations from the plan in :attr:`u` while their unconstrained optima meet
        the bounds: (:data:`INSIDE`, iterations) with the plan in :attr:`u`, or
        (:data:`NEED_QP`, the iteration that needs the QP, counted from 0) with its QP in
        :attr:`hessian` and :attr:`q` along :attr:`u`."""
        self.calls += 1
        code = self._rti()
        if code == ERROR:
            raise RuntimeError("the compiled NMPC iteration's feature map failed")
        return code, int(self.dims[D_DONE]) + (code == INSIDE)

    def iterate(self) -> int:
        """One iteration along :attr:`u` from :attr:`memory` (:data:`INSIDE`,
        :data:`NEED_QP`; RuntimeError when the generated code reports an error)."""
        self.calls += 1
        code = self._iterate()
        if code == ERROR:
            raise RuntimeError("the compiled NMPC iteration's feature map failed")
        return code

    def apply(self, u: float) -> float:
        """Step :attr:`memory` with the applied volts ``u``; their z (equivalent V)."""
        self.calls += 1
        self.scalars[S_U_APPLIED] = u
        if self._apply() == ERROR:
            raise RuntimeError("the compiled NMPC memory step's feature map failed")
        return float(self.scalars[S_Z_APPLIED])

    def bind_estimators(
        self,
        bank: Any,
        gain: Any,
        *,
        u_max: float,
        reach: tuple[float, float],
    ) -> None:
        """Point :meth:`step` at an :class:`controllers.observer.ObserverBank`'s arrays and a
        :class:`controllers.gain.GainEstimate`'s (None: no gain), both run by the compiled
        kernels (:mod:`controllers.native.step_kernels`), with the drive limit ``u_max`` (V)
        and the static reach (um, :func:`controllers.nmpc.static_reach`). The arrays stay
        their owners' (the controller keeps them); called at each episode's start."""
        n_x = int(self.dims[D_LINEAR])
        if int(bank._dims[1]) < n_x + 1 or bank.c_aug.size != bank._dims[1]:
            raise ValueError(f"the bank's estimates must hold [x; d] with x of size {n_x}")
        buffers = {
            P_BANK_DIMS: bank._dims,
            P_BANK_PAR: bank._parameters,
            P_BANK_C: bank._c_aug,
            P_BANK_GAINS: bank._gains,
            P_BANK_HLV: bank._half_log_var,
            P_BANK_HIV: bank._half_inverse_var,
            P_BANK_ST: bank._state,
            P_BANK_COUNTERS: bank._counters,
            P_BANK_COUNTS: bank.selection_counts,
            P_BANK_A: bank._a_aug,
            P_BANK_B: bank._b_aug,
        }
        self.dims[D_HAS_GAIN] = gain is not None
        if gain is not None:
            if gain.size != 1:
                raise ValueError("the NMPC's gain estimate has one part")
            dims, par = gain._kernel_data
            buffers.update(
                {
                    P_GAIN_DIMS: dims,
                    P_GAIN_PAR: par,
                    P_GAIN_C: gain._c,
                    P_GAIN_X: gain._x,
                    P_GAIN_ST: gain._state,
                    P_GAIN_A: gain._a,
                    P_GAIN_B: gain._b,
                }
            )
        for index, buffer in buffers.items():
            self._point(index, buffer, keep=False)
        self._bound = buffers  # held while bound: the table never points at freed memory
        self.scalars[S_U_MAX] = u_max
        self.scalars[S_REACH_LOW], self.scalars[S_REACH_HIGH] = reach
        self.fused = True

    def step(self) -> int:
        """The whole step from :attr:`observation` (``nmpc_step``, after
        :meth:`bind_estimators`): :data:`INSIDE` (the volts in ``scalars[S_U_APPLIED]``),
        :data:`NEED_QP` (iteration ``dims[D_DONE]`` needs the QP; then :meth:`finish`) or
        :data:`NON_FINITE`; RuntimeError when the generated code reports an error."""
        self.calls += 1
        code = self._step()
        if code == ERROR:
            raise RuntimeError("the compiled NMPC step's feature map failed")
        return code

    def finish(self) -> float:
        """The step's end for the plan in :attr:`plan` (``nmpc_finish``): its first move in
        the window, rounded to float32, steps the memory and the estimators; the volts."""
        self.calls += 1
        if self._finish() == ERROR:
            raise RuntimeError("the compiled NMPC memory step's feature map failed")
        return float(self.scalars[S_U_APPLIED])

    def _point(self, index: int, buffer: np.ndarray, *, keep: bool = True) -> None:
        """Write ``buffer``'s address into the table (``keep``: hold a reference to it, for the
        kernel's own buffers; the estimators' arrays are their owners')."""
        if not (buffer.flags.c_contiguous and buffer.dtype in (np.float64, np.int64)):
            raise ValueError(f"table entry {index}: needs a C-contiguous float64 or int64 array")
        self.table[index] = buffer.ctypes.data
        if keep:
            self._keep.append(buffer)

    def _casadi(
        self, library: ctypes.CDLL, function: Any, inputs: list[np.ndarray]
    ) -> list[np.ndarray]:
        """Point the table at the argument, result and work arrays of the generated Function
        (:func:`controllers.native.codegen.call_buffers`, by nonzeros), its inputs at
        ``inputs``; returns its output buffers (nonzeros, casadi's column-major order)."""
        buffers = call_buffers(library, function, inputs, nonzeros=True)
        self.table[[P_ARG, P_RES, P_IW, P_W]] = buffers.addresses
        self._keep.append(buffers)
        return buffers.outputs
