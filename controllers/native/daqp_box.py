"""DAQP's C solver called from C: the box QP's workspace without Python between the steps.

:class:`controllers.box_qp.DAQPBoxQP` solves the MPCs' box QP with DAQP (Arnstrom, Bemporad and
Axehill, IEEE TAC 67(8), 2022). Through DAQP's Python interface a solve costs a few
microseconds of DAQP and tens of Python and Cython: the arrays' conversions, the result's
dictionary. On a 10 kHz loop that is not the median's problem but the worst case's: the QP runs
only on the samples where a bound is active (a step of the reference entering the preview),
after thousands of steps that did not touch it, and the cold Python path then costs 100-250 us
against a deadline of 100 us (``benchmarks/results/controller_latency.md`` has the history).

This module calls the same DAQP, the library that the ``daqp`` package ships compiled, from a
small C wrapper (:data:`HEADER`, :data:`SOURCE`) whose workspace the compiled MPC step
(:mod:`controllers.native.fused_step`) solves in place, with no Python in between. Nothing is
reimplemented: the wrapper makes the calls DAQP's own Python interface makes, in the same
order, on the same data (set-up with the default settings, then the iteration limit; each
solve updates the linear term and the bounds, and the constraints' states where the solve
starts from no active set), so that its solutions are DAQP's to the bit; the tests hold the two
to equality on random box QPs, cold and warm, with and without general rows.

How DAQP is reached. The ``daqp`` extension module exports its C functions; their addresses are
read with ctypes and handed to the wrapper (no link against the extension). The workspace
struct is opaque here except for two facts, read from the headers of the version in
:data:`LAYOUTS`: its size, and where it keeps its settings pointer. Both are checked before the
first use in a process (:func:`library`): after DAQP allocates the settings of a zeroed
workspace, the only non-zero word must be at the recorded offset and point to DAQP's defaults;
every workspace is allocated with 4 kB of slack past the recorded size, filled with a canary
that DAQP's set-up and solve must leave intact; and solves must equal the Python interface's
to the bit. A ``daqp`` whose version is not in
:data:`LAYOUTS`, or one that fails a check, is not called this way: the QP then runs through the
Python interface, and the MPC's ``describe()["native"]["daqp_box_qp"]`` record says why
(nothing falls back silently). The structs that are DAQP's public interface (the problem, the
settings' ``iter_limit``, the result) are declared in :data:`HEADER` as the headers give them.

The workspaces driven from C are those of a fixed Hessian (the linear MPCs',
:class:`controllers.box_qp.DAQPBoxQP` with ``hessian``); the NMPC, whose Hessian changes with
every linearisation, keeps DAQP's Python interface.
"""

from __future__ import annotations

import ctypes
import functools
import weakref
from dataclasses import dataclass
from importlib.metadata import version

import daqp
import numpy as np

from controllers.native.codegen import NUMPY, NativeBuild, compile_source, native_policy
from controllers.native.step_kernels import FLAGS

__all__ = [
    "HEADER",
    "LAYOUTS",
    "OUT_OF_MEMORY",
    "SOURCE",
    "Layout",
    "NativeDAQP",
    "SetupRefused",
    "build_record",
    "library",
]


OUT_OF_MEMORY = -100
"""The set-up's flag when the wrapper found no memory for the workspace (not a DAQP flag)."""


@dataclass(frozen=True)
class Layout:
    """What the wrapper must know of one DAQP version's workspace (bytes).

    Attributes
    ----------
    workspace : int
        ``sizeof(DAQPWorkspace)``.
    settings_offset : int
        ``offsetof(DAQPWorkspace, settings)``.
    """

    workspace: int
    settings_offset: int


LAYOUTS = {"0.11.0": Layout(workspace=328, settings_offset=224)}
"""DAQP versions whose workspace layout this wrapper knows (read from each version's
``csrc/include/types.h`` with its default double precision, compiled on x86-64 Linux; other
platforms rely on the checks in :func:`library`)."""

