"""ARMAX (PEM) and OE on data from known systems: recovery, Monte Carlo calibration of the
reported standard errors, multi-experiment, bad input."""

import numpy as np
import pytest
from scipy.signal import lfilter

from greybox import blackbox as bb

A = np.array([1.0, -1.5, 0.7])
B = np.array([0.0, 1.0, 0.5])
C = np.array([1.0, -0.6, 0.2])
TRUTH = np.r_[A[1:], B[1:], C[1:]]
N = 1000  # fixed length: one compilation of the jitted solver serves every fit


def _armax_data(rng, sigma=0.3):
    u = np.sign(rng.standard_normal(N))
    y = lfilter(B, A, u) + lfilter(C, A, sigma * rng.standard_normal(N))
    return bb.UniformData(u, y, 0.1)


def test_armax_monte_carlo_calibration():
    rng = np.random.default_rng(10)
    est, se = [], []
    for _ in range(60):
        m = bb.fit_armax(_armax_data(rng), 2, 2, 2, 1)
        assert m.converged
        est.append(m.parameters[0])
        se.append(m.std_errors[0])
    est, se = np.array(est), np.array(se)
    assert np.all(np.abs(est[0] - TRUTH) < 3 * se[0])
    assert np.all(np.abs(est.mean(0) - TRUTH) < 4 * est.std(0) / np.sqrt(len(est)))
    ratio = est.std(0) / se.mean(0)
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    assert m.noise_variance[0] == pytest.approx(0.09, rel=0.15)


def test_armax_beats_arx_in_simulation_and_multi_experiment():
    rng = np.random.default_rng(11)
    d1, d2, val = _armax_data(rng), _armax_data(rng), _armax_data(rng)
    arm = bb.fit_armax([d1, d2.segment(0, 700)], 2, 2, 2, 1)
    arx = bb.fit_arx([d1, d2.segment(0, 700)], 2, 2, 1)
    assert arm.n_rows == (N - 2) + (700 - 2)
    assert np.all(np.abs(arm.parameters[0] - TRUTH) < 4 * arm.std_errors[0])
    # ARX is biased under coloured noise; the PEM estimate is not.
    assert bb.compare(arm, val).fit_percent[0] > bb.compare(arx, val).fit_percent[0]
    # The one-step predictor of the true system: PEM's residuals match its innovations.
    true = bb.ARMAX.from_coefficients(A, [B], C, dt=0.1)
    e_true = bb.innovations(true, val)[:, 0]
    e_fit = bb.innovations(arm, val)[:, 0]
    assert np.std(e_fit) == pytest.approx(np.std(e_true), rel=0.02)


def test_armax_matches_sippy_fit_or_better():
    sippy = pytest.importorskip("sippy_unipi")
    rng = np.random.default_rng(12)
    est, val = _armax_data(rng), _armax_data(rng)
    m = bb.fit_armax(est, 2, 2, 2, 1)
    sys = sippy.system_identification(
        est.y[:, 0],
        est.u[:, 0],
        "ARMAX",
        ARMAX_orders=[2, 2, 2, 0],
        ARMAX_mod="ILLS",
        max_iterations=200,
        centering="None",
    )
    a_s = np.trim_zeros(np.asarray(sys.DENOMINATOR[0][0], float), "b")
    b_s = np.trim_zeros(np.asarray(sys.NUMERATOR[0][0], float), "f")
    ref = bb.ARMAX.from_coefficients(a_s, [np.r_[0.0, b_s]], [1.0], dt=0.1)
    assert bb.compare(m, val).fit_percent[0] >= bb.compare(ref, val).fit_percent[0] - 0.1


def test_oe_recovers_system_and_simulation_error_is_minimal():
    rng = np.random.default_rng(13)
    u = np.sign(rng.standard_normal(N))
    y = lfilter(B, A, u) + 0.3 * rng.standard_normal(N)
    d = bb.UniformData(u, y, 0.1)
    m = bb.fit_oe(d, 2, 2, 1)
    truth = np.r_[B[1:], A[1:]]
    assert m.converged
    assert np.all(np.abs(m.parameters[0] - truth) < 3.5 * m.std_errors[0])
    assert m.noise_variance[0] == pytest.approx(0.09, rel=0.15)
    # OE minimises exactly the simulation error: no ARX of the same orders simulates better.
    arx = bb.fit_arx(d, 2, 2, 1)
    assert bb.compare(m, d).fit_percent[0] >= bb.compare(arx, d).fit_percent[0]
    np.testing.assert_allclose(bb.predict(m, d, 1), bb.simulate(m, d), atol=1e-12)


def test_oe_miso_two_experiments():
    rng = np.random.default_rng(14)
    exps = []
    for n in (600, 500):
        u = rng.standard_normal((n, 2))
        y = lfilter([0, 1.0], [1, -0.8], u[:, 0]) + lfilter([0, 0, 0.5], [1, -0.5], u[:, 1])
        exps.append(bb.UniformData(u, y + 0.05 * rng.standard_normal(n), 0.1))
    m = bb.fit_oe(exps, [1, 1], [1, 1], [1, 2])
    np.testing.assert_allclose(m.parameters[0], [1.0, 0.5, -0.8, -0.5], atol=0.03)
    assert np.all(np.abs(m.parameters[0] - [1.0, 0.5, -0.8, -0.5]) < 4 * m.std_errors[0])


def test_armax_bad_input():
    with pytest.raises(ValueError, match="C\\(q\\).*unit circle"):
        bb.ARMAX.from_coefficients(A, [B], [1.0, -1.2], dt=0.1)
    d = bb.UniformData(np.ones(5), np.arange(5.0), 1.0)
    with pytest.raises(ValueError, match="nc: must be >= 1"):
        bb.fit_armax(d, 1, 1, 0, 1)
    with pytest.raises(ValueError, match="usable regression rows|prediction errors"):
        bb.fit_armax(d, 2, 2, 2, 1)
    with pytest.raises(ValueError, match="single-output"):
        bb.fit_armax(bb.UniformData(np.ones(50), np.ones((50, 2)), 1.0), 1, 1, 1, 1)
