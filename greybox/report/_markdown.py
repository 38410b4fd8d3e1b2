"""Markdown fit reports (pure: results in, text out; no files, no printing).

The report states plainly what every number is: fit % are free-run simulation (the model
driven by the laser waveform alone, never corrected by measured outputs), one figure per
output channel; sigma is estimated from the residuals or known; outliers are flagged at a
fixed threshold; each parameter carries a verdict on whether the data determine it. Its
first lines say whether the estimate is valid (the fit's status) and whether the residuals
are white (a model that misses dynamics leaves structure in them, however good its fit %).
"""

from __future__ import annotations

import numpy as np

from greybox._estimate.metrics import OUTLIER_SIGMAS
from greybox._estimate.metrics import noise_ceiling as noise_ceiling
from greybox._estimate.residuals import (
    OUTLIER_SCALES,
    SHUFFLES_TEXT,
    _ranges,
    p_phrase,
    p_value_text,
)
from greybox._estimate.result_text import display_unit as display_unit
from greybox._estimate.result_text import estimate_texts as estimate_texts
from greybox._estimate.result_text import fmt as fmt
from greybox._estimate.result_text import verdict_text as _verdict_text

VERDICT_MEANING = {
    "identifiable": "the data alone pin it down (its 95 % interval comes from the data)",
    "weakly identified": "the data determine it only roughly: its 95 % interval spans more "
    "than a factor 10 (upper / lower), so read the value as an order of magnitude",
    "prior-dominated": "its value and interval mostly restate the prior you gave; the data "
    "did not shrink the prior's spread by 2x",
    "not identifiable": "the data do not determine it (only a combination with other "
    "parameters is known); no interval is reported",
    "at bound": "the fit ended on one of its bounds: the estimate is the boundary, not what "
    "the data say, and no interval is reported",
    "not needed": "a noise intensity, variance or sd that went to zero: the data need no such "
    "noise (no process noise on that state, or no measurement noise beyond the process "
    "noise); the fit stays valid, no interval is reported",
}

STATUS_MEANING = {
    "converged": "an interior optimum; the estimate is valid",
    "local optimum": "the starting values led to a higher optimum than another start; the "
    "best start's estimate is reported and valid, but the cost surface has several minima",
    "at bound": "a parameter ended on one of its bounds; the estimate is NOT valid",
    "ran out of steps": "the optimiser used its whole step budget before meeting its "
    "tolerances ([fit] max_steps); the estimate is NOT valid",
    "not converged": "the optimiser stopped before meeting its tolerances; the estimate is "
    "NOT valid",
    "diverged": "the fit diverged; there is no estimate",
}


def channel_unit(channel) -> tuple[float, str]:
    """(factor from SI, unit) to show a channel's values in: the readable unit (um, mW) when
    the channel declares it, else the channel's own first declared unit (a heating power
    declared in W stays in W, a user's x_mm output in mm), else its SI unit."""
    factor, unit = display_unit(channel.si_unit)
    units = getattr(channel, "units", None) or {}
    if unit == channel.si_unit or unit in units or not units:
        return factor, unit
    for name, conv in units.items():
        if conv is not None and conv[1] == 0.0 and conv[0] > 0:
            return 1.0 / conv[0], name
    return 1.0, channel.si_unit


def _value_cells(p) -> list[str]:
    value, ci, unit = estimate_texts(p)
    f, _ = display_unit(p.unit, p.value)
    return [value, unit if unit != "1" else "-", fmt(p.se * f, 2), ci]


def parameter_table(
    parameters, *, truth: dict | None = None, both_errors: bool = False
) -> list[str]:
    """Markdown table rows for `ParameterEstimate`s (optionally with a true-value column).

    `both_errors` adds the Gauss-Newton and the Newey-West (HAC) standard errors beside the
    headline one (which of the two the headline is: `ParameterEstimate.se_method`)."""
    head = ["parameter", "value", "unit", "std. error", "95 % interval", "verdict"]
    if both_errors:
        head += ["s.e. Gauss-Newton", "s.e. HAC (Newey-West)"]
    if truth is not None:
        head.insert(2, "true")
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in parameters:
        cells = [f"`{p.name}`", *_value_cells(p), _verdict_text(p)]
        if both_errors:
            f, _ = display_unit(p.unit, p.value)
            cells += [fmt(p.se_gauss_newton * f, 2), fmt(p.se_hac * f, 2)]
        if truth is not None:
            f, _ = display_unit(p.unit, p.value)
            t = truth.get(p.name)
            cells.insert(2, fmt(t * f, 5) if t is not None else "-")
        rows.append("| " + " | ".join(cells) + " |")
    return rows