HEADER = r"""
#include <stddef.h>
#include <stdint.h>

/* DAQP's public problem, settings and result structs (csrc/include/types.h, api.h). */
typedef struct {
    int n, m, ms;
    double *H, *f, *A, *bupper, *blower;
    int *sense;
    int *break_points;
    int nh;
    int problem_type;
} daqp_problem;

typedef struct {
    double primal_tol, dual_tol, zero_tol, pivot_tol, progress_tol;
    int cycle_tol;
    int iter_limit;
    /* later fields are not read or written here */
} daqp_settings_head;

typedef struct {
    double *x, *lam;
    double fval, soft_slack;
    int exitflag, iter, nodes;
    double solve_time, setup_time;
} daqp_result;

/* DAQP's update masks and its constraint state "active" (csrc/include/constants.h). */
enum { DAQP_UPDATE_v = 4, DAQP_UPDATE_d = 8, DAQP_UPDATE_sense = 16 };

/* The functions the wrapper calls, in the order of box_qp.functions. */
enum { FN_SETUP, FN_UPDATE, FN_SOLVE, FN_ALLOCATE_SETTINGS, FN_DEFAULT_SETTINGS,
       FN_FREE_WORKSPACE, FN_FREE_LDP, FN_COUNT };

/* One box QP: DAQP's workspace, the problem it was set up on, and the buffers (the caller's)
   that the solves read and write. status: DAQP's exit flag, its iterations, whether the last
   solve gave no usable solution (flag <= 0 or a non-finite x: the next starts cold), and
   whether DAQP refused the data at the update (crossed bounds: no solve ran). */
typedef struct {
    void *functions[FN_COUNT];
    void *work;
    daqp_problem qp;
    int *sense;
    int *no_active_set;
    double *x, *lam;
    int64_t *status;
} box_qp;

typedef int (*box_qp_solve_t)(box_qp *, int);
"""

