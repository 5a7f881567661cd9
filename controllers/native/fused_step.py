"""The linear MPC's step in one compiled call: estimators, unconstrained plan, inverse.

A step of :class:`controllers.mpc.LinearMPC` without an active constraint (the unconstrained
optimum lies inside the box, :func:`controllers.box_qp.within`) is a fixed sequence of small
operations: the gain estimate's update, the observer bank's measurement update, the stacked
vector ``[x; d; r; z_t-1]``, the reachable range from the nonlinearity's memory, the plan
``-P^-1 q``, the box test, the nonlinearity's inverse, and the estimators' time updates. Each
is cheap; called one by one from Python, the calls' overhead is most of the step. Here they
run in one C function, :func:`library`'s ``fused_step``, on the controller's own arrays (the
estimators', the plan's, the bounds' and the memory's, updated in place).

The translation unit is the generated C of the nonlinearity's inverse and its reachable range
(the identified NLS's, or the oracle's plant hysteresis: any
:class:`controllers.native.compiled_inverse.InverseMap`)
(:func:`controllers.native.compiled_inverse.inverse_function` and
:func:`~controllers.native.compiled_inverse.reachable_function`, the same casadi Functions
:class:`~controllers.native.compiled_inverse.CompiledInverse` compiles), the estimator kernels
(:data:`controllers.native.step_kernels.SOURCE`) and the step below, compiled with the same
flags (:data:`controllers.native.step_kernels.FLAGS`: no fused multiply-adds). Every operation
is therefore the IEEE operation of the unfused native path on the same operands, except two dot
products that the unfused path leaves to numpy's matrix products (BLAS): the plan
``-P^-1 q`` (a row of the plan per dot product) and the output ``C x`` by which a change of the
learned gain rescales each filter's state (:func:`controllers.observer.rescale_states`). Here
they are summed left to right, so a plan may differ from the unfused one in its last bits
(about 1e-16 relative), which a closed loop carries on at the level of 1e-12 equivalent V in z;
the float32 volts the plant receives then round alike but where such a difference straddles a
float32 rounding boundary (the tests hold the two paths to one float32 ulp and z to 1e-11).

A plan outside the box goes to the QP in the same call when the MPC's QP is a DAQP workspace
driven from C (:mod:`controllers.native.daqp_box`, the default): its linear term ``q = G
stacked`` is summed left to right (numpy's matrix product may pair the terms differently, so q
may differ in its last bits from the unfused path's), DAQP solves from its last active set
unless the last plan was unconstrained or the last solve failed (as
:meth:`controllers.mpc.LinearMPC._solve_constrained`), and the first move of the clipped
solution goes on to the inverse; Python then only counts the solve's iterations and status.
This is what keeps a 10 kHz loop within its deadline on the samples that need the QP: through
DAQP's Python interface such a sample took 100-400 us after thousands that did not
(``benchmarks/results/controller_latency.md``).

With a learned drive (:mod:`controllers.drive`, the adaptive MPC's default) the step runs the
drive estimate's update after the gain's, moves the observer bank's states when the drive of
the member in use changes (:func:`controllers.observer.shift_states`), plans in the drive and
inverts the mixed map (:class:`controllers.native.compiled_inverse.MixedMap`, whose generated
functions take the drive as their parameter input), as :meth:`controllers.mpc.LinearMPC.
_set_drive` and :meth:`~controllers.mpc.LinearMPC._convert` do.

With the amplifier's slew limit (the ``bench`` plant) the step does what
:meth:`controllers.mpc.LinearMPC._solve` does then: the first move's z bounds are the map at
the slew window's ends u_t-1 +- S dt (the same generated ``nls_reachable``, called with the
window instead of the drive range, that the Python step calls), the unconstrained plan must
also meet the z rate rows, and the QP gets those rows' bounds g z_rate. Through Python that
step took 80-130 us against 20-25 us here (PL140 at 1 ms, 77 mA amplifier); the volts are the
same to the bit (``tests/test_fused_step.py``).

What leaves the compiled call for Python (the return codes): a plan outside the box with any
other QP workspace (OSQP, DAQP's Python interface: the QP solver runs, then ``fused_finish``
converts its first move), an inverse the compiled Newton
iteration hands back (a non-monotone map, a non-finite target: the numpy inverse runs), with
a slew limit a first move whose float32 volts leave the window (Python clips it and steps the
map there, :meth:`controllers.mpc.LinearMPC._convert`), a
non-finite observation (the base class's check raises, before any state changes), and for the
adaptive MPC a sample on which its selection may change something (the set of plausible models
or the model in use: Python then runs :meth:`controllers.adaptive.AdaptiveMPC._select` and
calls ``fused_solve``); on the other samples the step tests that in C.

The library is built once per machine and nonlinearity through
:func:`controllers.native.codegen.compile_source` (cached, digest-verified, the
``PIEZO_NATIVE`` policy applies); without it the MPC runs its step in numpy and Python, and its
``describe()["native"]["mpc_step"]`` record says why.
"""

from __future__ import annotations

import array
import ctypes
import weakref
from typing import Any

import numpy as np

