"""`Posterior.band` of a process-noise model: the spread of sample paths (process noise,
parameter draws, measurement noise on request), against the closed-form variance of the
scalar OU process of tests/ou_reference.py.

With the parameters known (zero covariance) the reading at frame k is Gaussian with mean the
noise-free response and variance P_k = qd (1 - a^(2k)) / (1 - a^2) (+ sd^2 with measurement
noise): the 95 % band is mean +- 1.96 sqrt(P_k). 200 paths estimate it to a few %; the test
compares the band's width averaged over the second half of the record (10 %).
"""

import numpy as np
import pytest

import greybox

from tests import ou_device as od
from tests import ou_reference as ou

N = 300


@pytest.fixture(scope="module")
def posterior():
    model = od.model(ou.TRUTH)
    raw = np.array([float(p.to_raw(v)) for p, v in zip(od.FREE, (ou.TRUTH[k] for k in od.NAMES))])
    return greybox.Posterior(
        model, od.FREE, raw, np.zeros((4, 4)), np.zeros((0, 4)), np.array([ou.TRUTH["sd"]]),
        "zoh", noise=greybox.ProcessNoise(od.STRUCTURE),
    )


def _closed_form_sd(with_measurement: bool) -> np.ndarray:
    tau, a, qd = ou._disc(ou.TRUTH)
    k = np.arange(N)
    var = qd * (1 - a ** (2 * k)) / (1 - a * a)
    return np.sqrt(var + (ou.TRUTH["sd"] ** 2 if with_measurement else 0.0))


@pytest.mark.parametrize("noise", [False, True])
def test_band_is_the_process_spread(posterior, noise):
    t = ou.frames(N)
    band = posterior.band(od.inputs(float(t[-1]) + ou.DT), t, noise=noise)
    assert "sample paths" in band.kind and ("measurement noise" in band.kind) == noise
    np.testing.assert_allclose(band.y[:, 0], ou.mean_response(ou.TRUTH, N), rtol=1e-9)
    half = slice(N // 2, N)
    width = (band.upper - band.lower)[half, 0]
    expected = 2 * 1.96 * _closed_form_sd(noise)[half]
    assert np.mean(width) == pytest.approx(np.mean(expected), rel=0.10)
    # the band sits around the response (no bias beyond the sampling error)
    centre = 0.5 * (band.upper + band.lower)[half, 0] - band.y[half, 0]
    assert abs(np.mean(centre)) < 0.1 * np.mean(expected)