def _output_names(n_y: int, outputs) -> tuple:
    if outputs is not None and len(outputs) == n_y:
        return tuple(outputs)
    return tuple(f"output {j + 1}" for j in range(n_y))


def _run_rows(result, validation, runs, outputs=None) -> list[str]:
    """One row per run and output channel: frames, outliers, fit %, noise ceiling, and the
    run's own Ljung-Box p-value."""
    info = {r.name: r for r in runs}
    n_y = result.n_outputs
    names = _output_names(n_y, outputs)
    multi = n_y > 1
    head = (
        ["run", "role"]
        + (["output"] if multi else [])
        + [
            "input waveform",
            "frames (valid)",
            "outliers flagged",
            "fit % (simulation, all valid frames)",
            "fit % without flagged frames",
            "noise ceiling % (unflagged frames)",
            "whiteness p (Ljung-Box)",
        ]
    )
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]

    def add(res, role):
        tests = {r.name: r for r in res.residuals.runs}
        for e in res.experiments:
            r = info.get(e.name)
            t = tests.get(e.name)
            for j in range(n_y):
                valid = int(e.mask[:, j].sum())
                cells = [e.name, role] + ([names[j]] if multi else [])
                cells += [
                    r.waveform if r else "-",
                    f"{e.n_frames} ({valid})",
                    str(res.n_outliers[e.name]) if j == 0 else "",
                    fmt(res.fit_percent[e.name][j], 3),
                    fmt(res.fit_percent_robust[e.name][j], 3),
                    fmt(res.noise_ceiling[e.name][j], 3),
                    p_value_text(t.p_value[j]) if t is not None else "n/a",
                ]
                rows.append("| " + " | ".join(cells) + " |")

    add(result, "estimation")
    if validation is not None:
        add(validation, "validation")
    return rows


def status_lines(result, validation=None) -> list[str]:
    """The first lines of a report: is the estimate valid, are the residuals white."""
    status = result.status
    head = f"**Fit status: {status}** ({STATUS_MEANING.get(status, '')})"
    lines = [head + ("." if status == "converged" else f": {result.message}.")]
    lines.append(f"**Residuals (estimation runs): {result.residuals.verdict}.**")
    if validation is not None:
        lines.append(f"**Residuals (validation runs): {validation.residuals.verdict}.**")
    if result.goodness_of_fit is not None:
        lines.append(
            f"**Against the known noise: {result.goodness_of_fit.line}.** A ratio well above "
            "1 means the model leaves more than noise."
        )
    return lines


RESIDUALS_ARE = "Residuals are measured - model (free-run simulation)"
INNOVATIONS_ARE = (
    "The residuals tested are the innovations: measured - the filter's one-step prediction "
    "(white when the model, its process noise included, leaves only noise)"
)