from controllers.native.codegen import (
    NUMPY,
    NativeBuild,
    call_buffers,
    compile_source,
    generated_text,
)
from controllers.native.daqp_box import HEADER as DAQP_HEADER
from controllers.native.step_kernels import FLAGS
from controllers.native.step_kernels import SOURCE as KERNELS

__all__ = [
    "BANK_SLOTS",
    "DONE",
    "ERROR",
    "NEED_INVERSE",
    "NEED_QP",
    "NEED_SELECT",
    "NON_FINITE",
    "FusedStep",
    "compile_step",
    "fused_source",
    "unavailable",
]

DONE, NON_FINITE, NEED_QP, NEED_INVERSE, ERROR, NEED_SELECT = range(6)
"""Return codes of the compiled step (module docstring)."""

# Pointer table (one int64 array of addresses), integer dimensions and scalars: their indices.
(
    P_OBS, P_GAIN_DIMS, P_GAIN_PAR, P_GAIN_C, P_GAIN_X, P_GAIN_ST, P_GAIN_A, P_GAIN_B,
    P_BANK_DIMS, P_BANK_PAR, P_BANK_C, P_BANK_GAINS, P_BANK_HLV, P_BANK_HIV, P_BANK_ST,
    P_BANK_COUNTERS, P_BANK_COUNTS, P_BANK_A, P_BANK_B, P_UNCONSTRAINED, P_STACKED, P_PLAN,
    P_LOWER, P_UPPER, P_MEMORY, P_INV_ARG, P_INV_RES, P_INV_IW, P_INV_W, P_REACH_ARG,
    P_REACH_RES, P_REACH_IW, P_REACH_W, P_DIMS, P_SCALARS, P_PLAUSIBLE, P_ALLOWED, P_Q_MATRIX,
    P_QP, P_QP_SOLVE, P_SCRATCH, P_GAIN_XU, P_DRIVE_PAR, P_DRIVE_ST, P_COUNT,
) = range(45)  # fmt: skip
(
    D_OBS, D_STATES, D_ESTIMATE, D_MOVES, D_SAMPLES, D_COLUMNS, D_MEMORY, D_HAS_GAIN, D_MEMBER,
    D_SHORTCUT, D_SELECTS, D_SLEW, D_DRIVE, D_COUNT,
) = range(14)  # fmt: skip
(
    S_G, S_Z_PREV, S_Z_APPLIED, S_U, S_Z_MODEL, S_Z_MIN, S_Z_MAX, S_INVERSE_STATUS, S_RUNAWAY,
    S_NOISE_VARIANCE, S_SWITCH_CHI2, S_NORMAL_95, S_DUALS_ANY, S_QP_RAN, S_QP_FLAG,
    S_QP_ITERATIONS, S_U_PREV, S_SLEW_STEP, S_U_MAX, S_Z_RATE, S_B, S_U_APPLIED, S_COUNT,
) = range(23)  # fmt: skip
BANK_SLOTS = np.array(
    [
        P_BANK_DIMS, P_BANK_PAR, P_BANK_C, P_BANK_GAINS, P_BANK_HLV, P_BANK_HIV, P_BANK_ST,
        P_BANK_COUNTERS, P_BANK_COUNTS, P_BANK_A, P_BANK_B, P_UNCONSTRAINED, P_STACKED, P_LOWER,
        P_UPPER, P_Q_MATRIX,
    ]
)  # fmt: skip
"""The table's slots of the model in use (:meth:`FusedStep.bank_addresses`)."""

