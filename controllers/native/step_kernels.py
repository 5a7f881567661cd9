"""The per-sample arithmetic of the MPCs' estimators in C: one ctypes call where numpy makes 30.

An MPC step runs the gain estimate's update and time update (:mod:`controllers.gain`) and the
observer bank's measurement and time updates (:class:`controllers.observer.ObserverBank`). Each
is a handful of operations on arrays of 1 to 50 entries, where numpy's cost is its call overhead
per operation, not the arithmetic (``benchmarks/results/design_measurements.md``). The kernels here
do the same operations, in the same order, in one C call each, on the estimators' own arrays
(updated in place, so that the Python objects read the same memory).

Where the results differ from numpy's: the dot products (``c . x`` of each part, each filter's
``c . estimate`` and its time update) are summed left to right here, while numpy's einsum and
matrix products may pair the terms differently, so a result may differ in its last bit (about
1e-16 relative); every other operation is the same IEEE operation on the same operands
(compiled without fused multiply-adds, :data:`controllers.native.codegen.DEFAULT_FLAGS`). The
tests hold both paths to each other step by step and over closed-loop episodes.

The library is built once per machine through :func:`controllers.native.codegen.compile_source`
(cached, digest-verified, the ``PIEZO_NATIVE`` policy applies); without it the estimators run
their numpy code, and their ``native`` records say so.
"""

from __future__ import annotations

import ctypes
import functools
from typing import Any

from controllers.native.codegen import (
    DEFAULT_FLAGS,
    NUMPY,
    NativeBuild,
    compile_source,
    native_policy,
)

__all__ = ["FLAGS", "MAX_STATES", "SOURCE", "bind", "kernels", "kernels_for"]

MAX_STATES = 64
"""Largest state size the kernels take (their time updates use a stack buffer of this size)."""

