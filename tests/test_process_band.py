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


def test_paths_do_not_depend_on_padding_and_similar_lengths_share_one_sampler(posterior):
    """A path draws its noise step by step (a key per step), so padding a run's grid to a
    bucketed length (0 s steps, no noise) leaves every real step's draw and the path as
    they are; waveforms of similar lengths (153 and 158 frames) therefore share one
    compiled sampler (each length compiled its own before). Truth: the paths on the run's
    own grid, unpadded, equal the padded ones exactly."""
    import jax
    import jax.numpy as jnp

    from greybox.stochastic import _sde_device as sde
    from tests.helpers import backend_compiles

    t = ou.frames(158)
    wave = od.inputs(float(t[-1]) + ou.DT)
    posterior.band(wave, t[:153])
    with backend_compiles() as compiled:
        band = posterior.band(wave, t)
    assert [c for c in compiled if "_draw_jit" in c] == [] and band.y.shape == (158, 1)
    model = posterior.model
    e = sde.unread_run(model, wave, t)
    keys = jax.random.split(jax.random.PRNGKey(4), 3)
    own = sde._grid(e)
    paths = []
    for lengths in ((own.n_frames, own.n_steps), None, (own.n_frames + 30, own.n_steps + 41)):
        grid, t_s, _ = sde.padded_record(e, lengths)
        z = sde._paths_jit(sde.as_arrays(model), grid, jnp.asarray(t_s), sde._t0(e), keys, True)
        paths.append(np.asarray(z)[:, :158])
    assert grid.n_steps > own.n_steps
    np.testing.assert_array_equal(paths[1], paths[0])
    np.testing.assert_array_equal(paths[2], paths[0])