def residual_lines(
    result, validation=None, outputs=None, residuals_are: str = RESIDUALS_ARE
) -> list[str]:
    """The residual analysis in words: the test, its verdict per output and set of runs,
    lags outside the band, correlation with the inputs, and how frames were handled;
    `residuals_are` says what was tested."""
    names = _output_names(result.n_outputs, outputs)
    lines = []
    for label, res in (("estimation", result), ("validation", validation)):
        if res is None:
            continue
        a = res.residuals
        lines.append(f"- {label.capitalize()} runs: {a.verdict}.")
        for j in range(len(a.q)):
            lags = a.lags_outside[j]
            out = f"lags outside the band: {_ranges(lags)}" if lags else "no lag outside the band"
            lines.append(
                f"  - {names[j]}: Q = {fmt(a.q[j], 4)} on {a.dof} dof, "
                f"{p_phrase(a.p_value[j])}; {out}."
            )
        lines += [f"  - {c}." for c in a.cross_lines()]
        lines += [f"  - Note: {n}." for n in a.notes]
    lines += [
        "",
        f"{residuals_are}. Autocorrelation over lags 1-"
        f"{result.residuals.max_lag} frames and cross-correlation with each input, with 99 % "
        "bands, as MATLAB `resid`; Ljung-Box statistic over lags 1-"
        f"{result.residuals.test_lag} pooled over the runs of each set, its p-value from "
        f"{SHUFFLES_TEXT} among each run's frames (the chi-square "
        "tail beyond their resolution; whiteness rejected at p < 0.01, split over the "
        "outputs). Frames sit on "
        "a uniform grid at the median frame interval; dropped frames leave empty slots and "
        "only pairs "
        "of valid frames enter a correlation; readings further than "
        f"{OUTLIER_SCALES:g} robust scales from the median residual are left out. A white "
        "result says the model leaves only noise; structure at short lags points at missing "
        "fast dynamics, at long lags at a missing slow mode or drift.",
    ]
    return lines


def error_lines(result) -> list[str]:
    """Which standard errors are the headline and why."""
    from greybox._estimate.verdict import standard_error_text  # never "allows for" when narrower

    why = standard_error_text(result)
    return [
        f"Standard errors: {why}. HAC: the part of the residuals explained by the inputs "
        "(an FIR model-error model, Ljung and Guo 1997) is removed first, the score "
        "contributions are prewhitened by a VAR(1) (Andrews and Monahan 1992), then a "
        f"Bartlett kernel with bandwidth {result.hac_bandwidth} frames (Andrews' 1991 AR(1) "
        "plug-in rule) and an n/(n-k) degrees-of-freedom factor.",
    ]


def identifiability_lines(result, parameter_notes: dict | None = None) -> list[str]:
    """The identifiability verdict in words, naming any undetermined combination."""
    notes = parameter_notes or {}
    ident = result.identifiability
    verdicts = {p.name: p.verdict for p in result.parameters}
    shared = [p for p in result.parameters if p.experiment is None]
    lines = []
    pinned = [p for p in result.parameters if p.verdict == "at bound"]
    determined = ("identifiable", "weakly identified", "at bound")
    bad = [p.name for p in result.parameters if p.verdict not in determined]
    weak = [p.name for p in result.parameters if p.verdict == "weakly identified"]
    if pinned:
        lines.append(
            f"**{len(pinned)} fitted value(s) ended on a bound:** "
            + ", ".join(f"`{p.name}` ({p.bound} bound)" for p in pinned)
            + ". The optimum the data want lies beyond the bound; identifiability is not "
            "the question for these, the model or its bounds are."
        )
        lines.append("")
    if not bad and not pinned and not weak:
        lines.append(
            "**Verdict: every fitted parameter is identifiable** from these data "
            "(no parameter combination is left undetermined)."
        )
    elif not bad:
        lines.append("Every other fitted parameter is identifiable from these data.")
    else:
        lines.append(
            f"**Verdict: {len(bad)} of {len(result.parameters)} fitted values are not "
            f"determined by the data alone:** "
            + ", ".join(f"`{n}` ({verdicts[n]})" for n in bad)
            + "."
        )
    if weak:  # determined by the data, but only to within a factor > 10
        lines.append(
            "Weakly identified (the 95 % interval spans more than a factor 10): "
            + ", ".join(f"`{n}`" for n in weak)
            + "."
        )
    if ident.weak_directions:
        lines += [
            "",
            "Parameter combinations the data do not determine (raw coordinates; "
            "a log or logit of each parameter):",
            "",
        ]
        for w in ident.weak_directions:
            names = sorted({_label_path(k) for k in w.combination})
            joined = " x ".join(f"`{n}`" for n in names)
            lines.append(
                f"- {joined}: the data fix their combined effect but not each one "
                f"(undetermined direction in raw coordinates: {w.describe()})."
            )
            for n in names:
                if n in notes and notes[n]:
                    lines.append(f"  - `{n}`: {notes[n]}")
    lines += [
        "",
        f"Singular values of the column-scaled weighted Jacobian: "
        f"{', '.join(fmt(s, 3) for s in ident.singular_values)} (condition number "
        f"{fmt(ident.condition_number, 3)}).",
    ]
    strong = []
    k = len(shared)
    corr = np.asarray(result.correlation)[:k, :k]
    for i in range(k):
        for j in range(i + 1, k):
            if np.isfinite(corr[i, j]) and abs(corr[i, j]) > 0.9:
                strong.append(f"`{shared[i].name}`-`{shared[j].name}` {corr[i, j]:+.3f}")
    if strong:
        lines.append(
            "Strongly correlated shared parameters (|r| > 0.9): " + ", ".join(strong) + "."
        )
    elif k > 1:
        lines.append(
            f"Largest correlation between shared parameters: "
            f"{_max_offdiag(corr):+.3f} (|r| > 0.9 would signal a trade-off)."
        )
    return lines


