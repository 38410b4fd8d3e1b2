"""`greybox fit` with `[fit] noise_model = "process"`, and `greybox simulate` on its params.json.

The experiment folder is the usual one (experiments/README.md) plus, in experiment.toml:

    [fit]
    noise_model = "process"     # "none" (default): deterministic least squares (free-run)

    [noise]
    process = { heaters = [0, 1] }          # state groups, each with one fitted process-noise
                                            # intensity [state unit^2/s] (0-based state
                                            # indices); "all": one group over every state;
                                            # leave out for none
    disturbances = ["ambient_random_walk"]  # random-walk disturbance states: one per output
                                            # ("ambient_random_walk"), one shared by every
                                            # output ("ambient_random_walk_shared"), one per
                                            # input ("input_random_walk")
    walk_initial_sd = 0.0                   # prior sd of the walks at the start (default 0)
    filter = "auto"                         # auto | kalman (linear device) | ekf
    substeps = 4                            # EKF local linearisations per step (default: 1
                                            # for a linear device, 4 for a nonlinear one)
    state_unit = "K"                        # SI unit of the device's states, for the
                                            # process intensities' unit (state_unit^2/s);
                                            # default: the outputs' unit when they share one
    k_step = 10                             # horizon (frames) of the k-step prediction fit %
    fixed = { "measurement.T1" = 0.1 }      # noise values held fixed (SI), not fitted
    initial = { "process.heaters" = 1e-3 }  # starting values (SI) of fitted noise parameters
    priors = { "measurement.T2" = { median = 0.093, log_sd = 0.5 } }  # log-normal priors (SI)

The noise parameters are `process.<group>`, `measurement.<output>` (sd per output),
`output_walk.<output>` (or `output_walk.shared`) and `input_walk.<input>`; every one not
fixed is fitted (log scale). The physical parameters are [fit] free as usual.

The result folder (atomic, like `greybox fit`'s): params.json (noise_model, the likelihood,
the noise structure, every parameter with its uncertainty, the raw estimate and covariance,
per-run diagnostics), report.md, predictions/<run>.csv (measured, simulation, one-step and
k-step prediction, their residuals, in the run file's units), metrics.csv (per run, output and
horizon -- simulation, one-step prediction, k-step prediction -- : fit %, RMSE, MAE, SAE),
validation_runs.json (per validation run: settings, per-horizon fit %, whiteness) and the
figures fit_<run>.png (measured, simulation and one-step prediction with its 95 % band) and
residuals_<run>.png (the innovations).
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

NOISE_MODELS = ("none", "process")
NOISE_KEYS = {
    "process",
    "disturbances",
    "walk_initial_sd",
    "filter",
    "substeps",
    "state_unit",
    "k_step",
    "fixed",
    "initial",
    "priors",
}
FORMAT = "greybox process-noise fit"
N_PATHS = 200


def requested(experiment_dir) -> bool:
    """Whether the folder asks for the process-noise fit (a broken file: False, the usual
    loader then reports the problem)."""
    import tomllib

    try:
        data = tomllib.loads((Path(experiment_dir) / "experiment.toml").read_text("utf-8"))
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError, RecursionError):
        return False
    fit = data.get("fit")
    return isinstance(fit, dict) and fit.get("noise_model") == "process"


def state_unit_default(spec) -> str | None:
    """The outputs' SI unit when every output shares it (a thermal network read by
    thermometers, positions read by a camera), else None."""
    units = {c.si_unit for c in spec.outputs}
    return units.pop() if len(units) == 1 else None


def _noise_units(spec, structure=None, state_unit: str | None = None) -> dict:
    """Display units of the noise parameters: measurement sd in the output's SI unit, walk
    intensities in (channel unit)^2/s, process intensities in (state unit)^2/s."""
    units = {}
    su = state_unit or state_unit_default(spec)
    for g, _ in getattr(structure, "process_groups", ()):
        units[f"process.{g}"] = f"{su}^2/s" if su else "(state unit)^2/s"
    for c in spec.outputs:
        units[f"measurement.{c.name}"] = c.si_unit
        units[f"output_walk.{c.name}"] = f"{c.si_unit}^2/s"
    units["output_walk.shared"] = f"{spec.outputs[0].si_unit}^2/s"
    for c in spec.inputs:
        units[f"input_walk.{c.name}"] = f"{c.si_unit}^2/s"
    return units


def parse_noise(doc, data: dict, model, spec):
    """([noise] -> NoiseStructure, fixed {path: SI}, initial {path: SI}), located errors."""
    from greybox._device import AbstractLinearDevice, AbstractODEDevice
    from greybox._sde_device import DEFAULT_K_STEP, DISTURBANCES, FILTERS, NoiseStructure

    table = doc.table(data, "noise", required=False)
    doc.check_keys(table, NOISE_KEYS, "noise")
    if not isinstance(model, AbstractODEDevice):
        raise doc.error(
            f"{spec.name} is not a state-space device (AbstractODEDevice); a process-noise "
            'fit needs one: use noise_model = "none"',
            "fit",
            "noise_model",
        )
    n = int(model.n_states)
    groups = []
    proc = table.get("process")
    if proc == "all":
        groups = [("states", tuple(range(n)))]
    elif isinstance(proc, dict):
        for name, idx in proc.items():
            where = ("noise", "process", name)
            if not str(name).isidentifier():
                raise doc.error("a group name: letters, digits and _ only", *where)
            if (
                not isinstance(idx, list)
                or not idx
                or not all(isinstance(i, int) and not isinstance(i, bool) for i in idx)
            ):
                raise doc.error(
                    f"give a list of 0-based state indices, e.g. [0, 1] (the device has {n} "
                    "states)",
                    *where,
                )
            bad = [i for i in idx if not 0 <= i < n]
            if bad:
                raise doc.error(
                    f"state(s) {bad} do not exist: {spec.name} has {n} states (0 to {n - 1})",
                    *where,
                )
            groups.append((name, tuple(idx)))
    elif proc is not None:
        raise doc.error(
            'give a table of groups, e.g. { heaters = [0, 1] }, or "all" (one group)',
            "noise",
            "process",
        )
    dist = table.get("disturbances", [])
    if not isinstance(dist, list) or not all(isinstance(d, str) for d in dist):
        raise doc.error(f"give a list of names from {list(DISTURBANCES)}", "noise", "disturbances")
    for i, d in enumerate(dist):
        if d not in DISTURBANCES:
            raise doc.error(
                f"{d!r} is unknown; use any of {', '.join(DISTURBANCES)}",
                "noise",
                "disturbances",
                i,
            )
    walk_sd = doc.number(table, "walk_initial_sd", "noise", default=0.0, nonneg=True)
    filt = doc.string(table, "filter", "noise", default="auto", choices=FILTERS)
    if filt == "kalman" and not isinstance(model, AbstractLinearDevice):
        raise doc.error(
            f"'kalman' needs a linear device and {type(model).__name__} is not linear (with "
            "these [model] options); use 'ekf' or 'auto'",
            "noise",
            "filter",
        )
    substeps = None
    if "substeps" in table:
        substeps = doc.integer(table, "substeps", "noise", minimum=1)
        if substeps > 64:
            raise doc.error(f"{substeps} is more than 64; 1-8 is usual", "noise", "substeps")
    state_unit = doc.string(table, "state_unit", "noise", default=None)
    k_step = doc.integer(table, "k_step", "noise", default=DEFAULT_K_STEP, minimum=1)
    try:
        structure = NoiseStructure(
            process_groups=tuple(groups),
            disturbances=tuple(dist),
            walk_initial_sd=float(walk_sd),
            filter=filt,
            substeps=substeps,
        )
    except ValueError as err:
        raise doc.error(str(err), "noise") from None
    values = {}
    for key in ("fixed", "initial"):
        sub = table.get(key, {})
        if not isinstance(sub, dict):
            raise doc.error('give a table { "path" = value }', "noise", key)
        out = {}
        for path, v in sub.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise doc.error("must be a finite number (SI)", "noise", key, path)
            if not v > 0:
                raise doc.error(f"{v} must be > 0 (an sd or an intensity)", "noise", key, path)
            out[str(path)] = float(v)
        values[key] = out
    both = set(values["fixed"]) & set(values["initial"])
    if both:
        raise doc.error(f"{sorted(both)} are both fixed and given an initial value", "noise")
    values["priors"] = _noise_priors(doc, table)
    both = set(values["fixed"]) & set(values["priors"])
    if both:
        raise doc.error(f"{sorted(both)} are both fixed and given a prior", "noise")
    options = {"state_unit": state_unit, "k_step": int(k_step), "priors": values["priors"]}
    return structure, values["fixed"], values["initial"], options


def _noise_priors(doc, table) -> dict:
    """[noise] priors: { "path" = { median = .., log_sd = .. } } (SI), log-normal, as a free
    parameter's prior_median / prior_log_sd: what the data cannot pin down (a sensor's
    quantisation noise on a record where it barely moves)."""
    sub = table.get("priors", {})
    if not isinstance(sub, dict):
        raise doc.error('give a table { "path" = { median = .., log_sd = .. } }', "noise", "priors")
    out = {}
    for path, prior in sub.items():
        where = ("noise", "priors", path)
        if not isinstance(prior, dict) or set(prior) != {"median", "log_sd"}:
            raise doc.error("give { median = .., log_sd = .. } (SI, log-normal)", *where)
        median = doc.number(prior, "median", *where, positive=True)
        log_sd = doc.number(prior, "log_sd", *where, positive=True)
        out[str(path)] = (float(median), float(log_sd))
    return out


def _stochastic_model(fs, structure, fixed, initial, doc=None, state_unit=None, priors=None):
    from greybox._sde_device import noise_parameters, stochastic_device

    sd = stochastic_device(fs.model, structure, outputs=fs.spec.outputs, inputs=fs.spec.inputs)
    noise_free = noise_parameters(sd, _noise_units(fs.spec, structure, state_unit))
    names = {p.path for p in noise_free}
    priors = priors or {}
    for key, vals in (("fixed", fixed), ("initial", initial), ("priors", priors)):
        for path in vals:
            if path not in names:
                msg = (
                    f"not a noise parameter of this structure; they are: {', '.join(sorted(names))}"
                )
                if doc is None:
                    raise ValueError(f"{path}: {msg}")
                raise doc.error(msg, "noise", key, path)
    from greybox._parameters import set_values

    sd = set_values(sd, list(fixed), list(fixed.values()))
    free = [
        dataclasses.replace(p, initial=initial.get(p.path))
        for p in noise_free
        if p.path not in fixed
    ]
    free = [
        dataclasses.replace(p, prior_median=priors[p.path][0], prior_log_sd=priors[p.path][1])
        if p.path in priors
        else p
        for p in free
    ]
    return sd, free


def fit_process_dir(experiment_dir, out, say, *, force: bool = False):
    """Load, fit (process noise), validate and write the result folder; returns a dict."""
    from greybox._process_fit import fit_process, validate_process
    from greybox.io._atomic import atomic_output_dir, check_output_dir
    from greybox.io._experiment_set import check_problem_size, load_experiment_set
    from greybox.io._toml import TomlDocument

    out = check_output_dir(out, force=force, inputs=[experiment_dir])
    say(f"loading {experiment_dir}")
    fs = load_experiment_set(experiment_dir)
    check_problem_size(fs)
    doc = TomlDocument(Path(experiment_dir) / "experiment.toml")
    structure, fixed, initial, options = parse_noise(doc, doc.data, fs.model, fs.spec)
    k_step = options["k_step"]
    try:
        sd, noise_free = _stochastic_model(
            fs,
            structure,
            fixed,
            initial,
            doc,
            state_unit=options["state_unit"],
            priors=options["priors"],
        )
    except ValueError as err:  # e.g. a device field named like a noise table
        raise doc.error(str(err), "noise") from None
    offsets, _ = fs.model.readout.quadrature()
    if np.size(offsets) != 1 or float(np.ravel(offsets)[0]) != 0.0:
        raise doc.error(
            "the Kalman filter needs instantaneous readings: set [camera] exposure_ms = 0",
            "fit",
            "noise_model",
        )
    free = list(fs.free) + noise_free
    say(
        f"{fs.device_name}: {len(fs.estimation)} estimation runs, {len(fs.validation)} "
        f"validation runs; maximum likelihood over {', '.join(p.path for p in free)}"
    )
    result = fit_process(sd, fs.estimation, free, progress=say, k_step=k_step)
    validation = validate_process(result, fs.validation, k_step=k_step) if fs.validation else ()
    if not all(np.isfinite(p.value) for p in result.parameters):
        from greybox._errors import InputError

        raise InputError(
            "the fit produced non-finite values; nothing was written. Check the settings, "
            "bounds and initial values",
            file=str(Path(fs.directory) / "experiment.toml"),
            field="fit",
        )
    document = params_document(fs, result, validation, structure, fixed, options)
    runs = [(r, e) for r, e in zip(result.runs, result.experiments)]
    runs += [(r, e) for r, e in zip(validation, fs.validation)]
    metrics = metrics_rows(fs, runs)
    say(f"writing {out}")
    from greybox.cli._fit import usual_permissions
    from greybox.io._params_file import write_params

    with atomic_output_dir(out, kind="fit", force=force) as tmp:
        usual_permissions(tmp)
        write_params(tmp / "params.json", document)
        (tmp / "report.md").write_text(report(fs, result, validation, structure, fixed, metrics))
        write_predictions(tmp, fs, runs)
        lines = ["run,role,output,horizon,unit,n,fit_percent,rmse,mae,sae"]
        for row in metrics:
            lines.append(",".join(_csv_cell(c) for c in row))
        (tmp / "metrics.csv").write_text("\n".join(lines) + "\n")
        write_validation_runs(tmp / "validation_runs.json", fs, validation)
        write_figures(tmp, fs, runs, result.model, say)
    return {"fitset": fs, "result": result, "validation": validation, "metrics": metrics}


def _text(x, spec: str) -> str:
    """A metric for the report: formatted, or n/a where undefined."""
    return "n/a" if x is None else format(x, spec)


def _csv_cell(c) -> str:
    """A metrics.csv cell: numbers as in `greybox fit`'s metrics.csv, empty where undefined."""
    if c is None:
        return ""
    return f"{c:.10g}" if isinstance(c, float) else str(c)


