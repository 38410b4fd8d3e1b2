"""The result folder of a fit, beside params.json and report.md: per-run predictions, metrics,
validation runs and figures, for every noise model (the writers take what the fit computed).

Each run is a `RunOutput`: its role, its `Experiment`, the model's predictions of its readings
at every horizon the fit's noise model supports (simulation always; one-step and k-step
prediction for a process-noise fit), and the simulation's 95 % band when one was computed.
Every number is written in the unit of that run's file (`T1_degC`, `y_um`, `y_px`).
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

SIMULATION = "simulation"
ONE_STEP = "one-step prediction"


@dataclasses.dataclass(frozen=True)
class RunOutput:
    """One run as the result folder shows it.

    - `horizons`: {label: (N, n_y) predicted readings [SI]}, "simulation" first, then
      "one-step prediction" and "<k>-step prediction" where the noise model defines them.
    - `band`: (lower, upper) distances (N, n_y) [SI] of the simulation's 95 % band from it,
      or None.
    - `sd`: {label: (N, n_y) sd of the prediction [SI]} where the fit computed one (the
      innovation sd of the one-step prediction), for the outlier marks of the figures.
    - `extra`: per-run diagnostics for validation_runs.json (log-likelihood, whiteness, the
      re-fitted per-run values and initial state).
    """

    role: str
    experiment: object
    horizons: dict
    band: tuple | None = None
    sd: dict = dataclasses.field(default_factory=dict)
    extra: dict = dataclasses.field(default_factory=dict)

    @property
    def name(self) -> str:
        return self.experiment.name

    @property
    def simulation(self) -> np.ndarray:
        return self.horizons[SIMULATION]


def usual_permissions(folder: Path) -> None:
    """Give a result folder the permissions of a folder made by mkdir (the temporary folder
    behind an atomic write is private)."""
    mask = os.umask(0)
    os.umask(mask)
    folder.chmod(0o777 & ~mask)


def output_units(fs, run: str | None = None) -> list:
    """Per output channel: (unit, (scale, offset) or None for px) of run `run`'s file; an
    output the run lacks, or `run` None, takes the first run's file unit that has it (the
    channel's SI unit when no run has it)."""
    from greybox.io._units import channel_conversion

    infos = list(fs.runs)
    if run is not None:
        infos.insert(0, fs.run_info(run))
    out = []
    for j, ch in enumerate(fs.spec.outputs):
        unit = next(
            (
                r.output_columns[j][1]
                for r in infos
                if len(r.output_columns) > j and r.output_columns[j] is not None
            ),
            None,
        )
        if unit is None:
            out.append((ch.si_unit, (1.0, 0.0)))
        else:
            out.append((unit, channel_conversion(ch, unit)))
    return out


def in_unit(values, conv, m_per_px, *, difference: bool = False):
    """SI -> file unit; a `difference` (residual, band width) takes the scale only."""
    values = np.asarray(values, dtype=float)
    if conv is None:
        return values / m_per_px
    scale, offset = conv
    return values / scale if difference else (values - offset) / scale


def horizon_tag(label: str) -> str:
    """The column tag of a horizon: sim, onestep, 10step."""
    if label == SIMULATION:
        return "sim"
    return label.split(" ")[0].replace("-", "")


def write_csv_table(path: Path, header, cols) -> None:
    """A CSV of numeric columns under `header`; an empty cell where a value is not finite."""
    lines = [",".join(header)]
    for row in np.column_stack(cols):
        lines.append(",".join("" if not np.isfinite(v) else f"{v:.10g}" for v in row))
    path.write_text("\n".join(lines) + "\n")


