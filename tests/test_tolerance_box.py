"""The tolerance box's models and the observer-bank screen built on them.

The box's models are checked against an independent construction (a continuous two-mode
cantilever sampled by scipy's zero-order hold at the vertex), and the screen against the true
benders of the env (the FE model at the box's vertices and at random interior points), which
the controllers never see.
"""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import scipy.signal

import controllers as ctl
from benchmarks.plants import sample_time, vertex_options
from controllers.loop import feedback_law, plant_margins, radii_matrix
from controllers.observer import ObserverBank
from controllers.settings import MS_MAX
from controllers.tolerance_box import (
    CANTILEVER_RATIOS,
    Vertex,
    arx_of,
    box_model,
    datasheet_model,
    unfolded_hz,
)
from identification.arx import ARXModel

PL127_MODEL = str(Path(__file__).parent / "data" / "pl127-model")
"""A PL127 model identified at its default 0.25 ms (``piezo identify --bender PL127``, seed 0):
its second bending mode (2.6 kHz) is folded to 1.4 kHz by the 4 kHz sampling."""


def _cantilever(f1: float, zeta1: float, dt: float, gain: float = 1.0) -> ARXModel:
    """Two-mode cantilever (second mode at the Euler-Bernoulli ratio, stiffness-proportional
    damping), sampled by zero-order hold: an ARX model of it."""
    w1 = 2 * math.pi * f1
    num, den = np.zeros(1), np.ones(1)
    for ratio, residue in ((1.0, 0.8), (CANTILEVER_RATIOS[0], 0.2)):
        w = ratio * w1
        zeta = zeta1 * ratio
        mode_num, mode_den = [gain * residue * w**2], [1.0, 2 * zeta * w, w**2]
        num = np.polyadd(np.polymul(num, mode_den), np.polymul(mode_num, den))
        den = np.polymul(den, mode_den)
    numd, dend, _ = scipy.signal.cont2discrete((num, den), dt, method="zoh")
    numd, dend = np.ravel(numd), np.ravel(dend)
    assert abs(numd[0]) < 1e-12  # strictly proper
    return ARXModel(-dend[1:] / dend[0], numd[1:] / dend[0], dt=dt)


def test_unfolded_frequency_of_an_aliased_second_mode():
    f1, dt = 420.0, 2.5e-4
    f2 = CANTILEVER_RATIOS[0] * f1  # 2632 Hz, above the 2 kHz Nyquist frequency
    assert unfolded_hz(1 / dt - f2, f1, dt) == pytest.approx(f2)
    assert unfolded_hz(f2, f1, 1e-4) == pytest.approx(f2)  # sampled at 10 kHz: no fold


@pytest.mark.parametrize("vertex", [Vertex(1.2, 1.2, 0.01), Vertex(0.8, 0.8, 0.04)])
def test_box_model_is_the_sampled_vertex_bender(vertex):
    """Moving the sampled nominal cantilever to a vertex gives the poles and static gain of the
    vertex's continuous cantilever sampled afresh, its folded second mode included (a stiffer
    bender moves that alias down, not up)."""
    f1, zeta1, dt = 420.0, 0.02, 2.5e-4
    nominal = _cantilever(f1, zeta1, dt)
    moved = box_model(nominal, vertex)
    expected = _cantilever(f1 * vertex.resonance, vertex.damping, dt, gain=vertex.gain)
    got, want = moved.poles(), expected.poles()
    for pole in want:
        assert np.min(np.abs(got - pole)) < 1e-6 * max(1.0, abs(pole)), (got, want)
    assert moved.static_gain() == pytest.approx(expected.static_gain(), rel=1e-9)


def _true_plant(bender: str, point: tuple[float, float, float], gain_ref: float):
    """The env's linear part at ``point`` (free deflection, resonance factors, damping), its gain
    scaled to ``gain_ref`` (the MPC has learned it)."""
    env = gym.make(
        "piezo_env:PiezoBender-v0", dt=sample_time(bender), **vertex_options(bender, point)
    )
    plant = ctl.PredictionModel.from_plant(env.unwrapped.model)
    a, b, c = plant.a, plant.b[:, 0], plant.c[0]
    dc = float(c @ np.linalg.solve(np.eye(a.shape[0]) - a, b))
    return a, b * gain_ref / dc, c


