"""Output-error refinement of the Hammerstein model: its network, then network and linear part
together (step e' of identify)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.signal

from identification.arx import ARXModel
from identification.config import IdentificationConfig
from identification.features import PastInputFeatures
from identification.nls import NLS
from identification.nls.output_error import (
    FreeRun,
    free_run_rms,
    move_gain,
    refine_nls_output_error,
)

# A lightly damped resonance (|p| = 0.97 at 50 Hz for dt = 1 ms) with a zero at -0.6: the
# bender's first mode in miniature, y = B/F z + v, with z = NLS(u) a static nonlinearity.
POLE = 0.97 * np.exp(2j * np.pi * 50e-3)
F_TRUE = np.array([2 * POLE.real, -(abs(POLE) ** 2)])
B_TRUE = np.array([0.05, 0.03])
U_MAX = 30.0
NOISE = 1.0  # sensor noise half-width (um): uniform, standard deviation 1/sqrt(3)


def _nls(params: dict[str, np.ndarray]) -> NLS:
    return NLS(PastInputFeatures(n_past=2), params, u_range=(-U_MAX, U_MAX))


def _true_params() -> dict[str, np.ndarray]:
    """z = u + 30 * 0.1 * w^T tanh(W x + c): the identity plus a smooth nonlinearity of a few
    volts that depends on the current and the two past inputs."""
    rng = np.random.default_rng(0)
    return {
        "feature_mean": np.zeros(3),
        "feature_scale": np.full(3, U_MAX),
        "z_mean": np.array(0.0),
        "z_scale": np.array(U_MAX),
        "layer0_weight": rng.normal(0.0, 1.5, (8, 3)),
        "layer0_bias": rng.normal(0.0, 0.5, 8),
        "out_weight": 0.1 * rng.normal(0.0, 1.0, 8),
        "out_bias": np.array(0.0),
        "skip_weight": np.array([1.0, 0.0, 0.0]),
        "skip_bias": np.array(0.0),
    }


def _record(nls: NLS, n: int, seed: int, noise: float = NOISE) -> tuple[np.ndarray, np.ndarray]:
    """A random-hold input over the full range, and the output of the true Hammerstein
    system (scipy's filter, not the code under test) plus white uniform sensor noise."""
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-U_MAX, U_MAX, n // 5 + 1), 5)[:n]
    y0 = scipy.signal.lfilter(np.r_[0.0, B_TRUE], np.r_[1.0, -F_TRUE], nls.evaluate(u))
    return u, y0 + noise * rng.uniform(-1.0, 1.0, n)


def _perturbed(params: dict[str, np.ndarray], scale: float, seed: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    out = {}
    for key, value in params.items():
        trainable = key not in ("feature_mean", "feature_scale", "z_mean", "z_scale")
        out[key] = value + scale * rng.normal(0.0, 1.0, np.shape(value)) if trainable else value
    return out


@pytest.fixture(scope="module")
def synthetic():
    """The true system's records; the start: the network perturbed, and the linear part with
    its resonance moved from 50 to 50.3 Hz, its damping and its gain changed (the size of the
    errors step b' leaves)."""
    true = _nls(_true_params())
    arx = ARXModel(F_TRUE, B_TRUE, dt=1e-3)
    records = [_record(true, 3000, seed) for seed in (1, 2)]
    start = _nls(_perturbed(_true_params(), 0.05, seed=3))
    pole = 0.969 * np.exp(2j * np.pi * 50.3e-3)
    start_arx = ARXModel([2 * pole.real, -(abs(pole) ** 2)], B_TRUE * 1.01, dt=1e-3)
    fixed = refine_nls_output_error(start, arx, records, max_iterations=200, refine_linear=False)
    joint = refine_nls_output_error(start, start_arx, records, max_iterations=200)
    return true, arx, records, start, start_arx, fixed, joint


def _recursion(f: np.ndarray, b: np.ndarray, z: np.ndarray) -> np.ndarray:
    """``y = B / (1 - A) z`` from rest by the difference equation, one sample at a time."""
    y = np.zeros(z.size)
    for t in range(z.size):
        y[t] = sum(f[i] * y[t - 1 - i] for i in range(f.size) if t - 1 - i >= 0) + sum(
            b[j] * z[t - 1 - j] for j in range(b.size) if t - 1 - j >= 0
        )
    return y


def test_the_free_run_is_the_arx_recursion_from_rest():
    """The free run the refinement differentiates is the difference equation B/(1 - A) from
    rest, to rounding."""
    torch = pytest.importorskip("torch")
    z = np.random.default_rng(4).normal(0.0, 10.0, 2000)
    expected = _recursion(F_TRUE, B_TRUE, z)
    run = FreeRun(z.size, F_TRUE.size, B_TRUE.size, torch)
    got = run.free_run(torch.from_numpy(z), torch.from_numpy(F_TRUE), torch.from_numpy(B_TRUE))
    got = got.numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(ARXModel(F_TRUE, B_TRUE).simulate(z), expected, atol=1e-9)


def test_the_free_runs_backward_pass_is_its_gradient():
    """The hand-written adjoint of the recursion against central finite differences, in the
    input and in both coefficient vectors (torch.autograd.gradcheck), with and without the
    coefficients among the inputs that need a gradient."""
    torch = pytest.importorskip("torch")
    from identification.nls.free_run import free_run

    rng = np.random.default_rng(7)
    pole = 0.9 * np.exp(2j * np.pi * 0.1)
    a = torch.tensor([2 * pole.real, -(abs(pole) ** 2), 0.05], dtype=torch.float64)
    b = torch.tensor([0.3, -0.2, 0.1, 0.05], dtype=torch.float64)
    z = torch.from_numpy(rng.normal(0.0, 1.0, 60))
    for needs in ((True, True, True), (True, False, False), (False, True, False)):
        inputs = [x.clone().requires_grad_(need) for x, need in zip((z, a, b), needs, strict=True)]
        assert torch.autograd.gradcheck(free_run, inputs, eps=1e-6, atol=1e-8)
    for n in (1, 2, 3):  # records shorter than the lags
        inputs = [x.clone().requires_grad_(True) for x in (z[:n], a, b)]
        assert torch.autograd.gradcheck(free_run, inputs, eps=1e-6, atol=1e-8)


def test_beyond_the_stability_boundary_the_free_run_is_the_recursion_until_it_overflows():
    """A line search may probe an unstable linear part: there the objective is still the
    recursion (a barrier growing as |p|^2n), until its squared error leaves float64's range;
    then the product of spectra on a grid twice the record (numpy's FFT here), finite."""
    torch = pytest.importorskip("torch")
    z = np.random.default_rng(8).normal(0.0, 1.0, 3000)
    size = 1 << (2 * z.size).bit_length()

    def spectral(f: np.ndarray, b: np.ndarray) -> np.ndarray:
        w = 2 * np.pi * np.arange(size // 2 + 1) / size
        lag = lambda n: np.exp(-1j * np.outer(w, np.arange(1, n + 1)))  # noqa: E731
        h = (lag(b.size) @ b) / (1.0 - lag(f.size) @ f)
        return np.fft.irfft(np.fft.rfft(z, size) * h, size)[: z.size]

    run = FreeRun(z.size, 2, 2, torch)

    def through(f: np.ndarray) -> np.ndarray:
        a, b = torch.from_numpy(f), torch.from_numpy(B_TRUE)
        return run.free_run(torch.from_numpy(z), a, b).numpy()

    mild = 1.02 * np.exp(2j * np.pi * 0.05)  # 1.02^3000: 6e25, no overflow
    f = np.array([2 * mild.real, -(abs(mild) ** 2)])
    expected = _recursion(f, B_TRUE, z)
    assert np.abs(expected).max() > 1e20
    np.testing.assert_allclose(through(f), expected, rtol=1e-9, atol=0)
    far = 1.5 * np.exp(2j * np.pi * 0.05)  # 1.5^3000 overflows
    f = np.array([2 * far.real, -(abs(far) ** 2)])
    with np.errstate(over="ignore", invalid="ignore"):
        assert not np.all(np.isfinite(_recursion(f, B_TRUE, z)))
    got = through(f)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, spectral(f, B_TRUE), atol=1e-9 * np.abs(got).max())


def test_a_joint_stage_that_ends_beyond_the_finite_range_is_refused():
    from identification.nls.output_error import _joint_end

    start = ARXModel(F_TRUE, B_TRUE, dt=1e-3, noise_bound=2.0)
    params = {"w": np.ones(3)}
    kept, why = _joint_end(start, F_TRUE, B_TRUE, params)
    assert why is None and kept.noise_bound == 2.0 and kept.dt == 1e-3
    np.testing.assert_array_equal(kept.a, F_TRUE)

    def refusal(a, b, params):
        kept, why = _joint_end(start, a, b, params)
        assert kept is None
        return why

    assert "non-finite" in refusal(np.array([np.nan, 0.1]), B_TRUE, params)
    assert "non-finite" in refusal(F_TRUE, B_TRUE, {"w": np.array([np.inf])})
    assert "unstable" in refusal(np.array([2.1, -1.1]), B_TRUE, params)


def test_the_free_runs_gradient_does_not_depend_on_the_blas_thread_count():
    """The backward pass sums its lagged products without BLAS, whose dot product of a long
    vector sums in an order that depends on its threads (OpenBLAS splits it above about
    10,000 elements): the gradient, and so the refined model, is the same to the bit with one
    BLAS thread as with the machine's default."""
    import threadpoolctl

    torch = pytest.importorskip("torch")
    from identification.nls.free_run import free_run

    rng = np.random.default_rng(11)
    z0 = rng.normal(0.0, 1.0, 40_000)
    g = torch.from_numpy(rng.normal(0.0, 1.0, z0.size))

    def gradients() -> list[np.ndarray]:
        z, a, b = (
            torch.tensor(x, dtype=torch.float64, requires_grad=True)
            for x in (z0, F_TRUE, B_TRUE)
        )
        free_run(z, a, b).backward(g)
        return [x.grad.numpy().copy() for x in (z, a, b)]

    default = gradients()
    with threadpoolctl.threadpool_limits(1):
        one = gradients()
    for got, expected in zip(one, default, strict=True):
        np.testing.assert_array_equal(got, expected)


def test_distinct_rows_spread_back_to_the_features():
    from identification.nls.output_error import distinct_rows

    x = np.repeat(np.random.default_rng(3).normal(size=(50, 3)), [1, 2, 5, 1, 3] * 10, axis=0)
    x[36] = x[35]  # a run of one made equal to the run before: one row with it
    rows, index = distinct_rows(x)
    np.testing.assert_array_equal(rows[index], x)
    assert np.all(np.any(rows[1:] != rows[:-1], axis=1))
    assert rows.shape[0] == 49


def test_refinement_recovers_the_true_hammerstein_output_to_the_noise_level(synthetic):
    """From a perturbed network (and, jointly, a perturbed resonance), the output-error fit
    brings the residual down to the sensor noise (uniform +-1 um: RMS 1/sqrt(3)) and the
    noise-free output on fresh input to well under it: the maximum-likelihood estimate of an
    output-error model with white noise."""
    true, arx, _records, start, start_arx, fixed, joint = synthetic
    noise_rms = NOISE / np.sqrt(3.0)
    fresh = _record(true, 3000, seed=9, noise=0.0)
    assert fixed.rms_before > 3 * noise_rms
    assert joint.rms_before > 4 * noise_rms
    assert free_run_rms(start, start_arx, [fresh]) > 4 * noise_rms
    for fit in (fixed, joint):
        assert fit.rms_after == pytest.approx(noise_rms, rel=0.03)
        assert free_run_rms(fit.nls, fit.arx, [fresh]) < 0.2 * noise_rms
        assert fit.iterations >= 1 and fit.evaluations >= fit.iterations
    assert fixed.arx is arx
    # the resonance itself is recovered (the gain split between the blocks is not identifiable)
    np.testing.assert_allclose(
        np.sort_complex(joint.arx.poles()),
        np.sort_complex(ARXModel(F_TRUE, B_TRUE).poles()),
        atol=1e-4,
    )


def test_moving_the_gain_between_the_blocks_leaves_the_output(synthetic):
    _true, arx, records, *_ = synthetic
    true = _nls({**_true_params(), "z_mean": np.array(2.5)})  # an offset scales with the gain
    u = records[0][0]
    scaled, linear = move_gain(true, arx, 1.7)
    np.testing.assert_allclose(scaled.evaluate(u), true.evaluate(u) / 1.7, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(
        linear.simulate(scaled.evaluate(u)), arx.simulate(true.evaluate(u)), atol=1e-9
    )
    with pytest.raises(ValueError, match="gain"):
        move_gain(true, arx, 0.0)


def test_the_refinement_leaves_its_start_alone_and_repeats_bitwise(synthetic):
    _true, _arx, records, start, start_arx, _fixed, joint = synthetic
    perturbed = _perturbed(_true_params(), 0.05, seed=3)
    for key, value in start.arrays().items():
        np.testing.assert_array_equal(value, perturbed[key])
    again = refine_nls_output_error(start, start_arx, records, max_iterations=200)
    for key, value in joint.nls.arrays().items():
        np.testing.assert_array_equal(again.nls.arrays()[key], value)
    np.testing.assert_array_equal(again.arx.theta, joint.arx.theta)
    assert joint.nls.feature_map == start.feature_map
    assert joint.nls.u_range == start.u_range
    assert [stage["iterations"] for stage in joint.stages] == [
        stage["iterations"] for stage in again.stages
    ]
    assert joint.linear_note is None
    # the refined linear part's r_hat is its own largest equation error, not the start's
    assert joint.arx.noise_bound != start_arx.noise_bound


def test_a_refusal_is_reported_not_raised():
    """Step e' on a model whose linear part is unstable has no free run to refine: it is
    refused with the reason, step e's model stays, and the markdown report renders it."""
    from identification.hammerstein import HammersteinModel
    from identification.report import _nls_refinement_section
    from identification.steps import NlsFit, refine_nonlinearity

    true = _nls(_true_params())
    unstable = ARXModel([1.5], [1.0], dt=1e-3)
    u, y = _record(true, 400, seed=1)
    fit = NlsFit(HammersteinModel(true, unstable), "past-inputs", {}, 1.0, (u, y))
    refinement = refine_nonlinearity(fit, [(u, y)], IdentificationConfig())
    assert not refinement.accepted and "unstable" in refinement.refusal
    assert refinement.model is fit.model and refinement.stages == ()
    record = {
        **refinement.record(),
        "linear_part": {
            "zeros": [],
            "poles": [[1.5, 0.0]],
            "frequencies_hz": [1.0],
            "response_error_vs_plant": [0.0],
        },
    }
    text = "\n".join(_nls_refinement_section(record, noise_bound=1.0))
    assert "not kept" in text and "unstable" in text and "n/a" in text
    record["training_rms_um"] = {"before": 1.0, "after": None}  # an infinite error in JSON
    assert "n/a" in "\n".join(_nls_refinement_section(record, noise_bound=1.0))


def test_bad_input_is_refused_with_the_reason():
    true = _nls(_true_params())
    arx = ARXModel(F_TRUE, B_TRUE, dt=1e-3)
    u, y = _record(true, 200, seed=1)
    with pytest.raises(ValueError, match="unstable"):
        refine_nls_output_error(true, ARXModel([1.5], [1.0]), [(u, y)])
    with pytest.raises(ValueError, match="same length"):
        refine_nls_output_error(true, arx, [(u, y[:-1])])
    with pytest.raises(ValueError, match="non-finite"):
        refine_nls_output_error(true, arx, [(u, np.r_[y[:-1], np.nan])])
    with pytest.raises(ValueError, match="at least one"):
        refine_nls_output_error(true, arx, [])
    with pytest.raises(ValueError, match="max_iterations"):
        refine_nls_output_error(true, arx, [(u, y)], max_iterations=0)
    with pytest.raises(ValueError, match="nls_refinement"):
        IdentificationConfig(nls_refinement="joint")
    with pytest.raises(ValueError, match="nls_refinement_iterations"):
        IdentificationConfig(nls_refinement_iterations=0)


# -- learned play radii -----------------------------------------------------------------------


def test_play_radius_derivatives_match_finite_differences():
    from identification.nls.play_radii import play_radius_derivatives
    from piezo_env.operators import play_sequence

    rng = np.random.default_rng(1)
    u = np.repeat(rng.uniform(-30, 30, 200), 3)
    radii = np.array([2.5, 7.3, 13.1])
    plays, _ = play_sequence(u, radii, np.zeros(3))
    derivative = play_radius_derivatives(u, radii, plays)
    step = 1e-6
    for i in range(radii.size):
        shift = np.zeros(3)
        shift[i] = step
        up = play_sequence(u, radii + shift, np.zeros(3))[0][:, i]
        down = play_sequence(u, radii - shift, np.zeros(3))[0][:, i]
        np.testing.assert_allclose(derivative[:, i], (up - down) / (2 * step), atol=1e-6)
    assert set(np.unique(derivative)) <= {-1.0, 0.0, 1.0}


def _play_plant(true_radii: tuple[float, float], seed: int = 0):
    """RAND input, z = 0.7 u + 0.15 (P_r1 + P_r2), y = first-order lag of z plus uniform noise
    of half-width 0.05 (standard deviation 0.0289); a network started on the grid radii
    (10, 20) V of two plays over +-30 V."""
    from identification.nls import fit_nls
    from piezo_env.operators import play_sequence

    rng = np.random.default_rng(seed)
    u = np.repeat(rng.uniform(-30, 30, 400), 10)
    plays, _ = play_sequence(u, np.asarray(true_radii), np.zeros(2))
    z = 0.7 * u + plays @ np.array([0.15, 0.15])
    arx = ARXModel([0.6], [0.4], dt=1e-3)
    y = arx.simulate(z) + rng.uniform(-0.05, 0.05, u.size)
    start = fit_nls(
        u, z, features="play", n_play=2, u_range=(-30, 30), hidden=(2,), max_epochs=30, seed=0
    )
    assert start.feature_map.radii == (10.0, 20.0)
    return start, arx, [(u, y)]


def test_learned_radii_find_plays_between_the_grid_radii(tmp_path):
    """Plays of 7 and 16 V (between the grid's 10 and 20): the radius stage lands within
    0.1 V of them (measured 0.017 V) and the fit reaches the noise floor, as good as with
    plays on the grid and the grid radii kept."""
    from identification.hammerstein import HammersteinModel

    start, arx, records = _play_plant((7.0, 16.0))
    fixed = refine_nls_output_error(start, arx, records, max_iterations=100, refine_linear=False)
    learned = refine_nls_output_error(
        start, arx, records, max_iterations=100, refine_linear=False, radius_iterations=150
    )
    np.testing.assert_allclose(learned.nls.feature_map.radii, (7.0, 16.0), atol=0.1)
    on_grid = refine_nls_output_error(
        *_play_plant((10.0, 20.0)), max_iterations=100, refine_linear=False
    )
    floor = 0.05 / np.sqrt(3.0)
    assert on_grid.rms_after < 1.1 * floor
    assert learned.rms_after < 1.1 * on_grid.rms_after
    assert fixed.rms_after > 3.0 * on_grid.rms_after  # the grid alone misses them (6x)
    assert learned.stages[0]["radii_after"] == list(learned.nls.feature_map.radii)
    # The model files carry the learned radii, and the inverse runs on them.
    model = HammersteinModel(learned.nls, learned.arx)
    loaded = HammersteinModel.load(model.save(tmp_path / "model"))
    assert loaded.nls.feature_map.radii == learned.nls.feature_map.radii
    state = loaded.nls.initial_state()
    for u in (12.0, -3.0, 5.0):
        z, state_next = loaded.nls.step(u, state)
        solved = loaded.nls.solve_inverse(z, state, xtol=1e-12)
        assert solved.u == pytest.approx(u, abs=1e-8)
        state = state_next


def test_radius_stage_is_refused_bad_counts_and_skipped_without_plays():
    start, arx, records = _play_plant((7.0, 16.0))
    with pytest.raises(ValueError, match="radius_iterations"):
        refine_nls_output_error(start, arx, records, radius_iterations=-1)
    past = _nls(_true_params())
    fit = refine_nls_output_error(
        past, arx, records, max_iterations=2, refine_linear=False, radius_iterations=5
    )
    assert len(fit.stages) == 1 and fit.nls.feature_map == past.feature_map


def test_play_radii_setting_is_validated():
    assert IdentificationConfig().play_radii == "learned"
    with pytest.raises(ValueError, match="play_radii"):
        IdentificationConfig(play_radii="fixed")


# -- rate-dependent plays ---------------------------------------------------------------------


def test_rate_play_features_follow_the_plant_plays_step_by_step():
    """The features' plays are the rate-dependent plant's (weights aside), bitwise, over a
    drive with ramps, holds and reversals; the batch, one-step, candidate and casadi paths
    agree and the map survives a dict round trip."""
    import casadi

    from identification.features import RatePlayFeatures, feature_map_from_dict
    from piezo_env.hysteresis import RateDependentPrandtlIshlinskii

    plant = RateDependentPrandtlIshlinskii.for_voltage(30.0)
    features = RatePlayFeatures(radii=plant.radii, rate_time=plant.rate_time, dt=plant.dt)
    rng = np.random.default_rng(2)
    u = np.repeat(rng.uniform(-30, 30, 120), rng.integers(1, 4, 120))
    batch, final = features.features(u, features.initial_state())
    state, one = features.initial_state(), features.initial_state()
    u_sym, s_sym = casadi.MX.sym("u"), casadi.MX.sym("s", features.n_state)
    step = casadi.Function("f", [u_sym, s_sym], list(features.casadi_step(u_sym, s_sym)))
    symbolic = features.initial_state()
    for t, v in enumerate(u):
        row = features.candidates(np.array([v, v + 1.0]), one)[0]
        f, one = features.step(float(v), one)
        state, _ = plant.step(state, v)
        np.testing.assert_array_equal(batch[t, 1:], state[2:])
        np.testing.assert_array_equal(f, batch[t])
        np.testing.assert_array_equal(row, batch[t])
        f_sym, symbolic = step(v, symbolic)
        np.testing.assert_allclose(np.asarray(f_sym).ravel(), batch[t], atol=1e-12)
        symbolic = np.asarray(symbolic).ravel()
    np.testing.assert_array_equal(final, state)
    assert feature_map_from_dict(features.to_dict()) == features


def _rate_plant(rate_time: float, seed: int = 0):
    """A multisine (1-30 Hz, +-28 V, no holds: every sample moves at its own rate) through
    rate-dependent plays of radii 7 and 16 V, z = 0.7 u + 0.15 (p_1 + p_2), a first-order
    lag and uniform noise of half-width 0.05; a network started on the grid radii (10, 20)."""
    from identification.nls import fit_nls
    from piezo_env.operators import rate_play_sequence

    rng = np.random.default_rng(seed)
    dt = 1e-3
    t = np.arange(6000) * dt
    frequencies, phases = rng.uniform(1, 30, 6), rng.uniform(0, 2 * np.pi, 6)
    u = np.sin(2 * np.pi * frequencies * t[:, None] + phases).sum(axis=1)
    u *= 28.0 / np.abs(u).max()
    plays, _ = rate_play_sequence(u, np.array([7.0, 16.0]), rate_time, dt, np.zeros(4))
    z = 0.7 * u + plays @ np.array([0.15, 0.15])
    arx = ARXModel([0.6], [0.4], dt=dt)
    y = arx.simulate(z) + rng.uniform(-0.05, 0.05, u.size)
    start = fit_nls(
        u, z, features="play", n_play=2, u_range=(-30, 30), hidden=(2,), max_epochs=30, seed=0
    )
    return start, arx, [(u, y)]


@pytest.mark.parametrize(
    ("rate_time", "tolerance"),
    [(7e-4, 5e-5), (0.0, 2e-5)],  # measured errors 2e-7 s and 2.3e-6 s
)
def test_rate_constant_is_learned(rate_time, tolerance):
    """A rate constant of 0.7 dt is learned within 0.05 dt, a rate-independent map gives
    c ~ 0 (within 0.02 dt); the radii land within 0.1 V of 7 and 16 V and the fit reaches the
    noise floor (0.0289)."""
    start, arx, records = _rate_plant(rate_time)
    fit = refine_nls_output_error(
        start,
        arx,
        records,
        max_iterations=100,
        refine_linear=False,
        radius_iterations=150,
        learn_rate=True,
    )
    features = fit.nls.feature_map
    assert features.name == "rate-play" and features.dt == 1e-3
    assert features.rate_time == pytest.approx(rate_time, abs=tolerance)
    assert fit.stages[0]["rate_time_s"] == features.rate_time
    np.testing.assert_allclose(features.radii, (7.0, 16.0), atol=0.1)
    assert fit.rms_after < 1.1 * 0.05 / np.sqrt(3.0)


def test_rate_aware_inverse_at_a_given_rate(tmp_path):
    """From a state holding the previous input and the previous rate (the plan's), the
    network's inverse gives back the voltage to 1e-9 V, also after a save and load."""
    from identification.hammerstein import HammersteinModel

    start, arx, records = _rate_plant(7e-4)
    fit = refine_nls_output_error(
        start,
        arx,
        records,
        max_iterations=20,
        refine_linear=False,
        radius_iterations=40,
        learn_rate=True,
    )
    loaded = HammersteinModel.load(HammersteinModel(fit.nls, fit.arx).save(tmp_path / "m"))
    assert loaded.nls.feature_map == fit.nls.feature_map
    for rate in (0.0, 2000.0, 8000.0):  # V/s
        _, state = loaded.nls.features(np.array([0.0, 12.0, 20.0, 25.0]))
        state[1] = rate
        for u in (24.0, 26.5, 10.0):
            z, _ = loaded.nls.step(u, state)
            solved = loaded.nls.solve_inverse(z, state, xtol=1e-13)
            assert solved.status == "ok"
            assert solved.u == pytest.approx(u, abs=1e-9)


def test_rate_threshold_and_settings():
    from identification.steps import rate_threshold

    # 12 sigma rms / sqrt(N) with sigma = bound / sqrt(3).
    assert rate_threshold(np.sqrt(3.0), 2.0, 3600) == pytest.approx(12.0 * 2.0 / 60.0)
    assert IdentificationConfig().rate == "auto"
    assert IdentificationConfig(rate="auto", play_radii="grid").rate == "auto"
    with pytest.raises(ValueError, match="rate must be"):
        IdentificationConfig(rate="yes")
    with pytest.raises(ValueError, match="play_radii='learned'"):
        IdentificationConfig(rate="on", play_radii="grid")
    start, arx, records = _rate_plant(0.0)
    with pytest.raises(ValueError, match="learn_rate needs"):
        refine_nls_output_error(start, arx, records, learn_rate=True)


def test_records_determine_a_rate_only_when_a_play_moves_right_after_a_move():
    from identification.nls.output_error import rate_is_determined

    _, _, held = _play_plant((7.0, 16.0))  # RAND held for 10 samples
    _, _, smooth = _rate_plant(7e-4)  # a multisine: every sample moves
    assert not rate_is_determined((10.0, 20.0), held, 1e-3)
    assert rate_is_determined((10.0, 20.0), smooth, 1e-3)


def test_rate_constant_is_zero_when_the_records_cannot_tell():
    """Held RAND records: every move follows a held sample, so no play meets a rate-grown
    edge; the rate constant is set to 0 and the stage says why."""
    start, arx, records = _play_plant((7.0, 16.0))
    fit = refine_nls_output_error(
        start,
        arx,
        records,
        max_iterations=5,
        refine_linear=False,
        radius_iterations=10,
        learn_rate=True,
    )
    assert fit.nls.feature_map.rate_time == 0.0
    assert "do not determine the rate constant" in fit.stages[0]["rate_note"]


# -- the feature set chosen after step e' -----------------------------------------------------


def _step_e(chosen: str, play_radii: tuple[float, float], seed: int):
    """Step e on the play plant of :func:`_play_plant`: a play network on the grid radii and a
    past-inputs network, both fitted to (u, z); ``chosen`` is the set step e is made to have
    chosen, as on a plant where it scored a few tenths above play. The selection record is
    a second RAND record of the same plant."""
    from identification.hammerstein import HammersteinModel
    from identification.nls import fit_nls
    from identification.steps import NlsFit
    from piezo_env.operators import play_sequence

    play, arx, records = _play_plant(play_radii, seed=seed)
    u = records[0][0]
    rng = np.random.default_rng(seed + 100)
    u_sel = np.repeat(rng.uniform(-30, 30, 200), 10)
    plays, _ = play_sequence(u_sel, np.asarray(play_radii), np.zeros(2))
    y_sel = arx.simulate(0.7 * u_sel + plays @ np.array([0.15, 0.15]))
    y_sel = y_sel + rng.uniform(-0.05, 0.05, u_sel.size)
    plays_u, _ = play_sequence(u, np.asarray(play_radii), np.zeros(2))
    past = fit_nls(
        u,
        0.7 * u + plays_u @ np.array([0.15, 0.15]),
        features="past-inputs",
        u_range=(-30, 30),
        hidden=(2,),
        max_epochs=30,
        seed=0,
    )
    candidates = {"play": play, "past-inputs": past}
    fit = NlsFit(
        HammersteinModel(candidates[chosen], arx), chosen, {}, 1.0, (u_sel, y_sel), 0, candidates
    )
    return fit, records


def test_play_is_refined_beside_step_e_choice_and_wins_after_step_e():
    """Step e chose past-inputs on a plant of plays at 7 and 16 V (off the grid radii 10 and
    20 that step e scores play on): step e' refines play too, learns its radii, and keeps it,
    with the lower held-out error; the choice is recorded with both errors."""
    from identification.steps import refine_and_choose

    fit, records = _step_e("past-inputs", (7.0, 16.0), seed=0)
    config = IdentificationConfig(nls_refinement_iterations=60, rate="off")
    kept, refinement = refine_and_choose(fit, records, config, sensor_noise_bound=0.05)
    choice = refinement.feature_choice
    assert choice["step_e"] == "past-inputs" and set(choice["held_out_rms_um"]) == {
        "past-inputs",
        "play",
    }
    assert choice["held_out_rms_um"]["play"] < choice["held_out_rms_um"]["past-inputs"]
    assert kept.features == "play" == choice["kept"]
    assert refinement.model.nls.feature_map.name == "play"
    np.testing.assert_allclose(refinement.model.nls.feature_map.radii, (7.0, 16.0), atol=0.2)
    assert refinement.record()["feature_choice"] == choice


def test_no_rival_when_step_e_chose_play_or_sits_at_the_noise_floor():
    """Step e chose play: step e' refines it alone and records no choice. Step e chose
    past-inputs, but the sensor's bound (100 um) puts its refined error below the noise
    floor: no rival could do measurably better, so play is not refined, and the record says
    why."""
    from identification.steps import refine_and_choose

    config = IdentificationConfig(nls_refinement_iterations=20, rate="off")
    fit, records = _step_e("play", (7.0, 16.0), seed=1)
    kept, refinement = refine_and_choose(fit, records, config, sensor_noise_bound=0.05)
    assert kept is fit and refinement.feature_choice is None
    fit, records = _step_e("past-inputs", (7.0, 16.0), seed=1)
    kept, refinement = refine_and_choose(fit, records, config, sensor_noise_bound=100.0)
    choice = refinement.feature_choice
    assert kept is fit and set(choice["held_out_rms_um"]) == {"past-inputs"}
    assert choice["excess_over_noise_um2"] <= choice["threshold_um2"]
    assert "noise floor" in choice["why"]


def _regression(n: int, p: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A linear regression y = X theta + v, v uniform within +-1, whose regressors are
    correlated and scaled over two decades (condition number about 150), so that L-BFGS needs
    several windows of iterations."""
    rng = np.random.default_rng(seed)
    mixing = np.eye(p) + 0.6 * rng.normal(size=(p, p)) / np.sqrt(p)
    x = rng.normal(size=(n, p)) @ mixing * np.logspace(0.0, -2.0, p)
    return x, x @ rng.normal(size=p) + rng.uniform(-1.0, 1.0, n)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_lbfgs_stops_within_its_tolerance_of_the_least_squares_optimum(seed):
    """The windowed L-BFGS of step e' stops once a window lowers the mean squared error by less
    than ``stop_tolerance``; on a least-squares problem its shortfall from the exact optimum
    (numpy's lstsq, an independent method) is within that tolerance, a fraction
    (``STOP_FRACTION``) of the estimation's own excess error p sigma^2 / N."""
    torch = pytest.importorskip("torch")
    from identification.nls.output_error import STOP_FRACTION, _autograd, _lbfgs, stop_tolerance

    n, p = 4000, 30
    x, y = _regression(n, p, seed)
    optimum = np.linalg.lstsq(x, y, rcond=None)[0]
    best = float(np.mean((y - x @ optimum) ** 2))
    theta = torch.zeros(p, dtype=torch.float64, requires_grad=True)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)

    def objective():
        error = xt @ theta - yt
        return (error * error).mean()

    stage = _lbfgs([theta], _autograd(objective, torch), 300, torch, n)
    reached = float(objective().detach())
    assert stage["stopped"] == "tolerance" and not stage["capped"]
    assert stage["iterations"] < 300
    assert 0.0 <= reached - best <= stop_tolerance(reached, p, n)
    assert stop_tolerance(2.0, 30, 4000) == pytest.approx(STOP_FRACTION * 30 * 2.0 / 4000)


def test_lbfgs_started_at_the_optimum_has_converged():
    """At the exact least-squares optimum the gradient vanishes (to rounding): L-BFGS's own test
    ends the stage before a line search."""
    torch = pytest.importorskip("torch")
    from identification.nls.output_error import _autograd, _lbfgs

    x, y = _regression(500, 4, 5)
    x, y = x * np.logspace(0.0, 2.0, 4), y  # a well-scaled optimum, exact to rounding
    optimum = np.linalg.solve(x.T @ x, x.T @ y)
    theta = torch.tensor(optimum, requires_grad=True)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)

    def objective():
        error = xt @ theta - yt
        return (error * error).mean()

    with torch.no_grad():
        error = xt @ theta - yt
        gradient = 2.0 * (xt.T @ error) / 500
    stage = _lbfgs([theta], _autograd(objective, torch), 300, torch, 500)
    assert stage["stopped"] == "converged", (stage, float(gradient.abs().max()))
    assert stage["iterations"] <= 1


def test_lbfgs_reports_its_cap():
    torch = pytest.importorskip("torch")
    from identification.nls.output_error import _autograd, _lbfgs

    x, y = _regression(2000, 30, 4)
    theta = torch.zeros(30, dtype=torch.float64, requires_grad=True)
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)

    def objective():
        error = xt @ theta - yt
        return (error * error).mean()

    for cap in (8, 21):  # within one window, and one iteration past the first
        theta = torch.zeros(30, dtype=torch.float64, requires_grad=True)
        stage = _lbfgs([theta], _autograd(objective, torch), cap, torch, 2000)
        assert stage["stopped"] == "cap" and stage["capped"]
        evaluations = cap * 5 // 4
        assert stage["iterations"] == cap or stage["evaluations"] >= evaluations
        assert stage["iterations"] <= cap and stage["evaluations"] <= evaluations + 1


def test_rate_play_outputs_are_the_directional_plays_move_by_move():
    """The scan of the radius stage's directional plays gives, move by move, what the plays'
    definition gives: a rising move raises an output to its lower edge u - (r + lag), a
    falling one lowers it to its upper edge u + (r + lag); the sign and the move of the edge
    each output last touched follow."""
    from identification.nls.play_radii import rate_play_outputs, rate_play_runs

    rng = np.random.default_rng(11)
    u = np.repeat(rng.uniform(-20.0, 20.0, 300), rng.integers(1, 4, 300))
    u[::9] = np.round(u[::9])
    radii = np.array([0.5, 2.0, 6.0, 11.0])
    moves, direction, rate, _ = rate_play_runs(u, 1e-3, 0.2)
    lag = 5e-4 * rate
    plays, sign, touch = rate_play_outputs(moves, direction, lag, radii, 0.2)
    p = np.full(radii.size, 0.2)
    last_sign, last_touch = np.zeros(radii.size), np.full(radii.size, -1)
    for t in range(moves.size):
        if direction[t] > 0:
            edge = moves[t] - (radii + lag[t])
            p = np.maximum(edge, p)
        else:
            edge = moves[t] + (radii + lag[t])
            p = np.minimum(edge, p)
        at_edge = p == edge
        last_sign = np.where(at_edge, -direction[t], last_sign)
        last_touch = np.where(at_edge, t, last_touch)
        np.testing.assert_array_equal(plays[t], p)
        np.testing.assert_array_equal(sign[t], last_sign)
        np.testing.assert_array_equal(touch[t], last_touch)
