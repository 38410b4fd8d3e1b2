"""Comparing model structures fitted to the same estimation runs.

Each candidate (a set of structural options and a free list) is fitted to the same runs; this
module scores the fits. The information criteria use the Gaussian log-likelihood of the
free-run simulation residuals of every valid reading, with each output's noise variance at its
maximum-likelihood value (the mean squared residual of that output):

    log L = sum_j -n_j / 2 (log(2 pi SSE_j / n_j) + 1),
    AIC = -2 log L + 2 k,   BIC = -2 log L + k log n,

k = every fitted value (shared and per-run) plus one noise variance per output, n = the number
of valid readings. A process-noise candidate brings its own maximum log-likelihood (the Kalman
filter's prediction-error decomposition over its scored readings), k = every fitted value
(noise parameters included). The rule that names the preferred structure uses estimation data
only (AIC by default); validation fit % is shown beside it and never used to choose.

Nested pairs (a candidate that contains another: the same options and a larger free set, or
declared with ``nests = [...]``) also get a likelihood-ratio test: D = 2 (log L_big -
log L_small), referred to chi-square with k_big - k_small degrees of freedom (Wilks); a small
p-value says the larger structure explains the data better than the nested one can.

Across runs: a per-run parameter (an offset, a drift, an ambient temperature fitted on each
estimation run) is either a property of each run or, if its estimates agree, something one
shared value would do. For each per-run path with two or more runs, the Wald test of equality

    X^2 = (C v)' (C V C')^-1 (C v),   C v = the differences v_i - v_m,

with V the joint covariance of the per-run estimates (the fit's headline covariance mapped to
values by the delta method, correlations included), is referred to chi-square with m - 1
degrees of freedom; p < `RUN_ALPHA` flags the parameter "run-specific": chosen on one run, it
does not hold on the others. The values re-fitted on the validation runs (physics fixed) join
the test as independent estimates, so a per-run effect chosen on a single estimation run is
held against the validation runs too.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

RULES = ("aic", "bic")
RUN_ALPHA = 0.01  # below this p-value per-run estimates differ between runs: run-specific


@dataclasses.dataclass(frozen=True)
class CandidateScore:
    """How one structure did: its name, options and free list as fitted, the criteria, fit %
    per run and output (estimation and validation, simulation), the residual verdict and the
    fit's status (converged / at bound / local optimum ...), and `note`: what `compare` did
    beyond the fit (a re-start from a nested structure's estimate)."""

    name: str
    options: dict
    free: tuple
    n_params: int
    n_data: int
    loglik: float
    aic: float
    bic: float
    fit_estimation: dict
    fit_validation: dict
    residual_verdict: str
    status: str
    valid: bool
    message: str
    note: str = ""  # how compare treated it beyond the fit (a nested-structure re-start)
    # each fitted value: {"name", "path", "unit", "value", "se", "ci95", "verdict", "run"}
    estimates: tuple = ()
    noise_model: str = "output error"  # or "process noise"
    noise: str = ""  # process noise: its structure in one line (`NoiseStructure.describe`)
    nests: tuple = ()  # names of candidates declared nested in this one
    # per-run paths across runs: {"path", "unit", "runs", "values", "mean", "statistic",
    # "dof", "p_value", "run_specific"} (`run_agreement`)
    run_agreement: tuple = ()


def gaussian_loglik(experiments: Sequence, predictions: Sequence) -> tuple[float, int, int]:
    """(log-likelihood, readings, outputs) of simulation residuals at the ML noise per output."""
    n_y = experiments[0].y.shape[1]
    sse, n = np.zeros(n_y), np.zeros(n_y)
    for e, z in zip(experiments, predictions):
        r = e.y - np.asarray(z).reshape(e.y.shape)
        ok = np.isfinite(r)
        sse += np.where(ok, r, 0.0).__pow__(2).sum(axis=0)
        n += ok.sum(axis=0)
    used = n > 0
    if np.any(sse[used] <= 0):
        return float("inf"), int(n.sum()), int(used.sum())
    ll = -0.5 * n[used] * (np.log(2 * np.pi * sse[used] / n[used]) + 1.0)
    return float(ll.sum()), int(n.sum()), int(used.sum())


def _estimates(result) -> tuple:
    def num(x):
        x = float(x)
        return x if np.isfinite(x) else None

    return tuple(
        {
            "name": p.name,
            "path": p.path,
            "unit": p.unit,
            "value": num(p.value),
            "se": num(p.se),
            "ci95": [num(p.ci95[0]), num(p.ci95[1])],
            "verdict": p.verdict,
            "run": p.experiment,
        }
        for p in result.parameters
    )


def run_agreement(
    estimates: Sequence, covariance_raw=None, validation: Sequence = (), alpha: float = RUN_ALPHA
) -> tuple:
    """The Wald test of equality across runs of each per-run parameter (module text).

    `estimates`: `ParameterEstimate`s (one per raw coordinate, in the covariance's order);
    `covariance_raw`: their raw-coordinate covariance (None: standard errors taken as
    independent); `validation`: the per-run values re-fitted on the validation runs
    (`ValidationResult.parameters`), independent of the estimation runs' (other data), so a
    value chosen on one estimation run is also held against the validation runs. Paths with
    fewer than two runs of finite standard error are left out."""
    from scipy.stats import chi2

    def usable(p):
        return p.experiment is not None and np.isfinite(p.se) and p.se > 0

    groups: dict = {}
    for k, p in enumerate(estimates):
        if usable(p):
            groups.setdefault(p.path, ([], []))[0].append(k)
    for p in validation:
        if usable(p) and p.path in groups:
            groups[p.path][1].append(p)
    cov = None if covariance_raw is None else np.asarray(covariance_raw, dtype=float)
    out = []
    for path, (idx, val) in groups.items():
        if len(idx) + len(val) < 2:
            continue
        v = np.array([estimates[k].value for k in idx] + [p.value for p in val])
        se = np.array([estimates[k].se for k in idx] + [p.se for p in val])
        var = np.diag(se**2)
        if cov is not None and cov.shape[0] == len(estimates):
            sd_raw = np.sqrt(np.clip(np.diag(cov)[idx], 0, None))
            g = se[: len(idx)] / np.where(sd_raw > 0, sd_raw, np.nan)  # d value / d raw
            block = cov[np.ix_(idx, idx)] * np.outer(g, g)  # delta method, correlations kept
            if np.all(np.isfinite(block)):
                var[: len(idx), : len(idx)] = block
        m = v.size
        c = np.eye(m)[:-1] - np.eye(m)[-1]  # v_i - v_m
        d = c @ v
        stat = float(d @ np.linalg.lstsq(c @ var @ c.T, d, rcond=None)[0])
        dof = m - 1
        p_value = float(chi2.sf(max(stat, 0.0), dof))
        w = 1.0 / se**2
        out.append(
            {
                "path": path,
                "unit": estimates[idx[0]].unit,
                "runs": [estimates[k].experiment for k in idx] + [p.experiment for p in val],
                "validation_runs": [p.experiment for p in val],
                "values": [float(x) for x in v],
                "se": [float(x) for x in se],
                "mean": float(np.sum(w * v) / np.sum(w)),
                "statistic": stat,
                "dof": dof,
                "p_value": p_value,
                "run_specific": bool(p_value < alpha),
            }
        )
    return tuple(out)


def run_agreement_text(a: dict) -> str:
    """One line for compare.md: what the test of equality across runs says."""
    test = f"X^2 = {a['statistic']:.4g} on {a['dof']} dof, p = {a['p_value']:.3g}"
    if a["run_specific"]:
        return (
            f"run-specific ({test}): the runs' estimates differ beyond their standard errors, "
            "so it is a property of each run, not of the device; a structure that needs it on "
            "one run must be checked on the others"
        )
    return f"agrees across runs ({test}): one shared value would do"


def _is_process(result) -> bool:
    return getattr(getattr(result, "noise", None), "name", "") == "process noise"


def score(name: str, options: dict, result, validation=None, nests=()) -> CandidateScore:
    """A `CandidateScore` for a `FitResult` (and its `ValidationResult`, if any); `nests`:
    the names of candidates declared nested in this one."""
    fit_val = (
        {r: np.atleast_1d(v) for r, v in validation.fit_percent.items()} if validation else {}
    )
    common = dict(
        name=name,
        options=dict(options),
        free=tuple(p.path for p in result.free),
        fit_estimation={
            r: np.atleast_1d(v) for r, v in (getattr(result, "fit_percent", None) or {}).items()
        },
        fit_validation=fit_val,
        status=result.status,
        valid=bool(result.valid),
        message=result.message,
        estimates=_estimates(result),
        nests=tuple(nests),
        run_agreement=run_agreement(
            result.parameters,
            getattr(result, "covariance_raw", None),
            getattr(validation, "parameters", ()),
        ),
    )
    if _is_process(result):  # the residual test every fit uses, on the innovations
        return CandidateScore(
            n_params=int(result.raw.size),
            n_data=int(result.n_observations),
            loglik=float(result.log_likelihood),
            aic=float(result.aic),
            bic=float(result.bic),
            residual_verdict=f"innovations: {result.residuals.verdict}",
            noise_model="process noise",
            noise=result.noise.structure.describe(),
            **common,
        )
    preds = _simulations(result)
    ll, n, n_out = gaussian_loglik(result.experiments, preds)
    k = int(result.raw.size) + n_out
    return CandidateScore(
        n_params=k,
        n_data=n,
        loglik=ll,
        aic=-2 * ll + 2 * k,
        bic=-2 * ll + k * np.log(max(n, 1)),
        residual_verdict=result.residuals.verdict,
        **common,
    )


def _simulations(result) -> list:
    """Per estimation run, the free-run simulation at the estimate: the one the fit computed
    at its end point when it kept it (no second compile and run of the simulator per run
    shape), else simulated again."""
    stored = getattr(result, "predictions", None) or {}
    sims = [stored.get(e.name, {}).get("simulation") for e in result.experiments]
    if all(s is not None for s in sims):
        return [np.asarray(s).reshape(e.n_frames, -1) for s, e in zip(sims, result.experiments)]
    return [result.predict(i) for i in range(len(result.experiments))]


@dataclasses.dataclass(frozen=True)
class LikelihoodRatio:
    """The likelihood-ratio test of `small` nested in `big`: D = 2 (log L_big - log L_small)
    against chi-square with `dof` = k_big - k_small degrees of freedom."""

    big: str
    small: str
    statistic: float
    dof: int
    p_value: float
    declared: bool  # nested by the user's ``nests`` (else by options and free set)


def nested(scores: Sequence[CandidateScore]) -> list[tuple[int, int, bool]]:
    """(larger, nested, declared) index pairs: the same options and a free set strictly inside
    the larger one's (and the same noise model), or declared by the larger's ``nests``."""
    out = []
    for i, big in enumerate(scores):
        for j, small in enumerate(scores):
            if i == j or big.noise_model != small.noise_model:
                continue
            declared = small.name in big.nests
            if declared or (big.options == small.options and set(small.free) < set(big.free)):
                out.append((i, j, declared))
    return out


def likelihood_ratios(scores: Sequence[CandidateScore]) -> list[LikelihoodRatio]:
    """A likelihood-ratio test per nested pair (see the module text); NaN where a
    log-likelihood is not finite or the larger structure has no more parameters."""
    from scipy.stats import chi2

    out = []
    for i, j, declared in nested(scores):
        big, small = scores[i], scores[j]
        dof = big.n_params - small.n_params
        stat = 2.0 * (big.loglik - small.loglik)
        ok = dof > 0 and np.isfinite(stat)
        p = float(chi2.sf(max(stat, 0.0), dof)) if ok else float("nan")
        out.append(LikelihoodRatio(big.name, small.name, float(stat), int(dof), p, declared))
    return out


def nested_pairs(scores: Sequence[CandidateScore]) -> list[tuple[int, int]]:
    """(larger, nested) index pairs where candidate `nested` has the same options and a free
    set strictly inside `larger`'s, yet a higher log-likelihood on the same estimation data.

    The larger structure contains the nested one (its extra parameters at their starting
    values), so its maximum likelihood can only be at least as high: a lower value means its
    fit stopped at a local optimum, and it should be re-started from the nested estimate."""
    out = []
    for i, big in enumerate(scores):
        for j, small in enumerate(scores):
            if i == j or big.options != small.options or not set(small.free) < set(big.free):
                continue
            tol = 1e-6 * max(1.0, abs(small.loglik))
            if np.isfinite(small.loglik) and not big.loglik >= small.loglik - tol:
                out.append((i, j))
    return out


def preferred(scores: Sequence[CandidateScore], rule: str = "aic") -> CandidateScore | None:
    """The candidate with the lowest criterion among those whose fit is valid (None if none)."""
    if rule not in RULES:
        raise ValueError(f"rule: {rule!r} is unknown; use one of {RULES}")
    ok = [s for s in scores if s.valid and np.isfinite(getattr(s, rule))]
    return min(ok, key=lambda s: getattr(s, rule)) if ok else None