def _points(seed: int, count: int) -> list[tuple[float, float, float]]:
    """The box's 8 vertices and ``count`` uniform interior points."""
    rng = np.random.default_rng(seed)
    corners = [(g, r, z) for g in (0.8, 1.2) for r in (0.8, 1.2) for z in (0.01, 0.04)]
    inner = [
        (float(rng.uniform(0.8, 1.2)), float(rng.uniform(0.8, 1.2)), float(rng.uniform(0.01, 0.04)))
        for _ in range(count)
    ]
    return corners + inner


@pytest.mark.parametrize(
    ("bender", "model"), [("PL127", PL127_MODEL), ("PL140", "docs/benchmark/model")]
)
def test_screened_bank_is_stable_on_the_true_benders(bender, model):
    """Every filter the screen keeps closes a loop that is stable on the env's own bender at
    each vertex of the box and at random interior points (gain learned), within the screen's
    sensitivity bound there too; without the screen the bank holds filters whose loop is
    not stable."""
    env = gym.make("piezo_env:PiezoBender-v0", bender=bender, dt=sample_time(bender))
    mpc = ctl.make("mpc", model, env)
    bank = mpc.observer
    assert isinstance(bank, ObserverBank) and mpc.screen["robust"]
    a, b, c = mpc.model.a, mpc.model.b[:, 0], mpc.model.c[0]
    gain_ref = float(c @ np.linalg.solve(np.eye(a.shape[0]) - a, b))
    plants = [_true_plant(bender, p, gain_ref) for p in _points(seed=7, count=6)]
    law = feedback_law(mpc._hessian, mpc._q_matrix, bank.a_aug.shape[0])
    radii = radii_matrix(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants).max(axis=1)
    assert np.all(radii[bank.admissible] < 1.0)
    margins = plant_margins(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains, *law, plants)
    assert margins[bank.admissible].min() >= 1.0 / MS_MAX
    assert np.any(radii[~bank.admissible] > 1.0)
    assert bank.admissible[bank.prior] and bank.admissible[bank.fallback]


def test_screen_is_off_for_the_oracle_and_when_asked():
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    assert ctl.make("mpc", "plant", env).screen["applied"] is False
    unscreened = ctl.make("mpc", "docs/benchmark/model", env, robust_bank=False)
    assert unscreened.screen == {"applied": False, "why": "robust_bank=False"}
    assert unscreened.observer.admissible.all()
    with pytest.raises(ValueError, match="robust_bank must be True or False"):
        ctl.make("mpc", "docs/benchmark/model", env, robust_bank="yes")


def test_restricted_bank_never_selects_an_excluded_filter():
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    bank = ctl.make("mpc", "docs/benchmark/model", env, robust_bank=False).observer
    mask = np.zeros(len(bank.noise_levels), dtype=bool)
    mask[[3, 40]] = True
    bank.restrict(mask)
    rng = np.random.default_rng(0)
    for _ in range(300):
        bank.correct(float(rng.normal(0.0, 50.0)))  # large innovations favour fast filters
        bank.predict(0.0)
        assert mask[bank.selected]
    assert mask[bank.prior] and mask[bank.fallback]
    with pytest.raises(ValueError, match="at least one True"):
        bank.restrict(np.zeros_like(mask))


def test_fixed_mpc_holds_the_pl127_corner_it_diverged_on():
    """Regression: the fixed MPC on the PL127 at 0.25 ms, the corner with gain and resonance
    20 % up and damping 0.01, 10 Hz sine, reached hundreds of % of the stroke before the
    screen."""
    from benchmarks.plants import stroke_um
    from benchmarks.references import make_reference
    from benchmarks.studies.corners import vertex_env

    dt = sample_time("PL127")
    nominal = gym.make("piezo_env:PiezoBender-v0", bender="PL127", preview=20, dt=dt)
    mpc = ctl.make("mpc", PL127_MODEL, nominal)
    env = vertex_env((1.2, 1.2, 0.01), "PL127")
    stroke = stroke_um("PL127")
    reference = make_reference("sine-10Hz", 8001, dt=dt, seed=0, stroke_um=stroke)
    episode = ctl.run_episode(env, mpc, seed=0, reference=reference, stroke_um=stroke)
    assert episode.metrics["rmse_percent"] < 0.25


