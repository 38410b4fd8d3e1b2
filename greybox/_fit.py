"""Multi-experiment least-squares fitting with honest uncertainty.

`fit(model, experiments, free)` minimises the simulation error (free-run, never one-step
prediction) of every experiment at once with optimistix Levenberg-Marquardt over transformed
parameters (see `greybox._freeparams`), with:

- shared and per-experiment parameters, NaN frames masked out;
- a robust loss (Huber or Student-t) so corrupted frames do not drag the fit;
- optional log-normal priors, appended as extra residuals (a MAP estimate);
- noise scale sigma re-estimated robustly from the residuals (MAD), then the fit is repeated
  at that sigma so that loss thresholds and priors are weighted correctly;
- multi-start from perturbed initial values, keeping the best and reporting the others;
- an inner solve that never aborts: a failed ODE solve yields a large penalty residual, so the
  trust region rejects that step instead of crashing the program.

The result carries the Gauss-Newton covariance, 95 % intervals, correlations, the
identifiability analysis (`greybox._identifiability`) and the simulation fit % per experiment.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from greybox._data import Experiment
from greybox._device import check_method
from greybox._freeparams import FreeParameter
from greybox._identifiability import IdentifiabilityReport, analyse
from greybox._metrics import fit_percent
from greybox._parameters import get_value, set_values
from greybox._simulate import (
    as_arrays,
    observe_schedule,
    pad_schedules,
    require_x64,
    schedule_for,
)

LOSSES = ("l2", "huber", "student_t")
FAILED_SOLVE_RESIDUAL = 1e3  # per residual, in units of sigma: far worse than any real misfit
OUTLIER_SIGMAS = 5.0  # frames further than this from the fit are reported as outliers


def _robust(r, loss: str, c: float, nu: float):
    """Residual transform whose sum of squares is 2 rho(r) for the chosen loss."""
    if loss == "l2":
        return r
    r2 = r**2
    safe = jnp.where(r2 > 0, r2, 1.0)
    if loss == "huber":
        rho2 = jnp.where(jnp.abs(r) <= c, r2, 2 * c * jnp.abs(r) - c**2)
        return r * jnp.where(r2 > 0, jnp.sqrt(rho2 / safe), 1.0)
    rho2 = (nu + 1.0) * jnp.log1p(r2 / nu)  # Student-t negative log-likelihood (x2)
    return r * jnp.where(r2 > 0, jnp.sqrt(rho2 / safe), jnp.sqrt((nu + 1.0) / nu))


@dataclasses.dataclass(frozen=True)
class ParameterEstimate:
    """One fitted value in SI with its standard error and 95 % interval.

    `verdict` is "identifiable", "prior-dominated" or "not identifiable"; for the last, `se`
    and the interval are NaN rather than a confident-looking number.
    """

    name: str
    path: str
    unit: str
    value: float
    se: float
    ci95: tuple[float, float]
    verdict: str
    experiment: str | None = None
    prior: tuple[float, float] | None = None


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Everything a fit established. All fit % are free-run simulation (`horizon`)."""

    model: object
    experiment_models: tuple
    experiments: tuple
    free: tuple
    parameters: tuple
    raw: np.ndarray
    covariance_raw: np.ndarray  # raw coordinates, determined subspace (see identifiability)
    correlation: np.ndarray  # NaN rows/columns for undetermined parameters
    sigma: np.ndarray
    cost: float
    n_data: int
    converged: bool
    message: str
    n_steps: int
    fit_percent: dict  # simulation fit % on every valid frame, per run
    fit_percent_robust: dict  # the same without the frames flagged as outliers
    n_outliers: dict
    identifiability: IdentifiabilityReport
    loss: str
    method: str
    multistart_costs: tuple
    horizon: str = "simulation"

    @property
    def n_params(self) -> int:
        return self.raw.size

    def estimate(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"{name}: not a fitted parameter; have {[p.name for p in self.parameters]}")

    def predict(self, experiment_index: int, method: str | None = None) -> np.ndarray:
        """Free-run simulation of experiment `experiment_index` with its fitted parameters (SI)."""
        from greybox._simulate import simulate

        exp = self.experiments[experiment_index]
        z = simulate(
            self.experiment_models[experiment_index],
            exp.inputs,
            exp.t_s,
            method=method or self.method,
            t_start_s=exp.t_start_s,
        )
        return np.asarray(z).reshape(exp.n_frames, -1)