def _horizons(run):
    return tuple((label, z) for label, z, _ in run.horizons)


def metrics_rows(fs, runs) -> list:
    """(run, role, output, horizon, unit, n, fit %, RMSE, MAE, SAE) in the file's units;
    None where undefined (as `greybox fit`'s metrics)."""
    from greybox.cli._fit import error_metrics, output_units

    rows = []
    m_per_px = fs.camera.get("m_per_px")
    for run, e in runs:
        units = output_units(fs, e.name)
        for horizon, z in _horizons(run):  # simulation, one-step, k-step prediction
            for j, (ch, (unit, conv)) in enumerate(zip(fs.spec.outputs, units)):
                m = error_metrics(e.y[:, j], z[:, j], conv, m_per_px)
                rows.append(
                    (e.name, run.role, ch.name, horizon, unit)
                    + tuple(m[k] for k in ("n", "fit_percent", "rmse", "mae", "sae"))
                )
    return rows


def write_predictions(folder: Path, fs, runs) -> None:
    from greybox.cli._fit import _in_unit, output_units, write_csv_table

    m_per_px = fs.camera.get("m_per_px")
    (folder / "predictions").mkdir()
    for run, e in runs:
        header, cols = ["t_s"], [e.t_s]
        for j, (ch, (unit, conv)) in enumerate(zip(fs.spec.outputs, output_units(fs, e.name))):
            header += [f"{ch.name}_{unit}", f"{ch.name}_sim_{unit}", f"{ch.name}_onestep_{unit}"]
            cols += [
                _in_unit(e.y[:, j], conv, m_per_px),
                _in_unit(run.y_simulation[:, j], conv, m_per_px),
                _in_unit(run.y_one_step[:, j], conv, m_per_px),
            ]
            header += [f"{ch.name}_{run.k_step}step_{unit}"]
            cols += [_in_unit(run.y_k_step[:, j], conv, m_per_px)]
            header += [f"{ch.name}_residual_sim_{unit}", f"{ch.name}_innovation_{unit}"]
            cols += [
                _in_unit(e.y[:, j] - run.y_simulation[:, j], conv, m_per_px, difference=True),
                _in_unit(e.y[:, j] - run.y_one_step[:, j], conv, m_per_px, difference=True),
            ]
        write_csv_table(folder / "predictions" / f"{e.name}.csv", header, cols)


