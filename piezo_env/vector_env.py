"""Natively batched PiezoBender-v0: N benders stepped with one matrix product.

Each sub-environment i has its own random generator, seeded ``seed + i`` on ``reset(seed=seed)``
(as SyncVectorEnv seeds its copies), and draws its reference and noise exactly as a single
``PiezoBenderEnv`` does, so sub-environment i reproduces the single env reset with seed + i
sample for sample. Autoreset follows Gymnasium's next-step mode, as ``SyncVectorEnv`` does: the
step after an episode ends resets that sub-environment, ignores its action, and returns reward 0,
both flags False, and the reset's observation and info (initial voltage 0 V, not saturated).

Performance: the batched state update is split into blocks of at most 1024 rows so that each
matrix product stays below OpenBLAS's multi-threading threshold (tiny threaded products stall
on small machines).

Domain randomisation (``randomize``): each sub-environment draws its own plant at each of its
resets, from its own generator and in the single env's order (plant, reference, noise), so
sub-environment i still reproduces the single env seeded seed + i. Plants of different damping
and resonance keep different modes (the reduction is exact per plant), so every plant's step
matrix is placed in one common layout that has a slot for every FE mode (zeros where a plant
drops a mode; :mod:`piezo_env.plant_rows`), and the step is one stacked
(N, 1, k) x (N, k, k) product. The default path (no randomisation) is unchanged: one shared
matrix, reduced to the nominal plant's modes.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from piezo_env.blas import single_blas_thread
from piezo_env.checks import require_int
from piezo_env.plant_rows import RowHysteresis, padded_layout, scaled_step_matrix_t
from piezo_env.randomization import PLANT_INFO_KEYS
from piezo_env.reference import (
    ReferenceStream,
    draw_reference,
    render_references,
    segment_samples,
)
from piezo_env.task import (
    DEFAULT_HORIZON,
    NOISE_BLOCK,
    TaskAttributes,
    TaskConfig,
    check_max_episode_steps,
    check_reset_options,
    episode_reference,
)

__all__ = ["PiezoBenderVectorEnv"]

_ROW_BLOCK = 1024
_INFO_KEYS = (
    "deflection_um",
    "voltage_V",
    "effective_voltage_V",
    "charge_uC",
    "reference_um",
    "saturated",
)


class PiezoBenderVectorEnv(TaskAttributes, VectorEnv):
    """``num_envs`` PiezoBender-v0 environments in one batched model.

    Spaces, reward, timing and info keys are those of :class:`piezo_env.env.PiezoBenderEnv`,
    batched along the first axis; every info key comes with its ``_key`` mask (all True), as
    ``SyncVectorEnv`` gives it. With ``randomize``, ``info["plant"]`` (a dict of arrays with
    their masks) reports the plants drawn at that reset or autoreset, masked to the
    sub-environments that drew one; ``plant_draws[i]`` is sub-environment i's current draw and
    ``task.draw_plant``/``piezo_env.task.drawn_plant`` rebuild its model.

    Parameters
    ----------
    num_envs : int
        Number of sub-environments (>= 1).
    max_episode_steps : int or None
        Episode length (steps); None or -1: no time limit (as ``gymnasium.make`` reads it).
    config : TaskConfig, optional
        Task settings; keyword settings override its fields.
    render_mode : None
        The vector env does not render.
    **settings
        The fields of :class:`piezo_env.task.TaskConfig`.
    """

    metadata: ClassVar[dict[str, Any]] = {
        "render_modes": [],
        "autoreset_mode": AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        num_envs: int = 1,
        *,
        max_episode_steps: int | None = DEFAULT_HORIZON,
        config: TaskConfig | None = None,
        render_mode: str | None = None,
        **settings: Any,
    ) -> None:
        require_int("num_envs", num_envs)
        if render_mode is not None:
            raise ValueError("the vector env does not render; make single envs to render")
        self.num_envs = int(num_envs)
        self.max_episode_steps = check_max_episode_steps(max_episode_steps)
        self._adopt_task(config, settings)
        if self.config.bench_options:
            raise ValueError(
                "the vector env does not model the amplifier, the sensor, the drift or the "
                f"disturbance (amplifier={self.config.amplifier!r}, "
                f"sensor={self.config.sensor!r}, drift={self.config.drift!r}, "
                f"disturbance={self.config.disturbance!r}); make single envs "
                '(gymnasium.make_vec(..., vectorization_mode="sync")) for these options'
            )
        self.render_mode = None
        self.single_observation_space = self.task.observation_space()
        self.single_action_space = self.task.action_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        # Rows per matrix product; a test may set it small to cross the split.
        self._row_block = _ROW_BLOCK

        self._setup_physics()
        self._setup_buffers()

    def _setup_physics(self) -> None:
        """Step matrices and state arrays of the N benders (per-env ones with randomisation)."""
        n = self.num_envs
        # The output columns come out scaled: deflection in um, Gamma theta_tip in uC.
        self._q_per_rad = self.model.params.piezo_moment * 1e6
        self._randomization = self.task.randomization
        self._row_hyst: RowHysteresis | None = None
        self._steps_t: np.ndarray | None = None  # per-env step matrices (randomisation only)
        if self._randomization is None:
            k = self.model.discrete.n_states
            self._step_t = scaled_step_matrix_t(self.model, np.arange(k + 2), k)
        else:
            k = self.model.discrete.n_creep + 2 * self.model.beam.n_dofs + 2
            layout = padded_layout(self.model.discrete, self.model.beam.n_dofs)
            self._step_t = scaled_step_matrix_t(self.model, layout, k)
            self._steps_t = np.repeat(self._step_t[None], n, axis=0)
            self._row_hyst = RowHysteresis(self.model.hysteresis, n)
        self.plant_draws: list[Any] = [None] * n
        self._plant_values = np.zeros((len(PLANT_INFO_KEYS), n))
        self._k = k
        self._x = np.zeros((n, k + 2))
        self._out = np.zeros((n, k + 2))
        # Column-major, so each state component of all envs is contiguous.
        self._hyst = np.zeros((n, self.model.hysteresis.state_size), order="F")
        self._y = np.zeros(n)  # true tip deflection (um)
        self._q_rot = np.zeros(n)  # rotation part of the charge, Gamma theta_tip (uC)

    def _segments(self, n: int) -> int:
        """``n`` samples rounded up to whole reference segments."""
        return -(-n // self._segment) * self._segment

    def _setup_buffers(self) -> None:
        """Generators, reference and noise buffers, step counters, lockstep bookkeeping."""
        n = self.num_envs
        self._rngs = [seeding.np_random(None)[0] for _ in range(n)]
        # References and noise are stored sample-major, (time, env): in lockstep one step reads
        # one contiguous row. Without a time limit the reference buffer grows when needed.
        horizon = DEFAULT_HORIZON if self.max_episode_steps is None else self.max_episode_steps
        self._segment = segment_samples(self.model.dt)
        self._ref_len = self._segments(horizon + self.preview + 1)
        self._ref = np.zeros((self._ref_len, n), dtype=np.float32)
        self._ref_filled = np.zeros(n, dtype=np.int64)
        self._streams: list[ReferenceStream | None] = [None] * n
        self._ref_filled_min = 0
        self._noise = np.zeros((NOISE_BLOCK, n))
        self._noise_index = np.zeros(n, dtype=np.int64)
        self._t = np.zeros(n, dtype=np.int64)
        self._prev_done = np.zeros(n, dtype=bool)
        self._reset_u_eff = np.zeros(n)  # effective voltage (V) of each env's latest reset
        self._rest: dict[float, tuple[np.ndarray, np.ndarray, float]] = {}
        # True while every sub-env is at the same step (reset together): then the reference and
        # noise are read as one column instead of a gather.
        self._lockstep = True
        self._rows = np.arange(n)
        self._all_true = np.ones(n, dtype=bool)
        self._window = np.arange(self.preview + 1)

    # -- Gymnasium API -------------------------------------------------------------------------

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        seeds = self._seeds(seed)
        options = dict(options or {})
        initial = check_reset_options(options, self._u_max)  # before anything changes
        spec = episode_reference(options, self._reference_spec)
        if spec is not None and not isinstance(spec, str):  # an array is checked now too
            self.task.reference_stream(spec, None)
        if seed is not None:
            self._rngs = [seeding.np_random(s)[0] for s in seeds]
        self._prev_done[:] = False
        self._reset_rows(self._rows, options)
        deflection = self._y.copy()
        reference = self._reference_now()
        measured = deflection + self._take_noise()
        voltage = np.full(self.num_envs, initial)
        _, u_eff = (self._row_hyst or self.model.hysteresis).step(self._hyst, voltage)
        info = self._info(deflection, reference, voltage, u_eff, np.zeros(self.num_envs, bool))
        if self._randomization is not None:
            self._add_plant_info(info, self._all_true)
        return self._observe(measured), info

    def step(
        self, actions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        voltage, saturated = self._drive_voltages(actions)
        self._hyst, u_eff = (self._row_hyst or self.model.hysteresis).step(self._hyst, voltage)
        self._advance(u_eff)

        done = self._prev_done
        any_done = bool(done.any())
        if any_done:
            self._reset_rows(np.flatnonzero(done), {})
        if self._reference_spec is not None:
            self._extend_references()
        deflection = self._y
        reference = self._reference_now()
        reward = np.subtract(deflection, reference)
        reward *= reward
        reward *= -1.0 / self.model.stroke_um**2
        terminated, truncated = self._episode_ends(deflection)
        if any_done:  # the reset's outcome, as SyncVectorEnv returns it
            reward[done] = 0.0
            terminated[done] = False
            truncated[done] = False
            voltage[done] = 0.0
            u_eff = np.array(u_eff, dtype=float)
            u_eff[done] = self._reset_u_eff[done]
            saturated[done] = False
        self._prev_done = terminated | truncated
        measured = deflection + self._take_noise()
        info = self._info(deflection, reference, voltage, u_eff, saturated)
        if any_done and self._randomization is not None:
            self._add_plant_info(info, done)
        return self._observe(measured), reward, terminated, truncated, info

    # -- helpers -------------------------------------------------------------------------------

    def _seeds(self, seed: int | list[int | None] | None) -> list[int | None]:
        """Each env's seed: ``seed + i`` for an int (as SyncVectorEnv), or one per env."""
        if seed is None:
            return [None] * self.num_envs
        if isinstance(seed, (int, np.integer)):
            return [int(seed) + i for i in range(self.num_envs)]
        seeds = list(seed)
        if len(seeds) != self.num_envs:
            raise ValueError(
                f"seed list must have num_envs = {self.num_envs} entries, got {len(seeds)}"
            )
        return seeds

    def _drive_voltages(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Validated, clipped voltages (V) and which were clipped (the amplifier saturates)."""
        a = np.asarray(actions)
        if a.dtype.kind not in "fiu" or a.shape not in ((self.num_envs, 1), (self.num_envs,)):
            raise ValueError(
                f"actions must be a numeric array of shape ({self.num_envs}, 1) (one voltage in "
                f"V per env), got {type(actions).__name__} of dtype {a.dtype} and shape {a.shape}"
            )
        a = a.astype(np.float64, copy=False).reshape(self.num_envs)
        finite = np.isfinite(a)
        if not finite.all():
            raise ValueError(f"actions must be finite voltages in V, got {a[~finite][0]!r}")
        voltage = np.clip(a, -self._u_max, self._u_max)
        return voltage, voltage != a

    def _advance(self, u_eff: np.ndarray) -> None:
        """One sample of every bender under its effective voltage (V): state, y (um), charge."""
        k, x, out = self._k, self._x, self._out
        x[:, k] = u_eff
        if self._steps_t is None:
            block = self._row_block
            for start in range(0, self.num_envs, block):
                rows = slice(start, start + block)
                np.matmul(x[rows], self._step_t, out=out[rows])
        else:  # one small matrix-vector product per env, looped in C
            np.matmul(x[:, None, :], self._steps_t, out=out[:, None, :])
        self._y = out[:, k].copy()  # a new array each step: the info returned keeps its own
        self._q_rot = out[:, k + 1].copy()
        self._x, self._out = out, x
        self._t += 1

    def _episode_ends(self, deflection: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(terminated, truncated) of every env after this step."""
        if self.deflection_limit is not None:
            terminated = np.abs(deflection) > self.deflection_limit
        else:
            terminated = np.zeros(self.num_envs, dtype=bool)
        if self.max_episode_steps is None:
            truncated = np.zeros(self.num_envs, dtype=bool)
        else:
            truncated = self._t >= self.max_episode_steps
        return terminated, truncated

    def _reset_rows(self, rows: np.ndarray, options: dict[str, Any]) -> None:
        """Start a new episode in each env of ``rows``: plant at rest, reference, noise."""
        voltage = check_reset_options(options, self._u_max)
        if self._randomization is None:
            self._rest_rows(rows, voltage)
        else:
            self._draw_plants(rows, voltage)
        self._t[rows] = 0
        self._lockstep = len(rows) == self.num_envs or (
            self._lockstep and bool(np.all(self._t == 0))
        )
        spec = episode_reference(options, self._reference_spec)
        # Each env's generator in the single env's order: reference, then noise.
        draws = self._draw_references(rows, spec)
        r = self.noise_bound
        if r > 0:
            noise = np.array([self._rngs[i].uniform(-r, r, NOISE_BLOCK) for i in rows])
            self._write_columns(self._noise, rows, noise, NOISE_BLOCK)
        self._noise_index[rows] = 0
        if spec is not None:
            self._start_references(rows, spec, draws)

    def _rest_rows(self, rows: np.ndarray, voltage: float) -> None:
        """Put the nominal plant of each env in ``rows`` at rest under ``voltage`` (V)."""
        state, hyst, u_eff = self._rest_state(voltage)
        self._x[rows, : self._k] = state
        self._x[rows, self._k :] = 0.0
        self._hyst[rows] = hyst
        self._reset_u_eff[rows] = u_eff
        self._y[rows] = self.model.discrete.output_matrix[0] @ state * 1e6
        self._q_rot[rows] = self.model.discrete.output_matrix[1] @ state * self._q_per_rad

    def _draw_references(self, rows: np.ndarray, spec: object) -> list[Any]:
        """The drawn parameters of each env's named reference (none for an array or None)."""
        if not isinstance(spec, str):
            return []
        model = self.model
        return [
            draw_reference(
                spec,
                self._segment,
                dt=model.dt,
                stroke_um=model.stroke_um,
                rng=self._rngs[i],
                band=self.task.reference_band,
            )
            for i in rows
        ]

    def _start_references(self, rows: np.ndarray, spec: object, draws: list[Any]) -> None:
        """The reference streams of ``rows`` and their first samples in the buffer."""
        if draws:  # rendered together: one batch, the same samples as one at a time
            first = render_references(draws, self._segment, dt=self.model.dt)
            first = first.astype(np.float32)
            streams = [
                self.task.reference_stream(spec, self._rngs[i], first=row)
                for i, row in zip(rows, first, strict=True)
            ]
        else:
            streams = [self.task.reference_stream(spec, None) for _ in rows]
        for i, stream in zip(rows, streams, strict=True):
            self._streams[i] = stream
        values = np.array([stream.ensure(self._segment)[: self._ref_len] for stream in streams])
        self._write_columns(self._ref, rows, values, values.shape[1])
        self._ref_filled[rows] = values.shape[1]
        self._ref_filled_min = int(self._ref_filled.min())

    def _draw_plants(self, rows: np.ndarray, voltage: float) -> None:
        """Draw the plant of each env in ``rows`` (first draw of its reset) and put it at rest.

        Each plant is rebuilt (FE, modes, matrix exponentials; about 1-5 ms) and its step
        matrix placed in the common padded layout.
        """
        k, n_modes = self._k, self.model.beam.n_dofs
        with single_blas_thread():
            for i in rows:
                model, draw = self.task.draw_plant(self._rngs[i])
                layout = padded_layout(model.discrete, n_modes)
                self._steps_t[i] = scaled_step_matrix_t(model, layout, k)
                state, hyst = model.static_state(voltage)
                self._x[i] = 0.0
                self._x[i, layout[: len(state)]] = state
                self._hyst[i] = hyst
                self._row_hyst.set_row(i, model.hysteresis)
                self._reset_u_eff[i] = float(model.hysteresis.step(hyst, voltage)[1])
                out = model.discrete.output_matrix @ state
                self._y[i] = out[0] * 1e6
                self._q_rot[i] = out[1] * model.params.piezo_moment * 1e6
                self.plant_draws[i] = draw
                values = draw.info()
                self._plant_values[:, i] = [values[key] for key in PLANT_INFO_KEYS]

    def _add_plant_info(self, info: dict[str, Any], mask: np.ndarray) -> None:
        """``info["plant"]``: the plants drawn by the envs in ``mask``, nested as SyncVectorEnv."""
        plant: dict[str, Any] = {}
        for key, values in zip(PLANT_INFO_KEYS, self._plant_values, strict=True):
            plant[key] = np.where(mask, values, 0.0)
            plant["_" + key] = mask.copy()
        info["plant"] = plant
        info["_plant"] = mask.copy()

    def _rest_state(self, voltage: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(LTI state, hysteresis state, u_eff V) at rest under ``voltage``, solved once each."""
        if voltage not in self._rest:
            state, hyst = self.model.static_state(voltage)
            u_eff = float(self.model.hysteresis.step(hyst, voltage)[1])
            self._rest[voltage] = (state, hyst, u_eff)
        return self._rest[voltage]

    def _write_columns(self, target: np.ndarray, rows: np.ndarray, values: np.ndarray, n: int):
        """target[:n, rows] = values.T, as one slice assignment when every env resets."""
        if len(rows) == self.num_envs:
            target[:n] = values.T
        else:
            target[:n, rows] = values.T

    def _extend_references(self) -> None:
        """Draw further reference segments where the coming preview reaches past them."""
        if self._lockstep and int(self._t[0]) + self.preview < self._ref_filled_min:
            return
        need = self._t + (self.preview + 1)
        longest = int(need.max())
        if longest > self._ref_len:  # only without a time limit
            self._grow_references(longest)
        for i in np.flatnonzero(need > self._ref_filled):
            values = self._streams[i].ensure(int(need[i]))
            end = min(len(values), self._ref_len)
            self._ref[self._ref_filled[i] : end, i] = values[self._ref_filled[i] : end]
            self._ref_filled[i] = end
        self._ref_filled_min = int(self._ref_filled.min())

    def _grow_references(self, n: int) -> None:
        """Make the reference buffer hold at least ``n`` samples per env (doubling)."""
        grown = np.zeros((self._segments(max(n, 2 * self._ref_len)), self.num_envs), np.float32)
        grown[: self._ref_len] = self._ref
        self._ref, self._ref_len = grown, len(grown)

    def _take_noise(self) -> np.ndarray:
        if self.noise_bound == 0:
            return np.zeros(self.num_envs)
        r = self.noise_bound
        if self._lockstep:
            j = int(self._noise_index[0])
            if j == NOISE_BLOCK:
                self._noise[:] = np.array([rng.uniform(-r, r, NOISE_BLOCK) for rng in self._rngs]).T
                self._noise_index[:] = j = 0
            self._noise_index += 1
            return self._noise[j].copy()
        for i in np.flatnonzero(self._noise_index == NOISE_BLOCK):
            self._noise[:, i] = self._rngs[i].uniform(-r, r, NOISE_BLOCK)
            self._noise_index[i] = 0
        values = self._noise[self._noise_index, self._rows]
        self._noise_index += 1
        return values

    def _reference_now(self) -> np.ndarray:
        if self._reference_spec is None:
            return np.zeros(self.num_envs)
        if self._lockstep:
            return self._ref[int(self._t[0])].astype(np.float64)
        return self._ref[self._t, self._rows].astype(np.float64)

    def _observe(self, measured: np.ndarray) -> np.ndarray:
        if self._reference_spec is None:
            return measured.astype(np.float32)[:, None]
        obs = np.empty((self.num_envs, 2 + self.preview), dtype=np.float32)
        obs[:, 0] = measured
        if self._lockstep:
            t = int(self._t[0])
            obs[:, 1:] = self._ref[t : t + self.preview + 1].T
        else:
            obs[:, 1:] = self._ref[self._t[:, None] + self._window, self._rows[:, None]]
        return obs

    def _charge_uc(self, voltage: np.ndarray) -> np.ndarray:
        """Drive charge (uC) from the applied voltage and the tip rotation."""
        params = self.model.params
        charge = np.multiply(voltage, params.capacitance * 1e6)
        charge += self._q_rot
        return charge

    def _info(self, deflection, reference, voltage, u_eff, saturated) -> dict[str, Any]:
        values = (
            deflection,
            voltage,
            np.asarray(u_eff, dtype=float),
            self._charge_uc(voltage),
            reference,
            saturated,
        )
        info: dict[str, Any] = {}
        for key, value in zip(_INFO_KEYS, values, strict=True):
            if key == "reference_um" and self._reference_spec is None:
                continue
            info[key] = value
            info["_" + key] = self._all_true.copy()
        return info
