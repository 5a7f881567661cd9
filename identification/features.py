"""Memory features of the NLS: what the network sees of the voltage history.

A static map u -> z cannot draw a hysteresis loop, so the NLS network (identification.nls)
takes memory features of the input. Each feature map is stateful, so that a controller can run
it step by step, and serialises to a plain dict.

``"play"``
    ``F_t = [u_t, p_1,t, ..., p_n,t]`` with Prandtl-Ishlinskii play (backlash) operators of radii
    ``r_i`` spread over the input range, ``p_i,t = max(u_t - r_i, min(u_t + r_i, p_i,t-1))``.
    Rate-independent memory: the output depends on the input's turning points, not on its speed.
    The feature state is the vector of play outputs.
``"rate-play"``
    ``F_t = [u_t, p_1,t, ..., p_n,t]`` with rate-dependent directional plays of radii
    ``r_i + c |u_t-1 - u_t-2| / dt`` (the plays of
    :class:`piezo_env.hysteresis.RateDependentPrandtlIshlinskii`): loops that widen with the
    drive's rate. Learned in step e' (``IdentificationConfig.rate``), never chosen in step e.
    The state is ``[u_t-1, rate_t-1, p_1, ..., p_n]``.
``"past-inputs"``
    ``F_t = [u_t, u_t-1, ..., u_t-k]``: the paper's nlarx regressors. The feature state is the
    buffer ``[u_t-1, ..., u_t-k]``.
``"bouc-wen"``
    ``F_t = [u_t, h_1,t, ..., h_n,t]`` with normalized Bouc-Wen operators
    ``dh = du - b |du| h - b du |h|`` (``b = 1 / (2 level)``), saturation levels spread over the
    input range, integrated exactly in ``u`` (:func:`bouc_wen_update`): rate-independent like
    plays, but with the rounded loops of piezo hysteresis. Beyond the paper: a single-state
    Bouc-Wen hysteresis is not a Prandtl-Ishlinskii operator, so play features plateau on it,
    while these represent it closely. The state is ``[u_t-1, h_1, ..., h_n]``.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from identification.arguments import as_range, as_scalar, as_signal
from piezo_env.checks import require_int
from piezo_env.operators import (
    BoucWenBatch,
    bouc_wen_casadi,
    bouc_wen_jump_batch,
    normalized_bouc_wen,
    play,
    play_casadi,
    play_sequence,
    rate_play_sequence,
)

__all__ = [
    "FEATURE_SETS",
    "REUSE_BYTES",
    "BoucWenFeatures",
    "FeatureMap",
    "PastInputFeatures",
    "PlayFeatures",
    "RatePlayFeatures",
    "bouc_wen_update",
    "default_bouc_wen_levels",
    "default_play_radii",
    "feature_map_from_dict",
    "play_operators",
    "reused_features",
    "sequence_features",
]

FEATURE_SETS = ("play", "past-inputs", "bouc-wen")
"""Names of the memory feature sets accepted by :func:`identification.nls.fit_nls`."""

# ---------------------------------------------------------------------------------------------
# memory features


def default_play_radii(u_range: Sequence[float], n_play: int) -> np.ndarray:
    """Play radii spread evenly over the input range, ``r_i = i (hi - lo) / (2 (n + 1))``.

    The largest radius stays below half the span, so every play operator moves on a full sweep.

    Parameters
    ----------
    u_range : (float, float)
        Input range ``(lo, hi)`` in V.
    n_play : int
        Number of play operators (>= 1).

    Returns
    -------
    numpy.ndarray, shape (n_play,)
        Radii in V, increasing.
    """
    low, high = as_range("u_range", u_range)
    n = require_int("n_play", n_play)
    return (high - low) / (2.0 * (n + 1)) * np.arange(1, n + 1, dtype=np.float64)


def play_operators(
    u: ArrayLike, radii: ArrayLike, state: ArrayLike | None = None, *, initial_input: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Outputs of Prandtl-Ishlinskii play operators, ``p_t = max(u_t - r, min(u_t + r, p_t-1))``.

    Parameters
    ----------
    u : array_like, shape (T,)
        Input sequence, V.
    radii : array_like, shape (n,)
        Play radii (half backlash widths), V, non-negative.
    state : array_like, shape (n,), optional
        Play outputs before ``u[0]``, V. Default: all equal to ``initial_input`` (a relaxed
        operator at rest).
    initial_input : float, optional
        Rest input used when ``state`` is None, V.

    Returns
    -------
    P : numpy.ndarray, shape (T, n)
        Play outputs, V.
    final_state : numpy.ndarray, shape (n,)
        Play outputs after the last sample (pass back as ``state`` to continue).
    """
    u_arr = as_signal("u", u)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(r)) or np.any(r < 0.0):
        raise ValueError(f"radii must be finite and non-negative; got {r}")
    if state is None:
        p = np.full(r.shape, as_scalar("initial_input", initial_input))
    else:
        p = np.array(state, dtype=np.float64).reshape(-1)
        if p.shape != r.shape or not np.all(np.isfinite(p)):
            raise ValueError(
                f"play state must be {r.size} finite values (one per radius); got {state!r}"
            )
    return play_sequence(u_arr, r, p)


