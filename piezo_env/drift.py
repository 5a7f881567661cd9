"""Slow drift of the bender during an episode: piezoelectric coefficient and stiffness.

Physics. A PZT bender's effective piezoelectric coefficient (d31, hence the moment per volt
Gamma) and its elastic modulus (hence the bending stiffness EI) both depend on temperature: a
warming soft-PZT bender becomes more active and softer. :class:`Drift` moves both linearly in
time from their start to their end values (relative to the datasheet bender) over
``duration`` seconds, as a temperature swing would, and holds the end values afterwards. The
mass is unchanged and K scales uniformly, so the mass-normalised mode shapes are unchanged:
mode k's frequency scales by sqrt(stiffness), its modal input by the piezoelectric factor, and
the modal damping ratios are held. The static gain moves as piezo / stiffness, the first
resonance as sqrt(stiffness). The modelled range: factors in [0.5, 2] (validated); the
``drift`` plant of the benchmark uses +5 % piezoelectric coefficient and -5 % stiffness over
2 s (static gain +10.5 %, resonance -2.5 %), within the datasheet's +-20 % tolerance band.

Stepping (cost and error). The drifted plant is piecewise constant over segments of
``segment_steps`` samples, each with the parameters of the ramp at the segment's midpoint, and
each segment is discretised exactly (zero-order hold) in the same modal state, which is
continuous across a switch (displacement and velocity of each mode). The step matrices of all
segments are computed once per task (one batched matrix exponential of the kept modes), so a
step costs one counter test more than the nominal one. The parameters deviate from the linear
ramp by at most |end - start| * segment_steps * dt / (2 duration): 0.0125 % of the parameter
for the default 10 steps over 2 s at dt = 1 ms and a 5 % swing. The modes the nominal model
drops as faster than one sample (spectral radius < 1e-10) stay dropped, and their one-sample
contribution (their static gain to within that tolerance) is scaled by piezo / stiffness.

Observation bound (:func:`drift_deflection_bound_um`), proven for the switched plant: the
smaller of two bounds.

- Time-varying L1 bound (no creep, drifts up to 6000 samples): the deflection is
  y_t = sum_s h(t, s) u_eff,s with h(t, s) = c Phi(t, s + 1) b_s the switched plant's response,
  so |y_t| <= sup_t sum_s |h(t, s)| max|u_eff|, the exact peak-to-peak gain of the time-varying
  plant; summed exactly from the rest state's history to the drift's end plus the end plant's
  decay to 1e-12, the rest in modal bases (:meth:`DriftPlan.l1_bound_m`). Without drift it
  equals the time-invariant L1 bound (41714.53 um on the PL140, to 1e-9); the default drift
  gives 46236 um (the end plant's static gain is 10.5 % higher).
- Energy bound (any drift, creep included). For a kept mode with state (eta, eta') write
  z = (omega eta, eta'): under eta'' + 2 zeta omega eta' + omega^2 eta = phi v(t),
  d|z|^2/dt = -4 zeta omega eta'^2 + 2 eta' phi v, so with v = 0 |z| never grows, and over one
  sample |z+| <= rho |z| + |phi| V dt with rho = ||E A_d E^-1||_2 < 1 (E = diag(omega, 1), A_d
  the sample's transition) and V >= |v| (the effective voltage plus creep: V = max|u_eff|
  (1 + sum c_i), creep states being convex averages of u_eff). A switch to a segment with
  frequency omega' rescales z by diag(omega' / omega, 1), a growth of at most
  max(1, omega' / omega); over a monotone ramp these factors multiply to G = max(1,
  omega_end / omega_start). Hence |z| <= G |phi|_max V dt / (1 - rho_max) at every sample (the
  rest state at reset is the limit of a constant drive under the first segment, covered by the
  same sum), and |eta| <= |z| / omega_min. The tip deflection is sum_k |c_k| |eta_k| over the
  kept modes plus the fast modes' one-sample contribution, bounded segment by segment from
  the step matrices. It is about 10x looser (the worst-case phase of each sample).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from piezo_env.blas import single_blas_thread
from piezo_env.checks import require_int, require_number
from piezo_env.discrete import _mode_block, mode_augmented

__all__ = ["Drift", "DriftPlan", "drift_deflection_bound_um"]

_FACTOR_RANGE = (0.5, 2.0)
LTV_MAX_STEPS = 6000
"""Longest drift (samples) whose time-varying L1 bound is summed (its cost grows as the square)."""
_BOUND_MARGIN = 1e-9


@dataclass(frozen=True)
class Drift:
    """Linear drift of the piezoelectric coefficient and the stiffness over an episode.

    Parameters
    ----------
    piezo_coefficient : (float, float)
        Start and end factor (-) of the effective piezoelectric coefficient (the moment per
        volt Gamma) relative to the datasheet bender, each in [0.5, 2].
    stiffness : (float, float)
        Start and end factor (-) of the bending stiffness EI, each in [0.5, 2].
    duration : float
        Time (s), > 0, over which the factors move from start to end; they hold afterwards.
        The default 2 s is the default episode (2000 steps at 1 ms).
    segment_steps : int
        Samples (>= 1) per piecewise-constant segment (module docstring: the error).
    """

    piezo_coefficient: tuple[float, float] = (1.0, 1.05)
    stiffness: tuple[float, float] = (1.0, 0.95)
    duration: float = 2.0
    segment_steps: int = 10

    def __post_init__(self) -> None:
        for name in ("piezo_coefficient", "stiffness"):
            pair = getattr(self, name)
            try:
                start, end = (float(v) for v in pair)
            except (TypeError, ValueError):
                raise ValueError(
                    f"Drift.{name} must be a pair (start, end) of factors, got {pair!r}"
                ) from None
            for value in (start, end):
                require_number(
                    f"Drift.{name} factor (-)", value, low=_FACTOR_RANGE[0], high=_FACTOR_RANGE[1]
                )
            object.__setattr__(self, name, (start, end))
        require_number("Drift.duration (s)", self.duration, low=0.0, low_open=True)
        require_int("Drift.segment_steps", self.segment_steps)

    def factors(self, time: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(piezo, stiffness) factors (-) at ``time`` (s) after the reset."""
        fraction = np.clip(np.asarray(time, dtype=float) / self.duration, 0.0, 1.0)
        g0, g1 = self.piezo_coefficient
        s0, s1 = self.stiffness
        return g0 + (g1 - g0) * fraction, s0 + (s1 - s0) * fraction

    def ramp_error(self, dt: float) -> tuple[float, float]:
        """Largest deviation (-) of the segment factors from the linear ramp (piezo, stiffness)."""
        half = self.segment_steps * dt / (2.0 * self.duration)
        return (
            abs(self.piezo_coefficient[1] - self.piezo_coefficient[0]) * min(half, 1.0),
            abs(self.stiffness[1] - self.stiffness[0]) * min(half, 1.0),
        )


