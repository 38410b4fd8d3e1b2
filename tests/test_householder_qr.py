"""The Levenberg-Marquardt step's QR on an accelerator (`greybox._model.householder`):
the factorisation against numpy's LAPACK QR, its least-squares and minimum-norm solves
against numpy's SVD `lstsq`, the damping rows at sqrt(float max) without overflow, and a
nonlinear fit through `levenberg_marquardt` with that solver against scipy's
`least_squares`, alone and under `vmap`."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
from scipy.optimize import least_squares

import greybox._platform
from greybox._model.freeparams import levenberg_marquardt
from greybox._model.householder import HouseholderQR, apply_q, householder_qr, lm_linear_solver

jax.config.update("jax_enable_x64", True)
RNG = np.random.default_rng(24)


def _solve(a, b):
    op = lx.MatrixLinearOperator(jnp.asarray(a))
    return np.asarray(lx.linear_solve(op, jnp.asarray(b), HouseholderQR()).value)


@pytest.mark.parametrize("m, n", [(392, 8), (12, 12), (40, 3)])
def test_factorisation_is_lapacks(m, n):
    a = RNG.normal(size=(m, n)) * np.logspace(-3, 3, n)
    r, v, tau = householder_qr(jnp.asarray(a))
    r_ref = np.linalg.qr(a, mode="r")
    # R is unique up to the signs of its rows; LAPACK's sign convention is the same
    np.testing.assert_allclose(np.asarray(r), r_ref, rtol=1e-12, atol=1e-12 * np.abs(r_ref).max())
    q = np.asarray(jax.vmap(lambda e: apply_q(v, tau, e), in_axes=1, out_axes=1)(jnp.eye(m)))
    np.testing.assert_allclose(q.T @ q, np.eye(m), atol=1e-13)
    np.testing.assert_allclose(q[:, :n] @ np.asarray(r), a, atol=1e-12 * np.abs(a).max())


def test_least_squares_and_minimum_norm_solutions_match_svd_lstsq():
    a = RNG.normal(size=(60, 5))
    b = RNG.normal(size=60)
    np.testing.assert_allclose(_solve(a, b), np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-12)
    wide, c = a.T, RNG.normal(size=5)  # underdetermined: the minimum-norm solution
    np.testing.assert_allclose(_solve(wide, c), np.linalg.lstsq(wide, c, rcond=None)[0], rtol=1e-11)


def test_damping_rows_at_sqrt_float_max_do_not_overflow():
    """optimistix damps a rejected step with lambda up to float max: rows sqrt(lambda) I,
    whose squares overflow a plain norm. The step x = J^T r / lambda is then below 1e-150
    (exact zeros, as LAPACK's QR gives them); at moderate damping it is numpy's `lstsq`."""
    j = RNG.normal(size=(30, 4))
    r = RNG.normal(size=30)
    for s in (1e4, 1e100, np.sqrt(np.finfo(float).max)):
        a, b = np.vstack([j, s * np.eye(4)]), np.r_[r, np.zeros(4)]
        x = _solve(a, b)
        lapack = lx.linear_solve(lx.MatrixLinearOperator(jnp.asarray(a)), jnp.asarray(b), lx.QR())
        assert np.all(np.isfinite(x))
        if s == 1e4:
            np.testing.assert_allclose(x, np.linalg.lstsq(a, b, rcond=None)[0], rtol=1e-10)
        else:
            assert np.max(np.abs(x)) < 1e-150
            np.testing.assert_array_equal(x, np.asarray(lapack.value))


T = np.linspace(0.0, 3.0, 50)
TRUE = np.array([[2.0, 1.3], [0.5, 0.4], [5.0, 3.0]])  # (amplitude, rate) of each problem


def _data(k):
    a, rate = TRUE[k]
    return a * np.exp(-rate * T) + 0.01 * np.sin(11.0 * T + k)  # a misfit: nonzero residuals


def _residuals(p, y):
    return p[0] * jnp.exp(-p[1] * T) - y


def test_levenberg_marquardt_with_it_matches_scipy(monkeypatch):
    monkeypatch.setattr(greybox._platform, "on_accelerator", lambda: True)
    assert isinstance(lm_linear_solver(), HouseholderQR)  # what an accelerator's fit uses

    def run(p0, y):
        return levenberg_marquardt(_residuals, p0, y, rtol=1e-10, atol=1e-12, max_steps=200)

    p0 = jnp.array([1.0, 1.0])
    ys = jnp.asarray(np.stack([_data(k) for k in range(3)]))
    batch = jax.jit(jax.vmap(run, in_axes=(None, 0)))(p0, ys)
    for k in range(3):
        ref = least_squares(lambda p: _residuals(p, np.asarray(ys[k])), [1.0, 1.0], xtol=1e-14,
                            ftol=1e-14, gtol=1e-14).x
        raw, ok, _, _ = jax.jit(run)(p0, ys[k])
        assert bool(ok) and bool(batch[1][k])
        np.testing.assert_allclose(np.asarray(raw), ref, rtol=1e-8)
        np.testing.assert_allclose(np.asarray(batch[0][k]), np.asarray(raw), rtol=1e-12)
