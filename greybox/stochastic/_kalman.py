"""Continuous-discrete Kalman filter, RTS smoother and likelihood for linear stochastic models.

The model (a linear stochastic differential equation observed at irregular frame times):

    dx = (A x + B u(t)) dt + dW,        E[dW dW^T] = Qc dt    (Qc = G G^T, the intensities)
    y_k = C x(t_k) + D u(t_k) + d + e_k,   e_k ~ N(0, R)      (or y_k = h(x(t_k), u(t_k)) + e_k)
    x(t0) ~ N(x0, P0)

`u(t)` is piecewise constant (zero-order hold) and may switch between frames. `FilterGrid`
steps through the union of the switching times and the frame times, so each step has a
constant input and its discretisation is exact (Van Loan 1978):

    expm([[-A, Qc, 0], [0, A^T, 0], [0, B^T, 0]] h) gives
    Ad = e^{A h},  Bd = int_0^h e^{A s} ds B,  Qd = int_0^h e^{A s} Qc e^{A^T s} ds,

evaluated on sub-steps short enough for a Taylor polynomial to be exact in float64 and
combined by doubling (`discretise`).

Prediction is m <- Ad m + Bd u, P <- Ad P Ad^T + Qd; the update at a frame uses the finite
outputs only (a NaN output is dropped, an all-NaN frame is a pure prediction). With the
Cholesky factor S = L L^T of the innovation covariance S = H P H^T + R, one triangular solve
gives W = L^{-1} H P and w = L^{-1} v, and m <- m + W^T w, P <- P - W^T W (symmetrised).
The log-likelihood is the prediction-error decomposition

    log p(y_1..y_N) = sum_k -1/2 (v_k^T S_k^{-1} v_k + log det S_k + m_k log 2 pi),

v_k the innovations and m_k the number of finite outputs in frame k.

What is exact: for a linear output (`C`, `D`, `d`) the filtered and smoothed moments and the
log-likelihood are the exact Gaussian ones (up to rounding), for any step length and
stiffness. With a nonlinear output function
`h(x, u)` the update is the extended Kalman update (h linearised at the predicted mean by
`jax.jacfwd`), so the likelihood is the usual EKF approximation. The dynamics are always linear.

Everything is a pure function of arrays (`lax.scan` over the grid, all the steps'
discretisations computed as one batch): differentiable, `jit`- and `vmap`-able. The library
never sets float64; enable it in your program.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, Float, Int

from greybox._compile import jax_jit, jit

__all__ = [
    "FilterGrid",
    "FilterResult",
    "LinearGaussianSDE",
    "SmootherResult",
    "discretise",
    "free_run",
    "kalman_filter",
    "log_likelihood",
    "rts_smoother",
    "with_output_random_walks",
]

_LOG_2PI = math.log(2.0 * math.pi)


class LinearGaussianSDE(eqx.Module):
    """Linear stochastic state-space model (continuous dynamics, discrete measurements).

    **Arguments** (SI units throughout; n states, p inputs, q outputs):

    - `A`: drift matrix [1/s], shape (n, n).
    - `B`: input matrix [state unit / (input unit s)], shape (n, p) (p may be 0).
    - `Qc`: diffusion intensity G G^T [state unit^2 / s], shape (n, n), symmetric PSD. A
      random-walk disturbance state has a zero row in `A` and its intensity on the diagonal.
    - `C`: output matrix, shape (q, n). Ignored when `output` is given.
    - `R`: measurement-noise covariance [output unit^2], shape (q, q), positive definite.
    - `x0`, `P0`: mean (n,) and covariance (n, n) of the state at the grid's start time `t0`.
      `P0 = 0` makes `x0` a deterministic (fittable) initial state.
    - `D`: feedthrough, shape (q, p); zeros by default. `u(t_k)` is the level at the frame.
    - `d`: output offset, shape (q,); zeros by default.
    - `output`: optional nonlinear measurement function `h(x, u) -> y` (shapes (n,), (p,) ->
      (q,)); then the filter uses the extended update and `C`, `D`, `d` are not used. It is a
      static part of the model: reuse one function object (or pass an `eqx.Module`, whose
      arrays stay traced) so that calls do not recompile.
    """

    A: Float[Array, "n n"]
    B: Float[Array, "n p"]
    Qc: Float[Array, "n n"]
    C: Float[Array, "q n"]
    R: Float[Array, "q q"]
    x0: Float[Array, " n"]
    P0: Float[Array, "n n"]
    D: Float[Array, "q p"]
    d: Float[Array, " q"]
    output: Callable | None

    def __init__(self, A, B, Qc, C, R, x0, P0, D=None, d=None, output=None):
        self.A = jnp.asarray(A)
        n = self.A.shape[0]
        self.B = jnp.asarray(B).reshape(n, -1)
        self.Qc = jnp.asarray(Qc)
        self.C = jnp.atleast_2d(jnp.asarray(C))
        self.R = jnp.atleast_2d(jnp.asarray(R))
        q = self.R.shape[0]
        self.x0 = jnp.asarray(x0).reshape(n)
        self.P0 = jnp.asarray(P0)
        p = self.B.shape[1]
        self.D = jnp.zeros((q, p), self.A.dtype) if D is None else jnp.asarray(D).reshape(q, p)
        self.d = jnp.zeros(q, self.A.dtype) if d is None else jnp.asarray(d).reshape(q)
        self.output = output

    def __check_init__(self):
        n = self.A.shape[0]
        q = self.R.shape[0]
        shapes = {
            "A": (self.A.shape, (n, n)),
            "Qc": (self.Qc.shape, (n, n)),
            "P0": (self.P0.shape, (n, n)),
            "R": (self.R.shape, (q, q)),
        }
        if self.output is None:
            shapes["C"] = (self.C.shape, (q, n))
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(
                    f"LinearGaussianSDE: {name} has shape {got}, expected {want} "
                    f"(n = {n} states from A, q = {q} outputs from R)"
                )

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    @property
    def n_inputs(self) -> int:
        return self.B.shape[1]

    @property
    def n_outputs(self) -> int:
        return self.R.shape[0]

    def observe(self, x, u):
        """Noise-free output for state `x` (n,) and input level `u` (p,)."""
        if self.output is not None:
            return self.output(x, u)
        return self.C @ x + self.D @ u + self.d


def with_output_random_walks(model: LinearGaussianSDE, intensities, loading=None, x0=None, P0=None):
    """Append random-walk disturbance states that add to the outputs (ambient, drift, offset).

    **Arguments:**

    - `model`: a linear-output `LinearGaussianSDE` with n states and q outputs.
    - `intensities`: diffusion intensity of each new state [output unit^2 / s], shape (m,);
      each state does d = sqrt(intensity) dW (variance intensity * t after time t).
    - `loading`: how the m states enter the outputs, shape (q, m); identity by default
      (m = q: one disturbance per output).
    - `x0`, `P0`: initial mean (m,) and covariance (m, m) of the new states; zeros by default
      (then `x0` is the disturbance at `t0`, e.g. a fitted initial ambient offset).

    **Returns:** the model with n + m states (dynamics, input and output of the first n
    states unchanged; the new states evolve independently of them).
    """
    if model.output is not None:
        raise ValueError("with_output_random_walks: needs a linear output (C), not `output`")
    q_new = jnp.atleast_1d(jnp.asarray(intensities))
    m, n, q = q_new.shape[0], model.n_states, model.n_outputs
    loading = jnp.eye(q, m, dtype=q_new.dtype) if loading is None else jnp.asarray(loading)
    if loading.shape != (q, m):
        raise ValueError(f"loading: shape {loading.shape}, expected ({q}, {m}) (outputs, walks)")
    x0 = jnp.zeros(m, q_new.dtype) if x0 is None else jnp.asarray(x0).reshape(m)
    P0 = jnp.zeros((m, m), q_new.dtype) if P0 is None else jnp.asarray(P0)
    zeros_nm = jnp.zeros((n, m), model.A.dtype)
    return LinearGaussianSDE(
        A=jnp.block([[model.A, zeros_nm], [zeros_nm.T, jnp.zeros((m, m), model.A.dtype)]]),
        B=jnp.concatenate([model.B, jnp.zeros((m, model.n_inputs), model.B.dtype)]),
        Qc=jnp.block([[model.Qc, zeros_nm], [zeros_nm.T, jnp.diag(q_new)]]),
        C=jnp.concatenate([model.C, loading], axis=1),
        R=model.R,
        x0=jnp.concatenate([model.x0, x0]),
        P0=jnp.block([[model.P0, zeros_nm], [zeros_nm.T, P0]]),
        D=model.D,
        d=model.d,
    )


# Taylor polynomial of degree 15 on a matrix with ||M||_1 <= 1/2: the truncation error is
# below (1/2)^16 / 16! e^(1/2) ~ 1e-18, i.e. exact in float64 (Higham 2008, ch. 10)
_TAYLOR_DEGREE = 15
# Van Loan is applied on sub-steps with ||A h||_1 <= 1/4 (the other blocks are scaled to 1/8
# each); 2^24 sub-steps cover ||A h||_1 up to 4e6, beyond which the result is NaN
_THETA_A = 0.25
_MAX_DOUBLINGS = 24


def _norm1(X):
    """Matrix 1-norm (largest column sum) over the last two axes."""
    return jnp.max(jnp.sum(jnp.abs(X), axis=-2), axis=-1)


def _expm_small(M):
    """e^M for a batch (..., m, m) with ||M||_1 <= 1/2: degree-15 Taylor polynomial.

    Paterson-Stockmeyer evaluation: 6 matrix products and no linear solve (no LAPACK call:
    jaxlib 0.10's batched LAPACK solves, as in a Pade approximant, deadlocked the CPU thread
    pool after 2-50 repeated fits, `lapack_dtrsm_ffi` waiting in `ParallelBatchMap`).
    """
    c = [1.0 / math.factorial(k) for k in range(_TAYLOR_DEGREE + 1)]
    eye = jnp.eye(M.shape[-1], dtype=M.dtype)
    powers = [eye, M, M @ M]
    powers.append(powers[2] @ M)
    M4 = powers[2] @ powers[2]
    # p(M) = sum_j (M^4)^j B_j(M), B_j = sum_{i<4} c[4j+i] M^i, by Horner in M^4
    blocks = [sum(c[4 * j + i] * powers[i] for i in range(4)) for j in range(4)]
    E = blocks[3]
    for j in (2, 1, 0):
        E = E @ M4 + blocks[j]
    return E


def _pow2_scale(X, h):
    """Powers of two 2^-k with ||X h||_1 2^-k <= 1/8 (1 where X h = 0), shape of `h`."""
    norm = _norm1(X) * jnp.abs(h)
    k = jnp.where(norm > 0, jnp.ceil(jnp.log2(jnp.where(norm > 0, norm, 1.0))) + 3, 0.0)
    return jax.lax.stop_gradient(2.0**-k)


@jax_jit
def discretise(A, B, Qc, dt_s):
    """Exact ZOH discretisation over steps of length `dt_s` [s] (Van Loan's method).

    **Arguments:** `A` (n, n), `B` (n, p), `Qc` (n, n) as in `LinearGaussianSDE`; `dt_s` a
    scalar or an array of step lengths of any shape (...).

    **Returns:** `(Ad, Bd, Qd)` of shapes (..., n, n), (..., n, p), (..., n, n) with
    `Ad = e^{A h}`, `Bd = int_0^h e^{A s} ds B`, `Qd = int_0^h e^{A s} Qc e^{A^T s} ds`.

    Each step is split into 2^s equal sub-steps with ||A h 2^-s||_1 <= 1/4. Van Loan's
    exponential of the sub-step (size 2n + p, with the `Qc` and `B` blocks rescaled by powers
    of two, an exact similarity transform) gives its (Ad, Bd, Qd), and s doublings
    Qd <- Qd + Ad Qd Ad^T, Bd <- Bd + Ad Bd, Ad <- Ad Ad give the step's. Unlike squaring the
    Van Loan exponential itself, whose e^{-A h} block grows without bound, the doublings only
    add positive semi-definite terms, so stiff or long steps stay accurate. The doubling loop
    (masked per step) runs (`lax.cond`) only if some step needs it, forward and backward.
    Van Loan's matrix is assembled from its blocks by concatenation (not by updates of a
    zero matrix: fewer operations in the gradient).
    """
    A = jnp.asarray(A)
    n = A.shape[0]
    B = jnp.asarray(B).reshape(n, -1)
    p = B.shape[1]
    Qc = jnp.asarray(Qc)
    h = jnp.asarray(dt_s)
    dtype = jnp.result_type(A, B, Qc, h)
    s = jnp.ceil(jnp.log2(jnp.maximum(_norm1(A) * jnp.abs(h), 1e-300) / _THETA_A))
    s = jax.lax.stop_gradient(jnp.maximum(s, 0))
    h_sub = h / 2.0 ** jnp.minimum(s, _MAX_DOUBLINGS)
    alpha = _pow2_scale(Qc, h_sub)[..., None, None]
    beta = _pow2_scale(B, h_sub)[..., None, None]
    lead = jnp.broadcast_shapes(alpha.shape[:-2], beta.shape[:-2])

    def tile(X):  # a block of Van Loan's matrix, broadcast to the steps
        return jnp.broadcast_to(X, (*lead, *X.shape[-2:]))

    zeros = functools.partial(jnp.zeros, dtype=dtype)
    Z = jnp.concatenate(  # [[-A, Qc alpha, 0], [0, A^T, 0], [0, B^T beta, 0]]
        [
            jnp.concatenate([tile(-A), tile(alpha * Qc), tile(zeros((n, p)))], axis=-1),
            jnp.concatenate([tile(zeros((n, n))), tile(A.T), tile(zeros((n, p)))], axis=-1),
            jnp.concatenate([tile(zeros((p, n))), tile(beta * B.T), tile(zeros((p, p)))], axis=-1),
        ],
        axis=-2,
    )
    E = _expm_small(Z * h_sub[..., None, None])
    Ad = jnp.swapaxes(E[..., n : 2 * n, n : 2 * n], -1, -2)
    Bd = jnp.swapaxes(E[..., 2 * n :, n : 2 * n], -1, -2) / beta
    Qd = Ad @ E[..., :n, n : 2 * n] / alpha

    def doublings(carry):
        def double(i, carry):
            Ad, Bd, Qd = carry
            on = (i < s)[..., None, None]
            Qd2 = Qd + Ad @ Qd @ jnp.swapaxes(Ad, -1, -2)
            return (
                jnp.where(on, Ad @ Ad, Ad),
                jnp.where(on, Bd + Ad @ Bd, Bd),
                jnp.where(on, Qd2, Qd),
            )

        return jax.lax.fori_loop(0, _MAX_DOUBLINGS, double, carry)

    # checkpointed: differentiated, a cond keeps the intermediate values of both branches,
    # 24 doublings' worth of (mostly zero) buffers per call, written in every step of the
    # extended Kalman filter's scan (2,400 calls per gradient on TCLab: a quarter of its time);
    # recomputed instead in the backward pass, only where the doublings ran
    Ad, Bd, Qd = jax.lax.cond(jnp.max(s) > 0, jax.checkpoint(doublings), lambda c: c, (Ad, Bd, Qd))
    ok = (s <= _MAX_DOUBLINGS)[..., None, None]
    Qd = 0.5 * (Qd + jnp.swapaxes(Qd, -1, -2))
    return jnp.where(ok, Ad, jnp.nan), jnp.where(ok, Bd, jnp.nan), jnp.where(ok, Qd, jnp.nan)


def discretise_steps(A, B, Qc, grid, dtype):
    """`discretise` over every step of `grid` (a `FilterGrid`): (Ad, Bd, Qd) of shapes
    (L, n, n), (L, n, p), (L, n, n), computed once per distinct step length and gathered
    (the same numbers; a sampled record has a few dozen distinct lengths, not one per step:
    the RC3 test record's 1,827 steps have 61, and the likelihood's gradient took half the
    time)."""
    distinct = discretise(A, B, Qc, jnp.asarray(grid.dt_distinct, dtype))
    if grid.dt_distinct.shape == grid.dt_s.shape:  # every step its own: no gather
        return distinct
    index = jnp.asarray(grid.dt_index)
    return tuple(X[index] for X in distinct)


class FilterGrid(eqx.Module):
    """Data-only stepping plan for one record: frame times and a ZOH input (built once, numpy).

    **Arguments:**

    - `t_s`: frame times [s], shape (N,), strictly increasing, any spacing.
    - `u_times_s`, `u_levels`: input breakpoints [s] (M,) and the level after each, (M,) or
      (M, p); the input is 0 before the first breakpoint. Omit both for a model without inputs.
    - `t0_s`: time [s] at which the state has the prior `N(x0, P0)`; default the first frame.

    The steps end at the union of the switching times and the frame times; `dt_s` (L,), `u`
    (L, p) the level held on each step, `frame` (L,) the frame observed at the end of each step
    (-1: none), `step` (N,) the step that ends at each frame, `u_frame` (N, p) the level at
    each frame (right-continuous). A frame at `t0_s` gets a zero-length first step.
    `dt_distinct` (K,) the distinct step lengths (K rounded up to a power of two by
    repeating the last, so records of similar sampling share one shape; K = L, the steps
    themselves, where that is more than a quarter of them) and `dt_index` (L,) each step's
    among them: a linear device's fit discretises once per distinct length
    (`discretise_steps`), a few dozen for a sampled record instead of every step.
    """

    t0_s: Float[Array, ""]
    t_s: Float[Array, " N"]
    dt_s: Float[Array, " L"]
    dt_distinct: Float[Array, " K"]
    dt_index: Int[Array, " L"]
    u: Float[Array, "L p"]
    frame: Int[Array, " L"]
    step: Int[Array, " N"]
    u_frame: Float[Array, "N p"]

    def __init__(self, t_s, u_times_s=None, u_levels=None, *, t0_s=None):
        t = np.asarray(t_s, dtype=float).reshape(-1)
        if t.size == 0 or not np.all(np.isfinite(t)):
            raise ValueError("t_s: give at least one finite frame time [s] (no NaN)")
        if np.any(np.diff(t) <= 0):
            bad = int(np.argmax(np.diff(t) <= 0))
            raise ValueError(
                f"t_s: frame times must be strictly increasing (frame {bad + 1} at {t[bad + 1]} s "
                f"follows {t[bad]} s); sort them and drop duplicates"
            )
        if (u_times_s is None) != (u_levels is None):
            raise ValueError("u_times_s, u_levels: give both (a ZOH input) or neither (no input)")
        if u_times_s is None:
            bt = np.zeros(0)
            lv = np.zeros((0, 0))
        else:
            bt = np.asarray(u_times_s, dtype=float).reshape(-1)
            lv = np.asarray(u_levels, dtype=float).reshape(bt.size, -1)
            if not (np.all(np.isfinite(bt)) and np.all(np.isfinite(lv))):
                raise ValueError("u_times_s, u_levels: contain NaN or infinite values")
            if np.any(np.diff(bt) <= 0):
                raise ValueError("u_times_s: breakpoints must be strictly increasing")
        t0 = float(t[0]) if t0_s is None else float(t0_s)
        if t0 > t[0]:
            raise ValueError(f"t0_s: {t0} s is after the first frame {t[0]} s; start earlier")
        switches = bt[(bt > t0) & (bt < t[-1])]
        ends = np.unique(np.concatenate([switches, t]))
        starts = np.concatenate([[t0], ends[:-1]])
        self.t0_s = np.asarray(t0)
        self.t_s = t
        self.dt_s = ends - starts
        self.dt_distinct, self.dt_index = _distinct_steps(self.dt_s)
        self.u = _level(bt, lv, starts)
        pos = np.searchsorted(t, ends)
        is_frame = (pos < t.size) & (t[np.minimum(pos, t.size - 1)] == ends)
        self.frame = np.where(is_frame, pos, -1).astype(np.int32)
        self.step = np.searchsorted(ends, t).astype(np.int32)
        self.u_frame = _level(bt, lv, t)

    @property
    def n_frames(self) -> int:
        return self.t_s.shape[0]

    @property
    def n_steps(self) -> int:
        return self.dt_s.shape[0]

    def padded(self, n_frames: int, n_steps: int) -> FilterGrid:
        """This grid with inert frames and steps appended up to `n_frames` and `n_steps`, so
        that records of similar lengths share one compiled filter: a padded step lasts 0 s
        (its discretisation is exactly the identity) and reads no frame (it adds nothing to
        the log-likelihood), a padded frame repeats the last frame's time and maps to the last
        step; read it with NaN readings and drop its rows from what the filter returns."""
        n, L = self.n_frames, self.n_steps
        if n_frames < n or n_steps < L:
            raise ValueError(f"padded: ({n_frames}, {n_steps}) from ({n}, {L}) frames and steps")

        def more(x, rows):  # x with its last row repeated up to `rows` rows
            x = np.asarray(x)
            return np.concatenate([x, np.repeat(x[-1:], rows - x.shape[0], axis=0)])

        dt = np.concatenate([np.asarray(self.dt_s), np.zeros(n_steps - L)])
        distinct, index = _distinct_steps(dt)
        step = np.concatenate([np.asarray(self.step), np.full(n_frames - n, n_steps - 1)])
        frame = np.concatenate([np.asarray(self.frame), np.full(n_steps - L, -1)])
        return eqx.tree_at(
            lambda g: (g.t_s, g.dt_s, g.dt_distinct, g.dt_index, g.u, g.frame, g.step, g.u_frame),
            self,
            (
                more(self.t_s, n_frames),
                dt,
                distinct,
                index,
                more(self.u, n_steps),
                frame.astype(np.int32),
                step.astype(np.int32),
                more(self.u_frame, n_frames),
            ),
        )


def _distinct_steps(dt_s) -> tuple[np.ndarray, np.ndarray]:
    """(`dt_distinct`, `dt_index`) of a grid's step lengths (see `FilterGrid`)."""
    distinct, index = np.unique(dt_s, return_inverse=True)
    k = 1 << max(distinct.size - 1, 0).bit_length()
    if 4 * k <= dt_s.size:  # worth a gather
        distinct = np.concatenate([distinct, np.full(k - distinct.size, distinct[-1])])
        return distinct, index.reshape(-1).astype(np.int32)
    return dt_s, np.arange(dt_s.size, dtype=np.int32)  # every step its own (a jittered record)


