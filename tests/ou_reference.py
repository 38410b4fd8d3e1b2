"""Independent reference for small process-noise problems: the one-node RC building
(tests/rc_building_device.py, `nodes=1`, the air read) as a scalar Ornstein-Uhlenbeck process
with a known input, simulated and filtered with numpy only (no greybox import).

    dTi = ((Ta - Ti)/(Rea Ci) + Ph/Ci) dt + dW,   E[dW^2] = q dt,   y = Ti + e, e ~ N(0, sd^2)

Regular frames every `DT` s, Ta constant, Ph a known square wave. The exact discretisation is
closed form: a = exp(-h/tau), tau = Rea Ci; x' = a x + (1 - a)(Ta + Rea Ph) + w,
Var w = q tau (1 - a^2) / 2. The Kalman filter has a known initial state (variance 0) and
conditions on the first frame (not scored), the convention of `greybox.InitialState()`.

`information` is the expected Fisher information of that likelihood from the closed-form
Gaussian moments of the readings (mean response, Cov(x_j, x_k) = a^|k-j| P_min(j,k)), not
from a filter.
"""

from __future__ import annotations

import numpy as np

TRUTH = {"Ci": 2.0e6, "Rea": 5.0e-3, "q": 2.0e-6, "sd": 0.05}
TA, T0, DT, PH = 280.0, 290.0, 300.0, 1500.0
PERIOD = 6 * 3600.0  # heater square wave period [s]


def heater(t):
    """Ph [W] at times `t`: PH for the first half of each period, else 0."""
    return np.where((np.asarray(t) % PERIOD) < PERIOD / 2, PH, 0.0)


def frames(n: int) -> np.ndarray:
    return DT * np.arange(n)


def _disc(p):
    tau = p["Rea"] * p["Ci"]
    a = np.exp(-DT / tau)
    return tau, a, p["q"] * tau * (1 - a * a) / 2


def simulate(p: dict, n: int, seed: int) -> np.ndarray:
    """(n,) noisy readings of one record (the heater switches only at frames)."""
    rng = np.random.default_rng(seed)
    t = frames(n)
    tau, a, qd = _disc(p)
    x = np.empty(n)
    x[0] = T0
    for k in range(1, n):
        drive = TA + p["Rea"] * heater(t[k - 1])
        x[k] = a * x[k - 1] + (1 - a) * drive + np.sqrt(qd) * rng.normal()
    return x + p["sd"] * rng.normal(size=n)


def innovations(p: dict, y: np.ndarray) -> tuple:
    """(innovations v (n-1,), their variances S (n-1,)) of the scalar Kalman filter."""
    t = frames(y.size)
    tau, a, qd = _disc(p)
    m, P = T0, 0.0
    vs, ss = [], []
    for k in range(1, y.size):
        m = a * m + (1 - a) * (TA + p["Rea"] * heater(t[k - 1]))
        P = a * a * P + qd
        s = P + p["sd"] ** 2
        v = y[k] - m
        vs.append(v)
        ss.append(s)
        g = P / s
        m, P = m + g * v, (1 - g) * P
    return np.array(vs), np.array(ss)


def loglik(p: dict, y: np.ndarray) -> float:
    v, s = innovations(p, y)
    return float(-0.5 * np.sum(v * v / s + np.log(2 * np.pi * s)))


def mean_response(p: dict, n: int) -> np.ndarray:
    """The noise-free response at the frames (the expected readings)."""
    t = frames(n)
    tau, a, _ = _disc(p)
    x = np.empty(n)
    x[0] = T0
    for k in range(1, n):
        x[k] = a * x[k - 1] + (1 - a) * (TA + p["Rea"] * heater(t[k - 1]))
    return x


def moments(p: dict, n: int) -> tuple:
    """(mean (n-1,), covariance (n-1, n-1)) of the scored readings y_2..y_n (the first is
    conditioned on; with a known initial state it is independent of the rest): closed form,
    Cov(x_j, x_k) = a^|k-j| P_min(j,k), P_k = qd (1 - a^(2k)) / (1 - a^2)."""
    _, a, qd = _disc(p)
    k = np.arange(1, n)
    P = qd * (1 - a ** (2 * k)) / (1 - a * a)
    lag = np.abs(k[:, None] - k[None, :])
    cov = a**lag * P[np.minimum.outer(k, k) - 1] + p["sd"] ** 2 * np.eye(n - 1)
    return mean_response(p, n)[1:], cov


def information(p: dict, n: int, names=("Ci", "Rea", "q", "sd"), rel=1e-6) -> np.ndarray:
    """Expected Fisher information of (log p[name] for name in `names`) from one record of `n`
    frames: the Gaussian formula dmu' S^-1 dmu + 0.5 tr(S^-1 dS_i S^-1 dS_j) on the closed-form
    moments, derivatives by central differences in log parameters."""
    mu, cov = moments(p, n)
    dmu, dcov = [], []
    for name in names:
        hi, lo = dict(p), dict(p)
        hi[name] *= np.exp(rel)
        lo[name] *= np.exp(-rel)
        (mh, ch), (ml, cl) = moments(hi, n), moments(lo, n)
        dmu.append((mh - ml) / (2 * rel))
        dcov.append(np.linalg.solve(cov, (ch - cl) / (2 * rel)))
    dmu = np.array(dmu)
    return dmu @ np.linalg.solve(cov, dmu.T) + 0.5 * np.einsum("iab,jba->ij", dcov, dcov)
