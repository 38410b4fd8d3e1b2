"""Output-error models y = sum_l B_l(q)/F_l(q) u_l + e by simulation-error minimisation."""

from __future__ import annotations

import functools as ft
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jax_jit

from ._arx import fit_arx
from ._data import UniformData, as_experiments
from ._pem import _lm_solve, ar_filter, covariance_direct, pad_experiments, stable_poly
from ._poly import (
    Polynomials,
    as_per_input,
    b_from_theta,
    lag_matrix,
    reflect_inside,
    reflection_from_poly,
)


@dataclass(frozen=True, eq=False)
class OE:
    """Output-error model y(t) = sum_l B_l(q)/F_l(q) u_l(t) + e(t), single output (MISO).

    **Fields:** `b` (1, nu, max(nk+nb)), `f` (1, nu, max(nf)+1) monic and stable (zero
    padded); orders `nb`, `nf`, `nk` per input; `parameters` (1, p) = [b (input by input),
    f_1..f_nf (input by input)]; `covariance` (1, p, p); `noise_variance` (1,) variance of
    the simulation error; `dt` [s]; `resampled`; `n_rows`; `converged`; `n_steps`.
    """

    b: np.ndarray
    f: np.ndarray
    nb: tuple[int, ...]
    nf: tuple[int, ...]
    nk: tuple[int, ...]
    parameters: np.ndarray
    covariance: np.ndarray
    noise_variance: np.ndarray
    dt: float
    resampled: bool
    n_rows: int
    converged: bool
    n_steps: int

    @property
    def std_errors(self) -> np.ndarray:
        return np.sqrt(np.diagonal(self.covariance, axis1=1, axis2=2))

    def polynomials(self) -> Polynomials:
        return Polynomials(np.ones((1, 1)), self.b, np.ones((1, 1)), self.f, np.zeros(1))


def _structure(nb, nk, nf):
    nd = sum(nf)
    width = max(k + n + nd - f for n, k, f in zip(nb, nk, nf))
    return nd, width, max(nd, width - 1)


def _oe_polys(theta, nb, nk, nf):
    """(den, nums) of the combined recursion den(q) w = sum_l num_l(q) u_l (JAX)."""
    nd, width, _ = _structure(nb, nk, nf)
    pos = 0
    bs = []
    for n, k in zip(nb, nk):
        bs.append(jnp.zeros(k + n).at[k:].set(theta[pos : pos + n]))
        pos += n
    fs = []
    for n in nf:
        fs.append(stable_poly(theta[pos : pos + n]))
        pos += n
    den = jnp.ones(1)
    for f in fs:
        den = jnp.convolve(den, f)
    nums = []
    for l, b in enumerate(bs):
        num = b
        for m, f in enumerate(fs):
            if m != l:
                num = jnp.convolve(num, f)
        nums.append(jnp.pad(num, (0, width - num.shape[0])))
    return den, jnp.concatenate(nums)


def _oe_resid(theta, args, nb, nk, nf):
    ulag, yv, mask, hist0 = args
    den, num = _oe_polys(theta, nb, nk, nf)
    x = ulag @ num
    w = jax.vmap(lambda xe, he: ar_filter(den, xe, he))(x, hist0)
    return ((yv - w) * mask).ravel()


@jax_jit(static_argnames=("nb", "nk", "nf"))
def _solve_oe(theta0, ulag, yv, mask, hist0, nb, nk, nf):
    pb = sum(nb)

    def to_direct(th):
        parts = [th[:pb]]
        pos = pb
        for n in nf:
            parts.append(stable_poly(th[pos : pos + n])[1:])
            pos += n
        return jnp.concatenate(parts)

    resid = ft.partial(_oe_resid, nb=nb, nk=nk, nf=nf)
    return _lm_solve(resid, theta0, (ulag, yv, mask, hist0), to_direct, 200)


def fit_oe(data: UniformData | Sequence[UniformData], nb, nf, nk) -> OE:
    """Estimate an output-error model [nb nf nk] by minimising the simulation error.

    The linear counterpart of a grey-box model fitted in simulation: residuals are
    y - simulate(model), with the first n_initial measured samples of each experiment as
    initial conditions (the rule of `simulate`). Start: ARX [max nf, nb, nk] (F from A,
    reflected stable); then Levenberg-Marquardt (optimistix) with every F_l kept stable.
    Single output (MISO allowed, one F per input). Detrend first: no offset is estimated.
    """
    data = as_experiments(data)
    if data[0].ny != 1:
        raise ValueError("data: OE is single-output; fit one model per output column")
    nu = data[0].nu
    nb = as_per_input(nb, nu, "nb")
    nf = as_per_input(nf, nu, "nf")
    nk = as_per_input(nk, nu, "nk")
    if not all(n > 0 for n in nb):
        raise ValueError("nb: every input needs nb >= 1 in an OE model; drop unused inputs")
    nd, width, n0 = _structure(nb, nk, nf)
    p = sum(nb) + sum(nf)
    rows = sum(max(d.n_samples - n0, 0) for d in data)
    if rows <= p:
        raise ValueError(
            f"data: {rows} usable samples for {p} parameters (each experiment "
            f"loses {n0} initial samples); use more data or lower orders"
        )
    arx = fit_arx(data, max(nf), nb, nk)
    k_arx = np.clip(reflection_from_poly(reflect_inside(arx.a[0])), -0.95, 0.95)
    theta0 = np.concatenate([arx.parameters[0, max(nf) :]] + [np.arctanh(k_arx[:n]) for n in nf])
    lags = np.arange(width)
    ulags, ys, hists = [], [], []
    for d in data:
        rws = np.arange(n0, d.n_samples)
        ulags.append(np.concatenate([lag_matrix(d.u[:, l], lags, rws) for l in range(nu)], 1))
        ys.append(d.y[n0:, 0])
        hists.append(d.y[n0 - np.arange(1, nd + 1), 0])
    ulag, mask = pad_experiments(ulags)
    yv, _ = pad_experiments(ys)
    theta, r, jac, g, ok, steps = _solve_oe(
        jnp.asarray(theta0),
        jnp.asarray(ulag),
        jnp.asarray(yv),
        jnp.asarray(mask),
        jnp.asarray(np.array(hists).reshape(len(data), nd)),
        nb,
        nk,
        nf,
    )
    if not bool(ok):
        warnings.warn(
            f"fit_oe: Levenberg-Marquardt stopped after {int(steps)} steps "
            "without converging; check `converged` and try other orders or scaled data",
            RuntimeWarning,
            stacklevel=2,
        )
    theta = np.asarray(theta)
    sigma2, cov = covariance_direct(r, jac, g, rows)
    pb = sum(nb)
    fs = np.zeros((nu, max(nf) + 1))
    direct = [theta[:pb]]
    pos = pb
    for l, n in enumerate(nf):
        f = np.asarray(stable_poly(jnp.asarray(theta[pos : pos + n])))
        fs[l, : n + 1] = f
        direct.append(f[1:])
        pos += n
    return OE(
        b=b_from_theta(theta[:pb], nb, nk)[None],
        f=fs[None],
        nb=nb,
        nf=nf,
        nk=nk,
        parameters=np.concatenate(direct)[None],
        covariance=cov[None],
        noise_variance=np.array([sigma2]),
        dt=data[0].dt,
        resampled=any(d.resampled for d in data),
        n_rows=rows,
        converged=bool(ok),
        n_steps=int(steps),
    )
