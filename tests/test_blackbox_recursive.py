"""Recursive ARX/ARMAX (Kalman / RLS): convergence to batch LS, tracking, carry-over."""

import numpy as np
import pytest
from scipy.signal import lfilter

from greybox import blackbox as bb

A = np.array([1.0, -1.5, 0.7])
B = np.array([0.0, 1.0, 0.5])


def _data(rng, n=1500, sigma=0.2, c=(1.0,)):
    u = np.sign(rng.standard_normal(n))
    y = lfilter(B, A, u) + lfilter(c, A, sigma * rng.standard_normal(n))
    return bb.UniformData(u, y, 0.1)


def test_rls_lambda_one_equals_batch_arx():
    d = _data(np.random.default_rng(20))
    r = bb.recursive_arx(d, 2, 2, 1, P0=1e10)
    batch = bb.fit_arx(d, 2, 2, 1)
    np.testing.assert_allclose(r.final_parameters, batch.parameters[0], atol=1e-7)
    # P_N = (P0^-1 + Phi^T Phi)^-1 -> (Phi^T Phi)^-1 = batch covariance / sigma^2.
    np.testing.assert_allclose(
        r.covariance, batch.covariance[0] / batch.noise_variance[0], rtol=1e-5
    )
    assert r.parameters.shape == (1500, 4)


def test_forgetting_tracks_parameter_step():
    rng = np.random.default_rng(21)
    n = 2000
    u = np.sign(rng.standard_normal(n))
    y = np.zeros(n)
    e = 0.05 * rng.standard_normal(n)
    for t in range(1, n):
        b1 = 1.0 if t < 1000 else 2.0  # gain doubles at t = 1000
        y[t] = 0.8 * y[t - 1] + b1 * u[t - 1] + e[t]
    d = bb.UniformData(u, y, 0.1)
    forget = bb.recursive_arx(d, 1, 1, 1, forgetting=0.97)
    rls = bb.recursive_arx(d, 1, 1, 1, forgetting=1.0)
    kalman = bb.recursive_arx(d, 1, 1, 1, process_noise=1e-4, noise_variance=0.05**2)
    assert forget.parameters[990, 1] == pytest.approx(1.0, abs=0.05)
    assert forget.parameters[1200, 1] == pytest.approx(2.0, abs=0.05)
    assert kalman.parameters[1200, 1] == pytest.approx(2.0, abs=0.05)
    # Without forgetting the estimate averages the two regimes.
    assert abs(rls.parameters[-1, 1] - 2.0) > 0.3


def test_carry_estimate_into_validation_and_armax():
    rng = np.random.default_rng(22)
    d = _data(rng, n=3000, c=(1.0, -0.6, 0.2))
    est, val = d.segment(0, 2000), d.segment(2000, 3000)
    r1 = bb.recursive_armax(est, 2, 2, 2, 1)
    r2 = bb.recursive_armax(val, 2, 2, 2, 1, init=r1)
    assert r2.parameters[0] == pytest.approx(r1.final_parameters)
    np.testing.assert_allclose(r2.final_parameters, [-1.5, 0.7, 1.0, 0.5, -0.6, 0.2], atol=0.05)
    batch = bb.fit_armax(d, 2, 2, 2, 1)
    np.testing.assert_allclose(r2.final_parameters, batch.parameters[0], atol=0.03)
    m = r2.model()
    assert isinstance(m, bb.ARMAX)
    assert bb.compare(m, val, 1).fit_percent[0] > bb.compare(m, val).fit_percent[0]


def test_recursive_bad_input():
    d = _data(np.random.default_rng(23), n=50)
    with pytest.raises(ValueError, match="C part"):
        bb.recursive_armax(d, 2, 2, 1, 1, theta0=[0, 0, 0, 0, 1.5])
    with pytest.raises(ValueError, match="forgetting"):
        bb.recursive_arx(d, 2, 2, 1, forgetting=1.5)
    with pytest.raises(ValueError, match="theta0: expected 4"):
        bb.recursive_arx(d, 2, 2, 1, theta0=[0.0])
    with pytest.raises(ValueError, match="process_noise: .* symmetric"):  # a covariance
        bb.recursive_arx(d, 2, 2, 1, process_noise=np.triu(np.ones((4, 4))))


def _textbook(rows, y, theta, P, lam, R1, R2, nc=0):
    """Reference recursion as the textbook writes it (Ljung 1999, eq. 11.66 with a random
    walk): K = P phi (lam R2 + phi^T P phi)^-1, theta += K eps, P = (I - K phi^T) P / lam + R1,
    the ARMAX regressor's C part the past a-posteriori residuals."""
    rows = rows.copy()
    past, traj = np.zeros(nc), []
    for r in range(len(y)):
        if nc:
            rows[r, -nc:] = past
        phi = rows[r][:, None]
        k = P @ phi @ np.linalg.inv(lam * R2 + phi.T @ P @ phi)
        theta = theta + (k * (y[r] - phi.T @ theta)).ravel()
        P = (np.eye(len(theta)) - k @ phi.T) @ P / lam + R1
        if nc:
            past = np.r_[y[r] - rows[r] @ theta, past[:-1]]
        traj.append(theta)
    return np.array(traj), P


@pytest.mark.parametrize("nc", [0, 2])
def test_recursion_equals_the_textbook_update(nc):
    """Forgetting and a random walk together, ARX and ARMAX: every parameter trajectory and
    the final covariance equal the textbook recursion's; the covariance stays exactly
    symmetric (its update is formed symmetric, not symmetrised afterwards)."""
    from greybox.blackbox._arx import arx_regressors

    d = _data(np.random.default_rng(24), n=400, c=(1.0, -0.6, 0.2))
    lam, q, r2, p0 = 0.98, 1e-4, 0.04, 100.0
    opts = dict(forgetting=lam, process_noise=q, noise_variance=r2, P0=p0)
    if nc:
        r = bb.recursive_armax(d, 2, 2, nc, 1, **opts)
    else:
        r = bb.recursive_arx(d, 2, 2, 1, **opts)
    phi, y = arx_regressors(d, 0, 2, (2,), (1,), False)
    rows = np.concatenate([phi, np.zeros((len(y), nc))], axis=1)
    p = rows.shape[1]
    traj, P = _textbook(rows, y, np.zeros(p), p0 * np.eye(p), lam, q * np.eye(p), r2, nc)
    n0 = d.n_samples - len(y)
    np.testing.assert_allclose(r.parameters[n0:], traj, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(r.covariance, P, rtol=1e-9, atol=1e-15)
    np.testing.assert_array_equal(r.covariance, r.covariance.T)