def write_predictions(folder: Path, fs, runs) -> None:
    """predictions/<run>.csv: t_s, then per output measured, simulated, the 95 % band and the
    residual (measured - simulated), then each prediction horizon (`_onestep_`, `_10step_`)
    and the innovation (measured - one-step prediction), in the unit of the run's file;
    empty = no reading."""
    m_per_px = fs.camera.get("m_per_px")
    (folder / "predictions").mkdir()
    for run in runs:
        e = run.experiment
        header, cols = ["t_s"], [e.t_s]
        for j, (ch, (unit, conv)) in enumerate(zip(fs.spec.outputs, output_units(fs, e.name))):
            z = run.simulation
            sim = in_unit(z[:, j], conv, m_per_px)
            header += [f"{ch.name}_{unit}", f"{ch.name}_sim_{unit}"]
            cols += [in_unit(e.y[:, j], conv, m_per_px), sim]
            if run.band is not None:
                header += [f"{ch.name}_lo95_{unit}", f"{ch.name}_hi95_{unit}"]
                cols += [
                    sim - in_unit(run.band[0][:, j], conv, m_per_px, difference=True),
                    sim + in_unit(run.band[1][:, j], conv, m_per_px, difference=True),
                ]
            header.append(f"{ch.name}_residual_{unit}")
            cols.append(in_unit(e.y[:, j] - z[:, j], conv, m_per_px, difference=True))
            for label, zh in run.horizons.items():
                if label == SIMULATION:
                    continue
                header.append(f"{ch.name}_{horizon_tag(label)}_{unit}")
                cols.append(in_unit(zh[:, j], conv, m_per_px))
            if ONE_STEP in run.horizons:
                header.append(f"{ch.name}_innovation_{unit}")
                r = e.y[:, j] - run.horizons[ONE_STEP][:, j]
                cols.append(in_unit(r, conv, m_per_px, difference=True))
        write_csv_table(folder / "predictions" / f"{e.name}.csv", header, cols)


def error_metrics(measured, predicted, conv, m_per_px) -> dict:
    """{"n", "fit_percent", "rmse", "mae", "sae"} of one output's prediction errors over its
    valid readings, in the file's unit (`conv`); None where undefined (no reading; fit %
    also needs two readings that vary)."""
    from greybox._estimate.metrics import fit_percent

    r = in_unit(measured - predicted, conv, m_per_px, difference=True)
    ok = np.isfinite(r)
    n = int(ok.sum())
    out = {"n": n, "fit_percent": None, "rmse": None, "mae": None, "sae": None}
    if n:
        r = r[ok]
        out.update(
            rmse=float(np.sqrt(np.mean(r**2))),
            mae=float(np.mean(np.abs(r))),
            sae=float(np.sum(np.abs(r))),
        )
        if n >= 2 and np.ptp(measured[ok]) > 0:
            out["fit_percent"] = float(fit_percent(measured[ok], predicted[ok]))
    return out


def metrics_table(fs, runs) -> dict:
    """Per run, horizon and output: fit %, RMSE, MAE and SAE in the unit of the run's file.

    ``{"horizons": [labels], "runs": {run: {"role", "outputs": {channel: {"unit", "n",
    "fit_percent", "rmse", "mae", "sae"}} (simulation), "by_horizon": {label: {channel:
    ...}}}}, "sae_total": {role: {channel: {"unit", "sae"}}}}`` (simulation; None where an
    output has no reading in a run; totals sum the role's runs in one unit per output, the
    first run's)."""
    common = output_units(fs)
    m_per_px = fs.camera.get("m_per_px")
    labels = list(runs[0].horizons) if runs else [SIMULATION]
    out = {"horizon": SIMULATION, "horizons": labels, "runs": {}, "sae_total": {}}
    for run in runs:
        e = run.experiment
        units = output_units(fs, e.name)
        by = {}
        for label, z in run.horizons.items():
            by[label] = {
                ch.name: {"unit": unit, **error_metrics(e.y[:, j], z[:, j], conv, m_per_px)}
                for j, (ch, (unit, conv)) in enumerate(zip(fs.spec.outputs, units))
            }
        for j, ch in enumerate(fs.spec.outputs):
            if by[SIMULATION][ch.name]["n"]:
                r = e.y[:, j] - run.simulation[:, j]
                totals = out["sae_total"].setdefault(run.role, {})
                total = totals.setdefault(ch.name, {"unit": common[j][0], "sae": 0.0})
                r = r[np.isfinite(r)]
                total["sae"] += float(
                    np.sum(np.abs(in_unit(r, common[j][1], m_per_px, difference=True)))
                )
        out["runs"][e.name] = {"role": run.role, "outputs": by[SIMULATION], "by_horizon": by}
    return out