def _run_doc(run, outputs) -> dict:
    from greybox.io._params_file import _num

    return {
        "role": run.role,
        "log_likelihood": _num(run.log_likelihood),
        "whiteness": {
            c: {
                "test": "Ljung-Box",
                "statistic": _num(w.statistic),
                "p_value": _num(w.p_value),
                "lags": w.lags,
                "white": bool(w.p_value > 0.01),
            }
            for c, w in zip(outputs, run.whiteness)
        },
        "fit_percent": {
            label: {c: _num(v) for c, v in zip(outputs, pct)} for label, _, pct in run.horizons
        },
        "k_step": run.k_step,
    }


def params_document(fs, result, validation, structure, fixed, options=None) -> dict:
    from greybox._parameters import get_value
    from greybox.io._params_file import _num, _nums, parameter_record

    outputs = [c.name for c in fs.spec.outputs]
    noise_paths = [
        f"{f}.{nm}"
        for f in ("process", "measurement", "output_walk", "input_walk")
        for nm in getattr(result.model, f).names
    ]
    return {
        "format": FORMAT,
        "noise_model": "process",
        "likelihood": result.likelihood,
        "filter": result.filter_name,
        "device": fs.device.ref,
        "device_name": fs.device_name,
        "device_location": fs.device.location,
        "experiment_dir": str(Path(fs.directory).resolve()),
        "options": fs.options,
        "fixed": {k: _num(v) for k, v in fs.fixed.items()},
        "camera": {k: _num(v) for k, v in fs.camera.items() if v is not None},
        "noise": {
            "process_groups": {g: list(idx) for g, idx in structure.process_groups},
            "disturbances": list(structure.disturbances),
            "walk_initial_sd": structure.walk_initial_sd,
            "filter": structure.filter,
            "substeps": structure.substeps,
            "ekf_substeps": result.model.ekf_substeps,
            "state_unit": (options or {}).get("state_unit"),
            "k_step": (options or {}).get("k_step"),
            "fixed": dict(fixed),
            "values": {p: _num(get_value(result.model, p)) for p in noise_paths},
        },
        "status": result.status,
        "message": result.message,
        "parameters": [parameter_record(p) for p in result.parameters],
        "free": [dataclasses.asdict(p) for p in result.free],
        "raw": _nums(result.raw),
        "covariance_raw": _nums(result.covariance_raw),
        "neg_log_likelihood": _num(result.neg_log_likelihood),
        "aic": _num(result.aic),
        "bic": _num(result.bic),
        "n_observations": result.n_observations,
        "runs": {r.name: _run_doc(r, outputs) for r in (*result.runs, *validation)},
        "file_units": {c.name: u for c, (u, _) in zip(fs.spec.outputs, _units(fs))},
    }