class _Problem(eqx.Module):
    """Residual function over the raw parameter vector (shared first, then per experiment).

    A PyTree: data arrays and the model are leaves, the parameter specs and settings are
    static, so one compiled solver serves every data set of the same shapes.
    """

    model: object
    sched: dict
    y: jnp.ndarray
    w: jnp.ndarray
    settings: jnp.ndarray  # (E, K) known per-run values for `setting_paths`
    setting_paths: tuple = eqx.field(static=True)
    shared: tuple = eqx.field(static=True)
    per_exp: tuple = eqx.field(static=True)
    n_exp: int = eqx.field(static=True)
    method: str = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    huber_c: float = eqx.field(static=True)
    student_nu: float = eqx.field(static=True)
    solver_opts: tuple = eqx.field(static=True)

    @staticmethod
    def build(model, experiments, free, method, loss, huber_c, student_nu, rtol, atol, max_steps):
        schedules = [
            schedule_for(model, e.inputs, e.t_s, t_start_s=e.t_start_s) for e in experiments
        ]
        sched = pad_schedules(schedules)
        n_exp = len(experiments)
        n_frames = sched["t_s"].shape[1]
        n_y = experiments[0].y.shape[1]
        y = np.zeros((n_exp, n_frames, n_y))
        w = np.zeros_like(y)
        for i, e in enumerate(experiments):
            if e.y.shape[1] != n_y:
                raise ValueError(f"{e.name}: has {e.y.shape[1]} output columns, others {n_y}")
            y[i, : e.n_frames] = np.nan_to_num(e.y)
            w[i, : e.n_frames] = e.mask
        setting_paths = tuple(sorted({k for e in experiments for k in e.settings}))
        settings = np.array(
            [
                [
                    e.settings.get(k, np.asarray(get_value(model, k), dtype=float))
                    for k in setting_paths
                ]
                for e in experiments
            ],
            dtype=float,
        )
        free_paths = {p.path for p in free}
        if free_paths & set(setting_paths):
            raise ValueError(
                f"settings: {sorted(free_paths & set(setting_paths))} are both "
                "fitted and given as known per-run settings; choose one"
            )
        return _Problem(
            model=as_arrays(model),
            sched=sched,
            y=jnp.asarray(y),
            w=jnp.asarray(w),
            settings=jnp.asarray(settings.reshape(n_exp, len(setting_paths))),
            setting_paths=setting_paths,
            shared=tuple(p for p in free if not p.per_experiment),
            per_exp=tuple(p for p in free if p.per_experiment),
            n_exp=n_exp,
            method=method,
            loss=loss,
            huber_c=float(huber_c),
            student_nu=float(student_nu),
            solver_opts=(
                ("rtol", float(rtol)),
                ("atol", float(atol)),
                ("max_steps", int(max_steps)),
            ),
        )

    @property
    def n_data(self) -> int:
        return int(np.asarray(self.w).sum())

    @property
    def priors(self) -> list:
        out = [(k, p) for k, p in enumerate(self.shared) if p.has_prior]
        out += [
            (len(self.shared) + i * len(self.per_exp) + j, p)
            for i in range(self.n_exp)
            for j, p in enumerate(self.per_exp)
            if p.has_prior
        ]
        return out

    @property
    def n_raw(self) -> int:
        return len(self.shared) + self.n_exp * len(self.per_exp)

    @property
    def flat_free(self) -> list:
        """The FreeParameter behind each raw coordinate (shared, then per experiment)."""
        return [*self.shared] + [p for _ in range(self.n_exp) for p in self.per_exp]

    def models(self, raw):
        """(shared model, per-experiment raw block (E, P))."""
        ns = len(self.shared)
        shared_vals = [p.to_value(raw[k]) for k, p in enumerate(self.shared)]
        base = set_values(self.model, [p.path for p in self.shared], shared_vals)
        return base, raw[ns:].reshape(self.n_exp, len(self.per_exp))

    def experiment_model(self, base, per_raw_row, settings_row):
        model = set_values(base, list(self.setting_paths), list(settings_row))
        vals = [p.to_value(per_raw_row[j]) for j, p in enumerate(self.per_exp)]
        return set_values(model, [p.path for p in self.per_exp], vals)

    def predictions(self, raw):
        """Camera readings (E, N, n_y) and per-experiment success flags."""
        base, per = self.models(raw)
        opts = dict(self.solver_opts)

        def one(per_row, settings_row, sched):
            return observe_schedule(
                self.experiment_model(base, per_row, settings_row),
                sched,
                method=self.method,
                **opts,
            )

        return jax.vmap(one)(per, self.settings, self.sched)

    def data_residuals(self, raw, sigma):
        z, ok = self.predictions(raw)
        r = (z - self.y) / sigma * self.w
        return jnp.where(ok[:, None, None], r, FAILED_SOLVE_RESIDUAL * self.w)

    def residuals(self, raw, sigma):
        r = _robust(self.data_residuals(raw, sigma), self.loss, self.huber_c, self.student_nu)
        parts = [r.reshape(-1)]
        if self.priors:
            parts.append(jnp.stack([p.prior_residual(p.to_value(raw[k])) for k, p in self.priors]))
        return jnp.concatenate(parts)