SOURCE = (
    HEADER
    + r"""
#include <math.h>
#include <stdlib.h>
#include <string.h>

typedef int (*setup_t)(daqp_problem *, void *, double *, int);
typedef int (*update_t)(int, void *, daqp_problem *);
typedef void (*solve_t)(daqp_result *, void *);
typedef void (*workspace_t)(void *);

/* Every workspace is allocated with SLACK bytes past the recorded size, filled with CANARY:
   were DAQP's workspace larger than recorded, its writes would land there (checked by
   box_qp_layout) instead of past the allocation. SLACK: 12 times the recorded 328 bytes. */
enum { SLACK = 4096, CANARY = 0xA5 };

static void *workspace_alloc(int64_t bytes)
{
    unsigned char *work = malloc(bytes + SLACK);
    if (work == NULL) return NULL;
    memset(work, 0, bytes);
    memset(work + bytes, CANARY, SLACK);
    return work;
}

static int slack_intact(const void *work, int64_t bytes)
{
    const unsigned char *tail = (const unsigned char *)work + bytes;
    for (int i = 0; i < SLACK; ++i)
        if (tail[i] != CANARY) return 0;
    return 1;
}

/* Whether the layout is the one DAQP uses. (1) In a zeroed workspace of `bytes`, DAQP's
   allocation of its settings writes one pointer, at `offset`, to its defaults (the head this
   file declares: the fields up to iter_limit). (2) DAQP's set-up and a solve of a small QP
   write nothing past `bytes`. 1 if so, else 0; nothing is freed that DAQP did not allocate
   (a workspace that fails a check is leaked rather than freed through a wrong layout). */
int box_qp_layout(void **functions, int64_t bytes, int64_t offset)
{
    if (bytes % sizeof(void *) || offset % sizeof(void *) || offset + sizeof(void *) > bytes)
        return 0;
    void **work = workspace_alloc(bytes);
    unsigned char *defaults = calloc(1, SLACK);
    int ok = work != NULL && defaults != NULL;
    if (ok) {
        ((workspace_t)functions[FN_ALLOCATE_SETTINGS])(work);
        ((workspace_t)functions[FN_DEFAULT_SETTINGS])(defaults);
        for (int64_t i = 0; i < bytes / (int64_t)sizeof(void *); ++i)
            if ((work[i] != NULL) != (i == offset / (int64_t)sizeof(void *))) ok = 0;
        void *found = work[offset / sizeof(void *)];
        if (!ok || !slack_intact(work, bytes) ||
            memcmp(found, defaults, sizeof(daqp_settings_head)) != 0) {
            free(defaults);
            return 0;
        }
        double H[4] = {2.0, 0.5, 0.5, 1.0}, f[2] = {-4.0, 3.0};
        double upper[2] = {1.0, 1.0}, lower[2] = {-1.0, -1.0}, x[2], lam[2];
        int sense[2] = {0, 0};
        daqp_problem qp = {2, 2, 2, H, f, NULL, upper, lower, sense, NULL, 0, 0};
        double setup_time = 0.0;
        int flag = ((setup_t)functions[FN_SETUP])(&qp, work, &setup_time, 0);
        if (!slack_intact(work, bytes)) {
            free(defaults);
            return 0;
        }
        if (flag >= 0) {
            daqp_result result = {x, lam, 0.0, 0.0, 0, 0, 0, 0.0, 0.0};
            ((solve_t)functions[FN_SOLVE])(&result, work);
            ok = slack_intact(work, bytes) && result.exitflag > 0;
            if (!ok) {
                free(defaults);
                return 0;
            }
            ((workspace_t)functions[FN_FREE_WORKSPACE])(work);
            ((workspace_t)functions[FN_FREE_LDP])(work);
        } else {
            ok = 0;
            ((workspace_t)functions[FN_FREE_WORKSPACE])(work);
            free(found);  /* DAQP's failed set-up drops the settings it did not allocate */
        }
    }
    free(defaults);
    free(work);
    return ok;
}

/* DAQP's set-up of min 1/2 v'Hv + f'v s.t. blower <= [v; A v] <= bupper (ms = n simple
   bounds, m - n rows of A), with the default settings and then iter_limit (DAQP's Python
   Model: setup, then settings). Returns the handle, or NULL with status[0] = DAQP's flag
   (-100: out of memory). */
box_qp *box_qp_new(void **functions, int64_t bytes, int64_t offset, int n, int m, double *H,
                   double *f, double *A, double *bupper, double *blower, int *sense,
                   int *no_active_set, double *x, double *lam, int64_t *status, int iter_limit)
{
    box_qp *b = calloc(1, sizeof(box_qp));
    void *work = workspace_alloc(bytes);
    status[0] = -100;
    if (b == NULL || work == NULL) { free(b); free(work); return NULL; }
    memcpy(b->functions, functions, sizeof(b->functions));
    b->work = work;
    b->qp = (daqp_problem){n, m, n, H, f, m > n ? A : NULL, bupper, blower, sense, NULL, 0, 0};
    b->sense = sense;
    b->no_active_set = no_active_set;
    b->x = x;
    b->lam = lam;
    b->status = status;
    ((workspace_t)functions[FN_ALLOCATE_SETTINGS])(work);
    void *settings = *(void **)((char *)work + offset);
    double setup_time = 0.0;
    int flag = ((setup_t)functions[FN_SETUP])(&b->qp, work, &setup_time, 0);
    status[0] = flag;
    if (flag < 0) {
        /* DAQP's failed set-up frees its own arrays and drops the settings it did not
           allocate (the pointer, not the memory): free them here. */
        ((workspace_t)functions[FN_FREE_WORKSPACE])(work);
        ((workspace_t)functions[FN_FREE_LDP])(work);
        if (*(void **)((char *)work + offset) == NULL) free(settings);
        free(work);
        free(b);
        return NULL;
    }
    ((daqp_settings_head *)settings)->iter_limit = iter_limit;
    status[1] = status[2] = status[3] = 0;
    return b;
}

/* One solve with the linear term and bounds in the handle's buffers (DAQP's Python Model:
   update(f, blower, bupper[, sense = no active set when cold]), then solve). Returns DAQP's
   exit flag (the update's, if it refused the data). */
int box_qp_solve(box_qp *b, int cold)
{
    int mask = DAQP_UPDATE_v | DAQP_UPDATE_d;
    if (cold) {
        b->qp.sense = b->no_active_set;
        mask |= DAQP_UPDATE_sense;
    }
    int flag = ((update_t)b->functions[FN_UPDATE])(mask, b->work, &b->qp);
    if (flag < 0) {
        b->status[0] = flag;
        b->status[1] = 0;
        b->status[2] = 1;
        b->status[3] = 1;
        return flag;
    }
    daqp_result result = {b->x, b->lam, 0.0, 0.0, 0, 0, 0, 0.0, 0.0};
    ((solve_t)b->functions[FN_SOLVE])(&result, b->work);
    int usable = result.exitflag > 0;
    for (int i = 0; usable && i < b->qp.n; ++i)
        if (!isfinite(b->x[i])) usable = 0;
    b->status[0] = result.exitflag;
    b->status[1] = result.iter;
    b->status[2] = !usable;
    b->status[3] = 0;
    return result.exitflag;
}

void box_qp_free(box_qp *b)
{
    if (b == NULL) return;
    ((workspace_t)b->functions[FN_FREE_WORKSPACE])(b->work);
    ((workspace_t)b->functions[FN_FREE_LDP])(b->work);
    free(b->work);
    free(b);
}
"""
)

