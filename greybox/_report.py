"""Markdown fit reports (pure: results in, text out; no files, no printing).

The report states plainly what every number is: fit % are free-run simulation (the model
driven by the laser waveform alone, never corrected by measured outputs), sigma is
estimated from the residuals, outliers are flagged at a fixed threshold, and each parameter
carries a verdict on whether the data determine it.
"""

from __future__ import annotations

import numpy as np

from greybox._fit import OUTLIER_SIGMAS

_DISPLAY = {"m": (1e6, "um"), "s": (1e3, "ms"), "m/s": (1e6, "um/s"), "W": (1e3, "mW")}

VERDICT_MEANING = {
    "identifiable": "the data alone pin it down (its 95 % interval comes from the data)",
    "prior-dominated": "its value and interval mostly restate the prior you gave; the data "
    "did not shrink the prior's spread by 2x",
    "not identifiable": "the data do not determine it (only a combination with other "
    "parameters is known); no interval is reported",
}


_PREFIXES = ((1e-3, "k"), (1.0, ""), (1e3, "m"), (1e6, "u"), (1e9, "n"), (1e12, "p"))


def display_unit(unit: str, value: float | None = None) -> tuple[float, str]:
    """(factor, readable unit) for an SI unit: m -> um, W -> mW, s -> ms (when `value` is
    under 1 s or not given); other units get an SI prefix when `value` is tiny or huge."""
    if unit == "s" and value is not None and np.isfinite(value) and abs(value) >= 1.0:
        return 1.0, "s"
    if unit in _DISPLAY:
        return _DISPLAY[unit]
    # Other units get an SI prefix when the number would otherwise be unreadable
    # (2.4e-7 J/K -> 240 nJ/K); not on units led by K (kK/W would mislead) or dimensionless ones.
    if (
        value is not None
        and np.isfinite(value)
        and value != 0
        and unit
        and unit[0] not in "K%1-"
        and not 1e-2 <= abs(value) < 1e4
    ):
        for factor, prefix in _PREFIXES:
            if abs(value) * factor >= 1.0 or factor == _PREFIXES[-1][0]:
                return factor, prefix + unit
    return 1.0, unit


def fmt(x, digits: int = 4) -> str:
    """A number for a table: `digits` significant figures, "n/a" for NaN/None."""
    if x is None or not np.isfinite(x):
        return "n/a"
    return f"{x:.{digits}g}"


def estimate_texts(p) -> tuple[str, str, str]:
    """(value, 95 % interval, display unit) of a `ParameterEstimate`, in display units, with
    as many decimals as its standard error warrants (two significant digits of the se)."""
    f, unit = display_unit(p.unit, p.value)
    digits = None
    if p.se is not None and np.isfinite(p.se) and p.se * f > 0:
        digits = max(0, 1 - int(np.floor(np.log10(abs(p.se * f)))))

    def one(x):
        if x is None or not np.isfinite(x):
            return "n/a"
        return f"{x * f:.{digits}f}" if digits is not None else fmt(x * f, 5)

    ci = "n/a" if not np.all(np.isfinite(p.ci95)) else f"[{one(p.ci95[0])}, {one(p.ci95[1])}]"
    return one(p.value), ci, unit


def _value_cells(p) -> list[str]:
    value, ci, unit = estimate_texts(p)
    f, _ = display_unit(p.unit, p.value)
    return [value, unit if unit != "1" else "-", fmt(p.se * f, 2), ci]


def parameter_table(parameters, *, truth: dict | None = None) -> list[str]:
    """Markdown table rows for `ParameterEstimate`s (optionally with a true-value column)."""
    head = ["parameter", "value", "unit", "std. error", "95 % interval", "verdict"]
    if truth is not None:
        head.insert(2, "true")
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for p in parameters:
        cells = [f"`{p.name}`", *_value_cells(p), p.verdict + (" (prior)" if p.prior else "")]
        if truth is not None:
            f, _ = display_unit(p.unit, p.value)
            t = truth.get(p.name)
            cells.insert(2, fmt(t * f, 5) if t is not None else "-")
        rows.append("| " + " | ".join(cells) + " |")
    return rows


def noise_ceiling(y, sigma: float) -> float:
    """Fit % a perfect model would score on readings `y` with noise `sigma` (approx.)."""
    y = np.asarray(y, dtype=float)
    y = y[np.isfinite(y)]
    spread = float(np.std(y)) if y.size > 1 else 0.0
    return 100.0 * (1.0 - sigma / spread) if spread > sigma else float("nan")


