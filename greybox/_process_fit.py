"""Maximum-likelihood fits of stochastic devices (`greybox._sde_device`): the same free
parameters, bounds, priors, covariance, verdicts and per-run diagnostics as `greybox.fit`.

`fit_process` maximises the likelihood (scipy's BFGS over the raw coordinates of the free
parameters, log-normal priors added, driven from the host over one compiled value-and-gradient
of the filter, so a fit compiles the filter's gradient once) and reports covariance (inverse
observed information: the Hessian by central differences of that exact gradient, 4.7e-9
relative from forward-over-forward AD on the TCLab test case), identifiability verdicts, and
per run: the innovations' whiteness (Ljung-Box per output), simulation (free-run,
deterministic), one-step and k-step prediction fit %, each labelled.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox._data import Experiment
from greybox._fit import ParameterEstimate, parameter_estimates
from greybox._freeparams import FreeParameter, apply_raw
from greybox._identifiability import analyse
from greybox._metrics import fit_percent
from greybox._parameters import get_value, set_values
from greybox._sde_device import (
    _NOISE_FIELDS,
    DEFAULT_K_STEP,
    LIKELIHOOD,
    StochasticDevice,
    _grid,
    _record_loglik,
    _run_arrays,
    _t0,
)
from greybox._simulate import as_arrays, require_x64
from greybox._stochastic import ljung_box

__all__ = ["ProcessFitResult", "RunDiagnostics", "fit_process", "validate_process"]


class _Problem(eqx.Module):
    model: StochasticDevice
    grids: tuple
    t_s: tuple
    t0: tuple
    y: tuple
    settings: jnp.ndarray  # (E, K)
    setting_paths: tuple = eqx.field(static=True)
    shared: tuple = eqx.field(static=True)
    per_exp: tuple = eqx.field(static=True)
    n_exp: int = eqx.field(static=True)

    @staticmethod
    def build(model, experiments, free):
        setting_paths = tuple(sorted({k for e in experiments for k in e.settings}))
        settings = np.array(
            [
                [e.settings.get(k, float(get_value(model, k))) for k in setting_paths]
                for e in experiments
            ],
            dtype=float,
        ).reshape(len(experiments), len(setting_paths))
        clash = {p.path for p in free} & set(setting_paths)
        if clash:
            raise ValueError(
                f"settings: {sorted(clash)} are both fitted and given as known per-run "
                "settings; choose one"
            )
        return _Problem(
            model=as_arrays(model),
            grids=tuple(_grid(e) for e in experiments),
            t_s=tuple(jnp.asarray(e.t_s) for e in experiments),
            t0=tuple(jnp.asarray(_t0(e)) for e in experiments),
            y=tuple(jnp.asarray(e.y) for e in experiments),
            settings=jnp.asarray(settings),
            setting_paths=setting_paths,
            shared=tuple(p for p in free if not p.per_experiment),
            per_exp=tuple(p for p in free if p.per_experiment),
            n_exp=len(experiments),
        )

    @property
    def flat_free(self) -> list:
        return [*self.shared] + [p for _ in range(self.n_exp) for p in self.per_exp]

    @property
    def n_raw(self) -> int:
        return len(self.shared) + self.n_exp * len(self.per_exp)

    def run_model(self, raw, i: int):
        ns, npr = len(self.shared), len(self.per_exp)
        base = apply_raw(self.model, self.shared, raw)
        m = set_values(base, list(self.setting_paths), list(self.settings[i]))
        return apply_raw(m, self.per_exp, raw[ns + i * npr : ns + (i + 1) * npr])

    def data_nll(self, raw):
        total = 0.0
        for i in range(self.n_exp):
            m = self.run_model(raw, i)
            total = total - _record_loglik(m, self.grids[i], self.t_s[i], self.t0[i], self.y[i])
        return total

    def prior_rows(self, raw):
        rows = [
            p.prior_residual(p.to_value(raw[k]))
            for k, p in enumerate(self.flat_free)
            if p.has_prior
        ]
        return jnp.stack(rows) if rows else jnp.zeros(0, raw.dtype)

    def nll(self, raw):
        r = self.prior_rows(raw)
        return self.data_nll(raw) + 0.5 * jnp.sum(r**2)


_FD_STEP = 1e-4  # raw-coordinate step of the central differences of the gradient


@eqx.filter_jit
def _data_value_and_grad(problem: _Problem, raw):
    """-log L (data term) and its gradient: the one compiled function of a fit."""
    return jax.value_and_grad(problem.data_nll)(raw)


@eqx.filter_jit
def _prior_terms(problem: _Problem, raw):
    """(0.5 |r|^2, its gradient, J = dr/draw) of the priors' residuals r."""

    def half(r):
        rows = problem.prior_rows(r)
        return 0.5 * jnp.sum(rows**2)

    v, g = jax.value_and_grad(half)(raw)
    return v, g, jax.jacfwd(problem.prior_rows)(raw)