_FUNCTIONS = (
    "setup_daqp_main",
    "daqp_update_ldp",
    "daqp_solve",
    "allocate_daqp_settings",
    "daqp_default_settings",
    "free_daqp_workspace",
    "free_daqp_ldp",
)
"""DAQP's exported C functions the wrapper calls (the order of its ``FN_`` enum)."""


@functools.cache
def _bound_under(
    policy: str,
) -> tuple[ctypes.CDLL | None, NativeBuild, tuple[int, ...], Layout | None]:
    """The wrapper's library, its record, DAQP's function addresses and layout, once per
    process and ``PIEZO_NATIVE`` policy (see the module docstring for the checks)."""
    found = version("daqp")
    layout = LAYOUTS.get(found)
    if layout is None:
        known = ", ".join(sorted(LAYOUTS))
        reason = (
            f"daqp {found}: its workspace layout is not known to this wrapper (known: {known}); "
            "the QP runs through daqp's Python interface"
        )
        return None, NativeBuild("daqp_box_qp", NUMPY, reason), (), None
    try:
        exported = ctypes.CDLL(daqp.__file__)
        addresses = tuple(
            ctypes.cast(getattr(exported, name), ctypes.c_void_p).value for name in _FUNCTIONS
        )
    except (OSError, AttributeError) as exc:
        reason = (
            f"daqp's C functions are not reachable ({exc}); "
            "the QP runs through its Python interface"
        )
        return None, NativeBuild("daqp_box_qp", NUMPY, reason), (), None
    lib, build = compile_source("daqp_box_qp", SOURCE, flags=FLAGS, cache="kernels")
    if lib is None:
        return None, build, (), None
    lib.box_qp_layout.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64]
    lib.box_qp_layout.restype = ctypes.c_int
    lib.box_qp_new.argtypes = (
        [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64]
        + [ctypes.c_int] * 2
        + [ctypes.c_void_p] * 10
        + [ctypes.c_int]
    )
    lib.box_qp_new.restype = ctypes.c_void_p
    lib.box_qp_solve.argtypes = [ctypes.c_void_p, ctypes.c_int]
    lib.box_qp_solve.restype = ctypes.c_int
    lib.box_qp_free.argtypes = [ctypes.c_void_p]
    lib.box_qp_free.restype = None
    table = (ctypes.c_void_p * len(addresses))(*addresses)
    if not lib.box_qp_layout(table, layout.workspace, layout.settings_offset):
        reason = (
            f"daqp {found}: its workspace does not have the recorded layout; "
            "the QP runs through daqp's Python interface"
        )
        return None, _refused(build, reason), (), None
    bound = lib, build, addresses, layout
    mismatch = _self_check(bound)
    if mismatch:
        reason = f"daqp {found}: {mismatch}; the QP runs through daqp's Python interface"
        return None, _refused(build, reason), (), None
    return bound


def _self_check(bound: tuple) -> str:
    """ "" when the wrapper's solves equal DAQP's Python interface's to the bit on a fixed
    problem (cold and warm starts, simple bounds and general rows), else what differed."""
    rng = np.random.default_rng(20221)
    n = 8
    factor = rng.normal(size=(n, n))
    hessian = factor @ factor.T + n * np.eye(n)
    rows = np.eye(n - 1, n, 1) - np.eye(n - 1, n)
    for general in (False, True):
        a = rows if general else np.zeros((0, n))
        low = np.r_[-np.ones(n), -0.3 * np.ones(a.shape[0])]
        high = np.r_[np.ones(n), 0.3 * np.ones(a.shape[0])]
        native = NativeDAQP(hessian, a, low, high, 50, _with=bound)
        model = daqp.Model()
        model.setup(hessian.copy(), np.zeros(n), a, high.copy(), low.copy())
        model.settings = {"iter_limit": 50}
        for k in range(6):
            q = 20.0 * rng.normal(size=n)
            cold = k % 3 == 0
            data = {"f": q, "blower": low, "bupper": high}
            if cold:
                data["sense"] = np.zeros(low.size, dtype=np.intc)
            model.update(**data)
            x, _, flag, info = model.solve()
            got = native.solve(q, cold)
            if got != (int(flag), int(info["iterations"])) or not (
                np.array_equal(x, native.x) and np.array_equal(info["lam"], native.lam)
            ):
                return "its C solve differs from its Python interface's on a check problem"
    return ""


def _bound() -> tuple[ctypes.CDLL | None, NativeBuild, tuple[int, ...], Layout | None]:
    """:func:`_bound_under` the ``PIEZO_NATIVE`` policy in force now (``off`` switches the
    wrapper off for the QPs set up after it, as for every other native build)."""
    return _bound_under(native_policy())


