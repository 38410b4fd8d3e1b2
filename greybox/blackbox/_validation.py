"""Validation of polynomial models: free-run simulation, k-step prediction, fit %,
residual tests and step responses.

Initial conditions (both `simulate` and `predict`): the first `n_initial(model)` samples
are taken from the measured output (n_initial = the model's largest lag), exactly as the
regression used them; the returned prediction equals the measurement there.
"""

from __future__ import annotations

from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from greybox._estimate.metrics import fit_percent
from greybox._estimate.residuals import lagged_sums, portmanteau

from ._data import UniformData
from ._poly import _ar_recursion, lfilter


def _check(model, data: UniformData) -> None:
    if not isinstance(data, UniformData):
        raise ValueError("data: pass one UniformData experiment (loop over experiments)")
    pol = model.polynomials()
    if data.nu != pol.nu or data.ny != pol.ny:
        raise ValueError(
            f"data: has nu={data.nu}, ny={data.ny} but the model expects nu={pol.nu}, ny={pol.ny}"
        )
    if data.n_samples <= n_initial(model):
        raise ValueError(
            f"data: {data.n_samples} samples, need more than the model's "
            f"{n_initial(model)} initial samples"
        )


def n_initial(model) -> int:
    """Number of leading measured samples used as initial conditions (largest lag)."""
    pol = model.polynomials()
    n = 0
    for i in range(pol.ny):
        den, num, _, _ = pol.io_rational(i)
        n = max(n, len(den) - 1, num.shape[1] - 1)
    return n


def _forced(num, const, u, n):
    """x(t) = sum_l num_l(q) u_l(t) + const (valid for t >= n)."""
    x = np.full(u.shape[0], const, dtype=float)
    for l in range(u.shape[1]):
        x += np.convolve(u[:, l], num[l])[: u.shape[0]]
    x[:n] = 0.0
    return x


def simulate(model, data: UniformData) -> np.ndarray:
    """Free-run (infinite-horizon) simulation from the inputs of `data`.

    Uses the measured outputs only as initial conditions (the first `n_initial(model)`
    samples); afterwards the model feeds back its own simulated outputs. Noise is zero.

    **Returns:** (N, ny) simulated outputs.
    """
    _check(model, data)
    pol = model.polynomials()
    n = n_initial(model)
    out = np.empty_like(data.y)
    for i in range(pol.ny):
        den, num, const, _ = pol.io_rational(i)
        out[:, i] = _ar_recursion(den, _forced(num, const, data.u, n), data.y[:, i], n)
    return out


def innovations(model, data: UniformData) -> np.ndarray:
    """One-step prediction errors e(t) (zero during the `n_initial` samples), (N, ny)."""
    _check(model, data)
    pol = model.polynomials()
    n = n_initial(model)
    e = np.zeros_like(data.y)
    for i in range(pol.ny):
        den, num, const, fprod = pol.io_rational(i)
        v = np.convolve(data.y[:, i], den)[: data.n_samples] - _forced(num, const, data.u, n)
        v[:n] = 0.0
        e[:, i] = lfilter([1.0], np.convolve(pol.c[i], fprod), v)
    return e


def predict(model, data: UniformData, k: int = 1) -> np.ndarray:
    """k-step-ahead prediction y_hat(t | t-k): uses measured outputs up to t-k and inputs.

    Computed as y(t) - sum_{j<k} h_j e(t-j), with h the impulse response of the noise
    model C/A and e the innovations. k = 1 is the one-step predictor; as k grows it tends
    to `simulate` (identical once k exceeds the record length).

    **Returns:** (N, ny) predictions.
    """
    if int(k) != k or k < 1:
        raise ValueError(
            f"k: prediction horizon must be an integer >= 1, got {k!r}; use "
            "`simulate` for the infinite horizon"
        )
    e = innovations(model, data)
    pol = model.polynomials()
    N = data.n_samples
    k = min(int(k), N)
    out = np.empty_like(data.y)
    for i in range(pol.ny):
        impulse = np.zeros(k)
        impulse[0] = 1.0
        h = lfilter(pol.c[i], pol.a[i], impulse)
        out[:, i] = data.y[:, i] - np.convolve(e[:, i], h)[:N]
    return out


@dataclass(frozen=True, eq=False)
class Comparison:
    """Model output vs measurement (MATLAB `compare`).

    - `y_hat`: (N, ny) simulated or predicted output; `fit_percent`: (ny,)
      100 (1 - ||y - y_hat|| / ||y - mean y||), over all samples or, with
      `skipped_initial`, over samples t >= `n_initial`;
    - `horizon`: "simulation" or "k-step" with `k`; `resampled`: model or data resampled.
    """

    y_hat: np.ndarray
    fit_percent: np.ndarray
    horizon: str
    k: int | None
    n_initial: int
    skipped_initial: bool
    resampled: bool
    data_name: str