STEP = r"""
enum { P_OBS, P_GAIN_DIMS, P_GAIN_PAR, P_GAIN_C, P_GAIN_X, P_GAIN_ST, P_GAIN_A, P_GAIN_B,
       P_BANK_DIMS, P_BANK_PAR, P_BANK_C, P_BANK_GAINS, P_BANK_HLV, P_BANK_HIV, P_BANK_ST,
       P_BANK_COUNTERS, P_BANK_COUNTS, P_BANK_A, P_BANK_B, P_UNCONSTRAINED, P_STACKED, P_PLAN,
       P_LOWER, P_UPPER, P_MEMORY, P_INV_ARG, P_INV_RES, P_INV_IW, P_INV_W, P_REACH_ARG,
       P_REACH_RES, P_REACH_IW, P_REACH_W, P_DIMS, P_SCALARS, P_PLAUSIBLE, P_ALLOWED, P_Q_MATRIX,
       P_QP, P_QP_SOLVE, P_SCRATCH, P_GAIN_XU, P_DRIVE_PAR, P_DRIVE_ST };
enum { D_OBS, D_STATES, D_ESTIMATE, D_MOVES, D_SAMPLES, D_COLUMNS, D_MEMORY, D_HAS_GAIN,
       D_MEMBER, D_SHORTCUT, D_SELECTS, D_SLEW, D_DRIVE };
enum { S_G, S_Z_PREV, S_Z_APPLIED, S_U, S_Z_MODEL, S_Z_MIN, S_Z_MAX, S_INVERSE_STATUS,
       S_RUNAWAY, S_NOISE_VARIANCE, S_SWITCH_CHI2, S_NORMAL_95, S_DUALS_ANY, S_QP_RAN,
       S_QP_FLAG, S_QP_ITERATIONS, S_U_PREV, S_SLEW_STEP, S_U_MAX, S_Z_RATE, S_B,
       S_U_APPLIED };
enum { DONE, NON_FINITE, NEED_QP, NEED_INVERSE, ERROR, NEED_SELECT };

#define D(p, i) (((const int64_t *)(p)[P_DIMS])[i])
#define S(p) ((double *)(p)[P_SCALARS])
#define F(p, i) ((double *)(p)[i])

/* Python's max(a, b) and min(a, b): the first argument unless the second compares beyond it
   (NaN stays where Python keeps it). */
static double py_max(double a, double b) { return b > a ? b : a; }
static double py_min(double a, double b) { return b < a ? b : a; }

/* controllers.predictive.PredictiveController._slew_window: the volts this sample's move may
   take with a slew limit, u_t-1 +- S dt within the drive range (D_SLEW only). */
static void slew_window(void **p, double *low, double *high)
{
    const double *sc = S(p), step = sc[S_SLEW_STEP], u_max = sc[S_U_MAX];
    *low = py_max(sc[S_U_PREV] - step, -u_max);
    *high = py_min(sc[S_U_PREV] + step, u_max);
}

/* The observation's check (non-finite entries) and the gain (or drive) estimate's update. */
int fused_begin(void **p)
{
    const double *obs = F(p, P_OBS);
    for (int64_t i = 0; i < D(p, D_OBS); ++i)
        if (!isfinite(obs[i])) return NON_FINITE;
    if (D(p, D_HAS_GAIN))
        gain_update(p[P_GAIN_DIMS], p[P_GAIN_PAR], p[P_GAIN_C], p[P_GAIN_X], p[P_GAIN_ST], obs[0]);
    if (D(p, D_DRIVE))
        drive_update(p[P_GAIN_DIMS], p[P_DRIVE_PAR], p[P_GAIN_C], p[P_GAIN_X], p[P_GAIN_XU],
                     p[P_DRIVE_ST], obs[0]);
    return DONE;
}

/* controllers.mpc.LinearMPC._applied: time updates with the z the nonlinearity produced (and
   with a learned drive the volts u that produced it). */
static void applied(void **p, double z, double u)
{
    double *sc = S(p);
    if (D(p, D_HAS_GAIN)) gain_advance(p[P_GAIN_DIMS], p[P_GAIN_A], p[P_GAIN_B], p[P_GAIN_X], z);
    sc[S_Z_APPLIED] = z;
    if (D(p, D_DRIVE)) {
        gain_advance(p[P_GAIN_DIMS], p[P_GAIN_A], p[P_GAIN_B], p[P_GAIN_XU], u);
        sc[S_U_APPLIED] = u;
        sc[S_Z_PREV] = sc[S_G] * z + sc[S_B] * u;
    } else {
        sc[S_Z_PREV] = sc[S_G] * z;
    }
    bank_predict(p[P_BANK_DIMS], p[P_BANK_A], p[P_BANK_B], p[P_BANK_ST], sc[S_Z_PREV]);
}

/* The first move z_model (g z, in S_Z_MODEL; with a learned drive g z + b u, which the mixed
   map's inverse takes as it is) to volts: the compiled inverse from the memory, then the time
   updates (LinearMPC._act after _solve: LinearMPC._convert). */
int fused_finish(void **p)
{
    double *sc = S(p), *memory = F(p, P_MEMORY);
    const int64_t n_memory = D(p, D_MEMORY);
    double z_target = D(p, D_DRIVE) ? sc[S_Z_MODEL] : sc[S_Z_MODEL] / sc[S_G];
    if (!isfinite(z_target)) return NEED_INVERSE;
    double **arg = (double **)p[P_INV_ARG], **res = (double **)p[P_INV_RES];
    arg[0][0] = z_target;
    for (int64_t i = 0; i < n_memory; ++i) arg[1][i] = memory[i];
    arg[4][0] = memory[0];
    if (nls_inverse((const casadi_real **)arg, res, p[P_INV_IW], p[P_INV_W], 0)) return ERROR;
    double status = res[2][0];
    if (status == 2.0) return NEED_INVERSE;
    const double u = (double)(float)res[0][0];  /* the float32 volts the plant receives */
    if (D(p, D_SLEW)) {  /* LinearMPC._convert: outside the window, Python clips */
        double low, high;
        slew_window(p, &low, &high);
        if (!(low <= u && u <= high)) return NEED_INVERSE;
        sc[S_U_PREV] = u;
    }
    sc[S_INVERSE_STATUS] = status;
    sc[S_U] = u;
    for (int64_t i = 0; i < n_memory; ++i) memory[i] = res[3][i];
    if (D(p, D_DRIVE))  /* the network's own output at the solution */
        applied(p, (res[1][0] - sc[S_B] * res[0][0]) / sc[S_G], u);
    else
        applied(p, res[1][0], u);
    return DONE;
}

/* numpy's clip of a finite x: minimum(maximum(x, lo), hi). */
static double np_clip(double x, double lo, double hi)
{
    double m = x > lo ? x : lo;
    return m < hi ? m : hi;
}

/* The rate rows' bound: g z_rate, with a learned drive g z_rate + b S dt
   (LinearMPC._rate). */
static double drive_rate(const double *sc, int64_t drive)
{
    return drive ? sc[S_G] * sc[S_Z_RATE] + sc[S_B] * sc[S_SLEW_STEP] : sc[S_G] * sc[S_Z_RATE];
}

/* controllers.mpc.LinearMPC._set_drive with (a, b) = the drive estimate's theta of the member
   in use: every filter's x moves by the change of the model's states, d takes C dx (summed
   left to right, as controllers.observer.shift_states), the plan scales with a, z_t-1 is the
   new drive of the last input, and the mixed map's inverse and reachable range take (a, b). */
static void set_drive(void **p, double *est, int64_t filters, int64_t n, int64_t m,
                      const double *c)
{
    double *sc = S(p), *plan = F(p, P_PLAN);
    const int64_t k = ((const int64_t *)p[P_GAIN_DIMS])[0], member = D(p, D_MEMBER);
    const int64_t moves = D(p, D_MOVES);
    const double *st = F(p, P_DRIVE_ST);
    const double a = st[8 * k + member], b = st[9 * k + member];
    if (a == sc[S_G] && b == sc[S_B]) return;
    const double *xz = F(p, P_GAIN_X) + member * n, *xu = F(p, P_GAIN_XU) + member * n;
    double dx[MAX_STATES], output = 0.0;
    for (int64_t j = 0; j < n; ++j) dx[j] = (a - sc[S_G]) * xz[j] + (b - sc[S_B]) * xu[j];
    for (int64_t j = 0; j < n; ++j) output += dx[j] * c[j];
    for (int64_t f = 0; f < filters; ++f) {
        double *e = est + f * m;
        for (int64_t j = 0; j < n; ++j) e[j] += dx[j];
        e[n] -= output;
    }
    const double ratio = a / sc[S_G];
    for (int64_t i = 0; i < moves; ++i) plan[i] = plan[i] * ratio;
    sc[S_G] = a;
    sc[S_B] = b;
    sc[S_Z_PREV] = a * sc[S_Z_APPLIED] + b * sc[S_U_APPLIED];
    double **inv = (double **)p[P_INV_ARG], **reach = (double **)p[P_REACH_ARG];
    inv[5][0] = a;
    inv[5][1] = b;
    reach[3][0] = a;
    reach[3][1] = b;
}

/* controllers.mpc.LinearMPC._solve_constrained: the box QP for the vector and bounds that
   fused_solve set, in the DAQP workspace of the model in use (controllers.native.daqp_box),
   from its last active set unless the last plan was unconstrained or the last solve failed;
   then fused_finish. Without such a workspace (OSQP, or DAQP through Python), NEED_QP. */
static int fused_qp(void **p)
{
    box_qp *qp = (box_qp *)p[P_QP];
    if (qp == NULL) return NEED_QP;
    double *sc = S(p), *plan = F(p, P_PLAN);
    const double *lower = F(p, P_LOWER), *upper = F(p, P_UPPER);
    const double *g = F(p, P_Q_MATRIX), *stacked = F(p, P_STACKED);
    const int64_t moves = D(p, D_MOVES), columns = D(p, D_COLUMNS);
    for (int64_t i = 0; i < moves; ++i) {  /* q = G stacked, summed left to right */
        const double *row = g + i * columns;
        double sum = 0.0;
        for (int64_t j = 0; j < columns; ++j) sum += row[j] * stacked[j];
        qp->qp.f[i] = sum;
        qp->qp.blower[i] = lower[i];
        qp->qp.bupper[i] = upper[i];
    }
    if (D(p, D_SLEW)) {  /* the rate rows |v_k - v_k-1| <= drive_rate (BoxQP.set_rate) */
        const double rate = drive_rate(sc, D(p, D_DRIVE));
        for (int64_t i = moves; i < qp->qp.m; ++i) {
            qp->qp.blower[i] = -rate;
            qp->qp.bupper[i] = rate;
        }
    }
    const int cold = sc[S_DUALS_ANY] == 0.0 || qp->status[2];
    sc[S_QP_FLAG] = ((box_qp_solve_t)p[P_QP_SOLVE])(qp, cold);
    sc[S_QP_ITERATIONS] = (double)qp->status[1];
    sc[S_QP_RAN] = qp->status[2] ? 2.0 : 1.0;
    if (qp->status[2]) {  /* no usable solution: the last plan, shifted, inside the box */
        const double last = plan[moves - 1];
        for (int64_t i = 0; i + 1 < moves; ++i) plan[i] = np_clip(plan[i + 1], lower[i], upper[i]);
        plan[moves - 1] = np_clip(last, lower[moves - 1], upper[moves - 1]);
    } else {
        double any = 0.0;
        for (int64_t i = 0; i < moves; ++i) plan[i] = np_clip(qp->x[i], lower[i], upper[i]);
        for (int64_t i = 0; i < qp->qp.m; ++i)
            if (qp->lam[i] != 0.0) any = 1.0;
        sc[S_DUALS_ANY] = any;
    }
    sc[S_Z_MODEL] = plan[0];
    return fused_finish(p);
}

/* controllers.mpc.LinearMPC._set_gain with g = the gain estimate's value of the member in use
   (with a learned drive, set_drive instead)
   (with a slew limit, fused_qp gives the QP its rate bound g z_rate), the bank's measurement
   update, the QP's vector and bounds, the unconstrained plan and its box (and rate) test;
   inside them, fused_finish. */
int fused_solve(void **p)
{
    double *sc = S(p);
    sc[S_QP_RAN] = 0.0;
    const int64_t n = D(p, D_STATES), m = D(p, D_ESTIMATE), moves = D(p, D_MOVES);
    const int64_t *bank_dims = (const int64_t *)p[P_BANK_DIMS];
    const int64_t filters = bank_dims[0];
    double *est = F(p, P_BANK_ST), *plan = F(p, P_PLAN);
    const double *obs = F(p, P_OBS), *c = F(p, P_BANK_C);
    if (D(p, D_DRIVE)) {
        set_drive(p, est, filters, n, m, c);
    } else if (D(p, D_HAS_GAIN)) {
        const int64_t k = ((const int64_t *)p[P_GAIN_DIMS])[0];
        double g = F(p, P_GAIN_ST)[9 * k + D(p, D_MEMBER)];
        if (g != sc[S_G]) {
            double ratio = g / sc[S_G];
            for (int64_t f = 0; f < filters; ++f) {  /* rescale_states */
                double *e = est + f * m, output = 0.0;
                for (int64_t j = 0; j < n; ++j) output += e[j] * c[j];
                for (int64_t j = 0; j < n; ++j) e[j] *= ratio;
                e[n] -= (ratio - 1.0) * output;
            }
            for (int64_t i = 0; i < moves; ++i) plan[i] = plan[i] * ratio;
            sc[S_Z_PREV] *= ratio;
            sc[S_G] = g;
        }
    }
    const double y = obs[0];
    bank_correct(p[P_BANK_DIMS], p[P_BANK_PAR], p[P_BANK_C], p[P_BANK_GAINS], p[P_BANK_HLV],
                 p[P_BANK_HIV], p[P_BANK_ST], p[P_BANK_COUNTERS], p[P_BANK_COUNTS], y);
    const int64_t *counters = (const int64_t *)p[P_BANK_COUNTERS];
    sc[S_RUNAWAY] = (double)counters[3];
    /* stacked = [x; d; r_t+1 .. r_t+Np; z_t-1] (ControlTask.targets: the last preview holds) */
    double *stacked = F(p, P_STACKED);
    const double *e = est + counters[0] * m;
    for (int64_t j = 0; j < m; ++j) stacked[j] = e[j];
    const int64_t samples = D(p, D_SAMPLES), seen_max = D(p, D_OBS) - 2;
    const int64_t seen = samples < seen_max ? samples : seen_max;
    for (int64_t j = 0; j < seen; ++j) stacked[m + j] = obs[2 + j];
    for (int64_t j = seen; j < samples; ++j) stacked[m + j] = obs[D(p, D_OBS) - 1];
    stacked[m + samples] = sc[S_Z_PREV];
    /* the first move's bounds: the reachable range from the memory, sorted; the later moves'
       the range over the drive range; all times g (with a learned drive, the mixed map's) */
    double **arg = (double **)p[P_REACH_ARG], **res = (double **)p[P_REACH_RES];
    const double *memory = F(p, P_MEMORY);
    for (int64_t i = 0; i < D(p, D_MEMORY); ++i) arg[0][i] = memory[i];
    if (D(p, D_SLEW)) slew_window(p, arg[1], arg[2]);  /* LinearMPC._reachable_in_window */
    if (nls_reachable((const casadi_real **)arg, res, p[P_REACH_IW], p[P_REACH_W], 0))
        return ERROR;
    double low = res[0][0], high = res[1][0];
    if (!(low <= high)) { double t = low; low = high; high = t; }
    double *lower = F(p, P_LOWER), *upper = F(p, P_UPPER);
    const double g = sc[S_G];
    if (D(p, D_DRIVE)) {  /* LinearMPC._drive_bounds: the mixed map's range is the drive's */
        double first = g * sc[S_Z_MIN] - sc[S_B] * sc[S_U_MAX];
        double last = g * sc[S_Z_MAX] + sc[S_B] * sc[S_U_MAX];
        if (last < first) { double t = first; first = last; last = t; }
        for (int64_t i = 1; i < moves; ++i) { lower[i] = first; upper[i] = last; }
        lower[0] = low;
        upper[0] = high;
    } else {
        for (int64_t i = 1; i < moves; ++i) {
            lower[i] = g * sc[S_Z_MIN];
            upper[i] = g * sc[S_Z_MAX];
        }
        lower[0] = g * low;
        upper[0] = g * high;
    }
    if (!D(p, D_SHORTCUT)) return fused_qp(p);
    /* the unconstrained optimum -P^-1 q, summed left to right, tested against the box (in
       scratch: outside it, the QP's warm start and fallback are the last plan, as in Python) */
    const double *u = F(p, P_UNCONSTRAINED);
    double *candidate = F(p, P_SCRATCH);
    const int64_t columns = D(p, D_COLUMNS);
    int inside = 1;
    for (int64_t i = 0; i < moves; ++i) {
        const double *row = u + i * columns;
        double sum = 0.0;
        for (int64_t j = 0; j < columns; ++j) sum += row[j] * stacked[j];
        candidate[i] = sum;
        if (!(sum >= lower[i] && sum <= upper[i])) inside = 0;
    }
    if (inside && D(p, D_SLEW)) {  /* LinearMPC._rates_within */
        const double rate = drive_rate(sc, D(p, D_DRIVE));
        for (int64_t i = 1; i < moves; ++i)
            if (!(fabs(candidate[i] - candidate[i - 1]) <= rate)) inside = 0;
    }
    if (!inside) return fused_qp(p);
    for (int64_t i = 0; i < moves; ++i) plan[i] = candidate[i];
    sc[S_DUALS_ANY] = 0.0;  /* no bound is active: the optimal multipliers are zero */
    sc[S_Z_MODEL] = plan[0];
    return fused_finish(p);
}

/* controllers.gain.GainEstimate.independent_fraction_of */
static double independent_fraction(const double *st, int64_t k, int64_t index)
{
    double rho = st[3 * k + index] / py_max(st[2 * k + index], 1e-300);
    rho = py_min(py_max(rho, 0.0), 1.0 - 1e-12);
    return (1.0 - rho) / (1.0 + rho);
}

/* Whether controllers.adaptive.AdaptiveMPC._select does nothing this sample: the set the
   likelihood-ratio test keeps is the last one (P_PLAUSIBLE, one flag per member), and the
   member in use explains the data to within the sensor noise or no allowed member
   (P_ALLOWED) beats it by the test. DONE then; else NEED_SELECT (Python selects). */
static int select_unchanged(void **p)
{
    const double *sc = S(p), *st = F(p, P_GAIN_ST);
    const int64_t k = ((const int64_t *)p[P_GAIN_DIMS])[0], member = D(p, D_MEMBER);
    const double *misfit = st + 10 * k, count = st[11 * k + 1];
    const double *plausible = F(p, P_PLAUSIBLE), *allowed = F(p, P_ALLOWED);
    const double noise = sc[S_NOISE_VARIANCE], chi2 = sc[S_SWITCH_CHI2];
    int64_t index = 0;  /* numpy's argmin: the first minimum, or the first NaN */
    double best = misfit[0];
    for (int64_t i = 1; i < k && best == best; ++i)
        if (misfit[i] < best || misfit[i] != misfit[i]) { best = misfit[i]; index = i; }
    double variance = py_max(best, noise);
    double samples = count * independent_fraction(st, k, index);
    for (int64_t i = 0; i < k; ++i) {
        double kept = (misfit[i] - best) * samples / variance <= chi2;
        if (kept != plausible[i]) return NEED_SELECT;
    }
    double in_use = count * independent_fraction(st, k, member);
    double dof = py_max(in_use, 1.0), spread = 2.0 / (9.0 * dof);
    double upper = dof * pow(1.0 - spread + sc[S_NORMAL_95] * sqrt(spread), 3.0);
    if (misfit[member] * in_use / noise <= upper) return DONE;
    int64_t choice = -1;
    double lowest = 0.0;
    for (int64_t i = 0; i < k; ++i) {  /* argmin over the allowed members, numpy's way */
        if (allowed[i] == 0.0) continue;
        if (choice < 0 || (lowest == lowest && (misfit[i] < lowest || misfit[i] != misfit[i]))) {
            choice = i;
            lowest = misfit[i];
        }
    }
    if (choice < 0 || choice == member) return DONE;
    variance = py_max(misfit[choice], noise);
    samples = count * independent_fraction(st, k, choice);
    return (misfit[member] - misfit[choice]) * samples / variance > chi2 ? NEED_SELECT : DONE;
}

/* The whole step: fused_begin, the adaptive MPC's selection test, then fused_solve. */
int fused_step(void **p)
{
    int code = fused_begin(p);
    if (code != DONE) return code;
    if (D(p, D_SELECTS) && select_unchanged(p) != DONE) return NEED_SELECT;
    return fused_solve(p);
}
"""