def _level(times, levels, t):
    """Right-continuous ZOH lookup (0 before the first breakpoint), shape (len(t), p)."""
    if times.size == 0:
        return np.zeros((t.size, levels.shape[1]))
    idx = np.searchsorted(times, t, side="right") - 1
    return np.where((idx >= 0)[:, None], levels[np.maximum(idx, 0)], 0.0)


class FilterResult(eqx.Module):
    """Kalman filter output at the N frames (q outputs, n states).

    - `log_likelihood`: log p(y) of the finite measurements, a scalar.
    - `predicted_mean` (N, n), `predicted_cov` (N, n, n): x(t_k) given frames before k.
    - `filtered_mean` (N, n), `filtered_cov` (N, n, n): x(t_k) given frames up to k.
    - `y_pred` (N, q), `y_pred_cov` (N, q, q): one-step-ahead prediction of y_k (its
      covariance includes R; it is the innovation covariance S_k of the observed entries).
    - `innovation` (N, q): y_k - y_pred, NaN where y_k is NaN.
    - `standardised_innovation` (N, q): innovation / sqrt(diag S_k), NaN where y_k is NaN;
      i.i.d. N(0, 1) in time for each output when the model is right.
    """

    log_likelihood: Float[Array, ""]
    predicted_mean: Float[Array, "N n"]
    predicted_cov: Float[Array, "N n n"]
    filtered_mean: Float[Array, "N n"]
    filtered_cov: Float[Array, "N n n"]
    y_pred: Float[Array, "N q"]
    y_pred_cov: Float[Array, "N q q"]
    innovation: Float[Array, "N q"]
    standardised_innovation: Float[Array, "N q"]


