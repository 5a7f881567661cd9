"""Exact zero-order-hold discretisation of the bender's linear dynamics, with modal reduction.

The beam is linear time-invariant and the drive is held constant over a sample, so the
step is exact: each mode k of the FE model (plus the optional creep states that feed it) is
discretised once with the matrix exponential of the augmented matrix [[A, B], [0, 0]] dt, and
a step is then one matrix-vector product. No ODE solver runs in the loop; any dt is stable.

Modal reduction (exact to ``tolerance``). Under stiffness-proportional damping the high FE
modes are overdamped (zeta_k = beta omega_k / 2 grows with frequency) and their discrete
transition blocks are ~1e-11 or smaller: whatever state they hold is gone one sample later.
Such a mode's state at step k+1 is, to that accuracy, its one-step response to the inputs
at step k, so it is replaced by what the outputs need of it: its contribution to the tip
deflection and tip rotation, carried as two extra states. A 10-element beam (40 states)
shrinks to 2 x 3 slow-mode states + 2 at dt = 1 ms with differences ~1e-14 m. Which modes
are dropped depends on dt (fewer at small dt), so the model stays exact at every dt.

Creep (optional): Kelvin-Voigt terms x_i' = (u_eff - x_i) / tau_i with the beam driven by
u_eff + sum_i c_i x_i: the static gain grows by c_i per decade of time around each tau_i,
which gives the logarithmic creep (1-2 % per decade) of piezo ceramics.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg

from piezo_env.checks import require_number
from piezo_env.fem import BeamFE

__all__ = ["Creep", "DiscreteBender", "discretize"]


@dataclass(frozen=True)
class Creep:
    """Linear creep as Kelvin-Voigt terms.

    Parameters
    ----------
    time_constants : tuple of float
        tau_i (s), one per decade.
    weights : tuple of float
        c_i (-): the static gain grows by c_i around t ~ tau_i (1.5 % per decade by default).
    """

    time_constants: tuple[float, ...] = (0.01, 0.1, 1.0, 10.0, 100.0)
    weights: tuple[float, ...] = (0.015, 0.015, 0.015, 0.015, 0.015)

    def __post_init__(self) -> None:
        for name in ("time_constants", "weights"):  # tuples: the settings stay as given
            try:
                values = tuple(float(v) for v in getattr(self, name))
            except (TypeError, ValueError):
                raise ValueError(
                    f"Creep.{name} must be a sequence of numbers, got {getattr(self, name)!r}"
                ) from None
            object.__setattr__(self, name, values)
        if len(self.time_constants) != len(self.weights):
            raise ValueError("creep time_constants and weights must have equal length")
        if any(t <= 0 for t in self.time_constants) or any(c < 0 for c in self.weights):
            raise ValueError("creep time constants must be > 0 s and weights >= 0")

    @property
    def size(self) -> int:
        """Number of creep states."""
        return len(self.time_constants)


@dataclass(frozen=True)
class DiscreteBender:
    """Reduced exact discrete model from effective voltage u_eff (V) to tip outputs.

    State s = [creep states (V), (eta_k, eta_k') of the kept modes, fast tip deflection (m),
    fast tip rotation (rad)]. One step is ``[s_next; y_next; theta_next] = step_matrix @ [s; u]``.

    Attributes
    ----------
    dt : float
        Sample time (s).
    step_matrix : ndarray, shape (n_s + 2, n_s + 1)
        [[A, B], [C_y A, C_y B], [C_theta A, C_theta B]]: next state and next outputs.
    output_matrix : ndarray, shape (2, n_s)
        Rows giving the tip deflection (m) and tip rotation (rad) from the state.
    kept_modes : ndarray of int
        Indices of the FE modes carried as states.
    nodal_matrix : ndarray, shape (n + 1, n_s)
        Nodal deflections (m, root first) from the kept modes' states (for drawing).
    n_creep : int
        Number of creep states at the start of the state vector.
    """

    dt: float
    step_matrix: np.ndarray
    output_matrix: np.ndarray
    kept_modes: np.ndarray
    nodal_matrix: np.ndarray
    n_creep: int

    @property
    def n_states(self) -> int:
        """Length of the reduced state vector."""
        return self.step_matrix.shape[1] - 1

    @property
    def a(self) -> np.ndarray:
        """State transition matrix A."""
        return self.step_matrix[: self.n_states, : self.n_states]

    @property
    def b(self) -> np.ndarray:
        """Input vector B (per volt of u_eff)."""
        return self.step_matrix[: self.n_states, -1]

    def state_space_matrices(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(A, B, C, D) from u_eff (V) to the tip deflection (um), copies: ``x_t+1 = A x_t +
        B u_eff,t``, ``y_t = C x_t``, D = 0 (:meth:`piezo_env.PiezoBenderModel.
        state_space_matrices`)."""
        c = self.output_matrix[:1] * 1e6
        return self.a.copy(), self.b.reshape(-1, 1).copy(), c, np.zeros((1, 1))

    def square_step_matrix(self) -> np.ndarray:
        """Step matrix on [state, u_eff, unused] giving [next state, y, theta] (square).

        Writing the next u_eff over y turns a product into the next input, so a stepping loop
        ping-pongs between two buffers instead of copying the state.
        """
        n = self.n_states
        square = np.zeros((n + 2, n + 2))
        square[:, : n + 1] = self.step_matrix
        return square

    def static_state(self, u_eff: float) -> np.ndarray:
        """Equilibrium state under a constant effective voltage (V)."""
        n = self.n_states
        return scipy.linalg.solve(np.eye(n) - self.a, self.b * u_eff)

    def simulate(self, u_eff: np.ndarray, state: np.ndarray | None = None) -> np.ndarray:
        """Tip deflection (m) for a u_eff sequence (V), y[k] after applying u_eff[k]."""
        s = np.zeros(self.n_states) if state is None else np.array(state, dtype=float)
        out = np.empty(len(u_eff))
        su = np.empty(self.n_states + 1)
        for i, u in enumerate(u_eff):
            su[:-1] = s
            su[-1] = u
            nxt = self.step_matrix @ su
            s = nxt[:-2]
            out[i] = nxt[-2]
        return out

    def mode_error_bounds(self, limit: float = np.inf) -> np.ndarray:
        """For each kept mode, a proven bound of the tip-deflection error (m per V of the
        largest |u_eff|) made by carrying it as its one-step response instead
        (:meth:`without_modes`), the way :func:`discretize` treats a mode below its tolerance.

        The mode's displacement is ``eta_t+1 = sum_j>=0 e' A_k^j (a_k x_t-j + b_k u_t-j)``
        (``A_k`` its 2 x 2 block, ``a_k`` its coupling to the creep states x, ``b_k`` its input
        column); the one-step response keeps the term j = 0. Each creep state is a unit-gain
        first-order low-pass of u_eff (a convex combination of its past values) and never
        exceeds the largest |u_eff|, so the rest, times the mode's tip gain c_k, is at most
        ``sum_j>=1 |c_k| (|e' A_k^j b_k| + sum_m |e' A_k^j a_k,m|)`` per volt (a_k,m: the
        coupling column of creep state m). The terms j <= J are summed. For the rest, the
        block is balanced, ``B = T^-1 A_k T`` with a diagonal T
        (:func:`scipy.linalg.matrix_balance`; the raw block's norm is inflated by the scale of
        eta' against eta); with ``q = ||B^J||_2 < 1`` the terms beyond J sum to at most
        ``|c_k| ||e' T|| ||T^-1|| (||b_k|| + sum_m ||a_k,m||) q / (1 - q) sum_i<J ||B^i||``
        (``||B^(J+i)|| <= q ||B^i||``, and the sum of all the powers' norms is at most that
        over i < J divided by 1 - q). J is the first power where this tail is below a
        thousandth of the summed terms, so that for a mode without creep the bound is within
        0.1 % of the exact worst case.

        Parameters
        ----------
        limit : float
            A mode whose summed terms pass this (m / V) gets ``inf``: the sum stops there (a
            lightly damped mode's takes about 1 / (zeta omega dt) terms).

        Returns
        -------
        ndarray, shape (len(kept_modes),)
            In the order of :attr:`kept_modes` (m / V).
        """
        nc, a, b = self.n_creep, self.a, self.b
        bounds = np.empty(len(self.kept_modes))
        for i in range(len(self.kept_modes)):
            rows = slice(nc + 2 * i, nc + 2 * i + 2)
            block, gain = a[rows, rows], abs(self.output_matrix[0, nc + 2 * i])
            columns = np.column_stack([b[rows], a[rows, :nc]])  # input, then each creep state
            if np.abs(np.linalg.eigvals(block)).max() >= 1.0:
                raise ValueError(f"kept mode {self.kept_modes[i]} is not stable: no bound")
            balanced, scale = scipy.linalg.matrix_balance(block, permute=False)
            spread = float(np.linalg.norm(scale[0]) * np.linalg.norm(np.linalg.inv(scale), 2))
            factor = gain * spread * float(np.linalg.norm(columns, axis=0).sum())
            power, powered = np.eye(2), np.eye(2)  # A^j and B^j
            norms, head = 1.0, 0.0  # sum_i<j ||B^i||, sum_1<=i<=j of the terms
            for _ in range(1_000_000):
                power, powered = power @ block, powered @ balanced
                head += gain * float(np.abs(power[0] @ columns).sum())
                if head > limit:
                    break
                q = float(np.linalg.norm(powered, 2))
                tail = factor * q / (1.0 - q) * norms if q < 1.0 else np.inf
                if tail <= 1e-3 * head or tail == 0.0:
                    break
                norms += q
            bounds[i] = np.inf if head > limit else (head + tail) * (1.0 + 1e-9)
        return bounds

    def without_modes(self, drop: np.ndarray | list[int]) -> DiscreteBender:
        """This model with the kept modes at positions ``drop`` (into :attr:`kept_modes`)
        carried as their one-step contribution to the tip outputs, as :func:`discretize` does
        for a mode below its tolerance (:meth:`mode_error_bounds` bounds what each costs).

        The nodal matrix keeps the remaining modes only (drawing a dropped mode's shape needs
        its state)."""
        drop = sorted({int(i) for i in drop})
        if not drop:
            return self
        nc, n_s = self.n_creep, self.n_states
        a, b, c = self.a.copy(), self.b.copy(), self.output_matrix.copy()
        fast = slice(n_s - 2, n_s)
        for i in drop:
            row = nc + 2 * i
            a[fast, :nc] += np.outer(c[:, row], a[row, :nc])
            b[fast] += c[:, row] * b[row]
        gone = [nc + 2 * i + j for i in drop for j in (0, 1)]
        keep = np.setdiff1d(np.arange(n_s), gone)
        a, b, c = a[np.ix_(keep, keep)], b[keep], c[:, keep]
        n = keep.size
        step = np.zeros((n + 2, n + 1))
        step[:n, :n], step[:n, n] = a, b
        step[n:, :n], step[n:, n] = c @ a, c @ b
        return DiscreteBender(
            dt=self.dt,
            step_matrix=step,
            output_matrix=c,
            kept_modes=np.delete(self.kept_modes, drop),
            nodal_matrix=self.nodal_matrix[:, keep],
            n_creep=nc,
        )

    def impulse_l1_bound(self) -> float:
        """Proven upper bound of sum_k |h_k| of the impulse response u_eff -> y (m / V).

        With A = V diag(lambda) V^-1, h_k = sum_j rho_j lambda_j^(k-1). The first N terms are
        summed exactly, N chosen so that the oscillating beam modes have decayed to 1e-16; the
        rest is bounded by sum_j |rho_j| |lambda_j|^N / (1 - |lambda_j|), which is exact for the
        slow, real creep modes. Creep, if present, is part of A, so the bound covers it.
        """
        lam, vec = np.linalg.eig(self.a)
        residues = (self.output_matrix[0] @ vec) * np.linalg.solve(vec, self.b)
        radius = np.abs(lam)
        if radius.max() >= 1.0:
            raise ValueError("the discrete model is not asymptotically stable: no finite bound")
        oscillating = radius[np.abs(lam.imag) > 0]
        slowest = oscillating.max() if oscillating.size else radius.max()
        n = int(min(max(64.0, np.log(1e-16) / np.log(max(slowest, 1e-300))), 1_000_000))
        total = 0.0
        power = np.ones_like(lam)
        chunk = 4096
        k = 0
        while k < n:
            m = min(chunk, n - k)
            powers = power[None, :] * lam[None, :] ** np.arange(m)[:, None]
            total += float(np.abs((powers * residues).sum(axis=1).real).sum())
            power = power * lam**m
            k += m
        tail = float(np.sum(np.abs(residues) * np.abs(power) / (1.0 - radius)))
        # The relative margin covers the rounding of the sum itself.
        return (total + tail) * (1.0 + 1e-9)


def _mode_block(omega: float, zeta: float, phi_b: float, creep: Creep | None, dt: float):
    """Exact ZOH of [creep; eta; eta'] for one mode driven by u_eff (creep rows included)."""
    aug = mode_augmented(omega, zeta, phi_b, creep, dt)
    n = aug.shape[0] - 1
    e = scipy.linalg.expm(aug)
    return e[:n, :n], e[:n, n]


def mode_augmented(
    omega: float, zeta: float, phi_b: float, creep: Creep | None, dt: float
) -> np.ndarray:
    """[[A, b], [0, 0]] dt of one mode (rad/s, -, modal input per V) with its creep rows: the
    matrix whose exponential is the mode's exact ZOH step."""
    nc = 0 if creep is None else creep.size
    n = nc + 2
    a = np.zeros((n, n))
    b = np.zeros(n)
    if creep is not None:
        tau = np.asarray(creep.time_constants)
        a[np.arange(nc), np.arange(nc)] = -1.0 / tau
        b[:nc] = 1.0 / tau
        a[nc + 1, :nc] = phi_b * np.asarray(creep.weights)
    a[nc, nc + 1] = 1.0
    a[nc + 1, nc] = -(omega**2)
    a[nc + 1, nc + 1] = -2.0 * zeta * omega
    b[nc + 1] = phi_b
    aug = np.zeros((n + 1, n + 1))
    aug[:n, :n] = a
    aug[:n, n] = b
    return aug * dt


def discretize(
    beam: BeamFE,
    dt: float,
    *,
    creep: Creep | None = None,
    tolerance: float = 1e-10,
    reduce: bool = True,
) -> DiscreteBender:
    """Exact ZOH discretisation of the FE beam, keeping the modes that outlive one sample.

    Parameters
    ----------
    beam : BeamFE
        Assembled beam with its modes.
    dt : float
        Sample time (s), > 0.
    creep : Creep or None
        Optional creep terms.
    tolerance : float
        A mode whose discrete transition block has spectral radius below this is replaced by
        its one-step contribution to the tip outputs.
    reduce : bool
        False keeps every mode (for checks).

    Returns
    -------
    DiscreteBender
    """
    require_number("dt (s)", dt, low=0.0, low_open=True)
    nc = 0 if creep is None else creep.size
    omega = 2.0 * np.pi * beam.frequencies
    phi_b = beam.modes.T @ beam.piezo_input
    tip_w = beam.modes[-2, :]
    tip_theta = beam.modes[-1, :]

    blocks = [
        _mode_block(w, z, pb, creep, dt)
        for w, z, pb in zip(omega, beam.damping_ratios, phi_b, strict=True)
    ]
    radius = np.array([np.abs(np.linalg.eigvals(ad[nc:, nc:])).max() for ad, _ in blocks])
    kept = np.arange(len(blocks)) if not reduce else np.flatnonzero(radius >= tolerance)
    fast = np.setdiff1d(np.arange(len(blocks)), kept)

    a, b, c = _assemble(blocks, kept, fast, nc, tip_w, tip_theta)
    n_s = a.shape[0]
    step = np.zeros((n_s + 2, n_s + 1))
    step[:n_s, :n_s] = a
    step[:n_s, n_s] = b
    step[n_s:, :n_s] = c @ a
    step[n_s:, n_s] = c @ b

    nodal = np.zeros((beam.n_elements + 1, n_s))
    for i, k in enumerate(kept):
        nodal[1:, nc + 2 * i] = beam.modes[0::2, k]
    return DiscreteBender(
        dt=float(dt),
        step_matrix=step,
        output_matrix=c,
        kept_modes=kept,
        nodal_matrix=nodal,
        n_creep=nc,
    )


def _assemble(
    blocks: list,
    kept: np.ndarray,
    fast: np.ndarray,
    nc: int,
    tip_w: np.ndarray,
    tip_theta: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A, b and C of the reduced model: creep states, the kept modes' (q, q') pairs, and two
    output states carrying the fast modes' one-step contribution to [w_tip, theta_tip]."""
    n_s = nc + 2 * len(kept) + 2
    a = np.zeros((n_s, n_s))
    b = np.zeros(n_s)
    c = np.zeros((2, n_s))
    if nc:
        ad0, bd0 = blocks[0]
        a[:nc, :nc] = ad0[:nc, :nc]
        b[:nc] = bd0[:nc]
    for i, k in enumerate(kept):
        ad, bd = blocks[k]
        rows = slice(nc + 2 * i, nc + 2 * i + 2)
        a[rows, rows] = ad[nc:, nc:]
        a[rows, :nc] = ad[nc:, :nc]
        b[rows] = bd[nc:]
        c[0, rows] = [tip_w[k], 0.0]
        c[1, rows] = [tip_theta[k], 0.0]
    fast_rows = slice(n_s - 2, n_s)
    for k in fast:
        ad, bd = blocks[k]
        # Next-step displacement of a fast mode from the current creep states and input.
        gain = np.array([tip_w[k], tip_theta[k]])
        a[fast_rows, :nc] += np.outer(gain, ad[nc, :nc])
        b[fast_rows] += gain * bd[nc]
    c[0, n_s - 2] = 1.0
    c[1, n_s - 1] = 1.0
    return a, b, c