def _units(fs):
    from greybox.cli._fit import output_units

    return output_units(fs)


def report(fs, result, validation, structure, fixed, metrics) -> str:
    k = result.runs[0].k_step if result.runs else 0
    from greybox._report import parameter_table

    outputs = [c.name for c in fs.spec.outputs]
    groups = ", ".join(f"{g} (states {list(i)})" for g, i in structure.process_groups) or "none"
    lines = [
        f"# {fs.name}: stochastic grey-box fit",
        "",
        f"Device `{fs.device_name}`; data `{fs.directory}`. {fs.description}".strip(),
        "",
        f"**Likelihood:** {result.likelihood} ({result.filter_name}"
        + (
            f", {result.model.ekf_substeps} local linearisations per step"
            if result.model.use_ekf
            else ""
        )
        + "); "
        f"status **{result.status}** ({result.message}, {result.n_steps} BFGS steps).",
        "",
        f"Noise model: process noise on {groups}; disturbances: "
        f"{', '.join(structure.disturbances) or 'none'}; measurement noise per output"
        + (f"; held fixed: {fixed}" if fixed else "")
        + ". Intensities are of the Wiener increments (variance per second).",
        "",
        f"-log L = {result.neg_log_likelihood:.6g} over {result.n_observations} readings; "
        f"AIC {result.aic:.6g}, BIC {result.bic:.6g}.",
        "",
        "## Parameters",
        "",
        "Standard errors from the inverse observed information (Hessian of -log L); 95 % "
        "intervals mapped through each parameter's transform.",
        "",
        *parameter_table(result.parameters),
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
    for row in metrics:
        run, role, out, horizon, unit, n, fp, rmse, mae, sae = row
        lines.append(
            f"| {run} | {role} | {out} | {horizon} | {_text(fp, '.2f')} | {_text(rmse, '.4g')} | "
            f"{_text(sae, '.4g')} | {unit} |"
        )
    lines += [
        "",
        "## Innovations whiteness (Ljung-Box, 20 lags, white when p > 0.01)",
        "",
        "| run | role | output | Q | p | verdict |",
        "|---|---|---|---|---|---|",
    ]
    for run in (*result.runs, *validation):
        for c, w in zip(outputs, run.whiteness):
            verdict = "white" if w.p_value > 0.01 else "NOT white"
            lines.append(
                f"| {run.name} | {run.role} | {c} | {w.statistic:.1f} | {w.p_value:.3g} | "
                f"{verdict} |"
            )
    return "\n".join(lines) + "\n"


def write_validation_runs(path: Path, fs, validation) -> None:
    """validation_runs.json: per validation run, its settings, fit % per horizon and the
    innovations' whiteness (physics and noise fixed at the estimate)."""
    from greybox.io._params_file import _num

    outputs = [c.name for c in fs.spec.outputs]
    by_name = {e.name: e for e in fs.validation}
    runs = {}
    for r in validation:
        e = by_name.get(r.name)
        doc = _run_doc(r, outputs)
        doc["settings"] = {k: _num(v) for k, v in (e.settings if e else {}).items()}
        runs[r.name] = doc
    body = {
        "note": "validation runs at the fitted parameters (per-run parameters, if any, "
        "re-fitted on each run): fit % per horizon and the innovations' Ljung-Box test",
        "runs": runs,
    }
    path.write_text(json.dumps(body, indent=2) + "\n")


def write_figures(folder: Path, fs, runs, model, say) -> list:
    """figures/fit_<run>.png (measured vs simulation, inputs beneath) and
    figures/innovations_<output>.png (one-step prediction errors per run)."""
    from greybox import _plots as plots

    (folder / "figures").mkdir()
    outputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.outputs)
    inputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.inputs)
    sd = np.asarray(model.measurement.array(), dtype=float)
    names = []
    for run, e in runs:
        name = f"figures/fit_{e.name}.png"
        plots.run_figure(
            folder / name,
            name=e.name,
            role=run.role,
            t_s=e.t_s,
            y=e.y,
            y_model=run.y_simulation,
            inputs=e.inputs,
            sigma=sd,
            fit_percent=np.asarray(run.simulation_fit_percent),
            outputs=outputs,
            input_labels=inputs,
        )
        names.append(name)
    for j, (ch, (label, unit)) in enumerate(zip(fs.spec.outputs, outputs)):
        name = f"figures/innovations_{ch.name}.png"
        plots.residuals_figure(
            folder / name,
            [(e.name, r.role, e.t_s, e.y[:, j], r.y_one_step[:, j]) for r, e in runs],
            sigma=float(sd[j]),
            output=(f"{label}, one-step prediction (innovations; sigma: measurement sd)", unit),
        )
        names.append(name)
    return names


