"""Householder QR least squares in plain array operations: the linear solve of each
Levenberg-Marquardt step on an accelerator.

Each step solves the damped least-squares problem [J; sqrt(lambda) I] d = [r; 0] by QR
(`optx.LevenbergMarquardt`'s default, `lx.QR`). On a GPU, `lx.QR` applies Q^T with LAPACK's
`ormqr`, which cuSOLVER has only for one matrix at a time: under `vmap`, jaxlib loops over
the batch, one small kernel per device, at every step of every solve, so a batch of 10,000
fits spent most of its time in that loop. Here the factorisation and Q^T b are the same
Householder reflections as LAPACK's (`dgeqrf`'s `dlarfg`: overflow-safe norms, H = I -
tau v v^T), written as array operations that vectorise over the batch; only the final
n x n triangular solve is a library call (batched on a GPU). On a CPU `lx.QR` (LAPACK) is
kept (`lm_linear_solver`).
"""

from __future__ import annotations

from typing import Any

import equinox.internal as eqxi
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import lineax as lx

from greybox import _platform

try:  # lineax's own helpers that flatten a PyTree operator's structures (the damped
    # operator's output is a (residuals, zeros) pair), the same ones `lx.QR` uses
    from lineax._solver.misc import (
        pack_structures,
        ravel_vector,
        transpose_packed_structures,
        unravel_solution,
    )
except ImportError:  # a lineax that moved them: LAPACK's QR everywhere (`lm_linear_solver`);
    pack_structures = None  # tests/test_householder_qr.py fails, which says so


def _scaled_norm(x):
    """||x||_2 without overflow or underflow (the damping rows reach sqrt(float max))."""
    scale = jnp.max(jnp.abs(x))
    safe = jnp.where(scale > 0, scale, 1.0)
    return scale * jnp.sqrt(jnp.sum((x / safe) ** 2))


def householder_qr(a):
    """(R (n, n), V (m, n), tau (n,)) of a tall `a` (m, n), m >= n: a = Q R with
    Q = H_1 ... H_n, H_k = I - tau_k v_k v_k^T (v_k = column k of V, zero above row k,
    one at row k), as LAPACK's `dgeqrf` forms them."""
    m, n = a.shape
    rows = jnp.arange(m)

    def reflect(k, carry):
        a, v_all, tau_all = carry
        col = a[:, k]
        alpha = col[k]
        below = jnp.where(rows > k, col, 0.0)
        xnorm = _scaled_norm(below)
        beta = -jnp.where(alpha >= 0, 1.0, -1.0) * jnp.hypot(alpha, xnorm)
        trivial = xnorm == 0  # already triangular in this column: H = I (LAPACK's tau = 0)
        safe_beta = jnp.where(trivial, 1.0, beta)
        safe_den = jnp.where(trivial, 1.0, alpha - beta)
        tau = jnp.where(trivial, 0.0, (beta - alpha) / safe_beta)
        v = jnp.where(rows == k, 1.0, below / safe_den)
        a = a - tau * jnp.outer(v, v @ a)
        # column k is now beta e_k; set it exactly so later reflections see true zeros
        a = a.at[:, k].set(jnp.where(rows == k, jnp.where(trivial, alpha, beta), col * (rows < k)))
        return a, v_all.at[:, k].set(v), tau_all.at[k].set(tau)

    init = (a, jnp.zeros_like(a), jnp.zeros(n, a.dtype))
    r_full, v, tau = jax.lax.fori_loop(0, n, reflect, init)
    return jnp.triu(r_full[:n]), v, tau


def _reflect(v, tau, k, b):
    """H_k b = b - tau_k v_k (v_k^T b)."""
    return b - tau[k] * v[:, k] * (v[:, k] @ b)


def apply_qt(v, tau, b):
    """Q^T b = H_n ... H_1 b."""
    return jax.lax.fori_loop(0, v.shape[1], lambda k, b: _reflect(v, tau, k, b), b)


def apply_q(v, tau, b):
    """Q b = H_1 ... H_n b."""
    n = v.shape[1]
    return jax.lax.fori_loop(0, n, lambda i, b: _reflect(v, tau, n - 1 - i, b), b)


class HouseholderQR(lx.AbstractLinearSolver):
    """`lx.QR` with the factorisation and Q^T b as array operations (see the module
    docstring); full-rank operators, tall (least squares) or wide (minimum norm)."""

    def init(self, operator, options):
        del options
        matrix = operator.as_matrix()
        m, n = matrix.shape
        transpose = n > m
        if transpose:
            matrix = matrix.T
        return householder_qr(matrix), eqxi.Static(transpose), pack_structures(operator)

    def compute(self, state, vector, options) -> tuple[Any, lx.RESULTS, dict]:
        (r, v, tau), transpose, packed = state
        del options
        vector = ravel_vector(vector, packed)
        if transpose.value:  # minimum norm: x = Q [R^{-T} b; 0]
            z = jsl.solve_triangular(r, vector, trans="T", lower=False)
            solution = apply_q(v, tau, jnp.zeros(v.shape[0], z.dtype).at[: z.shape[0]].set(z))
        else:  # least squares: x = R^{-1} (Q^T b)[:n]
            qtb = apply_qt(v, tau, vector)[: r.shape[0]]
            solution = jsl.solve_triangular(r, qtb, lower=False)
        return unravel_solution(solution, packed), lx.RESULTS.successful, {}

    def transpose(self, state, options):
        factors, transpose, packed = state
        return (factors, eqxi.Static(not transpose.value), transpose_packed_structures(packed)), {}

    def conj(self, state, options):  # real matrices only (a fit's Jacobians are real)
        return state, {}

    def assume_full_rank(self):
        return True


def lm_linear_solver() -> lx.AbstractLinearSolver:
    """The QR solver of each Levenberg-Marquardt step: LAPACK's (`lx.QR`) on a CPU, the
    vectorised Householder one on an accelerator (same reflections, see the docstring)."""
    if _platform.on_accelerator() and pack_structures is not None:
        return HouseholderQR()
    return lx.QR()