@eqx.filter_jit
def _solve(problem: _Problem, raw_start, sigma, rtol: float, atol: float, max_steps: int):
    """One Levenberg-Marquardt run plus everything the result needs at its end point.

    A single compiled function (the solve, the residuals, the Jacobian and the predictions)
    keeps compile time to one trace of the model. Never throws: the result code says how the
    solve ended.
    """
    lm = optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    sol = optx.least_squares(
        lambda r, s: problem.residuals(r, s),
        lm,
        raw_start,
        args=sigma,
        max_steps=max_steps,
        throw=False,
    )
    raw = sol.value
    z, solved = problem.predictions(raw)
    return dict(
        raw=raw,
        ok=sol.result == optx.RESULTS.successful,
        steps=sol.stats["num_steps"],
        cost=0.5 * jnp.sum(problem.residuals(raw, sigma) ** 2),
        data_residuals=problem.data_residuals(raw, sigma),
        jacobian=jax.jacfwd(lambda r: problem.residuals(r, sigma))(raw),
        predictions=z,
        solved=solved,
    )


def _initial_raw(problem: _Problem, model) -> np.ndarray:
    """Raw start vector: each parameter's `initial` or else the model's value (bounds checked)."""
    raw = []
    for p in problem.flat_free:
        v = p.initial if p.initial is not None else get_value(model, p.path)
        p.check_value(v)
        raw.append(float(p.to_raw(v)))
    return np.asarray(raw)