def _hessian(vg, raw):
    """Hessian of the function whose (value, gradient) is `vg` by central differences of the
    exact (reverse-mode) gradient, 2 P calls of the already compiled `vg`.

    A raw step of 1e-4 makes the Hessian accurate to ~1e-8 relative (4.7e-9 against
    forward-over-forward AD, `benchmarks/kalman.py --coverage-device`), far below what
    standard errors need, and costs no second compilation through the filter's scan."""
    raw = np.asarray(raw, dtype=float)
    p = raw.size
    hess = np.empty((p, p))
    for k in range(p):
        step = np.zeros(p)
        step[k] = _FD_STEP
        g_hi = np.asarray(vg(raw + step)[1])
        g_lo = np.asarray(vg(raw - step)[1])
        hess[:, k] = (g_hi - g_lo) / (2 * _FD_STEP)
    return 0.5 * (hess + hess.T)


def _solve(problem: _Problem, raw0, max_steps: int, gtol: float):
    """BFGS (scipy, Wolfe line search) on -log L + priors, driven from the host over the
    compiled value-and-gradient; then the data term's Hessian at the optimum."""
    import scipy.optimize as so

    n_prior = sum(1 for p in problem.flat_free if p.has_prior)

    def data_vg(r):
        v, g = _data_value_and_grad(problem, jnp.asarray(r))
        return float(v), np.asarray(g, dtype=float)

    def total(r):
        v, g = data_vg(r)
        if n_prior:
            pv, pg, _ = _prior_terms(problem, jnp.asarray(r))
            v, g = v + float(pv), g + np.asarray(pg)
        if not (np.isfinite(v) and np.all(np.isfinite(g))):
            return np.inf, np.zeros_like(g)
        return v, g

    with np.errstate(invalid="ignore", over="ignore"):
        sol = so.minimize(
            total,
            np.asarray(raw0, dtype=float),
            jac=True,
            method="BFGS",
            options={"gtol": float(gtol), "maxiter": int(max_steps)},
        )
    raw = np.asarray(sol.x, dtype=float)
    data_nll, grad = data_vg(raw)
    g_total = total(raw)[1]
    # scipy stops with "precision loss" when the line search can no longer decrease a
    # function that is flat to rounding: at the optimum when the gradient is small there too
    converged = bool(sol.success) or (
        sol.status == 2 and float(np.max(np.abs(g_total), initial=0.0)) <= 100 * gtol
    )
    hess = _hessian(data_vg, raw)
    if n_prior:
        jac_prior = np.asarray(_prior_terms(problem, jnp.asarray(raw))[2])
    else:
        jac_prior = np.zeros((0, raw.size))
    return dict(
        raw=raw,
        converged=converged,
        message="successful" if converged else str(sol.message),
        steps=int(sol.nit),
        data_nll=data_nll,
        hess=hess,
        jac_prior=jac_prior,
    )