@pytest.mark.parametrize("name", ["mpc", "nmpc"])
def test_a_transient_at_the_drive_s_ends_does_not_ring_the_stiff_corner(name):
    """Regression: on the PL140 with free deflection and resonance 20 % up and damping 0.01
    (its second mode folded next to the first at 1 kHz), a 500 um 50 Hz sine switched on
    mid-period (155 um at the first sample) drove ``mpc`` and ``nmpc`` into a limit cycle
    between the drive's ends (68 % of the stroke) before the screen asked Ms <= MS_MAX on the
    box's vertices; the true-plant MPC reaches 0.01 %."""
    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    controller = ctl.make(name, "docs/benchmark/model", env)
    stiff = vertex_options("PL140", (1.2, 1.2, 0.01))
    corner = gym.make("piezo_env:PiezoBender-v0", preview=20, **stiff)
    t = np.arange(1, 2022) * 1e-3
    reference = 500.0 * np.sin(2.0 * np.pi * 50.0 * t)
    episode = ctl.run_episode(corner, controller, seed=0, reference=reference, stroke_um=1000.0)
    assert episode.metrics["rmse_percent"] < 2.0
    assert np.mean(np.abs(episode.voltage_V[1000:]) > 29.9) < 0.01  # not at the drive's ends


def test_plant_margins_are_the_distance_of_the_nyquist_curve_from_the_critical_point():
    """plant_margins against python-control's frequency responses of the controller (observer
    and feedback law as one system) and of the plant, on the same frequency grid."""
    import control

    from controllers.loop import FREQUENCY_POINTS, output_feedback

    env = gym.make("piezo_env:PiezoBender-v0", preview=20)
    mpc = ctl.make("mpc", "docs/benchmark/model", env, robust_bank=False)
    bank = mpc.observer
    law = feedback_law(mpc._hessian, mpc._q_matrix, bank.a_aug.shape[0])
    a, b, c = mpc.model.a, mpc.model.b[:, 0], mpc.model.c[0]
    gain_ref = float(c @ np.linalg.solve(np.eye(a.shape[0]) - a, b))
    plants = [_true_plant("PL140", p, gain_ref) for p in ((1.2, 1.2, 0.01), (0.8, 0.8, 0.04))]
    filters = [0, 13, 27]
    got = plant_margins(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains[filters], *law, plants)
    w = np.linspace(np.pi / FREQUENCY_POINTS, np.pi, FREQUENCY_POINTS)
    for i, k in enumerate(filters):
        f = output_feedback(bank.a_aug, bank.b_aug, bank.c_aug, bank.gains[k], *law)
        controller = control.ss(f.a, f.b[:, None], f.c[None, :], [[f.d]], 1e-3)
        for j, (pa, pb, pc) in enumerate(plants):
            plant = control.ss(pa, pb[:, None], pc[None, :], [[0.0]], 1e-3)
            loop = (plant * controller)(np.exp(1j * w))
            want = np.min(np.abs(1.0 - np.ravel(loop)))
            assert got[i, j] == pytest.approx(want, rel=1e-8)


