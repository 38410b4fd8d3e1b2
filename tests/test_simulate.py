"""Simulation: closed forms, the two paths against each other, and JAX transformations."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import greybox
from greybox._model.parameters import set_values
from greybox._model.waveforms import PiecewiseConstant, PulseTrain
from greybox._simulate.schedules import model_schedules, schedule_for
from greybox._simulate.simulate import (
    COMPARE_ALL_MAX_BREAKS,
    as_arrays,
    input_at,
    observe_schedule,
    simulate,
)
from greybox.blocks._mechanics import ChevronLinear

default_model = greybox.get_device("chevron_laser").model

P_W = 0.02


def linear_model(exposure_s=0.0):
    """Chevron with linearised kinematics: y = K_mech * theta, so y is a scaled RC response."""
    m = greybox.devices.with_camera(default_model(), exposure_s=exposure_s)
    return eqx.tree_at(lambda m: m.kinematics, m, ChevronLinear(m.kinematics.angle_rad))


def gains(m):
    """(steady-state rise per W of laser [K/W], displacement per K [m/K]) for `linear_model`."""
    k_th = float(m.absorbed_fraction() * m.thermal.resistance_K_per_W)
    k_mech = float(
        m.elongation.cte_per_K
        * m.elongation.length_m
        * m.elongation.beam_fraction
        / np.sin(m.kinematics.angle_rad)
    )
    return k_th, k_mech


@pytest.mark.parametrize("method", ["zoh", "adaptive"])
def test_one_node_step_response_closed_form(method):
    m = linear_model()
    tau = float(m.thermal.tau_s)
    k_th, k_mech = gains(m)
    step = PiecewiseConstant(np.array([0.0]), np.array([P_W]), 0.5)
    t = np.sort(np.random.default_rng(1).uniform(0.001, 0.5, 40))
    y = simulate(m, step, t, method=method, rtol=1e-11, atol=1e-13)
    expected = k_mech * k_th * P_W * (1 - np.exp(-t / tau))
    np.testing.assert_allclose(y, expected, rtol=1e-8, atol=1e-16)


def test_periodic_swing_equals_tanh_formula():
    m = linear_model()
    tau = float(m.thermal.tau_s)
    k_th, k_mech = gains(m)
    period = 0.1
    w = PulseTrain(P_W, period, 0.5, 60)
    # peak just before the last fall, trough just before the last rise
    t_peak = 59 * period + 0.5 * period - 1e-9
    t_trough = 59 * period - 1e-9
    y = simulate(m, w, np.array([t_trough, t_peak]))
    swing = (y[1] - y[0]) / k_mech
    theta_ss = k_th * P_W
    assert swing == pytest.approx(theta_ss * np.tanh(period / (4 * tau)), rel=1e-7)
    # and the mean temperature over a cycle is D * theta_ss
    tt = 50 * period + np.linspace(0, period, 2001)[:-1]
    assert np.mean(simulate(m, w, tt)) / k_mech == pytest.approx(0.5 * theta_ss, rel=1e-3)


def test_exposure_average_matches_integral():
    te = 0.01
    m = linear_model(exposure_s=te)
    tau = float(m.thermal.tau_s)
    k_th, k_mech = gains(m)
    step = PiecewiseConstant(np.array([0.0]), np.array([P_W]), 0.3)
    t = np.array([0.02, 0.05, 0.11, 0.3])
    y = simulate(m, step, t)
    mean = 1 - tau / te * (np.exp(-(t - te) / tau) - np.exp(-t / tau))
    np.testing.assert_allclose(y, k_mech * k_th * P_W * mean, rtol=1e-6)


def stitched_inputs():
    rng = np.random.default_rng(7)
    runs = [
        (PulseTrain(p * 1e-3, per, 0.5, 8), np.sort(rng.uniform(0, 8 * per, 60)))
        for p, per in [(5, 0.2), (20, 0.5), (30, 0.3)]
    ]
    return runs


def test_zoh_and_adaptive_agree_within_1e6_um_on_default_model():
    m = default_model()
    for wave, t in stitched_inputs():
        zoh = simulate(m, wave, t, method="zoh")
        ada = simulate(m, wave, t, method="adaptive", rtol=1e-10, atol=1e-12)
        assert np.max(np.abs(zoh - ada)) / 1e-6 < 1e-6
        assert np.max(zoh) > 0.3e-6  # a real stroke, not a trivial agreement


@pytest.mark.parametrize("method", ["zoh", "adaptive"])
def test_vmap_over_experiments_matches_loop(method):
    m = as_arrays(default_model())
    runs = stitched_inputs()
    batch = model_schedules(m, [(w, t, 0.0) for w, t in runs])
    z, ok = jax.jit(jax.vmap(lambda s: observe_schedule(m, s, method=method)))(batch)
    assert bool(jnp.all(ok))
    for i, (w, t) in enumerate(runs):
        loop = simulate(m, w, t, method=method)
        # ZOH is exact arithmetic either way; adaptive differs only at solver tolerance (STYLE G.4)
        tol = 1e-12 if method == "zoh" else 1e-6
        np.testing.assert_allclose(np.asarray(z[i, : t.size, 0]), loop, rtol=tol, atol=1e-18)


def _output_of(params, method, adjoint):
    m = as_arrays(default_model())
    wave, t = stitched_inputs()[1]
    row = {k: v[0] for k, v in schedule_for(m, wave, t).items()}
    m = set_values(m, ["thermal.tau_s", "absorptance"], [params[0], params[1]])
    z, _ = observe_schedule(m, row, method=method, rtol=1e-11, atol=1e-13, adjoint=adjoint)
    return z[: t.size, 0]


@pytest.mark.parametrize("method", ["zoh", "adaptive"])
def test_forward_and_reverse_mode_derivatives_agree(method):
    p = jnp.array([0.04, 0.6])
    # each under one jit: one compile instead of an op-by-op trace (the adaptive case: 16 -> 9 s)
    forward = jax.jit(lambda q: _output_of(q, method, "forward"))
    fwd = jax.jit(jax.jacfwd(forward))(p)
    rev = jax.jit(jax.jacrev(lambda q: _output_of(q, method, "reverse")))(p)
    assert float(jnp.max(jnp.abs(fwd))) > 0
    np.testing.assert_allclose(fwd, rev, rtol=1e-7, atol=1e-7 * float(jnp.max(jnp.abs(fwd))))
    # and a central finite difference with tight solver tolerances (STYLE G.3)
    eps = 1e-6
    fd = (forward(p.at[0].add(eps)) - forward(p.at[0].add(-eps))) / (2 * eps)
    np.testing.assert_allclose(fwd[:, 0], fd, rtol=1e-4, atol=1e-5 * float(jnp.max(jnp.abs(fd))))


def test_changing_parameter_values_does_not_recompile():
    m = as_arrays(default_model())
    wave, t = stitched_inputs()[0]
    row = {k: v[0] for k, v in schedule_for(m, wave, t).items()}

    @eqx.filter_jit
    @eqx.debug.assert_max_traces(max_traces=1)
    def run(model):
        return observe_schedule(model, row)[0]

    a = run(m)
    b = run(as_arrays(set_values(m, ["thermal.tau_s", "absorptance"], [0.02, 0.3])))
    assert not np.allclose(a, b)  # the values really changed, and there was a single trace


def test_simulate_rejects_bad_times_and_needs_linear_for_zoh():
    m = default_model()
    w = PulseTrain(P_W, 0.2, 0.5, 3)
    with pytest.raises(ValueError, match="strictly increasing"):
        simulate(m, w, np.array([0.1, 0.05, 0.2]))
    with pytest.raises(ValueError, match="NaN"):
        simulate(m, w, np.array([0.1, np.nan]))
    with pytest.raises(ValueError, match="method"):
        simulate(m, w, np.array([0.1]), method="euler")


def test_batched_expm_matches_scipy_and_its_derivative():
    """`expm_taylor` on a batch mixing matrices that need no squaring and matrices that need
    many (the squarings stop at the batch's largest count): every one agrees with
    scipy.linalg.expm, and its forward- and reverse-mode derivatives (the fits use the first,
    `jax.grad` of a user's the second) agree with a central difference of scipy's."""
    import jax
    import jax.numpy as jnp
    import scipy.linalg

    from greybox._simulate.simulate import expm_taylor

    rng = np.random.default_rng(3)
    base = -np.eye(4) * 2.0 + 0.5 * rng.standard_normal((4, 4))  # a stable 4x4
    scales = np.array([1e-5, 0.01, 0.1, 1.0, 30.0, 2000.0])
    got = np.asarray(expm_taylor(jnp.asarray(base[None] * scales[:, None, None])))
    for g, s in zip(got, scales):
        ref = scipy.linalg.expm(base * s)
        assert np.max(np.abs(g - ref)) <= 1e-12 * max(np.max(np.abs(ref)), 1e-300) + 1e-300

    w = rng.standard_normal((4, 4))

    def f(h):
        steps = jnp.stack([h, 3 * h])[:, None, None]
        return jnp.sum(w * expm_taylor(jnp.asarray(base[None]) * steps))

    h, eps = 0.7, 1e-6
    e = scipy.linalg.expm
    fd = sum(np.sum(w * (e(base * k * (h + eps)) - e(base * k * (h - eps)))) for k in (1, 3))
    fd /= 2 * eps
    assert float(jax.jacfwd(f)(h)) == pytest.approx(fd, rel=1e-7)
    # reverse mode too (a user's jax.grad through a multi-node simulation reaches it)
    assert float(jax.grad(f)(h)) == pytest.approx(fd, rel=1e-7)


@pytest.mark.parametrize("n", [5, COMPARE_ALL_MAX_BREAKS, COMPARE_ALL_MAX_BREAKS + 1, 2000])
def test_input_lookup_is_the_right_continuous_level_on_both_sides_of_the_method_switch(n):
    """`input_at` (all-at-once comparison up to COMPARE_ALL_MAX_BREAKS breakpoints, binary
    search above) against numpy's searchsorted, with repeated breakpoints, times on them,
    before the first and after the last, vmapped and under jit as the adaptive solver uses it."""
    rng = np.random.default_rng(n)
    breaks = np.sort(np.round(rng.uniform(0.0, 10.0, n), 2))  # rounding repeats some
    levels = rng.normal(size=(n, 2))
    t = np.concatenate([rng.uniform(-1.0, 11.0, 300), breaks[:: max(1, n // 50)], [-5.0, 20.0]])
    idx = np.searchsorted(breaks, t, side="right") - 1
    want = np.where((idx >= 0)[:, None], levels[np.clip(idx, 0, None)], 0.0)
    got = jax.jit(jax.vmap(input_at, in_axes=(None, None, 0)))(breaks, levels, t)
    np.testing.assert_array_equal(np.asarray(got), want)


def test_a_device_simulated_by_zoh_never_imports_diffrax():
    """diffrax is imported by the adaptive and stiff methods only: a ZOH simulation (the
    chevron, the demo) skips its import (`greybox simulate` of the demo result: 2.32-2.54 ->
    1.92-2.05 s), and gives the closed-form step response."""
    import subprocess
    import sys
    from pathlib import Path

    code = (
        "import sys, jax, numpy as np\n"
        "jax.config.update('jax_enable_x64', True)\n"
        "import tests.test_simulate as t\n"
        "m = t.linear_model()\n"
        "k_th, k_mech = t.gains(m)\n"
        "times = np.linspace(0.001, 0.5, 40)\n"
        "step = t.PiecewiseConstant(np.array([0.0]), np.array([t.P_W]), 0.5)\n"
        "y = np.asarray(t.simulate(m, step, times, method='zoh')).ravel()\n"
        "exact = k_mech * k_th * t.P_W * (1 - np.exp(-times / float(m.thermal.tau_s)))\n"
        "print('diffrax' in sys.modules, np.allclose(y, exact, rtol=1e-8, atol=1e-16))\n"
    )
    root = Path(__file__).resolve().parents[1]
    done = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=root, timeout=120
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["False", "True"]
