"""Expected Fisher information of the Kalman-filter likelihood of one run (process noise).

For a linear device with Gaussian process and measurement noise the readings of one run are
jointly Gaussian, y ~ N(mu(theta), Sigma(theta)), and the Kalman filter's likelihood is exactly
that density (the prediction-error decomposition). Its expected information is the Gaussian
one,

    I_ij = dmu/dtheta_i' Sigma^-1 dmu/dtheta_j + 0.5 tr(Sigma^-1 dSigma_i Sigma^-1 dSigma_j),

which the innovations form I = sum_k E[dv_k' S_k^-1 dv_k] + 0.5 tr(S_k^-1 dS_k S_k^-1 dS_k)
equals (the expectation taken over the random parts of dv_k, not only its mean). mu and Sigma
are built from the same exact discretisation the filter uses (`discretise`): the state mean and
covariance are propagated over the filter's steps, and the cross-covariance of every earlier
frame's state with the current one is carried along (Cov(x_j, x_k) = Ad Cov(x_j, x_{k-1})),
so Sigma is the dense (N q, N q) covariance of the readings and its derivatives come from
forward-mode autodiff. Cost O((N q)^3) per run: exact and simple, meant for design runs of up
to a few thousand readings, not for long logs. When the first frame is conditioned on (a known
initial state, `score_first` False) the information of y_1 alone is subtracted (chain rule:
I(y_2..N | y_1) = I(y) - I(y_1)). Nonlinear devices (the EKF) are refused.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from greybox._compile import jit
from greybox._model.freeparams import apply_raw, as_leaves
from greybox.stochastic._kalman import FilterGrid, discretise_steps
from greybox.stochastic._sde_device import StochasticDevice, _readout_terms


def reading_moments(model: StochasticDevice, grid: FilterGrid, t_s, t0):
    """(mean (N, q), covariance (N q, N q)) of the readings of one run, frame-major."""
    if model.use_ekf:
        raise ValueError(
            "process-noise information: computed for linear devices (the Kalman filter); "
            f"{type(model.device).__name__} is filtered by the EKF"
        )
    dtype = jnp.result_type(float)
    sde = model.linear_sde(dtype)
    Ad, Bd, Qd = discretise_steps(sde.A, sde.B, sde.Qc, grid, dtype)
    n_frames = t_s.shape[0]
    n = sde.A.shape[0]

    def step(carry, inp):
        m, P, K = carry
        A_i, B_i, Q_i, u_i, f = inp
        m = A_i @ m + B_i @ u_i
        P = A_i @ P @ A_i.T + Q_i
        K = K @ A_i.T  # Cov(x_frame_j, x_now) for every frame j already passed
        K = jnp.where(f >= 0, K.at[jnp.maximum(f, 0)].set(P), K)
        return (m, P, K), (m, K)

    init = (sde.x0, sde.P0, jnp.zeros((n_frames, n, n), dtype))
    u = jnp.asarray(grid.u, dtype)
    _, (ms, Ks) = jax.lax.scan(step, init, (Ad, Bd, Qd, u, jnp.asarray(grid.frame)))
    mean_x = ms[grid.step]  # (N, n)
    T = Ks[grid.step]  # T[k, j] = Cov(x_j, x_k) for j <= k, 0 for j > k
    lower = (jnp.arange(n_frames)[None, :] <= jnp.arange(n_frames)[:, None])[..., None, None]
    # cov[j, k] = Cov(x_j, x_k): T[k, j] below the diagonal, T[j, k]^T above
    cov = jnp.where(
        jnp.swapaxes(lower, 0, 1), jnp.swapaxes(T, 0, 1), jnp.swapaxes(T, -1, -2)
    )
    C, R = sde.C, sde.R
    q = C.shape[0]
    off = _readout_terms(model.device, t_s, t0, q).reshape(n_frames, q)
    mean_y = mean_x @ C.T + sde.d + off
    cov_y = jnp.einsum("ia,jkab,lb->jikl", C, cov, C) + jnp.eye(n_frames)[:, None, :, None] * R[
        None, :, None, :
    ]
    return mean_y, cov_y.reshape(n_frames * q, n_frames * q)


def _gaussian_information(dmu, dsig, sig):
    """Fisher information of N(mu, Sigma): dmu (M, P), dsig (M, M, P), sig (M, M)."""
    L = jnp.linalg.cholesky(0.5 * (sig + sig.T))

    def solve(b):
        return jax.scipy.linalg.cho_solve((L, True), b)

    a = solve(dmu)
    W = jax.vmap(solve, in_axes=-1, out_axes=0)(dsig)  # (P, M, M): Sigma^-1 dSigma_i
    return dmu.T @ a + 0.5 * jnp.einsum("iab,jba->ij", W, W)


@jit
def _information(model, free, raw, grid, t_s, t0):
    def moments(r):
        return reading_moments(apply_raw(model, free, r), grid, t_s, t0)

    mu, sig = moments(raw)
    dmu, dsig = jax.jacfwd(moments)(raw)
    q = mu.shape[1]
    n_raw = raw.shape[0]
    info = _gaussian_information(dmu.reshape(-1, n_raw), dsig, sig)
    if model.score_first:
        return info
    first = _gaussian_information(dmu[0], dsig[:q, :q], sig[:q, :q])
    return info - first


def expected_information(model: StochasticDevice, free, raw, inputs, t_s, *, t_start_s=0.0):
    """(P, P) expected Fisher information of the raw coordinates `raw` of `free` from one run
    of `model` (a linear `StochasticDevice`) driven by `inputs` and read at `t_s` [s]: the
    information of the likelihood `greybox.fit(..., noise=ProcessNoise(...))` maximises
    (module docstring). Its inverse is the Cramer-Rao bound of the raw estimates."""
    import numpy as np

    from greybox._simulate.simulate import as_arrays
    from greybox.stochastic._sde_device import _grid, _t0, unread_run

    e = unread_run(model, inputs, t_s, t_start_s)
    out = _information(
        as_arrays(model), as_leaves(free), jnp.asarray(raw, dtype=float), _grid(e),
        jnp.asarray(e.t_s), _t0(e),
    )
    return np.asarray(out)
