"""The unconstrained MPC with its observer as one linear controller, and the loop it closes.

Away from its bounds the linear MPC's first move is linear in what it knows::

    z_t = k_e [x_hat; d_hat (; s_hat)]_t|t + k_z z_t-1 + (feedforward of the previewed targets)

(the first row of ``-P^-1 G``, :func:`controllers.condensed.qp_matrices`), and the observer
(:class:`controllers.observer.DisturbanceObserver`, gain L) is linear in y and z. The feedback
part, from the measured deflection y (um) to z (equivalent V), is therefore a linear controller
K(q) of the state ``[e; z_t-1]``, e the observer's predicted estimate::

    f_t = (I - L c) e_t + L y_t                 (correction)
    z_t = k_e f_t + k_z z_t-1
    e_t+1 = A f_t + B z_t                      (prediction)

Closed around a linear part G (z -> y, strictly proper: ``y_t = c x_t``), the loop is
``y = G z, z = K y``; its return difference is ``1 - G K`` and its modulus margin
``min_w |1 - G K(e^jw)|``, the distance of the Nyquist curve from the critical point
(Astrom & Murray, *Feedback Systems*, 2nd ed., sec. 10.3; the inverse of the sensitivity peak
Ms). :meth:`controllers.adaptive.AdaptiveMPC.stabilises` closes this loop around a candidate
model (:func:`loop_is_stable`), and the MPCs report the margin of their loop around their
own model (``describe()["observer"]``).

What the margin on the model does not decide: which filter of the observer bank may run. On a
bender whose first resonance sits near the Nyquist frequency (the PL127 at 1 kHz with a damping
ratio of 0.04), the bank's fastest filters put the loop's pole at Nyquist outside the unit
circle, and a screen keeping only the filters with a margin of at least 0.5 on the model
(Ms <= 2, the textbook bound) holds that loop. On a bender 20 % softer, though, the resonance
moves by 10 % (sqrt(0.8)), a relative model error far above 1 near a lightly damped mode,
which no margin on one model covers; there the fast filters, which re-estimate the modal state
from the data, are what keeps the loop. The plants need opposite filters, and a screen on every
vertex of the datasheet's tolerance box covers both: the filters kept are those whose loop is
stable on every vertex's linear part (:func:`radii_matrix`, with the box's models moving every
mode, aliases included, :mod:`controllers.tolerance_box`) and within the Ms bound on the model
(:func:`controllers.predictive.screen_bank`). The MPCs learn the gain (:mod:`controllers.gain`),
so the softer bender whose resonance the fast filters have to chase is a vertex the kept
filters are stable on; :mod:`benchmarks.studies.corners` measures the result
(``benchmarks/results/corners*.md``). Among the kept filters the data choose (the likelihood),
and the runaway guard of :class:`controllers.observer.ObserverBank` is the last line for what
the box does not hold. What the screen on the model alone and the guard's alternatives cost on
the robustness plants is recorded in ``benchmarks/results/design_measurements.md``.

The frequency responses of all filters of a bank are computed together: they share A, B, c
and the feedback law, and differ only by L, so with ``R(q) = (qI - A)^-1`` (one inverse per
frequency for the whole bank) the correction's rank-one term is folded in by the
Sherman-Morrison formula, leaving two dot products per filter and frequency::

    (qI - A + L c A)^-1 = S = R - R L (c A R) / (1 + c A R L)
    K(q) = q k_e S L / (1 - k_z / q - k_e S (I - L c) B)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = [
    "OutputFeedback",
    "closed_loop_matrix",
    "feedback_law",
    "loop_is_stable",
    "modulus_margins",
    "output_feedback",
    "plant_margins",
    "radii_matrix",
]

FREQUENCY_POINTS = 1024
"""Frequencies on (0, pi] (rad per sample, Nyquist included) at which margins are evaluated."""


@dataclass(frozen=True)
class OutputFeedback:
    """A linear controller from y (um) to z (equivalent V): ``xi_t+1 = a xi_t + b y_t``,
    ``z_t = c xi_t + d y_t``, with ``xi = [e; z_t-1]`` (see the module docstring)."""

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    d: float


def feedback_law(
    hessian: np.ndarray, q_matrix: np.ndarray, n_estimate: int
) -> tuple[np.ndarray, float]:
    """``(k_e, k_z)``: the unconstrained first move's gains on the estimate and on z_t-1.

    Parameters
    ----------
    hessian, q_matrix : numpy.ndarray
        P (N, N) and G of :func:`controllers.condensed.qp_matrices`
        (``q = G [x; d (; s); r; z_prev]``).
    n_estimate : int
        Size m of the observer's estimate ``[x; d (; s)]``.

    Returns
    -------
    k_e : numpy.ndarray
        (m,) gains on the estimate (equivalent V per um; per um/sample for a slope s).
    k_z : float
        Gain on z_t-1 (dimensionless).
    """
    first = -np.linalg.solve(hessian, q_matrix)[0]
    return first[:n_estimate], float(first[-1])


def output_feedback(
    a_aug: np.ndarray,
    b_aug: np.ndarray,
    c_aug: np.ndarray,
    gain: np.ndarray,
    k_estimate: np.ndarray,
    k_previous: float,
) -> OutputFeedback:
    """The observer with the feedback law as one controller from y (um) to z (equivalent V).

    Parameters
    ----------
    a_aug, b_aug, c_aug : numpy.ndarray
        The observer's augmented model ((m, m), (m,), (m,); see
        :class:`controllers.observer.DisturbanceObserver`).
    gain : numpy.ndarray
        (m,) its filter gain L (the current-estimate form: ``f = e + L (y - c e)``).
    k_estimate, k_previous
        The feedback law (:func:`feedback_law`).

    Returns
    -------
    OutputFeedback
        State ``[e; z_t-1]`` (m + 1), e the predicted estimate.
    """
    m = a_aug.shape[0]
    correct = np.eye(m) - np.outer(gain, c_aug)  # f = correct e + L y
    k_e = k_estimate @ correct
    a = np.zeros((m + 1, m + 1))
    a[:m, :m] = a_aug @ correct + np.outer(b_aug, k_e)
    a[:m, m] = b_aug * k_previous
    a[m, :m], a[m, m] = k_e, k_previous
    direct = float(k_estimate @ gain)
    b = np.r_[a_aug @ gain + b_aug * direct, direct]
    return OutputFeedback(a=a, b=b, c=np.r_[k_e, k_previous], d=direct)


def closed_loop_matrix(
    controller: OutputFeedback, a: np.ndarray, b: np.ndarray, c: np.ndarray
) -> np.ndarray:
    """State matrix of the loop ``z = K y`` around ``x_t+1 = a x_t + b z_t, y_t = c x_t``.

    Parameters
    ----------
    controller : OutputFeedback
        K (:func:`output_feedback`).
    a, b, c : numpy.ndarray
        The linear part the loop closes around ((n, n), (n, 1) or (n,), (1, n) or (n,); um
        per equivalent V), the controller's own model or another.

    Returns
    -------
    numpy.ndarray
        (n + m + 1, n + m + 1) over ``[x; e; z_t-1]``: the loop is stable when its spectral
        radius is below 1.
    """
    n, k = a.shape[0], controller.a.shape[0]
    b, c = b.reshape(n), c.reshape(n)
    loop = np.zeros((n + k, n + k))
    loop[:n, :n] = a + controller.d * np.outer(b, c)
    loop[:n, n:] = np.outer(b, controller.c)
    loop[n:, :n] = np.outer(controller.b, c)
    loop[n:, n:] = controller.a
    return loop


def loop_is_stable(controller: OutputFeedback, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> bool:
    """True if the loop of :func:`closed_loop_matrix` has every pole inside the unit circle."""
    return bool(np.max(np.abs(np.linalg.eigvals(closed_loop_matrix(controller, a, b, c)))) < 1.0)


def radii_matrix(
    a_aug: np.ndarray,
    b_aug: np.ndarray,
    c_aug: np.ndarray,
    gains: np.ndarray,
    k_estimate: np.ndarray,
    k_previous: float,
    plants: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> np.ndarray:
    """Spectral radius (-) of each filter's loop on each plant.

    Parameters
    ----------
    a_aug, b_aug, c_aug : numpy.ndarray
        The observer's augmented model.
    gains : numpy.ndarray
        Filter gains, one row per filter.
    k_estimate, k_previous
        The feedback law (:func:`feedback_law`).
    plants : list of (a, b, c)
        Linear parts the loop is closed around (:func:`closed_loop_matrix`); the plants of each
        order are built and solved as one batch.

    Returns
    -------
    numpy.ndarray
        (filters, plants): below 1 where that filter's loop is stable on that plant.
    """
    loops = [
        output_feedback(a_aug, b_aug, c_aug, gain, k_estimate, k_previous)
        for gain in np.atleast_2d(gains)
    ]
    k = loops[0].a.shape[0]
    ca = np.array([loop.a for loop in loops])  # (F, k, k)
    cb = np.array([loop.b for loop in loops])  # (F, k)
    cc = np.array([loop.c for loop in loops])
    cd = np.array([loop.d for loop in loops])  # (F,)
    out = np.empty((len(loops), len(plants)))
    for index, a, b, c in _batches(plants):  # (P, n, n), (P, n), (P, n)
        n = a.shape[1]
        matrices = np.zeros((len(loops), len(index), n + k, n + k))
        matrices[:, :, :n, :n] = a[None] + cd[:, None, None, None] * (b[:, :, None] * c[:, None, :])
        matrices[:, :, :n, n:] = b[None, :, :, None] * cc[:, None, None, :]
        matrices[:, :, n:, :n] = cb[:, None, :, None] * c[None, :, None, :]
        matrices[:, :, n:, n:] = ca[:, None]
        out[:, index] = np.max(np.abs(np.linalg.eigvals(matrices)), axis=-1)
    return out


def _batches(
    plants: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
) -> list[tuple[list[int], np.ndarray, np.ndarray, np.ndarray]]:
    """The plants grouped by order, each group stacked for one batched solve: (their indices
    in ``plants``, a (P, n, n), b (P, n), c (P, n))."""
    out = []
    for order in sorted({plant[0].shape[0] for plant in plants}):
        index = [j for j, plant in enumerate(plants) if plant[0].shape[0] == order]
        a = np.array([plants[j][0] for j in index])
        b = np.array([np.reshape(plants[j][1], order) for j in index])
        c = np.array([np.reshape(plants[j][2], order) for j in index])
        out.append((index, a, b, c))
    return out


def modulus_margins(
    a_aug: np.ndarray,
    b_aug: np.ndarray,
    c_aug: np.ndarray,
    gains: np.ndarray,
    k_estimate: np.ndarray,
    k_previous: float,
    n: int,
    points: int = FREQUENCY_POINTS,
) -> np.ndarray:
    """Modulus margin of each filter's loop around the observer's own model (0 when that loop
    is unstable: its margin then means nothing).

    Parameters
    ----------
    a_aug, b_aug, c_aug : numpy.ndarray
        The observer's augmented model; its ``[x]`` block is the model the loop closes around.
    gains : numpy.ndarray
        Filter gains, one row per filter.
    k_estimate, k_previous
        The feedback law (:func:`feedback_law`).
    n : int
        Number of model states (the leading block of the augmented model).
    points : int
        Frequencies on (0, pi], Nyquist included.

    Returns
    -------
    numpy.ndarray
        ``min_w |1 - G K(e^jw)|`` per filter (dimensionless).
    """
    gains = np.atleast_2d(gains)
    q = _frequencies(points)
    model, controller = _responses(q, a_aug, b_aug, c_aug, gains, k_estimate, k_previous)
    margins = np.min(np.abs(1.0 - model[:, None] * controller), axis=0)
    a, b, c = a_aug[:n, :n], b_aug[:n], c_aug[:n]
    for k, gain in enumerate(gains):
        feedback = output_feedback(a_aug, b_aug, c_aug, gain, k_estimate, k_previous)
        if not loop_is_stable(feedback, a, b, c):
            margins[k] = 0.0
    return margins


def _frequencies(points: int) -> np.ndarray:
    """``points`` frequencies on the unit circle, (0, pi], Nyquist included."""
    return np.exp(1j * np.linspace(np.pi / points, np.pi, points))


def _responses(
    q: np.ndarray,
    a_aug: np.ndarray,
    b_aug: np.ndarray,
    c_aug: np.ndarray,
    gains: np.ndarray,
    k_estimate: np.ndarray,
    k_previous: float,
) -> tuple[np.ndarray, np.ndarray]:
    """G(q) of the observer's own model (W,) and K(q) of each filter's controller (W, F)
    (module docstring: one resolvent per frequency for the whole bank)."""
    m = a_aug.shape[0]
    resolvent = np.linalg.inv(q[:, None, None] * np.eye(m) - a_aug)  # R(q), (W, m, m)
    r_b = resolvent @ b_aug  # (W, m)
    model = r_b @ c_aug  # G(q) = c R B: the disturbance rows of B are zero
    u_r = np.einsum("i,fij->fj", c_aug @ a_aug, resolvent)  # c A R
    k_r = np.einsum("i,fij->fj", k_estimate, resolvent)  # k_e R
    u_b, c_b, k_b = u_r @ b_aug, c_aug @ b_aug, k_r @ b_aug
    u_l = u_r @ gains.T  # c A R L, (W, filters)
    k_l = k_r @ gains.T  # k_e R L
    k_s_l = k_l / (1.0 + u_l)  # k_e S L
    # k_e S (I - L c) B = k_e R B - k_e S L (c A R B + c B)
    k_s_b = k_b[:, None] - k_s_l * (u_b[:, None] + c_b)
    controller = q[:, None] * k_s_l / (1.0 - k_previous / q[:, None] - k_s_b)
    return model, controller


def _plant_responses(
    plants: list[tuple[np.ndarray, np.ndarray, np.ndarray]], points: int = FREQUENCY_POINTS
) -> np.ndarray:
    """Frequency responses ``G_p(e^jw)`` (um per equivalent V) of ``plants`` (each (a, b, c),
    z -> y, in any realization) at the margins' frequencies: (plants, points)."""
    q = _frequencies(points)
    out = np.empty((len(plants), points), dtype=complex)
    for index, a, b, c in _batches(plants):  # one batched solve per order
        order = a.shape[1]
        pencil = q[None, :, None, None] * np.eye(order) - a[:, None]  # (P, W, n, n)
        rhs = np.broadcast_to(b[:, None, :, None], (*pencil.shape[:3], 1))
        out[index] = np.einsum("pn,pwn->pw", c, np.linalg.solve(pencil, rhs)[..., 0])
    return out


