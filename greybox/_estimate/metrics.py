"""Goodness-of-fit metrics: pure functions of arrays (NaN entries are ignored).

Every function here is horizon-agnostic: whether `y_hat` is a free-run simulation or a
k-step-ahead prediction is the caller's statement, and reports must say which.

Fit % is a per-output figure: channels with different spreads (a shuttle that swings 5 um
and one that stays within 0.1 um) cannot be pooled into one number, so `fit_percent` takes
one output and `fit_percent_per_output` scores each column of (N, n_y) arrays on its own
valid samples, as MATLAB `compare` does.
"""

from __future__ import annotations

import numpy as np

OUTLIER_SIGMAS = 5.0  # readings further than this (x their noise sd) from the model: outliers


def _valid(y, y_hat):
    y = np.asarray(y, dtype=float)
    y_hat = np.asarray(y_hat, dtype=float)
    if y.shape != y_hat.shape:
        raise ValueError(f"y and y_hat: shapes differ ({y.shape} vs {y_hat.shape})")
    ok = np.isfinite(y) & np.isfinite(y_hat)
    if not ok.any():
        raise ValueError("y: no finite samples to score")
    return y[ok], y_hat[ok]


def fit_percent(y, y_hat) -> float:
    """MATLAB `compare` fit of one output: 100 (1 - ||y - y_hat|| / ||y - mean(y)||), in
    percent. `y`, `y_hat`: (N,) or (N, 1); several outputs: `fit_percent_per_output`.

    100 is a perfect fit, 0 is no better than the mean, and it is unbounded below.
    """
    if np.ndim(y) == 2 and np.shape(y)[1] > 1:
        raise ValueError(
            f"y: has {np.shape(y)[1]} output columns; fit % is per output, use "
            "fit_percent_per_output (pooling channels with different spreads misleads)"
        )
    _valid(y, y_hat)  # the checks: same shapes, at least one finite sample
    return float(fit_percent_per_output(y, y_hat)[0])  # NaN for a constant signal


def rmse(y, y_hat) -> float:
    """Root-mean-square error, in the units of y."""
    y, y_hat = _valid(y, y_hat)
    return float(np.sqrt(np.mean((y - y_hat) ** 2)))


def mae(y, y_hat) -> float:
    """Mean absolute error, in the units of y."""
    y, y_hat = _valid(y, y_hat)
    return float(np.mean(np.abs(y - y_hat)))


def sae(y, y_hat) -> float:
    """Sum of absolute errors, in the units of y (the TCLab benchmark's metric)."""
    y, y_hat = _valid(y, y_hat)
    return float(np.sum(np.abs(y - y_hat)))


def r_squared(y, y_hat) -> float:
    """Coefficient of determination 1 - SSE/SST (variance explained, not fit %)."""
    y, y_hat = _valid(y, y_hat)
    return float(1.0 - np.sum((y - y_hat) ** 2) / np.sum((y - y.mean()) ** 2))


def fit_percent_per_output(y, y_hat) -> np.ndarray:
    """(n_y,) fit % of each output column of `y`, `y_hat` ((N,) or (N, n_y)), each over its
    own finite samples; NaN for a column with fewer than two of them or no spread (a constant
    signal has no variation to explain). All columns at once; stacks of runs too: (..., N,
    n_y) arrays give (..., n_y) (runs of different lengths padded with NaN). `fit_percent`
    is its one-column case."""
    y = np.asarray(y, dtype=float)
    y_hat = np.asarray(y_hat, dtype=float)
    if y.shape != y_hat.shape:
        raise ValueError(f"y and y_hat: shapes differ ({y.shape} vs {y_hat.shape})")
    if y.ndim <= 2:
        y, y_hat = y.reshape(y.shape[0], -1), y_hat.reshape(y.shape[0], -1)
    ok = np.isfinite(y) & np.isfinite(y_hat)
    n, centred = _centred_squares(y, ok)
    spread = np.sqrt(centred)
    error = np.sqrt(np.sum(np.where(ok, y - y_hat, 0.0) ** 2, axis=-2))
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 100.0 * (1.0 - error / spread)
    return np.where((n > 1) & (spread > 0), out, np.nan)


def _centred_squares(y, ok) -> tuple[np.ndarray, np.ndarray]:
    """(count, sum of squared deviations from the mean) of each column of `y` (..., N, n_y)
    over its `ok` samples: the spread both fit % and the noise ceiling measure against."""
    n = ok.sum(axis=-2)
    mean = np.where(ok, y, 0.0).sum(axis=-2) / np.maximum(n, 1)
    return n, np.sum(np.where(ok, y - mean[..., None, :], 0.0) ** 2, axis=-2)


def noise_ceiling_per_output(y, sigma) -> np.ndarray:
    """`noise_ceiling` of each output column of `y` (..., N, n_y) (stacks of runs, padded
    with NaN), `sigma` broadcastable to it: (..., n_y)."""
    y = np.asarray(y, dtype=float)
    s = np.broadcast_to(np.asarray(sigma, dtype=float), y.shape)
    ok = np.isfinite(y) & np.isfinite(s)
    n, centred = _centred_squares(y, ok)
    m = np.maximum(n, 1)
    spread = np.sqrt(centred / m)
    level = np.sqrt(np.sum(np.where(ok, s, 0.0) ** 2, axis=-2) / m)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = 100.0 * (1.0 - level / spread)
    return np.where((n >= 2) & (spread > level), out, np.nan)


def noise_ceiling(y, sigma) -> float:
    """Fit % that the true model would score on one output `y` (N,) with noise sd `sigma`:
    about 100 (1 - sigma / std(y)) (finite samples of `y` only; NaN when the spread is not
    above the noise). `sigma` is a scalar or per-sample (N,) (its RMS over the samples used).

    Only as good as `sigma`: a noise level estimated from the residuals of a wrong model is
    inflated by the misfit, and the ceiling it gives is too low.
    """
    y = np.asarray(y, dtype=float).reshape(-1, 1)
    s = np.reshape(np.asarray(sigma, dtype=float), (-1, 1))
    return float(noise_ceiling_per_output(y, s)[0])
