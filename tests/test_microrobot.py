"""The 3-DOF micro-robot: physics anchors, play/detailed agreement, gait analysis, gradients,
long-run robustness and parameter recovery from tracked features (PHYSICS.md §3-5, §8-9, §14).

Compiled functions are shared: `history` is one jitted `mr.pose_history` with the cycle
count and steps per cycle static, so every test using the same grid and contact model reuses
one compilation."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import greybox
from greybox._estimate.fit import fit
from greybox._model.parameters import set_values
from greybox._model.waveforms import PulseTrain
from greybox._simulate.synthetic import CameraDefects, record
from greybox.blocks._robot import TwoSidedThermal

mr = greybox.device_module("microrobot")

POWER_W = 0.02


@functools.partial(jax.jit, static_argnums=(4, 5))  # model values traced: no recompiles
def history(model, period_s, duty, power_W, n_cycles, steps_per_cycle):
    return mr.pose_history(model, period_s, duty, power_W, n_cycles, steps_per_cycle)


def symmetric(model):
    """Both frames bare Si and the spot centred: equal heating of the two sides."""
    return set_values(model, ["absorptance_right", "spot.y_m"], [model.absorptance_left, 0.0])


def test_spot_capture_matches_physics_anchor():
    m = mr.SPEC.model()
    f = m.absorbed_fractions(jnp.zeros(3)) / jnp.array([m.absorptance_left, m.absorptance_right])
    np.testing.assert_allclose(f, [0.2304, 0.0491], atol=2e-4)  # PHYSICS.md §14


def test_closed_form_thermal_zoh_matches_matrix_exponential():
    h = np.array([1e-4, 1e-3, 0.016, 0.3])
    for thermal in (
        TwoSidedThermal(),
        TwoSidedThermal(side_coupling_W_per_K=0.0, beam_capacitance_J_per_K=3e-7),
    ):
        phi, gamma = thermal.zoh_matrices(jnp.asarray(h))
        a, b = (np.asarray(m) for m in thermal.network().linear_matrices())
        aug = np.zeros((6, 6))
        aug[:4, :4], aug[:4, 4:] = a, b
        for k, hk in enumerate(h):  # expm([[A, B], [0, 0]] h) = [[Phi, Gamma], [0, I]]
            ref = scipy.linalg.expm(aug * hk)
            np.testing.assert_allclose(phi[k], ref[:4, :4], rtol=0, atol=1e-11)
            np.testing.assert_allclose(
                gamma[k], ref[:4, 4:], rtol=0, atol=1e-10 * np.abs(ref[:4, 4:]).max()
            )


# PHYSICS.md §14 reference: P = 20 mW, T_p = 0.5 s, 3 s, h = 2 ms
ANCHOR = (0.5, 0.5, POWER_W, 6, 250)


def test_detailed_reduces_to_play_under_symmetric_heating():
    play = symmetric(mr.SPEC.model(substeps=1))
    detailed = set_values(
        symmetric(mr.SPEC.model(substeps=1, contacts="friction")),
        ["locomotion.law.v_eps_m_per_s"],
        [1e-10],
    )
    out = []
    for m in (play, detailed):
        advance, turn, swing = mr.cycle_summary(m, history(m, *ANCHOR), ANCHOR[-1])
        out.append((np.asarray(advance), np.asarray(turn), np.asarray(swing)))
    (a_p, t_p, s_p), (a_d, _, _) = out
    # play closed form per side: max(0, S_pp - W) once the thermal cycle is periodic
    expected = max(0.0, float(s_p[-1, 0]) - float(play.locomotion.play_width_m()))
    assert expected > 0.1e-6
    assert float(a_p[-1]) == pytest.approx(expected, abs=2e-9)
    assert float(a_d[-1]) == pytest.approx(expected, abs=5e-9)
    assert np.max(np.abs(t_p)) < 1e-9
    assert float(a_d.sum()) == pytest.approx(float(a_p.sum()), abs=0.01e-6)  # whole 3 s
    # PHYSICS.md §8.2/§14: at the nominal v_eps = 10 nm/s creep adds to it, X = 0.66 um in 3 s
    creeping = set_values(detailed, ["locomotion.law.v_eps_m_per_s"], [1e-8])
    assert float(history(creeping, *ANCHOR)[-1, 4]) == pytest.approx(0.66e-6, rel=0.03)


def test_one_sided_heating_detailed_matches_reference_and_turns_to_cool_side():
    # PHYSICS.md §14: 3-DOF, one-sided heating, 3 s: X = 0.68 um, Y ~ 0, psi = -0.001 deg
    m = mr.SPEC.model(substeps=1, contacts="friction")
    x, y, psi = (float(v) for v in history(m, *ANCHOR)[-1, 4:7])
    assert x == pytest.approx(0.68e-6, rel=0.05)
    assert abs(y) < 0.01e-6
    assert -1e-4 < psi < 0.0  # clockwise: towards the cooler (gold, -y) side


def test_turning_sign_and_symmetry_play():
    m = mr.SPEC.model(substeps=1)
    r = jax.jit(
        lambda m: mr.turning_vs_power_ratio(m, jnp.array([60e-6, 30e-6]), 0.016, 0.5, POWER_W)
    )(m)
    ratio, rate = np.asarray(r["power_ratio_left_right"]), np.asarray(r["turn_rate_rad_per_s"])
    assert ratio[0] > ratio[1] > 1.0
    assert (
        rate[0] < rate[1] < 0.0
    )  # hotter left side: turns right (psi decreases), more so at higher ratio
    states = history(symmetric(m), 0.016, 0.5, POWER_W, 8, 20)
    assert float(states[-1, 4]) > 0.3e-6 and abs(float(states[-1, 6])) < 1e-6


def test_speed_has_an_optimum_period_of_a_few_time_constants():
    m = mr.SPEC.model(substeps=1)
    periods = jnp.array([3e-3, 6e-3, 10e-3, 16e-3, 24e-3, 48e-3, 96e-3])
    r = jax.jit(lambda m: mr.speed_vs_period(m, periods, 0.5, POWER_W))(m)
    speed = np.asarray(r["speed_m_per_s"])
    best = int(np.argmax(speed))
    assert 0 < best < periods.size - 1
    tau = float(m.thermal.frame_time_constant_s())
    assert 2.0 < float(periods[best]) / tau < 20.0
    # long periods: full swing, one-sided play step = 1/2 (S_pp - W) per cycle
    w = float(m.locomotion.play_width_m())
    assert float(r["step_m"][-1]) == pytest.approx(
        0.5 * (float(r["stroke_swing_m"][-1]) - w), abs=2e-9
    )
    assert abs(float(speed[0])) < 1e-8  # short period: swing below W, no motion


def test_gradients_forward_equal_reverse_play_model():
    paths = ["absorptance_left", "locomotion.foot_forward_N", "thermal.frame_capacitance_J_per_K"]
    x0 = jnp.array([0.448, 0.3e-6, 1.9e-7])

    def final(v, m):
        mm = set_values(m, paths, [v[0], v[1], v[2]])
        return mr.pose_history(mm, 0.016, 0.5, POWER_W, 2, 16)[-1, 4]

    # (the detailed solver's implicit-function derivative: tests/test_contacts.py)
    m = mr.SPEC.model(substeps=1)
    rev, fwd = jax.jit(lambda v, m: (jax.grad(final)(v, m), jax.jacfwd(final)(v, m)))(x0, m)
    assert np.all(np.isfinite(rev)) and np.all(rev[:1] > 0)
    np.testing.assert_allclose(rev, fwd, rtol=1e-7, atol=0)
    d = 1e-6 * 0.448  # independent check of the gain entry by central differences
    value = jax.jit(final)
    fd = (value(x0.at[0].add(d), m) - value(x0.at[0].add(-d), m)) / (2 * d)
    assert float(rev[0]) == pytest.approx(float(fd), rel=1e-4)


def test_ten_thousand_cycles_without_nan():
    m = mr.SPEC.model(substeps=1)
    states = history(m, 0.016, 0.5, POWER_W, 10_000, 10)
    assert bool(jnp.all(jnp.isfinite(states)))
    # it walks (and turns) out of the world-fixed spot, then stops: tens of um, not mm
    assert 20e-6 < float(states[-1, 4]) < 1e-3


# ---------------------------------------------------------------- recovery from tracked pose

TRUTH = {
    "absorptance_left": 0.40,
    "thermal.frame_capacitance_J_per_K": 2.4e-7,
    "locomotion.foot_forward_N": 0.35e-6,
    "locomotion.stiffness_N_per_m": 5.0,
    "locomotion.turn_gain": 0.6,
}
# (spot y [m], period [s], power [W]): powers separate the thermal gain from the play width
# (the step is ~ gain * P - W), periods the time constant, spot positions the turning
RUNS = [(60e-6, 0.016, 0.015), (60e-6, 0.016, 0.025), (60e-6, 0.040, 0.02), (30e-6, 0.016, 0.02)]
DURATION_S = 0.6
FIT_SUBSTEPS, TRUTH_SUBSTEPS = 4, 16  # the data come from a finer-stepped reference


@pytest.fixture(scope="module")
def recovery_data():
    truth = set_values(mr.SPEC.model(substeps=TRUTH_SUBSTEPS), list(TRUTH), list(TRUTH.values()))
    rng = np.random.default_rng(7)
    defects = CameraDefects(
        fps=30,
        jitter_s=1e-3,
        noise_m=0.065e-6,
        drop_fraction=0.05,
        burst_length=2,
        burst_size_m=3e-6,
    )
    experiments = []
    for i, (spot_y, period, power) in enumerate(RUNS):
        offsets = rng.uniform(-20e-6, 20e-6, 2)
        run_model = set_values(
            truth, ["spot.y_m", "image_offset_x_m", "image_offset_y_m"], [spot_y, *offsets]
        )
        wave = PulseTrain(power, period, 0.5, n_pulses=int(round(DURATION_S / period)))
        exp, _ = record(run_model, wave, name=f"run{i}", defects=defects, seed=100 + i)
        experiments.append(dataclasses.replace(exp, settings={"spot.y_m": spot_y}))
    return truth, experiments


@pytest.fixture(scope="module")
def recovery(recovery_data):
    truth, experiments = recovery_data
    return truth, fit(
        mr.SPEC.model(substeps=FIT_SUBSTEPS), experiments, mr.default_free_parameters()
    )


def test_fit_recovers_identifiable_parameters(recovery):
    truth, result = recovery
    assert result.converged, result.message
    verdicts = {p.name: p.verdict for p in result.parameters}
    for name in ("absorptance_left", "thermal.frame_capacitance_J_per_K", "locomotion.turn_gain"):
        assert verdicts[name] == "identifiable"
        est = result.estimate(name)
        assert abs(est.value - TRUTH[name]) < 3 * est.se, (name, est.value, est.se)
    # the stiffness is not separable from the friction capacities: its prior dominates
    assert verdicts["locomotion.stiffness_N_per_m"] == "prior-dominated"
    assert verdicts["locomotion.foot_forward_N"] == "prior-dominated"
    # ... but their combination, the play width, is what the pose data pin down
    w, se = mr.play_width_estimate(result)
    w_true = float(truth.locomotion.play_width_m())
    assert se < 0.2 * w_true and abs(w - w_true) < 3 * se, (w, se, w_true)


def test_fit_percent_is_per_output_as_matlab_compare(recovery):
    """Fit % is one figure per output channel, as MATLAB `compare` reports it, never pooled
    over the four feature coordinates (pooled, the +-20 um image offsets between channels
    make any fit read ~99.9 %): each equals `greybox.blackbox.compare`'s fit % of the same
    predictions (an identity polynomial model passes them through compare's simulation)."""
    from greybox import blackbox as bb

    _, result = recovery
    n_y = result.n_outputs

    class PassThrough:  # y_hat(t) = u(t): compare's free-run simulation of the predictions
        resampled = False

        def polynomials(self):
            return bb.Polynomials(
                a=np.ones((n_y, 1)),
                b=np.eye(n_y)[:, :, None],
                c=np.ones((n_y, 1)),
                f=np.ones((n_y, n_y, 1)),
                offset=np.zeros(n_y),
            )

    for i, e in enumerate(result.experiments):
        keep = e.mask.all(axis=1)  # frames are dropped whole
        z = result.predict(i)
        reference = bb.compare(PassThrough(), bb.UniformData(u=z[keep], y=e.y[keep], dt=1 / 30))
        assert result.fit_percent[e.name].shape == (n_y,)
        np.testing.assert_allclose(result.fit_percent[e.name], reference.fit_percent, rtol=1e-7)
        pooled = 100 * (
            1 - np.linalg.norm((e.y - z)[keep]) / np.linalg.norm(e.y[keep] - e.y[keep].mean())
        )
        # what pooling hid: ~99 % pooled, while per channel the two corrupted frames of each
        # run (3 um on 0.065 um noise) cost every channel most of its fit %
        assert pooled > 98.0 and result.fit_percent[e.name].max() < pooled - 50.0