def metric_rows(metrics: dict) -> list:
    """(run, role, output, horizon, unit, n, fit %, RMSE, MAE, SAE) per run, horizon, output."""
    rows = []
    for run, entry in metrics["runs"].items():
        for label, per in entry["by_horizon"].items():
            for ch, m in per.items():
                rows.append(
                    (run, entry["role"], ch, label, m["unit"], m["n"])
                    + tuple(m[k] for k in ("fit_percent", "rmse", "mae", "sae"))
                )
    return rows


def write_metrics(path: Path, metrics: dict) -> None:
    """metrics.csv: one row per run and output (and horizon, a column that a fit with only
    the simulation horizon leaves out); units as in the run files; empty where undefined."""
    several = len(metrics["horizons"]) > 1
    head = ["run", "role", "output"] + (["horizon"] if several else [])
    lines = [",".join(head + ["unit", "n", "fit_percent", "rmse", "mae", "sae"])]
    for run, role, ch, label, unit, n, *vals in metric_rows(metrics):
        cells = [run, role, ch] + ([label] if several else []) + [unit, str(n)]
        cells += ["" if v is None else f"{v:.10g}" for v in vals]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def write_validation_runs(path: Path, fs, runs, per_run_paths) -> None:
    """validation_runs.json: per validation run, the settings it was simulated with (given or
    read off its data by the device's rule), its clock shift, the per-run values re-fitted on
    it (with their standard errors) and the run's diagnostics (`RunOutput.extra`)."""
    from greybox.io._params_file import _num

    out = {}
    for run in runs:
        if run.role != "validation":
            continue
        e = run.experiment
        info = fs.run_info(e.name)
        out[e.name] = {
            "settings": {k: _num(v) for k, v in e.settings.items()},
            "settings_from_data": [k for k, _ in info.defaults],
            "time_shift_s": info.time_shift_s,
            **run.extra,
        }
    doc = {
        "per_run_parameters": sorted(per_run_paths),
        "note": "per-run values re-fitted on each validation run (physics fixed), with "
        "their standard errors; {} when the fit has no per-run parameter",
        "runs": out,
    }
    path.write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")


def figure_jobs(fs, runs, sigma, fit_percent, *, result=None, fmt: str = "png") -> list:
    """The figures of a result folder, as (relative path, `greybox.report._plots` function
    name, positional arguments, keyword arguments), plain data only (arrays, waveforms,
    labels, the residual analysis), so that another process can draw them: figures/fit_<run>
    (`fmt`: png, svg or pdf; measured vs simulation, inputs beneath), one residuals figure per
    output (simulation residuals against the simulation's noise scale `sigma`), for a
    process-noise fit one innovations figure per output (against the innovation sd), and,
    with `result` (a least-squares fit), the residual tests and parameter correlation.
    `fit_percent`: {run: simulation fit % per output}."""
    outputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.outputs)
    inputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.inputs)
    jobs = []
    for run in runs:
        e = run.experiment
        kwargs = dict(
            name=e.name,
            role=run.role,
            t_s=e.t_s,
            y=e.y,
            y_model=run.simulation,
            inputs=e.inputs,
            sigma=sigma,
            fit_percent=fit_percent[e.name],
            outputs=outputs,
            input_labels=inputs,
        )
        jobs.append((f"figures/fit_{e.name}.{fmt}", "run_figure", (), kwargs))
    one = len(outputs) == 1
    for j, (ch, out) in enumerate(zip(fs.spec.outputs, outputs)):
        name = f"figures/residuals.{fmt}" if one else f"figures/residuals_{ch.name}.{fmt}"
        series = [
            (r.name, r.role, r.experiment.t_s, r.experiment.y[:, j], r.simulation[:, j])
            for r in runs
        ]
        kwargs = dict(sigma=float(np.atleast_1d(sigma)[j]), output=out)
        jobs.append((name, "residuals_figure", (series,), kwargs))
        if runs and ONE_STEP in runs[0].horizons:
            scale = [np.asarray(r.sd.get(ONE_STEP))[:, j] for r in runs if ONE_STEP in r.sd]
            scale = float(np.nanmedian(np.concatenate(scale))) if scale else float(sigma[j])
            series = [
                (r.name, r.role, r.experiment.t_s, r.experiment.y[:, j], r.horizons[ONE_STEP][:, j])
                for r in runs
            ]
            label = (f"{out[0]}, one-step prediction (innovations; sigma: innovation sd)", out[1])
            kwargs = dict(sigma=scale, output=label)
            name = f"figures/innovations_{ch.name}.{fmt}"
            jobs.append((name, "residuals_figure", (series,), kwargs))
    if result is not None:
        kwargs = dict(
            outputs=tuple(c.name for c in fs.spec.outputs),
            input_labels=tuple(c.name for c in fs.spec.inputs),
        )
        name = f"figures/residual_tests.{fmt}"
        jobs.append((name, "residual_correlation_figure", (result.residuals,), kwargs))
        args = ([p.name for p in result.parameters], np.asarray(result.correlation))
        jobs.append((f"figures/correlation.{fmt}", "correlation_figure", args, {}))
    return jobs


