"""Levenberg-Marquardt stops a start whose cost has stalled (`levenberg_marquardt`'s stall
test): a fit whose optimum is exactly on a bound (raw -> inf in its logit coordinate, the
raw tolerances never met) stops far inside its step budget and is judged "at bound"; a
problem with a closed-form interior optimum ends exactly where plain Levenberg-Marquardt
ends, and a parameter chasing its bound stops no later than without the test."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import greybox
from greybox._estimate.fit import fit
from greybox._model.freeparams import (
    STALL_WINDOW,
    FreeParameter,
    levenberg_marquardt,
    pinned_fn,
)
from greybox._model.parameters import set_values
from tests.helpers import chevron_runs

jax.config.update("jax_enable_x64", True)

X = np.linspace(0.0, 1.0, 60)
Y = 1.7 * X + 0.05 * np.sin(37.0 * X)  # a slope and a misfit the model cannot follow
A_STAR = float(X @ Y / (X @ X))  # closed-form least-squares slope
LOWER = 0.2
THETA = FreeParameter("theta", lower=LOWER)  # log coordinate: value = 0.2 + exp(raw)
SLOPE = FreeParameter("a", scale=1.0)
MAX_STEPS = 200


def _solve(theta_target: float, stall_window):
    """Residuals: the slope fit, and theta pulled toward `theta_target` (theta* =
    max(target, 0.2) and a* = A_STAR in closed form)."""

    def residuals(raw, _):
        theta = THETA.to_value(raw[0])
        return jnp.concatenate([SLOPE.to_value(raw[1]) * X - Y, jnp.stack([theta - theta_target])])

    raw0 = jnp.array([float(THETA.to_raw(1.0)), 1.0])
    run = jax.jit(
        lambda r0: levenberg_marquardt(
            residuals,
            r0,
            None,
            rtol=1e-6,
            atol=1e-6,
            max_steps=MAX_STEPS,
            stall_window=stall_window,
            pinned=pinned_fn([THETA, SLOPE], r0),
        )
    )
    raw, ok, steps, stalled = run(raw0)
    return np.asarray(raw), bool(ok), int(steps), bool(stalled), raw0


def test_fit_with_its_optimum_on_a_bound_stops_early_and_reports_it():
    """Data 2.5x hotter than the fixed thermal resistance allows at absorptance <= 1: the
    constrained optimum is absorptance = 1 exactly (its upper bound; unconstrained it would
    be ~1.7). Levenberg-Marquardt chases the bound in the logit coordinate (raw -> +inf);
    the start stops once its cost stalls (44 steps, then 26 for the refit at the estimated
    noise; without the stall test 61 + 50, and "converged" only by the raw tolerances), and
    the result says "at bound" with the optimiser stopped short."""
    chevron = greybox.get_device("chevron_laser")
    truth = set_values(chevron.model(), ["absorptance", "thermal.tau_s"], [0.62, 0.045])
    start = set_values(truth, ["absorptance", "thermal.tau_s"], [0.4, 0.09])
    hot = set_values(
        truth,
        ["thermal.resistance_K_per_W", "thermal.tau_s", "absorptance"],
        [2.5 * float(truth.thermal.resistance_K_per_W), 2e-4, 0.67],
    )
    exps, _ = chevron_runs(hot, runs=((10, 0.3), (30, 0.6)), duration_s=4.0, seed=7)
    lines = []
    r = fit(start, exps, list(chevron.free_parameters()), progress=lines.append)
    assert r.status == "at bound" and not r.valid
    a = r.estimate("absorptance")
    assert (a.bound, a.value) == ("upper", pytest.approx(1.0, abs=1e-3))
    assert "optimiser also stopped short" in r.message
    assert any("stalled (cost no longer falling)" in ln for ln in lines)
    assert r.n_steps <= 80  # 111 without the stall test


def test_interior_optimum_is_unchanged_by_the_stall_test():
    target = 0.7  # inside the bound: theta* = 0.7
    plain = _solve(target, None)
    stall = _solve(target, STALL_WINDOW)
    assert plain[1] and stall[1] and not stall[3]
    np.testing.assert_array_equal(stall[0], plain[0])
    assert stall[2] == plain[2] < STALL_WINDOW
    assert float(THETA.to_value(stall[0][0])) == pytest.approx(target, rel=1e-6)
    assert stall[0][1] == pytest.approx(A_STAR, rel=1e-9)


def test_a_parameter_chasing_its_bound_stops_no_later():
    """theta pulled onto its lower bound: plain Levenberg-Marquardt spends its whole budget
    (the damping swamps theta's vanishing curvature, raw creeps toward -inf); with the stall
    test the start ends earlier, on the bound, with the closed-form slope."""
    raw, ok, steps, stalled, _ = _solve(LOWER, None)
    assert (ok, steps, stalled) == (False, MAX_STEPS, False)
    raw, ok, steps, stalled, raw0 = _solve(LOWER, STALL_WINDOW)
    assert stalled and not ok and steps < MAX_STEPS
    assert THETA.bound_hit(raw[0], raw0[0]) == "lower"
    assert raw[1] == pytest.approx(A_STAR, rel=1e-9)


def test_gauss_newton_decrement_is_twice_the_cost_left_to_gain():
    """For linear residuals r = A x - b the decrement g^T H^+ g at any x is exactly
    2 (cost(x) - min cost) (the Gauss-Newton step is exact), also when A is rank deficient
    (the undetermined direction is left out; the minimum from numpy's lstsq)."""
    from greybox._estimate.fit import _gauss_newton_decrement

    rng = np.random.default_rng(3)
    a = rng.normal(size=(40, 3)) * [1.0, 1e3, 1e-2]  # badly scaled columns
    a = np.column_stack([a, a[:, 0] + a[:, 2]])  # a fourth column the others determine
    b = rng.normal(size=40)
    x_star = np.linalg.lstsq(a, b, rcond=None)[0]
    min_cost = 0.5 * np.sum((a @ x_star - b) ** 2)
    for x in (rng.normal(size=4), x_star + 1e-4 * rng.normal(size=4)):
        left = 0.5 * np.sum((a @ x - b) ** 2) - min_cost
        got = float(_gauss_newton_decrement(jnp.asarray(a), jnp.asarray(a @ x - b)))
        assert got == pytest.approx(2.0 * left, rel=1e-8)
    a[3, 1] = np.nan  # a Jacobian that is not finite settles nothing
    assert np.isnan(float(_gauss_newton_decrement(jnp.asarray(a), jnp.asarray(b))))


def test_a_stalled_start_with_nothing_left_to_gain_has_converged():
    """Raw tolerances that cannot be met (rtol = atol = 0): the start stops on the stall test
    in the interior, where the Gauss-Newton decrement is far below SETTLED_DECREMENT, so the
    fit has converged, at the estimates of a fit with the usual tolerances to 1e-6 relative (a
    fraction of their standard errors)."""
    chevron = greybox.get_device("chevron_laser")
    truth = set_values(chevron.model(), ["absorptance", "thermal.tau_s"], [0.62, 0.045])
    start = set_values(truth, ["absorptance", "thermal.tau_s"], [0.5, 0.06])
    exps, _ = chevron_runs(truth, runs=((10, 0.3), (30, 0.6)), duration_s=2.0, seed=5)
    free = list(chevron.free_parameters())
    lines = []
    strict = fit(start, exps, free, rtol=0.0, atol=0.0, n_starts=1, progress=lines.append)
    usual = fit(start, exps, free, n_starts=1)
    assert strict.status == "converged" and strict.converged and strict.valid
    assert not any("stalled (cost no longer falling)" in ln for ln in lines)
    assert strict.n_steps >= STALL_WINDOW  # it did run into the stall test
    np.testing.assert_allclose(strict.raw, usual.raw, rtol=1e-6)
    ses = np.array([p.se for p in strict.parameters])
    vals = np.array([p.value for p in strict.parameters])
    assert np.all(np.abs(vals - [p.value for p in usual.parameters]) < 1e-3 * ses)


@pytest.mark.parametrize("stall_window", [STALL_WINDOW, None])
def test_the_end_point_is_the_evaluation_at_the_returned_estimate(stall_window):
    """`end_point=True` returns the solver's last accepted evaluation: its residuals, its
    linearisation and its aux must be those at the estimate returned, also when steps were
    rejected (here one of 29, counted by optimistix itself), where the last point evaluated
    is not the estimate. The truth: the residual function and `jax.jacfwd` at the estimate."""
    import equinox as eqx
    import optimistix as optx

    from greybox._model.householder import lm_linear_solver

    def residuals(y, a):  # Rosenbrock's valley, and a term that keeps its optimum off 0 cost
        r = jnp.stack([a * (y[1] - y[0] ** 2), 1.0 - y[0], 0.1 * jnp.sin(3.0 * y[1])])
        return r, (r, 2.0 * y)

    y0 = jnp.array([-1.2, 1.0])
    lm = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8, linear_solver=lm_linear_solver())
    plain = optx.least_squares(residuals, lm, y0, args=10.0, has_aux=True, max_steps=200)
    assert int(plain.state.num_accepted_steps) < int(plain.state.num_steps)  # a rejection

    raw, ok, _, _, (res, jac, aux) = eqx.filter_jit(
        lambda y: levenberg_marquardt(
            residuals, y, 10.0, rtol=1e-8, atol=1e-8, max_steps=200,
            stall_window=stall_window, has_aux=True, end_point=True,
        )
    )(y0)  # fmt: skip
    assert bool(ok)
    np.testing.assert_allclose(raw, plain.value, rtol=1e-12)
    want, (want_aux, doubled) = residuals(raw, 10.0)
    np.testing.assert_allclose(res, want, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(aux[0], want_aux, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(aux[1], doubled, rtol=1e-15)
    np.testing.assert_allclose(
        jac.as_matrix(), jax.jacfwd(lambda y: residuals(y, 10.0)[0])(raw), rtol=1e-12, atol=1e-15
    )
