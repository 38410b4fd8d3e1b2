"""ARX: DaISy hair-dryer reference, closed-form least squares, Monte Carlo calibration,
MIMO/multi-experiment, order selection, bad input."""

from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from greybox import blackbox as bb

DRYER = Path(__file__).resolve().parents[1] / "experiments" / "hair_dryer" / "dryer.dat"
A_TRUE = np.array([1.0, -1.5, 0.7])
B_TRUE = np.array([0.0, 1.0, 0.5])  # nk = 1, nb = 2


def _dryer():
    raw = np.loadtxt(DRYER)
    full = bb.UniformData(raw[:, 0], raw[:, 1], 0.08, name="dryer")
    return bb.detrend(full.segment(0, 300)), bb.detrend(full.segment(799, 900))


def _arx_data(rng, n=400, sigma=0.3):
    u = np.sign(rng.standard_normal(n))
    y = lfilter(B_TRUE, A_TRUE, u) + lfilter([1.0], A_TRUE, sigma * rng.standard_normal(n))
    return bb.UniformData(u, y, 0.1)


def test_hair_dryer_arx_223_matches_reference():
    ze, zv = _dryer()
    m = bb.fit_arx(ze, 2, 2, 3)
    np.testing.assert_allclose(m.a[0], [1, -1.2737, 0.3935], atol=5e-4)
    np.testing.assert_allclose(m.b[0, 0], [0, 0, 0, 0.0666, 0.0445], atol=5e-4)
    fits = {
        (name, k): bb.compare(m, d, k).fit_percent[0]
        for name, d in (("est", ze), ("val", zv))
        for k in (None, 1)
    }
    # Reference table (PROVENANCE.md): simulation vs one-step, estimation and validation.
    assert fits["est", None] == pytest.approx(88.9, abs=0.06)
    assert fits["est", 1] == pytest.approx(95.1, abs=0.06)
    assert fits["val", None] == pytest.approx(88.2, abs=0.06)
    assert fits["val", 1] == pytest.approx(94.5, abs=0.06)


def _loop_regressors(d, i, na, nb, nk, offset):
    """Independent, loop-based regressor (GEKKO form, own past only)."""
    n0 = max([na] + [k + b - 1 for b, k in zip(nb, nk)])
    rows, ys = [], []
    for t in range(n0, d.n_samples):
        row = [-d.y[t - j, i] for j in range(1, na + 1)]
        for l in range(d.nu):
            row += [d.u[t - nk[l] - j, l] for j in range(nb[l])]
        rows.append(row + ([1.0] if offset else []))
        ys.append(d.y[t, i])
    return np.array(rows), np.array(ys)


def test_mimo_multi_experiment_matches_lstsq():
    rng = np.random.default_rng(1)
    exps = [
        bb.UniformData(rng.standard_normal((n, 2)), rng.standard_normal((n, 3)), 0.5)
        for n in (80, 120)
    ]
    nb, nk = (2, 1), (1, 3)
    m = bb.fit_arx(exps, 2, nb, nk, offset=True)
    for i in range(3):
        parts = [_loop_regressors(d, i, 2, nb, nk, True) for d in exps]
        phi = np.concatenate([p[0] for p in parts])
        y = np.concatenate([p[1] for p in parts])
        theta, res, *_ = np.linalg.lstsq(phi, y, rcond=None)
        np.testing.assert_allclose(m.parameters[i], theta, rtol=1e-10, atol=1e-12)
        s2 = res[0] / (len(y) - len(theta))
        np.testing.assert_allclose(m.covariance[i], s2 * np.linalg.inv(phi.T @ phi), rtol=1e-8)
    assert m.n_rows == (80 - 3) + (120 - 3)  # max lag = nk_2 + nb_2 - 1 = 3


def test_mimo_gekko_form_noise_free_recovery():
    rng = np.random.default_rng(2)
    n = 300
    u = rng.standard_normal((n, 2))
    y = np.zeros((n, 2))
    for t in range(1, n):  # y_i(k) = a y_i(k-1) + sum_l b_il u_l(k-1) + gamma_i
        y[t, 0] = 0.8 * y[t - 1, 0] + 0.5 * u[t - 1, 0] - 0.2 * u[t - 1, 1] + 0.3
        y[t, 1] = 0.6 * y[t - 1, 1] + 0.1 * u[t - 1, 0] + 0.9 * u[t - 1, 1] - 1.0
    m = bb.fit_arx(bb.UniformData(u, y, 1.0), 1, 1, 1, offset=True)
    np.testing.assert_allclose(
        m.parameters, [[-0.8, 0.5, -0.2, 0.3], [-0.6, 0.1, 0.9, -1.0]], atol=1e-10
    )
    sim = bb.simulate(m, bb.UniformData(u, y, 1.0))
    np.testing.assert_allclose(sim, y, atol=1e-8)