def fused_source(inverse: Any, reachable: Any) -> str:
    """The translation unit (module docstring): the generated C of the casadi Functions
    ``inverse`` (``nls_inverse``) and ``reachable`` (``nls_reachable``), the estimator kernels
    and the step."""
    generated = generated_text("mpc_step.c", [inverse, reachable])
    return "\n".join((generated, KERNELS, DAQP_HEADER, STEP))


_LIBRARIES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def compile_step(inverse: Any) -> tuple[ctypes.CDLL | None, NativeBuild]:
    """The library of the step for a :class:`controllers.native.compiled_inverse.
    CompiledInverse` (its casadi Functions), built once per inverse object: None and the
    record of why when there is none."""
    if inverse in _LIBRARIES:
        return _LIBRARIES[inverse]
    if inverse.functions is None:
        built = None, unavailable(f"the inverse is not compiled ({inverse.backend})")
    else:
        source = fused_source(*inverse.functions)
        built = compile_source("mpc_step", source, flags=FLAGS, cache="kernels")
    _LIBRARIES[inverse] = built
    return built


def unavailable(reason: str) -> NativeBuild:
    """The record of an MPC whose step runs in numpy and Python, and why."""
    return NativeBuild("mpc_step", NUMPY, reason)


def _check_buffer(index: int, buffer: np.ndarray) -> None:
    """A table entry must point at a C-contiguous float64 or int64 array."""
    if not (buffer.flags.c_contiguous and buffer.dtype in (np.float64, np.int64)):
        raise ValueError(f"table entry {index}: needs a C-contiguous float64 or int64 array")