def estimation_figure_jobs(fs, result, fmt: str = "png") -> list:
    """The jobs of `figure_jobs` that a least-squares fit's validation cannot change (each
    estimation run's figure, the residual tests, the parameter correlation), as the result
    folder's writing makes them, so that they can be drawn while the validation runs
    (`greybox.io._drawing.drawing_ahead`); none for a process-noise fit, whose figures'
    scale depends on the validation runs too."""
    if _is_process(result):
        return []
    runs = run_outputs(fs, result, None)
    jobs = figure_jobs(fs, runs, result.sigma, dict(result.fit_percent), result=result, fmt=fmt)
    return [job for job in jobs if job[1] != "residuals_figure"]  # those pool every run


# --------------------------------------------------------------------------------------------
# From the fit's results to the runs of the result folder


def _is_process(result) -> bool:
    return getattr(getattr(result, "noise", None), "name", "") == "process noise"


def horizon_labels(result) -> dict:
    """{the fit's horizon key: the label the result folder uses}."""
    k = getattr(result, "k_step", None) or getattr(getattr(result, "noise", None), "k_step", 10)
    return {"simulation": SIMULATION, "one-step": ONE_STEP, "k-step": f"{k}-step prediction"}


BAND_Z = 1.959963984540054  # the 95 % two-sided normal quantile


def _band(sd, e):
    """(lower, upper) distances (N, n_y) [SI] of the simulation's 95 % confidence band from
    the response, from the sd the fit computed (delta method; `FitResult.prediction_sd`);
    None when it could not be had (no sd, or an infinite or NaN one)."""
    if sd is None:
        return None
    half = BAND_Z * np.asarray(sd, dtype=float).reshape(e.n_frames, -1)
    if not np.all(np.isfinite(half)):
        return None
    return half, half


def _whiteness_doc(whiteness, outputs) -> dict:
    from greybox.io._params_file import _num

    return {
        c: {
            "test": "Ljung-Box",
            "statistic": _num(w.statistic),
            "p_value": _num(w.p_value),
            "lags": w.lags,
            "white": bool(w.p_value > 0.01),
        }
        for c, w in zip(outputs, whiteness)
    }


def diagnostics_doc(run, outputs) -> dict:
    """A process-noise run's diagnostics (`RunDiagnostics`): log-likelihood, innovations'
    whiteness, fit % per horizon."""
    from greybox.io._params_file import _num

    return {
        "role": run.role,
        "log_likelihood": _num(run.log_likelihood),
        "whiteness": _whiteness_doc(run.whiteness, outputs),
        "fit_percent": {
            label: {c: _num(v) for c, v in zip(outputs, pct)} for label, _, pct in run.horizons
        },
        "k_step": run.k_step,
    }


def _refitted(validation, name) -> dict | None:
    from greybox.io._params_file import _num

    params = getattr(validation, "parameters", None)
    if params is None:
        return None
    return {
        p.path: {"value": _num(p.value), "se": _num(p.se), "unit": p.unit}
        for p in params
        if p.experiment == name
    }