def _label_path(raw_label: str) -> str:
    """``logit(absorptance)`` / ``log(thermal.tau_s - 0.0001)`` / ``x/1e-06`` -> the path."""
    inner = raw_label
    for fn in ("logit(", "log("):
        if inner.startswith(fn):
            inner = inner[len(fn) : -1]
    return inner.split(" - ")[0].split("/")[0].split("[")[0]


def _max_offdiag(corr) -> float:
    k = corr.shape[0]
    off = [corr[i, j] for i in range(k) for j in range(k) if i != j and np.isfinite(corr[i, j])]
    return max(off, key=abs) if off else float("nan")


def fit_report(
    result,
    validation=None,
    *,
    title: str,
    device_name: str,
    runs=(),
    parameter_notes: dict | None = None,
    figures=(),
    source: str = "",
    output_unit: str = "m",
    outputs: tuple | None = None,
    physical_ranges: dict | None = None,
    metrics=(),
    noise_table=None,
) -> str:
    """Markdown report of a fit (and its validation) for people who did not run it.

    It opens with the headline verdict (`greybox._estimate.verdict`), its fitted values checked
    against `physical_ranges` ({path: PhysicalRange}).

    - `result`: `greybox.FitResult`; `validation`: `greybox.ValidationResult` or None.
    - `runs`: per-run info with `name` and `waveform` (one-line laser description).
    - `parameter_notes`: {path: what limits its identifiability} from the device table.
    - `figures`: relative paths of figures to link; `source`: where the data came from.
    - `output_unit`: SI unit of the measured outputs (for sigma); `outputs`: their names
      (default "output 1", ...).
    - `metrics`: rows (run, role, output, horizon, unit, n, fit %, RMSE, MAE, SAE) of the
      result folder (a process-noise fit's report tabulates every horizon);
      `noise_table`: the `[noise]` settings of a process-noise fit.
    """
    if getattr(getattr(result, "noise", None), "name", "") == "process noise":
        return process_report(
            result,
            validation,
            title=title,
            device_name=device_name,
            source=source,
            outputs=outputs,
            metrics=metrics,
            noise_table=noise_table,
            figures=figures,
            physical_ranges=physical_ranges,
        )
    shared = [p for p in result.parameters if p.experiment is None]
    per_run = [p for p in result.parameters if p.experiment is not None]
    n_frames = sum(e.n_frames for e in result.experiments)
    sigma_f, sigma_u = display_unit(output_unit)
    n_out = sum(result.n_outliers.values())
    from greybox._estimate.verdict import fit_headline

    head = fit_headline(result, physical_ranges or {})
    lines = [f"# greybox fit: {title}", "", *head.lines, "", *status_lines(result, validation), ""]
    if source:
        lines += [source, ""]
    lines += [
        f"Device model `{device_name}`; {len(result.experiments)} estimation runs "
        f"({n_frames} frames, {result.n_data} valid readings fitted)"
        + (
            f", {len(validation.experiments)} validation runs"
            if validation is not None
            else ", no validation runs"
        )
        + ".",
        "",
        "**All fit % in this report are free-run simulation**: the model is driven by the "
        "inputs alone from its initial state and never corrected by the measured outputs. They "
        "are not one-step-ahead prediction (which re-uses each measured frame and scores far "
        "higher on slow systems). Fit % = 100 (1 - |y - y_model| / |y - mean(y)|), as "
        "MATLAB `compare`; 100 is perfect, 0 is no better than the mean.",
        "",
        "## Parameters",
        "",
        *parameter_table(shared, both_errors=True),
        "",
    ]
    if per_run:
        lines += [
            "Per-run nuisance values (one per estimation run):",
            "",
            *parameter_table(per_run, both_errors=True),
            "",
        ]
    lines += [
        "Verdicts: " + "; ".join(f"*{k}*: {v}" for k, v in VERDICT_MEANING.items()) + ".",
        "",
        *error_lines(result),
        "",
        "## Fit per run (simulation)",
        "",
        *_run_rows(result, validation, runs, outputs),
        "",
    ]
    ceiling_sigma = (
        "the known noise level"
        if result.noise_known
        else "the noise sigma estimated from the residuals (inflated by any misfit, so the "
        "ceiling is then too low: trust it only when the residuals are white)"
    )
    lines += [
        "Fit % and noise ceiling are per output channel (channels are never pooled). Noise "
        f"ceiling: the fit % that the true model would score given {ceiling_sigma}, about "
        "100 (1 - sigma / std(y)) over the frames not flagged as outliers (compare it with "
        "the fit % without flagged frames); a run whose fit % is close to it is fitted down "
        "to the measurement noise, whatever the absolute number.",
        "",
    ]
    if validation is not None:
        refit = ", ".join(sorted({p.path for p in per_run}))
        lines += [
            "Validation runs are simulated with the fitted physical parameters held fixed"
            + (
                f"; only their per-run values ({refit}) are re-estimated, as MATLAB "
                "`compare` estimates initial conditions."
                if refit
                else "."
            ),
            "",
        ]
    sigmas = ", ".join(fmt(s * sigma_f, 3) for s in result.sigma)
    noise = {
        "estimated": "estimated from the residuals (robust median-absolute-deviation scale), "
        "then the fit was repeated at that scale",
        "declared": "known (declared by the user): the readings are weighted by it and it is "
        "not re-estimated",
        "per-frame": "known per frame (RMS shown): each reading is weighted by its own level "
        "and the noise is not re-estimated",
    }[result.sigma_source]
    lines += [
        "## Residual analysis",
        "",
        *residual_lines(result, validation, outputs),
        "",
        "## Noise, outliers and convergence",
        "",
        f"- Measurement noise sigma: **{sigmas} {sigma_u}**, {noise}.",
        f"- Outliers flagged: **{n_out}** frames further than {OUTLIER_SIGMAS:g} sigma from the "
        f"model (estimation runs); the {result.loss} loss limits their pull. The headline "
        "fit % counts every valid frame; the column beside it leaves the flagged frames out. "
        "On a validation run, many flagged frames mean the model drifts from the data, not "
        "that the sensor failed.",
        f"- Frames: {n_frames} in estimation runs, {result.n_data} valid readings fitted; "
        f"{result.n_params} fitted values.",
        f"- Status: **{result.status}**"
        f"{'' if result.valid else ' (the estimate is NOT valid)'}: {result.message}; "
        f"optimiser {'converged' if result.converged else 'NOT CONVERGED'} after "
        f"{result.n_steps} Levenberg-Marquardt steps, cost {fmt(result.cost, 6)}, simulation "
        f"path `{result.method}`.",
    ]
    if result.goodness_of_fit is not None:
        lines.append(
            f"- Goodness of fit against the known noise: {result.goodness_of_fit.line} "
            "(all valid readings of the estimation runs)."
        )
    if len(result.multistart_costs) > 1:
        lines.append(
            f"- Multi-start: {len(result.multistart_costs)} starts (the first from the given "
            f"values), {result.n_starts_at_best} reached the lowest cost; start "
            f"{result.best_start + 1} is reported. Costs (at the first noise scale): "
            + ", ".join(
                f"{fmt(c, 6)}{'' if ok else ' (not converged)'}"
                for c, ok in result.multistart_costs
            )
        )
    lines += ["", "## Identifiability", "", *identifiability_lines(result, parameter_notes), ""]
    if figures:
        lines += ["## Figures", ""]
        lines += [f"- [{f}]({f})" for f in figures]
        lines.append("")
    return "\n".join(lines)


