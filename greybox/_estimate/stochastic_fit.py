"""Maximum-likelihood fitting of stochastic grey-box models (prediction-error form).

A stochastic grey-box model is a `LinearGaussianSDE` built from named physical parameters,

    dx = (A(theta) x + B(theta) u) dt + dW,  E[dW dW^T] = Qc(theta) dt,
    y_k = C(theta) x(t_k) + D u + d + e_k,   e_k ~ N(0, R(theta)),   x(t0) ~ N(x0(theta), P0),

so process-noise intensities (e.g. of a random-walk ambient or drift state), the measurement
noise and the initial state are parameters like any time constant. `fit_stochastic` minimises

    -log p(y | theta) = 1/2 sum_k (v_k^T S_k^{-1} v_k + log det S_k + m_k log 2 pi)

over all records, v_k and S_k the Kalman filter's innovations and their covariances
(`greybox.stochastic._kalman`, exact for a linear output), with the likelihood optimiser of
`greybox.fit(noise=ProcessNoise(...))` (`greybox._estimate.likelihood`: BFGS, then Newton) on
transformed parameters (log for the positive ones). It is the estimator for a hand-built
`LinearGaussianSDE`; devices go through `greybox.fit`. Standard errors come from the inverse
Hessian of the negative log-likelihood in the transformed coordinates (central differences
of the exact gradient); 95 % intervals are
+-1.96 se there, mapped back (so asymmetric for positive parameters), and the physical
standard errors use the delta method.

Diagnostics per record and output: Ljung-Box whiteness test of the standardised innovations
(a right model leaves i.i.d. innovations), one-step-ahead prediction fit % (the filter's
predictions) and free-run simulation fit % (the deterministic mean from x0, no measurement
updates); fit % is MATLAB's `compare` measure.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Collection, Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.stats

from greybox._estimate.likelihood import _newton
from greybox._estimate.metrics import fit_percent
from greybox._estimate.residuals import LjungBox, ljung_box  # the one portmanteau core
from greybox._simulate.simulate import require_x64
from greybox.stochastic._kalman import (
    FilterGrid,
    LinearGaussianSDE,
    free_run,
    kalman_filter,
    log_likelihood,
)

__all__ = [
    "LjungBox",
    "RecordDiagnostics",
    "StochasticFitResult",
    "fit_stochastic",
    "ljung_box",
]

_Z95 = float(scipy.stats.norm.ppf(0.975))


@dataclasses.dataclass(frozen=True)
class RecordDiagnostics:
    """Diagnostics of one record at the fitted parameters (q outputs).

    - `standardised_innovation` (N, q): NaN where the frame was missing.
    - `whiteness`: one `LjungBox` per output.
    - `one_step_fit_percent`, `simulation_fit_percent`: per output, in percent (horizons named).
    - `log_likelihood`: this record's log p(y).
    """

    standardised_innovation: np.ndarray
    whiteness: tuple[LjungBox, ...]
    one_step_fit_percent: tuple[float, ...]
    simulation_fit_percent: tuple[float, ...]
    log_likelihood: float


@dataclasses.dataclass(frozen=True)
class StochasticFitResult:
    """Maximum-likelihood estimate of a stochastic grey-box model.

    - `values`, `standard_errors`, `ci95`: physical values (SI), delta-method standard errors
      and 95 % Wald intervals built in the fitted coordinates (log for `positive` names).
    - `raw`, `raw_cov`: the estimate and inverse-Hessian covariance in fitted coordinates.
    - `hessian_positive_definite`: False means the optimum is not a strict local minimum in
      some direction (an undetermined combination); intervals are then NaN.
    - `model`: the `LinearGaussianSDE` at the estimate.
    - `records`: one `RecordDiagnostics` per record.
    """

    names: tuple[str, ...]
    positive: tuple[str, ...]
    values: dict[str, float]
    standard_errors: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    raw: np.ndarray
    raw_cov: np.ndarray
    hessian_positive_definite: bool
    neg_log_likelihood: float
    n_observations: int
    aic: float
    bic: float
    converged: bool
    message: str
    n_steps: int
    model: LinearGaussianSDE
    records: tuple[RecordDiagnostics, ...]

    def z_scores(self, truth: Mapping[str, float]) -> dict[str, float]:
        """(estimate - truth) / standard error in the fitted coordinates, per named parameter."""
        se = np.sqrt(np.diag(self.raw_cov))
        out = {}
        for i, name in enumerate(self.names):
            if name in truth:
                true_raw = _to_raw(name in self.positive, float(truth[name]))
                out[name] = float((self.raw[i] - true_raw) / se[i])
        return out


def _to_raw(positive: bool, value: float) -> float:
    if positive:
        if not value > 0:
            raise ValueError(f"a positive parameter needs a value > 0, got {value}")
        return float(np.log(value))
    return float(value)


class _SpecObjective(eqx.Module):
    """-log L of the records over the raw vector, in the interface of the likelihood back
    end's optimiser (`greybox._estimate.likelihood._newton`: `total`, `data_nll`, `prior_nll`)."""

    data: list
    build: Callable = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    positive: tuple[bool, ...] = eqx.field(static=True)

    def theta(self, raw):
        return {
            name: (jnp.exp(raw[i]) if pos else raw[i])
            for i, (name, pos) in enumerate(zip(self.names, self.positive))
        }

    def data_nll(self, raw):
        model = self.build(self.theta(raw))
        return -sum(log_likelihood(model, grid, y) for grid, y in self.data)

    def prior_nll(self, raw):
        return jnp.zeros((), raw.dtype)

    def total(self, raw):
        return self.data_nll(raw)