def _int_array(values: list[int]) -> np.ndarray:
    return np.array(values, dtype=np.int64)


class FusedStep:
    """The compiled step bound to one controller's arrays (see the module docstring).

    Parameters
    ----------
    library : ctypes.CDLL
        The library of :func:`fused_source`.
    inverse, reachable : casadi.Function
        The Functions it was generated from (for their work sizes).
    u_range : (float, float)
        Drive range (V) the inverse searches.
    parameters : numpy.ndarray
        The inverse's parameter input (:attr:`controllers.native.compiled_inverse.
        InverseMap.parameters`): written here, and with a learned drive rewritten by the step
        at each change of the drive (and by the caller after its own).
    sizes : dict
        ``observation``, ``states`` (n), ``estimate`` (n + disturbance states), ``moves``,
        ``samples``, ``columns``, ``memory``, ``shortcut`` (0 or 1), ``selects`` (1 for the
        adaptive MPC's selection test), ``members`` (its gain estimate's parts).
    slew : (float, float, float), optional
        With an amplifier's slew limit: the largest move per sample S dt (V), the drive limit
        (V) and the z rate per sample at g = 1 (:attr:`controllers.mpc.LinearMPC.z_rate`).
        The step then takes the first move's z bounds over the slew window u_t-1 +- S dt
        (u_t-1 in the scalars, written by the caller), tests the unconstrained plan's rates,
        gives the QP its rate rows and hands a first move whose volts leave the window to
        Python (``NEED_INVERSE``: :meth:`controllers.mpc.LinearMPC._convert` clips it).

    Attributes
    ----------
    observation : numpy.ndarray
        The buffer the caller writes each observation into (float64).
    scalars : array.array
        g, z_t-1, z applied, u (V), the first move g z, z_min, z_max, the inverse's status,
        the bank's runaway sample (-1: none), for the selection test the sensor noise's
        variance (um^2), the chi2 threshold and the one-sided normal quantile; then whether
        the last QP's multipliers were not all zero (its warm start), and of this step's QP
        in C: 0 none, 1 solved, 2 no usable solution (the shifted plan), DAQP's exit flag and
        its iterations; with a slew limit u_t-1 (V, updated by a step that ends in C), S dt,
        the drive limit and the z rate; with a learned drive its theta_u (``S_B``; theta_z is
        g) and the volts last applied.
    plausible, allowed : numpy.ndarray
        Per member, 1.0 where the adaptive MPC's last selection kept it plausible, and where
        it has a filter it may use on every plausible member (and its twin).
    """

    def __init__(
        self,
        library: ctypes.CDLL,
        inverse: Any,
        reachable: Any,
        u_range: tuple[float, float],
        parameters: np.ndarray,
        sizes: dict[str, int],
        slew: tuple[float, float, float] | None = None,
    ) -> None:
        self._library = library
        self.observation = np.zeros(sizes["observation"])
        self.plan = np.zeros(sizes["moves"])
        self._qp: Any = None  # the DAQP workspace the table points at (bind_qp)
        self._scratch = np.zeros(sizes["moves"])
        self.memory = np.zeros(sizes["memory"])
        self.scalars = array.array("d", [0.0] * S_COUNT)
        self.dims = _int_array([0] * D_COUNT)
        for index, key in (
            (D_OBS, "observation"),
            (D_STATES, "states"),
            (D_ESTIMATE, "estimate"),
            (D_MOVES, "moves"),
            (D_SAMPLES, "samples"),
            (D_COLUMNS, "columns"),
            (D_MEMORY, "memory"),
            (D_SHORTCUT, "shortcut"),
            (D_SELECTS, "selects"),
        ):
            self.dims[index] = sizes[key]
        self.scalars[S_U_MAX] = u_range[1]  # the drive bounds' (a learned drive's) and the slew's
        if slew is not None:
            self.dims[D_SLEW] = 1
            scalars = self.scalars
            scalars[S_SLEW_STEP], scalars[S_U_MAX], scalars[S_Z_RATE] = slew
        self.table = np.zeros(P_COUNT, dtype=np.uint64)
        self._keep: list[Any] = []  # what the table points into, kept alive
        self._point(P_OBS, self.observation)
        self._point(P_PLAN, self.plan)
        self._point(P_SCRATCH, self._scratch)
        self._point(P_MEMORY, self.memory)
        self._point(P_DIMS, self.dims)
        # The adaptive MPC's member flags (one per member of its gain estimate; 0 or 1).
        self.plausible = np.zeros(max(sizes["members"], 1))
        self.allowed = np.zeros(max(sizes["members"], 1))
        self._point(P_PLAUSIBLE, self.plausible)
        self._point(P_ALLOWED, self.allowed)
        self.table[P_SCALARS] = self.scalars.buffer_info()[0]
        self.inverse_inputs = self._casadi(inverse, (P_INV_ARG, P_INV_RES, P_INV_IW, P_INV_W))
        self.inverse_inputs[2][0], self.inverse_inputs[3][0] = u_range
        self.inverse_inputs[5][:] = parameters
        self.reach_inputs = self._casadi(
            reachable, (P_REACH_ARG, P_REACH_RES, P_REACH_IW, P_REACH_W)
        )
        self.reach_inputs[1][0], self.reach_inputs[2][0] = u_range
        self.reach_inputs[3][:] = parameters
        pointer = self.table.ctypes.data
        functions = {}
        for name in ("fused_begin", "fused_solve", "fused_finish", "fused_step"):
            function = getattr(library, name)
            function.argtypes, function.restype = [ctypes.c_void_p], ctypes.c_int
            functions[name] = function
        # Bound once: each call converts one integer argument.
        self.begin = lambda: functions["fused_begin"](pointer)
        self.solve = lambda: functions["fused_solve"](pointer)
        self.finish = lambda: functions["fused_finish"](pointer)
        self.step = lambda: functions["fused_step"](pointer)

    def _point(self, index: int, buffer: np.ndarray, *, keep: bool = True) -> None:
        """Write ``buffer``'s address into the table (``keep``: hold a reference to it, for the
        step's own buffers; the estimators' arrays are their owners')."""
        _check_buffer(index, buffer)
        self.table[index] = buffer.ctypes.data
        if keep:
            self._keep.append(buffer)

    def _casadi(self, function: Any, slots: tuple[int, int, int, int]) -> list[np.ndarray]:
        """Point the table's ``slots`` at the argument, result and work arrays of a generated
        Function (:func:`controllers.native.codegen.call_buffers`, dense); returns its input
        buffers."""
        buffers = call_buffers(self._library, function)
        self.table[list(slots)] = buffers.addresses
        self._keep.append(buffers)
        return buffers.inputs

    def bind_gain(self, gain: Any, member: int) -> None:
        """Point at a :class:`controllers.gain.GainEstimate`'s or a
        :class:`controllers.drive.DriveEstimate`'s arrays (None: no gain)."""
        self.dims[D_HAS_GAIN] = gain is not None
        self.dims[D_MEMBER] = member
        drive = hasattr(gain, "theta_u")
        self.dims[D_DRIVE] = drive
        if gain is None:
            return
        estimate = gain.gain if drive else gain  # a drive runs beside its gain estimate
        dims, par = estimate._kernel_data
        for index, buffer in (
            (P_GAIN_DIMS, dims),
            (P_GAIN_PAR, par),
            (P_GAIN_C, estimate._c),
            (P_GAIN_X, estimate._x),
            (P_GAIN_ST, estimate._state),
            (P_GAIN_A, estimate._a),
            (P_GAIN_B, estimate._b),
        ):
            self._point(index, buffer, keep=False)
        if drive:
            self._point(P_GAIN_XU, gain._xu, keep=False)
            self._point(P_DRIVE_PAR, gain._kernel_data[1], keep=False)
            self._point(P_DRIVE_ST, gain._state, keep=False)

    def bank_addresses(
        self,
        bank: Any,
        unconstrained: np.ndarray,
        stacked: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        q_matrix: np.ndarray,
    ) -> np.ndarray:
        """The table entries of an :class:`controllers.observer.ObserverBank`'s arrays, the
        plan's matrix ``-P^-1 G``, the QP's vector, its bounds and the matrix G of its linear
        term ``q = G stacked``, checked and read once
        (uint64, one per slot of :data:`BANK_SLOTS`), for :meth:`bind_addresses`: a controller
        that changes banks mid-episode reads them before the episode and binds them by a slice
        assignment. The arrays must outlive their use: their owners (bank, controller) keep
        them."""
        buffers = (
            bank._dims,
            bank._parameters,
            bank._c_aug,
            bank._gains,
            bank._half_log_var,
            bank._half_inverse_var,
            bank._state,
            bank._counters,
            bank.selection_counts,
            bank._a_aug,
            bank._b_aug,
            unconstrained,
            stacked,
            lower,
            upper,
            q_matrix,
        )
        for index, buffer in zip(BANK_SLOTS, buffers, strict=True):
            _check_buffer(index, buffer)
        return np.array([buffer.ctypes.data for buffer in buffers], dtype=np.uint64)

    def bind_addresses(self, addresses: np.ndarray) -> None:
        """Write :meth:`bank_addresses`' entries into the table."""
        self.table[BANK_SLOTS] = addresses

    def bind_qp(self, qp: Any) -> None:
        """Solve the QP in ``qp``'s DAQP workspace when it has one driven from C
        (:class:`controllers.native.daqp_box.NativeDAQP`, as
        :attr:`controllers.box_qp.DAQPBoxQP.native`); else the step hands the QP to Python
        (``NEED_QP``). The step keeps the workspace alive until the next binding, so that
        the table never points at freed memory."""
        native = getattr(qp, "native", None)
        if native is None or native.x.size != self.plan.size:
            self.table[P_QP] = 0
            self._qp = None
            return
        self._qp = native
        self.table[P_QP] = native.handle
        self.table[P_QP_SOLVE] = native.solve_address