def _freeze_operator_fields(features: Any, field: str, what: str) -> np.ndarray:
    """Check an operator feature map's ``field`` (V) and ``initial_input``, store them as floats.

    ``field`` must hold one or more positive finite numbers (play radii, Bouc-Wen levels); it is
    stored as a tuple of floats and returned as a float64 array.
    """
    given = getattr(features, field)
    values = np.asarray(given, dtype=np.float64)
    if values.ndim != 1 or values.size < 1 or not np.isfinite(values).all() or (values <= 0).any():
        raise ValueError(f"{what} must be one or more positive numbers; got {given}")
    object.__setattr__(features, field, tuple(float(x) for x in values))
    rest = as_scalar("initial_input", features.initial_input)
    object.__setattr__(features, "initial_input", rest)
    return values


class _StateChecks:
    """``check_state`` of a feature map, and its rest state with every value at ``initial_input``.

    The map names its state for the error message in :meth:`_state_text`.
    """

    n_state: int
    initial_input: float

    def _state_text(self) -> str:
        raise NotImplementedError

    def initial_state(self) -> np.ndarray:
        """State at rest: every state value equal to ``initial_input`` (V)."""
        return np.full(self.n_state, self.initial_input)

    def check_state(self, state: ArrayLike | None) -> np.ndarray:
        """Validated ``state`` as a float64 vector (the rest state for None); never mutated.

        A float64 vector of the right length is returned as is (no copy: feature maps never
        write into a state, they return new ones), which keeps per-step calls cheap.
        """
        if state is None:
            return self.initial_state()
        if type(state) is np.ndarray and state.dtype == np.float64 and state.ndim == 1:
            s = state
        else:
            try:
                s = np.array(state, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                raise ValueError(f"{self._state_text()}; got {state!r}") from None
        if s.shape != (self.n_state,) or not np.isfinite(s).all():
            raise ValueError(f"{self._state_text()}; got {np.asarray(state).tolist()}")
        return s


@dataclass(frozen=True)
class PlayFeatures(_StateChecks):
    """Play-operator features ``F_t = [u_t, p_1,t, ..., p_n,t]``; state: play outputs (V).

    Attributes
    ----------
    radii : tuple of float
        Play radii, V, positive and increasing.
    initial_input : float
        Rest input, V: the default state has every play output equal to it.
    """

    radii: tuple[float, ...]
    initial_input: float = 0.0

    name = "play"

    def __post_init__(self) -> None:
        object.__setattr__(self, "_r", _freeze_operator_fields(self, "radii", "play radii"))

    @property
    def n_features(self) -> int:
        """Number of features: the input plus one per play operator."""
        return 1 + len(self.radii)

    @property
    def n_state(self) -> int:
        """Length of the state vector (one play output per radius)."""
        return len(self.radii)

    def _state_text(self) -> str:
        return f"play feature state must be {self.n_state} finite play outputs (V)"

    def features(self, u: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features of a validated input sequence ``u`` (T,) from ``state``: (T, n_f), state."""
        plays, final = play_sequence(u, self._r, state)
        return np.column_stack([u, plays]), final

    def candidates(self, u: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Features of each candidate input ``u`` (N,) applied one step from the same state."""
        return np.column_stack([u, play(state, u[:, None], self._r)])

    def step(self, u: float, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One-step features ``(n_f,)`` and the next state for a scalar input ``u`` (V)."""
        new = play(state, u, self._r)
        f = np.empty(self.n_features)
        f[0] = u
        f[1:] = new
        return f, new

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        """Casadi expressions of the features and next state (max/min form)."""
        import casadi

        new = play_casadi(state, u, self.radii)
        return casadi.vertcat(u, new), new

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe description."""
        return {"name": self.name, "radii": list(self.radii), "initial_input": self.initial_input}


@dataclass(frozen=True)
class RatePlayFeatures(_StateChecks):
    """Rate-dependent play features ``F_t = [u_t, p_1,t, ..., p_n,t]``.

    The plays of :class:`piezo_env.hysteresis.RateDependentPrandtlIshlinskii` (weights left to
    the network): radii ``r_i + rate_time |u_t-1 - u_t-2| / dt``, directional updates. Within a
    sample the radii are fixed by the state, so each play output is non-decreasing in ``u_t``
    and the network's inverse from a state is that of a static map. State
    ``[u_t-1 (V), rate_t-1 (V/s), p_1, ..., p_n (V)]``.

    Attributes
    ----------
    radii : tuple of float
        Base (zero-rate) play radii, V, positive.
    rate_time : float
        Radius growth per unit drive rate, s (V per V/s), >= 0.
    dt : float
        Sample time the rate is measured over, s, > 0.
    initial_input : float
        Rest input, V: the default state has u_t-1 and every play output equal to it, rate 0.
    """

    radii: tuple[float, ...]
    rate_time: float
    dt: float
    initial_input: float = 0.0

    name = "rate-play"

    def __post_init__(self) -> None:
        from piezo_env.hysteresis import RateDependentPrandtlIshlinskii

        r = _freeze_operator_fields(self, "radii", "play radii")
        object.__setattr__(self, "_r", r)
        rate_time, dt = float(self.rate_time), float(self.dt)
        object.__setattr__(self, "rate_time", rate_time)
        object.__setattr__(self, "dt", dt)
        plays = RateDependentPrandtlIshlinskii(
            linear_weight=1.0,
            radii=self.radii,
            weights=(0.0,) * r.size,
            rate_time=rate_time,
            dt=dt,
        )
        object.__setattr__(self, "_plays", plays)

    @property
    def n_features(self) -> int:
        """Number of features: the input plus one per play operator."""
        return 1 + len(self.radii)

    @property
    def n_state(self) -> int:
        """Length of the state vector: previous input, previous rate, play outputs."""
        return 2 + len(self.radii)

    def initial_state(self) -> np.ndarray:
        """State at rest: previous input and plays at ``initial_input`` (V), rate 0."""
        state = np.full(self.n_state, self.initial_input)
        state[1] = 0.0
        return state

    def _state_text(self) -> str:
        n = len(self.radii)
        return f"rate-play feature state must be [u_t-1, rate_t-1, p_1, ..., p_{n}], finite"

    def features(self, u: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features of a validated input sequence ``u`` (T,) from ``state``: (T, n_f), state."""
        plays, final = rate_play_sequence(u, self._r, self.rate_time, self.dt, state)
        return np.column_stack([u, plays]), final

    def candidates(self, u: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Features of each candidate input ``u`` (N,) applied one step from the same state."""
        new, _ = self._plays.step(np.broadcast_to(state, (u.size, self.n_state)), u)
        return np.column_stack([u, new[:, 2:]])

    def step(self, u: float, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One-step features ``(n_f,)`` and the next state for a scalar input ``u`` (V)."""
        new, _ = self._plays.step(state, u)
        f = np.empty(self.n_features)
        f[0] = u
        f[1:] = new[2:]
        return f, new

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        """Casadi expressions of the features and next state."""
        import casadi

        _, new = self._plays.casadi_step(u, state)
        return casadi.vertcat(u, new[2:]), new

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe description."""
        return {
            "name": self.name,
            "radii": list(self.radii),
            "rate_time": self.rate_time,
            "dt": self.dt,
            "initial_input": self.initial_input,
        }


@dataclass(frozen=True)
class PastInputFeatures(_StateChecks):
    """Past-input (nlarx) features ``F_t = [u_t, u_t-1, ..., u_t-k]``; state: ``[u_t-1..u_t-k]``.

    Attributes
    ----------
    n_past : int
        Number of past inputs ``k`` (>= 1).
    initial_input : float
        Rest input, V: the default state is a buffer filled with it.
    """

    n_past: int
    initial_input: float = 0.0

    name = "past-inputs"

    def __post_init__(self) -> None:
        object.__setattr__(self, "n_past", require_int("n_past", self.n_past))
        object.__setattr__(self, "initial_input", as_scalar("initial_input", self.initial_input))

    @property
    def n_features(self) -> int:
        """Number of features: the current input plus ``n_past`` past inputs."""
        return 1 + self.n_past

    @property
    def n_state(self) -> int:
        """Length of the state vector (the input buffer)."""
        return self.n_past

    def _state_text(self) -> str:
        return (
            f"past-input feature state must be the {self.n_state} previous inputs "
            "[u_t-1, ..., u_t-k] (V), finite"
        )

    def features(self, u: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features of a validated input sequence ``u`` (T,) from ``state``: (T, n_f), state."""
        k = self.n_past
        extended = np.concatenate([state[::-1], u])
        windows = np.lib.stride_tricks.sliding_window_view(extended, k + 1)
        features = np.ascontiguousarray(windows[:, ::-1])
        return features, extended[-k:][::-1].copy()

    def candidates(self, u: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Features of each candidate input ``u`` (N,) applied one step from the same state."""
        return np.column_stack([u, np.broadcast_to(state, (u.size, self.n_state))])

    def step(self, u: float, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One-step features ``(n_f,)`` and the next state for a scalar input ``u`` (V)."""
        f = np.empty(self.n_features)
        f[0] = u
        f[1:] = state
        return f, f[:-1].copy()

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        """Casadi expressions of the features and next state (a shift register)."""
        import casadi

        features = casadi.vertcat(u, state)
        return features, features[: self.n_past]

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe description."""
        return {"name": self.name, "n_past": self.n_past, "initial_input": self.initial_input}


def bouc_wen_update(h: np.ndarray, du: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Exact update of normalized Bouc-Wen operators over an input change ``du`` (V).

    Each operator obeys ``dh = du - b |du| h - b du |h|`` with ``b = 1 / (2 level)`` (Bouc-Wen
    with exponent 1, ``alpha = 1``, ``beta = gamma = b``). While ``du`` and ``h`` have opposite
    signs, ``h`` follows the input linearly (``dh = du``); once they share a sign it relaxes
    exponentially towards ``sign(du) level``. Integrated in ``u`` rather than in time, so it is
    exact for any step size and rate-independent. Broadcasts over ``h``, ``du`` and ``levels``.
    The operator is :func:`piezo_env.operators.bouc_wen_jump_batch` with
    :func:`piezo_env.operators.normalized_bouc_wen` parameters.
    """
    return bouc_wen_jump_batch(h, du, *normalized_bouc_wen(levels))


@dataclass(frozen=True)
class BoucWenFeatures(_StateChecks):
    """Bouc-Wen operator features ``F_t = [u_t, h_1,t, ..., h_n,t]``.

    Smooth, saturating relatives of play operators (see :func:`bouc_wen_update`) with
    saturation levels spread over the input range: rate-independent memory whose loops have the
    rounded shape of piezo hysteresis. The state is ``[u_t-1, h_1,t-1, ..., h_n,t-1]``.

    Attributes
    ----------
    levels : tuple of float
        Saturation levels, V, positive and increasing.
    initial_input : float
        Rest input, V: the default state is ``[initial_input, 0, ..., 0]``.
    """

    levels: tuple[float, ...]
    initial_input: float = 0.0

    name = "bouc-wen"

    def __post_init__(self) -> None:
        lv = _freeze_operator_fields(self, "levels", "Bouc-Wen levels")
        object.__setattr__(self, "_lv", lv)
        object.__setattr__(self, "_operator", normalized_bouc_wen(lv))
        object.__setattr__(self, "_batch", BoucWenBatch(*self._operator))

    @property
    def n_features(self) -> int:
        """Number of features: the input plus one per operator."""
        return 1 + len(self.levels)

    @property
    def n_state(self) -> int:
        """Length of the state vector: the previous input and one value per operator."""
        return 1 + len(self.levels)

    def initial_state(self) -> np.ndarray:
        """State at rest: previous input ``initial_input``, operators at 0 (V)."""
        state = np.zeros(self.n_state)
        state[0] = self.initial_input
        return state

    def _state_text(self) -> str:
        n = len(self.levels)
        return f"Bouc-Wen feature state must be [u_t-1, h_1, ..., h_{n}] (V), finite"

    def features(self, u: np.ndarray, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Features of a validated input sequence ``u`` (T,) from ``state``: (T, n_f), state."""
        out = np.empty((u.size, self.n_features))
        out[:, 0] = u
        du = np.diff(u, prepend=state[0])
        h = state[1:]
        batch = self._batch
        for t in range(u.size):
            h = batch(h, du[t])
            out[t, 1:] = h
        final = np.empty(self.n_state)
        final[0] = u[-1] if u.size else state[0]
        final[1:] = h
        return out, final

    def candidates(self, u: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Features of each candidate input ``u`` (N,) applied one step from the same state."""
        out = np.empty((u.size, self.n_features))
        out[:, 0] = u
        out[:, 1:] = self._batch(state[1:], (u - state[0])[:, None])
        return out

    def step(self, u: float, state: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One-step features ``(n_f,)`` and the next state for a scalar input ``u`` (V)."""
        f = np.empty(self.n_features)
        f[0] = u
        f[1:] = self._batch(state[1:], u - state[0])
        return f, f.copy()

    def casadi_step(self, u: Any, state: Any) -> tuple[Any, Any]:
        """Casadi expressions of the features and next state (closed-form update)."""
        import casadi

        du = u - state[0]
        ak, b, _ = self._operator
        new = [bouc_wen_casadi(state[1 + i], du, ak, bi, bi) for i, bi in enumerate(b)]
        features = casadi.vertcat(u, *new)
        return features, features

    def to_dict(self) -> dict[str, Any]:
        """JSON-safe description."""
        return {"name": self.name, "levels": list(self.levels), "initial_input": self.initial_input}


def default_bouc_wen_levels(u_range: Sequence[float], n: int) -> np.ndarray:
    """Saturation levels spaced geometrically from 0.1 to 2 half-spans of the input range (V).

    Fixed, unlike play radii (which step e' learns): a Bouc-Wen loop is smooth, and the network
    draws a plant's level between two grid levels within about 0.01 um of one on a grid level,
    well inside the sensor's noise (``benchmarks/results/bouc_wen_levels.md``, one seed per
    plant); only levels beyond the grid's ends leave an error several times larger.

    Parameters
    ----------
    u_range : (float, float)
        Input range ``(lo, hi)`` in V.
    n : int
        Number of operators (>= 1).

    Returns
    -------
    numpy.ndarray, shape (n,)
        Levels in V, increasing.
    """
    low, high = as_range("u_range", u_range)
    half = 0.5 * (high - low)
    return half * np.geomspace(0.1, 2.0, require_int("n_bouc_wen", n))


FeatureMap = PlayFeatures | RatePlayFeatures | PastInputFeatures | BoucWenFeatures


def feature_map_from_dict(config: dict[str, Any]) -> FeatureMap:
    """Rebuild a feature map from :meth:`to_dict` output."""
    name = config.get("name")
    if name == "play":
        return PlayFeatures(radii=tuple(config["radii"]), initial_input=config["initial_input"])
    if name == "rate-play":
        return RatePlayFeatures(
            radii=tuple(config["radii"]),
            rate_time=config["rate_time"],
            dt=config["dt"],
            initial_input=config["initial_input"],
        )
    if name == "past-inputs":
        return PastInputFeatures(n_past=config["n_past"], initial_input=config["initial_input"])
    if name == "bouc-wen":
        return BoucWenFeatures(
            levels=tuple(config["levels"]), initial_input=config["initial_input"]
        )
    raise ValueError(f"unknown NLS feature set {name!r}; expected one of {FEATURE_SETS}")


REUSE_BYTES = 64 * 2**20
"""Most bytes of features :func:`reused_features` keeps at once (64 MiB): about 16 times the
features of the default PL140 experiment's records (some 30 000 samples x 17 features x 8 B),
so a longer experiment is still reused whole, while the features of a long measured record
are computed afresh instead of doubling the run's memory."""

_REUSED: ContextVar[dict | None] = ContextVar("reused_features", default=None)


@contextmanager
def reused_features() -> Iterator[None]:
    """Reuse each record's features within the block (:func:`sequence_features`).

    An identification run evaluates models that share one feature map (step e's network, its
    refinements and the gain moved out of them) on the same few records many times over, and
    the Bouc-Wen features of a record cost a Python loop over its samples.

    Notes
    -----
    The reuse is exact: the features are a function of the map, the input and the state, and
    a map is immutable (a learned radius or rate makes a new map). At most
    :data:`REUSE_BYTES` are kept, and nothing outlives the block. Only the thread that entered
    the block reuses them.
    """
    token = _REUSED.set({})
    try:
        yield
    finally:
        _REUSED.reset(token)


def sequence_features(
    feature_map: FeatureMap, u: np.ndarray, state: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The features of a record, computed once per feature map, input and state inside
    :func:`reused_features` (otherwise computed each time).

    Parameters
    ----------
    feature_map : FeatureMap
        The map (its object identity is part of the key; the entry holds the map, so that its
        identity cannot pass to another map while the entry lives).
    u : numpy.ndarray
        Input sequence, V, validated float64 (T,).
    state : numpy.ndarray
        The map's state at the record's start, validated float64.

    Returns
    -------
    (numpy.ndarray, numpy.ndarray)
        ``feature_map.features(u, state)``: the features (T, n_features) and the final state;
        copies, which the caller may change.
    """
    reused = _REUSED.get()
    if reused is None:
        return feature_map.features(u, state)
    key = (id(feature_map), u.dtype.str, u.tobytes(), state.dtype.str, state.tobytes())
    entry = reused.get(key)
    if entry is None:
        features, final = feature_map.features(u, state)
        kept = sum(e[1].nbytes + e[2].nbytes for e in reused.values())
        if kept + features.nbytes + final.nbytes > REUSE_BYTES:
            return features, final
        entry = reused[key] = (feature_map, features, final)
    return entry[1].copy(), entry[2].copy()