@dataclasses.dataclass(frozen=True)
class RunDiagnostics:
    """One run at the fitted parameters (q outputs), every number labelled by its horizon.

    - `log_likelihood`; `whiteness`: Ljung-Box of the standardised innovations per output;
    - `one_step_fit_percent`, `simulation_fit_percent`, `k_step_fit_percent` (per output, %;
      the k-step-ahead prediction `k_step` frames ahead);
    - `y_one_step`, `y_simulation`, `y_k_step` (N, q) readings [SI]; `y_simulation_sd` with
      process noise.
    """

    name: str
    role: str
    log_likelihood: float
    whiteness: tuple
    one_step_fit_percent: tuple
    simulation_fit_percent: tuple
    k_step: int
    k_step_fit_percent: tuple
    y_one_step: np.ndarray
    y_simulation: np.ndarray
    y_k_step: np.ndarray
    y_simulation_sd: np.ndarray
    standardised_innovation: np.ndarray

    @property
    def horizons(self) -> tuple:
        """((label, predictions (N, q), fit % per output), ...): simulation, one-step and
        k-step prediction, each labelled."""
        return (
            ("simulation", self.y_simulation, self.simulation_fit_percent),
            ("one-step prediction", self.y_one_step, self.one_step_fit_percent),
            (f"{self.k_step}-step prediction", self.y_k_step, self.k_step_fit_percent),
        )

    @property
    def white(self) -> bool:
        return all(w.p_value > 0.01 for w in self.whiteness)


@dataclasses.dataclass(frozen=True)
class ProcessFitResult:
    """A maximum-likelihood fit of a `StochasticDevice` (`likelihood` says which).

    - `model`: the stochastic device at the shared estimates; `experiment_models`: per run
      (settings and per-run estimates applied); `free`, `raw`, `covariance_raw` (inverse
      observed information, data + priors, determined subspace), `parameters`
      (`ParameterEstimate`s, as `greybox.fit`'s), `identifiability`.
    - `neg_log_likelihood` (data term), `aic`, `bic`, `n_observations`;
    - `converged`, `message`, `n_steps`, `status` ("converged", "at bound", "not converged"),
      `valid`;
    - `runs`: `RunDiagnostics` per estimation run.
    """

    model: StochasticDevice
    experiment_models: tuple
    experiments: tuple
    free: tuple
    parameters: tuple
    raw: np.ndarray
    covariance_raw: np.ndarray
    identifiability: object
    neg_log_likelihood: float
    n_observations: int
    aic: float
    bic: float
    converged: bool
    message: str
    n_steps: int
    status: str
    runs: tuple
    likelihood: str = LIKELIHOOD

    @property
    def valid(self) -> bool:
        return self.status == "converged"

    @property
    def filter_name(self) -> str:
        return "extended Kalman filter" if self.model.use_ekf else "Kalman filter (exact)"

    def estimate(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"{name}: not a fitted parameter; have {[p.name for p in self.parameters]}")

    def z_scores(self, truth: dict) -> dict:
        """(estimate - truth) / se in raw coordinates, per shared parameter path in `truth`."""
        out = {}
        sd = np.sqrt(np.clip(np.diag(self.covariance_raw), 0, None))
        for k, p in enumerate(self.free):
            if not p.per_experiment and p.path in truth:
                out[p.path] = float((self.raw[k] - float(p.to_raw(truth[p.path]))) / sd[k])
        return out