def _perturbed(problem: _Problem, raw0: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A multi-start point: log/logit parameters moved by ~x2, linear ones left alone."""
    raw = raw0.copy()
    for k, p in enumerate(problem.shared):
        if p.transform != "linear":
            raw[k] += rng.normal(0.0, 0.7)
    return raw


def _robust_sigma(r_scaled: np.ndarray, w: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Per-output noise scale from the median absolute residual (robust to outliers)."""
    out = []
    for j in range(r_scaled.shape[-1]):
        vals = np.abs(r_scaled[..., j][w[..., j] > 0])
        out.append(1.4826 * np.median(vals) * sigma[j])
    return np.maximum(np.asarray(out), 1e-300)


def fit(
    model,
    experiments: Sequence[Experiment],
    free: Sequence[FreeParameter],
    *,
    method: str | None = None,
    loss: str = "huber",
    huber_c: float = 1.5,
    student_nu: float = 4.0,
    sigma: float | Sequence[float] | None = None,
    n_starts: int = 1,
    seed: int = 0,
    max_steps: int = 200,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    solver_rtol: float = 1e-8,
    solver_atol: float = 1e-10,
    solver_max_steps: int = 16384,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Fit `free` parameters of `model` to the estimation `experiments` (free-run simulation error).

    **Main arguments:**
    - `model`: device at its starting values; fields not in `free` stay fixed.
    - `experiments`: runs to fit (their `role` is not consulted; pass estimation runs).
    - `free`: `FreeParameter`s (shared or per-experiment, bounds, priors).

    **Other arguments:**
    - `method`: "zoh" (exact, linear devices) or "adaptive" (diffrax with jump times); None
      = the device's default (ZOH where it is linear).
    - `loss`: "huber" (default; threshold `huber_c` sigmas), "student_t" (`student_nu` dof) or "l2".
    - `sigma`: measurement noise [SI] per output; None estimates it robustly from residuals.
    - `n_starts`, `seed`: multi-start count (>= 1) and its random seed.
    - `max_steps`, `rtol`, `atol`: Levenberg-Marquardt budget and tolerances (raw space).
    - `solver_*`: adaptive ODE solver tolerances and step budget.
    - `progress`: called with a short text line at each stage (the CLI prints it).

    **Returns:** a `FitResult`. A fit that does not converge says so in `converged`/`message`;
    it never presents NaN parameters as a success.
    """
    require_x64("fit")
    experiments = tuple(experiments)
    free = tuple(free)
    say = progress or (lambda _msg: None)
    if not experiments:
        raise ValueError("experiments: zero runs in the estimation set; give at least one")
    if not free:
        raise ValueError("free: no free parameters; list at least one FreeParameter")
    if loss not in LOSSES:
        raise ValueError(f"loss: {loss!r} is unknown; use one of {LOSSES}")
    method = check_method(model, method)
    paths = [p.path for p in free]
    if len(set(paths)) != len(paths):
        raise ValueError(f"free: a parameter is listed twice ({paths})")
    for p in free:
        get_value(model, p.path)  # a clear error for a misspelt path

    problem = _Problem.build(
        model,
        experiments,
        free,
        method,
        loss,
        huber_c,
        student_nu,
        solver_rtol,
        solver_atol,
        solver_max_steps,
    )
    n_y = problem.y.shape[-1]
    if problem.n_data <= problem.n_raw:
        raise ValueError(
            f"experiments: {problem.n_data} valid frames cannot determine "
            f"{problem.n_raw} parameters; add data or free fewer parameters"
        )
    raw0 = _initial_raw(problem, model)

    def solve(raw_start, sig):
        return _solve(problem, raw_start, sig, float(rtol), float(atol), int(max_steps))

    if sigma is None:
        sig = np.full(n_y, _initial_sigma_guess(experiments))
        estimate_sigma = True
    else:
        sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n_y,)).copy()
        if not np.all(sig > 0):
            raise ValueError("sigma: noise scale must be > 0 (SI units of the output)")
        estimate_sigma = False

    rng = np.random.default_rng(seed)
    starts = [raw0] + [_perturbed(problem, raw0, rng) for _ in range(max(n_starts, 1) - 1)]
    runs = []
    for i, start in enumerate(starts):
        say(
            f"start {i + 1}/{len(starts)}: Levenberg-Marquardt ({method}, {loss} loss, "
            f"{problem.n_raw} parameters, {problem.n_data} frames)"
        )
        out = jax.device_get(solve(jnp.asarray(start), jnp.asarray(sig)))
        runs.append(out)
        say(
            f"start {i + 1}/{len(starts)}: cost {float(out['cost']):.6g}, "
            f"{'converged' if out['ok'] else 'not converged'} after {int(out['steps'])} steps"
        )
    finite = [r for r in runs if np.isfinite(r["cost"]) and np.all(np.isfinite(r["raw"]))]
    best = min(finite, key=lambda r: r["cost"]) if finite else runs[0]
    steps = int(best["steps"])

    if estimate_sigma and np.all(np.isfinite(best["raw"])):
        sig = _robust_sigma(np.asarray(best["data_residuals"]), np.asarray(problem.w), sig)
        say(
            f"noise estimated from residuals: sigma = {', '.join(f'{s:.4g}' for s in sig)} (SI); "
            "refitting at that scale"
        )
        best = jax.device_get(solve(jnp.asarray(best["raw"]), jnp.asarray(sig)))
        steps += int(best["steps"])

    return _assemble(problem, best, sig, steps, runs, experiments, free, say)


def _initial_sigma_guess(experiments) -> float:
    """A first noise scale: the spread of frame-to-frame differences (refined after the fit)."""
    diffs = np.concatenate([np.diff(e.y, axis=0).reshape(-1) for e in experiments])
    diffs = diffs[np.isfinite(diffs)]
    scale = 1.4826 * np.median(np.abs(diffs)) / np.sqrt(2) if diffs.size else 0.0
    span = max(np.nanmax(np.abs(e.y)) for e in experiments)
    return float(max(scale, 1e-3 * span, 1e-300))


def _assemble(problem, best, sig, steps, runs, experiments, free, say) -> FitResult:
    raw, cost, ok = np.asarray(best["raw"]), float(best["cost"]), bool(best["ok"])
    raw_j = jnp.asarray(raw)
    finite = bool(np.all(np.isfinite(raw))) and np.isfinite(cost)
    if not finite:
        message = "the fit diverged (non-finite parameters or cost); no estimate is reported"
        ok = False
    elif not ok:
        message = (
            "Levenberg-Marquardt stopped without meeting its tolerances (step budget or "
            "stalled); treat the estimates as unconverged"
        )
    else:
        message = "converged"
    say("computing covariance and identifiability")
    jac = np.asarray(best["jacobian"]) if finite else np.full_like(best["jacobian"], np.nan)
    n_rows_data = jac.shape[0] - len(problem.priors)
    labels, owners = _labels(problem, experiments)
    report = analyse(jac[:n_rows_data], jac[n_rows_data:], problem.flat_free, raw, labels)

    cov = report.covariance_raw
    corr = correlation(report)
    params = parameter_estimates(problem.flat_free, raw, report, labels, owners)
    unidentified = [p.name for p in params if p.verdict == "not identifiable"]
    if ok and unidentified:
        message = (
            f"converged, but {len(unidentified)} parameter(s) are not identifiable from "
            f"these data: {', '.join(unidentified)}"
        )

    base, per = problem.models(raw_j)
    exp_models = tuple(
        problem.experiment_model(base, per[i], problem.settings[i]) for i in range(problem.n_exp)
    )
    z, solved = np.asarray(best["predictions"]), np.asarray(best["solved"])
    fits, robust, outliers = {}, {}, {}
    for i, e in enumerate(experiments):
        fits[e.name], robust[e.name], outliers[e.name] = _scored(e, z[i, : e.n_frames], sig)
    if not bool(np.all(np.asarray(solved))):
        ok, message = False, "an experiment's simulation failed at the final parameters"
    return FitResult(
        model=base,
        experiment_models=exp_models,
        experiments=tuple(experiments),
        free=tuple(free),
        parameters=params,
        raw=raw,
        covariance_raw=cov,
        correlation=corr,
        sigma=np.asarray(sig),
        cost=float(cost),
        n_data=problem.n_data,
        converged=bool(ok),
        message=message,
        n_steps=int(steps),
        fit_percent=fits,
        fit_percent_robust=robust,
        n_outliers=outliers,
        identifiability=report,
        loss=problem.loss,
        method=problem.method,
        multistart_costs=tuple((float(r["cost"]), bool(r["ok"])) for r in runs),
    )


Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def correlation(report: IdentifiabilityReport) -> np.ndarray:
    """Correlation matrix of the raw coordinates (NaN rows/columns where undetermined)."""
    cov = report.covariance_raw
    sd = np.where(report.undetermined, np.nan, np.sqrt(np.clip(np.diag(cov), 0, None)))
    with np.errstate(invalid="ignore", divide="ignore"):
        return cov / np.outer(sd, sd)


def parameter_estimates(
    free_flat, raw, report: IdentifiabilityReport, labels=None, owners=None
) -> tuple:
    """One `ParameterEstimate` per raw coordinate: SI value, delta-method standard error and a
    95 % interval mapped through the transform (so bounds and positivity are respected).

    A parameter reported "not identifiable" (or touching an undetermined direction) gets NaN
    standard error and interval: no confident-looking number for what the data cannot tell.
    """
    cov = report.covariance_raw
    sd_raw = np.where(report.undetermined, np.nan, np.sqrt(np.clip(np.diag(cov), 0, None)))
    out = []
    for k, p in enumerate(free_flat):
        value = float(p.to_value(raw[k]))
        verdict = report.verdicts[k]
        if verdict == "not identifiable" or not np.isfinite(sd_raw[k]):
            se, ci = float("nan"), (float("nan"), float("nan"))
        else:
            se = abs(p.value_derivative(raw[k])) * sd_raw[k]
            lo, hi = (float(p.to_value(raw[k] + s * Z95 * sd_raw[k])) for s in (-1, 1))
            ci = (min(lo, hi), max(lo, hi))
        prior = (p.prior_median, p.prior_log_sd) if p.has_prior else None
        label = labels[k] if labels is not None else p.path
        owner = owners[k] if owners is not None else None
        out.append(ParameterEstimate(label, p.path, p.unit, value, se, ci, verdict, owner, prior))
    return tuple(out)


def _labels(problem, experiments):
    """Display name and owning experiment (None if shared) of each raw coordinate."""
    labels = [p.path for p in problem.shared]
    owners = [None] * len(problem.shared)
    for e in experiments:
        labels += [f"{p.path}[{e.name}]" for p in problem.per_exp]
        owners += [e.name] * len(problem.per_exp)
    return labels, owners


@dataclasses.dataclass(frozen=True)
class ValidationResult:
    """Free-run simulation of runs not used for fitting (physical parameters held fixed).

    Only per-run nuisance parameters (offsets, drift, initial state) are re-estimated on each
    validation run, as MATLAB `compare` estimates initial conditions; `fit_percent` is
    simulation fit %, never one-step prediction.
    """

    experiments: tuple
    predictions: tuple  # (N, n_y) SI per run
    fit_percent: dict  # every valid frame
    fit_percent_robust: dict  # without the frames flagged as outliers
    n_outliers: dict
    horizon: str = "simulation"


def validate(
    result: FitResult, experiments: Sequence[Experiment], **fit_kwargs
) -> ValidationResult:
    """Score fitted physics on new runs: re-fit only per-experiment parameters, then simulate."""
    per_exp = [p for p in result.free if p.per_experiment]
    experiments = tuple(experiments)
    if not experiments:
        raise ValueError("experiments: no validation runs given")
    if not per_exp:
        preds, fits, robust, outl = [], {}, {}, {}
        for e in experiments:
            from greybox._simulate import simulate

            z = np.asarray(
                simulate(
                    e.apply_settings(result.model),
                    e.inputs,
                    e.t_s,
                    method=result.method,
                    t_start_s=e.t_start_s,
                )
            ).reshape(e.n_frames, -1)
            preds.append(z)
            fits[e.name], robust[e.name], outl[e.name] = _scored(e, z, result.sigma)
        return ValidationResult(experiments, tuple(preds), fits, robust, outl)
    fit_kwargs.setdefault("method", result.method)
    fit_kwargs.setdefault("loss", result.loss)
    fit_kwargs.setdefault("sigma", result.sigma)
    nuisance = fit(result.model, experiments, per_exp, **fit_kwargs)
    preds = tuple(nuisance.predict(i) for i in range(len(experiments)))
    return ValidationResult(
        experiments, preds, nuisance.fit_percent, nuisance.fit_percent_robust, nuisance.n_outliers
    )


def _scored(e: Experiment, z: np.ndarray, sigma) -> tuple[float, float, int]:
    """(simulation fit % on every valid frame, fit % without the frames more than
    OUTLIER_SIGMAS from the model, the number of such frames).

    The first is MATLAB `compare`'s figure and the honest headline: a model that drifts away
    from the data loses fit % for it. The second shows what a few corrupted camera frames
    cost; reports label both.
    """
    flagged = (np.abs((e.y - z) / sigma) > OUTLIER_SIGMAS) & e.mask

    def score(y):
        return fit_percent(y, z) if np.isfinite(y).sum() > 1 else float("nan")

    return score(e.y), score(np.where(flagged, np.nan, e.y)), int(np.sum(flagged))
