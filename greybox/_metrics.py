"""Goodness-of-fit metrics: pure functions of arrays (NaN entries are ignored).

Every function here is horizon-agnostic: whether `y_hat` is a free-run simulation or a
k-step-ahead prediction is the caller's statement, and reports must say which.
"""

from __future__ import annotations

import numpy as np


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
    """MATLAB `compare` fit: 100 (1 - ||y - y_hat|| / ||y - mean(y)||), in percent.

    100 is a perfect fit, 0 is no better than the mean, and it is unbounded below.
    """
    y, y_hat = _valid(y, y_hat)
    spread = np.linalg.norm(y - y.mean())
    if spread == 0:
        return float("nan")  # a constant signal has no variation to explain
    return float(100.0 * (1.0 - np.linalg.norm(y - y_hat) / spread))


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
