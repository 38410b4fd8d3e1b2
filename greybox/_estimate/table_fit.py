"""Least-squares fit of physical parameters to a static table (no time series).

For data such as an amplitude-frequency-displacement table (periodic steady states) or forces
against DC voltage, the prediction is a pure function `predict(model, x) -> (N,)` [SI] instead
of a simulated trajectory. The fit reuses the core pieces of `greybox._estimate.fit`:

- `FreeParameter` transforms (log/logit/linear) and log-normal priors (extra residuals);
- optimistix Levenberg-Marquardt on the raw (transformed) vector;
- the Gauss-Newton covariance and identifiability verdicts of
  `greybox._estimate.identifiability.analyse` from the weighted Jacobian, reported as
  `greybox._estimate.fit.ParameterEstimate` rows.

Noise: `sigma` known (scalar or per row, e.g. standard errors of averaged repeats), or estimated
as sqrt(RSS / (n - p)) (the unbiased Gaussian estimate) and the covariance scaled by it.
`weights` (0/1 or relative) mask rows, e.g. for leave-one-out cross-validation without
changing array shapes (so one compiled solver serves every fold).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._estimate.fit import ParameterEstimate, correlation, parameter_estimates
from greybox._estimate.identifiability import IdentifiabilityReport, analyse
from greybox._estimate.metrics import r_squared, rmse
from greybox._model.freeparams import FreeParameter, apply_raw, as_leaves, levenberg_marquardt
from greybox._model.parameters import get_value
from greybox._simulate.simulate import as_arrays, require_x64


class _TableProblem(eqx.Module):
    """Residuals over the raw vector of the shared free parameters."""

    model: object
    x: object
    y: jnp.ndarray
    w: jnp.ndarray
    shared: tuple  # FreeParameters with array numbers (`as_leaves`): inputs, not structure
    predict: Callable = eqx.field(static=True)

    def model_at(self, raw):
        return apply_raw(self.model, self.shared, raw)

    def data_residuals(self, raw, sigma):
        return (self.predict(self.model_at(raw), self.x) - self.y) / sigma * self.w

    def residuals(self, raw, sigma):
        priors = [
            p.prior_residual(p.to_value(raw[k])) for k, p in enumerate(self.shared) if p.has_prior
        ]
        r = self.data_residuals(raw, sigma)
        return jnp.concatenate([r, jnp.stack(priors)]) if priors else r


@jit
def _solve(problem: _TableProblem, raw0, sigma, rtol: float, atol: float, max_steps: int):
    raw, ok, steps, _ = levenberg_marquardt(  # no stall stop: a table fit is cheap
        problem.residuals, raw0, sigma, rtol=rtol, atol=atol, max_steps=max_steps,
        stall_window=None,
    )
    return dict(
        raw=raw,
        ok=ok,
        steps=steps,
        jacobian=jax.jacfwd(lambda r: problem.residuals(r, sigma))(raw),
        prediction=problem.predict(problem.model_at(raw), problem.x),
    )


@dataclasses.dataclass(frozen=True)
class TableFitResult:
    """A static-table fit. `prediction` is the model's steady-state output (a simulation of the
    physics at each table point, no measured values fed back): `horizon` says so."""

    model: object
    free: tuple
    parameters: tuple
    raw: np.ndarray
    covariance_raw: np.ndarray
    correlation: np.ndarray
    sigma: np.ndarray
    sigma_estimated: bool
    cost: float
    n_data: int
    converged: bool
    message: str
    n_steps: int
    identifiability: IdentifiabilityReport
    prediction: np.ndarray
    residuals: np.ndarray
    rmse: float
    r_squared: float
    horizon: str = "steady-state simulation"

    def estimate(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"{name}: not a fitted parameter; have {[p.name for p in self.parameters]}")


def fit_table(
    model,
    predict: Callable,
    x,
    y,
    free: Sequence[FreeParameter],
    *,
    sigma=None,
    weights=None,
    max_steps: int = 200,
    rtol: float = 1e-8,
    atol: float = 1e-10,
) -> TableFitResult:
    """Fit `free` parameters of `model` so that `predict(model, x)` matches `y` (SI).

    **Arguments:**
    - `predict`: pure JAX function (model, x) -> (N,) [SI]; keep the same function object across
      calls to reuse the compiled solver (e.g. `greybox._simulate.periodic.response_function`).
    - `x`: the table's inputs (any PyTree of arrays, e.g. (amplitude_V, frequency_Hz)).
    - `y`: measured values (N,) [SI], finite.
    - `free`: shared `FreeParameter`s (per-experiment parameters have no meaning here).
    - `sigma`: known noise sd (scalar or (N,)) [SI]; None estimates one scalar from the residuals.
    - `weights`: (N,) >= 0 multipliers of the residuals (0 = row left out).

    **Returns:** a `TableFitResult` with intervals and identifiability verdicts.
    """
    require_x64("fit_table")
    free = tuple(free)
    y = np.asarray(y, dtype=float).reshape(-1)
    if not free:
        raise ValueError("free: no free parameters; list at least one FreeParameter")
    if any(p.per_experiment for p in free):
        raise ValueError(
            "free: per_experiment parameters need several experiments; a table fit has one"
        )
    if not np.all(np.isfinite(y)):
        raise ValueError("y: contains NaN or inf; drop those table rows")
    w = np.ones_like(y) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    if w.shape != y.shape or np.any(~np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights: need one finite value >= 0 per row")
    n_data = int(np.sum(w > 0))
    if n_data <= len(free):
        raise ValueError(
            f"y: {n_data} rows cannot determine {len(free)} parameters; add data or "
            "free fewer parameters"
        )
    raw0 = []
    for p in free:
        v = p.initial if p.initial is not None else get_value(model, p.path)
        p.check_value(v)
        raw0.append(float(p.to_raw(v)))
    raw0 = jnp.asarray(raw0)
    problem = _TableProblem(
        model=as_arrays(model),
        x=jax.tree.map(jnp.asarray, x),
        y=jnp.asarray(y),
        w=jnp.asarray(w),
        shared=as_leaves(free),
        predict=predict,
    )
    has_priors = any(p.has_prior for p in free)
    estimate = sigma is None
    sig = np.std(y[w > 0]) * 1e-2 + 1e-300 if estimate else np.asarray(sigma, dtype=float)
    if not estimate and not np.all(sig > 0):
        raise ValueError("sigma: noise sd must be > 0 (SI units of y)")
    sig = np.broadcast_to(sig, y.shape).astype(float)

    def solve(start, s):
        return jax.device_get(
            _solve(problem, start, jnp.asarray(s), float(rtol), float(atol), int(max_steps))
        )

    out = solve(raw0, sig)
    steps = int(out["steps"])
    raw = np.asarray(out["raw"])
    resid_w = (np.asarray(out["prediction"]) - y) * w
    if estimate and np.all(np.isfinite(raw)):
        s_hat = float(np.sqrt(np.sum(resid_w**2) / (n_data - len(free))))
        scale = sig[0] / max(s_hat, 1e-300)
        sig = np.full_like(sig, max(s_hat, 1e-300))
        if has_priors:  # the prior's weight against the data depends on sigma: refit
            out = solve(jnp.asarray(raw), sig)
            steps += int(out["steps"])
            raw = np.asarray(out["raw"])
        else:  # the L2 optimum does not depend on sigma; only the data rows rescale
            out["jacobian"] = np.asarray(out["jacobian"]) * scale
    jac = np.asarray(out["jacobian"])
    n_rows = y.size
    finite = bool(np.all(np.isfinite(raw)) and np.all(np.isfinite(jac)))
    report = analyse(jac[:n_rows], jac[n_rows:], free, raw, [p.path for p in free])
    cov = report.covariance_raw
    corr = correlation(report)
    pred = np.asarray(out["prediction"])
    ok = bool(out["ok"]) and finite
    message = (
        "converged"
        if ok
        else (
            "diverged: non-finite parameters"
            if not finite
            else "Levenberg-Marquardt stopped without meeting its tolerances"
        )
    )
    keep = w > 0
    cost = 0.5 * float(np.sum(((pred - y) * w / sig) ** 2))
    return TableFitResult(
        model=problem.model_at(jnp.asarray(raw)),
        free=free,
        parameters=parameter_estimates(free, raw, report),
        raw=raw,
        covariance_raw=cov,
        correlation=corr,
        sigma=sig,
        sigma_estimated=estimate,
        cost=cost,
        n_data=n_data,
        converged=ok,
        message=message,
        n_steps=steps,
        identifiability=report,
        prediction=pred,
        residuals=y - pred,
        rmse=rmse(y[keep], pred[keep]),
        r_squared=r_squared(y[keep], pred[keep]),
    )
