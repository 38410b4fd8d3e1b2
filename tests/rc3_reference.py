"""Independent reference for process-noise fits: a three-state stochastic RC building model
simulated, filtered and fitted with numpy/scipy only (no greybox import).

The model (CTSM-R's TiTeTh structure; temperatures in K, powers in W, time in s):

    Ci dTi = ((Te - Ti)/Rie + (Th - Ti)/Rih + Aw Ps) dt + Ci dW_i     (indoor air)
    Ce dTe = ((Ti - Te)/Rie + (Ta - Te)/Rea) dt      + Ce dW_e        (envelope)
    Ch dTh = ((Ti - Th)/Rih + Ph) dt                 + Ch dW_h        (heater)
    y = (Ti, Te) + e,   e ~ N(0, diag(sd_Ti^2, sd_Te^2))

with process-noise intensities q_i, q_e, q_h [K^2/s] (E[dW dW^T] = diag(q) dt in K^2 after
the division by C), three inputs u = (Ta [K], Ph [W], Ps [W/m^2]) held constant between
breakpoints (zero-order hold), irregular frame times and dropped readings (NaN).

`simulate` draws the states by the exact discretisation of the SDE on every interval between
frames and input switches (Van Loan's block matrix through `scipy.linalg.expm`), so the data
are exact samples of the continuous-time model. `loglik` is a plain numpy Kalman filter on the
same exact discretisation (the prediction-error decomposition), with the initial state known
(mean `x0`, zero covariance) and the first frame of the record conditioned on, not scored (the
convention `greybox.InitialState()` documents). `reference_max` maximises it with scipy
(trust-region Newton in log parameters, finite-difference gradient and Hessian, from several
starts): the reference maximum log-likelihood and its estimate.

Parameter order (`NAMES`): Ci, Ce, Ch [J/K], Rie, Rea, Rih [K/W], Aw [m^2], q_i, q_e, q_h
[K^2/s], sd_Ti, sd_Te [K].
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.optimize as so
from threadpoolctl import threadpool_limits

NAMES = ("Ci", "Ce", "Ch", "Rie", "Rea", "Rih", "Aw", "q_i", "q_e", "q_h", "sd_Ti", "sd_Te")
TRUTH = {
    "Ci": 1.5e6,
    "Ce": 1.2e7,
    "Ch": 4.0e5,
    "Rie": 4.0e-3,
    "Rea": 8.0e-3,
    "Rih": 2.0e-3,
    "Aw": 3.0,
    "q_i": 4.0e-6,
    "q_e": 5.0e-7,
    "q_h": 2.0e-5,
    "sd_Ti": 0.05,
    "sd_Te": 0.08,
}
X0 = np.array([293.0, 288.0, 295.0])  # Ti, Te, Th at t = 0 [K]
N_FRAMES = 1500


def matrices(p: dict) -> tuple:
    """(A (3, 3), B (3, 3), Qc (3, 3), C (2, 3), R (2, 2)) of parameters `p` (keys `NAMES`)."""
    ci, ce, ch = p["Ci"], p["Ce"], p["Ch"]
    rie, rea, rih = p["Rie"], p["Rea"], p["Rih"]
    A = np.array(
        [
            [-1 / (rie * ci) - 1 / (rih * ci), 1 / (rie * ci), 1 / (rih * ci)],
            [1 / (rie * ce), -1 / (rie * ce) - 1 / (rea * ce), 0.0],
            [1 / (rih * ch), 0.0, -1 / (rih * ch)],
        ]
    )
    B = np.array(
        [
            [0.0, 0.0, p["Aw"] / ci],
            [1 / (rea * ce), 0.0, 0.0],
            [0.0, 1 / ch, 0.0],
        ]
    )
    Qc = np.diag([p["q_i"], p["q_e"], p["q_h"]])
    C = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    R = np.diag([p["sd_Ti"] ** 2, p["sd_Te"] ** 2])
    return A, B, Qc, C, R


def van_loan(A, B, Qc, h):
    """Exact discretisation over `h` s: (Ad, Bd, Qd) with Qd = int_0^h e^{As} Qc e^{A's} ds."""
    n, p = B.shape
    m = np.zeros((2 * n + p, 2 * n + p))
    m[:n, :n], m[:n, n : 2 * n], m[n : 2 * n, n : 2 * n] = -A, Qc, A.T
    m[n : 2 * n, 2 * n :] = 0.0
    e = sla.expm(m * h)
    Ad = e[n : 2 * n, n : 2 * n].T
    Qd = Ad @ e[:n, n : 2 * n]
    # Bd from the augmented [[A, B], [0, 0]] exponential
    aug = np.zeros((n + p, n + p))
    aug[:n, :n], aug[:n, n:] = A, B
    Bd = sla.expm(aug * h)[:n, n:]
    return Ad, Bd, 0.5 * (Qd + Qd.T)


def inputs(seed: int = 0, t_end: float = 6.0e5):
    """(breakpoints (M,) [s], levels (M, 3)): ambient Ta [K] (daily cycle + slow weather),
    heater Ph [W] (a PRBS of 0 / 1500 W, 2-8 h holds), solar Ps [W/m^2] (clear days)."""
    rng = np.random.default_rng(1000 + seed)
    times = np.arange(0.0, t_end, 1800.0)  # inputs logged every 30 min
    day = 86400.0
    ta = 278.0 + 4.0 * np.sin(2 * np.pi * (times - 0.3 * day) / day) + 2.0 * np.sin(
        2 * np.pi * times / (3.7 * day)
    )
    ps = np.clip(450.0 * np.sin(2 * np.pi * (times - 0.25 * day) / day), 0.0, None)
    ph = np.zeros_like(times)
    t, on = 0.0, True
    while t < t_end:
        hold = rng.uniform(2, 8) * 3600.0
        ph[(times >= t) & (times < t + hold)] = 1500.0 if on else 0.0
        t, on = t + hold, not on
    return times, np.column_stack([ta, ph, ps])


def frame_times(seed: int = 0, n: int = N_FRAMES) -> np.ndarray:
    """Irregular frame times: 200-600 s apart in whole tens of seconds (mean ~6.7 min),
    starting at 0 (a logger's clock ticks in 10 s; the few distinct intervals let the numpy
    filter discretise each interval length once)."""
    rng = np.random.default_rng(2000 + seed)
    return np.concatenate([[0.0], np.cumsum(10.0 * rng.integers(20, 61, n - 1))])


def _steps(t_frames, u_times, u_levels):
    """(step lengths, input level held on each step, frame index at each step's end or -1)."""
    ends = np.unique(np.concatenate([t_frames, u_times[(u_times > 0) & (u_times < t_frames[-1])]]))
    ends = ends[ends > 0]
    starts = np.concatenate([[0.0], ends[:-1]])
    idx = np.searchsorted(u_times, starts, side="right") - 1
    levels = u_levels[np.maximum(idx, 0)]
    pos = np.searchsorted(t_frames, ends)
    is_frame = (pos < t_frames.size) & (t_frames[np.minimum(pos, t_frames.size - 1)] == ends)
    return ends - starts, levels, np.where(is_frame, pos, -1)


def simulate(seed: int = 0, n: int = N_FRAMES, truth: dict | None = None, x0=X0) -> dict:
    """One record of the stochastic model: {"t_s" (n,), "u_times_s" (M,), "u_levels" (M, 3),
    "y" (n, 2) with NaN drops, "x" (n, 3) the true states, "truth", "x0"}.

    Dropped readings: 2 % of single readings and 1 % of whole frames (NaN)."""
    p = dict(TRUTH if truth is None else truth)
    rng = np.random.default_rng(seed)
    t = frame_times(seed, n)
    u_times, u_levels = inputs(seed, t_end=t[-1] + 1.0)
    A, B, Qc, C, R = matrices(p)
    dts, levels, frame = _steps(t, u_times, u_levels)
    x = np.asarray(x0, dtype=float).copy()
    xs = np.zeros((n, 3))
    xs[0] = x
    for h, u, f in zip(dts, levels, frame):
        Ad, Bd, Qd = van_loan(A, B, Qc, h)
        x = Ad @ x + Bd @ u + np.linalg.cholesky(Qd + 1e-30 * np.eye(3)) @ rng.normal(size=3)
        if f >= 0:
            xs[f] = x
    y = xs @ C.T + rng.normal(size=(n, 2)) * np.sqrt(np.diag(R))
    drop_one = rng.random((n, 2)) < 0.02
    drop_all = rng.random(n) < 0.01
    drop_one[0] = drop_all[0] = False  # the first frame is read (the initial state)
    y[drop_one] = np.nan
    y[drop_all] = np.nan
    return {
        "t_s": t,
        "u_times_s": u_times,
        "u_levels": u_levels,
        "y": y,
        "x": xs,
        "truth": p,
        "x0": np.asarray(x0, dtype=float),
    }


def loglik(p: dict, data: dict, x0=None) -> float:
    """log p(y_2..y_N | y_1) of `data` under parameters `p` (numpy Kalman filter, exact
    discretisation, known initial state `x0` (default the record's), NaN readings skipped, the
    first frame conditioned on)."""
    A, B, Qc, C, R = matrices(p)
    t = data["t_s"]
    dts, levels, frame = _steps(t, data["u_times_s"], data["u_levels"])
    lengths, which = np.unique(np.round(dts, 9), return_inverse=True)
    disc = [van_loan(A, B, Qc, h) for h in lengths]
    m = np.asarray(data["x0"] if x0 is None else x0, dtype=float).copy()
    P = np.zeros((3, 3))
    ll = 0.0
    r_diag = np.diag(R)
    y_all = data["y"]
    log2pi = np.log(2 * np.pi)
    for k, u, f in zip(which, levels, frame):
        Ad, Bd, Qd = disc[k]
        m = Ad @ m + Bd @ u
        P = Ad @ P @ Ad.T + Qd
        if f < 0:
            continue
        for j in range(2):  # sequential scalar updates (R is diagonal): exact
            yj = y_all[f, j]
            if yj != yj:  # NaN: dropped reading
                continue
            ph = P[:, j]  # P C_j^T (C_j picks state j)
            s_j = ph[j] + r_diag[j]
            v = yj - m[j]
            gain = ph / s_j
            m = m + gain * v
            P = P - np.outer(gain, ph)
            ll -= 0.5 * (v * v / s_j + np.log(s_j) + log2pi)
        P = 0.5 * (P + P.T)
    return float(ll)


def loglik_many(thetas, data: dict) -> np.ndarray:
    """`loglik` of K parameter vectors at once, `thetas` (K, 12) in the order `NAMES` (the
    same filter, vectorised over K: a finite-difference gradient costs about one filter
    pass)."""
    thetas = np.atleast_2d(np.asarray(thetas, dtype=float))
    mats = [matrices(dict(zip(NAMES, th))) for th in thetas]
    A = np.stack([m[0] for m in mats])
    B = np.stack([m[1] for m in mats])
    Qc = np.stack([m[2] for m in mats])
    r = np.stack([np.diag(m[4]) for m in mats])  # (K, 2)
    dts, levels, frame = _steps(data["t_s"], data["u_times_s"], data["u_levels"])
    lengths, which = np.unique(np.round(dts, 9), return_inverse=True)
    K, n, p = A.shape[0], 3, 3
    # Van Loan for every (parameter set, interval length) in one batched expm
    M = np.zeros((K, lengths.size, 2 * n, 2 * n))
    M[:, :, :n, :n] = -A[:, None]
    M[:, :, :n, n:] = Qc[:, None]
    M[:, :, n:, n:] = np.swapaxes(A, 1, 2)[:, None]
    E = sla.expm(M * lengths[None, :, None, None])
    Ad = np.swapaxes(E[:, :, n:, n:], 2, 3)
    Qd = Ad @ E[:, :, :n, n:]
    Qd = 0.5 * (Qd + np.swapaxes(Qd, 2, 3))
    G = np.zeros((K, lengths.size, n + p, n + p))
    G[:, :, :n, :n] = A[:, None]
    G[:, :, :n, n:] = B[:, None]
    Bd = sla.expm(G * lengths[None, :, None, None])[:, :, :n, n:]
    m = np.tile(np.asarray(data["x0"], dtype=float), (K, 1))
    P = np.zeros((K, n, n))
    ll = np.zeros(K)
    y_all = data["y"]
    log2pi = np.log(2 * np.pi)
    for k, u, f in zip(which, levels, frame):
        Ad_k = Ad[:, k]
        m = np.einsum("kij,kj->ki", Ad_k, m) + Bd[:, k] @ u
        P = Ad_k @ P @ np.swapaxes(Ad_k, 1, 2) + Qd[:, k]
        if f < 0:
            continue
        for j in range(2):
            yj = y_all[f, j]
            if yj != yj:
                continue
            ph = P[:, :, j].copy()
            s_j = ph[:, j] + r[:, j]
            v = yj - m[:, j]
            gain = ph / s_j[:, None]
            m = m + gain * v[:, None]
            P = P - gain[:, :, None] * ph[:, None, :]
            ll -= 0.5 * (v * v / s_j + np.log(s_j) + log2pi)
        P = 0.5 * (P + np.swapaxes(P, 1, 2))
    return ll


def _vec(p: dict) -> np.ndarray:
    return np.log([p[k] for k in NAMES])


def _dict(v) -> dict:
    return dict(zip(NAMES, np.exp(np.asarray(v, dtype=float))))


def _stencil(v, h):
    """The points of a finite-difference gradient and Hessian at `v`: v, v +- h e_i, and
    v + h e_i + h e_j (i < j), as rows (1 + 2n + n(n-1)/2)."""
    n = v.size
    eye = h * np.eye(n)
    i, j = np.triu_indices(n, 1)
    return np.vstack([v, v + eye, v - eye, v + eye[i] + eye[j]])


def _derivatives(f, n, h):
    """(gradient, Hessian) from `f` at the `_stencil` points: central differences for the
    gradient and the Hessian's diagonal, forward differences for its off-diagonal."""
    f0, fp, fm, fij = f[0], f[1 : n + 1], f[n + 1 : 2 * n + 1], f[2 * n + 1 :]
    g = (fp - fm) / (2 * h)
    H = np.diag((fp - 2 * f0 + fm) / h**2)
    i, j = np.triu_indices(n, 1)
    H[i, j] = H[j, i] = (fij - fp[i] - fp[j] + f0) / h**2
    return g, H


def reference_max(data: dict, n_starts: int = 3, seed: int = 0, extra_starts=()) -> tuple:
    """(max log-likelihood, estimate dict): scipy's trust-region Newton (`trust-exact`) on the
    log parameters from the truth, from `n_starts` - 1 starts a factor up to ~2 away from it
    and from each dict in `extra_starts`; the gradient and Hessian by finite differences of
    `loglik_many` (one batched filter pass per Newton step; no greybox); the best value
    found. (Newton converges in tens of steps where L-BFGS-B took ~170 gradient passes.)"""
    rng = np.random.default_rng(seed)
    truth = _vec(data["truth"])
    starts = [truth] + [truth + rng.uniform(-0.7, 0.7, truth.size) for _ in range(n_starts - 1)]
    starts += [_vec(s) for s in extra_starts]

    h = 1e-4  # difference step in log parameters
    bad = 1e12  # the negative log-likelihood where the filter fails (a rejected step)
    memo = {}

    def nll(points):
        with np.errstate(all="ignore"):
            try:
                vals = -loglik_many(np.exp(points), data)
            except (np.linalg.LinAlgError, ValueError):
                return np.full(len(points), np.nan)
        return vals

    def value(v):
        vals = nll(v[None])
        return float(vals[0]) if np.isfinite(vals[0]) else bad

    def derivatives(v):
        key = v.tobytes()
        if key not in memo:
            vals = nll(_stencil(v, h))
            memo.clear()  # trust-exact asks for both at one point, then moves on
            if np.all(np.isfinite(vals)):
                memo[key] = _derivatives(vals, v.size, h)
            else:
                memo[key] = np.zeros_like(v), np.eye(v.size)
        return memo[key]

    best = None
    for s in starts:
        with threadpool_limits(1):  # tiny batched matrices: BLAS threads only contend
            r = so.minimize(
                value,
                s,
                jac=lambda v: derivatives(v)[0],
                hess=lambda v: derivatives(v)[1],
                method="trust-exact",
                options={"gtol": 1e-5, "maxiter": 200},
            )
        if best is None or r.fun < best.fun:
            best = r
    return -float(best.fun), _dict(best.x)