class DriftPlan:
    """Step matrices of every segment of a drift on one model (computed once per task).

    Attributes
    ----------
    drift : Drift
    square_matrices : ndarray, shape (n_segments, n_s + 2, n_s + 2)
        Square step matrices (see ``DiscreteBender.square_step_matrix``), one per segment; the
        last one holds from the end of the drift on.
    piezo_moments : ndarray, shape (n_segments,)
        Gamma (N m / V) of each segment, for the charge Q = C_p u + Gamma theta_tip.
    piezo, stiffness : ndarray, shape (n_segments,)
        The segments' factors (-).
    """

    def __init__(self, model, drift: Drift) -> None:
        self.drift = drift
        self.segment_steps = int(drift.segment_steps)
        dt = model.dt
        n_ramp = math.ceil(drift.duration / (drift.segment_steps * dt))
        mid = (np.arange(n_ramp) + 0.5) * drift.segment_steps * dt
        piezo, stiff = drift.factors(mid)
        end_g, end_s = drift.factors(drift.duration)
        self.piezo = np.append(piezo, end_g)
        self.stiffness = np.append(stiff, end_s)
        self.piezo_moments = model.params.piezo_moment * self.piezo
        with single_blas_thread():  # tiny matrices: threads only stall (piezo_env.blas)
            self._build(model)

    def _build(self, model) -> None:
        beam, discrete, creep, dt = model.beam, model.discrete, model.creep, model.dt
        nc = discrete.n_creep
        omega = 2.0 * np.pi * beam.frequencies
        phi_b = beam.modes.T @ beam.piezo_input
        zeta = beam.damping_ratios
        tip_w, tip_theta = beam.modes[-2, :], beam.modes[-1, :]
        kept = discrete.kept_modes
        fast = np.setdiff1d(np.arange(len(omega)), kept)
        fast_blocks = {k: _mode_block(omega[k], zeta[k], phi_b[k], creep, dt) for k in fast}
        n_seg = self.piezo.size
        aug = np.array(
            [
                mode_augmented(omega[k] * math.sqrt(s), zeta[k], phi_b[k] * g, creep, dt)
                for g, s in zip(self.piezo, self.stiffness, strict=True)
                for k in kept
            ]
        )
        expo = scipy.linalg.expm(aug).reshape(n_seg, len(kept), nc + 3, nc + 3)
        n_s = discrete.n_states
        c = discrete.output_matrix
        self.square_matrices = np.zeros((n_seg, n_s + 2, n_s + 2))
        self._mode_transitions = expo[:, :, nc:-1, nc:-1]
        self._fast_rows = np.zeros((n_seg, 2, n_s + 1))
        for j in range(n_seg):
            scale = self.piezo[j] / self.stiffness[j]
            a = np.zeros((n_s, n_s))
            b = np.zeros(n_s)
            if nc:
                a[:nc, :nc] = expo[j, 0, :nc, :nc]
                b[:nc] = expo[j, 0, :nc, -1]
            for i in range(len(kept)):
                rows = slice(nc + 2 * i, nc + 2 * i + 2)
                a[rows, rows] = expo[j, i, nc:-1, nc:-1]
                a[rows, :nc] = expo[j, i, nc:-1, :nc]
                b[rows] = expo[j, i, nc:-1, -1]
            for k in fast:
                ad, bd = fast_blocks[k]
                gain = np.array([tip_w[k], tip_theta[k]])
                a[n_s - 2 :, :nc] += scale * np.outer(gain, ad[nc, :nc])
                b[n_s - 2 :] += scale * gain * bd[nc]
            self._fast_rows[j, :, :nc] = a[n_s - 2 :, :nc]
            self._fast_rows[j, :, n_s] = b[n_s - 2 :]
            m = self.square_matrices[j]
            m[:n_s, :n_s] = a
            m[:n_s, n_s] = b
            m[n_s:, :n_s] = c @ a
            m[n_s:, n_s] = c @ b
        self._omega = omega[kept][None, :] * np.sqrt(self.stiffness)[:, None]
        self._phi = np.abs(phi_b[kept])[None, :] * self.piezo[:, None]
        self._tip = np.abs(tip_w[kept])
        self._nc = nc
        self._n_s = n_s
        self._c = c[0].copy()
        self._ramp_steps = (n_seg - 1) * self.segment_steps
        self._creep_sum = 0.0 if creep is None else float(sum(creep.weights))
        self._dt = dt

    @property
    def n_segments(self) -> int:
        """Number of segments (the last holds the end values)."""
        return self.piezo.size

    def deflection_bound_m(self, u_eff_max: float) -> float:
        """Proven bound (m) of |tip deflection| under |u_eff| <= ``u_eff_max`` (module doc):
        the smaller of the energy bound and, without creep, the time-varying L1 bound."""
        energy = self.energy_bound_m(u_eff_max)
        if self._nc or self._ramp_steps > LTV_MAX_STEPS:
            return energy
        return min(energy, self.l1_bound_m(u_eff_max))

    def l1_bound_m(self, u_eff_max: float) -> float:
        """Time-varying L1 bound (m): sup_t sum_s |h(t, s)| u_eff_max (module docstring).

        h(t, s) = c Phi(t, s + 1) b_s is the switched plant's response at sample t to a unit
        input at s; the rest state at reset counts as an infinite past under the first
        segment: summed exactly over the M_0 samples before 0 in which its slowest mode decays
        to 1e-12, and before that in its modal basis (each mode's geometric tail in closed
        form, by the triangle inequality). The sums are exact up to the drift's end plus ``M``
        samples (the end plant's slowest mode decayed to 1e-12); later, the response to inputs
        up to the end is bounded in the end plant's modal basis with |lambda|^M, and the inputs
        after it by the end plant's own L1 bound
        (:meth:`piezo_env.discrete.DiscreteBender.impulse_l1_bound`). No creep: its real modes
        near 1 would need far longer sums (the energy bound covers creep).
        """
        from piezo_env.discrete import DiscreteBender

        n = self._n_s
        c = self._c
        mats = self.square_matrices
        a0, b0 = mats[0][:n, :n], mats[0][:n, n]
        lam0, vec0 = np.linalg.eig(a0)
        weights = np.abs(np.linalg.solve(vec0, b0)) / (1.0 - np.abs(lam0))
        lam, vec = np.linalg.eig(mats[-1][:n, :n])
        m_start, m_steps = _decay_steps(lam0), _decay_steps(lam)
        total = m_start + self._ramp_steps + m_steps
        columns = np.zeros((n, total))
        past = vec0.astype(complex)  # inputs before -m_start, in the first segment's modes
        worst = 0.0
        for i in range(total):
            t = i - m_start  # samples before 0: the rest state's history, first segment
            j = 0 if t < 0 else min(t // self.segment_steps, self.n_segments - 1)
            a, b = mats[j][:n, :n], mats[j][:n, n]
            columns[:, :i] = a @ columns[:, :i]
            columns[:, i] = b
            past = a @ past
            if t + 1 < 0:  # the rest state's history itself: not an output of the episode
                continue
            value = float(np.abs(c @ columns[:, : i + 1]).sum() + np.abs(c @ past) @ weights)
            worst = max(worst, value)
            if t + 1 == self._ramp_steps:
                old_columns, old_past = columns[:, : i + 1].copy(), past.copy()
        modal_out = np.abs(c @ vec)
        inverse = np.linalg.inv(vec)
        old = np.abs(inverse @ old_columns).sum(axis=1) + np.abs(inverse @ old_past) @ weights
        tail = float(modal_out @ (np.abs(lam) ** m_steps * old))
        end = DiscreteBender(
            dt=self._dt,
            step_matrix=mats[-1][: n + 2, : n + 1],
            output_matrix=np.vstack([c, np.zeros(n)]),
            kept_modes=np.zeros(0, dtype=int),
            nodal_matrix=np.zeros((1, n)),
            n_creep=0,
        )
        worst = max(worst, end.impulse_l1_bound() + tail)
        return worst * u_eff_max * (1.0 + _BOUND_MARGIN)

    def energy_bound_m(self, u_eff_max: float) -> float:
        """Energy bound (m) of the module docstring (any drift, creep included)."""
        v_max = u_eff_max * (1.0 + self._creep_sum)
        total = 0.0
        for i in range(self._tip.size):
            w = self._omega[:, i]
            rho = max(
                float(np.linalg.norm(np.diag([wj, 1.0]) @ t @ np.diag([1.0 / wj, 1.0]), 2))
                for wj, t in zip(w, self._mode_transitions[:, i], strict=True)
            )
            if not rho < 1.0:
                raise ValueError("a drifted mode is not contractive: no finite bound")
            growth = float(np.prod(np.maximum(1.0, w[1:] / w[:-1])))
            z_max = growth * float(self._phi[:, i].max()) * v_max * self._dt / (1.0 - rho)
            total += self._tip[i] * z_max / float(w.min())
        # Fast modes' one-sample contribution: creep states and u_eff are both <= u_eff_max.
        fast = float(np.abs(self._fast_rows[:, 0, :]).sum(axis=1).max()) * u_eff_max
        return (total + fast) * (1.0 + _BOUND_MARGIN)


def _decay_steps(eigenvalues: np.ndarray) -> int:
    """Samples after which the slowest of these modes has decayed below 1e-12."""
    radius = float(np.abs(eigenvalues).max())
    if not radius < 1.0:
        raise ValueError("a drift segment is not asymptotically stable: no finite bound")
    return math.ceil(math.log(1e-12) / math.log(max(radius, 1e-300))) + 1


def drift_deflection_bound_um(model, plan: DriftPlan) -> float:
    """Proven bound (um) of |tip deflection| of ``model`` drifting as ``plan`` for any drive
    within [-U_r, U_r] (module docstring)."""
    u_eff_max = model.hysteresis.max_effective_voltage(model.rated_voltage)
    return plan.deflection_bound_m(u_eff_max) * 1e6