class SmootherResult(eqx.Module):
    """RTS smoother output at the N frames: state given every frame of the record.

    - `mean` (N, n), `cov` (N, n, n): smoothed state moments.
    - `y_mean` (N, q): noise-free output at the smoothed mean (C m + D u + d, or h(m, u)).
    - `log_likelihood`: the filter's log p(y).
    """

    mean: Float[Array, "N n"]
    cov: Float[Array, "N n n"]
    y_mean: Float[Array, "N q"]
    log_likelihood: Float[Array, ""]


def _as_rows(model: LinearGaussianSDE, grid: FilterGrid, y) -> Array:
    y = jnp.asarray(y)
    q = model.n_outputs
    if y.ndim == 1 and q == 1:
        y = y[:, None]
    if y.shape != (grid.n_frames, q):
        raise ValueError(
            f"y: shape {y.shape}, expected ({grid.n_frames}, {q}) (frames, outputs); "
            "mark dropped frames with NaN instead of removing them"
        )
    if grid.u.shape[1] != model.n_inputs:
        raise ValueError(
            f"grid: has {grid.u.shape[1]} input channel(s) but B has {model.n_inputs} columns"
        )
    return y


_UNROLL_MAX = 4  # outputs up to which the Cholesky factorisation is written out


def _cholesky_solve(S, rhs):
    """S = L L^T; returns (log diag L, L^{-1} rhs).

    For a few outputs the factorisation and the forward substitution are written out element
    by element: XLA fuses them, which inside the filter's `lax.scan` (one tiny S per step) is
    several times cheaper, forward and backward, than calling LAPACK once per step.
    """
    q = S.shape[0]
    if q > _UNROLL_MAX:
        L = jnp.linalg.cholesky(S)
        return jnp.log(jnp.diag(L)), jsl.solve_triangular(L, rhs, lower=True)
    L = [[None] * q for _ in range(q)]
    for j in range(q):
        L[j][j] = jnp.sqrt(S[j, j] - sum(L[j][k] ** 2 for k in range(j)))
        for i in range(j + 1, q):
            L[i][j] = (S[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    rows = []
    for i in range(q):
        rows.append((rhs[i] - sum(L[i][k] * rows[k] for k in range(i))) / L[i][i])
    return jnp.log(jnp.stack([L[j][j] for j in range(q)])), jnp.stack(rows)


def measurement_update(m_p, P_p, y_i, y_hat, H, R):
    """Kalman update at one frame, NaN readings skipped: (mean, covariance, log-likelihood
    term) after reading `y_i` predicted as `y_hat` with output Jacobian `H` and noise `R`."""
    n = m_p.shape[0]
    mask = jnp.isfinite(y_i)
    v = jnp.where(mask, jnp.where(mask, y_i, 0.0) - y_hat, 0.0)
    Hm = jnp.where(mask[:, None], H, 0.0)
    both = mask[:, None] & mask[None, :]
    Rm = jnp.where(both, R, 0.0) + jnp.diag(jnp.where(mask, 0.0, 1.0))
    S = Hm @ P_p @ Hm.T + Rm
    # one triangular solve gives W = L^{-1} H P and w = L^{-1} v: K v = W^T w, K S K^T = W^T W
    log_diag_L, Ww = _cholesky_solve(S, jnp.concatenate([Hm @ P_p, v[:, None]], axis=1))
    W, w = Ww[:, :n], Ww[:, n]
    m_f = m_p + W.T @ w
    P_f = P_p - W.T @ W
    P_f = 0.5 * (P_f + P_f.T)
    n_obs = jnp.sum(mask.astype(S.dtype))
    ll_i = -0.5 * (w @ w) - jnp.sum(log_diag_L) - 0.5 * _LOG_2PI * n_obs
    return m_f, P_f, ll_i


def _run(model: LinearGaussianSDE, grid: FilterGrid, y, keep_path: bool):
    """Forward pass over the L grid steps: (log L, path, Ad, y), the path a tuple of the
    per-step log-likelihood terms (L,) and, with `keep_path`, the per-step m_p, P_p, m_f,
    P_f, y_hat, S after them."""
    y = _as_rows(model, grid, y)
    dtype = jnp.result_type(model.A, y)
    Ad, Bd, Qd = discretise_steps(model.A, model.B, model.Qc, grid, dtype)
    is_frame = grid.frame >= 0
    idx = jnp.maximum(grid.frame, 0)
    y_step = jnp.where(is_frame[:, None], y[idx], jnp.nan)
    u_obs = jnp.asarray(grid.u_frame, dtype)[idx]

    def step(carry, inputs):
        m, P, ll = carry
        Ad_i, Bd_i, Qd_i, u_i, y_i, uo_i = inputs
        m_p = Ad_i @ m + Bd_i @ u_i
        P_p = Ad_i @ P @ Ad_i.T + Qd_i
        P_p = 0.5 * (P_p + P_p.T)
        y_hat = model.observe(m_p, uo_i)
        H = jax.jacfwd(model.observe)(m_p, uo_i) if model.output is not None else model.C
        m_f, P_f, ll_i = measurement_update(m_p, P_p, y_i, y_hat, H, model.R)
        out = (ll_i,)  # each step's log-likelihood term, then (with the path) its moments
        if keep_path:
            out += (m_p, P_p, m_f, P_f, y_hat, H @ P_p @ H.T + model.R)
        return (m_f, P_f, ll + ll_i), out

    init = (jnp.asarray(model.x0, dtype), jnp.asarray(model.P0, dtype), jnp.zeros((), dtype))
    u_steps = jnp.asarray(grid.u, dtype)
    (_, _, ll), path = jax.lax.scan(step, init, (Ad, Bd, Qd, u_steps, y_step, u_obs))
    return ll, path, Ad, y


def scored_log_likelihood(ll, terms, grid: FilterGrid, score_first: bool):
    """log L of a record as fitted: the filter's `ll` and per-step `terms`; without
    `score_first` the first frame is conditioned on, not scored: log p(y_2..y_N | y_1)."""
    return ll if score_first else ll - terms[grid.step[0]]


@jit
def log_likelihood(model: LinearGaussianSDE, grid: FilterGrid, y) -> Float[Array, ""]:
    """Exact Gaussian log-likelihood log p(y) of one record (extended for a nonlinear output).

    **Arguments:**

    - `model`: a `LinearGaussianSDE`.
    - `grid`: the record's `FilterGrid` (frame times and ZOH input).
    - `y`: measurements, shape (N, q) (or (N,) for one output); NaN marks a missing value.

    **Returns:** a scalar; differentiable in every array of `model`.
    """
    return _run(model, grid, y, keep_path=False)[0]


@jit
def kalman_filter(model: LinearGaussianSDE, grid: FilterGrid, y) -> FilterResult:
    """Continuous-discrete Kalman filter at the frame times; see `FilterResult`.

    Arguments as for `log_likelihood`.
    """
    ll, (_, m_p, P_p, m_f, P_f, y_hat, S), _, y = _run(model, grid, y, keep_path=True)
    k = grid.step
    v = y - y_hat[k]
    sd = jnp.sqrt(jnp.diagonal(S[k], axis1=1, axis2=2))
    return FilterResult(
        log_likelihood=ll,
        predicted_mean=m_p[k],
        predicted_cov=P_p[k],
        filtered_mean=m_f[k],
        filtered_cov=P_f[k],
        y_pred=y_hat[k],
        y_pred_cov=S[k],
        innovation=v,
        standardised_innovation=v / sd,
    )


@jit
def rts_smoother(model: LinearGaussianSDE, grid: FilterGrid, y) -> SmootherResult:
    """Rauch-Tung-Striebel smoother: state moments at each frame given the whole record.

    Runs the filter over the grid, then the backward pass
    G = P_f Ad^T P_p^+, m_s = m_f + G (m_s' - m_p'), P_s = P_f + G (P_s' - P_p') G^T
    (pseudo-inverse: states without process noise give a singular P_p). Arguments as for
    `log_likelihood`.
    """
    ll, (_, m_p, P_p, m_f, P_f, _, _), Ad, _ = _run(model, grid, y, keep_path=True)

    def back(carry, inputs):
        m_s, P_s = carry
        m_f_i, P_f_i, m_p_next, P_p_next, Ad_next = inputs
        G = P_f_i @ Ad_next.T @ jnp.linalg.pinv(P_p_next, hermitian=True)
        m = m_f_i + G @ (m_s - m_p_next)
        P = P_f_i + G @ (P_s - P_p_next) @ G.T
        P = 0.5 * (P + P.T)
        return (m, P), (m, P)

    _, (m_s, P_s) = jax.lax.scan(
        back,
        (m_f[-1], P_f[-1]),
        (m_f[:-1], P_f[:-1], m_p[1:], P_p[1:], Ad[1:]),
        reverse=True,
    )
    m_s = jnp.concatenate([m_s, m_f[-1:]])
    P_s = jnp.concatenate([P_s, P_f[-1:]])
    k = grid.step
    u_frame = jnp.asarray(grid.u_frame, m_s.dtype)
    y_mean = jax.vmap(model.observe)(m_s[k], u_frame)
    return SmootherResult(mean=m_s[k], cov=P_s[k], y_mean=y_mean, log_likelihood=ll)


def free_run(model: LinearGaussianSDE, grid: FilterGrid) -> tuple[Array, Array]:
    """Free-run (simulation) prediction: output mean (N, q) and covariance (N, q, q) at the frames.

    The filter with every measurement missing: the state mean follows the deterministic
    dynamics from `x0` and the covariance grows with the process noise (plus `R`).
    """
    y = jnp.full((grid.n_frames, model.n_outputs), jnp.nan, jnp.result_type(model.A))
    res = kalman_filter(model, grid, y)
    return res.y_pred, res.y_pred_cov