def _run_rows(result, validation, runs) -> list[str]:
    info = {r.name: r for r in runs}
    sigma = float(np.asarray(result.sigma).reshape(-1)[0])
    rows = [
        "| run | role | input waveform | frames (valid) | outliers flagged | "
        "fit % (simulation, all valid frames) | fit % without flagged frames | "
        "noise ceiling % |",
        "|---|---|---|---|---|---|---|---|",
    ]

    def add(res, role):
        for e in res.experiments:
            r = info.get(e.name)
            valid = int(e.mask.all(axis=1).sum())
            rows.append(
                f"| {e.name} | {role} | {r.waveform if r else '-'} | {e.n_frames} "
                f"({valid}) | {res.n_outliers[e.name]} | {fmt(res.fit_percent[e.name], 3)} | "
                f"{fmt(res.fit_percent_robust[e.name], 3)} | "
                f"{fmt(noise_ceiling(e.y[:, 0], sigma), 3)} |"
            )

    add(result, "estimation")
    if validation is not None:
        add(validation, "validation")
    return rows


def identifiability_lines(result, parameter_notes: dict | None = None) -> list[str]:
    """The identifiability verdict in words, naming any undetermined combination."""
    notes = parameter_notes or {}
    ident = result.identifiability
    verdicts = {p.name: p.verdict for p in result.parameters}
    shared = [p for p in result.parameters if p.experiment is None]
    lines = []
    bad = [p.name for p in result.parameters if p.verdict != "identifiable"]
    if not bad:
        lines.append(
            "**Verdict: every fitted parameter is identifiable** from these data "
            "(no parameter combination is left undetermined)."
        )
    else:
        lines.append(
            f"**Verdict: {len(bad)} of {len(result.parameters)} fitted values are not "
            f"determined by the data alone:** "
            + ", ".join(f"`{n}` ({verdicts[n]})" for n in bad)
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
        f"Singular values of the weighted Jacobian: "
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
) -> str:
    """Markdown report of a fit (and its validation) for people who did not run it.

    - `result`: `greybox.FitResult`; `validation`: `greybox.ValidationResult` or None.
    - `runs`: per-run info with `name` and `waveform` (one-line laser description).
    - `parameter_notes`: {path: what limits its identifiability} from the device table.
    - `figures`: relative paths of figures to link; `source`: where the data came from.
    - `output_unit`: SI unit of the measured output (for sigma).
    """
    shared = [p for p in result.parameters if p.experiment is None]
    per_run = [p for p in result.parameters if p.experiment is not None]
    n_frames = sum(e.n_frames for e in result.experiments)
    sigma_f, sigma_u = display_unit(output_unit)
    n_out = sum(result.n_outliers.values())
    lines = [f"# greybox fit: {title}", ""]
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
        "laser waveform alone from rest and never corrected by the measured positions. They "
        "are not one-step-ahead prediction (which re-uses each measured frame and scores far "
        "higher on slow systems). Fit % = 100 (1 - |y - y_model| / |y - mean(y)|), as "
        "MATLAB `compare`; 100 is perfect, 0 is no better than the mean.",
        "",
        "## Parameters",
        "",
        *parameter_table(shared),
        "",
    ]
    if per_run:
        lines += [
            "Per-run nuisance values (one per estimation run):",
            "",
            *parameter_table(per_run),
            "",
        ]
    lines += [
        "Verdicts: " + "; ".join(f"*{k}*: {v}" for k, v in VERDICT_MEANING.items()) + ".",
        "",
        "## Fit per run (simulation)",
        "",
        *_run_rows(result, validation, runs),
        "",
    ]
    lines += [
        "Noise ceiling: the fit % that a perfect model would score given the noise "
        "sigma, about 100 (1 - sigma / std(y)); a run whose fit % is close to it is "
        "fitted down to the measurement noise, whatever the absolute number.",
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
    lines += [
        "## Noise, outliers and convergence",
        "",
        f"- Measurement noise sigma: **{', '.join(fmt(s * sigma_f, 3) for s in result.sigma)} "
        f"{sigma_u}**, estimated from the residuals (robust median-absolute-deviation scale), "
        "then the fit was repeated at that scale.",
        f"- Outliers flagged: **{n_out}** frames further than {OUTLIER_SIGMAS:g} sigma from the "
        f"model (estimation runs); the {result.loss} loss limits their pull. The headline "
        "fit % counts every valid frame; the column beside it leaves the flagged frames out. "
        "On a validation run, many flagged frames mean the model drifts from the data, not "
        "that the camera failed.",
        f"- Frames: {n_frames} in estimation runs, {result.n_data} valid readings fitted; "
        f"{result.n_params} fitted values.",
        f"- Convergence: **{'converged' if result.converged else 'NOT CONVERGED'}**"
        f"{'' if result.converged else ' (' + result.message + ')'}; {result.n_steps} "
        "Levenberg-Marquardt steps, cost "
        f"{fmt(result.cost, 6)}, simulation path `{result.method}`.",
    ]
    if len(result.multistart_costs) > 1:
        lines.append(
            "- Multi-start costs: "
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