def _start_noise(model: StochasticDevice, experiments, free) -> StochasticDevice:
    """Data-based starting values for the free noise parameters left at their default 1.

    Measurement sd: the robust spread of frame-to-frame differences / sqrt 2 per output;
    intensities: 0.1 sd^2 / (median frame interval), the noise per frame, a tenth of it."""
    diffs, dts = [], []
    for e in experiments:
        diffs.append(np.diff(e.y, axis=0))
        dts.append(np.diff(e.t_s))
    d = np.concatenate(diffs)
    sd = np.array(
        [1.4826 * np.nanmedian(np.abs(d[:, j] - np.nanmedian(d[:, j]))) for j in range(d.shape[1])]
    ) / np.sqrt(2)
    spread = np.array(
        [np.nanstd(np.concatenate([e.y[:, j] for e in experiments])) for j in range(d.shape[1])]
    )
    # quantised, slowly moving readings can have a zero median difference: their RMS then
    rms = np.array([np.sqrt(np.nanmean(d[:, j] ** 2)) for j in range(d.shape[1])]) / np.sqrt(2)
    sd = np.where(np.isfinite(sd) & (sd > 0), sd, rms)
    sd = np.where(np.isfinite(sd) & (sd > 0), sd, np.maximum(1e-3 * spread, 1e-12))
    dt = float(np.median(np.concatenate(dts))) if np.concatenate(dts).size else 1.0
    paths, vals = [], []
    free_paths = {p.path: p for p in free}
    for path, p in free_paths.items():
        field, _, name = path.partition(".")
        if field not in _NOISE_FIELDS or p.initial is not None:
            continue
        if field == "measurement":
            j = model.measurement.names.index(name)
            v = sd[j]
        else:
            v = 0.1 * float(np.mean(sd)) ** 2 / dt
        paths.append(path)
        vals.append(float(v))
    return set_values(model, paths, vals)


def fit_process(
    model: StochasticDevice,
    experiments: Sequence[Experiment],
    free: Sequence[FreeParameter],
    *,
    max_steps: int = 2000,
    gtol: float = 1e-6,
    whiteness_lags: int = 20,
    k_step: int = DEFAULT_K_STEP,
    start_noise: bool = True,
    progress: Callable[[str], None] | None = None,
) -> ProcessFitResult:
    """Maximum-likelihood fit of a stochastic device to the estimation `experiments`.

    **Arguments:**

    - `model`: a `StochasticDevice` (`stochastic_device(device, structure, ...)`).
    - `experiments`: runs (settings applied per run; NaN readings are dropped frames).
    - `free`: `FreeParameter`s over device paths and noise paths (`noise_parameters(model)`
      lists the noise ones); shared or per run, bounds, priors as in `greybox.fit`.
    - `max_steps`, `gtol`: BFGS iteration budget and gradient tolerance (largest |d(-log L)/d
      raw|; raw coordinates are scaled so that 1e-6 is far below a standard error).
    - `whiteness_lags`: lags of the Ljung-Box test on the innovations.
    - `k_step`: the horizon (frames) of the k-step-ahead prediction fit % in the diagnostics.
    - `start_noise`: start free noise parameters without `initial` from the data (the
      measurement sd from frame-to-frame differences, intensities a tenth of it per frame).

    **Returns:** a `ProcessFitResult`.
    """
    require_x64("fit_process")
    say = progress or (lambda _m: None)
    experiments = tuple(experiments)
    free = tuple(free)
    if not experiments:
        raise ValueError("experiments: give at least one run")
    if not free:
        raise ValueError("free: no free parameters")
    paths = [p.path for p in free]
    if len(set(paths)) != len(paths):
        raise ValueError(f"free: a parameter is listed twice ({paths})")
    for p in free:
        get_value(model, p.path)
    if start_noise:
        model = _start_noise(model, experiments, free)
    starts = [p.initial if p.initial is not None else float(get_value(model, p.path)) for p in free]
    free = tuple(p.with_scale_from(v) for p, v in zip(free, starts))
    problem = _Problem.build(model, experiments, free)
    raw0 = []
    for p in problem.flat_free:
        v = p.initial if p.initial is not None else float(get_value(model, p.path))
        p.check_value(v)
        raw0.append(float(p.to_raw(v)))
    raw0 = jnp.asarray(raw0)
    say(
        f"maximum likelihood ({'extended Kalman filter' if model.use_ekf else 'Kalman filter'}"
        f", {problem.n_raw} parameters, {len(experiments)} runs)"
    )
    out = _solve(problem, raw0, int(max_steps), float(gtol))
    raw = np.asarray(out["raw"])
    converged = out["converged"]
    message = out["message"]
    say(f"-log L = {float(out['data_nll']):.6g} after {int(out['steps'])} BFGS steps ({message})")
    flat = problem.flat_free
    labels, owners = [p.path for p in problem.shared], [None] * len(problem.shared)
    for e in experiments:
        labels += [f"{p.path}[{e.name}]" for p in problem.per_exp]
        owners += [e.name] * len(problem.per_exp)
    bounds = [p.bound_hit(raw[k], raw0[k]) for k, p in enumerate(flat)]
    hess = np.asarray(out["hess"])
    hess = 0.5 * (hess + hess.T)
    if np.all(np.isfinite(hess)):
        vals, vecs = np.linalg.eigh(hess)
        jac_data = np.sqrt(np.clip(vals, 0, None))[:, None] * vecs.T
    else:
        jac_data = np.full_like(hess, np.nan)
    report = analyse(jac_data, np.asarray(out["jac_prior"]), flat, raw, labels, bounds)
    params = parameter_estimates(flat, raw, report, labels, owners)
    n_obs = int(sum(int(np.isfinite(e.y).sum()) for e in experiments))
    nll = float(out["data_nll"])
    k = raw.size
    status = "converged" if converged and np.all(np.isfinite(raw)) else "not converged"
    if status == "converged" and any(b is not None for b in bounds):
        status = "at bound"
    base = apply_raw(problem.model, problem.shared, jnp.asarray(raw))
    run_models = tuple(problem.run_model(jnp.asarray(raw), i) for i in range(len(experiments)))
    runs = tuple(
        _diagnose(m_i, e, "estimation", whiteness_lags, k_step, settings_applied=True)
        for m_i, e in zip(run_models, experiments)
    )
    return ProcessFitResult(
        model=base,
        experiment_models=run_models,
        experiments=experiments,
        free=free,
        parameters=params,
        raw=raw,
        covariance_raw=np.asarray(report.covariance_raw),
        identifiability=report,
        neg_log_likelihood=nll,
        n_observations=n_obs,
        aic=2 * nll + 2 * k,
        bic=2 * nll + k * float(np.log(n_obs)),
        converged=converged,
        message=message,
        n_steps=int(out["steps"]),
        status=status,
        runs=runs,
    )


