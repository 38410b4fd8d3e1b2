"""ARMAX models A(q) y = B(q) u + C(q) e by the prediction-error method (SISO/MISO)."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jax_jit

from ._arx import _check_rows, arx_regressors, fit_arx
from ._data import UniformData, as_experiments
from ._pem import _lm_solve, ar_filter, covariance_direct, pad_experiments, stable_poly
from ._poly import (
    Polynomials,
    as_order,
    as_per_input,
    b_from_theta,
    is_stable_poly,
    lag_matrix,
    max_lag,
    reflect_inside,
    reflection_from_poly,
)
from ._validation import innovations


@dataclass(frozen=True, eq=False)
class ARMAX:
    """ARMAX model A(q) y(t) = sum_l B_l(q) u_l(t) + C(q) e(t), single output.

    **Fields:** `a` (1, na+1), `b` (1, nu, max(nk+nb)), `c` (1, nc+1) monic and
    minimum-phase (roots strictly inside the unit circle); orders `na`, `nb`, `nc`, `nk`;
    `parameters` (1, p) = [a_1..a_na, b (input by input, lags nk..nk+nb-1), c_1..c_nc];
    `covariance` (1, p, p); `noise_variance` (1,) innovation variance; `dt` [s];
    `resampled`; `n_rows` (prediction errors used); `converged`, `n_steps` (optimiser).
    MIMO is not supported: fit one model per output (each with all inputs).
    """

    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    na: int
    nb: tuple[int, ...]
    nc: int
    nk: tuple[int, ...]
    parameters: np.ndarray
    covariance: np.ndarray
    noise_variance: np.ndarray
    dt: float
    resampled: bool
    n_rows: int
    converged: bool
    n_steps: int

    def __post_init__(self):
        if not is_stable_poly(self.c[0]):
            raise ValueError(
                f"c: C(q) = {np.round(self.c[0], 4).tolist()} has roots on or outside the unit "
                "circle; the predictor 1/C would be unstable. Reflect the roots inside "
                "(r -> 1/conj(r)) or refit with fit_armax"
            )

    @property
    def std_errors(self) -> np.ndarray:
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2))

    @property
    def offset(self) -> np.ndarray:
        return np.zeros(1)

    def polynomials(self) -> Polynomials:
        nu = self.b.shape[1]
        return Polynomials(self.a, self.b, self.c, np.ones((1, nu, 1)), np.zeros(1))

    @classmethod
    def from_coefficients(
        cls, a, b, c, *, dt: float, nk=None, noise_variance: float = 0.0, resampled: bool = False
    ) -> ARMAX:
        """A known ARMAX system (e.g. for simulation); `b` (nu, W) includes leading zeros."""
        a = np.atleast_1d(np.asarray(a, float))
        c = np.atleast_1d(np.asarray(c, float))
        b = np.atleast_2d(np.asarray(b, float))
        nu = b.shape[0]
        if nk is None:
            nk = tuple(int(np.argmax(row != 0)) for row in b)
        nk = as_per_input(nk, nu, "nk")
        nb = tuple(int(b.shape[1] - k) for k in nk)
        theta = np.concatenate([a[1:]] + [row[k:] for row, k in zip(b, nk)] + [c[1:]])
        p = len(theta)
        return cls(
            a=a[None],
            b=b[None],
            c=c[None],
            na=len(a) - 1,
            nb=nb,
            nc=len(c) - 1,
            nk=nk,
            parameters=theta[None],
            covariance=np.zeros((1, p, p)),
            noise_variance=np.array([noise_variance]),
            dt=float(dt),
            resampled=resampled,
            n_rows=0,
            converged=True,
            n_steps=0,
        )


def _armax_resid(theta, args):
    phi, yv, mask = args
    pab = phi.shape[-1]
    c = stable_poly(theta[pab:])
    v = yv - phi @ theta[:pab]
    hist0 = jnp.zeros(c.shape[0] - 1)
    e = jax.vmap(lambda vv: ar_filter(c, vv, hist0))(v)
    return (e * mask).ravel()


@jax_jit
def _solve_armax(theta0, phi, yv, mask):
    pab = phi.shape[-1]

    def to_direct(th):
        return jnp.concatenate([th[:pab], stable_poly(th[pab:])[1:]])

    return _lm_solve(_armax_resid, theta0, (phi, yv, mask), to_direct, 200)


def _initial_armax(data, na, nb, nc, nk):
    """Hannan-Rissanen start: innovations from a higher-order ARX, then one linear LS with
    lagged innovations as extra regressors (ARX-initialised, as the thesis did)."""
    high = fit_arx(data, na + nc, tuple(n + nc for n in nb), nk)
    n0 = max(max_lag(na, nb, nk, nc), max_lag(high.na, high.nb, high.nk))
    phis, ys = [], []
    for d in data:
        e_hat = innovations(high, d)[:, 0]
        phi, target = arx_regressors(d, 0, na, nb, nk, False, start=n0)
        rows = np.arange(n0, d.n_samples)
        phis.append(np.concatenate([phi, lag_matrix(e_hat, np.arange(1, nc + 1), rows)], 1))
        ys.append(target)
    theta, *_ = np.linalg.lstsq(np.concatenate(phis), np.concatenate(ys), rcond=None)
    c0 = reflect_inside(np.concatenate([[1.0], theta[-nc:]]))
    k0 = np.clip(reflection_from_poly(c0), -0.95, 0.95)
    return np.concatenate([theta[:-nc], np.arctanh(k0)])


def fit_armax(data: UniformData | Sequence[UniformData], na: int, nb, nc: int, nk) -> ARMAX:
    """Estimate ARMAX [na nb nc nk] by the prediction-error method (MATLAB `armax`).

    The start comes from ARX fits (Hannan-Rissanen); then Levenberg-Marquardt (optimistix)
    minimises the sum of squared one-step prediction errors e = (A y - B u) / C over all
    experiments, with C kept minimum-phase by its reflection-coefficient parameterisation.
    The prediction errors start at the first max(na, nk+nb-1) samples of each experiment with
    zero past errors (the rule used by `predict`). Single-output (MISO allowed).

    **Arguments:** `data` (one or a list of `UniformData`, ny = 1; detrend first: no offset
    is estimated); `na`, `nc` >= 1 orders; `nb`, `nk` per input or scalars.

    **Returns:** `ARMAX` with covariance sigma^2 (J^T J)^-1 of the direct parameters.
    """
    data = as_experiments(data)
    if data[0].ny != 1:
        raise ValueError("data: ARMAX is single-output; fit one model per output column")
    na = as_order(na, "na")
    nc = as_order(nc, "nc")
    if nc == 0:
        raise ValueError("nc: must be >= 1 for ARMAX; with nc = 0 use fit_arx")
    nu = data[0].nu
    nb = as_per_input(nb, nu, "nb")
    nk = as_per_input(nk, nu, "nk")
    rows, p_ab = _check_rows(data, na, nb, nk, False)
    if rows <= p_ab + nc:
        raise ValueError(
            f"data: {rows} prediction errors for {p_ab + nc} parameters; use "
            "more samples or lower orders"
        )
    theta0 = _initial_armax(data, na, nb, nc, nk)
    parts = [arx_regressors(d, 0, na, nb, nk, False) for d in data]
    phi, mask = pad_experiments([p[0] for p in parts])
    yv, _ = pad_experiments([p[1] for p in parts])
    theta, r, jac, g, ok, steps = _solve_armax(
        jnp.asarray(theta0), jnp.asarray(phi), jnp.asarray(yv), jnp.asarray(mask)
    )
    if not bool(ok):
        warnings.warn(
            f"fit_armax: Levenberg-Marquardt stopped after {int(steps)} steps "
            "without converging; check `converged` and try other orders or scaled data",
            RuntimeWarning,
            stacklevel=2,
        )
    theta = np.asarray(theta)
    sigma2, cov = covariance_direct(r, jac, g, rows)
    c = np.asarray(stable_poly(jnp.asarray(theta[p_ab:])))
    direct = np.concatenate([theta[:p_ab], c[1:]])
    a = np.concatenate([[1.0], theta[:na]])
    b = b_from_theta(theta[na:p_ab], nb, nk)
    return ARMAX(
        a=a[None],
        b=b[None],
        c=c[None],
        na=na,
        nb=nb,
        nc=nc,
        nk=nk,
        parameters=direct[None],
        covariance=cov[None],
        noise_variance=np.array([sigma2]),
        dt=data[0].dt,
        resampled=any(d.resampled for d in data),
        n_rows=rows,
        converged=bool(ok),
        n_steps=int(steps),
    )