def compare(
    model, data: UniformData, k: int | None = None, *, skip_initial: bool = False
) -> Comparison:
    """Fit % of free-run simulation (`k=None`, MATLAB `compare` default) or k-step prediction.

    The `n_initial` leading samples are initial conditions copied from the measurement. By
    default they are scored like every other sample (as MATLAB `compare` scores its whole
    record); `skip_initial=True` leaves them out, which is stricter on short records.
    """
    y_hat = simulate(model, data) if k is None else predict(model, data, k)
    n = n_initial(model)
    s = n if skip_initial else 0
    fits = np.array([fit_percent(data.y[s:, i], y_hat[s:, i]) for i in range(data.ny)])
    return Comparison(
        y_hat=y_hat,
        fit_percent=fits,
        horizon="simulation" if k is None else "k-step",
        k=None if k is None else int(k),
        n_initial=n,
        skipped_initial=bool(skip_initial),
        resampled=bool(model.resampled or data.resampled),
        data_name=data.name,
    )


@dataclass(frozen=True, eq=False)
class ResidualTest:
    """Residual analysis of one-step prediction errors (MATLAB `resid`).

    - `lags`: (M+1,) 0..M for `autocorrelation` (ny, M+1), normalised so lag 0 is 1.
    - `cross_lags`: (2M+1,) -M..M for `cross_correlation` (ny, nu, 2M+1) between input
      u(t - tau) and residual e(t); non-zero values at negative tau point at feedback.
    - `band`: half-width of the `confidence` band for one lag, z / sqrt(N).
    - `q_auto` (ny,), `q_cross` (ny, nu): portmanteau statistics N sum r^2 over lags
      1..M and -M..M, with thresholds `q_auto_limit`, `q_cross_limit` (chi-square quantile).
    - `white` (ny,), `independent` (ny, nu): statistics below their thresholds.
    """

    lags: np.ndarray
    autocorrelation: np.ndarray
    cross_lags: np.ndarray
    cross_correlation: np.ndarray
    band: float
    confidence: float
    q_auto: np.ndarray
    q_cross: np.ndarray
    q_auto_limit: float
    q_cross_limit: float
    white: np.ndarray
    independent: np.ndarray
    n_samples: int
    resampled: bool


def _chi2_quantile(p: float, dof: int) -> float:
    z = NormalDist().inv_cdf(p)  # Wilson-Hilferty: accurate to < 1 % for dof >= 10
    return dof * (1 - 2 / (9 * dof) + z * np.sqrt(2 / (9 * dof))) ** 3


def residual_test(
    model, data: UniformData, max_lag: int = 25, confidence: float = 0.99
) -> ResidualTest:
    """Whiteness of residuals and their independence from past inputs, with bands."""
    if int(max_lag) != max_lag or max_lag < 1:
        raise ValueError(f"max_lag: must be an integer >= 1, got {max_lag!r}")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence: must lie in (0, 1), got {confidence!r}")
    n = n_initial(model)
    e = innovations(model, data)[n:]
    u = data.u[n:] - data.u[n:].mean(0)
    N = e.shape[0]
    M = int(max_lag)
    if N <= 2 * M:
        raise ValueError(f"max_lag: {M} is too large for {N} residual samples; use <= {N // 4}")
    lags = np.arange(M + 1)
    cross_lags = np.arange(-M, M + 1)
    ny, nu = e.shape[1], u.shape[1]
    auto = np.zeros((ny, M + 1))
    cross = np.zeros((ny, nu, 2 * M + 1))
    every = np.ones(N, dtype=bool)
    for i in range(ny):
        ei = e[:, i] - e[:, i].mean()
        r0 = ei @ ei / N
        auto[i] = lagged_sums(ei, every, ei, every, lags)[0] / N / r0
        for l in range(nu):
            ul = u[:, l]
            # r_ue(tau) = (1/N) sum_t e(t) u(t - tau)
            c = lagged_sums(ei, every, ul, every, cross_lags)[0] / N
            cross[i, l] = c / np.sqrt(r0 * (ul @ ul / N))
    z = NormalDist().inv_cdf(0.5 + confidence / 2)
    # Box-Pierce (MATLAB `resid`): the biased r with null variance 1 / N
    q_auto = portmanteau(auto[:, 1:], 1.0 / N)
    q_cross = portmanteau(cross, 1.0 / N)
    qa_lim = _chi2_quantile(confidence, M)
    qc_lim = _chi2_quantile(confidence, 2 * M + 1)
    return ResidualTest(
        lags=lags,
        autocorrelation=auto,
        cross_lags=cross_lags,
        cross_correlation=cross,
        band=float(z / np.sqrt(N)),
        confidence=confidence,
        q_auto=q_auto,
        q_cross=q_cross,
        q_auto_limit=qa_lim,
        q_cross_limit=qc_lim,
        white=q_auto <= qa_lim,
        independent=q_cross <= qc_lim,
        n_samples=N,
        resampled=bool(model.resampled or data.resampled),
    )


def step_response(model, n_samples: int) -> np.ndarray:
    """Response to unit steps applied at sample 0, zero initial state, offset excluded.

    **Returns:** (n_samples, ny, nu); sample k is at time k * model.dt [s].
    """
    if int(n_samples) != n_samples or n_samples < 1:
        raise ValueError(f"n_samples: must be an integer >= 1, got {n_samples!r}")
    pol = model.polynomials()
    out = np.zeros((int(n_samples), pol.ny, pol.nu))
    step = np.ones(int(n_samples))
    for i in range(pol.ny):
        den, num, _, _ = pol.io_rational(i)
        for l in range(pol.nu):
            out[:, i, l] = lfilter(num[l], den, step)
    return out