def _text(x, spec: str) -> str:
    """A metric for the report: formatted, or n/a where undefined."""
    return "n/a" if x is None else format(x, spec)


def process_report(
    result,
    validation=None,
    *,
    title: str,
    device_name: str,
    source: str = "",
    outputs: tuple | None = None,
    metrics=(),
    noise_table=None,
    figures=(),
    physical_ranges: dict | None = None,
) -> str:
    """Markdown report of a process-noise (maximum-likelihood, Kalman filter) fit: the
    headline verdict (`greybox._estimate.verdict`, its residual test on the one-step innovations),
    status, likelihood and criteria, parameters with intervals and verdicts, fit % per run,
    output and horizon (simulation, one-step, k-step prediction), the innovations'
    whiteness (the headline's residual test, on the estimation and the validation runs)."""
    from greybox._estimate.verdict import fit_headline

    k = result.k_step
    structure = result.noise.structure
    fixed = dict(getattr(noise_table, "fixed", {}) or {})
    status = result.status
    head = f"**Fit status: {status}** ({STATUS_MEANING.get(status, '')})"
    # the headline's residual test, on the innovations, is the one the report shows
    tested = validation if getattr(validation, "residuals", None) is not None else None
    lines = [
        f"# greybox fit: {title} (stochastic grey-box fit)",
        "",
        *fit_headline(result, physical_ranges or {}).lines,
        "",
        head + ("." if status == "converged" else f": {result.message}."),
        f"**Innovations (estimation runs): {result.residuals.verdict}.**",
        *(
            [f"**Innovations (validation runs): {tested.residuals.verdict}.**"]
            if tested is not None
            else []
        ),
        "",
    ]
    if source:
        lines += [source, ""]
    initial = getattr(noise_table, "initial_state", "known")
    lines += [
        f"Device `{device_name}`. **Likelihood:** {result.likelihood} ({result.filter_name}); "
        f"{result.n_steps} optimiser steps.",
        "",
        f"Noise model: {structure.describe()}; measurement noise per output"
        + (f"; held fixed: {fixed}" if fixed else "")
        + ". Intensities are of the Wiener increments (variance per second). Initial state: "
        + (
            "known (each run's first reading is conditioned on, not scored)"
            if initial == "known"
            else "diffuse (a vague prior; the first reading conditioned on)"
            if initial == "diffuse"
            else f"declared sd {initial} (state units; every reading scored)"
        )
        + ".",
        "",
        f"log L = {fmt(result.log_likelihood, 8)} over {result.n_observations} readings; "
        f"AIC {fmt(result.aic, 8)}, BIC {fmt(result.bic, 8)}.",
        "",
        "## Parameters",
        "",
        "Standard errors from the inverse observed information (Hessian of -log L); 95 % "
        "intervals mapped through each parameter's transform.",
        "",
        *parameter_table(result.parameters),
        "",
        "Verdicts: " + "; ".join(f"*{k_}*: {v}" for k_, v in VERDICT_MEANING.items()) + ".",
        "",
        "## Fit per run, output and horizon",
        "",
        "Simulation: the deterministic model from the initial state, no reading used. One-step "
        "prediction: the filter's prediction of each reading from the readings before it. "
        f"{k}-step prediction: each reading predicted from the readings up to {k} frames "
        f"before it (from the initial state for the first {k} frames).",
        "",
        "| run | role | output | horizon | fit % | RMSE | SAE | unit |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for run, role, out, horizon, unit, n, fp, rmse, mae, sae in metrics:
        lines.append(
            f"| {run} | {role} | {out} | {horizon} | {_text(fp, '.2f')} | "
            f"{_text(rmse, '.4g')} | {_text(sae, '.4g')} | {unit} |"
        )
    lines += [
        "",
        "## Innovations whiteness",
        "",
        *residual_lines(result, tested, outputs, INNOVATIONS_ARE),
    ]
    if figures:
        lines += ["", "## Figures", ""]
        lines += [f"- [{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"