@pytest.mark.parametrize(
    ("bender", "vertex"),
    [
        ("PL140", Vertex(0.8, 0.8, 0.01)),
        ("PL140", Vertex(1.2, 1.2, 0.04)),
        ("PL127", Vertex(1.0, 1.2, 0.01)),
    ],
)
def test_the_datasheet_member_of_the_true_nominal_part_is_the_vertex_bender(bender, vertex):
    """Moved by the datasheet's physics, the nominal bender's own linear part becomes the
    vertex's, aliases and lumped higher modes included, to the fit's accuracy: checked against
    the env built at the vertex (its FE model assembled afresh), over the band a controller
    tracks in (up to a quarter of the sampling rate)."""
    dt = sample_time(bender)
    nominal = gym.make("piezo_env:PiezoBender-v0", bender=bender, dt=dt)
    base = arx_of(ctl.PredictionModel.from_plant(nominal.unwrapped.model))
    member, error = datasheet_model(
        base,
        nominal.unwrapped.config.bender,
        vertex,
        damping_ratio=nominal.unwrapped.config.damping_ratio,
        order=base.na + 1,
    )
    assert error < 1e-8  # the ratio cancels the nominal part: measured 1e-11 .. 1e-12
    options = vertex_options(bender, (vertex.gain, vertex.resonance, vertex.damping))
    truth = ctl.PredictionModel.from_plant(
        gym.make("piezo_env:PiezoBender-v0", dt=dt, **options).unwrapped.model
    )
    freq = np.geomspace(1.0, 0.25 / dt, 60)
    z = np.exp(2j * np.pi * freq * dt)
    eye = np.eye(truth.a.shape[0])
    want = np.array(
        [(truth.c[:1] @ np.linalg.solve(zk * eye - truth.a, truth.b[:, :1]))[0, 0] for zk in z]
    )
    got = np.array(
        [
            np.polyval(np.r_[member.b[::-1], 0.0], 1.0 / zk)
            / np.polyval(np.r_[-member.a[::-1], 1.0], 1.0 / zk)
            for zk in z
        ]
    )
    ratio = got / want
    assert np.max(np.abs(np.abs(ratio) - 1.0)) < 2e-3
    assert np.max(np.abs(np.angle(ratio, deg=True))) < 0.05


def _env_response(bender: str, dt: float, freq: np.ndarray, **options) -> np.ndarray:
    """The env's own linear part's frequency response (first input and output)."""
    env = gym.make("piezo_env:PiezoBender-v0", bender=bender, dt=dt, **options)
    linear = ctl.PredictionModel.from_plant(env.unwrapped.model)
    eye = np.eye(linear.a.shape[0])
    return np.array(
        [
            (linear.c[:1] @ np.linalg.solve(zk * eye - linear.a, linear.b[:, :1]))[0, 0]
            for zk in np.exp(2j * np.pi * freq * dt)
        ]
    )


def test_the_datasheet_member_of_an_identified_model_is_its_response_times_the_ratio():
    """An identified model is not the FE model, so nothing cancels: the member is the ARX one
    order higher whose response is the identified model's times the FE ratio (both FE models
    built here through the env), within the fit error it reports, over the tracked band."""
    model = ctl.PredictionModel.from_hammerstein("docs/benchmark/model", 30.0)
    from controllers.adaptive import arx_from_realization

    arx = arx_from_realization(model)
    vertex = Vertex(1.0, 0.8, 0.01)
    member, error = datasheet_model(arx, "PL140", vertex, damping_ratio=0.02, order=arx.na + 1)
    assert error < 1e-3  # measured 2.6e-4
    freq = np.geomspace(1.0, 250.0, 60)
    w = np.exp(-2j * np.pi * freq * arx.dt)

    def response(m: ARXModel) -> np.ndarray:
        return np.array(
            [
                np.polyval(np.r_[m.b[::-1], 0.0], wk) / np.polyval(np.r_[-m.a[::-1], 1.0], wk)
                for wk in w
            ]
        )

    vertex_options_ = vertex_options("PL140", (1.0, 0.8, 0.01))
    moved = _env_response(vertex_options_.pop("bender"), arx.dt, freq, **vertex_options_)
    target = response(arx) * moved / _env_response("PL140", arx.dt, freq)
    ratio = response(member) / target
    assert np.max(np.abs(ratio - 1.0)) <= error * 1.01
    # and not the identified model itself: the corner moves the response by percents here
    assert np.max(np.abs(response(arx) / target - 1.0)) > 10 * error


def test_a_controller_is_refused_on_an_env_of_another_sample_time():
    """A vertex env made without dt takes the default of its own resonance (the PL127 at
    resonance x0.8: 0.5 ms); the PL127's controller (0.25 ms) is refused there in one line,
    where it used to run to 569 % of the stroke."""
    nominal = gym.make("piezo_env:PiezoBender-v0", bender="PL127", preview=20)
    mpc = ctl.make("mpc", PL127_MODEL, nominal)
    soft = vertex_options("PL127", (0.8, 0.8, 0.01))
    corner = gym.make("piezo_env:PiezoBender-v0", preview=20, **soft)
    assert corner.unwrapped.model.dt != nominal.unwrapped.model.dt
    with pytest.raises(ValueError, match=r"made for dt = 0.00025 s and the env steps every 0.0005"):
        ctl.run_episode(corner, mpc, seed=0)