def run(args, say, out) -> int:
    """`greybox fit` for a process-noise folder: prints a summary, returns the exit status."""
    from greybox._report import estimate_texts

    outcome = fit_process_dir(args.experiment_dir, out, say, force=args.force)
    res = outcome["result"]
    lines = ["parameter                  value        95 % interval               verdict"]
    for p in res.parameters:
        value, ci, unit = estimate_texts(p)
        lines.append(f"{p.name:<26} {value:>8} {unit:<6} {ci:<27} {p.verdict}")
    for row in outcome["metrics"]:
        lines.append(f"{row[0]} ({row[1]}) {row[2]} {row[3]} fit % {_text(row[6], '.2f')}")
    white = all(r.white for r in res.runs)
    lines.append(
        f"likelihood: {res.likelihood}; innovations "
        f"{'white' if white else 'NOT white'} (estimation, Ljung-Box p > 0.01); {res.status}"
    )
    print("\n".join(lines))
    print(
        f"wrote {out}/ (params.json, report.md, predictions/, metrics.csv, figures/, "
        f"validation_runs.json) in {say.elapsed:.1f} s"
    )
    if not res.valid:
        import sys

        print(f"greybox fit: warning: {res.status}: the estimate is not valid", file=sys.stderr)
        return 1
    return 0