def fit_stochastic(
    build: Callable[[dict[str, jax.Array]], LinearGaussianSDE],
    theta0: Mapping[str, float],
    data: Sequence[tuple[FilterGrid, np.ndarray]],
    *,
    positive: Collection[str] = (),
    max_steps: int = 1000,
    whiteness_lags: int = 20,
    throw: bool = True,
) -> StochasticFitResult:
    """Maximum-likelihood fit of a stochastic grey-box model to one or more records.

    **Main arguments:**

    - `build`: `theta -> LinearGaussianSDE`, with `theta` a dict of scalar JAX arrays in SI
      (e.g. `tau_s`, `gain_K_per_W`, `q_ambient_K2_per_s`, `sigma_K`, `ambient0_K`). It must be
      traceable (jnp operations) and is used as a static (hashable) callable: pass the same
      function object to reuse the compiled fit.
    - `theta0`: initial values {name: value} in SI; every name is fitted.
    - `data`: records `[(FilterGrid, y), ...]`, `y` of shape (N, q) (or (N,)), NaN = missing.
      All records share the model, including its initial state (no per-record parameters).

    **Other arguments:**

    - `positive`: names fitted as log(value) (time constants, intensities, noise levels).
    - `max_steps`: optimiser step limit (per phase: BFGS, then Newton).
    - `whiteness_lags`: lags of the Ljung-Box test.
    - `throw`: raise `RuntimeError` when the optimiser does not report success; with `False`
      the result says `converged=False` and carries the optimiser's message.

    **Returns:** a `StochasticFitResult`.
    """
    require_x64("fit_stochastic")
    names = tuple(theta0)
    unknown = set(positive) - set(names)
    if unknown:
        raise ValueError(f"positive: {sorted(unknown)} are not in theta0 ({list(names)})")
    if isinstance(data, tuple) and len(data) == 2 and isinstance(data[0], FilterGrid):
        data = [data]
    data = [(grid, jnp.asarray(y)) for grid, y in data]
    if not data:
        raise ValueError("data: give at least one (FilterGrid, y) record")
    pos = tuple(name in positive for name in names)
    objective = _SpecObjective(data=data, build=build, names=names, positive=pos)
    raw0 = jnp.asarray([_to_raw(p, float(theta0[n])) for n, p in zip(names, pos)])
    # the one likelihood optimiser (greybox.fit's with ProcessNoise): BFGS, then Newton on
    # the central-difference Hessian of the exact gradient
    out = jax.device_get(_newton(objective, raw0, jnp.asarray(int(max_steps))))
    raw, n_steps, nll = out["raw"], out["steps"], out["data_nll"]
    converged = bool(out["converged"]) and bool(np.all(np.isfinite(raw)))
    message = "successful" if converged else (
        "ran out of steps" if bool(out["ran_out"]) else "stalled (no decreasing step)"
    )
    if throw and not converged:
        raise RuntimeError(f"fit_stochastic: the optimiser did not converge: {message}")
    raw = np.asarray(raw)
    hess = np.asarray(out["hessian"])
    hess = 0.5 * (hess + hess.T)
    pd = bool(np.all(np.isfinite(hess)) and np.all(np.linalg.eigvalsh(hess) > 0))
    cov = np.linalg.inv(hess) if pd else np.full_like(hess, np.nan)
    se_raw = np.sqrt(np.diag(cov))
    values, ses, ci = {}, {}, {}
    for i, (name, p) in enumerate(zip(names, pos)):
        lo, hi = raw[i] - _Z95 * se_raw[i], raw[i] + _Z95 * se_raw[i]
        if p:
            values[name] = float(np.exp(raw[i]))
            ses[name] = float(values[name] * se_raw[i])
            ci[name] = (float(np.exp(lo)), float(np.exp(hi)))
        else:
            values[name] = float(raw[i])
            ses[name] = float(se_raw[i])
            ci[name] = (float(lo), float(hi))
    model = build({k: jnp.asarray(v) for k, v in values.items()})
    records = tuple(_diagnose(model, grid, y, whiteness_lags) for grid, y in data)
    n_obs = int(sum(np.isfinite(np.asarray(y)).sum() for _, y in data))
    nll = float(nll)
    k = len(names)
    return StochasticFitResult(
        names=names,
        positive=tuple(n for n, p in zip(names, pos) if p),
        values=values,
        standard_errors=ses,
        ci95=ci,
        raw=raw,
        raw_cov=cov,
        hessian_positive_definite=pd,
        neg_log_likelihood=nll,
        n_observations=n_obs,
        aic=2 * nll + 2 * k,
        bic=2 * nll + k * float(np.log(n_obs)),
        converged=converged,
        message=message,
        n_steps=int(n_steps),
        model=model,
        records=records,
    )


def _diagnose(model: LinearGaussianSDE, grid: FilterGrid, y, lags: int) -> RecordDiagnostics:
    res = kalman_filter(model, grid, y)
    y = np.asarray(y).reshape(grid.n_frames, -1)
    e = np.asarray(res.standardised_innovation)
    y_one = np.asarray(res.y_pred)
    y_sim = np.asarray(free_run(model, grid)[0])
    q = y.shape[1]
    return RecordDiagnostics(
        standardised_innovation=e,
        whiteness=tuple(ljung_box(e[:, j], lags) for j in range(q)),
        one_step_fit_percent=tuple(fit_percent(y[:, j], y_one[:, j]) for j in range(q)),
        simulation_fit_percent=tuple(fit_percent(y[:, j], y_sim[:, j]) for j in range(q)),
        log_likelihood=float(res.log_likelihood),
    )