def _refused(build: NativeBuild, reason: str) -> NativeBuild:
    """The record of a compiled wrapper that is not used, and why."""
    return NativeBuild(
        build.function, NUMPY, reason, build.compiler, build.flags, build.key, build.library,
        build.sha256, build.compiler_output,
    )  # fmt: skip


def library() -> ctypes.CDLL | None:
    """The wrapper's library when DAQP can be called from C in this process, else None."""
    return _bound()[0]


def build_record() -> NativeBuild:
    """Whether the box QP runs DAQP from C, and why not if it does not (for ``describe()``)."""
    return _bound()[1]


class SetupRefused(ValueError):
    """DAQP refused a problem at set-up; ``flag`` is its exit flag."""

    def __init__(self, flag: int) -> None:
        super().__init__(f"DAQP refused the QP at set-up (exit flag {flag})")
        self.flag = flag


class NativeDAQP:
    """One box QP's DAQP workspace driven by the C wrapper (see the module docstring).

    ``min 1/2 v' H v + f' v  s.t.  lower <= [v; A v] <= upper``.

    Parameters
    ----------
    hessian : numpy.ndarray
        H (n, n), symmetric positive definite.
    rows : numpy.ndarray
        A (m - n, n), the general rows (may have no rows).
    lower, upper : numpy.ndarray
        Bounds of the m constraints at set-up.
    iter_limit : int
        DAQP's iteration limit.

    Raises
    ------
    RuntimeError
        Without the wrapper (:func:`library` is None): check it first.
    SetupRefused
        DAQP refused the problem at set-up (its exit flag is the error's ``flag``).
    """

    def __init__(
        self,
        hessian: np.ndarray,
        rows: np.ndarray,
        lower: np.ndarray,
        upper: np.ndarray,
        iter_limit: int,
        *,
        _with: tuple | None = None,
    ) -> None:
        lib, _, addresses, layout = _bound() if _with is None else _with
        if lib is None or layout is None:
            raise RuntimeError(f"DAQP cannot be called from C here: {build_record().reason}")
        n = hessian.shape[0]
        m = lower.size
        self.hessian = np.array(hessian, dtype=float, order="C")
        self.rows = np.array(rows, dtype=float, order="C").reshape(m - n, n)
        self.f = np.zeros(n)
        self.lower = np.array(lower, dtype=float)
        self.upper = np.array(upper, dtype=float)
        self.sense = np.zeros(m, dtype=np.intc)
        self.no_active_set = np.zeros(m, dtype=np.intc)
        self.x = np.zeros(n)
        self.lam = np.zeros(m)
        self.status = np.zeros(4, dtype=np.int64)
        table = (ctypes.c_void_p * len(addresses))(*addresses)
        rows_address = self.rows.ctypes.data if m > n else None
        handle = lib.box_qp_new(
            table, layout.workspace, layout.settings_offset, n, m,
            self.hessian.ctypes.data, self.f.ctypes.data, rows_address,
            self.upper.ctypes.data, self.lower.ctypes.data, self.sense.ctypes.data,
            self.no_active_set.ctypes.data, self.x.ctypes.data, self.lam.ctypes.data,
            self.status.ctypes.data, int(iter_limit),
        )  # fmt: skip
        if not handle:
            raise SetupRefused(int(self.status[0]))
        self.handle = handle
        self._solve = lib.box_qp_solve
        self.solve_address = ctypes.cast(lib.box_qp_solve, ctypes.c_void_p).value
        """Address of the wrapper's ``box_qp_solve`` (the compiled MPC step calls it with
        :attr:`handle`)."""
        weakref.finalize(self, lib.box_qp_free, handle)

    def __reduce__(self):
        raise TypeError("a DAQP workspace holds C memory: it cannot be copied or pickled")

    @property
    def failed(self) -> bool:
        """Whether the last solve gave no usable solution (the next then starts cold)."""
        return bool(self.status[2])

    @property
    def refused(self) -> bool:
        """Whether DAQP refused the last solve's data at the update (no solve ran)."""
        return bool(self.status[3])

    def solve(self, q: np.ndarray, cold: bool) -> tuple[int, int]:
        """Solve for the linear term ``q`` and the bounds in :attr:`lower`/:attr:`upper`
        (starting from no active set when ``cold``, else from the last solve's): DAQP's exit
        flag and iterations; the solution is in :attr:`x` and :attr:`lam`."""
        self.f[:] = q
        flag = self._solve(self.handle, int(cold))
        return flag, int(self.status[1])