def run_outputs(fs, result, validation) -> list:
    """A `RunOutput` per estimation and validation run, from what the fit and the validation
    computed (estimation runs with their fitted per-run values, validation runs as
    validated)."""
    outputs = [c.name for c in fs.spec.outputs]
    out = []
    if _is_process(result):
        labels = horizon_labels(result)
        diag = {r.name: r for r in getattr(result, "runs", ())}
        for e in result.experiments:
            pred = result.predictions[e.name]
            horizons = {labels[k]: np.asarray(z).reshape(e.n_frames, -1) for k, z in pred.items()}
            sds = (getattr(result, "prediction_sd", None) or {}).get(e.name, {})
            sd = {labels[k]: np.asarray(v).reshape(e.n_frames, -1) for k, v in sds.items()}
            extra = diagnostics_doc(diag[e.name], outputs) if e.name in diag else {}
            out.append(RunOutput("estimation", e, horizons, None, sd, extra))
        if validation is not None:
            by_name = {e.name: e for e in fs.validation}
            for r in validation.runs:
                e = by_name[r.name]
                horizons = {
                    label: np.asarray(z).reshape(e.n_frames, -1) for label, z, _ in r.horizons
                }
                with np.errstate(divide="ignore", invalid="ignore"):
                    sd1 = (e.y - np.asarray(r.y_one_step).reshape(e.y.shape)) / np.asarray(
                        r.standardised_innovation
                    ).reshape(e.y.shape)
                extra = diagnostics_doc(r, outputs)
                extra["refitted"] = _refitted(validation, e.name)
                out.append(
                    RunOutput("validation", e, horizons, None, {ONE_STEP: np.abs(sd1)}, extra)
                )
        return out
    # the fit's own predictions and band sds: writing simulates and compiles nothing
    for e in result.experiments:
        z = np.asarray(result.predictions[e.name][SIMULATION]).reshape(e.n_frames, -1)
        band = _band(result.prediction_sd.get(e.name, {}).get(SIMULATION), e)
        out.append(RunOutput("estimation", e, {SIMULATION: z}, band))
    if validation is not None:
        sds = validation.prediction_sd or (None,) * len(validation.experiments)
        for e, z, sd in zip(validation.experiments, validation.predictions, sds):
            z = np.asarray(z).reshape(e.n_frames, -1)
            # the band of the shared physics, around the validated response (per-run values
            # re-fitted on the run shift it, they do not widen it here)
            band = _band(sd, e)
            extra = {"refitted": _refitted(validation, e.name)}
            out.append(RunOutput("validation", e, {SIMULATION: z}, band, {}, extra))
    return out


def check_finite_result(fs, result) -> None:
    """Refuse a fit whose values or model response are not finite (nothing is written)."""
    from greybox._model.errors import InputError

    bad = [p.name for p in result.parameters if not np.isfinite(p.value)]
    if not bad:
        for e in result.experiments:
            z = result.predictions[e.name][SIMULATION]
            if not np.all(np.isfinite(np.asarray(z))):
                bad = [f"the model response of run {e.name}"]
                break
    if bad:
        raise InputError(
            f"the fit produced non-finite values ({', '.join(bad)}); nothing was written. "
            "Check the [experiment] settings and the free parameters' bounds and initial "
            "values (a start far from the data can overflow the model)",
            file=str(Path(fs.directory) / "experiment.toml"),
            field="fit",
        )


@dataclasses.dataclass(frozen=True)
class WrittenFit:
    """What `write_fit_result` wrote: params.json's content, the metrics, the runs."""

    out: Path
    document: dict
    metrics: dict
    runs: tuple
    figures: tuple


def _simulation_scale(runs, n_y) -> np.ndarray:
    """Per output, the RMS of the simulation residuals of the estimation runs: the scale the
    simulation residuals of a process-noise fit are marked against (not the measurement sd)."""
    r = [run.experiment.y - run.simulation for run in runs if run.role == "estimation"]
    if not r:
        return np.full(n_y, np.nan)
    r = np.concatenate(r)
    return np.sqrt(np.nanmean(r**2, axis=0))


def copy_device_file(folder: Path, device) -> None:
    """A user's device file travels with the result: `load_params` (and `greybox simulate`)
    read the copy beside params.json, which needs no --trust-device."""
    import shutil

    if device.source == "file" and Path(device.location).is_file():
        shutil.copy2(device.location, Path(folder) / Path(device.location).name)