SOURCE = r"""
#include <math.h>
#include <stdint.h>

#define MAX_STATES 64

/* numpy's maximum and minimum: NaN if either operand is NaN. */
static double np_max(double a, double b) { return (a != a || b != b) ? a + b : (a < b ? b : a); }
static double np_min(double a, double b) { return (a != a || b != b) ? a + b : (a > b ? b : a); }

/* controllers.gain.GainEstimate.update: K parts of order n.
   dims = {K, n}; par = {prior precision, variance floor, low bound, high bound, z_975,
   noise bound, relative widening, relative observation rounding};
   st = {s_ss, s_sy, s_ee, s_lag, residual, mean, std, low, high, value, misfit} (K each),
   then s_yy, count, then {exact low, exact high, emptied at} (K each). */
void gain_update(const int64_t *dims, const double *par, const double *c, const double *x,
                 double *st, double y)
{
    const int64_t K = dims[0], n = dims[1];
    const double pp = par[0], floor_ = par[1], lo = par[2], hi = par[3], zc = par[4];
    double *s_ss = st, *s_sy = st + K, *s_ee = st + 2 * K, *s_lag = st + 3 * K;
    double *res = st + 4 * K, *mean = st + 5 * K, *sd = st + 6 * K, *low = st + 7 * K;
    double *high = st + 8 * K, *value = st + 9 * K, *misfit = st + 10 * K;
    double *s_yy = st + 11 * K, *count = st + 11 * K + 1;
    double *ex_lo = st + 11 * K + 2, *ex_hi = st + 12 * K + 2, *emptied = st + 13 * K + 2;
    const double eb = par[5] + par[7] * fabs(y), widen = par[6];
    *count += 1.0;
    *s_yy += y * y;
    for (int64_t k = 0; k < K; ++k) {
        double s = 0.0;
        for (int64_t j = 0; j < n; ++j) s += c[k * n + j] * x[k * n + j];
        double r = y - mean[k] * s;
        s_ee[k] += r * r;
        s_lag[k] += r * res[k];
        res[k] = r;
        s_ss[k] += s * s;
        s_sy[k] += s * y;
        double variance = np_max(s_ee[k] / *count, floor_);
        double precision = pp + s_ss[k] / variance;
        double m = (pp + s_sy[k] / variance) / precision;
        mean[k] = m;
        sd[k] = 1.0 / sqrt(precision);
        double half = zc * sd[k];
        double l = np_min(np_max(m - half, lo), hi), h = np_min(np_max(m + half, lo), hi);
        low[k] = l;
        high[k] = h;
        value[k] = np_min(np_max(1.0, l), h);
        misfit[k] = (*s_yy - 2.0 * m * s_sy[k] + m * m * s_ss[k]) / *count;
        double el, eh;
        if (s != 0.0) {
            el = (s > 0.0 ? y - eb : y + eb) / s;
            eh = (s > 0.0 ? y + eb : y - eb) / s;
            if (isfinite(el)) el = el - widen * fabs(el);
            if (isfinite(eh)) eh = eh + widen * fabs(eh);
        } else if (y != y) {
            el = eh = y;
        } else {
            el = fabs(y) <= eb ? -INFINITY : INFINITY;
            eh = -el;
        }
        ex_lo[k] = np_max(ex_lo[k], el);
        ex_hi[k] = np_min(ex_hi[k], eh);
        if (emptied[k] == 0.0 && ex_lo[k] > ex_hi[k]) emptied[k] = *count;
    }
}

/* controllers.drive.DriveEstimate._project: the box's point nearest (t1, t2) in the metric
   [[p11, p12], [p12, p22]]; box = {z_low, z_high, r_low, r_high}. */
static void drive_project(double *t1, double *t2, double p11, double p12, double p22,
                          const double *box)
{
    const double zl = box[0], zh = box[1], rl = box[2], rh = box[3];
    const double det = p11 * p22 - p12 * p12;
    const double c11 = p22 / det, c12 = -p12 / det, c22 = p11 / det;
    double cand[9][2] = {{zl, rl * zl}, {zl, rh * zl}, {zh, rl * zh}, {zh, rh * zh}};
    const double edges[4][3] = {{1.0, 0.0, zl}, {1.0, 0.0, zh}, {-rl, 1.0, 0.0}, {-rh, 1.0, 0.0}};
    for (int e = 0; e < 4; ++e) {
        const double a0 = edges[e][0], a1 = edges[e][1], c = edges[e][2];
        const double ca0 = c11 * a0 + c12 * a1, ca1 = c12 * a0 + c22 * a1;
        const double f = (a0 * *t1 + a1 * *t2 - c) / (a0 * ca0 + a1 * ca1);
        cand[4 + e][0] = *t1 - ca0 * f;
        cand[4 + e][1] = *t2 - ca1 * f;
    }
    cand[8][0] = *t1;  /* itself, when it lies on the box */
    cand[8][1] = *t2;
    double bz = cand[0][0], bu = cand[0][1], best = INFINITY;
    for (int i = 0; i < 9; ++i) {
        const double z = cand[i][0], u = cand[i][1], tol = 1e-12 * (1.0 + fabs(z));
        const int inside = zl - tol <= z && z <= zh + tol && rl * z - tol <= u && u <= rh * z + tol;
        const double dz = z - *t1, du = u - *t2;
        const double distance = dz * (p11 * dz + p12 * du) + du * (p12 * dz + p22 * du);
        if (inside && distance < best) { bz = z; bu = u; best = distance; }
    }
    *t1 = bz;
    *t2 = bu;
}

/* controllers.drive.DriveEstimate.update (after the gain estimate's): K parts of order n.
   dims = {K, n}; par = {prior z, prior u, variance floor, theta_z low, high, ratio low, high,
   chi2_2 95 %}; st = {s_ss, s_sv, s_vv, s_sy, s_vy, s_ee, mean_z, mean_u, theta_z, theta_u}
   (K each), then (unused), count. */
void drive_update(const int64_t *dims, const double *par, const double *c, const double *xz,
                  const double *xu, double *st, double y)
{
    const int64_t K = dims[0], n = dims[1];
    const double p1 = par[0], p2 = par[1], floor_ = par[2], chi2 = par[7];
    double *s_ss = st, *s_sv = st + K, *s_vv = st + 2 * K, *s_sy = st + 3 * K;
    double *s_vy = st + 4 * K, *s_ee = st + 5 * K, *mean_z = st + 6 * K, *mean_u = st + 7 * K;
    double *theta_z = st + 8 * K, *theta_u = st + 9 * K, *count = st + 10 * K + 1;
    *count += 1.0;
    for (int64_t k = 0; k < K; ++k) {
        double s = c[k * n] * xz[k * n], v = c[k * n] * xu[k * n];
        for (int64_t j = 1; j < n; ++j) {
            s += c[k * n + j] * xz[k * n + j];
            v += c[k * n + j] * xu[k * n + j];
        }
        double r = y - (mean_z[k] * s + mean_u[k] * v);
        s_ee[k] += r * r;
        s_ss[k] += s * s;
        s_sv[k] += s * v;
        s_vv[k] += v * v;
        s_sy[k] += s * y;
        s_vy[k] += v * y;
        double variance = np_max(s_ee[k] / *count, floor_);
        double p11 = p1 + s_ss[k] / variance, p12 = s_sv[k] / variance;
        double p22 = p2 + s_vv[k] / variance;
        double r1 = p1 + s_sy[k] / variance, r2 = s_vy[k] / variance;
        double det = p11 * p22 - p12 * p12;
        double m1 = (p22 * r1 - p12 * r2) / det, m2 = (p11 * r2 - p12 * r1) / det;
        mean_z[k] = m1;
        mean_u[k] = m2;
        double d1 = 1.0 - m1, d2 = -m2;
        double q = p11 * d1 * d1 + 2.0 * p12 * d1 * d2 + p22 * d2 * d2;
        double reach = q > chi2 ? sqrt(chi2 / np_max(q, 1e-300)) : 1.0;
        double t1 = m1 + reach * d1, t2 = m2 + reach * d2;
        if (!(par[3] <= t1 && t1 <= par[4] && par[5] * t1 <= t2 && t2 <= par[6] * t1))
            drive_project(&t1, &t2, p11, p12, p22, par + 3);
        theta_z[k] = t1;
        theta_u[k] = t2;
    }
}

/* controllers.gain.GainEstimate.advance: x_k <- a_k x_k + b_k z, K parts of order n. */
void gain_advance(const int64_t *dims, const double *a, const double *b, double *x, double z)
{
    const int64_t K = dims[0], n = dims[1];
    double next[MAX_STATES];
    for (int64_t k = 0; k < K; ++k) {
        const double *ak = a + k * n * n, *xk = x + k * n;
        for (int64_t i = 0; i < n; ++i) {
            double sum = 0.0;
            for (int64_t j = 0; j < n; ++j) sum += ak[i * n + j] * xk[j];
            next[i] = sum + b[k * n + i] * z;
        }
        for (int64_t i = 0; i < n; ++i) x[k * n + i] = next[i];
    }
}

/* controllers.observer.ObserverBank.correct: F filters of state size m.
   dims = {F, m, fallback, persistence}; par = {keep, guard keep, NIS limit, correlation};
   st = {estimates (F x m), score, mean NIS, mean lag, last innovation, penalty} (F each);
   counters = {selected, samples, suspect run, runaway at (-1: none)}; counts: F. */
void bank_correct(const int64_t *dims, const double *par, const double *c, const double *gains,
                  const double *half_log_var, const double *half_inverse_var, double *st,
                  int64_t *counters, int64_t *counts, double y)
{
    const int64_t F = dims[0], m = dims[1], fallback = dims[2], persistence = dims[3];
    const double keep = par[0], new_ = 1.0 - par[0], gkeep = par[1], gnew = 1.0 - par[1];
    double *est = st, *score = st + F * m, *nis = score + F, *lag = nis + F;
    double *last = lag + F, *penalty = last + F;
    for (int64_t f = 0; f < F; ++f) {
        double *e = est + f * m;
        double predicted = 0.0;
        for (int64_t j = 0; j < m; ++j) predicted += e[j] * c[j];
        double innovation = y - predicted;
        for (int64_t j = 0; j < m; ++j) e[j] += gains[f * m + j] * innovation;
        double log_likelihood = -half_log_var[f] - innovation * innovation * half_inverse_var[f];
        score[f] = keep * score[f] + new_ * log_likelihood;
        double normalised = 2.0 * half_inverse_var[f] * innovation;
        nis[f] = gkeep * nis[f] + gnew * normalised * innovation;
        lag[f] = gkeep * lag[f] + gnew * normalised * last[f];
        last[f] = innovation;
    }
    counters[1] += 1;
    if (counters[3] < 0) {
        /* numpy's argmax: the first maximum, or the first NaN */
        int64_t best = 0;
        double top = score[0] + penalty[0];
        for (int64_t f = 1; f < F && top == top; ++f) {
            double v = score[f] + penalty[f];
            if (v > top || v != v) { top = v; best = f; }
        }
        double n = nis[best];
        int suspect = best != fallback && n > par[2] && lag[best] < par[3] * n;
        counters[2] = suspect ? counters[2] + 1 : 0;
        if (counters[2] >= persistence) {
            counters[3] = counters[1] - 1 > 0 ? counters[1] - 1 : 0;
            counters[0] = fallback;
        } else {
            counters[0] = best;
        }
    }
    counts[counters[0]] += 1;
}

/* controllers.observer.ObserverBank.predict: each filter's estimate e <- a e + b z. */
void bank_predict(const int64_t *dims, const double *a, const double *b, double *est, double z)
{
    const int64_t F = dims[0], m = dims[1];
    double next[MAX_STATES];
    for (int64_t f = 0; f < F; ++f) {
        double *e = est + f * m;
        for (int64_t i = 0; i < m; ++i) {
            double sum = 0.0;
            for (int64_t j = 0; j < m; ++j) sum += e[j] * a[i * m + j];
            next[i] = sum + b[i] * z;
        }
        for (int64_t i = 0; i < m; ++i) e[i] = next[i];
    }
}
"""

