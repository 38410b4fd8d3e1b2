"""Multi-experiment least-squares fitting with honest uncertainty.

`fit(model, experiments, free)` minimises the simulation error (free-run, never one-step
prediction) of every experiment at once with optimistix Levenberg-Marquardt over transformed
parameters (see `greybox._model.freeparams`), with:

- shared and per-experiment parameters, NaN frames masked out;
- a robust loss (Huber or Student-t) so corrupted frames do not drag the fit;
- optional log-normal priors, appended as extra residuals (a MAP estimate);
- noise scale sigma re-estimated robustly from the residuals (MAD), then the fit is repeated
  at that sigma so that loss thresholds and priors are weighted correctly; or a known noise
  level (`Experiment.sigma` per frame, or `sigma=`), which weights the readings, is never
  re-estimated, and is tested against the residuals (chi-square goodness of fit);
- multi-start from perturbed initial values (on by default when more than two shared
  parameters are free), keeping the best and saying when the starting values led elsewhere;
- an inner solve that never aborts: a failed ODE solve yields a large penalty residual, so the
  trust region rejects that step instead of crashing the program.

The result carries a `status` ("converged", "local optimum", "at bound", "not converged",
"diverged") and `valid` (the estimate is an interior optimum the optimiser reached); the
Gauss-Newton covariance and, beside it, the Newey-West (HAC) sandwich covariance, which is
the headline when the residuals are not white (`se_method`); 95 % intervals, correlations,
the identifiability analysis (`greybox._estimate.identifiability`); per run and per output the
simulation fit %, its noise ceiling and the residual analysis (`greybox._estimate.residuals`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._estimate import problem as _problem
from greybox._estimate.blas import small_blas
from greybox._estimate.identifiability import RANK_TOL, IdentifiabilityReport, analyse
from greybox._estimate.metrics import (
    OUTLIER_SIGMAS,
    fit_percent_per_output,
    noise_ceiling_per_output,
)
from greybox._estimate.posterior import Posterior
from greybox._estimate.residuals import (
    GoodnessOfFit,
    ResidualAnalysis,
    _sorted_median,
    goodness_of_fit,
    padded_stack,
)
from greybox._estimate.residuals import analyse as analyse_residuals
from greybox._estimate.sandwich import HACMeat, hac_meats, model_error_residuals_many
from greybox._estimate.starts import run_starts
from greybox._estimate.verdict import interval_verdict
from greybox._model.data import Experiment
from greybox._model.device import check_method
from greybox._model.freeparams import (
    STALL_RTOL,
    STALL_RTOL_AT_BOUND,
    STALL_WINDOW,
    FreeParameter,
    apply_raw,
    as_leaves,
    levenberg_marquardt,
    pinned_fn,
    step_bound,
)
from greybox._simulate.schedules import schedules_for
from greybox._simulate.simulate import (
    SOLVER_FAILED,
    SolverFailed,
    as_arrays,
    observe_schedule,
    require_x64,
)

LOSSES = ("l2", "huber", "student_t")
FAILED_SOLVE_RESIDUAL = 1e3  # per residual, in units of sigma: far worse than any real misfit
AUTO_STARTS = _problem.AUTO_STARTS  # starts when n_starts=None and > 2 shared parameters
# A start the stall test stopped in the interior has converged when the Gauss-Newton step
# still to take is below this decrement g' H^-1 g: the step's squared length in standard
# errors (sigma-scaled residuals), 1e-5 = 0.003 standard errors, the default `nrtolerance`
# of Stata's ml. An adaptive ODE solve resolves the cost only to its tolerances, so the raw
# step tolerances can fail on that noise at the optimum: a 10 ms lag beside a 60 s plate
# (Kvaerno5, tests/test_stiff_method.py) stalled at decrements 7e-7 and 3e-8 at the truth,
# reported "not converged" under the likelihood's 1e-9 (`DECREMENT_TOL`, a stopping rule
# there, on an exact discretisation).
SETTLED_DECREMENT = 1e-5
SAME_COST = 1e-5  # relative cost difference within which two starts reached the same optimum
STATUSES = (
    "converged",
    "local optimum",
    "at bound",
    "ran out of steps",
    "not converged",
    "diverged",
)
VALID_STATUSES = ("converged", "local optimum")


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

    `verdict` is "identifiable", "weakly identified" (its 95 % interval spans more than a
    factor `greybox._estimate.verdict.WEAK_FACTOR`), "prior-dominated", "not identifiable" or
    "at bound"; for the last two, `se` and the interval are NaN rather than a confident-looking
    number, and `bound` says which bound ("lower" / "upper") the value sits on.

    `se` and `ci95` are the headline (`se_method`: "gauss-newton", or "hac" when the fit's
    residuals are not white); `se_gauss_newton` and `se_hac` (Newey-West sandwich) are both
    kept.
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
    se_gauss_newton: float = float("nan")
    se_hac: float = float("nan")
    se_method: str = "gauss-newton"
    bound: str | None = None


@dataclasses.dataclass(frozen=True)
class FitResult:
    """Everything a fit established. All fit % are free-run simulation (`horizon`).

    - `status`: "converged" (an interior optimum, every start that reached the lowest cost
      agrees), "local optimum" (the starting values stopped at a higher cost than another
      start; the best start's estimate is reported), "at bound" (a parameter ended on one of
      its bounds: the estimate is the boundary, not an optimum of the data, and its intervals
      mean nothing), "not converged" (step budget, or a stall with cost still to gain, or a
      simulation failed), or "diverged". `valid` is True for the first two. `converged` is
      the optimiser's own answer (tolerances met, or stopped by the stall test in the interior
      with a Gauss-Newton decrement below `SETTLED_DECREMENT`: the step still to take is a
      few thousandths of a standard error; every simulation succeeded), whatever the bounds
      say.
    - `free`: the free-parameter specs as fitted (a `scale` left at None is filled in).
    - `covariance_raw`: the headline covariance of the raw coordinates (`se_method`:
      "gauss-newton", or "hac" when the residuals are not white);
      `covariance_gauss_newton_raw`, `covariance_hac_raw`: both, determined subspace only;
      `hac_bandwidth`: Newey-West bandwidth in frames.
    - `sigma` (n_y,): noise sd per output [SI]; `sigma_source`: "estimated" (robust scale of
      the residuals), "declared" (`fit(sigma=...)`) or "per-frame" (`Experiment.sigma`; `sigma`
      is then its RMS); `goodness_of_fit`: the test against known noise (None if estimated).
    - per run name: `fit_percent`, `fit_percent_robust`, `noise_ceiling` ((n_y,) arrays, one
      figure per output channel), `n_outliers` (readings flagged).
    - `residuals`: the residual analysis (whiteness, correlations with the inputs) of the
      simulation residuals; with process noise, of the one-step innovations.
    - `multistart_costs`: ((cost, converged) per start, at the first noise scale);
      `best_start`: the start whose estimate is reported; `n_starts_at_best`: how many
      starts reached its cost.
    - `noise`: the noise-model object of the fit (`OutputError` or `ProcessNoise`);
      `process_noise`: True for the likelihood back end.
    - `predictions`: {run: {horizon: (N, n_y) SI}}: "simulation" always, "one-step" and
      "k-step" (`noise.k_step` frames ahead) with process noise; `prediction_sd` their sds
      (least squares: the simulation's 95 % band sd from the parameters' covariance, computed
      with the fit's solver settings, so writing a result simulates nothing again).
    - process noise only (NaN / empty for least squares): `log_likelihood` (data term; the
      first frame conditioned on when the initial state is known), `aic`, `bic`,
      `whiteness` ({run: per output, the chi-square Ljung-Box of that run's standardised
      innovations over `noise.whiteness_lags` lags; the verdict's test is `residuals`}), `runs`
      (`RunDiagnostics` per run). `n_observations`: readings scored (least squares: n_data).
      For process noise `covariance_raw` is the inverse Hessian of -log L + priors,
      `residuals` the analysis of the one-step innovations, `sigma` the fitted measurement sd
      and `fit_percent` the simulation fit %.

    The status vocabulary is `STATUSES`, derived in one place (`fit_status`) for both back
    ends; besides the above, "ran out of steps" (the optimiser spent `max_steps`). A
    parameter's verdict "not needed" (a noise intensity or measurement sd that went to zero)
    leaves the fit valid.
    """

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
    fit_percent: dict  # run -> (n_y,) simulation fit % on every valid frame
    fit_percent_robust: dict  # the same without the frames flagged as outliers
    n_outliers: dict
    identifiability: IdentifiabilityReport
    loss: str
    method: str
    multistart_costs: tuple
    status: str
    valid: bool
    noise_ceiling: dict  # run -> (n_y,) fit % of the true model given the noise
    residuals: ResidualAnalysis
    covariance_gauss_newton_raw: np.ndarray
    covariance_hac_raw: np.ndarray
    se_method: str
    hac_bandwidth: int
    sigma_source: str
    goodness_of_fit: GoodnessOfFit | None
    best_start: int
    n_starts_at_best: int
    horizon: str = "simulation"
    noise: object = None  # the noise-model object (OutputError / ProcessNoise)
    log_likelihood: float = float("nan")  # process noise: log L of the data (priors apart)
    aic: float = float("nan")
    bic: float = float("nan")
    n_observations: int = 0  # readings scored (least squares: n_data)
    predictions: dict = dataclasses.field(default_factory=dict)  # run -> {horizon: (N, q)}
    prediction_sd: dict = dataclasses.field(default_factory=dict)  # run -> {horizon: (N, q)}
    whiteness: dict = dataclasses.field(default_factory=dict)  # run -> (LjungBox per output)
    runs: tuple = ()  # process noise: `RunDiagnostics` per estimation run
    # least squares: the adaptive solver's settings the fit simulated with (`solver_rtol`,
    # `solver_atol`, `solver_max_steps`); its validation, predictions and bands use them too
    solver: dict = dataclasses.field(default_factory=dict)

    @property
    def process_noise(self) -> bool:
        """True for a process-noise (likelihood) fit."""
        return getattr(self.noise, "name", "") == "process noise"

    @property
    def neg_log_likelihood(self) -> float:
        return -float(self.log_likelihood)

    @property
    def likelihood(self) -> str:
        """How the likelihood was computed (process noise), else ""."""
        from greybox.stochastic._sde_device import LIKELIHOOD

        return LIKELIHOOD if self.process_noise else ""

    @property
    def filter_name(self) -> str:
        if not self.process_noise:
            return ""
        return "extended Kalman filter" if self.model.use_ekf else "Kalman filter (exact)"

    @property
    def k_step(self) -> int:
        return int(self.noise.k_step) if self.process_noise else 0

    @property
    def posterior(self) -> Posterior:
        """What the fit established, as the object predictions and designs take."""
        return Posterior(
            self.model,
            self.free,
            self.raw,
            self.covariance_raw,
            self.identifiability.null_directions,
            self.sigma,
            self.method,
            self.noise,
            dict(self.solver),
        )

    @property
    def n_params(self) -> int:
        return self.raw.size

    @property
    def n_outputs(self) -> int:
        return int(np.size(self.sigma))

    @property
    def noise_known(self) -> bool:
        return self.sigma_source != "estimated"

    def estimate(self, name: str) -> ParameterEstimate:
        for p in self.parameters:
            if p.name == name:
                return p
        raise KeyError(f"{name}: not a fitted parameter; have {[p.name for p in self.parameters]}")

    def z_scores(self, truth: dict) -> dict:
        """(estimate - truth) / sd in raw coordinates, per shared parameter path in `truth`."""
        out = {}
        sd = np.sqrt(np.clip(np.diag(self.covariance_raw), 0, None))
        shared = [p for p in self.free if not p.per_experiment]  # raw order: shared first
        for k, p in enumerate(shared):
            if p.path in truth:
                out[p.path] = float((self.raw[k] - float(p.to_raw(truth[p.path]))) / sd[k])
        return out

    def __reduce__(self):
        # Results cross processes by pickle (`fit_distributed` gathers thousands into one
        # client, whose unpickling bounds the cluster): the run models differ from `model`
        # only in their leaves, and unpickling them as module trees was most of a result's
        # unpickling (0.74 ms of ~0.8; rebuilt from their leaves, 0.05 ms)
        state = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        shape = jax.tree_util.tree_structure(self.model)
        runs = [jax.tree_util.tree_flatten(m) for m in self.experiment_models]
        if all(treedef == shape for _, treedef in runs):
            state["experiment_models"] = _RunLeaves(leaves for leaves, _ in runs)
        return (_unpickle_fit_result, (state,))

    # text, HTML and DataFrame views: greybox/_estimate/result_text.py
    def __repr__(self) -> str:
        from greybox._estimate.result_text import short_repr

        return short_repr(self)

    def summary(self) -> str:
        """The status line and the parameter table (estimate, 95 % interval, unit, verdict)."""
        from greybox._estimate.result_text import summary_text

        return summary_text(self)

    def _repr_html_(self) -> str:
        from greybox._estimate.result_text import summary_html

        return summary_html(self)

    def to_dataframe(self):
        """One row per parameter in SI: value, sd, 95 % interval, unit, verdict (pandas)."""
        from greybox._estimate.result_text import parameter_frame

        return parameter_frame(self)

    def predict(self, experiment_index: int, method: str | None = None) -> np.ndarray:
        """Free-run simulation of experiment `experiment_index` with its fitted parameters (SI)."""
        from greybox._simulate.simulate import simulate

        exp = self.experiments[experiment_index]
        z = simulate(
            self.experiment_models[experiment_index],
            exp.inputs,
            exp.t_s,
            method=method or self.method,
            t_start_s=exp.t_start_s,
            **simulate_settings(self.solver),
        )
        return np.asarray(z).reshape(exp.n_frames, -1)


class _RunLeaves(list):
    """A pickled result's run models as their leaves (their structure is the model's)."""


def _unpickle_fit_result(state: dict) -> FitResult:
    runs = state["experiment_models"]
    if isinstance(runs, _RunLeaves):
        shape = jax.tree_util.tree_structure(state["model"])
        state["experiment_models"] = tuple(jax.tree_util.tree_unflatten(shape, x) for x in runs)
    return FitResult(**state)


class _Problem(eqx.Module):
    """Residual function over the raw parameter vector (shared first, then per experiment).

    A PyTree: data arrays, the model and the free parameters' numbers (bounds, scales,
    priors: `as_leaves`) are leaves; the settings' paths, the free parameters' structure and
    the simulation's solver options are static, so one compiled solver serves every data set
    of the same shapes and every device of the same structure, whatever its starts, bounds,
    scales and priors (and the optimiser's tolerances and budget: `solver_settings`).
    """

    model: object
    sched: dict
    y: jnp.ndarray
    w: jnp.ndarray
    noise: jnp.ndarray  # (E, N, n_y) known per-frame noise sd (ones when not known)
    settings: jnp.ndarray  # (E, K) known per-run values for `setting_paths`
    shared: tuple  # FreeParameters with array numbers (`as_leaves`)
    per_exp: tuple
    setting_paths: tuple = eqx.field(static=True)
    n_exp: int = eqx.field(static=True)
    method: str = eqx.field(static=True)
    loss: str = eqx.field(static=True)
    huber_c: float = eqx.field(static=True)
    student_nu: float = eqx.field(static=True)
    solver_opts: tuple = eqx.field(static=True)

    @staticmethod
    def build(  # the problem's settings, in `fit`'s order
        model, experiments, free, method, loss, huber_c, student_nu, rtol, atol, max_steps,
        *, padded=None, on_device: bool = True,
    ):  # fmt: skip
        """`padded`: the runs' stacked, padded schedule arrays (`schedules_for`) when a batch
        already padded them jointly with other devices' runs; `on_device=False` keeps numpy
        leaves (a batch stacks many problems before one transfer)."""
        sched = padded
        if sched is None:
            sched = schedules_for(model, experiments, on_device=False)
        n_exp = len(experiments)
        n_frames = sched["t_s"].shape[1]
        n_y = _output_columns(experiments)
        y = np.zeros((n_exp, n_frames, n_y))
        w = np.zeros_like(y)
        noise = np.ones_like(y)
        for i, e in enumerate(experiments):
            y[i, : e.n_frames] = e.y
            w[i, : e.n_frames] = e.mask
            if e.sigma is not None:
                noise[i, : e.n_frames] = np.where(e.mask, e.sigma, 1.0)
        np.nan_to_num(y, copy=False)  # once for every run (the padding is zero already)
        setting_paths, settings = _problem.settings_matrix(model, experiments, free)
        data = (as_arrays(model, on_device=False), sched, y, w, noise, np.asarray(settings))
        if on_device:  # one transfer, not one per leaf; the parameters' numbers stay on the
            # host, where the reports read them (a solve takes them as inputs)
            arrays, rest = eqx.partition(data, eqx.is_array)
            data = eqx.combine(jax.device_put(arrays), rest)
        shared, per_exp = _problem.split(free)
        return _Problem(
            *data,
            shared=as_leaves(shared),
            per_exp=as_leaves(per_exp),
            setting_paths=setting_paths,
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
        """(raw index, FreeParameter) of every parameter with a prior."""
        return _problem.prior_index(self.flat_free)

    @property
    def n_raw(self) -> int:
        return len(self.shared) + self.n_exp * len(self.per_exp)

    @property
    def flat_free(self) -> list:
        """The FreeParameter behind each raw coordinate (shared, then per experiment)."""
        return _problem.flat_free(self.shared, self.per_exp, self.n_exp)

    def models(self, raw):
        """(shared model, per-experiment raw block (E, P))."""
        ns = len(self.shared)
        base = apply_raw(self.model, self.shared, raw)
        return base, raw[ns:].reshape(self.n_exp, len(self.per_exp))

    def experiment_model(self, base, per_raw_row, settings_row):
        return _problem.run_model(base, self.setting_paths, settings_row, self.per_exp, per_raw_row)

    def run_prediction(self, shared_raw, per_row, settings_row, sched):
        """Camera readings (N, n_y) and success flag of one run, from the shared raw values
        and that run's own raw row."""
        base = apply_raw(self.model, self.shared, shared_raw)
        return observe_schedule(
            self.experiment_model(base, per_row, settings_row),
            sched,
            method=self.method,
            **dict(self.solver_opts),
        )

    def predictions(self, raw):
        """Camera readings (E, N, n_y) and per-experiment success flags.

        Differentiated by blocks (`_block_predictions`): a run's readings depend on the shared
        raw values and on its own row only, so each run's simulation carries the tangents of
        those (shared + per-run) and not of every other run's row as well."""
        return _block_predictions(self, raw)

    def scaled_errors(self, z, ok, sigma):
        """Data residuals (E, N, n_y) of the predictions `z` (success flags `ok`)."""
        r = (z - self.y) / (sigma * self.noise) * self.w
        return jnp.where(ok[:, None, None], r, FAILED_SOLVE_RESIDUAL * self.w)

    def residuals_and_sensitivities(self, raw, sigma):
        """(least-squares residual vector, (data residuals (E, N, n_y), predictions (E, N,
        n_y), success flags (E,), d predictions / d shared raw (E, N, n_y, ns), d predictions
        / d own row (E, N, n_y, P))) at `raw`: one simulation gives the solver's residuals
        and, at its last accepted point, every output of the fit's end point (`_solve`)."""
        z, solved, j_sh, j_pr = _block_predictions(self, raw, sensitivities=True)
        d = self.scaled_errors(z, solved, sigma)
        return self.loss_residuals(d, raw), (d, z, solved, j_sh, j_pr)

    def loss_residuals(self, data_residuals, raw):
        """The least-squares residual vector: robustified data residuals, then the priors."""
        r = _robust(data_residuals, self.loss, self.huber_c, self.student_nu)
        parts = [r.reshape(-1)]
        if self.priors:
            parts.append(jnp.stack([p.prior_residual(p.to_value(raw[k])) for k, p in self.priors]))
        return jnp.concatenate(parts)


def _block_predictions(problem: _Problem, raw, sensitivities: bool = False):
    """`problem`'s predictions at `raw` with a block-structured forward derivative: per run,
    the Jacobian with respect to (shared, that run's row) by `jax.jacfwd` (ns + P tangents
    through its simulation), assembled into the product with the tangent. The Jacobian
    depends on the primal only, so under `jax.jacfwd` over all ns + E P raw values (the
    optimiser's) it is computed once, not once per raw direction: every simulation carries
    ns + P tangents instead of ns + E P.

    `sensitivities`: also return those per-run Jacobians (E, N, n_y, ns) and (E, N, n_y, P)
    as outputs (their own derivative is not carried: zero), so that a derivative of the
    predictions also yields them without simulating again."""
    ns, n_per, n_exp = len(problem.shared), len(problem.per_exp), problem.n_exp

    def split(r):
        return r[:ns], r[ns:].reshape(n_exp, n_per)

    def plain(r):
        shared, per = split(r)

        def run(p, st, sc):
            return problem.run_prediction(shared, p, st, sc)

        return jax.vmap(run)(per, problem.settings, problem.sched)

    def with_sensitivities(r):
        shared, per = split(r)

        def one(p, st, sc):
            def readings(sh, pr):
                z, ok = problem.run_prediction(sh, pr, st, sc)
                return z, (z, ok)

            (j_sh, j_pr), (z, ok) = jax.jacfwd(readings, argnums=(0, 1), has_aux=True)(
                shared, p
            )
            return z, ok, j_sh, j_pr

        return jax.vmap(one)(per, problem.settings, problem.sched)

    @jax.custom_jvp
    def predict(r):
        return with_sensitivities(r) if sensitivities else plain(r)

    @predict.defjvp
    def predict_jvp(primals, tangents):
        (r,), (t,) = primals, tangents
        z, ok, j_sh, j_pr = with_sensitivities(r)
        t_sh, t_pr = split(t)
        dz = jnp.einsum("enys,s->eny", j_sh, t_sh) + jnp.einsum("enyp,ep->eny", j_pr, t_pr)
        d_ok = np.zeros(ok.shape, dtype=jax.dtypes.float0)
        if not sensitivities:
            return (z, ok), (dz, d_ok)
        return (z, ok, j_sh, j_pr), (dz, d_ok, jnp.zeros_like(j_sh), jnp.zeros_like(j_pr))

    return predict(raw)


def _prediction_jacobian(j_sh, j_pr):
    """d readings / d raw (E, N, n_y, ns + E P) from the per-run blocks of
    `_block_predictions`: the shared columns, then run e's own row in its block only."""
    n_exp = j_pr.shape[0]
    own = jnp.einsum("enyp,ef->enyfp", j_pr, jnp.eye(n_exp, dtype=j_pr.dtype))
    return jnp.concatenate([j_sh, own.reshape(*j_pr.shape[:3], -1)], axis=-1)


def solver_settings(rtol: float, atol: float, max_steps: int) -> tuple:
    """`_solve`'s (rtol, atol, max_steps, bound): the tolerances and the step budget as
    arrays, inputs of the compiled solver (a fit with another budget or tolerance compiles
    nothing new), and the loop's static bound (`step_bound`). numpy's: sent with the call's
    other inputs, where a JAX array made here costs a dispatch of its own (a batch makes
    them for every compiled call)."""
    return (
        np.asarray(float(rtol)),
        np.asarray(float(atol)),
        np.asarray(int(max_steps)),
        step_bound(max_steps),
    )


@jit
def _solve(problem: _Problem, raw_start, sigma, rtol, atol, max_steps, bound: int, raw_ref=None):
    """One Levenberg-Marquardt run plus everything the result needs at its end point.

    `rtol`, `atol`, `max_steps`, `bound`: `solver_settings`. The run stops early when its
    cost stalls (`levenberg_marquardt`); "on a bound" is judged from `raw_ref` (the fit's
    starting values; None: `raw_start`), as the result is.

    A single compiled function (the solve, the residuals, the Jacobian and the predictions)
    from one trace of the model keeps compile time down. Never throws: the result code says
    how the solve ended.
    """
    ref = raw_start if raw_ref is None else raw_ref
    pinned = pinned_fn(problem.flat_free, ref)

    # the model traced once into one jaxpr, which the solver evaluates and differentiates
    # (it traces its function more than once: its shapes, then each step's linearisation)
    residuals = eqx.filter_closure_convert(
        problem.residuals_and_sensitivities, raw_start, sigma
    )
    raw, ok, steps, stalled, end = levenberg_marquardt(
        residuals,
        raw_start,
        sigma,
        rtol=rtol,
        atol=atol,
        max_steps=bound,
        pinned=pinned,
        step_cap=max_steps,
        has_aux=True,
        end_point=True,
    )
    # the end point is the solver's last accepted evaluation (at `raw`): its residuals, its
    # linearisation and the sensitivities it was built from, not a second simulation with
    # its derivative (whose compiled copy was a third of an adaptive structure's XLA
    # compile: a chevron's first adaptive fit 5.1 -> 4.3 s, its XLA compile 2.3 -> 1.6 s)
    res, jac_op, (d, z, solved, j_sh, j_pr) = end
    jac = jac_op.as_matrix()
    jac_z = _prediction_jacobian(j_sh, j_pr)
    # a start stopped by the stall test in the interior, with (almost) nothing left to gain,
    # has converged: its raw tolerances failed only on rounding or on an adaptive solver's
    # resolution of the cost (`SETTLED_DECREMENT`)
    decrement = _gauss_newton_decrement(jac, res)
    settled = stalled & ~pinned(raw) & (decrement < SETTLED_DECREMENT)
    return dict(
        raw=raw,
        ok=ok | settled,
        steps=steps,
        stalled=stalled & ~settled,
        decrement=decrement,
        cost=0.5 * jnp.sum(res**2),
        residuals=res,
        data_residuals=d,
        jacobian=jac,
        predictions=z,
        # d predictions / d raw (E, N, n_y, n_raw): the 95 % bands the result folder draws
        prediction_jacobian=jac_z,
        solved=solved,
    )


def _gauss_newton_decrement(jac, res):
    """g^T H^+ g (twice the cost a Gauss-Newton step would still gain; g = J^T r, H = J^T J)
    on the determined subspace: columns scaled to unit norm, eigenvalues of H at least
    RANK_TOL^2 of the largest (the identifiability report's rank cut). Drift along an
    undetermined direction is the identifiability report's to flag, not non-convergence.
    NaN when the Jacobian or the residuals are not finite (nothing is known then)."""
    finite = jnp.all(jnp.isfinite(jac)) & jnp.all(jnp.isfinite(res))
    jac, res = jnp.where(finite, jac, 0.0), jnp.where(finite, res, 0.0)
    norm = jnp.sqrt(jnp.sum(jac**2, axis=0))
    js = jac / jnp.where(norm > 0, norm, 1.0)
    w, v = jnp.linalg.eigh(js.T @ js)
    keep = w > RANK_TOL**2 * w[-1]
    gt = v.T @ (js.T @ res)
    decrement = jnp.sum(jnp.where(keep, gt**2 / jnp.where(keep, w, 1.0), 0.0))
    return jnp.where(finite, decrement, jnp.nan)


def _ending(out) -> str:
    """How one start ended, for its progress line."""
    if bool(out["ok"]):
        return "converged"
    return "stalled (cost no longer falling)" if bool(out.get("stalled")) else "not converged"


def _stall_reason(best) -> str | None:
    """The words for a best start that stopped because its cost stalled (else None)."""
    if not bool(best.get("stalled", False)):
        return None
    return (
        f"the cost fell by less than {STALL_RTOL:g} (relative; {STALL_RTOL_AT_BOUND:g} while a "
        f"parameter sat on a bound) over the last {STALL_WINDOW} "
        f"Levenberg-Marquardt steps (stopped after {int(best['steps'])}; a Gauss-Newton step "
        f"would still lower the cost by {0.5 * float(best.get('decrement', np.nan)):.3g}): "
        "the optimiser stalled, "
        "typically a parameter drifting along a direction the data barely constrain or "
        "toward a bound; fix or bound that parameter, or revise the model"
    )


@jit
def _response(problem: _Problem, raw):
    """Predictions (E, N, n_y), success flags (E,) and d predictions / d raw (E, N, n_y,
    n_raw) of `problem` at `raw`: one compiled simulation with its sensitivities."""

    def f(r):
        z, ok = problem.predictions(r)
        return z, (z, ok)

    jac, (z, ok) = jax.jacfwd(f, has_aux=True)(raw)
    return z, ok, jac


@jit
def _fitted_models(problem: _Problem, raw):
    """(shared model, per-run models) at `raw`: one compiled call, not a chain of eager
    updates per run (most of a batch's per-device host time before)."""
    base, per = problem.models(raw)
    runs = tuple(
        problem.experiment_model(base, per[i], problem.settings[i]) for i in range(problem.n_exp)
    )
    return base, runs


_start_values = _problem.start_values  # (kept for greybox._estimate.batch)


def _initial_raw(problem: _Problem, model) -> np.ndarray:
    """Raw start vector of `problem` (`_problem.initial_raw`)."""
    return _problem.initial_raw(problem.flat_free, model)


def _perturbed(problem: _Problem, raw0: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A multi-start point (`_problem.perturbed`)."""
    return _problem.perturbed(problem.shared, raw0, rng)


def _robust_sigma(r_scaled: np.ndarray, w: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Per-output noise scale from the median absolute residual (robust to outliers).

    `r_scaled`: residuals divided by `sigma`; `w`: their weights (0 = no valid reading). An
    output with no valid reading in any run (a single-sensor log of a two-sensor device)
    carries no weight in the fit and has nothing to estimate its noise from: it keeps its
    scale `sigma[j]` (the declared noise, or the fit's starting guess), never NaN."""
    stacked = (np.asarray(x)[None] for x in (r_scaled, w, sigma))
    return _robust_sigmas(*stacked)[0]


def _robust_sigmas(r_scaled: np.ndarray, w: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """`_robust_sigma` of D fits at once (`fit_batch`'s wave of devices): `r_scaled` and `w`
    (D, ..., n_y), `sigma` (D, n_y); one sort of every (fit, output) row, each row's median
    as np.median gives it (`_sorted_median`), so a fit alone and in a batch get the same."""
    r = np.asarray(r_scaled, dtype=float)
    d, n_y = r.shape[0], r.shape[-1]
    rows = np.swapaxes(r.reshape(d, -1, n_y), 1, 2).reshape(d * n_y, -1)
    used = np.swapaxes((np.asarray(w) > 0).reshape(d, -1, n_y), 1, 2).reshape(d * n_y, -1)
    count = used.sum(axis=1)
    median = _sorted_median(np.sort(np.where(used, np.abs(rows), np.inf), axis=1), count)
    sigma = np.asarray(sigma, dtype=float).reshape(d, n_y)
    out = np.where((count > 0).reshape(d, n_y), 1.4826 * median.reshape(d, n_y) * sigma, sigma)
    return np.maximum(out, 1e-300)


def _outputs_without_data(w: np.ndarray) -> list[int]:
    """Indices of the outputs with no valid reading in any run (weight 0 everywhere)."""
    w = np.asarray(w)
    return [j for j in range(w.shape[-1]) if not np.any(w[..., j] > 0)]


def _output_columns(experiments) -> int:
    """The runs' number of output columns; runs that disagree are refused."""
    n_y = experiments[0].y.shape[1]
    for e in experiments:
        if e.y.shape[1] != n_y:
            raise ValueError(f"{e.name}: has {e.y.shape[1]} output columns, others {n_y}")
    return n_y


def _checked_data(model, experiments, free, sigma) -> str:
    """The noise source (`_noise_source`) of a least-squares fit of `free` to `experiments`,
    after the checks of its data that need no problem built, which `fit` and every device
    of a batch (`batch.checked_devices`) make before any solve: the runs' output columns and
    known settings, enough readings for the parameters, a declared sigma > 0 (one value or
    one per output)."""
    source = _noise_source(experiments, sigma)
    n_y = _output_columns(experiments)
    _problem.settings_matrix(model, experiments, free)
    shared, per_exp = _problem.split(free)
    n_raw = len(shared) + len(experiments) * len(per_exp)
    n_data = sum(int(e.mask.sum()) for e in experiments)
    if n_data <= n_raw:
        raise ValueError(
            f"experiments: {n_data} valid frames cannot determine {n_raw} parameters; add "
            "data or free fewer parameters"
        )
    if source == "declared":
        s = np.asarray(sigma, dtype=float)
        if s.ndim > 1 or s.size not in (1, n_y) or not np.all(s > 0):
            raise ValueError(
                "sigma: noise scale must be > 0 (SI units of the output), one value or one "
                f"per output ({n_y})"
            )
    return source


def _noise_source(experiments, sigma) -> str:
    """ "per-frame" (every run carries `Experiment.sigma`), "declared" (`sigma=` given) or
    "estimated"; mixing is an error (which noise would be meant is ambiguous)."""
    carry = [e.sigma is not None for e in experiments]
    if any(carry) and not all(carry):
        have = [e.name for e, c in zip(experiments, carry) if c]
        lack = [e.name for e, c in zip(experiments, carry) if not c]
        raise ValueError(
            f"sigma: runs {have} carry a per-frame noise level and {lack} do not; give "
            "Experiment.sigma for every run or for none"
        )
    if all(carry):
        if sigma is not None:
            raise ValueError(
                "sigma: the runs carry per-frame noise (Experiment.sigma); do not pass "
                "sigma= as well"
            )
        return "per-frame"
    return "declared" if sigma is not None else "estimated"


_OLD_NOISE_KEYWORDS = ("loss", "huber_c", "student_nu", "sigma")
_OLD_SIMULATION_KEYWORDS = ("method", "solver_rtol", "solver_atol", "solver_max_steps")


def fit(
    model,
    experiments: Sequence[Experiment],
    free: Sequence[FreeParameter],
    *,
    noise=None,
    simulation=None,
    n_starts: int | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    start_values=None,
    progress: Callable[[str], None] | None = None,
    method: str | None = None,
    loss: str | None = None,
    huber_c: float | None = None,
    student_nu: float | None = None,
    sigma: float | Sequence[float] | None = None,
    solver_rtol: float | None = None,
    solver_atol: float | None = None,
    solver_max_steps: int | None = None,
) -> FitResult:
    """Fit `free` parameters of `model` to the estimation `experiments`: the one fit.

    **Main arguments:**
    - `model`: device at its starting values; fields not in `free` stay fixed. With process
      noise: a `StochasticDevice` (`stochastic_device(...)`) or a plain device (wrapped with
      the structure of `noise`).
    - `experiments`: runs to fit (their `role` is not consulted; pass estimation runs). Runs
      that carry `Experiment.sigma` (known noise per frame) are weighted by it.
    - `free`: `FreeParameter`s (shared or per-experiment, bounds, priors); with process noise
      also noise paths (`noise_parameters`).
    - `noise`: the noise model. `OutputError(loss, sigma)` (default: `OutputError()`, Huber
      1.5, sigma estimated): least squares on the simulation (free-run) error.
      `ProcessNoise(structure, filter, initial_state, ...)`: maximum likelihood through the
      (extended) Kalman filter.
    - `simulation`: `ZOH()` or `Adaptive(rtol, atol, max_steps)`; None: the device's default.

    **Other arguments:**
    - `n_starts`, `seed`: multi-start count and its seed; None starts `AUTO_STARTS` times when
      more than two shared parameters are free, else once. Every start reuses one compiled
      solver; `multistart_costs` reports them.
    - `max_steps`: optimiser budget (None: 200 Levenberg-Marquardt steps for least squares,
      `_likelihood.MAX_STEPS` damped-Newton steps for the likelihood); `rtol`, `atol`: least
      squares tolerances (raw space).
    - `start_values`: a hook ``(model, free, experiments) -> free`` setting data-based
      starting values (e.g. camera offsets from rest readings), or a `DeviceSpec` whose
      `start_values` hook is used; the command line applies the spec's hook the same way.
    - `progress`: called with a short text line at each stage (the CLI prints it).
    - Old string keywords (still accepted, mapped once to the objects): `method`, `loss`,
      `huber_c`, `student_nu`, `sigma`, `solver_rtol`, `solver_atol`, `solver_max_steps`.

    **Returns:** a `FitResult`. Its `status` and `valid` say whether the estimate is usable:
    a fit that does not converge, ends on a bound or diverges says so; it never presents NaN
    parameters as a success.
    """
    from greybox._estimate import noise_models as nm

    old = dict(
        method=method,
        loss=loss,
        huber_c=huber_c,
        student_nu=student_nu,
        sigma=sigma,
        solver_rtol=solver_rtol,
        solver_atol=solver_atol,
        solver_max_steps=solver_max_steps,
    )
    given = [k for k, v in old.items() if v is not None]
    if noise is None:
        noise = nm.OutputError(
            nm.loss_from_string(
                loss or "huber", 1.5 if huber_c is None else huber_c, student_nu or 4.0
            ),
            sigma,
        )
    elif not isinstance(noise, nm.ProcessNoise):
        clash = [k for k in given if k in _OLD_NOISE_KEYWORDS]
        if clash:
            raise ValueError(
                f"{clash[0]}: give it inside the noise object (OutputError(loss=..., "
                "sigma=...)), not beside noise="
            )
    if isinstance(noise, nm.ProcessNoise):
        if given or simulation is not None:
            what = given[0] if given else "simulation"
            raise ValueError(
                f"{what}: applies to OutputError (least squares) only; a ProcessNoise fit "
                "takes its filter, initial state and horizons from the ProcessNoise object"
            )
        from greybox._estimate.likelihood import fit_likelihood

        return fit_likelihood(
            model,
            experiments,
            free,
            noise,
            n_starts=n_starts,
            seed=seed,
            max_steps=max_steps,
            start_values=start_values,
            progress=progress,
        )
    if not isinstance(noise, nm.OutputError):
        raise ValueError(
            f"noise: {noise!r} is not a noise model; use greybox.OutputError(...) or "
            "greybox.ProcessNoise(...)"
        )
    if simulation is not None:
        clash = [k for k in given if k in _OLD_SIMULATION_KEYWORDS]
        if clash:
            raise ValueError(
                f"{clash[0]}: give it inside the simulation object (ZOH() / Adaptive(...)), "
                "not beside simulation="
            )
        if not isinstance(simulation, (nm.ZOH, nm.Adaptive)):
            raise ValueError(
                f"simulation: {simulation!r}: use greybox.ZOH() or greybox.Adaptive(...)"
            )
    else:
        simulation = nm.simulation_from_string(
            method,
            1e-8 if solver_rtol is None else solver_rtol,
            1e-10 if solver_atol is None else solver_atol,
            16384 if solver_max_steps is None else solver_max_steps,
        )
    solver = (
        dict(
            solver_rtol=simulation.rtol,
            solver_atol=simulation.atol,
            solver_max_steps=simulation.max_steps,
        )
        if isinstance(simulation, nm.Adaptive)
        else dict(
            solver_rtol=1e-8 if solver_rtol is None else solver_rtol,
            solver_atol=1e-10 if solver_atol is None else solver_atol,
            solver_max_steps=16384 if solver_max_steps is None else solver_max_steps,
        )
    )
    free = apply_start_values(start_values, model, free, experiments)
    # one BLAS thread for a small problem (`blas.small_blas`): on busy cores the LAPACK calls
    # of the solver and of the host on a 3,072 x 8 Jacobian waited for OpenBLAS threads
    # (a warm chevron fit 450 -> 57 ms)
    with small_blas(jacobian_size_bound(experiments, len(free))):
        result = _fit_least_squares(
            model,
            experiments,
            free,
            method=None if simulation is None else simulation.name,
            loss=noise.loss.name,
            huber_c=getattr(noise.loss, "c", 1.5),
            student_nu=getattr(noise.loss, "nu", 4.0),
            sigma=noise.sigma,
            n_starts=n_starts,
            seed=seed,
            max_steps=200 if max_steps is None else max_steps,
            rtol=rtol,
            atol=atol,
            progress=progress,
            **solver,
        )
    return dataclasses.replace(result, noise=noise)


def simulate_settings(solver: dict) -> dict:
    """`greybox.simulate`'s `rtol`, `atol`, `max_steps` from a fit's `solver` settings."""
    return {k.removeprefix("solver_"): v for k, v in solver.items()}


def jacobian_size_bound(experiments, n_free: int) -> int:
    """An upper bound on the elements of a fit's Jacobian (readings x raw parameters, with
    every free parameter counted once per run): what `small_blas` is sized by."""
    return sum(int(np.size(e.y)) for e in experiments) * int(n_free) * len(experiments)


def apply_start_values(start_values, model, free, experiments) -> tuple:
    """`free` after the data-based start-value hook (a callable or a `DeviceSpec`'s)."""
    hook = getattr(start_values, "start_values", start_values)
    if hook is None:
        return tuple(free)
    return tuple(hook(model, tuple(free), tuple(experiments)))


def _fit_least_squares(
    model,
    experiments: Sequence[Experiment],
    free: Sequence[FreeParameter],
    *,
    method: str | None = None,
    loss: str = "huber",
    huber_c: float = 1.5,
    student_nu: float = 4.0,
    sigma: float | Sequence[float] | None = None,
    n_starts: int | None = None,
    seed: int = 0,
    max_steps: int = 200,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    solver_rtol: float = 1e-8,
    solver_atol: float = 1e-10,
    solver_max_steps: int = 16384,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """The least-squares back end of `fit` (free-run simulation error).

    **Main arguments:**
    - `model`: device at its starting values; fields not in `free` stay fixed.
    - `experiments`: runs to fit (their `role` is not consulted; pass estimation runs). Runs
      that carry `Experiment.sigma` (known noise per frame) are weighted by it.
    - `free`: `FreeParameter`s (shared or per-experiment, bounds, priors).

    **Other arguments:**
    - `method`: "zoh" (exact, linear devices), "adaptive" (diffrax with jump times) or
      "stiff" (the same, implicit: time scales far apart); None takes the device's default.
    - `loss`: "huber" (default; threshold `huber_c` sigmas), "student_t" (`student_nu` dof) or "l2".
    - `sigma`: known measurement noise [SI] per output (declared): the readings are weighted
      by it, it is not re-estimated, and the residuals are tested against it. None estimates
      it robustly from the residuals; an output with no valid reading in any run is left out
      of the fit and keeps the starting guess (or its declared value) as its `sigma`.
    - `n_starts`, `seed`: multi-start count and its random seed; None starts `AUTO_STARTS`
      times when more than two shared parameters are free, else once.
    - `max_steps`, `rtol`, `atol`: Levenberg-Marquardt budget and tolerances (raw space).
    - `solver_*`: adaptive ODE solver tolerances and step budget.
    - `progress`: called with a short text line at each stage (the CLI prints it).

    **Returns:** a `FitResult`. Its `status` and `valid` say whether the estimate is usable:
    a fit that does not converge, ends on a bound or diverges says so; it never presents NaN
    parameters as a success.
    """
    require_x64("fit")
    experiments = tuple(experiments)
    say = progress or (lambda _msg: None)
    if not experiments:
        raise ValueError("experiments: zero runs in the estimation set; give at least one")
    free = _problem.check_free(model, free)
    method = check_method(model, method)
    if loss not in LOSSES:
        raise ValueError(f"loss: {loss!r} is unknown; use one of {LOSSES}")
    free = _problem.with_scales(free, model)
    source = _checked_data(model, experiments, free, sigma)

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
    raw0 = _initial_raw(problem, model)
    empty = _outputs_without_data(np.asarray(problem.w))
    if empty:
        say(
            f"output(s) {', '.join(str(j + 1) for j in empty)} have no valid reading in any "
            "run: left out of the fit; their noise scale is not estimated (it stays at the "
            "declared sigma, or the starting guess)"
        )

    settings = solver_settings(rtol, atol, max_steps)

    def solve(raw_start, sig):
        return _solve(problem, raw_start, sig, *settings, jnp.asarray(raw0))

    if source == "estimated":
        sig = np.full(n_y, _initial_sigma_guess(experiments))
    elif source == "declared":
        sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n_y,)).copy()
    else:
        sig = np.ones(n_y)  # the per-frame levels are in the problem's `noise`

    n_starts = _problem.n_starts_for(n_starts, problem.shared)
    rng = np.random.default_rng(seed)
    starts = [raw0] + [_perturbed(problem, raw0, rng) for _ in range(int(n_starts) - 1)]

    def announce(i):
        say(
            f"start {i + 1}/{len(starts)}: Levenberg-Marquardt ({method}, {loss} loss, "
            f"{problem.n_raw} parameters, {problem.n_data} frames)"
        )

    def report(i, out):
        say(
            f"start {i + 1}/{len(starts)}: cost {float(out['cost']):.6g}, "
            f"{_ending(out)} after {int(out['steps'])} steps"
        )

    try:
        working = _problem.solve_bytes(problem)
    except Exception:  # noqa: BLE001 (a device that knows its size only per run: one at a time)
        working = float("inf")
    runs = run_starts(
        lambda start: jax.device_get(solve(jnp.asarray(start), jnp.asarray(sig))),
        starts,
        announce,
        report,
        working,
    )
    best_index = _problem.best_start(runs)
    best = runs[best_index]
    steps = int(best["steps"])

    if source == "estimated" and np.all(np.isfinite(best["raw"])):
        sig = _robust_sigma(np.asarray(best["data_residuals"]), np.asarray(problem.w), sig)
        say(
            f"noise estimated from residuals: sigma = {', '.join(f'{s:.4g}' for s in sig)} (SI); "
            "refitting at that scale"
        )
        best = jax.device_get(solve(jnp.asarray(best["raw"]), jnp.asarray(sig)))
        steps += int(best["steps"])

    return _assemble(
        problem,
        best,
        sig,
        steps,
        runs,
        best_index,
        raw0,
        experiments,
        free,
        source,
        say,
        int(max_steps),
    )


def _initial_sigma_guess(experiments) -> float:
    """A first noise scale: the spread of frame-to-frame differences (refined after the fit)."""
    # every run's readings end to end, the differences across a run boundary left out (one
    # pass over all runs: a batch guesses this for every device)
    ys = [np.asarray(e.y, dtype=float) for e in experiments]
    y = np.concatenate([v.reshape(v.shape[0], -1) for v in ys])
    diffs = np.diff(y, axis=0)
    ends = np.cumsum([v.shape[0] for v in ys])[:-1]
    diffs = np.delete(diffs, ends[(ends > 0) & (ends < y.shape[0])] - 1, axis=0).reshape(-1)
    diffs = diffs[np.isfinite(diffs)]
    scale = 1.4826 * np.median(np.abs(diffs)) / np.sqrt(2) if diffs.size else 0.0
    span = np.max(np.abs(y), initial=0.0, where=~np.isnan(y))
    return float(max(scale, 1e-3 * span, 1e-300))


def _frame_sigma(e: Experiment, sig: np.ndarray) -> np.ndarray:
    """(N, n_y) noise sd [SI] of each reading: the known per-frame level, else `sig`."""
    if e.sigma is not None:
        return np.asarray(e.sigma, dtype=float)
    return np.broadcast_to(np.asarray(sig, dtype=float), e.y.shape)


def _output_sigma(experiments, n_y: int, source: str, sig) -> np.ndarray:
    """(n_y,) the noise level a fit reports and scores with: the RMS of the known per-frame
    levels (`source` "per-frame"), else `sig` (declared or estimated)."""
    return _rms_sigma(experiments, n_y) if source == "per-frame" else np.asarray(sig)


def _rms_sigma(experiments, n_y: int) -> np.ndarray:
    """(n_y,) RMS of the known per-frame noise over every valid reading."""
    num, den = np.zeros(n_y), np.zeros(n_y)
    for e in experiments:
        s = np.where(e.mask, e.sigma, 0.0)
        num += np.sum(s**2, axis=0)
        den += e.mask.sum(axis=0)
    return np.sqrt(num / np.maximum(den, 1))


def _predictions(best, experiments) -> list:
    """Per run, the (N, n_y) simulated response of the solve `best` (padding cut off)."""
    z = np.asarray(best["predictions"])
    return [z[i, : e.n_frames] for i, e in enumerate(experiments)]


def _residual_runs(experiments, predictions) -> list:
    """(name, t_s, residual, valid, inputs at the frames) per run, for `_residuals.analyse`."""
    return [
        (e.name, e.t_s, e.y - z, e.mask, e.frame_inputs())
        for e, z in zip(experiments, predictions)
    ]


def _finite(best) -> bool:
    """Whether the solve `best` ended at finite parameters and cost."""
    return bool(np.all(np.isfinite(np.asarray(best["raw"])))) and bool(
        np.isfinite(float(best["cost"]))
    )


def _sandwich_meats(fits) -> list[HACMeat]:
    """The HAC meat (`sandwich.hac_meats`) of each fit of `fits`, (problem, best solve,
    experiments, lags) each: the score contributions g_t = sum_outputs J_t^T r~_t, r~ the
    residuals less their FIR model-error model on the run's input levels at frame lags
    0..`lags`-1 on the frame grid (as the residual analysis counts lags), every regression of
    every run of every fit in one stacked pass and every meat in another (`fit_batch` passes
    the devices of a wave, `fit` its own fit), the model-error coefficients counted in the
    degrees of freedom."""
    regressions, stacked = [], []
    for problem, best, experiments, lags in fits:
        n_rows = _data_rows(problem, best)
        r3 = np.asarray(best["residuals"])[:n_rows].reshape(problem.y.shape)
        w3 = np.asarray(problem.w).reshape(problem.y.shape) > 0
        j4 = np.asarray(best["jacobian"])[:n_rows].reshape(*r3.shape, -1)
        stacked.append((r3, j4))
        for i, e in enumerate(experiments):
            n = e.n_frames
            regressions.append((e.t_s, r3[i, :n], w3[i, :n], e.frame_inputs(), lags))
    cleaned = iter(model_error_residuals_many(regressions))
    runs_of, n_readings, n_fitted = [], [], []
    for (problem, _, experiments, _), (r3, j4) in zip(fits, stacked):
        left, fitted = np.zeros_like(r3), 0  # what the model-error model leaves, per run
        for i, e in enumerate(experiments):
            left[i, : e.n_frames], k = next(cleaned)
            fitted += k
        g = np.sum(j4 * left[..., None], axis=2)  # every run's scores in one product
        runs_of.append([(e.t_s, g[i, : e.n_frames]) for i, e in enumerate(experiments)])
        n_readings.append(problem.n_data)
        n_fitted.append(problem.n_raw + fitted)
    return hac_meats(runs_of, n_readings=n_readings, n_fitted=n_fitted)


def _data_rows(problem, best) -> int:
    """Rows of the solve's Jacobian and residual vector that are data (the rest: priors)."""
    return int(np.shape(best["jacobian"])[0]) - len(problem.priors)


def _assemble(
    problem,
    best,
    sig,
    steps,
    runs,
    best_index,
    raw0,
    experiments,
    free,
    source,
    say,
    max_steps: int | None = None,
    models=None,
    residuals: ResidualAnalysis | None = None,
    hac: HACMeat | None = None,
    scores: tuple | None = None,
) -> FitResult:
    """The `FitResult` of the best solve `best` (covariance, identifiability, residual tests,
    scores). `models`: (shared model, per-run models) at its raw vector, `residuals`: the
    residual analysis of its predictions (`_residual_runs`), `hac`: the meat of its sandwich
    (`_sandwich_meats`), and `scores`: its runs' `_scored_runs` at `_output_sigma`, when
    already computed (`fit_batch` computes them for many devices at once)."""
    raw, cost, ok = np.asarray(best["raw"]), float(best["cost"]), bool(best["ok"])
    finite = _finite(best)
    say("computing covariance, identifiability and residual tests")
    jac = np.asarray(best["jacobian"]) if finite else np.full_like(best["jacobian"], np.nan)
    n_rows_data = _data_rows(problem, best)
    labels, owners = _labels(problem, experiments)
    flat_free = problem.flat_free
    bounds = [p.bound_hit(raw[k], raw0[k]) if finite else None for k, p in enumerate(flat_free)]
    report = analyse(jac[:n_rows_data], jac[n_rows_data:], flat_free, raw, labels, bounds)

    solved = np.asarray(best["solved"])
    preds = _predictions(best, experiments)
    n_y = problem.y.shape[-1]
    if residuals is None:
        residuals = analyse_residuals(_residual_runs(experiments, preds))

    # Gauss-Newton and HAC sandwich covariance (same determined subspace); the meat leaves
    # out what the inputs explain of the residuals (misfit, not noise: `sandwich`)
    cov_gn = report.covariance_raw
    if not finite:
        hac = None
    elif hac is None:
        (hac,) = _sandwich_meats([(problem, best, experiments, residuals.max_lag)])
    if hac is not None:
        jp = jac[n_rows_data:]
        cov_hac = cov_gn @ (hac.meat + jp.T @ jp) @ cov_gn
    else:
        cov_hac = np.full_like(cov_gn, np.nan)
    se_method = "gauss-newton" if residuals.all_white else "hac"
    cov = cov_hac if se_method == "hac" else cov_gn
    params = parameter_estimates(
        flat_free, raw, report, labels, owners, covariance_hac=cov_hac, headline=se_method
    )
    corr = correlation(report, cov)
    band_sd = _simulation_sd(problem, best, cov, experiments, solved if finite else None)

    base, exp_models = _fitted_models(problem, jnp.asarray(raw)) if models is None else models
    sigma_out = _output_sigma(experiments, n_y, source, sig)
    if scores is None:
        scores = _scored_runs(experiments, preds, sigma_out)
    fits, robust, outliers, ceilings, scaled = scores
    gof = (
        goodness_of_fit(scaled, [e.mask for e in experiments], problem.n_raw)
        if source != "estimated" and finite
        else None
    )

    pinned = [
        (p.name, p.bound, _bound_value(q, p.bound))
        for p, q in zip(params, flat_free)
        if p.bound is not None
    ]
    unidentified = unidentified_with_reasons(params, report)
    status, message, at_best = fit_status(
        finite=finite,
        solved=bool(np.all(solved)),
        optimiser_ok=ok,
        pinned=pinned,
        costs=[float(r["cost"]) for r in runs],
        best_index=best_index,
        unidentified=unidentified,
        ran_out=max_steps is not None and int(best["steps"]) >= max_steps,
        reason=_stall_reason(best),
        start_converged=[bool(r["ok"]) for r in runs],
    )
    converged = bool(ok and finite and np.all(solved))
    return FitResult(
        model=base,
        experiment_models=exp_models,
        experiments=tuple(experiments),
        free=tuple(free),
        parameters=params,
        raw=raw,
        covariance_raw=cov,
        correlation=corr,
        sigma=np.asarray(sigma_out, dtype=float),
        cost=float(cost),
        n_data=problem.n_data,
        converged=converged,
        message=message,
        n_steps=int(steps),
        fit_percent=fits,
        fit_percent_robust=robust,
        n_outliers=outliers,
        identifiability=report,
        loss=problem.loss,
        method=problem.method,
        multistart_costs=tuple((float(r["cost"]), bool(r["ok"])) for r in runs),
        status=status,
        valid=status in VALID_STATUSES,
        noise_ceiling=ceilings,
        residuals=residuals,
        covariance_gauss_newton_raw=cov_gn,
        covariance_hac_raw=cov_hac,
        se_method=se_method,
        hac_bandwidth=int(hac.bandwidth) if hac is not None else 0,
        sigma_source=source,
        goodness_of_fit=gof,
        best_start=int(best_index),
        n_starts_at_best=len(at_best),
        n_observations=problem.n_data,
        predictions={e.name: {"simulation": zi} for e, zi in zip(experiments, preds)},
        prediction_sd={e.name: {"simulation": band_sd[i]} for i, e in enumerate(experiments)},
        solver={f"solver_{k}": v for k, v in problem.solver_opts},
    )


def _simulation_sd(problem, best, cov, experiments, solved) -> list:
    """Per run, the (N, n_y) sd of the simulated response from the shared parameters'
    covariance `cov`, from the fit's own prediction Jacobian (`_response_sd`); NaN for every
    run when `solved` is None (a fit that is not finite)."""
    n_shared = len(problem.shared)
    jac = best.get("prediction_jacobian")
    if solved is None or jac is None:
        return [np.full((e.n_frames, problem.y.shape[-1]), np.nan) for e in experiments]
    g, c = np.asarray(jac)[..., :n_shared], cov[:n_shared, :n_shared]
    return _response_sd(g, c, experiments, solved)


def _response_sd(jac, cov, experiments, solved) -> list:
    """Per run, the (N, n_y) sd of a response whose sensitivities are `jac` (runs, frames,
    n_y, P) given the covariance `cov` (P, P) (delta method, `prediction.delta_variance`, all
    runs in one call; inf where it depends on an undetermined direction); NaN for a run whose
    simulation failed (`solved` False)."""
    from greybox._estimate.prediction import delta_variance

    jac = np.asarray(jac)
    r, f, n_y, p = jac.shape
    var = delta_variance(jac.reshape(r * f, n_y, p), cov).reshape(r, f, n_y)
    sd = np.sqrt(np.clip(var, 0.0, None))
    return [
        sd[i, : e.n_frames] if bool(solved[i]) else np.full((e.n_frames, jac.shape[2]), np.nan)
        for i, e in enumerate(experiments)
    ]


def unidentified_with_reasons(params, report) -> list:
    """ "name (the weak combination)" of every "not identifiable" estimate."""
    return [
        f"{p.name} ({report.explain(k)})"
        for k, p in enumerate(params)
        if p.verdict == "not identifiable"
    ]


def _bound_value(p: FreeParameter, bound: str) -> float:
    return float(p.lower if bound == "lower" else p.upper)


def _unidentified_note(names) -> str:
    if not names:
        return ""
    return f"; {len(names)} parameter(s) are not identifiable from these data: {', '.join(names)}"


def fit_status(
    *,
    finite: bool,
    solved: bool,
    optimiser_ok: bool,
    pinned,
    costs,
    best_index: int,
    unidentified=(),
    ran_out: bool = False,
    reason: str | None = None,
    start_converged=None,
    optimiser: str = "Levenberg-Marquardt",
) -> tuple[str, str, list]:
    """(status, message, indices of the starts that reached the lowest cost) of a fit.

    Most serious first: "diverged" (non-finite estimate), "not converged" (a simulation
    failed, or the optimiser stopped short while no parameter sits on a bound), "at bound"
    (`pinned`: (name, "lower"/"upper", bound value) per parameter on a bound; an optimiser
    chasing a bound often stops short, and the bound is then the cause), "local optimum"
    (start 0, the given values, converged at a cost above the lowest cost of `costs` by more
    than SAME_COST relative; the best start is `best_index`), else "converged".

    The one place that derives the status, for both back ends. When the optimiser stopped
    short: "ran out of steps" (`ran_out`: the step budget was spent) or "not converged"
    (with `reason` in words when known). `start_converged`: per start, whether it met its
    tolerances (a start that ran out of steps at a higher cost is not a local optimum).
    """
    costs = [float(c) for c in costs]
    best = costs[best_index] if costs else float("nan")
    tol = SAME_COST * abs(best) + 1e-12
    at_best = [i for i, c in enumerate(costs) if np.isfinite(c) and c <= best + tol]
    if not finite:
        return (
            "diverged",
            "the fit diverged (non-finite parameters or cost); no estimate is reported",
            at_best,
        )
    if not solved:
        return (
            "not converged",
            f"an experiment's simulation failed at the final parameters: {SOLVER_FAILED}",
            at_best,
        )
    if pinned:
        where = ", ".join(f"{name} at its {side} bound {value:g}" for name, side, value in pinned)
        message = (
            f"at bound: {where}; the estimate is not valid (the best fit the bounds allow is "
            "on the boundary, not an optimum of the data, so its standard errors and "
            "intervals mean nothing): widen the bound, fix the parameter, or revise the model"
        )
        if not optimiser_ok:
            message += " (the optimiser also stopped short, as it does chasing a bound)"
        return "at bound", message + _unidentified_note(unidentified), at_best
    if not optimiser_ok:
        if ran_out:
            return (
                "ran out of steps",
                f"ran out of steps: {optimiser} spent its step budget `max_steps` before "
                "meeting its tolerances; raise max_steps or start closer; treat the "
                "estimates as unconverged" + _unidentified_note(unidentified),
                at_best,
            )
        return (
            "not converged",
            (
                f"not converged: {reason}"
                if reason
                else f"{optimiser} stopped without meeting its tolerances (stalled); treat "
                "the estimates as unconverged"
            )
            + _unidentified_note(unidentified),
            at_best,
        )
    start0_converged = True if start_converged is None else bool(start_converged[0])
    if 0 not in at_best and start0_converged:
        status = "local optimum"
        message = (
            f"local optimum: the starting values stopped at cost {costs[0]:.6g}; start "
            f"{best_index + 1} reached a lower cost {best:.6g} ({len(at_best)} of "
            f"{len(costs)} starts reached it) and its estimate is reported"
        )
    else:
        status, message = "converged", "converged"
        if 0 not in at_best:
            message += (
                f" (the starting values ran out of steps at cost {costs[0]:.6g}; start "
                f"{best_index + 1} converged at the lowest cost {best:.6g}, reported)"
            )
        elif len(costs) > 1 and len(at_best) < len(costs):
            message += (
                f" ({len(at_best)} of {len(costs)} starts reached the lowest cost; the "
                "others stopped in local optima)"
            )
    return status, message + _unidentified_note(unidentified), at_best


Z95 = 1.959963984540054  # two-sided 95 % normal quantile


def correlation(report: IdentifiabilityReport, covariance=None) -> np.ndarray:
    """Correlation matrix of the raw coordinates (NaN rows/columns where undetermined), of
    `covariance` (default: the report's Gauss-Newton covariance)."""
    cov = report.covariance_raw if covariance is None else np.asarray(covariance)
    sd = np.where(report.undetermined, np.nan, np.sqrt(np.clip(np.diag(cov), 0, None)))
    with np.errstate(invalid="ignore", divide="ignore"):
        return cov / np.outer(sd, sd)


def parameter_estimates(
    free_flat,
    raw,
    report: IdentifiabilityReport,
    labels=None,
    owners=None,
    *,
    covariance_hac=None,
    headline: str = "gauss-newton",
) -> tuple:
    """One `ParameterEstimate` per raw coordinate: SI value, delta-method standard error and a
    95 % interval mapped through the transform (so bounds and positivity are respected).

    A parameter reported "not identifiable" or "at bound" (or touching an undetermined
    direction) gets NaN standard error and interval: no confident-looking number for what
    the data cannot tell. `headline` ("gauss-newton" or "hac") chooses which covariance gives
    `se` and `ci95`; both standard errors are kept.
    """
    undetermined = report.undetermined

    def sds(cov):
        if cov is None:
            return np.full(len(free_flat), np.nan)
        return np.where(undetermined, np.nan, np.sqrt(np.clip(np.diag(cov), 0, None)))

    sd_gn, sd_hac = sds(report.covariance_raw), sds(covariance_hac)
    sd_head = sd_hac if headline == "hac" else sd_gn
    bounds = report.bounds or (None,) * len(free_flat)
    out = []
    for k, p in enumerate(free_flat):
        # the value and both interval ends through the transform in one call (not three)
        half = 0.0 if not np.isfinite(sd_head[k]) else Z95 * sd_head[k]
        value, lo, hi = (float(v) for v in p.to_value(raw[k] + np.array([0.0, -half, half])))
        verdict = report.verdicts[k]
        deriv = abs(p.value_derivative(raw[k]))
        blank = verdict in ("not identifiable", "at bound", "not needed")
        se_gn = float("nan") if blank else deriv * sd_gn[k]
        se_hac = float("nan") if blank else deriv * sd_hac[k]
        if blank or not np.isfinite(sd_head[k]):
            se, ci = float("nan"), (float("nan"), float("nan"))
        else:
            se = deriv * sd_head[k]
            ci = (min(lo, hi), max(lo, hi))
            verdict = interval_verdict(verdict, ci)  # > WEAK_FACTOR wide: weakly identified
        prior = (float(p.prior_median), float(p.prior_log_sd)) if p.has_prior else None
        label = labels[k] if labels is not None else p.path
        owner = owners[k] if owners is not None else None
        out.append(
            ParameterEstimate(
                label,
                p.path,
                p.unit,
                value,
                se,
                ci,
                verdict,
                owner,
                prior,
                se_gauss_newton=float(se_gn),
                se_hac=float(se_hac),
                se_method=headline,
                bound=bounds[k] if bounds[k] in ("lower", "upper") else None,
            )
        )
    return tuple(out)


def _labels(problem, experiments):
    """Display name and owning experiment (None if shared) of each raw coordinate."""
    return _problem.labels(problem.shared, problem.per_exp, experiments)


@dataclasses.dataclass(frozen=True)
class ValidationResult:
    """Free-run simulation of runs not used for fitting (physical parameters held fixed).

    Only per-run nuisance parameters (offsets, drift, initial state) are re-estimated on each
    validation run, as MATLAB `compare` estimates initial conditions; `fit_percent` is
    simulation fit %, never one-step prediction. Per run name: `fit_percent`,
    `fit_percent_robust`, `noise_ceiling` ((n_y,) per output), `n_outliers`; `residuals`: the
    residual analysis of the validation runs (with process noise: of their one-step
    innovations, as the fit's); `goodness_of_fit`: against the known noise
    (None when the fit estimated it); `parameters`: the per-run values re-fitted on the
    validation runs (`ParameterEstimate`s with `experiment` set to the run; empty when the
    fit has no per-run parameter).
    """

    experiments: tuple
    predictions: tuple  # (N, n_y) SI per run
    fit_percent: dict  # every valid frame
    fit_percent_robust: dict  # without the frames flagged as outliers
    n_outliers: dict
    noise_ceiling: dict
    residuals: ResidualAnalysis
    goodness_of_fit: GoodnessOfFit | None = None
    horizon: str = "simulation"
    parameters: tuple = ()
    runs: tuple = ()  # process noise: `RunDiagnostics` per run (innovations, every horizon)
    # least squares: per run (N, n_y) sd of the shared physics' simulated response (delta
    # method, the fit's covariance; per-run values at the model's own): the 95 % band
    prediction_sd: tuple = ()

    def refitted(self, run: str) -> dict:
        """{path: ParameterEstimate} re-fitted on validation run `run`."""
        return {p.path: p for p in self.parameters if p.experiment == run}


def validate(
    result: FitResult, experiments: Sequence[Experiment], **fit_kwargs
) -> ValidationResult:
    """Score fitted physics on new runs: re-fit only per-experiment parameters, then simulate
    (process noise: also filter, scoring the innovations and every horizon in `runs`), with
    the fit's adaptive-solver settings (`FitResult.solver`) unless `fit_kwargs` give others."""
    per_exp = [p for p in result.free if p.per_experiment]
    experiments = tuple(experiments)
    if not experiments:
        raise ValueError("experiments: no validation runs given")
    for key, value in result.solver.items():  # the fit's own, unless given here
        fit_kwargs.setdefault(key, value)
    if result.process_noise:
        from greybox._estimate.likelihood import validate_runs

        pairs = validate_runs(result, experiments)
        diags = tuple(d for d, _ in pairs)
        preds = [d.y_simulation for d in diags]
        # the residual test of a process-noise model is on its one-step innovations, on the
        # validation runs as on the estimation runs (its simulation is expected to wander)
        one_step = [d.y_one_step for d in diags]
        scores = _validation_scores(experiments, preds, result.sigma, False, 0, one_step)
        refit = tuple(p for _, ps in pairs for p in ps)
        return dataclasses.replace(scores, parameters=refit, runs=diags)
    known = result.noise_known
    z, sd, ok = _shared_response(result, experiments, fit_kwargs)
    if not per_exp:
        if not ok:
            raise SolverFailed(f"validate: a validation run's simulation failed: {SOLVER_FAILED}")
        scores = _validation_scores(experiments, z, result.sigma, known, 0)
        return dataclasses.replace(scores, prediction_sd=tuple(sd))
    fit_kwargs.setdefault("method", result.method)
    fit_kwargs.setdefault("loss", result.loss)
    if not all(e.sigma is not None for e in experiments):
        fit_kwargs.setdefault("sigma", result.sigma)
    nuisance = fit(result.model, experiments, per_exp, **fit_kwargs)
    preds = [nuisance.predictions[e.name]["simulation"] for e in experiments]
    scores = _validation_scores(experiments, preds, result.sigma, known, nuisance.n_params)
    return dataclasses.replace(
        scores, parameters=tuple(nuisance.parameters), prediction_sd=tuple(sd)
    )


def _shared_response(result: FitResult, experiments, fit_kwargs) -> tuple[list, list, bool]:
    """(per run (N, n_y) simulation, its sd from the shared parameters' covariance (NaN where
    it cannot be had), every simulation succeeded) of the fitted physics on `experiments`
    (per-run values at the model's own), with the fit's solver settings (`fit_kwargs`
    solver_*): one compiled simulation with its sensitivities."""
    shared = tuple(p for p in result.free if not p.per_experiment)
    solver = [fit_kwargs.get(k) for k in ("solver_rtol", "solver_atol", "solver_max_steps")]
    solver = [d if v is None else v for v, d in zip(solver, (1e-8, 1e-10, 16384))]
    problem = _Problem.build(
        result.model, experiments, shared, result.method, "l2", 1.5, 4.0, *solver
    )
    n = len(shared)
    z, ok, jac = jax.device_get(_response(problem, jnp.asarray(result.raw[:n])))
    cov = np.asarray(result.covariance_raw, dtype=float)[:n, :n]
    finite = np.all(np.isfinite(result.raw[:n]))
    preds = [np.asarray(z[i, : e.n_frames]) for i, e in enumerate(experiments)]
    sds = _response_sd(jac, cov, experiments, np.asarray(ok) & finite)
    return preds, sds, bool(np.all(ok))


def _validation_scores(experiments, preds, sigma, known: bool, n_params: int, tested=None):
    """The `ValidationResult` of simulations `preds`; its residual test is on `tested` (the
    predictions whose residuals are tested; default `preds`)."""
    fits, robust, outl, ceilings, scaled = _scored_runs(experiments, preds, sigma)
    gof = goodness_of_fit(scaled, [e.mask for e in experiments], n_params) if known else None
    tested = preds if tested is None else tested
    return ValidationResult(
        experiments,
        tuple(preds),
        fits,
        robust,
        outl,
        ceilings,
        analyse_residuals(_residual_runs(experiments, tested)),
        gof,
    )


def _scored_runs(experiments, preds, sigma) -> tuple:
    """Per run {name: value}: (simulation fit % per output (n_y,) on every valid frame, fit %
    without the readings more than OUTLIER_SIGMAS from the model, the number of such readings
    (int), the noise ceiling per output), and per run the residuals scaled by each reading's
    noise sd (`_frame_sigma` from `sigma`). All runs in one stacked pass.

    The first is MATLAB `compare`'s figure (per output channel, as `compare` reports it) and
    the honest headline: a model that drifts away from the data loses fit % for it. The
    second shows what a few corrupted camera frames cost; reports label both. The ceiling is
    the fit % the true model would score at this noise on the unflagged readings (a few
    corrupted frames would otherwise inflate std(y) and the ceiling with it); compare it with
    the second figure.
    """
    return _scored_runs_many([(experiments, preds, sigma)])[0]


def _scored_runs_many(fits) -> list:
    """`_scored_runs` of each (experiments, predictions, sigma) of `fits` (of one number of
    outputs), every run of every fit in one stacked pass (`fit_batch` passes a wave's
    devices)."""
    runs = [
        (e, zi, sigma) for experiments, preds, sigma in fits for e, zi in zip(experiments, preds)
    ]
    s_frames = [np.broadcast_to(_frame_sigma(e, sigma), e.y.shape) for e, _, sigma in runs]
    y = padded_stack([e.y for e, _, _ in runs], np.nan)
    z = padded_stack([np.asarray(zi, dtype=float) for _, zi, _ in runs], np.nan)
    s = padded_stack(s_frames, 1.0)
    with np.errstate(invalid="ignore"):
        scaled_all = (y - z) / s
        flagged = (np.abs(scaled_all) > OUTLIER_SIGMAS) & np.isfinite(y)
    clean = np.where(flagged, np.nan, y)
    fit_all, robust_all = fit_percent_per_output(y, z), fit_percent_per_output(clean, z)
    outliers_all, ceilings_all = flagged.sum(axis=(1, 2)), noise_ceiling_per_output(clean, s)
    out, k = [], 0
    for experiments, _, _ in fits:
        names, own = [e.name for e in experiments], slice(k, k + len(experiments))
        out.append(
            (
                dict(zip(names, fit_all[own])),
                dict(zip(names, robust_all[own])),
                {n: int(c) for n, c in zip(names, outliers_all[own])},
                dict(zip(names, ceilings_all[own])),
                [scaled_all[k + j, : e.n_frames] for j, e in enumerate(experiments)],
            )
        )
        k += len(experiments)
    return out
