"""ARX models by linear least squares (MIMO with diagonal A, multi-experiment)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._data import UniformData, as_experiments
from ._poly import (
    Polynomials,
    as_order,
    as_per_input,
    b_from_theta,
    input_lags,
    lag_matrix,
    max_lag,
)


@dataclass(frozen=True, eq=False)
class ARX:
    """ARX model A_i(q) y_i(t) = sum_l B_il(q) u_l(t) + offset_i + e_i(t), one per output.

    Each output regresses on its own past only (diagonal A, the GEKKO `sysid` / Park et al.
    2020 MIMO form) and on all inputs. Sign convention as MATLAB: A = 1 + a_1 q^-1 + ...

    **Fields:**
    - `a`: (ny, na+1) monic A coefficients; `b`: (ny, nu, max(nk+nb)) B coefficients of
      q^0, q^-1, ... (delays are leading zeros); `offset`: (ny,) offset gamma (0 if not fitted).
    - `na`, `nb`, `nk`: orders (nb, nk one per input); `has_offset`.
    - `parameters`: (ny, p) vectors [a_1..a_na, b_1 (input 1, lag nk_1) .., gamma].
    - `covariance`: (ny, p, p) = noise_variance (Phi^T Phi)^-1.
    - `noise_variance`: (ny,) residual variance SSR / (rows - p), in output units squared.
    - `dt` [s], `resampled`, `n_rows` (regression rows used).
    """

    a: np.ndarray
    b: np.ndarray
    offset: np.ndarray
    na: int
    nb: tuple[int, ...]
    nk: tuple[int, ...]
    has_offset: bool
    parameters: np.ndarray
    covariance: np.ndarray
    noise_variance: np.ndarray
    dt: float
    resampled: bool
    n_rows: int

    @property
    def std_errors(self) -> np.ndarray:
        """(ny, p) one-sigma standard errors of `parameters`."""
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2))

    @property
    def parameter_names(self) -> tuple[str, ...]:
        names = [f"a{j}" for j in range(1, self.na + 1)]
        for l, (n, k) in enumerate(zip(self.nb, self.nk)):
            names += [f"b{l + 1}_{k + j}" for j in range(n)]
        return tuple(names + (["offset"] if self.has_offset else []))

    def polynomials(self) -> Polynomials:
        ny, nu = self.b.shape[:2]
        return Polynomials(self.a, self.b, np.ones((ny, 1)), np.ones((ny, nu, 1)), self.offset)


def _normalise_orders(data: tuple[UniformData, ...], na, nb, nk):
    nu = data[0].nu
    na = as_order(na, "na")
    nb = as_per_input(nb, nu, "nb")
    nk = as_per_input(nk, nu, "nk")
    return na, nb, nk


def arx_regressors(
    data: UniformData,
    i: int,
    na: int,
    nb,
    nk,
    offset: bool,
    start: int | None = None,
    extra_lag: int = 0,
):
    """Regressor matrix Phi and target for output i of one experiment (rows t >= start).

    Columns: [-y_i(t-1) .. -y_i(t-na), u_l(t-nk_l) .. u_l(t-nk_l-nb_l+1) per input, 1].
    """
    n0 = max_lag(na, nb, nk, extra_lag) if start is None else start
    rows = np.arange(n0, data.n_samples)
    y = data.y[:, i]
    blocks = [-lag_matrix(y, np.arange(1, na + 1), rows)]
    for l, lags in enumerate(input_lags(nb, nk)):
        blocks.append(lag_matrix(data.u[:, l], lags, rows))
    if offset:
        blocks.append(np.ones((len(rows), 1)))
    return np.concatenate(blocks, axis=1), y[rows]


def _stack(data, i, na, nb, nk, offset, start=None):
    parts = [arx_regressors(d, i, na, nb, nk, offset, start) for d in data]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _check_rows(data, na, nb, nk, offset, start=None):
    n0 = max_lag(na, nb, nk) if start is None else start
    p = na + sum(nb) + int(offset)
    rows = sum(max(d.n_samples - n0, 0) for d in data)
    if rows <= p:
        raise ValueError(
            f"data: {rows} usable regression rows for {p} parameters (each experiment loses "
            f"its first {n0} samples to the lags); use more samples or lower orders na/nb/nk"
        )
    if p == 0:
        raise ValueError("na, nb: all orders are zero; nothing to estimate")
    return rows, p


def _ls(phi: np.ndarray, target: np.ndarray):
    """Least squares via QR: estimate, covariance, residual variance, residuals."""
    q, r = np.linalg.qr(phi)
    diag = np.abs(np.diag(r))
    if diag.min() <= 1e-12 * diag.max():
        raise ValueError(
            "data: the regressor matrix is rank deficient (input not persistently exciting "
            "for these orders, or a constant input with offset=True); lower nb/na or use a "
            "richer input"
        )
    theta = np.linalg.solve(r, q.T @ target)
    resid = target - phi @ theta
    dof = len(target) - len(theta)
    sigma2 = float(resid @ resid) / dof
    rinv = np.linalg.solve(r, np.eye(len(theta)))
    return theta, sigma2 * (rinv @ rinv.T), sigma2, resid


def fit_arx(
    data: UniformData | Sequence[UniformData], na: int, nb, nk, *, offset: bool = False
) -> ARX:
    """Estimate an ARX [na nb nk] model by linear least squares.

    **Arguments:**
    - `data`: one `UniformData` or a list (multi-experiment: regressors never span two
      experiments; every experiment gives up its first max-lag samples).
    - `na`: number of past outputs per output (own past only).
    - `nb`, `nk`: numbers of input coefficients and input delays [samples], scalars or one
      per input. nk = 0 means direct feedthrough; nk = 1 is the usual one-sample delay.
    - `offset`: also estimate a constant gamma per output (GEKKO `sysid` form).

    **Returns:** an `ARX` with parameter covariance and noise variance per output.
    """
    data = as_experiments(data)
    na, nb, nk = _normalise_orders(data, na, nb, nk)
    rows, p = _check_rows(data, na, nb, nk, offset)
    ny, nu = data[0].ny, data[0].nu
    thetas, covs, sig = [], [], []
    for i in range(ny):
        phi, target = _stack(data, i, na, nb, nk, offset)
        theta, cov, s2, _ = _ls(phi, target)
        thetas.append(theta)
        covs.append(cov)
        sig.append(s2)
    thetas = np.array(thetas)
    a = np.concatenate([np.ones((ny, 1)), thetas[:, :na]], axis=1)
    b = np.stack([b_from_theta(t[na : na + sum(nb)], nb, nk) for t in thetas])
    off = thetas[:, -1] if offset else np.zeros(ny)
    return ARX(
        a=a,
        b=b.reshape(ny, nu, -1),
        offset=off,
        na=na,
        nb=nb,
        nk=nk,
        has_offset=bool(offset),
        parameters=thetas,
        covariance=np.array(covs),
        noise_variance=np.array(sig),
        dt=data[0].dt,
        resampled=any(d.resampled for d in data),
        n_rows=rows,
    )


@dataclass(frozen=True, eq=False)
class OrderSearch:
    """Result of `arx_order_search` (like MATLAB `arxstruc` + `selstruc`).

    - `orders`: (M, 3) rows [na, nb, nk]; `loss`: (M,) mean squared one-step prediction
      error on the scoring data; `n_parameters`: (M,); `n_rows`: scoring rows (common to
      all candidates); `aic` = N log(loss) + 2 d; `mdl` = N log(loss) + d log(N).
    - `best`: (na, nb, nk) minimising `criterion`; `criterion`: "aic" or "mdl";
      `on_validation`: whether the loss was scored on separate validation data.
    """

    orders: np.ndarray
    loss: np.ndarray
    n_parameters: np.ndarray
    n_rows: int
    aic: np.ndarray
    mdl: np.ndarray
    best: tuple[int, int, int]
    criterion: str
    on_validation: bool
    resampled: bool


def arx_order_search(
    estimation,
    validation=None,
    *,
    na: Sequence[int] = range(1, 5),
    nb: Sequence[int] = range(1, 5),
    nk: Sequence[int] = range(0, 4),
    criterion: str = "aic",
) -> OrderSearch:
    """Fit every ARX [na nb nk] on a grid and rank by AIC or MDL (single-output data).

    Losses are one-step prediction errors over a common set of rows (those valid for the
    largest lag in the grid), on `validation` data if given, else on the estimation data.
    nb and nk apply to every input.
    """
    if criterion not in ("aic", "mdl"):
        raise ValueError(f"criterion: unknown {criterion!r}; use 'aic' or 'mdl'")
    est = as_experiments(estimation)
    val = est if validation is None else as_experiments(validation)
    if est[0].ny != 1:
        raise ValueError(
            "estimation: order search is for single-output data; pass one "
            "output column at a time (y[:, [i]])"
        )
    nu = est[0].nu
    grid = [(a, b, k) for a in na for b in nb for k in nk if a + b * nu > 0]
    if not grid:
        raise ValueError("na, nb: the grid has no model with parameters")
    start = max(max_lag(a, (b,) * nu, (k,) * nu) for a, b, k in grid)
    losses, npar = [], []
    n_rows = None
    for a, b, k in grid:
        model = fit_arx(est, a, b, k)
        phi, target = _stack(val, 0, a, (b,) * nu, (k,) * nu, False, start)
        resid = target - phi @ model.parameters[0]
        losses.append(float(np.mean(resid**2)))
        npar.append(a + b * nu)
        n_rows = len(target)
    loss = np.array(losses)
    d = np.array(npar)
    aic = n_rows * np.log(loss) + 2 * d
    mdl = n_rows * np.log(loss) + d * np.log(n_rows)
    score = aic if criterion == "aic" else mdl
    best = tuple(int(v) for v in grid[int(np.argmin(score))])
    return OrderSearch(
        orders=np.array(grid),
        loss=loss,
        n_parameters=d,
        n_rows=n_rows,
        aic=aic,
        mdl=mdl,
        best=best,
        criterion=criterion,
        on_validation=validation is not None,
        resampled=any(x.resampled for x in est + val),
    )
