"""`greybox fit`: experiment folder -> params.json, report.md and figures (written atomically)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import textwrap
import time
from pathlib import Path

from greybox._verdict import exit_status_help

HELP = """\
Fit the physical parameters of a device model to an experiment folder and write the
result: params.json (every fitted value in SI with its unit, standard error, 95 %
interval and identifiability verdict), report.md (tables, simulation fit % per run for the
estimation and validation runs, the identifiability verdict), figures/*.png (measured vs
model per run with the laser waveform beneath, residuals, parameter correlation),
predictions/<run>.csv (per run: time, then per output measured, simulated, 95 % band and
residual, in the unit of the run's file), metrics.csv (per run and output: simulation fit %,
RMSE, MAE, SAE in the file's unit) and validation_runs.json (per validation run: its
settings and the per-run values re-fitted on it).

EXPERIMENT_DIR holds experiment.toml and one CSV per run (format: experiments/README.md):
  [camera]   fps [frames/s], exposure_ms [ms], um_per_px [um per pixel]
  run CSVs   t_s [s], y_um [um] or y_px [pixels, converted with um_per_px], optional
             laser_mW [mW] when the laser is logged rather than described; any unit
             pint knows (T1_degC, t_ms), or the logger's own names mapped in [columns]
             (header-less files: [data] header = false, columns = [...])
  waveform   per run: { type = "pulse_train", power_mW [mW], period_ms [ms], duty [0-1],
             n_pulses, delay_ms [ms], tail_ms [ms] } or { type = "logged" }

Units in the output: params.json holds SI values (m, s, W, K/W) with each unit named;
report.md and the figures show um, ms and mW. Every fit % is free-run simulation (the
model driven by the laser alone), never one-step prediction. With [fit] noise_model =
"process" and a [noise] table (experiments/README.md) the fit is maximum likelihood through
a Kalman filter instead, and the report gives fit % in simulation, one-step and k-step
prediction, each labelled.

The result folder is written atomically: it appears complete or not at all (an error, a
bad input, Ctrl-C or SIGTERM leaves no partial result, and an earlier result stays as it
was). --out must be absent, empty or an earlier greybox result (it holds a
.greybox-result marker); any other folder is refused before any work unless --force.
"""
HELP += textwrap.fill(exit_status_help(), width=92) + "\n"


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "fit",
        help="fit physical parameters to an experiment folder (TOML + CSV runs)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "experiment_dir",
        metavar="EXPERIMENT_DIR",
        help="folder with experiment.toml and the run CSVs",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="result folder (default results/<experiment folder name>); replaced "
        "as a whole when the new result is complete",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out even if it is a non-empty folder greybox did not write",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument(
        "--strict",
        action="store_true",
        help="exit 1 also when the residual test rejects the structure or a fitted value is "
        "physically implausible (the result is written either way)",
    )
    p.set_defaults(func=run)
    return p


class Progress:
    """Progress lines with elapsed seconds, on stderr (stdout stays for results)."""

    def __init__(self, quiet: bool = False):
        self.t0 = time.perf_counter()
        self.quiet = quiet

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(
                f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=sys.stderr, flush=True
            )

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0


@dataclasses.dataclass(frozen=True)
class FitOutcome:
    fitset: object
    result: object
    validation: object
    out: Path
    document: dict
    metrics: dict | None = None  # metrics_table(): per run and output, in the file units


def default_out(experiment_dir) -> Path:
    return Path("results") / Path(experiment_dir).resolve().name


def fit_experiment_dir(experiment_dir, out, say, *, force: bool = False) -> FitOutcome:
    """Load, fit, validate and write the result folder atomically (the work of `greybox fit`).

    `out` is checked first (absent, empty or an earlier result, writable; `force` replaces
    any other folder), then the problem size, before anything is compiled."""
    from greybox._fit import fit, validate
    from greybox.io._atomic import atomic_output_dir, check_output_dir
    from greybox.io._experiment_set import check_problem_size, load_experiment_set
    from greybox.io._params_file import params_document, write_params

    out = check_output_dir(out, force=force, inputs=[experiment_dir])
    say(f"loading {experiment_dir}")
    fs = load_experiment_set(experiment_dir)
    check_problem_size(fs)
    n_est = sum(e.n_frames for e in fs.estimation)
    n_val = sum(e.n_frames for e in fs.validation)
    say(
        f"{fs.device_name}: {len(fs.estimation)} estimation runs ({n_est} frames), "
        f"{len(fs.validation)} validation runs ({n_val} frames); fitting "
        f"{', '.join(p.path + (' (per run)' if p.per_experiment else '') for p in fs.free)}"
    )
    say("fitting (the first solve includes compiling the model, a few seconds)")
    result = fit(fs.model, fs.estimation, fs.free, progress=say, **fs.fit_options)
    validation = None
    if fs.validation:
        per_run = sorted({p.path for p in fs.free if p.per_experiment})
        say(
            f"validating on {len(fs.validation)} runs (physics fixed"
            + (f"; per-run {', '.join(per_run)} re-fitted)" if per_run else ")")
        )
        solver = {k: v for k, v in fs.fit_options.items() if k.startswith("solver_")}
        validation = validate(result, fs.validation, **solver)  # the fit's solver settings
    check_finite_result(fs, result)
    document = params_document(fs, result, validation)
    # the unit each output had in the run files, so `greybox simulate` answers in it
    document.setdefault(
        "file_units", {c.name: u for c, (u, _) in zip(fs.spec.outputs, output_units(fs))}
    )
    say(f"writing {out}")
    runs = run_predictions(fs, result, validation)
    metrics = metrics_table(fs, runs)
    with atomic_output_dir(out, kind="fit", force=force) as tmp:
        usual_permissions(tmp)
        figures = write_figures(tmp, fs, result, validation)
        write_params(tmp / "params.json", document)
        (tmp / "report.md").write_text(render_report(fs, result, validation, figures))
        write_predictions(tmp, fs, runs)
        write_metrics(tmp / "metrics.csv", metrics)
        write_validation_runs(tmp / "validation_runs.json", fs, result, validation)
    return FitOutcome(fs, result, validation, Path(out), document, metrics)


# --------------------------------------------------------------------------------------
# Results as users need them: per-run predictions and metrics in the files' own units


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


def _band_halfwidths(model, result, e):
    """(lower, upper) distances (N, n_y) [SI] of the 95 % confidence band from the response,
    from the shared parameters' covariance (delta method); None when it cannot be had."""
    import numpy as np

    from greybox._prediction import prediction_band

    try:
        band = prediction_band(
            model,
            result.free,
            result.raw,
            result.covariance_raw,
            e.inputs,
            e.t_s,
            method=result.method,
            t_start_s=e.t_start_s,
        )
    except (ValueError, FloatingPointError):
        return None
    y, lo, hi = (np.asarray(a).reshape(e.n_frames, -1) for a in (band.y, band.lower, band.upper))
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return None
    return y - lo, hi - y


def run_predictions(fs, result, validation) -> list:
    """[(role, Experiment, simulated (N, n_y) SI, band half-widths or None)] for every run:
    estimation runs with their fitted per-run values, validation runs as validated."""
    import numpy as np

    out = []
    for i, e in enumerate(result.experiments):
        z = np.asarray(result.predict(i)).reshape(e.n_frames, -1)
        out.append(("estimation", e, z, _band_halfwidths(result.experiment_models[i], result, e)))
    if validation is not None:
        for e, z in zip(validation.experiments, validation.predictions):
            z = np.asarray(z).reshape(e.n_frames, -1)
            # the band of the shared physics, around the validated response (per-run values
            # re-fitted on the run shift it, they do not widen it here)
            band = _band_halfwidths(e.apply_settings(result.model), result, e)
            out.append(("validation", e, z, band))
    return out


def _in_unit(values, conv, m_per_px, *, difference: bool = False):
    """SI -> file unit; a `difference` (residual, band width) takes the scale only."""
    import numpy as np

    values = np.asarray(values, dtype=float)
    if conv is None:
        return values / m_per_px
    scale, offset = conv
    return values / scale if difference else (values - offset) / scale


def write_predictions(folder: Path, fs, runs) -> None:
    """predictions/<run>.csv: t_s, then per output measured, simulated, the 95 % band and
    the residual (measured - simulated), in the unit of the run's file; empty = no reading."""

    m_per_px = fs.camera.get("m_per_px")
    (folder / "predictions").mkdir()
    for role, e, z, band in runs:
        units = output_units(fs, e.name)
        header, cols = ["t_s"], [e.t_s]
        for j, (ch, (unit, conv)) in enumerate(zip(fs.spec.outputs, units)):
            meas = _in_unit(e.y[:, j], conv, m_per_px)
            sim = _in_unit(z[:, j], conv, m_per_px)
            header += [f"{ch.name}_{unit}", f"{ch.name}_sim_{unit}"]
            cols += [meas, sim]
            if band is not None:
                header += [f"{ch.name}_lo95_{unit}", f"{ch.name}_hi95_{unit}"]
                cols += [
                    sim - _in_unit(band[0][:, j], conv, m_per_px, difference=True),
                    sim + _in_unit(band[1][:, j], conv, m_per_px, difference=True),
                ]
            header.append(f"{ch.name}_residual_{unit}")
            cols.append(_in_unit(e.y[:, j] - z[:, j], conv, m_per_px, difference=True))
        write_csv_table(folder / "predictions" / f"{e.name}.csv", header, cols)


def write_csv_table(path: Path, header, cols) -> None:
    """A CSV of numeric columns under `header`; an empty cell where a value is not finite."""
    import numpy as np

    lines = [",".join(header)]
    for row in np.column_stack(cols):
        lines.append(",".join("" if not np.isfinite(v) else f"{v:.10g}" for v in row))
    path.write_text("\n".join(lines) + "\n")


def error_metrics(measured, predicted, conv, m_per_px) -> dict:
    """{"n", "fit_percent", "rmse", "mae", "sae"} of one output's prediction errors over its
    valid readings, in the file's unit (`conv`); None where undefined (no reading; fit %
    also needs two readings that vary)."""
    import numpy as np

    from greybox._metrics import fit_percent

    r = _in_unit(measured - predicted, conv, m_per_px, difference=True)
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
    """Per run and output: simulation fit %, RMSE, MAE and SAE in the unit of the run's file.

    ``{"horizon": "simulation", "runs": {run: {"role", "outputs": {channel: {"unit", "n",
    "fit_percent", "rmse", "mae", "sae"}}}}, "sae_total": {role: {channel: {"unit", "sae"}}}}``
    (None where an output has no reading in a run; totals sum the role's runs in one unit
    per output, the first run's)."""
    import numpy as np

    common = output_units(fs)
    m_per_px = fs.camera.get("m_per_px")
    out = {"horizon": "simulation", "runs": {}, "sae_total": {}}
    for role, e, z, _ in runs:
        units = output_units(fs, e.name)
        per = {}
        for j, (ch, (unit, conv)) in enumerate(zip(fs.spec.outputs, units)):
            entry = {"unit": unit, **error_metrics(e.y[:, j], z[:, j], conv, m_per_px)}
            if entry["n"]:
                ok = np.isfinite(e.y[:, j] - z[:, j])
                totals = out["sae_total"].setdefault(role, {})
                total = totals.setdefault(ch.name, {"unit": common[j][0], "sae": 0.0})
                residual_si = (e.y[:, j] - z[:, j])[ok]
                total["sae"] += float(
                    np.sum(np.abs(_in_unit(residual_si, common[j][1], m_per_px, difference=True)))
                )
            per[ch.name] = entry
        out["runs"][e.name] = {"role": role, "outputs": per}
    return out


def write_metrics(path: Path, metrics: dict) -> None:
    """metrics.csv: one row per run and output (simulation; units as in the run files)."""
    lines = ["run,role,output,unit,n,fit_percent,rmse,mae,sae"]
    for run, entry in metrics["runs"].items():
        for ch, m in entry["outputs"].items():
            cells = [run, entry["role"], ch, m["unit"], str(m["n"])]
            cells += [
                "" if m[k] is None else f"{m[k]:.10g}"
                for k in ("fit_percent", "rmse", "mae", "sae")
            ]
            lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def write_validation_runs(path: Path, fs, result, validation) -> None:
    """validation_runs.json: per validation run, the settings it was simulated with (given
    or read off its data by the device's rule) and the per-run values re-fitted on it."""
    import json

    from greybox.io._params_file import _num

    runs = {}
    refitted = validation.parameters if validation is not None else None
    for e in () if validation is None else validation.experiments:
        info = fs.run_info(e.name)
        runs[e.name] = {
            "settings": {k: _num(v) for k, v in e.settings.items()},
            "settings_from_data": [k for k, _ in info.defaults],
            "time_shift_s": info.time_shift_s,
            "refitted": None
            if refitted is None
            else {
                p.path: {"value": _num(p.value), "se": _num(p.se), "unit": p.unit}
                for p in refitted
                if p.experiment == e.name
            },
        }
    doc = {
        "per_run_parameters": sorted({p.path for p in result.free if p.per_experiment}),
        "note": "per-run values re-fitted on each validation run (physics fixed), with "
        "their standard errors; {} when the fit has no per-run parameter",
        "runs": runs,
    }
    path.write_text(json.dumps(doc, indent=2) + "\n")


def check_finite_result(fs, result) -> None:
    """Refuse a fit whose values or model response are not finite (nothing is written)."""
    import numpy as np

    from greybox._errors import InputError

    bad = [p.name for p in result.parameters if not np.isfinite(p.value)]
    if not bad:
        for i, e in enumerate(result.experiments):
            if not np.all(np.isfinite(np.asarray(result.predict(i)))):
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


def usual_permissions(folder: Path) -> None:
    """Give a result folder the permissions of a folder made by mkdir (the temporary folder
    behind an atomic write is private)."""
    mask = os.umask(0)
    os.umask(mask)
    folder.chmod(0o777 & ~mask)


def render_report(fs, result, validation, figures) -> str:
    from greybox._report import fit_report

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
        physical_ranges=fs.physical_ranges,
    )


def write_figures(folder: Path, fs, result, validation) -> list[str]:
    """Per-run fit figures, residuals and correlation under `folder`/figures; relative paths."""
    from greybox import _plots as plots

    outputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.outputs)
    inputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.inputs)
    (folder / "figures").mkdir()
    runs = [
        (e, "estimation", result.predict(i), result.fit_percent[e.name])
        for i, e in enumerate(result.experiments)
    ]
    if validation is not None:
        runs += [
            (e, "validation", z, validation.fit_percent[e.name])
            for e, z in zip(validation.experiments, validation.predictions)
        ]  # figure titles: fit % on every valid frame (the headline number)
    names = []
    for e, role, z, pct in runs:
        name = f"figures/fit_{e.name}.png"
        plots.run_figure(
            folder / name,
            name=e.name,
            role=role,
            t_s=e.t_s,
            y=e.y,
            y_model=z,
            inputs=e.inputs,
            sigma=result.sigma,
            fit_percent=pct,
            outputs=outputs,
            input_labels=inputs,
        )
        names.append(name)
    # one residuals figure per output channel (units and noise differ between channels)
    for j, (channel, out) in enumerate(zip(fs.spec.outputs, outputs)):
        name = (
            "figures/residuals.png"
            if len(outputs) == 1
            else f"figures/residuals_{channel.name}.png"
        )
        plots.residuals_figure(
            folder / name,
            [(e.name, role, e.t_s, e.y[:, j], z[:, j]) for e, role, z, _ in runs],
            sigma=float(result.sigma[j]),
            output=out,
        )
        names.append(name)
    plots.residual_correlation_figure(
        folder / "figures/residual_tests.png",
        result.residuals,
        outputs=tuple(c.name for c in fs.spec.outputs),
        input_labels=tuple(c.name for c in fs.spec.inputs),
    )
    plots.correlation_figure(
        folder / "figures/correlation.png", [p.name for p in result.parameters], result.correlation
    )
    return names + ["figures/residual_tests.png", "figures/correlation.png"]


def parameter_lines(result) -> list[str]:
    """Terminal table of the shared parameters: value, 95 % interval, verdict."""
    from greybox._report import estimate_texts

    lines = ["parameter                  value        95 % interval               verdict"]
    for p in result.parameters:
        if p.experiment is not None:
            continue
        value, ci, unit = estimate_texts(p)
        lines.append(
            f"{p.name:<26} {value:>8} {unit if unit != '1' else '':<3} {ci:<27} {p.verdict}"
        )
    return lines


def fit_lines(outcome: FitOutcome) -> list[str]:
    """Terminal lines: simulation fit % per run, sigma, outliers, convergence."""
    from greybox._report import display_unit, fmt

    r, v = outcome.result, outcome.validation
    f, unit = display_unit(outcome.fitset.spec.outputs[0].si_unit)

    def scores(res) -> str:
        out = []
        for k, x in res.fit_percent.items():
            n = res.n_outliers[k]
            extra = f" ({fmt(res.fit_percent_robust[k], 3)} without {n} flagged)" if n else ""
            out.append(f"{k} {fmt(x, 3)}{extra}")
        return ", ".join(out)

    lines = ["simulation fit % (estimation): " + scores(r)]
    if v is not None:
        lines.append("simulation fit % (validation): " + scores(v))
    lines.append(
        f"noise sigma {', '.join(fmt(float(s) * f, 3) for s in r.sigma)} {unit} "
        "(estimated), "
        f"{sum(r.n_outliers.values())} outliers flagged, "
        f"{r.status if r.valid else r.status.upper() + ': ' + r.message}"
    )
    lines.append(f"residuals (estimation): {r.residuals.verdict}")
    return lines


def run(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    say = Progress(args.quiet)
    out = Path(args.out) if args.out else default_out(args.experiment_dir)
    from greybox.cli import _fit_process

    if _fit_process.requested(args.experiment_dir):  # [fit] noise_model = "process"
        return _fit_process.run(args, say, out)
    from greybox.io._experiment_set import InputErrors

    try:
        outcome = fit_experiment_dir(args.experiment_dir, out, say, force=args.force)
    except InputErrors as err:  # every loader problem, one per line
        print(
            f"greybox fit: error: {len(err.errors)} problems in {args.experiment_dir}:",
            file=sys.stderr,
        )
        for e in err.errors[:20]:
            print(f"greybox fit: error: {' '.join(str(e).split())}", file=sys.stderr)
        if len(err.errors) > 20:
            print(f"greybox fit: error: ... and {len(err.errors) - 20} more", file=sys.stderr)
        return 2
    print("\n".join(parameter_lines(outcome.result) + fit_lines(outcome)))
    print(
        f"wrote {out}/ (params.json, report.md, figures/, predictions/, metrics.csv, "
        f"validation_runs.json) in {say.elapsed:.1f} s"
    )
    from greybox._verdict import fit_headline  # one verdict: status, bounds, physics, residuals

    head = fit_headline(outcome.result, outcome.fitset.physical_ranges, strict=args.strict)
    print("\n".join([head.text, *[f"  {d}" for d in head.details], head.intervals]))
    if not outcome.result.valid:
        print(
            f"greybox fit: warning: {outcome.result.status}: the estimate is not valid "
            f"({outcome.result.message}); the result is written but its numbers are not "
            "trustworthy",
            file=sys.stderr,
        )
        return 1
    return head.exit_status
