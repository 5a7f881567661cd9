"""The settings of the identification procedure, each default held once."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from identification.features import FEATURE_SETS
from piezo_env.checks import require_int, require_number
from piezo_env.signals import SIGNAL_DEFAULTS, make_signal
from piezo_env.task import TaskConfig

__all__ = [
    "MAX_RECORD_SAMPLES",
    "NLS_REFINEMENTS",
    "ORDER_TIE_PERCENT",
    "PLAY_RADII",
    "RADIUS_ITERATIONS",
    "RAND_HOLD_S",
    "RATES",
    "RECORD_SECONDS",
    "REFINEMENTS",
    "RICH_DEFAULTS",
    "IdentificationConfig",
    "env_sample_time",
]

REFINEMENTS = ("output-error", "none")
"""Choices of ``IdentificationConfig.refinement`` (step b')."""

NLS_REFINEMENTS = ("output-error", "none")
"""Choices of ``IdentificationConfig.nls_refinement`` (step e')."""

PLAY_RADII = ("learned", "grid")
"""Choices of ``IdentificationConfig.play_radii`` (step e' with play features)."""

RATES = ("off", "on", "auto")
"""Choices of ``IdentificationConfig.rate`` (step e' with play features)."""

RADIUS_ITERATIONS = 150
"""L-BFGS iterations at most of step e''s radius stage (``play_radii="learned"``): enough for
the learned radii of the Prandtl-Ishlinskii plant (plays of 3, 9 and 15 V on the PL140) to
settle within 0.02 V of them from the grid of 10 radii; each iteration costs a play pass over
the records' runs of equal input besides the free run."""

RAND_HOLD_S = 0.01
"""Hold of the RAND records (s): the paper's 10 samples at 1 ms. A new level every 10 ms puts
the records' large-signal power below about 100 Hz at any sample time."""

RECORD_SECONDS: dict[str, float] = {"rich": 12.0, "validation": 6.0}
"""Length (s) of the rich and the validation records when their sample counts are None: what
the NLS learns from is the number of RAND levels (length over hold), so the length is a
duration, as the hold is (12000 and 6000 samples at 1 ms)."""

MAX_RECORD_SAMPLES = 1_000_000
"""Most samples a record of :data:`RECORD_SECONDS` may become at a fine dt: the rich record's
features then take about 136 MB (17 features of 8 bytes per sample) and each training epoch a
million samples; 12 s reach it at dt = 12 us, a tenth of the finest default sample time
(the PL112's 0.1 ms). ``piezo simulate`` has the same limit on a run."""

RICH_DEFAULTS: dict[str, dict[str, float]] = {"sine": {"frequency": 5.0}}
"""Parameters of the rich signal when ``rich_params`` is None, besides RAND's hold
(:data:`RAND_HOLD_S`, in samples at the env's dt): the paper's 5 Hz sine (Hz)."""

ORDER_TIE_PERCENT = 0.25
"""Held-out fits (percentage points) this close to the best count as a tie between orders."""


@dataclass(frozen=True)
class IdentificationConfig:
    """Settings of :func:`identify` (validated at construction).

    The comparisons that chose the defaults below are recorded in
    ``benchmarks/results/design_measurements.md``; the defaults' own figures are regenerated in
    ``benchmarks/results/identification_precision.md``.

    Attributes
    ----------
    seed : int
        Seeds every signal, the environment and the network training.
    env_kwargs : dict
        Keyword arguments of PiezoBender-v0 (``reference`` is always None here).
    prbs_amplitude : float
        PRBS level C_P (V). 2 V, twice the paper's 1 V. Under a two-level input a
        rate-independent nonlinearity is affine at any level (Bai 2004), so the level is bounded
        only by the stroke: the white PRBS rings the first bending mode (a +-30 V PRBS would
        drive a PL140 to ~11x its rated deflection), and at 2 V its peak stays below the rated
        deflection on every catalogue bender (``tests/test_pipeline.py`` holds it below 0.9 of
        it). The level sets the signal-to-noise ratio of steps b and b' (the linear part
        alone), and above the rich record's band (about 100 Hz) of step e', so it is about as
        large as the stroke allows on every catalogue bender; its effect in closed loop is
        measured by the ratio of ``mpc`` to the oracle of
        ``benchmarks/studies/identification_precision.py``.
    prbs_clock : int
        PRBS clock period (samples). One sample: the PRBS is white up to the Nyquist frequency
        at any dt, the band the ARX model at that dt is fitted over.
    prbs_samples : int
        Length of the PRBS record (samples); its last quarter scores the candidate orders. In
        samples, not seconds: under a white input the variance of the ARX estimate goes as its
        parameters over the samples (Ljung 1999, sec. 9.4), whatever the sample time.
    orders : tuple of int
        Candidate ARX orders n (na = nb = n), scored by free-run fit on the last quarter of the
        PRBS record; near-ties (ORDER_TIE_PERCENT) go to the larger order.
    refinement : str
        Step b' after the Bayesian ARX estimate: ``"output-error"`` (default) refines the
        linear part by minimising its free-run error and chooses its order again
        (:func:`identification.steps.refine_linear_part`); ``"none"`` keeps the step b
        estimate (the paper's procedure as it is).
    rich_signal : str
        Rich excitation for the NLS and for step e': ``"random"`` (default: RAND, a new level
        drawn uniformly in +-``rich_amplitude`` every 10 ms (:data:`RAND_HOLD_S`), the paper's
        validation signal; the bender traces random loops at every amplitude, and the record
        carries large-signal power up to about 100 Hz), ``"decaying-multisine"`` (1, 3 and 7
        Hz under a decaying envelope: nested minor loops at every amplitude), ``"sine"`` (the
        paper's, one major
        loop: an NLS trained on it errs most on loops of half the stroke, where tracking
        references live), ``"multisine"``, ... Step e' estimates the linear part from the PRBS
        and this record together: the small +-2 V PRBS alone leaves it uncertain between 50 and
        100 Hz, which the MPC pays at those frequencies, and RAND's large-signal power up to
        about 100 Hz pins it there (the closed-loop ratios of
        ``benchmarks/results/identification_precision.md`` run on it).
    rich_amplitude : float
        Its amplitude (V).
    rich_params : dict or None
        Further parameters of the rich signal, in the units of :mod:`piezo_env.signals` (e.g.
        frequency, Hz; RAND's hold, samples); None: for the random signal a hold of
        :data:`RAND_HOLD_S` at the env's dt, :data:`RICH_DEFAULTS` for the sine,
        ``piezo_env.signals.SIGNAL_DEFAULTS`` for the others.
    rich_samples : int or None
        Length of the rich record (samples); None: :data:`RECORD_SECONDS` ``["rich"]`` (12 s)
        at the env's dt.
    features : str
        NLS memory features: ``"auto"`` (chosen on the selection record), or one of
        ``"play"``, ``"past-inputs"``, ``"bouc-wen"``.
    hidden : tuple of int
        Hidden layer widths of the NLS network (three tanh layers in the paper). Default
        ``(2, 2, 2)``: the network's MLP learns only the residual of an affine map of the memory
        features (:mod:`identification.nls.network`), and a wider one fits the sensor noise:
        its free-run fit stays at the noise floor as the narrow one's does, but its errors of
        about 1e-4 of the stroke, invisible in the fit, differ from seed to seed, and the MPC,
        which trusts its model, pays for them. ``benchmarks/results/identification_precision.md``
        compares it in closed loop with a 3 x 32 network and 8 Bouc-Wen operators.
    n_bouc_wen : int
        Number of Bouc-Wen operator features (``features="bouc-wen"``), their saturation levels
        spaced geometrically (:func:`identification.features.default_bouc_wen_levels`).
        16 rather than 8: the levels span a factor of 20, so 8 operators are 20^(1/7) = 1.53
        apart and a piezo loop's saturation level falls between two of them, where the affine
        map misses it; 16 are 20^(1/15) = 1.22 apart.
    max_epochs : int
        Training epochs at most (early stopping on a validation split).
    nls_refinement : str
        Step e' after the NLS training: ``"output-error"`` (default) refines the selected
        network, then the network and the linear part together, on the free-run output error
        of the PRBS and rich records, and keeps the result if the held-out selection record
        agrees (:func:`identification.steps.refine_nonlinearity`); ``"none"`` keeps step e's
        model (the paper's procedure).
    nls_refinement_iterations : int
        L-BFGS iterations at most of each of step e''s two stages. A stage normally ends
        earlier, once a window of iterations gains less than a hundredth of the estimation's own
        excess error (:data:`identification.nls.output_error.STOP_FRACTION`); 300 is a cap
        for a stage the data keep improving, high enough that the estimate is the optimum of
        the output-error cost within that tolerance rather than wherever the cap stopped the
        search. The identification report says of each stage how it ended;
        ``benchmarks/results/identification_accuracy.md`` gives step e''s share of the
        identification's time.
    play_radii : str
        With play features selected: ``"learned"`` (default) starts step e' with a stage that
        learns the play radii together with the network on the free-run output error (at most
        :data:`RADIUS_ITERATIONS` L-BFGS iterations; :mod:`identification.nls.play_radii`),
        so that plays between the grid's radii are represented by their own; ``"grid"`` keeps
        the radii of :func:`identification.features.default_play_radii`. No effect with other
        features or ``nls_refinement="none"``.
    rate : str
        With play features and learned radii (with ``play_radii="grid"`` only ``"off"`` and
        ``"auto"``, which then fits no rate): ``"on"`` learns, with the radii, a rate constant
        c >= 0 (s) and makes the plays rate-dependent, radii ``r_i + c |u_t-1 - u_t-2| / dt``
        with directional updates (:class:`identification.features.RatePlayFeatures`, the
        plays of the rate-dependent Prandtl-Ishlinskii model of Al Janaideh, Rakheja and Su
        2011, whose thresholds grow additively with the rate); ``"off"`` (default) keeps them
        rate-independent. The model stays a Hammerstein model: a static map of the input and of
        memory features, then the ARX part. The closest published extension is Kuklisova
        Pavelkova, "Estimation of Rate-Dependent Hammerstein Model of Piezo Bender Actuator"
        (2025): an ARX part after a spline static part fed with the input and a hidden variable.
        Rate-dependent radii rather than the rate as a further network input: the loop's
        widening is a lag that the plays carry until the next reversal, which a static function
        of the current rate cannot draw, and the radii keep each play output non-decreasing in
        the input within a sample, so the inverse from a state stays that of a monotone map.
        ``"auto"`` (default) fits both and keeps the rate-dependent model only if its free-run
        mean squared error on the held-out selection record is lower by more than
        :func:`identification.steps.rate_threshold`; when the records cannot determine a rate
        constant (every move follows a held sample, as under RAND and a +-2 V PRBS without an
        amplifier's slew) it fits only the rate-independent one, at no extra cost.
    validation_amplitude : float
        RAND amplitude C_R (V) of the selection and validation records.
    validation_hold : int or None
        RAND hold (samples); None: :data:`RAND_HOLD_S` (10 ms) at the env's dt.
    validation_samples : int or None
        Length of the validation record (samples; the selection record is half of it); None:
        :data:`RECORD_SECONDS` ``["validation"]`` (6 s) at the env's dt.

    The fields left None are durations in time: :func:`identification.identify` runs
    :meth:`at_sample_time` with the env's dt, and its report records the samples used.
    """

    seed: int = 0
    env_kwargs: dict = field(default_factory=dict)
    prbs_amplitude: float = 2.0
    prbs_clock: int = 1
    prbs_samples: int = 8000
    orders: tuple[int, ...] = (2, 3, 4, 5, 6)
    refinement: str = "output-error"
    rich_signal: str = "random"
    rich_amplitude: float = 30.0
    rich_params: dict | None = None
    rich_samples: int | None = None
    features: str = "auto"
    hidden: tuple[int, ...] = (2, 2, 2)
    n_bouc_wen: int = 16
    max_epochs: int = 200
    nls_refinement: str = "output-error"
    nls_refinement_iterations: int = 300
    play_radii: str = "learned"
    rate: str = "auto"
    validation_amplitude: float = 30.0
    validation_hold: int | None = None
    validation_samples: int | None = None

    def __post_init__(self) -> None:
        if self.features != "auto" and self.features not in FEATURE_SETS:
            raise ValueError(
                f"features must be 'auto' or one of {FEATURE_SETS}, got {self.features!r}"
            )
        if self.refinement not in REFINEMENTS:
            raise ValueError(f"refinement must be one of {REFINEMENTS}, got {self.refinement!r}")
        if self.nls_refinement not in NLS_REFINEMENTS:
            raise ValueError(
                f"nls_refinement must be one of {NLS_REFINEMENTS}, got {self.nls_refinement!r}"
            )
        if self.play_radii not in PLAY_RADII:
            raise ValueError(f"play_radii must be one of {PLAY_RADII}, got {self.play_radii!r}")
        if self.rate not in RATES:
            raise ValueError(f"rate must be one of {RATES}, got {self.rate!r}")
        if self.rate == "on" and self.features in ("past-inputs", "bouc-wen"):
            raise ValueError(
                f"rate='on' makes the play operators rate-dependent, and features="
                f"{self.features!r} has none: set features='play' (or 'auto'), or rate='off'"
            )
        if self.rate == "on" and self.play_radii != "learned":
            raise ValueError(
                "rate='on' learns its rate constant with the play radii: set "
                "play_radii='learned' (or rate='off')"
            )
        if not self.orders or not self.hidden:
            raise ValueError("orders and hidden must each list at least one value")
        for n in self.orders:
            require_int("ARX order", n)
        for width in self.hidden:
            require_int("hidden width", width)
        for name in ("prbs_samples", "rich_samples", "validation_samples"):
            if name == "prbs_samples" or getattr(self, name) is not None:
                require_int(f"{name} (or None)", getattr(self, name), minimum=200)
        for name in (
            "prbs_clock",
            "validation_hold",
            "max_epochs",
            "nls_refinement_iterations",
            "n_bouc_wen",
        ):
            if name != "validation_hold" or self.validation_hold is not None:
                require_int(name, getattr(self, name))
        for name in ("prbs_amplitude", "rich_amplitude", "validation_amplitude"):
            require_number(name, getattr(self, name), low=0.0, low_open=True)
        if "reference" in self.env_kwargs:
            raise ValueError("env_kwargs must not set 'reference': identification runs open loop")
        # Build a few samples of the rich signal now, so that a wrong name or parameter fails
        # here and not after the PRBS experiment.
        dt = env_sample_time(self.env_kwargs)
        make_signal(
            self.rich_signal,
            16,
            dt=dt,
            rng=np.random.default_rng(0),
            amplitude=self.rich_amplitude,
            **self.rich_signal_params(dt),
        )

    def rich_signal_params(self, dt: float | None = None) -> dict:
        """Parameters of the rich signal besides its amplitude.

        Parameters
        ----------
        dt : float, optional
            Sample time (s) the default RAND hold is counted at; default: that of
            ``env_kwargs`` (:func:`env_sample_time`).
        """
        if self.rich_params is not None:
            return dict(self.rich_params)
        if self.rich_signal == "random":
            dt = env_sample_time(self.env_kwargs) if dt is None else dt
            return {"hold": _samples(RAND_HOLD_S, dt)}
        if self.rich_signal in RICH_DEFAULTS:
            return dict(RICH_DEFAULTS[self.rich_signal])
        return dict(SIGNAL_DEFAULTS.get(self.rich_signal, {}))

    def at_sample_time(self, dt: float) -> IdentificationConfig:
        """This config with its durations counted in samples at ``dt`` (s).

        ``rich_samples``, ``validation_samples`` and ``validation_hold`` left None become
        :data:`RECORD_SECONDS` and :data:`RAND_HOLD_S` at ``dt``, and ``rich_params`` the rich
        signal's parameters (:meth:`rich_signal_params`); values given stay as they are.

        Raises
        ------
        ValueError
            If ``dt`` is not a positive number, or a record would be shorter than 200 samples
            or longer than :data:`MAX_RECORD_SAMPLES` at it (then give the record's length in
            samples, or another dt).
        """
        require_number("dt (s)", dt, low=0.0, low_open=True)
        seconds = {
            name: RECORD_SECONDS[key]
            for name, key in (("rich_samples", "rich"), ("validation_samples", "validation"))
            if getattr(self, name) is None
        }
        counts = {name: _samples(duration, dt) for name, duration in seconds.items()}
        # Each message names the dt that suits every record left to its default duration.
        for name, count in counts.items():
            record = f"the {name.removesuffix('_samples')} record of {seconds[name]:g} s"
            if count < 200:
                raise ValueError(
                    f"{record} is {count} samples at dt = {dt:g} s, fewer than 200: use a dt "
                    f"of at most {min(seconds.values()) / 200:g} s (--dt on the command line), "
                    f"or give {name} (>= 200) in IdentificationConfig"
                )
            if count > MAX_RECORD_SAMPLES:
                raise ValueError(
                    f"{record} is {count:,} samples at dt = {dt:g} s, more than the "
                    f"{MAX_RECORD_SAMPLES:,} an identification takes: use a dt of at least "
                    f"{max(seconds.values()) / MAX_RECORD_SAMPLES:g} s (--dt on the command "
                    f"line), or give {name} in IdentificationConfig"
                )
        if self.validation_hold is None:
            counts["validation_hold"] = _samples(RAND_HOLD_S, dt)
        return dataclasses.replace(self, rich_params=self.rich_signal_params(dt), **counts)


def env_sample_time(env_kwargs: dict) -> float:
    """The sample time (s) of ``PiezoBender-v0`` made with ``env_kwargs``: its ``dt``, else
    the bender's default (:func:`piezo_env.default_dt`)."""
    settings = {name: env_kwargs[name] for name in ("bender", "dt") if name in env_kwargs}
    return float(TaskConfig.from_kwargs(**settings).dt)


def _samples(seconds: float, dt: float) -> int:
    """``seconds`` as a whole number of samples at ``dt`` (s), at least one."""
    return max(1, round(seconds / dt))