def write_fit_files(
    folder: Path,
    fs,
    result,
    validation,
    *,
    figures: bool = True,
    tables: bool = True,
    fmt: str = "png",
    defer: list | None = None,
    ahead=None,
) -> WrittenFit:
    """Write a fit's files into the existing `folder`: params.json and report.md, with
    `figures` figures/ (in `fmt`: png, svg or pdf), with `tables` predictions/, metrics.csv
    and validation_runs.json. `defer`: a list that receives (folder, `figure_jobs`) instead
    of the figures being drawn here (report.md names them all the same); `ahead`: figures
    drawn already (`greybox.io._drawing.drawing_ahead` of `estimation_figure_jobs`), moved
    in rather than drawn again."""
    from greybox.io._params_file import params_document, write_params

    folder = Path(folder)
    check_finite_result(fs, result)
    document = params_document(fs, result, validation)
    # the unit each output had in the run files, so `greybox simulate` answers in it
    document.setdefault(
        "file_units", {c.name: u for c, (u, _) in zip(fs.spec.outputs, output_units(fs))}
    )
    runs = run_outputs(fs, result, validation)
    metrics = metrics_table(fs, runs)
    process = _is_process(result)
    if process:
        sigma = _simulation_scale(runs, len(fs.spec.outputs))
        fit_percent = {r.name: np.atleast_1d(metrics_fit(metrics, r.name)) for r in runs}
    else:
        sigma = result.sigma
        fit_percent = dict(result.fit_percent)
        if validation is not None:
            fit_percent.update(validation.fit_percent)
    names = []
    if figures:
        fitted = None if process else result
        jobs = figure_jobs(fs, runs, sigma, fit_percent, result=fitted, fmt=fmt)
        names = [rel for rel, *_ in jobs]
        if defer is None:
            from greybox.io._drawing import draw_figures

            draw_figures(folder, jobs if ahead is None else ahead.take(folder, jobs))
        else:  # the caller draws them (`draw_many`: many devices' figures side by side)
            defer.append((folder, jobs))
    write_params(folder / "params.json", document)
    copy_device_file(folder, fs.device)
    (folder / "report.md").write_text(report_text(fs, result, validation, names, metrics))
    if tables:
        per_run = {p.path for p in result.free if p.per_experiment}
        write_predictions(folder, fs, runs)
        write_metrics(folder / "metrics.csv", metrics)
        write_validation_runs(folder / "validation_runs.json", fs, runs, per_run)
    return WrittenFit(folder, document, metrics, tuple(runs), tuple(names))


def report_text(fs, result, validation, figures=(), metrics=None) -> str:
    """report.md of a fit of the folder `fs` (`metrics`: `metrics_table`, computed when
    None)."""
    from greybox.report._markdown import fit_report

    if metrics is None:
        metrics = metrics_table(fs, run_outputs(fs, result, validation))
    notes = {p.path: p.identifiability for p in fs.spec.parameter_table(fs.options)}
    source = " ".join(filter(None, [fs.description, f"Data: `{fs.directory}`."]))
    return fit_report(
        result,
        validation,
        title=fs.name,
        device_name=fs.device_name,
        runs=fs.runs,
        parameter_notes=notes,
        figures=figures,
        source=source,
        output_unit=fs.spec.outputs[0].si_unit,
        outputs=tuple(c.name for c in fs.spec.outputs),
        metrics=metric_rows(metrics),
        noise_table=fs.noise,
        physical_ranges=fs.physical_ranges,
    )


def write_fit_result(
    out, fs, result, validation, *, force: bool = False, fmt: str | None = "png", ahead=None
) -> WrittenFit:
    """The result folder of a fit, written atomically (it appears complete or not at all):
    params.json, report.md, predictions/, metrics.csv, validation_runs.json, figures/ (in
    `fmt`; none when `fmt` is None; `ahead`: those drawn already, `write_fit_files`)."""
    from greybox.io._atomic import atomic_output_dir

    check_finite_result(fs, result)  # before the folder is touched
    with atomic_output_dir(out, kind="fit", force=force) as tmp:
        usual_permissions(tmp)
        written = write_fit_files(
            tmp, fs, result, validation, figures=fmt is not None, fmt=fmt or "png", ahead=ahead
        )
    return dataclasses.replace(written, out=Path(out))


def metrics_fit(metrics: dict, run: str) -> list:
    """Simulation fit % per output of `run` (NaN where undefined)."""
    per = metrics["runs"][run]["outputs"]
    return [np.nan if m["fit_percent"] is None else m["fit_percent"] for m in per.values()]