# ---------------------------------------------------------------------------------------------
# greybox simulate on a process-noise params.json


def is_process_params(path) -> bool:
    try:
        doc = json.loads(Path(path).read_text("utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and doc.get("noise_model") == "process"


def load_process_params(path):
    """(spec, stochastic model at the estimate, shared free, shared raw, covariance, doc)."""
    from greybox._errors import InputError
    from greybox._freeparams import FreeParameter, apply_raw
    from greybox._parameters import set_values
    from greybox._registry import DeviceNotFound, resolve
    from greybox._sde_device import NoiseStructure, stochastic_device
    from greybox._spec import DeviceSpecError
    from greybox.io._experiment_set import configure_model

    doc = json.loads(Path(path).read_text("utf-8"))
    try:
        if doc.get("format") != FORMAT:
            raise KeyError("format")
        try:
            device = resolve(doc["device"], base_dir=doc["experiment_dir"])
        except (DeviceNotFound, DeviceSpecError) as err:
            raise InputError(str(err), file=str(path), field="device") from None
        spec = device.spec
        cam = {k: v for k, v in doc["camera"].items() if k in ("m_per_px", "exposure_s")}
        model = configure_model(spec, doc["options"], cam, doc["fixed"])
        nz = doc["noise"]
        structure = NoiseStructure(
            process_groups=tuple((g, tuple(i)) for g, i in nz["process_groups"].items()),
            disturbances=tuple(nz["disturbances"]),
            walk_initial_sd=float(nz["walk_initial_sd"]),
            filter=nz["filter"],
            substeps=None if nz.get("substeps") is None else int(nz["substeps"]),
        )
        sd = stochastic_device(model, structure, outputs=spec.outputs, inputs=spec.inputs)
        sd = set_values(sd, list(nz["values"]), [float(v) for v in nz["values"].values()])
        free = [FreeParameter(**f) for f in doc["free"]]
        shared = [p for p in free if not p.per_experiment]
        k = len(shared)
        raw = np.asarray(doc["raw"], dtype=float)[:k]
        cov = np.asarray(
            [[np.nan if v is None else v for v in row] for row in doc["covariance_raw"]],
            dtype=float,
        )[:k, :k]
        sd = apply_raw(sd, shared, raw)
    except (KeyError, TypeError, ValueError) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(
            f"not a complete process-noise params.json ({err}); re-run greybox fit",
            file=str(path),
            field="params",
        ) from None
    return spec, sd, shared, raw, cov, doc


def simulate_process(args) -> int:
    """`greybox simulate` for a process-noise fit: sample paths (process noise by exact
    discretisation of the SDE, parameters drawn from the fit's covariance) and their 95 %
    pointwise band."""
    from greybox._errors import InputError
    from greybox._prediction import Band
    from greybox._sde_device import draw_paths
    from greybox._simulate import simulate
    from greybox.cli._simulate import (
        read_waveform,
        sample_times,
        simulation_columns,
        write_simulation,
    )

    spec, sd, shared, raw, cov, doc = load_process_params(args.params)
    inputs, outputs = tuple(spec.inputs), tuple(spec.outputs)
    wave, text, specs = read_waveform(args.waveform, inputs)
    t = sample_times(wave, args.dt_ms, n_default=2000, n_max=200_000)
    n = t.size
    rng = np.random.default_rng(0)
    finite = np.all(np.isfinite(cov)) and cov.size
    if finite:
        draws = rng.multivariate_normal(raw, 0.5 * (cov + cov.T), size=N_PATHS)
        what = "parameter draws from the fit's covariance"
    else:
        draws = np.tile(raw, (N_PATHS, 1))
        what = "parameters at the estimate (their covariance is not finite)"
    paths = draw_paths(sd, shared, draws, wave, t, measurement_noise=bool(args.noise))
    y = np.asarray(simulate(sd.device, wave, t)).reshape(n, -1)
    lo, hi = np.percentile(paths, [2.5, 97.5], axis=0)
    for arr in (y, lo, hi):
        if not np.all(np.isfinite(arr)):
            raise InputError(
                "the simulated response or band is not finite; nothing was written",
                file=str(args.params),
                field="--waveform",
            )
    kind = (
        f"95 % band of {N_PATHS} sample paths: process noise (exact discretisation of the SDE) "
        f"and {what}" + ("; measurement noise added" if args.noise else "")
    )
    header, cols, described, peaks = simulation_columns(
        outputs, inputs, doc.get("file_units") or {}, t, (y, lo, hi), wave
    )
    sdv = (hi - lo) / (2 * 1.96)
    band = Band(t, y, lo, hi, sdv, sdv, 0.95, bool(args.noise))
    meta = {
        "params": str(args.params),
        "device": spec.name,
        "noise_model": "process",
        "waveform": {"spec": specs if len(specs) > 1 else specs[0], "description": text},
        "band": {
            "kind": kind,
            "level": 0.95,
            "n_paths": N_PATHS,
            "includes_measurement_noise": bool(args.noise),
            "includes_process_noise": True,
        },
        "columns": described,
        "peaks": peaks,
    }
    write_simulation(
        args.out, args.force, header, cols, meta, band, wave, spec.name, text, outputs, inputs
    )
    print(f"simulated {text}: {n} samples, {N_PATHS} sample paths")
    print(f"band: {kind}")
    print(f"wrote {Path(args.out)}/ (simulation.csv, simulation.png, simulation.json)")
    return 0