def plant_margins(
    a_aug: np.ndarray,
    b_aug: np.ndarray,
    c_aug: np.ndarray,
    gains: np.ndarray,
    k_estimate: np.ndarray,
    k_previous: float,
    plants: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    points: int = FREQUENCY_POINTS,
) -> np.ndarray:
    """Modulus margin ``min_w |1 - G_p K(e^jw)|`` of each filter's loop on each of ``plants``
    (the loops of :func:`radii_matrix`; the margin means something only where that loop is
    stable).

    Parameters
    ----------
    a_aug, b_aug, c_aug, gains, k_estimate, k_previous
        As :func:`modulus_margins`.
    plants : list of (a, b, c)
        Linear parts (z -> y) the loop is closed around, each in any realization.
    points : int
        Frequencies on (0, pi], Nyquist included.

    Returns
    -------
    numpy.ndarray
        (filters, plants), dimensionless.
    """
    q = _frequencies(points)
    _, controller = _responses(q, a_aug, b_aug, c_aug, np.atleast_2d(gains), k_estimate, k_previous)
    responses = _plant_responses(plants, points)
    out = np.empty((controller.shape[1], responses.shape[0]))
    for j, response in enumerate(responses):  # (W, filters) at a time: a bounded temporary
        out[:, j] = np.abs(1.0 - response[:, None] * controller).min(axis=0)
    return out