def _diagnose(model, e: Experiment, role: str, lags: int, k_step: int, settings_applied=False):
    m = model if settings_applied else e.apply_settings(model)
    m = as_arrays(m)
    ll, yp, sd1, ys, sds, _, yk, _ = _run_arrays(m, e, k_step)
    y = np.asarray(e.y)
    yp, ys, yk = np.asarray(yp), np.asarray(ys), np.asarray(yk)
    z = (y - yp) / np.asarray(sd1)
    q = y.shape[1]
    return RunDiagnostics(
        name=e.name,
        role=role,
        log_likelihood=float(ll),
        whiteness=tuple(ljung_box(z[:, j], lags) for j in range(q)),
        one_step_fit_percent=tuple(fit_percent(y[:, j], yp[:, j]) for j in range(q)),
        simulation_fit_percent=tuple(fit_percent(y[:, j], ys[:, j]) for j in range(q)),
        k_step=int(k_step),
        k_step_fit_percent=tuple(fit_percent(y[:, j], yk[:, j]) for j in range(q)),
        y_one_step=yp,
        y_simulation=ys,
        y_k_step=yk,
        y_simulation_sd=np.asarray(sds),
        standardised_innovation=z,
    )


def validate_process(
    result: ProcessFitResult,
    experiments: Sequence[Experiment],
    *,
    whiteness_lags: int = 20,
    k_step: int = DEFAULT_K_STEP,
) -> tuple:
    """Diagnostics of new runs at the fitted shared parameters (`RunDiagnostics` each, role
    "validation"): per-run free parameters, if any, are re-fitted on each run (physics and
    noise fixed), as `greybox.validate` does."""
    per = tuple(p for p in result.free if p.per_experiment)
    out = []
    for e in experiments:
        m = result.model
        if per:
            sub = fit_process(
                m, [e], per, start_noise=False, whiteness_lags=whiteness_lags, k_step=k_step
            )
            out.append(dataclasses.replace(sub.runs[0], role="validation"))
            continue
        out.append(_diagnose(m, e, "validation", whiteness_lags, k_step))
    return tuple(out)