FLAGS = ("-O2", *DEFAULT_FLAGS[1:])
"""The kernels' compiler flags: optimised loops, still no fused multiply-adds (see
:data:`controllers.native.codegen.DEFAULT_FLAGS`)."""

_P = ctypes.c_void_p
_SIGNATURES = {
    "gain_update": [_P] * 5 + [ctypes.c_double],
    "gain_advance": [_P] * 4 + [ctypes.c_double],
    "drive_update": [_P] * 6 + [ctypes.c_double],
    "bank_correct": [_P] * 9 + [ctypes.c_double],
    "bank_predict": [_P] * 4 + [ctypes.c_double],
}


@functools.lru_cache(maxsize=3)
def _build(policy: str) -> tuple[ctypes.CDLL | None, NativeBuild]:
    library, build = compile_source("step_kernels", SOURCE, flags=FLAGS)
    if library is not None:
        for name, argtypes in _SIGNATURES.items():
            function = getattr(library, name)
            function.argtypes, function.restype = argtypes, None
    return library, build


def bind(function: Any, *arrays: Any) -> Any:
    """``function`` (a kernel of the library) with the addresses of ``arrays`` as its leading
    arguments: what remains is the per-sample scalars. The arrays must outlive the binding
    (their owners keep them)."""
    return functools.partial(function, *(array.ctypes.data for array in arrays))


def kernels() -> tuple[Any, NativeBuild]:
    """The compiled kernels (None without native code) and the record of their build, once
    per process and ``PIEZO_NATIVE`` policy."""
    return _build(native_policy())


def kernels_for(states: int) -> tuple[Any, NativeBuild]:
    """:func:`kernels` for an estimator of ``states`` states; beyond :data:`MAX_STATES` none,
    and the record that says numpy runs it, and why."""
    if states <= MAX_STATES:
        return kernels()
    reason = f"{states} states, more than the kernels' {MAX_STATES}: numpy runs the estimator"
    return None, NativeBuild("step_kernels", NUMPY, reason)
