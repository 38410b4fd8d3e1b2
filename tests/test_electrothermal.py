"""Joule block, electro-thermal chevron, periodic steady state and the grey-box table fit."""

import numpy as np
import pytest

import greybox
from greybox._estimate.table_fit import fit_table
from greybox._model.waveforms import PulseTrain
from greybox._simulate.simulate import simulate
from greybox.blocks._joule import JouleHeating

ec = greybox.device_module("electrothermal_chevron")
fit_polynomial = ec.surface.fit_polynomial


@pytest.fixture(scope="module")
def linear_model():
    return ec.SPEC.model(joule__tcr_per_K=0.0)


@pytest.fixture(scope="module")
def tcr_model():
    return ec.SPEC.model()


def test_joule_steady_rise_solves_the_balance():
    joule = JouleHeating(resistance_ohm=2000.0, tcr_per_K=1e-3)
    theta = float(joule.steady_rise_K(24.0, 300.0))
    c = 300.0 * 24.0**2 / 2000.0  # 86.4 K without the TCR
    assert theta == pytest.approx((-1 + np.sqrt(1 + 4e-3 * c)) / 2e-3, rel=1e-12)
    assert theta == pytest.approx(300.0 * float(joule.power_W(24.0, theta)), rel=1e-12)
    assert float(JouleHeating(2000.0).steady_rise_K(24.0, 300.0)) == pytest.approx(c, rel=1e-14)


def test_device_linearity_flags(linear_model, tcr_model):
    assert linear_model.is_state_affine() and not tcr_model.is_state_affine()
    # V^2 input: the ZOH path of simulate does not apply
    assert greybox.devices.default_method(linear_model) == "adaptive"
    with pytest.raises(ValueError, match="needs a linear device"):
        greybox.simulate(linear_model, greybox.PulseTrain(1.0, 0.01, 0.5, 2), [0.01], method="zoh")
    with pytest.raises(ValueError, match="adaptive"):
        simulate(linear_model, PulseTrain(10.0, 0.02), np.array([0.01]), method="zoh")


def _last_cycle_reference(model, volts, freq, n_cycles, t_cycle):
    period = 1.0 / freq
    t = (n_cycles - 1) * period + t_cycle
    t[-1] -= 1e-12  # the cycle's end, just before the next rising edge
    return simulate(
        model,
        PulseTrain(volts, period, 0.5, n_pulses=n_cycles),
        t,
        method="adaptive",
        rtol=1e-11,
        atol=1e-12,
    )


@pytest.mark.parametrize(
    "which,method,n_steps,tol", [("linear", "analytic", 16, 1e-8), ("tcr", "numerical", 32, 2e-6)]
)
def test_periodic_cycle_matches_long_simulation(
    which, method, n_steps, tol, linear_model, tcr_model
):
    model = linear_model if which == "linear" else tcr_model
    volts, freq = 24.0, 50.0
    t_cycle, states = greybox.waveforms.square_wave_cycle(
        model, volts, freq, n_steps=n_steps, method=method
    )
    y_cycle = np.array([float(model.output(x)[0]) for x in states])
    # 40 cycles = 800 ms = 114 tau from a cold start: the transient is gone to 1e-49
    y_sim = _last_cycle_reference(model, volts, freq, 40, np.asarray(t_cycle))
    assert np.max(np.abs(y_cycle - y_sim)) < tol * np.max(y_sim)
    mean, pp = greybox.waveforms.square_wave_response(
        model, volts, freq, n_steps=n_steps, method=method
    )
    assert float(pp) == pytest.approx(y_sim.max() - y_sim.min(), rel=10 * tol)


def test_thermal_swing_matches_closed_form(linear_model):
    """PHYSICS.md §5: theta_pp = theta_ss tanh(T / (4 tau)) at 50 % duty."""
    volts, tau = 20.0, ec.NOMINAL_TAU_S
    theta_ss = ec.NOMINAL_RESISTANCE_K_PER_W * volts**2 / ec.NOMINAL_R0_OHM
    for freq in (10.0, 100.0, 400.0):
        _, x = greybox.waveforms.square_wave_cycle(linear_model, volts, freq, n_steps=16)
        swing = float(np.max(x) - np.min(x))
        assert swing == pytest.approx(theta_ss * np.tanh(1 / freq / (4 * tau)), rel=1e-10)


def test_dc_limit_and_bad_input(tcr_model):
    mean, pp = greybox.waveforms.square_wave_response(tcr_model, [24.0], [0.0])
    stroke = float(tcr_model.stroke(tcr_model.dc_rise_K(24.0)))
    assert pp[0] == pytest.approx(stroke, rel=1e-10) and mean[0] == pytest.approx(
        stroke / 2, rel=1e-10
    )
    with pytest.raises(ValueError, match="frequency_Hz"):
        greybox.waveforms.square_wave_response(tcr_model, [10.0], [-5.0])
    with pytest.raises(ValueError, match="affine"):
        greybox.waveforms.square_wave_response(tcr_model, [10.0], [5.0], method="analytic")
    with pytest.raises(ValueError, match="resistance_ohm"):
        JouleHeating(resistance_ohm=0.0)


@pytest.fixture(scope="module")
def synthetic_table(tcr_model):
    amps, freqs = np.meshgrid(np.arange(0.0, 25.0, 4.0), np.arange(0.0, 401.0, 40.0), indexing="ij")
    a, f = amps.ravel(), freqs.ravel()
    _, pp = greybox.waveforms.square_wave_response(tcr_model, a, f, n_steps=16)
    noise = 0.1e-6
    return a, f, pp + np.random.default_rng(7).normal(0.0, noise, pp.shape), noise


def test_greybox_table_fit_recovers_parameters(tcr_model, synthetic_table):
    a, f, y, noise = synthetic_table
    respond = greybox.waveforms.response_function(tcr_model, n_steps=16)
    start = ec.SPEC.model(
        thermal__tau_s=0.015, thermal__resistance_K_per_W=150.0, joule__tcr_per_K=0.0
    )
    result = fit_table(
        start, lambda m, x: respond(m, x[0], x[1])[1], (a, f), y, ec.default_free_parameters()
    )
    assert result.converged
    truth = {
        "thermal.tau_s": ec.NOMINAL_TAU_S,
        "thermal.resistance_K_per_W": ec.NOMINAL_RESISTANCE_K_PER_W,
        "joule.tcr_per_K": ec.NOMINAL_TCR_PER_K,
    }
    for p in result.parameters:
        assert p.verdict == "identifiable"
        assert p.ci95[0] < truth[p.path] < p.ci95[1], p
    assert result.sigma[0] == pytest.approx(noise, rel=0.3)
    # the thesis' cubic surface cannot follow the tanh roll-off: several times the noise
    poly = fit_polynomial(np.column_stack([a, f]), y, (3, 2))
    assert poly.rmse > 3 * result.rmse
