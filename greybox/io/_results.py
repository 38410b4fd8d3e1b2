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
    from greybox._metrics import fit_percent

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


def write_figures(folder: Path, fs, runs, sigma, fit_percent, *, result=None) -> list[str]:
    """figures/fit_<run>.png (measured vs simulation, inputs beneath), one residuals figure
    per output (simulation residuals against the simulation's noise scale `sigma`), for a
    process-noise fit one innovations figure per output (against the innovation sd), and,
    with `result` (a least-squares fit), the residual tests and parameter correlation.
    `fit_percent`: {run: simulation fit % per output}. Returns the relative paths."""
    from greybox import _plots as plots

    outputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.outputs)
    inputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.inputs)
    (folder / "figures").mkdir()
    names = []
    for run in runs:
        e = run.experiment
        name = f"figures/fit_{e.name}.png"
        plots.run_figure(
            folder / name,
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
        names.append(name)
    one = len(outputs) == 1
    for j, (ch, out) in enumerate(zip(fs.spec.outputs, outputs)):
        name = "figures/residuals.png" if one else f"figures/residuals_{ch.name}.png"
        plots.residuals_figure(
            folder / name,
            [(r.name, r.role, r.experiment.t_s, r.experiment.y[:, j], r.simulation[:, j]) for r in runs],
            sigma=float(np.atleast_1d(sigma)[j]),
            output=out,
        )
        names.append(name)
        if runs and ONE_STEP in runs[0].horizons:
            name = f"figures/innovations_{ch.name}.png"
            scale = [np.asarray(r.sd.get(ONE_STEP))[:, j] for r in runs if ONE_STEP in r.sd]
            scale = float(np.nanmedian(np.concatenate(scale))) if scale else float(sigma[j])
            plots.residuals_figure(
                folder / name,
                [
                    (r.name, r.role, r.experiment.t_s, r.experiment.y[:, j], r.horizons[ONE_STEP][:, j])
                    for r in runs
                ],
                sigma=scale,
                output=(f"{out[0]}, one-step prediction (innovations; sigma: innovation sd)", out[1]),
            )
            names.append(name)
    if result is not None:
        plots.residual_correlation_figure(
            folder / "figures/residual_tests.png",
            result.residuals,
            outputs=tuple(c.name for c in fs.spec.outputs),
            input_labels=tuple(c.name for c in fs.spec.inputs),
        )
        plots.correlation_figure(
            folder / "figures/correlation.png",
            [p.name for p in result.parameters],
            result.correlation,
        )
        names += ["figures/residual_tests.png", "figures/correlation.png"]
    return names
