"""Prediction-error machinery shared by ARMAX and OE: experiments padded to one shape,
residuals filtered by `lax.scan`, Levenberg-Marquardt from optimistix, covariance from
the Jacobian at the optimum.

Stable polynomials (C for ARMAX, F for OE) are parameterised by kappa with reflection
coefficients tanh(kappa) (Levinson step-up), so every iterate is minimum-phase/stable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from greybox._model.householder import lm_linear_solver

from ._poly import poly_from_reflection


def pad_experiments(blocks: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stack per-experiment arrays (L_e, ...) into (E, L_max, ...) plus a (E, L_max) mask.

    Padding goes at the end so that it never feeds back into valid samples of a filter.
    """
    L = max(b.shape[0] for b in blocks)
    out = np.zeros((len(blocks), L) + blocks[0].shape[1:])
    mask = np.zeros((len(blocks), L))
    for e, b in enumerate(blocks):
        out[e, : b.shape[0]] = b
        mask[e, : b.shape[0]] = 1.0
    return out, mask


def ar_filter(den, w, hist0):
    """y(t) = w(t) - sum_{j>=1} den_j y(t-j) along the last axis of w (JAX scan).

    `hist0` holds [y(-1), y(-2), ...] (length len(den) - 1), the initial conditions.
    """
    tail = den[1:]

    def step(hist, wt):
        yt = wt - jnp.dot(tail, hist)
        return jnp.concatenate([yt[None], hist[:-1]]), yt

    _, ys = jax.lax.scan(step, hist0, w)
    return ys


def stable_poly(kappa):
    return poly_from_reflection(jnp.tanh(kappa))


def _lm_solve(resid, theta0, args, to_direct, max_steps):
    """LM on resid(theta, args); also returns the Jacobian and d(direct)/d(theta)."""
    solver = optx.LevenbergMarquardt(rtol=1e-7, atol=1e-10, linear_solver=lm_linear_solver())
    sol = optx.least_squares(resid, solver, theta0, args, max_steps=max_steps, throw=False)
    theta = sol.value
    r = resid(theta, args)
    jac = jax.jacfwd(resid)(theta, args)
    g = jax.jacfwd(to_direct)(theta)
    ok = sol.result == optx.RESULTS.successful
    return theta, r, jac, g, ok, sol.stats["num_steps"]


def covariance_direct(r, jac, g, n_rows: int):
    """sigma^2 (J_d^T J_d)^-1 in the direct parameters, J_d = J_kappa G^-1."""
    r = np.asarray(r)
    jac = np.asarray(jac)
    g = np.asarray(g)
    p = jac.shape[1]
    sigma2 = float(r @ r) / (n_rows - p)
    # A reflection coefficient at +-1 (a pole or zero on the unit circle) makes the map to the
    # direct parameters singular; the covariance is then undefined, not a crash.
    if not np.all(np.isfinite(jac)) or np.linalg.cond(g) > 1e12:
        return sigma2, np.full((p, p), np.nan)
    jd = np.linalg.solve(g.T, jac.T).T
    info = jd.T @ jd
    return sigma2, sigma2 * np.linalg.pinv(info, rcond=1e-13)