def test_arx_standard_errors_calibrated_by_monte_carlo():
    rng = np.random.default_rng(3)
    truth = np.r_[A_TRUE[1:], B_TRUE[1:]]
    est, se = [], []
    for _ in range(300):
        m = bb.fit_arx(_arx_data(rng), 2, 2, 1)
        est.append(m.parameters[0])
        se.append(m.std_errors[0])
    est, se = np.array(est), np.array(se)
    assert np.all(np.abs(est[0] - truth) < 3 * se[0])
    ratio = est.std(0) / se.mean(0)
    assert np.all((ratio > 1 / 1.5) & (ratio < 1.5)), ratio
    assert np.all(np.abs(est.mean(0) - truth) < 4 * est.std(0) / np.sqrt(len(est)))


def test_arx_matches_sippy():
    sippy = pytest.importorskip("sippy_unipi")
    ze, _ = _dryer()
    m = bb.fit_arx(ze, 2, 2, 3)
    # SIPPY's theta = nk - 1 (its theta = 0 already means one sample of delay).
    sys = sippy.system_identification(
        ze.y[:, 0], ze.u[:, 0], "ARX", ARX_orders=[2, 2, 2], centering="None"
    )
    den = np.trim_zeros(np.asarray(sys.DENOMINATOR[0][0], float), "b")
    num = np.trim_zeros(np.asarray(sys.NUMERATOR[0][0], float), "f")
    np.testing.assert_allclose(den, m.a[0], atol=1e-6)
    np.testing.assert_allclose(num, m.b[0, 0, 3:], atol=1e-6)


def test_predict_horizons_and_simulation():
    rng = np.random.default_rng(4)
    d = _arx_data(rng, n=200)
    m = bb.fit_arx(d, 2, 2, 1)
    n = bb.n_initial(m)
    a, b = m.a[0], m.b[0, 0]
    y, u = d.y[:, 0], d.u[:, 0]
    # Independent 2-step predictor: iterate the ARX once with the predicted y(t-1).
    p1 = np.array(
        [
            -a[1] * y[t - 1] - a[2] * y[t - 2] + b[1] * u[t - 1] + b[2] * u[t - 2]
            for t in range(n, 200)
        ]
    )
    p2 = [
        -a[1] * p1[t - n - 1] - a[2] * y[t - 2] + b[1] * u[t - 1] + b[2] * u[t - 2]
        for t in range(n + 1, 200)
    ]
    np.testing.assert_allclose(bb.predict(m, d, 1)[n:, 0], p1, atol=1e-12)
    np.testing.assert_allclose(bb.predict(m, d, 2)[n + 1 :, 0], p2, atol=1e-12)
    np.testing.assert_allclose(bb.predict(m, d, 10_000), bb.simulate(m, d), atol=1e-10)
    sim = bb.simulate(m, d)[:, 0]
    ref = y.copy()
    for t in range(n, 200):
        ref[t] = -a[1] * ref[t - 1] - a[2] * ref[t - 2] + b[1] * u[t - 1] + b[2] * u[t - 2]
    np.testing.assert_allclose(sim, ref, atol=1e-10)
    assert bb.compare(m, d, 1).fit_percent[0] > bb.compare(m, d).fit_percent[0]


def test_order_search_finds_true_orders():
    rng = np.random.default_rng(5)
    est, val = _arx_data(rng, n=1000), _arx_data(rng, n=1000)
    s = bb.arx_order_search(
        est, val, na=range(1, 4), nb=range(1, 4), nk=range(0, 3), criterion="mdl"
    )
    assert s.best == (2, 2, 1)
    assert s.on_validation and len(s.loss) == 27
    # Loss of the true structure is close to the noise variance 0.09.
    true_row = np.flatnonzero((s.orders == [2, 2, 1]).all(1))[0]
    assert s.loss[true_row] == pytest.approx(0.09, rel=0.15)


def test_bad_input_messages():
    d = bb.UniformData(np.ones(6), np.arange(6.0), 1.0)
    with pytest.raises(ValueError, match="regression rows"):
        bb.fit_arx(d, 3, 3, 1)
    with pytest.raises(ValueError, match="nk.*non-causal"):
        bb.fit_arx(d, 1, 1, -1)
    with pytest.raises(ValueError, match="non-finite.*sample 2"):
        bb.UniformData([1.0, 2, 3], [1.0, 2, np.nan], 1.0)
    with pytest.raises(ValueError, match="dt"):
        bb.UniformData([1.0, 2], [1.0, 2], 0.0)
    with pytest.raises(ValueError, match="nb: got 1 values for 2 inputs"):
        bb.fit_arx(bb.UniformData(np.ones((9, 2)), np.ones(9), 1.0), 1, [1], 1)
