"""The black-box filters and the ZOH inversion against independent references.

- `d2c(..., "zoh")` of the exact ZOH sampling of 1/(s+1)^2 (a repeated pole, sampled by
  scipy.signal.cont2discrete) must give back 1/(s^2 + 2 s + 1);
- the filters behind simulation and prediction (scipy.signal.lfilter) must reproduce the
  plain-Python recursion they replaced to 1e-12 (the recursion is kept here as reference).
"""

import numpy as np
import pytest
from scipy import signal

from greybox import blackbox as bb
from greybox.blackbox._poly import _ar_recursion, lfilter


def _reference_recursion(a, w, y, start):
    """The plain loop: y(t) = w(t) - sum_j a_j y(t-j), y[:start] given, zeros before 0."""
    n = len(a) - 1
    out = np.zeros(len(w))
    out[:start] = y[:start]
    for t in range(start, len(w)):
        acc = w[t]
        for j in range(1, n + 1):
            if t - j >= 0:
                acc -= a[j] * out[t - j]
        out[t] = acc
    return out


@pytest.mark.parametrize("start", [0, 1, 2, 5])
def test_ar_recursion_matches_the_plain_loop(start):
    rng = np.random.default_rng(start)
    a = np.array([1.0, -1.2, 0.5, -0.1])
    w = rng.standard_normal(300)
    y = rng.standard_normal(300)
    got = _ar_recursion(a, w, y, start)
    want = _reference_recursion(a, w, y, start)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_lfilter_matches_the_plain_loop():
    rng = np.random.default_rng(1)
    x = rng.standard_normal(500)
    b, a = np.array([0.0, 0.3, 0.2]), np.array([1.0, -0.9, 0.2])
    w = np.convolve(x, b)[: x.size]
    np.testing.assert_allclose(
        lfilter(b, a, x), _reference_recursion(a, w, np.zeros(500), 0), rtol=0, atol=1e-12
    )


def test_d2c_zoh_recovers_a_repeated_pole():
    dt = 0.1
    num_z, den_z, _ = signal.cont2discrete(([1.0], [1.0, 2.0, 1.0]), dt, method="zoh")
    num_z = np.ravel(num_z)  # descending powers of z = powers of q^-1 (same length)
    tf = bb.DiscreteTF(((num_z,),), ((np.asarray(den_z, dtype=float),),), dt)
    c = bb.d2c(tf, "zoh")
    np.testing.assert_allclose(c.den[0][0], [1.0, 2.0, 1.0], rtol=1e-9, atol=1e-9)
    num = np.asarray(c.num[0][0])
    np.testing.assert_allclose(num[-1], 1.0, rtol=1e-9)  # numerator 1: the rest is round-off
    np.testing.assert_allclose(num[:-1], 0.0, atol=1e-12)
    assert c.delay_s[0, 0] == pytest.approx(0.0)
