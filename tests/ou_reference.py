"""Independent reference for small process-noise problems: the one-node RC building
(tests/rc_building_device.py, `nodes=1`, the air read) as a scalar Ornstein-Uhlenbeck process
with a known input, simulated and filtered with numpy only (no greybox import).

    dTi = ((Ta - Ti)/(Rea Ci) + Ph/Ci) dt + dW,   E[dW^2] = q dt,   y = Ti + e, e ~ N(0, sd^2)

Regular frames every `DT` s, Ta constant, Ph a known square wave. The exact discretisation is
closed form: a = exp(-h/tau), tau = Rea Ci; x' = a x + (1 - a)(Ta + Rea Ph) + w,
Var w = q tau (1 - a^2) / 2. The Kalman filter has a known initial state (variance 0) and
conditions on the first frame (not scored), the convention of `greybox.InitialState()`.

`information` is the expected Fisher information of the innovations form,
I_ij = sum_k [dv_k/dth_i dv_k/dth_j / S_k + 0.5 dS_k/dth_i dS_k/dth_j / S_k^2],
by central differences of the (deterministic) innovation means and variances: v_k(th) is the
innovation of the filter run on the noise-free mean response at the nominal parameters.
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


def information(p: dict, n: int, names=("Ci", "Rea", "q", "sd"), rel=1e-5) -> np.ndarray:
    """Expected Fisher information of (log p[name] for name in `names`) for one record of `n`
    frames (innovations form, central differences in log parameters)."""
    y0 = mean_response(p, n)  # data at the nominal mean: innovation means vanish there
    dv, ds = [], []
    for name in names:
        hi, lo = dict(p), dict(p)
        hi[name] *= np.exp(rel)
        lo[name] *= np.exp(-rel)
        vh, sh = innovations(hi, y0)
        vl, sl = innovations(lo, y0)
        dv.append((vh - vl) / (2 * rel))
        ds.append((sh - sl) / (2 * rel))
    _, s = innovations(p, y0)
    dv, ds = np.array(dv), np.array(ds)
    return (dv / s) @ dv.T + 0.5 * (ds / s**2) @ ds.T
