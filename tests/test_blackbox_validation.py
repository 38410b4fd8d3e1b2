"""Resampling, residual tests, step response, conversions and python-control export."""

import numpy as np
import pytest
from scipy.interpolate import PchipInterpolator
from scipy.signal import lfilter

from greybox import blackbox as bb

A = np.array([1.0, -1.5, 0.7])
B = np.array([0.0, 1.0, 0.5])


def test_resample_matches_scipy_and_labels_results():
    rng = np.random.default_rng(30)
    t = np.cumsum(rng.uniform(0.5, 1.5, 191))  # irregular camera frames
    y = np.sin(0.3 * t) + 0.1 * rng.standard_normal(191)
    u = (np.sin(0.11 * t) > 0).astype(float)
    dt = (t[-1] - t[0]) / 1909
    d = bb.resample(t, u, y, dt, method="pchip", input_method="zoh")
    tq = t[0] + dt * np.arange(d.n_samples)
    assert d.resampled and d.n_samples == 1910
    np.testing.assert_allclose(d.y[:, 0], PchipInterpolator(t, y)(tq), atol=1e-12)
    idx = np.searchsorted(t, tq, side="right") - 1
    np.testing.assert_array_equal(d.u[:, 0], u[idx])
    lin = bb.interpolate(t, y, tq, "linear")
    np.testing.assert_allclose(lin, np.interp(tq, t, y), atol=1e-12)
    m = bb.fit_arx(d, 2, 2, 1)
    assert m.resampled and bb.compare(m, d).resampled
    with pytest.raises(ValueError, match="values: contains NaN"):
        bb.resample(t, u, np.where(t > 50, np.nan, y), dt)
    with pytest.raises(ValueError, match="strictly increasing"):
        bb.interpolate(t[::-1], y, tq)


def test_residual_test_detects_colour_and_missing_input():
    rng = np.random.default_rng(31)
    n = 2000
    u = rng.standard_normal(n)
    y = lfilter(B, A, u) + lfilter([1.0, 0.9], A, 0.3 * rng.standard_normal(n))
    d = bb.UniformData(u, y, 0.1)
    good = bb.fit_armax(d, 2, 2, 1, 1)
    r_good = bb.residual_test(good, d)
    assert r_good.white[0] and r_good.independent[0, 0]
    arx = bb.fit_arx(d, 2, 2, 1)
    assert not bb.residual_test(arx, d).white[0]  # MA(1) noise left in ARX residuals
    short = bb.fit_arx(d, 2, 1, 1)  # misses the input lag 2
    r_short = bb.residual_test(short, d)
    assert not r_short.independent[0, 0]
    lag2 = np.flatnonzero(r_short.cross_lags == 2)[0]
    assert abs(r_short.cross_correlation[0, 0, lag2]) > r_short.band
    assert r_good.band == pytest.approx(2.5758 / np.sqrt(r_good.n_samples), rel=1e-4)


def test_step_response_and_dc_gain():
    m = bb.ARMAX.from_coefficients(A, [B], [1.0, 0.5], dt=0.1)
    s = bb.step_response(m, 300)[:, 0, 0]
    np.testing.assert_allclose(s, lfilter(B, A, np.ones(300)), atol=1e-12)
    assert bb.dc_gain(m)[0, 0] == pytest.approx(1.5 / 0.2)
    assert s[-1] == pytest.approx(7.5, rel=1e-6)
    np.testing.assert_allclose(np.sort(np.abs(bb.poles(m)[0][0])), [np.sqrt(0.7)] * 2)
    np.testing.assert_allclose(bb.zeros(m)[0][0], [-0.5])


def test_d2c_zoh_first_order_and_round_trips():
    dt, gain, tau = 0.1, 2.0, 0.5
    a = np.exp(-dt / tau)
    m = bb.ARMAX.from_coefficients([1, -a], [[0, 0, 0, gain * (1 - a)]], [1.0], dt=dt)
    c = bb.d2c(m, "zoh")
    np.testing.assert_allclose(c.den[0][0], [1, 1 / tau], rtol=1e-10)
    np.testing.assert_allclose(c.num[0][0], [gain / tau], rtol=1e-10)
    assert c.delay_s[0, 0] == pytest.approx(2 * dt)  # nk = 3: one sample is the ZOH lag
    arx = bb.fit_arx(
        bb.UniformData(
            np.sign(np.sin(np.arange(400) * 0.37)),
            lfilter(B, A, np.sign(np.sin(np.arange(400) * 0.37))),
            0.05,
        ),
        2,
        2,
        1,
    )
    for method in ("zoh", "tustin"):
        back = bb.c2d(bb.d2c(arx, method), 0.05, method)
        np.testing.assert_allclose(back.den[0][0], A, atol=1e-8)
        np.testing.assert_allclose(np.trim_zeros(back.num[0][0], "b"), B, atol=1e-8)
        assert bb.dc_gain(bb.d2c(arx, method))[0, 0] == pytest.approx(7.5, rel=1e-6)


def test_against_python_control():
    control = pytest.importorskip("control")
    arx = bb.ARMAX.from_coefficients(A, [B], [1.0], dt=0.05)
    ct = bb.d2c(arx, "tustin")
    # Independent reference: python-control's own Tustin sampling of our continuous model
    # (dead time left out on both sides).
    g = control.tf(list(ct.num[0][0]), list(ct.den[0][0]))
    gd = control.sample_system(g, 0.05, method="tustin")
    no_delay = bb.ContinuousTF(ct.num, ct.den, np.zeros((1, 1)), "tustin", 0.05)
    gz = bb.to_control(bb.c2d(no_delay, 0.05, "tustin"))
    gzoh = control.sample_system(g, 0.05, method="zoh")
    np.testing.assert_allclose(
        bb.to_control(bb.c2d(no_delay, 0.05, "zoh"))(np.exp(1j * np.linspace(0.1, 3.0, 7))),
        gzoh(np.exp(1j * np.linspace(0.1, 3.0, 7))),
        rtol=1e-8,
    )
    w = np.exp(1j * np.linspace(0.1, 3.0, 7))
    np.testing.assert_allclose(gz(w), gd(w), rtol=1e-8)
    exported = bb.to_control(arx)
    assert exported.dt == 0.05
    np.testing.assert_allclose(
        exported(w), (w**-1 + 0.5 * w**-2) / (1 - 1.5 / w + 0.7 / w**2), rtol=1e-10
    )
    ss = bb.to_control(arx, "ss")
    np.testing.assert_allclose(control.dcgain(ss), 7.5, rtol=1e-10)
    with pytest.raises(ValueError, match="pade_order"):
        bb.to_control(ct)
